use depthmill_geometry::raster::{Roi, grid_for_roi, raster_cell};
use nalgebra::Translation3;
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

use super::*;
use depthmill_geometry::HeightMapMeta;

fn never() -> bool {
    false
}

/// Boxes `[lo, hi]` as one mesh (touching boxes keep their shared faces: samples there are
/// inside the solid and never reached).
/// A 20 × 20 × 12 mm block on a 30 × 30 × 2 mm base, with a 12 × 12 × 7 mm pocket in its top.
pub(crate) const POCKETED_BLOCK: [([f64; 3], [f64; 3]); 6] = [
    ([-5.0, -5.0, 0.0], [25.0, 25.0, 2.0]),
    ([0.0, 0.0, 2.0], [20.0, 20.0, 5.0]),
    ([0.0, 0.0, 5.0], [20.0, 4.0, 12.0]),
    ([0.0, 16.0, 5.0], [20.0, 20.0, 12.0]),
    ([0.0, 4.0, 5.0], [4.0, 16.0, 12.0]),
    ([16.0, 4.0, 5.0], [20.0, 16.0, 12.0]),
];

pub(crate) fn boxes(list: &[([f64; 3], [f64; 3])]) -> Mesh {
    let mut m = Mesh { vertices: Vec::new(), triangles: Vec::new() };
    for (lo, hi) in list {
        let mut b = Mesh::cuboid(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]);
        b.transform(&Translation3::new(lo[0], lo[1], lo[2]).into());
        let base = m.vertices.len() as u32;
        m.vertices.extend(b.vertices);
        m.triangles.extend(b.triangles.iter().map(|t| [t[0] + base, t[1] + base, t[2] + base]));
    }
    m
}

fn sample_index(s: &SurfaceSamples, p: Point3<f64>) -> usize {
    s.points
        .iter()
        .enumerate()
        .min_by(|(_, a), (_, b)| (*a - p).norm().total_cmp(&(*b - p).norm()))
        .map(|(i, _)| i)
        .expect("samples")
}

#[test]
fn settings_are_checked_and_named() {
    assert_eq!(FaceChoiceOptions::default().resolve().ok(), Some(FaceChoiceSettings::default()));
    for (opts, field) in [
        (FaceChoiceOptions { step_deg: Some(0.5), ..Default::default() }, "step_deg"),
        (FaceChoiceOptions { max_faces: Some(0), ..Default::default() }, "max_faces"),
        (FaceChoiceOptions { max_faces: Some(9), ..Default::default() }, "max_faces"),
        (FaceChoiceOptions { min_gain_pct: Some(f64::NAN), ..Default::default() }, "min_gain_pct"),
        (FaceChoiceOptions { cell_mm: Some(0.0), ..Default::default() }, "cell_mm"),
        (FaceChoiceOptions { reach_radius_mm: Some(-1.0), ..Default::default() }, "reach_radius_mm"),
        (FaceChoiceOptions { tolerance_mm: Some(f64::INFINITY), ..Default::default() }, "tolerance_mm"),
    ] {
        let e = opts.resolve().expect_err(field).to_string();
        assert!(e.contains(&format!("reconstruct.face_choice.{field}")), "{e}");
    }
}

#[test]
fn candidates_go_round_once() {
    let c = candidates(90.0, 180.0);
    assert_eq!(
        c,
        vec![
            Face::PosZ,
            Face::A { angle_deg: 90.0 },
            Face::A { angle_deg: 180.0 },
            Face::A { angle_deg: -90.0 }
        ]
    );
    assert_eq!(candidates(15.0, 180.0).len(), 24);
    assert_eq!(candidates(180.0, 180.0).len(), 2);
    // A cloud's: none looking up from below.
    assert_eq!(candidates(15.0, 90.0).len(), 13);
}

#[test]
fn a_block_needs_its_top_and_its_bottom() {
    let m = Mesh::cuboid(20.0, 16.0, 12.0);
    let s = FaceChoiceSettings { step_deg: 45.0, ..Default::default() };
    let samples = SurfaceSamples::from_mesh(&m, s.cell_mm).expect("samples");
    let (faces, report) = choose_faces(&samples, &s, &[], &never).expect("choice");
    // From above: the top and the four walls (cut with the tool's side); turned to A=90 the +Y
    // wall, the top and bottom (walls now) and the ends. Two setups reach everything, and no
    // single one does.
    assert_eq!(faces.len(), 2, "{report:#?}");
    assert!(report.covered_pct > 99.9, "{report:#?}");
    assert!(report.unreached_pct < 0.1, "{report:#?}");
    let reach = |f: &str| report.candidates.iter().find(|c| c.face == f).map_or(0.0, |c| c.reach_pct);
    // Top 320 + walls 2·(20+16)·12 = 864 of 1504 mm²; from A=90: 240 + 2·320 + 2·16·12 = 1264.
    for (f, area) in [("+Z", 320.0 + 864.0), ("A=90", 1264.0), ("A=180", 320.0 + 864.0)] {
        let expected = 100.0 * area / 1504.0;
        assert!((reach(f) - expected).abs() < 2.0, "{f}: {} %, expected about {expected} %", reach(f));
    }
    // The first face is the one that reaches the most.
    assert_eq!(report.chosen[0].face, "A=90");
    assert!(report.exact);
}

#[test]
fn an_overhang_is_reached_from_below_and_a_tunnel_along_the_axis_from_nowhere() {
    // A table on one leg: the cap's underside is reached with the part turned over.
    let t = boxes(&[([8.0, 8.0, 0.0], [12.0, 12.0, 10.0]), ([0.0, 0.0, 10.0], [20.0, 20.0, 13.0])]);
    let s = FaceChoiceSettings { step_deg: 45.0, ..Default::default() };
    let samples = SurfaceSamples::from_mesh(&t, s.cell_mm).expect("samples");
    let under = sample_index(&samples, Point3::new(3.0, 3.0, 10.0));
    assert!(!reached(&samples, Face::PosZ, &s).expect("reach")[under], "the underside is hidden from above");
    assert!(reached(&samples, Face::A { angle_deg: 180.0 }, &s).expect("reach")[under]);
    let (faces, _) = choose_faces(&samples, &s, &[], &never).expect("choice");
    assert!(faces.contains(&Face::A { angle_deg: 180.0 }), "{faces:?}");

    // A 4 x 4 mm tunnel along X (the A axis) through a block: no turn about X looks into it.
    let tunnel = boxes(&[
        ([0.0, 0.0, 0.0], [20.0, 20.0, 8.0]),
        ([0.0, 0.0, 12.0], [20.0, 20.0, 20.0]),
        ([0.0, 0.0, 8.0], [20.0, 8.0, 12.0]),
        ([0.0, 12.0, 8.0], [20.0, 20.0, 12.0]),
    ]);
    let samples = SurfaceSamples::from_mesh(&tunnel, s.cell_mm).expect("samples");
    let floor = sample_index(&samples, Point3::new(10.0, 10.0, 8.0));
    for f in candidates(s.step_deg, 180.0) {
        assert!(!reached(&samples, f, &s).expect("reach")[floor], "{f} reaches the tunnel floor");
    }
    let (_, report) = choose_faces(&samples, &s, &[], &never).expect("choice");
    let r = report
        .unreached_regions
        .iter()
        .find(|r| (0..3).all(|k| (r.center_mm[k] - 10.0).abs() <= r.size_mm[k] / 2.0 + 1.0))
        .unwrap_or_else(|| panic!("no unreached region around the tunnel: {report:#?}"));
    assert!(r.size_mm[0] > 15.0, "the region runs along the tunnel: {r:?}");
    assert!(report.diagnostics().iter().any(|d| d.contains("no A-axis orientation")), "{report:#?}");
}

#[test]
fn a_slot_narrower_than_the_tool_is_not_reached() {
    // A 2 mm slot along X, 5 mm deep.
    let slot = boxes(&[
        ([0.0, 0.0, 0.0], [20.0, 20.0, 10.0]),
        ([0.0, 0.0, 10.0], [20.0, 9.0, 15.0]),
        ([0.0, 11.0, 10.0], [20.0, 20.0, 15.0]),
    ]);
    let wide = FaceChoiceSettings { step_deg: 45.0, reach_radius_mm: 0.4, ..Default::default() };
    let samples = SurfaceSamples::from_mesh(&slot, wide.cell_mm).expect("samples");
    let floor = sample_index(&samples, Point3::new(10.0, 10.0, 10.0));
    assert!(reached(&samples, Face::PosZ, &wide).expect("reach")[floor], "a 0.8 mm tool goes in");
    let ball3 = FaceChoiceSettings { reach_radius_mm: 1.5, ..wide };
    for f in candidates(ball3.step_deg, 180.0) {
        assert!(!reached(&samples, f, &ball3).expect("reach")[floor], "{f}: a 3 mm tool does not");
    }
}

#[test]
fn a_scanned_cloud_is_not_seen_from_inside() {
    // What a scanner sees of a block on the table: top and walls, no bottom.
    let m = Mesh::cuboid(20.0, 16.0, 12.0);
    let mesh_samples = SurfaceSamples::from_mesh(&m, 0.25).expect("samples");
    let points: Vec<Point3<f64>> = mesh_samples.points.into_iter().filter(|p| p.z > 0.01).collect();
    let cloud = PointCloud::from_points(points);
    let s = FaceChoiceSettings { step_deg: 45.0, ..Default::default() };
    let samples = SurfaceSamples::from_cloud(&cloud, s.cell_mm).expect("samples");
    assert!(!samples.occluders.is_empty());
    let top = sample_index(&samples, Point3::new(10.0, 8.0, 12.0));
    assert!(
        !reached(&samples, Face::A { angle_deg: 180.0 }, &s).expect("reach")[top],
        "seen through the table"
    );
    let (faces, report) = choose_faces(&samples, &s, &[], &never).expect("choice");
    assert_eq!(faces, vec![Face::PosZ], "{report:#?}");
    assert!(report.covered_pct > 99.5, "{report:#?}");
}

#[test]
fn a_cloud_seen_only_from_above_is_solid_from_the_side() {
    // A pocketed block on a wider base, scanned from above with its steep walls unseen: the
    // cloud holds the base's rim, the block's top and the pocket's floor, nothing vertical.
    let part = boxes(&POCKETED_BLOCK);
    let all = SurfaceSamples::from_mesh(&part, 0.25).expect("samples");
    let inside = |p: &Point3<f64>, lo: f64, hi: f64| (lo..=hi).contains(&p.x) && (lo..=hi).contains(&p.y);
    let seen: Vec<Point3<f64>> = all
        .points
        .into_iter()
        .filter(|p| {
            ((p.z - 2.0).abs() < 1e-6 && !inside(p, 0.0, 20.0))
                || (p.z - 12.0).abs() < 1e-6
                || ((p.z - 5.0).abs() < 1e-6 && inside(p, 4.0, 16.0))
        })
        .collect();
    let cloud = PointCloud::from_points(seen);
    let s = FaceChoiceSettings { step_deg: 45.0, ..Default::default() };
    let samples = SurfaceSamples::from_cloud(&cloud, s.cell_mm).expect("samples");
    let floor = sample_index(&samples, Point3::new(10.0, 10.0, 5.0));
    assert!(reached(&samples, Face::PosZ, &s).expect("reach")[floor], "from above");
    for a in [-90.0, -45.0, 45.0, 90.0] {
        let f = Face::A { angle_deg: a };
        assert!(!reached(&samples, f, &s).expect("reach")[floor], "{f}: through the pocket's walls");
    }
    let (faces, report) = choose_faces(&samples, &s, &[], &never).expect("choice");
    assert_eq!(faces, vec![Face::PosZ], "{report:#?}");
}

#[test]
fn a_cloud_s_lowest_layer_is_not_reached_past_the_table() {
    // A slab scanned from above, and under its overhang a few points of the floor plate it
    // stands on (seen at a tilt): the lowest layer of the cloud, with the table under it.
    let mut points = Vec::new();
    for i in 0..=80 {
        for j in 0..=80 {
            points.push(Point3::new(0.25 * f64::from(i), 0.25 * f64::from(j), 10.0));
        }
    }
    for i in 0..=32 {
        for j in 0..=6 {
            points.push(Point3::new(2.0 + 0.5 * f64::from(i), 2.0 + 0.5 * f64::from(j), 1.0));
        }
    }
    let cloud = PointCloud::from_points(points);
    let s = FaceChoiceSettings { step_deg: 45.0, ..Default::default() };
    let samples = SurfaceSamples::from_cloud(&cloud, s.cell_mm).expect("samples");
    let floor = sample_index(&samples, Point3::new(10.0, 3.0, 1.0));
    for f in candidates(s.step_deg, samples.max_turn_deg) {
        assert!(!reached(&samples, f, &s).expect("reach")[floor], "{f}: reached from under the part");
    }
}

/// The obviously right reach test: every cell's highest sample by a scan of all samples, the
/// closing and the neighbourhood by loops over the disk's cells.
fn reached_reference(samples: &SurfaceSamples, face: Face, s: &FaceChoiceSettings) -> Vec<bool> {
    let rot = face.view_from_part();
    let view: Vec<Point3<f64>> = samples.points.iter().map(|p| rot * p).collect();
    let all: Vec<Point3<f64>> =
        view.iter().copied().chain(samples.occluders.iter().map(|p| rot * p)).collect();
    let roi = Roi::around(&all, s.reach_radius_mm + 2.0 * samples.cell_mm).expect("roi");
    let grid = grid_for_roi(&roi, samples.cell_mm).expect("grid");
    let (w, h) = (grid.width as i64, grid.height as i64);
    let floor = all.iter().map(|p| p.z).fold(f64::INFINITY, f64::min) as f32 - 1.0;
    let mut top = vec![floor; (w * h) as usize];
    let mut seen = vec![false; (w * h) as usize];
    for p in &all {
        if let Some((c, r)) = raster_cell(&grid, p.x, p.y) {
            let i = (r as i64 * w + c as i64) as usize;
            top[i] = if seen[i] { top[i].max(p.z as f32) } else { p.z as f32 };
            seen[i] = true;
        }
    }
    let rad = s.reach_radius_mm / samples.cell_mm;
    let disk = |f: &dyn Fn(f32, f32) -> f32, src: &[f32], init: f32| -> Vec<f32> {
        let mut out = vec![init; src.len()];
        for r in 0..h {
            for c in 0..w {
                let mut acc = init;
                for rr in 0..h {
                    for cc in 0..w {
                        let d2 = ((rr - r) * (rr - r) + (cc - c) * (cc - c)) as f64;
                        if d2 <= rad * rad {
                            acc = f(acc, src[(rr * w + cc) as usize]);
                        }
                    }
                }
                out[(r * w + c) as usize] = acc;
            }
        }
        out
    };
    let dil = disk(&f32::max, &top, f32::NEG_INFINITY);
    let closed = disk(&f32::min, &dil, f32::INFINITY);
    view.iter()
        .map(|p| {
            let Some((c, r)) = raster_cell(&grid, p.x, p.y) else { return true };
            let mut lo = f32::INFINITY;
            for dr in -1..=1 {
                for dc in -1..=1 {
                    let (cc, rr) = (c as i64 + dc, r as i64 + dr);
                    if (0..w).contains(&cc) && (0..h).contains(&rr) {
                        lo = lo.min(closed[(rr * w + cc) as usize]);
                    }
                }
            }
            p.z as f32 >= lo - s.tolerance_mm as f32
        })
        .collect()
}

#[test]
fn reach_equals_the_reference_on_random_surfaces() {
    let mut rng = StdRng::seed_from_u64(7);
    for case in 0..12 {
        let n = rng.random_range(5..120);
        let points: Vec<Point3<f64>> = (0..n)
            .map(|_| {
                Point3::new(
                    rng.random_range(0.0..8.0),
                    rng.random_range(0.0..6.0),
                    rng.random_range(0.0..5.0),
                )
            })
            .collect();
        let occluders = if case % 2 == 0 {
            Vec::new()
        } else {
            (0..10)
                .map(|_| Point3::new(rng.random_range(0.0..8.0), rng.random_range(0.0..6.0), 0.0))
                .collect()
        };
        let samples = SurfaceSamples { points, occluders, cell_mm: 0.5, max_turn_deg: 180.0, body: None };
        // 2.6 cells: no cell centre lies near the disk's edge.
        let s = FaceChoiceSettings { reach_radius_mm: 1.3, tolerance_mm: 0.1, ..Default::default() };
        for face in [Face::PosZ, Face::A { angle_deg: 60.0 }, Face::A { angle_deg: 180.0 }] {
            assert_eq!(
                reached(&samples, face, &s).expect("reach"),
                reached_reference(&samples, face, &s),
                "case {case}, face {face}"
            );
        }
    }
}

#[test]
fn the_best_subsets_are_the_brute_force_ones() {
    let mut rng = StdRng::seed_from_u64(11);
    for _ in 0..20 {
        let n_sets = rng.random_range(1..9);
        let n = rng.random_range(1..200);
        let bools: Vec<Vec<bool>> =
            (0..n_sets).map(|_| (0..n).map(|_| rng.random_bool(0.3)).collect()).collect();
        let sets: Vec<Bits> = bools.iter().map(|b| Bits::from_bools(b)).collect();
        let (best, exact) = best_subsets(&sets, 4, 0, &vec![0.0; n_sets]);
        assert!(exact);
        for (k, (subset, count, best_count)) in best.iter().enumerate() {
            assert_eq!(subset.len(), k + 1);
            // Brute force over bitmasks: the most points any (k+1)-subset covers.
            let mut most = 0;
            for mask in 0u32..(1 << n_sets) {
                if mask.count_ones() as usize != k + 1 {
                    continue;
                }
                let c = (0..n).filter(|&i| (0..n_sets).any(|j| mask >> j & 1 == 1 && bools[j][i])).count();
                most = most.max(c as u64);
            }
            assert_eq!((*count, *best_count), (most, most), "size {}", k + 1);
            let c = (0..n).filter(|&i| subset.iter().any(|&j| bools[j][i])).count() as u64;
            assert_eq!(c, *count);
        }
    }
}

#[test]
fn about_as_much_reach_with_less_turning_wins() {
    // Candidate 0 (+Z) reaches one sample fewer than candidate 1 (A=15): within the tolerance,
    // +Z is taken; beyond it, the better one.
    let a: Vec<bool> = (0..100).map(|i| i < 99).collect();
    let b: Vec<bool> = vec![true; 100];
    let sets = [Bits::from_bools(&a), Bits::from_bools(&b)];
    let (best, _) = best_subsets(&sets, 1, 1, &[0.0, 15.0]);
    assert_eq!(best[0], (vec![0], 99, 100));
    let (best, _) = best_subsets(&sets, 1, 0, &[0.0, 15.0]);
    assert_eq!(best[0], (vec![1], 100, 100));
}

#[test]
fn the_turning_tie_break_never_asks_for_another_face() {
    // +Z reaches 742 of 1000 samples, A=30 750, A=60 13 more beyond +Z's: the most any one face
    // reaches leaves less than 1 % of what the candidates reach together, so one face is
    // enough, and within 1 % of the best the one that does not turn wins: +Z alone (not +Z with
    // two faces that add under 1 % between them).
    let n = 1000;
    let range = |lo: usize, hi: usize| -> Vec<bool> { (0..n).map(|i| (lo..hi).contains(&i)).collect() };
    let faces = [Face::PosZ, Face::A { angle_deg: 30.0 }, Face::A { angle_deg: 60.0 }];
    let sets = [range(0, 742), range(0, 750), range(742, 755)].map(|b| Bits::from_bools(&b));
    let costs: Vec<f64> = faces.iter().map(|&f| turn_of(f)).collect();
    let (best, _) = best_subsets(&sets, 3, 10, &costs);
    assert_eq!(best[0], (vec![0], 742, 750));
    assert_eq!(enough(&best, 755, n as u64, 1.0), Some(&best[0]));
    assert_eq!(pick_faces(&sets, &best, 755, n as u64, 1.0, 10, &costs), vec![0]);
    // When the best single face leaves 1 % or more, a pair is needed (760), but one face within
    // 1 % of the best pair is one set-up fewer: A=30 alone (750), not +Z with A=60.
    let sets = [range(0, 742), range(0, 750), range(742, 760)].map(|b| Bits::from_bools(&b));
    let (best, _) = best_subsets(&sets, 3, 10, &costs);
    assert_eq!(enough(&best, 760, n as u64, 1.0), Some(&best[1]));
    assert_eq!(pick_faces(&sets, &best, 760, n as u64, 1.0, 10, &costs), vec![1]);
    // ... and +Z when it is that close itself.
    let sets = [range(0, 752), range(0, 750), range(742, 770)].map(|b| Bits::from_bools(&b));
    let (best, _) = best_subsets(&sets, 3, 10, &costs);
    assert_eq!(enough(&best, 770, n as u64, 1.0), Some(&best[1]));
    assert_eq!(pick_faces(&sets, &best, 770, n as u64, 1.0, 10, &costs), vec![0, 2]);
    let sets = [range(0, 761), range(0, 750), range(742, 770)].map(|b| Bits::from_bools(&b));
    let (best, _) = best_subsets(&sets, 3, 10, &costs);
    assert_eq!(pick_faces(&sets, &best, 770, n as u64, 1.0, 10, &costs), vec![0]);
}

#[test]
fn an_excluded_orientation_is_never_chosen_and_the_report_says_so() {
    let m = Mesh::cuboid(20.0, 16.0, 12.0);
    let s = FaceChoiceSettings { step_deg: 45.0, ..Default::default() };
    let samples = SurfaceSamples::from_mesh(&m, s.cell_mm).expect("samples");
    let (faces, _) = choose_faces(&samples, &s, &[], &never).expect("choice");
    assert!(faces.contains(&Face::A { angle_deg: 90.0 }), "{faces:?}");
    let out = [ExcludedFace { face: "A=90".into(), measured_pct: 5.0 }];
    let (faces, report) = choose_faces(&samples, &s, &out, &never).expect("choice");
    assert!(!faces.contains(&Face::A { angle_deg: 90.0 }), "{faces:?}");
    assert!(report.candidates.iter().all(|c| c.face != "A=90"), "{report:#?}");
    assert_eq!(report.excluded, out);
    // Still every side of the block from the others (A=-90 sees what A=90 did).
    assert!(report.covered_pct > 99.9, "{report:#?}");
}

#[test]
fn a_turned_view_reaches_only_what_the_scanned_body_does_not_hide() {
    // A plateau (z = 10, y in [0, 20]) and a terrace (z = 2, y in [24, 30]) scanned from above;
    // between them a band no point and no table showed, which the body lids at the plateau's
    // height. The samples alone leave the band open, so one of the views tilted about A sees the
    // terrace across it; past the body, neither does.
    let mut points = Vec::new();
    for i in 0..=40 {
        for j in 0..=40 {
            points.push(Point3::new(0.5 * f64::from(i), 0.5 * f64::from(j), 10.0));
        }
        for j in 0..=12 {
            points.push(Point3::new(0.5 * f64::from(i), 24.0 + 0.5 * f64::from(j), 2.0));
        }
    }
    let cloud = PointCloud::from_points(points);
    let s = FaceChoiceSettings { step_deg: 45.0, ..Default::default() };
    let mut samples = SurfaceSamples::from_cloud(&cloud, s.cell_mm).expect("samples");
    let terrace: Vec<usize> = (0..samples.points.len()).filter(|&i| samples.points[i].y > 23.0).collect();
    assert!(terrace.len() > 100);
    let open: Vec<(Face, usize)> = candidates(s.step_deg, samples.max_turn_deg)
        .into_iter()
        .map(|f| {
            let r = reached(&samples, f, &s).expect("reach");
            (f, terrace.iter().filter(|&&i| r[i]).count())
        })
        .collect();
    // The views from the plateau's side: the tool comes from -Y, over the band.
    let tilted = open
        .iter()
        .filter(|(f, _)| (f.view_from_part().inverse() * Vector3::z()).y < -0.1)
        .max_by_key(|(_, n)| *n)
        .copied()
        .expect("a tilted candidate");
    assert!(tilted.1 * 4 > terrace.len(), "without the body, {} sees the terrace: {open:?}", tilted.0);
    let meta = HeightMapMeta { origin_x_mm: -2.0, origin_y_mm: -2.0, ..HeightMapMeta::new(100, 140, 0.25) };
    let body = HeightMap::from_fn(meta, |c, r| {
        let (_, y) = meta.cell_center(c, r);
        if (-0.25..24.0).contains(&y) {
            10.0
        } else if (24.0..30.25).contains(&y) {
            2.0
        } else {
            f32::NAN
        }
    })
    .expect("body");
    samples.body = Some((body.clone(), 0.125));
    let r = reached(&samples, tilted.0, &s).expect("reach");
    let seen = terrace.iter().filter(|&&i| r[i]).count();
    assert_eq!(seen, 0, "{} sees {seen} terrace samples through the lidded band", tilted.0);
    // From above nothing is hidden, and elsewhere the body takes nothing the view reached.
    assert_eq!(
        reached(&samples, Face::PosZ, &s).expect("reach").iter().filter(|v| **v).count(),
        samples.points.len()
    );
    let plateau = sample_index(&samples, Point3::new(10.0, 10.0, 10.0));
    assert!(r[plateau], "the plateau's top is seen from {}", tilted.0);
}
