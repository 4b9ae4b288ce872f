//! Scanning service: a laser line scanner on a 6-axis robot arm, the part on a rotary table, positions latched at every frame.
//!
//! `ScanPart` scans a part given as a mesh (STL/PLY) on the simulated cell and stores the
//! registered cloud (binary PLY with intensity and pass ids, the format reconstruction reads) and a
//! JSON scan report; `PlanScan` returns the plan without scanning. The cell's devices are served
//! too: `MotionControllerService` (arm and table) and `EncoderLatchService`.
//!
//! # Layout
//! - [`Config`]: listen address, artifact folder, where the rotary table's controller listens.
//! - [`serve`]: the gRPC server on a bound listener (and the simulated table when no address is
//!   configured).
//! - [`domain`]: the devices' models, scan planning and execution (pure, synchronous).
//! - [`devices`]: device I/O (the table on a socket and its driver).
//! - [`session`]: a whole scan with the table driven over its protocol.
//! - `grpc`, `grpc_devices`: the tonic adapters (the only modules that know proto types).

pub mod devices;
pub mod domain;
mod grpc;
mod grpc_devices;
pub mod session;

pub use grpc::encode_cloud;

use std::future::Future;
use std::net::SocketAddr;
use std::path::PathBuf;

pub use depthmill_common::grpc::ServeError;

/// Configuration of the scanning service (`deploy/config/scanning.toml`, env `DEPTHMILL_SCANNING__KEY`).
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
    /// Address (`host:port`) of the rotary table's controller. Unset: the service runs a
    /// simulated table on a loopback port of its own and drives it over the same protocol.
    #[serde(default)]
    pub table_addr: Option<String>,
    /// Largest part mesh accepted, in triangles.
    #[serde(default = "default_max_triangles")]
    pub max_triangles: u64,
    /// Shared secret the orchestrator sends with every call (`authorization: Bearer <token>`);
    /// calls without it are refused (UNAUTHENTICATED). Unset: no check (loopback or a private
    /// network). Health, reflection and `/metrics` stay open.
    #[serde(default)]
    pub service_token: Option<String>,
    /// How far the simulated cell truly is from its drawing (table axis, tilt, runout, encoder
    /// zero, robot base, scanner mount, joint encoders); realistic amounts by default. The
    /// software sees only the drawing or the calibration a request hands it.
    #[serde(default)]
    pub cell_errors: domain::calibration::CellErrors,
}

fn default_max_triangles() -> u64 {
    depthmill_geometry::formats::ReadLimits::default().max_triangles
}

fn default_grpc_addr() -> SocketAddr {
    SocketAddr::from(([127, 0, 0, 1], 50051))
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
            table_addr: None,
            max_triangles: default_max_triangles(),
            service_token: None,
            cell_errors: domain::calibration::CellErrors::default(),
        }
    }
}

/// The gRPC service names this server reports in its health service.
pub const SERVICE_NAMES: &[&str] =
    &[grpc::SERVICE_NAME, grpc_devices::MOTION_SERVICE_NAME, grpc_devices::LATCH_SERVICE_NAME];

/// Why the service could not start or stopped.
#[derive(Debug, thiserror::Error)]
pub enum ScanServeError {
    #[error(transparent)]
    Serve(#[from] ServeError),
    #[error("cannot open the artifact store")]
    Artifacts(#[from] depthmill_common::artifacts::ArtifactError),
    #[error("cannot start the simulated rotary table: {0}")]
    Table(String),
    #[error("configuration: {0}")]
    Config(String),
}

/// Serves the scanning service on `listener` until `shutdown` completes.
pub async fn serve(
    listener: tokio::net::TcpListener,
    config: Config,
    shutdown: impl Future<Output = ()> + Send,
) -> Result<(), ScanServeError> {
    config.cell_errors.validate().map_err(|e| ScanServeError::Config(e.to_string()))?;
    let options =
        depthmill_common::grpc::GrpcOptions { token: config.service_token.clone(), ..Default::default() };
    let store =
        depthmill_common::artifacts::open_store(&config.artifacts_dir, config.artifact_store.as_ref())
            .await?;
    let stop_table = tokio_util::sync::CancellationToken::new();
    let table_addr = match &config.table_addr {
        Some(a) => a.clone(),
        None => {
            let l = tokio::net::TcpListener::bind(("127.0.0.1", 0))
                .await
                .map_err(|e| ScanServeError::Table(e.to_string()))?;
            let addr = l.local_addr().map_err(|e| ScanServeError::Table(e.to_string()))?;
            let sim = devices::table::SimulatedTable::new(domain::table::TableConfig::default())
                .map_err(|e| ScanServeError::Table(e.to_string()))?;
            let stop = stop_table.clone().cancelled_owned();
            tokio::spawn(sim.serve(l, stop));
            tracing::info!(%addr, "simulated rotary table listening");
            addr.to_string()
        }
    };
    let limits =
        depthmill_geometry::formats::ReadLimits { max_triangles: config.max_triangles, ..Default::default() };
    let cell = std::sync::Arc::new(grpc::Cell {
        store: std::sync::Arc::new(store),
        limits,
        table_addr: table_addr.clone(),
        layout: domain::scan::CellLayout::default(),
        errors: config.cell_errors,
        busy: tokio::sync::Mutex::new(()),
    });
    let devices = grpc_devices::Devices::new(table_addr).map_err(|e| ScanServeError::Table(e.to_string()))?;
    let routes = grpc_devices::add_routes(grpc::routes(cell), std::sync::Arc::new(devices));
    let r = depthmill_common::grpc::serve_grpc_with(listener, routes, SERVICE_NAMES, options, shutdown).await;
    stop_table.cancel();
    Ok(r?)
}
