//! Measuring the simulated part: distances to its surface and its surface as a closed mesh.
//!
//! # Distances
//!
//! The part's surface is where the dexels end: every interval end of every grid is a surface
//! sample, standing for the cell-sized square of its ray. [`DexelStock::surface_distance`] is the
//! distance from a point to the nearest such square (searched ring by ring around the point's
//! own ray, stopping once a ring cannot be nearer): exact for a surface across a grid's rays (a
//! face seen along a grid axis) and a lower bound within half a cell's diagonal elsewhere.
//!
//! # Deviations
//!
//! [`DexelStock::deviation_at`] measures a point against the surface between the rays. The
//! nearest dexel end alone reads a point on a slope of angle θ (against a grid's plane) up to
//! `tan θ` times half a cell off, either way: a stock cut exactly to a 38° slope on 0.1 mm cells
//! would show 0.039 mm gouges and leftovers. So each grid interpolates, bilinearly between the four
//! rays around the point, the end nearest the point on each ray; where the four ends face the same
//! way and no two neighbours differ by more than [`LOCAL_MAX_SLOPE`] times the cell, the distance
//! to that local surface (the distance along the ray times the cosine of its slope) is exact on
//! any plane. The grid that sees the surface flattest measures it. A point farther than
//! [`LOCAL_MAX_CELLS`] cells from that surface, or without such a stencil on any grid (at a wall
//! or edge between rays, a thin feature, the stock's border), is measured as above: the nearest
//! end's distance, signed as in [`DexelStock::inside`] (positive in material, material left over
//! on a surface that should be there; negative out of it, a gouge).
//!
//! # Mesh
//!
//! [`DexelStock::surface_mesh`] samples a signed distance on a regular lattice (negative in
//! material: the smallest distance along any grid's ray through the sample to where that ray's
//! material starts or ends, signed by that ray) and extracts its zero level
//! with Naive Surface Nets (the `fast-surface-nets` crate). Surface Nets is dual: one vertex per
//! lattice cube the surface crosses, one quad per lattice edge with a sign change, so on a
//! lattice whose outer layer lies outside the material every edge of the mesh is shared by an
//! even number of faces with opposite directions (closed and consistently oriented: watertight
//! as STL needs it), without the ambiguous cases and case tables of marching cubes. Its vertices
//! sit inside the cubes, so sharp edges are rounded within one lattice step; dual contouring
//! would keep them but needs surface normals the dexels do not hold across their rays.

use depthmill_geometry::Mesh;
use fast_surface_nets::ndshape::{RuntimeShape, Shape};
use fast_surface_nets::{SurfaceNetsBuffer, surface_nets};
use nalgebra::Point3;
use rayon::prelude::*;

use super::{DexelError, DexelStock, Grid, plane_axes};

/// Most lattice samples [`DexelStock::surface_mesh`] takes (2^24: 64 MiB of distances).
pub const MAX_SURFACE_SAMPLES: u64 = 1 << 24;

/// Steepest local surface a grid interpolates, rise over run between neighbouring rays (tan 60°;
/// a surface leaning more than 54.7° from every grid's plane does not exist, so one of three grids
/// always sees a smooth surface within it).
pub const LOCAL_MAX_SLOPE: f64 = 1.732_050_807_568_877_2;
/// Farthest a point may lie from the interpolated surface, in the grid's cells, to be measured on
/// it: nearer, the cell's size is what the nearest end gets wrong; farther, the nearest part of the
/// surface may be another one.
pub const LOCAL_MAX_CELLS: f64 = 2.0;

impl Grid {
    /// The signed distance from `p` to the surface interpolated between the four rays around it
    /// (positive in material), and that surface's squared slope against the grid's plane; `None`
    /// where there is no such surface (see the module docs).
    pub(super) fn local(&self, p: &Point3<f64>) -> Option<(f64, f64)> {
        let (a, b) = plane_axes(self.axis);
        let u = (p[a] - self.origin[0]) / self.cell - 0.5;
        let v = (p[b] - self.origin[1]) / self.cell - 0.5;
        let (i0, j0) = (u.floor(), v.floor());
        // NaN fails the comparisons.
        if !(i0 >= 0.0 && j0 >= 0.0 && i0 + 1.0 < self.n[0] as f64 && j0 + 1.0 < self.n[1] as f64) {
            return None;
        }
        let (i, j) = (i0 as usize, j0 as usize);
        let t = p[self.axis];
        // The end nearest `t` on each ray, and which way its material lies: +1 below it (the
        // interval's upper end), -1 above it.
        let mut ends = [0.0f64; 4];
        let mut facing = 0.0f64;
        for (k, (di, dj)) in [(0, 0), (1, 0), (0, 1), (1, 1)].into_iter().enumerate() {
            let ray = &self.rays[(j + dj) * self.n[0] + i + di];
            let (end, side) = ray
                .iter()
                .flat_map(|s| [(f64::from(s[0]), -1.0), (f64::from(s[1]), 1.0)])
                .min_by(|x, y| (x.0 - t).abs().total_cmp(&(y.0 - t).abs()))?;
            if k > 0 && side != facing {
                return None;
            }
            facing = side;
            ends[k] = end;
        }
        let [e00, e10, e01, e11] = ends;
        let rise = LOCAL_MAX_SLOPE * self.cell;
        if [e10 - e00, e11 - e01, e01 - e00, e11 - e10].iter().any(|d| d.abs() > rise) {
            return None;
        }
        let (s, w) = (u - i0, v - j0);
        let h = (e00 * (1.0 - s) + e10 * s) * (1.0 - w) + (e01 * (1.0 - s) + e11 * s) * w;
        let ga = ((e10 - e00) * (1.0 - w) + (e11 - e01) * w) / self.cell;
        let gb = ((e01 - e00) * (1.0 - s) + (e11 - e10) * s) / self.cell;
        let slope2 = ga * ga + gb * gb;
        let d = facing * (h - t) / (1.0 + slope2).sqrt();
        (d.abs() <= LOCAL_MAX_CELLS * self.cell).then_some((d, slope2))
    }

    /// Distance from `x` to the interval `[lo, lo + cell]` (0 inside).
    fn gap(x: f64, lo: f64, cell: f64) -> f64 {
        if x < lo {
            lo - x
        } else if x > lo + cell {
            x - lo - cell
        } else {
            0.0
        }
    }

    /// Lowers `best` (squared) to the squared distance from `p` to the nearest dexel end of this
    /// grid within `max_mm`, each end taken as the square of its ray's cell.
    fn nearest_end(&self, p: &Point3<f64>, best: &mut f64, max_mm: f64) {
        let (a, b) = plane_axes(self.axis);
        let i0 = ((p[a] - self.origin[0]) / self.cell).floor();
        let j0 = ((p[b] - self.origin[1]) / self.cell).floor();
        if !(i0.is_finite() && j0.is_finite()) {
            return;
        }
        let (n0, n1) = (self.n[0] as i64, self.n[1] as i64);
        // A point far outside the grid: start where the grid is.
        let (i0, j0) = (i0.clamp(-1.0, n0 as f64) as i64, j0.clamp(-1.0, n1 as f64) as i64);
        let t = p[self.axis];
        let kmax = (max_mm / self.cell).ceil() as i64 + 2;
        let visit = |i: i64, j: i64, best: &mut f64| {
            if i < 0 || j < 0 || i >= n0 || j >= n1 {
                return;
            }
            let dx = Self::gap(p[a], self.origin[0] + i as f64 * self.cell, self.cell);
            let dy = Self::gap(p[b], self.origin[1] + j as f64 * self.cell, self.cell);
            let lat = dx * dx + dy * dy;
            if lat >= *best {
                return;
            }
            for s in &self.rays[(j * n0 + i) as usize] {
                for e in [s[0], s[1]] {
                    let d = f64::from(e) - t;
                    *best = best.min(lat + d * d);
                }
            }
        };
        for k in 0..=kmax {
            let lb = (k as f64 - 1.0).max(0.0) * self.cell;
            if lb * lb >= *best || lb > max_mm {
                break;
            }
            if k == 0 {
                visit(i0, j0, best);
                continue;
            }
            for d in -k..=k {
                visit(i0 + d, j0 - k, best);
                visit(i0 + d, j0 + k, best);
            }
            for d in -k + 1..k {
                visit(i0 - k, j0 + d, best);
                visit(i0 + k, j0 + d, best);
            }
        }
    }

    /// `(in material, distance along the ray to the nearest end)` at `p`; `None` off the grid or
    /// on an empty ray (no material anywhere along it).
    fn axial(&self, p: &Point3<f64>) -> Option<(bool, f64)> {
        let ray = self.ray_at(p)?;
        let t = p[self.axis];
        let mut out: Option<(bool, f64)> = None;
        for s in ray {
            let (lo, hi) = (f64::from(s[0]), f64::from(s[1]));
            if t >= lo && t <= hi {
                return Some((true, (t - lo).min(hi - t)));
            }
            let d = if t < lo { lo - t } else { t - hi };
            out = Some((false, out.map_or(d, |(_, o)| o.min(d))));
        }
        out
    }
}

impl DexelStock {
    /// The blank's bounding box (`min`, `max`), which bounds the material.
    pub fn extent(&self) -> ([f64; 3], [f64; 3]) {
        self.extent
    }

    /// Distance from `p` to the simulated part's surface (see the module docs), `None` when it
    /// is farther than `max_mm`.
    pub fn surface_distance(&self, p: &Point3<f64>, max_mm: f64) -> Option<f64> {
        debug_assert!(self.is_flushed(), "surface_distance before flush");
        // Every grid's own ray first: on a face across one grid's rays that grid finds the
        // surface at once, and the others' ring searches stop as soon as they cannot beat it
        // (a wall seen along the Z rays would otherwise be searched ring by ring out to its top).
        let mut best = f64::INFINITY;
        for g in &self.grids {
            if let Some((_, d)) = g.axial(p) {
                best = best.min(d * d);
            }
        }
        for g in &self.grids {
            g.nearest_end(p, &mut best, max_mm);
        }
        let d = best.sqrt();
        (d <= max_mm).then_some(d)
    }

    /// The signed distance from `p` to the simulated part's surface, positive in material,
    /// within `±max_mm`: to the surface interpolated between the rays where `p` is near a smooth
    /// stretch of it, else the signed [`surface_distance`](Self::surface_distance) (see the
    /// module docs).
    pub fn deviation_at(&self, p: &Point3<f64>, max_mm: f64) -> f64 {
        debug_assert!(self.is_flushed(), "deviation_at before flush");
        if let Some((d, _)) = self.grids.iter().filter_map(|g| g.local(p)).min_by(|x, y| x.1.total_cmp(&y.1))
        {
            return d.clamp(-max_mm, max_mm);
        }
        let d = self.surface_distance(p, max_mm).unwrap_or(max_mm);
        if self.inside(p) { d } else { -d }
    }

    /// Whether `p` is in material, read on the grid whose ray through `p` has a dexel end
    /// nearest to `p` (the grid that sees the nearby surface across its rays, where its own cell
    /// size does not blur it; [`contains`](Self::contains) asks every grid, which erodes walls
    /// parallel to one grid's rays by up to that grid's half cell).
    pub fn inside(&self, p: &Point3<f64>) -> bool {
        self.signed_distance(p, f64::INFINITY) < 0.0
    }

    /// A signed distance at `p`, negative in material, within `cap`: the distance along the ray
    /// through `p`, of the grid whose ray has its nearest dexel end nearest to `p`, to that end
    /// (see the module docs).
    pub fn signed_distance(&self, p: &Point3<f64>, cap: f64) -> f64 {
        debug_assert!(self.is_flushed(), "signed_distance before flush");
        let mut best: Option<(bool, f64)> = None;
        for g in &self.grids {
            if let Some((g_in, g_d)) = g.axial(p)
                && best.is_none_or(|(_, d)| g_d < d)
            {
                best = Some((g_in, g_d));
            }
        }
        match best {
            Some((true, d)) => -d.min(cap),
            Some((false, d)) => d.min(cap),
            None => cap,
        }
    }

    /// The lattice step [`surface_mesh`](Self::surface_mesh) needs to stay within `max_samples`:
    /// the smallest grid cell, or coarser.
    pub fn surface_step_mm(&self, max_samples: u64) -> f64 {
        let (lo, hi) = self.extent;
        let mut h = self.min_cell_mm();
        for _ in 0..64 {
            if lattice(lo, hi, h).is_some_and(|n| n.iter().map(|&k| k as u64).product::<u64>() <= max_samples)
            {
                break;
            }
            h *= 1.25;
        }
        h
    }

    /// The simulated part's surface as a closed, outward-wound triangle mesh (part frame, mm),
    /// sampled every `step_mm` (see the module docs).
    ///
    /// Errors: a step that is not finite and positive, or a lattice of more than
    /// [`MAX_SURFACE_SAMPLES`] samples.
    pub fn surface_mesh(&self, step_mm: f64) -> Result<Mesh, DexelError> {
        debug_assert!(self.is_flushed(), "surface_mesh before flush");
        let (lo, hi) = self.extent;
        let too_large =
            |samples: u64| DexelError::TooManySamples { step_mm, samples, limit: MAX_SURFACE_SAMPLES };
        if !(step_mm.is_finite() && step_mm > 0.0) {
            return Err(DexelError::Invalid {
                field: "surface step_mm".into(),
                value: step_mm,
                expected: "a finite positive step",
            });
        }
        let n = lattice(lo, hi, step_mm).ok_or(too_large(u64::MAX))?;
        let samples: u64 = n.iter().map(|&k| u64::from(k)).product();
        if samples > MAX_SURFACE_SAMPLES {
            return Err(too_large(samples));
        }
        let origin = [lo[0] - step_mm, lo[1] - step_mm, lo[2] - step_mm];
        let cap = 2.0 * step_mm;
        let (nx, ny) = (n[0] as usize, n[1] as usize);
        let mut sdf = vec![0f32; samples as usize];
        sdf.par_chunks_mut(nx * ny).enumerate().for_each(|(k, slab)| {
            let z = origin[2] + k as f64 * step_mm;
            for (idx, v) in slab.iter_mut().enumerate() {
                let x = origin[0] + (idx % nx) as f64 * step_mm;
                let y = origin[1] + (idx / nx) as f64 * step_mm;
                *v = (self.signed_distance(&Point3::new(x, y, z), cap) / step_mm) as f32;
            }
        });
        // The outer layer is outside the blank, so no material reaches the lattice's boundary.
        let shape = RuntimeShape::<u32, 3>::new(n);
        debug_assert_eq!(shape.size() as u64, samples);
        let mut buf = SurfaceNetsBuffer::default();
        surface_nets(&sdf, &shape, [0; 3], [n[0] - 1, n[1] - 1, n[2] - 1], &mut buf);
        // Vertices at the same place (as STL's f32 stores them) are one, and the triangles they
        // collapse are dropped: what an STL reader that welds vertices sees is what is written.
        let mut vertices: Vec<Point3<f64>> = Vec::with_capacity(buf.positions.len());
        let mut index: std::collections::HashMap<[u32; 3], u32> = std::collections::HashMap::new();
        let remap: Vec<u32> = buf
            .positions
            .iter()
            .map(|p| {
                let q = [0, 1, 2].map(|k| (origin[k] + f64::from(p[k]) * step_mm) as f32);
                *index.entry(q.map(f32::to_bits)).or_insert_with(|| {
                    vertices.push(Point3::new(f64::from(q[0]), f64::from(q[1]), f64::from(q[2])));
                    (vertices.len() - 1) as u32
                })
            })
            .collect();
        let mut triangles: Vec<[u32; 3]> = buf
            .indices
            .chunks_exact(3)
            .map(|t| [remap[t[0] as usize], remap[t[1] as usize], remap[t[2] as usize]])
            .filter(|t| t[0] != t[1] && t[1] != t[2] && t[0] != t[2])
            .collect();
        // Wind outward whatever the extractor's convention: the enclosed volume comes out positive.
        let signed: f64 = triangles
            .iter()
            .map(|t| {
                let [a, b, c] = t.map(|i| vertices[i as usize].coords);
                a.dot(&b.cross(&c))
            })
            .sum();
        if signed < 0.0 {
            for t in &mut triangles {
                t.swap(1, 2);
            }
        }
        Mesh::new(vertices, triangles).map_err(|e| DexelError::Map(e.to_string()))
    }
}

/// Samples per axis of a lattice over `[lo, hi]` at step `h` with one layer outside on each side.
fn lattice(lo: [f64; 3], hi: [f64; 3], h: f64) -> Option<[u32; 3]> {
    let mut n = [0u32; 3];
    for k in 0..3 {
        let c = ((hi[k] - lo[k]) / h).ceil() + 3.0;
        if !(c.is_finite() && c <= f64::from(u32::MAX / 4)) {
            return None;
        }
        n[k] = c.max(3.0) as u32;
    }
    Some(n)
}

/// Signed volume enclosed by a mesh (positive when wound outward), mm³.
pub fn mesh_volume_mm3(mesh: &Mesh) -> f64 {
    mesh.triangles
        .iter()
        .map(|t| {
            let [a, b, c] = t.map(|i| mesh.vertices[i as usize].coords);
            a.dot(&b.cross(&c)) / 6.0
        })
        .sum()
}
