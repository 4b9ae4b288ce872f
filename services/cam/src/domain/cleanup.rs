//! Path clean-up: Douglas–Peucker simplification, arc fitting and linking passes into one
//! sequence of [`Segment`]s for the G-code writer.
//!
//! Units: millimetres throughout (points, tolerances, radii). Angles are radians inside this
//! module only; nothing angular crosses the API.
//!
//! Tolerance budget of [`link`]: arcs are fitted to a pass's own points within `tol/2` (both
//! ways: points near the arc, arc near the polyline), and the stretches left straight are
//! simplified by Douglas–Peucker to `tol/2`, so every pass point is within `tol/2` of the emitted
//! path (the brief's order, simplify then fit, found almost no arcs: see [`link`]).

use nalgebra::{Point3, Vector2, Vector3};
use rayon::prelude::*;

use super::path::{Link, Segment, Toolpath};

/// Distance from `p` to the segment `a`–`b` (a point when `a == b`).
fn dist_to_segment(p: &Point3<f64>, a: &Point3<f64>, b: &Point3<f64>) -> f64 {
    let ab = b - a;
    let len2 = ab.norm_squared();
    if len2 <= 0.0 {
        return (p - a).norm();
    }
    let t = ((p - a).dot(&ab) / len2).clamp(0.0, 1.0);
    (p - (a + ab * t)).norm()
}

/// `a <= b`, false when either is NaN (so a NaN distance never passes a check).
fn within(a: f64, b: f64) -> bool {
    a <= b
}

/// A tolerance usable in comparisons: NaN and negatives become 0.
fn sane_tol(tol_mm: f64) -> f64 {
    if tol_mm > 0.0 { tol_mm } else { 0.0 }
}

/// Douglas–Peucker in 3D.
///
/// Algorithm: keep the first and last point; find the point of the span farthest from the chord
/// *segment* between the span's kept ends; if it is farther than `tol_mm`, keep it and recurse on
/// both halves (an explicit stack, so long passes cannot overflow the call stack). O(n log n)
/// typical, O(n²) worst case.
///
/// Guarantees: the output is a subsequence of the input (same order), it starts with the first
/// and ends with the last input point, and every dropped point is within `tol_mm` (mm) of the
/// output segment that spans it, hence of the simplified polyline. Fewer than 3 points are
/// returned unchanged. A negative or NaN tolerance acts as 0 (only exactly collinear points go).
pub fn simplify_3d(points: &[Point3<f64>], tol_mm: f64) -> Vec<Point3<f64>> {
    let n = points.len();
    if n < 3 {
        return points.to_vec();
    }
    let tol = sane_tol(tol_mm);
    let mut keep = vec![false; n];
    keep[0] = true;
    keep[n - 1] = true;
    let mut stack = vec![(0usize, n - 1)];
    while let Some((i, j)) = stack.pop() {
        if j <= i + 1 {
            continue;
        }
        let (a, b) = (&points[i], &points[j]);
        let mut worst = (i, -1.0f64);
        for (k, p) in points.iter().enumerate().take(j).skip(i + 1) {
            let d = dist_to_segment(p, a, b);
            // `!(d <= worst)` also catches NaN coordinates: such a point is kept.
            if d.is_nan() || d > worst.1 {
                worst = (k, d);
            }
        }
        if !within(worst.1, tol) {
            keep[worst.0] = true;
            stack.push((i, worst.0));
            stack.push((worst.0, j));
        }
    }
    points.iter().zip(&keep).filter(|(_, k)| **k).map(|(p, _)| *p).collect()
}

/// Largest radius fitted as an arc (mm); flatter runs stay linear.
const MAX_ARC_RADIUS_MM: f64 = 1000.0;
/// Smallest radius fitted as an arc whatever the tolerance (mm), so that I/J never round to 0.
const MIN_ARC_RADIUS_MM: f64 = 0.01;
/// Smallest XY distance between an arc's ends (mm): keeps a near-full circle from collapsing
/// into a full circle when the G-code writer rounds to 0.0001 mm.
const MIN_ARC_CHORD_MM: f64 = 0.002;
/// Largest angle between consecutive points of a fitted arc (rad): 90°.
const MAX_STEP_RAD: f64 = std::f64::consts::FRAC_PI_2;
/// Largest sweep of a fitted arc (rad): a little under 360°.
const MAX_SWEEP_RAD: f64 = std::f64::consts::TAU - 1e-3;

/// A circle (helix) accepted for a run of points.
#[derive(Debug, Clone, Copy)]
struct ArcFit {
    center: [f64; 2],
    clockwise: bool,
}

/// Helix through `run[0]` and `run[last]` with the centre on their XY bisector, Z linear in the
/// angle. Returns it when every point of the run is within `tol` of it and every piece of it
/// between consecutive points is within `tol` of the chord between them.
fn try_arc(run: &[Point3<f64>], tol: f64) -> Option<ArcFit> {
    let n = run.len();
    if n < 4 || tol <= 0.0 {
        return None;
    }
    let (s, e) = (run[0], run[n - 1]);
    let chord = Vector2::new(e.x - s.x, e.y - s.y);
    let c_len = chord.norm();
    if !within(MIN_ARC_CHORD_MM, c_len) {
        return None;
    }
    let m = Vector2::new((s.x + e.x) / 2.0, (s.y + e.y) / 2.0);
    let normal = Vector2::new(-chord.y, chord.x) / c_len;
    let h = c_len / 2.0;
    // Each interior point p on the circle centred at m + t·normal through s and e satisfies
    // 2(p-m)·normal · t = |p-m|² - h²: a one-parameter linear least-squares problem.
    let (mut saa, mut sab) = (0.0, 0.0);
    for p in &run[1..n - 1] {
        let q = Vector2::new(p.x, p.y) - m;
        let a = 2.0 * q.dot(&normal);
        let b = q.norm_squared() - h * h;
        saa += a * a;
        sab += a * b;
    }
    if saa.is_nan() || saa <= 1e-18 {
        return None;
    }
    let t = sab / saa;
    let c = m + normal * t;
    let r = (h * h + t * t).sqrt();
    if !(r <= MAX_ARC_RADIUS_MM && r >= (2.0 * tol).max(MIN_ARC_RADIUS_MM)) {
        return None;
    }
    let angle = |p: &Point3<f64>| (p.y - c.y).atan2(p.x - c.x);
    // Signed angular steps; all must turn the same way.
    let mut phis = Vec::with_capacity(n);
    phis.push(0.0);
    let mut dir = 0.0f64;
    let mut prev = angle(&s);
    for p in &run[1..] {
        let a = angle(p);
        let step = (a - prev + std::f64::consts::PI).rem_euclid(std::f64::consts::TAU) - std::f64::consts::PI;
        prev = a;
        if step.abs() > MAX_STEP_RAD {
            return None;
        }
        if dir == 0.0 && step.abs() > 1e-12 {
            dir = step.signum();
        }
        if step * dir < -1e-12 {
            return None;
        }
        phis.push(phis.last().copied().unwrap_or(0.0) + step.abs());
    }
    let sweep = phis[n - 1];
    if dir == 0.0 || !(sweep > 0.0 && sweep < MAX_SWEEP_RAD) {
        return None;
    }
    let a0 = angle(&s);
    let helix = |phi: f64| {
        let a = a0 + dir * phi;
        Point3::new(c.x + r * a.cos(), c.y + r * a.sin(), s.z + (e.z - s.z) * phi / sweep)
    };
    // Every point within tol of the helix point at its own angle (an upper bound of its distance).
    for (p, &phi) in run.iter().zip(&phis) {
        if !within((p - helix(phi)).norm(), tol) {
            return None;
        }
    }
    // Every piece of helix within tol of its chord: sampled densely enough that the helix between
    // samples is within `slack` of the straight line between them (distance to a segment is
    // convex along that line, so its maximum there is at a sample).
    let dz_dphi = (e.z - s.z) / sweep;
    let max_delta = (0.2 * tol / (r + dz_dphi.abs())).sqrt();
    for k in 1..n {
        let (p0, p1, f0, f1) = (&run[k - 1], &run[k], phis[k - 1], phis[k]);
        let samples = ((f1 - f0) / max_delta).ceil().max(1.0);
        if samples > 10_000.0 {
            return None;
        }
        let m_samples = samples as usize;
        let delta = (f1 - f0) / samples;
        let slack = (r + dz_dphi.abs()) * delta * delta / 4.0;
        for i in 1..m_samples {
            let q = helix(f0 + delta * i as f64);
            if !within(dist_to_segment(&q, p0, p1) + slack, tol) {
                return None;
            }
        }
    }
    Some(ArcFit { center: [c.x, c.y], clockwise: dir < 0.0 })
}

/// Arc fitting in XY (helices allowed: Z linear along the arc).
///
/// Algorithm: greedy from the start; at point `i` the run `i..=j` grows (4 points at least, by
/// doubling then bisection on `j`) while the arc check's checks hold: the circle passes through the
/// run's two ends with its centre fitted by least squares on the bisector of their XY chord (so
/// start and end radii are equal by construction), radius in `[max(2·tol, 0.01), 1000]` mm,
/// every angular step in the same direction and at most 90°, sweep below 360°, ends at least
/// 0.002 mm apart in XY. A run that fits becomes one [`Segment::Arc`] ending exactly at the run's
/// last input point; otherwise one [`Segment::Linear`] to the next point.
///
/// The path starts at `points[0]`, which is not emitted (the caller is already there); every
/// later point is. Guarantees (mm): every input point is within `tol_mm` of the output path and
/// every point of the output path is within `tol_mm` of the input polyline. A tolerance that is
/// not positive gives only Linear segments. Cost: O(n log n) arc checks, each linear in its run.
pub fn fit_arcs(points: &[Point3<f64>], tol_mm: f64) -> Vec<Segment> {
    let n = points.len();
    let tol = sane_tol(tol_mm);
    let mut out = Vec::new();
    let mut i = 0;
    while i + 1 < n {
        let fits = |j: usize| try_arc(&points[i..=j], tol);
        let mut best: Option<(usize, ArcFit)> = None;
        if i + 3 < n
            && let Some(f) = fits(i + 3)
        {
            let mut good = (i + 3, f);
            let mut step = 1;
            loop {
                let next = (good.0 + step).min(n - 1);
                if next == good.0 {
                    break;
                }
                match fits(next) {
                    Some(f) => {
                        good = (next, f);
                        step *= 2;
                    }
                    None => {
                        let (mut lo, mut hi) = (good, next);
                        while hi > lo.0 + 1 {
                            let mid = lo.0 + (hi - lo.0) / 2;
                            match fits(mid) {
                                Some(f) => lo = (mid, f),
                                None => hi = mid,
                            }
                        }
                        good = lo;
                        break;
                    }
                }
            }
            best = Some(good);
        }
        match best {
            Some((j, f)) => {
                out.push(Segment::Arc { end: points[j], center: f.center, clockwise: f.clockwise });
                i = j;
            }
            None => {
                out.push(Segment::Linear(points[i + 1]));
                i += 1;
            }
        }
    }
    out
}

/// Links a strategy's passes into one move sequence.
///
/// - Before the first pass: Rapid to (first.x, first.y, safe Z), Plunge to the pass start.
/// - [`Link::Retract`]: Rapid straight up to safe Z, Rapid across at safe Z, Plunge (plunge feed)
///   down to the pass start.
/// - [`Link::Direct`]: one Linear (cutting feed) to the pass start.
/// - The pass, when `arcs`: [`fit_arcs`] to `tol_mm/2` on the pass's own points, then every
///   stretch left Linear is simplified by [`simplify_3d`] to `tol_mm/2`; without `arcs`: simplified
///   to `tol_mm/2`, Linear moves through the kept points. Arcs are fitted before simplifying
///   because fitting to an already simplified polyline (whose chords cut inside a curve by up to
///   the whole DP tolerance) leaves almost no room for an arc that must stay near those chords.
///   Every pass point ends within `tol_mm/2` of the emitted path, and every arc within
///   `tol_mm/2` of the pass polyline.
/// - After the last pass: Rapid straight up to safe Z.
///
/// Moves to where the tool already is are left out; passes without points are skipped; no
/// passes give no segments. Units: mm; safe Z is the toolpath's `safe_z_mm`.
pub fn link(toolpath: &Toolpath, tol_mm: f64, arcs: bool) -> Vec<Segment> {
    let safe = toolpath.safe_z_mm;
    let half = sane_tol(tol_mm) / 2.0;
    let push = |out: &mut Vec<Segment>, pos: &mut Option<Point3<f64>>, seg: Segment| {
        if *pos != Some(seg.end()) || matches!(seg, Segment::Arc { .. }) {
            out.push(seg);
            *pos = Some(seg.end());
        }
    };
    // Every link into a pass ends at its first point, so each pass's own moves (arcs fitted, the
    // rest simplified) depend on that pass alone: made in parallel, joined in order.
    let bodies: Vec<Vec<Segment>> = toolpath
        .passes
        .par_iter()
        .map(|pass| {
            let mut out = Vec::new();
            let Some(&first) = pass.points.first() else { return out };
            let mut pos = Some(first);
            let linear_run = |out: &mut Vec<Segment>, pos: &mut Option<Point3<f64>>, run: &[Point3<f64>]| {
                for p in simplify_3d(run, half).iter().skip(1) {
                    push(out, pos, Segment::Linear(*p));
                }
            };
            if arcs {
                // Stretches of Linear segments (with the point they start from) are simplified.
                let mut run: Vec<Point3<f64>> = vec![first];
                for seg in fit_arcs(&pass.points, half) {
                    match seg {
                        Segment::Linear(p) => run.push(p),
                        _ => {
                            linear_run(&mut out, &mut pos, &run);
                            push(&mut out, &mut pos, seg);
                            run.clear();
                            run.push(seg.end());
                        }
                    }
                }
                linear_run(&mut out, &mut pos, &run);
            } else {
                linear_run(&mut out, &mut pos, &pass.points);
            }
            out
        })
        .collect();
    let mut out: Vec<Segment> = Vec::new();
    let mut pos: Option<Point3<f64>> = None;
    for (pass, body) in toolpath.passes.iter().zip(bodies) {
        let (Some(&first), Some(&last)) = (pass.points.first(), pass.points.last()) else {
            continue;
        };
        let above = Point3::new(first.x, first.y, safe);
        match (pos, pass.link) {
            (Some(_), Link::Direct) => push(&mut out, &mut pos, Segment::Linear(first)),
            (Some(p), Link::Retract) => {
                push(&mut out, &mut pos, Segment::Rapid(Point3::new(p.x, p.y, safe)));
                push(&mut out, &mut pos, Segment::Rapid(above));
                push(&mut out, &mut pos, Segment::Plunge(first));
            }
            (None, _) => {
                out.push(Segment::Rapid(above));
                pos = Some(above);
                push(&mut out, &mut pos, Segment::Plunge(first));
            }
        }
        out.extend(body);
        pos = Some(last);
    }
    if let Some(p) = pos {
        push(&mut out, &mut pos, Segment::Rapid(Point3::new(p.x, p.y, safe)));
    }
    out
}

/// `segments` with every rapid straight up out of a cut preceded by a feed move up by
/// `clearance_mm` (or to the rapid's height when that is lower): the tool leaves the material
/// at the cutting feed, so a sliver over its face left by the last cut is taken off cutting, not
/// by a rapid. Used for the rest pass, whose small tool engages little enough that such a sliver
/// is a large share of its face.
pub fn feed_retracts(segments: Vec<Segment>, clearance_mm: f64) -> Vec<Segment> {
    let mut out: Vec<Segment> = Vec::with_capacity(segments.len());
    for seg in segments {
        if let (Segment::Rapid(to), Some(prev)) = (seg, out.last())
            && matches!(prev, Segment::Linear(_) | Segment::Arc { .. } | Segment::Plunge(_))
        {
            let from = prev.end();
            if (to.x - from.x).abs() < 1e-9 && (to.y - from.y).abs() < 1e-9 && to.z > from.z {
                let z = (from.z + clearance_mm).min(to.z);
                if z < to.z {
                    out.push(Segment::Linear(Point3::new(from.x, from.y, z)));
                }
            }
        }
        out.push(seg);
    }
    out
}

/// Length (mm) of a move from `from`, and its unit tangents at start and end. Arcs sweep as the
/// G-code does: in their direction from the start angle to the end angle, a full turn when the
/// two coincide; the radius is the start's.
pub(crate) fn move_geometry(from: Point3<f64>, seg: &Segment) -> (f64, Vector3<f64>, Vector3<f64>) {
    match *seg {
        Segment::Rapid(to) | Segment::Linear(to) | Segment::Plunge(to) => {
            let d = to - from;
            let len = d.norm();
            let u = if len > 0.0 { d / len } else { Vector3::zeros() };
            (len, u, u)
        }
        Segment::Arc { end, center, clockwise } => {
            let (cx, cy) = (center[0], center[1]);
            let r = (from.x - cx).hypot(from.y - cy);
            let a0 = (from.y - cy).atan2(from.x - cx);
            let a1 = (end.y - cy).atan2(end.x - cx);
            let tau = std::f64::consts::TAU;
            let mut sweep = if clockwise { a0 - a1 } else { a1 - a0 }.rem_euclid(tau);
            if sweep < 1e-12 {
                sweep = tau;
            }
            let dz = end.z - from.z;
            let len = (sweep * r).hypot(dz);
            let s = if clockwise { -1.0 } else { 1.0 };
            let tangent = |a: f64| {
                let v = Vector3::new(-a.sin() * s * sweep * r, a.cos() * s * sweep * r, dz);
                let l = v.norm();
                if l > 0.0 { v / l } else { Vector3::zeros() }
            };
            (len, tangent(a0), tangent(a1))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::domain::path::Pass;
    use proptest::prelude::*;

    fn p(x: f64, y: f64, z: f64) -> Point3<f64> {
        Point3::new(x, y, z)
    }

    /// Dense samples of a segment sequence starting at `start` (reference for the checks).
    fn sample_path(start: Point3<f64>, segs: &[Segment], step: f64) -> Vec<Point3<f64>> {
        let mut out = vec![start];
        let mut from = start;
        for seg in segs {
            let (len, _, _) = move_geometry(from, seg);
            let k = (len / step).ceil().max(1.0) as usize;
            match *seg {
                Segment::Arc { end, center, clockwise } => {
                    let r = (from.x - center[0]).hypot(from.y - center[1]);
                    let a0 = (from.y - center[1]).atan2(from.x - center[0]);
                    let a1 = (end.y - center[1]).atan2(end.x - center[0]);
                    let mut sw = if clockwise { a0 - a1 } else { a1 - a0 }.rem_euclid(std::f64::consts::TAU);
                    if sw < 1e-12 {
                        sw = std::f64::consts::TAU;
                    }
                    for i in 1..=k {
                        let t = i as f64 / k as f64;
                        let a = if clockwise { a0 - sw * t } else { a0 + sw * t };
                        out.push(p(
                            center[0] + r * a.cos(),
                            center[1] + r * a.sin(),
                            from.z + (end.z - from.z) * t,
                        ));
                    }
                }
                _ => {
                    let to = seg.end();
                    for i in 1..=k {
                        out.push(from + (to - from) * (i as f64 / k as f64));
                    }
                }
            }
            from = seg.end();
        }
        out
    }

    fn dist_to_polyline(q: &Point3<f64>, poly: &[Point3<f64>]) -> f64 {
        if poly.len() == 1 {
            return (q - poly[0]).norm();
        }
        poly.windows(2).map(|w| dist_to_segment(q, &w[0], &w[1])).fold(f64::INFINITY, f64::min)
    }

    /// Both-way check: inputs near the output and output near the input polyline.
    fn assert_within(points: &[Point3<f64>], segs: &[Segment], tol: f64) {
        // Samples 0.05 mm apart: the dense polyline is within step²/(8·r) < 2e-4 mm of the path
        // (r >= 2 mm), and the check between samples is left to the sample spacing.
        let step = 0.05;
        let dense = sample_path(points[0], segs, step);
        for (k, q) in points.iter().enumerate() {
            let d = dist_to_polyline(q, &dense);
            assert!(d <= tol + 2e-4, "input point {k} {q:?} is {d} from the output (tol {tol})");
        }
        for q in &dense {
            let d = dist_to_polyline(q, points);
            assert!(d <= tol + 1e-9, "output point {q:?} is {d} from the input (tol {tol})");
        }
    }

    #[test]
    fn simplify_keeps_corners_and_drops_collinear_points() {
        let pts: Vec<_> =
            (0..=10).map(|i| p(i as f64, 0.0, 0.0)).chain((1..=5).map(|i| p(10.0, i as f64, 0.0))).collect();
        assert_eq!(simplify_3d(&pts, 0.01), vec![p(0.0, 0.0, 0.0), p(10.0, 0.0, 0.0), p(10.0, 5.0, 0.0)]);
        assert_eq!(simplify_3d(&pts[..2], 0.01), pts[..2].to_vec());
        assert!(simplify_3d(&[], 0.01).is_empty());
        // A closed loop keeps both (equal) ends and its far points.
        let square =
            [p(0.0, 0.0, 0.0), p(1.0, 0.0, 0.0), p(1.0, 1.0, 0.0), p(0.0, 1.0, 0.0), p(0.0, 0.0, 0.0)];
        assert_eq!(simplify_3d(&square, 0.1).len(), 5);
    }

    proptest! {
        #[test]
        fn simplify_keeps_ends_and_tolerance(
            raw in prop::collection::vec((-20.0f64..20.0, -20.0f64..20.0, -5.0f64..5.0), 0..60),
            tol in 0.0f64..2.0,
            smooth in any::<bool>(),
        ) {
            // Either random points or a gently wiggling line (where DP drops a lot).
            let pts: Vec<_> = raw.iter().enumerate().map(|(i, &(x, y, z))| if smooth {
                p(i as f64, y * 0.05, z * 0.05 + x * 0.01)
            } else {
                p(x, y, z)
            }).collect();
            let out = simplify_3d(&pts, tol);
            if pts.is_empty() {
                prop_assert!(out.is_empty());
                return Ok(());
            }
            prop_assert_eq!(out[0], pts[0]);
            prop_assert_eq!(out[out.len() - 1], pts[pts.len() - 1]);
            // Subsequence, and each dropped point within tol of the segment spanning it
            // (brute force: scan every point, track which kept points bracket it).
            let mut k = 0;
            let mut idx = Vec::new();
            for (i, q) in pts.iter().enumerate() {
                if k < out.len() && *q == out[k] && (k > 0 || i == 0) {
                    idx.push(i);
                    k += 1;
                }
            }
            prop_assert_eq!(k, out.len(), "output is not a subsequence");
            for w in idx.windows(2) {
                for q in &pts[w[0] + 1..w[1]] {
                    let d = dist_to_segment(q, &pts[w[0]], &pts[w[1]]);
                    prop_assert!(d <= tol + 1e-12, "dropped {:?} at {} > {}", q, d, tol);
                    prop_assert!(dist_to_polyline(q, &out) <= tol + 1e-12);
                }
            }
        }
    }

    fn circle(c: [f64; 2], r: f64, a0: f64, sweep: f64, n: usize, z0: f64, dz: f64) -> Vec<Point3<f64>> {
        (0..n)
            .map(|i| {
                let t = i as f64 / (n - 1) as f64;
                let a = a0 + sweep * t;
                p(c[0] + r * a.cos(), c[1] + r * a.sin(), z0 + dz * t)
            })
            .collect()
    }

    #[test]
    fn exact_circle_becomes_one_arc() {
        let pts = circle([5.0, -3.0], 10.0, 0.3, 2.0, 40, 1.0, 0.0);
        let segs = fit_arcs(&pts, 0.01);
        assert_eq!(segs.len(), 1, "{segs:?}");
        match segs[0] {
            Segment::Arc { end, center, clockwise } => {
                assert_eq!(end, pts[39]);
                assert!(!clockwise);
                assert!((center[0] - 5.0).abs() < 1e-9 && (center[1] + 3.0).abs() < 1e-9, "{center:?}");
            }
            other => panic!("{other:?}"),
        }
        // Clockwise helix.
        let pts = circle([0.0, 0.0], 4.0, 1.0, -3.0, 30, 0.0, -2.0);
        let segs = fit_arcs(&pts, 0.01);
        assert_eq!(segs.len(), 1, "{segs:?}");
        assert!(matches!(segs[0], Segment::Arc { clockwise: true, .. }));
        assert_within(&pts, &segs, 0.01);
    }

    #[test]
    fn lines_corners_and_full_circles() {
        let line: Vec<_> = (0..10).map(|i| p(i as f64, 2.0 * i as f64, 0.0)).collect();
        assert!(fit_arcs(&line, 0.01).iter().all(|s| matches!(s, Segment::Linear(_))));
        assert_eq!(fit_arcs(&line, 0.01).len(), 9);
        // A full circle (last point = first) needs two arcs: an arc must sweep < 360°.
        let pts = circle([0.0, 0.0], 5.0, 0.0, std::f64::consts::TAU, 73, 0.0, 0.0);
        let segs = fit_arcs(&pts, 0.01);
        assert!(segs.len() >= 2 && segs.len() <= 3, "{segs:?}");
        assert_within(&pts, &segs, 0.01);
        // Too few points: 3 points stay linear.
        let pts = circle([0.0, 0.0], 5.0, 0.0, 1.0, 3, 0.0, 0.0);
        assert_eq!(fit_arcs(&pts, 0.01).len(), 2);
        // Radius too large for the limit: a gentle curve of r = 5000 stays linear.
        let pts = circle([0.0, -5000.0], 5000.0, std::f64::consts::FRAC_PI_2, 0.002, 10, 0.0, 0.0);
        assert!(fit_arcs(&pts, 0.01).iter().all(|s| matches!(s, Segment::Linear(_))));
        assert!(fit_arcs(&[], 0.01).is_empty() && fit_arcs(&[p(0.0, 0.0, 0.0)], 0.01).is_empty());
    }

    /// Points on a circle (helix) dense enough that chords sag at most `sag` mm, with radial and
    /// axial noise of at most `noise` mm each.
    #[allow(clippy::too_many_arguments)]
    fn noisy_circle(
        c: [f64; 2],
        r: f64,
        a0: f64,
        sweep: f64,
        dz: f64,
        sag: f64,
        noise: f64,
        unit: &[(f64, f64)],
    ) -> Vec<Point3<f64>> {
        let step = (8.0 * sag / r).sqrt();
        let n = ((sweep.abs() / step).ceil() as usize + 1).clamp(5, 400);
        let mut pts = circle(c, r, a0, sweep, n, 0.0, dz);
        for (q, (nr, nz)) in pts.iter_mut().zip(unit.iter().cycle()) {
            let d = Vector2::new(q.x - c[0], q.y - c[1]).normalize() * (nr * noise);
            q.x += d.x;
            q.y += d.y;
            q.z += nz * noise;
        }
        pts
    }

    proptest! {
        #![proptest_config(ProptestConfig { cases: 40, ..ProptestConfig::default() })]
        #[test]
        fn arcs_recover_noisy_circles_within_tolerance(
            cx in -50.0f64..50.0, cy in -50.0f64..50.0, r in 2.0f64..30.0,
            a0 in -3.2f64..3.2, sweep in 0.4f64..6.2, ccw in any::<bool>(), dz in -3.0f64..3.0,
            tol in 0.005f64..0.05,
            unit in prop::collection::vec((-1.0f64..1.0, -1.0f64..1.0), 1..64),
            prefix in 0usize..4,
        ) {
            let sweep = if ccw { sweep } else { -sweep };
            // Noise below tol/4 per axis, chord sag below tol/4: the circle must be found.
            let pts = noisy_circle([cx, cy], r, a0, sweep, dz, tol / 4.0, tol / 4.0, &unit);
            let n = pts.len();
            // Sometimes straight lines before the arc.
            let mut all: Vec<_> = (0..prefix).rev().map(|i| pts[0] + Vector3::new(0.0, 0.0, 1.0 + i as f64)).collect();
            all.extend(pts);
            let segs = fit_arcs(&all, tol);
            assert_within(&all, &segs, tol);
            let arcs = segs.iter().filter(|s| matches!(s, Segment::Arc { .. })).count();
            prop_assert!(arcs >= 1, "no arc in {:?}", segs);
            prop_assert!(segs.len() <= prefix + n / 3 + 2, "{} segments for {} points", segs.len(), n);
        }

        #[test]
        fn arcs_stay_within_tolerance_of_very_noisy_circles(
            r in 2.0f64..30.0, a0 in -3.2f64..3.2, sweep in -6.2f64..6.2, dz in -3.0f64..3.0,
            tol in 0.005f64..0.05, sag in 0.0f64..2.0, noise in 0.0f64..0.7,
            unit in prop::collection::vec((-1.0f64..1.0, -1.0f64..1.0), 1..64),
        ) {
            // Noise up to 0.7·tol per axis (|noise| < tol), chords up to 2·tol from the circle:
            // arcs or not, the guarantee holds.
            let pts = noisy_circle([1.0, 2.0], r, a0, sweep, dz, sag * tol, noise * tol, &unit);
            assert_within(&pts, &fit_arcs(&pts, tol), tol);
        }
    }

    #[test]
    fn fitting_a_dense_circle_is_fast() {
        let pts = circle([0.0, 0.0], 30.0, 0.0, 6.0, 4000, 0.0, 1.0);
        let t = std::time::Instant::now();
        let segs = fit_arcs(&pts, 0.005);
        eprintln!("fit_arcs: 4000 points -> {} segments in {:?}", segs.len(), t.elapsed());
        assert!(segs.len() <= 3);
    }

    #[test]
    fn link_builds_rapids_plunges_and_direct_moves() {
        let tp = Toolpath {
            strategy: "finishing-raster-x".into(),
            tool: "ball-3".into(),
            passes: vec![
                Pass {
                    link: Link::Retract,
                    points: vec![p(0.0, 0.0, 1.0), p(1.0, 0.0, 1.0), p(2.0, 0.0, 1.0)],
                },
                Pass { link: Link::Direct, points: vec![p(2.0, 1.0, 1.0), p(0.0, 1.0, 1.5)] },
                Pass { link: Link::Retract, points: vec![p(5.0, 5.0, 0.5), p(6.0, 5.0, 0.5)] },
                Pass { link: Link::Retract, points: vec![] },
            ],
            safe_z_mm: 10.0,
        };
        let segs = link(&tp, 0.01, true);
        use Segment::*;
        assert_eq!(
            segs,
            vec![
                Rapid(p(0.0, 0.0, 10.0)),
                Plunge(p(0.0, 0.0, 1.0)),
                Linear(p(2.0, 0.0, 1.0)),
                Linear(p(2.0, 1.0, 1.0)),
                Linear(p(0.0, 1.0, 1.5)),
                Rapid(p(0.0, 1.0, 10.0)),
                Rapid(p(5.0, 5.0, 10.0)),
                Plunge(p(5.0, 5.0, 0.5)),
                Linear(p(6.0, 5.0, 0.5)),
                Rapid(p(6.0, 5.0, 10.0)),
            ]
        );
        assert!(link(&Toolpath { passes: vec![], ..tp.clone() }, 0.01, true).is_empty());
    }

    #[test]
    fn link_stays_within_tolerance_with_arcs() {
        let pts = circle([10.0, 10.0], 8.0, 0.0, 4.0, 400, 2.0, 0.0);
        let tp = Toolpath {
            strategy: "finishing-iso-level".into(),
            tool: "ball-3".into(),
            passes: vec![Pass { link: Link::Retract, points: pts.clone() }],
            safe_z_mm: 10.0,
        };
        let segs = link(&tp, 0.01, true);
        assert!(segs.len() <= 5, "{segs:?}");
        // The cutting part (after the plunge, before the final rapid).
        let cut = &segs[2..segs.len() - 1];
        assert_within(&pts, cut, 0.01);
        let lin = link(&tp, 0.01, false);
        assert!(lin.iter().all(|s| !matches!(s, Segment::Arc { .. })));
        assert_within(&pts, &lin[2..lin.len() - 1], 0.01);
    }

    #[test]
    fn feed_retracts_go_before_rapids_straight_up_out_of_a_cut() {
        let p = |x: f64, y: f64, z: f64| Point3::new(x, y, z);
        let segs = vec![
            Segment::Rapid(p(0.0, 0.0, 10.0)),
            Segment::Plunge(p(0.0, 0.0, 1.0)),
            Segment::Linear(p(2.0, 0.0, 1.0)),
            Segment::Rapid(p(2.0, 0.0, 10.0)),
            Segment::Rapid(p(5.0, 0.0, 10.0)),
            Segment::Plunge(p(5.0, 0.0, 9.5)),
            Segment::Rapid(p(5.0, 0.0, 10.0)),
        ];
        let out = feed_retracts(segs, 1.0);
        assert_eq!(
            out,
            vec![
                Segment::Rapid(p(0.0, 0.0, 10.0)),
                Segment::Plunge(p(0.0, 0.0, 1.0)),
                Segment::Linear(p(2.0, 0.0, 1.0)),
                Segment::Linear(p(2.0, 0.0, 2.0)),
                Segment::Rapid(p(2.0, 0.0, 10.0)),
                Segment::Rapid(p(5.0, 0.0, 10.0)),
                Segment::Plunge(p(5.0, 0.0, 9.5)),
                // Less than the clearance to go: the rapid stays as it was.
                Segment::Rapid(p(5.0, 0.0, 10.0)),
            ]
        );
    }
}
