//! The calibration's fits: spheres, planes, the scanner's mount and the table, and how well the
//! result registers the scans (see the module root for the model).

use nalgebra::{
    Isometry3, Matrix3, Matrix4, Point3, SymmetricEigen, Translation3, UnitQuaternion, Vector3, Vector4,
};
use serde::Serialize;

use super::routine::CalibrationOptions;
use super::{Calibration, CalibrationError, CellTruth, Offset, TableModel};
use crate::domain::scan::CellLayout;

/// Fewest sphere points a station must give.
pub const MIN_SPHERE_POINTS: usize = 300;
/// Fewest table-top points a station must give.
pub const MIN_TABLE_POINTS: usize = 500;
/// Sphere points per station the mount fit uses (evenly subsampled beyond).
const FIT_SPHERE_POINTS: usize = 3000;
/// Table points per station the plane fit uses.
const FIT_TABLE_POINTS: usize = 20000;
/// The sensor must have seen the sphere turned by at least this about two independent axes for
/// the mount to be found, degrees.
const MIN_VIEW_SPREAD_DEG: f64 = 5.0;
/// Lever that turns a normal's error (radians) into millimetres in the table fit: the table's
/// radius scale.
const NORMAL_LEVER_MM: f64 = 100.0;

/// One frame of a calibration scan as the cell measured it.
#[derive(Debug, Clone)]
pub struct CapturedFrame {
    /// Index of the station (table angle) in the options.
    pub station: usize,
    /// The table's encoder reading, degrees.
    pub table_deg: f64,
    /// `world_from_flange` as measured (latched or read).
    pub world_from_flange: Isometry3<f64>,
    /// `table_from_sensor` as it truly was (the simulation's truth: used only to report the
    /// registration error against the truth).
    pub true_table_from_sensor: Isometry3<f64>,
    /// Points on the sphere, sensor frame.
    pub sphere: Vec<Point3<f64>>,
    /// Points on the table top, sensor frame.
    pub table: Vec<Point3<f64>>,
}

/// How one station fitted.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct StationFit {
    /// Encoder reading, degrees.
    pub table_deg: f64,
    pub sphere_points: usize,
    pub table_points: usize,
    /// RMS distance of the sphere's points from the fitted sphere, mm.
    pub sphere_rms_mm: f64,
    /// RMS distance of the table's points from their plane, mm.
    pub plane_rms_mm: f64,
    /// Distance between the sphere's fitted centre and where the table model puts it, mm.
    pub centre_residual_mm: f64,
    /// Angle between the top's fitted normal and the table model's, degrees.
    pub normal_residual_deg: f64,
    /// Distance of the top's points (their centroid) from the table model's top, mm.
    pub plane_offset_mm: f64,
}

/// Placement error of calibration scan points, mm.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct RegistrationCheck {
    /// RMS distance between where points were placed and where they truly are.
    pub rms_mm: f64,
    /// Largest such distance.
    pub max_mm: f64,
    /// RMS after the one rigid transform that best aligns the placed points with the true ones
    /// (how well the views agree with each other: the merge error).
    pub merge_rms_mm: f64,
}

/// The calibration against the simulated cell's truth.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct TruthCheck {
    /// Largest distance, over the table's angles in the calibration and points on its top within
    /// its radius, between where the calibrated model and the truth (as the robot sees it) put
    /// the point, mm.
    pub table_error_mm: f64,
    /// Same before calibrating (the model it started from), mm.
    pub table_error_before_mm: f64,
    /// Distance between where the calibrated and the true mount put the middle of the scanner's
    /// window (155 mm out), mm.
    pub mount_error_mm: f64,
    /// Same before calibrating, mm.
    pub mount_error_before_mm: f64,
    /// The calibrated encoder zero minus the true one, degrees (a robot-base yaw shows here too).
    pub zero_error_deg: f64,
}

/// What a calibration produced and how well it fits.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct CalibrationReport {
    pub calibration: Calibration,
    /// The calibration the scans were placed with (the one it replaces, or the drawing).
    pub previous: Calibration,
    pub options: CalibrationOptions,
    pub stations: Vec<StationFit>,
    /// RMS distance of every sphere point from its fitted sphere, mm.
    pub sphere_rms_mm: f64,
    /// RMS over the stations of the centre, normal (as mm at 100 mm) and plane residuals of
    /// the table fit, mm.
    pub table_fit_rms_mm: f64,
    /// How far the sensor turned between the views of the sphere, about the two axes it turned
    /// most about, degrees.
    pub view_spread_deg: [f64; 2],
    /// RMS distance of the sphere's centres, placed in the table's frame, from their mean: with
    /// the previous calibration and with the new one, mm (no truth needed: the sphere does not
    /// move on the table).
    pub centre_spread_before_mm: f64,
    pub centre_spread_after_mm: f64,
    /// The calibration scans' points placed with the previous and the new calibration against
    /// the truth (simulated cell only).
    pub registration_before: Option<RegistrationCheck>,
    pub registration_after: Option<RegistrationCheck>,
    pub truth: Option<TruthCheck>,
    /// Simulated time of the calibration scans, s.
    pub scan_time_s: f64,
    pub frames: u64,
    pub points: u64,
    pub diagnostics: Vec<String>,
}

/// Running moments of pairs (placed, true) from which the RMS after the best rigid alignment
/// follows without keeping the points (Kabsch on the cross-covariance).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct AlignmentMoments {
    n: f64,
    origin: Option<Vector3<f64>>,
    sp: Vector3<f64>,
    sq: Vector3<f64>,
    spp: f64,
    sqq: f64,
    spq: Matrix3<f64>,
}

impl AlignmentMoments {
    /// Adds one pair.
    pub fn add(&mut self, placed: &Point3<f64>, truth: &Point3<f64>) {
        let o = *self.origin.get_or_insert(truth.coords);
        let p = placed.coords - o;
        let q = truth.coords - o;
        self.n += 1.0;
        self.sp += p;
        self.sq += q;
        self.spp += p.norm_squared();
        self.sqq += q.norm_squared();
        self.spq += p * q.transpose();
    }

    /// Adds another accumulator's pairs.
    pub fn merge(&mut self, other: &AlignmentMoments) {
        let Some(oo) = other.origin else { return };
        let o = *self.origin.get_or_insert(oo);
        // Shift the other's sums from its origin to ours: p' = p + d.
        let d = oo - o;
        let (n, sp, sq) = (other.n, other.sp, other.sq);
        self.n += n;
        self.sp += sp + d * n;
        self.sq += sq + d * n;
        self.spp += other.spp + 2.0 * d.dot(&sp) + n * d.norm_squared();
        self.sqq += other.sqq + 2.0 * d.dot(&sq) + n * d.norm_squared();
        self.spq += other.spq + sp * d.transpose() + d * sq.transpose() + d * d.transpose() * n;
    }

    /// Pairs added.
    pub fn count(&self) -> u64 {
        self.n as u64
    }

    /// RMS distance after the rigid transform that best maps the placed points onto the true
    /// ones, mm (0 without pairs).
    pub fn rms_after_alignment(&self) -> f64 {
        if self.n < 3.0 {
            return 0.0;
        }
        let n = self.n;
        let mp = self.sp / n;
        let mq = self.sq / n;
        let ep = self.spp - n * mp.norm_squared();
        let eq = self.sqq - n * mq.norm_squared();
        let h = self.spq - mp * mq.transpose() * n;
        let svd = h.svd(true, true);
        let (Some(u), Some(vt)) = (svd.u, svd.v_t) else { return 0.0 };
        let d = (vt.transpose() * u.transpose()).determinant().signum();
        let s = svd.singular_values;
        let tr = s[0] + s[1] + d * s[2];
        ((ep + eq - 2.0 * tr).max(0.0) / n).sqrt()
    }
}

/// Least squares by Levenberg-Marquardt (the `levenberg-marquardt` crate) with a central
/// difference Jacobian: minimises `Σ r(x)²` from `x0`.
pub(crate) fn least_squares(
    x0: Vec<f64>,
    residuals: impl Fn(&[f64], &mut Vec<f64>),
) -> Result<Vec<f64>, CalibrationError> {
    use levenberg_marquardt::{LeastSquaresProblem, LevenbergMarquardt};
    use nalgebra_lm::storage::Owned;
    use nalgebra_lm::{DMatrix, DVector, Dyn};

    struct Problem<F> {
        x: DVector<f64>,
        f: F,
    }

    impl<F: Fn(&[f64], &mut Vec<f64>)> Problem<F> {
        fn eval(&self, x: &[f64]) -> Vec<f64> {
            let mut r = Vec::new();
            (self.f)(x, &mut r);
            r
        }
    }

    impl<F: Fn(&[f64], &mut Vec<f64>)> LeastSquaresProblem<f64, Dyn, Dyn> for Problem<F> {
        type ResidualStorage = Owned<f64, Dyn>;
        type JacobianStorage = Owned<f64, Dyn, Dyn>;
        type ParameterStorage = Owned<f64, Dyn>;

        fn set_params(&mut self, x: &DVector<f64>) {
            self.x.copy_from(x);
        }

        fn params(&self) -> DVector<f64> {
            self.x.clone()
        }

        fn residuals(&self) -> Option<DVector<f64>> {
            let r = self.eval(self.x.as_slice());
            r.iter().all(|v| v.is_finite()).then(|| DVector::from_vec(r))
        }

        fn jacobian(&self) -> Option<DMatrix<f64>> {
            let n = self.x.len();
            let mut x: Vec<f64> = self.x.as_slice().to_vec();
            let mut cols: Vec<Vec<f64>> = Vec::with_capacity(n);
            for j in 0..n {
                let h = 1e-5 * x[j].abs().max(1.0);
                let x0 = x[j];
                x[j] = x0 + h;
                let up = self.eval(&x);
                x[j] = x0 - h;
                let down = self.eval(&x);
                x[j] = x0;
                cols.push(up.iter().zip(&down).map(|(a, b)| (a - b) / (2.0 * h)).collect());
            }
            let m = cols.first().map_or(0, Vec::len);
            let jac = DMatrix::from_fn(m, n, |i, j| cols[j][i]);
            jac.iter().all(|v| v.is_finite()).then_some(jac)
        }
    }

    let problem = Problem { x: DVector::from_vec(x0), f: residuals };
    let (done, report) = LevenbergMarquardt::new().minimize(problem);
    if !report.termination.was_successful() {
        return Err(CalibrationError::NoFit(format!(
            "{:?} after {} evaluations",
            report.termination, report.number_of_evaluations
        )));
    }
    Ok(done.x.as_slice().to_vec())
}

/// Sphere through `points` by the algebraic fit `|p|² = 2 c·p + k`: centre and radius.
pub fn fit_sphere_algebraic(points: &[Point3<f64>]) -> Option<(Point3<f64>, f64)> {
    if points.len() < 4 {
        return None;
    }
    let o = points.iter().fold(Vector3::zeros(), |a, p| a + p.coords) / points.len() as f64;
    let mut ata = Matrix4::<f64>::zeros();
    let mut atb = Vector4::<f64>::zeros();
    for p in points {
        let d = p.coords - o;
        let row = Vector4::new(2.0 * d.x, 2.0 * d.y, 2.0 * d.z, 1.0);
        ata += row * row.transpose();
        atb += row * d.norm_squared();
    }
    let sol = ata.cholesky()?.solve(&atb);
    let c = Vector3::new(sol[0], sol[1], sol[2]);
    let r2 = sol[3] + c.norm_squared();
    (r2 > 0.0 && sol.iter().all(|v| v.is_finite())).then(|| (Point3::from(c + o), r2.sqrt()))
}

/// Least-squares plane: centroid, unit normal (+Z side) and RMS distance.
pub fn fit_plane(points: &[Point3<f64>]) -> Option<(Point3<f64>, Vector3<f64>, f64)> {
    if points.len() < 3 {
        return None;
    }
    let n = points.len() as f64;
    let c = points.iter().fold(Vector3::zeros(), |a, p| a + p.coords) / n;
    let mut cov = Matrix3::zeros();
    for p in points {
        let d = p.coords - c;
        cov += d * d.transpose();
    }
    let eig = SymmetricEigen::new(cov / n);
    let (k, _) = eig.eigenvalues.iter().enumerate().min_by(|a, b| a.1.total_cmp(b.1))?;
    let mut normal: Vector3<f64> = eig.eigenvectors.column(k).into_owned();
    if normal.z < 0.0 {
        normal = -normal;
    }
    let mut sorted: Vec<f64> = eig.eigenvalues.iter().copied().collect();
    sorted.sort_by(f64::total_cmp);
    // Points on a line (the two larger spreads not both present) give no plane.
    if sorted[1] < 1e-6 * sorted[2].max(1e-12) {
        return None;
    }
    Some((Point3::from(c), normal, eig.eigenvalues[k].max(0.0).sqrt()))
}

/// Every `ceil(len / max)`-th item.
fn thin<T: Copy>(v: &[T], max: usize) -> Vec<T> {
    let step = v.len().div_ceil(max.max(1)).max(1);
    v.iter().step_by(step).copied().collect()
}

/// Small correction `(ω in mrad, τ in mm)` as a transform.
fn correction(x: &[f64]) -> Isometry3<f64> {
    Isometry3::from_parts(
        Translation3::new(x[3], x[4], x[5]),
        UnitQuaternion::from_scaled_axis(Vector3::new(x[0], x[1], x[2]) * 1e-3),
    )
}

/// The points of one station, in the measured flange frames.
struct StationData {
    table_deg: f64,
    /// (world_from_flange, sensor point) on the sphere, thinned.
    sphere: Vec<(Isometry3<f64>, Point3<f64>)>,
    /// Same on the table top.
    table: Vec<(Isometry3<f64>, Point3<f64>)>,
    sphere_total: usize,
    table_total: usize,
}

fn stations(
    frames: &[CapturedFrame],
    opts: &CalibrationOptions,
) -> Result<Vec<StationData>, CalibrationError> {
    let mut out = Vec::with_capacity(opts.table_angles_deg.len());
    for (k, &deg) in opts.table_angles_deg.iter().enumerate() {
        let mine: Vec<&CapturedFrame> = frames.iter().filter(|f| f.station == k).collect();
        let sphere: Vec<(Isometry3<f64>, Point3<f64>)> =
            mine.iter().flat_map(|f| f.sphere.iter().map(|p| (f.world_from_flange, *p))).collect();
        let table: Vec<(Isometry3<f64>, Point3<f64>)> =
            mine.iter().flat_map(|f| f.table.iter().map(|p| (f.world_from_flange, *p))).collect();
        if sphere.len() < MIN_SPHERE_POINTS {
            return Err(CalibrationError::Degenerate(format!(
                "at table angle {deg}° the reference sphere gave {} points (at least {MIN_SPHERE_POINTS}): it was not seen; check sphere_at_mm and sphere_radius_mm",
                sphere.len()
            )));
        }
        if table.len() < MIN_TABLE_POINTS {
            return Err(CalibrationError::Degenerate(format!(
                "at table angle {deg}° the table top gave {} points (at least {MIN_TABLE_POINTS}): it was not seen",
                table.len()
            )));
        }
        let table_deg = mine.iter().map(|f| f.table_deg).sum::<f64>() / mine.len().max(1) as f64;
        out.push(StationData {
            table_deg,
            sphere_total: sphere.len(),
            table_total: table.len(),
            sphere: thin(&sphere, FIT_SPHERE_POINTS),
            table: thin(&table, FIT_TABLE_POINTS),
        });
    }
    if out.len() < 3 {
        return Err(CalibrationError::Degenerate(format!(
            "the sphere was seen at {} table angles, at least 3 are needed to find the axis",
            out.len()
        )));
    }
    Ok(out)
}

/// How far the flange turned between the frames, about the two axes it turned most about
/// (square roots of the two largest eigenvalues of the rotation vectors' covariance), degrees.
fn view_spread(frames: &[CapturedFrame]) -> [f64; 2] {
    let Some(first) = frames.first() else { return [0.0; 2] };
    let r0 = first.world_from_flange.rotation;
    let ws: Vec<Vector3<f64>> =
        frames.iter().map(|f| (f.world_from_flange.rotation * r0.inverse()).scaled_axis()).collect();
    let n = ws.len() as f64;
    let m = ws.iter().fold(Vector3::zeros(), |a, w| a + w) / n;
    let cov = ws.iter().fold(Matrix3::zeros(), |a, w| a + (w - m) * (w - m).transpose()) / n;
    let mut e: Vec<f64> =
        SymmetricEigen::new(cov).eigenvalues.iter().map(|v| v.max(0.0).sqrt().to_degrees()).collect();
    e.sort_by(|a, b| b.total_cmp(a));
    [e[0], e[1]]
}

/// Fits the calibration to the captured frames. `previous` is the calibration the frames were
/// placed with; `truth`, when the cell is simulated, is used only for the report's comparison.
pub fn solve(
    frames: &[CapturedFrame],
    opts: &CalibrationOptions,
    layout: &CellLayout,
    previous: &Calibration,
    truth: Option<&CellTruth>,
) -> Result<(Calibration, CalibrationReport), CalibrationError> {
    let data = stations(frames, opts)?;
    let spread = view_spread(frames);
    if spread[1] < MIN_VIEW_SPREAD_DEG {
        return Err(CalibrationError::Degenerate(format!(
            "the sphere was seen with the scanner turned by {:.1}° and {:.1}° about its two main axes: the mount needs at least {MIN_VIEW_SPREAD_DEG}° about two axes",
            spread[0], spread[1]
        )));
    }
    let radius = opts.sphere_radius_mm;
    let m0 = previous.flange_from_scanner();

    // Initial centres: the sphere's points placed with the previous mount.
    let mut x0 = vec![0.0; 6];
    let mut centres_before = Vec::with_capacity(data.len());
    for s in &data {
        let pts: Vec<Point3<f64>> = s.sphere.iter().map(|(f, p)| f * (m0 * p)).collect();
        let Some((c, r)) = fit_sphere_algebraic(&pts) else {
            return Err(CalibrationError::Degenerate(format!(
                "at table angle {}° the sphere's points do not span a sphere",
                s.table_deg
            )));
        };
        if (r - radius).abs() > 0.2 * radius {
            return Err(CalibrationError::Degenerate(format!(
                "at table angle {}° the points fit a sphere of radius {r:.2} mm, not the reference's {radius} mm: something else was scanned",
                s.table_deg
            )));
        }
        centres_before.push(c);
        x0.extend_from_slice(c.coords.as_slice());
    }

    // The mount and every centre (hand-eye): the centre must not move as the sensor turns.
    let sphere_residuals = |x: &[f64], r: &mut Vec<f64>| {
        let m = m0 * correction(x);
        for (k, s) in data.iter().enumerate() {
            let c = Point3::new(x[6 + 3 * k], x[7 + 3 * k], x[8 + 3 * k]);
            for (f, p) in &s.sphere {
                r.push(((f * (m * p)) - c).norm() - radius);
            }
        }
    };
    let x = least_squares(x0, sphere_residuals)?;
    let mount_iso = m0 * correction(&x);
    let bracket_inv = depthmill_geometry::arm::ArmModel::scanner_bracket().inverse();
    let mount = Offset::from_iso(&(bracket_inv * mount_iso));
    let centres: Vec<Point3<f64>> =
        (0..data.len()).map(|k| Point3::new(x[6 + 3 * k], x[7 + 3 * k], x[8 + 3 * k])).collect();
    let mut per_sphere = Vec::new();
    sphere_residuals(&x, &mut per_sphere);
    let mut sphere_rms = Vec::with_capacity(data.len());
    let mut at = 0;
    for s in &data {
        let r = &per_sphere[at..at + s.sphere.len()];
        at += s.sphere.len();
        sphere_rms.push((r.iter().map(|v| v * v).sum::<f64>() / r.len().max(1) as f64).sqrt());
    }
    let sphere_rms_all =
        (per_sphere.iter().map(|v| v * v).sum::<f64>() / per_sphere.len().max(1) as f64).sqrt();

    // The top's plane at every station, with the new mount.
    let mut planes = Vec::with_capacity(data.len());
    for s in &data {
        let pts: Vec<Point3<f64>> = s.table.iter().map(|(f, p)| f * (mount_iso * p)).collect();
        let Some(plane) = fit_plane(&pts) else {
            return Err(CalibrationError::Degenerate(format!(
                "at table angle {}° the table top's points lie on a line: no plane",
                s.table_deg
            )));
        };
        planes.push(plane);
    }

    // The table: the centres on the circle the nest describes, the top's planes.
    let nest = Point3::from(opts.sphere_at_mm);
    let table_residuals = |p: &[f64], r: &mut Vec<f64>| {
        let mut q = [0.0; 8];
        q.copy_from_slice(&p[..8]);
        let t = TableModel::from_params(&q);
        for (k, s) in data.iter().enumerate() {
            let w = t.world_from_table(s.table_deg);
            let c = w * nest - centres[k];
            r.extend_from_slice(&[c.x, c.y, c.z]);
            let n = w.rotation * Vector3::z();
            let dn = (n - planes[k].1) * NORMAL_LEVER_MM;
            r.extend_from_slice(&[dn.x, dn.y, dn.z]);
            r.push(n.dot(&(planes[k].0 - Point3::from(w.translation.vector))));
        }
    };
    let t0 = previous.table.to_params().to_vec();
    let tp = least_squares(t0, table_residuals)?;
    let mut q = [0.0; 8];
    q.copy_from_slice(&tp[..8]);
    let mut table = TableModel::from_params(&q);
    table.zero_deg = table.zero_deg.rem_euclid(360.0);
    if table.zero_deg > 180.0 {
        table.zero_deg -= 360.0;
    }
    let calibration = Calibration { table, scanner_mount: mount };
    calibration.validate(layout)?;

    let mut res = Vec::new();
    table_residuals(&tp, &mut res);
    let table_fit_rms = (res.iter().map(|v| v * v).sum::<f64>() / res.len().max(1) as f64).sqrt();
    let stations_fit: Vec<StationFit> = data
        .iter()
        .enumerate()
        .map(|(k, s)| {
            let w = table.world_from_table(s.table_deg);
            let n = w.rotation * Vector3::z();
            StationFit {
                table_deg: s.table_deg,
                sphere_points: s.sphere_total,
                table_points: s.table_total,
                sphere_rms_mm: sphere_rms[k],
                plane_rms_mm: planes[k].2,
                centre_residual_mm: (w * nest - centres[k]).norm(),
                normal_residual_deg: n.angle(&planes[k].1).to_degrees(),
                plane_offset_mm: n.dot(&(planes[k].0 - Point3::from(w.translation.vector))),
            }
        })
        .collect();

    let spread_of = |model: &TableModel, cs: &[Point3<f64>]| {
        let local: Vec<Point3<f64>> =
            data.iter().zip(cs).map(|(s, c)| model.world_from_table(s.table_deg).inverse() * c).collect();
        let m = local.iter().fold(Vector3::zeros(), |a, p| a + p.coords) / local.len() as f64;
        (local.iter().map(|p| (p.coords - m).norm_squared()).sum::<f64>() / local.len() as f64).sqrt()
    };

    let registration = |cal: &Calibration| -> RegistrationCheck {
        let m = cal.flange_from_scanner();
        let mut moments = AlignmentMoments::default();
        let (mut sq, mut mx) = (0.0, 0.0f64);
        for f in frames {
            let placed_from_sensor =
                cal.table.world_from_table(f.table_deg).inverse() * f.world_from_flange * m;
            for p in thin(&f.sphere, 64).iter().chain(thin(&f.table, 64).iter()) {
                let a = placed_from_sensor * p;
                let b = f.true_table_from_sensor * p;
                let e = (a - b).norm_squared();
                sq += e;
                mx = mx.max(e);
                moments.add(&a, &b);
            }
        }
        let n = moments.count().max(1) as f64;
        RegistrationCheck {
            rms_mm: (sq / n).sqrt(),
            max_mm: mx.sqrt(),
            merge_rms_mm: moments.rms_after_alignment(),
        }
    };
    let has_truth = frames.iter().any(|f| f.true_table_from_sensor != Isometry3::identity());

    let truth_check = truth.map(|t| {
        // The truth as the robot sees it: its base error moves the world.
        let base_inv = t.arm.base.inverse();
        let rim: Vec<Point3<f64>> = (0..8)
            .map(|k| {
                let a = k as f64 * std::f64::consts::FRAC_PI_4;
                Point3::new(200.0 * a.cos(), 200.0 * a.sin(), 0.0)
            })
            .chain(std::iter::once(Point3::origin()))
            .collect();
        let table_err = |m: &TableModel| {
            data.iter()
                .flat_map(|s| {
                    let truth_w = base_inv * t.table.world_from_table(s.table_deg);
                    let ours = m.world_from_table(s.table_deg);
                    rim.iter().map(move |p| (truth_w * p - ours * p).norm())
                })
                .fold(0.0, f64::max)
        };
        let window = Point3::new(0.0, 0.0, 155.0);
        let mount_err = |c: &Calibration| (c.flange_from_scanner() * window - t.arm.tool * window).norm();
        let mut dz = (table.zero_deg - t.table.zero_deg).rem_euclid(360.0);
        if dz > 180.0 {
            dz -= 360.0;
        }
        TruthCheck {
            table_error_mm: table_err(&table),
            table_error_before_mm: table_err(&previous.table),
            mount_error_mm: mount_err(&calibration),
            mount_error_before_mm: mount_err(previous),
            zero_error_deg: dz,
        }
    });

    let report = CalibrationReport {
        calibration,
        previous: *previous,
        options: opts.clone(),
        stations: stations_fit,
        sphere_rms_mm: sphere_rms_all,
        table_fit_rms_mm: table_fit_rms,
        view_spread_deg: spread,
        centre_spread_before_mm: spread_of(&previous.table, &centres_before),
        centre_spread_after_mm: spread_of(&table, &centres),
        registration_before: has_truth.then(|| registration(previous)),
        registration_after: has_truth.then(|| registration(&calibration)),
        truth: truth_check,
        scan_time_s: 0.0,
        frames: frames.len() as u64,
        points: frames.iter().map(|f| (f.sphere.len() + f.table.len()) as u64).sum(),
        diagnostics: Vec::new(),
    };
    Ok((calibration, report))
}
