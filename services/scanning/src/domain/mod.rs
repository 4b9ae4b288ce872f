//! The scanning library: simulated devices behind the interfaces real ones sit behind.
//!
//! - [`robot`]: the Adept Viper s650 arm (DH model, forward and inverse kinematics, Jacobian and
//!   dexterity, the scanner bracket) and its simulated motion controller.

pub mod robot;
