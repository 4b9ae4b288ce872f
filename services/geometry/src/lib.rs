//! Plain domain types of depthmill, shared by every service: height maps and their PNG/`.npy`
//! exchange formats, point clouds, poses and frames, tool profiles, artifact references.
//!
//! Units: millimetres and degrees at the API (names say so: `x_mm`, `angle_deg`), radians inside.
//! This crate has no async code, no configuration, no network; its only I/O is the explicit file
//! functions (`HeightMap::read`/`write`, `read_png`, `write_npy`, `ToolProfile::read_tool_file`, ...),
//! each with a stream variant (`*_from`/`*_to`) that does no I/O of its own.
//!
//! # Layout
//!
//! - [`error`]: [`GeometryError`], the crate's one error type.
//! - [`heightmap`]: [`HeightMap`] and [`HeightMapMeta`]; the grid convention (cell corners,
//!   centre samples, row 0 at minimum Y).
//! - [`face`]: [`Face`], the view a map looks from (`+Z`, `-X`, `A=90`, ...).
//! - [`png_io`]: 8/16-bit grayscale PNG with `depthmill:` text metadata; quantisation.
//! - [`npy`]: NumPy `.npy` arrays plus the `MAP.npy.json` sidecar.
//! - [`heightmap_io`]: [`HeightMap::read`]/[`HeightMap::write`] by extension, [`HeightMapFormat`].
//! - [`cloud`]: [`PointCloud`] and [`Aabb`].
//! - [`pose`]: [`Pose`], [`XyzYpr`] (ZYX angles), [`Face::view_from_part`].
//! - [`tool`]: [`ToolProfile`] (solid of revolution) and [`ToolSpec`] (`ball-6`, `v-6-90`, ...).
//! - [`artifact`]: [`ArtifactRef`] and [`MediaType`].

pub mod artifact;
pub mod cloud;
pub mod error;
pub mod face;
pub mod heightmap;
pub mod heightmap_io;
pub mod npy;
pub mod png_io;
pub mod pose;
pub mod tool;

pub use artifact::{ArtifactRef, MediaType};
pub use cloud::{Aabb, PointCloud};
pub use error::GeometryError;
pub use face::Face;
pub use heightmap::{HeightMap, HeightMapMeta, MAX_CELLS};
pub use heightmap_io::HeightMapFormat;
pub use npy::{read_npy, read_npy_from, write_npy, write_npy_to};
pub use png_io::{ImageMapping, PngDepth, read_png, read_png_from, write_png, write_png_to};
pub use pose::{Pose, XyzYpr};
pub use tool::{ToolProfile, ToolSpec};

/// The nalgebra version this crate's types use, re-exported so callers match it.
pub use nalgebra;
