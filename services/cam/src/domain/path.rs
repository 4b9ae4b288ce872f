//! Toolpath types shared by the strategies, the clean-up and the G-code writer.
//!
//! Coordinates are the tool **tip** in the depth map's frame, millimetres. A [`Pass`] is one
//! continuous cut; how the tool gets from the end of one pass to the start of the next is the
//! pass's [`Link`], decided by the strategy, which knows the surface between them.

use nalgebra::Point3;

/// How the tool reaches the start of a pass from where the previous one ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Link {
    /// Retract to the safe Z, rapid over, plunge (at plunge feed) to the start.
    Retract,
    /// Feed straight to the start: the strategy checked the straight move stays clear of the part.
    Direct,
}

/// One continuous cutting move: a polyline of tip positions fed at the cutting feed.
#[derive(Debug, Clone, PartialEq)]
pub struct Pass {
    pub link: Link,
    pub points: Vec<Point3<f64>>,
}

/// What a strategy produced for one tool.
#[derive(Debug, Clone, PartialEq)]
pub struct Toolpath {
    /// `roughing-x`, `roughing-contour`, `finishing-raster-x`, `finishing-iso-level`, ...
    pub strategy: String,
    /// Name of the tool that cuts it.
    pub tool: String,
    pub passes: Vec<Pass>,
    /// Height above every point of the stock and the part at which rapid moves are safe.
    pub safe_z_mm: f64,
}

impl Toolpath {
    /// Total number of points of all passes.
    pub fn point_count(&self) -> usize {
        self.passes.iter().map(|p| p.points.len()).sum()
    }
}

/// A move after clean-up, as the G-code writer emits it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Segment {
    /// G0 to the point.
    Rapid(Point3<f64>),
    /// G1 to the point at the cutting feed.
    Linear(Point3<f64>),
    /// G1 to the point at the plunge feed (downward entry).
    Plunge(Point3<f64>),
    /// G2 (clockwise seen from +Z) or G3 in the XY plane to `end` about `center` (XY), Z moving
    /// linearly from the start's Z to `end.z` (a helix when they differ).
    Arc { end: Point3<f64>, center: [f64; 2], clockwise: bool },
}

impl Segment {
    /// The point the move ends at.
    pub fn end(&self) -> Point3<f64> {
        match *self {
            Segment::Rapid(p) | Segment::Linear(p) | Segment::Plunge(p) => p,
            Segment::Arc { end, .. } => end,
        }
    }
}
