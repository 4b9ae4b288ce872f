//! `depthmill compensate` and `depthmill plan`: CAM on local files, no server.

use std::path::{Path, PathBuf};

use anyhow::{Context as _, bail};
use depthmill_cam::domain::compensate::{CompensateOptions, PixelModel, compensate};
use depthmill_cam::domain::feeds::MachineLimits;
use depthmill_cam::domain::plan::{FaceInput, PlanOptions, plan};
use depthmill_cam::domain::tool::{Tool, ToolLibrary};
use depthmill_geometry::{HeightMap, HeightMapFormat, ImageMapping, PngDepth};

/// How to read a depth image that has no depthmill metadata.
#[derive(clap::Args, Clone)]
pub struct MapArgs {
    /// Pixel size (mm) of an image without depthmill metadata.
    #[arg(long)]
    pub pixel_mm: Option<f64>,
    /// Z (mm) of black in an image without depthmill metadata.
    #[arg(long, allow_negative_numbers = true)]
    pub z_min_mm: Option<f64>,
    /// Z (mm) of white in an image without depthmill metadata.
    #[arg(long, allow_negative_numbers = true)]
    pub z_max_mm: Option<f64>,
}

impl MapArgs {
    fn read(&self, path: &Path) -> anyhow::Result<HeightMap> {
        let fallback = self.pixel_mm.map(|p| ImageMapping {
            pixel_mm: p,
            z_min_mm: self.z_min_mm,
            z_max_mm: self.z_max_mm,
        });
        HeightMap::read(path, fallback.as_ref()).with_context(|| format!("reading {}", path.display()))
    }
}

fn library(tools_dir: Option<&Path>) -> anyhow::Result<ToolLibrary> {
    let mut lib = ToolLibrary::builtin()?;
    if let Some(dir) = tools_dir {
        lib = lib.merged(ToolLibrary::load_dir(dir)?);
    }
    Ok(lib)
}

pub(crate) fn tool(name: &str, tools_dir: Option<&Path>) -> anyhow::Result<Tool> {
    if name.ends_with(".tool") {
        return Ok(Tool::read_file(Path::new(name))?);
    }
    Ok(library(tools_dir)?.resolve(name)?)
}

fn write_map(map: &HeightMap, path: &Path) -> anyhow::Result<()> {
    let format = HeightMapFormat::from_path(path)?;
    map.write(path, format).with_context(|| format!("writing {}", path.display()))
}

/// `depthmill compensate`.
pub fn run_compensate(
    map_path: &Path,
    tool_name: &str,
    model: &str,
    floor: Option<f64>,
    map_args: &MapArgs,
    tools_dir: Option<&Path>,
    output: &Path,
) -> anyhow::Result<()> {
    let map = map_args.read(map_path)?;
    let tool = tool(tool_name, tools_dir)?;
    let pixel_model = match model {
        "column" => PixelModel::Column,
        "point" => PixelModel::Point,
        "facet" => PixelModel::Facet,
        other => bail!("--model '{other}' is not column, point or facet"),
    };
    let started = std::time::Instant::now();
    let tip = compensate(&map, &tool.profile, &CompensateOptions { pixel_model, outside_z_mm: floor })?;
    let elapsed = started.elapsed();
    write_map(&tip, output)?;
    crate::outln!(
        "{}: {}x{} at {} mm, {} ({model} model), {:.1} ms",
        output.display(),
        map.width(),
        map.height(),
        map.pixel_mm(),
        tool.name,
        elapsed.as_secs_f64() * 1000.0
    );
    Ok(())
}

/// `depthmill plan`: writes the program, `<stem>.report.json`, `<stem>.preview.png` (the surface it
/// leaves) and `<stem>.leftover.png`.
pub fn run_plan(
    map_path: &Path,
    options: Option<&Path>,
    roughing_map: Option<&Path>,
    map_args: &MapArgs,
    tools_dir: Option<&Path>,
    output: &Path,
) -> anyhow::Result<()> {
    let opts: PlanOptions = match options {
        Some(p) => {
            let text = std::fs::read_to_string(p).with_context(|| format!("reading {}", p.display()))?;
            let de = &mut serde_json::Deserializer::from_str(&text);
            serde_path_to_error::deserialize(de)
                .map_err(|e| anyhow::anyhow!("{}: plan.{}: {}", p.display(), e.path(), e.inner()))?
        }
        None => PlanOptions::default(),
    };
    let map = map_args.read(map_path)?;
    let roughing_map = roughing_map.map(|p| map_args.read(p)).transpose()?;
    let lib = library(tools_dir)?;
    let progress = |f: f64, step: &str| tracing::debug!(fraction = f, step, "planning");
    let out = plan(
        &[FaceInput { a_deg: None, map, roughing_map }],
        &opts,
        &lib,
        &MachineLimits::emco_f1(),
        &progress,
        &|| false,
    )?;
    let sibling = |suffix: &str| -> PathBuf {
        let stem =
            output.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_else(|| "program".into());
        output.with_file_name(format!("{stem}.{suffix}"))
    };
    // The four files at once (the PNGs' compression is the slow part; fast DEFLATE for these
    // pictures).
    let (program, report) = std::thread::scope(|scope| {
        let preview = scope.spawn(|| {
            depthmill_geometry::write_png_fast(
                &out.preview.final_surface,
                sibling("preview.png"),
                PngDepth::Bits16,
            )
        });
        let leftover = scope.spawn(|| {
            depthmill_geometry::write_png_fast(
                &out.preview.leftover,
                sibling("leftover.png"),
                PngDepth::Bits8,
            )
        });
        let program =
            std::fs::write(output, &out.gcode).with_context(|| format!("writing {}", output.display()));
        let report = serde_json::to_vec_pretty(&out.report)
            .map_err(anyhow::Error::from)
            .and_then(|json| Ok(std::fs::write(sibling("report.json"), json)?));
        let join = |h: std::thread::ScopedJoinHandle<'_, Result<(), depthmill_geometry::GeometryError>>| {
            h.join()
                .map_err(|_| anyhow::anyhow!("writing a preview image panicked"))?
                .map_err(anyhow::Error::from)
        };
        (program.and(join(preview)).and(join(leftover)), report)
    });
    program?;
    report?;
    crate::outln!(
        "{}: {} blocks, estimated {:.1} min; preview max gouge {:.4} mm, max leftover {:.3} mm, mean leftover {:.3} mm",
        output.display(),
        out.report.blocks,
        out.report.estimated_time_s / 60.0,
        out.preview.max_gouge_mm,
        out.preview.max_leftover_mm,
        out.preview.mean_leftover_mm
    );
    for s in ["report.json", "preview.png", "leftover.png"] {
        crate::outln!("{}", sibling(s).display());
    }
    Ok(())
}
