//! Passes of one layer of a sliced part (seed 001): the tool-centre rings that take the layer's
//! material off from the stock boundary in to the part, pass by pass at a radial depth.
//!
//! The part's section `P` (a [`Layer`]'s contours: outer boundaries counter-clockwise, holes
//! clockwise) is offset outward by `d_k = r + k·a_e` for `k = K, …, 1, 0` (`r` the tool radius,
//! `a_e` the radial depth of cut): ring `k` is where the tool centre runs to take material from
//! `d_k − r` to `d_k + r` off the part; ring 0 is the finishing contour, the tool touching the
//! part. `K` is the smallest count whose outermost ring reaches the stock's farthest corner
//! (`d_K + r >= D`, `D` the largest distance from the part to a stock corner). Each ring is kept
//! only where it passes over stock (within `r` of the stock rectangle): the parts in the air are
//! cut out, leaving open pieces.
//!
//! Offsetting is i_overlay's (round joins, the arc tolerance given): against clipper2-rust, the
//! other pure-Rust offsetter considered, it is 12-15x faster on many contours in one call, exact
//! to 1e-9 mm inward where clipper2-rust's port rounds to its 1e-6 grid, and scales linearly where
//! the port took 38 s for 10 000 contours (`cargo bench -p depthmill-cam --bench offset`).
//!
//! Holes of the part the tool cannot enter (narrower than its diameter, so ring 0 has no hole
//! inside them) are reported with where they are, not silently skipped.

use i_overlay::mesh::float::outline::offset::OutlineOffset;
use i_overlay::mesh::float::style::{LineJoin, OutlineStyle};

use super::slice::{ContourKind, Layer};

/// A 2-D polyline (or closed loop), mm.
pub type Polyline2 = Vec<[f64; 2]>;

/// Most rings of one layer.
pub const MAX_RINGS: usize = 10_000;

/// Why a layer's passes could not be planned.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum PassError {
    #[error("{field} {value}: {reason}")]
    Invalid { field: &'static str, value: f64, reason: String },
}

/// What a layer is cut with, and from.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct PassOptions {
    pub tool_radius_mm: f64,
    /// Radial depth of cut between rings, at most the tool's diameter.
    pub radial_depth_mm: f64,
    /// Largest chord error of the rings' round corners.
    pub arc_tolerance_mm: f64,
    /// The stock's rectangle in the layer's plane: `[x_min, y_min, x_max, y_max]`.
    pub stock: [f64; 4],
}

/// One ring: where the tool centre runs at `offset_mm` from the part.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Ring {
    pub offset_mm: f64,
    /// Closed loops (the last point joins the first) where the whole ring passes over stock.
    pub loops: Vec<Vec<[f64; 2]>>,
    /// Open pieces where the ring was cut to the stock.
    pub pieces: Vec<Vec<[f64; 2]>>,
}

/// A hole of the part the tool does not enter.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Unreached {
    /// A point inside the hole and the hole's area.
    pub at: [f64; 2],
    pub area_mm2: f64,
}

/// A layer's rings, outermost first (the last is the finishing contour).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct LayerPasses {
    pub z_mm: f64,
    pub rings: Vec<Ring>,
    pub unreached: Vec<Unreached>,
}

fn invalid(field: &'static str, value: f64, reason: impl Into<String>) -> PassError {
    PassError::Invalid { field, value, reason: reason.into() }
}

/// The part's section offset outward by `d` (round joins within `tol`): oriented contours,
/// outer boundaries counter-clockwise.
pub fn offset(contours: &[Vec<[f64; 2]>], d: f64, tol: f64) -> Vec<Vec<[f64; 2]>> {
    if contours.is_empty() {
        return Vec::new();
    }
    if d <= 0.0 {
        return contours.to_vec();
    }
    // The chord angle whose sagitta is `tol` on an arc of radius `d`.
    let angle = 2.0 * (1.0 - (tol / d).min(1.0)).acos();
    let style = OutlineStyle::new(d).line_join(LineJoin::Round(angle.max(1e-3)));
    contours.to_vec().outline_as::<i64>(&style).into_iter().flatten().collect()
}

fn area(p: &[[f64; 2]]) -> f64 {
    let n = p.len();
    0.5 * (0..n).map(|i| p[i][0] * p[(i + 1) % n][1] - p[(i + 1) % n][0] * p[i][1]).sum::<f64>()
}

fn contains(p: &[[f64; 2]], q: [f64; 2]) -> bool {
    let mut inside = false;
    let n = p.len();
    let mut j = n - 1;
    for i in 0..n {
        let (a, b) = (p[i], p[j]);
        if (a[1] > q[1]) != (b[1] > q[1]) && q[0] < a[0] + (q[1] - a[1]) / (b[1] - a[1]) * (b[0] - a[0]) {
            inside = !inside;
        }
        j = i;
    }
    inside
}

/// Distance from `q` to the nearest edge of any of `contours`.
pub fn distance_to(contours: &[Vec<[f64; 2]>], q: [f64; 2]) -> f64 {
    contours
        .iter()
        .flat_map(|c| (0..c.len()).map(move |i| (c[i], c[(i + 1) % c.len()])))
        .map(|(a, b)| {
            let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
            let l2 = dx * dx + dy * dy;
            let t =
                if l2 > 0.0 { (((q[0] - a[0]) * dx + (q[1] - a[1]) * dy) / l2).clamp(0.0, 1.0) } else { 0.0 };
            (q[0] - a[0] - t * dx).hypot(q[1] - a[1] - t * dy)
        })
        .fold(f64::INFINITY, f64::min)
}

/// The pieces of the closed loop `ring` inside the rectangle `[x0, y0, x1, y1]`: the loop itself
/// when it stays inside, else its open runs inside (segments clipped at the border).
fn clip_loop(ring: &[[f64; 2]], b: [f64; 4]) -> (Option<Polyline2>, Vec<Polyline2>) {
    let inside = |p: [f64; 2]| p[0] >= b[0] && p[0] <= b[2] && p[1] >= b[1] && p[1] <= b[3];
    if ring.iter().all(|&p| inside(p)) {
        return (Some(ring.to_vec()), Vec::new());
    }
    // Liang–Barsky on each edge, starting at a vertex outside so runs do not wrap.
    let n = ring.len();
    let start = (0..n).find(|&i| !inside(ring[i])).unwrap_or(0);
    let mut pieces: Vec<Vec<[f64; 2]>> = Vec::new();
    let mut cur: Vec<[f64; 2]> = Vec::new();
    for k in 0..n {
        let (a, c) = (ring[(start + k) % n], ring[(start + k + 1) % n]);
        let (dx, dy) = (c[0] - a[0], c[1] - a[1]);
        let (mut t0, mut t1) = (0.0f64, 1.0f64);
        let mut keep = true;
        for (p, q) in [(-dx, a[0] - b[0]), (dx, b[2] - a[0]), (-dy, a[1] - b[1]), (dy, b[3] - a[1])] {
            if p == 0.0 {
                if q < 0.0 {
                    keep = false;
                }
            } else {
                let t = q / p;
                if p < 0.0 {
                    t0 = t0.max(t);
                } else {
                    t1 = t1.min(t);
                }
            }
        }
        if !keep || t0 > t1 {
            if cur.len() >= 2 {
                pieces.push(std::mem::take(&mut cur));
            }
            cur.clear();
            continue;
        }
        let p0 = [a[0] + t0 * dx, a[1] + t0 * dy];
        let p1 = [a[0] + t1 * dx, a[1] + t1 * dy];
        if cur.last() != Some(&p0) {
            if cur.len() >= 2 {
                pieces.push(std::mem::take(&mut cur));
            }
            cur.clear();
            cur.push(p0);
        }
        cur.push(p1);
        if t1 < 1.0 {
            pieces.push(std::mem::take(&mut cur));
        }
    }
    if cur.len() >= 2 {
        pieces.push(cur);
    }
    (None, pieces)
}

/// The rings of `layer`. See the module docs.
///
/// Errors: a tool radius, radial depth (at most the diameter) or tolerance that is not a
/// positive finite number, a stock rectangle that is empty or not finite, more than
/// [`MAX_RINGS`] rings.
pub fn layer_passes(layer: &Layer, o: &PassOptions) -> Result<LayerPasses, PassError> {
    let r = o.tool_radius_mm;
    if !(r.is_finite() && r > 0.0) {
        return Err(invalid("tool_radius_mm", r, "must be a positive number of millimetres"));
    }
    let ae = o.radial_depth_mm;
    if !(ae.is_finite() && ae > 0.0 && ae <= 2.0 * r) {
        return Err(invalid(
            "radial_depth_mm",
            ae,
            format!("must be in (0, {}] (the tool's diameter)", 2.0 * r),
        ));
    }
    let tol = o.arc_tolerance_mm;
    if !(tol.is_finite() && tol > 0.0 && tol < r) {
        return Err(invalid("arc_tolerance_mm", tol, format!("must be in (0, {r}) mm")));
    }
    let s = o.stock;
    if !(s.iter().all(|v| v.is_finite()) && s[0] < s[2] && s[1] < s[3]) {
        return Err(invalid("stock", s[0], format!("{s:?}: need x_min < x_max and y_min < y_max, finite")));
    }
    let part: Vec<Vec<[f64; 2]>> = layer.contours.iter().map(|c| c.points.clone()).collect();
    // The farthest stock corner from the part (a corner inside the part is 0 away).
    let corners = [[s[0], s[1]], [s[2], s[1]], [s[2], s[3]], [s[0], s[3]]];
    let far = corners
        .iter()
        .map(|&c| {
            let inside = layer.contours.iter().filter(|k| contains(&k.points, c)).count() % 2 == 1;
            if inside || part.is_empty() { 0.0 } else { distance_to(&part, c) }
        })
        .fold(0.0, f64::max);
    let count = if part.is_empty() { 0.0 } else { ((far - 2.0 * r) / ae).ceil().max(0.0) };
    if count >= MAX_RINGS as f64 {
        return Err(invalid(
            "radial_depth_mm",
            ae,
            format!("{count:.0} rings to reach the stock's corner {far:.3} mm away: more than {MAX_RINGS}"),
        ));
    }
    let grown = [s[0] - r, s[1] - r, s[2] + r, s[3] + r];
    let mut rings = Vec::new();
    for k in (0..=count as usize).rev() {
        if part.is_empty() {
            break;
        }
        let d = r + k as f64 * ae;
        let mut ring = Ring { offset_mm: d, loops: Vec::new(), pieces: Vec::new() };
        for lp in offset(&part, d, tol) {
            let (whole, pieces) = clip_loop(&lp, grown);
            ring.loops.extend(whole);
            ring.pieces.extend(pieces);
        }
        if !ring.loops.is_empty() || !ring.pieces.is_empty() {
            rings.push(ring);
        }
    }
    // Holes of the part with no hole of the finishing contour inside them.
    let finish = offset(&part, r, tol);
    let unreached = layer
        .contours
        .iter()
        .filter(|c| c.kind == ContourKind::Hole)
        .filter(|h| {
            !finish.iter().any(|f| area(f) < 0.0 && f.first().is_some_and(|&q| contains(&h.points, q)))
        })
        .map(|h| {
            let n = h.points.len() as f64;
            let c = h.points.iter().fold([0.0, 0.0], |a, p| [a[0] + p[0] / n, a[1] + p[1] / n]);
            Unreached { at: c, area_mm2: h.area_mm2.abs() }
        })
        .collect();
    Ok(LayerPasses { z_mm: layer.z_mm, rings, unreached })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::domain::slice::Contour;
    use proptest::prelude::*;

    fn layer(contours: Vec<Vec<[f64; 2]>>) -> Layer {
        let contours = contours
            .into_iter()
            .map(|p| {
                let a = area(&p);
                Contour {
                    points: p,
                    area_mm2: a,
                    kind: if a > 0.0 { ContourKind::Outer } else { ContourKind::Hole },
                    depth: u32::from(a < 0.0),
                    parent: None,
                }
            })
            .collect();
        Layer { z_mm: 1.0, contours, open: Vec::new(), defects: Vec::new() }
    }

    fn square(x0: f64, y0: f64, w: f64, ccw: bool) -> Vec<[f64; 2]> {
        let mut p = vec![[x0, y0], [x0 + w, y0], [x0 + w, y0 + w], [x0, y0 + w]];
        if !ccw {
            p.reverse();
        }
        p
    }

    fn opts(r: f64, ae: f64, stock: [f64; 4]) -> PassOptions {
        PassOptions { tool_radius_mm: r, radial_depth_mm: ae, arc_tolerance_mm: 0.005, stock }
    }

    #[test]
    fn a_square_in_its_stock_gets_rings_out_to_the_corners() {
        let l = layer(vec![square(0.0, 0.0, 10.0, true)]);
        let p = layer_passes(&l, &opts(1.0, 1.5, [-10.0, -10.0, 20.0, 20.0])).expect("passes");
        // The farthest corner is 14.14 mm from the part: rings at 1 + 1.5 k, k = 9..0.
        assert_eq!(p.rings.len(), 10);
        assert!((p.rings[0].offset_mm - 14.5).abs() < 1e-12 && (p.rings[9].offset_mm - 1.0).abs() < 1e-12);
        // The finishing ring: the square grown by 1 with round corners.
        let fin = &p.rings[9];
        assert_eq!((fin.loops.len(), fin.pieces.len()), (1, 0));
        let a = area(&fin.loops[0]);
        let want = 12.0 * 12.0 - (4.0 - std::f64::consts::PI);
        // The corners' arcs are chords within 0.005 mm: at most 2π·r·0.005 less area.
        assert!(a <= want + 1e-9 && want - a <= std::f64::consts::TAU * 0.005, "{a} vs {want}");
        // Outer rings leave the stock (grown by the radius) and are cut into pieces.
        assert!(p.rings[0].loops.is_empty() && !p.rings[0].pieces.is_empty());
        for piece in &p.rings[0].pieces {
            assert!(piece.iter().all(|q| q[0] >= -11.0 - 1e-9 && q[0] <= 21.0 + 1e-9));
        }
        assert!(p.unreached.is_empty());
    }

    #[test]
    fn a_hole_narrower_than_the_tool_is_reported_and_a_wide_one_is_cut() {
        let l = layer(vec![
            square(0.0, 0.0, 30.0, true),
            square(5.0, 5.0, 1.5, false), // 1.5 mm wide: a 2 mm tool cannot enter
            square(15.0, 15.0, 10.0, false), // 10 mm wide
        ]);
        let p = layer_passes(&l, &opts(1.0, 1.0, [-2.0, -2.0, 32.0, 32.0])).expect("passes");
        assert_eq!(p.unreached.len(), 1, "{:?}", p.unreached);
        assert!((p.unreached[0].at[0] - 5.75).abs() < 1e-9 && (p.unreached[0].area_mm2 - 2.25).abs() < 1e-9);
        let fin = p.rings.last().expect("finishing ring");
        // The outer loop and the wide hole's loop (8 x 8 inside it).
        assert_eq!(fin.loops.len(), 2);
        let hole = fin.loops.iter().find(|l| area(l) < 0.0).expect("hole loop");
        assert!((area(hole) + 64.0).abs() < 1e-6, "{}", area(hole));
    }

    #[test]
    fn bad_options_are_refused_with_the_field() {
        let l = layer(vec![square(0.0, 0.0, 10.0, true)]);
        let s = [-5.0, -5.0, 15.0, 15.0];
        let e = layer_passes(&l, &opts(0.0, 1.0, s)).expect_err("radius");
        assert!(e.to_string().starts_with("tool_radius_mm 0"), "{e}");
        let e = layer_passes(&l, &opts(1.0, 2.5, s)).expect_err("depth");
        assert!(e.to_string().contains("radial_depth_mm 2.5: must be in (0, 2]"), "{e}");
        assert!(layer_passes(&l, &opts(1.0, 1.0, [5.0, 0.0, 1.0, 10.0])).is_err());
        let e = layer_passes(&l, &opts(1.0, 1e-6, [-1e6, -1e6, 1e6, 1e6])).expect_err("rings");
        assert!(e.to_string().contains("more than 10000"), "{e}");
    }

    proptest! {
        #![proptest_config(ProptestConfig { cases: 32, ..ProptestConfig::default() })]

        /// Random star-shaped parts: every vertex of every ring is at the ring's offset from the
        /// part (within the arc tolerance, by brute force over the part's edges), outside it.
        #[test]
        fn ring_vertices_lie_at_their_offset_from_the_part(
            radii in proptest::collection::vec(2.0f64..6.0, 5..24),
            r in 0.5f64..2.0,
            ae_frac in 0.3f64..1.0,
        ) {
            let n = radii.len();
            let star: Vec<[f64; 2]> = radii
                .iter()
                .enumerate()
                .map(|(i, &rho)| {
                    let a = std::f64::consts::TAU * i as f64 / n as f64;
                    [rho * a.cos(), rho * a.sin()]
                })
                .collect();
            let part = vec![star.clone()];
            let l = layer(part.clone());
            let o = PassOptions { tool_radius_mm: r, radial_depth_mm: 2.0 * r * ae_frac, arc_tolerance_mm: 0.005, stock: [-8.0, -8.0, 8.0, 8.0] };
            let p = layer_passes(&l, &o).expect("passes");
            prop_assert!(!p.rings.is_empty());
            prop_assert!((p.rings.last().expect("ring").offset_mm - r).abs() < 1e-12);
            for ring in &p.rings {
                for q in ring.loops.iter().chain(&ring.pieces).flatten() {
                    let border = q[0].abs() >= 8.0 + r - 1e-9 || q[1].abs() >= 8.0 + r - 1e-9;
                    let d = distance_to(&part, *q);
                    // Clipped ends on the stock's border lie on the ring too.
                    prop_assert!((d - ring.offset_mm).abs() < 0.005 + 1e-6 || border && d >= ring.offset_mm - 0.006,
                        "offset {} vertex {:?} at {}", ring.offset_mm, q, d);
                    prop_assert!(!contains(&star, *q));
                }
            }
        }
    }
}
