//! The whole job over real gRPC: a part's mesh scanned, reconstructed, planned, machined on the
//! simulated EMCO and reported, the machined part compared with the part itself and with the part
//! opened by the finishing tool; and a job that outlives a stage service going down.

use std::io::Cursor;
use std::time::Duration;

use depthmill_tests::{StackOptions, TestStack};
use serde_json::json;

use crate::scan::{dome, dome_stl};

/// Radius of the finishing ball, mm.
const R: f64 = 1.5;

/// Height of the ball's surface above its tip at horizontal distance `d` (∞ beyond the radius).
fn ball(d: f64) -> f64 {
    if d <= R { R - (R * R - d * d).sqrt() } else { f64::INFINITY }
}

/// The part opened by the ball, brute force on a grid of step `h`: the tip surface
/// `c(t) = max_q h(q) − s(q − t)`, then the lowest the tool reaches at `p`,
/// `min_t c(t) + s(p − t)`. This is the best surface a ball of radius R can leave.
struct Opened {
    h: f64,
    n: usize,
    lo: f64,
    tip: Vec<f64>,
}

impl Opened {
    fn new(lo: f64, hi: f64, h: f64) -> Self {
        let n = ((hi - lo) / h).round() as usize + 1;
        let k = (R / h).ceil() as i64;
        let at = |i: usize| lo + i as f64 * h;
        let mut tip = vec![f64::NEG_INFINITY; n * n];
        for j in 0..n {
            for i in 0..n {
                let (tx, ty) = (at(i), at(j));
                let mut c = f64::NEG_INFINITY;
                for dj in -k..=k {
                    for di in -k..=k {
                        let (qx, qy) = (tx + di as f64 * h, ty + dj as f64 * h);
                        let s = ball((di as f64 * h).hypot(dj as f64 * h));
                        if s.is_finite() {
                            c = c.max(dome(qx, qy) - s);
                        }
                    }
                }
                tip[j * n + i] = c;
            }
        }
        Self { h, n, lo, tip }
    }

    fn at(&self, x: f64, y: f64) -> f64 {
        let k = (R / self.h).ceil() as i64;
        let ci = ((x - self.lo) / self.h).round() as i64;
        let cj = ((y - self.lo) / self.h).round() as i64;
        let mut best = f64::INFINITY;
        for dj in -k..=k {
            for di in -k..=k {
                let (i, j) = (ci + di, cj + dj);
                if i < 0 || j < 0 || i >= self.n as i64 || j >= self.n as i64 {
                    continue;
                }
                let (tx, ty) = (self.lo + i as f64 * self.h, self.lo + j as f64 * self.h);
                let s = ball((x - tx).hypot(y - ty));
                if s.is_finite() {
                    best = best.min(self.tip[j as usize * self.n + i as usize] + s);
                }
            }
        }
        best
    }
}

#[tokio::test]
async fn the_whole_job_reproduces_the_part_within_tolerance() -> anyhow::Result<()> {
    let stack = TestStack::start_with(StackOptions { stage_deadline_s: 600.0, ..Default::default() }).await?;
    let sha = stack.upload("model/stl", dome_stl()).await?;
    let job = json!({
        "name": "whole job",
        "input": {"kind": "mesh", "artifact": sha},
        "scan": {"table_angles_deg": [0, 180], "line_spacing_mm": 0.3, "line_rate_hz": 150},
        "reconstruct": {"pixel_mm": 0.25},
        "plan": {"stock": {"z_mm": 7, "material": "aluminium"},
                 "roughing": {"tool": "flat-6", "step_down_mm": 2.5, "stock_to_leave_mm": 0.3},
                 "finishing": {"tool": "ball-3", "strategy": "raster_x", "step_over_mm": 0.4, "tolerance_mm": 0.01}},
        "execute": {"machine": "emco-f1", "adaptive": "aco"}
    });
    let (status, created) = stack.post_job(&job, None).await?;
    assert_eq!(status, 201, "{created}");
    let id = created["id"].as_str().expect("id").to_string();
    let done = stack.wait_for_end(&id, Duration::from_secs(900)).await?;
    assert_eq!(done["status"], "succeeded", "{done}");
    for stage in ["scan", "reconstruct", "plan", "execute", "report"] {
        assert!(done["stage_timings_s"][stage].as_f64().is_some(), "{stage} timing missing: {done}");
    }
    for name in ["point_cloud", "depth_map", "gcode", "final_stock", "deviation_map", "telemetry", "report"] {
        assert!(done["artifacts"][name]["sha256"].is_string(), "{name} missing: {done}");
    }
    assert_eq!(done["artifacts"]["report"]["media_type"], "text/html");
    let m = &done["metrics"];
    let (with, without) =
        (m["cycle_time_s"].as_f64().unwrap_or(0.0), m["cycle_time_no_adaptive_s"].as_f64().unwrap_or(0.0));
    assert!(with > 0.0 && with < without, "the loop shortens the cycle: {m}");

    // The report is served as a page with every section.
    let resp = stack.http.get(stack.url(&format!("/v1/jobs/{id}/report"))).send().await?;
    assert_eq!(resp.status().as_u16(), 200);
    assert!(resp.headers()["content-type"].to_str()?.starts_with("text/html"));
    let page = resp.text().await?;
    for needle in
        ["Point cloud", "Depth map", "Toolpaths", "Deviation", "Cycle time", "data:image/png;base64,"]
    {
        assert!(page.to_lowercase().contains(&needle.to_lowercase()), "report lacks {needle}");
    }

    // The machined part against the part and against the part opened by the ball.
    let sha = done["artifacts"]["final_stock"]["sha256"].as_str().unwrap_or_default();
    let bytes = stack.http.get(stack.url(&format!("/v1/artifacts/{sha}"))).send().await?.bytes().await?;
    let stock = depthmill_geometry::read_png_from(Cursor::new(bytes.to_vec()), None)?;
    let opened = Opened::new(-14.0, 14.0, 0.1);
    let meta = *stock.meta();
    let (mut gouge, mut gouge_open, mut left_open, mut sq, mut n) = (0.0f64, 0.0f64, 0.0f64, 0.0, 0usize);
    for row in 0..meta.height {
        for col in 0..meta.width {
            let (x, y) = meta.cell_center(col, row);
            // Inside the part, clear of its edge (the sheet ends at ±15 mm).
            if x.abs() > 11.5 || y.abs() > 11.5 {
                continue;
            }
            let z = f64::from(stock.get(col, row).unwrap_or(f32::NAN));
            if !z.is_finite() {
                continue;
            }
            let truth = dome(x, y);
            let open = opened.at(x, y);
            gouge = gouge.max(truth - z);
            gouge_open = gouge_open.max(open - z);
            left_open = left_open.max(z - open);
            sq += (z - open) * (z - open);
            n += 1;
        }
    }
    let rms = (sq / n.max(1) as f64).sqrt();
    println!(
        "machined vs part: max gouge {gouge:.4} mm; vs part opened by ball-3: max gouge {gouge_open:.4} mm, max leftover {left_open:.4} mm, RMS {rms:.4} mm over {n} cells"
    );
    // Tolerances. The scan's noise is σ = 35 µm and max-Z binning keeps the highest sample of a
    // 0.25 mm pixel (about +2σ = 0.07 mm above the surface); the CAM reads each pixel as a
    // column as high as its highest corner (the conservative pixel model), which on the dome's
    // flanks (slope up to 0.42) lifts the surface by up to slope × pixel = 0.1 mm; the CAM works
    // to 0.01 mm and the mill's steps are 0.01 mm; a 0.4 mm step-over of a 1.5 mm ball leaves
    // scallops of R − √(R² − 0.2²) = 0.013 mm. So: no gouge below the part beyond the noise's low
    // side (≤ 0.15 mm), leftover above the part opened by the ball ≤ 0.07 + 0.1 + 0.013 + steps
    // (≤ 0.3 mm), and the copy within 0.15 mm RMS of the best a 3 mm ball can do.
    assert!(n > 5_000, "{n} cells compared");
    assert!(gouge < 0.15 && gouge_open < 0.15, "gouge {gouge} / {gouge_open}");
    assert!(left_open < 0.3, "leftover {left_open}");
    assert!(rms < 0.15, "RMS {rms}");
    stack.shutdown().await
}

#[tokio::test]
async fn a_job_outlives_a_stage_service_going_down_and_coming_back() -> anyhow::Result<()> {
    let mut stack = TestStack::start_with(StackOptions { max_attempts: 40, ..Default::default() }).await?;
    let sha = stack.upload("model/stl", dome_stl()).await?;
    stack.stop_service("reconstruction").await?;
    let job = json!({
        "input": {"kind": "mesh", "artifact": sha},
        "scan": {"table_angles_deg": [0], "line_spacing_mm": 1.0},
        "reconstruct": {"pixel_mm": 0.5},
        "plan": {"stock": {"z_mm": 7}, "roughing": {"tool": "flat-6", "step_down_mm": 3.0},
                 "finishing": {"tool": "ball-6", "step_over_mm": 2.0}}
    });
    let (_, created) = stack.post_job(&job, None).await?;
    let id = created["id"].as_str().expect("id").to_string();
    // Wait until the job is stuck retrying the reconstruct stage.
    let mut tries = 0;
    loop {
        let j = stack.get_job(&id).await?;
        let retried = j["attempts"]
            .as_array()
            .is_some_and(|a| a.iter().filter(|x| x["stage"] == "reconstruct").count() >= 2);
        if retried {
            break;
        }
        assert!(j["status"] != "failed", "{j}");
        tries += 1;
        assert!(tries < 3000, "the job never reached reconstruct: {j}");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    stack.start_service("reconstruction").await?;
    let done = stack.wait_for_end(&id, Duration::from_secs(600)).await?;
    assert_eq!(done["status"], "succeeded", "{done}");
    let outcomes: Vec<String> = done["attempts"]
        .as_array()
        .into_iter()
        .flatten()
        .filter(|a| a["stage"] == "reconstruct")
        .map(|a| a["outcome"].as_str().unwrap_or("?").to_string())
        .collect();
    assert!(outcomes.len() >= 2 && outcomes.last().map(String::as_str) == Some("ok"), "{outcomes:?}");
    stack.shutdown().await
}
