//! A machine service whose behaviour a test scripts: transient failures, rejections, delays,
//! holding a stage until released or cancelled. It speaks the real `MachineService` contract over a
//! real socket and reads and writes the real artifact store, so the orchestrator cannot tell it
//! from a machine service; it exists to drive the orchestrator through its failure paths.

use std::net::SocketAddr;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;

use depthmill_common::artifacts::{ArtifactStore, ObjectArtifactStore};
use depthmill_common::stage::StageRegistry;
use depthmill_proto::machine::v1 as pb;
use depthmill_proto::machine::v1::machine_service_server::{MachineService, MachineServiceServer};
use depthmill_proto::types::v1::{CancelStageRequest, CancelStageResponse, Progress};
use tokio::net::TcpListener;
use tokio::sync::{Notify, mpsc};
use tokio_util::sync::CancellationToken;
use tonic::{Request, Response, Status};

#[derive(Default)]
struct State {
    fail_unavailable: u32,
    fail_mid: u32,
    fault_mid: Option<String>,
    reject: Option<String>,
    delay: Duration,
    hold: bool,
    calls: u32,
    completed: u32,
    cancels: u32,
    addr: Option<SocketAddr>,
}

/// Shared script of a scripted machine service. Clones share state.
#[derive(Clone, Default)]
pub struct Script {
    state: Arc<Mutex<State>>,
    released: Arc<Notify>,
    changed: Arc<Notify>,
}

impl Script {
    fn lock(&self) -> MutexGuard<'_, State> {
        match self.state.lock() {
            Ok(g) => g,
            Err(p) => p.into_inner(),
        }
    }

    /// The next `n` calls fail with UNAVAILABLE.
    pub fn fail_next(&self, n: u32) {
        self.lock().fail_unavailable = n;
    }

    /// The next `n` calls start, report progress, then fail with UNAVAILABLE mid-stage (a drive
    /// that drops out mid-run).
    pub fn fail_mid_next(&self, n: u32) {
        self.lock().fail_mid = n;
    }

    /// Every call starts, reports progress, then fails with INTERNAL and this message (a fault the
    /// service cannot recover from); `None` stops it.
    pub fn fault_mid(&self, message: Option<&str>) {
        self.lock().fault_mid = message.map(str::to_string);
    }

    /// Every call fails with INVALID_ARGUMENT and this message.
    pub fn reject(&self, message: &str) {
        self.lock().reject = Some(message.to_string());
    }

    /// Each call takes this long before its result.
    pub fn set_delay(&self, d: Duration) {
        self.lock().delay = d;
    }

    /// Calls wait for [`Script::release`] (or a cancel) before their result.
    pub fn hold(&self, on: bool) {
        self.lock().hold = on;
    }

    pub fn release(&self) {
        self.lock().hold = false;
        self.released.notify_waiters();
    }

    pub fn calls(&self) -> u32 {
        self.lock().calls
    }

    pub fn completed(&self) -> u32 {
        self.lock().completed
    }

    /// CancelStage requests that found a running stage.
    pub fn cancels(&self) -> u32 {
        self.lock().cancels
    }

    pub fn addr(&self) -> Option<SocketAddr> {
        self.lock().addr
    }

    pub(crate) fn set_addr(&self, addr: SocketAddr) {
        self.lock().addr = Some(addr);
    }

    /// Waits until at least `n` calls arrived.
    pub async fn wait_for_calls(&self, n: u32, timeout: Duration) -> anyhow::Result<()> {
        let deadline = tokio::time::Instant::now() + timeout;
        while self.calls() < n {
            let wait = self.changed.notified();
            if tokio::time::timeout_at(deadline, wait).await.is_err() && self.calls() < n {
                anyhow::bail!("expected {n} calls, got {} within {timeout:?}", self.calls());
            }
        }
        Ok(())
    }

    /// Serves the scripted machine service on `listener` until `shutdown`.
    pub async fn serve(
        self,
        listener: TcpListener,
        store: ObjectArtifactStore,
        shutdown: CancellationToken,
    ) -> anyhow::Result<()> {
        let svc = Scripted { script: self, store: Arc::new(store), running: StageRegistry::default() };
        let routes = tonic::service::Routes::new(MachineServiceServer::new(svc));
        depthmill_common::grpc::serve_grpc(
            listener,
            routes,
            &["depthmill.machine.v1.MachineService"],
            async move { shutdown.cancelled().await },
        )
        .await?;
        Ok(())
    }
}

struct Scripted {
    script: Script,
    store: Arc<ObjectArtifactStore>,
    running: StageRegistry,
}

type Updates = tokio_stream::wrappers::ReceiverStream<Result<pb::ExecuteProgramUpdate, Status>>;

#[tonic::async_trait]
impl MachineService for Scripted {
    type ExecuteProgramStream = Updates;
    type ExecuteRobotStream = tokio_stream::wrappers::ReceiverStream<Result<pb::ExecuteRobotUpdate, Status>>;

    /// The scripted machine is a mill: it answers as a machine service without a robot cell.
    async fn execute_robot(
        &self,
        _request: Request<pb::ExecuteRobotRequest>,
    ) -> Result<Response<Self::ExecuteRobotStream>, Status> {
        Err(Status::unimplemented("scripted machine: no robot cell"))
    }

    /// A scripted machine has no profiles to check against: it answers as a service that predates
    /// the call, so the orchestrator leaves the check to the stage.
    async fn validate_params(
        &self,
        _request: Request<pb::ValidateExecuteRequest>,
    ) -> Result<Response<depthmill_proto::types::v1::ValidateParamsResponse>, Status> {
        Err(Status::unimplemented("scripted machine: no parameter check"))
    }

    async fn list_machines(
        &self,
        _request: Request<pb::ListMachinesRequest>,
    ) -> Result<Response<pb::ListMachinesResponse>, Status> {
        Err(Status::unimplemented("scripted machine: no profiles"))
    }

    async fn execute_program(
        &self,
        request: Request<pb::ExecuteProgramRequest>,
    ) -> Result<Response<Self::ExecuteProgramStream>, Status> {
        let req = request.into_inner();
        let (fail, reject, delay, hold, mid) = {
            let mut s = self.script.lock();
            s.calls += 1;
            let fail = s.fail_unavailable > 0;
            if fail {
                s.fail_unavailable -= 1;
            }
            let mid = if s.fail_mid > 0 {
                s.fail_mid -= 1;
                Some(Status::unavailable("scripted: the spindle drive dropped out mid-run"))
            } else {
                s.fault_mid.clone().map(Status::internal)
            };
            (fail, s.reject.clone(), s.delay, s.hold, mid)
        };
        self.script.changed.notify_waiters();
        if fail {
            return Err(Status::unavailable("scripted: machine busy"));
        }
        if let Some(msg) = reject {
            return Err(Status::invalid_argument(msg));
        }
        let job_id = req.context.as_ref().map(|c| c.job_id.clone()).unwrap_or_default();
        let gcode = req.gcode.ok_or_else(|| Status::invalid_argument("gcode is required"))?;
        let guard = self.running.start(&job_id);
        let (tx, rx) = mpsc::channel(8);
        let script = self.script.clone();
        let store = self.store.clone();
        tokio::spawn(async move {
            let token = guard.token().clone();
            let progress = pb::ExecuteProgramUpdate {
                update: Some(pb::execute_program_update::Update::Progress(Progress {
                    fraction: 0.5,
                    message: "cutting".into(),
                })),
            };
            let _ = tx.send(Ok(progress)).await;
            if let Some(status) = mid {
                let _ = tx.send(Err(status)).await;
                return;
            }
            let released = script.released.notified();
            let wait = async {
                if hold {
                    released.await;
                }
                tokio::time::sleep(delay).await;
            };
            tokio::select! {
                () = wait => {}
                () = token.cancelled() => {
                    let _ = tx.send(Err(Status::cancelled("scripted: stopped on request"))).await;
                    return;
                }
            }
            let program = match store.read_all(&gcode.sha256, 64 << 20).await {
                Ok(p) => p,
                Err(e) => {
                    let _ = tx.send(Err(Status::invalid_argument(e.to_string()))).await;
                    return;
                }
            };
            let lines = program.split(|b| *b == b'\n').filter(|l| !l.is_empty()).count();
            let mut csv = String::from("line,time_s\n");
            for i in 0..lines {
                csv.push_str(&format!("{},{:.1}\n", i + 1, i as f64 * 0.1));
            }
            let telemetry = match store.put_bytes("text/csv", csv.as_bytes()).await {
                Ok(a) => a,
                Err(e) => {
                    let _ = tx.send(Err(Status::internal(e.to_string()))).await;
                    return;
                }
            };
            let result = pb::ExecuteProgramResult {
                telemetry: Some(telemetry.into()),
                metrics: Some(pb::MachinedPartMetrics {
                    cycle_time_s: lines as f64 * 0.1,
                    ..Default::default()
                }),
                ..Default::default()
            };
            let update =
                pb::ExecuteProgramUpdate { update: Some(pb::execute_program_update::Update::Result(result)) };
            if tx.send(Ok(update)).await.is_ok() {
                script.lock().completed += 1;
            }
            drop(guard);
        });
        Ok(Response::new(tokio_stream::wrappers::ReceiverStream::new(rx)))
    }

    async fn cancel_stage(
        &self,
        request: Request<CancelStageRequest>,
    ) -> Result<Response<CancelStageResponse>, Status> {
        let found = self.running.cancel(&request.get_ref().job_id);
        if found {
            self.script.lock().cancels += 1;
        }
        Ok(Response::new(CancelStageResponse { found }))
    }

    async fn get_status(
        &self,
        _r: Request<pb::GetStatusRequest>,
    ) -> Result<Response<pb::MachineStatus>, Status> {
        Ok(Response::new(pb::MachineStatus { state: "idle".into(), ..Default::default() }))
    }

    async fn stop(&self, _r: Request<pb::StopRequest>) -> Result<Response<pb::MachineStatus>, Status> {
        Ok(Response::new(pb::MachineStatus { state: "stopped".into(), ..Default::default() }))
    }

    async fn reset(&self, _r: Request<pb::ResetRequest>) -> Result<Response<pb::MachineStatus>, Status> {
        Ok(Response::new(pb::MachineStatus { state: "idle".into(), ..Default::default() }))
    }
}
