#![allow(clippy::unwrap_used)] // tests may unwrap

use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

use super::*;

fn gauss(rng: &mut StdRng) -> f64 {
    let u: f64 = rng.random_range(1e-12..1.0);
    let v: f64 = rng.random_range(0.0..1.0);
    (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
}

/// A scanned-like surface: a wavy height field with bumps in both directions (so no direction
/// slides), `n` points over `size` mm, noise `sigma`.
fn surface(rng: &mut StdRng, n: usize, size: f64, sigma: f64) -> Vec<Point3<f64>> {
    (0..n)
        .map(|_| {
            let (x, y) = (rng.random_range(-size..size), rng.random_range(-size..size));
            let z = 4.0 * (x / 9.0).sin() * (y / 13.0).cos()
                + 0.0005 * x * y
                + 3.0 * (-(x * x + y * y) / 400.0).exp();
            Point3::new(x, y, z + sigma * gauss(rng))
        })
        .collect()
}

fn small_transform(rng: &mut StdRng, deg: f64, mm: f64) -> Isometry3<f64> {
    let axis = Vector3::new(gauss(rng), gauss(rng), gauss(rng)).normalize();
    Isometry3::from_parts(
        Translation3::new(rng.random_range(-mm..mm), rng.random_range(-mm..mm), rng.random_range(-mm..mm)),
        UnitQuaternion::from_scaled_axis(axis * rng.random_range(-deg..deg).to_radians()),
    )
}

/// The obviously right reference: brute-force nearest neighbours, sequential sums, the same
/// normal equations, levels and stopping rule.
fn icp_reference(
    source: &[Point3<f64>],
    target: &Target,
    init: &Isometry3<f64>,
    opts: &IcpOptions,
) -> IcpResult {
    let pass = |pts: &[Point3<f64>], t: &Isometry3<f64>, it: u32| {
        let kernel = opts.kernel.annealed(it, opts.max_correspondence_mm);
        let mut s = Sums::zero();
        for p in pts {
            let p = t * p;
            let mut best: Option<(usize, f64)> = None;
            for (i, q) in target.points().iter().enumerate() {
                let d2 = (p - q).norm_squared();
                if best.is_none_or(|(_, b)| d2 < b) {
                    best = Some((i, d2));
                }
            }
            if let Some((i, d2)) = best.filter(|b| b.1 <= opts.max_correspondence_mm.powi(2)) {
                s = s.add(contribution(&p, &target.points()[i], &target.normals()[i], d2, &kernel));
            }
        }
        s
    };
    let level = |pts: &[Point3<f64>], mut t: Isometry3<f64>, first: u32, stop: f64| {
        let mut s = pass(pts, &t, first);
        let mut last = result_of(&s, pts.len(), t, first);
        let mut it = first;
        for _ in 0..opts.max_iterations {
            it += 1;
            let d = step(&s.a, &s.b).unwrap();
            t = d * t;
            s = pass(pts, &t, it);
            let now = result_of(&s, pts.len(), t, it);
            let df = (now.fitness - last.fitness).abs() / last.fitness.max(1e-300);
            let dr = (now.inlier_rmse_mm - last.inlier_rmse_mm).abs() / last.inlier_rmse_mm.max(1e-300);
            last = now;
            let moved = d.translation.vector.norm() + d.rotation.angle() * opts.max_correspondence_mm * 100.0;
            if (df < opts.relative_fitness && dr < opts.relative_rmse) || moved < stop {
                break;
            }
        }
        (t, last, it)
    };
    let stride = coarse_stride(source.len());
    let (mut t, mut it) = (*init, 0);
    if stride > 1 {
        let coarse: Vec<Point3<f64>> = source.iter().step_by(stride).copied().collect();
        (t, _, it) = level(&coarse, t, 0, COARSE_STEP_MM);
    }
    level(source, t, it, MIN_STEP_MM).1
}

fn transform_error(a: &Isometry3<f64>, b: &Isometry3<f64>) -> (f64, f64) {
    let d = a.inverse() * b;
    (d.translation.vector.norm(), d.rotation.angle().to_degrees())
}

#[test]
fn kernels_weigh_as_defined() {
    assert_eq!(Kernel::L2.weight(5.0), 1.0);
    assert_eq!(Kernel::Huber(1.0).weight(0.5), 1.0);
    assert!((Kernel::Huber(1.0).weight(4.0) - 0.25).abs() < 1e-15);
    assert_eq!(Kernel::Tukey(1.0).weight(1.5), 0.0);
    assert!((Kernel::Tukey(2.0).weight(1.0) - 0.5625).abs() < 1e-15);
    assert!((Kernel::Cauchy(1.0).weight(1.0) - 0.5).abs() < 1e-15);
}

#[test]
fn icp_matches_the_brute_force_reference_on_random_clouds() {
    let mut rng = StdRng::seed_from_u64(11);
    for case in 0..12 {
        let target_pts = surface(&mut rng, 600, 30.0, 0.01);
        let target = Target::new(target_pts.clone(), 12).unwrap();
        let truth = small_transform(&mut rng, 1.5, 0.8);
        let source: Vec<Point3<f64>> =
            surface(&mut rng, 300, 25.0, 0.01).iter().map(|p| truth.inverse() * p).collect();
        let kernel = match case % 4 {
            0 => Kernel::L2,
            1 => Kernel::Huber(0.2),
            2 => Kernel::Tukey(0.5),
            _ => Kernel::Cauchy(0.2),
        };
        let opts =
            IcpOptions { max_correspondence_mm: 2.0, kernel, max_iterations: 15, ..Default::default() };
        let fast = icp(&source, &target, &Isometry3::identity(), &opts).unwrap();
        let slow = icp_reference(&source, &target, &Isometry3::identity(), &opts);
        let (dt, da) = transform_error(&fast.transform, &slow.transform);
        assert!(dt < 1e-7 && da < 1e-7, "case {case}: {dt} mm {da}°");
        assert_eq!(fast.correspondences, slow.correspondences, "case {case}");
        assert!((fast.inlier_rmse_mm - slow.inlier_rmse_mm).abs() < 1e-9, "case {case}");
    }
}

#[test]
fn icp_recovers_a_misplacement_within_the_noise() {
    let mut rng = StdRng::seed_from_u64(12);
    let target = Target::new(surface(&mut rng, 20_000, 40.0, 0.01), 20).unwrap();
    for _ in 0..5 {
        let truth = small_transform(&mut rng, 2.0, 1.5);
        // Another scan of the same surface (other samples, other noise), misplaced.
        let source: Vec<Point3<f64>> =
            surface(&mut rng, 8000, 35.0, 0.01).iter().map(|p| truth.inverse() * p).collect();
        let r = icp(
            &source,
            &target,
            &Isometry3::identity(),
            &IcpOptions { max_correspondence_mm: 3.0, ..Default::default() },
        )
        .unwrap();
        let (dt, da) = transform_error(&r.transform, &truth);
        assert!(dt < 0.005 && da < 0.005, "{dt} mm {da}° after {} iterations", r.iterations);
        assert!(r.fitness > 0.99 && r.plane_rmse_mm < 0.03, "{r:?}");
    }
}

#[test]
fn the_robust_kernel_ignores_outliers_that_pull_least_squares_off() {
    let mut rng = StdRng::seed_from_u64(13);
    let target = Target::new(surface(&mut rng, 20_000, 40.0, 0.01), 20).unwrap();
    let truth = small_transform(&mut rng, 1.0, 0.5);
    let mut source: Vec<Point3<f64>> =
        surface(&mut rng, 8000, 35.0, 0.01).iter().map(|p| truth.inverse() * p).collect();
    // 10 % of the points 0.3-0.8 mm off the surface, all on one side (a fixture, a reflection).
    for p in source.iter_mut().step_by(10) {
        p.z += rng.random_range(0.3..0.8);
    }
    let run = |kernel| {
        let r = icp(
            &source,
            &target,
            &Isometry3::identity(),
            &IcpOptions { max_correspondence_mm: 2.0, kernel, ..Default::default() },
        )
        .unwrap();
        transform_error(&r.transform, &truth).0
    };
    let (l2, tukey) = (run(Kernel::L2), run(Kernel::Tukey(0.15)));
    assert!(tukey < 0.01, "Tukey {tukey} mm");
    assert!(l2 > 3.0 * tukey, "least squares {l2} mm vs Tukey {tukey} mm");
}

#[test]
fn a_start_off_by_tens_of_degrees_is_found_by_the_coarse_search() {
    let mut rng = StdRng::seed_from_u64(14);
    let target = Target::new(surface(&mut rng, 20_000, 40.0, 0.01), 20).unwrap();
    let truth = Isometry3::from_parts(
        Translation3::new(1.0, -2.0, 0.2),
        UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 50f64.to_radians()),
    );
    let source: Vec<Point3<f64>> =
        surface(&mut rng, 8000, 30.0, 0.01).iter().map(|p| truth.inverse() * p).collect();
    let opts = IcpOptions { max_correspondence_mm: 1.0, ..Default::default() };
    let plain = icp(&source, &target, &Isometry3::identity(), &opts);
    let plain_err = plain.map_or(f64::INFINITY, |r| transform_error(&r.transform, &truth).0);
    assert!(plain_err > 1.0, "a 50° start is beyond plain ICP ({plain_err} mm)");
    let r = icp_with_coarse_start(&source, &target, &Isometry3::identity(), &opts, 24).unwrap();
    let (dt, da) = transform_error(&r.transform, &truth);
    assert!(dt < 0.01 && da < 0.01, "{dt} mm {da}°");
}

#[test]
fn bad_input_is_refused_naming_it() {
    let mut rng = StdRng::seed_from_u64(15);
    let pts = surface(&mut rng, 100, 10.0, 0.0);
    let target = Target::new(pts.clone(), 10).unwrap();
    let id = Isometry3::identity();
    let e = icp(&pts[..3], &target, &id, &IcpOptions::default()).unwrap_err();
    assert!(e.to_string().contains("source cloud has 3 points"), "{e}");
    let mut nan = pts.clone();
    nan[7].y = f64::NAN;
    assert!(icp(&nan, &target, &id, &IcpOptions::default()).unwrap_err().to_string().contains("index 7"));
    assert!(Target::new(nan, 10).is_err());
    let e = icp(&pts, &target, &id, &IcpOptions { max_correspondence_mm: -1.0, ..Default::default() })
        .unwrap_err();
    assert!(e.to_string().contains("max_correspondence_mm"), "{e}");
    // A flat patch slides along itself: refused, not a made-up answer.
    let flat: Vec<Point3<f64>> =
        (0..400).map(|k| Point3::new((k % 20) as f64, (k / 20) as f64, 0.0)).collect();
    let t = Target::new(flat.clone(), 8).unwrap();
    let e = icp(&flat, &t, &id, &IcpOptions::default()).unwrap_err();
    assert!(e.to_string().contains("slides"), "{e}");
    // No overlap at all.
    let far: Vec<Point3<f64>> = pts.iter().map(|p| p + Vector3::new(500.0, 0.0, 0.0)).collect();
    let e = icp(&far, &target, &id, &IcpOptions::default()).unwrap_err();
    assert!(e.to_string().contains("do not overlap"), "{e}");
}

#[test]
fn the_f32_tree_answers_exactly_like_a_brute_force_search() {
    let mut rng = StdRng::seed_from_u64(77);
    for round in 0..4 {
        // Far from the origin, with exact duplicates and points on a fine lattice (ties that
        // rounding to f32 cannot order).
        let base = Vector3::new(400.0, -250.0, 80.0) * f64::from(round);
        let mut pts: Vec<Point3<f64>> = (0..3000)
            .map(|_| {
                Point3::from(
                    base + Vector3::new(
                        rng.random_range(-60.0..60.0),
                        rng.random_range(-60.0..60.0),
                        rng.random_range(-5.0..5.0),
                    ),
                )
            })
            .collect();
        for k in 0..300u32 {
            pts.push(pts[k as usize]);
            let q =
                Point3::from(base + Vector3::new(f64::from(k % 20) * 1e-5, f64::from(k / 20) * 1e-5, 0.0));
            pts.push(q);
        }
        let target = Target::new(pts.clone(), 10).unwrap();
        let queries = (0..2000).map(|_| {
            Point3::from(
                base + Vector3::new(
                    rng.random_range(-70.0..70.0),
                    rng.random_range(-70.0..70.0),
                    rng.random_range(-8.0..8.0),
                ),
            )
        });
        let near_lattice = (0..200).map(|k| {
            Point3::from(base + Vector3::new(f64::from(k % 20) * 1e-5 + 3e-6, f64::from(k / 20) * 1e-5, 1e-6))
        });
        for q in queries.chain(near_lattice) {
            let mut d: Vec<f64> = pts.iter().map(|p| (q - p).norm()).collect();
            let (bi, bd) =
                d.iter().enumerate().min_by(|a, b| a.1.total_cmp(b.1)).map(|(i, v)| (i, *v)).unwrap();
            d.sort_by(f64::total_cmp);
            for bound in [f64::INFINITY, 2.0, 0.5, 1e-5] {
                match target.nearest_two(&q, bound) {
                    (Some(i), d1, d2) => {
                        assert_eq!(d1, bd, "nearest distance at {q}");
                        assert_eq!((q - pts[i]).norm(), bd, "index {i} vs {bi}");
                        assert!(bd <= bound * (1.0 + 1e-6) + 1e-4, "found {bd} beyond {bound}");
                        // Every other point (the second nearest, which may tie) is at least d2 away.
                        assert!(d2 <= d[1] + 1e-15, "{d2} > second {}", d[1]);
                    }
                    (None, at_least, _) => {
                        assert!(at_least <= bd, "nearest {bd} said to be at least {at_least}");
                        assert!(bd > bound * (1.0 - 1e-6) - 1e-4, "{bd} within {bound} not found");
                    }
                }
            }
        }
    }
}
