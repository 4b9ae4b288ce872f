//! [`ReconError`]: the one error type of the reconstruction library.
//!
//! Messages are lowercase, carry no trailing period and name the file, line or byte offset, field,
//! value or limit involved, so they can be shown to a user as they are.

use std::fmt;

use depthmill_geometry::{FormatError, GeometryError, RasterError};

/// Everything that can go wrong in reading, cleaning and rasterising.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ReconError {
    /// The input could not be read (malformed, too large, unsupported, or an I/O error on it).
    #[error(transparent)]
    Format(#[from] FormatError),

    /// A parameter is outside its domain; `field` uses the job JSON's path where there is one
    /// (e.g. `reconstruct.fill.max_hole_mm`).
    #[error("invalid {field} = {value}: {reason}")]
    InvalidParameter { field: String, value: String, reason: String },

    /// An operation needs data the cloud does not carry (e.g. intensity for the intensity window).
    #[error("{operation} needs {what}, which the cloud does not have")]
    MissingAttribute { operation: &'static str, what: &'static str },

    /// Nothing left to work on (e.g. every point was removed, or the region of interest is empty).
    #[error("{0}")]
    Empty(String),

    /// The job was cancelled while the stage ran.
    #[error("cancelled")]
    Cancelled,

    /// A geometry type rejected a value.
    #[error(transparent)]
    Geometry(#[from] GeometryError),
}

impl ReconError {
    /// Shorthand for [`ReconError::InvalidParameter`].
    pub fn param(field: impl Into<String>, value: impl fmt::Display, reason: impl Into<String>) -> Self {
        // A number far out of range reads as 1e308, not as its 309 digits.
        let mut value = value.to_string();
        if value.len() > 24
            && let Ok(v) = value.parse::<f64>()
        {
            value = format!("{v:e}");
        }
        ReconError::InvalidParameter { field: field.into(), value, reason: reason.into() }
    }

    /// True when the caller's input is at fault (as opposed to the machine: I/O errors).
    pub fn is_invalid_input(&self) -> bool {
        match self {
            ReconError::Format(e) => e.is_invalid_input(),
            _ => true,
        }
    }
}

/// The rasterisers name their parameters relative to the job's `reconstruct` section; this
/// service exposes them under `reconstruct.`.
impl From<RasterError> for ReconError {
    fn from(e: RasterError) -> Self {
        match e {
            RasterError::InvalidParameter { field, value, reason } => {
                ReconError::InvalidParameter { field: format!("reconstruct.{field}"), value, reason }
            }
            RasterError::Geometry(g) => ReconError::Geometry(g),
        }
    }
}

/// Result with [`ReconError`].
pub type Result<T, E = ReconError> = std::result::Result<T, E>;
