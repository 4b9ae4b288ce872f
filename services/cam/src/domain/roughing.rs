//! Roughing: a flat end mill clears the stock in constant-Z levels, leaving `stock_to_leave_mm` on
//! the part (DESIGN §4).
//!
//! # Keep-out map
//!
//! With R the tool radius and `leave` the stock to leave, the keep-out height of a cell centre is
//! `K = D + leave`, where D is the flat-disk dilation of the part A with radius `R + leave` under
//! the conservative column reading ([`PixelModel::Column`]: a part cell counts when the nearest
//! point of its square is within `R + leave` of the tool axis), computed by [`compensate`] with
//! `ToolProfile::flat(2·(R + leave))`. Cells outside the map and cells without data (NaN) count
//! as material up to `floor_mm`. At level Z the tool axis may stand on a cell centre iff `K <= Z`.
//! Then every part column within `R + leave` horizontally lies at least `leave` below the tool's
//! bottom, and every other one is more than `leave` away sideways: the tool never comes closer to
//! the part than `stock_to_leave_mm`.
//!
//! # Levels
//!
//! `stock_top − step_down`, `stock_top − 2·step_down`, ... while above the last level
//! `max(floor_mm, min K)`, then the last level itself: no step exceeds `step_down_mm`, and the
//! last level is the lowest height at which anything may be cleared, so nothing above
//! `floor + leave` stays unreachable. A level where nothing is allowed ends the roughing (lower
//! levels allow even less).
//!
//! # Patterns
//!
//! - X / Y: passes along cell rows (X) or columns (Y) through cell centres, lines at most
//!   `step_over_mm` apart (at least one pixel; the first and last row/column are always
//!   included), split where `K > Z`, zig-zag (each line's passes run opposite to the previous
//!   line's). A straight move along a row (column) between two allowed centres is safe: the
//!   distance to any cell square along it is smallest at one of the allowed centres it passes.
//! - Contour: the allowed centres' Euclidean distance to the nearest forbidden centre (outside the
//!   map counts as forbidden) is contoured by marching squares at `p, p + step_over, ...`
//!   (p = pixel): closed offset loops, outer ring first. Every loop segment is then checked
//!   exactly (below) and dropped where it would come too close, which splits the loop.
//!
//! # Links
//!
//! The first pass of each level starts with [`Link::Retract`]. Later passes are
//! [`Link::Direct`] only when the straight move at level Z from the previous pass's end to the
//! pass's start is clear, checked exactly: every part cell (columns, floor outside) whose top
//! plus `leave` is above Z must lie farther than `R + leave` from the segment in XY (segment to
//! square distance); otherwise [`Link::Retract`]. Links whose XY bounding box spans more than
//! 250 000 cells are not checked and retract.

use depthmill_geometry::{HeightMap, ToolProfile};
use nalgebra::{Point2, Point3};

use super::CamError;
use super::compensate::{CompensateOptions, PixelModel, compensate};
use super::contour::{Polyline, SampleGrid, contour_grid};
use super::path::{Link, Pass, Toolpath};
use super::tool::{Tool, ToolKind};

/// Direction of the roughing passes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RoughingPattern {
    /// Passes parallel to X (along cell rows).
    X,
    /// Passes parallel to Y (along cell columns).
    Y,
    /// Offset loops of the region the tool may reach, outer to inner.
    Contour,
}

/// Parameters of [`roughing`]; lengths in mm.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RoughingParams {
    /// Largest drop between levels (> 0).
    pub step_down_mm: f64,
    /// Material left on the part (>= 0).
    pub stock_to_leave_mm: f64,
    /// Distance between passes (> 0, at most the tool diameter).
    pub step_over_mm: f64,
    pub pattern: RoughingPattern,
    /// Top of the stock (> floor).
    pub stock_top_mm: f64,
    /// Lowest level allowed.
    pub floor_mm: f64,
    /// Rapid height (>= stock top).
    pub safe_z_mm: f64,
}

/// Largest number of levels, lines or rings one call may produce.
const MAX_STEPS: f64 = 100_000.0;
/// Largest number of cells an exact link check may visit.
const MAX_LINK_CELLS: i64 = 250_000;

/// Flat end mill, constant-Z levels from stock_top down by at most step_down to floor; at each level clears
/// everything whose keep-out height allows it.
///
/// See the module docs for the keep-out map K, the levels, the patterns and the links. Every pass
/// point lies at a level Z on a position where the tool is at least `stock_to_leave_mm` from the
/// part (column reading), and so does every move within a pass and every [`Link::Direct`] move.
/// Strategy names: `roughing-x`, `roughing-y`, `roughing-contour`.
///
/// Errors: a tool that is not flat ([`CamError::InvalidTool`] naming it), parameters out of
/// range ([`CamError::InvalidParameter`] naming field, value and limit).
pub fn roughing(map: &HeightMap, tool: &Tool, p: &RoughingParams) -> Result<Toolpath, CamError> {
    if tool.kind != ToolKind::Flat {
        return Err(CamError::InvalidTool {
            name: tool.name.clone(),
            message: format!("roughing needs a flat end mill, got a {} tool", tool.kind.as_str()),
        });
    }
    validate(tool, p)?;
    let strategy = match p.pattern {
        RoughingPattern::X => "roughing-x",
        RoughingPattern::Y => "roughing-y",
        RoughingPattern::Contour => "roughing-contour",
    };
    let keep = KeepOut::new(map, tool.radius_mm(), p)?;
    let mut passes = Vec::new();
    for z in levels(&keep, p)? {
        let before = passes.len();
        match p.pattern {
            RoughingPattern::X | RoughingPattern::Y => {
                raster_level(&keep, z, p.step_over_mm, p.pattern == RoughingPattern::Y, &mut passes)
            }
            RoughingPattern::Contour => contour_level(&keep, z, p.step_over_mm, &mut passes)?,
        }
        if passes.len() == before {
            break;
        }
    }
    Ok(Toolpath { strategy: strategy.into(), tool: tool.name.clone(), passes, safe_z_mm: p.safe_z_mm })
}

fn validate(tool: &Tool, p: &RoughingParams) -> Result<(), CamError> {
    let positive = |field: &str, v: f64| {
        if v.is_finite() && v > 0.0 {
            Ok(())
        } else {
            Err(CamError::param(field, format!("must be finite and positive, got {v}")))
        }
    };
    positive("step_down_mm", p.step_down_mm)?;
    positive("step_over_mm", p.step_over_mm)?;
    if p.step_over_mm > tool.diameter_mm() {
        return Err(CamError::param(
            "step_over_mm",
            format!("{} exceeds the tool diameter {} mm", p.step_over_mm, tool.diameter_mm()),
        ));
    }
    if !(p.stock_to_leave_mm.is_finite() && p.stock_to_leave_mm >= 0.0) {
        return Err(CamError::param(
            "stock_to_leave_mm",
            format!("must be finite and >= 0, got {}", p.stock_to_leave_mm),
        ));
    }
    for (field, v) in [("stock_top_mm", p.stock_top_mm), ("floor_mm", p.floor_mm), ("safe_z_mm", p.safe_z_mm)]
    {
        if !v.is_finite() {
            return Err(CamError::param(field, format!("must be finite, got {v}")));
        }
    }
    if p.floor_mm >= p.stock_top_mm {
        return Err(CamError::param(
            "floor_mm",
            format!("{} must be below stock_top_mm {}", p.floor_mm, p.stock_top_mm),
        ));
    }
    if p.safe_z_mm < p.stock_top_mm {
        return Err(CamError::param(
            "safe_z_mm",
            format!("{} is below stock_top_mm {}", p.safe_z_mm, p.stock_top_mm),
        ));
    }
    if (p.stock_top_mm - p.floor_mm) / p.step_down_mm > MAX_STEPS {
        return Err(CamError::param(
            "step_down_mm",
            format!("{} gives more than {MAX_STEPS} levels", p.step_down_mm),
        ));
    }
    Ok(())
}

/// The levels, top down (see the module docs).
fn levels(keep: &KeepOut<'_>, p: &RoughingParams) -> Result<Vec<f64>, CamError> {
    let kmin = keep.k.iter().copied().fold(f64::INFINITY, f64::min);
    let last = p.floor_mm.max(kmin);
    let mut out = Vec::new();
    if last.is_nan() || last >= p.stock_top_mm {
        return Ok(out);
    }
    let mut i = 1.0;
    loop {
        let z = p.stock_top_mm - i * p.step_down_mm;
        if z <= last + 1e-9 {
            break;
        }
        out.push(z);
        i += 1.0;
    }
    out.push(last);
    Ok(out)
}

/// The keep-out map K and the part as columns for exact checks.
struct KeepOut<'a> {
    map: &'a HeightMap,
    /// K per cell (mm), row-major.
    k: Vec<f64>,
    w: i64,
    h: i64,
    pixel: f64,
    x0: f64,
    y0: f64,
    /// R + leave.
    reach: f64,
    leave: f64,
    /// Height of cells outside the map or without data (as f32, like the compensation).
    floor: f64,
}

impl<'a> KeepOut<'a> {
    fn new(map: &'a HeightMap, radius: f64, p: &RoughingParams) -> Result<Self, CamError> {
        let reach = radius + p.stock_to_leave_mm;
        let disk = ToolProfile::flat(2.0 * reach)
            .map_err(|e| CamError::param("stock_to_leave_mm", e.to_string()))?;
        let opts = CompensateOptions { pixel_model: PixelModel::Column, outside_z_mm: Some(p.floor_mm) };
        let dilated = compensate(map, &disk, &opts)?;
        let k = dilated.data().iter().map(|&d| f64::from(d) + p.stock_to_leave_mm).collect();
        Ok(KeepOut {
            map,
            k,
            w: i64::from(map.width()),
            h: i64::from(map.height()),
            pixel: map.pixel_mm(),
            x0: map.origin_x_mm(),
            y0: map.origin_y_mm(),
            reach,
            leave: p.stock_to_leave_mm,
            floor: f64::from(p.floor_mm as f32),
        })
    }

    fn allowed(&self, c: i64, r: i64, z: f64) -> bool {
        self.k[(r * self.w + c) as usize] <= z
    }

    fn centre(&self, c: i64, r: i64) -> Point2<f64> {
        Point2::new(self.x0 + (c as f64 + 0.5) * self.pixel, self.y0 + (r as f64 + 0.5) * self.pixel)
    }

    /// Part height of a cell as a column (floor outside the map and for NaN).
    fn column(&self, c: i64, r: i64) -> f64 {
        if c < 0 || r < 0 || c >= self.w || r >= self.h {
            return self.floor;
        }
        let a = self.map.data()[(r * self.w + c) as usize];
        if a.is_nan() { self.floor } else { f64::from(a) }
    }

    /// Exact check of a straight move at level `z` (see the module docs, Links).
    fn segment_clear(&self, a: Point2<f64>, b: Point2<f64>, z: f64) -> bool {
        let p = self.pixel;
        let lo = |v: f64, o: f64| ((v - self.reach - o) / p).floor() as i64 - 1;
        let hi = |v: f64, o: f64| ((v + self.reach - o) / p).floor() as i64 + 1;
        let (c0, c1) = (lo(a.x.min(b.x), self.x0), hi(a.x.max(b.x), self.x0));
        let (r0, r1) = (lo(a.y.min(b.y), self.y0), hi(a.y.max(b.y), self.y0));
        if (c1 - c0 + 1).saturating_mul(r1 - r0 + 1) > MAX_LINK_CELLS {
            return false;
        }
        for r in r0..=r1 {
            for c in c0..=c1 {
                if self.column(c, r) + self.leave <= z {
                    continue;
                }
                let bx = [self.x0 + c as f64 * p, self.y0 + r as f64 * p];
                let sq = Square { x0: bx[0], y0: bx[1], x1: bx[0] + p, y1: bx[1] + p };
                if segment_square_distance(a, b, &sq) <= self.reach + 1e-9 {
                    return false;
                }
            }
        }
        true
    }
}

/// An axis-aligned square (closed) in XY.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Square {
    pub x0: f64,
    pub y0: f64,
    pub x1: f64,
    pub y1: f64,
}

fn point_square_distance(q: Point2<f64>, s: &Square) -> f64 {
    let dx = (s.x0 - q.x).max(0.0).max(q.x - s.x1);
    let dy = (s.y0 - q.y).max(0.0).max(q.y - s.y1);
    dx.hypot(dy)
}

fn point_segment_distance(q: Point2<f64>, a: Point2<f64>, b: Point2<f64>) -> f64 {
    let d = b - a;
    let l2 = d.norm_squared();
    let t = if l2 > 0.0 { ((q - a).dot(&d) / l2).clamp(0.0, 1.0) } else { 0.0 };
    (q - (a + d * t)).norm()
}

/// Parameter range `[t0, t1]` of the segment `a + t·(b − a)`, `t in [0, 1]`, inside the closed
/// square, or `None` (Liang-Barsky).
pub(crate) fn clip_segment(a: Point2<f64>, b: Point2<f64>, s: &Square) -> Option<(f64, f64)> {
    let (mut t0, mut t1) = (0.0f64, 1.0f64);
    let d = b - a;
    for (pv, qv) in [(-d.x, a.x - s.x0), (d.x, s.x1 - a.x), (-d.y, a.y - s.y0), (d.y, s.y1 - a.y)] {
        if pv == 0.0 {
            if qv < 0.0 {
                return None;
            }
        } else {
            let r = qv / pv;
            if pv < 0.0 {
                t0 = t0.max(r);
            } else {
                t1 = t1.min(r);
            }
        }
    }
    (t0 <= t1).then_some((t0, t1))
}

/// Smallest XY distance between the segment `ab` and the closed square.
fn segment_square_distance(a: Point2<f64>, b: Point2<f64>, s: &Square) -> f64 {
    if clip_segment(a, b, s).is_some() {
        return 0.0;
    }
    let corners =
        [Point2::new(s.x0, s.y0), Point2::new(s.x1, s.y0), Point2::new(s.x0, s.y1), Point2::new(s.x1, s.y1)];
    corners
        .iter()
        .map(|&q| point_segment_distance(q, a, b))
        .fold(point_square_distance(a, s).min(point_square_distance(b, s)), f64::min)
}

/// Appends `pass` with a Direct link when the move from the previous pass's end is clear.
fn push_pass(
    keep: &KeepOut<'_>,
    z: f64,
    first_of_level: bool,
    points: Vec<Point3<f64>>,
    passes: &mut Vec<Pass>,
) {
    let link = match (first_of_level, passes.last().and_then(|p: &Pass| p.points.last()), points.first()) {
        (false, Some(prev), Some(start))
            if keep.segment_clear(Point2::new(prev.x, prev.y), Point2::new(start.x, start.y), z) =>
        {
            Link::Direct
        }
        _ => Link::Retract,
    };
    passes.push(Pass { link, points });
}

/// Line indices `0, s, 2s, ...` plus the last, with `s = max(1, floor(step_over / pixel))`.
fn line_indices(n: i64, step_over: f64, pixel: f64) -> Vec<i64> {
    let stride = ((step_over / pixel + 1e-9).floor() as i64).max(1);
    let mut v: Vec<i64> = (0..n).step_by(stride as usize).collect();
    if v.last() != Some(&(n - 1)) {
        v.push(n - 1);
    }
    v
}

fn raster_level(keep: &KeepOut<'_>, z: f64, step_over: f64, along_y: bool, passes: &mut Vec<Pass>) {
    let (n_lines, n_along) = if along_y { (keep.w, keep.h) } else { (keep.h, keep.w) };
    let cell = |line: i64, i: i64| if along_y { (line, i) } else { (i, line) };
    let mut forward = true;
    let mut first = true;
    for line in line_indices(n_lines, step_over, keep.pixel) {
        let mut runs: Vec<(i64, i64)> = Vec::new();
        let mut start = None;
        for i in 0..n_along {
            let (c, r) = cell(line, i);
            match (keep.allowed(c, r, z), start) {
                (true, None) => start = Some(i),
                (false, Some(s)) => {
                    runs.push((s, i - 1));
                    start = None;
                }
                _ => {}
            }
        }
        if let Some(s) = start {
            runs.push((s, n_along - 1));
        }
        if runs.is_empty() {
            continue;
        }
        if !forward {
            runs.reverse();
            for r in &mut runs {
                *r = (r.1, r.0);
            }
        }
        for (a, b) in runs {
            let to3 = |i: i64| {
                let (c, r) = cell(line, i);
                let q = keep.centre(c, r);
                Point3::new(q.x, q.y, z)
            };
            let points = if a == b { vec![to3(a)] } else { vec![to3(a), to3(b)] };
            push_pass(keep, z, first, points, passes);
            first = false;
        }
        forward = !forward;
    }
}

/// Squared Euclidean distance transform along one line (Felzenszwalb-Huttenlocher).
fn edt_1d(f: &[f64], out: &mut [f64]) {
    let n = f.len();
    let mut v = vec![0usize; n];
    let mut zb = vec![0.0f64; n + 1];
    let mut k = 0usize;
    zb[0] = f64::NEG_INFINITY;
    zb[1] = f64::INFINITY;
    let parabola = |q: usize, vk: usize| {
        ((f[q] + (q * q) as f64) - (f[vk] + (vk * vk) as f64)) / (2.0 * (q as f64 - vk as f64))
    };
    for q in 1..n {
        let mut s = parabola(q, v[k]);
        // zb[0] is -inf, so k stops at 0.
        while s <= zb[k] {
            k -= 1;
            s = parabola(q, v[k]);
        }
        k += 1;
        v[k] = q;
        zb[k] = s;
        zb[k + 1] = f64::INFINITY;
    }
    k = 0;
    for (q, o) in out.iter_mut().enumerate() {
        while zb[k + 1] < q as f64 {
            k += 1;
        }
        let d = q as f64 - v[k] as f64;
        *o = d * d + f[v[k]];
    }
}

/// Distance (mm) of each allowed centre to the nearest forbidden one on the grid padded by one
/// forbidden ring; forbidden centres get 0. Returns the padded field, row-major.
fn distance_field(keep: &KeepOut<'_>, z: f64) -> Vec<f32> {
    let (w, h) = ((keep.w + 2) as usize, (keep.h + 2) as usize);
    const FAR: f64 = 1e18;
    let mut f = vec![0.0f64; w * h];
    for r in 0..keep.h {
        for c in 0..keep.w {
            if keep.allowed(c, r, z) {
                f[(r as usize + 1) * w + c as usize + 1] = FAR;
            }
        }
    }
    let mut row_out = vec![0.0; w];
    for j in 0..h {
        edt_1d(&f[j * w..(j + 1) * w], &mut row_out);
        f[j * w..(j + 1) * w].copy_from_slice(&row_out);
    }
    let (mut col, mut col_out) = (vec![0.0; h], vec![0.0; h]);
    for i in 0..w {
        for j in 0..h {
            col[j] = f[j * w + i];
        }
        edt_1d(&col, &mut col_out);
        for j in 0..h {
            f[j * w + i] = col_out[j];
        }
    }
    f.iter().map(|&d2| (d2.sqrt() * keep.pixel) as f32).collect()
}

fn contour_level(keep: &KeepOut<'_>, z: f64, step_over: f64, passes: &mut Vec<Pass>) -> Result<(), CamError> {
    let field = distance_field(keep, z);
    let grid = SampleGrid {
        values: &field,
        width: (keep.w + 2) as usize,
        height: (keep.h + 2) as usize,
        x0_mm: keep.x0 - keep.pixel / 2.0,
        y0_mm: keep.y0 - keep.pixel / 2.0,
        step_mm: keep.pixel,
    };
    let max_d = field.iter().copied().fold(0.0f32, f32::max);
    let mut first = true;
    let mut ring = 0.0;
    loop {
        let level = keep.pixel + ring * step_over;
        if level > f64::from(max_d) + 1e-9 || ring > MAX_STEPS {
            break;
        }
        ring += 1.0;
        let mut pieces: Vec<Polyline> = Vec::new();
        for line in contour_grid(&grid, level)? {
            split_clear(keep, z, line, &mut pieces);
        }
        let mut pos = passes.last().and_then(|p| p.points.last()).map(|q| Point2::new(q.x, q.y));
        for piece in order_nearest(pieces, &mut pos) {
            let points = piece.into_iter().map(|q| Point3::new(q.x, q.y, z)).collect();
            push_pass(keep, z, first, points, passes);
            first = false;
        }
    }
    Ok(())
}

/// Splits `line` at the segments that are not clear at `z` (dropping them).
fn split_clear(keep: &KeepOut<'_>, z: f64, line: Polyline, out: &mut Vec<Polyline>) {
    line.split_segments(|a, b| keep.segment_clear(a, b, z), out);
}

/// Orders polylines by nearest start from `pos`: open lines may be reversed, closed loops are
/// rotated to their vertex nearest `pos` and closed by repeating it. Updates `pos`.
pub(crate) fn order_nearest(
    mut lines: Vec<Polyline>,
    pos: &mut Option<Point2<f64>>,
) -> Vec<Vec<Point2<f64>>> {
    let mut out = Vec::with_capacity(lines.len());
    while !lines.is_empty() {
        let here = pos.unwrap_or_else(|| lines[0].points[0]);
        let mut best = (f64::INFINITY, 0usize, 0usize, false);
        for (li, l) in lines.iter().enumerate() {
            if l.closed {
                for (vi, q) in l.points.iter().enumerate() {
                    let d = (q - here).norm();
                    if d < best.0 {
                        best = (d, li, vi, false);
                    }
                }
            } else {
                let (a, b) = (l.points[0], l.points[l.points.len() - 1]);
                if (a - here).norm() < best.0 {
                    best = ((a - here).norm(), li, 0, false);
                }
                if (b - here).norm() < best.0 {
                    best = ((b - here).norm(), li, 0, true);
                }
            }
        }
        let l = lines.swap_remove(best.1);
        let pts = if l.closed {
            let mut v: Vec<Point2<f64>> =
                l.points[best.2..].iter().chain(&l.points[..best.2]).copied().collect();
            v.push(v[0]);
            v
        } else if best.3 {
            l.points.into_iter().rev().collect()
        } else {
            l.points
        };
        *pos = pts.last().copied();
        out.push(pts);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use depthmill_geometry::{HeightMapMeta, ToolSpec};
    use proptest::prelude::*;

    fn flat(d: f64) -> Tool {
        Tool::from_spec(&ToolSpec::Flat { diameter_mm: d }).expect("tool")
    }

    fn params(pattern: RoughingPattern) -> RoughingParams {
        RoughingParams {
            step_down_mm: 2.0,
            stock_to_leave_mm: 0.3,
            step_over_mm: 1.2,
            pattern,
            stock_top_mm: 6.0,
            floor_mm: 0.0,
            safe_z_mm: 11.0,
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

    /// 3D distance between the flat tool (cylinder of `radius`, bottom at `q.z`, unbounded
    /// upward) and the part column of cell (c, r) (square, from below up to `top`).
    fn tool_column_distance(q: Point3<f64>, radius: f64, sq: &Square, top: f64) -> f64 {
        let dh = point_square_distance(Point2::new(q.x, q.y), sq);
        let dr = (dh - radius).max(0.0);
        let dz = (q.z - top).max(0.0);
        dr.hypot(dz)
    }

    /// Brute force: the smallest distance from the tool at `q` to any part column (cells of the
    /// map, NaN and a wide ring outside the map as columns at the floor).
    fn min_distance(map: &HeightMap, radius: f64, floor: f64, q: Point3<f64>) -> f64 {
        let p = map.pixel_mm();
        let pad = (radius / p).ceil() as i64 + 4;
        let (w, h) = (i64::from(map.width()), i64::from(map.height()));
        let mut best = f64::INFINITY;
        for r in -pad..h + pad {
            for c in -pad..w + pad {
                let top = if c < 0 || r < 0 || c >= w || r >= h {
                    floor
                } else {
                    let a = map.data()[(r * w + c) as usize];
                    if a.is_nan() { floor } else { f64::from(a) }
                };
                let x0 = map.origin_x_mm() + c as f64 * p;
                let y0 = map.origin_y_mm() + r as f64 * p;
                let sq = Square { x0, y0, x1: x0 + p, y1: y0 + p };
                best = best.min(tool_column_distance(q, radius, &sq, top));
            }
        }
        best
    }

    /// Checks every point, samples along every pass segment and every Direct link.
    fn assert_clear(map: &HeightMap, tool: &Tool, prm: &RoughingParams, tp: &Toolpath) {
        let floor = f64::from(prm.floor_mm as f32);
        let r = tool.radius_mm();
        let need = prm.stock_to_leave_mm - 1e-6;
        let step = map.pixel_mm() / 4.0;
        let check_seg = |a: Point3<f64>, b: Point3<f64>, what: &str| {
            let n = ((b - a).norm() / step).ceil().max(1.0) as usize;
            for i in 0..=n {
                let q = a + (b - a) * (i as f64 / n as f64);
                let d = min_distance(map, r, floor, q);
                assert!(d >= need, "{what}: tool at {q:?} is {d} mm from the part");
            }
        };
        let mut prev: Option<Point3<f64>> = None;
        for pass in &tp.passes {
            if let (Link::Direct, Some(a)) = (pass.link, prev) {
                check_seg(a, pass.points[0], "direct link");
            }
            for pt in &pass.points {
                assert!(pt.z >= prm.floor_mm - 1e-9 && pt.z < prm.stock_top_mm);
                assert!(min_distance(map, r, floor, *pt) >= need, "point {pt:?}");
            }
            for w in pass.points.windows(2) {
                check_seg(w[0], w[1], "pass");
            }
            prev = pass.points.last().copied();
        }
    }

    #[test]
    fn rejects_non_flat_tool_naming_it() {
        let map = hemisphere(10, 0.5, 2.0);
        let ball = Tool::from_spec(&ToolSpec::Ball { diameter_mm: 3.0 }).expect("tool");
        let e = roughing(&map, &ball, &params(RoughingPattern::X)).expect_err("ball");
        assert!(e.to_string().contains(&ball.name) && e.to_string().contains("flat"), "{e}");
        let mut p = params(RoughingPattern::X);
        p.step_over_mm = 7.0;
        assert!(roughing(&map, &flat(3.0), &p).expect_err("step over").to_string().contains("step_over_mm"));
        p = params(RoughingPattern::X);
        p.floor_mm = 7.0;
        assert!(roughing(&map, &flat(3.0), &p).is_err());
    }

    #[test]
    fn flat_plate_levels_and_direct_zigzag() {
        // Empty plate at 0: levels 4, 2, then the last at floor + leave = 0.3.
        let map = HeightMap::filled(HeightMapMeta::new(20, 12, 0.5), 0.0).expect("map");
        let tool = flat(3.0);
        let prm = params(RoughingPattern::X);
        let tp = roughing(&map, &tool, &prm).expect("ok");
        assert_eq!(tp.strategy, "roughing-x");
        let mut zs: Vec<f64> = tp.passes.iter().map(|p| p.points[0].z).collect();
        zs.dedup();
        assert_eq!(zs.len(), 3);
        assert!(
            (zs[0] - 4.0).abs() < 1e-9 && (zs[1] - 2.0).abs() < 1e-9 && (zs[2] - 0.3).abs() < 1e-6,
            "{zs:?}"
        );
        // Lines at rows 0, 2, 4, ... 10 and 11: 7 per level, one Retract per level.
        assert_eq!(tp.passes.len(), 21);
        assert_eq!(tp.passes.iter().filter(|p| p.link == Link::Retract).count(), 3);
        // Zig-zag: the second pass runs the other way.
        assert!(tp.passes[1].points[0].x > tp.passes[1].points[1].x);
        assert_clear(&map, &tool, &prm, &tp);
    }

    #[test]
    fn hemisphere_all_patterns_keep_their_distance() {
        let map = hemisphere(40, 0.5, 6.0);
        let tool = flat(3.0);
        for pattern in [RoughingPattern::X, RoughingPattern::Y, RoughingPattern::Contour] {
            let prm = params(pattern);
            let tp = roughing(&map, &tool, &prm).expect("ok");
            assert!(tp.passes.len() > 4, "{pattern:?}");
            assert_clear(&map, &tool, &prm, &tp);
            // Something is cut at the last level near the corner of the map.
            let last = tp.passes.last().expect("passes").points[0].z;
            assert!((last - 0.3).abs() < 1e-6, "{pattern:?} last level {last}");
        }
    }

    #[test]
    fn step_contour_loops_close() {
        // A block 4 mm high in the middle of a plate: at level 4.3+ nothing blocks; below, loops
        // run around the block.
        let meta = HeightMapMeta::new(30, 30, 0.5);
        let map =
            HeightMap::from_fn(
                meta,
                |c, r| if (10..20).contains(&c) && (10..20).contains(&r) { 4.0 } else { 0.0 },
            )
            .expect("map");
        let tool = flat(3.0);
        let prm = params(RoughingPattern::Contour);
        let tp = roughing(&map, &tool, &prm).expect("ok");
        assert_eq!(tp.strategy, "roughing-contour");
        let closed = tp
            .passes
            .iter()
            .filter(|p| p.points.len() > 3 && p.points[0] == *p.points.last().expect("p"))
            .count();
        assert!(closed >= 2, "closed loops {closed}");
        assert_clear(&map, &tool, &prm, &tp);
    }

    #[test]
    fn edt_matches_brute_force() {
        let mask = [1u8, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0];
        let f: Vec<f64> = mask.iter().map(|&m| if m == 1 { 0.0 } else { 1e18 }).collect();
        let mut out = vec![0.0; f.len()];
        edt_1d(&f, &mut out);
        for (i, o) in out.iter().enumerate() {
            let bf = mask
                .iter()
                .enumerate()
                .filter(|(_, m)| **m == 1)
                .map(|(j, _)| (i as f64 - j as f64).powi(2))
                .fold(f64::INFINITY, f64::min);
            assert_eq!(*o, bf);
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(24))]
        /// Random block maps (with holes): no point, pass move or Direct link comes closer to the
        /// part than the stock to leave.
        #[test]
        fn never_closer_than_stock_to_leave(
            cells in proptest::collection::vec(prop_oneof![4 => 0.0f32..5.0, 1 => Just(f32::NAN)], 16 * 14),
            pattern in prop_oneof![Just(RoughingPattern::X), Just(RoughingPattern::Y), Just(RoughingPattern::Contour)],
            leave in 0.0f64..0.6,
            step_down in 0.7f64..3.0,
            diameter in 1.0f64..3.0,
            step_over_frac in 0.2f64..1.0,
        ) {
            // Blocks of 2x2 cells so there is room to cut between them.
            let meta = HeightMapMeta::new(16, 14, 0.4);
            let map = HeightMap::from_fn(meta, |c, r| {
                let v = cells[((r / 2) * 16 + c / 2) as usize];
                if v.is_nan() || v < 2.5 { v.min(0.5) } else { v }
            }).expect("map");
            let tool = flat(diameter);
            let prm = RoughingParams {
                step_down_mm: step_down, stock_to_leave_mm: leave, step_over_mm: step_over_frac * diameter,
                pattern, stock_top_mm: 5.5, floor_mm: 0.0, safe_z_mm: 10.0,
            };
            let tp = roughing(&map, &tool, &prm).expect("ok");
            assert_clear(&map, &tool, &prm, &tp);
        }
    }
}
