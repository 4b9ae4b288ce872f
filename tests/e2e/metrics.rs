//! Every gRPC server answers `GET /metrics` on its gRPC port with per-call metrics.

use tokio_util::sync::CancellationToken;
use tonic_health::pb::{HealthCheckRequest, health_client::HealthClient};

/// Starts the scanning service on an ephemeral port, makes a health call, and reads the call's
/// counter and histogram back from `GET /metrics` on the same port (HTTP/1.1 beside gRPC).
#[tokio::test]
async fn grpc_port_serves_metrics_with_the_calls_it_answered() -> anyhow::Result<()> {
    // Installing twice returns the same recorder (the test process runs many services).
    depthmill_common::metrics::install_prometheus()?;
    depthmill_common::metrics::install_prometheus()?;
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
    let addr = listener.local_addr()?;
    let token = CancellationToken::new();
    let stop = token.clone();
    let server = tokio::spawn(async move {
        depthmill_scanning::serve(listener, depthmill_scanning::Config::default(), async move {
            stop.cancelled().await
        })
        .await
    });

    let channel = tonic::transport::Channel::from_shared(format!("http://{addr}"))?.connect().await?;
    let mut health = HealthClient::new(channel);
    let service = depthmill_scanning::SERVICE_NAMES[0];
    let reply = health.check(HealthCheckRequest { service: service.to_string() }).await?.into_inner();
    assert_eq!(reply.status, 1, "SERVING");
    // An unknown name answers NOT_FOUND: counted with its status.
    let missing = health.check(HealthCheckRequest { service: "no.such.Service".into() }).await;
    assert_eq!(missing.err().map(|s| s.code()), Some(tonic::Code::NotFound));

    let ok = r#"depthmill_grpc_requests_total{service="grpc.health.v1.Health",method="Check",status="Ok"}"#;
    let not_found =
        r#"depthmill_grpc_requests_total{service="grpc.health.v1.Health",method="Check",status="NotFound"}"#;
    let histogram = r#"depthmill_grpc_request_duration_seconds_bucket{service="grpc.health.v1.Health",method="Check",status="Ok",le="0.005"}"#;
    // A call is recorded when the server finishes its response, which may be just after the
    // client has read it: read /metrics until the lines are there (a few tries at most).
    let mut body = String::new();
    for _ in 0..50 {
        let response = reqwest::get(format!("http://{addr}/metrics")).await?;
        assert_eq!(response.status(), 200);
        let content_type = response
            .headers()
            .get(reqwest::header::CONTENT_TYPE)
            .and_then(|v| v.to_str().ok())
            .unwrap_or_default()
            .to_string();
        assert!(content_type.starts_with("text/plain"), "Prometheus text format, got {content_type}");
        body = response.text().await?;
        if [ok, not_found, histogram].iter().all(|e| body.lines().any(|l| l.starts_with(e))) {
            break;
        }
        tokio::time::sleep(std::time::Duration::from_millis(20)).await;
    }
    for expected in [ok, not_found, histogram] {
        assert!(body.lines().any(|l| l.starts_with(expected)), "{expected} missing from /metrics:\n{body}");
    }

    // Other paths over HTTP/1.1 get tonic's answer to an unknown route: gRPC UNIMPLEMENTED (12).
    let other = reqwest::get(format!("http://{addr}/nothing")).await?;
    assert_eq!(other.headers().get("grpc-status").and_then(|v| v.to_str().ok()), Some("12"));

    token.cancel();
    server.await??;
    Ok(())
}
