//! Point-cloud pictures: a top view (X right, Y up, coloured by Z) and a side view from the
//! front (X right, Z up, coloured by distance from the viewer), each a z-buffer splat of every
//! point with a Lambert shade of the z-buffer so the surface reads as 3D.
//!
//! Bounds are robust (0.1 and 99.9 percentiles of a sample of the points, plus 3 %), so stray
//! points do not shrink the part to a dot; points outside are not drawn. Cost: one pass over the
//! points per view, both views in parallel (about 10 ms per million points in release).

use std::io::{BufReader, Cursor};

use depthmill_geometry::{CloudPoint, PointCloud};

use super::raster::{ColorMap, RgbImage, VIRIDIS};

/// Reads a stored cloud (XYZ, PLY) or mesh (STL, PLY with faces: its vertices) from its bytes,
/// keeping at most [`crate::digest::CLOUD_SAMPLE`] points (see [`crate::digest::cloud`]).
pub fn read_cloud(bytes: &[u8], name: &str) -> Result<crate::digest::SampledCloud, String> {
    let r = BufReader::with_capacity(1 << 20, Cursor::new(bytes));
    crate::digest::cloud(r, name, Some(bytes.len() as u64))
}

/// One rendered view and the extent it shows.
pub struct CloudView {
    pub image: RgbImage,
    /// Horizontal axis range, mm.
    pub h_range: (f64, f64),
    /// Vertical axis range, mm.
    pub v_range: (f64, f64),
    /// Colour (depth) axis range, mm.
    pub c_range: (f64, f64),
    /// Points inside the shown bounds.
    pub drawn: usize,
}

fn robust_bounds(points: &[depthmill_geometry::nalgebra::Point3<f32>], axis: usize) -> Option<(f64, f64)> {
    let step = (points.len() / 100_000).max(1);
    let mut v: Vec<f64> =
        points.iter().step_by(step).map(|p| f64::from(p[axis])).filter(|x| x.is_finite()).collect();
    if v.is_empty() {
        return None;
    }
    v.sort_unstable_by(f64::total_cmp);
    let q = |f: f64| v[((v.len() - 1) as f64 * f).round() as usize];
    let (lo, hi) = (q(0.001), q(0.999));
    let pad = ((hi - lo) * 0.03).max(1e-3);
    Some((lo - pad, hi + pad))
}

/// Splats the points seen along `depth_axis` (2 = from above, 1 = from the front) onto
/// (`h_axis`, `v_axis`); the long side gets `side_px` pixels. The nearest point wins each pixel:
/// the highest Z from above, the smallest Y from the front.
fn splat(
    cloud: &PointCloud,
    h_axis: usize,
    v_axis: usize,
    depth_axis: usize,
    side_px: f64,
) -> Option<CloudView> {
    let pts = &cloud.points;
    let (h0, h1) = robust_bounds(pts, h_axis)?;
    let (v0, v1) = robust_bounds(pts, v_axis)?;
    let (c0, c1) = robust_bounds(pts, depth_axis)?;
    let s = side_px / (h1 - h0).max(v1 - v0);
    let w = ((h1 - h0) * s).round().clamp(16.0, 4000.0) as usize;
    let h = ((v1 - v0) * s).round().clamp(16.0, 4000.0) as usize;
    // From above the viewer is at +Z (larger is nearer); from the front at -Y (smaller is nearer).
    let sign = if depth_axis == 2 { 1.0 } else { -1.0 };
    let mut zbuf = vec![f32::NEG_INFINITY; w * h];
    // Sparse clouds get square splats about as wide as the mean point spacing, so the surface
    // reads as a surface; dense ones (the usual case) one pixel per point.
    let spacing_px = ((w * h) as f64 / pts.len().max(1) as f64).sqrt();
    let r = ((spacing_px * 0.6).round() as i64).clamp(0, 6);
    let mut drawn = 0usize;
    for p in pts {
        let p = p.at();
        let u = (p[h_axis] - h0) * s;
        let v = (v1 - p[v_axis]) * s;
        if !(u >= 0.0 && v >= 0.0 && u < w as f64 && v < h as f64) {
            continue;
        }
        let d = (sign * p[depth_axis]) as f32;
        drawn += 1;
        let (ui, vi) = (u as i64, v as i64);
        for y in (vi - r).max(0)..=(vi + r).min(h as i64 - 1) {
            for x in (ui - r).max(0)..=(ui + r).min(w as i64 - 1) {
                if let Some(z) = zbuf.get_mut(y as usize * w + x as usize)
                    && d > *z
                {
                    *z = d;
                }
            }
        }
    }
    // Close pinholes of sparse clouds: an empty pixel takes the nearest of its 8 neighbours when
    // at least 3 of them hold a point (edges of the part stay sharp).
    let src = zbuf.clone();
    for y in 1..h.saturating_sub(1) {
        for x in 1..w.saturating_sub(1) {
            if src[y * w + x].is_finite() {
                continue;
            }
            let (mut best, mut n) = (f32::NEG_INFINITY, 0);
            for (dx, dy) in [(-1i64, -1i64), (0, -1), (1, -1), (-1, 0), (1, 0), (-1, 1), (0, 1), (1, 1)] {
                let j = ((y as i64 + dy) as usize) * w + (x as i64 + dx) as usize;
                if let Some(&z) = src.get(j)
                    && z.is_finite()
                {
                    n += 1;
                    best = best.max(z);
                }
            }
            if n >= 3 {
                zbuf[y * w + x] = best;
            }
        }
    }
    let cmap = ColorMap::new(VIRIDIS);
    let (lo, hi) = if sign > 0.0 { (c0, c1) } else { (-c1, -c0) };
    let px_mm = 1.0 / s;
    let mut img = RgbImage::new(w as u32, h as u32, [255, 255, 255]);
    for y in 0..h {
        for x in 0..w {
            let z = zbuf[y * w + x];
            if !z.is_finite() {
                continue;
            }
            let at = |xx: usize, yy: usize| {
                zbuf.get(yy * w + xx).copied().filter(|v| v.is_finite()).map_or(f64::from(z), f64::from)
            };
            let dzdx = (at((x + 1).min(w - 1), y) - at(x.saturating_sub(1), y)) / (2.0 * px_mm);
            // Image rows grow downwards: up is -y.
            let dzdy = (at(x, y.saturating_sub(1)) - at(x, (y + 1).min(h - 1))) / (2.0 * px_mm);
            let n = (dzdx * dzdx + dzdy * dzdy + 1.0).sqrt();
            let lambert = ((0.5 * dzdx - 0.5 * dzdy + std::f64::consts::FRAC_1_SQRT_2) / n).clamp(0.0, 1.0);
            let shade = 0.55 + 0.45 * lambert / std::f64::consts::FRAC_1_SQRT_2;
            let t = (f64::from(z) - lo) / (hi - lo);
            // The front view colours nearer points (larger -Y) brighter, like the top view's height.
            let c = cmap.at(t);
            let i = (y * w + x) * 3;
            if let Some(px) = img.data.get_mut(i..i + 3) {
                for k in 0..3 {
                    px[k] = (f64::from(c[k]) * shade.min(1.2)).round().clamp(0.0, 255.0) as u8;
                }
            }
        }
    }
    Some(CloudView { image: img, h_range: (h0, h1), v_range: (v0, v1), c_range: (c0, c1), drawn })
}

/// Top view (X right, Y up, colour = Z) and front view (X right, Z up, colour = Y, nearer is
/// brighter), rendered in parallel. `None` for an empty cloud.
pub fn views(cloud: &PointCloud) -> (Option<CloudView>, Option<CloudView>) {
    rayon::join(|| splat(cloud, 0, 1, 2, 900.0), || splat(cloud, 0, 2, 1, 900.0))
}
