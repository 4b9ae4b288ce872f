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

    /// A closed box `[0, x] × [0, y] × [0, z]`, 8 vertices and 12 triangles wound outward.
    pub fn cuboid(x: f64, y: f64, z: f64) -> Self {
        let vertices = (0..8)
            .map(|k| {
                Point3::new(
                    if k & 1 == 0 { 0.0 } else { x },
                    if k & 2 == 0 { 0.0 } else { y },
                    if k & 4 == 0 { 0.0 } else { z },
                )
            })
            .collect();
        let triangles = vec![
            [0, 2, 1],
            [1, 2, 3],
            [4, 5, 6],
            [5, 7, 6],
            [0, 1, 4],
            [1, 5, 4],
            [2, 6, 3],
            [3, 6, 7],
            [0, 4, 2],
            [2, 4, 6],
            [1, 3, 5],
            [3, 7, 5],
        ];
        Mesh { vertices, triangles }
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_cuboid_is_closed_and_wound_outward() {
        let m = Mesh::cuboid(2.0, 3.0, 5.0);
        // Every directed edge once, its reverse once: closed and consistently wound.
        let mut edges = std::collections::BTreeMap::new();
        for t in &m.triangles {
            for k in 0..3 {
                *edges.entry((t[k], t[(k + 1) % 3])).or_insert(0) += 1;
            }
        }
        assert!(edges.iter().all(|(&(a, b), &n)| n == 1 && edges.get(&(b, a)) == Some(&1)));
        // Outward: the signed volume is the box's.
        let vol: f64 = (0..m.triangles.len())
            .map(|t| {
                let [a, b, c] = m.triangle(t);
                a.coords.dot(&b.coords.cross(&c.coords)) / 6.0
            })
            .sum();
        assert!((vol - 30.0).abs() < 1e-9, "{vol}");
    }
}
