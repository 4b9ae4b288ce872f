#![allow(clippy::unwrap_used)] // tests may unwrap

use super::*;
use crate::domain::scanner::tests::add_box;
use depthmill_geometry::arm::pose_distance;
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

/// Height field `z = f(x, y)` over `[-hx, hx] × [-hy, hy]` at `step` mm, as a triangle sheet.
fn height_field(hx: f64, hy: f64, step: f64, f: impl Fn(f64, f64) -> f64) -> Mesh {
    let nx = (2.0 * hx / step).round() as usize + 1;
    let ny = (2.0 * hy / step).round() as usize + 1;
    let mut vertices = Vec::with_capacity(nx * ny);
    for j in 0..ny {
        for i in 0..nx {
            let x = -hx + 2.0 * hx * i as f64 / (nx - 1) as f64;
            let y = -hy + 2.0 * hy * j as f64 / (ny - 1) as f64;
            vertices.push(Point3::new(x, y, f(x, y)));
        }
    }
    let mut triangles = Vec::new();
    for j in 0..ny - 1 {
        for i in 0..nx - 1 {
            let a = (j * nx + i) as u32;
            let b = a + 1;
            let c = a + nx as u32;
            let d = c + 1;
            triangles.push([a, b, d]);
            triangles.push([a, d, c]);
        }
    }
    Mesh { vertices, triangles }
}

/// A low dome: `z = 5 + 10·(1 − r²/40²)` inside r < 40, 5 outside (a relief on a base).
fn dome(x: f64, y: f64) -> f64 {
    let r2 = x * x + y * y;
    5.0 + 10.0 * (1.0 - r2 / 1600.0).max(0.0)
}

/// Distance from `p` to the height field `f` along the normal, to first order:
/// `|z − f| / sqrt(1 + |∇f|²)` (exact for planes, a fine approximation for the gentle dome).
fn field_distance(p: &Point3<f64>, f: &impl Fn(f64, f64) -> f64) -> f64 {
    let h = 1e-4;
    let gx = (f(p.x + h, p.y) - f(p.x - h, p.y)) / (2.0 * h);
    let gy = (f(p.x, p.y + h) - f(p.x, p.y - h)) / (2.0 * h);
    (p.z - f(p.x, p.y)).abs() / (1.0 + gx * gx + gy * gy).sqrt()
}

fn scan_all(mesh: &Mesh, opts: ScanOptions) -> ScanOutput {
    let mut s = ScanSession::new(mesh, opts, CellLayout::default()).unwrap();
    let plan = s.plan().unwrap();
    for st in &plan.stations {
        s.run_station(st, st.table_deg, false, &mut |_, _| {}, &|| false).unwrap();
    }
    s.finish()
}

/// RMS and max distance of the points (inside `|x|, |y| < lim`, away from the sheet's border)
/// from the surface.
fn distances(out: &ScanOutput, f: impl Fn(f64, f64) -> f64, lim: f64) -> (f64, f64, usize) {
    let mut sq = 0.0;
    let mut mx: f64 = 0.0;
    let mut n = 0;
    for p in out.cloud.points_f64() {
        if p.x.abs() > lim || p.y.abs() > lim {
            continue;
        }
        let d = field_distance(&p, &f);
        sq += d * d;
        mx = mx.max(d);
        n += 1;
    }
    ((sq / n.max(1) as f64).sqrt(), mx, n)
}

#[test]
fn automatic_plan_covers_the_part_and_every_pass_is_reachable() {
    let mesh = height_field(45.0, 30.0, 1.0, dome);
    let mut s = ScanSession::new(&mesh, ScanOptions::default(), CellLayout::default()).unwrap();
    let plan = s.plan().unwrap();
    assert_eq!(plan.stations.len(), 4);
    let arm = ArmModel::viper_s650();
    let spec = ScannerSpec::slp400();
    for st in &plan.stations {
        assert!(!st.passes.is_empty());
        let (lo, hi) = s.placement().world_extent(s.layout(), st.table_deg);
        // The lines together span the part's extent across the passes.
        let half = 0.5 * spec.line_length_at(150.0);
        let xs: Vec<f64> = st.passes.iter().map(|p| p.start.translation.vector.x).collect();
        let min_x = xs.iter().copied().fold(f64::INFINITY, f64::min) - half;
        let max_x = xs.iter().copied().fold(f64::NEG_INFINITY, f64::max) + half;
        assert!(min_x <= lo.x + 1e-6 && max_x >= hi.x - 1e-6, "{min_x}..{max_x} vs {}..{}", lo.x, hi.x);
        for p in &st.passes {
            // FK of the planned joints is the planned pose.
            let (dp, da) = pose_distance(&arm.fk(&p.q_start_deg), &p.start);
            assert!(dp < 1e-6 && da < 1e-6, "start pose off by {dp} mm / {da} rad");
            let (dp, _) = pose_distance(&arm.fk(&p.q_end_deg), &p.end);
            assert!(dp < 1e-6);
            // The sensor is at the standoff above the top and covers Y with margin.
            assert!((p.start.translation.vector.z - (hi.z + 150.0)).abs() < 1e-9);
            let (y0, y1) = (p.start.translation.vector.y, p.end.translation.vector.y);
            assert!(y0.min(y1) < lo.y && y0.max(y1) > hi.y);
            assert!(p.min_dexterity > 0.0);
        }
    }
}

#[test]
fn move_duration_matches_the_controllers_timing() {
    let mut rng = StdRng::seed_from_u64(3);
    let arm = ArmModel::viper_s650();
    for _ in 0..200 {
        let mut c = MotionController::viper_s650();
        c.initialize(0.0).unwrap();
        let t0 = c.home(0.0, 1.0).unwrap();
        let q0 = c.read_position(t0).unwrap();
        let q1: [f64; 6] = std::array::from_fn(|j| {
            let l = &arm.limits[j];
            rng.random_range(l.min_deg..l.max_deg)
        });
        let frac = rng.random_range(0.05..1.0);
        let arrive = c.move_joints(t0, &q1, frac).unwrap();
        let expect = plan::move_duration(&arm.limits, &q0, &q1, frac);
        assert!((arrive - t0 - expect).abs() < 1e-9, "{} vs {expect}", arrive - t0);
        // And the fraction that gives a wanted duration reproduces it.
        let want = expect * rng.random_range(1.0..3.0);
        let f = plan::speed_fraction_for(&arm.limits, &q0, &q1, want);
        assert!((plan::move_duration(&arm.limits, &q0, &q1, f) - want).abs() < 1e-6);
    }
}

#[test]
fn dynamic_scan_lies_on_the_part_within_the_noise() {
    let mesh = height_field(45.0, 30.0, 0.5, dome);
    let opts =
        ScanOptions { table_angles_deg: vec![0.0, 180.0], line_spacing_mm: 0.5, ..ScanOptions::default() };
    let out = scan_all(&mesh, opts);
    let (rms, max, n) = distances(&out, dome, 40.0);
    println!(
        "dynamic: {n} points, RMS {rms:.4} mm, max {max:.4} mm, registration RMS {:.2e} mm, {} frames",
        out.report.registration_rms_mm, out.report.frames
    );
    assert!(n > 50_000, "{n} points");
    // Noise is 35 µm along the ray; the default latch (50 µs, compensated) adds < 1 µm.
    assert!(rms > 0.025 && rms < 0.045, "RMS {rms}");
    assert!(max < 0.25, "max {max}");
    assert!(out.report.registration_rms_mm < 0.002);
    assert_eq!(out.pass.len(), out.cloud.points.len());
    assert_eq!(out.cloud.intensity.as_ref().map(Vec::len), Some(out.cloud.points.len()));
    let ids: std::collections::BTreeSet<u16> = out.pass.iter().copied().collect();
    let planned: usize = out.report.stations.iter().map(|s| s.passes.len()).sum();
    assert_eq!(ids.len(), planned, "every pass contributed points");
    // The speed is rate × spacing on the pass.
    for p in out.report.stations.iter().flat_map(|s| &s.passes) {
        assert!(p.speed_mm_s <= 100.0 * 0.5 + 1e-6 && p.speed_mm_s > 30.0, "speed {}", p.speed_mm_s);
    }
}

#[test]
fn stop_and_move_scan_lies_on_the_part_and_runs_at_a_few_frames_per_second() {
    let mesh = height_field(30.0, 20.0, 0.5, dome);
    let opts = ScanOptions {
        mode: ScanMode::StopAndMove,
        table_angles_deg: vec![90.0],
        line_spacing_mm: 1.0,
        ..ScanOptions::default()
    };
    let out = scan_all(&mesh, opts);
    let (rms, max, n) = distances(&out, dome, 25.0);
    println!("stop-and-move: {n} points, RMS {rms:.4} mm, max {max:.4} mm");
    assert!(n > 5_000);
    assert!(rms > 0.025 && rms < 0.045, "RMS {rms}");
    assert!(max < 0.25);
    assert_eq!(out.report.registration_rms_mm, 0.0, "poses read at rest are exact");
    // n frames of a pass span n − 1 intervals.
    let passes = out.report.stations.iter().map(|s| s.passes.len()).sum::<usize>() as f64;
    let intervals = out.report.frames as f64 - passes;
    let busy: f64 = out.report.stations.iter().flat_map(|s| &s.passes).map(|p| p.duration_s).sum();
    let rate = intervals / busy;
    assert!(rate <= 2.5 * 1.001 && rate > 1.0, "{rate} frames/s");
}

#[test]
fn latch_latency_shows_up_as_registration_error_and_is_compensated() {
    let mesh = height_field(20.0, 15.0, 0.5, dome);
    let base = ScanOptions {
        table_angles_deg: vec![0.0],
        line_spacing_mm: 0.25,
        latch_latency_s: 0.004,
        latch_jitter_s: 0.0,
        ..ScanOptions::default()
    };
    let raw = scan_all(&mesh, ScanOptions { compensate_latency: false, ..base.clone() });
    let fixed = scan_all(&mesh, ScanOptions { compensate_latency: true, ..base });
    // At 25 mm/s a 4 ms latency places points 0.1 mm along the pass (less in the ramps).
    let expected = 100.0 * 0.25 * 0.004;
    println!(
        "latency 4 ms: registration RMS {:.4} mm (expected ≤ {expected}), compensated {:.2e} mm",
        raw.report.registration_rms_mm, fixed.report.registration_rms_mm
    );
    assert!(raw.report.registration_max_mm <= expected * 1.05 + 1e-6, "{}", raw.report.registration_max_mm);
    assert!(
        raw.report.registration_rms_mm > 0.7 * expected && raw.report.registration_rms_mm <= expected * 1.05
    );
    assert!(fixed.report.registration_rms_mm < 0.05 * expected, "{}", fixed.report.registration_rms_mm);
}

#[test]
fn interpolation_matches_the_pose_at_the_time() {
    // Poses on a screw motion: interpolation reproduces them exactly in between and beyond.
    let at = |t: f64| {
        Isometry3::from_parts(
            Translation3::new(10.0 * t, -3.0 * t, 2.0),
            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 0.3 * t),
        )
    };
    for t in [-0.5, 0.0, 0.25, 0.5, 1.0, 1.7] {
        let p = interpolate_pose(&(0.0, at(0.0)), &(1.0, at(1.0)), t);
        let (dp, da) = pose_distance(&p, &at(t));
        assert!(dp < 1e-9 && da < 1e-9, "t {t}: {dp} {da}");
    }
}

#[test]
fn scans_are_reproducible() {
    let mesh = height_field(15.0, 10.0, 0.5, dome);
    let opts = ScanOptions { table_angles_deg: vec![0.0], line_spacing_mm: 1.0, ..ScanOptions::default() };
    let a = scan_all(&mesh, opts.clone());
    let b = scan_all(&mesh, opts);
    assert_eq!(a.cloud.points, b.cloud.points);
    assert_eq!(a.cloud.intensity, b.cloud.intensity);
}

/// A base with a tall block in the middle: the camera's line of sight is blocked on one side of
/// the block (the triangulation shadow), which one table angle cannot fill.
fn block(x: f64, y: f64) -> f64 {
    if x.abs() < 6.0 && y.abs() < 6.0 { 25.0 } else { 5.0 }
}

#[test]
fn adaptive_rescan_aims_at_the_holes_and_fills_some() {
    let mesh = height_field(25.0, 25.0, 0.25, block);
    let opts = ScanOptions { table_angles_deg: vec![0.0], line_spacing_mm: 0.5, ..ScanOptions::default() };
    let mut s = ScanSession::new(&mesh, opts, CellLayout::default()).unwrap();
    let plan = s.plan().unwrap();
    for st in &plan.stations {
        s.run_station(st, st.table_deg, false, &mut |_, _| {}, &|| false).unwrap();
    }
    let (before, targets) = s.holes().unwrap();
    assert!(before.holes > 0 && !targets.is_empty(), "the shadow leaves a hole: {before:?}");
    let rescan = s.rescan_plan(&targets, 0.0);
    println!("rescan: {} passes for {} holes", rescan.passes(), targets.len());
    assert!(rescan.passes() > 0);
    // The candidates: the first scan's angle and that + 45°.
    assert!(rescan.stations.iter().all(|st| st.table_deg.abs() < 1e-9 || (st.table_deg - 45.0).abs() < 1e-9));
    for st in &rescan.stations {
        s.run_station(st, st.table_deg, true, &mut |_, _| {}, &|| false).unwrap();
    }
    let (after, _) = s.holes().unwrap();
    println!(
        "coverage {:.2} % ({} holes, {:.1} mm²) -> {:.2} % ({} holes, {:.1} mm²)",
        before.covered_pct,
        before.holes,
        before.hole_area_mm2,
        after.covered_pct,
        after.holes,
        after.hole_area_mm2
    );
    assert!(after.hole_area_mm2 < 0.5 * before.hole_area_mm2, "{before:?} -> {after:?}");
    s.record_rescan(before, Some(after), targets);
    let out = s.finish();
    assert!(out.pass.iter().any(|&p| p > plan.passes() as u16), "rescan points carry their own pass ids");
}

#[test]
fn bad_options_name_the_field_and_unreachable_passes_are_refused() {
    let mesh = height_field(10.0, 10.0, 1.0, dome);
    let spec = ScannerSpec::slp400();
    let e = ScanOptions { standoff_mm: 300.0, ..ScanOptions::default() }.validate(&spec).unwrap_err();
    assert!(e.to_string().contains("scan.standoff_mm = 300"), "{e}");
    let e = ScanOptions { line_rate_hz: 10.0, ..ScanOptions::default() }.validate(&spec).unwrap_err();
    assert!(e.to_string().contains("scan.line_rate_hz"), "{e}");
    let e = ScanOptions::from_json(r#"{"mode": "sideways"}"#).unwrap_err();
    assert!(e.to_string().contains("scan.mode"), "{e}");
    let e = ScanOptions::from_json(r#"{"standof_mm": 150}"#).unwrap_err();
    assert!(e.to_string().contains("standof_mm"), "{e}");
    let o = ScanOptions::from_json(r#"{"mode": "stop_and_move", "table_angles_deg": [0, 90]}"#).unwrap();
    assert_eq!(o.mode, ScanMode::StopAndMove);
    assert_eq!(o.standoff_mm, 150.0);
    // A pass 1.5 m away from the robot.
    let far = ScanOptions {
        passes: Some(vec![PassSpec {
            table_deg: 0.0,
            start_mm: [1500.0, 0.0, 150.0],
            end_mm: [1500.0, 50.0, 150.0],
        }]),
        ..ScanOptions::default()
    };
    let mut s = ScanSession::new(&mesh, far, CellLayout::default()).unwrap();
    let e = s.plan().unwrap_err();
    assert!(matches!(e, ScanError::Unreachable { pass: 1, .. }), "{e}");
    assert!(e.to_string().contains("start of the pass"), "{e}");
    // Too many frames for the guard.
    let mut s = ScanSession::new(
        &mesh,
        ScanOptions { max_frames: 10, ..ScanOptions::default() },
        CellLayout::default(),
    )
    .unwrap();
    assert!(matches!(s.plan().unwrap_err(), ScanError::TooManyFrames { .. }));
    // A part in metres.
    let tiny = height_field(0.04, 0.03, 0.01, |_, _| 0.0);
    let e = ScanSession::new(&tiny, ScanOptions::default(), CellLayout::default()).err().unwrap();
    assert!(e.to_string().contains("millimetres"), "{e}");
    // A part wider than the table.
    let wide = height_field(300.0, 10.0, 10.0, |_, _| 0.0);
    assert!(matches!(
        ScanSession::new(&wide, ScanOptions::default(), CellLayout::default()).err(),
        Some(ScanError::PartTooLarge { .. })
    ));
}

#[test]
fn a_large_part_is_planned_from_the_near_side_at_each_angle() {
    // 280 × 280 mm: the far passes at each angle are out of the arm's reach; the other angles
    // bring that side near, and the plan says what it left out.
    let mesh = height_field(140.0, 140.0, 5.0, |x, y| 5.0 + 0.02 * (x + y));
    let fixed = ScanOptions { table_search_deg: 0.0, ..ScanOptions::default() };
    let mut s = ScanSession::new(&mesh, fixed, CellLayout::default()).unwrap();
    let plan = s.plan().unwrap();
    println!("table fixed: {} passes planned, {} left out", plan.passes(), plan.skipped.len());
    assert_eq!(plan.stations.len(), 4);
    assert!(plan.passes() >= 8);
    assert!(!plan.skipped.is_empty(), "the far passes of a 280 mm part are out of reach");
    for p in &plan.skipped {
        assert!(p.contains("cannot reach"), "{p}");
    }
    // The table as the seventh joint turns each far pass nearer the arm: more of them reached.
    let mut s = ScanSession::new(&mesh, ScanOptions::default(), CellLayout::default()).unwrap();
    let seven = s.plan().unwrap();
    println!("seventh joint: {} passes planned, {} left out", seven.passes(), seven.skipped.len());
    assert!(seven.passes() > plan.passes() && seven.skipped.len() < plan.skipped.len());
    assert!(seven.stations.iter().any(|st| st.table_offset_deg != 0.0));
    // Given passes out of reach stay errors (bad_options_name_the_field... checks that).
}

#[test]
fn passes_keep_clear_of_the_cell_and_a_blocking_obstacle_is_named() {
    let mesh = height_field(20.0, 20.0, 1.0, dome);
    let mut s = ScanSession::new(&mesh, ScanOptions::default(), CellLayout::default()).unwrap();
    let plan = s.plan().unwrap();
    for p in plan.stations.iter().flat_map(|st| &st.passes) {
        assert!(
            p.min_clearance_mm >= 10.0 && p.min_clearance_mm.is_finite(),
            "pass {}: {}",
            p.id,
            p.min_clearance_mm
        );
    }
    // A fixture box where the scanner passes over the part.
    let blocked = ScanOptions {
        obstacles: vec![obstacles::Obstacle::Box {
            name: "clamp".into(),
            min_mm: [480.0, -200.0, 0.0],
            max_mm: [520.0, 200.0, 40.0],
        }],
        ..ScanOptions::default()
    };
    let mut s = ScanSession::new(&mesh, blocked, CellLayout::default()).unwrap();
    let e = s.plan().unwrap_err();
    assert!(matches!(e, ScanError::Unreachable { .. }) && e.to_string().contains("clamp"), "{e}");
    let bad = ScanOptions {
        obstacles: vec![obstacles::Obstacle::Sphere {
            name: "s".into(),
            center_mm: [0.0; 3],
            radius_mm: -1.0,
        }],
        ..ScanOptions::default()
    };
    let e = bad.validate(&ScannerSpec::slp400()).unwrap_err();
    assert!(e.to_string().contains("scan.obstacles[0]"), "{e}");
}

#[test]
fn given_passes_are_scanned_where_asked() {
    let mesh = height_field(20.0, 20.0, 0.5, dome);
    let opts = ScanOptions {
        passes: Some(vec![PassSpec {
            table_deg: 30.0,
            start_mm: [0.0, -25.0, 165.0],
            end_mm: [0.0, 25.0, 165.0],
        }]),
        line_spacing_mm: 0.5,
        ..ScanOptions::default()
    };
    let out = scan_all(&mesh, opts);
    assert_eq!(out.report.stations.len(), 1);
    assert_eq!(out.report.stations[0].table_deg_commanded, 30.0);
    let (rms, _, n) = distances(&out, dome, 18.0);
    assert!(n > 1000 && rms < 0.045, "{n} {rms}");
    // The line crosses the centre: points span x about ±half a line length around 0.
    let xs: Vec<f64> = out.cloud.points.iter().map(|p| f64::from(p.x)).collect();
    let lo = xs.iter().copied().fold(f64::INFINITY, f64::min);
    let hi = xs.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    assert!(lo > -40.0 && hi < 40.0 && lo < -15.0 && hi > 15.0, "{lo}..{hi}");
}

/// The sample relief scaled by `k` (its far passes nearer the edge of the arm's reach).
fn relief_scaled(k: f64) -> Mesh {
    let m = depthmill_geometry::sample::sample_relief(1.0);
    Mesh { vertices: m.vertices.iter().map(|v| Point3::from(v.coords * k)).collect(), triangles: m.triangles }
}

fn plan_of(mesh: &Mesh, search: f64) -> (ScanSession, ScanPlan) {
    let opts = ScanOptions { table_search_deg: search, ..ScanOptions::default() };
    let mut s = ScanSession::new(mesh, opts, CellLayout::default()).unwrap();
    let plan = s.plan().unwrap();
    (s, plan)
}

#[test]
fn the_seventh_joint_keeps_the_path_on_the_part_and_turns_the_table_only_for_a_better_posture() {
    let mesh = relief_scaled(2.6);
    let (s, fixed) = plan_of(&mesh, 0.0);
    let (_, seven) = plan_of(&mesh, 30.0);
    let layout = CellLayout::default();
    let in_part = |deg: f64, p: &Isometry3<f64>| s.placement().world_from_part(&layout, deg).inverse() * p;
    let f: Vec<(f64, &Pass)> =
        fixed.stations.iter().flat_map(|st| st.passes.iter().map(move |p| (st.table_deg, p))).collect();
    let v: Vec<(f64, &Pass)> =
        seven.stations.iter().flat_map(|st| st.passes.iter().map(move |p| (st.table_deg, p))).collect();
    assert_eq!(f.len(), v.len(), "the same passes are reached");
    assert!(fixed.stations.iter().all(|s| s.table_offset_deg == 0.0));
    let mut turned = 0;
    for ((fd, fp), (vd, vp)) in f.iter().zip(&v) {
        // The same sensor path over the part (start, end and orientation in the part's frame).
        for (a, b) in [(&fp.start, &vp.start), (&fp.end, &vp.end)] {
            let (d_mm, d_rad) = pose_distance(&in_part(*fd, a), &in_part(*vd, b));
            assert!(d_mm < 1e-6 && d_rad < 1e-9, "pass {}: {d_mm} mm {d_rad} rad apart on the part", fp.id);
        }
        if (vd - fd).abs() > 1e-9 {
            turned += 1;
            assert!(
                vp.quality >= fp.quality + 0.01,
                "pass {} turned for nothing: {} vs {}",
                fp.id,
                vp.quality,
                fp.quality
            );
        } else {
            assert_eq!(vp.quality, fp.quality);
        }
    }
    assert!(turned > 0, "the large relief's far passes are better with the table turned");
    let worst =
        |p: &ScanPlan| p.stations.iter().flat_map(|s| &s.passes).map(|p| p.quality).fold(1.0, f64::min);
    assert!(worst(&seven) > worst(&fixed), "{} vs {}", worst(&seven), worst(&fixed));
    // The demo-sized part: every pass comfortable at the angles asked, the table not turned.
    let (_, small) = plan_of(&depthmill_geometry::sample::sample_relief(1.0), 30.0);
    assert!(small.stations.iter().all(|s| s.table_offset_deg == 0.0));
}

#[test]
fn table_moves_match_a_stepped_trapezoid() {
    for (from, to) in [(0.0, 90.0), (350.0, 10.0), (0.0, 5.0), (90.0, 90.0), (10.0, -170.0)] {
        let m = plan::TableMove::between(from, to, 45.0, 200.0);
        // Reference: accelerate at full rate while the rest can still be braked, else cruise or
        // brake, in 10 µs steps.
        let (mut x, mut v, mut t, dt) = (0.0_f64, 0.0_f64, 0.0_f64, 1e-5);
        let d: f64 = m.turn_deg.abs();
        let mut peak: f64 = 0.0;
        while x < d - 1e-9 && t < 100.0 {
            let brake = v * v / (2.0 * 200.0);
            let a = if d - x <= brake + 1e-12 {
                -200.0
            } else if v < 45.0 {
                200.0
            } else {
                0.0
            };
            v = (v + a * dt).clamp(0.0, 45.0);
            x += v * dt;
            t += dt;
            peak = peak.max(v);
            if v <= 0.0 && a < 0.0 {
                break;
            }
        }
        assert!((m.time_s - t).abs() < 0.01, "{from}->{to}: {} vs {t}", m.time_s);
        assert!((m.peak_speed_deg_s - peak).abs() < 0.05, "{from}->{to}: {} vs {peak}", m.peak_speed_deg_s);
    }
    assert!((plan::TableMove::between(350.0, 10.0, 45.0, 200.0).turn_deg - 20.0).abs() < 1e-12);
}

#[test]
fn stations_are_visited_from_where_the_table_stands() {
    let quarter = [0.0, 90.0, 180.0, 270.0];
    // Total turning over a visit order, from `at`.
    let turning = |order: &[f64], at: f64| {
        let mut from = at;
        let mut sum = 0.0;
        for &a in order {
            sum += plan::TableMove::between(from, a, 45.0, 200.0).turn_deg.abs();
            from = a;
        }
        sum
    };
    // After a calibration that ended at 270°: 270, 0, 90, 180 (three quarter turns, not four).
    assert_eq!(plan::visit_order(&quarter, 270.0), vec![270.0, 0.0, 90.0, 180.0]);
    assert_eq!(turning(&plan::visit_order(&quarter, 270.0), 270.0), 270.0);
    assert_eq!(turning(&quarter, 270.0), 360.0);
    // Encoder readings off a little, beyond a turn or negative; a tie keeps the list's first.
    assert_eq!(plan::visit_order(&quarter, 89.97), vec![90.0, 180.0, 270.0, 0.0]);
    assert_eq!(plan::visit_order(&quarter, -90.0), vec![270.0, 0.0, 90.0, 180.0]);
    assert_eq!(plan::visit_order(&quarter, 405.0), vec![0.0, 90.0, 180.0, 270.0]);
    assert_eq!(plan::visit_order(&[30.0, 200.0], 115.0), vec![30.0, 200.0]);
    assert_eq!(plan::visit_order(&[], 10.0), Vec::<f64>::new());
    assert_eq!(plan::visit_order(&quarter, f64::NAN), quarter.to_vec());
    // Every order is a rotation of the list whose first turn is the shortest.
    let mut rng = StdRng::seed_from_u64(7);
    for _ in 0..200 {
        let n = rng.random_range(1..7);
        let angles: Vec<f64> = (0..n).map(|_| rng.random_range(-360.0..360.0)).collect();
        let at = rng.random_range(-360.0..720.0);
        let order = plan::visit_order(&angles, at);
        let start = (0..n).find(|&s| {
            let mut r = angles.clone();
            r.rotate_left(s);
            r == order
        });
        assert!(start.is_some(), "{order:?} is not a rotation of {angles:?}");
        let first = |o: &[f64]| plan::TableMove::between(at, o[0], 45.0, 200.0).turn_deg.abs();
        assert!(angles.iter().all(|&a| first(&order) <= first(&[a]) + 1e-9));
    }
}

/// The view prediction against the scanner's own simulation (the reference): a pass of the
/// noise-free scanner over a block on a base, straight down and tilted both ways; each cell of a
/// 0.5 mm grid is filled or not by the simulated frames, and predicted or not by
/// [`views::ViewModel::sees`] on its samples. They agree but for cells the pass only grazes (edges
/// of the block, of its shadow and of the fan).
#[test]
fn the_view_prediction_agrees_with_the_scanners_simulation() {
    let mesh = height_field(25.0, 25.0, 0.25, block);
    let spec = ScannerSpec { noise_sigma_mm: 0.0, ..ScannerSpec::default() };
    let scanner = crate::domain::scanner::Scanner::new(spec.clone(), &mesh, 1).unwrap();
    let model = views::ViewModel::new(&mesh, &spec).unwrap();
    let pixel = 0.5;
    let n = 76usize;
    let centres: Vec<[f64; 2]> = (0..n * n)
        .map(|i| [-19.0 + ((i % n) as f64 + 0.5) * pixel, -19.0 + ((i / n) as f64 + 0.5) * pixel])
        .collect();
    let cells = model.surface(&centres, pixel);
    assert_eq!(cells.len(), n * n, "every cell is over the sheet");
    let mut rng = StdRng::seed_from_u64(7);
    let (mut agree, mut total, mut seen_any, mut hidden_any) = (0usize, 0usize, 0usize, 0usize);
    for tilt in [0.0, 30.0, -30.0, 20.0] {
        let dir = Vector3::new(rng.random_range(-0.3..0.3), 1.0, 0.0);
        let rot = plan::sensor_orientation(&dir, tilt);
        let axis = rot * Vector3::z();
        let x0 = rng.random_range(-8.0..8.0);
        let (pa, pb) = (Point3::new(x0, -22.0, 5.0), Point3::new(x0, 22.0, 5.0));
        let standoff = rng.random_range(120.0..200.0);
        let s0 = Isometry3::from_parts(Translation3::from((pa - axis * standoff).coords), rot);
        let s1 = Isometry3::from_parts(Translation3::from((pb - axis * standoff).coords), rot);
        // Simulated: frames every 0.05 mm along the pass, binned on the grid.
        let mut filled = vec![false; n * n];
        let steps = ((pb - pa).norm() / 0.05) as usize;
        for k in 0..=steps {
            let u = k as f64 / steps as f64;
            let pose = Isometry3::from_parts(
                Translation3::from(s0.translation.vector * (1.0 - u) + s1.translation.vector * u),
                rot,
            );
            for q in scanner.profile_seeded(&pose, k as u64, 1).points {
                let p = pose * q;
                let (c, r) = (((p.x + 19.0) / pixel).floor(), ((p.y + 19.0) / pixel).floor());
                if (0.0..n as f64).contains(&c) && (0.0..n as f64).contains(&r) {
                    filled[r as usize * n + c as usize] = true;
                }
            }
        }
        for (i, cell) in cells.iter().enumerate() {
            let predicted = model.sees(&s0, &s1, cell);
            total += 1;
            agree += usize::from(predicted == filled[i]);
            seen_any += usize::from(predicted && filled[i]);
            hidden_any += usize::from(!predicted && !filled[i]);
        }
    }
    let rate = agree as f64 / total as f64;
    println!("view prediction: {agree} of {total} cells agree ({:.2} %)", 100.0 * rate);
    assert!(seen_any > 1000 && hidden_any > 1000, "both seen and hidden cells: {seen_any}, {hidden_any}");
    assert!(rate > 0.97, "{rate}");
}

#[test]
fn the_tour_takes_the_quickest_order_from_where_the_table_stands() {
    let table = |a: f64, b: f64| TableMove::between(a, b, 45.0, 200.0).time_s;
    let (t, order) = tour(270.0, &[45.0, 315.0], &table);
    assert_eq!(order, vec![1, 0]);
    assert!((t - table(270.0, 315.0) - table(315.0, 45.0)).abs() < 1e-9);
    assert_eq!(tour(10.0, &[], &table), (0.0, Vec::new()));
    // Against every order tried by hand, on random sets.
    let mut rng = StdRng::seed_from_u64(3);
    for _ in 0..50 {
        let k = rng.random_range(1..=5);
        let degs: Vec<f64> = (0..k).map(|_| rng.random_range(0.0..360.0)).collect();
        let from = rng.random_range(0.0..360.0);
        let (t, order) = tour(from, &degs, &table);
        let mut sorted = order.clone();
        sorted.sort_unstable();
        assert_eq!(sorted, (0..k).collect::<Vec<_>>());
        // No single swap of two stops is quicker.
        for i in 0..k {
            for j in i + 1..k {
                let mut o = order.clone();
                o.swap(i, j);
                let mut at = from;
                let alt: f64 = o
                    .iter()
                    .map(|&x| {
                        let dt = table(at, degs[x]);
                        at = degs[x];
                        dt
                    })
                    .sum();
                assert!(alt >= t - 1e-9, "{degs:?} from {from}: {order:?} {t} vs {o:?} {alt}");
            }
        }
    }
}

#[test]
fn a_table_point_is_free_space_when_shown_clear_over_the_part_around_it() {
    // The reference: every cloud point within `reach` (a disc) of the sample, by brute force.
    let mut rng = StdRng::seed_from_u64(5);
    let reach = 2.0;
    for round in 0..20 {
        let cloud: Vec<Point3<f64>> = (0..400)
            .map(|_| {
                Point3::new(
                    rng.random_range(-10.0..10.0),
                    rng.random_range(-10.0..10.0),
                    rng.random_range(0.0..20.0),
                )
            })
            .collect();
        // Every other round the table was seen on one side only, up to the cloud's edge: cloud
        // points beyond the samples' extent still count.
        let x_max = if round % 2 == 0 { 20.0 } else { -9.0 };
        let samples: Vec<FreeSample> = (0..500)
            .map(|_| {
                let at = Point3::new(rng.random_range(-20.0..x_max), rng.random_range(-20.0..20.0), 0.0);
                FreeSample { at, clear_to_z: rng.random_range(0.0..25.0) }
            })
            .collect();
        let kept = free_space(&samples, &cloud, reach);
        let within = |s: &FreeSample, r: f64| {
            cloud
                .iter()
                .filter(|p| (p.x - s.at.x).hypot(p.y - s.at.y) <= r)
                .map(|p| p.z)
                .fold(f64::NEG_INFINITY, f64::max)
        };
        for s in &samples {
            let is_kept = kept.contains(&s.at);
            // Kept: clear over everything within `reach`. Clear over everything within the
            // grid's rounded-out square window (0.5 mm cells, `reach` and two cells more across
            // each side): kept.
            if is_kept {
                assert!(s.clear_to_z >= within(s, reach) + FREE_SPACE_CLEARANCE_MM, "{s:?}");
            }
            let window = std::f64::consts::SQRT_2 * (reach + 1.0);
            if s.clear_to_z >= within(s, window) + FREE_SPACE_CLEARANCE_MM {
                assert!(is_kept, "{s:?}");
            }
        }
        // Far from the cloud, a table point needs nothing shown clear.
        assert!(kept.iter().any(|p| p.x.abs() > 14.0 || p.y.abs() > 14.0));
        // Next to it, something is kept and something is not.
        let near: Vec<&FreeSample> =
            samples.iter().filter(|s| s.at.x > -11.0 && s.at.y.abs() < 9.0).collect();
        assert!(near.iter().any(|s| kept.contains(&s.at)) && near.iter().any(|s| !kept.contains(&s.at)));
    }
}

#[test]
fn a_point_is_shadowed_when_a_steep_rise_beside_it_was_not_shown_clear_over_it() {
    // Terraces and towers of points (steps of 0-20 mm, slopes and cliffs) with random clear
    // heights, against the brute-force reading of the rule: every other point of the cloud
    // tried as the rise.
    let mut rng = StdRng::seed_from_u64(41);
    let (mut flagged, mut certified_near_rise) = (0usize, 0usize);
    for round in 0..12 {
        let mut cloud = Vec::new();
        let towers: Vec<(f64, f64, f64, f64)> = (0..6)
            .map(|_| {
                (
                    rng.random_range(-8.0..8.0),
                    rng.random_range(-8.0..8.0),
                    rng.random_range(0.3..3.0),
                    rng.random_range(0.0..20.0),
                )
            })
            .collect();
        let slope = rng.random_range(0.0..2.0);
        for _ in 0..1500 {
            let (x, y) = (rng.random_range(-10.0..10.0), rng.random_range(-10.0..10.0));
            let mut z = slope * x + rng.random_range(-0.05..0.05);
            for (tx, ty, r, h) in &towers {
                if (x - tx).hypot(y - ty) < *r {
                    z = z.max(slope * tx + h);
                }
            }
            cloud.push(Point3::new(x, y, z));
        }
        let top = cloud.iter().map(|p| p.z).fold(f64::NEG_INFINITY, f64::max);
        let clear_to: Vec<f64> = cloud
            .iter()
            .map(|p| match rng.random_range(0..3) {
                0 => p.z,
                1 => top + FREE_SPACE_CLEARANCE_MM,
                _ => p.z + rng.random_range(0.0..25.0),
            })
            .collect();
        let fast = shadowed(&cloud, &clear_to);
        assert_eq!(fast.len(), cloud.len());
        for (i, p) in cloud.iter().enumerate() {
            let threat = cloud
                .iter()
                .filter(|q| {
                    let rise = q.z - p.z;
                    rise > FREE_SPACE_CLEARANCE_MM && rise > (q.x - p.x).hypot(q.y - p.y) * STEP_TAN
                })
                .map(|q| q.z)
                .fold(f64::NEG_INFINITY, f64::max);
            let shown_beside = cloud.iter().zip(&clear_to).any(|(q, c)| {
                *c >= threat + FREE_SPACE_CLEARANCE_MM
                    && (q.z - p.z).abs() <= SHADOW_LEVEL_MM
                    && (q.x - p.x).hypot(q.y - p.y) <= SHADOW_NEIGHBOUR_MM
            });
            let reference = threat.is_finite() && !shown_beside;
            assert_eq!(
                fast[i], reference,
                "round {round}, point {i} {p:?}, threat {threat}, clear {}",
                clear_to[i]
            );
            flagged += usize::from(reference);
            certified_near_rise += usize::from(threat.is_finite() && !reference);
        }
    }
    assert!(
        flagged > 500 && certified_near_rise > 500,
        "{flagged} shadowed, {certified_near_rise} shown clear"
    );
    assert!(shadowed(&[], &[]).is_empty());
}

#[test]
fn the_floor_seen_under_an_overhang_is_shadowed_and_open_surface_is_not() {
    // A mushroom on a base plate: a 4 mm stem and a 12 x 12 mm cap from z = 20 to 22 over a
    // base at z = 5. The fan's slanted rays see the base under the cap's rim; a top view taken
    // from those points would cut the cap away. (Within SHADOW_NEIGHBOUR_MM of the rim, the open
    // floor beside a point speaks for it.)
    let mut mesh = height_field(25.0, 25.0, 1.0, |_, _| 5.0);
    add_box(&mut mesh, [-2.0, -2.0, 5.0], [2.0, 2.0, 20.0]);
    add_box(&mut mesh, [-6.0, -6.0, 20.0], [6.0, 6.0, 22.0]);
    // Straight-down passes off to each side of the cap: its rim sits near the fan's ends, whose
    // rays slant under it.
    let pass = |start: [f64; 3], end: [f64; 3]| PassSpec { table_deg: 0.0, start_mm: start, end_mm: end };
    let opts = ScanOptions {
        passes: Some(vec![
            pass([20.0, -25.0, 165.0], [20.0, 25.0, 165.0]),
            pass([-20.0, -25.0, 165.0], [-20.0, 25.0, 165.0]),
            pass([-25.0, 20.0, 165.0], [25.0, 20.0, 165.0]),
            pass([-25.0, -20.0, 165.0], [25.0, -20.0, 165.0]),
        ]),
        line_spacing_mm: 0.25,
        ..ScanOptions::default()
    };
    let mut sess = ScanSession::new(&mesh, opts, CellLayout::default()).unwrap();
    let plan = sess.plan().unwrap();
    for st in &plan.stations {
        sess.run_station(st, st.table_deg, false, &mut |_, _| {}, &|| false).unwrap();
    }
    let out = sess.finish();
    // The cloud holds single-precision copies of the points: compare through them.
    let key = |p: &Point3<f32>| [p.x.to_bits(), p.y.to_bits(), p.z.to_bits()];
    let shadowed: std::collections::HashSet<[u32; 3]> =
        out.shadowed.iter().map(|p| key(&depthmill_geometry::cloud::single(p))).collect();
    assert_eq!(out.report.shadowed_points as usize, out.shadowed.len());
    let is_shadowed = |p: &Point3<f32>| shadowed.contains(&key(p));
    let (mut under, mut open, mut open_flagged, mut near, mut near_flagged, mut cap) = (0, 0, 0, 0, 0, 0);
    for p in &out.cloud.points {
        let outside = (p.x.abs() - 6.0).max(p.y.abs() - 6.0);
        if p.z < 19.0
            && p.z > 4.0
            && f64::from(outside) < -(SHADOW_NEIGHBOUR_MM + 0.05)
            && (p.x.abs() > 2.3 || p.y.abs() > 2.3)
        {
            under += 1;
            assert!(is_shadowed(p), "the base under the cap is shadowed: {p:?}");
        } else if p.z > 21.5 {
            cap += 1;
            assert!(!is_shadowed(p), "the cap's top is open: {p:?}");
        } else if p.z < 6.0 && outside > 3.5 {
            open += 1;
            open_flagged += usize::from(is_shadowed(p));
        } else if p.z < 6.0 && outside > 0.5 {
            near += 1;
            near_flagged += usize::from(is_shadowed(p));
        }
    }
    println!(
        "under the cap {under}, cap {cap}; near the cap {near_flagged} of {near} shadowed, far {open_flagged} of {open}"
    );
    assert!(under > 20, "the fan reaches under the cap's rim: {under}");
    assert!(cap > 100 && open > 1000);
    assert_eq!(open_flagged, 0);
    // Beside the cap, on open floor, the lines along the cap's edge show the vertical clear.
    assert!(near_flagged * 2 < near, "{near_flagged} of {near}");
}

#[test]
fn the_rescans_tilted_passes_keep_the_vertical_in_their_laser_plane() {
    // Rolled about the pass direction, as the rescan tilts its passes: the fan's rays show how
    // high each point's vertical is clear. Pitched across the pass, a plane holds no vertical.
    for deg in [0.0, 10.0, -15.0, 30.0, -30.0, 45.0] {
        for dir in [Vector3::x(), Vector3::y(), Vector3::new(0.6, -0.8, 0.0)] {
            let rot = plan::sensor_orientation(&dir, deg);
            assert!(vertical_in_plane(&rot), "rolled {deg}° along {dir:?}");
            let pitched = rot * UnitQuaternion::from_axis_angle(&Vector3::x_axis(), 5f64.to_radians());
            assert!(!vertical_in_plane(&pitched), "pitched 5° along {dir:?}");
        }
    }
}
