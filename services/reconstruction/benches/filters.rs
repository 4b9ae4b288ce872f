//! Radius outlier removal and voxel decimation on 10^6 points, against Open3D's
//! `remove_radius_outlier` and `voxel_down_sample` on the same cloud in the same run (through
//! `scripts/compare_open3d_filters.py`).
//!
//! ```text
//! cargo bench -p depthmill-reconstruction --bench filters -- [--points 1000000] [--radius-mm 0.25]
//!     [--min-neighbours 8] [--voxel-mm 0.5] [--repeat 3] [--seed 7] [--python python3] [--no-open3d]
//! ```
//!
//! The cloud is the SOR bench's (a wavy height field on a jittered 0.1 mm grid with 10 µm noise,
//! plus 1 % outliers over the box around it). Times `radius_outlier_removal` and
//! `voxel_decimate` (best of `--repeat`, the cloud clone excluded), then the script times Open3D
//! and checks:
//!
//! - radius: the same points removed. Open3D keeps a point whose radius search (points strictly
//!   within the radius, the point itself among them) returns more than `nb_points`, so
//!   `nb_points = min_neighbours` (checked against a brute force when this was written).
//! - voxel: each tool's voxel count against numpy's count of the voxels under its own rule
//!   (depthmill: `floor(p / voxel)`, one original point kept per voxel, the one nearest the
//!   voxel's centroid; Open3D: voxels from the cloud's minimum bound less half a voxel, one
//!   averaged point per voxel). The rules differ, so the counts differ slightly; the times
//!   compare the same work.
//!
//! Needs `pip install open3d numpy`; without them it prints how to install and skips the
//! comparison.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

use depthmill_geometry::PointCloud;
use depthmill_reconstruction::domain::filters::{
    radius_outlier_mask, radius_outlier_removal, voxel_decimate,
};

mod support;

use support::{
    BoxResult, cpu_seconds, field, run_reference, scan_like_cloud, write_cloud_npy, write_mask_npy,
};

struct Args {
    points: usize,
    radius_mm: f64,
    min_neighbours: usize,
    voxel_mm: f64,
    repeat: u32,
    seed: u64,
    python: String,
    open3d: bool,
}

fn parse_args() -> BoxResult<Args> {
    let mut a = Args {
        points: 1_000_000,
        radius_mm: 0.25,
        min_neighbours: 8,
        voxel_mm: 0.5,
        repeat: 3,
        seed: 7,
        python: "python3".into(),
        open3d: true,
    };
    let mut it = std::env::args().skip(1);
    while let Some(flag) = it.next() {
        let mut value = || it.next().ok_or_else(|| format!("{flag} needs a value"));
        match flag.as_str() {
            "--points" => a.points = value()?.parse()?,
            "--radius-mm" => a.radius_mm = value()?.parse()?,
            "--min-neighbours" => a.min_neighbours = value()?.parse()?,
            "--voxel-mm" => a.voxel_mm = value()?.parse()?,
            "--repeat" => a.repeat = value()?.parse::<u32>()?.max(1),
            "--seed" => a.seed = value()?.parse()?,
            "--python" => a.python = value()?,
            "--no-open3d" => a.open3d = false,
            "--bench" => {} // cargo bench passes this
            other => return Err(format!("unknown argument {other}").into()),
        }
    }
    Ok(a)
}

/// Best wall time and mean CPU time per run (ms) of `repeat` runs of `run` on clones of
/// `cloud`, and the points the last run kept.
fn time_filter(
    cloud: &PointCloud,
    repeat: u32,
    run: impl Fn(PointCloud) -> BoxResult<PointCloud>,
) -> BoxResult<(f64, Option<f64>, usize)> {
    let (mut best, mut cpu, mut kept) = (f64::INFINITY, 0.0, 0);
    for _ in 0..repeat {
        let input = cloud.clone();
        let (c0, t) = (cpu_seconds(), Instant::now());
        let out = run(input)?;
        best = best.min(t.elapsed().as_secs_f64() * 1e3);
        cpu += cpu_seconds().zip(c0).map_or(f64::NAN, |(b, a)| b - a);
        kept = out.len();
    }
    Ok((best, Some(cpu * 1e3 / f64::from(repeat)).filter(|c| c.is_finite()), kept))
}

fn script_path() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/compare_open3d_filters.py")
}

/// A number from the script's output.
fn number(out: &str, key: &str) -> Option<f64> {
    field(out, key)?.parse().ok()
}

fn main() -> BoxResult<()> {
    let args = parse_args()?;
    let threads = rayon::current_num_threads();
    let cloud = scan_like_cloud(args.points, args.seed);
    println!("cloud: {} points (wavy height field on a jittered 0.1 mm grid + 1 % outliers)", cloud.len());

    let (ror_ms, ror_cpu, ror_kept) = time_filter(&cloud, args.repeat, |c| {
        Ok(radius_outlier_removal(c, args.radius_mm, args.min_neighbours)?.0)
    })?;
    println!(
        "depthmill radius_outlier_removal radius {} mm, {} neighbours: best of {} = {:.1} ms ({} rayon threads; \
         {:.0} ms CPU per run), kept {}",
        args.radius_mm,
        args.min_neighbours,
        args.repeat,
        ror_ms,
        threads,
        ror_cpu.unwrap_or(f64::NAN),
        ror_kept
    );
    let (vox_ms, vox_cpu, vox_kept) =
        time_filter(&cloud, args.repeat, |c| Ok(voxel_decimate(c, args.voxel_mm)?.0))?;
    println!(
        "depthmill voxel_decimate {} mm: best of {} = {:.1} ms ({:.0} ms CPU per run), {} voxels",
        args.voxel_mm,
        args.repeat,
        vox_ms,
        vox_cpu.unwrap_or(f64::NAN),
        vox_kept
    );
    if !args.open3d {
        return Ok(());
    }

    let dir = tempfile::tempdir()?;
    let (cloud_path, keep_path) = (dir.path().join("cloud.npy"), dir.path().join("ror_keep.npy"));
    write_cloud_npy(&cloud_path, &cloud)?;
    write_mask_npy(&keep_path, &radius_outlier_mask(&cloud.points, args.radius_mm, args.min_neighbours)?)?;
    let mut cmd = Command::new(&args.python);
    cmd.arg(script_path())
        .arg("--cloud")
        .arg(&cloud_path)
        .arg("--ror-keep")
        .arg(&keep_path)
        .args(["--radius-mm", &args.radius_mm.to_string()])
        .args(["--min-neighbours", &args.min_neighbours.to_string()])
        .args(["--voxel-mm", &args.voxel_mm.to_string()])
        .args(["--depthmill-voxels", &vox_kept.to_string()])
        .args(["--repeat", &args.repeat.to_string()]);
    let Some((stdout, _)) = run_reference(&mut cmd, &args.python) else {
        return Ok(());
    };
    let ratio = |theirs: Option<f64>, ours: f64| theirs.map_or(f64::NAN, |t| t / ours);
    println!(
        "open3d remove_radius_outlier: {:.1} ms; depthmill is {:.2}x faster (CPU {:.2}x); mismatched points: {}",
        number(&stdout, "open3d_ror_ms").unwrap_or(f64::NAN),
        ratio(number(&stdout, "open3d_ror_ms"), ror_ms),
        ratio(number(&stdout, "open3d_ror_cpu_ms"), ror_cpu.unwrap_or(f64::NAN)),
        number(&stdout, "ror_mismatches").map_or("?".into(), |m| format!("{m:.0}"))
    );
    println!(
        "open3d voxel_down_sample: {:.1} ms; depthmill is {:.2}x faster (CPU {:.2}x); voxels {} (depthmill {})",
        number(&stdout, "open3d_voxel_ms").unwrap_or(f64::NAN),
        ratio(number(&stdout, "open3d_voxel_ms"), vox_ms),
        ratio(number(&stdout, "open3d_voxel_cpu_ms"), vox_cpu.unwrap_or(f64::NAN)),
        number(&stdout, "open3d_voxels").map_or("?".into(), |m| format!("{m:.0}")),
        vox_kept
    );
    Ok(())
}
