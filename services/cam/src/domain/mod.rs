//! CAM domain: pure and synchronous (rayon allowed); no tokio, tonic, proto or I/O beyond explicit
//! file functions.
//!
//! Pipeline: a depth map A and a [`tool::Tool`] -> the compensated tip surface C
//! ([`compensate`]) -> roughing and finishing passes ([`roughing`], [`finishing`]) -> cleaned
//! segments with arcs ([`cleanup`]) -> G-code ([`gcode`]); [`holder`] checks the tool holder,
//! [`feeds`] picks feeds and speeds and estimates time, [`preview`] sweeps the program over the
//! stock to measure gouge and leftover, [`plan`] runs it all. [`slice`] cuts a mesh into planar
//! layers (contours, holes, islands) for layer-by-layer milling, [`layer_passes`] the rings that
//! cut a layer from the stock in to the part, [`clearance`] checks the tool, shank and holder
//! against the mesh and tilts the tool where the upright one collides, and [`robot`] turns the
//! checked path into a joint trajectory of the 6-axis arm with a spindle on its flange;
//! [`robot_job`] holds a robot job's settings, defaults and report.

pub mod cleanup;
pub mod clearance;
pub mod compensate;
pub mod contour;
pub mod error;
pub mod feeds;
pub mod finishing;
pub mod gcode;
pub mod holder;
pub mod layer_passes;
pub mod path;
pub mod plan;
pub mod preview;
pub mod rest;
pub mod robot;
pub mod robot_job;
pub mod roughing;
pub mod slice;
pub mod tool;

pub use error::CamError;
