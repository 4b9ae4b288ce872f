//! Plain domain types of depthmill and the formats they travel in, shared by every service:
//! height maps and their PNG/`.npy` exchange formats, point clouds and meshes with their readers
//! and writers (XYZ, PLY, STL), the rasterisers that turn both into height maps, poses and frames,
//! tool profiles, artifact references. Every stage service builds on this crate and none on
//! another stage service, so a format or a mesh has one home.
//!
//! Units: millimetres and degrees at the API (names say so: `x_mm`, `angle_deg`), radians inside.
//! This crate has no async code, no configuration, no network; its only I/O is the explicit file
//! functions (`HeightMap::read`/`write`, `read_png`, `write_npy`, `ToolProfile::read_tool_file`, ...),
//! each with a stream variant (`*_from`/`*_to`) that does no I/O of its own.
//!
//! # Layout
//!
//! - [`error`]: [`GeometryError`], the error type of the plain types ([`formats`] and [`raster`]
//!   have their own: [`FormatError`] names files, lines and bytes; [`RasterError`] parameters).
//! - [`heightmap`]: [`HeightMap`] and [`HeightMapMeta`]; the grid convention (cell corners,
//!   centre samples, row 0 at minimum Y).
//! - [`face`]: [`Face`], the view a map looks from (`+Z`, `-X`, `A=90`, ...).
//! - [`png_io`]: 8/16-bit grayscale PNG with `depthmill:` text metadata; quantisation.
//! - [`npy`]: NumPy `.npy` arrays plus the `MAP.npy.json` sidecar.
//! - [`heightmap_io`]: [`HeightMap::read`]/[`HeightMap::write`] by extension, [`HeightMapFormat`].
//! - [`cloud`]: [`PointCloud`] (single-precision points, read through [`CloudPoint`]) and [`Aabb`]; [`mesh`]: [`Mesh`], an indexed triangle mesh.
//! - [`formats`]: streaming readers of XYZ, PLY (ascii and binary) and STL (ascii and binary) with
//!   [`formats::ReadLimits`], format sniffing, and the PLY and STL writers.
//! - [`raster`]: point clouds to height maps (max-Z binning, enclosed-hole filling, coverage);
//!   [`mesh_raster`]: a mesh's exact top surface at cell centres (z-buffer).
//! - [`pass_align`]: each pass of a cloud moved by the translation that lays it on the surface
//!   the whole cloud describes (a calibration's residual between the passes).
//! - [`surface_fit`]: a cloud to a height map by a robust local quadric fit (the unbiased
//!   finishing target).
//! - [`sample`]: the generated sample part (a relief) of the demo, the tests and the benches.
//! - [`pose`]: [`Pose`], [`XyzYpr`] (ZYX angles), [`Face::view_from_part`].
//! - [`tool`]: [`ToolProfile`] (solid of revolution) and [`ToolSpec`] (`ball-6`, `v-6-90`, ...).
//! - [`compensate`]: tool compensation of a height map (grayscale dilation by the tool, exact and
//!   fast), for the CAM's toolpaths and the machine's part opened by the tools.
//! - [`arm`]: a 6-axis arm (the Adept Viper s650) by its DH table: forward and inverse kinematics,
//!   Jacobian, dexterity, singularity margins, joint limits and trapezoidal move times.
//! - [`artifact`]: [`ArtifactRef`] and [`MediaType`].
//! - [`units`]: [`LengthUnit`], [`Units`] (given or detected from the header and the size).

pub mod arm;
pub mod artifact;
pub mod cloud;
pub mod compensate;
pub mod error;
pub mod face;
pub mod facet;
pub mod formats;
pub mod heightmap;
pub mod heightmap_io;
pub mod icp;
pub mod mesh;
pub mod mesh_raster;
pub mod multi_face;
pub mod npy;
pub mod pass_align;
pub mod png_io;
pub mod pose;
pub mod raster;
pub mod sample;
pub mod surface_fit;
pub mod tool;
pub mod units;

pub use artifact::{ArtifactRef, MediaType};
pub use cloud::{Aabb, CloudPoint, PointCloud};
pub use error::GeometryError;
pub use face::Face;
pub use formats::FormatError;
pub use heightmap::{HeightMap, HeightMapMeta, MAX_CELLS};
pub use heightmap_io::HeightMapFormat;
pub use mesh::Mesh;
pub use npy::{read_npy, read_npy_from, write_npy, write_npy_to};
pub use png_io::{ImageMapping, PngDepth, read_png, read_png_from, write_png, write_png_fast, write_png_to};
pub use pose::{Pose, XyzYpr};
pub use raster::RasterError;
pub use tool::{ToolProfile, ToolSpec};
pub use units::{LengthUnit, Units, UnitsDecision};

/// The nalgebra version this crate's types use, re-exported so callers match it.
pub use nalgebra;
