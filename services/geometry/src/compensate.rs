//! Tool compensation (shared by the CAM service, which plans on it, and the machine service, which
//! measures against the part opened by the tools): the surface C the tool tip follows so the tool touches the part A without
//! gouging it: `C(x, y) = max over (i, j) in the footprint of A(x+i, y+j) - B(i, j)`, where B is the
//! height of the tool's surface above its tip at offset (i, j) (grayscale dilation of A by the
//! tool's negative).
//!
//! Pixel reading ([`PixelModel`]): `Point` treats each cell as a sample at its centre, so B(i, j) is
//! the tool height at the distance between centres. `Column` treats each cell as a square column
//! over the whole cell, so B(i, j) is the tool height at the *nearest* point of the neighbour cell:
//! the conservative reading, which never lets the tool dip between samples beside a step.
//! Cells outside the map, and cells without data (NaN), count as the floor `outside_z_mm`
//! (the map's `z_min_mm` unless given).
//!
//! # Algorithm ([`compensate`] / [`dilate`])
//!
//! The kernel is decomposed into its rows. Rows with the same profile (the same `dx0` and heights:
//! always `dy` and `-dy`, since B depends on |dy|, and for flat tools every row of the same
//! half-width) form a group; for each output row `y` and group, `M = max` of the source rows
//! `y + dy` (one comparison per cell per row), and the group's row profile is applied to `M` once:
//!
//! - symmetric rows (all rows [`kernel`] makes: B depends on |dx|) fold the two sides:
//!   `max(M[x-j], M[x+j]) - h_j` for `j = 0..=k`; the leading run of equal heights (the flat bottom
//!   of flat, bull-nose and flat-tipped V tools) is one running maximum of width `2·run + 1`
//!   (doubling up to 128 cells, van Herk/Gil-Werman beyond), so flat tools cost O(1)–O(log k) per
//!   cell per group instead of O(k);
//! - other rows (only hand-made kernels) apply each column on its own.
//!
//! The map is copied once into rows padded with the floor (NaN replaced by it), so inner loops have
//! no bounds checks and no edge cases; columns are processed in blocks of 64 whose accumulators stay
//! in registers across a row's columns, which the compiler vectorises (portable code; on x86-64 the
//! same code is also compiled for AVX2 and AVX-512F and chosen at run time). Output rows run in
//! parallel (rayon).
//!
//! Bounds ([`Bounds`]): per tile of 32 output rows by 64 columns, the map is bounded above over
//! the cells the tile reads by a plane plus a margin (from 8 x 8 block maxima) and below over the
//! tile's own cells by the same plane; a kernel cell whose best possible difference stays below the
//! centre cell's for every output of the tile is skipped. On smooth parts of a map only the pairs
//! near the tool's contact point are visited (on the 2000 x 2000 bench relief about half the work
//! goes); on rough parts nothing is skipped. The maximum taken is unchanged, so the result is too.
//! A group's row maximum is then built only over the columns its remaining pairs read. Kernels
//! whose flat runs hold more than a quarter of the pairs (flat and bull-nose tools, which cost a
//! running maximum per row whatever is skipped) are not bounded.
//!
//! Cost: O(W·H·(R + P)) for R kernel rows and P = the number of column pairs outside the flat runs
//! (about a quarter of the kernel cells for a ball) in the worst case, less where the bounds skip.
//! Memory: one padded copy of the map, its 8 x 8 block maxima, and a few rows per thread.
//!
//! Exactness: the result is the maximum of the same f32 differences `A - B` as
//! [`compensate_reference`] (`max(a, b) - h == max(a - h, b - h)` holds exactly because rounding is
//! monotone), so the two agree bit for bit up to the sign of a zero; proptests check it on random
//! maps with NaN cells, every tool shape, both pixel models and sizes from 1x1.

use crate::{GeometryError, HeightMap, ToolProfile};
use rayon::prelude::*;

/// What a depth-map cell means to the compensation.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PixelModel {
    /// A sample at the cell centre.
    Point,
    /// A square column over the cell (conservative).
    #[default]
    Column,
    /// A sample of a piecewise-linear surface through the centres that stands above every convex
    /// edge the neighbouring samples imply, flat for half a pixel beside a step or a wall
    /// ([`crate::facet`]): exact on planes, as `Point`, and not dipping between samples at a rim,
    /// as `Column`. The tip surface is a dilation at half the pixel.
    Facet,
}

/// Options of [`compensate`].
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct CompensateOptions {
    pub pixel_model: PixelModel,
    /// Height of everything outside the map and of cells without data; `None`: the map's `z_min_mm`.
    pub outside_z_mm: Option<f64>,
}

/// The tool as a height image at the map's scale: for each footprint row `dy`, the columns
/// `dx0 .. dx0 + heights.len()` and the tool's height above its tip there (mm).
#[derive(Debug, Clone, PartialEq)]
pub struct Kernel {
    pub rows: Vec<KernelRow>,
    /// Largest |dx| or |dy| of the footprint, in cells.
    pub half: i32,
}

/// One row of a [`Kernel`].
#[derive(Debug, Clone, PartialEq)]
pub struct KernelRow {
    pub dy: i32,
    pub dx0: i32,
    pub heights: Vec<f32>,
}

/// Renders `profile` as a [`Kernel`] at `pixel_mm` under `model`. `Facet` renders as `Point`: the
/// facet reading is a dilation of the map's nodes by the point kernel at half the pixel
/// ([`compensate`]); on the map's own grid (a region's envelope, what a pass reaches) the cells
/// are its samples.
pub fn kernel(profile: &ToolProfile, pixel_mm: f64, model: PixelModel) -> Kernel {
    let radius = profile.radius_mm();
    let half = (radius / pixel_mm).floor() as i32 + 1;
    let mut rows = Vec::new();
    for dy in -half..=half {
        let mut dx0 = None;
        let mut heights = Vec::new();
        for dx in -half..=half {
            let (fx, fy) = match model {
                PixelModel::Point | PixelModel::Facet => (f64::from(dx), f64::from(dy)),
                PixelModel::Column => {
                    ((f64::from(dx).abs() - 0.5).max(0.0), (f64::from(dy).abs() - 0.5).max(0.0))
                }
            };
            let r = pixel_mm * (fx * fx + fy * fy).sqrt();
            if let Some(h) = profile.height_at(r) {
                dx0.get_or_insert(dx);
                heights.push(h as f32);
            } else if dx0.is_some() {
                break;
            }
        }
        if let Some(dx0) = dx0 {
            rows.push(KernelRow { dy, dx0, heights });
        }
    }
    let half = rows
        .iter()
        .map(|r| r.dy.abs().max(r.dx0.abs()).max(r.dx0 + r.heights.len() as i32 - 1))
        .max()
        .unwrap_or(0);
    Kernel { rows, half }
}

/// Brute force, O(M·N·m·n): the obviously right reference the fast kernel is tested against.
pub fn compensate_reference(map: &HeightMap, kernel: &Kernel, outside_z: f32) -> Vec<f32> {
    let (w, h) = (map.width() as i64, map.height() as i64);
    let data = map.data();
    let at = |x: i64, y: i64| -> f32 {
        if x < 0 || y < 0 || x >= w || y >= h {
            return outside_z;
        }
        let z = data[(y * w + x) as usize];
        if z.is_nan() { outside_z } else { z }
    };
    let mut out = vec![f32::NEG_INFINITY; data.len()];
    for y in 0..h {
        for x in 0..w {
            let mut best = f32::NEG_INFINITY;
            for row in &kernel.rows {
                for (k, b) in row.heights.iter().enumerate() {
                    let v = at(x + i64::from(row.dx0) + k as i64, y + i64::from(row.dy)) - b;
                    if v > best {
                        best = v;
                    }
                }
            }
            out[(y * w + x) as usize] = best;
        }
    }
    out
}

/// The compensated tip surface of `map` for `profile`, on the same grid.
///
/// Renders the tool with [`kernel`] under `opts.pixel_model` and dilates the map with [`dilate`]:
/// equal to [`compensate_reference`] (the same f32 differences, maximised), in
/// O(W·H·(rows + pairs/lanes)) time, parallel over output rows. Errors: a non-finite
/// `outside_z_mm` ([`GeometryError::InvalidParameter`]).
pub fn compensate(
    map: &HeightMap,
    profile: &ToolProfile,
    opts: &CompensateOptions,
) -> Result<HeightMap, GeometryError> {
    let outside = opts.outside_z_mm.unwrap_or(map.z_min_mm());
    if !outside.is_finite() {
        return Err(GeometryError::invalid("outside_z_mm", outside, "a finite height"));
    }
    if opts.pixel_model == PixelModel::Facet {
        return compensate_facets(map, profile, outside as f32);
    }
    let k = kernel(profile, map.pixel_mm(), opts.pixel_model);
    let data = dilate(map, &k, outside as f32);
    HeightMap::new(*map.meta(), data)
}

/// [`compensate`] under [`PixelModel::Facet`]: the map's [`crate::facet::facet_nodes`] dilated by
/// the tool at half the pixel, read back at the cells' centres.
fn compensate_facets(
    map: &HeightMap,
    profile: &ToolProfile,
    outside: f32,
) -> Result<HeightMap, GeometryError> {
    let nodes = crate::facet::facet_nodes(map, crate::facet::FACET_STEEP_SLOPE)?;
    let k = kernel(profile, nodes.pixel_mm(), PixelModel::Point);
    // The node rows on the cells' centres (1, 3, 5, ...), then their nodes on the centres.
    let fine = dilate_rows(&nodes, &k, outside, 2);
    let (w, fw) = (map.width() as usize, nodes.width() as usize);
    let data = fine.chunks_exact(fw).flat_map(|row| (0..w).map(move |i| row[2 * i + 1])).collect();
    HeightMap::new(*map.meta(), data)
}

/// The fast counterpart of [`compensate_reference`], for any kernel (same inputs, same result up to
/// the sign of zero): `out(x, y) = max over kernel cells of A(x+dx, y+dy) - B(dx, dy)`, cells
/// outside the map and NaN cells reading as `outside_z`. An empty kernel gives −∞ everywhere.
///
/// See the module docs for the algorithm: kernel rows with equal profiles share one row maximum,
/// symmetric rows fold `±dx`, flat runs use a van Herk/Gil-Werman running maximum.
pub fn dilate(map: &HeightMap, kernel: &Kernel, outside_z: f32) -> Vec<f32> {
    dilate_rows(map, kernel, outside_z, 1)
}

/// [`dilate`] at the output rows `y` with `y % step == step / 2` only (every row for `step` 1;
/// rows 1, 3, 5, ... for 2), packed in order: what [`PixelModel::Facet`] reads back.
fn dilate_rows(map: &HeightMap, kernel: &Kernel, outside_z: f32, step: usize) -> Vec<f32> {
    let w = map.width() as usize;
    let h = map.height() as usize;
    let first = step / 2;
    let out_rows = if h > first { (h - first).div_ceil(step) } else { 0 };
    let groups = plan_groups(kernel);
    let padded = Padded::new(map, kernel, outside_z);
    if groups.is_empty() || w == 0 {
        return vec![f32::NEG_INFINITY; w * out_rows];
    }
    // Every cell is written below.
    let mut out = vec![0.0; w * out_rows];
    let bounds = Bounds::new(&padded, kernel, &groups);
    let stride = padded.stride;
    let cols = padded.cols;
    let tiles = cols / LANES;
    // A band holds BAND map rows, of which BAND / step are output.
    let per_band = BAND / step;
    out.par_chunks_mut(w * per_band).enumerate().for_each_init(
        || (Scratch::new(stride, cols), vec![(0u32, 0u32); tiles * groups.len()], BoundScratch::default()),
        |(scratch, ranges, res), (band, out_rows)| {
            let y0 = band * BAND;
            let y1 = (y0 + BAND).min(h);
            for t in 0..tiles {
                let tile = &mut ranges[t * groups.len()..(t + 1) * groups.len()];
                let x0 = t * LANES;
                let valid = LANES.min(w.saturating_sub(x0));
                let pruned = valid > 0
                    && bounds
                        .as_ref()
                        .is_some_and(|b| b.tile_ranges(&padded, &groups, y0, y1, x0, valid, tile, res));
                if !pruned {
                    for (r, g) in tile.iter_mut().zip(&groups) {
                        *r = (0, g.shape.len() as u32);
                    }
                }
            }
            for (k, y) in (y0 + first..y1).step_by(step).enumerate() {
                simd::dilate_row(&padded, &groups, ranges, y as i64, scratch);
                out_rows[k * w..(k + 1) * w].copy_from_slice(&scratch.acc[..w]);
            }
        },
    );
    out
}

/// Per-thread buffers of [`Bounds::tile_ranges`].
#[derive(Default)]
struct BoundScratch {
    res: Vec<f64>,
    span: Vec<f64>,
    colmax: Vec<f64>,
    ext: Vec<f64>,
}

/// Output rows sharing one set of [`Bounds`] per tile of [`LANES`] columns.
const BAND: usize = 32;
/// Side of the blocks whose maxima bound the map (cells).
const BLOCK: usize = 8;

/// Which kernel cells can matter, per tile of `BAND` output rows by [`LANES`] columns.
///
/// Over the cells a tile reads, the map is bounded above by a plane `g` plus `e_up` (from the
/// maxima of 8 x 8 blocks, with the plane's slack over a block), and over the tile's own cells
/// below by the same plane plus `e_lo` (exactly). A kernel cell `d` with height `h_d` adds at most
/// `e_up + g·(x + d) - h_d` to output cell `x`, which already holds at least `A(x) - h_0 >=
/// e_lo + g·x - h_0` from the kernel's centre: when `e_up - e_lo + g·d - h_d + h_0` is below zero
/// by more than the arithmetic's error, `d` cannot change the maximum (rounding is monotone, so
/// the f32 difference it gives is not above the centre's either) and is skipped. `e_up` is taken
/// per group of kernel rows over the block rows they read and per column pair over the block
/// columns it reads, so on smooth parts of the map only the kernel cells near the tool's contact
/// point are visited; on rough parts nothing is skipped. The result is the same maximum of the
/// same f32 differences: bit-identical.
struct Bounds {
    /// Block maxima: block `(bi, bj)` covers map rows `BLOCK·bi - ry ..` and padded columns
    /// `BLOCK·bj ..` (map columns `BLOCK·bj - pad ..`).
    max: Vec<f32>,
    brows: usize,
    bcols: usize,
    /// Rows the kernel reaches above and below a cell.
    ry: usize,
    /// Height of the kernel's centre cell.
    h0: f32,
    /// Largest |height| in the kernel.
    hmax: f64,
}

impl Bounds {
    /// `None` when the kernel has no centre cell (then there is no lower bound to prune with).
    fn new(padded: &Padded, kernel: &Kernel, groups: &[Group]) -> Option<Self> {
        // Flat runs cost one running maximum per row whatever is skipped: where they hold more
        // than a quarter of the pairs (flat and bull-nose tools) the bounds cannot pay for
        // themselves.
        let (mut in_runs, mut pairs) = (0, 0);
        for g in groups {
            pairs += g.shape.len();
            if let Shape::Symmetric { flat, .. } = &g.shape
                && *flat >= MIN_FLAT_RUN
            {
                in_runs += flat + 1;
            }
        }
        if in_runs * 4 > pairs {
            return None;
        }
        let h0 = kernel.rows.iter().find_map(|r| {
            let k = -i64::from(r.dx0);
            (r.dy == 0 && k >= 0 && (k as usize) < r.heights.len()).then(|| r.heights[k as usize])
        })?;
        let ry =
            kernel.rows.iter().filter(|r| !r.heights.is_empty()).map(|r| r.dy.unsigned_abs()).max()? as usize;
        let hmax =
            kernel.rows.iter().flat_map(|r| &r.heights).map(|h| f64::from(h.abs())).fold(0.0, f64::max);
        let rows = padded.height as usize + 2 * ry;
        let brows = rows.div_ceil(BLOCK);
        let bcols = padded.stride.div_ceil(BLOCK);
        let mut max = vec![f32::NEG_INFINITY; brows * bcols];
        max.par_chunks_mut(bcols).enumerate().for_each(|(bi, out)| {
            let mut colmax = vec![f32::NEG_INFINITY; padded.stride];
            for r in BLOCK * bi..(BLOCK * (bi + 1)).min(rows) {
                let row = padded.row(r as i64 - ry as i64);
                for (m, &v) in colmax.iter_mut().zip(row) {
                    *m = fmax(*m, v);
                }
            }
            for (o, c) in out.iter_mut().zip(colmax.chunks(BLOCK)) {
                *o = c.iter().copied().fold(f32::NEG_INFINITY, fmax);
            }
        });
        Some(Bounds { max, brows, bcols, ry, h0, hmax })
    }

    /// Writes, for the tile of output rows `y0..y1` and the `valid` columns from `x0`, each group's
    /// range of pairs (symmetric shapes: `|dx|`) or columns (general shapes) that can matter, as
    /// `(first, end)`. Returns false (nothing written) when the bounds are not finite.
    #[allow(clippy::too_many_arguments)]
    fn tile_ranges(
        &self,
        padded: &Padded,
        groups: &[Group],
        y0: usize,
        y1: usize,
        x0: usize,
        valid: usize,
        ranges: &mut [(u32, u32)],
        scratch: &mut BoundScratch,
    ) -> bool {
        let BoundScratch { res, span, colmax, ext } = scratch;
        let (ry, pad) = (self.ry as i64, padded.pad as i64);
        let (y0, y1, x0, valid) = (y0 as i64, y1 as i64, x0 as i64, valid as i64);
        let bs = BLOCK as i64;
        // The blocks holding every cell the tile reads.
        let (bi0, bi1) = (y0 / bs, ((y1 - 1 + 2 * ry) / bs).min(self.brows as i64 - 1));
        let (bj0, bj1) = (x0 / bs, ((x0 + valid - 1 + 2 * pad) / bs).min(self.bcols as i64 - 1));
        let (nr, nc) = ((bi1 - bi0 + 1) as usize, (bj1 - bj0 + 1) as usize);
        let cx = x0 as f64 + (valid - 1) as f64 / 2.0;
        let cy = y0 as f64 + (y1 - y0 - 1) as f64 / 2.0;
        let half_block = (bs as f64 - 1.0) / 2.0;
        let bx = |bj: i64| (bs * bj - pad) as f64 + half_block - cx;
        let by = |bi: i64| (bs * bi - ry) as f64 + half_block - cy;
        let at = |bi: i64, bj: i64| f64::from(self.max[bi as usize * self.bcols + bj as usize]);
        // The plane: least squares through the block maxima (on a full grid of blocks the x and
        // y slopes separate). Any plane gives valid bounds; a good one gives tight ones.
        let (mut sz, mut szx, mut szy, mut sabs) = (0.0, 0.0, 0.0, 0.0f64);
        for bi in bi0..=bi1 {
            for bj in bj0..=bj1 {
                let z = at(bi, bj);
                sz += z;
                szx += z * bx(bj);
                szy += z * by(bi);
                sabs = sabs.max(z.abs());
            }
        }
        let mean = |f: &dyn Fn(i64) -> f64, a: i64, b: i64| (a..=b).map(f).sum::<f64>() / (b - a + 1) as f64;
        let (mx, my) = (mean(&bx, bj0, bj1), mean(&by, bi0, bi1));
        let vx: f64 = (bj0..=bj1).map(|j| (bx(j) - mx).powi(2)).sum::<f64>() * nr as f64;
        let vy: f64 = (bi0..=bi1).map(|i| (by(i) - my).powi(2)).sum::<f64>() * nc as f64;
        let gx = if vx > 0.0 { (szx - mx * sz) / vx } else { 0.0 };
        let gy = if vy > 0.0 { (szy - my * sz) / vy } else { 0.0 };
        // Upper residuals per block (the plane's slack over a block included).
        let slack = (gx.abs() + gy.abs()) * half_block;
        res.clear();
        for bi in bi0..=bi1 {
            for bj in bj0..=bj1 {
                res.push(at(bi, bj) - gx * bx(bj) - gy * by(bi) + slack);
            }
        }
        // Lower residual over the tile's own cells.
        // In f32 (vectorised): the few roundings are covered by the margin below.
        let mut ramp = [0.0f32; LANES];
        for (i, r) in ramp.iter_mut().enumerate() {
            *r = (gx * ((x0 + i as i64) as f64 - cx)) as f32;
        }
        let mut lanes = [f32::INFINITY; LANES];
        for y in y0..y1 {
            let row = &padded.row(y)[(x0 + pad) as usize..(x0 + pad + valid) as usize];
            let off = (gy * (y as f64 - cy)) as f32;
            for ((m, &v), &r) in lanes.iter_mut().zip(row).zip(&ramp) {
                let r = v - r - off;
                if r < *m {
                    *m = r;
                }
            }
        }
        let e_lo = f64::from(lanes.iter().copied().fold(f32::INFINITY, f32::min));
        let reach = (2 * pad + valid + 2 * ry + (y1 - y0)) as f64;
        let scale = 1.0 + sabs + e_lo.abs() + (gx.abs() + gy.abs()) * reach + self.hmax;
        if !(scale.is_finite() && gx.is_finite() && gy.is_finite() && e_lo.is_finite()) {
            return false;
        }
        // Everything the arithmetic above can have rounded (a few f32 roundings at most), many
        // times over.
        let margin = scale * 4e-6;
        let base = f64::from(self.h0) - e_lo + margin;
        // span[(r0 · nr + r1) · nc + c]: the largest residual of block column c over block rows
        // r0..=r1.
        span.clear();
        span.resize(nr * nr * nc, f64::NEG_INFINITY);
        for r0 in 0..nr {
            let at = (r0 * nr + r0) * nc;
            span[at..at + nc].copy_from_slice(&res[r0 * nc..(r0 + 1) * nc]);
            for r1 in r0 + 1..nr {
                let (prev, next) = span.split_at_mut((r0 * nr + r1) * nc);
                let prev = &prev[(r0 * nr + r1 - 1) * nc..];
                for ((n, &p), &v) in next[..nc].iter_mut().zip(prev).zip(&res[r1 * nc..(r1 + 1) * nc]) {
                    *n = if v > p { v } else { p };
                }
            }
        }
        colmax.clear();
        colmax.resize(nc, f64::NEG_INFINITY);
        for (group, range) in groups.iter().zip(ranges.iter_mut()) {
            // The block rows this group's source rows fall in.
            colmax.fill(f64::NEG_INFINITY);
            let mut tdy = f64::NEG_INFINITY;
            for &dy in &group.dys {
                let dy = i64::from(dy);
                tdy = tdy.max(gy * dy as f64);
                let (r0, r1) =
                    (((y0 + dy + ry) / bs - bi0) as usize, ((y1 - 1 + dy + ry) / bs - bi0) as usize);
                let at = (r0 * nr + r1) * nc;
                for (m, &v) in colmax.iter_mut().zip(&span[at..at + nc]) {
                    if v > *m {
                        *m = v;
                    }
                }
            }
            // Block column of map column `x` (relative to the tile's blocks).
            let col = |x: i64| ((x + pad) / bs - bj0) as usize;
            let mut first = u32::MAX;
            let mut end = 0u32;
            match &group.shape {
                Shape::Symmetric { half, flat } => {
                    // Inside a flat run (one running maximum) only whether any pair can matter
                    // counts: the run's last pair has the largest bound of the run.
                    let skip = if *flat >= MIN_FLAT_RUN { *flat } else { 0 };
                    // ext[c]: the largest residual over block columns from c to the tile's own
                    // (either side), so pair j's bound is that at its two ends.
                    let (c0, c1) = (col(x0), col(x0 + valid - 1));
                    ext.clear();
                    ext.extend_from_slice(colmax);
                    let mid = colmax[c0..=c1].iter().copied().fold(f64::NEG_INFINITY, f64::max);
                    ext[c0..=c1].fill(mid);
                    for c in (0..c0).rev() {
                        ext[c] = ext[c].max(ext[c + 1]);
                    }
                    for c in c1 + 1..nc {
                        ext[c] = ext[c].max(ext[c - 1]);
                    }
                    let keep = |j: usize| {
                        let up = ext[col(x0 - j as i64)].max(ext[col(x0 + valid - 1 + j as i64)]);
                        up + gx.abs() * j as f64 + tdy - f64::from(half[j]) + base >= 0.0
                    };
                    // The first pair kept from the front, the last from the back.
                    if let Some(j) = (skip..half.len()).find(|&j| keep(j)) {
                        first = if j == skip { 0 } else { j as u32 };
                        end = (j..half.len()).rev().find(|&j| keep(j)).map_or(j, |l| l) as u32 + 1;
                    }
                }
                Shape::General { dx0, heights } => {
                    for (k, &h) in heights.iter().enumerate() {
                        let dx = i64::from(*dx0) + k as i64;
                        let up = colmax[col(x0 + dx)..=col(x0 + valid - 1 + dx)]
                            .iter()
                            .copied()
                            .fold(f64::NEG_INFINITY, f64::max);
                        if up + gx * dx as f64 + tdy - f64::from(h) + base >= 0.0 {
                            first = first.min(k as u32);
                            end = k as u32 + 1;
                        }
                    }
                }
            }
            *range = if first < end { (first, end) } else { (0, 0) };
        }
        true
    }
}

/// Output columns processed together; their accumulators stay in registers across a kernel row.
const LANES: usize = 64;
/// Shortest flat run (in cells either side of the centre) worth a running maximum.
const MIN_FLAT_RUN: usize = 3;

/// How one distinct row profile is applied.
#[derive(Debug, Clone, PartialEq)]
enum Shape {
    /// `heights[c + j] == heights[c - j]` about the centre column `c = -dx0`: `half[j]` is the
    /// height at `|dx| = j`; `half[0..=flat]` are all equal to `half[0]`.
    Symmetric { half: Vec<f32>, flat: usize },
    /// Anything else: every column on its own.
    General { dx0: i32, heights: Vec<f32> },
}

impl Shape {
    /// Number of pairs (symmetric) or columns (general).
    fn len(&self) -> usize {
        match self {
            Shape::Symmetric { half, .. } => half.len(),
            Shape::General { heights, .. } => heights.len(),
        }
    }
}

/// Kernel rows with the same profile (`dx0` and heights), applied once to the maximum of their
/// source rows.
#[derive(Debug, Clone, PartialEq)]
struct Group {
    dys: Vec<i32>,
    shape: Shape,
}

fn plan_groups(kernel: &Kernel) -> Vec<Group> {
    let mut groups: Vec<(i32, Vec<f32>, Vec<i32>)> = Vec::new();
    for row in &kernel.rows {
        if row.heights.is_empty() {
            continue;
        }
        let same = |g: &&mut (i32, Vec<f32>, Vec<i32>)| {
            g.0 == row.dx0
                && g.1.len() == row.heights.len()
                && g.1.iter().zip(&row.heights).all(|(a, b)| a.to_bits() == b.to_bits())
        };
        match groups.iter_mut().find(same) {
            Some(g) => g.2.push(row.dy),
            None => groups.push((row.dx0, row.heights.clone(), vec![row.dy])),
        }
    }
    groups
        .into_iter()
        .map(|(dx0, heights, dys)| {
            let n = heights.len();
            let symmetric = i64::from(dx0) + n as i64 - 1 == -i64::from(dx0)
                && (0..n).all(|i| heights[i].to_bits() == heights[n - 1 - i].to_bits());
            let shape = if symmetric {
                let half = heights[n / 2..].to_vec();
                let flat = half.iter().take_while(|h| h.to_bits() == half[0].to_bits()).count() - 1;
                Shape::Symmetric { half, flat }
            } else {
                Shape::General { dx0, heights }
            };
            Group { dys, shape }
        })
        .collect()
}

/// The map with NaN replaced by the floor, each row padded with `pad` floor cells on the left and
/// `pad` plus the rounding of the width to [`LANES`] on the right; rows outside the map read as one
/// floor row.
struct Padded {
    data: Vec<f32>,
    floor_row: Vec<f32>,
    stride: usize,
    pad: usize,
    /// Map width rounded up to a multiple of [`LANES`].
    cols: usize,
    height: i64,
}

impl Padded {
    fn new(map: &HeightMap, kernel: &Kernel, floor: f32) -> Self {
        let reach = kernel
            .rows
            .iter()
            .filter(|r| !r.heights.is_empty())
            .map(|r| i64::from(r.dx0).abs().max((i64::from(r.dx0) + r.heights.len() as i64 - 1).abs()))
            .max()
            .unwrap_or(0);
        let pad = reach as usize;
        let w = map.width() as usize;
        let cols = w.div_ceil(LANES) * LANES;
        let stride = cols + 2 * pad;
        // Zeroed (untouched pages until written), then every cell written once, rows in parallel.
        let mut data = vec![0.0; stride * map.height() as usize];
        data.par_chunks_exact_mut(stride).zip(map.data().par_chunks_exact(w.max(1))).for_each(
            |(dst, src)| {
                dst[..pad].fill(floor);
                for (d, &s) in dst[pad..pad + w].iter_mut().zip(src) {
                    *d = if s.is_nan() { floor } else { s };
                }
                dst[pad + w..].fill(floor);
            },
        );
        Padded { data, floor_row: vec![floor; stride], stride, pad, cols, height: i64::from(map.height()) }
    }

    fn row(&self, y: i64) -> &[f32] {
        if y < 0 || y >= self.height {
            &self.floor_row
        } else {
            let start = y as usize * self.stride;
            &self.data[start..start + self.stride]
        }
    }
}

/// Per-thread buffers.
struct Scratch {
    /// Maximum of a group's source rows (padded like [`Padded`]).
    m: Vec<f32>,
    /// The output row being built (`cols` cells).
    acc: Vec<f32>,
    /// Running-maximum buffers.
    run: Vec<f32>,
    prefix: Vec<f32>,
    suffix: Vec<f32>,
    /// Column spans of the row maximum still to build.
    spans: Vec<(usize, usize)>,
}

impl Scratch {
    fn new(stride: usize, cols: usize) -> Self {
        Scratch {
            m: vec![0.0; stride],
            acc: vec![f32::NEG_INFINITY; cols],
            run: vec![0.0; cols],
            prefix: Vec::new(),
            suffix: Vec::new(),
            spans: Vec::new(),
        }
    }
}

/// `a > b ? a : b` (one `maxps`; the operands here are never NaN).
#[inline(always)]
fn fmax(a: f32, b: f32) -> f32 {
    if a > b { a } else { b }
}

/// Longest window [`window_max`] handles by doubling; longer ones use [`running_max`].
const MAX_DOUBLING_WINDOW: usize = 128;

/// `out[i] = max(src[i .. i + w])` for every `i < out.len()`. Requires `w >= 1` and
/// `src.len() >= out.len() + w - 1`.
///
/// Up to [`MAX_DOUBLING_WINDOW`] cells by doubling (maxima of windows of 1, 2, 4, ... cells, then two
/// overlapping power-of-two windows per output: ⌈log2 w⌉ + 1 vectorised passes); longer windows by
/// [`running_max`] (three scalar passes whatever `w`).
pub(crate) fn window_max(src: &[f32], w: usize, out: &mut [f32], a: &mut Vec<f32>, b: &mut Vec<f32>) {
    if w > MAX_DOUBLING_WINDOW {
        running_max(src, w, out, a, b);
        return;
    }
    let mut len = out.len() + w - 1;
    a.clear();
    a.extend_from_slice(&src[..len]);
    b.clear();
    b.resize(len, 0.0);
    let mut span = 1;
    while span * 2 <= w {
        len -= span;
        for ((d, &x), &y) in b[..len].iter_mut().zip(&a[..len]).zip(&a[span..span + len]) {
            *d = fmax(x, y);
        }
        std::mem::swap(a, b);
        span *= 2;
    }
    // a[i] = max(src[i .. i + span]) with span <= w < 2·span.
    let shift = w - span;
    for ((o, &x), &y) in out.iter_mut().zip(&a[..]).zip(&a[shift..]) {
        *o = fmax(x, y);
    }
}

/// `out[i] = max(src[i .. i + w])` for every `i < out.len()` (van Herk/Gil-Werman: a prefix and a
/// suffix maximum per block of `w` cells, then one maximum per output: three comparisons per cell
/// whatever `w`). Requires `w >= 1` and `src.len() >= out.len() + w - 1`.
pub(crate) fn running_max(
    src: &[f32],
    w: usize,
    out: &mut [f32],
    prefix: &mut Vec<f32>,
    suffix: &mut Vec<f32>,
) {
    let n = out.len() + w - 1;
    let src = &src[..n];
    prefix.clear();
    prefix.extend_from_slice(src);
    suffix.clear();
    suffix.extend_from_slice(src);
    for block in prefix.chunks_mut(w) {
        for i in 1..block.len() {
            block[i] = fmax(block[i], block[i - 1]);
        }
    }
    for block in suffix.chunks_mut(w) {
        for i in (0..block.len().saturating_sub(1)).rev() {
            block[i] = fmax(block[i], block[i + 1]);
        }
    }
    for ((o, s), p) in out.iter_mut().zip(&suffix[..]).zip(&prefix[w - 1..]) {
        *o = fmax(*s, *p);
    }
}

/// The per-row kernel, compiled once portably and, on x86-64 with AVX2, once more for AVX2
/// (chosen at run time).
mod simd {
    #![allow(unsafe_code)]

    use super::{Group, Padded, Scratch, dilate_row_portable};

    pub(super) fn dilate_row(
        padded: &Padded,
        groups: &[Group],
        ranges: &[(u32, u32)],
        y: i64,
        scratch: &mut Scratch,
    ) {
        #[cfg(target_arch = "x86_64")]
        {
            if std::arch::is_x86_feature_detected!("avx512f") {
                // SAFETY: `dilate_row_avx512` only requires the CPU to support AVX-512F, checked just above.
                unsafe { dilate_row_avx512(padded, groups, ranges, y, scratch) };
                return;
            }
            if std::arch::is_x86_feature_detected!("avx2") {
                // SAFETY: `dilate_row_avx2` only requires the CPU to support AVX2, checked just above.
                unsafe { dilate_row_avx2(padded, groups, ranges, y, scratch) };
                return;
            }
        }
        dilate_row_portable(padded, groups, ranges, y, scratch);
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx512f")]
    fn dilate_row_avx512(
        padded: &Padded,
        groups: &[Group],
        ranges: &[(u32, u32)],
        y: i64,
        scratch: &mut Scratch,
    ) {
        dilate_row_portable(padded, groups, ranges, y, scratch);
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    fn dilate_row_avx2(
        padded: &Padded,
        groups: &[Group],
        ranges: &[(u32, u32)],
        y: i64,
        scratch: &mut Scratch,
    ) {
        dilate_row_portable(padded, groups, ranges, y, scratch);
    }
}

/// Builds output row `y` into `scratch.acc[..cols]`, applying to the tile of [`LANES`] columns `t`
/// only group `g`'s pairs (or columns) `ranges[t · groups + g]`.
#[inline(always)]
fn dilate_row_portable(
    padded: &Padded,
    groups: &[Group],
    ranges: &[(u32, u32)],
    y: i64,
    scratch: &mut Scratch,
) {
    let pad = padded.pad;
    let cols = padded.cols;
    let ng = groups.len();
    let Scratch { m, acc, run, prefix, suffix, spans } = scratch;
    acc.fill(f32::NEG_INFINITY);
    for (gi, group) in groups.iter().enumerate() {
        let tile_range = |t: usize| {
            let (a, b) = ranges[t * ng + gi];
            (a as usize, b as usize)
        };
        let tiles = cols / LANES;
        if (0..tiles).all(|t| tile_range(t).0 >= tile_range(t).1) {
            continue;
        }
        // The maximum of the group's source rows over columns s..e of the padded row.
        match &group.shape {
            Shape::Symmetric { half, flat } => {
                let mut start = 0;
                let run_needed = *flat >= MIN_FLAT_RUN
                    && (0..tiles).any(|t| {
                        let (a, b) = tile_range(t);
                        a < b && a <= *flat
                    });
                if run_needed {
                    fill_rows(m, padded, &group.dys, y, 0, padded.stride);
                } else {
                    fill_spans(m, spans, padded, &group.dys, y, tiles, tile_range, |b, _, end| {
                        (pad + b + 1 - end, pad + b + LANES + end - 1)
                    });
                }
                if *flat >= MIN_FLAT_RUN {
                    // Columns |dx| <= flat share the height half[0]: one running maximum.
                    if run_needed {
                        window_max(&m[pad - flat..], 2 * flat + 1, &mut run[..cols], prefix, suffix);
                        let h0 = half[0];
                        for (a, &r) in acc.iter_mut().zip(run.iter()) {
                            *a = fmax(*a, r - h0);
                        }
                    }
                    start = flat + 1;
                }
                for (t, b) in (0..cols).step_by(LANES).enumerate() {
                    let (lo, end) = tile_range(t);
                    let lo = lo.max(start);
                    if lo >= end {
                        continue;
                    }
                    let mut a: [f32; LANES] = lanes(&acc[b..]);
                    for (j, &h) in (lo..end).zip(&half[lo..end]) {
                        let lo: [f32; LANES] = lanes(&m[pad + b - j..]);
                        let hi: [f32; LANES] = lanes(&m[pad + b + j..]);
                        for l in 0..LANES {
                            a[l] = fmax(a[l], fmax(lo[l], hi[l]) - h);
                        }
                    }
                    acc[b..b + LANES].copy_from_slice(&a);
                }
            }
            Shape::General { dx0, heights } => {
                // pad + dx0 >= 0 by the choice of pad.
                let at0 = (pad as i64 + i64::from(*dx0)) as usize;
                fill_spans(m, spans, padded, &group.dys, y, tiles, tile_range, |b, lo, end| {
                    (at0 + b + lo, at0 + b + end - 1 + LANES)
                });
                for (t, b) in (0..cols).step_by(LANES).enumerate() {
                    let (lo, end) = tile_range(t);
                    if lo >= end {
                        continue;
                    }
                    let mut a: [f32; LANES] = lanes(&acc[b..]);
                    for (k, &h) in (lo..end).zip(&heights[lo..end]) {
                        // pad + dx0 >= 0 by the choice of pad.
                        let at = (pad as i64 + i64::from(*dx0)) as usize + b + k;
                        let v: [f32; LANES] = lanes(&m[at..]);
                        for l in 0..LANES {
                            a[l] = fmax(a[l], v[l] - h);
                        }
                    }
                    acc[b..b + LANES].copy_from_slice(&a);
                }
            }
        }
    }
}

/// `m[s..e]` = the maximum of the padded rows `y + dy`, `dy` in `dys`, over columns `s..e`.
#[inline(always)]
fn fill_rows(m: &mut [f32], padded: &Padded, dys: &[i32], y: i64, s: usize, e: usize) {
    let mut dys = dys.iter();
    if let Some(&first) = dys.next() {
        m[s..e].copy_from_slice(&padded.row(y + i64::from(first))[s..e]);
    }
    for &dy in dys {
        for (a, &b) in m[s..e].iter_mut().zip(&padded.row(y + i64::from(dy))[s..e]) {
            *a = fmax(*a, b);
        }
    }
}

/// [`fill_rows`] over the union of the columns the tiles with pairs left read: tile `t`'s
/// range `tile_range(t)` reads `span(first column, first pair, end)`. (Spans of kernels wider than
/// a tile need not start in tile order, so they are sorted before they are merged.)
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn fill_spans(
    m: &mut [f32],
    spans: &mut Vec<(usize, usize)>,
    padded: &Padded,
    dys: &[i32],
    y: i64,
    tiles: usize,
    tile_range: impl Fn(usize) -> (usize, usize),
    span: impl Fn(usize, usize, usize) -> (usize, usize),
) {
    spans.clear();
    for t in 0..tiles {
        let (lo, end) = tile_range(t);
        if lo < end {
            spans.push(span(t * LANES, lo, end));
        }
    }
    spans.sort_unstable_by_key(|s| s.0);
    let (mut s0, mut e0) = (0, 0);
    for &(s, e) in spans.iter() {
        if s > e0 {
            if s0 < e0 {
                fill_rows(m, padded, dys, y, s0, e0);
            }
            s0 = s;
        }
        e0 = e0.max(e);
    }
    if s0 < e0 {
        fill_rows(m, padded, dys, y, s0, e0);
    }
}

/// The first [`LANES`] values of `s` as an array (one bounds check instead of one per lane).
#[inline(always)]
fn lanes(s: &[f32]) -> [f32; LANES] {
    let mut a = [0.0; LANES];
    a.copy_from_slice(&s[..LANES]);
    a
}

/// The surface `tool` leaves of the part `map` at best: the map dilated by the tool into the
/// surface its tip follows, then eroded back by the tool (material stays where the tool cannot
/// reach into a concave corner or a narrow pocket; never below the map). `None` when the tool is
/// smaller than a cell.
pub fn opened(map: &HeightMap, tool: &ToolProfile) -> Option<HeightMap> {
    let k = kernel(tool, map.pixel_mm(), PixelModel::Point);
    if k.rows.is_empty() {
        return None;
    }
    let tip = dilate(map, &k, map.z_min_mm() as f32);
    let meta = *map.meta();
    let neg: Vec<f32> = tip.iter().map(|z| -z).collect();
    let neg_map = HeightMap::new(meta, neg).ok()?;
    // Erosion = −dilation of the negated surface (the tool is symmetric); outside the map there
    // is nothing to erode against.
    let surface: Vec<f32> = dilate(&neg_map, &k, f32::NEG_INFINITY).into_iter().map(|z| -z).collect();
    let data = surface
        .iter()
        .zip(map.data())
        .map(|(&s, &t)| if t.is_finite() { s.max(t) } else { f32::NAN })
        .collect();
    HeightMap::new(meta, data).ok()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::HeightMapMeta;
    use proptest::prelude::*;

    fn map_of(w: u32, h: u32, pixel: f64, data: Vec<f32>) -> HeightMap {
        let mut meta = HeightMapMeta::new(w, h, pixel);
        meta.z_min_mm = -1.0;
        meta.z_max_mm = 10.0;
        HeightMap::new(meta, data).expect("map")
    }

    fn profiles() -> Vec<ToolProfile> {
        vec![
            ToolProfile::ball(6.0).expect("ball"),
            ToolProfile::ball(1.3).expect("ball"),
            ToolProfile::flat(3.0).expect("flat"),
            ToolProfile::flat(0.25).expect("flat small"),
            ToolProfile::bull(4.0, 0.5).expect("bull"),
            ToolProfile::v(3.0, 90.0, 0.0).expect("v"),
            ToolProfile::v(4.0, 60.0, 1.2).expect("v tip"),
            ToolProfile::custom(vec![0.0, 0.4, 0.9, 1.5], vec![0.0, 0.0, 0.7, 2.0]).expect("custom"),
        ]
    }

    fn assert_close(fast: &[f32], slow: &[f32], what: &str) {
        assert_eq!(fast.len(), slow.len());
        for (i, (a, b)) in fast.iter().zip(slow).enumerate() {
            assert!((a - b).abs() <= 1e-4 || a == b, "{what}: cell {i}: fast {a} vs reference {b}");
        }
    }

    #[test]
    fn matches_the_reference_for_every_shape_and_model() {
        let (w, h) = (37u32, 23u32);
        let data: Vec<f32> = (0..w * h)
            .map(|i| {
                let (x, y) = (f64::from(i % w), f64::from(i / w));
                if i % 17 == 3 { f32::NAN } else { ((x * 0.7).sin() * 2.0 + (y * 0.4).cos() * 3.0) as f32 }
            })
            .collect();
        let map = map_of(w, h, 0.1, data);
        for profile in profiles() {
            for model in [PixelModel::Point, PixelModel::Column] {
                let k = kernel(&profile, 0.1, model);
                let slow = compensate_reference(&map, &k, -1.0);
                let opts = CompensateOptions { pixel_model: model, outside_z_mm: Some(-1.0) };
                let fast = compensate(&map, &profile, &opts).expect("compensate");
                assert_close(fast.data(), &slow, &format!("{profile:?} {model:?}"));
            }
        }
    }

    #[test]
    fn flat_tool_on_a_spike_gives_its_disk() {
        let mut data = vec![0.0f32; 21 * 21];
        data[10 * 21 + 10] = 5.0;
        let map = map_of(21, 21, 1.0, data);
        let opts = CompensateOptions { pixel_model: PixelModel::Point, outside_z_mm: Some(0.0) };
        let c = compensate(&map, &ToolProfile::flat(10.0).expect("flat"), &opts).expect("c");
        for y in 0..21i32 {
            for x in 0..21i32 {
                let inside = (x - 10).pow(2) + (y - 10).pow(2) <= 25;
                let z = c.get(x as u32, y as u32).expect("cell");
                assert_eq!(z, if inside { 5.0 } else { 0.0 }, "({x}, {y})");
            }
        }
    }

    #[test]
    fn general_kernels_match_the_reference() {
        // Not symmetric and with a hole-free but off-centre row: the fallback path.
        let k = Kernel {
            rows: vec![
                KernelRow { dy: -2, dx0: 1, heights: vec![0.5, 0.1, 0.3] },
                KernelRow { dy: 0, dx0: -3, heights: vec![0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0] },
                KernelRow { dy: 1, dx0: -1, heights: vec![0.2, 0.0, 0.2] },
                KernelRow { dy: 3, dx0: -1, heights: vec![0.2, 0.0, 0.2] },
            ],
            half: 3,
        };
        let data: Vec<f32> = (0..15 * 9).map(|i| ((i * 7919) % 31) as f32 * 0.1).collect();
        let map = map_of(15, 9, 1.0, data);
        assert_close(&dilate(&map, &k, 0.25), &compensate_reference(&map, &k, 0.25), "general");
        // On a smooth map wider and taller than one tile, where the bounds skip columns.
        let (w, h) = (150u32, 70u32);
        let data =
            (0..w * h).map(|i| (0.03 * f64::from(i % w) + 0.01 * f64::from(i / w)).sin() as f32).collect();
        let map = map_of(w, h, 1.0, data);
        let (fast, slow) = (dilate(&map, &k, -1.0), compensate_reference(&map, &k, -1.0));
        assert!(fast.iter().zip(&slow).all(|(a, b)| identical(*a, *b)));
        let empty = Kernel { rows: vec![], half: 0 };
        assert!(dilate(&map, &empty, 0.0).iter().all(|z| *z == f32::NEG_INFINITY));
    }

    #[test]
    fn kernels_wider_than_a_tile_match_the_reference_bit_for_bit() {
        // A ball reaching 71 cells (more than a tile of 64 columns) over a plane on the left,
        // where the bounds keep a few pairs for the first tile, and rough ground from column 140,
        // which the second tile reaches: its columns start left of the first tile's.
        let (w, h) = (260u32, 40u32);
        let data = (0..w * h)
            .map(|i| {
                let (x, y) = (i % w, i / w);
                let z = if x < 140 {
                    0.0005 * f64::from(x) + 0.0002 * f64::from(y)
                } else {
                    f64::from((i * 7919) % 31) * 0.1
                };
                z as f32
            })
            .collect();
        let map = map_of(w, h, 0.1, data);
        let k = kernel(&ToolProfile::ball(14.0).expect("ball"), 0.1, PixelModel::Point);
        assert!(k.half > LANES as i32);
        let (fast, slow) = (dilate(&map, &k, -1.0), compensate_reference(&map, &k, -1.0));
        for (i, (a, b)) in fast.iter().zip(&slow).enumerate() {
            assert!(identical(*a, *b), "cell {i}: {a} vs {b}");
        }
    }

    #[test]
    fn window_maxima_match_brute_force() {
        let src: Vec<f32> = (0..400).map(|i| ((i * 37) % 23) as f32 - (i as f32) * 0.01).collect();
        for (w, fast) in (1..300).flat_map(|w| [(w, true), (w, false)]) {
            let n = src.len() + 1 - w;
            let mut out = vec![0.0; n];
            if fast {
                window_max(&src, w, &mut out, &mut Vec::new(), &mut Vec::new());
            } else {
                running_max(&src, w, &mut out, &mut Vec::new(), &mut Vec::new());
            }
            for (i, o) in out.iter().enumerate() {
                let brute = src[i..i + w].iter().copied().fold(f32::NEG_INFINITY, f32::max);
                assert_eq!(*o, brute, "w {w} i {i}");
            }
        }
    }

    #[test]
    fn rejects_a_non_finite_floor() {
        let map = map_of(3, 3, 1.0, vec![0.0; 9]);
        let opts = CompensateOptions { pixel_model: PixelModel::Point, outside_z_mm: Some(f64::NAN) };
        assert!(compensate(&map, &ToolProfile::ball(2.0).expect("b"), &opts).is_err());
    }

    fn arb_profile() -> impl Strategy<Value = ToolProfile> {
        prop_oneof![
            (0.05f64..3.0).prop_map(|d| ToolProfile::ball(d).expect("ball")),
            (0.05f64..3.0).prop_map(|d| ToolProfile::flat(d).expect("flat")),
            (0.05f64..3.0, 0.0f64..1.0).prop_map(|(d, f)| ToolProfile::bull(d, f * d / 2.0).expect("bull")),
            (0.05f64..3.0, 10.0f64..170.0, 0.0f64..0.9)
                .prop_map(|(d, a, f)| ToolProfile::v(d, a, f * d).expect("v")),
            prop::collection::vec((0.0f64..0.5, 0.0f64..1.0), 1..6).prop_map(|steps| {
                let (mut r, mut h) = (vec![0.0], vec![0.0]);
                for (dr, dh) in steps {
                    r.push(r[r.len() - 1] + dr);
                    h.push(h[h.len() - 1] + dh);
                }
                if let Some(last) = r.last_mut() {
                    *last += 0.05;
                }
                ToolProfile::custom(r, h).expect("custom")
            }),
        ]
    }

    fn arb_map() -> impl Strategy<Value = HeightMap> {
        (1u32..40, 1u32..20, 0.05f64..0.3).prop_flat_map(|(w, h, pixel)| {
            prop::collection::vec(prop_oneof![9 => -2.0f32..5.0, 1 => Just(f32::NAN)], (w * h) as usize)
                .prop_map(move |data| map_of(w, h, pixel, data))
        })
    }

    /// A smooth random surface (plane, bowl or dome, waves) with optional steps, holes and
    /// noise: the maps where the bounds skip most of the kernel.
    fn arb_smooth_map() -> impl Strategy<Value = HeightMap> {
        (
            (1u32..100, 1u32..40, 0.05f64..0.3),
            (-3.0f64..3.0, -1.0f64..1.0, -1.0f64..1.0, -0.05f64..0.05),
            (0.0f64..0.5, 0.02f64..0.5, 0.0f64..1.0),
            (any::<bool>(), -2.0f64..2.0, any::<bool>(), 0.0f64..0.01),
        )
            .prop_map(
                |((w, h, pixel), (z0, gx, gy, curv), (amp, freq, phase), (step, rise, hole, noise))| {
                    let data = (0..w * h)
                        .map(|i| {
                            let (x, y) = (f64::from(i % w), f64::from(i / w));
                            let (u, v) = (x * pixel, y * pixel);
                            if hole
                                && (x - f64::from(w) / 3.0).abs() < 3.0
                                && (y - f64::from(h) / 2.0).abs() < 2.0
                            {
                                return f32::NAN;
                            }
                            let mut z = z0 + gx * u + gy * v + curv * ((u - 2.0).powi(2) + (v - 1.0).powi(2));
                            z += amp * (freq * u + phase).sin() * (freq * v).cos();
                            if step && x > f64::from(w) / 2.0 {
                                z += rise;
                            }
                            // Deterministic "noise" from the cell index.
                            z += noise * ((i.wrapping_mul(2_654_435_761) % 1000) as f64 / 500.0 - 1.0);
                            z as f32
                        })
                        .collect();
                    map_of(w, h, pixel, data)
                },
            )
    }

    #[test]
    fn bounds_skip_most_of_a_ball_on_a_sloped_plane() {
        let (w, h) = (256u32, 96u32);
        let data = (0..w * h)
            .map(|i| (0.2 * f64::from(i % w) * 0.1 + 0.05 * f64::from(i / w) * 0.1) as f32)
            .collect();
        let map = map_of(w, h, 0.1, data);
        let k = kernel(&ToolProfile::ball(6.0).expect("ball"), 0.1, PixelModel::Point);
        let groups = plan_groups(&k);
        let padded = Padded::new(&map, &k, -1.0);
        let bounds = Bounds::new(&padded, &k, &groups).expect("a centre cell");
        let mut ranges = vec![(0, 0); groups.len()];
        let full: usize = groups.iter().map(|g| g.shape.len()).sum();
        // An interior tile: everything it reads lies on the plane.
        assert!(bounds.tile_ranges(
            &padded,
            &groups,
            40,
            56,
            128,
            LANES,
            &mut ranges,
            &mut BoundScratch::default()
        ));
        let kept: usize = ranges.iter().map(|&(a, b)| (b - a) as usize).sum();
        assert!(kept * 3 < full, "kept {kept} of {full} pairs");
        // The centre pair is always kept.
        let centre = groups.iter().position(|g| g.dys.contains(&0)).expect("dy 0");
        assert_eq!(ranges[centre].0, 0);
        let fast = dilate(&map, &k, -1.0);
        let slow = compensate_reference(&map, &k, -1.0);
        assert!(fast.iter().zip(&slow).all(|(a, b)| identical(*a, *b)));
    }

    /// The same f32, up to the sign of a zero.
    fn identical(a: f32, b: f32) -> bool {
        a.to_bits() == b.to_bits() || (a == 0.0 && b == 0.0)
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(264))]
        /// Bit for bit, on random maps (where the bounds skip nothing) and on smooth ones (where
        /// they skip most of a kernel).
        #[test]
        fn fast_equals_reference(
            map in prop_oneof![3 => arb_map(), 1 => arb_smooth_map()],
            profile in arb_profile(),
            column in any::<bool>(),
            floor in prop_oneof![Just(None), (-3.0f64..6.0).prop_map(Some)],
        ) {
            let model = if column { PixelModel::Column } else { PixelModel::Point };
            let opts = CompensateOptions { pixel_model: model, outside_z_mm: floor };
            let outside = floor.unwrap_or(map.z_min_mm()) as f32;
            let slow = compensate_reference(&map, &kernel(&profile, map.pixel_mm(), model), outside);
            let fast = compensate(&map, &profile, &opts).expect("compensate");
            for (i, (a, b)) in fast.data().iter().zip(&slow).enumerate() {
                prop_assert!(identical(*a, *b), "cell {}: {} vs {}", i, a, b);
            }
        }
    }
}
