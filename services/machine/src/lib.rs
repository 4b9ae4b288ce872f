//! Machine service: G-code interpreter, simulated EMCO mill, material removal, adaptive feed/speed loop.
//!
//! `ExecuteProgram` runs a program on the simulated mill under the job's feed/speed policy and
//! stores the final stock, deviation map, telemetry (CSV and plot) and a report; `Stop`, `Reset`
//! (emergency stop) and `GetStatus` act on the running program. `ExecuteRobot` replays a robot
//! job's joint trajectory on a dexel stock and measures the part against its mesh. See [`domain`].
//!
//! # Layout
//! - [`domain`]: the library (machine profiles so far).
//! - [`Config`]: listen address and artifact folder.
//! - [`serve`]: the gRPC server on a bound listener.
//! - `grpc`, `grpc_robot`: the tonic adapter (the only modules that know proto types).

pub mod domain;
#[cfg(feature = "service")]
mod grpc;
#[cfg(feature = "service")]
mod grpc_robot;
#[cfg(feature = "service")]
mod service;

#[cfg(feature = "service")]
pub use service::*;
