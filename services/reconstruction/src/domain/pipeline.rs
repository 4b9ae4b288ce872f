//! The reconstruct stage: a point cloud (or a mesh) and options -> one depth map, coverage map,
//! roughing map and statistics per face.
//!
//! Order, for a cloud: rigid user transform -> intensity window -> voxel decimation -> statistical
//! outlier removal -> radius outlier removal -> per face: rotate into the face frame, region of
//! interest (given, or the points' extent plus a margin), rasterisation (each cell the max Z of
//! its points, or their median with `estimator: "median"`), hole filling (enclosed holes only),
//! coverage, robust Z range (after the filters, quantiles: one stray point does not set `z_max`),
//! roughing map (always from the max, so it never cuts into the part whatever the estimator). A
//! mesh skips the filters and is z-buffered per face.
//!
//! Options mirror the `reconstruct` object of a job request (DESIGN.md §7), extended with `roi`,
//! `margin_mm`, `z_min_mm`/`z_max_mm`, `filters`, `roughing_factor` and `estimator`. Defaults: pixel 0.1 mm,
//! one face `+Z`, IDW fill (power 2) of holes up to 2 mm, margin 2 pixels, statistical outlier
//! removal with k = 12 and n·σ = 3, keeping the flagged points on a sparsely sampled surface
//! (when `filters` is absent; a given `filters` object runs exactly the filters it names), roughing lattice of 4 pixels, estimator `max`.

use std::time::Instant;

use depthmill_geometry::cloud::single;
use depthmill_geometry::{CloudPoint, Face, HeightMap, PointCloud};
use nalgebra::{Isometry3, Point3, Translation3, Vector3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::error::{ReconError, Result};
use super::face_choice::{
    ExcludedFace, FaceChoiceOptions, FaceChoiceReport, FaceChoiceSettings, SurfaceSamples, choose_faces,
};
use super::filters::{
    FilterReport, intensity_window, radius_outlier_removal, rigid_from_matrix, statistical_outlier_removal,
    statistical_outlier_removal_keeping_surface, voxel_decimate,
};
use super::roughing::continuous_over;
use super::table::{TableReport, TableSettings, level_on_table};
use depthmill_geometry::Mesh;
use depthmill_geometry::formats::Geometry;
use depthmill_geometry::mesh_raster::rasterize_mesh_with_stats;
use depthmill_geometry::raster::{
    COVERAGE_ASSUMED, CoverageStats, FillMethod, FillParams, FillReport, Roi, auto_z_range, coverage,
    fill_holes, grid_for_roi, rasterize_median, try_rasterize_max,
};
use depthmill_geometry::surface_fit::{FitParams, FitReport, rasterize_fit};

/// Default pixel size, mm.
pub const DEFAULT_PIXEL_MM: f64 = 0.1;
/// Default largest hole filled, mm.
pub const DEFAULT_MAX_HOLE_MM: f64 = 2.0;
/// Height scale of the `median_bilateral` estimator's filter, mm: about three times the noise of a
/// triangulation line scanner's points (σ 0.035 mm for the simulated SLP-400).
pub const BILATERAL_SIGMA_Z_MM: f64 = 0.1;
/// Default roughing lattice, pixels.
pub const DEFAULT_ROUGHING_FACTOR: u32 = 4;

/// The `reconstruct` object of a job request.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ReconstructOptions {
    #[serde(default)]
    pub pixel_mm: Option<f64>,
    #[serde(default)]
    pub faces: Option<Vec<FaceOptions>>,
    /// Choose the faces from the shape ([`crate::domain::face_choice`]); not with `faces`.
    #[serde(default)]
    pub face_choice: Option<FaceChoiceOptions>,
    #[serde(default)]
    pub fill: Option<FillOptions>,
    #[serde(default)]
    pub roi: Option<RoiOptions>,
    /// Margin around the points' extent when `roi` is not given (default 2 pixels).
    #[serde(default)]
    pub margin_mm: Option<f64>,
    #[serde(default)]
    pub z_min_mm: Option<f64>,
    #[serde(default)]
    pub z_max_mm: Option<f64>,
    #[serde(default)]
    pub filters: Option<FilterOptions>,
    #[serde(default)]
    pub roughing_factor: Option<u32>,
    /// How a cell's points make the depth map: `max` (default) or `median`.
    #[serde(default)]
    pub estimator: Option<String>,
}

/// How the points of a cell make its height in the depth map (the finishing target).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum CellEstimator {
    /// The highest point: never below the measured surface, but about two standard deviations of
    /// the scanner's noise above it (the noise is cut into the part).
    #[default]
    Max,
    /// The median point: an unbiased estimate of the surface under symmetric noise. The roughing
    /// map still comes from the max.
    Median,
    /// The median, then a bilateral filter (σ one pixel across, [`BILATERAL_SIGMA_Z_MM`] in
    /// height): each cell the weighted mean of its neighbours at about its height, so the noise
    /// of a few points per cell is averaged over a dozen cells while steps much taller than σ
    /// (walls, edges) keep their place. The roughing map still comes from the max.
    MedianBilateral,
    /// A robust local quadric fit of a few hundred points around each cell
    /// ([`depthmill_geometry::surface_fit`]): the noise averaged an order of magnitude down,
    /// curved surfaces kept, steps and convex edges kept by weighting the other side out. The
    /// roughing map still comes from the max.
    Fit,
}

/// A face: exactly one of `view`, `a_deg` and `normal`; `origin` only with `normal`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FaceOptions {
    /// `+Z`, `-Z`, `+X`, `-X`, `+Y` or `-Y`.
    #[serde(default)]
    pub view: Option<String>,
    #[serde(default)]
    pub a_deg: Option<f64>,
    /// Outward normal in the part frame (any length but zero).
    #[serde(default)]
    pub normal: Option<[f64; 3]>,
    /// A point of the face; the face frame puts it at the origin.
    #[serde(default)]
    pub origin: Option<[f64; 3]>,
}

#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FillOptions {
    /// `idw` or `max`.
    #[serde(default)]
    pub method: Option<String>,
    #[serde(default)]
    pub max_hole_mm: Option<f64>,
    #[serde(default)]
    pub radius_mm: Option<f64>,
    #[serde(default)]
    pub power: Option<f64>,
}

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RoiOptions {
    pub x_min_mm: f64,
    pub y_min_mm: f64,
    pub x_max_mm: f64,
    pub y_max_mm: f64,
}

#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FilterOptions {
    #[serde(default)]
    pub intensity: Option<IntensityOptions>,
    #[serde(default)]
    pub voxel_mm: Option<f64>,
    #[serde(default)]
    pub statistical: Option<StatisticalOptions>,
    #[serde(default)]
    pub radius: Option<RadiusOptions>,
    /// Rigid transform applied first: a row-major 4x4 matrix.
    #[serde(default)]
    pub transform: Option<[[f64; 4]; 4]>,
    /// The table the part stood on, found in the cloud and made the XY plane (after the
    /// transform, before the other filters; [`crate::domain::table`]).
    #[serde(default)]
    pub table: Option<TableOptions>,
}

/// `reconstruct.filters.table`: every field optional.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TableOptions {
    /// Points within this of the plane are the table's, mm (default 1).
    #[serde(default)]
    pub tolerance_mm: Option<f64>,
    /// Keep only the largest group of points above the table (default true).
    #[serde(default)]
    pub largest_only: Option<bool>,
    /// Points farther apart than this (twice this, at most) make separate groups, mm (default 3).
    #[serde(default)]
    pub gap_mm: Option<f64>,
}

impl TableOptions {
    /// Applies defaults and checks every value, naming the job field at fault.
    pub fn resolve(&self) -> Result<TableSettings> {
        let d = TableSettings::default();
        let tolerance_mm = self.tolerance_mm.unwrap_or(d.tolerance_mm);
        if !(tolerance_mm.is_finite() && tolerance_mm > 0.0 && tolerance_mm <= 100.0) {
            return Err(ReconError::param(
                "reconstruct.filters.table.tolerance_mm",
                tolerance_mm,
                "must be in (0, 100] mm",
            ));
        }
        let gap_mm = self.gap_mm.unwrap_or(d.gap_mm);
        if !(gap_mm.is_finite() && (0.01..=1000.0).contains(&gap_mm)) {
            return Err(ReconError::param(
                "reconstruct.filters.table.gap_mm",
                gap_mm,
                "must be in [0.01, 1000] mm",
            ));
        }
        Ok(TableSettings { tolerance_mm, largest_only: self.largest_only.unwrap_or(d.largest_only), gap_mm })
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct IntensityOptions {
    pub min: f32,
    pub max: f32,
}

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StatisticalOptions {
    pub k: usize,
    pub n_sigma: f64,
    /// Keep the flagged points that lie on the surface their neighbours sample
    /// ([`statistical_outlier_removal_keeping_surface`]); false: Open3D's rule alone.
    #[serde(default)]
    pub keep_surface: bool,
}

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RadiusOptions {
    pub radius_mm: f64,
    pub min_neighbours: usize,
}

impl FilterOptions {
    /// What runs when a job names no filters.
    pub fn defaults() -> Self {
        FilterOptions {
            statistical: Some(StatisticalOptions { k: 12, n_sigma: 3.0, keep_surface: true }),
            ..Default::default()
        }
    }
}

/// A face resolved from [`FaceOptions`]: the view and the optional origin.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FaceFrame {
    pub face: Face,
    pub origin: Option<Point3<f64>>,
}

impl FaceFrame {
    /// `face_from_part`: `p ↦ R·(p − origin)` with `R` the face's rotation ([`Face::view_from_part`]).
    pub fn face_from_part(&self) -> Isometry3<f64> {
        let rot = Isometry3::from_parts(Translation3::identity(), self.face.view_from_part());
        match self.origin {
            Some(o) => rot * Translation3::new(-o.x, -o.y, -o.z),
            None => rot,
        }
    }
}

impl FaceOptions {
    /// Resolves and checks the face; `field` names it in errors (`reconstruct.faces[0]`).
    pub fn resolve(&self, field: &str) -> Result<FaceFrame> {
        let face = match (&self.view, self.a_deg, self.normal) {
            (Some(v), None, None) => {
                let face: Face = v.parse().map_err(|_| {
                    ReconError::param(format!("{field}.view"), v, "expected +Z, -Z, +X, -X, +Y or -Y")
                })?;
                if !Face::NAMED.contains(&face) {
                    return Err(ReconError::param(
                        format!("{field}.view"),
                        v,
                        "expected +Z, -Z, +X, -X, +Y or -Y (use a_deg or normal for other faces)",
                    ));
                }
                face
            }
            (None, Some(a), None) if a.is_finite() => Face::A { angle_deg: a },
            (None, Some(a), None) => {
                return Err(ReconError::param(format!("{field}.a_deg"), a, "must be finite"));
            }
            (None, None, Some([x, y, z])) => Face::normal(Vector3::new(x, y, z)).ok_or_else(|| {
                ReconError::param(
                    format!("{field}.normal"),
                    format!("[{x}, {y}, {z}]"),
                    "must be finite and non-zero",
                )
            })?,
            _ => return Err(ReconError::param(field, "{..}", "give exactly one of view, a_deg and normal")),
        };
        let origin = match self.origin {
            None => None,
            Some(_) if self.normal.is_none() => {
                return Err(ReconError::param(format!("{field}.origin"), "[..]", "only allowed with normal"));
            }
            Some(o) if o.iter().all(|c| c.is_finite()) => Some(Point3::from(o)),
            Some(o) => {
                return Err(ReconError::param(format!("{field}.origin"), format!("{o:?}"), "must be finite"));
            }
        };
        Ok(FaceFrame { face, origin })
    }
}

/// Options after defaults and checks.
#[derive(Debug, Clone)]
pub struct Resolved {
    pub pixel_mm: f64,
    /// The faces the job names (`+Z` when it names none and asks for no choice).
    pub faces: Vec<FaceFrame>,
    /// When set, the faces are chosen from the shape and `faces` is ignored.
    pub face_choice: Option<FaceChoiceSettings>,
    pub fill: FillParams,
    pub roi: Option<Roi>,
    pub margin_mm: f64,
    pub z_range: (Option<f64>, Option<f64>),
    pub filters: FilterOptions,
    pub roughing_factor: u32,
    pub estimator: CellEstimator,
}

impl ReconstructOptions {
    /// Applies defaults and checks every value, naming the field of the job JSON at fault.
    pub fn resolve(&self) -> Result<Resolved> {
        let pixel_mm = self.pixel_mm.unwrap_or(DEFAULT_PIXEL_MM);
        if !(pixel_mm.is_finite() && pixel_mm > 0.0 && pixel_mm <= 100.0) {
            return Err(ReconError::param(
                "reconstruct.pixel_mm",
                pixel_mm,
                "must be positive and at most 100 mm",
            ));
        }
        if self.faces.is_some() && self.face_choice.is_some() {
            return Err(ReconError::param(
                "reconstruct.face_choice",
                "{..}",
                "give either faces or face_choice, not both",
            ));
        }
        let face_choice = self.face_choice.as_ref().map(FaceChoiceOptions::resolve).transpose()?;
        let faces = match &self.faces {
            None => vec![FaceFrame { face: Face::PosZ, origin: None }],
            Some(f) if f.is_empty() || f.len() > 36 => {
                return Err(ReconError::param("reconstruct.faces", f.len(), "needs 1 to 36 faces"));
            }
            Some(f) => f
                .iter()
                .enumerate()
                .map(|(i, face)| face.resolve(&format!("reconstruct.faces[{i}]")))
                .collect::<Result<_>>()?,
        };
        let fill_opts = self.fill.clone().unwrap_or_default();
        let method = match fill_opts.method.as_deref() {
            None | Some("idw") => {
                let power = fill_opts.power.unwrap_or(2.0);
                if !(power.is_finite() && (0.0..=16.0).contains(&power)) {
                    return Err(ReconError::param("reconstruct.fill.power", power, "must be in [0, 16]"));
                }
                FillMethod::Idw { power }
            }
            Some("max") => FillMethod::Max,
            Some(m) => return Err(ReconError::param("reconstruct.fill.method", m, "expected idw or max")),
        };
        let max_hole_mm = fill_opts.max_hole_mm.unwrap_or(DEFAULT_MAX_HOLE_MM);
        if !(max_hole_mm.is_finite() && (0.0..=1000.0).contains(&max_hole_mm)) {
            return Err(ReconError::param(
                "reconstruct.fill.max_hole_mm",
                max_hole_mm,
                "must be in [0, 1000] mm",
            ));
        }
        if let Some(r) = fill_opts.radius_mm
            && !(r.is_finite() && r > 0.0 && r <= 1000.0)
        {
            return Err(ReconError::param("reconstruct.fill.radius_mm", r, "must be in (0, 1000] mm"));
        }
        let fill = FillParams { method, max_hole_mm, radius_mm: fill_opts.radius_mm };
        let roi = self
            .roi
            .map(|r| {
                let roi = Roi {
                    x_min_mm: r.x_min_mm,
                    y_min_mm: r.y_min_mm,
                    x_max_mm: r.x_max_mm,
                    y_max_mm: r.y_max_mm,
                };
                roi.validate().map(|()| roi)
            })
            .transpose()?;
        let margin_mm = self.margin_mm.unwrap_or(2.0 * pixel_mm);
        if !(margin_mm.is_finite() && (0.0..=1000.0).contains(&margin_mm)) {
            return Err(ReconError::param("reconstruct.margin_mm", margin_mm, "must be in [0, 1000] mm"));
        }
        for (field, v) in [("reconstruct.z_min_mm", self.z_min_mm), ("reconstruct.z_max_mm", self.z_max_mm)] {
            if let Some(v) = v
                && !v.is_finite()
            {
                return Err(ReconError::param(field, v, "must be finite"));
            }
        }
        if let (Some(lo), Some(hi)) = (self.z_min_mm, self.z_max_mm)
            && lo >= hi
        {
            return Err(ReconError::param(
                "reconstruct.z_max_mm",
                hi,
                format!("must exceed z_min_mm = {lo}"),
            ));
        }
        let filters = self.filters.clone().unwrap_or_else(FilterOptions::defaults);
        if let Some(t) = filters.table {
            t.resolve()?;
        }
        if let Some(s) = filters.statistical
            && !(1..=256).contains(&s.k)
        {
            return Err(ReconError::param("reconstruct.filters.statistical.k", s.k, "must be in 1..=256"));
        }
        if let Some(r) = filters.radius
            && r.min_neighbours > 10_000
        {
            return Err(ReconError::param(
                "reconstruct.filters.radius.min_neighbours",
                r.min_neighbours,
                "must be at most 10000",
            ));
        }
        let roughing_factor = self.roughing_factor.unwrap_or(DEFAULT_ROUGHING_FACTOR);
        if !(1..=256).contains(&roughing_factor) {
            return Err(ReconError::param(
                "reconstruct.roughing_factor",
                roughing_factor,
                "must be in 1..=256",
            ));
        }
        let estimator = match self.estimator.as_deref() {
            Some("max") => CellEstimator::Max,
            Some("median") => CellEstimator::Median,
            Some("median_bilateral") => CellEstimator::MedianBilateral,
            None | Some("fit") => CellEstimator::Fit,
            Some(other) => {
                return Err(ReconError::param(
                    "reconstruct.estimator",
                    other,
                    "expected max, median, median_bilateral or fit",
                ));
            }
        };
        Ok(Resolved {
            pixel_mm,
            faces,
            face_choice,
            fill,
            roi,
            margin_mm,
            z_range: (self.z_min_mm, self.z_max_mm),
            filters,
            roughing_factor,
            estimator,
        })
    }
}

/// One face's outputs.
#[derive(Debug, Clone)]
pub struct FaceOutput {
    pub face: FaceFrame,
    /// Max-Z map before filling (NaN = no data).
    pub raw: HeightMap,
    /// The depth map: `raw` with enclosed holes filled.
    pub depth_map: HeightMap,
    /// 1 measured, 0.5 filled (a hole between measurements), 0.25 assumed (never seen, filled by
    /// [`fill_unseen`]), 0 hole, NaN outside the footprint; z range [0, 1].
    pub coverage_map: HeightMap,
    /// Continuous over-approximation of `depth_map` for roughing.
    pub roughing_map: HeightMap,
    pub stats: FaceStats,
}

/// Numbers of one face, as they go into the report.
#[derive(Debug, Clone, Serialize)]
pub struct FaceStats {
    /// The face as text (`+Z`, `A=90`, `N=0,0.6,0.8`).
    pub face: String,
    /// The part-frame point the face's frame is centred on (a turned set-up's centre on the A
    /// axis, or the face's own origin), when not the part frame's origin.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub part_origin_mm: Option<[f64; 3]>,
    pub width: u32,
    pub height: u32,
    pub pixel_mm: f64,
    pub origin_x_mm: f64,
    pub origin_y_mm: f64,
    pub z_min_mm: f64,
    pub z_max_mm: f64,
    pub points_binned: usize,
    pub points_outside: usize,
    pub coverage: CoverageStats,
    pub fill: FillReport,
    /// Cells the scanner saw neither the part nor the table in, filled with the highest height
    /// around them (only with free-space evidence; see [`reconstruct_with_free_space`]).
    pub unseen_filled: usize,
    /// Of those, cells whose highest point the scanner did not show clear above (under a wall's
    /// or an overhang's edge: [`ScanSpace::shadowed`]), lidded instead of taken from that point.
    pub shadowed_lidded: usize,
    /// [`FaceStats::mostly_assumed`]'s warning, when the face's map is more assumed than measured.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub warning: Option<String>,
    /// What the `fit` estimator did (the noise it found, its windows).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub fit: Option<FitReport>,
    pub seconds: f64,
}

/// A face's map with more than this many assumed cells per measured one is named
/// ([`FaceStats::mostly_assumed`]). A turned face of a part scanned from above commonly holds one
/// to two assumed cells per measured one (the sides the scan saw at a slant); a view along a
/// side the scan never saw holds tens.
pub const ASSUMED_PER_MEASURED_WARN: usize = 3;
/// Most times the faces of a cloud are chosen again without the turned faces whose maps came out
/// mostly assumed (a choice that leaves out at least one more each time ends well before: a
/// cloud's candidates are 13 at the default 15° step).
const MAX_RECHOICES: usize = 12;

impl FaceStats {
    /// Share of the map's cells the scan measured, percent.
    pub fn measured_pct(&self) -> f64 {
        let c = &self.coverage;
        if c.cells == 0 { 0.0 } else { 100.0 * c.measured as f64 / c.cells as f64 }
    }

    /// A warning when the face's map holds more than [`ASSUMED_PER_MEASURED_WARN`] assumed cells
    /// (never shown by a point, set at the height around them: [`fill_unseen`]) per measured
    /// one: the scan hardly saw the part from that side, so its program leaves material over
    /// most of it. The job names the face and the shares rather than cut a part the map only
    /// guesses at without a word.
    pub fn mostly_assumed(&self) -> Option<String> {
        let c = &self.coverage;
        if self.unseen_filled <= ASSUMED_PER_MEASURED_WARN * c.measured || c.cells == 0 {
            return None;
        }
        let pct = |n: usize| 100.0 * n as f64 / c.cells as f64;
        Some(format!(
            "face {}: {:.1} % of its map was measured and {:.1} % assumed (cells no point showed, set at the height around them): the scan hardly saw the part from this side, so the program leaves material over most of it; name the faces to cut (reconstruct.faces) or scan that side",
            self.face,
            pct(c.measured),
            pct(self.unseen_filled)
        ))
    }
}

impl FaceStats {
    /// The `unseen_filled` diagnostic: the area lidded at the height around it, and how much of
    /// it lay under a wall's or an overhang's edge (points the scanner did not show clear above,
    /// [`FaceStats::shadowed_lidded`]).
    pub fn unseen_message(&self) -> String {
        let area = |cells: usize| cells as f64 * self.pixel_mm * self.pixel_mm;
        let shadowed = if self.shadowed_lidded > 0 {
            format!(
                " ({:.1} mm² of it under a wall's or an overhang's edge, where the scanner saw points but did not show the space above them clear)",
                area(self.shadowed_lidded)
            )
        } else {
            String::new()
        };
        format!(
            "face {}: {:.1} mm² where the scanner saw neither the part nor the table were filled at the height around them{shadowed}: material is left there, not cut",
            self.face,
            area(self.unseen_filled)
        )
    }
}

/// What [`reconstruct`] produced.
#[derive(Debug, Clone)]
pub struct ReconstructOutput {
    pub faces: Vec<FaceOutput>,
    pub report: ReconstructReport,
}

/// The stage's report (stored as JSON).
#[derive(Debug, Clone, Serialize)]
pub struct ReconstructReport {
    /// `point_cloud` or `mesh`.
    pub input: &'static str,
    pub points_in: usize,
    pub points_kept: usize,
    pub triangles: usize,
    pub filters: Vec<FilterReport>,
    pub faces: Vec<FaceStats>,
    pub seconds: f64,
    /// How the input's units were decided (set by the caller that read the file).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub units: Option<depthmill_geometry::UnitsDecision>,
    /// How the faces were chosen, when the job asked for a choice (`reconstruct.face_choice`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub face_choice: Option<FaceChoiceReport>,
    /// The table the cloud was found standing on (`reconstruct.filters.table`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub table: Option<TableReport>,
}

/// Progress callback: fraction in [0, 1] and a short message.
pub type ProgressFn<'a> = &'a (dyn Fn(f64, &str) + Sync);
/// Cancellation check.
pub type CancelFn<'a> = &'a (dyn Fn() -> bool + Sync);

fn check_cancel(cancelled: CancelFn<'_>) -> Result<()> {
    if cancelled() { Err(ReconError::Cancelled) } else { Ok(()) }
}

/// A cloud after the clean-up filters.
#[derive(Debug, Clone)]
pub struct Cleaned {
    pub cloud: PointCloud,
    pub reports: Vec<FilterReport>,
    /// What the table filter found, when it ran.
    pub table: Option<TableReport>,
    /// The rigid motion the cloud went through (`transform`, then the table's), when it moved:
    /// anything in the input's frame (the scan's free space) must follow it.
    pub moved: Option<Isometry3<f64>>,
}

/// Runs the clean-up filters of `opts` on `cloud`, in the documented order.
pub fn clean(mut cloud: PointCloud, opts: &FilterOptions) -> Result<Cleaned> {
    let mut reports = Vec::new();
    let mut moved = None;
    if let Some(m) = opts.transform {
        let iso = rigid_from_matrix(m)?;
        cloud.transform(&iso);
        moved = Some(iso);
    }
    let mut table = None;
    if let Some(t) = opts.table {
        let before = cloud.len();
        let (c, r) = level_on_table(cloud, &t.resolve()?)?;
        cloud = c;
        reports.push(FilterReport { filter: "table", kept: cloud.len(), removed: before - cloud.len() });
        moved = Some(r.motion * moved.unwrap_or_else(Isometry3::identity));
        table = Some(r);
    }
    if let Some(w) = opts.intensity {
        let (c, r) = intensity_window(cloud, w.min, w.max)?;
        cloud = c;
        reports.push(r);
    }
    if let Some(v) = opts.voxel_mm {
        let (c, r) = voxel_decimate(cloud, v)?;
        cloud = c;
        reports.push(r);
    }
    if let Some(s) = opts.statistical {
        let (c, r) = if s.keep_surface {
            statistical_outlier_removal_keeping_surface(cloud, s.k, s.n_sigma)?
        } else {
            statistical_outlier_removal(cloud, s.k, s.n_sigma)?
        };
        cloud = c;
        reports.push(r);
    }
    if let Some(s) = opts.radius {
        let (c, r) = radius_outlier_removal(cloud, s.radius_mm, s.min_neighbours)?;
        cloud = c;
        reports.push(r);
    }
    Ok(Cleaned { cloud, reports, table, moved })
}

/// The whole stage on an already-read input.
pub fn reconstruct(
    input: Geometry,
    opts: &ReconstructOptions,
    progress: ProgressFn<'_>,
    cancelled: CancelFn<'_>,
) -> Result<ReconstructOutput> {
    reconstruct_with_free_space(input, opts, None, progress, cancelled)
}

/// What the scanner showed of the space around the part, part frame (the free-space artifact,
/// [`depthmill_geometry::cloud::FREE_KIND`]).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ScanSpace {
    /// Table points seen with nothing over them: no part there.
    pub table: Vec<Point3<f32>>,
    /// Points of the cloud whose vertical the scanner did not show clear under a wall or an
    /// overhang's edge beside them: a `+Z` cell whose highest point is one of these is lidded
    /// at the height around it instead of taken from that point.
    pub shadowed: Vec<Point3<f32>>,
}

impl ScanSpace {
    /// Table points only (a free space without shadowed points).
    pub fn table(table: Vec<Point3<f32>>) -> Self {
        ScanSpace { table, shadowed: Vec::new() }
    }

    /// Splits a free-space cloud by its per-point kind (every point a table point when the file
    /// carries none).
    ///
    /// Errors: a kind other than the two known, named with its point.
    pub fn from_labelled(points: Vec<Point3<f32>>, kind: Option<Vec<u16>>) -> Result<Self> {
        use depthmill_geometry::cloud::{FREE_KIND, FREE_KIND_SHADOWED, FREE_KIND_TABLE};
        let Some(kind) = kind else { return Ok(ScanSpace::table(points)) };
        let mut out = ScanSpace::default();
        for (i, (p, k)) in points.into_iter().zip(kind).enumerate() {
            match k {
                FREE_KIND_TABLE => out.table.push(p),
                FREE_KIND_SHADOWED => out.shadowed.push(p),
                other => {
                    return Err(ReconError::param(
                        format!("free_space: vertex {i}: {FREE_KIND}"),
                        other,
                        format!(
                            "expected {FREE_KIND_TABLE} (a table point) or {FREE_KIND_SHADOWED} (a shadowed point)"
                        ),
                    ));
                }
            }
        }
        Ok(out)
    }

    fn moved(&self, iso: &Isometry3<f64>) -> ScanSpace {
        let mv = |v: &[Point3<f32>]| v.par_iter().map(|p| single(&(iso * p.at()))).collect();
        ScanSpace { table: mv(&self.table), shadowed: mv(&self.shadowed) }
    }
}

/// [`reconstruct`] with the scanner's free-space evidence: `free_space` holds points where the
/// scanner saw the table past the part (same frame as the input). On a `+Z` face of a cloud, the
/// automatic region of interest also covers them, and a cell left without data after the fill
/// is then either empty (a free-space point in it: nothing there, cut to the floor) or unseen
/// (no point of any kind: a steep or hidden surface); unseen regions are filled with the highest
/// measured height around them, so the tools leave material there rather than cut into a part
/// nobody saw ([`FaceStats::unseen_filled`]).
pub fn reconstruct_with_free_space(
    input: Geometry,
    opts: &ReconstructOptions,
    scan_space: Option<&ScanSpace>,
    progress: ProgressFn<'_>,
    cancelled: CancelFn<'_>,
) -> Result<ReconstructOutput> {
    let started = Instant::now();
    let mut r = opts.resolve()?;
    let mut choice_report = None;
    let mut table_report = None;
    let (points_in, triangles) = match &input {
        Geometry::Cloud(c) => (c.len(), 0),
        Geometry::Mesh(m) => (m.vertices.len(), m.triangles.len()),
    };
    let mut faces = Vec::new();
    let (kind, points_kept, filter_reports) = match input {
        Geometry::Cloud(cloud) => {
            progress(0.02, "cleaning the point cloud");
            let Cleaned { cloud, reports, table, moved } = clean(cloud, &r.filters)?;
            table_report = table;
            // The free space was seen in the input's frame: it follows the cloud.
            let moved_space: Option<ScanSpace> = moved.zip(scan_space).map(|(iso, s)| s.moved(&iso));
            let scan_space = moved_space.as_ref().or(scan_space);
            let free_space = scan_space.map(|s| &s.table[..]);
            let shadowed: &[Point3<f32>] = scan_space.map_or(&[], |s| &s.shadowed[..]);
            if cloud.is_empty() {
                return Err(ReconError::Empty(if points_in == 0 {
                    "the input holds no point with finite coordinates (NaN or infinite ones are dropped)"
                        .into()
                } else {
                    format!("none of the input's {points_in} points is left after the clean-up filters")
                }));
            }
            check_cancel(cancelled)?;
            // A cloud the scanner took from above, the part on the table (its free space says
            // so), is solid under what the scanner saw: a turned face sees only the points that
            // body does not hide from the side it looks from, and the face choice counts only
            // those.
            let turned_named = r.faces.iter().any(|fr| fr.face != Face::PosZ);
            let body_map = match free_space {
                Some(f) if !f.is_empty() && (r.face_choice.is_some() || turned_named) => {
                    progress(0.15, "the part's body seen from above");
                    Some(body_from_above(&cloud.points, f, shadowed, &r, cancelled)?)
                }
                _ => None,
            };
            let samples = match r.face_choice {
                Some(settings) => {
                    progress(0.2, "choosing the faces from the shape");
                    let mut samples = SurfaceSamples::from_cloud(&cloud, settings.cell_mm)?;
                    samples.body = body_map.clone().map(|b| (b, occlusion_tolerance_mm(r.pixel_mm)));
                    Some((samples, settings))
                }
                None => None,
            };
            let mut body_surface_points: Option<Vec<Point3<f64>>> = None;
            // A turned face the choice took whose map comes out mostly assumed (the scan hardly
            // saw the part from that side) would be cut blind: it is left out and the faces are
            // chosen again, until none is (at most MAX_RECHOICES times).
            let mut excluded: Vec<ExcludedFace> = Vec::new();
            let kept = cloud.len();
            for attempt in 0..=MAX_RECHOICES {
                if let Some((samples, settings)) = &samples {
                    choice_report = Some(choose(&mut r, samples, settings, &excluded, cancelled)?);
                }
                centre_turned_faces(&mut r, cloud.bounds());
                faces.clear();
                let body = match (free_space, &body_map) {
                    (Some(f), Some(map)) if r.faces.iter().any(|fr| fr.face != Face::PosZ) => {
                        let surface = body_surface_points
                            .get_or_insert_with(|| body_surface(map, table_height(f, map)));
                        Some((map, &*surface))
                    }
                    _ => None,
                };
                let n_faces = r.faces.len() as f64;
                for (i, frame) in r.faces.iter().enumerate() {
                    progress(0.3 + 0.7 * i as f64 / n_faces, &format!("face {}: rasterising", frame.face));
                    let iso = frame.face_from_part();
                    let visible = body.as_ref().filter(|_| frame.face != Face::PosZ).map(|(b, _)| {
                        let up = iso.rotation.inverse() * Vector3::z();
                        visible_from(&cloud.points, &up, b, occlusion_tolerance_mm(r.pixel_mm))
                    });
                    // The cloud itself for a face that views it as it is (`+Z`, no origin), else a
                    // turned copy (single precision, like the cloud) of the points it sees.
                    let turned: Vec<Point3<f32>>;
                    // The region the whole turned cloud covers, hidden points included.
                    let mut whole_roi = None;
                    let points: &[Point3<f32>] = if iso == Isometry3::identity() && visible.is_none() {
                        &cloud.points
                    } else {
                        let all: Vec<Point3<f32>> =
                            cloud.points.par_iter().map(|p| single(&(iso * p.at()))).collect();
                        turned = match &visible {
                            Some(v) => {
                                whole_roi = Roi::around(&all, r.margin_mm);
                                all.into_iter().zip(v).filter(|(_, seen)| **seen).map(|(p, _)| p).collect()
                            }
                            None => all,
                        };
                        &turned
                    };
                    if points.is_empty() {
                        return Err(ReconError::Empty(format!(
                            "reconstruct.faces[{i}] ({}): the scanned part's body hides every point of the cloud from that side (the scanner saw it from above)",
                            frame.face
                        )));
                    }
                    // Seen past the body, an empty cell is surface nobody saw from that side (a wall
                    // the scanner saw edge-on, or not at all), not a gap between scan lines: it is
                    // lidded at the height around it, never interpolated from what lies behind. The
                    // map covers the whole part as the face sees it, hidden points and the body's
                    // surface included; that surface bounds the part from that side.
                    let bound: Option<Vec<Point3<f32>>> = body
                        .as_ref()
                        .filter(|_| visible.is_some())
                        .map(|(_, surface)| surface.par_iter().map(|p| single(&(iso * p))).collect());
                    let face_r = bound.as_ref().map(|bound| {
                        let roi = r.roi.or_else(|| match (whole_roi, Roi::around(bound, r.margin_mm)) {
                            (Some(a), Some(b)) => Some(roi_union(a, b)),
                            (a, b) => a.or(b),
                        });
                        Resolved { roi, fill: FillParams { max_hole_mm: 0.0, ..r.fill }, ..r.clone() }
                    });
                    // Free space is what the scanner saw from above: it speaks for the top view only.
                    let free: Option<Vec<Point3<f64>>> = free_space
                        .filter(|f| !f.is_empty() && frame.face == depthmill_geometry::Face::PosZ)
                        .map(|f| f.iter().map(|p| iso * p.at()).collect());
                    // So are the points it did not show clear above (see `ScanSpace::shadowed`).
                    let shadow: Vec<Point3<f32>> = if frame.face == depthmill_geometry::Face::PosZ {
                        shadowed.iter().map(|p| single(&(iso * p.at()))).collect()
                    } else {
                        Vec::new()
                    };
                    let face_r = face_r.as_ref().unwrap_or(&r);
                    let mut face =
                        cloud_face(points, free.as_deref(), &shadow, *frame, face_r, i, cancelled)?;
                    if let Some(bound) = &bound {
                        lid_with_body(&mut face, bound, face_r)?;
                    }
                    faces.push(face);
                }
                let blind: Vec<ExcludedFace> = faces
                    .iter()
                    .filter(|f| f.face.face != Face::PosZ && f.stats.mostly_assumed().is_some())
                    .map(|f| ExcludedFace {
                        face: f.stats.face.clone(),
                        measured_pct: f.stats.measured_pct(),
                    })
                    .collect();
                if samples.is_none() || blind.is_empty() || attempt == MAX_RECHOICES {
                    break;
                }
                tracing::info!(faces = ?blind.iter().map(|b| b.face.clone()).collect::<Vec<_>>(), "faces mostly assumed: choosing again without them");
                excluded.extend(blind);
            }
            ("point_cloud", kept, reports)
        }
        Geometry::Mesh(mesh) => {
            if let Some(settings) = r.face_choice {
                progress(0.02, "choosing the faces from the shape");
                let samples = SurfaceSamples::from_mesh(&mesh, settings.cell_mm)?;
                choice_report = Some(choose(&mut r, &samples, &settings, &[], cancelled)?);
            }
            centre_turned_faces(&mut r, mesh.bounds());
            let n_faces = r.faces.len() as f64;
            for (i, frame) in r.faces.iter().enumerate() {
                progress(
                    0.05 + 0.95 * i as f64 / n_faces,
                    &format!("face {}: z-buffering the mesh", frame.face),
                );
                let mut m = mesh.clone();
                m.transform(&frame.face_from_part());
                faces.push(mesh_face(&m, *frame, &r, i, cancelled)?);
            }
            ("mesh", points_in, Vec::new())
        }
    };
    progress(1.0, "depth maps ready");
    let report = ReconstructReport {
        input: kind,
        points_in,
        points_kept,
        triangles,
        filters: filter_reports,
        faces: faces.iter().map(|f| f.stats.clone()).collect(),
        seconds: started.elapsed().as_secs_f64(),
        units: None,
        face_choice: choice_report,
        table: table_report,
    };
    Ok(ReconstructOutput { faces, report })
}

/// The part's body as the scanner saw it from above: the `+Z` map of the cloud at the job's
/// pixel, highest point per cell, with the free space and the unseen fill of a `+Z` face (a cell
/// where the table was seen is empty, any other empty one is lidded at the height around it, and
/// so is a cell whose highest point the scanner did not show clear above: `shadowed`, under a
/// wall's or an overhang's edge), over the whole cloud whatever the job's region of interest.
/// The part lies under it: a turned face does not take a point under a tooth's flank or an
/// overhang for the surface it sees.
fn body_from_above(
    points: &[Point3<f32>],
    free_space: &[Point3<f32>],
    shadowed: &[Point3<f32>],
    r: &Resolved,
    cancelled: CancelFn<'_>,
) -> Result<HeightMap> {
    let free: Vec<Point3<f64>> = free_space.iter().map(|p| p.at()).collect();
    // An empty cell between measurements is lidded at the height around it, not interpolated:
    // the body bounds the part from above, at a step's edge too.
    let fill = FillParams { max_hole_mm: 0.0, ..r.fill };
    let rb = Resolved { roi: None, estimator: CellEstimator::Max, fill, ..r.clone() };
    let frame = FaceFrame { face: Face::PosZ, origin: None };
    Ok(cloud_face(points, Some(&free), shadowed, frame, &rb, 0, cancelled)?.depth_map)
}

/// The height of the table the part stood on: the median of the free space's heights (the
/// table the scanner saw past the part), never above the body's lowest cell.
fn table_height(free_space: &[Point3<f32>], body: &HeightMap) -> f64 {
    let mut z: Vec<f32> = free_space.iter().map(|p| p.z).filter(|z| z.is_finite()).collect();
    let lowest = body.z_range_of_data().map_or(f64::INFINITY, |(lo, _)| f64::from(lo));
    if z.is_empty() {
        return lowest;
    }
    let mid = z.len() / 2;
    let (_, m, _) = z.select_nth_unstable_by(mid, f32::total_cmp);
    f64::from(*m).min(lowest)
}

/// The surface of the body ([`body_from_above`]) standing on the table at `floor`, as points
/// (part frame) every half cell: each cell's column, its top and each side that stands above the
/// neighbouring column (or the table). Seen from any side, a map at the body's pixel gets a point
/// in every cell the body covers.
fn body_surface(body: &HeightMap, floor: f64) -> Vec<Point3<f64>> {
    let px = body.pixel_mm();
    let (w, h) = (body.width(), body.height());
    let height = |c: i64, r: i64| -> f64 {
        if c < 0 || r < 0 || c >= i64::from(w) || r >= i64::from(h) {
            return floor;
        }
        body.get(c as u32, r as u32).filter(|z| z.is_finite()).map_or(floor, |z| f64::from(z).max(floor))
    };
    (0..h)
        .into_par_iter()
        .flat_map_iter(|r| {
            let mut out = Vec::new();
            for c in 0..w {
                let Some(t) = body.get(c, r).filter(|z| z.is_finite()).map(|z| f64::from(z).max(floor))
                else {
                    continue;
                };
                let (cx, cy) = body.cell_center(c, r);
                let q = 0.25 * px;
                for (dx, dy) in [(-q, -q), (q, -q), (-q, q), (q, q)] {
                    out.push(Point3::new(cx + dx, cy + dy, t));
                }
                // Sides, just inside this cell, down to the lower neighbour.
                let inside = 0.5 * px * (1.0 - 1e-3);
                let (ci, ri) = (i64::from(c), i64::from(r));
                for (nc, nr, ox, oy) in [
                    (ci - 1, ri, -1.0, 0.0),
                    (ci + 1, ri, 1.0, 0.0),
                    (ci, ri - 1, 0.0, -1.0),
                    (ci, ri + 1, 0.0, 1.0),
                ] {
                    let lo = height(nc, nr);
                    if t - lo <= 1e-9 {
                        continue;
                    }
                    // From half a cell under the top down, then the foot on the neighbour.
                    let steps = ((t - lo) / (0.5 * px)).ceil().min(1e5) as usize;
                    for k in 1..=steps {
                        let z = (t - 0.5 * px * k as f64).max(lo);
                        for along in [-q, q] {
                            let (x, y) = if ox != 0.0 {
                                (cx + ox * inside, cy + along)
                            } else {
                                (cx + along, cy + oy * inside)
                            };
                            out.push(Point3::new(x, y, z));
                        }
                    }
                }
            }
            out
        })
        .collect()
}

/// Raises a turned face's cells no visible point showed (assumed, lidded at the height around
/// them) to the body's surface seen from that face, `bound` (in the face's frame): the height
/// around an unseen region is what lies behind it, while the body bounds what may stand in front.
/// The roughing map is raised alike, and the map's range widened when the user set none.
fn lid_with_body(face: &mut FaceOutput, bound: &[Point3<f32>], r: &Resolved) -> Result<()> {
    let grid = *face.depth_map.meta();
    let (front, _) = try_rasterize_max(bound, &grid)?;
    let mut raised = 0usize;
    for (((z, c), f), rough) in face
        .depth_map
        .data_mut()
        .iter_mut()
        .zip(face.coverage_map.data())
        .zip(front.data())
        .zip(face.roughing_map.data_mut())
    {
        if !f.is_finite() {
            continue;
        }
        if *c == COVERAGE_ASSUMED && *z < *f {
            *z = *f;
            raised += 1;
        }
        if rough.is_nan() || *rough < *z {
            *rough = *z;
        }
    }
    if raised > 0 {
        let hi = face.depth_map.z_range_of_data().map_or(grid.z_max_mm, |(_, hi)| f64::from(hi));
        let z_max = r.z_range.1.unwrap_or(grid.z_max_mm.max(hi));
        face.depth_map.set_z_range(grid.z_min_mm, z_max)?;
        face.roughing_map.set_z_range(grid.z_min_mm, z_max)?;
        face.stats.z_max_mm = z_max;
    }
    Ok(())
}

/// How far above the ray towards the tool the body must stand to hide a point, mm: the scanner's
/// noise on the highest point of a cell, and half a cell of slope.
fn occlusion_tolerance_mm(pixel_mm: f64) -> f64 {
    (0.5 * pixel_mm).max(0.1)
}

/// Which `points` (part frame) a face whose tool comes from direction `up` (part frame, unit)
/// sees past `body` (the part's `+Z` map from above: the part is solid under it): a point is hidden when the
/// ray from it towards the tool crosses a cell other than the point's own at `tol` or more under
/// the body's height there (the ray's lowest height in the cell). The cells are walked in the
/// order the ray crosses them (a grid traversal, exact), until the ray leaves the map or rises
/// above the body's highest cell. A face looking straight down (`up` = +Z) sees every point.
pub fn visible_from(points: &[Point3<f32>], up: &Vector3<f64>, body: &HeightMap, tol: f64) -> Vec<bool> {
    if up.x.abs() < 1e-12 && up.y.abs() < 1e-12 {
        return vec![true; points.len()];
    }
    let top = body.data().iter().copied().filter(|z| z.is_finite()).fold(f32::NEG_INFINITY, f32::max);
    let top = f64::from(top) + tol;
    let px = body.pixel_mm();
    let (w, h) = (i64::from(body.width()), i64::from(body.height()));
    let (x0, y0) = (body.origin_x_mm(), body.origin_y_mm());
    let hidden_in = |c: i64, r: i64, z_low: f64| {
        (0..w).contains(&c)
            && (0..h).contains(&r)
            && body.get(c as u32, r as u32).is_some_and(|t| t.is_finite() && f64::from(t) >= z_low + tol)
    };
    points
        .par_iter()
        .map(|p| {
            let p = p.at();
            if !p.coords.iter().all(|c| c.is_finite()) {
                return false;
            }
            // Position in cells; the ray's parameter is the distance along `up`.
            let (u, v) = ((p.x - x0) / px, (p.y - y0) / px);
            let (mut c, mut r) = (u.floor() as i64, v.floor() as i64);
            let axis = |o: f64, cell: i64, d: f64| -> (i64, f64, f64) {
                let d = d / px;
                if d > 0.0 {
                    (1, (cell as f64 + 1.0 - o) / d, 1.0 / d)
                } else if d < 0.0 {
                    (-1, (cell as f64 - o) / d, -1.0 / d)
                } else {
                    (0, f64::INFINITY, f64::INFINITY)
                }
            };
            let (sc, mut next_c, dc) = axis(u, c, up.x);
            let (sr, mut next_r, dr) = axis(v, r, up.y);
            // Where the ray leaves the grid's rectangle (or never enters it).
            let leave = |o: f64, d: f64, n: i64| -> f64 {
                let d = d / px;
                if d > 0.0 {
                    (n as f64 - o) / d
                } else if d < 0.0 {
                    -o / d
                } else if (0.0..n as f64).contains(&o) {
                    f64::INFINITY
                } else {
                    f64::NEG_INFINITY
                }
            };
            let end = leave(u, up.x, w).min(leave(v, up.y, h));
            loop {
                let entry = next_c.min(next_r);
                if entry >= end {
                    return true;
                }
                if next_c < next_r {
                    c += sc;
                    next_c += dc;
                } else {
                    r += sr;
                    next_r += dr;
                }
                let exit = next_c.min(next_r).min(end);
                let z_low = p.z + up.z * if up.z >= 0.0 { entry } else { exit };
                if up.z >= 0.0 && z_low > top {
                    return true;
                }
                if hidden_in(c, r, z_low) {
                    return false;
                }
            }
        })
        .collect()
}

/// Centres a turned set-up on the A axis: when any face of `r` is not `+Z`, the faces without
/// an origin of their own turn about the centre of the part's bounding box `bounds` (to 0.01 mm)
/// instead of the origin of the file's frame, which may lie anywhere (an assembly's origin, a
/// scanner's): turned about that, the part would swing out of the machine's travel. Each map
/// carries the point ([`depthmill_geometry::HeightMapMeta::part_origin_mm`]) for the stages that
/// compare with the part in its own frame. A part cut from `+Z` alone stays where it lies, and so
/// does one whose job frames the faces itself: a region of interest or a Z window is given in
/// the view of the file's own frame (a scan's `roi` and `z_min_mm` around the part where the
/// sensor saw it), and moving the faces' origin would leave the part outside them.
fn centre_turned_faces(r: &mut Resolved, bounds: Option<depthmill_geometry::Aabb>) {
    let turned = r.faces.iter().any(|f| f.face != depthmill_geometry::Face::PosZ);
    let framed = r.roi.is_some() || r.z_range.0.is_some() || r.z_range.1.is_some();
    let Some(b) = bounds.filter(|_| turned && !framed) else { return };
    let centre = nalgebra::center(&b.min, &b.max).map(|c| (c * 100.0).round() / 100.0);
    if !centre.coords.iter().all(|c| c.is_finite()) {
        return;
    }
    for f in &mut r.faces {
        f.origin.get_or_insert(centre);
    }
    tracing::info!(centre_mm = ?[centre.x, centre.y, centre.z], "turned set-up centred on the A axis");
}

/// Runs the face choice and puts its faces in `r`.
fn choose(
    r: &mut Resolved,
    samples: &SurfaceSamples,
    settings: &FaceChoiceSettings,
    exclude: &[ExcludedFace],
    cancelled: CancelFn<'_>,
) -> Result<FaceChoiceReport> {
    let (faces, report) = choose_faces(samples, settings, exclude, cancelled)?;
    tracing::info!(faces = ?faces.iter().map(ToString::to_string).collect::<Vec<_>>(), covered_pct = report.covered_pct, "faces chosen");
    r.faces = faces.into_iter().map(|face| FaceFrame { face, origin: None }).collect();
    Ok(report)
}

fn face_roi<P: CloudPoint>(r: &Resolved, points: &[P], index: usize) -> Result<Roi> {
    match r.roi {
        Some(roi) => Ok(roi),
        None => Roi::around(points, r.margin_mm).ok_or_else(|| {
            ReconError::Empty(format!(
                "reconstruct.faces[{index}]: no finite points to take a region of interest from"
            ))
        }),
    }
}

/// Free-space evidence on a face's grid: the cells with a table point, and the same closed over
/// the gaps between scan lines ([`close_mask`], radius `k` cells).
struct FreeCells {
    hits: Vec<bool>,
    closed: Vec<bool>,
    k: usize,
}

impl FreeCells {
    /// The cells taken as empty next to `map` (after the hole fill): those with a table point,
    /// and those the closing adds unless a cell with data lies within the closing's radius
    /// (closing rounds the free region's concave corners, which are the part's convex corners,
    /// and bridges an unseen wall or outline thinner than twice its radius between table points
    /// on both sides of it).
    fn effective(&self, map: &HeightMap) -> Vec<bool> {
        let (w, h) = (map.width() as usize, map.height() as usize);
        let data: Vec<bool> = map.data().iter().map(|z| z.is_finite()).collect();
        let near_data = dilate_mask(&data, w, h, self.k);
        (0..data.len()).map(|i| self.hits[i] || (self.closed[i] && !near_data[i])).collect()
    }
}

/// Gaps between free-space samples up to this wide (twice this, across) are free too, mm: more
/// than the scanner's line spacing, less than a flank worth protecting.
const FREE_GAP_MM: f64 = 1.0;

/// Morphological closing of `mask` (`w` x `h`, row-major) by a `(2k+1)`-cell square: a cell is
/// set when every cell within `k` of it (Chebyshev) is within `k` of a set cell. Fills gaps up
/// to `2k` cells between set cells without moving the set region's outline outward.
pub fn close_mask(mask: &[bool], w: usize, h: usize, k: usize) -> Vec<bool> {
    // Dilate, then erode: set where no unset cell of the dilation lies within k.
    let dilated = dilate_mask(mask, w, h, k);
    let unset: Vec<bool> = dilated.iter().map(|v| !v).collect();
    dilate_mask(&unset, w, h, k).iter().map(|v| !v).collect()
}

/// The cells of `mask` (`w` x `h`, row-major) with a set cell within `k` (Chebyshev; cells off
/// the grid do not count), separable: along the row, then along the column.
fn dilate_mask(mask: &[bool], w: usize, h: usize, k: usize) -> Vec<bool> {
    let mut rows = vec![false; mask.len()];
    for r in 0..h {
        for c in 0..w {
            let (lo, hi) = (c.saturating_sub(k), (c + k).min(w - 1));
            rows[r * w + c] = (lo..=hi).any(|cc| mask[r * w + cc]);
        }
    }
    let mut out = vec![false; mask.len()];
    for r in 0..h {
        for c in 0..w {
            let (lo, hi) = (r.saturating_sub(k), (r + k).min(h - 1));
            out[r * w + c] = (lo..=hi).any(|rr| rows[rr * w + c]);
        }
    }
    out
}

/// The smallest region holding both.
fn roi_union(a: Roi, b: Roi) -> Roi {
    Roi {
        x_min_mm: a.x_min_mm.min(b.x_min_mm),
        y_min_mm: a.y_min_mm.min(b.y_min_mm),
        x_max_mm: a.x_max_mm.max(b.x_max_mm),
        y_max_mm: a.y_max_mm.max(b.y_max_mm),
    }
}

/// Fills every 8-connected region of cells that are empty in `map` and not `free` (no point of
/// any kind landed there) with the highest finite height of the cells around it; a region with no
/// finite neighbour stays empty. Returns the number of cells filled.
pub fn fill_unseen(map: &mut HeightMap, free: &[bool]) -> usize {
    let (w, h) = (map.width() as usize, map.height() as usize);
    let data = map.data().to_vec();
    let unseen = |i: usize| data[i].is_nan() && !free[i];
    let mut seen = vec![false; data.len()];
    let mut out = data.clone();
    let mut filled = 0usize;
    let mut stack = Vec::new();
    let mut region = Vec::new();
    for start in 0..data.len() {
        if seen[start] || !unseen(start) {
            continue;
        }
        seen[start] = true;
        stack.push(start);
        region.clear();
        let mut top = f32::NEG_INFINITY;
        while let Some(i) = stack.pop() {
            region.push(i);
            let (r, c) = ((i / w) as i64, (i % w) as i64);
            for dr in -1..=1 {
                for dc in -1..=1 {
                    let (rr, cc) = (r + dr, c + dc);
                    if rr < 0 || cc < 0 || rr >= h as i64 || cc >= w as i64 {
                        continue;
                    }
                    let j = rr as usize * w + cc as usize;
                    if data[j].is_finite() {
                        top = top.max(data[j]);
                    } else if !seen[j] && unseen(j) {
                        seen[j] = true;
                        stack.push(j);
                    }
                }
            }
        }
        if top.is_finite() {
            for &i in &region {
                out[i] = top;
            }
            filled += region.len();
        }
    }
    if filled > 0 {
        map.data_mut().copy_from_slice(&out);
    }
    filled
}

fn cloud_face(
    points: &[Point3<f32>],
    free: Option<&[Point3<f64>]>,
    shadowed: &[Point3<f32>],
    frame: FaceFrame,
    r: &Resolved,
    index: usize,
    cancelled: CancelFn<'_>,
) -> Result<FaceOutput> {
    let started = Instant::now();
    let mut roi = face_roi(r, points, index)?;
    if let (None, Some(f)) = (r.roi, free)
        && let Some(around) = Roi::around(f, r.margin_mm)
    {
        roi = roi_union(roi, around);
    }
    let mut grid = grid_for_roi(&roi, r.pixel_mm)?;
    grid.face = frame.face;
    grid.part_origin_mm = frame.origin.map_or([0.0; 3], |o| o.coords.into());
    // Cells where the scanner saw the table: nothing there. Scan lines sample the table every
    // line spacing, so the gaps between them are closed (up to FREE_GAP_MM).
    let free_cells: Option<FreeCells> = match free {
        Some(f) => {
            let hits: Vec<bool> =
                try_rasterize_max(f, &grid)?.0.data().iter().map(|z| z.is_finite()).collect();
            let k = ((FREE_GAP_MM / r.pixel_mm).ceil() as usize).clamp(1, 16);
            let closed = close_mask(&hits, grid.width as usize, grid.height as usize, k);
            Some(FreeCells { hits, closed, k })
        }
        // A face other than +Z has no evidence of where the part is not (the scanner saw the
        // table from above only): a cell no point falls in may hide the part, so every one is
        // lidded at the highest height around it, and the tools leave material there instead of
        // cutting down to the floor through a part nobody saw from that side.
        None if frame.face != Face::PosZ => {
            let n = grid.width as usize * grid.height as usize;
            Some(FreeCells { hits: vec![false; n], closed: vec![false; n], k: 0 })
        }
        None => None,
    };
    let (max, raster) = try_rasterize_max(points, &grid)?;
    if raster.points_binned == 0 {
        return Err(ReconError::Empty(format!(
            "reconstruct.faces[{index}]: no point falls inside the region of interest"
        )));
    }
    check_cancel(cancelled)?;
    // A cell whose highest point is one the scanner did not show clear above (under a wall's or
    // an overhang's edge) has an unknown top: it is lidded like an unseen cell, never cut to
    // that point.
    let lid: Option<Vec<bool>> = if shadowed.is_empty() {
        None
    } else {
        let (shadow, _) = try_rasterize_max(shadowed, &grid)?;
        let lid: Vec<bool> =
            shadow.data().iter().zip(max.data()).map(|(s, m)| s.is_finite() && s >= m).collect();
        lid.contains(&true).then_some(lid)
    };
    let mut fit = None;
    let (raw, upper) = match r.estimator {
        CellEstimator::Max => (max, None),
        // The same cells hold data in both (one binning rule).
        CellEstimator::Median => (rasterize_median(points, &grid)?.0, Some(max)),
        CellEstimator::MedianBilateral => {
            let median = rasterize_median(points, &grid)?.0;
            let smooth = super::image_ops::bilateral(&median, grid.pixel_mm, BILATERAL_SIGMA_Z_MM)?;
            (smooth, Some(max))
        }
        CellEstimator::Fit => {
            let (fitted, _, report) = rasterize_fit(points, &grid, &FitParams::default())?;
            fit = Some(report);
            (fitted, Some(max))
        }
    };
    check_cancel(cancelled)?;
    let counts = (raster.points_binned, raster.points_outside);
    let mut out =
        finish_face(raw, upper, free_cells.as_ref(), lid.as_deref(), frame, r, counts, started, cancelled)?;
    out.stats.fit = fit;
    Ok(out)
}

fn mesh_face(
    mesh: &Mesh,
    frame: FaceFrame,
    r: &Resolved,
    index: usize,
    cancelled: CancelFn<'_>,
) -> Result<FaceOutput> {
    let started = Instant::now();
    let roi = face_roi(r, &mesh.vertices, index)?;
    let mut grid = grid_for_roi(&roi, r.pixel_mm)?;
    grid.face = frame.face;
    grid.part_origin_mm = frame.origin.map_or([0.0; 3], |o| o.coords.into());
    let (raw, _) = rasterize_mesh_with_stats(mesh, &grid)?;
    if raw.valid_count() == 0 {
        return Err(ReconError::Empty(format!(
            "reconstruct.faces[{index}]: the mesh covers no cell centre of the region of interest"
        )));
    }
    check_cancel(cancelled)?;
    finish_face(raw, None, None, None, frame, r, (0, 0), started, cancelled)
}

/// Z range, fill, coverage and roughing of one face. `raw` is the finishing target as rasterised;
/// `upper`, when given, an upper bound of it on the same cells (the max where `raw` is a median),
/// which the roughing map is built from instead so it never cuts into the part. `free`, when
/// given, marks the cells where the scanner saw the table: the other empty cells are unseen and
/// filled by [`fill_unseen`] after the hole fill, in the target and in the roughing bound alike.
/// `lid`, when given, marks cells whose top the scan left unknown: they are emptied after the
/// hole fill and lidded by [`fill_unseen`] too (never free).
#[allow(clippy::too_many_arguments)]
fn finish_face(
    mut raw: HeightMap,
    upper: Option<HeightMap>,
    free: Option<&FreeCells>,
    lid: Option<&[bool]>,
    frame: FaceFrame,
    r: &Resolved,
    (points_binned, points_outside): (usize, usize),
    started: Instant,
    cancelled: CancelFn<'_>,
) -> Result<FaceOutput> {
    // Robust range of the measured heights; the user's values win.
    let (auto_lo, auto_hi) = auto_z_range(raw.data().iter().copied()).unwrap_or((0.0, 1.0));
    let z_min = r.z_range.0.unwrap_or(auto_lo);
    let mut z_max = r.z_range.1.unwrap_or(auto_hi);
    if z_max <= z_min {
        z_max = z_min + 1.0;
    }
    raw.set_z_range(z_min, z_max)?;
    let (mut depth_map, fill) = if r.fill.max_hole_mm > 0.0 {
        fill_holes(&raw, &r.fill)?
    } else {
        (raw.clone(), FillReport::default())
    };
    let mut free = free.map(|f| f.effective(&depth_map));
    if let Some(lid) = lid {
        // Without table evidence, the lidded cells are the only unseen ones (the rest of an
        // empty map stays empty, as without free space).
        let n = lid.len();
        let free = free.get_or_insert_with(|| vec![true; n]);
        for ((z, f), &l) in depth_map.data_mut().iter_mut().zip(free.iter_mut()).zip(lid) {
            if l {
                *z = f32::NAN;
                *f = false;
            }
        }
    }
    // The cells empty before the unseen fill (only when there is one).
    let empty_before: Option<Vec<bool>> =
        free.as_ref().map(|_| depth_map.data().iter().map(|z| !z.is_finite()).collect());
    let unseen_filled = free.as_deref().map_or(0, |f| fill_unseen(&mut depth_map, f));
    check_cancel(cancelled)?;
    let (mut coverage_map, coverage) = coverage(&raw, &depth_map);
    if let Some(empty_before) = empty_before.filter(|_| unseen_filled > 0) {
        // The cells only the unseen fill gave a height: assumed, not filled between measurements.
        for ((c, &was_empty), z) in
            coverage_map.data_mut().iter_mut().zip(&empty_before).zip(depth_map.data())
        {
            if was_empty && z.is_finite() {
                *c = COVERAGE_ASSUMED;
            }
        }
    }
    let mut roughing_map = match upper {
        None => continuous_over(&depth_map, r.roughing_factor)?,
        Some(mut upper) => {
            upper.set_z_range(z_min, z_max)?;
            // Filling is monotone in the samples (max, or a weighted mean with the same weights
            // over the same cells) but for its step rules, so the filled bound stays above the
            // filled target but at a step (below); the unseen fill takes the highest neighbour,
            // also monotone.
            let mut filled = if r.fill.max_hole_mm > 0.0 { fill_holes(&upper, &r.fill)?.0 } else { upper };
            if let Some(lid) = lid {
                for (z, &l) in filled.data_mut().iter_mut().zip(lid) {
                    if l {
                        *z = f32::NAN;
                    }
                }
            }
            if let Some(f) = &free {
                fill_unseen(&mut filled, f);
            }
            // Where a fill's step rule lifted a target cell that the bound's own fill (over
            // samples a little higher, so a little less of a step) did not, the bound takes the
            // target: roughing never goes under the finishing target.
            for (u, &t) in filled.data_mut().iter_mut().zip(depth_map.data()) {
                if t.is_finite() && (u.is_nan() || *u < t) {
                    *u = t;
                }
            }
            continuous_over(&filled, r.roughing_factor)?
        }
    };
    roughing_map.set_z_range(z_min, z_max)?;
    let m = depth_map.meta();
    let stats = FaceStats {
        face: frame.face.to_string(),
        part_origin_mm: frame.origin.map(|o| o.coords.into()),
        width: m.width,
        height: m.height,
        pixel_mm: m.pixel_mm,
        origin_x_mm: m.origin_x_mm,
        origin_y_mm: m.origin_y_mm,
        z_min_mm: z_min,
        z_max_mm: z_max,
        points_binned,
        points_outside,
        coverage,
        fill,
        unseen_filled,
        shadowed_lidded: lid.map_or(0, |l| l.iter().filter(|&&l| l).count()),
        warning: None,
        fit: None,
        seconds: started.elapsed().as_secs_f64(),
    };
    let stats = FaceStats { warning: stats.mostly_assumed(), ..stats };
    Ok(FaceOutput { face: frame, raw, depth_map, coverage_map, roughing_map, stats })
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::rngs::StdRng;
    use rand::{Rng, SeedableRng};

    /// 30 x 20 mm at z = 5 with ±0.05 mm uniform noise, about 16 points a 0.5 mm cell, and an
    /// unscanned disc of 1 mm radius in the middle (filled).
    fn noisy_plane() -> PointCloud {
        let mut rng = StdRng::seed_from_u64(5);
        PointCloud::from_points((0..40_000).filter_map(|_| {
            let (x, y) = (rng.random_range(0.0..30.0), rng.random_range(0.0..20.0));
            let z = 5.0 + rng.random_range(-0.05..0.05);
            ((x - 15.0f64).hypot(y - 10.0) > 1.0).then(|| Point3::new(x, y, z))
        }))
    }

    fn face(estimator: Option<&str>) -> FaceOutput {
        let opts = ReconstructOptions {
            pixel_mm: Some(0.5),
            filters: Some(FilterOptions::default()),
            estimator: estimator.map(str::to_string),
            ..Default::default()
        };
        let out =
            reconstruct(Geometry::Cloud(noisy_plane()), &opts, &|_, _| {}, &|| false).expect("reconstruct");
        out.faces.into_iter().next().expect("one face")
    }

    fn finite_mean(m: &HeightMap) -> f64 {
        let v: Vec<f64> = m.data().iter().filter(|z| z.is_finite()).map(|&z| f64::from(z)).collect();
        v.iter().sum::<f64>() / v.len() as f64
    }

    #[test]
    fn the_median_target_is_unbiased_and_roughing_still_comes_from_the_max() {
        let max = face(Some("max"));
        let median = face(Some("median"));
        // The max stands about 0.04 mm proud with 16 samples of ±0.05 mm; the median does not.
        assert!(finite_mean(&max.depth_map) - 5.0 > 0.03, "max mean {}", finite_mean(&max.depth_map));
        assert!(
            (finite_mean(&median.depth_map) - 5.0).abs() < 0.005,
            "median mean {}",
            finite_mean(&median.depth_map)
        );
        // The same cells are measured and filled.
        assert_eq!(max.stats.coverage, median.stats.coverage);
        assert!(median.stats.fill.filled > 0, "the hole is filled");
        // Roughing never below the max target, nor below the median target.
        let rough = median.roughing_map.data();
        for ((&r, &hi), &lo) in rough.iter().zip(max.depth_map.data()).zip(median.depth_map.data()) {
            assert_eq!(hi.is_finite(), lo.is_finite());
            if hi.is_finite() {
                assert!(r >= hi && hi >= lo, "roughing {r}, max {hi}, median {lo}");
            }
        }
    }

    fn rms_about(m: &HeightMap, z: f64) -> f64 {
        let v: Vec<f64> =
            m.data().iter().filter(|z| z.is_finite()).map(|&c| (f64::from(c) - z).powi(2)).collect();
        (v.iter().sum::<f64>() / v.len() as f64).sqrt()
    }

    #[test]
    fn the_fit_target_averages_far_below_the_median_reports_its_noise_and_roughs_from_the_max() {
        let median = face(Some("median"));
        let fit = face(Some("fit"));
        let max = face(Some("max"));
        // The fit is the default.
        let default = face(None);
        assert!(
            default
                .depth_map
                .data()
                .iter()
                .zip(fit.depth_map.data())
                .all(|(a, b)| a.to_bits() == b.to_bits()),
            "the default estimator is not the fit"
        );
        let (rm, rf) = (rms_about(&median.depth_map, 5.0), rms_about(&fit.depth_map, 5.0));
        assert!(rf < rm / 1.8, "median RMS {rm}, fit RMS {rf}");
        assert!((finite_mean(&fit.depth_map) - 5.0).abs() < 0.003, "{}", finite_mean(&fit.depth_map));
        let report = fit.stats.fit.expect("the fit reports");
        // Uniform noise of ±0.05 mm: σ = 0.1 / √12.
        assert!(
            report.noise_estimated && (report.noise_mm / (0.1 / 12f64.sqrt()) - 1.0).abs() < 0.2,
            "{report:?}"
        );
        assert!(median.stats.fit.is_none());
        let rough = fit.roughing_map.data();
        for (&r, &hi) in rough.iter().zip(max.depth_map.data()) {
            if hi.is_finite() {
                assert!(r >= hi, "roughing {r} below the max {hi}");
            }
        }
    }

    #[test]
    fn the_bilateral_median_averages_the_noise_down_and_keeps_steps() {
        let median = face(Some("median"));
        let smooth = face(Some("median_bilateral"));
        let (rm, rs) = (rms_about(&median.depth_map, 5.0), rms_about(&smooth.depth_map, 5.0));
        assert!(rs < rm / 2.0, "median RMS {rm}, median_bilateral RMS {rs}");
        assert!((finite_mean(&smooth.depth_map) - 5.0).abs() < 0.005, "{}", finite_mean(&smooth.depth_map));
        // A 2 mm step stays a step: the cells next to it keep their side's height.
        let mut rng = StdRng::seed_from_u64(9);
        let points: Vec<Point3<f64>> = (0..40_000)
            .map(|_| {
                let (x, y) = (rng.random_range(0.0..20.0), rng.random_range(0.0..10.0));
                let z = if x < 10.0 { 5.0 } else { 7.0 } + rng.random_range(-0.05..0.05);
                Point3::new(x, y, z)
            })
            .collect();
        let opts = ReconstructOptions {
            pixel_mm: Some(0.5),
            filters: Some(FilterOptions::default()),
            estimator: Some("median_bilateral".into()),
            roi: Some(RoiOptions { x_min_mm: 0.0, y_min_mm: 0.0, x_max_mm: 20.0, y_max_mm: 10.0 }),
            ..Default::default()
        };
        let out = reconstruct(Geometry::Cloud(PointCloud::from_points(points)), &opts, &|_, _| {}, &|| false)
            .expect("reconstruct");
        let m = &out.faces[0].depth_map;
        for row in 2..m.height() - 2 {
            let (lo, hi) = (m.get(19, row).unwrap_or(0.0), m.get(20, row).unwrap_or(0.0));
            assert!((lo - 5.0).abs() < 0.03 && (hi - 7.0).abs() < 0.03, "row {row}: {lo} | {hi}");
        }
    }

    #[test]
    fn a_turned_face_of_a_cloud_lids_what_no_point_shows() {
        // A plate at z = 5 with a 4 mm band no point fell in: from +Z without free space it stays
        // empty (as before); seen turned, where nothing says the part is not there, it is lidded.
        let mut rng = StdRng::seed_from_u64(3);
        let points: Vec<Point3<f64>> = (0..30_000)
            .filter_map(|_| {
                let (x, y) = (rng.random_range(0.0..30.0), rng.random_range(0.0..20.0));
                (!(10.0..14.0).contains(&x)).then(|| Point3::new(x, y, 5.0))
            })
            .collect();
        let run = |face: FaceOptions| {
            let opts = ReconstructOptions {
                pixel_mm: Some(0.5),
                faces: Some(vec![face]),
                filters: Some(FilterOptions::default()),
                ..Default::default()
            };
            reconstruct(Geometry::Cloud(PointCloud::from_points(points.clone())), &opts, &|_, _| {}, &|| {
                false
            })
            .expect("reconstruct")
            .faces
            .remove(0)
        };
        let up = run(FaceOptions { view: Some("+Z".into()), ..Default::default() });
        assert_eq!(up.stats.unseen_filled, 0);
        assert!(up.depth_map.data().iter().any(|z| z.is_nan()), "the band stays empty from +Z");
        let turned = run(FaceOptions { a_deg: Some(10.0), ..Default::default() });
        assert!(turned.stats.unseen_filled > 0);
        assert!(turned.depth_map.data().iter().all(|z| z.is_finite()), "every empty cell is lidded");
        // The coverage map marks exactly those cells as assumed, apart from filled holes.
        let assumed =
            |f: &FaceOutput| f.coverage_map.data().iter().filter(|&&c| c == COVERAGE_ASSUMED).count();
        assert_eq!(assumed(&turned), turned.stats.unseen_filled);
        assert_eq!(assumed(&up), 0);
        // The roughing map stays at or above the target.
        for (r, t) in turned.roughing_map.data().iter().zip(turned.depth_map.data()) {
            assert!(r >= t, "roughing {r} below target {t}");
        }
    }

    #[test]
    fn a_turned_set_up_turns_about_the_parts_centre() {
        // A 30 x 20 x 10 mm box far from the file's origin, as a part of an assembly lies.
        let mut mesh = depthmill_geometry::Mesh::cuboid(30.0, 20.0, 10.0);
        mesh.transform(&Isometry3::translation(100.0, -250.0, -400.0));
        let run = |faces: Vec<FaceOptions>| {
            let opts = ReconstructOptions { pixel_mm: Some(0.5), faces: Some(faces), ..Default::default() };
            reconstruct(Geometry::Mesh(mesh.clone()), &opts, &|_, _| {}, &|| false).expect("reconstruct")
        };
        // Milled from +Z alone, it stays where it lies.
        let up = run(vec![FaceOptions { view: Some("+Z".into()), ..Default::default() }]);
        assert_eq!(up.faces[0].depth_map.part_origin_mm(), [0.0; 3]);
        assert!(up.faces[0].stats.part_origin_mm.is_none());
        assert!((up.faces[0].depth_map.origin_x_mm() - 100.0).abs() < 2.0);
        // Turned, every face turns about the box's centre: on the A axis, whatever the file says.
        let turned = run(vec![
            FaceOptions { view: Some("+Z".into()), ..Default::default() },
            FaceOptions { a_deg: Some(90.0), ..Default::default() },
        ]);
        let centre = [115.0, -240.0, -395.0];
        for f in &turned.faces {
            assert_eq!(f.depth_map.part_origin_mm(), centre, "{}", f.face.face);
            assert_eq!(f.roughing_map.part_origin_mm(), centre);
            assert_eq!(f.stats.part_origin_mm, Some(centre));
            // The map's frame puts the box's centre at the origin: half its height on top, and its
            // grid about the axis.
            let m = &f.depth_map;
            let top = m.data().iter().copied().filter(|z| z.is_finite()).fold(f32::MIN, f32::max);
            let half = if f.face.face == Face::PosZ { 5.0 } else { 10.0 };
            assert!((f64::from(top) - half).abs() < 1e-3, "{}: top {top}", f.face.face);
            let y_mid = m.origin_y_mm() + f64::from(m.height()) * m.pixel_mm() / 2.0;
            assert!(y_mid.abs() < 1.0, "{}: grid centred at y {y_mid}", f.face.face);
            // The map's own motion takes the part's centre to its frame's origin.
            let c = m.meta().view_from_part() * Point3::from(centre);
            assert!(c.coords.norm() < 1e-9, "{c}");
        }
        // A normal face keeps the origin the job gives it.
        let own = run(vec![
            FaceOptions { view: Some("+Z".into()), ..Default::default() },
            FaceOptions {
                normal: Some([0.0, -1.0, 1.0]),
                origin: Some([100.0, -250.0, -400.0]),
                ..Default::default()
            },
        ]);
        assert_eq!(own.faces[0].depth_map.part_origin_mm(), centre);
        assert_eq!(own.faces[1].depth_map.part_origin_mm(), [100.0, -250.0, -400.0]);
        // A job that frames the view itself (a region of interest, a Z window, in the file's
        // frame seen from the face) keeps the file's origin: the part stays inside its frame.
        // Seen from -Z (half a turn about X) the box's x 100..130, y -250..-230 read as x
        // 100..130, y 230..250, its bottom at z = -400 on top at 400.
        for (roi, z_range) in [(true, false), (false, true), (true, true)] {
            let opts = ReconstructOptions {
                pixel_mm: Some(0.5),
                faces: Some(vec![FaceOptions { view: Some("-Z".into()), ..Default::default() }]),
                roi: roi.then_some(RoiOptions {
                    x_min_mm: 95.0,
                    x_max_mm: 135.0,
                    y_min_mm: 225.0,
                    y_max_mm: 255.0,
                }),
                z_min_mm: z_range.then_some(380.0),
                z_max_mm: z_range.then_some(420.0),
                ..Default::default()
            };
            let out =
                reconstruct(Geometry::Mesh(mesh.clone()), &opts, &|_, _| {}, &|| false).expect("reconstruct");
            let f = &out.faces[0];
            assert_eq!(f.depth_map.part_origin_mm(), [0.0; 3], "roi {roi} z {z_range}");
            let top = f.depth_map.data().iter().copied().filter(|z| z.is_finite()).fold(f32::MIN, f32::max);
            assert!((f64::from(top) - 400.0).abs() < 1e-3, "roi {roi} z {z_range}: top {top}");
            assert!(f.stats.coverage.measured > 1000, "roi {roi} z {z_range}: {:?}", f.stats.coverage);
        }
    }

    #[test]
    fn a_face_the_scan_hardly_saw_is_named() {
        // A box's top (z = 10) and the outline where it meets the table (z = 0), as a scan from
        // above shows it: seen from the side (A = 90), only those two rows of its map are measured.
        let mut points = Vec::new();
        for i in 0..=120 {
            for j in 0..=80 {
                points.push(Point3::new(f64::from(i) * 0.25, f64::from(j) * 0.25, 10.0));
            }
        }
        for i in 0..=120 {
            for y in [0.0, 20.0] {
                points.push(Point3::new(f64::from(i) * 0.25, y, 0.0));
            }
        }
        let opts = ReconstructOptions {
            pixel_mm: Some(0.5),
            faces: Some(vec![
                FaceOptions { view: Some("+Z".into()), ..Default::default() },
                FaceOptions { a_deg: Some(90.0), ..Default::default() },
            ]),
            filters: Some(FilterOptions::default()),
            ..Default::default()
        };
        let out = reconstruct(Geometry::Cloud(PointCloud::from_points(points)), &opts, &|_, _| {}, &|| false)
            .expect("reconstruct");
        assert!(out.faces[0].stats.mostly_assumed().is_none(), "+Z is measured");
        let side = &out.faces[1].stats;
        let w = side.mostly_assumed().expect("the side view is mostly assumed");
        assert_eq!(side.warning.as_ref(), Some(&w), "the report carries it");
        assert!(w.starts_with("face A=90: ") && w.contains("% assumed"), "{w}");
        assert!(side.unseen_filled > 3 * side.coverage.measured, "{side:?}");
    }

    #[test]
    fn an_unknown_estimator_is_named() {
        let opts = ReconstructOptions { estimator: Some("mean".into()), ..Default::default() };
        match opts.resolve() {
            Err(ReconError::InvalidParameter { field, .. }) => assert_eq!(field, "reconstruct.estimator"),
            Err(e) => panic!("expected an invalid parameter, got {e}"),
            Ok(_) => panic!("an unknown estimator was accepted"),
        }
    }

    /// A 20 x 20 mm plateau at z = 8 on a table at z = 0, seen from above: the plateau measured
    /// except a band 10 <= x < 12 (a steep face the scanner missed) and a 3 mm through hole at
    /// (5, 5) where the table shows; the table measured around the plateau out to 6 mm and
    /// through the hole, except in the band's shadow (nothing seen there either).
    fn plateau_with_band() -> (PointCloud, Vec<Point3<f64>>) {
        let (mut part, mut table) = (Vec::new(), Vec::new());
        let step = 0.1;
        let n = (32.0 / step) as i32;
        for j in 0..n {
            for i in 0..n {
                let (x, y) = (-6.0 + step * (f64::from(i) + 0.5), -6.0 + step * (f64::from(j) + 0.5));
                let on_plateau = (0.0..20.0).contains(&x) && (0.0..20.0).contains(&y);
                let in_hole = (x - 5.0).hypot(y - 5.0) < 1.5;
                let band = (10.0..12.0).contains(&x);
                if band && (-6.0..26.0).contains(&y) && on_plateau {
                    continue;
                }
                if on_plateau && !in_hole {
                    part.push(Point3::new(x, y, 8.0));
                } else {
                    table.push(Point3::new(x, y, 0.0));
                }
            }
        }
        (PointCloud::from_points(part), table)
    }

    /// `cloud` reconstructed with `table` as its free-space evidence.
    fn over_table(cloud: PointCloud, table: &[Point3<f64>], opts: &ReconstructOptions) -> ReconstructOutput {
        let free = ScanSpace::table(PointCloud::from_points(table.iter().copied()).points);
        reconstruct_with_free_space(Geometry::Cloud(cloud), opts, Some(&free), &|_, _| {}, &|| false)
            .expect("reconstruct")
    }

    #[test]
    fn a_cell_whose_highest_point_the_scanner_did_not_show_clear_above_is_lidded() {
        // A terrace at z = 2 with a block to z = 12 beside it (x >= 12), the table around. The
        // terrace's points at 9 <= x < 12 are shadowed (a wall or an overhang's edge beside
        // them, their vertical not shown clear); at 9 <= x < 9.5 a point shown clear stands
        // over them in every cell.
        let (mut part, mut table, mut shadowed) = (Vec::new(), Vec::new(), Vec::new());
        let step = 0.1;
        for j in 0..300 {
            for i in 0..300 {
                let (x, y) = (-5.0 + step * (f64::from(i) + 0.5), -5.0 + step * (f64::from(j) + 0.5));
                if !((0.0..20.0).contains(&x) && (0.0..20.0).contains(&y)) {
                    table.push(Point3::new(x, y, 0.0));
                } else if x >= 12.0 {
                    part.push(Point3::new(x, y, 12.0));
                } else if x >= 9.0 {
                    shadowed.push(single(&Point3::new(x, y, 2.0)));
                    part.push(Point3::new(x, y, 2.0));
                    if (9.0..9.5).contains(&x) && i % 2 == 0 {
                        part.push(Point3::new(x, y, 2.05));
                    }
                } else {
                    part.push(Point3::new(x, y, 2.0));
                }
            }
        }
        let free = PointCloud::from_points(table.iter().copied()).points;
        for estimator in ["max", "median"] {
            let opts = ReconstructOptions {
                pixel_mm: Some(0.25),
                estimator: Some(estimator.into()),
                ..Default::default()
            };
            let run = |shadowed: Vec<Point3<f32>>| {
                let space = ScanSpace { table: free.clone(), shadowed };
                let cloud = PointCloud::from_points(part.iter().copied());
                reconstruct_with_free_space(Geometry::Cloud(cloud), &opts, Some(&space), &|_, _| {}, &|| {
                    false
                })
                .expect("reconstruct")
                .faces
                .remove(0)
            };
            let (plain, lidded) = (run(Vec::new()), run(shadowed.clone()));
            let m = *lidded.depth_map.meta();
            let (mut lid, mut kept, mut far) = (0, 0, 0);
            for row in 0..m.height {
                let y = m.origin_y_mm + (f64::from(row) + 0.5) * m.pixel_mm;
                if !(1.0..19.0).contains(&y) {
                    continue;
                }
                for col in 0..m.width {
                    let x = m.origin_x_mm + (f64::from(col) + 0.5) * m.pixel_mm;
                    let at = |f: &FaceOutput| f.depth_map.get(col, row).expect("cell");
                    let coverage = lidded.coverage_map.get(col, row).expect("cell");
                    let rough = lidded.roughing_map.get(col, row).expect("cell");
                    if !(0.5..19.5).contains(&x) {
                        continue;
                    }
                    assert!(
                        rough >= at(&lidded) - 1e-3,
                        "{estimator}: roughing {rough} under {}",
                        at(&lidded)
                    );
                    if (9.8..11.7).contains(&x) {
                        // Lidded at the block beside it, and read as assumed.
                        assert!((at(&plain) - 2.0).abs() < 1e-3, "{estimator}: {}", at(&plain));
                        assert!(
                            (at(&lidded) - 12.0).abs() < 1e-3,
                            "{estimator}: ({x}, {y}) at {}",
                            at(&lidded)
                        );
                        assert_eq!(coverage, COVERAGE_ASSUMED);
                        lid += 1;
                    } else if (9.1..9.4).contains(&x) {
                        // The highest point is shown clear: the cell keeps its measurement.
                        assert!(
                            at(&lidded) <= 2.05 + 1e-3 && at(&lidded) >= 2.0 - 1e-3,
                            "{estimator}: {}",
                            at(&lidded)
                        );
                        assert_eq!(at(&lidded), at(&plain));
                        kept += 1;
                    } else if (1.0..8.0).contains(&x) || x > 12.5 {
                        assert_eq!(at(&lidded), at(&plain), "{estimator}: ({x}, {y})");
                        far += 1;
                    }
                }
            }
            assert!(lid > 300 && kept > 50 && far > 3000, "{lid} {kept} {far}");
            assert!(lidded.stats.unseen_filled >= lid, "{}", lidded.stats.unseen_filled);
            assert_eq!(lidded.stats.shadowed_lidded, lidded.stats.unseen_filled);
            // The job's diagnostic names the shadowed share.
            let area =
                |n: usize| format!("{:.1} mm²", n as f64 * lidded.stats.pixel_mm * lidded.stats.pixel_mm);
            let message = lidded.stats.unseen_message();
            assert!(message.contains(&format!("{} where", area(lidded.stats.unseen_filled))), "{message}");
            assert!(
                message.contains(&format!("({} of it under", area(lidded.stats.shadowed_lidded))),
                "{message}"
            );
            // Without table points, the shadowed cells are lidded alike and nothing else is:
            // the map's empty surroundings stay empty.
            let space = ScanSpace { table: Vec::new(), shadowed: shadowed.clone() };
            let cloud = PointCloud::from_points(part.iter().copied());
            let bare =
                reconstruct_with_free_space(Geometry::Cloud(cloud), &opts, Some(&space), &|_, _| {}, &|| {
                    false
                })
                .expect("reconstruct")
                .faces
                .remove(0);
            assert_eq!(bare.stats.unseen_filled, bare.stats.shadowed_lidded);
            assert!(bare.stats.shadowed_lidded >= lid, "{}", bare.stats.shadowed_lidded);
            let (mut lidded_at_block, mut empty) = (0, 0);
            for (z, c) in bare.depth_map.data().iter().zip(bare.coverage_map.data()) {
                lidded_at_block += usize::from(*c == COVERAGE_ASSUMED && (z - 12.0).abs() < 1e-3);
                empty += usize::from(z.is_nan());
            }
            assert!(lidded_at_block >= lid && empty > 0, "{lidded_at_block} {empty}");
        }
        // The body seen from above, which a turned face's view is checked against, is lidded
        // alike: a point under the edge is not the top of the part's body.
        let r = ReconstructOptions { pixel_mm: Some(0.25), ..Default::default() }.resolve().expect("resolve");
        let points = PointCloud::from_points(part.iter().copied()).points;
        let body = |sh: &[Point3<f32>]| body_from_above(&points, &free, sh, &r, &|| false).expect("body");
        let (plain, lidded) = (body(&[]), body(&shadowed));
        let m = *lidded.meta();
        let (mut lid, mut same) = (0, 0);
        for row in 0..m.height {
            let y = m.origin_y_mm + (f64::from(row) + 0.5) * m.pixel_mm;
            for col in 0..m.width {
                let x = m.origin_x_mm + (f64::from(col) + 0.5) * m.pixel_mm;
                let (a, b) = (plain.get(col, row).expect("cell"), lidded.get(col, row).expect("cell"));
                if (1.0..19.0).contains(&y) && (9.8..11.7).contains(&x) {
                    assert!((a - 2.0).abs() < 1e-3 && (b - 12.0).abs() < 1e-3, "({x}, {y}): {a} -> {b}");
                    lid += 1;
                } else if !(9.0..12.0).contains(&x) {
                    assert!(a == b || (a.is_nan() && b.is_nan()), "({x}, {y}): {a} -> {b}");
                    same += 1;
                }
            }
        }
        assert!(lid > 300 && same > 5000, "{lid} {same}");
    }

    #[test]
    fn a_free_space_cloud_splits_by_its_kind_and_names_an_unknown_one() {
        let pts: Vec<Point3<f32>> = (0..4).map(|i| Point3::new(i as f32, 0.0, 0.0)).collect();
        let all = ScanSpace::from_labelled(pts.clone(), None).expect("no kinds");
        assert_eq!((all.table.len(), all.shadowed.len()), (4, 0));
        let split = ScanSpace::from_labelled(pts.clone(), Some(vec![0, 1, 0, 1])).expect("kinds");
        assert_eq!(split.table, vec![pts[0], pts[2]]);
        assert_eq!(split.shadowed, vec![pts[1], pts[3]]);
        let e = ScanSpace::from_labelled(pts, Some(vec![0, 1, 7, 0])).expect_err("kind 7");
        let text = e.to_string();
        assert!(text.contains("vertex 2") && text.contains("kind") && text.contains('7'), "{text}");
    }

    #[test]
    fn the_free_space_moves_with_the_cloud() {
        // The reference: the plateau and its table given where the filters put them. The same
        // scene given tilted and shifted, stood back by `filters.transform` or found again by
        // `filters.table`, makes the same map: the free space went with the cloud.
        let (cloud, table) = plateau_with_band();
        let opts = ReconstructOptions {
            pixel_mm: Some(0.25),
            filters: Some(FilterOptions::default()),
            ..Default::default()
        };
        let reference = over_table(cloud.clone(), &table, &opts);
        let away = Isometry3::from_parts(
            Translation3::new(3.0, -40.0, 200.0),
            nalgebra::UnitQuaternion::from_axis_angle(&Vector3::x_axis(), 0.5),
        );
        let moved = |p: Point3<f64>| away * p;
        let tilted = PointCloud::from_points(cloud.points.iter().map(|p| moved(p.at())));
        let tilted_table: Vec<Point3<f64>> = table.iter().map(|p| moved(*p)).collect();
        let m = away.inverse().to_homogeneous();
        let back: [[f64; 4]; 4] = std::array::from_fn(|r| std::array::from_fn(|c| m[(r, c)]));
        let by_transform = ReconstructOptions {
            filters: Some(FilterOptions { transform: Some(back), ..Default::default() }),
            ..opts.clone()
        };
        let out = over_table(tilted.clone(), &tilted_table, &by_transform);
        let (a, b) = (&reference.faces[0], &out.faces[0]);
        assert_eq!(a.stats.unseen_filled, b.stats.unseen_filled);
        assert_eq!(a.stats.coverage.footprint, b.stats.coverage.footprint);
        // Found by the table filter, in a raw scan that holds the table too: the plateau's top
        // stands 8 mm over the table, and the cells the table was seen in are left empty as in
        // the reference (the frame differs by a turn about Z, so the counts are compared).
        let by_table = ReconstructOptions {
            filters: Some(FilterOptions { table: Some(TableOptions::default()), ..Default::default() }),
            ..opts.clone()
        };
        let raw =
            PointCloud::from_points(tilted.points.iter().map(|p| p.at()).chain(tilted_table.iter().copied()));
        let out = over_table(raw, &tilted_table, &by_table);
        let c = &out.faces[0];
        assert!((c.stats.z_max_mm - 8.0).abs() < 0.3, "{:?}", c.stats);
        let empty = |f: &FaceOutput| f.depth_map.data().iter().filter(|z| z.is_nan()).count();
        assert!(
            empty(c) > 0 && c.stats.unseen_filled <= a.stats.unseen_filled + 40,
            "{:?} against {:?}",
            c.stats,
            a.stats
        );
        assert!(empty(c) + 200 > empty(a), "{} empty against {}", empty(c), empty(a));
    }

    #[test]
    fn a_turned_face_of_a_scan_sees_nothing_through_the_part() {
        // A pocketed block with a step in its pocket, on a wider base, scanned from above: the
        // cloud holds what faces up (the steep walls went unseen), the free space the table
        // around it. Seen from the side, the step's top lies behind the pocket's wall: a map
        // taking it as the surface there would cut through the wall to reach it.
        use crate::domain::face_choice::tests::{POCKETED_BLOCK, boxes};
        let list: Vec<_> = POCKETED_BLOCK.into_iter().chain([([7.0, 7.0, 5.0], [13.0, 13.0, 8.0])]).collect();
        let part = boxes(&list);
        let solid =
            |p: Point3<f64>| list.iter().any(|(lo, hi)| (0..3).all(|k| lo[k] <= p[k] && p[k] <= hi[k]));
        // The boxes' faces on the part's outside (a face two boxes share is inside the solid).
        let surface: Vec<Point3<f64>> = SurfaceSamples::from_mesh(&part, 0.2)
            .expect("samples")
            .points
            .into_iter()
            .filter(|p| (0..3).any(|k| [-1e-3, 1e-3].iter().any(|d| !solid(p + Vector3::ith(k, *d)))))
            .collect();
        let up_facing = |p: &Point3<f64>| {
            let within = |lo: f64, hi: f64| (lo..=hi).contains(&p.x) && (lo..=hi).contains(&p.y);
            let at = |z: f64| (p.z - z).abs() < 1e-6;
            (at(2.0) && !within(0.0, 20.0))
                || at(12.0)
                || (at(8.0) && within(7.0, 13.0))
                || (at(5.0) && within(4.0, 16.0) && !within(7.0, 13.0))
        };
        let cloud = PointCloud::from_points(surface.iter().copied().filter(up_facing));
        let table: Vec<Point3<f64>> = (0..=140)
            .flat_map(|i| {
                (0..=140)
                    .map(move |j| Point3::new(-10.0 + 0.3 * f64::from(i), -10.0 + 0.3 * f64::from(j), 0.0))
            })
            .filter(|p| !((-5.0..=25.0).contains(&p.x) && (-5.0..=25.0).contains(&p.y)))
            .collect();
        let opts = ReconstructOptions {
            pixel_mm: Some(0.25),
            faces: Some(vec![
                FaceOptions { view: Some("+Z".into()), ..Default::default() },
                FaceOptions { a_deg: Some(-90.0), ..Default::default() },
                FaceOptions { a_deg: Some(-45.0), ..Default::default() },
            ]),
            filters: Some(FilterOptions::default()),
            ..Default::default()
        };
        let out = over_table(cloud.clone(), &table, &opts);
        // The highest of the map's cells around a point's: a face seen edge-on lies on a cell's
        // edge, and either cell holds it.
        let around = |map: &HeightMap, v: Point3<f64>| -> Option<f64> {
            let (c, r) = map.cell_of(v.x, v.y)?;
            let mut best: Option<f64> = None;
            for (dc, dr) in [(-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 0), (0, 1), (1, -1), (1, 0), (1, 1)] {
                let (cc, rr) = (i64::from(c) + dc, i64::from(r) + dr);
                if cc < 0 || rr < 0 {
                    continue;
                }
                if let Some(z) = map.get(cc as u32, rr as u32).filter(|z| z.is_finite()) {
                    best = Some(best.map_or(f64::from(z), |b: f64| b.max(f64::from(z))));
                }
            }
            best
        };
        for face in &out.faces[1..] {
            // No cell of the turned map lies below the part's surface seen from that side.
            let view = face.depth_map.meta().view_from_part();
            let worst = surface
                .iter()
                .filter_map(|p| {
                    let v = view * p;
                    around(&face.depth_map, v).map(|z| v.z - z)
                })
                .fold(0.0f64, f64::max);
            assert!(worst < 0.3, "{}: the map lies {worst:.2} mm inside the part", face.stats.face);
        }
        // Without the free space nothing says the cloud was scanned from above: every point
        // counts, and the step shows through the wall.
        let plain = reconstruct(Geometry::Cloud(cloud), &opts, &|_, _| {}, &|| false).expect("reconstruct");
        let through = plain.faces[1..]
            .iter()
            .flat_map(|side| {
                let view = side.depth_map.meta().view_from_part();
                surface.iter().filter_map(move |p| {
                    let v = view * p;
                    let (c, r) = side.depth_map.cell_of(v.x, v.y)?;
                    side.depth_map.get(c, r).filter(|z| z.is_finite()).map(|z| v.z - f64::from(z))
                })
            })
            .fold(0.0f64, f64::max);
        assert!(through > 3.0, "the case shows what the body prevents: {through}");
    }

    /// The obviously right visibility: every cell of the body the ray from the point crosses (its
    /// exact entry and exit), hidden when the ray's lowest height in a crossed cell other than the
    /// point's own is `tol` or more under the cell's height.
    fn visible_reference(p: Point3<f64>, up: Vector3<f64>, body: &HeightMap, tol: f64) -> bool {
        let own = body.cell_of(p.x, p.y);
        for r in 0..body.height() {
            for c in 0..body.width() {
                if Some((c, r)) == own {
                    continue;
                }
                let Some(t) = body.get(c, r).filter(|z| z.is_finite()) else { continue };
                let (cx, cy) = body.cell_center(c, r);
                let half = 0.5 * body.pixel_mm();
                // The ray's parameter interval inside the cell's square (slab method).
                let (mut lo, mut hi) = (0.0f64, f64::INFINITY);
                for (o, d, centre) in [(p.x, up.x, cx), (p.y, up.y, cy)] {
                    if d.abs() < 1e-12 {
                        if o < centre - half || o >= centre + half {
                            lo = f64::INFINITY;
                        }
                    } else {
                        let (a, b) = ((centre - half - o) / d, (centre + half - o) / d);
                        lo = lo.max(a.min(b));
                        hi = hi.min(a.max(b));
                    }
                }
                if lo < hi {
                    let z_low = p.z + up.z * if up.z >= 0.0 { lo } else { hi };
                    if f64::from(t) >= z_low + tol {
                        return false;
                    }
                }
            }
        }
        true
    }

    #[test]
    fn visibility_past_the_body_matches_a_cell_by_cell_reference() {
        let mut rng = StdRng::seed_from_u64(11);
        for case in 0..40 {
            let (w, h) = (rng.random_range(3..14u32), rng.random_range(3..14u32));
            let meta = depthmill_geometry::HeightMapMeta {
                origin_x_mm: rng.random_range(-3.0..3.0),
                origin_y_mm: rng.random_range(-3.0..3.0),
                ..depthmill_geometry::HeightMapMeta::new(w, h, 0.5)
            };
            let data: Vec<f32> = (0..w * h)
                .map(|_| if rng.random_bool(0.2) { f32::NAN } else { rng.random_range(0.0..6.0) })
                .collect();
            let body = HeightMap::new(meta, data).expect("map");
            let points: Vec<Point3<f32>> = (0..60)
                .map(|_| {
                    Point3::new(
                        rng.random_range(-4.0..10.0),
                        rng.random_range(-4.0..10.0),
                        rng.random_range(-1.0..7.0),
                    )
                })
                .collect();
            // The A faces (rays along Y) and turns about other axes.
            let a = rng.random_range(-90.0f64..=90.0).to_radians();
            let up = if case % 2 == 0 {
                Vector3::new(0.0, -a.sin(), a.cos())
            } else {
                let b = rng.random_range(0.0..std::f64::consts::TAU);
                Vector3::new(a.sin() * b.cos(), a.sin() * b.sin(), a.cos())
            };
            let tol = 0.1;
            let fast = visible_from(&points, &up, &body, tol);
            for (p, seen) in points.iter().zip(&fast) {
                let exact = visible_reference(p.at(), up, &body, tol);
                assert_eq!(*seen, exact, "case {case}: {p:?} up {up:?}");
            }
        }
    }

    /// The height of the cell holding `(x, y)`, NaN off the grid or without data.
    fn height_at(map: &HeightMap, x: f64, y: f64) -> f32 {
        map.cell_of(x, y).and_then(|(c, r)| map.get(c, r)).unwrap_or(f32::NAN)
    }

    #[test]
    fn unseen_cells_are_filled_from_above_and_empty_ones_left_to_cut() {
        let (cloud, table) = plateau_with_band();
        let opts = ReconstructOptions {
            pixel_mm: Some(0.5),
            // Cell edges 0.025 mm off the points' lattice, so no point lies on one.
            margin_mm: Some(1.025),
            fill: Some(FillOptions { max_hole_mm: Some(1.0), ..Default::default() }),
            ..Default::default()
        };
        let out = over_table(cloud.clone(), &table, &opts);
        let map = &out.faces[0].depth_map;
        let at = |x: f64, y: f64| height_at(map, x, y);
        // The unseen band is filled at the plateau's height: the tools leave it.
        assert_eq!(at(11.0, 10.0), 8.0);
        // The hole, where the table shows, and the table around stay empty: cut to the floor.
        assert!(at(5.0, 5.0).is_nan() && at(-3.0, 10.0).is_nan() && at(23.0, 10.0).is_nan());
        // The map covers the free space around the plateau (the table out to 6 mm).
        assert!(map.meta().origin_x_mm <= -5.5, "{:?}", map.meta());
        assert_eq!(out.faces[0].stats.unseen_filled, 4 * 40);
        let cov = &out.faces[0].coverage_map;
        let cov_at = |x: f64, y: f64| cov.cell_of(x, y).and_then(|(c, r)| cov.get(c, r)).unwrap_or(f32::NAN);
        assert_eq!(cov_at(11.0, 10.0), COVERAGE_ASSUMED, "the unseen band is assumed, not measured");
        // The roughing map never dips below the target.
        let rough = out.faces[0].roughing_map.data();
        assert!(map.data().iter().zip(rough).all(|(z, r)| !z.is_finite() || *r >= *z));
        // Without free-space evidence the band is outside what was seen: left empty, as before.
        let plain = reconstruct(Geometry::Cloud(cloud), &opts, &|_, _| {}, &|| false).expect("reconstruct");
        let m = &plain.faces[0].depth_map;
        let v = m.cell_of(11.0, 10.0).and_then(|(c, r)| m.get(c, r)).unwrap_or(f32::NAN);
        assert!(v.is_nan(), "{v}");
        assert_eq!(plain.faces[0].stats.unseen_filled, 0);
    }

    #[test]
    fn the_gap_closing_spares_cells_near_the_part() {
        // A plateau at z = 8 over x < 9 mm; the table (z = 0) seen beyond it, except a notch
        // 9 <= x < 11, 5 <= y < 6 mm that nobody saw (a thin unseen edge between table lines on
        // either side of it). On 0.5 mm cells the closing (radius 2 cells) bridges the notch; the
        // cells of it within that radius of the plateau's data are not taken as empty but
        // lidded, the ones farther out stay empty.
        let (mut part, mut table) = (Vec::new(), Vec::new());
        let step = 0.1;
        for j in 0..(16.0 / step) as i32 {
            for i in 0..(20.0 / step) as i32 {
                let (x, y) = (-2.0 + step * (f64::from(i) + 0.5), -2.0 + step * (f64::from(j) + 0.5));
                if x < 9.0 {
                    part.push(Point3::new(x, y, 8.0));
                } else if !((9.0..11.0).contains(&x) && (5.0..6.0).contains(&y)) {
                    table.push(Point3::new(x, y, 0.0));
                }
            }
        }
        let opts = ReconstructOptions {
            pixel_mm: Some(0.5),
            margin_mm: Some(0.025),
            fill: Some(FillOptions { max_hole_mm: Some(1.0), ..Default::default() }),
            ..Default::default()
        };
        let out = over_table(PointCloud::from_points(part), &table, &opts);
        let map = &out.faces[0].depth_map;
        let at = |x: f64, y: f64| height_at(map, x, y);
        // One and two cells from the plateau: lidded at its height.
        assert_eq!(at(9.25, 5.25), 8.0);
        assert_eq!(at(9.75, 5.75), 8.0);
        // Three and four cells out: bridged by the table on both sides, empty.
        assert!(
            at(10.25, 5.25).is_nan() && at(10.75, 5.75).is_nan(),
            "{} {}",
            at(10.25, 5.25),
            at(10.75, 5.75)
        );
        // The table itself stays empty.
        assert!(at(12.0, 3.0).is_nan());
    }

    #[test]
    fn fill_unseen_matches_a_cell_by_cell_reference() {
        // Random maps: data, free and unseen cells; every unseen cell gets the max over its
        // region's finite neighbours (found here by repeated relaxation), or stays empty.
        let mut rng = StdRng::seed_from_u64(11);
        for _ in 0..50 {
            let (w, h) = (rng.random_range(1..12u32), rng.random_range(1..12u32));
            let n = (w * h) as usize;
            let data: Vec<f32> = (0..n)
                .map(|_| if rng.random_bool(0.4) { rng.random_range(0.0..10.0f32) } else { f32::NAN })
                .collect();
            let free: Vec<bool> = data.iter().map(|z| z.is_nan() && rng.random_bool(0.3)).collect();
            let meta = depthmill_geometry::HeightMapMeta {
                z_min_mm: 0.0,
                z_max_mm: 10.0,
                ..depthmill_geometry::HeightMapMeta::new(w, h, 1.0)
            };
            let mut map = HeightMap::new(meta, data.clone()).expect("map");
            let filled = fill_unseen(&mut map, &free);
            // Reference: label regions by relaxation to the smallest index, then take maxima.
            let unseen: Vec<bool> = (0..n).map(|i| data[i].is_nan() && !free[i]).collect();
            let mut label: Vec<usize> = (0..n).collect();
            let nb = |i: usize| {
                let (r, c) = ((i / w as usize) as i64, (i % w as usize) as i64);
                let mut v = Vec::new();
                for dr in -1..=1i64 {
                    for dc in -1..=1i64 {
                        let (rr, cc) = (r + dr, c + dc);
                        if (dr, dc) != (0, 0) && rr >= 0 && cc >= 0 && rr < h as i64 && cc < w as i64 {
                            v.push(rr as usize * w as usize + cc as usize);
                        }
                    }
                }
                v
            };
            loop {
                let mut changed = false;
                for i in 0..n {
                    for j in nb(i) {
                        if unseen[i] && unseen[j] && label[j] < label[i] {
                            label[i] = label[j];
                            changed = true;
                        }
                    }
                }
                if !changed {
                    break;
                }
            }
            let mut top = vec![f32::NEG_INFINITY; n];
            for i in (0..n).filter(|&i| unseen[i]) {
                for j in nb(i) {
                    if data[j].is_finite() {
                        top[label[i]] = top[label[i]].max(data[j]);
                    }
                }
            }
            let mut count = 0;
            for i in 0..n {
                let want = if unseen[i] && top[label[i]].is_finite() {
                    count += 1;
                    top[label[i]]
                } else {
                    data[i]
                };
                let got = map.data()[i];
                assert!(got == want || (got.is_nan() && want.is_nan()), "cell {i}: {got} vs {want}");
            }
            assert_eq!(filled, count);
        }
    }

    #[test]
    fn close_mask_matches_the_definition() {
        let mut rng = StdRng::seed_from_u64(3);
        for _ in 0..40 {
            let (w, h, k) =
                (rng.random_range(1..15usize), rng.random_range(1..15usize), rng.random_range(0..4usize));
            let m: Vec<bool> = (0..w * h).map(|_| rng.random_bool(0.3)).collect();
            let within = |i: usize, j: usize| {
                let (ri, ci, rj, cj) = (i / w, i % w, j / w, j % w);
                ri.abs_diff(rj) <= k && ci.abs_diff(cj) <= k
            };
            let dil: Vec<bool> = (0..w * h).map(|i| (0..w * h).any(|j| m[j] && within(i, j))).collect();
            let want: Vec<bool> = (0..w * h).map(|i| (0..w * h).all(|j| !within(i, j) || dil[j])).collect();
            assert_eq!(close_mask(&m, w, h, k), want, "{w}x{h} k {k}");
        }
    }
}
