//! The part several 3-axis cuts leave, each from above in its own face's view, seen from one face.
//!
//! A program cut at A = `a` from above removes everything over the surface its tools sweep, in
//! that face's frame: what is left is the set of points below that surface (a height map on the
//! face's grid) and within the grid's sides. Several faces cut on one stock leave the
//! intersection of those sets. Seen from face `v`, each cell's height is the first point of that
//! intersection on the vertical through the cell centre, from the face's own surface down.
//!
//! The height maps are read as columns: a cell's height holds over its whole half-open square.
//! Along a vertical of face `v`, each face's set is then a union of intervals, one per cell the
//! vertical's shadow crosses in that face's grid, found exactly by walking the grid lines the
//! shadow crosses ([`surface_seen_from`]); a brute-force version over every cell is in the tests.

use nalgebra::{Point3, UnitQuaternion, Vector3};
use rayon::prelude::*;

use crate::{GeometryError, HeightMap};

/// One face's surface: what its program leaves, in its own view.
#[derive(Debug, Clone, Copy)]
pub struct FaceSurface<'a> {
    /// From the part frame to the face's view ([`crate::Face::view_from_part`]).
    pub view_from_part: UnitQuaternion<f64>,
    /// The surface, on the face's grid, heights along the view's Z.
    pub map: &'a HeightMap,
}

/// Intervals of the ray parameter shorter than this hold no material (a ray grazing an edge).
const MIN_INTERVAL: f64 = 1e-9;

/// The part every face's cut leaves, seen from `faces[view]`, on that face's grid: per cell, the
/// highest view-frame Z of a point below every face's surface (in that face's frame) and inside
/// every face's grid, searched from the face's own surface down to `floor`. A cell with no such
/// point above `floor` reads `floor`; a cell without value (NaN) in the view's own map stays NaN;
/// so does a cell of another face whose surface has no value (no material there).
///
/// Errors: `view` out of range, `floor` not finite, or a map the result's grid refuses.
pub fn surface_seen_from(
    faces: &[FaceSurface<'_>],
    view: usize,
    floor: f64,
) -> Result<HeightMap, GeometryError> {
    let Some(own) = faces.get(view) else {
        return Err(GeometryError::InvalidParameter {
            field: "view".into(),
            value: format!("face {view} of {}", faces.len()),
            expected: "one of the faces given",
        });
    };
    if !floor.is_finite() {
        return Err(GeometryError::InvalidParameter {
            field: "floor".into(),
            value: format!("{floor} mm"),
            expected: "a finite height",
        });
    }
    let part_from_view = own.view_from_part.inverse();
    // Each face's frame from the view's, and the downward direction there.
    let frames: Vec<(UnitQuaternion<f64>, Vector3<f64>)> = faces
        .iter()
        .map(|f| {
            let m = f.view_from_part * part_from_view;
            (m, m * Vector3::new(0.0, 0.0, -1.0))
        })
        .collect();
    let meta = *own.map.meta();
    let w = meta.width as usize;
    let first_window = 8.0 * faces.iter().map(|f| f.map.pixel_mm()).fold(0.0, f64::max);
    let data: Vec<f32> = own
        .map
        .data()
        .par_iter()
        .enumerate()
        .map_init(
            || (Vec::new(), Vec::new(), Vec::new()),
            |(acc, next, breaks), (k, &z0)| {
                if !z0.is_finite() {
                    return f32::NAN;
                }
                let z0 = f64::from(z0);
                let len = z0 - floor;
                if len <= 0.0 {
                    return z0 as f32;
                }
                let (x, y) = meta.cell_center((k % w) as u32, (k / w) as u32);
                let top = Point3::new(x, y, z0);
                // Windows of growing depth from the surface down: most cells find material in
                // the first, so a deep grid's lines are walked only where it is empty.
                let (mut lo, mut win) = (0.0, first_window);
                loop {
                    let hi = (lo + win).min(len);
                    acc.clear();
                    acc.push((lo, hi));
                    for (f, (m, dir)) in faces.iter().zip(&frames) {
                        let a = m * top;
                        next.clear();
                        inside_intervals(f.map, &a, dir, (lo, hi), breaks, next);
                        intersect(acc, next);
                        if acc.is_empty() {
                            break;
                        }
                    }
                    if let Some(&(t, _)) = acc.first() {
                        return (z0 - t) as f32;
                    }
                    if hi >= len {
                        return floor as f32;
                    }
                    lo = hi;
                    win *= 2.0;
                }
            },
        )
        .collect();
    let mut m = meta;
    m.z_min_mm = m.z_min_mm.min(floor);
    HeightMap::new(m, data)
}

/// The parameters `t ∈ [lo, hi]` at which `a + t·dir` lies in `map`'s grid and at or below its
/// cell's height, as sorted disjoint intervals appended to `out` (`breaks` is scratch).
fn inside_intervals(
    map: &HeightMap,
    a: &Point3<f64>,
    dir: &Vector3<f64>,
    (lo, hi): (f64, f64),
    breaks: &mut Vec<f64>,
    out: &mut Vec<(f64, f64)>,
) {
    let meta = map.meta();
    breaks.clear();
    breaks.push(lo);
    breaks.push(hi);
    // Where the shadow crosses the grid's lines (only the lines of the grid matter: beyond them
    // every point is outside).
    for (axis, origin, n) in [(0, meta.origin_x_mm, meta.width), (1, meta.origin_y_mm, meta.height)] {
        let d = dir[axis];
        if d == 0.0 {
            continue;
        }
        let u0 = (a[axis] + lo * d - origin) / meta.pixel_mm;
        let u1 = (a[axis] + hi * d - origin) / meta.pixel_mm;
        let first = u0.min(u1).ceil().max(0.0);
        let last = u0.max(u1).floor().min(f64::from(n));
        let mut k = first;
        while k <= last {
            let t = (origin + k * meta.pixel_mm - a[axis]) / d;
            if t > lo && t < hi {
                breaks.push(t);
            }
            k += 1.0;
        }
    }
    breaks.sort_unstable_by(f64::total_cmp);
    for s in breaks.windows(2) {
        let (t0, t1) = (s[0], s[1]);
        if t1 - t0 <= MIN_INTERVAL {
            continue;
        }
        let mid = a + dir * (0.5 * (t0 + t1));
        let Some(h) = meta.cell_of(mid.x, mid.y).and_then(|(c, r)| map.get(c, r)).filter(|h| h.is_finite())
        else {
            continue;
        };
        // a.z + t·dir.z <= h.
        let rest = f64::from(h) - a.z;
        let (lo, hi) = if dir.z > 0.0 {
            (t0, t1.min(rest / dir.z))
        } else if dir.z < 0.0 {
            (t0.max(rest / dir.z), t1)
        } else if rest >= 0.0 {
            (t0, t1)
        } else {
            continue;
        };
        push_merged(out, lo, hi);
    }
}

/// Appends `[lo, hi]` to sorted disjoint intervals, joining it to the last one when they touch;
/// intervals of at most [`MIN_INTERVAL`] are dropped.
fn push_merged(out: &mut Vec<(f64, f64)>, lo: f64, hi: f64) {
    if hi - lo <= MIN_INTERVAL {
        return;
    }
    match out.last_mut() {
        Some(last) if lo <= last.1 => last.1 = last.1.max(hi),
        _ => out.push((lo, hi)),
    }
}

/// `acc ∩ other` (both sorted and disjoint) into `acc`.
fn intersect(acc: &mut Vec<(f64, f64)>, other: &[(f64, f64)]) {
    let mut out = Vec::with_capacity(acc.len().min(other.len()) + 1);
    let (mut i, mut j) = (0, 0);
    while i < acc.len() && j < other.len() {
        let lo = acc[i].0.max(other[j].0);
        let hi = acc[i].1.min(other[j].1);
        push_merged(&mut out, lo, hi);
        if acc[i].1 < other[j].1 {
            i += 1;
        } else {
            j += 1;
        }
    }
    *acc = out;
}

#[cfg(test)]
mod tests {
    use nalgebra::Vector3;
    use rand::{Rng, SeedableRng, rngs::StdRng};

    use super::*;
    use crate::{Face, HeightMapMeta};

    /// The first material along each vertical, brute force: every cell of every face gives the
    /// ray's interval inside its square (slabs) and below its height; the union per face, the
    /// intersection over faces, its first point.
    fn reference(faces: &[FaceSurface<'_>], view: usize, floor: f64) -> Vec<f32> {
        let own = faces[view].map;
        let meta = *own.meta();
        let part_from_view = faces[view].view_from_part.inverse();
        let mut out = Vec::new();
        for (k, &z0) in own.data().iter().enumerate() {
            if !z0.is_finite() {
                out.push(f32::NAN);
                continue;
            }
            let z0 = f64::from(z0);
            let len = z0 - floor;
            let (x, y) = meta.cell_center((k % meta.width as usize) as u32, (k / meta.width as usize) as u32);
            let mut acc = vec![(0.0, len)];
            for f in faces {
                let m = f.view_from_part * part_from_view;
                let a = m * Point3::new(x, y, z0);
                let d = m * Vector3::new(0.0, 0.0, -1.0);
                let fm = f.map.meta();
                let mut pieces = Vec::new();
                for r in 0..fm.height {
                    for c in 0..fm.width {
                        let Some(h) = f.map.get(c, r).filter(|h| h.is_finite()) else { continue };
                        let mut lo: f64 = 0.0;
                        let mut hi: f64 = len;
                        let lows = [
                            fm.origin_x_mm + f64::from(c) * fm.pixel_mm,
                            fm.origin_y_mm + f64::from(r) * fm.pixel_mm,
                        ];
                        for axis in 0..2 {
                            let (l, u) = (lows[axis], lows[axis] + fm.pixel_mm);
                            if d[axis] == 0.0 {
                                if !(a[axis] >= l && a[axis] < u) {
                                    hi = -1.0;
                                }
                            } else {
                                let (t1, t2) = ((l - a[axis]) / d[axis], (u - a[axis]) / d[axis]);
                                lo = lo.max(t1.min(t2));
                                hi = hi.min(t1.max(t2));
                            }
                        }
                        let rest = f64::from(h) - a.z;
                        if d.z > 0.0 {
                            hi = hi.min(rest / d.z);
                        } else if d.z < 0.0 {
                            lo = lo.max(rest / d.z);
                        } else if rest < 0.0 {
                            hi = -1.0;
                        }
                        if hi - lo > MIN_INTERVAL {
                            pieces.push((lo, hi));
                        }
                    }
                }
                pieces.sort_by(|p, q| p.0.total_cmp(&q.0));
                let mut merged = Vec::new();
                for (lo, hi) in pieces {
                    push_merged(&mut merged, lo, hi);
                }
                intersect(&mut acc, &merged);
            }
            out.push(acc.first().map_or(floor, |&(t, _)| z0 - t) as f32);
        }
        out
    }

    fn random_map(rng: &mut StdRng, origin: (f64, f64), size: (u32, u32), pixel: f64) -> HeightMap {
        let mut meta = HeightMapMeta::new(size.0, size.1, pixel);
        meta.origin_x_mm = origin.0;
        meta.origin_y_mm = origin.1;
        meta.z_min_mm = -10.0;
        meta.z_max_mm = 10.0;
        // A few bumps over a tilted plane, some holes without value.
        let bumps: Vec<(f64, f64, f64, f64)> = (0..3)
            .map(|_| {
                (
                    rng.random_range(-4.0..4.0),
                    rng.random_range(-4.0..4.0),
                    rng.random_range(1.0..3.0),
                    rng.random_range(0.0..4.0),
                )
            })
            .collect();
        let (gx, gy) = (rng.random_range(-0.3..0.3), rng.random_range(-0.3..0.3));
        let data = (0..size.0 * size.1)
            .map(|k| {
                let (x, y) = meta.cell_center(k % size.0, k / size.0);
                if rng.random_bool(0.03) {
                    return f32::NAN;
                }
                let mut z = 2.0 + gx * x + gy * y;
                for &(bx, by, r, hgt) in &bumps {
                    let d2 = ((x - bx).powi(2) + (y - by).powi(2)) / (r * r);
                    z += hgt * (-d2).exp();
                }
                z as f32
            })
            .collect();
        HeightMap::new(meta, data).expect("map")
    }

    #[test]
    fn one_face_is_its_own_surface() {
        let mut rng = StdRng::seed_from_u64(7);
        let map = random_map(&mut rng, (-5.0, -5.0), (20, 20), 0.5);
        let faces = [FaceSurface { view_from_part: Face::A { angle_deg: 30.0 }.view_from_part(), map: &map }];
        let seen = surface_seen_from(&faces, 0, -10.0).expect("seen");
        for (a, b) in seen.data().iter().zip(map.data()) {
            assert!(a.to_bits() == b.to_bits(), "{a} vs {b}");
        }
    }

    #[test]
    fn a_second_face_cuts_what_the_first_leaves() {
        // Face +Z leaves a flat top at z = 5 over x, y in [-5, 5]; face +Y (90° about X: view
        // z = part y, view y = -part z) leaves the part's y <= 2.
        let flat = |origin: (f64, f64), size: (u32, u32), z: f32| {
            let mut meta = HeightMapMeta::new(size.0, size.1, 0.5);
            meta.origin_x_mm = origin.0;
            meta.origin_y_mm = origin.1;
            meta.z_min_mm = -10.0;
            meta.z_max_mm = 10.0;
            HeightMap::new(meta, vec![z; (size.0 * size.1) as usize]).expect("map")
        };
        let top = flat((-5.0, -5.0), (20, 20), 5.0);
        let side = flat((-5.0, -10.0), (20, 40), 2.0);
        let faces = [
            FaceSurface { view_from_part: Face::PosZ.view_from_part(), map: &top },
            FaceSurface { view_from_part: Face::PosY.view_from_part(), map: &side },
        ];
        let seen = surface_seen_from(&faces, 0, -10.0).expect("seen");
        let meta = *seen.meta();
        for r in 0..meta.height {
            for c in 0..meta.width {
                let (_, y) = meta.cell_center(c, r);
                let z = seen.get(c, r).expect("cell");
                // +Y's view maps part y to view z: material where part y <= 2.
                let expect = if y <= 2.0 { 5.0 } else { -10.0 };
                assert_eq!(z, expect, "cell ({c}, {r}) at y {y}");
            }
        }
    }

    #[test]
    fn matches_the_brute_force_on_random_faces() {
        let mut rng = StdRng::seed_from_u64(11);
        for case in 0..12 {
            let n = rng.random_range(1..4);
            let maps: Vec<HeightMap> = (0..n)
                .map(|_| {
                    let p = rng.random_range(0.3..0.8);
                    let o = (rng.random_range(-7.0..-3.0), rng.random_range(-7.0..-3.0));
                    let size = (rng.random_range(8..20), rng.random_range(8..20));
                    random_map(&mut rng, o, size, p)
                })
                .collect();
            let faces: Vec<FaceSurface<'_>> = maps
                .iter()
                .map(|m| {
                    let face = match rng.random_range(0..3) {
                        0 => Face::A { angle_deg: rng.random_range(-90.0..90.0) },
                        1 => Face::PosX,
                        _ => {
                            let n =
                                Vector3::new(rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0), 1.0)
                                    .normalize();
                            Face::Normal { x: n.x, y: n.y, z: n.z }
                        }
                    };
                    FaceSurface { view_from_part: face.view_from_part(), map: m }
                })
                .collect();
            // A floor near the surfaces, and one far below them (the search goes down in several
            // windows before it finds the floor).
            for floor in [-6.0, -40.0] {
                for view in 0..faces.len() {
                    let fast = surface_seen_from(&faces, view, floor).expect("seen");
                    let slow = reference(&faces, view, floor);
                    for (i, (a, b)) in fast.data().iter().zip(&slow).enumerate() {
                        assert!(
                            (a.is_nan() && b.is_nan()) || (a - b).abs() <= 1e-5,
                            "case {case} floor {floor} view {view} cell {i}: {a} vs {b}"
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn bad_arguments_are_named() {
        let mut rng = StdRng::seed_from_u64(3);
        let map = random_map(&mut rng, (-5.0, -5.0), (4, 4), 1.0);
        let faces = [FaceSurface { view_from_part: Face::PosZ.view_from_part(), map: &map }];
        let e = surface_seen_from(&faces, 1, 0.0).expect_err("no face 1");
        assert!(e.to_string().contains("face 1 of 1"), "{e}");
        let e = surface_seen_from(&faces, 0, f64::NAN).expect_err("floor");
        assert!(e.to_string().contains("floor"), "{e}");
    }
}
