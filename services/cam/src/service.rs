//! The gRPC service: configuration and server (feature `service`, on by default).

use std::future::Future;
use std::net::SocketAddr;
use std::path::PathBuf;

pub use depthmill_common::grpc::ServeError;

/// Configuration of the cam service (`deploy/config/cam.toml`, env `DEPTHMILL_CAM__KEY`).
#[derive(Debug, Clone, serde::Serialize, serde::Deserialize)]
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
    /// Folder of `.tool` files added to (and overriding) the shipped tool library.
    #[serde(default)]
    pub tools_dir: Option<PathBuf>,
    /// Shared secret the orchestrator sends with every call (`authorization: Bearer <token>`);
    /// calls without it are refused (UNAUTHENTICATED). Unset: no check (loopback or a private
    /// network). Health, reflection and `/metrics` stay open.
    #[serde(default)]
    pub service_token: Option<String>,
}

fn default_grpc_addr() -> SocketAddr {
    SocketAddr::from(([127, 0, 0, 1], 50053))
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
            tools_dir: None,
            service_token: None,
        }
    }
}

/// The gRPC service names this server reports in its health service.
pub const SERVICE_NAMES: &[&str] = &[crate::grpc::SERVICE_NAME];

/// Why the CAM service could not start.
#[derive(Debug, thiserror::Error)]
pub enum CamServeError {
    #[error(transparent)]
    Serve(#[from] ServeError),
    #[error("cannot open the artifact store")]
    Artifacts(#[from] depthmill_common::artifacts::ArtifactError),
    #[error("cannot load the tool library")]
    Tools(#[from] crate::domain::CamError),
}

/// Serves the cam service on `listener` until `shutdown` completes.
pub async fn serve(
    listener: tokio::net::TcpListener,
    config: Config,
    shutdown: impl Future<Output = ()> + Send,
) -> Result<(), CamServeError> {
    let options =
        depthmill_common::grpc::GrpcOptions { token: config.service_token.clone(), ..Default::default() };
    let mut library = crate::domain::tool::ToolLibrary::builtin()?;
    if let Some(dir) = &config.tools_dir {
        library = library.merged(crate::domain::tool::ToolLibrary::load_dir(dir)?);
    }
    let store =
        depthmill_common::artifacts::open_store(&config.artifacts_dir, config.artifact_store.as_ref())
            .await?;
    let routes = crate::grpc::routes(store, library);
    Ok(depthmill_common::grpc::serve_grpc_with(listener, routes, SERVICE_NAMES, options, shutdown).await?)
}
