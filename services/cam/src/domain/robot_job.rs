//! A robot milling job as users ask for it: the settings of a job's `robot` section (and of
//! `depthmill plan MESH --robot`), their defaults and checks, the [`RobotJob`] they make for a
//! mesh, and what a plan is reported as (the JSON report and the warnings a job shows).
//!
//! Field names in errors are the job's (`robot.step_mm`), so the REST API, gRPC and the command
//! line name the same thing.

use depthmill_geometry::Mesh;
use nalgebra::{Isometry3, Vector3};

use super::CamError;
use super::clearance::{Blocked, ClearedPath, TiltOptions};
use super::layer_passes::MeshProgramOptions;
use super::robot::{OUT_OF_REACH, RobotCell, RobotJob, RobotPlan};
use super::slice::Topology;
use super::tool::Tool;

/// Tool when none is named.
pub const DEFAULT_TOOL: &str = "flat-6";
/// Distance between layers, mm.
pub const DEFAULT_STEP_MM: f64 = 2.0;
/// Stock around the part's box in X and Y, mm.
pub const DEFAULT_STOCK_MARGIN_MM: f64 = 5.0;
/// Feed, mm/min.
pub const DEFAULT_FEED_MM_MIN: f64 = 600.0;
/// Spindle speed, rpm.
pub const DEFAULT_RPM: f64 = 12_000.0;
/// Distance of the part's centre in front of the robot's base (along its X), mm.
pub const DEFAULT_PART_DISTANCE_MM: f64 = 420.0;

/// Positions, defects and stretches listed in a report (the counts are complete).
pub const LISTED: usize = 100;

/// The settings of a robot job; `None` takes the default (documented on each field).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct RobotSettings {
    /// Library tool name (default [`DEFAULT_TOOL`]).
    pub tool: Option<String>,
    /// Distance between layers, mm (default [`DEFAULT_STEP_MM`]); at most the tool's flute length.
    pub step_mm: Option<f64>,
    /// Radial depth of cut between rings, mm (default: the tool's radius).
    pub radial_depth_mm: Option<f64>,
    /// Stock around the part in X and Y, mm (default [`DEFAULT_STOCK_MARGIN_MM`]).
    pub stock_margin_mm: Option<f64>,
    /// Where the part's origin stands in the robot's base frame, mm (default: the part's box
    /// centred [`DEFAULT_PART_DISTANCE_MM`] in front of the base, its bottom at Z 0).
    pub part_at_mm: Option<[f64; 3]>,
    /// The part's turn about the base's Z axis, degrees (default 0).
    pub part_yaw_deg: Option<f64>,
    /// Feed, mm/min (default [`DEFAULT_FEED_MM_MIN`]).
    pub feed_mm_min: Option<f64>,
    /// Spindle speed, rpm (default [`DEFAULT_RPM`]).
    pub rpm: Option<f64>,
    /// Largest tilt of the tool from upright, degrees (default 40).
    pub max_tilt_deg: Option<f64>,
    /// Flange to spindle nose, mm (default 150).
    pub spindle_length_mm: Option<f64>,
    /// Angle between the flange's axis and the spindle's, degrees (default 90: across the flange).
    pub spindle_mount_deg: Option<f64>,
    /// Spindle body diameter, mm (default 60).
    pub spindle_diameter_mm: Option<f64>,
}

fn range(field: &str, v: Option<f64>, lo: f64, hi: f64, what: &str) -> Result<(), CamError> {
    match v {
        Some(x) if !(x.is_finite() && (lo..=hi).contains(&x)) => {
            Err(CamError::param(format!("robot.{field}"), format!("{x}: must be {what} from {lo} to {hi}")))
        }
        _ => Ok(()),
    }
}

impl RobotSettings {
    /// Checks every value given (ranges only; the tool is looked up by [`RobotSettings::job`]).
    pub fn check(&self) -> Result<(), CamError> {
        if let Some(t) = &self.tool
            && (t.trim().is_empty() || t.len() > 128)
        {
            return Err(CamError::param("robot.tool", "must name a tool of the library, e.g. flat-6"));
        }
        range("step_mm", self.step_mm, 0.05, 100.0, "a layer distance in mm")?;
        range("radial_depth_mm", self.radial_depth_mm, 0.01, 100.0, "a radial depth in mm")?;
        range("stock_margin_mm", self.stock_margin_mm, 0.0, 1000.0, "a margin in mm")?;
        if let Some(at) = self.part_at_mm {
            for (k, v) in ["x", "y", "z"].iter().zip(at) {
                range(&format!("part_at_mm.{k}"), Some(v), -5000.0, 5000.0, "a position in mm")?;
            }
        }
        range("part_yaw_deg", self.part_yaw_deg, -360.0, 360.0, "an angle in degrees")?;
        range("feed_mm_min", self.feed_mm_min, 1.0, 60_000.0, "a feed in mm/min")?;
        range("rpm", self.rpm, 1.0, 100_000.0, "a spindle speed in rpm")?;
        range("max_tilt_deg", self.max_tilt_deg, 0.0, 80.0, "a tilt in degrees")?;
        range("spindle_length_mm", self.spindle_length_mm, 0.0, 1000.0, "a length in mm")?;
        range("spindle_mount_deg", self.spindle_mount_deg, 0.0, 90.0, "an angle in degrees")?;
        range("spindle_diameter_mm", self.spindle_diameter_mm, 0.0, 500.0, "a diameter in mm")?;
        Ok(())
    }

    /// The tool's name.
    pub fn tool_name(&self) -> &str {
        self.tool.as_deref().unwrap_or(DEFAULT_TOOL)
    }

    pub fn feed(&self) -> f64 {
        self.feed_mm_min.unwrap_or(DEFAULT_FEED_MM_MIN)
    }

    pub fn spindle_rpm(&self) -> f64 {
        self.rpm.unwrap_or(DEFAULT_RPM)
    }

    /// [`RobotSettings::check`], then what needs the tool: a layer step within its flutes.
    pub fn check_with(&self, tool: &Tool) -> Result<(), CamError> {
        self.check()?;
        let step = self.step_mm.unwrap_or(DEFAULT_STEP_MM);
        if step > tool.cutting_length_mm {
            return Err(CamError::param(
                "robot.step_mm",
                format!(
                    "{step}: a layer deeper than the flutes of {} ({} mm long); take a step of at most that",
                    tool.name, tool.cutting_length_mm
                ),
            ));
        }
        Ok(())
    }

    /// The job of cutting `mesh` (millimetres) with `tool`, after [`RobotSettings::check_with`].
    pub fn job(&self, mesh: &Mesh, tool: Tool) -> Result<RobotJob, CamError> {
        self.check_with(&tool)?;
        let step = self.step_mm.unwrap_or(DEFAULT_STEP_MM);
        let bounds = mesh
            .bounds()
            .ok_or_else(|| CamError::param("input.artifact", "the mesh has no finite vertex"))?;
        let (lo, hi) = (bounds.min.coords, bounds.max.coords);
        let at = match self.part_at_mm {
            Some(a) => Vector3::from(a),
            None => Vector3::new(DEFAULT_PART_DISTANCE_MM - 0.5 * (lo.x + hi.x), -0.5 * (lo.y + hi.y), -lo.z),
        };
        let base_from_part = Isometry3::new(at, Vector3::z() * self.part_yaw_deg.unwrap_or(0.0).to_radians());
        let default_cell = RobotCell::viper_s650(base_from_part);
        let cell = RobotCell {
            spindle_length_mm: self.spindle_length_mm.unwrap_or(default_cell.spindle_length_mm),
            spindle_mount_deg: self.spindle_mount_deg.unwrap_or(default_cell.spindle_mount_deg),
            spindle_diameter_mm: self.spindle_diameter_mm.unwrap_or(default_cell.spindle_diameter_mm),
            ..default_cell
        };
        let tilt = TiltOptions::default();
        Ok(RobotJob {
            layers: MeshProgramOptions {
                radial_depth_mm: self.radial_depth_mm,
                stock_margin_mm: self.stock_margin_mm.unwrap_or(DEFAULT_STOCK_MARGIN_MM),
                ..MeshProgramOptions::new(step, tool.radius_mm())
            },
            tilt: TiltOptions { max_tilt_deg: self.max_tilt_deg.unwrap_or(tilt.max_tilt_deg), ..tilt },
            cell,
            feed_mm_min: self.feed(),
            tool,
            auto_place: self.part_at_mm.is_none() && self.part_yaw_deg.is_none(),
        })
    }
}

fn clearance_json(p: &ClearedPath) -> serde_json::Value {
    serde_json::json!({
        "positions": p.points.len(),
        "colliding_upright": p.colliding,
        "tilted": p.tilted,
        "max_tilt_deg": p.max_tilt_deg,
        "max_axis_rate_deg_mm": p.max_rate_deg_mm,
        "blocked": p.blocked.len(),
        "blocked_positions": p.blocked.iter().take(LISTED).collect::<Vec<_>>(),
    })
}

/// The report of a robot plan (JSON): the mesh's edge check and layer defects, layers, rings,
/// links, holes too narrow for the tool, the clearance check (tilts, blocked positions), the
/// arm's program (branch, timing, dexterity, margins, unreachable stretches) and the time taken.
/// `input` names the mesh; `topology` is its edge check.
pub fn robot_report(
    plan: &RobotPlan,
    topology: &Topology,
    input: &str,
    tool: &str,
    planning_s: f64,
) -> serde_json::Value {
    let unreached: Vec<serde_json::Value> = plan
        .layers
        .passes
        .iter()
        .flat_map(|p| {
            p.unreached
                .iter()
                .map(move |u| serde_json::json!({"z_mm": p.z_mm, "at_mm": u.at, "area_mm2": u.area_mm2}))
        })
        .take(LISTED)
        .collect();
    let r = &plan.robot;
    let defects: Vec<&super::slice::Defect> = plan.layers.layers.iter().flat_map(|l| &l.defects).collect();
    let open_chains: usize = plan.layers.layers.iter().map(|l| l.open.len()).sum();
    serde_json::json!({
        "input": input,
        "mesh": {
            "closed_manifold": topology.is_closed_manifold(),
            "boundary_edges": topology.boundary.len(),
            "non_manifold_edges": topology.non_manifold.len(),
            "misoriented_edges": topology.misoriented.len(),
            "layer_defects": defects.len(),
            "listed_layer_defects": defects.iter().take(LISTED).collect::<Vec<_>>(),
            "open_chains": open_chains,
        },
        "tool": tool,
        "layers": plan.layers.layers.len(),
        "rings": plan.layers.passes.iter().map(|p| p.rings.len()).sum::<usize>(),
        "feed_links": plan.layers.program.feed_links,
        "retracts": plan.layers.program.retracts,
        "holes_too_narrow": unreached,
        "clearance": clearance_json(&plan.path),
        "robot": {
            "arm": r.arm,
            "configuration": r.configuration,
            "spin_deg": r.spin_deg,
            "base_from_part": r.base_from_part,
            "duration_s": r.duration_s,
            "feed_s": r.feed_s,
            "rapid_s": r.rapid_s,
            "joint_limited_steps": r.joint_limited_steps,
            "min_dexterity": r.min_dexterity,
            "min_margins": r.min_margins,
            "unreachable": r.unreachable.iter().take(LISTED).collect::<Vec<_>>(),
            "unreachable_stretches": r.unreachable.len(),
        },
        "placement": plan.placement,
        "planning_s": planning_s,
    })
}

/// What a person should hear about a robot plan, as `(code, message)`: an open or non-manifold
/// mesh, layer defects and open chains, holes too narrow for the tool, positions no tilt clears
/// (lifted over) and stretches the arm cannot reach, each with where.
pub fn robot_warnings(plan: &RobotPlan, topology: &Topology) -> Vec<(&'static str, String)> {
    let mut out = Vec::new();
    if let Some(p) = &plan.placement {
        out.push((
            "placement",
            format!(
                "at the default place the arm reaches {} of the program's {} positions; the part was placed {:.0} mm in front of the base, turned {:.0}°, its bottom at {:.0} mm, where it reaches {} ({} places tried; set robot.part_at_mm to choose)",
                p.reached_at_default, p.positions, p.distance_mm, p.yaw_deg, p.height_mm, p.reached, p.tried
            ),
        ));
    }
    if !topology.is_closed_manifold() {
        out.push((
            "mesh_not_closed",
            format!(
                "the mesh is not closed: {} open, {} non-manifold and {} misoriented edges; layers are sliced where they close",
                topology.boundary.len(),
                topology.non_manifold.len(),
                topology.misoriented.len()
            ),
        ));
    }
    let defects: Vec<&super::slice::Defect> = plan.layers.layers.iter().flat_map(|l| &l.defects).collect();
    if let Some(d) = defects.first() {
        out.push((
            "layer_defects",
            format!(
                "{} layer defects (closed where the chain's ends meet), the first at z {:.3} mm, ({:.3}, {:.3}): {}",
                defects.len(),
                d.z_mm,
                d.at[0],
                d.at[1],
                d.message
            ),
        ));
    }
    let open: usize = plan.layers.layers.iter().map(|l| l.open.len()).sum();
    if open > 0 {
        out.push((
            "open_chains",
            format!("{open} open contour chains are not cut (the mesh has holes there)"),
        ));
    }
    let narrow: Vec<(f64, &super::layer_passes::Unreached)> =
        plan.layers.passes.iter().flat_map(|p| p.unreached.iter().map(move |u| (p.z_mm, u))).collect();
    if let Some((z, u)) = narrow.first() {
        out.push((
            "too_narrow",
            format!(
                "{} holes or slots are narrower than the tool and stay uncut, the first {:.2} mm² at ({:.2}, {:.2}) on layer z {z:.3} mm",
                narrow.len(),
                u.area_mm2,
                u.at[0],
                u.at[1]
            ),
        ));
    }
    let (reach, collide): (Vec<&Blocked>, Vec<&Blocked>) =
        plan.path.blocked.iter().partition(|b| b.part == OUT_OF_REACH);
    if let Some(b) = collide.first() {
        out.push((
            "blocked",
            format!(
                "{} positions no tilt up to the limit clears (lifted over, left uncut), the first at ({:.2}, {:.2}, {:.2}) mm where the {} would enter the part {:.2} mm",
                collide.len(),
                b.at_mm[0],
                b.at_mm[1],
                b.at_mm[2],
                b.part,
                b.depth_mm
            ),
        ));
    }
    if let Some(b) = reach.first() {
        out.push((
            "out_of_reach",
            format!(
                "{} cutting positions the arm cannot follow (lifted over, left uncut), the first at ({:.2}, {:.2}, {:.2}) mm",
                reach.len(),
                b.at_mm[0],
                b.at_mm[1],
                b.at_mm[2]
            ),
        ));
    }
    if let Some(s) = plan.robot.unreachable.first() {
        out.push((
            "unreachable",
            format!(
                "{} stretches the arm cannot follow, the first from ({:.2}, {:.2}, {:.2}) mm: {}",
                plan.robot.unreachable.len(),
                s.at_mm[0],
                s.at_mm[1],
                s.at_mm[2],
                s.reason
            ),
        ));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::domain::tool::ToolLibrary;

    #[test]
    fn values_out_of_range_are_named_by_their_job_field() {
        let cases: [(RobotSettings, &str); 5] = [
            (RobotSettings { step_mm: Some(0.0), ..Default::default() }, "robot.step_mm"),
            (RobotSettings { feed_mm_min: Some(f64::NAN), ..Default::default() }, "robot.feed_mm_min"),
            (RobotSettings { part_at_mm: Some([0.0, 9e9, 0.0]), ..Default::default() }, "robot.part_at_mm.y"),
            (
                RobotSettings { spindle_mount_deg: Some(120.0), ..Default::default() },
                "robot.spindle_mount_deg",
            ),
            (RobotSettings { tool: Some(" ".into()), ..Default::default() }, "robot.tool"),
        ];
        for (s, field) in cases {
            match s.check() {
                Err(CamError::InvalidParameter { field: f, .. }) => assert_eq!(f, field),
                other => panic!("{field}: {other:?}"),
            }
        }
        assert!(RobotSettings::default().check().is_ok());
    }

    #[test]
    fn defaults_place_the_part_in_front_of_the_arm_and_a_step_deeper_than_the_flutes_is_refused() {
        let tool = ToolLibrary::builtin().expect("library").resolve("flat-6").expect("tool");
        let mesh = Mesh::cuboid(20.0, 10.0, 8.0);
        let job = RobotSettings::default().job(&mesh, tool.clone()).expect("job");
        let t = job.cell.base_from_part.translation.vector;
        assert_eq!([t.x, t.y, t.z], [DEFAULT_PART_DISTANCE_MM - 10.0, -5.0, 0.0]);
        assert_eq!(job.layers.step_mm, DEFAULT_STEP_MM);
        assert_eq!(job.feed_mm_min, DEFAULT_FEED_MM_MIN);
        let deep = RobotSettings { step_mm: Some(tool.cutting_length_mm + 1.0), ..Default::default() };
        match deep.job(&mesh, tool) {
            Err(CamError::InvalidParameter { field, message }) => {
                assert_eq!(field, "robot.step_mm");
                assert!(message.contains("flutes"), "{message}");
            }
            other => panic!("{other:?}"),
        }
    }
}
