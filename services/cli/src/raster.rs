//! `depthmill raster`: a point cloud or mesh to depth maps on local files, no server.

use std::path::{Path, PathBuf};

use anyhow::{Context as _, bail};
use depthmill_geometry::formats::{ReadLimits, read_any};
use depthmill_geometry::{HeightMap, HeightMapFormat};
use depthmill_reconstruction::domain::pipeline::{FaceOptions, FillOptions, ReconstructOptions, reconstruct};

/// Options of `depthmill raster` besides the input and output.
#[derive(clap::Args, Clone)]
pub struct RasterArgs {
    /// Pixel size, mm (default 0.1).
    #[arg(long)]
    pub pixel_mm: Option<f64>,
    /// Face: +Z, -Z, +X, -X, +Y, -Y, A=<deg> or N=<x>,<y>,<z>; repeat for several faces.
    #[arg(long, allow_hyphen_values = true)]
    pub face: Vec<String>,
    /// Length unit of the input: auto (default; the header, else metres under 2 units across,
    /// else mm), mm, m or in. The maps are in millimetres.
    #[arg(long)]
    pub units: Option<String>,
    /// Fill method: idw or max.
    #[arg(long)]
    pub fill: Option<String>,
    /// Largest hole filled, mm (0: no filling).
    #[arg(long)]
    pub max_hole_mm: Option<f64>,
    /// The job's "reconstruct" object as JSON (roi, margin_mm, z range, filters, ...); the flags
    /// above override its fields.
    #[arg(long)]
    pub options: Option<PathBuf>,
}

fn face_options(text: &str) -> anyhow::Result<FaceOptions> {
    let face: depthmill_geometry::Face = text.parse()?;
    Ok(match face {
        depthmill_geometry::Face::A { angle_deg } => {
            FaceOptions { a_deg: Some(angle_deg), ..Default::default() }
        }
        depthmill_geometry::Face::Normal { x, y, z } => {
            FaceOptions { normal: Some([x, y, z]), ..Default::default() }
        }
        named => FaceOptions { view: Some(named.to_string()), ..Default::default() },
    })
}

fn sibling(output: &Path, suffix: &str, ext: &str) -> PathBuf {
    let stem = output.file_stem().and_then(|s| s.to_str()).unwrap_or("map");
    output.with_file_name(format!("{stem}{suffix}.{ext}"))
}

fn write(map: &HeightMap, path: &Path) -> anyhow::Result<()> {
    let format = HeightMapFormat::from_path(path)?;
    map.write(path, format).with_context(|| format!("writing {}", path.display()))
}

/// `depthmill raster`. Writes OUTPUT (the filled depth map; with several faces OUTPUT is the
/// first and the others get `.face<i>` suffixes), `<stem>.coverage.png`, `<stem>.roughing.<ext>`
/// and `<stem>.report.json`; prints the coverage statistics.
pub fn run(input: &Path, args: &RasterArgs, output: &Path) -> anyhow::Result<()> {
    let ext = match HeightMapFormat::from_path(output)? {
        HeightMapFormat::Png8 | HeightMapFormat::Png16 => "png",
        HeightMapFormat::Npy => "npy",
    };
    let mut opts: ReconstructOptions = match &args.options {
        Some(p) => {
            let text = std::fs::read_to_string(p).with_context(|| format!("reading {}", p.display()))?;
            let de = &mut serde_json::Deserializer::from_str(&text);
            serde_path_to_error::deserialize(de)
                .map_err(|e| anyhow::anyhow!("{}: field '{}': {}", p.display(), e.path(), e.inner()))?
        }
        None => ReconstructOptions::default(),
    };
    if args.pixel_mm.is_some() {
        opts.pixel_mm = args.pixel_mm;
    }
    if !args.face.is_empty() {
        opts.faces = Some(args.face.iter().map(|f| face_options(f)).collect::<anyhow::Result<_>>()?);
    }
    if args.fill.is_some() || args.max_hole_mm.is_some() {
        let fill = opts.fill.get_or_insert_with(FillOptions::default);
        if args.fill.is_some() {
            fill.method = args.fill.clone();
        }
        if args.max_hole_mm.is_some() {
            fill.max_hole_mm = args.max_hole_mm;
        }
    }
    opts.resolve()?;
    let started = std::time::Instant::now();
    let (mut geometry, stats) = read_any(input, &ReadLimits::default())?;
    let units = match args.units.as_deref() {
        None | Some("auto") => depthmill_geometry::Units::Auto,
        Some(u) => depthmill_geometry::Units::Given(
            depthmill_geometry::LengthUnit::parse(u)
                .with_context(|| format!("--units {u}: expected auto, mm, m or in"))?,
        ),
    };
    let head = depthmill_geometry::units::read_head(input)
        .with_context(|| format!("reading {}", input.display()))?;
    if let Some(d) = depthmill_geometry::units::normalise(&mut geometry, &head, units) {
        crate::outln!("{}: read in {} ({}: {})", input.display(), d.unit, d.source, d.reason);
        if let Some(w) = &d.warning {
            crate::outln!("{}: {w}", input.display());
        }
    }
    let read_s = started.elapsed().as_secs_f64();
    let progress = |_: f64, _: &str| {};
    let never = || false;
    let out = reconstruct(geometry, &opts, &progress, &never)?;
    if out.faces.is_empty() {
        bail!("no face produced");
    }
    if let Some(dir) = output.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    for (i, f) in out.faces.iter().enumerate() {
        let main = if i == 0 { output.to_path_buf() } else { sibling(output, &format!(".face{i}"), ext) };
        write(&f.depth_map, &main)?;
        let cov = sibling(&main, ".coverage", "png");
        f.coverage_map
            .write(&cov, HeightMapFormat::Png8)
            .with_context(|| format!("writing {}", cov.display()))?;
        write(&f.roughing_map, &sibling(&main, ".roughing", ext))?;
        let s = &f.stats;
        let hole = |h: Option<&depthmill_geometry::raster::HoleStats>| {
            h.map_or("none".to_string(), |h| {
                format!("{:.2} mm² at ({:.2}, {:.2})", h.area_mm2, h.center_x_mm, h.center_y_mm)
            })
        };
        crate::outln!(
            "{}: face {}, {}x{} at {} mm, z {:.3}..{:.3} mm, covered {:.2} %, {} cells filled, {} holes (largest {}), {} still empty (largest {})",
            main.display(),
            s.face,
            s.width,
            s.height,
            s.pixel_mm,
            s.z_min_mm,
            s.z_max_mm,
            s.coverage.covered_pct,
            s.fill.filled,
            s.coverage.holes,
            hole(s.coverage.largest_hole.as_ref()),
            s.coverage.unfilled_holes,
            hole(s.coverage.largest_unfilled_hole.as_ref()),
        );
    }
    let report_path = sibling(output, ".report", "json");
    let json = serde_json::json!({ "read": {
            "points": stats.points, "dropped_non_finite": stats.dropped_non_finite,
            "triangles": stats.triangles, "bytes": stats.bytes, "seconds": read_s },
        "reconstruct": out.report });
    std::fs::write(&report_path, serde_json::to_vec_pretty(&json)?)
        .with_context(|| format!("writing {}", report_path.display()))?;
    crate::outln!(
        "read {} points{} in {read_s:.2} s; kept {} after filters; report {}",
        stats.points,
        if stats.triangles > 0 { format!(" / {} triangles", stats.triangles) } else { String::new() },
        out.report.points_kept,
        report_path.display()
    );
    Ok(())
}
