//! The machine library: pure domain code, no network, no async.
//!
//! - [`profile`]: [`profile::MachineProfile`], a machine's travel, limits, spindle motor, sensors
//!   and tool table, read from `machines/<name>.toml`.
//! - [`gcode`]: the streaming G-code interpreter emitting canonical machine commands, and the
//!   side-by-side check against LinuxCNC's `rs274`.
//! - [`cutting`]: Kienzle materials, chip thickness, torque and power of a revolution.
//! - [`sensors`]: torque ADC, current sensor and speed encoder with resolution and noise.
//! - [`adaptive`]: the seed's adaptive feed/speed loop, the feed-only baseline, the productivity
//!   index.

pub mod adaptive;
pub mod cutting;
pub mod gcode;
pub mod profile;
pub mod sensors;
