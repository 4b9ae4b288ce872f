//! The simulated mill: canonical commands from the interpreter in, motion with acceleration
//! limits, material removal per spindle revolution, forces, sensors and a feed/speed policy, out
//! a cut stock, telemetry and a cycle time.
//!
//! # Steps
//! Positions reach the stock on whole motor steps (`step_mm`, 0.01 mm on the F1): each
//! revolution's piece of a move starts and ends at the commanded point rounded to the step grid.
//!
//! # Frames
//! The interpreter gives machine coordinates of the controlled point (work offset and `G43`
//! tool length added). The simulated control applies each tool's measured length at `M6` (the
//! EMCO/Fanuc convention of this machine class), so the tip is the canonical position minus the
//! `G43` offset the program asked for: a program with or without `G43 H` puts the tip where it
//! says. The spindle nose is the tip plus the tool's length; the travel limits apply to the nose.
//! The stock lives in the work frame of `G54` (the profile's work offset), like the depth map the
//! CAM service planned on, so the final stock and the target map share coordinates.
//!
//! # Motion
//! Every move is a trapezoid in path length with the profile's acceleration. Consecutive moves
//! blend: the junction speed is limited by the direction change (the junction-deviation rule with
//! the program's `G64 P` tolerance, default 0.01 mm), by both moves' feeds, and by what the next
//! move's length allows to stop in (a one-move look-ahead, conservative). `G61` stops at every
//! junction. Rapids run at the profile's rapid rate and must not touch the stock (a rapid into
//! material is a crash and ends the run with an error); feed moves into material with the
//! spindle stopped end the run the same way.
//!
//! # Per revolution
//! Feed moves are cut in pieces of one spindle revolution (`w/n` mm at the current feed `w` and
//! speed `n`). Each piece: exact material removal, Kienzle torque from the hardness-weighted
//! volume and the engagement, motor current, sensor readings (several samples per revolution,
//! averaged), and one step of the feed/speed policy, whose feed and speed apply from the next
//! revolution. XY arcs are cut as sub-arcs; arcs in other planes as chords.
//!
//! # Multi-axis parts
//! A part machined from several A-axis faces, or whose program turns the A axis, is cut on one
//! dexel stock ([`super::dexel`]) in the part frame (the frame of the A = 0 face): the work frame
//! at A = `a` is the part turned by `a` about X (`work = R_x(a) · part`, the axis through the work
//! origin), so a tip at work point `w` with the spindle along +Z is at `R_x(−a) · w` with its axis
//! along `R_x(−a) · Z` in the part. The blank is the material common to every face's block (each
//! face's stock spec in its own view frame), each block reaching down through the A axis to the
//! far side of all of them when there are several (a map bounds the part from above and across,
//! not from below): the bar the faces' tops and sides bound. Feed moves at a fixed A are swept exactly; pieces
//! that turn A or follow an arc are stepped so that no tool point strays more than a quarter of
//! the finest dexel cell ([`DexelStock::cut_moving`]); every material removal, from any face,
//! is seen by every other. Each face's final stock is the one stock seen from that face.

use std::io::BufRead;

use depthmill_geometry::{HeightMap, ToolProfile};
use nalgebra::{Point3, Rotation3, Unit, Vector3};
use serde::Serialize;

use super::adaptive::{
    Aco, Constraint, Economics, FeedOnly, Fixed, Limits, Measured, Policy, Tuning, productivity,
};
use super::cutting::{Material, rev_load};
use super::dexel::{Blank, DexelCells, DexelError, DexelStock, HardSphere, OrientedBox, ToolSolid};
use super::gcode::{
    Canon, FeedMode, GcodeError, InterpConfig, Interpreter, PathMode, Plane, Pos, SpindleDir,
};
use super::profile::MachineProfile;
use super::removal::{Cut, RemovalError, Stock};
use super::sensors::{RevAverager, SensorBank};

/// Largest error of a stepped (turning or arc) piece on the dexel stock, in its finest cells.
pub const DEXEL_STEP_CELLS: f64 = 0.25;

/// Raw sensor samples averaged per revolution.
const SAMPLES_PER_REV: usize = 8;

/// Which feed/speed policy runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum PolicyKind {
    /// The seed's adaptive control of feed and speed.
    Aco,
    /// Hold cutting power by a feed override (what commercial controllers do).
    FeedOnly,
    /// The programmed feed and speed.
    Off,
}

impl PolicyKind {
    pub fn parse(s: &str) -> Option<PolicyKind> {
        match s {
            "aco" => Some(PolicyKind::Aco),
            "feed_only" => Some(PolicyKind::FeedOnly),
            "off" => Some(PolicyKind::Off),
            _ => None,
        }
    }

    pub fn as_str(self) -> &'static str {
        match self {
            PolicyKind::Aco => "aco",
            PolicyKind::FeedOnly => "feed_only",
            PolicyKind::Off => "off",
        }
    }
}

/// A tool the machine holds: its shape, teeth and measured length.
#[derive(Debug, Clone)]
pub struct MachineTool {
    pub number: u32,
    pub name: String,
    pub profile: ToolProfile,
    pub teeth: u32,
    pub length_mm: f64,
}

/// The raw stock, in the work frame (`G54`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct StockSpec {
    pub min_x_mm: f64,
    pub min_y_mm: f64,
    pub min_z_mm: f64,
    pub x_mm: f64,
    pub y_mm: f64,
    pub z_mm: f64,
    /// Z-map cell size.
    pub cell_mm: f64,
}

/// One face of a multi-axis part: the part turned to `a_deg` about the A axis, and the block of
/// stock that face's map bounds, in the work frame at that angle (the frame the CAM planned the
/// face in). The one dexel stock is the material every face's block holds.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct FaceStock {
    pub a_deg: f64,
    pub stock: StockSpec,
}

/// A hard inclusion in the stock (work frame).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Inclusion {
    pub center: [f64; 3],
    pub radius_mm: f64,
    pub factor: f32,
}

/// Everything a run needs besides the program.
#[derive(Debug, Clone)]
pub struct SimSetup {
    pub profile: MachineProfile,
    pub material: Material,
    /// The stock at A = 0 when `faces` is empty.
    pub stock: StockSpec,
    /// Multi-axis parts: each face's block at its A angle (then `stock` is not used). The part is
    /// cut on one dexel stock, the material common to every face's block (see the module docs),
    /// with the cell sizes of `dexel` (every grid at `stock.cell_mm` when `None`).
    pub faces: Vec<FaceStock>,
    pub dexel: Option<DexelCells>,
    pub tools: Vec<MachineTool>,
    pub policy: PolicyKind,
    /// Clamp F and S to the machine's ranges (with a warning) instead of refusing the program.
    pub clamp: bool,
    pub inclusions: Vec<Inclusion>,
    /// Sensor noise seed.
    pub seed: u64,
    /// Simulated seconds between telemetry rows (every revolution's data still drives the loop).
    pub telemetry_interval_s: f64,
    /// Skip material removal (motion and time only): the no-adaptation cycle time.
    pub motion_only: bool,
}

/// Errors of a run; each names the program line where there is one.
#[derive(Debug, thiserror::Error)]
pub enum SimError {
    #[error(transparent)]
    Gcode(#[from] GcodeError),
    /// Refused before anything moved on that line; `word` is the letter of the word at fault
    /// (an axis, F, S) and `column` its 1-based column in the line, when known.
    #[error("line {line}{}: {message}", at_column(.column))]
    Rejected { line: u64, message: String, word: Option<char>, column: Option<u32> },
    #[error("line {line}: crash: {message}")]
    Crash { line: u64, message: String },
    #[error("invalid setup: {0}")]
    Setup(String),
    #[error(transparent)]
    Removal(#[from] RemovalError),
    #[error("dexel stock: {0}")]
    Dexel(#[from] DexelError),
    #[error("stopped at line {line}")]
    Stopped { line: u64 },
}

fn at_column(column: &Option<u32>) -> String {
    column.map_or(String::new(), |c| format!(", column {c}"))
}

impl SimError {
    /// A refusal of `line` that names no word.
    pub fn rejected(line: u64, message: impl Into<String>) -> Self {
        SimError::Rejected { line, message: message.into(), word: None, column: None }
    }

    /// A refusal of `line` caused by its `word` (the column is found in the line's text by
    /// [`SimError::located`]).
    pub fn rejected_word(line: u64, word: char, message: impl Into<String>) -> Self {
        SimError::Rejected { line, message: message.into(), word: Some(word), column: None }
    }

    /// Fills in the column of a refusal's word from the text of line `line_no`: the first word
    /// with that letter outside comments.
    fn located(self, line_no: u64, text: &str) -> Self {
        match self {
            SimError::Rejected { line, message, word: Some(w), column: None } if line == line_no => {
                let column = word_column(text, w);
                SimError::Rejected { line, message, word: Some(w), column }
            }
            other => other,
        }
    }
}

/// 1-based column of the first `letter` word (a letter followed by a number) outside `( )` and
/// `;` comments.
fn word_column(text: &str, letter: char) -> Option<u32> {
    let bytes = text.as_bytes();
    let mut depth = 0u32;
    for (i, &b) in bytes.iter().enumerate() {
        match b {
            b'(' => depth += 1,
            b')' => depth = depth.saturating_sub(1),
            b';' if depth == 0 => return None,
            _ if depth == 0 && b.eq_ignore_ascii_case(&(letter as u8)) => {
                let next = bytes[i + 1..].iter().find(|c| !c.is_ascii_whitespace());
                if next.is_some_and(|c| c.is_ascii_digit() || matches!(c, b'-' | b'+' | b'.')) {
                    return u32::try_from(i + 1).ok();
                }
            }
            _ => {}
        }
    }
    None
}

/// One telemetry row.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct TelemetryRow {
    pub time_s: f64,
    pub line: u64,
    /// Tip position, work frame.
    pub x_mm: f64,
    pub y_mm: f64,
    pub z_mm: f64,
    pub a_deg: f64,
    pub feed_mm_min: f64,
    pub spindle_rpm: f64,
    /// Cutting torque, the model's truth.
    pub torque_true_nm: f64,
    /// Torque ADC, revolution mean and counts of the last sample.
    pub torque_adc_nm: f64,
    pub torque_counts: i32,
    /// Spindle current, revolution mean.
    pub current_a: f64,
    /// Cutting torque estimated from the current (what the loop uses).
    pub torque_from_current_nm: f64,
    pub power_w: f64,
    pub removal_mm3_s: f64,
    /// Active constraints as a bit mask over `Constraint::ALL` (see [`active_names`]).
    pub active: u16,
}

/// Warnings and figures of a finished run.
#[derive(Debug, Clone, Default, Serialize)]
pub struct SimReport {
    pub policy: &'static str,
    pub blocks: u64,
    pub moves: u64,
    pub revolutions: u64,
    pub cycle_time_s: f64,
    pub cutting_time_s: f64,
    pub removed_mm3: f64,
    pub max_torque_nm: f64,
    pub max_power_w: f64,
    pub max_current_a: f64,
    /// Revolutions during which torque or power exceeded the limits.
    pub revs_over_torque: u64,
    pub revs_over_power: u64,
    pub productivity_index: f64,
    pub cells_updated: u64,
    /// Moves that turn the A axis or run at A != 0 (a program that has any is cut on the dexel
    /// stock).
    pub turned_moves: u64,
    pub warnings: Vec<String>,
}

/// Live progress callback: (fraction of lines, telemetry row).
pub type Observer<'a> = &'a mut dyn FnMut(&TelemetryRow);

/// The permitted region for a tool on this machine. Torque: 60 % of the motor's at the speed, and
/// at most what the tool's shank takes (`0.1·r³` N·m with r in mm, an assumption for carbide
/// end mills); deflection: a carbide cantilever of 0.8·D core over 3·D stick-out bending 10 µm;
/// feed per tooth 0.002 mm to `0.02·r` (0.01-0.15); power 90 % of the motor's.
fn limits_for(profile: &MachineProfile, tool: &MachineTool, rpm_hint: f64) -> Limits {
    let r = tool.profile.radius_mm().max(0.1);
    let d_core = 1.6 * r;
    let stick = 6.0 * r;
    let inertia = std::f64::consts::PI * d_core.powi(4) / 64.0;
    let stiffness = 3.0 * 600_000.0 * inertia / stick.powi(3);
    Limits {
        torque_max_nm: (0.6 * profile.spindle.max_torque_nm(rpm_hint.max(profile.spindle.rpm_min)))
            .min(0.002 * r.powi(3) * 50.0),
        force_max_n: stiffness * 0.01,
        tool_radius_mm: r,
        teeth: tool.teeth.max(1),
        fz_min_mm: 0.002,
        fz_max_mm: (0.02 * r).clamp(0.01, 0.15),
        feed_min_mm_min: profile.motion.feed_min_mm_min,
        feed_max_mm_min: profile.motion.feed_max_mm_min,
        rpm_min: profile.spindle.rpm_min,
        rpm_max: profile.spindle.rpm_max,
        power_max_w: 0.9 * profile.spindle.power_w,
    }
}

/// Trapezoid of a path of `len` from speed `v0` to `v1` (clamped to what `a` allows) at cruise
/// `vmax`: the time.
fn trapezoid_time(len: f64, v0: f64, v1: f64, vmax: f64, a: f64) -> f64 {
    if len <= 0.0 {
        return 0.0;
    }
    let vmax = vmax.max(1e-9);
    let v0 = v0.min(vmax);
    let v1 = v1.min(vmax).min((v0 * v0 + 2.0 * a * len).sqrt());
    // Peak speed if accelerating then decelerating with no cruise.
    let vp = ((2.0 * a * len + v0 * v0 + v1 * v1) / 2.0).sqrt();
    if vp <= vmax {
        (vp - v0) / a + (vp - v1) / a
    } else {
        let d_acc = (vmax * vmax - v0 * v0) / (2.0 * a);
        let d_dec = (vmax * vmax - v1 * v1) / (2.0 * a);
        (vmax - v0) / a + (vmax - v1) / a + (len - d_acc - d_dec).max(0.0) / vmax
    }
}

/// Junction speed between two unit directions at the given tolerance (junction deviation).
fn junction_speed(d0: [f64; 3], d1: [f64; 3], tolerance_mm: f64, a: f64) -> f64 {
    let cos = -(d0[0] * d1[0] + d0[1] * d1[1] + d0[2] * d1[2]);
    if cos > 0.999_999 {
        return 0.0; // reversal
    }
    if cos < -0.999_999 {
        return f64::INFINITY; // straight on
    }
    let sin_half = ((1.0 - cos) / 2.0).sqrt();
    (a * tolerance_mm * sin_half / (1.0 - sin_half)).sqrt()
}

/// A pending motion (one-move look-ahead for the junction speed).
#[derive(Debug, Clone, Copy)]
struct Pending {
    canon: Canon,
    from: Pos,
    len: f64,
    dir_start: [f64; 3],
    dir_end: [f64; 3],
    rapid: bool,
}

/// The running machine.
pub struct Machine<'a> {
    setup: &'a SimSetup,
    interp_cfg: InterpConfig,
    /// The Z-map stock of a 3-axis part (at A = 0); empty when motion only or multi-axis.
    stocks: Vec<(f64, Stock)>,
    /// The one stock of a multi-axis part, and each tool as a solid (by index in `setup.tools`).
    dexel: Option<(DexelStock, Vec<ToolSolid>)>,
    sensors: SensorBank,
    policy: Box<dyn Policy>,
    policy_enabled: bool,
    /// Machine coordinates of the controlled point (as the interpreter sees it).
    pos: Pos,
    tlo_mm: f64,
    tool: Option<usize>,
    feed_prog: f64,
    feed_mode: FeedMode,
    /// Inverse time (G93): the running move's length (mm, or degrees for a rotary-only move),
    /// which F times gives the feed.
    inverse_len: f64,
    rpm_prog: f64,
    spindle: SpindleDir,
    /// Feed and speed the policy commands now.
    feed_now: f64,
    rpm_now: f64,
    /// Path speed at the end of the last move, mm/s.
    v_end: f64,
    blend_tol: Option<f64>,
    time_s: f64,
    next_row_s: f64,
    pending: Option<Pending>,
    avg: RevAverager,
    pub report: SimReport,
    last_row: Option<TelemetryRow>,
    /// The last cut on a Z-map stock: the stock's index, the tool's and the tip's end point. A
    /// cut from that point with that tool continues it ([`Stock::cut_line_after`]).
    last_cut: Option<(usize, Option<usize>, Point3<f64>)>,
    /// Continue cuts (off: every piece is cut as a fresh move, the reference in the tests).
    continue_cuts: bool,
}

impl<'a> Machine<'a> {
    /// A machine ready to run, the stock in place.
    pub fn new(setup: &'a SimSetup) -> Result<Self, SimError> {
        let p = &setup.profile;
        let w = p.work_offset;
        let mut interp_cfg = InterpConfig {
            home: Pos::new(0.0, 0.0, p.axes.z.max_mm, 0.0),
            initial_position: Pos::new(p.axes.x.min_mm, p.axes.y.min_mm, p.axes.z.max_mm, 0.0),
            ..Default::default()
        };
        interp_cfg.work_offsets = [Pos::new(w.x_mm, w.y_mm, w.z_mm, 0.0); 6];
        for t in &setup.tools {
            interp_cfg.tools.insert(t.number, t.length_mm);
        }
        let mut stocks = Vec::new();
        let mut dexel = None;
        if !setup.motion_only && !setup.faces.is_empty() {
            dexel = Some(dexel_stock(setup)?);
        } else if !setup.motion_only {
            for (a_deg, s) in [(0.0, setup.stock)] {
                let mut stock = Stock::block(
                    Point3::new(s.min_x_mm, s.min_y_mm, s.min_z_mm),
                    s.x_mm,
                    s.y_mm,
                    s.z_mm,
                    s.cell_mm,
                )?;
                for inc in &setup.inclusions {
                    stock.set_hardness_sphere(Point3::from(inc.center), inc.radius_mm, inc.factor)?;
                }
                stocks.push((a_deg, stock));
            }
        }
        let policy: Box<dyn Policy> = Box::new(Fixed::default());
        Ok(Machine {
            setup,
            pos: interp_cfg.initial_position,
            interp_cfg,
            stocks,
            last_cut: None,
            continue_cuts: true,
            dexel,
            sensors: SensorBank::new(p.sensors, setup.seed),
            policy,
            policy_enabled: true,
            tlo_mm: 0.0,
            tool: None,
            feed_prog: 0.0,
            feed_mode: FeedMode::PerMinute,
            inverse_len: 0.0,
            rpm_prog: 0.0,
            spindle: SpindleDir::Off,
            feed_now: 0.0,
            rpm_now: 0.0,
            v_end: 0.0,
            blend_tol: Some(0.01),
            time_s: 0.0,
            next_row_s: 0.0,
            pending: None,
            avg: RevAverager::default(),
            report: SimReport { policy: setup.policy.as_str(), ..Default::default() },
            last_row: None,
        })
    }

    /// The interpreter configuration matching this machine (tool table, offsets, home).
    pub fn interp_config(&self) -> InterpConfig {
        self.interp_cfg.clone()
    }

    /// The stock as it is now (work frame), `None` for a motion-only run.
    pub fn stock(&self) -> Option<&Stock> {
        self.stocks.first().map(|(_, s)| s)
    }

    /// The 3-axis stock with its A angle (empty for a multi-axis part).
    pub fn stocks(&self) -> &[(f64, Stock)] {
        &self.stocks
    }

    /// The multi-axis part's one stock.
    pub fn dexel(&self) -> Option<&DexelStock> {
        self.dexel.as_ref().map(|(d, _)| d)
    }

    /// Each face's final stock: the Z-map of a 3-axis part, or the one dexel stock seen from every
    /// face on the grid of its block (from 1 mm above the block's top; the block's bottom where
    /// the view finds no material, and no value (NaN) where the blank itself had none along the
    /// view: a face's block reaches beyond the material common to every face, and what a face's
    /// map asks for there was never in the stock to be cut).
    pub fn face_maps(&self) -> Result<Vec<(f64, HeightMap)>, SimError> {
        let Some((dexel, _)) = &self.dexel else {
            return Ok(self.stocks.iter().map(|(a, s)| (*a, s.to_height_map())).collect());
        };
        let blank = blank_of(self.setup);
        self.setup
            .faces
            .iter()
            .map(|f| {
                let s = f.stock;
                let nx = (s.x_mm / s.cell_mm).ceil().max(1.0) as u32;
                let ny = (s.y_mm / s.cell_mm).ceil().max(1.0) as u32;
                let mut meta = depthmill_geometry::HeightMapMeta::new(nx, ny, s.cell_mm);
                meta.origin_x_mm = s.min_x_mm;
                meta.origin_y_mm = s.min_y_mm;
                meta.z_min_mm = s.min_z_mm;
                meta.z_max_mm = s.min_z_mm + s.z_mm;
                let z_top = s.min_z_mm + s.z_mm + 1.0;
                let part_from_view = part_from_work(f.a_deg);
                let mut map = dexel.view_heights(&part_from_view, &meta, z_top)?;
                let down = part_from_view * Vector3::new(0.0, 0.0, -1.0);
                let depth = z_top - s.min_z_mm;
                let width = meta.width as usize;
                for (k, z) in map.data_mut().iter_mut().enumerate() {
                    let (x, y) = meta.cell_center((k % width) as u32, (k / width) as u32);
                    let start = part_from_view * Point3::new(x, y, z_top);
                    if !blank.ray_extent(&start, &down).is_some_and(|(l, h)| h > 0.0 && l < depth) {
                        *z = f32::NAN;
                    }
                }
                Ok((f.a_deg, map))
            })
            .collect()
    }

    /// The face whose A angle is `a_deg` (to 0.001°, modulo 360).
    fn face_index(&self, a_deg: f64) -> Option<usize> {
        self.stocks.iter().position(|(a, _)| {
            let d = (a_deg - a).rem_euclid(360.0);
            d.min(360.0 - d) < 1e-3
        })
    }

    /// The tip in the work frame for a commanded machine position, on whole motor steps (the
    /// steppers move in `step_mm` increments).
    fn work(&self, p: Pos) -> Point3<f64> {
        work_tip(&self.setup.profile, self.tlo_mm, p, true)
    }

    fn current_tool(&self) -> Option<&MachineTool> {
        self.tool.map(|i| &self.setup.tools[i])
    }

    fn make_policy(&self, tool: &MachineTool) -> Box<dyn Policy> {
        let limits = limits_for(&self.setup.profile, tool, self.rpm_prog);
        match self.setup.policy {
            PolicyKind::Aco => Box::new(Aco::new(limits, Tuning::default())),
            PolicyKind::FeedOnly => Box::new(FeedOnly::new(limits, 0.5 * limits.power_max_w.min(200.0))),
            PolicyKind::Off => Box::new(Fixed::default()),
        }
    }

    fn feed_mm_min(&self) -> f64 {
        match self.feed_mode {
            FeedMode::PerMinute => self.feed_prog,
            FeedMode::PerRevolution => self.feed_prog * self.rpm_prog,
            FeedMode::InverseTime => self.feed_prog * self.inverse_len,
        }
    }

    /// Feeds one canonical command. `observe` sees telemetry rows as they are made.
    pub fn execute(&mut self, canon: Canon, observe: Observer<'_>) -> Result<(), SimError> {
        match canon {
            Canon::Traverse { .. } | Canon::Feed { .. } | Canon::Arc { .. } => {
                self.check_envelope(&canon)?;
                let next = self.plan(canon);
                if let Some(prev) = self.pending.replace(next) {
                    let v_junction = self.junction(&prev, &next);
                    self.run_move(prev, v_junction, observe)?;
                }
            }
            other => {
                self.flush(observe)?;
                self.apply(other)?;
            }
        }
        Ok(())
    }

    /// Ends the program: runs the last move to a stop.
    pub fn finish(&mut self, observe: Observer<'_>) -> Result<(), SimError> {
        self.flush(observe)?;
        if let Some((stock, _)) = &mut self.dexel {
            stock.flush()?;
        }
        if let Some(row) = self.last_row {
            observe(&row);
        }
        Ok(())
    }

    fn flush(&mut self, observe: Observer<'_>) -> Result<(), SimError> {
        if let Some(prev) = self.pending.take() {
            self.run_move(prev, 0.0, observe)?;
        }
        Ok(())
    }

    fn apply(&mut self, canon: Canon) -> Result<(), SimError> {
        let prof = &self.setup.profile;
        match canon {
            Canon::SetFeedRate { line, rate, mode } => {
                self.feed_mode = mode;
                self.feed_prog = rate;
                let w = self.feed_mm_min();
                // Inverse time: each move's feed is checked as it starts (it depends on its length).
                if rate > 0.0
                    && (mode == FeedMode::PerMinute
                        || (mode == FeedMode::PerRevolution && self.rpm_prog > 0.0))
                {
                    self.check_range(
                        line,
                        "F",
                        w,
                        prof.motion.feed_min_mm_min,
                        prof.motion.feed_max_mm_min,
                        "mm/min",
                    )?;
                }
                // programmed() clamps to the machine's range (refused above unless clamping).
                self.programmed();
            }
            Canon::SetSpindleSpeed { line, rpm } => {
                if rpm > 0.0 {
                    self.check_range(line, "S", rpm, prof.spindle.rpm_min, prof.spindle.rpm_max, "rpm")?;
                }
                self.rpm_prog = rpm.clamp(0.0, prof.spindle.rpm_max);
                if rpm > 0.0 {
                    self.rpm_prog = self.rpm_prog.max(prof.spindle.rpm_min);
                }
                self.programmed();
            }
            Canon::Spindle { dir, .. } => {
                // The spindle ramps to speed before the next move (a dwell of the ramp time).
                if dir != SpindleDir::Off && self.spindle == SpindleDir::Off {
                    self.time_s += self.rpm_prog / prof.spindle.accel_rpm_s;
                }
                self.spindle = dir;
            }
            Canon::ToolChange { line, tool } => {
                self.tool = if tool == 0 {
                    None
                } else {
                    let i = self.setup.tools.iter().position(|t| t.number == tool).ok_or_else(|| {
                        SimError::rejected_word(
                            line,
                            'T',
                            format!("T{tool} is not in the machine's tool table"),
                        )
                    })?;
                    Some(i)
                };
                self.spindle = SpindleDir::Off;
                // A manual change on this machine class: 20 s.
                self.time_s += 20.0;
                if let Some(t) = self.current_tool().cloned() {
                    self.policy = self.make_policy(&t);
                    self.programmed();
                }
            }
            Canon::ToolLengthOffset { mm, .. } => self.tlo_mm = mm,
            Canon::Dwell { seconds, .. } => self.time_s += seconds.max(0.0),
            Canon::AdaptiveFeed { enabled, .. } => {
                self.policy_enabled = enabled;
                // Off: back to the programmed feed and speed; on: the loop starts from them.
                self.programmed();
            }
            Canon::SetPathMode { mode, .. } => {
                self.blend_tol = match mode {
                    PathMode::ExactPath | PathMode::ExactStop => None,
                    PathMode::Blend { tolerance_mm, .. } => Some(tolerance_mm.unwrap_or(0.01).max(0.001)),
                }
            }
            Canon::Pause { .. }
            | Canon::Coolant { .. }
            | Canon::WorkOffset { .. }
            | Canon::ProgramEnd { .. }
            | Canon::Traverse { .. }
            | Canon::Feed { .. }
            | Canon::Arc { .. } => {}
        }
        Ok(())
    }

    fn check_range(
        &mut self,
        line: u64,
        word: &str,
        v: f64,
        lo: f64,
        hi: f64,
        unit: &str,
    ) -> Result<(), SimError> {
        if v >= lo - 1e-9 && v <= hi + 1e-9 {
            return Ok(());
        }
        let message = format!("{word}{v} is outside the machine's {lo}-{hi} {unit}");
        if self.setup.clamp {
            self.report.warnings.push(format!("line {line}: {message}; clamped"));
            Ok(())
        } else {
            Err(SimError::rejected_word(line, word.chars().next().unwrap_or('F'), message))
        }
    }

    fn programmed(&mut self) {
        let prof = &self.setup.profile;
        let w = self.feed_mm_min().clamp(prof.motion.feed_min_mm_min, prof.motion.feed_max_mm_min);
        let n = self.rpm_prog.clamp(prof.spindle.rpm_min, prof.spindle.rpm_max);
        self.feed_now = w;
        self.rpm_now = n;
        self.policy.programmed(w, n);
    }

    fn check_envelope(&self, canon: &Canon) -> Result<(), SimError> {
        let Some(to) = canon.end_point() else { return Ok(()) };
        let prof = &self.setup.profile;
        let length = self.current_tool().map_or(0.0, |t| t.length_mm);
        let line = canon.line();
        let a = &prof.axes;
        // The end point, and for an arc the points where it is widest along the plane's axes (it
        // can bulge out of the travel between two ends inside it).
        let mut points = vec![to];
        if let Canon::Arc { end, plane, center, rotation, .. } = *canon {
            let from = self.pending.as_ref().map_or(self.pos, |p| p.canon.end_point().unwrap_or(p.from));
            points.extend(arc_extremes(from, end, plane, center, rotation));
        }
        for p in points {
            // Nose = tip + length; the tip is the canonical point minus the program's G43 offset.
            let nose_z = p.z - self.tlo_mm + length;
            for (axis, v, r) in [("X", p.x, a.x), ("Y", p.y, a.y), ("Z", nose_z, a.z)] {
                if !r.contains(v, 1e-6) {
                    return Err(SimError::rejected_word(
                        line,
                        axis.chars().next().unwrap_or('X'),
                        format!(
                            "the move leaves the machine's travel: {axis} {v:.3} mm (spindle nose) is outside [{}, {}]",
                            r.min_mm, r.max_mm
                        ),
                    ));
                }
            }
        }
        if !prof.a_is_continuous() && !a.a.contains(to.a, 1e-6) {
            return Err(SimError::rejected_word(
                line,
                'A',
                format!("A {:.3}° is outside [{}, {}]", to.a, a.a.min_mm, a.a.max_mm),
            ));
        }
        if !prof.has_c() && to.c.abs() > 1e-9 {
            return Err(SimError::rejected_word(
                line,
                'C',
                format!("C {:.3}°: the {} has no C axis (axes X, Y, Z, A)", to.c, prof.name),
            ));
        }
        if let Some(c) = prof.c_limits()
            && !c.contains(to.c, 1e-6)
        {
            return Err(SimError::rejected_word(
                line,
                'C',
                format!("C {:.3}° is outside [{}, {}]", to.c, c.min_mm, c.max_mm),
            ));
        }
        Ok(())
    }

    fn plan(&self, canon: Canon) -> Pending {
        let from = self.pending.as_ref().map_or(self.pos, |p| p.canon.end_point().unwrap_or(p.from));
        let rapid = matches!(canon, Canon::Traverse { .. });
        let to = canon.end_point().unwrap_or(from);
        let (len, d0, d1) = match canon {
            Canon::Arc { end, plane, center, rotation, .. } => {
                arc_geometry(from, end, plane, center, rotation)
            }
            _ => {
                let d = [to.x - from.x, to.y - from.y, to.z - from.z];
                let l = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
                let u = if l > 0.0 { [d[0] / l, d[1] / l, d[2] / l] } else { [0.0; 3] };
                (l, u, u)
            }
        };
        Pending { canon, from, len, dir_start: d0, dir_end: d1, rapid }
    }

    fn junction(&self, prev: &Pending, next: &Pending) -> f64 {
        let a = self.setup.profile.motion.accel_mm_s2;
        let Some(tol) = self.blend_tol else { return 0.0 };
        if prev.rapid != next.rapid || prev.len <= 0.0 || next.len <= 0.0 {
            return 0.0;
        }
        let v_feed = if next.rapid { self.setup.profile.motion.rapid_mm_min } else { self.feed_now } / 60.0;
        junction_speed(prev.dir_end, next.dir_start, tol, a).min(v_feed).min((2.0 * a * next.len).sqrt())
    }

    fn run_move(&mut self, m: Pending, v_exit: f64, observe: Observer<'_>) -> Result<(), SimError> {
        /// Depth of material over the tool's face a rapid may shave without counting as a crash, mm.
        const RAPID_SCRAPE_MM: f64 = 0.05;
        let prof = &self.setup.profile;
        let a = prof.motion.accel_mm_s2;
        self.report.moves += 1;
        let to = m.canon.end_point().unwrap_or(m.from);
        let line = m.canon.line();
        let a_move = (to.a - m.from.a).abs();
        let c_move = (to.c - m.from.c).abs();
        let turned = a_move > 1e-9 || c_move > 1e-9 || to.a.abs() > 1e-9 || to.c.abs() > 1e-9;
        if !m.rapid && turned {
            self.report.turned_moves += 1;
        }
        // The rotary axes' time for the move, each at its rate.
        let rotary_s =
            (a_move / (prof.motion.a_rate_deg_min / 60.0)).max(c_move / (prof.c_rate_deg_min() / 60.0));
        if m.rapid
            && let (Some(ti), true) = (self.tool, self.dexel.is_some())
        {
            // A rapid that touches material is a crash (see below); on the one stock.
            let cut = self.cut_dexel(&m, ti, 0.0, 1.0)?;
            let r = self.setup.tools[ti].profile.radius_mm();
            // Besides the scrape the Z-map allows, the slivers a turning feed move's stepped
            // sweep may leave along the tool's side (at most the step error thick over the
            // tool's length and diameter).
            let sliver = self.dexel.as_ref().map_or(0.0, |(d, solids)| {
                let len = solids.get(ti).map_or(0.0, ToolSolid::length_mm);
                2.0 * r * len * DEXEL_STEP_CELLS * d.min_cell_mm()
            });
            let allowed = (std::f64::consts::PI * r * r * RAPID_SCRAPE_MM + sliver).max(1e-3);
            if cut.volume_mm3 > allowed {
                return Err(SimError::Crash {
                    line,
                    message: format!("rapid move into the stock ({:.3} mm³ in the way)", cut.volume_mm3),
                });
            }
        }
        // Cut per revolution. A move that only turns A or C runs its degrees at the feed read as
        // degrees per minute (as LinuxCNC does), capped by the axis's rate.
        let rotary_only = m.len <= 1e-9 && (a_move > 1e-9 || c_move > 1e-9);
        let plen = if rotary_only { a_move.max(c_move) } else { m.len };
        if !m.rapid && self.feed_mode == FeedMode::InverseTime {
            // G93: the move takes 1/F minutes, so its feed is its length times F.
            self.inverse_len = plen;
            let w = self.feed_mm_min();
            if w > prof.motion.feed_max_mm_min {
                self.report.warnings.push(format!(
                    "line {line}: inverse time F{} asks {w:.1} mm/min over {plen:.3}, above the machine's {} mm/min: the move takes longer",
                    self.feed_prog, prof.motion.feed_max_mm_min
                ));
            }
            self.programmed();
        }
        let prof = &self.setup.profile;
        if m.rapid || (self.stocks.is_empty() && self.dexel.is_none()) {
            let vmax = if m.rapid { prof.motion.rapid_mm_min } else { self.feed_now } / 60.0;
            let mut t = trapezoid_time(m.len, self.v_end, v_exit, vmax, a);
            t = t.max(rotary_s);
            if m.rapid
                && to.c.abs() < 1e-9
                && let Some(i) = self.face_index(to.a)
            {
                let stock = &mut self.stocks[i].1;
                // A rapid that touches material is a crash.
                let tool = self.tool.map(|i| &self.setup.tools[i]);
                if let Some(tool) = tool {
                    // On whole motor steps, as the feed moves are cut: from exact positions a
                    // grid cell on the rim of the tool the feed left standing (by a fraction of a
                    // step) would read as a full column of material in the way.
                    let (f, e) =
                        (work_tip(prof, self.tlo_mm, m.from, true), work_tip(prof, self.tlo_mm, to, true));
                    let cut = if self.continue_cuts && self.last_cut == Some((i, self.tool, f)) {
                        stock.cut_line_after(&tool.profile, f, e)?
                    } else {
                        stock.cut_line(&tool.profile, f, e)?
                    };
                    self.last_cut = Some((i, self.tool, e));
                    // A rapid that shaves a sliver (left by the feed move's last partial
                    // revolution, or the steps' rounding) marks the part; one that engages the
                    // tool's face deeper than RAPID_SCRAPE_MM is a crash.
                    let r = tool.profile.radius_mm();
                    let allowed = (std::f64::consts::PI * r * r * RAPID_SCRAPE_MM).max(1e-3);
                    if cut.volume_mm3 > allowed {
                        return Err(SimError::Crash {
                            line,
                            message: format!(
                                "rapid move into the stock ({:.3} mm³ in the way)",
                                cut.volume_mm3
                            ),
                        });
                    }
                }
            }
            self.time_s += t;
            self.v_end = v_exit.min(vmax);
            self.pos = to;
            return Ok(());
        }
        if self.feed_now <= 0.0 {
            return Err(SimError::rejected(line, "feed move with no feed rate"));
        }
        if self.dexel.is_none()
            && (a_move > 1e-9 || c_move > 1e-9 || to.c.abs() > 1e-9 || self.face_index(to.a).is_none())
        {
            self.report.warnings.push(format!(
                "line {line}: a feed move {} A={:.3}° C={:.3}° is timed but not cut: a 3-axis run's Z-map stock cuts at A = 0, C = 0 only (a multi-axis setup cuts it on the dexel stock)",
                if a_move > 1e-9 || c_move > 1e-9 { "turning to" } else { "at" },
                to.a,
                to.c
            ));
            let t = trapezoid_time(m.len, self.v_end, v_exit, self.feed_now / 60.0, a);
            self.time_s += t.max(rotary_s);
            self.pos = to;
            self.v_end = 0.0;
            return Ok(());
        }
        let Some(tool) = self.current_tool().cloned() else {
            return Err(SimError::rejected(line, "feed move with no tool in the spindle"));
        };
        let rotary_rate = if c_move > a_move {
            self.setup.profile.c_rate_deg_min()
        } else {
            self.setup.profile.motion.a_rate_deg_min
        };
        let mut s = 0.0;
        let mut v = self.v_end;
        let mut prev_tip = self.work(m.from);
        let mut guard = 0u64;
        while s < plen - 1e-12 {
            guard += 1;
            if guard > 50_000_000 {
                return Err(SimError::rejected(
                    line,
                    "move too long to simulate per revolution (more than 50 000 000 revolutions)",
                ));
            }
            let rpm = if self.spindle == SpindleDir::Off { 0.0 } else { self.rpm_now };
            let w = self.feed_now;
            let vmax = if rotary_only { w.min(rotary_rate) } else { w };
            let per_rev = if rpm > 0.0 { w / rpm } else { plen };
            let ds = per_rev.min(plen - s).max(1e-6);
            let s1 = (s + ds).min(plen);
            // Speed along the piece: accelerate toward w, decelerate to reach v_exit at the end.
            let v_target = (vmax / 60.0).min((v_exit * v_exit + 2.0 * a * (plen - s1)).sqrt());
            let v1 = if v_target >= v {
                v_target.min((v * v + 2.0 * a * ds).sqrt())
            } else {
                v_target.max((v * v - 2.0 * a * ds).max(0.0).sqrt())
            };
            // Constant acceleration from v to v1, or, when the piece starts and ends (nearly) at
            // rest (a move shorter than one revolution between two stops), the time to speed up
            // and slow down within it.
            let dt = (2.0 * ds / (v + v1).max(1e-9)).min(trapezoid_time(
                ds,
                v,
                v1,
                (vmax / 60.0).max(v).max(v1),
                a,
            ));
            let tip = self.work(point_at(&m, s1 / plen));
            let cut = match (self.tool, self.dexel.is_some()) {
                (Some(ti), true) => self.cut_dexel(&m, ti, s / plen, s1 / plen)?,
                _ => self.cut_piece(&m, &tool.profile, prev_tip, tip)?,
            };
            if cut.volume_mm3 > 1e-6 && rpm <= 0.0 {
                return Err(SimError::Crash {
                    line,
                    message: "feed move into the stock with the spindle stopped".into(),
                });
            }
            self.time_s += dt;
            self.revolution(&tool, &cut, w, rpm, dt, line, tip, to.a, observe);
            prev_tip = tip;
            s = s1;
            v = v1;
        }
        self.v_end = v;
        self.pos = to;
        Ok(())
    }

    /// Cuts one revolution's piece of move `m` on the Z-map stock of its face. A straight piece
    /// that starts where the last straight cut on that stock, by the same tool, ended continues
    /// it.
    fn cut_piece(
        &mut self,
        m: &Pending,
        tool: &ToolProfile,
        from: Point3<f64>,
        to: Point3<f64>,
    ) -> Result<Cut, SimError> {
        let a = m.canon.end_point().map_or(0.0, |p| p.a);
        let Some(i) = self.face_index(a) else { return Ok(Cut::default()) };
        let after = self.continue_cuts && self.last_cut == Some((i, self.tool, from));
        self.last_cut = Some((i, self.tool, to));
        let stock = &mut self.stocks[i].1;
        match m.canon {
            Canon::Arc { plane: Plane::Xy, center, rotation, .. } => {
                // A level arc is cut on its mean radius, so its end may lie a fraction of a
                // cell off `to`: what follows does not continue it.
                self.last_cut = None;
                let w = self.setup.profile.work_offset;
                let c = (center[0] - w.x_mm, center[1] - w.y_mm);
                // A piece is less than a full turn: no extra turns.
                Ok(stock.cut_arc_xy(tool, from, to, c, rotation > 0, 0)?)
            }
            _ if after => Ok(stock.cut_line_after(tool, from, to)?),
            _ => Ok(stock.cut_line(tool, from, to)?),
        }
    }

    /// Cuts the piece `[t0, t1]` (fractions of the move) of move `m` with tool `ti` on the dexel
    /// stock, in the part frame (see the module docs). The piece's ends are on whole motor steps;
    /// a piece at a fixed A along a line is swept exactly, one that turns A or follows an arc is
    /// stepped within a quarter of the finest cell (between the stepped ends, the true path is
    /// shifted linearly so it meets them).
    fn cut_dexel(&mut self, m: &Pending, ti: usize, t0: f64, t1: f64) -> Result<Cut, SimError> {
        let prof = &self.setup.profile;
        let tlo = self.tlo_mm;
        let Some((stock, solids)) = &mut self.dexel else { return Ok(Cut::default()) };
        let Some(solid) = solids.get(ti) else { return Ok(Cut::default()) };
        let (p0, p1) = (point_at(m, t0), point_at(m, t1));
        let exact = |p: Pos| work_tip(prof, tlo, p, false);
        let (q0, q1) = (work_tip(prof, tlo, p0, true), work_tip(prof, tlo, p1, true));
        let (d0, d1) = (q0 - exact(p0), q1 - exact(p1));
        let straight = !matches!(m.canon, Canon::Arc { .. })
            && (p1.a - p0.a).abs() < 1e-12
            && (p1.c - p0.c).abs() < 1e-12;
        if straight {
            let r = part_from_table(p0.a, p0.c);
            let axis = Unit::new_normalize(r * Vector3::z());
            // The other grids take runs of pieces as one line within one motor step of them (the
            // pieces' ends are already up to half a step off the commanded path in each axis).
            let err = prof.step_mm.min(DEXEL_STEP_CELLS * stock.min_cell_mm());
            return Ok(stock.cut_run(solid, &(r * q0), &(r * q1), &axis, err)?);
        }
        let pose = |s: f64| {
            let p = point_at(m, t0 + (t1 - t0) * s);
            let w = exact(p) + d0 * (1.0 - s) + d1 * s;
            let r = part_from_table(p.a, p.c);
            (r * w, Unit::new_normalize(r * Vector3::z()))
        };
        let err = DEXEL_STEP_CELLS * stock.min_cell_mm();
        Ok(stock.cut_moving(solid, &pose, err)?)
    }

    #[allow(clippy::too_many_arguments)]
    fn revolution(
        &mut self,
        tool: &MachineTool,
        cut: &Cut,
        w: f64,
        rpm: f64,
        dt: f64,
        line: u64,
        tip: Point3<f64>,
        a_deg: f64,
        observe: Observer<'_>,
    ) {
        let prof = &self.setup.profile;
        self.report.revolutions += 1;
        self.report.removed_mm3 += cut.volume_mm3;
        self.report.cells_updated += cut.cells_updated;
        if cut.volume_mm3 > 0.0 {
            self.report.cutting_time_s += dt;
        }
        let fz = if rpm > 0.0 { w / rpm / f64::from(tool.teeth.max(1)) } else { 0.0 };
        let load =
            rev_load(&self.setup.material, cut.hard_volume_mm3, fz, cut.engagement_deg.to_radians(), rpm);
        let current = if rpm > 0.0 { prof.spindle.current_for_torque(load.torque_nm) } else { 0.0 };
        for _ in 0..SAMPLES_PER_REV {
            let r = self.sensors.read(load.torque_nm, current, rpm, dt / SAMPLES_PER_REV as f64);
            self.avg.push(&r);
        }
        let (t_adc, i_avg, t_max) = self.avg.take().unwrap_or_default();
        let t_est =
            ((i_avg - prof.spindle.no_load_current_a) * prof.spindle.torque_constant_nm_per_a).max(0.0);
        let power = t_est * rpm * std::f64::consts::TAU / 60.0;
        self.report.max_torque_nm = self.report.max_torque_nm.max(load.torque_nm);
        self.report.max_power_w = self.report.max_power_w.max(load.power_w);
        self.report.max_current_a = self.report.max_current_a.max(current);
        let limits = limits_for(prof, tool, rpm);
        if load.torque_nm > limits.torque_max_nm {
            self.report.revs_over_torque += 1;
        }
        if load.power_w > limits.power_max_w {
            self.report.revs_over_power += 1;
        }
        let measured =
            Measured { feed_mm_min: w, rpm, torque_nm: t_est, torque_adc_max_nm: t_max, power_w: power };
        let decision =
            if self.policy_enabled && rpm > 0.0 { Some(self.policy.step(&measured)) } else { None };
        let active = decision.as_ref().map_or(0, |d| active_mask(&d.active));
        if let Some(d) = decision {
            self.feed_now = d.feed_mm_min;
            self.rpm_now = d.rpm;
        }
        let row = TelemetryRow {
            time_s: self.time_s,
            line,
            x_mm: tip.x,
            y_mm: tip.y,
            z_mm: tip.z,
            a_deg,
            feed_mm_min: w,
            spindle_rpm: rpm,
            torque_true_nm: load.torque_nm,
            torque_adc_nm: t_adc,
            torque_counts: (t_adc / prof.sensors.torque_nm_per_count).round() as i32,
            current_a: i_avg,
            torque_from_current_nm: t_est,
            power_w: power,
            removal_mm3_s: if dt > 0.0 { cut.volume_mm3 / dt } else { 0.0 },
            active,
        };
        self.last_row = Some(row);
        if self.time_s >= self.next_row_s {
            self.next_row_s = self.time_s + self.setup.telemetry_interval_s;
            observe(&row);
        }
    }

    /// The productivity index of the run (seed 002) from its mean feed, with the cut's width and
    /// depth estimated from the removed volume.
    pub fn finish_report(&mut self) {
        self.report.cycle_time_s = self.time_s;
        if self.report.cutting_time_s > 0.0 {
            let mean_feed = self.report.removed_mm3 / self.report.cutting_time_s * 60.0;
            let cut_power_kw = self.report.max_power_w / 1000.0;
            // I ∝ w·B·Δ: the removal rate (mm³/min) stands for w·B·Δ.
            self.report.productivity_index = productivity(
                &Economics::default(),
                mean_feed,
                1.0,
                1.0,
                self.setup.material.density_g_cm3,
                cut_power_kw,
            );
        }
    }
}

/// The rotation taking work coordinates at A = `a_deg` to the part frame (`R_x(−a)`).
pub fn part_from_work(a_deg: f64) -> Rotation3<f64> {
    part_from_table(a_deg, 0.0)
}

/// The rotation taking work coordinates at A = `a_deg`, C = `c_deg` to the part frame: the
/// part sits on the C table, which the A trunnion tilts (`work = R_x(a)·R_z(c)·part`, see
/// [`super::profile`]).
pub fn part_from_table(a_deg: f64, c_deg: f64) -> Rotation3<f64> {
    Rotation3::from_axis_angle(&Vector3::z_axis(), -c_deg.to_radians())
        * Rotation3::from_axis_angle(&Vector3::x_axis(), -a_deg.to_radians())
}

/// The tip in the work frame for a commanded machine position, on whole motor steps when
/// `stepped`.
fn work_tip(prof: &MachineProfile, tlo_mm: f64, p: Pos, stepped: bool) -> Point3<f64> {
    let w = prof.work_offset;
    let q = |v: f64| if stepped { prof.quantise(v) } else { v };
    Point3::new(q(p.x) - w.x_mm, q(p.y) - w.y_mm, q(p.z - tlo_mm) - w.z_mm)
}

/// The blank of a multi-axis setup: the material common to every face's block.
fn blank_of(setup: &SimSetup) -> Blank {
    // A face's map bounds the part from above and across in its view, not from below (its floor
    // is where its data ends): with several faces, each block reaches down through the A axis to
    // the far side of every block, so the blank is the bar their tops and sides bound.
    let far = if setup.faces.len() > 1 {
        setup
            .faces
            .iter()
            .flat_map(|f| {
                let s = f.stock;
                [s.min_y_mm, s.min_y_mm + s.y_mm]
                    .into_iter()
                    .flat_map(move |y| [s.min_z_mm, s.min_z_mm + s.z_mm].map(|z| y.hypot(z)))
            })
            .fold(f64::NEG_INFINITY, f64::max)
    } else {
        f64::NEG_INFINITY
    };
    let boxes = setup
        .faces
        .iter()
        .map(|f| {
            let s = f.stock;
            OrientedBox {
                part_from_box: part_from_work(f.a_deg),
                min: Point3::new(s.min_x_mm, s.min_y_mm, s.min_z_mm.min(-far)),
                max: Point3::new(s.min_x_mm + s.x_mm, s.min_y_mm + s.y_mm, s.min_z_mm + s.z_mm),
            }
        })
        .collect();
    Blank { boxes }
}

/// The one dexel stock of a multi-axis setup and its tools as solids (see the module docs).
fn dexel_stock(setup: &SimSetup) -> Result<(DexelStock, Vec<ToolSolid>), SimError> {
    let cell = setup.faces.iter().map(|f| f.stock.cell_mm).fold(setup.stock.cell_mm, f64::min);
    let cells = setup.dexel.unwrap_or(DexelCells::tri(cell));
    let mut stock = DexelStock::new(&blank_of(setup), &cells)?;
    for inc in &setup.inclusions {
        stock.add_hard_sphere(HardSphere {
            center: Point3::from(inc.center),
            radius_mm: inc.radius_mm,
            factor: f64::from(inc.factor),
        })?;
    }
    let solids = setup
        .tools
        .iter()
        .map(|t| {
            let p = &t.profile;
            ToolSolid::new(p, t.length_mm.max(p.max_height_mm() + 4.0 * p.radius_mm()))
        })
        .collect::<Result<Vec<_>, _>>()?;
    Ok((stock, solids))
}

/// Bit `i` set when `Constraint::ALL[i]` is active.
fn active_mask(active: &[Constraint]) -> u16 {
    active.iter().filter_map(|c| Constraint::ALL.iter().position(|k| k == c)).fold(0, |m, i| m | (1 << i))
}

/// The names of the constraints in a telemetry mask, `|`-separated.
pub fn active_names(mask: u16) -> String {
    Constraint::ALL
        .iter()
        .enumerate()
        .filter(|(i, _)| mask & (1 << i) != 0)
        .map(|(_, c)| c.as_str())
        .collect::<Vec<_>>()
        .join("|")
}

/// Length and start/end tangents of an arc.
fn arc_geometry(
    from: Pos,
    end: Pos,
    plane: Plane,
    center: [f64; 2],
    rotation: i32,
) -> (f64, [f64; 3], [f64; 3]) {
    let [i0, i1, i2] = plane.axes();
    let f = from.to_array();
    let e = end.to_array();
    let (r0x, r0y) = (f[i0] - center[0], f[i1] - center[1]);
    let (r1x, r1y) = (e[i0] - center[0], e[i1] - center[1]);
    let r = (r0x * r0x + r0y * r0y).sqrt();
    let sweep = super::gcode::arc_sweep(plane, from, end, center, rotation);
    let planar = r * sweep.abs();
    let axial = e[i2] - f[i2];
    let len = (planar * planar + axial * axial).sqrt();
    let sign = if rotation > 0 { 1.0 } else { -1.0 };
    let tangent = |rx: f64, ry: f64| {
        let mut t = [0.0; 3];
        let n = (rx * rx + ry * ry).sqrt().max(1e-12);
        t[i0] = -sign * ry / n * planar / len.max(1e-12);
        t[i1] = sign * rx / n * planar / len.max(1e-12);
        t[i2] = axial / len.max(1e-12);
        t
    };
    (len, tangent(r0x, r0y), tangent(r1x, r1y))
}

/// The points of an arc from `from` where it reaches its extremes along its plane's two axes (the
/// angles 0, 90, 180 and 270 degrees about the centre that its sweep passes), at the start's
/// normal-axis coordinate (a helix moves that one linearly between the two ends, both checked).
fn arc_extremes(from: Pos, end: Pos, plane: Plane, center: [f64; 2], rotation: i32) -> Vec<Pos> {
    use std::f64::consts::{FRAC_PI_2, TAU};
    let [i0, i1, _] = plane.axes();
    let f = from.to_array();
    let (r0x, r0y) = (f[i0] - center[0], f[i1] - center[1]);
    let r = r0x.hypot(r0y);
    let a0 = r0y.atan2(r0x);
    let sweep = super::gcode::arc_sweep(plane, from, end, center, rotation);
    let mut out = Vec::new();
    for k in 0..4 {
        let target = f64::from(k) * FRAC_PI_2;
        let ahead = if sweep >= 0.0 { (target - a0).rem_euclid(TAU) } else { (a0 - target).rem_euclid(TAU) };
        if sweep.abs() >= TAU || ahead <= sweep.abs() {
            let mut p = f;
            p[i0] = center[0] + r * target.cos();
            p[i1] = center[1] + r * target.sin();
            out.push(Pos::from_array(p));
        }
    }
    out
}

/// The point at fraction `t` of a pending move (machine coordinates).
fn point_at(m: &Pending, t: f64) -> Pos {
    let to = m.canon.end_point().unwrap_or(m.from);
    match m.canon {
        Canon::Arc { end, plane, center, rotation, .. } => {
            let [i0, i1, i2] = plane.axes();
            let f = m.from.to_array();
            let e = end.to_array();
            let (r0x, r0y) = (f[i0] - center[0], f[i1] - center[1]);
            let sweep = super::gcode::arc_sweep(plane, m.from, end, center, rotation);
            let (r, a0) = ((r0x * r0x + r0y * r0y).sqrt(), r0y.atan2(r0x));
            let ang = a0 + sweep * t;
            let mut p = f;
            p[i0] = center[0] + r * ang.cos();
            p[i1] = center[1] + r * ang.sin();
            p[i2] = f[i2] + (e[i2] - f[i2]) * t;
            p[3] = f[3] + (e[3] - f[3]) * t;
            p[4] = f[4] + (e[4] - f[4]) * t;
            Pos::from_array(p)
        }
        _ => {
            let (f, e) = (m.from.to_array(), to.to_array());
            Pos::from_array([0, 1, 2, 3, 4].map(|i| f[i] + (e[i] - f[i]) * t))
        }
    }
}

/// Runs a whole program. `stop` is polled between lines; `observe` sees telemetry rows.
pub fn simulate<R: BufRead>(
    program: R,
    setup: &SimSetup,
    stop: &dyn Fn() -> bool,
    observe: Observer<'_>,
) -> Result<(SimReport, Option<HeightMap>), SimError> {
    let (report, maps) = simulate_faces(program, setup, stop, observe)?;
    Ok((report, maps.into_iter().next().map(|(_, m)| m)))
}

/// Like [`simulate`], returning the final stock of every face with its A angle.
pub fn simulate_faces<R: BufRead>(
    program: R,
    setup: &SimSetup,
    stop: &dyn Fn() -> bool,
    observe: Observer<'_>,
) -> Result<(SimReport, Vec<(f64, HeightMap)>), SimError> {
    let (report, maps, _) = simulate_stock(program, setup, stop, observe)?;
    Ok((report, maps))
}

/// A run's report, every face's final stock with its A angle, and the one dexel stock.
pub type SimOutcome = (SimReport, Vec<(f64, HeightMap)>, Option<DexelStock>);

/// Like [`simulate_faces`], also returning the one dexel stock of a multi-axis part (`None` for
/// a 3-axis part on its Z-map, or motion only).
pub fn simulate_stock<R: BufRead>(
    program: R,
    setup: &SimSetup,
    stop: &dyn Fn() -> bool,
    observe: Observer<'_>,
) -> Result<SimOutcome, SimError> {
    run_machine(program, Machine::new(setup)?, stop, observe)
}

/// Runs `program` on `machine` (see [`simulate_stock`]).
fn run_machine<R: BufRead>(
    program: R,
    mut machine: Machine<'_>,
    stop: &dyn Fn() -> bool,
    observe: Observer<'_>,
) -> Result<SimOutcome, SimError> {
    let mut interp = Interpreter::new(machine.interp_config());
    let mut buf: Vec<Canon> = Vec::with_capacity(8);
    let mut line = String::new();
    let mut reader = program;
    let mut line_no = 0u64;
    loop {
        line.clear();
        let n = reader.read_line(&mut line).map_err(|source| GcodeError::Io { line: line_no + 1, source })?;
        if n == 0 {
            break;
        }
        line_no += 1;
        if line_no.is_multiple_of(256) && stop() {
            return Err(SimError::Stopped { line: line_no });
        }
        buf.clear();
        interp.execute_line(line.trim_end_matches(['\n', '\r']), line_no, &mut |c| buf.push(c))?;
        for c in buf.drain(..) {
            machine.execute(c, observe).map_err(|e| e.located(line_no, &line))?;
        }
        if interp.is_ended() {
            break;
        }
    }
    interp.finish(line_no)?;
    machine.finish(observe)?;
    machine.report.blocks = interp.blocks();
    machine.finish_report();
    let maps = machine.face_maps()?;
    let dexel = machine.dexel.take().map(|(d, _)| d);
    Ok((machine.report, maps, dexel))
}

#[cfg(test)]
mod tests {
    use std::io::Cursor;

    use super::*;
    use crate::domain::cutting::material;

    fn setup(policy: PolicyKind) -> SimSetup {
        SimSetup {
            profile: MachineProfile::builtin("emco-f1").expect("profile"),
            material: material("aluminium").expect("al"),
            stock: StockSpec {
                min_x_mm: 0.0,
                min_y_mm: 0.0,
                min_z_mm: 0.0,
                x_mm: 30.0,
                y_mm: 20.0,
                z_mm: 10.0,
                cell_mm: 0.1,
            },
            faces: Vec::new(),
            dexel: None,
            tools: vec![MachineTool {
                number: 1,
                name: "flat-6".into(),
                profile: ToolProfile::flat(6.0).expect("flat"),
                teeth: 2,
                length_mm: 45.0,
            }],
            policy,
            clamp: false,
            inclusions: Vec::new(),
            seed: 1,
            telemetry_interval_s: 0.0,
            motion_only: false,
        }
    }

    /// A 2 mm deep slot along X through the stock.
    const SLOT: &str = "%\nG21 G90 G17 G94 G40 G49 G80\nT1 M6\nS1500 M3\nG43 H1\nG0 X-5 Y10\nG0 Z5\nG1 Z8 F100\nG1 X35 F200\nG0 Z15\nG53 G0 Z0\nM30\n%\n";

    fn run(
        setup: &SimSetup,
        program: &str,
    ) -> Result<(SimReport, Vec<TelemetryRow>, Option<HeightMap>), SimError> {
        let mut rows = Vec::new();
        let (report, map) = simulate(Cursor::new(program), setup, &|| false, &mut |r| rows.push(*r))?;
        Ok((report, rows, map))
    }

    /// A 30 x 20 x 20 mm bar centred on the A axis (X), on cells of `cell_mm`.
    fn bar(cell_mm: f64) -> StockSpec {
        StockSpec {
            min_x_mm: 0.0,
            min_y_mm: -10.0,
            min_z_mm: -10.0,
            x_mm: 30.0,
            y_mm: 20.0,
            z_mm: 20.0,
            cell_mm,
        }
    }

    #[test]
    fn every_face_cuts_the_one_stock_and_sees_the_others_cuts() {
        // A 30 x 20 x 20 mm bar centred on the A axis, the same block seen from A 0 and A 90.
        let mut s = setup(PolicyKind::Off);
        let bar = bar(0.1);
        s.faces = vec![FaceStock { a_deg: 0.0, stock: bar }, FaceStock { a_deg: 90.0, stock: bar }];
        // A0: a slot 2 mm deep along the edge at Y 7 (Y 4 to 10); A90: a slot 1 mm deep on the
        // middle of the face then facing up.
        let program = "%\nG21 G90 G17 G94 G40 G49 G80\nT1 M6\nS1500 M3\nG43 H1\nG0 X-5 Y7\nG0 Z15\n\
                       G1 Z8 F100\nG1 X35 F200\nG0 Z15\nG0 A90\nG0 X-5 Y0\nG1 Z9 F100\nG1 X35 F200\nG0 Z15\n\
                       G0 A0\nG53 G0 Z0\nM30\n%\n";
        let mut rows = Vec::new();
        let (report, maps) =
            simulate_faces(Cursor::new(program), &s, &|| false, &mut |r| rows.push(*r)).expect("runs");
        assert_eq!(maps.len(), 2);
        let depth = |m: &HeightMap, y: f64| {
            let (c, r) = m.cell_of(15.0, y).expect("inside");
            f64::from(m.get(c, r).unwrap_or(f32::NAN))
        };
        let (a0, a90) = (&maps[0].1, &maps[1].1);
        assert_eq!((maps[0].0, maps[1].0), (0.0, 90.0));
        assert!((depth(a0, 7.0) - 8.0).abs() < 0.02 && (depth(a0, 0.0) - 10.0).abs() < 1e-4, "face A0");
        assert!((depth(a90, 0.0) - 9.0).abs() < 0.02 && (depth(a90, 5.0) - 10.0).abs() < 1e-4, "face A90");
        // The A0 slot seen from A90: at view Y −9 (the part's Z 9) the first material is at the
        // slot's wall, the part's Y 4.
        assert!((depth(a90, -9.0) - 4.0).abs() < 0.1, "A0's slot from A90: {}", depth(a90, -9.0));
        let expected = 30.0 * 6.0 * 2.0 + 30.0 * 6.0 * 1.0;
        assert!((report.removed_mm3 - expected).abs() < 0.03 * expected, "{}", report.removed_mm3);
        assert_eq!(report.turned_moves, 2, "the A90 feed moves");
        assert!(report.warnings.iter().all(|w| !w.contains("not cut")), "{:?}", report.warnings);
    }

    #[test]
    fn a_feed_move_turning_the_a_axis_cuts_a_groove_around_the_bar() {
        // The tool at Z 9, 1 mm into the bar's top, while the part turns from A 0 to A 90 (a
        // feed move of the A axis alone, at 400°/min): it takes the bar's corner off.
        let mut s = setup(PolicyKind::Off);
        let bar = bar(0.4);
        s.faces = vec![FaceStock { a_deg: 0.0, stock: bar }];
        let program = "%\nG21 G90 G17 G94 G40 G49 G80\nT1 M6\nS1500 M3\nG43 H1\nG0 X15 Y0\nG0 Z15\n\
                       G1 Z9 F100\nG1 A90 F400\nG0 Z15\nG53 G0 Z0\nM30\n%\n";
        let (report, maps) = simulate_faces(Cursor::new(program), &s, &|| false, &mut |_| {}).expect("runs");
        assert!(report.warnings.iter().all(|w| !w.contains("not cut")), "{:?}", report.warnings);
        // The tool sweeps radius 9 about X: everything of the bar farther than 9 mm from the
        // axis within the tool's width is gone, from the top face (A0) round to the face at A90.
        let a0 = &maps[0].1;
        let (c, r) = a0.cell_of(15.0, 0.0).expect("inside");
        assert!((f64::from(a0.get(c, r).unwrap_or(f32::NAN)) - 9.0).abs() < 0.2);
        assert!(report.removed_mm3 > 10.0, "{}", report.removed_mm3);
    }

    /// Whether the dexel stock holds material at part point (x, y, z).
    fn solid_at(s: &SimSetup, program: &str, points: &[([f64; 3], bool)]) -> SimReport {
        let (report, _, dexel) =
            simulate_stock(Cursor::new(program), s, &|| false, &mut |_| {}).expect("runs");
        let dexel = dexel.expect("a dexel stock");
        for (p, solid) in points {
            assert_eq!(dexel.contains(&Point3::new(p[0], p[1], p[2])), *solid, "material at {p:?}");
        }
        report
    }

    #[test]
    fn the_table_table_machine_cuts_the_part_tilted_by_a_and_turned_by_c() {
        let mut s = setup(PolicyKind::Off);
        s.profile = MachineProfile::builtin("emco-f1-tt").expect("profile");
        // A 20 mm cube centred on the work origin (where the A and C axes cross).
        let cube = StockSpec {
            min_x_mm: -10.0,
            min_y_mm: -10.0,
            min_z_mm: -10.0,
            x_mm: 20.0,
            y_mm: 20.0,
            z_mm: 20.0,
            cell_mm: 0.25,
        };
        s.faces = vec![FaceStock { a_deg: 0.0, stock: cube }];
        let head = "%\nG21 G90 G17 G94 G40 G49 G80\nT1 M6\nS1500 M3\nG43 H1\n";
        // C 90: a slot along work X at work Y 5, 2 mm deep, runs along the part's Y at part X 5
        // (work = R_z(90)·part).
        let program =
            format!("{head}G0 C90\nG0 X-15 Y5\nG0 Z15\nG1 Z8 F100\nG1 X15 F200\nG0 Z15\nG53 G0 Z0\nM30\n%\n");
        let report = solid_at(
            &s,
            &program,
            &[([5.0, 0.0, 9.0], false), ([0.0, 5.0, 9.0], true), ([5.0, 0.0, 7.5], true)],
        );
        assert_eq!(report.turned_moves, 2, "the feed moves at C 90");
        assert!(report.warnings.iter().all(|w| !w.contains("not cut")), "{:?}", report.warnings);
        // A −90 then C 30: the slot at work Y 0 is on the part's face that the tilt turned up.
        // part = R_z(−30)·R_x(90)·work: work (x, 0, 9) is part R_z(−30)·(x, −9, 0).
        let program = format!(
            "{head}G0 A-90 C30\nG0 X-15 Y0\nG0 Z15\nG1 Z8 F100\nG1 X15 F200\nG0 Z15\nG53 G0 Z0\nM30\n%\n"
        );
        let part = |x: f64, z_work: f64| {
            let p = part_from_table(-90.0, 30.0) * Point3::new(x, 0.0, z_work);
            [p.x, p.y, p.z]
        };
        solid_at(&s, &program, &[(part(0.0, 9.0), false), (part(0.0, 7.5), true), (part(6.0, 9.0), false)]);
        // The tilt is limited: A 40 is refused with its line before anything moves.
        let program = format!("{head}G0 X0 Y0 Z15\nG0 A40\nM30\n%\n");
        let e =
            simulate_stock(Cursor::new(program), &s, &|| false, &mut |_| {}).map(|_| ()).expect_err("A 40");
        assert!(
            matches!(&e, SimError::Rejected { line: 7, message, column: Some(4), .. } if message.contains("A 40")),
            "{e}"
        );
    }

    #[test]
    fn a_feed_move_turning_the_c_table_cuts_a_ring() {
        // The tool 1 mm into the cube's top at 7 mm from the C axis while C turns a full circle:
        // a ring groove 6 mm wide (radius 4 to 10) around the axis.
        let mut s = setup(PolicyKind::Off);
        s.profile = MachineProfile::builtin("emco-f1-tt").expect("profile");
        let cube = StockSpec {
            min_x_mm: -12.0,
            min_y_mm: -12.0,
            min_z_mm: -10.0,
            x_mm: 24.0,
            y_mm: 24.0,
            z_mm: 20.0,
            cell_mm: 0.25,
        };
        s.faces = vec![FaceStock { a_deg: 0.0, stock: cube }];
        let program = "%\nG21 G90 G17 G94 G40 G49 G80\nT1 M6\nS1500 M3\nG43 H1\nG0 X7 Y0\nG0 Z15\nG1 Z9 F100\nG1 C360 F400\nG0 Z15\nG53 G0 Z0\nM30\n%\n";
        let ring = |r: f64, deg: f64| [r * deg.to_radians().cos(), r * deg.to_radians().sin(), 9.5];
        let report = solid_at(
            &s,
            program,
            &[
                (ring(7.0, 0.0), false),
                (ring(7.0, 135.0), false),
                (ring(7.0, 250.0), false),
                (ring(2.0, 60.0), true),
                (ring(11.5, 200.0), true),
            ],
        );
        assert!(report.warnings.iter().all(|w| !w.contains("not cut")), "{:?}", report.warnings);
        // 360° at 400°/min: 54 s of turning.
        assert!(report.cycle_time_s > 54.0, "{}", report.cycle_time_s);
    }

    #[test]
    fn c_words_are_refused_on_a_machine_without_a_c_axis_and_g93_times_the_move() {
        let s = setup(PolicyKind::Off);
        let e =
            run(&s, "%\nG21 G90\nG0 X5 Y5 Z30\nG0 C10\nM30\n%\n").map(|_| ()).expect_err("no C on the F1");
        assert!(
            matches!(&e, SimError::Rejected { line: 4, message, column: Some(4), .. } if message.contains("no C axis")),
            "{e}"
        );
        // Inverse time: G1 X20 F6 takes 1/6 min = 10 s (120 mm/min over 20 mm), in the air.
        let mut m = setup(PolicyKind::Off);
        m.motion_only = true;
        let g94 = run(&m, "%\nG21 G90 G94\nG0 X0 Y5 Z30\nG1 X20 F120\nM30\n%\n").expect("runs").0;
        let g93 = run(&m, "%\nG21 G90 G93\nG0 X0 Y5 Z30\nG1 X20 F6\nM30\n%\n").expect("runs").0;
        assert!(
            (g93.cycle_time_s - g94.cycle_time_s).abs() < 1e-9,
            "{} vs {}",
            g93.cycle_time_s,
            g94.cycle_time_s
        );
        assert!(g93.cycle_time_s > 10.0, "{}", g93.cycle_time_s);
    }

    /// Cuts that continue the last one ([`Stock::cut_line_after`]: the next revolution, the
    /// next move, a rapid after a feed) leave the run as cutting every piece as a fresh move
    /// does: a random program of short moves over a relief, with rapids, a second tool and both
    /// policies.
    #[test]
    fn continued_cuts_run_the_program_as_fresh_cuts_do() {
        use rand::rngs::StdRng;
        use rand::{Rng, SeedableRng};
        let mut rng = StdRng::seed_from_u64(23);
        let mut program = String::from("%\nG21 G90 G17 G94 G40 G49 G80\n");
        for tool in [1, 2] {
            program += &format!("G53 G0 Z0\nT{tool} M6\nS2000 M3\nG43 H{tool}\nG0 X2 Y2\nG0 Z12\n");
            for pass in 0..6 {
                let (mut x, mut y): (f64, f64) = (rng.random_range(2.0..28.0), rng.random_range(2.0..18.0));
                program += &format!("G0 X{x:.3} Y{y:.3}\nG1 Z{:.3} F150\n", rng.random_range(7.0..9.5));
                for _ in 0..40 {
                    x = (x + rng.random_range(-1.5..1.5)).clamp(0.0, 30.0);
                    y = (y + rng.random_range(-1.5..1.5)).clamp(0.0, 20.0);
                    let z = rng.random_range(6.5..9.8);
                    program += &format!("G1 X{x:.3} Y{y:.3} Z{z:.3} F{}\n", 120 + 40 * pass);
                }
                program += "G0 Z12\n";
            }
        }
        program += "G53 G0 Z0\nM30\n%\n";
        for policy in [PolicyKind::Aco, PolicyKind::Off] {
            let mut setup = setup(policy);
            setup.tools.push(MachineTool {
                number: 2,
                name: "ball-3".into(),
                profile: "ball-3".parse().expect("ball"),
                teeth: 2,
                length_mm: 50.0,
            });
            let run_with = |continue_cuts: bool| {
                let mut machine = Machine::new(&setup).expect("machine");
                machine.continue_cuts = continue_cuts;
                let mut rows = Vec::new();
                let (report, maps, _) =
                    run_machine(Cursor::new(program.as_str()), machine, &|| false, &mut |r| rows.push(*r))
                        .expect("run");
                (report, rows, maps)
            };
            let (fast, fast_rows, fast_maps) = run_with(true);
            let (fresh, fresh_rows, fresh_maps) = run_with(false);
            assert!(fresh.revolutions > 2000, "{policy:?}: {} revolutions", fresh.revolutions);
            assert_eq!(fast.revolutions, fresh.revolutions, "{policy:?}");
            let close = |a: f64, b: f64, what: &str| {
                assert!((a - b).abs() <= 1e-6 * (1.0 + a.abs()), "{policy:?} {what}: {a} vs {b}");
            };
            close(fast.removed_mm3, fresh.removed_mm3, "removed volume");
            close(fast.cycle_time_s, fresh.cycle_time_s, "cycle time");
            close(fast.max_torque_nm, fresh.max_torque_nm, "peak torque");
            assert_eq!(fast_rows.len(), fresh_rows.len(), "{policy:?}");
            for (a, b) in fast_rows.iter().zip(&fresh_rows) {
                close(a.torque_true_nm, b.torque_true_nm, "torque");
                close(a.feed_mm_min, b.feed_mm_min, "feed");
            }
            let (a, b) = (&fast_maps[0].1, &fresh_maps[0].1);
            for (u, v) in a.data().iter().zip(b.data()) {
                assert!((u - v).abs() <= 2e-6, "{policy:?}: final stock {u} vs {v}");
            }
        }
    }

    #[test]
    fn on_a_3_axis_program_the_dexel_stock_drives_the_adaptive_loop_as_the_z_map_does() {
        // The same program and loop on the Z-map and on the one dexel stock (the program's block
        // as the only face): a full slot, then a half-immersion pass beside it, then a ramp.
        let program = "%\nG21 G90 G17 G94 G40 G49 G80\nT1 M6\nS1500 M3\nG43 H1\nG0 X-5 Y10\nG0 Z5\nG1 Z8 F100\n\
                       G1 X35 F200\nG0 Z15\nG0 X-5 Y13\nG1 Z8.5 F100\nG1 X35 F250\nG1 X10 Y3 Z7.5 F150\nG0 Z15\nG53 G0 Z0\nM30\n%\n";
        let zmap = setup(PolicyKind::Aco);
        let mut dexel = setup(PolicyKind::Aco);
        dexel.faces = vec![FaceStock { a_deg: 0.0, stock: dexel.stock }];
        let (rz, rows_z, _) = run(&zmap, program).expect("z-map");
        let (rd, rows_d, _) = run(&dexel, program).expect("dexel");
        let close = |a: f64, b: f64, rel: f64, what: &str| {
            assert!((a - b).abs() <= rel * a.abs().max(b.abs()), "{what}: Z-map {a} against dexel {b}");
        };
        close(rz.removed_mm3, rd.removed_mm3, 0.01, "removed volume");
        close(rz.cycle_time_s, rd.cycle_time_s, 0.02, "cycle time under the loop");
        close(rz.max_torque_nm, rd.max_torque_nm, 0.05, "peak torque");
        let mean = |rows: &[TelemetryRow]| {
            let cutting: Vec<f64> =
                rows.iter().filter(|r| r.removal_mm3_s > 0.0).map(|r| r.torque_true_nm).collect();
            cutting.iter().sum::<f64>() / cutting.len().max(1) as f64
        };
        close(mean(&rows_z), mean(&rows_d), 0.03, "mean cutting torque");
        let mean_feed = |rows: &[TelemetryRow]| {
            let cutting: Vec<f64> =
                rows.iter().filter(|r| r.removal_mm3_s > 0.0).map(|r| r.feed_mm_min).collect();
            cutting.iter().sum::<f64>() / cutting.len().max(1) as f64
        };
        close(mean_feed(&rows_z), mean_feed(&rows_d), 0.03, "mean feed the loop chose");
    }

    #[test]
    fn a_refused_word_is_named_by_its_column() {
        assert_eq!(word_column("G0 X5 (a C in a comment) C10", 'C'), Some(26));
        assert_eq!(word_column("g1 x-5 f300", 'F'), Some(8));
        assert_eq!(word_column("G1 X5 ; C10", 'C'), None);
        assert_eq!(word_column("(COMMENT) T2 M6", 'T'), Some(11));
        // Out of the travel in X: the line and the X word's column.
        let s = setup(PolicyKind::Off);
        let e = run(&s, "%\nG21 G90\nG53 G0 Z0\nG0 Y5   X900\nM30\n%\n").map(|_| ()).expect_err("X 900");
        assert!(e.to_string().starts_with("line 4, column 9: "), "{e}");
        // A feed out of range: the F word.
        let e = run(&s, "%\nG21 G90\nG1 X1 F9000\nM30\n%\n").map(|_| ()).expect_err("F 9000");
        assert!(e.to_string().starts_with("line 3, column 7: "), "{e}");
    }

    #[test]
    fn moves_shorter_than_a_revolution_between_stops_take_their_motion_time() {
        // Step-downs of 0.01 mm (less than one revolution's feed) between passes that reverse:
        // each starts and ends at rest. Without adaptation the cutting run takes the time of the
        // motion-only run.
        let mut program =
            String::from("%\nG21 G90 G17 G94 G40 G49 G80\nT1 M6\nS1500 M3\nG43 H1\nG0 X-5 Y10\nG0 Z10.5\n");
        for k in 0..20 {
            program.push_str(&format!(
                "G1 Z{:.2} F100\nG1 X{} F200\n",
                10.0 - 0.01 * f64::from(k),
                if k % 2 == 0 { 35 } else { -5 }
            ));
        }
        program.push_str("G0 Z15\nG53 G0 Z0\nM30\n%\n");
        let s = setup(PolicyKind::Off);
        let (cut, _, _) = run(&s, &program).expect("runs");
        let (motion, _, _) = run(&SimSetup { motion_only: true, ..s.clone() }, &program).expect("runs");
        let ratio = cut.cycle_time_s / motion.cycle_time_s;
        assert!((ratio - 1.0).abs() < 0.02, "cut {} s, motion {} s", cut.cycle_time_s, motion.cycle_time_s);
    }

    #[test]
    fn a_slot_removes_its_volume_and_takes_its_time() {
        let s = setup(PolicyKind::Off);
        let (report, rows, map) = run(&s, SLOT).expect("runs");
        let map = map.expect("stock");
        // The slot: 30 mm long through the stock, 6 mm wide, 2 mm deep, round ends outside.
        let expected = 30.0 * 6.0 * 2.0;
        assert!((report.removed_mm3 - expected).abs() < 0.03 * expected, "{}", report.removed_mm3);
        let volume_before = 30.0 * 20.0 * 10.0;
        let volume_after: f64 = map.data().iter().map(|z| f64::from(*z) * 0.01).sum();
        assert!((volume_before - volume_after - report.removed_mm3).abs() < 0.5, "conservation");
        // The bottom of the slot at Z 8 on the centre line, untouched stock beside it.
        let (c, r) = map.cell_of(15.0, 10.0).expect("cell");
        assert!((map.get(c, r).unwrap_or(0.0) - 8.0).abs() < 1e-3);
        let (c, r) = map.cell_of(15.0, 2.0).expect("cell");
        assert!((map.get(c, r).unwrap_or(0.0) - 10.0).abs() < 1e-6);
        // 40 mm at 200 mm/min is 12 s of feed; plus the tool change, spindle ramp, rapids.
        assert!(report.cycle_time_s > 12.0 + 20.0 && report.cycle_time_s < 60.0, "{}", report.cycle_time_s);
        assert!(!rows.is_empty());
        let cutting: Vec<_> = rows.iter().filter(|r| r.removal_mm3_s > 0.0).collect();
        assert!(!cutting.is_empty());
        // Slotting 2 mm deep at 0.133 mm/rev in aluminium: about a torque count, a clear current.
        let t = cutting.iter().map(|r| r.torque_true_nm).fold(0.0, f64::max);
        assert!((0.05..1.0).contains(&t), "{t}");
        let i = cutting.iter().map(|r| r.current_a).fold(0.0, f64::max);
        assert!(i > 0.35, "{i}");
    }

    #[test]
    fn out_of_range_programs_are_refused_with_their_line_or_clamped() {
        let s = setup(PolicyKind::Off);
        let fast = SLOT.replace("F200", "F900");
        let e = run(&s, &fast).map(|_| ()).expect_err("F900");
        assert!(
            e.to_string().starts_with("line 9, column 8: F900 is outside the machine's 5-400 mm/min"),
            "{e}"
        );
        let mut clamped = setup(PolicyKind::Off);
        clamped.clamp = true;
        let (report, _, _) = run(&clamped, &fast).expect("clamped");
        assert!(report.warnings.iter().any(|w| w.contains("F900") && w.contains("clamped")));
        let e = run(&s, &SLOT.replace("S1500", "S5000")).map(|_| ()).expect_err("S5000");
        assert!(e.to_string().contains("line 4, column 1: S5000"), "{e}");
        let e = run(&s, &SLOT.replace("G1 X35", "G1 X400")).map(|_| ()).expect_err("travel");
        assert!(e.to_string().contains("line 9") && e.to_string().contains("travel"), "{e}");
    }

    #[test]
    fn crashes_end_the_run() {
        let s = setup(PolicyKind::Off);
        let e = run(&s, &SLOT.replace("G1 X35 F200", "G0 X35")).map(|_| ()).expect_err("rapid into stock");
        assert!(matches!(e, SimError::Crash { line: 9, .. }), "{e}");
        let e = run(&s, &SLOT.replace("S1500 M3", "S1500")).map(|_| ()).expect_err("spindle off");
        assert!(e.to_string().contains("spindle stopped"), "{e}");
    }

    #[test]
    fn the_adaptive_loop_holds_torque_through_a_hard_inclusion() {
        let deep = SLOT.replace("G1 Z8 F100", "G1 Z6 F100");
        let mut fixed = setup(PolicyKind::Off);
        fixed.inclusions = vec![Inclusion { center: [15.0, 10.0, 7.0], radius_mm: 4.0, factor: 4.0 }];
        let mut aco = fixed.clone();
        aco.policy = PolicyKind::Aco;
        let (r_fixed, _, _) = run(&fixed, &deep).expect("fixed");
        let (r_aco, rows, _) = run(&aco, &deep).expect("aco");
        assert!(r_fixed.revs_over_torque > 0, "the fixed feed overloads in the inclusion: {r_fixed:?}");
        assert!(
            r_aco.revs_over_torque * 4 < r_fixed.revs_over_torque,
            "aco {} vs fixed {} revolutions over the torque limit",
            r_aco.revs_over_torque,
            r_fixed.revs_over_torque
        );
        let seen: std::collections::BTreeSet<String> = rows.iter().map(|r| active_names(r.active)).collect();
        // The binding limit of a 6 mm end mill 4 mm deep is its deflection (then torque).
        assert!(
            seen.iter().any(|a| a.contains("deflection") || a.contains("torque")),
            "the loop reports the active limit: {seen:?}"
        );
        assert_eq!(r_aco.revs_over_power, 0);
        assert!(r_fixed.revs_over_power > 0);
    }

    #[test]
    fn an_arc_that_bulges_out_of_the_travel_is_refused_though_its_ends_are_inside() {
        let s = setup(PolicyKind::Off);
        // Both ends in the travel; clockwise from (5, 10) to (5, 20) about a centre 150 mm to the
        // left is the long way round, 300 mm across.
        let program = SLOT.replace("G1 X35 F200", "G1 X5 Y10 F200\nG2 X5 Y20 I-150 J5");
        let e = run(&s, &program).map(|_| ()).expect_err("bulge");
        assert!(e.to_string().contains("line 10") && e.to_string().contains("travel"), "{e}");
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig::with_cases(48))]
        /// Random programs of rapids, feeds and arcs (clockwise and counter-clockwise, some far
        /// out of the travel, some with radii that do not agree): the simulated mill either
        /// refuses a program naming a line, or runs it without its spindle nose ever leaving the
        /// travel. The reference walks the interpreter's commands itself and samples every move
        /// densely (arcs at 1° steps).
        #[test]
        fn the_mill_never_leaves_its_travel(
            moves in proptest::collection::vec(
                (0u8..4, -60.0..260.0f64, -60.0..200.0f64, -40.0..120.0f64, -40.0..40.0f64, -40.0..40.0f64),
                1..10,
            ),
        ) {
            use std::fmt::Write as _;
            use crate::domain::gcode::{Interpreter, Plane};
            let mut s = setup(PolicyKind::Off);
            s.motion_only = true;
            let mut program = String::from("%\nG21 G90 G17 G94\nT1 M6\nS1500 M3\nG0 Z60\n");
            for (kind, x, y, z, i, j) in &moves {
                let _ = match kind {
                    0 => writeln!(program, "G0 X{x:.3} Y{y:.3} Z{z:.3}"),
                    1 => writeln!(program, "G1 X{x:.3} Y{y:.3} Z{z:.3} F300"),
                    2 => writeln!(program, "G2 X{x:.3} Y{y:.3} I{i:.3} J{j:.3} F300"),
                    _ => writeln!(program, "G3 X{x:.3} Y{y:.3} I{i:.3} J{j:.3} F300"),
                };
            }
            program.push_str("M30\n%\n");
            let outcome = run(&s, &program);
            let Ok(_) = outcome else {
                let e = outcome.map(|_| ()).expect_err("refused");
                proptest::prop_assert!(e.to_string().contains("line "), "refused without a line: {}", e);
                return Ok(());
            };
            // It ran: walk the same commands and check every sampled point.
            let machine = Machine::new(&s).expect("machine");
            let mut interp = Interpreter::new(machine.interp_config());
            let mut canons = Vec::new();
            for (n, text) in program.lines().enumerate() {
                interp.execute_line(text, n as u64 + 1, &mut |c| canons.push(c)).expect("ran once already");
            }
            let axes = &s.profile.axes;
            let length = s.tools[0].length_mm;
            let mut pos: Option<Pos> = None;
            for c in canons {
                let Some(end) = c.end_point() else { continue };
                let samples: Vec<Pos> = match (c, pos) {
                    (Canon::Arc { plane: Plane::Xy, center, rotation, .. }, Some(from)) => {
                        let sweep = crate::domain::gcode::arc_sweep(Plane::Xy, from, end, center, rotation);
                        let (rx, ry) = (from.x - center[0], from.y - center[1]);
                        let (r, a0) = (rx.hypot(ry), ry.atan2(rx));
                        let steps = (sweep.abs().to_degrees().ceil() as usize).max(1);
                        (0..=steps)
                            .map(|k| {
                                let ang = a0 + sweep * k as f64 / steps as f64;
                                let mut p = from;
                                p.x = center[0] + r * ang.cos();
                                p.y = center[1] + r * ang.sin();
                                p
                            })
                            .collect()
                    }
                    _ => vec![end],
                };
                for p in samples {
                    let nose_z = p.z + length;
                    proptest::prop_assert!(
                        axes.x.contains(p.x, 1e-3) && axes.y.contains(p.y, 1e-3) && axes.z.contains(nose_z, 1e-3),
                        "line {}: ({:.3}, {:.3}, nose {:.3}) is outside the travel\n{}", c.line(), p.x, p.y, nose_z, program
                    );
                }
                pos = Some(end);
            }
        }
    }

    #[test]
    fn motion_only_runs_time_the_program() {
        let mut s = setup(PolicyKind::Off);
        s.motion_only = true;
        let (report, _, map) = run(&s, SLOT).expect("runs");
        assert!(map.is_none());
        assert!(report.cycle_time_s > 32.0, "{}", report.cycle_time_s);
    }
}
