//! Finishing on the compensated tip surface C (DESIGN §4): rasters along X, Y or any angle, and
//! constant-Z iso-level loops.
//!
//! # What "never below C" means here
//!
//! C is read as columns: cell `(col, row)` is a closed square of the grid with height `C` (NaN:
//! no data). A toolpath is safe when for every straight move and every cell whose closed square
//! the move touches, the move's Z over the part of the move inside that square is `>= C` of the
//! cell. Both strategies guarantee this exactly (up to f64 rounding of positions):
//!
//! - Raster: a line is cut at every grid line it crosses (breakpoints). Each piece between two
//!   breakpoints lies in one cell (two if it runs along a grid line) and gets a point at its middle
//!   at the max C of those cells; each breakpoint gets the max C of every cell touching it. Every
//!   move then runs from a breakpoint (>= all its cells) to a piece middle (= its cells' max) or
//!   back, inside one piece, so it never dips below a touched cell. Points are at most half a
//!   cell diagonal apart. Pieces in NaN cells are skipped, splitting the pass.
//! - Iso-level: each loop is a marching-squares contour, at the level Z, of the field M sampled at
//!   the grid's *corners*, `M(corner) = max C of the (up to four) cells touching it`. A contour
//!   segment lies in one cell and crosses edges whose one end has `M < Z`, i.e. every cell touching
//!   that corner (among them the cell and the neighbour across the edge) has `C < Z`; a contour
//!   through a corner with `M = Z` touches only cells with `C <= Z`. So the loop, at constant Z,
//!   is `>= C` everywhere it goes, and it hugs the surface to within one cell. Segments in NaN
//!   cells are dropped (the loop splits).
//!
//! # Links
//!
//! The first pass is reached by [`Link::Retract`]. A later pass is [`Link::Direct`] when the
//! straight move from the previous pass's end stays `>= C` over every cell it touches (exact, as
//! above) and, when it is longer than two step-overs (a travel move rather than a step-over),
//! `>= C +` [`LINK_CLEARANCE_MM`] in every cell but the two it starts and ends in; it never crosses
//! a NaN cell. Otherwise [`Link::Retract`].

use depthmill_geometry::HeightMap;
use nalgebra::{Point2, Point3, Vector2};

use super::CamError;
use super::contour::{Polyline, SampleGrid, contour_grid};
use super::path::{Link, Pass, Toolpath};
use super::roughing::order_nearest;
use super::tool::Tool;

/// Clearance a Direct travel link keeps above C (mm).
pub const LINK_CLEARANCE_MM: f64 = 0.02;

/// Largest number of lines or levels one call may produce.
const MAX_STEPS: f64 = 100_000.0;

/// How the finishing passes run.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum FinishingPattern {
    /// Lines parallel to X through cell-row centres.
    RasterX,
    /// Lines parallel to Y through cell-column centres.
    RasterY,
    /// Lines at `angle_deg` from +X (counter-clockwise).
    RasterAngle { angle_deg: f64 },
    /// Constant-Z contours of C.
    IsoLevel,
}

/// Parameters of [`finishing`]; lengths in mm.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FinishingParams {
    pub pattern: FinishingPattern,
    /// Distance between raster lines (> 0); below one pixel the rasters X/Y use one pixel.
    pub step_over_mm: f64,
    /// Distance between iso-levels (> 0; used by `IsoLevel`).
    pub level_step_mm: f64,
    /// Raster lines alternate direction; otherwise every line runs the same way.
    pub zigzag: bool,
    /// Rapid height (>= the highest point of C).
    pub safe_z_mm: f64,
}

/// Ball: s = 2·sqrt(h·(2r − h)) from h = r − sqrt(r² − (s/2)²); other shapes: document what you do (flat: the flat
/// part's width bounds it; bull/V: use the profile).
///
/// For every shape: the scallop two neighbouring passes leave on a flat surface is the profile
/// height at half the step-over, so the step-over is `2·r*` with `r*` the largest radius where the
/// profile's height is `<= scallop_mm` (found by bisection on the monotone profile, exact for the
/// ball's formula above). Ball: the formula (capped at the diameter when `scallop >= r`). Flat:
/// the diameter (a flat bottom leaves no scallop on a flat surface; on slopes the steps depend on
/// the slope and are not bounded by this). Bull-nose: the flat width plus the torus part. V: the
/// tip flat plus `2·scallop·tan(angle/2)`. In mm. Errors: a non-positive or non-finite scallop,
/// or a profile that leaves no positive step-over.
pub fn step_over_for_scallop(tool: &Tool, scallop_mm: f64) -> Result<f64, CamError> {
    if !(scallop_mm.is_finite() && scallop_mm > 0.0) {
        return Err(CamError::param("scallop_mm", format!("must be finite and positive, got {scallop_mm}")));
    }
    let profile = &tool.profile;
    let r = profile.radius_mm();
    let ok = |x: f64| profile.height_at(x).is_some_and(|h| h <= scallop_mm);
    let half = if ok(r) {
        r
    } else {
        let (mut lo, mut hi) = (0.0f64, r);
        for _ in 0..200 {
            let mid = 0.5 * (lo + hi);
            if ok(mid) {
                lo = mid;
            } else {
                hi = mid;
            }
        }
        lo
    };
    if half <= 1e-9 {
        return Err(CamError::InvalidTool {
            name: tool.name.clone(),
            message: format!("the profile leaves no positive step-over for a scallop of {scallop_mm} mm"),
        });
    }
    Ok(2.0 * half)
}

/// Paths on the compensated tip surface `tip` (C). Tip Z at every point >= C there, and between consecutive points
/// the straight segment stays >= C at every cell it crosses (take the max of C over the cells a segment crosses).
///
/// See the module docs for how each pattern guarantees it and how links are chosen. Raster lines
/// are at most `step_over_mm` apart (X/Y: through cell centres, every `floor(step_over/pixel)`-th
/// row/column plus the last; angle: evenly over the map, half a spacing from its corners); points
/// along a line are at most half a cell diagonal apart. Iso-levels run from `max(C) −
/// level_step` down in `level_step` steps while above `min(C)`; loops at one level are ordered
/// nearest-neighbour from where the tool is (closed loops rotated to their nearest vertex, open
/// ones possibly reversed), levels top down. The tool is not used beyond its name (C already
/// holds its shape). Strategy names: `finishing-raster-x`, `-raster-y`, `-raster-angle`,
/// `-iso-level`.
pub fn finishing(tip: &HeightMap, tool: &Tool, p: &FinishingParams) -> Result<Toolpath, CamError> {
    let positive = |field: &str, v: f64| {
        if v.is_finite() && v > 0.0 {
            Ok(())
        } else {
            Err(CamError::param(field, format!("must be finite and positive, got {v}")))
        }
    };
    let (c_min, c_max) = tip
        .z_range_of_data()
        .ok_or_else(|| CamError::InvalidMap { message: "the tip surface has no data".into() })?;
    let (c_min, c_max) = (f64::from(c_min), f64::from(c_max));
    if !p.safe_z_mm.is_finite() || p.safe_z_mm < c_max {
        return Err(CamError::param(
            "safe_z_mm",
            format!("{} is below the tip surface's highest point {c_max}", p.safe_z_mm),
        ));
    }
    let s = Surface::new(tip);
    let mut passes = Vec::new();
    let strategy = match p.pattern {
        FinishingPattern::IsoLevel => {
            positive("level_step_mm", p.level_step_mm)?;
            if (c_max - c_min) / p.level_step_mm > MAX_STEPS {
                return Err(CamError::param(
                    "level_step_mm",
                    format!("{} gives more than {MAX_STEPS} levels", p.level_step_mm),
                ));
            }
            iso_levels(&s, c_min, c_max, p, &mut passes)?;
            "finishing-iso-level"
        }
        pattern => {
            positive("step_over_mm", p.step_over_mm)?;
            let lines = raster_lines(&s, pattern, p.step_over_mm)?;
            let mut forward = true;
            for (a, b) in lines {
                let mut runs = s.raster_runs(a, b);
                if runs.is_empty() {
                    continue;
                }
                if !forward {
                    runs.reverse();
                    for r in &mut runs {
                        r.reverse();
                    }
                }
                for points in runs {
                    push_pass(&s, p, points, &mut passes);
                }
                if p.zigzag {
                    forward = !forward;
                }
            }
            match pattern {
                FinishingPattern::RasterX => "finishing-raster-x",
                FinishingPattern::RasterY => "finishing-raster-y",
                _ => "finishing-raster-angle",
            }
        }
    };
    Ok(Toolpath { strategy: strategy.into(), tool: tool.name.clone(), passes, safe_z_mm: p.safe_z_mm })
}

fn push_pass(s: &Surface<'_>, p: &FinishingParams, points: Vec<Point3<f64>>, passes: &mut Vec<Pass>) {
    let step = match p.pattern {
        FinishingPattern::IsoLevel => p.level_step_mm.max(p.step_over_mm),
        _ => p.step_over_mm,
    };
    let link = match (passes.last().and_then(|q: &Pass| q.points.last()), points.first()) {
        (Some(a), Some(b)) => {
            let travel = (Point2::new(a.x, a.y) - Point2::new(b.x, b.y)).norm() > 2.0 * step.max(s.p);
            if s.link_clear(*a, *b, if travel { LINK_CLEARANCE_MM } else { 0.0 }) {
                Link::Direct
            } else {
                Link::Retract
            }
        }
        _ => Link::Retract,
    };
    passes.push(Pass { link, points });
}

/// A straight line in XY: (start, end) in mm.
type Segment2 = (Point2<f64>, Point2<f64>);

/// Raster lines as (start, end) in mm, clipped to the map.
fn raster_lines(
    s: &Surface<'_>,
    pattern: FinishingPattern,
    step_over: f64,
) -> Result<Vec<Segment2>, CamError> {
    let indices = |n: usize| {
        let stride = ((step_over / s.p + 1e-9).floor() as usize).max(1);
        let mut v: Vec<usize> = (0..n).step_by(stride).collect();
        if v.last() != Some(&(n - 1)) {
            v.push(n - 1);
        }
        v
    };
    let (x1, y1) = (s.x0 + s.w as f64 * s.p, s.y0 + s.h as f64 * s.p);
    Ok(match pattern {
        FinishingPattern::RasterX => indices(s.h)
            .into_iter()
            .map(|r| {
                let y = s.y0 + (r as f64 + 0.5) * s.p;
                (Point2::new(s.x0, y), Point2::new(x1, y))
            })
            .collect(),
        FinishingPattern::RasterY => indices(s.w)
            .into_iter()
            .map(|c| {
                let x = s.x0 + (c as f64 + 0.5) * s.p;
                (Point2::new(x, s.y0), Point2::new(x, y1))
            })
            .collect(),
        FinishingPattern::RasterAngle { angle_deg } => {
            if !angle_deg.is_finite() {
                return Err(CamError::param("angle_deg", format!("must be finite, got {angle_deg}")));
            }
            let a = angle_deg.to_radians();
            let d = Vector2::new(a.cos(), a.sin());
            let n = Vector2::new(-d.y, d.x);
            let centre = Point2::new((s.x0 + x1) / 2.0, (s.y0 + y1) / 2.0);
            let half = Vector2::new((x1 - s.x0) / 2.0, (y1 - s.y0) / 2.0);
            let extent = half.x * n.x.abs() + half.y * n.y.abs();
            let along = half.x * d.x.abs() + half.y * d.y.abs() + s.p;
            let count = (2.0 * extent / step_over).ceil().max(1.0);
            if count > MAX_STEPS {
                return Err(CamError::param(
                    "step_over_mm",
                    format!("{step_over} gives more than {MAX_STEPS} lines"),
                ));
            }
            let spacing = 2.0 * extent / count;
            let sq = super::roughing::Square { x0: s.x0, y0: s.y0, x1, y1 };
            (0..count as usize)
                .filter_map(|k| {
                    let off = -extent + (k as f64 + 0.5) * spacing;
                    let (a, b) = (centre + n * off - d * along, centre + n * off + d * along);
                    super::roughing::clip_segment(a, b, &sq)
                        .filter(|(t0, t1)| (t1 - t0) * 2.0 * along > 1e-9)
                        .map(|(t0, t1)| (a + (b - a) * t0, a + (b - a) * t1))
                })
                .collect()
        }
        FinishingPattern::IsoLevel => Vec::new(),
    })
}

/// C with the grid for column-reading queries.
struct Surface<'a> {
    c: &'a [f32],
    w: usize,
    h: usize,
    p: f64,
    x0: f64,
    y0: f64,
}

/// One piece of a line walk between two consecutive breakpoints (segment parameters).
struct Piece {
    t0: f64,
    t1: f64,
}

impl<'a> Surface<'a> {
    fn new(map: &'a HeightMap) -> Self {
        Surface {
            c: map.data(),
            w: map.width() as usize,
            h: map.height() as usize,
            p: map.pixel_mm(),
            x0: map.origin_x_mm(),
            y0: map.origin_y_mm(),
        }
    }

    /// Calls `f` with C of every map cell whose closed square contains `q` (NaN for no data).
    fn cells_at(&self, q: Point2<f64>, mut f: impl FnMut(f32)) {
        let eps = 1e-9;
        let range = |v: f64, o: f64, n: usize| {
            let u = (v - o) / self.p;
            let k = u.floor();
            let lo = if u - k < eps { k - 1.0 } else { k };
            let hi = if k + 1.0 - u < eps { k + 1.0 } else { k };
            (lo.max(0.0) as i64, hi.min(n as f64 - 1.0) as i64)
        };
        let (c0, c1) = range(q.x, self.x0, self.w);
        let (r0, r1) = range(q.y, self.y0, self.h);
        for r in r0..=r1 {
            for c in c0..=c1 {
                f(self.c[r as usize * self.w + c as usize]);
            }
        }
    }

    /// (max C ignoring NaN, whether any cell is NaN, whether any cell touches) at `q`.
    fn max_at(&self, q: Point2<f64>) -> (f64, bool, bool) {
        let (mut m, mut nan, mut any) = (f64::NEG_INFINITY, false, false);
        self.cells_at(q, |v| {
            any = true;
            if v.is_nan() {
                nan = true;
            } else {
                m = m.max(f64::from(v));
            }
        });
        (m, nan, any)
    }

    /// Breakpoints of the segment `ab` at grid lines, `0` and `1` included, sorted, deduplicated.
    fn breakpoints(&self, a: Point2<f64>, b: Point2<f64>) -> Vec<f64> {
        let mut ts = vec![0.0, 1.0];
        for (pa, pb, o) in [(a.x, b.x, self.x0), (a.y, b.y, self.y0)] {
            if (pb - pa).abs() < 1e-15 {
                continue;
            }
            let (u0, u1) = ((pa.min(pb) - o) / self.p, (pa.max(pb) - o) / self.p);
            let mut k = u0.ceil();
            while k <= u1 {
                let t = (o + k * self.p - pa) / (pb - pa);
                if t > 0.0 && t < 1.0 {
                    ts.push(t);
                }
                k += 1.0;
            }
        }
        ts.sort_by(f64::total_cmp);
        let len = (b - a).norm().max(1e-300);
        ts.dedup_by(|x, y| (*x - *y) * len < 1e-9);
        if let Some(l) = ts.last_mut() {
            *l = 1.0;
        }
        ts
    }

    fn pieces(&self, ts: &[f64]) -> Vec<Piece> {
        ts.windows(2).map(|w| Piece { t0: w[0], t1: w[1] }).collect()
    }

    /// The runs of a raster line from `a` to `b` (see the module docs).
    fn raster_runs(&self, a: Point2<f64>, b: Point2<f64>) -> Vec<Vec<Point3<f64>>> {
        let at = |t: f64| a + (b - a) * t;
        let ts = self.breakpoints(a, b);
        let mut runs = Vec::new();
        let mut run: Vec<Point3<f64>> = Vec::new();
        let flush = |run: &mut Vec<Point3<f64>>, runs: &mut Vec<Vec<Point3<f64>>>| {
            let pts = simplify_flat(std::mem::take(run));
            if !pts.is_empty() {
                runs.push(pts);
            }
        };
        for piece in self.pieces(&ts) {
            let mid = at(0.5 * (piece.t0 + piece.t1));
            let (v, nan, any) = self.max_at(mid);
            if nan || !any {
                flush(&mut run, &mut runs);
                continue;
            }
            let (q0, q1) = (at(piece.t0), at(piece.t1));
            if run.is_empty() {
                let z0 = self.max_at(q0).0.max(v);
                run.push(Point3::new(q0.x, q0.y, z0));
            }
            run.push(Point3::new(mid.x, mid.y, v));
            let z1 = self.max_at(q1).0.max(v);
            run.push(Point3::new(q1.x, q1.y, z1));
        }
        flush(&mut run, &mut runs);
        runs
    }

    /// Exact link check (see the module docs, Links).
    fn link_clear(&self, a: Point3<f64>, b: Point3<f64>, clearance: f64) -> bool {
        let (a2, b2) = (Point2::new(a.x, a.y), Point2::new(b.x, b.y));
        let z = |t: f64| a.z + (b.z - a.z) * t;
        let ts = self.breakpoints(a2, b2);
        let mut end_cells: Vec<(usize, usize)> = Vec::new();
        for q in [a2, b2] {
            self.cell_indices_at(q, |c, r| end_cells.push((c, r)));
        }
        let mut ok = true;
        let mut check = |q: Point2<f64>, zmin: f64| {
            self.cell_indices_at(q, |c, r| {
                let v = self.c[r * self.w + c];
                let clr = if end_cells.contains(&(c, r)) { 0.0 } else { clearance };
                if v.is_nan() || zmin < f64::from(v) + clr {
                    ok = false;
                }
            });
        };
        for &t in &ts {
            check(a2 + (b2 - a2) * t, z(t));
        }
        for piece in self.pieces(&ts) {
            let mid = a2 + (b2 - a2) * (0.5 * (piece.t0 + piece.t1));
            check(mid, z(piece.t0).min(z(piece.t1)));
        }
        ok
    }

    fn cell_indices_at(&self, q: Point2<f64>, mut f: impl FnMut(usize, usize)) {
        let eps = 1e-9;
        let range = |v: f64, o: f64, n: usize| {
            let u = (v - o) / self.p;
            let k = u.floor();
            let lo = if u - k < eps { k - 1.0 } else { k };
            let hi = if k + 1.0 - u < eps { k + 1.0 } else { k };
            (lo.max(0.0) as i64, hi.min(n as f64 - 1.0) as i64)
        };
        let (c0, c1) = range(q.x, self.x0, self.w);
        let (r0, r1) = range(q.y, self.y0, self.h);
        for r in r0..=r1 {
            for c in c0..=c1 {
                f(c as usize, r as usize);
            }
        }
    }
}

/// Drops interior points whose Z equals both neighbours' (the line is straight in XY, so the
/// merged move is the same flat move); also drops points closer than 1e-9 mm to the previous.
fn simplify_flat(points: Vec<Point3<f64>>) -> Vec<Point3<f64>> {
    let mut out: Vec<Point3<f64>> = Vec::with_capacity(points.len());
    for q in points {
        if out.last().is_some_and(|l| (l - q).norm() < 1e-9) {
            continue;
        }
        let n = out.len();
        if n >= 2 && out[n - 1].z == q.z && out[n - 2].z == q.z {
            out[n - 1] = q;
        } else {
            out.push(q);
        }
    }
    out
}

/// M at the grid corners: max C of the touching cells (NaN where all are NaN).
fn corner_max(s: &Surface<'_>) -> Vec<f32> {
    let (w, h) = (s.w + 1, s.h + 1);
    let mut m = vec![f32::NAN; w * h];
    for j in 0..h {
        for i in 0..w {
            let mut best = f32::NAN;
            for (c, r) in [
                (i.wrapping_sub(1), j.wrapping_sub(1)),
                (i, j.wrapping_sub(1)),
                (i.wrapping_sub(1), j),
                (i, j),
            ] {
                if c < s.w && r < s.h {
                    let v = s.c[r * s.w + c];
                    if !v.is_nan() && (best.is_nan() || v > best) {
                        best = v;
                    }
                }
            }
            m[j * w + i] = best;
        }
    }
    m
}

fn iso_levels(
    s: &Surface<'_>,
    c_min: f64,
    c_max: f64,
    p: &FinishingParams,
    passes: &mut Vec<Pass>,
) -> Result<(), CamError> {
    let m = corner_max(s);
    let grid =
        SampleGrid { values: &m, width: s.w + 1, height: s.h + 1, x0_mm: s.x0, y0_mm: s.y0, step_mm: s.p };
    let mut pos: Option<Point2<f64>> = None;
    let mut k = 1.0;
    loop {
        let z = c_max - k * p.level_step_mm;
        if z <= c_min {
            break;
        }
        k += 1.0;
        let mut pieces = Vec::new();
        for line in contour_grid(&grid, z)? {
            split_nan(s, line, &mut pieces);
        }
        for pts in order_nearest(pieces, &mut pos) {
            let points = pts.into_iter().map(|q| Point3::new(q.x, q.y, z)).collect();
            push_pass(s, p, points, passes);
        }
    }
    Ok(())
}

/// Splits `line` where a segment's middle touches a NaN cell.
fn split_nan(s: &Surface<'_>, line: Polyline, out: &mut Vec<Polyline>) {
    line.split_segments(|a, b| !s.max_at(Point2::from((a.coords + b.coords) / 2.0)).1, out);
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::domain::compensate::{CompensateOptions, PixelModel, compensate};
    use depthmill_geometry::{HeightMapMeta, ToolSpec};
    use proptest::prelude::*;

    fn tool(spec: ToolSpec) -> Tool {
        Tool::from_spec(&spec).expect("tool")
    }

    fn params(pattern: FinishingPattern) -> FinishingParams {
        FinishingParams { pattern, step_over_mm: 0.5, level_step_mm: 0.5, zigzag: true, safe_z_mm: 20.0 }
    }

    /// Brute force: for every move (and Direct link), every cell whose closed square the move
    /// touches, the move's Z over its part inside the square is >= C (no move enters a NaN cell
    /// beyond a point).
    fn assert_above(c: &HeightMap, tp: &Toolpath) {
        let p = c.pixel_mm();
        let check = |a: Point3<f64>, b: Point3<f64>, what: &str| {
            for r in 0..c.height() {
                for col in 0..c.width() {
                    let x0 = c.origin_x_mm() + f64::from(col) * p;
                    let y0 = c.origin_y_mm() + f64::from(r) * p;
                    let sq = crate::domain::roughing::Square { x0, y0, x1: x0 + p, y1: y0 + p };
                    let Some((t0, t1)) = crate::domain::roughing::clip_segment(
                        Point2::new(a.x, a.y),
                        Point2::new(b.x, b.y),
                        &sq,
                    ) else {
                        continue;
                    };
                    let v = c.get(col, r).expect("cell");
                    if v.is_nan() {
                        assert!(
                            (t1 - t0) * (b - a).xy().norm() < 1e-7,
                            "{what} {a:?}->{b:?} enters NaN cell"
                        );
                        continue;
                    }
                    let zmin = (a.z + (b.z - a.z) * t0).min(a.z + (b.z - a.z) * t1);
                    assert!(
                        zmin >= f64::from(v) - 1e-6,
                        "{what} {a:?}->{b:?} at {zmin} below C {v} in cell ({col},{r})"
                    );
                }
            }
        };
        let mut prev: Option<Point3<f64>> = None;
        for pass in &tp.passes {
            if let (Link::Direct, Some(a)) = (pass.link, prev) {
                check(a, pass.points[0], "link");
            }
            if pass.points.len() == 1 {
                check(pass.points[0], pass.points[0], "point");
            }
            for w in pass.points.windows(2) {
                check(w[0], w[1], "move");
            }
            prev = pass.points.last().copied();
        }
    }

    fn hemisphere(n: u32, pixel: f64, r: f64) -> HeightMap {
        let mut meta = HeightMapMeta::new(n, n, pixel);
        meta.origin_x_mm = -f64::from(n) * pixel / 2.0;
        meta.origin_y_mm = meta.origin_x_mm;
        meta.z_max_mm = r;
        HeightMap::from_fn(meta, |c, rr| {
            let (x, y) = meta.cell_center(c, rr);
            (r * r - x * x - y * y).max(0.0).sqrt() as f32
        })
        .expect("map")
    }

    fn tip_of(map: &HeightMap, t: &Tool) -> HeightMap {
        let opts = CompensateOptions { pixel_model: PixelModel::Column, outside_z_mm: Some(0.0) };
        compensate(map, &t.profile, &opts).expect("tip")
    }

    #[test]
    fn scallop_step_over_by_shape() {
        let ball = tool(ToolSpec::Ball { diameter_mm: 6.0 });
        let h: f64 = 0.01;
        let s = step_over_for_scallop(&ball, h).expect("ok");
        assert!((s - 2.0 * (h * (6.0 - h)).sqrt()).abs() < 1e-9, "{s}");
        assert!((step_over_for_scallop(&ball, 5.0).expect("ok") - 6.0).abs() < 1e-12);
        let flat = tool(ToolSpec::Flat { diameter_mm: 4.0 });
        assert_eq!(step_over_for_scallop(&flat, 0.01).expect("ok"), 4.0);
        let bull = tool(ToolSpec::Bull { diameter_mm: 6.0, corner_radius_mm: 1.0 });
        let sb = step_over_for_scallop(&bull, h).expect("ok");
        assert!((sb - (4.0 + 2.0 * (h * (2.0 - h)).sqrt())).abs() < 1e-6, "{sb}");
        let v = tool(ToolSpec::V { diameter_mm: 6.0, included_angle_deg: 90.0, tip_flat_diameter_mm: 0.0 });
        assert!((step_over_for_scallop(&v, 0.1).expect("ok") - 0.2).abs() < 1e-9);
        assert!(step_over_for_scallop(&ball, 0.0).expect_err("zero").to_string().contains("scallop_mm"));
    }

    #[test]
    fn hemisphere_rasters_follow_c_exactly() {
        let ball = tool(ToolSpec::Ball { diameter_mm: 3.0 });
        let tip = tip_of(&hemisphere(40, 0.5, 6.0), &ball);
        for pattern in [
            FinishingPattern::RasterX,
            FinishingPattern::RasterY,
            FinishingPattern::RasterAngle { angle_deg: 30.0 },
            FinishingPattern::RasterAngle { angle_deg: 90.0 },
        ] {
            let tp = finishing(&tip, &ball, &params(pattern)).expect("ok");
            assert_above(&tip, &tp);
            assert!(tp.passes.len() >= 20, "{pattern:?} {}", tp.passes.len());
            // Every piece middle sits exactly on C: the path's max is C's max.
            let zmax = tp.passes.iter().flat_map(|p| &p.points).map(|q| q.z).fold(f64::MIN, f64::max);
            let cmax = f64::from(tip.z_range_of_data().expect("data").1);
            assert!(cmax - zmax < 0.3, "{pattern:?} {zmax} {cmax}");
            // Zig-zag over the flat border: step-over links are Direct.
            assert!(tp.passes.iter().filter(|p| p.link == Link::Direct).count() > 10, "{pattern:?}");
        }
    }

    #[test]
    fn step_is_climbed_before_the_high_cell() {
        // Column 5 onward is 2 mm high: along X, the tool reaches 2 mm on the boundary x = 2.5.
        let meta = HeightMapMeta::new(10, 3, 0.5);
        let c = HeightMap::from_fn(meta, |col, _| if col >= 5 { 2.0 } else { 0.0 }).expect("map");
        let t = tool(ToolSpec::Ball { diameter_mm: 1.0 });
        let tp = finishing(&c, &t, &params(FinishingPattern::RasterX)).expect("ok");
        assert_above(&c, &tp);
        let pts = &tp.passes[0].points;
        let at_edge = pts.iter().find(|q| (q.x - 2.5).abs() < 1e-9).expect("boundary point");
        assert_eq!(at_edge.z, 2.0);
        // One-way: every line starts at x = 0 and the links retract or feed over the top.
        let mut one_way = params(FinishingPattern::RasterX);
        one_way.zigzag = false;
        let tp = finishing(&c, &t, &one_way).expect("ok");
        assert!(tp.passes.iter().all(|p| p.points[0].x < 1e-9));
        assert!(tp.passes.iter().all(|p| p.link == Link::Retract));
    }

    #[test]
    fn hemisphere_iso_levels_are_circles_above_c() {
        let ball = tool(ToolSpec::Ball { diameter_mm: 3.0 });
        let tip = tip_of(&hemisphere(40, 0.5, 6.0), &ball);
        let tp = finishing(&tip, &ball, &params(FinishingPattern::IsoLevel)).expect("ok");
        assert_eq!(tp.strategy, "finishing-iso-level");
        assert_above(&tip, &tp);
        assert!(tp.passes.len() >= 10);
        for pass in &tp.passes {
            let z = pass.points[0].z;
            assert!(pass.points.iter().all(|q| q.z == z));
            // Ball centre on the sphere of radius 6 + 1.5: tip at z lies at rho = sqrt(7.5² − (z + 1.5)²).
            let rho = (7.5f64.powi(2) - (z + 1.5).powi(2)).sqrt();
            for q in &pass.points {
                let d = q.x.hypot(q.y);
                assert!(d >= rho - 0.75 && d <= rho + 1.0, "z {z}: {d} vs {rho}");
            }
            assert!(pass.points.len() > 8 && pass.points[0] == *pass.points.last().expect("p"), "closed");
        }
    }

    #[test]
    fn errors_name_the_field() {
        let c = HeightMap::filled(HeightMapMeta::new(4, 4, 1.0), 1.0).expect("map");
        let t = tool(ToolSpec::Ball { diameter_mm: 1.0 });
        let mut p = params(FinishingPattern::RasterX);
        p.safe_z_mm = 0.5;
        assert!(finishing(&c, &t, &p).expect_err("safe").to_string().contains("safe_z_mm"));
        p = params(FinishingPattern::RasterX);
        p.step_over_mm = -1.0;
        assert!(finishing(&c, &t, &p).expect_err("so").to_string().contains("step_over_mm"));
        let empty = HeightMap::filled(HeightMapMeta::new(4, 4, 1.0), f32::NAN).expect("map");
        assert!(finishing(&empty, &t, &params(FinishingPattern::IsoLevel)).is_err());
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(48))]
        /// Random surfaces with holes: no move and no Direct link goes below C in any cell it
        /// touches, for every pattern.
        #[test]
        fn never_below_c(
            cells in proptest::collection::vec(prop_oneof![6 => -1.0f32..3.0, 1 => Just(f32::NAN)], 12 * 10),
            pattern in prop_oneof![
                Just(FinishingPattern::RasterX), Just(FinishingPattern::RasterY), Just(FinishingPattern::IsoLevel),
                (-180.0f64..180.0).prop_map(|angle_deg| FinishingPattern::RasterAngle { angle_deg }),
                Just(FinishingPattern::RasterAngle { angle_deg: 0.0 }), Just(FinishingPattern::RasterAngle { angle_deg: 45.0 }),
            ],
            step_over in 0.1f64..1.5,
            zigzag in any::<bool>(),
        ) {
            let mut meta = HeightMapMeta::new(12, 10, 0.5);
            meta.origin_x_mm = -1.3;
            let c = HeightMap::new(meta, cells).expect("map");
            let t = tool(ToolSpec::Ball { diameter_mm: 1.0 });
            let p = FinishingParams { pattern, step_over_mm: step_over, level_step_mm: step_over, zigzag, safe_z_mm: 5.0 };
            if c.valid_count() > 0 {
                let tp = finishing(&c, &t, &p).expect("ok");
                assert_above(&c, &tp);
            }
        }
    }
}
