//! Errors of the CAM domain. Messages are lowercase and name the field, value and limit.

/// Why planning (or one of its steps) failed.
#[derive(Debug, thiserror::Error)]
pub enum CamError {
    /// A parameter is out of range or inconsistent.
    #[error("{field}: {message}")]
    InvalidParameter { field: String, message: String },
    /// A `.tool` file or tool name could not be used.
    #[error("tool {name}: {message}")]
    InvalidTool { name: String, message: String },
    /// The depth map cannot be machined as given.
    #[error("depth map: {message}")]
    InvalidMap { message: String },
    /// The holder or shank would touch the part.
    #[error("{message}")]
    HolderCollision { message: String, min_stickout_mm: f64 },
    /// Planning was cancelled.
    #[error("planning cancelled")]
    Cancelled,
    /// Reading or writing a file failed.
    #[error("{path}: {message}")]
    Io { path: String, message: String },
}

impl CamError {
    /// An [`CamError::InvalidParameter`].
    pub fn param(field: impl Into<String>, message: impl Into<String>) -> Self {
        CamError::InvalidParameter { field: field.into(), message: message.into() }
    }
}
