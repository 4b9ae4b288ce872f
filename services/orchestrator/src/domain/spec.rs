//! The job request (`POST /v1/jobs` body), its validation and documented defaults.
//!
//! Every struct denies unknown fields, so a misspelt parameter is an error that names it, never a
//! silently ignored setting. Sections a job never reaches (a `scan` section on a job that starts
//! from a depth map) are rejected the same way. Defaults are applied by the stage services; they
//! are documented here so the OpenAPI document shows them.
//!
//! [`JobSpec::validate`] checks what the job model itself knows (shape, ranges of the plan and
//! execute sections, sections a job never reaches). The `scan` and `reconstruct` sections are
//! checked by the services that own them (`ValidateParams` on the scanning and reconstruction
//! services), which the orchestrator asks before it accepts a job; this crate imports no stage
//! service's code.

use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

use super::job::Stage;

/// A job request. Every section but `input` is optional.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct JobSpec {
    /// A name for people; need not be unique.
    #[serde(default)]
    pub name: String,
    pub input: JobInput,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub scan: Option<ScanParams>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub reconstruct: Option<ReconstructParams>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub plan: Option<PlanParams>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub execute: Option<ExecuteParams>,
    /// How the part is made (default `mill`): `robot` cuts a mesh input layer by layer with the
    /// 6-axis arm holding a spindle (plan, execute and report stages; no scan).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub process: Option<Process>,
    /// Robot milling settings (`"process": "robot"` only).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub robot: Option<RobotParams>,
}

/// Smallest dexel cell of a robot job's simulation, mm (the machine service's limit).
pub const ROBOT_MIN_CELL_MM: f64 = 0.01;

/// How the part is made.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum Process {
    /// Scan (a mesh input), reconstruct depth maps, plan and run a program on the mill.
    Mill,
    /// From a mesh: sliced into layers, each cut ring by ring from the stock in to the part by the
    /// 6-axis arm with a spindle on its flange; the tool body checked against the mesh at every
    /// position and tilted where the upright tool collides; the joint trajectory replayed on a
    /// dexel stock and the part measured against the mesh.
    Robot,
}

/// Robot milling settings (README "Robot milling"). Defaults: tool `flat-6`, layers 2 mm apart
/// (at most the tool's flute length), radial depth the tool's radius, 5 mm of stock around the
/// part, the part's box centred 420 mm in front of the robot's base with its bottom at Z 0, feed
/// 600 mm/min, 12000 rpm, tilt up to 40°, a 150 mm x 60 mm spindle mounted at 90° across the
/// flange.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct RobotParams {
    /// Library tool name.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tool: Option<String>,
    /// Distance between layers, mm.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub step_mm: Option<f64>,
    /// Radial depth of cut between rings, mm.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub radial_depth_mm: Option<f64>,
    /// Stock around the part in X and Y, mm.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stock_margin_mm: Option<f64>,
    /// Where the part's origin stands in the robot's base frame, `[x, y, z]` mm.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub part_at_mm: Option<[f64; 3]>,
    /// The part's turn about the base's Z axis, degrees.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub part_yaw_deg: Option<f64>,
    /// Feed, mm/min.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub feed_mm_min: Option<f64>,
    /// Spindle speed, rpm.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rpm: Option<f64>,
    /// Largest tilt of the tool from upright, degrees (0 to 80).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max_tilt_deg: Option<f64>,
    /// Flange to spindle nose, mm.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub spindle_length_mm: Option<f64>,
    /// Angle between the flange's axis and the spindle's, degrees (0 to 90).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub spindle_mount_deg: Option<f64>,
    /// Spindle body diameter, mm (checked against the part like the holder).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub spindle_diameter_mm: Option<f64>,
}

/// What the job starts from. The kind decides the first stage.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct JobInput {
    pub kind: InputKind,
    /// sha256 of an artifact uploaded with `POST /v1/artifacts`.
    pub artifact: String,
    /// Pixel size of a depth image without depthmill metadata.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pixel_mm: Option<f64>,
    /// Z of black in a depth image without depthmill metadata.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub z_min_mm: Option<f64>,
    /// Z of white in a depth image without depthmill metadata.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub z_max_mm: Option<f64>,
    /// Length unit of a mesh or point-cloud input (default `auto`: a unit named in the file's
    /// header, else metres for a model under 2 units across, else millimetres; inches must be
    /// given or named in the header). The stage's report says what was decided and why.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub units: Option<InputUnits>,
}

/// Length unit of an input file.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
pub enum InputUnits {
    /// Decide from the header and the size.
    #[serde(rename = "auto")]
    Auto,
    /// Millimetres.
    #[serde(rename = "mm")]
    Mm,
    /// Metres.
    #[serde(rename = "m")]
    M,
    /// Inches.
    #[serde(rename = "in")]
    In,
}

/// The kind of a job's input.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum InputKind {
    /// STL mesh of the part: the job starts with a simulated scan.
    Mesh,
    /// XYZ or PLY point cloud: the job starts with reconstruction.
    PointCloud,
    /// 8/16-bit PNG or `.npy` depth map: the job starts with planning.
    DepthMap,
    /// G-code program: the job starts with execution.
    Gcode,
}

impl InputKind {
    /// The stage a job with this input starts at.
    pub fn first_stage(self) -> Stage {
        match self {
            InputKind::Mesh => Stage::Scan,
            InputKind::PointCloud => Stage::Reconstruct,
            InputKind::DepthMap => Stage::Plan,
            InputKind::Gcode => Stage::Execute,
        }
    }

    /// The wire name.
    pub fn as_str(self) -> &'static str {
        match self {
            InputKind::Mesh => "mesh",
            InputKind::PointCloud => "point_cloud",
            InputKind::DepthMap => "depth_map",
            InputKind::Gcode => "gcode",
        }
    }

    /// Media types an input of this kind may have.
    pub fn media_types(self) -> &'static [&'static str] {
        match self {
            InputKind::Mesh => &["model/stl", "application/x-ply", "model/obj", "model/x-off"],
            InputKind::PointCloud => &[
                "text/x-xyz",
                "application/x-ply",
                "application/x-pcd",
                "model/obj",
                "application/octet-stream",
            ],
            InputKind::DepthMap => &["image/png", "application/x-npy"],
            InputKind::Gcode => &["text/x-gcode"],
        }
    }
}

/// Scan stage parameters (the scanning library's `ScanOptions`; README "Scan options"). Defaults:
/// dynamic mode, table angles 0/90/180/270, standoff 150 mm, 100 lines/s, 0.25 mm between lines,
/// 30 % pass overlap, latch latency compensated, no adaptive rescan.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct ScanParams {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mode: Option<ScanMode>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub table_angles_deg: Option<Vec<f64>>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub standoff_mm: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub line_rate_hz: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub adaptive_rescan: Option<bool>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub line_spacing_mm: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub overlap: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub margin_mm: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tilt_deg: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stop_and_move_rate_hz: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub latch_latency_s: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub latch_jitter_s: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub compensate_latency: Option<bool>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rescan_pixel_mm: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rescan_standoff_mm: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub seed: Option<u64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max_frames: Option<u64>,
    /// Given passes instead of the automatic plan.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub passes: Option<Vec<ScanPassSpec>>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub obstacle_clearance_mm: Option<f64>,
    /// The table as the seventh joint: how far an automatic pass's table angle may turn from its
    /// station's for a better arm posture, degrees (default 30; 0 keeps the angles as asked).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub table_search_deg: Option<f64>,
    /// Obstacles besides the table and the part, world frame: `{"shape": "box", "name",
    /// "min_mm", "max_mm"}`, `{"shape": "cylinder", "name", "center_mm": [x, y], "radius_mm",
    /// "z_min_mm", "z_max_mm"}` or `{"shape": "sphere", "name", "center_mm", "radius_mm"}`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schema(value_type = Option<Vec<Object>>)]
    pub obstacles: Option<Vec<Obstacle>>,
}

/// An obstacle in the world frame (the robot's base), mm: the JSON form of the wire's
/// `ScanObstacle`. The scanning service checks the values.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "shape", rename_all = "snake_case", deny_unknown_fields)]
pub enum Obstacle {
    /// An axis-aligned box.
    Box { name: String, min_mm: [f64; 3], max_mm: [f64; 3] },
    /// A cylinder with a vertical axis through `center_mm` (x, y).
    Cylinder { name: String, center_mm: [f64; 2], radius_mm: f64, z_min_mm: f64, z_max_mm: f64 },
    /// A sphere.
    Sphere { name: String, center_mm: [f64; 3], radius_mm: f64 },
}

/// A straight sensor path in the part frame at one table angle.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct ScanPassSpec {
    pub table_deg: f64,
    pub start_mm: [f64; 3],
    pub end_mm: [f64; 3],
}

/// How the robot and table move while scanning.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum ScanMode {
    Dynamic,
    StopAndMove,
}

/// Reconstruct stage parameters. Defaults: pixel 0.1 mm, one face `+Z`, IDW fill (power 2) of
/// holes up to 2 mm, region of interest = the points' extent plus 2 pixels, Z range from robust
/// quantiles of the data, statistical outlier removal (k 12, 3 σ) when `filters` is absent,
/// roughing lattice of 4 pixels.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct ReconstructParams {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pixel_mm: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub faces: Option<Vec<FaceSpec>>,
    /// Choose the faces from the shape instead of naming them (not with `faces`): the fewest
    /// orientations about the machine's A axis from which a tool of `reach_radius_mm` reaches the
    /// surface; the reconstruct report's `face_choice` gives what each face adds and where no
    /// orientation reaches. `{}` takes every default.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub face_choice: Option<FaceChoice>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fill: Option<FillParams>,
    /// Region of interest in the face frame (default: the points' extent plus `margin_mm`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub roi: Option<Roi>,
    /// Margin around the points' extent (default 2 pixels).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub margin_mm: Option<f64>,
    /// Z of black in the depth image (default: robust low quantile of the data).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub z_min_mm: Option<f64>,
    /// Z of white in the depth image (default: robust high quantile of the data).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub z_max_mm: Option<f64>,
    /// Clean-up filters; when given, exactly the filters named run.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub filters: Option<Filters>,
    /// Lattice of the continuous roughing map, in pixels (default 4).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub roughing_factor: Option<u32>,
    /// How a cell's points make the depth map (default `fit`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub estimator: Option<CellEstimator>,
}

/// How faces are chosen from the shape (every field optional).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct FaceChoice {
    /// Angle between candidate orientations about the A axis, degrees (default 15).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub step_deg: Option<f64>,
    /// Most faces, 1 to 8 (default 4).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max_faces: Option<u32>,
    /// Least share of the surface a face must add, percent (default 1).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub min_gain_pct: Option<f64>,
    /// Surface sampling cell, mm (default 0.5).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cell_mm: Option<f64>,
    /// Radius of the smallest tool that must reach, mm (default 1.5, the default finishing
    /// tool's); a pocket narrower than about twice it is not reached.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub reach_radius_mm: Option<f64>,
    /// Height tolerance of the reach test, mm (default 0.2).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tolerance_mm: Option<f64>,
}

/// How the points of a cell make its height in the depth map, the finishing target.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum CellEstimator {
    /// The highest point: never below the measured surface, but about two standard deviations of
    /// the scanner's noise above it.
    Max,
    /// The median point: unbiased under symmetric noise; the roughing map still comes from the max.
    Median,
    /// The median, then an edge-preserving average of the neighbouring cells (a bilateral filter,
    /// σ one pixel across and 0.1 mm in height): the noise averaged down, steps and walls kept.
    MedianBilateral,
    /// A robust local quadric fit of a few hundred points around each cell: the noise averaged an
    /// order of magnitude down, curved surfaces kept, steps and convex edges kept.
    Fit,
}

/// A face to cut from above: exactly one of a named view, an angle about the machine's A axis,
/// or an outward normal (optionally with a point of the face put at the frame's origin).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct FaceSpec {
    /// `+Z`, `-Z`, `+X`, `-X`, `+Y` or `-Y`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub view: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub a_deg: Option<f64>,
    /// Outward normal `[x, y, z]` in the part frame.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub normal: Option<[f64; 3]>,
    /// With `normal`: a point of the face, mm, that becomes the face frame's origin.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub origin: Option<[f64; 3]>,
}

/// How holes in the raw depth map are filled: only holes enclosed by data, up to `max_hole_mm`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct FillParams {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub method: Option<FillMethod>,
    /// Largest hole filled, mm across (default 2; 0 disables filling).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max_hole_mm: Option<f64>,
    /// Neighbourhood searched for values, mm (default derived from `max_hole_mm`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub radius_mm: Option<f64>,
    /// IDW weight exponent (default 2).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub power: Option<f64>,
}

/// Region of interest in the face frame, mm.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct Roi {
    pub x_min_mm: f64,
    pub y_min_mm: f64,
    pub x_max_mm: f64,
    pub y_max_mm: f64,
}

/// Clean-up filters, applied in this order: transform, table, intensity, voxel, statistical,
/// radius.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct Filters {
    /// Keep points whose intensity lies in `[min, max]`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub intensity: Option<IntensityWindow>,
    /// Voxel-grid decimation: per voxel the point nearest the centroid.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub voxel_mm: Option<f64>,
    /// Statistical outlier removal.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub statistical: Option<StatisticalFilter>,
    /// Radius outlier removal.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub radius: Option<RadiusFilter>,
    /// Rigid transform applied first: a row-major 4x4 matrix.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub transform: Option<[[f64; 4]; 4]>,
    /// The table the part stood on, found in the cloud and made the XY plane (`{}` for the
    /// defaults): for a range scan in its sensor's frame.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub table: Option<TableFilter>,
}

/// Finds the table in the cloud (the plane most points lie within `tolerance_mm` of), turns the
/// cloud to stand on it at z = 0, removes the table and what lies under it and, unless
/// `largest_only` is false, keeps only the largest group of points above it (points more than
/// `gap_mm`, at most twice that, apart make separate groups). The reconstruct report's `table`
/// gives the plane, the counts and the transform applied.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct TableFilter {
    /// mm, default 1.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tolerance_mm: Option<f64>,
    /// Default true.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub largest_only: Option<bool>,
    /// mm, default 3.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub gap_mm: Option<f64>,
}

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct IntensityWindow {
    pub min: f32,
    pub max: f32,
}

/// Removes points whose mean distance to their `k` nearest neighbours exceeds the mean of that
/// distance over the cloud by more than `n_sigma` standard deviations (Open3D's
/// `remove_statistical_outlier`). With `keep_surface`, a point so flagged is kept when it lies on
/// the surface its `k` nearest neighbours sample (close together and flat around it, on their
/// plane within four times their scatter, among them): a wall or a pass the scanner sampled sparsely, not a stray point.
/// The default filters (a job without `filters`) are `k` 12, `n_sigma` 3, `keep_surface` true.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct StatisticalFilter {
    pub k: usize,
    pub n_sigma: f64,
    /// Keep flagged points on a sparsely sampled surface (default false: Open3D's rule alone).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub keep_surface: bool,
}

/// Removes points with fewer than `min_neighbours` other points within `radius_mm`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct RadiusFilter {
    pub radius_mm: f64,
    pub min_neighbours: usize,
}

/// Hole filling method.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum FillMethod {
    /// Inverse-distance-weighted mean of the neighbours.
    Idw,
    /// Highest neighbour.
    Max,
}

/// Plan stage parameters.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct PlanParams {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stock: Option<Stock>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub roughing: Option<Roughing>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub finishing: Option<Finishing>,
    /// G-code dialect. Default `linuxcnc`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub dialect: Option<Dialect>,
    /// Rest finishing: a smaller ball where the finishing tool left material on the simulated
    /// stock (off unless `enabled`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rest: Option<Rest>,
}

/// Rest finishing after the finishing pass.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct Rest {
    /// `true`: a rest pass wherever it removes something (default `false`, see the README).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub enabled: Option<bool>,
    /// The rest tool (default: the library's largest ball smaller than the finishing tool).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tool: Option<String>,
    /// Least leftover the rest pass goes after, mm (default 0.05).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub min_leftover_mm: Option<f64>,
}

/// The raw block. Default: the depth map's extent and Z range, aluminium.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct Stock {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub x_mm: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub y_mm: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub z_mm: Option<f64>,
    /// `aluminium`, `brass`, `mild_steel`, ... (default: `execute.material`, else aluminium).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub material: Option<String>,
}

/// Roughing. Defaults: `flat-6`, 2 mm step-down, 0.3 mm stock to leave, raster along X.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct Roughing {
    /// `flat-D`, `ball-D`, `bull-D-R`, `v-D-ANGLE` (D diameter in mm) or a tool library name.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tool: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub step_down_mm: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stock_to_leave_mm: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub direction: Option<RoughingDirection>,
}

/// Roughing clearing pattern.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum RoughingDirection {
    X,
    Y,
    Contour,
}

/// Finishing. Defaults: `ball-3`, raster along X, step-over 0.3 mm, tolerance 0.01 mm, arcs on.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct Finishing {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tool: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub strategy: Option<FinishingStrategy>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub angle_deg: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub step_over_mm: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tolerance_mm: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub arcs: Option<bool>,
    /// What a depth-map cell means to the finishing tool: `column` (a square column at its
    /// height; on a slope the tool stands off by up to the slope times half a pixel) or `point`
    /// (a sample of a continuous surface at the cell's centre) or `facet` (a sample of a
    /// piecewise-linear surface through the centres that stands above the convex edges between
    /// them and extends a step's top half a pixel flat). Default: `facet` for the depth maps a
    /// job reconstructs with the `fit` estimator (the best estimate of the surface, read as
    /// one), `column` otherwise (an uploaded depth map, or one made with `max`, whose cells
    /// stand at their highest point).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pixel_model: Option<String>,
}

/// Finishing strategy.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum FinishingStrategy {
    RasterX,
    RasterY,
    RasterAngle,
    IsoLevel,
}

/// G-code dialect.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum Dialect {
    Linuxcnc,
    Fanuc,
}

/// Execute stage parameters. Defaults: machine `emco-f1`, adaptive `aco`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct ExecuteParams {
    /// Machine profile (default `emco-f1`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub machine: Option<String>,
    /// Feed/speed policy (default `aco`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub adaptive: Option<AdaptiveMode>,
    /// Work material (default: the plan's stock material, else aluminium).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub material: Option<String>,
    /// Stock height above the depth map's z_min (default: the plan's stock height, else up to the highest point).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stock_z_mm: Option<f64>,
    /// Cell of the simulated stock, mm: the Z-map, and every dexel grid unless `dexel` sets them (default: the depth map's pixel, at most 0.1).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cell_mm: Option<f64>,
    /// Clamp F and S to the machine's ranges with a warning instead of refusing the program.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub clamp: Option<bool>,
    /// Also time the program without adaptation and with the other policy (default true).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub compare: Option<bool>,
    /// Cell sizes of the dexel grids a multi-axis part is cut on (default: every grid at
    /// `cell_mm`); a grid left out is not kept when another is given.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub dexel: Option<DexelCells>,
}

/// The dexel grids, by the axis their rays run along (part frame), mm.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct DexelCells {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub x_cell_mm: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub y_cell_mm: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub z_cell_mm: Option<f64>,
}

/// Adaptive feed/speed control while cutting.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum AdaptiveMode {
    /// Feed and spindle speed both adapt.
    Aco,
    FeedOnly,
    Off,
}

/// A job request that is well-formed JSON but asks for something invalid.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{field}: {message}")]
pub struct SpecError {
    /// Dotted path of the offending field, e.g. `plan.finishing.step_over_mm`.
    pub field: String,
    pub message: String,
}

/// A job request that is not one: malformed JSON, an unknown field or a value of the wrong type.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{message}")]
pub struct JsonError {
    /// Dotted path of the offending field, when there is one.
    pub field: Option<String>,
    /// What is wrong, starting with `malformed JSON` or `invalid job` and naming the field.
    pub message: String,
}

fn err(field: &str, message: impl Into<String>) -> SpecError {
    SpecError { field: field.to_string(), message: message.into() }
}

fn positive(field: &str, v: Option<f64>, max: f64) -> Result<(), SpecError> {
    match v {
        Some(x) if !x.is_finite() || x <= 0.0 => {
            Err(err(field, format!("must be a positive number, got {x}")))
        }
        Some(x) if x > max => Err(err(field, format!("{x} is above the limit of {max}"))),
        _ => Ok(()),
    }
}

fn non_negative(field: &str, v: Option<f64>, max: f64) -> Result<(), SpecError> {
    match v {
        Some(x) if !x.is_finite() || x < 0.0 => Err(err(field, format!("must be zero or positive, got {x}"))),
        Some(x) if x > max => Err(err(field, format!("{x} is above the limit of {max}"))),
        _ => Ok(()),
    }
}

fn finite(field: &str, v: Option<f64>) -> Result<(), SpecError> {
    match v {
        Some(x) if !x.is_finite() => Err(err(field, format!("must be a finite number, got {x}"))),
        _ => Ok(()),
    }
}

fn tool_name(field: &str, v: Option<&String>) -> Result<(), SpecError> {
    match v {
        Some(t) if t.trim().is_empty() => Err(err(field, "must name a tool, e.g. ball-3 or flat-6")),
        Some(t) if t.len() > 128 => {
            Err(err(field, format!("tool name is {} characters, the limit is 128", t.len())))
        }
        _ => Ok(()),
    }
}

impl JobSpec {
    /// Parses a job request (JSON), naming the offending field of any error. The values are
    /// checked by [`JobSpec::validate`].
    pub fn from_json(body: &[u8]) -> Result<JobSpec, JsonError> {
        let de = &mut serde_json::Deserializer::from_slice(body);
        serde_path_to_error::deserialize::<_, JobSpec>(de).map_err(|e| {
            let path = e.path().to_string();
            let inner = e.inner();
            let message = inner.to_string();
            // The path ends at the unknown field itself; at the top level serde names it only in
            // the message.
            let field = match message.strip_prefix("unknown field `").and_then(|r| r.split('`').next()) {
                Some(unknown) if path == "." => unknown.to_string(),
                _ if path == "." => String::new(),
                _ => path,
            };
            let what = if inner.is_syntax() || inner.is_eof() { "malformed JSON" } else { "invalid job" };
            let text = if field.is_empty() {
                format!("{what}: {message}")
            } else {
                format!("{what}: {field}: {message}")
            };
            JsonError { field: (!field.is_empty()).then_some(field), message: text }
        })
    }

    /// The stage this job starts at: a robot job plans from its mesh, other jobs start where
    /// their input kind does.
    pub fn first_stage(&self) -> Stage {
        if self.is_robot() { Stage::Plan } else { self.input.kind.first_stage() }
    }

    /// Whether the plan's depth maps come from this job's reconstruction with the `fit`
    /// estimator (its default): a mesh or point-cloud input on the mill.
    pub fn plans_a_fitted_map(&self) -> bool {
        !self.is_robot()
            && matches!(self.input.kind, InputKind::Mesh | InputKind::PointCloud)
            && matches!(self.reconstruct.as_ref().and_then(|r| r.estimator), None | Some(CellEstimator::Fit))
    }

    /// A robot milling job (`"process": "robot"`).
    pub fn is_robot(&self) -> bool {
        self.process == Some(Process::Robot)
    }

    /// The robot job's rules: a mesh input, no scan, reconstruct or plan section (the robot
    /// section plans), of `execute` only the dexel cell; and no robot section on a mill job.
    fn validate_process(&self) -> Result<(), SpecError> {
        if !self.is_robot() {
            if self.robot.is_some() {
                return Err(err("robot", "applies only to a job with \"process\": \"robot\""));
            }
            return Ok(());
        }
        if self.input.kind != InputKind::Mesh {
            return Err(err(
                "process",
                format!(
                    "a robot job cuts the part from its mesh: input.kind must be mesh, got {}",
                    self.input.kind.as_str()
                ),
            ));
        }
        for (field, present) in [
            ("scan", self.scan.is_some()),
            ("reconstruct", self.reconstruct.is_some()),
            ("plan", self.plan.is_some()),
        ] {
            if present {
                return Err(err(
                    field,
                    "a robot job plans from the mesh with its robot section and never runs this stage: remove this section",
                ));
            }
        }
        if let Some(ex) = &self.execute {
            let given = [
                ("execute.machine", ex.machine.is_some()),
                ("execute.adaptive", ex.adaptive.is_some()),
                ("execute.material", ex.material.is_some()),
                ("execute.stock_z_mm", ex.stock_z_mm.is_some()),
                ("execute.clamp", ex.clamp.is_some()),
                ("execute.compare", ex.compare.is_some()),
                ("execute.dexel", ex.dexel.is_some()),
            ];
            if let Some((field, _)) = given.iter().find(|(_, p)| *p) {
                return Err(err(
                    field,
                    "a robot job runs on the robot cell's dexel simulation: only execute.cell_mm applies",
                ));
            }
            if let Some(c) = ex.cell_mm
                && c.is_finite()
                && c < ROBOT_MIN_CELL_MM
            {
                return Err(err(
                    "execute.cell_mm",
                    format!("a robot job's dexel cell must be at least {ROBOT_MIN_CELL_MM} mm, got {c}"),
                ));
            }
        }
        Ok(())
    }

    /// Checks values and that every section given is one the job will run.
    /// Returns the first problem found, naming its field.
    pub fn validate(&self) -> Result<(), SpecError> {
        if self.name.len() > 256 {
            return Err(err("name", format!("is {} characters, the limit is 256", self.name.len())));
        }
        self.validate_process()?;
        let first = self.first_stage();
        let sections = [
            ("scan", Stage::Scan, self.scan.is_some()),
            ("reconstruct", Stage::Reconstruct, self.reconstruct.is_some()),
            ("plan", Stage::Plan, self.plan.is_some()),
            ("execute", Stage::Execute, self.execute.is_some()),
        ];
        for (field, stage, present) in sections {
            if present && stage < first {
                return Err(err(
                    field,
                    format!(
                        "a job whose input is a {} starts at the {first} stage and never runs {stage}: remove this section",
                        self.input.kind.as_str()
                    ),
                ));
            }
        }
        let input = &self.input;
        if !depthmill_geometry::artifact::is_sha256_hex(&input.artifact) {
            return Err(err(
                "input.artifact",
                "must be the sha256 (64 lowercase hex digits) of an uploaded artifact",
            ));
        }
        positive("input.pixel_mm", input.pixel_mm, 100.0)?;
        finite("input.z_min_mm", input.z_min_mm)?;
        finite("input.z_max_mm", input.z_max_mm)?;
        if (input.pixel_mm.is_some() || input.z_min_mm.is_some() || input.z_max_mm.is_some())
            && input.kind != InputKind::DepthMap
        {
            return Err(err("input.pixel_mm", "pixel size and Z range are for depth-map inputs only"));
        }
        if input.units.is_some() && !matches!(input.kind, InputKind::Mesh | InputKind::PointCloud) {
            return Err(err(
                "input.units",
                format!(
                    "units are for mesh and point_cloud inputs; a {} input is in millimetres",
                    input.kind.as_str()
                ),
            ));
        }
        if let (Some(lo), Some(hi)) = (input.z_min_mm, input.z_max_mm)
            && lo >= hi
        {
            return Err(err("input.z_max_mm", format!("must be above z_min_mm ({lo}), got {hi}")));
        }
        if let Some(ex) = &self.execute {
            positive("execute.stock_z_mm", ex.stock_z_mm, 10_000.0)?;
            positive("execute.cell_mm", ex.cell_mm, 10.0)?;
            if let Some(d) = &ex.dexel {
                positive("execute.dexel.x_cell_mm", d.x_cell_mm, 10.0)?;
                positive("execute.dexel.y_cell_mm", d.y_cell_mm, 10.0)?;
                positive("execute.dexel.z_cell_mm", d.z_cell_mm, 10.0)?;
                if d.x_cell_mm.is_none() && d.y_cell_mm.is_none() && d.z_cell_mm.is_none() {
                    return Err(err(
                        "execute.dexel",
                        "must set at least one of x_cell_mm, y_cell_mm, z_cell_mm",
                    ));
                }
            }
            if let Some(c) = ex.cell_mm
                && c < 0.005
            {
                return Err(err("execute.cell_mm", format!("must be at least 0.005 mm, got {c}")));
            }
        }
        if let Some(plan) = &self.plan {
            if let Some(stock) = &plan.stock {
                positive("plan.stock.x_mm", stock.x_mm, 10_000.0)?;
                positive("plan.stock.y_mm", stock.y_mm, 10_000.0)?;
                positive("plan.stock.z_mm", stock.z_mm, 10_000.0)?;
                if let Some(m) = &stock.material
                    && (m.trim().is_empty() || m.len() > 64)
                {
                    return Err(err("plan.stock.material", "must name a material, e.g. aluminium"));
                }
            }
            if let Some(r) = &plan.roughing {
                tool_name("plan.roughing.tool", r.tool.as_ref())?;
                positive("plan.roughing.step_down_mm", r.step_down_mm, 100.0)?;
                non_negative("plan.roughing.stock_to_leave_mm", r.stock_to_leave_mm, 100.0)?;
            }
            if let Some(f) = &plan.finishing {
                tool_name("plan.finishing.tool", f.tool.as_ref())?;
                finite("plan.finishing.angle_deg", f.angle_deg)?;
                if f.angle_deg.is_some() && f.strategy != Some(FinishingStrategy::RasterAngle) {
                    return Err(err("plan.finishing.angle_deg", "applies only to strategy raster_angle"));
                }
                positive("plan.finishing.step_over_mm", f.step_over_mm, 100.0)?;
                positive("plan.finishing.tolerance_mm", f.tolerance_mm, 10.0)?;
            }
        }
        if let Some(exec) = &self.execute
            && let Some(m) = &exec.machine
            && (m.trim().is_empty() || m.len() > 64)
        {
            return Err(err("execute.machine", "must name a machine profile, e.g. emco-f1"));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(json: &str) -> Result<JobSpec, String> {
        let de = &mut serde_json::Deserializer::from_str(json);
        serde_path_to_error::deserialize(de).map_err(|e| format!("{}: {}", e.path(), e.inner()))
    }

    const SHA: &str = "aaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaa";

    #[test]
    fn the_design_example_parses_and_validates() {
        let json = format!(
            r#"{{"name": "bracket",
                "input": {{"kind": "mesh", "artifact": "{SHA}"}},
                "scan": {{"mode": "dynamic", "table_angles_deg": [0, 90, 180, 270], "standoff_mm": 150,
                          "line_rate_hz": 100, "adaptive_rescan": true}},
                "reconstruct": {{"pixel_mm": 0.1, "faces": [{{"view": "+Z"}}], "fill": {{"method": "idw", "max_hole_mm": 2.0}}}},
                "plan": {{"stock": {{"x_mm": 100, "y_mm": 80, "z_mm": 25, "material": "aluminium"}},
                         "roughing": {{"tool": "flat-6", "step_down_mm": 2.0, "stock_to_leave_mm": 0.3, "direction": "x"}},
                         "finishing": {{"tool": "ball-3", "strategy": "raster_x", "step_over_mm": 0.3,
                                       "tolerance_mm": 0.01, "arcs": true}},
                         "dialect": "linuxcnc"}},
                "execute": {{"machine": "emco-f1", "adaptive": "aco"}}}}"#
        );
        let spec = parse(&json).expect("parse");
        spec.validate().expect("valid");
        assert_eq!(spec.first_stage(), Stage::Scan);
        // Serialising and parsing again gives the same spec.
        let again = parse(&serde_json::to_string(&spec).expect("ser")).expect("reparse");
        assert_eq!(spec, again);
    }

    #[test]
    fn unknown_fields_and_values_are_named() {
        let e = parse(&format!(
            r#"{{"input": {{"kind": "depth_map", "artifact": "{SHA}"}}, "plan": {{"finishing": {{"step_ovr_mm": 1}}}}}}"#
        ))
        .expect_err("unknown field");
        assert!(e.starts_with("plan.finishing") && e.contains("step_ovr_mm"), "{e}");
        let e =
            parse(&format!(r#"{{"input": {{"kind": "photo", "artifact": "{SHA}"}}}}"#)).expect_err("kind");
        assert!(e.starts_with("input.kind") && e.contains("photo"), "{e}");
    }

    #[test]
    fn values_out_of_range_and_unreachable_sections_are_rejected() {
        let base =
            |extra: &str| format!(r#"{{"input": {{"kind": "depth_map", "artifact": "{SHA}"}}{extra}}}"#);
        let cases = [
            (r#", "plan": {"finishing": {"step_over_mm": -1}}"#, "plan.finishing.step_over_mm"),
            (r#", "scan": {}"#, "scan"),
            (r#", "reconstruct": {"pixel_mm": 0.1}"#, "reconstruct"),
            (r#", "plan": {"roughing": {"tool": " "}}"#, "plan.roughing.tool"),
            (r#", "plan": {"finishing": {"angle_deg": 30}}"#, "plan.finishing.angle_deg"),
            (
                r#", "execute": {"machine": "emco-f1", "dexel": {"x_cell_mm": -0.1}}"#,
                "execute.dexel.x_cell_mm",
            ),
            (r#", "execute": {"machine": "emco-f1", "dexel": {}}"#, "execute.dexel"),
        ];
        for (extra, field) in cases {
            let spec = parse(&base(extra)).expect("parse");
            assert_eq!(spec.validate().expect_err(extra).field, field, "{extra}");
        }
        let spec = parse(&base(r#", "execute": {"machine": "emco-f1", "dexel": {"z_cell_mm": 0.05}}"#))
            .expect("parse");
        assert!(spec.validate().is_ok(), "one dexel grid is a valid choice");
        let spec = parse(r#"{"input": {"kind": "gcode", "artifact": "abc"}}"#).expect("parse");
        assert_eq!(spec.validate().expect_err("digest").field, "input.artifact");
    }

    #[test]
    fn a_robot_job_starts_at_the_plan_from_a_mesh_and_refuses_what_it_never_runs() {
        let mesh = |extra: &str| {
            format!(r#"{{"input": {{"kind": "mesh", "artifact": "{SHA}"}}, "process": "robot"{extra}}}"#)
        };
        let spec = parse(&mesh(
            r#", "robot": {"tool": "flat-6", "step_mm": 1.5, "part_at_mm": [400, 0, 0]}, "execute": {"cell_mm": 0.2}"#,
        ))
        .expect("parse");
        spec.validate().expect("valid");
        assert_eq!(spec.first_stage(), Stage::Plan);
        assert!(spec.is_robot());
        let again = parse(&serde_json::to_string(&spec).expect("ser")).expect("reparse");
        assert_eq!(spec, again);
        let cases = [
            (mesh(r#", "scan": {}"#), "scan"),
            (mesh(r#", "reconstruct": {}"#), "reconstruct"),
            (mesh(r#", "plan": {}"#), "plan"),
            (mesh(r#", "execute": {"machine": "emco-f1"}"#), "execute.machine"),
            (mesh(r#", "execute": {"adaptive": "off"}"#), "execute.adaptive"),
            (mesh(r#", "execute": {"cell_mm": 0.006}"#), "execute.cell_mm"),
            (
                format!(r#"{{"input": {{"kind": "depth_map", "artifact": "{SHA}"}}, "process": "robot"}}"#),
                "process",
            ),
            (format!(r#"{{"input": {{"kind": "mesh", "artifact": "{SHA}"}}, "robot": {{}}}}"#), "robot"),
            (
                format!(
                    r#"{{"input": {{"kind": "mesh", "artifact": "{SHA}"}}, "process": "mill", "robot": {{}}}}"#
                ),
                "robot",
            ),
        ];
        for (json, field) in cases {
            let spec = parse(&json).expect("parse");
            assert_eq!(spec.validate().expect_err(&json).field, field, "{json}");
        }
        assert!(parse(&mesh(r#", "robot": {"stepmm": 1}"#)).expect_err("unknown").contains("stepmm"));
        assert!(
            parse(&format!(r#"{{"input": {{"kind": "mesh", "artifact": "{SHA}"}}, "process": "lathe"}}"#))
                .expect_err("unknown process")
                .contains("lathe")
        );
        // A mill job is the default.
        let mill =
            parse(&format!(r#"{{"input": {{"kind": "mesh", "artifact": "{SHA}"}}, "process": "mill"}}"#))
                .expect("parse");
        mill.validate().expect("valid");
        assert_eq!(mill.first_stage(), Stage::Scan);
    }
}
