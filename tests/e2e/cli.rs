//! The `depthmill` command line as a process (this test binary in the `Cli` child role, which runs
//! exactly what the binary runs): output into a pipe closed early ends quietly with success, a
//! server that is down or answers garbage gets one line on standard error and exit code 1.

use std::io::{BufRead as _, BufReader, Read as _};
use std::process::{Command, Stdio};

use anyhow::Context as _;
use depthmill_tests::TestStack;
use serde_json::json;

use crate::children::Role;

/// Runs the command line `args` in a child process; (exit code, stdout, stderr).
fn depthmill(args: &[&str]) -> anyhow::Result<(i32, String, String)> {
    let mut argv = vec!["depthmill".to_string()];
    argv.extend(args.iter().map(|a| a.to_string()));
    let role = serde_json::to_string(&Role::Cli { args: argv, after_stdin: false })?;
    let out = Command::new(std::env::current_exe()?)
        .args(["--ignored", "--exact", "children::child_process", "--nocapture", "--test-threads=1"])
        .env("DEPTHMILL_E2E_CHILD", role)
        .env_remove("DEPTHMILL_URL")
        .env_remove("DEPTHMILL_TOKEN")
        .stdin(Stdio::null())
        .output()?;
    Ok((
        out.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    ))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn output_into_a_closed_pipe_ends_quietly() -> anyhow::Result<()> {
    let stack = TestStack::start().await?;
    let sha = stack.upload("text/x-gcode", b"%\nG21 G90\nG0 X1\nM30\n%\n".to_vec()).await?;
    let (status, created) = stack
        .post_job(&json!({"input": {"kind": "gcode", "artifact": sha}, "execute": {"adaptive": "off"}}), None)
        .await?;
    anyhow::ensure!(status == 201, "{created}");
    let id = created["id"].as_str().context("id")?.to_string();
    let url = stack.rest_url.clone();

    // `depthmill status ID --json --url URL | head -0`: the reader is gone before the first write.
    let argv: Vec<String> =
        ["depthmill", "status", &id, "--json", "--url", &url].iter().map(|s| s.to_string()).collect();
    let role = serde_json::to_string(&Role::Cli { args: argv, after_stdin: true })?;
    let output = tokio::task::spawn_blocking(move || -> anyhow::Result<(i32, String)> {
        // Terse output (`-q`): the harness prints nothing between "running 1 test" and the end
        // of the test, which this process never reaches.
        let mut child = Command::new(std::env::current_exe()?)
            .args([
                "--ignored",
                "--exact",
                "children::child_process",
                "--nocapture",
                "--test-threads=1",
                "-q",
            ])
            .env("DEPTHMILL_E2E_CHILD", role)
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()?;
        // The test harness's own lines (up to "running 1 test"), then the pipe closes.
        let mut stdout = BufReader::new(child.stdout.take().context("stdout")?);
        let mut line = String::new();
        while stdout.read_line(&mut line)? > 0 && line.trim() != "running 1 test" {
            line.clear();
        }
        drop(stdout);
        drop(child.stdin.take());
        let mut stderr = String::new();
        child.stderr.take().context("stderr")?.read_to_string(&mut stderr)?;
        let status = child.wait()?;
        Ok((status.code().unwrap_or(-1), stderr))
    })
    .await??;
    let (code, stderr) = output;
    assert_eq!(code, 0, "a closed pipe is not an error: {stderr}");
    assert!(!stderr.contains("panicked"), "{stderr}");
    assert!(stderr.trim().is_empty(), "nothing on standard error: {stderr}");

    // The same verb into an open pipe prints the job.
    let (code, out, err) = depthmill(&["status", &id, "--json", "--url", &url])?;
    assert_eq!(code, 0, "{err}");
    assert!(out.contains(&id), "{out}");
    stack.shutdown().await
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_server_that_is_down_or_answers_garbage_gets_one_line_and_exit_1() -> anyhow::Result<()> {
    // Down: nothing listens on the port.
    let port = crate::children::free_addr()?.port();
    let down = format!("http://127.0.0.1:{port}");
    let (code, out, err) =
        tokio::task::spawn_blocking(move || depthmill(&["status", "some-job", "--url", &down])).await??;
    assert_eq!(code, 1, "{out}{err}");
    let line = err.trim();
    assert!(line.starts_with("depthmill: ") && !line.contains('\n'), "one line: {err:?}");
    assert!(!err.contains("panicked"), "{err}");

    // Garbage: an HTTP server answering 200 with something that is not the API's JSON.
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
    let garbage = format!("http://{}", listener.local_addr()?);
    tokio::spawn(async move {
        use tokio::io::{AsyncReadExt as _, AsyncWriteExt as _};
        while let Ok((mut socket, _)) = listener.accept().await {
            let mut buf = [0u8; 4096];
            let _ = socket.read(&mut buf).await;
            let _ = socket
                .write_all(b"HTTP/1.1 200 OK\r\ncontent-type: text/html\r\ncontent-length: 14\r\nconnection: close\r\n\r\n<html>hi</html")
                .await;
        }
    });
    let dir = tempfile::tempdir()?;
    let into = dir.path().join("fetched").display().to_string();
    for verb in [vec!["status", "some-job"], vec!["fetch", "some-job", "-o", into.as_str()]] {
        let mut args: Vec<String> = verb.iter().map(|s| s.to_string()).collect();
        args.extend(["--url".to_string(), garbage.clone()]);
        let (code, out, err) = tokio::task::spawn_blocking(move || {
            let refs: Vec<&str> = args.iter().map(String::as_str).collect();
            depthmill(&refs)
        })
        .await??;
        assert_eq!(code, 1, "{verb:?}: {out}{err}");
        let line = err.trim();
        assert!(line.starts_with("depthmill: ") && !line.contains('\n'), "{verb:?}: one line: {err:?}");
        assert!(!err.contains("panicked"), "{err}");
    }
    Ok(())
}

/// A box `lo`..`hi` as triangles, faces outward (or inward: a cavity), vertex indices from `o`.
fn cuboid(
    v: &mut Vec<depthmill_geometry::nalgebra::Point3<f64>>,
    t: &mut Vec<[u32; 3]>,
    lo: [f64; 3],
    hi: [f64; 3],
    inward: bool,
) {
    let o = v.len() as u32;
    for k in 0..8 {
        v.push(depthmill_geometry::nalgebra::Point3::new(
            if k & 1 == 0 { lo[0] } else { hi[0] },
            if k & 2 == 0 { lo[1] } else { hi[1] },
            if k & 4 == 0 { lo[2] } else { hi[2] },
        ));
    }
    for f in [[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2], [1, 3, 7, 5]] {
        let (a, b, c, d) = (o + f[0], o + f[1], o + f[2], o + f[3]);
        for tri in [[a, b, c], [a, c, d]] {
            t.push(if inward { [tri[0], tri[2], tri[1]] } else { tri });
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn slicing_a_mesh_writes_its_layers_and_names_what_is_wrong() -> anyhow::Result<()> {
    let dir = tempfile::tempdir()?;
    let (mut v, mut t) = (Vec::new(), Vec::new());
    cuboid(&mut v, &mut t, [0.0; 3], [20.0, 20.0, 10.0], false);
    cuboid(&mut v, &mut t, [5.0, 5.0, 2.0], [15.0, 15.0, 8.0], true);
    let write = |name: &str, t: &[[u32; 3]]| -> anyhow::Result<String> {
        let path = dir.path().join(name);
        let mesh = depthmill_geometry::Mesh::new(v.clone(), t.to_vec())?;
        let mut f = std::fs::File::create(&path)?;
        depthmill_geometry::formats::write_stl(&mut f, &mesh, "test box")?;
        Ok(path.display().to_string())
    };
    let closed = write("box.stl", &t)?;
    let out = dir.path().join("layers.json").display().to_string();
    let (code, stdout, stderr) = depthmill(&["slice", &closed, "--step-mm", "2", "-o", &out])?;
    assert_eq!(code, 0, "{stdout}{stderr}");
    assert!(stdout.contains("5 layers from 1.0000 to 9.0000 mm every 2 mm"), "{stdout}");
    let doc: serde_json::Value = serde_json::from_slice(&std::fs::read(&out)?)?;
    assert_eq!(doc["topology"]["closed_manifold"], json!(true));
    let layers = doc["layers"].as_array().context("layers")?;
    assert_eq!(layers.len(), 5);
    // z = 3, 5, 7 cut the cavity: an outer square and a hole in it; z = 1 and 9 the block only.
    let kinds = |l: &serde_json::Value| -> Vec<String> {
        l["contours"].as_array().map_or(Vec::new(), |c| {
            let mut k: Vec<String> =
                c.iter().map(|c| c["kind"].as_str().unwrap_or("?").to_string()).collect();
            k.sort();
            k
        })
    };
    assert_eq!(kinds(&layers[0]), ["outer"]);
    assert_eq!(kinds(&layers[2]), ["hole", "outer"]);
    let area: f64 = layers[2]["contours"]
        .as_array()
        .context("contours")?
        .iter()
        .filter_map(|c| c["area_mm2"].as_f64())
        .sum();
    assert!((area - 300.0).abs() < 1e-9, "{area}");

    // Rings for a tool: the cavity (10 mm) takes a 6 mm tool, a 12 mm one is reported.
    let (code, stdout, stderr) =
        depthmill(&["slice", &closed, "--step-mm", "2", "--tool", "flat-6", "-o", &out])?;
    assert_eq!(code, 0, "{stdout}{stderr}");
    assert!(stdout.contains("flat-6: ") && !stdout.contains("not cut"), "{stdout}");
    let doc: serde_json::Value = serde_json::from_slice(&std::fs::read(&out)?)?;
    let rings = doc["passes"]["layers"][2]["rings"].as_array().context("rings")?;
    // Out to the stock's corners 5 mm beyond the part, then the finishing ring 3 mm off it.
    assert!(rings.len() >= 2, "{rings:?}");
    assert_eq!(rings.last().context("ring")?["offset_mm"], json!(3.0));
    // The layers' program as G-code: LinuxCNC-style, the tool in the header, and the machine
    // service's interpreter takes it within the mill's travel.
    let ngc = dir.path().join("box.ngc").display().to_string();
    let (code, stdout, stderr) =
        depthmill(&["slice", &closed, "--step-mm", "2", "--tool", "flat-6", "--gcode", &ngc, "-o", &out])?;
    assert_eq!(code, 0, "{stdout}{stderr}");
    assert!(stdout.contains("program: ") && stdout.contains("feed links"), "{stdout}");
    let text = std::fs::read_to_string(&ngc)?;
    assert!(
        text.contains("(T1 flat-6: flat D6.0000 mm, 2 flutes - layers)") && text.trim_end().ends_with('%')
    );
    let (code, stdout, stderr) = depthmill(&["check", &ngc])?;
    assert_eq!(code, 0, "{stdout}{stderr}");
    let (code, stdout, stderr) =
        depthmill(&["slice", &closed, "--step-mm", "2", "--tool", "flat-12", "-o", &out])?;
    assert_eq!(code, 0, "{stdout}{stderr}");
    assert!(stdout.contains("3 holes narrower than the tool are not cut"), "{stdout}");
    let (code, _, stderr) = depthmill(&["slice", &closed, "--tool", "spoon-3", "-o", &out])?;
    assert_eq!(code, 1);
    assert!(stderr.contains("--tool spoon-3"), "{stderr}");

    // An open mesh: the edges are listed and the layer through the gap has an open chain.
    let mut open = t.clone();
    let gone = open.remove(4); // a -y wall triangle of the block
    let path = write("open.stl", &open)?;
    let (code, stdout, stderr) = depthmill(&["slice", &path, "--step-mm", "2", "-o", &out])?;
    assert_eq!(code, 0, "{stdout}{stderr}");
    assert!(stdout.contains("3 boundary edges (open)"), "{stdout}");
    let doc: serde_json::Value = serde_json::from_slice(&std::fs::read(&out)?)?;
    assert_eq!(doc["topology"]["boundary_edges"], json!(3));
    let listed = doc["topology"]["boundary"].as_array().context("boundary")?;
    // (Listed by coordinates too: the reader renumbers the welded vertices.)
    let corners: Vec<[f64; 3]> =
        gone.iter().map(|&i| [v[i as usize].x, v[i as usize].y, v[i as usize].z]).collect();
    let is_corner = |p: &serde_json::Value| -> bool {
        corners.iter().any(|c| (0..3).all(|k| p[k].as_f64().is_some_and(|x| (x - c[k]).abs() < 1e-9)))
    };
    assert_eq!(listed.len(), 3);
    assert!(listed.iter().all(|e| is_corner(&e["from_mm"]) && is_corner(&e["to_mm"])), "{listed:?}");
    let chains: usize = doc["layers"]
        .as_array()
        .context("layers")?
        .iter()
        .map(|l| l["open"].as_array().map_or(0, Vec::len))
        .sum();
    assert!(chains > 0, "{doc}");

    // Bad calls: one line naming what is wrong, exit 1, nothing written.
    let none = dir.path().join("none.json");
    let (code, _, stderr) =
        depthmill(&["slice", &closed, "--step-mm", "-1", "-o", &none.display().to_string()])?;
    assert_eq!(code, 1);
    assert!(stderr.contains("--step-mm -1: must be a positive number"), "{stderr}");
    let (code, _, stderr) =
        depthmill(&["slice", &closed, "--from-mm", "50", "-o", &none.display().to_string()])?;
    assert_eq!(code, 1);
    assert!(stderr.contains("above the mesh's highest point"), "{stderr}");
    assert!(!none.exists());
    Ok(())
}

/// `depthmill plan MESH --robot`: a block 20 x 20 x 60 mm milled layer by layer by the arm. Near
/// its foot the upright holder (32 mm across, 34 mm above the tip) would hit the block's own
/// wall, so the tool leans out; every position of the joint trajectory puts the tip where the
/// program says (checked here by the arm's forward kinematics), one branch throughout. Then
/// `depthmill simulate --robot` replays the joints on a dexel stock and measures the part against
/// the mesh. Bad combinations, a part out of reach and a file that is not a trajectory are
/// refused with what is wrong.
#[test]
fn a_mesh_is_planned_for_the_robot_with_the_holder_clear() -> anyhow::Result<()> {
    use depthmill_geometry::arm::ArmModel;
    use depthmill_geometry::nalgebra::{Matrix4, Vector3};
    let dir = tempfile::tempdir()?;
    let (mut v, mut t) = (Vec::new(), Vec::new());
    cuboid(&mut v, &mut t, [0.0; 3], [20.0, 20.0, 60.0], false);
    let stl = dir.path().join("tall.stl");
    let mesh = depthmill_geometry::Mesh::new(v, t)?;
    depthmill_geometry::formats::write_stl(&mut std::fs::File::create(&stl)?, &mesh, "tall block")?;
    let stl = stl.display().to_string();
    let ngc = dir.path().join("tall.ngc").display().to_string();
    let (code, stdout, stderr) = depthmill(&["plan", &stl, "--robot", "--step-mm", "10", "-o", &ngc])?;
    assert_eq!(code, 0, "{stdout}{stderr}");
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("tall.robot.json"))?)?;
    let c = &report["clearance"];
    assert!(c["colliding_upright"].as_u64().context("colliding")? > 0, "{c}");
    assert!(c["tilted"].as_u64().context("tilted")? > 0, "{c}");
    // A few corner positions need a lean the arm cannot take there: lifted over, each listed.
    let blocked = c["blocked"].as_u64().context("blocked")?;
    assert!(blocked * 50 <= c["positions"].as_u64().context("positions")?, "{c}");
    assert_eq!(c["blocked_positions"].as_array().context("listed")?.len() as u64, blocked.min(100));
    assert!(c["max_tilt_deg"].as_f64().context("tilt")? > 10.0, "{c}");
    assert_eq!(report["layers"], json!(6));
    let joints: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("tall.joints.json"))?)?;
    assert_eq!(joints["format"], json!("depthmill-joint-trajectory/1"));
    let matrix = |v: &serde_json::Value| -> anyhow::Result<Matrix4<f64>> {
        let rows: Vec<Vec<f64>> = serde_json::from_value(v.clone())?;
        Ok(Matrix4::from_fn(|r, c| rows[r][c]))
    };
    let base_from_part = matrix(&joints["base_from_part"])?;
    let flange_from_tip = matrix(&joints["flange_from_tip"])?;
    let arm = ArmModel::viper_s650();
    let points = joints["points"].as_array().context("points")?;
    assert!(points.len() > 100);
    let mut branches = std::collections::HashSet::new();
    for p in points.iter().filter(|p| p["reachable"] == json!(true)) {
        let q: [f64; 6] = serde_json::from_value(p["q_deg"].clone())?;
        let tip: [f64; 3] = serde_json::from_value(p["tip_mm"].clone())?;
        let axis: [f64; 3] = serde_json::from_value(p["axis"].clone())?;
        let part_from_tip = base_from_part.try_inverse().context("inverse")?
            * arm.flange(&q).to_homogeneous()
            * flange_from_tip;
        let at = Vector3::new(part_from_tip[(0, 3)], part_from_tip[(1, 3)], part_from_tip[(2, 3)]);
        assert!((at - Vector3::from(tip)).norm() < 1e-4, "{at:?} vs {tip:?}");
        // The tool frame's Z runs from the holder to the tip: against the program's axis.
        let z = Vector3::new(part_from_tip[(0, 2)], part_from_tip[(1, 2)], part_from_tip[(2, 2)]);
        assert!((z + Vector3::from(axis)).norm() < 1e-6, "{z:?} vs {axis:?}");
        branches.insert(arm.configuration(&q));
    }
    assert_eq!(branches.len(), 1, "{branches:?}");
    let program = std::fs::read_to_string(&ngc)?;
    let word = |l: &str, w: char| -> Option<f64> {
        l.split_whitespace().find_map(|t| t.strip_prefix(w).and_then(|x| x.parse::<f64>().ok()))
    };
    assert!(
        program.lines().filter(|l| l.starts_with("G1 ")).any(|l| {
            word(l, 'A').is_some_and(|a| a.abs() > 1.0) || word(l, 'B').is_some_and(|b| b.abs() > 1.0)
        }),
        "leaning feed moves in the program"
    );

    // Run on the simulated arm: the joints replayed through its kinematics on a dexel stock,
    // the part measured against the mesh: nothing cut by a rapid, no gouge beyond a cell.
    let sim = dir.path().join("sim").display().to_string();
    let joints_path = dir.path().join("tall.joints.json").display().to_string();
    let (code, stdout, stderr) =
        depthmill(&["simulate", &joints_path, "--robot", "--part", &stl, "--cell-mm", "0.5", "-o", &sim])?;
    assert_eq!(code, 0, "{stdout}{stderr}");
    let run: serde_json::Value = serde_json::from_slice(&std::fs::read(dir.path().join("sim/report.json"))?)?;
    assert_eq!(run["rapid_removed_mm3"], json!(0.0), "{run}");
    assert!(run["removed_mm3"].as_f64().context("removed")? > 1000.0, "{run}");
    let gouge = run["deviation"]["max_gouge_mm"].as_f64().context("gouge")?;
    assert!(gouge <= 0.5, "max gouge {gouge} mm: {run}");
    assert!(dir.path().join("sim/part.stl").is_file());
    let (code, _, stderr) = depthmill(&["simulate", &stl, "--robot", "-o", &sim])?;
    assert_eq!(code, 1);
    assert!(stderr.contains("trajectory:"), "{stderr}");

    let (code, _, stderr) = depthmill(&["plan", &stl, "--robot", "--options", &stl, "-o", &ngc])?;
    assert_eq!(code, 1);
    assert!(stderr.contains("--options and --roughing-map do not apply"), "{stderr}");
    let (code, _, stderr) = depthmill(&["plan", &stl, "--robot", "--part-at", "3000,0,0", "-o", &ngc])?;
    assert_eq!(code, 1);
    assert!(stderr.contains("the arm reaches none"), "{stderr}");
    let (code, _, stderr) = depthmill(&["plan", &stl, "--robot", "--part-at", "1,2", "-o", &ngc])?;
    assert_eq!(code, 1);
    assert!(stderr.contains("--part-at 1,2"), "{stderr}");
    Ok(())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_part_scanned_on_the_mill_merges_by_the_chain_and_bad_options_are_named() -> anyhow::Result<()> {
    let dir = tempfile::tempdir()?;
    let (mut v, mut t) = (Vec::new(), Vec::new());
    cuboid(&mut v, &mut t, [0.0, -15.0, -15.0], [50.0, 15.0, 15.0], false);
    let mesh = dir.path().join("bar.stl");
    {
        let m = depthmill_geometry::Mesh::new(v, t)?;
        let mut f = std::fs::File::create(&mesh)?;
        depthmill_geometry::formats::write_stl(&mut f, &m, "bar")?;
    }
    let opts = dir.path().join("mill.json");
    std::fs::write(&opts, r#"{"a_angles_deg": [0, 180]}"#)?;
    let out = dir.path().join("bar.ply");
    let (mesh_s, opts_s, out_s) =
        (mesh.display().to_string(), opts.display().to_string(), out.display().to_string());
    let (code, stdout, stderr) =
        depthmill(&["scan", &mesh_s, "--on-machine", "--options", &opts_s, "-o", &out_s])?;
    assert_eq!(code, 0, "{stdout}{stderr}");
    assert!(stdout.contains("scanner calibrated against the machine"), "{stdout}");
    assert!(stdout.contains("merge error without markers"), "{stdout}");
    let report: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("bar.scan.json"))?)?;
    let merge = report["scan"]["registration"]["merge_rms_mm"].as_f64().context("merge")?;
    let noise = report["scan"]["registration_truth"]["rms_mm"].as_f64().context("noise")?;
    let drawing = report["scan"]["registration_drawing"]["merge_rms_mm"].as_f64().context("drawing")?;
    assert!(merge <= 2.0 * noise && drawing > 10.0 * merge, "{merge} {noise} {drawing}");
    assert_eq!(report["calibration"]["observations"].as_array().map(Vec::len), Some(13));
    // The cloud: a binary PLY with a shot id per point.
    let ply = std::fs::read(&out)?;
    let head = String::from_utf8_lossy(&ply[..ply.len().min(400)]).into_owned();
    assert!(head.contains("format binary_little_endian") && head.contains("property ushort pass"), "{head}");
    let points = report["scan"]["points"].as_u64().context("points")?;
    assert!(head.contains(&format!("element vertex {points}")) && points > 10_000, "{head}");
    // A bad option is named, nothing is written.
    std::fs::write(&opts, r#"{"a_angles_deg": [0], "standoff": 100}"#)?;
    let out2 = dir.path().join("bad.ply").display().to_string();
    let (code, stdout, stderr) =
        depthmill(&["scan", &mesh_s, "--on-machine", "--options", &opts_s, "-o", &out2])?;
    assert_eq!(code, 1, "{stdout}{stderr}");
    assert!(stderr.contains("standoff") && stderr.contains("mill.json"), "{stderr}");
    assert!(!std::path::Path::new(&out2).exists());
    Ok(())
}

/// `depthmill raster` of a part as OBJ (quads, relative references) and of a cloud as ASCII PCD,
/// each into a folder that does not exist yet (created), gives the same map as the STL of the
/// same block; a PCD missing its `z` field is refused naming the line, and writes nothing.
#[test]
fn raster_reads_obj_and_pcd_into_a_new_folder() -> anyhow::Result<()> {
    let dir = tempfile::tempdir()?;
    let (mut v, mut t) = (Vec::new(), Vec::new());
    cuboid(&mut v, &mut t, [0.0; 3], [20.0, 10.0, 5.0], false);
    let mesh = depthmill_geometry::Mesh::new(v.clone(), t.clone())?;
    let stl = dir.path().join("block.stl");
    depthmill_geometry::formats::write_stl(std::fs::File::create(&stl)?, &mesh, "block")?;
    let mut obj = String::from("# block in mm\no block\n");
    for p in &v {
        obj += &format!("v {} {} {}\n", p.x, p.y, p.z);
    }
    for tri in &t {
        let n = v.len() as i64;
        obj += &format!(
            "f {}//1 {}//1 {}//1\n",
            i64::from(tri[0]) - n,
            i64::from(tri[1]) - n,
            i64::from(tri[2]) - n
        );
    }
    let obj_path = dir.path().join("block.obj");
    std::fs::write(&obj_path, obj)?;
    let mut pcd = String::from(
        "# .PCD v0.7\nVERSION 0.7\nFIELDS x y z rgb\nSIZE 4 4 4 4\nTYPE F F F U\nCOUNT 1 1 1 1\n",
    );
    let grid: Vec<(f64, f64)> =
        (0..=40).flat_map(|i| (0..=20).map(move |j| (f64::from(i) * 0.5, f64::from(j) * 0.5))).collect();
    pcd += &format!(
        "WIDTH {}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {}\nDATA ascii\n",
        grid.len(),
        grid.len()
    );
    for (x, y) in &grid {
        pcd += &format!("{x} {y} 5 4278190080\n");
    }
    let pcd_path = dir.path().join("top.pcd");
    std::fs::write(&pcd_path, &pcd)?;

    let map_of =
        |input: &std::path::Path, out: &std::path::Path| -> anyhow::Result<depthmill_geometry::HeightMap> {
            let (code, stdout, stderr) = depthmill(&[
                "raster",
                &input.display().to_string(),
                "--pixel-mm",
                "0.5",
                "--units",
                "mm",
                "-o",
                &out.display().to_string(),
            ])?;
            assert_eq!(code, 0, "{stdout}{stderr}");
            Ok(depthmill_geometry::HeightMap::read(out, None)?)
        };
    let from_stl = map_of(&stl, &dir.path().join("stl/map.npy"))?;
    let from_obj = map_of(&obj_path, &dir.path().join("new/folder/map.npy"))?;
    assert_eq!((from_obj.width(), from_obj.height()), (from_stl.width(), from_stl.height()));
    let same = from_obj.data().iter().zip(from_stl.data()).all(|(a, b)| a == b || (a.is_nan() && b.is_nan()));
    assert!(same, "the OBJ's map differs from the STL's");
    // Gzip-compressed, the same map.
    let gz_path = dir.path().join("block.obj.gz");
    let mut gz =
        flate2::write::GzEncoder::new(std::fs::File::create(&gz_path)?, flate2::Compression::default());
    std::io::Write::write_all(&mut gz, &std::fs::read(&obj_path)?)?;
    gz.finish()?;
    let from_gz = map_of(&gz_path, &dir.path().join("gz/map.npy"))?;
    assert!(from_gz.bitwise_eq(&from_obj), "the gzip OBJ's map differs from the OBJ's");
    let from_pcd = map_of(&pcd_path, &dir.path().join("pcd/map.npy"))?;
    let measured: Vec<f32> = from_pcd.data().iter().copied().filter(|z| z.is_finite()).collect();
    assert!(measured.len() > 100 && measured.iter().all(|&z| (z - 5.0).abs() < 1e-6), "{}", measured.len());

    std::fs::write(&pcd_path, pcd.replace("FIELDS x y z rgb", "FIELDS x y q rgb"))?;
    let out = dir.path().join("bad/map.npy");
    let (code, _, stderr) =
        depthmill(&["raster", &pcd_path.display().to_string(), "-o", &out.display().to_string()])?;
    assert_eq!(code, 1, "{stderr}");
    assert!(stderr.contains("line 3: PCD: no field z (the fields are x y q rgb)"), "{stderr}");
    assert!(!out.exists() && !dir.path().join("bad").exists());
    Ok(())
}
