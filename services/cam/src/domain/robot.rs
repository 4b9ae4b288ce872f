//! Robot milling (seed 001): a checked toolpath ([`super::clearance::ClearedPath`]: tip
//! positions and tool axes in the part frame) becomes a joint trajectory of the 6-axis arm the
//! scanning cell uses ([`depthmill_geometry::arm`], the Adept Viper s650), with a spindle on its
//! flange instead of the scanner.
//!
//! # Frames
//!
//! - `base_from_part` ([`RobotCell::base_from_part`]) places the part in the robot's base frame
//!   (the arm's `base` is `world_from_base`, the identity by default).
//! - `flange_from_tip` ([`RobotCell::flange_from_tip`]): the spindle's axis is the flange's Z
//!   turned by `spindle_mount_deg` about the flange's X (90° by default: the spindle on a bracket
//!   across the flange, as robot milling cells mount it, so that a tool pointing down leaves the
//!   wrist bent, far from its singularity); the tool tip sits `spindle_length_mm +
//!   holder_length_mm + stickout_mm` out along that axis. The
//!   tool frame's Z points from the holder to the tip (minus the toolpath's axis); the spindle is
//!   symmetric about it, so the turn about it (the *spin*) is free: one spin is chosen for the
//!   whole program (with the spindle off the flange's axis it moves the wrist, so it is chosen
//!   before the tilts, which must keep that wrist clear).
//!
//! # Planning
//!
//! 1. **Branch and spin** ([`choose_branch`], on the upright program before the tilts): for each
//!    spin in 30° steps and each IK branch found at the first reachable position, the program is
//!    followed on up to [`CHOICE_SAMPLES`] evenly spread positions keeping that branch; the pair
//!    reaching the most positions, then keeping the joints farthest from their limits (in 10°
//!    steps up to 60°: a wrist joint near its limit winds up against it along rings and would
//!    have to turn a whole turn back in the cut), then with the greatest smallest dexterity
//!    `sqrt(det(JᵀJ))`, is kept.
//! 2. **Along the path**: every position is solved in that one branch (no flips), nearest to the
//!    previous joints, refused within the arm's singularity margins and outside its joint
//!    limits. A step (feed or rapid) whose joints turn more than [`JOINT_STEP_DEG`] is split along
//!    its line, the axis turning as the clearance check turned it, so the controller's joint
//!    interpolation between the points stays on the line. Positions that fail are grouped into
//!    unreachable stretches with the reason (out of reach, a joint limit, a singularity); a feed
//!    step whose joints still jump more than [`MAX_FEED_JUMP_DEG`] is reported the same way (the
//!    arm cannot follow the straight line there without turning a joint through a large angle).
//! 3. **Timing** with the arm's motion model: a rapid is a synchronised rest-to-rest trapezoid
//!    per joint ([`ArmModel::move_time_s`]); a feed step takes the longer of its length at the
//!    feed and its largest joint turn at that joint's top speed (the controller blends feed
//!    steps, so they do not stop; the joint speeds cap the feed where the wrist turns fast).
//!    All speeds are scaled by [`RobotCell::speed_frac`].

use depthmill_geometry::arm::{ArmModel, Configuration, IkConfig, SingularityMargins};
use nalgebra::{Isometry3, Matrix4, Point3, Rotation3, Translation3, Unit, UnitQuaternion, Vector3};

use depthmill_geometry::{Mesh, ToolProfile};

use super::clearance::{
    ClearedPath, MeshIndex, OrientedPoint, TiltOptions, ToolBody, axis_between, clear_path,
};
use super::layer_passes::{MeshProgram, MeshProgramOptions, MoveKind, PassError, mesh_program};
use super::tool::Tool;

/// Rounds of lifting over cutting positions the arm cannot follow.
pub const REACH_ROUNDS: usize = 3;

/// What a position lifted over for the arm's reach (not a collision) lists as what hits.
pub const OUT_OF_REACH: &str = "arm (out of reach)";

/// Positions sampled to choose the branch and the spin.
pub const CHOICE_SAMPLES: usize = 64;

/// A tilted tool axis keeps the arm's wrist at least this far from its singularity, degrees
/// (the joints 4 and 6 swing fast near it).
pub const TILT_WRIST_MARGIN_DEG: f64 = 10.0;

/// A step whose joints turn more than this is split along its line, degrees.
pub const JOINT_STEP_DEG: f64 = 2.0;

/// Most pieces a step is split into.
pub const MAX_SPLIT: usize = 64;

/// Largest turn of any joint over one feed step, degrees.
pub const MAX_FEED_JUMP_DEG: f64 = 20.0;

/// The arm with a spindle and where the part stands.
#[derive(Debug, Clone, PartialEq)]
pub struct RobotCell {
    /// The arm; its `tool` is replaced by the spindle and the tool ([`RobotCell::arm_for`]).
    pub arm: ArmModel,
    pub base_from_part: Isometry3<f64>,
    /// Flange face to spindle nose along the spindle's axis, mm.
    pub spindle_length_mm: f64,
    /// Angle between the flange's axis and the spindle's, degrees (a turn about the flange's X
    /// axis): 0 puts the spindle on the flange's axis, 90 across it on a bracket, which keeps the
    /// wrist far from its singularity while the tool points down.
    pub spindle_mount_deg: f64,
    pub spindle_diameter_mm: f64,
    /// Fraction of the joints' top speeds the program uses (0, 1].
    pub speed_frac: f64,
}

/// Why no robot program could be made.
#[derive(Debug, PartialEq, thiserror::Error)]
pub enum RobotPlanError {
    #[error("{field} {value}: {expected}")]
    Invalid { field: &'static str, value: String, expected: &'static str },
    #[error("the arm reaches none of the program's {positions} positions: at the first, {reason}")]
    Unreachable { positions: usize, reason: String },
    #[error("layers: {0}")]
    Layers(PassError),
    #[error("tool clearance: {0}")]
    Clearance(String),
    #[error("planning cancelled")]
    Cancelled,
}

impl From<PassError> for RobotPlanError {
    fn from(e: PassError) -> Self {
        RobotPlanError::Layers(e)
    }
}

impl RobotCell {
    /// The Viper s650 at the world origin, the part at `base_from_part`, a 150 mm x 60 mm spindle
    /// mounted across the flange, joints at most at 50 % of their top speed.
    pub fn viper_s650(base_from_part: Isometry3<f64>) -> Self {
        RobotCell {
            arm: ArmModel::viper_s650(),
            base_from_part,
            spindle_length_mm: 150.0,
            spindle_mount_deg: 90.0,
            spindle_diameter_mm: 60.0,
            speed_frac: 0.5,
        }
    }

    /// Checks the settings.
    pub fn validate(&self) -> Result<(), RobotPlanError> {
        let bad = |field, value: f64, expected| {
            Err(RobotPlanError::Invalid { field, value: value.to_string(), expected })
        };
        if !(self.spindle_length_mm.is_finite() && self.spindle_length_mm >= 0.0) {
            return bad("spindle_length_mm", self.spindle_length_mm, "must be a non-negative length");
        }
        if !(self.spindle_diameter_mm.is_finite() && self.spindle_diameter_mm >= 0.0) {
            return bad("spindle_diameter_mm", self.spindle_diameter_mm, "must be a non-negative diameter");
        }
        if !(self.spindle_mount_deg.is_finite() && (0.0..=90.0).contains(&self.spindle_mount_deg)) {
            return bad("spindle_mount_deg", self.spindle_mount_deg, "must be from 0 to 90 degrees");
        }
        if !(self.speed_frac.is_finite() && self.speed_frac > 0.0 && self.speed_frac <= 1.0) {
            return bad("speed_frac", self.speed_frac, "must be in (0, 1]");
        }
        let t = self.base_from_part.translation.vector;
        if !(t.iter().all(|v| v.is_finite())
            && self.base_from_part.rotation.coords.iter().all(|v| v.is_finite()))
        {
            return Err(RobotPlanError::Invalid {
                field: "base_from_part",
                value: format!("{t:?}"),
                expected: "must be finite",
            });
        }
        Ok(())
    }

    /// `flange_from_tip` for `tool` (see the module docs).
    pub fn flange_from_tip(&self, tool: &Tool) -> Isometry3<f64> {
        let mount = UnitQuaternion::from_axis_angle(&Vector3::x_axis(), self.spindle_mount_deg.to_radians());
        let reach = self.spindle_length_mm + tool.holder_length_mm + tool.stickout_mm;
        Isometry3::from_parts(Translation3::from(mount * Vector3::new(0.0, 0.0, reach)), mount)
    }

    /// The arm with `tool` in the spindle as its tool frame.
    pub fn arm_for(&self, tool: &Tool) -> ArmModel {
        self.arm.clone().with_tool(self.flange_from_tip(tool))
    }

    /// `world_from_tip` with the tip at `tip` and the axis along `axis` (part frame), turned
    /// by `spin` (radians) about the tool's axis.
    pub fn target(&self, tip: &[f64; 3], axis: &[f64; 3], spin: f64) -> Isometry3<f64> {
        let a = Unit::new_normalize(Vector3::from(*axis));
        let lean = UnitQuaternion::rotation_between(&Vector3::z(), &a).unwrap_or_else(|| {
            // Straight down: half a turn about X.
            UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI)
        });
        let r = lean
            * UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI)
            * UnitQuaternion::from_axis_angle(&Vector3::z_axis(), spin);
        self.arm.base
            * self.base_from_part
            * Isometry3::from_parts(Translation3::from(Vector3::from(*tip)), r)
    }
}

/// One position of the joint trajectory.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct JointPoint {
    /// Time from the program's start, s.
    pub t_s: f64,
    /// Joints 1-6, degrees (the previous position's when not reachable).
    pub q_deg: [f64; 6],
    /// Tip and tool axis in the part frame.
    pub tip_mm: [f64; 3],
    pub axis: [f64; 3],
    pub rapid: bool,
    pub reachable: bool,
}

/// Consecutive positions the arm cannot take.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Stretch {
    /// Indices into the trajectory's points, inclusive.
    pub from_point: usize,
    pub to_point: usize,
    /// The first position's tip, part frame.
    pub at_mm: [f64; 3],
    pub reason: String,
}

/// The robot program (see the module docs); serialised, it is the joint-trajectory file.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct RobotProgram {
    /// `"depthmill-joint-trajectory/1"`.
    pub format: &'static str,
    pub arm: &'static str,
    pub configuration: String,
    pub spin_deg: f64,
    /// Row-major 4 x 4 transforms, mm.
    pub base_from_part: [[f64; 4]; 4],
    pub flange_from_tip: [[f64; 4]; 4],
    pub speed_frac: f64,
    pub feed_mm_min: f64,
    /// The tool's cutting profile and its length out of the holder (the solid the simulation
    /// sweeps), mm.
    pub tool_profile: ToolProfile,
    pub tool_length_mm: f64,
    /// The stock the program starts from, an axis-aligned box of the part frame (set by the
    /// planner; the part's box when planned from a path alone), mm.
    pub stock_min_mm: [f64; 3],
    pub stock_max_mm: [f64; 3],
    pub duration_s: f64,
    pub feed_s: f64,
    pub rapid_s: f64,
    /// Feed steps slowed by a joint's top speed.
    pub joint_limited_steps: usize,
    pub min_dexterity: f64,
    /// The smallest margins from each singularity over the program.
    pub min_margins: SingularityMargins,
    pub unreachable: Vec<Stretch>,
    pub points: Vec<JointPoint>,
}

/// Frame format of the trajectory file.
pub const TRAJECTORY_FORMAT: &str = "depthmill-joint-trajectory/1";

fn matrix(i: &Isometry3<f64>) -> [[f64; 4]; 4] {
    let m: Matrix4<f64> = i.to_homogeneous();
    std::array::from_fn(|r| std::array::from_fn(|c| m[(r, c)]))
}

/// Follows `points` in `config` with `spin` from the first reachable one; positions reached and
/// the smallest dexterity on the way.
fn follow(
    arm: &ArmModel,
    cell: &RobotCell,
    points: &[([f64; 3], [f64; 3])],
    config: Configuration,
    spin: f64,
) -> (usize, f64, f64) {
    let ik = IkConfig::only(config);
    let mut prev: Option<[f64; 6]> = None;
    let (mut reached, mut dex, mut margin) = (0, f64::INFINITY, f64::INFINITY);
    for (tip, axis) in points {
        let target = cell.target(tip, axis, spin);
        let sol = match prev {
            Some(q) => arm.ik_nearest(&target, &q, &ik).ok(),
            None => arm.ik_solutions(&target, &ik).ok().and_then(|s| s.into_iter().next()),
        };
        if let Some(s) = sol {
            reached += 1;
            dex = dex.min(arm.dexterity(&s.q_deg));
            for (l, q) in arm.limits.iter().zip(&s.q_deg) {
                margin = margin.min((q - l.min_deg).min(l.max_deg - q));
            }
            prev = Some(s.q_deg);
        }
    }
    (reached, dex, margin)
}

/// The branch and spin (radians) that reach the most of up to [`CHOICE_SAMPLES`] positions spread
/// evenly over `points` (tip, axis), then keep the joints farthest from their limits (in 10°
/// steps up to 60°), then with the greatest smallest dexterity; only `branch` when given.
pub fn choose_branch(
    arm: &ArmModel,
    cell: &RobotCell,
    points: &[([f64; 3], [f64; 3])],
    branch: Option<Configuration>,
) -> Result<(Configuration, f64), RobotPlanError> {
    let step = points.len().div_ceil(CHOICE_SAMPLES).max(1);
    let samples: Vec<([f64; 3], [f64; 3])> = points.iter().step_by(step).copied().collect();
    let mut best: Option<(usize, i64, f64, Configuration, f64)> = None;
    let mut first_error = String::new();
    for k in 0..12 {
        let spin = (k as f64 * 30.0).to_radians();
        // Branches at the first sample the arm reaches with this spin.
        let branches = samples.iter().find_map(|(tip, axis)| {
            match arm.ik_solutions(&cell.target(tip, axis, spin), &IkConfig::default()) {
                Ok(s) if !s.is_empty() => Some(s),
                Ok(_) => None,
                Err(e) => {
                    if first_error.is_empty() {
                        first_error = e.to_string();
                    }
                    None
                }
            }
        });
        for s in branches.unwrap_or_default() {
            if branch.is_some_and(|b| b != s.configuration) {
                continue;
            }
            let (n, dex, margin) = follow(arm, cell, &samples, s.configuration, spin);
            // Joints kept off their limits (in 10° steps up to 60°) before dexterity: a wrist
            // joint near its limit winds up against it along rings.
            let room = (margin.min(60.0) / 10.0).floor() as i64;
            if best
                .is_none_or(|(bn, br, bd, _, _)| (n, room) > (bn, br) || ((n, room) == (bn, br) && dex > bd))
            {
                best = Some((n, room, dex, s.configuration, spin));
            }
        }
    }
    best.map(|(_, _, _, c, spin)| (c, spin))
        .ok_or(RobotPlanError::Unreachable { positions: points.len(), reason: first_error })
}

/// The joint trajectory of `path` (its blocked positions are not cut: the caller lifts over
/// them) for `tool` at `feed_mm_min` (see the module docs), in `branch` (a configuration and a
/// spin, radians) when given, else the one [`choose_branch`] picks.
pub fn robot_program(
    cell: &RobotCell,
    tool: &Tool,
    path: &ClearedPath,
    feed_mm_min: f64,
    branch: Option<(Configuration, f64)>,
) -> Result<RobotProgram, RobotPlanError> {
    cell.validate()?;
    if !(feed_mm_min.is_finite() && feed_mm_min > 0.0) {
        return Err(RobotPlanError::Invalid {
            field: "feed_mm_min",
            value: feed_mm_min.to_string(),
            expected: "must be a positive feed",
        });
    }
    let arm = cell.arm_for(tool);
    let points: Vec<&OrientedPoint> = path.points.iter().filter(|p| !p.blocked).collect();
    let stock = points.iter().fold(([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]), |(lo, hi), p| {
        (std::array::from_fn(|k| lo[k].min(p.tip[k])), std::array::from_fn(|k| hi[k].max(p.tip[k])))
    });
    if points.is_empty() {
        return Err(RobotPlanError::Unreachable {
            positions: 0,
            reason: "the program has no position".into(),
        });
    }
    // 1. Branch and spin.
    let samples: Vec<([f64; 3], [f64; 3])> = points.iter().map(|p| (p.tip, p.axis)).collect();
    let (config, spin) = match branch {
        Some(b) => b,
        None => choose_branch(&arm, cell, &samples, None)?,
    };
    // 2. Along the path, 3. timing.
    let ik = IkConfig::only(config);
    let feed = feed_mm_min / 60.0;
    let mut out: Vec<JointPoint> = Vec::with_capacity(points.len());
    let mut unreachable: Vec<Stretch> = Vec::new();
    let mut prev_q: Option<[f64; 6]> = None;
    let (mut t, mut feed_s, mut rapid_s, mut limited) = (0.0, 0.0, 0.0, 0);
    let mut dex_min = f64::INFINITY;
    let mut margins =
        SingularityMargins { wrist_deg: f64::INFINITY, shoulder_mm: f64::INFINITY, elbow_deg: f64::INFINITY };
    let mut prev_tip: Option<[f64; 3]> = None;
    // One position: IK nearest the last, the reports, the time from the last.
    let mut push = |tip: [f64; 3], axis: [f64; 3], rapid: bool, out: &mut Vec<JointPoint>| {
        let i = out.len();
        let target = cell.target(&tip, &axis, spin);
        let sol = match prev_q {
            Some(q) => arm.ik_nearest(&target, &q, &ik),
            None => arm.ik_solutions(&target, &ik).and_then(|s| {
                s.into_iter().next().ok_or(depthmill_geometry::arm::IkError::NotConverged {
                    position_error_mm: f64::NAN,
                    angle_error_deg: f64::NAN,
                })
            }),
        };
        let mut reason = None;
        let mut jumped = false;
        let q = match (sol, prev_q) {
            (Ok(s), Some(q0)) => {
                let jump = (0..6).map(|j| (s.q_deg[j] - q0[j]).abs()).fold(0.0, f64::max);
                if !rapid && jump > MAX_FEED_JUMP_DEG {
                    // The arm gets there, but not along the line: reported, and followed on
                    // from there.
                    reason = Some(format!(
                        "a joint turns {jump:.1}° over one feed step (more than {MAX_FEED_JUMP_DEG}°): the straight line passes near a singularity or a joint limit"
                    ));
                    jumped = true;
                }
                s.q_deg
            }
            (Ok(s), None) => s.q_deg,
            (Err(e), q0) => {
                reason = Some(e.to_string());
                q0.unwrap_or(ArmModel::HOME_DEG)
            }
        };
        let reachable = reason.is_none();
        if let Some(r) = reason {
            match unreachable.last_mut() {
                Some(s) if s.to_point + 1 == i && s.reason == r => s.to_point = i,
                _ => unreachable.push(Stretch { from_point: i, to_point: i, at_mm: tip, reason: r }),
            }
        } else {
            dex_min = dex_min.min(arm.dexterity(&q));
            let m = arm.singularity_margins(&q);
            margins.wrist_deg = margins.wrist_deg.min(m.wrist_deg);
            margins.shoulder_mm = margins.shoulder_mm.min(m.shoulder_mm);
            margins.elbow_deg = margins.elbow_deg.min(m.elbow_deg);
        }
        if let (Some(q0), Some(tip0)) = (prev_q, prev_tip) {
            if rapid {
                let dt = arm.move_time_s(&q0, &q, cell.speed_frac);
                rapid_s += dt;
                t += dt;
            } else {
                let len = (0..3).map(|k| (tip[k] - tip0[k]).powi(2)).sum::<f64>().sqrt();
                let joint = (0..6)
                    .map(|j| (q[j] - q0[j]).abs() / (arm.limits[j].max_speed_deg_s * cell.speed_frac))
                    .fold(0.0, f64::max);
                let dt = (len / feed).max(joint);
                if joint > len / feed {
                    limited += 1;
                }
                feed_s += dt;
                t += dt;
            }
        }
        out.push(JointPoint { t_s: t, q_deg: q, tip_mm: tip, axis, rapid, reachable });
        if reachable || jumped {
            prev_q = Some(q);
        }
        prev_tip = Some(tip);
    };
    for p in &points {
        // A step whose joints turn more than JOINT_STEP_DEG is split along the line (the axis
        // turning as the clearance check turned it, `axis_between`), so the arm's joint
        // interpolation between the points it is given stays near the line; rapids too (a
        // joint-interpolated rapid swings the tip off its line).
        if let Some(last) = out.last().copied()
            && last.reachable
            && let Ok(s) = arm.ik_nearest(&cell.target(&p.tip, &p.axis, spin), &last.q_deg, &ik)
        {
            let turn = (0..6).map(|j| (s.q_deg[j] - last.q_deg[j]).abs()).fold(0.0, f64::max);
            let n = ((turn / JOINT_STEP_DEG).ceil() as usize).clamp(1, MAX_SPLIT);
            for k in 1..n {
                let f = k as f64 / n as f64;
                let tip = std::array::from_fn(|c| last.tip_mm[c] + f * (p.tip[c] - last.tip_mm[c]));
                push(tip, axis_between(&last.axis, &p.axis, f), p.rapid, &mut out);
            }
        }
        push(p.tip, p.axis, p.rapid, &mut out);
    }
    if out.iter().all(|p| !p.reachable) {
        return Err(RobotPlanError::Unreachable {
            positions: out.len(),
            reason: unreachable.first().map_or_else(String::new, |s| s.reason.clone()),
        });
    }
    Ok(RobotProgram {
        format: TRAJECTORY_FORMAT,
        arm: "Adept Viper s650",
        configuration: config.to_string(),
        spin_deg: spin.to_degrees(),
        base_from_part: matrix(&cell.base_from_part),
        flange_from_tip: matrix(&cell.flange_from_tip(tool)),
        speed_frac: cell.speed_frac,
        feed_mm_min,
        tool_profile: tool.profile.clone(),
        tool_length_mm: tool.stickout_mm,
        stock_min_mm: stock.0,
        stock_max_mm: stock.1,
        duration_s: t,
        feed_s,
        rapid_s,
        joint_limited_steps: limited,
        min_dexterity: dex_min,
        min_margins: margins,
        unreachable,
        points: out,
    })
}

/// A robot milling job from a mesh.
#[derive(Debug, Clone, PartialEq)]
pub struct RobotJob {
    pub tool: Tool,
    pub layers: MeshProgramOptions,
    pub tilt: TiltOptions,
    pub cell: RobotCell,
    pub feed_mm_min: f64,
    /// The part's place was left to the planner: when the arm cannot reach every position of
    /// the program at `cell.base_from_part`, other places are tried ([`choose_placement`]).
    pub auto_place: bool,
}

/// Distances of the part's centre in front of the robot's base tried by [`choose_placement`],
/// mm, in order of preference (the default first).
pub const PLACE_DISTANCES_MM: [f64; 8] = [420.0, 380.0, 460.0, 340.0, 500.0, 300.0, 540.0, 260.0];
/// Turns of the part about the base's Z axis tried, degrees.
pub const PLACE_YAWS_DEG: [f64; 4] = [0.0, 90.0, -90.0, 180.0];
/// Heights of the part's bottom above the base tried, mm.
pub const PLACE_HEIGHTS_MM: [f64; 3] = [0.0, -100.0, 100.0];
/// Positions a candidate place is first tried on (spread evenly over the program).
pub const PLACE_SAMPLES: usize = 4096;

/// Where [`choose_placement`] put the part and why.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Placement {
    /// The part's box centre this far in front of the base, mm, turned this much about Z,
    /// degrees, its bottom this high, mm.
    pub distance_mm: f64,
    pub yaw_deg: f64,
    pub height_mm: f64,
    /// Upright program positions the arm reaches there, of all.
    pub reached: usize,
    pub positions: usize,
    /// ... and at the default place.
    pub reached_at_default: usize,
    /// Places tried.
    pub tried: usize,
}

/// The part's place in the base frame: its box (`lo`, `hi` in the part frame) centred
/// `distance_mm` in front of the base, turned `yaw_deg` about Z, its bottom at `height_mm`.
pub fn place(lo: [f64; 3], hi: [f64; 3], distance_mm: f64, yaw_deg: f64, height_mm: f64) -> Isometry3<f64> {
    Isometry3::new(Vector3::new(distance_mm, 0.0, height_mm), Vector3::z() * yaw_deg.to_radians())
        * Translation3::new(-0.5 * (lo[0] + hi[0]), -0.5 * (lo[1] + hi[1]), -lo[2])
}

/// Positions of `points` (tip, axis) the arm reaches at `cell`'s place in the branch and spin
/// [`choose_branch`] picks there (in parallel); 0 when it picks none.
fn reach_count(arm: &ArmModel, cell: &RobotCell, points: &[([f64; 3], [f64; 3])]) -> usize {
    use rayon::prelude::*;
    let Ok((config, spin)) = choose_branch(arm, cell, points, None) else { return 0 };
    let ik = IkConfig::only(config);
    points
        .par_iter()
        .filter(|(tip, axis)| {
            arm.ik_solutions(&cell.target(tip, axis, spin), &ik).is_ok_and(|s| !s.is_empty())
        })
        .count()
}

/// Where to put a part whose place the job left open: the default place ([`PLACE_DISTANCES_MM`]
/// first entry, no turn, bottom at the base's height) when the arm reaches every position of
/// the upright program `points` there; else the first place, in the order of
/// [`PLACE_DISTANCES_MM`] x [`PLACE_YAWS_DEG`] x [`PLACE_HEIGHTS_MM`], where it reaches every one
/// (tried first on [`PLACE_SAMPLES`] spread positions, then on all); else the place reaching
/// the most. `lo`/`hi` is the part's box. `None` when the default reaches everything.
pub fn choose_placement(
    arm: &ArmModel,
    cell: &RobotCell,
    points: &[([f64; 3], [f64; 3])],
    lo: [f64; 3],
    hi: [f64; 3],
    cancelled: &(dyn Fn() -> bool + Sync),
) -> Result<Option<(Isometry3<f64>, Placement)>, RobotPlanError> {
    let at =
        |d: f64, yaw: f64, h: f64| RobotCell { base_from_part: place(lo, hi, d, yaw, h), ..cell.clone() };
    let n = points.len();
    let default = reach_count(arm, &at(PLACE_DISTANCES_MM[0], 0.0, 0.0), points);
    if default == n {
        return Ok(None);
    }
    let step = n.div_ceil(PLACE_SAMPLES).max(1);
    let sample: Vec<([f64; 3], [f64; 3])> = points.iter().step_by(step).copied().collect();
    let mut best = (default, PLACE_DISTANCES_MM[0], 0.0, 0.0);
    let mut tried = 1;
    for h in PLACE_HEIGHTS_MM {
        for yaw in PLACE_YAWS_DEG {
            for d in PLACE_DISTANCES_MM {
                if (d, yaw, h) == (PLACE_DISTANCES_MM[0], 0.0, 0.0) {
                    continue;
                }
                if cancelled() {
                    return Err(RobotPlanError::Cancelled);
                }
                tried += 1;
                let c = at(d, yaw, h);
                if reach_count(arm, &c, &sample) < sample.len() {
                    continue;
                }
                let all = reach_count(arm, &c, points);
                if all > best.0 {
                    best = (all, d, yaw, h);
                }
                if all == n {
                    break;
                }
            }
            if best.0 == n {
                break;
            }
        }
        if best.0 == n {
            break;
        }
    }
    let (reached, d, yaw, h) = best;
    if reached == default {
        return Ok(None);
    }
    Ok(Some((
        place(lo, hi, d, yaw, h),
        Placement {
            distance_mm: d,
            yaw_deg: yaw,
            height_mm: h,
            reached,
            positions: n,
            reached_at_default: default,
            tried,
        },
    )))
}

/// What [`plan_robot`] made.
#[derive(Debug, Clone, PartialEq)]
pub struct RobotPlan {
    /// The layers, their rings and the 3-axis program joining them.
    pub layers: MeshProgram,
    /// Every position checked and tilted, blocked stretches lifted over.
    pub path: ClearedPath,
    pub robot: RobotProgram,
    /// Where the part was moved to when the arm could not reach all of it at the default place.
    pub placement: Option<Placement>,
}

/// The whole robot plan of a mesh: slice and ring the layers ([`mesh_program`]), check the tool
/// body (with the spindle) against the mesh at every position and tilt it where needed
/// ([`clear_path`]), lift over what no tilt clears, and solve the arm along it
/// ([`robot_program`]).
pub fn plan_robot(mesh: &Mesh, job: &RobotJob) -> Result<RobotPlan, RobotPlanError> {
    plan_robot_watched(mesh, job, &|_, _| {}, &|| false)
}

/// Progress of a robot plan: the fraction done (0..=1) and what it is doing.
pub type Progress<'a> = &'a (dyn Fn(f64, &str) + Sync);

/// [`plan_robot`] reporting its progress and asking `cancelled` as it goes (between phases and
/// every [`super::clearance::STOP_EVERY`] positions of the clearance check, the long part):
/// [`RobotPlanError::Cancelled`] once it says so.
pub fn plan_robot_watched(
    mesh: &Mesh,
    job: &RobotJob,
    progress: Progress<'_>,
    cancelled: &(dyn Fn() -> bool + Sync),
) -> Result<RobotPlan, RobotPlanError> {
    job.cell.validate()?;
    progress(0.0, "slicing the mesh into layers");
    let layers = mesh_program(mesh, &job.layers)?;
    if cancelled() {
        return Err(RobotPlanError::Cancelled);
    }
    let index = MeshIndex::new(mesh);
    let spindle = Some((job.cell.spindle_diameter_mm, job.cell.spindle_length_mm));
    let body = ToolBody::new(&job.tool, job.tilt.gouge_tol_mm, spindle);
    let start = layers
        .program
        .moves
        .first()
        .map_or([0.0, 0.0, layers.clear_z_mm], |m| [m.to[0], m.to[1], layers.clear_z_mm]);
    // A retract straight up runs at feed: stock may stand above where a stretch was lifted over.
    let mut moves: Vec<([f64; 3], bool)> = Vec::with_capacity(layers.program.moves.len());
    let mut from = start;
    for m in &layers.program.moves {
        let up = m.to[0] == from[0] && m.to[1] == from[1] && m.to[2] > from[2];
        moves.push((m.to, m.kind == MoveKind::Rapid && !up));
        from = m.to;
    }
    // The program keeps the branch and spin chosen on the upright program, and its tilts keep
    // that branch's wrist at least TILT_WRIST_MARGIN_DEG from its singularity and its joints
    // within their limits (with the spindle off the flange's axis, the spin moves the wrist).
    let arm = job.cell.arm_for(&job.tool);
    let upright: Vec<([f64; 3], [f64; 3])> = moves.iter().map(|m| (m.0, [0.0, 0.0, 1.0])).collect();
    let mut cell = job.cell.clone();
    let mut placement = None;
    if job.auto_place {
        progress(0.05, "checking the arm reaches the part where it stands");
        let [x0, y0, x1, y1] = layers.options.stock;
        let (lo, hi) = ([x0, y0, layers.z_range_mm[0]], [x1, y1, layers.z_range_mm[1]]);
        if let Some((at, p)) = choose_placement(&arm, &cell, &upright, lo, hi, cancelled)? {
            cell.base_from_part = at;
            placement = Some(p);
        }
    }
    let (config, spin) = choose_branch(&arm, &cell, &upright, None)?;
    let tilt_ik = IkConfig {
        singularity_thresholds: SingularityMargins {
            wrist_deg: TILT_WRIST_MARGIN_DEG,
            ..SingularityMargins::DEFAULT
        },
        ..IkConfig::only(config)
    };
    let accept = |tip: &Point3<f64>, axis: &Unit<Vector3<f64>>| -> bool {
        let target = cell.target(&tip.coords.into(), &axis.into_inner().into(), spin);
        arm.ik_solutions(&target, &tilt_ik).is_ok_and(|s| !s.is_empty())
    };
    // Progress in whole percent of the check, each told once.
    let told = std::sync::atomic::AtomicUsize::new(usize::MAX);
    let stop = |done: usize, total: usize| {
        let pct = 100 * done / total.max(1);
        if told.swap(pct, std::sync::atomic::Ordering::Relaxed) != pct {
            progress(
                0.1 + 0.8 * done as f64 / total.max(1) as f64,
                &format!("checking the tool body at position {done} of {total}"),
            );
        }
        cancelled()
    };
    progress(0.1, "checking the tool body against the mesh");
    let mut checked = clear_path(&index, &body, start, &moves, &job.tilt, &accept, &stop)
        .map_err(|e| if cancelled() { RobotPlanError::Cancelled } else { RobotPlanError::Clearance(e) })?;
    let mut path = checked.lifted(&index, &body, layers.clear_z_mm, &job.tilt, &accept);
    if cancelled() {
        return Err(RobotPlanError::Cancelled);
    }
    progress(0.9, "solving the arm's joints along the path");
    let mut robot = robot_program(&cell, &job.tool, &path, job.feed_mm_min, Some((config, spin)))?;
    // Cutting positions the arm cannot follow (and their neighbours, where the arm would leave
    // and rejoin the path) are lifted over like those no tilt clears: holding the joints and
    // then moving on would sweep the tool through the part.
    for _ in 0..REACH_ROUNDS {
        if robot.unreachable.is_empty() || cancelled() {
            break;
        }
        let bits = |t: &[f64; 3]| t.map(f64::to_bits);
        let at: std::collections::HashMap<[u64; 3], usize> =
            checked.points.iter().enumerate().map(|(i, p)| (bits(&p.tip), i)).collect();
        let mut newly = 0;
        for st in &robot.unreachable {
            let (lo, hi) = (st.from_point.saturating_sub(1), (st.to_point + 1).min(robot.points.len() - 1));
            for jp in robot.points.get(lo..=hi).unwrap_or_default() {
                if let Some(&i) = at.get(&bits(&jp.tip_mm))
                    && !checked.points[i].blocked
                {
                    checked.points[i].blocked = true;
                    checked.blocked.push(super::clearance::Blocked {
                        at_mm: jp.tip_mm,
                        part: OUT_OF_REACH,
                        depth_mm: 0.0,
                    });
                    newly += 1;
                }
            }
        }
        if newly == 0 {
            break;
        }
        let again = checked.lifted(&index, &body, layers.clear_z_mm, &job.tilt, &accept);
        let r = robot_program(&cell, &job.tool, &again, job.feed_mm_min, Some((config, spin)))?;
        let bad = |r: &RobotProgram| r.points.iter().filter(|p| !p.reachable).count();
        if bad(&r) >= bad(&robot) {
            break;
        }
        (path, robot) = (again, r);
    }
    let st = layers.options.stock;
    robot.stock_min_mm = [st[0], st[1], layers.z_range_mm[0]];
    robot.stock_max_mm = [st[2], st[3], layers.z_range_mm[1]];
    progress(1.0, "robot program planned");
    Ok(RobotPlan { layers, path, robot, placement })
}

/// The robot program as G-code (LinuxCNC's words): the tool tip in the part frame (X, Y, Z) and
/// the tool axis as A and B ([`axis_to_ab`]), rapids as G0 and feeds as G1, the tool in T1, the
/// joint trajectory named in the header. `title` goes into the header comment.
///
/// Errors: a feed or spindle speed that is not positive.
pub fn robot_gcode(
    plan: &RobotPlan,
    tool: &str,
    feed_mm_min: f64,
    rpm: f64,
    title: &str,
) -> Result<String, RobotPlanError> {
    use std::fmt::Write as _;
    let bad =
        |field, value: f64, expected| RobotPlanError::Invalid { field, value: value.to_string(), expected };
    if !(feed_mm_min.is_finite() && feed_mm_min > 0.0) {
        return Err(bad("feed_mm_min", feed_mm_min, "must be a positive feed"));
    }
    if !(rpm.is_finite() && rpm > 0.0) {
        return Err(bad("rpm", rpm, "must be a positive speed"));
    }
    let clean = |t: &str| t.replace(['(', ')'], "");
    let mut g = String::new();
    let mut line = |text: std::fmt::Arguments<'_>| {
        let _ = g.write_fmt(text);
        g.push('\n');
    };
    line(format_args!("%"));
    line(format_args!("(depthmill robot program: {})", clean(title)));
    line(format_args!(
        "(tool tip X Y Z in the part frame, mm; tool axis from A and B, degrees: axis = Ry B . Rx A . Z)"
    ));
    line(format_args!(
        "(arm: {}, {}, spin {:.0} deg; joint trajectory in the .joints.json beside this file)",
        plan.robot.arm, plan.robot.configuration, plan.robot.spin_deg
    ));
    line(format_args!("G21 G90 G17 G94 G40 G49 G80"));
    line(format_args!("(T1 {})", clean(tool)));
    line(format_args!("T1 M6"));
    line(format_args!("S{rpm:.0} M3"));
    let mut feed_set = false;
    for p in &plan.path.points {
        let [x, y, z] = p.tip;
        let (a, b) = axis_to_ab(&p.axis);
        let (a, b) = (if a.abs() < 5e-5 { 0.0 } else { a }, if b.abs() < 5e-5 { 0.0 } else { b });
        if p.rapid {
            line(format_args!("G0 X{x:.4} Y{y:.4} Z{z:.4} A{a:.4} B{b:.4}"));
        } else if !feed_set {
            line(format_args!("G1 X{x:.4} Y{y:.4} Z{z:.4} A{a:.4} B{b:.4} F{feed_mm_min:.1}"));
            feed_set = true;
        } else {
            line(format_args!("G1 X{x:.4} Y{y:.4} Z{z:.4} A{a:.4} B{b:.4}"));
        }
    }
    line(format_args!("M5"));
    line(format_args!("M30"));
    line(format_args!("%"));
    Ok(g)
}

/// The tool axis as the A and B words of the robot program's G-code: the axis is
/// `Ry(B) · Rx(A) · Z` = `(cos A sin B, −sin A, cos A cos B)`, degrees.
pub fn axis_to_ab(axis: &[f64; 3]) -> (f64, f64) {
    let a = (-axis[1]).clamp(-1.0, 1.0).asin();
    let b = axis[0].atan2(axis[2]);
    (a.to_degrees(), b.to_degrees())
}

/// The inverse of [`axis_to_ab`].
pub fn ab_to_axis(a_deg: f64, b_deg: f64) -> [f64; 3] {
    let r = Rotation3::from_axis_angle(&Vector3::y_axis(), b_deg.to_radians())
        * Rotation3::from_axis_angle(&Vector3::x_axis(), a_deg.to_radians());
    let v = r * Vector3::z();
    [v.x, v.y, v.z]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::domain::clearance::{ClearedPath, OrientedPoint};

    fn tool() -> Tool {
        Tool::from_spec(&"flat-6".parse().expect("spec")).expect("tool")
    }

    fn cell() -> RobotCell {
        RobotCell::viper_s650(Isometry3::translation(420.0, 0.0, 0.0))
    }

    fn path(points: Vec<([f64; 3], [f64; 3], bool)>) -> ClearedPath {
        ClearedPath {
            points: points
                .into_iter()
                .map(|(tip, axis, rapid)| OrientedPoint { tip, axis, rapid, blocked: false })
                .collect(),
            ..ClearedPath::default()
        }
    }

    /// The most positions the arm reaches at `cell` in any one branch and spin, every one of
    /// the 8 x 12 tried (the slow reference of the placement's reach count, which takes the
    /// branch and spin [`choose_branch`] picks on a sample).
    fn most_in_one_branch(arm: &ArmModel, cell: &RobotCell, pts: &[([f64; 3], [f64; 3])]) -> usize {
        use depthmill_geometry::arm::{Elbow, Shoulder, Wrist};
        let mut best = 0;
        for shoulder in [Shoulder::Front, Shoulder::Back] {
            for elbow in [Elbow::Up, Elbow::Down] {
                for wrist in [Wrist::NoFlip, Wrist::Flip] {
                    let ik = IkConfig::only(Configuration { shoulder, elbow, wrist });
                    for k in 0..12 {
                        let spin = (k as f64 * 30.0).to_radians();
                        let n = pts
                            .iter()
                            .filter(|(tip, axis)| {
                                arm.ik_solutions(&cell.target(tip, axis, spin), &ik)
                                    .is_ok_and(|s| !s.is_empty())
                            })
                            .count();
                        best = best.max(n);
                    }
                }
            }
        }
        best
    }

    #[test]
    fn a_part_the_arm_cannot_reach_where_it_stands_by_default_is_placed_where_it_can() {
        let arm = cell().arm_for(&tool());
        // A bar 500 mm long along X, cut upright at its top (z 20) and bottom (z 0).
        let (lo, hi) = ([-250.0, -10.0, 0.0], [250.0, 10.0, 20.0]);
        let pts: Vec<([f64; 3], [f64; 3])> = (0..=50)
            .flat_map(|i| [0.0, 20.0].map(|z| ([-250.0 + 10.0 * i as f64, 0.0, z], [0.0, 0.0, 1.0])))
            .collect();
        let at_default = RobotCell { base_from_part: place(lo, hi, 420.0, 0.0, 0.0), ..cell() };
        let default = reach_count(&arm, &at_default, &pts);
        assert!(default < pts.len(), "the bar's ends are out of reach in one branch by default");
        assert!(default <= most_in_one_branch(&arm, &at_default, &pts));
        let (at, p) = choose_placement(&arm, &cell(), &pts, lo, hi, &|| false).expect("plan").expect("moved");
        assert_eq!((p.reached, p.positions, p.reached_at_default), (pts.len(), pts.len(), default));
        assert!(p.tried > 1);
        assert_eq!(at, place(lo, hi, p.distance_mm, p.yaw_deg, p.height_mm));
        let moved = RobotCell { base_from_part: at, ..cell() };
        assert_eq!(most_in_one_branch(&arm, &moved, &pts), pts.len());
        assert_eq!(reach_count(&arm, &moved, &pts), pts.len());
        // A small part the arm reaches where it stands stays there.
        let small: Vec<([f64; 3], [f64; 3])> =
            pts.iter().filter(|(t, _)| t[0].abs() <= 20.0).copied().collect();
        let small_box = ([-20.0, -10.0, 0.0], [20.0, 10.0, 20.0]);
        assert_eq!(
            choose_placement(&arm, &cell(), &small, small_box.0, small_box.1, &|| false).expect("plan"),
            None
        );
        // Asked to stop, it stops.
        assert_eq!(
            choose_placement(&arm, &cell(), &pts, lo, hi, &|| true).expect_err("cancelled"),
            RobotPlanError::Cancelled
        );
    }

    #[test]
    fn ab_words_round_trip() {
        for (a, b) in [(0.0, 0.0), (10.0, -20.0), (-35.0, 40.0), (25.0, 0.0)] {
            let v = ab_to_axis(a, b);
            let (a2, b2) = axis_to_ab(&v);
            assert!((a - a2).abs() < 1e-9 && (b - b2).abs() < 1e-9, "{a} {b} -> {a2} {b2}");
        }
    }

    #[test]
    fn the_arm_puts_the_tip_and_axis_where_the_program_says() {
        let c = cell();
        let t = tool();
        let mut pts = vec![([0.0, -20.0, 30.0], [0.0, 0.0, 1.0], true)];
        // Leaning up to 20° at 2° per millimetre, then back.
        for i in 0..=40 {
            let y = -20.0 + i as f64;
            let tilt = (2.0 * (10.0 - (i as f64 - 20.0).abs())).max(0.0).to_radians();
            pts.push(([10.0, y, 10.0], [tilt.sin(), 0.0, tilt.cos()], false));
        }
        let prog = robot_program(&c, &t, &path(pts), 600.0, None).expect("program");
        assert!(prog.unreachable.is_empty(), "{:?}", prog.unreachable);
        let arm = c.arm_for(&t);
        for p in &prog.points {
            let world = arm.fk(&p.q_deg);
            let part = c.base_from_part.inverse() * world;
            let tip = part.translation.vector;
            assert!((tip - Vector3::from(p.tip_mm)).norm() < 1e-5, "{tip:?} vs {:?}", p.tip_mm);
            // The tool frame's Z points from the holder to the tip: minus the axis.
            let z = part.rotation * Vector3::z();
            assert!((z + Vector3::from(p.axis)).norm() < 1e-6, "{z:?} vs {:?}", p.axis);
        }
        // One branch throughout.
        let branches: std::collections::HashSet<String> =
            prog.points.iter().map(|p| arm.configuration(&p.q_deg).to_string()).collect();
        assert_eq!(branches.len(), 1, "{branches:?}");
        // Times increase; the 40 mm of feed at 10 mm/s take at least 4 s.
        assert!(prog.points.windows(2).all(|w| w[1].t_s >= w[0].t_s));
        assert!(prog.feed_s >= 4.0 - 1e-9, "{}", prog.feed_s);
        assert!(prog.min_dexterity > 0.0 && prog.min_margins.wrist_deg >= 1.0);
    }

    #[test]
    fn positions_out_of_reach_are_reported_as_stretches() {
        let c = cell();
        let t = tool();
        let mut pts = vec![([0.0, 0.0, 30.0], [0.0, 0.0, 1.0], true)];
        // Feed out to 900 mm from the base: beyond the reach on the way.
        for i in 0..=50 {
            pts.push(([i as f64 * 10.0, 0.0, 10.0], [0.0, 0.0, 1.0], false));
        }
        let prog = robot_program(&c, &t, &path(pts), 600.0, None).expect("program");
        assert!(!prog.unreachable.is_empty());
        let s = &prog.unreachable[0];
        assert!(s.reason.contains("reach"), "{s:?}");
        assert!(s.to_point >= s.from_point);
        // The far end is among the unreachable points, the near ones are fine.
        assert!(!prog.points.last().expect("last").reachable);
        assert!(prog.points[1].reachable);
    }

    #[test]
    fn an_abrupt_turn_of_the_tool_is_split_along_the_line() {
        let c = cell();
        let t = tool();
        let s30 = 30f64.to_radians();
        let mut pts = vec![([0.0, -20.0, 30.0], [0.0, 0.0, 1.0], true)];
        for i in 0..=40 {
            let axis = if i > 20 { [s30.sin(), 0.0, s30.cos()] } else { [0.0, 0.0, 1.0] };
            pts.push(([10.0, -20.0 + i as f64, 10.0], axis, false));
        }
        let prog = robot_program(&c, &t, &path(pts), 600.0, None).expect("program");
        assert!(prog.unreachable.is_empty(), "{:?}", prog.unreachable);
        // The 30° turn over one millimetre is split into steps of at most 2° of any joint, each
        // on the line between the two positions.
        assert!(prog.points.len() > 42 + 5, "{}", prog.points.len());
        let on_line =
            prog.points.iter().position(|p| p.tip_mm == [10.0, -20.0, 10.0]).expect("first feed point");
        for w in prog.points[on_line..].windows(2) {
            let turn = (0..6).map(|j| (w[1].q_deg[j] - w[0].q_deg[j]).abs()).fold(0.0, f64::max);
            assert!(turn <= JOINT_STEP_DEG + 0.5, "{turn}° between {:?} and {:?}", w[0].tip_mm, w[1].tip_mm);
            assert!((w[1].tip_mm[0] - 10.0).abs() < 1e-9 && (w[1].tip_mm[2] - 10.0).abs() < 1e-9);
        }
    }

    #[test]
    fn bad_settings_are_refused() {
        let t = tool();
        let p = path(vec![([0.0; 3], [0.0, 0.0, 1.0], true)]);
        let e =
            robot_program(&RobotCell { speed_frac: 1.5, ..cell() }, &t, &p, 600.0, None).expect_err("speed");
        assert!(e.to_string().contains("speed_frac 1.5"), "{e}");
        let e = robot_program(&cell(), &t, &p, 0.0, None).expect_err("feed");
        assert!(e.to_string().contains("feed_mm_min 0"), "{e}");
        let far = RobotCell::viper_s650(Isometry3::translation(3000.0, 0.0, 0.0));
        let e = robot_program(&far, &t, &p, 600.0, None).expect_err("reach");
        assert!(matches!(e, RobotPlanError::Unreachable { .. }), "{e}");
    }
}
