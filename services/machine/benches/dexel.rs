//! Dexel-stock throughput against seed 004's figure (`cargo bench -p depthmill-machine --bench
//! dexel`; a plain `main`, harness = false).
//!
//! The seed cut a 30 x 30 x 320 mm stock at 5 µm at 19 moves (frames) per second on one 3 GHz
//! core in 2012. Here the same stock and resolution: one dexel grid with its rays along the
//! 320 mm length (as the seed's map, whose length does not change the time), 6000 x 6000 rays.
//! The program finishes the 30 x 30 end face with a ball-2 at 0.1 mm depth in zig-zag rows
//! 0.2 mm apart, moves of 0.05 mm (a fine-finishing program's segment length at this
//! resolution), in two variants:
//!
//! - (a) the tool along the rays (3-axis), with the Z-map of the same grid (6000 x 6000 cells)
//!   cutting the same moves as the baseline measured in the same run;
//! - (b) the tool tilted 20° from the rays in the direction of the rows (5-axis lead angle).
//!
//! Each is run on one rayon thread and on every thread; the figures are moves per second, the
//! ratio to the seed's 19, and the memory the rays take. `DEXEL_MOVES` sets the moves per run
//! (default 400); `DEXEL_CASE=a` (or `b`) runs one case only and `DEXEL_THREADS=N` one thread
//! count only, for a profiler.

use std::time::Instant;

use depthmill_geometry::ToolProfile;
use depthmill_machine::domain::dexel::{Blank, DexelCells, DexelStock, OrientedBox, ToolSolid};
use depthmill_machine::domain::removal::Stock;
use nalgebra::{Point3, Unit, Vector3};

const SIDE_MM: f64 = 30.0;
const LENGTH_MM: f64 = 320.0;
const CELL_MM: f64 = 0.005;
const SEED_MOVES_S: f64 = 19.0;
const MOVE_MM: f64 = 0.05;
const ROW_MM: f64 = 0.2;

fn program(moves: usize) -> Vec<Point3<f64>> {
    let z = LENGTH_MM - 0.1;
    let (x0, x1) = (3.0, SIDE_MM - 3.0);
    let mut pts = vec![Point3::new(x0, 3.0, z)];
    let (mut x, mut y, mut dir) = (x0, 3.0, 1.0);
    while pts.len() <= moves {
        x += dir * MOVE_MM;
        if x > x1 || x < x0 {
            x = x.clamp(x0, x1);
            y += ROW_MM;
            dir = -dir;
        }
        pts.push(Point3::new(x, y, z));
    }
    pts
}

fn peak_rss_mib() -> f64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmHWM:"))
                .and_then(|l| l.split_whitespace().nth(1)?.parse::<f64>().ok())
        })
        .map_or(f64::NAN, |kib| kib / 1024.0)
}

fn run_dexel(
    stock: &mut DexelStock,
    tool: &ToolSolid,
    pts: &[Point3<f64>],
    axis: &Unit<Vector3<f64>>,
) -> (f64, f64) {
    let t = Instant::now();
    let mut vol = 0.0;
    for w in pts.windows(2) {
        vol += stock.cut_line(tool, &w[0], &w[1], axis).expect("cut").volume_mm3;
    }
    (t.elapsed().as_secs_f64(), vol)
}

fn main() {
    let moves: usize = std::env::var("DEXEL_MOVES").ok().and_then(|v| v.parse().ok()).unwrap_or(400);
    let cores = std::thread::available_parallelism().map_or(1, usize::from);
    println!(
        "dexel benchmark: {SIDE_MM} x {SIDE_MM} x {LENGTH_MM} mm stock at {} µm, {moves} moves of {MOVE_MM} mm, ball-2, {cores} cores",
        CELL_MM * 1000.0
    );
    if let Ok(load) = std::fs::read_to_string("/proc/loadavg") {
        println!("load average at start: {}", load.trim());
    }
    let blank = Blank {
        boxes: vec![OrientedBox::aligned(Point3::origin(), Point3::new(SIDE_MM, SIDE_MM, LENGTH_MM))],
    };
    let cells = DexelCells { x_mm: None, y_mm: None, z_mm: Some(CELL_MM) };
    let profile = ToolProfile::ball(2.0).expect("ball");
    let tool = ToolSolid::new(&profile, 30.0).expect("tool");
    let pts = program(moves);
    let vertical = Vector3::z_axis();
    let tilted =
        Unit::new_normalize(Vector3::new((20f64).to_radians().sin(), 0.0, (20f64).to_radians().cos()));

    let t = Instant::now();
    let fresh = DexelStock::new(&blank, &cells).expect("stock");
    println!(
        "stock: {} rays, {:.0} MiB of rays ({} bytes each, one interval inline), built in {:.2} s",
        fresh.grids().iter().map(|g| g.2[0] * g.2[1]).sum::<usize>(),
        fresh.bytes() as f64 / (1 << 20) as f64,
        depthmill_machine::domain::dexel::RAY_BYTES,
        t.elapsed().as_secs_f64()
    );

    let pool1 = rayon::ThreadPoolBuilder::new().num_threads(1).build().expect("pool");
    let mut rows = Vec::new();
    // `DEXEL_CASE=a` or `b` runs one case only (for a profiler); `DEXEL_THREADS=1` one thread only.
    let case = std::env::var("DEXEL_CASE").unwrap_or_default();
    let thread_counts: Vec<usize> = match std::env::var("DEXEL_THREADS").ok().and_then(|v| v.parse().ok()) {
        Some(n) => vec![n],
        None => vec![1, cores],
    };
    for (name, axis) in [("(a) 3-axis, tool along the rays", &vertical), ("(b) tool tilted 20°", &tilted)] {
        if !case.is_empty() && !name.starts_with(&format!("({case})")) {
            continue;
        }
        for &threads in &thread_counts {
            let mut stock = fresh.clone();
            let (secs, vol) = if threads == 1 {
                pool1.install(|| run_dexel(&mut stock, &tool, &pts, axis))
            } else {
                run_dexel(&mut stock, &tool, &pts, axis)
            };
            let rate = moves as f64 / secs;
            println!(
                "{name}, {threads} thread(s): {rate:.1} moves/s ({:.2}x the seed's {SEED_MOVES_S}), {vol:.3} mm³ removed, {:.0} MiB of rays after",
                rate / SEED_MOVES_S,
                stock.bytes() as f64 / (1 << 20) as f64
            );
            rows.push((name, threads, rate));
        }
    }
    drop(fresh);

    // The Z-map baseline on the same grid and moves (3-axis only).
    let zmap = Stock::block(Point3::origin(), SIDE_MM, SIDE_MM, LENGTH_MM, CELL_MM).expect("zmap");
    for &threads in &thread_counts {
        if case == "b" {
            break;
        }
        let mut z = zmap.clone();
        let t = Instant::now();
        let mut run = || {
            let mut vol = 0.0;
            for w in pts.windows(2) {
                vol += z.cut_line(&profile, w[0], w[1]).expect("cut").volume_mm3;
            }
            vol
        };
        let vol = if threads == 1 { pool1.install(run) } else { run() };
        let rate = moves as f64 / t.elapsed().as_secs_f64();
        let dexel = rows.iter().find(|r| r.1 == threads).map_or(f64::NAN, |r| r.2);
        println!(
            "Z-map baseline (a), {threads} thread(s): {rate:.1} moves/s, {vol:.3} mm³ removed; dexel (a) / Z-map = {:.2}",
            dexel / rate
        );
    }
    println!("peak resident memory: {:.0} MiB", peak_rss_mib());
}
