//! A simulated motion controller for the arm, with the interface of DESIGN §6: Initialize,
//! Uninitialize, IsInitialized, Home, Move (one axis), CoordinatedMove (several), ReadPosition,
//! ReadStatus, Reset (emergency stop) and Stop (one axis), plus [`MotionController::move_pose`]
//! (IK to the nearest solution) and [`MotionController::latch`] (the tool pose for encoder
//! latching).
//!
//! # Simulated time
//!
//! There is no clock inside: every command and every read takes the simulated time `t_s`
//! (seconds). Commands must come in non-decreasing time order; reads may sample any time, past or
//! future, and see the trajectory as planned by the commands issued so far (the scanning
//! simulation samples it at each scanner frame). A command at `t` replaces the planned motion of
//! the axes it touches from `t` on; the history before `t` is kept.
//!
//! # State machine
//!
//! ```text
//!   Uninitialized --Initialize--> Initialized --Home--> Homed --Move/CoordinatedMove/...--> Homed
//!         ^                                                                 |
//!         +------------------------------ Uninitialize --------------------+
//!   any state --Reset--> EmergencyStop (latched) --Initialize--> Initialized (home again)
//! ```
//!
//! - Moves need an initialized, homed controller and no latched emergency stop; `Home` needs an
//!   initialized controller. A refused command changes nothing and is kept as the status's
//!   `last_error` (cleared by Initialize).
//! - **Reset is the emergency stop**, as on a real controller: every axis halts at once (the
//!   simulation freezes the position where it was at the reset time; a real arm's brakes stop it
//!   within a few millimetres) and the stop *latches*: every motion command is refused until
//!   Initialize, which clears the latch but also the homed flag, so the arm must be homed again.
//! - Uninitialize (power off) also freezes every axis where it is and clears the homed flag.
//! - An axis that is still moving refuses a new move ([`RobotError::Busy`]); Stop it first or wait.
//!
//! # Trajectories
//!
//! Every move is a trapezoidal velocity profile per joint (accelerate at the joint's maximum
//! acceleration, cruise, decelerate), a triangle when the distance is too short to reach the
//! cruise speed. The cruise speed is at most `speed_frac` × the joint's top speed; accelerations
//! are always the joint's maximum. A coordinated move is synchronised: it lasts
//! `T = maxⱼ Tⱼ`, the longest single-joint minimum time, and every other joint is re-timed to start
//! and end with it, keeping its acceleration and lowering its cruise speed to
//! `v = 2aD / (aT + √(a²T² − 4aD))` (the root of `D = v·(T − v/a)`). Stop decelerates one axis
//! at its maximum acceleration. Targets are checked against the joint limits before anything moves,
//! and a stopped move never leaves the segment between its start and its target, so positions stay
//! within the limits.

use depthmill_geometry::pose::XyzYpr;
use nalgebra::Isometry3;
use serde::{Deserialize, Serialize};
use thiserror::Error;

use depthmill_geometry::arm::{ArmModel, IkConfig, IkError, JointLimitViolation, Singularity, min_move_time};

/// Below this distance (degrees) an axis is "in position" and a move of it is skipped.
const IN_POSITION_DEG: f64 = 1e-6;

/// Why the controller refused a command.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum RobotError {
    /// The controller is not initialized.
    #[error("{command} refused: the controller is not initialized (call Initialize first)")]
    NotInitialized {
        /// The refused command.
        command: &'static str,
    },
    /// The arm has not been homed since the last Initialize.
    #[error("{command} refused: the arm is not homed (call Home after Initialize)")]
    NotHomed {
        /// The refused command.
        command: &'static str,
    },
    /// An emergency stop (Reset) is latched.
    #[error("{command} refused: emergency stop latched at t = {at_s:.3} s by Reset; Initialize clears it")]
    EstopLatched {
        /// The refused command.
        command: &'static str,
        /// When Reset was issued (s).
        at_s: f64,
    },
    /// A joint target outside its range.
    #[error("target refused: {0}")]
    JointLimit(JointLimitViolation),
    /// A pose target the arm cannot reach (out of reach, no solution within the limits or in the
    /// requested configuration).
    #[error("target refused: {0}")]
    Unreachable(IkError),
    /// A pose target whose every solution is too close to a singularity.
    #[error("target refused: {0}")]
    Singular(Singularity),
    /// A joint the command needs is still moving.
    #[error("{command} refused: joint {joint} is still moving until t = {until_s:.3} s (wait, or Stop it)")]
    Busy {
        /// The refused command.
        command: &'static str,
        /// The moving joint (1-6).
        joint: usize,
        /// When it comes to rest (s).
        until_s: f64,
    },
    /// An argument out of its domain.
    #[error("bad parameter {name} = {value}: expected {expected}")]
    BadParameter {
        /// The argument.
        name: &'static str,
        /// Its value.
        value: String,
        /// What was expected.
        expected: String,
    },
}

impl From<IkError> for RobotError {
    fn from(e: IkError) -> Self {
        match e {
            IkError::Singular(s) => RobotError::Singular(s),
            IkError::InvalidTarget { what } => RobotError::BadParameter {
                name: "target pose",
                value: format!("non-finite {what}"),
                expected: "a finite pose".to_string(),
            },
            other => RobotError::Unreachable(other),
        }
    }
}

/// The controller's state (see the module doc for the transitions).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum ControllerState {
    /// Powered off: only Initialize (and reads) are accepted.
    Uninitialized,
    /// Powered and ready to Home; moves are refused until then.
    Initialized,
    /// Homed: moves are accepted.
    Homed,
    /// Emergency stop latched by Reset; Initialize clears it.
    EmergencyStop,
}

/// What ReadStatus reports.
#[derive(Debug, Clone, PartialEq)]
pub struct Status {
    /// The controller state.
    pub state: ControllerState,
    /// Whether any axis is moving at the sampled time.
    pub moving: bool,
    /// Per axis: at rest on its commanded target (after Stop, the target is where it stops).
    pub in_position: [bool; 6],
    /// The last refused command's error, if any since Initialize.
    pub last_error: Option<RobotError>,
}

/// Joint positions and velocities at one instant.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct JointSample {
    /// Positions (degrees).
    pub position_deg: [f64; 6],
    /// Velocities (°/s).
    pub velocity_deg_s: [f64; 6],
}

/// One constant-acceleration piece of an axis trajectory.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Phase {
    t0: f64,
    p0: f64,
    v0: f64,
    a: f64,
    dur: f64,
}

impl Phase {
    fn at(&self, tau: f64) -> (f64, f64) {
        (self.p0 + self.v0 * tau + 0.5 * self.a * tau * tau, self.v0 + self.a * tau)
    }

    fn end(&self) -> f64 {
        self.t0 + self.dur
    }
}

/// The planned motion of one axis: the position before any phase, the phases in time order, and
/// the rest position after the last phase.
#[derive(Debug, Clone, PartialEq)]
struct Track {
    initial_deg: f64,
    phases: Vec<Phase>,
    rest_deg: f64,
    target_deg: f64,
}

impl Track {
    fn new(q: f64) -> Self {
        Track { initial_deg: q, phases: Vec::new(), rest_deg: q, target_deg: q }
    }

    fn sample(&self, t: f64) -> (f64, f64) {
        let idx = self.phases.partition_point(|p| p.t0 <= t);
        if idx == 0 {
            return (if self.phases.is_empty() { self.rest_deg } else { self.initial_deg }, 0.0);
        }
        let ph = &self.phases[idx - 1];
        let tau = t - ph.t0;
        if tau < ph.dur {
            ph.at(tau)
        } else if idx == self.phases.len() {
            (self.rest_deg, 0.0)
        } else {
            (ph.at(ph.dur).0, 0.0)
        }
    }

    fn end_time(&self) -> f64 {
        self.phases.last().map_or(f64::NEG_INFINITY, Phase::end)
    }

    fn moving_at(&self, t: f64) -> bool {
        t < self.end_time()
    }

    /// Cuts the plan at `t` (keeping the history) and returns the position and velocity there.
    fn truncate(&mut self, t: f64) -> (f64, f64) {
        let (p, v) = self.sample(t);
        self.phases.retain(|ph| ph.t0 < t);
        if let Some(last) = self.phases.last_mut()
            && t < last.end()
        {
            last.dur = t - last.t0;
        }
        self.rest_deg = p;
        (p, v)
    }

    /// Halts at `t` where the axis is (emergency stop, power off).
    fn freeze(&mut self, t: f64) {
        let (p, _) = self.truncate(t);
        self.target_deg = p;
    }
}

/// The phases moving `p0 → p0 + dist` from rest to rest in exactly `total` seconds (≥ the minimum
/// time) with acceleration `a`: trapezoid with the cruise speed that fits (see the module doc).
fn timed_profile(t0: f64, p0: f64, dist: f64, a: f64, total: f64) -> Vec<Phase> {
    let d = dist.abs();
    if d == 0.0 || total <= 0.0 {
        return Vec::new();
    }
    let sign = dist.signum();
    let disc = (a * a * total * total - 4.0 * a * d).max(0.0);
    let v = 2.0 * a * d / (a * total + disc.sqrt());
    let ta = (v / a).min(total / 2.0);
    let tc = (total - 2.0 * ta).max(0.0);
    let mut phases = Vec::with_capacity(3);
    let accel = Phase { t0, p0, v0: 0.0, a: sign * a, dur: ta };
    let (p1, v1) = accel.at(ta);
    phases.push(accel);
    let (mut p2, mut t2) = (p1, t0 + ta);
    if tc > 0.0 {
        let cruise = Phase { t0: t2, p0: p1, v0: v1, a: 0.0, dur: tc };
        p2 = cruise.at(tc).0;
        t2 = cruise.end();
        phases.push(cruise);
    }
    // The last phase ends at exactly t0 + total so that all joints of a move finish together.
    phases.push(Phase { t0: t2, p0: p2, v0: v1, a: -sign * a, dur: (t0 + total - t2).max(0.0) });
    phases
}

/// The simulated six-axis motion controller (see the module doc).
#[derive(Debug, Clone)]
pub struct MotionController {
    model: ArmModel,
    home_deg: [f64; 6],
    ik_config: IkConfig,
    tracks: [Track; 6],
    initialized: bool,
    homed: bool,
    estop_at_s: Option<f64>,
    last_command_s: f64,
    last_error: Option<RobotError>,
}

fn bad(name: &'static str, value: impl ToString, expected: impl ToString) -> RobotError {
    RobotError::BadParameter { name, value: value.to_string(), expected: expected.to_string() }
}

impl MotionController {
    /// A powered-off controller for `model` with the arm standing at `start_deg`; homes to
    /// [`ArmModel::HOME_DEG`] and solves poses with [`IkConfig::default`].
    pub fn new(model: ArmModel, start_deg: [f64; 6]) -> Result<Self, RobotError> {
        for (i, l) in model.limits.iter().enumerate() {
            let ok = l.min_deg.is_finite()
                && l.max_deg.is_finite()
                && l.min_deg < l.max_deg
                && l.max_speed_deg_s.is_finite()
                && l.max_speed_deg_s > 0.0
                && l.max_accel_deg_s2.is_finite()
                && l.max_accel_deg_s2 > 0.0;
            if !ok {
                return Err(bad(
                    "limits",
                    format!("joint {}: {l:?}", i + 1),
                    "finite min < max and positive top speed and acceleration",
                ));
            }
        }
        Self::check_joints(&model, &start_deg)?;
        Self::check_joints(&model, &ArmModel::HOME_DEG)?;
        Ok(MotionController {
            tracks: start_deg.map(Track::new),
            model,
            home_deg: ArmModel::HOME_DEG,
            ik_config: IkConfig::default(),
            initialized: false,
            homed: false,
            estop_at_s: None,
            last_command_s: 0.0,
            last_error: None,
        })
    }

    /// The Viper s650 with the scanner bracket, standing at Adept's READY pose, powered off.
    pub fn viper_s650() -> Self {
        let model = ArmModel::viper_s650();
        let tracks = ArmModel::READY_DEG.map(Track::new);
        MotionController {
            model,
            home_deg: ArmModel::HOME_DEG,
            ik_config: IkConfig::default(),
            tracks,
            initialized: false,
            homed: false,
            estop_at_s: None,
            last_command_s: 0.0,
            last_error: None,
        }
    }

    /// Uses `home_deg` as the home position (checked against the limits).
    pub fn with_home(mut self, home_deg: [f64; 6]) -> Result<Self, RobotError> {
        Self::check_joints(&self.model, &home_deg)?;
        self.home_deg = home_deg;
        Ok(self)
    }

    /// Sets the IK configuration [`MotionController::move_pose`] uses.
    pub fn set_ik_config(&mut self, config: IkConfig) {
        self.ik_config = config;
    }

    /// The arm model.
    pub fn model(&self) -> &ArmModel {
        &self.model
    }

    /// Sets the tool frame (`flange_from_tool`) poses are reported and solved in, as a
    /// controller's TCP is set after the tool is measured; joint motion is unaffected.
    pub fn set_tool(&mut self, tool: nalgebra::Isometry3<f64>) {
        self.model.tool = tool;
    }

    /// The home position (degrees).
    pub fn home_deg(&self) -> [f64; 6] {
        self.home_deg
    }

    /// The current state.
    pub fn state(&self) -> ControllerState {
        if self.estop_at_s.is_some() {
            ControllerState::EmergencyStop
        } else if !self.initialized {
            ControllerState::Uninitialized
        } else if self.homed {
            ControllerState::Homed
        } else {
            ControllerState::Initialized
        }
    }

    fn check_joints(model: &ArmModel, q: &[f64; 6]) -> Result<(), RobotError> {
        if let Some(i) = q.iter().position(|v| !v.is_finite()) {
            return Err(bad("joint position", format!("joint {} = {}", i + 1, q[i]), "a finite angle"));
        }
        model.check_limits(q).map_err(RobotError::JointLimit)
    }

    /// Records a refusal as the last error.
    fn record<T>(&mut self, r: Result<T, RobotError>) -> Result<T, RobotError> {
        if let Err(e) = &r {
            self.last_error = Some(e.clone());
        }
        r
    }

    /// Validates a command time and advances the command clock.
    fn command_time(&mut self, t_s: f64) -> Result<f64, RobotError> {
        if !t_s.is_finite() || t_s < self.last_command_s {
            return Err(bad(
                "t_s",
                t_s,
                format!("a finite time not before the previous command at {} s", self.last_command_s),
            ));
        }
        self.last_command_s = t_s;
        Ok(t_s)
    }

    fn check_read_time(t_s: f64) -> Result<(), RobotError> {
        if t_s.is_finite() { Ok(()) } else { Err(bad("t_s", t_s, "a finite time")) }
    }

    fn ready_for_motion(&self, command: &'static str, need_home: bool) -> Result<(), RobotError> {
        if let Some(at_s) = self.estop_at_s {
            return Err(RobotError::EstopLatched { command, at_s });
        }
        if !self.initialized {
            return Err(RobotError::NotInitialized { command });
        }
        if need_home && !self.homed {
            return Err(RobotError::NotHomed { command });
        }
        Ok(())
    }

    fn axis_index(axis: usize) -> Result<usize, RobotError> {
        if (1..=6).contains(&axis) { Ok(axis - 1) } else { Err(bad("axis", axis, "a joint number 1 to 6")) }
    }

    fn check_speed(speed_frac: f64) -> Result<(), RobotError> {
        if speed_frac.is_finite() && speed_frac > 0.0 && speed_frac <= 1.0 {
            Ok(())
        } else {
            Err(bad("speed_frac", speed_frac, "a fraction of the top speed in (0, 1]"))
        }
    }

    /// Initialize: powers the arm, clears a latched emergency stop (and with it the homed flag)
    /// and the last error. Idempotent when already initialized.
    pub fn initialize(&mut self, t_s: f64) -> Result<(), RobotError> {
        let r = self.command_time(t_s);
        self.record(r)?;
        if self.estop_at_s.take().is_some() || !self.initialized {
            self.homed = false;
        }
        self.initialized = true;
        self.last_error = None;
        Ok(())
    }

    /// Uninitialize: powers the arm off; every axis halts where it is and the homed flag clears.
    pub fn uninitialize(&mut self, t_s: f64) -> Result<(), RobotError> {
        let r = self.command_time(t_s);
        let t = self.record(r)?;
        for track in &mut self.tracks {
            track.freeze(t);
        }
        self.initialized = false;
        self.homed = false;
        Ok(())
    }

    /// IsInitialized: powered and no emergency stop latched.
    pub fn is_initialized(&self) -> bool {
        self.initialized && self.estop_at_s.is_none()
    }

    /// Home: a coordinated move to the home position at `speed_frac` of the top speeds; the arm
    /// counts as homed from now on (moves are refused as busy until it arrives). Returns the
    /// arrival time (s).
    pub fn home(&mut self, t_s: f64, speed_frac: f64) -> Result<f64, RobotError> {
        let r = self.command_time(t_s).and_then(|t| {
            self.ready_for_motion("Home", false)?;
            let targets: Vec<(usize, f64)> = self.home_deg.iter().copied().enumerate().collect();
            self.start_move("Home", t, &targets, speed_frac)
        });
        let end = self.record(r)?;
        self.homed = true;
        Ok(end)
    }

    /// Move: one axis (1-6) to `target_deg` at `speed_frac` of its top speed. Returns the arrival
    /// time (s).
    pub fn move_joint(
        &mut self,
        t_s: f64,
        axis: usize,
        target_deg: f64,
        speed_frac: f64,
    ) -> Result<f64, RobotError> {
        let r = self.command_time(t_s).and_then(|t| {
            self.ready_for_motion("Move", true)?;
            let i = Self::axis_index(axis)?;
            self.start_move("Move", t, &[(i, target_deg)], speed_frac)
        });
        self.record(r)
    }

    /// CoordinatedMove: several axes `(axis 1-6, target_deg)`, synchronised to start and end
    /// together. Returns the arrival time (s).
    pub fn coordinated_move(
        &mut self,
        t_s: f64,
        targets: &[(usize, f64)],
        speed_frac: f64,
    ) -> Result<f64, RobotError> {
        let r = self.command_time(t_s).and_then(|t| {
            self.ready_for_motion("CoordinatedMove", true)?;
            let mut indexed = Vec::with_capacity(targets.len());
            for &(axis, q) in targets {
                let i = Self::axis_index(axis)?;
                if indexed.iter().any(|&(j, _)| j == i) {
                    return Err(bad(
                        "targets",
                        format!("joint {axis} given twice"),
                        "each joint at most once",
                    ));
                }
                indexed.push((i, q));
            }
            self.start_move("CoordinatedMove", t, &indexed, speed_frac)
        });
        self.record(r)
    }

    /// CoordinatedMove of all six joints to `target_deg`. Returns the arrival time (s).
    pub fn move_joints(
        &mut self,
        t_s: f64,
        target_deg: &[f64; 6],
        speed_frac: f64,
    ) -> Result<f64, RobotError> {
        let targets: Vec<(usize, f64)> = target_deg.iter().enumerate().map(|(i, q)| (i + 1, *q)).collect();
        self.coordinated_move(t_s, &targets, speed_frac)
    }

    /// A coordinated move to the tool pose `target` (`world_from_tool`): the IK solution nearest
    /// the current joints ([`ArmModel::ik_nearest`] with the controller's [`IkConfig`]). Returns
    /// the arrival time (s).
    pub fn move_pose(
        &mut self,
        t_s: f64,
        target: &Isometry3<f64>,
        speed_frac: f64,
    ) -> Result<f64, RobotError> {
        let r = self.command_time(t_s).and_then(|t| {
            self.ready_for_motion("MovePose", true)?;
            Self::check_speed(speed_frac)?;
            self.check_idle("MovePose", t, 0..6)?;
            let here = self.positions_at(t);
            let solution = self.model.ik_nearest(target, &here, &self.ik_config)?;
            let targets: Vec<(usize, f64)> = solution.q_deg.iter().copied().enumerate().collect();
            self.start_move("MovePose", t, &targets, speed_frac)
        });
        self.record(r)
    }

    fn check_idle(
        &self,
        command: &'static str,
        t: f64,
        axes: impl IntoIterator<Item = usize>,
    ) -> Result<(), RobotError> {
        for i in axes {
            if self.tracks[i].moving_at(t) {
                return Err(RobotError::Busy { command, joint: i + 1, until_s: self.tracks[i].end_time() });
            }
        }
        Ok(())
    }

    fn positions_at(&self, t: f64) -> [f64; 6] {
        std::array::from_fn(|i| self.tracks[i].sample(t).0)
    }

    /// Plans a synchronised move of `targets` (0-based axis, degrees) starting at `t`; all checks
    /// first, then the tracks change.
    fn start_move(
        &mut self,
        command: &'static str,
        t: f64,
        targets: &[(usize, f64)],
        speed_frac: f64,
    ) -> Result<f64, RobotError> {
        Self::check_speed(speed_frac)?;
        for &(i, q) in targets {
            if !q.is_finite() {
                return Err(bad("target_deg", format!("joint {} = {q}", i + 1), "a finite angle"));
            }
            self.model.limits[i].check(i + 1, q).map_err(RobotError::JointLimit)?;
        }
        self.check_idle(command, t, targets.iter().map(|&(i, _)| i))?;
        let mut total: f64 = 0.0;
        for &(i, q) in targets {
            let l = &self.model.limits[i];
            let d = (q - self.tracks[i].sample(t).0).abs();
            if d > IN_POSITION_DEG {
                total = total.max(min_move_time(d, l.max_speed_deg_s * speed_frac, l.max_accel_deg_s2));
            }
        }
        for &(i, q) in targets {
            let a = self.model.limits[i].max_accel_deg_s2;
            let track = &mut self.tracks[i];
            let (p0, _) = track.truncate(t);
            if (q - p0).abs() > IN_POSITION_DEG {
                track.phases.extend(timed_profile(t, p0, q - p0, a, total));
            }
            track.rest_deg = q;
            track.target_deg = q;
        }
        Ok(t + total)
    }

    /// ReadPosition: joint positions (degrees) at simulated time `t_s`.
    pub fn read_position(&self, t_s: f64) -> Result<[f64; 6], RobotError> {
        Self::check_read_time(t_s)?;
        Ok(self.positions_at(t_s))
    }

    /// Joint positions and velocities at simulated time `t_s`.
    pub fn sample(&self, t_s: f64) -> Result<JointSample, RobotError> {
        Self::check_read_time(t_s)?;
        let s: [(f64, f64); 6] = std::array::from_fn(|i| self.tracks[i].sample(t_s));
        Ok(JointSample { position_deg: s.map(|x| x.0), velocity_deg_s: s.map(|x| x.1) })
    }

    /// ReadStatus: state, motion and in-position flags at `t_s`, and the last refusal.
    pub fn read_status(&self, t_s: f64) -> Result<Status, RobotError> {
        Self::check_read_time(t_s)?;
        let in_position = std::array::from_fn(|i| {
            let tr = &self.tracks[i];
            !tr.moving_at(t_s) && (tr.sample(t_s).0 - tr.target_deg).abs() < IN_POSITION_DEG
        });
        Ok(Status {
            state: self.state(),
            moving: self.tracks.iter().any(|tr| tr.moving_at(t_s)),
            in_position,
            last_error: self.last_error.clone(),
        })
    }

    /// Reset, the emergency stop: every axis halts at `t_s` where it is, and the stop latches
    /// until Initialize. Accepted in every state.
    pub fn reset(&mut self, t_s: f64) -> Result<(), RobotError> {
        let r = self.command_time(t_s);
        let t = self.record(r)?;
        for track in &mut self.tracks {
            track.freeze(t);
        }
        if self.estop_at_s.is_none() {
            self.estop_at_s = Some(t);
        }
        Ok(())
    }

    /// Stop: decelerates `axis` (1-6) to rest at its maximum acceleration; its target becomes the
    /// rest position. Returns when it is at rest (s); a no-op for an axis at rest.
    pub fn stop(&mut self, t_s: f64, axis: usize) -> Result<f64, RobotError> {
        let r = self.command_time(t_s).and_then(|t| Ok((t, Self::axis_index(axis)?)));
        let (t, i) = self.record(r)?;
        let a = self.model.limits[i].max_accel_deg_s2;
        let track = &mut self.tracks[i];
        if !track.moving_at(t) {
            return Ok(t);
        }
        let (p, v) = track.truncate(t);
        if v == 0.0 {
            track.target_deg = p;
            return Ok(t);
        }
        let dur = v.abs() / a;
        let decel = Phase { t0: t, p0: p, v0: v, a: -v.signum() * a, dur };
        track.rest_deg = decel.at(dur).0;
        track.target_deg = track.rest_deg;
        track.phases.push(decel);
        Ok(t + dur)
    }

    /// The tool pose (`world_from_tool`) at `t_s` as X, Y, Z, yaw, pitch, roll — what the encoder
    /// latch reports at a sync pulse.
    pub fn latch(&self, t_s: f64) -> Result<XyzYpr, RobotError> {
        let q = self.read_position(t_s)?;
        Ok(XyzYpr::from_pose(&self.model.fk(&q)))
    }
}

#[cfg(test)]
mod tests {
    use rand::rngs::StdRng;
    use rand::{Rng, SeedableRng};

    use super::*;
    use depthmill_geometry::arm::pose_distance;

    /// Initialized and homed at t = 0 with the home move finished; returns the time it finished.
    fn ready() -> (MotionController, f64) {
        let mut c = MotionController::viper_s650();
        c.initialize(0.0).expect("init");
        let t = c.home(0.0, 1.0).expect("home");
        (c, t)
    }

    /// Reference: the textbook minimum time of a rest-to-rest trapezoid.
    fn trapezoid_time(d: f64, v: f64, a: f64) -> f64 {
        let t_acc = v / a;
        let d_acc = 0.5 * a * t_acc * t_acc;
        if 2.0 * d_acc <= d { 2.0 * t_acc + (d - 2.0 * d_acc) / v } else { 2.0 * (d / a).sqrt() }
    }

    #[test]
    fn coordinated_move_timing() {
        let (mut c, t0) = ready();
        let start = c.read_position(t0).expect("pos");
        let target = [30.0, -60.0, 150.0, -40.0, 60.0, 200.0];
        let frac = 0.5;
        let end = c.move_joints(t0, &target, frac).expect("move");
        let expect = (0..6)
            .map(|i| {
                let l = &c.model().limits[i];
                trapezoid_time((target[i] - start[i]).abs(), l.max_speed_deg_s * frac, l.max_accel_deg_s2)
            })
            .fold(0.0, f64::max);
        assert!((end - t0 - expect).abs() < 1e-9, "{} vs {expect}", end - t0);
        // Every joint that moves is still moving just before the end and at rest on target after it.
        let before = c.sample(end - 1e-4).expect("sample");
        let after = c.sample(end).expect("sample");
        for (i, goal) in target.iter().enumerate() {
            assert!(before.velocity_deg_s[i].abs() > 0.0, "joint {} finished early", i + 1);
            assert!((after.position_deg[i] - goal).abs() < 1e-9);
            assert_eq!(after.velocity_deg_s[i], 0.0);
        }
        let s = c.read_status(end - 0.01).expect("status");
        assert!(s.moving && s.in_position.iter().all(|p| !p));
        let s = c.read_status(end + 0.01).expect("status");
        assert!(!s.moving && s.in_position.iter().all(|p| *p) && s.state == ControllerState::Homed);
        // Start together: every joint has moved shortly after the start.
        let early = c.read_position(t0 + 1e-3).expect("pos");
        assert!((0..6).all(|i| early[i] != start[i]));
    }

    #[test]
    fn speed_and_acceleration_limits_hold_on_dense_samples() {
        let (mut c, mut t) = ready();
        let mut rng = StdRng::seed_from_u64(21);
        for _ in 0..6 {
            let target: [f64; 6] = std::array::from_fn(|i| {
                let l = &c.model().limits[i];
                rng.random_range(l.min_deg..l.max_deg)
            });
            let frac = rng.random_range(0.1..=1.0);
            let end = c.move_joints(t, &target, frac).expect("move");
            let h = 5e-4;
            let mut s = t;
            while s < end {
                let (pm, p0, pp) = (
                    c.read_position(s - h).expect("p"),
                    c.read_position(s).expect("p"),
                    c.read_position(s + h).expect("p"),
                );
                let v = c.sample(s).expect("v").velocity_deg_s;
                for i in 0..6 {
                    let l = &c.model().limits[i];
                    let vmax = l.max_speed_deg_s * frac;
                    assert!(v[i].abs() <= vmax * (1.0 + 1e-9), "joint {} speed {} > {vmax}", i + 1, v[i]);
                    assert!(((pp[i] - p0[i]) / h).abs() <= vmax * (1.0 + 1e-9) + 1e-6);
                    let acc = (pp[i] - 2.0 * p0[i] + pm[i]) / (h * h);
                    assert!(
                        acc.abs() <= l.max_accel_deg_s2 * (1.0 + 1e-6) + 1e-3,
                        "joint {} accel {acc}",
                        i + 1
                    );
                    assert!(l.contains(p0[i]));
                }
                s += h;
            }
            t = end;
        }
    }

    #[test]
    fn reset_mid_move_freezes_and_latches() {
        let (mut c, t0) = ready();
        let end = c.move_joints(t0, &[60.0, -40.0, 120.0, 30.0, 30.0, 90.0], 1.0).expect("move");
        let t_reset = t0 + 0.5 * (end - t0);
        let at_reset = c.read_position(t_reset).expect("pos");
        c.reset(t_reset).expect("reset");
        assert_eq!(c.read_position(t_reset + 5.0).expect("pos"), at_reset);
        assert_eq!(c.sample(t_reset + 1e-6).expect("s").velocity_deg_s, [0.0; 6]);
        // History before the reset is kept.
        assert_ne!(c.read_position(t_reset - 0.1).expect("pos"), at_reset);
        let s = c.read_status(t_reset + 1.0).expect("status");
        assert_eq!(s.state, ControllerState::EmergencyStop);
        assert!(!s.moving && !c.is_initialized());
        // Latched: moves and Home are refused until Initialize.
        let e = c.move_joint(t_reset + 1.0, 1, 0.0, 0.5).expect_err("latched");
        assert_eq!(e, RobotError::EstopLatched { command: "Move", at_s: t_reset });
        assert!(e.to_string().contains("emergency stop latched"), "{e}");
        assert!(matches!(c.home(t_reset + 1.0, 0.5), Err(RobotError::EstopLatched { .. })));
        assert_eq!(
            c.read_status(t_reset + 1.0).expect("s").last_error,
            Some(RobotError::EstopLatched { command: "Home", at_s: t_reset })
        );
        // Initialize clears the latch but the arm must be homed again.
        c.initialize(t_reset + 2.0).expect("init");
        assert_eq!(c.state(), ControllerState::Initialized);
        assert!(matches!(c.move_joint(t_reset + 2.0, 1, 0.0, 0.5), Err(RobotError::NotHomed { .. })));
        let home_end = c.home(t_reset + 2.0, 1.0).expect("home");
        assert_eq!(c.read_position(home_end).expect("pos"), ArmModel::HOME_DEG);
    }

    #[test]
    fn stop_decelerates_within_the_acceleration_limit() {
        let (mut c, t0) = ready();
        let end = c.coordinated_move(t0, &[(1, 150.0), (3, 60.0)], 1.0).expect("move");
        let t_stop = t0 + 0.4 * (end - t0);
        let before = c.sample(t_stop).expect("s");
        let v = before.velocity_deg_s[0];
        assert!(v > 0.0);
        let a = c.model().limits[0].max_accel_deg_s2;
        let rest_t = c.stop(t_stop, 1).expect("stop");
        assert!((rest_t - t_stop - v / a).abs() < 1e-12);
        let rest = c.read_position(rest_t + 1.0).expect("pos")[0];
        assert!((rest - (before.position_deg[0] + v * v / (2.0 * a))).abs() < 1e-9);
        assert!(rest < 150.0);
        let h = 1e-4;
        let mut s = t_stop;
        while s < rest_t + 0.01 {
            let p: Vec<f64> = [s - h, s, s + h].iter().map(|t| c.read_position(*t).expect("p")[0]).collect();
            let acc = (p[2] - 2.0 * p[1] + p[0]) / (h * h);
            assert!(acc.abs() <= a * (1.0 + 1e-6) + 1e-3, "{acc}");
            s += h;
        }
        // Joint 3 carries on to its target; joint 1 is in position at its new rest.
        assert!((c.read_position(end).expect("p")[2] - 60.0).abs() < 1e-9);
        let st = c.read_status(end + 0.1).expect("status");
        assert!(st.in_position[0] && st.in_position[2] && !st.moving);
        // Stopping an axis at rest is a no-op.
        assert_eq!(c.stop(end + 0.2, 2).expect("noop"), end + 0.2);
    }

    #[test]
    fn refusals_say_what_and_why() {
        let mut c = MotionController::viper_s650();
        let e = c.move_joint(0.0, 1, 10.0, 0.5).expect_err("not initialized");
        assert_eq!(e.to_string(), "Move refused: the controller is not initialized (call Initialize first)");
        assert!(matches!(c.home(0.0, 1.0), Err(RobotError::NotInitialized { .. })));
        c.initialize(0.0).expect("init");
        assert!(c.is_initialized());
        let e = c.coordinated_move(0.0, &[(1, 10.0)], 0.5).expect_err("not homed");
        assert_eq!(
            e.to_string(),
            "CoordinatedMove refused: the arm is not homed (call Home after Initialize)"
        );
        let home_end = c.home(0.0, 1.0).expect("home");
        // READY → HOME turns joint 5 only.
        let e = c.move_joint(home_end / 2.0, 5, 10.0, 0.5).expect_err("busy");
        assert!(matches!(e, RobotError::Busy { joint: 5, .. }), "{e:?}");
        let t = home_end;
        let e = c.move_joint(t, 3, 261.2, 0.5).expect_err("limit");
        assert_eq!(e.to_string(), "target refused: joint 3 = 261.2° is outside [-29.0°, 256.0°]");
        assert_eq!(c.read_status(t).expect("s").last_error, Some(e));
        let e = c.move_joint(t, 7, 0.0, 0.5).expect_err("axis");
        assert_eq!(e.to_string(), "bad parameter axis = 7: expected a joint number 1 to 6");
        assert!(matches!(
            c.move_joint(t, 1, 0.0, 0.0),
            Err(RobotError::BadParameter { name: "speed_frac", .. })
        ));
        assert!(matches!(c.move_joint(t, 1, f64::NAN, 0.5), Err(RobotError::BadParameter { .. })));
        assert!(matches!(
            c.coordinated_move(t, &[(2, -80.0), (2, -70.0)], 0.5),
            Err(RobotError::BadParameter { name: "targets", .. })
        ));
        let e = c.move_joint(t - 1.0, 1, 0.0, 0.5).expect_err("time backwards");
        assert!(e.to_string().contains("not before the previous command"), "{e}");
        // Nothing moved through all those refusals.
        assert_eq!(c.read_position(t + 10.0).expect("pos"), ArmModel::HOME_DEG);
        // Power off freezes and needs Initialize + Home again.
        let end = c.move_joint(t, 1, 90.0, 1.0).expect("move");
        c.uninitialize((t + end) / 2.0).expect("off");
        let frozen = c.read_position(end).expect("pos")[0];
        assert!(frozen > 0.0 && frozen < 90.0);
        assert_eq!(c.state(), ControllerState::Uninitialized);
        assert!(matches!(c.move_joint(end, 1, 0.0, 1.0), Err(RobotError::NotInitialized { .. })));
    }

    #[test]
    fn move_pose_goes_to_the_nearest_solution_and_latch_reports_it() {
        let (mut c, t0) = ready();
        let q_goal = [20.0, -80.0, 160.0, 10.0, 70.0, -30.0];
        let goal = c.model().fk(&q_goal);
        let end = c.move_pose(t0, &goal, 0.8).expect("move_pose");
        let q = c.read_position(end).expect("pos");
        assert!(q.iter().zip(&q_goal).all(|(a, b)| (a - b).abs() < 1e-6), "{q:?}");
        let latched = c.latch(end).expect("latch");
        let pose = latched.to_pose().expect("finite");
        let (dp, da) = pose_distance(&pose, &goal);
        assert!(dp < 1e-6 && da < 1e-9, "{dp} {da}");
        // Mid-move the latch follows the joints.
        let mid = (t0 + end) / 2.0;
        let expect = XyzYpr::from_pose(&c.model().fk(&c.read_position(mid).expect("pos")));
        assert_eq!(c.latch(mid).expect("latch"), expect);
        // Out of reach, refused with the distance and the reach.
        let far = Isometry3::translation(1500.0, 0.0, 300.0);
        let e = c.move_pose(end, &far, 0.5).expect_err("far");
        assert!(matches!(e, RobotError::Unreachable(IkError::OutOfReach { .. })), "{e:?}");
        assert!(e.to_string().contains("is beyond the reach 578.4 mm"), "{e}");
        // Singular targets are refused with the margin: the wrist centre on the axis of joint 1.
        let singular = c.model().fk(&ArmModel::viper_wrist_on_joint1_axis_deg());
        let e = c.move_pose(end, &singular, 0.5).expect_err("singular");
        assert!(matches!(e, RobotError::Singular(Singularity::Shoulder { .. })), "{e:?}");
        assert!(e.to_string().starts_with("target refused: shoulder singularity"), "{e}");
    }
}
