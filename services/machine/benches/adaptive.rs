//! A whole simulated run of a 1M-move finishing program under the adaptive loop: G-code
//! interpretation, motion planning, material removal per spindle revolution, Kienzle forces,
//! sensors and the feed/speed policy, through the machine stage's own entry point
//! ([`depthmill_machine::domain::job::execute`]), as a job runs it.
//!
//! The program: ball-3 (2 flutes) zig-zag rasters over a 60 x 50 mm block on 0.05 mm cells, short
//! `G1` moves (0.05-0.25 mm, uniformly random) following a gently wavy surface 0.1-0.9 mm below
//! the block's top, stepover 0.3 mm, passes alternating along X and Y with shifted line
//! positions until the program has 1M feed moves: the first pass cuts the block down to the
//! surface, the rest re-cut finished material (the EMCO F1 runs it in about 20 h at its
//! 400 mm/min top feed and 2000 rpm).
//!
//! Runs (each timed wall and CPU, against the target), both including the stage's motion-only
//! pass over the program (travel and feed checks, the cycle time without adaptation):
//! - `aco, one run`: the stage with `compare` off (the main run alone);
//! - `aco + comparison`: the stage as a job runs it by default (the main run and the feed-only
//!   comparison in parallel, after the motion-only pass).
//!
//! `cargo bench -p depthmill-machine --bench adaptive [-- --moves N --cell MM --no-compare]`.
//! Target: 1M moves through the whole loop in < 60 s on 2 cores.

use std::fs::File;
use std::io::{BufReader, BufWriter, Write};
use std::path::Path;
use std::time::Instant;

use depthmill_machine::domain::job::{ExecuteOptions, execute};
use depthmill_machine::domain::sim::{PolicyKind, StockSpec};

const TARGET_S: f64 = 60.0;
const STEPOVER_MM: f64 = 0.3;

struct Args {
    moves: usize,
    cell_mm: f64,
    compare: bool,
}

fn args() -> Result<Args, String> {
    let mut a = Args { moves: 1_000_000, cell_mm: 0.05, compare: true };
    let mut it = std::env::args().skip(1);
    while let Some(arg) = it.next() {
        let mut value = |name: &str| it.next().ok_or(format!("{name} needs a value"));
        match arg.as_str() {
            "--moves" => a.moves = value("--moves")?.parse().map_err(|e| format!("--moves: {e}"))?,
            "--cell" => a.cell_mm = value("--cell")?.parse().map_err(|e| format!("--cell: {e}"))?,
            "--no-compare" => a.compare = false,
            "--bench" => {}
            other => return Err(format!("unknown argument {other}")),
        }
    }
    Ok(a)
}

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
    -0.8 + 0.3 * (TAU * x / 23.0).sin() * (TAU * y / 17.0).cos() + 0.1 * (TAU * (x + y) / 9.0).sin()
}

/// Writes the program; returns its feed moves and path length (mm).
fn write_program(path: &Path, moves: usize) -> std::io::Result<(usize, f64)> {
    let mut w = BufWriter::with_capacity(1 << 20, File::create(path)?);
    for l in [
        "%",
        "(depthmill adaptive-loop benchmark)",
        "G21 G90 G17 G94 G40 G49 G80",
        "G64 P0.0100",
        "G53 G0 Z0.0000",
        "(T1 ball-3: ball D3.0000 mm, 2 flutes - finishing)",
        "T1 M6",
        "S2000 M3",
        "G43 H1",
        "G0 X0.0000 Y0.0000",
        "Z2.0000",
        "G1 F300.0000",
    ] {
        writeln!(w, "{l}")?;
    }
    let mut rng = Rng(0x9e37_79b9_7f4a_7c15);
    let (width, height) = (60.0, 50.0);
    let (mut n, mut length) = (0usize, 0.0);
    let mut last = [0.0, 0.0, 2.0];
    let mut emit = |w: &mut BufWriter<File>, p: [f64; 3], n: &mut usize| -> std::io::Result<()> {
        let q = p.map(|v| (v * 1e4).round() / 1e4);
        length += ((q[0] - last[0]).powi(2) + (q[1] - last[1]).powi(2) + (q[2] - last[2]).powi(2)).sqrt();
        last = q;
        *n += 1;
        writeln!(w, "X{:.4} Y{:.4} Z{:.4}", q[0], q[1], q[2])
    };
    let mut pass = 0usize;
    'passes: loop {
        let along_x = pass.is_multiple_of(2);
        let (len, across) = if along_x { (width, height) } else { (height, width) };
        let phase = (pass as f64 * STEPOVER_MM * 0.618).rem_euclid(STEPOVER_MM);
        let mut forward = true;
        let mut c = phase;
        while c <= across {
            let mut a = if forward { 0.0 } else { len };
            loop {
                if n >= moves {
                    break 'passes;
                }
                let (x, y) = if along_x { (a, c) } else { (c, a) };
                emit(&mut w, [x, y, surface(x, y)], &mut n)?;
                let done = if forward { a >= len } else { a <= 0.0 };
                if done {
                    break;
                }
                let step = 0.05 + 0.2 * rng.unit();
                a = if forward { (a + step).min(len) } else { (a - step).max(0.0) };
            }
            forward = !forward;
            c += STEPOVER_MM;
        }
        pass += 1;
    }
    for l in ["G0 Z2.0000", "M5", "G53 G0 Z0.0000", "M30", "%"] {
        writeln!(w, "{l}")?;
    }
    w.flush()?;
    Ok((n, length))
}

/// CPU time of this process (all threads, user + system) from `/proc/self/stat`, in seconds.
fn cpu_secs() -> f64 {
    let Ok(stat) = std::fs::read_to_string("/proc/self/stat") else { return 0.0 };
    let Some(rest) = stat.rsplit_once(')').map(|(_, r)| r) else { return 0.0 };
    let f: Vec<&str> = rest.split_whitespace().collect();
    let num = |i: usize| f.get(i).and_then(|x| x.parse::<f64>().ok());
    match (num(11), num(12)) {
        (Some(u), Some(s)) => (u + s) / 100.0,
        _ => 0.0,
    }
}

fn main() -> Result<(), String> {
    let a = args()?;
    let threads = rayon::current_num_threads();
    let dir = std::env::temp_dir().join(format!("depthmill-adaptive-bench-{}", std::process::id()));
    std::fs::create_dir_all(&dir).map_err(|e| format!("{}: {e}", dir.display()))?;
    let prog = dir.join("finishing.ngc");
    let t = Instant::now();
    let (moves, length) = write_program(&prog, a.moves).map_err(|e| format!("{}: {e}", prog.display()))?;
    println!(
        "adaptive-loop benchmark: {moves} feed moves, {:.1} m of path (mean move {:.3} mm), written in {:.2} s; \
         60 x 50 mm block on {} mm cells; {threads} rayon threads",
        length / 1000.0,
        length / moves.max(1) as f64,
        t.elapsed().as_secs_f64(),
        a.cell_mm
    );
    let open = || -> std::io::Result<Box<dyn std::io::BufRead + Send>> {
        Ok(Box::new(BufReader::with_capacity(1 << 16, File::open(&prog)?)))
    };
    let stock = StockSpec {
        min_x_mm: -3.0,
        min_y_mm: -3.0,
        min_z_mm: -10.0,
        x_mm: 66.0,
        y_mm: 56.0,
        z_mm: 9.7,
        cell_mm: a.cell_mm,
    };
    let mut runs = vec![("aco, one run (compare off)", PolicyKind::Aco, false)];
    if a.compare {
        runs.push(("aco + feed-only comparison (the stage's default)", PolicyKind::Aco, true));
    }
    for (label, policy, compare) in runs {
        let opts = ExecuteOptions {
            policy,
            compare,
            stock: Some(stock),
            cell_mm: Some(a.cell_mm),
            ..ExecuteOptions::default()
        };
        let (t, c) = (Instant::now(), cpu_secs());
        let mut rows = 0usize;
        let out = execute(&open, &opts, None, &|| false, &mut |_| rows += 1).map_err(|e| e.to_string())?;
        let (wall, cpu) = (t.elapsed().as_secs_f64(), cpu_secs() - c);
        let r = &out.report.run;
        println!(
            "{label}: wall {wall:.2} s, CPU {cpu:.2} s; {} revolutions ({:.0}/s wall), {} moves, removed {:.1} mm3, \
             simulated cycle {:.1} h (programmed feeds {:.1} h), max torque {:.3} N m, {rows} telemetry rows",
            r.revolutions,
            r.revolutions as f64 / wall,
            r.moves,
            r.removed_mm3,
            out.report.cycle_time_s / 3600.0,
            out.report.cycle_time_no_adaptive_s / 3600.0,
            r.max_torque_nm,
        );
        println!(
            "    target < {TARGET_S} s on {threads} cores: {} (wall / target = {:.2})",
            if wall < TARGET_S { "MET" } else { "NOT MET" },
            wall / TARGET_S
        );
    }
    let _ = std::fs::remove_dir_all(&dir);
    Ok(())
}
