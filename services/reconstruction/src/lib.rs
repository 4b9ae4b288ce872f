//! Reconstruction service: registered point clouds and meshes to depth maps, coverage and roughing maps.
//!
//! `BuildDepthMaps` reads the input artifact (XYZ/PLY cloud or STL/PLY mesh), cleans the cloud,
//! and writes per face a depth map, a coverage map and a roughing map (PNG with depthmill
//! metadata) plus a JSON report; see [`domain::pipeline`].
//!
//! # Layout
//! - [`domain`]: the library (readers, filters, rasterisation, fills, mesh z-buffer, roughing
//!   maps, image operations, the stage pipeline).
//! - [`Config`]: listen address, artifact folder, input limits.
//! - [`serve`]: the gRPC server on a bound listener.
//! - `grpc`: the tonic adapter (the only module that knows proto types).

pub mod domain;
mod grpc;

use std::future::Future;
use std::net::SocketAddr;
use std::path::PathBuf;

pub use depthmill_common::grpc::ServeError;

/// Configuration of the reconstruction service (`deploy/config/reconstruction.toml`, env `DEPTHMILL_RECONSTRUCTION__KEY`).
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
    /// Largest input accepted, in points (clouds) or vertices.
    #[serde(default = "default_max_points")]
    pub max_points: u64,
    /// Largest mesh accepted, in triangles.
    #[serde(default = "default_max_triangles")]
    pub max_triangles: u64,
    /// Shared secret the orchestrator sends with every call (`authorization: Bearer <token>`);
    /// calls without it are refused (UNAUTHENTICATED). Unset: no check (loopback or a private
    /// network). Health, reflection and `/metrics` stay open.
    #[serde(default)]
    pub service_token: Option<String>,
}

fn default_max_points() -> u64 {
    depthmill_geometry::formats::ReadLimits::default().max_points
}

fn default_max_triangles() -> u64 {
    depthmill_geometry::formats::ReadLimits::default().max_triangles
}

fn default_grpc_addr() -> SocketAddr {
    SocketAddr::from(([127, 0, 0, 1], 50052))
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
            max_points: default_max_points(),
            max_triangles: default_max_triangles(),
            service_token: None,
        }
    }
}

/// The gRPC service names this server reports in its health service.
pub const SERVICE_NAMES: &[&str] = &[grpc::SERVICE_NAME];

/// Serves the reconstruction service on `listener` until `shutdown` completes.
pub async fn serve(
    listener: tokio::net::TcpListener,
    config: Config,
    shutdown: impl Future<Output = ()> + Send,
) -> Result<(), ReconServeError> {
    let options =
        depthmill_common::grpc::GrpcOptions { token: config.service_token.clone(), ..Default::default() };
    let store =
        depthmill_common::artifacts::open_store(&config.artifacts_dir, config.artifact_store.as_ref())
            .await?;
    let limits = depthmill_geometry::formats::ReadLimits {
        max_points: config.max_points,
        max_triangles: config.max_triangles,
        ..Default::default()
    };
    let routes = grpc::routes(store, limits);
    Ok(depthmill_common::grpc::serve_grpc_with(listener, routes, SERVICE_NAMES, options, shutdown).await?)
}

/// Why the service could not start or stopped.
#[derive(Debug, thiserror::Error)]
pub enum ReconServeError {
    #[error(transparent)]
    Serve(#[from] ServeError),
    #[error("cannot open the artifact store")]
    Artifacts(#[from] depthmill_common::artifacts::ArtifactError),
}
