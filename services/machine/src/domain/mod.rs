//! The machine library: pure domain code, no network, no async.
//!
//! - [`profile`]: [`profile::MachineProfile`], a machine's travel, limits, spindle motor, sensors
//!   and tool table, read from `machines/<name>.toml`.

pub mod profile;
