//! Point-to-plane ICP speed and accuracy against Open3D's `registration_icp` on the same clouds in
//! the same run (through `scripts/compare_open3d_icp.py`).
//!
//! ```text
//! cargo bench -p depthmill-geometry --bench icp -- [--target-points 200000] [--source-points 100000]
//!     [--noise 0.035] [--max-corr 2.0] [--tukey 0.1] [--normal-k 20] [--repeat 3] [--seed 5]
//!     [--python python3] [--no-open3d]
//! ```
//!
//! Two partial scans of one part: a 100 x 100 mm relief (waves, a dome, a step) sampled like a
//! laser scan with `--noise` mm of noise; the source covers a region shifted 30 mm from the
//! target's (about 70 % overlap) and is misplaced by 1.2° and 0.9 mm. Times the target's normals
//! (PCA over `--normal-k` nearest points) and the ICP from the identity, best of `--repeat`, for
//! depthmill and Open3D (TukeyLoss of the same width, the same convergence rule), and measures both
//! results the same way: the error against the true transform (translation at the source's
//! centre, rotation) and the RMS distance of the source's points to their nearest target points.

use std::io::{BufWriter, Write};
use std::path::Path;
use std::process::Command;
use std::time::Instant;

use depthmill_geometry::icp::{IcpOptions, Kernel, Target, icp};
use nalgebra::{Isometry3, Matrix4, Point3, Translation3, UnitQuaternion, Vector3};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

mod support;

use support::{BoxResult, arg, gauss};

fn relief(x: f64, y: f64) -> f64 {
    let waves = 3.0 * (x / 11.0).sin() * (y / 17.0).cos();
    let dome = 6.0 * (-((x - 10.0).powi(2) + (y + 5.0).powi(2)) / 300.0).exp();
    let step = if x > 25.0 && y < -10.0 { 4.0 } else { 0.0 };
    waves + dome + step + 0.0004 * x * y
}

fn scan(rng: &mut StdRng, n: usize, x0: f64, noise: f64) -> Vec<Point3<f64>> {
    (0..n)
        .map(|_| {
            let (x, y) = (rng.random_range(x0 - 50.0..x0 + 50.0), rng.random_range(-50.0..50.0));
            Point3::new(x, y, relief(x, y) + noise * gauss(rng))
        })
        .collect()
}

fn npy(path: &Path, pts: &[Point3<f64>]) -> BoxResult<()> {
    let mut dict = format!("{{'descr': '<f8', 'fortran_order': False, 'shape': ({}, 3), }}", pts.len());
    while (10 + dict.len() + 1) % 64 != 0 {
        dict.push(' ');
    }
    dict.push('\n');
    let mut w = BufWriter::new(std::fs::File::create(path)?);
    w.write_all(b"\x93NUMPY\x01\x00")?;
    w.write_all(&(dict.len() as u16).to_le_bytes())?;
    w.write_all(dict.as_bytes())?;
    for p in pts {
        for c in [p.x, p.y, p.z] {
            w.write_all(&c.to_le_bytes())?;
        }
    }
    w.flush()?;
    Ok(())
}

/// Error of `got` against `truth`: translation at `at` (mm) and rotation (degrees).
fn error(got: &Isometry3<f64>, truth: &Isometry3<f64>, at: &Point3<f64>) -> (f64, f64) {
    ((got * at - truth * at).norm(), got.rotation.angle_to(&truth.rotation).to_degrees())
}

/// RMS distance of the moved source points to their nearest target points within `max`.
fn nn_rms(source: &[Point3<f64>], target: &Target, t: &Isometry3<f64>, max: f64) -> (f64, f64) {
    let (mut sq, mut n) = (0.0, 0usize);
    for p in source {
        if let Some((_, d2)) = target.nearest_within(&(t * p), max) {
            sq += d2;
            n += 1;
        }
    }
    ((sq / n.max(1) as f64).sqrt(), n as f64 / source.len() as f64)
}

fn main() -> BoxResult<()> {
    let args: Vec<String> = std::env::args().collect();
    let (nt, ns) = (arg(&args, "--target-points", 200_000usize), arg(&args, "--source-points", 100_000usize));
    let noise = arg(&args, "--noise", 0.035);
    let max_corr = arg(&args, "--max-corr", 2.0);
    let tukey = arg(&args, "--tukey", 0.1);
    let normal_k = arg(&args, "--normal-k", 20usize);
    let repeat = arg(&args, "--repeat", 3u32).max(1);
    let seed = arg(&args, "--seed", 5u64);
    let python = arg(&args, "--python", "python3".to_string());
    let mut rng = StdRng::seed_from_u64(seed);
    let target_pts = scan(&mut rng, nt, 0.0, noise);
    let truth = Isometry3::from_parts(
        Translation3::new(0.6, -0.5, 0.4),
        UnitQuaternion::from_scaled_axis(Vector3::new(0.3, -0.5, 1.0).normalize() * 1.2f64.to_radians()),
    );
    let source: Vec<Point3<f64>> =
        scan(&mut rng, ns, 30.0, noise).iter().map(|p| truth.inverse() * p).collect();
    let centre =
        Point3::from(source.iter().fold(Vector3::zeros(), |a, p| a + p.coords) / source.len() as f64);
    let opts =
        IcpOptions { max_correspondence_mm: max_corr, kernel: Kernel::Tukey(tukey), ..Default::default() };

    let (mut normals_ms, mut icp_ms) = (f64::INFINITY, f64::INFINITY);
    let mut ours = None;
    let mut target = None;
    for _ in 0..repeat {
        let t0 = Instant::now();
        let t = Target::new(target_pts.clone(), normal_k)?;
        normals_ms = normals_ms.min(t0.elapsed().as_secs_f64() * 1e3);
        let t1 = Instant::now();
        let r = icp(&source, &t, &Isometry3::identity(), &opts)?;
        icp_ms = icp_ms.min(t1.elapsed().as_secs_f64() * 1e3);
        ours = Some(r);
        target = Some(t);
    }
    let (Some(ours), Some(target)) = (ours, target) else { return Err("no run".into()) };
    let (et, ea) = error(&ours.transform, &truth, &centre);
    let (rms, fit) = nn_rms(&source, &target, &ours.transform, max_corr);
    println!(
        "clouds: target {nt} points, source {ns} points, noise {noise} mm, misplaced 1.2° / 0.9 mm; Tukey {tukey} mm, max correspondence {max_corr} mm, normals from {normal_k} nearest"
    );
    println!(
        "depthmill: normals {normals_ms:.1} ms, icp {icp_ms:.1} ms ({} iterations); error {et:.4} mm {ea:.5}°; fitness {fit:.4}, nearest-point RMS {rms:.5} mm, plane RMS {:.5} mm",
        ours.iterations, ours.plane_rmse_mm
    );
    if args.iter().any(|a| a == "--no-open3d") {
        return Ok(());
    }
    let dir = std::env::temp_dir().join(format!("depthmill-icp-{}", std::process::id()));
    std::fs::create_dir_all(&dir)?;
    let (sp, tp) = (dir.join("source.npy"), dir.join("target.npy"));
    npy(&sp, &source)?;
    npy(&tp, &target_pts)?;
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/compare_open3d_icp.py");
    let out = Command::new(&python)
        .arg(&script)
        .args(["--source", &sp.to_string_lossy(), "--target", &tp.to_string_lossy()])
        .args(["--max-corr", &max_corr.to_string(), "--tukey", &tukey.to_string()])
        .args(["--normal-k", &normal_k.to_string(), "--max-iter", "30", "--repeat", &repeat.to_string()])
        .output()?;
    let _ = std::fs::remove_dir_all(&dir);
    let text = String::from_utf8_lossy(&out.stdout).to_string();
    if !out.status.success() {
        println!(
            "open3d: not run ({}); python3 -m pip install open3d numpy",
            String::from_utf8_lossy(&out.stderr).trim()
        );
        return Ok(());
    }
    let field =
        |name: &str| text.lines().find_map(|l| l.strip_prefix(&format!("{name}="))).map(str::to_string);
    let num = |name: &str| field(name).and_then(|v| v.parse::<f64>().ok()).unwrap_or(f64::NAN);
    let m: Vec<f64> =
        field("transform").unwrap_or_default().split(',').filter_map(|v| v.parse().ok()).collect();
    if m.len() != 16 {
        return Err(format!("open3d printed no transform: {text}").into());
    }
    let m4 = Matrix4::from_row_slice(&m);
    let rot = nalgebra::Rotation3::from_matrix(&m4.fixed_view::<3, 3>(0, 0).into_owned());
    let theirs = Isometry3::from_parts(
        Translation3::new(m4[(0, 3)], m4[(1, 3)], m4[(2, 3)]),
        UnitQuaternion::from_rotation_matrix(&rot),
    );
    let (ot, oa) = error(&theirs, &truth, &centre);
    let (orms, ofit) = nn_rms(&source, &target, &theirs, max_corr);
    let (on, oi) = (num("normals_ms"), num("icp_ms"));
    println!(
        "open3d:    normals {on:.1} ms, icp {oi:.1} ms; error {ot:.4} mm {oa:.5}°; fitness {ofit:.4}, nearest-point RMS {orms:.5} mm (its own inlier_rmse {:.5})",
        num("inlier_rmse")
    );
    println!(
        "speed-up: normals x{:.2}, icp x{:.2}, both x{:.2}; nearest-point RMS depthmill/open3d {:.4}",
        on / normals_ms,
        oi / icp_ms,
        (on + oi) / (normals_ms + icp_ms),
        rms / orms
    );
    Ok(())
}
