//! `depthmill plan MESH --robot`: robot milling from a mesh on local files, no server. The mesh is
//! sliced and cut layer by layer by the 6-axis arm with a spindle on its flange; the tool, shank,
//! holder and spindle are checked against the mesh at every position and tilted where the
//! upright tool collides.

use std::path::{Path, PathBuf};

use anyhow::{Context as _, bail};
use depthmill_cam::domain::clearance::{ClearedPath, TiltOptions};
use depthmill_cam::domain::layer_passes::MeshProgramOptions;
use depthmill_cam::domain::robot::{RobotCell, RobotJob, plan_robot, robot_gcode};
use nalgebra::{Isometry3, Vector3};

/// Options of `depthmill plan --robot`.
#[derive(clap::Args, Clone, Debug)]
pub struct RobotArgs {
    /// Plan robot milling from a mesh (STL/PLY) instead of a 3-axis program from a depth map.
    #[arg(long)]
    pub robot: bool,
    /// With --robot: the tool (library name or .tool file).
    #[arg(long, default_value = "flat-6", requires = "robot")]
    pub tool: String,
    /// With --robot: distance between layers, mm.
    #[arg(long, default_value_t = 2.0, requires = "robot")]
    pub step_mm: f64,
    /// With --robot: radial depth of cut between rings, mm (default: the tool's radius).
    #[arg(long, requires = "robot")]
    pub radial_depth_mm: Option<f64>,
    /// With --robot: stock around the part in X and Y, mm.
    #[arg(long, default_value_t = 5.0, requires = "robot")]
    pub stock_margin_mm: f64,
    /// With --robot: length unit of the mesh: mm, m or in.
    #[arg(long, default_value = "mm", requires = "robot")]
    pub units: String,
    /// With --robot: where the part's origin stands in the robot's base frame, "X,Y,Z" mm
    /// (default: the part's box centred 420 mm in front of the base, its bottom at Z 0).
    #[arg(long, requires = "robot", allow_hyphen_values = true)]
    pub part_at: Option<String>,
    /// With --robot: the part's turn about the base's Z axis, degrees.
    #[arg(long, default_value_t = 0.0, requires = "robot", allow_hyphen_values = true)]
    pub part_yaw_deg: f64,
    /// With --robot: feed, mm/min.
    #[arg(long, default_value_t = 600.0, requires = "robot")]
    pub feed_mm_min: f64,
    /// With --robot: spindle speed, rpm.
    #[arg(long, default_value_t = 12000.0, requires = "robot")]
    pub rpm: f64,
    /// With --robot: largest tilt of the tool from upright, degrees.
    #[arg(long, default_value_t = 40.0, requires = "robot")]
    pub max_tilt_deg: f64,
    /// With --robot: flange to spindle nose, mm.
    #[arg(long, default_value_t = 150.0, requires = "robot")]
    pub spindle_length_mm: f64,
    /// With --robot: angle between the flange's axis and the spindle's, degrees (90: across the
    /// flange on a bracket; 0: on the flange's axis).
    #[arg(long, default_value_t = 90.0, requires = "robot")]
    pub spindle_mount_deg: f64,
    /// With --robot: spindle body diameter, mm (checked against the part like the holder).
    #[arg(long, default_value_t = 60.0, requires = "robot")]
    pub spindle_diameter_mm: f64,
}

fn parse_xyz(text: &str) -> anyhow::Result<[f64; 3]> {
    let v: Vec<f64> = text
        .split(',')
        .map(|s| s.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|e| anyhow::anyhow!("--part-at {text}: {e}; expected X,Y,Z in mm"))?;
    match v.as_slice() {
        [x, y, z] if v.iter().all(|c| c.is_finite()) => Ok([*x, *y, *z]),
        _ => bail!("--part-at {text}: expected three finite numbers X,Y,Z in mm"),
    }
}

fn clearance_json(p: &ClearedPath) -> serde_json::Value {
    serde_json::json!({
        "positions": p.points.len(),
        "colliding_upright": p.colliding,
        "tilted": p.tilted,
        "max_tilt_deg": p.max_tilt_deg,
        "max_axis_rate_deg_mm": p.max_rate_deg_mm,
        "blocked": p.blocked.len(),
        "blocked_positions": p.blocked.iter().take(100).collect::<Vec<_>>(),
    })
}

/// `depthmill plan MESH --robot -o OUTPUT.ngc`: writes OUTPUT (the Cartesian program),
/// `<stem>.joints.json` (the joint trajectory) and `<stem>.robot.json` (the report).
pub fn run(input: &Path, args: &RobotArgs, tools_dir: Option<&Path>, output: &Path) -> anyhow::Result<()> {
    let mesh = crate::slice::read_mesh_in(input, &args.units, "--units")?;
    let tool = crate::cam::tool(&args.tool, tools_dir).with_context(|| format!("--tool {}", args.tool))?;
    let (lo, hi) = mesh
        .vertices
        .iter()
        .fold((Vector3::repeat(f64::INFINITY), Vector3::repeat(f64::NEG_INFINITY)), |(lo, hi), p| {
            (lo.inf(&p.coords), hi.sup(&p.coords))
        });
    let at = match &args.part_at {
        Some(t) => Vector3::from(parse_xyz(t)?),
        None => Vector3::new(420.0 - 0.5 * (lo.x + hi.x), -0.5 * (lo.y + hi.y), -lo.z),
    };
    if !args.part_yaw_deg.is_finite() {
        bail!("--part-yaw-deg {}: must be finite", args.part_yaw_deg);
    }
    let base_from_part = Isometry3::new(at, Vector3::z() * args.part_yaw_deg.to_radians());
    let cell = RobotCell {
        spindle_length_mm: args.spindle_length_mm,
        spindle_mount_deg: args.spindle_mount_deg,
        spindle_diameter_mm: args.spindle_diameter_mm,
        ..RobotCell::viper_s650(base_from_part)
    };
    let job = RobotJob {
        layers: MeshProgramOptions {
            radial_depth_mm: args.radial_depth_mm,
            stock_margin_mm: args.stock_margin_mm,
            ..MeshProgramOptions::new(args.step_mm, tool.radius_mm())
        },
        tilt: TiltOptions { max_tilt_deg: args.max_tilt_deg, ..TiltOptions::default() },
        cell,
        feed_mm_min: args.feed_mm_min,
        tool: tool.clone(),
    };
    // The mesh's edge check first: an open or non-manifold mesh may fail to plan, and says why.
    let topo = depthmill_cam::domain::slice::topology(&mesh);
    if !topo.is_closed_manifold() {
        crate::outln!(
            "warning: {}: the mesh is not closed: {} open, {} non-manifold and {} misoriented edges (listed by `depthmill slice`)",
            input.display(),
            topo.boundary.len(),
            topo.non_manifold.len(),
            topo.misoriented.len()
        );
    }
    let started = std::time::Instant::now();
    let plan = plan_robot(&mesh, &job).with_context(|| format!("planning {}", input.display()))?;
    let elapsed = started.elapsed().as_secs_f64();
    let sibling = |suffix: &str| -> PathBuf {
        let stem =
            output.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_else(|| "robot".into());
        output.with_file_name(format!("{stem}.{suffix}"))
    };
    let title = input.file_name().map_or(String::new(), |n| n.to_string_lossy().into_owned());
    let text = robot_gcode(&plan, &tool.name, args.feed_mm_min, args.rpm, &title)?;
    std::fs::write(output, text).with_context(|| format!("writing {}", output.display()))?;
    let joints = sibling("joints.json");
    std::fs::write(&joints, serde_json::to_vec(&plan.robot)?)
        .with_context(|| format!("writing {}", joints.display()))?;
    let unreached: Vec<serde_json::Value> = plan
        .layers
        .passes
        .iter()
        .flat_map(|p| {
            p.unreached
                .iter()
                .map(move |u| serde_json::json!({"z_mm": p.z_mm, "at_mm": u.at, "area_mm2": u.area_mm2}))
        })
        .collect();
    let r = &plan.robot;
    let defects: Vec<&depthmill_cam::domain::slice::Defect> =
        plan.layers.layers.iter().flat_map(|l| &l.defects).collect();
    let open_chains: usize = plan.layers.layers.iter().map(|l| l.open.len()).sum();
    let report = serde_json::json!({
        "input": input.display().to_string(),
        "mesh": {
            "closed_manifold": topo.is_closed_manifold(),
            "boundary_edges": topo.boundary.len(),
            "non_manifold_edges": topo.non_manifold.len(),
            "misoriented_edges": topo.misoriented.len(),
            "layer_defects": defects.iter().take(100).collect::<Vec<_>>(),
            "open_chains": open_chains,
        },
        "tool": tool.name,
        "layers": plan.layers.layers.len(),
        "rings": plan.layers.passes.iter().map(|p| p.rings.len()).sum::<usize>(),
        "feed_links": plan.layers.program.feed_links,
        "retracts": plan.layers.program.retracts,
        "holes_too_narrow": unreached,
        "clearance": clearance_json(&plan.path),
        "robot": {
            "arm": r.arm,
            "configuration": r.configuration,
            "spin_deg": r.spin_deg,
            "base_from_part": r.base_from_part,
            "duration_s": r.duration_s,
            "feed_s": r.feed_s,
            "rapid_s": r.rapid_s,
            "joint_limited_steps": r.joint_limited_steps,
            "min_dexterity": r.min_dexterity,
            "min_margins": r.min_margins,
            "unreachable": r.unreachable,
        },
        "planning_s": elapsed,
    });
    let report_path = sibling("robot.json");
    std::fs::write(&report_path, serde_json::to_vec_pretty(&report)?)
        .with_context(|| format!("writing {}", report_path.display()))?;
    if !defects.is_empty() || open_chains > 0 {
        crate::outln!(
            "warning: {}: {} layer defects (closed where the chain's ends meet), {} open chains (not cut); listed in {}",
            input.display(),
            defects.len(),
            open_chains,
            report_path.display()
        );
        for d in defects.iter().take(3) {
            crate::outln!("  z {:.3} at ({:.3}, {:.3}): {}", d.z_mm, d.at[0], d.at[1], d.message);
        }
    }
    let c = &plan.path;
    crate::outln!(
        "{}: {} layers, {} rings, {} positions; upright tool collides at {}, {} tilted (max {:.1}°, axis turning at most {:.2}°/mm), {} blocked and lifted over",
        input.display(),
        plan.layers.layers.len(),
        plan.layers.passes.iter().map(|p| p.rings.len()).sum::<usize>(),
        c.points.len(),
        c.colliding,
        c.tilted,
        c.max_tilt_deg,
        c.max_rate_deg_mm,
        c.blocked.len()
    );
    crate::outln!(
        "arm {} ({}, spin {:.0}°): {:.1} min ({:.1} min feed, {:.1} min rapid), min dexterity {:.3e}, {} unreachable stretches; planned in {elapsed:.2} s",
        r.arm,
        r.configuration,
        r.spin_deg,
        r.duration_s / 60.0,
        r.feed_s / 60.0,
        r.rapid_s / 60.0,
        r.min_dexterity,
        r.unreachable.len()
    );
    for s in r.unreachable.iter().take(5) {
        crate::outln!(
            "  unreachable: points {}-{} from ({:.2}, {:.2}, {:.2}) mm: {}",
            s.from_point,
            s.to_point,
            s.at_mm[0],
            s.at_mm[1],
            s.at_mm[2],
            s.reason
        );
    }
    for p in [output.to_path_buf(), joints, report_path] {
        crate::outln!("{}", p.display());
    }
    Ok(())
}
