//! Z-buffer of a triangle mesh: the exact top surface of the mesh at every cell centre.
//!
//! # Conventions
//!
//! The mesh arrives already rotated into the face frame (+Z up, looking down). The output is a
//! [`HeightMap`] on the caller's grid (its metadata unchanged): cell `(col, row)` holds the
//! largest Z, at the cell centre `(x0 + (col+½)·p, y0 + (row+½)·p)`, of the planes of the
//! triangles whose vertical projection contains that centre, rounded to f32; `NaN` where no
//! triangle covers the centre. It is a point sample, like the cloud rasteriser's output: a
//! feature narrower than a pixel that covers no centre leaves no trace.
//!
//! # Coverage rule (watertight)
//!
//! Every vertex is mapped once to grid units, `u = (x − x0)/p − ½`, `v = (y − y0)/p − ½` (cell
//! centres at integer `(col, row)`), and snapped to a fixed-point lattice of `1/2^16` pixel
//! ([`SUBPIXEL_BITS`]); all coverage decisions are then made in exact integer arithmetic on those
//! snapped positions. A triangle covers a centre when the centre lies in the *closed* projected
//! triangle: each of the three edge functions is ≥ 0 (for counter-clockwise order, ≤ 0 for
//! clockwise). Consequences:
//!
//! - A centre exactly on an edge or vertex is counted, by every triangle that has the edge, so
//!   two triangles sharing an edge leave no crack and a centre on the shared edge takes the
//!   larger of the (equal, up to rounding) plane heights there. Coincident vertices (an STL's
//!   unshared corners) snap identically, so triangle soups are watertight too.
//! - Triangles with zero projected area after snapping (vertical walls, degenerate slivers)
//!   contribute nothing; the top edge of a vertical wall is still represented, exactly, by the
//!   adjacent upward-facing triangles, whose closed projections contain it. Where a wall's top
//!   edge passes through a centre, that centre takes the max of the top and bottom faces (the
//!   top).
//! - Triangles with a non-finite coordinate, or a vertex farther than [`MAX_VERTEX_OFFSET_PX`]
//!   pixels from the grid origin, are ignored (counted in [`MeshRasterStats::triangles_invalid`]).
//!
//! The snapping moves a coverage boundary by at most `2^-17` pixel. The height at a covered
//! centre is the barycentric interpolation `z_a + (λ_b (z_b − z_a) + λ_c (z_c − z_a))` with
//! `λ = edge / area` from the exact integer edge functions, so it never leaves the triangle's Z
//! range (a near-vertical triangle cannot extrapolate), a flat face gives exactly its Z, and the
//! deviation from the unsnapped plane is at most `slope · p · 2^-17`.
//!
//! # Algorithm
//!
//! 1. Snap the vertices (parallel).
//! 2. Classify each triangle and bin it by the bands of rows (about 8 per thread) that its
//!    bounding box reaches (parallel over chunks of triangles).
//! 3. Per band (parallel), rasterise each binned triangle over its bounding box clipped to the
//!    band: the three edge functions are evaluated once at the box corner and then stepped by
//!    integer increments per column and row; a row stops at the first uncovered centre after a
//!    covered one (the projection is convex). A triangle whose box is small (< 2^13 pixels and
//!    vertices near it) runs in `i64`, the rare others in `i128`; both are exact.
//!
//! Cost: O(triangles + covered box area); memory: the output, one snapped position per vertex
//! and the bins (one index per triangle and band it touches).

use std::ops::{Add, AddAssign, Mul, Sub};

use crate::{HeightMap, HeightMapMeta};
use rayon::prelude::*;

use crate::mesh::Mesh;
use crate::raster::Result;

/// Vertices are snapped to `1/2^SUBPIXEL_BITS` of a pixel before the coverage tests.
pub const SUBPIXEL_BITS: u32 = 16;

/// Vertices farther than this many pixels (2^39) from the grid origin make their triangles
/// invalid; below it every edge function fits `i128` exactly.
pub const MAX_VERTEX_OFFSET_PX: f64 = (1u64 << 39) as f64;

const SUB: i64 = 1 << SUBPIXEL_BITS;

/// Row bands per worker thread (load balance against repeated set-up of band-crossing triangles).
const BANDS_PER_THREAD: usize = 8;

/// Triangles per binning task.
const BIN_CHUNK: usize = 1 << 14;

/// What a rasterisation did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct MeshRasterStats {
    /// Triangles in the mesh.
    pub triangles_in: usize,
    /// Triangles ignored for a non-finite coordinate or a vertex beyond [`MAX_VERTEX_OFFSET_PX`].
    pub triangles_invalid: usize,
    /// Valid triangles with zero projected area (vertical walls, slivers): they cover nothing.
    pub triangles_vertical: usize,
    /// Valid, non-vertical triangles whose bounding box holds at least one cell centre of the
    /// grid (each was rasterised; it may still cover no centre if it is thin).
    pub triangles_used: usize,
    /// Cells holding a height.
    pub cells_covered: usize,
}

/// Rasterises `mesh` (already in the face frame, +Z up) onto `grid`: the exact top surface at
/// every cell centre, NaN where no triangle covers it (see the module docs for the rules).
///
/// # Panics
///
/// If `grid` fails [`HeightMapMeta::validate`] (a caller bug: grids made by the pipeline are
/// validated); use [`rasterize_mesh_with_stats`] to get an error instead.
pub fn rasterize_mesh(mesh: &Mesh, grid: &HeightMapMeta) -> HeightMap {
    match rasterize_mesh_with_stats(mesh, grid) {
        Ok((map, _)) => map,
        Err(e) => panic!("rasterize_mesh needs a valid grid: {e}"),
    }
}

/// [`rasterize_mesh`] with statistics; an invalid `grid` is an error.
pub fn rasterize_mesh_with_stats(mesh: &Mesh, grid: &HeightMapMeta) -> Result<(HeightMap, MeshRasterStats)> {
    grid.validate()?;
    let (data, stats) = raster_core::<f32>(mesh, grid);
    Ok((HeightMap::new(*grid, data)?, stats))
}

/// Output sample type of the core (f32 for maps, f64 for the precision tests). Rounding f64 to
/// f32 is monotone, so the max of rounded heights is the rounded max.
pub(crate) trait Depth: Copy + Send + Sync {
    const NAN: Self;
    fn from_f64(z: f64) -> Self;
    /// Keeps the larger of `self` and `z` (`z` is never NaN; `self` may be).
    fn keep_max(&mut self, z: Self);
    fn is_data(self) -> bool;
}

impl Depth for f32 {
    const NAN: Self = f32::NAN;
    fn from_f64(z: f64) -> Self {
        z as f32
    }
    fn keep_max(&mut self, z: Self) {
        if self.is_nan() || z > *self {
            *self = z;
        }
    }
    fn is_data(self) -> bool {
        !self.is_nan()
    }
}

impl Depth for f64 {
    const NAN: Self = f64::NAN;
    fn from_f64(z: f64) -> Self {
        z
    }
    fn keep_max(&mut self, z: Self) {
        if self.is_nan() || z > *self {
            *self = z;
        }
    }
    fn is_data(self) -> bool {
        !self.is_nan()
    }
}

/// A vertex in fixed-point grid units (cell centres at multiples of `2^SUBPIXEL_BITS`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct FixVertex {
    pub x: i64,
    pub y: i64,
    pub z: f64,
}

/// Snaps a vertex to the fixed-point lattice of `grid`, `None` when it is unusable.
pub(crate) fn snap(grid: &HeightMapMeta, p: &nalgebra::Point3<f64>) -> Option<FixVertex> {
    let u = (p.x - grid.origin_x_mm) / grid.pixel_mm - 0.5;
    let v = (p.y - grid.origin_y_mm) / grid.pixel_mm - 0.5;
    // NaN fails both comparisons.
    let ok = |t: f64| t.abs() <= MAX_VERTEX_OFFSET_PX;
    if !(ok(u) && ok(v) && p.z.is_finite()) {
        return None;
    }
    let scale = SUB as f64;
    // |u·2^16| <= 2^55: the casts are exact.
    Some(FixVertex { x: (u * scale).round() as i64, y: (v * scale).round() as i64, z: p.z })
}

/// `⌈a / 2^SUBPIXEL_BITS⌉` and `⌊a / 2^SUBPIXEL_BITS⌋`.
fn ceil_sub(a: i64) -> i64 {
    -((-a) >> SUBPIXEL_BITS)
}
fn floor_sub(a: i64) -> i64 {
    a >> SUBPIXEL_BITS
}

/// Twice the signed projected area of `abc` (positive counter-clockwise), exact.
fn area2(a: &FixVertex, b: &FixVertex, c: &FixVertex) -> i128 {
    let (abx, aby) = (i128::from(b.x - a.x), i128::from(b.y - a.y));
    let (acx, acy) = (i128::from(c.x - a.x), i128::from(c.y - a.y));
    abx * acy - aby * acx
}

/// Inclusive range of cell indices whose centres lie in `[lo, hi]` (fixed point), clipped to
/// `0..n`; `None` when empty.
fn centre_range(lo: i64, hi: i64, n: u32) -> Option<(i64, i64)> {
    let first = ceil_sub(lo).max(0);
    let last = floor_sub(hi).min(i64::from(n) - 1);
    (first <= last).then_some((first, last))
}

enum Class {
    Invalid,
    Vertical,
    Outside,
    /// Inclusive row range of covered-candidate centres.
    Rows(i64, i64),
}

fn classify(v: &[Option<FixVertex>], tri: &[u32; 3], grid: &HeightMapMeta) -> Class {
    let get = |i: u32| v.get(i as usize).copied().flatten();
    let (Some(a), Some(b), Some(c)) = (get(tri[0]), get(tri[1]), get(tri[2])) else {
        return Class::Invalid;
    };
    if area2(&a, &b, &c) == 0 {
        return Class::Vertical;
    }
    let (xl, xh) = (a.x.min(b.x).min(c.x), a.x.max(b.x).max(c.x));
    let (yl, yh) = (a.y.min(b.y).min(c.y), a.y.max(b.y).max(c.y));
    match (centre_range(xl, xh, grid.width), centre_range(yl, yh, grid.height)) {
        (Some(_), Some((r0, r1))) => Class::Rows(r0, r1),
        _ => Class::Outside,
    }
}

#[derive(Default)]
struct Bins {
    /// Triangle indices per band.
    bands: Vec<Vec<usize>>,
    invalid: usize,
    vertical: usize,
    used: usize,
}

/// The rasteriser shared by the public functions and the precision tests; `grid` must be valid.
pub(crate) fn raster_core<T: Depth>(mesh: &Mesh, grid: &HeightMapMeta) -> (Vec<T>, MeshRasterStats) {
    let (w, h) = (grid.width as usize, grid.height as usize);
    let mut data = vec![T::NAN; w * h];
    let verts: Vec<Option<FixVertex>> = mesh.vertices.par_iter().map(|p| snap(grid, p)).collect();

    let n_bands = (rayon::current_num_threads() * BANDS_PER_THREAD).clamp(1, h);
    let band_rows = h.div_ceil(n_bands);
    let n_bands = h.div_ceil(band_rows);

    let chunks: Vec<Bins> = mesh
        .triangles
        .par_chunks(BIN_CHUNK)
        .enumerate()
        .map(|(ci, tris)| {
            let mut bins = Bins { bands: vec![Vec::new(); n_bands], ..Bins::default() };
            for (k, tri) in tris.iter().enumerate() {
                match classify(&verts, tri, grid) {
                    Class::Invalid => bins.invalid += 1,
                    Class::Vertical => bins.vertical += 1,
                    Class::Outside => {}
                    Class::Rows(r0, r1) => {
                        bins.used += 1;
                        // r0, r1 are in 0..h.
                        for band in (r0 as usize / band_rows)..=(r1 as usize / band_rows) {
                            bins.bands[band].push(ci * BIN_CHUNK + k);
                        }
                    }
                }
            }
            bins
        })
        .collect();

    let covered: usize = data
        .par_chunks_mut(band_rows * w)
        .enumerate()
        .map(|(band, out)| {
            let row0 = band * band_rows;
            let rows = out.len() / w;
            for bins in &chunks {
                for &t in &bins.bands[band] {
                    if let Some(tri) = mesh.triangles.get(t) {
                        raster_triangle(&verts, tri, grid, row0, rows, out);
                    }
                }
            }
            out.iter().filter(|z| z.is_data()).count()
        })
        .sum();

    let stats = MeshRasterStats {
        triangles_in: mesh.triangles.len(),
        triangles_invalid: chunks.iter().map(|b| b.invalid).sum(),
        triangles_vertical: chunks.iter().map(|b| b.vertical).sum(),
        triangles_used: chunks.iter().map(|b| b.used).sum(),
        cells_covered: covered,
    };
    (data, stats)
}

/// Exact integer type of the edge functions.
trait Fx: Copy + PartialOrd + Add<Output = Self> + Sub<Output = Self> + Mul<Output = Self> + AddAssign {
    const ZERO: Self;
    fn of(v: i64) -> Self;
    fn to_f64(self) -> f64;
}

impl Fx for i64 {
    const ZERO: Self = 0;
    fn of(v: i64) -> Self {
        v
    }
    fn to_f64(self) -> f64 {
        self as f64
    }
}

impl Fx for i128 {
    const ZERO: Self = 0;
    fn of(v: i64) -> Self {
        v.into()
    }
    fn to_f64(self) -> f64 {
        self as f64
    }
}

/// Rasterises one triangle into the band `out` (rows `row0 .. row0 + rows` of the grid).
fn raster_triangle<T: Depth>(
    verts: &[Option<FixVertex>],
    tri: &[u32; 3],
    grid: &HeightMapMeta,
    row0: usize,
    rows: usize,
    out: &mut [T],
) {
    let get = |i: u32| verts.get(i as usize).copied().flatten();
    let (Some(a), Some(b), Some(mut c)) = (get(tri[0]), get(tri[1]), get(tri[2])) else {
        return;
    };
    let mut b = b;
    let area = area2(&a, &b, &c);
    if area == 0 {
        return;
    }
    if area < 0 {
        std::mem::swap(&mut b, &mut c);
    }
    let (xl, xh) = (a.x.min(b.x).min(c.x), a.x.max(b.x).max(c.x));
    let (yl, yh) = (a.y.min(b.y).min(c.y), a.y.max(b.y).max(c.y));
    let (Some((c0, c1)), Some((r0, r1))) =
        (centre_range(xl, xh, grid.width), centre_range(yl, yh, grid.height))
    else {
        return;
    };
    // Clip the rows to the band (row0 + rows <= height, so the casts are exact).
    let r0 = r0.max(row0 as i64);
    let r1 = r1.min((row0 + rows) as i64 - 1);
    if r0 > r1 {
        return;
    }
    // Coordinates relative to the first centre of the box.
    let (ox, oy) = (c0 * SUB, r0 * SUB);
    let rel = [(a.x - ox, a.y - oy), (b.x - ox, b.y - oy), (c.x - ox, c.y - oy)];
    let span =
        rel.iter().map(|&(x, y)| x.abs().max(y.abs())).max().unwrap_or(0).max((c1 - c0).max(r1 - r0) * SUB);
    let job = Job {
        rel,
        z: [a.z, b.z - a.z, c.z - a.z],
        cols: (c1 - c0 + 1) as usize,
        rows: (r1 - r0 + 1) as usize,
        first: (r0 as usize - row0) * grid.width as usize + c0 as usize,
        stride: grid.width as usize,
    };
    // |coordinates| < 2^29 bounds every edge value by 8·2^58 = 2^61.
    if span < 1 << 29 { job.run::<i64, T>(out) } else { job.run::<i128, T>(out) }
}

struct Job {
    /// Vertices a, b, c (counter-clockwise) relative to the box's first centre, fixed point.
    rel: [(i64, i64); 3],
    /// `z_a`, `z_b − z_a`, `z_c − z_a`.
    z: [f64; 3],
    cols: usize,
    rows: usize,
    /// Index in the band of the box's first cell.
    first: usize,
    stride: usize,
}

impl Job {
    fn run<I: Fx, T: Depth>(&self, out: &mut [T]) {
        let [a, b, c] = self.rel.map(|(x, y)| (I::of(x), I::of(y)));
        let sub = I::of(SUB);
        // Edge function of p→q at the origin centre, and its steps per column and per row.
        let edge = |p: (I, I), q: (I, I)| {
            let (dx, dy) = (q.0 - p.0, q.1 - p.1);
            (dy * p.0 - dx * p.1, I::ZERO - dy * sub, dx * sub)
        };
        // e_bc weighs a, e_ca weighs b, e_ab weighs c.
        let (mut r_bc, sx_bc, sy_bc) = edge(b, c);
        let (mut r_ca, sx_ca, sy_ca) = edge(c, a);
        let (mut r_ab, sx_ab, sy_ab) = edge(a, b);
        let area = (r_bc + r_ca + r_ab).to_f64();
        let [za, dzb, dzc] = self.z;
        for j in 0..self.rows {
            let start = self.first + j * self.stride;
            let Some(line) = out.get_mut(start..start + self.cols) else { return };
            let (mut e_bc, mut e_ca, mut e_ab) = (r_bc, r_ca, r_ab);
            let mut seen = false;
            for cell in line {
                if e_bc >= I::ZERO && e_ca >= I::ZERO && e_ab >= I::ZERO {
                    let z = za + (e_ca.to_f64() * dzb + e_ab.to_f64() * dzc) / area;
                    cell.keep_max(T::from_f64(z));
                    seen = true;
                } else if seen {
                    break;
                }
                e_bc += sx_bc;
                e_ca += sx_ca;
                e_ab += sx_ab;
            }
            r_bc += sy_bc;
            r_ca += sy_ca;
            r_ab += sy_ab;
        }
    }
}

#[cfg(test)]
mod tests {
    use std::f64::consts::PI;

    use nalgebra::Point3;
    use rand::rngs::StdRng;
    use rand::{Rng, SeedableRng};

    use super::*;

    fn grid(w: u32, h: u32, p: f64, ox: f64, oy: f64) -> HeightMapMeta {
        HeightMapMeta { origin_x_mm: ox, origin_y_mm: oy, ..HeightMapMeta::new(w, h, p) }
    }

    fn mesh(vertices: Vec<Point3<f64>>, triangles: Vec<[u32; 3]>) -> Mesh {
        Mesh::new(vertices, triangles).expect("valid mesh")
    }

    /// Brute force: every cell centre against every triangle, edge functions from scratch in
    /// `i128`, closed-triangle test, barycentric height.
    fn reference(mesh: &Mesh, grid: &HeightMapMeta) -> Vec<f64> {
        let orient = |a: &FixVertex, b: &FixVertex, px: i128, py: i128| -> i128 {
            (i128::from(b.x) - i128::from(a.x)) * (py - i128::from(a.y))
                - (i128::from(b.y) - i128::from(a.y)) * (px - i128::from(a.x))
        };
        let tris: Vec<[FixVertex; 3]> = mesh
            .triangles
            .iter()
            .filter_map(|t| {
                let v = |i: u32| snap(grid, &mesh.vertices[i as usize]);
                Some([v(t[0])?, v(t[1])?, v(t[2])?])
            })
            .collect();
        let mut out = Vec::new();
        for row in 0..grid.height {
            for col in 0..grid.width {
                let (px, py) = (i128::from(col) << SUBPIXEL_BITS, i128::from(row) << SUBPIXEL_BITS);
                let mut best = f64::NAN;
                for [a, b, c] in &tris {
                    let area = orient(a, b, i128::from(c.x), i128::from(c.y));
                    let (wa, wb, wc) = (orient(b, c, px, py), orient(c, a, px, py), orient(a, b, px, py));
                    let inside = (area > 0 && wa >= 0 && wb >= 0 && wc >= 0)
                        || (area < 0 && wa <= 0 && wb <= 0 && wc <= 0);
                    if inside {
                        let z = a.z + (wb as f64 * (b.z - a.z) + wc as f64 * (c.z - a.z)) / area as f64;
                        if best.is_nan() || z > best {
                            best = z;
                        }
                    }
                }
                out.push(best);
            }
        }
        out
    }

    fn assert_matches_reference(mesh: &Mesh, grid: &HeightMapMeta) {
        let (fast, _) = raster_core::<f64>(mesh, grid);
        let slow = reference(mesh, grid);
        for (i, (f, s)) in fast.iter().zip(&slow).enumerate() {
            assert_eq!(f.is_nan(), s.is_nan(), "coverage differs at cell {i}: {f} vs {s}");
            if s.is_finite() {
                assert!((f - s).abs() <= 1e-9 * (1.0 + s.abs()), "cell {i}: {f} vs {s}");
            }
        }
        // The f32 map is the f64 result rounded.
        let (map, stats) = rasterize_mesh_with_stats(mesh, grid).expect("valid grid");
        for (z, f) in map.data().iter().zip(&fast) {
            assert_eq!(z.to_bits(), (*f as f32).to_bits());
        }
        assert_eq!(stats.cells_covered, map.valid_count());
    }

    /// A random soup over (and around) the grid: shared vertices (so shared edges), vertices on
    /// cell centres and cell corners, vertical and degenerate triangles, far and NaN vertices.
    fn random_soup(rng: &mut StdRng, grid: &HeightMapMeta, n_vertices: usize, n_tris: usize) -> Mesh {
        let (w, h, p) = (grid.width_mm(), grid.height_mm(), grid.pixel_mm);
        let mut vertices: Vec<Point3<f64>> = Vec::new();
        for _ in 0..n_vertices {
            let z = rng.random_range(-5.0..5.0);
            let pt = match rng.random_range(0..10) {
                0..=2 => {
                    let (c, r) = (
                        rng.random_range(-2..grid.width as i32 + 2),
                        rng.random_range(-2..grid.height as i32 + 2),
                    );
                    let (x, y) = grid.cell_center(0, 0);
                    Point3::new(x + f64::from(c) * p, y + f64::from(r) * p, z)
                }
                3 => {
                    let (c, r) = (rng.random_range(0..=grid.width), rng.random_range(0..=grid.height));
                    Point3::new(grid.origin_x_mm + f64::from(c) * p, grid.origin_y_mm + f64::from(r) * p, z)
                }
                _ => Point3::new(
                    grid.origin_x_mm + rng.random_range(-0.2..1.2) * w,
                    grid.origin_y_mm + rng.random_range(-0.2..1.2) * h,
                    z,
                ),
            };
            vertices.push(pt);
        }
        // A vertical triangle's partner: same XY, other Z.
        let base = vertices[0];
        vertices.push(Point3::new(base.x, base.y, base.z + 3.0));
        vertices.push(Point3::new(1e15, 0.0, 0.0));
        vertices.push(Point3::new(f64::NAN, 0.0, 0.0));
        let n = vertices.len() as u32;
        let mut triangles: Vec<[u32; 3]> = (0..n_tris)
            .map(|_| {
                // Mostly small triangles from nearby indices of the pool.
                let a = rng.random_range(0..n_vertices as u32);
                [a, rng.random_range(0..n_vertices as u32), rng.random_range(0..n_vertices as u32)]
            })
            .collect();
        triangles.push([0, n - 3, 1]);
        triangles.push([0, 1, n - 2]);
        triangles.push([0, 1, n - 1]);
        triangles.push([2, 2, 3]);
        mesh(vertices, triangles)
    }

    #[test]
    fn matches_brute_force_on_random_soups() {
        let mut rng = StdRng::seed_from_u64(7);
        for case in 0..40 {
            let g = grid(
                rng.random_range(1..30),
                rng.random_range(1..30),
                rng.random_range(0.05..2.0),
                rng.random_range(-50.0..50.0),
                rng.random_range(-50.0..50.0),
            );
            let (nv, nt) = (rng.random_range(3..40), rng.random_range(1..60));
            let m = random_soup(&mut rng, &g, nv, nt);
            assert_matches_reference(&m, &g);
            let (_, stats) = rasterize_mesh_with_stats(&m, &g).expect("grid");
            assert_eq!(stats.triangles_in, m.triangles.len(), "case {case}");
            assert!(stats.triangles_invalid >= 2 && stats.triangles_vertical >= 2, "{stats:?}");
        }
    }

    #[test]
    fn large_triangles_take_the_wide_path_and_agree() {
        // Vertices 2^20 pixels away force the i128 path; the reference is independent of it.
        let g = grid(16, 12, 0.5, 0.0, 0.0);
        let far = f64::from(1 << 20) * 0.5;
        let m = mesh(
            vec![
                Point3::new(-far, -far, 0.0),
                Point3::new(far, -1.3, 10.0),
                Point3::new(3.1, far, -2.0),
                Point3::new(7.0, 2.0, 1.0),
                Point3::new(7.6, 5.0, 1.0),
                Point3::new(1.0, 3.25, 9.0),
            ],
            vec![[0, 1, 2], [3, 4, 5]],
        );
        assert_matches_reference(&m, &g);
        let (map, stats) = rasterize_mesh_with_stats(&m, &g).expect("grid");
        assert_eq!(map.valid_count(), 16 * 12);
        assert_eq!(stats.triangles_used, 2);
    }

    /// A regular grid of jittered vertices triangulated over a rectangle covering the whole map.
    fn jittered_terrain(rng: &mut StdRng, g: &HeightMapMeta, n: u32, soup: bool) -> Mesh {
        let (x0, y0) = (g.origin_x_mm - 0.3, g.origin_y_mm - 0.3);
        let (sx, sy) = ((g.width_mm() + 0.6) / f64::from(n), (g.height_mm() + 0.6) / f64::from(n));
        let mut verts = Vec::new();
        for j in 0..=n {
            for i in 0..=n {
                let border = i == 0 || j == 0 || i == n || j == n;
                let (jx, jy) = if border {
                    (0.0, 0.0)
                } else {
                    (rng.random_range(-0.3..0.3), rng.random_range(-0.3..0.3))
                };
                let mut pt = Point3::new(
                    x0 + (f64::from(i) + jx) * sx,
                    y0 + (f64::from(j) + jy) * sy,
                    rng.random_range(0.0..2.0),
                );
                if !border && rng.random_range(0..4) == 0 {
                    // Exactly on a cell centre: a vertex shared by several triangles.
                    if let Some((c, r)) = g.cell_of(pt.x, pt.y) {
                        (pt.x, pt.y) = g.cell_center(c, r);
                    }
                }
                verts.push(pt);
            }
        }
        let id = |i: u32, j: u32| j * (n + 1) + i;
        let mut tris = Vec::new();
        for j in 0..n {
            for i in 0..n {
                let (a, b, c, d) = (id(i, j), id(i + 1, j), id(i + 1, j + 1), id(i, j + 1));
                if (i + j) % 2 == 0 {
                    tris.extend([[a, b, c], [a, c, d]]);
                } else {
                    tris.extend([[a, b, d], [b, c, d]]);
                }
            }
        }
        if soup {
            // Unshared corners, as in STL, with some triangles clockwise.
            let mut v2 = Vec::new();
            let mut t2 = Vec::new();
            for (k, t) in tris.iter().enumerate() {
                let base = v2.len() as u32;
                v2.extend(t.iter().map(|&i| verts[i as usize]));
                t2.push(if k % 3 == 0 { [base, base + 2, base + 1] } else { [base, base + 1, base + 2] });
            }
            return mesh(v2, t2);
        }
        mesh(verts, tris)
    }

    #[test]
    fn terrain_is_watertight() {
        let mut rng = StdRng::seed_from_u64(11);
        for soup in [false, true] {
            for _ in 0..5 {
                let g = grid(37, 29, 0.25, -3.0, 2.0);
                let m = jittered_terrain(&mut rng, &g, 13, soup);
                let map = rasterize_mesh(&m, &g);
                assert_eq!(map.valid_count(), 37 * 29, "a crack in the terrain");
                assert_matches_reference(&m, &g);
            }
        }
    }

    #[test]
    fn fan_around_a_centre_covers_it() {
        // 12 triangles meet at a vertex exactly on a cell centre; the rim passes through centres.
        let g = grid(9, 9, 1.0, 0.0, 0.0);
        let (cx, cy) = g.cell_center(4, 4);
        let mut verts = vec![Point3::new(cx, cy, 5.0)];
        for k in 0..12 {
            let a = f64::from(k) * PI / 6.0;
            verts.push(Point3::new(cx + 3.0 * a.cos(), cy + 3.0 * a.sin(), 1.0));
        }
        let tris: Vec<[u32; 3]> = (0..12u32).map(|k| [0, 1 + k, 1 + (k + 1) % 12]).collect();
        let map = rasterize_mesh(&mesh(verts, tris), &g);
        assert_eq!(map.get(4, 4), Some(5.0));
        // Every centre within the inscribed radius 3·cos(15°) is covered.
        for r in 0..9 {
            for c in 0..9 {
                let (x, y) = g.cell_center(c, r);
                let d = (x - cx).hypot(y - cy);
                let z = map.get(c, r).expect("in grid");
                if d <= 3.0 * (PI / 12.0).cos() {
                    assert!((f64::from(z) - (5.0 - 4.0 * d / 3.0)).abs() < 4.0 / 3.0 * 0.2, "({c},{r}) {z}");
                }
                if d > 3.0 {
                    assert!(z.is_nan());
                }
            }
        }
        // (7,4) lies on the rim vertex at angle 0: covered, at the rim height.
        assert_eq!(map.get(7, 4), Some(1.0));
    }

    /// A closed axis-aligned box, 12 triangles, outward counter-clockwise.
    fn boxed(lo: Point3<f64>, hi: Point3<f64>) -> (Vec<Point3<f64>>, Vec<[u32; 3]>) {
        let v: Vec<Point3<f64>> = (0..8)
            .map(|i| {
                Point3::new(
                    if i & 1 == 0 { lo.x } else { hi.x },
                    if i & 2 == 0 { lo.y } else { hi.y },
                    if i & 4 == 0 { lo.z } else { hi.z },
                )
            })
            .collect();
        let t = vec![
            [0, 2, 1],
            [1, 2, 3], // bottom
            [4, 5, 6],
            [5, 7, 6], // top
            [0, 1, 4],
            [1, 5, 4], // -Y wall
            [2, 6, 3],
            [3, 6, 7], // +Y wall
            [0, 4, 2],
            [2, 4, 6], // -X wall
            [1, 3, 5],
            [3, 7, 5], // +X wall
        ];
        (v, t)
    }

    #[test]
    fn box_top_is_exact_and_walls_lie_on_centres() {
        let g = grid(40, 30, 0.5, -10.0, -7.5);
        // Walls exactly through centres: x from centre 5 to centre 30, y from centre 4 to 20.
        let (xa, ya) = g.cell_center(5, 4);
        let (xb, yb) = g.cell_center(30, 20);
        let (v, t) = boxed(Point3::new(xa, ya, -2.0), Point3::new(xb, yb, 3.25));
        let m = mesh(v, t);
        let (map, stats) = rasterize_mesh_with_stats(&m, &g).expect("grid");
        assert_eq!((stats.triangles_in, stats.triangles_vertical, stats.triangles_used), (12, 8, 4));
        for r in 0..30 {
            for c in 0..40 {
                let z = map.get(c, r).expect("in grid");
                if (5..=30).contains(&c) && (4..=20).contains(&r) {
                    assert_eq!(z, 3.25, "({c},{r})");
                } else {
                    assert!(z.is_nan(), "({c},{r}) = {z}");
                }
            }
        }
        assert_eq!(map.valid_count(), 26 * 17);
        assert_matches_reference(&m, &g);
    }

    #[test]
    fn step_between_two_boxes_keeps_the_higher_top_on_the_shared_wall() {
        let g = grid(20, 10, 1.0, 0.0, 0.0);
        let (x_mid, _) = g.cell_center(10, 0);
        let (mut v, mut t) = boxed(Point3::new(0.0, 0.0, 0.0), Point3::new(x_mid, 10.0, 1.0));
        let (v2, t2) = boxed(Point3::new(x_mid, 0.0, 0.0), Point3::new(20.0, 10.0, 4.0));
        let off = v.len() as u32;
        v.extend(v2);
        t.extend(t2.iter().map(|tr| tr.map(|i| i + off)));
        let map = rasterize_mesh(&mesh(v, t), &g);
        for r in 0..10 {
            for c in 0..20 {
                let want = if c < 10 { 1.0 } else { 4.0 };
                assert_eq!(map.get(c, r), Some(want), "({c},{r})");
            }
        }
    }

    /// UV sphere of radius `r` at the origin: `n_lat` bands, `n_lon` sectors.
    fn sphere(r: f64, n_lat: u32, n_lon: u32) -> Mesh {
        let mut v = vec![Point3::new(0.0, 0.0, r), Point3::new(0.0, 0.0, -r)];
        for i in 1..n_lat {
            let th = PI * f64::from(i) / f64::from(n_lat);
            for j in 0..n_lon {
                let ph = 2.0 * PI * f64::from(j) / f64::from(n_lon);
                v.push(Point3::new(r * th.sin() * ph.cos(), r * th.sin() * ph.sin(), r * th.cos()));
            }
        }
        let ring = |i: u32, j: u32| 2 + (i - 1) * n_lon + j % n_lon;
        let mut t = Vec::new();
        for j in 0..n_lon {
            t.push([0, ring(1, j), ring(1, j + 1)]);
            t.push([1, ring(n_lat - 1, j + 1), ring(n_lat - 1, j)]);
        }
        for i in 1..n_lat - 1 {
            for j in 0..n_lon {
                t.push([ring(i, j), ring(i + 1, j), ring(i + 1, j + 1)]);
                t.push([ring(i, j), ring(i + 1, j + 1), ring(i, j + 1)]);
            }
        }
        mesh(v, t)
    }

    #[test]
    fn sphere_matches_the_analytic_top_within_half_a_pixel() {
        let (r, p) = (9.0, 0.1);
        let (n_lat, n_lon) = (90u32, 180u32);
        let g = grid(200, 200, p, -10.0, -10.0);
        let map = rasterize_mesh(&sphere(r, n_lat, n_lon), &g);
        // Chord error: a facet lies at least r·cos(ρ) from the centre, ρ its angular circumradius;
        // every edge spans at most `diag` radians and the circumradius of a triangle is at most
        // its longest edge / √3.
        let diag = (PI / f64::from(n_lat)).hypot(2.0 * PI / f64::from(n_lon));
        let sag = r * (1.0 - (diag / 3f64.sqrt()).cos());
        assert!(sag < p / 2.0);
        // The equator polygon's inradius bounds the covered disk.
        let r_in = r * (PI / f64::from(n_lon)).cos();
        for row in 0..200 {
            for col in 0..200 {
                let (x, y) = g.cell_center(col, row);
                let z = map.get(col, row).map(f64::from).expect("in grid");
                let d = x.hypot(y);
                if d < r_in {
                    let truth = (r * r - d * d).sqrt();
                    assert!(z <= truth + 1e-5, "({col},{row}) above the sphere: {z} > {truth}");
                    // Radial distance of the surface point from the sphere.
                    let radial = r - (d * d + z * z).sqrt();
                    assert!(radial <= sag + 1e-5, "({col},{row}) radial error {radial}");
                    if d < 0.9 * r {
                        assert!(truth - z <= p / 2.0, "({col},{row}) vertical error {}", truth - z);
                    }
                } else if d > r {
                    assert!(z.is_nan(), "({col},{row}) outside the sphere: {z}");
                }
            }
        }
    }

    #[test]
    fn cone_matches_the_analytic_top_within_half_a_pixel() {
        let (rb, hgt, n) = (7.0, 5.0, 96u32);
        let p = 0.1;
        let g = grid(160, 160, p, -8.0, -8.0);
        let mut v = vec![Point3::new(0.0, 0.0, hgt), Point3::new(0.0, 0.0, 0.0)];
        for k in 0..n {
            let a = 2.0 * PI * f64::from(k) / f64::from(n);
            v.push(Point3::new(rb * a.cos(), rb * a.sin(), 0.0));
        }
        let mut t = Vec::new();
        for k in 0..n {
            t.push([0, 2 + k, 2 + (k + 1) % n]);
            t.push([1, 2 + (k + 1) % n, 2 + k]);
        }
        let map = rasterize_mesh(&mesh(v, t), &g);
        let bound = hgt * (1.0 - (PI / f64::from(n)).cos());
        assert!(bound < p / 2.0);
        let r_in = rb * (PI / f64::from(n)).cos();
        for row in 0..160 {
            for col in 0..160 {
                let (x, y) = g.cell_center(col, row);
                let z = map.get(col, row).map(f64::from).expect("in grid");
                let d = x.hypot(y);
                if d < r_in {
                    let truth = hgt * (1.0 - d / rb);
                    assert!(z <= truth + 1e-5 && truth - z <= bound + 1e-5, "({col},{row}) {z} vs {truth}");
                } else if d > rb {
                    assert!(z.is_nan());
                }
            }
        }
        // Apex exactly reached where a centre sits on it.
        let g2 = grid(3, 3, 1.0, -1.5, -1.5);
        let mut v = vec![Point3::new(0.0, 0.0, hgt)];
        for k in 0..n {
            let a = 2.0 * PI * f64::from(k) / f64::from(n);
            v.push(Point3::new(rb * a.cos(), rb * a.sin(), 0.0));
        }
        let t: Vec<[u32; 3]> = (0..n).map(|k| [0, 1 + k, 1 + (k + 1) % n]).collect();
        let map = rasterize_mesh(&mesh(v, t), &g2);
        assert_eq!(map.get(1, 1), Some(hgt as f32));
    }

    #[test]
    fn degenerate_inputs() {
        let g = grid(4, 4, 1.0, 0.0, 0.0);
        let (map, stats) = rasterize_mesh_with_stats(&Mesh::default(), &g).expect("grid");
        assert_eq!((map.valid_count(), stats), (0, MeshRasterStats::default()));
        // Entirely outside the grid, and a triangle too thin to hold a centre.
        let m = mesh(
            vec![
                Point3::new(10.0, 10.0, 0.0),
                Point3::new(12.0, 10.0, 0.0),
                Point3::new(10.0, 12.0, 0.0),
                // A sliver beside the centre (0.5, 0.5), its box holding that centre.
                Point3::new(0.1, 0.2, 0.0),
                Point3::new(0.9, 1.0, 0.0),
                Point3::new(0.9, 0.95, 0.0),
            ],
            vec![[0, 1, 2], [3, 4, 5]],
        );
        let (map, stats) = rasterize_mesh_with_stats(&m, &g).expect("grid");
        assert_eq!(map.valid_count(), 0);
        assert_eq!(stats.triangles_used, 1);
        let bad = HeightMapMeta { pixel_mm: 0.0, ..g };
        assert!(rasterize_mesh_with_stats(&m, &bad).is_err());
    }
}
