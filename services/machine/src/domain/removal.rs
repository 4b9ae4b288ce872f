//! Material removal for 3-axis work: the stock as a Z-map, the tool as a solid of revolution swept
//! along lines and arcs, and what each move (or each spindle revolution) removed.
//!
//! # Model
//!
//! - **Stock** ([`Stock`]): a Z-map. Each cell holds the height of the stock's top (f32, mm) on
//!   the [`HeightMap`] grid convention (corner origin, row 0 at minimum Y, the value is a point
//!   sample at the cell centre); the material of a cell is the column `[bottom, top]` over the
//!   whole cell, so the volume is `Σ (top − bottom) · cell²`. A cut never lowers a top below the
//!   bottom (a tool passing under the stock leaves an empty column).
//! - **Hardness**: a cell may carry one *hard band* `[lo, hi]` in Z with a factor (1 = nominal);
//!   material of the cell inside the band weighs `factor`, the rest 1. A sphere
//!   ([`Stock::set_hardness_sphere`]) gives each cell whose centre lies within its radius the
//!   sphere's chord above that centre as its band. Simplification: one band per cell; where two
//!   inclusions overlap in XY the cell takes the hull of both bands and the later factor.
//!   The hardness is stored only once an inclusion is set (no cost otherwise).
//! - **Tool** ([`ToolProfile`]): a solid of revolution. Its lower surface is
//!   `z = tip_z + h(r)` for `r <= R` with `h` non-decreasing, `h(0) = 0`; above that surface the
//!   tool (and its shank and holder) fills the whole cylinder of radius `R`, which is all a Z-map
//!   can see from above. `h` is the exact arc for ball and bull-nose tools (not their polylines)
//!   and the polyline itself for flat, V and custom tools, as [`ToolProfile::height_at`] defines.
//!
//! # The swept envelope
//!
//! When the tip moves along `P(t) = (p(t), z(t))`, `t ∈ [0, 1]`, the tool occupies the column over
//! a cell centre `q` from `E(q) = min_t [ z(t) + h(|q − p(t)|) ]` up (terms with `|q − p(t)| > R`
//! are `+∞`), and the cut sets `top(q) ← max(bottom, min(top(q), E(q)))`. Everything below is
//! about computing `E(q)` exactly at every cell centre the tool reaches.
//!
//! **Straight moves.** Put `q` in the move's horizontal frame: `s` along the move (0 at the start,
//! `L` = horizontal length at the end), `e` across it; `m = Δz / L` is the slope. With `σ` the
//! tip's position along the move relative to `q` (`σ ∈ [−s, L − s]`) the tool height over `q` is
//! `f(σ) = z₀ + m·(s + σ) + h(√(σ² + e²))`, and `E(q) = min f`. Three cases:
//!
//! - *Level moves* (`m = 0`) and *vertical moves* (`L = 0`, plunges and retracts): `h` grows with
//!   distance, so the nearest tool position wins: `E(q) = z_low + h(d)`, with `d` the distance
//!   from `q` to the horizontal segment (or point). Exact; one square root for a ball, none for a
//!   flat end.
//! - *Ball mill, sloped*: `h(r) = R − √(R² − r²)`, so with `w² = R² − e²`,
//!   `f(σ) = z₀ + m·(s + σ) + R − √(w² − σ²)`: convex, stationary at `σ* = −m·w/√(1 + m²)`, where
//!   `f = z₀ + m·(s + σ*) + R − w/√(1 + m²)` (the lower intersection of the vertical through `q`
//!   with the cylinder of radius `R` around the centre line: the swept solid is a capsule). When
//!   `σ*` falls outside `[−s, L − s]` the minimum is at the clamped end, on an end sphere.
//! - *Any other profile, sloped*: split `h` into its pieces. On a straight piece
//!   `h = h₀ + k·(r − r₀)`, `r ∈ [r₀, r₁]`, the piece's `σ`-set is one interval
//!   (`e >= r₀`: `|σ| <= √(r₁² − e²)`) or two (`√(r₀² − e²) <= |σ| <= √(r₁² − e²)`), and on each
//!   `g(σ) = m·σ + k·√(σ² + e²)` is convex with stationary point `σ = −m·e/√(k² − m²)` when
//!   `k > |m|` (otherwise `g` is monotone and an end wins). The clamp of the stationary point to
//!   the interval (intersected with `[−s, L − s]`) is the piece's exact minimum, and `E` is the
//!   lowest over pieces. This is exact for every polyline, including non-convex custom profiles,
//!   because no convexity across pieces is needed. The torus of a bull-nose mill is one convex
//!   piece (`h` convex and non-decreasing composed with the convex `√(σ² + e²)`); there the root
//!   of `f′` is found by bisection to 1e-10 mm of tool travel, which leaves an error far below the
//!   f32 heights (this is the one iterative step).
//!
//! A move whose horizontal length is below [`VERTICAL_EPS_MM`] is treated as vertical (error
//! below that length in XY).
//!
//! **Arcs in XY.** A level arc whose start and end radii agree within `cell · ARC_SAGITTA_CELLS`
//! is exact: `E(q) = z + h(d)` with `d` the distance to the arc (`|‖q − c‖ − ρ|` when `q`'s
//! direction from the centre lies within the swept angle, else the distance to the nearer end),
//! using the mean radius (the arc's end points then move by at most half that tolerance).
//! Full circles (start angle = end angle, or `turns > 0`) are whole rings. Helices (Z changes)
//! and spirals (radii differ) are cut as chords, each chord exactly as a straight move, with the
//! chord count chosen so the sagitta is at most [`ARC_SAGITTA_CELLS`] of a cell: every tool
//! position of the chords lies within that distance (in XY) of the true path and vice versa, so
//! the swept solids differ by at most that Hausdorff distance. This is the only geometric
//! approximation in the module.
//!
//! # What a cut reports ([`Cut`])
//!
//! - Volume: `Σ (old − new) · cell²` over the lowered cells, in f64 from the f32 tops (the
//!   difference of two f32 is exact in f64), so `volume before − volume after = Σ volumes` up to
//!   f64 summation rounding. Hardness-weighted volume adds `(factor − 1) · cell² · |[new, old] ∩
//!   [lo, hi]|` per cell.
//! - Engagement ([`Cut::engagement_deg`]): seen from the tool axis at the end of the move, in the
//!   horizontal travel direction there (the tangent for arcs). The *engaged cells* are the cells
//!   in the front half (`(q − p_end)·dir >= 0`) that the move lowered within `R` of the axis,
//!   plus, for profiles with a horizontal part (flat, bull-nose, ...), those just outside the rim
//!   (`R < ρ <= R + cell`) where material stands above the rim's lowest point `z_end + h(R)`
//!   (the periphery touches it: without these, a flat end advancing less than a cell per
//!   revolution removes a crescent too thin for the grid to resolve at its tips; a sloped
//!   profile lowers the whole front half of its contact disc at any feed). With `e` their signed offset across the travel direction, `ρ_c` the largest
//!   distance of an engaged cell from the axis (the contact radius: about `R` for a flat end,
//!   less for a ball at a shallow depth) and `p` the cell size, the engaged arc runs from
//!   `θ_min = asin((e_min − p/2)/ρ_c)` to `θ_max = asin((e_max + p/2)/ρ_c)` (clamped to ±90°; the
//!   half cell is the column a cell stands for), and the engagement is `θ_max − θ_min`: 180° for a
//!   slot, 90° for half immersion, `acos(1 − ae/R)` for a side cut of radial width `ae` (all
//!   within 2° in the tests, also per revolution and at an angle to the grid); gaps between the
//!   extremes count as engaged. A move that lowers no cell reports 0 (an air cut, or a tool
//!   grazing a wall). A move without horizontal travel (a plunge) reports
//!   `180° × (occupied 10° sectors around the axis) / 36`.
//! - Axial depth ([`Cut::axial_depth_mm`]): over the same engaged cells, the largest height of
//!   the material (before the cut; beside the rim, as it stands) above the tip's end Z; 0 when
//!   nothing was removed.
//!
//! [`cut_line_per_rev`] and [`cut_arc_xy_per_rev`] split a move into pieces of one feed per
//! revolution; the envelope of the whole move is the minimum over its pieces, so the pieces
//! remove the same material as one cut (up to f32 rounding of the shared end points).
//!
//! # Speed
//!
//! Only the footprint is visited: the rows within `R` of the move and, per row, the columns
//! inside the capsule (segment ⊕ disc of radius `R`; ring ∩ box for arcs). Before the envelope
//! is computed at a cell, a cheap test decides whether it can lower the cell at all:
//!
//! - Ball mills: an *exact* test without square roots. The envelope is at least a level `t`
//!   exactly when both end spheres are (`b = z_end + R − t >= 0` and `b² >= R² − d_end²`) and,
//!   when the stationary point lies on the move, the cylinder value is
//!   (`a = z₀ + m·s + R − t >= 0` and `a² >= (R² − e²)(1 + m²)`); whether `σ*` lies on the move
//!   is a squared comparison too. `t` is the cell's top lowered by just under half an f32 step,
//!   so an envelope at or above it cannot change the f32 top. The tests of a chunk of 64 cells
//!   run branch-free (vectorised), and only the cells that will really be lowered pay for the
//!   envelope's square roots: in the finishing benchmark about as many as are updated.
//! - Other tools: a lower bound `z_low + h_lb(d²)` (the lowest tip Z plus `h` at the distance
//!   to the segment, from a 256-entry table of `h` by `d²` rounded down) against the top.
//!
//! A cut that continues the same tool's last one from where it ended ([`Stock::cut_line_after`]:
//! the next revolution of a feed move, which the simulator cuts one after another) skips the
//! cells behind its start that the tool's position there already bounds: every cell behind it on
//! a level or rising move, those more than `R·|m|/√(1+m²)` behind it for a ball on a descending
//! one (see `LineJob::skip_before`). About half of a revolution's footprint.
//!
//! [`Stock::cut_path`] runs a program of straight moves in parallel strips: rows are split into
//! bands of [`BAND_ROWS`], each band applies, in program order, the moves whose footprint reaches
//! it (in batches of 4096 moves); every cell sees the same sequence of updates as in a sequential
//! run, so the result is identical and each move's figures are the sums over bands. A single
//! move whose footprint exceeds [`PAR_CELLS`] cells is itself split into bands across threads.
//! [`Stock::cut_line_baseline`] is the same sweep over the whole bounding box of the move
//! without any test (the benchmark's reference; identical result).

use std::f64::consts::{PI, TAU};

use depthmill_geometry::{HeightMap, HeightMapMeta, MAX_CELLS, ToolProfile, ToolSpec};
use nalgebra::Point3;
use rayon::prelude::*;

/// Largest absolute coordinate accepted for a point (mm): 1 km.
pub const MAX_COORD_MM: f64 = 1.0e6;
/// Largest number of pieces (revolutions, or chords of a helix) one move may be split into.
pub const MAX_PIECES: u64 = 10_000_000;
/// Largest chord sagitta for helical and spiral arcs, in cells (1/20 of a cell).
pub const ARC_SAGITTA_CELLS: f64 = 0.05;
/// A straight move whose horizontal length is below this (mm) is treated as vertical.
pub const VERTICAL_EPS_MM: f64 = 1.0e-7;
/// Rows per band in the parallel sweeps.
pub const BAND_ROWS: usize = 32;
/// A single move whose footprint has more cells than this is swept in parallel bands.
pub const PAR_CELLS: u64 = 1 << 18;
/// Moves per batch in [`Stock::cut_path`] (bounds the per-band bookkeeping).
const PATH_CHUNK: usize = 4096;
/// Entries of the lower-bound table of `h` (non-ball tools).
const LB_TABLE: usize = 256;
/// Cells per chunk of a row in the branch-free sweep.
const ROW_CHUNK: usize = 64;
/// Material must stand this far above the rim's lowest point to count as touching it (mm).
const RIM_EPS_MM: f64 = 1.0e-4;
/// Bisection tolerance for the bull-nose torus, mm of tool travel.
const TORUS_TOL_MM: f64 = 1.0e-10;

/// Invalid parameters of the material-removal model; each names the field and its value.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RemovalError {
    /// A scalar outside its domain (non-positive cell size, non-finite length, ...).
    #[error("invalid {field} {value}: expected {expected}")]
    InvalidParameter { field: String, value: f64, expected: &'static str },
    /// A point with a non-finite or absurdly large coordinate.
    #[error("invalid {field} ({x}, {y}, {z}): expected finite coordinates within ±{limit} mm")]
    InvalidPoint { field: String, x: f64, y: f64, z: f64, limit: f64 },
    /// The stock grid would exceed [`MAX_CELLS`].
    #[error("stock of {nx} x {ny} cells exceeds the limit of {limit} cells")]
    TooManyCells { nx: u64, ny: u64, limit: u64 },
    /// The stock's grid was refused by the height-map checks.
    #[error("invalid stock grid: {reason}")]
    Grid { reason: String },
    /// A move would be split into more than [`MAX_PIECES`] pieces.
    #[error("{field} {value} splits the move into {pieces} pieces, more than the limit of {limit}")]
    TooManyPieces { field: &'static str, value: f64, pieces: f64, limit: u64 },
}

fn invalid(field: impl Into<String>, value: f64, expected: &'static str) -> RemovalError {
    RemovalError::InvalidParameter { field: field.into(), value, expected }
}

fn check_point(field: impl FnOnce() -> String, p: &Point3<f64>) -> Result<(), RemovalError> {
    if p.iter().all(|v| v.is_finite() && v.abs() <= MAX_COORD_MM) {
        Ok(())
    } else {
        Err(RemovalError::InvalidPoint { field: field(), x: p.x, y: p.y, z: p.z, limit: MAX_COORD_MM })
    }
}

/// What one cut removed.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Cut {
    /// Cells whose envelope was considered (the footprint after row/column clipping).
    pub cells_visited: u64,
    /// Cells whose top was lowered.
    pub cells_updated: u64,
    /// Removed volume, mm³.
    pub volume_mm3: f64,
    /// Removed volume weighted by the hardness factor (equals `volume_mm3` in nominal stock).
    pub hard_volume_mm3: f64,
    /// Largest drop of a single cell's top, mm.
    pub max_depth_mm: f64,
    /// Radial engagement at the end of the move, degrees in `[0, 180]` (see the module docs).
    pub engagement_deg: f64,
    /// Height of the engaged material above the tip at the end of the move, mm.
    pub axial_depth_mm: f64,
}

impl Cut {
    /// Adds a cut that followed this one: counts and volumes add up, the depth is the larger,
    /// engagement and axial depth are the later cut's (they describe the end of the motion).
    pub fn accumulate(&mut self, later: &Cut) {
        self.cells_visited += later.cells_visited;
        self.cells_updated += later.cells_updated;
        self.volume_mm3 += later.volume_mm3;
        self.hard_volume_mm3 += later.hard_volume_mm3;
        self.max_depth_mm = self.max_depth_mm.max(later.max_depth_mm);
        self.engagement_deg = later.engagement_deg;
        self.axial_depth_mm = later.axial_depth_mm;
    }
}

/// A cell's hard band: material with `lo <= z <= hi` weighs `factor`.
#[derive(Debug, Clone, Copy, PartialEq)]
struct HardBand {
    factor: f32,
    lo: f32,
    hi: f32,
}

const NOMINAL: HardBand = HardBand { factor: 1.0, lo: 0.0, hi: 0.0 };

/// The stock: a Z-map of top heights over a flat bottom, with an optional hardness field
/// (see the module docs).
#[derive(Debug, Clone)]
pub struct Stock {
    top: HeightMap,
    bottom: f32,
    hard: Option<Vec<HardBand>>,
    /// The last tool's prepared shape.
    cache: Option<(ToolProfile, Shape)>,
}

impl Stock {
    /// A block `x_mm × y_mm × z_mm` with its minimum corner at `origin` (mm), on cells of
    /// `cell_mm`. The grid has `ceil(x_mm / cell_mm)` × `ceil(y_mm / cell_mm)` cells (a length that
    /// is not a whole number of cells is rounded up); the top is at `origin.z + z_mm`.
    ///
    /// Errors: non-finite or non-positive sizes, a non-finite origin, more than [`MAX_CELLS`] cells.
    pub fn block(
        origin: Point3<f64>,
        x_mm: f64,
        y_mm: f64,
        z_mm: f64,
        cell_mm: f64,
    ) -> Result<Stock, RemovalError> {
        check_point(|| "origin".into(), &origin)?;
        for (field, v) in [("cell_mm", cell_mm), ("x_mm", x_mm), ("y_mm", y_mm), ("z_mm", z_mm)] {
            if !(v.is_finite() && v > 0.0) {
                return Err(invalid(field, v, "a finite positive length"));
            }
        }
        if z_mm > MAX_COORD_MM {
            return Err(invalid("z_mm", z_mm, "a height within 1 km"));
        }
        let count = |len: f64| ((len / cell_mm) - 1e-9).ceil().max(1.0);
        let (nx, ny) = (count(x_mm), count(y_mm));
        let limit = MAX_CELLS as f64;
        if nx * ny > limit || nx > f64::from(u32::MAX) || ny > f64::from(u32::MAX) {
            return Err(RemovalError::TooManyCells {
                nx: nx.min(u64::MAX as f64) as u64,
                ny: ny.min(u64::MAX as f64) as u64,
                limit: MAX_CELLS,
            });
        }
        let bottom = origin.z as f32;
        let top0 = (origin.z + z_mm) as f32;
        let mut meta = HeightMapMeta::new(nx as u32, ny as u32, cell_mm);
        meta.origin_x_mm = origin.x;
        meta.origin_y_mm = origin.y;
        meta.z_min_mm = f64::from(bottom);
        meta.z_max_mm = f64::from(top0).max(f64::from(bottom) + 1e-3);
        let top = HeightMap::filled(meta, top0).map_err(|e| RemovalError::Grid { reason: e.to_string() })?;
        Ok(Stock { top, bottom, hard: None, cache: None })
    }

    /// The current top as a height map (Z range: bottom to initial top).
    pub fn to_height_map(&self) -> HeightMap {
        self.top.clone()
    }

    /// The current top, borrowed.
    pub fn height_map(&self) -> &HeightMap {
        &self.top
    }

    /// Edge of a cell, mm.
    pub fn cell_mm(&self) -> f64 {
        self.top.pixel_mm()
    }

    /// Z of the stock's bottom, mm.
    pub fn bottom_z_mm(&self) -> f64 {
        f64::from(self.bottom)
    }

    /// Top of the stock over the cell containing `(x_mm, y_mm)`, or `None` off the grid.
    pub fn top_at(&self, x_mm: f64, y_mm: f64) -> Option<f64> {
        let (c, r) = self.top.meta().cell_of(x_mm, y_mm)?;
        self.top.data().get(r as usize * self.top.width() as usize + c as usize).map(|z| f64::from(*z))
    }

    /// Material volume, mm³: `Σ (top − bottom) · cell²`.
    pub fn volume_mm3(&self) -> f64 {
        let b = f64::from(self.bottom);
        let sum: f64 = self.top.data().iter().map(|z| f64::from(*z) - b).sum();
        sum * self.cell_mm() * self.cell_mm()
    }

    /// Hardness factor of the material at `(x, y, z)` (1 = nominal, also off the grid).
    pub fn hardness_at(&self, x_mm: f64, y_mm: f64, z_mm: f64) -> f32 {
        let (Some(hard), Some((c, r))) = (&self.hard, self.top.meta().cell_of(x_mm, y_mm)) else {
            return 1.0;
        };
        match hard.get(r as usize * self.top.width() as usize + c as usize) {
            Some(b) if z_mm >= f64::from(b.lo) && z_mm <= f64::from(b.hi) => b.factor,
            _ => 1.0,
        }
    }

    /// Makes the material inside a sphere weigh `factor` (a hard inclusion; see the module docs
    /// for the per-cell band this is stored as).
    ///
    /// Errors: non-finite centre, radius not finite and positive, factor not finite and positive.
    pub fn set_hardness_sphere(
        &mut self,
        center: Point3<f64>,
        radius_mm: f64,
        factor: f32,
    ) -> Result<(), RemovalError> {
        check_point(|| "center".into(), &center)?;
        if !(radius_mm.is_finite() && radius_mm > 0.0 && radius_mm <= MAX_COORD_MM) {
            return Err(invalid("radius_mm", radius_mm, "a finite positive radius"));
        }
        if !(factor.is_finite() && factor > 0.0) {
            return Err(invalid("factor", f64::from(factor), "a finite positive factor"));
        }
        let meta = *self.top.meta();
        let w = meta.width as usize;
        let hard = self.hard.get_or_insert_with(|| vec![NOMINAL; self.top.data().len()]);
        let (p, x0, y0) = (meta.pixel_mm, meta.origin_x_mm, meta.origin_y_mm);
        let rows = index_range(center.y - radius_mm, center.y + radius_mm, y0, p, 0, meta.height as usize);
        let cols = index_range(center.x - radius_mm, center.x + radius_mm, x0, p, 0, w);
        let (Some((r0, r1)), Some((c0, c1))) = (rows, cols) else { return Ok(()) };
        for row in r0..=r1 {
            let dy = y0 + (row as f64 + 0.5) * p - center.y;
            for col in c0..=c1 {
                let dx = x0 + (col as f64 + 0.5) * p - center.x;
                let d2 = dx * dx + dy * dy;
                if d2 > radius_mm * radius_mm {
                    continue;
                }
                let half = (radius_mm * radius_mm - d2).sqrt();
                let (lo, hi) = ((center.z - half) as f32, (center.z + half) as f32);
                if let Some(b) = hard.get_mut(row * w + col) {
                    *b = if b.factor == 1.0 {
                        HardBand { factor, lo, hi }
                    } else {
                        HardBand { factor, lo: b.lo.min(lo), hi: b.hi.max(hi) }
                    };
                }
            }
        }
        Ok(())
    }

    /// Sweeps `tool` with its tip moving in a straight line `from` → `to` and removes everything
    /// the tool occupies. Returns what was removed.
    ///
    /// Errors: a non-finite point ([`RemovalError::InvalidPoint`]).
    pub fn cut_line(
        &mut self,
        tool: &ToolProfile,
        from: Point3<f64>,
        to: Point3<f64>,
    ) -> Result<Cut, RemovalError> {
        self.line(tool, from, to, false, true)
    }

    /// [`Stock::cut_line`] for a move that continues the same tool's previous cut on this stock
    /// from where that cut ended (the next revolution of a feed move, the next move of a
    /// path): `from` must be a point the previous cut's tool passed through, with nothing else
    /// cut since. The cells behind `from` that the tool's position there already bounds are not
    /// visited (on a level or rising move every cell behind it; see the module docs), so
    /// a revolution of a feed move visits about half its footprint. Same result as `cut_line`
    /// up to f32 rounding of the envelope (a cell the two positions bound equally).
    ///
    /// Errors: a non-finite point ([`RemovalError::InvalidPoint`]).
    pub fn cut_line_after(
        &mut self,
        tool: &ToolProfile,
        from: Point3<f64>,
        to: Point3<f64>,
    ) -> Result<Cut, RemovalError> {
        self.line(tool, from, to, true, true)
    }

    /// [`Stock::cut_line`] without the per-row column clipping and the per-cell early-out: every
    /// cell of the move's bounding box gets the exact envelope. Same result; the benchmark's
    /// reference for the speed-ups.
    pub fn cut_line_baseline(
        &mut self,
        tool: &ToolProfile,
        from: Point3<f64>,
        to: Point3<f64>,
    ) -> Result<Cut, RemovalError> {
        self.line(tool, from, to, false, false)
    }

    /// One straight move as one cut: `after`, it continues the last cut; `fast`, with the
    /// clipping and early-outs.
    fn line(
        &mut self,
        tool: &ToolProfile,
        from: Point3<f64>,
        to: Point3<f64>,
        after: bool,
        fast: bool,
    ) -> Result<Cut, RemovalError> {
        check_point(|| "from".into(), &from)?;
        check_point(|| "to".into(), &to)?;
        let job = LineJob { after, ..LineJob::new(from, to) };
        Ok(self.run(tool, &[Job::Line(job), Job::Probe(job.frame)], fast))
    }

    /// Arc in the XY plane around `center` (x, y) from `from` to `to`, `ccw` (G3) or clockwise
    /// (G2), plus `turns` extra full turns; Z is linear in the angle (a helix when it changes).
    /// As LinuxCNC's `ARC_FEED`: an end angle equal to the start angle is a full circle, and
    /// `turns` is the G2/G3 `P` word minus one (`P1`, the default, is `turns = 0`). The radius
    /// is the start point's; an end radius that differs makes a spiral. Level arcs are exact,
    /// helices and spirals are chorded (see the module docs).
    ///
    /// Errors: non-finite points or centre; more than [`MAX_PIECES`] chords.
    #[allow(clippy::too_many_arguments)]
    pub fn cut_arc_xy(
        &mut self,
        tool: &ToolProfile,
        from: Point3<f64>,
        to: Point3<f64>,
        center: (f64, f64),
        ccw: bool,
        turns: u32,
    ) -> Result<Cut, RemovalError> {
        let arc = ArcPath::new(from, to, center, ccw, turns)?;
        let jobs = arc.jobs(self.cell_mm())?;
        Ok(self.run(tool, &jobs, true))
    }

    /// Cuts the program of straight moves `path[0] → path[1] → …` and returns one [`Cut`] per
    /// move, in order. Runs in parallel strips of rows (see the module docs); the stock ends
    /// exactly as after calling [`Stock::cut_line`] on each move in turn, and each move's figures
    /// equal the sequential ones up to the order of floating-point sums.
    ///
    /// Errors: a non-finite point (named `path[i]`).
    pub fn cut_path(&mut self, tool: &ToolProfile, path: &[Point3<f64>]) -> Result<Vec<Cut>, RemovalError> {
        for (i, p) in path.iter().enumerate() {
            check_point(|| format!("path[{i}]"), p)?;
        }
        let moves = path.len().saturating_sub(1);
        let mut cuts = Vec::with_capacity(moves);
        self.prepare(tool);
        let grid = self.grid();
        let Some((_, shape)) = &self.cache else { return Ok(cuts) };
        let ctx = Ctx { grid: &grid, hard: self.hard.as_deref(), r: shape.r, r2: shape.r2 };
        let tops = self.top.data_mut();
        let bands = grid.h.div_ceil(BAND_ROWS);
        let mut buckets: Vec<Vec<u32>> = vec![Vec::new(); bands];
        let mut tallies = Vec::new();
        for start in (0..moves).step_by(PATH_CHUNK) {
            let end = (start + PATH_CHUNK).min(moves);
            let jobs: Vec<Job> =
                (start..end).map(|i| Job::Line(LineJob::new(path[i], path[i + 1]))).collect();
            buckets.iter_mut().for_each(Vec::clear);
            for (k, job) in jobs.iter().enumerate() {
                // (One cell more than the footprint: the rim probe looks just outside it.)
                let (ylo, yhi) = job.y_range(shape.r + grid.p);
                if let Some((r0, r1)) = index_range(ylo, yhi, grid.y0, grid.p, 0, grid.h) {
                    for bucket in &mut buckets[r0 / BAND_ROWS..=r1 / BAND_ROWS] {
                        bucket.push(k as u32);
                    }
                }
            }
            let partial: Vec<Vec<(u32, Tally)>> = tops
                .par_chunks_mut(BAND_ROWS * grid.w)
                .zip(buckets.par_iter())
                .enumerate()
                .map(|(b, (chunk, bucket))| {
                    let mut band = Band { rows: chunk.len() / grid.w, tops: chunk, row0: b * BAND_ROWS };
                    bucket
                        .iter()
                        .filter_map(|&k| {
                            let mut t = Tally::new();
                            let job = jobs.get(k as usize)?;
                            run_job::<true>(job, shape, &ctx, &mut band, &mut t);
                            if let (Job::Line(line), true) = (job, shape.flat_part) {
                                probe_rim(&line.frame, shape, &ctx, &mut band, &mut t);
                            }
                            Some((k, t))
                        })
                        .collect()
                })
                .collect();
            tallies.clear();
            tallies.resize(jobs.len(), Tally::new());
            for (k, t) in partial.iter().flatten() {
                if let Some(total) = tallies.get_mut(*k as usize) {
                    total.merge(t);
                }
            }
            cuts.extend(tallies.iter().map(|t| t.to_cut(grid.p)));
        }
        Ok(cuts)
    }

    fn grid(&self) -> Grid {
        let m = self.top.meta();
        Grid {
            w: m.width as usize,
            h: m.height as usize,
            x0: m.origin_x_mm,
            y0: m.origin_y_mm,
            p: m.pixel_mm,
            bottom: self.bottom,
        }
    }

    fn prepare(&mut self, tool: &ToolProfile) {
        if self.cache.as_ref().is_none_or(|(t, _)| t != tool) {
            self.cache = Some((tool.clone(), Shape::new(tool)));
        }
    }

    /// Applies `jobs` in order as one cut.
    fn run(&mut self, tool: &ToolProfile, jobs: &[Job], fast: bool) -> Cut {
        self.prepare(tool);
        let grid = self.grid();
        let Some((_, shape)) = &self.cache else { return Cut::default() };
        let ctx = Ctx { grid: &grid, hard: self.hard.as_deref(), r: shape.r, r2: shape.r2 };
        let tops = self.top.data_mut();
        let cells: u64 = jobs.iter().map(|j| j.box_cells(shape.r, grid.p)).sum();
        let run_band = |band: &mut Band, t: &mut Tally| {
            for job in jobs {
                if fast {
                    run_job::<true>(job, shape, &ctx, band, t);
                } else {
                    run_job::<false>(job, shape, &ctx, band, t);
                }
            }
        };
        let tally = if cells > PAR_CELLS {
            tops.par_chunks_mut(BAND_ROWS * grid.w)
                .enumerate()
                .map(|(b, chunk)| {
                    let mut t = Tally::new();
                    let mut band = Band { rows: chunk.len() / grid.w, tops: chunk, row0: b * BAND_ROWS };
                    run_band(&mut band, &mut t);
                    t
                })
                .reduce(Tally::new, |mut a, b| {
                    a.merge(&b);
                    a
                })
        } else {
            let mut t = Tally::new();
            let mut band = Band { tops, row0: 0, rows: grid.h };
            run_band(&mut band, &mut t);
            t
        };
        tally.to_cut(grid.p)
    }
}

/// Splits a linear move into pieces of `feed_per_rev_mm` (3D path length, one spindle revolution
/// each; the last piece takes the remainder) and cuts them one by one, calling `per_rev(&Cut)`
/// after each. Returns the whole move's cut ([`Cut::accumulate`] of the pieces).
///
/// Errors: bad points, `feed_per_rev_mm` not finite and positive, more than [`MAX_PIECES`] pieces.
pub fn cut_line_per_rev(
    stock: &mut Stock,
    tool: &ToolProfile,
    from: Point3<f64>,
    to: Point3<f64>,
    feed_per_rev_mm: f64,
    mut per_rev: impl FnMut(&Cut),
) -> Result<Cut, RemovalError> {
    check_point(|| "from".into(), &from)?;
    check_point(|| "to".into(), &to)?;
    let n = revolutions(feed_per_rev_mm, (to - from).norm())?;
    let len = (to - from).norm();
    let mut total = Cut::default();
    let mut prev = from;
    for i in 1..=n {
        let next = if i == n { to } else { from + (to - from) * (i as f64 * feed_per_rev_mm / len) };
        // Each piece after the first continues the one before it.
        let job = LineJob { after: i > 1, ..LineJob::new(prev, next) };
        let cut = stock.run(tool, &[Job::Line(job), Job::Probe(job.frame)], true);
        per_rev(&cut);
        total.accumulate(&cut);
        prev = next;
    }
    Ok(total)
}

/// [`Stock::cut_arc_xy`] split into pieces of `feed_per_rev_mm` of 3D path length, calling
/// `per_rev(&Cut)` after each piece. Returns the whole move's cut.
///
/// Errors: as [`Stock::cut_arc_xy`], plus a bad `feed_per_rev_mm` or too many pieces.
#[allow(clippy::too_many_arguments)]
pub fn cut_arc_xy_per_rev(
    stock: &mut Stock,
    tool: &ToolProfile,
    from: Point3<f64>,
    to: Point3<f64>,
    center: (f64, f64),
    ccw: bool,
    turns: u32,
    feed_per_rev_mm: f64,
    mut per_rev: impl FnMut(&Cut),
) -> Result<Cut, RemovalError> {
    let arc = ArcPath::new(from, to, center, ccw, turns)?;
    let n = revolutions(feed_per_rev_mm, arc.length())?;
    let len = arc.length();
    let mut total = Cut::default();
    let mut t0 = 0.0;
    for i in 1..=n {
        let t1 = if i == n { 1.0 } else { i as f64 * feed_per_rev_mm / len };
        let jobs = arc.sub(t0, t1).jobs(stock.cell_mm())?;
        let cut = stock.run(tool, &jobs, true);
        per_rev(&cut);
        total.accumulate(&cut);
        t0 = t1;
    }
    Ok(total)
}

/// Number of pieces of `feed` in a path of `len`.
fn revolutions(feed: f64, len: f64) -> Result<u64, RemovalError> {
    if !(feed.is_finite() && feed > 0.0) {
        return Err(invalid("feed_per_rev_mm", feed, "a finite positive feed"));
    }
    let n = (len / feed - 1e-9).ceil().max(1.0);
    if n > MAX_PIECES as f64 {
        return Err(RemovalError::TooManyPieces {
            field: "feed_per_rev_mm",
            value: feed,
            pieces: n,
            limit: MAX_PIECES,
        });
    }
    Ok(n as u64)
}

// ---------------------------------------------------------------------------------------------
// Tool shape

/// One piece of the profile `h(r)`, `r ∈ [r0, r1]`.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Piece {
    /// `h = h0 + k·(r − r0)`.
    Line { r0: f64, r1: f64, h0: f64, k: f64 },
    /// Lower quarter of a circle centred at `(rc, hc)` of radius `rho`: `h = hc − √(ρ² − (r − rc)²)`.
    Torus { r0: f64, r1: f64, rc: f64, hc: f64, rho: f64 },
}

impl Piece {
    fn range(&self) -> (f64, f64) {
        match *self {
            Piece::Line { r0, r1, .. } | Piece::Torus { r0, r1, .. } => (r0, r1),
        }
    }

    #[inline]
    fn h(&self, r: f64) -> f64 {
        match *self {
            Piece::Line { r0, r1, h0, k } => h0 + k * (r.clamp(r0, r1) - r0),
            Piece::Torus { r0, r1, rc, hc, rho } => {
                let u = r.clamp(r0, r1) - rc;
                hc - (rho * rho - u * u).max(0.0).sqrt()
            }
        }
    }

    /// Minimum over `σ ∈ [lo, hi]` with `√(σ² + e²)` in the piece of `m·σ + h(√(σ² + e²))`.
    #[inline]
    fn min_along(&self, e: f64, lo: f64, hi: f64, m: f64) -> f64 {
        let (r0, r1) = self.range();
        if e > r1 {
            return f64::INFINITY;
        }
        let b = (r1 * r1 - e * e).max(0.0).sqrt();
        if e >= r0 {
            self.min_interval(e, (-b).max(lo), b.min(hi), m)
        } else {
            let a = (r0 * r0 - e * e).max(0.0).sqrt();
            self.min_interval(e, (-b).max(lo), (-a).min(hi), m).min(self.min_interval(
                e,
                a.max(lo),
                b.min(hi),
                m,
            ))
        }
    }

    /// The same on one interval where the piece applies (the function is convex there).
    #[inline]
    fn min_interval(&self, e: f64, lo: f64, hi: f64, m: f64) -> f64 {
        if lo.partial_cmp(&hi).is_none_or(|o| o.is_gt()) {
            return f64::INFINITY;
        }
        let g = |sigma: f64| m * sigma + self.h((sigma * sigma + e * e).sqrt());
        match *self {
            Piece::Line { k, .. } => {
                let stat = if k > m.abs() {
                    -m * e / (k * k - m * m).sqrt()
                } else if m < 0.0 {
                    hi
                } else if m > 0.0 {
                    lo
                } else {
                    0.0
                };
                g(stat.clamp(lo, hi))
            }
            Piece::Torus { rc, rho, .. } => {
                // f'(σ) = m + h'(r)·σ/r, h'(r) = u/√(ρ² − u²), u = r − rc; f is convex here.
                let slope = |sigma: f64| {
                    let r = (sigma * sigma + e * e).sqrt();
                    let u = r - rc;
                    let den = (rho * rho - u * u).max(0.0).sqrt();
                    if r <= 0.0 {
                        m
                    } else if den <= 0.0 {
                        if sigma > 0.0 {
                            f64::INFINITY
                        } else if sigma < 0.0 {
                            f64::NEG_INFINITY
                        } else {
                            m
                        }
                    } else {
                        m + u / den * sigma / r
                    }
                };
                if slope(lo) >= 0.0 {
                    return g(lo);
                }
                if slope(hi) <= 0.0 {
                    return g(hi);
                }
                let (mut a, mut b) = (lo, hi);
                for _ in 0..200 {
                    if b - a <= TORUS_TOL_MM {
                        break;
                    }
                    let mid = 0.5 * (a + b);
                    if slope(mid) > 0.0 {
                        b = mid;
                    } else {
                        a = mid;
                    }
                }
                g(a).min(g(b))
            }
        }
    }
}

#[derive(Debug, Clone, PartialEq)]
enum Kind {
    /// Spherical end of radius `r` (closed forms).
    Ball,
    /// Pieces of the profile, by increasing radius.
    Pieces(Vec<Piece>),
}

/// A tool prepared for sweeping.
#[derive(Debug, Clone, PartialEq)]
struct Shape {
    r: f64,
    r2: f64,
    kind: Kind,
    /// `lb[i] = h(√(i·R²/N))`: a lower bound of `h` for `d² >= i·R²/N`.
    lb: Vec<f64>,
    lb_scale: f64,
    /// The profile has a horizontal part: probe the rim for engagement (see [`probe_rim`]).
    flat_part: bool,
}

impl Shape {
    fn new(tool: &ToolProfile) -> Shape {
        let r = tool.radius_mm();
        let kind = match tool.spec() {
            Some(ToolSpec::Ball { .. }) => Kind::Ball,
            Some(ToolSpec::Bull { corner_radius_mm: c, .. }) if c >= r => Kind::Ball,
            Some(ToolSpec::Bull { corner_radius_mm: c, .. }) if c > 0.0 => Kind::Pieces(vec![
                Piece::Line { r0: 0.0, r1: r - c, h0: 0.0, k: 0.0 },
                Piece::Torus { r0: r - c, r1: r, rc: r - c, hc: c, rho: c },
            ]),
            _ => {
                let (rs, hs) = (tool.radii_mm(), tool.heights_mm());
                let pieces = rs
                    .windows(2)
                    .zip(hs.windows(2))
                    .filter(|(rw, _)| rw[1] > rw[0])
                    .map(|(rw, hw)| Piece::Line {
                        r0: rw[0],
                        r1: rw[1],
                        h0: hw[0],
                        k: (hw[1] - hw[0]) / (rw[1] - rw[0]),
                    })
                    .collect();
                Kind::Pieces(pieces)
            }
        };
        let flat_part = match &kind {
            Kind::Ball => false,
            Kind::Pieces(ps) => ps.iter().any(|p| matches!(p, Piece::Line { k, .. } if *k == 0.0)),
        };
        let mut shape = Shape { r, r2: r * r, kind, lb: Vec::new(), lb_scale: 0.0, flat_part };
        if let Kind::Pieces(_) = shape.kind {
            let lb: Vec<f64> =
                (0..=LB_TABLE).map(|i| shape.h(shape.r2 * i as f64 / LB_TABLE as f64)).collect();
            shape.lb = lb;
            shape.lb_scale = LB_TABLE as f64 / shape.r2;
        }
        shape
    }

    /// Exact `h` at squared distance `d2 <= R²`.
    #[inline]
    fn h(&self, d2: f64) -> f64 {
        match &self.kind {
            Kind::Ball => self.r - (self.r2 - d2).max(0.0).sqrt(),
            Kind::Pieces(ps) => {
                let r = d2.sqrt();
                for p in ps {
                    if r <= p.range().1 {
                        return p.h(r);
                    }
                }
                ps.last().map_or(0.0, |p| p.h(r))
            }
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Moves

/// Where and how engagement is measured (see the module docs).
#[derive(Debug, Clone, Copy, PartialEq)]
enum Frame {
    /// End point and unit horizontal travel direction there.
    Dir { ex: f64, ey: f64, ez: f64, dx: f64, dy: f64 },
    /// End point of a move without horizontal travel.
    Axis { ex: f64, ey: f64, ez: f64 },
}

/// A straight move, in its horizontal frame.
#[derive(Debug, Clone, Copy, PartialEq)]
struct LineJob {
    ax: f64,
    ay: f64,
    az: f64,
    bx: f64,
    by: f64,
    ux: f64,
    uy: f64,
    len: f64,
    /// Slope `Δz / L` and `m/√(1+m²)`.
    m: f64,
    mk: f64,
    zlo: f64,
    /// Level or vertical: `E = zlo + h(d)`.
    level: bool,
    frame: Frame,
    /// The same tool's previous cut on this stock ended at this move's start (the next
    /// revolution of one feed move): cells the tool's position at the start already bounds are
    /// not visited (see [`Stock::cut_line_after`]).
    after: bool,
}

impl LineJob {
    fn new(a: Point3<f64>, b: Point3<f64>) -> LineJob {
        let len = (b.x - a.x).hypot(b.y - a.y);
        let zlo = a.z.min(b.z);
        if len < VERTICAL_EPS_MM {
            return LineJob {
                ax: a.x,
                ay: a.y,
                az: zlo,
                bx: a.x,
                by: a.y,
                ux: 1.0,
                uy: 0.0,
                len: 0.0,
                m: 0.0,
                mk: 0.0,
                zlo,
                level: true,
                frame: Frame::Axis { ex: b.x, ey: b.y, ez: b.z },
                after: false,
            };
        }
        let (ux, uy) = ((b.x - a.x) / len, (b.y - a.y) / len);
        let m = (b.z - a.z) / len;
        let k = (1.0 + m * m).sqrt();
        LineJob {
            ax: a.x,
            ay: a.y,
            az: a.z,
            bx: b.x,
            by: b.y,
            ux,
            uy,
            len,
            m,
            mk: m / k,
            zlo,
            level: b.z == a.z,
            frame: Frame::Dir { ex: b.x, ey: b.y, ez: b.z, dx: ux, dy: uy },
            after: false,
        }
    }

    /// Along coordinate (from the start, in the move's direction) below which no cell can be
    /// lowered, when the same tool's previous cut ended at the start; `-∞` otherwise.
    ///
    /// With `P` the start, a cell behind it (`s <= 0`) is farther from every later tool position
    /// than from `P` (`|q − p(σ)|` grows with `σ` once `s <= 0`), and on a level or rising move
    /// the tip does not go down either: since `h` is non-decreasing the envelope over the cell is
    /// the tool's value at `P`, which the previous cut already applied. A ball's envelope along a
    /// descending move is convex in `σ` with its minimum at `σ* = −m·w/√(1+m²)` (`w <= R`), so
    /// it is still the value at `P` for `s <= m·R/√(1+m²)`. Other profiles on a descending move
    /// (a flat end's bottom comes down over the cells behind it) skip nothing.
    fn skip_before(&self, ball: bool, r: f64) -> f64 {
        if !self.after || self.len <= 0.0 {
            return f64::NEG_INFINITY;
        }
        let bound = if self.m >= 0.0 {
            0.0
        } else if ball {
            self.mk * r
        } else {
            return f64::NEG_INFINITY;
        };
        // A hair of slack for the rounding of the cells' along coordinates.
        bound - 1e-9 * (1.0 + r)
    }

    /// X range of the capsule (segment ⊕ disc of radius `r`) on the line `y = cy`.
    #[inline]
    fn capsule_x(&self, cy: f64, r: f64, r2: f64) -> Option<(f64, f64)> {
        capsule_x((self.ax, self.ay), (self.bx, self.by), (self.ux, self.uy), self.len, cy, r, r2)
    }
}

/// X range on the line `y = cy` of the capsule of radius `r` (`r2 = r²`) around the segment
/// `a → b` (unit direction `u`, length `len`): the chords of the two end discs and of the band
/// between them (the capsule is convex, so their hull). Shared by the Z-map's sweeps and the
/// dexel stock's rows.
#[inline]
pub(crate) fn capsule_x(
    a: (f64, f64),
    b: (f64, f64),
    u: (f64, f64),
    len: f64,
    cy: f64,
    r: f64,
    r2: f64,
) -> Option<(f64, f64)> {
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for (px, py) in [a, b] {
        let dy = cy - py;
        let h2 = r2 - dy * dy;
        if h2 >= 0.0 {
            let h = h2.sqrt();
            lo = lo.min(px - h);
            hi = hi.max(px + h);
        }
    }
    if len > 0.0 {
        // Band: 0 <= along <= len and |across| <= r, as a range of x − a.x.
        let dy = cy - a.1;
        let (mut blo, mut bhi) = (f64::NEG_INFINITY, f64::INFINITY);
        let along0 = dy * u.1;
        if u.0 != 0.0 {
            let (t0, t1) = (-along0 / u.0, (len - along0) / u.0);
            blo = blo.max(t0.min(t1));
            bhi = bhi.min(t0.max(t1));
        } else if !(0.0..=len).contains(&along0) {
            bhi = f64::NEG_INFINITY;
        }
        let across0 = dy * u.0;
        if u.1 != 0.0 {
            let (c0, c1) = ((across0 - r) / u.1, (across0 + r) / u.1);
            blo = blo.max(c0.min(c1));
            bhi = bhi.min(c0.max(c1));
        } else if across0.abs() > r {
            bhi = f64::NEG_INFINITY;
        }
        if blo <= bhi {
            lo = lo.min(a.0 + blo);
            hi = hi.max(a.0 + bhi);
        }
    }
    (lo <= hi).then_some((lo, hi))
}

/// A level arc swept exactly.
#[derive(Debug, Clone, Copy, PartialEq)]
struct ArcJob {
    cx: f64,
    cy: f64,
    rho: f64,
    z: f64,
    /// End points relative to the centre.
    a: (f64, f64),
    b: (f64, f64),
    /// Unit directions bounding the swept angle counter-clockwise: from `p` to `q`.
    p: (f64, f64),
    q: (f64, f64),
    /// Swept angle, radians (`>= 2π`: a full ring).
    span: f64,
    /// Bounding box of the arc (absolute).
    xlo: f64,
    xhi: f64,
    ylo: f64,
    yhi: f64,
    frame: Frame,
}

impl ArcJob {
    #[inline]
    fn in_span(&self, vx: f64, vy: f64) -> bool {
        let cross = |a: (f64, f64), b: (f64, f64)| a.0 * b.1 - a.1 * b.0;
        let v = (vx, vy);
        if self.span >= TAU {
            true
        } else if self.span <= PI {
            cross(self.p, v) >= 0.0 && cross(v, self.q) >= 0.0
        } else {
            !(cross(self.q, v) > 0.0 && cross(v, self.p) > 0.0)
        }
    }

    /// Squared distance from `(vx, vy)` (relative to the centre) to the arc.
    #[inline]
    fn dist2(&self, vx: f64, vy: f64) -> f64 {
        if self.in_span(vx, vy) {
            let d = (vx * vx + vy * vy).sqrt() - self.rho;
            d * d
        } else {
            let da = (vx - self.a.0).powi(2) + (vy - self.a.1).powi(2);
            let db = (vx - self.b.0).powi(2) + (vy - self.b.1).powi(2);
            da.min(db)
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum Job {
    Line(LineJob),
    Arc(ArcJob),
    /// Looks for material standing beside the tool's rim at the end of the cut (engagement).
    Probe(Frame),
}

impl Job {
    fn y_range(&self, r: f64) -> (f64, f64) {
        match self {
            Job::Line(j) => (j.ay.min(j.by) - r, j.ay.max(j.by) + r),
            Job::Arc(a) => (a.ylo - r, a.yhi + r),
            Job::Probe(Frame::Dir { ey, .. } | Frame::Axis { ey, .. }) => (ey - r, ey + r),
        }
    }

    fn box_cells(&self, r: f64, p: f64) -> u64 {
        let (xlo, xhi) = match self {
            Job::Line(j) => (j.ax.min(j.bx), j.ax.max(j.bx)),
            Job::Arc(a) => (a.xlo, a.xhi),
            Job::Probe(_) => return 0,
        };
        let (ylo, yhi) = self.y_range(r);
        let cols = ((xhi - xlo + 2.0 * r) / p + 1.0).min(1e12);
        let rows = ((yhi - ylo) / p + 1.0).min(1e12);
        (cols * rows) as u64
    }
}

/// An arc or helix (or spiral, when the end radii differ) as a function of `t ∈ [0, 1]`.
#[derive(Debug, Clone, Copy, PartialEq)]
struct ArcPath {
    cx: f64,
    cy: f64,
    a0: f64,
    /// Signed swept angle (positive counter-clockwise).
    sweep: f64,
    r0: f64,
    r1: f64,
    z0: f64,
    z1: f64,
    from: Point3<f64>,
    to: Point3<f64>,
}

impl ArcPath {
    fn new(
        from: Point3<f64>,
        to: Point3<f64>,
        center: (f64, f64),
        ccw: bool,
        turns: u32,
    ) -> Result<ArcPath, RemovalError> {
        check_point(|| "from".into(), &from)?;
        check_point(|| "to".into(), &to)?;
        check_point(|| "center".into(), &Point3::new(center.0, center.1, 0.0))?;
        let (cx, cy) = center;
        let a0 = (from.y - cy).atan2(from.x - cx);
        let a1 = (to.y - cy).atan2(to.x - cx);
        let mut phi = if ccw { (a1 - a0).rem_euclid(TAU) } else { (a0 - a1).rem_euclid(TAU) };
        if phi <= 1e-12 || phi >= TAU - 1e-12 {
            phi = TAU;
        }
        phi += TAU * f64::from(turns);
        Ok(ArcPath {
            cx,
            cy,
            a0,
            sweep: if ccw { phi } else { -phi },
            r0: (from.x - cx).hypot(from.y - cy),
            r1: (to.x - cx).hypot(to.y - cy),
            z0: from.z,
            z1: to.z,
            from,
            to,
        })
    }

    fn at(&self, t: f64) -> Point3<f64> {
        if t <= 0.0 {
            return self.from;
        }
        if t >= 1.0 {
            return self.to;
        }
        let (r, a) = (self.r0 + (self.r1 - self.r0) * t, self.a0 + self.sweep * t);
        Point3::new(self.cx + r * a.cos(), self.cy + r * a.sin(), self.z0 + (self.z1 - self.z0) * t)
    }

    fn length(&self) -> f64 {
        (self.sweep.abs() * 0.5 * (self.r0 + self.r1)).hypot(self.z1 - self.z0)
    }

    fn sub(&self, t0: f64, t1: f64) -> ArcPath {
        let lerp = |a: f64, b: f64, t: f64| a + (b - a) * t;
        ArcPath {
            a0: self.a0 + self.sweep * t0,
            sweep: self.sweep * (t1 - t0),
            r0: lerp(self.r0, self.r1, t0),
            r1: lerp(self.r0, self.r1, t1),
            z0: lerp(self.z0, self.z1, t0),
            z1: lerp(self.z0, self.z1, t1),
            from: self.at(t0),
            to: self.at(t1),
            ..*self
        }
    }

    /// The jobs that sweep this path on a grid of `cell` mm.
    fn jobs(&self, cell: f64) -> Result<Vec<Job>, RemovalError> {
        let sag = cell * ARC_SAGITTA_CELLS;
        let a_end = self.a0 + self.sweep;
        let sign = self.sweep.signum();
        let (tx, ty) = (-a_end.sin() * sign, a_end.cos() * sign);
        let frame = Frame::Dir { ex: self.to.x, ey: self.to.y, ez: self.to.z, dx: tx, dy: ty };
        let rmax = self.r0.max(self.r1);
        if rmax < VERTICAL_EPS_MM {
            let job = LineJob::new(self.from, self.to);
            return Ok(vec![Job::Line(job), Job::Probe(job.frame)]);
        }
        if self.z0 == self.z1 && (self.r1 - self.r0).abs() <= sag {
            let rho = 0.5 * (self.r0 + self.r1);
            let (u0, u1) = ((self.a0.cos(), self.a0.sin()), (a_end.cos(), a_end.sin()));
            let (p, q) = if self.sweep > 0.0 { (u0, u1) } else { (u1, u0) };
            let mut arc = ArcJob {
                cx: self.cx,
                cy: self.cy,
                rho,
                z: self.z0,
                a: (rho * u0.0, rho * u0.1),
                b: (rho * u1.0, rho * u1.1),
                p,
                q,
                span: self.sweep.abs(),
                xlo: 0.0,
                xhi: 0.0,
                ylo: 0.0,
                yhi: 0.0,
                frame,
            };
            let (mut xlo, mut xhi) = (arc.a.0.min(arc.b.0), arc.a.0.max(arc.b.0));
            let (mut ylo, mut yhi) = (arc.a.1.min(arc.b.1), arc.a.1.max(arc.b.1));
            for (dx, dy) in [(1.0, 0.0), (0.0, 1.0), (-1.0, 0.0), (0.0, -1.0)] {
                if arc.in_span(dx, dy) {
                    (xlo, xhi) = (xlo.min(rho * dx), xhi.max(rho * dx));
                    (ylo, yhi) = (ylo.min(rho * dy), yhi.max(rho * dy));
                }
            }
            (arc.xlo, arc.xhi, arc.ylo, arc.yhi) =
                (self.cx + xlo, self.cx + xhi, self.cy + ylo, self.cy + yhi);
            return Ok(vec![Job::Arc(arc), Job::Probe(frame)]);
        }
        // Chords with a sagitta of at most `sag`: ρ·(1 − cos(Δ/2)) <= sag.
        let step = if sag < rmax { 2.0 * (1.0 - sag / rmax).acos() } else { PI / 2.0 };
        let n = (self.sweep.abs() / step).ceil().max(1.0);
        if n > MAX_PIECES as f64 {
            return Err(RemovalError::TooManyPieces {
                field: "turns",
                value: self.sweep.abs() / TAU,
                pieces: n,
                limit: MAX_PIECES,
            });
        }
        let n = n as usize;
        let mut prev = self.from;
        let mut jobs: Vec<Job> = (1..=n)
            .map(|i| {
                let next = self.at(i as f64 / n as f64);
                let mut job = LineJob::new(prev, next);
                job.frame = frame;
                prev = next;
                Job::Line(job)
            })
            .collect();
        jobs.push(Job::Probe(frame));
        Ok(jobs)
    }
}

// ---------------------------------------------------------------------------------------------
// Sweeping

#[derive(Debug, Clone, Copy)]
struct Grid {
    w: usize,
    h: usize,
    x0: f64,
    y0: f64,
    p: f64,
    bottom: f32,
}

/// Rows `row0 .. row0 + rows` of the tops.
struct Band<'a> {
    tops: &'a mut [f32],
    row0: usize,
    rows: usize,
}

struct Ctx<'a> {
    grid: &'a Grid,
    hard: Option<&'a [HardBand]>,
    r: f64,
    r2: f64,
}

/// Per-move accumulator (mergeable across bands).
#[derive(Debug, Clone, Copy)]
struct Tally {
    visited: u64,
    updated: u64,
    removed: f64,
    hard_extra: f64,
    max_depth: f64,
    /// Extremes of the across-travel offset of engaged cells, and their largest squared distance
    /// from the axis.
    e_max: f64,
    e_min: f64,
    rho2_max: f64,
    engaged: u64,
    sectors: u64,
    axial: f64,
}

impl Tally {
    fn new() -> Tally {
        Tally {
            visited: 0,
            updated: 0,
            removed: 0.0,
            hard_extra: 0.0,
            max_depth: 0.0,
            e_max: f64::NEG_INFINITY,
            e_min: f64::INFINITY,
            rho2_max: 0.0,
            engaged: 0,
            sectors: 0,
            axial: 0.0,
        }
    }

    fn merge(&mut self, o: &Tally) {
        self.visited += o.visited;
        self.updated += o.updated;
        self.removed += o.removed;
        self.hard_extra += o.hard_extra;
        self.max_depth = self.max_depth.max(o.max_depth);
        self.e_max = self.e_max.max(o.e_max);
        self.e_min = self.e_min.min(o.e_min);
        self.rho2_max = self.rho2_max.max(o.rho2_max);
        self.engaged += o.engaged;
        self.sectors |= o.sectors;
        self.axial = self.axial.max(o.axial);
    }

    /// The cut on cells of `p` mm.
    fn to_cut(self, p: f64) -> Cut {
        let area = p * p;
        let engagement_deg = if self.updated == 0 {
            0.0
        } else if self.sectors != 0 {
            180.0 * f64::from(self.sectors.count_ones()) / 36.0
        } else if self.engaged > 0 {
            let rho = self.rho2_max.sqrt().max(0.5 * p);
            let angle = |e: f64| (e / rho).clamp(-1.0, 1.0).asin();
            (angle(self.e_max + 0.5 * p) - angle(self.e_min - 0.5 * p)).to_degrees()
        } else {
            0.0
        };
        Cut {
            cells_visited: self.visited,
            cells_updated: self.updated,
            volume_mm3: self.removed * area,
            hard_volume_mm3: (self.removed + self.hard_extra) * area,
            max_depth_mm: self.max_depth,
            engagement_deg,
            axial_depth_mm: if self.updated == 0 { 0.0 } else { self.axial },
        }
    }
}

/// Books a lowered cell.
#[inline]
#[allow(clippy::too_many_arguments)]
fn record(t: &mut Tally, ctx: &Ctx<'_>, frame: &Frame, gi: usize, cx: f64, cy: f64, old: f32, new: f32) {
    let (o, n) = (f64::from(old), f64::from(new));
    let dz = o - n;
    t.updated += 1;
    t.removed += dz;
    t.max_depth = t.max_depth.max(dz);
    if let Some(b) = ctx.hard.and_then(|h| h.get(gi))
        && b.factor != 1.0
    {
        let overlap = (o.min(f64::from(b.hi)) - n.max(f64::from(b.lo))).max(0.0);
        t.hard_extra += (f64::from(b.factor) - 1.0) * overlap;
    }
    let reach2 = ctx.r2 * (1.0 + 1e-9);
    match *frame {
        Frame::Dir { ex, ey, ez, dx, dy } => {
            let (rx, ry) = (cx - ex, cy - ey);
            let s = rx * dx + ry * dy;
            let rr = rx * rx + ry * ry;
            if s >= 0.0 && rr <= reach2 {
                let e = dx * ry - dy * rx;
                t.e_max = t.e_max.max(e);
                t.e_min = t.e_min.min(e);
                t.rho2_max = t.rho2_max.max(rr);
                t.engaged += 1;
                t.axial = t.axial.max(o - ez);
            }
        }
        Frame::Axis { ex, ey, ez } => {
            let (rx, ry) = (cx - ex, cy - ey);
            if rx * rx + ry * ry <= reach2 {
                let sector = ((ry.atan2(rx) + PI) / TAU * 36.0) as u32;
                t.sectors |= 1u64 << sector.min(35);
                t.engaged += 1;
                t.axial = t.axial.max(o - ez);
            }
        }
    }
}

/// The level at or above which an envelope cannot lower a cell whose top is `top`: any `z` at or
/// above it rounds to an f32 `>= top`. Below `top` by less than half the f32 spacing under it
/// (which is at least `|top|·2⁻²⁴`), plus 1e-9 mm (relative above 1 mm) for the rounding of
/// the tests themselves. Cells the tool last touched at the same position (an envelope equal to
/// the top) are thus skipped too.
#[inline(always)]
fn skip_level(top: f32) -> f64 {
    let t = f64::from(top);
    let a = t.abs();
    t - a * (1.0 / 33_554_432.0) + 1e-9 * (1.0 + a)
}

/// Indices `i` in `[min, end)` whose cell centre `origin + (i + ½)·p` lies in `[lo, hi]`
/// (with a hair of slack; callers test the exact condition per cell). Inputs are finite.
#[inline]
fn index_range(lo: f64, hi: f64, origin: f64, p: f64, min: usize, end: usize) -> Option<(usize, usize)> {
    // Without SSE4.1, `f64::floor`/`ceil` are library calls; a truncating cast is not.
    let floor = |x: f64| {
        let i = x as i64;
        i - i64::from((i as f64) > x)
    };
    let ceil = |x: f64| {
        let i = x as i64;
        i + i64::from((i as f64) < x)
    };
    let a = ceil((lo - origin) / p - 0.5 - 1e-9).max(min as i64);
    let b = floor((hi - origin) / p - 0.5 + 1e-9).min(end as i64 - 1);
    (a <= b).then_some((a as usize, b as usize))
}

/// The envelope of one move over a cell, in the move's frame.
trait Env {
    /// [`Env::above`] is implemented: use it instead of the lower bound.
    const EXACT_TEST: bool;
    /// A lower bound of `h` at squared distance `d2` (relative to the move's lowest tip Z).
    fn lb(&self, d2: f64) -> f64;
    /// Whether the envelope is certainly at or above `t` (so a top below `t` stays), decided
    /// exactly and without square roots. Only called when `EXACT_TEST`.
    fn above(&self, _s: f64, _e: f64, _d2: f64, _t: f64) -> bool {
        false
    }
    /// The exact envelope (absolute Z) at along/across coordinates `s`, `e` with `d2` the squared
    /// distance to the horizontal segment (`<= R²`).
    fn z(&self, s: f64, e: f64, d2: f64) -> f64;
}

struct BallLevel {
    z: f64,
    r: f64,
    r2: f64,
    inv2r: f64,
}

impl Env for BallLevel {
    const EXACT_TEST: bool = true;
    #[inline(always)]
    fn lb(&self, d2: f64) -> f64 {
        d2 * self.inv2r
    }
    /// `z + R − √(R² − d²) >= t` ⟺ `b = z + R − t >= 0` and `b² >= R² − d²`.
    #[inline(always)]
    fn above(&self, _s: f64, _e: f64, d2: f64, t: f64) -> bool {
        let b = self.z + self.r - t;
        (b >= 0.0) & (b * b >= self.r2 - d2)
    }
    #[inline(always)]
    fn z(&self, _s: f64, _e: f64, d2: f64) -> f64 {
        self.z + self.r - (self.r2 - d2).max(0.0).sqrt()
    }
}

struct BallSlope {
    az: f64,
    r: f64,
    r2: f64,
    inv2r: f64,
    len: f64,
    m: f64,
    mk: f64,
    /// `1 + m²`.
    k2: f64,
}

impl Env for BallSlope {
    const EXACT_TEST: bool = true;
    #[inline(always)]
    fn lb(&self, d2: f64) -> f64 {
        d2 * self.inv2r
    }
    /// The envelope is the cylinder value `az + m·s + R − w·√(1+m²)` when the stationary point
    /// `σ* = −m·w/√(1+m²)` lies on the move (`0 <= s + σ* <= L`), else the value of the end
    /// sphere it is clamped to; both spheres are never below the envelope. So the envelope is at
    /// least `t` exactly when both spheres are (one out of reach counts as `+∞`) and, if `σ*` is on
    /// the move, the cylinder value is. Each comparison is squared, as in [`BallLevel::above`],
    /// and so is the test of `σ*`'s position.
    #[inline(always)]
    fn above(&self, s: f64, e: f64, _d2: f64, t: f64) -> bool {
        let e2 = e * e;
        let w2 = self.r2 - e2;
        let a = self.az + self.m * s + self.r - t;
        let cyl = (a >= 0.0) & (a * a >= w2 * self.k2);
        let da2 = s * s + e2;
        let b = self.az + self.r - t;
        let start = (da2 > self.r2) | ((b >= 0.0) & (b * b >= self.r2 - da2));
        let u = s - self.len;
        let db2 = u * u + e2;
        let c = self.az + self.m * self.len + self.r - t;
        let end = (db2 > self.r2) | ((c >= 0.0) & (c * c >= self.r2 - db2));
        // σ* on the move ⟺ s − L <= mk·w <= s, with w = √w2 >= 0.
        let q = self.mk * self.mk * w2;
        let on = if self.mk >= 0.0 {
            ((s >= 0.0) & (q <= s * s)) & ((u <= 0.0) | (q >= u * u))
        } else {
            ((s >= 0.0) | (q >= s * s)) & ((u <= 0.0) & (q <= u * u))
        };
        start & end & (cyl | !on)
    }

    /// Branch-free: the clamp of the stationary point; inside the move `√(w² − σ*²) = w/√(1+m²)`.
    #[inline(always)]
    fn z(&self, s: f64, e: f64, _d2: f64) -> f64 {
        let w2 = (self.r2 - e * e).max(0.0);
        let sc = (s - self.mk * w2.sqrt()).max(0.0).min(self.len);
        let ds = sc - s;
        self.az + self.m * sc + self.r - (w2 - ds * ds).max(0.0).sqrt()
    }
}

struct PolyLevel<'a> {
    z: f64,
    sh: &'a Shape,
}

impl Env for PolyLevel<'_> {
    const EXACT_TEST: bool = false;
    #[inline(always)]
    fn lb(&self, d2: f64) -> f64 {
        let i = ((d2 * self.sh.lb_scale) as usize).min(LB_TABLE);
        self.sh.lb.get(i).copied().unwrap_or(0.0)
    }
    #[inline(always)]
    fn z(&self, _s: f64, _e: f64, d2: f64) -> f64 {
        self.z + self.sh.h(d2)
    }
}

struct PolySlope<'a> {
    az: f64,
    len: f64,
    m: f64,
    sh: &'a Shape,
    pieces: &'a [Piece],
}

impl Env for PolySlope<'_> {
    const EXACT_TEST: bool = false;
    #[inline(always)]
    fn lb(&self, d2: f64) -> f64 {
        let i = ((d2 * self.sh.lb_scale) as usize).min(LB_TABLE);
        self.sh.lb.get(i).copied().unwrap_or(0.0)
    }
    #[inline]
    fn z(&self, s: f64, e: f64, _d2: f64) -> f64 {
        let e = e.abs();
        let (lo, hi) = (-s, self.len - s);
        let best = self.pieces.iter().fold(f64::INFINITY, |best, p| best.min(p.min_along(e, lo, hi, self.m)));
        // `min_along` is relative to the tip at σ = 0 (z₀ + m·s).
        self.az + self.m * s + best
    }
}

fn run_job<const FAST: bool>(job: &Job, sh: &Shape, ctx: &Ctx<'_>, band: &mut Band<'_>, t: &mut Tally) {
    let (r, r2, inv2r) = (sh.r, sh.r2, 0.5 / sh.r);
    let skip =
        |j: &LineJob| if FAST { j.skip_before(matches!(sh.kind, Kind::Ball), r) } else { f64::NEG_INFINITY };
    match (job, &sh.kind) {
        (Job::Line(j), Kind::Ball) if j.level => {
            sweep_line::<FAST, _>(j, &BallLevel { z: j.zlo, r, r2, inv2r }, skip(j), ctx, band, t)
        }
        (Job::Line(j), Kind::Ball) => {
            let env = BallSlope { az: j.az, r, r2, inv2r, len: j.len, m: j.m, mk: j.mk, k2: 1.0 + j.m * j.m };
            sweep_line::<FAST, _>(j, &env, skip(j), ctx, band, t)
        }
        (Job::Line(j), Kind::Pieces(_)) if j.level => {
            sweep_line::<FAST, _>(j, &PolyLevel { z: j.zlo, sh }, skip(j), ctx, band, t)
        }
        (Job::Line(j), Kind::Pieces(pieces)) => {
            let env = PolySlope { az: j.az, len: j.len, m: j.m, sh, pieces };
            sweep_line::<FAST, _>(j, &env, skip(j), ctx, band, t)
        }
        (Job::Arc(a), Kind::Ball) => {
            sweep_arc::<FAST, _>(a, &BallLevel { z: a.z, r, r2, inv2r }, ctx, band, t)
        }
        (Job::Arc(a), Kind::Pieces(_)) => sweep_arc::<FAST, _>(a, &PolyLevel { z: a.z, sh }, ctx, band, t),
        (Job::Probe(frame), _) if sh.flat_part => probe_rim(frame, sh, ctx, band, t),
        (Job::Probe(_), _) => {}
    }
}

/// Books, as engaged, the front-half cells just outside the tool's rim at the end of the cut
/// (`R < ρ <= R + cell`) where material stands above the rim's lowest point: the periphery is
/// in contact there. A flat part of a profile advancing by less than a cell removes only a thin
/// crescent, whose outermost cells the grid may miss; the material beside the rim is always
/// resolved. (Only for profiles with a horizontal part: elsewhere any forward motion lowers the
/// whole front half of the contact disc.)
fn probe_rim(frame: &Frame, sh: &Shape, ctx: &Ctx<'_>, band: &mut Band<'_>, t: &mut Tally) {
    let Frame::Dir { ex, ey, ez, dx, dy } = *frame else { return };
    let g = ctx.grid;
    let (r, outer) = (ctx.r, ctx.r + g.p);
    let level = ez + sh.h(sh.r2) + RIM_EPS_MM;
    let Some((row_lo, row_hi)) =
        index_range(ey - outer, ey + outer, g.y0, g.p, band.row0, band.row0 + band.rows)
    else {
        return;
    };
    for row in row_lo..=row_hi {
        let vy = g.y0 + (row as f64 + 0.5) * g.p - ey;
        let o2 = outer * outer - vy * vy;
        if o2 < 0.0 {
            continue;
        }
        let (ho, hi) = (o2.sqrt(), (r * r - vy * vy).max(0.0).sqrt());
        // The front half on this row: rx·dx >= −vy·dy.
        let (mut flo, mut fhi) = (f64::NEG_INFINITY, f64::INFINITY);
        if dx > 0.0 {
            flo = -vy * dy / dx;
        } else if dx < 0.0 {
            fhi = -vy * dy / dx;
        } else if vy * dy < 0.0 {
            continue;
        }
        for (xlo, xhi) in [(-ho, -hi), (hi, ho)] {
            let (xlo, xhi) = (xlo.max(flo), xhi.min(fhi));
            if xlo > xhi {
                continue;
            }
            let Some((c_lo, c_hi)) = index_range(ex + xlo, ex + xhi, g.x0, g.p, 0, g.w) else { continue };
            let base = (row - band.row0) * g.w;
            for c in c_lo..=c_hi {
                let rx = g.x0 + (c as f64 + 0.5) * g.p - ex;
                let rr = rx * rx + vy * vy;
                let top = band.tops.get(base + c).map_or(f64::NEG_INFINITY, |z| f64::from(*z));
                if rr <= ctx.r2 || rr > outer * outer || rx * dx + vy * dy < 0.0 || top <= level {
                    continue;
                }
                let e = dx * vy - dy * rx;
                t.e_max = t.e_max.max(e);
                t.e_min = t.e_min.min(e);
                t.rho2_max = t.rho2_max.max(rr);
                t.engaged += 1;
                t.axial = t.axial.max(top - ez);
            }
        }
    }
}

/// Lowers the cells of `band` under a straight move; cells whose along coordinate is below
/// `skip_before` are known to stay (see [`LineJob::skip_before`]) and are not visited.
#[inline(never)]
fn sweep_line<const FAST: bool, E: Env>(
    j: &LineJob,
    env: &E,
    skip_before: f64,
    ctx: &Ctx<'_>,
    band: &mut Band<'_>,
    t: &mut Tally,
) {
    let g = ctx.grid;
    let (r, r2) = (ctx.r, ctx.r2);
    let Some((row_lo, row_hi)) =
        index_range(j.ay.min(j.by) - r, j.ay.max(j.by) + r, g.y0, g.p, band.row0, band.row0 + band.rows)
    else {
        return;
    };
    let (bxlo, bxhi) = (j.ax.min(j.bx) - r, j.ax.max(j.bx) + r);
    // Along/across coordinates of column c's centre on a row: s0 + c·ds, e0 + c·de (the same
    // formula in every code path, so all of them compute the same envelope bit for bit).
    let (ds, de) = (g.p * j.ux, -g.p * j.uy);
    let dx0 = g.x0 + 0.5 * g.p - j.ax;
    for row in row_lo..=row_hi {
        let cy = g.y0 + (row as f64 + 0.5) * g.p;
        let (xlo, xhi) = if FAST {
            match j.capsule_x(cy, r, r2) {
                Some(x) => x,
                None => continue,
            }
        } else {
            (bxlo, bxhi)
        };
        let Some((mut c_lo, mut c_hi)) = index_range(xlo, xhi, g.x0, g.p, 0, g.w) else { continue };
        let dyr = cy - j.ay;
        let (s0, e0) = (dx0 * j.ux + dyr * j.uy, dyr * j.ux - dx0 * j.uy);
        if skip_before > f64::NEG_INFINITY {
            // s0 + c·ds >= skip_before, kept one column wide of the exact bound.
            let lim = (c_lo as f64 - 1.0, c_hi as f64 + 1.0);
            if ds > 0.0 {
                let c = ((skip_before - s0) / ds).clamp(lim.0, lim.1).floor();
                if c > c_lo as f64 {
                    c_lo = c as usize;
                }
            } else if ds < 0.0 {
                let c = ((skip_before - s0) / ds).clamp(lim.0, lim.1).ceil();
                if c < c_hi as f64 {
                    if c < c_lo as f64 {
                        continue;
                    }
                    c_hi = c as usize;
                }
            } else if s0 < skip_before {
                continue;
            }
            if c_lo > c_hi {
                continue;
            }
        }
        let at = |c: usize| {
            // Columns fit in i32 (at most MAX_CELLS cells); i32 → f64 vectorises, usize does not.
            let cf = f64::from(c as i32);
            let (s, e) = (s0 + cf * ds, e0 + cf * de);
            let out = s - s.max(0.0).min(j.len);
            (s, e, out * out + e * e)
        };
        let base = (row - band.row0) * g.w;
        let Some(line) = band.tops.get_mut(base + c_lo..=base + c_hi) else { continue };
        t.visited += (c_hi - c_lo + 1) as u64;
        let mut lower = |cell: &mut f32, c: usize, s: f64, e: f64, d2: f64| {
            let new = (env.z(s, e, d2) as f32).max(g.bottom);
            if new < *cell {
                let old = *cell;
                *cell = new;
                let cx = g.x0 + (c as f64 + 0.5) * g.p;
                record(t, ctx, &j.frame, row * g.w + c, cx, cy, old, new);
            }
        };
        if FAST && E::EXACT_TEST {
            // Per chunk of the row: the branch-free, square-root-free test of every cell first,
            // then the envelope only where a cell may be lowered.
            let mut need = [false; ROW_CHUNK];
            for (i, cells) in line.chunks_mut(ROW_CHUNK).enumerate() {
                let c0 = c_lo + i * ROW_CHUNK;
                let mut any = false;
                for (k, (flag, top)) in need.iter_mut().zip(cells.iter()).enumerate() {
                    let (s, e, d2) = at(c0 + k);
                    *flag = (d2 <= r2) & !env.above(s, e, d2, skip_level(*top));
                    any |= *flag;
                }
                if any {
                    for (k, (cell, _)) in cells.iter_mut().zip(&need).enumerate().filter(|(_, (_, f))| **f) {
                        let (s, e, d2) = at(c0 + k);
                        lower(cell, c0 + k, s, e, d2);
                    }
                }
            }
            continue;
        }
        for (k, cell) in line.iter_mut().enumerate() {
            let (s, e, d2) = at(c_lo + k);
            if d2 > r2 || (FAST && f64::from(*cell) <= j.zlo + env.lb(d2)) {
                continue;
            }
            lower(cell, c_lo + k, s, e, d2);
        }
    }
}

/// Lowers the cells of `band` under a level arc.
#[inline(never)]
fn sweep_arc<const FAST: bool, E: Env>(
    a: &ArcJob,
    env: &E,
    ctx: &Ctx<'_>,
    band: &mut Band<'_>,
    t: &mut Tally,
) {
    let g = ctx.grid;
    let (r, r2) = (ctx.r, ctx.r2);
    let Some((row_lo, row_hi)) =
        index_range(a.ylo - r, a.yhi + r, g.y0, g.p, band.row0, band.row0 + band.rows)
    else {
        return;
    };
    let outer = a.rho + r;
    for row in row_lo..=row_hi {
        let cy = g.y0 + (row as f64 + 0.5) * g.p;
        let vy = cy - a.cy;
        let (mut xlo, mut xhi) = (a.xlo - r, a.xhi + r);
        if FAST {
            let h2 = outer * outer - vy * vy;
            if h2 < 0.0 {
                continue;
            }
            let h = h2.sqrt();
            (xlo, xhi) = (xlo.max(a.cx - h), xhi.min(a.cx + h));
        }
        let Some((c_lo, c_hi)) = index_range(xlo, xhi, g.x0, g.p, 0, g.w) else { continue };
        let base = (row - band.row0) * g.w;
        let Some(line) = band.tops.get_mut(base + c_lo..=base + c_hi) else { continue };
        t.visited += (c_hi - c_lo + 1) as u64;
        for (k, cell) in line.iter_mut().enumerate() {
            let cx = g.x0 + ((c_lo + k) as f64 + 0.5) * g.p;
            let d2 = a.dist2(cx - a.cx, vy);
            if d2 > r2 {
                continue;
            }
            if FAST
                && if E::EXACT_TEST {
                    env.above(0.0, 0.0, d2, skip_level(*cell))
                } else {
                    f64::from(*cell) <= a.z + env.lb(d2)
                }
            {
                continue;
            }
            let new = (env.z(0.0, 0.0, d2) as f32).max(g.bottom);
            if new < *cell {
                let old = *cell;
                *cell = new;
                record(t, ctx, &a.frame, row * g.w + c_lo + k, cx, cy, old, new);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use rand::rngs::StdRng;
    use rand::{Rng, SeedableRng};

    use super::*;

    fn p(x: f64, y: f64, z: f64) -> Point3<f64> {
        Point3::new(x, y, z)
    }

    fn tools() -> Vec<(&'static str, ToolProfile)> {
        vec![
            ("ball-3", "ball-3".parse().expect("ball")),
            ("flat-2", "flat-2".parse().expect("flat")),
            ("bull-4-1", "bull-4-1".parse().expect("bull")),
            ("v-3-90", "v-3-90".parse().expect("v")),
            ("v-3-60-0.6", "v-3-60-0.6".parse().expect("v tip")),
            // Non-convex: steep, then nearly flat, then steep again, with a shank run.
            (
                "custom",
                ToolProfile::custom(vec![0.0, 0.4, 1.0, 1.5, 1.5], vec![0.0, 0.5, 0.6, 1.4, 5.0])
                    .expect("custom"),
            ),
        ]
    }

    /// `h(r)` straight from the tool's own definition, `None` beyond the radius.
    fn h_ref(tool: &ToolProfile, r: f64) -> Option<f64> {
        tool.height_at(r)
    }

    /// How much `h` can grow over `δ` (its modulus of continuity), scanning `r`.
    fn omega(tool: &ToolProfile, delta: f64) -> f64 {
        let rr = tool.radius_mm();
        let n = 4000;
        (0..=n)
            .map(|i| {
                let r = rr * f64::from(i) / f64::from(n);
                let hi = (r + delta).min(rr);
                h_ref(tool, hi).unwrap_or(0.0) - h_ref(tool, r).unwrap_or(0.0)
            })
            .fold(0.0, f64::max)
    }

    fn small_stock(top: f64) -> Stock {
        Stock::block(p(-3.0, -3.0, top - 10.0), 6.0, 6.0, 10.0, 0.2).expect("stock")
    }

    fn centres(s: &Stock) -> Vec<(f64, f64)> {
        let m = s.height_map().meta();
        (0..m.height).flat_map(|r| (0..m.width).map(move |c| m.cell_center(c, r))).collect()
    }

    /// Dense reference of one move: the lowest tool surface over each cell centre among the
    /// `n + 1` positions `pos(i/n)`, with the index of the best sample; `None` where no sample
    /// reaches. (Plain arrays: generic nalgebra code would run unoptimised in test builds.)
    fn dense(
        tool: &ToolProfile,
        cells: &[(f64, f64)],
        n: usize,
        pos: impl Fn(f64) -> [f64; 3],
    ) -> Vec<Option<(f64, usize)>> {
        let samples: Vec<[f64; 3]> = (0..=n).map(|i| pos(i as f64 / n as f64)).collect();
        let r = tool.radius_mm();
        cells
            .iter()
            .map(|&(x, y)| {
                let mut best: Option<(f64, usize)> = None;
                for (i, s) in samples.iter().enumerate() {
                    let (dx, dy) = (x - s[0], y - s[1]);
                    if dx.abs() > r || dy.abs() > r {
                        continue;
                    }
                    if let Some(h) = h_ref(tool, (dx * dx + dy * dy).sqrt())
                        && best.is_none_or(|(b, _)| s[2] + h < b)
                    {
                        best = Some((s[2] + h, i));
                    }
                }
                best
            })
            .collect()
    }

    /// Refines a dense reference at cell `(x, y)` whose best sample is `k` of `n`: golden-section
    /// search on each side of it (the tool height over a cell is unimodal in `t` near its
    /// minimum, `+∞` off the disc).
    fn refine(tool: &ToolProfile, x: f64, y: f64, n: usize, k: usize, pos: &impl Fn(f64) -> [f64; 3]) -> f64 {
        let f = |t: f64| {
            let q = pos(t);
            h_ref(tool, (x - q[0]).hypot(y - q[1])).map_or(f64::INFINITY, |h| q[2] + h)
        };
        // Where both probes are off the disc (+∞), move towards the bracket's end at the sample.
        let g = 0.5 * (5f64.sqrt() - 1.0);
        let golden = |mut a: f64, mut b: f64, finite_at_b: bool| {
            let mut best = f64::INFINITY;
            for _ in 0..60 {
                let (c, d) = (b - g * (b - a), a + g * (b - a));
                let (fc, fd) = (f(c), f(d));
                best = best.min(fc).min(fd);
                let left = if fc.is_infinite() && fd.is_infinite() { !finite_at_b } else { fc <= fd };
                if left {
                    b = d;
                } else {
                    a = c;
                }
            }
            best
        };
        let tk = k as f64 / n as f64;
        let lo = golden(k.saturating_sub(1) as f64 / n as f64, tk, true);
        let hi = golden(tk, (k + 1).min(n) as f64 / n as f64, false);
        f(tk).min(lo).min(hi)
    }

    fn dist_to_segment(x: f64, y: f64, a: Point3<f64>, b: Point3<f64>) -> f64 {
        let (vx, vy) = (b.x - a.x, b.y - a.y);
        let l2 = vx * vx + vy * vy;
        let t = if l2 > 0.0 { (((x - a.x) * vx + (y - a.y) * vy) / l2).clamp(0.0, 1.0) } else { 0.0 };
        (x - a.x - t * vx).hypot(y - a.y - t * vy)
    }

    /// Compares a cut stock with a dense reference: never above a sampled tool position (no
    /// material left where a real position of the tool was), and at most `tol` below the samples.
    fn check_against_dense(
        what: &str,
        stock: &Stock,
        top0: f64,
        reference: &[Option<f64>],
        tol: f64,
        rim: impl Fn(f64, f64) -> bool,
    ) {
        for ((x, y), (z, want)) in centres(stock).iter().zip(stock.height_map().data().iter().zip(reference))
        {
            let z = f64::from(*z);
            match want {
                Some(w) => {
                    let w = w.min(top0);
                    assert!(z <= w + 2e-6, "{what} at ({x}, {y}): {z} above a tool position at {w}");
                    assert!(w - z <= tol, "{what} at ({x}, {y}): {z} more than {tol} below samples {w}");
                }
                None => assert!(
                    (z - top0).abs() < 1e-9 || rim(*x, *y),
                    "{what} at ({x}, {y}): cut to {z} where no sample reaches"
                ),
            }
        }
    }

    #[test]
    fn lines_match_dense_sampling_for_all_tools() {
        let mut rng = StdRng::seed_from_u64(7);
        let n = 2000;
        for (name, tool) in tools() {
            for case in 0..6 {
                let a =
                    p(rng.random_range(-2.0..2.0), rng.random_range(-2.0..2.0), rng.random_range(-1.5..0.5));
                let mut b =
                    p(rng.random_range(-2.0..2.0), rng.random_range(-2.0..2.0), rng.random_range(-1.5..0.5));
                match case {
                    0 => b.z = a.z,                             // level
                    1 => (b.x, b.y) = (a.x, a.y),               // plunge
                    2 => b.z = a.z + 3.0 * (b - a).xy().norm(), // steep ramp
                    _ => {}
                }
                let mut stock = small_stock(1.0);
                stock.cut_line(&tool, a, b).expect("cut");
                let pos = |t: f64| [a.x + (b.x - a.x) * t, a.y + (b.y - a.y) * t, a.z + (b.z - a.z) * t];
                let cells = centres(&stock);
                let reference = dense(&tool, &cells, n, pos);
                // The minimiser may sit on the rim, where the nearest sample inside the disc can be a
                // whole step away: one step of Z plus h's growth over one step of XY.
                let step = (b - a) / n as f64;
                let dxy = step.xy().norm();
                let tol = step.z.abs() + omega(&tool, dxy) + 1e-5;
                let r = tool.radius_mm();
                let coarse: Vec<Option<f64>> = reference.iter().map(|o| o.map(|(v, _)| v)).collect();
                check_against_dense(&format!("{name} case {case}"), &stock, 1.0, &coarse, tol, |x, y| {
                    dist_to_segment(x, y, a, b) >= r - dxy - 1e-9
                });
                // Sharper: the refined reference is a feasible tool height within float error of
                // the true minimum, so the exact envelope must match it to f32 precision.
                for (((x, y), z), best) in cells.iter().zip(stock.height_map().data()).zip(&reference) {
                    let want = best.map_or(1.0, |(_, k)| refine(&tool, *x, *y, n, k, &pos).min(1.0));
                    let z = f64::from(*z);
                    assert!(
                        (z - want).abs() <= 1e-5,
                        "{name} case {case} at ({x}, {y}): {z} vs refined {want}"
                    );
                }
            }
        }
    }

    #[test]
    fn level_moves_are_exact() {
        let mut rng = StdRng::seed_from_u64(11);
        for (name, tool) in tools() {
            for _ in 0..4 {
                let z = rng.random_range(-1.0..0.5);
                let a = p(rng.random_range(-2.0..2.0), rng.random_range(-2.0..2.0), z);
                let b = p(rng.random_range(-2.0..2.0), rng.random_range(-2.0..2.0), z);
                let mut stock = small_stock(1.0);
                stock.cut_line(&tool, a, b).expect("cut");
                for ((x, y), got) in centres(&stock).iter().zip(stock.height_map().data()) {
                    let want = h_ref(&tool, dist_to_segment(*x, *y, a, b)).map_or(1.0, |h| (z + h).min(1.0));
                    assert!(
                        (f64::from(*got) - want).abs() <= 1e-5,
                        "{name} line at ({x},{y}): {got} vs {want}"
                    );
                }
                // A level arc: distance by angle (atan2), independent of the cross-product test.
                let (cx, cy) = (rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0));
                let rho = rng.random_range(0.3..2.0);
                let (t0, t1) = (rng.random_range(-PI..PI), rng.random_range(-PI..PI));
                let ccw = rng.random_bool(0.5);
                let from = p(cx + rho * t0.cos(), cy + rho * t0.sin(), z);
                let to = p(cx + rho * t1.cos(), cy + rho * t1.sin(), z);
                let mut stock = small_stock(1.0);
                stock.cut_arc_xy(&tool, from, to, (cx, cy), ccw, 0).expect("arc");
                let span = if ccw { (t1 - t0).rem_euclid(TAU) } else { (t0 - t1).rem_euclid(TAU) };
                for ((x, y), got) in centres(&stock).iter().zip(stock.height_map().data()) {
                    let ang = (y - cy).atan2(x - cx);
                    let off = if ccw { (ang - t0).rem_euclid(TAU) } else { (t0 - ang).rem_euclid(TAU) };
                    let d = if off <= span {
                        ((x - cx).hypot(y - cy) - rho).abs()
                    } else {
                        (x - from.x).hypot(y - from.y).min((x - to.x).hypot(y - to.y))
                    };
                    let want = h_ref(&tool, d).map_or(1.0, |h| (z + h).min(1.0));
                    assert!(
                        (f64::from(*got) - want).abs() <= 1e-5,
                        "{name} arc at ({x},{y}): {got} vs {want}"
                    );
                }
            }
        }
    }

    #[test]
    fn helical_arcs_match_dense_sampling() {
        let mut rng = StdRng::seed_from_u64(5);
        for (name, tool) in tools() {
            let (cx, cy) = (rng.random_range(-0.5..0.5), rng.random_range(-0.5..0.5));
            let rho = rng.random_range(0.8..2.0);
            let (t0, t1) = (rng.random_range(-PI..PI), rng.random_range(-PI..PI));
            let ccw = rng.random_bool(0.5);
            let turns = u32::from(rng.random_bool(0.3));
            let from = p(cx + rho * t0.cos(), cy + rho * t0.sin(), 0.3);
            let to = p(cx + rho * t1.cos(), cy + rho * t1.sin(), -0.9);
            let mut stock = small_stock(1.0);
            stock.cut_arc_xy(&tool, from, to, (cx, cy), ccw, turns).expect("arc");
            let arc = ArcPath::new(from, to, (cx, cy), ccw, turns).expect("path");
            // Chord points lie within the sagitta of the helix point of the same parameter (same
            // Z), so the chorded envelope lies between the helix sweeps of the tool grown and
            // shrunk by the sagitta; both bounds by dense sampling of the true helix.
            let n = 4000;
            let sag = stock.cell_mm() * ARC_SAGITTA_CELLS;
            let r = tool.radius_mm();
            let cells = centres(&stock);
            let samples: Vec<Point3<f64>> = (0..=n).map(|i| arc.at(i as f64 / n as f64)).collect();
            let dxy = arc.sweep.abs() * rho / n as f64;
            let tol = 1.2 / n as f64 + omega(&tool, dxy) + 1e-5;
            for ((x, y), z) in cells.iter().zip(stock.height_map().data()) {
                let z = f64::from(*z);
                let (mut lower, mut upper) = (f64::INFINITY, f64::INFINITY);
                for s in &samples {
                    let d = (x - s.x).hypot(y - s.y);
                    if let Some(h) = h_ref(&tool, (d - sag).max(0.0)) {
                        lower = lower.min(s.z + h);
                    }
                    if let Some(h) = h_ref(&tool, d + sag) {
                        upper = upper.min(s.z + h);
                    }
                }
                assert!(z <= upper.min(1.0) + 2e-6, "{name} helix at ({x},{y}): {z} above {upper}");
                if lower.is_finite() {
                    assert!(
                        z >= lower.min(1.0) - tol,
                        "{name} helix at ({x},{y}): {z} below {lower} - {tol}"
                    );
                } else {
                    let d = ((x - cx).hypot(y - cy) - rho).abs();
                    assert!(z == 1.0 || d >= r + sag - dxy, "{name} helix at ({x},{y}): {z}");
                }
            }
        }
    }

    #[test]
    fn volume_is_conserved_over_random_programs() {
        let mut rng = StdRng::seed_from_u64(3);
        for (name, tool) in tools() {
            let mut stock = Stock::block(p(0.0, 0.0, -5.0), 10.0, 8.0, 5.0, 0.1).expect("stock");
            stock.set_hardness_sphere(p(5.0, 4.0, -1.0), 1.5, 2.5).expect("hard");
            let before = stock.volume_mm3();
            let mut removed = 0.0;
            let mut at = p(1.0, 1.0, 1.0);
            for i in 0..25 {
                let to =
                    p(rng.random_range(-1.0..11.0), rng.random_range(-1.0..9.0), rng.random_range(-6.0..0.5));
                let cut = if i % 4 == 3 {
                    let c = (0.5 * (at.x + to.x) + 0.7, 0.5 * (at.y + to.y) - 0.4);
                    stock.cut_arc_xy(&tool, at, to, c, rng.random_bool(0.5), 0).expect("arc")
                } else {
                    stock.cut_line(&tool, at, to).expect("line")
                };
                assert!(cut.hard_volume_mm3 >= cut.volume_mm3 - 1e-9, "{name}");
                removed += cut.volume_mm3;
                at = to;
            }
            let after = stock.volume_mm3();
            assert!(removed > 1.0, "{name}: {removed}");
            assert!(
                ((before - after) - removed).abs() <= 1e-9 * before,
                "{name}: {before} - {after} != {removed}"
            );
            assert!(stock.height_map().data().iter().all(|z| f64::from(*z) >= stock.bottom_z_mm()));
        }
    }

    #[test]
    fn the_same_move_twice_removes_nothing_the_second_time() {
        for (name, tool) in tools() {
            let mut stock = small_stock(0.0);
            let (a, b) = (p(-2.0, -1.0, -0.5), p(1.5, 1.7, -1.1));
            let first = stock.cut_line(&tool, a, b).expect("cut");
            assert!(first.volume_mm3 > 0.0, "{name}");
            let again = stock.cut_line(&tool, a, b).expect("cut");
            assert_eq!((again.cells_updated, again.volume_mm3), (0, 0.0), "{name}");
            let arc = |s: &mut Stock| {
                s.cut_arc_xy(&tool, p(1.0, 0.0, -0.3), p(-1.0, 0.0, -0.8), (0.0, 0.0), true, 0)
            };
            assert!(arc(&mut stock).expect("arc").volume_mm3 > 0.0, "{name}");
            assert_eq!(arc(&mut stock).expect("arc").cells_updated, 0, "{name}");
        }
    }

    #[test]
    fn a_plunge_leaves_the_tool_shape() {
        let tool: ToolProfile = "ball-6".parse().expect("ball");
        let mut stock = Stock::block(p(-5.0, -5.0, -10.0), 10.0, 10.0, 10.0, 0.05).expect("stock");
        let cut = stock.cut_line(&tool, p(0.0, 0.0, 5.0), p(0.0, 0.0, -2.0)).expect("plunge");
        for ((x, y), z) in centres(&stock).iter().zip(stock.height_map().data()) {
            let want = h_ref(&tool, x.hypot(*y)).map_or(0.0, |h| (-2.0 + h).min(0.0));
            assert!((f64::from(*z) - want).abs() <= 1e-5, "({x},{y}): {z} vs {want}");
        }
        let cap = PI * 4.0 * (9.0 - 2.0) / 3.0; // π d² (3R − d) / 3, d = 2
        assert!((cut.volume_mm3 - cap).abs() < 0.01 * cap, "{} vs {cap}", cut.volume_mm3);
        assert!((cut.max_depth_mm - 2.0).abs() < 1e-3 && (cut.axial_depth_mm - 2.0).abs() < 1e-3, "{cut:?}");
        assert!((cut.engagement_deg - 180.0).abs() < 1e-9, "{cut:?}");
    }

    #[test]
    fn per_revolution_pieces_remove_what_one_cut_removes() {
        for (name, tool) in tools() {
            let (a, b) = (p(-2.2, -1.0, 0.2), p(2.0, 1.3, -0.9));
            let mut whole = small_stock(0.0);
            let one = whole.cut_line(&tool, a, b).expect("cut");
            let mut split = small_stock(0.0);
            let mut revs = Vec::new();
            let total = cut_line_per_rev(&mut split, &tool, a, b, 0.13, |c| revs.push(*c)).expect("per rev");
            assert_eq!(revs.len(), ((b - a).norm() / 0.13).ceil() as usize, "{name}");
            let sum: f64 = revs.iter().map(|c| c.volume_mm3).sum();
            assert!((sum - total.volume_mm3).abs() < 1e-9, "{name}");
            assert!(
                (one.volume_mm3 - total.volume_mm3).abs() <= 1e-6 * one.volume_mm3,
                "{name}: {one:?} {total:?}"
            );
            for (u, v) in whole.height_map().data().iter().zip(split.height_map().data()) {
                assert!((u - v).abs() <= 2e-6, "{name}: {u} vs {v}");
            }
            // Arcs, a helix included.
            for (z1, turns) in [(-0.5, 0), (-1.0, 1)] {
                let (from, to) = (p(1.5, 0.0, -0.5), p(0.0, 1.5, z1));
                let mut whole = small_stock(0.0);
                let one = whole.cut_arc_xy(&tool, from, to, (0.0, 0.0), false, turns).expect("arc");
                let mut split = small_stock(0.0);
                let mut count = 0;
                let total =
                    cut_arc_xy_per_rev(&mut split, &tool, from, to, (0.0, 0.0), false, turns, 0.2, |_| {
                        count += 1
                    })
                    .expect("arc per rev");
                assert!(count > 10, "{name}");
                let tol = if z1 == -0.5 { 1e-6 } else { 2e-3 }; // chords of pieces vs chords of the whole
                assert!(
                    (one.volume_mm3 - total.volume_mm3).abs() <= tol * one.volume_mm3,
                    "{name} arc {z1}: {one:?} {total:?}"
                );
            }
        }
    }

    /// A cut that continues the previous one ([`Stock::cut_line_after`]) leaves what a plain
    /// [`Stock::cut_line`] leaves, piece by piece, on random reliefs, tools and moves (level,
    /// rising, descending, steep, at any angle to the grid, on a coarse step grid), and visits
    /// fewer cells.
    #[test]
    fn a_continued_cut_equals_the_plain_cut_and_visits_fewer_cells() {
        let mut rng = StdRng::seed_from_u64(17);
        let (mut visited_plain, mut visited_after) = (0u64, 0u64);
        for (name, tool) in tools() {
            for case in 0..12 {
                // A relief: a few random cuts by a coarse flat end and a ball.
                let mut plain = Stock::block(p(-4.0, -4.0, -10.0), 8.0, 8.0, 10.0, 0.05).expect("stock");
                for t in ["flat-2", "ball-1", "ball-1"] {
                    let t: ToolProfile = t.parse().expect("tool");
                    let a = p(
                        rng.random_range(-4.0..4.0),
                        rng.random_range(-4.0..4.0),
                        rng.random_range(-1.5..0.0),
                    );
                    let b = p(
                        rng.random_range(-4.0..4.0),
                        rng.random_range(-4.0..4.0),
                        rng.random_range(-1.5..0.0),
                    );
                    plain.cut_line(&t, a, b).expect("relief");
                }
                let mut after = plain.clone();
                let a =
                    p(rng.random_range(-3.0..3.0), rng.random_range(-3.0..3.0), rng.random_range(-1.8..0.2));
                let mut b =
                    p(rng.random_range(-3.0..3.0), rng.random_range(-3.0..3.0), rng.random_range(-1.8..0.2));
                match case % 4 {
                    0 => b.z = a.z,                             // level
                    1 => b.z = a.z + 2.0 * (b - a).xy().norm(), // steep rise
                    2 => b.z = a.z - 2.0 * (b - a).xy().norm(), // steep descent
                    _ => {}
                }
                // Pieces of one revolution on a 0.01 mm step grid (their directions wobble).
                let n = rng.random_range(5..40);
                let step = |q: Point3<f64>| {
                    p(
                        (q.x * 100.0).round() / 100.0,
                        (q.y * 100.0).round() / 100.0,
                        (q.z * 100.0).round() / 100.0,
                    )
                };
                let pts: Vec<Point3<f64>> =
                    (0..=n).map(|i| step(a + (b - a) * (i as f64 / n as f64))).collect();
                for (i, w) in pts.windows(2).enumerate() {
                    let u = plain.cut_line(&tool, w[0], w[1]).expect("plain");
                    let v = if i == 0 {
                        after.cut_line(&tool, w[0], w[1])
                    } else {
                        after.cut_line_after(&tool, w[0], w[1])
                    }
                    .expect("after");
                    let what = format!("{name} case {case} piece {i}");
                    assert!(
                        (u.volume_mm3 - v.volume_mm3).abs() <= 1e-6 * (1.0 + u.volume_mm3),
                        "{what}: {u:?} {v:?}"
                    );
                    assert!((u.engagement_deg - v.engagement_deg).abs() <= 1e-9, "{what}: {u:?} {v:?}");
                    assert!((u.axial_depth_mm - v.axial_depth_mm).abs() <= 1e-6, "{what}: {u:?} {v:?}");
                    assert!(v.cells_visited <= u.cells_visited, "{what}: {u:?} {v:?}");
                    visited_plain += u.cells_visited;
                    visited_after += v.cells_visited;
                }
                for (k, (u, v)) in plain.height_map().data().iter().zip(after.height_map().data()).enumerate()
                {
                    assert!((u - v).abs() <= 2e-6, "{name} case {case} cell {k}: {u} vs {v}");
                }
            }
        }
        // The rear half of every continued piece's footprint is skipped (all but the steep
        // descents of non-ball tools).
        assert!(
            (visited_after as f64) < 0.8 * visited_plain as f64,
            "visited {visited_after} of {visited_plain}"
        );
    }

    #[test]
    fn engagement_of_slots_side_cuts_and_air() {
        for name in ["flat-6", "ball-6", "bull-6-1"] {
            let tool: ToolProfile = name.parse().expect("tool");
            let fresh = || Stock::block(p(0.0, 0.0, -10.0), 40.0, 20.0, 10.0, 0.05).expect("stock");
            // Slot through fresh stock, one long move and per revolution.
            let mut s = fresh();
            let slot = s.cut_line(&tool, p(-5.0, 10.0, -1.0), p(20.0, 10.0, -1.0)).expect("slot");
            assert!((slot.engagement_deg - 180.0).abs() < 2.0, "{name} slot {slot:?}");
            assert!((slot.axial_depth_mm - 1.0).abs() < 1e-4, "{name} slot {slot:?}");
            let mut last = Cut::default();
            cut_line_per_rev(&mut s, &tool, p(20.0, 10.0, -1.0), p(22.0, 10.0, -1.0), 0.1, |c| last = *c)
                .expect("per rev");
            assert!((last.engagement_deg - 180.0).abs() < 2.0, "{name} slot per rev {last:?}");
            // Half immersion: the axis runs along the wall left by a first pass.
            // (The first pass is a flat end, so nothing is left on that side at the cut's depth.)
            let mut s = fresh();
            let flat: ToolProfile = "flat-6".parse().expect("flat");
            s.cut_line(&flat, p(-5.0, 7.0, -1.0), p(45.0, 7.0, -1.0)).expect("first pass");
            let half = s.cut_line(&tool, p(-5.0, 10.0, -1.0), p(20.0, 10.0, -1.0)).expect("half");
            assert!((half.engagement_deg - 90.0).abs() < 2.0, "{name} half {half:?}");
            cut_line_per_rev(&mut s, &tool, p(20.0, 10.0, -1.0), p(22.0, 10.0, -1.0), 0.1, |c| last = *c)
                .expect("per rev");
            assert!((last.engagement_deg - 90.0).abs() < 2.0, "{name} half per rev {last:?}");
            // Air.
            let air = s.cut_line(&tool, p(0.0, 10.0, 1.0), p(30.0, 10.0, 1.0)).expect("air");
            assert_eq!((air.engagement_deg, air.volume_mm3, air.cells_updated), (0.0, 0.0, 0), "{name}");
        }
        // Travel at an angle to the grid: the cells' cross-track offsets no longer line up.
        for name in ["flat-6", "ball-6"] {
            let tool: ToolProfile = name.parse().expect("tool");
            let mut s = Stock::block(p(0.0, 0.0, -10.0), 30.0, 30.0, 10.0, 0.05).expect("stock");
            let slot = s.cut_line(&tool, p(2.0, 3.0, -1.0), p(20.0, 17.3, -1.0)).expect("slot");
            let mut last = Cut::default();
            cut_line_per_rev(&mut s, &tool, p(20.0, 17.3, -1.0), p(21.6, 18.5, -1.0), 0.07, |c| last = *c)
                .expect("per rev");
            assert!((slot.engagement_deg - 180.0).abs() < 2.0, "{name} diagonal slot {slot:?}");
            assert!((last.engagement_deg - 180.0).abs() < 2.0, "{name} diagonal per rev {last:?}");
            // Half immersion at that angle: a flat end first clears the side to the right.
            let mut s = Stock::block(p(0.0, 0.0, -10.0), 30.0, 30.0, 10.0, 0.05).expect("stock");
            let flat: ToolProfile = "flat-6".parse().expect("flat");
            let (ux, uy) = (18.0f64, 14.3f64); // the direction of travel
            let n = ux.hypot(uy);
            let (nx, ny) = (uy / n * 3.0, -ux / n * 3.0); // 3 mm to the right
            let (a, b) = (p(2.0 + nx, 3.0 + ny, -1.0), p(2.0 + 1.3 * ux + nx, 3.0 + 1.3 * uy + ny, -1.0));
            s.cut_line(&flat, a, b).expect("clear");
            let half = s.cut_line(&tool, p(2.0, 3.0, -1.0), p(20.0, 17.3, -1.0)).expect("half");
            cut_line_per_rev(&mut s, &tool, p(20.0, 17.3, -1.0), p(21.6, 18.5, -1.0), 0.07, |c| last = *c)
                .expect("per rev");
            assert!((half.engagement_deg - 90.0).abs() < 3.0, "{name} diagonal half {half:?}");
            assert!((last.engagement_deg - 90.0).abs() < 3.0, "{name} diagonal half per rev {last:?}");
        }
        // Grazing a wall removes nothing: no engagement, although the rim touches material.
        let flat: ToolProfile = "flat-6".parse().expect("flat");
        let mut s = Stock::block(p(0.0, 0.0, -10.0), 30.0, 30.0, 10.0, 0.05).expect("stock");
        s.cut_line(&flat, p(-5.0, 5.0, -1.0), p(35.0, 5.0, -1.0)).expect("slot");
        let graze = s.cut_line(&flat, p(5.0, 5.0, -1.0), p(25.0, 5.0, -1.0)).expect("graze");
        assert_eq!((graze.cells_updated, graze.engagement_deg, graze.axial_depth_mm), (0, 0.0, 0.0));
        // A side cut of radial width ae = R/2 with a flat end: acos(1 − ae/R) = 60°.
        let tool: ToolProfile = "flat-6".parse().expect("flat");
        let mut s = Stock::block(p(0.0, 0.0, -10.0), 40.0, 20.0, 10.0, 0.05).expect("stock");
        s.cut_line(&tool, p(-5.0, 8.5, -1.0), p(45.0, 8.5, -1.0)).expect("first pass");
        let side = s.cut_line(&tool, p(-5.0, 10.0, -1.0), p(20.0, 10.0, -1.0)).expect("side");
        assert!((side.engagement_deg - 60.0).abs() < 2.0, "{side:?}");
    }

    #[test]
    fn hardness_weighs_the_inclusion() {
        let tool: ToolProfile = "flat-4".parse().expect("flat");
        let mut s = Stock::block(p(0.0, 0.0, -10.0), 20.0, 20.0, 10.0, 0.05).expect("stock");
        s.set_hardness_sphere(p(10.0, 10.0, -4.0), 2.0, 3.0).expect("hard");
        assert_eq!(s.hardness_at(10.0, 10.0, -4.0), 3.0);
        assert_eq!(s.hardness_at(10.0, 10.0, -1.0), 1.0);
        assert_eq!(s.hardness_at(1.0, 1.0, -4.0), 1.0);
        // Above the inclusion: nominal.
        let above = s.cut_line(&tool, p(5.0, 10.0, -1.5), p(15.0, 10.0, -1.5)).expect("cut");
        assert!(above.volume_mm3 > 0.0 && (above.hard_volume_mm3 - above.volume_mm3).abs() < 1e-9);
        // Face the whole block down below the inclusion: the extra weight is (3 − 1) × its volume.
        let mut total = Cut::default();
        for i in 0..=12 {
            let y = -1.0 + 2.0 * f64::from(i);
            total.accumulate(&s.cut_line(&tool, p(-3.0, y, -7.0), p(23.0, y, -7.0)).expect("face"));
        }
        let sphere = 4.0 / 3.0 * PI * 8.0;
        let extra = total.hard_volume_mm3 - total.volume_mm3;
        assert!((extra - 2.0 * sphere).abs() < 0.01 * 2.0 * sphere, "{extra} vs {}", 2.0 * sphere);
        // A cut through half of it.
        let mut s = Stock::block(p(0.0, 0.0, -10.0), 20.0, 20.0, 10.0, 0.05).expect("stock");
        s.set_hardness_sphere(p(10.0, 10.0, -4.0), 2.0, 3.0).expect("hard");
        let half = s.cut_line(&tool, p(10.0, 10.0, -4.0), p(10.0, 10.0, -4.0)).expect("plunge");
        let inside = s.cut_line(&tool, p(10.0, 10.0, -4.0), p(10.0, 10.0, -8.0)).expect("plunge");
        let extra_half = half.hard_volume_mm3 - half.volume_mm3;
        // Upper half of the sphere is the part removed down to its centre plane: 2/3 π R³.
        assert!((extra_half - 2.0 * sphere / 2.0).abs() < 0.02 * sphere, "{extra_half}");
        assert!((inside.hard_volume_mm3 - inside.volume_mm3 - sphere).abs() < 0.02 * sphere, "{inside:?}");
    }

    #[test]
    fn paths_baseline_and_parallel_sweeps_agree_with_single_moves() {
        let mut rng = StdRng::seed_from_u64(9);
        for (name, tool) in tools() {
            let mut path = vec![p(1.0, 1.0, 0.5)];
            for _ in 0..120 {
                let q = path[path.len() - 1];
                path.push(p(
                    (q.x + rng.random_range(-1.0..1.0)).clamp(-1.0, 21.0),
                    (q.y + rng.random_range(-1.5..1.5)).clamp(-1.0, 41.0),
                    if rng.random_bool(0.3) { q.z } else { rng.random_range(-2.0..0.2) },
                ));
            }
            let fresh = || Stock::block(p(0.0, 0.0, -5.0), 20.0, 40.0, 5.0, 0.1).expect("stock");
            let (mut seq, mut base, mut par) = (fresh(), fresh(), fresh());
            let mut cuts = Vec::new();
            for w in path.windows(2) {
                cuts.push(seq.cut_line(&tool, w[0], w[1]).expect("seq"));
                base.cut_line_baseline(&tool, w[0], w[1]).expect("base");
            }
            let batch = par.cut_path(&tool, &path).expect("path");
            assert!(seq.height_map().data() == base.height_map().data(), "{name}: baseline differs");
            assert!(seq.height_map().data() == par.height_map().data(), "{name}: cut_path differs");
            assert_eq!(batch.len(), cuts.len());
            for (a, b) in cuts.iter().zip(&batch) {
                assert_eq!((a.cells_visited, a.cells_updated), (b.cells_visited, b.cells_updated), "{name}");
                assert!((a.volume_mm3 - b.volume_mm3).abs() <= 1e-9 * (1.0 + a.volume_mm3), "{a:?} {b:?}");
                assert!((a.engagement_deg - b.engagement_deg).abs() < 1e-9, "{name}: {a:?} {b:?}");
                assert_eq!((a.max_depth_mm, a.axial_depth_mm), (b.max_depth_mm, b.axial_depth_mm));
            }
        }
        // A footprint above PAR_CELLS is swept in parallel bands: check it cell by cell.
        let big: ToolProfile = "bull-20-4".parse().expect("bull");
        let mut stock = Stock::block(p(0.0, 0.0, -5.0), 60.0, 60.0, 5.0, 0.05).expect("stock");
        let (a, b) = (p(-5.0, 20.0, -1.5), p(65.0, 40.0, -1.5));
        let before = stock.volume_mm3();
        let cut = stock.cut_line(&big, a, b).expect("big");
        assert!(cut.cells_visited > PAR_CELLS, "{cut:?}");
        for ((x, y), z) in centres(&stock).iter().zip(stock.height_map().data()) {
            let want = h_ref(&big, dist_to_segment(*x, *y, a, b)).map_or(0.0, |h| (-1.5 + h).min(0.0));
            assert!((f64::from(*z) - want).abs() <= 1e-5, "({x}, {y}): {z} vs {want}");
        }
        assert!((before - stock.volume_mm3() - cut.volume_mm3).abs() < 1e-9 * before);
    }

    #[test]
    fn square_root_free_skip_tests_are_exact() {
        // `above(t)` must hold exactly when the envelope is at least `t` (up to rounding).
        let mut rng = StdRng::seed_from_u64(13);
        let (r, mut wrong) = (1.5f64, 0);
        for i in 0..200_000 {
            let len = if i % 4 == 0 { 0.0 } else { rng.random_range(0.0..3.0) };
            let m: f64 = [0.0, rng.random_range(-3.0..3.0), rng.random_range(-0.2..0.2)][i % 3];
            let k = (1.0 + m * m).sqrt();
            let slope = BallSlope { az: 0.3, r, r2: r * r, inv2r: 0.5 / r, len, m, mk: m / k, k2: k * k };
            let level = BallLevel { z: 0.3, r, r2: r * r, inv2r: 0.5 / r };
            let (s, e): (f64, f64) = (rng.random_range(-2.0..5.0), rng.random_range(-1.6..1.6));
            let out = s - s.max(0.0).min(len);
            let d2 = out * out + e * e;
            if d2 > r * r {
                continue;
            }
            let t = rng.random_range(-1.0..2.0);
            let z = slope.z(s, e, d2);
            if (z - t).abs() > 1e-9 && slope.above(s, e, d2, t) != (z >= t) {
                wrong += 1;
            }
            let z = level.z(s, e, d2);
            if (z - t).abs() > 1e-9 && level.above(s, e, d2, t) != (z >= t) {
                wrong += 1;
            }
        }
        assert_eq!(wrong, 0);
        // The skip level: anything at or above it rounds to an f32 at or above the top.
        for top in [0.0f32, 1.0, -1.0, 2.0, 0.75, -3.1, 1e-30, 49.99, -0.015625] {
            let lvl = skip_level(top);
            assert!((lvl as f32) >= top && lvl <= f64::from(top) + 1e-8, "{top}: {lvl}");
        }
    }

    #[test]
    fn bad_parameters_are_named() {
        let o = p(0.0, 0.0, 0.0);
        let msg = |r: Result<Stock, RemovalError>| r.map(|_| ()).expect_err("error").to_string();
        assert_eq!(
            msg(Stock::block(o, 10.0, 10.0, 10.0, 0.0)),
            "invalid cell_mm 0: expected a finite positive length"
        );
        assert_eq!(
            msg(Stock::block(o, 10.0, f64::NAN, 10.0, 0.1)),
            "invalid y_mm NaN: expected a finite positive length"
        );
        assert_eq!(
            msg(Stock::block(o, 1e5, 1e5, 10.0, 0.001)),
            "stock of 100000000 x 100000000 cells exceeds the limit of 268435456 cells"
        );
        assert!(
            msg(Stock::block(p(f64::INFINITY, 0.0, 0.0), 1.0, 1.0, 1.0, 0.1))
                .starts_with("invalid origin (inf, 0, 0)")
        );
        let tool: ToolProfile = "ball-3".parse().expect("ball");
        let mut s = Stock::block(o, 10.0, 10.0, 10.0, 0.1).expect("stock");
        let e = s.cut_line(&tool, o, p(1.0, f64::NAN, 0.0)).expect_err("nan");
        assert!(e.to_string().starts_with("invalid to (1, NaN, 0)"), "{e}");
        let e = s.cut_path(&tool, &[o, o, p(0.0, 2e6, 0.0)]).expect_err("far");
        assert!(e.to_string().starts_with("invalid path[2] (0, 2000000, 0)"), "{e}");
        let e = cut_line_per_rev(&mut s, &tool, o, p(1.0, 0.0, 0.0), -0.1, |_| {}).expect_err("feed");
        assert_eq!(e.to_string(), "invalid feed_per_rev_mm -0.1: expected a finite positive feed");
        let e = cut_line_per_rev(&mut s, &tool, o, p(1000.0, 0.0, 0.0), 1e-6, |_| {}).expect_err("revs");
        assert!(e.to_string().starts_with("feed_per_rev_mm 0.000001 splits the move into"), "{e}");
        let e = s.set_hardness_sphere(o, -1.0, 2.0).expect_err("radius");
        assert_eq!(e.to_string(), "invalid radius_mm -1: expected a finite positive radius");
        let e = s.cut_arc_xy(&tool, o, o, (f64::NAN, 0.0), true, 0).expect_err("centre");
        assert!(e.to_string().starts_with("invalid center (NaN, 0, 0)"), "{e}");
        let e = s.cut_arc_xy(&tool, p(1.0, 0.0, 0.0), p(1.0, 0.0, -1.0), (0.0, 0.0), true, u32::MAX);
        assert!(matches!(e, Err(RemovalError::TooManyPieces { .. })), "{e:?}");
        // Moves entirely off the grid cut nothing.
        let off = s.cut_line(&tool, p(-50.0, -50.0, -1.0), p(-40.0, -60.0, -1.0)).expect("off");
        assert_eq!(off, Cut::default());
    }
}
