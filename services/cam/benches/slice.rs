//! Slicing a 1M-triangle mesh into 200 layers (`cargo bench -p depthmill-cam --bench slice`).
//!
//! The mesh: a torus (R 40 mm, r 15 mm, 1000 x 500 sections = 10^6 triangles) tilted 30° about
//! X, so layers cut it into one or two rings or two separate loops. It is written as binary STL
//! and read back (STL holds f32 coordinates; the reader welds the corners), so what is sliced is
//! exactly what another tool reading the file gets. Layers: 200 heights evenly inside the mesh's
//! Z range. Prints the time of [`slice`] (best of 3) and of the every-triangle reference
//! (once, unless `--no-reference`), and checks both agree.
//!
//! `-- --out DIR` keeps `DIR/mesh.stl`, `DIR/levels.txt` and `DIR/ours.json` (every layer's
//! closed contours) for `services/cam/scripts/compare_trimesh.py`, which times trimesh's
//! `section_multiplane` on the same file and compares the contours.

use std::fs::File;
use std::io::{BufReader, BufWriter, Write};
use std::path::PathBuf;
use std::time::Instant;

use depthmill_cam::domain::slice::{Layer, slice, slice_reference, topology};
use depthmill_geometry::Mesh;
use depthmill_geometry::formats::{ReadLimits, read_stl_from, write_stl};
use depthmill_geometry::nalgebra::{Point3, Rotation3, Vector3};

fn torus(nu: usize, nv: usize, big: f64, small: f64, tilt_deg: f64) -> Mesh {
    use std::f64::consts::TAU;
    let rot = Rotation3::from_axis_angle(&Vector3::x_axis(), tilt_deg.to_radians());
    let mut v = Vec::with_capacity(nu * nv);
    for i in 0..nu {
        for j in 0..nv {
            let (u, w) = (TAU * i as f64 / nu as f64, TAU * j as f64 / nv as f64);
            let r = big + small * w.cos();
            v.push(rot * Point3::new(r * u.cos(), r * u.sin(), small * w.sin()));
        }
    }
    let id = |i: usize, j: usize| ((i % nu) * nv + (j % nv)) as u32;
    let mut t = Vec::with_capacity(2 * nu * nv);
    for i in 0..nu {
        for j in 0..nv {
            t.push([id(i, j), id(i + 1, j), id(i + 1, j + 1)]);
            t.push([id(i, j), id(i + 1, j + 1), id(i, j + 1)]);
        }
    }
    Mesh { vertices: v, triangles: t }
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut out: Option<PathBuf> = None;
    let mut reference = true;
    let mut it = std::env::args().skip(1);
    while let Some(a) = it.next() {
        match a.as_str() {
            "--out" => out = it.next().map(PathBuf::from),
            "--no-reference" => reference = false,
            "--bench" => {}
            other => return Err(format!("unknown argument {other}").into()),
        }
    }
    let dir = out
        .clone()
        .unwrap_or_else(|| std::env::temp_dir().join(format!("depthmill-slice-{}", std::process::id())));
    std::fs::create_dir_all(&dir)?;
    let stl = dir.join("mesh.stl");
    {
        let m = torus(1000, 500, 40.0, 15.0, 30.0);
        let mut w = BufWriter::new(File::create(&stl)?);
        write_stl(&mut w, &m, "depthmill slicing benchmark: tilted torus")?;
        w.flush()?;
    }
    let size = std::fs::metadata(&stl)?.len();
    let (mesh, _) =
        read_stl_from(BufReader::new(File::open(&stl)?), "mesh.stl", Some(size), &ReadLimits::default())?;
    let topo = topology(&mesh);
    let (zmin, zmax) =
        mesh.vertices.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), p| (a.min(p.z), b.max(p.z)));
    let n = 200;
    let levels: Vec<f64> = (0..n).map(|i| zmin + (zmax - zmin) * (i as f64 + 0.5) / n as f64).collect();
    println!(
        "slicing benchmark: {} triangles, {} vertices (closed 2-manifold: {}), {n} layers over z {zmin:.3}..{zmax:.3} mm; {} rayon threads",
        mesh.triangles.len(),
        mesh.vertices.len(),
        topo.is_closed_manifold(),
        rayon::current_num_threads()
    );
    let mut best = f64::INFINITY;
    let mut layers: Vec<Layer> = Vec::new();
    for _ in 0..3 {
        let t = Instant::now();
        layers = slice(&mesh, &levels)?;
        best = best.min(t.elapsed().as_secs_f64());
    }
    let contours: usize = layers.iter().map(|l| l.contours.len()).sum();
    let points: usize = layers.iter().flat_map(|l| &l.contours).map(|c| c.points.len()).sum();
    let problems: usize = layers.iter().map(|l| l.open.len() + l.defects.len()).sum();
    println!(
        "slice: {best:.3} s (best of 3): {contours} closed contours, {points} points, {problems} open chains or defects"
    );
    if reference {
        let t = Instant::now();
        let slow = slice_reference(&mesh, &levels)?;
        let ts = t.elapsed().as_secs_f64();
        println!(
            "every-triangle reference: {ts:.3} s ({:.1}x slower); results equal: {}",
            ts / best,
            slow == layers
        );
    }
    if out.is_some() {
        std::fs::write(
            dir.join("levels.txt"),
            levels.iter().map(|z| format!("{z:.17e}\n")).collect::<String>(),
        )?;
        let mut w = BufWriter::new(File::create(dir.join("ours.json"))?);
        serde_json::to_writer(
            &mut w,
            &layers
                .iter()
                .map(|l| l.contours.iter().map(|c| &c.points).collect::<Vec<_>>())
                .collect::<Vec<_>>(),
        )?;
        w.flush()?;
        println!("kept {}", dir.display());
    } else {
        let _ = std::fs::remove_dir_all(&dir);
    }
    Ok(())
}
