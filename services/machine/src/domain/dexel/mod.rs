//! The stock as dexels, for cutting at any tool orientation and for every face of a part on one
//! stock (seed 004's "map of height segments").
//!
//! # Model
//!
//! - **Grids** ([`DexelStock`]): up to three, one per axis of the part frame (tri-dexel). The grid
//!   along axis `k` has its rays parallel to `k`, one ray per cell centre of a square grid over
//!   the other two axes (`(k+1) % 3`, `(k+2) % 3`), cell size set per grid ([`DexelCells`]).
//!   Each ray holds its material as sorted disjoint intervals `[lo, hi]` of the coordinate along
//!   `k` (f32, mm). Every grid holds the whole solid: one grid alone (the seed's model) is exact
//!   along its rays and resolves the surfaces across them to its cell; the other two add the
//!   walls and undercuts that are parallel to the first grid's rays.
//! - **Storage**: a ray is a `SmallVec<[[f32; 2]; 1]>` (24 bytes, the first interval inline, a heap
//!   list once a ray holds two or more); [`DexelStock::new`] refuses a stock whose rays would
//!   take more than [`MAX_DEXEL_BYTES`] before allocating anything.
//! - **Blank** ([`Blank`]): the material common to one or more boxes, each in its own rotated
//!   frame (a plain block is one box; a part seen from several A-axis faces is the intersection of
//!   every face's block). Each ray starts with its one interval inside all boxes.
//! - **Sectors**: a cut visits only the rays whose cell centre lies in the tool's bounding box
//!   projected on the grid, and skips a ray at once when its material's range along the ray
//!   does not meet that box; only the remaining rays get the exact test. On the grid whose rays
//!   are parallel to the tool's axis (the Z grid of a 3-axis cut) a row visits only its chord of
//!   the capsule the tip's path sweeps with the tool's radius, a ray whose material ends below a
//!   table lower bound of the tool's lower surface is skipped, and a level move (no motion along
//!   the rays) takes the tool's own intervals at the ray's distance from the path instead of the
//!   closed form per piece.
//!
//! # Cutting
//!
//! [`DexelStock::cut_line`] sweeps a [`ToolSolid`] along a straight move at a fixed orientation
//! and subtracts, on every ray, the exact interval the ray spends in each convex piece of the
//! swept tool ([`sweep`]; no sampling along the move). Arcs are chords, as in the Z-map
//! ([`crate::domain::removal::ARC_SAGITTA_CELLS`]). [`DexelStock::cut_moving`] cuts a move whose
//! orientation changes (a feed move that turns the A axis): the move is split into steps, each
//! swept as a straight move at its start orientation, and the steps are fine enough that every
//! tool point stays within `max_error_mm` of where it truly is (see [`DexelStock::cut_moving`]).
//!
//! # What a cut reports
//!
//! The Z-map's [`Cut`]: the volume is measured on the primary grid (Z, else X, else Y) as the sum
//! of the removed lengths times the cell area; the engagement and axial depth come from the
//! primary grid's removed segments too (every grid holds the whole removed volume), seen from
//! the tool at the end of the move, with the same definitions as [`crate::domain::removal`]
//! (front half, contact radius, half a cell of padding; 10° sectors for a plunge).
//!
//! A simulation cuts in pieces of one spindle revolution, and only the primary grid's figures
//! drive its loop: [`DexelStock::cut_run`] cuts the primary grid per piece and the other grids
//! once per run of pieces that stay within a stated error of one straight line (a move's
//! revolutions, a finishing pass's short segments along a flat stretch), which is where most of
//! a 3-axis cut's work on the other grids went.

pub mod surface;
pub mod sweep;
#[cfg(test)]
mod tests;

use std::f64::consts::PI;

use depthmill_geometry::{HeightMap, HeightMapMeta};
use nalgebra::{Point3, Rotation3, Unit, Vector3};
use rayon::prelude::*;
use smallvec::SmallVec;

pub use sweep::{AxisFrame, Piece, RayMove, ToolSolid};

use super::removal::Cut;

/// The most memory the rays of one stock may take, bytes (4 GiB).
pub const MAX_DEXEL_BYTES: u64 = 4 << 30;
/// Largest absolute coordinate accepted, mm.
pub const MAX_COORD_MM: f64 = 1.0e6;
/// Material shorter than this along a ray is dropped after a cut, mm.
pub const MIN_SEGMENT_MM: f32 = 1.0e-6;
/// A cut visiting more rays than this runs its rows in parallel.
const PAR_RAYS: usize = 1 << 14;
/// Most steps one orientation-changing move is split into.
pub const MAX_STEPS: usize = 1_000_000;

/// One ray's material: sorted disjoint `[lo, hi]` intervals.
pub type Ray = SmallVec<[[f32; 2]; 1]>;

/// Bytes one ray takes in memory (without its heap list).
pub const RAY_BYTES: u64 = std::mem::size_of::<Ray>() as u64;

/// Invalid dexel-stock parameters; each names the field, its value and the limit.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum DexelError {
    #[error("invalid {field} {value}: expected {expected}")]
    Invalid { field: String, value: f64, expected: &'static str },
    #[error(
        "the dexel stock would take {bytes} bytes in {rays} rays, more than the limit of {limit} bytes: make {field} coarser"
    )]
    TooLarge { field: String, rays: u64, bytes: u64, limit: u64 },
    #[error("invalid {field} ({x}, {y}, {z}): expected finite coordinates within ±{limit} mm")]
    InvalidPoint { field: String, x: f64, y: f64, z: f64, limit: f64 },
    #[error("the blank is empty: its boxes have no material in common")]
    EmptyBlank,
    #[error("invalid view grid: {0}")]
    Map(String),
    #[error("no dexel grid: set at least one of the cell sizes along X, Y and Z")]
    NoGrid,
    #[error(
        "the surface lattice at a step of {step_mm} mm would take {samples} samples, more than the limit of {limit}: take a coarser step"
    )]
    TooManySamples { step_mm: f64, samples: u64, limit: u64 },
    #[error("a move turning the tool by {angle_deg:.3}° needs {steps} steps, more than the limit of {limit}")]
    TooManySteps { angle_deg: f64, steps: f64, limit: usize },
}

/// A cut's error bound: finite and positive.
fn check_error(max_error_mm: f64) -> Result<(), DexelError> {
    if max_error_mm.is_finite() && max_error_mm > 0.0 {
        Ok(())
    } else {
        Err(DexelError::Invalid {
            field: "max_error_mm".into(),
            value: max_error_mm,
            expected: "a finite positive error",
        })
    }
}

fn check_point(field: &str, p: &Point3<f64>) -> Result<(), DexelError> {
    if p.iter().all(|v| v.is_finite() && v.abs() <= MAX_COORD_MM) {
        Ok(())
    } else {
        Err(DexelError::InvalidPoint { field: field.into(), x: p.x, y: p.y, z: p.z, limit: MAX_COORD_MM })
    }
}

/// A box given in its own frame, placed in the part frame by a rotation (`part = R · box`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OrientedBox {
    pub part_from_box: Rotation3<f64>,
    pub min: Point3<f64>,
    pub max: Point3<f64>,
}

impl OrientedBox {
    /// An axis-aligned box of the part frame.
    pub fn aligned(min: Point3<f64>, max: Point3<f64>) -> Self {
        OrientedBox { part_from_box: Rotation3::identity(), min, max }
    }

    /// The `t` interval of the ray `o + t·d` inside the box (slab method).
    fn clip(&self, o: &Point3<f64>, d: &Vector3<f64>) -> Option<(f64, f64)> {
        let ob = self.part_from_box.inverse() * o;
        let db = self.part_from_box.inverse() * d;
        let (mut lo, mut hi) = (f64::NEG_INFINITY, f64::INFINITY);
        for k in 0..3 {
            if db[k].abs() < 1e-12 {
                if ob[k] < self.min[k] || ob[k] > self.max[k] {
                    return None;
                }
            } else {
                let (a, b) = ((self.min[k] - ob[k]) / db[k], (self.max[k] - ob[k]) / db[k]);
                lo = lo.max(a.min(b));
                hi = hi.min(a.max(b));
            }
        }
        (lo < hi).then_some((lo, hi))
    }

    /// Axis-aligned bounds in the part frame.
    fn aabb(&self) -> ([f64; 3], [f64; 3]) {
        let mut lo = [f64::INFINITY; 3];
        let mut hi = [f64::NEG_INFINITY; 3];
        for c in 0..8 {
            let p = Point3::new(
                if c & 1 == 0 { self.min.x } else { self.max.x },
                if c & 2 == 0 { self.min.y } else { self.max.y },
                if c & 4 == 0 { self.min.z } else { self.max.z },
            );
            let q = self.part_from_box * p;
            for k in 0..3 {
                lo[k] = lo[k].min(q[k]);
                hi[k] = hi[k].max(q[k]);
            }
        }
        (lo, hi)
    }
}

/// The blank: the material common to every box.
#[derive(Debug, Clone, PartialEq)]
pub struct Blank {
    pub boxes: Vec<OrientedBox>,
}

impl Blank {
    /// Bounds in the part frame (the intersection of the boxes' bounds), or `None` when empty.
    pub fn aabb(&self) -> Option<([f64; 3], [f64; 3])> {
        let mut lo = [f64::NEG_INFINITY; 3];
        let mut hi = [f64::INFINITY; 3];
        for b in &self.boxes {
            let (l, h) = b.aabb();
            for k in 0..3 {
                lo[k] = lo[k].max(l[k]);
                hi[k] = hi[k].min(h[k]);
            }
        }
        (!self.boxes.is_empty() && (0..3).all(|k| lo[k] < hi[k])).then_some((lo, hi))
    }

    /// The `t` interval of the ray `o + t·d` inside every box (the blank is convex), or `None`.
    pub fn ray_extent(&self, o: &Point3<f64>, d: &Vector3<f64>) -> Option<(f64, f64)> {
        let mut iv = (f64::NEG_INFINITY, f64::INFINITY);
        for b in &self.boxes {
            let (l, h) = b.clip(o, d)?;
            iv = (iv.0.max(l), iv.1.min(h));
        }
        (!self.boxes.is_empty() && iv.0 < iv.1).then_some(iv)
    }
}

/// Cell size of each grid, by the axis its rays run along; `None` leaves that grid out.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct DexelCells {
    pub x_mm: Option<f64>,
    pub y_mm: Option<f64>,
    pub z_mm: Option<f64>,
}

impl DexelCells {
    /// All three grids at one cell size.
    pub fn tri(cell_mm: f64) -> Self {
        DexelCells { x_mm: Some(cell_mm), y_mm: Some(cell_mm), z_mm: Some(cell_mm) }
    }

    fn get(&self, axis: usize) -> Option<f64> {
        [self.x_mm, self.y_mm, self.z_mm][axis]
    }
}

/// The two plane axes of the grid along `axis`.
fn plane_axes(axis: usize) -> (usize, usize) {
    ((axis + 1) % 3, (axis + 2) % 3)
}

/// One dexel grid.
#[derive(Debug, Clone)]
struct Grid {
    axis: usize,
    cell: f64,
    /// Plane coordinates of the grid's minimum corner (axes `plane_axes(axis)`).
    origin: [f64; 2],
    n: [usize; 2],
    rays: Vec<Ray>,
}

impl Grid {
    fn ray_origin(&self, i: usize, j: usize) -> Point3<f64> {
        let (a, b) = plane_axes(self.axis);
        let mut p = Point3::origin();
        p[a] = self.origin[0] + (i as f64 + 0.5) * self.cell;
        p[b] = self.origin[1] + (j as f64 + 0.5) * self.cell;
        p
    }

    fn dir(&self) -> Vector3<f64> {
        let mut d = Vector3::zeros();
        d[self.axis] = 1.0;
        d
    }

    /// Index range of the cell centres within `[lo, hi]` on plane axis `k` (0 or 1).
    fn span(&self, k: usize, lo: f64, hi: f64) -> Option<(usize, usize)> {
        g_span(self.origin[k], self.cell, self.n[k], lo, hi)
    }

    /// The ray through the cell containing plane coordinates of `p`.
    fn ray_at(&self, p: &Point3<f64>) -> Option<&Ray> {
        let (a, b) = plane_axes(self.axis);
        let i = ((p[a] - self.origin[0]) / self.cell).floor();
        let j = ((p[b] - self.origin[1]) / self.cell).floor();
        if i < 0.0 || j < 0.0 || i >= self.n[0] as f64 || j >= self.n[1] as f64 {
            return None;
        }
        self.rays.get(j as usize * self.n[0] + i as usize)
    }

    fn contains(&self, p: &Point3<f64>) -> bool {
        let x = p[self.axis] as f32;
        self.ray_at(p).is_some_and(|r| r.iter().any(|s| x >= s[0] && x <= s[1]))
    }
}

/// What one row of rays removed (merged into a [`Cut`]).
#[derive(Debug, Clone, Copy)]
struct Tally {
    visited: u64,
    updated: u64,
    volume: f64,
    hard_extra: f64,
    max_depth: f64,
    e_min: f64,
    e_max: f64,
    /// The largest squared radial distance of the material taken ahead of the tool.
    rho_c2: f64,
    sectors: u64,
    axial: f64,
    any: bool,
}

impl Tally {
    fn new() -> Self {
        Tally {
            visited: 0,
            updated: 0,
            volume: 0.0,
            hard_extra: 0.0,
            max_depth: 0.0,
            e_min: f64::INFINITY,
            e_max: f64::NEG_INFINITY,
            rho_c2: 0.0,
            sectors: 0,
            axial: 0.0,
            any: false,
        }
    }

    fn merge(&mut self, o: &Tally) {
        self.visited += o.visited;
        self.updated += o.updated;
        self.volume += o.volume;
        self.hard_extra += o.hard_extra;
        self.max_depth = self.max_depth.max(o.max_depth);
        self.e_min = self.e_min.min(o.e_min);
        self.e_max = self.e_max.max(o.e_max);
        self.rho_c2 = self.rho_c2.max(o.rho_c2);
        self.sectors |= o.sectors;
        self.axial = self.axial.max(o.axial);
        self.any |= o.any;
    }
}

/// How the tool sits at the end of a move, for the engagement.
#[derive(Debug, Clone, Copy)]
struct EndView {
    tip: Point3<f64>,
    u: Vector3<f64>,
    e1: Vector3<f64>,
    e2: Vector3<f64>,
    /// Travel direction across the axis and the lateral direction, when the move travels across.
    fwd: Option<(Vector3<f64>, Vector3<f64>)>,
    radius: f64,
    half_cell: f64,
}

impl EndView {
    /// The view along the ray `o + x·d` (`d` a unit grid axis): every quantity [`Self::observe`]
    /// needs is linear or quadratic in `x`, so each point costs a few scalar operations.
    fn along(&self, o: &Point3<f64>, d: &Vector3<f64>) -> RayView {
        let y0 = o - self.tip;
        let (w0, dw) = (y0.dot(&self.u), d.dot(&self.u));
        // The part across the axis: p0 + x·q.
        let p0 = y0 - self.u * w0;
        let q = d - self.u * dw;
        let (a, b) = self.fwd.unwrap_or((self.e1, self.e2));
        RayView {
            w0,
            dw,
            pp: p0.norm_squared(),
            pq: p0.dot(&q),
            qq: q.norm_squared(),
            a: (p0.dot(&a), q.dot(&a)),
            b: (p0.dot(&b), q.dot(&b)),
        }
    }

    /// Records removed material at `x` along the ray `r` views.
    #[inline]
    fn observe(&self, r: &RayView, x: f64, t: &mut Tally) {
        // Squared: no square root per point (the largest is rooted once, in `to_cut`).
        let rho2 = (r.pp + x * (2.0 * r.pq + x * r.qq)).max(0.0);
        let reach = self.radius + self.half_cell;
        if rho2 > reach * reach {
            return;
        }
        t.any = true;
        t.axial = t.axial.max(r.w0 + x * r.dw);
        let (pa, pb) = (r.a.0 + x * r.a.1, r.b.0 + x * r.b.1);
        if self.fwd.is_some() {
            // Ahead of the tool (or level with it): the lateral extent of the engagement.
            if pa >= -self.half_cell {
                t.e_min = t.e_min.min(pb);
                t.e_max = t.e_max.max(pb);
                t.rho_c2 = t.rho_c2.max(rho2);
            }
        } else {
            let ang = pb.atan2(pa).rem_euclid(2.0 * PI);
            t.sectors |= 1 << ((ang.to_degrees() / 10.0) as u32).min(35);
        }
    }
}

/// [`EndView`] along one ray: the axial height `w0 + x·dw`, the squared distance from the axis
/// `pp + 2·pq·x + qq·x²`, and the coordinates across the axis along the travel and lateral
/// directions (or `e1`, `e2` when the move does not travel across), each `(value at 0, slope)`.
#[derive(Debug, Clone, Copy)]
struct RayView {
    w0: f64,
    dw: f64,
    pp: f64,
    pq: f64,
    qq: f64,
    a: (f64, f64),
    b: (f64, f64),
}

/// A hard inclusion: material inside the sphere weighs `factor`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HardSphere {
    pub center: Point3<f64>,
    pub radius_mm: f64,
    pub factor: f64,
}

/// The stock as up to three dexel grids (see the module docs).
#[derive(Debug, Clone)]
pub struct DexelStock {
    grids: Vec<Grid>,
    hard: Vec<HardSphere>,
    /// The blank's bounding box (the material only shrinks).
    extent: ([f64; 3], [f64; 3]),
    /// Straight cuts the grids after the primary have not taken yet ([`DexelStock::cut_run`]).
    run: Option<Run>,
}

/// Consecutive straight cuts of one tool at one orientation, all within `max_error_mm` of the
/// straight line from the first point to the last: the grids after the primary take that line
/// as one cut.
#[derive(Debug, Clone)]
struct Run {
    tool: ToolSolid,
    axis: Unit<Vector3<f64>>,
    max_error_mm: f64,
    /// The tip's points, first to last.
    points: Vec<Point3<f64>>,
}

/// Most points one [`Run`] gathers before its grids are cut.
const RUN_POINTS: usize = 256;

/// Which of a stock's grids a sweep cuts.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Grids {
    All,
    Primary,
    Rest,
}

impl Grids {
    fn has(self, gi: usize) -> bool {
        match self {
            Grids::All => true,
            Grids::Primary => gi == 0,
            Grids::Rest => gi > 0,
        }
    }
}

impl DexelStock {
    /// The blank on the grids `cells` asks for.
    ///
    /// Errors: a non-positive or non-finite cell, an empty blank, no grid, or rays that would take
    /// more than [`MAX_DEXEL_BYTES`] (checked before anything is allocated).
    pub fn new(blank: &Blank, cells: &DexelCells) -> Result<Self, DexelError> {
        for b in &blank.boxes {
            check_point("blank min", &b.min)?;
            check_point("blank max", &b.max)?;
        }
        let (lo, hi) = blank.aabb().ok_or(DexelError::EmptyBlank)?;
        let mut sizes = Vec::new();
        let mut total: u64 = 0;
        for axis in [2, 0, 1] {
            let Some(cell) = cells.get(axis) else { continue };
            let name = ["dexel.x_cell_mm", "dexel.y_cell_mm", "dexel.z_cell_mm"][axis];
            if !(cell.is_finite() && cell > 0.0) {
                return Err(DexelError::Invalid {
                    field: name.into(),
                    value: cell,
                    expected: "a finite positive cell",
                });
            }
            let (a, b) = plane_axes(axis);
            let na = ((hi[a] - lo[a]) / cell).ceil().max(1.0);
            let nb = ((hi[b] - lo[b]) / cell).ceil().max(1.0);
            let rays = na * nb;
            let bytes = rays * RAY_BYTES as f64;
            total = total.saturating_add(if bytes.is_finite() && bytes < u64::MAX as f64 {
                bytes as u64
            } else {
                u64::MAX
            });
            if total > MAX_DEXEL_BYTES {
                return Err(DexelError::TooLarge {
                    field: name.into(),
                    rays: rays.min(u64::MAX as f64) as u64,
                    bytes: total,
                    limit: MAX_DEXEL_BYTES,
                });
            }
            sizes.push((axis, cell, [na as usize, nb as usize], [lo[a], lo[b]]));
        }
        if sizes.is_empty() {
            return Err(DexelError::NoGrid);
        }
        let grids = sizes
            .into_iter()
            .map(|(axis, cell, n, origin)| {
                let mut g = Grid { axis, cell, origin, n, rays: Vec::new() };
                let d = g.dir();
                g.rays = (0..n[0] * n[1])
                    .into_par_iter()
                    .map(|k| {
                        let o = g.ray_origin(k % n[0], k / n[0]);
                        let Some(iv) = blank.ray_extent(&o, &d) else { return Ray::new() };
                        let (l, h) = (iv.0 as f32, iv.1 as f32);
                        if h - l > MIN_SEGMENT_MM { smallvec::smallvec![[l, h]] } else { Ray::new() }
                    })
                    .collect();
                g
            })
            .collect();
        Ok(DexelStock { grids, hard: Vec::new(), extent: (lo, hi), run: None })
    }

    /// Makes the material inside a sphere weigh `factor` (a hard inclusion).
    ///
    /// Errors: a non-finite centre, a radius or factor not finite and positive.
    pub fn add_hard_sphere(&mut self, s: HardSphere) -> Result<(), DexelError> {
        check_point("inclusion center", &s.center)?;
        if !(s.radius_mm.is_finite() && s.radius_mm > 0.0) {
            return Err(DexelError::Invalid {
                field: "inclusion radius_mm".into(),
                value: s.radius_mm,
                expected: "a finite positive radius",
            });
        }
        if !(s.factor.is_finite() && s.factor > 0.0) {
            return Err(DexelError::Invalid {
                field: "inclusion factor".into(),
                value: s.factor,
                expected: "a finite positive factor",
            });
        }
        self.hard.push(s);
        Ok(())
    }

    /// The grids' axes and cell sizes, primary first.
    pub fn grids(&self) -> Vec<(usize, f64, [usize; 2])> {
        self.grids.iter().map(|g| (g.axis, g.cell, g.n)).collect()
    }

    /// Memory the rays take now, bytes (inline part and heap lists).
    pub fn bytes(&self) -> u64 {
        self.grids
            .iter()
            .map(|g| {
                let heap: u64 = g.rays.iter().filter(|r| r.spilled()).map(|r| r.capacity() as u64 * 8).sum();
                g.rays.len() as u64 * RAY_BYTES + heap
            })
            .sum()
    }

    /// Material volume on the primary grid, mm³.
    pub fn volume_mm3(&self) -> f64 {
        let Some(g) = self.grids.first() else { return 0.0 };
        let len: f64 =
            g.rays.par_iter().map(|r| r.iter().map(|s| f64::from(s[1]) - f64::from(s[0])).sum::<f64>()).sum();
        len * g.cell * g.cell
    }

    /// Whether `p` is material on every grid (each grid reads the ray of the cell `p` is in).
    pub fn contains(&self, p: &Point3<f64>) -> bool {
        debug_assert!(self.is_flushed(), "contains before flush");
        self.grids.iter().all(|g| g.contains(p))
    }

    /// The smallest cell of the grids, mm.
    pub fn min_cell_mm(&self) -> f64 {
        self.grids.iter().map(|g| g.cell).fold(f64::INFINITY, f64::min)
    }

    /// Sweeps `tool` with its tip moving straight `from → to` and its axis along `axis` (part
    /// frame), and removes everything it occupies (see the module docs).
    ///
    /// Errors: a non-finite point.
    pub fn cut_line(
        &mut self,
        tool: &ToolSolid,
        from: &Point3<f64>,
        to: &Point3<f64>,
        axis: &Unit<Vector3<f64>>,
    ) -> Result<Cut, DexelError> {
        self.sweep_line(tool, from, to, axis, true, Grids::All)
    }

    /// [`cut_line`](Self::cut_line) for the pieces of a path (one spindle revolution each, say):
    /// the primary grid, which the cut's figures come from, is cut now and exactly; the other
    /// grids take consecutive pieces of one tool at one orientation as one straight cut from
    /// the first piece's start to the last one's end, as long as every point between stays
    /// within `max_error_mm` of that line (so no tool point of their sweep strays farther from
    /// the pieces' own). A piece that does not continue the run (another tool or orientation,
    /// a gap, a bend beyond the error) cuts the run first. [`flush`](Self::flush) cuts what is
    /// left; the stock's readers expect it done.
    ///
    /// Errors: a non-finite point, `max_error_mm` not finite and positive.
    pub fn cut_run(
        &mut self,
        tool: &ToolSolid,
        from: &Point3<f64>,
        to: &Point3<f64>,
        axis: &Unit<Vector3<f64>>,
        max_error_mm: f64,
    ) -> Result<Cut, DexelError> {
        check_error(max_error_mm)?;
        let cut = self.sweep_line(tool, from, to, axis, true, Grids::Primary)?;
        if self.grids.len() < 2 {
            return Ok(cut);
        }
        let joins = self.run.as_ref().is_some_and(|r| {
            r.points.len() < RUN_POINTS
                && r.points.last() == Some(from)
                && r.axis == *axis
                && r.max_error_mm == max_error_mm
                && r.tool.same_shape(tool)
                && r.points.iter().all(|p| segment_distance(p, &r.points[0], to) <= max_error_mm)
        });
        if joins {
            if let Some(r) = &mut self.run {
                r.points.push(*to);
            }
        } else {
            self.flush()?;
            self.run = Some(Run { tool: tool.clone(), axis: *axis, max_error_mm, points: vec![*from, *to] });
        }
        Ok(cut)
    }

    /// Cuts the grids after the primary with the run [`cut_run`](Self::cut_run) gathered.
    ///
    /// Errors: a non-finite point (checked when the run's pieces came in, so not in practice).
    pub fn flush(&mut self) -> Result<(), DexelError> {
        if let Some(r) = self.run.take()
            && let (Some(a), Some(b)) = (r.points.first(), r.points.last())
        {
            self.sweep_line(&r.tool, a, b, &r.axis, true, Grids::Rest)?;
        }
        Ok(())
    }

    /// Whether every cut has reached every grid ([`flush`](Self::flush) after
    /// [`cut_run`](Self::cut_run)).
    pub fn is_flushed(&self) -> bool {
        self.run.is_none()
    }

    /// [`cut_line`](Self::cut_line); `prune = false` visits every ray of the tool's box with
    /// every piece and no bound (the reference the pruned sweep is tested against).
    fn sweep_line(
        &mut self,
        tool: &ToolSolid,
        from: &Point3<f64>,
        to: &Point3<f64>,
        axis: &Unit<Vector3<f64>>,
        prune: bool,
        which: Grids,
    ) -> Result<Cut, DexelError> {
        check_point("from", from)?;
        check_point("to", to)?;
        let f = AxisFrame::new(axis);
        let v = to - from;
        let perp = v - f.u * v.dot(&f.u);
        let fwd = (perp.norm() > 1e-9).then(|| {
            let fw = perp.normalize();
            (fw, f.u.cross(&fw))
        });
        let end = EndView {
            tip: *to,
            u: f.u,
            e1: f.e1,
            e2: f.e2,
            fwd,
            radius: tool.radius_mm(),
            half_cell: 0.5 * self.min_cell_mm(),
        };
        // Bounds of the swept tool: both ends, from the tip to the tool's length, ± R.
        let mut lo = [f64::INFINITY; 3];
        let mut hi = [f64::NEG_INFINITY; 3];
        for p in [from, to] {
            for w in [0.0, tool.length_mm()] {
                let q = p + f.u * w;
                for k in 0..3 {
                    lo[k] = lo[k].min(q[k] - tool.radius_mm());
                    hi[k] = hi[k].max(q[k] + tool.radius_mm());
                }
            }
        }
        let hard = &self.hard;
        let stock_extent = self.extent;
        let mut total = Tally::new();
        for (gi, g) in self.grids.iter_mut().enumerate().filter(|(gi, _)| which.has(*gi)) {
            let primary = gi == 0;
            let (a, b) = plane_axes(g.axis);
            // Rays along the tool's axis (the Z grid of a 3-axis cut): the swept tool starts on
            // such a ray no nearer than the lowest tip plus the tool's lower surface at the ray's
            // distance from the tip's path (exact for a level move), so material that ends
            // before that is untouched and the exact test is skipped.
            let along = f.u[g.axis];
            let r2 = tool.radius_mm() * tool.radius_mm();
            let axial = (along.abs() > 1.0 - 1e-12).then(|| {
                let sgn = along.signum();
                let tip_low = (sgn * from[g.axis]).min(sgn * to[g.axis]);
                (sgn, tip_low, [from[a], from[b]], [to[a] - from[a], to[b] - from[b]])
            });
            // A level move along such rays (no motion along them: a 3-axis cut at one height)
            // covers, on a ray at distance d from the tip's path, the tool's intervals at d
            // (see `ToolSolid::intervals_at`): no closed form per piece needed.
            let level = axial.is_some() && v[g.axis].abs() < 1e-12;
            // Rays across the tool's axis and a move across it too (the other grids of a 3-axis
            // cut): a ray stays at one axial height `w`, where the tool is a disc of radius
            // `radius_at(w)` (the pieces are concentric), so the swept tool on the ray is that
            // disc's capsule along the move: one closed form per ray.
            let across = (along.abs() < 1e-12 && v.dot(&f.u).abs() < 1e-12)
                .then(|| sweep::AcrossMove::new(&f.u, &g.dir(), g.axis, &v));
            // 1 / |e|² of the tip's path across the rays (0 for a move along them: every ray
            // then measures from the start).
            let inv_ee = axial.map_or(0.0, |(_, _, _, e)| {
                let ee = e[0] * e[0] + e[1] * e[1];
                if ee > 0.0 { 1.0 / ee } else { 0.0 }
            });
            let d = g.dir();
            let area = g.cell * g.cell;
            let ni = g.n[0];
            let geo = (g.axis, g.cell, g.origin);
            let k = g.axis;
            // Each piece's swept core (its axis segment moved along the move; a ball's centre)
            // seen along the rays: a ray farther than the piece's radius from it misses the
            // piece, and so does a ray outside the piece's range along the rays. A piece whose
            // range misses the stock's (the blank's box: the material only shrinks) is left out
            // (the shank above a tilted ball's cut).
            let shadows: Vec<Shadow> = tool
                .pieces()
                .iter()
                .map(|piece| {
                    let (c, e, rho, widen, ball) = match *piece {
                        Piece::Sphere { c, r } => {
                            let c = from + f.u * c;
                            (c, Vector3::zeros(), r, r, Some((c[k], c[k] + v[k], r * r)))
                        }
                        _ => {
                            let (w0, w1, rho) = piece.bounds();
                            // The axis segment's ends widened by a disc of its radius across
                            // the axis.
                            let widen = rho * (1.0 - f.u[k] * f.u[k]).max(0.0).sqrt();
                            (from + f.u * w0, f.u * (w1 - w0), rho, widen, None)
                        }
                    };
                    let ends = [c[k], c[k] + e[k], c[k] + v[k], c[k] + e[k] + v[k]];
                    let lo = ends.iter().copied().fold(f64::INFINITY, f64::min) - widen - 1e-6;
                    let hi = ends.iter().copied().fold(f64::NEG_INFINITY, f64::max) + widen + 1e-6;
                    let live = !prune || (hi >= stock_extent.0[k] && lo <= stock_extent.1[k]);
                    Shadow::new([c[a], c[b]], [v[a], v[b]], [e[a], e[b]], rho + 1e-6, (lo, hi), ball, live)
                })
                .collect();
            // The rays to visit: with the tool along them, the tool's box (rows clipped below to
            // the tip path's capsule); otherwise the live pieces' shadows (rows clipped to their
            // chords).
            let (plo, phi, tlo, thi) = if axial.is_some() || !prune {
                ([lo[a], lo[b]], [hi[a], hi[b]], lo[k], hi[k])
            } else {
                let (mut plo, mut phi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
                let (mut tlo, mut thi) = (f64::INFINITY, f64::NEG_INFINITY);
                for s in shadows.iter().filter(|s| s.live) {
                    let (l, h) = s.bbox();
                    for m in 0..2 {
                        plo[m] = plo[m].min(l[m]);
                        phi[m] = phi[m].max(h[m]);
                    }
                    tlo = tlo.min(s.range.0);
                    thi = thi.max(s.range.1);
                }
                (plo, phi, tlo, thi)
            };
            let (Some((i0, i1)), Some((j0, j1))) = (g.span(0, plo[0], phi[0]), g.span(1, plo[1], phi[1]))
            else {
                continue;
            };
            let (tlo, thi) = (tlo as f32, thi as f32);
            let row = |j: usize, rays: &mut [Ray]| -> Tally {
                let mut t = Tally::new();
                let (axis, cell, origin) = geo;
                // Rays along the tool's axis: only the row's chord of the capsule the tip's path
                // sweeps with the tool's radius can meet the tool.
                let (mut ri0, mut ri1) = (i0, i1);
                let yb = origin[1] + (j as f64 + 0.5) * cell;
                // Each piece's chord of the row (empty for a piece left out), and the rays
                // within any of them; with the tool along the rays, the tip path's capsule's.
                let chords: SmallVec<[(f64, f64); 4]> = shadows
                    .iter()
                    .filter(|_| !level)
                    .map(|s| match (prune, s.live) {
                        (false, _) => (f64::NEG_INFINITY, f64::INFINITY),
                        (true, true) => s.chord(yb).unwrap_or((f64::INFINITY, f64::NEG_INFINITY)),
                        (true, false) => (f64::INFINITY, f64::NEG_INFINITY),
                    })
                    .collect();
                let (xl, xh) = match axial {
                    Some((_, _, p0, e)) => {
                        let Some(c) = capsule_chord(p0, e, tool.radius_mm(), yb) else { return t };
                        c
                    }
                    None => chords
                        .iter()
                        .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), c| (l.min(c.0), h.max(c.1))),
                };
                let Some((l, h)) = g_span(origin[0], cell, ni, xl, xh) else { return t };
                ri0 = ri0.max(l);
                ri1 = ri1.min(h);
                if ri0 > ri1 {
                    return t;
                }
                for (i, ray) in rays.iter_mut().enumerate().take(ri1 + 1).skip(ri0) {
                    let (first, last) = {
                        let sl = ray.as_slice();
                        let (Some(first), Some(last)) = (sl.first(), sl.last()) else { continue };
                        (*first, *last)
                    };
                    if last[1] < tlo || first[0] > thi || (prune && !meets(ray, tlo, thi)) {
                        continue;
                    }
                    t.visited += 1;
                    let xa = origin[0] + (i as f64 + 0.5) * cell;
                    let mut ext: SmallVec<[(f64, f64); 4]> = SmallVec::new();
                    let mut swept = false;
                    if let Some((sgn, tip_low, p0, e)) = axial {
                        let rel = [xa - p0[0], yb - p0[1]];
                        let k = ((rel[0] * e[0] + rel[1] * e[1]) * inv_ee).clamp(0.0, 1.0);
                        let (dx, dy) = (rel[0] - k * e[0], rel[1] - k * e[1]);
                        let d2 = dx * dx + dy * dy;
                        if d2 > r2 {
                            continue;
                        }
                        // The tool spans sgn·t >= tip_low + lower(d) on this ray: material that
                        // ends before a lower bound of that is untouched (most rays under a
                        // finishing tool, cut by the move before).
                        // Compared in f32 after rounding the bound (rounding is monotone): a
                        // ray skipped is one whose exact interval, rounded as the subtraction
                        // rounds it, would not reach the material.
                        let bound = tip_low + tool.lower_bound_d2(d2) - 1e-9 - 1e-12 * tip_low.abs();
                        let untouched =
                            if sgn > 0.0 { last[1] <= bound as f32 } else { first[0] >= (-bound) as f32 };
                        if prune && untouched {
                            continue;
                        }
                        if level {
                            let tip = from[g.axis];
                            ext = tool
                                .intervals_at(d2.sqrt())
                                .into_iter()
                                .map(|(l, h)| if sgn > 0.0 { (tip + l, tip + h) } else { (tip - h, tip - l) })
                                .collect();
                            swept = true;
                        }
                    }
                    let mut o = Point3::origin();
                    o[a] = xa;
                    o[b] = yb;
                    if let Some(m) = &across {
                        if let Some(e) = m.extent(tool, &o, from) {
                            ext.push(e);
                        }
                        swept = true;
                    }
                    if !swept {
                        // The ray's interval in each piece's sweep, merged where they overlap
                        // (the pieces of a tool stack along its axis, so on most rays they make
                        // one interval), then subtracted once each.
                        let mut rm: Option<RayMove> = None;
                        let (ray_lo, ray_hi) = (f64::from(first[0]), f64::from(last[1]));
                        for ((piece, shadow), &(cl, ch)) in tool.pieces().iter().zip(&shadows).zip(&chords) {
                            if xa < cl || xa > ch || ray_hi < shadow.range.0 || ray_lo > shadow.range.1 {
                                continue;
                            }
                            // Material only outside the piece's range along the ray (the shank
                            // passing between a relief's peaks): untouched.
                            if prune && !meets(ray, shadow.range.0 as f32, shadow.range.1 as f32) {
                                continue;
                            }
                            if prune && !shadow.may_cut(xa, yb, first[0], last[1]) {
                                continue;
                            }
                            let e = match *piece {
                                // A ball swept straight is a capsule: its own closed form.
                                Piece::Sphere { c, r } => {
                                    sweep::capsule_extent(&o, &d, &(from + f.u * c), &v, r)
                                }
                                // A cylinder seen along rays across its axis: see
                                // `sweep::cylinder_across_extent`.
                                Piece::Frustum { h0, h1, r0, r1 } if r0 == r1 && along.abs() < 1e-12 => {
                                    sweep::cylinder_across_extent(&o, &d, from, &v, &f.u, (h0, h1), r0)
                                }
                                _ => {
                                    rm.get_or_insert_with(|| RayMove::new(&o, &d, from, &v, &f)).extent(piece)
                                }
                            };
                            if let Some(e) = e {
                                ext.push(e);
                            }
                        }
                    }
                    if ext.len() > 1 {
                        ext.sort_unstable_by(|x, y| x.0.total_cmp(&y.0));
                        let mut merged: SmallVec<[(f64, f64); 4]> = SmallVec::new();
                        for e in ext {
                            match merged.last_mut() {
                                Some(m) if e.0 <= m.1 => m.1 = m.1.max(e.1),
                                _ => merged.push(e),
                            }
                        }
                        ext = merged;
                    }
                    let mut changed = false;
                    let mut view: Option<RayView> = None;
                    for (l, h) in ext {
                        subtract(ray, l as f32, h as f32, |sa, sb| {
                            changed = true;
                            let (sa, sb) = (f64::from(sa), f64::from(sb));
                            if primary {
                                t.volume += (sb - sa) * area;
                                t.max_depth = t.max_depth.max(sb - sa);
                                for s in hard {
                                    let mut c = o;
                                    c[axis] = 0.0;
                                    let dd = (s.center - c) - d * (s.center[axis]);
                                    let h2 = s.radius_mm * s.radius_mm - dd.norm_squared();
                                    if h2 > 0.0 {
                                        let half = h2.sqrt();
                                        let ov = (sb.min(s.center[axis] + half)
                                            - sa.max(s.center[axis] - half))
                                        .max(0.0);
                                        t.hard_extra += (s.factor - 1.0) * ov * area;
                                    }
                                }
                                // The engagement, from the same grid (every grid holds the
                                // whole removed volume).
                                let view = *view.get_or_insert_with(|| end.along(&o, &d));
                                for x in [sa, 0.5 * (sa + sb), sb] {
                                    end.observe(&view, x, &mut t);
                                }
                            }
                        });
                    }
                    if changed {
                        t.updated += 1;
                    }
                }
                t
            };
            let rays = &mut g.rays[j0 * ni..(j1 + 1) * ni];
            let count = (i1 - i0 + 1) * (j1 - j0 + 1);
            let tally = if count > PAR_RAYS {
                rays.par_chunks_mut(ni).enumerate().map(|(k, r)| row(j0 + k, r)).reduce(
                    Tally::new,
                    |mut x, y| {
                        x.merge(&y);
                        x
                    },
                )
            } else {
                let mut x = Tally::new();
                for (k, r) in rays.chunks_mut(ni).enumerate() {
                    x.merge(&row(j0 + k, r));
                }
                x
            };
            total.merge(&tally);
        }
        Ok(to_cut(&total, &end))
    }

    /// Cuts a move whose tool pose changes along it: `pose(s)`, `s ∈ [0, 1]`, gives the tip and
    /// the axis (part frame). The move is split into `n` steps, each swept straight at its start
    /// orientation, with `n` the smallest count for which, on every step, the axis turns by at
    /// most `max_error_mm / √(L² + R²)` (so no tool point moves more than `max_error_mm` through
    /// the turn) and the true tip at the step's middle lies within `max_error_mm / 2` of the
    /// straight step (checked, doubling `n` until it holds). The swept volume is then within
    /// `max_error_mm` (plus the chord's half) of the true one at every point.
    ///
    /// Errors: a bad pose, `max_error_mm` not positive, more than [`MAX_STEPS`] steps.
    pub fn cut_moving(
        &mut self,
        tool: &ToolSolid,
        pose: &dyn Fn(f64) -> (Point3<f64>, Unit<Vector3<f64>>),
        max_error_mm: f64,
    ) -> Result<Cut, DexelError> {
        check_error(max_error_mm)?;
        let (p0, u0) = pose(0.0);
        let (p1, u1) = pose(1.0);
        check_point("from", &p0)?;
        check_point("to", &p1)?;
        let reach = (tool.length_mm().powi(2) + tool.radius_mm().powi(2)).sqrt();
        // A first step count from the largest turn seen at 16 samples (the axis may turn and come
        // back); the loop below checks every step and refines it.
        let turn = (1..16).map(|k| u0.angle(&pose(k as f64 / 16.0).1)).fold(u0.angle(&u1), f64::max);
        let mut n = ((turn * 1.25 * reach / max_error_mm).ceil() as usize).max(1);
        loop {
            if n > MAX_STEPS {
                return Err(DexelError::TooManySteps {
                    angle_deg: turn.to_degrees(),
                    steps: n as f64,
                    limit: MAX_STEPS,
                });
            }
            let ok = (0..n).all(|k| {
                let (a, b) = (k as f64 / n as f64, (k + 1) as f64 / n as f64);
                let (pa, ua) = pose(a);
                let (pb, ub) = pose(b);
                let (pm, _) = pose(0.5 * (a + b));
                let chord = (pm - (pa + (pb - pa) * 0.5)).norm();
                ua.angle(&ub) * reach <= max_error_mm && chord <= 0.5 * max_error_mm
            });
            if ok {
                break;
            }
            n *= 2;
        }
        let mut total = Cut::default();
        for k in 0..n {
            let (pa, ua) = pose(k as f64 / n as f64);
            let (pb, _) = pose((k + 1) as f64 / n as f64);
            let cut = self.cut_line(tool, &pa, &pb, &ua)?;
            total.accumulate(&cut);
        }
        Ok(total)
    }

    /// The stock seen from a view, as a height map on `meta`'s grid: for each cell centre
    /// `(x, y)` the highest view-frame Z of material on the vertical through it, from `z_top`
    /// down (`meta.z_min_mm` where there is none). `part_from_view` turns view coordinates into
    /// the part frame.
    ///
    /// The grid whose rays are most nearly along the view's vertical answers. When they are
    /// exactly along it (a face at A = 0, 90, 180 or 270 degrees seen by the grid along Z or Y) the
    /// answer is the end of a dexel, exact; otherwise the vertical is marched in steps of half
    /// that grid's cell and the surface found by bisection to 1e-4 mm.
    ///
    /// Errors: a grid the height map refuses (named by the map's checks).
    pub fn view_heights(
        &self,
        part_from_view: &Rotation3<f64>,
        meta: &HeightMapMeta,
        z_top: f64,
    ) -> Result<HeightMap, DexelError> {
        debug_assert!(self.is_flushed(), "view_heights before flush");
        let floor = meta.z_min_mm;
        let down = part_from_view * Vector3::new(0.0, 0.0, -1.0);
        let best = self.grids.iter().max_by(|a, b| down[a.axis].abs().total_cmp(&down[b.axis].abs()));
        let (w, h) = (meta.width as usize, meta.height as usize);
        let data: Vec<f32> = (0..w * h)
            .into_par_iter()
            .map(|k| {
                let Some(g) = best else { return floor as f32 };
                let (c, r) = (k % w, k / w);
                let x = meta.origin_x_mm + (c as f64 + 0.5) * meta.pixel_mm;
                let y = meta.origin_y_mm + (r as f64 + 0.5) * meta.pixel_mm;
                let start = part_from_view * Point3::new(x, y, z_top);
                let depth = surface_along(g, &start, &down, z_top - floor);
                depth.map_or(floor, |d| z_top - d) as f32
            })
            .collect();
        let mut m = *meta;
        m.z_max_mm = m.z_max_mm.max(z_top);
        HeightMap::new(m, data).map_err(|e| DexelError::Map(e.to_string()))
    }
}

/// Distance along `dir` from `start` to the first material of grid `g`, within `max_len`.
fn surface_along(g: &Grid, start: &Point3<f64>, dir: &Vector3<f64>, max_len: f64) -> Option<f64> {
    let along = dir[g.axis];
    if (along.abs() - 1.0).abs() < 1e-9 {
        let ray = g.ray_at(start)?;
        let s0 = start[g.axis];
        // Walking +axis from s0 or −axis from s0: the nearest interval end in that direction.
        let hit = if along > 0.0 {
            ray.iter().find(|s| f64::from(s[1]) >= s0).map(|s| (f64::from(s[0]) - s0).max(0.0))
        } else {
            ray.iter().rev().find(|s| f64::from(s[0]) <= s0).map(|s| (s0 - f64::from(s[1])).max(0.0))
        };
        return hit.filter(|d| *d <= max_len);
    }
    let step = 0.5 * g.cell;
    let n = (max_len / step).ceil() as usize;
    let mut prev = 0.0;
    for k in 0..=n {
        let d = (k as f64 * step).min(max_len);
        if g.contains(&(start + dir * d)) {
            if k == 0 {
                return Some(0.0);
            }
            let (mut a, mut b) = (prev, d);
            while b - a > 1e-4 {
                let m = 0.5 * (a + b);
                if g.contains(&(start + dir * m)) {
                    b = m;
                } else {
                    a = m;
                }
            }
            return Some(b);
        }
        prev = d;
    }
    None
}

/// A parallelogram `c + x·p + y·q` (`x, y ∈ [0, 1]`) of a grid's plane, grown by `r`: the
/// shadow of a piece's swept axis segment (a ball's swept centre) along the rays.
#[derive(Debug, Clone, Copy)]
struct Shadow {
    c: [f64; 2],
    p: [f64; 2],
    q: [f64; 2],
    r: f64,
    /// 1 / |p|² (0 for a zero edge).
    inv_pp: f64,
    /// The piece's range along the rays.
    range: (f64, f64),
    /// For a ball: its centre's coordinate along the rays at both ends of the move, and r².
    ball: Option<(f64, f64, f64)>,
    /// Whether the range meets the stock's.
    live: bool,
}

impl Shadow {
    fn new(
        c: [f64; 2],
        p: [f64; 2],
        q: [f64; 2],
        r: f64,
        range: (f64, f64),
        ball: Option<(f64, f64, f64)>,
        live: bool,
    ) -> Self {
        let pp = p[0] * p[0] + p[1] * p[1];
        Shadow { c, p, q, r, inv_pp: if pp > 0.0 { 1.0 / pp } else { 0.0 }, range, ball, live }
    }

    /// The parallelogram's box grown by `r`.
    fn bbox(&self) -> ([f64; 2], [f64; 2]) {
        let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
        for (x, y) in [(0.0, 0.0), (1.0, 0.0), (0.0, 1.0), (1.0, 1.0)] {
            for m in 0..2 {
                let v = self.c[m] + x * self.p[m] + y * self.q[m];
                lo[m] = lo[m].min(v - self.r);
                hi[m] = hi[m].max(v + self.r);
            }
        }
        (lo, hi)
    }

    /// The chord of the row `y = yb` through the grown parallelogram (convex: the hull of its
    /// grown edges' chords), or `None`.
    fn chord(&self, yb: f64) -> Option<(f64, f64)> {
        let (c, p, q) = (self.c, self.p, self.q);
        let cp = [c[0] + p[0], c[1] + p[1]];
        let cq = [c[0] + q[0], c[1] + q[1]];
        let edges: &[([f64; 2], [f64; 2])] = if q == [0.0, 0.0] {
            &[(c, p)]
        } else if p == [0.0, 0.0] {
            &[(c, q)]
        } else {
            &[(c, p), (c, q), (cp, q), (cq, p)]
        };
        let mut out: Option<(f64, f64)> = None;
        for &(o, e) in edges {
            if let Some((l, h)) = capsule_chord(o, e, self.r, yb) {
                out = Some(out.map_or((l, h), |(a, b)| (a.min(l), b.max(h))));
            }
        }
        out
    }

    /// Whether the piece can meet material between `bottom` and `top` (the ray's first and last
    /// ends) on the ray at `(x, y)`: for a ball, the swept ball's points on the ray lie within
    /// `√(r² − δ²)` of its centre's range along the rays (`δ` the ray's distance from the
    /// centre's path across them). Compared in `f32` against the ends after rounding the bound
    /// to `f32` (rounding is monotone), so a ray skipped here is one the exact interval, rounded
    /// as the subtraction rounds it, would not change. Other pieces: always `true`.
    #[inline]
    fn may_cut(&self, x: f64, y: f64, bottom: f32, top: f32) -> bool {
        let Some((z0, z1, r2)) = self.ball else { return true };
        let rel = [x - self.c[0], y - self.c[1]];
        let s = ((rel[0] * self.p[0] + rel[1] * self.p[1]) * self.inv_pp).clamp(0.0, 1.0);
        let (dx, dy) = (rel[0] - s * self.p[0], rel[1] - s * self.p[1]);
        let d2 = dx * dx + dy * dy;
        if d2 > r2 * (1.0 + 1e-9) {
            return false;
        }
        let h2 = (r2 - d2).max(0.0);
        // Slack for the rounding of the exact interval's computation.
        let slack = 1e-9 + 1e-12 * (z0.abs() + z1.abs() + r2.sqrt());
        let (zmin, zmax) = (z0.min(z1) - slack, z0.max(z1) + slack);
        // Clear misses without a square root: `top <= zmin − half` and `bottom >= zmax + half`
        // in f64 (then also after rounding to f32).
        let (below, above) = (zmin - f64::from(top), f64::from(bottom) - zmax);
        if (below >= 0.0 && below * below >= h2) || (above >= 0.0 && above * above >= h2) {
            return false;
        }
        let half = h2.sqrt();
        top > (zmin - half) as f32 && bottom < (zmax + half) as f32
    }
}

/// Distance from `p` to the segment `a → b`.
fn segment_distance(p: &Point3<f64>, a: &Point3<f64>, b: &Point3<f64>) -> f64 {
    let e = b - a;
    let ee = e.norm_squared();
    let s = if ee > 0.0 { ((p - a).dot(&e) / ee).clamp(0.0, 1.0) } else { 0.0 };
    (p - (a + e * s)).norm()
}

/// Whether any of a ray's material reaches into `[lo, hi]` (ends included). A sweep whose
/// interval on the ray lies within `[lo, hi]` (after rounding to `f32`, which is monotone) takes
/// nothing from a ray this is `false` for.
#[inline]
fn meets(ray: &[[f32; 2]], lo: f32, hi: f32) -> bool {
    ray.iter().any(|s| s[1] >= lo && s[0] <= hi)
}

/// Index range of the cell centres within `[lo, hi]` on a grid axis from `origin` in cells of
/// `cell`, `n` of them.
fn g_span(origin: f64, cell: f64, n: usize, lo: f64, hi: f64) -> Option<(usize, usize)> {
    let a = ((lo - origin) / cell - 0.5).ceil().max(0.0);
    let b = ((hi - origin) / cell - 0.5).floor().min(n as f64 - 1.0);
    (a <= b && b >= 0.0).then_some((a as usize, b as usize))
}

/// The chord of the row `y = yb` through the capsule of radius `r` around the segment
/// `p0 → p0 + e` (2-D): `[x_min, x_max]`, or `None` when the row misses it (the Z-map's
/// [`capsule_x`](super::removal::capsule_x)), with a whisker of slack for rounding: the exact
/// distance test follows for every ray.
fn capsule_chord(p0: [f64; 2], e: [f64; 2], r: f64, yb: f64) -> Option<(f64, f64)> {
    let len = (e[0] * e[0] + e[1] * e[1]).sqrt();
    let u = if len > 0.0 { (e[0] / len, e[1] / len) } else { (0.0, 0.0) };
    let (lo, hi) =
        super::removal::capsule_x((p0[0], p0[1]), (p0[0] + e[0], p0[1] + e[1]), u, len, yb, r, r * r)?;
    Some((lo - 1e-9, hi + 1e-9))
}

/// Subtracts `[lo, hi]` from a ray, calling `removed(a, b)` for each piece of material taken
/// (in order). In place: the segments it overlaps give way to at most the two ends left
/// standing, so a cut that trims a segment's end moves nothing and allocates nothing.
fn subtract(ray: &mut Ray, lo: f32, hi: f32, mut removed: impl FnMut(f32, f32)) {
    if lo.partial_cmp(&hi) != Some(std::cmp::Ordering::Less) {
        return;
    }
    // The overlapped segments: `first..end` (sorted and disjoint: those ending after `lo` up to
    // the first starting at or after `hi`).
    let first = ray.partition_point(|s| s[1] <= lo);
    let end = first + ray[first..].partition_point(|s| s[0] < hi);
    if first == end {
        return;
    }
    for s in &ray[first..end] {
        removed(s[0].max(lo), s[1].min(hi));
    }
    let (head, tail) = (ray[first][0], ray[end - 1][1]);
    let mut keep: SmallVec<[[f32; 2]; 2]> = SmallVec::new();
    if lo - head > MIN_SEGMENT_MM {
        keep.push([head, lo]);
    }
    if tail - hi > MIN_SEGMENT_MM {
        keep.push([hi, tail]);
    }
    let (old, new) = (end - first, keep.len());
    for (k, seg) in keep.iter().enumerate().take(old) {
        ray[first + k] = *seg;
    }
    if new > old {
        // One segment split in two.
        ray.insert(first + old, keep[old]);
    } else if new < old {
        ray.drain(first + new..end);
        if ray.spilled() && ray.len() <= 1 {
            ray.shrink_to_fit();
        }
    }
}

/// [`subtract`] as a new list: the reference the in-place version is tested against.
#[cfg(test)]
fn subtract_rebuilt(ray: &mut Ray, lo: f32, hi: f32, mut removed: impl FnMut(f32, f32)) {
    if lo.partial_cmp(&hi) != Some(std::cmp::Ordering::Less) || !ray.iter().any(|s| s[1] > lo && s[0] < hi) {
        return;
    }
    let mut out = Ray::new();
    for s in ray.iter() {
        if s[1] <= lo || s[0] >= hi {
            out.push(*s);
            continue;
        }
        removed(s[0].max(lo), s[1].min(hi));
        if lo - s[0] > MIN_SEGMENT_MM {
            out.push([s[0], lo]);
        }
        if s[1] - hi > MIN_SEGMENT_MM {
            out.push([hi, s[1]]);
        }
    }
    *ray = out;
}

fn to_cut(t: &Tally, end: &EndView) -> Cut {
    let engagement_deg = if !t.any {
        0.0
    } else if end.fwd.is_some() {
        let rho_c = t.rho_c2.sqrt();
        if rho_c <= 0.0 || t.e_min > t.e_max {
            0.0
        } else {
            let p = end.half_cell;
            let a = ((t.e_max + p) / rho_c).clamp(-1.0, 1.0).asin();
            let b = ((t.e_min - p) / rho_c).clamp(-1.0, 1.0).asin();
            (a - b).to_degrees().clamp(0.0, 180.0)
        }
    } else {
        180.0 * f64::from(t.sectors.count_ones()) / 36.0
    };
    Cut {
        cells_visited: t.visited,
        cells_updated: t.updated,
        volume_mm3: t.volume,
        hard_volume_mm3: t.volume + t.hard_extra,
        max_depth_mm: t.max_depth,
        engagement_deg: if t.volume > 0.0 { engagement_deg } else { 0.0 },
        axial_depth_mm: if t.volume > 0.0 { t.axial.max(0.0) } else { 0.0 },
    }
}
