//! Material-removal throughput (`cargo bench --bench removal`; a plain `main`, harness = false).
//!
//! (a) A 1M-move finishing program over a 60 × 50 mm stock on 0.05 mm cells (1200 × 1000 cells):
//!     one roughing-like level raster with a flat-6 at Z −0.6, then ball-3 zig-zag rasters of short
//!     G1 moves (0.1–1 mm, uniformly random) following a wavy surface, stepover 0.3 mm, passes
//!     alternating along X and Y with shifted line positions until the program has 1M moves: the
//!     first pass removes the roughing cusps, the rest re-cut already finished material.
//!     Run with [`Stock::cut_path`] (parallel strips).
//! (b) The same moves 500 000..510 000 per spindle revolution (0.05 mm/rev), pieces per second.
//! (c) 100k moves, sequential [`Stock::cut_line`] against [`Stock::cut_line_baseline`] (every cell
//!     of the bounding box, no early-out) and against `cut_path`, from the same stock, with the
//!     results checked equal: once right after roughing (heavy first pass) and once from the
//!     middle of the program (re-cutting).

use std::time::Instant;

use depthmill_geometry::ToolProfile;
use depthmill_machine::domain::removal::{Cut, Stock, cut_line_per_rev};
use nalgebra::Point3;

const MOVES: usize = 1_000_000;
const CELL_MM: f64 = 0.05;
const STEPOVER_MM: f64 = 0.3;
const TARGET_S: f64 = 60.0;

/// xorshift64*: a deterministic generator without extra dependencies.
struct Rng(u64);

impl Rng {
    fn unit(&mut self) -> f64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        (self.0.wrapping_mul(0x2545_f491_4f6c_dd1d) >> 11) as f64 / (1u64 << 53) as f64
    }
}

fn surface(x: f64, y: f64) -> f64 {
    use std::f64::consts::TAU;
    -2.5 + 1.2 * (TAU * x / 23.0).sin() * (TAU * y / 17.0).cos() + 0.4 * (TAU * (x + y) / 9.0).sin()
}

/// Zig-zag finishing rasters until `moves` moves (`moves + 1` points).
fn finishing_program(moves: usize) -> Vec<Point3<f64>> {
    let mut rng = Rng(0x9e37_79b9_7f4a_7c15);
    let (w, h) = (60.0, 50.0);
    let mut pts = Vec::with_capacity(moves + 1);
    let mut pass = 0usize;
    'passes: loop {
        let along_x = pass.is_multiple_of(2);
        let (len, across) = if along_x { (w, h) } else { (h, w) };
        let phase = (pass as f64 * STEPOVER_MM * 0.618).rem_euclid(STEPOVER_MM);
        let mut forward = true;
        let mut c = phase;
        while c <= across {
            let mut a = if forward { 0.0 } else { len };
            loop {
                let (x, y) = if along_x { (a, c) } else { (c, a) };
                pts.push(Point3::new(x, y, surface(x, y)));
                if pts.len() > moves {
                    break 'passes;
                }
                let step = 0.1 + 0.9 * rng.unit();
                let done = if forward { a >= len } else { a <= 0.0 };
                if done {
                    break;
                }
                a = if forward { (a + step).min(len) } else { (a - step).max(0.0) };
            }
            forward = !forward;
            c += STEPOVER_MM;
        }
        pass += 1;
    }
    pts
}

fn roughed_stock(flat: &ToolProfile) -> Stock {
    let mut stock = Stock::block(Point3::new(0.0, 0.0, -20.0), 60.0, 50.0, 20.0, CELL_MM).expect("stock");
    let mut path = Vec::new();
    let mut y = 0.0;
    let mut forward = true;
    while y <= 53.0 {
        let (x0, x1) = if forward { (-4.0, 64.0) } else { (64.0, -4.0) };
        path.push(Point3::new(x0, y, -0.6));
        path.push(Point3::new(x1, y, -0.6));
        forward = !forward;
        y += 5.0;
    }
    stock.cut_path(flat, &path).expect("roughing");
    stock
}

fn totals(cuts: &[Cut]) -> (u64, u64, f64) {
    cuts.iter().fold((0, 0, 0.0), |(v, u, m), c| (v + c.cells_visited, u + c.cells_updated, m + c.volume_mm3))
}

fn secs(t: Instant) -> f64 {
    t.elapsed().as_secs_f64()
}

/// CPU time of this process (all threads, user + system) from `/proc/self/stat`, in seconds;
/// 0 where unavailable. On a shared machine wall time depends on the load, CPU time much less.
fn cpu_secs() -> f64 {
    let Ok(stat) = std::fs::read_to_string("/proc/self/stat") else { return 0.0 };
    // Fields after the command name (which is in parentheses and may contain spaces).
    let Some(rest) = stat.rsplit_once(')').map(|(_, r)| r) else { return 0.0 };
    let f: Vec<&str> = rest.split_whitespace().collect();
    // Index 0 is field 3 (state); utime and stime are fields 14 and 15.
    let num = |i: usize| f.get(i).and_then(|x| x.parse::<f64>().ok());
    match (num(11), num(12)) {
        (Some(u), Some(s)) => (u + s) / 100.0, // USER_HZ is 100 on Linux
        _ => 0.0,
    }
}

/// CPU seconds of each thread of this process by thread id (from `/proc/self/task/*/stat`).
fn thread_cpu_secs() -> Vec<(String, f64)> {
    let Ok(dir) = std::fs::read_dir("/proc/self/task") else { return Vec::new() };
    dir.filter_map(|e| {
        let path = e.ok()?.path();
        let stat = std::fs::read_to_string(path.join("stat")).ok()?;
        let f: Vec<&str> = stat.rsplit_once(')')?.1.split_whitespace().collect();
        let secs = (f.get(11)?.parse::<f64>().ok()? + f.get(12)?.parse::<f64>().ok()?) / 100.0;
        Some((path.file_name()?.to_string_lossy().into_owned(), secs))
    })
    .collect()
}

/// Runs `f`, returning its result with the wall and CPU seconds it took.
fn timed<T>(f: impl FnOnce() -> T) -> (T, f64, f64) {
    let (t, c) = (Instant::now(), cpu_secs());
    let out = f();
    (out, secs(t), cpu_secs() - c)
}

/// (c): sequential, baseline and parallel-strip runs of the same moves from the same stock.
fn compare(label: &str, start: &Stock, ball: &ToolProfile, path: &[Point3<f64>]) {
    let moves = (path.len() - 1) as f64;
    let mut seq = start.clone();
    let ((visited, updated), t_seq, c_seq) = timed(|| {
        let (mut v, mut u) = (0u64, 0u64);
        for w in path.windows(2) {
            let c = seq.cut_line(ball, w[0], w[1]).expect("cut");
            (v, u) = (v + c.cells_visited, u + c.cells_updated);
        }
        (v as f64, u as f64)
    });
    let mut base = start.clone();
    let (base_visited, t_base, c_base) = timed(|| {
        let mut v = 0u64;
        for w in path.windows(2) {
            v += base.cut_line_baseline(ball, w[0], w[1]).expect("cut").cells_visited;
        }
        v as f64
    });
    let mut par = start.clone();
    let (_, t_par, c_par) = timed(|| par.cut_path(ball, path).expect("path"));
    let same = seq.height_map().data() == base.height_map().data()
        && seq.height_map().data() == par.height_map().data();
    println!("(c) {label}: {moves} moves, results identical: {same}");
    println!("    run                          wall s   CPU s   moves/s (wall)  M cells visited/CPU s");
    println!(
        "    baseline (box, no early-out) {t_base:7.3} {c_base:7.2} {:>12.0}      {:6.1}  ({:.2}x the cells)",
        moves / t_base,
        base_visited / c_base.max(1e-9) / 1e6,
        base_visited / visited.max(1.0)
    );
    println!(
        "    cut_line (1 thread)          {t_seq:7.3} {c_seq:7.2} {:>12.0}      {:6.1}  ({:.3} M cells updated/CPU s)",
        moves / t_seq,
        visited / c_seq.max(1e-9) / 1e6,
        updated / c_seq.max(1e-9) / 1e6
    );
    println!("    cut_path (parallel strips)   {t_par:7.3} {c_par:7.2} {:>12.0}", moves / t_par);
    println!(
        "    ratios vs baseline: cut_line {:.2}x faster (CPU {:.2}x), cut_path {:.2}x faster (wall); cut_path/cut_line {:.2}x",
        t_base / t_seq,
        c_base / c_seq.max(1e-9),
        t_base / t_par,
        t_seq / t_par
    );
    assert!(same, "the three runs must agree");
}

fn main() {
    let threads = rayon::current_num_threads();
    let cores = std::thread::available_parallelism().map_or(1, usize::from);
    println!(
        "material removal benchmark: 60 x 50 mm stock, {CELL_MM} mm cells, {threads} rayon threads, {cores} cores"
    );
    if let Ok(load) = std::fs::read_to_string("/proc/loadavg") {
        println!("load average at start: {}", load.trim());
    }
    let flat: ToolProfile = "flat-6".parse().expect("flat");
    let ball: ToolProfile = "ball-3".parse().expect("ball");

    let (path, t_gen, _) = timed(|| finishing_program(MOVES));
    let path_len: f64 = path.windows(2).map(|w| (w[1] - w[0]).norm()).sum();
    println!(
        "program: {} moves, {:.1} m of path, mean move {:.3} mm (generated in {t_gen:.2} s)",
        path.len() - 1,
        path_len / 1000.0,
        path_len / (path.len() - 1) as f64,
    );
    let (roughed, t_rough, _) = timed(|| roughed_stock(&flat));
    println!("roughing (flat-6 level raster at Z -0.6): {t_rough:.3} s");

    // (a) The whole program, in two halves so the middle state is kept for (b) and (c).
    let mid = MOVES / 2;
    let threads_before = thread_cpu_secs();
    let mut stock = roughed.clone();
    let before = stock.volume_mm3();
    let (first, t1, c1) = timed(|| stock.cut_path(&ball, &path[..=mid]).expect("first half"));
    let middle = stock.clone();
    let (second, t2, c2) = timed(|| stock.cut_path(&ball, &path[mid..]).expect("second half"));
    let (total, cpu) = (t1 + t2, c1 + c2);
    let (v1, u1, m1) = totals(&first);
    let (v2, u2, m2) = totals(&second);
    let (visited, updated, removed) = ((v1 + v2) as f64, (u1 + u2) as f64, m1 + m2);
    let after = stock.volume_mm3();
    // Wall time if the process had the cores to itself: CPU time over the threads it kept busy
    // (bounded by the measured wall time, which includes waiting for other processes).
    let alone = (cpu / threads as f64).min(total);
    println!("(a) 1M-move finishing program (ball-3, cut_path, {threads} threads):");
    println!(
        "    wall {total:.2} s ({t1:.2} s for the first half, with the heavy first pass), CPU {cpu:.2} s \
         (CPU / threads = {:.2} s)",
        cpu / threads as f64
    );
    println!(
        "    {:.0} moves/s; cells visited {visited:.0} ({:.0} per move): {:.1} M/s wall, {:.1} M per CPU s",
        MOVES as f64 / total,
        visited / MOVES as f64,
        visited / total / 1e6,
        visited / cpu.max(1e-9) / 1e6
    );
    println!(
        "    cells updated {updated:.0}: {:.2} M/s wall, {:.2} M per CPU s",
        updated / total / 1e6,
        updated / cpu.max(1e-9) / 1e6
    );
    // How the work was shared: per-thread CPU time spent in (a) (threads that did any work).
    let threads_after = thread_cpu_secs();
    let mut split: Vec<f64> = threads_after
        .iter()
        .map(|(tid, t)| t - threads_before.iter().find(|(b, _)| b == tid).map_or(0.0, |(_, b)| *b))
        .filter(|t| *t > 0.05)
        .collect();
    split.sort_by(|a, b| b.total_cmp(a));
    let split: Vec<String> = split.iter().map(|t| format!("{t:.2}")).collect();
    println!("    CPU s per thread (all threads of the process, sorted): [{}]", split.join(", "));
    println!(
        "    removed {removed:.3} mm3; volume before - after = {:.3} mm3 (difference {:.2e})",
        before - after,
        (before - after - removed).abs()
    );
    println!(
        "    target 1M moves < {TARGET_S} s on {threads} cores: wall {total:.1} s {}, \
         unloaded estimate {alone:.1} s {}",
        if total < TARGET_S { "MET" } else { "NOT MET" },
        if alone < TARGET_S { "MET" } else { "NOT MET" },
    );

    // (b) Per revolution on a 10k-move subset.
    let sub = &path[mid..=mid + 10_000];
    let mut whole = middle.clone();
    let (whole_volume, t_whole, c_whole) = timed(|| {
        sub.windows(2).map(|w| whole.cut_line(&ball, w[0], w[1]).expect("cut").volume_mm3).sum::<f64>()
    });
    let mut revs = middle.clone();
    let ((pieces, rev_volume), t_rev, c_rev) = timed(|| {
        let (mut n, mut v) = (0u64, 0.0);
        for w in sub.windows(2) {
            cut_line_per_rev(&mut revs, &ball, w[0], w[1], 0.05, |c| (n, v) = (n + 1, v + c.volume_mm3))
                .expect("per rev");
        }
        (n as f64, v)
    });
    println!("(b) per revolution, 10k moves at 0.05 mm/rev (1 thread):");
    println!(
        "    {pieces} revolutions: wall {t_rev:.3} s, CPU {c_rev:.2} s: {:.0} revolutions/s wall, {:.0} per CPU s \
         ({:.1} us each); whole moves: wall {t_whole:.3} s, CPU {c_whole:.2} s",
        pieces / t_rev,
        pieces / c_rev.max(1e-9),
        c_rev.max(1e-9) / pieces * 1e6
    );
    println!(
        "    removed {rev_volume:.4} mm3 per revolution vs {whole_volume:.4} mm3 whole (rel. diff {:.1e})",
        (rev_volume - whole_volume).abs() / whole_volume.max(1e-12)
    );

    // (c) Reference runs.
    compare("right after roughing (moves 0..100k)", &roughed, &ball, &path[..=100_000]);
    compare("mid-program re-cutting (moves 500k..600k)", &middle, &ball, &path[mid..=mid + 100_000]);
}
