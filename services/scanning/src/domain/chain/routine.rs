//! Seed 003's routine on the simulated mill: the calibration point (the centre of a reference
//! ball on the rotor) seen at three or more positions of every linear axis and of the A axis,
//! the chain fitted from those views, then partial scans of a part at any axis positions placed
//! by the chain alone and merged, with the merge error against the truth.

use depthmill_geometry::Mesh;
use nalgebra::{DMatrix, Isometry3, Point2, Point3, Translation3, Unit, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

use super::area::{AreaScanner, AreaScannerSpec, Shot};
use super::{ChainCalibration, ChainErrors, ChainTruth, MachineConfig, MachineGeometry, invalid, rotor_axes};
use crate::domain::calibration::fit::{AlignmentMoments, fit_plane, fit_sphere_algebraic, least_squares};
use crate::domain::calibration::routine::sphere_mesh;
use crate::domain::calibration::{CalibrationError, RegistrationCheck};

/// Fewest points on the ball for its centre to count as seen.
const MIN_SPHERE_POINTS: usize = 200;
/// Points of one view used in the fixed-radius sphere fit (every n-th).
const FIT_SPHERE_POINTS: usize = 4000;
/// A ball fitted with a radius further than this fraction from the nominal one is not the ball.
const RADIUS_TOLERANCE: f64 = 0.05;
/// Least arc of A the ball must be seen over, degrees.
const MIN_A_ARC_DEG: f64 = 20.0;
/// Least distance of the calibration point from the A axis, mm.
const MIN_RADIAL_MM: f64 = 5.0;

/// The simulated mill with the area scanner in its holder.
#[derive(Debug, Clone)]
pub struct MachineCell {
    pub truth: ChainTruth,
    pub scanner: AreaScannerSpec,
}

impl MachineCell {
    pub fn new(
        geometry: &MachineGeometry,
        errors: &ChainErrors,
        scanner: AreaScannerSpec,
    ) -> Result<Self, CalibrationError> {
        scanner.validate()?;
        Ok(Self { truth: ChainTruth::new(geometry, errors)?, scanner })
    }

    pub fn geometry(&self) -> &MachineGeometry {
        &self.truth.geometry
    }
}

/// Runs the shots of a plan: each configuration quantised to whole steps and checked against the
/// travels, the move timed, the shot taken with the truth.
struct Runner<'a> {
    cell: &'a MachineCell,
    scanner: AreaScanner,
    at: MachineConfig,
    time_s: f64,
    shots: u64,
}

impl<'a> Runner<'a> {
    fn new(
        cell: &'a MachineCell,
        mesh: &Mesh,
        seed: u64,
        start: MachineConfig,
    ) -> Result<Self, CalibrationError> {
        let scanner = AreaScanner::new(cell.scanner.clone(), mesh, seed)?;
        Ok(Self { cell, scanner, at: start, time_s: 0.0, shots: 0 })
    }

    fn shoot(&mut self, c: MachineConfig, what: &str) -> Result<(MachineConfig, Shot), CalibrationError> {
        let g = self.cell.geometry();
        let c = g.quantise(c);
        g.check_travel(&c).map_err(|e| CalibrationError::Scan(format!("{what}: {e}")))?;
        self.time_s += g.move_time_s(&self.at, &c) + g.settle_s + self.cell.scanner.exposure_s;
        self.at = c;
        let shot = self.scanner.shot(&self.cell.truth.rotor_from_sensor(&c), self.shots);
        self.shots += 1;
        Ok((c, shot))
    }
}

/// Where the reference ball stands and how far each axis is moved to see it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ChainCalibrationOptions {
    /// Radius of the reference ball, mm.
    pub sphere_radius_mm: f64,
    /// Its centre (the calibration point) in the rotor's frame: along the axis from the
    /// faceplate, then across it (Y, Z at the rotor's reference direction), mm.
    pub sphere_at_mm: [f64; 3],
    /// X, Y and Z are each moved this far either side of the reference, mm (the ball must stay
    /// in the scanner's field: 50 x 40 mm at 120 mm by default).
    pub linear_steps_mm: [f64; 3],
    /// The A axis is turned by this step, `a_steps` times either side of the reference, degrees.
    pub a_step_deg: f64,
    pub a_steps: u32,
    /// The A reading the calibration is referenced at, degrees.
    pub reference_a_deg: f64,
    /// Distance from the scanner to the ball's centre at the reference, mm.
    pub standoff_mm: f64,
    /// Noise seed.
    pub seed: u64,
}

impl Default for ChainCalibrationOptions {
    /// A 12.7 mm ball on a post 25 mm along the axis and 30 mm out from it; X, Y, Z moved 20,
    /// 12 and 30 mm either way, A over ±90° in 30° steps (the scanner following the ball).
    fn default() -> Self {
        Self {
            sphere_radius_mm: 6.35,
            sphere_at_mm: [25.0, 0.0, 30.0],
            linear_steps_mm: [20.0, 12.0, 30.0],
            a_step_deg: 30.0,
            a_steps: 3,
            reference_a_deg: 0.0,
            standoff_mm: 120.0,
            seed: 3003,
        }
    }
}

impl ChainCalibrationOptions {
    pub fn validate(&self, spec: &AreaScannerSpec) -> Result<(), CalibrationError> {
        if !(self.sphere_radius_mm.is_finite() && (1.0..=30.0).contains(&self.sphere_radius_mm)) {
            return Err(invalid("sphere_radius_mm", self.sphere_radius_mm, "1 to 30 mm"));
        }
        if self.sphere_at_mm.iter().any(|v| !v.is_finite() || v.abs() > 200.0) {
            return Err(invalid("sphere_at_mm", format!("{:?}", self.sphere_at_mm), "finite, within 200 mm"));
        }
        let radial = self.sphere_at_mm[1].hypot(self.sphere_at_mm[2]);
        if radial < MIN_RADIAL_MM {
            return Err(CalibrationError::Degenerate(format!(
                "the calibration point is {radial:.2} mm from the A axis (sphere_at_mm): at least {MIN_RADIAL_MM} mm is needed for its circle to show the axis"
            )));
        }
        for (i, v) in self.linear_steps_mm.iter().enumerate() {
            if !(v.is_finite() && (1.0..=50.0).contains(v)) {
                return Err(invalid(&format!("linear_steps_mm[{i}]"), v, "1 to 50 mm"));
            }
        }
        if !(self.a_step_deg.is_finite() && (1.0..=90.0).contains(&self.a_step_deg)) {
            return Err(invalid("a_step_deg", self.a_step_deg, "1 to 90 degrees"));
        }
        if !(1..=8).contains(&self.a_steps) {
            return Err(invalid("a_steps", self.a_steps, "1 to 8 (A is seen at 2·a_steps + 1 positions)"));
        }
        let arc = 2.0 * f64::from(self.a_steps) * self.a_step_deg;
        if arc < MIN_A_ARC_DEG {
            return Err(CalibrationError::Degenerate(format!(
                "A would be seen over {arc:.1}° (2 x a_steps x a_step_deg): at least {MIN_A_ARC_DEG}° is needed to find the axis"
            )));
        }
        if !self.reference_a_deg.is_finite() {
            return Err(invalid("reference_a_deg", self.reference_a_deg, "finite degrees"));
        }
        let window = spec.standoff_min_mm + self.sphere_radius_mm..=spec.standoff_max_mm;
        if !(self.standoff_mm.is_finite() && window.contains(&self.standoff_mm)) {
            return Err(invalid(
                "standoff_mm",
                self.standoff_mm,
                &format!(
                    "within the scanner's window less the ball's radius, {:.1} to {:.1} mm",
                    window.start(),
                    window.end()
                ),
            ));
        }
        Ok(())
    }
}

/// One view of the calibration point.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Observation {
    /// Which move: `reference`, `X+`, `X-`, `Y+`, ..., `A+20`, ...
    pub label: String,
    pub config: MachineConfig,
    pub points: usize,
    /// Radius of the free sphere fit, mm (a check that the ball is what was seen).
    pub radius_mm: f64,
    /// RMS distance of the points from the ball (fixed radius), mm.
    pub sphere_rms_mm: f64,
    /// The ball's centre in the scanner's frame, mm.
    pub centre_in_scanner_mm: [f64; 3],
    /// Distance from where the fitted chain puts the centre, mm.
    pub residual_mm: f64,
}

/// The chain against the simulation's truth.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct ChainTruthCheck {
    /// Largest distance, over configurations spread across the travels and A at every quarter
    /// turn and points across the scanner's field and window, between where the chain places a
    /// point and where it truly is on the rotor, mm: calibrated and drawn.
    pub placement_error_mm: f64,
    pub placement_error_before_mm: f64,
    /// Angle between the fitted A axis and the true one, degrees, and how far the fitted axis's
    /// point nearest the calibration point lies from the true axis, mm.
    pub a_axis_direction_error_deg: f64,
    pub a_axis_position_error_mm: f64,
}

/// What a chain calibration produced and how well it fits.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ChainCalibrationReport {
    pub calibration: ChainCalibration,
    pub previous: ChainCalibration,
    pub options: ChainCalibrationOptions,
    pub observations: Vec<Observation>,
    /// RMS of the residuals of the linear axes' fit and of the A axis's, mm.
    pub linear_fit_rms_mm: f64,
    pub rotary_fit_rms_mm: f64,
    /// The slides' pitch as measured (true travel per commanded mm − 1), ppm.
    pub scale_ppm: [f64; 3],
    /// The slides' angles minus 90° as measured: X-Y, X-Z, Y-Z, degrees.
    pub squareness_deg: [f64; 3],
    /// Angle between the A axis and the X slide as measured, degrees.
    pub a_axis_to_x_deg: f64,
    /// Radius of the calibration point's circle about A, mm.
    pub a_circle_radius_mm: f64,
    pub truth: Option<ChainTruthCheck>,
    /// Simulated time of the calibration (moves, settling, shots), s.
    pub scan_time_s: f64,
    pub shots: u64,
    pub points: u64,
}

/// The ball's centre in the scanner's frame from one shot: a free algebraic fit (its radius must
/// be the ball's), then the centre at the known radius by least squares.
fn ball_centre(
    shot: &Shot,
    radius: f64,
    label: &str,
    c: &MachineConfig,
) -> Result<(Point3<f64>, f64, f64), CalibrationError> {
    let pts = &shot.points;
    if pts.len() < MIN_SPHERE_POINTS {
        return Err(CalibrationError::Degenerate(format!(
            "the reference ball gave {} points at {label} ({c}), at least {MIN_SPHERE_POINTS} are needed: it was not seen; check sphere_at_mm, sphere_radius_mm and standoff_mm",
            pts.len()
        )));
    }
    let (centre, r) = fit_sphere_algebraic(pts).ok_or_else(|| {
        CalibrationError::Degenerate(format!("the points seen at {label} ({c}) fit no sphere"))
    })?;
    if (r - radius).abs() > RADIUS_TOLERANCE * radius {
        return Err(CalibrationError::Degenerate(format!(
            "the points seen at {label} ({c}) fit a sphere of radius {r:.3} mm, not the ball's {radius:.3} mm: something else is in view"
        )));
    }
    let step = pts.len().div_ceil(FIT_SPHERE_POINTS).max(1);
    let thin: Vec<Point3<f64>> = pts.iter().step_by(step).copied().collect();
    let x = least_squares(vec![centre.x, centre.y, centre.z], |x, r| {
        let c = Point3::new(x[0], x[1], x[2]);
        r.clear();
        r.extend(thin.iter().map(|p| (p - c).norm() - radius));
    })?;
    let centre = Point3::new(x[0], x[1], x[2]);
    let rms =
        (thin.iter().map(|p| ((p - centre).norm() - radius).powi(2)).sum::<f64>() / thin.len() as f64).sqrt();
    Ok((centre, r, rms))
}

/// Least squares `A·X = B` by SVD; `None` when `A` has a null direction.
fn solve_lsq(a: &DMatrix<f64>, b: &DMatrix<f64>) -> Option<DMatrix<f64>> {
    let svd = a.clone().svd(true, true);
    let s = &svd.singular_values;
    let max = s.iter().copied().fold(0.0, f64::max);
    let min = s.iter().copied().fold(f64::INFINITY, f64::min);
    if !(max > 0.0 && min > 1e-9 * max) {
        return None;
    }
    svd.solve(b, 1e-12).ok()
}

/// Plans the calibration: the reference configuration (the scanner `standoff_mm` above the ball
/// by the drawing), then each linear axis either side and A at `a_steps` steps either side
/// (the linear axes following the ball).
pub fn calibration_plan(
    geometry: &MachineGeometry,
    opts: &ChainCalibrationOptions,
) -> Result<Vec<(String, MachineConfig)>, CalibrationError> {
    let nominal = ChainTruth::new(geometry, &ChainErrors::exact())?;
    let ball = nominal.table_from_rotor(opts.reference_a_deg) * Point3::from(opts.sphere_at_mm);
    let sensor = ball + Vector3::new(0.0, 0.0, opts.standoff_mm);
    let nose = sensor.coords + Vector3::new(0.0, 0.0, geometry.scanner_below_nose_mm);
    let c = nose - Vector3::from(geometry.nose_at_zero_mm);
    let c0 = geometry.quantise(MachineConfig::new(c.x, c.y, c.z, opts.reference_a_deg));
    let mut plan = vec![("reference".to_string(), c0)];
    for (i, (name, d)) in
        [("X", Vector3::x()), ("Y", Vector3::y()), ("Z", Vector3::z())].into_iter().enumerate()
    {
        for sign in [1.0, -1.0] {
            let v = d * opts.linear_steps_mm[i] * sign;
            let label = format!("{name}{}", if sign > 0.0 { "+" } else { "-" });
            plan.push((label, MachineConfig::new(c0.x + v.x, c0.y + v.y, c0.z + v.z, c0.a)));
        }
    }
    // A from one end of its arc to the other (the follow moves stay short).
    let n = i64::from(opts.a_steps);
    for k in (-n..=n).filter(|k| *k != 0) {
        let da = k as f64 * opts.a_step_deg;
        // The scanner follows the ball (by the drawing) so it stays in the middle of the
        // field; the linear axes are calibrated by then, so the fit takes the follow out.
        let moved = nominal.table_from_rotor(c0.a + da) * Point3::from(opts.sphere_at_mm);
        let f = moved - ball;
        let c = geometry.quantise(MachineConfig::new(c0.x + f.x, c0.y + f.y, c0.z + f.z, c0.a + da));
        plan.push((format!("A{da:+}"), c));
    }
    for (label, c) in &plan {
        geometry
            .check_travel(c)
            .map_err(|e| CalibrationError::Scan(format!("calibration view {label}: {e}")))?;
    }
    Ok(plan)
}

/// Fits the chain to views of the calibration point: `(label, config, centre in the scanner's
/// frame)`. The reference is the first view.
pub fn fit_chain(
    views: &[(String, MachineConfig, Point3<f64>)],
    sphere_at_mm: [f64; 3],
) -> Result<(ChainCalibration, Vec<f64>, f64, f64, f64), CalibrationError> {
    let Some((_, c0, _)) = views.first() else {
        return Err(CalibrationError::Degenerate("no view of the calibration point".into()));
    };
    let c0 = *c0;
    let same_a = |c: &MachineConfig| (c.a - c0.a).abs() < 1e-9;
    let same_lin = |c: &MachineConfig| (c.x - c0.x).abs() + (c.y - c0.y).abs() + (c.z - c0.z).abs() < 1e-9;
    // Linear axes: p = m0 − Σ Δc_i u_i over the views at the reference A.
    let lin: Vec<&(String, MachineConfig, Point3<f64>)> = views.iter().filter(|v| same_a(&v.1)).collect();
    for (i, name) in ["X", "Y", "Z"].iter().enumerate() {
        let mut vals: Vec<f64> = lin.iter().map(|v| [v.1.x, v.1.y, v.1.z][i]).collect();
        vals.sort_by(f64::total_cmp);
        vals.dedup_by(|a, b| (*a - *b).abs() < 1e-6);
        if vals.len() < 3 {
            return Err(CalibrationError::Degenerate(format!(
                "the calibration point was seen at {} positions of axis {name}: at least 3 are needed",
                vals.len()
            )));
        }
    }
    let a = DMatrix::from_fn(lin.len(), 4, |r, k| {
        let c = &lin[r].1;
        match k {
            0 => 1.0,
            1 => -(c.x - c0.x),
            2 => -(c.y - c0.y),
            _ => -(c.z - c0.z),
        }
    });
    let b = DMatrix::from_fn(lin.len(), 3, |r, k| lin[r].2[k]);
    let x = solve_lsq(&a, &b).ok_or_else(|| {
        CalibrationError::Degenerate("the linear axes' moves do not span three directions".into())
    })?;
    let row = |r: usize| Vector3::new(x[(r, 0)], x[(r, 1)], x[(r, 2)]);
    let m0 = Point3::from(row(0));
    let axes = [row(1), row(2), row(3)];
    let predict_lin =
        |c: &MachineConfig| m0 - axes[0] * (c.x - c0.x) - axes[1] * (c.y - c0.y) - axes[2] * (c.z - c0.z);
    // The A axis from the views at other A readings and the reference, each brought back to
    // the reference X, Y, Z by the linear axes just found (the scanner followed the ball).
    let shift = |c: &MachineConfig| axes[0] * (c.x - c0.x) + axes[1] * (c.y - c0.y) + axes[2] * (c.z - c0.z);
    let rot: Vec<(f64, Point3<f64>)> = views
        .iter()
        .filter(|v| !same_a(&v.1) || same_lin(&v.1))
        .map(|v| (v.1.a - c0.a, v.2 + shift(&v.1)))
        .collect();
    let mut angles: Vec<f64> = rot.iter().map(|r| r.0).collect();
    angles.sort_by(f64::total_cmp);
    angles.dedup_by(|a, b| (*a - *b).abs() < 1e-6);
    if angles.len() < 3 {
        return Err(CalibrationError::Degenerate(format!(
            "the calibration point was seen at {} positions of axis A: at least 3 are needed",
            angles.len()
        )));
    }
    let arc = angles[angles.len() - 1] - angles[0];
    if arc < MIN_A_ARC_DEG {
        return Err(CalibrationError::Degenerate(format!(
            "the calibration point was seen over {arc:.1}° of A: at least {MIN_A_ARC_DEG}° is needed"
        )));
    }
    let pts: Vec<Point3<f64>> = rot.iter().map(|r| r.1).collect();
    let (centroid, normal, _) = fit_plane(&pts).ok_or_else(|| {
        CalibrationError::Degenerate("the calibration point's positions about A lie on a line".into())
    })?;
    let e1 = normal
        .cross(&Vector3::x())
        .try_normalize(1e-6)
        .unwrap_or_else(|| normal.cross(&Vector3::y()).normalize());
    let e2 = normal.cross(&e1);
    // Circle in the plane: |q|² = 2 c·q + k.
    let q: Vec<Point2<f64>> =
        pts.iter().map(|p| Point2::new((p - centroid).dot(&e1), (p - centroid).dot(&e2))).collect();
    let ca = DMatrix::from_fn(q.len(), 3, |r, k| [2.0 * q[r].x, 2.0 * q[r].y, 1.0][k]);
    let cb = DMatrix::from_fn(q.len(), 1, |r, _| q[r].coords.norm_squared());
    let cs = solve_lsq(&ca, &cb).ok_or_else(|| {
        CalibrationError::Degenerate("the calibration point's positions about A fit no circle".into())
    })?;
    let centre0 = centroid + e1 * cs[(0, 0)] + e2 * cs[(1, 0)];
    // The turning sense: positive A must turn the point positively about the axis (judged on
    // the turn nearest the reference, well short of a half turn).
    let m_ref = rot.iter().find(|r| r.0.abs() < 1e-9).map_or(m0, |r| r.1);
    let (da, p) = rot
        .iter()
        .filter(|r| r.0.abs() >= 1e-9)
        .min_by(|a, b| a.0.abs().total_cmp(&b.0.abs()))
        .map_or((1.0, m_ref), |r| (r.0, r.1));
    let sense = (m_ref - centre0).cross(&(p - centre0)).dot(&normal) * da.signum();
    let normal = if sense >= 0.0 { normal } else { -normal };
    let e2 = normal.cross(&e1);
    let model = |x: &[f64]| {
        let turn = UnitQuaternion::from_scaled_axis(e1 * x[0] * 1e-3 + e2 * x[1] * 1e-3);
        let dir = Unit::new_normalize(turn * normal);
        let c = centre0 + e1 * x[2] + e2 * x[3];
        (dir, c, Point3::new(x[4], x[5], x[6]))
    };
    let x0 = vec![0.0, 0.0, 0.0, 0.0, m_ref.x, m_ref.y, m_ref.z];
    let xs = least_squares(x0, |x, r| {
        let (dir, c, m) = model(x);
        r.clear();
        for (da, p) in &rot {
            let q = UnitQuaternion::from_axis_angle(&dir, da.to_radians()) * (m - c) + c.coords;
            r.extend((q - p.coords).iter().copied());
        }
    })?;
    let (dir, centre, m_rot) = model(&xs);
    let predict_rot = |da: f64| {
        Point3::from(
            UnitQuaternion::from_axis_angle(&dir, da.to_radians()) * (m_rot - centre) + centre.coords,
        )
    };
    let radius = (m_rot - centre).cross(&dir).norm();
    if radius < MIN_RADIAL_MM {
        return Err(CalibrationError::Degenerate(format!(
            "the calibration point turns on a circle of {radius:.2} mm about A: at least {MIN_RADIAL_MM} mm is needed"
        )));
    }
    let residuals: Vec<f64> = views
        .iter()
        .map(|(_, c, p)| {
            if !same_a(c) {
                (predict_rot(c.a - c0.a) - (p + shift(c))).norm()
            } else {
                (predict_lin(c) - p).norm()
            }
        })
        .collect();
    let rms = |v: &[f64]| (v.iter().map(|r| r * r).sum::<f64>() / v.len().max(1) as f64).sqrt();
    let lin_res: Vec<f64> = lin.iter().map(|v| (predict_lin(&v.1) - v.2).norm()).collect();
    let rot_res: Vec<f64> = rot.iter().map(|(da, p)| (predict_rot(*da) - p).norm()).collect();
    // The part frame: the rotor at the reference A, found from where the ball sits on it.
    let d = dir.into_inner();
    let foot = centre + d * (m0 - centre).dot(&d);
    let w = (m0 - foot).normalize();
    let [sx, sy, sz] = sphere_at_mm;
    let r = rotor_axes(&d, &w, sy, sz)
        .ok_or_else(|| CalibrationError::Degenerate("the calibration point lies on the A axis".into()))?;
    let rot3 = nalgebra::Rotation3::from_matrix_unchecked(r);
    let origin = foot - d * sx;
    let s0_from_part =
        Isometry3::from_parts(Translation3::from(origin.coords), UnitQuaternion::from_rotation_matrix(&rot3));
    let cal = ChainCalibration {
        source: "calibrated".into(),
        reference: c0,
        axes_in_scanner: axes.map(|u| [u.x, u.y, u.z]),
        a_point_mm: [centre.x, centre.y, centre.z],
        a_dir: [d.x, d.y, d.z],
        s0_from_part,
    };
    Ok((cal, residuals, rms(&lin_res), rms(&rot_res), radius))
}

/// Configurations spread over the travels and A at every quarter turn, and points across the
/// scanner's field and window: where the chain is checked against the truth.
fn check_points(cell: &MachineCell) -> (Vec<MachineConfig>, Vec<Point3<f64>>) {
    let g = cell.geometry();
    let at = |i: usize, f: f64| g.travel_mm[i][0] + f * (g.travel_mm[i][1] - g.travel_mm[i][0]);
    let mut configs = Vec::new();
    for fx in [0.1, 0.5, 0.9] {
        for fy in [0.2, 0.8] {
            for fz in [0.2, 0.8] {
                for a in [0.0, 90.0, 180.0, 270.0] {
                    configs.push(MachineConfig::new(at(0, fx), at(1, fy), at(2, fz), a));
                }
            }
        }
    }
    let s = &cell.scanner;
    let mut pts = Vec::new();
    for z in [s.standoff_min_mm, s.reference_mm, s.standoff_max_mm] {
        let [fx, fy] = s.field_at(z).map(|f| 0.5 * f);
        for (x, y) in [(0.0, 0.0), (-fx, -fy), (fx, -fy), (-fx, fy), (fx, fy)] {
            pts.push(Point3::new(x, y, z));
        }
    }
    (configs, pts)
}

fn placement_error(cell: &MachineCell, cal: &ChainCalibration) -> f64 {
    let (configs, pts) = check_points(cell);
    let mut worst: f64 = 0.0;
    for c in &configs {
        let truth = cell.truth.rotor_from_sensor(c);
        let placed = cal.part_from_scanner(c);
        for p in &pts {
            worst = worst.max((placed * p - truth * p).norm());
        }
    }
    worst
}

/// Calibrates the chain on the simulated mill: plans and shoots the views, fits, and checks the
/// result against the truth. `previous` is the chain in force (the drawing when none).
pub fn calibrate_chain(
    cell: &MachineCell,
    previous: &ChainCalibration,
    opts: &ChainCalibrationOptions,
) -> Result<ChainCalibrationReport, CalibrationError> {
    opts.validate(&cell.scanner)?;
    let plan = calibration_plan(cell.geometry(), opts)?;
    let mesh = sphere_mesh(Point3::from(opts.sphere_at_mm), opts.sphere_radius_mm);
    let start =
        MachineConfig::new(cell.geometry().travel_mm[0][0], cell.geometry().travel_mm[1][0], 0.0, 0.0);
    let mut runner = Runner::new(cell, &mesh, opts.seed, cell.geometry().quantise(start))?;
    let mut views = Vec::with_capacity(plan.len());
    let mut observations = Vec::with_capacity(plan.len());
    let mut points = 0u64;
    for (label, c) in plan {
        let (c, shot) = runner.shoot(c, &format!("calibration view {label}"))?;
        let (centre, radius, rms) = ball_centre(&shot, opts.sphere_radius_mm, &label, &c)?;
        points += shot.points.len() as u64;
        observations.push(Observation {
            label: label.clone(),
            config: c,
            points: shot.points.len(),
            radius_mm: radius,
            sphere_rms_mm: rms,
            centre_in_scanner_mm: [centre.x, centre.y, centre.z],
            residual_mm: 0.0,
        });
        views.push((label, c, centre));
    }
    let (calibration, residuals, linear_fit_rms_mm, rotary_fit_rms_mm, a_circle_radius_mm) =
        fit_chain(&views, opts.sphere_at_mm)?;
    for (o, r) in observations.iter_mut().zip(&residuals) {
        o.residual_mm = *r;
    }
    let exact = ChainCalibration::from_truth(&cell.truth, calibration.reference);
    let dir = Vector3::from(calibration.a_dir);
    let true_dir = Vector3::from(exact.a_dir);
    let ball = Point3::from(observations[0].centre_in_scanner_mm);
    let dist_to_line = |p: &Point3<f64>, a: &Point3<f64>, d: &Vector3<f64>| (p - a).cross(d).norm();
    let truth = ChainTruthCheck {
        placement_error_mm: placement_error(cell, &calibration),
        placement_error_before_mm: placement_error(cell, previous),
        a_axis_direction_error_deg: dir.angle(&true_dir).to_degrees(),
        // The fitted axis's point nearest the calibration point, off the true axis.
        a_axis_position_error_mm: {
            let a = Point3::from(calibration.a_point_mm);
            let foot = a + dir * (ball - a).dot(&dir);
            dist_to_line(&foot, &Point3::from(exact.a_point_mm), &true_dir)
        },
    };
    Ok(ChainCalibrationReport {
        scale_ppm: calibration.scale_ppm(),
        squareness_deg: calibration.squareness_deg(),
        a_axis_to_x_deg: calibration.a_to_x_deg(),
        calibration,
        previous: previous.clone(),
        options: opts.clone(),
        observations,
        linear_fit_rms_mm,
        rotary_fit_rms_mm,
        a_circle_radius_mm,
        truth: Some(truth),
        scan_time_s: runner.time_s,
        shots: runner.shots,
        points,
    })
}

/// How to scan a part on the mill.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ChainScanOptions {
    /// A readings the part is scanned at, degrees.
    pub a_angles_deg: Vec<f64>,
    /// Distance from the scanner to the part's highest point in each view, mm.
    pub standoff_mm: f64,
    /// Fraction of the field the tiles of one view overlap by (0: side by side, as the chain
    /// needs no overlap).
    pub overlap: f64,
    pub seed: u64,
}

impl Default for ChainScanOptions {
    fn default() -> Self {
        Self { a_angles_deg: vec![0.0, 90.0, 180.0, 270.0], standoff_mm: 100.0, overlap: 0.0, seed: 3103 }
    }
}

/// A part scanned on the mill and placed by the chain.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ChainScanReport {
    pub shots: u64,
    pub points: u64,
    /// Simulated time, s.
    pub scan_time_s: f64,
    /// The points placed by the chain in use, by the drawing, and by the true chain (the
    /// scanner's noise alone), against where they truly are on the part.
    pub registration: RegistrationCheck,
    pub registration_drawing: RegistrationCheck,
    pub registration_truth: RegistrationCheck,
}

/// The merged cloud of a part scanned on the mill.
#[derive(Debug, Clone, Default)]
pub struct MachineScan {
    /// Points in the part frame (the rotor's at the calibration's reference A).
    pub points: Vec<Point3<f64>>,
    /// The shot each point came from.
    pub shot: Vec<u16>,
}

/// A mesh placed on the rotor the way a part is clamped on a 4th axis: its X along the axis,
/// its bounding box centred on the axis, its near end `gap_mm` from the faceplate.
pub fn place_on_rotor(mesh: &Mesh, gap_mm: f64) -> Mesh {
    let (mut lo, mut hi) = (Vector3::repeat(f64::INFINITY), Vector3::repeat(f64::NEG_INFINITY));
    for v in &mesh.vertices {
        lo = lo.inf(&v.coords);
        hi = hi.sup(&v.coords);
    }
    let shift = Vector3::new(gap_mm - lo.x, -0.5 * (lo.y + hi.y), -0.5 * (lo.z + hi.z));
    Mesh { vertices: mesh.vertices.iter().map(|v| v + shift).collect(), triangles: mesh.triangles.clone() }
}

/// Scans `mesh` (in the rotor's frame) at each A of the options, every view tiled by shots side
/// by side; places every point by `calibration`. Returns the merged cloud in the part frame.
pub fn scan_on_machine(
    cell: &MachineCell,
    mesh: &Mesh,
    calibration: &ChainCalibration,
    opts: &ChainScanOptions,
) -> Result<(MachineScan, ChainScanReport), CalibrationError> {
    if opts.a_angles_deg.is_empty() || opts.a_angles_deg.len() > 36 {
        return Err(invalid("a_angles_deg", opts.a_angles_deg.len(), "1 to 36 angles"));
    }
    if let Some(a) = opts.a_angles_deg.iter().find(|a| !a.is_finite()) {
        return Err(invalid("a_angles_deg", a, "finite degrees"));
    }
    let spec = &cell.scanner;
    if !(opts.standoff_mm.is_finite()
        && opts.standoff_mm >= spec.standoff_min_mm
        && opts.standoff_mm < spec.standoff_max_mm)
    {
        return Err(invalid(
            "standoff_mm",
            opts.standoff_mm,
            &format!("within the scanner's window {} to {} mm", spec.standoff_min_mm, spec.standoff_max_mm),
        ));
    }
    if !(opts.overlap.is_finite() && (0.0..0.9).contains(&opts.overlap)) {
        return Err(invalid("overlap", opts.overlap, "0 to 0.9"));
    }
    if mesh.triangles.is_empty() || mesh.vertices.iter().any(|v| !v.coords.iter().all(|c| c.is_finite())) {
        return Err(CalibrationError::Scan("the part's mesh has no triangles or a non-finite vertex".into()));
    }
    let g = cell.geometry();
    let drawing = ChainCalibration::nominal(g);
    let nominal = ChainTruth::new(g, &ChainErrors::exact())?;
    let exact = ChainCalibration::from_truth(&cell.truth, calibration.reference);
    let start =
        g.quantise(MachineConfig::new(g.travel_mm[0][0], g.travel_mm[1][0], 0.0, opts.a_angles_deg[0]));
    let mut runner = Runner::new(cell, mesh, opts.seed, start)?;
    let mut cloud = MachineScan::default();
    let (mut used, mut drawn, mut ideal) = (Stats::default(), Stats::default(), Stats::default());
    let field = spec.field_at(opts.standoff_mm).map(|f| f * (1.0 - opts.overlap));
    for &a in &opts.a_angles_deg {
        // The part's extent over the table at this A, by the drawing (what the planner knows).
        let w = nominal.table_from_rotor(a);
        let (mut lo, mut hi) = (Vector3::repeat(f64::INFINITY), Vector3::repeat(f64::NEG_INFINITY));
        for v in &mesh.vertices {
            let p = (w * v).coords;
            lo = lo.inf(&p);
            hi = hi.sup(&p);
        }
        let n = [0, 1].map(|i| ((hi[i] - lo[i]) / field[i]).ceil().max(1.0) as usize);
        for j in 0..n[1] {
            for i in 0..n[0] {
                let cx = lo.x + (hi.x - lo.x) * (i as f64 + 0.5) / n[0] as f64;
                let cy = lo.y + (hi.y - lo.y) * (j as f64 + 0.5) / n[1] as f64;
                // The scanner looks down (sensor Y = −table Y): its optical centre over (cx, cy).
                let nose = Vector3::new(cx, cy, hi.z + opts.standoff_mm + g.scanner_below_nose_mm);
                let c = nose - Vector3::from(g.nose_at_zero_mm);
                let what = format!("view at A{a} tile {}/{}", j * n[0] + i + 1, n[0] * n[1]);
                let (c, shot) = runner.shoot(MachineConfig::new(c.x, c.y, c.z, a), &what)?;
                let iso = calibration.part_from_scanner(&c);
                let iso_d = drawing.part_from_scanner(&c);
                let iso_t = exact.part_from_scanner(&c);
                for (p, t) in shot.points.iter().zip(&shot.truth) {
                    let q = iso * p;
                    used.add(&q, t);
                    drawn.add(&(iso_d * p), t);
                    ideal.add(&(iso_t * p), t);
                    cloud.points.push(q);
                    cloud.shot.push(u16::try_from(runner.shots - 1).unwrap_or(u16::MAX));
                }
            }
        }
    }
    let report = ChainScanReport {
        shots: runner.shots,
        points: cloud.points.len() as u64,
        scan_time_s: runner.time_s,
        registration: used.check(),
        registration_drawing: drawn.check(),
        registration_truth: ideal.check(),
    };
    Ok((cloud, report))
}

/// Placement errors against the truth.
#[derive(Default)]
struct Stats {
    moments: AlignmentMoments,
    sum2: f64,
    max: f64,
}

impl Stats {
    fn add(&mut self, placed: &Point3<f64>, truth: &Point3<f64>) {
        let d = (placed - truth).norm();
        self.sum2 += d * d;
        self.max = self.max.max(d);
        self.moments.add(placed, truth);
    }

    fn check(&self) -> RegistrationCheck {
        let n = self.moments.count().max(1) as f64;
        RegistrationCheck {
            rms_mm: (self.sum2 / n).sqrt(),
            max_mm: self.max,
            merge_rms_mm: self.moments.rms_after_alignment(),
        }
    }
}
