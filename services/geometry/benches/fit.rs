//! Surface-fit benchmark: the robust local fit of a cloud to a height map
//! ([`depthmill_geometry::surface_fit`]) with the ridge apexes tried nowhere, only where the
//! quadric bends enough to round a crease (the default), and wherever it bends down, timed in the
//! same run, with how far the default's map strays from trying everywhere; then the default with
//! the plane never taken for a quadric whose bend is the noise's (`Planes::Never`), and, on the
//! synthetic part, each map against the part itself.
//!
//! The default cloud imitates a scanned machined part: 40 x 40 mm at 5 points per 0.1 mm cell
//! with 0.035 mm noise; a flat face, a wavy relief, a chamfered boss (four creases at 30°
//! to the axes) and a roof whose crease runs at 20°. `--cloud FILE` fits any cloud the readers
//! take (PLY, XYZ, STL vertices) instead, over its bounds; the demo's scan is
//! `point_cloud.ply` in a `depthmill demo -o DIR` output.
//!
//! Run: `cargo bench -p depthmill-geometry --bench fit [-- --cloud FILE --pixel-mm 0.1 --repeat 3]`.

use std::path::PathBuf;
use std::time::Instant;

use depthmill_geometry::HeightMap;
use depthmill_geometry::formats::{ReadLimits, read_cloud};
use depthmill_geometry::raster::{Roi, grid_for_roi};
use depthmill_geometry::surface_fit::{FitParams, FitReport, Planes, Ridges, rasterize_fit};
use nalgebra::Point3;
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

mod support;

use support::{BoxResult, arg, gauss};

/// The synthetic part's height at `(x, y)`, mm.
fn part(x: f64, y: f64) -> f64 {
    if x < 20.0 && y < 20.0 {
        // A chamfered boss: a 6 mm top, 45° chamfers, on a flat face.
        let (sa, ca) = 30f64.to_radians().sin_cos();
        let (u, v) = ((x - 10.0) * ca + (y - 10.0) * sa, -(x - 10.0) * sa + (y - 10.0) * ca);
        let d = u.abs().max(v.abs());
        10.0 + (4.0 - (d - 3.0).max(0.0)).clamp(0.0, 4.0)
    } else if x >= 20.0 && y < 20.0 {
        10.0 + 2.0 * (x / 3.0).sin() * (y / 4.0).cos() + 0.3 * (x / 1.1 + y / 1.7).sin()
    } else if x < 20.0 {
        10.0
    } else {
        // A roof: 30° faces meeting along a crease at 20°.
        let (sa, ca) = 20f64.to_radians().sin_cos();
        let d = (x - 30.0) * sa - (y - 30.0) * ca;
        14.0 - 30f64.to_radians().tan() * d.abs()
    }
}

fn synthetic(per_cell: f64, pixel: f64, noise: f64) -> Vec<Point3<f64>> {
    let mut rng = StdRng::seed_from_u64(11);
    let n = (per_cell * (40.0 / pixel) * (40.0 / pixel)) as usize;
    (0..n)
        .map(|_| {
            let (x, y) = (rng.random_range(0.0..40.0), rng.random_range(0.0..40.0));
            Point3::new(x, y, part(x, y) + noise * gauss(&mut rng))
        })
        .collect()
}

fn run(
    points: &[Point3<f64>],
    roi: &Roi,
    pixel: f64,
    params: FitParams,
    repeat: u32,
) -> BoxResult<(f64, HeightMap, FitReport)> {
    let grid = grid_for_roi(roi, pixel)?;
    let mut best = f64::INFINITY;
    let mut out = None;
    for _ in 0..repeat {
        let t = Instant::now();
        let (map, _, report) = rasterize_fit(points, &grid, &params)?;
        best = best.min(t.elapsed().as_secs_f64());
        out = Some((map, report));
    }
    let (map, report) = out.ok_or("no run")?;
    Ok((best, map, report))
}

/// Cells the fit gave a height.
fn cells(r: &FitReport) -> usize {
    r.quadric_cells + r.plane_cells + r.mean_cells + r.own_cells + r.ridge_cells + r.held_cells + r.flat_cells
}

fn main() -> BoxResult<()> {
    let args: Vec<String> = std::env::args().collect();
    let pixel = arg(&args, "--pixel-mm", 0.1);
    let repeat = arg(&args, "--repeat", 3u32).max(1);
    let cloud: Option<PathBuf> =
        args.iter().position(|a| a == "--cloud").and_then(|i| args.get(i + 1)).map(PathBuf::from);
    let (points, what) = match &cloud {
        Some(path) => {
            let (c, _) = read_cloud(path, &ReadLimits::default())?;
            (c.points.iter().map(|p| p.cast::<f64>()).collect(), path.display().to_string())
        }
        None => (synthetic(5.0, pixel, 0.035), "the synthetic part".to_string()),
    };
    let (lo, hi) = points
        .iter()
        .fold(((f64::INFINITY, f64::INFINITY), (f64::NEG_INFINITY, f64::NEG_INFINITY)), |(lo, hi), p| {
            ((lo.0.min(p.x), lo.1.min(p.y)), (hi.0.max(p.x), hi.1.max(p.y)))
        });
    let roi = Roi { x_min_mm: lo.0, y_min_mm: lo.1, x_max_mm: hi.0 + pixel, y_max_mm: hi.1 + pixel };
    println!("{what}: {} points, {pixel} mm cells, best of {repeat}", points.len());
    let ridges = |ridges| FitParams { ridges, ..FitParams::default() };
    let (t_all, all, r_all) = run(&points, &roi, pixel, ridges(Ridges::Everywhere), repeat)?;
    let (t_scr, scr, r_scr) = run(&points, &roi, pixel, ridges(Ridges::Screened), repeat)?;
    let (t_off, _, r_off) = run(&points, &roi, pixel, ridges(Ridges::Off), repeat)?;
    let never = FitParams { planes: Planes::Never, ..FitParams::default() };
    let (t_never, quad, r_never) = run(&points, &roi, pixel, never, repeat)?;
    for (name, t, r) in [("everywhere", t_all, &r_all), ("screened", t_scr, &r_scr), ("off", t_off, &r_off)] {
        println!(
            "ridges {name:>10}: {t:.3} s ({:.2}x everywhere); tried at {} cells, apex at {} of {} cells",
            t / t_all,
            r.ridge_tried_cells,
            r.ridge_cells,
            cells(r)
        );
    }
    println!(
        "planes      never: {t_never:.3} s; the default (where flat) {t_scr:.3} s, {:.2}x; the plane at {} of {} cells",
        t_scr / t_never,
        r_scr.flat_cells,
        cells(&r_never)
    );
    let (mut worst, mut moved, mut lower) = (0.0f64, 0usize, 0usize);
    for (a, b) in scr.data().iter().zip(all.data()) {
        let d = f64::from(*a) - f64::from(*b);
        if d.is_finite() {
            worst = worst.max(d.abs());
            moved += usize::from(d.abs() > 0.001);
            lower += usize::from(d < -0.001);
        }
    }
    println!(
        "screened against everywhere: largest change {worst:.4} mm; {moved} cells moved by more than 0.001 mm, {lower} of them lower (noise {:.4} mm)",
        r_scr.noise_mm
    );
    if cloud.is_none() {
        // Against the part itself, off the steps between its four regions and the map's border.
        for (name, map) in [("ridges everywhere", &all), ("the default", &scr), ("planes never", &quad)] {
            let (mut sum, mut sq, mut deepest, mut n) = (0.0, 0.0, f64::INFINITY, 0usize);
            let m = *map.meta();
            for r in 0..m.height {
                for c in 0..m.width {
                    let (x, y) = m.cell_center(c, r);
                    let off_steps = (x - 20.0).abs() > 0.5 && (y - 20.0).abs() > 0.5;
                    let inside = x > 1.0 && y > 1.0 && x < 39.0 && y < 39.0;
                    let Some(z) = map.get(c, r).filter(|z| z.is_finite() && off_steps && inside) else {
                        continue;
                    };
                    let e = f64::from(z) - part(x, y);
                    sum += e;
                    sq += e * e;
                    deepest = deepest.min(e);
                    n += 1;
                }
            }
            let n = n.max(1) as f64;
            println!(
                "{name:>17} against the part: mean {:+.4} mm, RMS {:.4} mm, deepest {deepest:+.4} mm",
                sum / n,
                (sq / n).sqrt()
            );
        }
    }
    Ok(())
}
