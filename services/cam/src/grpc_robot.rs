//! tonic adapter of the CAM service's robot milling: `PlanRobot` (a mesh artifact -> the
//! Cartesian program, the joint trajectory and the report) and `ValidateRobotParams`.

use std::sync::Arc;

use depthmill_common::artifacts::{ArtifactError, ArtifactStore, ObjectArtifactStore};
use depthmill_geometry::formats::{Geometry, ReadLimits};
use depthmill_geometry::{Mesh, UnitsDecision};
use depthmill_proto::ErrorCode;
use depthmill_proto::cam::v1 as pb;
use depthmill_proto::types::v1::{Diagnostic, FieldViolation, Progress};
use tokio::sync::mpsc;
use tonic::Status;

use crate::domain::CamError;
use crate::domain::robot::{RobotPlanError, plan_robot_watched, robot_gcode};
use crate::domain::robot_job::{RobotSettings, robot_report, robot_warnings};
use crate::domain::tool::ToolLibrary;

/// Wire parameters -> the job's robot settings.
pub(crate) fn settings(p: pb::RobotParams) -> RobotSettings {
    RobotSettings {
        tool: p.tool,
        step_mm: p.step_mm,
        radial_depth_mm: p.radial_depth_mm,
        stock_margin_mm: p.stock_margin_mm,
        part_at_mm: p.part_at_mm.map(|v| [v.x, v.y, v.z]),
        part_yaw_deg: p.part_yaw_deg,
        feed_mm_min: p.feed_mm_min,
        rpm: p.rpm,
        max_tilt_deg: p.max_tilt_deg,
        spindle_length_mm: p.spindle_length_mm,
        spindle_mount_deg: p.spindle_mount_deg,
        spindle_diameter_mm: p.spindle_diameter_mm,
    }
}

/// The first problem of a job's robot section, named by its field; `None` when it is accepted.
pub(crate) fn check(p: pb::RobotParams, library: &ToolLibrary) -> Option<FieldViolation> {
    let s = settings(p);
    let named = |e: CamError| match e {
        CamError::InvalidParameter { field, message } => FieldViolation { field, message },
        other => FieldViolation { field: "robot".into(), message: other.to_string() },
    };
    // The ranges before the tool, so a bad value is named even with an unknown tool.
    if let Err(e) = s.check() {
        return Some(named(e));
    }
    match library.resolve(s.tool_name()) {
        Ok(tool) => s.check_with(&tool).err().map(named),
        Err(e) => Some(FieldViolation { field: "robot.tool".into(), message: e.to_string() }),
    }
}

fn plan_status(e: RobotPlanError) -> Status {
    match e {
        RobotPlanError::Cancelled => ErrorCode::Cancelled.status("planning cancelled"),
        other => ErrorCode::InvalidArgument.status(other.to_string()),
    }
}

/// Reads the mesh artifact and scales it to millimetres.
async fn read_mesh(
    store: &ObjectArtifactStore,
    sha: &str,
    units: i32,
) -> Result<(Mesh, Option<UnitsDecision>), Status> {
    let read = depthmill_common::artifacts::read_geometry(
        store,
        sha,
        units,
        "input.units",
        "mesh",
        &ReadLimits::default(),
    )
    .await?;
    match read.geometry {
        Geometry::Mesh(m) if !m.triangles.is_empty() => Ok((m, read.units)),
        Geometry::Mesh(_) => {
            Err(ErrorCode::InvalidArgument.status(format!("{}: the mesh has no triangles", read.name)))
        }
        Geometry::Cloud(_) => Err(ErrorCode::InvalidArgument.status(format!(
            "{}: is a point cloud; robot milling needs the part's mesh (STL, OBJ, OFF, or PLY with faces)",
            read.name
        ))),
    }
}

fn progress_update(fraction: f64, message: &str) -> pb::PlanRobotUpdate {
    pb::PlanRobotUpdate {
        update: Some(pb::plan_robot_update::Update::Progress(Progress {
            fraction,
            message: message.to_string(),
        })),
    }
}

/// Everything `PlanRobot` needs once the request is read.
pub(crate) struct RobotCall {
    pub store: Arc<ObjectArtifactStore>,
    pub library: Arc<ToolLibrary>,
    pub guard: depthmill_common::stage::StageGuard,
}

/// Starts `PlanRobot`: checks the request, reads the mesh, then plans on a blocking thread while
/// the returned channel streams progress and the result.
pub(crate) async fn plan(
    req: pb::PlanRobotRequest,
    call: RobotCall,
) -> Result<mpsc::Receiver<Result<pb::PlanRobotUpdate, Status>>, Status> {
    let RobotCall { store, library, guard } = call;
    let s = settings(req.params.unwrap_or_default());
    s.check().map_err(Status::from)?;
    let tool = library
        .resolve(s.tool_name())
        .map_err(|e| ErrorCode::InvalidArgument.status(format!("robot.tool: {e}")))?;
    let mesh_ref =
        req.mesh.ok_or_else(|| ErrorCode::InvalidArgument.status("mesh: an artifact is required"))?;
    let (mesh, units) = read_mesh(&store, &mesh_ref.sha256, req.units).await?;
    let job = s.job(&mesh, tool).map_err(Status::from)?;
    let (tx, rx) = mpsc::channel(32);
    let span = tracing::Span::current();
    let input = format!("mesh {}", &mesh_ref.sha256[..12.min(mesh_ref.sha256.len())]);
    tokio::spawn(async move {
        let token = guard.token().clone();
        let progress_tx = tx.clone();
        let planned = tokio::task::spawn_blocking(move || {
            span.in_scope(|| {
                let progress = move |f: f64, m: &str| {
                    let _ = progress_tx.try_send(Ok(progress_update(f, m)));
                };
                let cancelled = move || token.is_cancelled();
                let started = std::time::Instant::now();
                let topology = crate::domain::slice::topology(&mesh);
                let plan = plan_robot_watched(&mesh, &job, &progress, &cancelled).map_err(plan_status)?;
                let elapsed = started.elapsed().as_secs_f64();
                let gcode = robot_gcode(&plan, &job.tool.name, s.feed(), s.spindle_rpm(), &input)
                    .map_err(plan_status)?;
                let mut report = robot_report(&plan, &topology, &input, &job.tool.name, elapsed);
                report["units"] = serde_json::to_value(&units).unwrap_or_default();
                report["settings"] = serde_json::json!({
                    "step_mm": job.layers.step_mm,
                    "radial_depth_mm": job.layers.radial_depth_mm,
                    "stock_margin_mm": job.layers.stock_margin_mm,
                    "feed_mm_min": job.feed_mm_min,
                    "rpm": s.spindle_rpm(),
                    "max_tilt_deg": job.tilt.max_tilt_deg,
                    "spindle_length_mm": job.cell.spindle_length_mm,
                    "spindle_mount_deg": job.cell.spindle_mount_deg,
                    "spindle_diameter_mm": job.cell.spindle_diameter_mm,
                });
                let mut diagnostics: Vec<Diagnostic> = robot_warnings(&plan, &topology)
                    .into_iter()
                    .map(|(code, message)| Diagnostic { code: code.into(), message })
                    .collect();
                if let Some(u) = &units {
                    diagnostics.push(Diagnostic {
                        code: "units".into(),
                        message: format!("mesh read in {} ({}: {})", u.unit, u.source, u.reason),
                    });
                }
                report["warnings"] = diagnostics
                    .iter()
                    .map(|d| serde_json::json!({"code": d.code, "message": d.message}))
                    .collect();
                let trajectory = serde_json::to_vec(&plan.robot)
                    .map_err(|e| Status::internal(format!("encoding the trajectory: {e}")))?;
                let report = serde_json::to_vec_pretty(&report)
                    .map_err(|e| Status::internal(format!("encoding the report: {e}")))?;
                Ok::<_, Status>((plan, gcode, trajectory, report, diagnostics))
            })
        })
        .await;
        let (plan, gcode, trajectory, report, diagnostics) = match planned {
            Ok(Ok(v)) => v,
            Ok(Err(status)) => {
                tracing::info!(error = %status.message(), "robot planning failed");
                let _ = tx.send(Err(status)).await;
                return;
            }
            Err(e) => {
                let _ = tx.send(Err(Status::internal(format!("robot planning panicked: {e}")))).await;
                return;
            }
        };
        let result = async {
            let gcode = store.put_bytes("text/x-gcode", gcode.as_bytes()).await?;
            let trajectory = store.put_bytes("application/json", &trajectory).await?;
            let report = store.put_bytes("application/json", &report).await?;
            let c = &plan.path;
            Ok::<_, ArtifactError>(pb::PlanRobotResult {
                gcode: Some(gcode.into()),
                joint_trajectory: Some(trajectory.into()),
                plan_report: Some(report.into()),
                estimated_time_s: plan.robot.duration_s,
                diagnostics,
                layers: plan.layers.layers.len() as u64,
                positions: c.points.len() as u64,
                colliding: c.colliding as u64,
                tilted: c.tilted as u64,
                blocked: c.blocked.len() as u64,
                unreachable_stretches: plan.robot.unreachable.len() as u64,
                max_tilt_deg: c.max_tilt_deg,
            })
        }
        .await;
        let msg = match result {
            Ok(r) => Ok(pb::PlanRobotUpdate { update: Some(pb::plan_robot_update::Update::Result(r)) }),
            Err(e) => Err(depthmill_common::artifacts::grpc_status(e)),
        };
        let _ = tx.send(msg).await;
        drop(guard);
    });
    Ok(rx)
}
