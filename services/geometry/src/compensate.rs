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
//! Cost: O(W·H·(R + P)) for R kernel rows and P = the number of column pairs outside the flat runs
//! (about a quarter of the kernel cells for a ball), with no data-dependent branches. Memory: one
//! padded copy of the map plus a few rows per thread.
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

/// Renders `profile` as a [`Kernel`] at `pixel_mm` under `model`.
pub fn kernel(profile: &ToolProfile, pixel_mm: f64, model: PixelModel) -> Kernel {
    let radius = profile.radius_mm();
    let half = (radius / pixel_mm).floor() as i32 + 1;
    let mut rows = Vec::new();
    for dy in -half..=half {
        let mut dx0 = None;
        let mut heights = Vec::new();
        for dx in -half..=half {
            let (fx, fy) = match model {
                PixelModel::Point => (f64::from(dx), f64::from(dy)),
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
    let k = kernel(profile, map.pixel_mm(), opts.pixel_model);
    let data = dilate(map, &k, outside as f32);
    HeightMap::new(*map.meta(), data)
}

/// The fast counterpart of [`compensate_reference`], for any kernel (same inputs, same result up to
/// the sign of zero): `out(x, y) = max over kernel cells of A(x+dx, y+dy) - B(dx, dy)`, cells
/// outside the map and NaN cells reading as `outside_z`. An empty kernel gives −∞ everywhere.
///
/// See the module docs for the algorithm: kernel rows with equal profiles share one row maximum,
/// symmetric rows fold `±dx`, flat runs use a van Herk/Gil-Werman running maximum.
pub fn dilate(map: &HeightMap, kernel: &Kernel, outside_z: f32) -> Vec<f32> {
    let w = map.width() as usize;
    let groups = plan_groups(kernel);
    let padded = Padded::new(map, kernel, outside_z);
    let mut out = vec![f32::NEG_INFINITY; map.data().len()];
    if groups.is_empty() {
        return out;
    }
    let stride = padded.stride;
    let cols = padded.cols;
    out.par_chunks_mut(w).enumerate().for_each_init(
        || Scratch::new(stride, cols),
        |scratch, (y, out_row)| {
            simd::dilate_row(&padded, &groups, y as i64, scratch);
            out_row.copy_from_slice(&scratch.acc[..w]);
        },
    );
    out
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
        let mut data = vec![floor; stride * map.height() as usize];
        for (dst, src) in data.chunks_exact_mut(stride).zip(map.data().chunks_exact(w)) {
            for (d, &s) in dst[pad..pad + w].iter_mut().zip(src) {
                *d = if s.is_nan() { floor } else { s };
            }
        }
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
}

impl Scratch {
    fn new(stride: usize, cols: usize) -> Self {
        Scratch {
            m: vec![0.0; stride],
            acc: vec![f32::NEG_INFINITY; cols],
            run: vec![0.0; cols],
            prefix: Vec::new(),
            suffix: Vec::new(),
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

    pub(super) fn dilate_row(padded: &Padded, groups: &[Group], y: i64, scratch: &mut Scratch) {
        #[cfg(target_arch = "x86_64")]
        {
            if std::arch::is_x86_feature_detected!("avx512f") {
                // SAFETY: `dilate_row_avx512` only requires the CPU to support AVX-512F, checked just above.
                unsafe { dilate_row_avx512(padded, groups, y, scratch) };
                return;
            }
            if std::arch::is_x86_feature_detected!("avx2") {
                // SAFETY: `dilate_row_avx2` only requires the CPU to support AVX2, checked just above.
                unsafe { dilate_row_avx2(padded, groups, y, scratch) };
                return;
            }
        }
        dilate_row_portable(padded, groups, y, scratch);
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx512f")]
    fn dilate_row_avx512(padded: &Padded, groups: &[Group], y: i64, scratch: &mut Scratch) {
        dilate_row_portable(padded, groups, y, scratch);
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    fn dilate_row_avx2(padded: &Padded, groups: &[Group], y: i64, scratch: &mut Scratch) {
        dilate_row_portable(padded, groups, y, scratch);
    }
}

/// Builds output row `y` into `scratch.acc[..cols]`.
#[inline(always)]
fn dilate_row_portable(padded: &Padded, groups: &[Group], y: i64, scratch: &mut Scratch) {
    let pad = padded.pad;
    let cols = padded.cols;
    let Scratch { m, acc, run, prefix, suffix } = scratch;
    acc.fill(f32::NEG_INFINITY);
    for group in groups {
        // The maximum of the group's source rows.
        let mut dys = group.dys.iter();
        let Some(&first) = dys.next() else { continue };
        m.copy_from_slice(padded.row(y + i64::from(first)));
        for &dy in dys {
            for (a, &b) in m.iter_mut().zip(padded.row(y + i64::from(dy))) {
                *a = fmax(*a, b);
            }
        }
        match &group.shape {
            Shape::Symmetric { half, flat } => {
                let mut start = 0;
                if *flat >= MIN_FLAT_RUN {
                    // Columns |dx| <= flat share the height half[0]: one running maximum.
                    window_max(&m[pad - flat..], 2 * flat + 1, &mut run[..cols], prefix, suffix);
                    let h0 = half[0];
                    for (a, &r) in acc.iter_mut().zip(run.iter()) {
                        *a = fmax(*a, r - h0);
                    }
                    start = flat + 1;
                }
                for b in (0..cols).step_by(LANES) {
                    let mut a: [f32; LANES] = lanes(&acc[b..]);
                    for (j, &h) in half.iter().enumerate().skip(start) {
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
                for b in (0..cols).step_by(LANES) {
                    let mut a: [f32; LANES] = lanes(&acc[b..]);
                    for (k, &h) in heights.iter().enumerate() {
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
        let empty = Kernel { rows: vec![], half: 0 };
        assert!(dilate(&map, &empty, 0.0).iter().all(|z| *z == f32::NEG_INFINITY));
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

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(200))]
        #[test]
        fn fast_equals_reference(
            map in arb_map(),
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
                prop_assert!((a - b).abs() <= 1e-4 || a == b, "cell {}: {} vs {}", i, a, b);
            }
        }
    }
}
