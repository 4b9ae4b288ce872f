//! The table as the seventh joint against the fixed table angles, on the demo relief and on
//! meshes of other shapes: the plan's worst posture (seed 002's criteria: dexterity, distances
//! from the wrist, elbow and shoulder singularities and from the joint limits), the passes
//! reached, the coverage of the first scan, the simulated scan time and the table's moves.
//!
//! Run: `cargo bench -p depthmill-scanning --bench redundancy` (harness = false, prints a table).
//! More meshes: `DEPTHMILL_PARTS_DIR=target/parts` (tests/parts/fetch.sh) adds every `mesh-*.stl`
//! there, scaled so its largest side is 120 mm.

use depthmill_geometry::Mesh;
use depthmill_geometry::formats::{ReadLimits, read_mesh};
use depthmill_scanning::domain::scan::{CellLayout, ScanOptions, ScanSession};
use nalgebra::{Point3, Vector3};

struct Row {
    stations: usize,
    offsets: Vec<f64>,
    passes: usize,
    skipped: usize,
    quality: f64,
    dexterity: f64,
    wrist: f64,
    elbow: f64,
    shoulder: f64,
    limit: f64,
    coverage: f64,
    scan_s: f64,
    table_deg: f64,
    table_s: f64,
    peak_speed: f64,
}

fn run(mesh: &Mesh, search: f64) -> Result<Row, String> {
    let opts = ScanOptions { table_search_deg: search, line_spacing_mm: 0.5, ..ScanOptions::default() };
    let mut s = ScanSession::new(mesh, opts, CellLayout::default()).map_err(|e| e.to_string())?;
    let plan = s.plan().map_err(|e| e.to_string())?;
    for st in &plan.stations {
        s.run_station(st, st.table_deg, false, &mut |_, _| {}, &|| false).map_err(|e| e.to_string())?;
    }
    let (cov, _) = s.holes().map_err(|e| e.to_string())?;
    let out = s.finish();
    let passes: Vec<_> = out.report.stations.iter().flat_map(|s| &s.passes).collect();
    let min = |f: &dyn Fn(&&depthmill_scanning::domain::scan::PassReport) -> f64| {
        passes.iter().map(f).fold(f64::INFINITY, f64::min)
    };
    let moves: Vec<_> = out.report.stations.iter().filter_map(|s| s.table_move).collect();
    Ok(Row {
        stations: plan.stations.len(),
        offsets: plan.stations.iter().map(|s| s.table_offset_deg).collect(),
        passes: plan.passes(),
        skipped: plan.skipped.len(),
        quality: min(&|p| p.quality),
        dexterity: min(&|p| p.min_dexterity),
        wrist: min(&|p| p.min_margins.wrist_deg),
        elbow: min(&|p| p.min_margins.elbow_deg),
        shoulder: min(&|p| p.min_margins.shoulder_mm),
        limit: min(&|p| p.min_limit_margin_deg),
        coverage: cov.covered_pct,
        scan_s: out.report.scan_time_s,
        table_deg: moves.iter().map(|m| m.turn_deg.abs()).sum(),
        table_s: moves.iter().map(|m| m.time_s).sum(),
        peak_speed: moves.iter().map(|m| m.peak_speed_deg_s).fold(0.0, f64::max),
    })
}

/// The mesh centred on the table, its base on the top, scaled so its largest side is `size`.
fn fit(mut m: Mesh, size: f64) -> Mesh {
    let (mut lo, mut hi) = (Vector3::repeat(f64::INFINITY), Vector3::repeat(f64::NEG_INFINITY));
    for v in &m.vertices {
        lo = lo.inf(&v.coords);
        hi = hi.sup(&v.coords);
    }
    let k = size / (hi - lo).max().max(1e-9);
    let c = Vector3::new(0.5 * (lo.x + hi.x), 0.5 * (lo.y + hi.y), lo.z);
    for v in &mut m.vertices {
        *v = Point3::from((v.coords - c) * k);
    }
    m
}

fn main() {
    let relief = depthmill_geometry::sample::sample_relief(0.5);
    let mut parts: Vec<(String, Mesh)> = vec![("demo relief".into(), relief.clone())];
    // The same relief larger: its far passes towards the edge of the arm's reach.
    for k in [2.0, 2.6] {
        parts.push((
            format!("relief x{k}"),
            Mesh {
                vertices: relief.vertices.iter().map(|v| Point3::from(v.coords * k)).collect(),
                triangles: relief.triangles.clone(),
            },
        ));
    }
    if let Ok(dir) = std::env::var("DEPTHMILL_PARTS_DIR") {
        let mut files: Vec<_> =
            std::fs::read_dir(&dir).map(|d| d.flatten().map(|e| e.path()).collect()).unwrap_or_default();
        files.sort();
        for f in files {
            let name = f.file_name().map(|n| n.to_string_lossy().to_string()).unwrap_or_default();
            if !(name.starts_with("mesh-") && name.ends_with(".stl")) {
                continue;
            }
            match read_mesh(&f, &ReadLimits::default()) {
                Ok((m, _)) => parts.push((format!("{name} (120 mm)"), fit(m, 120.0))),
                Err(e) => eprintln!("{name}: {e}"),
            }
        }
    }
    println!(
        "{:<28} {:<8} {:>5} {:>5} {:>7} {:>9} {:>7} {:>7} {:>8} {:>7} {:>7} {:>7} {:>7} {:>7} {:>7}  offsets",
        "part",
        "table",
        "pass",
        "skip",
        "worst",
        "dex",
        "wrist",
        "elbow",
        "shoulder",
        "limits",
        "cover%",
        "scan s",
        "turn°",
        "table s",
        "peak°/s"
    );
    for (name, mesh) in &parts {
        for (label, search) in [("fixed", 0.0), ("7-dof", 30.0)] {
            match run(mesh, search) {
                Ok(r) => println!(
                    "{:<28} {:<8} {:>5} {:>5} {:>7.3} {:>9.3e} {:>7.1} {:>7.1} {:>8.1} {:>7.1} {:>7.2} {:>7.1} {:>7.1} {:>7.2} {:>7.1}  {:?} ({} stations)",
                    name,
                    label,
                    r.passes,
                    r.skipped,
                    r.quality,
                    r.dexterity,
                    r.wrist,
                    r.elbow,
                    r.shoulder,
                    r.limit,
                    r.coverage,
                    r.scan_s,
                    r.table_deg,
                    r.table_s,
                    r.peak_speed,
                    r.offsets,
                    r.stations
                ),
                Err(e) => println!("{name:<28} {label:<8} failed: {e}"),
            }
        }
    }
}
