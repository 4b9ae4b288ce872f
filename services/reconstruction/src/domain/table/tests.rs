use super::*;

/// A scene in a sensor's frame: a table plane (`n`, through `o`), a 20 x 16 x 12 mm block
/// standing on it (top and four walls), a 2 mm cube 40 mm away, scanner noise, and outliers;
/// `(cloud, pose)` with `pose` the table's frame (the table at z = 0, the block's corner at the
/// origin) in the sensor's.
fn scene(rng: &mut StdRng, tilt_deg: f64) -> (PointCloud, Isometry3<f64>, usize) {
    let axis = Vector3::new(rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0), 0.0)
        .try_normalize(1e-9)
        .unwrap_or_else(Vector3::x);
    let rot = UnitQuaternion::from_axis_angle(&nalgebra::Unit::new_normalize(axis), tilt_deg.to_radians());
    let pose = Isometry3::from_parts(
        Translation3::new(
            rng.random_range(-50.0..50.0),
            rng.random_range(-50.0..50.0),
            rng.random_range(-400.0..-200.0),
        ),
        rot,
    );
    let mut noise = || 0.05 * (rng.random::<f64>() - 0.5);
    let mut local = Vec::new();
    // The table, 120 x 120 mm around the block, not under it.
    let mut table = 0;
    for i in 0..240 {
        for j in 0..240 {
            let (x, y) = (-50.0 + 0.5 * f64::from(i), -50.0 + 0.5 * f64::from(j));
            if !((0.0..=20.0).contains(&x) && (0.0..=16.0).contains(&y)) {
                local.push(Point3::new(x, y, noise()));
                table += 1;
            }
        }
    }
    for i in 0..=40 {
        for j in 0..=32 {
            local.push(Point3::new(0.5 * f64::from(i), 0.5 * f64::from(j), 12.0 + noise()));
        }
        for k in 3..24 {
            let z = 0.5 * f64::from(k);
            local.push(Point3::new(0.5 * f64::from(i), noise(), z));
            local.push(Point3::new(0.5 * f64::from(i), 16.0 + noise(), z));
        }
    }
    // A small cube off to the side.
    for i in 0..5 {
        for j in 0..5 {
            local.push(Point3::new(60.0 + 0.5 * f64::from(i), 0.5 * f64::from(j), 2.0 + noise()));
        }
    }
    let mut pts: Vec<Point3<f64>> = local.iter().map(|p| pose * p).collect();
    // Stray points around.
    for _ in 0..50 {
        let p = Point3::new(
            rng.random_range(-60.0..80.0),
            rng.random_range(-60.0..70.0),
            rng.random_range(-30.0..40.0),
        );
        pts.push(pose * p);
    }
    let cloud = PointCloud::from_points(pts);
    (cloud, pose, table)
}

#[test]
fn a_scene_stands_on_its_table_with_only_the_part_kept() {
    let mut rng = StdRng::seed_from_u64(3);
    for tilt in [0.0, 20.0, 65.0, 150.0] {
        let (cloud, pose, table) = scene(&mut rng, tilt);
        let (out, report) = level_on_table(cloud, &TableSettings::default()).expect("table");
        // The plane: the table's normal (towards the block) within a tenth of a degree.
        let truth = pose.rotation * Vector3::z();
        let found = Vector3::from(report.normal);
        assert!(found.angle(&truth).to_degrees() < 0.1, "tilt {tilt}: {found:?} against {truth:?}");
        assert!((report.tilt_deg - truth.z.abs().acos().to_degrees()).abs() < 0.1, "{report:?}");
        assert!(report.on_table >= table, "tilt {tilt}: {} on the table of {table}", report.on_table);
        // Kept: the block alone (the cube and the strays apart from it), standing on z = 0 with
        // its top at 12 mm.
        assert!(report.groups >= 2 && report.in_other_groups >= 25, "{report:?}");
        let zs: Vec<f64> = out.points.iter().map(|p| f64::from(p.z)).collect();
        let top = zs.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        let low = zs.iter().copied().fold(f64::INFINITY, f64::min);
        assert!((top - 12.0).abs() < 0.1, "tilt {tilt}: top at {top}");
        assert!(low > 0.9 && low < 2.0, "tilt {tilt}: lowest at {low}");
        assert!(out.len() >= 41 * 33 + 2 * 41 * 19, "tilt {tilt}: {} kept", out.len());
        assert_eq!(out.len(), report.kept);
        // The matrix reported is the motion applied.
        let m = nalgebra::Matrix4::from_fn(|r, c| report.transform[r][c]);
        let corner = m.transform_point(&(pose * Point3::new(0.0, 0.0, 12.0)));
        assert!((corner.z - 12.0).abs() < 0.05, "{corner:?}");
    }
}

#[test]
fn the_plane_holds_as_many_points_as_the_true_one() {
    // The reference: the true plane's count of points within the tolerance. RANSAC with its
    // refinement must find a plane holding at least nearly as many, on random scenes.
    let mut rng = StdRng::seed_from_u64(11);
    for _ in 0..6 {
        let tilt = rng.random_range(0.0..90.0);
        let (cloud, pose, _) = scene(&mut rng, tilt);
        let pts: Vec<Point3<f64>> = cloud.points.iter().map(|p| p.at()).collect();
        let n_true = pose.rotation * Vector3::z();
        let d_true = n_true.dot(&pose.translation.vector);
        let within =
            |n: &Vector3<f64>, d: f64| pts.iter().filter(|p| (n.dot(&p.coords) - d).abs() <= 1.0).count();
        let (n, d) = find_plane(&pts, 1.0).expect("plane");
        assert!(within(&n, d) as f64 >= 0.999 * within(&n_true, d_true) as f64, "tilt {tilt}");
    }
}

#[test]
fn groups_match_a_flood_fill_over_touching_cells() {
    // The reference: a flood fill over the points, two points joined when their cells touch.
    let mut rng = StdRng::seed_from_u64(5);
    for _ in 0..10 {
        let gap = rng.random_range(0.5..3.0);
        let pts: Vec<Point3<f64>> = (0..300)
            .map(|_| {
                Point3::new(
                    rng.random_range(0.0..30.0),
                    rng.random_range(0.0..30.0),
                    rng.random_range(0.0..5.0),
                )
            })
            .collect();
        let g = groups(&pts, gap);
        let cell = |p: &Point3<f64>| {
            [(p.x / gap).floor() as i64, (p.y / gap).floor() as i64, (p.z / gap).floor() as i64]
        };
        let touch =
            |a: &Point3<f64>, b: &Point3<f64>| cell(a).iter().zip(cell(b)).all(|(x, y)| (x - y).abs() <= 1);
        let mut reference = vec![usize::MAX; pts.len()];
        let mut next = 0;
        for s in 0..pts.len() {
            if reference[s] != usize::MAX {
                continue;
            }
            let mut stack = vec![s];
            reference[s] = next;
            while let Some(i) = stack.pop() {
                for j in 0..pts.len() {
                    if reference[j] == usize::MAX && touch(&pts[i], &pts[j]) {
                        reference[j] = next;
                        stack.push(j);
                    }
                }
            }
            next += 1;
        }
        assert_eq!(g, reference, "gap {gap}");
    }
}

#[test]
fn no_table_is_named() {
    let line = PointCloud::from_points((0..10).map(|i| Point3::new(f64::from(i), 0.0, 0.0)));
    let e = level_on_table(line, &TableSettings::default()).expect_err("a line");
    assert!(e.to_string().contains("reconstruct.filters.table: no table found"), "{e}");
    let two = PointCloud::from_points(vec![Point3::new(0.0, 0.0, 0.0), Point3::new(1.0, 0.0, 0.0)]);
    let e = level_on_table(two, &TableSettings::default()).expect_err("two points");
    assert!(e.to_string().contains("2 points, a plane needs 3"), "{e}");
    // A flat patch alone: nothing above the table.
    let flat =
        PointCloud::from_points((0..100).map(|i| Point3::new(f64::from(i % 10), f64::from(i / 10), 0.0)));
    let e = level_on_table(flat, &TableSettings::default()).expect_err("flat");
    assert!(e.to_string().contains("nothing stands more than 1 mm above the table"), "{e}");
}
