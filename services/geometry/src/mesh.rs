//! [`Mesh`]: an indexed triangle mesh in millimetres.

use nalgebra::{Isometry3, Point3};

use crate::{Aabb, GeometryError};

/// An indexed triangle mesh. Triangles are counter-clockwise seen from outside (the STL and PLY
/// convention); nothing here relies on the winding.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Mesh {
    pub vertices: Vec<Point3<f64>>,
    pub triangles: Vec<[u32; 3]>,
}

impl Mesh {
    /// A mesh from vertices and triangles, checked: every index in range.
    pub fn new(vertices: Vec<Point3<f64>>, triangles: Vec<[u32; 3]>) -> Result<Self, GeometryError> {
        let n = vertices.len();
        if let Some((t, bad)) = triangles
            .iter()
            .enumerate()
            .find_map(|(t, tri)| tri.iter().find(|&&i| i as usize >= n).map(|&i| (t, i)))
        {
            return Err(GeometryError::MeshIndex { triangle: t, index: bad, vertices: n });
        }
        Ok(Mesh { vertices, triangles })
    }

    /// The three corners of triangle `t`.
    pub fn triangle(&self, t: usize) -> [Point3<f64>; 3] {
        let [a, b, c] = self.triangles[t];
        [self.vertices[a as usize], self.vertices[b as usize], self.vertices[c as usize]]
    }

    /// Bounding box of the vertices, `None` for an empty mesh.
    pub fn bounds(&self) -> Option<Aabb> {
        let mut it = self.vertices.iter();
        let first = *it.next()?;
        Some(it.fold(Aabb { min: first, max: first }, |b, p| Aabb { min: b.min.inf(p), max: b.max.sup(p) }))
    }

    /// Multiplies every coordinate by `factor` (a change of units).
    pub fn scale(&mut self, factor: f64) {
        for p in &mut self.vertices {
            p.coords *= factor;
        }
    }

    /// Maps every vertex by `iso`.
    pub fn transform(&mut self, iso: &Isometry3<f64>) {
        for p in &mut self.vertices {
            *p = iso * *p;
        }
    }
}
