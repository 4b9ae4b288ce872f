//! The plan stage over gRPC: a depth map job planned by the real CAM service.

use std::time::Duration;

use depthmill_geometry::{HeightMap, HeightMapMeta, PngDepth};
use depthmill_tests::scripted::Script;
use depthmill_tests::{MachineBackend, StackOptions, TestStack};
use serde_json::{Value, json};

/// A 24 x 20 mm block at 0.4 mm pixels with a dome of radius 7 mm rising to 9 mm from a 2 mm base.
pub(crate) fn dome_png() -> anyhow::Result<Vec<u8>> {
    let mut meta = HeightMapMeta::new(60, 50, 0.4);
    meta.z_min_mm = 0.0;
    meta.z_max_mm = 10.0;
    let map = HeightMap::from_fn(meta, |c, r| {
        let (x, y) = ((f64::from(c) + 0.5) * 0.4 - 12.0, (f64::from(r) + 0.5) * 0.4 - 10.0);
        let d2 = x * x + y * y;
        (2.0 + if d2 < 49.0 { (49.0 - d2).sqrt() } else { 0.0 }) as f32
    })?;
    let mut bytes = Vec::new();
    depthmill_geometry::write_png_to(&map, &mut bytes, PngDepth::Bits16)?;
    Ok(bytes)
}

#[tokio::test]
async fn a_depth_map_job_is_planned_by_the_cam_service_and_executed() -> anyhow::Result<()> {
    let script = Script::default();
    let stack = TestStack::start_with(StackOptions {
        machine: MachineBackend::Scripted(script.clone()),
        ..Default::default()
    })
    .await?;
    let sha = stack.upload("image/png", dome_png()?).await?;
    let job = json!({
        "name": "dome",
        "input": {"kind": "depth_map", "artifact": sha},
        "plan": {"stock": {"z_mm": 10, "material": "aluminium"},
                 "roughing": {"tool": "flat-3", "step_down_mm": 2.5, "stock_to_leave_mm": 0.3},
                 "finishing": {"tool": "ball-3", "strategy": "raster_x", "step_over_mm": 0.5, "tolerance_mm": 0.01},
                 "dialect": "linuxcnc"}
    });
    let (status, created) = stack.post_job(&job, None).await?;
    assert_eq!(status, 201, "{created}");
    let id = created["id"].as_str().expect("id").to_string();
    let done = stack.wait_for_end(&id, Duration::from_secs(120)).await?;
    assert_eq!(done["status"], "succeeded", "{done}");
    for name in ["gcode", "plan_report", "toolpath_preview", "leftover_map", "telemetry", "report"] {
        assert!(done["artifacts"][name]["sha256"].is_string(), "{name} missing: {done}");
    }
    let gcode_sha = done["artifacts"]["gcode"]["sha256"].as_str().expect("gcode");
    let gcode = stack.http.get(stack.url(&format!("/v1/artifacts/{gcode_sha}"))).send().await?.text().await?;
    assert!(gcode.contains("G21"), "{}", &gcode[..gcode.len().min(400)]);
    assert!(gcode.contains("M30"));
    assert!(gcode.contains("T1") && gcode.contains("T2"), "roughing and finishing tools");
    // The machine received the program the CAM service wrote.
    assert_eq!(script.completed(), 1);
    let report_sha = done["artifacts"]["plan_report"]["sha256"].as_str().expect("report");
    let report: Value =
        stack.http.get(stack.url(&format!("/v1/artifacts/{report_sha}"))).send().await?.json().await?;
    let face = &report["faces"][0];
    assert!(face["max_gouge_mm"].as_f64().unwrap_or(1.0) <= 0.001 + 0.01, "{report}");
    // Roughing, finishing and, where finishing left material a smaller ball takes off, rest.
    let ops = face["operations"].as_array().cloned().unwrap_or_default();
    assert!(ops.len() == 2 || ops.len() == 3, "{report}");
    if let Some(rest) = ops.get(2) {
        assert_eq!(rest["tool_number"], 3, "{rest}");
        assert!(rest["strategy"].as_str().is_some_and(|s| s.starts_with("rest-finishing")), "{rest}");
        assert!(face["rest"]["region_mm2"].as_f64().is_some_and(|a| a > 0.0), "{report}");
    }
    assert!(done["stage_timings_s"]["plan"].is_number());
    stack.shutdown().await
}

#[tokio::test]
async fn a_plan_the_cam_service_rejects_fails_without_retries() -> anyhow::Result<()> {
    let stack = TestStack::start().await?;
    let sha = stack.upload("image/png", dome_png()?).await?;
    // A tool the library does not have: refused at submission by the CAM service, named.
    let job =
        json!({"input": {"kind": "depth_map", "artifact": sha}, "plan": {"finishing": {"tool": "spoon-3"}}});
    let (status, body) = stack.post_job(&job, None).await?;
    assert_eq!(status, 400, "{body}");
    assert_eq!(body["error"]["field"], "plan.finishing.tool", "{body}");
    assert!(body["error"]["message"].as_str().unwrap_or_default().contains("spoon-3"), "{body}");
    // What only the map can tell (a stock lower than the part): the stage fails, once.
    let job = json!({"input": {"kind": "depth_map", "artifact": sha}, "plan": {"stock": {"z_mm": 0.01}}});
    let (_, created) = stack.post_job(&job, None).await?;
    let done = stack.wait_for_end(created["id"].as_str().expect("id"), Duration::from_secs(60)).await?;
    assert_eq!(done["status"], "failed");
    assert_eq!(done["error"]["code"], "invalid_argument");
    assert_eq!(done["error"]["stage"], "plan");
    assert!(done["error"]["message"].as_str().unwrap_or_default().contains("plan.stock.z_mm"), "{done}");
    assert_eq!(done["attempts"].as_array().map(Vec::len), Some(1));
    // The failed stage's time is there too.
    assert!(done["stage_timings_s"]["plan"].as_f64().is_some_and(|t| t >= 0.0), "{done}");
    stack.shutdown().await
}

#[tokio::test]
async fn a_planned_program_is_machined_and_measured_against_the_depth_map() -> anyhow::Result<()> {
    let stack = TestStack::start().await?;
    let sha = stack.upload("image/png", dome_png()?).await?;
    let job = json!({
        "name": "dome on the mill",
        "input": {"kind": "depth_map", "artifact": sha},
        "plan": {"stock": {"z_mm": 10, "material": "aluminium"},
                 "roughing": {"tool": "flat-3", "step_down_mm": 2.5, "stock_to_leave_mm": 0.3},
                 "finishing": {"tool": "ball-3", "strategy": "raster_x", "step_over_mm": 0.5, "tolerance_mm": 0.01}},
        "execute": {"machine": "emco-f1", "adaptive": "aco"}
    });
    let (status, created) = stack.post_job(&job, None).await?;
    assert_eq!(status, 201, "{created}");
    let done = stack.wait_for_end(created["id"].as_str().expect("id"), Duration::from_secs(600)).await?;
    assert_eq!(done["status"], "succeeded", "{done}");
    for name in ["final_stock", "deviation_map", "telemetry", "telemetry_plot", "machine_report"] {
        assert!(done["artifacts"][name]["sha256"].is_string(), "{name} missing: {done}");
    }
    let m = &done["metrics"];
    // The map's pixel is 0.4 mm and the finishing tool a 3 mm ball at 0.5 mm step-over: the part
    // is never cut below the map by more than the Z-map's resolution, and material is left only
    // where the ball cannot reach (scallops, and the concave foot of the dome).
    let gouge = m["max_gouge_mm"].as_f64().unwrap_or(f64::NAN);
    assert!(gouge < 0.05, "max gouge {gouge}: {m}");
    let cycle = m["cycle_time_s"].as_f64().unwrap_or(0.0);
    let plain = m["cycle_time_no_adaptive_s"].as_f64().unwrap_or(0.0);
    // Light cuts in aluminium: the loop raises the feed, the cycle is shorter than as programmed.
    assert!(cycle > 10.0 && plain > cycle, "{m}");
    // The CAM's own figures are the job's too: its sweep of the program finds no gouge either,
    // and it estimated a time.
    let planned = m["plan_max_gouge_mm"].as_f64().unwrap_or(f64::NAN);
    assert!(planned < 0.05, "planned gouge {planned}: {m}");
    assert!(m["estimated_time_s"].as_f64().unwrap_or(0.0) > 0.0, "{m}");
    assert!(m["removed_mm3"].as_f64().unwrap_or(0.0) > 0.0, "{m}");
    let report_sha = done["artifacts"]["machine_report"]["sha256"].as_str().expect("report");
    let report: Value =
        stack.http.get(stack.url(&format!("/v1/artifacts/{report_sha}"))).send().await?.json().await?;
    assert!(report["run"]["removed_mm3"].as_f64().unwrap_or(0.0) > 100.0, "{report}");
    let mean_left = report["deviation"]["mean_leftover_mm"].as_f64().unwrap_or(f64::NAN);
    assert!(mean_left < 0.2, "mean leftover {mean_left}");
    assert_eq!(report["run"]["revs_over_torque"], 0, "{report}");
    let csv_sha = done["artifacts"]["telemetry"]["sha256"].as_str().expect("telemetry");
    let csv = stack.http.get(stack.url(&format!("/v1/artifacts/{csv_sha}"))).send().await?.text().await?;
    assert!(csv.starts_with("time_s,line,x_mm"), "{}", &csv[..csv.len().min(200)]);
    assert!(csv.lines().count() > 10);
    stack.shutdown().await
}

/// A depth map without depthmill metadata (a plain `.npy` of heights in millimetres, a plain
/// 16-bit PNG) is scaled by the job's `input.pixel_mm` and Z range, and that scale reaches every
/// stage that reads the map: the CAM service plans it and the machine service measures the part
/// against it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_map_without_metadata_is_scaled_by_the_job_through_plan_and_execute() -> anyhow::Result<()> {
    let stack = TestStack::start().await?;
    // The dome's heights, 60 x 50 cells, as a bare .npy (f32, C order, mm).
    let mut payload = Vec::new();
    for r in 0..50 {
        for c in 0..60 {
            let (x, y) = ((f64::from(c) + 0.5) * 0.4 - 12.0, (f64::from(r) + 0.5) * 0.4 - 10.0);
            let d2 = x * x + y * y;
            let z = (2.0 + if d2 < 49.0 { (49.0 - d2).sqrt() } else { 0.0 }) as f32;
            payload.extend_from_slice(&z.to_le_bytes());
        }
    }
    let header = format!("{{'descr': '<f4', 'fortran_order': False, 'shape': (50, 60), }}{:1$}\n", "", 53);
    let mut npy = b"\x93NUMPY\x01\x00".to_vec();
    npy.extend_from_slice(&u16::try_from(header.len())?.to_le_bytes());
    npy.extend_from_slice(header.as_bytes());
    npy.extend_from_slice(&payload);
    let sha = stack.upload("application/x-npy", npy).await?;
    let job = json!({
        "input": {"kind": "depth_map", "artifact": sha, "pixel_mm": 0.4, "z_min_mm": 0.0, "z_max_mm": 10.0},
        "plan": {"stock": {"z_mm": 10}, "roughing": {"tool": "flat-6", "step_down_mm": 3.0},
                 "finishing": {"tool": "ball-6", "step_over_mm": 1.0}},
        "execute": {"adaptive": "off", "compare": false, "cell_mm": 0.4}
    });
    let (status, created) = stack.post_job(&job, None).await?;
    assert_eq!(status, 201, "{created}");
    let done = stack.wait_for_end(created["id"].as_str().expect("id"), Duration::from_secs(300)).await?;
    assert_eq!(done["status"], "succeeded", "{done}");
    // Measured against the map: the deviation figures exist and are small.
    let gouge = done["metrics"]["max_gouge_mm"].as_f64().expect("max_gouge_mm");
    assert!(gouge < 0.2, "{done}");
    stack.shutdown().await
}
