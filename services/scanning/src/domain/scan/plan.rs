//! Scan planning: straight passes of the sensor at a set standoff over the part, station by
//! station (one table angle each), each pass checked for reachability by inverse kinematics.

use nalgebra::{Isometry3, Point3, Rotation3, Translation3, UnitQuaternion, Vector3};
use serde::Serialize;

use super::options::{ScanMode, ScanOptions};
use super::{CellLayout, PartPlacement, ScanError};
use crate::domain::scanner::ScannerSpec;
use depthmill_geometry::arm::{ArmModel, IkConfig, JointLimit, SingularityMargins};

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
    /// Smallest distances from the wrist, shoulder and elbow singularities along the pass.
    pub min_margins: SingularityMargins,
    /// Smallest distance of any joint from its limits along the pass, degrees.
    pub min_limit_margin_deg: f64,
    /// The posture score of the pass's worst pose, 0..1 ([`posture_score`]).
    pub quality: f64,
}

/// The passes at one table angle.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Station {
    /// Commanded table angle, degrees.
    pub table_deg: f64,
    pub passes: Vec<Pass>,
    /// The seventh joint: how far the planner turned the table from the angle asked for
    /// (`table_deg` − asked) to give the arm a better posture, degrees (0: fixed).
    pub table_offset_deg: f64,
}

/// The table's indexing speed, °/s (the controller's maximum), and acceleration, °/s².
pub const TABLE_INDEX_SPEED_DEG_S: f64 = 45.0;
pub const TABLE_INDEX_ACCEL_DEG_S2: f64 = 200.0;

/// The table's index to a station from the previous one at the controller's speed and
/// acceleration (a trapezoid, or a triangle on a short move).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct TableMove {
    /// Shortest turn, degrees.
    pub turn_deg: f64,
    pub peak_speed_deg_s: f64,
    pub peak_accel_deg_s2: f64,
    pub time_s: f64,
}

impl TableMove {
    pub fn between(from_deg: f64, to_deg: f64, speed_deg_s: f64, accel_deg_s2: f64) -> Self {
        let turn = (to_deg - from_deg + 180.0).rem_euclid(360.0) - 180.0;
        let d = turn.abs();
        if d < 1e-12 {
            return Self { turn_deg: turn, peak_speed_deg_s: 0.0, peak_accel_deg_s2: 0.0, time_s: 0.0 };
        }
        let (peak, time) = if d <= speed_deg_s * speed_deg_s / accel_deg_s2 {
            let v = (d * accel_deg_s2).sqrt();
            (v, 2.0 * v / accel_deg_s2)
        } else {
            (speed_deg_s, d / speed_deg_s + speed_deg_s / accel_deg_s2)
        };
        Self { turn_deg: turn, peak_speed_deg_s: peak, peak_accel_deg_s2: accel_deg_s2, time_s: time }
    }
}

/// Where each posture criterion stops mattering: dexterity (mm³/rad³), the wrist and elbow
/// margins (°), the shoulder margin (mm), the joint-limit margin (°).
pub const POSTURE_REFERENCE: (f64, f64, f64, f64, f64) = (5.0e6, 30.0, 30.0, 150.0, 20.0);

/// Seed 002's criteria for a pose in one number, 0 (singular, at a limit) to 1 (comfortable):
/// the smallest of dexterity `sqrt(det(JᵀJ))`, the distances from the wrist, elbow and shoulder
/// singularities and from the joint limits, each over the reference where it stops mattering.
pub fn posture_score(arm: &ArmModel, q: &[f64; 6]) -> (f64, SingularityMargins, f64, f64) {
    let (dex_ref, wrist_ref, elbow_ref, shoulder_ref, limit_ref) = POSTURE_REFERENCE;
    let dex = arm.dexterity(q);
    let m = arm.singularity_margins(q);
    let limit = arm
        .limits
        .iter()
        .zip(q)
        .map(|(l, v)| (v - l.min_deg).min(l.max_deg - v))
        .fold(f64::INFINITY, f64::min);
    let score = [
        dex / dex_ref,
        m.wrist_deg / wrist_ref,
        m.elbow_deg / elbow_ref,
        m.shoulder_mm / shoulder_ref,
        limit / limit_ref,
    ]
    .into_iter()
    .fold(1.0_f64, f64::min)
    .max(0.0);
    (score, m, limit, dex)
}

/// Table offsets tried per station, nearest first: 0, +step, −step, ... within ±`search`.
fn offsets(search_deg: f64) -> Vec<f64> {
    const STEP_DEG: f64 = 5.0;
    let n = (search_deg / STEP_DEG).floor() as i32;
    let mut v = vec![0.0];
    for k in 1..=n {
        v.push(f64::from(k) * STEP_DEG);
        v.push(-f64::from(k) * STEP_DEG);
    }
    v
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

/// `angles` in the same cyclic order, starting from the one the table reaches soonest from
/// `from_deg` (the shortest way; the first of a tie): a list visited from where the table
/// stands instead of from its first entry saves the turn back to it.
pub fn visit_order(angles: &[f64], from_deg: f64) -> Vec<f64> {
    let away = |a: f64| TableMove::between(from_deg, a, 1.0, 1.0).turn_deg.abs();
    let start = angles
        .iter()
        .enumerate()
        .min_by(|x, y| away(*x.1).total_cmp(&away(*y.1)).then(x.0.cmp(&y.0)))
        .map_or(0, |(k, _)| k);
    let mut out = angles.to_vec();
    out.rotate_left(start);
    out
}

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
    let mut stations: Vec<Station> = Vec::with_capacity(raw.len());
    let mut skipped = Vec::new();
    let mut first_error = None;
    let automatic = opts.passes.is_none();
    // The seventh joint (seed 002): every automatic pass is a path in the part's frame, so the
    // table may turn by up to `table_search_deg` from the station's angle, the path turning with
    // it, when the arm then reaches the pass or holds a better worst posture along it. The same
    // sensor path over the part either way: only the arm's posture and the table's moves change.
    // Offsets are tried nearest the previous pass's first, so the table turns only for a gain.
    let search = if automatic { opts.table_search_deg } else { 0.0 };
    let mut offset = 0.0_f64;
    for (deg, lines) in raw {
        let base = layout.world_from_table(deg);
        let mut tries = offsets(search);
        tries.sort_by(|a, b| (a - offset).abs().total_cmp(&(b - offset).abs()));
        for (a, b) in lines {
            let next = id.checked_add(1).ok_or_else(|| ScanError::InvalidOption {
                field: "scan".into(),
                value: "more than 65535 passes".into(),
                reason: "a scan has at most 65535 passes (pass ids are 16-bit)".into(),
            })?;
            // (reached, posture in steps of 0.05), the pass or why not, the offset.
            type Tried = ((bool, i64), Result<Pass, ScanError>, f64);
            let mut best: Option<Tried> = None;
            for &off in &tries {
                let turn = layout.world_from_table(deg + off) * base.inverse();
                let r = match make_pass(arm, opts, &obstacles, next, deg + off, turn * a, turn * b, &seed) {
                    Ok(p) => Ok(p),
                    // An automatic pass out of reach here may be reached at another angle; a
                    // given pass out of reach is the user's error.
                    Err(e @ ScanError::Unreachable { .. }) if automatic => Err(e),
                    Err(e) => return Err(e),
                };
                let key = match &r {
                    Ok(p) => (true, (p.quality * 20.0).floor() as i64),
                    Err(_) => (false, 0),
                };
                let done = key == (true, 20);
                if best.as_ref().is_none_or(|b| key > b.0) {
                    best = Some((key, r, off));
                }
                if done {
                    break;
                }
            }
            let Some((_, r, off)) = best else { continue };
            match r {
                Ok(pass) => {
                    id = next;
                    seed = pass.q_end_deg;
                    offset = off;
                    let angle = deg + off;
                    match stations.last_mut() {
                        Some(st)
                            if st.table_deg == angle
                                && st.passes.last().is_some_and(|p| p.id + 1 == pass.id) =>
                        {
                            st.passes.push(pass)
                        }
                        _ => stations.push(Station {
                            table_deg: angle,
                            passes: vec![pass],
                            table_offset_deg: off,
                        }),
                    }
                }
                // An automatic pass out of reach at every angle tried: the other stations bring
                // that side of the part nearer.
                Err(e) => {
                    skipped.push(e.to_string());
                    first_error.get_or_insert(e);
                }
            }
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
    let (mut quality, mut min_margins, mut min_limit, mut min_dex) = posture_score(arm, &q);
    let mut track = |q: &[f64; 6]| {
        let (score, m, limit, dex) = posture_score(arm, q);
        quality = quality.min(score);
        min_margins = SingularityMargins {
            wrist_deg: min_margins.wrist_deg.min(m.wrist_deg),
            shoulder_mm: min_margins.shoulder_mm.min(m.shoulder_mm),
            elbow_deg: min_margins.elbow_deg.min(m.elbow_deg),
        };
        min_limit = min_limit.min(limit);
        min_dex = min_dex.min(dex);
    };
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
        track(&q);
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
        min_margins,
        min_limit_margin_deg: min_limit,
        quality,
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
