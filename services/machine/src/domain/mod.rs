//! The machine library: pure domain code, no network, no async.
//!
//! - [`profile`]: [`profile::MachineProfile`], a machine's travel, limits, spindle motor, sensors
//!   and tool table, read from `machines/<name>.toml`.
//! - [`gcode`]: the streaming G-code interpreter emitting canonical machine commands, and the
//!   side-by-side check against LinuxCNC's `rs274`.
//! - [`cutting`]: Kienzle materials, chip thickness, torque and power of a revolution.
//! - [`sensors`]: torque ADC, current sensor and speed encoder with resolution and noise.
//! - [`removal`]: the stock as a Z-map and the exact sweep of a tool of revolution along lines
//!   and arcs (material removal per revolution, engagement, hardness field).
//! - [`sim`]: the simulated mill running a program: motion with acceleration and blending,
//!   removal, forces and sensors per revolution, the feed/speed policy, telemetry.
//! - [`dexel`]: the one stock of a multi-axis part as tri-dexels, cut at any tool orientation;
//!   distances to its surface and its surface as a closed mesh.
//! - [`part`]: the simulated part measured against the original part (reference points) and
//!   against the part opened by the tools.
//! - [`job`]: the execute stage as one call: tools, stock, runs with and without adaptation,
//!   deviation from the target, telemetry CSV and plot.
//! - [`adaptive`]: the seed's adaptive feed/speed loop, the feed-only baseline, the productivity
//!   index.

pub mod adaptive;
pub mod cutting;
pub mod dexel;
pub mod gcode;
pub mod job;
pub mod part;
pub mod profile;
pub mod removal;
pub mod robot;
pub mod sensors;
pub mod sim;
