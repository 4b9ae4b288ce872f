//! Reader throughput: binary PLY (float and double), against `std::fs::read` of the same file
//! measured in the same run (page cache warm), plus ASCII XYZ.
//!
//! Run: `cargo bench --bench read_ply` (release). `DEPTHMILL_BENCH_POINTS` overrides the 10^7
//! points of the PLY files (the XYZ file has a tenth of them). Target: binary PLY at >= 500 MB/s.

use std::fs::File;
use std::hint::black_box;
use std::io::{BufWriter, Write};
use std::path::Path;
use std::time::{Duration, Instant};

use depthmill_geometry::PointCloud;
use depthmill_geometry::formats::{PlyEncoding, ReadLimits, read_any, write_ply};
use nalgebra::Point3;
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

const TARGET_MB_S: f64 = 500.0;

fn best_of_3<T>(mut f: impl FnMut() -> T) -> Duration {
    (0..3)
        .map(|_| {
            let t = Instant::now();
            black_box(f());
            t.elapsed()
        })
        .min()
        .unwrap_or_default()
}

fn mb_s(bytes: u64, t: Duration) -> f64 {
    bytes as f64 / 1e6 / t.as_secs_f64()
}

fn cloud(n: usize) -> PointCloud {
    let mut rng = StdRng::seed_from_u64(7);
    let points = (0..n)
        .map(|_| {
            Point3::new(
                rng.random_range(-150.0..150.0),
                rng.random_range(-150.0..150.0),
                rng.random_range(0.0..40.0),
            )
        })
        .collect();
    let intensity = Some((0..n).map(|_| rng.random_range(0.0..4096.0)).collect());
    PointCloud { points, intensity, normals: None }
}

fn write_double_ply(path: &Path, cloud: &PointCloud) -> std::io::Result<()> {
    let mut w = BufWriter::with_capacity(1 << 20, File::create(path)?);
    write!(
        w,
        "ply\nformat binary_little_endian 1.0\nelement vertex {}\nproperty double x\nproperty double y\n\
         property double z\nproperty float intensity\nend_header\n",
        cloud.len()
    )?;
    let intensity = cloud.intensity.as_deref().unwrap_or_default();
    for (p, i) in cloud.points.iter().zip(intensity) {
        for c in [p.x, p.y, p.z] {
            w.write_all(&c.to_le_bytes())?;
        }
        w.write_all(&i.to_le_bytes())?;
    }
    w.flush()
}

fn write_xyz(path: &Path, cloud: &PointCloud, n: usize) -> std::io::Result<()> {
    let mut w = BufWriter::with_capacity(1 << 20, File::create(path)?);
    writeln!(w, "# x y z intensity")?;
    let intensity = cloud.intensity.as_deref().unwrap_or_default();
    for (p, i) in cloud.points.iter().zip(intensity).take(n) {
        writeln!(w, "{:.4} {:.4} {:.4} {:.1}", p.x, p.y, p.z, i)?;
    }
    w.flush()
}

/// Measures `std::fs::read` and `read_any` on `path`; returns read_any's MB/s.
fn measure(label: &str, path: &Path, points: u64, target: bool) -> f64 {
    let bytes = std::fs::metadata(path).map(|m| m.len()).unwrap_or(0);
    let _ = std::fs::read(path); // warm the page cache
    let base = best_of_3(|| std::fs::read(path).map(|v| v.len()).unwrap_or(0));
    let limits = ReadLimits::default();
    let mut got = 0;
    let read = best_of_3(|| match read_any(path, &limits) {
        Ok((_, stats)) => got = stats.points,
        Err(e) => panic!("{label}: {e}"),
    });
    assert_eq!(got, points, "{label}: points read");
    let (base_mb, read_mb) = (mb_s(bytes, base), mb_s(bytes, read));
    println!(
        "{label}: {:.1} MB, {points} points\n  reference std::fs::read: {base_mb:.0} MB/s ({:.1} ms)\n  \
         read_any: {read_mb:.0} MB/s ({:.1} ms), {:.1} M points/s, {:.2} x the reference",
        bytes as f64 / 1e6,
        base.as_secs_f64() * 1e3,
        read.as_secs_f64() * 1e3,
        points as f64 / 1e6 / read.as_secs_f64(),
        read_mb / base_mb,
    );
    if target {
        let verdict = if read_mb >= TARGET_MB_S { "met" } else { "NOT met" };
        println!("  target >= {TARGET_MB_S:.0} MB/s: {verdict}");
    }
    read_mb
}

fn main() -> std::io::Result<()> {
    let n: usize =
        std::env::var("DEPTHMILL_BENCH_POINTS").ok().and_then(|v| v.parse().ok()).unwrap_or(10_000_000);
    let dir = tempfile::tempdir()?;
    let cloud = cloud(n);

    let float_ply = dir.path().join("float.ply");
    let t = Instant::now();
    let w = BufWriter::with_capacity(1 << 20, File::create(&float_ply)?);
    write_ply(w, &cloud, None, PlyEncoding::BinaryLittleEndian, &[]).map_err(std::io::Error::other)?;
    let written = std::fs::metadata(&float_ply)?.len();
    println!("write_ply (binary LE, float xyz + intensity): {:.0} MB/s", mb_s(written, t.elapsed()));
    measure("binary LE PLY, float x y z intensity", &float_ply, n as u64, true);
    std::fs::remove_file(&float_ply)?;

    let double_ply = dir.path().join("double.ply");
    write_double_ply(&double_ply, &cloud)?;
    measure("binary LE PLY, double x y z + float intensity", &double_ply, n as u64, true);
    std::fs::remove_file(&double_ply)?;

    let xyz = dir.path().join("cloud.xyz");
    let nx = (n / 10).max(1);
    write_xyz(&xyz, &cloud, nx)?;
    measure("ASCII XYZ, x y z intensity", &xyz, nx as u64, false);
    Ok(())
}
