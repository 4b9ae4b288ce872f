//! Pass-to-pass alignment of a scanned cloud whose points carry their pass.
//!
//! Why: the passes are placed with the cell's calibration, which leaves each a residual error of
//! a few hundredths of a millimetre (the demo's tilted passes lie about 0.03 mm off the others,
//! in a direction that turns with the table). A slope `s` turns a horizontal offset `d` into a
//! height error `s · d`: 0.03 to 0.1 mm on a steep rim, where the estimator averages the passes
//! into a surface under the part. Each pass is moved by the translation that best lays its points
//! on the surface the whole cloud describes, the cloud as a whole staying where the calibration
//! put it.
//!
//! How, for [`ALIGN_PASS_ROUNDS`] rounds: the cloud is fitted to a height map
//! ([`rasterize_fit`] on [`ALIGN_PIXEL_MM`] cells). Each pass's points where the map holds the
//! four cells around them (read bilinearly, slope under [`ALIGN_MAX_SLOPE`]) give residuals
//! `r = z − m(x, y)`, and the linearised model `r = dz − m_x·dx − m_y·dy` of a pass displaced by
//! `(dx, dy, dz)` is solved by reweighted least squares (Tukey, cut off at 4.685 times the
//! residuals' robust spread; the first round keeps residuals under [`ALIGN_MAX_RESIDUAL_MM`])
//! with a weak prior toward no shift ([`ALIGN_PRIOR_MM`]), re-reading the map at the shifted
//! points. Where the faces a pass sees do not fix its horizontal offset (a flat; the standard
//! deviation over [`ALIGN_MAX_SD_MM`]) only its height is solved. The offsets less their mean
//! (weighted by points read) are moved back, for a pass of at least [`ALIGN_MIN_POINTS`] points
//! read whose total stays under [`ALIGN_MAX_SHIFT_MM`] (more is a placement error no residual of a
//! calibration explains). A pass's own points are part of the map it is read against, which takes
//! its share of the offset off each round's estimate; the rounds give it back. Translations only:
//! the residual of a calibrated cell over one pass is a translation to within the noise, and the
//! faces a pass sees fix three unknowns far better than six.

use std::collections::BTreeMap;
use std::time::Instant;

use crate::HeightMap;
use crate::raster::{Roi, grid_for_roi};
use crate::surface_fit::{FitParams, Planes, Ridges, rasterize_fit, robust_sd};
use nalgebra::{Matrix3, Point3, Vector3};
use rayon::prelude::*;
use serde::Serialize;

/// Cells of the reference passes' map, mm.
pub const ALIGN_PIXEL_MM: f64 = 0.25;
/// Steepest slope of the map a point is read at: steeper, the map's cells straddle a wall.
pub const ALIGN_MAX_SLOPE: f64 = 1.5;
/// Largest residual the first round keeps, mm (a point on a surface the map does not hold).
pub const ALIGN_MAX_RESIDUAL_MM: f64 = 0.3;
/// Fewest points read for a pass to be moved. With fewer, the offset's error (the map's noise,
/// which the points of one cell read alike, and the surfaces a small part's pass straddles) is of
/// the size of the offsets themselves: on the parts set, passes of 1 000 to 5 000 points moved by
/// their offsets raised the registration error against the true poses (the bunny's 0.0123 to
/// 0.0138 mm RMS), while the demo's passes of 100 000 lowered it from 0.0257 to 0.0151 mm.
pub const ALIGN_MIN_POINTS: usize = 20_000;
/// Largest shift applied, mm.
pub const ALIGN_MAX_SHIFT_MM: f64 = 0.5;
/// Standard deviation of the prior on each component of a pass's shift, mm.
pub const ALIGN_PRIOR_MM: f64 = 0.1;
/// Largest standard deviation of a horizontal component for the horizontal offset to be applied,
/// mm: above it the faces the pass sees do not fix where it lies across them (a flat, or slopes
/// all one way), and only its height is corrected. The figure is the points' own; the map's noise,
/// which many points read alike, makes the true one larger.
pub const ALIGN_MAX_SD_MM: f64 = 0.005;
/// Rounds of reweighting, each re-reading the map at the shifted points.
const ALIGN_ROUNDS: usize = 4;
/// Rounds of fitting the whole cloud and moving every pass onto it: a pass's own points are part
/// of the map it is read against, which takes its share of the offset off each round's estimate.
pub const ALIGN_PASS_ROUNDS: usize = 3;
/// Tukey's cut-off, in robust standard deviations of the residuals.
const TUKEY: f64 = 4.685;

/// One pass's alignment.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PassShift {
    pub pass: u16,
    /// Points of the pass read against the cloud's surface (the last round's, weighted in).
    pub points_used: u64,
    /// How far the pass lay off the rest of the cloud (X, Y, Z, part frame), mm: its points were
    /// moved back by it.
    pub offset_mm: [f64; 3],
    /// The last round's standard deviation per component, mm (0 for a component not solved).
    pub sd_mm: [f64; 3],
    /// The residuals' robust standard deviation in the last round, mm.
    pub residual_sd_mm: f64,
    /// Whether the pass was moved.
    pub applied: bool,
}

/// What the alignment did.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PassAlignment {
    /// Rounds of fitting the whole cloud and moving every pass onto it.
    pub rounds: usize,
    pub pixel_mm: f64,
    /// The passes of at least [`ALIGN_MIN_POINTS`] points (the others stay as placed).
    pub passes: Vec<PassShift>,
    /// The registration error before the shifts (RMS over all points, against the true poses;
    /// the report's `registration_rms_mm` is after them), mm.
    pub registration_rms_before_mm: f64,
    /// The merge error before the shifts, mm.
    pub registration_merge_rms_before_mm: f64,
    pub seconds: f64,
}

/// Moves the points of every pass by the translation that lays them on the surface the whole
/// cloud describes (see the module docs). `pass[i]` is point `i`'s pass. `None` when there is
/// nothing to align (fewer than two passes of [`ALIGN_MIN_POINTS`] points, or a cloud too
/// small for a map).
pub fn align_passes(points: &mut [Point3<f64>], pass: &[u16]) -> Option<PassAlignment> {
    let started = Instant::now();
    if points.len() != pass.len() {
        return None;
    }
    let mut by_pass: BTreeMap<u16, Vec<usize>> = BTreeMap::new();
    for (i, &p) in pass.iter().enumerate() {
        by_pass.entry(p).or_default().push(i);
    }
    by_pass.retain(|_, idx| idx.len() >= ALIGN_MIN_POINTS);
    if by_pass.len() < 2 {
        return None;
    }
    // Per pass: the offset moved back so far, and the last round's figures.
    let mut total: BTreeMap<u16, Vector3<f64>> = by_pass.keys().map(|&p| (p, Vector3::zeros())).collect();
    let mut last: BTreeMap<u16, PassShift> = BTreeMap::new();
    let mut rounds = 0;
    for round in 0..ALIGN_PASS_ROUNDS {
        // A map that the first round could make, a later one can too; should it not, the shifts
        // made so far stand and are reported.
        let Some(map) = reference_map(points) else {
            if round == 0 {
                return None;
            }
            break;
        };
        rounds += 1;
        let cloud: &[Point3<f64>] = points;
        let shifts: Vec<(u16, PassShift, bool)> = by_pass
            .par_iter()
            .map(|(&id, idx)| {
                let pts: Vec<Point3<f64>> = idx.iter().map(|&i| cloud[i]).collect();
                let shift = solve_offset(&map, &pts, true);
                if shift.sd_mm[0].max(shift.sd_mm[1]) > ALIGN_MAX_SD_MM {
                    (id, PassShift { pass: id, ..solve_offset(&map, &pts, false) }, false)
                } else {
                    (id, PassShift { pass: id, ..shift }, true)
                }
            })
            .collect();
        // The cloud as a whole stays where the calibration put it: the offsets are taken from
        // their mean (per component, over the passes that fix it, weighted by points read).
        let usable = |s: &PassShift| s.points_used as usize >= ALIGN_MIN_POINTS;
        let (mut sum, mut weight) = (Vector3::<f64>::zeros(), Vector3::<f64>::zeros());
        for (_, s, horizontal) in &shifts {
            if usable(s) {
                let w = s.points_used as f64;
                let mask =
                    Vector3::new(f64::from(u8::from(*horizontal)), f64::from(u8::from(*horizontal)), 1.0);
                sum += Vector3::from(s.offset_mm).component_mul(&mask) * w;
                weight += mask * w;
            }
        }
        let mean = sum.zip_map(&weight, |s, w| if w > 0.0 { s / w } else { 0.0 });
        for (id, s, horizontal) in shifts {
            if usable(&s) {
                let mut d = Vector3::from(s.offset_mm) - mean;
                if !horizontal {
                    (d.x, d.y) = (0.0, 0.0);
                }
                if let (Some(t), Some(idx)) = (total.get_mut(&id), by_pass.get(&id))
                    && (*t + d).norm() <= ALIGN_MAX_SHIFT_MM
                {
                    for &i in idx {
                        points[i] -= d;
                    }
                    *t += d;
                }
            }
            last.insert(id, s);
        }
    }
    let passes = last
        .into_values()
        .map(|s| {
            let t = total.get(&s.pass).copied().unwrap_or_else(Vector3::zeros);
            PassShift { offset_mm: [t.x, t.y, t.z], applied: t != Vector3::zeros(), ..s }
        })
        .collect();
    Some(PassAlignment {
        rounds,
        pixel_mm: ALIGN_PIXEL_MM,
        passes,
        registration_rms_before_mm: 0.0,
        registration_merge_rms_before_mm: 0.0,
        seconds: started.elapsed().as_secs_f64(),
    })
}

/// The cloud's surface: its points fitted over their bounds.
fn reference_map(points: &[Point3<f64>]) -> Option<HeightMap> {
    if points.len() < ALIGN_MIN_POINTS {
        return None;
    }
    let (lo, hi) = points
        .iter()
        .fold(((f64::INFINITY, f64::INFINITY), (f64::NEG_INFINITY, f64::NEG_INFINITY)), |(lo, hi), p| {
            ((lo.0.min(p.x), lo.1.min(p.y)), (hi.0.max(p.x), hi.1.max(p.y)))
        });
    let roi = Roi {
        x_min_mm: lo.0,
        y_min_mm: lo.1,
        x_max_mm: hi.0 + ALIGN_PIXEL_MM,
        y_max_mm: hi.1 + ALIGN_PIXEL_MM,
    };
    let grid = grid_for_roi(&roi, ALIGN_PIXEL_MM).ok()?;
    // A ridge's apex changes no slope the offsets are read on; the plane where a bend is the
    // noise's lowers a cell's noise, which the offsets average away over thousands of points, at
    // almost twice the fit's time.
    let params = FitParams { ridges: Ridges::Off, planes: Planes::Never, ..FitParams::default() };
    rasterize_fit(points, &grid, &params).ok().map(|(map, _, _)| map)
}

/// The map's height and gradient at `(x, y)`, bilinear between the four cell centres around it
/// when all four hold a height and the slope is under [`ALIGN_MAX_SLOPE`].
fn read(map: &HeightMap, x: f64, y: f64) -> Option<(f64, f64, f64)> {
    let m = map.meta();
    let p = m.pixel_mm;
    let fx = (x - m.origin_x_mm) / p - 0.5;
    let fy = (y - m.origin_y_mm) / p - 0.5;
    if !(fx >= 0.0 && fy >= 0.0) {
        return None;
    }
    let (c, r) = (fx.floor() as u32, fy.floor() as u32);
    let (tx, ty) = (fx - f64::from(c), fy - f64::from(r));
    let z = |dc: u32, dr: u32| map.get(c + dc, r + dr).filter(|z| z.is_finite()).map(f64::from);
    let (z00, z10, z01, z11) = (z(0, 0)?, z(1, 0)?, z(0, 1)?, z(1, 1)?);
    let h = z00 * (1.0 - tx) * (1.0 - ty) + z10 * tx * (1.0 - ty) + z01 * (1.0 - tx) * ty + z11 * tx * ty;
    let gx = ((z10 - z00) * (1.0 - ty) + (z11 - z01) * ty) / p;
    let gy = ((z01 - z00) * (1.0 - tx) + (z11 - z10) * tx) / p;
    (gx.hypot(gy) < ALIGN_MAX_SLOPE).then_some((h, gx, gy))
}

/// The offset of the points `pts` of one pass against `map` (see the module docs); with
/// `horizontal` false, its height only.
fn solve_offset(map: &HeightMap, pts: &[Point3<f64>], horizontal: bool) -> PassShift {
    let mut d = Vector3::<f64>::zeros();
    let mut sd = [f64::NAN; 3];
    let (mut used, mut spread) = (0u64, f64::NAN);
    for round in 0..ALIGN_ROUNDS {
        // Residuals and gradients at the points moved back by the current offset.
        let rows: Vec<(f64, f64, f64)> = pts
            .iter()
            .filter_map(|q| {
                let (h, gx, gy) = read(map, q.x - d.x, q.y - d.y)?;
                let r = q.z - d.z - h;
                (r.abs() < ALIGN_MAX_RESIDUAL_MM).then_some((r, gx, gy))
            })
            .collect();
        let mut residuals: Vec<f64> = rows.iter().map(|t| t.0).collect();
        let sigma = robust_sd(&mut residuals).max(1e-4);
        spread = sigma;
        let cut = TUKEY * sigma;
        let (mut a, mut b) = (Matrix3::<f64>::zeros(), Vector3::<f64>::zeros());
        used = 0;
        for &(r, gx, gy) in &rows {
            let w = if round == 0 {
                1.0
            } else {
                let t = r / cut;
                if t.abs() >= 1.0 { 0.0 } else { (1.0 - t * t).powi(2) }
            };
            if w <= 0.0 {
                continue;
            }
            used += 1;
            // r ≈ Δx·(−m_x) + Δy·(−m_y) + Δz.
            let phi = Vector3::new(-gx, -gy, 1.0);
            a += phi * phi.transpose() * (w / (sigma * sigma));
            b += phi * (w * r / (sigma * sigma));
        }
        // The prior: each component of the whole offset `d + Δ` is N(0, ALIGN_PRIOR_MM²).
        let prior = 1.0 / (ALIGN_PRIOR_MM * ALIGN_PRIOR_MM);
        let fixed = if horizontal { prior } else { 1e12 * prior };
        let p = Vector3::new(fixed, fixed, prior);
        a += Matrix3::from_diagonal(&p);
        b -= d.component_mul(&p);
        let Some(chol) = a.cholesky() else { break };
        let step = chol.solve(&b);
        d += step;
        let inv = chol.inverse();
        sd = [inv[(0, 0)].sqrt(), inv[(1, 1)].sqrt(), inv[(2, 2)].sqrt()];
    }
    PassShift {
        pass: 0,
        points_used: used,
        offset_mm: [d.x, d.y, d.z],
        sd_mm: sd,
        residual_sd_mm: spread,
        applied: false,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::rngs::StdRng;
    use rand::{Rng, SeedableRng};

    /// A relief with slopes every way: domes, a ridge, a flat and a rounded rim.
    fn surface(x: f64, y: f64) -> f64 {
        let dome = 3.0 * (-((x - 8.0).powi(2) + (y - 10.0).powi(2)) / 18.0).exp();
        let waves = 0.8 * (x / 2.3).sin() * (y / 3.1).cos();
        let ridge = 1.5 - 0.4 * (x + 0.5 * y - 22.0).abs().min(3.75);
        10.0 + dome + waves + ridge
    }

    fn gauss(rng: &mut StdRng) -> f64 {
        let u: f64 = rng.random_range(1e-12..1.0);
        let v: f64 = rng.random_range(0.0..1.0);
        (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
    }

    /// `n` points of `surface` over 0..30 x 0..30 mm, noise `sigma`, displaced by `off`.
    fn pass_points(rng: &mut StdRng, n: usize, sigma: f64, off: Vector3<f64>) -> Vec<Point3<f64>> {
        (0..n)
            .map(|_| {
                let (x, y) = (rng.random_range(0.0..30.0), rng.random_range(0.0..30.0));
                Point3::new(x, y, surface(x, y) + sigma * gauss(rng)) + off
            })
            .collect()
    }

    /// The reference: the offset minimising the squared residuals of the pass against the true
    /// surface, by a brute-force search on a grid of 2 µm steps (Z by its mean at each X, Y).
    fn brute_force(pts: &[Point3<f64>]) -> Vector3<f64> {
        let mut best = (f64::INFINITY, Vector3::zeros());
        let (mut cx, mut cy) = (0.0, 0.0);
        for step in [0.01, 0.002] {
            let (ox, oy) = (cx, cy);
            for i in -10..=10 {
                for j in -10..=10 {
                    let (dx, dy) = (ox + f64::from(i) * step, oy + f64::from(j) * step);
                    let r: Vec<f64> = pts.iter().map(|q| q.z - surface(q.x - dx, q.y - dy)).collect();
                    let dz = r.iter().sum::<f64>() / r.len() as f64;
                    let cost: f64 = r.iter().map(|v| (v - dz).powi(2)).sum();
                    if cost < best.0 {
                        best = (cost, Vector3::new(dx, dy, dz));
                        (cx, cy) = (dx, dy);
                    }
                }
            }
        }
        best.1
    }

    #[test]
    fn a_displaced_pass_is_moved_back_onto_the_clouds_surface() {
        let mut rng = StdRng::seed_from_u64(3);
        let sigma = 0.035;
        let mut points = pass_points(&mut rng, 120_000, sigma, Vector3::zeros());
        let mut pass = vec![1u16; points.len()];
        let offsets = [
            (2u16, Vector3::new(0.03, -0.01, 0.004)),
            (3, Vector3::new(-0.025, 0.028, -0.006)),
            (4, Vector3::new(0.0, 0.0, 0.0)),
            (5, Vector3::new(0.08, 0.05, 0.01)),
        ];
        for (id, off) in offsets {
            let pts = pass_points(&mut rng, 25_000, sigma, off);
            pass.extend(std::iter::repeat_n(id, pts.len()));
            points.extend(pts);
        }
        let before = points.clone();
        let report = align_passes(&mut points, &pass).expect("aligned");
        let offset = |id: u16| {
            let s = report.passes.iter().find(|s| s.pass == id).expect("pass");
            assert!(s.points_used > 20_000, "{s:?}");
            Vector3::from(s.offset_mm)
        };
        let own = |id: u16| -> Vec<Point3<f64>> {
            before.iter().zip(&pass).filter(|(_, p)| **p == id).map(|(q, _)| *q).collect()
        };
        // Offsets are relative to the cloud: pass 1's (the bulk, not displaced) against the
        // others'.
        let (base, base_bf) = (offset(1), brute_force(&own(1)));
        for (id, off) in offsets {
            let got = offset(id) - base;
            let reference = brute_force(&own(id)) - base_bf;
            eprintln!("pass {id}: offset {got:?}, brute force {reference:?}, truth {off:?}");
            assert!((got - reference).norm() < 0.004, "pass {id}: {got:?} against {reference:?}");
            assert!((got - off).norm() < 0.006, "pass {id}: {got:?} against the truth {off:?}");
        }
        // Every point moved by its pass's offset, back.
        for ((q, b), p) in points.iter().zip(&before).zip(&pass) {
            assert!(((b - q) - offset(*p)).norm() < 1e-9);
        }
        // The cloud as a whole stays put: the offsets weighted by points average to nothing.
        let n = |id: u16| pass.iter().filter(|p| **p == id).count() as f64;
        let mean: Vector3<f64> =
            [1u16, 2, 3, 4, 5].iter().map(|&id| offset(id) * n(id)).sum::<Vector3<f64>>() / pass.len() as f64;
        assert!(mean.norm() < 0.003, "{mean:?}");
    }

    #[test]
    fn a_pass_over_a_flat_face_keeps_its_place_and_nothing_to_align_is_none() {
        let mut rng = StdRng::seed_from_u64(4);
        let flat = |rng: &mut StdRng, n: usize, off: Vector3<f64>| -> Vec<Point3<f64>> {
            (0..n)
                .map(|_| {
                    let (x, y) = (rng.random_range(0.0..20.0), rng.random_range(0.0..20.0));
                    Point3::new(x + off.x, y + off.y, 5.0 + 0.035 * gauss(rng) + off.z)
                })
                .collect()
        };
        let mut points = flat(&mut rng, 40_000, Vector3::zeros());
        let mut pass = vec![1u16; points.len()];
        let off = Vector3::new(0.2, -0.2, 0.01);
        let other = flat(&mut rng, 25_000, off);
        pass.extend(std::iter::repeat_n(2, other.len()));
        points.extend(other);
        let report = align_passes(&mut points, &pass).expect("aligned");
        let (a, b) = (&report.passes[0], &report.passes[1]);
        // A flat face fixes the height, not where the pass lies across it.
        assert!((b.offset_mm[2] - a.offset_mm[2] - 0.01).abs() < 0.002, "{a:?} {b:?}");
        for s in [a, b] {
            assert!(s.offset_mm[0] == 0.0 && s.offset_mm[1] == 0.0, "{s:?}");
            assert!(s.sd_mm[0] < 1e-6 && s.sd_mm[1] < 1e-6 && s.sd_mm[2] < 0.002, "{s:?}");
        }
        // Nothing to align: one pass, or arrays that do not match.
        assert!(align_passes(&mut points.clone(), &vec![1; points.len()]).is_none());
        assert!(align_passes(&mut points.clone(), &pass[1..]).is_none());
    }
}
