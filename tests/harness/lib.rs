//! The in-process test stack: the orchestrator and every stage service on `127.0.0.1:0`, over real
//! gRPC and HTTP sockets, with artifacts in a temporary directory and jobs in SQLite there (or in
//! the PostgreSQL database [`StackOptions::database_url`] names).
//!
//! # Layout
//! - [`TestStack`]: start, restart the orchestrator, stop; REST helpers.
//! - [`scripted`]: a machine service for exercising the orchestrator (delays, transient failures,
//!   rejections, cancellation), served over gRPC like the real one.

pub mod scripted;

use depthmill_common::artifacts::ObjectStoreConfig;
use std::path::PathBuf;
use std::sync::LazyLock;
use std::time::Duration;

use anyhow::{Context as _, bail};
use depthmill_proto::orchestrator::v1::orchestrator_service_client::OrchestratorServiceClient;
use serde_json::Value;
use tokio::net::TcpListener;
use tokio::task::JoinHandle;
use tokio_util::sync::CancellationToken;
use tonic::transport::Channel;

static TRACING: LazyLock<()> = LazyLock::new(|| {
    if std::env::var_os("TEST_LOG").is_some() {
        depthmill_common::telemetry::init_tracing(false);
    }
});

/// Which machine service the stack runs.
#[derive(Clone)]
pub enum MachineBackend {
    /// The real machine service.
    Real,
    /// The scripted service.
    Scripted(scripted::Script),
}

/// Options of [`TestStack::start_with`].
#[derive(Clone)]
pub struct StackOptions {
    pub machine: MachineBackend,
    pub max_upload_bytes: u64,
    /// The orchestrator's `max_active_jobs_per_client` (default: the product's, 1000).
    pub max_active_jobs_per_client: u32,
    pub max_attempts: u32,
    pub stage_deadline_s: f64,
    /// Run the scanning service (without it, the orchestrator has no scanning endpoint).
    pub scanning: bool,
    /// The job database; `None`: SQLite in the stack's data folder.
    pub database_url: Option<String>,
    /// API tokens (default: not required, the stack is on loopback).
    pub auth: depthmill_orchestrator::auth::AuthConfig,
    /// The artifact folder of every service (default: `artifacts/` in the stack's data folder).
    pub artifacts_dir: Option<PathBuf>,
    /// The artifacts in an object store (every service shares it; `artifacts_dir` then holds the
    /// services' local copies).
    pub artifact_store: Option<ObjectStoreConfig>,
}

impl Default for StackOptions {
    fn default() -> Self {
        Self {
            scanning: true,
            machine: MachineBackend::Real,
            max_upload_bytes: 1 << 20,
            max_active_jobs_per_client: 1000,
            max_attempts: 4,
            stage_deadline_s: 30.0,
            database_url: None,
            auth: Default::default(),
            artifacts_dir: None,
            artifact_store: None,
        }
    }
}

struct Running {
    token: CancellationToken,
    handle: JoinHandle<anyhow::Result<()>>,
}

/// Every service of depthmill in this process.
pub struct TestStack {
    pub rest_url: String,
    pub grpc_url: String,
    pub http: reqwest::Client,
    pub data_dir: PathBuf,
    config: depthmill_orchestrator::Config,
    orchestrator: Option<Running>,
    services: Vec<Running>,
    /// (kind, address) of each stage service, in the order of `services`.
    stages: Vec<(String, std::net::SocketAddr)>,
    artifacts_dir: PathBuf,
    artifact_store: Option<ObjectStoreConfig>,
    service_urls: Vec<(String, String)>,
    _dir: tempfile::TempDir,
}

async fn loopback() -> anyhow::Result<TcpListener> {
    Ok(TcpListener::bind("127.0.0.1:0").await?)
}

/// The secret the test stacks' orchestrators send to their stage services, which require it.
pub const SERVICE_TOKEN: &str = "test-service-token";

/// Adds the test stacks' service token to every call, as the orchestrator does.
#[derive(Clone, Copy, Debug, Default)]
pub struct ServiceToken;

impl tonic::service::Interceptor for ServiceToken {
    fn call(&mut self, mut request: tonic::Request<()>) -> Result<tonic::Request<()>, tonic::Status> {
        let value = format!("Bearer {SERVICE_TOKEN}")
            .parse()
            .map_err(|_| tonic::Status::internal("the service token is not a header value"))?;
        request.metadata_mut().insert("authorization", value);
        Ok(request)
    }
}

/// A channel to a stage service of a test stack, carrying the service token.
pub type ServiceChannel = tonic::service::interceptor::InterceptedService<Channel, ServiceToken>;

/// Connects to a stage service of a test stack as its orchestrator would.
pub async fn service_channel(url: String) -> anyhow::Result<ServiceChannel> {
    let channel = Channel::from_shared(url)?.connect().await?;
    Ok(tonic::service::interceptor::InterceptedService::new(channel, ServiceToken))
}

/// Starts the real stage service `kind` on `listener`.
fn spawn_stage(
    kind: &str,
    listener: TcpListener,
    artifacts_dir: PathBuf,
    artifact_store: Option<ObjectStoreConfig>,
) -> anyhow::Result<Running> {
    let addr = listener.local_addr()?;
    let token = CancellationToken::new();
    let stop = token.clone();
    macro_rules! spawn {
        ($krate:ident) => {{
            // Service configs differ beyond these two fields (the cam service has more).
            #[allow(clippy::needless_update)]
            let cfg = $krate::Config {
                grpc_addr: addr,
                artifacts_dir,
                artifact_store,
                service_token: Some(SERVICE_TOKEN.into()),
                ..Default::default()
            };
            tokio::spawn(async move {
                $krate::serve(listener, cfg, async move { stop.cancelled().await }).await?;
                Ok(())
            })
        }};
    }
    let handle = match kind {
        "scanning" => spawn!(depthmill_scanning),
        "reconstruction" => spawn!(depthmill_reconstruction),
        "cam" => spawn!(depthmill_cam),
        "machine" => spawn!(depthmill_machine),
        other => bail!("no stage service {other}"),
    };
    Ok(Running { token, handle })
}

impl TestStack {
    /// The stack with every real service.
    pub async fn start() -> anyhow::Result<Self> {
        Self::start_with(StackOptions::default()).await
    }

    pub async fn start_with(opts: StackOptions) -> anyhow::Result<Self> {
        LazyLock::force(&TRACING);
        let dir = tempfile::tempdir()?;
        let data_dir = dir.path().join("data");
        let artifacts_dir = opts.artifacts_dir.clone().unwrap_or_else(|| data_dir.join("artifacts"));
        let mut services = Vec::new();
        let mut stages = Vec::new();
        let mut service_urls = Vec::new();
        let mut endpoints = depthmill_orchestrator::Endpoints::none();
        endpoints.token = Some(SERVICE_TOKEN.into());

        macro_rules! real {
            ($krate:ident, $field:ident) => {{
                let listener = loopback().await?;
                let addr = listener.local_addr()?;
                endpoints.$field = format!("http://{addr}");
                for name in $krate::SERVICE_NAMES {
                    service_urls.push((name.to_string(), endpoints.$field.clone()));
                }
                let running = spawn_stage(
                    stringify!($field),
                    listener,
                    artifacts_dir.clone(),
                    opts.artifact_store.clone(),
                )?;
                stages.push((stringify!($field).to_string(), addr));
                services.push(running);
            }};
        }
        if opts.scanning {
            real!(depthmill_scanning, scanning);
        }
        real!(depthmill_reconstruction, reconstruction);
        real!(depthmill_cam, cam);
        match &opts.machine {
            MachineBackend::Real => real!(depthmill_machine, machine),
            MachineBackend::Scripted(script) => {
                let listener = loopback().await?;
                let addr = listener.local_addr()?;
                endpoints.machine = format!("http://{addr}");
                service_urls
                    .push(("depthmill.machine.v1.MachineService".to_string(), endpoints.machine.clone()));
                script.set_addr(addr);
                stages.push(("machine-scripted".to_string(), addr));
                let store =
                    depthmill_common::artifacts::open_store(&artifacts_dir, opts.artifact_store.as_ref())
                        .await?;
                let token = CancellationToken::new();
                let stop = token.clone();
                let script = script.clone();
                let handle = tokio::spawn(async move { script.serve(listener, store, stop).await });
                services.push(Running { token, handle });
            }
        }

        let config = depthmill_orchestrator::Config {
            rest_addr: "127.0.0.1:0".parse()?,
            grpc_addr: "127.0.0.1:0".parse()?,
            data_dir: data_dir.clone(),
            artifacts_dir: Some(artifacts_dir.clone()),
            artifact_store: opts.artifact_store.clone(),
            database_url: opts.database_url.clone(),
            max_upload_bytes: opts.max_upload_bytes,
            max_active_jobs_per_client: opts.max_active_jobs_per_client,
            services: endpoints,
            worker: depthmill_orchestrator::WorkerConfig {
                concurrency: 2,
                lease_s: 3.0,
                poll_ms: 50,
                max_attempts: opts.max_attempts,
                backoff_min_ms: 20,
                backoff_max_ms: 200,
                stage_deadline_s: opts.stage_deadline_s,
                cancel_grace_s: 2.0,
            },
            auth: opts.auth.clone(),
            tls: None,
        };
        let mut stack = Self {
            rest_url: String::new(),
            grpc_url: String::new(),
            http: depthmill_common::tls::http_client().build()?,
            data_dir,
            config,
            orchestrator: None,
            services,
            stages,
            artifacts_dir,
            artifact_store: opts.artifact_store.clone(),
            service_urls,
            _dir: dir,
        };
        stack.start_orchestrator().await?;
        Ok(stack)
    }

    async fn start_orchestrator(&mut self) -> anyhow::Result<()> {
        let rest = loopback().await?;
        let grpc = loopback().await?;
        self.rest_url = format!("http://{}", rest.local_addr()?);
        self.grpc_url = format!("http://{}", grpc.local_addr()?);
        let token = CancellationToken::new();
        let stop = token.clone();
        let cfg = self.config.clone();
        let handle = tokio::spawn(async move {
            depthmill_orchestrator::serve(rest, grpc, cfg, None, async move { stop.cancelled().await })
                .await?;
            Ok(())
        });
        self.orchestrator = Some(Running { token, handle });
        // Ready when /readyz answers.
        for _ in 0..200 {
            if let Ok(r) = self.http.get(self.url("/readyz")).send().await
                && r.status().is_success()
            {
                return Ok(());
            }
            tokio::time::sleep(Duration::from_millis(25)).await;
        }
        bail!("orchestrator did not become ready")
    }

    /// Stops the orchestrator as a crash would leave it (running stages abandoned, nothing
    /// finalised), then starts a new one on the same database and artifact folder.
    pub async fn restart_orchestrator(&mut self) -> anyhow::Result<()> {
        self.stop_orchestrator().await?;
        self.start_orchestrator().await
    }

    /// Stops the orchestrator, abandoning whatever it was running.
    pub async fn stop_orchestrator(&mut self) -> anyhow::Result<()> {
        if let Some(o) = self.orchestrator.take() {
            o.token.cancel();
            o.handle.abort();
            match o.handle.await {
                Ok(r) => r?,
                Err(e) if e.is_cancelled() => {}
                Err(e) => bail!("orchestrator task failed: {e}"),
            }
        }
        Ok(())
    }

    /// Stops the stage service `kind` (`scanning`, `reconstruction`, `cam`, `machine`): its port
    /// refuses connections until [`TestStack::start_service`].
    pub async fn stop_service(&mut self, kind: &str) -> anyhow::Result<()> {
        let i = self.stage_index(kind)?;
        let r = &self.services[i];
        r.token.cancel();
        // Wait until the server has let go of its port.
        for _ in 0..200 {
            if r.handle.is_finished() {
                return Ok(());
            }
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
        bail!("the {kind} service did not stop")
    }

    /// Starts the stage service `kind` again on the same port.
    pub async fn start_service(&mut self, kind: &str) -> anyhow::Result<()> {
        let i = self.stage_index(kind)?;
        let addr = self.stages[i].1;
        let listener = TcpListener::bind(addr).await.with_context(|| format!("rebinding {addr}"))?;
        self.services[i] =
            spawn_stage(kind, listener, self.artifacts_dir.clone(), self.artifact_store.clone())?;
        Ok(())
    }

    fn stage_index(&self, kind: &str) -> anyhow::Result<usize> {
        self.stages
            .iter()
            .position(|(k, _)| k == kind)
            .with_context(|| format!("no {kind} service in this stack"))
    }

    /// (gRPC service name, URL) of every server: the orchestrator and each stage service.
    pub fn service_urls(&self) -> Vec<(String, String)> {
        let mut all = vec![(depthmill_orchestrator::SERVICE_NAMES[0].to_string(), self.grpc_url.clone())];
        all.extend(self.service_urls.iter().cloned());
        all
    }

    pub fn url(&self, path: &str) -> String {
        format!("{}{path}", self.rest_url)
    }

    /// A gRPC client of the orchestrator.
    pub async fn grpc(&self) -> anyhow::Result<OrchestratorServiceClient<Channel>> {
        Ok(OrchestratorServiceClient::connect(self.grpc_url.clone()).await?)
    }

    /// Issues an API token with `scopes` (e.g. `submit`) on the stack's job database, as
    /// `depthmill token create` does.
    pub async fn issue_token(
        &self,
        name: &str,
        scopes: &str,
    ) -> anyhow::Result<depthmill_orchestrator::auth::IssuedToken> {
        let url = match &self.config.database_url {
            Some(url) => url.clone(),
            None => format!("sqlite://{}", self.data_dir.join("jobs.sqlite").display()),
        };
        let store = depthmill_orchestrator::store::open(&url).await?;
        let now = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH)?.as_millis() as i64;
        Ok(depthmill_orchestrator::auth::issue(&*store, name, scopes, None, now).await?)
    }

    /// Uploads bytes; returns the sha256.
    pub async fn upload(&self, media_type: &str, bytes: Vec<u8>) -> anyhow::Result<String> {
        let resp = self
            .http
            .post(self.url("/v1/artifacts"))
            .header("content-type", media_type)
            .body(bytes)
            .send()
            .await?;
        let status = resp.status();
        let body: Value = resp.json().await?;
        if status.as_u16() != 201 {
            bail!("upload failed: {status} {body}");
        }
        Ok(body["sha256"].as_str().context("no sha256")?.to_string())
    }

    /// Posts a job; returns status code and body.
    pub async fn post_job(&self, body: &Value, key: Option<&str>) -> anyhow::Result<(u16, Value)> {
        let mut req = self.http.post(self.url("/v1/jobs")).json(body);
        if let Some(k) = key {
            req = req.header("Idempotency-Key", k);
        }
        let resp = req.send().await?;
        Ok((resp.status().as_u16(), resp.json().await?))
    }

    pub async fn get_job(&self, id: &str) -> anyhow::Result<Value> {
        Ok(self.http.get(self.url(&format!("/v1/jobs/{id}"))).send().await?.json().await?)
    }

    /// Polls until the job ends or `timeout` passes.
    pub async fn wait_for_end(&self, id: &str, timeout: Duration) -> anyhow::Result<Value> {
        let deadline = tokio::time::Instant::now() + timeout;
        loop {
            let job = self.get_job(id).await?;
            if matches!(job["status"].as_str(), Some("succeeded" | "failed" | "cancelled")) {
                return Ok(job);
            }
            if tokio::time::Instant::now() > deadline {
                bail!("job {id} did not end within {timeout:?}: {job}");
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    }

    /// Stops everything.
    pub async fn shutdown(mut self) -> anyhow::Result<()> {
        self.stop_orchestrator().await?;
        for s in self.services.drain(..) {
            s.token.cancel();
            let _ = s.handle.await;
        }
        Ok(())
    }
}

impl Drop for TestStack {
    fn drop(&mut self) {
        if let Some(o) = &self.orchestrator {
            o.token.cancel();
            o.handle.abort();
        }
        for s in &self.services {
            s.token.cancel();
            s.handle.abort();
        }
    }
}
