//! The gRPC service: configuration and server (feature `service`, on by default).

use std::future::Future;
use std::net::SocketAddr;
use std::path::PathBuf;

pub use depthmill_common::grpc::ServeError;

/// Configuration of the machine service (`deploy/config/machine.toml`, env `DEPTHMILL_MACHINE__KEY`).
#[derive(Debug, Clone, serde::Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub struct Config {
    /// gRPC listen address.
    #[serde(default = "default_grpc_addr")]
    pub grpc_addr: SocketAddr,
    /// Folder of the artifact store shared with the orchestrator.
    #[serde(default = "default_artifacts_dir")]
    pub artifacts_dir: PathBuf,
    /// The artifacts in an object store (`s3://...`) instead of `artifacts_dir`, which then
    /// holds local copies of the blobs this service reads from files.
    #[serde(default)]
    pub artifact_store: Option<depthmill_common::artifacts::ObjectStoreConfig>,
    /// Shared secret the orchestrator sends with every call (`authorization: Bearer <token>`);
    /// calls without it are refused (UNAUTHENTICATED). Unset: no check (loopback or a private
    /// network). Health, reflection and `/metrics` stay open.
    #[serde(default)]
    pub service_token: Option<String>,
}

fn default_grpc_addr() -> SocketAddr {
    SocketAddr::from(([127, 0, 0, 1], 50054))
}

fn default_artifacts_dir() -> PathBuf {
    PathBuf::from("data/artifacts")
}

impl Default for Config {
    fn default() -> Self {
        Self {
            grpc_addr: default_grpc_addr(),
            artifacts_dir: default_artifacts_dir(),
            artifact_store: None,
            service_token: None,
        }
    }
}

/// The gRPC service names this server reports in its health service.
pub const SERVICE_NAMES: &[&str] = &[crate::grpc::SERVICE_NAME];

/// Serves the machine service on `listener` until `shutdown` completes.
pub async fn serve(
    listener: tokio::net::TcpListener,
    config: Config,
    shutdown: impl Future<Output = ()> + Send,
) -> Result<(), MachineServeError> {
    let options =
        depthmill_common::grpc::GrpcOptions { token: config.service_token.clone(), ..Default::default() };
    let store =
        depthmill_common::artifacts::open_store(&config.artifacts_dir, config.artifact_store.as_ref())
            .await?;
    Ok(depthmill_common::grpc::serve_grpc_with(
        listener,
        crate::grpc::routes(store),
        SERVICE_NAMES,
        options,
        shutdown,
    )
    .await?)
}

/// Why the service could not start or stopped.
#[derive(Debug, thiserror::Error)]
pub enum MachineServeError {
    #[error(transparent)]
    Serve(#[from] ServeError),
    #[error("cannot open the artifact store")]
    Artifacts(#[from] depthmill_common::artifacts::ArtifactError),
}
