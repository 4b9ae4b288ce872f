//! [`PointCloud`]: points in millimetres with optional per-point intensity and normals, and
//! [`CloudPoint`], what the rasterisers and filters read a point through.

use nalgebra::{Isometry3, Point3, Vector3};
use serde::{Deserialize, Serialize};

use crate::error::{GeometryError, Result};

/// An axis-aligned box, `min <= max` componentwise.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Aabb {
    pub min: Point3<f64>,
    pub max: Point3<f64>,
}

impl Aabb {
    /// `max − min`.
    pub fn extent(&self) -> Vector3<f64> {
        self.max - self.min
    }

    /// True when `p` lies inside or on the box.
    pub fn contains(&self, p: &Point3<f64>) -> bool {
        (0..3).all(|i| p[i] >= self.min[i] && p[i] <= self.max[i])
    }
}

/// A point the rasterisers, ROIs and filters can read: stored in single or double precision,
/// always read as `f64` (exactly: every `f32` is an `f64`).
pub trait CloudPoint: Copy + Send + Sync {
    /// The point in double precision.
    fn at(&self) -> Point3<f64>;
}

impl CloudPoint for Point3<f64> {
    #[inline(always)]
    fn at(&self) -> Point3<f64> {
        *self
    }
}

impl CloudPoint for Point3<f32> {
    #[inline(always)]
    fn at(&self) -> Point3<f64> {
        Point3::new(f64::from(self.x), f64::from(self.y), f64::from(self.z))
    }
}

/// A point in double precision rounded to the cloud's single precision (to nearest; beyond
/// `f32`'s range a coordinate becomes infinite, and the point is then not finite).
#[inline]
pub fn single(p: &Point3<f64>) -> Point3<f32> {
    Point3::new(p.x as f32, p.y as f32, p.z as f32)
}

/// The scanner's free-space artifact is a PLY cloud whose points carry this `ushort` property
/// ([`crate::formats::write_ply_labelled`]): [`FREE_KIND_TABLE`] or [`FREE_KIND_SHADOWED`].
pub const FREE_KIND: &str = "kind";
/// A table point the scanner saw with nothing over it: no part there.
pub const FREE_KIND_TABLE: u16 = 0;
/// A point of the scanned cloud whose vertical the scanner did not show clear under a wall or
/// an overhang's edge beside it: in a top view it may lie under material nobody saw.
pub const FREE_KIND_SHADOWED: u16 = 1;

/// A point cloud in millimetres, in whatever frame its producer documents.
///
/// Points are stored in single precision (`f32`: 24 bits of mantissa, under 0.031 µm of
/// rounding for coordinates within ±1 m; the scanner's noise is about a thousand times that),
/// like the float PLY files clouds come in, so a cloud takes no more memory than its file; all
/// arithmetic on them is done in `f64` ([`CloudPoint::at`]).
///
/// `intensity` and `normals`, when present, run parallel to `points` (same length; checked by
/// [`PointCloud::new`] and [`PointCloud::validate`]). Normals are unit vectors or zero (unknown).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct PointCloud {
    pub points: Vec<Point3<f32>>,
    pub intensity: Option<Vec<f32>>,
    pub normals: Option<Vec<Vector3<f32>>>,
}

impl PointCloud {
    /// A cloud with the given arrays, validated for equal lengths.
    pub fn new(
        points: Vec<Point3<f32>>,
        intensity: Option<Vec<f32>>,
        normals: Option<Vec<Vector3<f32>>>,
    ) -> Result<Self> {
        let cloud = PointCloud { points, intensity, normals };
        cloud.validate()?;
        Ok(cloud)
    }

    /// A cloud of bare points given in double precision (rounded, see [`single`]).
    pub fn from_points(points: impl IntoIterator<Item = Point3<f64>>) -> Self {
        PointCloud {
            points: points.into_iter().map(|p| single(&p)).collect(),
            intensity: None,
            normals: None,
        }
    }

    /// Checks that the parallel arrays have one entry per point.
    pub fn validate(&self) -> Result<()> {
        let points = self.points.len();
        if let Some(len) = self.intensity.as_ref().map(Vec::len).filter(|&l| l != points) {
            return Err(GeometryError::ParallelLength { field: "intensity", len, points });
        }
        if let Some(len) = self.normals.as_ref().map(Vec::len).filter(|&l| l != points) {
            return Err(GeometryError::ParallelLength { field: "normals", len, points });
        }
        Ok(())
    }

    pub fn len(&self) -> usize {
        self.points.len()
    }

    pub fn is_empty(&self) -> bool {
        self.points.is_empty()
    }

    /// The points in double precision.
    pub fn points_f64(&self) -> Vec<Point3<f64>> {
        self.points.iter().map(CloudPoint::at).collect()
    }

    /// Bounding box of the points with all-finite coordinates, or `None` if there are none.
    pub fn bounds(&self) -> Option<Aabb> {
        let mut it =
            self.points.iter().map(CloudPoint::at).filter(|p| p.coords.iter().all(|c| c.is_finite()));
        let first = it.next()?;
        Some(it.fold(Aabb { min: first, max: first }, |b, p| Aabb { min: b.min.inf(&p), max: b.max.sup(&p) }))
    }

    /// Multiplies every coordinate by `factor` (a change of units; computed in `f64`, then
    /// rounded); normals are unchanged.
    pub fn scale(&mut self, factor: f64) {
        for p in &mut self.points {
            *p = single(&(p.at() * factor));
        }
    }

    /// Maps every point by `iso` (`p ↦ iso · p`, computed in `f64`, then rounded) and rotates the
    /// normals by its rotation, in place. Use it to change frames: with `iso = b_from_a`, a cloud
    /// in frame `a` ends up in frame `b`.
    pub fn transform(&mut self, iso: &Isometry3<f64>) {
        for p in &mut self.points {
            *p = single(&(iso * p.at()));
        }
        if let Some(normals) = &mut self.normals {
            let rot = iso.rotation.to_rotation_matrix().matrix().cast::<f32>();
            for n in normals {
                *n = rot * *n;
            }
        }
    }

    /// Appends `other`'s points; a parallel array survives only if both clouds have it.
    pub fn extend(&mut self, other: PointCloud) {
        self.intensity = match (self.intensity.take(), other.intensity) {
            (Some(mut a), Some(b)) => {
                a.extend(b);
                Some(a)
            }
            _ => None,
        };
        self.normals = match (self.normals.take(), other.normals) {
            (Some(mut a), Some(b)) => {
                a.extend(b);
                Some(a)
            }
            _ => None,
        };
        self.points.extend(other.points);
    }
}

#[cfg(test)]
mod tests {
    use std::f64::consts::FRAC_PI_2;

    use nalgebra::{Translation3, UnitQuaternion};

    use super::*;

    #[test]
    fn validate_parallel_lengths() {
        let pts = vec![Point3::origin(), Point3::new(1.0f32, 2.0, 3.0)];
        assert!(PointCloud::new(pts.clone(), Some(vec![1.0, 2.0]), None).is_ok());
        let e = PointCloud::new(pts.clone(), None, Some(vec![Vector3::z()])).expect_err("normals");
        assert_eq!(e.to_string(), "point cloud normals has 1 entries but the cloud has 2 points");
        let e = PointCloud::new(pts, Some(vec![]), None).expect_err("intensity");
        assert!(e.to_string().contains("intensity has 0 entries"));
    }

    #[test]
    fn bounds_and_transform() {
        let mut cloud = PointCloud::new(
            vec![Point3::new(1.0, 0.0, 0.0), Point3::new(0.0, 2.0, -1.0), Point3::new(f32::NAN, 0.0, 0.0)],
            None,
            Some(vec![Vector3::x(), Vector3::y(), Vector3::z()]),
        )
        .expect("valid");
        let b = cloud.bounds().expect("bounds");
        assert_eq!((b.min, b.max), (Point3::new(0.0, 0.0, -1.0), Point3::new(1.0, 2.0, 0.0)));
        assert!(b.contains(&Point3::new(0.5, 1.0, -0.5)));
        // Quarter turn about Z then shift by (10, 0, 0): x ↦ y.
        let iso = Isometry3::from_parts(
            Translation3::new(10.0, 0.0, 0.0),
            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), FRAC_PI_2),
        );
        cloud.transform(&iso);
        assert!((cloud.points[0].at() - Point3::new(10.0, 1.0, 0.0)).norm() < 1e-6);
        assert!((cloud.points[1].at() - Point3::new(8.0, 0.0, -1.0)).norm() < 1e-6);
        let n = cloud.normals.as_ref().expect("normals");
        assert!((n[0] - Vector3::y()).norm() < 1e-6 && (n[1] + Vector3::x()).norm() < 1e-6);
        assert_eq!(PointCloud::default().bounds(), None);
    }
}
