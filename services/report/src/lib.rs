//! The job report: one self-contained HTML page (inline CSS, pictures as `data:` URIs, one inline
//! script for the 3-D view of a multi-axis part, no external request) showing what a job did, with pictures where a person would rather look
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
//!   readers of `depthmill_geometry::formats`, splatted from above and from the front ([`cloud`]).
//! - Depth and coverage maps per face: `depth_map`, `coverage_map`, then `depth_map@1`, ... (the
//!   orchestrator's names for further faces): 16-bit PNG with depthmill metadata (or `.npy`), read
//!   with `depthmill_geometry::read_png_from`; coverage classes 1 / 0.5 / 0 / no data; stats from
//!   the map itself and, if stored, a `reconstruct_report` JSON.
//! - Toolpaths per face: `gcode` parsed for drawing ([`gcode`]), over the face's depth map (or the
//!   final stock, or nothing) in work coordinates = the map's frame.
//! - Machined part: `final_stock` (16-bit PNG height map), Lambert-lit; else the CAM's
//!   `toolpath_preview`.
//! - Deviation: `deviation_map` (8-bit PNG, stock − target, Z range ±max) on a diverging scale.
//! - Simulated part in 3-D: `machined_part_view` (binary PLY mesh, deviation per vertex, from the
//!   machine service for a multi-axis part) in an interactive viewer (`sections/solid.rs`), and
//!   `machine_report.part` (figures against the original part and the opened part, per face).
//! - Telemetry: `telemetry_plot` (SVG, embedded as an image so nothing in it runs), else the
//!   `telemetry` CSV drawn with [`plot`].
//! - Cycle time: `job.metrics` (or `machine_report`) with and without adaptation.
//! - A robot job (`spec.process` = `robot`) instead of the maps, toolpaths, Z-map stock,
//!   deviation map, telemetry and cycle-time sections: its summary from `job.metrics`, the plan
//!   from `plan_report` (the CAM's robot report: layers, rings, clearance and tilts, the arm's
//!   program, warnings), the tip path from `gcode`, and the run from `machine_report` (the robot
//!   run: volumes, rapid cuts, deviation against the mesh); the 3-D view as for a multi-axis part
//!   (`sections/robot.rs`).
//!
//! # Layout
//! This file holds [`render`], which puts the sections together in page order, and the context
//! every section reads the job and its artifacts through. Each section is a module of `sections`:
//! - `sections/summary.rs`: header, summary and parameters;
//! - `sections/scan.rs`: point cloud and scan figures;
//! - `sections/faces.rs`: depth and coverage maps per face;
//! - `sections/toolpaths.rs`: toolpaths over the depth map ([`toolpath_image`]);
//! - `sections/part.rs`: the machined part, its deviation, against the original part and the
//!   CAM's prediction;
//! - `sections/solid.rs`: the simulated part in 3-D (the page's one script);
//! - `sections/machine.rs`: telemetry and cycle time;
//! - `sections/robot.rs`: a robot milling job's summary, plan and run.
//!
//! The picture kit they share:
//! - [`raster`]: RGB image, PNG, base64, colour maps and legends, lines, [`raster::View`].
//! - [`maps`]: height-map decoding and pictures; [`cloud`]: point-cloud views;
//!   [`gcode`]: G-code for drawing; [`charts`]: SVG bars and the telemetry chart; [`plot`]: SVG
//!   line charts (also drawn by the machine service for its telemetry); `html`: escaping and page
//!   pieces.
//!
//! # Architecture Invariant
//! Pure and synchronous: no async, no network, no configuration; it depends on
//! `depthmill-geometry` alone among depthmill crates, so the orchestrator renders reports without
//! any stage service's code and the machine service draws with [`plot`] without the orchestrator.

pub mod charts;
pub mod cloud;
pub mod digest;
pub mod gcode;
mod html;
pub mod maps;
pub mod plot;
pub mod raster;
mod sections;
#[cfg(test)]
mod tests;

use std::collections::BTreeMap;
use std::fmt::Write as _;

use depthmill_geometry::{HeightMap, HeightMapMeta, ImageMapping};
use serde_json::Value;

use html::{esc, figure_svg, kv_table, missing, section, table};
use raster::{ColorMap, RgbImage, View, data_uri, fmt_num};

pub use gcode::{OpKind, Program};
pub use sections::toolpath_image;

/// What the report is made from.
pub struct ReportInput<'a> {
    /// The job as `GET /v1/jobs/{id}` returns it: id, name, status, spec (the submitted job JSON),
    /// stage_timings_s, metrics, artifacts (kind -> {sha256, size, media_type}), attempts, ...
    pub job: &'a Value,
    /// Artifact kind (the keys of `job.artifacts`) -> its bytes.
    pub artifacts: &'a BTreeMap<String, Vec<u8>>,
    /// Artifacts read by streaming instead ([`digest`]; [`digest::Digests::NONE`] when every
    /// artifact comes as bytes). A kind here is not looked for in `artifacts`.
    pub digests: &'a digest::Digests,
}

/// The rendered report.
pub struct ReportOutput {
    /// One self-contained HTML page: images embedded as `data:` URIs (PNG or SVG), inline CSS, the
    /// 3-D viewer's inline script when there is a simulated part mesh, no external requests.
    pub html: String,
    /// The same pictures as files (`depth_map.png`, `telemetry.svg`, ...), for an output folder.
    pub files: Vec<(String, Vec<u8>)>,
    /// Figures the report measured itself, by name (mm unless the name says otherwise):
    /// `part_max_gouge_mm`, `part_max_leftover_mm`, `part_mean_leftover_mm`, `part_mean_mm`
    /// (signed), `part_rms_mm` (the machined part against the original part, when the job
    /// started from its mesh), `part_off_walls_max_gouge_mm`, `part_off_walls_mean_mm`,
    /// `part_off_walls_rms_mm` (the same without the cells next to walls), `part_opened_max_gouge_mm`,
    /// `part_opened_mean_mm`, `part_opened_rms_mm`, `part_opened_cells` (off the walls where the
    /// program's smallest tool reaches the part, against the part opened by that tool;
    /// `part_opened_max_gouge_x_mm`, `part_opened_max_gouge_y_mm`: where the deepest of those
    /// gouges is, in the depth map's frame, when there is one; `part_opened_measured_max_gouge_mm`,
    /// `_mean_mm`, `_rms_mm`, `_cells`: the same over the cells the first face's coverage map
    /// marks measured, when it lies on the stock's grid) and `preview_max_below_mm`, `preview_max_above_mm`,
    /// `preview_mean_mm`, `preview_rms_mm` (against the CAM's predicted surface, the part opened
    /// by the tools).
    pub figures: BTreeMap<String, f64>,
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
    if ctx.is_robot() {
        // A robot job: no depth maps, Z-map stock or adaptive loop; its own plan and run.
        body.push_str(&ctx.robot_summary());
        body.push_str(&ctx.findings());
        body.push_str(&ctx.parameters());
        body.push_str(&ctx.point_cloud()?);
        body.push_str(&ctx.robot()?);
        body.push_str(&ctx.solid()?);
    } else {
        body.push_str(&ctx.summary());
        body.push_str(&ctx.findings());
        body.push_str(&ctx.parameters());
        body.push_str(&ctx.point_cloud()?);
        body.push_str(&ctx.mill_sections()?);
    }
    let title = format!("depthmill report: {}", ctx.name());

    let html = format!(
        "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\"><meta name=\"viewport\" content=\"width=device-width, initial-scale=1\"><title>{}</title><style>{}</style></head><body><main>{body}<footer>Generated by depthmill from job {}. Self-contained page: every picture is embedded.</footer></main></body></html>\n",
        esc(&title),
        html::CSS,
        esc(ctx.str_at("id").unwrap_or("?")),
    );
    Ok(ReportOutput { html, files: ctx.files, figures: ctx.figures })
}

impl Ctx<'_> {
    /// The sections of a milling job after the point cloud.
    fn mill_sections(&mut self) -> Result<String, ReportError> {
        let mut body = String::new();
        body.push_str(&self.maps()?);
        body.push_str(&self.toolpaths()?);
        body.push_str(&self.machined()?);
        body.push_str(&self.solid()?);
        body.push_str(&self.deviation()?);
        body.push_str(&self.telemetry());
        body.push_str(&self.cycle_time());
        Ok(body)
    }
}

struct Ctx<'a> {
    job: &'a Value,
    artifacts: &'a BTreeMap<String, Vec<u8>>,
    digests: &'a digest::Digests,
    files: Vec<(String, Vec<u8>)>,
    figures: BTreeMap<String, f64>,
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
            digests: input.digests,
            files: Vec::new(),
            figures: BTreeMap::new(),
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
        if self.is_robot() {
            return Some("plan");
        }
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
