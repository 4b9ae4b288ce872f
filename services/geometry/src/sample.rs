//! The sample part of `depthmill demo` and the end-to-end tests: a closed relief 80 × 60 mm,
//! generated, so the repository ships no binary model.
//!
//! On an 8 mm plate with sharp vertical edges: a rounded dome (3.5 mm, cos² profile), a hip roof
//! with a sharp crest and sharp hips (3 mm, 18° flanks), a round boss with a filleted top edge,
//! and four small blind holes (Ø1.2 mm, 5 mm deep) the scanner cannot see to the bottom of. The
//! top is a height field sampled every `step_mm`, so every face is undercut-free; flanks stay
//! under about 20° so a sensor looking straight down sees them within its 25° incidence limit.

use crate::Mesh;
use nalgebra::Point3;

/// Header of the sample's STL file.
pub const STL_HEADER: &str = "depthmill sample relief";

/// Footprint half sizes, mm.
pub const HALF_X_MM: f64 = 40.0;
pub const HALF_Y_MM: f64 = 30.0;
/// Plate thickness, mm.
pub const PLATE_MM: f64 = 8.0;
/// Blind holes: centres (x, y), mm.
pub const HOLES: [(f64, f64); 4] = [(-32.0, -22.0), (-8.0, -23.0), (8.0, 23.0), (32.0, 22.0)];
/// Hole radius and depth, mm.
pub const HOLE_RADIUS_MM: f64 = 0.6;
pub const HOLE_DEPTH_MM: f64 = 5.0;

/// Height of the sample's top at (x, y), mm (the plate's bottom is z = 0).
pub fn sample_height(x: f64, y: f64) -> f64 {
    let mut z = PLATE_MM;
    // Dome: cos² bump, radius 15, height 3.5 (max slope 3.5·π/30 = 0.37, 20°).
    let r = (x + 20.0).hypot(y - 5.0);
    if r < 15.0 {
        let c = (std::f64::consts::FRAC_PI_2 * r / 15.0).cos();
        z += 3.5 * c * c;
    }
    // Hip roof: crest along Y at x = 18, flanks of slope 1/3.
    let roof = (3.0 - (x - 18.0).abs() / 3.0).min((20.0 - y.abs()) / 3.0);
    if roof > 0.0 {
        z += roof.min(3.0);
    }
    // Boss at (-20, -19): flat top 2 mm up to r = 4.5, a 1.5 mm fillet to r = 6.
    let rb = (x + 20.0).hypot(y + 19.0);
    if rb < 6.0 {
        z += if rb <= 4.5 {
            2.0
        } else {
            let u = (rb - 4.5) / 1.5;
            0.5 + 1.5 * (1.0 - u * u).max(0.0).sqrt()
        };
    }
    for (hx, hy) in HOLES {
        if (x - hx).hypot(y - hy) < HOLE_RADIUS_MM {
            return z - HOLE_DEPTH_MM;
        }
    }
    z
}

/// The sample as a closed triangle mesh (outward normals), top sampled every `step_mm`
/// (0.25 mm gives about 157 000 triangles).
pub fn sample_relief(step_mm: f64) -> Mesh {
    let step = if step_mm.is_finite() && step_mm >= 0.05 { step_mm } else { 0.25 };
    let nx = (2.0 * HALF_X_MM / step).round() as usize + 1;
    let ny = (2.0 * HALF_Y_MM / step).round() as usize + 1;
    let mut vertices = Vec::with_capacity(nx * ny + 2 * (nx + ny) + 1);
    for j in 0..ny {
        for i in 0..nx {
            let x = -HALF_X_MM + 2.0 * HALF_X_MM * i as f64 / (nx - 1) as f64;
            let y = -HALF_Y_MM + 2.0 * HALF_Y_MM * j as f64 / (ny - 1) as f64;
            vertices.push(Point3::new(x, y, sample_height(x, y)));
        }
    }
    let top = |i: usize, j: usize| (j * nx + i) as u32;
    let mut triangles = Vec::with_capacity(2 * (nx - 1) * (ny - 1) + 6 * (nx + ny));
    for j in 0..ny - 1 {
        for i in 0..nx - 1 {
            let (a, b, c, d) = (top(i, j), top(i + 1, j), top(i, j + 1), top(i + 1, j + 1));
            triangles.push([a, b, d]);
            triangles.push([a, d, c]);
        }
    }
    // The perimeter counter-clockwise seen from above, as top-vertex indices.
    let mut ring: Vec<u32> = Vec::with_capacity(2 * (nx + ny));
    ring.extend((0..nx - 1).map(|i| top(i, 0)));
    ring.extend((0..ny - 1).map(|j| top(nx - 1, j)));
    ring.extend((1..nx).rev().map(|i| top(i, ny - 1)));
    ring.extend((1..ny).rev().map(|j| top(0, j)));
    // Bottom copies of the ring at z = 0, and a centre for the bottom fan.
    let base = vertices.len() as u32;
    for &k in &ring {
        let p = vertices[k as usize];
        vertices.push(Point3::new(p.x, p.y, 0.0));
    }
    let centre = vertices.len() as u32;
    vertices.push(Point3::new(0.0, 0.0, 0.0));
    let n = ring.len();
    for s in 0..n {
        let t = (s + 1) % n;
        let (ta, tb) = (ring[s], ring[t]);
        let (ba, bb) = (base + s as u32, base + t as u32);
        // Wall quad, outward: the ring runs counter-clockwise, so outward is to its right.
        triangles.push([ba, bb, tb]);
        triangles.push([ba, tb, ta]);
        // Bottom, facing down.
        triangles.push([centre, bb, ba]);
    }
    Mesh { vertices, triangles }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use crate::formats::{Geometry, read_any_from, write_stl};
    use std::collections::HashMap;

    #[test]
    fn the_sample_is_closed_and_oriented_outward() {
        let m = sample_relief(1.0);
        // Every edge is used exactly twice, once in each direction: closed and consistently oriented.
        let mut edges: HashMap<(u32, u32), i32> = HashMap::new();
        for t in &m.triangles {
            for k in 0..3 {
                let (a, b) = (t[k], t[(k + 1) % 3]);
                *edges.entry((a.min(b), a.max(b))).or_default() += if a < b { 1 } else { -1 };
            }
        }
        assert!(edges.values().all(|&v| v == 0), "open or inconsistently oriented edges");
        // Positive signed volume (outward normals), close to the plate plus the features.
        let vol: f64 = m
            .triangles
            .iter()
            .map(|t| {
                let [a, b, c] = t.map(|i| m.vertices[i as usize].coords);
                a.dot(&b.cross(&c)) / 6.0
            })
            .sum();
        let plate = 80.0 * 60.0 * PLATE_MM;
        assert!(vol > plate && vol < plate * 1.1, "volume {vol}");
    }

    #[test]
    fn features_are_where_the_doc_says() {
        assert_eq!(sample_height(39.0, 29.0), PLATE_MM);
        assert!((sample_height(-20.0, 5.0) - (PLATE_MM + 3.5)).abs() < 1e-12);
        assert!((sample_height(18.0, 0.0) - (PLATE_MM + 3.0)).abs() < 1e-12);
        assert!((sample_height(-20.0, -19.0) - (PLATE_MM + 2.0)).abs() < 1e-12);
        assert!((sample_height(-32.0, -22.0) - (PLATE_MM - HOLE_DEPTH_MM)).abs() < 1e-12);
    }

    #[test]
    fn stl_round_trips_through_the_reader() {
        let m = sample_relief(2.0);
        let mut bytes = Vec::new();
        write_stl(&mut bytes, &m, STL_HEADER).unwrap();
        let (g, _) = read_any_from(
            std::io::Cursor::new(&bytes),
            "sample.stl",
            Some(bytes.len() as u64),
            &Default::default(),
        )
        .unwrap();
        let Geometry::Mesh(r) = g else { panic!("not a mesh") };
        assert_eq!(r.triangles.len(), m.triangles.len());
    }
}
