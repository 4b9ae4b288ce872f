//! A part machined on two faces: reconstruction makes a depth map per face, CAM one program that
//! turns the A axis between them, the machine cuts both faces on one dexel stock, and the report
//! shows both.

use std::fmt::Write as _;
use std::time::Duration;

use depthmill_tests::{StackOptions, TestStack};
use serde_json::json;

/// Where the part lies in its file: far from the file's origin, as a part of an assembly does.
/// The set-up turns it about its own centre, so the A axis does not swing it out of the travel.
const OFFSET: [f64; 3] = [40.0, -120.0, -300.0];

/// The centre of the part's bounding box in the file (see [`two_face_ply`]).
const CENTRE: [f64; 3] = [OFFSET[0], OFFSET[1] + 0.75, OFFSET[2] + 1.0];

/// A 30 × 20 × 20 mm block with a bump on its top (+Z) and a ridge on its +Y side, moved by
/// [`OFFSET`]: two height fields, written as an ASCII PLY mesh.
fn two_face_ply() -> Vec<u8> {
    let top = |x: f64, y: f64| 10.0 + 2.0 * (1.0 - (x * x + y * y) / 64.0).max(0.0);
    let side =
        |x: f64, z: f64| 10.0 + 1.5 * (1.0 - (x - 5.0).abs() / 6.0).max(0.0) * (1.0 - (z / 10.0).powi(2));
    let n = 61;
    let mut verts = Vec::new();
    // Top: z = top(x, y) over x ∈ [-15, 15], y ∈ [-10, 10].
    for j in 0..n {
        for i in 0..n {
            let x = -15.0 + 30.0 * i as f64 / (n - 1) as f64;
            let y = -10.0 + 20.0 * j as f64 / (n - 1) as f64;
            verts.push([x, y, top(x, y)]);
        }
    }
    // Side: y = side(x, z) over x ∈ [-15, 15], z ∈ [-10, 10].
    for j in 0..n {
        for i in 0..n {
            let x = -15.0 + 30.0 * i as f64 / (n - 1) as f64;
            let z = -10.0 + 20.0 * j as f64 / (n - 1) as f64;
            verts.push([x, side(x, z), z]);
        }
    }
    let mut faces = Vec::new();
    for sheet in 0..2 {
        let b = sheet * n * n;
        for j in 0..n - 1 {
            for i in 0..n - 1 {
                let a = b + j * n + i;
                faces.push([a, a + 1, a + n + 1]);
                faces.push([a, a + n + 1, a + n]);
            }
        }
    }
    let mut s = String::new();
    let _ = write!(
        s,
        "ply\nformat ascii 1.0\nelement vertex {}\nproperty float x\nproperty float y\nproperty float z\nelement face {}\nproperty list uchar int vertex_indices\nend_header\n",
        verts.len(),
        faces.len()
    );
    for v in &verts {
        let _ = writeln!(s, "{:.4} {:.4} {:.4}", v[0] + OFFSET[0], v[1] + OFFSET[1], v[2] + OFFSET[2]);
    }
    for f in &faces {
        let _ = writeln!(s, "3 {} {} {}", f[0], f[1], f[2]);
    }
    s.into_bytes()
}

#[tokio::test]
async fn a_two_face_part_is_planned_with_the_a_axis_and_machined_on_both_faces() -> anyhow::Result<()> {
    let stack = TestStack::start_with(StackOptions { stage_deadline_s: 600.0, ..Default::default() }).await?;
    let sha = stack.upload("application/x-ply", two_face_ply()).await?;
    let job = json!({
        "name": "two faces",
        "input": {"kind": "point_cloud", "artifact": sha},
        "reconstruct": {"pixel_mm": 0.3, "faces": [{"view": "+Z"}, {"view": "+Y"}]},
        "plan": {"stock": {"material": "aluminium"},
                 "roughing": {"tool": "flat-6", "step_down_mm": 2.0},
                 "finishing": {"tool": "ball-3", "strategy": "raster_x", "step_over_mm": 0.6}},
        "execute": {"machine": "emco-f1", "adaptive": "aco"}
    });
    let (status, created) = stack.post_job(&job, None).await?;
    assert_eq!(status, 201, "{created}");
    let id = created["id"].as_str().expect("id").to_string();
    let done = stack.wait_for_end(&id, Duration::from_secs(900)).await?;
    assert_eq!(done["status"], "succeeded", "{done}");
    for name in
        ["depth_map", "depth_map@1", "final_stock", "final_stock@1", "deviation_map", "deviation_map@1"]
    {
        assert!(done["artifacts"][name]["sha256"].is_string(), "{name} missing: {done}");
    }
    // Both faces turn about the part's centre, which each map records.
    let sha = done["artifacts"]["reconstruct_report"]["sha256"].as_str().unwrap_or_default();
    let rec: serde_json::Value =
        stack.http.get(stack.url(&format!("/v1/artifacts/{sha}"))).send().await?.json().await?;
    for f in rec["faces"].as_array().cloned().unwrap_or_default() {
        assert_eq!(f["part_origin_mm"], json!(CENTRE), "{rec}");
    }
    // One program turning the A axis between the faces.
    let sha = done["artifacts"]["gcode"]["sha256"].as_str().unwrap_or_default();
    let gcode = stack.http.get(stack.url(&format!("/v1/artifacts/{sha}"))).send().await?.text().await?;
    assert!(gcode.contains("A90"), "the program turns to the +Y face");
    // Both faces were cut: the report has no "timed but not cut" warnings and the deviation is
    // the depth maps' within the finishing tool's reach.
    let sha = done["artifacts"]["machine_report"]["sha256"].as_str().unwrap_or_default();
    let report: serde_json::Value =
        stack.http.get(stack.url(&format!("/v1/artifacts/{sha}"))).send().await?.json().await?;
    let warnings = report["run"]["warnings"].as_array().cloned().unwrap_or_default();
    assert!(!warnings.iter().any(|w| w.as_str().unwrap_or("").contains("not cut")), "{warnings:?}");
    let faces = report["faces"].as_array().cloned().unwrap_or_default();
    assert_eq!(faces.len(), 2, "{report}");
    for f in &faces {
        let gouge = f["deviation"]["max_gouge_mm"].as_f64().unwrap_or(1.0);
        let rms = f["deviation"]["rms_deviation_mm"].as_f64().unwrap_or(1.0);
        println!("face A={}: max gouge {gouge:.4} mm, RMS {rms:.4} mm", f["a_deg"]);
    }
    for f in &faces {
        let gouge = f["deviation"]["max_gouge_mm"].as_f64().unwrap_or(1.0);
        let rms = f["deviation"]["rms_deviation_mm"].as_f64().unwrap_or(1.0);
        // Both faces are cut on one stock, so each face's deviation also holds what the other
        // face's program took off the shared edge, where each map sees the other sheet edge-on
        // as a near-vertical wall on 0.3 mm cells: no face is cut below its map by more than a
        // third of a cell. Leftover is where a 3 mm ball cannot follow, so the RMS is loose.
        assert!(gouge < 0.1, "face {}: gouge {gouge}", f["a_deg"]);
        assert!(rms < 1.0, "face {}: RMS {rms}", f["a_deg"]);
    }
    assert_eq!(faces[1]["a_deg"], 90.0);
    // The one stock measured against the original part (the input mesh, sampled) and against the
    // part opened by the smallest tool (ball-3).
    let m = &done["metrics"];
    println!("stage timings (s): {}", done["stage_timings_s"]);
    println!(
        "against the part: {}; opened: {}; faces {}",
        report["part"]["against_part"], report["part"]["against_opened"], report["part"]["faces"]
    );
    let metric = |k: &str| m[k].as_f64().unwrap_or_else(|| panic!("metric {k} missing: {m}"));
    assert!(metric("original_points") > 10_000.0, "{m}");
    assert!(metric("original_max_gouge_mm") < 0.15, "{m}");
    // A multi-face job's headline figures are the original part's; the depth maps' keep `map_`.
    for k in ["max_gouge_mm", "max_leftover_mm", "rms_deviation_mm"] {
        assert_eq!(metric(k), metric(&format!("original_{k}")), "{k}: {m}");
    }
    for k in ["max_gouge_mm", "max_leftover_mm", "mean_leftover_mm", "rms_deviation_mm"] {
        assert!(metric(&format!("map_{k}")).is_finite(), "{k}: {m}");
    }
    assert_eq!(report["part"]["opened_by"], "ball-3", "{report}");
    // The machined part against what both faces' programs leave together (each face's preview,
    // the second under the depth map's suffix), seen from the first face.
    assert!(done["artifacts"]["toolpath_preview@1"]["sha256"].is_string(), "{done}");
    println!("against the faces' prediction: RMS {} mm", m["preview_rms_mm"]);
    // About 0.02 mm: the machine's steps and cells. Against the first face's preview alone
    // (which still holds what the +Y face's program takes off the shared edge) it reads 0.3 mm.
    assert!(metric("preview_rms_mm") < 0.05, "{m}");
    assert!(metric("opened_max_gouge_mm") <= metric("original_max_gouge_mm") + 1e-12);
    assert!(metric("opened_mean_leftover_mm") <= metric("original_mean_leftover_mm") + 1e-12);
    // The simulated part as a closed STL whose volume is the stock's.
    let sha = done["artifacts"]["machined_part"]["sha256"].as_str().expect("machined_part");
    let stl = stack.http.get(stack.url(&format!("/v1/artifacts/{sha}"))).send().await?.bytes().await?;
    let (mesh, stats) = depthmill_geometry::formats::read_stl_from(
        std::io::Cursor::new(stl.to_vec()),
        "machined_part",
        Some(stl.len() as u64),
        &depthmill_geometry::formats::ReadLimits::default(),
    )?;
    let info = &report["part_mesh"];
    // Every triangle written is read back but the few flat slivers a reader drops as zero-area.
    let written = info["triangles"].as_u64().unwrap_or(0);
    assert_eq!(mesh.triangles.len() as u64 + stats.dropped_triangles, written, "{info}");
    assert!(stats.dropped_triangles * 100 < written, "{} of {written} dropped", stats.dropped_triangles);
    let (v_mesh, v_dexel) =
        (info["volume_mm3"].as_f64().unwrap_or(0.0), info["dexel_volume_mm3"].as_f64().unwrap_or(1.0));
    assert!((v_mesh - v_dexel).abs() < 0.02 * v_dexel, "{info}");
    // ... in the part's own frame, where the original part lies: within the block (the blank
    // the faces' maps bound, a few mm around the part).
    let b = mesh.bounds().expect("a machined part");
    for k in 0..3 {
        let (lo, hi) = ([-15.0, -10.0, -10.0][k] + OFFSET[k], [15.0, 11.5, 12.0][k] + OFFSET[k]);
        assert!(b.min[k] > lo - 5.0 && b.max[k] < hi + 5.0 && b.max[k] > lo, "axis {k}: {b:?}");
    }
    // The report shows each face.
    let page = stack.http.get(stack.url(&format!("/v1/jobs/{id}/report"))).send().await?.text().await?;
    assert!(page.contains("Face 2"), "the report shows the second face");
    assert!(page.contains(r#"<section id="part3d">"#), "the report shows the part in 3-D");
    stack.shutdown().await
}
