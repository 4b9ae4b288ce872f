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
        let along_x = pass % 2 == 0;
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

/// (c): sequential, baseline and parallel-strip runs of the same moves from the same stock.
fn compare(label: &str, start: &Stock, ball: &ToolProfile, path: &[Point3<f64>]) {
    let moves = path.len() - 1;
    let mut seq = start.clone();
    let t = Instant::now();
    let (mut visited, mut updated) = (0u64, 0u64);
    for w in path.windows(2) {
        let c = seq.cut_line(ball, w[0], w[1]).expect("cut");
        visited += c.cells_visited;
        updated += c.cells_updated;
    }
    let t_seq = secs(t);
    let mut base = start.clone();
    let t = Instant::now();
    let mut base_visited = 0u64;
    for w in path.windows(2) {
        base_visited += base.cut_line_baseline(ball, w[0], w[1]).expect("cut").cells_visited;
    }
    let t_base = secs(t);
    let mut par = start.clone();
    let t = Instant::now();
    par.cut_path(ball, path).expect("path");
    let t_par = secs(t);
    let same = seq.height_map().data() == base.height_map().data()
        && seq.height_map().data() == par.height_map().data();
    println!("(c) {label}: {moves} moves, results identical: {same}");
    println!(
        "    cut_line (1 thread)        {t_seq:7.3} s  {:>9.0} moves/s  {:>6.1} M visited/s  {:>6.2} M updated/s",
        moves as f64 / t_seq,
        visited as f64 / t_seq / 1e6,
        updated as f64 / t_seq / 1e6
    );
    println!(
        "    baseline (box, no early-out) {t_base:5.3} s  {:>9.0} moves/s  {:>6.1} M visited/s  ({:.2}x the cells)",
        moves as f64 / t_base,
        base_visited as f64 / t_base / 1e6,
        base_visited as f64 / visited.max(1) as f64
    );
    println!("    cut_path (parallel strips) {t_par:6.3} s  {:>9.0} moves/s", moves as f64 / t_par);
    println!(
        "    speed-up: cut_line / baseline = {:.2}x, cut_path / baseline = {:.2}x, cut_path / cut_line = {:.2}x",
        t_base / t_seq,
        t_base / t_par,
        t_seq / t_par
    );
    assert!(same, "the three runs must agree");
}

fn main() {
    let threads = rayon::current_num_threads();
    println!("material removal benchmark: 60 x 50 mm stock, {CELL_MM} mm cells, {threads} rayon threads");
    let flat: ToolProfile = "flat-6".parse().expect("flat");
    let ball: ToolProfile = "ball-3".parse().expect("ball");

    let t = Instant::now();
    let path = finishing_program(MOVES);
    let path_len: f64 = path.windows(2).map(|w| (w[1] - w[0]).norm()).sum();
    println!(
        "program: {} moves, {:.1} m of path, mean move {:.3} mm (generated in {:.2} s)",
        path.len() - 1,
        path_len / 1000.0,
        path_len / (path.len() - 1) as f64,
        secs(t)
    );

    let t = Instant::now();
    let roughed = roughed_stock(&flat);
    println!("roughing (flat-6 level raster at Z -0.6): {:.3} s", secs(t));

    // (a) The whole program, in two halves so the middle state is kept for (b) and (c).
    let mid = MOVES / 2;
    let mut stock = roughed.clone();
    let before = stock.volume_mm3();
    let t = Instant::now();
    let first = stock.cut_path(&ball, &path[..=mid]).expect("first half");
    let t_first = secs(t);
    let middle = stock.clone();
    let t = Instant::now();
    let second = stock.cut_path(&ball, &path[mid..]).expect("second half");
    let total = t_first + secs(t);
    let (v1, u1, m1) = totals(&first);
    let (v2, u2, m2) = totals(&second);
    let (visited, updated, removed) = (v1 + v2, u1 + u2, m1 + m2);
    let after = stock.volume_mm3();
    println!("(a) 1M-move finishing program (ball-3, cut_path):");
    println!(
        "    total {total:.2} s ({t_first:.2} s first half incl. the heavy first pass)  {:.0} moves/s",
        MOVES as f64 / total
    );
    println!(
        "    cells visited {visited} ({:.1} M/s, {:.0} per move), cells updated {updated} ({:.2} M/s)",
        visited as f64 / total / 1e6,
        visited as f64 / MOVES as f64,
        updated as f64 / total / 1e6
    );
    println!(
        "    removed {removed:.3} mm3; volume before - after = {:.3} mm3 (difference {:.2e})",
        before - after,
        (before - after - removed).abs()
    );
    println!(
        "    target: 1M moves in < {TARGET_S} s on this machine: {} ({:.1}x margin)",
        if total < TARGET_S { "MET" } else { "NOT MET" },
        TARGET_S / total
    );

    // (b) Per revolution on a 10k-move subset.
    let sub = &path[mid..=mid + 10_000];
    let mut whole = middle.clone();
    let t = Instant::now();
    let mut whole_volume = 0.0;
    for w in sub.windows(2) {
        whole_volume += whole.cut_line(&ball, w[0], w[1]).expect("cut").volume_mm3;
    }
    let t_whole = secs(t);
    let mut revs = middle.clone();
    let (mut pieces, mut rev_volume, mut max_eng) = (0u64, 0.0, 0.0f64);
    let t = Instant::now();
    for w in sub.windows(2) {
        cut_line_per_rev(&mut revs, &ball, w[0], w[1], 0.05, |c| {
            pieces += 1;
            rev_volume += c.volume_mm3;
            max_eng = max_eng.max(c.engagement_deg);
        })
        .expect("per rev");
    }
    let t_rev = secs(t);
    println!("(b) per revolution, 10k moves at 0.05 mm/rev (1 thread):");
    println!(
        "    {pieces} revolutions in {t_rev:.3} s: {:.0} revolutions/s ({:.1} us each); whole moves {t_whole:.3} s",
        pieces as f64 / t_rev,
        t_rev / pieces as f64 * 1e6
    );
    println!(
        "    removed {rev_volume:.4} mm3 per revolution vs {whole_volume:.4} mm3 whole (rel. diff {:.1e})",
        (rev_volume - whole_volume).abs() / whole_volume.max(1e-12)
    );

    // (c) Reference runs.
    compare("right after roughing (moves 0..100k)", &roughed, &ball, &path[..=100_000]);
    compare("mid-program re-cutting (moves 500k..600k)", &middle, &ball, &path[mid..=mid + 100_000]);
}
