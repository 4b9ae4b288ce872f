//! tonic adapter of the machine service: one simulated machine, one program at a time.
//!
//! `ExecuteProgram` reads the program from the artifact store (streaming, several passes), runs
//! [`execute`] on a blocking thread, streams progress and telemetry (at most 10 rows a second of
//! simulated time reach the stream; the CSV artifact has them all at 20 Hz), and stores the
//! final stock (16-bit PNG), the deviation map (8-bit PNG), the telemetry CSV and its SVG plot
//! and a JSON report. `Stop` ends the running program at the next line (feed hold and end, the
//! machine stays referenced); `Reset` is the emergency stop: it ends the program the same way and
//! latches `estop` until the next program starts. `GetStatus` reports state, job, line and the
//! tip position.

use std::io::{BufReader, Cursor};
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use depthmill_common::artifacts::{ArtifactError, ArtifactStore, ObjectArtifactStore};
use depthmill_common::stage::StageRegistry;
use depthmill_geometry::{CloudPoint, HeightMap, PngDepth};
use depthmill_proto::ErrorCode;
use depthmill_proto::machine::v1 as pb;
use depthmill_proto::types::v1 as pb_types;
use depthmill_proto::types::v1::{CancelStageRequest, CancelStageResponse, Diagnostic, Progress};
use tokio::sync::mpsc;
use tonic::{Request, Response, Status};

use crate::domain::dexel::DexelCells;
use crate::domain::job::{ExecuteError, ExecuteOptions, FaceTarget, Reference, execute_faces};
use crate::domain::part::{MAX_REFERENCE_POINTS, mesh_samples};
use crate::domain::sim::{PolicyKind, SimError, active_names};

pub(crate) const SERVICE_NAME: &str = "depthmill.machine.v1.MachineService";

/// Largest program accepted, bytes.
const MAX_PROGRAM_BYTES: u64 = 2 << 30;
/// Largest target map accepted, bytes.
const MAX_MAP_BYTES: u64 = 1 << 30;
/// Shortest wall time between two live telemetry messages of a run (20 a second).
const LIVE_TELEMETRY_PERIOD: std::time::Duration = std::time::Duration::from_millis(50);

#[derive(Debug, Default)]
struct Shared {
    state: Mutex<MachineState>,
    stop: AtomicBool,
    estop: AtomicBool,
    line: AtomicU64,
}

impl Shared {
    /// State after a run: `estop` while latched, `stopped` after a stop, else `idle`.
    fn settle(&self) {
        let state = if self.estop.load(Ordering::SeqCst) {
            "estop"
        } else if self.stop.load(Ordering::SeqCst) {
            "stopped"
        } else {
            "idle"
        };
        set_state(self, state, None);
    }
}

#[derive(Debug, Clone, Default)]
struct MachineState {
    state: &'static str,
    job_id: String,
    pos: [f64; 4],
}

struct MachineServiceImpl {
    running: StageRegistry,
    store: Arc<ObjectArtifactStore>,
    shared: Arc<Shared>,
    /// The machine itself: one program at a time, the others wait their turn in arrival order
    /// (tokio's mutex is fair).
    machine: Arc<tokio::sync::Mutex<()>>,
}

pub(crate) fn routes(store: ObjectArtifactStore) -> tonic::service::Routes {
    let shared = Arc::new(Shared::default());
    if let Ok(mut s) = shared.state.lock() {
        s.state = "idle";
    }
    tonic::service::Routes::new(pb::machine_service_server::MachineServiceServer::new(MachineServiceImpl {
        running: StageRegistry::default(),
        store: Arc::new(store),
        shared,
        machine: Arc::new(tokio::sync::Mutex::new(())),
    }))
}

fn exec_status(e: ExecuteError) -> Status {
    match &e {
        ExecuteError::Sim(SimError::Stopped { .. }) => ErrorCode::Cancelled.status(e.to_string()),
        ExecuteError::Io(_) => ErrorCode::Internal.status(e.to_string()),
        _ => ErrorCode::InvalidArgument.status(e.to_string()),
    }
}

fn artifact_status(e: ArtifactError) -> Status {
    depthmill_common::artifacts::grpc_status(e)
}

fn options(p: pb::ExecuteParams) -> Result<ExecuteOptions, Status> {
    let policy = match pb::AdaptiveMode::try_from(p.adaptive) {
        Ok(pb::AdaptiveMode::Unspecified | pb::AdaptiveMode::Aco) => PolicyKind::Aco,
        Ok(pb::AdaptiveMode::FeedOnly) => PolicyKind::FeedOnly,
        Ok(pb::AdaptiveMode::Off) => PolicyKind::Off,
        Err(_) => {
            return Err(
                ErrorCode::InvalidArgument.status(format!("execute.adaptive: unknown value {}", p.adaptive))
            );
        }
    };
    Ok(ExecuteOptions {
        machine: p.machine.unwrap_or_else(|| "emco-f1".into()),
        policy,
        material: p.material,
        stock_z_mm: p.stock_z_mm,
        cell_mm: p.cell_mm,
        clamp: p.clamp,
        compare: p.compare.unwrap_or(true),
        dexel: p.dexel.map(|d| DexelCells { x_mm: d.x_cell_mm, y_mm: d.y_cell_mm, z_mm: d.z_cell_mm }),
        ..Default::default()
    })
}

/// The problems of a job's execute section and, when its size is given, of the part against the
/// machine's travel; empty when the job can run here.
pub(crate) fn check_params(req: pb::ValidateExecuteRequest) -> Vec<pb_types::FieldViolation> {
    let violation = |field: &str, message: String| pb_types::FieldViolation { field: field.into(), message };
    let opts = match options(req.params.unwrap_or_default()) {
        Ok(o) => o,
        Err(status) => return vec![violation("execute", status.message().into())],
    };
    let mut out = Vec::new();
    if let Some(d) = opts.dexel {
        for (name, c) in [("x_cell_mm", d.x_mm), ("y_cell_mm", d.y_mm), ("z_cell_mm", d.z_mm)] {
            if let Some(c) = c
                && !(c.is_finite() && (0.001..=10.0).contains(&c))
            {
                out.push(violation(
                    &format!("execute.dexel.{name}"),
                    format!("{c} mm is outside [0.001, 10] mm"),
                ));
            }
        }
        if d.x_mm.is_none() && d.y_mm.is_none() && d.z_mm.is_none() {
            out.push(violation(
                "execute.dexel",
                "set at least one of x_cell_mm, y_cell_mm, z_cell_mm".into(),
            ));
        }
    }
    if let Some(m) = &opts.material
        && crate::domain::cutting::material(m).is_none()
    {
        let known: Vec<String> = crate::domain::cutting::materials().into_iter().map(|m| m.name).collect();
        out.push(violation(
            "execute.material",
            format!("unknown material \"{m}\"; expected one of {}", known.join(", ")),
        ));
    }
    match crate::domain::profile::MachineProfile::by_name_or_file(&opts.machine) {
        Err(e) => out.push(violation("execute.machine", e.to_string())),
        Ok(profile) => {
            if let Some(size) = req.part_size_mm {
                let size = [size.x, size.y, size.z];
                if size.iter().any(|v| !v.is_finite() || *v < 0.0) {
                    out.push(violation("input", format!("part size {size:?} mm is not a size")));
                } else if let Err(e) = profile.check_part_fits(size) {
                    out.push(violation("input", e));
                }
            }
        }
    }
    out
}

fn status_msg(shared: &Shared) -> pb::MachineStatus {
    let s = shared.state.lock().map(|s| s.clone()).unwrap_or_default();
    pb::MachineStatus {
        state: s.state.to_string(),
        job_id: s.job_id,
        line: shared.line.load(Ordering::Relaxed),
        x_mm: s.pos[0],
        y_mm: s.pos[1],
        z_mm: s.pos[2],
        a_deg: s.pos[3],
    }
}

fn set_state(shared: &Shared, state: &'static str, job_id: Option<&str>) {
    if let Ok(mut s) = shared.state.lock() {
        s.state = state;
        if let Some(j) = job_id {
            s.job_id = j.to_string();
        }
    }
}

type UpdateStream =
    Pin<Box<dyn tokio_stream::Stream<Item = Result<pb::ExecuteProgramUpdate, Status>> + Send>>;

fn update(u: pb::execute_program_update::Update) -> pb::ExecuteProgramUpdate {
    pb::ExecuteProgramUpdate { update: Some(u) }
}

impl MachineServiceImpl {
    /// The original part's points (see [`crate::domain::part`]): sampled on a mesh, or a cloud
    /// thinned to [`MAX_REFERENCE_POINTS`], scaled to millimetres.
    async fn read_reference(&self, sha: &str, units: i32) -> Result<Reference, Status> {
        use depthmill_geometry::formats::{Geometry, ReadLimits};
        let read = depthmill_common::artifacts::read_geometry(
            self.store.as_ref(),
            sha,
            units,
            "reference_units",
            "reference",
            &ReadLimits::default(),
        )
        .await?;
        tokio::task::spawn_blocking(move || match read.geometry {
            Geometry::Mesh(m) => {
                Reference { source: "mesh".into(), points: mesh_samples(&m, MAX_REFERENCE_POINTS) }
            }
            Geometry::Cloud(c) => {
                let stride = c.points.len().div_ceil(MAX_REFERENCE_POINTS).max(1);
                Reference {
                    source: "point cloud".into(),
                    points: c.points.iter().step_by(stride).map(CloudPoint::at).collect(),
                }
            }
        })
        .await
        .map_err(|e| Status::internal(format!("sampling the reference failed: {e}")))
    }
}

type RobotStream = Pin<Box<dyn tokio_stream::Stream<Item = Result<pb::ExecuteRobotUpdate, Status>> + Send>>;

#[tonic::async_trait]
impl pb::machine_service_server::MachineService for MachineServiceImpl {
    type ExecuteProgramStream = UpdateStream;
    type ExecuteRobotStream = RobotStream;

    #[tracing::instrument(skip_all, fields(job_id))]
    async fn execute_robot(
        &self,
        request: Request<pb::ExecuteRobotRequest>,
    ) -> Result<Response<Self::ExecuteRobotStream>, Status> {
        let req = request.into_inner();
        let job_id = req.context.as_ref().map(|c| c.job_id.clone()).unwrap_or_default();
        tracing::Span::current().record("job_id", job_id.as_str());
        let traj = req
            .trajectory
            .ok_or_else(|| ErrorCode::InvalidArgument.status("trajectory: an artifact is required"))?;
        let bytes = self
            .store
            .read_all(&traj.sha256, crate::grpc_robot::MAX_TRAJECTORY_BYTES)
            .await
            .map_err(artifact_status)?;
        let reference = match &req.reference {
            Some(r) => Some(self.read_reference(&r.sha256, req.reference_units).await?),
            None => None,
        };
        let guard = self.running.start(&job_id);
        let rx = crate::grpc_robot::execute(bytes, reference, req.cell_mm, self.store.clone(), guard)?;
        Ok(Response::new(Box::pin(tokio_stream::wrappers::ReceiverStream::new(rx))))
    }

    #[tracing::instrument(skip_all, fields(job_id))]
    async fn execute_program(
        &self,
        request: Request<pb::ExecuteProgramRequest>,
    ) -> Result<Response<Self::ExecuteProgramStream>, Status> {
        let req = request.into_inner();
        let job_id = req.context.as_ref().map(|c| c.job_id.clone()).unwrap_or_default();
        tracing::Span::current().record("job_id", job_id.as_str());
        let gcode =
            req.gcode.ok_or_else(|| ErrorCode::InvalidArgument.status("gcode: an artifact is required"))?;
        let mut opts = options(req.params.unwrap_or_default())?;
        let stat = self.store.stat(&gcode.sha256).await.map_err(artifact_status)?.ok_or_else(|| {
            ErrorCode::InvalidArgument.status(format!("gcode: no artifact {}", gcode.sha256))
        })?;
        if stat.size > MAX_PROGRAM_BYTES {
            return Err(ErrorCode::InvalidArgument
                .status(format!("gcode: {} bytes exceeds the limit of {MAX_PROGRAM_BYTES}", stat.size)));
        }
        let path = self.store.local_file(&gcode.sha256).await.map_err(artifact_status)?;
        // The target(s): one map, or one per face with the A angle from its face metadata (the
        // CAM service's rule for several faces).
        let mut targets: Vec<(f64, HeightMap)> = Vec::new();
        let several = req.face_maps.len() > 1;
        let refs: Vec<(String, pb_types::ArtifactRef)> = if req.face_maps.is_empty() {
            req.target_map.iter().map(|t| ("target_map".to_string(), t.clone())).collect()
        } else {
            req.face_maps.iter().enumerate().map(|(i, t)| (format!("face_maps[{i}]"), t.clone())).collect()
        };
        // Maps without depthmill metadata take their scale from the job, as in the CAM service.
        let fallback = req.pixel_mm.map(|p| depthmill_geometry::ImageMapping {
            pixel_mm: p,
            z_min_mm: req.z_min_mm,
            z_max_mm: req.z_max_mm,
        });
        for (field, t) in refs {
            let bytes = self.store.read_all(&t.sha256, MAX_MAP_BYTES).await.map_err(artifact_status)?;
            let f = field.clone();
            let media_type = t.media_type.clone();
            let map = tokio::task::spawn_blocking(move || match media_type.as_str() {
                "application/x-npy" => {
                    depthmill_geometry::read_npy_from(Cursor::new(bytes), None, fallback.as_ref())
                }
                _ => depthmill_geometry::read_png_from(Cursor::new(bytes), fallback.as_ref()),
            })
            .await
            .map_err(|e| Status::internal(format!("decoding failed: {e}")))?
            .map_err(|e| ErrorCode::InvalidArgument.status(format!("{f}: {e}")))?;
            use depthmill_geometry::Face;
            let a = match map.face() {
                Face::A { angle_deg } => angle_deg,
                _ if !several => 0.0,
                Face::PosZ => 0.0,
                Face::PosY => 90.0,
                Face::NegZ => 180.0,
                Face::NegY => -90.0,
                other => {
                    return Err(ErrorCode::InvalidArgument.status(format!(
                        "{field}: the view {other} cannot be reached by turning the part about the A axis"
                    )));
                }
            };
            targets.push((a, map));
        }
        // The original part, for a part cut on the one dexel stock (several faces or a turned one).
        if let Some(r) = &req.reference
            && (targets.len() > 1 || targets.iter().any(|(a, _)| a.abs() > 1e-9))
        {
            opts.reference = Some(Arc::new(self.read_reference(&r.sha256, req.reference_units).await?));
        }
        let guard = self.running.start(&job_id);
        let (tx, rx) = mpsc::channel(64);
        let store = self.store.clone();
        let shared = self.shared.clone();
        let machine = self.machine.clone();
        let span = tracing::Span::current();
        tokio::spawn(async move {
            let token = guard.token().clone();
            // One program at a time: a program sent while another runs waits for the machine
            // (cancellable), as a job queues at a real cell, instead of failing.
            let _machine = match machine.clone().try_lock_owned() {
                Ok(g) => g,
                Err(_) => {
                    let _ = tx.try_send(Ok(update(pb::execute_program_update::Update::Progress(Progress {
                        fraction: 0.0,
                        message: "waiting for the machine: another program is running".into(),
                    }))));
                    tokio::select! {
                        g = machine.lock_owned() => g,
                        () = token.cancelled() => {
                            let _ = tx.send(Err(ErrorCode::Cancelled.status("cancelled while waiting for the machine"))).await;
                            return;
                        }
                    }
                }
            };
            let claimed = match shared.state.lock() {
                Ok(mut st) => {
                    // A new program clears a latched emergency stop (reset, then cycle start).
                    shared.estop.store(false, Ordering::SeqCst);
                    shared.stop.store(false, Ordering::SeqCst);
                    st.state = "running";
                    st.job_id = job_id.clone();
                    true
                }
                Err(_) => false,
            };
            if !claimed {
                let _ = tx.send(Err(Status::internal("machine state lock poisoned"))).await;
                return;
            }
            shared.line.store(0, Ordering::Relaxed);
            let live_tx = tx.clone();
            let shared_run = shared.clone();
            let _ = tx.try_send(Ok(update(pb::execute_program_update::Update::Progress(Progress {
                fraction: 0.0,
                message: "running the program".into(),
            }))));
            let worked = tokio::task::spawn_blocking(move || {
                span.in_scope(|| {
                    let open = || -> std::io::Result<Box<dyn std::io::BufRead + Send>> {
                        Ok(Box::new(BufReader::with_capacity(1 << 16, std::fs::File::open(&path)?)))
                    };
                    let stop = || token.is_cancelled() || shared_run.stop.load(Ordering::Relaxed);
                    // Live telemetry: every 0.1 s of simulated time, at most every
                    // LIVE_TELEMETRY_PERIOD of wall time (a run simulated faster than real time
                    // would otherwise stream thousands of rows a second that no view can show).
                    let mut next_live = 0.0;
                    let mut last_live: Option<std::time::Instant> = None;
                    let mut observe = |r: &crate::domain::sim::TelemetryRow| {
                        shared_run.line.store(r.line, Ordering::Relaxed);
                        if let Ok(mut s) = shared_run.state.lock() {
                            s.pos = [r.x_mm, r.y_mm, r.z_mm, r.a_deg];
                        }
                        if r.time_s >= next_live
                            && last_live.is_none_or(|t| t.elapsed() >= LIVE_TELEMETRY_PERIOD)
                        {
                            next_live = r.time_s + 0.1;
                            last_live = Some(std::time::Instant::now());
                            let _ = live_tx.try_send(Ok(update(
                                pb::execute_program_update::Update::Telemetry(pb::Telemetry {
                                    time_s: r.time_s,
                                    line: r.line,
                                    feed_mm_min: r.feed_mm_min,
                                    spindle_rpm: r.spindle_rpm,
                                    torque_nm: r.torque_from_current_nm,
                                    current_a: r.current_a,
                                    power_w: r.power_w,
                                    x_mm: r.x_mm,
                                    y_mm: r.y_mm,
                                    z_mm: r.z_mm,
                                    active_limits: active_names(r.active),
                                }),
                            )));
                        }
                    };
                    let faces: Vec<FaceTarget<'_>> =
                        targets.iter().map(|(a, m)| FaceTarget { a_deg: *a, map: m }).collect();
                    let out =
                        execute_faces(&open, &opts, &faces, &stop, &mut observe).map_err(exec_status)?;
                    let stock_png = png(&out.final_stock, PngDepth::Bits16)?;
                    // Every face's stock and deviation when there are several.
                    let mut face_pngs = Vec::new();
                    if out.faces.len() > 1 {
                        for f in &out.faces {
                            let dev = match &f.deviation {
                                Some(d) => Some(png(&d.map, PngDepth::Bits8)?),
                                None => None,
                            };
                            face_pngs.push((png(&f.final_stock, PngDepth::Bits16)?, dev));
                        }
                    }
                    let dev_png = match &out.report.deviation {
                        Some(d) => Some(png(&d.map, PngDepth::Bits8)?),
                        None => None,
                    };
                    Ok::<_, Status>((out, stock_png, dev_png, face_pngs))
                })
            })
            .await;
            shared.settle();
            let (out, stock_png, dev_png, face_pngs) = match worked {
                Ok(Ok(v)) => v,
                Ok(Err(status)) => {
                    tracing::info!(error = %status.message(), "execution failed");
                    let status = if shared.estop.load(Ordering::SeqCst) {
                        ErrorCode::Cancelled.status(format!("emergency stop: {}", status.message()))
                    } else {
                        status
                    };
                    let _ = tx.send(Err(status)).await;
                    return;
                }
                Err(e) => {
                    let _ = tx.send(Err(Status::internal(format!("execution panicked: {e}")))).await;
                    return;
                }
            };
            let result = async {
                let final_stock = store.put_bytes("image/png", &stock_png).await?;
                let deviation_map = match dev_png {
                    Some(b) => Some(store.put_bytes("image/png", &b).await?.into()),
                    None => None,
                };
                let telemetry = store.put_bytes("text/csv", out.telemetry_csv.as_bytes()).await?;
                let plot = store.put_bytes("image/svg+xml", out.telemetry_svg.as_bytes()).await?;
                let report_json = serde_json::to_vec_pretty(&out.report).unwrap_or_default();
                let report = store.put_bytes("application/json", &report_json).await?;
                let mut faces = Vec::new();
                for (f, (stock_png, dev_png)) in out.faces.iter().zip(face_pngs) {
                    let final_stock = store.put_bytes("image/png", &stock_png).await?;
                    let deviation_map = match dev_png {
                        Some(b) => Some(store.put_bytes("image/png", &b).await?.into()),
                        None => None,
                    };
                    let d = f.deviation.as_ref();
                    faces.push(pb::FaceResult {
                        a_deg: f.a_deg,
                        final_stock: Some(final_stock.into()),
                        deviation_map,
                        max_gouge_mm: d.map_or(0.0, |d| d.max_gouge_mm),
                        max_leftover_mm: d.map_or(0.0, |d| d.max_leftover_mm),
                        rms_deviation_mm: d.map_or(0.0, |d| d.rms_deviation_mm),
                    });
                }
                let part_mesh = match &out.part_stl {
                    Some(b) => Some(store.put_bytes("model/stl", b).await?.into()),
                    None => None,
                };
                let part_view = match &out.part_view_ply {
                    Some(b) => Some(store.put_bytes("application/x-ply", b).await?.into()),
                    None => None,
                };
                let r = &out.report;
                let d = r.deviation.as_ref();
                let figures = |f: &crate::domain::part::Figures| pb::PartFigures {
                    points: f.points as u64,
                    max_gouge_mm: f.max_gouge_mm,
                    max_leftover_mm: f.max_leftover_mm,
                    mean_leftover_mm: f.mean_leftover_mm,
                    rms_deviation_mm: f.rms_deviation_mm,
                };
                Ok::<_, ArtifactError>(pb::ExecuteProgramResult {
                    part_mesh,
                    part_view,
                    faces,
                    final_stock: Some(final_stock.into()),
                    deviation_map,
                    telemetry: Some(telemetry.into()),
                    metrics: Some(pb::MachinedPartMetrics {
                        max_gouge_mm: d.map_or(0.0, |d| d.max_gouge_mm),
                        max_leftover_mm: d.map_or(0.0, |d| d.max_leftover_mm),
                        mean_leftover_mm: d.map_or(0.0, |d| d.mean_leftover_mm),
                        rms_deviation_mm: d.map_or(0.0, |d| d.rms_deviation_mm),
                        cycle_time_s: r.cycle_time_s,
                        cycle_time_no_adaptive_s: r.cycle_time_no_adaptive_s,
                        cycle_time_other_s: r.cycle_time_other_s,
                        removed_mm3: r.run.removed_mm3,
                        against_part: r.part.as_ref().map(|p| figures(&p.against_part)),
                        against_opened: r.part.as_ref().and_then(|p| p.against_opened.as_ref()).map(figures),
                    }),
                    diagnostics: r
                        .run
                        .warnings
                        .iter()
                        .take(100)
                        .map(|w| Diagnostic { code: "machine".into(), message: w.clone() })
                        .collect(),
                    telemetry_plot: Some(plot.into()),
                    machine_report: Some(report.into()),
                })
            }
            .await;
            let msg = match result {
                Ok(r) => Ok(update(pb::execute_program_update::Update::Result(r))),
                Err(e) => Err(artifact_status(e)),
            };
            let _ = tx.send(msg).await;
            drop(guard);
        });
        Ok(Response::new(Box::pin(tokio_stream::wrappers::ReceiverStream::new(rx))))
    }

    async fn cancel_stage(
        &self,
        request: Request<CancelStageRequest>,
    ) -> Result<Response<CancelStageResponse>, Status> {
        let found = self.running.cancel(&request.get_ref().job_id);
        Ok(Response::new(CancelStageResponse { found }))
    }

    async fn validate_params(
        &self,
        request: Request<pb::ValidateExecuteRequest>,
    ) -> Result<Response<pb_types::ValidateParamsResponse>, Status> {
        Ok(Response::new(pb_types::ValidateParamsResponse { violations: check_params(request.into_inner()) }))
    }

    async fn list_machines(
        &self,
        _request: Request<pb::ListMachinesRequest>,
    ) -> Result<Response<pb::ListMachinesResponse>, Status> {
        use crate::domain::profile::{AxisRange, BUILTIN_PROFILES, MachineProfile};
        let travel = |r: &AxisRange| pb::AxisTravel { min: r.min_mm, max: r.max_mm };
        let mut machines = Vec::new();
        for name in BUILTIN_PROFILES {
            let p = MachineProfile::builtin(name)
                .map_err(|e| ErrorCode::Internal.status(format!("shipped profile {name}: {e}")))?;
            machines.push(pb::MachineProfileInfo {
                name: p.name.clone(),
                description: p.description.clone(),
                x: Some(travel(&p.axes.x)),
                y: Some(travel(&p.axes.y)),
                z: Some(travel(&p.axes.z)),
                a: Some(travel(&p.axes.a)),
                c: p.axes.c.as_ref().map(travel),
                feed_min_mm_min: p.motion.feed_min_mm_min,
                feed_max_mm_min: p.motion.feed_max_mm_min,
                rapid_mm_min: p.motion.rapid_mm_min,
                rpm_min: p.spindle.rpm_min,
                rpm_max: p.spindle.rpm_max,
                spindle_power_w: p.spindle.power_w,
            });
        }
        let materials = crate::domain::cutting::materials().into_iter().map(|m| m.name).collect();
        Ok(Response::new(pb::ListMachinesResponse { machines, materials }))
    }

    async fn get_status(
        &self,
        _request: Request<pb::GetStatusRequest>,
    ) -> Result<Response<pb::MachineStatus>, Status> {
        Ok(Response::new(status_msg(&self.shared)))
    }

    async fn stop(&self, _request: Request<pb::StopRequest>) -> Result<Response<pb::MachineStatus>, Status> {
        self.shared.stop.store(true, Ordering::SeqCst);
        Ok(Response::new(status_msg(&self.shared)))
    }

    async fn reset(
        &self,
        _request: Request<pb::ResetRequest>,
    ) -> Result<Response<pb::MachineStatus>, Status> {
        self.shared.estop.store(true, Ordering::SeqCst);
        self.shared.stop.store(true, Ordering::SeqCst);
        set_state(&self.shared, "estop", None);
        Ok(Response::new(status_msg(&self.shared)))
    }
}

fn png(map: &depthmill_geometry::HeightMap, depth: PngDepth) -> Result<Vec<u8>, Status> {
    let mut out = Vec::new();
    depthmill_geometry::write_png_to(map, &mut out, depth)
        .map_err(|e| ErrorCode::Internal.status(format!("encoding a map failed: {e}")))?;
    Ok(out)
}
