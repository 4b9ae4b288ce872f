//! Conversions between the job model and the wire types, both directions: the orchestrator's
//! gRPC API takes and returns jobs, and the worker sends each stage its parameters.

use depthmill_proto::cam::v1 as cam;
use depthmill_proto::machine::v1 as machine;
use depthmill_proto::orchestrator::v1 as pb;
use depthmill_proto::reconstruction::v1 as rec;
use depthmill_proto::scanning::v1 as scan;
use depthmill_proto::types::v1 as types;

use crate::domain::spec::{
    AdaptiveMode, CellEstimator, Dialect, ExecuteParams, FaceChoice, FaceSpec, FillMethod, FillParams,
    Filters, Finishing, FinishingStrategy, InputKind, InputUnits, IntensityWindow, JobInput, Obstacle,
    PlanParams, Process, RadiusFilter, ReconstructParams, Rest, RobotParams, Roi, Roughing,
    RoughingDirection, ScanMode, ScanParams, ScanPassSpec, StatisticalFilter, Stock, TableFilter,
};
use crate::domain::{Job, JobMetrics, JobSpec, JobStatus, SpecError, Stage};
use depthmill_proto::types::v1::Vec3;

fn spec_err(field: &str, message: &str) -> SpecError {
    SpecError { field: field.to_string(), message: message.to_string() }
}

// ---- domain -> wire -------------------------------------------------------------------------

pub fn scan_params(p: &ScanParams) -> scan::ScanParams {
    scan::ScanParams {
        mode: match p.mode {
            None => scan::ScanMode::Unspecified,
            Some(ScanMode::Dynamic) => scan::ScanMode::Dynamic,
            Some(ScanMode::StopAndMove) => scan::ScanMode::StopAndMove,
        } as i32,
        table_angles_deg: p.table_angles_deg.clone().unwrap_or_default(),
        standoff_mm: p.standoff_mm,
        line_rate_hz: p.line_rate_hz,
        adaptive_rescan: p.adaptive_rescan,
        line_spacing_mm: p.line_spacing_mm,
        overlap: p.overlap,
        margin_mm: p.margin_mm,
        tilt_deg: p.tilt_deg,
        stop_and_move_rate_hz: p.stop_and_move_rate_hz,
        latch_latency_s: p.latch_latency_s,
        latch_jitter_s: p.latch_jitter_s,
        compensate_latency: p.compensate_latency,
        rescan_pixel_mm: p.rescan_pixel_mm,
        rescan_standoff_mm: p.rescan_standoff_mm,
        seed: p.seed,
        max_frames: p.max_frames,
        passes: p
            .passes
            .iter()
            .flatten()
            .map(|s| scan::ScanPass {
                table_deg: s.table_deg,
                start_mm: Some(vec3(s.start_mm)),
                end_mm: Some(vec3(s.end_mm)),
            })
            .collect(),
        obstacle_clearance_mm: p.obstacle_clearance_mm,
        obstacles: p.obstacles.iter().flatten().map(obstacle_to_wire).collect(),
        table_search_deg: p.table_search_deg,
    }
}

fn obstacle_to_wire(o: &Obstacle) -> scan::ScanObstacle {
    use scan::scan_obstacle::Shape;
    let (name, shape) = match o {
        Obstacle::Box { name, min_mm, max_mm } => (
            name.clone(),
            Shape::Box(scan::ObstacleBox { min_mm: Some(vec3(*min_mm)), max_mm: Some(vec3(*max_mm)) }),
        ),
        Obstacle::Cylinder { name, center_mm, radius_mm, z_min_mm, z_max_mm } => (
            name.clone(),
            Shape::Cylinder(scan::ObstacleCylinder {
                center_x_mm: center_mm[0],
                center_y_mm: center_mm[1],
                radius_mm: *radius_mm,
                z_min_mm: *z_min_mm,
                z_max_mm: *z_max_mm,
            }),
        ),
        Obstacle::Sphere { name, center_mm, radius_mm } => (
            name.clone(),
            Shape::Sphere(scan::ObstacleSphere { center_mm: Some(vec3(*center_mm)), radius_mm: *radius_mm }),
        ),
    };
    scan::ScanObstacle { name, shape: Some(shape) }
}

fn obstacle_from_wire(o: scan::ScanObstacle, i: usize) -> Result<Obstacle, SpecError> {
    use scan::scan_obstacle::Shape;
    let field = format!("scan.obstacles[{i}]");
    let arr = |v: Option<Vec3>, what: &str| {
        v.map(|v| [v.x, v.y, v.z])
            .ok_or_else(|| SpecError { field: format!("{field}.{what}"), message: "required".into() })
    };
    Ok(match o.shape {
        None => return Err(SpecError { field, message: "give one of box, cylinder and sphere".into() }),
        Some(Shape::Box(b)) => {
            Obstacle::Box { name: o.name, min_mm: arr(b.min_mm, "min_mm")?, max_mm: arr(b.max_mm, "max_mm")? }
        }
        Some(Shape::Cylinder(c)) => Obstacle::Cylinder {
            name: o.name,
            center_mm: [c.center_x_mm, c.center_y_mm],
            radius_mm: c.radius_mm,
            z_min_mm: c.z_min_mm,
            z_max_mm: c.z_max_mm,
        },
        Some(Shape::Sphere(s)) => Obstacle::Sphere {
            name: o.name,
            center_mm: arr(s.center_mm, "center_mm")?,
            radius_mm: s.radius_mm,
        },
    })
}

fn vec3(v: [f64; 3]) -> Vec3 {
    Vec3 { x: v[0], y: v[1], z: v[2] }
}

pub fn face(f: &FaceSpec) -> rec::FaceSpec {
    rec::FaceSpec {
        face: match (&f.view, f.a_deg, f.normal) {
            (Some(v), _, _) => Some(rec::face_spec::Face::View(v.clone())),
            (None, Some(a), _) => Some(rec::face_spec::Face::ADeg(a)),
            (None, None, Some(n)) => Some(rec::face_spec::Face::Normal(vec3(n))),
            (None, None, None) => None,
        },
        origin: f.origin.map(vec3),
    }
}

pub fn reconstruct_params(p: &ReconstructParams) -> rec::ReconstructParams {
    rec::ReconstructParams {
        pixel_mm: p.pixel_mm,
        faces: p.faces.iter().flatten().map(face).collect(),
        face_choice: p.face_choice.as_ref().map(|c| rec::FaceChoiceParams {
            step_deg: c.step_deg,
            max_faces: c.max_faces,
            min_gain_pct: c.min_gain_pct,
            cell_mm: c.cell_mm,
            reach_radius_mm: c.reach_radius_mm,
            tolerance_mm: c.tolerance_mm,
        }),
        fill: p.fill.as_ref().map(|f| rec::FillParams {
            method: match f.method {
                None => rec::FillMethod::Unspecified,
                Some(FillMethod::Idw) => rec::FillMethod::Idw,
                Some(FillMethod::Max) => rec::FillMethod::Max,
            } as i32,
            max_hole_mm: f.max_hole_mm,
            radius_mm: f.radius_mm,
            power: f.power,
        }),
        roi: p.roi.map(|r| rec::Roi {
            x_min_mm: r.x_min_mm,
            y_min_mm: r.y_min_mm,
            x_max_mm: r.x_max_mm,
            y_max_mm: r.y_max_mm,
        }),
        margin_mm: p.margin_mm,
        z_min_mm: p.z_min_mm,
        z_max_mm: p.z_max_mm,
        filters: p.filters.as_ref().map(|f| rec::FilterParams {
            intensity: f.intensity.map(|w| rec::IntensityWindow { min: w.min, max: w.max }),
            voxel_mm: f.voxel_mm,
            statistical: f.statistical.map(|s| rec::StatisticalOutlierParams {
                k: s.k.min(u32::MAX as usize) as u32,
                n_sigma: s.n_sigma,
                keep_surface: s.keep_surface,
            }),
            radius: f.radius.map(|r| rec::RadiusOutlierParams {
                radius_mm: r.radius_mm,
                min_neighbours: r.min_neighbours.min(u32::MAX as usize) as u32,
            }),
            transform: f.transform.map(|m| m.iter().flatten().copied().collect()).unwrap_or_default(),
            table: f.table.map(|t| rec::TableParams {
                tolerance_mm: t.tolerance_mm,
                largest_only: t.largest_only,
                gap_mm: t.gap_mm,
            }),
        }),
        roughing_factor: p.roughing_factor,
        estimator: match p.estimator {
            None => rec::CellEstimator::Unspecified,
            Some(CellEstimator::Max) => rec::CellEstimator::Max,
            Some(CellEstimator::Median) => rec::CellEstimator::Median,
            Some(CellEstimator::MedianBilateral) => rec::CellEstimator::MedianBilateral,
            Some(CellEstimator::Fit) => rec::CellEstimator::Fit,
        } as i32,
    }
}

pub fn plan_params(p: &PlanParams) -> cam::PlanParams {
    cam::PlanParams {
        stock: p.stock.as_ref().map(|s| cam::Stock {
            x_mm: s.x_mm,
            y_mm: s.y_mm,
            z_mm: s.z_mm,
            material: s.material.clone(),
        }),
        roughing: p.roughing.as_ref().map(|r| cam::Roughing {
            tool: r.tool.clone(),
            step_down_mm: r.step_down_mm,
            stock_to_leave_mm: r.stock_to_leave_mm,
            direction: match r.direction {
                None => cam::RasterDirection::Unspecified,
                Some(RoughingDirection::X) => cam::RasterDirection::X,
                Some(RoughingDirection::Y) => cam::RasterDirection::Y,
                Some(RoughingDirection::Contour) => cam::RasterDirection::Contour,
            } as i32,
        }),
        finishing: p.finishing.as_ref().map(|f| cam::Finishing {
            tool: f.tool.clone(),
            strategy: match f.strategy {
                None => cam::FinishingStrategy::Unspecified,
                Some(FinishingStrategy::RasterX) => cam::FinishingStrategy::RasterX,
                Some(FinishingStrategy::RasterY) => cam::FinishingStrategy::RasterY,
                Some(FinishingStrategy::RasterAngle) => cam::FinishingStrategy::RasterAngle,
                Some(FinishingStrategy::IsoLevel) => cam::FinishingStrategy::IsoLevel,
            } as i32,
            angle_deg: f.angle_deg,
            step_over_mm: f.step_over_mm,
            tolerance_mm: f.tolerance_mm,
            arcs: f.arcs,
            pixel_model: f.pixel_model.clone(),
        }),
        dialect: match p.dialect {
            None => cam::Dialect::Unspecified,
            Some(Dialect::Linuxcnc) => cam::Dialect::Linuxcnc,
            Some(Dialect::Fanuc) => cam::Dialect::Fanuc,
        } as i32,
        rest: p.rest.as_ref().map(|r| cam::Rest {
            enabled: r.enabled,
            tool: r.tool.clone(),
            min_leftover_mm: r.min_leftover_mm,
        }),
    }
}

pub fn execute_params(p: &ExecuteParams) -> machine::ExecuteParams {
    machine::ExecuteParams {
        machine: p.machine.clone(),
        adaptive: match p.adaptive {
            None => machine::AdaptiveMode::Unspecified,
            Some(AdaptiveMode::Aco) => machine::AdaptiveMode::Aco,
            Some(AdaptiveMode::FeedOnly) => machine::AdaptiveMode::FeedOnly,
            Some(AdaptiveMode::Off) => machine::AdaptiveMode::Off,
        } as i32,
        material: p.material.clone(),
        stock_z_mm: p.stock_z_mm,
        cell_mm: p.cell_mm,
        clamp: p.clamp.unwrap_or(false),
        compare: p.compare,
        dexel: p.dexel.map(|d| machine::DexelCells {
            x_cell_mm: d.x_cell_mm,
            y_cell_mm: d.y_cell_mm,
            z_cell_mm: d.z_cell_mm,
        }),
    }
}

/// The execute stage's parameters, the plan's stock filling what the job's `execute` leaves open.
/// The plan stage's parameters for a job: its `plan` section, with the stock's material taken
/// from `execute.material` when only that names one (the feeds are then chosen for the material
/// the machine will cut), and the finishing pixel model `facet` when the job reconstructs its
/// maps with the `fit` estimator and names none (see `Finishing::pixel_model`).
pub fn plan_params_for_job(spec: &JobSpec) -> cam::PlanParams {
    let mut plan = spec.plan.clone().unwrap_or_default();
    if spec.plans_a_fitted_map() {
        let finishing = plan.finishing.get_or_insert_with(Default::default);
        if finishing.pixel_model.is_none() {
            finishing.pixel_model = Some("facet".into());
        }
    }
    if let Some(m) = spec.execute.as_ref().and_then(|e| e.material.clone()) {
        let stock = plan.stock.get_or_insert_with(Default::default);
        if stock.material.is_none() {
            stock.material = Some(m);
        }
    }
    plan_params(&plan)
}

pub fn execute_params_for_job(spec: &JobSpec) -> machine::ExecuteParams {
    let mut p = execute_params(&spec.execute.clone().unwrap_or_default());
    if let Some(stock) = spec.plan.as_ref().and_then(|pl| pl.stock.as_ref()) {
        if p.material.is_none() {
            p.material = stock.material.clone();
        }
        if p.stock_z_mm.is_none() {
            p.stock_z_mm = stock.z_mm;
        }
    }
    p
}

/// A robot job's settings for the CAM service.
pub fn robot_params(p: &RobotParams) -> cam::RobotParams {
    cam::RobotParams {
        tool: p.tool.clone(),
        step_mm: p.step_mm,
        radial_depth_mm: p.radial_depth_mm,
        stock_margin_mm: p.stock_margin_mm,
        part_at_mm: p.part_at_mm.map(vec3),
        part_yaw_deg: p.part_yaw_deg,
        feed_mm_min: p.feed_mm_min,
        rpm: p.rpm,
        max_tilt_deg: p.max_tilt_deg,
        spindle_length_mm: p.spindle_length_mm,
        spindle_mount_deg: p.spindle_mount_deg,
        spindle_diameter_mm: p.spindle_diameter_mm,
    }
}

fn robot_params_from_pb(p: cam::RobotParams) -> RobotParams {
    RobotParams {
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

/// The wire unit of a job's input (`auto` and none are both unspecified on the wire).
pub fn input_units(u: Option<InputUnits>) -> types::LengthUnit {
    match u {
        None | Some(InputUnits::Auto) => types::LengthUnit::Unspecified,
        Some(InputUnits::Mm) => types::LengthUnit::Mm,
        Some(InputUnits::M) => types::LengthUnit::M,
        Some(InputUnits::In) => types::LengthUnit::In,
    }
}

pub fn input_kind(k: InputKind) -> pb::InputKind {
    match k {
        InputKind::Mesh => pb::InputKind::Mesh,
        InputKind::PointCloud => pb::InputKind::PointCloud,
        InputKind::DepthMap => pb::InputKind::DepthMap,
        InputKind::Gcode => pb::InputKind::Gcode,
    }
}

pub fn job_spec(s: &JobSpec) -> pb::JobSpec {
    pb::JobSpec {
        name: s.name.clone(),
        input: Some(pb::JobInput {
            kind: input_kind(s.input.kind) as i32,
            artifact: s.input.artifact.clone(),
            pixel_mm: s.input.pixel_mm,
            z_min_mm: s.input.z_min_mm,
            z_max_mm: s.input.z_max_mm,
            units: input_units(s.input.units) as i32,
        }),
        scan: s.scan.as_ref().map(scan_params),
        reconstruct: s.reconstruct.as_ref().map(reconstruct_params),
        plan: s.plan.as_ref().map(plan_params),
        execute: s.execute.as_ref().map(execute_params),
        process: match s.process {
            None => pb::Process::Unspecified,
            Some(Process::Mill) => pb::Process::Mill,
            Some(Process::Robot) => pb::Process::Robot,
        } as i32,
        robot: s.robot.as_ref().map(robot_params),
    }
}

pub fn stage(s: Stage) -> pb::Stage {
    match s {
        Stage::Scan => pb::Stage::Scan,
        Stage::Reconstruct => pb::Stage::Reconstruct,
        Stage::Plan => pb::Stage::Plan,
        Stage::Execute => pb::Stage::Execute,
        Stage::Report => pb::Stage::Report,
    }
}

pub fn status(s: JobStatus) -> pb::JobStatus {
    match s {
        JobStatus::Queued => pb::JobStatus::Queued,
        JobStatus::Running => pb::JobStatus::Running,
        JobStatus::Succeeded => pb::JobStatus::Succeeded,
        JobStatus::Failed => pb::JobStatus::Failed,
        JobStatus::Cancelled => pb::JobStatus::Cancelled,
    }
}

/// A job's metrics on the wire: every REST metric under its own name, but the original part's
/// mean material left, which is `mean_leftover_mm`.
pub fn job_metrics(m: &JobMetrics) -> pb::JobMetrics {
    pb::JobMetrics {
        coverage_pct: m.coverage_pct,
        max_gouge_mm: m.max_gouge_mm,
        max_leftover_mm: m.max_leftover_mm,
        rms_deviation_mm: m.rms_deviation_mm,
        cycle_time_s: m.cycle_time_s,
        cycle_time_no_adaptive_s: m.cycle_time_no_adaptive_s,
        scan_points: m.scan_points,
        scan_time_s: m.scan_time_s,
        scan_coverage_pct: m.scan_coverage_pct,
        scan_registration_rms_mm: m.scan_registration_rms_mm,
        scan_registration_merge_rms_mm: m.scan_registration_merge_rms_mm,
        scan_calibration_version: m.scan_calibration_version,
        mean_leftover_mm: m.original_mean_leftover_mm,
        robot_layers: m.robot_layers,
        robot_positions: m.robot_positions,
        robot_colliding_upright: m.robot_colliding_upright,
        robot_tilted: m.robot_tilted,
        robot_blocked: m.robot_blocked,
        robot_unreachable_stretches: m.robot_unreachable_stretches,
        robot_max_tilt_deg: m.robot_max_tilt_deg,
        robot_removed_mm3: m.robot_removed_mm3,
        robot_rapid_removed_mm3: m.robot_rapid_removed_mm3,
        estimated_time_s: m.estimated_time_s,
        removed_mm3: m.removed_mm3,
        cycle_time_other_policy_s: m.cycle_time_other_policy_s,
        plan_max_gouge_mm: m.plan_max_gouge_mm,
        plan_max_leftover_mm: m.plan_max_leftover_mm,
        plan_mean_leftover_mm: m.plan_mean_leftover_mm,
        scan_silhouette_coverage_pct: m.scan_silhouette_coverage_pct,
        part_max_gouge_mm: m.part_max_gouge_mm,
        part_max_leftover_mm: m.part_max_leftover_mm,
        part_mean_leftover_mm: m.part_mean_leftover_mm,
        part_mean_mm: m.part_mean_mm,
        part_rms_mm: m.part_rms_mm,
        part_off_walls_max_gouge_mm: m.part_off_walls_max_gouge_mm,
        part_off_walls_mean_mm: m.part_off_walls_mean_mm,
        part_off_walls_rms_mm: m.part_off_walls_rms_mm,
        part_opened_max_gouge_mm: m.part_opened_max_gouge_mm,
        part_opened_mean_mm: m.part_opened_mean_mm,
        part_opened_rms_mm: m.part_opened_rms_mm,
        part_opened_max_gouge_x_mm: m.part_opened_max_gouge_x_mm,
        part_opened_max_gouge_y_mm: m.part_opened_max_gouge_y_mm,
        part_opened_measured_max_gouge_mm: m.part_opened_measured_max_gouge_mm,
        part_opened_measured_mean_mm: m.part_opened_measured_mean_mm,
        part_opened_measured_rms_mm: m.part_opened_measured_rms_mm,
        preview_rms_mm: m.preview_rms_mm,
        original_points: m.original_points,
        original_max_gouge_mm: m.original_max_gouge_mm,
        original_max_leftover_mm: m.original_max_leftover_mm,
        original_rms_deviation_mm: m.original_rms_deviation_mm,
        opened_points: m.opened_points,
        opened_max_gouge_mm: m.opened_max_gouge_mm,
        opened_max_leftover_mm: m.opened_max_leftover_mm,
        opened_mean_leftover_mm: m.opened_mean_leftover_mm,
        opened_rms_deviation_mm: m.opened_rms_deviation_mm,
        map_max_gouge_mm: m.map_max_gouge_mm,
        map_max_leftover_mm: m.map_max_leftover_mm,
        map_mean_leftover_mm: m.map_mean_leftover_mm,
        map_rms_deviation_mm: m.map_rms_deviation_mm,
    }
}

pub fn job(j: &Job) -> pb::Job {
    pb::Job {
        id: j.id.clone(),
        name: j.name.clone(),
        status: status(j.status) as i32,
        stage: stage(j.stage) as i32,
        progress: j.progress,
        error: j.error.as_ref().map(|e| pb::JobError {
            code: e.code.clone(),
            message: e.message.clone(),
            stage: stage(e.stage) as i32,
        }),
        stage_timings_s: j.stage_timings_s.iter().map(|(k, v)| (k.clone(), *v)).collect(),
        artifacts: j.artifacts.iter().map(|(k, v)| (k.clone(), v.clone().into())).collect(),
        metrics: Some(job_metrics(&j.metrics)),
        spec: Some(job_spec(&j.spec)),
        created_at_ms: j.created_at_ms,
        updated_at_ms: j.updated_at_ms,
        cancel_requested: j.cancel_requested,
        attempts: j
            .attempts
            .iter()
            .map(|a| pb::StageAttempt {
                stage: stage(a.stage) as i32,
                attempt: a.attempt,
                started_at_ms: a.started_at_ms,
                finished_at_ms: a.finished_at_ms.unwrap_or(0),
                outcome: a.outcome.as_str().to_string(),
                error_code: a.error_code.clone().unwrap_or_default(),
                error_message: a.error_message.clone().unwrap_or_default(),
            })
            .collect(),
        diagnostics: j
            .diagnostics
            .iter()
            .map(|d| pb::JobDiagnostic {
                stage: stage(d.stage) as i32,
                code: d.code.clone(),
                message: d.message.clone(),
            })
            .collect(),
    }
}

// ---- wire -> domain -------------------------------------------------------------------------

fn enum_value<T: TryFrom<i32>>(field: &str, v: i32) -> Result<T, SpecError> {
    T::try_from(v).map_err(|_| spec_err(field, &format!("unknown enum value {v}")))
}

pub fn job_status_filter(v: i32) -> Result<Option<JobStatus>, SpecError> {
    Ok(match enum_value::<pb::JobStatus>("status", v)? {
        pb::JobStatus::Unspecified => None,
        pb::JobStatus::Queued => Some(JobStatus::Queued),
        pb::JobStatus::Running => Some(JobStatus::Running),
        pb::JobStatus::Succeeded => Some(JobStatus::Succeeded),
        pb::JobStatus::Failed => Some(JobStatus::Failed),
        pb::JobStatus::Cancelled => Some(JobStatus::Cancelled),
    })
}

/// A job request received over gRPC, checked field by field like the REST body.
pub fn job_spec_from_pb(s: pb::JobSpec) -> Result<JobSpec, SpecError> {
    let input = s.input.ok_or_else(|| spec_err("input", "is required"))?;
    let kind = match enum_value::<pb::InputKind>("input.kind", input.kind)? {
        pb::InputKind::Unspecified => return Err(spec_err("input.kind", "is required")),
        pb::InputKind::Mesh => InputKind::Mesh,
        pb::InputKind::PointCloud => InputKind::PointCloud,
        pb::InputKind::DepthMap => InputKind::DepthMap,
        pb::InputKind::Gcode => InputKind::Gcode,
    };
    let scan = s
        .scan
        .map(|p| -> Result<ScanParams, SpecError> {
            Ok(ScanParams {
                mode: match enum_value::<scan::ScanMode>("scan.mode", p.mode)? {
                    scan::ScanMode::Unspecified => None,
                    scan::ScanMode::Dynamic => Some(ScanMode::Dynamic),
                    scan::ScanMode::StopAndMove => Some(ScanMode::StopAndMove),
                },
                table_angles_deg: (!p.table_angles_deg.is_empty()).then_some(p.table_angles_deg),
                standoff_mm: p.standoff_mm,
                line_rate_hz: p.line_rate_hz,
                adaptive_rescan: p.adaptive_rescan,
                line_spacing_mm: p.line_spacing_mm,
                overlap: p.overlap,
                margin_mm: p.margin_mm,
                tilt_deg: p.tilt_deg,
                stop_and_move_rate_hz: p.stop_and_move_rate_hz,
                latch_latency_s: p.latch_latency_s,
                latch_jitter_s: p.latch_jitter_s,
                compensate_latency: p.compensate_latency,
                rescan_pixel_mm: p.rescan_pixel_mm,
                rescan_standoff_mm: p.rescan_standoff_mm,
                seed: p.seed,
                max_frames: p.max_frames,
                obstacle_clearance_mm: p.obstacle_clearance_mm,
                table_search_deg: p.table_search_deg,
                obstacles: if p.obstacles.is_empty() {
                    None
                } else {
                    Some(
                        p.obstacles
                            .into_iter()
                            .enumerate()
                            .map(|(i, o)| obstacle_from_wire(o, i))
                            .collect::<Result<Vec<_>, SpecError>>()?,
                    )
                },
                passes: if p.passes.is_empty() {
                    None
                } else {
                    Some(
                        p.passes
                            .into_iter()
                            .enumerate()
                            .map(|(i, s)| {
                                let v = |x: Option<Vec3>, name: &str| {
                                    x.map(|v| [v.x, v.y, v.z]).ok_or_else(|| SpecError {
                                        field: format!("scan.passes[{i}].{name}"),
                                        message: "required".into(),
                                    })
                                };
                                Ok(ScanPassSpec {
                                    table_deg: s.table_deg,
                                    start_mm: v(s.start_mm, "start_mm")?,
                                    end_mm: v(s.end_mm, "end_mm")?,
                                })
                            })
                            .collect::<Result<Vec<_>, SpecError>>()?,
                    )
                },
            })
        })
        .transpose()?;
    let reconstruct = s
        .reconstruct
        .map(|p| -> Result<ReconstructParams, SpecError> {
            let arr = |v: Vec3| [v.x, v.y, v.z];
            let faces: Vec<FaceSpec> = p
                .faces
                .into_iter()
                .map(|f| {
                    let origin = f.origin.map(arr);
                    match f.face {
                        Some(rec::face_spec::Face::View(v)) => {
                            FaceSpec { view: Some(v), origin, ..Default::default() }
                        }
                        Some(rec::face_spec::Face::ADeg(a)) => {
                            FaceSpec { a_deg: Some(a), origin, ..Default::default() }
                        }
                        Some(rec::face_spec::Face::Normal(n)) => {
                            FaceSpec { normal: Some(arr(n)), origin, ..Default::default() }
                        }
                        None => FaceSpec { origin, ..Default::default() },
                    }
                })
                .collect();
            let filters = p
                .filters
                .map(|f| -> Result<Filters, SpecError> {
                    let transform =
                        depthmill_proto::convert::matrix4_row_major(&f.transform).map_err(|n| {
                            spec_err(
                                "reconstruct.filters.transform",
                                &format!("needs 16 numbers (a row-major 4x4 matrix), got {n}"),
                            )
                        })?;
                    Ok(Filters {
                        intensity: f.intensity.map(|w| IntensityWindow { min: w.min, max: w.max }),
                        voxel_mm: f.voxel_mm,
                        statistical: f.statistical.map(|s| StatisticalFilter {
                            k: s.k as usize,
                            n_sigma: s.n_sigma,
                            keep_surface: s.keep_surface,
                        }),
                        radius: f.radius.map(|r| RadiusFilter {
                            radius_mm: r.radius_mm,
                            min_neighbours: r.min_neighbours as usize,
                        }),
                        transform,
                        table: f.table.map(|t| TableFilter {
                            tolerance_mm: t.tolerance_mm,
                            largest_only: t.largest_only,
                            gap_mm: t.gap_mm,
                        }),
                    })
                })
                .transpose()?;
            Ok(ReconstructParams {
                pixel_mm: p.pixel_mm,
                faces: (!faces.is_empty()).then_some(faces),
                face_choice: p.face_choice.map(|c| FaceChoice {
                    step_deg: c.step_deg,
                    max_faces: c.max_faces,
                    min_gain_pct: c.min_gain_pct,
                    cell_mm: c.cell_mm,
                    reach_radius_mm: c.reach_radius_mm,
                    tolerance_mm: c.tolerance_mm,
                }),
                fill: p
                    .fill
                    .map(|f| -> Result<FillParams, SpecError> {
                        Ok(FillParams {
                            method: match enum_value::<rec::FillMethod>("reconstruct.fill.method", f.method)?
                            {
                                rec::FillMethod::Unspecified => None,
                                rec::FillMethod::Idw => Some(FillMethod::Idw),
                                rec::FillMethod::Max => Some(FillMethod::Max),
                            },
                            max_hole_mm: f.max_hole_mm,
                            radius_mm: f.radius_mm,
                            power: f.power,
                        })
                    })
                    .transpose()?,
                roi: p.roi.map(|r| Roi {
                    x_min_mm: r.x_min_mm,
                    y_min_mm: r.y_min_mm,
                    x_max_mm: r.x_max_mm,
                    y_max_mm: r.y_max_mm,
                }),
                margin_mm: p.margin_mm,
                z_min_mm: p.z_min_mm,
                z_max_mm: p.z_max_mm,
                filters,
                roughing_factor: p.roughing_factor,
                estimator: match enum_value::<rec::CellEstimator>("reconstruct.estimator", p.estimator)? {
                    rec::CellEstimator::Unspecified => None,
                    rec::CellEstimator::Max => Some(CellEstimator::Max),
                    rec::CellEstimator::Median => Some(CellEstimator::Median),
                    rec::CellEstimator::MedianBilateral => Some(CellEstimator::MedianBilateral),
                    rec::CellEstimator::Fit => Some(CellEstimator::Fit),
                },
            })
        })
        .transpose()?;
    let plan = s
        .plan
        .map(|p| -> Result<PlanParams, SpecError> {
            Ok(PlanParams {
                stock: p.stock.map(|st| Stock {
                    x_mm: st.x_mm,
                    y_mm: st.y_mm,
                    z_mm: st.z_mm,
                    material: st.material,
                }),
                roughing: p
                    .roughing
                    .map(|r| -> Result<Roughing, SpecError> {
                        Ok(Roughing {
                            tool: r.tool,
                            step_down_mm: r.step_down_mm,
                            stock_to_leave_mm: r.stock_to_leave_mm,
                            direction: match enum_value::<cam::RasterDirection>(
                                "plan.roughing.direction",
                                r.direction,
                            )? {
                                cam::RasterDirection::Unspecified => None,
                                cam::RasterDirection::X => Some(RoughingDirection::X),
                                cam::RasterDirection::Y => Some(RoughingDirection::Y),
                                cam::RasterDirection::Contour => Some(RoughingDirection::Contour),
                            },
                        })
                    })
                    .transpose()?,
                finishing: p
                    .finishing
                    .map(|f| -> Result<Finishing, SpecError> {
                        Ok(Finishing {
                            tool: f.tool,
                            strategy: match enum_value::<cam::FinishingStrategy>(
                                "plan.finishing.strategy",
                                f.strategy,
                            )? {
                                cam::FinishingStrategy::Unspecified => None,
                                cam::FinishingStrategy::RasterX => Some(FinishingStrategy::RasterX),
                                cam::FinishingStrategy::RasterY => Some(FinishingStrategy::RasterY),
                                cam::FinishingStrategy::RasterAngle => Some(FinishingStrategy::RasterAngle),
                                cam::FinishingStrategy::IsoLevel => Some(FinishingStrategy::IsoLevel),
                            },
                            angle_deg: f.angle_deg,
                            step_over_mm: f.step_over_mm,
                            tolerance_mm: f.tolerance_mm,
                            arcs: f.arcs,
                            pixel_model: f.pixel_model.clone(),
                        })
                    })
                    .transpose()?,
                dialect: match enum_value::<cam::Dialect>("plan.dialect", p.dialect)? {
                    cam::Dialect::Unspecified => None,
                    cam::Dialect::Linuxcnc => Some(Dialect::Linuxcnc),
                    cam::Dialect::Fanuc => Some(Dialect::Fanuc),
                },
                rest: p.rest.map(|r| Rest {
                    enabled: r.enabled,
                    tool: r.tool,
                    min_leftover_mm: r.min_leftover_mm,
                }),
            })
        })
        .transpose()?;
    let execute = s
        .execute
        .map(|p| -> Result<ExecuteParams, SpecError> {
            Ok(ExecuteParams {
                machine: p.machine,
                material: p.material,
                stock_z_mm: p.stock_z_mm,
                cell_mm: p.cell_mm,
                clamp: Some(p.clamp).filter(|c| *c),
                compare: p.compare,
                dexel: p.dexel.map(|d| crate::domain::spec::DexelCells {
                    x_cell_mm: d.x_cell_mm,
                    y_cell_mm: d.y_cell_mm,
                    z_cell_mm: d.z_cell_mm,
                }),
                adaptive: match enum_value::<machine::AdaptiveMode>("execute.adaptive", p.adaptive)? {
                    machine::AdaptiveMode::Unspecified => None,
                    machine::AdaptiveMode::Aco => Some(AdaptiveMode::Aco),
                    machine::AdaptiveMode::FeedOnly => Some(AdaptiveMode::FeedOnly),
                    machine::AdaptiveMode::Off => Some(AdaptiveMode::Off),
                },
            })
        })
        .transpose()?;
    let units = match enum_value::<types::LengthUnit>("input.units", input.units)? {
        types::LengthUnit::Unspecified => None,
        types::LengthUnit::Mm => Some(InputUnits::Mm),
        types::LengthUnit::M => Some(InputUnits::M),
        types::LengthUnit::In => Some(InputUnits::In),
    };
    Ok(JobSpec {
        name: s.name,
        input: JobInput {
            kind,
            artifact: input.artifact,
            pixel_mm: input.pixel_mm,
            z_min_mm: input.z_min_mm,
            z_max_mm: input.z_max_mm,
            units,
        },
        scan,
        reconstruct,
        plan,
        execute,
        process: match enum_value::<pb::Process>("process", s.process)? {
            pb::Process::Unspecified => None,
            pb::Process::Mill => Some(Process::Mill),
            pb::Process::Robot => Some(Process::Robot),
        },
        robot: s.robot.map(robot_params_from_pb),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_full_spec_survives_the_wire() {
        let json = r#"{"name": "bracket",
            "input": {"kind": "mesh", "artifact": "aaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaa"},
            "scan": {"mode": "stop_and_move", "table_angles_deg": [0, 90], "standoff_mm": 150,
                     "line_spacing_mm": 0.5, "compensate_latency": false, "seed": 3,
                     "passes": [{"table_deg": 30, "start_mm": [0, -20, 160], "end_mm": [0, 20, 160]}],
                     "obstacle_clearance_mm": 15,
                     "obstacles": [{"shape": "box", "name": "vice", "min_mm": [400, -50, -100], "max_mm": [420, 50, -60]},
                                   {"shape": "cylinder", "name": "column", "center_mm": [300, 300], "radius_mm": 50, "z_min_mm": -500, "z_max_mm": 500},
                                   {"shape": "sphere", "name": "lamp", "center_mm": [0, 400, 600], "radius_mm": 80}]},
            "reconstruct": {"pixel_mm": 0.1, "faces": [{"view": "+Z"}, {"a_deg": 90}], "fill": {"method": "max"}},
            "plan": {"stock": {"x_mm": 100, "material": "brass"},
                     "roughing": {"tool": "flat-6", "direction": "contour"},
                     "finishing": {"strategy": "raster_angle", "angle_deg": 30, "arcs": false},
                     "dialect": "fanuc", "rest": {"enabled": true, "tool": "ball-1", "min_leftover_mm": 0.1}},
            "execute": {"machine": "emco-f1", "adaptive": "feed_only"}}"#;
        let spec: JobSpec = serde_json::from_str(json).expect("parse");
        assert_eq!(job_spec_from_pb(job_spec(&spec)).expect("back"), spec);
        // Faces chosen from the shape.
        let chosen = json.replace(
            r#""faces": [{"view": "+Z"}, {"a_deg": 90}]"#,
            r#""face_choice": {"step_deg": 30, "max_faces": 3, "min_gain_pct": 0.5, "cell_mm": 0.4, "reach_radius_mm": 1, "tolerance_mm": 0.1}"#,
        );
        let spec: JobSpec = serde_json::from_str(&chosen).expect("parse");
        assert!(spec.reconstruct.as_ref().is_some_and(|r| r.face_choice.is_some()));
        assert_eq!(job_spec_from_pb(job_spec(&spec)).expect("back"), spec); // A robot job with every setting.
        let robot: JobSpec = serde_json::from_value(serde_json::json!({
            "name": "robot", "process": "robot",
            "input": {"kind": "mesh", "artifact": "a".repeat(64), "units": "in"},
            "robot": {"tool": "ball-6", "step_mm": 1.5, "radial_depth_mm": 2, "stock_margin_mm": 4,
                      "part_at_mm": [400, -20, 5], "part_yaw_deg": 30, "feed_mm_min": 900, "rpm": 15000,
                      "max_tilt_deg": 30, "spindle_length_mm": 120, "spindle_mount_deg": 45,
                      "spindle_diameter_mm": 50},
            "execute": {"cell_mm": 0.2}
        }))
        .expect("robot spec");
        assert_eq!(job_spec_from_pb(job_spec(&robot)).expect("back"), robot);
    }

    #[test]
    fn every_rest_metric_reaches_the_wire_under_its_name() {
        // Every metric the REST job's schema lists, set to a value of its own, read back from the
        // message's debug form by field name.
        use utoipa::PartialSchema;
        let utoipa::openapi::RefOr::T(utoipa::openapi::Schema::Object(schema)) = JobMetrics::schema() else {
            panic!("the metrics' schema is an object");
        };
        let names: Vec<String> = schema.properties.keys().cloned().collect();
        assert!(names.len() > 50, "{names:?}");
        let json: serde_json::Map<String, serde_json::Value> =
            names.iter().enumerate().map(|(i, n)| (n.clone(), serde_json::json!(i as f64 + 0.5))).collect();
        let m: JobMetrics = serde_json::from_value(serde_json::Value::Object(json)).expect("metrics");
        let wire = format!("{:?}", job_metrics(&m));
        for (i, n) in names.iter().enumerate() {
            let field = if n == "original_mean_leftover_mm" { "mean_leftover_mm" } else { n };
            let want = format!(" {field}: Some({}),", i as f64 + 0.5);
            assert!(
                wire.contains(&want) || wire.contains(&want.replace(',', " }")),
                "{n} is not on the wire: {wire}"
            );
        }
        assert!(!wire.contains("None"), "a wire field without a REST metric: {wire}");
    }

    #[test]
    fn the_material_named_once_is_used_by_both_stages() {
        let spec: JobSpec = serde_json::from_value(serde_json::json!({
            "input": {"kind": "mesh", "artifact": "a".repeat(64)},
            "execute": {"material": "wax"}
        }))
        .expect("spec");
        assert_eq!(plan_params_for_job(&spec).stock.and_then(|s| s.material).as_deref(), Some("wax"));
        let spec: JobSpec = serde_json::from_value(serde_json::json!({
            "input": {"kind": "mesh", "artifact": "a".repeat(64)},
            "plan": {"stock": {"material": "brass"}}
        }))
        .expect("spec");
        assert_eq!(execute_params_for_job(&spec).material.as_deref(), Some("brass"));
        assert_eq!(plan_params_for_job(&spec).stock.and_then(|s| s.material).as_deref(), Some("brass"));
    }

    #[test]
    fn a_fitted_map_is_finished_as_facets_unless_the_job_says_otherwise() {
        let model = |job: serde_json::Value| {
            let spec: JobSpec = serde_json::from_value(job).expect("spec");
            plan_params_for_job(&spec).finishing.and_then(|f| f.pixel_model)
        };
        let a = "a".repeat(64);
        for kind in ["mesh", "point_cloud"] {
            let facet = model(serde_json::json!({"input": {"kind": kind, "artifact": a}}));
            assert_eq!(facet.as_deref(), Some("facet"), "{kind}");
            let fit = serde_json::json!({"input": {"kind": kind, "artifact": a}, "reconstruct": {"estimator": "fit"}});
            assert_eq!(model(fit).as_deref(), Some("facet"), "{kind}");
            let max = serde_json::json!({"input": {"kind": kind, "artifact": a}, "reconstruct": {"estimator": "max"}});
            assert_eq!(model(max), None, "{kind}: the cam's own default, columns");
            let named = serde_json::json!({"input": {"kind": kind, "artifact": a},
                "plan": {"finishing": {"pixel_model": "point", "tool": "ball-2"}}});
            let spec: JobSpec = serde_json::from_value(named).expect("spec");
            let fin = plan_params_for_job(&spec).finishing.expect("finishing");
            assert_eq!((fin.pixel_model.as_deref(), fin.tool.as_deref()), (Some("point"), Some("ball-2")));
        }
        assert_eq!(model(serde_json::json!({"input": {"kind": "depth_map", "artifact": a}})), None);
    }

    #[test]
    fn missing_input_and_bad_enums_name_the_field() {
        assert_eq!(job_spec_from_pb(pb::JobSpec::default()).expect_err("input").field, "input");
        let bad = pb::JobSpec {
            input: Some(pb::JobInput { kind: 99, ..Default::default() }),
            ..Default::default()
        };
        assert_eq!(job_spec_from_pb(bad).expect_err("kind").field, "input.kind");
    }
}
