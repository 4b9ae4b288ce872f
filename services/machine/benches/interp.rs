//! Throughput of the G-code interpreter against LinuxCNC's standalone interpreter `rs274`.
//!
//! Generates a 1M-block finishing program in the CAM service's LinuxCNC style (raster passes of
//! modal `X Z` moves with 4 decimals, a G2/G3 semicircle between passes, header and footer), then
//! in the same run:
//! - ours: `run` over a `BufReader` of the file, counting canonical commands (best of 3);
//! - rs274: `rs274 -t tool.tbl -b -g prog.ngc /dev/null` (best of 3; exit status checked), if
//!   `rs274` is on PATH (Debian package linuxcnc-uspace);
//! - the ratio against the >= 10x target, and whether both runs made the same moves
//!   (endpoints within 1e-4 mm, same arcs).
//!
//! `cargo bench -p depthmill-machine --bench interp [-- --blocks N --runs N --no-compare
//!  --program FILE.ngc --tool-table FILE.tbl]` (tool tables in inches, as the standalone rs274
//! reads them). `scripts/compare_rs274.sh` runs the same comparison from the shell.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::fs::File;
use std::hint::black_box;
use std::io::{BufReader, BufWriter, Write};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use depthmill_machine::domain::gcode::rs274::{Rs274Options, compare, find_rs274, run_rs274_with};
use depthmill_machine::domain::gcode::{Canon, InterpConfig, MM_PER_INCH, run};

struct Args {
    blocks: usize,
    runs: usize,
    compare: bool,
    program: Option<PathBuf>,
    tool_table: Option<PathBuf>,
}

fn args() -> Result<Args, String> {
    let mut a = Args { blocks: 1_000_000, runs: 3, compare: true, program: None, tool_table: None };
    let mut it = std::env::args().skip(1);
    while let Some(arg) = it.next() {
        let mut value = |name: &str| it.next().ok_or(format!("{name} needs a value"));
        match arg.as_str() {
            "--blocks" => a.blocks = value("--blocks")?.parse().map_err(|e| format!("--blocks: {e}"))?,
            "--runs" => a.runs = value("--runs")?.parse().map_err(|e| format!("--runs: {e}"))?,
            "--no-compare" => a.compare = false,
            "--program" => a.program = Some(PathBuf::from(value("--program")?)),
            "--tool-table" => a.tool_table = Some(PathBuf::from(value("--tool-table")?)),
            "--bench" => {}
            other => return Err(format!("unknown argument {other}")),
        }
    }
    Ok(a)
}

/// Tool table of the generated program, inches: T1 25.4 mm.
const TOOL_TABLE: &str = "T1 P1 Z1.0 D0.125 ;ball-3\n";

/// Writes the finishing program; returns the number of blocks (lines other than `%`).
fn write_program(path: &Path, blocks: usize) -> std::io::Result<usize> {
    let mut w = BufWriter::with_capacity(1 << 20, File::create(path)?);
    let header = [
        "%",
        "(depthmill finishing benchmark)",
        "(tolerance 0.01 mm)",
        "G21 G90 G17 G94 G40 G49 G80",
        "G64 P0.0100",
        "G53 G0 Z0.0000",
        "(T1 ball-3: ball D3.0000 mm, 2 flutes - finishing-raster-x)",
        "T1 M6",
        "S2000 M3",
        "M8",
        "G43 H1",
        "G0 X0.0000 Y0.0000",
        "Z5.0000",
        "G1 Z-0.5000 F300.0000",
    ];
    let mut n = 0;
    for l in header {
        writeln!(w, "{l}")?;
        n += usize::from(l != "%");
    }
    let per_pass = 1000;
    let step = 0.2;
    let mut line = String::with_capacity(64);
    let mut pass = 0usize;
    let footer_blocks = 5;
    while n + footer_blocks < blocks {
        let y = pass as f64 * step;
        let forward = pass.is_multiple_of(2);
        // The last pass may be partial (no turn at its end), so the total is exactly `blocks`.
        let points = per_pass.min(blocks - footer_blocks - n);
        let turn = points == per_pass && n + points + 1 + footer_blocks <= blocks;
        for i in 1..=points {
            let t = i as f64 / per_pass as f64;
            let x = if forward { 50.0 * t } else { 50.0 * (1.0 - t) };
            let z = -0.5 + 0.3 * (x * 0.21).sin() * (y * 0.17).cos() - 0.05 * (x * 0.05 + y * 0.03).cos();
            line.clear();
            if i == 1 && pass > 0 {
                line.push_str("G1 ");
            }
            write!(line, "X{x:.4} Z{z:.4}").map_err(std::io::Error::other)?;
            writeln!(w, "{line}")?;
            n += 1;
        }
        if !turn {
            break;
        }
        // Semicircle to the next pass.
        let x_end = if forward { 50.0 } else { 0.0 };
        let g = if forward { 3 } else { 2 };
        writeln!(w, "G{g} X{x_end:.4} Y{:.4} I0.0000 J{:.4}", y + step, step / 2.0)?;
        n += 1;
        pass += 1;
    }
    for l in ["G0 Z5.0000", "M5", "M9", "G53 G0 Z0.0000", "M30", "%"] {
        writeln!(w, "{l}")?;
        n += usize::from(l != "%");
    }
    w.flush()?;
    Ok(n)
}

/// Our config matching a LinuxCNC tool table (lengths in inches).
fn config_for(tool_table: &str) -> InterpConfig {
    let mut tools = BTreeMap::new();
    for line in tool_table.lines() {
        let line = line.split(';').next().unwrap_or("");
        let (mut t, mut z) = (None, 0.0);
        for w in line.split_whitespace() {
            if let Some(v) = w.strip_prefix(['T', 't']) {
                t = v.parse::<u32>().ok();
            } else if let Some(v) = w.strip_prefix(['Z', 'z']) {
                z = v.parse::<f64>().unwrap_or(0.0) * MM_PER_INCH;
            }
        }
        if let Some(t) = t {
            tools.insert(t, z);
        }
    }
    InterpConfig { tools, ..InterpConfig::default() }
}

/// CPU time (user + system) of this thread so far (Linux `/proc/thread-self/schedstat`, ns).
fn thread_cpu() -> Option<Duration> {
    let s = std::fs::read_to_string("/proc/thread-self/schedstat").ok()?;
    Some(Duration::from_nanos(s.split_whitespace().next()?.parse().ok()?))
}

/// CPU time (user + system) of this process's waited-for children (Linux `/proc/self/stat`
/// cutime + cstime, in USER_HZ = 100 ticks per second).
fn children_cpu() -> Option<Duration> {
    let s = std::fs::read_to_string("/proc/self/stat").ok()?;
    // Fields after the parenthesised command name; cutime and cstime are fields 16 and 17.
    let rest = &s[s.rfind(')')? + 2..];
    let f: Vec<&str> = rest.split_whitespace().collect();
    let ticks: u64 = f.get(13)?.parse::<u64>().ok()? + f.get(14)?.parse::<u64>().ok()?;
    Some(Duration::from_millis(ticks * 10))
}

/// Peak resident set size of this process, kB (Linux).
fn peak_rss_kb() -> Option<u64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    let l = s.lines().find(|l| l.starts_with("VmHWM:"))?;
    l.split_whitespace().nth(1)?.parse().ok()
}

/// Best (smallest) CPU time and wall time over `runs` runs of `f`; `cpu` reads the CPU clock
/// that `f` advances.
fn best<T>(
    runs: usize,
    cpu: fn() -> Option<Duration>,
    mut f: impl FnMut() -> Result<T, String>,
) -> Result<(Duration, Duration, T), String> {
    let mut best: Option<(Duration, Duration, T)> = None;
    for _ in 0..runs.max(1) {
        let (c0, t0) = (cpu().ok_or("no CPU clock (needs Linux /proc)")?, Instant::now());
        let v = f()?;
        let (c1, dt) = (cpu().ok_or("no CPU clock")?, t0.elapsed());
        let dc = c1.saturating_sub(c0);
        let wall = best.as_ref().map_or(dt, |b| b.1.min(dt));
        if best.as_ref().is_none_or(|(b, _, _)| dc < *b) {
            best = Some((dc, wall, v));
        } else if let Some(b) = best.as_mut() {
            b.1 = wall;
        }
    }
    best.ok_or_else(|| "no run".to_string())
}

fn main() {
    if let Err(e) = real_main() {
        eprintln!("error: {e}");
        std::process::exit(1);
    }
}

fn real_main() -> Result<(), String> {
    let a = args()?;
    let dir = tempfile::tempdir().map_err(|e| e.to_string())?;
    let (program, tool_table) = match (&a.program, &a.tool_table) {
        (Some(p), t) => {
            let t = match t {
                Some(t) => t.clone(),
                None => {
                    let t = dir.path().join("tool.tbl");
                    std::fs::write(&t, TOOL_TABLE).map_err(|e| e.to_string())?;
                    t
                }
            };
            (p.clone(), t)
        }
        (None, _) => {
            let p = dir.path().join("finishing.ngc");
            let t = dir.path().join("tool.tbl");
            std::fs::write(&t, TOOL_TABLE).map_err(|e| e.to_string())?;
            let n = write_program(&p, a.blocks).map_err(|e| e.to_string())?;
            println!("generated {n} blocks");
            (p, t)
        }
    };
    let size = std::fs::metadata(&program).map_err(|e| e.to_string())?.len();
    let table_text = std::fs::read_to_string(&tool_table).map_err(|e| e.to_string())?;
    let config = config_for(&table_text);
    println!("program: {} ({:.1} MB)", program.display(), size as f64 / 1e6);

    // Ours.
    let rss_before = peak_rss_kb();
    let (ours, ours_wall, summary) = best(a.runs, thread_cpu, || {
        let f = File::open(&program).map_err(|e| e.to_string())?;
        let mut count = 0u64;
        let mut check = 0.0f64;
        let s = run(BufReader::with_capacity(1 << 16, f), config.clone(), |c| {
            count += 1;
            if let Some(p) = c.end_point() {
                check += p.x;
            }
        })
        .map_err(|e| e.to_string())?;
        black_box(check);
        Ok((s, count))
    })?;
    let (s, count) = summary;
    let ours_rate = s.blocks as f64 / ours.as_secs_f64();
    println!(
        "ours:  best of {}: {:.3} s CPU ({:.3} s wall), {} lines, {} blocks, {} canonical commands -> {:.2} M blocks/s CPU",
        a.runs,
        ours.as_secs_f64(),
        ours_wall.as_secs_f64(),
        s.lines,
        s.blocks,
        count,
        ours_rate / 1e6
    );
    if let (Some(b), Some(after)) = (rss_before, peak_rss_kb()) {
        println!(
            "ours:  peak RSS {:.1} MB before, {:.1} MB after (streaming: flat in program length)",
            b as f64 / 1e3,
            after as f64 / 1e3
        );
    }

    // rs274.
    let Some(rs274) = find_rs274() else {
        println!("rs274: not on PATH (apt-get install linuxcnc-uspace): no reference figure");
        return Ok(());
    };
    let home = dir.path().join("home");
    std::fs::create_dir_all(&home).map_err(|e| e.to_string())?;
    let (theirs, theirs_wall, ()) = best(a.runs, children_cpu, || {
        let out = Command::new(&rs274)
            .env("HOME", &home)
            .arg("-t")
            .arg(&tool_table)
            .arg("-b")
            .arg("-g")
            .arg(&program)
            .arg("/dev/null")
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .output()
            .map_err(|e| format!("rs274: {e}"))?;
        let err = String::from_utf8_lossy(&out.stderr);
        let err = err.lines().filter(|l| l.trim() != "executing" && !l.trim().is_empty()).collect::<Vec<_>>();
        if !out.status.success() || !err.is_empty() {
            return Err(format!("rs274 failed ({}): {}", out.status, err.join(" | ")));
        }
        Ok(())
    })?;
    let theirs_rate = s.blocks as f64 / theirs.as_secs_f64();
    println!(
        "rs274: best of {}: {:.3} s CPU ({:.3} s wall) -> {:.2} M blocks/s CPU ({} -t tool.tbl -b -g prog.ngc /dev/null)",
        a.runs,
        theirs.as_secs_f64(),
        theirs_wall.as_secs_f64(),
        theirs_rate / 1e6,
        rs274.display()
    );
    let ratio = ours_rate / theirs_rate;
    let wall_ratio = theirs_wall.as_secs_f64() / ours_wall.as_secs_f64();
    println!(
        "ratio: {ratio:.1}x rs274's CPU throughput (target >= 10x: {}); wall-clock ratio {wall_ratio:.1}x",
        if ratio >= 10.0 { "met" } else { "NOT met" }
    );

    if a.compare {
        let t0 = Instant::now();
        let mut mine: Vec<Canon> = Vec::with_capacity(s.blocks as usize);
        let f = File::open(&program).map_err(|e| e.to_string())?;
        run(BufReader::new(f), config.clone(), |c| {
            if c.is_motion() {
                mine.push(c);
            }
        })
        .map_err(|e| e.to_string())?;
        let theirs =
            run_rs274_with(&program, &tool_table, &Rs274Options::default()).map_err(|e| e.to_string())?;
        let n = compare(&mine, &theirs, 1e-4).map_err(|e| e.to_string())?;
        println!(
            "agreement: {n} moves identical within 1e-4 mm (+ rs274's print resolution), arcs equal ({:.1} s)",
            t0.elapsed().as_secs_f64()
        );
    }
    Ok(())
}
