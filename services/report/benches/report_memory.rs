//! Memory of rendering a report against the size of its largest artifacts: the scanned cloud
//! (binary PLY) and the program (G-code), each at growing sizes. Two ways, each size in a fresh
//! child process so the peak resident set (`VmHWM`) is that run's alone:
//!
//! - `whole`: the artifacts' bytes in memory, the cloud read whole and the program parsed whole
//!   (how the report stage read them before streaming);
//! - `streamed`: the cloud and the program streamed from their files through
//!   `depthmill_report::digest` (what the orchestrator does now), everything else as bytes.
//!
//! Run: `cargo bench -p depthmill-report --bench report_memory` (release). Sizes:
//! `DEPTHMILL_BENCH_SCALES` (default `1,4,16`): a scale of k is k x 10^6 cloud points and
//! k x 2.5 x 10^5 program moves. Target: the streamed peak flat in the artifacts' size (the
//! largest scale within 1.5x of the smallest).

use std::collections::BTreeMap;
use std::fs::File;
use std::io::{BufReader, BufWriter, Write};
use std::path::{Path, PathBuf};
use std::time::Instant;

use depthmill_geometry::PointCloud;
use depthmill_geometry::formats::{PlyEncoding, write_ply};
use depthmill_geometry::nalgebra::Point3;
use depthmill_report::digest::{self, Digests};
use depthmill_report::{ReportInput, render};

fn peak_rss_mb() -> f64 {
    let status = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmHWM:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<f64>().ok())
        .map_or(f64::NAN, |kb| kb / 1024.0)
}

fn write_cloud(path: &Path, n: usize) -> std::io::Result<()> {
    let side = (n as f64).sqrt().ceil() as usize;
    let cloud = PointCloud::from_points((0..n).map(|i| {
        let (x, y) = ((i % side) as f64 * 0.05, (i / side) as f64 * 0.05);
        Point3::new(x, y, 5.0 + (x * 0.2).sin() * (y * 0.3).cos())
    }));
    let mut w = BufWriter::new(File::create(path)?);
    write_ply(&mut w, &cloud, None, PlyEncoding::BinaryLittleEndian, &[]).map_err(std::io::Error::other)?;
    w.flush()
}

fn write_program(path: &Path, moves: usize) -> std::io::Result<()> {
    let mut w = BufWriter::new(File::create(path)?);
    writeln!(
        w,
        "%\nG21 G90 G17\n(T1 ball-6: ball D6 mm - finishing-x with ball-6)\nT1 M6\nS8000 M3\nG0 X0 Y0 Z5"
    )?;
    let per_row = 1000;
    for k in 0..moves {
        let (row, i) = (k / per_row, k % per_row);
        let x = if row % 2 == 0 { i as f64 * 0.05 } else { (per_row - i) as f64 * 0.05 };
        let y = row as f64 * 0.2;
        writeln!(w, "G1 X{x:.3} Y{y:.3} Z{:.3} F1200", (x * 0.2).sin() * (y * 0.3).cos())?;
    }
    writeln!(w, "G0 Z5\nM30\n%")?;
    w.flush()
}

fn job(cloud: &Path, program: &Path) -> serde_json::Value {
    let size = |p: &Path| std::fs::metadata(p).map(|m| m.len()).unwrap_or(0);
    serde_json::json!({
        "id": "0193a1b2-c3d4-7e5f-8a9b-0c1d2e3f4a5b", "name": "memory bench", "status": "succeeded",
        "stage": "report", "progress": 1.0, "spec": {"input": {"kind": "point_cloud"}},
        "artifacts": {
            "point_cloud": {"sha256": "0".repeat(64), "size": size(cloud), "media_type": "application/x-ply"},
            "gcode": {"sha256": "1".repeat(64), "size": size(program), "media_type": "text/x-gcode"}
        },
        "metrics": {}, "attempts": [], "stage_timings_s": {}
    })
}

/// One rendering in this process; prints `peak_mb seconds`.
fn child(mode: &str, cloud: &Path, program: &Path) -> Result<(), String> {
    let job = job(cloud, program);
    let t = Instant::now();
    let out = if mode == "whole" {
        let mut artifacts = BTreeMap::new();
        artifacts.insert("point_cloud".to_string(), std::fs::read(cloud).map_err(|e| e.to_string())?);
        artifacts.insert("gcode".to_string(), std::fs::read(program).map_err(|e| e.to_string())?);
        // The cloud read whole and the program parsed whole, as before streaming.
        let bytes = &artifacts["point_cloud"];
        let (whole, _) = depthmill_geometry::formats::read_any_from(
            std::io::Cursor::new(bytes),
            "point_cloud",
            Some(bytes.len() as u64),
            &depthmill_geometry::formats::ReadLimits::default(),
        )
        .map_err(|e| e.to_string())?;
        let parsed = depthmill_report::gcode::parse(&String::from_utf8_lossy(&artifacts["gcode"]));
        std::hint::black_box((&whole, &parsed));
        render(&ReportInput { job: &job, artifacts: &artifacts, digests: &Digests::NONE })
    } else {
        let mut digests = Digests::default();
        let size = std::fs::metadata(cloud).map(|m| m.len()).ok();
        let file = File::open(cloud).map_err(|e| e.to_string())?;
        let sampled = digest::cloud(BufReader::with_capacity(1 << 20, file), "point_cloud", size)?;
        digests.clouds.insert("point_cloud".into(), sampled);
        let file = File::open(program).map_err(|e| e.to_string())?;
        let parsed = digest::program(BufReader::with_capacity(1 << 20, file)).map_err(|e| e.to_string())?;
        digests.programs.insert("gcode".into(), parsed);
        render(&ReportInput { job: &job, artifacts: &BTreeMap::new(), digests: &digests })
    }
    .map_err(|e| e.to_string())?;
    std::hint::black_box(&out.html);
    println!("{:.1} {:.2}", peak_rss_mb(), t.elapsed().as_secs_f64());
    Ok(())
}

fn run_child(mode: &str, cloud: &Path, program: &Path) -> Result<(f64, f64), String> {
    let exe = std::env::current_exe().map_err(|e| e.to_string())?;
    let out = std::process::Command::new(exe)
        .env("DEPTHMILL_BENCH_CHILD", format!("{mode}\n{}\n{}", cloud.display(), program.display()))
        .output()
        .map_err(|e| e.to_string())?;
    if !out.status.success() {
        return Err(format!("{mode} run failed: {}", String::from_utf8_lossy(&out.stderr)));
    }
    let text = String::from_utf8_lossy(&out.stdout);
    let mut f = text.split_whitespace().filter_map(|v| v.parse::<f64>().ok());
    match (f.next(), f.next()) {
        (Some(mb), Some(s)) => Ok((mb, s)),
        _ => Err(format!("{mode} run printed {text:?}")),
    }
}

fn main() -> Result<(), String> {
    if let Ok(spec) = std::env::var("DEPTHMILL_BENCH_CHILD") {
        let mut parts = spec.lines();
        let (Some(mode), Some(cloud), Some(program)) = (parts.next(), parts.next(), parts.next()) else {
            return Err("bad child spec".into());
        };
        return child(mode, Path::new(cloud), Path::new(program));
    }
    let scales: Vec<usize> = std::env::var("DEPTHMILL_BENCH_SCALES")
        .unwrap_or_else(|_| "1,4,16".into())
        .split(',')
        .filter_map(|s| s.trim().parse().ok())
        .collect();
    let dir = tempfile::tempdir().map_err(|e| e.to_string())?;
    println!("report memory: peak resident set of one rendering, fresh process per row");
    println!(
        "{:>5} {:>12} {:>12} {:>10} {:>10} {:>10} {:>10} {:>8}",
        "scale", "cloud pts", "moves", "MB files", "whole MB", "stream MB", "ratio", "stream s"
    );
    let mut streamed_peaks = Vec::new();
    for k in scales {
        let (points, moves) = (k * 1_000_000, k * 250_000);
        let cloud: PathBuf = dir.path().join(format!("cloud-{k}.ply"));
        let program: PathBuf = dir.path().join(format!("program-{k}.ngc"));
        write_cloud(&cloud, points).map_err(|e| e.to_string())?;
        write_program(&program, moves).map_err(|e| e.to_string())?;
        let files_mb = [&cloud, &program]
            .iter()
            .map(|p| std::fs::metadata(p).map(|m| m.len()).unwrap_or(0))
            .sum::<u64>() as f64
            / 1e6;
        let (whole, _) = run_child("whole", &cloud, &program)?;
        let (streamed, secs) = run_child("streamed", &cloud, &program)?;
        streamed_peaks.push(streamed);
        println!(
            "{k:>5} {points:>12} {moves:>12} {files_mb:>10.1} {whole:>10.1} {streamed:>10.1} {:>9.2}x {secs:>8.2}",
            whole / streamed
        );
        let _ = std::fs::remove_file(&cloud);
        let _ = std::fs::remove_file(&program);
    }
    if let (Some(first), Some(last)) = (streamed_peaks.first(), streamed_peaks.last()) {
        println!(
            "streamed peak, largest / smallest scale: {:.2}x (target <= 1.5x: flat in the artifacts' size)",
            last / first
        );
    }
    Ok(())
}
