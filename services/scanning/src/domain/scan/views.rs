//! Which rescan passes see which unseen cells, predicted on the part's nominal mesh.
//!
//! The first scan's coverage map says where the cloud has nothing (its enclosed holes and the
//! unseen part of the mesh's top-view silhouette). Whether a candidate pass would fill such a cell
//! is a question about the part, which the job's mesh answers: the cell's surface point is the
//! mesh's top surface there, and the pass sees it when the scanner's own acceptance rules hold on
//! the mesh (the point in the measuring window and under the fan, the laser's ray reaching it
//! first, the incidence limit, the camera on the lit side with a clear line of sight). The same
//! rules as the scanner's model (`super::super::scanner`), applied to the nominal part and a
//! planned pose instead of the part on the table and a measured one, so the rescan's view
//! choice is what an inspection planner does with a CAD model: it aims the passes at what was
//! actually missed and keeps only the views predicted to fill it.

use nalgebra::{Isometry3, Point3, Vector3};

use crate::domain::scanner::{Bvh, ScannerSpec};
use depthmill_geometry::Mesh;

/// Most unseen cells the prediction looks at; a larger set is thinned evenly.
pub const MAX_CELLS: usize = 6000;

/// Slack on the measuring window and the fan's edge when predicting, mm: the pose the pass will
/// take differs from the planned one by the robot's path deviation.
const EDGE_SLACK_MM: f64 = 1.0;

/// Every how many of `n` unseen cells [`ViewModel::surface`] keeps one.
pub fn thinning(n: usize) -> usize {
    n.div_ceil(MAX_CELLS).max(1)
}

/// A surface point on the nominal mesh (part frame) and its normal, turned up.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SurfacePoint {
    pub point: Point3<f64>,
    pub normal: Vector3<f64>,
}

/// An unseen cell: the mesh's top surface at its centre and at the centres of its four quarters
/// (a cell is filled by any point that lands in it).
#[derive(Debug, Clone, PartialEq)]
pub struct UnseenCell {
    pub samples: Vec<SurfacePoint>,
}

/// The nominal part for view prediction.
pub struct ViewModel {
    bvh: Bvh,
    spec: ScannerSpec,
    /// Height above which a downward ray starts, mm (part frame).
    top_z: f64,
    cos_limit: f64,
}

impl ViewModel {
    /// `None` for a mesh the ray caster refuses or without a finite extent.
    pub fn new(mesh: &Mesh, spec: &ScannerSpec) -> Option<Self> {
        let b = mesh.bounds()?;
        let bvh = Bvh::build(mesh).ok()?;
        Some(Self {
            bvh,
            spec: spec.clone(),
            top_z: b.max.z + 1.0,
            cos_limit: spec.incidence_limit_deg.to_radians().cos(),
        })
    }

    /// The mesh's top surface in each cell of side `pixel_mm` centred on `(x, y)` (part frame);
    /// cells over no surface are left out. At most [`MAX_CELLS`], thinned evenly.
    pub fn surface(&self, cells: &[[f64; 2]], pixel_mm: f64) -> Vec<UnseenCell> {
        let stride = thinning(cells.len());
        let q = 0.25 * pixel_mm;
        cells
            .iter()
            .step_by(stride)
            .filter_map(|&[x, y]| {
                let samples: Vec<SurfacePoint> = [(0.0, 0.0), (-q, -q), (q, -q), (-q, q), (q, q)]
                    .iter()
                    .filter_map(|&(dx, dy)| {
                        let o = Point3::new(x + dx, y + dy, self.top_z);
                        let hit = self.bvh.cast(&o, &-Vector3::z(), f64::INFINITY)?;
                        let n = if hit.normal.z < 0.0 { -hit.normal } else { hit.normal };
                        Some(SurfacePoint { point: o - Vector3::z() * hit.t, normal: n })
                    })
                    .collect();
                (!samples.is_empty()).then_some(UnseenCell { samples })
            })
            .collect()
    }

    /// Whether a straight pass of the sensor from `s0` to `s1` (`part_from_sensor`, one
    /// orientation) would measure `cell`: the laser plane sweeps over it during the pass, and the
    /// scanner's model accepts the spot (module doc).
    pub fn sees(&self, s0: &Isometry3<f64>, s1: &Isometry3<f64>, cell: &UnseenCell) -> bool {
        cell.samples.iter().any(|p| self.sees_point(s0, s1, p))
    }

    fn sees_point(&self, s0: &Isometry3<f64>, s1: &Isometry3<f64>, cell: &SurfacePoint) -> bool {
        let y = s0.rotation * Vector3::y();
        let p = cell.point;
        // Where along the pass the laser plane (the sensor's XZ plane) contains the point.
        let (o0, o1) = (s0.translation.vector, s1.translation.vector);
        let (d0, run) = ((p.coords - o0).dot(&y), (o1 - o0).dot(&y));
        let u = if run.abs() < 1e-9 {
            if d0.abs() > EDGE_SLACK_MM {
                return false;
            }
            0.0
        } else {
            let reach = EDGE_SLACK_MM / run.abs();
            let u = d0 / run;
            if !(-reach..=1.0 + reach).contains(&u) {
                return false;
            }
            u.clamp(0.0, 1.0)
        };
        let sensor = Isometry3::from_parts((o0 + (o1 - o0) * u).into(), s0.rotation);
        let q = sensor.inverse_transform_point(&p);
        let spec = &self.spec;
        if q.z < spec.standoff_min_mm - EDGE_SLACK_MM || q.z > spec.standoff_max_mm + EDGE_SLACK_MM {
            return false;
        }
        let z0 = spec.apex_z_mm();
        if q.x.abs() > (q.z - z0) * spec.fan_half_tan() + EDGE_SLACK_MM {
            return false;
        }
        let apex = sensor * Point3::new(0.0, 0.0, z0);
        let camera = sensor * Point3::new(0.0, spec.camera_baseline_mm, 0.0);
        let ray = p - apex;
        let len = ray.norm();
        if !(len.is_finite() && len > 0.0) {
            return false;
        }
        let d = ray / len;
        let n = cell.normal;
        if n.dot(&d).abs() < self.cos_limit {
            return false;
        }
        if n.dot(&(apex - p)) * n.dot(&(camera - p)) <= 0.0 {
            return false;
        }
        // The laser reaches the spot first (a hit short of it by more than a hair is an occluder),
        // and the camera sees it.
        let first = self.bvh.cast(&apex, &d, len + 1.0).map_or(len, |h| h.t);
        first >= len - 0.05 && !self.bvh.occluded(&p, &camera)
    }
}
