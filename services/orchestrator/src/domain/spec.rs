//! The job request (`POST /v1/jobs` body), its validation and documented defaults.
//!
//! Every struct denies unknown fields, so a misspelt parameter is an error that names it, never a
//! silently ignored setting. Sections a job never reaches (a `scan` section on a job that starts
//! from a depth map) are rejected the same way. Defaults are applied by the stage services; they
//! are documented here so the OpenAPI document shows them.

use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

use super::job::Stage;

/// A job request. Every section but `input` is optional.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct JobSpec {
    /// A name for people; need not be unique.
    #[serde(default)]
    pub name: String,
    pub input: JobInput,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub scan: Option<ScanParams>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub reconstruct: Option<ReconstructParams>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub plan: Option<PlanParams>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub execute: Option<ExecuteParams>,
}

/// What the job starts from. The kind decides the first stage.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct JobInput {
    pub kind: InputKind,
    /// sha256 of an artifact uploaded with `POST /v1/artifacts`.
    pub artifact: String,
    /// Pixel size of a depth image without depthmill metadata.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pixel_mm: Option<f64>,
    /// Z of black in a depth image without depthmill metadata.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub z_min_mm: Option<f64>,
    /// Z of white in a depth image without depthmill metadata.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub z_max_mm: Option<f64>,
}

/// The kind of a job's input.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum InputKind {
    /// STL mesh of the part: the job starts with a simulated scan.
    Mesh,
    /// XYZ or PLY point cloud: the job starts with reconstruction.
    PointCloud,
    /// 8/16-bit PNG or `.npy` depth map: the job starts with planning.
    DepthMap,
    /// G-code program: the job starts with execution.
    Gcode,
}

impl InputKind {
    /// The stage a job with this input starts at.
    pub fn first_stage(self) -> Stage {
        match self {
            InputKind::Mesh => Stage::Scan,
            InputKind::PointCloud => Stage::Reconstruct,
            InputKind::DepthMap => Stage::Plan,
            InputKind::Gcode => Stage::Execute,
        }
    }

    /// The wire name.
    pub fn as_str(self) -> &'static str {
        match self {
            InputKind::Mesh => "mesh",
            InputKind::PointCloud => "point_cloud",
            InputKind::DepthMap => "depth_map",
            InputKind::Gcode => "gcode",
        }
    }

    /// Media types an input of this kind may have.
    pub fn media_types(self) -> &'static [&'static str] {
        match self {
            InputKind::Mesh => &["model/stl", "application/x-ply"],
            InputKind::PointCloud => &["text/x-xyz", "application/x-ply", "application/octet-stream"],
            InputKind::DepthMap => &["image/png", "application/x-npy"],
            InputKind::Gcode => &["text/x-gcode"],
        }
    }
}

/// Scan stage parameters. Defaults: dynamic mode, table angles 0/90/180/270, standoff 150 mm,
/// 100 lines/s, no adaptive rescan.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct ScanParams {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mode: Option<ScanMode>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub table_angles_deg: Option<Vec<f64>>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub standoff_mm: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub line_rate_hz: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub adaptive_rescan: Option<bool>,
}

/// How the robot and table move while scanning.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum ScanMode {
    Dynamic,
    StopAndMove,
}

/// Reconstruct stage parameters. Defaults: pixel 0.1 mm, one face `+Z`, IDW fill of holes up to 2 mm.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct ReconstructParams {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pixel_mm: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub faces: Option<Vec<FaceSpec>>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fill: Option<FillParams>,
}

/// A face to cut from above: a named view or an angle about the machine's A axis (exactly one).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct FaceSpec {
    /// `+Z`, `-Z`, `+X`, `-X`, `+Y` or `-Y`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub view: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub a_deg: Option<f64>,
}

/// How holes in the raw depth map are filled.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct FillParams {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub method: Option<FillMethod>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max_hole_mm: Option<f64>,
}

/// Hole filling method.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum FillMethod {
    /// Inverse-distance-weighted mean of the neighbours.
    Idw,
    /// Highest neighbour.
    Max,
}

/// Plan stage parameters.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct PlanParams {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stock: Option<Stock>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub roughing: Option<Roughing>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub finishing: Option<Finishing>,
    /// G-code dialect. Default `linuxcnc`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub dialect: Option<Dialect>,
}

/// The raw block. Default: the depth map's extent and Z range, aluminium.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct Stock {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub x_mm: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub y_mm: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub z_mm: Option<f64>,
    /// `aluminium`, `brass`, `mild_steel`, ...
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub material: Option<String>,
}

/// Roughing. Defaults: `flat-6`, 2 mm step-down, 0.3 mm stock to leave, raster along X.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct Roughing {
    /// `flat-D`, `ball-D`, `bull-D-R`, `v-D-ANGLE` (D diameter in mm) or a tool library name.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tool: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub step_down_mm: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stock_to_leave_mm: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub direction: Option<RoughingDirection>,
}

/// Roughing clearing pattern.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum RoughingDirection {
    X,
    Y,
    Contour,
}

/// Finishing. Defaults: `ball-3`, raster along X, step-over 0.3 mm, tolerance 0.01 mm, arcs on.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct Finishing {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tool: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub strategy: Option<FinishingStrategy>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub angle_deg: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub step_over_mm: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tolerance_mm: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub arcs: Option<bool>,
}

/// Finishing strategy.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum FinishingStrategy {
    RasterX,
    RasterY,
    RasterAngle,
    IsoLevel,
}

/// G-code dialect.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum Dialect {
    Linuxcnc,
    Fanuc,
}

/// Execute stage parameters. Defaults: machine `emco-f1`, adaptive `aco`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct ExecuteParams {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub machine: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub adaptive: Option<AdaptiveMode>,
}

/// Adaptive feed/speed control while cutting.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum AdaptiveMode {
    /// Feed and spindle speed both adapt.
    Aco,
    FeedOnly,
    Off,
}

/// A job request that is well-formed JSON but asks for something invalid.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{field}: {message}")]
pub struct SpecError {
    /// Dotted path of the offending field, e.g. `plan.finishing.step_over_mm`.
    pub field: String,
    pub message: String,
}

fn err(field: &str, message: impl Into<String>) -> SpecError {
    SpecError { field: field.to_string(), message: message.into() }
}

fn positive(field: &str, v: Option<f64>, max: f64) -> Result<(), SpecError> {
    match v {
        Some(x) if !x.is_finite() || x <= 0.0 => {
            Err(err(field, format!("must be a positive number, got {x}")))
        }
        Some(x) if x > max => Err(err(field, format!("{x} is above the limit of {max}"))),
        _ => Ok(()),
    }
}

fn non_negative(field: &str, v: Option<f64>, max: f64) -> Result<(), SpecError> {
    match v {
        Some(x) if !x.is_finite() || x < 0.0 => Err(err(field, format!("must be zero or positive, got {x}"))),
        Some(x) if x > max => Err(err(field, format!("{x} is above the limit of {max}"))),
        _ => Ok(()),
    }
}

fn finite(field: &str, v: Option<f64>) -> Result<(), SpecError> {
    match v {
        Some(x) if !x.is_finite() => Err(err(field, format!("must be a finite number, got {x}"))),
        _ => Ok(()),
    }
}

fn tool_name(field: &str, v: Option<&String>) -> Result<(), SpecError> {
    match v {
        Some(t) if t.trim().is_empty() => Err(err(field, "must name a tool, e.g. ball-3 or flat-6")),
        Some(t) if t.len() > 128 => {
            Err(err(field, format!("tool name is {} characters, the limit is 128", t.len())))
        }
        _ => Ok(()),
    }
}

const NAMED_VIEWS: [&str; 6] = ["+Z", "-Z", "+X", "-X", "+Y", "-Y"];

impl JobSpec {
    /// The stage this job starts at.
    pub fn first_stage(&self) -> Stage {
        self.input.kind.first_stage()
    }

    /// Checks values and that every section given is one the job will run.
    /// Returns the first problem found, naming its field.
    pub fn validate(&self) -> Result<(), SpecError> {
        if self.name.len() > 256 {
            return Err(err("name", format!("is {} characters, the limit is 256", self.name.len())));
        }
        let first = self.first_stage();
        let sections = [
            ("scan", Stage::Scan, self.scan.is_some()),
            ("reconstruct", Stage::Reconstruct, self.reconstruct.is_some()),
            ("plan", Stage::Plan, self.plan.is_some()),
            ("execute", Stage::Execute, self.execute.is_some()),
        ];
        for (field, stage, present) in sections {
            if present && stage < first {
                return Err(err(
                    field,
                    format!(
                        "a job whose input is a {} starts at the {first} stage and never runs {stage}: remove this section",
                        self.input.kind.as_str()
                    ),
                ));
            }
        }
        let input = &self.input;
        if !depthmill_geometry::artifact::is_sha256_hex(&input.artifact) {
            return Err(err(
                "input.artifact",
                "must be the sha256 (64 lowercase hex digits) of an uploaded artifact",
            ));
        }
        positive("input.pixel_mm", input.pixel_mm, 100.0)?;
        finite("input.z_min_mm", input.z_min_mm)?;
        finite("input.z_max_mm", input.z_max_mm)?;
        if (input.pixel_mm.is_some() || input.z_min_mm.is_some() || input.z_max_mm.is_some())
            && input.kind != InputKind::DepthMap
        {
            return Err(err("input.pixel_mm", "pixel size and Z range are for depth-map inputs only"));
        }
        if let (Some(lo), Some(hi)) = (input.z_min_mm, input.z_max_mm)
            && lo >= hi
        {
            return Err(err("input.z_max_mm", format!("must be above z_min_mm ({lo}), got {hi}")));
        }
        if let Some(scan) = &self.scan {
            positive("scan.standoff_mm", scan.standoff_mm, 10_000.0)?;
            positive("scan.line_rate_hz", scan.line_rate_hz, 100_000.0)?;
            if let Some(angles) = &scan.table_angles_deg {
                if angles.is_empty() || angles.len() > 360 {
                    return Err(err(
                        "scan.table_angles_deg",
                        format!("needs 1 to 360 angles, got {}", angles.len()),
                    ));
                }
                if let Some((i, a)) = angles.iter().enumerate().find(|(_, a)| !a.is_finite()) {
                    return Err(err(
                        &format!("scan.table_angles_deg[{i}]"),
                        format!("must be finite, got {a}"),
                    ));
                }
            }
        }
        if let Some(rec) = &self.reconstruct {
            positive("reconstruct.pixel_mm", rec.pixel_mm, 100.0)?;
            if let Some(faces) = &rec.faces {
                if faces.is_empty() || faces.len() > 36 {
                    return Err(err(
                        "reconstruct.faces",
                        format!("needs 1 to 36 faces, got {}", faces.len()),
                    ));
                }
                for (i, f) in faces.iter().enumerate() {
                    let field = format!("reconstruct.faces[{i}]");
                    match (&f.view, f.a_deg) {
                        (Some(v), None) if NAMED_VIEWS.contains(&v.as_str()) => {}
                        (Some(v), None) => {
                            return Err(err(
                                &format!("{field}.view"),
                                format!("unknown view '{v}' (expected one of {})", NAMED_VIEWS.join(", ")),
                            ));
                        }
                        (None, Some(a)) => finite(&format!("{field}.a_deg"), Some(a))?,
                        _ => return Err(err(&field, "give exactly one of view and a_deg")),
                    }
                }
            }
            if let Some(fill) = &rec.fill {
                non_negative("reconstruct.fill.max_hole_mm", fill.max_hole_mm, 1000.0)?;
            }
        }
        if let Some(plan) = &self.plan {
            if let Some(stock) = &plan.stock {
                positive("plan.stock.x_mm", stock.x_mm, 10_000.0)?;
                positive("plan.stock.y_mm", stock.y_mm, 10_000.0)?;
                positive("plan.stock.z_mm", stock.z_mm, 10_000.0)?;
                if let Some(m) = &stock.material
                    && (m.trim().is_empty() || m.len() > 64)
                {
                    return Err(err("plan.stock.material", "must name a material, e.g. aluminium"));
                }
            }
            if let Some(r) = &plan.roughing {
                tool_name("plan.roughing.tool", r.tool.as_ref())?;
                positive("plan.roughing.step_down_mm", r.step_down_mm, 100.0)?;
                non_negative("plan.roughing.stock_to_leave_mm", r.stock_to_leave_mm, 100.0)?;
            }
            if let Some(f) = &plan.finishing {
                tool_name("plan.finishing.tool", f.tool.as_ref())?;
                finite("plan.finishing.angle_deg", f.angle_deg)?;
                if f.angle_deg.is_some() && f.strategy != Some(FinishingStrategy::RasterAngle) {
                    return Err(err("plan.finishing.angle_deg", "applies only to strategy raster_angle"));
                }
                positive("plan.finishing.step_over_mm", f.step_over_mm, 100.0)?;
                positive("plan.finishing.tolerance_mm", f.tolerance_mm, 10.0)?;
            }
        }
        if let Some(exec) = &self.execute
            && let Some(m) = &exec.machine
            && (m.trim().is_empty() || m.len() > 64)
        {
            return Err(err("execute.machine", "must name a machine profile, e.g. emco-f1"));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(json: &str) -> Result<JobSpec, String> {
        let de = &mut serde_json::Deserializer::from_str(json);
        serde_path_to_error::deserialize(de).map_err(|e| format!("{}: {}", e.path(), e.inner()))
    }

    const SHA: &str = "aaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaa";

    #[test]
    fn the_design_example_parses_and_validates() {
        let json = format!(
            r#"{{"name": "bracket",
                "input": {{"kind": "mesh", "artifact": "{SHA}"}},
                "scan": {{"mode": "dynamic", "table_angles_deg": [0, 90, 180, 270], "standoff_mm": 150,
                          "line_rate_hz": 100, "adaptive_rescan": true}},
                "reconstruct": {{"pixel_mm": 0.1, "faces": [{{"view": "+Z"}}], "fill": {{"method": "idw", "max_hole_mm": 2.0}}}},
                "plan": {{"stock": {{"x_mm": 100, "y_mm": 80, "z_mm": 25, "material": "aluminium"}},
                         "roughing": {{"tool": "flat-6", "step_down_mm": 2.0, "stock_to_leave_mm": 0.3, "direction": "x"}},
                         "finishing": {{"tool": "ball-3", "strategy": "raster_x", "step_over_mm": 0.3,
                                       "tolerance_mm": 0.01, "arcs": true}},
                         "dialect": "linuxcnc"}},
                "execute": {{"machine": "emco-f1", "adaptive": "aco"}}}}"#
        );
        let spec = parse(&json).expect("parse");
        spec.validate().expect("valid");
        assert_eq!(spec.first_stage(), Stage::Scan);
        // Serialising and parsing again gives the same spec.
        let again = parse(&serde_json::to_string(&spec).expect("ser")).expect("reparse");
        assert_eq!(spec, again);
    }

    #[test]
    fn unknown_fields_and_values_are_named() {
        let e = parse(&format!(
            r#"{{"input": {{"kind": "depth_map", "artifact": "{SHA}"}}, "plan": {{"finishing": {{"step_ovr_mm": 1}}}}}}"#
        ))
        .expect_err("unknown field");
        assert!(e.starts_with("plan.finishing") && e.contains("step_ovr_mm"), "{e}");
        let e =
            parse(&format!(r#"{{"input": {{"kind": "photo", "artifact": "{SHA}"}}}}"#)).expect_err("kind");
        assert!(e.starts_with("input.kind") && e.contains("photo"), "{e}");
    }

    #[test]
    fn values_out_of_range_and_unreachable_sections_are_rejected() {
        let base =
            |extra: &str| format!(r#"{{"input": {{"kind": "depth_map", "artifact": "{SHA}"}}{extra}}}"#);
        let cases = [
            (r#", "plan": {"finishing": {"step_over_mm": -1}}"#, "plan.finishing.step_over_mm"),
            (r#", "scan": {}"#, "scan"),
            (r#", "reconstruct": {"pixel_mm": 0.1}"#, "reconstruct"),
            (r#", "plan": {"roughing": {"tool": " "}}"#, "plan.roughing.tool"),
            (r#", "plan": {"finishing": {"angle_deg": 30}}"#, "plan.finishing.angle_deg"),
        ];
        for (extra, field) in cases {
            let spec = parse(&base(extra)).expect("parse");
            assert_eq!(spec.validate().expect_err(extra).field, field, "{extra}");
        }
        let spec = parse(&format!(
            r#"{{"input": {{"kind": "point_cloud", "artifact": "{SHA}"}}, "reconstruct": {{"faces": [{{"view": "up"}}]}}}}"#
        ))
        .expect("parse");
        assert_eq!(spec.validate().expect_err("view").field, "reconstruct.faces[0].view");
        let spec = parse(r#"{"input": {"kind": "gcode", "artifact": "abc"}}"#).expect("parse");
        assert_eq!(spec.validate().expect_err("digest").field, "input.artifact");
    }
}
