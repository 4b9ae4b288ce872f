//! The scanning library: simulated devices behind the interfaces real ones sit behind.
//!
//! - [`robot`]: the Adept Viper s650 arm (its model, `depthmill_geometry::arm`, re-exported) and
//!   its simulated motion controller.
//! - [`calibration`]: the cell as it truly is (off its drawing by a profile of errors), what the
//!   software believes, and the calibration from scans of the table top and a reference sphere.
//! - [`chain`]: seed 003, an area scanner in the mill's tool holder, the part on the A axis: the
//!   scanner calibrated against the machine's axes from one calibration point, partial scans
//!   placed by the kinematic chain alone.
//! - [`latch`]: the encoder-latching device: positions of the robot and the table stored at
//!   every scanner sync pulse, with latency and jitter.
//! - [`scanner`]: the SLP-400 class laser line scanner cast at the part's mesh (own BVH):
//!   standoff window, fan, incidence limit, camera occlusion, 35 µm noise, intensity, frame times.
//! - [`table`]: the rotary table's physics (DC motor, 1:480 gearbox, 11520-count encoder, PID on
//!   trapezoidal profiles) and its ASCII protocol; the socket server and client driver are in
//!   [`crate::devices`].
//! - [`scan`]: scan planning (straight passes at a standoff, per table angle, IK-checked) and
//!   execution (dynamic with latched poses, or stop-and-move), the registered cloud, the adaptive
//!   rescan of the holes.

pub mod calibration;
pub mod chain;
pub mod latch;
pub mod robot;
pub mod scan;
pub mod scanner;
pub mod table;
