//! Scan planning: straight passes of the sensor at a set standoff over the part, station by
//! station (one table angle each), each pass checked for reachability by inverse kinematics.

use nalgebra::{Isometry3, Point3, Rotation3, Translation3, UnitQuaternion, Vector3};
use serde::Serialize;

use super::options::{ScanMode, ScanOptions};
use super::{CellLayout, PartPlacement, ScanError};
use crate::domain::scanner::ScannerSpec;
use depthmill_geometry::arm::{ArmModel, IkConfig, JointLimit};

/// One straight pass of the sensor at rest orientation.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Pass {
    /// Pass id (written with every point it produced), from 1.
    pub id: u16,
    /// `world_from_sensor` where the pass starts.
    #[serde(skip)]
    pub start: Isometry3<f64>,
    /// `world_from_sensor` where it ends (same orientation).
    #[serde(skip)]
    pub end: Isometry3<f64>,
    /// Joints at the start, degrees.
    pub q_start_deg: [f64; 6],
    /// Joints at the end, degrees.
    pub q_end_deg: [f64; 6],
    /// Length, mm.
    pub length_mm: f64,
    /// Largest distance (mm) of the joint-interpolated path from the straight line (dynamic mode
    /// moves the joints together; every frame is placed with its latched pose, so this bends the
    /// pass but does not misplace points).
    pub path_deviation_mm: f64,
    /// Dexterity `sqrt(det(J^T J))` at the start, the lowest along the pass.
    pub min_dexterity: f64,
    /// Smallest distance of the arm and the scanner from the cell's obstacles along the pass, mm.
    pub min_clearance_mm: f64,
}

/// The passes at one table angle.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Station {
    /// Commanded table angle, degrees.
    pub table_deg: f64,
    pub passes: Vec<Pass>,
}

/// The whole plan.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ScanPlan {
    pub stations: Vec<Station>,
    /// Automatic passes left out because the arm cannot reach them at that table angle (the
    /// other angles bring that side of the part nearer), with the reason.
    pub skipped: Vec<String>,
}

impl ScanPlan {
    /// Number of passes.
    pub fn passes(&self) -> usize {
        self.stations.iter().map(|s| s.passes.len()).sum()
    }

    /// Total path length, mm.
    pub fn length_mm(&self) -> f64 {
        self.stations.iter().flat_map(|s| &s.passes).map(|p| p.length_mm).sum()
    }

    /// Frames the plan takes at `opts`' line spacing (an estimate for progress and the frame guard).
    pub fn estimated_frames(&self, opts: &ScanOptions) -> u64 {
        (self.length_mm() / opts.line_spacing_mm).ceil() as u64 + self.passes() as u64
    }
}

/// `world_from_sensor` orientation of a pass along world `dir` (horizontal unit vector), looking
/// down, tilted by `tilt_deg` about the pass direction: sensor Y along `−dir`, X across, Z down.
pub fn sensor_orientation(dir: &Vector3<f64>, tilt_deg: f64) -> UnitQuaternion<f64> {
    let y = -dir.normalize();
    let z = Vector3::new(0.0, 0.0, -1.0);
    let x = y.cross(&z);
    let r = Rotation3::from_basis_unchecked(&[x, y, z]);
    let base = UnitQuaternion::from_rotation_matrix(&r);
    base * UnitQuaternion::from_axis_angle(&Vector3::y_axis(), tilt_deg.to_radians())
}

/// A straight sensor path, world frame: start and end.
type Segment = (Point3<f64>, Point3<f64>);

/// Builds the plan: automatic from the part's bounds, or from `opts.passes`.
pub fn plan_scan(
    placement: &PartPlacement,
    layout: &CellLayout,
    arm: &ArmModel,
    spec: &ScannerSpec,
    opts: &ScanOptions,
) -> Result<ScanPlan, ScanError> {
    let mut raw: Vec<(f64, Vec<Segment>)> = Vec::new();
    if let Some(given) = &opts.passes {
        for p in given {
            let w = placement.world_from_part(layout, p.table_deg);
            let a = w * Point3::from(p.start_mm);
            let b = w * Point3::from(p.end_mm);
            match raw.iter_mut().find(|(deg, _)| *deg == p.table_deg) {
                Some((_, list)) => list.push((a, b)),
                None => raw.push((p.table_deg, vec![(a, b)])),
            }
        }
    } else {
        for &deg in &opts.table_angles_deg {
            raw.push((deg, auto_passes(placement, layout, spec, opts, deg, opts.standoff_mm)));
        }
    }
    let mut obstacles = super::obstacles::cell_obstacles(layout, placement);
    obstacles.extend(opts.obstacles.iter().cloned());
    let mut seed = ArmModel::HOME_DEG;
    let mut id: u16 = 0;
    let mut stations = Vec::with_capacity(raw.len());
    let mut skipped = Vec::new();
    let mut first_error = None;
    let automatic = opts.passes.is_none();
    for (deg, lines) in raw {
        let mut passes = Vec::with_capacity(lines.len());
        for (a, b) in lines {
            let next = id.checked_add(1).ok_or_else(|| ScanError::InvalidOption {
                field: "scan".into(),
                value: "more than 65535 passes".into(),
                reason: "a scan has at most 65535 passes (pass ids are 16-bit)".into(),
            })?;
            match make_pass(arm, opts, &obstacles, next, deg, a, b, &seed) {
                Ok(pass) => {
                    id = next;
                    seed = pass.q_end_deg;
                    passes.push(pass);
                }
                // An automatic pass out of reach at this angle: the other angles bring that side
                // nearer. A given pass out of reach is the user's error.
                Err(e @ ScanError::Unreachable { .. }) if automatic => {
                    skipped.push(e.to_string());
                    first_error.get_or_insert(e);
                }
                Err(e) => return Err(e),
            }
        }
        if !passes.is_empty() {
            stations.push(Station { table_deg: deg, passes });
        }
    }
    if stations.is_empty()
        && let Some(e) = first_error
    {
        return Err(e);
    }
    Ok(ScanPlan { stations, skipped })
}

/// Parallel passes along world Y over the part's extent at table angle `deg`, alternating in
/// direction, sensor at `standoff` above the part's top.
pub(crate) fn auto_passes(
    placement: &PartPlacement,
    layout: &CellLayout,
    spec: &ScannerSpec,
    opts: &ScanOptions,
    deg: f64,
    standoff: f64,
) -> Vec<Segment> {
    let (lo, hi) = placement.world_extent(layout, deg);
    let line = spec.line_length_at(standoff);
    let width = line * (1.0 - opts.overlap);
    let ex = hi.x - lo.x;
    let n = if ex <= line { 1 } else { 1 + ((ex - line) / width).ceil() as usize };
    let step = if n > 1 { (ex - line) / (n - 1) as f64 } else { 0.0 };
    let z = hi.z + standoff;
    (0..n)
        .map(|i| {
            let x = if n == 1 { 0.5 * (lo.x + hi.x) } else { lo.x + 0.5 * line + step * i as f64 };
            let y0 = lo.y - opts.margin_mm;
            let y1 = hi.y + opts.margin_mm;
            let (a, b) = (Point3::new(x, y0, z), Point3::new(x, y1, z));
            if i % 2 == 0 { (a, b) } else { (b, a) }
        })
        .collect()
}

/// A pass from sensor position `a` to `b` (world), IK-checked at both ends and along the way.
#[allow(clippy::too_many_arguments)]
pub(crate) fn make_pass(
    arm: &ArmModel,
    opts: &ScanOptions,
    obstacles: &[super::obstacles::Obstacle],
    id: u16,
    table_deg: f64,
    a: Point3<f64>,
    b: Point3<f64>,
    seed: &[f64; 6],
) -> Result<Pass, ScanError> {
    let d = b - a;
    let length_mm = d.norm();
    let mut horizontal = Vector3::new(d.x, d.y, 0.0);
    if horizontal.norm() < 1e-9 {
        horizontal = Vector3::y();
    }
    let rot = sensor_orientation(&horizontal, opts.tilt_deg);
    let start = Isometry3::from_parts(Translation3::from(a.coords), rot);
    let end = Isometry3::from_parts(Translation3::from(b.coords), rot);
    let cfg = IkConfig::default();
    let unreachable = |which: &str, p: &Point3<f64>, e: &dyn std::fmt::Display| ScanError::Unreachable {
        pass: id,
        table_deg,
        reason: format!("{which} of the pass, sensor at ({:.1}, {:.1}, {:.1}) mm: {e}", p.x, p.y, p.z),
    };
    let s = arm.ik_nearest(&start, seed, &cfg).map_err(|e| unreachable("start", &a, &e))?;
    let mut min_clear = f64::INFINITY;
    let mut check = |q: &[f64; 6], which: &str, p: &Point3<f64>| -> Result<(), ScanError> {
        if let Some((d, name, what)) = super::obstacles::clearance(arm, q, obstacles) {
            if d < opts.obstacle_clearance_mm {
                return Err(unreachable(
                    which,
                    p,
                    &format!(
                        "{what} comes within {d:.1} mm of the {name} (clearance {} mm)",
                        opts.obstacle_clearance_mm
                    ),
                ));
            }
            min_clear = min_clear.min(d);
        }
        Ok(())
    };
    check(&s.q_deg, "start", &a)?;
    // Walk to the end through intermediate poses so the end takes the branch continuous with the
    // start (a straight stop-and-move pass visits them all), checking each on the way.
    let steps = ((length_mm / 20.0).ceil() as usize).max(1);
    let mut q = s.q_deg;
    let mut min_dex = arm.dexterity(&q);
    for k in 1..=steps {
        let t = k as f64 / steps as f64;
        let p = a + d * t;
        let pose = Isometry3::from_parts(Translation3::from(p.coords), rot);
        let sol = arm.ik_nearest(&pose, &q, &cfg).map_err(|e| unreachable("middle", &p, &e))?;
        if arm.joint_distance(&sol.q_deg, &q) > 90.0 {
            return Err(unreachable(
                "middle",
                &p,
                &"the arm would have to change configuration mid-pass (a flip of more than 90°)",
            ));
        }
        q = sol.q_deg;
        check(&q, "middle", &p)?;
        min_dex = min_dex.min(arm.dexterity(&q));
    }
    let path_deviation_mm =
        if opts.mode == ScanMode::Dynamic { joint_path_deviation(arm, &s.q_deg, &q, &a, &b) } else { 0.0 };
    Ok(Pass {
        id,
        start,
        end,
        q_start_deg: s.q_deg,
        q_end_deg: q,
        length_mm,
        path_deviation_mm,
        min_dexterity: min_dex,
        min_clearance_mm: min_clear,
    })
}

/// Largest distance of the sensor from segment `a..b` along a linear joint interpolation.
fn joint_path_deviation(
    arm: &ArmModel,
    q0: &[f64; 6],
    q1: &[f64; 6],
    a: &Point3<f64>,
    b: &Point3<f64>,
) -> f64 {
    let d = b - a;
    let len2 = d.norm_squared().max(1e-12);
    (1..16)
        .map(|k| {
            let t = k as f64 / 16.0;
            let q: [f64; 6] = std::array::from_fn(|j| q0[j] + (q1[j] - q0[j]) * t);
            let p = Point3::from(arm.fk(&q).translation.vector);
            let s = ((p - a).dot(&d) / len2).clamp(0.0, 1.0);
            (p - (a + d * s)).norm()
        })
        .fold(0.0, f64::max)
}

/// Duration (s) of a synchronised joint move from `q0` to `q1` at `speed_frac` of the top speeds:
/// the slowest joint's trapezoid (or triangle), as the controller times it.
pub fn move_duration(limits: &[JointLimit; 6], q0: &[f64; 6], q1: &[f64; 6], speed_frac: f64) -> f64 {
    (0..6)
        .map(|j| {
            let dist = (q1[j] - q0[j]).abs();
            if dist < 1e-6 {
                return 0.0;
            }
            let v = limits[j].max_speed_deg_s * speed_frac;
            let a = limits[j].max_accel_deg_s2;
            if dist >= v * v / a { dist / v + v / a } else { 2.0 * (dist / a).sqrt() }
        })
        .fold(0.0, f64::max)
}

/// The speed fraction (≤ 1) that makes the move last `duration_s`, or 1 if even full speed is
/// slower; bisection on the monotone [`move_duration`].
pub fn speed_fraction_for(limits: &[JointLimit; 6], q0: &[f64; 6], q1: &[f64; 6], duration_s: f64) -> f64 {
    if move_duration(limits, q0, q1, 1.0) >= duration_s {
        return 1.0;
    }
    let (mut lo, mut hi) = (1e-6, 1.0);
    for _ in 0..60 {
        let mid = 0.5 * (lo + hi);
        if move_duration(limits, q0, q1, mid) > duration_s {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    hi
}
