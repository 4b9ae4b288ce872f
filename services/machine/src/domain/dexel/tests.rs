use super::surface::MAX_SURFACE_SAMPLES;
use super::*;
use crate::domain::removal::Stock;
use depthmill_geometry::ToolProfile;
use rand::{Rng, SeedableRng, rngs::StdRng};

fn block(x: f64, y: f64, z: f64) -> Blank {
    Blank { boxes: vec![OrientedBox::aligned(Point3::origin(), Point3::new(x, y, z))] }
}

fn z_axis() -> Unit<Vector3<f64>> {
    Vector3::z_axis()
}

/// The top of the Z grid's ray through `(x, y)`.
fn top(stock: &DexelStock, x: f64, y: f64) -> Option<f32> {
    let g = stock.grids.iter().find(|g| g.axis == 2)?;
    g.ray_at(&Point3::new(x, y, 0.0)).and_then(|r| r.last().map(|s| s[1]))
}

fn tools() -> Vec<ToolProfile> {
    vec![
        ToolProfile::ball(3.0).expect("ball"),
        ToolProfile::flat(2.0).expect("flat"),
        ToolProfile::bull(4.0, 1.0).expect("bull"),
        ToolProfile::v(3.0, 90.0, 0.0).expect("v"),
    ]
}

#[test]
fn three_axis_programs_leave_the_z_maps_tops() {
    // Random 3-axis programs: the Z grid's top of every ray equals the Z-map's top of the same
    // cell within one f32 quantum of the heights (both take the exact envelope at cell centres).
    let mut rng = StdRng::seed_from_u64(3);
    for case in 0..12 {
        let profile = &tools()[case % 4];
        let cell = 0.25;
        let mut zmap = Stock::block(Point3::origin(), 20.0, 15.0, 10.0, cell).expect("zmap");
        let mut dex = DexelStock::new(
            &block(20.0, 15.0, 10.0),
            &DexelCells { x_mm: None, y_mm: None, z_mm: Some(cell) },
        )
        .expect("dexel");
        let solid = ToolSolid::new(profile, 40.0).expect("solid");
        let mut p = Point3::new(rng.random_range(0.0..20.0), rng.random_range(0.0..15.0), 11.0);
        for _ in 0..15 {
            let q = Point3::new(
                rng.random_range(-2.0..22.0),
                rng.random_range(-2.0..17.0),
                rng.random_range(4.0..11.0),
            );
            let a = zmap.cut_line(profile, p, q).expect("zmap cut");
            let b = dex.cut_line(&solid, &p, &q, &z_axis()).expect("dexel cut");
            assert!(
                (a.volume_mm3 - b.volume_mm3).abs() <= 1e-3 * (1.0 + a.volume_mm3),
                "case {case}: volumes {} vs {}",
                a.volume_mm3,
                b.volume_mm3
            );
            p = q;
        }
        let map = zmap.height_map();
        for r in 0..map.height() {
            for c in 0..map.width() {
                let (x, y) = map.cell_center(c, r);
                let z = map.get(c, r).unwrap_or(f32::NAN);
                let d = top(&dex, x, y).unwrap_or(0.0);
                // Exact tools agree to the f32 quantum; the bull nose's torus is a 64-segment
                // polyline in the dexel solid (inscribed: never lower), whose last chord, near the
                // vertical end of the arc, stands up to c·Δ/4 = c·π/512 above the arc (Δ the
                // segment's angle, c = 1 mm the corner radius).
                let tol = if case % 4 == 2 {
                    std::f64::consts::PI / 512.0 + 2e-5
                } else {
                    2e-5 * f64::from(z.abs().max(1.0))
                };
                let tol = tol as f32;
                assert!(
                    d - z <= tol && z - d <= 2e-5 * z.abs().max(1.0),
                    "case {case} cell ({c}, {r}): zmap {z} dexel {d}"
                );
            }
        }
        let vtol = if case % 4 == 2 { 0.05 } else { 1e-2 };
        assert!(
            (zmap.volume_mm3() - dex.volume_mm3()).abs() < vtol,
            "case {case}: {} vs {}",
            zmap.volume_mm3(),
            dex.volume_mm3()
        );
    }
}

/// A move's sampled tool poses: tip and axis.
type Poses = Vec<(Point3<f64>, Vector3<f64>)>;

/// The tool's poses at `n + 1` even steps of a move.
fn poses(pose: &dyn Fn(f64) -> (Point3<f64>, Unit<Vector3<f64>>), n: usize) -> Poses {
    (0..=n)
        .map(|i| {
            let (p, u) = pose(i as f64 / n as f64);
            (p, u.into_inner())
        })
        .collect()
}

/// Whether `x` lies in `tool` at one of the sampled poses (the dense reference).
fn in_swept(tool: &ToolSolid, x: &Point3<f64>, poses: &[(Point3<f64>, Vector3<f64>)]) -> bool {
    let reach = tool.length_mm() + tool.radius_mm();
    poses.iter().any(|(p, u)| {
        let y = x - p;
        if y.norm_squared() > reach * reach {
            return false;
        }
        let w = y.dot(u);
        tool.contains((y - u * w).norm(), w, 0.0)
    })
}

#[test]
fn pruned_sweeps_leave_what_the_full_sweep_leaves_bit_for_bit() {
    // Random programs of short and long moves at random orientations (tilted, along a grid's
    // rays, level and ramping) with every tool shape, on all three grids, the blank's top close
    // under the tool so that pieces above the stock are left out: the pruned sweep (pieces left
    // out, rows clipped to each piece's chord, a ball's range bound) against every ray of the
    // tool's box with every piece.
    let mut rng = StdRng::seed_from_u64(17);
    let (mut visited_fast, mut visited_slow) = (0, 0);
    for case in 0..24 {
        let profile = &tools()[case % 4];
        let solid = ToolSolid::new(profile, 9.0).expect("solid");
        let blank = block(8.0, 7.0, 5.0);
        let mut fast = DexelStock::new(&blank, &DexelCells::tri(0.11)).expect("dexel");
        let mut slow = fast.clone();
        let axis = match case % 3 {
            0 => z_axis(),
            1 => Unit::new_normalize(Vector3::new(
                rng.random_range(-0.5..0.5),
                rng.random_range(-0.5..0.5),
                1.0,
            )),
            _ => Unit::new_normalize(Vector3::new(
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
            )),
        };
        let mut at =
            Point3::new(rng.random_range(1.0..7.0), rng.random_range(1.0..6.0), rng.random_range(2.5..4.8));
        for step in 0..12 {
            let len = if step % 3 == 0 { 3.0 } else { 0.3 };
            let mut to = at + Vector3::new(rng.random_range(-len..len), rng.random_range(-len..len), 0.0);
            if step % 4 == 1 {
                to.z += rng.random_range(-0.4..0.2);
            }
            let a = fast.sweep_line(&solid, &at, &to, &axis, true, Grids::All).expect("pruned");
            let b = slow.sweep_line(&solid, &at, &to, &axis, false, Grids::All).expect("full");
            assert_eq!(
                a.volume_mm3.to_bits(),
                b.volume_mm3.to_bits(),
                "case {case} step {step}: {a:?} {b:?}"
            );
            assert_eq!(a.cells_updated, b.cells_updated, "case {case} step {step}");
            assert!(a.cells_visited <= b.cells_visited, "case {case} step {step}");
            visited_fast += a.cells_visited;
            visited_slow += b.cells_visited;
            at = to;
        }
        assert!(fast.volume_mm3() < 8.0 * 7.0 * 5.0 - 0.05, "case {case}: nothing cut");
        for (g, h) in fast.grids.iter().zip(&slow.grids) {
            assert!(g.rays == h.rays, "case {case} {profile:?}: grid {} differs", g.axis);
        }
    }
    assert!(5 * visited_fast < 4 * visited_slow, "pruning visited {visited_fast} of {visited_slow} rays");
}

#[test]
fn removed_volume_matches_a_voxel_reference_at_any_orientation() {
    // Small cases: a block cut by a tilted tool on one straight move, on all three grids; the
    // removed volume of the primary grid against a brute-force count of voxel centres in the
    // swept tool (voxels of 0.15 mm), and every grid's removed material against the same
    // membership test at the segment ends.
    let mut rng = StdRng::seed_from_u64(5);
    for case in 0..3 {
        let profile = &tools()[[0, 2, 3][case]];
        let solid = ToolSolid::new(profile, 12.0).expect("solid");
        let (sx, sy, sz) = (10.0, 8.0, 6.0);
        let mut dex = DexelStock::new(&block(sx, sy, sz), &DexelCells::tri(0.2)).expect("dexel");
        let axis =
            Unit::new_normalize(Vector3::new(rng.random_range(-0.7..0.7), rng.random_range(-0.7..0.7), 1.0));
        let p0 =
            Point3::new(rng.random_range(2.0..8.0), rng.random_range(2.0..6.0), rng.random_range(3.0..5.5));
        let p1 =
            Point3::new(rng.random_range(2.0..8.0), rng.random_range(2.0..6.0), rng.random_range(3.0..5.5));
        let before = dex.volume_mm3();
        let cut = dex.cut_line(&solid, &p0, &p1, &axis).expect("cut");
        assert!((before - dex.volume_mm3() - cut.volume_mm3).abs() < 1e-6 * before, "case {case}");
        let pose = poses(&|s: f64| (p0 + (p1 - p0) * s, axis), 300);
        let vox = 0.15;
        let (nx, ny, nz) = ((sx / vox) as usize, (sy / vox) as usize, (sz / vox) as usize);
        // Only voxels near the move's bounding box can be inside.
        let near = |x: &Point3<f64>| {
            (0..3).all(|k| {
                let (a, b) = (p0[k].min(p1[k]) - 3.0, p0[k].max(p1[k]) + 3.0 + 12.0 * axis[k].max(0.0));
                let lo = a + 12.0 * axis[k].min(0.0);
                x[k] >= lo && x[k] <= b
            })
        };
        let inside: usize = (0..nz)
            .into_par_iter()
            .map(|k| {
                let mut n = 0;
                for j in 0..ny {
                    for i in 0..nx {
                        let x = Point3::new(
                            (i as f64 + 0.5) * vox,
                            (j as f64 + 0.5) * vox,
                            (k as f64 + 0.5) * vox,
                        );
                        if near(&x) && in_swept(&solid, &x, &pose) {
                            n += 1;
                        }
                    }
                }
                n
            })
            .sum();
        let reference = inside as f64 * vox.powi(3);
        // The two samplings differ by about half a voxel of depth over the cut surface.
        let tol = 0.05 * reference + 0.3;
        assert!(
            (cut.volume_mm3 - reference).abs() <= tol,
            "case {case} {profile:?}: dexel {} voxels {reference}",
            cut.volume_mm3
        );
    }
}

#[test]
fn every_grid_keeps_what_the_tool_misses_and_loses_what_it_sweeps() {
    let mut rng = StdRng::seed_from_u64(9);
    let profile = ToolProfile::bull(4.0, 1.0).expect("bull");
    let solid = ToolSolid::new(&profile, 12.0).expect("solid");
    let mut dex = DexelStock::new(&block(10.0, 8.0, 6.0), &DexelCells::tri(0.25)).expect("dexel");
    let axis = Unit::new_normalize(Vector3::new(0.4, -0.3, 1.0));
    let (p0, p1) = (Point3::new(3.0, 3.0, 4.0), Point3::new(7.5, 5.0, 3.0));
    dex.cut_line(&solid, &p0, &p1, &axis).expect("cut");
    let pose = poses(&|s: f64| (p0 + (p1 - p0) * s, axis), 300);
    for g in &dex.grids {
        for _ in 0..3000 {
            let (i, j) = (rng.random_range(0..g.n[0]), rng.random_range(0..g.n[1]));
            let mut x = g.ray_origin(i, j);
            x[g.axis] = rng.random_range(0.0..[10.0, 8.0, 6.0][g.axis]);
            let solid_here = g.contains(&x);
            // Points well inside or well outside the swept tool (the membership of a point at
            // the sampled positions is exact only away from the surface).
            let near = |d: f64| {
                let mut y = x;
                y[g.axis] += d;
                in_swept(&solid, &y, &pose)
            };
            let (a, b, c) = (near(-0.02), near(0.0), near(0.02));
            if a && b && c {
                assert!(!solid_here, "grid {} keeps material at {x:?} inside the swept tool", g.axis);
            } else if !a && !b && !c {
                assert!(solid_here, "grid {} lost material at {x:?} outside the swept tool", g.axis);
            }
        }
    }
}

#[test]
fn turning_moves_are_cut_within_the_stated_error() {
    // The part turns 40° about X (an A-axis feed move) under a ball end: the stepped sweep
    // removes everything the densely sampled tool passes through, deeper than the stated error,
    // and nothing farther than it from the tool's path.
    let profile = ToolProfile::ball(4.0).expect("ball");
    let solid = ToolSolid::new(&profile, 10.0).expect("solid");
    let blank = Blank {
        boxes: vec![OrientedBox::aligned(Point3::new(0.0, -6.0, -6.0), Point3::new(10.0, 6.0, 6.0))],
    };
    let mut dex = DexelStock::new(&blank, &DexelCells::tri(0.2)).expect("dexel");
    // Machine frame: tip at (5, 0, 4.5), axis +Z; the part turns from A 0 to A 40: in the part
    // frame the tip and the axis turn by −A about X.
    let pose = |s: f64| {
        let a = (40.0 * s).to_radians();
        let r = Rotation3::from_axis_angle(&Vector3::x_axis(), -a);
        (r * Point3::new(5.0, 0.0, 4.5), Unit::new_normalize(r * Vector3::z()))
    };
    let err = 0.05;
    let cut = dex.cut_moving(&solid, &pose, err).expect("cut");
    let pose = poses(&pose, 300);
    assert!(cut.volume_mm3 > 5.0, "removed {}", cut.volume_mm3);
    let mut rng = StdRng::seed_from_u64(2);
    let mut checked = 0;
    for _ in 0..20_000 {
        let x =
            Point3::new(rng.random_range(0.5..9.5), rng.random_range(-5.5..5.5), rng.random_range(-5.5..5.5));
        let inside = |d: f64| {
            // Every point within d of x is in (d > 0) or out (d < 0) of the swept tool.
            [
                Vector3::zeros(),
                Vector3::x(),
                -Vector3::x(),
                Vector3::y(),
                -Vector3::y(),
                Vector3::z(),
                -Vector3::z(),
            ]
            .iter()
            .all(|e| in_swept(&solid, &(x + e * d.abs()), &pose) == (d > 0.0))
        };
        let material = dex.contains(&x);
        if inside(2.0 * err) {
            assert!(!material, "material left at {x:?}");
            checked += 1;
        } else if inside(-(2.0 * err + 0.2)) {
            assert!(material, "material lost at {x:?}");
        }
    }
    assert!(checked > 10, "{checked}");
}

#[test]
fn engagement_reads_a_slot_and_a_half_immersion_cut() {
    let profile = ToolProfile::flat(6.0).expect("flat");
    let solid = ToolSolid::new(&profile, 30.0).expect("solid");
    let mut dex = DexelStock::new(&block(40.0, 20.0, 10.0), &DexelCells::tri(0.1)).expect("dexel");
    // A slot along X through the middle, then one revolution further.
    dex.cut_line(&solid, &Point3::new(-5.0, 10.0, 8.0), &Point3::new(20.0, 10.0, 8.0), &z_axis())
        .expect("slot");
    let c = dex
        .cut_line(&solid, &Point3::new(20.0, 10.0, 8.0), &Point3::new(20.1, 10.0, 8.0), &z_axis())
        .expect("rev");
    assert!((c.engagement_deg - 180.0).abs() < 5.0, "slot {}", c.engagement_deg);
    assert!((c.axial_depth_mm - 2.0).abs() < 0.05, "axial {}", c.axial_depth_mm);
    // Half immersion: beside a slot through the whole stock, the tool 3 mm over.
    let mut dex = DexelStock::new(&block(40.0, 20.0, 10.0), &DexelCells::tri(0.1)).expect("dexel");
    dex.cut_line(&solid, &Point3::new(-5.0, 10.0, 8.0), &Point3::new(45.0, 10.0, 8.0), &z_axis())
        .expect("slot");
    dex.cut_line(&solid, &Point3::new(-5.0, 13.0, 8.0), &Point3::new(20.0, 13.0, 8.0), &z_axis())
        .expect("side");
    let c = dex
        .cut_line(&solid, &Point3::new(20.0, 13.0, 8.0), &Point3::new(20.1, 13.0, 8.0), &z_axis())
        .expect("rev");
    assert!((c.engagement_deg - 90.0).abs() < 6.0, "half {}", c.engagement_deg);
    // A plunge engages all around.
    let mut dex = DexelStock::new(&block(40.0, 20.0, 10.0), &DexelCells::tri(0.1)).expect("dexel");
    let c = dex
        .cut_line(&solid, &Point3::new(20.0, 10.0, 11.0), &Point3::new(20.0, 10.0, 9.0), &z_axis())
        .expect("plunge");
    assert!(c.engagement_deg > 170.0, "plunge {}", c.engagement_deg);
}

#[test]
fn view_heights_read_each_face_of_one_stock() {
    // A 10 mm cube centred on the A axis; a 2 mm deep slot cut into the top (A 0) and, turning
    // the part, one into the side that faces up at A 90. Seen from A 0 and A 90, each view
    // shows its slot and, at the edge, the other face's.
    let blank = Blank {
        boxes: vec![OrientedBox::aligned(Point3::new(0.0, -5.0, -5.0), Point3::new(10.0, 5.0, 5.0))],
    };
    let mut dex = DexelStock::new(&blank, &DexelCells::tri(0.1)).expect("dexel");
    let solid = ToolSolid::new(&ToolProfile::flat(2.0).expect("flat"), 20.0).expect("solid");
    dex.cut_line(&solid, &Point3::new(-2.0, 0.0, 3.0), &Point3::new(12.0, 0.0, 3.0), &z_axis()).expect("top");
    // At A 90 the view's +Z is the part's +Y: a point (x, y, z) of the view is R_x(−90)·p.
    let part_from_view = |a: f64| Rotation3::from_axis_angle(&Vector3::x_axis(), -a.to_radians());
    let r = part_from_view(90.0);
    let axis = Unit::new_normalize(r * Vector3::z());
    dex.cut_line(&solid, &(r * Point3::new(-2.0, 0.0, 3.0)), &(r * Point3::new(12.0, 0.0, 3.0)), &axis)
        .expect("side");
    let mut meta = HeightMapMeta::new(100, 100, 0.1);
    meta.origin_x_mm = 0.0;
    meta.origin_y_mm = -5.0;
    meta.z_min_mm = -5.0;
    meta.z_max_mm = 5.0;
    for a in [0.0, 90.0] {
        let map = dex.view_heights(&part_from_view(a), &meta, 8.0).expect("view");
        let at = |y: f64| {
            let (c, r) = map.cell_of(5.0, y).expect("on the map");
            map.get(c, r).unwrap_or(f32::NAN)
        };
        assert!((at(0.0) - 3.0).abs() < 1e-4, "A {a}: slot floor {}", at(0.0));
        assert!((at(-3.0) - 5.0).abs() < 1e-4, "A {a}: top {}", at(-3.0));
    }
    // A 45° view marches: the top face there is the cube's edge region.
    let map = dex.view_heights(&part_from_view(45.0), &meta, 8.0).expect("view");
    let (c, r) = map.cell_of(5.0, 0.0).expect("on");
    let z = map.get(c, r).unwrap_or(f32::NAN);
    // Along the 45° diagonal the cube's corner is at 5√2 = 7.07; both slots cut 2 mm: the corner
    // region (|y|, |z| <= 1 excluded) is intact there: the ray hits the corner.
    assert!((z - 7.071).abs() < 0.1, "45° {z}");
}

#[test]
fn bad_parameters_are_named_before_anything_is_allocated() {
    // The seed's stock, 30 x 30 x 320 mm at 5 µm, on three grids: refused with the limit.
    let blank = block(30.0, 30.0, 320.0);
    let err = DexelStock::new(&blank, &DexelCells::tri(0.005)).expect_err("too large");
    assert!(err.to_string().contains("limit of 4294967296 bytes"), "{err}");
    let err =
        DexelStock::new(&blank, &DexelCells { x_mm: Some(-1.0), y_mm: None, z_mm: None }).expect_err("cell");
    assert!(err.to_string().contains("dexel.x_cell_mm"), "{err}");
    assert!(matches!(
        DexelStock::new(&blank, &DexelCells { x_mm: None, y_mm: None, z_mm: None }),
        Err(DexelError::NoGrid)
    ));
    let two = Blank {
        boxes: vec![
            OrientedBox::aligned(Point3::origin(), Point3::new(1.0, 1.0, 1.0)),
            OrientedBox::aligned(Point3::new(2.0, 2.0, 2.0), Point3::new(3.0, 3.0, 3.0)),
        ],
    };
    assert!(matches!(DexelStock::new(&two, &DexelCells::tri(0.1)), Err(DexelError::EmptyBlank)));
    let mut dex = DexelStock::new(&block(5.0, 5.0, 5.0), &DexelCells::tri(0.5)).expect("dexel");
    let solid = ToolSolid::new(&ToolProfile::ball(2.0).expect("ball"), 10.0).expect("solid");
    let err = dex
        .cut_line(&solid, &Point3::new(f64::NAN, 0.0, 0.0), &Point3::origin(), &z_axis())
        .expect_err("nan");
    assert!(err.to_string().contains("from"), "{err}");
}

/// A block with a tilted ball groove and a flat pocket, on three grids.
fn cut_block(cell: f64) -> DexelStock {
    let mut dex = DexelStock::new(&block(20.0, 16.0, 10.0), &DexelCells::tri(cell)).expect("dexel");
    let ball = ToolSolid::new(&ToolProfile::ball(6.0).expect("ball"), 30.0).expect("solid");
    let flat = ToolSolid::new(&ToolProfile::flat(4.0).expect("flat"), 30.0).expect("solid");
    let tilted = Unit::new_normalize(Vector3::new(0.0, -0.5, 1.0));
    dex.cut_line(&ball, &Point3::new(-4.0, 5.0, 7.0), &Point3::new(24.0, 9.0, 8.0), &tilted).expect("groove");
    dex.cut_line(&flat, &Point3::new(5.0, 12.0, 6.0), &Point3::new(14.0, 12.0, 6.0), &z_axis())
        .expect("pocket");
    dex
}

/// Brute force: the squared distance from `p` to the nearest dexel end of any grid, each end
/// taken as its ray's cell square.
fn nearest_end_reference(dex: &DexelStock, p: &Point3<f64>) -> f64 {
    let mut best = f64::INFINITY;
    for g in &dex.grids {
        let (a, b) = plane_axes(g.axis);
        for j in 0..g.n[1] {
            for i in 0..g.n[0] {
                let gap = |x: f64, lo: f64| {
                    if x < lo {
                        lo - x
                    } else if x > lo + g.cell {
                        x - lo - g.cell
                    } else {
                        0.0
                    }
                };
                let dx = gap(p[a], g.origin[0] + i as f64 * g.cell);
                let dy = gap(p[b], g.origin[1] + j as f64 * g.cell);
                for s in &g.rays[j * g.n[0] + i] {
                    for e in [s[0], s[1]] {
                        let d = f64::from(e) - p[g.axis];
                        best = best.min(dx * dx + dy * dy + d * d);
                    }
                }
            }
        }
    }
    best
}

#[test]
fn surface_distance_is_the_nearest_dexel_end() {
    let dex = cut_block(0.4);
    let mut rng = StdRng::seed_from_u64(21);
    for _ in 0..400 {
        let p = Point3::new(
            rng.random_range(-3.0..23.0),
            rng.random_range(-3.0..19.0),
            rng.random_range(-3.0..13.0),
        );
        let reference = nearest_end_reference(&dex, &p).sqrt();
        match dex.surface_distance(&p, 5.0) {
            Some(d) => assert!((d - reference).abs() < 1e-9, "{p:?}: {d} against {reference}"),
            None => assert!(reference > 5.0 - 1e-9, "{p:?}: none within 5 mm, the reference has {reference}"),
        }
        // Away from a smooth stretch of surface between the rays, the deviation is that
        // distance, signed by the material at the point.
        if dex.grids.iter().all(|g| g.local(&p).is_none()) {
            let signed = dex.deviation_at(&p, 5.0);
            assert!((signed.abs() - reference.min(5.0)).abs() < 1e-9, "{p:?}: {signed}");
            assert_eq!(signed > 0.0, dex.inside(&p) && reference > 0.0, "{p:?}: sign of {signed}");
        }
    }
    // On a face seen along a grid's rays the distance is exact: 0.3 mm above the untouched top.
    let d = dex.surface_distance(&Point3::new(18.9, 1.1, 10.3), 5.0).expect("near the top");
    assert!((d - 0.3).abs() < 1e-5, "{d}");
    assert!(dex.deviation_at(&Point3::new(18.9, 1.1, 9.8), 5.0) > 0.19);
}

#[test]
fn the_surface_mesh_is_closed_wound_outward_and_holds_the_stocks_volume() {
    let dex = cut_block(0.25);
    let step = dex.surface_step_mm(MAX_SURFACE_SAMPLES);
    assert!((step - 0.25).abs() < 1e-12, "a small stock is meshed at its cell: {step}");
    let mesh = dex.surface_mesh(step).expect("mesh");
    assert!(mesh.triangles.len() > 1000);
    // Watertight: every directed edge is matched by the same edge the other way.
    let mut edges: std::collections::HashMap<(u32, u32), i64> = std::collections::HashMap::new();
    for t in &mesh.triangles {
        for k in 0..3 {
            let (a, b) = (t[k], t[(k + 1) % 3]);
            *edges.entry((a.min(b), a.max(b))).or_default() += if a < b { 1 } else { -1 };
        }
    }
    assert!(edges.values().all(|&c| c == 0), "an edge is not matched by its reverse");
    let (v_mesh, v_dex) = (surface::mesh_volume_mm3(&mesh), dex.volume_mm3());
    assert!(v_mesh > 0.0, "wound outward");
    assert!((v_mesh - v_dex).abs() < 0.01 * v_dex, "mesh {v_mesh} mm³ against the dexels' {v_dex}");
    // Every vertex lies on the part's surface within a lattice step.
    for v in mesh.vertices.iter().step_by(7) {
        let d = dex.surface_distance(v, 2.0).unwrap_or(2.0);
        assert!(d <= step, "vertex {v:?} is {d} mm from the surface");
    }
    // A coarser lattice when the samples are limited; a bad step is named.
    assert!(dex.surface_step_mm(20_000) > 0.25);
    assert!(matches!(dex.surface_mesh(0.001), Err(DexelError::TooManySamples { .. })));
    assert!(matches!(dex.surface_mesh(f64::NAN), Err(DexelError::Invalid { .. })));
}

#[test]
fn the_capsule_chord_of_a_row_holds_every_point_within_the_radius_and_no_more() {
    let mut rng = StdRng::seed_from_u64(33);
    for _ in 0..300 {
        let p0 = [rng.random_range(-5.0..5.0), rng.random_range(-5.0..5.0)];
        let e = if rng.random_bool(0.2) {
            [0.0, 0.0]
        } else {
            [rng.random_range(-6.0..6.0), rng.random_range(-6.0..6.0)]
        };
        let r = rng.random_range(0.1..3.0);
        let yb = rng.random_range(-12.0..12.0);
        // Brute force: points of the row every 1e-3 mm, their distance to the segment.
        let dist = |x: f64| {
            let rel = [x - p0[0], yb - p0[1]];
            let ee = e[0] * e[0] + e[1] * e[1];
            let k = if ee > 0.0 { ((rel[0] * e[0] + rel[1] * e[1]) / ee).clamp(0.0, 1.0) } else { 0.0 };
            ((rel[0] - k * e[0]).powi(2) + (rel[1] - k * e[1]).powi(2)).sqrt()
        };
        let inside: Vec<f64> =
            (0..30_000).map(|i| -15.0 + i as f64 * 1e-3).filter(|&x| dist(x) <= r).collect();
        match capsule_chord(p0, e, r, yb) {
            None => assert!(inside.is_empty(), "{p0:?} {e:?} {r} {yb}: missed {} points", inside.len()),
            Some((lo, hi)) => {
                for x in &inside {
                    assert!(*x >= lo && *x <= hi, "{p0:?} {e:?} {r} {yb}: {x} outside [{lo}, {hi}]");
                }
                assert!(
                    dist(lo + 1e-9) <= r + 1e-6 && dist(hi - 1e-9) <= r + 1e-6,
                    "chord ends off the capsule"
                );
            }
        }
    }
}

#[test]
fn the_lower_surface_table_bounds_it_from_below() {
    let mut rng = StdRng::seed_from_u64(34);
    for profile in tools() {
        let solid = ToolSolid::new(&profile, 30.0).expect("solid");
        let r = solid.radius_mm();
        for _ in 0..2000 {
            let d = rng.random_range(0.0..=r);
            let exact = solid.lower(d).expect("within the radius");
            let bound = solid.lower_bound_d2(d * d);
            assert!(bound <= exact + 1e-12, "{profile:?} at {d}: {bound} above {exact}");
            assert!(exact - bound < 0.05 * r, "{profile:?} at {d}: {bound} far below {exact}");
        }
    }
}

/// A vector with each coordinate uniform in `-half..half`.
fn random_vector(rng: &mut StdRng, half: f64) -> Vector3<f64> {
    Vector3::new(rng.random_range(-half..half), rng.random_range(-half..half), rng.random_range(-half..half))
}

/// A ray along a random grid axis `k` (its unit direction and its origin on the plane through 0).
fn random_grid_ray(rng: &mut StdRng) -> (usize, Vector3<f64>, Point3<f64>) {
    let k = rng.random_range(0..3usize);
    let mut d = Vector3::zeros();
    d[k] = 1.0;
    let mut o = Point3::from(random_vector(rng, 4.0));
    o[k] = 0.0;
    (k, d, o)
}

/// A random tool axis across grid axis `k` (in the plane of the other two), or `None` when the
/// draw is too short to normalise well.
fn random_axis_across(rng: &mut StdRng, k: usize) -> Option<AxisFrame> {
    let mut a = random_vector(rng, 1.0);
    a[k] = 0.0;
    (a.norm() >= 0.1).then(|| AxisFrame::new(&Unit::new_normalize(a)))
}

/// A closed form's interval against the general one: equal within 1e-6 mm where both meet the
/// ray (returns 1 then, to count the hits), or both missing it but for grazing rays, where one form
/// may keep a point interval the other rounds away.
fn same_extent(general: Option<(f64, f64)>, closed: Option<(f64, f64)>) -> usize {
    match (general, closed) {
        (Some(g), Some(q)) => {
            assert!((g.0 - q.0).abs() < 1e-6 && (g.1 - q.1).abs() < 1e-6, "{g:?} against {q:?}");
            1
        }
        (None, None) => 0,
        (Some(g), None) | (None, Some(g)) => {
            assert!(g.1 - g.0 < 1e-4, "{general:?} against {closed:?}");
            0
        }
    }
}

#[test]
fn the_capsule_closed_form_matches_the_general_sweep_of_a_ball() {
    let mut rng = StdRng::seed_from_u64(35);
    let mut hits = 0;
    for _ in 0..5000 {
        let axis = Unit::new_normalize(random_vector(&mut rng, 1.0));
        let f = AxisFrame::new(&axis);
        let p0 = Point3::from(random_vector(&mut rng, 2.0));
        let v = if rng.random_bool(0.1) { Vector3::zeros() } else { random_vector(&mut rng, 3.0) };
        let (_, dvec, o) = random_grid_ray(&mut rng);
        let (c, r) = (rng.random_range(0.2..2.0), rng.random_range(0.2..2.0));
        let piece = Piece::Sphere { c, r };
        let general = RayMove::new(&o, &dvec, &p0, &v, &f).extent(&piece);
        hits += same_extent(general, sweep::capsule_extent(&o, &dvec, &(p0 + f.u * c), &v, r));
    }
    assert!(hits > 400, "{hits} rays met the capsule");
}

#[test]
fn the_cylinder_closed_form_across_its_axis_matches_the_general_sweep() {
    // Rays across the axis (the axis random in the plane across a grid's rays), moves of any
    // direction (level, ramping, plunging along the axis, none), cylinders of random heights.
    let mut rng = StdRng::seed_from_u64(37);
    let mut hits = 0;
    for _ in 0..5000 {
        let (k, dvec, o) = random_grid_ray(&mut rng);
        let Some(f) = random_axis_across(&mut rng, k) else { continue };
        let p0 = Point3::from(random_vector(&mut rng, 2.0));
        let v = match rng.random_range(0..4) {
            0 => Vector3::zeros(),
            1 => f.u * rng.random_range(-2.0..2.0),
            _ => random_vector(&mut rng, 3.0),
        };
        let h0 = rng.random_range(0.0..1.5);
        let (h1, r) = (h0 + rng.random_range(0.1..3.0), rng.random_range(0.2..2.0));
        let piece = Piece::Frustum { h0, h1, r0: r, r1: r };
        let general = RayMove::new(&o, &dvec, &p0, &v, &f).extent(&piece);
        hits += same_extent(general, sweep::cylinder_across_extent(&o, &dvec, &p0, &v, &f.u, (h0, h1), r));
    }
    assert!(hits > 400, "{hits} rays met the cylinder");
}

#[test]
fn level_moves_along_the_rays_match_the_general_sweep_either_way_up() {
    // The axial shortcut (a level move with the tool parallel to a grid's rays, pointing either
    // way along them) and the shortcut across the axis (the other two grids: the tool's disc at
    // the ray's height swept into a capsule) against the general closed form, forced by tilting
    // the axis by 1e-7 rad.
    let mut rng = StdRng::seed_from_u64(36);
    for profile in tools() {
        let solid = ToolSolid::new(&profile, 12.0).expect("solid");
        for sgn in [1.0, -1.0] {
            let exact_axis = Unit::new_normalize(Vector3::new(0.0, 0.0, sgn));
            let tilted = Unit::new_normalize(Vector3::new(1e-7, 0.0, sgn));
            let mut fast = DexelStock::new(&block(10.0, 8.0, 6.0), &DexelCells::tri(0.2)).expect("dexel");
            let mut general = fast.clone();
            for _ in 0..10 {
                // Tip 1 mm into the block from the side the tool comes from.
                let z = if sgn > 0.0 { rng.random_range(4.5..5.5) } else { rng.random_range(0.5..1.5) };
                // Level moves, and ramps and plunges (the closed form across the axis for a
                // cylinder piece).
                let dz = match rng.random_range(0..4) {
                    0 | 1 => 0.0,
                    _ => rng.random_range(-0.6..0.6),
                };
                let p0 = Point3::new(rng.random_range(1.0..9.0), rng.random_range(1.0..7.0), z);
                let p1 = if rng.random_bool(0.15) {
                    p0 + Vector3::new(0.0, 0.0, dz)
                } else {
                    Point3::new(rng.random_range(1.0..9.0), rng.random_range(1.0..7.0), z + dz)
                };
                let a = fast.cut_line(&solid, &p0, &p1, &exact_axis).expect("cut");
                let b = general.cut_line(&solid, &p0, &p1, &tilted).expect("cut");
                assert!(
                    (a.volume_mm3 - b.volume_mm3).abs() < 1e-3 * b.volume_mm3.max(1.0),
                    "{profile:?} {sgn}: {} against {}",
                    a.volume_mm3,
                    b.volume_mm3
                );
            }
            assert_eq!(fast.grids.len(), 3);
            for (gf, gg) in fast.grids.iter().zip(&general.grids) {
                let axis = gf.axis;
                for (rf, rg) in gf.rays.iter().zip(&gg.rays) {
                    assert_eq!(rf.len(), rg.len(), "{profile:?} {sgn} grid {axis}: {rf:?} against {rg:?}");
                    for (x, y) in rf.iter().zip(rg.iter()) {
                        assert!(
                            (x[0] - y[0]).abs() < 1e-4 && (x[1] - y[1]).abs() < 1e-4,
                            "{profile:?} {sgn} grid {axis}: {rf:?} against {rg:?}"
                        );
                    }
                }
            }
        }
    }
}

#[test]
fn subtracting_in_place_matches_rebuilding_the_list() {
    // Random rays of up to six segments (some spilled to the heap) and random cuts, many on a
    // segment's end or within the smallest segment of one: the same segments left, the same
    // pieces reported in the same order.
    let mut rng = StdRng::seed_from_u64(29);
    for _ in 0..20_000 {
        let n = rng.random_range(0..7);
        let mut ends: Vec<f32> = (0..2 * n).map(|_| rng.random_range(0..40) as f32 * 0.25).collect();
        ends.sort_by(f32::total_cmp);
        ends.dedup();
        let mut ray = Ray::new();
        for pair in ends.chunks_exact(2) {
            ray.push([pair[0], pair[1]]);
        }
        let pick = |rng: &mut StdRng| match rng.random_range(0..3) {
            0 => ends.get(rng.random_range(0..ends.len().max(1))).copied().unwrap_or(1.0),
            1 => rng.random_range(0..40) as f32 * 0.25 + MIN_SEGMENT_MM * 0.5,
            _ => rng.random_range(-1.0..11.0),
        };
        let (a, b) = (pick(&mut rng), pick(&mut rng));
        let (lo, hi) = if rng.random_bool(0.9) { (a.min(b), a.max(b)) } else { (a, b) };
        let (mut fast, mut slow) = (ray.clone(), ray.clone());
        let (mut got, mut want) = (Vec::new(), Vec::new());
        subtract(&mut fast, lo, hi, |x, y| got.push([x, y]));
        subtract_rebuilt(&mut slow, lo, hi, |x, y| want.push([x, y]));
        assert_eq!(fast.as_slice(), slow.as_slice(), "ray {ray:?} minus [{lo}, {hi}]");
        assert_eq!(got, want, "ray {ray:?} minus [{lo}, {hi}]");
        assert!(fast.len() > 1 || !fast.spilled(), "a ray of one segment is kept inline");
    }
}

#[test]
fn the_end_view_along_a_ray_reads_what_it_reads_at_each_point() {
    // The per-ray linear and quadratic forms against the point-by-point reading: random tool
    // poses, travel directions (or none), rays and points.
    let mut rng = StdRng::seed_from_u64(31);
    for case in 0..5000 {
        let axis = Unit::new_normalize(random_vector(&mut rng, 1.0) + Vector3::new(0.0, 0.0, 1e-3));
        let f = AxisFrame::new(&axis);
        let fwd = (case % 3 != 0).then(|| {
            let t = random_vector(&mut rng, 1.0);
            let perp = (t - f.u * t.dot(&f.u)).normalize();
            (perp, f.u.cross(&perp))
        });
        let end = EndView {
            tip: Point3::from(random_vector(&mut rng, 5.0)),
            u: f.u,
            e1: f.e1,
            e2: f.e2,
            fwd,
            radius: rng.random_range(0.5..4.0),
            half_cell: 0.05,
        };
        // On the ray's plane through the origin, as the sweep's rays are.
        let (_, d, o) = random_grid_ray(&mut rng);
        let view = end.along(&o, &d);
        let xs: Vec<f64> = (0..3).map(|_| rng.random_range(-6.0..6.0)).collect();
        let mut fast = Tally::new();
        for &x in &xs {
            end.observe(&view, x, &mut fast);
        }
        // The reference: each point's offset from the tip, split along and across the axis.
        let mut slow = Tally::new();
        for &x in &xs {
            let y = (o + d * x) - end.tip;
            let w = y.dot(&end.u);
            let perp = y - end.u * w;
            let rho2 = perp.norm_squared();
            let reach = end.radius + end.half_cell;
            // Points within rounding of the reach are left out of the comparison.
            if (rho2 - reach * reach).abs() < 1e-9 {
                fast = Tally::new();
                slow = Tally::new();
                break;
            }
            if rho2 > reach * reach {
                continue;
            }
            slow.any = true;
            slow.axial = slow.axial.max(w);
            match end.fwd {
                Some((fw, g)) => {
                    if perp.dot(&fw) >= -end.half_cell {
                        slow.e_min = slow.e_min.min(perp.dot(&g));
                        slow.e_max = slow.e_max.max(perp.dot(&g));
                        slow.rho_c2 = slow.rho_c2.max(rho2);
                    }
                }
                None => {
                    let ang =
                        perp.dot(&end.e2).atan2(perp.dot(&end.e1)).rem_euclid(2.0 * std::f64::consts::PI);
                    slow.sectors |= 1 << ((ang.to_degrees() / 10.0) as u32).min(35);
                }
            }
        }
        assert_eq!(fast.any, slow.any, "case {case}");
        for (a, b) in [
            (fast.axial, slow.axial),
            (fast.e_min, slow.e_min),
            (fast.e_max, slow.e_max),
            (fast.rho_c2, slow.rho_c2),
        ] {
            assert!(a == b || (a - b).abs() < 1e-9, "case {case}: {a} vs {b}");
        }
        // A point on a sector's edge may fall either side of it.
        let diff = fast.sectors ^ slow.sectors;
        assert!(diff.count_ones() <= 2, "case {case}: sectors {:b} vs {:b}", fast.sectors, slow.sectors);
    }
}

#[test]
fn the_disc_chord_across_the_axis_matches_the_capsule_in_space() {
    // A level move across the tool's axis, rays across it too: the 2-D chord in the ray's plane
    // against the 3-D capsule of the tool's section at the ray's height (random tools, axes in
    // the plane across a grid's rays, moves across the axis or none).
    let mut rng = StdRng::seed_from_u64(41);
    let solids: Vec<ToolSolid> = tools().iter().map(|p| ToolSolid::new(p, 10.0).expect("solid")).collect();
    let mut hits = 0;
    for case in 0..20_000 {
        let tool = &solids[case % solids.len()];
        let (k, dvec, o) = random_grid_ray(&mut rng);
        let Some(f) = random_axis_across(&mut rng, k) else { continue };
        let from = Point3::from(random_vector(&mut rng, 3.0));
        let v = if case % 10 == 0 {
            Vector3::zeros()
        } else {
            let t = random_vector(&mut rng, 3.0);
            t - f.u * t.dot(&f.u)
        };
        let w = (o - from).dot(&f.u);
        let space =
            tool.radius_at(w).and_then(|rho| sweep::capsule_extent(&o, &dvec, &(from + f.u * w), &v, rho));
        let plane = sweep::AcrossMove::new(&f.u, &dvec, k, &v).extent(tool, &o, &from);
        hits += same_extent(space, plane);
    }
    assert!(hits > 2000, "{hits} rays met the tool");
}

#[test]
fn runs_of_pieces_cut_the_primary_grid_exactly_and_the_others_within_their_error() {
    // Paths of short pieces (a revolution's each) whose ends stray from straight lines by up
    // to the error, some bending beyond it, tools changing: `cut_run` against `cut_line` per
    // piece. The primary grid and every piece's figures are equal bit for bit; on the other
    // grids, material the run took that the pieces did not lies within the error of the
    // pieces' swept tool (dense reference).
    let mut rng = StdRng::seed_from_u64(43);
    let err = 0.01;
    let solids: Vec<ToolSolid> = tools().iter().map(|p| ToolSolid::new(p, 9.0).expect("solid")).collect();
    for case in 0..8 {
        let axis = if case % 2 == 0 {
            z_axis()
        } else {
            Unit::new_normalize(Vector3::new(rng.random_range(-0.4..0.4), rng.random_range(-0.4..0.4), 1.0))
        };
        let blank = block(8.0, 7.0, 5.0);
        let mut fast = DexelStock::new(&blank, &DexelCells::tri(0.13)).expect("dexel");
        let mut slow = fast.clone();
        // Each piece's tool and its dense poses.
        let mut swept: Vec<(usize, Poses)> = Vec::new();
        let mut at =
            Point3::new(rng.random_range(2.0..6.0), rng.random_range(2.0..5.0), rng.random_range(3.5..4.8));
        let mut ti = case % solids.len();
        for mv in 0..6 {
            if mv == 3 {
                ti = (ti + 1) % solids.len();
            }
            let dir = Vector3::new(
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
                rng.random_range(-0.2..0.1),
            )
            .normalize();
            for _ in 0..rng.random_range(2..9) {
                let jitter = random_vector(&mut rng, err / 2.0 / 3f64.sqrt());
                let bend =
                    if rng.random_bool(0.15) { random_vector(&mut rng, 0.05) } else { Vector3::zeros() };
                let to = at + dir * rng.random_range(0.05..0.3) + jitter + bend;
                let a = fast.cut_run(&solids[ti], &at, &to, &axis, err).expect("run");
                let b = slow.cut_line(&solids[ti], &at, &to, &axis).expect("line");
                assert_eq!(a.volume_mm3.to_bits(), b.volume_mm3.to_bits(), "case {case}");
                assert_eq!(a.engagement_deg.to_bits(), b.engagement_deg.to_bits(), "case {case}");
                assert_eq!(a.axial_depth_mm.to_bits(), b.axial_depth_mm.to_bits(), "case {case}");
                swept.push((ti, poses(&|s| (at + (to - at) * s, axis), 60)));
                at = to;
            }
        }
        assert!(!fast.is_flushed(), "case {case}: the last run waits for a flush");
        fast.flush().expect("flush");
        assert!(fast.grids[0].rays == slow.grids[0].rays, "case {case}: the primary grid differs");
        for (g, h) in fast.grids.iter().zip(&slow.grids).skip(1) {
            for (k, (ra, rb)) in g.rays.iter().zip(&h.rays).enumerate() {
                if ra == rb {
                    continue;
                }
                // Material the reference keeps and the run took: each piece's middle.
                let mut left = rb.clone();
                for s in ra.iter() {
                    // Keep only what `ra` lacks: subtract `ra`'s material from `rb`'s.
                    subtract(&mut left, s[0], s[1], |_, _| {});
                }
                let o = g.ray_origin(k % g.n[0], k / g.n[0]);
                for s in left.iter().filter(|s| s[1] - s[0] > 1e-5) {
                    let x = o + g.dir() * f64::from(0.5 * (s[0] + s[1]));
                    let near = swept.iter().any(|(ti, ps)| {
                        let tool = &solids[*ti];
                        ps.iter().any(|(p, u)| {
                            let y = x - p;
                            let w = y.dot(u);
                            tool.contains((y - u * w).norm(), w, 2.0 * err + 2e-3)
                        })
                    });
                    assert!(near, "case {case}: grid {} took {x:?} beyond the error", g.axis);
                }
            }
        }
    }
}

/// A blank whose top is the plane through the origin with unit normal `n` (tilted less than 70°
/// from Z), cut to a 16 × 12 mm footprint.
fn tilted_top(n: &Vector3<f64>, cell: f64) -> DexelStock {
    let rot = Rotation3::rotation_between(&Vector3::z(), n).expect("not upside down");
    let slab = OrientedBox {
        part_from_box: rot,
        min: Point3::new(-60.0, -60.0, -60.0),
        max: Point3::new(60.0, 60.0, 0.0),
    };
    let footprint = OrientedBox::aligned(Point3::new(-8.0, -6.0, -40.0), Point3::new(8.0, 6.0, 40.0));
    DexelStock::new(&Blank { boxes: vec![slab, footprint] }, &DexelCells::tri(cell)).expect("stock")
}

#[test]
fn a_plane_measures_exactly_at_any_tilt_where_the_nearest_end_is_off_by_the_slope() {
    let mut rng = StdRng::seed_from_u64(38);
    let cell = 0.1;
    let mut nearest_worst = 0.0f64;
    for _ in 0..12 {
        let tilt = rng.random_range(0.0..70.0f64).to_radians();
        let az = rng.random_range(0.0..std::f64::consts::TAU);
        let n = Vector3::new(tilt.sin() * az.cos(), tilt.sin() * az.sin(), tilt.cos());
        let dex = tilted_top(&n, cell);
        for _ in 0..300 {
            let (x, y) = (rng.random_range(-6.0..6.0), rng.random_range(-4.0..4.0));
            // On the plane, then `off` along its normal (into the material when negative).
            let on = Point3::new(x, y, -(n.x * x + n.y * y) / n.z);
            let off = rng.random_range(-0.15..0.15);
            let p = on + n * off;
            let d = dex.deviation_at(&p, 5.0);
            assert!((d + off).abs() < 2e-5, "tilt {:.1}°, {p:?}: {d} against {}", tilt.to_degrees(), -off);
            let nearest = dex.surface_distance(&on, 5.0).unwrap_or(5.0);
            nearest_worst = nearest_worst.max(nearest);
        }
    }
    // The nearest dexel end alone reads points on the plane up to half a cell times the slope off.
    assert!(nearest_worst > 0.3 * cell, "{nearest_worst}");
}

#[test]
fn a_ball_groove_measures_within_the_curvature_between_rays() {
    let cell = 0.25;
    let dex = cut_block(cell);
    // The groove's ball: centre line `tip + R·axis`, radius 3 mm; its surface in the block is the
    // lower half of the cylinder around that line.
    let (a, b) = (Point3::new(-4.0, 5.0, 7.0), Point3::new(24.0, 9.0, 8.0));
    let axis = Vector3::new(0.0, -0.5, 1.0).normalize();
    let m = (b - a).normalize();
    let down = -(axis - m * axis.dot(&m)).normalize();
    let side = m.cross(&down);
    let mut rng = StdRng::seed_from_u64(5);
    let (mut worst, mut nearest_worst, mut n) = (0.0f64, 0.0f64, 0);
    while n < 2000 {
        let s = rng.random_range(0.0..1.0);
        let phi = rng.random_range(-1.2..1.2f64);
        let u = down * phi.cos() + side * phi.sin();
        let p = a + (b - a) * s + axis * 3.0 + u * 3.0;
        // In the block, away from its sides and the pocket's reach.
        if !(p.x > 1.0 && p.x < 19.0 && p.y > 1.0 && p.y < 9.5 && p.z < 9.7) {
            continue;
        }
        n += 1;
        worst = worst.max(dex.deviation_at(&p, 5.0).abs());
        nearest_worst = nearest_worst.max(dex.surface_distance(&p, 5.0).unwrap_or(5.0));
    }
    // A chord of a 3 mm circle over a cell's diagonal sags (0.35)² / 24 ≈ 0.005 mm.
    assert!(worst < 0.01, "{worst}");
    assert!(nearest_worst > 3.0 * worst, "{nearest_worst} against {worst}");
}
