//! Preview: sweep the planned tools over the stock to render the surface the program leaves, and
//! measure it against the model: gouge (cut below the part) and leftover (material above it).
//!
//! Algorithm: the stock is a Z-map on the depth map's grid, initially flat at the stock top. Every
//! move counts (rapids too: a rapid through material shows up as a gouge). A straight move at
//! constant Z is applied exactly: each cell whose centre is within the tool radius of the segment
//! drops to `z + height_at(distance to the segment)` (the tool's height grows with distance, so the
//! nearest point of the segment is the deepest). Other moves are sampled at no more than half a
//! pixel, and each sample lowers the cells within its radius to `tip_z + height_at(distance)`;
//! between samples the surface can be higher than the true envelope by at most the tool's height
//! change over a quarter pixel, so leftover is slightly over-reported there. Rows are split into bands processed in parallel,
//! each band applying the samples whose footprint reaches it.

use depthmill_geometry::HeightMap;
use nalgebra::Point3;
use rayon::prelude::*;

use super::CamError;
use super::path::Segment;
use super::tool::Tool;

/// One tool's moves, from `start`.
pub struct SweptOp<'a> {
    pub tool: &'a Tool,
    pub start: Point3<f64>,
    pub segments: &'a [Segment],
}

/// What the program leaves.
#[derive(Debug, Clone)]
pub struct PreviewReport {
    /// Top of the machined stock at each cell centre.
    pub final_surface: HeightMap,
    /// `final - target` (NaN where the target has no data); negative values are gouges.
    pub leftover: HeightMap,
    /// Largest depth cut below the target (0 when nothing was gouged).
    pub max_gouge_mm: f64,
    /// Where the largest gouge is (cell centre, mm), when there is one.
    pub gouge_at_mm: Option<[f64; 2]>,
    pub max_leftover_mm: f64,
    pub mean_leftover_mm: f64,
    /// Tool positions applied.
    pub samples: u64,
}

const BAND_ROWS: usize = 16;

/// Sampling step along moves, in pixels.
const SAMPLE_STEP_PX: f64 = 0.5;

/// The tool's height above its tip as a function of the squared distance from its axis, with
/// closed forms for the common shapes (one square root for a ball, none for a flat end).
enum Shape<'a> {
    Ball { r: f64 },
    Flat { r2: f64 },
    Profile(&'a depthmill_geometry::ToolProfile),
}

impl<'a> Shape<'a> {
    fn of(profile: &'a depthmill_geometry::ToolProfile) -> Self {
        match profile.spec() {
            Some(depthmill_geometry::ToolSpec::Ball { diameter_mm }) => Shape::Ball { r: diameter_mm / 2.0 },
            Some(depthmill_geometry::ToolSpec::Flat { diameter_mm }) => {
                Shape::Flat { r2: (diameter_mm / 2.0).powi(2) }
            }
            _ => Shape::Profile(profile),
        }
    }

    #[inline]
    fn height_at_d2(&self, d2: f64) -> Option<f64> {
        match *self {
            Shape::Ball { r } => (d2 <= r * r).then(|| r - (r * r - d2).max(0.0).sqrt()),
            Shape::Flat { r2 } => (d2 <= r2).then_some(0.0),
            Shape::Profile(p) => p.height_at(d2.sqrt()),
        }
    }
}

/// Samples a move from `from` along `seg` at most `step` apart (excluding `from`, including the end).
pub fn sample_segment(from: Point3<f64>, seg: &Segment, step: f64, out: &mut Vec<Point3<f64>>) {
    match *seg {
        Segment::Rapid(to) | Segment::Linear(to) | Segment::Plunge(to) => {
            let n = ((to - from).norm() / step).ceil().max(1.0) as usize;
            for i in 1..=n {
                out.push(from + (to - from) * (i as f64 / n as f64));
            }
        }
        Segment::Arc { end, center, clockwise } => {
            let (cx, cy) = (center[0], center[1]);
            let r = ((from.x - cx).powi(2) + (from.y - cy).powi(2)).sqrt();
            let a0 = (from.y - cy).atan2(from.x - cx);
            let a1 = (end.y - cy).atan2(end.x - cx);
            let tau = std::f64::consts::TAU;
            let mut sweep = if clockwise { a0 - a1 } else { a1 - a0 };
            sweep = sweep.rem_euclid(tau);
            if sweep < 1e-12 {
                sweep = tau;
            }
            let len = (sweep * r).hypot(end.z - from.z);
            let n = (len / step).ceil().max(1.0) as usize;
            for i in 1..=n {
                let t = i as f64 / n as f64;
                let a = if clockwise { a0 - sweep * t } else { a0 + sweep * t };
                let z = from.z + (end.z - from.z) * t;
                out.push(if i == n { end } else { Point3::new(cx + r * a.cos(), cy + r * a.sin(), z) });
            }
        }
    }
}

/// One piece of a tool's motion as the preview applies it.
#[derive(Debug, Clone, Copy)]
enum Sweep {
    /// The tool at one position (moves that change Z are sampled).
    Point(Point3<f64>),
    /// A straight move at constant Z from `a` to `b` (XY): the envelope is exact, each cell takes
    /// the tool's height at its distance from the segment.
    Level { a: [f64; 2], b: [f64; 2], z: f64 },
    /// A ball end mill on a straight sloped move from tip `a` to tip `b`: the swept solid is a
    /// capsule, and each cell takes the lowest point of the capsule above it (closed form).
    BallLine { a: Point3<f64>, b: Point3<f64>, r: f64 },
}

/// The moves of `op` as sweeps: straight moves at constant Z whole, the rest sampled `step` apart.
fn sweeps(op: &SweptOp<'_>, step: f64) -> Vec<Sweep> {
    let ball = match op.tool.profile.spec() {
        Some(depthmill_geometry::ToolSpec::Ball { diameter_mm }) => Some(diameter_mm / 2.0),
        _ => None,
    };
    let mut out = vec![Sweep::Point(op.start)];
    let mut samples = Vec::new();
    let mut at = op.start;
    for seg in op.segments {
        match *seg {
            Segment::Rapid(to) | Segment::Linear(to) | Segment::Plunge(to) if (to.z - at.z).abs() < 1e-12 => {
                out.push(Sweep::Level { a: [at.x, at.y], b: [to.x, to.y], z: at.z });
            }
            Segment::Rapid(to) | Segment::Linear(to) | Segment::Plunge(to) if ball.is_some() => {
                out.push(Sweep::BallLine { a: at, b: to, r: ball.unwrap_or_default() });
            }
            _ => {
                samples.clear();
                sample_segment(at, seg, step, &mut samples);
                out.extend(samples.iter().map(|s| Sweep::Point(*s)));
            }
        }
        at = seg.end();
    }
    out
}

struct Grid {
    w: usize,
    x0: f64,
    y0: f64,
    p: f64,
}

/// Lowest point, above the horizontal position `c`, of the solid a ball end mill of radius `r`
/// sweeps when its tip moves straight from `a` to `b`: the capsule of radius `r` around the
/// centre segment `a + r·ẑ` .. `b + r·ẑ`. It is the lowest of: the lower intersection of the
/// vertical line through `c` with the infinite cylinder around the centre line, when that point
/// projects inside the segment, and the lowest points of the two end spheres. `None` when the
/// vertical line misses the capsule.
fn capsule_bottom(c: [f64; 2], a: Point3<f64>, b: Point3<f64>, r: f64) -> Option<f64> {
    let sphere = |q: Point3<f64>| {
        let d2 = (c[0] - q.x).powi(2) + (c[1] - q.y).powi(2);
        (d2 <= r * r).then(|| q.z + r - (r * r - d2).sqrt())
    };
    let mut best = match (sphere(a), sphere(b)) {
        (Some(x), Some(y)) => Some(x.min(y)),
        (x, y) => x.or(y),
    };
    let v = b - a;
    let l2 = v.norm_squared();
    let hxy2 = v.x * v.x + v.y * v.y;
    if l2 > 0.0 && hxy2 > 1e-18 {
        // w(z) = (c - centre_a) with the vertical coordinate z - centre_a.z = s: |w|² - (w·v)²/L² = r².
        let (ux, uy) = (c[0] - a.x, c[1] - a.y);
        let uv = ux * v.x + uy * v.y; // horizontal part of w·v; the vertical part is s·v.z
        let alpha = hxy2 / l2;
        let beta = -uv * v.z / l2;
        let gamma = ux * ux + uy * uy - uv * uv / l2 - r * r;
        let disc = beta * beta - alpha * gamma;
        if disc >= 0.0 {
            let s = (-beta - disc.sqrt()) / alpha; // lower root: centre-relative height
            let t = (uv + s * v.z) / l2;
            if (0.0..=1.0).contains(&t) {
                let z = a.z + r + s; // a point on the capsule surface (centre line is at tip + r)
                best = Some(best.map_or(z, |x| x.min(z)));
            }
        }
    }
    best
}

/// Squared distance from `c` to the segment `a`–`b` (XY).
#[inline]
fn dist2_to_segment(c: [f64; 2], a: [f64; 2], b: [f64; 2]) -> f64 {
    let (vx, vy) = (b[0] - a[0], b[1] - a[1]);
    let (wx, wy) = (c[0] - a[0], c[1] - a[1]);
    let len2 = vx * vx + vy * vy;
    let t = if len2 > 0.0 { ((wx * vx + wy * vy) / len2).clamp(0.0, 1.0) } else { 0.0 };
    let (dx, dy) = (wx - t * vx, wy - t * vy);
    dx * dx + dy * dy
}

/// Lowers the cells of one band (rows `row0 .. row0 + rows`) under one sweep.
fn apply(sw: &Sweep, shape: &Shape<'_>, r2: f64, g: &Grid, band: &mut [f32], row0: usize, rows: usize) {
    let radius = r2.sqrt();
    let (xlo, xhi, ylo, yhi) = match *sw {
        Sweep::Point(s) => (s.x, s.x, s.y, s.y),
        Sweep::Level { a, b, .. } => (a[0].min(b[0]), a[0].max(b[0]), a[1].min(b[1]), a[1].max(b[1])),
        Sweep::BallLine { a, b, .. } => (a.x.min(b.x), a.x.max(b.x), a.y.min(b.y), a.y.max(b.y)),
    };
    let row_lo = (((ylo - radius - g.y0) / g.p - 0.5).floor() as i64).max(row0 as i64);
    let row_hi = (((yhi + radius - g.y0) / g.p - 0.5).ceil() as i64).min((row0 + rows) as i64 - 1);
    for row in row_lo..=row_hi {
        let cy = g.y0 + (row as f64 + 0.5) * g.p;
        let line = &mut band[(row as usize - row0) * g.w..][..g.w];
        match *sw {
            Sweep::Point(s) => {
                let dy2 = (cy - s.y).powi(2);
                if dy2 > r2 {
                    continue;
                }
                // Only the columns inside the tool's circle on this row.
                let half = (r2 - dy2).sqrt();
                let col_lo = (((s.x - half - g.x0) / g.p - 0.5).floor() as i64).max(0);
                let col_hi = (((s.x + half - g.x0) / g.p - 0.5).ceil() as i64).min(g.w as i64 - 1);
                for col in col_lo..=col_hi {
                    let dx = g.x0 + (col as f64 + 0.5) * g.p - s.x;
                    if let Some(hgt) = shape.height_at_d2(dx * dx + dy2) {
                        let z = (s.z + hgt) as f32;
                        let cell = &mut line[col as usize];
                        if z < *cell {
                            *cell = z;
                        }
                    }
                }
            }
            Sweep::BallLine { a, b, r } => {
                let col_lo = (((xlo - radius - g.x0) / g.p - 0.5).floor() as i64).max(0);
                let col_hi = (((xhi + radius - g.x0) / g.p - 0.5).ceil() as i64).min(g.w as i64 - 1);
                for col in col_lo..=col_hi {
                    let cx = g.x0 + (col as f64 + 0.5) * g.p;
                    if let Some(zz) = capsule_bottom([cx, cy], a, b, r) {
                        let zz = zz as f32;
                        let cell = &mut line[col as usize];
                        if zz < *cell {
                            *cell = zz;
                        }
                    }
                }
            }
            Sweep::Level { a, b, z } => {
                let col_lo = (((xlo - radius - g.x0) / g.p - 0.5).floor() as i64).max(0);
                let col_hi = (((xhi + radius - g.x0) / g.p - 0.5).ceil() as i64).min(g.w as i64 - 1);
                for col in col_lo..=col_hi {
                    let cx = g.x0 + (col as f64 + 0.5) * g.p;
                    if let Some(hgt) = shape.height_at_d2(dist2_to_segment([cx, cy], a, b)) {
                        let zz = (z + hgt) as f32;
                        let cell = &mut line[col as usize];
                        if zz < *cell {
                            *cell = zz;
                        }
                    }
                }
            }
        }
    }
}

/// Sweeps `ops` over a stock flat at `stock_top_mm` on `target`'s grid and compares with `target`.
pub fn simulate(
    target: &HeightMap,
    stock_top_mm: f64,
    ops: &[SweptOp<'_>],
) -> Result<PreviewReport, CamError> {
    if !stock_top_mm.is_finite() {
        return Err(CamError::param("stock_top_mm", format!("must be finite, got {stock_top_mm}")));
    }
    let meta = *target.meta();
    let (w, h) = (meta.width as usize, meta.height as usize);
    let p = meta.pixel_mm;
    let (x0, y0) = (meta.origin_x_mm, meta.origin_y_mm);
    let mut surface = vec![stock_top_mm as f32; w * h];
    let mut samples_total = 0u64;
    for op in ops {
        let radius = op.tool.radius_mm();
        let r2 = radius * radius;
        let sweeps = sweeps(op, p * SAMPLE_STEP_PX);
        samples_total += sweeps.len() as u64;
        // Bucket sweeps by the row bands their footprint reaches.
        let bands = h.div_ceil(BAND_ROWS);
        let mut buckets: Vec<Vec<Sweep>> = vec![Vec::new(); bands];
        for sw in sweeps {
            let (ylo, yhi, z) = match sw {
                Sweep::Point(s) => (s.y, s.y, s.z),
                Sweep::Level { a, b, z } => (a[1].min(b[1]), a[1].max(b[1]), z),
                Sweep::BallLine { a, b, .. } => (a.y.min(b.y), a.y.max(b.y), a.z.min(b.z)),
            };
            // The tool's lowest point is its tip: a sweep at or above the stock top cuts nothing.
            if z >= stock_top_mm {
                continue;
            }
            let row_lo = (((ylo - radius - y0) / p).floor() as i64).max(0);
            let row_hi = (((yhi + radius - y0) / p).ceil() as i64).min(h as i64 - 1);
            if row_hi < 0 || row_lo > h as i64 - 1 || row_lo > row_hi {
                continue;
            }
            for bucket in &mut buckets[row_lo as usize / BAND_ROWS..=row_hi as usize / BAND_ROWS] {
                bucket.push(sw);
            }
        }
        let shape = Shape::of(&op.tool.profile);
        let grid = Grid { w, x0, y0, p };
        surface.par_chunks_mut(BAND_ROWS * w).zip(buckets.par_iter()).enumerate().for_each(
            |(b, (band, items))| {
                let band_row0 = b * BAND_ROWS;
                let band_rows = band.len() / w;
                for sw in items {
                    apply(sw, &shape, r2, &grid, band, band_row0, band_rows);
                }
            },
        );
    }
    let t = target.data();
    let mut leftover = vec![f32::NAN; w * h];
    let (mut max_gouge, mut gouge_idx, mut max_left, mut sum_left, mut n) =
        (0.0f64, None, 0.0f64, 0.0f64, 0u64);
    for i in 0..w * h {
        if t[i].is_nan() {
            continue;
        }
        let d = f64::from(surface[i]) - f64::from(t[i]);
        leftover[i] = d as f32;
        if -d > max_gouge {
            max_gouge = -d;
            gouge_idx = Some(i);
        }
        if d > 0.0 {
            max_left = max_left.max(d);
            sum_left += d;
        }
        n += 1;
    }
    let gouge_at_mm = gouge_idx.map(|i| {
        let (c, r) = ((i % w) as u32, (i / w) as u32);
        let (x, y) = meta.cell_center(c, r);
        [x, y]
    });
    let map_err = |e: depthmill_geometry::GeometryError| CamError::InvalidMap { message: e.to_string() };
    let mut surface_meta = meta;
    let lo = surface.iter().copied().fold(f32::INFINITY, f32::min);
    surface_meta.z_min_mm = f64::from(lo).min(meta.z_min_mm);
    surface_meta.z_max_mm = stock_top_mm.max(surface_meta.z_min_mm + 1e-3);
    let mut left_meta = meta;
    left_meta.z_min_mm = -max_gouge.max(1e-3);
    left_meta.z_max_mm = max_left.max(1e-3);
    Ok(PreviewReport {
        final_surface: HeightMap::new(surface_meta, surface).map_err(map_err)?,
        leftover: HeightMap::new(left_meta, leftover).map_err(map_err)?,
        max_gouge_mm: max_gouge,
        gouge_at_mm,
        max_leftover_mm: max_left,
        mean_leftover_mm: if n > 0 { sum_left / n as f64 } else { 0.0 },
        samples: samples_total,
    })
}

#[cfg(test)]
mod tests {
    use depthmill_geometry::{HeightMapMeta, ToolSpec};

    use super::*;

    fn flat_target(w: u32, h: u32, z: f32) -> HeightMap {
        let mut meta = HeightMapMeta::new(w, h, 0.1);
        meta.z_max_mm = 10.0;
        HeightMap::filled(meta, z).expect("map")
    }

    /// Brute force, every sweep against every cell: level moves by the exact distance to the
    /// segment, the others by samples.
    fn reference(
        target: &HeightMap,
        stock: f64,
        tool: &Tool,
        start: Point3<f64>,
        segs: &[Segment],
    ) -> Vec<f32> {
        let op = SweptOp { tool, start, segments: segs };
        let all = sweeps(&op, target.pixel_mm() * SAMPLE_STEP_PX);
        let mut out = vec![stock as f32; target.data().len()];
        for r in 0..target.height() {
            for c in 0..target.width() {
                let (x, y) = target.cell_center(c, r);
                for sw in &all {
                    let (d, z) = match *sw {
                        Sweep::Point(p) => (((x - p.x).powi(2) + (y - p.y).powi(2)).sqrt(), p.z),
                        Sweep::Level { a, b, z } => (dist2_to_segment([x, y], a, b).sqrt(), z),
                        Sweep::BallLine { a, b, .. } => {
                            // Dense samples: the exact capsule must be at least as low, and close.
                            let mut lowest = f64::INFINITY;
                            for k in 0..=400 {
                                let q = a + (b - a) * (f64::from(k) / 400.0);
                                if let Some(hh) =
                                    tool.profile.height_at(((x - q.x).powi(2) + (y - q.y).powi(2)).sqrt())
                                {
                                    lowest = lowest.min(q.z + hh);
                                }
                            }
                            let i = (r * target.width() + c) as usize;
                            out[i] = out[i].min(lowest as f32);
                            continue;
                        }
                    };
                    if let Some(hh) = tool.profile.height_at(d) {
                        let i = (r * target.width() + c) as usize;
                        out[i] = out[i].min((z + hh) as f32);
                    }
                }
            }
        }
        out
    }

    #[test]
    fn a_ball_groove_matches_the_brute_force_and_its_depth() {
        let target = flat_target(60, 40, 0.0);
        let tool = Tool::from_spec(&"ball-2".parse::<ToolSpec>().expect("spec")).expect("tool");
        let start = Point3::new(-1.0, 2.0, 5.0);
        let segs = [
            Segment::Rapid(Point3::new(0.5, 2.0, 5.0)),
            Segment::Plunge(Point3::new(0.5, 2.0, 1.0)),
            Segment::Linear(Point3::new(5.5, 2.0, 1.0)),
            Segment::Arc { end: Point3::new(5.5, 3.0, 1.0), center: [5.5, 2.5], clockwise: false },
            Segment::Rapid(Point3::new(5.5, 3.0, 5.0)),
        ];
        let op = SweptOp { tool: &tool, start, segments: &segs };
        let rep = simulate(&target, 3.0, &[op]).expect("sim");
        let expect = reference(&target, 3.0, &tool, start, &segs);
        for (a, b) in rep.final_surface.data().iter().zip(&expect) {
            assert!((a - b).abs() <= 1e-5, "{a} vs {b}");
        }
        // The groove bottom is the tip's Z where a centre lies on the path.
        let (c, r) = target.cell_of(3.05, 2.05).expect("cell");
        let z = rep.final_surface.get(c, r).expect("z");
        assert!((f64::from(z) - 1.0).abs() < 0.01, "{z}");
        assert_eq!(rep.max_gouge_mm, 0.0);
        assert!((rep.max_leftover_mm - 3.0).abs() < 1e-6);
    }

    #[test]
    fn sloped_ball_moves_take_the_exact_capsule_bottom() {
        let target = flat_target(60, 40, 0.0);
        let tool = Tool::from_spec(&"ball-2".parse::<ToolSpec>().expect("spec")).expect("tool");
        let start = Point3::new(0.5, 1.0, 2.0);
        let segs = [
            Segment::Linear(Point3::new(5.0, 3.0, 0.5)),
            Segment::Linear(Point3::new(1.0, 3.5, 1.5)),
            Segment::Linear(Point3::new(1.0, 3.5, 1.0)),
        ];
        let rep = simulate(&target, 3.0, &[SweptOp { tool: &tool, start, segments: &segs }]).expect("sim");
        let dense = reference(&target, 3.0, &tool, start, &segs);
        for (exact, sampled) in rep.final_surface.data().iter().zip(&dense) {
            // The exact envelope is never above dense samples of it, and barely below them.
            assert!(*exact <= sampled + 1e-5 && sampled - exact <= 0.01, "{exact} vs {sampled}");
        }
    }

    #[test]
    fn cutting_below_the_target_is_reported_as_a_gouge_where_it_happens() {
        let target = flat_target(30, 30, 2.0);
        let tool = Tool::from_spec(&"flat-1".parse::<ToolSpec>().expect("spec")).expect("tool");
        let segs = [Segment::Plunge(Point3::new(1.5, 1.5, 1.5))];
        let rep = simulate(
            &target,
            3.0,
            &[SweptOp { tool: &tool, start: Point3::new(1.5, 1.5, 5.0), segments: &segs }],
        )
        .expect("sim");
        assert!((rep.max_gouge_mm - 0.5).abs() < 1e-6, "{}", rep.max_gouge_mm);
        let at = rep.gouge_at_mm.expect("where");
        assert!((at[0] - 1.5).abs() <= 0.5 && (at[1] - 1.5).abs() <= 0.5, "{at:?}");
    }

    #[test]
    fn full_circle_arcs_sweep_all_the_way_round() {
        let mut pts = Vec::new();
        let from = Point3::new(1.0, 0.0, 0.0);
        sample_segment(
            from,
            &Segment::Arc { end: from, center: [0.0, 0.0], clockwise: true },
            0.01,
            &mut pts,
        );
        let len: f64 = std::iter::once(from)
            .chain(pts.iter().copied())
            .collect::<Vec<_>>()
            .windows(2)
            .map(|w| (w[1] - w[0]).norm())
            .sum();
        assert!((len - std::f64::consts::TAU).abs() < 1e-3, "{len}");
    }
}
