//! Streaming reads of the artifacts that grow with the job (the scanned cloud, the program), so
//! that rendering a report takes memory flat in their size: the caller (the orchestrator, from
//! its artifact store) streams them through these readers instead of handing the report their
//! bytes, and the report draws from the bounded results.
//!
//! - A cloud keeps a uniform sample of at most [`CLOUD_SAMPLE`] points
//!   ([`depthmill_geometry::formats::sample_cloud_from`]) and the number of points it holds.
//! - A program is parsed line by line ([`crate::gcode::parse_reader`]), keeping at most
//!   [`crate::gcode::MAX_SEGS`] drawing pieces.
//! - The telemetry CSV is read line by line: statistics of every row, at most
//!   [`crate::charts::TELEMETRY_SAMPLE`] rows kept for the chart.

use std::collections::BTreeMap;
use std::io::BufRead;

use depthmill_geometry::PointCloud;
use depthmill_geometry::formats::{ReadLimits, sample_cloud_from};

use crate::gcode::Program;

/// Points a cloud picture is drawn from at most (a 4000-pixel view has 16 M pixels, but the
/// pictures are at most about 1600 pixels across: a million points cover them).
pub const CLOUD_SAMPLE: usize = 1 << 20;

/// A cloud read for its pictures.
#[derive(Debug, Clone)]
pub struct SampledCloud {
    /// At most [`CLOUD_SAMPLE`] points, a uniform sample.
    pub cloud: PointCloud,
    /// Points the artifact holds.
    pub points: u64,
}

/// Artifacts read by streaming, by kind (the keys of `job.artifacts`).
#[derive(Debug, Default)]
pub struct Digests {
    pub clouds: BTreeMap<String, SampledCloud>,
    pub programs: BTreeMap<String, Program>,
    /// The `telemetry` CSV: its statistics over every row and a sample of the rows.
    pub telemetry: Option<crate::charts::Telemetry>,
}

impl Digests {
    /// No streamed artifacts: everything comes as bytes.
    pub const NONE: Digests = Digests { clouds: BTreeMap::new(), programs: BTreeMap::new(), telemetry: None };
}

/// How the report reads an artifact kind.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Reading {
    /// By streaming, as a cloud ([`cloud`]).
    Cloud,
    /// By streaming, as a program ([`program`]).
    Program,
    /// By streaming, as telemetry ([`telemetry`]).
    Telemetry,
    /// Its bytes, whole.
    Bytes,
    /// Not at all.
    Unused,
}

/// How the report reads the artifact `kind`.
pub fn reading(kind: &str) -> Reading {
    match kind {
        "point_cloud" => Reading::Cloud,
        // The mesh is compared with the machined part whole; its vertices are drawn only when
        // there is no scanned cloud.
        "mesh" => Reading::Bytes,
        "gcode" => Reading::Program,
        "telemetry" => Reading::Telemetry,
        // Outputs of the report itself.
        "report" | "report_json" => Reading::Unused,
        _ => Reading::Bytes,
    }
}

/// Reads a cloud (XYZ, PLY; an STL's vertices) for its pictures. `size` is the artifact's size.
pub fn cloud<R: BufRead>(r: R, name: &str, size: Option<u64>) -> Result<SampledCloud, String> {
    let (cloud, stats) =
        sample_cloud_from(r, name, size, &ReadLimits::default(), CLOUD_SAMPLE).map_err(|e| e.to_string())?;
    Ok(SampledCloud { cloud, points: stats.points })
}

/// Reads the telemetry CSV: statistics of every row, a sample of at most
/// [`crate::charts::TELEMETRY_SAMPLE`] rows for the chart.
pub fn telemetry<R: BufRead>(r: R) -> Result<crate::charts::Telemetry, String> {
    crate::charts::read_telemetry(r, crate::charts::TELEMETRY_SAMPLE)
}

/// Reads a program for drawing.
pub fn program<R: BufRead>(r: R) -> std::io::Result<Program> {
    crate::gcode::parse_reader(r)
}
