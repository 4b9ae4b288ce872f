//! Tool compensation for planning: the kernel and the fast dilation are
//! [`depthmill_geometry::compensate`] (shared with the machine service, which measures the
//! simulated part against the part opened by the tools); [`compensate`] gives their result with the
//! CAM service's errors.

pub use depthmill_geometry::compensate::{
    CompensateOptions, Kernel, KernelRow, PixelModel, compensate_reference, dilate, kernel,
};
use depthmill_geometry::{GeometryError, HeightMap, ToolProfile};

use super::CamError;

/// [`depthmill_geometry::compensate::compensate`]: the compensated tip surface of `map` for
/// `profile`. Errors: a non-finite `outside_z_mm` ([`CamError::InvalidParameter`]), a map the
/// result cannot be built on ([`CamError::InvalidMap`]).
pub fn compensate(
    map: &HeightMap,
    profile: &ToolProfile,
    opts: &CompensateOptions,
) -> Result<HeightMap, CamError> {
    depthmill_geometry::compensate::compensate(map, profile, opts).map_err(|e| match e {
        GeometryError::InvalidParameter { field, value, expected } => {
            CamError::param(field, format!("must be {expected}, got {value}"))
        }
        other => CamError::InvalidMap { message: other.to_string() },
    })
}
