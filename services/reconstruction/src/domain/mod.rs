//! The reconstruction library: pure domain code, no network, no async; its only I/O is reading
//! input files and streams.
//!
//! - [`error`]: [`ReconError`], the one error type.
//! - [`io`]: streaming readers for XYZ, PLY (ASCII and binary) and STL, and the PLY writer the
//!   scanning service uses.
//! - [`mesh`]: [`mesh::Mesh`], an indexed triangle mesh.
//! - [`filters`]: clean-up filters (intensity window, statistical and radius outlier removal,
//!   voxel decimation), sphere fitting and beacon frames, rigid user transforms.
//! - [`raster`]: max-Z rasterisation, enclosed-hole filling, coverage.
//! - [`mesh_raster`]: z-buffer of a mesh (exact top surface at cell centres).
//! - [`roughing`]: block-max and continuous over-approximations for roughing.
//! - [`image_ops`]: histogram stretch, median and bilateral denoise, morphology, foreign images.
//! - [`pipeline`]: the reconstruct stage: options (the job's `reconstruct` object) -> maps.

pub mod error;
pub mod filters;
pub mod image_ops;
pub mod io;
pub mod mesh;
pub mod mesh_raster;
pub mod pipeline;
pub mod raster;
pub mod roughing;

pub use error::{ReconError, Result};
