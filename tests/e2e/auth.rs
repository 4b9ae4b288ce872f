//! API tokens: REST and gRPC refuse calls without a token that allows them, with 401/UNAUTHENTICATED
//! or 403/PERMISSION_DENIED and nothing else; health stays open; the server keeps serving.

use depthmill_orchestrator::auth::{self, AuthConfig, AuthMode};
use depthmill_proto::orchestrator::v1 as pb;
use depthmill_tests::{StackOptions, TestStack};
use serde_json::Value;
use tonic::metadata::MetadataValue;

use crate::{gcode_job, program};

fn client(token: Option<&str>) -> anyhow::Result<reqwest::Client> {
    let mut headers = reqwest::header::HeaderMap::new();
    if let Some(t) = token {
        headers.insert(reqwest::header::AUTHORIZATION, format!("Bearer {t}").parse()?);
    }
    Ok(depthmill_common::tls::http_client().default_headers(headers).build()?)
}

/// A gRPC request carrying `token`.
fn with<T>(token: &str, message: T) -> anyhow::Result<tonic::Request<T>> {
    let mut r = tonic::Request::new(message);
    r.metadata_mut().insert("authorization", MetadataValue::try_from(format!("Bearer {token}"))?);
    Ok(r)
}

async fn error_of(resp: reqwest::Response) -> anyhow::Result<(u16, String, String)> {
    let status = resp.status().as_u16();
    let body: Value = resp.json().await?;
    Ok((
        status,
        body["error"]["code"].as_str().unwrap_or_default().to_string(),
        body["error"]["message"].as_str().unwrap_or_default().to_string(),
    ))
}

#[tokio::test]
async fn tokens_guard_rest_and_grpc_by_scope() -> anyhow::Result<()> {
    let mut stack = TestStack::start_with(StackOptions {
        auth: AuthConfig { mode: AuthMode::Tokens, cache_s: 0.0 },
        ..Default::default()
    })
    .await?;
    let store = depthmill_orchestrator::store::open(&format!(
        "sqlite://{}",
        stack.data_dir.join("jobs.sqlite").display()
    ))
    .await?;
    let now = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH)?.as_millis() as i64;
    let reader = auth::issue(&*store, "dashboard", "read", None, now).await?;
    let submitter = auth::issue(&*store, "cell-3 MES", "submit", None, now).await?;
    let expired = auth::issue(&*store, "old", "admin", Some(0.001), now - 10_000).await?;
    let revoked = auth::issue(&*store, "lost laptop", "admin", None, now).await?;
    assert!(store.revoke_token(&revoked.record.id, now).await?);
    // Only hashes are stored.
    let listed = store.list_tokens().await?;
    assert_eq!(listed.len(), 4);
    assert!(listed.iter().all(|t| !format!("{t:?}").contains(&submitter.token[4..])));

    let jobs = stack.url("/v1/jobs");
    // No token, a wrong one, an expired one, a revoked one: 401 with a challenge, nothing else.
    let resp = client(None)?.get(&jobs).send().await?;
    assert_eq!(resp.headers().get("www-authenticate").and_then(|v| v.to_str().ok()), Some("Bearer"));
    let (status, code, message) = error_of(resp).await?;
    assert_eq!((status, code.as_str()), (401, "unauthenticated"), "{message}");
    assert!(message.contains("Authorization: Bearer"), "{message}");
    for (token, needle) in
        [("dmt_0000", "unknown"), (expired.token.as_str(), "expired"), (revoked.token.as_str(), "revoked")]
    {
        let (status, code, message) = error_of(client(Some(token))?.get(&jobs).send().await?).await?;
        assert_eq!((status, code.as_str()), (401, "unauthenticated"), "{message}");
        assert!(message.contains(needle), "{message}");
    }
    let (status, _, message) = error_of(
        depthmill_common::tls::http_client()
            .build()?
            .get(&jobs)
            .header("authorization", "Basic eDp5")
            .send()
            .await?,
    )
    .await?;
    assert_eq!(status, 401, "{message}");
    // Health and the API description stay open.
    for open in ["/healthz", "/readyz", "/openapi.json"] {
        assert_eq!(client(None)?.get(stack.url(open)).send().await?.status().as_u16(), 200, "{open}");
    }

    // A read token reads but cannot submit: 403, and no job appears.
    stack.http = client(Some(&submitter.token))?;
    let sha = stack.upload("text/x-gcode", program()).await?;
    let read = client(Some(&reader.token))?;
    assert_eq!(read.get(&jobs).send().await?.status().as_u16(), 200);
    let (status, code, message) = error_of(read.post(&jobs).json(&gcode_job(&sha)).send().await?).await?;
    assert_eq!((status, code.as_str()), (403, "permission_denied"), "{message}");
    assert!(message.contains("'submit'"), "{message}");
    let listed: Value = read.get(&jobs).send().await?.json().await?;
    assert_eq!(listed["jobs"].as_array().map(Vec::len), Some(0), "the refused submission left no job");

    // The submit token submits; the worker runs the job (the machine refuses this toolless
    // program: the job gets that far).
    let (status, job) = stack.post_job(&gcode_job(&sha), None).await?;
    assert_eq!(status, 201, "{job}");
    let id = job["id"].as_str().unwrap_or_default().to_string();
    let done = stack.wait_for_end(&id, std::time::Duration::from_secs(60)).await?;
    assert_eq!(done["attempts"][0]["stage"], "execute", "{done}");

    // gRPC: the same rules through the `authorization` metadata.
    let mut grpc = stack.grpc().await?;
    let err = grpc.list_jobs(pb::ListJobsRequest::default()).await.expect_err("no token");
    assert_eq!(err.code(), tonic::Code::Unauthenticated, "{err:?}");
    let listed = grpc.list_jobs(with(&reader.token, pb::ListJobsRequest::default())?).await?.into_inner();
    assert_eq!(listed.jobs.len(), 1);
    let err = grpc
        .cancel_job(with(&reader.token, pb::CancelJobRequest { id: id.clone() })?)
        .await
        .expect_err("read cannot cancel");
    assert_eq!(err.code(), tonic::Code::PermissionDenied, "{err:?}");
    let err =
        grpc.get_job(with(&revoked.token, pb::GetJobRequest { id: id.clone() })?).await.expect_err("revoked");
    assert_eq!(err.code(), tonic::Code::Unauthenticated, "{err:?}");
    let got = grpc.get_job(with(&submitter.token, pb::GetJobRequest { id: id.clone() })?).await?.into_inner();
    assert_eq!(got.id, id);
    // The health service needs no token.
    let channel = tonic::transport::Channel::from_shared(stack.grpc_url.clone())?.connect().await?;
    let health = tonic_health::pb::health_client::HealthClient::new(channel)
        .check(tonic_health::pb::HealthCheckRequest { service: String::new() })
        .await?;
    assert_eq!(
        health.into_inner().status,
        tonic_health::pb::health_check_response::ServingStatus::Serving as i32
    );
    stack.http = client(Some(&submitter.token))?;
    stack.shutdown().await
}

#[tokio::test]
async fn without_tokens_the_server_refuses_a_network_address() -> anyhow::Result<()> {
    let rest = tokio::net::TcpListener::bind("0.0.0.0:0").await?;
    let grpc = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
    let dir = tempfile::tempdir()?;
    let config = depthmill_orchestrator::Config { data_dir: dir.path().to_path_buf(), ..Default::default() };
    let err = depthmill_orchestrator::serve(rest, grpc, config, None, std::future::pending())
        .await
        .expect_err("open on the network");
    let chain = depthmill_common::ErrorChain(&err).to_string();
    assert!(chain.contains("not loopback") && chain.contains("mode = \"tokens\""), "{chain}");
    assert!(!dir.path().join("jobs.sqlite").exists(), "refused before touching anything");
    Ok(())
}

#[tokio::test]
async fn stage_services_take_calls_with_the_service_token_only() -> anyhow::Result<()> {
    use depthmill_proto::machine::v1 as machine;
    let stack = TestStack::start().await?;
    let url = stack
        .service_urls()
        .into_iter()
        .find(|(name, _)| name == "depthmill.machine.v1.MachineService")
        .map(|(_, url)| url)
        .ok_or_else(|| anyhow::anyhow!("no machine service"))?;
    let channel = tonic::transport::Channel::from_shared(url)?.connect().await?;
    let mut m = machine::machine_service_client::MachineServiceClient::new(channel.clone());
    let err = m.get_status(machine::GetStatusRequest {}).await.expect_err("no token");
    assert_eq!(err.code(), tonic::Code::Unauthenticated, "{err:?}");
    let err =
        m.get_status(with("not-the-token", machine::GetStatusRequest {})?).await.expect_err("wrong token");
    assert_eq!(err.code(), tonic::Code::Unauthenticated, "{err:?}");
    let status =
        m.get_status(with(depthmill_tests::SERVICE_TOKEN, machine::GetStatusRequest {})?).await?.into_inner();
    assert_eq!(status.state, "idle");
    // Health stays open (load balancers and probes carry no secret).
    let health = tonic_health::pb::health_client::HealthClient::new(channel)
        .check(tonic_health::pb::HealthCheckRequest { service: String::new() })
        .await?;
    assert_eq!(
        health.into_inner().status,
        tonic_health::pb::health_check_response::ServingStatus::Serving as i32
    );
    stack.shutdown().await
}
