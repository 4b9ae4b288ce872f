//! [`ReconError`]: the one error type of the reconstruction library.
//!
//! Messages are lowercase, carry no trailing period and name the file, line or byte offset, field,
//! value or limit involved, so they can be shown to a user as they are.

use std::fmt;

use depthmill_geometry::GeometryError;

/// Where in an input a problem sits.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Location {
    /// A 1-based line of a text file.
    Line(u64),
    /// A 0-based byte offset of a binary file (or of a text file's header).
    Byte(u64),
}

impl fmt::Display for Location {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Location::Line(n) => write!(f, "line {n}"),
            Location::Byte(n) => write!(f, "byte {n}"),
        }
    }
}

/// Everything that can go wrong in reading, cleaning and rasterising.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ReconError {
    /// Malformed input: `file` at `at` has `problem` (e.g. "expected 3 numbers, found 2").
    #[error("{file}: {at}: {problem}")]
    Parse { file: String, at: Location, problem: String },

    /// An input exceeds a configured limit (`what` is "bytes", "points", "triangles", ...).
    #[error("{file}: {what} {value} exceeds the limit of {limit}")]
    TooLarge { file: String, what: &'static str, value: u64, limit: u64 },

    /// The input's format is not one the reader handles.
    #[error("{file}: unsupported format: {reason}")]
    UnsupportedFormat { file: String, reason: String },

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

    /// An I/O error on `file`.
    #[error("{file}: {source}")]
    Io {
        file: String,
        #[source]
        source: std::io::Error,
    },

    /// A geometry type rejected a value.
    #[error(transparent)]
    Geometry(#[from] GeometryError),
}

impl ReconError {
    /// Shorthand for [`ReconError::InvalidParameter`].
    pub fn param(field: impl Into<String>, value: impl fmt::Display, reason: impl Into<String>) -> Self {
        ReconError::InvalidParameter { field: field.into(), value: value.to_string(), reason: reason.into() }
    }

    /// True when the caller's input is at fault (as opposed to the machine: I/O errors).
    pub fn is_invalid_input(&self) -> bool {
        !matches!(self, ReconError::Io { .. })
    }
}

/// Result with [`ReconError`].
pub type Result<T, E = ReconError> = std::result::Result<T, E>;
