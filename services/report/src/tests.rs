//! Tests of the report on synthetic artifacts made with the real writers: a hemisphere depth map
//! (16-bit PNG with metadata), its coverage map, a CAM-style program with roughing and finishing
//! headers, the machine's telemetry CSV and plot, a binary PLY cloud.

use std::collections::BTreeMap;

use crate::plot::{Chart, Panel, Series};
use depthmill_geometry::formats::{PlyEncoding, write_ply};
use depthmill_geometry::{HeightMap, HeightMapMeta, PngDepth, PointCloud, nalgebra::Point3, write_png_to};
use serde_json::{Value, json};

use super::*;

const W: u32 = 120;
const H: u32 = 80;
const P: f64 = 0.25;
const X0: f64 = -15.0;
const Y0: f64 = -10.0;

fn meta(z_min: f64, z_max: f64) -> HeightMapMeta {
    let mut m = HeightMapMeta::new(W, H, P);
    m.origin_x_mm = X0;
    m.origin_y_mm = Y0;
    m.z_min_mm = z_min;
    m.z_max_mm = z_max;
    m
}

/// A dome of radius 8 mm, 6 mm high, on a 1 mm plate.
fn dome_z(x: f64, y: f64) -> f64 {
    let r2 = x * x + y * y;
    1.0 + if r2 < 64.0 { 6.0 * (1.0 - r2 / 64.0).sqrt() } else { 0.0 }
}

fn map_png(map: &HeightMap, depth: PngDepth) -> Vec<u8> {
    let mut out = Vec::new();
    write_png_to(map, &mut out, depth).expect("png");
    out
}

fn depth_map() -> HeightMap {
    let m = meta(0.0, 8.0);
    HeightMap::from_fn(m, |c, r| {
        let (x, y) = m.cell_center(c, r);
        dome_z(x, y) as f32
    })
    .expect("map")
}

fn coverage_map() -> HeightMap {
    let m = meta(0.0, 1.0);
    HeightMap::from_fn(m, |c, r| {
        let (x, y) = m.cell_center(c, r);
        if x.abs() > 14.0 {
            f32::NAN
        } else if (x - 3.0).powi(2) + (y - 2.0).powi(2) < 2.0 {
            0.0
        } else if x > 11.0 {
            0.25
        } else if x > 8.0 {
            0.5
        } else {
            1.0
        }
    })
    .expect("map")
}

fn gcode() -> String {
    let mut g = String::from(
        "%\n(depthmill)\n(material aluminium)\nG21 G90 G17 G94 G40 G49 G80\nG64 P0.0100\n\
(T1 flat-6: flat D6.0000 mm, 2 flutes - roughing-x with flat-6)\nG53 G0 Z0.0000\nT1 M6\nS2000 M3\nG43 H1\n",
    );
    let mut y = -9.0;
    g.push_str("G0 X-14.0000 Y-9.0000\nZ12.0000\nG1 Z4.0000 F100.0000\n");
    while y <= 9.0 {
        g.push_str(&format!("G1 Y{y:.4}\nX14.0000\nG0 Z12.0000\nX-14.0000\nG1 Z4.0000\n"));
        y += 2.4;
    }
    g.push_str("G0 Z12.0000\nM5\n(T2 ball-3: ball D3.0000 mm, 2 flutes - finishing-raster-x with ball-3)\nG53 G0 Z0.0000\nT2 M6\nS2000 M3\nG43 H2\n");
    g.push_str("G0 X-14.0000 Y-9.0000\nZ10.0000\nG1 Z1.0000 F60.0000\n");
    let mut y = -9.0;
    let mut dir = 1.0;
    while y <= 9.0 {
        g.push_str(&format!("G1 Y{y:.4} F120.0000\n"));
        let mut x = -14.0;
        while x <= 14.0 {
            let xx = x * dir;
            g.push_str(&format!("X{xx:.4} Z{:.4}\n", dome_z(xx, y)));
            x += 1.0;
        }
        dir = -dir;
        y += 0.7;
    }
    g.push_str("G3 X-2.0000 Y0.0000 I2.0000 J0.0000\nG0 Z10.0000\nM5\nG53 G0 Z0.0000\nM30\n%\n");
    g
}

fn telemetry_csv() -> String {
    let mut s = String::from(
        "time_s,line,x_mm,y_mm,z_mm,a_deg,feed_mm_min,spindle_rpm,torque_true_nm,torque_adc_nm,torque_counts,current_a,torque_from_current_nm,power_w,removal_mm3_s,active\n",
    );
    for k in 0..200 {
        let t = f64::from(k) * 0.05;
        let feed = 100.0 + 50.0 * (t * 0.7).sin();
        let active = if k % 3 == 0 { "torque|power" } else { "" };
        s.push_str(&format!(
            "{t:.4},{},0.0000,0.0000,0.0000,0.000,{feed:.2},{:.1},0.10000,0.1390,1,0.50000,0.09000,{:.3},1.0000,{active}\n",
            10 + k,
            1500.0 + 100.0 * (t * 0.3).cos(),
            20.0 + 5.0 * t.sin()
        ));
    }
    s
}

fn telemetry_svg() -> String {
    Chart {
        title: "Spindle and feed over time (aco)".into(),
        x_label: "time [s]".into(),
        width: 900,
        panel_height: 120,
        panels: vec![Panel {
            title: "feed".into(),
            unit: "mm/min".into(),
            series: vec![Series {
                label: "feed".into(),
                color: "#1f77b4".into(),
                points: vec![(0.0, 1.0), (1.0, 2.0)],
            }],
        }],
    }
    .to_svg()
}

fn cloud_ply(n: usize) -> Vec<u8> {
    let mut pts = Vec::with_capacity(n);
    let side = (n as f64).sqrt().ceil() as usize;
    for k in 0..n {
        let (i, j) = (k % side, k / side);
        let x = X0 + (i as f64 + 0.5) / side as f64 * f64::from(W) * P;
        let y = Y0 + (j as f64 + 0.5) / side as f64 * f64::from(H) * P;
        pts.push(Point3::new(x, y, dome_z(x, y)));
    }
    let mut out = Vec::new();
    write_ply(&mut out, &PointCloud::from_points(pts), None, PlyEncoding::BinaryLittleEndian, &[])
        .expect("ply");
    out
}

fn final_stock() -> HeightMap {
    let m = meta(0.0, 10.0);
    HeightMap::from_fn(m, |c, r| {
        let (x, y) = m.cell_center(c, r);
        (dome_z(x, y) + 0.05 * (x * 2.0).sin().abs()) as f32
    })
    .expect("map")
}

fn deviation_map() -> HeightMap {
    let m = meta(-0.2, 0.2);
    HeightMap::from_fn(m, |c, r| {
        let (x, y) = m.cell_center(c, r);
        ((x / 15.0) * 0.2 + 0.01 * y.sin()) as f32
    })
    .expect("map")
}

fn aref(kind: &str, media: &str, size: usize) -> Value {
    let sha = format!("{:0>64}", kind.len());
    json!({"uri": format!("file:///a/{sha}"), "sha256": sha, "size": size, "media_type": media})
}

fn full_artifacts() -> BTreeMap<String, Vec<u8>> {
    let mut a = BTreeMap::new();
    a.insert("point_cloud".to_string(), cloud_ply(20_000));
    a.insert("depth_map".to_string(), map_png(&depth_map(), PngDepth::Bits16));
    a.insert("coverage_map".to_string(), map_png(&coverage_map(), PngDepth::Bits8));
    a.insert("roughing_map".to_string(), map_png(&depth_map(), PngDepth::Bits16));
    a.insert("gcode".to_string(), gcode().into_bytes());
    a.insert("final_stock".to_string(), map_png(&final_stock(), PngDepth::Bits16));
    a.insert("deviation_map".to_string(), map_png(&deviation_map(), PngDepth::Bits8));
    a.insert("telemetry".to_string(), telemetry_csv().into_bytes());
    a.insert("telemetry_plot".to_string(), telemetry_svg().into_bytes());
    a.insert(
        "machine_report".to_string(),
        serde_json::to_vec(&json!({
            "machine": "emco-f1", "cycle_time_s": 812.5, "cycle_time_no_adaptive_s": 1040.0,
            "cycle_time_other_s": 900.0, "other_policy": "feed_only",
            "run": {"policy": "aco"},
            "deviation": {"max_gouge_mm": 0.012, "max_leftover_mm": 0.2, "mean_leftover_mm": 0.05, "rms_deviation_mm": 0.07, "cells": 9600},
            "part": {"source": "mesh", "points": 5000, "unseen": 1200, "max_search_mm": 10.0, "opened_by": "ball-3",
                     "against_part": {"points": 3800, "max_gouge_mm": 0.021, "max_leftover_mm": 0.61, "mean_leftover_mm": 0.08, "rms_deviation_mm": 0.11},
                     "against_opened": {"points": 3800, "max_gouge_mm": 0.021, "max_leftover_mm": 0.09, "mean_leftover_mm": 0.02, "rms_deviation_mm": 0.03},
                     "faces": [{"a_deg": 0.0, "against_part": {"points": 2000, "max_gouge_mm": 0.02, "max_leftover_mm": 0.6, "mean_leftover_mm": 0.07, "rms_deviation_mm": 0.1}, "against_opened": null}]}
        }))
        .expect("json"),
    );
    a.insert("plan_report".to_string(), br#"{"estimated_time_s": 990.0}"#.to_vec());
    a.insert("machined_part_view".to_string(), part_view_ply());
    a
}

/// A bumpy ball 20 mm across as the machine's view mesh, its deviation varying over it (NaN on a
/// cap: not measured).
fn part_view_ply() -> Vec<u8> {
    let (nu, nv) = (48u32, 24u32);
    let mut vertices = Vec::new();
    let mut dev = Vec::new();
    for j in 0..=nv {
        let th = std::f64::consts::PI * f64::from(j) / f64::from(nv);
        for i in 0..nu {
            let ph = 2.0 * std::f64::consts::PI * f64::from(i) / f64::from(nu);
            let r = 10.0 + 0.5 * (3.0 * ph).sin() * th.sin();
            vertices.push(Point3::new(r * th.sin() * ph.cos(), r * th.sin() * ph.sin(), r * th.cos()));
            dev.push(if j < 3 { f32::NAN } else { (0.05 * (2.0 * ph).sin()) as f32 });
        }
    }
    let mut triangles = Vec::new();
    for j in 0..nv {
        for i in 0..nu {
            let (a, b) = (j * nu + i, j * nu + (i + 1) % nu);
            let (c, d) = (a + nu, b + nu);
            triangles.push([a, c, b]);
            triangles.push([b, c, d]);
        }
    }
    let mesh = depthmill_geometry::Mesh::new(vertices, triangles).expect("mesh");
    let mut out = Vec::new();
    depthmill_geometry::formats::write_mesh_ply(&mut out, &mesh, "deviation", &dev, &[]).expect("ply");
    out
}

fn job(name: &str, status: &str, artifacts: &BTreeMap<String, Vec<u8>>) -> Value {
    let arts: serde_json::Map<String, Value> =
        artifacts.iter().map(|(k, v)| (k.clone(), aref(k, "application/octet-stream", v.len()))).collect();
    json!({
        "id": "0193a1b2-c3d4-7e5f-8a9b-0c1d2e3f4a5b",
        "name": name,
        "status": status,
        "stage": "report",
        "progress": 1.0,
        "error": null,
        "stage_timings_s": {"reconstruct": 1.2, "plan": 0.8, "execute": 14.5, "report": 0.1},
        "artifacts": arts,
        "metrics": {"coverage_pct": 97.3, "max_gouge_mm": 0.012, "max_leftover_mm": 0.2, "rms_deviation_mm": 0.07,
                    "cycle_time_s": 812.5, "cycle_time_no_adaptive_s": 1040.0},
        "spec": {"name": name, "input": {"kind": "point_cloud", "artifact": "ab".repeat(32)},
                 "reconstruct": {"pixel_mm": 0.25, "faces": [{"view": "+Z"}], "fill": {"method": "idw", "max_hole_mm": 2.0}},
                 "plan": {"roughing": {"tool": "flat-6", "step_down_mm": 2.0}, "finishing": {"tool": "ball-3", "strategy": "raster_x"}},
                 "execute": {"machine": "emco-f1", "adaptive": "aco"}},
        "cancel_requested": false,
        "created_at_ms": 1_795_000_000_000i64,
        "updated_at_ms": 1_795_000_017_000i64,
        "attempts": [{"stage": "reconstruct", "attempt": 1, "started_at_ms": 1, "finished_at_ms": 1201, "outcome": "ok"}]
    })
}

fn b64_decode(s: &str) -> Vec<u8> {
    let val = |c: u8| match c {
        b'A'..=b'Z' => c - b'A',
        b'a'..=b'z' => c - b'a' + 26,
        b'0'..=b'9' => c - b'0' + 52,
        b'+' => 62,
        _ => 63,
    };
    let bytes: Vec<u8> = s.bytes().filter(|&c| c != b'=').collect();
    let mut out = Vec::new();
    for ch in bytes.chunks(4) {
        let mut n = 0u32;
        for (i, &c) in ch.iter().enumerate() {
            n |= u32::from(val(c)) << (18 - 6 * i);
        }
        for i in 0..ch.len().saturating_sub(1) {
            out.push((n >> (16 - 8 * i)) as u8);
        }
    }
    out
}

/// Every `data:<media>;base64,...` URI in the page, decoded.
fn data_uris(html: &str) -> Vec<(String, Vec<u8>)> {
    let mut out = Vec::new();
    let mut rest = html;
    while let Some(i) = rest.find("data:") {
        rest = &rest[i + 5..];
        let Some(semi) = rest.find(";base64,") else { break };
        let media = rest[..semi].to_string();
        rest = &rest[semi + 8..];
        let end = rest.find('"').unwrap_or(rest.len());
        out.push((media, b64_decode(&rest[..end])));
        rest = &rest[end..];
    }
    out
}

fn render_ok(job: &Value, artifacts: &BTreeMap<String, Vec<u8>>) -> ReportOutput {
    render(&ReportInput { job, artifacts, digests: &crate::digest::Digests::NONE }).expect("render")
}

const SECTIONS: [&str; 10] = [
    "summary",
    "parameters",
    "point-cloud",
    "depth-map",
    "toolpaths",
    "final-stock",
    "deviation",
    "telemetry",
    "cycle-time",
    "<header>",
];

fn has_section(html: &str, s: &str) -> bool {
    if s.starts_with('<') { html.contains(s) } else { html.contains(&format!(r#"<section id="{s}">"#)) }
}

#[test]
fn a_full_job_has_every_section_and_every_picture_decodes() {
    let arts = full_artifacts();
    let job = job("bracket", "succeeded", &arts);
    let out = render_ok(&job, &arts);
    for s in SECTIONS {
        assert!(has_section(&out.html, s), "section {s} missing");
    }
    assert!(!out.html.contains("class=\"missing\""), "nothing should be missing: {}", out.html);
    let names: Vec<&str> = out.files.iter().map(|f| f.0.as_str()).collect();
    for n in [
        "point_cloud_top.png",
        "point_cloud_side.png",
        "depth_map.png",
        "coverage_map.png",
        "toolpaths.png",
        "final_stock.png",
        "deviation_map.png",
        "telemetry.svg",
        "cycle_time.svg",
    ] {
        assert!(names.contains(&n), "file {n} missing from {names:?}");
    }
    for (name, bytes) in &out.files {
        if name.ends_with(".png") {
            let img = image::load_from_memory(bytes).unwrap_or_else(|e| panic!("{name}: {e}"));
            assert!(img.width() >= 100 && img.height() >= 50, "{name} {}x{}", img.width(), img.height());
        } else {
            assert!(String::from_utf8_lossy(bytes).contains("<svg"), "{name}");
        }
    }
    // What the page embeds decodes too, and is self-contained.
    let uris = data_uris(&out.html);
    let pngs: Vec<_> = uris.iter().filter(|u| u.0 == "image/png").collect();
    assert_eq!(pngs.len(), out.files.iter().filter(|f| f.0.ends_with(".png")).count());
    for (_, b) in &pngs {
        image::load_from_memory(b).expect("embedded png");
    }
    assert!(uris.iter().any(|u| u.0 == "image/svg+xml"));
    assert!(!out.html.contains("src=\"http") && !out.html.contains("href=\"http"));
    // The one script is the 3-D viewer's.
    assert_eq!(out.html.to_ascii_lowercase().matches("<script").count(), 1);
    assert!(out.html.contains(&format!("<script>{}</script>", sections::solid::VIEWER_JS)));
    // Metrics and numbers a reader looks for.
    for needle in ["97.3 %", "0.012 mm", "0.200 mm", "0.050 mm", "0.070 mm", "21.9 %", "13 min", "feed_only"]
    {
        assert!(out.html.contains(needle), "{needle} not in the page");
    }
    // Parameters are shown as rows, not only JSON.
    assert!(out.html.contains("<th>roughing.tool</th><td><code>flat-6</code></td>"));
}

#[test]
fn a_scanned_job_shows_its_scan() {
    let mut arts = full_artifacts();
    let report = serde_json::json!({
        "mode": "dynamic", "frames": 1200, "points": 480000, "scan_time_s": 31.5, "table_wait_s": 6.9,
        "registration_rms_mm": 0.0002, "registration_max_mm": 0.0007,
        "registration_merge_rms_mm": 0.0135, "calibrated": true,
        "calibration": {"id": "cal_x<y>", "version": 3, "sphere_rms_mm": 0.0332, "table_fit_rms_mm": 0.0023,
                        "registration_before": {"merge_rms_mm": 1.5416}, "registration_after": {"merge_rms_mm": 0.0113},
                        "truth": {"table_error_mm": 0.0214, "mount_error_mm": 0.0066}},
        "dropped": {"out_of_window": 1, "incidence": 2, "occluded": 3, "miss": 4},
        "coverage_before_rescan": {"pixel_mm": 0.5, "covered_pct": 97.5, "footprint_cells": 100, "holes": 3, "hole_area_mm2": 12.0},
        "coverage_after_rescan": {"pixel_mm": 0.5, "covered_pct": 99.1, "footprint_cells": 100, "holes": 1, "hole_area_mm2": 2.0},
        "stations": [{"table_deg_commanded": 0.0, "table_deg_measured": 0.0, "rescan": false,
                      "passes": [{"frames": 600, "points": 240000}, {"frames": 600, "points": 240000}]},
                     {"table_deg_commanded": 110.0, "table_deg_measured": 110.0, "rescan": false, "table_offset_deg": 20.0,
                      "table_move": {"turn_deg": 110.0, "peak_speed_deg_s": 45.0, "peak_accel_deg_s2": 200.0, "time_s": 2.67},
                      "passes": [{"frames": 600, "points": 240000, "quality": 0.95, "min_dexterity": 1.85e7,
                                  "min_margins": {"wrist_deg": 28.5, "elbow_deg": 40.2, "shoulder_mm": 450.0}}]},
                     {"table_deg_commanded": 45.0, "table_deg_measured": 45.0, "rescan": true, "passes": []}],
        "silhouette": {"pixel_mm": 0.5, "silhouette_cells": 4702, "seen_cells": 3471, "covered_pct": 73.82,
                       "unseen_area_mm2": 307.8,
                       "unseen_regions": [{"center_x_mm": -7.65, "center_y_mm": 12.77, "extent_mm": 20.5, "area_mm2": 76.25}]},
        "units": {"unit": "m", "scale_to_mm": 1000.0, "source": "size", "reason": "largest extent 0.0520 units"}
    });
    arts.insert("scan_report".into(), serde_json::to_vec(&report).expect("json"));
    let plan = serde_json::json!({"tool_choice": ["roughing flat-6, finishing ball-3: tool ball-3: the holder touches <here>",
                                                  "chose roughing flat-6, finishing ball-6: every point they visit is reachable"]});
    arts.insert("plan_report".into(), serde_json::to_vec(&plan).expect("json"));
    let job = job("scanned", "succeeded", &arts);
    let out = render_ok(&job, &arts);
    for needle in [
        "Registration error",
        "RMS 0.0002 mm",
        "Merge error (after the best rigid fit)",
        "RMS 0.0135 mm",
        "version 3 (cal_x&lt;y&gt;): sphere fit RMS 0.0332 mm, table fit RMS 0.0023 mm; merge error of its scans 1.5416 mm before, 0.0113 mm after; against the simulated cell's truth: table 0.0214 mm, scanner mount 0.0066 mm",
        "97.50 % (3 holes",
        "99.10 % (1 holes",
        "rescan",
        "4 missing the part",
        "73.82 %, 307.8 mm² unseen; largest: 76.2 mm² at (-7.7, 12.8)",
        "m (size: largest extent 0.0520 units)",
        "Tool choice",
        "touches &lt;here&gt;",
        "chose roughing flat-6, finishing ball-6",
        "turned for the arm",
        "+20°",
        "1.85e7",
        "28.5° / 40.2° / 450 mm",
        "110.0° at up to 45.0 °/s, 2.67 s",
    ] {
        assert!(out.html.contains(needle), "{needle} missing from the scan summary");
    }
    // A calibration made for this scan: its version from the job's metrics, and how it was made.
    let mut made = report.clone();
    made["calibration"] = serde_json::json!({"made_for_this_scan": true, "during_scan": true,
                                            "why_not_during_scan": null, "sphere_rms_mm": 0.0331,
                                            "table_fit_rms_mm": 0.0024});
    let mut arts2 = arts.clone();
    arts2.insert("scan_report".into(), serde_json::to_vec(&made).expect("json"));
    let mut job2 = job.clone();
    job2["metrics"]["scan_calibration_version"] = serde_json::json!(1.0);
    let out2 = render_ok(&job2, &arts2);
    assert!(
        out2.html.contains("version 1, made for this scan at its own stations: sphere fit RMS 0.0331 mm"),
        "the calibration made during the scan"
    );
    made["calibration"]["why_not_during_scan"] = serde_json::json!("the part reaches <the nest>");
    arts2.insert("scan_report".into(), serde_json::to_vec(&made).expect("json"));
    let out3 = render_ok(&job2, &arts2);
    assert!(
        out3.html.contains("made for this scan by the routine before it (the part reaches &lt;the nest&gt;)")
    );
    // Without a scan report there is no scan table.
    let plain = render_ok(&job, &full_artifacts());
    assert!(!plain.html.contains("Registration error"));
}

/// The dome as a fine height-field mesh, each vertex moved by `place`, as binary STL.
fn dome_stl(place: &depthmill_geometry::Pose) -> Vec<u8> {
    let n = 161;
    let (x0, y0, w, h) = (X0, Y0, f64::from(W) * P, f64::from(H) * P);
    let mut vertices = Vec::new();
    for j in 0..n {
        for i in 0..n {
            let x = x0 + w * i as f64 / (n - 1) as f64;
            let y = y0 + h * j as f64 / (n - 1) as f64;
            vertices.push(place * depthmill_geometry::nalgebra::Point3::new(x, y, dome_z(x, y)));
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
    let mesh = depthmill_geometry::Mesh { vertices, triangles };
    let mut stl = Vec::new();
    depthmill_geometry::formats::write_stl(&mut stl, &mesh, "report test").expect("stl");
    stl
}

#[test]
fn the_machined_part_is_compared_with_the_original_mesh() {
    // The dome as a fine height-field mesh; the final stock is the dome plus up to 0.05 mm.
    let mut arts = full_artifacts();
    arts.insert("mesh".into(), dome_stl(&depthmill_geometry::Pose::identity()));
    let job = job("from a mesh", "succeeded", &arts);
    let out = render_ok(&job, &arts);
    assert!(out.html.contains("Against the original part"));
    assert!(out.files.iter().any(|f| f.0 == "deviation_from_part.png"));
    let at = out.html.find("Against the original part").expect("section");
    let part = &out.html[at..];
    // The stock is the dome plus 0.05·|sin 2x|: mean leftover 0.05 · 2/π = 0.032 mm. (At the
    // dome's vertical rim the mesh's facets chord across the step, so single cells there read
    // tenths of a millimetre either way: the max rows are not checked.)
    let row = &part[part.find("Mean leftover").expect("row")..][..60];
    assert!(row.contains("0.03"), "{row}");
    assert!(part.contains("mm over 9600 cells"), "every cell of the grid is compared");
    // Against the dome opened by the program's finest tool (ball-3) where it reaches: the dome
    // is convex, so the opening is the dome there and the same leftover shows, no gouge.
    assert!(part.contains("Against the part opened by ball-3"), "opened row");
    let mean = out.figures["part_opened_mean_mm"];
    assert!((0.028..0.036).contains(&mean), "opened mean {mean}");
    assert!(out.figures["part_opened_max_gouge_mm"] < 1e-3 && out.figures["part_opened_cells"] > 5000.0);
}

#[test]
fn the_deepest_gouge_against_the_opened_part_is_located() {
    // The dome machined exactly, except a 0.2 mm dent over 3 x 3 cells around (0.125, 0.125).
    let mut arts = full_artifacts();
    arts.insert("mesh".into(), dome_stl(&depthmill_geometry::Pose::identity()));
    let m = meta(0.0, 10.0);
    let stock = HeightMap::from_fn(m, |c, r| {
        let (x, y) = m.cell_center(c, r);
        let dent = if (59..=61).contains(&c) && (39..=41).contains(&r) { 0.2 } else { 0.0 };
        (dome_z(x, y) - dent) as f32
    })
    .expect("map");
    arts.insert("final_stock".to_string(), map_png(&stock, PngDepth::Bits16));
    let job = job("a dent", "succeeded", &arts);
    let out = render_ok(&job, &arts);
    let gouge = out.figures["part_opened_max_gouge_mm"];
    assert!((0.15..0.25).contains(&gouge), "gouge {gouge}");
    let (x, y) = (out.figures["part_opened_max_gouge_x_mm"], out.figures["part_opened_max_gouge_y_mm"]);
    assert!((x - 0.125).abs() <= P + 1e-9 && (y - 0.125).abs() <= P + 1e-9, "at ({x}, {y})");
    // The dent lies where the scan measured: the measured cells' figures hold it too.
    let measured = out.figures["part_opened_measured_max_gouge_mm"];
    assert_eq!(measured, gouge);
    assert!(out.figures["part_opened_measured_cells"] < out.figures["part_opened_cells"]);

    // The same with the dent's cells filled between points rather than measured: the measured
    // figures leave it out, the others keep it.
    let mut cov = coverage_map();
    for r in 38..=42 {
        for c in 58..=62 {
            let i = (r * W + c) as usize;
            cov.data_mut()[i] = 0.5;
        }
    }
    arts.insert("coverage_map".to_string(), map_png(&cov, PngDepth::Bits8));
    let out = render_ok(&job, &arts);
    assert_eq!(out.figures["part_opened_max_gouge_mm"], gouge);
    let measured = out.figures["part_opened_measured_max_gouge_mm"];
    assert!(measured < 0.01, "measured cells' gouge {measured}");
}

#[test]
fn a_part_turned_for_its_first_face_is_compared_turned_the_same_way() {
    // The dome seen with the part turned to A=30: the mesh is the dome turned back by -30° about
    // X, so that the report, turning it to the first face's view, finds the dome again.
    let face = depthmill_geometry::Face::A { angle_deg: 30.0 };
    let stl = dome_stl(&face.view_from_part_pose().inverse());
    let mut arts = full_artifacts();
    let mut turned = depth_map();
    turned.set_face(face).expect("face");
    arts.insert("depth_map".into(), map_png(&turned, PngDepth::Bits16));
    arts.insert("mesh".into(), stl);
    let job = job("turned", "succeeded", &arts);
    let out = render_ok(&job, &arts);
    let at = out.html.find("Against the original part").expect("the turned part is compared");
    let part = &out.html[at..];
    let row = &part[part.find("Mean leftover").expect("row")..][..60];
    assert!(row.contains("0.03"), "{row}");
}

#[test]
fn the_machined_part_is_compared_with_the_cams_preview() {
    let mut arts = full_artifacts();
    let stock = final_stock();
    let lowered: Vec<f32> = stock.data().iter().map(|z| z - 0.02).collect();
    let preview = HeightMap::new(*stock.meta(), lowered).expect("map");
    arts.insert("toolpath_preview".into(), map_png(&preview, PngDepth::Bits16));
    let job = job("compared", "succeeded", &arts);
    let out = render_ok(&job, &arts);
    assert!(out.html.contains("Against the surface the program can leave"));
    assert!(out.files.iter().any(|f| f.0 == "deviation_from_preview.png"));
    // 16-bit PNG quantisation aside, the stock is 0.02 mm above the preview everywhere.
    let at = out.html.find("Highest above the preview").expect("row");
    let row = &out.html[at..at + 200];
    assert!(row.contains("0.02"), "{row}");
    // Without a preview the comparison is left out.
    let plain = render_ok(&job, &full_artifacts());
    assert!(!plain.html.contains("Against the surface the program can leave"));
}

#[test]
fn toolpaths_show_roughing_and_finishing_in_their_colours() {
    let arts = full_artifacts();
    let out = render_ok(&job("p", "succeeded", &arts), &arts);
    let bytes = &out.files.iter().find(|f| f.0 == "toolpaths.png").expect("toolpaths").1;
    let img = image::load_from_memory(bytes).expect("png").to_rgb8();
    let (mut orange, mut blue) = (0, 0);
    for p in img.pixels() {
        let [r, g, b] = p.0;
        if r > 180 && (80..150).contains(&g) && b < 70 {
            orange += 1;
        }
        if b > 180 && r < 70 && g < 130 {
            blue += 1;
        }
    }
    assert!(orange > 500, "roughing pixels: {orange}");
    assert!(blue > 500, "finishing pixels: {blue}");
    // The program's table names both operations.
    assert!(out.html.contains("T1 flat-6: roughing-x with flat-6"));
    assert!(out.html.contains("T2 ball-3: finishing-raster-x with ball-3"));
}

#[test]
fn toolpaths_land_on_the_map_where_the_program_says() {
    let p = gcode::parse(&gcode());
    let img = toolpath_image(Some(&depth_map()), &p, 0).expect("image");
    // The map spans 30 x 20 mm and the moves stay inside it: the view is the map's, 800 px wide.
    assert_eq!((img.width, img.height), (800, 533));
    // The roughing line at y = -9 + 2.4 = -6.6 mm from x = -14 to 14 is orange in the middle.
    let s = 800.0 / 30.0;
    let (u, v) = ((0.0 - X0) * s, (Y0 + 20.0 - (-6.6)) * s);
    let px = img.get(u as u32, v as u32).expect("pixel");
    assert!(px[0] > 180 && px[2] < 70, "{px:?}");
}

#[test]
fn missing_artifacts_give_notes_not_errors() {
    let arts = BTreeMap::new();
    let mut j = job("empty", "failed", &arts);
    j["error"] =
        json!({"code": "invalid_argument", "message": "plan.stock.z_mm: must be positive", "stage": "plan"});
    j["metrics"] = json!({});
    j["stage_timings_s"] = json!({});
    let out = render_ok(&j, &arts);
    for s in SECTIONS {
        assert!(has_section(&out.html, s), "section {s} missing");
    }
    assert!(out.files.is_empty());
    assert!(out.html.contains("Not produced: the job failed in the plan stage"), "{}", out.html);
    assert!(out.html.matches(r#"class="missing""#).count() >= 7);
    // A job that started from a depth map never had a cloud.
    let mut arts = BTreeMap::new();
    arts.insert("depth_map".to_string(), map_png(&depth_map(), PngDepth::Bits16));
    let mut j = job("from a map", "running", &arts);
    j["spec"]["input"]["kind"] = json!("depth_map");
    let out = render_ok(&j, &arts);
    assert!(out.html.contains("the job started at the plan stage"), "{}", out.html);
    assert!(out.html.contains("the job is running and the execute stage has not finished"));
    // Listed in the job but bytes not passed.
    let mut j = job("x", "succeeded", &arts);
    j["artifacts"]["gcode"] = aref("gcode", "text/x-gcode", 10);
    let out = render_ok(&j, &arts);
    assert!(out.html.contains("its bytes were not passed to the report"));
}

#[test]
fn unreadable_artifacts_are_reported_in_their_section() {
    let mut arts = full_artifacts();
    arts.insert("depth_map".to_string(), b"not an image".to_vec());
    arts.insert("point_cloud".to_string(), b"1 2\n".to_vec());
    arts.insert("gcode".to_string(), vec![0xff, 0xfe, 0x00]);
    arts.insert("telemetry_plot".to_string(), b"garbage".to_vec());
    arts.insert("telemetry".to_string(), b"a,b\n1,2\n".to_vec());
    let out = render_ok(&job("bad", "succeeded", &arts), &arts);
    assert!(out.html.contains("the depth_map artifact could not be read"), "{}", out.html);
    assert!(out.html.contains("the point_cloud artifact could not be read"));
    assert!(out.html.contains("not UTF-8"));
    assert!(out.html.contains("telemetry CSV could not be read"));
}

#[test]
fn text_from_the_job_is_escaped() {
    let arts = full_artifacts();
    let evil = "<script>alert('x')</script>\"><img src=x onerror=alert(1)>";
    let mut j = job(evil, "succeeded", &arts);
    j["spec"]["plan"]["finishing"]["tool"] = json!("</td><script>alert(2)</script>");
    j["error"] = json!({"code": "<b>", "message": "<iframe>", "stage": "plan"});
    let out = render_ok(&j, &arts);
    let lower = out.html.to_ascii_lowercase();
    // The viewer's script only.
    assert_eq!(lower.matches("<script").count(), 1, "unescaped script");
    assert!(out.html.contains(&format!("<script>{}</script>", sections::solid::VIEWER_JS)));
    assert!(!lower.contains("<iframe") && !lower.contains("<img src=x"));
    assert!(out.html.contains("&lt;script&gt;alert(&#39;x&#39;)&lt;/script&gt;"));
}

#[test]
fn a_job_that_is_not_an_object_is_an_error() {
    let arts = BTreeMap::new();
    let e = render(&ReportInput {
        job: &json!([1, 2]),
        artifacts: &arts,
        digests: &crate::digest::Digests::NONE,
    })
    .err()
    .expect("error");
    assert!(matches!(e, ReportError::JobNotAnObject { found: "an array" }), "{e}");
}

#[test]
fn several_faces_get_one_picture_each() {
    let mut arts = full_artifacts();
    let mut m1 = depth_map();
    m1.set_face(depthmill_geometry::Face::A { angle_deg: 90.0 }).expect("face");
    arts.insert("depth_map@1".to_string(), map_png(&m1, PngDepth::Bits16));
    arts.insert("coverage_map@1".to_string(), map_png(&coverage_map(), PngDepth::Bits8));
    // The same operations again after a face comment.
    let g = gcode().replace("M30\n%\n", "");
    let second = gcode().replacen("(T1 flat-6", "(face 2 at A 90.0000 deg)\n(T1 flat-6", 1);
    let g =
        format!("{}{}", g.replacen("G64 P0.0100\n", "G64 P0.0100\n(face 1 at A 0.0000 deg)\n", 1), second);
    arts.insert("gcode".to_string(), g.into_bytes());
    let out = render_ok(&job("two faces", "succeeded", &arts), &arts);
    let names: Vec<&str> = out.files.iter().map(|f| f.0.as_str()).collect();
    for n in [
        "depth_map.png",
        "depth_map_face2.png",
        "coverage_map_face2.png",
        "toolpaths.png",
        "toolpaths_face2.png",
    ] {
        assert!(names.contains(&n), "{n} not in {names:?}");
    }
    assert!(out.html.contains("<h3>Face 2 (A=90)</h3>"), "{}", out.html);
}

#[test]
fn telemetry_is_drawn_from_the_csv_without_the_plot() {
    let mut arts = full_artifacts();
    arts.remove("telemetry_plot");
    let out = render_ok(&job("csv", "succeeded", &arts), &arts);
    let svg = &out.files.iter().find(|f| f.0 == "telemetry.svg").expect("svg").1;
    let svg = String::from_utf8_lossy(svg);
    assert!(svg.contains("from the telemetry CSV") && svg.contains("cutting power"));
    assert!(out.html.contains("Limit &#39;torque&#39; active"));
}

#[test]
fn coverage_classes_are_counted_from_the_8_bit_map() {
    let d = maps::decode_map(&map_png(&coverage_map(), PngDepth::Bits8), None).expect("decode");
    let c = maps::coverage_counts(&d.map);
    assert!(c.iter().all(|&n| n > 0), "{c:?}");
    assert_eq!(c.iter().sum::<usize>(), (W * H) as usize);
}

fn chromium() -> Option<std::path::PathBuf> {
    let path = std::env::var_os("PATH")?;
    for dir in std::env::split_paths(&path) {
        for name in ["chromium", "chromium-browser", "google-chrome", "google-chrome-stable"] {
            let p = dir.join(name);
            if p.is_file() {
                return Some(p);
            }
        }
    }
    None
}

/// The browser, or `None` (the test is skipped) when there is none and
/// `DEPTHMILL_REQUIRE_CHROMIUM=1` does not make that a failure.
fn chromium_or_skip() -> Option<std::path::PathBuf> {
    let bin = chromium();
    if bin.is_none() {
        if std::env::var("DEPTHMILL_REQUIRE_CHROMIUM").as_deref() == Ok("1") {
            panic!("DEPTHMILL_REQUIRE_CHROMIUM=1 but no chromium, chromium-browser or google-chrome on PATH");
        }
        eprintln!("skipped: no chromium on PATH (set DEPTHMILL_REQUIRE_CHROMIUM=1 to make this fail)");
    }
    bin
}

#[test]
fn chromium_renders_the_page() {
    let Some(bin) = chromium_or_skip() else { return };
    let arts = full_artifacts();
    let out = render_ok(&job("chromium check", "succeeded", &arts), &arts);
    let dir = std::env::temp_dir().join(format!("depthmill-report-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("tmp");
    let page = dir.join("report.html");
    let shot = dir.join("shot.png");
    std::fs::write(&page, &out.html).expect("write");
    let _ = std::fs::remove_file(&shot);
    let status = std::process::Command::new(&bin)
        .args([
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--hide-scrollbars",
            &format!("--user-data-dir={}", dir.join("profile").display()),
            &format!("--screenshot={}", shot.display()),
            "--window-size=1280,4000",
            &format!("file://{}", page.display()),
        ])
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .status()
        .expect("run chromium");
    assert!(status.success(), "chromium exited with {status}");
    let img = image::open(&shot).expect("screenshot").to_rgb8();
    assert_eq!((img.width(), img.height()), (1280, 4000));
    // Not blank: many distinct colours, and the coloured pictures are there.
    let mut colours = std::collections::HashSet::new();
    let mut saturated = 0usize;
    for p in img.pixels() {
        colours.insert(p.0);
        let [r, g, b] = p.0.map(i32::from);
        if r.max(g).max(b) - r.min(g).min(b) > 80 {
            saturated += 1;
        }
    }
    assert!(colours.len() > 500, "{} colours only", colours.len());
    assert!(saturated > 50_000, "{saturated} coloured pixels");
    let keep = std::env::var_os("DEPTHMILL_KEEP_SHOT").is_some();
    if keep {
        eprintln!("screenshot kept at {}", shot.display());
    } else {
        let _ = std::fs::remove_dir_all(&dir);
    }
}

#[test]
fn the_3d_view_shows_the_part_and_the_figures() {
    let arts = full_artifacts();
    let out = render_ok(&job("viewer", "succeeded", &arts), &arts);
    let html = &out.html;
    assert!(html.contains(r#"<section id="part3d">"#), "no 3-D section");
    assert_eq!(html.matches("<script>").count(), 1, "one script: the viewer");
    assert!(
        html.contains("class=\"viewer3d\"")
            && html.contains("tabindex=\"0\"")
            && html.contains("aria-label=")
    );
    assert!(html.contains("Part opened by ball-3") && html.contains("0.6100"), "figures table");
    // No mesh: no section, no script. A bad mesh: a note, no script.
    let mut none = full_artifacts();
    none.remove("machined_part_view");
    let out = render_ok(&job("no viewer", "succeeded", &none), &none);
    assert!(!out.html.contains("<script>") && !out.html.contains("part3d"));
    let mut bad = full_artifacts();
    bad.insert("machined_part_view".into(), b"ply\nformat ascii 1.0\nend_header\n".to_vec());
    let out = render_ok(&job("bad viewer", "succeeded", &bad), &bad);
    assert!(
        !out.html.contains("<script>") && out.html.contains("could not be read"),
        "a note names the problem"
    );
}

/// The viewer runs in the real browser: it draws the part, and dragging, a key and the wheel turn
/// and zoom it.
#[test]
fn chromium_turns_the_3d_view() {
    let Some(bin) = chromium_or_skip() else { return };
    let arts = full_artifacts();
    let out = render_ok(&job("viewer check", "succeeded", &arts), &arts);
    // After the page's own script: count the canvas's drawn pixels, then drag, press a key and
    // turn the wheel, and write what the viewer reports into the page for --dump-dom.
    let probe = r#"<script>
(function () {
  var f = document.querySelector('figure.viewer3d'), cv = f.querySelector('canvas');
  var px = cv.getContext('2d').getImageData(0, 0, cv.width, cv.height).data, coloured = 0;
  for (var i = 0; i < px.length; i += 4) {
    var mx = Math.max(px[i], px[i + 1], px[i + 2]), mn = Math.min(px[i], px[i + 1], px[i + 2]);
    if (mx < 250 || mx - mn > 30) coloured++;
  }
  var before = [f.dataset.yaw, f.dataset.pitch, f.dataset.zoom, f.dataset.drawn];
  var ev = function (type, x, y) { return new PointerEvent(type, { clientX: x, clientY: y, pointerId: 7, bubbles: true }); };
  cv.dispatchEvent(ev('pointerdown', 100, 100));
  cv.dispatchEvent(ev('pointermove', 160, 130));
  cv.dispatchEvent(ev('pointerup', 160, 130));
  var dragged = [f.dataset.yaw, f.dataset.pitch];
  cv.dispatchEvent(new KeyboardEvent('keydown', { key: 'ArrowRight', bubbles: true }));
  cv.dispatchEvent(new WheelEvent('wheel', { deltaY: -200, bubbles: true, cancelable: true }));
  var out = document.createElement('pre');
  out.id = 'probe';
  out.textContent = JSON.stringify({ coloured: coloured, before: before, dragged: dragged, after: [f.dataset.yaw, f.dataset.zoom] });
  document.body.appendChild(out);
})();
</script>"#;
    let page_html = out.html.replace("</body>", &format!("{probe}</body>"));
    let dir = std::env::temp_dir().join(format!("depthmill-viewer-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("tmp");
    let page = dir.join("report.html");
    std::fs::write(&page, page_html).expect("write");
    let output = std::process::Command::new(&bin)
        .args([
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            &format!("--user-data-dir={}", dir.join("profile").display()),
            "--virtual-time-budget=5000",
            "--dump-dom",
            &format!("file://{}", page.display()),
        ])
        .stderr(std::process::Stdio::null())
        .output()
        .expect("run chromium");
    let _ = std::fs::remove_dir_all(&dir);
    assert!(output.status.success(), "chromium exited with {}", output.status);
    let dom = String::from_utf8_lossy(&output.stdout);
    let start = dom.find("<pre id=\"probe\">").expect("the probe ran") + "<pre id=\"probe\">".len();
    let end = start + dom[start..].find("</pre>").expect("end of the probe");
    let probe: Value = serde_json::from_str(&dom[start..end].replace("&quot;", "\"")).expect("probe JSON");
    let num = |v: &Value| v.as_str().and_then(|s| s.parse::<f64>().ok()).expect("a number");
    assert!(probe["coloured"].as_u64().unwrap_or(0) > 20_000, "the part is drawn: {probe}");
    let drawn = num(&probe["before"][3]);
    assert!(drawn > 500.0 && drawn < 2304.0, "front faces only: {probe}");
    assert!((num(&probe["dragged"][0]) - num(&probe["before"][0]) - 0.6).abs() < 1e-3, "drag turns: {probe}");
    assert!((num(&probe["dragged"][1]) - num(&probe["before"][1]) - 0.3).abs() < 1e-3, "drag tilts: {probe}");
    assert!(
        (num(&probe["after"][0]) - num(&probe["dragged"][0]) - 0.1).abs() < 1e-3,
        "the arrow key turns: {probe}"
    );
    assert!(num(&probe["after"][1]) > num(&probe["before"][2]) * 1.2, "the wheel zooms in: {probe}");
}

/// Release timing on a realistic job: `cargo test --release -- --ignored --nocapture timing`.
#[test]
#[ignore]
fn timing_realistic_job() {
    let (w, h, p) = (1000u32, 800u32, 0.1);
    let mut m = HeightMapMeta::new(w, h, p);
    (m.origin_x_mm, m.origin_y_mm, m.z_min_mm, m.z_max_mm) = (-50.0, -40.0, 0.0, 12.0);
    let z = |x: f64, y: f64| 2.0 + 8.0 * (-(x * x + y * y) / 600.0).exp() + 0.5 * (x / 3.0).sin();
    let depth = HeightMap::from_fn(m, |c, r| {
        let (x, y) = m.cell_center(c, r);
        z(x, y) as f32
    })
    .expect("map");
    let mut cm = m;
    (cm.z_min_mm, cm.z_max_mm) = (0.0, 1.0);
    let cov = HeightMap::from_fn(cm, |c, r| if (c / 7 + r / 5) % 17 == 0 { 0.5 } else { 1.0 }).expect("map");
    let mut dm = m;
    (dm.z_min_mm, dm.z_max_mm) = (-0.3, 0.3);
    let dev =
        HeightMap::from_fn(dm, |c, r| ((f64::from(c) - 500.0) / 2000.0 + f64::from(r % 9) * 0.01) as f32)
            .expect("map");
    let n = 1_000_000usize;
    let mut pts = Vec::with_capacity(n);
    let mut s = 12345u64;
    for _ in 0..n {
        s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        let x = -50.0 + (s >> 11) as f64 / (1u64 << 53) as f64 * 100.0;
        s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        let y = -40.0 + (s >> 11) as f64 / (1u64 << 53) as f64 * 80.0;
        pts.push(Point3::new(x, y, z(x, y)));
    }
    let mut ply = Vec::new();
    write_ply(&mut ply, &PointCloud::from_points(pts), None, PlyEncoding::BinaryLittleEndian, &[])
        .expect("ply");
    // A raster finishing program over the map: 0.3 mm step-over, 0.5 mm points (~ 130 000 blocks).
    let mut g = String::from(
        "(T1 flat-6: flat D6.0000 mm, 2 flutes - roughing-x with flat-6)\nT1 M6\nG0 X-50 Y-40\nZ15\nG1 Z8 F300\n",
    );
    let mut y = -40.0;
    while y < 40.0 {
        g.push_str(&format!("G1 Y{y:.4}\nX50\nG0 Z15\nX-50\nG1 Z8\n"));
        y += 2.4;
    }
    g.push_str("(T2 ball-3: ball D3.0000 mm, 2 flutes - finishing-raster-x with ball-3)\nT2 M6\n");
    let mut y = -40.0;
    let mut dir = 1.0;
    while y < 40.0 {
        g.push_str(&format!("G1 Y{y:.4}\n"));
        let mut x = -50.0;
        while x <= 50.0 {
            let xx = x * dir;
            g.push_str(&format!("X{xx:.4} Z{:.4}\n", z(xx, y)));
            x += 0.5;
        }
        dir = -dir;
        y += 0.3;
    }
    let mut arts = BTreeMap::new();
    arts.insert("point_cloud".to_string(), ply);
    arts.insert("depth_map".to_string(), map_png(&depth, PngDepth::Bits16));
    arts.insert("coverage_map".to_string(), map_png(&cov, PngDepth::Bits8));
    arts.insert("final_stock".to_string(), map_png(&depth, PngDepth::Bits16));
    arts.insert("deviation_map".to_string(), map_png(&dev, PngDepth::Bits8));
    arts.insert("gcode".to_string(), g.into_bytes());
    arts.insert("telemetry".to_string(), telemetry_csv().into_bytes());
    let j = job("timing", "succeeded", &arts);
    let t = std::time::Instant::now();
    let out = render_ok(&j, &arts);
    let total = t.elapsed();
    let t = std::time::Instant::now();
    let cloud = cloud::read_cloud(&arts["point_cloud"], "point_cloud").expect("cloud");
    let read = t.elapsed();
    let t = std::time::Instant::now();
    let _ = cloud::views(&cloud.cloud);
    let views = t.elapsed();
    eprintln!(
        "render: {total:?} total (cloud read {read:?}, cloud views {views:?}); html {:.1} MB, {} files, {} G-code bytes",
        out.html.len() as f64 / 1e6,
        out.files.len(),
        arts["gcode"].len()
    );
}

#[test]
fn the_wall_zone_is_the_cells_near_steep_steps_and_the_outline() {
    // A 10 x 10 grid of 0.1 mm cells: a 5 mm step between columns 4 and 5, a gentle 10° ramp
    // beyond, the last row off the part.
    let meta = HeightMapMeta { z_min_mm: 0.0, z_max_mm: 10.0, ..HeightMapMeta::new(10, 10, 0.1) };
    let data: Vec<f32> = (0..100)
        .map(|i| {
            let (r, c) = (i / 10, i % 10);
            if r == 9 {
                f32::NAN
            } else if c < 5 {
                0.0
            } else {
                5.0 + 0.1 * (c as f32) * 10f32.to_radians().tan()
            }
        })
        .collect();
    let part = HeightMap::new(meta, data).expect("map");
    let walls = crate::sections::part::wall_zone(&part, 0.2);
    for r in 0..9 {
        for c in 0..10 {
            let want = (3..=6).contains(&c) || r >= 7;
            assert_eq!(walls[r * 10 + c], want, "row {r} column {c}");
        }
    }
    assert!(!walls[90], "cells off the part are not counted at all");
}

/// The report from streamed digests (what the orchestrator renders) is the report from bytes,
/// picture for picture, for artifacts under the digests' bounds.
#[test]
fn a_report_from_streamed_artifacts_equals_the_one_from_bytes() {
    let artifacts = full_artifacts();
    let job = job("streamed", "succeeded", &artifacts);
    let from_bytes = render_ok(&job, &artifacts);
    let mut rest = artifacts.clone();
    let mut digests = crate::digest::Digests::default();
    for (kind, bytes) in &artifacts {
        let r = std::io::BufReader::new(&bytes[..]);
        match crate::digest::reading(kind) {
            crate::digest::Reading::Cloud => {
                let c = crate::digest::cloud(r, kind, Some(bytes.len() as u64)).expect("cloud");
                digests.clouds.insert(kind.clone(), c);
                rest.remove(kind);
            }
            crate::digest::Reading::Program => {
                digests.programs.insert(kind.clone(), crate::digest::program(r).expect("program"));
                rest.remove(kind);
            }
            crate::digest::Reading::Telemetry => {
                digests.telemetry = Some(crate::digest::telemetry(r).expect("telemetry"));
                rest.remove(kind);
            }
            crate::digest::Reading::Unused => {
                rest.remove(kind);
            }
            crate::digest::Reading::Bytes => {}
        }
    }
    assert!(!digests.clouds.is_empty() && !digests.programs.is_empty() && digests.telemetry.is_some());
    let streamed = render(&ReportInput { job: &job, artifacts: &rest, digests: &digests }).expect("render");
    assert_eq!(streamed.html, from_bytes.html);
    assert_eq!(streamed.figures, from_bytes.figures);
}

/// A program past the parser's piece budget is drawn from joined pieces: the same operations,
/// lengths, extents and warnings, at most about the budget of pieces, and every move's end within
/// the join tolerance of the joined drawing.
#[test]
fn a_long_program_is_drawn_from_bounded_pieces_within_tolerance() {
    // A finishing raster of short moves over a wavy surface, with arcs, two tools and rapids.
    let mut text = String::from(
        "%\nG21 G90 G17\n(T1 flat-6: flat D6 mm - roughing-x with flat-6)\nT1 M6\nG0 X0 Y0 Z5\n",
    );
    let mut points = Vec::new();
    for row in 0..40 {
        let y = f64::from(row) * 0.5;
        text.push_str(&format!("G0 X0 Y{y:.3}\nG1 Z0 F500\n"));
        for k in 1..=200 {
            let x = f64::from(k) * 0.25;
            let z = (x * 0.3).sin() * 0.2;
            text.push_str(&format!("G1 X{x:.4} Y{:.4} Z{z:.4}\n", y + 0.02 * (x * 0.7).sin()));
            points.push([x, y + 0.02 * (x * 0.7).sin()]);
        }
        text.push_str("G0 Z5\n");
    }
    text.push_str("(T2 ball-6: ball D6 mm - finishing-x with ball-6)\nT2 M6\nG0 X10 Y10\nG1 Z0\nG2 X20 Y10 I5 J0\nM30\n");
    let exact = gcode::parse(&text);
    let mut parser = gcode::Parser::with_max_segs(500);
    for line in text.lines() {
        parser.line(line);
    }
    let joined = parser.finish();
    assert_eq!(joined.ops, exact.ops);
    assert_eq!(joined.blocks, exact.blocks);
    assert_eq!(joined.feed_extent, exact.feed_extent);
    assert_eq!(joined.warnings, exact.warnings);
    assert!(exact.segs.len() > 8000, "{}", exact.segs.len());
    assert!(joined.segs.len() <= 1000, "{} pieces kept", joined.segs.len());
    // Each original end point lies near the joined pieces of its operation.
    let extent = 50f64.hypot(20.0);
    let bound = extent / 4000.0 * 64.0; // the tolerance after at most 6 doublings, summed
    let dist = |p: [f64; 2], s: &gcode::Seg| {
        let (a, b) = (s.a.map(f64::from), s.b.map(f64::from));
        let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
        let l2 = dx * dx + dy * dy;
        let t = if l2 > 0.0 { (((p[0] - a[0]) * dx + (p[1] - a[1]) * dy) / l2).clamp(0.0, 1.0) } else { 0.0 };
        (p[0] - a[0] - t * dx).hypot(p[1] - a[1] - t * dy)
    };
    for p in points.iter().step_by(7) {
        let d = joined.segs.iter().filter(|s| !s.rapid).map(|s| dist(*p, s)).fold(f64::INFINITY, f64::min);
        assert!(d <= bound, "({}, {}) is {d} mm off the drawing (bound {bound})", p[0], p[1]);
    }
    // Streaming from a reader gives what parsing the text gives.
    let streamed = gcode::parse_reader(std::io::BufReader::new(text.as_bytes())).expect("read");
    assert_eq!(streamed.segs, exact.segs);
    assert_eq!(streamed.ops, exact.ops);
}

/// Telemetry read with a small sample budget: the statistics are those of every row (as the whole
/// parse gives them), the sample is every 2^k-th row, and no more than the budget.
#[test]
fn telemetry_statistics_cover_every_row_and_the_sample_is_bounded() {
    let mut csv = String::from("time_s,feed_mm_min,spindle_rpm,torque_from_current_nm,power_w,active\n");
    for i in 0..1000 {
        let t = f64::from(i) * 0.05;
        let feed = 100.0 + f64::from(i % 37);
        let active = if i % 3 == 0 { "torque" } else { "" };
        csv.push_str(&format!(
            "{t},{feed},{},{},{},{active}\n",
            1500 + i % 11,
            f64::from(i % 7) * 0.1,
            i % 13
        ));
    }
    let whole = charts::parse_telemetry(&csv).expect("whole");
    let small = charts::read_telemetry(csv.as_bytes(), 64).expect("sampled");
    assert_eq!(small.rows, 1000);
    assert_eq!(whole.rows, 1000);
    assert!(small.time_s.len() < 64 && small.time_s.len() >= 32, "{}", small.time_s.len());
    // Every 2^k-th row.
    let stride = whole.time_s.len().div_ceil(small.time_s.len()).next_power_of_two();
    let expected: Vec<f64> = whole.time_s.iter().copied().step_by(stride).collect();
    assert_eq!(small.time_s, expected);
    for (a, b) in [
        (small.feed_stat, whole.feed_stat),
        (small.rpm_stat, whole.rpm_stat),
        (small.torque_current_stat, whole.torque_current_stat),
        (small.power_stat, whole.power_stat),
    ] {
        assert!((a.mean() - b.mean()).abs() < 1e-9 && a.max() == b.max());
    }
    // The exact figures from every row.
    let feeds: Vec<f64> = (0..1000).map(|i| 100.0 + f64::from(i % 37)).collect();
    let mean = feeds.iter().sum::<f64>() / 1000.0;
    assert!((small.feed_stat.mean() - mean).abs() < 1e-9);
    assert_eq!(small.feed_stat.max(), 136.0);
    assert_eq!(small.time_span, Some((0.0, 999.0 * 0.05)));
    assert_eq!(small.active, vec![("torque".to_string(), 334)]);
}

#[test]
fn the_deviation_leaves_out_cells_the_scanner_never_saw() {
    // The coverage map's assumed band (never seen, a height from around it): its deviation is
    // left out of the picture, and the caption says how many cells.
    let arts = full_artifacts();
    let out = render_ok(&job("assumed", "succeeded", &arts), &arts);
    let cov = coverage_map();
    let dev = deviation_map();
    let want = cov.data().iter().zip(dev.data()).filter(|(c, d)| **c == 0.25 && d.is_finite()).count();
    assert!(want > 0);
    let text = format!("Left out (grey): {} cells the scanner never saw", fmt_count(want));
    assert!(out.html.contains(&text), "{text} not in the report");
    // Without the coverage map nothing is left out.
    let mut bare = full_artifacts();
    bare.remove("coverage_map");
    let out = render_ok(&job("bare", "succeeded", &bare), &bare);
    assert!(!out.html.contains("Left out (grey)"));
}

#[test]
fn a_face_the_scan_hardly_saw_is_flagged_in_the_report() {
    let mut arts = full_artifacts();
    let warning = "face A=90: 3.3 % of its map was measured and 96.7 % assumed (cells no point showed, set at the height around them): the scan hardly saw the part from this side";
    arts.insert(
        "reconstruct_report".into(),
        serde_json::to_vec(&serde_json::json!({"faces": [{"face": "A=90", "warning": warning}]}))
            .expect("json"),
    );
    let j = job("housing", "succeeded", &arts);
    let out = render_ok(&j, &arts);
    assert!(
        out.html.contains(r#"<p class="missing">face A=90: 3.3 % of its map was measured"#),
        "{}",
        out.html
    );
    // Without the warning, nothing is flagged.
    arts.insert("reconstruct_report".into(), br#"{"faces": [{"face": "+Z"}]}"#.to_vec());
    let j = job("housing", "succeeded", &arts);
    assert!(!render_ok(&j, &arts).html.contains("hardly saw"));
}

#[test]
fn the_stages_findings_come_first_where_the_part_differs_and_the_rest_folded() {
    let arts = BTreeMap::new();
    let mut j = job("findings", "succeeded", &arts);
    let html = render_ok(&j, &arts).html;
    assert!(!has_section(&html, "findings"), "no diagnostics, no section");
    j["diagnostics"] = json!([
        {"stage": "reconstruct", "code": "face_choice", "message": "faces chosen from the shape: +Z (+98.1 %)"},
        {"stage": "plan", "code": "material_left", "message": "face 1: 5.9 mm² around (0.0, 0.6) mm stay <up to> 3.188 mm"},
        {"stage": "execute", "code": "machine", "message": "feed clamped at line 12 & on"},
    ]);
    let html = render_ok(&j, &arts).html;
    let section = html.split(r#"<section id="findings">"#).nth(1).expect("a findings section");
    let section = section.split("</section>").next().unwrap_or_default();
    // The two that say the part differs, escaped, before the fold; the choice inside it.
    let (attention, folded) = section.split_once("<details>").expect("the notes are folded");
    assert!(attention.contains("2 finding(s)"), "{attention}");
    assert!(
        attention.contains("<code>material_left</code>") && attention.contains("&lt;up to&gt;"),
        "{attention}"
    );
    assert!(
        attention.contains("<code>machine</code>") && attention.contains("line 12 &amp; on"),
        "{attention}"
    );
    assert!(!attention.contains("face_choice"), "{attention}");
    assert!(folded.contains("<code>face_choice</code>") && folded.contains("1 further note(s)"), "{folded}");
    // The section follows the summary.
    let (summary, findings) =
        (html.find(r#"<section id="summary">"#), html.find(r#"<section id="findings">"#));
    assert!(summary < findings, "{summary:?} {findings:?}");
}
