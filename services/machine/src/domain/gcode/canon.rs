//! Canonical machine commands: what the interpreter emits and the rest of the machine consumes.
//!
//! Modelled on LinuxCNC's canonical interface (`STRAIGHT_TRAVERSE`, `STRAIGHT_FEED`, `ARC_FEED`,
//! ...), so a program run by both can be compared call by call (see [`super::rs274`]).
//!
//! # Frame and units
//! Every position is in **machine coordinates of the controlled point** (the spindle gauge line),
//! in mm, with the A and C axes in degrees:
//!
//! ```text
//! machine = program value x units (1 or 25.4) + work offset (G54-G59) + tool length offset (Z only, G43)
//! ```
//!
//! G53 words are machine coordinates already. Where the tool tip is follows from the physical
//! tool length the consumer knows from [`Canon::ToolChange`]; [`Canon::ToolLengthOffset`] and
//! [`Canon::WorkOffset`] say how program coordinates map to machine ones and never move anything.
//! Feeds are mm/min (G94) or mm/rev (G95).

use std::f64::consts::TAU;

/// A point of the machine: X, Y, Z in mm, A and C in degrees.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Pos {
    /// X, mm.
    pub x: f64,
    /// Y, mm.
    pub y: f64,
    /// Z, mm.
    pub z: f64,
    /// A (rotation about X), degrees.
    pub a: f64,
    /// C (rotation about Z), degrees.
    pub c: f64,
}

impl Pos {
    /// The origin.
    pub const ZERO: Pos = Pos { x: 0.0, y: 0.0, z: 0.0, a: 0.0, c: 0.0 };

    /// A point from its coordinates, C at 0.
    pub const fn new(x: f64, y: f64, z: f64, a: f64) -> Pos {
        Pos { x, y, z, a, c: 0.0 }
    }

    /// The same point with C at `c`.
    pub const fn with_c(self, c: f64) -> Pos {
        Pos { c, ..self }
    }

    /// `[x, y, z, a, c]`.
    pub const fn to_array(self) -> [f64; 5] {
        [self.x, self.y, self.z, self.a, self.c]
    }

    /// From `[x, y, z, a, c]`.
    pub const fn from_array(v: [f64; 5]) -> Pos {
        Pos { x: v[0], y: v[1], z: v[2], a: v[3], c: v[4] }
    }

    /// Coordinate `i` (0 X, 1 Y, 2 Z, 3 A, 4 C); `None` beyond.
    pub fn get(self, i: usize) -> Option<f64> {
        self.to_array().get(i).copied()
    }

    /// Largest absolute coordinate difference (mm or degrees).
    pub fn max_abs_diff(self, other: Pos) -> f64 {
        let (a, b) = (self.to_array(), other.to_array());
        (0..5).map(|i| (a[i] - b[i]).abs()).fold(0.0, f64::max)
    }
}

/// The plane of circular moves (G17/G18/G19), with LinuxCNC's axis order.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Plane {
    /// G17: first axis X, second Y, normal Z.
    #[default]
    Xy,
    /// G18: first axis Z, second X, normal Y (LinuxCNC `CANON_PLANE_XZ`).
    Zx,
    /// G19: first axis Y, second Z, normal X.
    Yz,
}

impl Plane {
    /// Indices (0 X, 1 Y, 2 Z) of the first, second and normal axis. A positive rotation turns from
    /// the first axis towards the second: counter-clockwise seen from the positive normal axis.
    pub const fn axes(self) -> [usize; 3] {
        match self {
            Plane::Xy => [0, 1, 2],
            Plane::Zx => [2, 0, 1],
            Plane::Yz => [1, 2, 0],
        }
    }

    /// `G17 XY`, `G18 ZX`, `G19 YZ`.
    pub const fn name(self) -> &'static str {
        match self {
            Plane::Xy => "G17 XY",
            Plane::Zx => "G18 ZX",
            Plane::Yz => "G19 YZ",
        }
    }
}

/// How F is read.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum FeedMode {
    /// G94: mm/min.
    #[default]
    PerMinute,
    /// G95: mm per spindle revolution.
    PerRevolution,
    /// G93: inverse time, F is 1 / (the move's duration in minutes), given on every feed move.
    InverseTime,
}

/// Spindle state (M3/M4/M5).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum SpindleDir {
    /// M3.
    Cw,
    /// M4.
    Ccw,
    /// M5 (also implied by M6).
    #[default]
    Off,
}

/// Coolant (M7/M8/M9).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Coolant {
    /// M7.
    Mist,
    /// M8.
    Flood,
    /// M9: both off.
    Off,
}

/// Path control (G61/G61.1/G64).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum PathMode {
    /// G61: exact path (may slow down at corners, never rounds them).
    ExactPath,
    /// G61.1: exact stop at the end of every move.
    ExactStop,
    /// G64: blending; `tolerance_mm` from P (`None`: as fast as possible), `naive_cam_mm` from Q.
    Blend {
        /// Largest path deviation allowed by blending, mm.
        tolerance_mm: Option<f64>,
        /// Naive CAM detector tolerance (collinear points merged), mm.
        naive_cam_mm: Option<f64>,
    },
}

/// One canonical machine command; `line` is the 1-based source line it came from.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Canon {
    /// Rapid move (G0, G28) to `to`.
    Traverse {
        /// Source line.
        line: u64,
        /// End point (machine).
        to: Pos,
    },
    /// Straight move at the feed rate (G1).
    Feed {
        /// Source line.
        line: u64,
        /// End point (machine).
        to: Pos,
    },
    /// Circular or helical move at the feed rate (G2/G3), LinuxCNC's `ARC_FEED`.
    Arc {
        /// Source line.
        line: u64,
        /// End point (machine); its normal-axis coordinate is the helix end, A moves linearly.
        end: Pos,
        /// The plane.
        plane: Plane,
        /// Centre in the plane's first and second axis (machine), see [`Plane::axes`].
        center: [f64; 2],
        /// Turns and direction: +1 counter-clockwise (G3), -1 clockwise (G2) as seen from the
        /// positive normal axis; |rotation| = 1 + number of extra full turns (G2/G3 P). An arc
        /// whose end equals its start is a full circle.
        rotation: i32,
    },
    /// Feed rate (F, or 0 after a G94/G95 mode change).
    SetFeedRate {
        /// Source line.
        line: u64,
        /// mm/min or mm/rev.
        rate: f64,
        /// How to read `rate`.
        mode: FeedMode,
    },
    /// Spindle speed (S), rpm.
    SetSpindleSpeed {
        /// Source line.
        line: u64,
        /// Revolutions per minute.
        rpm: f64,
    },
    /// Spindle on/off (M3/M4/M5; `Off` before a tool change when it was running).
    Spindle {
        /// Source line.
        line: u64,
        /// Direction or off.
        dir: SpindleDir,
    },
    /// Tool change (M6) to the tool selected by T (0: no tool).
    ToolChange {
        /// Source line.
        line: u64,
        /// Tool number.
        tool: u32,
    },
    /// Tool length offset now in effect (G43 H / G49), mm along Z.
    ToolLengthOffset {
        /// Source line.
        line: u64,
        /// Offset, mm.
        mm: f64,
    },
    /// Work coordinate system now in effect (G54-G59).
    WorkOffset {
        /// Source line.
        line: u64,
        /// 1 (G54) ..= 6 (G59).
        system: u8,
        /// Its origin in machine coordinates.
        offset: Pos,
    },
    /// Coolant.
    Coolant {
        /// Source line.
        line: u64,
        /// Which.
        coolant: Coolant,
    },
    /// Dwell (G4 P), seconds.
    Dwell {
        /// Source line.
        line: u64,
        /// Seconds.
        seconds: f64,
    },
    /// Program stop (M0) or optional stop (M1).
    Pause {
        /// Source line.
        line: u64,
        /// M1.
        optional: bool,
    },
    /// Adaptive feed (M52 P1 on / M52 P0 off): the adaptive loop may change the feed.
    AdaptiveFeed {
        /// Source line.
        line: u64,
        /// On.
        enabled: bool,
    },
    /// Path control mode.
    SetPathMode {
        /// Source line.
        line: u64,
        /// The mode.
        mode: PathMode,
    },
    /// End of program (M2, M30 or the closing `%`): the spindle and coolant stop.
    ProgramEnd {
        /// Source line.
        line: u64,
    },
}

impl Canon {
    /// The source line.
    pub fn line(&self) -> u64 {
        match *self {
            Canon::Traverse { line, .. }
            | Canon::Feed { line, .. }
            | Canon::Arc { line, .. }
            | Canon::SetFeedRate { line, .. }
            | Canon::SetSpindleSpeed { line, .. }
            | Canon::Spindle { line, .. }
            | Canon::ToolChange { line, .. }
            | Canon::ToolLengthOffset { line, .. }
            | Canon::WorkOffset { line, .. }
            | Canon::Coolant { line, .. }
            | Canon::Dwell { line, .. }
            | Canon::Pause { line, .. }
            | Canon::AdaptiveFeed { line, .. }
            | Canon::SetPathMode { line, .. }
            | Canon::ProgramEnd { line } => line,
        }
    }

    /// End point of a motion command, `None` for the others.
    pub fn end_point(&self) -> Option<Pos> {
        match *self {
            Canon::Traverse { to, .. } | Canon::Feed { to, .. } => Some(to),
            Canon::Arc { end, .. } => Some(end),
            _ => None,
        }
    }

    /// Traverse, feed or arc.
    pub fn is_motion(&self) -> bool {
        self.end_point().is_some()
    }
}

/// Signed sweep angle (radians, positive counter-clockwise) of an arc from `start`, as LinuxCNC
/// runs it: from the start angle to the end angle in the direction of `rotation`, plus
/// `|rotation| - 1` full turns; an end angle equal to the start angle is a full turn.
pub fn arc_sweep(plane: Plane, start: Pos, end: Pos, center: [f64; 2], rotation: i32) -> f64 {
    let [i, j, _] = plane.axes();
    let (s, e) = (start.to_array(), end.to_array());
    let a0 = (s[j] - center[1]).atan2(s[i] - center[0]);
    let a1 = (e[j] - center[1]).atan2(e[i] - center[0]);
    let extra = f64::from(rotation.unsigned_abs().saturating_sub(1));
    if rotation >= 0 {
        let mut d = a1 - a0;
        while d <= 1e-12 {
            d += TAU;
        }
        d + extra * TAU
    } else {
        let mut d = a0 - a1;
        while d <= 1e-12 {
            d += TAU;
        }
        -(d + extra * TAU)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::PI;

    #[test]
    fn sweep_directions_full_circles_and_turns() {
        let c = [0.0, 0.0];
        let s = Pos::new(1.0, 0.0, 0.0, 0.0);
        let e = Pos::new(0.0, 1.0, 0.0, 0.0);
        assert!((arc_sweep(Plane::Xy, s, e, c, 1) - PI / 2.0).abs() < 1e-12);
        assert!((arc_sweep(Plane::Xy, s, e, c, -1) + 3.0 * PI / 2.0).abs() < 1e-12);
        assert!((arc_sweep(Plane::Xy, s, s, c, 1) - TAU).abs() < 1e-12);
        assert!((arc_sweep(Plane::Xy, s, s, c, -2) + 2.0 * TAU).abs() < 1e-12);
        assert!((arc_sweep(Plane::Xy, s, e, c, 3) - (PI / 2.0 + 2.0 * TAU)).abs() < 1e-12);
        // G18: first axis Z, second X.
        let s = Pos::new(0.0, 0.0, 1.0, 0.0);
        let e = Pos::new(1.0, 0.0, 0.0, 0.0);
        assert!((arc_sweep(Plane::Zx, s, e, c, 1) - PI / 2.0).abs() < 1e-12);
    }

    #[test]
    fn canon_accessors() {
        let c = Canon::Arc {
            line: 7,
            end: Pos::new(1.0, 2.0, 3.0, 4.0),
            plane: Plane::Yz,
            center: [0.0, 0.0],
            rotation: -1,
        };
        assert_eq!(c.line(), 7);
        assert_eq!(c.end_point(), Some(Pos::new(1.0, 2.0, 3.0, 4.0)));
        assert!(!Canon::Dwell { line: 1, seconds: 1.0 }.is_motion());
        assert_eq!(Plane::Zx.axes(), [2, 0, 1]);
        assert_eq!(Pos::new(1.0, 2.0, 3.0, 4.0).get(3), Some(4.0));
        assert_eq!(Pos::ZERO.max_abs_diff(Pos::new(0.0, -2.0, 1.0, 0.5)), 2.0);
    }
}
