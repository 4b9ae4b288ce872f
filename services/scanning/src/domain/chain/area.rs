//! A structured-light area scanner (a camera and a projector on a baseline, as in seed 003's
//! example 3): one shot gives a grid of 3-D points in the scanner's own frame. Simulated by
//! casting the camera's rays at the mesh: a point counts when it lies in the depth window, the
//! projector lights it (not shadowed by the part), both see it within the incidence limit, and
//! its depth carries triangulation noise growing with the square of the distance.

use depthmill_geometry::Mesh;
use nalgebra::{Isometry3, Point3, Vector3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::invalid;
use crate::domain::calibration::CalibrationError;
use crate::domain::scanner::Bvh;

/// The scanner's optics and timing.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct AreaScannerSpec {
    /// Depth window along the camera's axis, mm.
    pub standoff_min_mm: f64,
    pub standoff_max_mm: f64,
    /// Field of view (sensor X, Y) at the reference distance, mm.
    pub field_mm: [f64; 2],
    /// Reference distance (the middle of the window), mm.
    pub reference_mm: f64,
    /// Measuring points across the field (sensor X, Y).
    pub grid: [u32; 2],
    /// Projector offset from the camera along sensor X, mm.
    pub baseline_mm: f64,
    /// Largest angle between a surface's normal and the camera's or the projector's ray, degrees.
    pub incidence_limit_deg: f64,
    /// Depth noise (1 sigma) at the reference distance, mm; it grows with the distance squared.
    pub noise_sigma_mm: f64,
    /// Time of one shot (the fringe sequence), s.
    pub exposure_s: f64,
}

impl Default for AreaScannerSpec {
    /// A compact fringe-projection sensor that fits a tool holder: 50 x 40 mm at 120 mm, 12 um.
    fn default() -> Self {
        Self {
            standoff_min_mm: 80.0,
            standoff_max_mm: 160.0,
            field_mm: [50.0, 40.0],
            reference_mm: 120.0,
            grid: [200, 160],
            baseline_mm: 50.0,
            incidence_limit_deg: 65.0,
            noise_sigma_mm: 0.012,
            exposure_s: 0.4,
        }
    }
}

impl AreaScannerSpec {
    pub fn validate(&self) -> Result<(), CalibrationError> {
        let positive = [
            ("standoff_min_mm", self.standoff_min_mm),
            ("reference_mm", self.reference_mm),
            ("field_mm[0]", self.field_mm[0]),
            ("field_mm[1]", self.field_mm[1]),
            ("exposure_s", self.exposure_s),
        ];
        for (field, v) in positive {
            if !(v.is_finite() && v > 0.0) {
                return Err(invalid(field, v, "a positive number"));
            }
        }
        if !(self.standoff_max_mm.is_finite() && self.standoff_max_mm > self.standoff_min_mm) {
            return Err(invalid("standoff_max_mm", self.standoff_max_mm, "finite, above standoff_min_mm"));
        }
        if self.grid.iter().any(|&g| !(2..=2000).contains(&g)) {
            return Err(invalid("grid", format!("{:?}", self.grid), "2 to 2000 points each way"));
        }
        if !(self.baseline_mm.is_finite() && self.baseline_mm >= 0.0) {
            return Err(invalid("baseline_mm", self.baseline_mm, "mm >= 0"));
        }
        if !(self.incidence_limit_deg > 0.0 && self.incidence_limit_deg < 90.0) {
            return Err(invalid("incidence_limit_deg", self.incidence_limit_deg, "between 0 and 90 degrees"));
        }
        if !(self.noise_sigma_mm.is_finite() && self.noise_sigma_mm >= 0.0) {
            return Err(invalid("noise_sigma_mm", self.noise_sigma_mm, "mm >= 0"));
        }
        Ok(())
    }

    /// The field's size at distance `z`, mm.
    pub fn field_at(&self, z: f64) -> [f64; 2] {
        self.field_mm.map(|f| f * z / self.reference_mm)
    }
}

/// One shot: points in the scanner's frame and, for checks, where they truly are.
#[derive(Debug, Clone, Default)]
pub struct Shot {
    pub points: Vec<Point3<f64>>,
    /// The exact surface point each came from, in the mesh's frame (the simulation's truth).
    pub truth: Vec<Point3<f64>>,
}

/// The simulated area scanner looking at one mesh.
#[derive(Debug, Clone)]
pub struct AreaScanner {
    spec: AreaScannerSpec,
    bvh: Bvh,
    seed: u64,
}

impl AreaScanner {
    pub fn new(spec: AreaScannerSpec, mesh: &Mesh, seed: u64) -> Result<Self, CalibrationError> {
        spec.validate()?;
        let bvh = Bvh::build(mesh).map_err(|e| CalibrationError::Scan(e.to_string()))?;
        Ok(Self { spec, bvh, seed })
    }

    pub fn spec(&self) -> &AreaScannerSpec {
        &self.spec
    }

    /// Takes shot number `shot` with the scanner at `mesh_from_sensor`. The noise is a function
    /// of (seed, shot, ray), so a shot replays exactly.
    pub fn shot(&self, mesh_from_sensor: &Isometry3<f64>, shot: u64) -> Shot {
        let s = &self.spec;
        let [nx, ny] = s.grid.map(|g| g as usize);
        let half = s.field_mm.map(|f| 0.5 * f / s.reference_mm);
        let cos_limit = s.incidence_limit_deg.to_radians().cos();
        let camera = mesh_from_sensor * Point3::origin();
        let projector = mesh_from_sensor * Point3::new(s.baseline_mm, 0.0, 0.0);
        let hits: Vec<Option<(Point3<f64>, Point3<f64>)>> = (0..nx * ny)
            .into_par_iter()
            .map(|k| {
                let (i, j) = (k % nx, k / nx);
                let tx = -half[0] + 2.0 * half[0] * i as f64 / (nx - 1) as f64;
                let ty = -half[1] + 2.0 * half[1] * j as f64 / (ny - 1) as f64;
                let d = Vector3::new(tx, ty, 1.0).normalize();
                let dw = mesh_from_sensor.rotation * d;
                let hit = self.bvh.cast(&camera, &dw, s.standoff_max_mm / d.z)?;
                let depth = hit.t * d.z;
                if depth < s.standoff_min_mm {
                    return None;
                }
                // Facing the camera within the limit (back faces are not seen).
                if -dw.dot(&hit.normal) < cos_limit {
                    return None;
                }
                let p = camera + dw * hit.t;
                let to_proj = projector - p;
                let dist = to_proj.norm();
                if dist <= 0.0
                    || to_proj.dot(&hit.normal) / dist < cos_limit
                    || self.bvh.occluded(&p, &projector)
                {
                    return None;
                }
                let sigma = s.noise_sigma_mm * (depth / s.reference_mm).powi(2);
                let t = hit.t + sigma * hash_gauss(self.seed, shot, k as u64);
                Some((Point3::from(d * t), p))
            })
            .collect();
        let mut out = Shot::default();
        for (p, q) in hits.into_iter().flatten() {
            out.points.push(p);
            out.truth.push(q);
        }
        out
    }
}

fn mix(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// A standard normal variate from the hash of `(seed, shot, k)` (Box-Muller on two uniforms).
fn hash_gauss(seed: u64, shot: u64, k: u64) -> f64 {
    let h = mix(seed ^ mix(shot.wrapping_add(0x9E37_79B9_7F4A_7C15) ^ mix(k)));
    let h2 = mix(h.wrapping_add(0x9E37_79B9_7F4A_7C15));
    let u1 = ((h >> 11) as f64 + 1.0) / (1u64 << 53) as f64;
    let u2 = (h2 >> 11) as f64 / (1u64 << 53) as f64;
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}

#[cfg(test)]
pub(crate) fn gauss_for_test(seed: u64, shot: u64, k: u64) -> f64 {
    hash_gauss(seed, shot, k)
}
