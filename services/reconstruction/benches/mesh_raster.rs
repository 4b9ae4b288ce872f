//! Benchmark of the mesh z-buffer and the image filters on 2000×2000 maps.
//!
//! Run: `cargo bench --bench mesh_raster` (a plain `main`, prints figures). Every figure is
//! measured on all threads and, as the reference, on a one-thread rayon pool in the same run.
//!
//! - z-buffer: 10^6 triangles of a wavy height field covering the whole grid, and 10^6
//!   triangles of a closed UV sphere (half of them facing down, hidden) inscribed in it;
//!   triangles/s and covered cells/s.
//! - median 5×5 (radius 2), bilateral with σ_s = 2 px (window 11×11), continuous roughing
//!   over-approximation at k = 8, on the rasterised wavy map.

use std::f64::consts::PI;
use std::hint::black_box;
use std::time::Instant;

use depthmill_geometry::Mesh;
use depthmill_geometry::mesh_raster::rasterize_mesh_with_stats;
use depthmill_geometry::{HeightMap, HeightMapMeta};
use depthmill_reconstruction::domain::image_ops::{bilateral, median};
use depthmill_reconstruction::domain::roughing::continuous_over;
use nalgebra::Point3;

const N: u32 = 2000;
const PIXEL: f64 = 0.1;

fn wavy(n: u32) -> Mesh {
    let side = f64::from(N) * PIXEL;
    let step = side / f64::from(n - 1);
    let mut v = Vec::with_capacity((n * n) as usize);
    for j in 0..n {
        for i in 0..n {
            let (x, y) = (f64::from(i) * step, f64::from(j) * step);
            v.push(Point3::new(x, y, 5.0 * (x / 7.0).sin() * (y / 11.0).cos() + 0.3 * (x * y / 50.0).sin()));
        }
    }
    let mut t = Vec::with_capacity(2 * ((n - 1) * (n - 1)) as usize);
    for j in 0..n - 1 {
        for i in 0..n - 1 {
            let a = j * n + i;
            t.push([a, a + 1, a + n + 1]);
            t.push([a, a + n + 1, a + n]);
        }
    }
    Mesh { vertices: v, triangles: t }
}

fn sphere(n_lat: u32, n_lon: u32) -> Mesh {
    let r = f64::from(N) * PIXEL / 2.0;
    let mut v = vec![Point3::new(r, r, 2.0 * r), Point3::new(r, r, 0.0)];
    for i in 1..n_lat {
        let th = PI * f64::from(i) / f64::from(n_lat);
        for j in 0..n_lon {
            let ph = 2.0 * PI * f64::from(j) / f64::from(n_lon);
            v.push(Point3::new(r + r * th.sin() * ph.cos(), r + r * th.sin() * ph.sin(), r + r * th.cos()));
        }
    }
    let ring = |i: u32, j: u32| 2 + (i - 1) * n_lon + j % n_lon;
    let mut t = Vec::new();
    for j in 0..n_lon {
        t.push([0, ring(1, j), ring(1, j + 1)]);
        t.push([1, ring(n_lat - 1, j + 1), ring(n_lat - 1, j)]);
    }
    for i in 1..n_lat - 1 {
        for j in 0..n_lon {
            t.push([ring(i, j), ring(i + 1, j), ring(i + 1, j + 1)]);
            t.push([ring(i, j), ring(i + 1, j + 1), ring(i, j + 1)]);
        }
    }
    Mesh { vertices: v, triangles: t }
}

/// Best of `reps` wall times, in seconds.
fn time<T>(reps: usize, mut f: impl FnMut() -> T) -> f64 {
    (0..reps)
        .map(|_| {
            let t = Instant::now();
            black_box(f());
            t.elapsed().as_secs_f64()
        })
        .fold(f64::INFINITY, f64::min)
}

/// (all threads, one thread) best times.
fn both<T: Send>(pool1: &rayon::ThreadPool, reps: usize, f: impl Fn() -> T + Sync) -> (f64, f64) {
    let all = time(reps, &f);
    let one = pool1.install(|| time(reps, &f));
    (all, one)
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let threads = rayon::current_num_threads();
    let pool1 = rayon::ThreadPoolBuilder::new().num_threads(1).build()?;
    let grid = HeightMapMeta { z_min_mm: -6.0, z_max_mm: 6.0, ..HeightMapMeta::new(N, N, PIXEL) };
    println!("mesh_raster bench: {N}x{N} cells of {PIXEL} mm, {threads} threads (reference: 1 thread)");

    let mut wavy_map = None;
    for (name, mesh) in [("wavy surface", wavy(708)), ("closed sphere", sphere(500, 1000))] {
        let (map, stats) = rasterize_mesh_with_stats(&mesh, &grid)?;
        let tris = mesh.triangles.len() as f64;
        let cells = stats.cells_covered as f64;
        let (all, one) = both(&pool1, 3, || rasterize_mesh_with_stats(&mesh, &grid));
        println!(
            "z-buffer {name:>13}: {:.2e} triangles, {} cells covered: {:7.1} ms = {:6.2} Mtri/s, {:6.1} Mcell/s; \
             1 thread {:7.1} ms (x{:.2})",
            tris,
            stats.cells_covered,
            all * 1e3,
            tris / all / 1e6,
            cells / all / 1e6,
            one * 1e3,
            one / all
        );
        if wavy_map.is_none() {
            wavy_map = Some(map);
        }
    }
    let map: HeightMap = wavy_map.ok_or("no map")?;
    let cells = f64::from(N) * f64::from(N);

    let report = |name: &str, (all, one): (f64, f64)| {
        println!(
            "{name:>22}: {:7.1} ms = {:6.1} Mcell/s; 1 thread {:7.1} ms (x{:.2})",
            all * 1e3,
            cells / all / 1e6,
            one * 1e3,
            one / all
        );
    };
    report("median 5x5", both(&pool1, 2, || median(&map, 2)));
    report("bilateral 11x11", both(&pool1, 2, || bilateral(&map, 2.0 * PIXEL, 0.5)));
    report("continuous_over k=8", both(&pool1, 3, || continuous_over(&map, 8)));
    Ok(())
}
