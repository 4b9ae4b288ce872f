//! The robot arm that carries the scanner: an Adept Viper s650 kinematic model ([`kinematics`])
//! and a simulated motion controller with the Initialize/Home/Move/…/Reset/Stop interface of
//! DESIGN §6 ([`controller`]).
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
//!   second). The scanner bracket ([`kinematics::ArmModel::scanner_bracket`]) is a nominal design,
//!   to be replaced by the calibrated transform.
//!
//! # Singularities
//!
//! [`kinematics::SingularityMargins`] measures the distance from the three singular families
//! named in DESIGN §6: wrist (axes 4 and 6 aligned, `q5 = 0`), shoulder/alignment (wrist centre
//! on the axis of joint 1 — axis 6 on axis 1 is a special case) and elbow (arm fully stretched,
//! `q3 = 180° − atan2(295, 90) = 106.97°`). The dexterity `sqrt(det(JᵀJ))` vanishes on all three.

pub mod controller;
pub mod kinematics;

pub use controller::{ControllerState, JointSample, MotionController, RobotError, Status};
pub use kinematics::{
    ArmModel, Configuration, Dh, Elbow, IK_ANGLE_TOLERANCE_RAD, IK_POSITION_TOLERANCE_MM, IkConfig, IkError,
    IkSolution, JointLimit, JointLimitViolation, Shoulder, Singularity, SingularityMargins, Wrist,
};
