//! The scan options: the job's `scan` object (DESIGN §7), extended, with defaults and checks that
//! name the field.

use serde::{Deserialize, Serialize};

use super::ScanError;
use crate::domain::scanner::{MAX_LINE_RATE_HZ, MIN_LINE_RATE_HZ, ScannerSpec};

/// How frames are taken.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ScanMode {
    /// Robot moving continuously along each pass; a sync pulse per frame latches the robot's and
    /// the table's positions (50–150 frames/s).
    #[default]
    Dynamic,
    /// Move, stop, read the position, take one frame (2–3 frames/s, no sync).
    StopAndMove,
}

/// One given pass: the sensor's straight path in the part frame at one table angle.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PassSpec {
    /// Table angle of the pass, degrees.
    pub table_deg: f64,
    /// Where the sensor's origin starts, part frame, mm.
    pub start_mm: [f64; 3],
    /// Where it ends, part frame, mm.
    pub end_mm: [f64; 3],
}

/// The job's `scan` object. Every field is optional; see [`ScanOptions::default`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ScanOptions {
    /// `dynamic` (default) or `stop_and_move`.
    pub mode: ScanMode,
    /// Table angles of the automatic plan, degrees (default 0, 90, 180, 270).
    pub table_angles_deg: Vec<f64>,
    /// Distance from the sensor to the part's top along the optical axis, mm (default 150; the
    /// window is 65–245).
    pub standoff_mm: f64,
    /// Line (frame) rate in dynamic mode, Hz (50–150, default 100).
    pub line_rate_hz: f64,
    /// Rescan the holes the first scan leaves, from other table angles and farther away.
    pub adaptive_rescan: bool,
    /// Distance between successive lines along a pass, mm (default 0.25): the pass speed in
    /// dynamic mode is `line_rate_hz · line_spacing_mm`; in stop-and-move mode the stop spacing.
    pub line_spacing_mm: f64,
    /// Fraction of the line length by which neighbouring passes overlap (0–0.9, default 0.3).
    pub overlap: f64,
    /// Run-in and run-out beyond the part's extent at both ends of a pass, mm (default 8).
    pub margin_mm: f64,
    /// Tilt of the optical axis about the pass direction, degrees (−40..40, default 0: looking
    /// straight down).
    pub tilt_deg: f64,
    /// Frames per second in stop-and-move mode (0.5–3, default 2.5).
    pub stop_and_move_rate_hz: f64,
    /// Latency of the encoder latch, s (default 50 µs).
    pub latch_latency_s: f64,
    /// Jitter (σ) of the latch, s (default 5 µs).
    pub latch_jitter_s: f64,
    /// Correct each latched pose for the device's nominal latency by interpolating between the
    /// neighbouring latches (default true).
    pub compensate_latency: bool,
    /// Pixel of the coverage map that aims the adaptive rescan, mm (default 0.5).
    pub rescan_pixel_mm: f64,
    /// Smallest hole worth a rescan, mm² (default 1).
    pub rescan_min_hole_mm2: f64,
    /// Most holes rescanned (default 24, the largest first).
    pub rescan_max_holes: usize,
    /// Standoff of the rescan passes, mm (default: 220, or less if the part is tall): farther away
    /// the camera's triangulation angle is smaller and it sees deeper into holes.
    pub rescan_standoff_mm: Option<f64>,
    /// Given passes instead of the automatic plan.
    pub passes: Option<Vec<PassSpec>>,
    /// Obstacles besides the table and the part (world frame: the robot's base).
    pub obstacles: Vec<super::obstacles::Obstacle>,
    /// Smallest distance the arm and the scanner keep from every obstacle, mm (default 10).
    pub obstacle_clearance_mm: f64,
    /// The table as the seventh joint: on the automatic plan each station's angle may turn up to
    /// this far from the one asked for when that reaches more passes or gives the arm a better
    /// posture (dexterity, singularity and joint-limit distances), degrees; 0 keeps the angles
    /// as asked (default 30).
    pub table_search_deg: f64,
    /// Seed of the scanner's and the latch's noise.
    pub seed: u64,
    /// Upper bound on frames, a guard against options that would scan for hours (default 400 000).
    pub max_frames: u64,
}

impl Default for ScanOptions {
    fn default() -> Self {
        Self {
            mode: ScanMode::Dynamic,
            table_angles_deg: vec![0.0, 90.0, 180.0, 270.0],
            standoff_mm: 150.0,
            line_rate_hz: 100.0,
            adaptive_rescan: false,
            line_spacing_mm: 0.25,
            overlap: 0.3,
            margin_mm: 8.0,
            tilt_deg: 0.0,
            stop_and_move_rate_hz: 2.5,
            latch_latency_s: 50e-6,
            latch_jitter_s: 5e-6,
            compensate_latency: true,
            rescan_pixel_mm: 0.5,
            rescan_min_hole_mm2: 1.0,
            rescan_max_holes: 24,
            rescan_standoff_mm: None,
            passes: None,
            obstacles: Vec::new(),
            obstacle_clearance_mm: 10.0,
            table_search_deg: 30.0,
            seed: 1,
            max_frames: 400_000,
        }
    }
}

impl ScanOptions {
    /// Time the sensor takes over a pass of `length_mm`, s: at `line_rate_hz · line_spacing_mm`
    /// in dynamic mode, one frame per stop at `stop_and_move_rate_hz` in stop-and-move mode.
    pub fn pass_time_s(&self, length_mm: f64) -> f64 {
        let lines = (length_mm / self.line_spacing_mm).ceil().max(1.0) + 1.0;
        match self.mode {
            ScanMode::Dynamic => lines / self.line_rate_hz,
            ScanMode::StopAndMove => lines / self.stop_and_move_rate_hz,
        }
    }
}

fn bad(field: &str, value: impl ToString, reason: impl Into<String>) -> ScanError {
    ScanError::InvalidOption {
        field: format!("scan.{field}"),
        value: value.to_string(),
        reason: reason.into(),
    }
}

fn finite_in(field: &str, v: f64, lo: f64, hi: f64) -> Result<(), ScanError> {
    if v.is_finite() && v >= lo && v <= hi {
        Ok(())
    } else {
        Err(bad(field, v, format!("must be within [{lo}, {hi}]")))
    }
}

impl ScanOptions {
    /// Checks every field against `spec`; the error names the first bad one (`scan.<field>`).
    pub fn validate(&self, spec: &ScannerSpec) -> Result<(), ScanError> {
        if self.passes.is_none() {
            if self.table_angles_deg.is_empty() {
                return Err(bad("table_angles_deg", "[]", "needs at least one angle"));
            }
            if self.table_angles_deg.len() > 36 {
                return Err(bad("table_angles_deg", self.table_angles_deg.len(), "at most 36 angles"));
            }
            for (i, a) in self.table_angles_deg.iter().enumerate() {
                finite_in(&format!("table_angles_deg[{i}]"), *a, -360.0, 360.0)?;
            }
        }
        finite_in("standoff_mm", self.standoff_mm, spec.standoff_min_mm, spec.standoff_max_mm)?;
        finite_in("line_rate_hz", self.line_rate_hz, MIN_LINE_RATE_HZ, MAX_LINE_RATE_HZ)?;
        finite_in("line_spacing_mm", self.line_spacing_mm, 0.01, 10.0)?;
        finite_in("overlap", self.overlap, 0.0, 0.9)?;
        finite_in("margin_mm", self.margin_mm, 0.0, 100.0)?;
        finite_in("tilt_deg", self.tilt_deg, -40.0, 40.0)?;
        finite_in("stop_and_move_rate_hz", self.stop_and_move_rate_hz, 0.5, 3.0)?;
        finite_in("latch_latency_s", self.latch_latency_s, 0.0, 0.05)?;
        finite_in("latch_jitter_s", self.latch_jitter_s, 0.0, 0.01)?;
        finite_in("rescan_pixel_mm", self.rescan_pixel_mm, 0.05, 10.0)?;
        finite_in("rescan_min_hole_mm2", self.rescan_min_hole_mm2, 0.0, 1e6)?;
        if self.rescan_max_holes > 1000 {
            return Err(bad("rescan_max_holes", self.rescan_max_holes, "at most 1000"));
        }
        if let Some(s) = self.rescan_standoff_mm {
            finite_in("rescan_standoff_mm", s, spec.standoff_min_mm, spec.standoff_max_mm)?;
        }
        finite_in("obstacle_clearance_mm", self.obstacle_clearance_mm, 0.0, 500.0)?;
        finite_in("table_search_deg", self.table_search_deg, 0.0, 90.0)?;
        if self.obstacles.len() > 16 {
            return Err(bad("obstacles", self.obstacles.len(), "at most 16 obstacles"));
        }
        for (i, o) in self.obstacles.iter().enumerate() {
            o.validate(&format!("scan.obstacles[{i}]"))?;
        }
        if self.max_frames == 0 || self.max_frames > 10_000_000 {
            return Err(bad("max_frames", self.max_frames, "must be within [1, 10000000]"));
        }
        if let Some(passes) = &self.passes {
            if passes.is_empty() {
                return Err(bad("passes", "[]", "give at least one pass or leave passes out"));
            }
            for (i, p) in passes.iter().enumerate() {
                finite_in(&format!("passes[{i}].table_deg"), p.table_deg, -360.0, 360.0)?;
                for (name, v) in [("start_mm", p.start_mm), ("end_mm", p.end_mm)] {
                    if v.iter().any(|c| !c.is_finite()) {
                        return Err(bad(&format!("passes[{i}].{name}"), format!("{v:?}"), "must be finite"));
                    }
                }
                let len = (0..3).map(|k| (p.end_mm[k] - p.start_mm[k]).powi(2)).sum::<f64>().sqrt();
                if !(1.0..=2000.0).contains(&len) {
                    return Err(bad(
                        &format!("passes[{i}]"),
                        format!("{len:.3} mm long"),
                        "a pass is 1 to 2000 mm long",
                    ));
                }
            }
        }
        Ok(())
    }

    /// Parses the job's `scan` JSON object; the error names the field (`scan.<path>`).
    pub fn from_json(text: &str) -> Result<Self, ScanError> {
        let de = &mut serde_json::Deserializer::from_str(text);
        serde_path_to_error::deserialize(de).map_err(|e| {
            let path = e.path().to_string();
            let field = if path == "." { "scan".to_string() } else { format!("scan.{path}") };
            ScanError::InvalidOption { field, value: String::new(), reason: e.into_inner().to_string() }
        })
    }
}
