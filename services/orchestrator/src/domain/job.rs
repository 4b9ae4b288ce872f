//! Jobs, stages, statuses and stage outputs.

use std::collections::BTreeMap;

use depthmill_geometry::ArtifactRef;
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

use super::spec::JobSpec;

/// The stages of a scan-to-part run, in order. A job starts at the stage its input allows.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum Stage {
    /// Mesh -> point cloud (scanning service).
    Scan,
    /// Point cloud -> depth maps (reconstruction service).
    Reconstruct,
    /// Depth maps -> G-code (CAM service).
    Plan,
    /// G-code -> machined part (machine service).
    Execute,
    /// Everything -> the job's report (the orchestrator itself).
    Report,
}

impl Stage {
    /// Every stage, in order.
    pub const ALL: [Stage; 5] = [Stage::Scan, Stage::Reconstruct, Stage::Plan, Stage::Execute, Stage::Report];

    /// The wire name.
    pub fn as_str(self) -> &'static str {
        match self {
            Stage::Scan => "scan",
            Stage::Reconstruct => "reconstruct",
            Stage::Plan => "plan",
            Stage::Execute => "execute",
            Stage::Report => "report",
        }
    }

    /// The stage after this one, or `None` after the last.
    pub fn next(self) -> Option<Stage> {
        Self::ALL.iter().position(|s| *s == self).and_then(|i| Self::ALL.get(i + 1)).copied()
    }

    /// Position in [`Stage::ALL`].
    pub fn index(self) -> usize {
        Self::ALL.iter().position(|s| *s == self).unwrap_or(0)
    }
}

impl std::fmt::Display for Stage {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

impl std::str::FromStr for Stage {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Self::ALL.into_iter().find(|x| x.as_str() == s).ok_or_else(|| format!("unknown stage '{s}'"))
    }
}

/// Where a job is in its life.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum JobStatus {
    Queued,
    Running,
    Succeeded,
    Failed,
    Cancelled,
}

impl JobStatus {
    /// The wire name.
    pub fn as_str(self) -> &'static str {
        match self {
            JobStatus::Queued => "queued",
            JobStatus::Running => "running",
            JobStatus::Succeeded => "succeeded",
            JobStatus::Failed => "failed",
            JobStatus::Cancelled => "cancelled",
        }
    }

    /// True for succeeded, failed and cancelled: nothing will change any more.
    pub fn is_terminal(self) -> bool {
        matches!(self, JobStatus::Succeeded | JobStatus::Failed | JobStatus::Cancelled)
    }
}

impl std::fmt::Display for JobStatus {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

impl std::str::FromStr for JobStatus {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        [JobStatus::Queued, JobStatus::Running, JobStatus::Succeeded, JobStatus::Failed, JobStatus::Cancelled]
            .into_iter()
            .find(|x| x.as_str() == s)
            .ok_or_else(|| {
                format!("unknown status '{s}' (expected queued, running, succeeded, failed or cancelled)")
            })
    }
}

/// Why a job failed.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct JobError {
    /// `invalid_argument`, `stage_not_available`, `unavailable`, `deadline_exceeded`, `internal`, ...
    pub code: String,
    pub message: String,
    pub stage: Stage,
}

/// The measurements of the machined part and the run, as far as the job got.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct JobMetrics {
    #[serde(skip_serializing_if = "Option::is_none")]
    pub coverage_pct: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub max_gouge_mm: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub max_leftover_mm: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub rms_deviation_mm: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub cycle_time_s: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub cycle_time_no_adaptive_s: Option<f64>,
    /// Points of the scanned cloud.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub scan_points: Option<f64>,
    /// Simulated duration of the scan (table moves excluded), s.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub scan_time_s: Option<f64>,
    /// Footprint coverage of the scan at the rescan pixel, %.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub scan_coverage_pct: Option<f64>,
    /// RMS distance between where scanned points were placed and where they truly are, mm.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub scan_registration_rms_mm: Option<f64>,
    /// Part of the mesh's top-view silhouette the scan has points in, %.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub scan_silhouette_coverage_pct: Option<f64>,
    /// The registration error after the one rigid transform that best aligns the cloud with the
    /// truth (how well the views agree: the merge error), mm.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub scan_registration_merge_rms_mm: Option<f64>,
    /// Version of the cell calibration the scan's points were placed with (`GET /v1/calibrations`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub scan_calibration_version: Option<f64>,
    /// The machined part against the original part (a mesh job; measured by the report stage on
    /// the stock's grid): deepest gouge, mm.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub part_max_gouge_mm: Option<f64>,
    /// ... most material left, mm.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub part_max_leftover_mm: Option<f64>,
    /// ... mean of the material left (gouges count as 0), mm.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub part_mean_leftover_mm: Option<f64>,
    /// ... signed mean deviation (material left positive), mm.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub part_mean_mm: Option<f64>,
    /// ... RMS deviation, mm.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub part_rms_mm: Option<f64>,
    /// ... deepest gouge off the walls (cells within one depth-map pixel of a surface steeper than
    /// 75° or of the outline left out, where a wall a fraction of a pixel off reads as its height), mm.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub part_off_walls_max_gouge_mm: Option<f64>,
    /// ... signed mean deviation off the walls, mm.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub part_off_walls_mean_mm: Option<f64>,
    /// ... RMS deviation off the walls, mm.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub part_off_walls_rms_mm: Option<f64>,
    /// ... off the walls where the program's smallest tool reaches the part, against the part
    /// opened by that tool (the best surface it can leave): deepest gouge, mm.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub part_opened_max_gouge_mm: Option<f64>,
    /// ... signed mean deviation, mm.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub part_opened_mean_mm: Option<f64>,
    /// ... RMS deviation, mm.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub part_opened_rms_mm: Option<f64>,
    /// ... where the deepest of those gouges is: the centre of its cell in the depth map's
    /// frame, mm (only when there is a gouge).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub part_opened_max_gouge_x_mm: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub part_opened_max_gouge_y_mm: Option<f64>,
    /// The `part_opened_*` figures over the cells the scan measured (not filled nor lidded):
    /// deepest gouge, signed mean, RMS, mm.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub part_opened_measured_max_gouge_mm: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub part_opened_measured_mean_mm: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub part_opened_measured_rms_mm: Option<f64>,
    /// The machined part against the CAM's predicted surface (the part opened by the tools): RMS, mm.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub preview_rms_mm: Option<f64>,
    /// A multi-axis part measured on its one dexel stock against the original part (the input mesh sampled, or the input cloud): reference points
    /// measured (those a face looks at).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub original_points: Option<f64>,
    /// ... deepest gouge (distance into the part), mm.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub original_max_gouge_mm: Option<f64>,
    /// ... most material left over a point, mm.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub original_max_leftover_mm: Option<f64>,
    /// ... mean material left (gouges count as 0), mm.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub original_mean_leftover_mm: Option<f64>,
    /// ... RMS deviation, mm.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub original_rms_deviation_mm: Option<f64>,
    /// A multi-axis part measured on its one dexel stock against the original part opened by the program's smallest tool: reference points
    /// measured (those a face looks at).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub opened_points: Option<f64>,
    /// ... deepest gouge (distance into the part), mm.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub opened_max_gouge_mm: Option<f64>,
    /// ... most material left over a point, mm.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub opened_max_leftover_mm: Option<f64>,
    /// ... mean material left (gouges count as 0), mm.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub opened_mean_leftover_mm: Option<f64>,
    /// ... RMS deviation, mm.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub opened_rms_deviation_mm: Option<f64>,
    /// A multi-face part's stock seen from each face against that face's depth map, over every
    /// face (the headline `max_gouge_mm`, ... are then the original part's): deepest gouge, mm.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub map_max_gouge_mm: Option<f64>,
    /// ... most material left, mm.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub map_max_leftover_mm: Option<f64>,
    /// ... mean material left (gouges count as 0), mm.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub map_mean_leftover_mm: Option<f64>,
    /// ... RMS deviation, mm.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub map_rms_deviation_mm: Option<f64>,
    /// The CAM's estimate of the program's cycle time (a robot job: the arm's time), s.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub estimated_time_s: Option<f64>,
    /// The CAM's own sweep of the program over its stock model against the depth map (the part
    /// opened by the tools): deepest gouge, most material left and its mean, mm.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub plan_max_gouge_mm: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub plan_max_leftover_mm: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub plan_mean_leftover_mm: Option<f64>,
    /// Material the simulated mill removed, mm³.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub removed_mm3: Option<f64>,
    /// Cycle time under the other adaptive policy (feed-only when the job ran aco, and the
    /// reverse), s.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub cycle_time_other_policy_s: Option<f64>,
    /// A robot job (`"process": "robot"`): layers the mesh was sliced into.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub robot_layers: Option<f64>,
    /// ... tool positions checked against the mesh.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub robot_positions: Option<f64>,
    /// ... positions where the upright tool body (flutes, shank, holder, spindle) hits the part.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub robot_colliding_upright: Option<f64>,
    /// ... positions cleared by tilting the tool.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub robot_tilted: Option<f64>,
    /// ... positions no tilt clears (lifted over, left uncut).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub robot_blocked: Option<f64>,
    /// ... stretches of the path the arm cannot follow (reach, joint limits, singularities).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub robot_unreachable_stretches: Option<f64>,
    /// ... largest tilt of the tool from upright, degrees.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub robot_max_tilt_deg: Option<f64>,
    /// ... material the simulated run removed, mm³.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub robot_removed_mm3: Option<f64>,
    /// ... of it removed by rapid moves (a crash on a real cell), mm³.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub robot_rapid_removed_mm3: Option<f64>,
}

impl JobMetrics {
    /// Collects the known metric names from a stage's metric map.
    pub fn absorb(&mut self, metrics: &BTreeMap<String, f64>) {
        for (k, v) in metrics {
            let slot = match k.as_str() {
                "coverage_pct" => &mut self.coverage_pct,
                "max_gouge_mm" => &mut self.max_gouge_mm,
                "max_leftover_mm" => &mut self.max_leftover_mm,
                "rms_deviation_mm" => &mut self.rms_deviation_mm,
                "cycle_time_s" => &mut self.cycle_time_s,
                "cycle_time_no_adaptive_s" => &mut self.cycle_time_no_adaptive_s,
                "scan_points" => &mut self.scan_points,
                "scan_time_s" => &mut self.scan_time_s,
                "scan_coverage_pct" => &mut self.scan_coverage_pct,
                "scan_registration_rms_mm" => &mut self.scan_registration_rms_mm,
                "scan_silhouette_coverage_pct" => &mut self.scan_silhouette_coverage_pct,
                "scan_registration_merge_rms_mm" => &mut self.scan_registration_merge_rms_mm,
                "scan_calibration_version" => &mut self.scan_calibration_version,
                "part_max_gouge_mm" => &mut self.part_max_gouge_mm,
                "part_max_leftover_mm" => &mut self.part_max_leftover_mm,
                "part_mean_leftover_mm" => &mut self.part_mean_leftover_mm,
                "part_mean_mm" => &mut self.part_mean_mm,
                "part_rms_mm" => &mut self.part_rms_mm,
                "preview_rms_mm" => &mut self.preview_rms_mm,
                "part_off_walls_max_gouge_mm" => &mut self.part_off_walls_max_gouge_mm,
                "part_off_walls_mean_mm" => &mut self.part_off_walls_mean_mm,
                "part_off_walls_rms_mm" => &mut self.part_off_walls_rms_mm,
                "part_opened_max_gouge_mm" => &mut self.part_opened_max_gouge_mm,
                "part_opened_mean_mm" => &mut self.part_opened_mean_mm,
                "part_opened_rms_mm" => &mut self.part_opened_rms_mm,
                "part_opened_max_gouge_x_mm" => &mut self.part_opened_max_gouge_x_mm,
                "part_opened_max_gouge_y_mm" => &mut self.part_opened_max_gouge_y_mm,
                "part_opened_measured_max_gouge_mm" => &mut self.part_opened_measured_max_gouge_mm,
                "part_opened_measured_mean_mm" => &mut self.part_opened_measured_mean_mm,
                "part_opened_measured_rms_mm" => &mut self.part_opened_measured_rms_mm,
                "original_points" => &mut self.original_points,
                "original_max_gouge_mm" => &mut self.original_max_gouge_mm,
                "original_max_leftover_mm" => &mut self.original_max_leftover_mm,
                "original_mean_leftover_mm" => &mut self.original_mean_leftover_mm,
                "original_rms_deviation_mm" => &mut self.original_rms_deviation_mm,
                "opened_points" => &mut self.opened_points,
                "opened_max_gouge_mm" => &mut self.opened_max_gouge_mm,
                "opened_max_leftover_mm" => &mut self.opened_max_leftover_mm,
                "opened_mean_leftover_mm" => &mut self.opened_mean_leftover_mm,
                "opened_rms_deviation_mm" => &mut self.opened_rms_deviation_mm,
                "map_max_gouge_mm" => &mut self.map_max_gouge_mm,
                "map_max_leftover_mm" => &mut self.map_max_leftover_mm,
                "map_mean_leftover_mm" => &mut self.map_mean_leftover_mm,
                "map_rms_deviation_mm" => &mut self.map_rms_deviation_mm,
                "estimated_time_s" => &mut self.estimated_time_s,
                "plan_max_gouge_mm" => &mut self.plan_max_gouge_mm,
                "plan_max_leftover_mm" => &mut self.plan_max_leftover_mm,
                "plan_mean_leftover_mm" => &mut self.plan_mean_leftover_mm,
                "removed_mm3" => &mut self.removed_mm3,
                "cycle_time_other_policy_s" => &mut self.cycle_time_other_policy_s,
                "robot_layers" => &mut self.robot_layers,
                "robot_positions" => &mut self.robot_positions,
                "robot_colliding_upright" => &mut self.robot_colliding_upright,
                "robot_tilted" => &mut self.robot_tilted,
                "robot_blocked" => &mut self.robot_blocked,
                "robot_unreachable_stretches" => &mut self.robot_unreachable_stretches,
                "robot_max_tilt_deg" => &mut self.robot_max_tilt_deg,
                "robot_removed_mm3" => &mut self.robot_removed_mm3,
                "robot_rapid_removed_mm3" => &mut self.robot_rapid_removed_mm3,
                _ => continue,
            };
            *slot = Some(*v);
        }
    }
}

/// What one stage produced: named artifacts (`point_cloud`, `depth_map`, `gcode`, ...), metrics
/// and what the stage's service said about the part (diagnostics).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct StageOutputs {
    #[schema(value_type = BTreeMap<String, ArtifactRefSchema>)]
    pub artifacts: BTreeMap<String, ArtifactRef>,
    pub metrics: BTreeMap<String, f64>,
    /// In the order the service gave them; absent from results recorded before diagnostics were
    /// kept.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub diagnostics: Vec<StageDiagnostic>,
    /// A cell calibration the scan stage made on its way (stored apart by the worker, as the next
    /// calibration version; not part of the stored result).
    #[serde(skip)]
    pub calibration_made: Option<CalibrationMade>,
}

/// A cell calibration made by the scanning service during a job's scan: its parameters and its
/// fit report, the scanning service's JSON.
#[derive(Debug, Clone, PartialEq)]
pub struct CalibrationMade {
    pub calibration_json: String,
    pub report_json: String,
}

/// Most diagnostics one stage's result keeps; a service that says more is cut here, with a last
/// diagnostic saying how many were left out (the whole list stays in the stage's report artifact).
pub const MAX_STAGE_DIAGNOSTICS: usize = 200;

/// Longest message kept, in bytes (cut at a character boundary, with an ellipsis).
pub const MAX_DIAGNOSTIC_MESSAGE_BYTES: usize = 2000;

/// One thing a stage's service said about the part or the run: what could not be done and where,
/// what it chose and why (`code`: `tool_choice`, `material_left`, `unreachable_surface`,
/// `face_mostly_assumed`, `unseen_filled`, `units_warning`, ...).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
pub struct StageDiagnostic {
    pub code: String,
    pub message: String,
}

impl StageOutputs {
    /// Keeps a service's diagnostics, bounded by [`MAX_STAGE_DIAGNOSTICS`] and
    /// [`MAX_DIAGNOSTIC_MESSAGE_BYTES`] so one verbose stage cannot swell every read of the job.
    pub fn set_diagnostics(&mut self, diagnostics: impl IntoIterator<Item = (String, String)>) {
        let mut kept = Vec::new();
        let mut left_out = 0usize;
        for (code, message) in diagnostics {
            if kept.len() < MAX_STAGE_DIAGNOSTICS {
                kept.push(StageDiagnostic { code, message: cut(message, MAX_DIAGNOSTIC_MESSAGE_BYTES) });
            } else {
                left_out += 1;
            }
        }
        if left_out > 0 {
            kept.push(StageDiagnostic {
                code: "diagnostics_truncated".into(),
                message: format!(
                    "{left_out} more diagnostics left out after the first {MAX_STAGE_DIAGNOSTICS} (the stage's report has them all)"
                ),
            });
        }
        self.diagnostics = kept;
    }
}

/// `s` cut to at most `max` bytes at a character boundary, ending in "…" when cut.
fn cut(mut s: String, max: usize) -> String {
    if s.len() <= max {
        return s;
    }
    let mut end = max.saturating_sub('…'.len_utf8());
    while !s.is_char_boundary(end) {
        end -= 1;
    }
    s.truncate(end);
    s.push('…');
    s
}

/// A stage's diagnostic as the job shows it.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
pub struct JobDiagnostic {
    pub stage: Stage,
    pub code: String,
    pub message: String,
}

/// A reference to a stored artifact.
#[derive(ToSchema)]
#[allow(dead_code)]
pub struct ArtifactRefSchema {
    /// Where the blob can be read (file:// for the local store).
    uri: String,
    /// Lowercase hex sha256 of the bytes.
    sha256: String,
    size: u64,
    media_type: String,
}

/// A completed stage, recorded exactly once per job.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StageResult {
    pub stage: Stage,
    pub outputs: StageOutputs,
    pub started_at_ms: i64,
    pub finished_at_ms: i64,
}

/// How one attempt at a stage ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum AttemptOutcome {
    /// Still running (or the process died while it ran; see `interrupted`).
    Running,
    Ok,
    /// Failed with a transient error; another attempt follows.
    Retry,
    Failed,
    Cancelled,
    /// The orchestrator stopped (crash or restart) while the attempt ran.
    Interrupted,
}

impl AttemptOutcome {
    /// The wire name.
    pub fn as_str(self) -> &'static str {
        match self {
            AttemptOutcome::Running => "running",
            AttemptOutcome::Ok => "ok",
            AttemptOutcome::Retry => "retry",
            AttemptOutcome::Failed => "failed",
            AttemptOutcome::Cancelled => "cancelled",
            AttemptOutcome::Interrupted => "interrupted",
        }
    }
}

impl std::str::FromStr for AttemptOutcome {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        [
            AttemptOutcome::Running,
            AttemptOutcome::Ok,
            AttemptOutcome::Retry,
            AttemptOutcome::Failed,
            AttemptOutcome::Cancelled,
            AttemptOutcome::Interrupted,
        ]
        .into_iter()
        .find(|x| x.as_str() == s)
        .ok_or_else(|| format!("unknown attempt outcome '{s}'"))
    }
}

/// One call of a stage's service.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct AttemptRecord {
    pub stage: Stage,
    pub attempt: u32,
    pub started_at_ms: i64,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub finished_at_ms: Option<i64>,
    pub outcome: AttemptOutcome,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub error_code: Option<String>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub error_message: Option<String>,
}

/// A job as clients see it (`GET /v1/jobs/{id}`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct Job {
    pub id: String,
    pub name: String,
    pub status: JobStatus,
    /// The stage running now, the next to run, or (when the job ended) the last one reached.
    pub stage: Stage,
    /// 0.0 ..= 1.0 over the stages this job runs.
    pub progress: f64,
    pub error: Option<JobError>,
    /// Wall time of each completed stage.
    pub stage_timings_s: BTreeMap<String, f64>,
    /// Every artifact the job has: its input and what its stages produced.
    #[schema(value_type = BTreeMap<String, ArtifactRefSchema>)]
    pub artifacts: BTreeMap<String, ArtifactRef>,
    pub metrics: JobMetrics,
    /// What the completed stages' services said about the part and the run, in stage order:
    /// what could not be done and where (`material_left`, `unreachable_surface`, ...), what was
    /// chosen and why (`tool_choice`, `face_choice`, `units`).
    #[serde(default)]
    pub diagnostics: Vec<JobDiagnostic>,
    pub spec: JobSpec,
    pub cancel_requested: bool,
    /// Creation time, milliseconds since the Unix epoch.
    pub created_at_ms: i64,
    pub updated_at_ms: i64,
    /// Every call of a stage's service, in order.
    pub attempts: Vec<AttemptRecord>,
}

/// Overall progress of a job that started at `first` and is in `stage` with `fraction` of it done.
pub fn overall_progress(first: Stage, stage: Stage, fraction: f64) -> f64 {
    let total = (Stage::Report.index() - first.index() + 1) as f64;
    let done = stage.index().saturating_sub(first.index()) as f64;
    ((done + fraction.clamp(0.0, 1.0)) / total).clamp(0.0, 1.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stages_run_in_order_and_progress_spans_only_the_job_s_stages() {
        assert_eq!(Stage::Scan.next(), Some(Stage::Reconstruct));
        assert_eq!(Stage::Report.next(), None);
        assert_eq!(overall_progress(Stage::Execute, Stage::Execute, 0.0), 0.0);
        assert_eq!(overall_progress(Stage::Execute, Stage::Report, 0.0), 0.5);
        assert_eq!(overall_progress(Stage::Scan, Stage::Report, 1.0), 1.0);
        for s in Stage::ALL {
            assert_eq!(s.as_str().parse::<Stage>(), Ok(s));
        }
    }

    #[test]
    fn a_stage_keeps_a_bounded_number_of_bounded_diagnostics() {
        let mut out = StageOutputs::default();
        let long = "é".repeat(MAX_DIAGNOSTIC_MESSAGE_BYTES);
        out.set_diagnostics(
            (0..MAX_STAGE_DIAGNOSTICS + 5)
                .map(|i| ("c".to_string(), if i == 0 { long.clone() } else { i.to_string() })),
        );
        assert_eq!(out.diagnostics.len(), MAX_STAGE_DIAGNOSTICS + 1);
        let first = &out.diagnostics[0].message;
        assert!(first.len() <= MAX_DIAGNOSTIC_MESSAGE_BYTES && first.ends_with('…'), "{}", first.len());
        assert_eq!(out.diagnostics[1].message, "1");
        let last = &out.diagnostics[MAX_STAGE_DIAGNOSTICS];
        assert_eq!(last.code, "diagnostics_truncated");
        assert!(last.message.starts_with("5 more"), "{}", last.message);
        // A result stored before diagnostics were kept still reads, and an empty list is not written.
        let old: StageOutputs =
            serde_json::from_str(r#"{"artifacts": {}, "metrics": {"x": 1.0}}"#).expect("an old result");
        assert!(old.diagnostics.is_empty());
        assert!(!serde_json::to_string(&old).expect("json").contains("diagnostics"));
    }
}
