//! Iso-lines of a sampled scalar field by marching squares.
//!
//! # Algorithm
//!
//! The field is a `width x height` grid of f32 samples; sample `(i, j)` sits at
//! `(x0 + i·step, y0 + j·step)` (row `j = 0` at minimum Y). A sample is *inside* when it is
//! `>= level`; NaN is always outside. Each square of four neighbouring samples is classified by
//! which corners are inside (16 cases) and gets 0, 1 or 2 segments between crossing points on its
//! edges. A crossing between two finite samples is placed by linear interpolation; one between a
//! sample and a NaN sample at the edge's midpoint. Saddles (two diagonal corners inside) are
//! resolved by the mean of the four corners: inside (`>= level`) connects the inside corners.
//! Segments are chained through the shared edges into polylines.
//!
//! # Guarantees
//!
//! - Orientation: walking along a polyline, the inside (higher values) is on the **left**. A closed
//!   loop around a region of high values is counter-clockwise (positive signed area, Y up); a loop
//!   around a hole is clockwise.
//! - A polyline is `closed` when it returns to its start; closed loops do not repeat their first
//!   point. Open polylines start and end on the grid's border (or beside NaN-free borders of the
//!   sampled area). Consecutive duplicate points are removed.
//! - Every segment lies inside one square of four samples (the closed square between them).
//!
//! For a [`HeightMap`] the samples are the cell centres: [`contours`] uses
//! `x0 = origin_x + pixel/2` (the grid convention of `depthmill_geometry::heightmap`).

use std::collections::HashMap;

use depthmill_geometry::HeightMap;
use nalgebra::Point2;

use super::CamError;

/// One iso-line in millimetres.
#[derive(Debug, Clone, PartialEq)]
pub struct Polyline {
    /// The points; a closed loop does not repeat its first point at the end.
    pub points: Vec<Point2<f64>>,
    /// Whether the last point connects back to the first.
    pub closed: bool,
}

impl Polyline {
    /// Splits the polyline at the segments `keep` rejects (dropping them) and appends the pieces
    /// to `out`; a closed loop with every segment kept stays whole, and the pieces of a broken loop
    /// start right after a rejected segment, so no piece is cut in two needlessly.
    pub fn split_segments(self, keep: impl Fn(Point2<f64>, Point2<f64>) -> bool, out: &mut Vec<Polyline>) {
        let n = self.points.len();
        if n < 2 {
            return;
        }
        let segs = if self.closed { n } else { n - 1 };
        let good: Vec<bool> = (0..segs).map(|i| keep(self.points[i], self.points[(i + 1) % n])).collect();
        if good.iter().all(|&g| g) {
            out.push(self);
            return;
        }
        let start = if self.closed { good.iter().position(|&g| !g).map_or(0, |i| i + 1) } else { 0 };
        let mut cur: Vec<Point2<f64>> = Vec::new();
        for k in 0..segs {
            let i = (start + k) % segs;
            if good[i] {
                if cur.is_empty() {
                    cur.push(self.points[i]);
                }
                cur.push(self.points[(i + 1) % n]);
            } else if !cur.is_empty() {
                out.push(Polyline { points: std::mem::take(&mut cur), closed: false });
            }
        }
        if !cur.is_empty() {
            out.push(Polyline { points: cur, closed: false });
        }
    }

    /// Length in mm (including the closing segment of a closed loop).
    pub fn length_mm(&self) -> f64 {
        let open: f64 = self.points.windows(2).map(|w| (w[1] - w[0]).norm()).sum();
        match (self.closed, self.points.first(), self.points.last()) {
            (true, Some(a), Some(b)) => open + (a - b).norm(),
            _ => open,
        }
    }

    /// Signed area in mm² by the shoelace formula, as if closed: positive when counter-clockwise
    /// (inside on the left of a loop around high values).
    pub fn signed_area_mm2(&self) -> f64 {
        let n = self.points.len();
        (0..n)
            .map(|i| {
                let (a, b) = (self.points[i], self.points[(i + 1) % n]);
                a.x * b.y - b.x * a.y
            })
            .sum::<f64>()
            / 2.0
    }
}

/// A sampled field: `values[j·width + i]` at `(x0_mm + i·step_mm, y0_mm + j·step_mm)`.
#[derive(Debug, Clone, Copy)]
pub struct SampleGrid<'a> {
    pub values: &'a [f32],
    pub width: usize,
    pub height: usize,
    pub x0_mm: f64,
    pub y0_mm: f64,
    pub step_mm: f64,
}

/// Iso-lines of `map` (cell-centre samples, NaN outside) at `level` mm; see the module docs.
pub fn contours(map: &HeightMap, level: f64) -> Result<Vec<Polyline>, CamError> {
    let p = map.pixel_mm();
    contour_grid(
        &SampleGrid {
            values: map.data(),
            width: map.width() as usize,
            height: map.height() as usize,
            x0_mm: map.origin_x_mm() + p / 2.0,
            y0_mm: map.origin_y_mm() + p / 2.0,
            step_mm: p,
        },
        level,
    )
}

/// Local edges of a square: 0 bottom (c0-c1), 1 right (c1-c2), 2 top (c3-c2), 3 left (c0-c3),
/// corners c0 (i, j), c1 (i+1, j), c2 (i+1, j+1), c3 (i, j+1). Returns oriented (from, to) pairs
/// with the inside on the left.
fn case_segments(case: u8, centre_inside: bool) -> &'static [(u8, u8)] {
    match case {
        // One corner k inside: e_k -> e_{k-1}.
        1 => &[(0, 3)],
        2 => &[(1, 0)],
        4 => &[(2, 1)],
        8 => &[(3, 2)],
        // One corner k outside: e_{k-1} -> e_k.
        14 => &[(3, 0)],
        13 => &[(0, 1)],
        11 => &[(1, 2)],
        7 => &[(2, 3)],
        // Two adjacent corners.
        3 => &[(1, 3)],
        12 => &[(3, 1)],
        9 => &[(0, 2)],
        6 => &[(2, 0)],
        // Saddles.
        5 if centre_inside => &[(0, 1), (2, 3)],
        5 => &[(0, 3), (2, 1)],
        10 if centre_inside => &[(3, 0), (1, 2)],
        10 => &[(1, 0), (3, 2)],
        _ => &[],
    }
}

/// Iso-lines of `grid` at `level`; see the module docs. Errors: a non-finite level or step, or
/// `values.len() != width·height`.
pub fn contour_grid(grid: &SampleGrid<'_>, level: f64) -> Result<Vec<Polyline>, CamError> {
    let (w, h) = (grid.width, grid.height);
    if grid.values.len() != w * h {
        return Err(CamError::param(
            "values",
            format!("has {} samples but {w}x{h} needs {}", grid.values.len(), w * h),
        ));
    }
    if !level.is_finite() {
        return Err(CamError::param("level", format!("must be finite, got {level}")));
    }
    if !(grid.step_mm.is_finite() && grid.step_mm > 0.0) {
        return Err(CamError::param("step_mm", format!("must be finite and positive, got {}", grid.step_mm)));
    }
    if w < 2 || h < 2 {
        return Ok(Vec::new());
    }
    let val = |i: usize, j: usize| grid.values[j * w + i];
    let inside = |v: f32| !v.is_nan() && f64::from(v) >= level;
    let pos = |i: usize, j: usize| {
        Point2::new(grid.x0_mm + i as f64 * grid.step_mm, grid.y0_mm + j as f64 * grid.step_mm)
    };
    let n_horizontal = (w - 1) * h;
    // Edge ids: horizontal (i, j)-(i+1, j) is j·(w-1)+i; vertical (i, j)-(i, j+1) is nh + j·w + i.
    let edge_point = |id: usize| -> Point2<f64> {
        let ((ia, ja), (ib, jb)) = if id < n_horizontal {
            let (i, j) = (id % (w - 1), id / (w - 1));
            ((i, j), (i + 1, j))
        } else {
            let k = id - n_horizontal;
            let (i, j) = (k % w, k / w);
            ((i, j), (i, j + 1))
        };
        let (a, b) = (val(ia, ja), val(ib, jb));
        let t = if a.is_nan() || b.is_nan() {
            0.5
        } else {
            ((level - f64::from(a)) / (f64::from(b) - f64::from(a))).clamp(0.0, 1.0)
        };
        let (pa, pb) = (pos(ia, ja), pos(ib, jb));
        pa + (pb - pa) * t
    };
    // from edge -> to edge
    let mut next: HashMap<usize, usize> = HashMap::new();
    let mut is_target: HashMap<usize, ()> = HashMap::new();
    for j in 0..h - 1 {
        for i in 0..w - 1 {
            let c = [val(i, j), val(i + 1, j), val(i + 1, j + 1), val(i, j + 1)];
            let case = c.iter().enumerate().fold(0u8, |acc, (k, &v)| acc | (u8::from(inside(v)) << k));
            if case == 0 || case == 15 {
                continue;
            }
            let mean = c.iter().map(|&v| f64::from(v)).sum::<f64>() / 4.0;
            let edges = [
                j * (w - 1) + i,
                n_horizontal + j * w + i + 1,
                (j + 1) * (w - 1) + i,
                n_horizontal + j * w + i,
            ];
            for &(a, b) in case_segments(case, !mean.is_nan() && mean >= level) {
                let (ea, eb) = (edges[usize::from(a)], edges[usize::from(b)]);
                next.insert(ea, eb);
                is_target.insert(eb, ());
            }
        }
    }
    let mut out = Vec::new();
    let mut starts: Vec<usize> = next.keys().copied().filter(|e| !is_target.contains_key(e)).collect();
    starts.sort_unstable();
    let push = |edges: Vec<usize>, closed: bool, out: &mut Vec<Polyline>| {
        let mut points: Vec<Point2<f64>> = Vec::with_capacity(edges.len());
        for e in edges {
            let p = edge_point(e);
            if points.last().is_none_or(|q| (p - q).norm() > 1e-12) {
                points.push(p);
            }
        }
        if closed && points.len() > 1 && (points[0] - points[points.len() - 1]).norm() <= 1e-12 {
            points.pop();
        }
        if points.len() >= 2 {
            out.push(Polyline { points, closed });
        }
    };
    for s in starts {
        let mut chain = vec![s];
        let mut cur = s;
        while let Some(n) = next.remove(&cur) {
            chain.push(n);
            cur = n;
        }
        push(chain, false, &mut out);
    }
    let mut rest: Vec<usize> = next.keys().copied().collect();
    rest.sort_unstable();
    for s in rest {
        if !next.contains_key(&s) {
            continue;
        }
        let mut chain = vec![s];
        let mut cur = s;
        while let Some(n) = next.remove(&cur) {
            if n != s {
                chain.push(n);
            }
            cur = n;
        }
        push(chain, true, &mut out);
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use depthmill_geometry::HeightMapMeta;
    use proptest::prelude::*;
    use std::f64::consts::PI;

    fn field(n: u32, p: f64, f: impl Fn(f64, f64) -> f64) -> HeightMap {
        let mut meta = HeightMapMeta::new(n, n, p);
        meta.origin_x_mm = -f64::from(n) * p / 2.0;
        meta.origin_y_mm = meta.origin_x_mm;
        HeightMap::from_fn(meta, |c, r| {
            let (x, y) = meta.cell_center(c, r);
            f(x, y) as f32
        })
        .expect("map")
    }

    #[test]
    fn circle_length_area_and_orientation() {
        let p = 0.25;
        let map = field(60, p, |x, y| 5.0 - (x * x + y * y).sqrt());
        let lines = contours(&map, 0.0).expect("ok");
        assert_eq!(lines.len(), 1);
        let l = &lines[0];
        assert!(l.closed);
        let area = l.signed_area_mm2();
        assert!(area > 0.0, "counter-clockwise around the peak");
        assert!((area - PI * 25.0).abs() < 2.0 * PI * 5.0 * p * 0.1, "{area}");
        assert!((l.length_mm() - 2.0 * PI * 5.0).abs() < 0.1 * p * 10.0, "{}", l.length_mm());
        for q in &l.points {
            let r = (q.x * q.x + q.y * q.y).sqrt();
            assert!((r - 5.0).abs() < 0.05 * p, "{r}");
        }
    }

    #[test]
    fn square() {
        let map = field(40, 0.5, |x, y| 4.0 - x.abs().max(y.abs()));
        let lines = contours(&map, 0.0).expect("ok");
        assert_eq!(lines.len(), 1);
        let l = &lines[0];
        assert!(l.closed);
        // Corners are cut by less than a pixel.
        assert!((l.signed_area_mm2() - 64.0).abs() < 0.5 * 0.5, "{}", l.signed_area_mm2());
        assert!((l.length_mm() - 32.0).abs() < 4.0 * (2.0 - 2f64.sqrt()) * 0.5, "{}", l.length_mm());
    }

    #[test]
    fn two_blobs() {
        let map = field(60, 0.25, |x, y| {
            let a = 2.0 - ((x + 3.5).powi(2) + y * y).sqrt();
            let b = 2.0 - ((x - 3.5).powi(2) + y * y).sqrt();
            a.max(b)
        });
        let mut lines = contours(&map, 0.0).expect("ok");
        assert_eq!(lines.len(), 2);
        lines.sort_by(|a, b| a.points[0].x.total_cmp(&b.points[0].x));
        for l in &lines {
            assert!(l.closed);
            assert!((l.signed_area_mm2() - PI * 4.0).abs() < 0.1, "{}", l.signed_area_mm2());
        }
        assert!(lines[0].points.iter().all(|q| q.x < 0.0));
        assert!(lines[1].points.iter().all(|q| q.x > 0.0));
    }

    #[test]
    fn ring_with_hole() {
        let map = field(60, 0.25, |x, y| {
            let r = (x * x + y * y).sqrt();
            (r - 2.0).min(5.0 - r)
        });
        let mut lines = contours(&map, 0.0).expect("ok");
        assert_eq!(lines.len(), 2);
        lines.sort_by(|a, b| b.signed_area_mm2().total_cmp(&a.signed_area_mm2()));
        assert!(lines.iter().all(|l| l.closed));
        assert!((lines[0].signed_area_mm2() - PI * 25.0).abs() < 0.2, "{}", lines[0].signed_area_mm2());
        assert!((lines[1].signed_area_mm2() + PI * 4.0).abs() < 0.2, "hole clockwise");
        let total: f64 = lines.iter().map(Polyline::signed_area_mm2).sum();
        assert!((total - PI * 21.0).abs() < 0.3);
    }

    #[test]
    fn open_at_border_and_nan_is_outside() {
        // Half plane x > 0: one open line going down (inside, +x, on the left when walking -y).
        let map = field(10, 1.0, |x, _| x);
        let lines = contours(&map, 0.0).expect("ok");
        assert_eq!(lines.len(), 1);
        assert!(!lines[0].closed);
        assert!(lines[0].points.first().expect("p").y > lines[0].points.last().expect("p").y);
        // A NaN cell inside a plateau makes a clockwise hole around it.
        let mut map = field(9, 1.0, |_, _| 1.0);
        map.set(4, 4, f32::NAN).expect("set");
        let lines = contours(&map, 0.5).expect("ok");
        assert_eq!(lines.len(), 1);
        assert!(lines[0].closed && lines[0].signed_area_mm2() < 0.0);
        assert!((lines[0].signed_area_mm2() + 0.5).abs() < 1e-9, "{}", lines[0].signed_area_mm2());
        assert!(contours(&map, f64::NAN).is_err());
    }

    proptest! {
        /// On a field with an outside border every line closes, and the loops' total signed area
        /// approximates the inside area (one cell per inside sample) within half a cell diagonal
        /// per unit of length.
        #[test]
        fn random_fields_close_and_area_matches(vals in proptest::collection::vec(-1.0f32..1.0, 12 * 12), level in -0.5f64..0.5) {
            let (w, h) = (14usize, 14usize);
            let mut v = vec![-2.0f32; w * h];
            for j in 0..12 { for i in 0..12 { v[(j + 1) * w + i + 1] = vals[j * 12 + i]; } }
            let g = SampleGrid { values: &v, width: w, height: h, x0_mm: 0.0, y0_mm: 0.0, step_mm: 1.0 };
            let lines = contour_grid(&g, level).expect("ok");
            let total: f64 = lines.iter().map(Polyline::signed_area_mm2).sum();
            let len: f64 = lines.iter().map(Polyline::length_mm).sum();
            let count = v.iter().filter(|&&x| f64::from(x) >= level).count() as f64;
            prop_assert!(lines.iter().all(|l| l.closed));
            // Each crossing lies on a sample-to-sample edge, at most half a cell from the Voronoi
            // boundary of the one-cell-per-sample count along that edge: at most half a diagonal
            // (0.5·√2) from it measured across a segment, per unit of contour length.
            prop_assert!((total - count).abs() <= 0.5 * std::f64::consts::SQRT_2 * len + 1e-9, "area {} count {} len {}", total, count, len);
            for l in &lines { prop_assert!(l.points.iter().all(|q| q.x >= 0.0 && q.x <= 13.0 && q.y >= 0.0 && q.y <= 13.0)); }
        }
    }
}
