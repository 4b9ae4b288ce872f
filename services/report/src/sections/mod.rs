//! The report's sections, one module each, in page order. Each adds methods to the render
//! context that return the section's HTML.

mod faces;
mod machine;
pub(crate) mod part;
mod robot;
mod scan;
pub(crate) mod solid;
mod summary;
mod toolpaths;

pub use toolpaths::toolpath_image;
