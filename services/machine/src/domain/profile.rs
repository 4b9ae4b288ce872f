//! [`MachineProfile`]: what a machine can do, read from a TOML file per machine
//! (`services/machine/machines/<name>.toml`; the EMCO F1 class ships built in).
//!
//! Machine coordinates: X and Y from the home corner, Z = 0 at the top of travel (where
//! `G53 G0 Z0` and `G28` go), negative downwards; A and C in degrees. A turns the part about X
//! through the work origin; a table-table machine's C table (`[axes.c]`) sits on the A trunnion
//! and turns the part about the table's Z axis, also through the work origin: a point `p` of the
//! part is at `R_x(A)·R_z(C)·p` in the work frame. Every commanded position is
//! quantised to `step_mm` (the stepper resolution). Feeds in mm/min, accelerations in mm/s²,
//! spindle in rpm.

use std::path::Path;

use serde::{Deserialize, Serialize};

/// The EMCO F1 profile, as shipped.
pub const EMCO_F1_TOML: &str = include_str!("../../machines/emco-f1.toml");
/// The 5-axis table-table profile (the EMCO F1 class with a tilting A trunnion and a C table).
pub const EMCO_F1_TT_TOML: &str = include_str!("../../machines/emco-f1-tt.toml");

/// A bad profile: the file, the field and why.
#[derive(Debug, thiserror::Error)]
pub enum ProfileError {
    #[error("{file}: {message}")]
    Parse { file: String, message: String },
    #[error("{file}: {field} = {value}: {reason}")]
    Invalid { file: String, field: String, value: String, reason: String },
    #[error("unknown machine '{name}': expected one of {known}")]
    Unknown { name: String, known: String },
    #[error("{file}: {source}")]
    Io {
        file: String,
        #[source]
        source: std::io::Error,
    },
}

/// Room kept around a part in X and Y, each side, when checking that it fits the travel, mm: the
/// 6 mm of surroundings the scan's free space adds to the stock, plus a roughing tool's radius.
pub const PART_MARGIN_MM: f64 = 10.0;
/// Z travel kept above a part for the tool and its holder when checking that it fits, mm.
pub const TOOL_ALLOWANCE_MM: f64 = 50.0;

/// Travel of one axis (`min_mm <= max_mm`; for A, degrees, and `min = max = 0` means continuous).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AxisRange {
    pub min_mm: f64,
    pub max_mm: f64,
}

impl AxisRange {
    /// True when `v` lies within the travel (with `tol` slack for rounding).
    pub fn contains(&self, v: f64, tol: f64) -> bool {
        v >= self.min_mm - tol && v <= self.max_mm + tol
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Axes {
    pub x: AxisRange,
    pub y: AxisRange,
    pub z: AxisRange,
    pub a: AxisRange,
    /// The C table of a table-table machine (degrees; `min = max = 0`: continuous); absent on a
    /// 4-axis machine, which refuses C words.
    #[serde(default)]
    pub c: Option<AxisRange>,
}

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Motion {
    pub feed_min_mm_min: f64,
    pub feed_max_mm_min: f64,
    pub rapid_mm_min: f64,
    pub accel_mm_s2: f64,
    pub a_rate_deg_min: f64,
    /// The C table's rate (a machine with a C axis).
    #[serde(default)]
    pub c_rate_deg_min: Option<f64>,
}

/// The spindle and its DC motor: torque at the spindle `T = kt·(I − i0)`, back-EMF `ke = kt`
/// (SI units), armature `U = R·I + kt·ω`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Spindle {
    pub rpm_min: f64,
    pub rpm_max: f64,
    pub power_w: f64,
    pub torque_constant_nm_per_a: f64,
    pub no_load_current_a: f64,
    pub armature_resistance_ohm: f64,
    pub supply_voltage_v: f64,
    pub accel_rpm_s: f64,
}

impl Spindle {
    /// Motor current drawn for a cutting torque `torque_nm` at the spindle.
    pub fn current_for_torque(&self, torque_nm: f64) -> f64 {
        self.no_load_current_a + torque_nm.max(0.0) / self.torque_constant_nm_per_a
    }

    /// Largest cutting torque at `rpm` within the motor's power rating.
    pub fn max_torque_nm(&self, rpm: f64) -> f64 {
        let omega = rpm.max(1.0) * std::f64::consts::TAU / 60.0;
        self.power_w / omega
    }

    /// Electrical power drawn at `rpm` with current `current_a`: `U·I` with `U = R·I + kt·ω`.
    pub fn electrical_power_w(&self, rpm: f64, current_a: f64) -> f64 {
        let omega = rpm * std::f64::consts::TAU / 60.0;
        (self.armature_resistance_ohm * current_a + self.torque_constant_nm_per_a * omega) * current_a
    }
}

/// Sensor resolutions and noise (noise as a standard deviation in counts).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Sensors {
    pub torque_nm_per_count: f64,
    pub torque_noise_counts: f64,
    pub torque_max_nm: f64,
    pub current_a_per_count: f64,
    pub current_noise_counts: f64,
    pub current_max_a: f64,
    pub encoder_pulses_per_rev: u32,
}

/// A point in machine coordinates.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Offset {
    pub x_mm: f64,
    pub y_mm: f64,
    pub z_mm: f64,
}

/// A tool table entry.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ToolEntry {
    pub number: u32,
    /// A tool of the CAM library or a spec (`ball-6`, `flat-3`, `bull-6-1`, `v-6-90`).
    pub name: String,
    /// Gauge length (spindle nose to tip), what `G43 H<number>` applies.
    pub length_mm: f64,
}

/// A machine: travel, motion limits, spindle, sensors, default work offset and tool table.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MachineProfile {
    pub name: String,
    #[serde(default)]
    pub description: String,
    pub step_mm: f64,
    pub axes: Axes,
    pub motion: Motion,
    pub spindle: Spindle,
    pub sensors: Sensors,
    pub work_offset: Offset,
    #[serde(default)]
    pub tools: Vec<ToolEntry>,
}

/// Names of the profiles shipped with the service ([`MachineProfile::builtin`]).
pub const BUILTIN_PROFILES: [&str; 2] = ["emco-f1", "emco-f1-tt"];

impl MachineProfile {
    /// The profiles shipped with the service, by name.
    pub fn builtin(name: &str) -> Result<Self, ProfileError> {
        match name.trim().to_ascii_lowercase().as_str() {
            "emco-f1" | "emco_f1" => Self::parse(EMCO_F1_TOML, "emco-f1.toml"),
            "emco-f1-tt" | "emco_f1_tt" => Self::parse(EMCO_F1_TT_TOML, "emco-f1-tt.toml"),
            _ => Err(ProfileError::Unknown { name: name.to_string(), known: "emco-f1, emco-f1-tt".into() }),
        }
    }

    /// Checks that a part of `size_mm` (x, y, z) can be machined here as it lies: with
    /// [`PART_MARGIN_MM`] of stock on every side in X and Y within the X and Y travel, and its
    /// height plus [`TOOL_ALLOWANCE_MM`] (tool and holder above the part) within the Z travel.
    /// The error says the part's and the machine's sizes and, when turning the part 90° about Z
    /// would make it fit, says so.
    pub fn check_part_fits(&self, size_mm: [f64; 3]) -> Result<(), String> {
        let travel = [
            self.axes.x.max_mm - self.axes.x.min_mm,
            self.axes.y.max_mm - self.axes.y.min_mm,
            self.axes.z.max_mm - self.axes.z.min_mm,
        ];
        let need = [
            size_mm[0] + 2.0 * PART_MARGIN_MM,
            size_mm[1] + 2.0 * PART_MARGIN_MM,
            size_mm[2] + TOOL_ALLOWANCE_MM,
        ];
        let over: Vec<&str> = ["X", "Y", "Z"]
            .into_iter()
            .zip(need.iter().zip(&travel))
            .filter(|(_, (n, t))| n > t)
            .map(|(a, _)| a)
            .collect();
        if over.is_empty() {
            return Ok(());
        }
        let turned = need[1] <= travel[0] && need[0] <= travel[1] && need[2] <= travel[2];
        Err(format!(
            "the part is {:.1} x {:.1} x {:.1} mm; with {PART_MARGIN_MM} mm of stock around it and {TOOL_ALLOWANCE_MM} mm above it for the tool it needs {:.1} x {:.1} x {:.1} mm of travel, and the {}'s is {:.1} x {:.1} x {:.1} mm (too large in {}){}",
            size_mm[0],
            size_mm[1],
            size_mm[2],
            need[0],
            need[1],
            need[2],
            self.name,
            travel[0],
            travel[1],
            travel[2],
            over.join(", "),
            if turned { "; turned 90° about Z it would fit: rotate the model" } else { "" }
        ))
    }

    /// A shipped profile by name, or a profile file when `name` ends in `.toml`.
    pub fn by_name_or_file(name: &str) -> Result<Self, ProfileError> {
        if name.ends_with(".toml") { Self::read(Path::new(name)) } else { Self::builtin(name) }
    }

    /// Reads and checks a profile file.
    pub fn read(path: &Path) -> Result<Self, ProfileError> {
        let file = path.display().to_string();
        let text = std::fs::read_to_string(path)
            .map_err(|source| ProfileError::Io { file: file.clone(), source })?;
        Self::parse(&text, &file)
    }

    /// Parses and checks profile text; `file` names it in errors.
    pub fn parse(text: &str, file: &str) -> Result<Self, ProfileError> {
        let profile: MachineProfile = toml::from_str(text)
            .map_err(|e| ProfileError::Parse { file: file.to_string(), message: e.to_string() })?;
        profile.validate(file)?;
        Ok(profile)
    }

    /// Checks every figure: finite, positive where it must be, ranges ordered, tools unique.
    pub fn validate(&self, file: &str) -> Result<(), ProfileError> {
        let bad = |field: &str, value: &dyn std::fmt::Display, reason: &str| ProfileError::Invalid {
            file: file.to_string(),
            field: field.to_string(),
            value: value.to_string(),
            reason: reason.to_string(),
        };
        let positive = [
            ("step_mm", self.step_mm),
            ("motion.feed_min_mm_min", self.motion.feed_min_mm_min),
            ("motion.feed_max_mm_min", self.motion.feed_max_mm_min),
            ("motion.rapid_mm_min", self.motion.rapid_mm_min),
            ("motion.accel_mm_s2", self.motion.accel_mm_s2),
            ("motion.a_rate_deg_min", self.motion.a_rate_deg_min),
            ("spindle.rpm_min", self.spindle.rpm_min),
            ("spindle.rpm_max", self.spindle.rpm_max),
            ("spindle.power_w", self.spindle.power_w),
            ("spindle.torque_constant_nm_per_a", self.spindle.torque_constant_nm_per_a),
            ("spindle.armature_resistance_ohm", self.spindle.armature_resistance_ohm),
            ("spindle.supply_voltage_v", self.spindle.supply_voltage_v),
            ("spindle.accel_rpm_s", self.spindle.accel_rpm_s),
            ("sensors.torque_nm_per_count", self.sensors.torque_nm_per_count),
            ("sensors.torque_max_nm", self.sensors.torque_max_nm),
            ("sensors.current_a_per_count", self.sensors.current_a_per_count),
            ("sensors.current_max_a", self.sensors.current_max_a),
        ];
        for (field, v) in positive {
            if !(v.is_finite() && v > 0.0) {
                return Err(bad(field, &v, "must be finite and positive"));
            }
        }
        for (field, v) in [
            ("spindle.no_load_current_a", self.spindle.no_load_current_a),
            ("sensors.torque_noise_counts", self.sensors.torque_noise_counts),
            ("sensors.current_noise_counts", self.sensors.current_noise_counts),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(bad(field, &v, "must be finite and not negative"));
            }
        }
        if self.sensors.encoder_pulses_per_rev == 0 {
            return Err(bad("sensors.encoder_pulses_per_rev", &0, "must be at least 1"));
        }
        if let Some(rate) = self.motion.c_rate_deg_min
            && !(rate.is_finite() && rate > 0.0)
        {
            return Err(bad("motion.c_rate_deg_min", &rate, "must be finite and positive"));
        }
        let c = self.axes.c.map(|c| ("c", c));
        for (axis, r) in [("x", self.axes.x), ("y", self.axes.y), ("z", self.axes.z), ("a", self.axes.a)]
            .into_iter()
            .chain(c)
        {
            if !(r.min_mm.is_finite() && r.max_mm.is_finite()) || r.min_mm > r.max_mm {
                return Err(bad(
                    &format!("axes.{axis}"),
                    &format!("[{}, {}]", r.min_mm, r.max_mm),
                    "needs finite min <= max",
                ));
            }
        }
        if self.motion.feed_min_mm_min > self.motion.feed_max_mm_min {
            return Err(bad(
                "motion.feed_min_mm_min",
                &self.motion.feed_min_mm_min,
                "is above feed_max_mm_min",
            ));
        }
        if self.spindle.rpm_min > self.spindle.rpm_max {
            return Err(bad("spindle.rpm_min", &self.spindle.rpm_min, "is above rpm_max"));
        }
        let w = self.work_offset;
        if ![w.x_mm, w.y_mm, w.z_mm].iter().all(|v| v.is_finite()) {
            return Err(bad("work_offset", &format!("{w:?}"), "must be finite"));
        }
        let mut seen = std::collections::BTreeSet::new();
        for (i, t) in self.tools.iter().enumerate() {
            if !seen.insert(t.number) {
                return Err(bad(&format!("tools[{i}].number"), &t.number, "appears twice"));
            }
            if !(t.length_mm.is_finite() && t.length_mm > 0.0) {
                return Err(bad(
                    &format!("tools[{i}].length_mm"),
                    &t.length_mm,
                    "must be finite and positive",
                ));
            }
            if t.name.trim().is_empty() {
                return Err(bad(&format!("tools[{i}].name"), &"''", "must name a tool"));
            }
        }
        Ok(())
    }

    /// A position quantised to whole steps.
    pub fn quantise(&self, v_mm: f64) -> f64 {
        (v_mm / self.step_mm).round() * self.step_mm
    }

    /// The tool table entry for `number`.
    pub fn tool(&self, number: u32) -> Option<&ToolEntry> {
        self.tools.iter().find(|t| t.number == number)
    }

    /// True when the A axis is continuous (no travel limits).
    pub fn a_is_continuous(&self) -> bool {
        self.axes.a.min_mm == 0.0 && self.axes.a.max_mm == 0.0
    }

    /// The C axis's travel, `None` when continuous or absent (see [`Self::has_c`]).
    pub fn c_limits(&self) -> Option<AxisRange> {
        self.axes.c.filter(|c| !(c.min_mm == 0.0 && c.max_mm == 0.0))
    }

    /// True on a table-table machine (a C table).
    pub fn has_c(&self) -> bool {
        self.axes.c.is_some()
    }

    /// The C table's rate, °/min (the A axis's when not given).
    pub fn c_rate_deg_min(&self) -> f64 {
        self.motion.c_rate_deg_min.unwrap_or(self.motion.a_rate_deg_min)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_shipped_emco_profile_is_valid_and_matches_the_class_figures() {
        let p = MachineProfile::builtin("emco-f1").expect("builtin");
        assert_eq!(p.step_mm, 0.01);
        assert_eq!((p.motion.feed_min_mm_min, p.motion.feed_max_mm_min), (5.0, 400.0));
        assert_eq!((p.spindle.rpm_min, p.spindle.rpm_max), (300.0, 2000.0));
        assert_eq!(p.spindle.power_w, 440.0);
        assert_eq!(p.sensors.encoder_pulses_per_rev, 100);
        assert!((p.sensors.current_a_per_count - 0.00625).abs() < 1e-12);
        // The scale check of DESIGN §5: at most about 2.1 N·m at 2000 rpm.
        assert!((p.spindle.max_torque_nm(2000.0) - 2.1).abs() < 0.01);
        // Full torque stays inside the ±5 A current sensor.
        assert!(p.spindle.current_for_torque(p.spindle.max_torque_nm(2000.0)) < p.sensors.current_max_a);
        assert_eq!(p.quantise(1.23456), 1.23);
        assert!(p.a_is_continuous());
        assert_eq!(p.tool(2).map(|t| t.name.as_str()), Some("ball-3"));
        assert!(MachineProfile::builtin("haas").is_err());
    }

    #[test]
    fn a_part_must_fit_the_travel_with_its_margins() {
        let p = MachineProfile::builtin("emco-f1").expect("builtin");
        // 200 x 100 x 200 travel: 180 x 80 x 150 is the largest part.
        assert!(p.check_part_fits([80.0, 60.0, 12.0]).is_ok());
        assert!(p.check_part_fits([180.0, 80.0, 150.0]).is_ok());
        assert!(p.check_part_fits([180.1, 80.0, 150.0]).is_err());
        let e = p.check_part_fits([250.0, 80.0, 30.0]).expect_err("too long");
        assert!(e.contains("250.0 x 80.0 x 30.0 mm") && e.contains("200.0 x 100.0 x 200.0 mm"), "{e}");
        assert!(e.contains("too large in X") && !e.contains("turned"), "{e}");
        let e = p.check_part_fits([60.0, 150.0, 30.0]).expect_err("too wide");
        assert!(e.contains("too large in Y") && e.contains("turned 90°"), "{e}");
        let e = p.check_part_fits([60.0, 60.0, 151.0]).expect_err("too tall");
        assert!(e.contains("too large in Z"), "{e}");
    }

    #[test]
    fn bad_profiles_name_the_field() {
        let bad = EMCO_F1_TOML.replace("feed_max_mm_min = 400.0", "feed_max_mm_min = -4.0");
        let e = MachineProfile::parse(&bad, "m.toml").expect_err("negative");
        assert!(e.to_string().contains("m.toml: motion.feed_max_mm_min = -4"), "{e}");
        let bad = EMCO_F1_TOML.replace("rapid_mm_min", "rapid_mm_mn");
        let e = MachineProfile::parse(&bad, "m.toml").expect_err("unknown field");
        assert!(e.to_string().contains("rapid_mm_mn"), "{e}");
        let bad = EMCO_F1_TOML.replace("number = 2", "number = 1");
        let e = MachineProfile::parse(&bad, "m.toml").expect_err("duplicate");
        assert!(e.to_string().contains("tools[1].number = 1: appears twice"), "{e}");
    }
}
