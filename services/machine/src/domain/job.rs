//! The execute stage as a library call: a program (re-openable, it is read in several passes,
//! each streaming), the job's `execute` options and an optional target depth map in; the final
//! stock, the deviation from the target, telemetry (CSV and an SVG plot) and a report out.
//!
//! Passes: (1) the tool list of the program's header comments (`(T1 flat-6: flat D6.0000 mm, 2
//! flutes - ...)`, what the CAM service writes) merged over the machine's tool table; (2) a
//! motion-only run with the programmed feeds: every line is checked against the travel, feed,
//! speed and tool table before anything is cut, and its cycle time is the one without
//! adaptation; (3) the run with the chosen policy (material removal, telemetry) and, in
//! parallel, the other adaptive policy on the same program for comparison.
//!
//! The stock: given, or from the target map exactly as the CAM service sized it (the map's extent,
//! bottom at its `z_min`, top at `z_min + stock_z_mm` or at the highest point), or, with neither,
//! the XY extent of the program's feed moves plus the largest tool radius, from 1 mm below the
//! deepest feed move up to Z 0 (the common hand-written convention: work Z 0 on the stock top).

use std::io::BufRead;
use std::sync::Arc;

use depthmill_geometry::nalgebra::{Point3, Vector3};
use depthmill_geometry::{HeightMap, HeightMapMeta, ToolProfile, ToolSpec};
use depthmill_report::plot::{Chart, Panel, Series};
use rayon::prelude::*;
use serde::Serialize;

use super::cutting::{Material, material, materials};
use super::dexel::DexelCells;
use super::dexel::surface::MAX_SURFACE_SAMPLES;
use super::gcode::{Canon, InterpConfig, run};
use super::part::{MeasureFace, PartDeviation, measure, vertex_deviation};
use super::profile::MachineProfile;
use super::sim::{
    Inclusion, MachineTool, PolicyKind, SimError, SimReport, SimSetup, StockSpec, TelemetryRow, active_names,
    simulate, simulate_stock,
};

/// A box as (min, max) corners.
type Extent = ([f64; 3], [f64; 3]);

/// Default cell of the Z-map and of the dexel grids, mm.
pub const DEFAULT_CELL_MM: f64 = 0.1;

/// The `execute` object of a job, plus what the CLI can give.
#[derive(Debug, Clone)]
pub struct ExecuteOptions {
    pub machine: String,
    pub policy: PolicyKind,
    pub material: Option<String>,
    /// Stock height above the target map's `z_min`.
    pub stock_z_mm: Option<f64>,
    /// Explicit stock (work frame), overriding the target-derived one.
    pub stock: Option<StockSpec>,
    pub cell_mm: Option<f64>,
    pub clamp: bool,
    pub inclusions: Vec<Inclusion>,
    /// Also run the comparison policies (cycle times with and without adaptation).
    pub compare: bool,
    pub seed: u64,
    /// Cell sizes of the dexel grids of a multi-axis part (every grid at the cell size when
    /// `None`).
    pub dexel: Option<DexelCells>,
    /// The original part, which a multi-axis part's simulated stock is measured against.
    pub reference: Option<Arc<Reference>>,
}

/// Points on the original part's surface in the part frame (see [`super::part`]).
#[derive(Debug, Clone)]
pub struct Reference {
    /// What they are, for the report (e.g. `point_cloud`, `mesh`).
    pub source: String,
    pub points: Vec<nalgebra::Point3<f64>>,
}

/// Lattice samples of the simulated part's mesh in the report's 3-D view (2^20: about 100 per
/// side).
pub const VIEW_SAMPLES: u64 = 1 << 20;

/// The simulated part's meshes.
#[derive(Debug, Clone, Serialize)]
pub struct PartMesh {
    /// The STL's lattice step and size.
    pub step_mm: f64,
    pub triangles: usize,
    /// Volume the mesh encloses, and the dexels' own volume.
    pub volume_mm3: f64,
    pub dexel_volume_mm3: f64,
    /// The view mesh's step and size.
    pub view_step_mm: f64,
    pub view_triangles: usize,
}

impl Default for ExecuteOptions {
    fn default() -> Self {
        ExecuteOptions {
            machine: "emco-f1".into(),
            policy: PolicyKind::Aco,
            material: None,
            stock_z_mm: None,
            stock: None,
            cell_mm: None,
            clamp: false,
            inclusions: Vec::new(),
            compare: true,
            seed: 1,
            dexel: None,
            reference: None,
        }
    }
}

/// Deviation of the machined part from the target map (positive = material left).
#[derive(Debug, Clone, Serialize)]
pub struct Deviation {
    pub max_gouge_mm: f64,
    pub max_leftover_mm: f64,
    pub mean_leftover_mm: f64,
    pub rms_deviation_mm: f64,
    pub cells: usize,
    #[serde(skip)]
    pub map: HeightMap,
}

/// The stage's report (stored as JSON).
#[derive(Debug, Clone, Serialize)]
pub struct ExecuteReport {
    pub machine: String,
    pub material: String,
    pub stock: StockSpec,
    pub tools: Vec<ToolLine>,
    pub run: SimReport,
    pub cycle_time_s: f64,
    /// The same program with the programmed feeds and speeds.
    pub cycle_time_no_adaptive_s: f64,
    /// The other adaptive policy on the same program.
    pub cycle_time_other_s: Option<f64>,
    pub other_policy: Option<&'static str>,
    pub deviation: Option<Deviation>,
    pub telemetry_rows: usize,
    /// The G54 work offset the program ran with (machine coordinates of the work origin).
    pub work_offset: super::profile::Offset,
    /// Decisions worth knowing (e.g. the work offset moved so the program fits the travel).
    pub notes: Vec<String>,
    /// Each face of a multi-face part (empty for one face).
    pub faces: Vec<FaceSummary>,
    /// A multi-axis part against the original part (when the job gave one).
    pub part: Option<PartDeviation>,
    /// A multi-axis part's simulated meshes.
    pub part_mesh: Option<PartMesh>,
}

#[derive(Debug, Clone, Serialize)]
pub struct ToolLine {
    pub number: u32,
    pub name: String,
    pub teeth: u32,
    pub length_mm: f64,
}

/// Everything the stage produces.
pub struct ExecuteOutput {
    pub report: ExecuteReport,
    /// The first face's final stock (the only one of a 3-axis part).
    pub final_stock: HeightMap,
    /// Every face's final stock and deviation (one entry for a 3-axis part).
    pub faces: Vec<FaceResult>,
    pub telemetry_csv: String,
    pub telemetry_svg: String,
    /// A multi-axis part: the simulated part as binary STL (closed, wound outward).
    pub part_stl: Option<Vec<u8>>,
    /// ... and a coarser mesh with each vertex's deviation from the original part (NaN where it
    /// was not measured) as binary PLY ([`depthmill_geometry::formats::write_mesh_ply`]).
    pub part_view_ply: Option<Vec<u8>>,
}

/// Errors of the stage.
#[derive(Debug, thiserror::Error)]
pub enum ExecuteError {
    #[error(transparent)]
    Sim(#[from] SimError),
    #[error(transparent)]
    Profile(#[from] super::profile::ProfileError),
    #[error("invalid {field} = {value}: {reason}")]
    Invalid { field: String, value: String, reason: String },
    #[error("cannot read the program: {0}")]
    Io(#[from] std::io::Error),
}

/// Longest program the simulator cuts, in machining time. Cutting is simulated per spindle
/// revolution (about 15 µs each), so a program's cost grows with its cycle time: 24 h at
/// 4000 rpm is about 85 s of computing. A longer one (a helix of a million turns, a crawl at the
/// slowest feed across the table) is refused after the motion-only pass, before anything is cut.
pub const MAX_CYCLE_TIME_S: f64 = 24.0 * 3600.0;

/// The comparison run coarsens a 3-axis part's Z-map only while every tool's radius spans this
/// many of its cells (see [`comparison_setup`]).
pub const COMPARISON_MIN_RADIUS_CELLS: f64 = 4.0;

fn invalid(field: &str, value: impl std::fmt::Display, reason: &str) -> ExecuteError {
    ExecuteError::Invalid { field: field.into(), value: value.to_string(), reason: reason.into() }
}

/// Tool lines of the CAM's program: `(T<n> <name>: <kind> D<d> mm, <z> flutes - ...)`, the first
/// of each number, wherever it is (the CAM writes each at its operation's start, which in a long
/// program lies far past the header).
pub fn header_tools(program: impl BufRead) -> Vec<(u32, String, Option<f64>, Option<u32>)> {
    let mut out: Vec<(u32, String, Option<f64>, Option<u32>)> = Vec::new();
    for line in program.lines().map_while(Result::ok) {
        let t = line.trim();
        let Some(rest) = t.strip_prefix("(T") else { continue };
        let Some((num, rest)) = rest.split_once(' ') else { continue };
        let Ok(number) = num.parse::<u32>() else { continue };
        let Some((name, rest)) = rest.split_once(':') else { continue };
        let diameter =
            rest.split_whitespace().find_map(|w| w.strip_prefix('D')).and_then(|d| d.parse::<f64>().ok());
        let teeth = rest
            .split(',')
            .nth(1)
            .and_then(|s| s.split_whitespace().next())
            .and_then(|n| n.parse::<u32>().ok());
        if !out.iter().any(|(n, ..)| *n == number) {
            out.push((number, name.trim().to_string(), diameter, teeth));
        }
    }
    out
}

fn tool_profile(name: &str, diameter: Option<f64>) -> Option<ToolProfile> {
    if let Ok(spec) = name.parse::<ToolSpec>() {
        return spec.profile().ok();
    }
    // A library name: take the kind from its first part and the diameter from the header.
    let kind = name.split('-').next()?.to_ascii_lowercase();
    let d = diameter?;
    match kind.as_str() {
        "ball" => ToolProfile::ball(d).ok(),
        "flat" => ToolProfile::flat(d).ok(),
        _ => None,
    }
}

/// The machine's tools for a program: the profile's table overridden by the program's header.
pub fn tools_for(
    profile: &MachineProfile,
    header: &[(u32, String, Option<f64>, Option<u32>)],
) -> Result<Vec<MachineTool>, ExecuteError> {
    let mut tools: Vec<MachineTool> = Vec::new();
    for t in &profile.tools {
        let p = tool_profile(&t.name, None)
            .ok_or_else(|| invalid(&format!("tools[T{}].name", t.number), &t.name, "is not a tool spec"))?;
        tools.push(MachineTool {
            number: t.number,
            name: t.name.clone(),
            profile: p,
            teeth: 2,
            length_mm: t.length_mm,
        });
    }
    for (number, name, d, teeth) in header {
        let Some(p) = tool_profile(name, *d) else {
            return Err(invalid(
                &format!("T{number}"),
                name,
                "unknown tool: name a spec (ball-6, flat-3, bull-6-1, v-6-90)",
            ));
        };
        // Gauge length: the table's for that number, else a stick-out of 4 diameters + 25 mm holder.
        let length = profile.tool(*number).map_or(25.0 + 4.0 * p.diameter_mm(), |t| t.length_mm);
        let tool = MachineTool {
            number: *number,
            name: name.clone(),
            profile: p,
            teeth: teeth.unwrap_or(2),
            length_mm: length,
        };
        match tools.iter_mut().find(|t| t.number == *number) {
            Some(slot) => *slot = tool,
            None => tools.push(tool),
        }
    }
    Ok(tools)
}

fn stock_spec(
    opts: &ExecuteOptions,
    target: Option<&HeightMap>,
    extent: Option<Extent>,
    max_radius: f64,
    cell: f64,
) -> Result<StockSpec, ExecuteError> {
    if let Some(s) = opts.stock {
        return Ok(StockSpec { cell_mm: cell, ..s });
    }
    if let Some(map) = target {
        let m = map.meta();
        let floor = m.z_min_mm;
        let highest = map.z_range_of_data().map_or(m.z_max_mm, |(_, hi)| f64::from(hi));
        let top = match opts.stock_z_mm {
            Some(z) if z.is_finite() && z > 0.0 => floor + z,
            Some(z) => return Err(invalid("execute.stock_z_mm", z, "must be positive")),
            None => highest,
        };
        return Ok(StockSpec {
            min_x_mm: m.origin_x_mm,
            min_y_mm: m.origin_y_mm,
            min_z_mm: floor,
            x_mm: m.width_mm(),
            y_mm: m.height_mm(),
            z_mm: (top - floor).max(cell),
            cell_mm: cell,
        });
    }
    let Some((lo, hi)) = extent else {
        return Err(invalid("execute.stock", "none", "the program has no feed moves and no stock was given"));
    };
    let top = 0.0f64.max(lo[2] + 0.5);
    Ok(StockSpec {
        min_x_mm: lo[0] - max_radius,
        min_y_mm: lo[1] - max_radius,
        min_z_mm: lo[2] - 1.0,
        x_mm: hi[0] - lo[0] + 2.0 * max_radius,
        y_mm: hi[1] - lo[1] + 2.0 * max_radius,
        z_mm: top - (lo[2] - 1.0),
        cell_mm: cell,
    })
}

/// Moves the work offset so the program's extent (`ext`, work frame, widened by the largest tool
/// radius for arcs) lies centred in the travel, when it does not fit at the profile's offset: in
/// X and Y the feed moves' tip positions; in Z the spindle nose from the lowest feed with the
/// shortest tool to [`RETRACT_ALLOWANCE_MM`] above the highest feed with the longest (a program in
/// the coordinates of a part whose model sits far from Z = 0, as an operator touching off on the
/// stock would). Returns what was done; `None` when the profile's offset is kept (it fits, or the
/// program is larger than the travel and the run will refuse it naming the line).
pub fn fit_work_offset(profile: &mut MachineProfile, ext: Extent, radius: f64) -> Option<String> {
    let w = profile.work_offset;
    let lengths = profile.tools.iter().map(|t| t.length_mm);
    let (lmin, lmax) = lengths.fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), l| (a.min(l), b.max(l)));
    let (lmin, lmax) = if lmin.is_finite() { (lmin, lmax) } else { (0.0, 0.0) };
    // Per axis: the range that must lie in the travel, less the offset.
    let lo = [ext.0[0] - radius, ext.0[1] - radius, ext.0[2] + lmin];
    let hi = [ext.1[0] + radius, ext.1[1] + radius, ext.1[2] + RETRACT_ALLOWANCE_MM + lmax];
    let axes = [profile.axes.x, profile.axes.y, profile.axes.z];
    let offs = [w.x_mm, w.y_mm, w.z_mm];
    let fits =
        |i: usize, off: f64| axes[i].contains(lo[i] + off, 1e-9) && axes[i].contains(hi[i] + off, 1e-9);
    if (0..3).all(|i| fits(i, offs[i])) {
        return None;
    }
    let mut new = offs;
    for i in 0..3 {
        let centred = 0.5 * (axes[i].min_mm + axes[i].max_mm) - 0.5 * (lo[i] + hi[i]);
        if !fits(i, offs[i]) && fits(i, centred) {
            // Whole machine steps, as an operator's touch-off would be.
            new[i] = profile.quantise(centred);
            if !fits(i, new[i]) {
                new[i] = centred;
            }
        }
    }
    if new == offs {
        return None;
    }
    profile.work_offset.x_mm = new[0];
    profile.work_offset.y_mm = new[1];
    profile.work_offset.z_mm = new[2];
    Some(format!(
        "the program spans X {:.3}..{:.3}, Y {:.3}..{:.3}, Z {:.3}..{:.3} mm (work frame): work offset G54 set to X {:.3} Y {:.3} Z {:.3} (profile: X {:.3} Y {:.3} Z {:.3}) so it lies centred in the travel",
        ext.0[0],
        ext.1[0],
        ext.0[1],
        ext.1[1],
        ext.0[2],
        ext.1[2],
        new[0],
        new[1],
        new[2],
        offs[0],
        offs[1],
        offs[2]
    ))
}

/// Z kept above a program's highest feed move for its rapids and retracts when fitting the work
/// offset, mm (the CAM retracts 5 mm above the stock).
pub const RETRACT_ALLOWANCE_MM: f64 = 10.0;

/// Tip extents of the feed moves (work frame), by interpreting the program once.
fn feed_extent(
    program: impl BufRead,
    cfg: InterpConfig,
    profile: &MachineProfile,
) -> Result<Option<Extent>, ExecuteError> {
    let w = profile.work_offset;
    let mut tlo = 0.0;
    let mut ext: Option<Extent> = None;
    run(program, cfg, |c| match c {
        Canon::ToolLengthOffset { mm, .. } => tlo = mm,
        Canon::Feed { to, .. } | Canon::Arc { end: to, .. } => {
            let p = [to.x - w.x_mm, to.y - w.y_mm, to.z - tlo - w.z_mm];
            ext = Some(match ext {
                None => (p, p),
                Some((lo, hi)) => ([0, 1, 2].map(|i| lo[i].min(p[i])), [0, 1, 2].map(|i| hi[i].max(p[i]))),
            });
        }
        _ => {}
    })
    .map_err(SimError::from)?;
    Ok(ext)
}

/// Runs the stage. `open` re-opens the program for each pass; `stop` is polled; `observe` sees
/// the main run's telemetry rows as they are made.
pub fn execute(
    open: &(dyn Fn() -> std::io::Result<Box<dyn BufRead + Send>> + Sync),
    opts: &ExecuteOptions,
    target: Option<&HeightMap>,
    stop: &(dyn Fn() -> bool + Sync),
    observe: &mut (dyn FnMut(&TelemetryRow) + Send),
) -> Result<ExecuteOutput, ExecuteError> {
    let targets: Vec<FaceTarget<'_>> = target.map(|map| FaceTarget { a_deg: 0.0, map }).into_iter().collect();
    execute_faces(open, opts, &targets, stop, observe)
}

/// One face of a multi-face part: its target map and the A angle it is machined at.
#[derive(Debug, Clone, Copy)]
pub struct FaceTarget<'a> {
    pub a_deg: f64,
    pub map: &'a HeightMap,
}

/// What one face came out as.
#[derive(Debug, Clone)]
pub struct FaceResult {
    pub a_deg: f64,
    pub final_stock: HeightMap,
    pub deviation: Option<Deviation>,
}

/// A face's figures in the report.
#[derive(Debug, Clone, Serialize)]
pub struct FaceSummary {
    pub a_deg: f64,
    pub stock: StockSpec,
    pub deviation: Option<Deviation>,
}

/// [`execute`] for a part machined on several faces, each with its target map at its A angle:
/// the part is cut on one dexel stock (the blank every face's block bounds; see
/// [`super::sim`]), and each face's final stock is that stock seen from the face. So is a single
/// turned face, and a program that feeds at A != 0. The report's deviation is over all faces
/// together (worst gouge and leftover, RMS over every cell); `faces` has each one.
pub fn execute_faces(
    open: &(dyn Fn() -> std::io::Result<Box<dyn BufRead + Send>> + Sync),
    opts: &ExecuteOptions,
    targets: &[FaceTarget<'_>],
    stop: &(dyn Fn() -> bool + Sync),
    observe: &mut (dyn FnMut(&TelemetryRow) + Send),
) -> Result<ExecuteOutput, ExecuteError> {
    let target = targets.first().map(|t| t.map);
    let part_origin = common_part_origin(targets)?;
    let profile = MachineProfile::by_name_or_file(&opts.machine)?;
    let material: Material = match &opts.material {
        None => material("aluminium").ok_or_else(|| invalid("execute.material", "aluminium", "missing"))?,
        Some(m) => material(m).ok_or_else(|| {
            let known: Vec<String> = materials().into_iter().map(|m| m.name).collect();
            invalid("execute.material", m, &format!("unknown; expected one of {}", known.join(", ")))
        })?,
    };
    let cell =
        opts.cell_mm.unwrap_or_else(|| target.map_or(DEFAULT_CELL_MM, |m| m.pixel_mm().min(DEFAULT_CELL_MM)));
    if !(cell.is_finite() && (0.005..=10.0).contains(&cell)) {
        return Err(invalid("execute.cell_mm", cell, "must be in [0.005, 10] mm"));
    }
    let header = header_tools(open()?);
    let tools = tools_for(&profile, &header)?;
    let max_radius = tools.iter().map(|t| t.profile.radius_mm()).fold(0.0, f64::max);
    let mut setup = SimSetup {
        profile: profile.clone(),
        material: material.clone(),
        stock: StockSpec {
            min_x_mm: 0.0,
            min_y_mm: 0.0,
            min_z_mm: 0.0,
            x_mm: 1.0,
            y_mm: 1.0,
            z_mm: 1.0,
            cell_mm: cell,
        },
        faces: Vec::new(),
        dexel: None,
        tools: tools.clone(),
        policy: opts.policy,
        clamp: opts.clamp,
        inclusions: opts.inclusions.clone(),
        seed: opts.seed,
        telemetry_interval_s: 0.05,
        motion_only: false,
    };
    // Where the operator clamps the stock: the profile's work offset when the program fits the
    // travel there, else one that centres the program's moves in X and Y (as an operator would
    // place a part whose program origin is its centre).
    let cfg0 = super::sim::Machine::new(&SimSetup { motion_only: true, ..setup.clone() })?.interp_config();
    let mut notes = Vec::new();
    // The feed moves only: rapids also go to machine positions (the tool change) that do not move
    // with the work.
    if let Some(ext) = feed_extent(open()?, cfg0, &profile)?
        && let Some(note) = fit_work_offset(&mut setup.profile, ext, max_radius)
    {
        tracing::info!(%note, "work offset");
        notes.push(note);
    }
    let profile = setup.profile.clone();
    // The interpreter configuration a machine with these tools uses.
    let cfg = super::sim::Machine::new(&SimSetup { motion_only: true, ..setup.clone() })?.interp_config();
    let extent =
        if target.is_none() && opts.stock.is_none() { feed_extent(open()?, cfg, &profile)? } else { None };
    setup.stock = stock_spec(opts, target, extent, max_radius, cell)?;
    setup.dexel = opts.dexel;

    let other = match (opts.compare, opts.policy) {
        (true, PolicyKind::Aco) => Some(PolicyKind::FeedOnly),
        (true, PolicyKind::FeedOnly) => Some(PolicyKind::Aco),
        _ => None,
    };
    // Motion only first: travel, feeds, speeds and tools are checked for the whole program
    // before anything is cut (a refused program changes nothing), and its cycle time is the one
    // without adaptation.
    let plain = {
        let s = SimSetup { policy: PolicyKind::Off, motion_only: true, ..setup.clone() };
        simulate(open()?, &s, stop, &mut |_| {})?.0
    };
    if plain.cycle_time_s > MAX_CYCLE_TIME_S {
        return Err(invalid(
            "program",
            format!("{:.1} h of machining", plain.cycle_time_s / 3600.0),
            &format!(
                "longer than the {} h the simulated mill runs one program for; split it",
                MAX_CYCLE_TIME_S / 3600.0
            ),
        ));
    }
    // A multi-axis part is cut on one dexel stock: several faces, a turned face, or a program
    // that feeds at A != 0.
    let indexed = targets.len() > 1 || targets.iter().any(|t| t.a_deg.abs() > 1e-9) || plain.turned_moves > 0;
    if indexed {
        setup.faces = targets
            .iter()
            .map(|t| {
                Ok(super::sim::FaceStock {
                    a_deg: t.a_deg,
                    stock: stock_spec(opts, Some(t.map), None, max_radius, cell)?,
                })
            })
            .collect::<Result<Vec<_>, ExecuteError>>()?;
        if setup.faces.is_empty() {
            // No target: the program's own stock, at A = 0.
            setup.faces = vec![super::sim::FaceStock { a_deg: 0.0, stock: setup.stock }];
        }
    }
    let mut rows: Vec<TelemetryRow> = Vec::new();
    let main_setup = setup.clone();
    let (main, other_run) = rayon::join(
        || -> Result<_, ExecuteError> {
            let mut sink = |r: &TelemetryRow| {
                rows.push(*r);
                observe(r);
            };
            Ok(simulate_stock(open()?, &main_setup, stop, &mut sink)?)
        },
        || {
            other
                .map(|p| -> Result<SimReport, ExecuteError> {
                    Ok(simulate(open()?, &comparison_setup(&setup, p), stop, &mut |_| {})?.0)
                })
                .transpose()
        },
    );
    let (run_report, stocks, dexel) = main?;
    let other_run = other_run?;
    let mut final_stock = stocks
        .first()
        .map(|(_, m)| m.clone())
        .ok_or_else(|| invalid("stock", "none", "the run kept no stock"))?;
    let faces: Vec<FaceResult> = if indexed {
        targets
            .iter()
            .zip(&stocks)
            .map(|(t, (a, m))| {
                // Labelled with the view its target records (the stock is seen from it).
                let mut final_stock = m.clone();
                if final_stock.set_face(t.map.face()).is_err()
                    || final_stock.set_part_origin(t.map.part_origin_mm()).is_err()
                {
                    tracing::warn!(face = %t.map.face(), "face label not kept on the final stock");
                }
                FaceResult { a_deg: *a, deviation: Some(deviation(t.map, &final_stock)), final_stock }
            })
            .collect()
    } else {
        vec![FaceResult {
            a_deg: 0.0,
            final_stock: final_stock.clone(),
            deviation: target.map(|t| deviation(t, &final_stock)),
        }]
    };
    if indexed && let Some(first) = faces.first() {
        final_stock = first.final_stock.clone();
    }
    let deviation = combine_deviations(&faces);
    // The program's smallest tool opens the part (the finest it can reach).
    let opening = tools
        .iter()
        .filter(|t| header.iter().any(|h| h.0 == t.number))
        .min_by(|a, b| a.profile.radius_mm().total_cmp(&b.profile.radius_mm()));
    // The dexel stock lives in the set-up's frame: the part frame less `part_origin`. The
    // reference points move there to be measured; the meshes move back to the part frame.
    let reference: Option<std::borrow::Cow<'_, [Point3<f64>]>> = opts.reference.as_ref().map(|r| {
        if part_origin == Vector3::zeros() {
            std::borrow::Cow::Borrowed(&r.points[..])
        } else {
            std::borrow::Cow::Owned(r.points.iter().map(|p| p - part_origin).collect())
        }
    });
    let measured = match (&dexel, &opts.reference, &reference) {
        (Some(stock), Some(r), Some(points)) => {
            let faces: Vec<MeasureFace<'_>> =
                targets.iter().map(|t| MeasureFace { a_deg: t.a_deg, map: t.map }).collect();
            Some(measure(stock, &r.source, points, &faces, opening.map(|t| (t.name.as_str(), &t.profile))))
        }
        _ => None,
    };
    let meshes = match &dexel {
        Some(stock) => Some(part_meshes(
            stock,
            reference.as_deref().zip(measured.as_ref()).map(|(r, m)| (r, &m.per_point[..])),
            &part_origin,
        )?),
        None => None,
    };
    let cycle = run_report.cycle_time_s;
    let report = ExecuteReport {
        machine: profile.name.clone(),
        material: material.name.clone(),
        stock: setup.stock,
        tools: tools
            .iter()
            .map(|t| ToolLine {
                number: t.number,
                name: t.name.clone(),
                teeth: t.teeth,
                length_mm: t.length_mm,
            })
            .collect(),
        cycle_time_s: cycle,
        cycle_time_no_adaptive_s: plain.cycle_time_s,
        cycle_time_other_s: other_run.as_ref().map(|r| r.cycle_time_s),
        other_policy: other.map(PolicyKind::as_str),
        run: run_report,
        deviation,
        telemetry_rows: rows.len(),
        work_offset: profile.work_offset,
        notes,
        faces: if targets.len() > 1 {
            faces
                .iter()
                .zip(&setup.faces)
                .map(|(f, s)| FaceSummary { a_deg: f.a_deg, stock: s.stock, deviation: f.deviation.clone() })
                .collect()
        } else {
            Vec::new()
        },
        part: measured,
        part_mesh: meshes.as_ref().map(|m| m.0.clone()),
    };
    let telemetry_csv = telemetry_csv(&rows);
    let telemetry_svg = telemetry_chart(&rows, report.run.policy).to_svg();
    let (part_stl, part_view_ply) = meshes.map_or((None, None), |(_, stl, ply)| (Some(stl), Some(ply)));
    Ok(ExecuteOutput { report, final_stock, faces, telemetry_csv, telemetry_svg, part_stl, part_view_ply })
}

/// The set-up of the comparison policy's run. Its figure is a cycle time, so the stock is cut
/// there on cells twice as coarse: a multi-axis part's dexels (a quarter of the rays per grid),
/// and a 3-axis part's Z-map when every tool's radius still spans at least
/// [`COMPARISON_MIN_RADIUS_CELLS`] of the coarse cells (a quarter of the cells per revolution).
/// The forces the loop reacts to come from the same engagement and volume, resolved to 2 cells.
fn comparison_setup(setup: &SimSetup, policy: PolicyKind) -> SimSetup {
    let mut s = SimSetup { policy, ..setup.clone() };
    if s.faces.is_empty() {
        let coarse = 2.0 * s.stock.cell_mm;
        let min_radius = s.tools.iter().map(|t| t.profile.radius_mm()).fold(f64::INFINITY, f64::min);
        if min_radius >= COMPARISON_MIN_RADIUS_CELLS * coarse && coarse <= 10.0 {
            s.stock.cell_mm = coarse;
        }
    } else {
        let cell = s.faces.iter().map(|f| f.stock.cell_mm).fold(s.stock.cell_mm, f64::min);
        let c = s.dexel.unwrap_or(DexelCells::tri(cell));
        s.dexel = Some(DexelCells {
            x_mm: c.x_mm.map(|v| 2.0 * v),
            y_mm: c.y_mm.map(|v| 2.0 * v),
            z_mm: c.z_mm.map(|v| 2.0 * v),
        });
    }
    s
}

/// The simulated part as STL (on the finest lattice within [`MAX_SURFACE_SAMPLES`]) and as the
/// view mesh (within [`VIEW_SAMPLES`]) coloured by the deviation of the nearest measured point.
/// The simulated part as binary STL and as a coarser view mesh (binary PLY) whose vertices carry
/// the deviation of the nearest `measured` reference point (points on the original part and
/// their deviations; NaN where not measured).
///
/// The stock and `measured` are in the set-up's frame; both meshes are written in the part frame
/// (moved by `part_origin`, see [`common_part_origin`]).
pub fn part_meshes(
    stock: &super::dexel::DexelStock,
    measured: Option<(&[Point3<f64>], &[f32])>,
    part_origin: &Vector3<f64>,
) -> Result<(PartMesh, Vec<u8>, Vec<u8>), ExecuteError> {
    let mesh_err = |e: super::dexel::DexelError| invalid("part mesh", "dexel stock", &e.to_string());
    let write_err =
        |e: depthmill_geometry::formats::FormatError| invalid("part mesh", "bytes", &e.to_string());
    let step = stock.surface_step_mm(MAX_SURFACE_SAMPLES);
    let mut mesh = stock.surface_mesh(step).map_err(mesh_err)?;
    for v in &mut mesh.vertices {
        *v += part_origin;
    }
    let mut stl = Vec::new();
    depthmill_geometry::formats::write_stl(&mut stl, &mesh, "depthmill simulated part (mm)")
        .map_err(write_err)?;
    let view_step = stock.surface_step_mm(VIEW_SAMPLES);
    let view = stock.surface_mesh(view_step).map_err(mesh_err)?;
    let values = match measured {
        Some((points, per_point)) => {
            vertex_deviation(&view.vertices, points, per_point, (2.0 * view_step).max(0.5))
        }
        None => vec![f32::NAN; view.vertices.len()],
    };
    let mut view = view;
    for v in &mut view.vertices {
        *v += part_origin;
    }
    let mut ply = Vec::new();
    depthmill_geometry::formats::write_mesh_ply(
        &mut ply,
        &view,
        "deviation",
        &values,
        &["depthmill simulated part: deviation from the original part, mm (NaN: not measured)".into()],
    )
    .map_err(write_err)?;
    let info = PartMesh {
        step_mm: step,
        triangles: mesh.triangles.len(),
        volume_mm3: super::dexel::surface::mesh_volume_mm3(&mesh),
        dexel_volume_mm3: stock.volume_mm3(),
        view_step_mm: view_step,
        view_triangles: view.triangles.len(),
    };
    Ok((info, stl, ply))
}

/// The part-frame point the set-up's frame is centred on: every target map's
/// [`depthmill_geometry::HeightMapMeta::part_origin_mm`] (zero without targets). A turned set-up
/// turns about one point, so maps that disagree are refused.
pub fn common_part_origin(targets: &[FaceTarget<'_>]) -> Result<Vector3<f64>, ExecuteError> {
    let Some(first) = targets.first() else { return Ok(Vector3::zeros()) };
    let o = first.map.part_origin_mm();
    if let Some((i, t)) = targets.iter().enumerate().find(|(_, t)| t.map.part_origin_mm() != o) {
        return Err(invalid(
            &format!("face_maps[{i}].part_origin_mm"),
            format!("{:?}", t.map.part_origin_mm()),
            &format!("every face of one set-up turns about one point; face_maps[0] turns about {o:?}"),
        ));
    }
    Ok(Vector3::from(o))
}

/// The deviation over every face: worst gouge and leftover, mean and RMS over all cells; the
/// first face's map.
fn combine_deviations(faces: &[FaceResult]) -> Option<Deviation> {
    let ds: Vec<&Deviation> = faces.iter().filter_map(|f| f.deviation.as_ref()).collect();
    let first = (*ds.first()?).clone();
    if ds.len() == 1 {
        return Some(first);
    }
    let cells: usize = ds.iter().map(|d| d.cells).sum();
    let n = cells.max(1) as f64;
    Some(Deviation {
        max_gouge_mm: ds.iter().map(|d| d.max_gouge_mm).fold(0.0, f64::max),
        max_leftover_mm: ds.iter().map(|d| d.max_leftover_mm).fold(0.0, f64::max),
        mean_leftover_mm: ds.iter().map(|d| d.mean_leftover_mm * d.cells as f64).sum::<f64>() / n,
        rms_deviation_mm: (ds.iter().map(|d| d.rms_deviation_mm.powi(2) * d.cells as f64).sum::<f64>() / n)
            .sqrt(),
        cells,
        map: first.map,
    })
}

/// Steepest surface, rise over run, read by interpolation between cells (tan 63°); across a
/// steeper step the nearest cell is read.
const INTERPOLATION_MAX_SLOPE: f64 = 2.0;

/// Signed deviation `stock − target` on the target's grid (NaN where the target or the stock has
/// no data: the stock has none where its blank never held material), with its statistics.
///
/// - Where the target reads smoothly around a cell (the four target centres around each of the
///   stock cells in it have data and no step steeper than tan 63° between neighbours) and the
///   stock is finer, the cell is measured at each of its stock cells, where the stock is exact,
///   against the target interpolated there ([`HeightMap::interpolated`]: a sampled surface,
///   linear between its centres as the planner's point and facet readings take it). The cell's
///   value is the deepest gouge among them, else their mean; each counts for its share of the
///   cell's area.
/// - Elsewhere (a step, a wall, a hole or the border of the target, or a stock as coarse as the
///   target) at the target cell's centre, the stock interpolated there, else its nearest cell.
///
/// The nearest stock cell alone reads a slope of angle θ off by `tan θ` times the distance
/// between the two grids' centres (±0.039 mm on a 38° slope cut exactly, on 0.1 mm cells), and
/// the stock read at the target's centres reads a target's single-cell peak against stock
/// interpolated under it (0.0235 mm on the hinge's filled cove, 0.0088 mm on the stock's cells).
pub fn deviation(target: &HeightMap, stock: &HeightMap) -> Deviation {
    let meta = *target.meta();
    let n = target.data().len();
    let fine = stock.pixel_mm() < target.pixel_mm() * (1.0 - 1e-9);
    // Per target cell, over its stock cells: whether every one reads the target smoothly, the
    // deepest deviation, the sum and the count; and each stock cell's (target cell, deviation).
    let (mut smooth, mut worst, mut sum, mut count) =
        (vec![fine; n], vec![f64::INFINITY; n], vec![0.0; n], vec![0u32; n]);
    let mut on_stock: Vec<(usize, f64)> = Vec::new();
    if fine {
        let sm = *stock.meta();
        for row in 0..sm.height {
            for col in 0..sm.width {
                let Some(s) = stock.get(col, row).filter(|s| s.is_finite()) else { continue };
                let (x, y) = sm.cell_center(col, row);
                let Some(i) = target.cell_of(x, y).and_then(|(c, r)| target.index(c, r)) else { continue };
                match target.interpolated(x, y, INTERPOLATION_MAX_SLOPE) {
                    Some(t) => {
                        let d = f64::from(s) - t;
                        worst[i] = worst[i].min(d);
                        sum[i] += d;
                        count[i] += 1;
                        on_stock.push((i, d));
                    }
                    None => smooth[i] = false,
                }
            }
        }
    }
    let share = (stock.pixel_mm() / target.pixel_mm()).powi(2);
    let mut data = vec![f32::NAN; n];
    let (mut max_gouge, mut max_left, mut sum_left, mut sum_sq, mut weight, mut cells) =
        (0.0f64, 0.0f64, 0.0f64, 0.0f64, 0.0f64, 0usize);
    let mut add = |d: f64, w: f64| {
        max_gouge = max_gouge.max(-d);
        max_left = max_left.max(d);
        sum_left += w * d.max(0.0);
        sum_sq += w * d * d;
        weight += w;
    };
    for row in 0..meta.height {
        for col in 0..meta.width {
            let i = (row * meta.width + col) as usize;
            let Some(t) = target.get(col, row).filter(|t| t.is_finite()) else { continue };
            if smooth[i] && count[i] > 0 {
                // Measured on its stock cells (counted below, each for its share of the cell).
                let k = f64::from(count[i]);
                data[i] = if worst[i] < 0.0 { worst[i] } else { sum[i] / k } as f32;
                cells += 1;
                continue;
            }
            let (x, y) = meta.cell_center(col, row);
            let nearest = || stock.cell_of(x, y).and_then(|(c, r)| stock.get(c, r)).map(f64::from);
            let Some(s) =
                stock.interpolated(x, y, INTERPOLATION_MAX_SLOPE).or_else(nearest).filter(|s| s.is_finite())
            else {
                continue;
            };
            let d = s - f64::from(t);
            data[i] = d as f32;
            add(d, 1.0);
            cells += 1;
        }
    }
    // The smooth cells' stock cells, each for its share of the cell (a cell interpolated at a
    // stock cell has data, so the smooth ones are those measured above).
    for &(i, d) in &on_stock {
        if smooth[i] {
            add(d, share);
        }
    }
    let range = max_gouge.max(max_left).max(0.01);
    let dev_meta = HeightMapMeta { z_min_mm: -range, z_max_mm: range, ..meta };
    let map = HeightMap::new(dev_meta, data).unwrap_or_else(|_| target.clone());
    // Nothing measured: the sums are 0, and so are the figures.
    let w = weight.max(f64::MIN_POSITIVE);
    Deviation {
        max_gouge_mm: max_gouge,
        max_leftover_mm: max_left,
        mean_leftover_mm: sum_left / w,
        rms_deviation_mm: (sum_sq / w).sqrt(),
        cells,
        map,
    }
}

/// Telemetry rows as CSV with a header line. Rows are formatted in parallel chunks (a run keeps
/// a row per revolution or per telemetry interval: 10^5 to 10^6 rows), joined in order.
pub fn telemetry_csv(rows: &[TelemetryRow]) -> String {
    const HEADER: &str = "time_s,line,x_mm,y_mm,z_mm,a_deg,feed_mm_min,spindle_rpm,torque_true_nm,torque_adc_nm,torque_counts,current_a,torque_from_current_nm,power_w,removal_mm3_s,active\n";
    let chunks: Vec<String> = rows
        .par_chunks(8192)
        .map(|chunk| {
            let mut s = String::with_capacity(chunk.len() * 110);
            chunk.iter().for_each(|r| csv_row(&mut s, r));
            s
        })
        .collect();
    let mut s = String::with_capacity(HEADER.len() + chunks.iter().map(String::len).sum::<usize>());
    s.push_str(HEADER);
    chunks.iter().for_each(|c| s.push_str(c));
    s
}

/// One telemetry row as a CSV line.
fn csv_row(s: &mut String, r: &TelemetryRow) {
    use std::fmt::Write as _;
    let _ = writeln!(
        s,
        "{:.4},{},{:.4},{:.4},{:.4},{:.3},{:.2},{:.1},{:.5},{:.4},{},{:.5},{:.5},{:.3},{:.4},{}",
        r.time_s,
        r.line,
        r.x_mm,
        r.y_mm,
        r.z_mm,
        r.a_deg,
        r.feed_mm_min,
        r.spindle_rpm,
        r.torque_true_nm,
        r.torque_adc_nm,
        r.torque_counts,
        r.current_a,
        r.torque_from_current_nm,
        r.power_w,
        r.removal_mm3_s,
        active_names(r.active)
    );
}

/// Feed, speed, torque (truth, ADC, from current) and power over time.
pub fn telemetry_chart(rows: &[TelemetryRow], policy: &str) -> Chart {
    let series = |label: &str, color: &str, f: &dyn Fn(&TelemetryRow) -> f64| Series {
        label: label.into(),
        color: color.into(),
        points: rows.iter().map(|r| (r.time_s, f(r))).collect(),
    };
    Chart {
        title: format!("Spindle and feed over time ({policy})"),
        x_label: "time [s]".into(),
        width: 900,
        panel_height: 120,
        panels: vec![
            Panel {
                title: "feed".into(),
                unit: "mm/min".into(),
                series: vec![series("feed", "#1f77b4", &|r| r.feed_mm_min)],
            },
            Panel {
                title: "spindle speed".into(),
                unit: "rpm".into(),
                series: vec![series("speed", "#2ca02c", &|r| r.spindle_rpm)],
            },
            Panel {
                title: "torque".into(),
                unit: "N·m".into(),
                series: vec![
                    series("ADC (0.139 N·m/count)", "#bbbbbb", &|r| r.torque_adc_nm),
                    series("from current", "#d62728", &|r| r.torque_from_current_nm),
                    series("model", "#000000", &|r| r.torque_true_nm),
                ],
            },
            Panel {
                title: "cutting power".into(),
                unit: "W".into(),
                series: vec![series("power", "#ff7f0e", &|r| r.power_w)],
            },
        ],
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A target's single-cell peak against a stock that follows the target read linearly between
    /// its centres (the planner's reading): no gouge, where the stock read at the peak's centre
    /// stands well under it. At the target's outline (no data beyond), a part edge inside the last
    /// cell does not read as a gouge of the part's height: that cell is measured at its centre.
    #[test]
    fn a_single_cell_peak_and_an_edge_inside_a_cell_are_measured_where_the_stock_is() {
        use depthmill_geometry::HeightMapMeta;
        let mut tm = HeightMapMeta::new(40, 40, 0.25);
        (tm.z_min_mm, tm.z_max_mm) = (0.0, 10.0);
        let target = HeightMap::from_fn(tm, |c, r| match (c, r) {
            (20, 20) => 5.3,
            (c, _) if c >= 30 => f32::NAN,
            _ => 5.0,
        })
        .expect("target");
        let mut sm = HeightMapMeta::new(90, 90, 0.1);
        (sm.origin_x_mm, sm.origin_y_mm, sm.z_min_mm, sm.z_max_mm) = (0.23, 0.37, 0.0, 10.0);
        // The part's edge at x = 7.43 mm, inside the last target column (7.25..7.5); beyond it the
        // stock is cut down to 0.
        let stock = HeightMap::from_fn(sm, |c, r| {
            let (x, y) = sm.cell_center(c, r);
            if x > 7.43 {
                0.0
            } else {
                target.interpolated(x, y, INTERPOLATION_MAX_SLOPE).unwrap_or(5.0) as f32
            }
        })
        .expect("stock");
        let d = deviation(&target, &stock);
        assert!(d.max_gouge_mm < 1e-5, "{d:?}");
        assert!(d.max_leftover_mm < 1e-5, "{d:?}");
        // The target cells with data that the stock covers (29 x 36 centres under it, and the
        // border cells whose stock cells lie under it).
        assert!((1044..=1100).contains(&d.cells), "{}", d.cells);
        let (px, py) = tm.cell_center(20, 20);
        let under = stock.interpolated(px, py, INTERPOLATION_MAX_SLOPE).expect("between stock cells");
        assert!(under < 5.3 - 0.05, "the stock read at the peak's centre: {under}");
    }

    /// A stock cut exactly to a slope, on finer cells than the target and offset from them, reads
    /// the target's slope with no deviation; a step in the stock reads at the nearest cell.
    #[test]
    fn the_deviation_reads_a_finer_stock_between_its_cells() {
        use depthmill_geometry::HeightMapMeta;
        let slope = |x: f64, y: f64| 0.78 * x + 0.2 * y;
        let mut tm = HeightMapMeta::new(40, 40, 0.25);
        (tm.origin_x_mm, tm.origin_y_mm, tm.z_min_mm, tm.z_max_mm) = (0.0, 0.0, -20.0, 20.0);
        let target = HeightMap::from_fn(tm, |c, r| {
            let (x, y) = tm.cell_center(c, r);
            slope(x, y) as f32
        })
        .expect("target");
        let mut sm = HeightMapMeta::new(120, 120, 0.1);
        (sm.origin_x_mm, sm.origin_y_mm, sm.z_min_mm, sm.z_max_mm) = (-0.97, -0.53, -20.0, 20.0);
        let mut stock = HeightMap::from_fn(sm, |c, r| {
            let (x, y) = sm.cell_center(c, r);
            slope(x, y) as f32
        })
        .expect("stock");
        let d = deviation(&target, &stock);
        assert_eq!(d.cells, 1600);
        assert!(
            d.max_gouge_mm < 1e-5 && d.max_leftover_mm < 1e-5,
            "{} {}",
            d.max_gouge_mm,
            d.max_leftover_mm
        );
        // A 3 mm step in the stock is not interpolated across: the cells beside it read one side.
        for r in 0..120 {
            for c in 60..120 {
                let (x, y) = sm.cell_center(c, r);
                stock.set(c, r, (slope(x, y) + 3.0) as f32).expect("cell");
            }
        }
        let d = deviation(&target, &stock);
        assert!(d.max_gouge_mm < 1e-5, "{}", d.max_gouge_mm);
        assert!((d.max_leftover_mm - 3.0).abs() < 1e-4, "{}", d.max_leftover_mm);
    }

    /// The CSV joined from parallel chunks reads as the rows written one after another: the
    /// header, then every row in order across the chunks' edges.
    #[test]
    fn telemetry_csv_holds_every_row_in_order() {
        let rows: Vec<TelemetryRow> = (0..20_000u32)
            .map(|i| {
                let f = f64::from(i);
                TelemetryRow {
                    time_s: f * 0.013,
                    line: u64::from(i / 3),
                    x_mm: (f * 0.1).sin() * 40.0,
                    y_mm: -f * 1e-3,
                    z_mm: 7.5 + (f * 0.01).cos(),
                    a_deg: 0.0,
                    feed_mm_min: 200.0 + f % 50.0,
                    spindle_rpm: 2000.0,
                    torque_true_nm: 0.01 * (f % 7.0),
                    torque_adc_nm: 0.0101 * (f % 7.0),
                    torque_counts: (i % 400) as i32 - 200,
                    current_a: 1.5,
                    torque_from_current_nm: 0.0099 * (f % 7.0),
                    power_w: f % 300.0,
                    removal_mm3_s: f * 1e-4,
                    active: (i % 4) as u16,
                }
            })
            .collect();
        let csv = telemetry_csv(&rows);
        let mut lines = csv.lines();
        assert!(lines.next().is_some_and(|h| h.starts_with("time_s,line,")));
        let mut n = 0;
        for (line, r) in lines.zip(&rows) {
            let mut one = String::new();
            csv_row(&mut one, r);
            assert_eq!(line, one.trim_end(), "row {n}");
            let t: f64 = line.split(',').next().and_then(|t| t.parse().ok()).expect("time");
            assert!((t - r.time_s).abs() <= 5e-5, "row {n}: {t}");
            n += 1;
        }
        assert_eq!(n, rows.len());
        assert_eq!(csv.lines().count(), rows.len() + 1);
    }

    fn emco() -> MachineProfile {
        MachineProfile::builtin("emco-f1").expect("shipped profile")
    }

    #[test]
    fn the_work_offset_moves_only_when_the_program_does_not_fit() {
        // Fits at the profile's offset (X 40, Y 10): kept.
        let mut p = emco();
        assert_eq!(fit_work_offset(&mut p, ([0.0, 0.0, 0.0], [60.0, 50.0, 10.0]), 3.0), None);
        assert_eq!(p.work_offset, emco().work_offset);
        // A program centred on its origin: moved so it is centred in the travel.
        let mut p = emco();
        let note = fit_work_offset(&mut p, ([-40.0, -30.0, 0.0], [40.0, 30.0, 10.0]), 3.0).expect("moved");
        assert!(note.contains("G54"), "{note}");
        let (x, y) = (p.axes.x, p.axes.y);
        assert!((p.work_offset.x_mm - 0.5 * (x.min_mm + x.max_mm)).abs() < 1e-9);
        assert!((p.work_offset.y_mm - 0.5 * (y.min_mm + y.max_mm)).abs() < 1e-9);
        assert_eq!(p.work_offset.z_mm, emco().work_offset.z_mm);
        // Wider than the travel: kept, the run refuses it naming the line.
        let mut p = emco();
        assert_eq!(fit_work_offset(&mut p, ([0.0, -80.0, 0.0], [60.0, 80.0, 10.0]), 3.0), None);
        // A program in the coordinates of a model far below Z = 0: the Z offset moves so the
        // spindle nose stays in the travel with every tool, from the lowest feed to the retract.
        let mut p = emco();
        let (zlo, zhi) = (-148.0, -80.0);
        let note = fit_work_offset(&mut p, ([0.0, 0.0, zlo], [60.0, 50.0, zhi]), 3.0).expect("moved in Z");
        assert!(note.contains("Z"), "{note}");
        assert_eq!(
            (p.work_offset.x_mm, p.work_offset.y_mm),
            (emco().work_offset.x_mm, emco().work_offset.y_mm)
        );
        let lens: Vec<f64> = p.tools.iter().map(|t| t.length_mm).collect();
        let (lmin, lmax) =
            (lens.iter().copied().fold(f64::INFINITY, f64::min), lens.iter().copied().fold(0.0, f64::max));
        let z = p.work_offset.z_mm;
        assert!(
            p.axes.z.contains(zlo + z + lmin, 1e-9)
                && p.axes.z.contains(zhi + RETRACT_ALLOWANCE_MM + z + lmax, 1e-9)
        );
        assert_eq!(p.quantise(z), z);
    }

    /// A program whose machining would take days is refused from its motion-only timing, at
    /// once, with nothing cut.
    #[test]
    fn a_program_longer_than_the_simulator_runs_is_refused_before_cutting() {
        let program = "(T1 flat-6: flat D6.0000 mm, 2 flutes - roughing-x with flat-6)\nG21 G90 G17 G94\nT1 M6\nS1500 M3\nG43 H1\n\
                       G0 X15 Y10 Z20\nG1 Z9 F100\nG2 X15 Y10 I1 J0 P1000000 F400\nG0 Z20\nM30\n";
        let open = || -> std::io::Result<Box<dyn BufRead + Send>> {
            Ok(Box::new(std::io::Cursor::new(program.as_bytes().to_vec())))
        };
        let opts = ExecuteOptions { stock_z_mm: Some(10.0), compare: false, ..Default::default() };
        // Refused from the motion-only pass (cutting it would take hours of computing).
        let e = execute(&open, &opts, None, &|| false, &mut |_| {}).map(|_| ()).expect_err("too long");
        assert!(e.to_string().contains("h of machining") && e.to_string().contains("24 h"), "{e}");
    }

    #[test]
    fn a_single_turned_face_is_cut_at_its_angle() {
        // A flat 20 x 20 mm target at Z 5 on a stock 10 mm high, seen with the part turned to
        // A=30; the program turns A to 30 and cuts a slot 2 mm deep.
        let meta = HeightMapMeta {
            z_min_mm: 0.0,
            z_max_mm: 10.0,
            origin_x_mm: 0.0,
            origin_y_mm: 0.0,
            face: depthmill_geometry::Face::A { angle_deg: 30.0 },
            ..HeightMapMeta::new(40, 40, 0.5)
        };
        let target = HeightMap::filled(meta, 5.0).expect("map");
        let program = "(T1 flat-6: flat D6.0000 mm, 2 flutes - roughing-x with flat-6)\nG21 G90 G17 G94 G40 G49 G80\n\
                       G53 G0 Z0\nG0 A30\nT1 M6\nS1800 M3\nG43 H1\nG0 X-4 Y10\nZ15\nG1 Z8 F100\nG1 X24 F300\nG0 Z15\nM30\n";
        let open = || -> std::io::Result<Box<dyn BufRead + Send>> {
            Ok(Box::new(std::io::Cursor::new(program.as_bytes().to_vec())))
        };
        let opts = ExecuteOptions { stock_z_mm: Some(10.0), compare: false, ..Default::default() };
        let out =
            execute_faces(&open, &opts, &[FaceTarget { a_deg: 30.0, map: &target }], &|| false, &mut |_| {})
                .expect("ran");
        assert_eq!(out.faces.len(), 1);
        assert_eq!(out.faces[0].a_deg, 30.0);
        // The slot is in the stock: at Y 10 the top came down from 10 to 8.
        let (c, r) = out.final_stock.cell_of(10.0, 10.0).expect("on the stock");
        let z = out.final_stock.get(c, r).unwrap_or(f32::NAN);
        assert!((z - 8.0).abs() < 0.05, "stock at the slot {z}");
        assert!(
            !out.report.run.warnings.iter().any(|w| w.contains("not cut")),
            "{:?}",
            out.report.run.warnings
        );
    }

    #[test]
    fn a_set_up_centred_off_the_files_origin_is_measured_in_the_parts_frame() {
        // The turned face above, its map centred on a point of the part far from the file's
        // origin, and points of the original part where the part lies in its file: the figures
        // are those of the part at the origin, and the meshes come back to the part's frame.
        let program = "(T1 flat-6: flat D6.0000 mm, 2 flutes - roughing-x with flat-6)\nG21 G90 G17 G94 G40 G49 G80\n\
                       G53 G0 Z0\nG0 A30\nT1 M6\nS1800 M3\nG43 H1\nG0 X-4 Y10\nZ15\nG1 Z8 F100\nG1 X24 F300\nG0 Z15\nM30\n";
        let open = || -> std::io::Result<Box<dyn BufRead + Send>> {
            Ok(Box::new(std::io::Cursor::new(program.as_bytes().to_vec())))
        };
        let face = depthmill_geometry::Face::A { angle_deg: 30.0 };
        let meta = HeightMapMeta { z_min_mm: 0.0, z_max_mm: 10.0, face, ..HeightMapMeta::new(40, 40, 0.5) };
        let part_from_view = super::super::sim::part_from_work(30.0);
        let surface: Vec<Point3<f64>> = (0..40 * 40)
            .map(|k| {
                part_from_view
                    * Point3::new(0.25 + 0.5 * f64::from(k % 40), 0.25 + 0.5 * f64::from(k / 40), 5.0)
            })
            .collect();
        let origin = Vector3::new(100.0, -50.0, -300.0);
        let run = |o: Vector3<f64>| {
            let mut target = HeightMap::filled(meta, 5.0).expect("map");
            target.set_part_origin(o.into()).expect("origin");
            let points = surface.iter().map(|p| p + o).collect();
            let opts = ExecuteOptions {
                stock_z_mm: Some(10.0),
                compare: false,
                reference: Some(Arc::new(Reference { source: "mesh".into(), points })),
                ..Default::default()
            };
            execute_faces(&open, &opts, &[FaceTarget { a_deg: 30.0, map: &target }], &|| false, &mut |_| {})
                .expect("ran")
        };
        let (at_zero, off) = (run(Vector3::zeros()), run(origin));
        let (a, b) = (at_zero.report.part.expect("measured"), off.report.part.expect("measured"));
        assert!(a.against_part.points > 1000, "{a:?}");
        assert_eq!(a.against_part.points, b.against_part.points);
        for (x, y) in [
            (a.against_part.max_gouge_mm, b.against_part.max_gouge_mm),
            (a.against_part.rms_deviation_mm, b.against_part.rms_deviation_mm),
            (a.against_part.mean_leftover_mm, b.against_part.mean_leftover_mm),
        ] {
            assert!((x - y).abs() < 1e-9, "{a:?}\n{b:?}");
        }
        assert_eq!(off.faces[0].final_stock.part_origin_mm(), <[f64; 3]>::from(origin));
        let bounds = |stl: &[u8]| {
            let (mesh, _) = depthmill_geometry::formats::read_stl_from(
                std::io::Cursor::new(stl.to_vec()),
                "part",
                Some(stl.len() as u64),
                &depthmill_geometry::formats::ReadLimits::default(),
            )
            .expect("stl");
            mesh.bounds().expect("bounds")
        };
        let (ba, bb) = (
            bounds(at_zero.part_stl.as_deref().expect("stl")),
            bounds(off.part_stl.as_deref().expect("stl")),
        );
        assert!(
            ((bb.min - ba.min) - origin).norm() < 1e-3 && ((bb.max - ba.max) - origin).norm() < 1e-3,
            "{ba:?} {bb:?}"
        );
        // Faces of one set-up turning about different points are refused before anything runs.
        let mut other = HeightMap::filled(meta, 5.0).expect("map");
        other.set_part_origin([1.0, 0.0, 0.0]).expect("origin");
        let first = HeightMap::filled(meta, 5.0).expect("map");
        let e = execute_faces(
            &open,
            &ExecuteOptions { stock_z_mm: Some(10.0), compare: false, ..Default::default() },
            &[FaceTarget { a_deg: 30.0, map: &first }, FaceTarget { a_deg: 30.0, map: &other }],
            &|| false,
            &mut |_| {},
        )
        .map(|_| ())
        .expect_err("two centres");
        assert!(e.to_string().contains("face_maps[1].part_origin_mm"), "{e}");
    }

    /// A feed-only run of the EMCO with its tool table on `stock` (and `faces`, when several).
    fn feed_only_setup(stock: StockSpec, faces: Vec<super::super::sim::FaceStock>) -> SimSetup {
        SimSetup {
            profile: emco(),
            material: material("aluminium").expect("al"),
            stock,
            faces,
            dexel: None,
            tools: tools_for(&emco(), &[]).expect("tools"),
            policy: PolicyKind::FeedOnly,
            clamp: false,
            inclusions: Vec::new(),
            seed: 1,
            telemetry_interval_s: 0.0,
            motion_only: false,
        }
    }

    /// Runs `program` on `setup` and on its comparison set-up (cells twice as coarse): the cycle
    /// time within 2 %, the removed volume within 3 %. Returns the fine run's removed volume.
    fn comparison_agrees(setup: &SimSetup, program: &str) -> f64 {
        let run = |s: &SimSetup| {
            simulate(std::io::Cursor::new(program), s, &|| false, &mut |_| {}).expect("runs").0
        };
        let (fine, coarse) = (run(setup), run(&comparison_setup(setup, PolicyKind::FeedOnly)));
        let rel = (fine.cycle_time_s - coarse.cycle_time_s).abs() / fine.cycle_time_s;
        assert!(
            rel < 0.02,
            "cycle time {} on the fine cells, {} on the coarse",
            fine.cycle_time_s,
            coarse.cycle_time_s
        );
        let rel = (fine.removed_mm3 - coarse.removed_mm3).abs() / fine.removed_mm3;
        assert!(rel < 0.03, "removed {} against {}", fine.removed_mm3, coarse.removed_mm3);
        fine.removed_mm3
    }

    #[test]
    fn the_comparison_run_on_coarser_dexels_keeps_the_cycle_time() {
        // Two faces of a 30 x 20 x 20 bar on 0.1 mm dexels: a slot on each, under the loop.
        let bar = StockSpec {
            min_x_mm: 0.0,
            min_y_mm: -10.0,
            min_z_mm: -10.0,
            x_mm: 30.0,
            y_mm: 20.0,
            z_mm: 20.0,
            cell_mm: 0.1,
        };
        let faces = vec![
            super::super::sim::FaceStock { a_deg: 0.0, stock: bar },
            super::super::sim::FaceStock { a_deg: 90.0, stock: bar },
        ];
        let program = "%\nG21 G90 G17 G94 G40 G49 G80\nT1 M6\nS1500 M3\nG43 H1\nG0 X-5 Y7\nG0 Z15\n\
                       G1 Z8 F100\nG1 X35 F200\nG0 Z15\nG0 A90\nG0 X-5 Y0\nG1 Z8.5 F100\nG1 X35 F250\nG0 Z15\n\
                       G0 A0\nG53 G0 Z0\nM30\n%\n";
        comparison_agrees(&feed_only_setup(bar, faces), program);
    }

    #[test]
    fn the_comparison_run_on_a_coarser_z_map_keeps_the_cycle_time() {
        // A 3-axis part on a 0.1 mm Z-map: a flat-6 slot, a ball-3 pass along its floor and a
        // sloped ball-3 pass across the block, under the feed-only loop (its feed answers the
        // forces).
        let block = StockSpec {
            min_x_mm: 0.0,
            min_y_mm: 0.0,
            min_z_mm: 0.0,
            x_mm: 30.0,
            y_mm: 20.0,
            z_mm: 10.0,
            cell_mm: 0.1,
        };
        let setup = feed_only_setup(block, Vec::new());
        let coarse = comparison_setup(&setup, PolicyKind::FeedOnly);
        assert!((coarse.stock.cell_mm - 0.2).abs() < 1e-12, "{:?}", coarse.stock);
        let program = "%\nG21 G90 G17 G94 G40 G49 G80\nT1 M6\nS1500 M3\nG43 H1\nG0 X-5 Y10\nG0 Z15\n\
                       G1 Z8 F100\nG1 X35 F200\nG0 Z15\nT2 M6\nS2000 M3\nG43 H2\nG0 X-3 Y10\nG1 Z8 F100\n\
                       G1 X33 F150\nG0 Z15\nG0 X-3 Y4\nG1 Z9.5 F100\nG1 X33 Z8.2 F150\nG0 Z15\nG53 G0 Z0\nM30\n%\n";
        let removed = comparison_agrees(&setup, program);
        assert!(removed > 300.0, "the program cuts: {removed}");

        // A tool spanning fewer than four coarse cells keeps the fine grid.
        let mut small = setup.clone();
        small.tools = tools_for(&emco(), &[(7, "ball-1".into(), None, None)]).expect("tools");
        let min_r = small.tools.iter().map(|t| t.profile.radius_mm()).fold(f64::INFINITY, f64::min);
        assert!(min_r < COMPARISON_MIN_RADIUS_CELLS * 0.2, "{min_r}");
        assert_eq!(comparison_setup(&small, PolicyKind::FeedOnly).stock.cell_mm, 0.1);
    }

    #[test]
    fn a_tool_named_deep_in_a_long_program_is_the_one_cut_with() {
        let mut program = String::from("(T1 flat-6: flat D6.0000 mm, 2 flutes - roughing-x with flat-6)\n");
        for i in 0..30_000 {
            program.push_str(&format!("G1 X{} F100\n", i % 10));
        }
        program.push_str(
            "(T3 ball-1: ball D1.0000 mm, 2 flutes - rest-finishing-raster-x with ball-1)\nT3 M6\n",
        );
        let header = header_tools(std::io::Cursor::new(program.as_bytes()));
        assert_eq!(header.len(), 2);
        let tools = tools_for(&emco(), &header).expect("tools");
        let t3 = tools.iter().find(|t| t.number == 3).expect("T3");
        // Not the table's T3 (ball-6): the program's.
        assert_eq!((t3.name.as_str(), t3.profile.diameter_mm()), ("ball-1", 1.0));
    }
}
