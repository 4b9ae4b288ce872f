//! The reconstruction library: pure domain code, no network, no async; its only I/O is reading
//! input files and streams.
//!
//! The readers (`depthmill_geometry::formats`), the mesh type and the rasterisers
//! (`depthmill_geometry::raster`, `depthmill_geometry::mesh_raster`) live in the geometry crate,
//! which the scanning service and the report share; this crate composes them into the stage.
//!
//! - [`error`]: [`ReconError`], the one error type.
//! - [`filters`]: clean-up filters (intensity window, statistical and radius outlier removal,
//!   voxel decimation), sphere fitting and beacon frames, rigid user transforms.
//! - [`roughing`]: block-max and continuous over-approximations for roughing.
//! - [`image_ops`]: histogram stretch, median and bilateral denoise, morphology, foreign images.
//! - [`table`]: the table a scanned part stood on, found in the cloud and made the XY plane.
//! - [`pipeline`]: the reconstruct stage: options (the job's `reconstruct` object) -> maps.

pub mod error;
pub mod face_choice;
pub mod filters;
pub mod image_ops;
pub mod pipeline;
pub mod roughing;
pub mod table;

pub use error::{ReconError, Result};
