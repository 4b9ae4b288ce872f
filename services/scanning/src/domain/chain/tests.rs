#![allow(clippy::unwrap_used)] // tests may unwrap

use std::sync::OnceLock;

use depthmill_geometry::Mesh;
use nalgebra::{Isometry3, Point3, Vector3};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

use super::routine::{calibration_plan, fit_chain};
use super::*;
use crate::domain::calibration::CalibrationError;

fn default_cell() -> MachineCell {
    MachineCell::new(&MachineGeometry::default(), &ChainErrors::default(), AreaScannerSpec::default())
        .unwrap()
}

/// The default mill's calibration, made once for the tests that need it.
fn default_calibration() -> &'static ChainCalibrationReport {
    static CAL: OnceLock<ChainCalibrationReport> = OnceLock::new();
    CAL.get_or_init(|| {
        let cell = default_cell();
        calibrate_chain(
            &cell,
            &ChainCalibration::nominal(cell.geometry()),
            &ChainCalibrationOptions::default(),
        )
        .unwrap()
    })
}

fn random_config(rng: &mut StdRng, g: &MachineGeometry) -> MachineConfig {
    let t = g.travel_mm;
    MachineConfig::new(
        rng.random_range(t[0][0]..t[0][1]),
        rng.random_range(t[1][0]..t[1][1]),
        rng.random_range(t[2][0]..t[2][1]),
        rng.random_range(-360.0..360.0),
    )
}

fn random_errors(rng: &mut StdRng) -> ChainErrors {
    let mut r = |s: f64| rng.random_range(-s..s);
    ChainErrors {
        scale_ppm: [r(200.0), r(200.0), r(200.0)],
        squareness_deg: [r(0.05), r(0.05), r(0.05)],
        a_axis_offset_mm: [r(1.0), r(1.0)],
        a_axis_tilt_deg: [r(0.1), r(0.1)],
        a_zero_deg: r(1.0),
        mount_offset_mm: [r(2.0), r(2.0), r(2.0)],
        mount_rotation_deg: [r(3.0), r(3.0), r(3.0)],
    }
}

#[test]
fn the_true_chain_places_points_where_the_simulation_has_them() {
    let mut rng = StdRng::seed_from_u64(31);
    let g = MachineGeometry::default();
    for _ in 0..20 {
        let truth = ChainTruth::new(&g, &random_errors(&mut rng)).unwrap();
        let chain = ChainCalibration::from_truth(&truth, random_config(&mut rng, &g));
        for _ in 0..20 {
            let c = random_config(&mut rng, &g);
            let p = Point3::new(
                rng.random_range(-30.0..30.0),
                rng.random_range(-30.0..30.0),
                rng.random_range(80.0..160.0),
            );
            let want = truth.rotor_from_sensor(&c) * p;
            let got = chain.place(&c, &p);
            assert!((want - got).norm() < 1e-9, "{want} vs {got}");
        }
    }
}

#[test]
fn the_drawing_is_the_chain_of_a_mill_without_errors() {
    let g = MachineGeometry::default();
    let exact = ChainTruth::new(&g, &ChainErrors::exact()).unwrap();
    let drawn = ChainCalibration::nominal(&g);
    assert_eq!(drawn.source, "drawing");
    let mut rng = StdRng::seed_from_u64(32);
    for _ in 0..50 {
        let c = random_config(&mut rng, &g);
        let p = Point3::new(rng.random_range(-30.0..30.0), rng.random_range(-30.0..30.0), 120.0);
        assert!((exact.rotor_from_sensor(&c) * p - drawn.place(&c, &p)).norm() < 1e-9);
    }
    assert!(drawn.scale_ppm().iter().all(|v| v.abs() < 1e-6));
    assert!(drawn.squareness_deg().iter().all(|v| v.abs() < 1e-9));
}

/// The ball's centre in the scanner's frame with the mill at `c`, exactly.
fn exact_view(truth: &ChainTruth, c: &MachineConfig, ball: [f64; 3]) -> Point3<f64> {
    truth.rotor_from_sensor(c).inverse() * Point3::from(ball)
}

#[test]
fn the_fit_recovers_random_chains_from_exact_views() {
    let mut rng = StdRng::seed_from_u64(33);
    let g = MachineGeometry::default();
    let opts = ChainCalibrationOptions::default();
    let plan = calibration_plan(&g, &opts).unwrap();
    for _ in 0..10 {
        let truth = ChainTruth::new(&g, &random_errors(&mut rng)).unwrap();
        let views: Vec<_> =
            plan.iter().map(|(l, c)| (l.clone(), *c, exact_view(&truth, c, opts.sphere_at_mm))).collect();
        let (cal, residuals, lin, rot, radius) = fit_chain(&views, opts.sphere_at_mm).unwrap();
        assert!(residuals.iter().all(|r| *r < 1e-6), "{residuals:?}");
        assert!(lin < 1e-6 && rot < 1e-6);
        assert!((radius - 30.0).abs() < 1e-6, "{radius}");
        for _ in 0..20 {
            let c = random_config(&mut rng, &g);
            let p = Point3::new(rng.random_range(-25.0..25.0), rng.random_range(-20.0..20.0), 120.0);
            let err = (truth.rotor_from_sensor(&c) * p - cal.place(&c, &p)).norm();
            assert!(err < 1e-5, "placement off by {err} mm at {c}");
        }
    }
}

#[test]
fn too_few_positions_of_an_axis_are_refused_naming_it() {
    let g = MachineGeometry::default();
    let opts = ChainCalibrationOptions::default();
    let truth = ChainTruth::new(&g, &ChainErrors::default()).unwrap();
    let plan = calibration_plan(&g, &opts).unwrap();
    let views = |skip: &[&str]| -> Vec<_> {
        plan.iter()
            .filter(|(l, _)| !skip.contains(&l.as_str()))
            .map(|(l, c)| (l.clone(), *c, exact_view(&truth, c, opts.sphere_at_mm)))
            .collect()
    };
    for (skip, axis) in [
        (&["X-"][..], "axis X"),
        (&["Z+"][..], "axis Z"),
        (&["A+30", "A+60", "A+90", "A-60", "A-90"][..], "axis A"),
    ] {
        match fit_chain(&views(skip), opts.sphere_at_mm) {
            Err(CalibrationError::Degenerate(m)) => assert!(m.contains(axis), "{m}"),
            other => panic!("{skip:?}: {other:?}"),
        }
    }
    // Three A positions over too short an arc.
    let short: Vec<_> = plan
        .iter()
        .filter(|(l, _)| !l.starts_with('A'))
        .map(|(l, c)| (l.clone(), *c, exact_view(&truth, c, opts.sphere_at_mm)))
        .chain([5.0, 10.0].map(|da| {
            let c = MachineConfig { a: plan[0].1.a + da, ..plan[0].1 };
            (format!("A+{da}"), c, exact_view(&truth, &c, opts.sphere_at_mm))
        }))
        .collect();
    match fit_chain(&short, opts.sphere_at_mm) {
        Err(CalibrationError::Degenerate(m)) => assert!(m.contains("of A"), "{m}"),
        other => panic!("{other:?}"),
    }
}

#[test]
fn bad_options_and_profiles_are_refused_naming_the_field() {
    let spec = AreaScannerSpec::default();
    let cases: Vec<(ChainCalibrationOptions, &str)> = vec![
        (ChainCalibrationOptions { sphere_radius_mm: -1.0, ..Default::default() }, "sphere_radius_mm"),
        (ChainCalibrationOptions { sphere_at_mm: [25.0, 1.0, 2.0], ..Default::default() }, "from the A axis"),
        (ChainCalibrationOptions { a_step_deg: 4.0, a_steps: 2, ..Default::default() }, "at least 20"),
        (ChainCalibrationOptions { a_steps: 0, ..Default::default() }, "a_steps"),
        (ChainCalibrationOptions { standoff_mm: 300.0, ..Default::default() }, "standoff_mm"),
        (
            ChainCalibrationOptions { linear_steps_mm: [10.0, f64::NAN, 10.0], ..Default::default() },
            "linear_steps_mm[1]",
        ),
    ];
    for (o, what) in cases {
        let e = o.validate(&spec).unwrap_err().to_string();
        assert!(e.contains(what), "{e} should name {what}");
    }
    let e = ChainErrors { squareness_deg: [0.0, 5.0, 0.0], ..ChainErrors::default() }.validate().unwrap_err();
    assert!(e.to_string().contains("squareness_deg"), "{e}");
    let e = AreaScannerSpec { grid: [1, 100], ..spec.clone() }.validate().unwrap_err();
    assert!(e.to_string().contains("grid"), "{e}");
    let g = MachineGeometry::default();
    let e = g.check_travel(&MachineConfig::new(10.0, 150.0, -10.0, 0.0)).unwrap_err();
    assert!(e.to_string().contains("axis Y") && e.to_string().contains("[0, 100]"), "{e}");
    // A calibration that cannot run leaves nothing behind: the call is refused before scanning.
    let cell = default_cell();
    let previous = ChainCalibration::nominal(cell.geometry());
    let bad = ChainCalibrationOptions { sphere_at_mm: [25.0, 0.0, 300.0], ..Default::default() };
    assert!(calibrate_chain(&cell, &previous, &bad).is_err());
}

/// A flat square at `z` (normal +Z).
fn plate(z: f64, half: f64) -> Mesh {
    let vertices = vec![
        Point3::new(-half, -half, z),
        Point3::new(half, -half, z),
        Point3::new(half, half, z),
        Point3::new(-half, half, z),
    ];
    Mesh { vertices, triangles: vec![[0, 1, 2], [0, 2, 3]] }
}

#[test]
fn the_area_scanner_sees_a_plate_with_its_noise_and_window() {
    let spec = AreaScannerSpec::default();
    let scanner = AreaScanner::new(spec.clone(), &plate(0.0, 200.0), 7).unwrap();
    // Looking straight down from 120 mm.
    let pose = Isometry3::new(Vector3::new(0.0, 0.0, 120.0), Vector3::x() * std::f64::consts::PI);
    let shot = scanner.shot(&pose, 0);
    let n = (spec.grid[0] * spec.grid[1]) as usize;
    assert_eq!(shot.points.len(), n, "every ray sees the plate");
    let dz: Vec<f64> = shot.points.iter().map(|p| (pose * p).z).collect();
    let mean = dz.iter().sum::<f64>() / n as f64;
    let sd = (dz.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / n as f64).sqrt();
    assert!(mean.abs() < 5e-4, "mean {mean}");
    assert!((sd / spec.noise_sigma_mm - 1.0).abs() < 0.1, "sd {sd}");
    // The field: 50 x 40 mm at 120 mm.
    let xs: Vec<f64> = shot.truth.iter().map(|p| p.x).collect();
    let span = xs.iter().copied().fold(f64::NEG_INFINITY, f64::max)
        - xs.iter().copied().fold(f64::INFINITY, f64::min);
    assert!((span - 50.0).abs() < 0.01, "{span}");
    // The same shot replays exactly; another shot draws other noise.
    assert_eq!(scanner.shot(&pose, 0).points, shot.points);
    assert_ne!(scanner.shot(&pose, 1).points, shot.points);
    // Out of the window: nothing.
    let far = Isometry3::new(Vector3::new(0.0, 0.0, 170.0), Vector3::x() * std::f64::consts::PI);
    assert!(scanner.shot(&far, 2).points.is_empty());
    // Beyond the incidence limit: nothing.
    // 77° from the vertical, the middle of the field 120 mm away: every ray meets the plate
    // more than 65° off its normal.
    let steep = Isometry3::new(Vector3::new(0.0, 0.0, 27.0), Vector3::x() * (std::f64::consts::PI - 1.35));
    assert!(scanner.shot(&steep, 3).points.is_empty());
}

#[test]
fn the_noise_is_standard_normal() {
    let n = 200_000;
    let v: Vec<f64> = (0..n).map(|k| area::gauss_for_test(5, 3, k)).collect();
    let mean = v.iter().sum::<f64>() / n as f64;
    let var = v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n as f64;
    assert!(mean.abs() < 0.01 && (var - 1.0).abs() < 0.02, "{mean} {var}");
    let within1 = v.iter().filter(|x| x.abs() < 1.0).count() as f64 / n as f64;
    assert!((within1 - 0.6827).abs() < 0.01, "{within1}");
}

#[test]
fn calibration_recovers_the_miscalibrated_mill() {
    let r = default_calibration();
    let t = r.truth.unwrap();
    eprintln!(
        "chain calibration: placement over the work volume {:.4} -> {:.4} mm, A axis {:.4}° / {:.4} mm off, \
         linear fit {:.4} mm, rotary fit {:.4} mm, scale {:?} ppm, squareness {:?}°, {} shots, {:.1} s",
        t.placement_error_before_mm,
        t.placement_error_mm,
        t.a_axis_direction_error_deg,
        t.a_axis_position_error_mm,
        r.linear_fit_rms_mm,
        r.rotary_fit_rms_mm,
        r.scale_ppm.map(|v| v.round()),
        r.squareness_deg.map(|v| (v * 1e4).round() / 1e4),
        r.shots,
        r.scan_time_s,
    );
    assert!(t.placement_error_before_mm > 1.0, "{t:?}");
    assert!(t.placement_error_mm < 0.025, "{t:?}");
    assert!(t.a_axis_direction_error_deg < 0.005, "{t:?}");
    assert!(r.scan_time_s < 60.0, "{}", r.scan_time_s);
    assert_eq!(r.observations.len(), 13);
    assert!(r.observations.iter().all(|o| o.residual_mm < 0.01 && o.points >= 200), "{:?}", r.observations);
    // The measured slides against the profile's errors.
    let e = ChainErrors::default();
    for i in 0..3 {
        assert!((r.scale_ppm[i] - e.scale_ppm[i]).abs() < 150.0, "{:?}", r.scale_ppm);
    }
    assert!((r.squareness_deg[0] - e.squareness_deg[0]).abs() < 0.01, "{:?}", r.squareness_deg);
}

/// A block along the A axis, `x` from the faceplate, a square section about the axis.
fn block(x0: f64, x1: f64, half: f64) -> Mesh {
    let mut m = Mesh::cuboid(x1 - x0, 2.0 * half, 2.0 * half);
    for v in &mut m.vertices {
        *v += Vector3::new(x0, -half, -half);
    }
    m
}

#[test]
fn partial_scans_merge_by_the_chain_within_twice_the_noise_only_once_calibrated() {
    let cell = default_cell();
    let cal = &default_calibration().calibration;
    let part = block(10.0, 70.0, 18.0);
    let (cloud, r) = scan_on_machine(&cell, &part, cal, &ChainScanOptions::default()).unwrap();
    eprintln!(
        "chain scan: {} shots, {} points, {:.1} s; merge RMS drawing {:.4} mm, calibrated {:.4} mm, true chain {:.4} mm; \
         registration RMS drawing {:.4}, calibrated {:.4}",
        r.shots,
        r.points,
        r.scan_time_s,
        r.registration_drawing.merge_rms_mm,
        r.registration.merge_rms_mm,
        r.registration_truth.merge_rms_mm,
        r.registration_drawing.rms_mm,
        r.registration.rms_mm,
    );
    assert_eq!(cloud.points.len() as u64, r.points);
    assert_eq!(cloud.shot.len(), cloud.points.len());
    assert_eq!(u64::from(*cloud.shot.last().unwrap()) + 1, r.shots);
    assert!(r.points > 100_000);
    // Four faces, each seen at one A: the shots share no points (no overlap, no markers).
    let noise = r.registration_truth.rms_mm;
    assert!(noise < 0.02, "{noise}");
    assert!(r.registration.merge_rms_mm <= 2.0 * noise, "{r:?}");
    assert!(r.registration.rms_mm <= 3.0 * noise, "{r:?}");
    assert!(r.registration_drawing.merge_rms_mm > 10.0 * r.registration.merge_rms_mm, "{r:?}");
    // Placed points lie on the block's faces.
    let off = cloud
        .points
        .iter()
        .map(|p| {
            let d = [(p.y.abs() - 18.0).abs(), (p.z.abs() - 18.0).abs(), (p.x - 70.0).abs()];
            d.into_iter().fold(f64::INFINITY, f64::min)
        })
        .fold(0.0, f64::max);
    assert!(off < 0.15, "a point {off} mm off the block");
}

#[test]
fn a_part_out_of_the_travels_is_refused_naming_the_axis() {
    let cell = default_cell();
    let cal = ChainCalibration::nominal(cell.geometry());
    let e =
        scan_on_machine(&cell, &block(10.0, 400.0, 10.0), &cal, &ChainScanOptions::default()).unwrap_err();
    assert!(e.to_string().contains("axis X"), "{e}");
    let e = scan_on_machine(
        &cell,
        &block(10.0, 40.0, 10.0),
        &cal,
        &ChainScanOptions { standoff_mm: 20.0, ..Default::default() },
    )
    .unwrap_err();
    assert!(e.to_string().contains("standoff_mm"), "{e}");
}
