//! Serving tonic routes on a bound listener, with the standard health service, reflection, gRPC
//! call metrics and `GET /metrics` on the same port.

use std::future::Future;

use tokio::net::TcpListener;
use tokio_stream::wrappers::TcpListenerStream;
use tonic::service::Routes;

/// Why a gRPC server could not start or stopped with an error.
#[derive(Debug, thiserror::Error)]
pub enum ServeError {
    #[error("cannot build the gRPC reflection service")]
    Reflection(#[source] tonic_reflection::server::Error),
    #[error("gRPC server failed")]
    Transport(#[source] tonic::transport::Error),
    #[error("cannot read the listener's address")]
    Io(#[source] std::io::Error),
}

/// `routes` behind a check of the caller's `authorization: Bearer <token>`: UNAUTHENTICATED
/// without it. Compared through SHA-256 digests, so the time taken says nothing of the token.
fn require_token(routes: Routes, token: &str) -> Routes {
    use sha2::{Digest as _, Sha256};
    let expected: std::sync::Arc<[u8]> = Sha256::digest(format!("Bearer {token}")).to_vec().into();
    let router = routes.into_axum_router().layer(axum::middleware::from_fn_with_state(
        expected,
        |axum::extract::State(expected): axum::extract::State<std::sync::Arc<[u8]>>,
         request: axum::extract::Request,
         next: axum::middleware::Next| async move {
            let given = request.headers().get("authorization").map(|v| Sha256::digest(v.as_bytes()));
            if given.as_deref() == Some(&expected[..]) {
                next.run(request).await
            } else {
                tonic::Status::unauthenticated(
                    "this service takes calls from its orchestrator only: missing or wrong service token",
                )
                .into_http()
            }
        },
    ));
    Routes::from(router)
}

/// The name of the standard gRPC health service every server registers.
pub const HEALTH_SERVICE: &str = "grpc.health.v1.Health";
/// The name of the gRPC reflection service every server registers.
pub const REFLECTION_SERVICE: &str = "grpc.reflection.v1.ServerReflection";

/// Serves `routes` plus `grpc.health.v1.Health` (every name in `service_names` and the empty
/// name reported SERVING) and gRPC reflection (v1) over the depthmill descriptors, on `listener`,
/// until `shutdown` completes. In-flight calls are drained on shutdown.
///
/// The same port also answers HTTP/1.1 `GET /metrics`: the process's Prometheus metrics (see
/// [`crate::metrics`]; 404 when the binary installed no recorder). Every gRPC call is counted and
/// timed by [`crate::metrics::GrpcMetricsLayer`]. HTTP/2 without TLS (h2c, what gRPC clients and
/// Kubernetes' `grpc` probes speak) and HTTP/1.1 are told apart per connection.
pub async fn serve_grpc(
    listener: TcpListener,
    routes: Routes,
    service_names: &[&str],
    shutdown: impl Future<Output = ()> + Send,
) -> Result<(), ServeError> {
    serve_grpc_with(listener, routes, service_names, GrpcOptions::default(), shutdown).await
}

/// How [`serve_grpc_with`] serves beyond [`serve_grpc`].
#[derive(Debug, Clone, Default)]
pub struct GrpcOptions {
    /// Serve over TLS with this identity.
    pub tls: Option<tonic::transport::ServerTlsConfig>,
    /// Require `authorization: Bearer <token>` on every call of `routes` (health, reflection and
    /// `/metrics` stay open): the shared secret of service-to-service calls.
    pub token: Option<String>,
}

/// [`serve_grpc`] with TLS and a required caller token as `options` say.
pub async fn serve_grpc_with(
    listener: TcpListener,
    routes: Routes,
    service_names: &[&str],
    options: GrpcOptions,
    shutdown: impl Future<Output = ()> + Send,
) -> Result<(), ServeError> {
    let tls = options.tls;
    let routes = match options.token.filter(|t| !t.is_empty()) {
        Some(token) => require_token(routes, &token),
        None => routes,
    };
    let addr = listener.local_addr().map_err(ServeError::Io)?;
    let (reporter, health) = tonic_health::server::health_reporter();
    reporter.set_service_status("", tonic_health::ServingStatus::Serving).await;
    for name in service_names {
        reporter.set_service_status(*name, tonic_health::ServingStatus::Serving).await;
    }
    let reflection = tonic_reflection::server::Builder::configure()
        .register_encoded_file_descriptor_set(depthmill_proto::FILE_DESCRIPTOR_SET)
        .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
        .build_v1()
        .map_err(ServeError::Reflection)?;
    let router = routes
        .add_service(health)
        .add_service(reflection)
        .into_axum_router()
        .route("/metrics", axum::routing::get(crate::metrics::render_metrics));
    let recorded = service_names.iter().copied().chain([HEALTH_SERVICE, REFLECTION_SERVICE]);
    tracing::info!(%addr, services = ?service_names, "gRPC listening (and GET /metrics)");
    let mut server = tonic::transport::Server::builder();
    if let Some(tls) = tls {
        server = server.tls_config(tls).map_err(ServeError::Transport)?;
    }
    server
        .accept_http1(true)
        .layer(crate::metrics::GrpcMetricsLayer::new(recorded))
        .add_routes(Routes::from(router))
        .serve_with_incoming_shutdown(TcpListenerStream::new(listener), shutdown)
        .await
        .map_err(ServeError::Transport)
}
