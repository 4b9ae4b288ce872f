//! The modal state machine: parsed blocks in, canonical commands out.
//!
//! Each block is executed in LinuxCNC's order of execution: feed mode (G94/G95, which reset F to
//! 0), F, S, T, M6, M3/M4/M5, M7/M8/M9, M52, G4, G17-G19, G20/G21, G40, G43/G49, G54-G59,
//! G61/G64, G90/G91, G90.1/G91.1, then G28 or the move (G0-G3, possibly G53), then M0/M1/M2/M30.
//! So F in a block that also switches G20/G21 is read in the units in effect before the block;
//! once set, a feed keeps its physical value across unit changes (as LinuxCNC does).
//!
//! The state is a handful of scalars; a line is parsed into a reused [`Block`], so running a
//! program allocates nothing per line and memory does not grow with program length.

use std::collections::{BTreeMap, VecDeque};
use std::f64::consts::FRAC_PI_2;
use std::io::{BufRead, Read};

use super::canon::{Canon, Coolant, FeedMode, PathMode, Plane, Pos, SpindleDir};
use super::error::{ErrorKind, GcodeError};
use super::lexer::{Block, BlockKind, GGroup, Letter, MGroup, error_at, parse_line};

/// Millimetres per inch (G20).
pub const MM_PER_INCH: f64 = 25.4;

/// When a centre-format arc (I/J/K) is refused for unequal start and end radii, and how small a
/// radius may be. LinuxCNC's rule (`interp_arc.cc`, `arc_data_ijk`; defaults from
/// `interp_internal.hh`, confirmed with `rs274` 2.9):
///
/// ```text
/// d = |r_start - r_end|, rel = d / max(r_start, r_end), abs = center_abs (in the program's units)
/// refused if d > hard_factor * abs  or  (rel > center_relative and d > abs)
/// ```
///
/// so with the defaults an arc is accepted when its radii differ by at most 0.0283 mm, or by up to
/// 2.83 mm if that is within 0.1 % of the radius. [`ArcTolerance::absolute`] gives a plain
/// absolute limit instead.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ArcTolerance {
    /// Absolute tolerance in G21 programs, mm (LinuxCNC `2 * 0.01 * sqrt(2)` = 0.028284).
    pub center_abs_mm: f64,
    /// Absolute tolerance in G20 programs, inches (LinuxCNC `2 * 0.001 * sqrt(2)`).
    pub center_abs_inch: f64,
    /// Relative tolerance (LinuxCNC 0.001).
    pub center_relative: f64,
    /// Never accepted beyond this multiple of the absolute tolerance (LinuxCNC 100).
    pub hard_factor: f64,
    /// Smallest radius; also how far an R too small to reach the end may fall short, mm
    /// (LinuxCNC 0.00005 in = 0.00127 mm in both unit systems).
    pub radius_mm: f64,
}

impl ArcTolerance {
    /// LinuxCNC 2.9's defaults.
    pub const LINUXCNC: ArcTolerance = ArcTolerance {
        center_abs_mm: 2.0 * 0.01 * std::f64::consts::SQRT_2,
        center_abs_inch: 2.0 * 0.001 * std::f64::consts::SQRT_2,
        center_relative: 0.001,
        hard_factor: 100.0,
        radius_mm: 0.00005 * MM_PER_INCH,
    };

    /// Radii may differ by at most `tolerance_mm`, whatever the radius and units.
    pub fn absolute(tolerance_mm: f64) -> ArcTolerance {
        ArcTolerance {
            center_abs_mm: tolerance_mm,
            center_abs_inch: tolerance_mm / MM_PER_INCH,
            center_relative: 0.0,
            hard_factor: 1.0,
            ..ArcTolerance::LINUXCNC
        }
    }
}

impl Default for ArcTolerance {
    fn default() -> Self {
        ArcTolerance::LINUXCNC
    }
}

/// Machine set-up the interpreter needs.
#[derive(Debug, Clone, PartialEq)]
pub struct InterpConfig {
    /// Arc checks.
    pub arc_tolerance: ArcTolerance,
    /// Tool table: tool number -> length, mm (used by G43 H; T must name a tool in it, or 0).
    pub tools: BTreeMap<u32, f64>,
    /// The G28 position, machine coordinates (LinuxCNC parameters 5161-5164; default machine zero).
    pub home: Pos,
    /// Origins of G54..G59 in machine coordinates (default all zero).
    pub work_offsets: [Pos; 6],
    /// Where the machine is when the program starts (machine coordinates).
    pub initial_position: Pos,
    /// Block-delete switch: when on, lines starting with `/` are skipped.
    pub block_delete: bool,
    /// Longest line accepted, bytes (without the line end).
    pub max_line_bytes: usize,
}

impl Default for InterpConfig {
    fn default() -> Self {
        InterpConfig {
            arc_tolerance: ArcTolerance::LINUXCNC,
            tools: BTreeMap::new(),
            home: Pos::ZERO,
            work_offsets: [Pos::ZERO; 6],
            initial_position: Pos::ZERO,
            block_delete: true,
            max_line_bytes: 4096,
        }
    }
}

/// What ended the program.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum EndReason {
    /// M2.
    M2,
    /// M30.
    M30,
    /// The closing `%` of a program that started with `%`.
    Percent,
}

/// The outcome of [`run`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RunSummary {
    /// Lines read (up to and including the line that ended the program).
    pub lines: u64,
    /// Blocks executed (lines with words or comments).
    pub blocks: u64,
    /// Canonical commands emitted.
    pub canons: u64,
    /// What ended the program.
    pub end: EndReason,
    /// Final machine position.
    pub position: Pos,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Phase {
    Start,
    Running,
    InPercent,
    Ended(EndReason),
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Motion {
    Rapid,
    Linear,
    Cw,
    Ccw,
}

impl Motion {
    fn from_code(code10: u16) -> Option<Motion> {
        match code10 {
            0 => Some(Motion::Rapid),
            10 => Some(Motion::Linear),
            20 => Some(Motion::Cw),
            30 => Some(Motion::Ccw),
            _ => None,
        }
    }
}

/// Modal state. Positions are machine coordinates, mm / degrees.
#[derive(Debug, Clone)]
struct State {
    pos: [f64; 5],
    inch: bool,
    incremental: bool,
    arc_absolute: bool,
    plane: Plane,
    feed_mode: FeedMode,
    /// mm/min or mm/rev; 0 = not set.
    feed: f64,
    speed: f64,
    spindle: SpindleDir,
    motion: Option<Motion>,
    /// Active work offset (machine coordinates of the program origin).
    offset: [f64; 5],
    /// Tool length offset, mm (Z).
    tlo: f64,
    selected_tool: u32,
    loaded_tool: u32,
}

impl State {
    #[inline]
    fn scale(&self) -> f64 {
        if self.inch { MM_PER_INCH } else { 1.0 }
    }

    /// Program-to-machine translation of axis `k`.
    #[inline]
    fn origin(&self, k: usize) -> f64 {
        if k == 2 { self.offset[2] + self.tlo } else { self.offset[k] }
    }
}

const AXES: [Letter; 5] = [Letter::X, Letter::Y, Letter::Z, Letter::A, Letter::C];

/// The interpreter: feed it lines in order; it calls `out` with the canonical commands.
#[derive(Debug, Clone)]
pub struct Interpreter {
    config: InterpConfig,
    block: Block,
    st: State,
    phase: Phase,
    blocks: u64,
    last_line: u64,
}

impl Interpreter {
    /// A fresh interpreter in LinuxCNC's start state: G17 G21 G90 G91.1 G94 G40 G49 G54 G80, F0,
    /// S0, M5, M9, tool 0, at `config.initial_position`.
    pub fn new(config: InterpConfig) -> Interpreter {
        let st = State {
            pos: config.initial_position.to_array(),
            inch: false,
            incremental: false,
            arc_absolute: false,
            plane: Plane::Xy,
            feed_mode: FeedMode::PerMinute,
            feed: 0.0,
            speed: 0.0,
            spindle: SpindleDir::Off,
            motion: None,
            offset: config.work_offsets[0].to_array(),
            tlo: 0.0,
            selected_tool: 0,
            loaded_tool: 0,
        };
        Interpreter { config, block: Block::new(), st, phase: Phase::Start, blocks: 0, last_line: 0 }
    }

    /// The configuration.
    pub fn config(&self) -> &InterpConfig {
        &self.config
    }

    /// Current machine position.
    pub fn position(&self) -> Pos {
        Pos::from_array(self.st.pos)
    }

    /// Current position in the active work coordinates (after the tool length offset), mm.
    pub fn program_position(&self) -> Pos {
        let p = self.st.pos;
        Pos::from_array([0, 1, 2, 3, 4].map(|k| p[k] - self.st.origin(k)))
    }

    /// M2/M30 or the closing `%` has been read: further lines are ignored.
    pub fn is_ended(&self) -> bool {
        matches!(self.phase, Phase::Ended(_))
    }

    /// Blocks executed so far.
    pub fn blocks(&self) -> u64 {
        self.blocks
    }

    /// Executes one line (`line_no` is 1-based, for messages and [`Canon::line`]).
    pub fn execute_line(
        &mut self,
        line: &str,
        line_no: u64,
        out: &mut impl FnMut(Canon),
    ) -> Result<(), GcodeError> {
        self.execute_bytes(line.as_bytes(), line_no, out)
    }

    /// Executes one line given as bytes (comments may hold any bytes; a trailing `\n` is ignored).
    pub fn execute_bytes(
        &mut self,
        line: &[u8],
        line_no: u64,
        out: &mut impl FnMut(Canon),
    ) -> Result<(), GcodeError> {
        if self.is_ended() {
            return Ok(());
        }
        self.last_line = line_no;
        let body = line.strip_suffix(b"\n").unwrap_or(line);
        let body = body.strip_suffix(b"\r").unwrap_or(body);
        if body.len() > self.config.max_line_bytes {
            let kind = ErrorKind::LineTooLong { max: self.config.max_line_bytes };
            return Err(GcodeError::Invalid { line: line_no, column: 1, word: String::new(), kind });
        }
        parse_line(body, line_no, self.config.block_delete, &mut self.block)?;
        match self.block.kind() {
            BlockKind::Blank => Ok(()),
            BlockKind::Percent => match self.phase {
                Phase::Start => {
                    self.phase = Phase::InPercent;
                    Ok(())
                }
                Phase::InPercent => {
                    out(Canon::ProgramEnd { line: line_no });
                    self.phase = Phase::Ended(EndReason::Percent);
                    Ok(())
                }
                _ => {
                    let at = body.iter().position(|&c| c == b'%').unwrap_or(0);
                    Err(error_at(body, line_no, at, ErrorKind::MisplacedPercent))
                }
            },
            BlockKind::Deleted | BlockKind::ProgramNumber => {
                self.started();
                Ok(())
            }
            BlockKind::Words => {
                self.started();
                self.blocks += 1;
                let end = execute_block(&self.config, &self.block, &mut self.st, body, line_no, out)?;
                if let Some(end) = end {
                    self.phase = Phase::Ended(end);
                }
                Ok(())
            }
        }
    }

    fn started(&mut self) {
        if self.phase == Phase::Start {
            self.phase = Phase::Running;
        }
    }

    /// Call at the end of the file (`lines` = lines read): how the program ended, or the error
    /// for a file without M2/M30 (or without its closing `%`).
    pub fn finish(&self, lines: u64) -> Result<EndReason, GcodeError> {
        let kind = match self.phase {
            Phase::Ended(end) => return Ok(end),
            Phase::InPercent => ErrorKind::MissingClosingPercent,
            Phase::Start | Phase::Running => ErrorKind::MissingProgramEnd,
        };
        Err(GcodeError::Invalid { line: lines + 1, column: 1, word: String::new(), kind })
    }
}

fn whole(v: f64, what: &'static str, min: f64) -> Result<u32, ErrorKind> {
    if v.fract() != 0.0 {
        return Err(ErrorKind::NotAnInteger { what, value: v });
    }
    if v < min || v > f64::from(u32::MAX) {
        let allowed = if min > 0.0 { "1 or more" } else { "0 or more" };
        return Err(ErrorKind::OutOfRange { what, value: v, allowed });
    }
    Ok(v as u32)
}

/// Executes a parsed block; `Some` when it ends the program.
fn execute_block(
    cfg: &InterpConfig,
    b: &Block,
    st: &mut State,
    s: &[u8],
    line: u64,
    out: &mut impl FnMut(Canon),
) -> Result<Option<EndReason>, GcodeError> {
    let fail = |column: u32, kind: ErrorKind| error_at(s, line, column.max(1) as usize - 1, kind);

    // Fast path: a modal move with axis words only (most lines of CAM output).
    if !b.has_codes() && b.has_axis_words() && b.has_only_axis_words() {
        return match st.motion {
            Some(Motion::Rapid) => {
                let to = target(b, st, false);
                out(Canon::Traverse { line, to: Pos::from_array(to) });
                st.pos = to;
                Ok(None)
            }
            Some(Motion::Linear) => {
                check_feed(st, b).map_err(|k| fail(b.first_column(), k))?;
                let to = target(b, st, false);
                out(Canon::Feed { line, to: Pos::from_array(to) });
                st.pos = to;
                Ok(None)
            }
            None => Err(fail(b.first_axis_column(), ErrorKind::AxisWordsWithoutMotion)),
            // Modal arcs always carry I/J/K or R: the general path below.
            Some(Motion::Cw | Motion::Ccw) => execute_general(cfg, b, st, s, line, out),
        };
    }
    execute_general(cfg, b, st, s, line, out)
}

/// Any block.
fn execute_general(
    cfg: &InterpConfig,
    b: &Block,
    st: &mut State,
    s: &[u8],
    line: u64,
    out: &mut impl FnMut(Canon),
) -> Result<Option<EndReason>, GcodeError> {
    let fail = |column: u32, kind: ErrorKind| error_at(s, line, column.max(1) as usize - 1, kind);

    let g_motion = b.g(GGroup::Motion);
    let g0 = b.g(GGroup::NonModal);
    let has_axes = b.has_axis_words();
    let explicit_move = g_motion.and_then(Motion::from_code);
    let motion_after = match g_motion {
        Some(800) => None,
        Some(c) => Motion::from_code(c),
        None => st.motion,
    };
    let is_g28 = g0 == Some(280);
    let g53 = g0 == Some(530);
    let mv = if is_g28 {
        if has_axes && explicit_move.is_some() {
            return Err(fail(b.g_column(GGroup::NonModal), ErrorKind::AxisWordsClaimedTwice));
        }
        None
    } else if explicit_move.is_some() {
        explicit_move
    } else if has_axes {
        match motion_after {
            Some(m) => Some(m),
            None => return Err(fail(b.first_axis_column(), ErrorKind::AxisWordsWithoutMotion)),
        }
    } else {
        None
    };
    let is_arc = matches!(mv, Some(Motion::Cw | Motion::Ccw));

    // Every word must be used by something in the block.
    for l in [Letter::I, Letter::J, Letter::K, Letter::R] {
        if b.has(l) && !is_arc {
            return Err(fail(b.column(l), ErrorKind::UnusedWord { letter: l.as_char(), needs: "G2/G3" }));
        }
    }
    let g64 = b.g(GGroup::PathControl) == Some(640);
    if b.has(Letter::P) && !(g0 == Some(40) || g64 || b.m(MGroup::Override).is_some() || is_arc) {
        let kind = ErrorKind::UnusedWord { letter: 'P', needs: "G4, G64, M52 or G2/G3" };
        return Err(fail(b.column(Letter::P), kind));
    }
    if b.has(Letter::Q) && !g64 {
        return Err(fail(b.column(Letter::Q), ErrorKind::UnusedWord { letter: 'Q', needs: "G64" }));
    }
    if b.has(Letter::H) && b.g(GGroup::ToolLength) != Some(430) {
        return Err(fail(b.column(Letter::H), ErrorKind::UnusedWord { letter: 'H', needs: "G43" }));
    }
    if g53 && !matches!(mv, Some(Motion::Rapid | Motion::Linear)) {
        return Err(fail(b.g_column(GGroup::NonModal), ErrorKind::G53NeedsLinearMove));
    }

    let scale_before = st.scale();
    // Feed mode, F, S, T.
    if let Some(code) = b.g(GGroup::FeedMode) {
        st.feed_mode = match code {
            930 => FeedMode::InverseTime,
            950 => FeedMode::PerRevolution,
            _ => FeedMode::PerMinute,
        };
        st.feed = 0.0;
        out(Canon::SetFeedRate { line, rate: 0.0, mode: st.feed_mode });
    }
    if let Some(f) = b.get(Letter::F) {
        if f < 0.0 {
            let kind = ErrorKind::OutOfRange { what: "F (feed rate)", value: f, allowed: "0 or more" };
            return Err(fail(b.column(Letter::F), kind));
        }
        // Inverse time is per minute whatever the length unit.
        st.feed = if st.feed_mode == FeedMode::InverseTime { f } else { f * scale_before };
        out(Canon::SetFeedRate { line, rate: st.feed, mode: st.feed_mode });
    }
    if let Some(v) = b.get(Letter::S) {
        if v < 0.0 {
            let kind = ErrorKind::OutOfRange { what: "S (spindle speed)", value: v, allowed: "0 or more" };
            return Err(fail(b.column(Letter::S), kind));
        }
        st.speed = v;
        out(Canon::SetSpindleSpeed { line, rpm: v });
    }
    if let Some(t) = b.get(Letter::T) {
        let col = b.column(Letter::T);
        let t = whole(t, "T (tool number)", 0.0).map_err(|k| fail(col, k))?;
        if t != 0 && !cfg.tools.contains_key(&t) {
            return Err(fail(col, ErrorKind::UnknownTool { tool: t }));
        }
        st.selected_tool = t;
    }
    // M6, spindle, coolant, M52.
    if b.m(MGroup::ToolChange).is_some() {
        if st.spindle != SpindleDir::Off {
            st.spindle = SpindleDir::Off;
            out(Canon::Spindle { line, dir: SpindleDir::Off });
        }
        st.loaded_tool = st.selected_tool;
        out(Canon::ToolChange { line, tool: st.loaded_tool });
    }
    if let Some(m) = b.m(MGroup::Spindle) {
        let dir = match m {
            3 => SpindleDir::Cw,
            4 => SpindleDir::Ccw,
            _ => SpindleDir::Off,
        };
        st.spindle = dir;
        out(Canon::Spindle { line, dir });
    }
    if let Some(m) = b.m(MGroup::Coolant) {
        let coolant = match m {
            7 => Coolant::Mist,
            8 => Coolant::Flood,
            _ => Coolant::Off,
        };
        out(Canon::Coolant { line, coolant });
    }
    if b.m(MGroup::Override).is_some() {
        let enabled = b.get(Letter::P).is_none_or(|p| p != 0.0);
        out(Canon::AdaptiveFeed { line, enabled });
    }
    // G4.
    if g0 == Some(40) {
        let col = b.g_column(GGroup::NonModal);
        let p = b.get(Letter::P).ok_or_else(|| fail(col, ErrorKind::DwellWithoutP))?;
        if p < 0.0 {
            let kind = ErrorKind::OutOfRange { what: "G4 P (seconds)", value: p, allowed: "0 or more" };
            return Err(fail(b.column(Letter::P), kind));
        }
        out(Canon::Dwell { line, seconds: p });
    }
    // Plane, units, G40, tool length offset, coordinate system, path control, distance modes.
    if let Some(code) = b.g(GGroup::Plane) {
        st.plane = match code {
            170 => Plane::Xy,
            180 => Plane::Zx,
            _ => Plane::Yz,
        };
    }
    if let Some(code) = b.g(GGroup::Units) {
        st.inch = code == 200;
    }
    match b.g(GGroup::ToolLength) {
        Some(430) => {
            let (tool, col) = match b.get(Letter::H) {
                Some(h) => {
                    let col = b.column(Letter::H);
                    (whole(h, "H (tool length offset number)", 0.0).map_err(|k| fail(col, k))?, col)
                }
                None => (st.loaded_tool, b.g_column(GGroup::ToolLength)),
            };
            let mm = if tool == 0 {
                0.0
            } else {
                *cfg.tools.get(&tool).ok_or_else(|| fail(col, ErrorKind::UnknownTool { tool }))?
            };
            st.tlo = mm;
            out(Canon::ToolLengthOffset { line, mm });
        }
        Some(_) => {
            st.tlo = 0.0;
            out(Canon::ToolLengthOffset { line, mm: 0.0 });
        }
        None => {}
    }
    if let Some(code) = b.g(GGroup::CoordSystem) {
        let idx = usize::from((code - 540) / 10).min(5);
        st.offset = cfg.work_offsets[idx].to_array();
        out(Canon::WorkOffset { line, system: idx as u8 + 1, offset: cfg.work_offsets[idx] });
    }
    if let Some(code) = b.g(GGroup::PathControl) {
        let scale = st.scale();
        let mode = match code {
            610 => PathMode::ExactPath,
            611 => PathMode::ExactStop,
            _ => {
                let mut tol = [None, None];
                for (k, l) in [Letter::P, Letter::Q].into_iter().enumerate() {
                    if let Some(v) = b.get(l) {
                        if v < 0.0 {
                            let kind = ErrorKind::OutOfRange {
                                what: "G64 P/Q tolerance",
                                value: v,
                                allowed: "0 or more",
                            };
                            return Err(fail(b.column(l), kind));
                        }
                        tol[k] = Some(v * scale);
                    }
                }
                PathMode::Blend { tolerance_mm: tol[0], naive_cam_mm: tol[1] }
            }
        };
        out(Canon::SetPathMode { line, mode });
    }
    if let Some(code) = b.g(GGroup::Distance) {
        st.incremental = code == 910;
    }
    if let Some(code) = b.g(GGroup::ArcDistance) {
        st.arc_absolute = code == 901;
    }
    if g53 && st.incremental {
        return Err(fail(b.g_column(GGroup::NonModal), ErrorKind::G53Incremental));
    }
    if g_motion.is_some() {
        st.motion = motion_after;
    }

    // G28 or the move.
    if is_g28 {
        let via = target(b, st, false);
        out(Canon::Traverse { line, to: Pos::from_array(via) });
        let home = cfg.home.to_array();
        let mut to = home;
        if has_axes {
            to = via;
            for (k, l) in AXES.into_iter().enumerate() {
                if b.has(l) {
                    to[k] = home[k];
                }
            }
        }
        out(Canon::Traverse { line, to: Pos::from_array(to) });
        st.pos = to;
    } else if let Some(m) = mv {
        let col = if explicit_move.is_some() { b.g_column(GGroup::Motion) } else { b.first_column() };
        match m {
            Motion::Rapid => {
                let to = target(b, st, g53);
                out(Canon::Traverse { line, to: Pos::from_array(to) });
                st.pos = to;
            }
            Motion::Linear => {
                check_feed(st, b).map_err(|k| fail(col, k))?;
                let to = target(b, st, g53);
                out(Canon::Feed { line, to: Pos::from_array(to) });
                st.pos = to;
            }
            Motion::Cw | Motion::Ccw => {
                check_feed(st, b).map_err(|k| fail(col, k))?;
                arc(cfg, b, st, m, line, out).map_err(|(c, k)| fail(if c == 0 { col } else { c }, k))?;
            }
        }
    }

    // Stops.
    Ok(match b.m(MGroup::Stop) {
        Some(0) => {
            out(Canon::Pause { line, optional: false });
            None
        }
        Some(1) => {
            out(Canon::Pause { line, optional: true });
            None
        }
        Some(m) => {
            out(Canon::ProgramEnd { line });
            st.spindle = SpindleDir::Off;
            Some(if m == 2 { EndReason::M2 } else { EndReason::M30 })
        }
        None => None,
    })
}

fn check_feed(st: &State, b: &Block) -> Result<(), ErrorKind> {
    if st.feed_mode == FeedMode::InverseTime && !b.has(Letter::F) {
        return Err(ErrorKind::InverseTimeWithoutF);
    }
    if st.feed == 0.0 {
        return Err(ErrorKind::ZeroFeedRate);
    }
    if st.feed_mode == FeedMode::PerRevolution && st.speed == 0.0 {
        return Err(ErrorKind::ZeroSpindleSpeedPerRev);
    }
    Ok(())
}

/// End point of a move: absolute words are program coordinates (or machine ones with G53),
/// incremental words add to the current point.
#[inline]
fn target(b: &Block, st: &State, g53: bool) -> [f64; 5] {
    let scale = st.scale();
    let mut t = st.pos;
    for (k, l) in AXES.into_iter().enumerate() {
        if let Some(v) = b.get(l) {
            let v = if k < 3 { v * scale } else { v };
            t[k] = if g53 {
                v
            } else if st.incremental {
                st.pos[k] + v
            } else {
                v + st.origin(k)
            };
        }
    }
    t
}

/// A G2/G3 move; on error the column (0: the block's motion word) and the reason.
fn arc(
    cfg: &InterpConfig,
    b: &Block,
    st: &mut State,
    m: Motion,
    line: u64,
    out: &mut impl FnMut(Canon),
) -> Result<(), (u32, ErrorKind)> {
    let cw = m == Motion::Cw;
    let plane = st.plane;
    let [i0, i1, _] = plane.axes();
    let (offsets, normal, axis_letters, axis_names) = match plane {
        Plane::Xy => ([Letter::I, Letter::J], Letter::K, [Letter::X, Letter::Y], "X and Y"),
        Plane::Zx => ([Letter::K, Letter::I], Letter::J, [Letter::Z, Letter::X], "Z and X"),
        Plane::Yz => ([Letter::J, Letter::K], Letter::I, [Letter::Y, Letter::Z], "Y and Z"),
    };
    if b.has(normal) {
        return Err((
            b.column(normal),
            ErrorKind::ArcOffsetOutOfPlane { letter: normal.as_char(), plane: plane.name() },
        ));
    }
    let has_r = b.has(Letter::R);
    let has_ijk = b.has(offsets[0]) || b.has(offsets[1]);
    if has_r && has_ijk {
        return Err((b.column(Letter::R), ErrorKind::ArcMixedFormat));
    }
    if !has_r && !has_ijk {
        return Err((0, ErrorKind::ArcWithoutCenter));
    }
    let turns = match b.get(Letter::P) {
        None => 1,
        Some(p) => {
            let t = whole(p, "G2/G3 P (turns)", 1.0).map_err(|k| (b.column(Letter::P), k))?;
            i32::try_from(t).map_err(|_| {
                (
                    b.column(Letter::P),
                    ErrorKind::OutOfRange { what: "G2/G3 P (turns)", value: p, allowed: "1 or more" },
                )
            })?
        }
    };
    let tol = &cfg.arc_tolerance;
    let scale = st.scale();
    let end = target(b, st, false);
    let start = [st.pos[i0], st.pos[i1]];
    let stop = [end[i0], end[i1]];
    let center = if let Some(r) = b.get(Letter::R) {
        if !b.has(axis_letters[0]) && !b.has(axis_letters[1]) {
            return Err((0, ErrorKind::ArcWithoutEnd { axes: axis_names }));
        }
        let col = b.column(Letter::R);
        if stop == start {
            return Err((col, ErrorKind::ArcRFullCircle));
        }
        let r = r * scale;
        let abs_r = r.abs();
        let mid = [(start[0] + stop[0]) / 2.0, (start[1] + stop[1]) / 2.0];
        let mut half = (mid[0] - stop[0]).hypot(mid[1] - stop[1]);
        if half - abs_r > tol.radius_mm {
            let kind = ErrorKind::ArcRadiusTooSmall {
                radius_mm: abs_r,
                half_chord_mm: half,
                tolerance_mm: tol.radius_mm,
            };
            return Err((col, kind));
        }
        if abs_r < tol.radius_mm {
            let kind = ErrorKind::ArcZeroRadius {
                start_radius_mm: abs_r,
                end_radius_mm: abs_r,
                min_mm: tol.radius_mm,
            };
            return Err((col, kind));
        }
        if half / abs_r > 1.0 - 1e-12 {
            half = abs_r;
        }
        let chord = (stop[1] - start[1]).atan2(stop[0] - start[0]);
        let theta = if cw == (r > 0.0) { chord - FRAC_PI_2 } else { chord + FRAC_PI_2 };
        let offset = abs_r * (half / abs_r).asin().cos();
        [mid[0] + offset * theta.cos(), mid[1] + offset * theta.sin()]
    } else {
        let o = [b.get(offsets[0]).unwrap_or(0.0) * scale, b.get(offsets[1]).unwrap_or(0.0) * scale];
        let c = if st.arc_absolute {
            [o[0] + st.origin(i0), o[1] + st.origin(i1)]
        } else {
            [start[0] + o[0], start[1] + o[1]]
        };
        let r1 = (c[0] - start[0]).hypot(c[1] - start[1]);
        let r2 = (c[0] - stop[0]).hypot(c[1] - stop[1]);
        if r1 < tol.radius_mm || r2 < tol.radius_mm {
            let kind =
                ErrorKind::ArcZeroRadius { start_radius_mm: r1, end_radius_mm: r2, min_mm: tol.radius_mm };
            return Err((0, kind));
        }
        let d = (r1 - r2).abs();
        let rel = d / r1.max(r2);
        let abs_tol = if st.inch { tol.center_abs_inch * MM_PER_INCH } else { tol.center_abs_mm };
        if d > tol.hard_factor * abs_tol || (rel > tol.center_relative && d > abs_tol) {
            let kind = ErrorKind::ArcRadiusMismatch {
                start_radius_mm: r1,
                end_radius_mm: r2,
                difference_mm: d,
                relative_pct: rel * 100.0,
                tolerance_mm: abs_tol,
                hard_limit_mm: tol.hard_factor * abs_tol,
                relative_tolerance_pct: tol.center_relative * 100.0,
            };
            return Err((0, kind));
        }
        c
    };
    let rotation = if cw { -turns } else { turns };
    out(Canon::Arc { line, end: Pos::from_array(end), plane, center, rotation });
    st.pos = end;
    Ok(())
}

/// Reads lines into a reused buffer, refusing lines longer than the limit without reading them
/// whole (so memory stays bounded whatever the input).
#[derive(Debug)]
struct LineReader<R> {
    reader: R,
    buf: Vec<u8>,
    line_no: u64,
    max: usize,
}

impl<R: BufRead> LineReader<R> {
    fn new(reader: R, max: usize) -> Self {
        LineReader { reader, buf: Vec::with_capacity(256), line_no: 0, max }
    }

    fn next_line(&mut self) -> Result<Option<(u64, &[u8])>, GcodeError> {
        self.buf.clear();
        // Room for the line, "\r\n" and one byte to detect an overlong line.
        let limit = self.max as u64 + 3;
        let n = (&mut self.reader)
            .take(limit)
            .read_until(b'\n', &mut self.buf)
            .map_err(|source| GcodeError::Io { line: self.line_no + 1, source })?;
        if n == 0 {
            return Ok(None);
        }
        self.line_no += 1;
        if n as u64 == limit && self.buf.last() != Some(&b'\n') {
            let kind = ErrorKind::LineTooLong { max: self.max };
            return Err(GcodeError::Invalid { line: self.line_no, column: 1, word: String::new(), kind });
        }
        Ok(Some((self.line_no, &self.buf)))
    }
}

/// Runs a whole program from `reader` (wrap files in a `BufReader`), streaming every canonical
/// command into `sink`. Stops at the first error; commands of earlier lines (and of the failing
/// line before the failure) have been delivered by then.
pub fn run<R: BufRead>(
    reader: R,
    config: InterpConfig,
    mut sink: impl FnMut(Canon),
) -> Result<RunSummary, GcodeError> {
    let max = config.max_line_bytes;
    let mut interp = Interpreter::new(config);
    let mut lines = LineReader::new(reader, max);
    let mut canons = 0u64;
    {
        let mut emit = |c: Canon| {
            canons += 1;
            sink(c);
        };
        while let Some((line_no, line)) = lines.next_line()? {
            interp.execute_bytes(line, line_no, &mut emit)?;
            if interp.is_ended() {
                break;
            }
        }
    }
    let end = interp.finish(lines.line_no)?;
    Ok(RunSummary { lines: lines.line_no, blocks: interp.blocks, canons, end, position: interp.position() })
}

/// Pull-based form of [`run`]: an iterator of canonical commands (then at most one error).
#[derive(Debug)]
pub struct Canons<R> {
    interp: Interpreter,
    lines: LineReader<R>,
    pending: VecDeque<Canon>,
    error: Option<GcodeError>,
    done: bool,
}

impl<R: BufRead> Canons<R> {
    /// Iterates over the program read from `reader`.
    pub fn new(reader: R, config: InterpConfig) -> Self {
        let max = config.max_line_bytes;
        Canons {
            interp: Interpreter::new(config),
            lines: LineReader::new(reader, max),
            pending: VecDeque::with_capacity(8),
            error: None,
            done: false,
        }
    }

    /// The interpreter (position, state) after the commands returned so far's lines.
    pub fn interpreter(&self) -> &Interpreter {
        &self.interp
    }
}

impl<R: BufRead> Iterator for Canons<R> {
    type Item = Result<Canon, GcodeError>;

    fn next(&mut self) -> Option<Self::Item> {
        loop {
            if let Some(c) = self.pending.pop_front() {
                return Some(Ok(c));
            }
            if let Some(e) = self.error.take() {
                return Some(Err(e));
            }
            if self.done {
                return None;
            }
            match self.lines.next_line() {
                Err(e) => {
                    self.done = true;
                    return Some(Err(e));
                }
                Ok(None) => {
                    self.done = true;
                    if let Err(e) = self.interp.finish(self.lines.line_no) {
                        return Some(Err(e));
                    }
                }
                Ok(Some((line_no, line))) => {
                    let pending = &mut self.pending;
                    let r = self.interp.execute_bytes(line, line_no, &mut |c| pending.push_back(c));
                    if let Err(e) = r {
                        self.error = Some(e);
                        self.done = true;
                    } else if self.interp.is_ended() {
                        self.done = true;
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;
    use std::f64::consts::SQRT_2;

    fn cfg() -> InterpConfig {
        let mut c = InterpConfig {
            tools: BTreeMap::from([(1, 25.0), (2, 40.0)]),
            home: Pos::new(1.0, 2.0, 3.0, 0.0),
            ..InterpConfig::default()
        };
        c.work_offsets[1] = Pos::new(100.0, 50.0, -20.0, 10.0);
        c
    }

    fn run_with(text: &str, config: InterpConfig) -> Result<Vec<Canon>, GcodeError> {
        let mut v = Vec::new();
        run(text.as_bytes(), config, |c| v.push(c)).map(|_| v)
    }

    fn canons(text: &str) -> Vec<Canon> {
        run_with(text, cfg()).unwrap_or_else(|e| panic!("{e}\n{text}"))
    }

    fn moves(text: &str) -> Vec<Canon> {
        canons(text).into_iter().filter(Canon::is_motion).collect()
    }

    fn ends(text: &str) -> Vec<[f64; 5]> {
        moves(text).iter().filter_map(|c| c.end_point()).map(Pos::to_array).collect()
    }

    fn err(text: &str) -> (u64, u32, String, ErrorKind) {
        match run_with(text, cfg()) {
            Err(GcodeError::Invalid { line, column, word, kind }) => (line, column, word, kind),
            other => panic!("{text:?}: expected an error, got {other:?}"),
        }
    }

    fn close(a: [f64; 5], b: [f64; 5]) -> bool {
        (0..5).all(|k| (a[k] - b[k]).abs() < 1e-9)
    }

    #[test]
    fn modal_moves_feeds_and_line_numbers() {
        let c = canons("G21 G90\nG0 X1 Y2\nZ3\nG1 X4 F100\n\nY5 (c)\nM2\n");
        let want = vec![
            Canon::Traverse { line: 2, to: Pos::new(1.0, 2.0, 0.0, 0.0) },
            Canon::Traverse { line: 3, to: Pos::new(1.0, 2.0, 3.0, 0.0) },
            Canon::SetFeedRate { line: 4, rate: 100.0, mode: FeedMode::PerMinute },
            Canon::Feed { line: 4, to: Pos::new(4.0, 2.0, 3.0, 0.0) },
            Canon::Feed { line: 6, to: Pos::new(4.0, 5.0, 3.0, 0.0) },
            Canon::ProgramEnd { line: 7 },
        ];
        assert_eq!(c, want);
        // An explicit motion code without axis words moves nowhere, like LinuxCNC (no error).
        let c = moves("G0 X1\nG1 F10\nG0\nF20\nM2\n");
        assert_eq!(
            c,
            vec![
                Canon::Traverse { line: 1, to: Pos::new(1.0, 0.0, 0.0, 0.0) },
                Canon::Feed { line: 2, to: Pos::new(1.0, 0.0, 0.0, 0.0) },
                Canon::Traverse { line: 3, to: Pos::new(1.0, 0.0, 0.0, 0.0) },
            ]
        );
    }

    #[test]
    fn comments_numbers_block_delete_and_percent() {
        let text = "%\nN10.5 (a ; b) G0 X1 ; (c\n/G0 X99\nN20 G1 X2 F5 (x;y)\n%\nG0 X7\n";
        assert_eq!(ends(text), vec![[1.0, 0.0, 0.0, 0.0, 0.0], [2.0, 0.0, 0.0, 0.0, 0.0]]);
        assert!(matches!(canons(text).last(), Some(Canon::ProgramEnd { line: 5 })));
        let mut off = cfg();
        off.block_delete = false;
        let v = run_with(text, off).expect("block delete off");
        assert_eq!(v.iter().filter(|c| c.is_motion()).count(), 3);
        // Lines after M30 are not read, even invalid ones.
        assert_eq!(ends("G0 X1\nM30\nG0 X7 X8 #1\n"), vec![[1.0, 0.0, 0.0, 0.0, 0.0]]);
        assert_eq!(err("%\nG0 X1\n").3, ErrorKind::MissingClosingPercent);
        assert_eq!(err("G0 X1\n").3, ErrorKind::MissingProgramEnd);
        assert_eq!(err("G0 X1\n").0, 2);
        assert_eq!(err("(c)\n%\nG0 X1\n%\n").3, ErrorKind::MisplacedPercent);
        assert_eq!(err("").3, ErrorKind::MissingProgramEnd);
        // Fanuc program number, non-UTF-8 bytes in a comment.
        let mut v = Vec::new();
        run(&b"%\nO0001 (T\xe9ST)\nG0 X1\n%\n"[..], cfg(), |c| v.push(c)).expect("bytes");
        assert_eq!(v.len(), 2);
    }

    #[test]
    fn incremental_inches_and_a_axis() {
        let p = ends("G91 G0 X1 Y1 A10\nX1 A-5\nG90 G20 G0 X1\nG91 Y0.5\nG21 G90 G0 Z2 A90\nM2\n");
        let want = [
            [1.0, 1.0, 0.0, 10.0, 0.0],
            [2.0, 1.0, 0.0, 5.0, 0.0],
            [25.4, 1.0, 0.0, 5.0, 0.0],
            [25.4, 13.7, 0.0, 5.0, 0.0],
            [25.4, 13.7, 2.0, 90.0, 0.0],
        ];
        assert_eq!(p.len(), want.len());
        for (a, b) in p.iter().zip(want) {
            assert!(close(*a, b), "{a:?} {b:?}");
        }
        // F is read in the units in effect before the block; feeds keep their value across G20/G21.
        let c = canons("G20 F10\nG1 X1\nF10\nG21 G1 X2\nM2\n");
        let feeds: Vec<f64> = c
            .iter()
            .filter_map(|c| if let Canon::SetFeedRate { rate, .. } = c { Some(*rate) } else { None })
            .collect();
        assert_eq!(feeds, vec![10.0, 254.0]);
    }

    #[test]
    fn arcs_ijk_absolute_centres_and_r() {
        let c = moves(
            "G0 X0 Y0\nF100\nG2 X10 Y0 I5 J0\nG90.1 G3 X0 Y0 I5 J0\nG91.1 G2 X10 Y0 R5\nG2 X0 Y0 R-5\nM2\n",
        );
        let arcs: Vec<([f64; 2], i32)> = c
            .iter()
            .filter_map(|c| {
                if let Canon::Arc { center, rotation, .. } = c { Some((*center, *rotation)) } else { None }
            })
            .collect();
        assert_eq!(arcs.len(), 4);
        for (k, (center, rot)) in arcs.iter().enumerate() {
            assert!((center[0] - 5.0).abs() < 1e-9 && center[1].abs() < 1e-9, "{k}: {center:?}");
            assert_eq!(*rot, if k == 1 { 1 } else { -1 });
        }
        // R picks the short (R > 0) or the long (R < 0) arc: centres on either side of the chord.
        let short = moves("G0 X0 Y0\nG2 X2 Y0 R2 F1\nM2\n");
        let long = moves("G0 X0 Y0\nG2 X2 Y0 R-2 F1\nM2\n");
        let cy = |m: &[Canon]| if let Canon::Arc { center, .. } = m[1] { center } else { panic!("{m:?}") };
        assert!((cy(&short)[0] - 1.0).abs() < 1e-12 && (cy(&short)[1] + 3f64.sqrt()).abs() < 1e-12);
        assert!((cy(&long)[0] - 1.0).abs() < 1e-12 && (cy(&long)[1] - 3f64.sqrt()).abs() < 1e-12);
        // G3 with R > 0 is short the other way.
        let g3 = moves("G0 X0 Y0\nG3 X2 Y0 R2 F1\nM2\n");
        assert!((cy(&g3)[1] - 3f64.sqrt()).abs() < 1e-12);
        // Absolute centre with a work offset and the tool length offset (G18: centre is Z, X).
        let g18 = moves("G55 G43 H1 G0 X0 Y0 Z0\nG18 G90.1 G2 X2 Z0 I1 K0 F1\nM2\n");
        let Canon::Arc { center, plane, end, .. } = g18[1] else { panic!("{g18:?}") };
        assert_eq!(plane, Plane::Zx);
        assert!(
            (center[0] - (-20.0 + 25.0)).abs() < 1e-12 && (center[1] - 101.0).abs() < 1e-12,
            "{center:?}"
        );
        assert!(close(end.to_array(), [102.0, 50.0, 5.0, 0.0, 0.0]));
    }

    #[test]
    fn full_circles_helices_turns_and_planes() {
        let m = moves("G0 X1 Y0 Z0\nG3 I-1 F50\nG2 X1 Y0 I-1 J0 Z-2 P3 A90\nM2\n");
        assert_eq!(
            m[1],
            Canon::Arc {
                line: 2,
                end: Pos::new(1.0, 0.0, 0.0, 0.0),
                plane: Plane::Xy,
                center: [0.0, 0.0],
                rotation: 1
            }
        );
        assert_eq!(
            m[2],
            Canon::Arc {
                line: 3,
                end: Pos::new(1.0, 0.0, -2.0, 90.0),
                plane: Plane::Xy,
                center: [0.0, 0.0],
                rotation: -3
            }
        );
        let y = moves("G0 X1 Y2 Z3\nG19 G3 Y4 Z5 J1 K1 X9 F1\nM2\n");
        assert_eq!(
            y[1],
            Canon::Arc {
                line: 2,
                end: Pos::new(9.0, 4.0, 5.0, 0.0),
                plane: Plane::Yz,
                center: [3.0, 4.0],
                rotation: 1
            }
        );
        assert_eq!(err("G0 X1\nG2 X1 Y0 R1 F1\nM2\n").3, ErrorKind::ArcRFullCircle);
        assert!(matches!(err("G2 X1 I0.001 F1\nM2\n").3, ErrorKind::ArcZeroRadius { .. }));
        assert_eq!(err("G2 X1 F1\nM2\n").3, ErrorKind::ArcWithoutCenter);
        assert_eq!(err("G2 R1 F1\nM2\n").3, ErrorKind::ArcWithoutEnd { axes: "X and Y" });
        assert_eq!(err("G2 X2 R1 I1 F1\nM2\n").3, ErrorKind::ArcMixedFormat);
        assert_eq!(
            err("G18 G2 X2 I1 J1 F1\nM2\n").3,
            ErrorKind::ArcOffsetOutOfPlane { letter: 'J', plane: "G18 ZX" }
        );
        assert!(matches!(err("G2 X2 I1 P0 F1\nM2\n").3, ErrorKind::OutOfRange { .. }));
        assert!(matches!(err("G2 X2 I1 P1.5 F1\nM2\n").3, ErrorKind::NotAnInteger { .. }));
    }

    #[test]
    fn arc_radius_tolerance_follows_linuxcnc_and_is_configurable() {
        let ok = |t: &str, c: InterpConfig| run_with(&format!("G0 X0 Y0\nF1\nG2 {t}\nM2\n"), c).is_ok();
        for (t, want) in [
            ("X200.05 Y0 I100 J0", true),
            ("X2.0015 Y0 I1 J0", true),
            ("X20002.5 Y0 I10000 J0", true),
            ("X20.02 Y0 I10 J0", true),
            ("X20.03 Y0 I10 J0", false),
            ("X202.8 Y0 I100 J0", false),
            ("X2003 Y0 I1000 J0", false),
        ] {
            assert_eq!(ok(t, cfg()), want, "{t}");
        }
        let strict = InterpConfig { arc_tolerance: ArcTolerance::absolute(0.01), ..cfg() };
        assert!(!ok("X200.05 Y0 I100 J0", strict.clone()));
        assert!(ok("X200.009 Y0 I100 J0", strict));
        // Inches: the absolute tolerance is 0.0028 in = 0.0718 mm.
        assert!(run_with("G20 G0 X0 Y0\nF1\nG2 X2.002 Y0 I1 J0\nM2\n", cfg()).is_ok());
        let (line, column, word, kind) = err("G0 X0 Y0\nF1\nG2 X20.05 Y0 I10 J0\nM2\n");
        assert_eq!((line, column, word.as_str()), (3, 1, "G2"));
        let ErrorKind::ArcRadiusMismatch { start_radius_mm, end_radius_mm, tolerance_mm, .. } = kind else {
            panic!("{kind:?}")
        };
        assert!((start_radius_mm - 10.0).abs() < 1e-9 && (end_radius_mm - 10.05).abs() < 1e-9);
        assert!((tolerance_mm - 0.02 * SQRT_2).abs() < 1e-12);
        let msg = err("G0 X0 Y0\nF1\nG2 X20.05 Y0 I10 J0\nM2\n");
        let text = GcodeError::Invalid { line: msg.0, column: msg.1, word: msg.2, kind: msg.3 }.to_string();
        assert!(
            text.contains("start radius 10.0000 mm, end radius 10.0500 mm") && text.contains("0.0283"),
            "{text}"
        );
    }

    #[test]
    fn g53_g28_and_work_offsets() {
        let c = canons(
            "G55\nG0 X1 Y1 Z1 A0\nG53 G0 Z0\nG53 G1 X2 F100\nG28\nG28 Z7\nG91 G28 Z0\nG90 G0 X0\nM2\n",
        );
        assert!(
            matches!(c[0], Canon::WorkOffset { system: 2, offset, .. } if offset == Pos::new(100.0, 50.0, -20.0, 10.0))
        );
        let e =
            ends("G55\nG0 X1 Y1 Z1 A0\nG53 G0 Z0\nG53 G1 X2 F100\nG28\nG28 Z7\nG91 G28 Z0\nG90 G0 X0\nM2\n");
        let want = [
            [101.0, 51.0, -19.0, 10.0, 0.0],
            [101.0, 51.0, 0.0, 10.0, 0.0],
            [2.0, 51.0, 0.0, 10.0, 0.0],
            [2.0, 51.0, 0.0, 10.0, 0.0],
            [1.0, 2.0, 3.0, 0.0, 0.0],
            [1.0, 2.0, -13.0, 0.0, 0.0],
            [1.0, 2.0, 3.0, 0.0, 0.0],
            [1.0, 2.0, 3.0, 0.0, 0.0],
            [1.0, 2.0, 3.0, 0.0, 0.0],
            [100.0, 2.0, 3.0, 0.0, 0.0],
        ];
        assert_eq!(e.len(), want.len(), "{e:?}");
        for (a, b) in e.iter().zip(want) {
            assert!(close(*a, b), "{a:?} vs {b:?}");
        }
        assert_eq!(err("G91 G53 G0 X1\nM2\n").3, ErrorKind::G53Incremental);
        assert_eq!(err("G53 G2 X1 I1 F1\nM2\n").3, ErrorKind::G53NeedsLinearMove);
        assert_eq!(err("G53 X1\nM2\n").3, ErrorKind::AxisWordsWithoutMotion);
        assert_eq!(
            err("G0\nG53 Z1 G4 P1\nM2\n").3,
            ErrorKind::ModalGroupConflict {
                group: super::super::lexer::GGroup::NonModal.name(),
                other: "G53".into()
            }
        );
        assert_eq!(err("G0 X1 G28\nM2\n").3, ErrorKind::AxisWordsClaimedTwice);
    }

    #[test]
    fn the_c_axis_and_inverse_time_feed() {
        // C words: degrees, absolute and incremental, never scaled by G20.
        let p = ends("G0 X1 C90\nG91 G0 C-30 A10\nG20 G0 C15\nM2\n");
        assert!(close(p[0], [1.0, 0.0, 0.0, 0.0, 90.0]), "{:?}", p[0]);
        assert!(close(p[1], [1.0, 0.0, 0.0, 10.0, 60.0]), "{:?}", p[1]);
        assert!(close(p[2], [1.0, 0.0, 0.0, 10.0, 75.0]), "{:?}", p[2]);
        // G93: F is 1/min, given on every feed move, not scaled by G20; G94 goes back.
        let c = canons("G93 G1 X10 C45 F2\nG20 G1 X1 F4\nG94 G21\nG1 X2 F100\nM2\n");
        let feeds: Vec<(f64, FeedMode)> = c
            .iter()
            .filter_map(|c| {
                if let Canon::SetFeedRate { rate, mode, .. } = c { Some((*rate, *mode)) } else { None }
            })
            .collect();
        assert_eq!(
            feeds,
            vec![
                (0.0, FeedMode::InverseTime),
                (2.0, FeedMode::InverseTime),
                (4.0, FeedMode::InverseTime),
                (0.0, FeedMode::PerMinute),
                (100.0, FeedMode::PerMinute)
            ]
        );
        let (line, column, word, kind) = err("G93\nG1 X10 F2\nX20\nM2\n");
        assert_eq!((line, column, kind), (3, 1, ErrorKind::InverseTimeWithoutF), "{word}");
        let (line, _, _, kind) = err("G93 G1 X1 F1\nG2 X2 I0.5\nM2\n");
        assert_eq!((line, kind), (2, ErrorKind::InverseTimeWithoutF));
        // B is still refused, naming the axes there are.
        assert!(matches!(err("G0 B5\nM2\n").3, ErrorKind::UnsupportedLetter { .. }));
    }

    #[test]
    fn tool_changes_and_length_offsets() {
        let c = canons("T1 M6\nS1000 M3\nG43\nG0 Z0\nT2 M6 G43 H2\nG0 Z0\nG49\nG0 Z0\nG43 H0\nM2\n");
        let tl: Vec<f64> = c
            .iter()
            .filter_map(|c| if let Canon::ToolLengthOffset { mm, .. } = c { Some(*mm) } else { None })
            .collect();
        assert_eq!(tl, vec![25.0, 40.0, 0.0, 0.0]);
        let z: Vec<f64> = c.iter().filter_map(|c| c.end_point()).map(|p| p.z).collect();
        assert_eq!(z, vec![25.0, 40.0, 0.0]);
        // M6 stops a running spindle first.
        let i = c.iter().position(|c| matches!(c, Canon::ToolChange { tool: 2, .. })).expect("change");
        assert_eq!(c[i - 1], Canon::Spindle { line: 5, dir: SpindleDir::Off });
        assert_eq!(err("T3\nM2\n").3, ErrorKind::UnknownTool { tool: 3 });
        assert_eq!(err("G43 H3\nM2\n").3, ErrorKind::UnknownTool { tool: 3 });
        assert!(matches!(err("T1.5\nM2\n").3, ErrorKind::NotAnInteger { .. }));
        assert_eq!(err("H1\nM2\n").3, ErrorKind::UnusedWord { letter: 'H', needs: "G43" });
    }

    #[test]
    fn feed_modes_spindle_coolant_dwell_pause_adaptive_path() {
        let c = canons(
            "S1200 M3\nG95 F0.1\nG1 X1\nM4\nM5\nM7\nM8\nM9\nG4 P1.5\nM0\nM1\nM52 P1\nM52 P0\nM52\nG61\nG61.1\nG64\n\
             G64 P0.02 Q0.01\nG20 G64 P0.001\nM2\n",
        );
        let want = [
            Canon::SetSpindleSpeed { line: 1, rpm: 1200.0 },
            Canon::Spindle { line: 1, dir: SpindleDir::Cw },
            Canon::SetFeedRate { line: 2, rate: 0.0, mode: FeedMode::PerRevolution },
            Canon::SetFeedRate { line: 2, rate: 0.1, mode: FeedMode::PerRevolution },
            Canon::Feed { line: 3, to: Pos::new(1.0, 0.0, 0.0, 0.0) },
            Canon::Spindle { line: 4, dir: SpindleDir::Ccw },
            Canon::Spindle { line: 5, dir: SpindleDir::Off },
            Canon::Coolant { line: 6, coolant: Coolant::Mist },
            Canon::Coolant { line: 7, coolant: Coolant::Flood },
            Canon::Coolant { line: 8, coolant: Coolant::Off },
            Canon::Dwell { line: 9, seconds: 1.5 },
            Canon::Pause { line: 10, optional: false },
            Canon::Pause { line: 11, optional: true },
            Canon::AdaptiveFeed { line: 12, enabled: true },
            Canon::AdaptiveFeed { line: 13, enabled: false },
            Canon::AdaptiveFeed { line: 14, enabled: true },
            Canon::SetPathMode { line: 15, mode: PathMode::ExactPath },
            Canon::SetPathMode { line: 16, mode: PathMode::ExactStop },
            Canon::SetPathMode { line: 17, mode: PathMode::Blend { tolerance_mm: None, naive_cam_mm: None } },
            Canon::SetPathMode {
                line: 18,
                mode: PathMode::Blend { tolerance_mm: Some(0.02), naive_cam_mm: Some(0.01) },
            },
        ];
        assert_eq!(&c[..want.len()], &want);
        assert!(
            matches!(c[want.len()], Canon::SetPathMode { mode: PathMode::Blend { tolerance_mm: Some(t), .. }, .. } if (t - 0.0254).abs() < 1e-12)
        );
        // G94/G95 reset F to 0: the next feed move is refused, like LinuxCNC.
        assert_eq!(err("F100\nG94\nG1 X1\nM2\n").3, ErrorKind::ZeroFeedRate);
        assert_eq!(err("G95 F0.1\nG1 X1\nM2\n").3, ErrorKind::ZeroSpindleSpeedPerRev);
        assert_eq!(err("G1 X1 F0\nM2\n").3, ErrorKind::ZeroFeedRate);
        assert_eq!(err("G4\nM2\n").3, ErrorKind::DwellWithoutP);
        assert!(matches!(err("G4 P-1\nM2\n").3, ErrorKind::OutOfRange { .. }));
        assert!(matches!(err("F-1\nM2\n").3, ErrorKind::OutOfRange { .. }));
        assert!(matches!(err("S-1\nM2\n").3, ErrorKind::OutOfRange { .. }));
        assert_eq!(
            err("G0 X1 P2\nM2\n").3,
            ErrorKind::UnusedWord { letter: 'P', needs: "G4, G64, M52 or G2/G3" }
        );
        assert_eq!(err("G0 X1 Q2\nM2\n").3, ErrorKind::UnusedWord { letter: 'Q', needs: "G64" });
        assert_eq!(err("G1 X1 I2 F1\nM2\n").3, ErrorKind::UnusedWord { letter: 'I', needs: "G2/G3" });
    }

    #[test]
    fn unsupported_features_name_line_and_column() {
        let cases: [(&str, u32, &str, ErrorKind); 8] = [
            ("G0 X0\nG1 G41 D1 X1 F1\n", 4, "G41", ErrorKind::CutterCompensation),
            ("G0 X0\nG42\n", 1, "G42", ErrorKind::CutterCompensation),
            ("G0 X0\nG98 G81 X1 Y1 Z-1 R1\n", 5, "G81", ErrorKind::CannedCycle),
            ("G0 X0\no100 sub\n", 1, "o100", ErrorKind::OWord),
            ("G0 X0\n#1 = 5\n", 1, "#", ErrorKind::Parameter),
            ("G0 X0\nG0 X[1 + 2]\n", 5, "[", ErrorKind::Expression),
            ("G0 X0\nG0 X1 (abc\n", 7, "(abc", ErrorKind::UnclosedComment),
            (
                "G0 X0\nX1 G1 Y2 G0\n",
                10,
                "G0",
                ErrorKind::ModalGroupConflict {
                    group: super::super::lexer::GGroup::Motion.name(),
                    other: "G1".into(),
                },
            ),
        ];
        for (text, column, word, kind) in cases {
            let e = err(text);
            assert_eq!((e.0, e.1, e.2.as_str(), &e.3), (2, column, word, &kind), "{text:?}");
        }
        let (line, column, word, kind) = err("G80\nG0 X1\nG80\nY1\n");
        assert_eq!((line, column, word.as_str(), kind), (4, 1, "Y1", ErrorKind::AxisWordsWithoutMotion));
        assert_eq!(err("X1\n").3, ErrorKind::AxisWordsWithoutMotion);
        let e = run_with("G0 X0\nG0 X1 Y2 Z3 A4\nG1 G41 X1\n", cfg()).expect_err("g41");
        assert_eq!(
            e.to_string(),
            "line 3, column 4 (`G41`): cutter radius compensation (G41/G42) is not supported"
        );
    }

    #[test]
    fn long_lines_are_refused_without_reading_them_whole() {
        let config = InterpConfig { max_line_bytes: 64, ..cfg() };
        let long = format!("G0 X1\n({})\nM2\n", "x".repeat(10_000));
        let e = run_with(&long, config.clone()).expect_err("long");
        assert_eq!((e.line(), e.kind()), (2, Some(&ErrorKind::LineTooLong { max: 64 })));
        let crlf = format!("G0 X1\r\n({})\r\nM2\r\n", "x".repeat(62));
        assert!(run_with(&crlf, config).is_ok());
    }

    #[test]
    fn iterator_and_line_api_agree_with_run() {
        let text = "%\nG0 X1\nG1 X2 F10\nG2 X4 I1\n%\n";
        let pulled: Vec<Canon> = Canons::new(text.as_bytes(), cfg()).collect::<Result<_, _>>().expect("iter");
        assert_eq!(pulled, canons(text));
        let mut it = Canons::new("G0 X1\nG0 X1 X2\nG0 X3\n".as_bytes(), cfg());
        assert!(matches!(it.next(), Some(Ok(Canon::Traverse { line: 1, .. }))));
        assert!(matches!(it.next(), Some(Err(GcodeError::Invalid { line: 2, column: 7, .. }))));
        assert!(it.next().is_none());
        let mut interp = Interpreter::new(cfg());
        let mut v = Vec::new();
        interp.execute_line("G55 G0 X1", 1, &mut |c| v.push(c)).expect("line");
        assert_eq!(interp.program_position(), Pos::new(1.0, -50.0, 20.0, -10.0));
        assert!(close(interp.position().to_array(), [101.0, 0.0, 0.0, 0.0, 0.0]));
        interp.execute_line("M2", 2, &mut |c| v.push(c)).expect("end");
        assert!(interp.is_ended());
        assert_eq!(interp.finish(2).expect("ended"), EndReason::M2);
        let s = run("G0 X1\nG1 Y1 F1\nM30\n".as_bytes(), cfg(), |_| {}).expect("run");
        assert_eq!((s.lines, s.blocks, s.canons, s.end), (3, 3, 4, EndReason::M30));
    }

    /// Reference: the end point of every move by plain accumulation of the written numbers.
    fn reference_end(words: &[[Option<f64>; 3]], absolute: &[bool]) -> [f64; 3] {
        let mut p = [0.0; 3];
        for (k, w) in words.iter().enumerate() {
            for (i, v) in w.iter().enumerate() {
                if let Some(v) = v {
                    p[i] = if absolute[k] { *v } else { p[i] + v };
                }
            }
        }
        p
    }

    proptest! {
        /// Random G0/G1/G2/G3 (valid arcs) in G90/G91 end where plain accumulation says.
        #[test]
        fn final_position_matches_accumulation(
            steps in prop::collection::vec(
                (0u8..4, -50.0f64..50.0, -50.0f64..50.0, -5.0f64..5.0, any::<bool>(), 0.5f64..20.0, -3.1f64..3.1,
                 any::<bool>()),
                1..40),
        ) {
            let r4 = |v: f64| (v * 1e4).round() / 1e4;
            let mut text = String::from("G21 G17 F500\n");
            let mut words = Vec::new();
            let mut absolute = Vec::new();
            let mut pos = [0.0f64; 3];
            for &(g, x, y, z, abs, r, ang, with_z) in &steps {
                let mode = if abs { "G90" } else { "G91" };
                if g < 2 {
                    let (x, y, z) = (r4(x), r4(y), r4(z));
                    text.push_str(&format!("{mode} G{g} X{x:.4} Y{y:.4} Z{z:.4}\n"));
                    words.push([Some(x), Some(y), Some(z)]);
                    pos = if abs { [x, y, z] } else { [pos[0] + x, pos[1] + y, pos[2] + z] };
                } else {
                    // Centre r away from the current point, end on the same circle.
                    let (i, j) = (r4(r * ang.cos()), r4(r * ang.sin()));
                    let (cx, cy) = (pos[0] + i, pos[1] + j);
                    let rr = i.hypot(j);
                    let e = ang + 1.3;
                    let (ex, ey) = (r4(cx + rr * e.cos()), r4(cy + rr * e.sin()));
                    let z = if with_z { Some(r4(z)) } else { None };
                    let (wx, wy) = if abs { (ex, ey) } else { (r4(ex - pos[0]), r4(ey - pos[1])) };
                    let wz = z;
                    let zs = wz.map_or(String::new(), |z| format!(" Z{z:.4}"));
                    text.push_str(&format!("{mode} G{g} X{wx:.4} Y{wy:.4}{zs} I{i:.4} J{j:.4}\n"));
                    words.push([Some(wx), Some(wy), wz]);
                    let nz = match wz { Some(z) if abs => z, Some(z) => pos[2] + z, None => pos[2] };
                    pos = if abs { [wx, wy, nz] } else { [pos[0] + wx, pos[1] + wy, nz] };
                }
                absolute.push(abs);
            }
            text.push_str("M2\n");
            let c = run_with(&text, InterpConfig::default())
                .map_err(|e| TestCaseError::fail(format!("{e}\n{text}")))?;
            let last = c.iter().rev().find_map(Canon::end_point).expect("a move");
            let want = reference_end(&words, &absolute);
            for (k, w) in want.iter().enumerate() {
                let got = last.to_array()[k];
                prop_assert!((got - w).abs() < 1e-9, "axis {} got {:?} want {:?}\n{}", k, last, want, text);
            }
        }
    }
}
