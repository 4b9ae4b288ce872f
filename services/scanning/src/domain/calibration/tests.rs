#![allow(clippy::unwrap_used)] // tests may unwrap

use std::sync::OnceLock;

use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

use super::fit::{AlignmentMoments, CapturedFrame, fit_plane, fit_sphere_algebraic, least_squares};
use super::*;
use crate::domain::scan::{ScanOptions, ScanOutput, ScanSession};

fn gauss(rng: &mut StdRng) -> f64 {
    // Box-Muller.
    let u: f64 = rng.random_range(1e-12..1.0);
    let v: f64 = rng.random_range(0.0..1.0);
    (-2.0 * u.ln()).sqrt() * (2.0 * std::f64::consts::PI * v).cos()
}

/// Runs a calibration scan on `cell` (stations at their commanded angles) and fits it.
fn calibrate(
    cell: &Cell,
    opts: &CalibrationOptions,
) -> Result<(Calibration, CalibrationReport), CalibrationError> {
    let (mut s, plan) = calibration_session(cell, CellLayout::default(), opts)?;
    for st in &plan.stations {
        s.run_station(st, st.table_deg, false, &mut |_, _| {}, &|| false)
            .map_err(|e| CalibrationError::Scan(e.to_string()))?;
    }
    s.finish_calibration()
}

/// The default miscalibrated cell's calibration, made once for the tests that need it.
fn default_calibration() -> &'static (Calibration, CalibrationReport) {
    static CAL: OnceLock<(Calibration, CalibrationReport)> = OnceLock::new();
    CAL.get_or_init(|| {
        let cell = Cell::new(&CellLayout::default(), &CellErrors::default(), None);
        calibrate(&cell, &CalibrationOptions::default()).unwrap()
    })
}

#[test]
fn the_nominal_table_model_is_the_layouts_drawing() {
    let layout = CellLayout::default();
    let m = TableModel::nominal(&layout);
    for deg in [0.0, 37.0, 180.0, 301.5] {
        let a = m.world_from_table(deg);
        let b = layout.world_from_table(deg);
        assert!((a.translation.vector - b.translation.vector).norm() < 1e-12);
        assert!(a.rotation.angle_to(&b.rotation) < 1e-12);
    }
    let cal = Calibration::nominal(&layout);
    assert!(
        (cal.flange_from_scanner().translation.vector
            - depthmill_geometry::arm::ArmModel::scanner_bracket().translation.vector)
            .norm()
            < 1e-12
    );
}

#[test]
fn the_sphere_fit_finds_a_noisy_cap() {
    let mut rng = StdRng::seed_from_u64(3);
    for _ in 0..20 {
        let c = Point3::new(
            rng.random_range(-500.0..500.0),
            rng.random_range(-500.0..500.0),
            rng.random_range(-100.0..100.0),
        );
        let r = rng.random_range(5.0..40.0);
        // A cap of 70° round +Z, as a scanner sees a ball from above.
        let pts: Vec<Point3<f64>> = (0..3000)
            .map(|_| {
                let th: f64 = rng.random_range(0.0..70f64.to_radians());
                let ph: f64 = rng.random_range(0.0..std::f64::consts::TAU);
                let d = Vector3::new(th.sin() * ph.cos(), th.sin() * ph.sin(), th.cos());
                c + d * (r + 0.035 * gauss(&mut rng))
            })
            .collect();
        let (fc, fr) = fit_sphere_algebraic(&pts).unwrap();
        assert!((fc - c).norm() < 0.05, "{fc} vs {c}");
        assert!((fr - r).abs() < 0.05, "{fr} vs {r}");
    }
    // Too few points, or points on a plane: no sphere.
    assert!(fit_sphere_algebraic(&[Point3::origin(); 3]).is_none());
}

#[test]
fn the_plane_fit_finds_a_tilted_plane_and_refuses_a_line() {
    let mut rng = StdRng::seed_from_u64(4);
    let n = Vector3::new(0.01, -0.02, 1.0).normalize();
    let o = Point3::new(500.0, 10.0, -100.0);
    let u = n.cross(&Vector3::x()).normalize();
    let v = n.cross(&u);
    let pts: Vec<Point3<f64>> = (0..5000)
        .map(|_| {
            o + u * rng.random_range(-50.0..50.0)
                + v * rng.random_range(-50.0..50.0)
                + n * 0.035 * gauss(&mut rng)
        })
        .collect();
    let (c, fnorm, rms) = fit_plane(&pts).unwrap();
    assert!(fnorm.angle(&n).to_degrees() < 0.002, "{fnorm}");
    assert!(n.dot(&(c - o)).abs() < 0.005);
    assert!((rms - 0.035).abs() < 0.003, "{rms}");
    let line: Vec<Point3<f64>> = (0..100).map(|k| Point3::new(k as f64, 2.0 * k as f64, 0.0)).collect();
    assert!(fit_plane(&line).is_none());
}

/// Reference for the merge error: explicit Kabsch on the stored points.
fn kabsch_rms(a: &[Point3<f64>], b: &[Point3<f64>]) -> f64 {
    let n = a.len() as f64;
    let ma = a.iter().fold(Vector3::zeros(), |s, p| s + p.coords) / n;
    let mb = b.iter().fold(Vector3::zeros(), |s, p| s + p.coords) / n;
    let h = a
        .iter()
        .zip(b)
        .fold(nalgebra::Matrix3::zeros(), |s, (p, q)| s + (p.coords - ma) * (q.coords - mb).transpose());
    let svd = h.svd(true, true);
    let (u, vt) = (svd.u.unwrap(), svd.v_t.unwrap());
    let mut d = nalgebra::Matrix3::identity();
    d[(2, 2)] = (vt.transpose() * u.transpose()).determinant().signum();
    let r = vt.transpose() * d * u.transpose();
    let sq: f64 = a.iter().zip(b).map(|(p, q)| (r * (p.coords - ma) + mb - q.coords).norm_squared()).sum();
    (sq / n).sqrt()
}

#[test]
fn alignment_moments_match_an_explicit_kabsch_fit_on_random_clouds() {
    let mut rng = StdRng::seed_from_u64(5);
    for case in 0..30 {
        let n = rng.random_range(3..400);
        let truth: Vec<Point3<f64>> = (0..n)
            .map(|_| {
                Point3::new(
                    rng.random_range(300.0..700.0),
                    rng.random_range(-200.0..200.0),
                    rng.random_range(-150.0..50.0),
                )
            })
            .collect();
        let g = Isometry3::from_parts(
            Translation3::new(
                rng.random_range(-3.0..3.0),
                rng.random_range(-3.0..3.0),
                rng.random_range(-3.0..3.0),
            ),
            UnitQuaternion::from_scaled_axis(Vector3::new(
                rng.random_range(-0.05..0.05),
                rng.random_range(-0.05..0.05),
                rng.random_range(-0.05..0.05),
            )),
        );
        let noise = if case % 3 == 0 { 0.0 } else { rng.random_range(0.001..0.2) };
        let placed: Vec<Point3<f64>> = truth
            .iter()
            .map(|p| g * p + Vector3::new(gauss(&mut rng), gauss(&mut rng), gauss(&mut rng)) * noise)
            .collect();
        // Accumulated in two halves and merged, as the scan's threads do.
        let (mut a, mut b) = (AlignmentMoments::default(), AlignmentMoments::default());
        for (k, (p, q)) in placed.iter().zip(&truth).enumerate() {
            if k % 2 == 0 { a.add(p, q) } else { b.add(p, q) }
        }
        a.merge(&b);
        assert_eq!(a.count(), n as u64);
        let want = kabsch_rms(&placed, &truth);
        let got = a.rms_after_alignment();
        // The moments lose about 1e-5 mm to cancellation (sums of squares of 500 mm coordinates).
        assert!((got - want).abs() < 2e-5 + 1e-6 * want, "case {case}: {got} vs {want}");
    }
}

#[test]
fn least_squares_solves_a_circle_fit() {
    let pts: Vec<(f64, f64)> = (0..12)
        .map(|k| {
            let a = k as f64 * 0.5;
            (3.0 + 2.0 * a.cos(), -1.0 + 2.0 * a.sin())
        })
        .collect();
    let x = least_squares(vec![0.0, 0.0, 1.0], |p, r| {
        for (x, y) in &pts {
            r.push((x - p[0]).hypot(y - p[1]) - p[2]);
        }
    })
    .unwrap();
    assert!((x[0] - 3.0).abs() < 1e-6 && (x[1] + 1.0).abs() < 1e-6 && (x[2] - 2.0).abs() < 1e-6, "{x:?}");
}

#[test]
fn bad_options_and_profiles_are_refused_naming_the_field() {
    let layout = CellLayout::default();
    let two = CalibrationOptions { table_angles_deg: vec![0.0, 90.0], ..Default::default() };
    assert!(two.validate(&layout).unwrap_err().to_string().contains("at 3 or more"));
    let near = CalibrationOptions { table_angles_deg: vec![0.0, 20.0, 40.0, 60.0], ..Default::default() };
    assert!(near.validate(&layout).unwrap_err().to_string().contains("cover only 60.0°"));
    let same = CalibrationOptions { table_angles_deg: vec![0.0, 90.0, 360.0], ..Default::default() };
    assert!(same.validate(&layout).unwrap_err().to_string().contains("within 5°"));
    let off = CalibrationOptions { sphere_at_mm: [190.0, 0.0, 30.0], ..Default::default() };
    assert!(off.validate(&layout).unwrap_err().to_string().contains("sphere_at_mm"));
    let big = CalibrationOptions { sphere_radius_mm: 80.0, ..Default::default() };
    assert!(big.validate(&layout).unwrap_err().to_string().contains("sphere_radius_mm"));
    let bad = CellErrors { table_axis_tilt_deg: [5.0, 0.0], ..Default::default() };
    assert!(bad.validate().unwrap_err().to_string().contains("table_axis_tilt_deg[0]"));
    let nan = CellErrors {
        scanner_mount: Offset { translation_mm: [f64::NAN, 0.0, 0.0], rotation_deg: [0.0; 3] },
        ..Default::default()
    };
    assert!(nan.validate().unwrap_err().to_string().contains("scanner_mount.translation_mm[0]"));
    assert!(CellErrors::default().validate().is_ok());
    let far = Calibration {
        table: TableModel { axis_x_mm: 600.0, ..TableModel::nominal(&layout) },
        scanner_mount: Offset::default(),
    };
    assert!(far.validate(&layout).unwrap_err().to_string().contains("table.axis_x_mm"));
}

#[test]
fn calibration_recovers_the_miscalibrated_cell() {
    let (cal, report) = default_calibration();
    eprintln!("{}", serde_json::to_string_pretty(report).unwrap());
    let truth = report.truth.as_ref().unwrap();
    // Before: the drawing is off by the profile's millimetre; after: within a few micrometres.
    assert!(truth.table_error_before_mm > 1.0, "{truth:?}");
    assert!(truth.table_error_mm < 0.03, "{truth:?}");
    assert!(truth.mount_error_before_mm > 0.4, "{truth:?}");
    assert!(truth.mount_error_mm < 0.03, "{truth:?}");
    let (before, after) = (report.registration_before.unwrap(), report.registration_after.unwrap());
    assert!(before.merge_rms_mm > 0.2, "{before:?}");
    assert!(after.rms_mm < 0.035 && after.merge_rms_mm < 0.035, "{after:?}");
    assert!(report.centre_spread_before_mm > 0.5 && report.centre_spread_after_mm < 0.02, "{report:?}");
    assert!(report.sphere_rms_mm < 0.06, "{}", report.sphere_rms_mm);
    assert!(report.scan_time_s < 60.0, "{} s of simulated scanning", report.scan_time_s);
    assert!(cal.validate(&CellLayout::default()).is_ok());
}

/// A dome on a base, as the scan tests use.
fn dome_mesh() -> depthmill_geometry::Mesh {
    let (hx, step) = (45.0f64, 1.0f64);
    let n = (2.0 * hx / step).round() as usize + 1;
    let f = |x: f64, y: f64| 5.0 + 10.0 * (1.0 - (x * x + y * y) / 1600.0).max(0.0);
    let mut vertices = Vec::new();
    for j in 0..n {
        for i in 0..n {
            let (x, y) = (-hx + step * i as f64, -hx + step * j as f64);
            vertices.push(Point3::new(x, y, f(x, y)));
        }
    }
    let mut triangles = Vec::new();
    for j in 0..n - 1 {
        for i in 0..n - 1 {
            let a = (j * n + i) as u32;
            triangles.push([a, a + 1, a + n as u32 + 1]);
            triangles.push([a, a + n as u32 + 1, a + n as u32]);
        }
    }
    depthmill_geometry::Mesh { vertices, triangles }
}

fn scan(cell: Cell) -> ScanOutput {
    let mut s =
        ScanSession::with_cell(&dome_mesh(), ScanOptions::default(), CellLayout::default(), cell).unwrap();
    let plan = s.plan().unwrap();
    for st in &plan.stations {
        s.run_station(st, st.table_deg, false, &mut |_, _| {}, &|| false).unwrap();
    }
    s.finish()
}

#[test]
fn a_scan_registers_within_twice_the_noise_only_once_calibrated() {
    let layout = CellLayout::default();
    let errors = CellErrors::default();
    let (cal, _) = default_calibration();
    let raw = scan(Cell::new(&layout, &errors, None));
    let fixed = scan(Cell::new(&layout, &errors, Some(*cal)));
    let noise = crate::domain::scanner::ScannerSpec::slp400().noise_sigma_mm;
    let (r, f) = (&raw.report, &fixed.report);
    eprintln!(
        "uncalibrated: rms {:.4} merge {:.4} mm; calibrated: rms {:.4} merge {:.4} mm",
        r.registration_rms_mm,
        r.registration_merge_rms_mm,
        f.registration_rms_mm,
        f.registration_merge_rms_mm
    );
    assert!(!r.calibrated && f.calibrated);
    // The calibration's residual leaves each pass a few hundredths off the others; moving every
    // pass onto the cloud's surface takes most of it off.
    let aligned = f.pass_alignment.as_ref().expect("the passes were aligned");
    eprintln!(
        "calibrated, before the pass alignment: rms {:.4} merge {:.4} mm",
        aligned.registration_rms_before_mm, aligned.registration_merge_rms_before_mm
    );
    assert!(aligned.passes.iter().any(|p| p.applied));
    assert!(f.registration_merge_rms_mm < 0.8 * aligned.registration_merge_rms_before_mm);
    assert!(f.registration_rms_mm < aligned.registration_rms_before_mm);
    assert!(f.registration_merge_rms_mm <= 2.0 * noise, "{}", f.registration_merge_rms_mm);
    assert!(f.registration_rms_mm <= 2.0 * noise, "{}", f.registration_rms_mm);
    assert!(
        r.registration_merge_rms_mm > 5.0 * f.registration_merge_rms_mm,
        "{} vs {}",
        r.registration_merge_rms_mm,
        f.registration_merge_rms_mm
    );
}

#[test]
fn a_scan_calibrates_the_cell_at_its_own_stations_and_places_the_part_with_it() {
    let layout = CellLayout::default();
    let errors = CellErrors::default();
    let mesh = dome_mesh();
    let opts = ScanOptions::default();
    let cell = || Cell::new(&layout, &errors, None);
    let mut s = ScanSession::with_cell_calibrating(
        &mesh,
        opts.clone(),
        layout,
        cell(),
        CalibrationOptions::default(),
    )
    .unwrap();
    let plan = s.plan().unwrap();
    let alone = ScanSession::with_cell(&mesh, opts.clone(), layout, cell()).unwrap().plan().unwrap();
    // The table turns once: the routine's passes head each of the scan's own stations.
    let angles =
        |p: &crate::domain::scan::ScanPlan| p.stations.iter().map(|s| s.table_deg).collect::<Vec<_>>();
    assert_eq!(angles(&plan), angles(&alone));
    for (both, scan) in plan.stations.iter().zip(&alone.stations) {
        assert!(both.passes.len() >= scan.passes.len() + 2, "{} passes", both.passes.len());
        let ids: Vec<u16> = both.passes.iter().rev().take(scan.passes.len()).rev().map(|p| p.id).collect();
        assert_eq!(
            ids,
            scan.passes.iter().map(|p| p.id).collect::<Vec<_>>(),
            "the part's passes keep their ids"
        );
    }
    for st in &plan.stations {
        s.run_station(st, st.table_deg, false, &mut |_, _| {}, &|| false).unwrap();
    }
    assert!(s.calibrating_in_scan());
    assert!(s.points().is_empty(), "the part's frames wait for the calibration");
    let (cal, report) = s.calibrate_in_scan().unwrap();
    assert!(!s.calibrating_in_scan());
    assert!(matches!(s.calibrate_in_scan(), Err(crate::domain::scan::ScanError::Calibration(_))));
    let truth = report.truth.as_ref().unwrap();
    eprintln!("in-scan calibration: {truth:?}, after {:?}", report.registration_after);
    assert!(truth.table_error_before_mm > 1.0 && truth.table_error_mm < 0.05, "{truth:?}");
    assert!(truth.mount_error_before_mm > 0.4 && truth.mount_error_mm < 0.03, "{truth:?}");
    assert!(cal.validate(&layout).is_ok());
    let out = s.finish();
    let noise = crate::domain::scanner::ScannerSpec::slp400().noise_sigma_mm;
    let r = &out.report;
    eprintln!("registration rms {:.4} merge {:.4} mm", r.registration_rms_mm, r.registration_merge_rms_mm);
    assert!(r.calibrated);
    assert!(r.registration_rms_mm <= 2.0 * noise && r.registration_merge_rms_mm <= 2.0 * noise, "{r:?}");
    // Only the part: the sphere 100 mm from the axis is left out of the cloud.
    assert!(r.points > 100_000, "{}", r.points);
    let far = out.cloud.points.iter().filter(|p| p.x.abs() > 47.0 || p.y.abs() > 47.0).count();
    assert_eq!(far, 0, "points off the part");
    // Each pass reports the points it placed; the sphere's passes place none.
    let per_pass: u64 = r.stations.iter().flat_map(|s| &s.passes).map(|p| p.points).sum();
    assert_eq!(per_pass, r.points);
    for (both, scan) in plan.stations.iter().zip(&alone.stations) {
        let report = r.stations.iter().find(|x| x.table_deg_commanded == both.table_deg).unwrap();
        let sphere_passes = both.passes.len() - scan.passes.len();
        assert!(report.passes[..sphere_passes].iter().all(|p| p.points == 0));
        assert!(report.passes[sphere_passes..].iter().all(|p| p.points > 0));
    }

    // A part that reaches the nest, or stations that cannot find the axis: the caller calibrates
    // first, told why.
    let mut big = dome_mesh();
    for v in &mut big.vertices {
        v.x *= 1.3;
        v.y *= 1.3;
    }
    let e =
        ScanSession::with_cell_calibrating(&big, opts.clone(), layout, cell(), CalibrationOptions::default())
            .err()
            .unwrap();
    assert!(
        matches!(&e, crate::domain::scan::ScanError::NotInScan(m) if m.contains("reference sphere")),
        "{e}"
    );
    let one = ScanOptions { table_angles_deg: vec![90.0], ..opts };
    let e =
        match ScanSession::with_cell_calibrating(&mesh, one, layout, cell(), CalibrationOptions::default())
            .unwrap()
            .plan()
        {
            Ok(p) => panic!("planned at {:?}", angles(&p)),
            Err(e) => e,
        };
    assert!(matches!(&e, crate::domain::scan::ScanError::NotInScan(m) if m.contains("3 or more")), "{e}");
}

#[test]
fn degenerate_calibration_data_is_refused_saying_what_is_missing() {
    let layout = CellLayout::default();
    let cell = Cell::new(&layout, &CellErrors::default(), None);
    let opts = CalibrationOptions::default();
    let (mut s, plan) = calibration_session(&cell, layout, &opts).unwrap();
    for st in &plan.stations {
        s.run_station(st, st.table_deg, false, &mut |_, _| {}, &|| false).unwrap();
    }
    // Reach into the capture through a fit on edited frames.
    let frames = capture_of(s);
    let previous = Calibration::nominal(&layout);
    // The sphere never seen at the second angle.
    let mut blind = frames.clone();
    for f in blind.iter_mut().filter(|f| f.station == 1) {
        f.sphere.clear();
    }
    let e = fit::solve(&blind, &opts, &layout, &previous, None).unwrap_err().to_string();
    assert!(e.contains("at table angle 90° the reference sphere gave 0 points"), "{e}");
    // Seen from one direction only: the mount cannot be found.
    let r0 = frames[0].world_from_flange.rotation;
    let one_view: Vec<CapturedFrame> = frames
        .iter()
        .filter(|f| f.world_from_flange.rotation.angle_to(&r0) < 1f64.to_radians())
        .cloned()
        .collect();
    let e = fit::solve(&one_view, &opts, &layout, &previous, None).unwrap_err().to_string();
    assert!(e.contains("about two axes"), "{e}");
    // Something else than the reference sphere.
    let wrong = CalibrationOptions { sphere_radius_mm: 20.0, ..opts.clone() };
    let e = fit::solve(&frames, &wrong, &layout, &previous, None).unwrap_err().to_string();
    assert!(e.contains("not the reference's 20 mm"), "{e}");
}

fn capture_of(s: ScanSession) -> Vec<CapturedFrame> {
    s.captured_frames()
}
