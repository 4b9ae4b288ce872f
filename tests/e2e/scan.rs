//! The scan stage over gRPC: a mesh job is scanned on the simulated cell (the rotary table driven
//! over its protocol on a socket) into a registered cloud that goes on to reconstruction; bad scan
//! options are refused naming the field; the cell's device services answer.

use std::io::Cursor;
use std::time::Duration;

use depthmill_geometry::Mesh;
use depthmill_geometry::formats::read_ply_cloud_with_pass;
use depthmill_proto::scanning::v1 as pb;
use depthmill_tests::scripted::Script;
use depthmill_tests::{MachineBackend, StackOptions, TestStack};
use futures::StreamExt as _;
use serde_json::json;

/// The test part: a 30 × 30 mm sheet at z = 3 with a gentle dome (radius 12, 2.5 mm high, flanks
/// under 23° so a sensor looking down sees them).
pub(crate) fn dome(x: f64, y: f64) -> f64 {
    3.0 + 2.5 * (1.0 - (x * x + y * y) / 144.0).max(0.0)
}

pub(crate) fn dome_stl() -> Vec<u8> {
    dome_stl_in(1.0, "e2e dome")
}

/// The dome with every coordinate multiplied by `scale` (a file in other units), STL header `header`.
fn dome_stl_in(scale: f64, header: &str) -> Vec<u8> {
    let n = 81;
    let mut vertices = Vec::new();
    for j in 0..n {
        for i in 0..n {
            let x = -15.0 + 30.0 * i as f64 / (n - 1) as f64;
            let y = -15.0 + 30.0 * j as f64 / (n - 1) as f64;
            vertices.push(nalgebra::Point3::new(x, y, dome(x, y)) * scale);
        }
    }
    let mut triangles = Vec::new();
    for j in 0..n - 1 {
        for i in 0..n - 1 {
            let a = (j * n + i) as u32;
            triangles.push([a, a + 1, a + 1 + n as u32]);
            triangles.push([a, a + 1 + n as u32, a + n as u32]);
        }
    }
    let mut bytes = Vec::new();
    depthmill_geometry::formats::write_stl(&mut bytes, &Mesh { vertices, triangles }, header)
        .expect("writing to memory");
    bytes
}

/// The stack with a scripted machine (these tests stop at planning).
async fn scripted_stack() -> anyhow::Result<TestStack> {
    TestStack::start_with(StackOptions {
        machine: MachineBackend::Scripted(Script::default()),
        ..Default::default()
    })
    .await
}

/// A quick job on the dome: one table angle, coarse lines and maps.
fn quick_job(sha: &str, mode: &str) -> serde_json::Value {
    json!({"input": {"kind": "mesh", "artifact": sha},
           "scan": {"table_angles_deg": [90], "line_spacing_mm": 1.0, "mode": mode},
           "reconstruct": {"pixel_mm": 0.5},
           "plan": {"stock": {"z_mm": 8}, "roughing": {"tool": "flat-6", "step_down_mm": 3.0},
                    "finishing": {"tool": "ball-6", "step_over_mm": 2.0}}})
}

async fn fetch(stack: &TestStack, job: &serde_json::Value, name: &str) -> anyhow::Result<Vec<u8>> {
    let sha = job["artifacts"][name]["sha256"].as_str().unwrap_or_default();
    Ok(stack.http.get(stack.url(&format!("/v1/artifacts/{sha}"))).send().await?.bytes().await?.to_vec())
}

#[tokio::test]
async fn a_mesh_job_is_scanned_into_a_cloud_on_the_part_and_goes_on_to_reconstruction() -> anyhow::Result<()>
{
    let stack = scripted_stack().await?;
    let sha = stack.upload("model/stl", dome_stl()).await?;
    let job = json!({
        "name": "scanned dome",
        "input": {"kind": "mesh", "artifact": sha},
        "scan": {"mode": "dynamic", "table_angles_deg": [0, 180], "line_spacing_mm": 0.4,
                 "line_rate_hz": 150, "adaptive_rescan": true},
        "reconstruct": {"pixel_mm": 0.3},
        "plan": {"stock": {"z_mm": 8, "material": "aluminium"},
                 "roughing": {"tool": "flat-6", "step_down_mm": 3.0},
                 "finishing": {"tool": "ball-3", "step_over_mm": 1.0}}
    });
    let (status, created) = stack.post_job(&job, None).await?;
    assert_eq!(status, 201, "{created}");
    let done = stack.wait_for_end(created["id"].as_str().expect("id"), Duration::from_secs(300)).await?;
    assert_eq!(done["status"], "succeeded", "{done}");
    for name in ["point_cloud", "scan_report", "depth_map", "coverage_map", "gcode"] {
        assert!(done["artifacts"][name]["sha256"].is_string(), "{name} missing: {done}");
    }
    assert!(done["stage_timings_s"]["scan"].as_f64().unwrap_or(0.0) > 0.0, "{done}");
    let m = &done["metrics"];
    assert!(m["scan_points"].as_f64().unwrap_or(0.0) > 20_000.0, "{m}");
    // The simulated cell is off its drawing: the job calibrated it first (version 1, in force)
    // and the views agree within twice the scanner's 35 µm noise.
    assert!(m["scan_registration_rms_mm"].as_f64().unwrap_or(1.0) < 0.07, "{m}");
    assert!(m["scan_registration_merge_rms_mm"].as_f64().unwrap_or(1.0) < 0.07, "{m}");
    assert_eq!(m["scan_calibration_version"].as_f64(), Some(1.0), "{m}");
    // Two stations cannot find the table's axis: the routine ran before the scan, and the job
    // says so.
    let how = done["diagnostics"].as_array().into_iter().flatten().find(|d| d["code"] == "cell_calibrated");
    let how = how.and_then(|d| d["message"].as_str()).unwrap_or_default();
    assert!(how.contains("by the routine before the scan") && how.contains("3 or more"), "{how}");

    // The cloud: binary PLY with intensity and pass ids, on the part within the scanner's noise.
    let ply = fetch(&stack, &done, "point_cloud").await?;
    let (cloud, pass, _) = read_ply_cloud_with_pass(Cursor::new(ply), "cloud.ply", &Default::default())?;
    let pass = pass.expect("pass ids");
    assert_eq!(pass.len(), cloud.points.len());
    assert!(cloud.intensity.is_some());
    let (mut sq, mut n, mut max) = (0.0, 0usize, 0.0f64);
    for p in cloud.points.iter().map(|p| p.cast::<f64>()).filter(|p| p.x.abs() < 14.0 && p.y.abs() < 14.0) {
        // Vertical distance; the dome's flanks are gentle, so this bounds the normal distance.
        let d = p.z - dome(p.x, p.y);
        sq += d * d;
        n += 1;
        max = max.max(d.abs());
    }
    let rms = (sq / n as f64).sqrt();
    println!("scanned cloud: {n} points on the part, RMS {rms:.4} mm, max {max:.4} mm");
    assert!(rms < 0.05 && max < 0.3, "RMS {rms} max {max}");

    // The report says what was done, including the rescan.
    let report: serde_json::Value = serde_json::from_slice(&fetch(&stack, &done, "scan_report").await?)?;
    assert_eq!(report["stations"][0]["table_deg_commanded"], 0.0);
    assert!(report["coverage_before_rescan"]["covered_pct"].as_f64().is_some(), "{report}");

    // The depth map of the scan matches the part.
    let errs = errors_against_dome(fetch(&stack, &done, "depth_map").await?)?;
    let median = errs[errs.len() / 2];
    let p99 = errs[errs.len() * 99 / 100];
    println!(
        "depth map vs part: median {median:.4} mm, 99th percentile {p99:.4} mm over {} cells",
        errs.len()
    );
    // Max-Z binning keeps the highest of a cell's samples: about +2σ of the noise on a 0.3 mm pixel.
    assert!(median < 0.1 && p99 < 0.25, "median {median} p99 {p99}");
    stack.shutdown().await
}

/// |depth map - dome| over the dome's inner cells (at least 100), mm, sorted.
fn errors_against_dome(png: Vec<u8>) -> anyhow::Result<Vec<f64>> {
    let map = depthmill_geometry::read_png_from(Cursor::new(png), None)?;
    let meta = *map.meta();
    let mut errs = Vec::new();
    for row in 0..meta.height {
        for col in 0..meta.width {
            let (x, y) = meta.cell_center(col, row);
            let z = map.get(col, row).unwrap_or(f32::NAN);
            if x.abs() < 13.0 && y.abs() < 13.0 && z.is_finite() {
                errs.push((f64::from(z) - dome(x, y)).abs());
            }
        }
    }
    anyhow::ensure!(errs.len() > 100, "only {} cells on the dome", errs.len());
    errs.sort_by(f64::total_cmp);
    Ok(errs)
}

#[tokio::test]
async fn meshes_in_metres_and_inches_are_scanned_in_millimetres() -> anyhow::Result<()> {
    let stack = scripted_stack().await?;
    // In metres with nothing saying so (read from its size); in inches named by the job; in
    // inches named by the STL header.
    let cases = [
        (dome_stl_in(0.001, "e2e dome"), None, "m", "size"),
        (dome_stl_in(1.0 / 25.4, "e2e dome"), Some("in"), "in", "given"),
        (dome_stl_in(1.0 / 25.4, "e2e dome, units: inch"), None, "in", "header"),
    ];
    for (stl, units, want_unit, want_source) in cases {
        let sha = stack.upload("model/stl", stl).await?;
        let mut job = quick_job(&sha, "dynamic");
        if let Some(u) = units {
            job["input"]["units"] = json!(u);
        }
        let (status, created) = stack.post_job(&job, None).await?;
        assert_eq!(status, 201, "{created}");
        let done = stack.wait_for_end(created["id"].as_str().expect("id"), Duration::from_secs(300)).await?;
        assert_eq!(done["status"], "succeeded", "{done}");
        let report: serde_json::Value = serde_json::from_slice(&fetch(&stack, &done, "scan_report").await?)?;
        assert_eq!(report["units"]["unit"], want_unit, "{}", report["units"]);
        assert_eq!(report["units"]["source"], want_source, "{}", report["units"]);
        let errs = errors_against_dome(fetch(&stack, &done, "depth_map").await?)?;
        let median = errs[errs.len() / 2];
        println!("dome in {want_unit} ({want_source}): depth map vs the dome in mm, median {median:.4} mm");
        assert!(median < 0.1, "median {median}");
    }
    // Units are for meshes and clouds only.
    let sha = stack.upload("text/x-gcode", b"G0 X0\nM30\n".to_vec()).await?;
    let (status, body) =
        stack.post_job(&json!({"input": {"kind": "gcode", "artifact": sha, "units": "in"}}), None).await?;
    assert_eq!(status, 400, "{body}");
    assert_eq!(body["error"]["field"], "input.units", "{body}");
    stack.shutdown().await
}

#[tokio::test]
async fn bad_scan_options_are_refused_and_the_service_keeps_working() -> anyhow::Result<()> {
    let stack = scripted_stack().await?;
    let sha = stack.upload("model/stl", dome_stl()).await?;
    // At submission: outside the scanner's window.
    let (status, body) = stack
        .post_job(&json!({"input": {"kind": "mesh", "artifact": sha}, "scan": {"standoff_mm": 300}}), None)
        .await?;
    assert_eq!(status, 400, "{body}");
    assert_eq!(body["error"]["field"], "scan.standoff_mm", "{body}");
    // In the stage: a given pass 1.5 m from the robot.
    let far = json!({"input": {"kind": "mesh", "artifact": sha},
                     "scan": {"passes": [{"table_deg": 0, "start_mm": [1500, 0, 150], "end_mm": [1500, 40, 150]}]}});
    let (status, created) = stack.post_job(&far, None).await?;
    assert_eq!(status, 201, "{created}");
    let failed = stack.wait_for_end(created["id"].as_str().expect("id"), Duration::from_secs(60)).await?;
    assert_eq!(failed["status"], "failed", "{failed}");
    assert_eq!(failed["error"]["stage"], "scan");
    assert_eq!(failed["error"]["code"], "invalid_argument", "{failed}");
    assert!(failed["error"]["message"].as_str().unwrap_or_default().contains("cannot reach"), "{failed}");
    assert!(failed["artifacts"].get("point_cloud").is_none());
    // The service still scans.
    let ok = quick_job(&sha, "stop_and_move");
    let (_, created) = stack.post_job(&ok, None).await?;
    let done = stack.wait_for_end(created["id"].as_str().expect("id"), Duration::from_secs(300)).await?;
    assert_eq!(done["status"], "succeeded", "{done}");
    stack.shutdown().await
}

#[tokio::test]
async fn the_cells_devices_answer_over_grpc() -> anyhow::Result<()> {
    let stack = TestStack::start().await?;
    let url = stack
        .service_urls()
        .into_iter()
        .find(|(name, _)| name == "depthmill.scanning.v1.MotionControllerService")
        .map(|(_, u)| u)
        .expect("the scanning service serves the motion controller");
    let channel = depthmill_tests::service_channel(url).await?;
    let mut motion =
        pb::motion_controller_service_client::MotionControllerServiceClient::new(channel.clone());
    let mut latch = pb::encoder_latch_service_client::EncoderLatchServiceClient::new(channel);
    let robot = || pb::MotionRequest { device: "robot".into() };
    let table = || pb::MotionRequest { device: "table".into() };

    // The arm: moves need Initialize and Home; Reset latches an emergency stop.
    let refused = motion
        .r#move(pb::MoveRequest { device: "robot".into(), axis: 1, target_deg: 10.0, ..Default::default() })
        .await;
    let status = refused.expect_err("not initialized");
    assert_eq!(status.code(), tonic::Code::FailedPrecondition, "{status:?}");
    assert!(motion.initialize(robot()).await?.into_inner().initialized);
    motion.home(robot()).await?;
    for _ in 0..100 {
        if !motion.read_status(robot()).await?.into_inner().moving {
            break;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let bad = motion
        .r#move(pb::MoveRequest { device: "robot".into(), axis: 2, target_deg: 100.0, ..Default::default() })
        .await;
    assert_eq!(bad.expect_err("joint limit").code(), tonic::Code::InvalidArgument);
    motion
        .r#move(pb::MoveRequest { device: "robot".into(), axis: 1, target_deg: 10.0, ..Default::default() })
        .await?;
    let mut q1 = 0.0;
    for _ in 0..100 {
        q1 = motion.read_position(robot()).await?.into_inner().joints_deg[0];
        if (q1 - 10.0).abs() < 1e-6 {
            break;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    assert!((q1 - 10.0).abs() < 1e-6, "joint 1 at {q1}");
    motion.reset(robot()).await?;
    let after = motion
        .r#move(pb::MoveRequest { device: "robot".into(), axis: 1, target_deg: 0.0, ..Default::default() })
        .await;
    assert!(after.expect_err("e-stop").message().contains("emergency stop"));

    // The table, over its protocol.
    motion.initialize(table()).await?;
    motion
        .r#move(pb::MoveRequest {
            device: "table".into(),
            axis: 1,
            target_deg: 10.0,
            speed_deg_s: Some(45.0),
            accel_deg_s2: Some(120.0),
        })
        .await?;
    let mut a = 0.0;
    for _ in 0..150 {
        a = motion.read_position(table()).await?.into_inner().joints_deg[0];
        if (a - 10.0).abs() < 0.05 {
            break;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    assert!((a - 10.0).abs() < 0.05, "table at {a}");

    // The latch: events at the sync pulses with the robot's pose and the table's angle.
    latch.initialize(pb::LatchRequest {}).await?;
    let caps = latch.dev_caps(pb::LatchRequest {}).await?.into_inner();
    assert_eq!(caps.encoders, 7);
    assert!(latch.latch_encoders(pb::LatchRequest {}).await.is_err(), "not latching yet");
    latch.begin_latching(pb::LatchRequest {}).await?;
    let mut events = latch.latch_encoders(pb::LatchRequest {}).await?.into_inner();
    let mut got = Vec::new();
    while got.len() < 5 {
        match tokio::time::timeout(Duration::from_secs(5), events.next()).await? {
            Some(e) => got.push(e?),
            None => break,
        }
    }
    assert_eq!(got.len(), 5);
    assert!(got[0].first_external_clock && !got[1].first_external_clock);
    assert!(got.windows(2).all(|w| w[1].pulse == w[0].pulse + 1 && w[1].time_s > w[0].time_s));
    assert!((got[0].table_deg - 10.0).abs() < 0.05);
    assert!(got[0].robot.as_ref().is_some_and(|p| p.z_mm.is_finite()));
    latch.end_latching(pb::LatchRequest {}).await?;
    // The stream ends once latching stops.
    let rest = tokio::time::timeout(Duration::from_secs(5), async {
        while let Some(e) = events.next().await {
            e?;
        }
        anyhow::Ok(())
    })
    .await;
    assert!(rest.is_ok(), "the event stream ends after EndLatching");
    stack.shutdown().await
}

#[tokio::test]
async fn a_running_scan_is_cancelled_through_the_service_which_then_scans_again() -> anyhow::Result<()> {
    let stack = scripted_stack().await?;
    let sha = stack.upload("model/stl", dome_stl()).await?;
    // Many table stations: the table turns in real time between them, so the stage runs for a while.
    let slow = json!({"input": {"kind": "mesh", "artifact": sha},
                      "scan": {"table_angles_deg": [0, 180, 0, 180, 0, 180, 0, 180], "line_spacing_mm": 1.0}});
    let (_, created) = stack.post_job(&slow, None).await?;
    let id = created["id"].as_str().expect("id").to_string();
    for _ in 0..500 {
        let j = stack.get_job(&id).await?;
        if j["status"] == "running" && j["stage"] == "scan" {
            break;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    tokio::time::sleep(Duration::from_millis(500)).await;
    let resp = stack.http.post(stack.url(&format!("/v1/jobs/{id}/cancel"))).send().await?;
    assert_eq!(resp.status(), 200);
    let job = stack.wait_for_end(&id, Duration::from_secs(60)).await?;
    assert_eq!(job["status"], "cancelled", "{job}");
    let scan_outcomes: Vec<&str> = job["attempts"]
        .as_array()
        .into_iter()
        .flatten()
        .filter(|a| a["stage"] == "scan")
        .filter_map(|a| a["outcome"].as_str())
        .collect();
    assert_eq!(scan_outcomes, ["cancelled"], "the scan itself was stopped, not finished: {job}");
    assert!(job["artifacts"].get("point_cloud").is_none(), "no half-written cloud");
    // The cell is free again.
    let ok = quick_job(&sha, "dynamic");
    let (_, created) = stack.post_job(&ok, None).await?;
    let done = stack.wait_for_end(created["id"].as_str().expect("id"), Duration::from_secs(300)).await?;
    assert_eq!(done["status"], "succeeded", "{done}");
    stack.shutdown().await
}

#[tokio::test]
async fn a_new_cell_is_calibrated_at_the_first_scans_own_stations() -> anyhow::Result<()> {
    let stack = scripted_stack().await?;
    let sha = stack.upload("model/stl", dome_stl()).await?;
    let job = |angles: serde_json::Value| {
        let mut j = quick_job(&sha, "dynamic");
        j["scan"]["table_angles_deg"] = angles;
        j["scan"]["line_spacing_mm"] = json!(0.5);
        j
    };
    // No calibration in force: three stations over 240° serve the routine too, and the part
    // leaves the reference sphere's nest free, so the table turns once for both.
    let (_, created) = stack.post_job(&job(json!([0, 120, 240])), None).await?;
    let done = stack.wait_for_end(created["id"].as_str().expect("id"), Duration::from_secs(300)).await?;
    assert_eq!(done["status"], "succeeded", "{done}");
    let m = &done["metrics"];
    assert_eq!(m["scan_calibration_version"].as_f64(), Some(1.0), "{m}");
    assert!(m["scan_registration_rms_mm"].as_f64().unwrap_or(1.0) < 0.07, "{m}");
    assert!(m["scan_registration_merge_rms_mm"].as_f64().unwrap_or(1.0) < 0.07, "{m}");
    let said: Vec<String> = done["diagnostics"]
        .as_array()
        .into_iter()
        .flatten()
        .filter(|d| d["code"] == "cell_calibrated")
        .filter_map(|d| d["message"].as_str().map(String::from))
        .collect();
    assert!(said.len() == 1 && said[0].contains("at this scan's stations"), "{said:?}");
    let report: serde_json::Value = serde_json::from_slice(&fetch(&stack, &done, "scan_report").await?)?;
    assert_eq!(report["calibration"]["during_scan"], true, "{}", report["calibration"]);
    // The table stopped at the scan's stations only: each scanned the part as well as the sphere.
    for st in report["stations"].as_array().into_iter().flatten() {
        let passes = st["passes"].as_array().cloned().unwrap_or_default();
        assert!(passes.iter().any(|p| p["points"].as_u64().unwrap_or(0) > 0), "{st}");
        assert!(passes.iter().any(|p| p["points"] == 0), "{st}");
    }
    assert!(report["calibration"]["truth"]["table_error_mm"].as_f64().unwrap_or(1.0) < 0.05, "{report}");
    // Stored as version 1 with its trigger, and in force for the next job, which calibrates
    // nothing; two stations could not have found the axis, but the cell is calibrated already.
    let list: serde_json::Value = stack.http.get(stack.url("/v1/calibrations")).send().await?.json().await?;
    let cals = list["calibrations"].as_array().cloned().unwrap_or_default();
    assert_eq!(cals.len(), 1, "{list}");
    assert_eq!(cals[0]["trigger"], "scan", "{list}");
    assert_eq!(cals[0]["version"], 1, "{list}");
    let (_, created) = stack.post_job(&job(json!([0, 180])), None).await?;
    let next = stack.wait_for_end(created["id"].as_str().expect("id"), Duration::from_secs(300)).await?;
    assert_eq!(next["status"], "succeeded", "{next}");
    assert_eq!(next["metrics"]["scan_calibration_version"].as_f64(), Some(1.0), "{next}");
    assert!(
        !next["diagnostics"].as_array().into_iter().flatten().any(|d| d["code"] == "cell_calibrated"),
        "{next}"
    );
    stack.shutdown().await
}

#[tokio::test]
async fn the_cell_is_calibrated_over_rest_versioned_and_used_by_the_next_scan() -> anyhow::Result<()> {
    let stack = scripted_stack().await?;
    let url = stack.url("/v1/calibrations");
    // Degenerate options: refused naming what is missing, nothing stored.
    let bad = stack.http.post(&url).json(&json!({"table_angles_deg": [0, 90]})).send().await?;
    assert_eq!(bad.status(), 400);
    let body: serde_json::Value = bad.json().await?;
    assert!(body["error"]["message"].as_str().unwrap_or_default().contains("3 or more"), "{body}");
    let unknown = stack.http.post(&url).json(&json!({"sphere": 3})).send().await?;
    assert_eq!(unknown.status(), 400);
    let list: serde_json::Value = stack.http.get(&url).send().await?.json().await?;
    assert_eq!(list["calibrations"].as_array().map(Vec::len), Some(0), "{list}");

    // Calibrate: version 1, the merge error of its own scans before (the drawing) and after.
    let made = stack.http.post(&url).send().await?;
    assert_eq!(made.status(), 201);
    let cal: serde_json::Value = made.json().await?;
    assert_eq!(cal["version"], 1, "{cal}");
    assert_eq!(cal["trigger"], "api");
    let report = &cal["report"];
    assert!(report["registration_before"]["merge_rms_mm"].as_f64().unwrap_or(0.0) > 0.2, "{report}");
    assert!(report["registration_after"]["merge_rms_mm"].as_f64().unwrap_or(1.0) < 0.07, "{report}");
    assert!(report["truth"]["table_error_mm"].as_f64().unwrap_or(1.0) < 0.05, "{report}");
    assert!(report["scan_time_s"].as_f64().unwrap_or(100.0) < 60.0, "{report}");
    assert!(cal["calibration"]["table"]["axis_x_mm"].as_f64().is_some(), "{cal}");
    let id = cal["id"].as_str().unwrap_or_default().to_string();
    let one: serde_json::Value =
        stack.http.get(stack.url(&format!("/v1/calibrations/{id}"))).send().await?.json().await?;
    assert_eq!(one["version"], 1);
    let missing = stack.http.get(stack.url("/v1/calibrations/cal_nope")).send().await?;
    assert_eq!(missing.status(), 404);

    // A second calibration starts from the first: version 2 is in force, already close.
    let again: serde_json::Value =
        stack.http.post(&url).json(&json!({"seed": 7})).send().await?.json().await?;
    assert_eq!(again["version"], 2, "{again}");
    assert!(again["report"]["registration_before"]["merge_rms_mm"].as_f64().unwrap_or(1.0) < 0.07, "{again}");
    let list: serde_json::Value = stack.http.get(&url).send().await?.json().await?;
    assert_eq!(list["calibrations"][0]["version"], 2, "{list}");
    // The same over gRPC: listed newest first, one by id, a bad option refused naming it.
    use depthmill_proto::orchestrator::v1 as opb;
    let mut grpc = stack.grpc().await?;
    let listed = grpc.list_calibrations(opb::ListCalibrationsRequest { limit: 0 }).await?.into_inner();
    assert_eq!(listed.calibrations.iter().map(|c| c.version).collect::<Vec<_>>(), [2, 1]);
    let first = grpc.get_calibration(opb::GetCalibrationRequest { id: id.clone() }).await?.into_inner();
    assert_eq!(first.version, 1);
    assert!(first.report_json.contains("registration_after"), "{}", first.report_json);
    let bad = grpc
        .create_calibration(opb::CreateCalibrationRequest {
            params_json: r#"{"sphere_radius_mm": 90}"#.into(),
        })
        .await
        .expect_err("a 90 mm ball is refused");
    assert_eq!(bad.code(), tonic::Code::InvalidArgument, "{bad:?}");
    assert!(bad.message().contains("sphere_radius_mm"), "{}", bad.message());

    // The next scan job places its points with version 2.
    let sha = stack.upload("model/stl", dome_stl()).await?;
    let (status, created) = stack.post_job(&quick_job(&sha, "dynamic"), None).await?;
    assert_eq!(status, 201, "{created}");
    let done = stack.wait_for_end(created["id"].as_str().expect("id"), Duration::from_secs(300)).await?;
    assert_eq!(done["status"], "succeeded", "{done}");
    assert_eq!(done["metrics"]["scan_calibration_version"].as_f64(), Some(2.0), "{done}");
    // Its report names the calibration with its residuals and its before/after merge error.
    let id = done["id"].as_str().unwrap_or_default();
    let html = stack.http.get(stack.url(&format!("/v1/jobs/{id}/report"))).send().await?.text().await?;
    for needle in [
        "Cell calibration",
        "version 2 (cal_",
        "sphere fit RMS",
        "merge error of its scans",
        "Merge error (after the best rigid fit)",
    ] {
        assert!(html.contains(needle), "{needle} missing from the report");
    }
    Ok(())
}
