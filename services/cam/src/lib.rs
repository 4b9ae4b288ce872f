//! CAM service: tool library, tool compensation, roughing and finishing toolpaths, G-code.
//!
//! # Layout
//! - [`domain`]: pure planning code (compensation, strategies, clean-up, G-code, preview).
//! - [`Config`]: listen address, artifact folder, extra tool folder.
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
