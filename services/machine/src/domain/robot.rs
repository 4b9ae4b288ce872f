//! Robot milling in simulation: the CAM's joint trajectory (`depthmill-joint-trajectory/1`, the
//! Adept Viper s650 with a spindle on its flange) replayed through the arm's forward kinematics
//! ([`depthmill_geometry::arm`]) on the dexel stock ([`super::dexel`]).
//!
//! What cuts is where the joints put the tool, not where the program meant it: between two
//! trajectory points the joints move linearly (as the controller interpolates them) and the tool
//! pose along the way comes from forward kinematics, so an IK error, a wrist swing or a joint
//! jump shows in the part. Each step is cut with [`DexelStock::cut_moving`] (tool turning along
//! the step, sampled within `max_error_mm`). Material removed by a rapid move is reported
//! separately: on a real cell it is a crash.
//!
//! The machined part is measured against the part's mesh (surface samples): positive where
//! material is left over the surface, negative where the tool cut into the part.

use depthmill_geometry::ToolProfile;
use depthmill_geometry::arm::ArmModel;
use nalgebra::{Isometry3, Matrix3, Matrix4, Point3, Rotation3, Translation3, Unit, UnitQuaternion, Vector3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::dexel::{Blank, DexelCells, DexelError, DexelStock, OrientedBox, ToolSolid};

/// The trajectory file format this module reads.
pub const TRAJECTORY_FORMAT: &str = "depthmill-joint-trajectory/1";

/// Most points of a trajectory.
pub const MAX_POINTS: usize = 5_000_000;

/// A joint trajectory file (see the CAM's robot module for its fields).
#[derive(Debug, Clone, Deserialize)]
pub struct Trajectory {
    pub format: String,
    pub base_from_part: [[f64; 4]; 4],
    pub flange_from_tip: [[f64; 4]; 4],
    pub tool_profile: ToolProfile,
    pub tool_length_mm: f64,
    pub stock_min_mm: [f64; 3],
    pub stock_max_mm: [f64; 3],
    pub points: Vec<TrajectoryPoint>,
}

/// One point of a [`Trajectory`].
#[derive(Debug, Clone, Copy, Deserialize)]
pub struct TrajectoryPoint {
    pub t_s: f64,
    pub q_deg: [f64; 6],
    pub rapid: bool,
}

/// Why a trajectory cannot be run.
#[derive(Debug, thiserror::Error)]
pub enum RobotRunError {
    #[error("trajectory: {0}")]
    Json(String),
    #[error("trajectory: {field} {value}: {expected}")]
    Invalid { field: String, value: String, expected: String },
    #[error(transparent)]
    Dexel(#[from] DexelError),
    #[error("the run was stopped on request")]
    Stopped,
}

fn invalid(field: impl Into<String>, value: impl ToString, expected: impl Into<String>) -> RobotRunError {
    RobotRunError::Invalid { field: field.into(), value: value.to_string(), expected: expected.into() }
}

/// A rigid transform from a row-major 4 x 4 matrix, checked: finite, last row `0 0 0 1`, a proper
/// rotation (orthonormal within 1e-6, determinant +1).
fn rigid(field: &str, m: &[[f64; 4]; 4]) -> Result<Isometry3<f64>, RobotRunError> {
    if m.iter().flatten().any(|v| !v.is_finite()) {
        return Err(invalid(field, format!("{m:?}"), "finite numbers"));
    }
    let h = Matrix4::from_fn(|r, c| m[r][c]);
    if (h.row(3) - nalgebra::RowVector4::new(0.0, 0.0, 0.0, 1.0)).norm() > 1e-9 {
        return Err(invalid(field, format!("last row {:?}", m[3]), "0 0 0 1"));
    }
    let r: Matrix3<f64> = h.fixed_view::<3, 3>(0, 0).into_owned();
    if (r * r.transpose() - Matrix3::identity()).norm() > 1e-6 || (r.determinant() - 1.0).abs() > 1e-6 {
        return Err(invalid(
            field,
            format!("{m:?}"),
            "a rotation (orthonormal, determinant 1) and a translation",
        ));
    }
    let rot = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(r));
    Ok(Isometry3::from_parts(Translation3::new(m[0][3], m[1][3], m[2][3]), rot))
}

impl Trajectory {
    /// Reads and checks a trajectory file's JSON; errors name the line and column, or the field
    /// and the point.
    pub fn from_json(bytes: &[u8]) -> Result<Self, RobotRunError> {
        let t: Trajectory = serde_json::from_slice(bytes).map_err(|e| RobotRunError::Json(e.to_string()))?;
        t.validate()?;
        Ok(t)
    }

    /// Checks the format, the transforms, the stock, the tool and every point against the arm's
    /// joint limits.
    pub fn validate(&self) -> Result<(), RobotRunError> {
        if self.format != TRAJECTORY_FORMAT {
            return Err(invalid("format", &self.format, format!("\"{TRAJECTORY_FORMAT}\"")));
        }
        rigid("base_from_part", &self.base_from_part)?;
        rigid("flange_from_tip", &self.flange_from_tip)?;
        if !(self.tool_length_mm.is_finite() && self.tool_length_mm > self.tool_profile.max_height_mm()) {
            return Err(invalid("tool_length_mm", self.tool_length_mm, "longer than the cutting profile"));
        }
        for k in 0..3 {
            let (lo, hi) = (self.stock_min_mm[k], self.stock_max_mm[k]);
            if !(lo.is_finite() && hi.is_finite() && hi > lo) {
                return Err(invalid(
                    format!("stock {}", ["x", "y", "z"][k]),
                    format!("{lo}..{hi}"),
                    "finite, min below max",
                ));
            }
        }
        if self.points.is_empty() || self.points.len() > MAX_POINTS {
            return Err(invalid("points", self.points.len(), format!("1 to {MAX_POINTS} points")));
        }
        let arm = ArmModel::viper_s650();
        let mut t_prev = f64::NEG_INFINITY;
        for (i, p) in self.points.iter().enumerate() {
            if !p.t_s.is_finite() || p.t_s < t_prev {
                return Err(invalid(
                    format!("points[{i}].t_s"),
                    p.t_s,
                    "finite and not before the point before",
                ));
            }
            t_prev = p.t_s;
            if let Some(j) = p.q_deg.iter().position(|q| !q.is_finite()) {
                return Err(invalid(format!("points[{i}].q_deg[{j}]"), p.q_deg[j], "a finite angle"));
            }
            arm.check_limits(&p.q_deg)
                .map_err(|e| invalid(format!("points[{i}]"), e, "within the arm's joint limits"))?;
        }
        Ok(())
    }
}

/// How a trajectory is simulated.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct RobotRunOptions {
    /// Dexel cell, mm (all three grids).
    pub cell_mm: f64,
    /// Largest distance of the swept tool from its true path within a step, mm.
    pub max_error_mm: f64,
}

/// The machined part against the part's mesh.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct MeshDeviation {
    pub points: usize,
    /// Deepest cut into the part (≥ 0), mm, and where (the surface sample).
    pub max_gouge_mm: f64,
    pub max_gouge_at_mm: [f64; 3],
    pub max_leftover_mm: f64,
    /// Signed mean (material left positive), and the mean material left (gouges count as 0).
    pub mean_mm: f64,
    pub mean_leftover_mm: f64,
    pub rms_mm: f64,
    /// Share of the samples within ±0.1 mm and within ±1 mm of the surface.
    pub within_0_1_mm: f64,
    pub within_1_mm: f64,
    /// Each reference point's deviation, in the order given (for the view mesh's colours).
    #[serde(skip)]
    pub per_point: Vec<f32>,
}

/// What a simulated robot run did.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct RobotRunReport {
    pub points: usize,
    pub steps_cut: usize,
    pub cycle_time_s: f64,
    pub stock_volume_mm3: f64,
    pub removed_mm3: f64,
    /// Removed by rapid moves (a crash on a real cell), and where (the first
    /// [`LISTED_RAPID_CUTS`]: the index of the point the rapid goes to and its tip).
    pub rapid_removed_mm3: f64,
    pub rapid_cuts: Vec<RapidCut>,
    pub final_volume_mm3: f64,
    pub options: RobotRunOptions,
    pub deviation: Option<MeshDeviation>,
}

/// A rapid move that removed material.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct RapidCut {
    pub point: usize,
    pub at_mm: [f64; 3],
    pub removed_mm3: f64,
}

/// Rapid cuts listed in a report (the total counts them all).
pub const LISTED_RAPID_CUTS: usize = 20;

/// Distances beyond this are clipped in the deviation figures, mm.
pub const DEVIATION_CAP_MM: f64 = 10.0;

/// Runs `traj` on a dexel stock of its stock box and measures the result at `reference` (points
/// on the part's surface, part frame), if given.
pub fn run(
    traj: &Trajectory,
    opts: &RobotRunOptions,
    reference: Option<&[Point3<f64>]>,
) -> Result<(RobotRunReport, DexelStock), RobotRunError> {
    run_watched(traj, opts, reference, &|_, _| false)
}

/// [`run`] asking `stop` with the steps done and their number before every step (progress for
/// a caller that streams it); `true` ends it with [`RobotRunError::Stopped`].
pub fn run_watched(
    traj: &Trajectory,
    opts: &RobotRunOptions,
    reference: Option<&[Point3<f64>]>,
    stop: &(dyn Fn(usize, usize) -> bool + Sync),
) -> Result<(RobotRunReport, DexelStock), RobotRunError> {
    traj.validate()?;
    if !(opts.max_error_mm.is_finite() && opts.max_error_mm > 0.0) {
        return Err(invalid("max_error_mm", opts.max_error_mm, "a positive distance"));
    }
    let base_from_part = rigid("base_from_part", &traj.base_from_part)?;
    let arm = ArmModel::viper_s650().with_tool(rigid("flange_from_tip", &traj.flange_from_tip)?);
    let part_from_base = base_from_part.inverse();
    let pose = |q: &[f64; 6]| -> (Point3<f64>, Unit<Vector3<f64>>) {
        let p = part_from_base * arm.fk(q);
        // The tool frame's Z points from the holder to the tip; the cut takes the axis the other way.
        (Point3::from(p.translation.vector), Unit::new_normalize(-(p.rotation * Vector3::z())))
    };
    let blank = Blank {
        boxes: vec![OrientedBox::aligned(Point3::from(traj.stock_min_mm), Point3::from(traj.stock_max_mm))],
    };
    let mut stock = DexelStock::new(&blank, &DexelCells::tri(opts.cell_mm))?;
    let tool = ToolSolid::new(&traj.tool_profile, traj.tool_length_mm)?;
    let start_volume = stock.volume_mm3();
    let (mut removed, mut rapid_removed, mut steps) = (0.0, 0.0, 0);
    let mut rapid_cuts = Vec::new();
    let total = traj.points.len().saturating_sub(1);
    for (i, w) in traj.points.windows(2).enumerate() {
        if stop(i, total) {
            return Err(RobotRunError::Stopped);
        }
        let (a, b) = (&w[0], &w[1]);
        if a.q_deg == b.q_deg {
            continue;
        }
        let along = |s: f64| pose(&std::array::from_fn(|j| a.q_deg[j] + s * (b.q_deg[j] - a.q_deg[j])));
        let cut = stock.cut_moving(&tool, &along, opts.max_error_mm)?;
        steps += 1;
        removed += cut.volume_mm3;
        if b.rapid && cut.volume_mm3 > 0.0 {
            rapid_removed += cut.volume_mm3;
            if rapid_cuts.len() < LISTED_RAPID_CUTS {
                rapid_cuts.push(RapidCut {
                    point: i + 1,
                    at_mm: pose(&b.q_deg).0.coords.into(),
                    removed_mm3: cut.volume_mm3,
                });
            }
        }
    }
    let deviation = reference.filter(|r| !r.is_empty()).map(|r| {
        let d: Vec<f64> = r.par_iter().map(|p| stock.deviation_at(p, DEVIATION_CAP_MM)).collect();
        let n = d.len() as f64;
        let within = |t: f64| d.iter().filter(|v| v.abs() <= t).count() as f64 / n;
        let worst = (0..d.len()).min_by(|&a, &b| d[a].total_cmp(&d[b])).unwrap_or(0);
        MeshDeviation {
            points: d.len(),
            max_gouge_mm: d.iter().fold(0.0f64, |m, v| m.max(-v)),
            max_gouge_at_mm: r[worst].coords.into(),
            max_leftover_mm: d.iter().fold(0.0f64, |m, v| m.max(*v)),
            mean_mm: d.iter().sum::<f64>() / n,
            mean_leftover_mm: d.iter().map(|v| v.max(0.0)).sum::<f64>() / n,
            rms_mm: (d.iter().map(|v| v * v).sum::<f64>() / n).sqrt(),
            within_0_1_mm: within(0.1),
            within_1_mm: within(1.0),
            per_point: d.iter().map(|&v| v as f32).collect(),
        }
    });
    let report = RobotRunReport {
        points: traj.points.len(),
        steps_cut: steps,
        cycle_time_s: traj.points.last().map_or(0.0, |p| p.t_s),
        stock_volume_mm3: start_volume,
        removed_mm3: removed,
        rapid_removed_mm3: rapid_removed,
        rapid_cuts,
        final_volume_mm3: stock.volume_mm3(),
        options: *opts,
        deviation,
    };
    Ok((report, stock))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rows(i: &Isometry3<f64>) -> [[f64; 4]; 4] {
        let m = i.to_homogeneous();
        std::array::from_fn(|r| std::array::from_fn(|c| m[(r, c)]))
    }

    /// A straight slot: the arm at two joint positions whose tips are 20 mm apart at the same
    /// height, the tool pointing down (solved here by the arm's own IK).
    fn slot(depth: f64) -> Trajectory {
        let flange_from_tip = Isometry3::from_parts(
            Translation3::new(0.0, -250.0, 0.0),
            UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::FRAC_PI_2),
        );
        let arm = ArmModel::viper_s650().with_tool(flange_from_tip);
        let base_from_part = Isometry3::translation(420.0, 0.0, 0.0);
        let down = UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI);
        let at = |x: f64, z: f64| base_from_part * Isometry3::from_parts(Translation3::new(x, 0.0, z), down);
        let mut q = ArmModel::HOME_DEG;
        let mut points = Vec::new();
        for (i, (x, z)) in
            [(-10.0, 20.0), (-10.0, 10.0 - depth), (10.0, 10.0 - depth), (10.0, 20.0)].iter().enumerate()
        {
            let c = depthmill_geometry::arm::IkConfig::default();
            let s = arm.ik_nearest(&at(*x, *z), &q, &c).expect("reachable");
            q = s.q_deg;
            points.push(TrajectoryPoint { t_s: i as f64, q_deg: q, rapid: false });
        }
        Trajectory {
            format: TRAJECTORY_FORMAT.into(),
            base_from_part: rows(&base_from_part),
            flange_from_tip: rows(&flange_from_tip),
            tool_profile: ToolProfile::flat(6.0).expect("tool"),
            tool_length_mm: 30.0,
            stock_min_mm: [-20.0, -10.0, 0.0],
            stock_max_mm: [20.0, 10.0, 10.0],
            points,
        }
    }

    #[test]
    fn a_slot_cut_by_the_arm_removes_the_swept_volume() {
        let t = slot(2.0);
        let opts = RobotRunOptions { cell_mm: 0.1, max_error_mm: 0.01 };
        let (r, stock) = run(&t, &opts, None).expect("run");
        // A 6 mm slot 20 mm long with round ends, 2 mm deep: (20·6 + π·9)·2 mm³, plus the
        // plunges (inside the same ends).
        let expected = (20.0 * 6.0 + std::f64::consts::PI * 9.0) * 2.0;
        assert!((r.removed_mm3 - expected).abs() < 0.03 * expected, "{} vs {expected}", r.removed_mm3);
        assert!((r.stock_volume_mm3 - r.final_volume_mm3 - r.removed_mm3).abs() < 1e-6 * r.stock_volume_mm3);
        assert_eq!(r.rapid_removed_mm3, 0.0);
        // The slot's floor is 2 mm down in its middle, untouched beside it.
        assert!(!stock.contains(&Point3::new(0.0, 0.0, 8.5)));
        assert!(stock.contains(&Point3::new(0.0, 0.0, 7.5)));
        assert!(stock.contains(&Point3::new(0.0, 5.0, 9.5)));
        // Measured against the slot's own floor and walls: on the surface.
        let floor: Vec<Point3<f64>> = (0..21).map(|i| Point3::new(-10.0 + i as f64, 0.0, 8.0)).collect();
        let (r, _) = run(&t, &opts, Some(&floor)).expect("run");
        let d = r.deviation.expect("deviation");
        assert!(d.max_gouge_mm < 0.1 && d.max_leftover_mm < 0.1, "{d:?}");
    }

    #[test]
    fn bad_trajectories_are_refused_with_what_is_wrong() {
        let mut t = slot(1.0);
        t.format = "something/2".into();
        assert!(t.validate().expect_err("format").to_string().contains("format something/2"));
        let mut t = slot(1.0);
        t.points[2].q_deg[4] = 170.0;
        let e = t.validate().expect_err("limit").to_string();
        assert!(e.contains("points[2]") && e.contains("joint 5"), "{e}");
        let mut t = slot(1.0);
        t.base_from_part[0][0] = 2.0;
        assert!(t.validate().expect_err("rigid").to_string().contains("base_from_part"));
        let mut t = slot(1.0);
        t.points[1].t_s = -1.0;
        assert!(t.validate().expect_err("time").to_string().contains("points[1].t_s"));
        let e = Trajectory::from_json(b"{\"format\": 3}").expect_err("json").to_string();
        assert!(e.contains("line 1"), "{e}");
        let e =
            run(&slot(1.0), &RobotRunOptions { cell_mm: 0.1, max_error_mm: 0.0 }, None).expect_err("error");
        assert!(e.to_string().contains("max_error_mm"), "{e}");
    }
}
