//! Preview: sweep the planned tools over the stock to render the surface the program leaves, and
//! measure it against the model: gouge (cut below the part) and leftover (material above it).
//!
//! Algorithm: the stock is a Z-map on the depth map's grid, initially flat at the stock top. Every
//! move (rapids too: a rapid through material shows up as a gouge) is sampled at no more than half
//! a pixel; at each sample the tool, a solid of revolution, lowers every cell whose centre
//! lies within its radius to `tip_z + height_at(distance)`. This is exact at cell centres for the
//! sampled positions; between samples the surface can be higher than the true swept envelope by at
//! most the tool's height change over half a pixel of travel (a quarter pixel either side), so leftover is slightly over-reported and
//! gouge never under-reported by more than that. Rows are split into bands processed in parallel,
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
        let mut samples = Vec::new();
        let mut at = op.start;
        samples.push(at);
        for seg in op.segments {
            sample_segment(at, seg, p * SAMPLE_STEP_PX, &mut samples);
            at = seg.end();
        }
        samples_total += samples.len() as u64;
        // Bucket samples by the row bands their footprint reaches.
        let bands = h.div_ceil(BAND_ROWS);
        let mut buckets: Vec<Vec<Point3<f64>>> = vec![Vec::new(); bands];
        for s in &samples {
            // The tool's lowest point is its tip: a sample at or above the stock top cuts nothing.
            if s.z >= stock_top_mm {
                continue;
            }
            let row_lo = (((s.y - radius - y0) / p).floor() as i64).max(0);
            let row_hi = (((s.y + radius - y0) / p).ceil() as i64).min(h as i64 - 1);
            if row_hi < 0 || row_lo > h as i64 - 1 {
                continue;
            }
            for bucket in &mut buckets[row_lo as usize / BAND_ROWS..=row_hi as usize / BAND_ROWS] {
                bucket.push(*s);
            }
        }
        let shape = Shape::of(&op.tool.profile);
        let r2 = radius * radius;
        surface.par_chunks_mut(BAND_ROWS * w).zip(buckets.par_iter()).enumerate().for_each(
            |(b, (band, pts))| {
                let band_row0 = b * BAND_ROWS;
                let band_rows = band.len() / w;
                for s in pts {
                    let row_lo = (((s.y - radius - y0) / p - 0.5).floor() as i64).max(band_row0 as i64);
                    let row_hi = (((s.y + radius - y0) / p - 0.5).ceil() as i64)
                        .min((band_row0 + band_rows) as i64 - 1);
                    for row in row_lo..=row_hi {
                        let cy = y0 + (row as f64 + 0.5) * p;
                        let dy2 = (cy - s.y).powi(2);
                        if dy2 > r2 {
                            continue;
                        }
                        // Only the columns inside the tool's circle on this row.
                        let half = (r2 - dy2).sqrt();
                        let col_lo = (((s.x - half - x0) / p - 0.5).floor() as i64).max(0);
                        let col_hi = (((s.x + half - x0) / p - 0.5).ceil() as i64).min(w as i64 - 1);
                        if col_lo > col_hi {
                            continue;
                        }
                        let line = &mut band[(row as usize - band_row0) * w..][..w];
                        for col in col_lo..=col_hi {
                            let dx = x0 + (col as f64 + 0.5) * p - s.x;
                            let d2 = dx * dx + dy2;
                            if let Some(hgt) = shape.height_at_d2(d2) {
                                let z = (s.z + hgt) as f32;
                                let cell = &mut line[col as usize];
                                if z < *cell {
                                    *cell = z;
                                }
                            }
                        }
                    }
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

    /// Brute force: every sample against every cell.
    fn reference(
        target: &HeightMap,
        stock: f64,
        tool: &Tool,
        start: Point3<f64>,
        segs: &[Segment],
    ) -> Vec<f32> {
        let mut pts = vec![start];
        let mut at = start;
        for s in segs {
            sample_segment(at, s, target.pixel_mm() * SAMPLE_STEP_PX, &mut pts);
            at = s.end();
        }
        let mut out = vec![stock as f32; target.data().len()];
        for r in 0..target.height() {
            for c in 0..target.width() {
                let (x, y) = target.cell_center(c, r);
                for p in &pts {
                    if let Some(hh) = tool.profile.height_at(((x - p.x).powi(2) + (y - p.y).powi(2)).sqrt()) {
                        let i = (r * target.width() + c) as usize;
                        out[i] = out[i].min((p.z + hh) as f32);
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
