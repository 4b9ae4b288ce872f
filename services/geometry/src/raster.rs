//! Point-cloud rasterisation, enclosed-hole filling and coverage.
//!
//! Turns a point cloud already rotated into a face frame (the face's outward normal along +Z) into
//! a [`HeightMap`]: each cell holds the highest Z of the points that fall into it ("max-Z"), then
//! the holes that data encloses are filled, and a coverage map says what was measured, what was
//! filled and what is still missing.
//!
//! # Grid convention (cell edges, centre samples)
//!
//! The grid is the one of [`HeightMapMeta`]: `(x0, y0)` is the **corner** of cell `(0, 0)`, cells
//! are `p × p` squares, column `c` spans `[x0 + c·p, x0 + (c+1)·p)` and row `r` spans
//! `[y0 + r·p, y0 + (r+1)·p)`; row 0 lies at minimum Y. Every cell is **half-open**: a point on the
//! edge between two cells belongs to the cell at higher index, a point exactly at `x0 + c·p`
//! lands in column `c`, and a point on the grid's max edge `x0 + width·p` is outside. The cell's
//! value is read as a sample at its **centre** `(x0 + (c+½)·p, y0 + (r+½)·p)` (fills, coverage
//! centroids and distances all use centres).
//!
//! The edges are the f64 values `x0 + (c as f64)·p` exactly as written, and [`rasterize_max`]
//! decides on them, not on a rounded quotient: it estimates `c` by truncating `(x − x0)·(1/p)` and
//! corrects it by one when `x` lies on the other side of one of those edges, so the fast path
//! agrees bit for bit with the obvious test `x0 + c·p <= x < x0 + (c+1)·p` ([`raster_cell`]).
//! (`HeightMapMeta::cell_of` divides instead and may differ from this within an ulp of an edge.)
//!
//! [`grid_for_roi`] puts the corner of cell `(0, 0)` at the ROI's minimum and takes
//! `width = ceil((x_max − x_min)/p)` columns (at least 1) — exactly: the smallest `n` whose far edge
//! `x_min + n·p` reaches `x_max`, so `0.7 mm / 0.1 mm` gives 7 columns, not 8. The ROI is
//! half-open like the cells; [`Roi::around`] therefore puts its max one ulp above the largest point.
//!
//! CloudCompare's `Rasterize` uses another convention: the bounding-box minimum is the *centre* of
//! cell 0 (`i = ⌊(x − min)/p + ½⌋`); shift the origin by half a pixel (`x0 = min − p/2`) to get
//! the same cells (the benchmark does exactly that to compare with it).
//!
//! # Rasterisation ([`rasterize_max`])
//!
//! Each cell gets the max Z (as f32) of its points, NaN where no point fell. Points with a NaN or
//! infinite coordinate, or a Z too large for a finite f32, are counted in
//! [`RasterStats::non_finite`] and skipped. Heights are kept as order-preserving `u32` keys (0 =
//! empty) so a max is one integer compare, and cell indices are computed branch-free in blocks of
//! points (points that miss the grid go to a dummy cell). Two parallel layouts give the same map:
//! when consecutive points fall into nearby cells (scan order, checked on a sample of the cloud)
//! every rayon thread bins a contiguous share into its own grid and the grids are merged by max;
//! otherwise (shuffled points, or more cells than points) every thread sorts its share's
//! `(cell, key)` pairs into buckets by band of 2^16 cells, and each band is then binned by one
//! task into its part of a single grid, which stays in cache (in rounds of 2^24 points, so the
//! pairs take at most 128 MiB). The map's Z range (`z_min_mm`/`z_max_mm`) is left as given in the
//! grid; [`auto_z_range`] computes a robust one.
//!
//! # Robust Z range ([`auto_z_range`])
//!
//! The 0.1 % and 99.9 % quantiles of the finite values (each end trims `ceil(n/1000)` values once
//! there are at least 100), widened by 2 % of their difference (at least 1 µm) on each side. One
//! stray point among a thousand or more cannot set `z_max`; a genuine feature covering less than
//! 0.1 % of the cells may end above `z_max` (image export clamps it; heights in memory keep it).
//!
//! # Hole filling ([`fill_holes`]): which cells are filled
//!
//! Only finite values are data; every other cell is empty. Let `p` be the pixel size and
//! `max_hole = max_hole_mm`.
//!
//! 1. **Bridge.** Along each of the four line directions — horizontal, vertical and the two
//!    diagonals — the empty cells around an empty cell form a run. The cell is *bridged* along that
//!    direction when the run is bounded by data cells at both ends (a run that reaches the grid
//!    border is not) and the run is at most `max_hole` long: `k·p <= max_hole` for `k` empty cells
//!    along a row or column, `k·p·√2 <= max_hole` along a diagonal (the gap between the two data
//!    cells, 1e-9 relative tolerance). The rule is evaluated once on the raw map, so a fill never
//!    feeds another and nothing grows step by step.
//! 2. **Enclosed holes are all or nothing.** An *enclosed hole* is an 8-connected component of empty
//!    cells that does not touch the grid border. It is filled entirely when every one of its cells
//!    is bridged (the hole is at most `max_hole` thick: any hole whose bounding box fits in
//!    `max_hole × max_hole`, a round hole of diameter up to `max_hole`, a crack at most `max_hole`
//!    wide along a row, column or diagonal), otherwise it stays entirely empty, rim included.
//! 3. **Open regions fill bridged cells only.** In an empty component that touches the border (the
//!    outside of the part, and everything connected to it: scan stripes that run out of the part,
//!    notches) exactly the bridged cells are filled.
//!
//! Consequences: empty columns left by a scanner whose point spacing is wider than the pixel
//! (stripes, even when they run out through the part's outline to the ROI border) are filled;
//! the outside of a convex part is never filled (a line through a point outside a convex set meets
//! it on one side at most); an empty margin between the part and the ROI border stays empty.
//! The rule is a closing along four line directions, so in an *open* region it also fills what is
//! at most `max_hole` wide in one of the directions: a notch of the outline up to `max_hole` wide,
//! and at the inner corner of a wider concave outline the triangle where a diagonal (or, for a
//! rotated corner, an axis) chord between the two walls is at most `max_hole`: at an axis-aligned
//! 90° corner the `i + j + 1 <= ⌊max_hole/(p·√2)⌋` cells, legs about `max_hole/√2`.
//!
//! # Hole filling: the values
//!
//! A selected cell takes, from the **valid raw cells** within its search radius (centre to centre,
//! `dx² + dy² <= (radius/p)²` in cells), either the highest value ([`FillMethod::Max`]) or the
//! inverse-distance-weighted mean with weights `1/d^power`, `d` in mm ([`FillMethod::Idw`];
//! `power = 0` is the plain mean). Filled cells never serve as samples, so the result does not
//! depend on any order. The radius is `radius_mm` when given; by default it is chosen **per cell**:
//! the distance to the cell's nearest valid sample plus `√2·p` (one more ring of samples), at most
//! `max_hole/2 + √2·p` (and [`MAX_FILL_RADIUS_PX`] pixels). Every bridged cell has the nearer end
//! of its bridge within that cap; a 1-pixel stripe sees both of its sides and little more, so the
//! fill stays local (a fixed radius of `max_hole/2` would average, or for `Max` take the top of, a
//! 2 mm wide neighbourhood across every stripe). A selected cell without any sample within the
//! radius stays empty ([`FillReport::left_empty_enclosed`]). An IDW cell whose highest and lowest
//! samples (each at its nearest distance) differ by more than a slope of [`FILL_STEP_SLOPE`]
//! (60°) rises over the path between them through the cell lies at a step whose edge the scan
//! did not show (a chamfer or a wall's top between a high and a low level): the mean there is
//! neither level and would cut into the edge, so the cell takes the highest sample, as the
//! roughing map does (material is left at the foot of the step, never cut from its edge). The
//! same test runs on the two ends of each bridge through the cell, which may lie past the radius:
//! in a gap wider than two rings at a step (a cove or a wall's foot the scanner's line did not
//! reach, seen from one side as a floor), the cells near the low side see only that side, and
//! would otherwise extend the floor flat under a surface that rises; where a bridge's ends imply
//! such a step, the cell takes at least the bridge's higher end. The
//! search walks the offsets nearest
//! first and stops at the radius: cost `O(cells)` for bridges and components plus
//! `O(Σ (radius/p)²)` over the filled cells only.
//!
//! # Coverage ([`coverage`])
//!
//! Per cell: 1 = measured (finite in the raw map), 0.5 = filled (empty in the raw map, finite in
//! the filled one), 0 = a hole (empty in both, inside the footprint), NaN = outside the footprint.
//! The footprint is the measured and filled cells plus the cells still empty after filling whose
//! 8-connected empty component does not touch the grid border (the enclosure of rule 2; the bridge
//! part of the rule is already in the filled cells). Holes are the 8-connected components of the
//! unmeasured footprint cells (filled or still empty) of the raw map; the largest by area is
//! reported with its centroid (mean of cell centres) and bounding box (cell edges). Because
//! stripes count as holes there, the components still empty after filling are reported apart
//! ([`CoverageStats::largest_unfilled_hole`]): those are what a rescan has to cover.

use std::f64::consts::SQRT_2;
use std::fmt;

use crate::{CloudPoint, HeightMap, HeightMapMeta, MAX_CELLS};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::GeometryError;

/// Why a grid cannot be built or a map cannot be rasterised or filled.
///
/// Parameters are named as the job's `reconstruct` section names them, relative to it (`roi`,
/// `pixel_mm`, `fill.max_hole_mm`, ...); a caller that exposes them under another path prefixes
/// the field (the reconstruction service adds `reconstruct.`).
#[derive(Debug, thiserror::Error)]
pub enum RasterError {
    /// A parameter is outside its domain.
    #[error("invalid {field} = {value}: {reason}")]
    InvalidParameter { field: String, value: String, reason: String },

    /// A grid or map rejected by its own checks.
    #[error(transparent)]
    Geometry(#[from] GeometryError),
}

impl RasterError {
    /// Shorthand for [`RasterError::InvalidParameter`].
    pub fn param(field: impl Into<String>, value: impl fmt::Display, reason: impl Into<String>) -> Self {
        RasterError::InvalidParameter { field: field.into(), value: value.to_string(), reason: reason.into() }
    }
}

/// Result with [`RasterError`].
pub type Result<T, E = RasterError> = std::result::Result<T, E>;

/// Largest fill radius, in pixels (a larger `radius_mm` is refused; the derived default is capped).
pub const MAX_FILL_RADIUS_PX: f64 = 128.0;

/// Largest IDW power accepted.
pub const MAX_IDW_POWER: f64 = 16.0;

/// Smallest pixel relative to the largest ROI coordinate: finer cells would have edges closer
/// than a few thousand ulps.
const MIN_RELATIVE_PIXEL: f64 = 1e-12;

/// Relative tolerance of the bridge length test.
const GAP_TOLERANCE: f64 = 1e-9;

/// Region of interest in the face frame, mm.
///
/// Half-open like the cells: `[x_min_mm, x_max_mm) × [y_min_mm, y_max_mm)`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Roi {
    /// Minimum X (the grid's origin X).
    pub x_min_mm: f64,
    /// Minimum Y (the grid's origin Y).
    pub y_min_mm: f64,
    /// Maximum X (exclusive).
    pub x_max_mm: f64,
    /// Maximum Y (exclusive).
    pub y_max_mm: f64,
}

impl fmt::Display for Roi {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "[{}, {}) x [{}, {}) mm", self.x_min_mm, self.x_max_mm, self.y_min_mm, self.y_max_mm)
    }
}

impl Roi {
    /// Checks: all four values finite, `x_min_mm < x_max_mm`, `y_min_mm < y_max_mm`
    /// (errors name `roi`).
    pub fn validate(&self) -> Result<()> {
        let all = [self.x_min_mm, self.y_min_mm, self.x_max_mm, self.y_max_mm];
        if !all.iter().all(|v| v.is_finite()) {
            return Err(RasterError::param("roi", self, "all bounds must be finite"));
        }
        if self.x_min_mm >= self.x_max_mm {
            return Err(RasterError::param("roi", self, "x_min_mm must be less than x_max_mm"));
        }
        if self.y_min_mm >= self.y_max_mm {
            return Err(RasterError::param("roi", self, "y_min_mm must be less than y_max_mm"));
        }
        Ok(())
    }

    /// The XY bounding box of the points with three finite coordinates, grown by `margin_mm` on
    /// every side (a negative or non-finite margin counts as 0), its max moved up by one ulp so the
    /// highest points lie inside the half-open ROI. `None` without such points.
    pub fn around<P: CloudPoint>(points: &[P], margin_mm: f64) -> Option<Roi> {
        let empty = (f64::INFINITY, f64::INFINITY, f64::NEG_INFINITY, f64::NEG_INFINITY);
        let (x0, y0, x1, y1) = points
            .par_iter()
            .with_min_len(1 << 14)
            .fold(
                || empty,
                |(x0, y0, x1, y1), p| {
                    let p = p.at();
                    if p.x.is_finite() && p.y.is_finite() && p.z.is_finite() {
                        (x0.min(p.x), y0.min(p.y), x1.max(p.x), y1.max(p.y))
                    } else {
                        (x0, y0, x1, y1)
                    }
                },
            )
            .reduce(|| empty, |a, b| (a.0.min(b.0), a.1.min(b.1), a.2.max(b.2), a.3.max(b.3)));
        if x0 > x1 {
            return None;
        }
        let m = if margin_mm.is_finite() && margin_mm > 0.0 { margin_mm } else { 0.0 };
        let roi = Roi {
            x_min_mm: x0 - m,
            y_min_mm: y0 - m,
            x_max_mm: (x1 + m).next_up(),
            y_max_mm: (y1 + m).next_up(),
        };
        roi.validate().ok().map(|()| roi)
    }

    /// `x_max_mm − x_min_mm`.
    pub fn width_mm(&self) -> f64 {
        self.x_max_mm - self.x_min_mm
    }

    /// `y_max_mm − y_min_mm`.
    pub fn height_mm(&self) -> f64 {
        self.y_max_mm - self.y_min_mm
    }
}

/// Smallest `n >= 1` with `min + n·p >= max` (that is `ceil((max − min)/p)` without the rounding
/// surplus), or `None` beyond `u32::MAX`.
fn cells_along(min: f64, max: f64, p: f64) -> Option<u32> {
    let est = ((max - min) / p).ceil();
    // Also rejects NaN and infinity.
    if est.is_nan() || est > f64::from(u32::MAX) {
        return None;
    }
    let mut n = (est as u64).max(1);
    while n > 1 && min + (n - 1) as f64 * p >= max {
        n -= 1;
    }
    while min + n as f64 * p < max {
        n += 1;
    }
    u32::try_from(n).ok()
}

/// The grid covering `roi` with square cells of `pixel_mm`: origin (corner of cell (0, 0)) at
/// `(x_min, y_min)`, `width = ceil(extent/p)` (at least 1; exactly the smallest count whose far edge
/// reaches the ROI's max, see the module docs), Z range `[0, 1]`, view `+Z`.
///
/// Errors: an invalid ROI (`roi`); a non-finite or non-positive pixel, or one too fine
/// for the coordinates' magnitude (`pixel_mm`); more than [`MAX_CELLS`] cells
/// (`pixel_mm`, naming the grid size and the limit).
pub fn grid_for_roi(roi: &Roi, pixel_mm: f64) -> Result<HeightMapMeta> {
    roi.validate()?;
    if !(pixel_mm.is_finite() && pixel_mm > 0.0) {
        return Err(RasterError::param("pixel_mm", pixel_mm, "must be finite and positive"));
    }
    let magnitude =
        [roi.x_min_mm, roi.y_min_mm, roi.x_max_mm, roi.y_max_mm].iter().fold(0.0f64, |m, v| m.max(v.abs()));
    if pixel_mm < magnitude * MIN_RELATIVE_PIXEL {
        return Err(RasterError::param(
            "pixel_mm",
            pixel_mm,
            format!(
                "is too fine for coordinates up to {magnitude} mm (at least {} mm)",
                magnitude * MIN_RELATIVE_PIXEL
            ),
        ));
    }
    let too_many = || {
        let w = (roi.width_mm() / pixel_mm).ceil();
        let h = (roi.height_mm() / pixel_mm).ceil();
        RasterError::param(
            "pixel_mm",
            pixel_mm,
            format!(
                "gives a {w}x{h} grid over the {} x {} mm region of interest, more than the {MAX_CELLS} cells allowed",
                roi.width_mm(),
                roi.height_mm()
            ),
        )
    };
    let width = cells_along(roi.x_min_mm, roi.x_max_mm, pixel_mm).ok_or_else(too_many)?;
    let height = cells_along(roi.y_min_mm, roi.y_max_mm, pixel_mm).ok_or_else(too_many)?;
    if u64::from(width) * u64::from(height) > MAX_CELLS {
        return Err(too_many());
    }
    let mut meta = HeightMapMeta::new(width, height, pixel_mm);
    meta.origin_x_mm = roi.x_min_mm;
    meta.origin_y_mm = roi.y_min_mm;
    meta.validate()?;
    Ok(meta)
}

/// What happened to the points of one [`rasterize_max`] call.
///
/// `points_in = points_binned + points_outside + non_finite`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct RasterStats {
    /// Points given.
    pub points_in: usize,
    /// Points that fell into a cell.
    pub points_binned: usize,
    /// Finite points outside the grid.
    pub points_outside: usize,
    /// Points with a NaN or infinite coordinate, or a Z beyond the f32 range.
    pub non_finite: usize,
}

/// `1.5·2^52`: adding and subtracting it rounds an f64 below 2^51 in magnitude to the nearest
/// integer, and the low 32 bits of the sum are that integer.
const ROUND_MAGIC: f64 = 6_755_399_441_055_744.0;

/// Binning along one axis: edges `origin + c·pixel`, `n` cells.
#[derive(Debug, Clone, Copy)]
struct AxisBins {
    origin: f64,
    pixel: f64,
    inv: f64,
    n_f: f64,
}

impl AxisBins {
    fn new(origin: f64, pixel: f64, n: u32) -> Self {
        AxisBins { origin, pixel, inv: 1.0 / pixel, n_f: f64::from(n) }
    }

    /// The `c` (an integer, as f64) with `origin + c·pixel <= v < origin + (c+1)·pixel` for `v`
    /// inside the grid or within a cell of it; some integer outside `0..n` for anything else (NaN
    /// included). Branch free: the quotient, clamped to `[-1, n]` and rounded, is off by at most
    /// one cell, and the two exact edge tests correct it.
    #[inline(always)]
    fn cell(&self, v: f64) -> f64 {
        // f64::max maps NaN to -1.
        let t = ((v - self.origin) * self.inv).max(-1.0).min(self.n_f);
        let mut c = (t + ROUND_MAGIC) - ROUND_MAGIC;
        c -= if v < self.origin + c * self.pixel { 1.0 } else { 0.0 };
        c += if v >= self.origin + (c + 1.0) * self.pixel { 1.0 } else { 0.0 };
        c
    }

    #[inline(always)]
    fn inside(&self, c: f64) -> bool {
        (c >= 0.0) & (c < self.n_f)
    }
}

/// Row-major binning of XY into a grid.
#[derive(Debug, Clone, Copy)]
struct Binner {
    x: AxisBins,
    y: AxisBins,
    width_f: f64,
    /// Index standing for "not binned": one past the last cell.
    dummy: u32,
}

impl Binner {
    fn new(grid: &HeightMapMeta) -> Self {
        Binner {
            x: AxisBins::new(grid.origin_x_mm, grid.pixel_mm, grid.width),
            y: AxisBins::new(grid.origin_y_mm, grid.pixel_mm, grid.height),
            width_f: f64::from(grid.width),
            // A valid grid has at most MAX_CELLS = 2^28 cells.
            dummy: u32::try_from(grid.cell_count()).unwrap_or(u32::MAX),
        }
    }
}

/// The cell `(col, row)` that [`rasterize_max`] puts a point at `(x_mm, y_mm)` into: the one with
/// `x0 + col·p <= x < x0 + (col+1)·p` and likewise in Y, or `None` outside the grid or for
/// non-finite input.
pub fn raster_cell(grid: &HeightMapMeta, x_mm: f64, y_mm: f64) -> Option<(u32, u32)> {
    let b = Binner::new(grid);
    let (c, r) = (b.x.cell(x_mm), b.y.cell(y_mm));
    (x_mm.is_finite() && y_mm.is_finite() && b.x.inside(c) && b.y.inside(r)).then_some((c as u32, r as u32))
}

const SIGN: u32 = 0x8000_0000;

/// Order-preserving key of a non-NaN f32 (never 0, which marks "empty").
#[inline(always)]
fn key_of(z: f32) -> u32 {
    let b = z.to_bits();
    if b & SIGN != 0 { !b } else { b | SIGN }
}

/// Inverse of [`key_of`]; 0 gives NaN.
#[inline(always)]
fn value_of(k: u32) -> f32 {
    if k == 0 {
        f32::NAN
    } else if k & SIGN != 0 {
        f32::from_bits(k & !SIGN)
    } else {
        f32::from_bits(!k)
    }
}

/// Points handled per block by the branch-free index pass.
const BLOCK: usize = 256;

/// Counts of a block or share: `(binned, non_finite)`.
type Counts = (usize, usize);

/// Cell index (or `bins.dummy`) and key of every point of `block` (at most [`BLOCK`] points).
#[inline(always)]
fn locate_block<P: CloudPoint>(
    block: &[P],
    bins: &Binner,
    idx: &mut [u32; BLOCK],
    key: &mut [u32; BLOCK],
) -> Counts {
    let mut binned = 0usize;
    for ((p, i), k) in block.iter().zip(idx.iter_mut()).zip(key.iter_mut()) {
        let p = p.at();
        let z = p.z as f32;
        // Non-finite X or Y land outside by themselves; the Z test is false for NaN and infinities.
        let (c, r) = (bins.x.cell(p.x), bins.y.cell(p.y));
        let inside = bins.x.inside(c) & bins.y.inside(r) & (z.abs() < f32::INFINITY);
        // Exact: the index is an integer below 2^28.
        let at = ((r * bins.width_f + c) + ROUND_MAGIC).to_bits() as u32;
        *i = if inside { at } else { bins.dummy };
        *k = key_of(z);
        binned += usize::from(inside);
    }
    // Tell the non-finite points from those outside the grid (only when some missed it).
    let mut non_finite = 0usize;
    if binned < block.len() {
        for (p, &i) in block.iter().zip(idx.iter()) {
            let p = p.at();
            let finite = p.x.is_finite() && p.y.is_finite() && (p.z as f32).is_finite();
            non_finite += usize::from(i == bins.dummy && !finite);
        }
    }
    (binned, non_finite)
}

/// Bins `points` into `keys` (one entry per cell plus the dummy at the end) by max.
fn bin_direct<P: CloudPoint>(points: &[P], bins: &Binner, keys: &mut [u32]) -> Counts {
    let (mut idx, mut key) = ([0u32; BLOCK], [0u32; BLOCK]);
    let mut counts = (0, 0);
    for block in points.chunks(BLOCK) {
        let (b, n) = locate_block(block, bins, &mut idx, &mut key);
        counts = (counts.0 + b, counts.1 + n);
        for (&i, &k) in idx.iter().zip(&key).take(block.len()) {
            if let Some(cell) = keys.get_mut(i as usize) {
                *cell = (*cell).max(k);
            }
        }
    }
    counts
}

/// Appends `(index << 32) | key` of every binned point of `points` to the bucket of its band
/// (`index >> shift`).
fn bin_partition<P: CloudPoint>(points: &[P], bins: &Binner, shift: u32, buckets: &mut [Vec<u64>]) -> Counts {
    let (mut idx, mut key) = ([0u32; BLOCK], [0u32; BLOCK]);
    let mut counts = (0, 0);
    for block in points.chunks(BLOCK) {
        let (b, n) = locate_block(block, bins, &mut idx, &mut key);
        counts = (counts.0 + b, counts.1 + n);
        for (&i, &k) in idx.iter().zip(&key).take(block.len()) {
            if i != bins.dummy
                && let Some(bucket) = buckets.get_mut((i >> shift) as usize)
            {
                bucket.push((u64::from(i) << 32) | u64::from(k));
            }
        }
    }
    counts
}

/// How [`rasterize_max`] spreads the work (all give the same map).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Strategy {
    /// One thread, one grid.
    Serial,
    /// Every thread bins a contiguous share into its own key grid, merged by max: best when
    /// consecutive points fall into nearby cells (scan order), so each grid is touched locally.
    Direct,
    /// Every thread sorts its share's (cell, key) pairs into buckets by band of cells, then every
    /// band is binned by one task into its part of a single grid, which stays in cache: for
    /// points in any order, and for grids with more cells than points.
    Partition,
}

/// Points below which one thread bins everything.
const SERIAL_POINTS: usize = 1 << 16;

/// Extra memory the private grids of [`Strategy::Direct`] may take, bytes.
const PRIVATE_GRID_BUDGET: usize = 1 << 30;

/// Points per round of [`Strategy::Partition`] (bounds its pair buffers to 8 bytes × this).
#[cfg(not(test))]
const PARTITION_ROUND: usize = 1 << 24;
/// Small rounds in tests, so several run.
#[cfg(test)]
const PARTITION_ROUND: usize = 1 << 12;

/// Whether consecutive points mostly fall within a few rows of each other (scan order): checked on
/// 64 windows of 32 consecutive points spread over the cloud.
fn is_local<P: CloudPoint>(points: &[P], bins: &Binner) -> bool {
    let (mut idx, mut key) = ([0u32; BLOCK], [0u32; BLOCK]);
    let (mut near, mut pairs) = (0usize, 0usize);
    let reach = (bins.width_f * 4.0).min(f64::from(u32::MAX)) as u32;
    for k in 0..64 {
        let start = k * points.len() / 64;
        let window = &points[start..(start + 32).min(points.len())];
        locate_block(window, bins, &mut idx, &mut key);
        for pair in idx[..window.len()].windows(2) {
            if pair[0] != bins.dummy && pair[1] != bins.dummy {
                pairs += 1;
                near += usize::from(pair[0].abs_diff(pair[1]) <= reach);
            }
        }
    }
    2 * near >= pairs
}

fn choose_strategy<P: CloudPoint>(points: &[P], bins: &Binner, cells: usize) -> Strategy {
    let threads = rayon::current_num_threads().max(1);
    if threads == 1 || points.len() < SERIAL_POINTS {
        Strategy::Serial
    } else if points.len() >= cells
        && (threads - 1).saturating_mul(cells).saturating_mul(4) <= PRIVATE_GRID_BUDGET
        && is_local(points, bins)
    {
        Strategy::Direct
    } else {
        Strategy::Partition
    }
}

/// The bits of the f32 max per cell (`cells + 1` entries, the last one the dummy) and the counts.
fn rasterize_keys<P: CloudPoint>(
    points: &[P],
    bins: &Binner,
    cells: usize,
    strategy: Strategy,
) -> (Vec<u32>, Counts) {
    let add = |a: Counts, b: Counts| (a.0 + b.0, a.1 + b.1);
    match strategy {
        Strategy::Serial => {
            let mut keys = vec![0u32; cells + 1];
            let counts = bin_direct(points, bins, &mut keys);
            keys.iter_mut().for_each(|k| *k = value_of(*k).to_bits());
            (keys, counts)
        }
        Strategy::Direct => {
            let parts = rayon::current_num_threads().max(1);
            let per = points.len().div_ceil(parts).max(1);
            let mut grids: Vec<(Vec<u32>, Counts)> = points
                .par_chunks(per)
                .map(|share| {
                    let mut keys = vec![0u32; cells + 1];
                    let counts = bin_direct(share, bins, &mut keys);
                    (keys, counts)
                })
                .collect();
            let (mut acc, mut counts) = grids.pop().unwrap_or_else(|| (vec![0u32; cells + 1], (0, 0)));
            for (_, c) in &grids {
                counts = add(counts, *c);
            }
            const MERGE: usize = 1 << 16;
            acc.par_chunks_mut(MERGE).enumerate().for_each(|(ci, a)| {
                let (start, len) = (ci * MERGE, a.len());
                for (g, _) in &grids {
                    for (x, &y) in a.iter_mut().zip(&g[start..start + len]) {
                        *x = (*x).max(y);
                    }
                }
                a.iter_mut().for_each(|k| *k = value_of(*k).to_bits());
            });
            (acc, counts)
        }
        Strategy::Partition => {
            // Bands of 2^16 cells (256 KiB of keys: cache-sized), at most 1024 of them.
            let mut shift = 16u32;
            while (cells >> shift) >= 1024 {
                shift += 1;
            }
            let bands = (cells >> shift) + 1;
            let parts = rayon::current_num_threads().max(1);
            let mut keys = vec![0u32; cells + 1];
            let mut sets: Vec<Vec<Vec<u64>>> = (0..parts).map(|_| vec![Vec::new(); bands]).collect();
            let mut counts = (0, 0);
            for round in points.chunks(PARTITION_ROUND) {
                let per = round.len().div_ceil(parts).max(1);
                let c = round
                    .par_chunks(per)
                    .zip(sets.par_iter_mut())
                    .map(|(share, set)| {
                        // Room for an even spread, so most pushes never reallocate.
                        let even = share.len() / bands + 64;
                        for bucket in set.iter_mut() {
                            bucket.clear();
                            bucket.reserve(even);
                        }
                        bin_partition(share, bins, shift, set)
                    })
                    .reduce(|| (0, 0), add);
                counts = add(counts, c);
                let sets = &sets;
                keys.par_chunks_mut(1 << shift).enumerate().for_each(|(band, g)| {
                    let base = (band as u64) << shift;
                    for set in sets {
                        for &e in set.get(band).map_or(&[][..], Vec::as_slice) {
                            if let Some(x) = g.get_mut(((e >> 32) - base) as usize) {
                                *x = (*x).max(e as u32);
                            }
                        }
                    }
                });
            }
            keys.par_chunks_mut(1 << 16).for_each(|g| g.iter_mut().for_each(|k| *k = value_of(*k).to_bits()));
            (keys, counts)
        }
    }
}

/// The number of cells of a valid grid, as an index.
pub(crate) fn checked_cells(grid: &HeightMapMeta) -> Result<usize> {
    grid.validate()?;
    Ok(usize::try_from(grid.cell_count()).map_err(|_| GeometryError::TooManyCells {
        width: u64::from(grid.width),
        height: u64::from(grid.height),
        limit: usize::MAX as u64,
    })?)
}

impl RasterStats {
    /// The stats of `points_in` points of which `binned` fell into a cell and `non_finite` were
    /// not finite (the rest fell outside).
    pub(crate) fn of(points_in: usize, binned: usize, non_finite: usize) -> Self {
        RasterStats {
            points_in,
            points_binned: binned,
            points_outside: points_in - binned - non_finite,
            non_finite,
        }
    }
}

fn rasterize_with<P: CloudPoint>(
    points: &[P],
    grid: &HeightMapMeta,
    strategy: Option<Strategy>,
) -> Result<(HeightMap, RasterStats)> {
    let cells = checked_cells(grid)?;
    let bins = Binner::new(grid);
    let strategy = strategy.unwrap_or_else(|| choose_strategy(points, &bins, cells));
    let (mut bits, (binned, non_finite)) = rasterize_keys(points, &bins, cells, strategy);
    bits.truncate(cells);
    // Same size and alignment: the collect reuses the allocation.
    let data: Vec<f32> = bits.into_iter().map(f32::from_bits).collect();
    let stats = RasterStats::of(points.len(), binned, non_finite);
    Ok((HeightMap::new(*grid, data)?, stats))
}

/// Max Z per cell (cell = the half-open square of the grid convention, see the module docs), NaN
/// where no point fell, in parallel (rayon). The returned map has exactly the metadata of `grid`:
/// its Z range is left as given (use [`auto_z_range`] on the result for a robust one).
///
/// # Panics
///
/// If `grid` fails [`HeightMapMeta::validate`] (grids from [`grid_for_roi`] never do); use
/// [`try_rasterize_max`] for a `Result`.
pub fn rasterize_max<P: CloudPoint>(points: &[P], grid: &HeightMapMeta) -> (HeightMap, RasterStats) {
    match rasterize_with(points, grid, None) {
        Ok(out) => out,
        Err(e) => panic!("rasterize_max needs a valid grid: {e}"),
    }
}

/// [`rasterize_max`] returning an error for an invalid grid instead of panicking.
pub fn try_rasterize_max<P: CloudPoint>(
    points: &[P],
    grid: &HeightMapMeta,
) -> Result<(HeightMap, RasterStats)> {
    rasterize_with(points, grid, None)
}

/// Median Z per cell, NaN where no point fell: the same cells, grid and [`RasterStats`] as
/// [`rasterize_max`] (a point is binned by the same exact edge test), but each cell holds the
/// median of its points' Z as f32 (for an even count, the mean of the two middle values, computed
/// in f64). Under symmetric measurement noise this is an unbiased estimate of the surface at the
/// cell, where the max stands about two standard deviations proud of it with a dozen points per
/// cell; it is not an upper bound, so roughing and anything that must never cut into the part
/// keep the max.
///
/// Cost: one pass to locate every point, a counting sort of the Z values by cell
/// (`O(points + cells)` memory: 4 bytes a point and 8 a cell) and a selection per cell, in
/// parallel over cells.
pub fn rasterize_median<P: CloudPoint>(
    points: &[P],
    grid: &HeightMapMeta,
) -> Result<(HeightMap, RasterStats)> {
    let cells = checked_cells(grid)?;
    let (index, binned, non_finite) = cell_indices(points, grid);
    // Counting sort of the binned Z values by cell.
    let mut start = vec![0usize; cells + 1];
    for &i in &index {
        if let Some(n) = start.get_mut(i as usize + 1) {
            *n += 1;
        }
    }
    for c in 0..cells {
        start[c + 1] += start[c];
    }
    let mut next = start.clone();
    let mut z = vec![0f32; binned];
    for (&i, p) in index.iter().zip(points) {
        if let Some(at) = next.get_mut(i as usize).filter(|_| (i as usize) < cells) {
            z[*at] = p.at().z as f32;
            *at += 1;
        }
    }
    drop(index);
    // One mutable run of Z values per cell, then a selection per cell in parallel.
    let mut runs: Vec<&mut [f32]> = Vec::with_capacity(cells);
    let mut rest: &mut [f32] = &mut z;
    for c in 0..cells {
        let (run, tail) = rest.split_at_mut(start[c + 1] - start[c]);
        runs.push(run);
        rest = tail;
    }
    let data: Vec<f32> = runs.into_par_iter().map(median_of).collect();
    let stats = RasterStats::of(points.len(), binned, non_finite);
    Ok((HeightMap::new(*grid, data)?, stats))
}

/// The cell of every point, row-major (`row · width + col`, the cell [`raster_cell`] gives; the
/// grid's cell count for a point not binned), with the counts of points binned and not finite.
pub(crate) fn cell_indices<P: CloudPoint>(points: &[P], grid: &HeightMapMeta) -> (Vec<u32>, usize, usize) {
    let bins = Binner::new(grid);
    let mut index = vec![bins.dummy; points.len()];
    let (binned, non_finite) = index
        .par_chunks_mut(BLOCK)
        .zip(points.par_chunks(BLOCK))
        .map(|(out, block)| {
            let (mut idx, mut key) = ([0u32; BLOCK], [0u32; BLOCK]);
            let counts = locate_block(block, &bins, &mut idx, &mut key);
            out.copy_from_slice(&idx[..block.len()]);
            counts
        })
        .reduce(|| (0, 0), |a, b| (a.0 + b.0, a.1 + b.1));
    (index, binned, non_finite)
}

/// Median of finite values (reorders them); NaN for none.
fn median_of(v: &mut [f32]) -> f32 {
    let n = v.len();
    if n == 0 {
        return f32::NAN;
    }
    let (below, &mut hi, _) = v.select_nth_unstable_by(n / 2, f32::total_cmp);
    if n % 2 == 1 {
        return hi;
    }
    // The largest of the lower half is the other middle value.
    let lo = below.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    ((f64::from(lo) + f64::from(hi)) / 2.0) as f32
}

/// Robust automatic Z range of a map's cells or of points' Z: the 0.1 % and 99.9 % quantiles of
/// the finite values (each end trims `ceil(n/1000)` values when `n >= 100`, none below), widened
/// by 2 % of their difference and at least 1 µm on each side, so a single stray point cannot set
/// `z_max` (or `z_min`). `None` when no value is finite. Always `lo < hi`.
pub fn auto_z_range(values: impl Iterator<Item = f32>) -> Option<(f64, f64)> {
    let mut v: Vec<f32> = values.filter(|z| z.is_finite()).collect();
    let n = v.len();
    if n == 0 {
        return None;
    }
    let trim = if n < 100 { 0 } else { n.div_ceil(1000) };
    let lo = f64::from(*v.select_nth_unstable_by(trim, f32::total_cmp).1);
    let hi = f64::from(*v.select_nth_unstable_by(n - 1 - trim, f32::total_cmp).1);
    let pad = (0.02 * (hi - lo)).max(1e-3);
    Some((lo - pad, hi + pad))
}

/// How a filled cell gets its value.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub enum FillMethod {
    /// Highest valid sample within the radius.
    Max,
    /// Inverse-distance-weighted mean of the valid samples within the radius, weight `1/d^power`
    /// with `d` in mm (`power` finite, in `[0, 16]`; 0 = plain mean).
    Idw {
        /// Exponent of the distance.
        power: f64,
    },
}

/// Parameters of [`fill_holes`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct FillParams {
    /// How filled cells get their value.
    pub method: FillMethod,
    /// Largest gap filled, mm (see the module docs for the exact rule); 0 fills nothing.
    pub max_hole_mm: f64,
    /// Sample radius, mm. `None`: per cell, the distance to its nearest valid sample plus
    /// `√2·pixel`, at most `max_hole_mm/2 + √2·pixel` and [`MAX_FILL_RADIUS_PX`] pixels (module docs).
    pub radius_mm: Option<f64>,
}

impl Default for FillParams {
    /// IDW with power 2 of holes up to 2 mm, derived radius.
    fn default() -> Self {
        FillParams { method: FillMethod::Idw { power: 2.0 }, max_hole_mm: 2.0, radius_mm: None }
    }
}

impl FillParams {
    /// Checks the parameters for a grid of `pixel_mm` and returns the largest sample radius in mm
    /// (`radius_mm`, or the cap of the per-cell default). Errors name `fill.max_hole_mm`, `fill.radius_mm` or
    /// `fill.power`.
    pub fn radius_for(&self, pixel_mm: f64) -> Result<f64> {
        let mh = self.max_hole_mm;
        if !(mh.is_finite() && mh >= 0.0) {
            return Err(RasterError::param("fill.max_hole_mm", mh, "must be finite and not negative"));
        }
        if let FillMethod::Idw { power } = self.method
            && !(power.is_finite() && (0.0..=MAX_IDW_POWER).contains(&power))
        {
            return Err(RasterError::param("fill.power", power, format!("must be in [0, {MAX_IDW_POWER}]")));
        }
        match self.radius_mm {
            Some(r) if !(r.is_finite() && r > 0.0) => {
                Err(RasterError::param("fill.radius_mm", r, "must be finite and positive"))
            }
            Some(r) if r / pixel_mm > MAX_FILL_RADIUS_PX => Err(RasterError::param(
                "fill.radius_mm",
                r,
                format!(
                    "is {:.1} pixels of {pixel_mm} mm; at most {MAX_FILL_RADIUS_PX} pixels are searched",
                    r / pixel_mm
                ),
            )),
            Some(r) => Ok(r),
            None => Ok((mh / 2.0 + SQRT_2 * pixel_mm).min(MAX_FILL_RADIUS_PX * pixel_mm)),
        }
    }
}

/// What [`fill_holes`] did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct FillReport {
    /// Cells given a value.
    pub filled: usize,
    /// Empty cells of enclosed holes left empty (holes thicker than `max_hole_mm`), plus cells
    /// selected for filling that had no valid sample within the radius.
    pub left_empty_enclosed: usize,
    /// Number of enclosed holes left empty because they are thicker than `max_hole_mm`.
    pub holes_too_large: usize,
}

/// Bits of the bridge mask, one per direction.
const BRIDGE_H: u8 = 1;
const BRIDGE_V: u8 = 2;
/// Diagonal along (1, 1).
const BRIDGE_D1: u8 = 4;
/// Diagonal along (-1, 1).
const BRIDGE_D2: u8 = 8;

/// Largest bridged run, in cells, along an axis and along a diagonal.
fn gap_limits(max_hole_mm: f64, pixel_mm: f64) -> (u32, u32) {
    let cap = f64::from(u32::MAX - 2);
    let axis = (max_hole_mm / pixel_mm * (1.0 + GAP_TOLERANCE)).floor().clamp(0.0, cap);
    let diag = (max_hole_mm / (pixel_mm * SQRT_2) * (1.0 + GAP_TOLERANCE)).floor().clamp(0.0, cap);
    (axis as u32, diag as u32)
}

/// Marks `bit` on the cells of horizontal runs of empty cells bounded by data at both ends and at
/// most `limit` long.
fn mark_rows(data: &[f32], w: usize, limit: u32, bit: u8, mask: &mut [u8]) {
    if limit == 0 {
        return;
    }
    mask.par_chunks_mut(w).zip(data.par_chunks(w)).for_each(|(m, d)| {
        let mut c = 0;
        while c < w {
            if d[c].is_finite() {
                c += 1;
                continue;
            }
            let a = c;
            while c < w && !d[c].is_finite() {
                c += 1;
            }
            if a > 0 && c < w && (c - a) as u64 <= u64::from(limit) {
                m[a..c].iter_mut().for_each(|x| *x |= bit);
            }
        }
    });
}

/// Like [`mark_rows`] along the lines of direction `(dx, 1)`, `dx ∈ {-1, 0, 1}`: rows are swept
/// upwards keeping per line the length of the current empty run (`UNBOUNDED` when it started at
/// the grid border); a data cell closing a short enough bounded run marks it backwards.
fn mark_lines(data: &[f32], w: usize, h: usize, dx: isize, limit: u32, bit: u8) -> Vec<u8> {
    const UNBOUNDED: u32 = u32::MAX;
    let mut mask = vec![0u8; data.len()];
    if limit == 0 || w == 0 {
        return mask;
    }
    let cap = limit + 1;
    // `before[c]`: the state of the line through (c, r) at row r - 1.
    let mut before = vec![UNBOUNDED; w];
    let mut cur = vec![UNBOUNDED; w];
    for (r, row) in data.chunks_exact(w).enumerate().take(h) {
        // Branch-free update of every line (vectorises).
        for ((s, &b), z) in cur.iter_mut().zip(&before).zip(row) {
            let run = if b == UNBOUNDED { UNBOUNDED } else { (b + 1).min(cap) };
            *s = if z.is_finite() { 0 } else { run };
        }
        // Data cells closing a bounded run of 1..=limit empty cells mark it.
        for (c, (&b, z)) in before.iter().zip(row).enumerate() {
            if z.is_finite() && b.wrapping_sub(1) < limit {
                for i in 1..=b as usize {
                    let cc = (c as isize - dx * i as isize) as usize;
                    mask[(r - i) * w + cc] |= bit;
                }
            }
        }
        // Shift the states along the direction for the next row.
        match dx {
            0 => before.copy_from_slice(&cur),
            1 => {
                before[0] = UNBOUNDED;
                before[1..].copy_from_slice(&cur[..w - 1]);
            }
            _ => {
                before[w - 1] = UNBOUNDED;
                before[..w - 1].copy_from_slice(&cur[1..]);
            }
        }
    }
    mask
}

/// Per cell, the directions along which it is bridged (bits `BRIDGE_*`; 0 for data cells).
fn bridge_mask(data: &[f32], w: usize, h: usize, axis: u32, diag: u32) -> Vec<u8> {
    let ((v, d1), (d2, mut mask)) = rayon::join(
        || {
            rayon::join(
                || mark_lines(data, w, h, 0, axis, BRIDGE_V),
                || mark_lines(data, w, h, 1, diag, BRIDGE_D1),
            )
        },
        || {
            rayon::join(
                || mark_lines(data, w, h, -1, diag, BRIDGE_D2),
                || {
                    let mut m = vec![0u8; data.len()];
                    mark_rows(data, w, axis, BRIDGE_H, &mut m);
                    m
                },
            )
        },
    );
    mask.par_chunks_mut(1 << 16).enumerate().for_each(|(ci, m)| {
        let s = ci << 16;
        for (i, x) in m.iter_mut().enumerate() {
            *x |= v[s + i] | d1[s + i] | d2[s + i];
        }
    });
    mask
}

/// 8-connected components of the cells for which `member` holds, as horizontal runs.
#[derive(Debug, Default)]
struct Components {
    /// `(row, first col, end col (exclusive))` of every run, in scan order.
    runs: Vec<(u32, u32, u32)>,
    /// Component of every run; components are numbered in scan order of their first cell.
    comp: Vec<u32>,
    /// Number of components.
    count: usize,
}

fn find_root(parent: &mut [u32], mut x: u32) -> u32 {
    while parent[x as usize] != x {
        let up = parent[parent[x as usize] as usize];
        parent[x as usize] = up;
        x = up;
    }
    x
}

fn components<F: Fn(usize) -> bool + Sync>(w: usize, h: usize, member: F) -> Components {
    let per_row: Vec<Vec<(u32, u32)>> = (0..h)
        .into_par_iter()
        .map(|r| {
            let base = r * w;
            let mut out = Vec::new();
            let mut c = 0;
            while c < w {
                if !member(base + c) {
                    c += 1;
                    continue;
                }
                let a = c;
                while c < w && member(base + c) {
                    c += 1;
                }
                out.push((a as u32, c as u32));
            }
            out
        })
        .collect();
    let total: usize = per_row.iter().map(Vec::len).sum();
    let mut runs = Vec::with_capacity(total);
    let mut row_start = Vec::with_capacity(h + 1);
    for (r, row) in per_row.iter().enumerate() {
        row_start.push(runs.len());
        runs.extend(row.iter().map(|&(a, b)| (r as u32, a, b)));
    }
    row_start.push(runs.len());
    let mut parent: Vec<u32> = (0..runs.len() as u32).collect();
    for r in 1..h {
        let (mut i, i_end) = (row_start[r - 1], row_start[r]);
        let (mut j, j_end) = (row_start[r], row_start[r + 1]);
        while i < i_end && j < j_end {
            let (_, a0, a1) = runs[i];
            let (_, b0, b1) = runs[j];
            // 8-adjacent: the column ranges overlap or touch at a corner.
            if a0 <= b1 && b0 <= a1 {
                let (ra, rb) = (find_root(&mut parent, i as u32), find_root(&mut parent, j as u32));
                if ra != rb {
                    let (lo, hi) = (ra.min(rb), ra.max(rb));
                    parent[hi as usize] = lo;
                }
            }
            if a1 < b1 {
                i += 1;
            } else {
                j += 1;
            }
        }
    }
    let mut comp = vec![0u32; runs.len()];
    let mut count = 0u32;
    for k in 0..runs.len() {
        let root = find_root(&mut parent, k as u32) as usize;
        if root == k {
            comp[k] = count;
            count += 1;
        } else {
            // The root is the set's smallest run, numbered already.
            comp[k] = comp[root];
        }
    }
    Components { runs, comp, count: count as usize }
}

/// Cells, bounding box and centroid sums of one component.
#[derive(Debug, Clone, Copy)]
struct CompAgg {
    cells: u64,
    min_c: u32,
    max_c: u32,
    min_r: u32,
    max_r: u32,
    sum_c: u64,
    sum_r: u64,
    border: bool,
}

impl Default for CompAgg {
    fn default() -> Self {
        CompAgg {
            cells: 0,
            min_c: u32::MAX,
            max_c: 0,
            min_r: u32::MAX,
            max_r: 0,
            sum_c: 0,
            sum_r: 0,
            border: false,
        }
    }
}

fn aggregate(comps: &Components, w: usize, h: usize) -> Vec<CompAgg> {
    let mut agg = vec![CompAgg::default(); comps.count];
    for (&(r, c0, c1), &k) in comps.runs.iter().zip(&comps.comp) {
        let a = &mut agg[k as usize];
        let n = u64::from(c1 - c0);
        a.cells += n;
        a.min_c = a.min_c.min(c0);
        a.max_c = a.max_c.max(c1 - 1);
        a.min_r = a.min_r.min(r);
        a.max_r = a.max_r.max(r);
        a.sum_c += (u64::from(c0) + u64::from(c1) - 1) * n / 2;
        a.sum_r += u64::from(r) * n;
        a.border |= r == 0 || r as usize == h - 1 || c0 == 0 || c1 as usize == w;
    }
    agg
}

/// Which empty cells of `data` the enclosure rule fills (module docs), and the number of enclosed
/// cells and holes it leaves empty.
fn fill_selection(data: &[f32], w: usize, h: usize, axis: u32, diag: u32) -> (Vec<u8>, usize, usize) {
    let mut mask = bridge_mask(data, w, h, axis, diag);
    let comps = components(w, h, |i| !data[i].is_finite());
    let agg = aggregate(&comps, w, h);
    let mut unbridged = vec![0u64; comps.count];
    for (&(r, c0, c1), &k) in comps.runs.iter().zip(&comps.comp) {
        let base = r as usize * w;
        let n = mask[base + c0 as usize..base + c1 as usize].iter().filter(|&&m| m == 0).count();
        unbridged[k as usize] += n as u64;
    }
    let mut left = 0usize;
    let mut too_large = 0usize;
    for (a, &u) in agg.iter().zip(&unbridged) {
        if !a.border && u > 0 {
            left += a.cells as usize;
            too_large += 1;
        }
    }
    for (&(r, c0, c1), &k) in comps.runs.iter().zip(&comps.comp) {
        let k = k as usize;
        let keep = agg[k].border || unbridged[k] == 0;
        let base = r as usize * w;
        for m in &mut mask[base + c0 as usize..base + c1 as usize] {
            *m = u8::from(keep && *m != 0);
        }
    }
    (mask, left, too_large)
}

/// Sample offsets within the search radius, nearest first: `(dx, dy, dx² + dy², weight)`.
#[derive(Debug)]
struct Offsets {
    list: Vec<(i32, i32, u32, f64)>,
    /// `(radius/p)²`: offsets with `dx² + dy² <=` this are within the radius.
    limit_sq: f64,
    /// Per-cell radius: stop at the nearest sample's distance plus `√2·p`.
    adaptive: bool,
}

/// `(radius/p)²`: cell offsets with `dx² + dy² <=` this are within the radius.
fn radius_cells_sq(radius_mm: f64, pixel_mm: f64) -> f64 {
    let rc = radius_mm / pixel_mm;
    rc * rc
}

/// The adaptive radius (squared, in cells) of a cell whose nearest sample is `sqrt(d0_sq)` cells
/// away: `(sqrt(d0_sq) + √2)²`, at most `cap_sq`.
fn adaptive_limit_sq(d0_sq: u32, cap_sq: f64) -> f64 {
    let r = f64::from(d0_sq).sqrt() + SQRT_2;
    (r * r).min(cap_sq)
}

/// IDW weight of a sample `sqrt(d_sq)` cells away.
fn idw_weight(d_sq: u32, pixel_mm: f64, power: f64) -> f64 {
    let d = pixel_mm * f64::from(d_sq).sqrt();
    d.powf(-power)
}

impl Offsets {
    fn new(radius_mm: f64, pixel_mm: f64, power: f64, adaptive: bool) -> Self {
        let limit_sq = radius_cells_sq(radius_mm, pixel_mm);
        let s = limit_sq.sqrt().floor() as i32 + 1;
        let mut list = Vec::new();
        for dy in -s..=s {
            for dx in -s..=s {
                let d_sq = (dx * dx + dy * dy) as u32;
                if d_sq > 0 && f64::from(d_sq) <= limit_sq {
                    list.push((dx, dy, d_sq, idw_weight(d_sq, pixel_mm, power)));
                }
            }
        }
        list.sort_by_key(|&(dx, dy, d_sq, _)| (d_sq, dy, dx));
        Offsets { list, limit_sq, adaptive }
    }
}

/// Steepest slope (rise over run, `tan 60°`) an IDW fill interpolates across: where the highest
/// and the lowest sample around an empty cell imply a steeper one, even over the longest path
/// between them (through the cell), the cell lies at a step whose edge nobody saw, and it takes
/// the highest sample (see the module docs).
pub const FILL_STEP_SLOPE: f64 = 1.732_050_807_568_877_2;

/// Whether samples `hi` (at `d_hi_sq` cells²) and `lo` (at `d_lo_sq`) around an empty cell imply a
/// slope steeper than [`FILL_STEP_SLOPE`] through it (`pixel_mm` the cell size).
fn fill_at_step(hi: f32, d_hi_sq: u32, lo: f32, d_lo_sq: u32, pixel_mm: f64) -> bool {
    let run = pixel_mm * (f64::from(d_hi_sq).sqrt() + f64::from(d_lo_sq).sqrt());
    f64::from(hi) - f64::from(lo) > FILL_STEP_SLOPE * run
}

/// The higher end of a bridge through the empty cell `(c, r)` whose two ends imply a slope
/// steeper than [`FILL_STEP_SLOPE`] through the cell ([`fill_at_step`]), or `-inf` when no bridge
/// does. A bridge is a run of empty cells along a row, a column or a diagonal bounded by data at
/// both ends and at most `axis` (`diag`) cells long, as [`fill_selection`] bridges them. The
/// sample radius stops one ring past the nearest sample, so a cell near the low side of a wide
/// gap at a step sees that side alone; its bridge still reaches the high side.
fn bridge_step_top(
    data: &[f32],
    w: usize,
    h: usize,
    c: usize,
    r: usize,
    (axis, diag): (u32, u32),
    p: f64,
) -> f32 {
    let at = |c: isize, r: isize| {
        (c >= 0 && r >= 0 && (c as usize) < w && (r as usize) < h).then(|| data[r as usize * w + c as usize])
    };
    let mut top = f32::NEG_INFINITY;
    for (dc, dr, limit) in [(1isize, 0isize, axis), (0, 1, axis), (1, 1, diag), (1, -1, diag)] {
        // The data cell ending the run each way, and how many steps away it is.
        let end = |sign: isize| -> Option<(f32, u32)> {
            let mut k = 1u32;
            loop {
                let v = at(c as isize + sign * dc * k as isize, r as isize + sign * dr * k as isize)?;
                if v.is_finite() {
                    return Some((v, k));
                }
                // The run holds `k` empty cells past this one on this side alone.
                if k >= limit {
                    return None;
                }
                k += 1;
            }
        };
        let (Some((a, ka)), Some((b, kb))) = (end(1), end(-1)) else { continue };
        // Empty cells in the run: this one and those on both sides.
        if ka + kb - 1 > limit {
            continue;
        }
        let d2 = |k: u32| k.saturating_mul(k).saturating_mul(if dc != 0 && dr != 0 { 2 } else { 1 });
        let ((hi, d_hi), (lo, d_lo)) =
            if a >= b { ((a, d2(ka)), (b, d2(kb))) } else { ((b, d2(kb)), (a, d2(ka))) };
        if fill_at_step(hi, d_hi, lo, d_lo, p) {
            top = top.max(hi);
        }
    }
    top
}

/// The fill value of cell `(c, r)` from the valid cells of `data` within the (fixed or adaptive)
/// radius, NaN without any. With `max` the highest sample; otherwise the IDW mean, or the highest
/// sample when the samples span a step ([`fill_at_step`]; `pixel_mm` the cell size).
#[allow(clippy::too_many_arguments)]
fn fill_value(
    data: &[f32],
    w: usize,
    h: usize,
    c: usize,
    r: usize,
    offsets: &Offsets,
    max: bool,
    pixel_mm: f64,
) -> f32 {
    let (mut best, mut sw, mut swz) = (f32::NEG_INFINITY, 0.0f64, 0.0f64);
    // The lowest and highest samples with their distances (the nearest of equal ones: the
    // offsets come nearest first).
    let (mut lo, mut d_lo, mut d_hi) = (f32::INFINITY, 0u32, 0u32);
    let mut limit_sq = offsets.limit_sq;
    let mut found = false;
    for &(dx, dy, d_sq, wt) in &offsets.list {
        if f64::from(d_sq) > limit_sq {
            break;
        }
        let (cc, rr) = (c as isize + dx as isize, r as isize + dy as isize);
        if cc < 0 || rr < 0 || cc >= w as isize || rr >= h as isize {
            continue;
        }
        let z = data[rr as usize * w + cc as usize];
        if !z.is_finite() {
            continue;
        }
        if !found {
            found = true;
            if offsets.adaptive {
                limit_sq = adaptive_limit_sq(d_sq, offsets.limit_sq);
            }
        }
        if z > best {
            (best, d_hi) = (z, d_sq);
        }
        if !max {
            if z < lo {
                (lo, d_lo) = (z, d_sq);
            }
            sw += wt;
            swz += wt * f64::from(z);
        }
    }
    if !found {
        f32::NAN
    } else if max || fill_at_step(best, d_hi, lo, d_lo, pixel_mm) {
        best
    } else {
        (swz / sw) as f32
    }
}

/// Fills the enclosed holes of `raw` (only those; see the module docs for the exact rule) from the
/// valid raw cells within the sample radius, and returns the filled map (same metadata) with a
/// report. Errors name the invalid field of `params`.
pub fn fill_holes(raw: &HeightMap, params: &FillParams) -> Result<(HeightMap, FillReport)> {
    let p = raw.pixel_mm();
    let radius = params.radius_for(p)?;
    let (w, h) = (raw.width() as usize, raw.height() as usize);
    let data = raw.data();
    let (axis, diag) = gap_limits(params.max_hole_mm, p);
    let (select, left, too_large) = fill_selection(data, w, h, axis, diag);
    let (power, max) = match params.method {
        FillMethod::Max => (0.0, true),
        FillMethod::Idw { power } => (power, false),
    };
    let offsets = Offsets::new(radius, p, power, params.radius_mm.is_none());
    let mut out = raw.clone();
    let (filled, no_sample) = out
        .data_mut()
        .par_chunks_mut(w)
        .zip(select.par_chunks(w))
        .enumerate()
        .map(|(r, (orow, srow))| {
            let (mut f, mut n) = (0usize, 0usize);
            for (c, (o, &s)) in orow.iter_mut().zip(srow).enumerate() {
                if s != 0 {
                    let mut v = fill_value(data, w, h, c, r, &offsets, max, p);
                    if !max && v.is_finite() {
                        v = v.max(bridge_step_top(data, w, h, c, r, (axis, diag), p));
                    }
                    if v.is_finite() {
                        *o = v;
                        f += 1;
                    } else {
                        n += 1;
                    }
                }
            }
            (f, n)
        })
        .reduce(|| (0, 0), |a, b| (a.0 + b.0, a.1 + b.1));
    Ok((out, FillReport { filled, left_empty_enclosed: left + no_sample, holes_too_large: too_large }))
}

/// One hole: a connected component of cells, in mm.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct HoleStats {
    /// Number of cells.
    pub cells: usize,
    /// `cells · pixel²`.
    pub area_mm2: f64,
    /// X of the centroid (mean of the cell centres).
    pub center_x_mm: f64,
    /// Y of the centroid.
    pub center_y_mm: f64,
    /// Bounding box of the cells' squares (edges, not centres).
    pub min_x_mm: f64,
    /// Bounding box, minimum Y.
    pub min_y_mm: f64,
    /// Bounding box, maximum X.
    pub max_x_mm: f64,
    /// Bounding box, maximum Y.
    pub max_y_mm: f64,
}

/// Coverage statistics of one map (see [`coverage`]).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct CoverageStats {
    /// Cells of the grid.
    pub cells: usize,
    /// Cells holding data in the raw map.
    pub measured: usize,
    /// Cells empty in the raw map and filled.
    pub filled: usize,
    /// Cells of the part's footprint: measured, filled, and enclosed cells still empty.
    pub footprint: usize,
    /// `measured / footprint · 100` (0 for an empty footprint).
    pub covered_pct: f64,
    /// Number of holes: 8-connected components of unmeasured footprint cells (filled or not).
    pub holes: usize,
    /// The largest of those by area (the first in scan order on a tie).
    pub largest_hole: Option<HoleStats>,
    /// Footprint cells still empty after filling (coverage value 0).
    pub empty: usize,
    /// Number of 8-connected components of those.
    pub unfilled_holes: usize,
    /// The largest of those: what a rescan has to cover.
    pub largest_unfilled_hole: Option<HoleStats>,
}

/// Counts of components and the largest one.
fn hole_summary<'a>(
    comps: impl Iterator<Item = &'a CompAgg>,
    meta: &HeightMapMeta,
) -> (usize, Option<HoleStats>) {
    let mut best: Option<&CompAgg> = None;
    let mut count = 0;
    for a in comps {
        count += 1;
        if best.is_none_or(|b| a.cells > b.cells) {
            best = Some(a);
        }
    }
    let p = meta.pixel_mm;
    let stats = best.map(|a| {
        let n = a.cells as f64;
        HoleStats {
            cells: a.cells as usize,
            area_mm2: n * p * p,
            center_x_mm: meta.origin_x_mm + (a.sum_c as f64 / n + 0.5) * p,
            center_y_mm: meta.origin_y_mm + (a.sum_r as f64 / n + 0.5) * p,
            min_x_mm: meta.origin_x_mm + f64::from(a.min_c) * p,
            min_y_mm: meta.origin_y_mm + f64::from(a.min_r) * p,
            max_x_mm: meta.origin_x_mm + f64::from(a.max_c + 1) * p,
            max_y_mm: meta.origin_y_mm + f64::from(a.max_r + 1) * p,
        }
    });
    (count, stats)
}

/// Coverage value of a measured cell.
pub const COVERAGE_MEASURED: f32 = 1.0;
/// Coverage value of a filled cell.
pub const COVERAGE_FILLED: f32 = 0.5;
/// Coverage value of a cell no scan could see (hidden behind the part from every station) that
/// the reconstruction filled with an assumed height (the highest seen around it): unlike a
/// filled hole, nothing measured bounds it on every side, so a deviation there says nothing
/// about the machining.
pub const COVERAGE_ASSUMED: f32 = 0.25;
/// Coverage value of a footprint cell still empty (a hole).
pub const COVERAGE_HOLE: f32 = 0.0;

/// Coverage map: same grid as `raw`, values 1.0 = measured, 0.5 = filled, 0.0 = inside the
/// part's footprint but empty (a hole), NaN = outside the footprint; Z range `[0, 1]`.
///
/// Footprint = measured ∪ filled ∪ the cells still empty after filling whose 8-connected empty
/// component does not touch the grid border. `covered_pct = measured / footprint · 100`. Holes are
/// the 8-connected components of the unmeasured footprint cells of the raw map (filled or not);
/// the ones still empty are reported apart (see [`CoverageStats`] and the module docs).
/// A `filled` map of another size than `raw` is ignored (as if nothing had been filled).
pub fn coverage(raw: &HeightMap, filled: &HeightMap) -> (HeightMap, CoverageStats) {
    let meta = *raw.meta();
    let (w, h) = (meta.width as usize, meta.height as usize);
    let rd = raw.data();
    let fd =
        if filled.width() == raw.width() && filled.height() == raw.height() { filled.data() } else { rd };
    let empty_after = components(w, h, |i| !rd[i].is_finite() && !fd[i].is_finite());
    let agg = aggregate(&empty_after, w, h);
    let mut map = raw.clone();
    let cov = map.data_mut();
    cov.par_iter_mut().zip(rd.par_iter().zip(fd.par_iter())).for_each(|(o, (&r, &f))| {
        *o = if r.is_finite() {
            COVERAGE_MEASURED
        } else if f.is_finite() {
            COVERAGE_FILLED
        } else {
            f32::NAN
        };
    });
    for (&(r, c0, c1), &k) in empty_after.runs.iter().zip(&empty_after.comp) {
        if !agg[k as usize].border {
            let base = r as usize * w;
            cov[base + c0 as usize..base + c1 as usize].fill(COVERAGE_HOLE);
        }
    }
    let (measured, filled_n, empty) = cov
        .par_iter()
        .fold(
            || (0usize, 0usize, 0usize),
            |(m, f, e), &v| {
                if v == COVERAGE_MEASURED {
                    (m + 1, f, e)
                } else if v == COVERAGE_FILLED {
                    (m, f + 1, e)
                } else if v == COVERAGE_HOLE {
                    (m, f, e + 1)
                } else {
                    (m, f, e)
                }
            },
        )
        .reduce(|| (0, 0, 0), |a, b| (a.0 + b.0, a.1 + b.1, a.2 + b.2));
    let cov: &[f32] = cov;
    let unmeasured = components(w, h, |i| cov[i] == COVERAGE_FILLED || cov[i] == COVERAGE_HOLE);
    let (holes, largest_hole) = hole_summary(aggregate(&unmeasured, w, h).iter(), &meta);
    // The cells still empty form exactly the enclosed components of the empty cells.
    let (unfilled_holes, largest_unfilled_hole) = hole_summary(agg.iter().filter(|a| !a.border), &meta);
    // Cannot fail: finite 0 < 1 on a valid grid.
    let _ = map.set_z_range(0.0, 1.0);
    let footprint = measured + filled_n + empty;
    let stats = CoverageStats {
        cells: w * h,
        measured,
        filled: filled_n,
        footprint,
        covered_pct: if footprint > 0 { measured as f64 / footprint as f64 * 100.0 } else { 0.0 },
        holes,
        largest_hole,
        empty,
        unfilled_holes,
        largest_unfilled_hole,
    };
    (map, stats)
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Point3;
    use rand::rngs::StdRng;
    use rand::{Rng, SeedableRng};

    fn meta(w: u32, h: u32, p: f64, x0: f64, y0: f64) -> HeightMapMeta {
        let mut m = HeightMapMeta::new(w, h, p);
        m.origin_x_mm = x0;
        m.origin_y_mm = y0;
        m
    }

    fn same(a: f32, b: f32) -> bool {
        (a.is_nan() && b.is_nan()) || a == b
    }

    /// Loop over cells; for each, scan all points with the half-open cell test.
    fn brute_raster(points: &[Point3<f64>], g: &HeightMapMeta) -> (Vec<f32>, usize) {
        let (w, h) = (g.width as usize, g.height as usize);
        let mut out = vec![f32::NAN; w * h];
        let mut binned = 0;
        for r in 0..h {
            let (y0, y1) =
                (g.origin_y_mm + r as f64 * g.pixel_mm, g.origin_y_mm + (r + 1) as f64 * g.pixel_mm);
            for c in 0..w {
                let (x0, x1) =
                    (g.origin_x_mm + c as f64 * g.pixel_mm, g.origin_x_mm + (c + 1) as f64 * g.pixel_mm);
                for p in points {
                    let z = p.z as f32;
                    if !(p.x.is_finite() && p.y.is_finite() && z.is_finite()) {
                        continue;
                    }
                    if x0 <= p.x && p.x < x1 && y0 <= p.y && p.y < y1 {
                        binned += 1;
                        let o = &mut out[r * w + c];
                        if o.is_nan() || z > *o {
                            *o = z;
                        }
                    }
                }
            }
        }
        (out, binned)
    }

    fn random_cloud(rng: &mut StdRng, g: &HeightMapMeta, n: usize) -> Vec<Point3<f64>> {
        let (p, x0, y0) = (g.pixel_mm, g.origin_x_mm, g.origin_y_mm);
        let (w, h) = (i64::from(g.width), i64::from(g.height));
        (0..n)
            .map(|_| {
                let z = if rng.random_bool(0.2) {
                    f64::from(rng.random_range(-3i32..3))
                } else {
                    rng.random_range(-5.0..5.0)
                };
                let edge_x = x0 + rng.random_range(-1..=w + 1) as f64 * p;
                let edge_y = y0 + rng.random_range(-1..=h + 1) as f64 * p;
                let free_x = x0 + rng.random_range(-1.5..w as f64 + 1.5) * p;
                let free_y = y0 + rng.random_range(-1.5..h as f64 + 1.5) * p;
                match rng.random_range(0..10) {
                    0 => Point3::new(edge_x, edge_y, z),
                    1 => Point3::new(edge_x, free_y, z),
                    2 => Point3::new(free_x, edge_y, z),
                    3 => Point3::new(edge_x.next_down(), edge_y.next_up(), z),
                    4 => match rng.random_range(0..5) {
                        0 => Point3::new(f64::NAN, free_y, z),
                        1 => Point3::new(free_x, f64::INFINITY, z),
                        2 => Point3::new(free_x, free_y, f64::NAN),
                        3 => Point3::new(free_x, free_y, 1e300),
                        _ => Point3::new(1e300, -1e300, z),
                    },
                    _ => Point3::new(free_x, free_y, z),
                }
            })
            .collect()
    }

    /// The median by its definition: every cell's points with the half-open cell test, sorted, the
    /// middle one (or the mean of the two middle ones).
    fn brute_median(points: &[Point3<f64>], g: &HeightMapMeta) -> Vec<f32> {
        let (w, h) = (g.width as usize, g.height as usize);
        let mut out = vec![f32::NAN; w * h];
        for r in 0..h {
            let (y0, y1) =
                (g.origin_y_mm + r as f64 * g.pixel_mm, g.origin_y_mm + (r + 1) as f64 * g.pixel_mm);
            for c in 0..w {
                let (x0, x1) =
                    (g.origin_x_mm + c as f64 * g.pixel_mm, g.origin_x_mm + (c + 1) as f64 * g.pixel_mm);
                let mut zs: Vec<f32> = points
                    .iter()
                    .filter(|p| p.x.is_finite() && p.y.is_finite() && (p.z as f32).is_finite())
                    .filter(|p| x0 <= p.x && p.x < x1 && y0 <= p.y && p.y < y1)
                    .map(|p| p.z as f32)
                    .collect();
                zs.sort_by(f32::total_cmp);
                let n = zs.len();
                if n > 0 {
                    out[r * w + c] = if n % 2 == 1 {
                        zs[n / 2]
                    } else {
                        ((f64::from(zs[n / 2 - 1]) + f64::from(zs[n / 2])) / 2.0) as f32
                    };
                }
            }
        }
        out
    }

    #[test]
    fn median_matches_brute_force_on_random_clouds() {
        let mut rng = StdRng::seed_from_u64(11);
        for case in 0..60 {
            let g = meta(
                rng.random_range(1..10),
                rng.random_range(1..10),
                [0.1, 0.25, 1.0 / 3.0, 1.0][case % 4],
                rng.random_range(-5.0..5.0),
                rng.random_range(-5.0..5.0),
            );
            let n = rng.random_range(0..600);
            let pts = random_cloud(&mut rng, &g, n);
            let want = brute_median(&pts, &g);
            let (map, stats) = rasterize_median(&pts, &g).expect("valid grid");
            assert_eq!(map.meta(), &g);
            for (i, (&a, &b)) in map.data().iter().zip(&want).enumerate() {
                assert!(same(a, b), "case {case} cell {i}: {a} vs {b}");
            }
            // The same cells and counts as the max, and never above it.
            let (max, max_stats) = rasterize_max(&pts, &g);
            assert_eq!(stats, max_stats, "case {case}");
            for (&m, &x) in map.data().iter().zip(max.data()) {
                assert_eq!(m.is_nan(), x.is_nan());
                assert!(m.is_nan() || m <= x);
            }
        }
    }

    #[test]
    fn the_median_of_a_noisy_plane_is_unbiased_where_the_max_stands_proud() {
        // 16 samples a cell of z = 1 with uniform noise of ±0.1 mm.
        let g = meta(20, 20, 0.5, 0.0, 0.0);
        let mut rng = StdRng::seed_from_u64(3);
        let pts: Vec<Point3<f64>> = (0..20 * 20 * 16)
            .map(|_| {
                Point3::new(
                    rng.random_range(0.0..10.0),
                    rng.random_range(0.0..10.0),
                    1.0 + rng.random_range(-0.1..0.1),
                )
            })
            .collect();
        let mean = |m: &HeightMap| {
            let v: Vec<f64> = m.data().iter().filter(|z| z.is_finite()).map(|&z| f64::from(z)).collect();
            v.iter().sum::<f64>() / v.len() as f64
        };
        let (median, _) = rasterize_median(&pts, &g).expect("valid grid");
        let (max, _) = rasterize_max(&pts, &g);
        assert!((mean(&median) - 1.0).abs() < 0.005, "median map mean {}", mean(&median));
        assert!(mean(&max) - 1.0 > 0.07, "max map mean {}", mean(&max));
    }

    #[test]
    fn rasterize_matches_brute_force_on_random_clouds() {
        let mut rng = StdRng::seed_from_u64(7);
        let pixels = [0.1, 0.25, 0.3, 1.0 / 3.0, 0.7, 1.0];
        for case in 0..60 {
            let p = pixels[case % pixels.len()];
            let g = meta(
                rng.random_range(1..12),
                rng.random_range(1..12),
                p,
                rng.random_range(-5.0..5.0),
                rng.random_range(-5.0..5.0),
            );
            let pts = random_cloud(&mut rng, &g, 400);
            let (want, binned) = brute_raster(&pts, &g);
            let non_finite = pts
                .iter()
                .filter(|q| !(q.x.is_finite() && q.y.is_finite() && (q.z as f32).is_finite()))
                .count();
            for strategy in [Strategy::Serial, Strategy::Direct, Strategy::Partition] {
                let (map, stats) = rasterize_with(&pts, &g, Some(strategy)).expect("valid grid");
                assert_eq!(map.meta(), &g);
                for (i, (&a, &b)) in map.data().iter().zip(&want).enumerate() {
                    assert!(same(a, b), "case {case} {strategy:?} cell {i}: {a} vs {b}");
                }
                assert_eq!(stats.points_in, pts.len());
                assert_eq!(stats.points_binned, binned, "case {case} {strategy:?}");
                assert_eq!(stats.non_finite, non_finite);
                assert_eq!(stats.points_outside, pts.len() - binned - non_finite);
            }
            // The public entry point and the single-point lookup agree with the brute force.
            let (map, _) = rasterize_max(&pts, &g);
            assert!(map.data().iter().zip(&want).all(|(&a, &b)| same(a, b)));
            for q in &pts {
                if let Some((c, r)) = raster_cell(&g, q.x, q.y) {
                    let x0 = g.origin_x_mm + f64::from(c) * p;
                    assert!(x0 <= q.x && q.x < g.origin_x_mm + f64::from(c + 1) * p);
                    let y0 = g.origin_y_mm + f64::from(r) * p;
                    assert!(y0 <= q.y && q.y < g.origin_y_mm + f64::from(r + 1) * p);
                }
            }
        }
    }

    #[test]
    fn large_cloud_paths_agree() {
        // Enough points for the parallel paths to split the work for real.
        let mut rng = StdRng::seed_from_u64(11);
        let g = meta(37, 23, 0.3, -2.0, 1.0);
        let pts = random_cloud(&mut rng, &g, 200_000);
        let (serial, s0) = rasterize_with(&pts, &g, Some(Strategy::Serial)).expect("grid");
        for strategy in [Strategy::Direct, Strategy::Partition] {
            let (m, s) = rasterize_with(&pts, &g, Some(strategy)).expect("grid");
            assert!(m.bitwise_eq(&serial), "{strategy:?}");
            assert_eq!(s, s0);
        }
    }

    #[test]
    fn scan_order_is_told_from_shuffled() {
        let g = meta(500, 400, 0.1, 0.0, 0.0);
        let scan: Vec<_> = (0..40_000)
            .map(|i| Point3::new((i % 500) as f64 * 0.1 + 0.05, (i / 500) as f64 * 0.5, 0.0))
            .collect();
        let bins = Binner::new(&g);
        assert!(is_local(&scan, &bins));
        let mut rng = StdRng::seed_from_u64(2);
        let mut shuffled = scan.clone();
        for i in (1..shuffled.len()).rev() {
            shuffled.swap(i, rng.random_range(0..=i));
        }
        assert!(!is_local(&shuffled, &bins));
    }

    #[test]
    fn grid_convention_edges_and_centres() {
        let g = grid_for_roi(&Roi { x_min_mm: 0.3, y_min_mm: -0.2, x_max_mm: 1.0, y_max_mm: 0.1 }, 0.1)
            .expect("grid");
        // 0.7 / 0.1 is 6.999...: exactly 7 columns, 3 rows, corner at the ROI minimum.
        assert_eq!((g.width, g.height, g.origin_x_mm, g.origin_y_mm), (7, 3, 0.3, -0.2));
        for k in 0..7u32 {
            let x = g.origin_x_mm + f64::from(k) * g.pixel_mm;
            assert_eq!(raster_cell(&g, x, -0.2), Some((k, 0)), "edge {k}");
            assert_eq!(raster_cell(&g, x.next_down(), -0.2), k.checked_sub(1).map(|c| (c, 0)));
            let (cx, _) = g.cell_center(k, 0);
            assert_eq!(raster_cell(&g, cx, -0.15), Some((k, 0)));
            assert!((cx - (0.3 + (f64::from(k) + 0.5) * 0.1)).abs() < 1e-12);
        }
        // The max edges are outside; the min edges inside.
        assert_eq!(raster_cell(&g, g.origin_x_mm + 7.0 * 0.1, 0.0), None);
        assert_eq!(raster_cell(&g, 0.5, g.origin_y_mm + 3.0 * 0.1), None);
        assert_eq!(raster_cell(&g, 0.3, -0.2), Some((0, 0)));
        assert_eq!(raster_cell(&g, f64::NAN, 0.0), None);
        // A point at x0 + k·p is binned into column k by rasterize_max too.
        let pts: Vec<_> =
            (0..=7).map(|k| Point3::new(0.3 + f64::from(k) * 0.1, -0.05, f64::from(k))).collect();
        let (map, stats) = rasterize_max(&pts, &g);
        for k in 0..7u32 {
            assert_eq!(map.get(k, 1), Some(k as f32));
        }
        assert_eq!((stats.points_binned, stats.points_outside), (7, 1));
    }

    #[test]
    fn grid_for_roi_sizes_and_errors() {
        let roi = Roi { x_min_mm: -1.0, y_min_mm: 2.0, x_max_mm: 1.05, y_max_mm: 2.0001 };
        let g = grid_for_roi(&roi, 0.1).expect("grid");
        assert_eq!((g.width, g.height), (21, 1));
        assert!(g.origin_x_mm + f64::from(g.width) * 0.1 >= roi.x_max_mm);
        assert!(g.origin_x_mm + f64::from(g.width - 1) * 0.1 < roi.x_max_mm);
        let e = grid_for_roi(&roi, 0.0).expect_err("zero pixel").to_string();
        assert!(e.contains("pixel_mm = 0"), "{e}");
        let e = grid_for_roi(&roi, f64::NAN).expect_err("nan").to_string();
        assert!(e.contains("pixel_mm = NaN"), "{e}");
        let big = Roi { x_min_mm: 0.0, y_min_mm: 0.0, x_max_mm: 2000.0, y_max_mm: 2000.0 };
        let e = grid_for_roi(&big, 0.1).expect_err("too many").to_string();
        assert!(e.contains("20000x20000") && e.contains("268435456"), "{e}");
        let e = grid_for_roi(&big, 1e-300).expect_err("too fine").to_string();
        assert!(e.contains("too fine"), "{e}");
        let bad = Roi { x_max_mm: -2.0, ..roi };
        let e = grid_for_roi(&bad, 0.1).expect_err("inverted").to_string();
        assert!(e.contains("roi") && e.contains("x_min_mm must be less than x_max_mm"), "{e}");
        let e = Roi { y_min_mm: f64::INFINITY, ..roi }.validate().expect_err("inf").to_string();
        assert!(e.contains("finite"), "{e}");
    }

    proptest::proptest! {
        /// The grid is the smallest one whose far edges reach the ROI's max, and every point of the
        /// half-open ROI lands in it.
        #[test]
        fn grid_for_roi_is_minimal_and_covers_the_roi(
            x0 in -500.0f64..500.0, y0 in -500.0f64..500.0,
            wx in 1e-3f64..50.0, wy in 1e-3f64..50.0,
            p in 0.01f64..2.0, fx in 0.0f64..1.0, fy in 0.0f64..1.0,
        ) {
            let roi = Roi { x_min_mm: x0, y_min_mm: y0, x_max_mm: x0 + wx, y_max_mm: y0 + wy };
            let g = grid_for_roi(&roi, p).expect("grid");
            proptest::prop_assert!(x0 + f64::from(g.width) * p >= roi.x_max_mm);
            proptest::prop_assert!(g.width == 1 || x0 + f64::from(g.width - 1) * p < roi.x_max_mm);
            proptest::prop_assert!(y0 + f64::from(g.height) * p >= roi.y_max_mm);
            proptest::prop_assert!(g.height == 1 || y0 + f64::from(g.height - 1) * p < roi.y_max_mm);
            let (x, y) = (x0 + fx * wx, y0 + fy * wy);
            if x < roi.x_max_mm && y < roi.y_max_mm {
                proptest::prop_assert!(raster_cell(&g, x, y).is_some());
            }
        }
    }

    #[test]
    fn roi_around_keeps_every_point_inside() {
        let mut rng = StdRng::seed_from_u64(3);
        let mut pts: Vec<_> = (0..500)
            .map(|_| {
                Point3::new(
                    rng.random_range(-3.0..7.0),
                    rng.random_range(1.0..2.0),
                    rng.random_range(0.0..1.0),
                )
            })
            .collect();
        // Extremes exactly on a whole number of pixels from the minimum.
        pts.push(Point3::new(-3.0, 1.0, 0.0));
        pts.push(Point3::new(7.0, 2.0, 0.0));
        pts.push(Point3::new(f64::NAN, 100.0, 0.0));
        pts.push(Point3::new(100.0, 1.5, f64::INFINITY));
        for margin in [0.0, 0.2, -1.0, f64::NAN] {
            let roi = Roi::around(&pts, margin).expect("points");
            assert_eq!(roi.x_min_mm, if margin > 0.0 { -3.2 } else { -3.0 });
            let g = grid_for_roi(&roi, 0.1).expect("grid");
            let (_, stats) = rasterize_max(&pts, &g);
            assert_eq!(stats.points_binned, 502, "margin {margin}");
            assert_eq!(stats.non_finite, 2);
        }
        assert_eq!(Roi::around(&[Point3::new(f64::NAN, 0.0, 0.0)], 1.0), None);
        assert_eq!(Roi::around::<Point3<f64>>(&[], 1.0), None);
        let one = Roi::around(&[Point3::new(1.0, 1.0, 1.0)], 0.0).expect("one point");
        assert!(one.validate().is_ok());
        assert_eq!(grid_for_roi(&one, 0.1).map(|g| (g.width, g.height)).expect("grid"), (1, 1));
    }

    #[test]
    fn auto_z_range_ignores_one_stray_point() {
        let mut rng = StdRng::seed_from_u64(5);
        let mut v: Vec<f32> = (0..100_000).map(|_| rng.random_range(0.0f32..10.0)).collect();
        v.push(1000.0);
        v.push(f32::NAN);
        v.push(f32::INFINITY);
        let (lo, hi) = auto_z_range(v.iter().copied()).expect("data");
        assert!(hi > 9.9 && hi < 10.3, "{hi}");
        assert!(lo < 0.1 && lo > -0.3, "{lo}");
        // A low stray point neither.
        v.push(-500.0);
        let (lo, _) = auto_z_range(v.into_iter()).expect("data");
        assert!(lo > -0.3, "{lo}");
        // Few values: their full range, widened; a flat map still gets lo < hi.
        assert_eq!(auto_z_range([1.0f32, 2.0, 3.0].into_iter()), Some((1.0 - 0.04, 3.0 + 0.04)));
        let (lo, hi) = auto_z_range(std::iter::repeat_n(5.0f32, 1000)).expect("flat");
        assert!(lo < 5.0 && hi > 5.0 && hi - lo < 0.01);
        assert_eq!(auto_z_range([f32::NAN].into_iter()), None);
    }

    // ---- hole filling references -------------------------------------------------------------

    const DIRS: [(isize, isize, u8); 4] =
        [(1, 0, BRIDGE_H), (0, 1, BRIDGE_V), (1, 1, BRIDGE_D1), (-1, 1, BRIDGE_D2)];

    /// Per empty cell and direction, walk both ways until data or the border.
    fn brute_bridges(d: &[f32], w: usize, h: usize, axis: u32, diag: u32) -> Vec<u8> {
        let at = |c: isize, r: isize| -> Option<bool> {
            (c >= 0 && r >= 0 && (c as usize) < w && (r as usize) < h)
                .then(|| d[r as usize * w + c as usize].is_finite())
        };
        let mut out = vec![0u8; w * h];
        for r in 0..h as isize {
            for c in 0..w as isize {
                if at(c, r) != Some(false) {
                    continue;
                }
                for (dx, dy, bit) in DIRS {
                    let limit = if dx != 0 && dy != 0 { diag } else { axis };
                    let mut k = 1u64;
                    let mut ends = 0;
                    for s in [1isize, -1] {
                        let mut t = 1;
                        loop {
                            match at(c + s * t * dx, r + s * t * dy) {
                                None => break,
                                Some(true) => {
                                    ends += 1;
                                    break;
                                }
                                Some(false) => k += 1,
                            }
                            t += 1;
                        }
                    }
                    if ends == 2 && k <= u64::from(limit) {
                        out[r as usize * w + c as usize] |= bit;
                    }
                }
            }
        }
        out
    }

    /// Flood fill labels (8-connected) of the member cells; usize::MAX elsewhere.
    fn brute_labels(w: usize, h: usize, member: impl Fn(usize) -> bool) -> Vec<usize> {
        let mut label = vec![usize::MAX; w * h];
        let mut next = 0;
        for start in 0..w * h {
            if !member(start) || label[start] != usize::MAX {
                continue;
            }
            let mut stack = vec![start];
            label[start] = next;
            while let Some(i) = stack.pop() {
                let (c, r) = ((i % w) as isize, (i / w) as isize);
                for dy in -1..=1 {
                    for dx in -1..=1 {
                        let (cc, rr) = (c + dx, r + dy);
                        if cc < 0 || rr < 0 || cc as usize >= w || rr as usize >= h {
                            continue;
                        }
                        let j = rr as usize * w + cc as usize;
                        if member(j) && label[j] == usize::MAX {
                            label[j] = next;
                            stack.push(j);
                        }
                    }
                }
            }
            next += 1;
        }
        label
    }

    fn labels_of(comps: &Components, w: usize, h: usize) -> Vec<usize> {
        let mut label = vec![usize::MAX; w * h];
        for (&(r, c0, c1), &k) in comps.runs.iter().zip(&comps.comp) {
            for c in c0..c1 {
                label[r as usize * w + c as usize] = k as usize;
            }
        }
        label
    }

    /// The enclosure rule spelled out on the brute-force bridges and flood-fill components.
    fn brute_selection(d: &[f32], w: usize, h: usize, axis: u32, diag: u32) -> Vec<bool> {
        let bridges = brute_bridges(d, w, h, axis, diag);
        let label = brute_labels(w, h, |i| !d[i].is_finite());
        (0..w * h)
            .map(|i| {
                if label[i] == usize::MAX || bridges[i] == 0 {
                    return false;
                }
                let members: Vec<usize> = (0..w * h).filter(|&j| label[j] == label[i]).collect();
                let border =
                    members.iter().any(|&j| j % w == 0 || j % w == w - 1 || j / w == 0 || j / w == h - 1);
                border || members.iter().all(|&j| bridges[j] != 0)
            })
            .collect()
    }

    /// Per selected cell, scan every valid cell within the radius (for the adaptive radius: first
    /// the nearest valid cell within the cap, then every valid cell within its distance + √2).
    fn brute_fill(d: &[f32], w: usize, h: usize, sel: &[bool], p: f64, params: &FillParams) -> Vec<f32> {
        let cap = radius_cells_sq(params.radius_for(p).expect("radius"), p);
        let method = params.method;
        let mut out = d.to_vec();
        for i in 0..w * h {
            if !sel[i] {
                continue;
            }
            let (c, r) = ((i % w) as isize, (i / w) as isize);
            let offset = |j: usize| ((j % w) as isize - c, (j / w) as isize - r);
            let d_sq = |j: usize| {
                let (dx, dy) = offset(j);
                (dx * dx + dy * dy) as u32
            };
            let nearest =
                (0..w * h).filter(|&j| d[j].is_finite() && f64::from(d_sq(j)) <= cap).map(d_sq).min();
            let rc2 = match (params.radius_mm, nearest) {
                (None, Some(d0)) => adaptive_limit_sq(d0, cap),
                _ => cap,
            };
            let (mut best, mut sw, mut swz) = (f32::NAN, 0.0, 0.0);
            let mut samples = Vec::new();
            for (j, &z) in d.iter().enumerate() {
                let (dx, dy) = offset(j);
                if !z.is_finite() || ((dx * dx + dy * dy) as f64) > rc2 {
                    continue;
                }
                samples.push((z, d_sq(j)));
                let dist = p * ((dx * dx + dy * dy) as f64).sqrt();
                best = if best.is_nan() || z > best { z } else { best };
                if let FillMethod::Idw { power } = method {
                    let wt = 1.0 / dist.powf(power);
                    sw += wt;
                    swz += wt * f64::from(z);
                }
            }
            // The step rule: the highest and the lowest sample, each at its nearest distance,
            // farther apart in height than a 60° slope through the cell rises.
            let lo = samples.iter().map(|s| s.0).fold(f32::INFINITY, f32::min);
            let near = |v: f32| samples.iter().filter(|s| s.0 == v).map(|s| s.1).min().unwrap_or(0);
            let run = p * (f64::from(near(best)).sqrt() + f64::from(near(lo)).sqrt());
            let step = f64::from(best) - f64::from(lo) > 3f64.sqrt() * run;
            out[i] = match method {
                FillMethod::Max => best,
                FillMethod::Idw { .. } if step => best,
                FillMethod::Idw { .. } if sw > 0.0 => (swz / sw) as f32,
                FillMethod::Idw { .. } => f32::NAN,
            };
            // The bridge rule: along each line through the cell, the nearest data on both sides
            // with at most the bridge limit of empty cells between them, farther apart in height
            // than a 60° slope over the path through the cell rises: at least the higher one.
            if matches!(method, FillMethod::Idw { .. }) && out[i].is_finite() {
                let (axis, diag) = gap_limits(params.max_hole_mm, p);
                for (dc, dr) in [(1isize, 0isize), (0, 1), (1, 1), (1, -1)] {
                    let limit = if dc != 0 && dr != 0 { diag } else { axis } as usize;
                    let side = |sign: isize| {
                        (1..w.max(h) as isize).find_map(|k| {
                            let (cc, rr) = (c + sign * dc * k, r + sign * dr * k);
                            if cc < 0 || rr < 0 || cc >= w as isize || rr >= h as isize {
                                return Some(None);
                            }
                            let z = d[rr as usize * w + cc as usize];
                            z.is_finite().then_some(Some((z, k as f64)))
                        })?
                    };
                    let (Some((a, ka)), Some((b, kb))) = (side(1), side(-1)) else { continue };
                    if ka + kb - 1.0 > limit as f64 {
                        continue;
                    }
                    let unit = if dc != 0 && dr != 0 { 2f64.sqrt() } else { 1.0 };
                    if f64::from((a - b).abs()) > 3f64.sqrt() * p * unit * (ka + kb) {
                        out[i] = out[i].max(a.max(b));
                    }
                }
            }
        }
        out
    }

    /// A smooth surface, on half the maps with a step across it in each direction (0 to 3 mm),
    /// with random rectangles, stripes, single cells and a border margin removed.
    fn holey_map(rng: &mut StdRng, w: u32, h: u32, p: f64) -> HeightMap {
        let m = meta(w, h, p, rng.random_range(-3.0..3.0), rng.random_range(-3.0..3.0));
        let steps = rng.random_bool(0.5).then(|| {
            (
                rng.random_range(0..w),
                rng.random_range(0.0..3.0f32),
                rng.random_range(0..h),
                rng.random_range(-3.0..3.0f32),
            )
        });
        let mut map = HeightMap::from_fn(m, |c, r| {
            let z = (f64::from(c) * 0.3).sin() as f32 + 0.1 * r as f32;
            match steps {
                Some((sc, dc, sr, dr)) => z + if c >= sc { dc } else { 0.0 } + if r >= sr { dr } else { 0.0 },
                None => z,
            }
        })
        .expect("map");
        let (wi, hi) = (w as usize, h as usize);
        let d = map.data_mut();
        for _ in 0..rng.random_range(0..4) {
            let (c0, r0) = (rng.random_range(0..wi), rng.random_range(0..hi));
            let (cw, rh) = (rng.random_range(1..8), rng.random_range(1..8));
            for r in r0..(r0 + rh).min(hi) {
                for c in c0..(c0 + cw).min(wi) {
                    d[r * wi + c] = f32::NAN;
                }
            }
        }
        for _ in 0..rng.random_range(0..3) {
            let c = rng.random_range(0..wi);
            for r in 0..hi {
                d[r * wi + c] = f32::NAN;
            }
        }
        for _ in 0..rng.random_range(0..3) {
            let r = rng.random_range(0..hi);
            let row = &mut d[r * wi..(r + 1) * wi];
            row.iter_mut().for_each(|z| *z = f32::NAN);
        }
        for z in d.iter_mut() {
            if rng.random_bool(0.08) {
                *z = if rng.random_bool(0.5) { f32::NAN } else { f32::INFINITY };
            }
        }
        if rng.random_bool(0.5) {
            let m = rng.random_range(1..3);
            for r in 0..hi {
                for c in 0..wi {
                    if r < m || c < m || r + m >= hi || c + m >= wi {
                        d[r * wi + c] = f32::NAN;
                    }
                }
            }
        }
        map
    }

    #[test]
    fn bridges_and_components_match_references() {
        let mut rng = StdRng::seed_from_u64(13);
        for case in 0..80 {
            let (w, h) = (rng.random_range(1..30u32), rng.random_range(1..30u32));
            let map = holey_map(&mut rng, w, h, 0.1);
            let (wi, hi) = (w as usize, h as usize);
            let (axis, diag) = (rng.random_range(0..8), rng.random_range(0..6));
            let fast = bridge_mask(map.data(), wi, hi, axis, diag);
            let slow = brute_bridges(map.data(), wi, hi, axis, diag);
            assert_eq!(fast, slow, "case {case} {w}x{h} limits {axis}/{diag}");
            let d = map.data();
            let comps = components(wi, hi, |i| !d[i].is_finite());
            let got = labels_of(&comps, wi, hi);
            let want = brute_labels(wi, hi, |i| !d[i].is_finite());
            // Same partition, numbered in scan order of the first cell by both.
            assert_eq!(got, want, "case {case}");
            let sel = fill_selection(d, wi, hi, axis, diag).0;
            let want_sel = brute_selection(d, wi, hi, axis, diag);
            assert_eq!(sel.iter().map(|&s| s != 0).collect::<Vec<_>>(), want_sel, "case {case}");
        }
    }

    /// A band nobody saw between a high level and a low one (a chamfer or a wall's top edge) is
    /// filled at the high level, not at a height between the two; the same band on a 30° slope
    /// is interpolated.
    #[test]
    fn an_idw_fill_across_a_step_takes_the_high_side() {
        let p = 0.25;
        for (what, step) in [("step", true), ("slope", false)] {
            let m = meta(20, 12, p, 0.0, 0.0);
            let slope = 30f64.to_radians().tan() as f32 * p as f32;
            let mut map = HeightMap::from_fn(m, |c, _| match (step, c) {
                (true, c) if c < 8 => 13.0,
                (true, _) => 3.0,
                (false, c) => 3.0 + slope * c as f32,
            })
            .expect("map");
            let w = 20;
            for r in 0..12 {
                for c in 8..10 {
                    map.data_mut()[r * w + c] = f32::NAN;
                }
            }
            let params =
                FillParams { method: FillMethod::Idw { power: 2.0 }, max_hole_mm: 2.0, radius_mm: None };
            let (out, report) = fill_holes(&map, &params).expect("fill");
            assert_eq!(report.filled, 24, "{what}");
            for r in 0..12 {
                for c in 8..10 {
                    let z = out.data()[r * w + c];
                    if step {
                        assert_eq!(z, 13.0, "{what} ({c}, {r})");
                    } else {
                        // Near the plane through the band (within one cell of its rise; the
                        // highest sample would stand three above it).
                        let plane = 3.0 + slope * c as f32;
                        assert!((z - plane).abs() < slope, "{what} ({c}, {r}): {z} vs {plane}");
                    }
                }
            }
        }
    }

    /// A gap wider than the sample radius at a step (a cove's foot the scanner did not reach, a
    /// floor seen on one side, a plateau on the other) is filled at the plateau all across, not
    /// with the floor extended under the rise; the same gap on a 30° slope is interpolated.
    #[test]
    fn a_wide_gap_at_a_step_takes_the_high_side_near_the_low_side_too() {
        let p = 0.25;
        let w = 10;
        for (what, step) in [("step", true), ("slope", false)] {
            let m = meta(10, 24, p, 0.0, 0.0);
            let slope = 30f64.to_radians().tan() as f32 * p as f32;
            let mut map = HeightMap::from_fn(m, |_, r| match (step, r) {
                (true, r) if r < 10 => 1.0,
                (true, _) => 5.0,
                (false, r) => 1.0 + slope * r as f32,
            })
            .expect("map");
            for r in 10..16 {
                for c in 0..w {
                    map.data_mut()[r * w + c] = f32::NAN;
                }
            }
            let params =
                FillParams { method: FillMethod::Idw { power: 2.0 }, max_hole_mm: 2.0, radius_mm: None };
            let (out, report) = fill_holes(&map, &params).expect("fill");
            assert_eq!(report.filled, 60, "{what}");
            for r in 10..16 {
                for c in 0..w {
                    let z = out.data()[r * w + c];
                    if step {
                        assert_eq!(z, 5.0, "{what} ({c}, {r})");
                    } else {
                        // Near the plane (the IDW extends each side a little flat), never a side's
                        // level carried across the gap: the bridge rule stays out.
                        let plane = 1.0 + slope * r as f32;
                        assert!((z - plane).abs() < 3.0 * slope, "{what} ({c}, {r}): {z} vs {plane}");
                    }
                }
            }
        }
    }

    #[test]
    fn fills_match_brute_force() {
        let mut rng = StdRng::seed_from_u64(17);
        let mut total_filled = 0;
        for case in 0..60 {
            let p = [0.1, 0.25, 0.5][case % 3];
            let (w, h) = (rng.random_range(3..28u32), rng.random_range(3..28u32));
            let map = holey_map(&mut rng, w, h, p);
            let method = if case % 2 == 0 {
                FillMethod::Max
            } else {
                FillMethod::Idw { power: [0.0, 1.0, 2.0, 3.5][rng.random_range(0..4)] }
            };
            let params = FillParams {
                method,
                max_hole_mm: rng.random_range(0.0..8.0) * p,
                radius_mm: rng.random_bool(0.5).then(|| rng.random_range(0.6..4.0) * p),
            };
            let (got, report) = fill_holes(&map, &params).expect("valid params");
            assert_eq!(got.meta(), map.meta());
            let (wi, hi) = (w as usize, h as usize);
            let (axis, diag) = gap_limits(params.max_hole_mm, p);
            let sel = brute_selection(map.data(), wi, hi, axis, diag);
            let want = brute_fill(map.data(), wi, hi, &sel, p, &params);
            let mut filled = 0;
            for (i, (&a, &b)) in got.data().iter().zip(&want).enumerate() {
                let ok = match method {
                    FillMethod::Max => same(a, b) || (!a.is_finite() && !b.is_finite()),
                    FillMethod::Idw { .. } => {
                        (!a.is_finite() && !b.is_finite()) || (a - b).abs() <= 1e-5 * (1.0 + b.abs())
                    }
                };
                assert!(ok, "case {case} {method:?} cell {i}: {a} vs {b}");
                if sel[i] && b.is_finite() {
                    filled += 1;
                }
            }
            assert_eq!(report.filled, filled, "case {case}");
            total_filled += filled;
            // Unselected cells are untouched, bit for bit.
            for (i, (&a, &b)) in got.data().iter().zip(map.data()).enumerate() {
                if !sel[i] {
                    assert_eq!(a.to_bits(), b.to_bits());
                }
            }
        }
        // The random maps exercise the fill for real.
        assert!(total_filled > 1000, "{total_filled}");
    }

    /// 0.1 mm cells; `part(c, r)` says where the part is (z = a gentle slope there).
    fn part_map(w: u32, h: u32, part: impl Fn(i64, i64) -> bool) -> HeightMap {
        HeightMap::from_fn(meta(w, h, 0.1, 0.0, 0.0), |c, r| {
            if part(i64::from(c), i64::from(r)) { 1.0 + 0.01 * c as f32 } else { f32::NAN }
        })
        .expect("map")
    }

    fn idw(max_hole_mm: f64) -> FillParams {
        FillParams { method: FillMethod::Idw { power: 2.0 }, max_hole_mm, radius_mm: None }
    }

    #[test]
    fn outer_margin_of_a_convex_part_is_never_filled() {
        // A disk of radius 2 mm with a 1-cell hole and a 3-cell hole inside; a wide empty margin.
        let inside = |c: i64, r: i64| (c - 30) * (c - 30) + (r - 30) * (r - 30) <= 400;
        let holes = |c: i64, r: i64| (c, r) == (30, 30) || (r == 25 && (20..23).contains(&c));
        let map = part_map(60, 60, |c, r| inside(c, r) && !holes(c, r));
        for method in [FillMethod::Max, FillMethod::Idw { power: 2.0 }] {
            let (filled, report) =
                fill_holes(&map, &FillParams { method, max_hole_mm: 5.0, radius_mm: None }).expect("fill");
            for r in 0..60 {
                for c in 0..60 {
                    let v = filled.get(c as u32, r as u32).expect("cell");
                    assert_eq!(v.is_finite(), inside(c, r), "({c}, {r})");
                }
            }
            assert_eq!(report.filled, 4);
            assert_eq!(report.left_empty_enclosed, 0);
        }
    }

    #[test]
    fn enclosed_hole_thicker_than_max_hole_stays_empty() {
        // 3 x 3 mm square hole and a 4 mm round hole in a full 10 x 10 mm part; max_hole 2 mm.
        let square = |c: i64, r: i64| (20..50).contains(&c) && (20..50).contains(&r);
        let round = |c: i64, r: i64| (c - 75) * (c - 75) + (r - 75) * (r - 75) < 400;
        let small = |c: i64, r: i64| (c - 20) * (c - 20) + (r - 80) * (r - 80) < 81;
        let map = part_map(100, 100, |c, r| !square(c, r) && !round(c, r) && !small(c, r));
        let (filled, report) = fill_holes(&map, &idw(2.0)).expect("fill");
        let mut big = 0;
        for r in 0..100 {
            for c in 0..100 {
                let v = filled.get(c as u32, r as u32).expect("cell");
                if square(c, r) || round(c, r) {
                    assert!(v.is_nan(), "({c}, {r}) was filled");
                    big += 1;
                } else {
                    assert!(v.is_finite(), "({c}, {r}) left empty");
                }
            }
        }
        assert_eq!(report.holes_too_large, 2);
        assert_eq!(report.left_empty_enclosed, big);
        // A 1.8 mm hole (the small one) is filled: values between the neighbours'.
        let (lo, hi) = map.z_range_of_data().expect("data");
        let v = filled.get(20, 80).expect("cell");
        assert!(v >= lo && v <= hi, "{v}");
    }

    #[test]
    fn one_pixel_stripes_across_the_whole_part_are_filled() {
        // A 6 x 6 mm part with a 0.5 mm empty margin; empty column 20 and empty rows 30-31 run
        // across the whole ROI, out through the margin to the border; a diagonal stripe too.
        let body = |c: i64, r: i64| (5..65).contains(&c) && (5..65).contains(&r);
        let stripe = |c: i64, r: i64| c == 20 || r == 30 || r == 31 || c - r == 7 || c - r == 8;
        let map = part_map(70, 70, |c, r| body(c, r) && !stripe(c, r));
        for method in [FillMethod::Max, FillMethod::Idw { power: 2.0 }] {
            let (filled, _) =
                fill_holes(&map, &FillParams { method, max_hole_mm: 0.5, radius_mm: None }).expect("fill");
            for r in 0..70 {
                for c in 0..70 {
                    let v = filled.get(c as u32, r as u32).expect("cell");
                    assert_eq!(v.is_finite(), body(c, r), "({c}, {r}) {method:?}");
                }
            }
            // Across a stripe on a slope the fill interpolates (IDW) or takes the neighbourhood max.
            let v = filled.get(20, 40).expect("cell");
            match method {
                FillMethod::Idw { .. } => assert!((v - 1.2).abs() < 0.01, "{v}"),
                FillMethod::Max => assert!(v > 1.2, "{v}"),
            }
        }
    }

    #[test]
    fn notch_wider_than_max_hole_is_not_filled_but_a_narrow_one_is() {
        // Part rows 5..55, cols 5..95, empty margin of 5 cells. Top edge: a 3 mm wide, 2 mm deep
        // notch (cols 20..50, rows 35..55) and a 1 mm wide one (cols 70..80).
        let body = |c: i64, r: i64| (5..95).contains(&c) && (5..55).contains(&r);
        let wide = |c: i64, r: i64| (20..50).contains(&c) && (35..55).contains(&r);
        let narrow = |c: i64, r: i64| (70..80).contains(&c) && (35..55).contains(&r);
        let map = part_map(100, 60, |c, r| body(c, r) && !wide(c, r) && !narrow(c, r));
        let (filled, _) = fill_holes(&map, &idw(2.0)).expect("fill");
        // Diagonal gap limit: floor(2 / (0.1·√2)) = 14 cells.
        let (_, diag) = gap_limits(2.0, 0.1);
        assert_eq!(diag, 14);
        let mut corner_cells = 0;
        for r in 0..60 {
            for c in 0..100 {
                let v = filled.get(c as u32, r as u32).expect("cell");
                if wide(c, r) {
                    // Only the two inner-corner triangles, where a diagonal chord between the
                    // notch's wall and floor is at most 2 mm, are filled.
                    let (i, i_right, j) = (c - 20, 49 - c, r - 35);
                    let corner = i + j < 14 || i_right + j < 14;
                    assert_eq!(v.is_finite(), corner, "wide notch ({c}, {r})");
                    corner_cells += usize::from(corner);
                } else {
                    assert_eq!(v.is_finite(), body(c, r), "({c}, {r})");
                }
            }
        }
        assert_eq!(corner_cells, 2 * (14 * 15 / 2));
        // Nothing above the part's top edge, the notch's centre line stays empty.
        assert!((35..55).all(|r| filled.get(35, r).is_some_and(f32::is_nan)));
    }

    #[test]
    fn fill_params_are_checked_by_name() {
        let map = part_map(5, 5, |_, _| true);
        let cases = [
            (FillParams { max_hole_mm: -1.0, ..idw(1.0) }, "fill.max_hole_mm = -1"),
            (FillParams { max_hole_mm: f64::NAN, ..idw(1.0) }, "fill.max_hole_mm = NaN"),
            (FillParams { radius_mm: Some(0.0), ..idw(1.0) }, "fill.radius_mm = 0"),
            (FillParams { radius_mm: Some(13.0), ..idw(1.0) }, "fill.radius_mm = 13"),
            (FillParams { method: FillMethod::Idw { power: -1.0 }, ..idw(1.0) }, "fill.power = -1"),
            (FillParams { method: FillMethod::Idw { power: f64::NAN }, ..idw(1.0) }, "fill.power = NaN"),
        ];
        for (params, msg) in cases {
            let e = fill_holes(&map, &params).expect_err(msg).to_string();
            assert!(e.starts_with(&format!("invalid {msg}")), "{e} / {msg}");
        }
        assert!((idw(2.0).radius_for(0.1).expect("ok") - (1.0 + 0.1 * SQRT_2)).abs() < 1e-12);
        assert_eq!(idw(1000.0).radius_for(0.1).expect("capped"), 12.8);
        let (same_map, report) = fill_holes(&map, &idw(0.0)).expect("nothing to do");
        assert!(same_map.bitwise_eq(&map));
        assert_eq!(report, FillReport::default());
    }

    /// Coverage spelled out with flood-fill labels: per component, its cells listed.
    fn brute_coverage(raw: &HeightMap, filled: &HeightMap) -> (Vec<f32>, usize, Option<HoleStats>, usize) {
        let m = *raw.meta();
        let (w, h) = (m.width as usize, m.height as usize);
        let (rd, fd) = (raw.data(), filled.data());
        let empty = |i: usize| !rd[i].is_finite() && !fd[i].is_finite();
        let label = brute_labels(w, h, empty);
        let on_border = |i: usize| i.is_multiple_of(w) || i % w == w - 1 || i / w == 0 || i / w == h - 1;
        let cov: Vec<f32> = (0..w * h)
            .map(|i| {
                if rd[i].is_finite() {
                    1.0
                } else if fd[i].is_finite() {
                    0.5
                } else if (0..w * h).any(|j| label[j] == label[i] && on_border(j)) {
                    f32::NAN
                } else {
                    0.0
                }
            })
            .collect();
        let summary = |member: &dyn Fn(usize) -> bool| {
            let label = brute_labels(w, h, member);
            let count = label.iter().filter(|&&l| l != usize::MAX).max().map_or(0, |&l| l + 1);
            let mut best: Option<Vec<usize>> = None;
            for l in 0..count {
                let cells: Vec<usize> = (0..w * h).filter(|&i| label[i] == l).collect();
                if best.as_ref().is_none_or(|b| cells.len() > b.len()) {
                    best = Some(cells);
                }
            }
            let p = m.pixel_mm;
            let stats = best.map(|cells| {
                let n = cells.len() as f64;
                let cols = cells.iter().map(|&i| (i % w) as u64);
                let rows = cells.iter().map(|&i| (i / w) as u64);
                let (c0, c1) = (cols.clone().min().unwrap_or(0), cols.clone().max().unwrap_or(0));
                let (r0, r1) = (rows.clone().min().unwrap_or(0), rows.clone().max().unwrap_or(0));
                HoleStats {
                    cells: cells.len(),
                    area_mm2: n * p * p,
                    center_x_mm: m.origin_x_mm + (cols.sum::<u64>() as f64 / n + 0.5) * p,
                    center_y_mm: m.origin_y_mm + (rows.sum::<u64>() as f64 / n + 0.5) * p,
                    min_x_mm: m.origin_x_mm + c0 as f64 * p,
                    min_y_mm: m.origin_y_mm + r0 as f64 * p,
                    max_x_mm: m.origin_x_mm + (c1 + 1) as f64 * p,
                    max_y_mm: m.origin_y_mm + (r1 + 1) as f64 * p,
                }
            });
            (count, stats)
        };
        let (holes, largest) = summary(&|i| cov[i] == 0.5 || cov[i] == 0.0);
        let (unfilled, _) = summary(&|i| cov[i] == 0.0);
        (cov, holes, largest, unfilled)
    }

    #[test]
    fn coverage_matches_reference() {
        let mut rng = StdRng::seed_from_u64(23);
        for case in 0..40 {
            let (w, h) = (rng.random_range(1..26u32), rng.random_range(1..26u32));
            let raw = holey_map(&mut rng, w, h, 0.2);
            let params = FillParams { max_hole_mm: rng.random_range(0.0..1.5), ..FillParams::default() };
            let (filled, _) = fill_holes(&raw, &params).expect("fill");
            let (map, stats) = coverage(&raw, &filled);
            let (want, holes, largest, unfilled) = brute_coverage(&raw, &filled);
            for (i, (&a, &b)) in map.data().iter().zip(&want).enumerate() {
                assert!(same(a, b), "case {case} cell {i}: {a} vs {b}");
            }
            assert_eq!(
                (stats.holes, stats.largest_hole, stats.unfilled_holes),
                (holes, largest, unfilled),
                "case {case}"
            );
            let count = |v: f32| want.iter().filter(|&&x| x == v).count();
            assert_eq!((stats.measured, stats.filled, stats.empty), (count(1.0), count(0.5), count(0.0)));
        }
    }

    #[test]
    fn coverage_of_planted_holes_is_exact() {
        // 50 x 40 cells of 0.5 mm at (10, 20); a 1-cell empty margin; a 6 x 4 hole and a 2-cell one.
        let big = |c: i64, r: i64| (10..16).contains(&c) && (5..9).contains(&r);
        let small = |c: i64, r: i64| r == 30 && (40..42).contains(&c);
        let border = |c: i64, r: i64| c == 0 || r == 0 || c == 49 || r == 39;
        let raw = HeightMap::from_fn(meta(50, 40, 0.5, 10.0, 20.0), |c, r| {
            let (c, r) = (i64::from(c), i64::from(r));
            if big(c, r) || small(c, r) || border(c, r) { f32::NAN } else { 3.0 }
        })
        .expect("map");
        // max_hole 1.5 mm fills the small hole (1 mm) but not the 3 x 2 mm one.
        let (filled, report) = fill_holes(&raw, &idw(1.5)).expect("fill");
        assert_eq!((report.filled, report.holes_too_large, report.left_empty_enclosed), (2, 1, 24));
        let (map, stats) = coverage(&raw, &filled);
        assert_eq!((map.z_min_mm(), map.z_max_mm()), (0.0, 1.0));
        assert_eq!(map.origin_x_mm(), 10.0);
        let measured = 48 * 38 - 26;
        assert_eq!(stats.cells, 2000);
        assert_eq!((stats.measured, stats.filled, stats.empty), (measured, 2, 24));
        assert_eq!(stats.footprint, measured + 26);
        assert!((stats.covered_pct - measured as f64 / (measured + 26) as f64 * 100.0).abs() < 1e-12);
        assert_eq!((stats.holes, stats.unfilled_holes), (2, 1));
        let want = HoleStats {
            cells: 24,
            area_mm2: 6.0,
            center_x_mm: 16.5,
            center_y_mm: 23.5,
            min_x_mm: 15.0,
            min_y_mm: 22.5,
            max_x_mm: 18.0,
            max_y_mm: 24.5,
        };
        assert_eq!(stats.largest_hole, Some(want));
        assert_eq!(stats.largest_unfilled_hole, Some(want));
        for r in 0..40 {
            for c in 0..50 {
                let v = map.get(c, r).expect("cell");
                let (ci, ri) = (i64::from(c), i64::from(r));
                let expect = if border(ci, ri) {
                    f32::NAN
                } else if big(ci, ri) {
                    COVERAGE_HOLE
                } else if small(ci, ri) {
                    COVERAGE_FILLED
                } else {
                    COVERAGE_MEASURED
                };
                assert!(same(v, expect), "({c}, {r}) {v}");
            }
        }
        // Without filling, both holes are empty footprint cells; a mismatched map is ignored.
        let (_, unfilled) = coverage(&raw, &raw);
        assert_eq!((unfilled.filled, unfilled.empty, unfilled.unfilled_holes), (0, 26, 2));
        let other = part_map(3, 3, |_, _| true);
        assert_eq!(coverage(&raw, &other).1, unfilled);
        // Everything empty: no footprint.
        let none = part_map(4, 4, |_, _| false);
        let (_, s) = coverage(&none, &none);
        assert_eq!((s.footprint, s.covered_pct, s.holes, s.largest_hole), (0, 0.0, 0, None));
    }
}
