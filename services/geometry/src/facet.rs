//! The surface a height map's samples stand for, as the [`crate::compensate::PixelModel::Facet`]
//! reading takes it: a piecewise-linear upper bound through the cell centres, on a grid of half
//! the pixel ([`facet_nodes`]).
//!
//! Why: a tool compensated against the samples alone (`Point`) may pass between two of them and
//! cut a convex edge lying between them (a rim, the top of a slope) by up to a quarter of the
//! slope's change times the pixel; against square columns (`Column`) it never dips between
//! samples beside a step, but on a slope every column's downhill edge stands half a pixel's rise
//! above the surface, and the tool rides on those edges (a slope of 20° at 0.25 mm: 0.045 mm
//! left). A surface through the samples that is linear on planes and stands above every convex
//! edge the neighbouring samples imply has neither cost.
//!
//! The rule, along one line of samples `z[i]` (rows first, then the columns of the result): the
//! node between samples `a = z[i]` and `b = z[i+1]` (half-way, at t = ½ in cells) is
//! - the chord `(a + b) / 2` raised to the bound `max(chord, min(L, R))`, where `L` extends the
//!   secant of `z[i-1], a` forward and `R` the secant of `b, z[i+2]` backward: a surface concave
//!   across the four samples lies under both extensions, one convex across them under the chord;
//! - and where `L` and `R` cross inside the interval above the chord (a convex edge between the
//!   samples), raised further to the line of the side the crossing lies on at t = ½, so that the
//!   two segments through the node stand above the crossing as well.
//!
//! On a plane every node is the plane's height (the map read exactly, as `Point` reads it). A pair
//! of samples steeper than `steep` (a wall), or rising more than tan 15° and three times the
//! slopes on either side (a step on a flat or a gentle slope: a pocket's edge, which a secant
//! would round), gets the higher of the two at the node: the top extends half a pixel flat, as a
//! column would. A sample beside a cell without data or the map's edge extends flat to the
//! half-way node, as a column; an extension is only used when its own pair of samples is not
//! steep and both have data.
//!
//! Cost: two passes of a few operations per node, parallel over rows; the compensation then
//! dilates a map of (2W+1) x (2H+1) nodes with the tool at half the pixel.

use crate::{GeometryError, HeightMap, HeightMapMeta};
use rayon::prelude::*;

/// Slope (rise over run) above which two neighbouring samples are a wall or a step, not a surface
/// to interpolate: tan 75°, the slope the surface fit also takes for a wall.
pub const FACET_STEEP_SLOPE: f64 = 3.732_050_807_568_877;

/// A rise between two samples steeper than this (tan 15°) and [`JUMP_RATIO`] times the slopes
/// beside it is a step, not a surface to interpolate.
pub const JUMP_MIN_SLOPE: f64 = 0.267_949_192_431_122_7;
/// See [`JUMP_MIN_SLOPE`].
pub const JUMP_RATIO: f64 = 3.0;

/// The half-way node between samples `a` and `b` (mm), with `p` the sample before `a` and `q`
/// the one after `b` (NaN where there is none), samples `d` mm apart. See the module docs.
pub fn mid_node(p: f32, a: f32, b: f32, q: f32, d: f64, steep: f64) -> f32 {
    if a.is_nan() {
        return b;
    }
    if b.is_nan() {
        return a;
    }
    let (a64, b64) = (f64::from(a), f64::from(b));
    let lim = steep * d;
    let rise = (b64 - a64).abs();
    if rise > lim {
        return a.max(b);
    }
    let chord = 0.5 * (a64 + b64);
    // Slopes in mm per cell of the secants on either side, where they describe a surface.
    let side = |u: f32, v: f32| -> Option<f64> {
        let s = f64::from(v) - f64::from(u);
        (u.is_finite() && s.abs() <= lim).then_some(s)
    };
    let (sl, sr) = (side(p, a), side(b, q));
    // A step: a rise over the jump's minimum that stands out from the slopes on both sides.
    let beside = sl.map_or(0.0, f64::abs).max(sr.map_or(0.0, f64::abs));
    if (sl.is_some() || sr.is_some()) && rise > JUMP_MIN_SLOPE * d && rise > JUMP_RATIO * beside {
        return a.max(b);
    }
    let (Some(sl), Some(sr)) = (sl, sr) else {
        return chord as f32;
    };
    let l = |t: f64| a64 + sl * t;
    let r = |t: f64| b64 + sr * (t - 1.0);
    let mut m = chord.max(l(0.5).min(r(0.5)));
    if sl != sr {
        let tk = (b64 - sr - a64) / (sl - sr);
        if tk > 0.0 && tk < 1.0 && l(tk) > a64 + (b64 - a64) * tk {
            m = m.max(if tk <= 0.5 { l(0.5) } else { r(0.5) });
        }
    }
    m as f32
}

/// Refines one line of `n` samples (`at(i)`) into its `2n + 1` nodes, written to `out`: node
/// `2i + 1` is sample `i`, node `2i + 2` the [`mid_node`] after it, nodes `0` and `2n` the first
/// and last samples (their cells' outer halves, flat).
fn refine_line(n: usize, at: impl Fn(usize) -> f32, out: &mut [f32], d: f64, steep: f64) {
    let get = |i: isize| -> f32 { if i < 0 || i as usize >= n { f32::NAN } else { at(i as usize) } };
    if n == 0 {
        out[0] = f32::NAN;
        return;
    }
    out[0] = at(0);
    for i in 0..n {
        out[2 * i + 1] = at(i);
        let k = i as isize;
        out[2 * i + 2] =
            if i + 1 == n { at(i) } else { mid_node(get(k - 1), get(k), get(k + 1), get(k + 2), d, steep) };
    }
}

/// The nodes of `map` read as [`crate::compensate::PixelModel::Facet`]: a map of `(2W+1) x (2H+1)`
/// nodes at half the pixel, node `(2i+1, 2j+1)` on cell `(i, j)`'s centre (the same heights),
/// the others between cells as the module docs say; NaN where no cell with data is beside a node.
/// Errors: the node map would exceed [`crate::heightmap::MAX_CELLS`].
pub fn facet_nodes(map: &HeightMap, steep: f64) -> Result<HeightMap, GeometryError> {
    let (w, h) = (map.width() as usize, map.height() as usize);
    let (fw, fh) = (2 * w + 1, 2 * h + 1);
    let d = map.pixel_mm();
    let data = map.data();
    // Rows first: h rows of fw nodes.
    let mut rows = vec![0.0f32; h * fw];
    rows.par_chunks_mut(fw).enumerate().for_each(|(j, out)| {
        let src = &data[j * w..(j + 1) * w];
        refine_line(w, |i| src[i], out, d, steep);
    });
    // Then the columns of that, row by row of the result (the same rule on every node column).
    let mut fine = vec![0.0f32; fh * fw];
    fine.par_chunks_mut(fw).enumerate().for_each(|(y, out)| {
        let row = |j: isize| -> Option<&[f32]> {
            (j >= 0 && (j as usize) < h).then(|| &rows[j as usize * fw..(j as usize + 1) * fw])
        };
        if h == 0 {
            out.fill(f32::NAN);
        } else if y % 2 == 1 || y == 0 || y == fh - 1 {
            // A row of cells (y = 2j + 1), or the outer half of the first (y = 0) or last (2h).
            match row((y / 2).min(h - 1) as isize) {
                Some(r) => out.copy_from_slice(r),
                None => out.fill(f32::NAN),
            }
        } else {
            let j = (y / 2) as isize - 1;
            let (p, a, b, q) = (row(j - 1), row(j), row(j + 1), row(j + 2));
            for (x, o) in out.iter_mut().enumerate() {
                let v = |r: Option<&[f32]>| r.map_or(f32::NAN, |r| r[x]);
                *o = mid_node(v(p), v(a), v(b), v(q), d, steep);
            }
        }
    });
    let mut meta: HeightMapMeta = *map.meta();
    meta.width = fw as u32;
    meta.height = fh as u32;
    meta.pixel_mm = d / 2.0;
    meta.origin_x_mm = map.origin_x_mm() - d / 4.0;
    meta.origin_y_mm = map.origin_y_mm() - d / 4.0;
    HeightMap::new(meta, fine)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ToolProfile;
    use crate::compensate::{CompensateOptions, PixelModel, compensate, compensate_reference, kernel};
    use proptest::prelude::*;

    const STEEP: f64 = FACET_STEEP_SLOPE;

    fn map_of(w: u32, h: u32, pixel: f64, f: impl Fn(f64, f64) -> f32) -> HeightMap {
        let mut meta = HeightMapMeta::new(w, h, pixel);
        meta.z_min_mm = -10.0;
        meta.z_max_mm = 10.0;
        HeightMap::from_fn(meta, |i, j| f((f64::from(i) + 0.5) * pixel, (f64::from(j) + 0.5) * pixel))
            .expect("map")
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(2000))]
        /// The two segments through the node stand above `max(chord, min(L, R))` everywhere
        /// between the samples (checked at 200 points), and the node is never under the chord.
        #[test]
        fn the_node_bounds_the_surface_its_neighbours_imply(
            p in -1.0f32..1.0, a in -1.0f32..1.0, b in -1.0f32..1.0, q in -1.0f32..1.0,
        ) {
            // Samples 1 mm apart: no pair is steep.
            let d = 1.0;
            let m = f64::from(mid_node(p, a, b, q, d, STEEP));
            let (p, a, b, q) = (f64::from(p), f64::from(a), f64::from(b), f64::from(q));
            for k in 0..=200 {
                let t = f64::from(k) / 200.0;
                let chord = a + (b - a) * t;
                let bound = chord.max((a + (a - p) * t).min(b + (q - b) * (t - 1.0)));
                let ours = if t <= 0.5 { a + (m - a) * t / 0.5 } else { m + (b - m) * (t - 0.5) / 0.5 };
                prop_assert!(ours >= bound - 1e-5, "t {t}: {ours} under {bound} (p {p} a {a} b {b} q {q}, node {m})");
            }
        }

        /// A plane (any slope under the steep limit) is read exactly: every node inside the outer
        /// ring of half cells is the plane's height there.
        #[test]
        fn a_plane_is_read_exactly(gx in -3.0f64..3.0, gy in -3.0f64..3.0, z0 in -2.0f64..2.0) {
            let d = 0.25;
            let map = map_of(9, 7, d, |x, y| (z0 + gx * x + gy * y) as f32);
            let nodes = facet_nodes(&map, STEEP).expect("nodes");
            prop_assert_eq!((nodes.width(), nodes.height()), (19, 15));
            for y in 1..14u32 {
                for x in 1..18u32 {
                    let (px, py) = (f64::from(x) * d / 2.0, f64::from(y) * d / 2.0);
                    let want = z0 + gx * px + gy * py;
                    let got = f64::from(nodes.get(x, y).expect("node"));
                    prop_assert!((got - want).abs() < 2e-5, "node ({x}, {y}): {got} vs {want}");
                }
            }
        }

        /// The compensation under `Facet` is the dilation of the nodes at half the pixel, read at
        /// the cells' centres (the brute-force reference on the node map), on random maps with
        /// cells without data; and it never lets the tool lower than `Point` does.
        #[test]
        fn facet_compensation_is_the_dilation_of_its_nodes(
            cells in prop::collection::vec(prop_oneof![9 => -2.0f32..2.0, 1 => Just(f32::NAN)], 1..120),
            w in 1u32..12,
        ) {
            let w = w.min(cells.len() as u32);
            let h = cells.len() as u32 / w;
            let data: Vec<f32> = cells[..(w * h) as usize].to_vec();
            let mut meta = HeightMapMeta::new(w, h, 0.3);
            meta.z_min_mm = -3.0;
            let map = HeightMap::new(meta, data).expect("map");
            for profile in [ToolProfile::ball(1.0).expect("ball"), ToolProfile::flat(0.8).expect("flat")] {
                let opts = |m| CompensateOptions { pixel_model: m, outside_z_mm: Some(-3.0) };
                let fast = compensate(&map, &profile, &opts(PixelModel::Facet)).expect("facet");
                let point = compensate(&map, &profile, &opts(PixelModel::Point)).expect("point");
                let nodes = facet_nodes(&map, STEEP).expect("nodes");
                let slow = compensate_reference(&nodes, &kernel(&profile, 0.15, PixelModel::Point), -3.0);
                let fw = nodes.width() as usize;
                for j in 0..h as usize {
                    for i in 0..w as usize {
                        let got = fast.data()[j * w as usize + i];
                        let want = slow[(2 * j + 1) * fw + 2 * i + 1];
                        prop_assert!((got - want).abs() <= 1e-5, "cell ({i}, {j}): {got} vs {want}");
                        prop_assert!(got >= point.data()[j * w as usize + i] - 1e-5);
                    }
                }
            }
        }
    }

    /// The deepest a ball whose tip follows `tip` goes under `truth` (mm), over the map's cells
    /// away from its left and right edges (the profiles vary along x only), with the true surface sampled every 1/40 pixel under the ball.
    fn gouge_under(tip: &HeightMap, truth: impl Fn(f64, f64) -> f64, radius: f64) -> f64 {
        let d = tip.pixel_mm();
        let reach = (radius / d).ceil() as u32 + 1;
        let mut worst = 0.0f64;
        for j in 0..tip.height() {
            for i in reach..tip.width() - reach {
                let (cx, cy) = ((f64::from(i) + 0.5) * d, (f64::from(j) + 0.5) * d);
                let t = f64::from(tip.get(i, j).expect("cell"));
                let n = (radius / d * 40.0) as i64;
                for k in -n..=n {
                    let u = k as f64 * d / 40.0;
                    if u.abs() > radius {
                        continue;
                    }
                    // Profiles vary along x only: the ball's lowest point over each x is on y = cy.
                    let ball = t + radius - (radius * radius - u * u).sqrt();
                    worst = worst.max(truth(cx + u, cy) - ball);
                }
            }
        }
        worst
    }

    /// A flat top meeting a slope at a convex edge anywhere between two cell centres: the tool
    /// following the `Facet` reading never goes under the true surface by more than a ball dips
    /// between nodes half a pixel apart; `Point` cuts into the edge, and `Column` stands off the
    /// slope by the rise of half a pixel.
    #[test]
    fn a_convex_edge_between_samples_is_not_cut_and_a_slope_is_not_stood_off() {
        let d: f64 = 0.25;
        let radius = 1.5;
        let ball = ToolProfile::ball(2.0 * radius).expect("ball");
        // How far a ball drops (vertically) between two nodes half a pixel apart across a slope of
        // `deg`: the gap of (spacing along the slope)² / 8R along the normal, over cos.
        let dip_at = |deg: f64| (d / 2.0).powi(2) / (8.0 * radius * deg.to_radians().cos().powi(3)) + 1e-4;
        let (mut worst_point, mut worst_facet) = (0.0f64, 0.0f64);
        for k in 0..10 {
            for deg in [15.0f64, 30.0, 45.0, 60.0] {
                let dip = dip_at(deg);
                let edge = 3.0 + d * f64::from(k) / 10.0;
                let s = deg.to_radians().tan();
                let truth = move |x: f64, _y: f64| if x <= edge { 2.0 } else { 2.0 - s * (x - edge) };
                let map = map_of(24, 3, d, |x, y| truth(x, y) as f32);
                let opts = |m| CompensateOptions { pixel_model: m, outside_z_mm: Some(-10.0) };
                let facet = compensate(&map, &ball, &opts(PixelModel::Facet)).expect("facet");
                let point = compensate(&map, &ball, &opts(PixelModel::Point)).expect("point");
                let g = gouge_under(&facet, truth, radius);
                assert!(g <= dip, "edge at {edge}, {deg}°: facet cuts {g} mm");
                worst_facet = worst_facet.max(g);
                worst_point = worst_point.max(gouge_under(&point, truth, radius));
            }
        }
        assert!(worst_point > 0.03, "point: {worst_point}");
        assert!(worst_facet <= dip_at(60.0), "facet: {worst_facet}");
        let dip = dip_at(30.0);

        // On a 30° plane the facet tip is the point tip (both exact), the column tip stands off.
        let s = 30f64.to_radians().tan();
        let map = map_of(24, 24, d, |x, _| (s * x) as f32);
        let opts = |m| CompensateOptions { pixel_model: m, outside_z_mm: Some(-10.0) };
        let tips: Vec<HeightMap> = [PixelModel::Facet, PixelModel::Point, PixelModel::Column]
            .into_iter()
            .map(|m| compensate(&map, &ball, &opts(m)).expect("tip"))
            .collect();
        let (i, j) = (12, 12);
        let exact = s * (f64::from(i) + 0.5) * d + radius * ((1.0 + s * s).sqrt() - 1.0);
        let at = |t: &HeightMap| f64::from(t.get(i, j).expect("cell"));
        assert!((at(&tips[0]) - exact).abs() < dip, "facet {} vs {exact}", at(&tips[0]));
        assert!((at(&tips[1]) - exact).abs() < 4.0 * dip, "point {} vs {exact}", at(&tips[1]));
        assert!(at(&tips[2]) - exact > 0.05, "column {} vs {exact}", at(&tips[2]));
    }

    /// A step: the top's half cell beside it is flat, as a column, and a cell without data beside
    /// a sample takes the sample at the node between them.
    #[test]
    fn a_step_and_a_hole_extend_the_sample_half_a_pixel() {
        let d = 0.25;
        assert_eq!(mid_node(1.0, 1.0, -2.0, -2.0, d, STEEP), 1.0);
        assert_eq!(mid_node(-2.0, -2.0, 1.0, 1.0, d, STEEP), 1.0);
        assert_eq!(mid_node(1.0, 1.0, f32::NAN, 0.0, d, STEEP), 1.0);
        assert_eq!(mid_node(1.0, f32::NAN, 0.5, 0.0, d, STEEP), 0.5);
        assert!(mid_node(0.0, f32::NAN, f32::NAN, 0.0, d, STEEP).is_nan());
        // A step of 0.1 mm between flats (22° over the cell, not steep) is a step; one of 0.05 mm
        // (11°) reads as a slope: the chord. The same 0.1 mm rise on a 20° slope is the slope.
        assert_eq!(mid_node(1.0, 1.0, 0.9, 0.9, d, STEEP), 1.0);
        assert_eq!(mid_node(1.0, 1.0, 0.95, 0.95, d, STEEP), 0.975);
        assert_eq!(mid_node(1.09, 1.0, 0.9, 0.81, d, STEEP), 0.95);
    }
}
