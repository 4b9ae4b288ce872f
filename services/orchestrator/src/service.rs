//! The service: configuration and server (feature `service`, on by default).

use crate::{app, auth, events, grpc, http, stages, store, worker};
use std::future::Future;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use depthmill_common::artifacts::{ArtifactError, ObjectStoreConfig};
use metrics_exporter_prometheus::PrometheusHandle;
use serde::Deserialize;
use tokio::net::TcpListener;
use tokio_util::sync::CancellationToken;

pub use stages::Endpoints;
pub use worker::WorkerConfig;

/// Configuration of the orchestrator (`deploy/config/orchestrator.toml`, env `DEPTHMILL_ORCHESTRATOR__KEY`).
#[derive(Debug, Clone, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct Config {
    /// REST listen address.
    pub rest_addr: SocketAddr,
    /// gRPC listen address.
    pub grpc_addr: SocketAddr,
    /// Holds `node_id`, `artifacts/` (unless `artifacts_dir` says otherwise) and, on the embedded
    /// default, `jobs.sqlite`. Each replica has its own (its `node_id` names its leases).
    pub data_dir: PathBuf,
    /// The artifact folder, shared with the stage services and the other replicas. Unset:
    /// `<data_dir>/artifacts`.
    pub artifacts_dir: Option<PathBuf>,
    /// The artifacts in an object store (`[artifact_store] url = "s3://BUCKET/PREFIX"`, shared by
    /// every replica and stage service) instead of `artifacts_dir`, which then holds local copies
    /// of the blobs read from files.
    pub artifact_store: Option<ObjectStoreConfig>,
    /// The job database: `sqlite://PATH` or `postgres://USER@HOST:PORT/DB`. Unset: the SQLite
    /// file `<data_dir>/jobs.sqlite`. Replicas sharing one job queue share one PostgreSQL database.
    pub database_url: Option<String>,
    /// Largest artifact upload, bytes.
    pub max_upload_bytes: u64,
    /// Most jobs one client may have queued or running at once; a submission past it is refused
    /// (429 `quota_exceeded`, gRPC RESOURCE_EXHAUSTED). A client is its API token when tokens are
    /// required, otherwise its IP address. 0: no limit.
    pub max_active_jobs_per_client: u32,
    /// Stage service URLs; an empty one makes its stage fail with `stage_not_available`.
    pub services: Endpoints,
    pub worker: WorkerConfig,
    /// API tokens: required, not required on loopback, or not at all.
    pub auth: auth::AuthConfig,
    /// TLS for REST (HTTPS) and gRPC: certificate and key files (PEM). Unset: plain TCP.
    pub tls: Option<depthmill_common::tls::TlsFiles>,
}

impl Default for Config {
    fn default() -> Self {
        Self {
            rest_addr: SocketAddr::from(([127, 0, 0, 1], 8080)),
            grpc_addr: SocketAddr::from(([127, 0, 0, 1], 50050)),
            data_dir: PathBuf::from("data"),
            artifacts_dir: None,
            artifact_store: None,
            database_url: None,
            max_upload_bytes: 4 << 30,
            max_active_jobs_per_client: 1000,
            services: Endpoints::default(),
            worker: WorkerConfig::default(),
            auth: auth::AuthConfig::default(),
            tls: None,
        }
    }
}

/// Why the orchestrator could not start or stopped with an error.
#[derive(Debug, thiserror::Error)]
pub enum OrchestratorError {
    #[error("cannot prepare the data directory {path}")]
    DataDir {
        path: String,
        #[source]
        source: std::io::Error,
    },
    #[error("cannot open the job store")]
    Store(#[from] store::StoreError),
    #[error("cannot open the artifact store")]
    Artifacts(#[from] ArtifactError),
    #[error("invalid service endpoint")]
    Endpoint(#[from] stages::EndpointError),
    #[error("REST server failed")]
    Rest(#[source] std::io::Error),
    #[error("gRPC server failed")]
    Grpc(#[from] depthmill_common::grpc::ServeError),
    #[error("refusing to serve without API tokens")]
    Open(#[from] auth::OpenOnNetwork),
    #[error("cannot set up TLS")]
    Tls(#[from] depthmill_common::tls::TlsError),
    #[error("cannot set up TLS for REST")]
    RestTls(#[source] rustls::Error),
}

/// The gRPC service names the orchestrator reports in its health service.
pub const SERVICE_NAMES: &[&str] = &[grpc::SERVICE_NAME];

fn node_id(data_dir: &Path) -> Result<String, OrchestratorError> {
    let path = data_dir.join("node_id");
    let err = |source| OrchestratorError::DataDir { path: path.display().to_string(), source };
    match std::fs::read_to_string(&path) {
        Ok(s) if !s.trim().is_empty() => Ok(s.trim().to_string()),
        Ok(_) => Err(err(std::io::Error::other("node_id is empty"))),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            let id = format!("node-{}", uuid::Uuid::now_v7());
            std::fs::write(&path, &id).map_err(err)?;
            Ok(id)
        }
        Err(e) => Err(err(e)),
    }
}

/// Serves REST on `rest` and gRPC on `grpc`, and runs the job worker, until `shutdown` completes.
/// `metrics` is the process's Prometheus recorder handle, rendered at `/metrics`.
pub async fn serve(
    rest: TcpListener,
    grpc: TcpListener,
    config: Config,
    metrics: Option<PrometheusHandle>,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> Result<(), OrchestratorError> {
    let rest_addr = rest.local_addr().map_err(OrchestratorError::Rest)?;
    let grpc_addr = grpc.local_addr().map_err(OrchestratorError::Rest)?;
    let tokens_required = auth::tokens_required(config.auth.mode, rest_addr, grpc_addr)?;
    // Certificates are checked before anything else is touched.
    let tls = config.tls.as_ref().map(depthmill_common::tls::Identity::load).transpose()?;
    let rest_tls =
        tls.as_ref().map(|t| t.http1_acceptor()).transpose().map_err(OrchestratorError::RestTls)?;
    let data_dir = &config.data_dir;
    std::fs::create_dir_all(data_dir)
        .map_err(|source| OrchestratorError::DataDir { path: data_dir.display().to_string(), source })?;
    let owner = node_id(data_dir)?;
    let database_url = match &config.database_url {
        Some(url) => url.clone(),
        None => format!("sqlite://{}", data_dir.join("jobs.sqlite").display()),
    };
    let store = store::open(&database_url).await?;
    tracing::info!(database = %store::redact(&database_url), node = %owner, "job store open");
    let artifacts_dir = config.artifacts_dir.clone().unwrap_or_else(|| data_dir.join("artifacts"));
    let artifacts =
        depthmill_common::artifacts::open_store(&artifacts_dir, config.artifact_store.as_ref()).await?;
    tracing::info!(artifacts = %artifacts.location(), "artifact store open");
    let stages = Arc::new(stages::GrpcStages::new(&config.services)?);
    let app = app::App {
        store: store.clone(),
        artifacts: Arc::new(artifacts),
        events: Arc::new(events::EventHub::default()),
        limits: app::ApiLimits {
            max_upload_bytes: config.max_upload_bytes,
            max_active_jobs_per_client: config.max_active_jobs_per_client,
            default_page: 50,
            max_page: 1000,
        },
        running: Default::default(),
        stages: stages.clone(),
        auth: Arc::new(auth::Authenticator::new(store.clone(), tokens_required, config.auth.cache_s)),
        in_flight: Default::default(),
    };
    let worker = Arc::new(worker::Worker::new(app.clone(), stages, config.worker.clone(), owner));

    let token = CancellationToken::new();
    let stop = token.clone();
    tokio::spawn(async move {
        shutdown.await;
        stop.cancel();
    });
    tracing::info!(addr = %rest_addr, tokens_required, tls = rest_tls.is_some(), "REST listening");
    let rest_token = token.clone();
    let router = http::router(app.clone(), metrics);
    let rest_server = async move {
        match rest_tls {
            Some(acceptor) => {
                depthmill_common::tls::serve_https(rest, router, acceptor, rest_token.cancelled()).await
            }
            None => {
                // The peer's address names the client when tokens are not required.
                axum::serve(rest, router.into_make_service_with_connect_info::<SocketAddr>())
                    .with_graceful_shutdown(rest_token.cancelled_owned())
                    .await
            }
        }
    };
    let grpc_token = token.clone();
    let grpc_server = depthmill_common::grpc::serve_grpc_with(
        grpc,
        grpc::routes(app),
        SERVICE_NAMES,
        depthmill_common::grpc::GrpcOptions { tls: tls.as_ref().map(|t| t.grpc()), token: None },
        async move { grpc_token.cancelled().await },
    );
    let worker_run = worker.run(token.clone());
    let (rest_result, grpc_result, worker_result) = tokio::join!(
        async {
            let r = rest_server.await;
            token.cancel();
            r
        },
        async {
            let r = grpc_server.await;
            token.cancel();
            r
        },
        async {
            let r = worker_run.await;
            token.cancel();
            r
        }
    );
    rest_result.map_err(OrchestratorError::Rest)?;
    grpc_result?;
    worker_result?;
    Ok(())
}
