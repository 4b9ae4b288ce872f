//! The programs the CAM service writes run in a real interpreter: LinuxCNC's standalone `rs274`
//! (Debian package `linuxcnc-uspace`, which `.ci/run` installs and then requires with
//! `DEPTHMILL_REQUIRE_RS274=1`). Without it and without the variable, the test says so and passes.
//! The machine service's interpreter must produce the same moves as `rs274` on each program.

use std::process::Command;

use depthmill_cam::domain::feeds::MachineLimits;
use depthmill_cam::domain::plan::{
    FaceInput, FinishingOptions, PlanOptions, RestOptions, RoughingOptions, StockOptions, plan,
};
use depthmill_cam::domain::tool::ToolLibrary;
use depthmill_geometry::{HeightMap, HeightMapMeta};
use depthmill_machine::domain::gcode;

fn rs274_available() -> bool {
    Command::new("rs274").arg("-h").output().is_ok()
}

fn dome() -> anyhow::Result<HeightMap> {
    let mut meta = HeightMapMeta::new(100, 80, 0.3);
    meta.z_max_mm = 12.0;
    Ok(HeightMap::from_fn(meta, |c, r| {
        let (x, y) = ((f64::from(c) + 0.5) * 0.3 - 15.0, (f64::from(r) + 0.5) * 0.3 - 12.0);
        let d2 = x * x + y * y;
        let step = if x > 8.0 { 1.5 } else { 0.0 };
        (1.0 + step + if d2 < 81.0 { (81.0 - d2).sqrt() } else { 0.0 }) as f32
    })?)
}

/// Whether `rs274` is here; without it the check is skipped, unless `DEPTHMILL_REQUIRE_RS274`
/// is set, which makes that a failure.
/// Runs `rs274 -t TABLE -g PROGRAM CANON` and fails naming the exit status and both outputs. A
/// run killed by a signal (no exit code: the machine under load, not the program) is tried once
/// more.
fn run_rs274_cli(
    table: &std::path::Path,
    program: &std::path::Path,
    canon: &std::path::Path,
    what: &str,
) -> anyhow::Result<()> {
    for attempt in 1..=2 {
        let run = Command::new("rs274").arg("-t").arg(table).arg("-g").arg(program).arg(canon).output()?;
        if run.status.success() {
            return Ok(());
        }
        if run.status.code().is_some() || attempt == 2 {
            anyhow::bail!(
                "{what}: rs274 failed ({}): stdout:\n{}\nstderr:\n{}",
                run.status,
                String::from_utf8_lossy(&run.stdout),
                String::from_utf8_lossy(&run.stderr)
            );
        }
        eprintln!("{what}: rs274 ended by a signal ({}), running it again", run.status);
    }
    Ok(())
}

fn rs274_or_skip() -> bool {
    if rs274_available() {
        return true;
    }
    assert!(
        std::env::var_os("DEPTHMILL_REQUIRE_RS274").is_none(),
        "DEPTHMILL_REQUIRE_RS274 is set but rs274 (linuxcnc-uspace) is not installed"
    );
    eprintln!("rs274 not installed (apt-get install linuxcnc-uspace): skipping the interpreter check");
    false
}

#[test]
fn cam_programs_run_in_linuxcnc_rs274() -> anyhow::Result<()> {
    if !rs274_or_skip() {
        return Ok(());
    }
    let dir = tempfile::tempdir()?;
    let table = dir.path().join("tool.tbl");
    std::fs::write(&table, "T1 P1 D6.0 Z0 ;roughing\nT2 P2 D3.0 Z0 ;finishing\nT3 P3 D1.0 Z0 ;rest\n")?;
    let library = ToolLibrary::builtin()?;
    let cases = [
        ("x", "raster_x", None, "linuxcnc"),
        ("contour", "raster_angle", Some(30.0), "linuxcnc"),
        ("y", "iso_level", None, "linuxcnc"),
        ("x", "raster_y", None, "linuxcnc"),
        ("x", "raster_x", None, "fanuc"),
    ];
    for (direction, strategy, angle, dialect) in cases {
        let options = PlanOptions {
            stock: Some(StockOptions { z_mm: Some(13.0), ..Default::default() }),
            roughing: Some(RoughingOptions {
                tool: Some("flat-6".into()),
                step_down_mm: Some(3.0),
                stock_to_leave_mm: Some(0.3),
                direction: Some(direction.into()),
            }),
            finishing: Some(FinishingOptions {
                tool: Some("ball-3".into()),
                strategy: Some(strategy.into()),
                angle_deg: angle,
                step_over_mm: Some(0.6),
                tolerance_mm: Some(0.01),
                arcs: Some(true),
                pixel_model: None,
            }),
            dialect: Some(dialect.into()),
            // Rest finishing: ball-1 as T3 where ball-3 left the dome's foot.
            rest: Some(RestOptions { enabled: Some(true), ..Default::default() }),
        };
        let out = plan(
            &[FaceInput { a_deg: None, map: dome()?, roughing_map: None }],
            &options,
            &library,
            &MachineLimits::emco_f1(),
            &|_, _| {},
            &|| false,
        )?;
        let program = dir.path().join(format!("{direction}-{strategy}-{dialect}.ngc"));
        std::fs::write(&program, &out.gcode)?;
        let canon = dir.path().join("canon.txt");
        run_rs274_cli(&table, &program, &canon, &format!("{direction}/{strategy}/{dialect}"))?;
        let moves = std::fs::read_to_string(&canon)?;
        let tail: String =
            moves.lines().rev().take(20).collect::<Vec<_>>().into_iter().rev().collect::<Vec<_>>().join("\n");
        assert!(
            moves.contains("PROGRAM_END"),
            "{direction}/{strategy}: the interpreter stopped early; its last moves:\n{tail}"
        );
        let feeds = moves.matches("STRAIGHT_FEED").count() + moves.matches("ARC_FEED").count();
        let blocks = out
            .gcode
            .lines()
            .map(|l| l.trim_start_matches(|c: char| c == 'N' || c.is_ascii_digit()).trim_start())
            .filter(|l| l.starts_with('G') || l.starts_with('X') || l.starts_with('Y'))
            .count();
        assert!(
            feeds > 0 && feeds <= blocks + 10,
            "{direction}/{strategy}: {feeds} feed moves for {blocks} blocks"
        );
        // The machine service's interpreter agrees with rs274 move by move on the same program.
        let theirs = gcode::rs274::run_rs274(&program, &table)?;
        let config = gcode::InterpConfig {
            tools: [(1, 0.0), (2, 0.0), (3, 0.0)].into_iter().collect(),
            ..Default::default()
        };
        let mut ours = Vec::new();
        gcode::run(std::io::Cursor::new(out.gcode.as_bytes()), config, |c| ours.push(c))?;
        let compared = gcode::rs274::compare(&ours, &theirs, 1e-4)
            .map_err(|m| anyhow::anyhow!("{direction}/{strategy}/{dialect}: {m}"))?;
        assert!(compared > 100, "{direction}/{strategy}/{dialect}: only {compared} moves compared");
    }
    Ok(())
}

/// The table-table words (A and C on every move, G93 inverse time, an arc turning C) read the same
/// in the machine service's interpreter as in LinuxCNC's, move by move.
#[test]
fn five_axis_words_agree_with_linuxcnc_rs274() -> anyhow::Result<()> {
    if !rs274_or_skip() {
        return Ok(());
    }
    let dir = tempfile::tempdir()?;
    let table = dir.path().join("tool.tbl");
    std::fs::write(&table, "T1 P1 D6.0 Z0 ;flat\n")?;
    let text = "G21 G90 G17 G94\nT1 M6\nS1000 M3\nG43 H1\nG54\nG0 X0 Y0 Z20 A-30 C45\nG1 Z5 F100\n\
                G1 X10 C90 F200\nG93 G1 X20 Y5 C135 F4\nG2 X30 Y5 I5 J0 C180 F2\nG1 A-60 F30\nG94 G1 X0 F300\n\
                G91 G0 C-90 A30\nG90 G0 Z20\nM30\n";
    let program = dir.path().join("five-axis.ngc");
    std::fs::write(&program, text)?;
    let theirs = gcode::rs274::run_rs274(&program, &table)?;
    let config = gcode::InterpConfig { tools: [(1, 0.0)].into_iter().collect(), ..Default::default() };
    let mut ours = Vec::new();
    gcode::run(std::io::Cursor::new(text.as_bytes()), config, |c| ours.push(c))?;
    let compared = gcode::rs274::compare(&ours, &theirs, 1e-4).map_err(|m| anyhow::anyhow!("{m}"))?;
    assert_eq!(compared, 9, "every move compared");
    let last = ours.iter().rev().find_map(|c| c.end_point()).expect("a move");
    assert!((last.c - 90.0).abs() < 1e-9 && (last.a + 30.0).abs() < 1e-9, "{last:?}");
    Ok(())
}

/// The robot program (tool tip X Y Z in the part frame, the tool axis as A and B) reads in
/// LinuxCNC's interpreter: one move per position of the checked path, with the A and B words as
/// the planner's axes give them.
#[test]
fn robot_programs_run_in_linuxcnc_rs274() -> anyhow::Result<()> {
    use depthmill_cam::domain::clearance::TiltOptions;
    use depthmill_cam::domain::layer_passes::MeshProgramOptions;
    use depthmill_cam::domain::robot::{RobotCell, RobotJob, ab_to_axis, plan_robot, robot_gcode};
    use depthmill_geometry::nalgebra::Isometry3;
    if !rs274_or_skip() {
        return Ok(());
    }
    let dir = tempfile::tempdir()?;
    // A block 20 x 20 x 60 mm: the holder leans clear of it near its foot.
    let mesh = depthmill_geometry::Mesh::cuboid(20.0, 20.0, 60.0);
    let tool = ToolLibrary::builtin()?.resolve("flat-6")?;
    let job = RobotJob {
        auto_place: false,
        layers: MeshProgramOptions::new(10.0, tool.radius_mm()),
        tilt: TiltOptions::default(),
        cell: RobotCell::viper_s650(Isometry3::translation(410.0, -10.0, 0.0)),
        feed_mm_min: 600.0,
        tool: tool.clone(),
    };
    let plan = plan_robot(&mesh, &job)?;
    let text = robot_gcode(&plan, &tool.name, 600.0, 12000.0, "tall block")?;
    let program = dir.path().join("robot.ngc");
    std::fs::write(&program, &text)?;
    let table = dir.path().join("tool.tbl");
    std::fs::write(&table, "T1 P1 D6.0 Z0 ;flat\n")?;
    let canon = dir.path().join("canon.txt");
    run_rs274_cli(&table, &program, &canon, "robot program")?;
    let moves = std::fs::read_to_string(&canon)?;
    assert!(moves.contains("PROGRAM_END"), "the interpreter stopped early");
    let straight: Vec<Vec<f64>> = moves
        .lines()
        .filter_map(|l| l.split_once("STRAIGHT_").map(|(_, r)| r))
        .filter_map(|r| r.split_once('(').and_then(|(_, args)| args.strip_suffix(')')))
        .map(|args| args.split(',').filter_map(|v| v.trim().parse::<f64>().ok()).collect())
        .collect();
    assert_eq!(straight.len(), plan.path.points.len(), "one move per position");
    let mut leaning = 0;
    for (m, p) in straight.iter().zip(&plan.path.points) {
        assert!((0..3).all(|k| (m[k] - p.tip[k]).abs() < 1e-3), "{m:?} vs {:?}", p.tip);
        let axis = ab_to_axis(m[3], m[4]);
        assert!((0..3).all(|k| (axis[k] - p.axis[k]).abs() < 1e-4), "{m:?} vs {:?}", p.axis);
        leaning += usize::from(p.axis[2] < 0.999);
    }
    assert!(leaning > 0, "some positions lean");
    Ok(())
}
