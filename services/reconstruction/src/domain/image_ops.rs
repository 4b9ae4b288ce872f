//! Image work on height maps: histogram stretch, edge-preserving denoise (median, bilateral),
//! grayscale and binary morphology with a flat disk, and reading foreign depth images.
//!
//! The linear gray mapping (black = `z_min`, white = `z_max`) and the PNG/`.npy` I/O live in
//! `depthmill_geometry` (`png_io`, `npy`, `HeightMap::read`/`write`); this module builds on them.
//!
//! # Conventions
//!
//! Only finite heights are data. Every filter is NaN-aware: a cell without data stays as it is
//! (NaN stays NaN) and neighbours without data are ignored, so holes neither grow nor shrink and
//! never leak into their surroundings. Windows are clipped at the grid border (cells outside the
//! grid are ignored, never padded). Outputs keep the input's metadata. All filters run in
//! parallel by rows.
//!
//! # Foreign images
//!
//! [`read_foreign_image`] reads 8/16-bit gray or RGB(A) PNGs such as those made for LinuxCNC's
//! `image-to-gcode`. That program reads the picture's top row as maximum Y (as `png_io` does),
//! reduces colour to Rec.601 luma (PIL's `convert("L")`: `0.299 R + 0.587 G + 0.114 B`, as
//! `png_io` does) and by default takes white as the top of the part (Z = 0) and black as the
//! deepest cut (Z = −depth), which is depthmill's black = `z_min`, white = `z_max` with
//! `z_min = −depth`, `z_max = 0`; its "Invert Image" option swaps them (black = top), which is
//! our `invert`. Its "Normalize Image" option (stretch the gray values to the full depth)
//! changes heights; [`stretch`] does not (it changes the exchange range instead).

use std::path::Path;

use depthmill_geometry::{Face, HeightMap, HeightMapMeta, ImageMapping, read_png};
use rayon::prelude::*;

use crate::domain::error::{ReconError, Result};

/// Largest median radius in pixels (a 129×129 window).
pub const MAX_MEDIAN_RADIUS_PX: u32 = 64;

/// Largest bilateral window radius in pixels, `⌈2.5·sigma_space/p⌉`.
pub const MAX_BILATERAL_RADIUS_PX: u32 = 64;

// ---------------------------------------------------------------------------------------------
// Histogram stretch

/// Sets the map's Z range (the heights shown black and white when exchanged as an image) to the
/// `low_pct` and `high_pct` percentiles of its data, so the image uses the full gray range;
/// `0`/`100` are the min/max, and the percentiles interpolate linearly between order statistics
/// (position `pct/100 · (n − 1)`, NumPy's default). Heights are unchanged: those outside the new
/// range clamp to black/white on export (robust stretching, e.g. `2`/`98`, ignores outliers).
///
/// Errors: percentiles not finite or not `0 <= low < high <= 100`; a map without data; data
/// whose two percentiles coincide (nothing to stretch).
pub fn stretch(map: &HeightMap, low_pct: f64, high_pct: f64) -> Result<HeightMap> {
    if !(low_pct.is_finite() && (0.0..100.0).contains(&low_pct)) {
        return Err(ReconError::param("stretch low_pct", low_pct, "must be in [0, 100)"));
    }
    if !(high_pct.is_finite() && high_pct > low_pct && high_pct <= 100.0) {
        return Err(ReconError::param("stretch high_pct", high_pct, format!("must be in ({low_pct}, 100]")));
    }
    let mut values: Vec<f32> = map.data().iter().copied().filter(|z| z.is_finite()).collect();
    if values.is_empty() {
        return Err(ReconError::Empty("stretch: the map has no data".into()));
    }
    let lo = percentile(&mut values, low_pct);
    let hi = percentile(&mut values, high_pct);
    if lo >= hi {
        return Err(ReconError::param(
            "stretch high_pct",
            high_pct,
            format!("the data is flat at {lo} mm between the {low_pct} and {high_pct} percentiles"),
        ));
    }
    let mut out = map.clone();
    out.set_z_range(lo, hi)?;
    Ok(out)
}

/// Linear-interpolated percentile of nonempty `values` (reorders them).
fn percentile(values: &mut [f32], pct: f64) -> f64 {
    let pos = pct / 100.0 * (values.len() - 1) as f64;
    // 0 <= pos <= len − 1.
    let i = (pos.floor() as usize).min(values.len() - 1);
    let (_, &mut a, rest) = values.select_nth_unstable_by(i, f32::total_cmp);
    let a = f64::from(a);
    let frac = pos - i as f64;
    match rest.iter().copied().min_by(f32::total_cmp) {
        Some(b) if frac > 0.0 => a + (f64::from(b) - a) * frac,
        _ => a,
    }
}

// ---------------------------------------------------------------------------------------------
// Median

/// Order-preserving key of a finite f32 (total order; −0 sorts before +0).
fn key(z: f32) -> u32 {
    let b = z.to_bits();
    if b & 0x8000_0000 != 0 { !b } else { b | 0x8000_0000 }
}

fn unkey(k: u32) -> f32 {
    f32::from_bits(if k & 0x8000_0000 != 0 { k & 0x7fff_ffff } else { !k })
}

/// Key of a cell without data (above every finite key).
const NO_KEY: u32 = u32::MAX;

/// Median filter over the square `(2r+1)²` window (`r = radius_px`, clipped at the border),
/// NaN-aware (see the module docs). The result is the element of rank `⌊(n−1)/2⌋` of the `n`
/// data cells in the window (the lower median when `n` is even), so it is always one of the
/// input heights and a straight step edge is kept exactly. `radius_px = 0` copies the map.
///
/// Algorithm: heights are mapped once to order-preserving `u32` keys; per cell the window's
/// data keys are gathered and the middle one selected (introselect, O(window)), so the cost is
/// O(w·h·(2r+1)²) and no precision is lost. (A sliding sorted window was slower in our
/// measurements for every radius up to 4.)
pub fn median(map: &HeightMap, radius_px: u32) -> Result<HeightMap> {
    if radius_px > MAX_MEDIAN_RADIUS_PX {
        return Err(ReconError::param(
            "median radius_px",
            radius_px,
            format!("must be at most {MAX_MEDIAN_RADIUS_PX}"),
        ));
    }
    let r = radius_px as usize;
    let (w, h) = (map.width() as usize, map.height() as usize);
    let keys: Vec<u32> = map.data().iter().map(|&z| if z.is_finite() { key(z) } else { NO_KEY }).collect();
    let mut out = map.clone();
    out.data_mut().par_chunks_mut(w).enumerate().for_each(|(j, row)| {
        let (j0, j1) = (j.saturating_sub(r), (j + r).min(h - 1));
        let band = &keys[j0 * w..(j1 + 1) * w];
        let own = &keys[j * w..(j + 1) * w];
        median_row(band, own, w, r, row);
    });
    Ok(out)
}

/// One output row; `band` holds the window's rows of keys, `own` the row's own keys.
fn median_row(band: &[u32], own: &[u32], w: usize, r: usize, row: &mut [f32]) {
    let mut buf: Vec<u32> = Vec::with_capacity((2 * r + 1) * (2 * r + 1));
    for (i, z) in row.iter_mut().enumerate() {
        if own[i] == NO_KEY {
            continue;
        }
        let (i0, i1) = (i.saturating_sub(r), (i + r).min(w - 1));
        buf.clear();
        for line in band.chunks_exact(w) {
            buf.extend(line[i0..=i1].iter().copied().filter(|&k| k != NO_KEY));
        }
        // The cell itself is data, so buf is not empty.
        let mid = buf.len().saturating_sub(1) / 2;
        if let Some((_, &mut m, _)) = (!buf.is_empty()).then(|| buf.select_nth_unstable(mid)) {
            *z = unkey(m);
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Bilateral

/// Weights below `exp(−EXP_CUTOFF) ≈ 1.1e−7` are dropped.
const EXP_CUTOFF: f32 = 16.0;

/// `exp(−x)` for `0 <= x <= EXP_CUTOFF`, relative error below `3e−7 + 1e−7·x` (mostly the f32
/// rounding of `x·log2(e)`, as large as that of `x` itself), branch-free so the window
/// loop vectorises: `2^y` with `y = −x·log2(e)` split as `n + f`, `n = round(y)` (by the
/// 1.5·2^23 trick, whose low mantissa bits then hold `n`), `|f| <= ½`, `2^f = e^(f·ln 2)` by its
/// degree-6 Taylor polynomial (remainder `0.35^7/7! < 1.3e−7`), `2^n` built in the exponent
/// field (`n >= −24`, so normal).
#[inline(always)]
fn exp_neg(x: f32) -> f32 {
    const MAGIC: f32 = 12_582_912.0; // 1.5·2^23
    let y = -x * std::f32::consts::LOG2_E;
    let shifted = y + MAGIC;
    let n = shifted - MAGIC;
    let t = (y - n) * std::f32::consts::LN_2;
    let p = 1.0
        + t * (1.0 + t * (0.5 + t * (1.0 / 6.0 + t * (1.0 / 24.0 + t * (1.0 / 120.0 + t * (1.0 / 720.0))))));
    // The low bits of `shifted` are n + 2^22 (two's complement); n in [−24, 0].
    let n_int = (shifted.to_bits() as i32).wrapping_sub(0x4B40_0000);
    let scale = f32::from_bits((n_int.wrapping_add(127) as u32) << 23);
    p * scale
}

/// Bilateral filter: each data cell becomes the weighted mean of the data cells in the square
/// window of radius `R = ⌈2.5·sigma_space_mm/p⌉`, with weights
/// `exp(−d²/(2σ_s²)) · exp(−Δz²/(2σ_z²))` (`d` the distance between cell centres, `Δz` the
/// height difference to the centre cell). Heights across a step much larger than `σ_z` get
/// negligible weight, so edges are kept while noise is averaged. NaN-aware (see module docs).
///
/// Weights use a branch-free f32 `exp` (relative error below 2e−6) and are dropped below
/// `exp(−16)`; the sums are taken over height differences, so the result is accurate relative
/// to the local relief. Cost O(w·h·(2R+1)²), vectorised along the window rows.
pub fn bilateral(map: &HeightMap, sigma_space_mm: f64, sigma_z_mm: f64) -> Result<HeightMap> {
    if !(sigma_space_mm.is_finite() && sigma_space_mm > 0.0) {
        return Err(ReconError::param(
            "bilateral sigma_space_mm",
            sigma_space_mm,
            "must be finite and positive",
        ));
    }
    if !(sigma_z_mm.is_finite() && sigma_z_mm > 0.0) {
        return Err(ReconError::param("bilateral sigma_z_mm", sigma_z_mm, "must be finite and positive"));
    }
    let p = map.pixel_mm();
    let radius = (2.5 * sigma_space_mm / p).ceil();
    if radius > f64::from(MAX_BILATERAL_RADIUS_PX) {
        return Err(ReconError::param(
            "bilateral sigma_space_mm",
            sigma_space_mm,
            format!("gives a window radius of {radius} pixels, more than {MAX_BILATERAL_RADIUS_PX}"),
        ));
    }
    let r = radius as usize;
    let (w, h) = (map.width() as usize, map.height() as usize);
    let side = 2 * r + 1;
    // Spatial exponent per window offset.
    let spatial: Vec<f32> = (0..side * side)
        .map(|k| {
            let (dx, dy) = (k % side, k / side);
            let d2 = ((dx as f64 - r as f64).powi(2) + (dy as f64 - r as f64).powi(2)) * p * p;
            (d2 / (2.0 * sigma_space_mm * sigma_space_mm)) as f32
        })
        .collect();
    let range_coef = (1.0 / (2.0 * sigma_z_mm * sigma_z_mm)) as f32;
    let src = map.data();
    let mut out = map.clone();
    out.data_mut().par_chunks_mut(w).enumerate().for_each(|(j, row)| {
        // Loop over window offsets outside and cells inside: every cell has its own sums, so
        // the inner loop has no reduction and vectorises.
        let centre = &src[j * w..(j + 1) * w];
        let (mut sw, mut swd) = (vec![0.0f32; w], vec![0.0f32; w]);
        for jj in j.saturating_sub(r)..=(j + r).min(h - 1) {
            let line = &src[jj * w..(jj + 1) * w];
            for ox in 0..side {
                let a = spatial[(jj + r - j) * side + ox];
                // Cell i reads line[i + ox − r]; keep both inside 0..w.
                let (i0, s0) = if ox < r { (r - ox, 0) } else { (0, ox - r) };
                if i0 >= w || s0 >= w {
                    continue;
                }
                let n = (w - i0).min(w - s0);
                let cells = centre[i0..i0 + n].iter().zip(&line[s0..s0 + n]);
                for ((&zc, &q), (acc_w, acc_wd)) in
                    cells.zip(sw[i0..i0 + n].iter_mut().zip(&mut swd[i0..i0 + n]))
                {
                    let d = q - zc;
                    let x = a + range_coef * d * d;
                    // NaN/inf heights give a non-finite x and fail the test.
                    let keep = x < EXP_CUTOFF;
                    let wt = if keep { exp_neg(x.min(EXP_CUTOFF)) } else { 0.0 };
                    *acc_w += wt;
                    *acc_wd += if keep { wt * d } else { 0.0 };
                }
            }
        }
        for ((z, &w_sum), &wd_sum) in row.iter_mut().zip(&sw).zip(&swd) {
            if z.is_finite() {
                // The centre cell has weight 1, so w_sum >= 1.
                *z = (f64::from(*z) + f64::from(wd_sum) / f64::from(w_sum)) as f32;
            }
        }
    });
    Ok(out)
}

// ---------------------------------------------------------------------------------------------
// Morphology

/// Half-widths of the rows of a disk of radius `r_px` pixels (centre distances `<= r_px`),
/// indexed by `dy + R`. `R` is capped at `max_dy` and the half-widths at `max_dx` (the grid's
/// height − 1 and width − 1: a larger reach adds no cell).
fn disk_rows(r_px: f64, max_dy: usize, max_dx: usize) -> Vec<usize> {
    let rr = r_px * r_px;
    // Float-to-int casts saturate (a huge radius gives usize::MAX, then the cap).
    let big_r = ((r_px + 1e-9).floor() as usize).min(max_dy);
    (0..=2 * big_r)
        .map(|k| {
            let dy = k as f64 - big_r as f64;
            (((rr - dy * dy).max(0.0).sqrt() + 1e-9).floor() as usize).min(max_dx)
        })
        .collect()
}

/// Sliding-window reduction of `line` by `op` over `[x − hw, x + hw]` (clipped), van Herk /
/// Gil–Werman: three passes, O(len) for any width. `g`, `s` are scratch buffers.
fn window_reduce<T: Copy>(
    line: &[T],
    hw: usize,
    identity: T,
    op: &impl Fn(T, T) -> T,
    g: &mut Vec<T>,
    s: &mut Vec<T>,
    out: &mut [T],
) {
    if hw == 0 {
        out.copy_from_slice(line);
        return;
    }
    let n = 2 * hw + 1;
    let len = line.len() + 2 * hw;
    let padded = |x: usize| if x >= hw && x - hw < line.len() { line[x - hw] } else { identity };
    g.clear();
    s.clear();
    s.resize(len, identity);
    for x in 0..len {
        let v = padded(x);
        g.push(if x % n == 0 { v } else { op(g[x - 1], v) });
    }
    for x in (0..len).rev() {
        let v = padded(x);
        s[x] = if x % n == n - 1 || x == len - 1 { v } else { op(s[x + 1], v) };
    }
    for (x, o) in out.iter_mut().enumerate() {
        *o = op(s[x], g[x + 2 * hw]);
    }
}

/// Reduces every cell's disk neighbourhood (`rows` from [`disk_rows`]) by `op`; cells outside
/// the grid are ignored (they act as `identity`).
fn disk_filter<T: Copy + Send + Sync>(
    src: &[T],
    w: usize,
    h: usize,
    rows: &[usize],
    identity: T,
    op: impl Fn(T, T) -> T + Sync,
) -> Vec<T> {
    let big_r = rows.len() / 2;
    let mut out = vec![identity; w * h];
    out.par_chunks_mut(w).enumerate().for_each(|(y, acc)| {
        let (mut g, mut s, mut tmp) = (Vec::new(), Vec::new(), vec![identity; w]);
        for (k, &hw) in rows.iter().enumerate() {
            let Some(sy) = (y + k).checked_sub(big_r).filter(|&sy| sy < h) else { continue };
            window_reduce(&src[sy * w..(sy + 1) * w], hw, identity, &op, &mut g, &mut s, &mut tmp);
            for (a, &t) in acc.iter_mut().zip(&tmp) {
                *a = op(*a, t);
            }
        }
    });
    out
}

fn check_radius(field: &str, r: f64) -> Result<()> {
    if r.is_finite() && r >= 0.0 {
        Ok(())
    } else {
        Err(ReconError::param(field, r, "must be finite and >= 0"))
    }
}

fn grey_disk(map: &HeightMap, radius_mm: f64, dilate: bool) -> Result<HeightMap> {
    check_radius("radius_mm", radius_mm)?;
    let (w, h) = (map.width() as usize, map.height() as usize);
    let rows = disk_rows(radius_mm / map.pixel_mm(), h - 1, w - 1);
    let identity = if dilate { f32::NEG_INFINITY } else { f32::INFINITY };
    let src: Vec<f32> = map.data().iter().map(|&z| if z.is_finite() { z } else { identity }).collect();
    let res = if dilate {
        disk_filter(&src, w, h, &rows, identity, f32::max)
    } else {
        disk_filter(&src, w, h, &rows, identity, f32::min)
    };
    let mut out = map.clone();
    for (o, r) in out.data_mut().iter_mut().zip(res) {
        if o.is_finite() {
            *o = r;
        }
    }
    Ok(out)
}

/// Grayscale dilation with a flat disk of radius `radius_mm` (cells whose centres are within
/// the radius): each data cell becomes the max of the data in its disk. NaN-aware (module docs).
pub fn grey_dilate_disk(map: &HeightMap, radius_mm: f64) -> Result<HeightMap> {
    grey_disk(map, radius_mm, true)
}

/// Grayscale erosion with a flat disk of radius `radius_mm`: each data cell becomes the min of
/// the data in its disk. NaN-aware (module docs).
pub fn grey_erode_disk(map: &HeightMap, radius_mm: f64) -> Result<HeightMap> {
    grey_disk(map, radius_mm, false)
}

fn binary_disk(mask: &[bool], width: u32, height: u32, radius_px: f64, dilate: bool) -> Result<Vec<bool>> {
    check_radius("radius_px", radius_px)?;
    let (w, h) = (width as usize, height as usize);
    if w.checked_mul(h) != Some(mask.len()) || mask.is_empty() {
        return Err(ReconError::param(
            "mask length",
            mask.len(),
            format!("must equal width × height = {width} × {height} (nonzero)"),
        ));
    }
    let rows = disk_rows(radius_px, h - 1, w - 1);
    Ok(if dilate {
        disk_filter(mask, w, h, &rows, false, |a, b| a | b)
    } else {
        disk_filter(mask, w, h, &rows, true, |a, b| a & b)
    })
}

/// Binary dilation of a row-major `width × height` mask by a disk of radius `radius_px` pixels:
/// a cell is set when any set cell's centre lies within the radius.
pub fn binary_dilate_disk(mask: &[bool], width: u32, height: u32, radius_px: f64) -> Result<Vec<bool>> {
    binary_disk(mask, width, height, radius_px, true)
}

/// Binary erosion of a row-major `width × height` mask by a disk of radius `radius_px` pixels: a
/// cell stays set when every cell of the grid within the radius is set (cells outside the grid
/// are ignored, so the border does not erode).
pub fn binary_erode_disk(mask: &[bool], width: u32, height: u32, radius_px: f64) -> Result<Vec<bool>> {
    binary_disk(mask, width, height, radius_px, false)
}

// ---------------------------------------------------------------------------------------------
// Foreign images

/// Reads a depth image without depthmill metadata, such as one made for LinuxCNC's
/// `image-to-gcode` (8/16-bit gray, gray+alpha, RGB or RGBA PNG; colour reduced to Rec.601
/// luma; alpha 0 = no data). Gray level `L` of `M` levels maps to
/// `z = z_min_mm + (z_max_mm − z_min_mm)·L/M` (black = `z_min_mm`), or with `invert` to
/// `z_max_mm − (z_max_mm − z_min_mm)·L/M` (black = `z_max_mm`, image-to-gcode's "Invert
/// Image"). The picture's top row is maximum Y; the grid has pixel `pixel_mm`, origin `(0, 0)`,
/// Z range `[z_min_mm, z_max_mm]` and view `face`. For image-to-gcode's defaults use
/// `z_min_mm = −depth`, `z_max_mm = 0`, `invert = false`.
///
/// Depthmill metadata, if the file has some, is ignored (the gray levels are recovered from it
/// and re-mapped with the caller's values); read depthmill maps with `HeightMap::read` instead.
pub fn read_foreign_image(
    path: &Path,
    pixel_mm: f64,
    z_min_mm: f64,
    z_max_mm: f64,
    face: Face,
    invert: bool,
) -> Result<HeightMap> {
    if !(pixel_mm.is_finite() && pixel_mm > 0.0) {
        return Err(ReconError::param("pixel_mm", pixel_mm, "must be finite and positive"));
    }
    if !(z_min_mm.is_finite() && z_max_mm.is_finite() && z_min_mm < z_max_mm) {
        return Err(ReconError::param(
            "z_max_mm",
            z_max_mm,
            format!("must be finite and greater than z_min_mm = {z_min_mm}"),
        ));
    }
    // Without metadata the file reads as the level fraction L/M itself.
    let unit = read_png(path, Some(&ImageMapping::new(pixel_mm, 0.0, 1.0)))?;
    let (lo, hi) = (unit.z_min_mm(), unit.z_max_mm());
    let meta = HeightMapMeta {
        pixel_mm,
        origin_x_mm: 0.0,
        origin_y_mm: 0.0,
        z_min_mm,
        z_max_mm,
        face,
        ..*unit.meta()
    };
    let range = z_max_mm - z_min_mm;
    let data = unit
        .into_data()
        .into_iter()
        .map(|z| {
            let t = (f64::from(z) - lo) / (hi - lo);
            (if invert { z_max_mm - range * t } else { z_min_mm + range * t }) as f32
        })
        .collect();
    Ok(HeightMap::new(meta, data)?)
}

#[cfg(test)]
mod tests {
    use std::io::BufWriter;

    use rand::rngs::StdRng;
    use rand::{Rng, SeedableRng};

    use super::*;

    fn random_map(rng: &mut StdRng, w: u32, h: u32, p: f64, nan_frac: f64, levels: bool) -> HeightMap {
        let meta = HeightMapMeta { z_min_mm: -10.0, z_max_mm: 10.0, ..HeightMapMeta::new(w, h, p) };
        HeightMap::from_fn(meta, |_, _| {
            if rng.random_bool(nan_frac) {
                f32::NAN
            } else if levels {
                rng.random_range(0..5) as f32 * 0.5
            } else {
                rng.random_range(-10.0f32..10.0)
            }
        })
        .expect("map")
    }

    /// Finite neighbours of `(i, j)` within the square radius `r`.
    fn window(map: &HeightMap, i: usize, j: usize, r: usize) -> Vec<(usize, usize, f32)> {
        let (w, h) = (map.width() as usize, map.height() as usize);
        let mut v = Vec::new();
        for jj in j.saturating_sub(r)..=(j + r).min(h - 1) {
            for ii in i.saturating_sub(r)..=(i + r).min(w - 1) {
                let z = map.data()[jj * w + ii];
                if z.is_finite() {
                    v.push((ii, jj, z));
                }
            }
        }
        v
    }

    fn median_ref(map: &HeightMap, r: usize) -> Vec<f32> {
        let w = map.width() as usize;
        map.data()
            .iter()
            .enumerate()
            .map(|(k, &z)| {
                if !z.is_finite() {
                    return z;
                }
                let mut v: Vec<f32> = window(map, k % w, k / w, r).into_iter().map(|t| t.2).collect();
                v.sort_by(f32::total_cmp);
                v[(v.len() - 1) / 2]
            })
            .collect()
    }

    fn bilateral_ref(map: &HeightMap, ss: f64, sz: f64) -> Vec<f32> {
        let w = map.width() as usize;
        let p = map.pixel_mm();
        let r = (2.5 * ss / p).ceil() as usize;
        map.data()
            .iter()
            .enumerate()
            .map(|(k, &z)| {
                if !z.is_finite() {
                    return z;
                }
                let (i, j) = (k % w, k / w);
                let (mut sw, mut swz) = (0.0, 0.0);
                for (ii, jj, q) in window(map, i, j, r) {
                    let d2 = ((ii as f64 - i as f64).powi(2) + (jj as f64 - j as f64).powi(2)) * p * p;
                    let dz = f64::from(q) - f64::from(z);
                    let wt = (-d2 / (2.0 * ss * ss) - dz * dz / (2.0 * sz * sz)).exp();
                    sw += wt;
                    swz += wt * f64::from(q);
                }
                (swz / sw) as f32
            })
            .collect()
    }

    #[test]
    fn exp_neg_is_accurate() {
        for i in 0..=16_000 {
            let x = i as f32 * 1e-3;
            let (got, want) = (f64::from(exp_neg(x)), (-f64::from(x)).exp());
            // f32 rounding of y = −x·log2(e) dominates: about 6e−8·x relative.
            assert!(((got - want) / want).abs() < 3e-7 + 1e-7 * f64::from(x), "x={x}: {got} vs {want}");
        }
    }

    #[test]
    fn keys_order_like_floats() {
        let mut v = vec![-3.5f32, 0.0, -0.0, 1e-40, -1e-40, 7.0, f32::MAX, f32::MIN, 2.0];
        let mut keys: Vec<u32> = v.iter().map(|&z| key(z)).collect();
        keys.sort_unstable();
        v.sort_by(f32::total_cmp);
        let back: Vec<f32> = keys.into_iter().map(unkey).collect();
        assert_eq!(
            back.iter().map(|z| z.to_bits()).collect::<Vec<_>>(),
            v.iter().map(|z| z.to_bits()).collect::<Vec<_>>()
        );
        assert!(key(f32::MAX) < NO_KEY);
    }

    #[test]
    fn median_matches_reference() {
        let mut rng = StdRng::seed_from_u64(3);
        for _ in 0..30 {
            let (w, h) = (rng.random_range(1..25), rng.random_range(1..25));
            let (nan, levels) = (rng.random_range(0.0..0.6), rng.random_bool(0.5));
            let map = random_map(&mut rng, w, h, 0.1, nan, levels);
            let r = rng.random_range(0..5);
            let got = median(&map, r).expect("median");
            assert_eq!(got.meta(), map.meta());
            let want = median_ref(&map, r as usize);
            for (a, b) in got.data().iter().zip(&want) {
                assert_eq!(a.to_bits(), b.to_bits(), "r={r}");
            }
        }
        let map = random_map(&mut rng, 5, 5, 0.1, 0.2, false);
        assert!(median(&map, 0).expect("r=0").bitwise_eq(&map));
        assert!(median(&map, 65).is_err());
    }

    #[test]
    fn median_removes_salt_and_keeps_a_step_exactly() {
        let meta = HeightMapMeta::new(40, 30, 0.1);
        let clean = HeightMap::from_fn(meta, |c, _| if c < 17 { 0.0 } else { 1.0 }).expect("map");
        let mut noisy = clean.clone();
        for j in (3..30).step_by(6) {
            for i in (3..40).step_by(6) {
                noisy.set(i, j, if (i + j) % 4 == 0 { 50.0 } else { -50.0 }).expect("salt");
            }
        }
        noisy.set(0, 0, f32::NAN).expect("hole");
        let out = median(&noisy, 2).expect("median");
        for (k, (a, b)) in out.data().iter().zip(clean.data()).enumerate() {
            if k == 0 {
                assert!(a.is_nan());
            } else {
                assert_eq!(a, b, "cell {k}");
            }
        }
    }

    #[test]
    fn bilateral_matches_reference() {
        let mut rng = StdRng::seed_from_u64(5);
        for _ in 0..20 {
            let (w, h) = (rng.random_range(1..20), rng.random_range(1..20));
            let p = rng.random_range(0.05..0.5);
            let (nan, levels) = (rng.random_range(0.0..0.5), rng.random_bool(0.5));
            let map = random_map(&mut rng, w, h, p, nan, levels);
            let ss = p * rng.random_range(0.3..3.0);
            let sz = rng.random_range(0.1..8.0);
            let got = bilateral(&map, ss, sz).expect("bilateral");
            let want = bilateral_ref(&map, ss, sz);
            for (k, (a, b)) in got.data().iter().zip(&want).enumerate() {
                assert_eq!(a.is_nan(), b.is_nan());
                if b.is_finite() {
                    let tol = 2e-4 * sz + 2e-6 * f64::from(b.abs());
                    assert!(f64::from((a - b).abs()) <= tol, "cell {k}: {a} vs {b} (ss={ss}, sz={sz})");
                }
            }
        }
    }

    /// Standard normal by Box–Muller.
    fn normal(rng: &mut StdRng) -> f64 {
        let (u, v): (f64, f64) = (rng.random_range(1e-12..1.0), rng.random_range(0.0..1.0));
        (-2.0 * u.ln()).sqrt() * (2.0 * std::f64::consts::PI * v).cos()
    }

    #[test]
    fn bilateral_keeps_a_step_and_reduces_noise() {
        let mut rng = StdRng::seed_from_u64(9);
        let meta = HeightMapMeta::new(80, 60, 0.1);
        let step = |c: u32| if c < 40 { 0.0f32 } else { 1.0 };
        let sd = 0.02;
        let noisy = HeightMap::from_fn(meta, |c, _| step(c) + (sd * normal(&mut rng)) as f32).expect("map");
        let out = bilateral(&noisy, 0.2, 0.06).expect("bilateral");
        let (mut n, mut before, mut after) = (0.0, 0.0, 0.0);
        for r in 0..60 {
            for c in 0..80 {
                let (z, clean) = (out.get(c, r).expect("cell"), step(c));
                assert!((z - clean).abs() <= 0.05, "({c},{r}) {z}");
                // Noise away from the border and the step.
                if (8..72).contains(&c) && !(32..48).contains(&c) && (8..52).contains(&r) {
                    n += 1.0;
                    before += f64::from(noisy.get(c, r).expect("cell") - clean).powi(2);
                    after += f64::from(z - clean).powi(2);
                }
            }
        }
        let (before, after) = ((before / n).sqrt(), (after / n).sqrt());
        assert!(before > 0.015 && after < before / 3.0, "noise {before} -> {after}");
    }

    #[test]
    fn bilateral_parameter_errors() {
        let map = HeightMap::filled(HeightMapMeta::new(3, 3, 0.1), 1.0).expect("map");
        assert!(bilateral(&map, 0.0, 1.0).is_err());
        assert!(bilateral(&map, 1.0, f64::NAN).is_err());
        let e = bilateral(&map, 10.0, 1.0).expect_err("window too large").to_string();
        assert!(e.contains("250 pixels") && e.contains("64"), "{e}");
        assert!(bilateral(&map, 0.1, 1.0).expect("flat").data().iter().all(|&z| z == 1.0));
    }

    #[test]
    fn stretch_on_known_data() {
        let meta = HeightMapMeta::new(101, 1, 1.0);
        let mut map = HeightMap::from_fn(meta, |c, _| (100 - c) as f32 * 0.5).expect("map");
        map.set(7, 0, f32::NAN).expect("hole");
        // 100 data values: 0, 0.5, ..., 50 without 46.5.
        let full = stretch(&map, 0.0, 100.0).expect("stretch");
        assert_eq!((full.z_min_mm(), full.z_max_mm()), (0.0, 50.0));
        assert!(full.data().iter().zip(map.data()).all(|(a, b)| a.to_bits() == b.to_bits()));
        let robust = stretch(&map, 10.0, 50.0).expect("stretch");
        // Sorted data v[i] = 0.5·i for i < 93; position 9.9 -> 4.95, position 49.5 -> 24.75.
        assert!((robust.z_min_mm() - 4.95).abs() < 1e-12, "{}", robust.z_min_mm());
        assert!((robust.z_max_mm() - 24.75).abs() < 1e-12, "{}", robust.z_max_mm());
        let two = HeightMap::new(HeightMapMeta::new(2, 1, 1.0), vec![10.0, 0.0]).expect("map");
        let mid = stretch(&two, 25.0, 50.0).expect("stretch");
        assert_eq!((mid.z_min_mm(), mid.z_max_mm()), (2.5, 5.0));

        assert!(stretch(&map, 50.0, 50.0).is_err());
        assert!(stretch(&map, -1.0, 50.0).is_err());
        assert!(stretch(&map, 0.0, f64::NAN).is_err());
        let flat = HeightMap::filled(meta, 3.0).expect("map");
        let e = stretch(&flat, 0.0, 100.0).expect_err("flat").to_string();
        assert!(e.contains("flat at 3 mm"), "{e}");
        let empty = HeightMap::filled(meta, f32::NAN).expect("map");
        assert_eq!(
            stretch(&empty, 0.0, 100.0).expect_err("empty").to_string(),
            "stretch: the map has no data"
        );
    }

    /// Writes a foreign 8-bit RGB PNG (no metadata); `rows` are image rows, top first.
    fn write_rgb(path: &Path, rows: &[Vec<[u8; 3]>]) {
        let file = std::fs::File::create(path).expect("create");
        let mut enc = png::Encoder::new(BufWriter::new(file), rows[0].len() as u32, rows.len() as u32);
        enc.set_color(png::ColorType::Rgb);
        enc.set_depth(png::BitDepth::Eight);
        let mut w = enc.write_header().expect("header");
        let bytes: Vec<u8> = rows.iter().flatten().flatten().copied().collect();
        w.write_image_data(&bytes).expect("data");
        w.finish().expect("finish");
    }

    #[test]
    fn foreign_rgb_image_maps_levels_and_puts_the_top_row_at_max_y() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("relief.png");
        // Top row: white, black, gray 51. Bottom row: pure red, gray 204, gray 102.
        write_rgb(&path, &[vec![[255; 3], [0; 3], [51; 3]], vec![[255, 0, 0], [204; 3], [102; 3]]]);
        let map =
            read_foreign_image(&path, 0.25, -6.0, 0.0, Face::A { angle_deg: 90.0 }, false).expect("read");
        assert_eq!((map.width(), map.height(), map.pixel_mm()), (3, 2, 0.25));
        assert_eq!((map.z_min_mm(), map.z_max_mm(), map.face()), (-6.0, 0.0, Face::A { angle_deg: 90.0 }));
        assert_eq!((map.origin_x_mm(), map.origin_y_mm()), (0.0, 0.0));
        let z = |c, r| f64::from(map.get(c, r).expect("cell"));
        let lum = |l: f64| -6.0 + 6.0 * l / 255.0;
        // Map row 1 (max Y) is the image's top row.
        for (c, want) in [(0, 0.0), (1, -6.0), (2, lum(51.0))] {
            assert!((z(c, 1) - want).abs() < 1e-5, "top row col {c}: {}", z(c, 1));
        }
        for (c, want) in [(0, lum(0.299 * 255.0)), (1, lum(204.0)), (2, lum(102.0))] {
            assert!((z(c, 0) - want).abs() < 1e-5, "bottom row col {c}: {}", z(c, 0));
        }
        // Cell (0, 1) is the top-left pixel: its centre at x = 0.125, y = 0.375.
        assert_eq!(map.cell_of(0.125, 0.375), Some((0, 1)));

        let inv = read_foreign_image(&path, 0.25, -6.0, 0.0, Face::PosZ, true).expect("read inverted");
        for (a, b) in inv.data().iter().zip(map.data()) {
            assert!((f64::from(*a) - (-6.0 - f64::from(*b))).abs() < 1e-5, "{a} {b}");
        }
        assert_eq!(inv.get(1, 1), Some(0.0));

        // A depthmill PNG read as foreign: its own mapping is ignored, the levels are kept.
        let own = HeightMap::new(
            HeightMapMeta { z_min_mm: 10.0, z_max_mm: 20.0, ..HeightMapMeta::new(2, 1, 3.0) },
            vec![10.0, 20.0],
        )
        .expect("map");
        let p2 = dir.path().join("own.png");
        depthmill_geometry::write_png(&own, &p2, depthmill_geometry::PngDepth::Bits8).expect("write");
        let back = read_foreign_image(&p2, 0.5, 0.0, 1.0, Face::PosZ, false).expect("read");
        assert_eq!((back.pixel_mm(), back.data()), (0.5, &[0.0f32, 1.0][..]));

        let e = read_foreign_image(&dir.path().join("missing.png"), 0.25, 0.0, 1.0, Face::PosZ, false)
            .expect_err("missing");
        assert!(e.to_string().contains("missing.png"), "{e}");
        assert!(read_foreign_image(&path, 0.0, 0.0, 1.0, Face::PosZ, false).is_err());
        assert!(read_foreign_image(&path, 0.1, 1.0, 1.0, Face::PosZ, false).is_err());
    }

    fn disk_ref(map: &HeightMap, r_mm: f64, dilate: bool) -> Vec<f32> {
        let (w, h) = (map.width() as i64, map.height() as i64);
        let rp = r_mm / map.pixel_mm();
        let reach = rp.floor() as i64 + 1;
        map.data()
            .iter()
            .enumerate()
            .map(|(k, &z)| {
                if !z.is_finite() {
                    return z;
                }
                let (i, j) = (k as i64 % w, k as i64 / w);
                let mut m = z;
                for jj in (j - reach).max(0)..=(j + reach).min(h - 1) {
                    for ii in (i - reach).max(0)..=(i + reach).min(w - 1) {
                        let q = map.data()[(jj * w + ii) as usize];
                        let d2 = ((ii - i).pow(2) + (jj - j).pow(2)) as f64;
                        if q.is_finite() && d2 <= rp * rp + 1e-9 {
                            m = if dilate { m.max(q) } else { m.min(q) };
                        }
                    }
                }
                m
            })
            .collect()
    }

    #[test]
    fn grey_and_binary_morphology_match_reference() {
        let mut rng = StdRng::seed_from_u64(13);
        for _ in 0..25 {
            let (w, h) = (rng.random_range(1..30), rng.random_range(1..30));
            let nan = rng.random_range(0.0..0.5);
            let map = random_map(&mut rng, w, h, 0.5, nan, false);
            // Includes exact integer radii (2.0 px = 1.0 mm) and zero.
            let r_mm = if rng.random_bool(0.3) {
                f64::from(rng.random_range(0..4)) * 0.5
            } else {
                rng.random_range(0.0..4.0)
            };
            for dilate in [true, false] {
                let got = if dilate { grey_dilate_disk(&map, r_mm) } else { grey_erode_disk(&map, r_mm) }
                    .expect("morph");
                let want = disk_ref(&map, r_mm, dilate);
                for (a, b) in got.data().iter().zip(&want) {
                    assert_eq!(a.to_bits(), b.to_bits(), "r={r_mm} dilate={dilate}");
                }
            }
            // Binary: the mask of data cells, as 0/1 heights through the grey reference.
            let mask: Vec<bool> = map.data().iter().map(|z| z.is_finite()).collect();
            let as01 =
                HeightMap::from_fn(*map.meta(), |c, r| f32::from(u8::from(mask[(r * w + c) as usize])))
                    .expect("map");
            let r_px = r_mm / 0.5;
            let dil = binary_dilate_disk(&mask, w, h, r_px).expect("dilate");
            let ero = binary_erode_disk(&mask, w, h, r_px).expect("erode");
            let (dref, eref) = (disk_ref(&as01, r_mm, true), disk_ref(&as01, r_mm, false));
            assert_eq!(dil, dref.iter().map(|&z| z == 1.0).collect::<Vec<_>>());
            assert_eq!(ero, eref.iter().map(|&z| z == 1.0).collect::<Vec<_>>());
        }
        let map = random_map(&mut rng, 4, 4, 0.5, 0.0, false);
        assert!(grey_dilate_disk(&map, -1.0).is_err());
        assert!(binary_erode_disk(&[true; 3], 2, 2, 1.0).is_err());
    }

    #[test]
    fn dilating_a_point_draws_a_disk() {
        let meta = HeightMapMeta::new(21, 21, 0.1);
        let mut map = HeightMap::filled(meta, 0.0).expect("map");
        map.set(10, 10, 5.0).expect("set");
        let d = grey_dilate_disk(&map, 0.3).expect("dilate");
        let count = d.data().iter().filter(|&&z| z == 5.0).count();
        // Lattice points within radius 3: 29.
        assert_eq!(count, 29);
        let e = grey_erode_disk(&d, 0.3).expect("erode");
        assert_eq!(e.get(10, 10), Some(5.0));
        assert_eq!(e.data().iter().filter(|&&z| z == 5.0).count(), 1);
        // A radius beyond the grid reaches everything (and allocates nothing large).
        let all = grey_dilate_disk(&map, 1e300).expect("huge radius");
        assert!(all.data().iter().all(|&z| z == 5.0));
        let mask: Vec<bool> = (0..21 * 21).map(|k| k == 0).collect();
        assert!(binary_dilate_disk(&mask, 21, 21, f64::MAX).expect("huge").iter().all(|&b| b));
    }
}
