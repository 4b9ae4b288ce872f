//! A scanner on the mill itself (seed 003): an area scanner clamped in the EMCO's tool holder,
//! the part on the mill's A axis, partial scans placed by the machine's kinematic chain alone.
//!
//! # Truth and belief
//! The mill's slides are not perfectly square nor their lead screws perfectly pitched, the A
//! axis does not lie exactly where the fixture drawing puts it and its encoder's zero is off, and
//! a scanner clamped by hand in the holder sits a millimetre and a degree or two from where its
//! drawing says. [`ChainErrors`] is that profile (realistic defaults), [`ChainTruth`] the geometry
//! the simulation runs on; the software sees only the drawing ([`MachineGeometry`]) until it
//! calibrates, and places points with a [`ChainCalibration`].
//!
//! # Frames
//! The table frame: the mill table, X/Y along its slides, Z up. With the axes at `c = (x, y, z)`
//! the spindle nose stands at `nose0 + x·e_x + y·e_y + z·e_z` over the table (the slides move
//! the table under the head; only the relative motion counts), the scanner hangs under it by
//! `head_from_scanner`. The A axis carries the part: `table_from_rotor(a) = T(p_a) · R_tilt ·
//! Rx(a − zero)`, the rotor frame having X along the axis from the faceplate's centre.
//!
//! # The chain (seed 003)
//! The head does not turn, so in the scanner's frame `S0` at a reference configuration `c0` a
//! point seen from configuration `c` is at `p_S + Σ_i (c_i − c0_i)·u_i`, `u_i` being how far the
//! scanner moves, in its own frame, per millimetre commanded on axis `i` (the slides' directions,
//! squareness and pitch and the scanner's mounting all folded in: what the calibration measures);
//! the A axis, a line `(a_point, a_dir)` in `S0`, then turns it back by `−(a − a0)`.
//! [`ChainCalibration::place`] is that chain followed by the part frame (the rotor frame at `a0`,
//! found from where the calibration point sits on the rotor).

pub mod area;
pub mod routine;
#[cfg(test)]
mod tests;

use nalgebra::{Isometry3, Matrix3, Point3, Rotation3, Translation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

pub use area::{AreaScanner, AreaScannerSpec, Shot};
pub use routine::{
    ChainCalibrationOptions, ChainCalibrationReport, ChainScanOptions, ChainScanReport, ChainTruthCheck,
    MachineCell, MachineScan, Observation, calibrate_chain, place_on_rotor, scan_on_machine,
};

use super::calibration::{CalibrationError, invalid};

/// Positions of the mill's axes: X, Y, Z in mm (machine coordinates) and A in degrees.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct MachineConfig {
    pub x: f64,
    pub y: f64,
    pub z: f64,
    pub a: f64,
}

impl MachineConfig {
    pub fn new(x: f64, y: f64, z: f64, a: f64) -> Self {
        Self { x, y, z, a }
    }

    fn linear(&self) -> Vector3<f64> {
        Vector3::new(self.x, self.y, self.z)
    }
}

impl std::fmt::Display for MachineConfig {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "X{:.3} Y{:.3} Z{:.3} A{:.3}", self.x, self.y, self.z, self.a)
    }
}

/// The drawing of the mill, its A axis and the scanner in its holder: what the software knows
/// before calibrating. Travels, resolution and rates of the EMCO F1 class profile
/// (`services/machine/machines/emco-f1.toml`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MachineGeometry {
    /// Travels, mm: `[min, max]` of X, Y and Z.
    pub travel_mm: [[f64; 2]; 3],
    /// Linear resolution (one motor step), mm: every position is a whole number of steps.
    pub step_mm: f64,
    /// A-axis resolution, degrees.
    pub a_step_deg: f64,
    /// Rapid rate of the linear axes, mm/min, and their acceleration, mm/s².
    pub rapid_mm_min: f64,
    pub accel_mm_s2: f64,
    /// A-axis rate, °/min, and acceleration, °/s².
    pub a_rate_deg_min: f64,
    pub a_accel_deg_s2: f64,
    /// Wait after a move before a shot (the slides settle), s.
    pub settle_s: f64,
    /// The spindle nose over the table frame's origin with every axis at 0, mm.
    pub nose_at_zero_mm: [f64; 3],
    /// The A axis's faceplate centre in the table frame, mm (the axis runs along +X from it).
    pub a_axis_at_mm: [f64; 3],
    /// How far below the spindle nose the scanner's optical centre sits, mm (it looks down).
    pub scanner_below_nose_mm: f64,
}

impl Default for MachineGeometry {
    fn default() -> Self {
        Self {
            travel_mm: [[0.0, 200.0], [0.0, 100.0], [-200.0, 0.0]],
            step_mm: 0.01,
            a_step_deg: 0.001,
            rapid_mm_min: 700.0,
            accel_mm_s2: 50.0,
            a_rate_deg_min: 1800.0,
            a_accel_deg_s2: 180.0,
            settle_s: 0.2,
            nose_at_zero_mm: [0.0, 0.0, 330.0],
            a_axis_at_mm: [20.0, 50.0, 70.0],
            scanner_below_nose_mm: 60.0,
        }
    }
}

impl MachineGeometry {
    /// Checks the drawing; the error names the field.
    pub fn validate(&self) -> Result<(), CalibrationError> {
        for (i, [lo, hi]) in self.travel_mm.iter().enumerate() {
            if !(lo.is_finite() && hi.is_finite() && hi > lo) {
                return Err(invalid(
                    &format!("travel_mm[{i}]"),
                    format!("[{lo}, {hi}]"),
                    "finite, min < max",
                ));
            }
        }
        let positive = [
            ("step_mm", self.step_mm),
            ("a_step_deg", self.a_step_deg),
            ("rapid_mm_min", self.rapid_mm_min),
            ("accel_mm_s2", self.accel_mm_s2),
            ("a_rate_deg_min", self.a_rate_deg_min),
            ("a_accel_deg_s2", self.a_accel_deg_s2),
            ("scanner_below_nose_mm", self.scanner_below_nose_mm),
        ];
        for (field, v) in positive {
            if !(v.is_finite() && v > 0.0) {
                return Err(invalid(field, v, "a positive number"));
            }
        }
        if !(self.settle_s.is_finite() && self.settle_s >= 0.0) {
            return Err(invalid("settle_s", self.settle_s, "seconds >= 0"));
        }
        for (field, v) in [("nose_at_zero_mm", self.nose_at_zero_mm), ("a_axis_at_mm", self.a_axis_at_mm)] {
            if v.iter().any(|c| !c.is_finite()) {
                return Err(invalid(field, format!("{v:?}"), "finite millimetres"));
            }
        }
        Ok(())
    }

    /// The configuration with every axis on a whole step.
    pub fn quantise(&self, c: MachineConfig) -> MachineConfig {
        let q = |v: f64, s: f64| (v / s).round() * s;
        MachineConfig::new(
            q(c.x, self.step_mm),
            q(c.y, self.step_mm),
            q(c.z, self.step_mm),
            q(c.a, self.a_step_deg),
        )
    }

    /// Refuses a configuration outside the travels, naming the axis.
    pub fn check_travel(&self, c: &MachineConfig) -> Result<(), CalibrationError> {
        for (i, (name, v)) in [("X", c.x), ("Y", c.y), ("Z", c.z)].into_iter().enumerate() {
            let [lo, hi] = self.travel_mm[i];
            if !(v.is_finite() && v >= lo - 1e-9 && v <= hi + 1e-9) {
                return Err(invalid(
                    &format!("axis {name}"),
                    format!("{v:.3} mm"),
                    &format!("outside the travel [{lo}, {hi}] mm"),
                ));
            }
        }
        if !c.a.is_finite() {
            return Err(invalid("axis A", c.a, "finite degrees"));
        }
        Ok(())
    }

    /// Time of a move between two configurations, every axis on its own trapezoidal profile at
    /// the rapid rate, s (the slowest axis decides).
    pub fn move_time_s(&self, from: &MachineConfig, to: &MachineConfig) -> f64 {
        let trap = |d: f64, v: f64, a: f64| {
            let d = d.abs();
            if d <= v * v / a { 2.0 * (d / a).sqrt() } else { d / v + v / a }
        };
        let v = self.rapid_mm_min / 60.0;
        let lin = [to.x - from.x, to.y - from.y, to.z - from.z]
            .into_iter()
            .map(|d| trap(d, v, self.accel_mm_s2))
            .fold(0.0, f64::max);
        lin.max(trap(to.a - from.a, self.a_rate_deg_min / 60.0, self.a_accel_deg_s2))
    }

    /// The scanner's nominal mounting: `scanner_below_nose_mm` under the nose, looking down
    /// (sensor +Z = table −Z), sensor X along table X.
    pub fn nominal_head_from_scanner(&self) -> Isometry3<f64> {
        Isometry3::from_parts(
            Translation3::new(0.0, 0.0, -self.scanner_below_nose_mm),
            UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::PI),
        )
    }
}

/// How the real mill, its A axis and the scanner's clamping differ from the drawing.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ChainErrors {
    /// Pitch error of each slide's lead screw (true travel per commanded millimetre − 1), ppm.
    pub scale_ppm: [f64; 3],
    /// Out-of-squareness of the slides, degrees: Y towards X, Z towards X, Z towards Y.
    pub squareness_deg: [f64; 3],
    /// The A axis's true line off the drawing across it (table Y, Z), mm.
    pub a_axis_offset_mm: [f64; 2],
    /// The A axis's tilt from table X about Y and about Z, degrees.
    pub a_axis_tilt_deg: [f64; 2],
    /// The A encoder's reading at the rotor's reference direction, degrees.
    pub a_zero_deg: f64,
    /// The scanner's clamping off its drawing: translation in the head frame, mm, and rotation
    /// (about head X, Y, Z), degrees.
    pub mount_offset_mm: [f64; 3],
    pub mount_rotation_deg: [f64; 3],
}

impl Default for ChainErrors {
    /// A bench mill as found: screws tens of ppm off, slides square within a few hundredths of a
    /// degree, a hand-set fixture a few tenths of a millimetre off, a scanner clamped in the
    /// holder a millimetre and a couple of degrees (mostly round the spindle) off.
    fn default() -> Self {
        Self {
            scale_ppm: [80.0, -60.0, 120.0],
            squareness_deg: [0.02, -0.015, 0.025],
            a_axis_offset_mm: [0.35, -0.25],
            a_axis_tilt_deg: [0.04, -0.03],
            a_zero_deg: 0.15,
            mount_offset_mm: [0.6, -0.8, 1.1],
            mount_rotation_deg: [0.3, -0.4, 1.8],
        }
    }
}

impl ChainErrors {
    /// None: the mill is its drawing.
    pub fn exact() -> Self {
        Self {
            scale_ppm: [0.0; 3],
            squareness_deg: [0.0; 3],
            a_axis_offset_mm: [0.0; 2],
            a_axis_tilt_deg: [0.0; 2],
            a_zero_deg: 0.0,
            mount_offset_mm: [0.0; 3],
            mount_rotation_deg: [0.0; 3],
        }
    }

    /// Checks the profile against what a mill can be; the error names the field.
    pub fn validate(&self) -> Result<(), CalibrationError> {
        let groups: [(&str, &[f64], f64); 7] = [
            ("scale_ppm", &self.scale_ppm, 5000.0),
            ("squareness_deg", &self.squareness_deg, 1.0),
            ("a_axis_offset_mm", &self.a_axis_offset_mm, 10.0),
            ("a_axis_tilt_deg", &self.a_axis_tilt_deg, 2.0),
            ("a_zero_deg", std::slice::from_ref(&self.a_zero_deg), 10.0),
            ("mount_offset_mm", &self.mount_offset_mm, 10.0),
            ("mount_rotation_deg", &self.mount_rotation_deg, 10.0),
        ];
        for (field, vs, limit) in groups {
            if let Some(v) = vs.iter().find(|v| !(v.is_finite() && v.abs() <= limit)) {
                return Err(invalid(field, v, &format!("finite, at most {limit} in size")));
            }
        }
        Ok(())
    }
}

/// The mill as it is: what the simulation moves and casts with.
#[derive(Debug, Clone, PartialEq)]
pub struct ChainTruth {
    pub geometry: MachineGeometry,
    /// True travel per commanded millimetre of X, Y, Z, table frame.
    pub axes: [Vector3<f64>; 3],
    pub head_from_scanner: Isometry3<f64>,
    /// Where the axis crosses the faceplate, its direction, its encoder zero.
    pub a_point: Point3<f64>,
    pub a_tilt: UnitQuaternion<f64>,
    pub a_zero_deg: f64,
}

impl ChainTruth {
    pub fn new(geometry: &MachineGeometry, errors: &ChainErrors) -> Result<Self, CalibrationError> {
        geometry.validate()?;
        errors.validate()?;
        let s = errors.scale_ppm.map(|p| 1.0 + p * 1e-6);
        let [xy, xz, yz] = errors.squareness_deg.map(f64::to_radians);
        let ex = Vector3::x() * s[0];
        let ey = Vector3::new(xy.sin(), xy.cos(), 0.0) * s[1];
        let ez = Vector3::new(xz.sin(), yz.sin(), 1.0).normalize() * s[2];
        let nominal = geometry.nominal_head_from_scanner();
        let r = errors.mount_rotation_deg.map(f64::to_radians);
        let turn = UnitQuaternion::from_euler_angles(r[0], r[1], r[2]);
        let head_from_scanner = Isometry3::from_parts(
            Translation3::from(nominal.translation.vector + Vector3::from(errors.mount_offset_mm)),
            turn * nominal.rotation,
        );
        let [ty, tz] = errors.a_axis_tilt_deg.map(f64::to_radians);
        let a_tilt = UnitQuaternion::from_euler_angles(0.0, ty, tz);
        let a = geometry.a_axis_at_mm;
        Ok(Self {
            geometry: geometry.clone(),
            axes: [ex, ey, ez],
            head_from_scanner,
            a_point: Point3::new(a[0], a[1] + errors.a_axis_offset_mm[0], a[2] + errors.a_axis_offset_mm[1]),
            a_tilt,
            a_zero_deg: errors.a_zero_deg,
        })
    }

    /// Where the scanner truly is over the table at `c`.
    pub fn table_from_sensor(&self, c: &MachineConfig) -> Isometry3<f64> {
        let nose = Vector3::from(self.geometry.nose_at_zero_mm)
            + self.axes[0] * c.x
            + self.axes[1] * c.y
            + self.axes[2] * c.z;
        Isometry3::from_parts(Translation3::from(nose), UnitQuaternion::identity()) * self.head_from_scanner
    }

    /// Where the rotor truly is over the table with the A encoder reading `a`.
    pub fn table_from_rotor(&self, a: f64) -> Isometry3<f64> {
        let turn = UnitQuaternion::from_axis_angle(&Vector3::x_axis(), (a - self.a_zero_deg).to_radians());
        Isometry3::from_parts(Translation3::from(self.a_point.coords), self.a_tilt * turn)
    }

    /// The scanner in the rotor's (the part's) frame at `c`: what the rays are cast with.
    pub fn rotor_from_sensor(&self, c: &MachineConfig) -> Isometry3<f64> {
        self.table_from_rotor(c.a).inverse() * self.table_from_sensor(c)
    }
}

/// The chain as the software believes it: measured (or, before calibrating, drawn) in the
/// scanner's frame at a reference configuration (module doc).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ChainCalibration {
    /// `"drawing"` (the nominal chain), `"calibrated"` or `"truth"` (the simulation's own, for
    /// checks).
    pub source: String,
    /// The configuration the frame `S0` is taken at.
    pub reference: MachineConfig,
    /// The scanner's displacement in its own frame per commanded millimetre of X, Y, Z.
    pub axes_in_scanner: [[f64; 3]; 3],
    /// The A axis in `S0`: a point on it and its unit direction (positive A turns about it).
    pub a_point_mm: [f64; 3],
    pub a_dir: [f64; 3],
    /// The part frame (the rotor at the reference A) in `S0`.
    pub s0_from_part: Isometry3<f64>,
}

impl ChainCalibration {
    /// What the drawing gives, with the reference at every axis 0.
    pub fn nominal(geometry: &MachineGeometry) -> Self {
        let truth = ChainTruth {
            geometry: geometry.clone(),
            axes: [Vector3::x(), Vector3::y(), Vector3::z()],
            head_from_scanner: geometry.nominal_head_from_scanner(),
            a_point: Point3::from(geometry.a_axis_at_mm),
            a_tilt: UnitQuaternion::identity(),
            a_zero_deg: 0.0,
        };
        Self { source: "drawing".into(), ..Self::from_truth(&truth, MachineConfig::new(0.0, 0.0, 0.0, 0.0)) }
    }

    /// The chain a geometry gives exactly, referenced at `reference`.
    pub fn from_truth(truth: &ChainTruth, reference: MachineConfig) -> Self {
        let s0 = truth.table_from_sensor(&reference);
        let inv = s0.inverse();
        let axes = truth.axes.map(|e| {
            let u = inv.rotation * e;
            [u.x, u.y, u.z]
        });
        let p = inv * truth.a_point;
        let d = inv.rotation * (truth.a_tilt * Vector3::x());
        Self {
            source: "truth".into(),
            reference,
            axes_in_scanner: axes,
            a_point_mm: [p.x, p.y, p.z],
            a_dir: [d.x, d.y, d.z],
            s0_from_part: inv * truth.table_from_rotor(reference.a),
        }
    }

    fn axis(&self, i: usize) -> Vector3<f64> {
        Vector3::from(self.axes_in_scanner[i])
    }

    /// A point seen in the scanner's frame with the mill at `c`, in the part frame.
    pub fn place(&self, c: &MachineConfig, p: &Point3<f64>) -> Point3<f64> {
        self.part_from_scanner(c) * p
    }

    /// The whole chain for configuration `c`: part frame from the scanner's frame there.
    pub fn part_from_scanner(&self, c: &MachineConfig) -> Isometry3<f64> {
        let d = c.linear() - self.reference.linear();
        let shift = self.axis(0) * d.x + self.axis(1) * d.y + self.axis(2) * d.z;
        let axis = nalgebra::Unit::new_normalize(Vector3::from(self.a_dir));
        let back = UnitQuaternion::from_axis_angle(&axis, -(c.a - self.reference.a).to_radians());
        let ap = Vector3::from(self.a_point_mm);
        // q = R(p + shift − ap) + ap
        let s0_from_scanner = Isometry3::from_parts(Translation3::from(shift), UnitQuaternion::identity());
        let unturn = Isometry3::from_parts(Translation3::from(ap - back * ap), back);
        self.s0_from_part.inverse() * unturn * s0_from_scanner
    }

    /// Measured scale of each slide (length of `u_i` − 1), ppm.
    pub fn scale_ppm(&self) -> [f64; 3] {
        [0, 1, 2].map(|i| (self.axis(i).norm() - 1.0) * 1e6)
    }

    /// Measured out-of-squareness of the slides, 90° minus the angle between them (positive:
    /// leaning towards each other): Y towards X, Z towards X, Z towards Y, degrees.
    pub fn squareness_deg(&self) -> [f64; 3] {
        let ang = |i: usize, j: usize| 90.0 - self.axis(i).angle(&self.axis(j)).to_degrees();
        [ang(0, 1), ang(0, 2), ang(1, 2)]
    }

    /// The A axis's angle from the X slide, degrees.
    pub fn a_to_x_deg(&self) -> f64 {
        let d = Vector3::from(self.a_dir);
        d.angle(&self.axis(0)).to_degrees()
    }
}

/// Frame with `x` along `dir` and the radial unit `w` (perpendicular to it) of a point at
/// rotor `(·, sy, sz)`: the rotor's Y and Z (`ez = (sz·w + sy·v)/ρ`, `ey = (sy·w − sz·v)/ρ`,
/// `v = x × w`).
fn rotor_axes(dir: &Vector3<f64>, w: &Vector3<f64>, sy: f64, sz: f64) -> Option<Matrix3<f64>> {
    let rho = sy.hypot(sz);
    if rho < 1e-9 {
        return None;
    }
    let v = dir.cross(w);
    let ez = (w * sz + v * sy) / rho;
    let ey = (w * sy - v * sz) / rho;
    let m = Matrix3::from_columns(&[*dir, ey, ez]);
    let r = Rotation3::from_matrix_eps(&m, 1e-12, 50, Rotation3::identity());
    Some(r.into_inner())
}
