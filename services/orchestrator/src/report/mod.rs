//! The job report: one self-contained HTML page (inline CSS, pictures as `data:` URIs, no script,
//! no external request) showing what a job did, with pictures where a person would rather look
//! than read; and the same pictures as files for `depthmill demo`'s output folder.
//!
//! [`render`] takes the job as `GET /v1/jobs/{id}` returns it and the bytes of its artifacts by
//! kind. Every section finds its own data and, when an artifact is missing or unreadable, says
//! so and why (the job started later, failed earlier, the stage has not run, the bytes were not
//! passed, the file did not decode) instead of failing the page. Only a job that is not a JSON
//! object is an error.
//!
//! # Sections and their data
//! - Header and summary: `job.name/id/status/stage/error`, `job.metrics` (`coverage_pct`,
//!   `max_gouge_mm`, `max_leftover_mm`, `rms_deviation_mm`, `cycle_time_s`,
//!   `cycle_time_no_adaptive_s`), `machine_report` (JSON: `deviation.mean_leftover_mm`,
//!   `other_policy`, `cycle_time_other_s`) and `plan_report` (JSON: `estimated_time_s`).
//! - Parameters: `job.spec` flattened per section, `job.stage_timings_s` as bars, `job.attempts`,
//!   `job.artifacts`.
//! - Point cloud: `point_cloud` (XYZ/PLY; else `mesh`, its vertices), read with the
//!   reconstruction service's readers, splatted from above and from the front ([`cloud`]).
//! - Depth and coverage maps per face: `depth_map`, `coverage_map`, then `depth_map@1`, ... (the
//!   orchestrator's names for further faces): 16-bit PNG with depthmill metadata (or `.npy`), read
//!   with `depthmill_geometry::read_png_from`; coverage classes 1 / 0.5 / 0 / no data; stats from
//!   the map itself and, if stored, a `reconstruct_report` JSON.
//! - Toolpaths per face: `gcode` parsed for drawing ([`gcode`]), over the face's depth map (or the
//!   final stock, or nothing) in work coordinates = the map's frame.
//! - Machined part: `final_stock` (16-bit PNG height map), Lambert-lit; else the CAM's
//!   `toolpath_preview`.
//! - Deviation: `deviation_map` (8-bit PNG, stock − target, Z range ±max) on a diverging scale.
//! - Telemetry: `telemetry_plot` (SVG, embedded as an image so nothing in it runs), else the
//!   `telemetry` CSV drawn with `depthmill_common::plot`.
//! - Cycle time: `job.metrics` (or `machine_report`) with and without adaptation.
//!
//! # Layout
//! - [`raster`]: RGB image, PNG, base64, colour maps and legends, lines, [`raster::View`].
//! - [`maps`]: height-map decoding and pictures; [`cloud`]: point-cloud views;
//!   [`gcode`]: G-code for drawing; [`charts`]: SVG bars and the telemetry chart; `html`: escaping
//!   and page pieces.

pub mod charts;
pub mod cloud;
pub mod gcode;
mod html;
pub mod maps;
pub mod raster;
#[cfg(test)]
mod tests;

use std::collections::BTreeMap;
use std::fmt::Write as _;

use depthmill_geometry::{HeightMap, HeightMapMeta, ImageMapping};
use serde_json::Value;

use html::{esc, figure_svg, kv_table, missing, section, table};
use raster::{ColorMap, RgbImage, View, data_uri, fmt_num};

pub use gcode::{OpKind, Program};

/// What the report is made from.
pub struct ReportInput<'a> {
    /// The job as `GET /v1/jobs/{id}` returns it: id, name, status, spec (the submitted job JSON),
    /// stage_timings_s, metrics, artifacts (kind -> {sha256, size, media_type}), attempts, ...
    pub job: &'a Value,
    /// Artifact kind (the keys of `job.artifacts`) -> its bytes.
    pub artifacts: &'a BTreeMap<String, Vec<u8>>,
}

/// The rendered report.
pub struct ReportOutput {
    /// One self-contained HTML page: images embedded as `data:` URIs (PNG or SVG), inline CSS, no
    /// scripts, no external requests.
    pub html: String,
    /// The same pictures as files (`depth_map.png`, `telemetry.svg`, ...), for an output folder.
    pub files: Vec<(String, Vec<u8>)>,
}

/// Input the report cannot be made from at all. Missing or unreadable artifacts are not errors:
/// their sections say what is missing and why.
#[derive(Debug, thiserror::Error)]
pub enum ReportError {
    #[error("the job is not a JSON object (got {found})")]
    JobNotAnObject { found: &'static str },
    #[error("encoding a picture as PNG failed")]
    Png(#[source] png::EncodingError),
}

/// Colours of the toolpath kinds (RGB) and of rapids.
pub const ROUGHING_RGB: [u8; 3] = [235, 110, 0];
pub const FINISHING_RGB: [u8; 3] = [0, 90, 230];
pub const OTHER_RGB: [u8; 3] = [150, 40, 170];
pub const RAPID_RGB: [u8; 3] = [90, 90, 90];

const STAGES: [&str; 5] = ["scan", "reconstruct", "plan", "execute", "report"];

fn stage_index(s: &str) -> Option<usize> {
    STAGES.iter().position(|x| *x == s)
}

fn json_kind(v: &Value) -> &'static str {
    match v {
        Value::Null => "null",
        Value::Bool(_) => "a boolean",
        Value::Number(_) => "a number",
        Value::String(_) => "a string",
        Value::Array(_) => "an array",
        Value::Object(_) => "an object",
    }
}

/// Renders the report of `input.job` (see the module documentation).
pub fn render(input: &ReportInput<'_>) -> Result<ReportOutput, ReportError> {
    if !input.job.is_object() {
        return Err(ReportError::JobNotAnObject { found: json_kind(input.job) });
    }
    let mut ctx = Ctx::new(input);
    let mut body = String::new();
    body.push_str(&ctx.header());
    body.push_str(&ctx.summary());
    body.push_str(&ctx.parameters());
    body.push_str(&ctx.point_cloud()?);
    body.push_str(&ctx.maps()?);
    body.push_str(&ctx.toolpaths()?);
    body.push_str(&ctx.machined()?);
    body.push_str(&ctx.deviation()?);
    body.push_str(&ctx.telemetry());
    body.push_str(&ctx.cycle_time());
    let title = format!("depthmill report: {}", ctx.name());
    let html = format!(
        "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\"><meta name=\"viewport\" content=\"width=device-width, initial-scale=1\"><title>{}</title><style>{}</style></head><body><main>{body}<footer>Generated by depthmill from job {}. Self-contained page: every picture is embedded.</footer></main></body></html>\n",
        esc(&title),
        html::CSS,
        esc(ctx.str_at("id").unwrap_or("?")),
    );
    Ok(ReportOutput { html, files: ctx.files })
}

struct Ctx<'a> {
    job: &'a Value,
    artifacts: &'a BTreeMap<String, Vec<u8>>,
    files: Vec<(String, Vec<u8>)>,
    fallback: Option<ImageMapping>,
    machine_report: Option<Value>,
    plan_report: Option<Value>,
    /// Decoded depth maps by key, kept for the toolpath overlays.
    depth_maps: BTreeMap<String, HeightMap>,
}

impl<'a> Ctx<'a> {
    fn new(input: &ReportInput<'a>) -> Self {
        let json = |k: &str| input.artifacts.get(k).and_then(|b| serde_json::from_slice::<Value>(b).ok());
        let inp = &input.job["spec"]["input"];
        let fallback = inp["pixel_mm"].as_f64().filter(|p| p.is_finite() && *p > 0.0).map(|p| ImageMapping {
            pixel_mm: p,
            z_min_mm: inp["z_min_mm"].as_f64(),
            z_max_mm: inp["z_max_mm"].as_f64(),
        });
        Ctx {
            job: input.job,
            artifacts: input.artifacts,
            files: Vec::new(),
            fallback,
            machine_report: json("machine_report"),
            plan_report: json("plan_report"),
            depth_maps: BTreeMap::new(),
        }
    }

    fn str_at(&self, k: &str) -> Option<&'a str> {
        self.job.get(k).and_then(Value::as_str)
    }

    fn name(&self) -> String {
        match self.str_at("name").filter(|s| !s.trim().is_empty()) {
            Some(n) => n.to_string(),
            None => format!("job {}", self.str_at("id").unwrap_or("?")),
        }
    }

    fn metric(&self, k: &str) -> Option<f64> {
        self.job["metrics"][k].as_f64().filter(|v| v.is_finite())
    }

    fn first_stage(&self) -> Option<&'static str> {
        match self.job["spec"]["input"]["kind"].as_str()? {
            "mesh" => Some("scan"),
            "point_cloud" => Some("reconstruct"),
            "depth_map" => Some("plan"),
            "gcode" => Some("execute"),
            _ => None,
        }
    }

    /// Why artifact `key` is not there (plain text).
    fn why_missing(&self, key: &str) -> String {
        let base = key.split('@').next().unwrap_or(key);
        if let Some(r) = self.job["artifacts"].get(key) {
            let sha = r["sha256"].as_str().unwrap_or("?");
            return format!(
                "Not shown: the job has a {key} artifact (sha256 {}…) but its bytes were not passed to the report.",
                sha.get(..12).unwrap_or(sha)
            );
        }
        let stage = match base {
            "point_cloud" | "mesh" => "scan",
            "depth_map" | "coverage_map" | "roughing_map" | "reconstruct_report" => "reconstruct",
            "gcode" | "toolpath_preview" | "plan_report" | "leftover_map" => "plan",
            _ => "execute",
        };
        let input_kind = self.job["spec"]["input"]["kind"].as_str();
        if input_kind == Some(base) {
            return format!(
                "Not shown: the job's input ({base}) is not among the artifacts given to the report."
            );
        }
        let status = self.str_at("status").unwrap_or("unknown");
        let first = self.first_stage();
        if let (Some(f), Some(si), Some(fi)) = (first, stage_index(stage), first.and_then(stage_index))
            && si < fi
        {
            let kind = self.job["spec"]["input"]["kind"].as_str().unwrap_or("?");
            return format!(
                "Not produced: the job started at the {f} stage (its input is a {kind}), so no {stage} stage ran and there is no {key}."
            );
        }
        let err_stage = self.job["error"]["stage"].as_str();
        match status {
            "failed" => {
                let msg = self.job["error"]["message"].as_str().unwrap_or("");
                let code = self.job["error"]["code"].as_str().unwrap_or("error");
                match err_stage {
                    Some(es) if stage_index(es) <= stage_index(stage) => format!(
                        "Not produced: the job failed in the {es} stage ({code}: {msg}) before the {stage} stage made a {key}."
                    ),
                    _ => format!(
                        "Not produced: the job failed ({code}: {msg}) and the {stage} stage made no {key}."
                    ),
                }
            }
            "cancelled" => {
                format!("Not produced: the job was cancelled before the {stage} stage made a {key}.")
            }
            "queued" | "running" => {
                format!("Not produced yet: the job is {status} and the {stage} stage has not finished.")
            }
            _ if base == "deviation_map" && !self.artifacts.contains_key("depth_map") => {
                "Not produced: the execute stage had no target depth map to compare the machined part with."
                    .into()
            }
            _ => format!("Not produced: the {stage} stage stored no {key} artifact."),
        }
    }

    /// Encodes `img` as PNG, keeps it as file `name` and returns the figure.
    fn picture(
        &mut self,
        name: &str,
        img: &RgbImage,
        alt: &str,
        caption: &str,
    ) -> Result<String, ReportError> {
        let png = img.to_png()?;
        let fig = html::figure_img(&data_uri("image/png", &png), alt, caption, img.width, img.height);
        self.files.push((name.to_string(), png));
        Ok(fig)
    }

    fn decode(&self, key: &str) -> Result<maps::Decoded, String> {
        match self.artifacts.get(key) {
            Some(b) => maps::decode_map(b, self.fallback.as_ref())
                .map_err(|e| format!("Not shown: the {key} artifact could not be read: {e}.")),
            None => Err(self.why_missing(key)),
        }
    }

    // ---------------------------------------------------------------------------------------
    // Header, summary, parameters.

    fn header(&self) -> String {
        let status = self.str_at("status").unwrap_or("unknown");
        let mut s = format!(
            r#"<header><h1>{}</h1><div class="sub">Job <code>{}</code> · <span class="status {}">{}</span>"#,
            esc(&self.name()),
            esc(self.str_at("id").unwrap_or("?")),
            esc(status),
            esc(status)
        );
        if let Some(st) = self.str_at("stage") {
            let _ = write!(s, " · stage {}", esc(st));
        }
        if let Some(p) = self.job["progress"].as_f64() {
            let _ = write!(s, " · {:.0} % done", (p * 100.0).clamp(0.0, 100.0));
        }
        for (k, label) in [("created_at_ms", "created"), ("updated_at_ms", "updated")] {
            if let Some(ms) = self.job[k].as_i64() {
                let _ = write!(s, " · {label} {}", esc(&utc(ms)));
            }
        }
        s.push_str("</div>");
        if let Some(e) = self.job.get("error").filter(|e| e.is_object()) {
            let _ = write!(
                s,
                r#"<p class="error"><strong>Error in the {} stage</strong> ({}): {}</p>"#,
                esc(e["stage"].as_str().unwrap_or("?")),
                esc(e["code"].as_str().unwrap_or("?")),
                esc(e["message"].as_str().unwrap_or(""))
            );
        }
        s.push_str("</header>");
        s
    }

    fn summary(&self) -> String {
        let mr = self.machine_report.as_ref();
        let mr_f = |path: &[&str]| {
            let mut v = mr?;
            for p in path {
                v = v.get(p)?;
            }
            v.as_f64().filter(|x| x.is_finite())
        };
        let mm = |v: Option<f64>| v.map_or("—".to_string(), |v| format!("{v:.3} mm"));
        let secs = |v: Option<f64>| v.map_or("—".to_string(), fmt_duration);
        let adaptive = self.metric("cycle_time_s").or_else(|| mr_f(&["cycle_time_s"]));
        let plain = self.metric("cycle_time_no_adaptive_s").or_else(|| mr_f(&["cycle_time_no_adaptive_s"]));
        let saving = match (adaptive, plain) {
            (Some(a), Some(p)) if p > 0.0 => format!("{:.1} %", (p - a) / p * 100.0),
            _ => "—".into(),
        };
        let rows = vec![
            (
                "Scan coverage".to_string(),
                self.metric("coverage_pct")
                    .map_or("—".into(), |v| format!("{v:.1} % of the part measured")),
            ),
            ("Max gouge (cut too deep)".into(), mm(self.metric("max_gouge_mm"))),
            ("Max leftover (material left)".into(), mm(self.metric("max_leftover_mm"))),
            ("Mean leftover".into(), mm(mr_f(&["deviation", "mean_leftover_mm"]))),
            ("RMS deviation".into(), mm(self.metric("rms_deviation_mm"))),
            ("Cycle time, adaptive".into(), secs(adaptive)),
            ("Cycle time, programmed feeds".into(), secs(plain)),
            ("Saved by the adaptive loop".into(), saving),
            (
                "CAM time estimate".into(),
                secs(
                    self.plan_report
                        .as_ref()
                        .and_then(|p| p["estimated_time_s"].as_f64())
                        .or_else(|| self.job["metrics"]["estimated_time_s"].as_f64()),
                ),
            ),
        ];
        let rows: Vec<(String, String)> = rows.into_iter().map(|(k, v)| (k, esc(&v))).collect();
        section("summary", "Summary", &kv_table(&rows))
    }

    fn parameters(&self) -> String {
        let mut body = String::new();
        let spec = &self.job["spec"];
        if let Some(obj) = spec.as_object() {
            body.push_str(r#"<div class="grid">"#);
            let order = ["input", "scan", "reconstruct", "plan", "execute"];
            let mut keys: Vec<&String> = obj.keys().filter(|k| k.as_str() != "name").collect();
            keys.sort_by_key(|k| order.iter().position(|o| o == k).unwrap_or(order.len()));
            for k in keys {
                let mut rows = Vec::new();
                flatten("", &obj[k.as_str()], &mut rows);
                if rows.is_empty() {
                    rows.push(("(all defaults)".into(), String::new()));
                }
                let rows: Vec<(String, String)> =
                    rows.into_iter().map(|(a, b)| (a, format!("<code>{}</code>", esc(&b)))).collect();
                let _ = write!(body, "<div><h3>{}</h3>{}</div>", esc(k), kv_table(&rows));
            }
            body.push_str("</div>");
            let pretty = serde_json::to_string_pretty(spec).unwrap_or_default();
            let _ = write!(
                body,
                "<details><summary>Job request as JSON</summary><pre>{}</pre></details>",
                esc(&pretty)
            );
        } else {
            body.push_str(&missing("The job has no spec."));
        }
        // Stage timings.
        body.push_str("<h3>Time per stage</h3>");
        let timings = self.job["stage_timings_s"].as_object();
        let mut rows: Vec<(String, f64, &str)> = Vec::new();
        if let Some(t) = timings {
            let mut ks: Vec<&String> = t.keys().collect();
            ks.sort_by_key(|k| stage_index(k).unwrap_or(STAGES.len()));
            for k in ks {
                if let Some(v) = t[k.as_str()].as_f64() {
                    rows.push((k.clone(), v, "#4c78a8"));
                }
            }
        }
        if rows.is_empty() {
            body.push_str(&missing("No stage has finished yet, so there are no timings."));
        } else {
            let total: f64 = rows.iter().map(|r| r.1).sum();
            body.push_str(&figure_svg(
                &charts::hbars(&rows, "s"),
                &format!("Wall time of each completed stage; total {}.", esc(&fmt_duration(total))),
            ));
        }
        // Attempts.
        if let Some(att) = self.job["attempts"].as_array().filter(|a| !a.is_empty()) {
            let rows: Vec<Vec<String>> = att
                .iter()
                .map(|a| {
                    let dur = match (a["started_at_ms"].as_i64(), a["finished_at_ms"].as_i64()) {
                        (Some(s), Some(f)) => fmt_duration((f - s) as f64 / 1000.0),
                        _ => "—".into(),
                    };
                    vec![
                        esc(a["stage"].as_str().unwrap_or("?")),
                        esc(&a["attempt"].as_u64().map_or("?".into(), |n| n.to_string())),
                        esc(a["outcome"].as_str().unwrap_or("?")),
                        esc(&dur),
                        esc(&format!(
                            "{} {}",
                            a["error_code"].as_str().unwrap_or(""),
                            a["error_message"].as_str().unwrap_or("")
                        )),
                    ]
                })
                .collect();
            body.push_str("<details><summary>Stage attempts</summary>");
            body.push_str(&table(&["stage", "attempt", "outcome", "took", "error"], &rows));
            body.push_str("</details>");
        }
        // Artifacts.
        if let Some(arts) = self.job["artifacts"].as_object().filter(|a| !a.is_empty()) {
            let rows: Vec<Vec<String>> = arts
                .iter()
                .map(|(k, a)| {
                    let sha = a["sha256"].as_str().unwrap_or("?");
                    vec![
                        format!("<code>{}</code>", esc(k)),
                        esc(a["media_type"].as_str().unwrap_or("?")),
                        format!(
                            r#"<span class="num">{}</span>"#,
                            esc(&a["size"].as_u64().map_or("?".into(), fmt_bytes))
                        ),
                        format!("<code>{}</code>", esc(sha.get(..16).unwrap_or(sha))),
                    ]
                })
                .collect();
            body.push_str("<details><summary>Artifacts</summary>");
            body.push_str(&table(&["kind", "media type", "size", "sha256"], &rows));
            body.push_str("</details>");
        }
        section("parameters", "Job parameters and timings", &body)
    }

    // ---------------------------------------------------------------------------------------
    // Pictures.

    fn point_cloud(&mut self) -> Result<String, ReportError> {
        let key = if self.artifacts.contains_key("point_cloud") || !self.artifacts.contains_key("mesh") {
            "point_cloud"
        } else {
            "mesh"
        };
        let body = match self.artifacts.get(key) {
            None => missing(&self.why_missing(key)),
            Some(bytes) => match cloud::read_cloud(bytes, key) {
                Err(e) => missing(&format!("Not shown: the {key} artifact could not be read: {e}.")),
                Ok(c) if c.is_empty() => missing(&format!("The {key} artifact holds no points.")),
                Ok(c) => {
                    let (top, side) = cloud::views(&c);
                    let mut s = format!(
                        "<p>{} points{}.</p><div class=\"grid\">",
                        fmt_count(c.len()),
                        if key == "mesh" { " (the mesh's vertices)" } else { "" }
                    );
                    for (v, name, title, axes, colour) in [
                        (top, "point_cloud_top.png", "Top view", ("X", "Y"), "Z (height)"),
                        (side, "point_cloud_side.png", "Front view", ("X", "Z"), "Y (nearer is brighter)"),
                    ] {
                        let Some(v) = v else { continue };
                        let caption = format!(
                            "{title}: {} {}–{} mm across, {} {}–{} mm up; colour = {colour}, {}–{} mm. {} of the points in view.",
                            axes.0,
                            fmt_num(v.h_range.0),
                            fmt_num(v.h_range.1),
                            axes.1,
                            fmt_num(v.v_range.0),
                            fmt_num(v.v_range.1),
                            fmt_num(v.c_range.0),
                            fmt_num(v.c_range.1),
                            fmt_count(v.drawn),
                        );
                        s.push_str(&self.picture(name, &v.image, title, &esc(&caption))?);
                    }
                    s.push_str("</div>");
                    s
                }
            },
        };
        let body = body + &self.scan_summary();
        Ok(section("point-cloud", "Point cloud", &body))
    }

    /// The scan's report (`scan_report`), when the job was scanned: stations, passes, frames,
    /// registration error, rays lost by reason, coverage before and after the rescan.
    fn scan_summary(&self) -> String {
        let Some(r) = self.artifacts.get("scan_report").and_then(|b| serde_json::from_slice::<Value>(b).ok())
        else {
            return String::new();
        };
        let f = |v: &Value, d: usize| v.as_f64().map_or("—".to_string(), |x| format!("{x:.d$}"));
        let cov = |v: &Value| {
            if v.is_object() {
                format!(
                    "{} % ({} holes, {} mm²)",
                    f(&v["covered_pct"], 2),
                    v["holes"],
                    f(&v["hole_area_mm2"], 1)
                )
            } else {
                "—".to_string()
            }
        };
        let d = &r["dropped"];
        let rows: Vec<(String, String)> = vec![
            ("Mode".into(), esc(r["mode"].as_str().unwrap_or("?"))),
            ("Frames / points".into(), format!("{} / {}", r["frames"], r["points"])),
            (
                "Simulated scan time".into(),
                format!(
                    "{} s (the table's wall time {} s)",
                    f(&r["scan_time_s"], 1),
                    f(&r["table_wait_s"], 1)
                ),
            ),
            (
                "Registration error (placed vs true)".into(),
                format!(
                    "RMS {} mm, max {} mm",
                    f(&r["registration_rms_mm"], 4),
                    f(&r["registration_max_mm"], 4)
                ),
            ),
            (
                "Rays without a point".into(),
                format!(
                    "{} out of the window, {} beyond the incidence limit, {} occluded, {} missing the part",
                    d["out_of_window"], d["incidence"], d["occluded"], d["miss"]
                ),
            ),
            ("Coverage after the first scan".into(), cov(&r["coverage_before_rescan"])),
            ("Coverage after the rescan".into(), cov(&r["coverage_after_rescan"])),
        ];
        let stations: Vec<Vec<String>> = r["stations"]
            .as_array()
            .into_iter()
            .flatten()
            .map(|st| {
                let passes = st["passes"].as_array().cloned().unwrap_or_default();
                let frames: u64 = passes.iter().filter_map(|p| p["frames"].as_u64()).sum();
                let points: u64 = passes.iter().filter_map(|p| p["points"].as_u64()).sum();
                vec![
                    format!("{}°", f(&st["table_deg_commanded"], 1)),
                    format!("{}°", f(&st["table_deg_measured"], 4)),
                    if st["rescan"].as_bool() == Some(true) { "rescan".into() } else { "first scan".into() },
                    passes.len().to_string(),
                    frames.to_string(),
                    points.to_string(),
                ]
            })
            .collect();
        let mut s = String::from("<h3>Scan</h3>");
        s.push_str(&kv_table(&rows));
        if !stations.is_empty() {
            s.push_str(&table(&["table angle", "encoder", "kind", "passes", "frames", "points"], &stations));
        }
        s
    }

    /// Suffixes of the faces (`""`, `"@1"`, ...) by the depth/coverage maps present.
    fn face_suffixes(&self) -> Vec<String> {
        let mut n: Vec<u32> = Vec::new();
        let keys =
            self.artifacts.keys().chain(self.job["artifacts"].as_object().into_iter().flat_map(|o| o.keys()));
        for k in keys {
            for base in ["depth_map", "coverage_map"] {
                if let Some(rest) = k.strip_prefix(base) {
                    if rest.is_empty() {
                        n.push(0);
                    } else if let Some(i) = rest.strip_prefix('@').and_then(|i| i.parse().ok()) {
                        n.push(i);
                    }
                }
            }
        }
        n.push(0);
        n.sort_unstable();
        n.dedup();
        n.into_iter().map(|i| if i == 0 { String::new() } else { format!("@{i}") }).collect()
    }

    fn maps(&mut self) -> Result<String, ReportError> {
        let mut body = String::new();
        let faces = self.face_suffixes();
        for (fi, suffix) in faces.iter().enumerate() {
            let dkey = format!("depth_map{suffix}");
            let ckey = format!("coverage_map{suffix}");
            let label = format!("Face {}", fi + 1);
            let mut s = String::from(r#"<div class="grid">"#);
            let mut face_name = String::new();
            match self.decode(&dkey) {
                Err(e) => s.push_str(&format!("<div>{}</div>", missing(&e))),
                Ok(d) => {
                    face_name = format!(" ({})", d.map.face());
                    s.push_str(&self.depth_figure(&d, &dkey, &label)?);
                    self.depth_maps.insert(dkey.clone(), d.map);
                }
            }
            match self.decode(&ckey) {
                Err(e) => s.push_str(&format!("<div>{}</div>", missing(&e))),
                Ok(d) => s.push_str(&self.coverage_figure(&d.map, &ckey, &label, fi)?),
            }
            s.push_str("</div>");
            if faces.len() > 1 {
                let _ = write!(body, "<h3>{}{}</h3>", esc(&label), esc(&face_name));
            }
            body.push_str(&s);
        }
        Ok(section("depth-map", "Depth map and scan coverage", &body))
    }

    fn depth_figure(&mut self, d: &maps::Decoded, key: &str, label: &str) -> Result<String, ReportError> {
        let map = &d.map;
        let Some(view) = maps::map_view(map) else {
            return Ok(missing(&format!("The {key} has an empty extent.")));
        };
        let Some((lo, hi)) = maps::robust_range(map) else {
            return Ok(missing(&format!("The {key} has no cell with data.")));
        };
        let img = maps::depth_image(map, &view, lo, hi);
        let m = map.meta();
        let legend = ColorMap::new(raster::VIRIDIS).legend_svg(
            &format!("lg-{}", key.replace('@', "-")),
            lo,
            hi,
            "height Z [mm]",
            "low",
            "high",
        );
        let caption = format!(
            "{label} depth map, {}×{} cells of {} mm = {}×{} mm, origin ({}, {}) mm, view {}; {} of {} cells hold data; image Z range {}–{} mm.{}",
            m.width,
            m.height,
            fmt_num(m.pixel_mm),
            fmt_num(m.width_mm()),
            fmt_num(m.height_mm()),
            fmt_num(m.origin_x_mm),
            fmt_num(m.origin_y_mm),
            m.face,
            fmt_count(map.valid_count()),
            fmt_count(map.data().len()),
            fmt_num(m.z_min_mm),
            fmt_num(m.z_max_mm),
            d.note.as_ref().map(|n| format!(" Note: {n}.")).unwrap_or_default()
        );
        let fig =
            self.picture(&file_name(key, "png"), &img, &format!("{label} depth map"), &esc(&caption))?;
        Ok(format!(
            "<div>{fig}{}</div>",
            figure_svg(&legend, "Colour scale (0.5–99.5 % of the heights); grey: no data.")
        ))
    }

    fn coverage_figure(
        &mut self,
        map: &HeightMap,
        key: &str,
        label: &str,
        face: usize,
    ) -> Result<String, ReportError> {
        let Some(view) = maps::map_view(map) else {
            return Ok(missing(&format!("The {key} has an empty extent.")));
        };
        let img = maps::coverage_image(map, &view);
        let counts = maps::coverage_counts(map);
        let footprint = counts[0] + counts[1] + counts[2];
        let pct = |n: usize| if footprint > 0 { n as f64 / footprint as f64 * 100.0 } else { 0.0 };
        let area = |n: usize| n as f64 * map.pixel_mm() * map.pixel_mm();
        let mut legend = String::from("<p>");
        for (k, c) in [
            maps::CoverageClass::Measured,
            maps::CoverageClass::Filled,
            maps::CoverageClass::Hole,
            maps::CoverageClass::Outside,
        ]
        .into_iter()
        .enumerate()
        {
            let col = c.color();
            let share = if k < 3 { format!(" {:.1} %", pct(counts[k])) } else { String::new() };
            let _ = write!(
                legend,
                r#"<span class="swatch" style="background:rgb({},{},{})"></span>{}{}"#,
                col[0],
                col[1],
                col[2],
                esc(c.label()),
                esc(&share)
            );
        }
        legend.push_str("</p>");
        let mut rows = vec![
            (
                "Footprint".to_string(),
                format!("{} cells, {} mm²", fmt_count(footprint), fmt_num(area(footprint))),
            ),
            ("Measured".into(), format!("{} cells ({:.1} %)", fmt_count(counts[0]), pct(counts[0]))),
            (
                "Filled from neighbours".into(),
                format!("{} cells ({:.1} %)", fmt_count(counts[1]), pct(counts[1])),
            ),
            (
                "Holes left".into(),
                format!("{} cells, {} mm²", fmt_count(counts[2]), fmt_num(area(counts[2]))),
            ),
        ];
        if face == 0
            && let Some(c) = self.metric("coverage_pct")
        {
            rows.push(("Coverage (job metric)".into(), format!("{c:.2} %")));
        }
        // The reconstruction's own report, when the job stored it.
        let rep = ["reconstruct_report", "reconstruction_report"]
            .iter()
            .find_map(|k| self.artifacts.get(*k))
            .and_then(|b| serde_json::from_slice::<Value>(b).ok());
        if let Some(cov) = rep.as_ref().map(|r| &r["faces"][face]["coverage"]).filter(|c| c.is_object()) {
            if let Some(h) = cov["holes"].as_u64() {
                rows.push(("Holes in the raw scan".into(), h.to_string()));
            }
            if let Some(h) = cov["unfilled_holes"].as_u64() {
                rows.push(("Holes left after filling".into(), h.to_string()));
            }
            let big = &cov["largest_unfilled_hole"];
            if let (Some(a), Some(x), Some(y)) =
                (big["area_mm2"].as_f64(), big["center_x_mm"].as_f64(), big["center_y_mm"].as_f64())
            {
                rows.push((
                    "Largest hole left".into(),
                    format!("{} mm² at ({}, {}) mm", fmt_num(a), fmt_num(x), fmt_num(y)),
                ));
            }
        }
        let rows: Vec<(String, String)> = rows.into_iter().map(|(k, v)| (k, esc(&v))).collect();
        let caption = format!(
            "{label} coverage map: what the scan measured, what was filled from neighbours, and the holes a rescan should cover."
        );
        let fig =
            self.picture(&file_name(key, "png"), &img, &format!("{label} coverage map"), &esc(&caption))?;
        Ok(format!("<div>{fig}{legend}{}</div>", kv_table(&rows)))
    }

    fn toolpaths(&mut self) -> Result<String, ReportError> {
        let Some(bytes) = self.artifacts.get("gcode") else {
            return Ok(section("toolpaths", "Toolpaths", &missing(&self.why_missing("gcode"))));
        };
        let program = match std::str::from_utf8(bytes) {
            Ok(t) => gcode::parse(t),
            Err(e) => {
                let e = format!("Not shown: the gcode artifact is not UTF-8 text: {e}.");
                return Ok(section("toolpaths", "Toolpaths", &missing(&e)));
            }
        };
        let mut body = String::new();
        let _ = write!(
            body,
            r#"<p>{} blocks, {} operations on {} face(s). <span class="swatch" style="background:rgb({},{},{})"></span>roughing<span class="swatch" style="background:rgb({},{},{})"></span>finishing<span class="swatch" style="background:rgb({},{},{})"></span>other feed moves<span class="swatch" style="background:rgb({},{},{})"></span>rapids (thin)</p>"#,
            fmt_count(program.blocks),
            program.ops.len(),
            program.faces.len(),
            ROUGHING_RGB[0],
            ROUGHING_RGB[1],
            ROUGHING_RGB[2],
            FINISHING_RGB[0],
            FINISHING_RGB[1],
            FINISHING_RGB[2],
            OTHER_RGB[0],
            OTHER_RGB[1],
            OTHER_RGB[2],
            RAPID_RGB[0],
            RAPID_RGB[1],
            RAPID_RGB[2],
        );
        let final_stock = if self.depth_maps.is_empty() {
            self.artifacts.get("final_stock").and_then(|b| maps::decode_map(b, None).ok()).map(|d| d.map)
        } else {
            None
        };
        for face in 0..program.faces.len() {
            let key = if face == 0 { "depth_map".to_string() } else { format!("depth_map@{face}") };
            let (base, base_name) = match self.depth_maps.get(&key) {
                Some(m) => (Some(m), format!("the {key}")),
                None if face == 0 && final_stock.is_some() => {
                    (final_stock.as_ref(), "the final stock".into())
                }
                None => (None, "no map (none was available)".into()),
            };
            let Some(img) = toolpath_image(base, &program, face) else {
                body.push_str(&missing(&format!("Face {}: no moves to draw.", face + 1)));
                continue;
            };
            let a = program
                .faces
                .get(face)
                .copied()
                .flatten()
                .map(|a| format!(" at A {} deg", fmt_num(a)))
                .unwrap_or_default();
            let caption = format!(
                "Face {}{a}: toolpaths over {base_name} in work coordinates (X right, Y up); roughing orange, finishing blue, rapids thin grey.",
                face + 1
            );
            let name = if face == 0 {
                "toolpaths.png".to_string()
            } else {
                format!("toolpaths_face{}.png", face + 1)
            };
            body.push_str(&self.picture(
                &name,
                &img,
                &format!("toolpaths of face {}", face + 1),
                &esc(&caption),
            )?);
        }
        let rows: Vec<Vec<String>> = program
            .ops
            .iter()
            .map(|o| {
                vec![
                    (o.face + 1).to_string(),
                    esc(o.kind.label()),
                    esc(&o.label),
                    format!(r#"<span class="num">{}</span>"#, fmt_num(o.feed_mm / 1000.0)),
                    format!(r#"<span class="num">{}</span>"#, fmt_num(o.rapid_mm / 1000.0)),
                    format!(r#"<span class="num">{}</span>"#, fmt_count(o.moves)),
                ]
            })
            .collect();
        body.push_str(&table(
            &["face", "kind", "tool and strategy", "feed path [m]", "rapids [m]", "moves"],
            &rows,
        ));
        if !program.warnings.is_empty() {
            let w: Vec<String> = program.warnings.iter().map(|w| esc(w)).collect();
            let _ = write!(
                body,
                "<details><summary>Lines the drawing skipped</summary><pre>{}</pre></details>",
                w.join("\n")
            );
        }
        Ok(section("toolpaths", "Toolpaths", &body))
    }

    fn machined(&mut self) -> Result<String, ReportError> {
        let mut all = String::new();
        let faces = self.face_suffixes();
        for (fi, suffix) in faces.iter().enumerate() {
            let stock_key = format!("final_stock{suffix}");
            if fi > 0 && !self.artifacts.contains_key(&stock_key) {
                continue;
            }
            let (key, note) = if self.artifacts.contains_key(&stock_key)
                || !self.artifacts.contains_key("toolpath_preview")
            {
                (stock_key, "")
            } else {
                (
                    "toolpath_preview".to_string(),
                    " This is the CAM's predicted surface: the machine stage has not produced a final stock.",
                )
            };
            let face = if faces.len() > 1 { format!(" Face {}.", fi + 1) } else { String::new() };
            let body = match self.decode(&key) {
                Err(e) => missing(&e),
                Ok(d) => {
                    let map = &d.map;
                    match (maps::map_view(map), maps::robust_range(map)) {
                        (Some(view), Some((lo, hi))) => {
                            let img = maps::shaded_image(map, &view, lo, hi);
                            let m = map.meta();
                            let caption = format!(
                                "Simulated machined part, lit from the top left: {}×{} mm, cells of {} mm, surface Z {}–{} mm.{note}{face}",
                                fmt_num(m.width_mm()),
                                fmt_num(m.height_mm()),
                                fmt_num(m.pixel_mm),
                                fmt_num(lo),
                                fmt_num(hi)
                            );
                            let file = format!("{}.png", key.replace('@', "_face"));
                            self.picture(&file, &img, "machined part", &esc(&caption))?
                        }
                        _ => missing(&format!("The {key} has no cell with data.")),
                    }
                }
            };
            all.push_str(&body);
        }
        Ok(section("final-stock", "Machined part", &all))
    }

    fn deviation(&mut self) -> Result<String, ReportError> {
        let mut body = String::new();
        let faces = self.face_suffixes();
        for (fi, suffix) in faces.iter().enumerate() {
            let dkey = format!("deviation_map{suffix}");
            if fi > 0 && !self.artifacts.contains_key(&dkey) {
                continue;
            }
            match self.decode(&dkey) {
                Err(e) => body.push_str(&missing(&e)),
                Ok(d) => {
                    let map = &d.map;
                    match (maps::map_view(map), maps::deviation_range(map)) {
                        (Some(view), Some((range, lo, hi))) => {
                            let img = maps::deviation_image(map, &view, range);
                            let legend = ColorMap::new(raster::RED_WHITE_BLUE).legend_svg(
                                &format!("lg-deviation{fi}"),
                                -range,
                                range,
                                "stock − target [mm]",
                                "gouge (too deep)",
                                "leftover (material left)",
                            );
                            let caption = format!(
                                "Machined part minus the target, per cell: red where the part was cut too deep, blue where material is left, white on target. Map values {}–{} mm; the scale saturates at ±{} mm (99.5 % of |deviation|).",
                                fmt_num(lo),
                                fmt_num(hi),
                                fmt_num(range)
                            );
                            let caption =
                                if faces.len() > 1 { format!("Face {}. {caption}", fi + 1) } else { caption };
                            let file = format!("{}.png", dkey.replace('@', "_face"));
                            body.push_str(&self.picture(&file, &img, "deviation map", &esc(&caption))?);
                            body.push_str(&figure_svg(&legend, "Colour scale of the deviation."));
                        }
                        _ => body.push_str(&missing("The deviation map has no cell with data.")),
                    }
                }
            }
        }
        let mr = self.machine_report.as_ref();
        let dev = |k: &str| mr.and_then(|m| m["deviation"][k].as_f64());
        let rows: Vec<(String, String)> = [
            ("Max gouge", self.metric("max_gouge_mm").or_else(|| dev("max_gouge_mm"))),
            ("Max leftover", self.metric("max_leftover_mm").or_else(|| dev("max_leftover_mm"))),
            ("Mean leftover", dev("mean_leftover_mm")),
            ("RMS deviation", self.metric("rms_deviation_mm").or_else(|| dev("rms_deviation_mm"))),
        ]
        .into_iter()
        .map(|(k, v)| (k.to_string(), esc(&v.map_or("—".into(), |v| format!("{v:.4} mm")))))
        .collect();
        body.push_str(&kv_table(&rows));
        body.push_str(&self.against_part()?);
        body.push_str(&self.against_preview()?);
        Ok(section("deviation", "Deviation from the original part", &body))
    }

    /// The machined part against the original part itself, when the job started from its mesh
    /// (a simulated scan): the mesh's top surface rasterised on the final stock's grid (exact
    /// z-buffer at cell centres). Only when the maps are in the mesh's own frame: first face `+Z`
    /// without a moved origin, and no `filters.transform`.
    fn against_part(&mut self) -> Result<String, ReportError> {
        let rec = &self.job["spec"]["reconstruct"];
        let same_frame = rec["filters"]["transform"].is_null()
            && match rec["faces"].as_array() {
                None => true,
                Some(f) => f.first().is_none_or(|f0| {
                    f0["view"].as_str().is_none_or(|v| v == "+Z")
                        && f0["origin"].is_null()
                        && f0["a_deg"].is_null()
                        && f0["normal"].is_null()
                }),
            };
        let Some(bytes) = self.artifacts.get("mesh").filter(|_| same_frame) else {
            return Ok(String::new());
        };
        let Ok(stock) = self.decode("final_stock") else { return Ok(String::new()) };
        let limits = depthmill_reconstruction::domain::io::ReadLimits::default();
        let mesh = match depthmill_reconstruction::domain::io::read_any_from(
            std::io::Cursor::new(bytes),
            "mesh",
            Some(bytes.len() as u64),
            &limits,
        ) {
            Ok((depthmill_reconstruction::domain::io::Geometry::Mesh(m), _)) => m,
            Ok(_) => return Ok(String::new()),
            Err(e) => {
                return Ok(missing(&format!("The original part could not be read to compare with: {e}.")));
            }
        };
        let meta = *stock.map.meta();
        let Ok((part, _)) =
            depthmill_reconstruction::domain::mesh_raster::rasterize_mesh_with_stats(&mesh, &meta)
        else {
            return Ok(String::new());
        };
        let mut data = vec![f32::NAN; part.data().len()];
        let (mut gouge, mut left, mut sum_left, mut sq, mut n) = (0.0f64, 0.0f64, 0.0f64, 0.0f64, 0usize);
        for (i, (p, z)) in part.data().iter().zip(stock.map.data()).enumerate() {
            if !(p.is_finite() && z.is_finite()) {
                continue;
            }
            let d = f64::from(*z) - f64::from(*p);
            data[i] = d as f32;
            gouge = gouge.max(-d);
            left = left.max(d);
            sum_left += d.max(0.0);
            sq += d * d;
            n += 1;
        }
        if n == 0 {
            return Ok(String::new());
        }
        let range = gouge.max(left).max(0.005);
        let Ok(map) = HeightMap::new(HeightMapMeta { z_min_mm: -range, z_max_mm: range, ..meta }, data)
        else {
            return Ok(String::new());
        };
        let mut body = String::from("<h3>Against the original part</h3>");
        if let (Some(view), Some((r, _, _))) = (maps::map_view(&map), maps::deviation_range(&map)) {
            let img = maps::deviation_image(&map, &view, r);
            let caption = format!(
                "Machined part minus the original part (the input mesh's top surface at each cell): the whole chain, scan to mill. Cells on vertical walls read large either way (a wall a fraction of a cell off is a full step in Z); holes the tools cannot enter show as leftover. Scale ±{} mm.",
                fmt_num(r)
            );
            body.push_str(&self.picture(
                "deviation_from_part.png",
                &img,
                "deviation from the part",
                &esc(&caption),
            )?);
        }
        let rows = vec![
            ("Max gouge".to_string(), format!("{gouge:.4} mm")),
            ("Max leftover".to_string(), format!("{left:.4} mm")),
            ("Mean leftover".to_string(), format!("{:.4} mm", sum_left / n as f64)),
            ("RMS".to_string(), format!("{:.4} mm over {} cells", (sq / n as f64).sqrt(), n)),
        ];
        body.push_str(&kv_table(&rows));
        Ok(body)
    }

    /// The machined part against the CAM's preview (`toolpath_preview`: the surface the program
    /// leaves, the part opened by the tools plus scallops). Leftover the tools cannot reach shows
    /// in the deviation from the part but not here; what shows here is the machine's doing (steps,
    /// the adaptive loop's feeds, the simulation's cells). First face only.
    fn against_preview(&mut self) -> Result<String, ReportError> {
        let (Ok(stock), Ok(preview)) = (self.decode("final_stock"), self.decode("toolpath_preview")) else {
            return Ok(String::new());
        };
        let meta = *preview.map.meta();
        let mut data = vec![f32::NAN; preview.map.data().len()];
        let (mut lo, mut hi, mut sq, mut n) = (0.0f64, 0.0f64, 0.0f64, 0usize);
        for row in 0..meta.height {
            for col in 0..meta.width {
                let Some(p) = preview.map.get(col, row).filter(|v| v.is_finite()) else { continue };
                let (x, y) = meta.cell_center(col, row);
                let Some(z) =
                    stock.map.cell_of(x, y).and_then(|(c, r)| stock.map.get(c, r)).filter(|v| v.is_finite())
                else {
                    continue;
                };
                let d = f64::from(z) - f64::from(p);
                data[(row * meta.width + col) as usize] = d as f32;
                lo = lo.min(d);
                hi = hi.max(d);
                sq += d * d;
                n += 1;
            }
        }
        if n == 0 {
            return Ok(String::new());
        }
        let range = (-lo).max(hi).max(0.005);
        let dev_meta = HeightMapMeta { z_min_mm: -range, z_max_mm: range, ..meta };
        let Ok(map) = HeightMap::new(dev_meta, data) else { return Ok(String::new()) };
        let mut body = String::from("<h3>Against the surface the program can leave</h3>");
        if let (Some(view), Some((r, _, _))) = (maps::map_view(&map), maps::deviation_range(&map)) {
            let img = maps::deviation_image(&map, &view, r);
            let caption = format!(
                "Machined part minus the CAM's predicted surface (the part opened by the tools, scallops included): what the machine itself added or left. Scale ±{} mm.",
                fmt_num(r)
            );
            body.push_str(&self.picture(
                "deviation_from_preview.png",
                &img,
                "deviation from the preview",
                &esc(&caption),
            )?);
        }
        let rows = vec![
            ("Deepest below the preview".to_string(), format!("{:.4} mm", (-lo).max(0.0))),
            ("Highest above the preview".to_string(), format!("{:.4} mm", hi.max(0.0))),
            ("RMS".to_string(), format!("{:.4} mm over {} cells", (sq / n as f64).sqrt(), n)),
        ];
        body.push_str(&kv_table(&rows));
        Ok(body)
    }

    fn telemetry(&mut self) -> String {
        let mut body = String::new();
        let plot = self.artifacts.get("telemetry_plot").filter(|b| {
            let head = String::from_utf8_lossy(&b[..b.len().min(512)]).to_ascii_lowercase();
            head.contains("<svg")
        });
        let csv =
            self.artifacts.get("telemetry").map(|b| charts::parse_telemetry(&String::from_utf8_lossy(b)));
        let svg: Option<(Vec<u8>, &str)> = match (plot, &csv) {
            (Some(p), _) => Some((p.clone(), "the machine service's telemetry plot")),
            (None, Some(Ok(t))) if t.rows > 0 => {
                Some((charts::telemetry_chart(t).to_svg().into_bytes(), "drawn from the telemetry CSV"))
            }
            _ => None,
        };
        match svg {
            Some((bytes, source)) => {
                let _ = write!(
                    body,
                    r#"<figure><img src="{}" alt="feed, speed, torque and power over time"><figcaption>Feed, spindle speed, torque and cutting power over the run under the adaptive loop ({}).</figcaption></figure>"#,
                    esc(&data_uri("image/svg+xml", &bytes)),
                    esc(source)
                );
                self.files.push(("telemetry.svg".into(), bytes));
            }
            None => {
                let why = match &csv {
                    Some(Err(e)) => format!("Not shown: the telemetry CSV could not be read: {e}."),
                    Some(Ok(_)) => "Not shown: the telemetry CSV has no rows.".into(),
                    None => self.why_missing("telemetry"),
                };
                body.push_str(&missing(&why));
            }
        }
        if let Some(Ok(t)) = &csv
            && t.rows > 0
        {
            let max = |v: &[f64]| v.iter().copied().filter(|x| x.is_finite()).fold(f64::NAN, f64::max);
            let mean = |v: &[f64]| {
                let f: Vec<f64> = v.iter().copied().filter(|x| x.is_finite()).collect();
                if f.is_empty() { f64::NAN } else { f.iter().sum::<f64>() / f.len() as f64 }
            };
            let dur = t.time_s.last().copied().unwrap_or(0.0) - t.time_s.first().copied().unwrap_or(0.0);
            let mut rows = vec![
                ("Samples".to_string(), format!("{} over {}", fmt_count(t.rows), fmt_duration(dur))),
                (
                    "Feed, mean / max".into(),
                    format!("{} / {} mm/min", fmt_num(mean(&t.feed)), fmt_num(max(&t.feed))),
                ),
                (
                    "Spindle, mean / max".into(),
                    format!("{} / {} rpm", fmt_num(mean(&t.rpm)), fmt_num(max(&t.rpm))),
                ),
                ("Torque from current, max".into(), format!("{} N·m", fmt_num(max(&t.torque_current)))),
                ("Cutting power, max".into(), format!("{} W", fmt_num(max(&t.power)))),
            ];
            for (name, n) in &t.active {
                rows.push((
                    format!("Limit '{name}' active"),
                    format!("{:.1} % of samples", *n as f64 / t.rows as f64 * 100.0),
                ));
            }
            let rows: Vec<(String, String)> = rows.into_iter().map(|(k, v)| (k, esc(&v))).collect();
            body.push_str(&kv_table(&rows));
        }
        section("telemetry", "Feed, speed, torque and power", &body)
    }

    fn cycle_time(&mut self) -> String {
        let mr = self.machine_report.as_ref();
        let mr_f = |k: &str| mr.and_then(|m| m[k].as_f64()).filter(|v| v.is_finite());
        let adaptive = self.metric("cycle_time_s").or_else(|| mr_f("cycle_time_s"));
        let plain = self.metric("cycle_time_no_adaptive_s").or_else(|| mr_f("cycle_time_no_adaptive_s"));
        let policy = mr
            .and_then(|m| m["run"]["policy"].as_str())
            .or_else(|| self.job["spec"]["execute"]["adaptive"].as_str())
            .unwrap_or("adaptive");
        let body = match (adaptive, plain) {
            (Some(a), Some(p)) => {
                let mut rows = vec![
                    ("programmed feeds".to_string(), p, "#9aa5b5"),
                    (format!("with the loop ({policy})"), a, "#2ca02c"),
                ];
                if let (Some(o), Some(name)) =
                    (mr_f("cycle_time_other_s"), mr.and_then(|m| m["other_policy"].as_str()))
                {
                    rows.push((format!("other policy ({name})"), o, "#7fb0d8"));
                }
                let svg = charts::hbars(&rows, "s");
                self.files.push(("cycle_time.svg".into(), svg.clone().into_bytes()));
                let saving = if p > 0.0 { (p - a) / p * 100.0 } else { 0.0 };
                let verdict = if saving >= 0.0 {
                    format!("The adaptive loop saved {} ({saving:.1} %).", fmt_duration(p - a))
                } else {
                    format!("The adaptive loop took {} longer ({:.1} %).", fmt_duration(a - p), -saving)
                };
                figure_svg(
                    &svg,
                    &esc(&format!(
                        "Simulated cycle time of the program with its programmed feeds and speeds and under the adaptive loop. {verdict}"
                    )),
                )
            }
            (Some(a), None) => missing(&format!(
                "Cycle time {} with the loop; the run without adaptation was not measured.",
                fmt_duration(a)
            )),
            _ => missing(&self.why_missing("machine_report")),
        };
        section("cycle-time", "Cycle time with and without the adaptive loop", &body)
    }
}

/// Toolpaths of `face` over `base` (grey hill-shade) or over white: finishing thin blue, then
/// roughing orange on top (it is sparser), rapids thin grey underneath, other feeds purple. The
/// view covers the map plus the program's feed moves (at most 15 % of the map beyond each side).
pub fn toolpath_image(base: Option<&HeightMap>, program: &Program, face: usize) -> Option<RgbImage> {
    let ext = program.feed_extent.get(face).copied().flatten();
    let (x0, y0, x1, y1) = match (base, ext) {
        (Some(m), e) => {
            let mm = m.meta();
            let (mx0, my0) = (mm.origin_x_mm, mm.origin_y_mm);
            let (mx1, my1) = (mx0 + mm.width_mm(), my0 + mm.height_mm());
            let (px, py) = (0.15 * (mx1 - mx0), 0.15 * (my1 - my0));
            match e {
                Some(e) => (
                    mx0.min(e[0].max(mx0 - px)),
                    my0.min(e[1].max(my0 - py)),
                    mx1.max(e[2].min(mx1 + px)),
                    my1.max(e[3].min(my1 + py)),
                ),
                None => (mx0, my0, mx1, my1),
            }
        }
        (None, Some(e)) => {
            let pad = 0.05 * (e[2] - e[0]).max(e[3] - e[1]).max(1.0);
            (e[0] - pad, e[1] - pad, e[2] + pad, e[3] + pad)
        }
        (None, None) => return None,
    };
    let side = base.map_or(800.0, |m| f64::from(m.width().max(m.height())).max(800.0));
    let view = View::fit(x0, y0, x1, y1, side)?;
    let mut img = match base.and_then(|m| maps::robust_range(m).map(|r| (m, r))) {
        Some((m, (lo, hi))) => maps::grey_image(m, &view, lo, hi),
        None => RgbImage::new(view.width, view.height, [255, 255, 255]),
    };
    let kind = |s: &gcode::Seg| program.ops.get(s.op as usize).map(|o| (o.face, o.kind));
    let draw = |img: &mut RgbImage, rapid: bool, k: OpKind, color: [u8; 3], alpha: f32, width: u32| {
        for s in &program.segs {
            let Some((f, k2)) = kind(s) else { continue };
            if f != face || s.rapid != rapid || (!rapid && k2 != k) {
                continue;
            }
            let a = view.to_px(f64::from(s.a[0]), f64::from(s.a[1]));
            let b = view.to_px(f64::from(s.b[0]), f64::from(s.b[1]));
            img.line(a, b, color, alpha, width);
        }
    };
    draw(&mut img, true, OpKind::Other, RAPID_RGB, 0.45, 1);
    draw(&mut img, false, OpKind::Other, OTHER_RGB, 0.85, 1);
    draw(&mut img, false, OpKind::Finishing, FINISHING_RGB, 0.85, 1);
    draw(&mut img, false, OpKind::Roughing, ROUGHING_RGB, 0.9, 2);
    Some(img)
}

/// `spec` values flattened to `a.b[0].c = value` rows (strings unquoted).
fn flatten(prefix: &str, v: &Value, out: &mut Vec<(String, String)>) {
    match v {
        Value::Object(o) => {
            for (k, x) in o {
                let p = if prefix.is_empty() { k.clone() } else { format!("{prefix}.{k}") };
                flatten(&p, x, out);
            }
        }
        Value::Array(a) if a.iter().all(|x| !x.is_object() && !x.is_array()) => {
            let parts: Vec<String> = a.iter().map(scalar).collect();
            out.push((prefix.to_string(), format!("[{}]", parts.join(", "))));
        }
        Value::Array(a) => {
            for (i, x) in a.iter().enumerate() {
                flatten(&format!("{prefix}[{i}]"), x, out);
            }
        }
        x => out.push((prefix.to_string(), scalar(x))),
    }
}

fn scalar(v: &Value) -> String {
    match v {
        Value::String(s) => s.clone(),
        other => other.to_string(),
    }
}

/// `depth_map@1` -> `depth_map_face2.png`; `depth_map` -> `depth_map.png`.
fn file_name(key: &str, ext: &str) -> String {
    match key.split_once('@') {
        Some((base, i)) => {
            let n = i.parse::<u32>().map_or(i.to_string(), |n| (n + 1).to_string());
            format!("{base}_face{n}.{ext}")
        }
        None => format!("{key}.{ext}"),
    }
}

fn fmt_count(n: usize) -> String {
    let s = n.to_string();
    let mut out = String::new();
    for (i, c) in s.chars().enumerate() {
        if i > 0 && (s.len() - i).is_multiple_of(3) {
            out.push('\u{202f}');
        }
        out.push(c);
    }
    out
}

fn fmt_bytes(n: u64) -> String {
    let f = n as f64;
    if f >= 1e9 {
        format!("{:.2} GB", f / 1e9)
    } else if f >= 1e6 {
        format!("{:.2} MB", f / 1e6)
    } else if f >= 1e3 {
        format!("{:.1} kB", f / 1e3)
    } else {
        format!("{n} B")
    }
}

/// `83.4 s`, `12 min 5 s`, `2 h 03 min`.
fn fmt_duration(s: f64) -> String {
    if !s.is_finite() {
        return "—".into();
    }
    let neg = if s < 0.0 { "-" } else { "" };
    let s = s.abs();
    if s < 60.0 {
        format!("{neg}{} s", fmt_num(s))
    } else if s < 3600.0 {
        format!("{neg}{} min {:.0} s", (s / 60.0).floor(), s % 60.0)
    } else {
        format!("{neg}{} h {:02.0} min", (s / 3600.0).floor(), ((s % 3600.0) / 60.0).floor())
    }
}

/// Milliseconds since the epoch as `YYYY-MM-DD HH:MM:SS UTC` (proleptic Gregorian).
fn utc(ms: i64) -> String {
    let secs = ms.div_euclid(1000);
    let (days, rem) = (secs.div_euclid(86_400), secs.rem_euclid(86_400));
    // Howard Hinnant's civil_from_days.
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z.rem_euclid(146_097);
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = doy - (153 * mp + 2) / 5 + 1;
    let m = if mp < 10 { mp + 3 } else { mp - 9 };
    let y = yoe + era * 400 + i64::from(m <= 2);
    format!("{y:04}-{m:02}-{d:02} {:02}:{:02}:{:02} UTC", rem / 3600, rem % 3600 / 60, rem % 60)
}
