//! Planning: depth maps and plan options -> one G-code program, a plan report and a preview.
//!
//! Per face: roughing with a flat end mill on the roughing map (or the depth map), compensation of
//! the depth map for the finishing tool (conservative column reading), finishing on the tip
//! surface, holder checks for both tools, clean-up (Douglas–Peucker then arcs), feeds and speeds
//! from the tool × material table, time estimate, and a preview sweep measuring gouge and leftover.
//! Faces with an A angle become A-axis rotations of one program.
//!
//! Options mirror the `plan` object of a job request (DESIGN.md §7); defaults: stock = the map's
//! extent and highest point, aluminium; roughing `flat-6`, 2 mm step-down, 0.3 mm stock to leave,
//! raster along X at 40 % of the diameter; finishing `ball-3`, raster along X, step-over from a
//! 0.01 mm scallop, tolerance 0.01 mm, arcs on; dialect `linuxcnc`.

use std::time::Instant;

use depthmill_geometry::HeightMap;
use nalgebra::Point3;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::CamError;
use super::compensate::{CompensateOptions, PixelModel, compensate};
use super::feeds::{MachineLimits, cutting_data, estimate_time_s};
use super::finishing::{FinishingParams, FinishingPattern, finishing, step_over_for_scallop};
use super::gcode::{Dialect, FaceProgram, Operation, ProgramInfo, write_program};
use super::holder::check_holder;
use super::path::{Segment, Toolpath};
use super::preview::{PreviewReport, SweptOp, simulate};
use super::rest::{LeftRegion, RestReport, left_regions};
use super::roughing::{RoughingParams, RoughingPattern, roughing};
use super::tool::ToolLibrary;

/// The `plan` object of a job request.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PlanOptions {
    #[serde(default)]
    pub stock: Option<StockOptions>,
    #[serde(default)]
    pub roughing: Option<RoughingOptions>,
    #[serde(default)]
    pub finishing: Option<FinishingOptions>,
    /// `linuxcnc` or `fanuc`.
    #[serde(default)]
    pub dialect: Option<String>,
    /// Rest finishing with a smaller ball where finishing left material ([`super::rest`]).
    #[serde(default)]
    pub rest: Option<RestOptions>,
}

/// The `plan.rest` object: rest finishing after the finishing pass.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RestOptions {
    /// `true`: a rest pass wherever it removes something (default `false`).
    #[serde(default)]
    pub enabled: Option<bool>,
    /// The rest tool (default: the library's largest ball smaller than the finishing tool).
    #[serde(default)]
    pub tool: Option<String>,
    /// Least leftover the rest pass goes after, mm (default 0.05).
    #[serde(default)]
    pub min_leftover_mm: Option<f64>,
}

#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StockOptions {
    #[serde(default)]
    pub x_mm: Option<f64>,
    #[serde(default)]
    pub y_mm: Option<f64>,
    #[serde(default)]
    pub z_mm: Option<f64>,
    #[serde(default)]
    pub material: Option<String>,
}

#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RoughingOptions {
    #[serde(default)]
    pub tool: Option<String>,
    #[serde(default)]
    pub step_down_mm: Option<f64>,
    #[serde(default)]
    pub stock_to_leave_mm: Option<f64>,
    /// `x`, `y` or `contour`.
    #[serde(default)]
    pub direction: Option<String>,
}

#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FinishingOptions {
    #[serde(default)]
    pub tool: Option<String>,
    /// `raster_x`, `raster_y`, `raster_angle` or `iso_level`.
    #[serde(default)]
    pub strategy: Option<String>,
    #[serde(default)]
    pub angle_deg: Option<f64>,
    #[serde(default)]
    pub step_over_mm: Option<f64>,
    #[serde(default)]
    pub tolerance_mm: Option<f64>,
    #[serde(default)]
    pub arcs: Option<bool>,
    /// What a depth-map cell means to the finishing tool: `column` (default: a square column at
    /// its height, never below it anywhere over the cell; on a slope the tool stands off by up to
    /// the slope times half a pixel) or `point` (a sample of a continuous surface at the cell's
    /// centre: no stand-off on slopes, for a fitted target such as `reconstruct.estimator: "fit"`;
    /// between samples the tool may dip by the surface's bulge over a pixel).
    #[serde(default)]
    pub pixel_model: Option<String>,
}

/// One face to cut.
pub struct FaceInput {
    /// Rotation of the part about the A axis for this face; `None` for a 3-axis job.
    pub a_deg: Option<f64>,
    pub map: HeightMap,
    /// Over-approximation of `map` for roughing, when the job has one.
    pub roughing_map: Option<HeightMap>,
}

/// What [`plan`] produced.
pub struct PlanOutput {
    pub gcode: String,
    pub report: PlanReport,
    /// Preview of the first face.
    pub preview: PreviewReport,
    /// The surface the program leaves on each further face (faces 2.., in order).
    pub later_surfaces: Vec<HeightMap>,
}

/// The plan report (JSON).
#[derive(Debug, Clone, Serialize)]
pub struct PlanReport {
    pub dialect: String,
    pub pixel_model: PixelModel,
    pub tolerance_mm: f64,
    pub material: String,
    pub faces: Vec<FaceReport>,
    pub blocks: usize,
    pub estimated_time_s: f64,
    pub timings_s: std::collections::BTreeMap<String, f64>,
    /// How the tools the job left unnamed were chosen, when the defaults could not reach (empty
    /// otherwise).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub tool_choice: Vec<String>,
}

#[derive(Debug, Clone, Serialize)]
pub struct FaceReport {
    pub a_deg: Option<f64>,
    pub width: u32,
    pub height: u32,
    pub pixel_mm: f64,
    pub stock_top_mm: f64,
    pub floor_mm: f64,
    pub operations: Vec<OperationReport>,
    pub max_gouge_mm: f64,
    pub gouge_at_mm: Option<[f64; 2]>,
    pub max_leftover_mm: f64,
    pub mean_leftover_mm: f64,
    /// The rest finishing pass, when there is one.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub rest: Option<RestReport>,
    /// Why there is no rest pass although one was asked for (no region, the tool cannot reach).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub rest_note: Option<String>,
    /// Material still above the part after every operation (more than the rest threshold), largest
    /// groups first: features narrower than the smallest tool used.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub left_regions: Vec<LeftRegion>,
}

#[derive(Debug, Clone, Serialize)]
pub struct OperationReport {
    pub strategy: String,
    pub tool: String,
    pub tool_number: u32,
    pub step_over_mm: f64,
    pub passes: usize,
    pub points: usize,
    pub lines: usize,
    pub arcs: usize,
    pub spindle_rpm: f64,
    pub feed_mm_min: f64,
    pub min_stickout_mm: f64,
    /// Smallest clearance of shank and holder over the part; `None` when the operation has no moves.
    pub holder_clearance_mm: Option<f64>,
    pub estimated_time_s: f64,
}

fn positive(field: &str, v: Option<f64>, default: f64) -> Result<f64, CamError> {
    match v {
        None => Ok(default),
        Some(x) if x.is_finite() && x > 0.0 => Ok(x),
        Some(x) => Err(CamError::param(field, format!("must be a positive number, got {x}"))),
    }
}

struct Steps<'a> {
    progress: &'a (dyn Fn(f64, &str) + Sync),
    cancelled: &'a (dyn Fn() -> bool + Sync),
    timings: std::collections::BTreeMap<String, f64>,
}

impl Steps<'_> {
    /// Two steps side by side (rayon's join: each has serial stretches the other fills), each
    /// timed on its own, so the report's step times then add up to more than the wall time.
    fn run_pair<A: Send, B: Send>(
        &mut self,
        fraction: f64,
        names: [&str; 2],
        a: impl FnOnce() -> Result<A, CamError> + Send,
        b: impl FnOnce() -> Result<B, CamError> + Send,
    ) -> Result<(A, B), CamError> {
        if (self.cancelled)() {
            return Err(CamError::Cancelled);
        }
        (self.progress)(fraction, &format!("{} and {}", names[0], names[1]));
        let timed = |t: Instant| t.elapsed().as_secs_f64();
        let (ra, rb) = rayon::join(
            || {
                let t = Instant::now();
                a().map(|v| (v, timed(t)))
            },
            || {
                let t = Instant::now();
                b().map(|v| (v, timed(t)))
            },
        );
        let ((va, ta), (vb, tb)) = (ra?, rb?);
        for (name, secs) in [(names[0], ta), (names[1], tb)] {
            *self.timings.entry(name.to_string()).or_insert(0.0) += secs;
        }
        Ok((va, vb))
    }

    fn run<T>(
        &mut self,
        name: &str,
        fraction: f64,
        f: impl FnOnce() -> Result<T, CamError>,
    ) -> Result<T, CamError> {
        if (self.cancelled)() {
            return Err(CamError::Cancelled);
        }
        (self.progress)(fraction, name);
        let t = Instant::now();
        let r = f()?;
        *self.timings.entry(name.to_string()).or_insert(0.0) += t.elapsed().as_secs_f64();
        Ok(r)
    }
}

fn face_top(map: &HeightMap) -> Result<f64, CamError> {
    map.z_range_of_data().map(|(_, hi)| f64::from(hi)).ok_or_else(|| CamError::InvalidMap {
        message: format!("{}x{} map has no cell with data", map.width(), map.height()),
    })
}

/// `target` with each cell it has no data for set to `rough`'s height there (at most `top`, the
/// stock's top) where `rough` has one; `None` when there is no such cell or the grids differ.
fn standing_target(target: &HeightMap, rough: &HeightMap, top: f64) -> Option<HeightMap> {
    let (t, r) = (target.meta(), rough.meta());
    if (t.width, t.height) != (r.width, r.height)
        || t.pixel_mm != r.pixel_mm
        || t.origin_x_mm != r.origin_x_mm
        || t.origin_y_mm != r.origin_y_mm
    {
        return None;
    }
    let mut out: Option<HeightMap> = None;
    for (i, (z, h)) in target.data().iter().zip(rough.data()).enumerate() {
        if z.is_nan() && h.is_finite() {
            let m = out.get_or_insert_with(|| target.clone());
            m.data_mut()[i] = h.min(top as f32);
        }
    }
    out
}

/// Default roughing tool when the job names none.
const DEFAULT_ROUGHING: &str = "flat-6";
/// The rest pass leaves each cut at the feed for this far before a rapid, mm.
const REST_FEED_RETRACT_MM: f64 = 1.0;
/// Default finishing tool when the job names none.
const DEFAULT_FINISHING: &str = "ball-3";

/// Plans every face into one program (see [`plan_with`]), choosing the tools the job leaves
/// unnamed: the defaults (`flat-6`, `ball-3`) when they reach every point they visit, else, when
/// the shank or holder of one of them would touch the part (a pocket deeper than its flutes, a
/// wall higher than its stick-out), the library's tools of its kind with a longer reach, shortest
/// first, until one reaches. A tool the job names is never replaced. The plan report says what
/// was tried and why (`tool_choice`); when no tool reaches, the error is the last one's, naming
/// the tools tried, unless the job named no tool: then the maps are raised to what the last tools
/// tried reach ([`raise_to_reach`]) and the report says how much was left where.
pub fn plan(
    faces: &[FaceInput],
    options: &PlanOptions,
    library: &ToolLibrary,
    limits: &MachineLimits,
    progress: &(dyn Fn(f64, &str) + Sync),
    cancelled: &(dyn Fn() -> bool + Sync),
) -> Result<PlanOutput, CamError> {
    let rough_given = options.roughing.as_ref().is_some_and(|r| r.tool.is_some());
    let fin_given = options.finishing.as_ref().is_some_and(|f| f.tool.is_some());
    // Longer-reaching tools of the default's kind, shortest reach first.
    let longer = |default: &str| -> Result<Vec<String>, CamError> {
        let d = library.resolve(default)?;
        let reach = |t: &super::tool::Tool| t.cutting_length_mm.min(t.stickout_mm);
        let mut v: Vec<&super::tool::Tool> =
            library.tools().filter(|t| t.kind == d.kind && reach(t) > reach(&d)).collect();
        v.sort_by(|a, b| {
            reach(a).total_cmp(&reach(b)).then(a.profile.radius_mm().total_cmp(&b.profile.radius_mm()))
        });
        Ok(v.into_iter().map(|t| t.name.clone()).collect())
    };
    let mut rough_alts = if rough_given { Vec::new() } else { longer(DEFAULT_ROUGHING)? }.into_iter();
    let mut fin_alts = if fin_given { Vec::new() } else { longer(DEFAULT_FINISHING)? }.into_iter();
    let mut o = options.clone();
    let mut tried: Vec<String> = Vec::new();
    // Last resort when no tool of the library reaches: the maps raised to what the tools reach.
    let mut within_reach: Option<Vec<FaceInput>> = None;
    loop {
        let faces = within_reach.as_deref().unwrap_or(faces);
        let rough =
            o.roughing.as_ref().and_then(|r| r.tool.clone()).unwrap_or_else(|| DEFAULT_ROUGHING.into());
        let fin =
            o.finishing.as_ref().and_then(|f| f.tool.clone()).unwrap_or_else(|| DEFAULT_FINISHING.into());
        match plan_with(faces, &o, library, limits, progress, cancelled) {
            Ok(mut out) => {
                if !tried.is_empty() {
                    tried.push(format!(
                        "chose roughing {rough}, finishing {fin}: every point they visit is reachable"
                    ));
                    out.report.tool_choice = tried;
                }
                return Ok(out);
            }
            Err(CamError::HolderCollision { message, min_stickout_mm }) => {
                // The message names the tool that cannot reach: `tool <name>: ...`.
                let next = if message.starts_with(&format!("tool {fin}:")) {
                    fin_alts.next().map(|t| (false, t))
                } else if message.starts_with(&format!("tool {rough}:")) {
                    rough_alts.next().map(|t| (true, t))
                } else {
                    None
                };
                let Some((is_rough, tool)) = next else {
                    // Tools left to the CAM: machine what they reach and say what is left. A job
                    // that names its tools gets the error (and the hint) instead.
                    if within_reach.is_none()
                        && !(rough_given || fin_given)
                        && let Some((raised, notes)) = raise_to_reach(faces, &o, library)?
                    {
                        tried.push(format!("roughing {rough}, finishing {fin}: {message}"));
                        tried.extend(notes);
                        within_reach = Some(raised);
                        continue;
                    }
                    let failing = if message.starts_with(&format!("tool {fin}:")) { &fin } else { &rough };
                    let hint = reach_hint(library, failing, min_stickout_mm);
                    let message = if tried.is_empty() {
                        format!("{message}{hint}")
                    } else {
                        format!("{message} (also tried: {}){hint}", tried.join("; "))
                    };
                    return Err(CamError::HolderCollision { message, min_stickout_mm });
                };
                tried.push(format!("roughing {rough}, finishing {fin}: {message}"));
                if is_rough {
                    o.roughing.get_or_insert_with(Default::default).tool = Some(tool);
                } else {
                    o.finishing.get_or_insert_with(Default::default).tool = Some(tool);
                }
            }
            Err(e) => return Err(e),
        }
    }
}

/// A job's plan options resolved against the tool library and the machine's limits: every value
/// checked and defaulted, before any map is looked at.
struct Settings {
    stock: StockOptions,
    material: String,
    dialect: Dialect,
    rough_tool: super::tool::Tool,
    fin_tool: super::tool::Tool,
    step_down: f64,
    leave: f64,
    pattern: RoughingPattern,
    tolerance: f64,
    arcs: bool,
    /// What a depth-map cell means to the finishing tool.
    fin_model: PixelModel,
    fin_pattern: FinishingPattern,
    step_over: f64,
    rough_data: super::feeds::CuttingData,
    fin_data: super::feeds::CuttingData,
    rest: Option<RestSettings>,
    /// Least leftover reported as left material, mm.
    min_leftover: f64,
}

/// Rest finishing, resolved.
struct RestSettings {
    tool: super::tool::Tool,
    step_over: f64,
    data: super::feeds::CuttingData,
}

/// The faces with every cell deeper than the job's tools reach below the face's highest point
/// raised to that depth (the fluted length and the stick-out, whichever is shorter, less 0.5 mm),
/// and a note per face saying how much was raised and to what height; `None` when nothing is
/// deeper than that (the collision is elsewhere).
#[allow(clippy::type_complexity)]
fn raise_to_reach(
    faces: &[FaceInput],
    options: &PlanOptions,
    library: &ToolLibrary,
) -> Result<Option<(Vec<FaceInput>, Vec<String>)>, CamError> {
    let named = |t: Option<&String>, default: &str| library.resolve(t.map_or(default, String::as_str));
    let rough = named(options.roughing.as_ref().and_then(|r| r.tool.as_ref()), DEFAULT_ROUGHING)?;
    let fin = named(options.finishing.as_ref().and_then(|f| f.tool.as_ref()), DEFAULT_FINISHING)?;
    let reach =
        [&rough, &fin].iter().map(|t| t.cutting_length_mm.min(t.stickout_mm)).fold(f64::INFINITY, f64::min)
            - 0.5;
    if !(reach.is_finite() && reach > 0.0) {
        return Ok(None);
    }
    let mut out = Vec::with_capacity(faces.len());
    let mut notes = Vec::new();
    for (i, f) in faces.iter().enumerate() {
        let lowest = (face_top(&f.map)? - reach) as f32;
        // The floor too: outside the map and in cells without data the tools go down to the
        // map's lowest Z, which must be within reach as well.
        let raise = |m: &HeightMap| -> Result<(HeightMap, usize), CamError> {
            let mut r = m.clone();
            let mut n = 0;
            for z in r.data_mut() {
                if z.is_finite() && *z < lowest {
                    *z = lowest;
                    n += 1;
                }
            }
            let lo = r.z_min_mm().max(f64::from(lowest));
            let hi = r.z_max_mm().max(lo + 1e-3);
            r.set_z_range(lo, hi).map_err(|e| CamError::InvalidMap { message: e.to_string() })?;
            Ok((r, n))
        };
        let (map, n) = raise(&f.map)?;
        let roughing_map = f.roughing_map.as_ref().map(|m| raise(m).map(|r| r.0)).transpose()?;
        if n > 0 || f.map.z_min_mm() < f64::from(lowest) {
            let p = f.map.pixel_mm();
            notes.push(format!(
                "face {}: no tool reaches the whole depth; {:.1} mm² deeper than {reach:.1} mm below the part's top are left standing at Z {lowest:.3} mm (a longer tool, or another face, would reach them)",
                i + 1,
                n as f64 * p * p
            ));
        }
        out.push(FaceInput { a_deg: f.a_deg, map, roughing_map });
    }
    Ok((!notes.is_empty()).then_some((out, notes)))
}

/// Checks and resolves `options` (tools, material, dialect, strategies, steps) without any map:
/// what [`plan`] does first, and what the service's `ValidateParams` answers at submission. The
/// error names the field as in the job JSON (`plan.finishing.tool`, ...).
pub fn check_options(
    options: &PlanOptions,
    library: &ToolLibrary,
    limits: &MachineLimits,
) -> Result<(), CamError> {
    settings(options, library, limits).map(|_| ())
}

fn settings(
    options: &PlanOptions,
    library: &ToolLibrary,
    limits: &MachineLimits,
) -> Result<Settings, CamError> {
    let stock = options.stock.clone().unwrap_or_default();
    let rough = options.roughing.clone().unwrap_or_default();
    let fin = options.finishing.clone().unwrap_or_default();
    let material = stock.material.clone().unwrap_or_else(|| "aluminium".into());
    let dialect = match options.dialect.as_deref().unwrap_or("linuxcnc") {
        "linuxcnc" => Dialect::Linuxcnc,
        "fanuc" => Dialect::Fanuc,
        other => return Err(CamError::param("plan.dialect", format!("'{other}' is not linuxcnc or fanuc"))),
    };
    let tool_field = |field: &str, e: CamError| match e {
        CamError::InvalidTool { .. } => CamError::param(field, e.to_string()),
        other => other,
    };
    let rough_tool = library
        .resolve(rough.tool.as_deref().unwrap_or(DEFAULT_ROUGHING))
        .map_err(|e| tool_field("plan.roughing.tool", e))?;
    let fin_tool = library
        .resolve(fin.tool.as_deref().unwrap_or(DEFAULT_FINISHING))
        .map_err(|e| tool_field("plan.finishing.tool", e))?;
    let step_down = positive("plan.roughing.step_down_mm", rough.step_down_mm, 2.0)?;
    let leave = match rough.stock_to_leave_mm {
        None => 0.3,
        Some(x) if x.is_finite() && x >= 0.0 => x,
        Some(x) => {
            return Err(CamError::param("plan.roughing.stock_to_leave_mm", format!("must be >= 0, got {x}")));
        }
    };
    let pattern = match rough.direction.as_deref().unwrap_or("x") {
        "x" => RoughingPattern::X,
        "y" => RoughingPattern::Y,
        "contour" => RoughingPattern::Contour,
        other => {
            return Err(CamError::param(
                "plan.roughing.direction",
                format!("'{other}' is not x, y or contour"),
            ));
        }
    };
    let tolerance = positive("plan.finishing.tolerance_mm", fin.tolerance_mm, 0.01)?;
    let arcs = fin.arcs.unwrap_or(true);
    let fin_model = match fin.pixel_model.as_deref().unwrap_or("column") {
        "column" => PixelModel::Column,
        "point" => PixelModel::Point,
        "facet" => PixelModel::Facet,
        other => {
            return Err(CamError::param(
                "plan.finishing.pixel_model",
                format!("'{other}' is not column, point or facet"),
            ));
        }
    };
    let fin_pattern = match fin.strategy.as_deref().unwrap_or("raster_x") {
        "raster_x" => FinishingPattern::RasterX,
        "raster_y" => FinishingPattern::RasterY,
        "raster_angle" => FinishingPattern::RasterAngle { angle_deg: fin.angle_deg.unwrap_or(45.0) },
        "iso_level" => FinishingPattern::IsoLevel,
        other => {
            return Err(CamError::param(
                "plan.finishing.strategy",
                format!("'{other}' is not raster_x, raster_y, raster_angle or iso_level"),
            ));
        }
    };
    if fin.angle_deg.is_some() && !matches!(fin_pattern, FinishingPattern::RasterAngle { .. }) {
        return Err(CamError::param("plan.finishing.angle_deg", "applies only to strategy raster_angle"));
    }
    let step_over = match fin.step_over_mm {
        Some(_) => positive("plan.finishing.step_over_mm", fin.step_over_mm, 0.0)?,
        None => step_over_for_scallop(&fin_tool, 0.01)?,
    };
    let material_field = |e: CamError| match e {
        CamError::InvalidParameter { field, message } if field == "material" => {
            CamError::param("plan.stock.material", message)
        }
        other => other,
    };
    let rough_data = cutting_data(&rough_tool, &material, limits).map_err(material_field)?;
    let fin_data = cutting_data(&fin_tool, &material, limits).map_err(material_field)?;
    let rest_opts = options.rest.clone().unwrap_or_default();
    let min_leftover = match rest_opts.min_leftover_mm {
        None => super::rest::DEFAULT_MIN_LEFTOVER_MM,
        Some(v) if v.is_finite() && v > 0.0 && v <= 10.0 => v,
        Some(v) => {
            return Err(CamError::param(
                "plan.rest.min_leftover_mm",
                format!("must be in (0, 10] mm, got {v}"),
            ));
        }
    };
    let rest_tool = match (rest_opts.enabled.unwrap_or(false), &rest_opts.tool) {
        (false, _) => None,
        (true, Some(name)) => Some(library.resolve(name).map_err(|e| tool_field("plan.rest.tool", e))?),
        // The largest ball smaller than the finishing tool; of equal ones, the longest reach.
        (true, None) => library
            .tools()
            .filter(|t| {
                t.kind == super::tool::ToolKind::Ball && t.diameter_mm() < fin_tool.diameter_mm() - 1e-9
            })
            .max_by(|a, b| {
                a.diameter_mm().total_cmp(&b.diameter_mm()).then(
                    a.stickout_mm.min(a.cutting_length_mm).total_cmp(&b.stickout_mm.min(b.cutting_length_mm)),
                )
            })
            .cloned(),
    };
    let rest = match rest_tool {
        None => None,
        Some(tool) => {
            let data = cutting_data(&tool, &material, limits).map_err(material_field)?;
            // The finishing scallop with the smaller ball: the step-over scales with the diameter.
            let step_over = match fin.step_over_mm {
                Some(_) => step_over * tool.diameter_mm() / fin_tool.diameter_mm(),
                None => step_over_for_scallop(&tool, 0.01)?,
            };
            Some(RestSettings { tool, step_over, data })
        }
    };
    Ok(Settings {
        stock,
        material,
        dialect,
        rough_tool,
        fin_tool,
        step_down,
        leave,
        pattern,
        tolerance,
        arcs,
        fin_model,
        fin_pattern,
        step_over,
        rough_data,
        fin_data,
        rest,
        min_leftover,
    })
}

/// A suggestion for a tool that reaches `need_mm` below its holder: the smallest standard tool
/// of `failing`'s kind by diameter (`ball-D`, `flat-D`, `bull-D-r`: cutting length 3·D, stick-out
/// 4·D + 10 mm) that does, to name in the job. Empty for kinds without such a spec.
fn reach_hint(library: &ToolLibrary, failing: &str, need_mm: f64) -> String {
    let Ok(t) = library.resolve(failing) else { return String::new() };
    let kind = match t.kind {
        super::tool::ToolKind::Ball => "ball",
        super::tool::ToolKind::Flat => "flat",
        _ => return String::new(),
    };
    if !need_mm.is_finite() {
        return String::new();
    }
    // Stick-out 4·D + 10 >= need; cutting length 3·D >= need as well.
    let d = ((need_mm - 10.0) / 4.0).max(need_mm / 3.0).max(t.profile.radius_mm() * 2.0).ceil();
    format!(
        "; stick-out cannot be set in a job, but a standard tool reaches farther: {kind}-{d} (cutting length {} mm, stick-out {} mm) in plan.{}.tool",
        3.0 * d,
        4.0 * d + 10.0,
        if kind == "ball" { "finishing" } else { "roughing" }
    )
}

/// A pass of `tool` over what the stock model `preview` left (see [`super::rest`]): the region
/// where the stock stands more than `min_leftover` above the part and `tool`, visiting every
/// position of its tip surface `tip`, would take that much off; the tip positions over it where
/// the shank and holder clear the stock model; a `pattern` raster on `tip` cut to runs over those
/// positions, its strategy's name after `prefix`. The toolpath, its holder check and the region's size in cells, or
/// `Err(note)` saying why there is none.
#[allow(clippy::too_many_arguments, clippy::type_complexity)]
fn pass_over_leftover(
    map: &HeightMap,
    tool: &super::tool::Tool,
    tip: &HeightMap,
    preview: &PreviewReport,
    min_leftover: f64,
    pattern: FinishingPattern,
    step_over: f64,
    safe_z: f64,
    opts: &CompensateOptions,
    prefix: &str,
) -> Result<Result<(Toolpath, super::holder::HolderCheck, usize), String>, CamError> {
    use super::rest::{MIN_REGION_CELLS, envelope, positions, region, restrict};
    let k = super::compensate::kernel(&tool.profile, map.pixel_mm(), opts.pixel_model);
    let reg = region(preview.final_surface.data(), map, &envelope(tip, &k), min_leftover);
    let cells = reg.iter().filter(|r| **r).count();
    if cells < MIN_REGION_CELLS {
        return Ok(Err(format!(
            "nothing stands more than {min_leftover} mm above the part that {} would take off",
            tool.name
        )));
    }
    let mut pos = positions(&reg, map.width() as usize, map.height() as usize, &k);
    // Only where the shank and the holder clear what is there: the highest point of the stock
    // model (the part plus what the operations before left) under each (flat disks of their
    // diameters) must stay below the tip plus the fluted length and the stick-out, with a
    // margin of 0.1 mm.
    let clear = |d: f64, reach: f64| -> Result<Vec<bool>, CamError> {
        let profile = depthmill_geometry::ToolProfile::flat(d.max(tool.diameter_mm()))
            .map_err(|e| CamError::param("tool", e.to_string()))?;
        let under = compensate(&preview.final_surface, &profile, opts)?;
        Ok(under.data().iter().zip(tip.data()).map(|(u, t)| f64::from(u - t) < reach - 0.1).collect())
    };
    let shank = clear(tool.shank_diameter_mm, tool.cutting_length_mm)?;
    let holder = clear(tool.holder_diameter_mm, tool.stickout_mm)?;
    for ((p, s), h) in pos.iter_mut().zip(&shank).zip(&holder) {
        *p &= *s && *h;
    }
    let full = finishing(
        tip,
        tool,
        &FinishingParams {
            pattern,
            step_over_mm: step_over,
            level_step_mm: step_over,
            zigzag: true,
            safe_z_mm: safe_z,
        },
    )?;
    let strategy = format!("{prefix}{}", full.strategy);
    let path = restrict(full, &pos, tip, &strategy);
    if path.passes.is_empty() {
        return Ok(Err(format!("no {} pass line crosses the region", tool.name)));
    }
    let points: Vec<Point3<f64>> = path.passes.iter().flat_map(|p| p.points.iter().copied()).collect();
    match check_holder(map, tool, tip, &points, opts.outside_z_mm.unwrap_or(map.z_min_mm())) {
        Ok(h) => Ok(Ok((path, h, cells))),
        Err(CamError::HolderCollision { message, .. }) => Ok(Err(message)),
        Err(e) => Err(e),
    }
}

/// Plans every face into one program. `progress` gets the fraction done and the step's name;
/// `cancelled` is polled between steps.
fn plan_with(
    faces: &[FaceInput],
    options: &PlanOptions,
    library: &ToolLibrary,
    limits: &MachineLimits,
    progress: &(dyn Fn(f64, &str) + Sync),
    cancelled: &(dyn Fn() -> bool + Sync),
) -> Result<PlanOutput, CamError> {
    if faces.is_empty() {
        return Err(CamError::param("faces", "no depth map to plan"));
    }
    let Settings {
        stock,
        material,
        dialect,
        rough_tool,
        fin_tool,
        step_down,
        leave,
        pattern,
        tolerance,
        arcs,
        fin_model,
        fin_pattern,
        step_over,
        rough_data,
        fin_data,
        rest,
        min_leftover,
    } = settings(options, library, limits)?;

    let mut steps = Steps { progress, cancelled, timings: Default::default() };
    let mut programs = Vec::new();
    let mut face_reports = Vec::new();
    let mut first_preview = None;
    let mut later_surfaces = Vec::new();
    let mut total_time = 0.0;
    let per_face = 1.0 / faces.len() as f64;
    for (fi, face) in faces.iter().enumerate() {
        let base = fi as f64 * per_face;
        // The depth map: what the preview measures against.
        let target = &face.map;
        let floor = target.z_min_mm();
        let top = match stock.z_mm {
            Some(z) if z.is_finite() && z > 0.0 => floor + z,
            Some(z) => return Err(CamError::param("plan.stock.z_mm", format!("must be positive, got {z}"))),
            None => face_top(target)?,
        };
        if top < face_top(target)? - 1e-9 {
            return Err(CamError::param(
                "plan.stock.z_mm",
                format!(
                    "stock top {top:.3} mm is below the part's highest point {:.3} mm",
                    face_top(target)?
                ),
            ));
        }
        for (field, given, need) in [
            ("plan.stock.x_mm", stock.x_mm, target.meta().width_mm()),
            ("plan.stock.y_mm", stock.y_mm, target.meta().height_mm()),
        ] {
            if let Some(g) = given
                && g + 1e-9 < need
            {
                return Err(CamError::param(
                    field,
                    format!("stock of {g} mm is smaller than the depth map's {need:.3} mm"),
                ));
            }
        }
        let safe_z = top + 5.0;
        let rough_map = face.roughing_map.as_ref().unwrap_or(target);
        // What finishing and rest machining follow: the depth map, with the cells it has no data
        // for standing at the roughing map's height where that keeps material (nobody saw them
        // and no ray showed them empty), so they are not read as the floor and cut.
        let standing = face.roughing_map.as_ref().and_then(|r| standing_target(target, r, top));
        let map = standing.as_ref().unwrap_or(target);

        let opts = CompensateOptions { pixel_model: PixelModel::Column, outside_z_mm: Some(floor) };
        // The finishing target read as the job says (columns, or samples of a continuous surface).
        let fin_opts = CompensateOptions { pixel_model: fin_model, ..opts };
        // Roughing (and its tool's tip surface, for the holder check) beside the finishing tool's
        // tip surface and passes.
        let ((rough_path, rough_tip), (tip, fin_path)) = steps.run_pair(
            base + 0.05 * per_face,
            ["roughing", "finishing"],
            || {
                Ok((
                    roughing(
                        rough_map,
                        &rough_tool,
                        &RoughingParams {
                            step_down_mm: step_down,
                            stock_to_leave_mm: leave,
                            step_over_mm: 0.4 * rough_tool.diameter_mm(),
                            pattern,
                            stock_top_mm: top,
                            floor_mm: floor,
                            safe_z_mm: safe_z,
                        },
                    )?,
                    compensate(map, &rough_tool.profile, &opts)?,
                ))
            },
            || {
                let tip = compensate(map, &fin_tool.profile, &fin_opts)?;
                let fin_path = finishing(
                    &tip,
                    &fin_tool,
                    &FinishingParams {
                        pattern: fin_pattern,
                        step_over_mm: step_over,
                        level_step_mm: step_over,
                        zigzag: true,
                        safe_z_mm: safe_z,
                    },
                )?;
                Ok((tip, fin_path))
            },
        )?;
        let mut fin_path = fin_path;
        let holders = steps.run("holder", base + 0.55 * per_face, || {
            let points = |t: &Toolpath| {
                t.passes.iter().flat_map(|p| p.points.iter().copied()).collect::<Vec<Point3<f64>>>()
            };
            let (rough, fin) = rayon::join(
                || check_holder(map, &rough_tool, &rough_tip, &points(&rough_path), floor),
                || check_holder(map, &fin_tool, &tip, &points(&fin_path), floor),
            );
            Ok((rough?, fin?))
        })?;
        let (rough_segs, mut fin_segs) = steps.run("cleanup", base + 0.6 * per_face, || {
            Ok((
                super::cleanup::link(&rough_path, tolerance, arcs),
                super::cleanup::link(&fin_path, tolerance, arcs),
            ))
        })?;
        let start = Point3::new(map.origin_x_mm(), map.origin_y_mm(), safe_z);
        // The stock model: roughing, finishing and, when there is one, the rest pass swept in turn.
        let sweep = |fin_segs: &[Segment], rest: Option<(&super::tool::Tool, &[Segment])>| {
            let fin_start = rough_segs.last().map_or(start, Segment::end);
            let mut ops = vec![
                SweptOp { tool: &rough_tool, start, segments: &rough_segs },
                SweptOp { tool: &fin_tool, start: fin_start, segments: fin_segs },
            ];
            if let Some((tool, segments)) = rest {
                ops.push(SweptOp { tool, start: fin_segs.last().map_or(fin_start, Segment::end), segments });
            }
            simulate(target, top, &ops)
        };
        let mut preview = steps.run("preview", base + 0.7 * per_face, || sweep(&fin_segs, None))?;
        // Iso-level contours step over flat areas wider than the tool: a raster over what the
        // stock model shows they left, with the same tool (no tool change).
        if matches!(fin_pattern, FinishingPattern::IsoLevel) {
            let flats = steps.run("flats", base + 0.75 * per_face, || {
                let raster = FinishingPattern::RasterX;
                pass_over_leftover(
                    map,
                    &fin_tool,
                    &tip,
                    &preview,
                    min_leftover,
                    raster,
                    step_over,
                    safe_z,
                    &fin_opts,
                    "",
                )
            })?;
            match flats {
                Err(note) => tracing::debug!(note, "no flats pass"),
                Ok((flats, ..)) => {
                    fin_path.passes.extend(flats.passes);
                    fin_segs = super::cleanup::link(&fin_path, tolerance, arcs);
                    preview = steps.run("preview", base + 0.78 * per_face, || sweep(&fin_segs, None))?;
                }
            }
        }
        // Rest finishing where the stock model says finishing left material.
        let mut rest_report = None;
        let mut rest_note = None;
        let mut rest_op = None;
        if let Some(rs) = &rest {
            let rest_pattern = match fin_pattern {
                FinishingPattern::IsoLevel => FinishingPattern::RasterX,
                p => p,
            };
            let planned = steps.run("rest", base + 0.8 * per_face, || {
                let rest_tip = compensate(map, &rs.tool.profile, &opts)?;
                pass_over_leftover(
                    map,
                    &rs.tool,
                    &rest_tip,
                    &preview,
                    min_leftover,
                    rest_pattern,
                    rs.step_over,
                    safe_z,
                    &opts,
                    "rest-",
                )
            })?;
            match planned {
                Err(note) => rest_note = Some(format!("no rest pass: {note}")),
                Ok((path, holder, region_cells)) => {
                    let segs = super::cleanup::feed_retracts(
                        super::cleanup::link(&path, tolerance, arcs),
                        REST_FEED_RETRACT_MM,
                    );
                    let before = (preview.max_leftover_mm, preview.mean_leftover_mm);
                    preview = steps.run("preview", base + 0.9 * per_face, || {
                        sweep(&fin_segs, Some((&rs.tool, &segs)))
                    })?;
                    rest_report = Some(RestReport {
                        tool: rs.tool.name.clone(),
                        region_mm2: region_cells as f64 * map.pixel_mm() * map.pixel_mm(),
                        max_leftover_before_mm: before.0,
                        mean_leftover_before_mm: before.1,
                    });
                    rest_op = Some((3u32, path, segs, &rs.tool, rs.data.clone(), holder, rs.step_over));
                }
            }
        }
        let left_regions = left_regions(&preview.leftover, min_leftover, 5);
        let mut ops_report = Vec::new();
        let mut operations = Vec::new();
        let mut prev_end = start;
        let mut ops = vec![
            (
                1u32,
                rough_path,
                rough_segs,
                &rough_tool,
                rough_data.clone(),
                holders.0,
                0.4 * rough_tool.diameter_mm(),
            ),
            (2u32, fin_path, fin_segs, &fin_tool, fin_data.clone(), holders.1, step_over),
        ];
        ops.extend(rest_op);
        // Each operation's time from where the one before ends, the operations side by side.
        let starts: Vec<Point3<f64>> = ops
            .iter()
            .map(|op| {
                let s = prev_end;
                prev_end = op.2.last().map_or(prev_end, Segment::end);
                s
            })
            .collect();
        let times: Vec<f64> = ops
            .par_iter()
            .zip(&starts)
            .map(|(op, &from)| estimate_time_s(from, &op.2, &op.4, limits))
            .collect();
        for ((number, path, segs, tool, data, holder, so), time) in ops.into_iter().zip(times) {
            total_time += time;
            let (lines, arcs_n) = segs.iter().fold((0, 0), |(l, a), s| match s {
                Segment::Arc { .. } => (l, a + 1),
                _ => (l + 1, a),
            });
            ops_report.push(OperationReport {
                strategy: path.strategy.clone(),
                tool: tool.name.clone(),
                tool_number: number,
                step_over_mm: so,
                passes: path.passes.len(),
                points: path.point_count(),
                lines,
                arcs: arcs_n,
                spindle_rpm: data.spindle_rpm,
                feed_mm_min: data.feed_mm_min,
                min_stickout_mm: holder.min_stickout_mm,
                holder_clearance_mm: holder.clearance_mm.is_finite().then_some(holder.clearance_mm),
                estimated_time_s: time,
            });
            operations.push(Operation {
                tool: tool.clone(),
                tool_number: number,
                data,
                segments: segs,
                comment: format!("{} with {}", path.strategy, tool.name),
            });
        }
        face_reports.push(FaceReport {
            a_deg: face.a_deg,
            width: map.width(),
            height: map.height(),
            pixel_mm: map.pixel_mm(),
            stock_top_mm: top,
            floor_mm: floor,
            operations: ops_report,
            max_gouge_mm: preview.max_gouge_mm,
            gouge_at_mm: preview.gouge_at_mm,
            max_leftover_mm: preview.max_leftover_mm,
            mean_leftover_mm: preview.mean_leftover_mm,
            rest: rest_report,
            rest_note,
            left_regions,
        });
        programs.push(FaceProgram { a_deg: face.a_deg, operations });
        if first_preview.is_none() {
            first_preview = Some(preview);
        } else {
            later_surfaces.push(preview.final_surface);
        }
    }
    let info = ProgramInfo {
        title: "depthmill".into(),
        lines: vec![
            format!("material {material}"),
            format!(
                "tolerance {tolerance} mm, finishing pixel model {}",
                match fin_model {
                    PixelModel::Column => "column",
                    PixelModel::Point => "point",
                    PixelModel::Facet => "facet",
                }
            ),
            format!("roughing step-down {step_down} mm, stock to leave {leave} mm"),
            format!("finishing step-over {step_over:.4} mm"),
        ],
    };
    let gcode = steps.run("gcode", 0.95, || Ok(write_program(&info, &programs, dialect)))?;
    // Every line of the program ends in a newline.
    let blocks = gcode.bytes().filter(|&b| b == b'\n').count();
    progress(1.0, "done");
    let preview = first_preview.ok_or_else(|| CamError::param("faces", "no depth map to plan"))?;
    Ok(PlanOutput {
        gcode,
        report: PlanReport {
            dialect: options.dialect.clone().unwrap_or_else(|| "linuxcnc".into()),
            pixel_model: fin_model,
            tolerance_mm: tolerance,
            material,
            faces: face_reports,
            blocks,
            estimated_time_s: total_time,
            timings_s: steps.timings,
            tool_choice: Vec::new(),
        },
        preview,
        later_surfaces,
    })
}

#[cfg(test)]
mod tests {
    use depthmill_geometry::{HeightMap, HeightMapMeta};

    use super::*;
    use crate::domain::tool::ToolLibrary;

    /// A 40 x 40 mm plate 30 mm high with a 20 mm wide slot down to 0 across it (0.5 mm cells).
    fn slotted_plate() -> HeightMap {
        let n = 80u32;
        let meta = HeightMapMeta { z_min_mm: 0.0, z_max_mm: 30.0, ..HeightMapMeta::new(n, n, 0.5) };
        let data =
            (0..n * n).map(|i| if ((i % n) as f64 * 0.5 - 20.0).abs() < 10.0 { 0.0 } else { 30.0 }).collect();
        HeightMap::new(meta, data).expect("valid map")
    }

    fn run(options: &PlanOptions) -> Result<PlanOutput, CamError> {
        let faces = [FaceInput { a_deg: None, map: slotted_plate(), roughing_map: None }];
        let library = ToolLibrary::builtin()?;
        plan(&faces, options, &library, &MachineLimits::emco_f1(), &|_, _| {}, &|| false)
    }

    #[test]
    fn cells_without_a_target_stand_where_the_roughing_map_keeps_material() {
        // A 6 mm plateau over x < 10 mm on a 20 x 10 mm map at 0.25 mm, floor 0; the depth map has
        // no data over x in [10, 16) mm (a side nobody saw), the roughing map keeps it at 6 mm
        // there; beyond x = 16 mm both are 1 mm.
        let (w, h) = (80u32, 40u32);
        let meta = HeightMapMeta { z_min_mm: 0.0, z_max_mm: 8.0, ..HeightMapMeta::new(w, h, 0.25) };
        let x = |i: u32| (f64::from(i % w) + 0.5) * 0.25;
        let depth: Vec<f32> = (0..w * h)
            .map(|i| match x(i) {
                v if v < 10.0 => 6.0,
                v if v < 16.0 => f32::NAN,
                _ => 1.0,
            })
            .collect();
        let rough: Vec<f32> = (0..w * h).map(|i| if x(i) < 16.0 { 6.0 } else { 1.0 }).collect();
        let map = HeightMap::new(meta, depth).expect("depth map");
        let roughing_map = Some(HeightMap::new(meta, rough).expect("roughing map"));
        let library = ToolLibrary::builtin().expect("library");
        let options = PlanOptions {
            stock: Some(StockOptions { z_mm: Some(7.0), ..Default::default() }),
            finishing: Some(FinishingOptions { step_over_mm: Some(0.5), ..Default::default() }),
            ..Default::default()
        };
        let run = |roughing_map: Option<HeightMap>| {
            let faces = [FaceInput { a_deg: None, map: map.clone(), roughing_map }];
            plan(&faces, &options, &library, &MachineLimits::emco_f1(), &|_, _| {}, &|| false)
                .expect("planned")
                .preview
                .final_surface
        };
        let lowest_unseen = |surface: &HeightMap| {
            (0..w * h)
                .filter(|&i| (10.0..16.0).contains(&x(i)))
                .map(|i| surface.data()[i as usize])
                .fold(f32::INFINITY, f32::min)
        };
        // With the roughing map the unseen cells keep its height (the tool stays off them); the
        // depth map alone reads them as the floor and finishing cuts them.
        let kept = lowest_unseen(&run(roughing_map));
        assert!(kept > 6.0 - 0.01, "unseen cells cut to {kept} mm");
        let cut = lowest_unseen(&run(None));
        assert!(cut < 1.0, "without a roughing map the unseen cells are the floor: {cut} mm");
    }

    #[test]
    fn point_and_facet_targets_stand_off_a_slope_less_than_columns_and_a_bad_model_is_named() {
        // A 20° slope on 0.25 mm cells, from 2 to 9 mm over 20 mm.
        let n = 80u32;
        let meta = HeightMapMeta { z_min_mm: 0.0, z_max_mm: 12.0, ..HeightMapMeta::new(n, n, 0.25) };
        let slope = 20f64.to_radians().tan();
        let data = (0..n * n).map(|i| (2.0 + slope * ((i % n) as f64 + 0.5) * 0.25) as f32).collect();
        let map = HeightMap::new(meta, data).expect("valid map");
        let library = ToolLibrary::builtin().expect("library");
        let leftover = |model: &str| {
            let options = PlanOptions {
                stock: Some(StockOptions { z_mm: Some(12.0), ..Default::default() }),
                finishing: Some(FinishingOptions {
                    step_over_mm: Some(0.25),
                    pixel_model: Some(model.into()),
                    ..Default::default()
                }),
                ..Default::default()
            };
            let faces = [FaceInput { a_deg: None, map: map.clone(), roughing_map: None }];
            let out = plan(&faces, &options, &library, &MachineLimits::emco_f1(), &|_, _| {}, &|| false)
                .expect("planned");
            let want = match model {
                "point" => PixelModel::Point,
                "facet" => PixelModel::Facet,
                _ => PixelModel::Column,
            };
            assert_eq!(out.report.pixel_model, want);
            (out.preview.mean_leftover_mm, out.preview.max_gouge_mm)
        };
        let (column, column_gouge) = leftover("column");
        let (point, point_gouge) = leftover("point");
        let (facet, facet_gouge) = leftover("facet");
        // Columns stand off by up to the slope times half a pixel (0.045 mm here); points and
        // facets read a plane as it is.
        assert!(column > point + 0.02, "mean leftover: column {column}, point {point}");
        assert!((facet - point).abs() < 5e-3, "mean leftover: facet {facet}, point {point}");
        for g in [column_gouge, point_gouge, facet_gouge] {
            assert!(g < 5e-3, "gouges {column_gouge} {point_gouge} {facet_gouge}");
        }
        let bad = PlanOptions {
            finishing: Some(FinishingOptions { pixel_model: Some("voxel".into()), ..Default::default() }),
            ..Default::default()
        };
        match check_options(&bad, &library, &MachineLimits::emco_f1()) {
            Err(CamError::InvalidParameter { field, message }) => {
                assert_eq!(field, "plan.finishing.pixel_model");
                assert!(message.contains("voxel"), "{message}");
            }
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn a_tool_left_unnamed_that_cannot_reach_is_replaced_by_one_that_can() {
        let coarse = FinishingOptions { step_over_mm: Some(2.0), ..Default::default() };
        // ball-3 sticks out 25 mm from its holder; the slot is 30 mm deep: ball-6 (35 mm) is
        // chosen, and the report says why.
        let out =
            run(&PlanOptions { finishing: Some(coarse.clone()), ..Default::default() }).expect("planned");
        let ops = &out.report.faces[0].operations;
        assert_eq!((ops[0].tool.as_str(), ops[1].tool.as_str()), ("flat-6", "ball-6"));
        assert!(
            out.report.tool_choice.first().is_some_and(|t| t.contains("ball-3")),
            "{:?}",
            out.report.tool_choice
        );
        assert!(out.report.tool_choice.last().is_some_and(|t| t.contains("chose") && t.contains("ball-6")));
        // A tool the job names is kept, and its error stands.
        let named = FinishingOptions { tool: Some("ball-3".into()), ..coarse };
        let e = run(&PlanOptions { finishing: Some(named), ..Default::default() })
            .err()
            .expect("ball-3 cannot reach");
        assert!(matches!(e, CamError::HolderCollision { .. }), "{e}");
        assert!(e.to_string().contains("ball-3") && !e.to_string().contains("also tried"), "{e}");
        // Tools and materials are checked before any map, naming the job's field.
        let bad = PlanOptions {
            finishing: Some(FinishingOptions { tool: Some("ball-3x".into()), ..Default::default() }),
            ..Default::default()
        };
        let library = ToolLibrary::builtin().expect("library");
        match check_options(&bad, &library, &MachineLimits::emco_f1()) {
            Err(CamError::InvalidParameter { field, message }) => {
                assert_eq!(field, "plan.finishing.tool");
                assert!(message.contains("ball-3x"), "{message}");
            }
            other => panic!("{other:?}"),
        }
        let bad = PlanOptions {
            stock: Some(StockOptions { material: Some("cheese".into()), ..Default::default() }),
            ..Default::default()
        };
        assert!(matches!(
            check_options(&bad, &library, &MachineLimits::emco_f1()),
            Err(CamError::InvalidParameter { field, .. }) if field == "plan.stock.material"
        ));
        assert!(check_options(&PlanOptions::default(), &library, &MachineLimits::emco_f1()).is_ok());
        // The error says which standard tool would reach: 30 mm under the holder takes ball-10.
        assert!(e.to_string().contains("ball-10 (cutting length 30 mm, stick-out 50 mm)"), "{e}");
    }

    #[test]
    fn rest_finishing_takes_what_the_finishing_ball_left_in_the_corners() {
        // A 40 x 40 mm plate 6 mm high with a 12 mm slot 2.5 mm deep (0.25 mm cells; ball-1 has 3
        // mm of flutes): ball-3 leaves a fillet along the slot's foot, ball-1 most of it.
        let n = 160u32;
        let meta = HeightMapMeta { z_min_mm: 0.0, z_max_mm: 6.0, ..HeightMapMeta::new(n, n, 0.25) };
        let data =
            (0..n * n).map(|i| if ((i % n) as f64 * 0.25 - 20.0).abs() < 6.0 { 3.5 } else { 6.0 }).collect();
        let map = HeightMap::new(meta, data).expect("map");
        let library = ToolLibrary::builtin().expect("library");
        let options = |rest: Option<RestOptions>| PlanOptions {
            finishing: Some(FinishingOptions { step_over_mm: Some(0.5), ..Default::default() }),
            rest,
            ..Default::default()
        };
        let go = |o: &PlanOptions| {
            let faces = [FaceInput { a_deg: None, map: map.clone(), roughing_map: None }];
            plan(&faces, o, &library, &MachineLimits::emco_f1(), &|_, _| {}, &|| false)
        };
        let with =
            go(&options(Some(RestOptions { enabled: Some(true), ..Default::default() }))).expect("planned");
        let f = &with.report.faces[0];
        let rest = f.rest.as_ref().unwrap_or_else(|| panic!("no rest pass: {:?}", f.rest_note));
        assert_eq!(rest.tool, "ball-1");
        assert!(rest.region_mm2 > 10.0, "{rest:?}");
        assert_eq!(f.operations.len(), 3);
        assert_eq!((f.operations[2].tool_number, f.operations[2].tool.as_str()), (3, "ball-1"));
        assert!(f.operations[2].strategy.starts_with("rest-finishing"), "{}", f.operations[2].strategy);
        assert!(with.gcode.contains("T3 M6"));
        // The stock model after the rest pass: less left, nothing gouged.
        assert!(f.max_leftover_mm < rest.max_leftover_before_mm - 0.2, "{} vs {rest:?}", f.max_leftover_mm);
        assert!(f.mean_leftover_mm < rest.mean_leftover_before_mm, "{} vs {rest:?}", f.mean_leftover_mm);
        assert!(f.max_gouge_mm < 1e-3, "gouge {}", f.max_gouge_mm);
        // What even ball-1 leaves is reported where it is: along the slot's two feet.
        assert!(f.left_regions.iter().all(|r| r.max_leftover_mm <= f.max_leftover_mm + 1e-6));
        // Off (the default): two operations.
        let off = go(&options(None)).expect("planned");
        let f = &off.report.faces[0];
        assert_eq!(f.operations.len(), 2);
        assert!(f.rest.is_none() && f.rest_note.is_none());
        assert!(!off.gcode.contains("T3 M6"));
        // A bad rest tool or threshold names its field.
        for (rest, field) in [
            (
                RestOptions { enabled: Some(true), tool: Some("ball-3x".into()), ..Default::default() },
                "plan.rest.tool",
            ),
            (RestOptions { min_leftover_mm: Some(0.0), ..Default::default() }, "plan.rest.min_leftover_mm"),
        ] {
            match check_options(&options(Some(rest)), &library, &MachineLimits::emco_f1()) {
                Err(CamError::InvalidParameter { field: f, .. }) => assert_eq!(f, field),
                other => panic!("{field}: {other:?}"),
            }
        }
    }

    #[test]
    fn iso_level_finishing_also_finishes_the_flats_between_its_contours() {
        // A 30 x 30 mm plate 2 mm high with a dome up to 8 mm in the middle (0.25 mm cells).
        let n = 120u32;
        let meta = HeightMapMeta { z_min_mm: 0.0, z_max_mm: 8.0, ..HeightMapMeta::new(n, n, 0.25) };
        let map = HeightMap::from_fn(meta, |c, r| {
            let (x, y) = (f64::from(c) * 0.25 - 15.0, f64::from(r) * 0.25 - 15.0);
            (2.0 + (36.0 - x * x - y * y).max(0.0).sqrt()) as f32
        })
        .expect("map");
        let library = ToolLibrary::builtin().expect("library");
        let options = PlanOptions {
            finishing: Some(FinishingOptions {
                strategy: Some("iso_level".into()),
                step_over_mm: Some(0.5),
                ..Default::default()
            }),
            rest: Some(RestOptions { enabled: Some(false), ..Default::default() }),
            ..Default::default()
        };
        let faces = [FaceInput { a_deg: None, map: map.clone(), roughing_map: None }];
        let out =
            plan(&faces, &options, &library, &MachineLimits::emco_f1(), &|_, _| {}, &|| false).expect("plan");
        let f = &out.report.faces[0];
        assert_eq!(f.operations.len(), 2);
        assert_eq!(f.operations[1].strategy, "finishing-iso-level");
        // The preview samples moves at half a pixel: a few µm of apparent gouge on the dome.
        assert!(f.max_gouge_mm < 5e-3, "gouge {}", f.max_gouge_mm);
        // The flat ring between the dome and the plate's edge comes out within the threshold
        // (the roughing left 0.3 mm there, which no contour crosses).
        let left = &out.preview.leftover;
        let mut worst = 0f32;
        for r in 0..n {
            for c in 0..n {
                let (x, y) = (f64::from(c) * 0.25 - 15.0, f64::from(r) * 0.25 - 15.0);
                let d = (x * x + y * y).sqrt();
                if d > 8.0 && x.abs() < 13.0 && y.abs() < 13.0 {
                    worst = worst.max(left.get(c, r).unwrap_or(0.0));
                }
            }
        }
        assert!(worst <= 0.06, "flat left {worst} mm above the part");
    }

    #[test]
    fn tools_left_to_the_cam_machine_what_they_reach_when_none_reaches_everything() {
        // A 70 mm deep, 20 mm wide slot: deeper than any ball of the library reaches.
        let n = 80u32;
        let meta = HeightMapMeta { z_min_mm: 0.0, z_max_mm: 70.0, ..HeightMapMeta::new(n, n, 0.5) };
        let data =
            (0..n * n).map(|i| if ((i % n) as f64 * 0.5 - 20.0).abs() < 10.0 { 0.0 } else { 70.0 }).collect();
        let map = HeightMap::new(meta, data).expect("map");
        let library = ToolLibrary::builtin().expect("library");
        let faces = [FaceInput { a_deg: None, map, roughing_map: None }];
        let coarse = FinishingOptions { step_over_mm: Some(2.0), ..Default::default() };
        let out = plan(
            &faces,
            &PlanOptions { finishing: Some(coarse.clone()), ..Default::default() },
            &library,
            &MachineLimits::emco_f1(),
            &|_, _| {},
            &|| false,
        )
        .expect("planned within reach");
        let note =
            out.report.tool_choice.iter().find(|t| t.contains("left standing")).cloned().unwrap_or_default();
        assert!(note.contains("face 1") && note.contains("mm²"), "{:?}", out.report.tool_choice);
        assert!(out.report.faces[0].max_gouge_mm < 0.05);
        // Named tools: the error stands.
        let named = PlanOptions {
            finishing: Some(FinishingOptions { tool: Some("ball-6".into()), ..coarse }),
            ..Default::default()
        };
        let e = plan(&faces, &named, &library, &MachineLimits::emco_f1(), &|_, _| {}, &|| false)
            .err()
            .expect("error");
        assert!(matches!(e, CamError::HolderCollision { .. }), "{e}");
    }
}
