//! What the reconstruction benches share: the scanned-like test cloud, CPU time, `.npy` output.

#![allow(dead_code)] // each bench uses its part

use std::io::{BufWriter, Write};
use std::path::Path;
use std::process::Command;

use depthmill_geometry::PointCloud;
use nalgebra::Point3;
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

pub type BoxResult<T> = Result<T, Box<dyn std::error::Error>>;

/// Standard normal sample (Box–Muller).
pub fn gauss(rng: &mut StdRng) -> f64 {
    let u1 = 1.0 - rng.random::<f64>();
    let u2 = rng.random::<f64>();
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}

/// A wavy height field on a jittered 0.1 mm grid (10 µm noise) plus 1 % outliers in its box
/// widened by 5 mm.
pub fn scan_like_cloud(n: usize, seed: u64) -> PointCloud {
    let mut rng = StdRng::seed_from_u64(seed);
    let outliers = n / 100;
    let surface = n - outliers;
    let side = (surface as f64).sqrt().ceil() as usize;
    let pitch = 0.1;
    let mut points = Vec::with_capacity(n);
    'rows: for r in 0..side {
        for c in 0..side {
            if points.len() == surface {
                break 'rows;
            }
            let x = (c as f64 + 0.5) * pitch + rng.random_range(-0.03..0.03);
            let y = (r as f64 + 0.5) * pitch + rng.random_range(-0.03..0.03);
            let z = 2.0 * (x * 0.1).sin() * (y * 0.13).cos()
                + 0.4 * (x * 0.9 + y * 0.4).sin()
                + 0.01 * gauss(&mut rng);
            points.push(Point3::new(x, y, z));
        }
    }
    let extent = side as f64 * pitch;
    for _ in 0..outliers {
        points.push(Point3::new(
            rng.random_range(-5.0..extent + 5.0),
            rng.random_range(-5.0..extent + 5.0),
            rng.random_range(-7.5..7.5),
        ));
    }
    PointCloud::from_points(points)
}

/// CPU time of this process so far (all threads, user + system), from `/proc/self/stat`
/// (clock ticks of 1/100 s, Linux's fixed USER_HZ); `None` elsewhere.
pub fn cpu_seconds() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    let mut fields = stat.rsplit_once(')')?.1.split_whitespace();
    let utime: f64 = fields.nth(11)?.parse().ok()?;
    let stime: f64 = fields.next()?.parse().ok()?;
    Some((utime + stime) / 100.0)
}

pub fn npy_header(descr: &str, shape: &str) -> Vec<u8> {
    let mut dict = format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape}, }}");
    while (10 + dict.len() + 1) % 64 != 0 {
        dict.push(' ');
    }
    dict.push('\n');
    let mut out = b"\x93NUMPY\x01\x00".to_vec();
    out.extend_from_slice(&(dict.len() as u16).to_le_bytes());
    out.extend_from_slice(dict.as_bytes());
    out
}

pub fn write_cloud_npy(path: &Path, cloud: &PointCloud) -> BoxResult<()> {
    let mut w = BufWriter::new(std::fs::File::create(path)?);
    w.write_all(&npy_header("<f8", &format!("({}, 3)", cloud.len())))?;
    for p in &cloud.points {
        // The cloud's single-precision coordinates, widened exactly.
        for c in [p.x, p.y, p.z].map(f64::from) {
            w.write_all(&c.to_le_bytes())?;
        }
    }
    w.flush()?;
    Ok(())
}

pub fn write_mask_npy(path: &Path, keep: &[bool]) -> BoxResult<()> {
    let mut w = BufWriter::new(std::fs::File::create(path)?);
    w.write_all(&npy_header("|b1", &format!("({},)", keep.len())))?;
    w.write_all(&keep.iter().map(|&k| u8::from(k)).collect::<Vec<_>>())?;
    w.flush()?;
    Ok(())
}

/// Runs a reference script (`cmd`, through the interpreter `python`) and echoes its standard
/// output indented. `None`, with the reason printed, when the interpreter cannot be started or
/// the script says its modules are missing (exit status 3); its standard error is printed when it
/// fails otherwise. Returns the standard output and the exit status.
pub fn run_reference(cmd: &mut Command, python: &str) -> Option<(String, Option<i32>)> {
    let output = match cmd.output() {
        Ok(o) => o,
        Err(e) => {
            println!("open3d: cannot run {python} ({e}); skipped");
            return None;
        }
    };
    let stdout = String::from_utf8_lossy(&output.stdout).into_owned();
    for line in stdout.lines() {
        println!("  | {line}");
    }
    if output.status.code() == Some(3) {
        println!("open3d: not importable by {python}; install with `{python} -m pip install open3d numpy`");
        return None;
    }
    if !output.status.success() {
        print!("{}", String::from_utf8_lossy(&output.stderr));
    }
    Some((stdout, output.status.code()))
}

/// The value of a `key=value` line of a script's output.
pub fn field<'a>(out: &'a str, key: &str) -> Option<&'a str> {
    out.lines().find_map(|l| l.trim().strip_prefix(key)?.strip_prefix('='))
}
