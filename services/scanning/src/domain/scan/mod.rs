//! Scan execution: the simulated cell scanning a part into a registered point cloud.
//!
//! # The cell
//! World frame = the robot's base frame (Z up, millimetres). The rotary table's axis is vertical
//! at [`CellLayout::table_axis_x_mm`] (500 mm from the robot's Z axis, DESIGN §6), its top at
//! [`CellLayout::table_top_z_mm`]. The part is the mesh, in its own frame (the *part frame*, where
//! the output cloud is written): it stands on the table with its bounding box centred on the axis
//! and its lowest point on the top ([`PartPlacement`]). At table angle θ,
//! `world_from_part(θ) = T(axis, top) · Rz(θ) · T(−centre, −z_min)`.
//!
//! # A scan
//! A [`plan::ScanPlan`] is a list of stations (one table angle each) of straight passes of the
//! sensor at the standoff above the part's top, looking down. The caller brings the table to each
//! station's angle (over the table's protocol, see `crate::session`), reads its encoder and hands
//! the measured angle to [`ScanSession::run_station`], which for every pass:
//! - **dynamic**: moves the arm to the pass start, then along the pass in one synchronised joint
//!   move timed so the sensor travels `line_rate_hz · line_spacing_mm` per second. At every frame
//!   (the scanner's sync pulse, `1 / line_rate_hz` apart) the encoder latch stores the robot's
//!   pose and the table angle, late by the latch's latency and jitter; the latched pose is
//!   corrected for the nominal latency when `compensate_latency` is set, by interpolating between
//!   neighbouring latches;
//! - **stop-and-move**: moves the arm (IK, nearest solution) to equally spaced poses on the straight
//!   pass, waits for it to settle, reads its position (ReadPosition) and takes one frame, at most
//!   `stop_and_move_rate_hz` frames per second.
//!
//! Each frame's profile is ray cast with the sensor's *true* pose (the physics) and placed into
//! the part frame with the *measured* pose (latched or read) and the measured table angle, the way
//! the real cell registers its data; the difference is reported as the registration error. Frames
//! of a pass are acquired in parallel (rayon), each with noise seeded by `(seed, frame)`, so a scan
//! is reproducible whatever the thread count.
//!
//! # Adaptive rescan
//! [`ScanSession::holes`] rasterises the cloud so far with `depthmill_geometry::raster`'s binning and
//! coverage code at `rescan_pixel_mm` and lists the enclosed holes (unmeasured cells of the
//! footprint). [`ScanSession::rescan_plan`] aims short passes at them, looking straight down and
//! tilted ±30° across the pass (a wall too steep for the incidence limit from above faces one of
//! the tilted views), from farther away (a smaller triangulation angle sees deeper), at the first
//! scan's table angles and halfway between them. Which of these candidate views run is a
//! next-best-view choice ([`views`]): what each would fill is predicted on the part's mesh, and
//! stations are taken by the unseen surface they add per second of turning and scanning, so the
//! table turns only where a view adds something.

pub mod obstacles;
pub mod options;
pub mod plan;
pub mod silhouette;
pub mod views;

use depthmill_geometry::Mesh;
use depthmill_geometry::pass_align::{self, PassAlignment};
use depthmill_geometry::raster::{COVERAGE_HOLE, Roi, coverage, grid_for_roi, try_rasterize_max};
use depthmill_geometry::{HeightMap, PointCloud, XyzYpr};
use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use rayon::prelude::*;
use serde::Serialize;

pub use options::{PassSpec, ScanMode, ScanOptions};
pub use plan::{Pass, ScanPlan, Station, TableMove, plan_scan, posture_score};

use super::calibration::fit::{AlignmentMoments, CapturedFrame};
use super::calibration::{CalibrationOptions, Cell, CellTruth, TableModel};
use super::latch::{EncoderLatch, LatchConfig, LatchError, PositionSource};
use super::robot::controller::{MotionController, RobotError};
use super::scanner::{DropCounts, Floor, Scanner, ScannerError, ScannerSpec};
use depthmill_geometry::arm::ArmModel;

/// Arm speed (fraction of the joints' top speeds) between passes.
const APPROACH_SPEED: f64 = 0.5;
/// Arm speed of the short stop-and-move steps.
const STEP_SPEED: f64 = 0.3;
/// Tilts of the rescan passes about their direction, degrees.
const RESCAN_TILTS_DEG: [f64; 3] = [0.0, 30.0, -30.0];
/// Directions of the rescan passes: `false` across the robot's reach (world Y), `true` along it
/// (world X).
const RESCAN_DIRECTIONS: [bool; 2] = [false, true];
/// The arm's approach to a rescan pass and its settling, s (for choosing the rescan's views).
const RESCAN_PASS_OVERHEAD_S: f64 = 1.0;
/// Wait after the arm arrives before a pass or a stop-and-move frame, s.
const SETTLE_S: f64 = 0.05;
/// In a calibration made during a scan, a point is the sphere's when it lies within this of the
/// sphere where the calibration in force places it, mm (more than that calibration's error on a
/// cell assembled to its drawing, about 2 mm at the nest).
pub const SPHERE_GATE_MM: f64 = 6.0;
/// Least gap between the part (its bounding circle about the axis) and the reference sphere for a
/// calibration during the scan, mm: twice the gate, so no point of the part passes for the sphere.
pub const NEST_CLEARANCE_MM: f64 = 12.0;
/// Points within this of the sphere's axis (beyond its radius), in the table's plane, are the
/// sphere and its post and are left out of the part's cloud, mm.
const NEST_MASK_MM: f64 = 5.0;

/// Why a scan cannot be planned or run.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ScanError {
    #[error("invalid {field}{}: {reason}", if value.is_empty() { String::new() } else { format!(" = {value}") })]
    InvalidOption { field: String, value: String, reason: String },
    #[error("pass {pass} at table angle {table_deg}°: the robot cannot reach the {reason}")]
    Unreachable { pass: u16, table_deg: f64, reason: String },
    #[error("the part mesh: {0}")]
    Mesh(String),
    #[error("the part is {size_mm:.1} mm across, more than the table's {limit_mm:.1} mm disc")]
    PartTooLarge { size_mm: f64, limit_mm: f64 },
    #[error(
        "the scan would take about {frames} frames, more than scan.max_frames = {max}; raise line_spacing_mm or max_frames"
    )]
    TooManyFrames { frames: u64, max: u64 },
    #[error("scanner: {0}")]
    Scanner(#[from] ScannerError),
    #[error("robot controller: {0}")]
    Robot(#[from] RobotError),
    #[error("encoder latch: {0}")]
    Latch(#[from] LatchError),
    #[error("rotary table: {0}")]
    Table(String),
    #[error("coverage map: {0}")]
    Coverage(String),
    /// The cell cannot be calibrated during this scan (the caller calibrates before it instead).
    #[error("no calibration during this scan: {0}")]
    NotInScan(String),
    /// The calibration made during the scan did not fit.
    #[error("cell calibration: {0}")]
    Calibration(String),
    #[error("the scan was cancelled")]
    Cancelled,
}

/// Where the table stands relative to the robot.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct CellLayout {
    /// X of the table's axis in the robot's base frame, mm.
    pub table_axis_x_mm: f64,
    /// Y of the table's axis, mm.
    pub table_axis_y_mm: f64,
    /// Height of the table top in the robot's base frame, mm.
    pub table_top_z_mm: f64,
    /// Radius of the table disc, mm.
    pub table_radius_mm: f64,
    /// The table as calibrated (axis position and tilt, encoder zero, top runout); `None`: the
    /// drawing above, a vertical axis and a square top.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub table: Option<TableModel>,
}

impl Default for CellLayout {
    /// Axis 500 mm from the robot's Z axis, a 400 mm disc (DESIGN §6), top 100 mm below the robot's
    /// base (an assumption: the arm stands on a pedestal beside the table).
    fn default() -> Self {
        Self {
            table_axis_x_mm: 500.0,
            table_axis_y_mm: 0.0,
            table_top_z_mm: -100.0,
            table_radius_mm: 200.0,
            table: None,
        }
    }
}

impl CellLayout {
    /// `world_from_table` at table angle `deg` (counter-clockwise seen from above): the
    /// calibrated table model when there is one, else the drawing.
    pub fn world_from_table(&self, deg: f64) -> Isometry3<f64> {
        if let Some(t) = &self.table {
            return t.world_from_table(deg);
        }
        Isometry3::from_parts(
            Translation3::new(self.table_axis_x_mm, self.table_axis_y_mm, self.table_top_z_mm),
            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), deg.to_radians()),
        )
    }
}

/// The part on the table: its bounds (part frame) and `table_from_part`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PartPlacement {
    pub min: Point3<f64>,
    pub max: Point3<f64>,
    pub table_from_part: Isometry3<f64>,
}

impl PartPlacement {
    /// Centred on the axis, lowest point on the top; refuses an empty mesh, non-finite vertices
    /// and a part wider than the disc.
    pub fn on_table(mesh: &Mesh, layout: &CellLayout) -> Result<Self, ScanError> {
        if mesh.triangles.is_empty() {
            return Err(ScanError::Mesh("the mesh has no triangles".into()));
        }
        let mut min = Point3::from(Vector3::repeat(f64::INFINITY));
        let mut max = Point3::from(Vector3::repeat(f64::NEG_INFINITY));
        for v in &mesh.vertices {
            if !(v.x.is_finite() && v.y.is_finite() && v.z.is_finite()) {
                return Err(ScanError::Mesh(format!("vertex ({}, {}, {}) is not finite", v.x, v.y, v.z)));
            }
            min = min.inf(v);
            max = max.sup(v);
        }
        let size = (max - min).max();
        if size < 1.0 {
            return Err(ScanError::Mesh(format!(
                "the part is only {size:.4} mm across: depthmill works in millimetres (is the mesh in metres or inches?)"
            )));
        }
        let half = 0.5 * ((max.x - min.x).hypot(max.y - min.y));
        if half > layout.table_radius_mm {
            return Err(ScanError::PartTooLarge {
                size_mm: 2.0 * half,
                limit_mm: 2.0 * layout.table_radius_mm,
            });
        }
        let table_from_part = Isometry3::translation(-0.5 * (min.x + max.x), -0.5 * (min.y + max.y), -min.z);
        Ok(Self { min, max, table_from_part })
    }

    /// A mesh given in the table's frame (the calibration's sphere on its post): the part frame is
    /// the table frame.
    pub fn in_table_frame(mesh: &Mesh) -> Result<Self, ScanError> {
        let mut min = Point3::from(Vector3::repeat(f64::INFINITY));
        let mut max = Point3::from(Vector3::repeat(f64::NEG_INFINITY));
        for v in &mesh.vertices {
            if !(v.x.is_finite() && v.y.is_finite() && v.z.is_finite()) {
                return Err(ScanError::Mesh(format!("vertex ({}, {}, {}) is not finite", v.x, v.y, v.z)));
            }
            min = min.inf(v);
            max = max.sup(v);
        }
        if mesh.triangles.is_empty() {
            return Err(ScanError::Mesh("the mesh has no triangles".into()));
        }
        Ok(Self { min, max, table_from_part: Isometry3::identity() })
    }

    /// `world_from_part` at table angle `deg`.
    pub fn world_from_part(&self, layout: &CellLayout, deg: f64) -> Isometry3<f64> {
        layout.world_from_table(deg) * self.table_from_part
    }

    /// The radius of the part's footprint about the table's axis (half its bounding box's
    /// diagonal in X and Y: the box is centred on the axis), mm.
    pub fn reach_mm(&self) -> f64 {
        0.5 * (self.max.x - self.min.x).hypot(self.max.y - self.min.y)
    }

    /// The table top the part stands on, in the part frame: rays past the part see it.
    fn floor(&self, layout: &CellLayout) -> Floor {
        Floor {
            z_mm: self.min.z,
            center_xy_mm: [0.5 * (self.min.x + self.max.x), 0.5 * (self.min.y + self.max.y)],
            radius_mm: layout.table_radius_mm,
        }
    }

    /// Part height, mm.
    pub fn height_mm(&self) -> f64 {
        self.max.z - self.min.z
    }

    /// World bounds of the part's bounding box at table angle `deg`.
    pub fn world_extent(&self, layout: &CellLayout, deg: f64) -> (Point3<f64>, Point3<f64>) {
        let w = self.world_from_part(layout, deg);
        let mut lo = Point3::from(Vector3::repeat(f64::INFINITY));
        let mut hi = Point3::from(Vector3::repeat(f64::NEG_INFINITY));
        for k in 0..8 {
            let c = Point3::new(
                if k & 1 == 0 { self.min.x } else { self.max.x },
                if k & 2 == 0 { self.min.y } else { self.max.y },
                if k & 4 == 0 { self.min.z } else { self.max.z },
            );
            let p = w * c;
            lo = lo.inf(&p);
            hi = hi.sup(&p);
        }
        (lo, hi)
    }
}

/// Rays dropped over the whole scan, by reason.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct DropTotals {
    pub out_of_window: u64,
    pub incidence: u64,
    pub occluded: u64,
    pub miss: u64,
}

impl DropTotals {
    fn add(&mut self, d: &DropCounts) {
        self.out_of_window += u64::from(d.out_of_window);
        self.incidence += u64::from(d.incidence);
        self.occluded += u64::from(d.occluded);
        self.miss += u64::from(d.miss);
    }
}

/// What one station did.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct StationReport {
    /// Angle asked of the table, degrees.
    pub table_deg_commanded: f64,
    /// Angle its encoder reported at rest (used to place the data), degrees.
    pub table_deg_measured: f64,
    pub passes: Vec<PassReport>,
    /// Rescan station (aimed at holes).
    pub rescan: bool,
    /// How far the planner turned the table from the angle asked for, the seventh joint, degrees.
    pub table_offset_deg: f64,
    /// The table's index from the previous station (none before the first).
    pub table_move: Option<plan::TableMove>,
}

/// What one pass did.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PassReport {
    pub id: u16,
    pub length_mm: f64,
    pub frames: u64,
    pub points: u64,
    /// Simulated duration of the pass itself (the arm moving along it), s.
    pub duration_s: f64,
    /// Mean sensor speed along the pass, mm/s.
    pub speed_mm_s: f64,
    pub path_deviation_mm: f64,
    pub min_dexterity: f64,
    pub min_clearance_mm: f64,
    /// Smallest distances from the wrist, shoulder and elbow singularities along the pass.
    pub min_margins: depthmill_geometry::arm::SingularityMargins,
    /// Smallest distance of a joint from its limits along the pass, degrees.
    pub min_limit_margin_deg: f64,
    /// Posture score of the pass's worst pose, 0..1 (seed 002's criteria in one number).
    pub quality: f64,
}

/// Coverage of the footprint by the cloud so far.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct CoverageSummary {
    pub pixel_mm: f64,
    /// Measured footprint cells / footprint cells, %.
    pub covered_pct: f64,
    pub footprint_cells: usize,
    /// Enclosed holes (8-connected components of unmeasured footprint cells).
    pub holes: usize,
    /// Their total area, mm².
    pub hole_area_mm2: f64,
}

/// One hole a rescan aims at, or an unseen region of the part's silhouette (part frame).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct HoleTarget {
    pub center_x_mm: f64,
    pub center_y_mm: f64,
    /// Larger side of its bounding box, mm.
    pub extent_mm: f64,
    pub area_mm2: f64,
}

/// The scan's report (written next to the cloud as JSON).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ScanReport {
    pub mode: ScanMode,
    pub options: ScanOptions,
    pub layout: CellLayout,
    pub mesh_triangles: usize,
    pub stations: Vec<StationReport>,
    pub frames: u64,
    pub points: u64,
    /// Points whose vertical the scan did not show clear under a wall or an overhang's edge
    /// beside them ([`ScanOutput::shadowed`]): a top view lids their cells.
    pub shadowed_points: u64,
    /// Simulated time from the first command to the last frame, table moves excluded, s.
    pub scan_time_s: f64,
    /// Rays that gave no point.
    pub dropped: DropTotals,
    /// RMS over all points of the distance between where the point was placed (measured poses)
    /// and where it truly is (true poses): the registration error, noise excluded, mm.
    pub registration_rms_mm: f64,
    /// Largest such distance, mm.
    pub registration_max_mm: f64,
    /// RMS of that distance after the one rigid transform that best aligns the whole cloud
    /// with the truth: how well the views agree with each other (the merge error), mm.
    pub registration_merge_rms_mm: f64,
    /// The passes moved onto the surface the whole cloud describes ([`pass_align::align_passes`]); the
    /// registration figures are after it.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub pass_alignment: Option<PassAlignment>,
    /// Whether the points were placed with a calibration of the cell (else with its drawing).
    pub calibrated: bool,
    /// The calibration in force and its figures (set by the service that was handed it).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub calibration: Option<serde_json::Value>,
    /// Coverage after the first scan.
    pub coverage_before_rescan: Option<CoverageSummary>,
    /// Coverage after the rescan.
    pub coverage_after_rescan: Option<CoverageSummary>,
    /// Holes the rescan aimed at.
    pub rescan_targets: Vec<HoleTarget>,
    /// Wall time spent waiting for the rotary table to reach and settle at the stations, s
    /// (recorded by the caller that drives the table).
    pub table_wait_s: f64,
    /// Things worth knowing (skipped rescan passes, slow passes, ...).
    pub diagnostics: Vec<String>,
    /// The part's top-view silhouette (from its mesh) against the cloud: what the scan did not
    /// see, and where.
    pub silhouette: Option<silhouette::SilhouetteCoverage>,
    /// How the mesh's units were decided (set by the caller that read the file); the cloud is in
    /// millimetres, in the mesh's frame scaled to millimetres.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub units: Option<depthmill_geometry::UnitsDecision>,
}

/// Table points are kept this far around the part's footprint (X and Y), mm: the free space the
/// depth map needs around the part (more than the largest tool's radius).
pub const FREE_SPACE_MARGIN_MM: f64 = 6.0;

/// Whether the vertical lies in the laser plane (sensor `y = 0`) of a sensor turned by
/// `world_from_sensor`, within [`FREE_SPACE_MAX_TILT_DEG`]: the plane's normal, sensor Y, is
/// horizontal. True looking straight down and rolled about the pass direction (sensor Y, as
/// [`plan::sensor_orientation`] tilts the rescan's passes); false pitched across it.
fn vertical_in_plane(world_from_sensor: &UnitQuaternion<f64>) -> bool {
    (world_from_sensor * Vector3::y()).dot(&Vector3::z()).abs() <= FREE_SPACE_MAX_TILT_DEG.to_radians().sin()
}

/// Table points are kept only from a sensor within this of looking straight down, degrees: the
/// vertical over a table point then stays within the laser plane (0.44 mm off it 25 mm up).
pub const FREE_SPACE_MAX_TILT_DEG: f64 = 1.0;

/// A table point is free space when the fan shows the vertical over it clear up to this much
/// over the part's top, mm.
pub const FREE_SPACE_CLEARANCE_MM: f64 = 1.0;

/// The scan's result: the registered cloud (part frame, with intensity), the pass id of every
/// point, and the report.
#[derive(Debug, Clone)]
pub struct ScanOutput {
    pub cloud: PointCloud,
    pub pass: Vec<u16>,
    pub report: ScanReport,
    /// Table points seen past the part around its footprint (part frame): where there is no part.
    pub free_space: Vec<Point3<f64>>,
    /// Points of the cloud (part frame) that may lie under material the scanner did not see
    /// ([`shadowed`]): the highest point of a cell of a top view is not its top when it is one.
    pub shadowed: Vec<Point3<f64>>,
}

/// A frame ray cast and not yet placed.
struct RawFrame {
    pass: u16,
    /// The table's encoder reading, degrees.
    table_deg: f64,
    /// `world_from_sensor` as measured, with the tool frame `tool` the controller reported in.
    measured_pose: Isometry3<f64>,
    tool: Isometry3<f64>,
    /// `part_from_sensor` as it truly was (for the registration error).
    truth: Isometry3<f64>,
    /// The sensor looked straight down (its table points say where the part is not).
    looks_down: bool,
    /// The vertical lay in the sensor's laser plane (within [`FREE_SPACE_MAX_TILT_DEG`]): a
    /// sensor looking down, or one rolled about its pass direction (the rescan's tilted passes),
    /// so the fan's rays show how high the vertical over each point is clear.
    vertical_in_plane: bool,
    profile: super::scanner::Profile,
}

impl RawFrame {
    /// `world_from_sensor` with the scanner mount `tool`: the measured pose itself when the
    /// controller reported in that tool frame, else moved to it through the flange.
    fn world_from_sensor(&self, tool: &Isometry3<f64>) -> Isometry3<f64> {
        if self.tool == *tool { self.measured_pose } else { self.measured_pose * self.tool.inverse() * tool }
    }
}

/// One frame's timing and poses before acquisition.
struct FrameRec {
    frame: u64,
    pulse_s: f64,
    /// `world_from_sensor` as it truly was at the pulse.
    true_pose: Isometry3<f64>,
    /// `world_from_sensor` as measured.
    measured_pose: Isometry3<f64>,
    /// Table angle as measured (degrees).
    table_deg: f64,
}

/// The latch's position source during a station: the robot controller and the table at rest.
struct StationSource<'a> {
    robot: &'a MotionController,
    table_deg: f64,
}

impl PositionSource for StationSource<'_> {
    fn robot_pose(&mut self, t_s: f64) -> Result<XyzYpr, LatchError> {
        self.robot.latch(t_s).map_err(|e| LatchError::Source(e.to_string()))
    }

    fn table_deg(&mut self, _t_s: f64) -> Result<f64, LatchError> {
        Ok(self.table_deg)
    }
}

/// One frame's points placed in the part frame ([`ScanSession::place`]).
struct Placed {
    pts: Vec<Point3<f64>>,
    inten: Vec<f32>,
    clear_to: Vec<f64>,
    /// Placed less true position, per point.
    errors: Vec<Vector3<f32>>,
    floor: Vec<FreeSample>,
    moments: AlignmentMoments,
}

/// A scan in progress; see the module doc.
pub struct ScanSession {
    opts: ScanOptions,
    layout: CellLayout,
    placement: PartPlacement,
    arm: ArmModel,
    scanner: Scanner,
    robot: MotionController,
    latch: EncoderLatch,
    t_s: f64,
    next_frame: u64,
    points: Vec<Point3<f64>>,
    intensity: Vec<f32>,
    pass: Vec<u16>,
    /// Per point, where it was placed less where it truly is (the registration error, kept so
    /// that the pass alignment's figures are the truth's).
    placement_error: Vec<Vector3<f32>>,
    dropped: DropTotals,
    err_sq: f64,
    err_max: f64,
    stations: Vec<StationReport>,
    diagnostics: Vec<String>,
    mesh_triangles: usize,
    coverage_before: Option<CoverageSummary>,
    coverage_after: Option<CoverageSummary>,
    rescan_targets: Vec<HoleTarget>,
    last_pass_id: u16,
    table_wait_s: f64,
    /// The part's top-view silhouette at the rescan pixel (from its mesh).
    silhouette: Option<silhouette::Silhouette>,
    /// The part's mesh for predicting what a rescan pass sees (with the silhouette).
    views: Option<views::ViewModel>,
    /// Table points seen past the part within [`FREE_SPACE_MARGIN_MM`] of its footprint (part
    /// frame), with how high the vertical over each was shown clear.
    free_space: Vec<FreeSample>,
    /// Per point of the cloud: the height (part frame) up to which a sensor looking down showed
    /// the vertical over it clear (the point's own height when none did).
    clear_to: Vec<f64>,
    /// The cell as it truly is (the physics); `layout` and `arm` hold what the software believes.
    truth: CellTruth,
    calibrated: bool,
    /// Placed against true points, for the merge error.
    moments: AlignmentMoments,
    /// Calibration scans: every frame kept for the fit.
    capture: Option<Capture>,
    /// A scan's frames ray cast before the calibration made during it is fitted.
    pending: Vec<RawFrame>,
    /// The reference sphere's nest on the table (table frame: its centre, and the radius within
    /// which points are left out of the cloud) when it stands there during the scan.
    nest: Option<(Point3<f64>, f64)>,
}

/// A calibration scan's frames.
struct Capture {
    opts: CalibrationOptions,
    frames: Vec<CapturedFrame>,
    /// The calibration passes of a scan that calibrates the cell at its own stations; `None`: a
    /// calibration routine, every pass is one.
    passes: Option<Vec<u16>>,
}

impl ScanSession {
    /// A scan on a cell exactly as drawn: [`ScanSession::with_cell`] with [`Cell::exact`].
    pub fn new(mesh: &Mesh, opts: ScanOptions, layout: CellLayout) -> Result<Self, ScanError> {
        let cell = Cell::exact(&layout);
        Self::with_cell(mesh, opts, layout, cell)
    }

    /// Checks the options, places the part, builds the scanner's ray-casting structure, powers and
    /// homes the arm and powers the latch. The physics runs on `cell.truth`; points are placed
    /// with its calibration (or the drawing when it has none).
    pub fn with_cell(
        mesh: &Mesh,
        opts: ScanOptions,
        layout: CellLayout,
        cell: Cell,
    ) -> Result<Self, ScanError> {
        let spec = ScannerSpec { line_rate_hz: opts.line_rate_hz, ..ScannerSpec::slp400() };
        opts.validate(&spec)?;
        let placement = PartPlacement::on_table(mesh, &layout)?;
        let floor = placement.floor(&layout);
        Self::build(mesh, None, opts, spec, layout, cell, placement, floor, None)
    }

    /// A calibration scan of `mesh` (the reference sphere, in the table's frame) on `cell`:
    /// every frame is kept for [`ScanSession::finish_calibration`].
    pub fn for_calibration(
        mesh: &Mesh,
        opts: ScanOptions,
        layout: CellLayout,
        cell: Cell,
        calibration: CalibrationOptions,
    ) -> Result<Self, ScanError> {
        let spec = ScannerSpec { line_rate_hz: opts.line_rate_hz, ..ScannerSpec::slp400() };
        opts.validate(&spec)?;
        let placement = PartPlacement::in_table_frame(mesh)?;
        let floor = Floor { z_mm: 0.0, center_xy_mm: [0.0, 0.0], radius_mm: layout.table_radius_mm };
        let capture = Capture { opts: calibration, frames: Vec::new(), passes: None };
        Self::build(mesh, None, opts, spec, layout, cell, placement, floor, Some(capture))
    }

    /// A scan of `mesh` that calibrates `cell` at its own stations: the reference sphere stays on
    /// its nest during the scan, each station scans it and the table top (the routine's passes,
    /// [`super::calibration::routine`]) before the part, and the part's frames are placed once the
    /// calibration is fitted ([`ScanSession::calibrate_in_scan`], after the first scan's stations).
    /// The table turns once for both. [`ScanError::NotInScan`] names why it cannot be done (the
    /// part over the nest, explicit passes; the stations are checked by [`ScanSession::plan`]):
    /// then calibrate first.
    pub fn with_cell_calibrating(
        mesh: &Mesh,
        opts: ScanOptions,
        layout: CellLayout,
        cell: Cell,
        calibration: CalibrationOptions,
    ) -> Result<Self, ScanError> {
        if opts.passes.is_some() {
            return Err(ScanError::NotInScan(
                "the scan's passes are given: the calibration's stations are the automatic plan's".into(),
            ));
        }
        let spec = ScannerSpec { line_rate_hz: opts.line_rate_hz, ..ScannerSpec::slp400() };
        opts.validate(&spec)?;
        let placement = PartPlacement::on_table(mesh, &layout)?;
        let centre = Point3::from(calibration.sphere_at_mm);
        let r = calibration.sphere_radius_mm;
        let reach = placement.reach_mm();
        let nest = centre.x.hypot(centre.y);
        if reach + NEST_CLEARANCE_MM > nest - r {
            return Err(ScanError::NotInScan(format!(
                "the part reaches {reach:.1} mm from the table's axis, within {NEST_CLEARANCE_MM} mm of the reference sphere (radius {r} mm, {nest:.1} mm from the axis)"
            )));
        }
        // The sphere in the part frame, in the scene the scanner sees with the part.
        let mut scene = mesh.clone();
        let sphere =
            super::calibration::routine::sphere_mesh(placement.table_from_part.inverse() * centre, r);
        let base = u32::try_from(scene.vertices.len())
            .map_err(|_| ScanError::Mesh("more than 2^32 vertices".into()))?;
        scene.vertices.extend(sphere.vertices);
        scene.triangles.extend(sphere.triangles.iter().map(|t| t.map(|i| i + base)));
        let floor = placement.floor(&layout);
        let capture = Capture { opts: calibration, frames: Vec::new(), passes: Some(Vec::new()) };
        let mut s =
            Self::build(mesh, Some(&scene), opts, spec, layout, cell, placement, floor, Some(capture))?;
        s.nest = Some((centre, r + NEST_MASK_MM));
        Ok(s)
    }

    /// Whether this scan calibrates the cell and the fit is still to come.
    pub fn calibrating_in_scan(&self) -> bool {
        self.capture.as_ref().is_some_and(|c| c.passes.is_some())
    }

    #[allow(clippy::too_many_arguments)]
    fn build(
        mesh: &Mesh,
        scene: Option<&Mesh>,
        opts: ScanOptions,
        spec: ScannerSpec,
        mut layout: CellLayout,
        cell: Cell,
        placement: PartPlacement,
        floor: Floor,
        capture: Option<Capture>,
    ) -> Result<Self, ScanError> {
        let belief = cell.belief(&layout);
        if let Some(c) = &cell.calibration {
            c.validate(&layout).map_err(|e| ScanError::InvalidOption {
                field: "calibration".into(),
                value: String::new(),
                reason: e.to_string(),
            })?;
            layout.table = Some(c.table);
        }
        let scanner = Scanner::new(spec.clone(), scene.unwrap_or(mesh), opts.seed)?.with_floor(floor);
        // At least two lines to a cell, so a cell between two lines is not taken for unseen.
        let (silhouette, views) = if capture.as_ref().is_some_and(|c| c.passes.is_none()) {
            (None, None)
        } else {
            (
                silhouette::Silhouette::of(mesh, opts.rescan_pixel_mm.max(2.0 * opts.line_spacing_mm)),
                opts.adaptive_rescan.then(|| views::ViewModel::new(mesh, &spec)).flatten(),
            )
        };
        let model = ArmModel::viper_s650().with_tool(belief.flange_from_scanner());
        let mut robot = MotionController::new(model, ArmModel::READY_DEG)?;
        robot.initialize(0.0)?;
        let t_s = robot.home(0.0, APPROACH_SPEED)?;
        let arm = robot.model().clone();
        let mut latch = EncoderLatch::new(LatchConfig {
            latency_s: opts.latch_latency_s,
            jitter_s: opts.latch_jitter_s,
            seed: opts.seed ^ 0x5EED,
            ..LatchConfig::default()
        })?;
        latch.initialize();
        Ok(Self {
            opts,
            layout,
            placement,
            arm,
            scanner,
            robot,
            latch,
            t_s,
            next_frame: 0,
            points: Vec::new(),
            intensity: Vec::new(),
            pass: Vec::new(),
            placement_error: Vec::new(),
            dropped: DropTotals::default(),
            err_sq: 0.0,
            err_max: 0.0,
            stations: Vec::new(),
            diagnostics: Vec::new(),
            mesh_triangles: mesh.triangles.len(),
            coverage_before: None,
            coverage_after: None,
            rescan_targets: Vec::new(),
            last_pass_id: 0,
            table_wait_s: 0.0,
            silhouette,
            views,
            free_space: Vec::new(),
            clear_to: Vec::new(),
            truth: cell.truth,
            calibrated: cell.calibration.is_some(),
            moments: AlignmentMoments::default(),
            capture,
            pending: Vec::new(),
            nest: None,
        })
    }

    /// A calibration scan's frames so far (tests edit them to make degenerate data).
    #[cfg(test)]
    pub(crate) fn captured_frames(&self) -> Vec<CapturedFrame> {
        self.capture.as_ref().map(|c| c.frames.clone()).unwrap_or_default()
    }

    /// The arm as the software believes it (the calibrated scanner mount).
    pub fn arm(&self) -> &ArmModel {
        &self.arm
    }

    /// The options.
    pub fn options(&self) -> &ScanOptions {
        &self.opts
    }

    /// Where the part stands.
    pub fn placement(&self) -> &PartPlacement {
        &self.placement
    }

    /// The cell layout.
    pub fn layout(&self) -> &CellLayout {
        &self.layout
    }

    /// Points so far.
    pub fn points(&self) -> &[Point3<f64>] {
        &self.points
    }

    /// The first scan's plan (automatic or given), with the frame guard applied.
    pub fn plan(&mut self) -> Result<ScanPlan, ScanError> {
        let mut plan = plan_scan(&self.placement, &self.layout, &self.arm, self.scanner.spec(), &self.opts)?;
        if self.calibrating_in_scan() {
            self.add_calibration_passes(&mut plan)?;
        }
        let frames = plan.estimated_frames(&self.opts);
        if frames > self.opts.max_frames {
            return Err(ScanError::TooManyFrames { frames, max: self.opts.max_frames });
        }
        self.last_pass_id = plan
            .stations
            .iter()
            .flat_map(|s| &s.passes)
            .map(|p| p.id)
            .max()
            .unwrap_or(0)
            .max(self.last_pass_id);
        for s in &plan.skipped {
            self.diagnostics.push(format!("pass left out: {s}"));
        }
        for p in plan.stations.iter().flat_map(|s| &s.passes) {
            if p.path_deviation_mm > 5.0 {
                self.diagnostics.push(format!(
                    "pass {}: the arm's joint-interpolated path bends up to {:.1} mm from the straight line (points are placed with the latched poses, coverage may shift)",
                    p.id, p.path_deviation_mm
                ));
            }
        }
        Ok(plan)
    }

    /// Puts the calibration routine's passes at the head of every station of `plan` (a scan that
    /// calibrates the cell, [`ScanSession::with_cell_calibrating`]): the calibration's angles are
    /// the stations'. [`ScanError::NotInScan`] when they cannot serve (fewer than three, spread
    /// over less than 90°), there is no room for the table-top pass or a pass is out of reach.
    fn add_calibration_passes(&mut self, plan: &mut ScanPlan) -> Result<(), ScanError> {
        let Some(capture) = self.capture.as_mut() else { return Ok(()) };
        let mut opts = capture.opts.clone();
        opts.table_angles_deg = plan.stations.iter().map(|s| s.table_deg).collect();
        let not = |e: &dyn std::fmt::Display| ScanError::NotInScan(e.to_string());
        opts.validate(&self.layout).map_err(|e| not(&format!("the scan's stations: {e}")))?;
        // The table-top pass runs across, clear of the part by the gap the sphere keeps.
        let reach = self.placement.reach_mm();
        let half = 0.5 * super::calibration::routine::TABLE_PASS_MM;
        let from_axis =
            (0.4 * opts.sphere_at_mm[0].hypot(opts.sphere_at_mm[1])).max(reach + NEST_CLEARANCE_MM + half);
        if from_axis.hypot(half) + 5.0 > self.layout.table_radius_mm {
            return Err(not(&format!(
                "no room on the {} mm table beside the part (reaching {reach:.1} mm from the axis) for the table-top pass",
                self.layout.table_radius_mm
            )));
        }
        let first =
            plan.stations.iter().flat_map(|s| &s.passes).map(|p| p.id).max().unwrap_or(0).saturating_add(1);
        let mut obstacles = obstacles::cell_obstacles(&self.layout, &self.placement);
        obstacles.extend(self.opts.obstacles.iter().cloned());
        let scan_opts = ScanOptions { table_angles_deg: opts.table_angles_deg.clone(), ..self.opts.clone() };
        let stations = super::calibration::routine::calibration_stations(
            &self.arm,
            &self.layout,
            &opts,
            &scan_opts,
            &obstacles,
            (true, from_axis),
            first,
        )
        .map_err(|e| not(&format!("calibration pass: {e}")))?;
        let mut ids = Vec::new();
        for (station, cal) in plan.stations.iter_mut().zip(stations) {
            ids.extend(cal.passes.iter().map(|p| p.id));
            let scan = std::mem::take(&mut station.passes);
            station.passes = cal.passes.into_iter().chain(scan).collect();
        }
        capture.opts = opts;
        capture.passes = Some(ids);
        Ok(())
    }

    /// Fits the calibration made during this scan to its sphere and table frames, takes it in
    /// force (the table model and the scanner mount, for the robot's tool frame too) and places
    /// the part's frames held for it. Called after the first scan's stations, before the rescan.
    pub fn calibrate_in_scan(
        &mut self,
    ) -> Result<(super::calibration::Calibration, super::calibration::CalibrationReport), ScanError> {
        let Some(capture) = self.capture.take_if(|c| c.passes.is_some()) else {
            return Err(ScanError::Calibration("this scan does not calibrate the cell".into()));
        };
        let (cal, mut report) = self.fit(&capture).map_err(|e| ScanError::Calibration(e.to_string()))?;
        report.scan_time_s = self.t_s;
        self.layout.table = Some(cal.table);
        let tool = cal.flange_from_scanner();
        self.arm.tool = tool;
        self.robot.set_tool(tool);
        self.calibrated = true;
        let pending = std::mem::take(&mut self.pending);
        self.place(pending);
        // The passes' point counts, now that their points are placed.
        let mut counts: std::collections::HashMap<u16, u64> = std::collections::HashMap::new();
        for id in &self.pass {
            *counts.entry(*id).or_default() += 1;
        }
        for p in self.stations.iter_mut().flat_map(|s| s.passes.iter_mut()) {
            p.points = counts.get(&p.id).copied().unwrap_or(0);
        }
        Ok((cal, report))
    }

    /// The calibration fitted to `capture`'s frames, starting from the calibration in force.
    fn fit(
        &self,
        capture: &Capture,
    ) -> Result<
        (super::calibration::Calibration, super::calibration::CalibrationReport),
        super::calibration::CalibrationError,
    > {
        let previous = super::calibration::Calibration {
            table: self.layout.table.unwrap_or_else(|| TableModel::nominal(&self.layout)),
            scanner_mount: super::calibration::Offset::from_iso(
                &(ArmModel::scanner_bracket().inverse() * self.arm.tool),
            ),
        };
        let nominal_layout = CellLayout { table: None, ..self.layout };
        super::calibration::fit::solve(
            &capture.frames,
            &capture.opts,
            &nominal_layout,
            &previous,
            Some(&self.truth),
        )
    }

    /// Runs every pass of `station` with the table at rest at `table_deg_measured` (its encoder
    /// reading). `progress(pass_done, passes)` after each pass; `cancelled()` is polled between
    /// passes.
    pub fn run_station(
        &mut self,
        station: &Station,
        table_deg_measured: f64,
        rescan: bool,
        progress: &mut dyn FnMut(usize, usize),
        cancelled: &dyn Fn() -> bool,
    ) -> Result<(), ScanError> {
        let mut report = StationReport {
            table_deg_commanded: station.table_deg,
            table_deg_measured,
            passes: Vec::with_capacity(station.passes.len()),
            rescan,
            table_offset_deg: station.table_offset_deg,
            table_move: self.stations.last().map(|s| {
                plan::TableMove::between(
                    s.table_deg_commanded,
                    station.table_deg,
                    plan::TABLE_INDEX_SPEED_DEG_S,
                    plan::TABLE_INDEX_ACCEL_DEG_S2,
                )
            }),
        };
        for (i, pass) in station.passes.iter().enumerate() {
            if cancelled() {
                return Err(ScanError::Cancelled);
            }
            let budget = self.opts.max_frames.saturating_sub(self.next_frame);
            let want = (pass.length_mm / self.opts.line_spacing_mm).ceil() as u64 + 1;
            if want > budget {
                return Err(ScanError::TooManyFrames {
                    frames: self.next_frame + want,
                    max: self.opts.max_frames,
                });
            }
            let (frames, duration_s) = match self.opts.mode {
                ScanMode::Dynamic => self.dynamic_frames(pass, table_deg_measured)?,
                ScanMode::StopAndMove => self.stop_and_move_frames(pass, table_deg_measured)?,
            };
            let before = self.points.len();
            let station_index = self
                .capture
                .as_ref()
                .and_then(|c| c.opts.table_angles_deg.iter().position(|a| *a == station.table_deg));
            self.acquire(&frames, table_deg_measured, pass.id, station_index);
            report.passes.push(PassReport {
                id: pass.id,
                length_mm: pass.length_mm,
                frames: frames.len() as u64,
                points: (self.points.len() - before) as u64,
                duration_s,
                speed_mm_s: if duration_s > 0.0 { pass.length_mm / duration_s } else { 0.0 },
                path_deviation_mm: pass.path_deviation_mm,
                min_dexterity: pass.min_dexterity,
                min_clearance_mm: pass.min_clearance_mm,
                min_margins: pass.min_margins,
                min_limit_margin_deg: pass.min_limit_margin_deg,
                quality: pass.quality,
            });
            progress(i + 1, station.passes.len());
        }
        self.stations.push(report);
        Ok(())
    }

    /// Dynamic pass: approach, then one timed joint move with a latch at every frame.
    fn dynamic_frames(&mut self, pass: &Pass, table_deg: f64) -> Result<(Vec<FrameRec>, f64), ScanError> {
        let t = self.robot.move_joints(self.t_s, &pass.q_start_deg, APPROACH_SPEED)? + SETTLE_S;
        let speed = self.opts.line_rate_hz * self.opts.line_spacing_mm;
        let frac = plan::speed_fraction_for(
            &self.arm.limits,
            &pass.q_start_deg,
            &pass.q_end_deg,
            pass.length_mm / speed,
        );
        let t0 = t;
        let t1 = self.robot.move_joints(t0, &pass.q_end_deg, frac)?;
        let period = 1.0 / self.opts.line_rate_hz;
        let n = ((t1 - t0) / period).floor() as usize + 1;
        self.latch.begin_latching()?;
        let mut recs = Vec::with_capacity(n);
        let mut latched: Vec<(f64, Isometry3<f64>)> = Vec::with_capacity(n);
        let result = (|| -> Result<(), ScanError> {
            for k in 0..n {
                let tk = t0 + k as f64 * period;
                let q = self.robot.read_position(tk)?;
                let true_pose = self.truth.world_from_sensor(&q);
                let mut src = StationSource { robot: &self.robot, table_deg };
                let ev = self.latch.sync_pulse(&mut src, tk)?;
                let super::latch::LatchEvent::Latch { pulse_s, values, .. } = ev else {
                    continue;
                };
                let pose = XyzYpr {
                    x_mm: values[0],
                    y_mm: values[1],
                    z_mm: values[2],
                    yaw_deg: values[3],
                    pitch_deg: values[4],
                    roll_deg: values[5],
                }
                .to_pose()
                .map_err(|e| ScanError::Latch(LatchError::Source(e.to_string())))?;
                latched.push((pulse_s + self.opts.latch_latency_s, pose));
                recs.push(FrameRec {
                    frame: self.next_frame,
                    pulse_s,
                    true_pose,
                    measured_pose: pose,
                    table_deg: values[6],
                });
                self.next_frame += 1;
            }
            Ok(())
        })();
        self.latch.take_events();
        self.latch.end_latching()?;
        result?;
        if self.opts.compensate_latency && latched.len() >= 2 {
            for (k, rec) in recs.iter_mut().enumerate() {
                let (i, j) = if k == 0 { (0, 1) } else { (k - 1, k) };
                rec.measured_pose = interpolate_pose(&latched[i], &latched[j], rec.pulse_s);
            }
        }
        self.t_s = t1 + SETTLE_S;
        Ok((recs, t1 - t0))
    }

    /// Stop-and-move pass: equally spaced stops on the straight line, one frame at rest each.
    fn stop_and_move_frames(
        &mut self,
        pass: &Pass,
        table_deg: f64,
    ) -> Result<(Vec<FrameRec>, f64), ScanError> {
        let mut t = self.robot.move_joints(self.t_s, &pass.q_start_deg, APPROACH_SPEED)? + SETTLE_S;
        let t_start = t;
        let a = pass.start.translation.vector;
        let d = pass.end.translation.vector - a;
        let stops = (pass.length_mm / self.opts.line_spacing_mm).ceil().max(1.0) as usize + 1;
        let min_gap = 1.0 / self.opts.stop_and_move_rate_hz;
        let mut last = f64::NEG_INFINITY;
        let mut recs = Vec::with_capacity(stops);
        for k in 0..stops {
            let s = k as f64 / (stops - 1).max(1) as f64;
            let target = Isometry3::from_parts(Translation3::from(a + d * s), pass.start.rotation);
            let arrive = if k == 0 { t } else { self.robot.move_pose(t, &target, STEP_SPEED)? + SETTLE_S };
            let tk = arrive.max(last + min_gap);
            let q = self.robot.read_position(tk)?;
            recs.push(FrameRec {
                frame: self.next_frame,
                pulse_s: tk,
                true_pose: self.truth.world_from_sensor(&q),
                measured_pose: self.arm.fk(&q),
                table_deg,
            });
            self.next_frame += 1;
            last = tk;
            t = tk;
        }
        self.t_s = t + SETTLE_S;
        Ok((recs, t - t_start))
    }

    /// Ray casts the frames in parallel (the true sensor and table poses make the physics) and
    /// hands them on: a calibration pass's frames are kept for the fit (station `station`), a
    /// scan pass's are placed ([`ScanSession::place`]), or held until the calibration made in
    /// this scan is fitted.
    fn acquire(&mut self, frames: &[FrameRec], table_deg: f64, pass_id: u16, station: Option<usize>) {
        let part_from_world_true =
            (self.truth.table.world_from_table(table_deg) * self.placement.table_from_part).inverse();
        let scanner = &self.scanner;
        let seed = self.opts.seed;
        let robot_tool = self.robot.model().tool;
        let raw: Vec<RawFrame> = frames
            .par_iter()
            .map(|f| {
                let truth = part_from_world_true * f.true_pose;
                RawFrame {
                    pass: pass_id,
                    table_deg: f.table_deg,
                    measured_pose: f.measured_pose,
                    tool: robot_tool,
                    truth,
                    looks_down: (f.true_pose.rotation * Vector3::z()).dot(&-Vector3::z())
                        >= FREE_SPACE_MAX_TILT_DEG.to_radians().cos(),
                    vertical_in_plane: vertical_in_plane(&f.true_pose.rotation),
                    profile: scanner.profile_seeded(&truth, f.frame, seed),
                }
            })
            .collect();
        let calibration_pass =
            self.capture.as_ref().is_some_and(|c| c.passes.as_ref().is_none_or(|p| p.contains(&pass_id)));
        if calibration_pass {
            self.capture_frames(&raw, station.unwrap_or(usize::MAX));
        }
        let in_scan = self.capture.as_ref().is_some_and(|c| c.passes.is_some());
        if calibration_pass && in_scan {
            // The sphere's frames of a calibration made in this scan add nothing to the cloud.
            for r in &raw {
                self.dropped.add(&r.profile.dropped);
            }
        } else if in_scan {
            self.pending.extend(raw);
        } else {
            self.place(raw);
        }
    }

    /// Keeps a calibration pass's frames for the fit. In a calibration made during a scan the
    /// sphere shares the table with the part: only the points within [`SPHERE_GATE_MM`] of where
    /// the calibration in force places the sphere are the sphere's.
    fn capture_frames(&mut self, raw: &[RawFrame], station: usize) {
        let table_from_part = self.placement.table_from_part;
        let tool = self.arm.tool;
        let layout = self.layout;
        let Some(c) = self.capture.as_mut() else { return };
        let gate = c.passes.is_some().then(|| (Point3::from(c.opts.sphere_at_mm), c.opts.sphere_radius_mm));
        for r in raw {
            let sphere = match gate {
                None => r.profile.points.clone(),
                Some((centre, radius)) => {
                    let sensor_from_world = r.world_from_sensor(&tool).inverse();
                    let c_s = sensor_from_world * (layout.world_from_table(r.table_deg) * centre);
                    r.profile
                        .points
                        .iter()
                        .filter(|p| (*p - c_s).norm() <= radius + SPHERE_GATE_MM)
                        .copied()
                        .collect()
                }
            };
            c.frames.push(CapturedFrame {
                station,
                table_deg: r.table_deg,
                world_from_flange: r.measured_pose * r.tool.inverse(),
                true_table_from_sensor: table_from_part * r.truth,
                sphere,
                table: r.profile.floor.clone(),
            });
        }
    }

    /// Places ray-cast frames into the part frame with their measured flange poses, the scanner
    /// mount and the table as the session believes them, and appends them to the cloud (and the
    /// table seen around the part to the free space). The points on the reference sphere's nest,
    /// when it stands on the table, are left out.
    fn place(&mut self, raw: Vec<RawFrame>) {
        let placement = &self.placement;
        let layout = &self.layout;
        let tool = self.arm.tool;
        let nest = self.nest;
        let scanner = &self.scanner;
        let results: Vec<_> = raw
            .into_par_iter()
            .map(|r| {
                let placed =
                    placement.world_from_part(layout, r.table_deg).inverse() * r.world_from_sensor(&tool);
                let profile = r.profile;
                let truth = r.truth;
                let mut sq = 0.0;
                let mut mx: f64 = 0.0;
                let mut moments = AlignmentMoments::default();
                let mut pts = Vec::with_capacity(profile.points.len());
                let mut inten = Vec::with_capacity(profile.points.len());
                let mut clear_to = Vec::with_capacity(profile.points.len());
                let mut errors = Vec::with_capacity(profile.points.len());
                // How high over each point the fan showed its vertical clear (a sensor whose laser
                // plane holds the vertical: looking down, or rolled about its pass direction; a
                // plane tilted across the pass holds no vertical but the point's own).
                let up = placed.rotation.inverse() * Vector3::z();
                let top = placement.max.z + FREE_SPACE_CLEARANCE_MM - placed.translation.vector.z;
                let point_clear = if r.vertical_in_plane {
                    scanner.point_clear_height(&profile, &up, top)
                } else {
                    vec![0.0; profile.points.len()]
                };
                for ((p, i), h) in profile.points.iter().zip(&profile.intensity).zip(point_clear) {
                    let q = placed * p;
                    if let Some((c, radius)) = nest {
                        let t = placement.table_from_part * q;
                        if (t.x - c.x).hypot(t.y - c.y) <= radius {
                            continue;
                        }
                    }
                    let t = truth * p;
                    let e = (q - t).norm_squared();
                    sq += e;
                    mx = mx.max(e);
                    moments.add(&q, &t);
                    errors.push((q - t).cast::<f32>());
                    pts.push(q);
                    inten.push(*i);
                    clear_to.push(q.z + h);
                }
                let (lo, hi) = (placement.min, placement.max);
                let m = FREE_SPACE_MARGIN_MM;
                // A tilted sensor sees the table far under an overhang (its rays reach under by
                // the height times the tilt's tangent): only a sensor looking down says where
                // the part is not, and the fan's own slant reaches under an overhang too: each
                // table point keeps the height up to which the fan shows the vertical over it
                // clear ([`FreeSample`]).
                let floor: Vec<FreeSample> = if r.looks_down {
                    let clear = scanner.floor_clear_height(&profile, &up, top);
                    profile
                        .floor
                        .iter()
                        .zip(clear)
                        .map(|(p, h)| {
                            let at = placed * p;
                            FreeSample { at, clear_to_z: at.z + h }
                        })
                        .filter(|f| {
                            let q = f.at;
                            q.x >= lo.x - m && q.x <= hi.x + m && q.y >= lo.y - m && q.y <= hi.y + m
                        })
                        .collect()
                } else {
                    Vec::new()
                };
                let placed = Placed { pts, inten, clear_to, errors, floor, moments };
                (r.pass, placed, profile.dropped, sq, mx.sqrt())
            })
            .collect();
        for (pass, placed, dropped, sq, mx) in results {
            let Placed { pts, inten, clear_to, errors, floor, moments } = placed;
            self.placement_error.extend(errors);
            self.free_space.extend(floor);
            self.clear_to.extend(clear_to);
            self.pass.extend(std::iter::repeat_n(pass, pts.len()));
            self.points.extend(pts);
            self.intensity.extend(inten);
            self.dropped.add(&dropped);
            self.err_sq += sq;
            self.err_max = self.err_max.max(mx);
            self.moments.merge(&moments);
        }
    }

    /// Coverage of the cloud so far at `rescan_pixel_mm` and its enclosed holes, largest first.
    pub fn holes(&self) -> Result<(CoverageSummary, Vec<HoleTarget>), ScanError> {
        let pixel = self.opts.rescan_pixel_mm;
        let err = |e: &dyn std::fmt::Display| ScanError::Coverage(e.to_string());
        let Some(roi) = Roi::around(&self.points, 2.0 * pixel) else {
            return Ok((
                CoverageSummary {
                    pixel_mm: pixel,
                    covered_pct: 0.0,
                    footprint_cells: 0,
                    holes: 0,
                    hole_area_mm2: 0.0,
                },
                Vec::new(),
            ));
        };
        let grid = grid_for_roi(&roi, pixel).map_err(|e| err(&e))?;
        let (raw, _) = try_rasterize_max(&self.points, &grid).map_err(|e| err(&e))?;
        let (cov, stats) = coverage(&raw, &raw);
        let holes = hole_components(&cov);
        let min_cells = (self.opts.rescan_min_hole_mm2 / (pixel * pixel)).ceil().max(1.0) as usize;
        let area: f64 = holes.iter().map(|h| h.area_mm2).sum();
        let summary = CoverageSummary {
            pixel_mm: pixel,
            covered_pct: stats.covered_pct,
            footprint_cells: stats.footprint,
            holes: holes.len(),
            hole_area_mm2: area,
        };
        let min_area = min_cells as f64 * pixel * pixel;
        let mut targets: Vec<HoleTarget> = holes.into_iter().filter(|h| h.area_mm2 >= min_area).collect();
        // The part's silhouette where the cloud has nothing, at the edge of what was seen (an
        // enclosed hole is already a target): steep flanks and hidden sides.
        if let Some(sil) = &self.silhouette {
            for r in sil.coverage(&self.points).unseen_regions {
                let covered = targets.iter().any(|t| {
                    (t.center_x_mm - r.center_x_mm).hypot(t.center_y_mm - r.center_y_mm)
                        < 0.5 * (t.extent_mm + r.extent_mm)
                });
                if r.area_mm2 >= min_area && !covered {
                    targets.push(r);
                }
            }
        }
        targets.sort_by(|a, b| b.area_mm2.total_cmp(&a.area_mm2));
        targets.truncate(self.opts.rescan_max_holes);
        Ok((summary, targets))
    }

    /// The first scan's table angles, each turned by 45°: the rescan's candidate stations besides
    /// the first scan's own angles.
    fn rescan_angles(&self) -> Vec<f64> {
        let mut angles: Vec<f64> = Vec::new();
        for a in self.first_angles() {
            let r = (a + 45.0).rem_euclid(360.0);
            if !angles.iter().any(|b| (b - r).abs() < 1e-6) {
                angles.push(r);
            }
        }
        angles
    }

    /// The first scan's table angles, as asked for.
    fn first_angles(&self) -> Vec<f64> {
        match &self.opts.passes {
            Some(p) => p.iter().map(|p| p.table_deg).collect(),
            None => self.opts.table_angles_deg.clone(),
        }
    }

    /// The cells the cloud so far leaves unseen, at `rescan_pixel_mm` (part frame, cell centres,
    /// mm): the enclosed holes of its coverage map and the unseen part of the mesh's top-view
    /// silhouette.
    fn unseen_cells(&self) -> Vec<[f64; 2]> {
        let pixel = self.opts.rescan_pixel_mm;
        let mut cells = Vec::new();
        let mut keys = std::collections::HashSet::new();
        let mut add = |c: [f64; 2], cells: &mut Vec<[f64; 2]>| {
            if keys.insert(((c[0] / pixel).floor() as i64, (c[1] / pixel).floor() as i64)) {
                cells.push(c);
            }
        };
        if let Some(roi) = Roi::around(&self.points, 2.0 * pixel)
            && let Ok(grid) = grid_for_roi(&roi, pixel)
            && let Ok((raw, _)) = try_rasterize_max(&self.points, &grid)
        {
            let (cov, _) = coverage(&raw, &raw);
            let w = grid.width as usize;
            for (i, _) in cov.data().iter().enumerate().filter(|(_, v)| **v == COVERAGE_HOLE) {
                let c = [
                    grid.origin_x_mm + ((i % w) as f64 + 0.5) * pixel,
                    grid.origin_y_mm + ((i / w) as f64 + 0.5) * pixel,
                ];
                add(c, &mut cells);
            }
        }
        if let Some(sil) = &self.silhouette {
            for c in sil.unseen_cells(&self.points) {
                add(c, &mut cells);
            }
        }
        cells
    }

    /// Passes aimed at `targets`, with the table at `table_at_deg`: a next-best-view choice.
    ///
    /// Candidates: at each first-scan angle and each first-scan angle + 45°, six short passes per
    /// hole, across the robot's reach and along it, each straight down and tilted ±30° (aimed so
    /// its optical axis meets the hole at the rescan standoff, or at the scan's own standoff where
    /// the arm cannot reach that).
    /// Each candidate's view of the unseen cells is predicted on the part's mesh
    /// ([`views::ViewModel::sees`]). Stations are chosen greedily by the unseen cells they add per
    /// second of the cell's time (the table's turn on the shortest tour from where it stands, and
    /// the passes), while one adds at least `rescan_min_hole_mm2`; within a chosen station only
    /// the passes that add cells are kept. Stations are visited in the tour's order.
    pub fn rescan_plan(&mut self, targets: &[HoleTarget], table_at_deg: f64) -> ScanPlan {
        let spec = self.scanner.spec().clone();
        let far = self.opts.rescan_standoff_mm.unwrap_or_else(|| {
            (spec.standoff_max_mm - self.placement.height_mm() - 10.0).min(220.0).max(self.opts.standoff_mm)
        });
        let standoffs: Vec<f64> = if (far - self.opts.standoff_mm).abs() > 1.0 {
            vec![far, self.opts.standoff_mm]
        } else {
            vec![far]
        };
        let mut angles = self.rescan_angles();
        for a in self.first_angles() {
            let a = a.rem_euclid(360.0);
            if !angles.iter().any(|b| (b - a).abs() < 1e-6) {
                angles.push(a);
            }
        }
        let (cells, stride) = match &self.views {
            Some(v) => {
                let unseen = self.unseen_cells();
                (v.surface(&unseen, self.opts.rescan_pixel_mm), views::thinning(unseen.len()))
            }
            None => (Vec::new(), 1),
        };
        let mut obstacles = obstacles::cell_obstacles(&self.layout, &self.placement);
        obstacles.extend(self.opts.obstacles.iter().cloned());
        // Every candidate station: its passes, the cells each would fill, and the passes out of reach.
        struct Candidate {
            deg: f64,
            passes: Vec<(Pass, Vec<u32>)>,
            skipped: Vec<(f64, [f64; 2], String)>,
        }
        // Each station planned on its own (in parallel): the arm's seed runs through its passes.
        let this = &*self;
        let candidates: Vec<Candidate> = angles
            .par_iter()
            .map(|&deg| {
                let w = this.placement.world_from_part(&this.layout, deg);
                let part_from_world = w.inverse();
                let mut seed = ArmModel::HOME_DEG;
                let mut passes = Vec::new();
                let mut skipped = Vec::new();
                for (k, h) in targets.iter().enumerate() {
                    let c = w * Point3::new(h.center_x_mm, h.center_y_mm, this.placement.max.z);
                    let half = 0.5 * h.extent_mm + this.opts.margin_mm + 2.0;
                    // Across the robot's reach (world Y) and along it (world X), each straight
                    // down and tilted both ways across the pass: a wall too steep for the
                    // incidence limit seen from above faces one of the tilted views, and the
                    // camera's baseline along the pass sees past the other side of a step.
                    for (along, tilt) in
                        RESCAN_DIRECTIONS.iter().flat_map(|&d| RESCAN_TILTS_DEG.map(|t| (d, t)))
                    {
                        if along && this.views.is_none() {
                            continue;
                        }
                        let dir = if along { Vector3::x() } else { Vector3::y() };
                        let (pa, pb) = (c - dir * half, c + dir * half);
                        let (pa, pb) = if k % 2 == 0 { (pa, pb) } else { (pb, pa) };
                        let axis = plan::sensor_orientation(&(pb - pa), tilt) * Vector3::z();
                        let opts = ScanOptions { tilt_deg: tilt, ..this.opts.clone() };
                        let mut why = None;
                        for &standoff in &standoffs {
                            let (a, b) = (pa - axis * standoff, pb - axis * standoff);
                            match plan::make_pass(&this.arm, &opts, &obstacles, 0, deg, a, b, &seed) {
                                Ok(p) => {
                                    seed = p.q_end_deg;
                                    let (s0, s1) = (part_from_world * p.start, part_from_world * p.end);
                                    let seen = match &this.views {
                                        Some(v) => (0..cells.len() as u32)
                                            .filter(|&i| v.sees(&s0, &s1, &cells[i as usize]))
                                            .collect(),
                                        None => Vec::new(),
                                    };
                                    passes.push((p, seen));
                                    why = None;
                                    break;
                                }
                                // The candidate has no pass id yet: the reason alone.
                                Err(ScanError::Unreachable { reason, .. }) => {
                                    why = why.or(Some(format!("the robot cannot reach the {reason}")))
                                }
                                Err(e) => why = why.or(Some(e.to_string())),
                            }
                        }
                        if let Some(why) = why {
                            skipped.push((tilt, [h.center_x_mm, h.center_y_mm], why));
                        }
                    }
                }
                Candidate { deg, passes, skipped }
            })
            .collect();
        let table = |from: f64, to: f64| {
            TableMove::between(from, to, plan::TABLE_INDEX_SPEED_DEG_S, plan::TABLE_INDEX_ACCEL_DEG_S2).time_s
        };
        let pass_s = |p: &Pass| self.opts.pass_time_s(p.length_mm) + RESCAN_PASS_OVERHEAD_S;
        let pixel = self.opts.rescan_pixel_mm;
        let min_cells = ((self.opts.rescan_min_hole_mm2 / (pixel * pixel)).ceil() as usize / stride).max(1);
        let chosen: Vec<usize> = if self.views.is_none() {
            // No model to predict with: every candidate station at the first-scan angles + 45°.
            (0..candidates.len().min(self.rescan_angles().len())).collect()
        } else {
            let mut covered = vec![false; cells.len()];
            let mut chosen: Vec<usize> = Vec::new();
            let mut gains = Vec::new();
            loop {
                let tour_now = tour(
                    table_at_deg,
                    &chosen.iter().map(|&i| candidates[i].deg).collect::<Vec<_>>(),
                    &table,
                )
                .0;
                let mut best: Option<(f64, usize)> = None;
                for (i, c) in candidates.iter().enumerate() {
                    if chosen.contains(&i) {
                        continue;
                    }
                    let (gain, secs) = station_gain(&c.passes, &covered, &pass_s);
                    if gain < min_cells {
                        continue;
                    }
                    let mut with: Vec<f64> = chosen.iter().map(|&j| candidates[j].deg).collect();
                    with.push(c.deg);
                    let dt = tour(table_at_deg, &with, &table).0 - tour_now + secs;
                    let score = gain as f64 / dt.max(0.1);
                    if best.is_none_or(|(s, _)| score > s) {
                        best = Some((score, i));
                    }
                }
                let Some((_, i)) = best else { break };
                let (gain, _) = station_gain(&candidates[i].passes, &covered, &pass_s);
                gains.push(format!(
                    "{}° {:.1} mm²",
                    candidates[i].deg,
                    (gain * stride) as f64 * pixel * pixel
                ));
                for (_, seen) in &candidates[i].passes {
                    for &k in seen {
                        covered[k as usize] = true;
                    }
                }
                chosen.push(i);
            }
            let out_of_sight = covered.iter().filter(|c| !**c).count();
            self.diagnostics.push(format!(
                "rescan views, predicted on the part's mesh: {} of {} candidate table angles chosen ({}); about {:.1} mm² of the unseen surface is out of sight of them",
                chosen.len(),
                candidates.len(),
                if gains.is_empty() { "none adds anything".to_string() } else { gains.join(", ") },
                (out_of_sight * stride) as f64 * pixel * pixel,
            ));
            chosen
        };
        let degs: Vec<f64> = chosen.iter().map(|&i| candidates[i].deg).collect();
        let order = tour(table_at_deg, &degs, &table).1;
        let mut covered = vec![false; cells.len()];
        let mut stations = Vec::new();
        for k in order {
            let c = &candidates[chosen[k]];
            let deg = c.deg;
            // The passes that add cells, most first, then in the order they were planned.
            let mut keep: Vec<usize> = Vec::new();
            if self.views.is_some() {
                let mut left: Vec<usize> = (0..c.passes.len()).collect();
                loop {
                    let new = |j: &usize| c.passes[*j].1.iter().filter(|&&k| !covered[k as usize]).count();
                    let Some(&j) = left.iter().max_by_key(|j| (new(j), std::cmp::Reverse(**j))) else {
                        break;
                    };
                    // A chosen station runs at least its best pass.
                    if new(&j) < if keep.is_empty() { 1 } else { min_cells } {
                        break;
                    }
                    for &k in &c.passes[j].1 {
                        covered[k as usize] = true;
                    }
                    keep.push(j);
                    left.retain(|&x| x != j);
                }
                keep.sort_unstable();
            } else {
                keep = (0..c.passes.len()).collect();
            }
            if let Some((tilt, [x, y], why)) = c.skipped.first() {
                let tilts: std::collections::BTreeSet<String> =
                    c.skipped.iter().map(|s| format!("{}°", s.0)).collect();
                self.diagnostics.push(format!(
                    "rescan at table angle {deg}°: {} of {} passes out of reach (tilts {}); the first, tilt {tilt}° over the hole at ({x:.1}, {y:.1}) mm: {why}",
                    c.skipped.len(),
                    c.skipped.len() + c.passes.len(),
                    tilts.into_iter().collect::<Vec<_>>().join(", ")
                ));
            }
            let mut passes = Vec::new();
            for j in keep {
                let Some(id) = self.last_pass_id.checked_add(1) else {
                    self.diagnostics.push("rescan: pass ids exhausted (65535 passes)".into());
                    break;
                };
                self.last_pass_id = id;
                let mut p = c.passes[j].0.clone();
                p.id = id;
                passes.push(p);
            }
            if !passes.is_empty() {
                stations.push(Station { table_deg: deg, passes, table_offset_deg: 0.0 });
            }
        }
        ScanPlan { stations, skipped: Vec::new() }
    }

    /// Records the coverage before and after the rescan and its targets (for the report).
    pub fn record_rescan(
        &mut self,
        before: CoverageSummary,
        after: Option<CoverageSummary>,
        targets: Vec<HoleTarget>,
    ) {
        self.coverage_before = Some(before);
        self.coverage_after = after;
        self.rescan_targets = targets;
    }

    /// Adds wall time spent waiting for the table (for the report).
    pub fn add_table_wait(&mut self, seconds: f64) {
        self.table_wait_s += seconds;
    }

    /// Adds a diagnostic line to the report.
    pub fn note(&mut self, line: String) {
        self.diagnostics.push(line);
    }

    /// Fits the calibration to a calibration scan's frames ([`ScanSession::for_calibration`]):
    /// the new calibration and its report (residuals, the registration before and after, and,
    /// the cell being simulated, the result against its truth).
    pub fn finish_calibration(
        mut self,
    ) -> Result<
        (super::calibration::Calibration, super::calibration::CalibrationReport),
        super::calibration::CalibrationError,
    > {
        let Some(capture) = self.capture.take() else {
            return Err(super::calibration::CalibrationError::Scan(
                "this session is not a calibration scan".into(),
            ));
        };
        let (cal, mut report) = self.fit(&capture)?;
        report.scan_time_s = self.t_s;
        report.diagnostics = std::mem::take(&mut self.diagnostics);
        Ok((cal, report))
    }

    /// Moves every pass onto the surface the whole cloud describes ([`pass_align::align_passes`]), and
    /// brings the registration figures, the clear heights over the points and the diagnostics up
    /// to date.
    fn align_passes(&mut self) -> Option<PassAlignment> {
        let n = self.points.len();
        if n == 0 || self.placement_error.len() != n || self.clear_to.len() != n {
            return None;
        }
        let mut alignment = pass_align::align_passes(&mut self.points, &self.pass)?;
        alignment.registration_rms_before_mm = (self.err_sq / n as f64).sqrt();
        alignment.registration_merge_rms_before_mm = self.moments.rms_after_alignment();
        // Each pass's points were moved back by its offset.
        let moved_by: std::collections::BTreeMap<u16, Vector3<f64>> =
            alignment.passes.iter().map(|s| (s.pass, -Vector3::from(s.offset_mm))).collect();
        let (mut sq, mut mx, mut moments) = (0.0, 0.0f64, AlignmentMoments::default());
        for (i, (q, p)) in self.points.iter().zip(&self.pass).enumerate() {
            let moved = moved_by.get(p).copied().unwrap_or_else(Vector3::zeros);
            let e = self.placement_error[i].cast::<f64>() + moved;
            self.placement_error[i] = e.cast::<f32>();
            self.clear_to[i] += moved.z;
            sq += e.norm_squared();
            mx = mx.max(e.norm());
            moments.add(q, &(q - e));
        }
        (self.err_sq, self.err_max, self.moments) = (sq, mx, moments);
        let moved: Vec<String> = alignment
            .passes
            .iter()
            .filter(|s| s.applied)
            .map(|s| {
                format!(
                    "{} by ({:+.4}, {:+.4}, {:+.4}) mm",
                    s.pass, -s.offset_mm[0], -s.offset_mm[1], -s.offset_mm[2]
                )
            })
            .collect();
        if !moved.is_empty() {
            self.diagnostics.push(format!("passes moved onto the cloud's surface: {}", moved.join("; ")));
        }
        Some(alignment)
    }

    /// The registered cloud, the pass ids and the report.
    pub fn finish(mut self) -> ScanOutput {
        let n = self.points.len();
        let pass_alignment = self.align_passes();
        let slant = (self.scanner.spec().fan_half_tan().atan() + FREE_SPACE_MAX_TILT_DEG.to_radians()).tan();
        let free_space = free_space(&self.free_space, &self.points, self.placement.height_mm() * slant);
        let shadowed: Vec<Point3<f64>> = shadowed(&self.points, &self.clear_to)
            .into_iter()
            .zip(&self.points)
            .filter(|(s, _)| *s)
            .map(|(_, p)| *p)
            .collect();
        let silhouette = self.silhouette.as_ref().map(|s| s.coverage(&self.points));
        if let Some(line) = silhouette.as_ref().and_then(|s| s.diagnostic()) {
            self.diagnostics.push(line);
        }
        let report = ScanReport {
            mode: self.opts.mode,
            options: self.opts.clone(),
            layout: self.layout,
            mesh_triangles: self.mesh_triangles,
            stations: self.stations,
            frames: self.next_frame,
            points: n as u64,
            shadowed_points: shadowed.len() as u64,
            scan_time_s: self.t_s,
            dropped: self.dropped,
            registration_rms_mm: if n > 0 { (self.err_sq / n as f64).sqrt() } else { 0.0 },
            registration_max_mm: self.err_max,
            registration_merge_rms_mm: self.moments.rms_after_alignment(),
            calibrated: self.calibrated,
            calibration: None,
            coverage_before_rescan: self.coverage_before,
            coverage_after_rescan: self.coverage_after,
            rescan_targets: self.rescan_targets,
            table_wait_s: self.table_wait_s,
            diagnostics: self.diagnostics,
            silhouette,
            units: None,
            pass_alignment,
        };
        ScanOutput {
            cloud: PointCloud {
                points: self.points.iter().map(depthmill_geometry::cloud::single).collect(),
                intensity: Some(self.intensity),
                normals: None,
            },
            pass: self.pass,
            report,
            free_space,
            shadowed,
        }
    }
}

/// A table point a sensor looking down saw, part frame, and how high over the table the fan
/// showed the vertical over it clear ([`Scanner::floor_clear_height`]).
#[derive(Debug, Clone, Copy, PartialEq)]
struct FreeSample {
    at: Point3<f64>,
    clear_to_z: f64,
}

/// The table points that show there is no part over them: those whose vertical was shown clear
/// to [`FREE_SPACE_CLEARANCE_MM`] over every point of the cloud within `reach` mm around (in X
/// and Y). Material over a table point the fan reached at a slant stands no farther than the
/// fan's slant times the part's height from where the ray passed it, and the part the scanner
/// saw there bounds it; far from every point of the cloud, no height needs showing clear.
fn free_space(samples: &[FreeSample], cloud: &[Point3<f64>], reach: f64) -> Vec<Point3<f64>> {
    /// Cell of the grid the cloud's heights are kept on, mm.
    const CELL_MM: f64 = 0.5;
    let (Some(lo), Some(hi)) = (
        samples.iter().map(|s| s.at).reduce(|a, b| a.inf(&b)),
        samples.iter().map(|s| s.at).reduce(|a, b| a.sup(&b)),
    ) else {
        return Vec::new();
    };
    // Every cloud point within `reach` of a sample falls on the grid.
    let grow = Vector3::new(reach + CELL_MM, reach + CELL_MM, 0.0);
    let (lo, hi) = (lo - grow, hi + grow);
    let w = ((hi.x - lo.x) / CELL_MM).floor() as usize + 1;
    let h = ((hi.y - lo.y) / CELL_MM).floor() as usize + 1;
    let cell = |p: &Point3<f64>| -> Option<usize> {
        let (cx, cy) = (((p.x - lo.x) / CELL_MM).floor(), ((p.y - lo.y) / CELL_MM).floor());
        (cx >= 0.0 && cy >= 0.0 && (cx as usize) < w && (cy as usize) < h)
            .then(|| cy as usize * w + cx as usize)
    };
    // The cloud's highest point per cell, then the highest within `reach` (a square around:
    // the disc's bound, rounded out).
    let mut top = vec![f64::NEG_INFINITY; w * h];
    for p in cloud {
        if let Some(i) = cell(p) {
            top[i] = top[i].max(p.z);
        }
    }
    let k = (reach / CELL_MM).ceil() as usize + 1;
    let mut rows = vec![f64::NEG_INFINITY; w * h];
    for y in 0..h {
        for x in 0..w {
            let (a, b) = (x.saturating_sub(k), (x + k).min(w - 1));
            rows[y * w + x] = top[y * w + a..=y * w + b].iter().fold(f64::NEG_INFINITY, |m, v| m.max(*v));
        }
    }
    for y in 0..h {
        for x in 0..w {
            let (a, b) = (y.saturating_sub(k), (y + k).min(h - 1));
            top[y * w + x] = (a..=b).map(|yy| rows[yy * w + x]).fold(f64::NEG_INFINITY, f64::max);
        }
    }
    samples
        .iter()
        .filter(|s| cell(&s.at).is_none_or(|i| s.clear_to_z >= top[i] + FREE_SPACE_CLEARANCE_MM))
        .map(|s| s.at)
        .collect()
}

/// Slope (tangent) past which a rise beside a point is a wall or an overhang rather than the
/// surface the point lies on: 75°, the report's wall test.
const STEP_TAN: f64 = 3.732_050_807_568_877;

/// Which points of `cloud` may lie under material the scanner did not see: those with a point
/// of the cloud higher by more than [`FREE_SPACE_CLEARANCE_MM`] and by more than a 75° slope
/// from it (a wall, or the edge of an overhang that may reach over it), whose vertical no sensor
/// looking down showed clear to [`FREE_SPACE_CLEARANCE_MM`] over that point (`clear_to`, per
/// point, part frame), nor that of a point within [`SHADOW_NEIGHBOUR_MM`] beside it and within
/// [`SHADOW_LEVEL_MM`] of its height. A line scanner sees under an overhang's edge at its fan's
/// slant, or from a tilted pass, and a surface sloped toward grazing may give no point at all:
/// the highest point in a cell of a top view is then the floor under the overhang, and a target
/// taken from it cuts the overhang away. Points on slopes under 75°, and every point shown
/// clear, are not shadowed.
fn shadowed(cloud: &[Point3<f64>], clear_to: &[f64]) -> Vec<bool> {
    /// Cell of the grid the cloud is binned on, mm.
    const CELL_MM: f64 = 0.5;
    let (Some(lo), Some(hi)) =
        (cloud.iter().copied().reduce(|a, b| a.inf(&b)), cloud.iter().copied().reduce(|a, b| a.sup(&b)))
    else {
        return Vec::new();
    };
    let w = ((hi.x - lo.x) / CELL_MM).floor() as usize + 1;
    let h = ((hi.y - lo.y) / CELL_MM).floor() as usize + 1;
    let cell_xy = |p: &Point3<f64>| {
        (
            (((p.x - lo.x) / CELL_MM).floor() as usize).min(w - 1),
            (((p.y - lo.y) / CELL_MM).floor() as usize).min(h - 1),
        )
    };
    // The points by cell (counting sort), and each cell's highest.
    let mut start = vec![0usize; w * h + 1];
    for p in cloud {
        let (x, y) = cell_xy(p);
        start[y * w + x + 1] += 1;
    }
    for i in 0..w * h {
        start[i + 1] += start[i];
    }
    let mut fill = start.clone();
    let mut order = vec![0usize; cloud.len()];
    let mut top = vec![f64::NEG_INFINITY; w * h];
    for (i, p) in cloud.iter().enumerate() {
        let (x, y) = cell_xy(p);
        let c = y * w + x;
        order[fill[c]] = i;
        fill[c] += 1;
        top[c] = top[c].max(p.z);
    }
    cloud
        .par_iter()
        .zip(clear_to)
        .map(|(p, &clear)| {
            let need = p.z + FREE_SPACE_CLEARANCE_MM;
            if clear >= hi.z + FREE_SPACE_CLEARANCE_MM || hi.z <= need {
                return false;
            }
            // No point farther than the cloud's top allows at the slope can rise over it.
            let reach = (hi.z - p.z) / STEP_TAN;
            let k = (reach / CELL_MM).ceil() as usize + 1;
            let (cx, cy) = cell_xy(p);
            let mut threat = f64::NEG_INFINITY;
            for y in cy.saturating_sub(k)..=(cy + k).min(h - 1) {
                for x in cx.saturating_sub(k)..=(cx + k).min(w - 1) {
                    let c = y * w + x;
                    if top[c] <= need.max(threat) {
                        continue;
                    }
                    // The cell's nearest point to `p`, for the slope bound.
                    let gx = (lo.x + x as f64 * CELL_MM - p.x)
                        .max(p.x - (lo.x + (x + 1) as f64 * CELL_MM))
                        .max(0.0);
                    let gy = (lo.y + y as f64 * CELL_MM - p.y)
                        .max(p.y - (lo.y + (y + 1) as f64 * CELL_MM))
                        .max(0.0);
                    if top[c] - p.z <= gx.hypot(gy) * STEP_TAN {
                        continue;
                    }
                    for &j in &order[start[c]..start[c + 1]] {
                        let q = &cloud[j];
                        let rise = q.z - p.z;
                        if q.z > threat
                            && rise > FREE_SPACE_CLEARANCE_MM
                            && rise > (q.x - p.x).hypot(q.y - p.y) * STEP_TAN
                        {
                            threat = q.z;
                        }
                    }
                }
            }
            if !threat.is_finite() || clear >= threat + FREE_SPACE_CLEARANCE_MM {
                return false;
            }
            // Another line may have shown the vertical beside it clear: one along a wall (whose
            // rays over the foot return from the floor beyond, where a line across the wall
            // meets the wall's face and gives no point), or from another station.
            let k = (SHADOW_NEIGHBOUR_MM / CELL_MM).ceil() as usize;
            for y in cy.saturating_sub(k)..=(cy + k).min(h - 1) {
                for x in cx.saturating_sub(k)..=(cx + k).min(w - 1) {
                    let c = y * w + x;
                    for &j in &order[start[c]..start[c + 1]] {
                        let q = &cloud[j];
                        if clear_to[j] >= threat + FREE_SPACE_CLEARANCE_MM
                            && (q.z - p.z).abs() <= SHADOW_LEVEL_MM
                            && (q.x - p.x).hypot(q.y - p.y) <= SHADOW_NEIGHBOUR_MM
                        {
                            return false;
                        }
                    }
                }
            }
            true
        })
        .collect()
}

/// A point shown clear above within this distance (in X and Y) of a point, and within
/// [`SHADOW_LEVEL_MM`] of its height, shows its vertical clear too, mm: the depth map's usual
/// cell. (A point higher up beside it is material over it, not evidence of space.)
pub const SHADOW_NEIGHBOUR_MM: f64 = 0.25;

/// See [`SHADOW_NEIGHBOUR_MM`], mm: where the fan's vertical test starts over a point.
const SHADOW_LEVEL_MM: f64 = 0.3;

/// The pose at time `t` on the line through two timed poses (slerp for the rotation; `t` may lie
/// outside the two times, which extrapolates).
fn interpolate_pose(a: &(f64, Isometry3<f64>), b: &(f64, Isometry3<f64>), t: f64) -> Isometry3<f64> {
    let dt = b.0 - a.0;
    if dt.abs() < 1e-12 {
        return a.1;
    }
    let u = (t - a.0) / dt;
    let pa = a.1.translation.vector;
    let pb = b.1.translation.vector;
    let ra = a.1.rotation;
    let rel = ra.inverse() * b.1.rotation;
    let rot = ra * rel.powf(u);
    Isometry3::from_parts(Translation3::from(pa + (pb - pa) * u), rot)
}

/// The quickest way for the table from `from_deg` through every angle of `degs`: its time, s, and
/// the order (indices into `degs`). Every order is tried up to six angles; more are visited in
/// their cyclic order from the nearest.
fn tour(from_deg: f64, degs: &[f64], table: &dyn Fn(f64, f64) -> f64) -> (f64, Vec<usize>) {
    let time = |order: &[usize]| {
        let mut at = from_deg;
        order.iter().fold(0.0, |t, &i| {
            let dt = table(at, degs[i]);
            at = degs[i];
            t + dt
        })
    };
    if degs.len() > 6 {
        let mut order: Vec<usize> = (0..degs.len()).collect();
        order.sort_by(|&a, &b| {
            (degs[a] - from_deg).rem_euclid(360.0).total_cmp(&(degs[b] - from_deg).rem_euclid(360.0))
        });
        return (time(&order), order);
    }
    let mut best = (f64::INFINITY, Vec::new());
    let mut order: Vec<usize> = (0..degs.len()).collect();
    permute(&mut order, 0, &mut |o| {
        let t = time(o);
        if t < best.0 - 1e-12 {
            best = (t, o.to_vec());
        }
    });
    best
}

/// Calls `f` with every permutation of `items[k..]` (Heap's recursion by swaps).
fn permute(items: &mut [usize], k: usize, f: &mut dyn FnMut(&[usize])) {
    if k + 1 >= items.len() {
        f(items);
        return;
    }
    for i in k..items.len() {
        items.swap(k, i);
        permute(items, k + 1, f);
        items.swap(k, i);
    }
}

/// The unseen cells a station's passes would add to `covered`, and the time of the passes that
/// add any, s.
fn station_gain(
    passes: &[(Pass, Vec<u32>)],
    covered: &[bool],
    pass_s: &dyn Fn(&Pass) -> f64,
) -> (usize, f64) {
    let mut new: std::collections::HashSet<u32> = std::collections::HashSet::new();
    let mut secs = 0.0;
    for (p, seen) in passes {
        let before = new.len();
        new.extend(seen.iter().copied().filter(|&k| !covered[k as usize]));
        if new.len() > before {
            secs += pass_s(p);
        }
    }
    (new.len(), secs)
}

/// 8-connected components of the hole cells (value [`COVERAGE_HOLE`]) of a coverage map.
fn hole_components(cov: &HeightMap) -> Vec<HoleTarget> {
    let meta = *cov.meta();
    let (w, h) = (meta.width as usize, meta.height as usize);
    let data = cov.data();
    let p = meta.pixel_mm;
    let mut seen = vec![false; data.len()];
    let mut out = Vec::new();
    let mut stack = Vec::new();
    for start in 0..data.len() {
        if seen[start] || data[start] != COVERAGE_HOLE {
            continue;
        }
        seen[start] = true;
        stack.push(start);
        let (mut n, mut sx, mut sy) = (0usize, 0.0, 0.0);
        let (mut c0, mut c1, mut r0, mut r1) = (usize::MAX, 0, usize::MAX, 0);
        while let Some(i) = stack.pop() {
            let (r, c) = (i / w, i % w);
            n += 1;
            sx += c as f64;
            sy += r as f64;
            c0 = c0.min(c);
            c1 = c1.max(c);
            r0 = r0.min(r);
            r1 = r1.max(r);
            for dr in -1i64..=1 {
                for dc in -1i64..=1 {
                    let (rr, cc) = (r as i64 + dr, c as i64 + dc);
                    if rr < 0 || cc < 0 || rr >= h as i64 || cc >= w as i64 {
                        continue;
                    }
                    let j = rr as usize * w + cc as usize;
                    if !seen[j] && data[j] == COVERAGE_HOLE {
                        seen[j] = true;
                        stack.push(j);
                    }
                }
            }
        }
        let nf = n as f64;
        out.push(HoleTarget {
            center_x_mm: meta.origin_x_mm + (sx / nf + 0.5) * p,
            center_y_mm: meta.origin_y_mm + (sy / nf + 0.5) * p,
            extent_mm: ((c1 - c0 + 1).max(r1 - r0 + 1)) as f64 * p,
            area_mm2: nf * p * p,
        });
    }
    out
}

#[cfg(test)]
mod tests;
