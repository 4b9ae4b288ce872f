//! tonic adapter of the machine service's robot cell: `ExecuteRobot` replays the CAM's joint
//! trajectory on a dexel stock ([`crate::domain::robot`]) on a blocking thread, streams progress,
//! and stores the simulated part (STL and the deviation view PLY) and the run's report. The robot
//! cell is a machine of its own: it does not wait for the mill's program.

use std::sync::Arc;

use depthmill_common::artifacts::{ArtifactError, ArtifactStore, ObjectArtifactStore};
use depthmill_common::stage::StageGuard;
use depthmill_proto::ErrorCode;
use depthmill_proto::machine::v1 as pb;
use depthmill_proto::types::v1::{Diagnostic, Progress};
use tokio::sync::mpsc;
use tonic::Status;

use crate::domain::job::{Reference, part_meshes};
use crate::domain::robot::{RobotRunError, RobotRunOptions, Trajectory, run_watched};

/// Largest trajectory accepted, bytes (about [`crate::domain::robot::MAX_POINTS`] points).
pub(crate) const MAX_TRAJECTORY_BYTES: u64 = 1 << 30;

/// Dexel cell when the job sets none, mm.
pub const DEFAULT_CELL_MM: f64 = 0.25;

fn run_status(e: RobotRunError) -> Status {
    match e {
        RobotRunError::Stopped => ErrorCode::Cancelled.status("the robot run was cancelled"),
        other => ErrorCode::InvalidArgument.status(other.to_string()),
    }
}

fn progress(fraction: f64, message: String) -> pb::ExecuteRobotUpdate {
    pb::ExecuteRobotUpdate {
        update: Some(pb::execute_robot_update::Update::Progress(Progress { fraction, message })),
    }
}

/// Starts a robot run of the trajectory in `bytes` measured against `reference`, on cells of
/// `cell_mm`; the returned channel streams progress and the result.
pub(crate) fn execute(
    bytes: Vec<u8>,
    reference: Option<Reference>,
    cell_mm: Option<f64>,
    store: Arc<ObjectArtifactStore>,
    guard: StageGuard,
) -> Result<mpsc::Receiver<Result<pb::ExecuteRobotUpdate, Status>>, Status> {
    let cell = cell_mm.unwrap_or(DEFAULT_CELL_MM);
    if !(cell.is_finite() && (0.01..=10.0).contains(&cell)) {
        return Err(
            ErrorCode::InvalidArgument.status(format!("execute.cell_mm {cell}: must be from 0.01 to 10 mm"))
        );
    }
    let (tx, rx) = mpsc::channel(32);
    let span = tracing::Span::current();
    tokio::spawn(async move {
        let token = guard.token().clone();
        let progress_tx = tx.clone();
        let worked = tokio::task::spawn_blocking(move || {
            span.in_scope(|| {
                let traj = Trajectory::from_json(&bytes).map_err(run_status)?;
                let opts = RobotRunOptions { cell_mm: cell, max_error_mm: 0.5 * cell };
                let every = (traj.points.len() / 50).max(1);
                let stop = |done: usize, total: usize| {
                    if done.is_multiple_of(every) {
                        let _ = progress_tx.try_send(Ok(progress(
                            0.9 * done as f64 / total.max(1) as f64,
                            format!("cutting step {done} of {total}"),
                        )));
                    }
                    token.is_cancelled()
                };
                let points = reference.as_ref().map(|r| &r.points[..]);
                let (report, stock) = run_watched(&traj, &opts, points, &stop).map_err(run_status)?;
                let _ = progress_tx.try_send(Ok(progress(0.9, "meshing the simulated part".into())));
                let measured = points.zip(report.deviation.as_ref()).map(|(p, d)| (p, &d.per_point[..]));
                let (part, stl, ply) = part_meshes(&stock, measured, &Default::default())
                    .map_err(|e| ErrorCode::Internal.status(e.to_string()))?;
                let mut json = serde_json::to_value(&report)
                    .map_err(|e| Status::internal(format!("encoding the report: {e}")))?;
                json["part_mesh"] = serde_json::to_value(&part).unwrap_or_default();
                json["reference"] = serde_json::json!(reference.as_ref().map(|r| r.source.clone()));
                let json = serde_json::to_vec_pretty(&json)
                    .map_err(|e| Status::internal(format!("encoding the report: {e}")))?;
                Ok::<_, Status>((report, stl, ply, json))
            })
        })
        .await;
        let (report, stl, ply, json) = match worked {
            Ok(Ok(v)) => v,
            Ok(Err(status)) => {
                tracing::info!(error = %status.message(), "robot run failed");
                let _ = tx.send(Err(status)).await;
                return;
            }
            Err(e) => {
                let _ = tx.send(Err(Status::internal(format!("robot run panicked: {e}")))).await;
                return;
            }
        };
        let result = async {
            let part_mesh = store.put_bytes("model/stl", &stl).await?;
            let part_view = store.put_bytes("application/x-ply", &ply).await?;
            let machine_report = store.put_bytes("application/json", &json).await?;
            let mut diagnostics = Vec::new();
            if report.rapid_removed_mm3 > 0.0 {
                let first = report.rapid_cuts.first();
                diagnostics.push(Diagnostic {
                    code: "rapid_cut".into(),
                    message: format!(
                        "rapid moves removed {:.1} mm³ (a crash on a real cell){}",
                        report.rapid_removed_mm3,
                        first.map_or(String::new(), |c| format!(
                            ", the first at point {} near ({:.2}, {:.2}, {:.2}) mm",
                            c.point, c.at_mm[0], c.at_mm[1], c.at_mm[2]
                        ))
                    ),
                });
            }
            let d = report.deviation.as_ref();
            Ok::<_, ArtifactError>(pb::ExecuteRobotResult {
                part_mesh: Some(part_mesh.into()),
                part_view: Some(part_view.into()),
                machine_report: Some(machine_report.into()),
                against_part: d.map(|d| pb::PartFigures {
                    points: d.points as u64,
                    max_gouge_mm: d.max_gouge_mm,
                    max_leftover_mm: d.max_leftover_mm,
                    mean_leftover_mm: d.mean_leftover_mm,
                    rms_deviation_mm: d.rms_mm,
                }),
                cycle_time_s: report.cycle_time_s,
                removed_mm3: report.removed_mm3,
                rapid_removed_mm3: report.rapid_removed_mm3,
                diagnostics,
            })
        }
        .await;
        let msg = match result {
            Ok(r) => Ok(pb::ExecuteRobotUpdate { update: Some(pb::execute_robot_update::Update::Result(r)) }),
            Err(e) => Err(depthmill_common::artifacts::grpc_status(e)),
        };
        let _ = tx.send(msg).await;
        drop(guard);
    });
    Ok(rx)
}
