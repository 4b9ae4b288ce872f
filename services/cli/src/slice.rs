//! `depthmill slice`: a mesh's planar sections on local files, no server.

use std::io::Write as _;
use std::path::Path;

use anyhow::{Context as _, bail};
use depthmill_cam::domain::layer_passes::{LayerProgram, MeshProgramOptions, MoveKind, mesh_program};
use depthmill_cam::domain::slice::{ContourKind, MAX_LAYERS, slice, topology};
use depthmill_geometry::formats::{ReadLimits, read_mesh};

/// Options of `depthmill slice` besides the input and output.
#[derive(clap::Args, Clone)]
pub struct SliceArgs {
    /// Distance between layers, mm.
    #[arg(long, default_value_t = 1.0, allow_hyphen_values = true)]
    pub step_mm: f64,
    /// Height of the first layer, mm (default: half a step above the mesh's lowest point).
    #[arg(long, allow_hyphen_values = true)]
    pub from_mm: Option<f64>,
    /// Length unit of the mesh: mm (default), m or in. The layers are in millimetres.
    #[arg(long, default_value = "mm")]
    pub units: String,
    /// Also plan each layer's rings for this tool (e.g. flat-6): from the stock in to the part.
    #[arg(long)]
    pub tool: Option<String>,
    /// Radial depth of cut between rings, mm (default: half the tool's diameter).
    #[arg(long)]
    pub radial_depth_mm: Option<f64>,
    /// Stock around the part in X and Y, mm (the stock is the part's box grown by it).
    #[arg(long, default_value_t = 5.0)]
    pub stock_margin_mm: f64,
    /// With --tool: write the layers' program as G-code (LinuxCNC dialect, the tool in T1),
    /// top layer first, rings joined by `link_layers`.
    #[arg(long)]
    pub gcode: Option<std::path::PathBuf>,
    /// Feed of the program, mm/min.
    #[arg(long, default_value_t = 150.0)]
    pub feed_mm_min: f64,
    /// Spindle speed of the program, rpm.
    #[arg(long, default_value_t = 1500.0)]
    pub rpm: f64,
}

/// The layer program as G-code for a 3-axis mill: the tool in T1 (named in the header the way
/// the machine service reads it), absolute millimetres, rapids as G0 and cuts and links as G1.
fn gcode(
    program: &LayerProgram,
    tool: &str,
    diameter: f64,
    feed: f64,
    rpm: f64,
    clear_z: f64,
    input: &Path,
) -> anyhow::Result<String> {
    if !(feed.is_finite() && feed > 0.0) {
        bail!("--feed-mm-min {feed}: must be a positive feed");
    }
    if !(rpm.is_finite() && rpm > 0.0) {
        bail!("--rpm {rpm}: must be a positive speed");
    }
    use std::fmt::Write as _;
    let mut g = String::new();
    let name = input.file_name().map_or(String::new(), |n| n.to_string_lossy().replace(['(', ')'], ""));
    writeln!(g, "%")?;
    writeln!(g, "(depthmill layer program: {name})")?;
    writeln!(g, "G21 G90 G17 G94 G40 G49 G80")?;
    writeln!(g, "(T1 {tool}: flat D{diameter:.4} mm, 2 flutes - layers)")?;
    writeln!(g, "T1 M6")?;
    writeln!(g, "S{rpm:.0} M3")?;
    writeln!(g, "G43 H1")?;
    writeln!(g, "G0 Z{clear_z:.4}")?;
    let mut feed_set = false;
    for m in &program.moves {
        let [x, y, z] = m.to;
        match m.kind {
            MoveKind::Rapid => writeln!(g, "G0 X{x:.4} Y{y:.4} Z{z:.4}")?,
            MoveKind::Feed if !feed_set => {
                writeln!(g, "G1 X{x:.4} Y{y:.4} Z{z:.4} F{feed:.1}")?;
                feed_set = true;
            }
            MoveKind::Feed => writeln!(g, "G1 X{x:.4} Y{y:.4} Z{z:.4}")?,
        }
    }
    writeln!(g, "M5")?;
    writeln!(g, "G53 G0 Z0")?;
    writeln!(g, "M30")?;
    writeln!(g, "%")?;
    Ok(g)
}

/// Reads a mesh (STL/OBJ/OFF/PLY) in `units` (`mm`, `m` or `in`, given by the option `flag`) and scales
/// it to millimetres; a mesh with no triangles is refused.
pub(crate) fn read_mesh_in(
    input: &Path,
    units: &str,
    flag: &str,
) -> anyhow::Result<depthmill_geometry::Mesh> {
    let Some(unit) = depthmill_geometry::units::LengthUnit::parse(units) else {
        bail!("{flag} {units}: expected mm, m or in");
    };
    let (mut mesh, _) =
        read_mesh(input, &ReadLimits::default()).with_context(|| format!("reading {}", input.display()))?;
    if mesh.triangles.is_empty() {
        bail!("{}: the mesh has no triangles", input.display());
    }
    for p in &mut mesh.vertices {
        p.coords *= unit.mm_per_unit();
    }
    Ok(mesh)
}

/// Edges listed per kind in the output (the counts are complete).
const LISTED_EDGES: usize = 100;

/// `depthmill slice`: writes OUTPUT (JSON: the mesh's topology check and every layer's
/// contours, open chains and defects) and prints a summary.
pub fn run(input: &Path, args: &SliceArgs, output: &Path) -> anyhow::Result<()> {
    let mesh = read_mesh_in(input, &args.units, "--units")?;
    let (zmin, zmax) =
        mesh.vertices.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), p| (a.min(p.z), b.max(p.z)));
    let step = args.step_mm;
    if !(step.is_finite() && step > 0.0) {
        bail!("--step-mm {step}: must be a positive number of millimetres");
    }
    let from = args.from_mm.unwrap_or(zmin + 0.5 * step);
    if !from.is_finite() {
        bail!("--from-mm {from}: must be finite");
    }
    let count = ((zmax - from) / step).floor() + 1.0;
    if count < 1.0 {
        bail!("--from-mm {from}: above the mesh's highest point {zmax:.4} mm: no layer cuts it");
    }
    if count > MAX_LAYERS as f64 {
        bail!(
            "{count:.0} layers from {from} mm to {zmax:.4} mm at {step} mm: more than {MAX_LAYERS}; take a larger --step-mm"
        );
    }
    let levels: Vec<f64> = (0..count as usize).map(|i| from + i as f64 * step).collect();
    let topo = topology(&mesh);
    let layers = slice(&mesh, &levels)?;
    let contours: usize = layers.iter().map(|l| l.contours.len()).sum();
    let holes: usize =
        layers.iter().flat_map(|l| &l.contours).filter(|c| c.kind == ContourKind::Hole).count();
    let open: usize = layers.iter().map(|l| l.open.len()).sum();
    let defects: usize = layers.iter().map(|l| l.defects.len()).sum();
    let passes = match &args.tool {
        None => None,
        Some(spec) => {
            let tool: depthmill_geometry::ToolProfile =
                spec.parse().map_err(|e| anyhow::anyhow!("--tool {spec}: {e}"))?;
            let planned_mesh = mesh_program(
                &mesh,
                &MeshProgramOptions {
                    step_mm: step,
                    from_mm: Some(from),
                    tool_radius_mm: tool.radius_mm(),
                    radial_depth_mm: args.radial_depth_mm,
                    stock_margin_mm: args.stock_margin_mm,
                    clearance_mm: 5.0,
                },
            )
            .map_err(|e| anyhow::anyhow!("layer passes: {e}"))?;
            let o = planned_mesh.options;
            let r = o.tool_radius_mm;
            let planned = &planned_mesh.passes;
            let rings: usize = planned.iter().map(|p| p.rings.len()).sum();
            let unreached: Vec<String> = planned
                .iter()
                .flat_map(|p| {
                    p.unreached.iter().map(move |u| {
                        format!("z {:.3} at ({:.3}, {:.3}), {:.3} mm²", p.z_mm, u.at[0], u.at[1], u.area_mm2)
                    })
                })
                .collect();
            crate::outln!(
                "{spec}: {rings} rings over {} layers, radial depth {} mm, stock {:?}",
                planned.len(),
                o.radial_depth_mm,
                o.stock
            );
            if !unreached.is_empty() {
                crate::outln!(
                    "{} holes narrower than the tool are not cut: {}",
                    unreached.len(),
                    unreached.iter().take(5).cloned().collect::<Vec<_>>().join("; ")
                );
            }
            let (program, clear_z) = (&planned_mesh.program, planned_mesh.clear_z_mm);
            crate::outln!(
                "program: {} moves, {} feed links, {} retracts to Z {clear_z:.3}",
                program.moves.len(),
                program.feed_links,
                program.retracts
            );
            if let Some(path) = &args.gcode {
                let text = gcode(program, spec, 2.0 * r, args.feed_mm_min, args.rpm, clear_z, input)?;
                std::fs::write(path, text).with_context(|| format!("writing {}", path.display()))?;
                crate::outln!("written {}", path.display());
            }
            Some(serde_json::json!({
                "tool": spec,
                "options": o,
                "layers": planned,
                "program": {"moves": program.moves.len(), "feed_links": program.feed_links, "retracts": program.retracts},
            }))
        }
    };
    let list = |edges: &[(u32, u32)]| -> serde_json::Value {
        edges
            .iter()
            .take(LISTED_EDGES)
            .map(|&(a, b)| {
                let (p, q) = (&mesh.vertices[a as usize], &mesh.vertices[b as usize]);
                serde_json::json!({"vertices": [a, b], "from_mm": [p.x, p.y, p.z], "to_mm": [q.x, q.y, q.z]})
            })
            .collect()
    };
    let doc = serde_json::json!({
        "input": input.display().to_string(),
        "triangles": mesh.triangles.len(),
        "vertices": mesh.vertices.len(),
        "z_range_mm": [zmin, zmax],
        "topology": {
            "closed_manifold": topo.is_closed_manifold(),
            "boundary_edges": topo.boundary.len(),
            "non_manifold_edges": topo.non_manifold.len(),
            "misoriented_edges": topo.misoriented.len(),
            "boundary": list(&topo.boundary),
            "non_manifold": list(&topo.non_manifold),
            "misoriented": list(&topo.misoriented),
        },
        "layers": layers,
        "passes": passes,
    });
    let mut w = std::io::BufWriter::new(
        std::fs::File::create(output).with_context(|| format!("creating {}", output.display()))?,
    );
    serde_json::to_writer(&mut w, &doc)?;
    w.flush().with_context(|| format!("writing {}", output.display()))?;
    crate::outln!(
        "{} layers from {from:.4} to {:.4} mm every {step} mm: {contours} contours ({holes} holes), {open} open chains, {defects} defects",
        levels.len(),
        levels.last().copied().unwrap_or(from)
    );
    if !topo.is_closed_manifold() {
        crate::outln!(
            "mesh: {} boundary edges (open), {} non-manifold, {} misoriented (listed in {})",
            topo.boundary.len(),
            topo.non_manifold.len(),
            topo.misoriented.len(),
            output.display()
        );
    }
    crate::outln!("written {}", output.display());
    Ok(())
}
