//! The cell as it truly is, as the software believes it is, and the calibration that brings the
//! belief to the truth.
//!
//! # Truth and belief
//! A real cell never matches its drawing: the rotary table's axis stands a millimetre or so from
//! where it should and leans by a few hundredths of a degree, its top is not square to the axis
//! (it wobbles as it turns), its encoder's zero is not the table's reference direction, the
//! robot's base is not exactly where it was set down, the scanner's bracket is bent by a fraction
//! of a degree and every joint's encoder reads a little off. [`CellErrors`] is that profile (set
//! in the scanning service's configuration, realistic amounts by default) and [`CellTruth`] the
//! geometry it gives: the physics (where the sensor truly is, where the table truly is) runs on
//! it. The software only sees the nominal description, or the last [`Calibration`]: the
//! measured poses and the table model that place every point come from there.
//!
//! # The model
//! World = the robot's base frame as the robot reports it. The table at encoder reading `θ`:
//!
//! `world_from_table(θ) = T(x, y, z) · Rx(a) · Ry(b) · Rz(θ − zero) · Rx(c) · Ry(d)`
//!
//! with `(x, y, z)` where the axis meets the top, `a, b` the axis's tilt from the vertical, `c, d`
//! the top's tilt against the axis (constant in the turning frame, so its normal precesses round
//! the axis: the wobble with angle) and `zero` the encoder reading of the table's reference
//! direction ([`TableModel`]). The scanner hangs on the flange by `flange_from_scanner =
//! bracket · mount` where `mount` is the calibrated correction of the nominal bracket.
//! A robot-base error moves everything the robot measures by one rigid transform: the
//! calibration finds the table in the robot's frame, which absorbs it.
//!
//! # The routine
//! Seed 002 calibrates the robot against the table by scanning the table top itself; with a
//! reference sphere on the table (a precision ball on a post at a known place) the table's zero
//! and the scanner's mount come out too. [`routine`] plans it: at every table angle of the
//! options a straight-down pass over the sphere and one over the table top across the axis; at
//! the angle where the sphere comes nearest the robot, passes over the sphere tilted ±20° about two directions and at two more
//! standoffs. [`fit`] solves it in two least-squares problems (Levenberg-Marquardt from the
//! `levenberg-marquardt` crate): the mount and the sphere's centre at every angle from the
//! sphere's points (a hand-eye calibration: the centre must not move when the sensor turns),
//! then the eight table parameters from the centres and the table-top planes.

pub mod fit;
pub mod routine;
#[cfg(test)]
mod tests;

use depthmill_geometry::arm::ArmModel;
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

use super::scan::CellLayout;

pub use fit::{CalibrationReport, RegistrationCheck, StationFit, TruthCheck};
pub use routine::{CalibrationOptions, calibration_session};

/// Why a calibration cannot be made or used.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CalibrationError {
    #[error("invalid {field} = {value}: {reason}")]
    Invalid { field: String, value: String, reason: String },
    #[error("not enough calibration data: {0}")]
    Degenerate(String),
    #[error("the calibration fit did not converge: {0}")]
    NoFit(String),
    #[error("calibration scan: {0}")]
    Scan(String),
    /// The rotary table did not answer or failed its move (a device fault, worth a retry).
    #[error("calibration scan: rotary table: {0}")]
    Table(String),
    #[error("the calibration was cancelled")]
    Cancelled,
}

pub(crate) fn invalid(field: &str, value: impl std::fmt::Display, reason: &str) -> CalibrationError {
    CalibrationError::Invalid { field: field.into(), value: value.to_string(), reason: reason.into() }
}

fn rx(deg: f64) -> UnitQuaternion<f64> {
    UnitQuaternion::from_axis_angle(&Vector3::x_axis(), deg.to_radians())
}

fn ry(deg: f64) -> UnitQuaternion<f64> {
    UnitQuaternion::from_axis_angle(&Vector3::y_axis(), deg.to_radians())
}

/// The rotary table as a rigid body turning about its axis, in the robot's base frame (see the
/// module doc for the formula).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct TableModel {
    /// X of the point where the axis meets the top, mm.
    pub axis_x_mm: f64,
    /// Y of that point, mm.
    pub axis_y_mm: f64,
    /// Z of that point (the top's height at the axis), mm.
    pub top_z_mm: f64,
    /// The axis's tilt from the vertical about world X, degrees.
    pub axis_tilt_x_deg: f64,
    /// ... then about Y, degrees.
    pub axis_tilt_y_deg: f64,
    /// Encoder reading at the table's reference direction, degrees.
    pub zero_deg: f64,
    /// The top's tilt against the axis about the table's X, degrees (the wobble).
    pub top_tilt_x_deg: f64,
    /// ... then about its Y, degrees.
    pub top_tilt_y_deg: f64,
}

impl TableModel {
    /// The drawing: a vertical axis at the layout's position, a square top, zero at 0.
    pub fn nominal(layout: &CellLayout) -> Self {
        Self {
            axis_x_mm: layout.table_axis_x_mm,
            axis_y_mm: layout.table_axis_y_mm,
            top_z_mm: layout.table_top_z_mm,
            axis_tilt_x_deg: 0.0,
            axis_tilt_y_deg: 0.0,
            zero_deg: 0.0,
            top_tilt_x_deg: 0.0,
            top_tilt_y_deg: 0.0,
        }
    }

    /// `world_from_table` at encoder reading `deg`.
    pub fn world_from_table(&self, deg: f64) -> Isometry3<f64> {
        let turn = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), (deg - self.zero_deg).to_radians());
        let rot = rx(self.axis_tilt_x_deg)
            * ry(self.axis_tilt_y_deg)
            * turn
            * rx(self.top_tilt_x_deg)
            * ry(self.top_tilt_y_deg);
        Isometry3::from_parts(Translation3::new(self.axis_x_mm, self.axis_y_mm, self.top_z_mm), rot)
    }

    /// The parameters in the order of the fields.
    pub(crate) fn to_params(self) -> [f64; 8] {
        [
            self.axis_x_mm,
            self.axis_y_mm,
            self.top_z_mm,
            self.axis_tilt_x_deg,
            self.axis_tilt_y_deg,
            self.zero_deg,
            self.top_tilt_x_deg,
            self.top_tilt_y_deg,
        ]
    }

    /// From [`TableModel::to_params`]' order.
    pub(crate) fn from_params(p: &[f64; 8]) -> Self {
        Self {
            axis_x_mm: p[0],
            axis_y_mm: p[1],
            top_z_mm: p[2],
            axis_tilt_x_deg: p[3],
            axis_tilt_y_deg: p[4],
            zero_deg: p[5],
            top_tilt_x_deg: p[6],
            top_tilt_y_deg: p[7],
        }
    }
}

/// A small rigid transform: a translation (mm) and a rotation vector (degrees).
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Offset {
    #[serde(default)]
    pub translation_mm: [f64; 3],
    #[serde(default)]
    pub rotation_deg: [f64; 3],
}

impl Offset {
    /// The transform.
    pub fn iso(&self) -> Isometry3<f64> {
        let [x, y, z] = self.translation_mm;
        let w = Vector3::from(self.rotation_deg) * std::f64::consts::PI / 180.0;
        Isometry3::from_parts(Translation3::new(x, y, z), UnitQuaternion::from_scaled_axis(w))
    }

    /// The offset of a transform.
    pub fn from_iso(iso: &Isometry3<f64>) -> Self {
        let t = iso.translation.vector;
        let w = iso.rotation.scaled_axis() * 180.0 / std::f64::consts::PI;
        Self { translation_mm: [t.x, t.y, t.z], rotation_deg: [w.x, w.y, w.z] }
    }

    fn check(&self, field: &str, max_mm: f64, max_deg: f64) -> Result<(), CalibrationError> {
        for (k, v) in self.translation_mm.iter().enumerate() {
            if !v.is_finite() || v.abs() > max_mm {
                return Err(invalid(
                    &format!("{field}.translation_mm[{k}]"),
                    v,
                    &format!("within ±{max_mm} mm"),
                ));
            }
        }
        for (k, v) in self.rotation_deg.iter().enumerate() {
            if !v.is_finite() || v.abs() > max_deg {
                return Err(invalid(
                    &format!("{field}.rotation_deg[{k}]"),
                    v,
                    &format!("within ±{max_deg}°"),
                ));
            }
        }
        Ok(())
    }
}

/// How far the simulated cell is from its nominal description (its profile; module doc).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct CellErrors {
    /// The table axis's offset in X and Y and the top's in Z, mm.
    pub table_axis_offset_mm: [f64; 3],
    /// The axis's tilt from the vertical about X then Y, degrees.
    pub table_axis_tilt_deg: [f64; 2],
    /// The top's tilt against the axis (the wobble as the table turns), degrees.
    pub table_top_runout_deg: [f64; 2],
    /// The table encoder's reading at the table's reference direction, degrees.
    pub table_encoder_zero_deg: f64,
    /// Where the robot's base truly stands against where it is believed to.
    pub robot_base: Offset,
    /// The scanner's true mounting against the nominal bracket.
    pub scanner_mount: Offset,
    /// What each joint's encoder reads minus the true joint angle, degrees.
    pub joint_offsets_deg: [f64; 6],
}

impl Default for CellErrors {
    /// Realistic amounts for a cell assembled to its drawing without measurement: a table placed
    /// to about a millimetre, levelled to a few hundredths of a degree with a top turned to
    /// 0.05 mm over its 400 mm, a bracket bent by a tenth of a degree, joint encoders
    /// referenced to a few thousandths of a degree.
    fn default() -> Self {
        Self {
            table_axis_offset_mm: [1.2, -0.8, 0.35],
            table_axis_tilt_deg: [0.04, -0.03],
            table_top_runout_deg: [0.012, -0.008],
            table_encoder_zero_deg: 0.15,
            robot_base: Offset { translation_mm: [0.3, -0.2, 0.4], rotation_deg: [0.01, -0.015, 0.03] },
            scanner_mount: Offset { translation_mm: [0.25, -0.35, 0.5], rotation_deg: [0.12, -0.08, 0.1] },
            joint_offsets_deg: [0.001, -0.001, 0.0015, -0.001, 0.001, -0.0015],
        }
    }
}

impl CellErrors {
    /// A cell exactly as drawn.
    pub fn none() -> Self {
        Self {
            table_axis_offset_mm: [0.0; 3],
            table_axis_tilt_deg: [0.0; 2],
            table_top_runout_deg: [0.0; 2],
            table_encoder_zero_deg: 0.0,
            robot_base: Offset::default(),
            scanner_mount: Offset::default(),
            joint_offsets_deg: [0.0; 6],
        }
    }

    /// Checks every amount against what a cell that works at all could have; the error names the
    /// field.
    pub fn validate(&self) -> Result<(), CalibrationError> {
        let within = |field: &str, vals: &[f64], max: f64, unit: &str| -> Result<(), CalibrationError> {
            for (k, v) in vals.iter().enumerate() {
                if !v.is_finite() || v.abs() > max {
                    return Err(invalid(&format!("{field}[{k}]"), v, &format!("within ±{max} {unit}")));
                }
            }
            Ok(())
        };
        within("cell_errors.table_axis_offset_mm", &self.table_axis_offset_mm, 10.0, "mm")?;
        within("cell_errors.table_axis_tilt_deg", &self.table_axis_tilt_deg, 2.0, "°")?;
        within("cell_errors.table_top_runout_deg", &self.table_top_runout_deg, 2.0, "°")?;
        within("cell_errors.table_encoder_zero_deg", &[self.table_encoder_zero_deg], 5.0, "°")?;
        within("cell_errors.joint_offsets_deg", &self.joint_offsets_deg, 0.5, "°")?;
        self.robot_base.check("cell_errors.robot_base", 10.0, 2.0)?;
        self.scanner_mount.check("cell_errors.scanner_mount", 10.0, 2.0)
    }
}

/// The cell as it is: the physics runs on it.
#[derive(Debug, Clone, PartialEq)]
pub struct CellTruth {
    /// The table in the (believed) robot base frame.
    pub table: TableModel,
    /// The arm with its true base and true scanner mounting.
    pub arm: ArmModel,
    /// Encoder reading minus true joint angle, degrees.
    pub joint_offsets_deg: [f64; 6],
}

impl CellTruth {
    /// The nominal cell of `layout` moved by `errors`.
    pub fn new(layout: &CellLayout, errors: &CellErrors) -> Self {
        let n = TableModel::nominal(layout);
        let [dx, dy, dz] = errors.table_axis_offset_mm;
        let table = TableModel {
            axis_x_mm: n.axis_x_mm + dx,
            axis_y_mm: n.axis_y_mm + dy,
            top_z_mm: n.top_z_mm + dz,
            axis_tilt_x_deg: errors.table_axis_tilt_deg[0],
            axis_tilt_y_deg: errors.table_axis_tilt_deg[1],
            zero_deg: errors.table_encoder_zero_deg,
            top_tilt_x_deg: errors.table_top_runout_deg[0],
            top_tilt_y_deg: errors.table_top_runout_deg[1],
        };
        let nominal = ArmModel::viper_s650();
        let arm = nominal
            .clone()
            .with_base(nominal.base * errors.robot_base.iso())
            .with_tool(nominal.tool * errors.scanner_mount.iso());
        Self { table, arm, joint_offsets_deg: errors.joint_offsets_deg }
    }

    /// Where the scanner truly is when the joint encoders read `q_read_deg`.
    pub fn world_from_sensor(&self, q_read_deg: &[f64; 6]) -> Isometry3<f64> {
        let mut q = *q_read_deg;
        for (qi, off) in q.iter_mut().zip(self.joint_offsets_deg) {
            *qi -= off;
        }
        self.arm.fk(&q)
    }
}

/// What the software believes about the cell after calibrating it.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Calibration {
    /// The table in the robot's frame.
    pub table: TableModel,
    /// The scanner's mounting against the nominal bracket
    /// (`flange_from_scanner = bracket · mount`).
    pub scanner_mount: Offset,
}

impl Calibration {
    /// The drawing.
    pub fn nominal(layout: &CellLayout) -> Self {
        Self { table: TableModel::nominal(layout), scanner_mount: Offset::default() }
    }

    /// `flange_from_scanner` believed.
    pub fn flange_from_scanner(&self) -> Isometry3<f64> {
        ArmModel::scanner_bracket() * self.scanner_mount.iso()
    }

    /// Checks a calibration handed in from outside (a stored one): finite, and within what the
    /// cell could be off its drawing (10 mm, 2°).
    pub fn validate(&self, layout: &CellLayout) -> Result<(), CalibrationError> {
        let n = TableModel::nominal(layout).to_params();
        let names = [
            "table.axis_x_mm",
            "table.axis_y_mm",
            "table.top_z_mm",
            "table.axis_tilt_x_deg",
            "table.axis_tilt_y_deg",
            "table.zero_deg",
            "table.top_tilt_x_deg",
            "table.top_tilt_y_deg",
        ];
        for (k, (v, n)) in self.table.to_params().iter().zip(n).enumerate() {
            let max = if k == 5 {
                5.0
            } else if k < 3 {
                10.0
            } else {
                2.0
            };
            if !v.is_finite() || (v - n).abs() > max {
                return Err(invalid(
                    &format!("calibration.{}", names[k]),
                    v,
                    &format!("within {max} of the nominal {n}"),
                ));
            }
        }
        self.scanner_mount.check("calibration.scanner_mount", 10.0, 2.0)
    }
}

/// The simulated cell a scan runs on: its truth, and the calibration in force (none: the
/// software believes the drawing).
#[derive(Debug, Clone, PartialEq)]
pub struct Cell {
    pub truth: CellTruth,
    pub calibration: Option<Calibration>,
}

impl Cell {
    /// A cell exactly as drawn, uncalibrated (belief = truth).
    pub fn exact(layout: &CellLayout) -> Self {
        Self { truth: CellTruth::new(layout, &CellErrors::none()), calibration: None }
    }

    /// A cell off its drawing by `errors`, with `calibration` in force.
    pub fn new(layout: &CellLayout, errors: &CellErrors, calibration: Option<Calibration>) -> Self {
        Self { truth: CellTruth::new(layout, errors), calibration }
    }

    /// What the software believes.
    pub fn belief(&self, layout: &CellLayout) -> Calibration {
        self.calibration.unwrap_or_else(|| Calibration::nominal(layout))
    }
}
