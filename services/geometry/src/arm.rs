//! Kinematics of a 6-axis arm described by standard Denavit–Hartenberg parameters: forward
//! kinematics, the geometric Jacobian, the dexterity measure, singularity margins and inverse
//! kinematics (closed form for the Viper/Denso layout with a spherical wrist, damped least squares
//! otherwise), and the arm's motion times (a synchronised trapezoid per joint). The scanning service's
//! arm carries the scanner with it; the CAM's robot milling puts a spindle on the same flange.
//!
//! # Conventions
//!
//! - **Units.** Millimetres and degrees at the API (`q_deg`, `*_mm`, `*_deg_s`), radians inside.
//!   Jacobians are per radian of joint motion (mm/rad and rad/rad). Joints are numbered 1 to 6 in
//!   messages and in the controller's `axis` arguments; arrays are indexed 0 to 5.
//! - **DH convention: standard (distal) Denavit–Hartenberg**, as in ViSP's Viper model (not
//!   Craig's modified convention). Link `i` maps frame `i` to frame `i−1`:
//!   `A_i = Rz(θ_i) · Tz(d_i) · Tx(a_i) · Rx(α_i)`, `θ_i = q_i + offset_i`, and joint `i` turns
//!   about the Z axis of frame `i−1`.
//! - **Frames** (poses are named `b_from_a`, as in `depthmill_geometry::pose`):
//!   - world: the cell frame; `ArmModel::base` is `world_from_base`.
//!   - base (DH frame 0): on the mounting face, Z up along joint 1, X forward (towards the arm at
//!     `q1 = 0`).
//!   - DH frames 1…6; frame 6 is the tool flange (row 6 carries the flange offset `d6`), Z out of
//!     the flange.
//!   - tool: the scanner's optical frame (Z along the viewing direction, X along the laser line);
//!     `ArmModel::tool` is `flange_from_tool`, the scanner bracket.
//!   - `ArmModel::fk` returns `world_from_tool`; IK takes the same.
//!
//! # The Adept Viper s650
//!
//! | joint | a (mm) | α    | d (mm) | θ offset | range          | top speed |
//! |-------|--------|------|--------|----------|----------------|-----------|
//! | 1     | 75     | −90° | 335    | 0        | −170° … +170°  | 328 °/s   |
//! | 2     | 270    | 0    | 0      | 0        | −190° … +45°   | 300 °/s   |
//! | 3     | 90     | −90° | 0      | −180°    | −29° … +256°   | 375 °/s   |
//! | 4     | 0      | +90° | 295    | 0        | −190° … +190°  | 375 °/s   |
//! | 5     | 0      | −90° | 0      | 0        | −120° … +120°  | 375 °/s   |
//! | 6     | 0      | 0    | 80     | −180°    | −360° … +360°  | 600 °/s   |
//!
//! The wrist is spherical (`a4 = a5 = d5 = 0`: the axes of joints 4, 5, 6 meet at the wrist
//! centre, 80 mm behind the flange), so IK is closed-form. At `q = 0` the upper arm is horizontal,
//! the forearm vertical and the flange frame parallel to the base, 255 mm forward and 710 mm up;
//! Adept's READY pose `(0, −90, 180, 0, 0, 0)` puts the flange at (450, 0, 695) mm pointing
//! forward. The wrist centre reaches `75 + 270 + √(90² + 295²) = 653.4` mm from the joint 1
//! axis, matching the 653 mm reach Adept quotes for the s650.
//!
//! Sources (numbers only; no code copied):
//! - DH lengths, offsets and joint ranges: ViSP (Inria), `vpViper650.h` (the DH table with the
//!   `q3 − π` and `q6 − π` offsets) and `vpViper650.cpp` (`a1 = 0.075, a2 = 0.270, a3 = 0.090,
//!   d1 = 0.335, d4 = 0.295, d6 = 0.080` m — ViSP adds a 101.6 mm tool changer to `d6`, we do not
//!   — and the software limits listed above), <https://github.com/lagadic/visp>,
//!   `modules/robot/{include/visp3,src/real-robot/viper}/`. ViSP drives a real s650 with these
//!   joint values, so the offsets follow Adept's joint zeroes.
//! - Cross-check of lengths, ranges and the top joint speeds: A. Dumitrache's Viper s650 simulator
//!   `RobotSim.py` (CIMR, Politehnica University of Bucharest, 2010: link offsets 203 + 132 = 335,
//!   75, 270, 90, 108 + 187 = 295, 60 + 20 = 80 mm, the same ranges, `max_joint_speed = [328, 300,
//!   375, 375, 375, 600]` °/s), and the ROS-Industrial experimental URDF
//!   `adept_s650_support/urdf/s650.urdf` (velocity limits 5.72468, 5.235, 6.544, 6.544, 6.544,
//!   10.47 rad/s = the same speeds; the same ranges except joint 6 clipped to ±180°).
//! - **Not verified**: Adept's own Viper s650 user's guide was not available to check the table
//!   against; the two independent models above agree on every number used here. The URDF's joint
//!   2 height (391 mm) disagrees with both (335 mm) and was not used. **Joint accelerations are not
//!   published**: the model assumes each joint reaches its top speed in 0.25 s (4 × top speed per
//!   second). The scanner bracket ([`ArmModel::scanner_bracket`]) is a nominal design,
//!   to be replaced by the calibrated transform.
//!
//! # Singularities
//!
//! [`SingularityMargins`] measures the distance from the three singular families
//! named in DESIGN §6: wrist (axes 4 and 6 aligned, `q5 = 0`), shoulder/alignment (wrist centre
//! on the axis of joint 1 — axis 6 on axis 1 is a special case) and elbow (arm fully stretched,
//! `q3 = 180° − atan2(295, 90) = 106.97°`). The dexterity `sqrt(det(JᵀJ))` vanishes on all three.
//!
//! # Inverse kinematics
//!
//! For the Viper layout (a spherical wrist: the axes of joints 4, 5 and 6 meet in one point, the
//! *wrist centre*) the problem splits in two:
//!
//! 1. **Position.** The wrist centre is `p_w = p_flange − d6·z_flange`. Joint 1 points the arm plane
//!    at it (`θ1 = atan2(y, x)`, shoulder *front*) or away from it (`θ1 + 180°`, shoulder *back*).
//!    In the arm plane the upper arm (`a2`) and the forearm (the fixed vector `(a3, d4)`, length
//!    `L = √(a3² + d4²)`) form a triangle with the shoulder–wrist distance `r`, so
//!    `a3·cos θ3 − d4·sin θ3 = (r² − a2² − L²) / (2·a2)` gives `θ3 + β = ±acos(…)` with
//!    `β = atan2(d4, a3)` (elbow *up* / *down*), and `θ2` follows from the triangle's orientation.
//! 2. **Orientation.** With `R03` known, `R36 = R03ᵀ·R06 = Rz(θ4)·Ry(−θ5)·Rz(θ6)` is a Z-Y-Z Euler
//!    decomposition with two solutions (`θ5` and `−θ5`: wrist *no-flip* / *flip*).
//!
//! That gives up to 2 × 2 × 2 = 8 solutions. Each is brought into the joint limits where a turn of
//! 360° allows it (joints 4 and 6 span more than a turn), polished by a few damped-least-squares
//! steps, and verified by forward kinematics to [`IK_POSITION_TOLERANCE_MM`] and
//! [`IK_ANGLE_TOLERANCE_RAD`]. Any other DH layout is solved numerically only (damped least
//! squares from a fixed set of seeds plus the caller's seed), which may miss some branches.
//!
//! At a wrist singularity (`θ5 = 0`) only `θ4 + θ6` is defined: joint 4 keeps the seed's value (0
//! without a seed) and joint 6 takes the rest. With the wrist centre on the axis of joint 1 any
//! `θ1` works: the seed's joint 1 is kept.

use std::f64::consts::PI;
use std::fmt;

use nalgebra::{Isometry3, Matrix6, Translation3, UnitQuaternion, Vector3, Vector6};
use serde::{Deserialize, Serialize};
use thiserror::Error;

/// Forward-kinematics check every IK solution passes: tool position within this distance (mm).
pub const IK_POSITION_TOLERANCE_MM: f64 = 1e-6;
/// Forward-kinematics check every IK solution passes: tool orientation within this angle (rad).
pub const IK_ANGLE_TOLERANCE_RAD: f64 = 1e-9;

/// Tolerance (degrees) when comparing a joint value with its limits, so that IK solutions landing
/// exactly on a limit are not refused for rounding.
const LIMIT_SLACK_DEG: f64 = 1e-9;
/// Characteristic length (mm per radian) that weighs orientation against position errors in the
/// damped-least-squares solver.
const ROT_SCALE_MM: f64 = 100.0;

/// One row of a standard (distal) Denavit–Hartenberg table, in millimetres and degrees.
///
/// The link transform is `Rz(θ)·Tz(d)·Tx(a)·Rx(α)` with `θ = q + theta_offset`, where `q` is the
/// joint value the controller reports.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Dh {
    /// Link length `a` along the new X axis (mm).
    pub a_mm: f64,
    /// Link twist `α` about the new X axis (degrees).
    pub alpha_deg: f64,
    /// Link offset `d` along the previous Z axis (mm).
    pub d_mm: f64,
    /// Constant added to the joint value to get the DH angle `θ` (degrees).
    pub theta_offset_deg: f64,
}

impl Dh {
    /// The link transform `Rz(q + offset)·Tz(d)·Tx(a)·Rx(α)` for joint value `q_deg`.
    pub fn transform(&self, q_deg: f64) -> Isometry3<f64> {
        let theta = (q_deg + self.theta_offset_deg).to_radians();
        let (s, c) = theta.sin_cos();
        let rotation = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), theta)
            * UnitQuaternion::from_axis_angle(&Vector3::x_axis(), self.alpha_deg.to_radians());
        Isometry3::from_parts(Translation3::new(self.a_mm * c, self.a_mm * s, self.d_mm), rotation)
    }
}

/// Travel, speed and acceleration limits of one joint (degrees, °/s, °/s²).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct JointLimit {
    /// Lowest joint value (degrees).
    pub min_deg: f64,
    /// Highest joint value (degrees).
    pub max_deg: f64,
    /// Top joint speed (°/s).
    pub max_speed_deg_s: f64,
    /// Top joint acceleration and deceleration (°/s²).
    pub max_accel_deg_s2: f64,
}

impl JointLimit {
    /// Whether `q_deg` lies in `[min_deg, max_deg]` (with a 1e-9° slack for rounding).
    pub fn contains(&self, q_deg: f64) -> bool {
        q_deg >= self.min_deg - LIMIT_SLACK_DEG && q_deg <= self.max_deg + LIMIT_SLACK_DEG
    }

    /// How far `q_deg` lies outside the range (0 inside).
    fn excess(&self, q_deg: f64) -> f64 {
        (self.min_deg - q_deg).max(q_deg - self.max_deg).max(0.0)
    }

    /// `Ok` when `q_deg` is within the range; otherwise the violation, naming `joint` (1-based).
    pub fn check(&self, joint: usize, q_deg: f64) -> Result<(), JointLimitViolation> {
        if self.contains(q_deg) {
            Ok(())
        } else {
            Err(JointLimitViolation { joint, value_deg: q_deg, min_deg: self.min_deg, max_deg: self.max_deg })
        }
    }
}

/// A joint value outside its range, e.g. "joint 3 = 261.2° is outside [-29.0°, 256.0°]".
#[derive(Debug, Clone, Copy, PartialEq, Error)]
#[error("joint {joint} = {value_deg:.1}° is outside [{min_deg:.1}°, {max_deg:.1}°]")]
pub struct JointLimitViolation {
    /// Joint number, 1 to 6.
    pub joint: usize,
    /// The refused value (degrees).
    pub value_deg: f64,
    /// Lower limit (degrees).
    pub min_deg: f64,
    /// Upper limit (degrees).
    pub max_deg: f64,
}

/// Shoulder configuration: where the wrist centre lies relative to the axis of joint 1.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum Shoulder {
    /// The arm plane points at the wrist centre (the arm reaches forward).
    Front,
    /// The arm plane points away from the wrist centre (the arm reaches back over itself).
    Back,
}

/// Elbow configuration, by the sign of the elbow bend `θ3 + β` (`β = atan2(d4, a3)`).
///
/// For the Viper s650, `Up` is `q3 > 106.97°` (the stretched angle `180° − β`): with the shoulder
/// in front the elbow is then above the shoulder–wrist line, as at the READY pose. Reaching back
/// (`Shoulder::Back`) the same bend puts the elbow below that line.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum Elbow {
    /// `sin(θ3 + β) ≥ 0`.
    Up,
    /// `sin(θ3 + β) < 0`.
    Down,
}

/// Wrist configuration, by the sign of the DH angle of joint 5 (for the Viper s650: of `q5`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum Wrist {
    /// `sin θ5 ≥ 0`.
    NoFlip,
    /// `sin θ5 < 0` (joint 5 bent the other way, joints 4 and 6 turned by 180°).
    Flip,
}

/// One of the (up to) eight IK branches.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct Configuration {
    /// Shoulder front/back.
    pub shoulder: Shoulder,
    /// Elbow up/down.
    pub elbow: Elbow,
    /// Wrist no-flip/flip.
    pub wrist: Wrist,
}

impl fmt::Display for Configuration {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let s = match self.shoulder {
            Shoulder::Front => "shoulder front",
            Shoulder::Back => "shoulder back",
        };
        let e = match self.elbow {
            Elbow::Up => "elbow up",
            Elbow::Down => "elbow down",
        };
        let w = match self.wrist {
            Wrist::NoFlip => "no flip",
            Wrist::Flip => "flip",
        };
        write!(f, "{s}, {e}, {w}")
    }
}

/// Distances of a joint position from the three singularities of the arm (or, used as
/// thresholds, the smallest distances accepted).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SingularityMargins {
    /// Angle between the axes of joints 4 and 6, folded to `[0°, 90°]` (for the Viper: `|q5|`
    /// away from 0° or ±180°). 0 = wrist singularity.
    pub wrist_deg: f64,
    /// Distance of the wrist centre from the axis of joint 1 (mm). 0 = shoulder singularity.
    pub shoulder_mm: f64,
    /// Angle between the upper arm (joint 2 → joint 3) and the forearm (joint 3 → wrist centre),
    /// folded to `[0°, 90°]`. 0 = elbow fully stretched (or folded).
    pub elbow_deg: f64,
}

impl SingularityMargins {
    /// Thresholds that accept every solution.
    pub const NONE: SingularityMargins =
        SingularityMargins { wrist_deg: 0.0, shoulder_mm: 0.0, elbow_deg: 0.0 };
    /// Default thresholds: 1° at the wrist and the elbow, 5 mm at the shoulder.
    pub const DEFAULT: SingularityMargins =
        SingularityMargins { wrist_deg: 1.0, shoulder_mm: 5.0, elbow_deg: 1.0 };

    /// The first singularity (wrist, shoulder, elbow) whose margin is below `thresholds`.
    pub fn violation(&self, thresholds: &SingularityMargins) -> Option<Singularity> {
        if self.wrist_deg < thresholds.wrist_deg {
            Some(Singularity::Wrist { margin_deg: self.wrist_deg, threshold_deg: thresholds.wrist_deg })
        } else if self.shoulder_mm < thresholds.shoulder_mm {
            Some(Singularity::Shoulder {
                distance_mm: self.shoulder_mm,
                threshold_mm: thresholds.shoulder_mm,
            })
        } else if self.elbow_deg < thresholds.elbow_deg {
            Some(Singularity::Elbow { margin_deg: self.elbow_deg, threshold_deg: thresholds.elbow_deg })
        } else {
            None
        }
    }
}

/// A singularity a joint position is too close to, with its margin and the threshold.
#[derive(Debug, Clone, Copy, PartialEq, Error)]
pub enum Singularity {
    /// Joints 4 and 6 aligned (joint 5 near 0°): only `q4 + q6` is defined.
    #[error(
        "wrist singularity: the axes of joints 4 and 6 are {margin_deg:.3}° from aligned \
         (joint 5 near 0°), below the margin {threshold_deg:.3}°"
    )]
    Wrist {
        /// Angle between the axes of joints 4 and 6 (degrees, folded to `[0, 90]`).
        margin_deg: f64,
        /// Smallest accepted angle (degrees).
        threshold_deg: f64,
    },
    /// Wrist centre on the axis of joint 1 (this includes DESIGN's "alignment" case, axis 6 on
    /// axis 1): joint 1 is undetermined.
    #[error(
        "shoulder singularity: the wrist centre is {distance_mm:.3} mm from the axis of joint 1, \
         below the margin {threshold_mm:.3} mm"
    )]
    Shoulder {
        /// Distance of the wrist centre from the axis of joint 1 (mm).
        distance_mm: f64,
        /// Smallest accepted distance (mm).
        threshold_mm: f64,
    },
    /// Elbow fully stretched (edge of the reach) or folded.
    #[error(
        "elbow singularity: the arm is {margin_deg:.3}° from fully stretched, below the margin \
         {threshold_deg:.3}°"
    )]
    Elbow {
        /// Angle between upper arm and forearm (degrees, folded to `[0, 90]`).
        margin_deg: f64,
        /// Smallest accepted angle (degrees).
        threshold_deg: f64,
    },
}

/// Which IK solutions to accept.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct IkConfig {
    /// Only this shoulder configuration (`None`: any).
    pub shoulder: Option<Shoulder>,
    /// Only this elbow configuration (`None`: any).
    pub elbow: Option<Elbow>,
    /// Only this wrist configuration (`None`: any).
    pub wrist: Option<Wrist>,
    /// Solutions closer to a singularity than these margins are refused.
    pub singularity_thresholds: SingularityMargins,
}

impl Default for IkConfig {
    /// Any configuration, [`SingularityMargins::DEFAULT`] thresholds.
    fn default() -> Self {
        IkConfig {
            shoulder: None,
            elbow: None,
            wrist: None,
            singularity_thresholds: SingularityMargins::DEFAULT,
        }
    }
}

impl IkConfig {
    /// Any configuration and no singularity thresholds.
    pub fn any() -> Self {
        IkConfig { singularity_thresholds: SingularityMargins::NONE, ..IkConfig::default() }
    }

    /// Exactly the configuration `c`, default singularity thresholds.
    pub fn only(c: Configuration) -> Self {
        IkConfig {
            shoulder: Some(c.shoulder),
            elbow: Some(c.elbow),
            wrist: Some(c.wrist),
            singularity_thresholds: SingularityMargins::DEFAULT,
        }
    }

    fn accepts(&self, c: &Configuration) -> bool {
        self.shoulder.is_none_or(|s| s == c.shoulder)
            && self.elbow.is_none_or(|e| e == c.elbow)
            && self.wrist.is_none_or(|w| w == c.wrist)
    }

    fn describe(&self) -> String {
        let mut parts = Vec::new();
        if let Some(s) = self.shoulder {
            parts.push(format!("shoulder {s:?}").to_lowercase());
        }
        if let Some(e) = self.elbow {
            parts.push(format!("elbow {e:?}").to_lowercase());
        }
        if let Some(w) = self.wrist {
            parts.push(match w {
                Wrist::NoFlip => "no flip".to_string(),
                Wrist::Flip => "flip".to_string(),
            });
        }
        if parts.is_empty() { "any configuration".to_string() } else { parts.join(", ") }
    }
}

/// One verified IK solution.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct IkSolution {
    /// Joint values (degrees), within the joint limits.
    pub q_deg: [f64; 6],
    /// Its branch.
    pub configuration: Configuration,
    /// Its distances from the singularities.
    pub margins: SingularityMargins,
}

/// Why inverse kinematics found no acceptable solution.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum IkError {
    /// The target pose has a non-finite component.
    #[error("invalid target pose: {what} is not finite")]
    InvalidTarget {
        /// Which part ("translation" or "rotation").
        what: &'static str,
    },
    /// The wrist centre is farther from the shoulder than the arm reaches.
    #[error(
        "target wrist centre {distance_mm:.1} mm from the shoulder (joint 2 axis) is beyond the reach \
         {reach_mm:.1} mm"
    )]
    OutOfReach {
        /// Shoulder–wrist-centre distance required (mm).
        distance_mm: f64,
        /// Largest shoulder–wrist-centre distance (mm): upper arm + forearm.
        reach_mm: f64,
    },
    /// The wrist centre is closer to the shoulder than the folded arm allows.
    #[error(
        "target wrist centre {distance_mm:.1} mm from the shoulder (joint 2 axis) is inside the minimum \
         reach {min_mm:.1} mm"
    )]
    InsideMinimumReach {
        /// Shoulder–wrist-centre distance required (mm).
        distance_mm: f64,
        /// Smallest shoulder–wrist-centre distance (mm).
        min_mm: f64,
    },
    /// Solutions exist but none in the requested configuration.
    #[error("no solution in the requested configuration ({requested}); solutions exist for: {available}")]
    NoMatchingConfiguration {
        /// The requested configuration.
        requested: String,
        /// The configurations that do solve the pose.
        available: String,
    },
    /// Every solution violates a joint limit; one violation per branch.
    #[error("no solution within the joint limits: {}", describe_violations(.violations))]
    JointLimits {
        /// For each branch, its configuration and first violated limit.
        violations: Vec<(Configuration, JointLimitViolation)>,
    },
    /// Every solution within the limits is too close to a singularity (the closest is reported).
    #[error("every solution is too close to a singularity: {0}")]
    Singular(Singularity),
    /// The numerical solver did not converge (non-analytic arm layouts only).
    #[error(
        "the numerical IK did not converge: best residual {position_error_mm:.3e} mm, \
         {angle_error_deg:.3e}°"
    )]
    NotConverged {
        /// Best position residual (mm).
        position_error_mm: f64,
        /// Best orientation residual (degrees).
        angle_error_deg: f64,
    },
}

fn describe_violations(v: &[(Configuration, JointLimitViolation)]) -> String {
    v.iter().map(|(c, l)| format!("{c}: {l}")).collect::<Vec<_>>().join("; ")
}

/// A 6-axis arm: DH table, joint limits, the robot's base in the world and the tool on the flange.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ArmModel {
    /// Standard DH rows, joint 1 first; row 6 includes the flange offset `d6`, so frame 6 is the
    /// tool flange.
    pub dh: [Dh; 6],
    /// Joint travel, speed and acceleration limits, joint 1 first.
    pub limits: [JointLimit; 6],
    /// `flange_from_tool`: the scanner bracket, flange → scanner optical frame.
    pub tool: Isometry3<f64>,
    /// `world_from_base`: where the robot base (DH frame 0) stands in the cell.
    pub base: Isometry3<f64>,
}

/// Closed-form branches, and the shoulder branches that are out of reach with the reason.
type Branches = (Vec<Candidate>, Vec<(Shoulder, IkError)>);

/// Raw IK branch before limits and filtering.
struct Candidate {
    q_deg: [f64; 6],
    configuration: Configuration,
}

impl ArmModel {
    /// Adept's READY pose (degrees): upper arm vertical, forearm horizontal, wrist straight (a
    /// wrist singularity: joint 5 = 0).
    pub const READY_DEG: [f64; 6] = [0.0, -90.0, 180.0, 0.0, 0.0, 0.0];
    /// The home pose used by the simulated controller (degrees): READY with joint 5 at 90°, so the
    /// flange points straight down, away from every singularity.
    pub const HOME_DEG: [f64; 6] = [0.0, -90.0, 180.0, 0.0, 90.0, 0.0];

    /// The Adept Viper s650 (see the module root for the table and its sources) with the nominal
    /// [`ArmModel::scanner_bracket`] as tool and the base at the world origin.
    pub fn viper_s650() -> Self {
        let dh = |a_mm, alpha_deg, d_mm, theta_offset_deg| Dh { a_mm, alpha_deg, d_mm, theta_offset_deg };
        let lim = |min_deg, max_deg, max_speed_deg_s: f64| JointLimit {
            min_deg,
            max_deg,
            max_speed_deg_s,
            // Not published: assumed, each joint reaches top speed in 0.25 s.
            max_accel_deg_s2: 4.0 * max_speed_deg_s,
        };
        ArmModel {
            dh: [
                dh(75.0, -90.0, 335.0, 0.0),
                dh(270.0, 0.0, 0.0, 0.0),
                dh(90.0, -90.0, 0.0, -180.0),
                dh(0.0, 90.0, 295.0, 0.0),
                dh(0.0, -90.0, 0.0, 0.0),
                dh(0.0, 0.0, 80.0, -180.0),
            ],
            limits: [
                lim(-170.0, 170.0, 328.0),
                lim(-190.0, 45.0, 300.0),
                lim(-29.0, 256.0, 375.0),
                lim(-190.0, 190.0, 375.0),
                lim(-120.0, 120.0, 375.0),
                lim(-360.0, 360.0, 600.0),
            ],
            tool: Self::scanner_bracket(),
            base: Isometry3::identity(),
        }
    }

    /// The nominal scanner bracket, `flange_from_scanner` (replace by the calibrated transform).
    ///
    /// The scanner sits 95 mm out along the flange axis (+Z) and 60 mm off it (−Y); its optical
    /// frame has Z along the viewing direction and X along the laser line. The optical axis is
    /// tilted by `asin(60/155) ≈ 22.8°` about X so that it crosses the flange axis at 155 mm, the
    /// middle of the SLP-400's 65–245 mm standoff window.
    pub fn scanner_bracket() -> Isometry3<f64> {
        let tilt = (60.0f64 / 155.0).asin();
        Isometry3::from_parts(
            Translation3::new(0.0, -60.0, 95.0),
            UnitQuaternion::from_axis_angle(&Vector3::x_axis(), -tilt),
        )
    }

    /// The same arm with another tool (`flange_from_tool`).
    pub fn with_tool(mut self, tool: Isometry3<f64>) -> Self {
        self.tool = tool;
        self
    }

    /// The same arm standing at `world_from_base`.
    pub fn with_base(mut self, base: Isometry3<f64>) -> Self {
        self.base = base;
        self
    }

    /// `world_from_tool` at joint values `q_deg` (degrees): `base · A1(q1) ⋯ A6(q6) · tool`.
    pub fn fk(&self, q_deg: &[f64; 6]) -> Isometry3<f64> {
        self.flange(q_deg) * self.tool
    }

    /// `world_from_flange` at `q_deg` (the tool not applied).
    pub fn flange(&self, q_deg: &[f64; 6]) -> Isometry3<f64> {
        self.dh.iter().zip(q_deg).fold(self.base, |t, (dh, q)| t * dh.transform(*q))
    }

    /// Every frame in world coordinates: `[0]` the robot base (DH frame 0), `[i]` DH frame `i`
    /// (after joint `i`, so `[6]` is the flange), `[7]` the tool (scanner optical frame).
    pub fn fk_all(&self, q_deg: &[f64; 6]) -> [Isometry3<f64>; 8] {
        let mut frames = [self.base; 8];
        for i in 0..6 {
            frames[i + 1] = frames[i] * self.dh[i].transform(q_deg[i]);
        }
        frames[7] = frames[6] * self.tool;
        frames
    }

    /// The geometric Jacobian at the tool point, in world coordinates: column `i` is
    /// `[zᵢ₋₁ × (p_tool − oᵢ₋₁); zᵢ₋₁]`, so `[v; ω] = J·q̇` with `q̇` in rad/s, `v` in mm/s and `ω`
    /// in rad/s.
    pub fn jacobian(&self, q_deg: &[f64; 6]) -> Matrix6<f64> {
        let frames = self.fk_all(q_deg);
        let p = frames[7].translation.vector;
        let mut j = Matrix6::zeros();
        for (i, frame) in frames.iter().take(6).enumerate() {
            let z = frame.rotation * Vector3::z();
            let o = frame.translation.vector;
            let v = z.cross(&(p - o));
            j.fixed_view_mut::<3, 1>(0, i).copy_from(&v);
            j.fixed_view_mut::<3, 1>(3, i).copy_from(&z);
        }
        j
    }

    /// Dexterity `sqrt(det(JᵀJ))` of [`ArmModel::jacobian`] (mm³/rad³; equals `|det J|`): 0 at a
    /// singularity, larger is better conditioned.
    pub fn dexterity(&self, q_deg: &[f64; 6]) -> f64 {
        let j = self.jacobian(q_deg);
        (j.transpose() * j).determinant().max(0.0).sqrt()
    }

    /// Distances of `q_deg` from the wrist, shoulder and elbow singularities (see
    /// [`SingularityMargins`]). The wrist centre is the origin of DH frame 5.
    pub fn singularity_margins(&self, q_deg: &[f64; 6]) -> SingularityMargins {
        let f = self.fk_all(q_deg);
        let z = |i: usize| f[i].rotation * Vector3::z();
        let o = |i: usize| f[i].translation.vector;
        let folded = |a: &Vector3<f64>, b: &Vector3<f64>| {
            let angle = a.cross(b).norm().atan2(a.dot(b)).to_degrees();
            angle.min(180.0 - angle)
        };
        let wrist = o(5);
        let from_base = wrist - o(0);
        let axis1 = z(0);
        SingularityMargins {
            wrist_deg: folded(&z(3), &z(5)),
            shoulder_mm: (from_base - axis1 * from_base.dot(&axis1)).norm(),
            elbow_deg: folded(&(o(2) - o(1)), &(wrist - o(2))),
        }
    }

    /// The branch `q_deg` belongs to (see [`Shoulder`], [`Elbow`], [`Wrist`]).
    pub fn configuration(&self, q_deg: &[f64; 6]) -> Configuration {
        let theta = |i: usize| (q_deg[i] + self.dh[i].theta_offset_deg).to_radians();
        let f = self.fk_all(q_deg);
        let wrist = f[0].inverse() * f[5].translation.vector;
        let (s1, c1) = theta(0).sin_cos();
        let beta = self.dh[3].d_mm.atan2(self.dh[2].a_mm);
        Configuration {
            shoulder: if c1 * wrist.x + s1 * wrist.y >= 0.0 { Shoulder::Front } else { Shoulder::Back },
            elbow: if (theta(2) + beta).sin() >= 0.0 { Elbow::Up } else { Elbow::Down },
            wrist: if theta(4).sin() >= 0.0 { Wrist::NoFlip } else { Wrist::Flip },
        }
    }

    /// `Ok` if every joint of `q_deg` is within its limits, else the first violation.
    pub fn check_limits(&self, q_deg: &[f64; 6]) -> Result<(), JointLimitViolation> {
        self.limits.iter().zip(q_deg).enumerate().try_for_each(|(i, (l, q))| l.check(i + 1, *q))
    }

    /// Weighted joint distance used to pick the nearest solution: `sqrt(Σ ((aᵢ − bᵢ)/vᵢ)²)` with
    /// `vᵢ` the joint's top speed, i.e. roughly the seconds the move takes.
    pub fn joint_distance(&self, a: &[f64; 6], b: &[f64; 6]) -> f64 {
        (0..6)
            .map(|i| {
                let v = self.limits[i].max_speed_deg_s;
                let w = if v.is_finite() && v > 0.0 { 1.0 / v } else { 1.0 };
                ((a[i] - b[i]) * w).powi(2)
            })
            .sum::<f64>()
            .sqrt()
    }

    /// Whether the DH table has the layout the closed-form IK assumes (Viper/Denso: twists −90°,
    /// 0°, −90°, 90°, −90°, 0°; `d2 = d3 = d5 = 0`; `a4 = a5 = a6 = 0`; `a2 > 0`).
    pub fn has_analytic_ik(&self) -> bool {
        let near = |x: f64, y: f64| (x - y).abs() < 1e-9;
        let alphas = [-90.0, 0.0, -90.0, 90.0, -90.0, 0.0];
        self.dh.iter().zip(alphas).all(|(d, a)| near(d.alpha_deg, a))
            && near(self.dh[1].d_mm, 0.0)
            && near(self.dh[2].d_mm, 0.0)
            && near(self.dh[4].d_mm, 0.0)
            && near(self.dh[3].a_mm, 0.0)
            && near(self.dh[4].a_mm, 0.0)
            && near(self.dh[5].a_mm, 0.0)
            && self.dh[1].a_mm > 0.0
    }

    /// A Viper s650 pose (degrees) with the wrist centre on the axis of joint 1, a shoulder
    /// singularity: with `q3 = 180°` the arm plane offset is `u = 360·cos q2 − 295·sin q2 = −a1 =
    /// −75` mm.
    pub fn viper_wrist_on_joint1_axis_deg() -> [f64; 6] {
        let (r, psi) = (360.0f64.hypot(295.0), 295.0f64.atan2(360.0));
        let q2 = -(-75.0 / r).acos() - psi;
        [0.0, q2.to_degrees(), 180.0, 0.0, 60.0, 0.0]
    }

    /// Shortest time (s) of a synchronised rest-to-rest move `from → to` (degrees) with every
    /// joint's cruise speed at most `speed_frac` × its top speed: the longest single-joint
    /// trapezoid ([`min_move_time`]), which every other joint is re-timed to match.
    pub fn move_time_s(&self, from: &[f64; 6], to: &[f64; 6], speed_frac: f64) -> f64 {
        self.limits.iter().zip(from.iter().zip(to)).fold(0.0, |t, (l, (a, b))| {
            t.max(min_move_time((b - a).abs(), l.max_speed_deg_s * speed_frac, l.max_accel_deg_s2))
        })
    }

    /// Largest shoulder–wrist-centre distance (mm) of the Viper layout: `a2 + √(a3² + d4²)`.
    pub fn reach_mm(&self) -> f64 {
        self.dh[1].a_mm + self.dh[2].a_mm.hypot(self.dh[3].d_mm)
    }

    /// All IK solutions (degrees) for the tool pose `target` (`world_from_tool`) accepted by
    /// `config`: up to 8 for the Viper layout, each within the limits and verified by FK.
    pub fn ik(&self, target: &Isometry3<f64>, config: IkConfig) -> Result<Vec<[f64; 6]>, IkError> {
        Ok(self.ik_solutions(target, &config)?.into_iter().map(|s| s.q_deg).collect())
    }

    /// Like [`ArmModel::ik`], with each solution's configuration and singularity margins.
    pub fn ik_solutions(
        &self,
        target: &Isometry3<f64>,
        config: &IkConfig,
    ) -> Result<Vec<IkSolution>, IkError> {
        self.solve(target, config, None)
    }

    /// The accepted IK solution nearest to `q_seed` by [`ArmModel::joint_distance`]; joints that
    /// can turn more than 360° take the turn nearest the seed.
    pub fn ik_nearest(
        &self,
        target: &Isometry3<f64>,
        q_seed: &[f64; 6],
        config: &IkConfig,
    ) -> Result<IkSolution, IkError> {
        let solutions = self.solve(target, config, Some(q_seed))?;
        solutions
            .into_iter()
            .min_by(|a, b| {
                self.joint_distance(&a.q_deg, q_seed).total_cmp(&self.joint_distance(&b.q_deg, q_seed))
            })
            .ok_or(IkError::NotConverged { position_error_mm: f64::NAN, angle_error_deg: f64::NAN })
    }

    fn solve(
        &self,
        target: &Isometry3<f64>,
        config: &IkConfig,
        seed: Option<&[f64; 6]>,
    ) -> Result<Vec<IkSolution>, IkError> {
        if !target.translation.vector.iter().all(|v| v.is_finite()) {
            return Err(IkError::InvalidTarget { what: "translation" });
        }
        if !target.rotation.coords.iter().all(|v| v.is_finite()) {
            return Err(IkError::InvalidTarget { what: "rotation" });
        }
        let prefer = seed.copied().unwrap_or([0.0; 6]);
        let (candidates, unreachable) = if self.has_analytic_ik() {
            let flange = self.base.inverse() * target * self.tool.inverse();
            self.analytic_candidates(&flange, &prefer)?
        } else {
            (self.numeric_candidates(target, seed)?, Vec::new())
        };

        // Fold into the limits, polish, verify, deduplicate.
        let mut verified: Vec<Candidate> = Vec::new();
        let mut worst = (0.0f64, 0.0f64);
        for c in candidates {
            let mut q = c.q_deg;
            for (i, v) in q.iter_mut().enumerate() {
                *v = fold_into(*v, &self.limits[i], prefer[i]);
            }
            let (q, pos_err, ang_err) = self.dls(target, q, 4);
            if pos_err > IK_POSITION_TOLERANCE_MM || ang_err > IK_ANGLE_TOLERANCE_RAD {
                worst = (worst.0.max(pos_err), worst.1.max(ang_err));
                continue;
            }
            if verified.iter().any(|v| same_joints(&v.q_deg, &q)) {
                continue;
            }
            verified.push(Candidate { q_deg: q, configuration: c.configuration });
        }
        if verified.is_empty() {
            return Err(IkError::NotConverged {
                position_error_mm: worst.0,
                angle_error_deg: worst.1.to_degrees(),
            });
        }

        let available: Vec<Configuration> = verified.iter().map(|c| c.configuration).collect();
        let wanted: Vec<Candidate> =
            verified.into_iter().filter(|c| config.accepts(&c.configuration)).collect();
        if wanted.is_empty() {
            // The requested shoulder branch is out of reach: say so rather than list the others.
            if let Some((_, e)) = unreachable.into_iter().find(|(s, _)| config.shoulder == Some(*s)) {
                return Err(e);
            }
            let mut names: Vec<String> = available.iter().map(|c| format!("[{c}]")).collect();
            names.dedup();
            return Err(IkError::NoMatchingConfiguration {
                requested: config.describe(),
                available: names.join(", "),
            });
        }

        let mut violations = Vec::new();
        let mut in_limits = Vec::new();
        for c in wanted {
            match self.check_limits(&c.q_deg) {
                Ok(()) => in_limits.push(c),
                Err(v) => violations.push((c.configuration, v)),
            }
        }
        if in_limits.is_empty() {
            return Err(IkError::JointLimits { violations });
        }

        let mut closest: Option<Singularity> = None;
        let mut out = Vec::new();
        for c in in_limits {
            let margins = self.singularity_margins(&c.q_deg);
            match margins.violation(&config.singularity_thresholds) {
                None => out.push(IkSolution { q_deg: c.q_deg, configuration: c.configuration, margins }),
                Some(s) => {
                    if closest.is_none_or(|old| relative_margin(&s) < relative_margin(&old)) {
                        closest = Some(s);
                    }
                }
            }
        }
        match (out.is_empty(), closest) {
            (true, Some(s)) => Err(IkError::Singular(s)),
            _ => Ok(out),
        }
    }

    /// Closed-form branches for the Viper layout; `flange` is `base_from_flange`; `hint` supplies
    /// joints 1 and 4 where they are undetermined (shoulder and wrist singularities).
    /// Also returns, per shoulder branch out of reach, why.
    fn analytic_candidates(&self, flange: &Isometry3<f64>, hint: &[f64; 6]) -> Result<Branches, IkError> {
        let dh = &self.dh;
        let off = |i: usize| dh[i].theta_offset_deg.to_radians();
        let (a1, d1) = (dh[0].a_mm, dh[0].d_mm);
        let (a2, a3, d4, d6) = (dh[1].a_mm, dh[2].a_mm, dh[3].d_mm, dh[5].d_mm);
        let l = a3.hypot(d4);
        let beta = d4.atan2(a3);
        let z6 = flange.rotation * Vector3::z();
        let pw = flange.translation.vector - z6 * d6;
        let rho = pw.x.hypot(pw.y);
        let azimuth = if rho > 1e-9 { pw.y.atan2(pw.x) } else { hint[0].to_radians() + off(0) };

        let mut out = Vec::new();
        let mut unreachable = Vec::new();
        for shoulder in [Shoulder::Front, Shoulder::Back] {
            let th1 = match shoulder {
                Shoulder::Front => azimuth,
                Shoulder::Back => azimuth + PI,
            };
            let (s1, c1) = th1.sin_cos();
            let u = c1 * pw.x + s1 * pw.y - a1;
            let v = d1 - pw.z;
            let r2 = u * u + v * v;
            let ratio = (r2 - a2 * a2 - l * l) / (2.0 * a2 * l);
            if ratio > 1.0 + 1e-12 {
                unreachable
                    .push((shoulder, IkError::OutOfReach { distance_mm: r2.sqrt(), reach_mm: a2 + l }));
                continue;
            }
            if ratio < -1.0 - 1e-12 {
                let e = IkError::InsideMinimumReach { distance_mm: r2.sqrt(), min_mm: (a2 - l).abs() };
                unreachable.push((shoulder, e));
                continue;
            }
            let gamma = ratio.clamp(-1.0, 1.0).acos();
            for elbow in [Elbow::Up, Elbow::Down] {
                let th3 = match elbow {
                    Elbow::Up => gamma - beta,
                    Elbow::Down => -gamma - beta,
                };
                let (s3, c3) = th3.sin_cos();
                let wx = a2 + a3 * c3 - d4 * s3;
                let wy = a3 * s3 + d4 * c3;
                let th2 = v.atan2(u) - wy.atan2(wx);
                let q1 = (th1 - off(0)).to_degrees();
                let q2 = (th2 - off(1)).to_degrees();
                let q3 = (th3 - off(2)).to_degrees();
                let r03 = dh[0].transform(q1).rotation
                    * dh[1].transform(q2).rotation
                    * dh[2].transform(q3).rotation;
                let m = (r03.inverse() * flange.rotation).to_rotation_matrix().into_inner();
                let s = m[(0, 2)].hypot(m[(1, 2)]);
                let th5_abs = s.atan2(m[(2, 2)]);
                for wrist in [Wrist::NoFlip, Wrist::Flip] {
                    let th5 = match wrist {
                        Wrist::NoFlip => th5_abs,
                        Wrist::Flip => -th5_abs,
                    };
                    let (th4, th6) = if s > 1e-9 {
                        let s5 = th5.sin();
                        ((-s5 * m[(1, 2)]).atan2(-s5 * m[(0, 2)]), (-s5 * m[(2, 1)]).atan2(s5 * m[(2, 0)]))
                    } else {
                        // Joints 4 and 6 aligned: keep the hint's joint 4, joint 6 takes the rest.
                        let th4 = hint[3].to_radians() + off(3);
                        if m[(2, 2)] > 0.0 {
                            (th4, m[(1, 0)].atan2(m[(0, 0)]) - th4)
                        } else {
                            (th4, th4 - (-m[(1, 0)]).atan2(-m[(0, 0)]))
                        }
                    };
                    let q = [
                        q1,
                        q2,
                        q3,
                        (th4 - off(3)).to_degrees(),
                        (th5 - off(4)).to_degrees(),
                        (th6 - off(5)).to_degrees(),
                    ];
                    out.push(Candidate { q_deg: q, configuration: Configuration { shoulder, elbow, wrist } });
                }
            }
        }
        match unreachable.first() {
            Some((_, e)) if out.is_empty() => Err(e.clone()),
            _ => Ok((out, unreachable)),
        }
    }

    /// Numerical branches for arms without the closed form: damped least squares from the seed (if
    /// any) and from 16 fixed seeds spread over the shoulder/elbow/wrist branches.
    fn numeric_candidates(
        &self,
        target: &Isometry3<f64>,
        seed: Option<&[f64; 6]>,
    ) -> Result<Vec<Candidate>, IkError> {
        let local = (self.base.inverse() * target).translation.vector;
        let azimuth = local.y.atan2(local.x).to_degrees() - self.dh[0].theta_offset_deg;
        let mut seeds: Vec<[f64; 6]> = seed.into_iter().copied().collect();
        for q1 in [azimuth, azimuth + 180.0] {
            for q2 in [-60.0, -120.0] {
                for q3 in [60.0, 180.0] {
                    for q5 in [60.0, -60.0] {
                        seeds.push([q1, q2, q3, 0.0, q5, 0.0]);
                    }
                }
            }
        }
        let mut out = Vec::new();
        let mut best = (f64::INFINITY, f64::INFINITY);
        for s in seeds {
            let (q, pos_err, ang_err) = self.dls(target, s, 200);
            if pos_err <= IK_POSITION_TOLERANCE_MM && ang_err <= IK_ANGLE_TOLERANCE_RAD {
                out.push(Candidate { q_deg: q, configuration: self.configuration(&q) });
            } else if pos_err + ang_err * ROT_SCALE_MM < best.0 + best.1 * ROT_SCALE_MM {
                best = (pos_err, ang_err);
            }
        }
        if out.is_empty() {
            return Err(IkError::NotConverged {
                position_error_mm: best.0,
                angle_error_deg: best.1.to_degrees(),
            });
        }
        Ok(out)
    }

    /// Damped least squares (Levenberg–Marquardt on the scaled residual) from `q_deg`; returns the
    /// best joints found with their position (mm) and angle (rad) residuals.
    fn dls(&self, target: &Isometry3<f64>, q_deg: [f64; 6], max_iter: usize) -> ([f64; 6], f64, f64) {
        let residual = |q: &[f64; 6]| -> Vector6<f64> {
            let pose = self.fk(q);
            let dp = target.translation.vector - pose.translation.vector;
            let dr = rotation_vector(&(target.rotation * pose.rotation.inverse())) * ROT_SCALE_MM;
            Vector6::new(dp.x, dp.y, dp.z, dr.x, dr.y, dr.z)
        };
        let split =
            |e: &Vector6<f64>| (e.fixed_rows::<3>(0).norm(), e.fixed_rows::<3>(3).norm() / ROT_SCALE_MM);
        let mut q = q_deg;
        let mut e = residual(&q);
        let mut lambda = 1e-3;
        for _ in 0..max_iter {
            let (pe, ae) = split(&e);
            if pe < 1e-10 && ae < 1e-13 {
                break;
            }
            let mut j = self.jacobian(&q);
            for r in 3..6 {
                for c in 0..6 {
                    j[(r, c)] *= ROT_SCALE_MM;
                }
            }
            let jjt = j * j.transpose();
            let mut improved = false;
            while lambda < 1e9 {
                let a = jjt + Matrix6::identity() * (lambda * lambda);
                let Some(chol) = a.cholesky() else {
                    lambda *= 10.0;
                    continue;
                };
                let dq = j.transpose() * chol.solve(&e);
                let mut q_new = q;
                for (qi, d) in q_new.iter_mut().zip(dq.iter()) {
                    *qi += d.to_degrees();
                }
                let e_new = residual(&q_new);
                if e_new.norm() < e.norm() {
                    q = q_new;
                    e = e_new;
                    lambda = (lambda * 0.1).max(1e-12);
                    improved = true;
                    break;
                }
                lambda *= 10.0;
            }
            if !improved {
                break;
            }
        }
        let (pe, ae) = split(&e);
        (q, pe, ae)
    }
}

/// Margin of a singularity relative to its threshold (smaller = closer).
fn relative_margin(s: &Singularity) -> f64 {
    let (m, t) = match *s {
        Singularity::Wrist { margin_deg, threshold_deg } => (margin_deg, threshold_deg),
        Singularity::Shoulder { distance_mm, threshold_mm } => (distance_mm, threshold_mm),
        Singularity::Elbow { margin_deg, threshold_deg } => (margin_deg, threshold_deg),
    };
    if t > 0.0 { m / t } else { f64::INFINITY }
}

/// The representative `q + k·360°` inside the limits nearest to `prefer`; when none is inside, the
/// one least outside (so the violation reported is the meaningful one).
fn fold_into(q: f64, limit: &JointLimit, prefer: f64) -> f64 {
    let base = q - 360.0 * ((q - prefer) / 360.0).round();
    (-2..=2)
        .map(|k| base + 360.0 * f64::from(k))
        .min_by(|a, b| {
            limit
                .excess(*a)
                .total_cmp(&limit.excess(*b))
                .then((a - prefer).abs().total_cmp(&(b - prefer).abs()))
        })
        .unwrap_or(q)
}

fn same_joints(a: &[f64; 6], b: &[f64; 6]) -> bool {
    a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-6)
}

/// Shortest time (s) to move one joint `d` degrees from rest to rest with top speed `v` (°/s) and
/// acceleration `a` (°/s²): a trapezoid, or a triangle when `d < v²/a`.
pub fn min_move_time(d: f64, v: f64, a: f64) -> f64 {
    if d <= 0.0 {
        0.0
    } else if d >= v * v / a {
        d / v + v / a
    } else {
        2.0 * (d / a).sqrt()
    }
}

/// Rotation vector (axis × angle, radians, angle in `[0, π]`) of `q`, accurate for tiny angles.
pub fn rotation_vector(q: &UnitQuaternion<f64>) -> Vector3<f64> {
    let (w, v) = if q.w < 0.0 { (-q.w, -q.imag()) } else { (q.w, q.imag()) };
    let n = v.norm();
    if n == 0.0 { Vector3::zeros() } else { v * (2.0 * n.atan2(w) / n) }
}

/// Position (mm) and angle (rad) between two poses; the angle is accurate for tiny differences.
pub fn pose_distance(a: &Isometry3<f64>, b: &Isometry3<f64>) -> (f64, f64) {
    let dp = (a.translation.vector - b.translation.vector).norm();
    let da = rotation_vector(&(a.rotation * b.rotation.inverse())).norm();
    (dp, da)
}

#[cfg(test)]
pub(crate) mod tests {
    use nalgebra::Rotation3;
    use proptest::prelude::*;
    use rand::rngs::StdRng;
    use rand::{Rng, SeedableRng};

    use super::*;

    fn bare() -> ArmModel {
        ArmModel::viper_s650().with_tool(Isometry3::identity())
    }

    fn random_q(rng: &mut StdRng, model: &ArmModel) -> [f64; 6] {
        std::array::from_fn(|i| rng.random_range(model.limits[i].min_deg..=model.limits[i].max_deg))
    }

    /// The slow, obviously right FK: 4×4 homogeneous matrices written out from the DH formula.
    fn fk_matrix_reference(model: &ArmModel, q: &[f64; 6]) -> nalgebra::Matrix4<f64> {
        let mut t = model.base.to_homogeneous();
        for (dh, qi) in model.dh.iter().zip(q) {
            let th = (qi + dh.theta_offset_deg).to_radians();
            let al = dh.alpha_deg.to_radians();
            let (st, ct) = th.sin_cos();
            let (sa, ca) = al.sin_cos();
            #[rustfmt::skip]
            let a = nalgebra::Matrix4::new(
                ct, -st * ca,  st * sa, dh.a_mm * ct,
                st,  ct * ca, -ct * sa, dh.a_mm * st,
                0.0,      sa,       ca, dh.d_mm,
                0.0,     0.0,      0.0, 1.0,
            );
            t *= a;
        }
        t * model.tool.to_homogeneous()
    }

    #[test]
    fn fk_matches_hand_computation_at_zero_and_ready() {
        let m = bare();
        // q = 0: upper arm horizontal forward (x = 75 + 270), the a3 offset back (−90), forearm
        // straight up (295) and the flange offset up (80); flange axes aligned with the base.
        let p = m.fk(&[0.0; 6]);
        assert!((p.translation.vector - Vector3::new(255.0, 0.0, 335.0 + 295.0 + 80.0)).norm() < 1e-9, "{p}");
        assert!(p.rotation.angle() < 1e-12);
        // READY: upper arm up (335 + 270), the a3 offset up (90), forearm + flange forward along +X.
        let p = m.fk(&ArmModel::READY_DEG);
        assert!(
            (p.translation.vector - Vector3::new(75.0 + 295.0 + 80.0, 0.0, 335.0 + 270.0 + 90.0)).norm()
                < 1e-9
        );
        assert!((p.rotation * Vector3::z() - Vector3::x()).norm() < 1e-12, "flange axis forward");
        // HOME: the flange points straight down from the wrist centre (370, 0, 695).
        let p = m.fk(&ArmModel::HOME_DEG);
        assert!((p.translation.vector - Vector3::new(370.0, 0.0, 695.0 - 80.0)).norm() < 1e-9);
        assert!((p.rotation * Vector3::z() + Vector3::z()).norm() < 1e-12);
        // Joint 1 turns everything about the vertical axis.
        let p = m.fk(&[90.0, -90.0, 180.0, 0.0, 0.0, 0.0]);
        assert!((p.translation.vector - Vector3::new(0.0, 450.0, 695.0)).norm() < 1e-9);
        // The scanner bracket: the optical axis crosses the flange axis 155 mm out.
        let scanner = ArmModel::scanner_bracket();
        let on_axis = scanner * nalgebra::Point3::new(0.0, 0.0, 155.0);
        assert!(on_axis.x.abs() < 1e-9 && on_axis.y.abs() < 1e-9, "{on_axis}");
        // Reach of the wrist centre from joint 1's axis: 75 + 270 + √(90² + 295²) ≈ 653 mm (datasheet).
        assert!((m.reach_mm() + 75.0 - 653.4).abs() < 0.1);
    }

    #[test]
    fn fk_all_and_fk_agree_with_matrix_reference() {
        let mut rng = StdRng::seed_from_u64(7);
        let m = ArmModel::viper_s650()
            .with_base(Isometry3::new(Vector3::new(10.0, -20.0, 5.0), Vector3::new(0.1, 0.2, 0.3)));
        for _ in 0..200 {
            let q = random_q(&mut rng, &m);
            let fast = m.fk(&q).to_homogeneous();
            let slow = fk_matrix_reference(&m, &q);
            assert!((fast - slow).abs().max() < 1e-9, "{q:?}");
            let frames = m.fk_all(&q);
            assert!((frames[7].to_homogeneous() - slow).abs().max() < 1e-9);
            assert!(
                (frames[6] * m.tool).translation.vector.metric_distance(&frames[7].translation.vector)
                    < 1e-12
            );
        }
    }

    fn assert_solution_ok(m: &ArmModel, target: &Isometry3<f64>, q: &[f64; 6]) {
        let (dp, da) = pose_distance(&m.fk(q), target);
        assert!(
            dp <= IK_POSITION_TOLERANCE_MM && da <= IK_ANGLE_TOLERANCE_RAD,
            "{q:?}: {dp:e} mm {da:e} rad"
        );
        assert!(m.check_limits(q).is_ok(), "{q:?}");
    }

    fn equal_mod_turns(a: &[f64; 6], b: &[f64; 6]) -> bool {
        (0..6).all(|i| {
            let d = a[i] - b[i];
            if i == 3 || i == 5 { (d - 360.0 * (d / 360.0).round()).abs() < 1e-6 } else { d.abs() < 1e-6 }
        })
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(300))]
        #[test]
        fn ik_round_trip(
            u in proptest::array::uniform6(0.0f64..1.0),
            tool_offset in -100.0f64..100.0,
        ) {
            let m = ArmModel::viper_s650().with_tool(
                Isometry3::new(Vector3::new(tool_offset, 20.0, 120.0), Vector3::new(0.3, -0.2, 0.1)),
            );
            let q: [f64; 6] = std::array::from_fn(|i| {
                let l = &m.limits[i];
                l.min_deg + u[i] * (l.max_deg - l.min_deg)
            });
            let margins = m.singularity_margins(&q);
            prop_assume!(margins.wrist_deg > 0.5 && margins.elbow_deg > 0.5 && margins.shoulder_mm > 1.0);
            let target = m.fk(&q);
            let sols = m.ik(&target, IkConfig::any()).expect("reachable");
            prop_assert!(!sols.is_empty() && sols.len() <= 8);
            for s in &sols {
                assert_solution_ok(&m, &target, s);
            }
            prop_assert!(sols.iter().any(|s| equal_mod_turns(s, &q)), "{q:?} not in {sols:?}");
            // The branch labels agree with the classification of the original.
            let c = m.configuration(&q);
            let labelled = m.ik_solutions(&target, &IkConfig { singularity_thresholds: SingularityMargins::NONE, ..IkConfig::only(c) })
                .expect("own branch");
            prop_assert!(labelled.iter().any(|s| equal_mod_turns(&s.q_deg, &q)));
            // The nearest solution to the original is the original itself (same turn on joints 4/6).
            let near = m.ik_nearest(&target, &q, &IkConfig::any()).expect("nearest");
            prop_assert!(near.q_deg.iter().zip(&q).all(|(a, b)| (a - b).abs() < 1e-6), "{:?} vs {q:?}", near.q_deg);
        }
    }

    #[test]
    fn eight_solutions_in_a_generic_pose() {
        let m = ArmModel::viper_s650();
        let q = [120.0, -90.0, 60.0, 30.0, 45.0, 20.0];
        let target = m.fk(&q);
        let sols = m.ik_solutions(&target, &IkConfig::default()).expect("solutions");
        assert_eq!(sols.len(), 8, "{sols:#?}");
        // Reaching back over the arm is out of reach for this one: asking for it says so.
        let front_only = m.fk(&[90.0, -70.0, 150.0, 30.0, 45.0, 20.0]);
        let back = IkConfig { shoulder: Some(Shoulder::Back), ..IkConfig::default() };
        assert!(matches!(m.ik(&front_only, back), Err(IkError::OutOfReach { .. })));
        assert_eq!(m.ik(&front_only, IkConfig::default()).expect("front").len(), 4);
        let mut configs: Vec<Configuration> = sols.iter().map(|s| s.configuration).collect();
        configs.dedup();
        assert_eq!(configs.len(), 8);
        for s in &sols {
            assert_solution_ok(&m, &target, &s.q_deg);
            assert_eq!(m.configuration(&s.q_deg), s.configuration, "{s:?}");
        }
    }

    #[test]
    fn unreachable_and_limit_errors_name_the_reason() {
        let m = bare();
        // 1 m in front of the robot at shoulder height: beyond the reach.
        let far = Isometry3::new(Vector3::new(1000.0, 0.0, 335.0), Vector3::zeros());
        let e = m.ik(&far, IkConfig::any()).expect_err("too far");
        assert!(matches!(e, IkError::OutOfReach { .. }), "{e:?}");
        let text = e.to_string();
        assert!(text.contains("beyond the reach 578.4 mm"), "{text}");
        // Wrist centre (1000, 0, 255): 925 mm forward of and 80 mm below the shoulder (75, 0, 335).
        assert!(text.starts_with("target wrist centre 928.5 mm from the shoulder"), "{text}");

        // Joint 1 narrowed to ±10°: a target at 90° azimuth is outside in both shoulder branches.
        let mut narrow = bare();
        narrow.limits[0].min_deg = -10.0;
        narrow.limits[0].max_deg = 10.0;
        let target = bare().fk(&[120.0, -90.0, 60.0, 30.0, 45.0, 20.0]);
        let e = narrow.ik(&target, IkConfig::any()).expect_err("limits");
        let IkError::JointLimits { violations } = &e else { panic!("{e:?}") };
        assert_eq!(violations.len(), 8);
        assert!(e.to_string().contains("joint 1 = 120.0° is outside [-10.0°, 10.0°]"), "{e}");
        assert!(e.to_string().contains("joint 1 = -60.0° is outside [-10.0°, 10.0°]"), "{e}");

        // Joint 3 beyond its upper limit, in the only configuration asked for.
        let q = [0.0, -20.0, 261.2, 10.0, 40.0, 0.0];
        let c = bare().configuration(&q);
        let e = m.ik(&m.fk(&q), IkConfig::only(c)).expect_err("q3 out");
        assert!(e.to_string().contains("joint 3 = 261.2° is outside [-29.0°, 256.0°]"), "{e}");

        // Non-finite targets.
        let bad = Isometry3::new(Vector3::new(f64::NAN, 0.0, 0.0), Vector3::zeros());
        assert_eq!(m.ik(&bad, IkConfig::any()), Err(IkError::InvalidTarget { what: "translation" }));
    }

    #[test]
    fn singular_targets_are_reported_with_their_margin() {
        let m = ArmModel::viper_s650();
        // Joint 5 at 0.3°: the solution of that branch is within 1° of the wrist singularity.
        let q = [0.0, -60.0, 160.0, 20.0, 0.3, 0.0];
        let c = m.configuration(&q);
        let e = m.ik(&m.fk(&q), IkConfig::only(c)).expect_err("singular");
        let IkError::Singular(Singularity::Wrist { margin_deg, threshold_deg }) = e else { panic!("{e:?}") };
        assert!((margin_deg - 0.3).abs() < 1e-6 && threshold_deg == 1.0);
        assert!(e.to_string().contains("0.300° from aligned"), "{e}");
        // Other branches of the same pose are not singular.
        assert!(!m.ik(&m.fk(&q), IkConfig::default()).expect("other branches").is_empty());
        // Wrist centre on the axis of joint 1: every branch shares it.
        let above = m.fk(&ArmModel::viper_wrist_on_joint1_axis_deg());
        assert!(m.singularity_margins(&ArmModel::viper_wrist_on_joint1_axis_deg()).shoulder_mm < 1e-9);
        let e = m.ik(&above, IkConfig::default()).expect_err("shoulder singular");
        assert!(
            matches!(e, IkError::Singular(Singularity::Shoulder { distance_mm, .. }) if distance_mm < 1e-9),
            "{e:?}"
        );
        // Accepted without thresholds; joint 1 then keeps the seed's value.
        let s =
            m.ik_nearest(&above, &[33.0, -90.0, 180.0, 0.0, 90.0, 0.0], &IkConfig::any()).expect("solves");
        assert!((s.q_deg[0] - 33.0).abs() < 1e-9, "{s:?}");
        assert_solution_ok(&m, &above, &s.q_deg);
        // Without thresholds it solves, and exactly at q5 = 0 joint 4 keeps the seed's value.
        let q0 = [0.0, -60.0, 160.0, 20.0, 0.0, 10.0];
        let near = m.ik_nearest(&m.fk(&q0), &q0, &IkConfig::any()).expect("solves");
        assert!(near.q_deg.iter().zip(&q0).all(|(a, b)| (a - b).abs() < 1e-6), "{near:?}");
        assert!(near.margins.wrist_deg < 1e-6);
    }

    /// Central differences of FK: the slow, obviously right Jacobian.
    fn jacobian_reference(m: &ArmModel, q: &[f64; 6]) -> Matrix6<f64> {
        let h_deg = 1e-5;
        let mut j = Matrix6::zeros();
        for i in 0..6 {
            let mut qp = *q;
            let mut qm = *q;
            qp[i] += h_deg;
            qm[i] -= h_deg;
            let (tp, tm) = (m.fk(&qp), m.fk(&qm));
            let h = 2.0 * h_deg.to_radians();
            let v = (tp.translation.vector - tm.translation.vector) / h;
            let w = rotation_vector(&(tp.rotation * tm.rotation.inverse())) / h;
            j.fixed_view_mut::<3, 1>(0, i).copy_from(&v);
            j.fixed_view_mut::<3, 1>(3, i).copy_from(&w);
        }
        j
    }

    #[test]
    fn jacobian_matches_finite_differences() {
        let mut rng = StdRng::seed_from_u64(11);
        let m = ArmModel::viper_s650()
            .with_base(Isometry3::new(Vector3::new(0.0, 500.0, 0.0), Vector3::new(0.0, 0.0, 0.7)));
        for _ in 0..100 {
            let q = random_q(&mut rng, &m);
            let fast = m.jacobian(&q);
            let slow = jacobian_reference(&m, &q);
            let err = (fast - slow).abs().max();
            assert!(err < 1e-5 * fast.abs().max().max(1.0), "{q:?}: {err}");
        }
    }

    #[test]
    fn dexterity_vanishes_at_singularities() {
        let m = ArmModel::viper_s650();
        let generic = m.dexterity(&[10.0, -70.0, 150.0, 30.0, 45.0, 20.0]);
        assert!(generic > 1e4, "{generic}");
        // Wrist: q5 = 0.
        let wrist = m.dexterity(&[10.0, -70.0, 150.0, 30.0, 0.0, 20.0]);
        assert!(wrist < 1e-6 * generic, "{wrist} vs {generic}");
        // Elbow fully stretched: q3 = 180° − atan2(d4, a3).
        let stretched = 180.0 - 295.0f64.atan2(90.0).to_degrees();
        let q = [10.0, -70.0, stretched, 30.0, 45.0, 20.0];
        assert!(m.singularity_margins(&q).elbow_deg < 1e-9);
        let elbow = m.dexterity(&q);
        assert!(elbow < 1e-6 * generic, "{elbow} vs {generic}");
        // dex = |det J| for a square Jacobian.
        let q = [10.0, -70.0, 150.0, 30.0, 45.0, 20.0];
        assert!((m.jacobian(&q).determinant().abs() - generic).abs() < 1e-6 * generic);
    }

    #[test]
    fn margins_match_joint_space_definitions() {
        let m = ArmModel::viper_s650();
        let mut rng = StdRng::seed_from_u64(5);
        let beta = 295.0f64.atan2(90.0);
        for _ in 0..200 {
            let q = random_q(&mut rng, &m);
            let g = m.singularity_margins(&q);
            let q5 = q[4].abs();
            assert!((g.wrist_deg - q5.min(180.0 - q5)).abs() < 1e-6, "{q:?} {g:?}");
            let bend = ((q[2].to_radians() - PI + beta).sin().abs()).asin().to_degrees();
            assert!((g.elbow_deg - bend).abs() < 1e-6, "{q:?} {g:?}");
            let w = m.fk_all(&q)[4].translation.vector;
            assert!((g.shoulder_mm - w.x.hypot(w.y)).abs() < 1e-9);
        }
    }

    #[test]
    fn numeric_ik_for_a_non_spherical_wrist() {
        let mut m = ArmModel::viper_s650();
        m.dh[4].a_mm = 15.0; // wrist axes no longer meet: no closed form
        assert!(!m.has_analytic_ik());
        let mut rng = StdRng::seed_from_u64(3);
        for k in 0..6 {
            let q = random_q(&mut rng, &m);
            let target = m.fk(&q);
            let seed: [f64; 6] = std::array::from_fn(|i| q[i] + rng.random_range(-5.0..5.0));
            let s = m.ik_nearest(&target, &seed, &IkConfig::any()).expect("converges near the seed");
            assert_solution_ok(&m, &target, &s.q_deg);
            assert!(m.joint_distance(&s.q_deg, &q) < 0.05, "{:?} vs {q:?}", s.q_deg);
            if k < 2 {
                // Without a seed: the 16 fixed seeds find some branches, each verified.
                for sol in m.ik(&target, IkConfig::any()).expect("some solutions") {
                    assert_solution_ok(&m, &target, &sol);
                }
            }
        }
    }

    #[test]
    fn rotation_vector_is_accurate_for_tiny_angles() {
        let axis = nalgebra::Unit::new_normalize(Vector3::new(1.0, 2.0, -0.5));
        for angle in [1e-12, 1e-9, 1e-3, 1.0, 3.0] {
            let r = UnitQuaternion::from_axis_angle(&axis, angle);
            let v = rotation_vector(&r);
            assert!((v.norm() - angle).abs() < 1e-15 + 1e-12 * angle, "{angle}");
            let back = Rotation3::from_scaled_axis(v);
            assert!((back.matrix() - r.to_rotation_matrix().matrix()).abs().max() < 1e-14);
        }
    }
}
