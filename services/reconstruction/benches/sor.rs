//! Statistical outlier removal speed on 10^6 points, against Open3D's `remove_statistical_outlier`
//! on the same cloud in the same run (through `scripts/compare_open3d.py`, which also checks that
//! both remove exactly the same points).
//!
//! ```text
//! cargo bench -p depthmill-reconstruction --bench sor -- [--points 1000000] [--k 20] [--n-sigma 2]
//!     [--repeat 3] [--seed 7] [--shape surface] [--python python3] [--script PATH] [--no-open3d]
//! cargo bench -p depthmill-reconstruction --bench sor -- --cloud IN.npy --keep-out KEEP.npy
//!     [--k 20] [--n-sigma 2] [--repeat 3]
//! ```
//!
//! First form: builds a scanned-like cloud (a wavy height field sampled on a jittered 0.1 mm grid
//! with 10 µm noise, plus 1 % outliers spread over the box around it), times
//! `statistical_outlier_removal` (best of `--repeat`, the cloud clone excluded), writes the cloud
//! (`<f8`, shape `(n, 3)`) and the keep mask (`|b1`, shape `(n,)`) as `.npy` to a temporary folder
//! and runs `python3 scripts/compare_open3d.py --cloud .. --keep .. --k .. --n-sigma .. --repeat ..`,
//! then prints both times and the ratio. Needs `pip install open3d numpy`; without them it prints
//! how to install and skips the comparison.
//!
//! `--shape cube|line|duplicates` replaces the cloud for robustness runs (uniform in a 100 mm
//! cube; a noisy 100 mm segment; the surface with every tenth point moved to one spot, where
//! Open3D and depthmill differ by design, see the filters module docs).
//!
//! Second form (used by the script when run on its own): reads a cloud `.npy`, runs the filter,
//! writes the keep mask and prints `sor_ms=<best ms>` and `kept=<count>`.

use std::io::Read;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

use depthmill_geometry::PointCloud;
use depthmill_reconstruction::domain::filters::{statistical_outlier_mask, statistical_outlier_removal};
use nalgebra::Point3;
use support::{cpu_seconds, field, gauss, run_reference, scan_like_cloud, write_cloud_npy, write_mask_npy};
mod support;

use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

type BoxResult<T> = Result<T, Box<dyn std::error::Error>>;

struct Args {
    points: usize,
    k: usize,
    n_sigma: f64,
    repeat: u32,
    seed: u64,
    python: String,
    script: Option<PathBuf>,
    open3d: bool,
    cloud: Option<PathBuf>,
    keep_out: Option<PathBuf>,
    shape: String,
}

fn parse_args() -> BoxResult<Args> {
    let mut a = Args {
        points: 1_000_000,
        k: 20,
        n_sigma: 2.0,
        repeat: 3,
        seed: 7,
        python: "python3".into(),
        script: None,
        open3d: true,
        cloud: None,
        keep_out: None,
        shape: "surface".into(),
    };
    let mut it = std::env::args().skip(1);
    while let Some(flag) = it.next() {
        let mut value = || it.next().ok_or_else(|| format!("{flag} needs a value"));
        match flag.as_str() {
            "--points" => a.points = value()?.parse()?,
            "--k" => a.k = value()?.parse()?,
            "--n-sigma" => a.n_sigma = value()?.parse()?,
            "--repeat" => a.repeat = value()?.parse::<u32>()?.max(1),
            "--seed" => a.seed = value()?.parse()?,
            "--python" => a.python = value()?,
            "--script" => a.script = Some(value()?.into()),
            "--no-open3d" => a.open3d = false,
            "--cloud" => a.cloud = Some(value()?.into()),
            "--keep-out" => a.keep_out = Some(value()?.into()),
            "--shape" => a.shape = value()?,
            "--bench" => {} // cargo bench passes this
            other => return Err(format!("unknown argument {other}").into()),
        }
    }
    Ok(a)
}

/// Other clouds for robustness runs: `cube` (uniform in a 100 mm cube), `line` (a noisy
/// 100 mm segment), `duplicates` (the surface with every tenth point moved to one spot).
fn other_cloud(shape: &str, n: usize, seed: u64) -> BoxResult<PointCloud> {
    let mut rng = StdRng::seed_from_u64(seed);
    let points: Vec<Point3<f64>> = match shape {
        "cube" => (0..n)
            .map(|_| Point3::new(rng.random::<f64>(), rng.random::<f64>(), rng.random::<f64>()) * 100.0)
            .collect(),
        "line" => (0..n)
            .map(|_| {
                let t = rng.random::<f64>() * 100.0;
                Point3::new(t, 0.01 * gauss(&mut rng), 0.01 * gauss(&mut rng))
            })
            .collect(),
        "duplicates" => {
            let mut c = scan_like_cloud(n, seed);
            for p in c.points.iter_mut().step_by(10) {
                *p = Point3::new(20.0, 20.0, 0.0);
            }
            c.points_f64()
        }
        other => return Err(format!("unknown --shape {other} (surface, cube, line, duplicates)").into()),
    };
    Ok(PointCloud::from_points(points))
}

/// Timing of `repeat` runs: best wall time and mean CPU time per run (ms).
struct Timing {
    best_ms: f64,
    cpu_ms: Option<f64>,
}

/// Times `repeat` runs of `statistical_outlier_removal` (the input clone not timed) and returns
/// the keep mask (from `statistical_outlier_mask`, the same rule, run once untimed).
fn time_sor(cloud: &PointCloud, k: usize, n_sigma: f64, repeat: u32) -> BoxResult<(Timing, Vec<bool>)> {
    let mut best_ms = f64::INFINITY;
    let mut cpu = 0.0;
    for _ in 0..repeat {
        let input = cloud.clone();
        let (c0, t) = (cpu_seconds(), Instant::now());
        let (out, report) = statistical_outlier_removal(input, k, n_sigma)?;
        let ms = t.elapsed().as_secs_f64() * 1e3;
        cpu += cpu_seconds().zip(c0).map_or(f64::NAN, |(b, a)| b - a);
        best_ms = best_ms.min(ms);
        assert_eq!(out.len(), report.kept);
    }
    let cpu_ms = Some(cpu * 1e3 / f64::from(repeat)).filter(|c| c.is_finite());
    let keep = statistical_outlier_mask(&cloud.points, k, n_sigma)?;
    Ok((Timing { best_ms, cpu_ms }, keep))
}

/// Reads an `(n, 3)` little-endian f64 C-order `.npy` (what `np.save` writes for such an array).
fn read_cloud_npy(path: &Path) -> BoxResult<PointCloud> {
    let mut bytes = Vec::new();
    std::fs::File::open(path)?.read_to_end(&mut bytes)?;
    if bytes.len() < 10 || &bytes[..6] != b"\x93NUMPY" {
        return Err(format!("{}: not a .npy file", path.display()).into());
    }
    let (header_len, data_at) = match bytes[6] {
        1 => (usize::from(u16::from_le_bytes([bytes[8], bytes[9]])), 10),
        _ => {
            let b = bytes.get(8..12).ok_or("truncated header")?;
            (u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize, 12)
        }
    };
    let header = std::str::from_utf8(bytes.get(data_at..data_at + header_len).ok_or("truncated header")?)?;
    if !header.contains("'<f8'") || header.contains("'fortran_order': True") {
        return Err(format!("{}: expected a C-order <f8 array, header {header}", path.display()).into());
    }
    let data = &bytes[data_at + header_len..];
    if data.len() % 24 != 0 {
        return Err(format!(
            "{}: {} data bytes is not a whole number of (x, y, z)",
            path.display(),
            data.len()
        )
        .into());
    }
    let f = |c: &[u8]| f64::from_le_bytes([c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]]);
    let points: Vec<Point3<f64>> =
        data.chunks_exact(24).map(|p| Point3::new(f(&p[0..8]), f(&p[8..16]), f(&p[16..24]))).collect();
    Ok(PointCloud::from_points(points))
}

fn script_path(args: &Args) -> PathBuf {
    if let Some(p) = &args.script {
        return p.clone();
    }
    let by_manifest = Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/compare_open3d.py");
    if by_manifest.exists() {
        return by_manifest;
    }
    // The bench source's own crate (when built from a scratch manifest that points at it).
    let src = Path::new(file!());
    src.parent()
        .and_then(Path::parent)
        .map_or(by_manifest.clone(), |crate_dir| crate_dir.join("scripts/compare_open3d.py"))
}

fn main() -> BoxResult<()> {
    let args = parse_args()?;
    let threads = rayon::current_num_threads();

    if let Some(cloud_path) = &args.cloud {
        let cloud = read_cloud_npy(cloud_path)?;
        let (timing, keep) = time_sor(&cloud, args.k, args.n_sigma, args.repeat)?;
        if let Some(out) = &args.keep_out {
            write_mask_npy(out, &keep)?;
        }
        println!("points={}", cloud.len());
        println!("threads={threads}");
        println!("sor_ms={:.3}", timing.best_ms);
        println!("sor_cpu_ms={:.0}", timing.cpu_ms.unwrap_or(f64::NAN));
        println!("kept={}", keep.iter().filter(|&&k| k).count());
        return Ok(());
    }

    let t = Instant::now();
    let cloud = match args.shape.as_str() {
        "surface" => scan_like_cloud(args.points, args.seed),
        other => other_cloud(other, args.points, args.seed)?,
    };
    println!(
        "cloud: {} points ({}), built in {:.0} ms",
        cloud.len(),
        if args.shape == "surface" {
            "wavy height field on a jittered 0.1 mm grid + 1 % outliers"
        } else {
            args.shape.as_str()
        },
        t.elapsed().as_secs_f64() * 1e3
    );
    let (timing, keep) = time_sor(&cloud, args.k, args.n_sigma, args.repeat)?;
    let ms = timing.best_ms;
    let kept = keep.iter().filter(|&&k| k).count();
    println!(
        "depthmill statistical_outlier_removal k={} n_sigma={}: best of {} = {:.1} ms ({:.2} Mpoints/s, {} rayon threads; \
         {:.0} ms CPU per run), kept {}, removed {}",
        args.k,
        args.n_sigma,
        args.repeat,
        ms,
        cloud.len() as f64 / ms / 1e3,
        threads,
        timing.cpu_ms.unwrap_or(f64::NAN),
        kept,
        cloud.len() - kept
    );
    if !args.open3d {
        return Ok(());
    }

    let dir = tempfile::tempdir()?;
    let cloud_path = dir.path().join("cloud.npy");
    let keep_path = dir.path().join("keep.npy");
    write_cloud_npy(&cloud_path, &cloud)?;
    write_mask_npy(&keep_path, &keep)?;
    let script = script_path(&args);
    let mut cmd = Command::new(&args.python);
    cmd.arg(&script)
        .arg("--cloud")
        .arg(&cloud_path)
        .arg("--keep")
        .arg(&keep_path)
        .args(["--k", &args.k.to_string(), "--n-sigma", &args.n_sigma.to_string()])
        .args(["--repeat", &args.repeat.to_string()]);
    let Some((stdout, code)) = run_reference(&mut cmd, &args.python) else {
        return Ok(());
    };
    match field(&stdout, "open3d_ms").and_then(|v| v.parse::<f64>().ok()) {
        Some(o3d_ms) => {
            println!(
                "open3d remove_statistical_outlier: best of {} = {:.1} ms; depthmill is {:.2}x faster (target >= 8x); \
                 mismatched points: {}",
                args.repeat,
                o3d_ms,
                o3d_ms / ms,
                field(&stdout, "mismatches").unwrap_or("?")
            );
            let o3d_cpu = field(&stdout, "open3d_cpu_ms").and_then(|v| v.parse::<f64>().ok());
            if let (Some(theirs), Some(ours)) = (o3d_cpu, timing.cpu_ms) {
                println!(
                    "CPU time per run: open3d {theirs:.0} ms, depthmill {ours:.0} ms, ratio {:.2}x",
                    theirs / ours
                );
            }
        }
        None => println!("open3d: no timing from {} (exit {:?})", script.display(), code),
    }
    Ok(())
}
