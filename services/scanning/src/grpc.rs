//! tonic adapter of the scanning service: `ScanPart` (mesh artifact -> registered PLY cloud and a
//! JSON report, progress streamed), `PlanScan`, `CancelStage`; the device services are in
//! [`crate::grpc_devices`].

use std::pin::Pin;
use std::sync::Arc;

use depthmill_common::artifacts::{ArtifactStore, ObjectArtifactStore};
use depthmill_common::stage::StageRegistry;
use depthmill_geometry::Mesh;
use depthmill_geometry::UnitsDecision;
use depthmill_geometry::cloud::{FREE_KIND, FREE_KIND_SHADOWED, FREE_KIND_TABLE};
use depthmill_geometry::formats::{Geometry, PlyEncoding, ReadLimits, write_ply, write_ply_labelled};
use depthmill_proto::ErrorCode;
use depthmill_proto::scanning::v1 as pb;
use depthmill_proto::types::v1::{
    CancelStageRequest, CancelStageResponse, Diagnostic, FieldViolation, Progress, ValidateParamsResponse,
};
use tokio::sync::mpsc;
use tonic::{Request, Response, Status};

use crate::devices::table::TableClient;
use crate::domain::calibration::{Calibration, CalibrationError, CalibrationOptions, Offset, TableModel};
use crate::domain::scan::obstacles::Obstacle;
use crate::domain::scan::{CellLayout, PassSpec, ScanError, ScanMode, ScanOptions, ScanSession};

pub(crate) const SERVICE_NAME: &str = "depthmill.scanning.v1.ScanningService";

/// What the scanning service needs to run scans.
pub(crate) struct Cell {
    pub store: Arc<ObjectArtifactStore>,
    pub limits: ReadLimits,
    /// Where the rotary table's controller listens.
    pub table_addr: String,
    pub layout: CellLayout,
    /// How far the simulated cell truly is from its drawing.
    pub errors: crate::domain::calibration::CellErrors,
    /// One scan at a time: the cell is one set of devices.
    pub busy: tokio::sync::Mutex<()>,
}

impl Cell {
    /// Waits for the cell (one scan or calibration at a time) unless `token` is cancelled first,
    /// then connects to the rotary table's controller: the lock held for the run and the driver.
    async fn claim(
        &self,
        token: &tokio_util::sync::CancellationToken,
    ) -> Result<(tokio::sync::MutexGuard<'_, ()>, TableClient<tokio::net::TcpStream>), Status> {
        let lock = tokio::select! {
            g = self.busy.lock() => g,
            () = token.cancelled() => return Err(Status::from(ScanError::Cancelled)),
        };
        let table = TableClient::connect(self.table_addr.as_str())
            .await
            .map_err(|e| Status::from(ScanError::Table(format!("connecting to {}: {e}", self.table_addr))))?;
        Ok((lock, table))
    }
}

struct ScanningServiceImpl {
    running: StageRegistry,
    cell: Arc<Cell>,
}

pub(crate) fn routes(cell: Arc<Cell>) -> tonic::service::Routes {
    tonic::service::Routes::new(pb::scanning_service_server::ScanningServiceServer::new(
        ScanningServiceImpl { running: StageRegistry::default(), cell },
    ))
}

impl From<ScanError> for Status {
    fn from(e: ScanError) -> Self {
        let code = match &e {
            ScanError::Cancelled => ErrorCode::Cancelled,
            ScanError::Table(_) => ErrorCode::Unavailable,
            ScanError::Robot(_)
            | ScanError::Latch(_)
            | ScanError::Coverage(_)
            | ScanError::Calibration(_)
            | ScanError::NotInScan(_) => ErrorCode::Internal,
            _ => ErrorCode::InvalidArgument,
        };
        code.status(e.to_string())
    }
}

/// Wire parameters -> the job's `scan` options (defaults for unset fields), checked.
pub(crate) fn options(p: pb::ScanParams) -> Result<ScanOptions, Status> {
    let d = ScanOptions::default();
    let mode = match pb::ScanMode::try_from(p.mode) {
        Ok(pb::ScanMode::Unspecified) => d.mode,
        Ok(pb::ScanMode::Dynamic) => ScanMode::Dynamic,
        Ok(pb::ScanMode::StopAndMove) => ScanMode::StopAndMove,
        Err(_) => {
            return Err(ErrorCode::InvalidArgument.status(format!("scan.mode: unknown value {}", p.mode)));
        }
    };
    let passes = if p.passes.is_empty() {
        None
    } else {
        let v = |x: Option<depthmill_proto::types::v1::Vec3>, i: usize, name: &str| {
            x.map(|v| [v.x, v.y, v.z]).ok_or_else(|| {
                ErrorCode::InvalidArgument.status(format!("scan.passes[{i}].{name}: required"))
            })
        };
        Some(
            p.passes
                .into_iter()
                .enumerate()
                .map(|(i, s)| {
                    Ok(PassSpec {
                        table_deg: s.table_deg,
                        start_mm: v(s.start_mm, i, "start_mm")?,
                        end_mm: v(s.end_mm, i, "end_mm")?,
                    })
                })
                .collect::<Result<Vec<_>, Status>>()?,
        )
    };
    let obstacles = p
        .obstacles
        .into_iter()
        .enumerate()
        .map(|(i, o)| {
            obstacle_from_wire(o)
                .map_err(|m| ErrorCode::InvalidArgument.status(format!("scan.obstacles[{i}]: {m}")))
        })
        .collect::<Result<Vec<_>, Status>>()?;
    Ok(ScanOptions {
        mode,
        obstacles,
        obstacle_clearance_mm: p.obstacle_clearance_mm.unwrap_or(d.obstacle_clearance_mm),
        table_angles_deg: if p.table_angles_deg.is_empty() { d.table_angles_deg } else { p.table_angles_deg },
        standoff_mm: p.standoff_mm.unwrap_or(d.standoff_mm),
        line_rate_hz: p.line_rate_hz.unwrap_or(d.line_rate_hz),
        adaptive_rescan: p.adaptive_rescan.unwrap_or(d.adaptive_rescan),
        line_spacing_mm: p.line_spacing_mm.unwrap_or(d.line_spacing_mm),
        overlap: p.overlap.unwrap_or(d.overlap),
        margin_mm: p.margin_mm.unwrap_or(d.margin_mm),
        tilt_deg: p.tilt_deg.unwrap_or(d.tilt_deg),
        stop_and_move_rate_hz: p.stop_and_move_rate_hz.unwrap_or(d.stop_and_move_rate_hz),
        latch_latency_s: p.latch_latency_s.unwrap_or(d.latch_latency_s),
        latch_jitter_s: p.latch_jitter_s.unwrap_or(d.latch_jitter_s),
        compensate_latency: p.compensate_latency.unwrap_or(d.compensate_latency),
        rescan_pixel_mm: p.rescan_pixel_mm.unwrap_or(d.rescan_pixel_mm),
        rescan_standoff_mm: p.rescan_standoff_mm.or(d.rescan_standoff_mm),
        seed: p.seed.unwrap_or(d.seed),
        max_frames: p.max_frames.unwrap_or(d.max_frames),
        table_search_deg: p.table_search_deg.unwrap_or(d.table_search_deg),
        passes,
        ..d
    })
}

/// The first problem ScanPart would find in the job's `scan` section before scanning, named by
/// its field in the job JSON (`scan` when the value has no field of its own).
pub(crate) fn check_params(p: pb::ScanParams) -> Option<FieldViolation> {
    let opts = match options(p) {
        Ok(o) => o,
        Err(status) => {
            return Some(FieldViolation { field: "scan".into(), message: status.message().into() });
        }
    };
    let spec = crate::domain::scanner::ScannerSpec { line_rate_hz: opts.line_rate_hz, ..Default::default() };
    match opts.validate(&spec) {
        Ok(()) => None,
        Err(ScanError::InvalidOption { field, value, reason }) => Some(FieldViolation {
            field,
            message: if value.is_empty() { reason } else { format!("{reason} (got {value})") },
        }),
        Err(other) => Some(FieldViolation { field: "scan".into(), message: other.to_string() }),
    }
}

/// A wire obstacle as the library's.
pub(crate) fn obstacle_from_wire(o: pb::ScanObstacle) -> Result<Obstacle, &'static str> {
    let v = |x: Option<depthmill_proto::types::v1::Vec3>| {
        x.map(|v| [v.x, v.y, v.z]).ok_or("a corner or centre is missing")
    };
    Ok(match o.shape.ok_or("give one of box, cylinder and sphere")? {
        pb::scan_obstacle::Shape::Box(b) => {
            Obstacle::Box { name: o.name, min_mm: v(b.min_mm)?, max_mm: v(b.max_mm)? }
        }
        pb::scan_obstacle::Shape::Cylinder(c) => Obstacle::Cylinder {
            name: o.name,
            center_mm: [c.center_x_mm, c.center_y_mm],
            radius_mm: c.radius_mm,
            z_min_mm: c.z_min_mm,
            z_max_mm: c.z_max_mm,
        },
        pb::scan_obstacle::Shape::Sphere(s) => {
            Obstacle::Sphere { name: o.name, center_mm: v(s.center_mm)?, radius_mm: s.radius_mm }
        }
    })
}

fn vec3(v: Option<depthmill_proto::types::v1::Vec3>) -> [f64; 3] {
    v.map_or([0.0; 3], |v| [v.x, v.y, v.z])
}

fn wire_vec3(v: [f64; 3]) -> Option<depthmill_proto::types::v1::Vec3> {
    Some(depthmill_proto::types::v1::Vec3 { x: v[0], y: v[1], z: v[2] })
}

/// A wire calibration as the library's, checked against the cell (InvalidArgument naming the field).
pub(crate) fn calibration_from_wire(
    c: pb::CellCalibration,
    layout: &CellLayout,
) -> Result<(Calibration, String, u32, String), Status> {
    let t = c.table.ok_or_else(|| ErrorCode::InvalidArgument.status("calibration.table: required"))?;
    let m = c.scanner_mount.unwrap_or_default();
    let cal = Calibration {
        table: TableModel {
            axis_x_mm: t.axis_x_mm,
            axis_y_mm: t.axis_y_mm,
            top_z_mm: t.top_z_mm,
            axis_tilt_x_deg: t.axis_tilt_x_deg,
            axis_tilt_y_deg: t.axis_tilt_y_deg,
            zero_deg: t.zero_deg,
            top_tilt_x_deg: t.top_tilt_x_deg,
            top_tilt_y_deg: t.top_tilt_y_deg,
        },
        scanner_mount: Offset { translation_mm: vec3(m.translation_mm), rotation_deg: vec3(m.rotation_deg) },
    };
    cal.validate(layout).map_err(|e| ErrorCode::InvalidArgument.status(e.to_string()))?;
    Ok((cal, c.id, c.version, c.report_json))
}

/// The library's calibration on the wire.
pub(crate) fn calibration_to_wire(c: &Calibration, id: String, version: u32) -> pb::CellCalibration {
    let t = &c.table;
    pb::CellCalibration {
        id,
        version,
        table: Some(pb::TableModel {
            axis_x_mm: t.axis_x_mm,
            axis_y_mm: t.axis_y_mm,
            top_z_mm: t.top_z_mm,
            axis_tilt_x_deg: t.axis_tilt_x_deg,
            axis_tilt_y_deg: t.axis_tilt_y_deg,
            zero_deg: t.zero_deg,
            top_tilt_x_deg: t.top_tilt_x_deg,
            top_tilt_y_deg: t.top_tilt_y_deg,
        }),
        scanner_mount: Some(pb::RigidOffset {
            translation_mm: wire_vec3(c.scanner_mount.translation_mm),
            rotation_deg: wire_vec3(c.scanner_mount.rotation_deg),
        }),
        report_json: String::new(),
    }
}

/// Wire calibration options -> the library's (defaults for unset fields), checked.
pub(crate) fn calibration_options(
    p: pb::CalibrationParams,
    layout: &CellLayout,
) -> Result<CalibrationOptions, Status> {
    let d = CalibrationOptions::default();
    let o = CalibrationOptions {
        table_angles_deg: if p.table_angles_deg.is_empty() { d.table_angles_deg } else { p.table_angles_deg },
        sphere_radius_mm: p.sphere_radius_mm.unwrap_or(d.sphere_radius_mm),
        sphere_at_mm: p.sphere_at_mm.map_or(d.sphere_at_mm, |v| [v.x, v.y, v.z]),
        line_spacing_mm: p.line_spacing_mm.unwrap_or(d.line_spacing_mm),
        seed: p.seed.unwrap_or(d.seed),
    };
    o.validate(layout).map_err(|e| ErrorCode::InvalidArgument.status(e.to_string()))?;
    Ok(o)
}

/// Reads the mesh artifact and scales it to millimetres (`units`, wire value of the request).
async fn read_mesh(cell: &Cell, sha: &str, units: i32) -> Result<(Mesh, Option<UnitsDecision>), Status> {
    let read = depthmill_common::artifacts::read_geometry(
        cell.store.as_ref(),
        sha,
        units,
        "input.units",
        "mesh",
        &cell.limits,
    )
    .await?;
    match read.geometry {
        Geometry::Mesh(m) => Ok((m, read.units)),
        Geometry::Cloud(_) => Err(ErrorCode::InvalidArgument.status(format!(
            "{}: is a point cloud; the simulated scan needs a mesh (STL, OBJ, OFF, or PLY with faces)",
            read.name
        ))),
    }
}

type CalibrateStream =
    Pin<Box<dyn tokio_stream::Stream<Item = Result<pb::CalibrateCellUpdate, Status>> + Send>>;

fn calibration_status(e: CalibrationError) -> Status {
    let code = match &e {
        CalibrationError::Invalid { .. } | CalibrationError::Degenerate(_) => ErrorCode::InvalidArgument,
        CalibrationError::NoFit(_) => ErrorCode::InvalidArgument,
        CalibrationError::Cancelled => ErrorCode::Cancelled,
        CalibrationError::Table(_) => ErrorCode::Unavailable,
        CalibrationError::Scan(_) => ErrorCode::Internal,
    };
    code.status(e.to_string())
}

type UpdateStream = Pin<Box<dyn tokio_stream::Stream<Item = Result<pb::ScanPartUpdate, Status>> + Send>>;

fn progress_update(fraction: f64, message: String) -> pb::ScanPartUpdate {
    pb::ScanPartUpdate {
        update: Some(pb::scan_part_update::Update::Progress(Progress { fraction, message })),
    }
}

/// Encodes the cloud as the PLY reconstruction reads (binary, intensity, pass id).
pub fn encode_cloud(out: &crate::domain::scan::ScanOutput) -> Result<Vec<u8>, ScanError> {
    let mut bytes = Vec::with_capacity(out.cloud.points.len() * 18 + 1024);
    let comments = vec![
        format!("scan mode {:?}", out.report.mode).to_lowercase(),
        format!(
            "frames {} passes {}",
            out.report.frames,
            out.report.stations.iter().map(|s| s.passes.len()).sum::<usize>()
        ),
        "frame part (the mesh's coordinates, scaled to millimetres)".to_string(),
        "units mm".to_string(),
    ];
    write_ply(&mut bytes, &out.cloud, Some(&out.pass), PlyEncoding::BinaryLittleEndian, &comments)
        .map_err(|e| ScanError::Mesh(format!("writing the cloud failed: {e}")))?;
    Ok(bytes)
}

#[tonic::async_trait]
impl pb::scanning_service_server::ScanningService for ScanningServiceImpl {
    type ScanPartStream = UpdateStream;

    #[tracing::instrument(skip_all, fields(job_id))]
    async fn scan_part(
        &self,
        request: Request<pb::ScanPartRequest>,
    ) -> Result<Response<Self::ScanPartStream>, Status> {
        let req = request.into_inner();
        let job_id = req.context.as_ref().map(|c| c.job_id.clone()).unwrap_or_default();
        tracing::Span::current().record("job_id", job_id.as_str());
        let mesh_ref =
            req.mesh.ok_or_else(|| ErrorCode::InvalidArgument.status("mesh: an artifact is required"))?;
        let opts = options(req.params.unwrap_or_default())?;
        opts.validate(&crate::domain::scanner::ScannerSpec {
            line_rate_hz: opts.line_rate_hz,
            ..Default::default()
        })?;
        let calibration = req.calibration.map(|c| calibration_from_wire(c, &self.cell.layout)).transpose()?;
        let calibrate = req.calibrate.map(|p| calibration_options(p, &self.cell.layout)).transpose()?;
        let (mesh, units) = read_mesh(&self.cell, &mesh_ref.sha256, req.units).await?;
        let guard = self.running.start(&job_id);
        let (tx, rx) = mpsc::channel(64);
        let cell = self.cell.clone();
        tokio::spawn(async move {
            let token = guard.token().clone();
            let ptx = tx.clone();
            let progress: crate::session::Progress = Arc::new(move |f, m| {
                let _ = ptx.try_send(Ok(progress_update(f.clamp(0.0, 1.0) * 0.95, m)));
            });
            progress(0.0, "waiting for the cell".into());
            let result: Result<_, Status> = async {
                let (_cell_lock, mut table) = cell.claim(&token).await?;
                let (cal, cal_id, cal_version, cal_report) = match calibration {
                    Some((c, id, v, report)) => (Some(c), id, v, report),
                    None => (None, String::new(), 0, String::new()),
                };
                let sim = crate::domain::calibration::Cell::new(&cell.layout, &cell.errors, cal);
                let (mut out, made) = crate::session::run_scan(
                    mesh,
                    opts,
                    cell.layout,
                    sim,
                    calibrate,
                    &mut table,
                    progress.clone(),
                    token.clone(),
                )
                .await?;
                out.report.units = units;
                if let Some(m) = &made {
                    // The calibration made for this scan and its figures, for the job report.
                    out.report.calibration = Some(serde_json::json!({
                        "made_for_this_scan": true,
                        "during_scan": m.during_scan(),
                        "why_not_during_scan": m.why_not,
                        "calibration": m.calibration,
                        "sphere_rms_mm": m.report.sphere_rms_mm,
                        "table_fit_rms_mm": m.report.table_fit_rms_mm,
                        "registration_before": m.report.registration_before,
                        "registration_after": m.report.registration_after,
                        "truth": m.report.truth,
                        "scan_time_s": m.report.scan_time_s,
                    }));
                } else if let Some(c) = &cal {
                    // The calibration in force and its own report's figures, for the job report.
                    let report: serde_json::Value = serde_json::from_str(&cal_report).unwrap_or(serde_json::Value::Null);
                    out.report.calibration = Some(serde_json::json!({
                        "id": cal_id,
                        "version": cal_version,
                        "calibration": c,
                        "sphere_rms_mm": report["sphere_rms_mm"],
                        "table_fit_rms_mm": report["table_fit_rms_mm"],
                        "registration_before": report["registration_before"],
                        "registration_after": report["registration_after"],
                        "truth": report["truth"],
                        "scan_time_s": report["scan_time_s"],
                    }));
                }
                progress(0.97, format!("writing {} points", out.cloud.points.len()));
                let (out, ply) = tokio::task::spawn_blocking(move || {
                    let ply = encode_cloud(&out);
                    (out, ply)
                })
                .await
                .map_err(|e| Status::internal(format!("encoding the cloud failed: {e}")))?;
                let ply = ply?;
                let cloud_ref = cell
                    .store
                    .put_bytes("application/x-ply", &ply)
                    .await
                    .map_err(depthmill_common::artifacts::grpc_status)?;
                let free_space = if out.free_space.is_empty() && out.shadowed.is_empty() {
                    None
                } else {
                    let n = out.free_space.len() + out.shadowed.len();
                    let mut bytes = Vec::with_capacity(n * 14 + 256);
                    let cloud = depthmill_geometry::PointCloud::from_points(
                        out.free_space.iter().chain(&out.shadowed).copied(),
                    );
                    let kind: Vec<u16> = std::iter::repeat_n(FREE_KIND_TABLE, out.free_space.len())
                        .chain(std::iter::repeat_n(FREE_KIND_SHADOWED, out.shadowed.len()))
                        .collect();
                    write_ply_labelled(
                        &mut bytes,
                        &cloud,
                        Some((FREE_KIND, &kind)),
                        PlyEncoding::BinaryLittleEndian,
                        &[
                            "free space: the table seen past the part (kind 0), and points of the cloud the scanner did not show clear above (kind 1)".to_string(),
                            "units mm".to_string(),
                        ],
                    )
                    .map_err(|e| Status::internal(format!("writing the free-space cloud failed: {e}")))?;
                    Some(
                        cell.store
                            .put_bytes("application/x-ply", &bytes)
                            .await
                            .map_err(depthmill_common::artifacts::grpc_status)?
                            .into(),
                    )
                };
                let report_json = serde_json::to_vec_pretty(&out.report)
                    .map_err(|e| Status::internal(format!("encoding the report failed: {e}")))?;
                let report_ref = cell
                    .store
                    .put_bytes("application/json", &report_json)
                    .await
                    .map_err(depthmill_common::artifacts::grpc_status)?;
                let r = &out.report;
                let coverage = r.coverage_after_rescan.or(r.coverage_before_rescan).map_or(0.0, |c| c.covered_pct);
                // The silhouette's line says where the part went unseen: a code of its own.
                let unseen = r.silhouette.as_ref().and_then(|s| s.diagnostic());
                let mut diagnostics: Vec<Diagnostic> = r
                    .diagnostics
                    .iter()
                    .map(|m| Diagnostic {
                        code: if unseen.as_ref() == Some(m) { "silhouette_unseen" } else { "scan" }.into(),
                        message: m.clone(),
                    })
                    .collect();
                if let Some(u) = &r.units {
                    diagnostics.push(Diagnostic {
                        code: "units".into(),
                        message: format!("mesh read in {} ({}: {})", u.unit, u.source, u.reason),
                    });
                    if let Some(w) = &u.warning {
                        diagnostics.push(Diagnostic { code: "units_warning".into(), message: w.clone() });
                    }
                }
                diagnostics.push(Diagnostic {
                    code: "dropped_rays".into(),
                    message: format!(
                        "rays without a point: {} out of the window, {} beyond the incidence limit, {} occluded, {} missing the part",
                        r.dropped.out_of_window, r.dropped.incidence, r.dropped.occluded, r.dropped.miss
                    ),
                });
                if let Some(m) = &made {
                    let merge = |c: Option<crate::domain::calibration::RegistrationCheck>| {
                        c.map_or("-".to_string(), |c| format!("{:.4}", c.merge_rms_mm))
                    };
                    diagnostics.push(Diagnostic {
                        code: "cell_calibrated".into(),
                        message: format!(
                            "the cell was calibrated {}: merge error of the sphere's scans {} mm with the calibration before, {} mm after",
                            match &m.why_not {
                                None => "at this scan's stations (the table turned once for both)".to_string(),
                                Some(why) => format!("by the routine before the scan ({why})"),
                            },
                            merge(m.report.registration_before),
                            merge(m.report.registration_after)
                        ),
                    });
                }
                let (new_calibration, new_calibration_report_json) = match &made {
                    Some(m) => (
                        Some(calibration_to_wire(&m.calibration, String::new(), 0)),
                        serde_json::to_string_pretty(&m.report)
                            .map_err(|e| Status::internal(format!("encoding the calibration report failed: {e}")))?,
                    ),
                    None => (None, String::new()),
                };
                tracing::info!(points = r.points, frames = r.frames, scan_time_s = r.scan_time_s, "scan done");
                Ok(pb::ScanPartResult {
                    point_cloud: Some(cloud_ref.into()),
                    points: r.points,
                    frames: r.frames,
                    scan_time_s: r.scan_time_s,
                    diagnostics,
                    report: Some(report_ref.into()),
                    coverage_pct: coverage,
                    registration_rms_mm: r.registration_rms_mm,
                    silhouette_coverage_pct: r.silhouette.as_ref().map(|s| s.covered_pct),
                    free_space,
                    registration_merge_rms_mm: r.registration_merge_rms_mm,
                    calibration_id: cal_id,
                    calibration_version: cal_version,
                    calibrated_during_scan: made.as_ref().is_some_and(|m| m.during_scan()),
                    new_calibration,
                    new_calibration_report_json,
                })
            }
            .await;
            let msg =
                result.map(|r| pb::ScanPartUpdate { update: Some(pb::scan_part_update::Update::Result(r)) });
            if let Err(s) = &msg {
                tracing::info!(error = %s.message(), "scan failed");
            }
            let _ = tx.send(msg).await;
            drop(guard);
        });
        Ok(Response::new(Box::pin(tokio_stream::wrappers::ReceiverStream::new(rx))))
    }

    async fn plan_scan(
        &self,
        request: Request<pb::ScanPartRequest>,
    ) -> Result<Response<pb::ScanPlanResponse>, Status> {
        let req = request.into_inner();
        let mesh_ref =
            req.mesh.ok_or_else(|| ErrorCode::InvalidArgument.status("mesh: an artifact is required"))?;
        let opts = options(req.params.unwrap_or_default())?;
        let calibration = req.calibration.map(|c| calibration_from_wire(c, &self.cell.layout)).transpose()?;
        let (mesh, _) = read_mesh(&self.cell, &mesh_ref.sha256, req.units).await?;
        let layout = self.cell.layout;
        let sim = crate::domain::calibration::Cell::new(&layout, &self.cell.errors, calibration.map(|c| c.0));
        let (plan, frames) = tokio::task::spawn_blocking(move || {
            let mut s = ScanSession::with_cell(&mesh, opts, layout, sim)?;
            let plan = s.plan()?;
            let frames = plan.estimated_frames(s.options());
            Ok::<_, ScanError>((plan, frames))
        })
        .await
        .map_err(|e| Status::internal(format!("planning failed: {e}")))??;
        Ok(Response::new(pb::ScanPlanResponse {
            stations: plan.stations.len() as u32,
            passes: plan.passes() as u32,
            length_mm: plan.length_mm(),
            estimated_frames: frames,
            plan_json: serde_json::to_string(&plan).unwrap_or_default(),
        }))
    }

    type CalibrateCellStream = CalibrateStream;

    #[tracing::instrument(skip_all, fields(job_id))]
    async fn calibrate_cell(
        &self,
        request: Request<pb::CalibrateCellRequest>,
    ) -> Result<Response<Self::CalibrateCellStream>, Status> {
        let req = request.into_inner();
        let job_id = req.context.as_ref().map(|c| c.job_id.clone()).unwrap_or_default();
        tracing::Span::current().record("job_id", job_id.as_str());
        let layout = self.cell.layout;
        let opts = calibration_options(req.params.unwrap_or_default(), &layout)?;
        let current = req.current.map(|c| calibration_from_wire(c, &layout)).transpose()?.map(|c| c.0);
        let guard = self.running.start(&job_id);
        let (tx, rx) = mpsc::channel(64);
        let cell = self.cell.clone();
        tokio::spawn(async move {
            let token = guard.token().clone();
            let ptx = tx.clone();
            let progress: crate::session::Progress = Arc::new(move |fraction, message| {
                let p = Progress { fraction: fraction.clamp(0.0, 1.0), message };
                let _ = ptx.try_send(Ok(pb::CalibrateCellUpdate {
                    update: Some(pb::calibrate_cell_update::Update::Progress(p)),
                }));
            });
            progress(0.0, "waiting for the cell".into());
            let result: Result<_, Status> = async {
                let (_cell_lock, mut table) = cell.claim(&token).await?;
                let sim = crate::domain::calibration::Cell::new(&cell.layout, &cell.errors, current);
                let (cal, report) = crate::session::run_calibration(
                    sim,
                    cell.layout,
                    opts,
                    &mut table,
                    progress,
                    token.clone(),
                )
                .await
                .map_err(calibration_status)?;
                let report_json = serde_json::to_string_pretty(&report)
                    .map_err(|e| Status::internal(format!("encoding the calibration report failed: {e}")))?;
                tracing::info!(
                    merge_before_mm = report.registration_before.map_or(0.0, |r| r.merge_rms_mm),
                    merge_after_mm = report.registration_after.map_or(0.0, |r| r.merge_rms_mm),
                    "cell calibrated"
                );
                Ok(pb::CalibrateCellResult {
                    calibration: Some(calibration_to_wire(&cal, String::new(), 0)),
                    report_json,
                    merge_rms_before_mm: report.registration_before.map_or(0.0, |r| r.merge_rms_mm),
                    merge_rms_after_mm: report.registration_after.map_or(0.0, |r| r.merge_rms_mm),
                })
            }
            .await;
            if let Err(s) = &result {
                tracing::info!(error = %s.message(), "calibration failed");
            }
            let msg = result.map(|r| pb::CalibrateCellUpdate {
                update: Some(pb::calibrate_cell_update::Update::Result(r)),
            });
            let _ = tx.send(msg).await;
            drop(guard);
        });
        Ok(Response::new(Box::pin(tokio_stream::wrappers::ReceiverStream::new(rx))))
    }

    async fn validate_params(
        &self,
        request: Request<pb::ScanParams>,
    ) -> Result<Response<ValidateParamsResponse>, Status> {
        let violations = check_params(request.into_inner()).into_iter().collect();
        Ok(Response::new(ValidateParamsResponse { violations }))
    }

    async fn cancel_stage(
        &self,
        request: Request<CancelStageRequest>,
    ) -> Result<Response<CancelStageResponse>, Status> {
        let found = self.running.cancel(&request.get_ref().job_id);
        Ok(Response::new(CancelStageResponse { found }))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn validate_params_names_the_field_as_the_job_json_does() {
        assert_eq!(check_params(pb::ScanParams::default()), None, "the defaults are valid");
        let far = pb::ScanParams { standoff_mm: Some(300.0), ..Default::default() };
        let v = check_params(far).expect("refused");
        assert_eq!(v.field, "scan.standoff_mm");
        assert!(v.message.contains("300"), "{}", v.message);
        let mode = pb::ScanParams { mode: 7, ..Default::default() };
        let v = check_params(mode).expect("refused");
        assert_eq!(v.field, "scan");
        assert!(v.message.contains("scan.mode"), "{}", v.message);
    }
}
