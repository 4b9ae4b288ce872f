//! Scanner throughput on a 10^5-triangle mesh: BVH build time, profiles/s and rays/s, against a
//! brute-force all-triangles ray cast (the reference) measured in the same run.
//!
//! Run: `cargo bench --bench scanner` (harness = false, prints figures).

use std::hint::black_box;
use std::time::Instant;

use depthmill_geometry::Mesh;
use depthmill_scanning::domain::scanner::{Bvh, Scanner, ScannerSpec};
use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};

/// Wavy height field, `n × n` vertices over 200 × 200 mm: 2 (n − 1)² triangles.
fn height_field(n: usize) -> Mesh {
    let mut vertices = Vec::with_capacity(n * n);
    for j in 0..n {
        for i in 0..n {
            let x = -100.0 + 200.0 * i as f64 / (n - 1) as f64;
            let y = -100.0 + 200.0 * j as f64 / (n - 1) as f64;
            let z = 3.0 * (x / 13.0).sin() * (y / 17.0).cos() + (x / 9.0 + y / 11.0).sin();
            vertices.push(Point3::new(x, y, z));
        }
    }
    let mut triangles = Vec::with_capacity(2 * (n - 1) * (n - 1));
    for j in 0..n - 1 {
        for i in 0..n - 1 {
            let a = (j * n + i) as u32;
            let b = a + 1;
            let c = a + n as u32;
            let d = c + 1;
            triangles.push([a, b, d]);
            triangles.push([a, d, c]);
        }
    }
    Mesh { vertices, triangles }
}

/// Möller–Trumbore over every triangle: the slow reference.
fn brute_cast(m: &Mesh, o: &Point3<f64>, d: &Vector3<f64>) -> Option<f64> {
    let mut best = f64::INFINITY;
    for tri in &m.triangles {
        let [a, b, c] = tri.map(|i| m.vertices[i as usize]);
        let e1 = b - a;
        let e2 = c - a;
        let p = d.cross(&e2);
        let det = e1.dot(&p);
        if det.abs() < 1e-14 {
            continue;
        }
        let inv = 1.0 / det;
        let s = o - a;
        let u = s.dot(&p) * inv;
        if !(0.0..=1.0).contains(&u) {
            continue;
        }
        let q = s.cross(&e1);
        let v = d.dot(&q) * inv;
        if v < 0.0 || u + v > 1.0 {
            continue;
        }
        let t = e2.dot(&q) * inv;
        if t > 1e-9 && t < best {
            best = t;
        }
    }
    best.is_finite().then_some(best)
}

fn main() {
    let mesh = height_field(225);
    println!("mesh: {} triangles, {} vertices", mesh.triangles.len(), mesh.vertices.len());

    let t0 = Instant::now();
    let bvh = Bvh::build(&mesh).expect("valid mesh");
    let build_s = t0.elapsed().as_secs_f64();
    println!("bvh build: {:.1} ms, {} nodes", build_s * 1e3, bvh.node_count());

    let spec = ScannerSpec::slp400();
    let mut scanner = Scanner::new(spec, &mesh, 1).expect("scanner");
    // Sensor looking down (sensor +Z = world −Z) from 150 mm, sweeping along world Y.
    let down = UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI);
    let frames = 2000u64;
    let poses: Vec<Isometry3<f64>> = (0..frames)
        .map(|k| {
            let y = -80.0 + 160.0 * k as f64 / frames as f64;
            Isometry3::from_parts(Translation3::new(0.0, y, 150.0), down)
        })
        .collect();
    let t0 = Instant::now();
    let mut points = 0usize;
    let mut occl_rays = 0usize;
    let mut dropped = [0usize; 4];
    for (k, pose) in poses.iter().enumerate() {
        let p = scanner.profile(pose, k as u64);
        points += p.points.len();
        // Every ray that passed the window and incidence checks cast an occlusion ray.
        occl_rays += p.points.len() + p.dropped.occluded as usize;
        dropped[0] += p.dropped.out_of_window as usize;
        dropped[1] += p.dropped.incidence as usize;
        dropped[2] += p.dropped.occluded as usize;
        dropped[3] += p.dropped.miss as usize;
        black_box(&p);
    }
    let scan_s = t0.elapsed().as_secs_f64();
    let primary = frames as usize * scanner.spec().points_per_line;
    let profiles_per_s = frames as f64 / scan_s;
    let rays_per_s = (primary + occl_rays) as f64 / scan_s;
    println!(
        "scanner: {frames} profiles in {:.3} s = {:.0} profiles/s ({:.1}x the 150 Hz line rate), \
         {:.2} M rays/s ({} primary + {} occlusion), {:.1} points/profile",
        scan_s,
        profiles_per_s,
        profiles_per_s / 150.0,
        rays_per_s / 1e6,
        primary,
        occl_rays,
        points as f64 / frames as f64
    );

    println!(
        "dropped: {} out of window, {} incidence, {} occluded, {} miss",
        dropped[0], dropped[1], dropped[2], dropped[3]
    );

    // BVH cast alone vs brute force on the same rays.
    let o = Point3::new(0.0, 0.0, 150.0);
    let rays: Vec<Vector3<f64>> = (0..200)
        .map(|k| {
            let a = -0.15 + 0.3 * (k % 20) as f64 / 19.0;
            let b = -0.15 + 0.3 * (k / 20) as f64 / 9.0;
            Vector3::new(a, b, -1.0).normalize()
        })
        .collect();
    let reps = 500;
    let t0 = Instant::now();
    let mut acc = 0.0;
    for _ in 0..reps {
        for d in &rays {
            acc += bvh.cast(&o, d, f64::INFINITY).map_or(0.0, |h| h.t);
        }
    }
    let bvh_s = t0.elapsed().as_secs_f64();
    let bvh_rate = (reps * rays.len()) as f64 / bvh_s;
    let t0 = Instant::now();
    let mut acc_ref = 0.0;
    for d in &rays {
        acc_ref += brute_cast(&mesh, &o, d).unwrap_or(0.0);
    }
    let brute_s = t0.elapsed().as_secs_f64();
    let brute_rate = rays.len() as f64 / brute_s;
    assert!(
        (acc / reps as f64 - acc_ref).abs() < 1e-6 * acc_ref.abs().max(1.0),
        "bvh and brute force differ"
    );
    println!(
        "cast: bvh {:.2} M rays/s, brute force (reference) {:.0} rays/s, speed-up {:.0}x",
        bvh_rate / 1e6,
        brute_rate,
        bvh_rate / brute_rate
    );
}
