//! [`GeometryError`]: the one error type of this crate.
//!
//! Messages are lowercase, carry no trailing period and name the field, value, limit or path
//! involved, so a caller can show them to a user as they are.

use std::path::PathBuf;

/// Everything that can go wrong when building, validating, reading or writing geometry types.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum GeometryError {
    /// A scalar parameter is out of its domain (`field` names it, `expected` says what is allowed).
    #[error("invalid {field} {value}: expected {expected}")]
    InvalidParameter { field: String, value: String, expected: &'static str },

    /// A height map's data length does not match its dimensions.
    #[error("height map data has {len} cells but {width}x{height} needs {expected}")]
    DataLength { width: u32, height: u32, expected: u64, len: usize },

    /// A grid is larger than [`crate::heightmap::MAX_CELLS`].
    #[error("height map {width}x{height} has more than {limit} cells")]
    TooManyCells { width: u64, height: u64, limit: u64 },

    /// A cell index lies outside the grid.
    #[error("cell ({col}, {row}) is outside the {width}x{height} grid")]
    OutOfBounds { col: u32, row: u32, width: u32, height: u32 },

    /// Parallel arrays of a point cloud disagree in length.
    #[error("point cloud {field} has {len} entries but the cloud has {points} points")]
    ParallelLength { field: &'static str, len: usize, points: usize },

    /// A mesh triangle refers to a vertex the mesh does not have.
    #[error(
        "invalid triangle {triangle} = {index}: vertex index out of range (mesh has {vertices} vertices)"
    )]
    MeshIndex { triangle: usize, index: u32, vertices: usize },

    /// A tool profile's radius and height vectors differ in length, or are too short.
    #[error("tool profile has {radii} radii and {heights} heights: expected two equal lengths of at least 2")]
    ProfileLength { radii: usize, heights: usize },

    /// A tool profile decreases somewhere.
    #[error("tool profile {field}[{index}] = {value} is less than the previous value {previous}")]
    ProfileNotMonotone { field: &'static str, index: usize, value: f64, previous: f64 },

    /// A bull-nose corner radius is larger than the tool radius.
    #[error("corner radius {corner_radius_mm} mm exceeds the tool radius {radius_mm} mm")]
    CornerRadius { corner_radius_mm: f64, radius_mm: f64 },

    /// A textual name (face, tool spec, media type, ...) does not parse.
    #[error("cannot parse {what} '{input}': expected {expected}")]
    Parse { what: &'static str, input: String, expected: &'static str },

    /// A SHA-256 digest is not 64 lowercase hexadecimal digits.
    #[error("invalid sha256 '{value}': expected 64 lowercase hex digits")]
    InvalidSha256 { value: String },

    /// A file extension that no height-map reader or writer handles.
    #[error("unsupported height map extension '{extension}': expected .png or .npy")]
    UnsupportedExtension { extension: String },

    /// Mapping metadata is missing from the file and no fallback supplies it.
    #[error("missing metadata key '{key}' and no fallback mapping supplies it")]
    MissingMetadata { key: &'static str },

    /// A metadata entry is present but unusable.
    #[error("invalid metadata {key} = '{value}': {reason}")]
    InvalidMetadata { key: String, value: String, reason: String },

    /// The PNG decoder or encoder rejected the data.
    #[error("invalid png: {reason}")]
    Png { reason: String },

    /// A PNG colour type or bit depth the reader does not handle.
    #[error("unsupported png format {color} at {bits} bit")]
    UnsupportedPng { color: String, bits: u8 },

    /// The first bytes are not the `.npy` magic string.
    #[error("not an npy file: bad magic")]
    NpyBadMagic,

    /// A `.npy` format version other than 1.0, 2.0 or 3.0.
    #[error("unsupported npy version {major}.{minor}")]
    NpyVersion { major: u8, minor: u8 },

    /// The `.npy` header dictionary is malformed.
    #[error("malformed npy header: {reason}")]
    NpyHeader { reason: String },

    /// A `.npy` dtype other than `<f4`, `>f4`, `<f8`, `>f8`.
    #[error("unsupported npy dtype '{dtype}': expected <f4, >f4, <f8 or >f8")]
    NpyDtype { dtype: String },

    /// Two descriptions of the same array disagree on its shape.
    #[error("shape mismatch: {found} found but {expected} expected")]
    ShapeMismatch { expected: String, found: String },

    /// The input ended before all announced data was read.
    #[error("truncated data at byte {offset}: expected {expected} bytes in total")]
    Truncated { offset: u64, expected: u64 },

    /// A sidecar or tool file is not the JSON it should be.
    #[error("invalid json: {reason}")]
    Json { reason: String },

    /// An I/O failure of the underlying reader or writer.
    #[error("i/o error: {error}")]
    Io { error: std::io::Error },

    /// An error while reading or writing a named file; `inner` says what went wrong.
    #[error("{}: {inner}", path.display())]
    File { path: PathBuf, inner: Box<GeometryError> },
}

impl From<std::io::Error> for GeometryError {
    fn from(error: std::io::Error) -> Self {
        GeometryError::Io { error }
    }
}

impl GeometryError {
    /// Wraps `self` with the file it concerns (no-op if it already names a file).
    pub fn in_file(self, path: impl Into<PathBuf>) -> Self {
        match self {
            e @ GeometryError::File { .. } => e,
            e => GeometryError::File { path: path.into(), inner: Box::new(e) },
        }
    }

    /// The error without any [`GeometryError::File`] wrapper, for matching on the cause.
    pub fn root(&self) -> &GeometryError {
        match self {
            GeometryError::File { inner, .. } => inner.root(),
            e => e,
        }
    }

    pub(crate) fn invalid(field: impl Into<String>, value: impl ToString, expected: &'static str) -> Self {
        GeometryError::InvalidParameter { field: field.into(), value: value.to_string(), expected }
    }
}

/// Result alias of this crate.
pub type Result<T, E = GeometryError> = std::result::Result<T, E>;
