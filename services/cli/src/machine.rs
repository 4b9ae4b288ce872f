//! `depthmill check` and `depthmill simulate`: the machine service's work on local files.

use std::io::BufRead;
use std::path::{Path, PathBuf};

use anyhow::{Context as _, bail};
use depthmill_geometry::{HeightMap, HeightMapFormat, ImageMapping};
use depthmill_machine::domain::job::{ExecuteOptions, execute, header_tools, tools_for};
use depthmill_machine::domain::profile::MachineProfile;
use depthmill_machine::domain::sim::{Machine, PolicyKind, SimSetup, StockSpec, simulate};

/// Options shared by `check` and `simulate`.
#[derive(clap::Args, Clone)]
pub struct MachineArgs {
    /// Machine profile: a shipped name (emco-f1) or a profile file (.toml, see machines/emco-f1.toml).
    #[arg(long, default_value = "emco-f1")]
    pub machine: String,
    /// Clamp F and S to the machine's ranges (with a warning) instead of refusing the program.
    #[arg(long)]
    pub clamp: bool,
}

fn opener(path: &Path) -> impl Fn() -> std::io::Result<Box<dyn BufRead + Send>> + Sync + '_ {
    move || Ok(Box::new(std::io::BufReader::with_capacity(1 << 16, std::fs::File::open(path)?)))
}

/// `depthmill check`: interpret and validate without cutting.
pub fn run_check(program: &Path, args: &MachineArgs) -> anyhow::Result<()> {
    let open = opener(program);
    let profile = MachineProfile::by_name_or_file(&args.machine)?;
    let header = header_tools(open().with_context(|| format!("reading {}", program.display()))?);
    let tools = tools_for(&profile, &header)?;
    let setup = SimSetup {
        profile,
        material: depthmill_machine::domain::cutting::material("aluminium").context("material table")?,
        stock: StockSpec {
            min_x_mm: 0.0,
            min_y_mm: 0.0,
            min_z_mm: 0.0,
            x_mm: 1.0,
            y_mm: 1.0,
            z_mm: 1.0,
            cell_mm: 1.0,
        },
        faces: Vec::new(),
        dexel: None,
        tools,
        policy: PolicyKind::Off,
        clamp: args.clamp,
        inclusions: Vec::new(),
        seed: 1,
        telemetry_interval_s: 1.0,
        motion_only: true,
    };
    let cfg = Machine::new(&setup)?.interp_config();
    // Extents of the tip over every move, work frame.
    let w = setup.profile.work_offset;
    let (mut lo, mut hi) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
    let (mut feeds, mut rapids, mut arcs, mut tlo) = (0u64, 0u64, 0u64, 0.0);
    let summary = depthmill_machine::domain::gcode::run(open()?, cfg, |c| {
        use depthmill_machine::domain::gcode::Canon;
        match c {
            Canon::ToolLengthOffset { mm, .. } => tlo = mm,
            Canon::Traverse { .. } => rapids += 1,
            Canon::Feed { .. } => feeds += 1,
            Canon::Arc { .. } => arcs += 1,
            _ => {}
        }
        if let Some(p) = c.end_point() {
            let t = [p.x - w.x_mm, p.y - w.y_mm, p.z - tlo - w.z_mm];
            for i in 0..3 {
                lo[i] = lo[i].min(t[i]);
                hi[i] = hi[i].max(t[i]);
            }
        }
    })
    .map_err(|e| anyhow::anyhow!("{}: {e}", program.display()))?;
    let (report, _) = simulate(open()?, &setup, &|| false, &mut |_| {})
        .map_err(|e| anyhow::anyhow!("{}: {e}", program.display()))?;
    crate::outln!("{}: ok on {}", program.display(), setup.profile.name);
    crate::outln!(
        "  lines {}, blocks {}, moves: {rapids} rapid, {feeds} linear, {arcs} arcs",
        summary.lines,
        summary.blocks
    );
    if lo[0].is_finite() {
        crate::outln!(
            "  tip extents (work frame): X {:.3}..{:.3}  Y {:.3}..{:.3}  Z {:.3}..{:.3} mm",
            lo[0],
            hi[0],
            lo[1],
            hi[1],
            lo[2],
            hi[2]
        );
    }
    for t in &setup.tools {
        if header.iter().any(|h| h.0 == t.number) {
            crate::outln!("  T{} {} ({} teeth, gauge length {} mm)", t.number, t.name, t.teeth, t.length_mm);
        }
    }
    crate::outln!(
        "  estimated cycle time {:.1} s (programmed feeds, acceleration and blending)",
        report.cycle_time_s
    );
    for w in &report.warnings {
        crate::outln!("  warning: {w}");
    }
    Ok(())
}

/// Options of `depthmill simulate`.
#[derive(clap::Args, Clone)]
pub struct SimulateArgs {
    #[command(flatten)]
    pub machine: MachineArgs,
    /// The depth map the part should come out as; the deviation is measured against it.
    #[arg(long)]
    pub target: Option<PathBuf>,
    /// Pixel size of a target image without depthmill metadata.
    #[arg(long)]
    pub pixel_mm: Option<f64>,
    /// Feed/speed policy: aco, feed_only or off.
    #[arg(long, default_value = "aco")]
    pub adaptive: String,
    /// Work material: aluminium, brass, mild_steel, wax, plastic.
    #[arg(long)]
    pub material: Option<String>,
    /// Stock height above the target's z_min, mm.
    #[arg(long)]
    pub stock_z_mm: Option<f64>,
    /// Z-map cell, mm.
    #[arg(long)]
    pub cell_mm: Option<f64>,
    /// Skip the comparison runs (no adaptation, other policy).
    #[arg(long)]
    pub no_compare: bool,
    /// PROGRAM is a robot joint trajectory (`depthmill plan MESH --robot` writes
    /// <stem>.joints.json): replay it through the arm's kinematics on a dexel stock.
    #[arg(long)]
    pub robot: bool,
    /// With --robot: the part's mesh (STL/OBJ/OFF/PLY) to measure the machined part against.
    #[arg(long, requires = "robot")]
    pub part: Option<PathBuf>,
    /// With --robot: length unit of the part's mesh: mm, m or in.
    #[arg(long, default_value = "mm", requires = "robot")]
    pub part_units: String,
}

/// `depthmill simulate JOINTS.json --robot`: the robot program cut on a dexel stock; writes
/// report.json and part.stl (the simulated part) to OUT_DIR.
fn run_robot(trajectory: &Path, args: &SimulateArgs, out_dir: &Path) -> anyhow::Result<()> {
    use depthmill_machine::domain::robot::{RobotRunOptions, Trajectory, run};
    let bytes = std::fs::read(trajectory).with_context(|| format!("reading {}", trajectory.display()))?;
    let traj = Trajectory::from_json(&bytes).map_err(|e| anyhow::anyhow!("{}: {e}", trajectory.display()))?;
    let reference = match &args.part {
        Some(p) => {
            let mesh = crate::slice::read_mesh_in(p, &args.part_units, "--part-units")?;
            Some(depthmill_machine::domain::part::mesh_samples(
                &mesh,
                depthmill_machine::domain::part::MAX_REFERENCE_POINTS,
            ))
        }
        None => None,
    };
    let cell = args.cell_mm.unwrap_or(0.25);
    let opts = RobotRunOptions { cell_mm: cell, max_error_mm: 0.5 * cell };
    let started = std::time::Instant::now();
    let (report, stock) = run(&traj, &opts, reference.as_deref())
        .map_err(|e| anyhow::anyhow!("{}: {e}", trajectory.display()))?;
    let wall = started.elapsed().as_secs_f64();
    std::fs::create_dir_all(out_dir).with_context(|| format!("creating {}", out_dir.display()))?;
    let report_path = out_dir.join("report.json");
    std::fs::write(&report_path, serde_json::to_vec_pretty(&report)?)
        .with_context(|| format!("writing {}", report_path.display()))?;
    let step = stock.surface_step_mm(depthmill_machine::domain::job::VIEW_SAMPLES);
    let mesh = stock.surface_mesh(step)?;
    let stl = out_dir.join("part.stl");
    let mut f = std::io::BufWriter::new(
        std::fs::File::create(&stl).with_context(|| format!("creating {}", stl.display()))?,
    );
    depthmill_geometry::formats::write_stl(&mut f, &mesh, "depthmill simulated robot-milled part")?;
    std::io::Write::flush(&mut f).with_context(|| format!("writing {}", stl.display()))?;
    crate::outln!(
        "{}: {} points, {} steps cut in {wall:.1} s on {cell} mm dexels; cycle {:.1} min; removed {:.0} mm³ ({:.0} mm³ by rapids)",
        trajectory.display(),
        report.points,
        report.steps_cut,
        report.cycle_time_s / 60.0,
        report.removed_mm3,
        report.rapid_removed_mm3
    );
    if let Some(d) = &report.deviation {
        crate::outln!(
            "against the part ({} samples): max gouge {:.3} mm, max leftover {:.3} mm, mean {:.3} mm, RMS {:.3} mm, {:.1} % within 0.1 mm, {:.1} % within 1 mm",
            d.points,
            d.max_gouge_mm,
            d.max_leftover_mm,
            d.mean_mm,
            d.rms_mm,
            100.0 * d.within_0_1_mm,
            100.0 * d.within_1_mm
        );
    }
    crate::outln!("{}", report_path.display());
    crate::outln!("{}", stl.display());
    Ok(())
}

/// `depthmill simulate`: run a program on the simulated machine; write the results to a folder.
pub fn run_simulate(program: &Path, args: &SimulateArgs, out_dir: &Path) -> anyhow::Result<()> {
    if args.robot {
        return run_robot(program, args, out_dir);
    }
    let Some(policy) = PolicyKind::parse(&args.adaptive) else {
        bail!("--adaptive '{}' is not aco, feed_only or off", args.adaptive);
    };
    let target = match &args.target {
        Some(p) => {
            let fallback =
                args.pixel_mm.map(|pixel_mm| ImageMapping { pixel_mm, z_min_mm: None, z_max_mm: None });
            Some(HeightMap::read(p, fallback.as_ref()).with_context(|| format!("reading {}", p.display()))?)
        }
        None => None,
    };
    let opts = ExecuteOptions {
        machine: args.machine.machine.clone(),
        policy,
        material: args.material.clone(),
        stock_z_mm: args.stock_z_mm,
        cell_mm: args.cell_mm,
        clamp: args.machine.clamp,
        compare: !args.no_compare,
        ..Default::default()
    };
    let open = opener(program);
    let started = std::time::Instant::now();
    let out = execute(&open, &opts, target.as_ref(), &|| false, &mut |_| {})
        .map_err(|e| anyhow::anyhow!("{}: {e}", program.display()))?;
    let wall = started.elapsed().as_secs_f64();
    std::fs::create_dir_all(out_dir).with_context(|| format!("creating {}", out_dir.display()))?;
    let write = |name: &str, bytes: &[u8]| -> anyhow::Result<()> {
        let p = out_dir.join(name);
        std::fs::write(&p, bytes).with_context(|| format!("writing {}", p.display()))
    };
    out.final_stock.write(out_dir.join("final_stock.png"), HeightMapFormat::Png16)?;
    out.final_stock.write(out_dir.join("final_stock.npy"), HeightMapFormat::Npy)?;
    if let Some(d) = &out.report.deviation {
        d.map.write(out_dir.join("deviation.png"), HeightMapFormat::Png8)?;
        d.map.write(out_dir.join("deviation.npy"), HeightMapFormat::Npy)?;
    }
    if let Some(stl) = &out.part_stl {
        write("part.stl", stl)?;
    }
    write("telemetry.csv", out.telemetry_csv.as_bytes())?;
    write("telemetry.svg", out.telemetry_svg.as_bytes())?;
    write("report.json", &serde_json::to_vec_pretty(&out.report)?)?;
    let r = &out.report;
    crate::outln!(
        "{}: simulated on {} ({}) in {wall:.1} s wall time",
        program.display(),
        r.machine,
        r.run.policy
    );
    crate::outln!(
        "  cycle time {:.1} s; without adaptation {:.1} s{}",
        r.cycle_time_s,
        r.cycle_time_no_adaptive_s,
        r.cycle_time_other_s
            .map_or(String::new(), |t| format!("; {} {t:.1} s", r.other_policy.unwrap_or("other")))
    );
    crate::outln!(
        "  removed {:.1} mm³ in {} revolutions; max torque {:.3} N·m, power {:.1} W, current {:.2} A",
        r.run.removed_mm3,
        r.run.revolutions,
        r.run.max_torque_nm,
        r.run.max_power_w,
        r.run.max_current_a
    );
    if let Some(d) = &r.deviation {
        crate::outln!(
            "  deviation from the target: max gouge {:.4} mm, max leftover {:.4} mm, mean leftover {:.4} mm, RMS {:.4} mm",
            d.max_gouge_mm,
            d.max_leftover_mm,
            d.mean_leftover_mm,
            d.rms_deviation_mm
        );
    }
    for w in r.run.warnings.iter().take(20) {
        crate::outln!("  warning: {w}");
    }
    crate::outln!("  results in {}", out_dir.display());
    Ok(())
}
