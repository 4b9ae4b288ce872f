//! Simulated scan throughput: points generated per second on a 10^5-triangle mesh, against the
//! real scanner's rate (150 lines/s × 450 points = 67 500 points/s), single-threaded and on every
//! core in the same run. Target: at least 20x real time on 2 cores.
//!
//! Run: `cargo bench -p depthmill-scanning --bench scan` (harness = false, prints figures).

use std::time::Instant;

use depthmill_geometry::Mesh;
use depthmill_scanning::domain::scan::{CellLayout, ScanOptions, ScanSession};
use nalgebra::Point3;

/// A relief 90 × 90 mm on `n × n` vertices: 2 (n − 1)² triangles.
fn relief(n: usize) -> Mesh {
    let mut vertices = Vec::with_capacity(n * n);
    for j in 0..n {
        for i in 0..n {
            let x = -45.0 + 90.0 * i as f64 / (n - 1) as f64;
            let y = -45.0 + 90.0 * j as f64 / (n - 1) as f64;
            let r2 = x * x + y * y;
            let z = 5.0 + 12.0 * (-r2 / 900.0).exp() + 1.5 * (x / 7.0).sin() * (y / 9.0).cos();
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

/// Scans the whole plan; returns (points, frames, wall seconds).
fn scan(mesh: &Mesh, opts: &ScanOptions) -> (u64, u64, f64) {
    let t = Instant::now();
    let mut s = ScanSession::new(mesh, opts.clone(), CellLayout::default()).expect("session");
    let plan = s.plan().expect("plan");
    for st in &plan.stations {
        s.run_station(st, st.table_deg, false, &mut |_, _| {}, &|| false).expect("station");
    }
    let out = s.finish();
    (out.report.points, out.report.frames, t.elapsed().as_secs_f64())
}

fn main() {
    let mesh = relief(225);
    println!("mesh: {} triangles", mesh.triangles.len());
    let opts = ScanOptions { table_angles_deg: vec![0.0, 90.0], ..ScanOptions::default() };
    let real_pts_s = 150.0 * 450.0;
    let threads = rayon::current_num_threads();
    let one = rayon::ThreadPoolBuilder::new().num_threads(1).build().expect("pool");
    // Warm-up.
    let _ = scan(&mesh, &ScanOptions { table_angles_deg: vec![0.0], line_spacing_mm: 2.0, ..opts.clone() });
    for round in 0..2 {
        let (p1, f1, s1) = one.install(|| scan(&mesh, &opts));
        let (pn, fnn, sn) = scan(&mesh, &opts);
        println!(
            "round {round}: 1 thread: {p1} points, {f1} frames in {s1:.2} s = {:.2} M pts/s ({:.0} frames/s) = {:.1}x real time",
            p1 as f64 / s1 / 1e6,
            f1 as f64 / s1,
            p1 as f64 / s1 / real_pts_s
        );
        println!(
            "round {round}: {threads} threads: {pn} points, {fnn} frames in {sn:.2} s = {:.2} M pts/s ({:.0} frames/s) = {:.1}x real time ({:.2}x the 1-thread run)",
            pn as f64 / sn / 1e6,
            fnn as f64 / sn,
            pn as f64 / sn / real_pts_s,
            s1 / sn
        );
    }
    println!(
        "reference: the real scanner at 150 lines/s x 450 points = {real_pts_s} points/s; target >= 20x"
    );
}
