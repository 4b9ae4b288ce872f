//! Scanner (placeholder).
