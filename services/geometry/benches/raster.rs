//! Rasterisation benchmark: 10^7 points into 2000 x 2000 px of 0.1 mm, hole filling and coverage,
//! against CloudCompare's `Rasterize` measured in the same run.
//!
//! The cloud imitates a line scanner: a 196 x 196 mm part with rounded corners (a wavy surface
//! plus 10 µm noise) swept in four 60 mm swaths; along a scan line the points are 0.133 mm apart
//! (450 points over 60 mm), wider than the 0.1 mm pixel, so about one column in four stays empty
//! (stripes that more scan lines do not fill); a few scan lines are dropped (empty rows), there
//! are holes of 0.8, 3 and 6 mm and 50 stray points 40 mm above the part.
//!
//! Run: `cargo bench --bench raster` (or `cargo run --release --bench raster`). The CloudCompare
//! part runs when `CloudCompare` is on the PATH (Debian: `apt-get install cloudcompare`; it runs
//! headless with `QT_QPA_PLATFORM=offscreen`, no X server needed). CloudCompare's rasterisation
//! time is the wall time of `-O cloud.ply -RASTERIZE -GRID_STEP 0.1 -PROJ MAX` minus that of a
//! load-only run `-O cloud.ply` (both with `-AUTO_SAVE OFF`, best of 3 each; its log has no
//! per-step timings). Set `RASTER_BENCH_POINTS` to change the point count (default 10^7) and
//! `RASTER_BENCH_NO_CC` to skip CloudCompare.

use std::io::{BufRead, BufReader, BufWriter, Read, Write};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use depthmill_geometry::raster::{
    FillMethod, FillParams, Roi, auto_z_range, coverage, fill_holes, grid_for_roi, rasterize_max,
};
use depthmill_geometry::{HeightMap, HeightMapMeta};
use nalgebra::Point3;
use rand::rngs::StdRng;
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use rayon::prelude::*;

const PIXEL_MM: f64 = 0.1;
const SPACING_MM: f64 = 60.0 / 450.0;
const SWATH_MM: f64 = 60.0;

type BenchResult<T> = Result<T, Box<dyn std::error::Error>>;

fn height(x: f64, y: f64) -> f64 {
    8.0 + 2.0 * (x / 15.0).sin() * (y / 20.0).cos() + 0.5 * (x / 3.0 + y / 7.0).sin()
}

fn in_part(x: f64, y: f64) -> bool {
    // 196 x 196 mm square at (2, 2) with 20 mm corner radius.
    let (cx, cy) = (x.clamp(22.0, 178.0), y.clamp(22.0, 178.0));
    (2.0..198.0).contains(&x) && (2.0..198.0).contains(&y) && (x - cx).powi(2) + (y - cy).powi(2) <= 400.0
}

fn in_hole(x: f64, y: f64) -> bool {
    [(50.0, 60.0, 0.4), (120.0, 140.0, 1.5), (150.0, 50.0, 3.0)]
        .iter()
        .any(|&(hx, hy, r)| (x - hx).powi(2) + (y - hy).powi(2) < r * r)
}

/// About `target` points in scan order (line by line, swath by swath), then thinned evenly to
/// exactly `target`.
fn scan_cloud(target: usize) -> Vec<Point3<f64>> {
    // Point density 1/(spacing·dy) over the part's ~38 000 mm², 3 % spare.
    let area = 196.0 * 196.0 - (4.0 - std::f64::consts::PI) * 400.0;
    let dy = area / (SPACING_MM * target as f64 * 1.03);
    let lines = (196.0 / dy).ceil() as usize;
    let swaths = (200.0 / SWATH_MM).ceil() as usize;
    let cloud: Vec<Point3<f64>> = (0..swaths * lines)
        .into_par_iter()
        .flat_map_iter(|k| {
            let (s, l) = (k / lines, k % lines);
            let mut rng = StdRng::seed_from_u64(k as u64);
            let y = 2.0 + l as f64 * dy;
            // Dropped scan lines: two 0.3 mm bands.
            let dropped = (70.0..70.3).contains(&y) || (130.0..130.3).contains(&y);
            let x0 = s as f64 * SWATH_MM + 0.037 * s as f64;
            let n = if dropped { 0 } else { 450 };
            let mut out = Vec::with_capacity(n);
            for i in 0..n {
                let x = x0 + i as f64 * SPACING_MM + rng.random_range(-0.003..0.003);
                let yy = y + rng.random_range(-0.003..0.003);
                if !in_part(x, yy) || in_hole(x, yy) {
                    continue;
                }
                let noise: f64 = (0..3).map(|_| rng.random_range(-0.01..0.01)).sum();
                out.push(Point3::new(x, yy, height(x, yy) + noise));
            }
            out
        })
        .collect();
    let n = cloud.len();
    let mut thinned: Vec<Point3<f64>> = cloud
        .into_iter()
        .enumerate()
        .filter(|(i, _)| (i + 1) * target / n > i * target / n)
        .map(|(_, p)| p)
        .collect();
    // Stray points 40 mm above the part.
    let mut rng = StdRng::seed_from_u64(99);
    for k in 0..50.min(thinned.len()) {
        let i = rng.random_range(0..thinned.len());
        thinned[i].z += 40.0 + k as f64 * 0.1;
    }
    thinned
}

fn best_of<T>(runs: usize, mut f: impl FnMut() -> T) -> (Duration, T) {
    let mut best = Duration::MAX;
    let mut out = None;
    for _ in 0..runs {
        let t = Instant::now();
        let v = f();
        best = best.min(t.elapsed());
        out = Some(v);
    }
    match out {
        Some(v) => (best, v),
        None => (best, f()),
    }
}

fn ms(d: Duration) -> f64 {
    d.as_secs_f64() * 1e3
}

fn write_ply(path: &Path, points: &[Point3<f64>]) -> BenchResult<()> {
    let mut w = BufWriter::with_capacity(1 << 20, std::fs::File::create(path)?);
    write!(
        w,
        "ply\nformat binary_little_endian 1.0\nelement vertex {}\nproperty float x\nproperty float y\nproperty float z\nend_header\n",
        points.len()
    )?;
    for p in points {
        for v in [p.x, p.y, p.z] {
            w.write_all(&(v as f32).to_le_bytes())?;
        }
    }
    w.flush()?;
    Ok(())
}

/// Vertices (x, y, z) of a binary little-endian PLY whose vertex properties are float or double.
fn read_ply_xyz(path: &Path) -> BenchResult<Vec<[f32; 3]>> {
    let mut r = BufReader::new(std::fs::File::open(path)?);
    let (mut count, mut props, mut in_vertex) = (0usize, Vec::new(), false);
    loop {
        let mut line = String::new();
        if r.read_line(&mut line)? == 0 {
            return Err("ply header ends early".into());
        }
        let t: Vec<&str> = line.split_whitespace().collect();
        match t.as_slice() {
            ["format", f, _] if *f != "binary_little_endian" => return Err(format!("ply format {f}").into()),
            ["element", "vertex", n] => {
                count = n.parse()?;
                in_vertex = true;
            }
            ["element", ..] => in_vertex = false,
            ["property", ty, name] if in_vertex => {
                let size = match *ty {
                    "float" | "float32" => 4,
                    "double" | "float64" => 8,
                    other => return Err(format!("ply property type {other}").into()),
                };
                props.push((name.to_string(), size));
            }
            ["end_header"] => break,
            _ => {}
        }
    }
    let stride: usize = props.iter().map(|p| p.1).sum();
    let offset = |n: &str| -> BenchResult<(usize, usize)> {
        let i = props.iter().position(|p| p.0 == n).ok_or(format!("ply has no {n}"))?;
        Ok((props[..i].iter().map(|p| p.1).sum(), props[i].1))
    };
    let fields = [offset("x")?, offset("y")?, offset("z")?];
    let mut buf = vec![0u8; stride * count];
    r.read_exact(&mut buf)?;
    let get = |rec: &[u8], (o, s): (usize, usize)| -> f32 {
        if s == 4 {
            f32::from_le_bytes([rec[o], rec[o + 1], rec[o + 2], rec[o + 3]])
        } else {
            let mut b = [0u8; 8];
            b.copy_from_slice(&rec[o..o + 8]);
            f64::from_le_bytes(b) as f32
        }
    };
    Ok(buf
        .chunks_exact(stride)
        .map(|rec| [get(rec, fields[0]), get(rec, fields[1]), get(rec, fields[2])])
        .collect())
}

fn find_cloudcompare() -> Option<PathBuf> {
    let path = std::env::var_os("PATH")?;
    std::env::split_paths(&path).map(|d| d.join("CloudCompare")).find(|p| p.is_file())
}

/// Runs CloudCompare headless; returns the wall time and its output.
fn run_cc(cc: &Path, dir: &Path, args: &[&str]) -> BenchResult<(Duration, String)> {
    let t = Instant::now();
    let out = Command::new(cc)
        .current_dir(dir)
        .env("QT_QPA_PLATFORM", "offscreen")
        .args(["-SILENT", "-AUTO_SAVE", "OFF", "-NO_TIMESTAMP"])
        .args(args)
        .output()?;
    let elapsed = t.elapsed();
    let text = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    if !out.status.success() {
        return Err(format!("CloudCompare failed ({}): {text}", out.status).into());
    }
    Ok((elapsed, text))
}

fn cc_best(cc: &Path, dir: &Path, args: &[&str], runs: usize) -> BenchResult<(Duration, String)> {
    let mut best: Option<(Duration, String)> = None;
    for _ in 0..runs {
        let (t, text) = run_cc(cc, dir, args)?;
        if best.as_ref().is_none_or(|b| t < b.0) {
            best = Some((t, text));
        }
    }
    best.ok_or_else(|| "no run".into())
}

fn grid_line(log: &str) -> String {
    log.lines().find(|l| l.starts_with("Grid size")).unwrap_or("grid size not logged").to_string()
}

/// Compares CloudCompare's raster cloud (one point per non-empty cell at its centre, z = max) with
/// `rasterize_max` on the grid shifted to CloudCompare's convention (bounding-box minimum = centre
/// of cell 0), on a smaller cloud of f32-exact coordinates.
fn check_against_cc(cc: &Path, dir: &Path, cloud: &[Point3<f64>]) -> BenchResult<()> {
    // A 30 x 30 mm window, coordinates rounded to f32 as in the PLY.
    let small: Vec<Point3<f64>> = cloud
        .iter()
        .filter(|p| (85.0..115.0).contains(&p.x) && (135.0..165.0).contains(&p.y))
        .map(|p| Point3::new(f64::from(p.x as f32), f64::from(p.y as f32), f64::from(p.z as f32)))
        .collect();
    let ply = dir.join("small.ply");
    write_ply(&ply, &small)?;
    let out = dir.join("small_raster.ply");
    let out_s = out.to_string_lossy().to_string();
    let (_, log) = run_cc(
        cc,
        dir,
        &[
            "-C_EXPORT_FMT",
            "PLY",
            "-O",
            "small.ply",
            "-RASTERIZE",
            "-GRID_STEP",
            "0.1",
            "-PROJ",
            "MAX",
            "-OUTPUT_CLOUD",
            "-SAVE_CLOUDS",
            "FILE",
            &out_s,
        ],
    )?;
    let cc_cells = read_ply_xyz(&out)?;
    let (mut x_min, mut y_min, mut x_max, mut y_max) = (f64::MAX, f64::MAX, f64::MIN, f64::MIN);
    for p in &small {
        (x_min, y_min, x_max, y_max) = (x_min.min(p.x), y_min.min(p.y), x_max.max(p.x), y_max.max(p.y));
    }
    // CloudCompare's convention: cell i is centred on x_min + i·p, i.e. our corner at x_min − p/2.
    let w = ((x_max - x_min) / PIXEL_MM + 0.5).floor() as u32 + 2;
    let h = ((y_max - y_min) / PIXEL_MM + 0.5).floor() as u32 + 2;
    let mut grid = HeightMapMeta::new(w, h, PIXEL_MM);
    grid.origin_x_mm = x_min - PIXEL_MM / 2.0;
    grid.origin_y_mm = y_min - PIXEL_MM / 2.0;
    let (ours, stats) = rasterize_max(&small, &grid);
    let mut seen = vec![false; ours.data().len()];
    let (mut equal, mut differ, mut cc_only) = (0usize, 0usize, 0usize);
    for &[x, y, z] in &cc_cells {
        let i = ((f64::from(x) - x_min) / PIXEL_MM).round();
        let j = ((f64::from(y) - y_min) / PIXEL_MM).round();
        match ours.index(i as u32, j as u32).filter(|_| i >= 0.0 && j >= 0.0) {
            Some(k) if ours.data()[k].is_finite() => {
                seen[k] = true;
                if ours.data()[k] == z { equal += 1 } else { differ += 1 }
            }
            _ => cc_only += 1,
        }
    }
    let ours_only = ours.data().iter().zip(&seen).filter(|(z, s)| z.is_finite() && !**s).count();
    let union = equal + differ + cc_only + ours_only;
    println!(
        "  check vs CloudCompare ({} points in a 30 x 30 mm window, {}; ours {}x{}, {} binned):",
        small.len(),
        grid_line(&log),
        w,
        h,
        stats.points_binned
    );
    println!(
        "    {} CC cells; equal max Z in {equal} cells, different Z in {differ}, only CC {cc_only}, only ours {ours_only} -> agreement {:.4} %",
        cc_cells.len(),
        100.0 * equal as f64 / union.max(1) as f64
    );
    Ok(())
}

/// The first three fields of /proc/loadavg (other work on the machine skews every figure).
fn load_average() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .map(|s| s.split_whitespace().take(3).collect::<Vec<_>>().join(" "))
        .unwrap_or_else(|_| "unknown".into())
}

/// CloudCompare's rasterisation time on `points` (best of 3 load + rasterize runs minus best of 3
/// load-only runs) and the grid size it logged.
fn cc_raster_time(
    cc: &Path,
    dir: &Path,
    points: &[Point3<f64>],
    name: &str,
) -> BenchResult<(Duration, String)> {
    let t = Instant::now();
    write_ply(&dir.join(name), points)?;
    println!("  {name}: PLY written in {:.0} ms; load average {}", ms(t.elapsed()), load_average());
    let (load, _) = cc_best(cc, dir, &["-O", name], 3)?;
    let (full, log) = cc_best(cc, dir, &["-O", name, "-RASTERIZE", "-GRID_STEP", "0.1", "-PROJ", "MAX"], 3)?;
    let raster = full.saturating_sub(load);
    println!("    load only:           {:>9.1} ms (best of 3, wall time incl. start-up)", ms(load));
    println!("    load + rasterize:    {:>9.1} ms (best of 3; {})", ms(full), grid_line(&log));
    println!(
        "    rasterize (diff):    {:>9.1} ms = {:.1} M points/s",
        ms(raster),
        points.len() as f64 / raster.as_secs_f64() / 1e6
    );
    Ok((raster, grid_line(&log)))
}

fn cloudcompare(
    cloud: &[Point3<f64>],
    shuffled: &[Point3<f64>],
    ours_scan: Duration,
    ours_shuffled: Duration,
) -> BenchResult<()> {
    if std::env::var_os("RASTER_BENCH_NO_CC").is_some() {
        println!("CloudCompare reference skipped (RASTER_BENCH_NO_CC is set)");
        return Ok(());
    }
    let Some(cc) = find_cloudcompare() else {
        println!("CloudCompare not installed: reference skipped.");
        println!(
            "  install it with: apt-get install -y cloudcompare   (runs headless with QT_QPA_PLATFORM=offscreen)"
        );
        return Ok(());
    };
    let dir = tempfile::tempdir()?;
    println!("CloudCompare reference ({}), same clouds, -RASTERIZE -GRID_STEP 0.1 -PROJ MAX:", cc.display());
    let (cc_scan, _) = cc_raster_time(&cc, dir.path(), cloud, "cloud.ply")?;
    println!(
        "    ratio CloudCompare / rasterize_max (scan order): {:.1}x",
        cc_scan.as_secs_f64() / ours_scan.as_secs_f64()
    );
    let (cc_shuf, _) = cc_raster_time(&cc, dir.path(), shuffled, "shuffled.ply")?;
    println!(
        "    ratio CloudCompare / rasterize_max (shuffled):   {:.1}x",
        cc_shuf.as_secs_f64() / ours_shuffled.as_secs_f64()
    );
    std::fs::remove_file(dir.path().join("shuffled.ply"))?;
    check_against_cc(&cc, dir.path(), cloud)
}

fn main() -> BenchResult<()> {
    let target: usize =
        std::env::var("RASTER_BENCH_POINTS").ok().and_then(|v| v.parse().ok()).unwrap_or(10_000_000);
    println!(
        "raster bench: {} rayon threads, {} CPUs, load average {}",
        rayon::current_num_threads(),
        std::thread::available_parallelism().map_or(0, |n| n.get()),
        load_average()
    );
    let t = Instant::now();
    let cloud = scan_cloud(target);
    println!("cloud: {} points generated in {:.0} ms", cloud.len(), ms(t.elapsed()));

    let roi = Roi { x_min_mm: 0.0, y_min_mm: 0.0, x_max_mm: 200.0, y_max_mm: 200.0 };
    let grid = grid_for_roi(&roi, PIXEL_MM)?;
    println!("grid: {} x {} px of {} mm", grid.width, grid.height, grid.pixel_mm);
    let n = cloud.len() as f64;

    let (scan_t, (raw, stats)) = best_of(10, || rasterize_max(&cloud, &grid));
    println!(
        "rasterize_max, scan order: {:>8.1} ms = {:>6.1} M points/s (best of 10; {} binned, {} cells with data)",
        ms(scan_t),
        n / scan_t.as_secs_f64() / 1e6,
        stats.points_binned,
        raw.valid_count()
    );
    let mut shuffled = cloud.clone();
    shuffled.shuffle(&mut StdRng::seed_from_u64(1));
    let (shuf_t, (raw_s, _)) = best_of(10, || rasterize_max(&shuffled, &grid));
    println!(
        "rasterize_max, shuffled:   {:>8.1} ms = {:>6.1} M points/s (best of 10; same map: {})",
        ms(shuf_t),
        n / shuf_t.as_secs_f64() / 1e6,
        raw_s.bitwise_eq(&raw)
    );
    drop(raw_s);
    let (roi_t, around) = best_of(3, || Roi::around(&cloud, 2.0 * PIXEL_MM));
    println!("Roi::around:               {:>8.1} ms ({around:?})", ms(roi_t));

    let (z_t, z_range) = best_of(3, || auto_z_range(raw.data().iter().copied()));
    let data_range = raw.z_range_of_data();
    println!(
        "auto_z_range:              {:>8.1} ms: {z_range:?} (data range with the 50 stray points: {data_range:?})",
        ms(z_t)
    );
    let mut raw = raw;
    if let Some((lo, hi)) = z_range {
        raw.set_z_range(lo, hi)?;
    }

    let (mut idw_t, mut cov_t) = (Duration::ZERO, Duration::ZERO);
    for (name, method) in [("IDW p=2", FillMethod::Idw { power: 2.0 }), ("Max", FillMethod::Max)] {
        let params = FillParams { method, max_hole_mm: 2.0, radius_mm: None };
        let radius = params.radius_for(PIXEL_MM)?;
        let (fill_t, filled) = best_of(3, || fill_holes(&raw, &params));
        let (filled, report) = filled?;
        println!(
            "fill_holes {name:<8} max_hole 2 mm, radius per cell up to {radius:.3} mm: {:>8.1} ms (best of 3; {report:?})",
            ms(fill_t)
        );
        report_fill_error(&raw, &filled);
        if let FillMethod::Idw { .. } = method {
            idw_t = fill_t;
            let (t, (_, cov)) = best_of(3, || coverage(&raw, &filled));
            cov_t = t;
            println!("coverage:                  {:>8.1} ms (best of 3)", ms(cov_t));
            println!(
                "  cells {}, measured {}, filled {}, footprint {}, covered {:.2} %, holes {} (largest {:.2} mm²), still empty {} in {} holes",
                cov.cells,
                cov.measured,
                cov.filled,
                cov.footprint,
                cov.covered_pct,
                cov.holes,
                cov.largest_hole.map_or(0.0, |h| h.area_mm2),
                cov.empty,
                cov.unfilled_holes
            );
            if let Some(h) = cov.largest_unfilled_hole {
                println!(
                    "  largest unfilled hole: {:.2} mm² at ({:.2}, {:.2}) mm, bbox [{:.1}, {:.1}] x [{:.1}, {:.1}] mm",
                    h.area_mm2, h.center_x_mm, h.center_y_mm, h.min_x_mm, h.max_x_mm, h.min_y_mm, h.max_y_mm
                );
            }
        }
    }
    println!(
        "rasterize (scan order) + fill_holes (IDW) + coverage: {:.1} ms",
        ms(scan_t) + ms(idw_t) + ms(cov_t)
    );
    cloudcompare(&cloud, &shuffled, scan_t, shuf_t)
}

/// How far the filled cells are from the true surface (the generator's height at the cell centre).
fn report_fill_error(raw: &HeightMap, filled: &HeightMap) {
    let m = filled.meta();
    let (mut worst, mut sum, mut n) = (0.0f64, 0.0f64, 0usize);
    for r in 0..m.height {
        for c in 0..m.width {
            let (x, y) = m.cell_center(c, r);
            if let (Some(a), Some(z)) = (raw.get(c, r), filled.get(c, r))
                && a.is_nan()
                && z.is_finite()
            {
                let e = (f64::from(z) - height(x, y)).abs();
                worst = worst.max(e);
                sum += e;
                n += 1;
            }
        }
    }
    println!(
        "  |filled - true surface at the cell centre| over the {n} filled cells: mean {:.4} mm, max {worst:.4} mm",
        sum / n.max(1) as f64
    );
}
