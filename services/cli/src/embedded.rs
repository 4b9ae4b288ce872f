//! `depthmill serve`: every service in one process, talking gRPC over loopback.

use std::net::SocketAddr;
use std::path::PathBuf;

use anyhow::Context as _;
use tokio::net::TcpListener;
use tokio_util::sync::CancellationToken;

async fn loopback() -> anyhow::Result<TcpListener> {
    TcpListener::bind("127.0.0.1:0").await.context("binding a loopback port for a stage service")
}

/// The embedded stack, running.
pub struct Stack {
    pub rest_addr: SocketAddr,
    /// `https` when the configuration gives TLS files, else `http`.
    pub scheme: &'static str,
    pub grpc_addr: SocketAddr,
    token: CancellationToken,
    tasks: tokio::task::JoinSet<anyhow::Result<()>>,
}

impl Stack {
    /// Waits until a part of the stack stops (then stops the rest) and returns the first error.
    pub async fn wait(mut self) -> anyhow::Result<()> {
        let mut first_error = None;
        while let Some(joined) = self.tasks.join_next().await {
            // Any part stopping stops the whole stack.
            self.token.cancel();
            match joined {
                Ok(Ok(())) => {}
                Ok(Err(e)) => {
                    tracing::error!(error = format!("{e:#}"), "a part of the stack failed");
                    first_error.get_or_insert(e);
                }
                Err(e) => {
                    first_error.get_or_insert(anyhow::anyhow!("a part of the stack panicked: {e}"));
                }
            }
        }
        first_error.map_or(Ok(()), Err)
    }

    /// Stops every part and waits for them.
    pub async fn stop(self) -> anyhow::Result<()> {
        self.token.cancel();
        self.wait().await
    }
}

/// `depthmill serve`: starts the stack, prints where it listens, runs until a signal.
pub async fn serve(
    data_dir: PathBuf,
    database_url: Option<String>,
    rest_addr: SocketAddr,
    grpc_addr: SocketAddr,
    config: Option<PathBuf>,
) -> anyhow::Result<()> {
    let stack = start(data_dir, database_url, rest_addr, grpc_addr, config).await?;
    crate::outln!("REST listening on {}://{}", stack.scheme, stack.rest_addr);
    crate::outln!("gRPC listening on {}://{}", stack.scheme, stack.grpc_addr);
    crate::outln!("Console: {}://{}/ (open it in a browser)", stack.scheme, stack.rest_addr);
    let stop = stack.token.clone();
    tokio::spawn(async move {
        depthmill_common::shutdown::shutdown_signal().await;
        stop.cancel();
    });
    stack.wait().await
}

/// Starts the orchestrator and the four stage services in this process (stage services on
/// loopback ports); returns once the REST and gRPC listeners are bound. `database_url` (when
/// given) overrides the configuration's job database.
pub async fn start(
    data_dir: PathBuf,
    database_url: Option<String>,
    rest_addr: SocketAddr,
    grpc_addr: SocketAddr,
    config: Option<PathBuf>,
) -> anyhow::Result<Stack> {
    // One recorder for the whole process: the orchestrator's REST /metrics and every service's
    // gRPC-port /metrics render the same registry (calls are labelled by service).
    let metrics = depthmill_common::metrics::install_prometheus()?;
    let mut cfg: depthmill_orchestrator::Config =
        depthmill_common::config::load(config.as_deref(), "DEPTHMILL_ORCHESTRATOR")
            .context("loading configuration")?;
    cfg.data_dir = data_dir;
    if database_url.is_some() {
        cfg.database_url = database_url;
    }
    cfg.rest_addr = rest_addr;
    cfg.grpc_addr = grpc_addr;
    // Every service shares the orchestrator's artifact store: its folder, or its object store
    // (`[artifact_store]`), with the folder holding the services' local copies.
    let artifacts_dir = cfg.artifacts_dir.clone().unwrap_or_else(|| cfg.data_dir.join("artifacts"));
    let artifact_store = cfg.artifact_store.clone();
    // The stage services listen on loopback ports other local users could reach: they take calls
    // carrying this run's secret only.
    let service_token = depthmill_orchestrator::auth::random_secret().context("making the service token")?;
    cfg.services.token = Some(service_token.clone());

    let token = CancellationToken::new();
    let mut tasks = tokio::task::JoinSet::new();
    macro_rules! service {
        ($krate:ident, $field:ident) => {{
            let listener = loopback().await?;
            let addr = listener.local_addr()?;
            cfg.services.$field = format!("http://{addr}");
            // Service configs differ beyond these two fields (the cam service has more).
            #[allow(clippy::needless_update)]
            let svc_cfg = $krate::Config {
                grpc_addr: addr,
                artifacts_dir: artifacts_dir.clone(),
                artifact_store: artifact_store.clone(),
                service_token: Some(service_token.clone()),
                ..Default::default()
            };
            let stop = token.clone();
            tasks.spawn(async move {
                $krate::serve(listener, svc_cfg, async move { stop.cancelled().await })
                    .await
                    .with_context(|| format!("{} service", stringify!($field)))
            });
        }};
    }
    service!(depthmill_scanning, scanning);
    service!(depthmill_reconstruction, reconstruction);
    service!(depthmill_cam, cam);
    service!(depthmill_machine, machine);

    let rest =
        TcpListener::bind(cfg.rest_addr).await.with_context(|| format!("binding REST {}", cfg.rest_addr))?;
    let grpc =
        TcpListener::bind(cfg.grpc_addr).await.with_context(|| format!("binding gRPC {}", cfg.grpc_addr))?;
    let rest_addr = rest.local_addr()?;
    let scheme = if cfg.tls.is_some() { "https" } else { "http" };
    let grpc_addr = grpc.local_addr()?;
    let stop = token.clone();
    tasks.spawn(async move {
        depthmill_orchestrator::serve(rest, grpc, cfg, Some(metrics), async move { stop.cancelled().await })
            .await
            .context("orchestrator")
    });
    Ok(Stack { rest_addr, scheme, grpc_addr, token, tasks })
}
