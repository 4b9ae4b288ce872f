//! Scanning service: a laser line scanner on a 6-axis robot arm, the part on a rotary table, positions latched at every frame.
//!
//! The scanning stage is not provided yet: `ScanPart` answers UNIMPLEMENTED ("stage not available"),
//! which the orchestrator reports as a failed job with code `stage_not_available`. The service
//! already serves health, reflection and `CancelStage`.
//!
//! # Layout
//! - [`Config`]: listen address and artifact folder.
//! - [`serve`]: the gRPC server on a bound listener.
//! - `grpc`: the tonic adapter (the only module that knows proto types).

pub mod devices;
pub mod domain;
mod grpc;

use std::future::Future;
use std::net::SocketAddr;
use std::path::PathBuf;

pub use depthmill_common::grpc::ServeError;

/// Configuration of the scanning service (`deploy/config/scanning.toml`, env `DEPTHMILL_SCANNING__KEY`).
#[derive(Debug, Clone, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Config {
    /// gRPC listen address.
    #[serde(default = "default_grpc_addr")]
    pub grpc_addr: SocketAddr,
    /// Folder of the artifact store shared with the orchestrator.
    #[serde(default = "default_artifacts_dir")]
    pub artifacts_dir: PathBuf,
}

fn default_grpc_addr() -> SocketAddr {
    SocketAddr::from(([127, 0, 0, 1], 50051))
}

fn default_artifacts_dir() -> PathBuf {
    PathBuf::from("data/artifacts")
}

impl Default for Config {
    fn default() -> Self {
        Self { grpc_addr: default_grpc_addr(), artifacts_dir: default_artifacts_dir() }
    }
}

/// The gRPC service names this server reports in its health service.
pub const SERVICE_NAMES: &[&str] = &[grpc::SERVICE_NAME];

/// Serves the scanning service on `listener` until `shutdown` completes.
pub async fn serve(
    listener: tokio::net::TcpListener,
    _config: Config,
    shutdown: impl Future<Output = ()> + Send,
) -> Result<(), ServeError> {
    depthmill_common::grpc::serve_grpc(listener, grpc::routes(), SERVICE_NAMES, shutdown).await
}
