//! The reconstruct stage over gRPC: a point cloud job becomes depth, coverage and roughing maps
//! and goes on to planning.

use std::fmt::Write as _;
use std::io::Cursor;
use std::time::Duration;

use depthmill_geometry::HeightMap;
use depthmill_tests::scripted::Script;
use depthmill_tests::{MachineBackend, StackOptions, TestStack};
use serde_json::{Value, json};

/// Height of the test part: a dome of radius 7 mm rising to 9 mm from a 2 mm plinth, 24 x 20 mm.
fn dome(x: f64, y: f64) -> f64 {
    let (dx, dy) = (x - 12.0, y - 10.0);
    let d2 = dx * dx + dy * dy;
    2.0 + if d2 < 49.0 { (49.0 - d2).sqrt() } else { 0.0 }
}

/// An XYZ cloud of the dome sampled every 0.15 mm with intensity, a 1.5 mm hole the scanner did not
/// see at (6, 15), a comment, and ten stray points far above the part.
fn dome_xyz() -> Vec<u8> {
    let mut s = String::from("# x y z intensity\n");
    let mut lcg = 12345u64;
    let mut noise = || {
        lcg = lcg.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        ((lcg >> 33) as f64 / (1u64 << 31) as f64 - 0.5) * 0.02
    };
    for j in 0..=133 {
        for i in 0..=160 {
            let (x, y) = (f64::from(i) * 0.15, f64::from(j) * 0.15);
            if (x - 6.0).hypot(y - 15.0) < 0.75 {
                continue;
            }
            let _ = writeln!(s, "{x:.3} {y:.3} {:.4} 0.8", dome(x, y) + noise());
        }
    }
    for k in 0..10 {
        let _ = writeln!(s, "{:.3} {:.3} 80.0 0.8", 3.0 + f64::from(k), 4.0);
    }
    s.into_bytes()
}

#[tokio::test]
async fn a_point_cloud_job_gets_depth_maps_and_goes_on_to_planning() -> anyhow::Result<()> {
    let script = Script::default();
    let stack = TestStack::start_with(StackOptions {
        machine: MachineBackend::Scripted(script.clone()),
        ..Default::default()
    })
    .await?;
    let sha = stack.upload("text/x-xyz", dome_xyz()).await?;
    let job = json!({
        "name": "dome cloud",
        "input": {"kind": "point_cloud", "artifact": sha},
        "reconstruct": {"pixel_mm": 0.2, "faces": [{"view": "+Z"}], "fill": {"method": "idw", "max_hole_mm": 2.0}},
        "plan": {"stock": {"z_mm": 10, "material": "aluminium"},
                 "roughing": {"tool": "flat-3", "step_down_mm": 3.0},
                 "finishing": {"tool": "ball-3", "step_over_mm": 0.6}}
    });
    let (status, created) = stack.post_job(&job, None).await?;
    assert_eq!(status, 201, "{created}");
    let done = stack.wait_for_end(created["id"].as_str().expect("id"), Duration::from_secs(180)).await?;
    assert_eq!(done["status"], "succeeded", "{done}");
    for name in ["depth_map", "coverage_map", "roughing_map", "gcode"] {
        assert!(done["artifacts"][name]["sha256"].is_string(), "{name} missing: {done}");
    }
    let coverage = done["metrics"]["coverage_pct"].as_f64().unwrap_or(0.0);
    assert!((99.0..100.0).contains(&coverage), "the hole is reported: {coverage} {done}");

    let fetch = |name: &str| {
        let sha = done["artifacts"][name]["sha256"].as_str().unwrap_or_default().to_string();
        let http = stack.http.clone();
        let url = stack.url(&format!("/v1/artifacts/{sha}"));
        async move { anyhow::Ok(http.get(url).send().await?.bytes().await?.to_vec()) }
    };
    let map = depthmill_geometry::read_png_from(Cursor::new(fetch("depth_map").await?), None)?;
    assert_eq!(map.pixel_mm(), 0.2);
    // The stray points neither set the top of the gray range nor appear in the map.
    assert!(map.z_max_mm() < 10.0, "z_max {}", map.z_max_mm());
    let cov: HeightMap = depthmill_geometry::read_png_from(Cursor::new(fetch("coverage_map").await?), None)?;
    assert!(cov.data().iter().any(|v| (v - 0.5).abs() < 0.01), "filled cells are marked");
    let (mut worst, mut at) = (0.0f64, (0.0, 0.0, 0.0f64));
    for row in 0..map.height() {
        for col in 0..map.width() {
            let (x, y) = map.cell_center(col, row);
            let z = map.get(col, row).unwrap_or(f32::NAN);
            if (0.3..23.7).contains(&x) && (0.3..19.7).contains(&y) {
                assert!(
                    z.is_finite(),
                    "cell ({col}, {row}) at ({x:.2}, {y:.2}) is empty (the hole is filled)"
                );
                // The max of the points in a 0.2 mm cell lies within the part's range over the
                // cell, give or take the 0.01 mm noise; a filled cell within the range over the
                // neighbourhood its values come from (the hole's rim, up to 1 mm away).
                let filled = cov.get(col, row).is_some_and(|v| (v - 0.5).abs() < 0.01);
                let reach = if filled { 1.0 } else { 0.1 };
                let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
                for (i, j) in (0..=20).flat_map(|i| (0..=20).map(move |j| (i, j))) {
                    let h =
                        dome(x - reach + reach * 0.1 * f64::from(i), y - reach + reach * 0.1 * f64::from(j));
                    (lo, hi) = (lo.min(h), hi.max(h));
                }
                let z = f64::from(z);
                let e = (lo - 0.015 - z).max(z - hi - 0.015);
                if e > worst {
                    (worst, at) = (e, (x, y, z));
                }
            }
        }
    }
    assert!(worst <= 0.0, "depth map deviates from the dome by {worst} mm beyond the allowance at {at:?}");
    let rough = depthmill_geometry::read_png_from(Cursor::new(fetch("roughing_map").await?), None)?;
    let below = map
        .data()
        .iter()
        .zip(rough.data())
        .filter(|(f, r)| f.is_finite() && (r.is_nan() || **r < **f - 1e-3))
        .count();
    assert_eq!(below, 0, "the roughing map never lies below the depth map");
    assert_eq!(script.completed(), 1, "the program reached the machine");
    stack.shutdown().await
}

#[tokio::test]
async fn a_malformed_cloud_fails_the_reconstruct_stage_naming_the_line() -> anyhow::Result<()> {
    let stack = TestStack::start().await?;
    let sha = stack.upload("text/x-xyz", b"1 2 3\n4 5 6\n7 8 nine\n".to_vec()).await?;
    let (_, created) =
        stack.post_job(&json!({"input": {"kind": "point_cloud", "artifact": sha}}), None).await?;
    let done: Value =
        stack.wait_for_end(created["id"].as_str().expect("id"), Duration::from_secs(60)).await?;
    assert_eq!(done["status"], "failed");
    assert_eq!(done["error"]["code"], "invalid_argument");
    assert_eq!(done["error"]["stage"], "reconstruct");
    let message = done["error"]["message"].as_str().unwrap_or_default();
    assert!(message.contains("line 3") && message.contains("nine"), "{message}");
    assert_eq!(done["attempts"].as_array().map(Vec::len), Some(1), "no retries for bad input");
    // The service keeps working: a good cloud right after succeeds through reconstruction.
    let sha = stack.upload("text/x-xyz", dome_xyz()).await?;
    let job = json!({"input": {"kind": "point_cloud", "artifact": sha}, "reconstruct": {"pixel_mm": 0.5}});
    let (_, created) = stack.post_job(&job, None).await?;
    let done = stack.wait_for_end(created["id"].as_str().expect("id"), Duration::from_secs(120)).await?;
    assert!(done["artifacts"]["depth_map"]["sha256"].is_string(), "{done}");
    stack.shutdown().await
}

#[tokio::test]
async fn a_scan_in_its_sensors_frame_stands_on_the_table_it_was_found_on() -> anyhow::Result<()> {
    // The dome on a table 55 x 44 mm, seen by a sensor tilted 30° about X and 300 mm away, with
    // a 4 mm block 12 mm off to the side: the job finds the table, stands the dome on it and
    // keeps the dome alone.
    let (c, s) = (30f64.to_radians().cos(), 30f64.to_radians().sin());
    let mut text = String::from("# x y z\n");
    let mut put = |x: f64, y: f64, z: f64| {
        let _ = writeln!(text, "{:.4} {:.4} {:.4}", x, c * y - s * z, s * y + c * z - 300.0);
    };
    for j in 0..=88 {
        for i in 0..=110 {
            let (x, y) = (-13.0 + 0.5 * f64::from(i), -12.0 + 0.5 * f64::from(j));
            if (0.0..=24.0).contains(&x) && (0.0..=20.0).contains(&y) {
                put(x, y, dome(x, y));
            } else if !((36.0..=40.0).contains(&x) && (8.0..=12.0).contains(&y)) {
                put(x, y, 0.0);
            } else {
                put(x, y, 4.0);
            }
        }
    }
    let stack = TestStack::start().await?;
    let sha = stack.upload("text/x-xyz", text.into_bytes()).await?;
    let job = json!({"input": {"kind": "point_cloud", "artifact": sha},
                     "reconstruct": {"pixel_mm": 0.5, "filters": {"table": {}}},
                     "plan": {"stock": {"z_mm": 12, "material": "wax"}}});
    let (status, created) = stack.post_job(&job, None).await?;
    assert_eq!(status, 201, "{created}");
    let done = stack.wait_for_end(created["id"].as_str().expect("id"), Duration::from_secs(300)).await?;
    assert_eq!(done["status"], "succeeded", "{done}");
    let sha = done["artifacts"]["reconstruct_report"]["sha256"].as_str().unwrap_or_default();
    let report: Value =
        stack.http.get(stack.url(&format!("/v1/artifacts/{sha}"))).send().await?.json().await?;
    let table = &report["table"];
    assert!((table["tilt_deg"].as_f64().unwrap_or(0.0) - 30.0).abs() < 0.05, "{table}");
    assert_eq!(table["groups"], 2, "{table}");
    assert_eq!(table["in_other_groups"], 81, "the block: {table}");
    assert_eq!(report["filters"][0]["filter"], "table", "{report}");
    // The dome's plinth stands 2 mm over the table and its top at 9 mm, in the depth map too.
    let face = &report["faces"][0];
    let z_max = face["z_max_mm"].as_f64().unwrap_or(0.0);
    assert!(z_max > 8.5 && z_max < 10.5, "{face}");
    let width = face["width"].as_f64().unwrap_or(0.0) * face["pixel_mm"].as_f64().unwrap_or(0.0);
    assert!(width > 23.0 && width < 28.5, "the dome alone, 24 mm wide: {face}");
    stack.shutdown().await
}

#[tokio::test]
async fn reconstruct_parameters_are_checked_at_submission() -> anyhow::Result<()> {
    let stack = TestStack::start().await?;
    let sha = stack.upload("text/x-xyz", b"1 2 3\n".to_vec()).await?;
    for (rec, field) in [
        (json!({"fill": {"method": "idw", "power": -1}}), "reconstruct.fill.power"),
        (json!({"faces": [{"normal": [0, 0, 0]}]}), "reconstruct.faces[0].normal"),
        (json!({"faces": [{"view": "+Z", "origin": [0, 0, 0]}]}), "reconstruct.faces[0].origin"),
        (json!({"filters": {"statistical": {"k": 0, "n_sigma": 2}}}), "reconstruct.filters.statistical.k"),
        (json!({"filters": {"table": {"tolerance_mm": 0}}}), "reconstruct.filters.table.tolerance_mm"),
        (json!({"roughing_factor": 0}), "reconstruct.roughing_factor"),
        (json!({"z_min_mm": 5, "z_max_mm": 1}), "reconstruct.z_max_mm"),
    ] {
        let body = json!({"input": {"kind": "point_cloud", "artifact": sha}, "reconstruct": rec});
        let (status, e) = stack.post_job(&body, None).await?;
        assert_eq!(status, 400, "{body} -> {e}");
        assert_eq!(e["error"]["field"], field, "{e}");
    }
    stack.shutdown().await
}

#[tokio::test]
async fn a_section_the_service_could_not_check_at_submission_is_checked_by_its_stage() -> anyhow::Result<()> {
    let mut stack = TestStack::start_with(StackOptions { max_attempts: 40, ..Default::default() }).await?;
    let sha = stack.upload("text/x-xyz", dome_xyz()).await?;
    stack.stop_service("reconstruction").await?;
    // The reconstruction service is down: the orchestrator cannot ask it, so it accepts the job.
    let body = json!({"input": {"kind": "point_cloud", "artifact": sha},
                      "reconstruct": {"fill": {"method": "idw", "power": -1}}});
    let (status, created) = stack.post_job(&body, None).await?;
    assert_eq!(status, 201, "{created}");
    let id = created["id"].as_str().expect("id").to_string();
    stack.start_service("reconstruction").await?;
    // Back up, the stage refuses the same value before any work, naming the field.
    let done = stack.wait_for_end(&id, Duration::from_secs(300)).await?;
    assert_eq!(done["status"], "failed", "{done}");
    assert_eq!(done["error"]["stage"], "reconstruct", "{done}");
    assert_eq!(done["error"]["code"], "invalid_argument", "{done}");
    let message = done["error"]["message"].as_str().unwrap_or_default();
    assert!(message.contains("reconstruct.fill.power"), "{message}");
    // Now that it answers, the same request is refused at submission.
    let (status, e) = stack.post_job(&body, None).await?;
    assert_eq!(status, 400, "{e}");
    assert_eq!(e["error"]["field"], "reconstruct.fill.power", "{e}");
    stack.shutdown().await
}
