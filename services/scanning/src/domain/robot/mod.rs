//! The robot arm that carries the scanner: an Adept Viper s650 kinematic model ([`depthmill_geometry::arm`])
//! and a simulated motion controller with the Initialize/Home/Move/…/Reset/Stop interface of
//! DESIGN §6 ([`controller`]).
//!
//! The arm's kinematics (DH table of the Viper s650, frames, IK, singularities, motion times)
//! live in [`depthmill_geometry::arm`], shared with the CAM's robot milling.

pub mod controller;

pub use controller::{ControllerState, JointSample, MotionController, RobotError, Status};
pub use depthmill_geometry::arm::{
    ArmModel, Configuration, Dh, Elbow, IK_ANGLE_TOLERANCE_RAD, IK_POSITION_TOLERANCE_MM, IkConfig, IkError,
    IkSolution, JointLimit, JointLimitViolation, Shoulder, Singularity, SingularityMargins, Wrist,
};
