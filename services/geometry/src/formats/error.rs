//! [`FormatError`]: what can go wrong reading or writing a point cloud or mesh file.
//!
//! Messages are lowercase, carry no trailing period and name the file, line or byte offset, field,
//! value or limit involved, so they can be shown to a user as they are.

use std::fmt;

use crate::GeometryError;

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

/// Everything that can go wrong in reading and writing clouds and meshes.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum FormatError {
    /// Malformed input: `file` at `at` has `problem` (e.g. "expected 3 numbers, found 2").
    #[error("{file}: {at}: {problem}")]
    Parse { file: String, at: Location, problem: String },

    /// An input exceeds a configured limit (`what` is "bytes", "points", "triangles", ...).
    #[error("{file}: {what} {value} exceeds the limit of {limit}")]
    TooLarge { file: String, what: &'static str, value: u64, limit: u64 },

    /// The input's format is not one the reader handles, or not the kind of geometry asked for.
    #[error("{file}: unsupported format: {reason}")]
    UnsupportedFormat { file: String, reason: String },

    /// A writer's argument is outside its domain (e.g. a comment with a line break).
    #[error("invalid {field} = {value}: {reason}")]
    InvalidParameter { field: String, value: String, reason: String },

    /// A gzip-compressed input whose compressed stream is broken (cut short, corrupt, a checksum
    /// that does not match); `at` is how many compressed bytes the decoder had taken.
    #[error("{file}: gzip: {problem} (after {at} compressed bytes)")]
    Gzip { file: String, at: u64, problem: String },

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

impl FormatError {
    /// Shorthand for [`FormatError::InvalidParameter`].
    pub fn param(field: impl Into<String>, value: impl fmt::Display, reason: impl Into<String>) -> Self {
        FormatError::InvalidParameter { field: field.into(), value: value.to_string(), reason: reason.into() }
    }

    /// True when the input is at fault (as opposed to the machine: I/O errors).
    pub fn is_invalid_input(&self) -> bool {
        !matches!(self, FormatError::Io { .. })
    }
}

/// Result with [`FormatError`].
pub type Result<T, E = FormatError> = std::result::Result<T, E>;
