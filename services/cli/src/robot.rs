//! `depthmill plan MESH --robot`: robot milling from a mesh on local files, no server. The mesh is
//! sliced and cut layer by layer by the 6-axis arm with a spindle on its flange; the tool, shank,
//! holder and spindle are checked against the mesh at every position and tilted where the
//! upright tool collides.

use std::path::{Path, PathBuf};

use anyhow::{Context as _, bail};
use depthmill_cam::domain::robot::{plan_robot, robot_gcode};
use depthmill_cam::domain::robot_job::{RobotSettings, robot_report, robot_warnings};

/// Options of `depthmill plan --robot` (the job's `robot` section; defaults in
/// `depthmill_cam::domain::robot_job`).
#[derive(clap::Args, Clone, Debug)]
pub struct RobotArgs {
    /// Plan robot milling from a mesh (STL/OBJ/OFF/PLY) instead of a 3-axis program from a depth map.
    #[arg(long)]
    pub robot: bool,
    /// With --robot: the tool (library name or .tool file; default flat-6).
    #[arg(long, requires = "robot")]
    pub tool: Option<String>,
    /// With --robot: distance between layers, mm (default 2).
    #[arg(long, requires = "robot")]
    pub step_mm: Option<f64>,
    /// With --robot: radial depth of cut between rings, mm (default: the tool's radius).
    #[arg(long, requires = "robot")]
    pub radial_depth_mm: Option<f64>,
    /// With --robot: stock around the part in X and Y, mm (default 5).
    #[arg(long, requires = "robot")]
    pub stock_margin_mm: Option<f64>,
    /// With --robot: length unit of the mesh: mm, m or in.
    #[arg(long, default_value = "mm", requires = "robot")]
    pub units: String,
    /// With --robot: where the part's origin stands in the robot's base frame, "X,Y,Z" mm
    /// (default: the part's box centred 420 mm in front of the base, its bottom at Z 0).
    #[arg(long, requires = "robot", allow_hyphen_values = true)]
    pub part_at: Option<String>,
    /// With --robot: the part's turn about the base's Z axis, degrees (default 0).
    #[arg(long, requires = "robot", allow_hyphen_values = true)]
    pub part_yaw_deg: Option<f64>,
    /// With --robot: feed, mm/min (default 600).
    #[arg(long, requires = "robot")]
    pub feed_mm_min: Option<f64>,
    /// With --robot: spindle speed, rpm (default 12000).
    #[arg(long, requires = "robot")]
    pub rpm: Option<f64>,
    /// With --robot: largest tilt of the tool from upright, degrees (default 40).
    #[arg(long, requires = "robot")]
    pub max_tilt_deg: Option<f64>,
    /// With --robot: flange to spindle nose, mm (default 150).
    #[arg(long, requires = "robot")]
    pub spindle_length_mm: Option<f64>,
    /// With --robot: angle between the flange's axis and the spindle's, degrees (90, the
    /// default: across the flange on a bracket; 0: on the flange's axis).
    #[arg(long, requires = "robot")]
    pub spindle_mount_deg: Option<f64>,
    /// With --robot: spindle body diameter, mm (checked against the part like the holder; default 60).
    #[arg(long, requires = "robot")]
    pub spindle_diameter_mm: Option<f64>,
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

impl RobotArgs {
    /// The job's `robot` settings these options give.
    fn settings(&self) -> anyhow::Result<RobotSettings> {
        Ok(RobotSettings {
            tool: self.tool.clone(),
            step_mm: self.step_mm,
            radial_depth_mm: self.radial_depth_mm,
            stock_margin_mm: self.stock_margin_mm,
            part_at_mm: self.part_at.as_deref().map(parse_xyz).transpose()?,
            part_yaw_deg: self.part_yaw_deg,
            feed_mm_min: self.feed_mm_min,
            rpm: self.rpm,
            max_tilt_deg: self.max_tilt_deg,
            spindle_length_mm: self.spindle_length_mm,
            spindle_mount_deg: self.spindle_mount_deg,
            spindle_diameter_mm: self.spindle_diameter_mm,
        })
    }
}

/// A settings error in the command line's words: `robot.step_mm` is `--step-mm`.
fn flag_error(e: depthmill_cam::domain::CamError) -> anyhow::Error {
    match e {
        depthmill_cam::domain::CamError::InvalidParameter { field, message } => {
            let flag = field.strip_prefix("robot.").unwrap_or(&field).replace('_', "-");
            let flag = flag.split('.').next().unwrap_or(&flag).replace("part-at-mm", "part-at");
            anyhow::anyhow!("--{flag} {message}")
        }
        other => other.into(),
    }
}

/// `depthmill plan MESH --robot -o OUTPUT.ngc`: writes OUTPUT (the Cartesian program),
/// `<stem>.joints.json` (the joint trajectory) and `<stem>.robot.json` (the report).
pub fn run(input: &Path, args: &RobotArgs, tools_dir: Option<&Path>, output: &Path) -> anyhow::Result<()> {
    let mesh = crate::slice::read_mesh_in(input, &args.units, "--units")?;
    let settings = args.settings()?;
    settings.check().map_err(flag_error)?;
    let tool = crate::cam::tool(settings.tool_name(), tools_dir)
        .with_context(|| format!("--tool {}", settings.tool_name()))?;
    let job = settings.job(&mesh, tool.clone()).map_err(flag_error)?;
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
    let text = robot_gcode(&plan, &tool.name, settings.feed(), settings.spindle_rpm(), &title)?;
    std::fs::write(output, text).with_context(|| format!("writing {}", output.display()))?;
    let joints = sibling("joints.json");
    std::fs::write(&joints, serde_json::to_vec(&plan.robot)?)
        .with_context(|| format!("writing {}", joints.display()))?;
    let report = robot_report(&plan, &topo, &input.display().to_string(), &tool.name, elapsed);
    let r = &plan.robot;
    let report_path = sibling("robot.json");
    std::fs::write(&report_path, serde_json::to_vec_pretty(&report)?)
        .with_context(|| format!("writing {}", report_path.display()))?;
    // What the plan found (the open mesh was said before planning); the report lists it all.
    for (code, message) in robot_warnings(&plan, &topo) {
        if code != "mesh_not_closed" {
            let kind = if code == "placement" { "note" } else { "warning" };
            crate::outln!("{kind}: {}: {message} (see {})", input.display(), report_path.display());
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
