//! Roughing maps: over-approximations of a height map, so a roughing pass planned on them never
//! cuts into the part.
//!
//! Only finite heights count as data; NaN (and ±inf) cells are ignored.
//!
//! # Block max ([`block_max`])
//!
//! A coarse map with pixel `k·p`, the same origin, `⌈w/k⌉ × ⌈h/k⌉` cells; coarse cell `(C, R)`
//! is the max of the fine cells `[Ck, (C+1)k) × [Rk, (R+1)k)` that hold data (NaN if none; the
//! last blocks are cut by the grid). Every fine cell with data is `<=` the coarse cell containing
//! its centre. The map is stepped.
//!
//! # Continuous over-approximation ([`continuous_over`])
//!
//! A map on the fine grid, bilinear between the nodes of a lattice of spacing `k` cells: node
//! `(I, J)` sits on fine cell centre `(Ik, Jk)`, and fine cell `(i, j)` with `i = Ik + s`,
//! `j = Jk + t` (`0 <= s, t < k`) takes
//!
//! ```text
//! g = (1−σ)(1−τ) N(I,J) + σ(1−τ) N(I+1,J) + (1−σ)τ N(I,J+1) + στ N(I+1,J+1),  σ = s/k, τ = t/k.
//! ```
//!
//! The node values are chosen as small as the guarantee allows: `N(I, J)` is the max of the
//! fine data in columns `[(I−1)k+1, (I+1)k−1]` × rows `[(J−1)k+1, (J+1)k−1]` (clipped to the
//! grid), which is exactly the set of fine cells in which node `(I, J)` has a positive weight.
//!
//! **Never below.** At a fine cell with data `f`, every node with positive weight has the cell
//! in its window, so is `>= f`; `g` is a convex combination of those nodes, so `g >= f`. To keep
//! this exact under rounding, `g` is computed in f64, clamped to `[min, max]` of its
//! positive-weight nodes (a no-op in exact arithmetic) and rounded to f32; rounding is monotone
//! and the bounds are f32 values, so `g >= min(nodes) >= f` holds bit for bit.
//!
//! **Close.** Every node window lies in the 3×3 coarse blocks around the cell's block, so
//! `g <= max(nodes) <=` the max of the [`block_max`] cells `(C−1..=C+1, R−1..=R+1)`, with
//! `C = ⌊i/k⌋`, `R = ⌊j/k⌋`. With `k = 1` the map is returned unchanged (but ±inf becomes NaN).
//!
//! **Continuous.** `g` samples one continuous piecewise-bilinear surface (node columns are
//! shared by neighbouring lattice cells), so two adjacent fine cells differ by at most
//! `(max − min of the nodes of the lattice cell (⌊i/k⌋, ⌊j/k⌋))/k` (the bilinear's slope bound),
//! hence by at most `(max − min of the fine data in columns [(I−1)k+1, (I+2)k−1] × rows
//! [(J−1)k+1, (J+2)k−1])/k`, since each node is the max of a nonempty subset of that window.
//!
//! **No data.** A fine cell without data gets the interpolated value when all of its
//! positive-weight nodes have data (holes smaller than about `k` are bridged by the
//! over-approximation), NaN otherwise. A cell with data always gets a finite value.
//!
//! Cost O(w·h) for any `k`, parallel by rows.
//!
//! # Other resolutions ([`upsample_block`])
//!
//! CAM may want the roughing map on another grid: [`upsample_block`] samples a coarse map at
//! the fine grid's centres (the coarse cell containing each centre).

use depthmill_geometry::{HeightMap, HeightMapMeta};
use rayon::prelude::*;

use crate::domain::error::{ReconError, Result};

fn check_k(k: u32) -> Result<usize> {
    if k == 0 {
        return Err(ReconError::param("roughing factor k", k, "must be at least 1"));
    }
    Ok(k as usize)
}

/// The height if it is data, NaN otherwise.
fn data(z: f32) -> f32 {
    if z.is_finite() { z } else { f32::NAN }
}

/// Max that ignores NaN (`f32::max` returns the other operand).
fn nmax(a: f32, b: f32) -> f32 {
    a.max(b)
}

/// Block max at factor `k` (see the module docs): pixel `k·p`, same origin, Z range and face.
pub fn block_max(map: &HeightMap, k: u32) -> Result<HeightMap> {
    let k = check_k(k)?;
    let m = map.meta();
    let (w, h) = (m.width as usize, m.height as usize);
    let (cw, ch) = (w.div_ceil(k), h.div_ceil(k));
    let meta = HeightMapMeta {
        // cw <= w and ch <= h fit u32.
        width: cw as u32,
        height: ch as u32,
        pixel_mm: m.pixel_mm * k as f64,
        ..*m
    };
    let mut out = vec![f32::NAN; cw * ch];
    let src = map.data();
    out.par_chunks_mut(cw).enumerate().for_each(|(r, acc)| {
        for row in src.chunks(w).skip(r * k).take(k) {
            for (a, block) in acc.iter_mut().zip(row.chunks(k)) {
                *a = block.iter().fold(*a, |m, &z| nmax(m, data(z)));
            }
        }
    });
    Ok(HeightMap::new(meta, out)?)
}

/// Node windows along one axis: `out[I] = max(z[(I−1)k+1 ..= (I+1)k−1])` over the data.
fn node_max_1d(z: &[f32], k: usize, out: &mut [f32]) {
    // full[I]: block I; tail[I]: block I without its first cell.
    let mut prev_tail = f32::NAN;
    for (i, node) in out.iter_mut().enumerate() {
        let block = z.get(i * k..((i + 1) * k).min(z.len())).unwrap_or(&[]);
        let tail = block.iter().skip(1).fold(f32::NAN, |m, &v| nmax(m, data(v)));
        let full = block.first().map_or(tail, |&v| nmax(tail, data(v)));
        *node = nmax(prev_tail, full);
        prev_tail = tail;
    }
}

/// The node lattice of [`continuous_over`]: `(nx, ny, values row-major)`.
fn nodes(map: &HeightMap, k: usize) -> (usize, usize, Vec<f32>) {
    let (w, h) = (map.width() as usize, map.height() as usize);
    let (nx, ny) = ((w - 1) / k + 2, (h - 1) / k + 2);
    // Horizontal pass: one row of node columns per fine row.
    let mut horiz = vec![f32::NAN; h * nx];
    horiz.par_chunks_mut(nx).zip(map.data().par_chunks(w)).for_each(|(out, row)| node_max_1d(row, k, out));
    // Vertical pass: node row J takes the fine rows (J−1)k+1 ..= (J+1)k−1.
    let mut out = vec![f32::NAN; ny * nx];
    out.par_chunks_mut(nx).enumerate().for_each(|(jn, acc)| {
        let first = (jn * k + 1).saturating_sub(k);
        let end = ((jn + 1) * k).min(h);
        for row in horiz.chunks(nx).take(end).skip(first) {
            for (a, &v) in acc.iter_mut().zip(row) {
                *a = nmax(*a, v);
            }
        }
    });
    (nx, ny, out)
}

/// Bilinear value at fractional offsets `(s, t)` (in cells, `< k`) of the lattice cell with
/// corners `n00 n10 n01 n11` (x then y), using only the nodes with positive weight; clamped to
/// their range; NaN if one of them is NaN.
fn interpolate(n00: f32, n10: f32, n01: f32, n11: f32, s: usize, t: usize, k: usize) -> f32 {
    let (sx, ty) = (s as f64 / k as f64, t as f64 / k as f64);
    let lerp = |a: f32, b: f32, f: f64, use_b: bool| -> (f64, f32, f32) {
        if use_b {
            (f64::from(a) + (f64::from(b) - f64::from(a)) * f, a.min(b), a.max(b))
        } else {
            (f64::from(a), a, a)
        }
    };
    let (bottom, lo0, hi0) = lerp(n00, n10, sx, s > 0);
    let (v, lo, hi) = if t > 0 {
        let (top, lo1, hi1) = lerp(n01, n11, sx, s > 0);
        (bottom + (top - bottom) * ty, lo0.min(lo1), hi0.max(hi1))
    } else {
        (bottom, lo0, hi0)
    };
    // f32::min/max drop NaN, so recheck: any NaN node with a positive weight makes v NaN.
    if v.is_nan() {
        return f32::NAN;
    }
    (v.clamp(f64::from(lo), f64::from(hi))) as f32
}

/// The continuous over-approximation at lattice spacing `k` on the fine grid (see the module
/// docs for the construction and the proofs). Metadata is the input's.
pub fn continuous_over(map: &HeightMap, k: u32) -> Result<HeightMap> {
    let k = check_k(k)?;
    let w = map.width() as usize;
    let (nx, _, nodes) = nodes(map, k);
    let mut out = vec![f32::NAN; map.data().len()];
    out.par_chunks_mut(w).enumerate().for_each(|(j, row)| {
        let (jn, t) = (j / k, j % k);
        let lower = &nodes[jn * nx..(jn + 1) * nx];
        // The node row above exists (ny = (h−1)/k + 2 > jn + 1).
        let upper = nodes.get((jn + 1) * nx..(jn + 2) * nx).unwrap_or(lower);
        for (i, g) in row.iter_mut().enumerate() {
            let (ni, s) = (i / k, i % k);
            let at = |r: &[f32], c: usize| r.get(c).copied().unwrap_or(f32::NAN);
            *g = interpolate(at(lower, ni), at(lower, ni + 1), at(upper, ni), at(upper, ni + 1), s, t, k);
        }
    });
    Ok(HeightMap::new(*map.meta(), out)?)
}

/// Samples `coarse` at the centres of the grid `fine_meta`: each fine cell takes the coarse cell
/// containing its centre, NaN outside the coarse grid. With `fine_meta` the grid a
/// [`block_max`] came from (same origin, pixel `p = coarse pixel / k`), this is the stepped
/// over-approximation on the fine grid: every fine centre lies strictly inside its own block.
pub fn upsample_block(coarse: &HeightMap, fine_meta: &HeightMapMeta) -> Result<HeightMap> {
    fine_meta.validate()?;
    let cols: Vec<Option<u32>> = (0..fine_meta.width)
        .map(|c| {
            let (x, _) = fine_meta.cell_center(c, 0);
            coarse.cell_of(x, coarse.origin_y_mm() + coarse.pixel_mm() / 2.0).map(|(cc, _)| cc)
        })
        .collect();
    let mut out = vec![f32::NAN; fine_meta.cell_count() as usize];
    out.par_chunks_mut(fine_meta.width as usize).enumerate().for_each(|(r, row)| {
        let (_, y) = fine_meta.cell_center(0, r as u32);
        let Some((_, cr)) = coarse.cell_of(coarse.origin_x_mm() + coarse.pixel_mm() / 2.0, y) else {
            return;
        };
        let Some(src) = coarse.row(cr) else { return };
        for (z, c) in row.iter_mut().zip(&cols) {
            if let Some(c) = c {
                *z = src.get(*c as usize).copied().unwrap_or(f32::NAN);
            }
        }
    });
    Ok(HeightMap::new(*fine_meta, out)?)
}

#[cfg(test)]
mod tests {
    use proptest::prelude::*;

    use super::*;

    fn arb_map() -> impl Strategy<Value = HeightMap> {
        (1u32..28, 1u32..28, 0..3).prop_flat_map(|(w, h, kind)| {
            let cell = match kind {
                // Rough noise with holes.
                0 => prop_oneof![6 => -50.0f32..50.0, 1 => Just(f32::NAN)].boxed(),
                // Few distinct levels (steps, ties), some holes and an infinity.
                1 => prop_oneof![
                    8 => (0i32..4).prop_map(|v| v as f32 * 2.5),
                    2 => Just(f32::NAN),
                    1 => Just(f32::INFINITY)
                ]
                .boxed(),
                // Mostly empty.
                _ => prop_oneof![1 => -5.0f32..5.0, 3 => Just(f32::NAN)].boxed(),
            };
            prop::collection::vec(cell, (w * h) as usize).prop_map(move |data| {
                let meta =
                    HeightMapMeta { origin_x_mm: -3.0, origin_y_mm: 7.5, ..HeightMapMeta::new(w, h, 0.3) };
                HeightMap::new(meta, data).expect("valid map")
            })
        })
    }

    fn fine(map: &HeightMap, i: usize, j: usize) -> f32 {
        let w = map.width() as usize;
        if i < w && j < map.height() as usize { data(map.data()[j * w + i]) } else { f32::NAN }
    }

    /// Max of the data in columns `c0..=c1`, rows `r0..=r1` (signed, clipped).
    fn window_max(map: &HeightMap, c0: i64, c1: i64, r0: i64, r1: i64) -> f32 {
        let mut m = f32::NAN;
        for j in r0.max(0)..=r1 {
            for i in c0.max(0)..=c1 {
                m = nmax(m, fine(map, i as usize, j as usize));
            }
        }
        m
    }

    fn window_min(map: &HeightMap, c0: i64, c1: i64, r0: i64, r1: i64) -> f32 {
        let mut m = f32::NAN;
        for j in r0.max(0)..=r1 {
            for i in c0.max(0)..=c1 {
                m = m.min(fine(map, i as usize, j as usize));
            }
        }
        m
    }

    /// Naive node value straight from the definition.
    fn node_ref(map: &HeightMap, k: usize, ni: usize, nj: usize) -> f32 {
        let (k, ni, nj) = (k as i64, ni as i64, nj as i64);
        window_max(map, (ni - 1) * k + 1, (ni + 1) * k - 1, (nj - 1) * k + 1, (nj + 1) * k - 1)
    }

    /// Naive continuous_over: nodes from the definition, same interpolation.
    fn continuous_ref(map: &HeightMap, k: usize) -> Vec<f32> {
        let (w, h) = (map.width() as usize, map.height() as usize);
        let mut out = Vec::new();
        for j in 0..h {
            for i in 0..w {
                let (ni, nj) = (i / k, j / k);
                out.push(interpolate(
                    node_ref(map, k, ni, nj),
                    node_ref(map, k, ni + 1, nj),
                    node_ref(map, k, ni, nj + 1),
                    node_ref(map, k, ni + 1, nj + 1),
                    i % k,
                    j % k,
                    k,
                ));
            }
        }
        out
    }

    proptest! {
        #[test]
        fn block_max_is_the_block_maximum_and_never_below(map in arb_map(), k in 1u32..9) {
            let coarse = block_max(&map, k).expect("block max");
            let ku = k as usize;
            let (w, h) = (map.width() as usize, map.height() as usize);
            prop_assert_eq!((coarse.width() as usize, coarse.height() as usize), (w.div_ceil(ku), h.div_ceil(ku)));
            prop_assert_eq!(coarse.pixel_mm(), 0.3 * f64::from(k));
            prop_assert_eq!((coarse.origin_x_mm(), coarse.origin_y_mm()), (-3.0, 7.5));
            for r in 0..coarse.height() {
                for c in 0..coarse.width() {
                    let (c0, r0) = (i64::from(c) * i64::from(k), i64::from(r) * i64::from(k));
                    let want = window_max(&map, c0, c0 + i64::from(k) - 1, r0, r0 + i64::from(k) - 1);
                    let got = coarse.get(c, r).expect("cell");
                    prop_assert_eq!(got.to_bits(), want.to_bits(), "coarse ({}, {})", c, r);
                }
            }
            // Never below, through the geometric lookup too.
            let up = upsample_block(&coarse, map.meta()).expect("upsample");
            for j in 0..h {
                for i in 0..w {
                    let f = fine(&map, i, j);
                    if f.is_finite() {
                        let (x, y) = map.cell_center(i as u32, j as u32);
                        let (c, r) = coarse.cell_of(x, y).expect("inside");
                        prop_assert!(coarse.get(c, r).expect("cell") >= f);
                        prop_assert!(up.data()[j * w + i] >= f);
                    }
                }
            }
        }

        #[test]
        fn continuous_over_is_above_close_and_continuous(map in arb_map(), k in 1u32..9) {
            let g = continuous_over(&map, k).expect("continuous");
            prop_assert_eq!(g.meta(), map.meta());
            let coarse = block_max(&map, k).expect("block max");
            let ku = k as usize;
            let (w, h) = (map.width() as usize, map.height() as usize);
            let reference = continuous_ref(&map, ku);
            let at = |i: usize, j: usize| g.data()[j * w + i];
            for j in 0..h {
                for i in 0..w {
                    let (v, f) = (at(i, j), fine(&map, i, j));
                    prop_assert_eq!(v.to_bits(), reference[j * w + i].to_bits(), "vs reference at ({}, {})", i, j);
                    if f.is_finite() {
                        prop_assert!(v >= f, "({}, {}): {} below {}", i, j, v, f);
                    }
                    if v.is_nan() {
                        continue;
                    }
                    // Close: at most the 3x3 block-max neighbourhood.
                    let (c, r) = ((i / ku) as i64, (j / ku) as i64);
                    let mut near = f32::NAN;
                    for rr in (r - 1).max(0)..=r + 1 {
                        for cc in (c - 1).max(0)..=c + 1 {
                            near = nmax(near, coarse.get(cc as u32, rr as u32).unwrap_or(f32::NAN));
                        }
                    }
                    prop_assert!(v <= near, "({}, {}): {} above the 3x3 block max {}", i, j, v, near);
                    // Continuous: right and up neighbours.
                    let (ni, nj) = (i / ku, j / ku);
                    let nodes = [(ni, nj), (ni + 1, nj), (ni, nj + 1), (ni + 1, nj + 1)]
                        .map(|(a, b)| node_ref(&map, ku, a, b));
                    let (nlo, nhi) = nodes.iter().filter(|z| z.is_finite())
                        .fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), &z| (lo.min(z), hi.max(z)));
                    let (x0, x1) = ((ni as i64 - 1) * ku as i64 + 1, (ni as i64 + 2) * ku as i64 - 1);
                    let (y0, y1) = ((nj as i64 - 1) * ku as i64 + 1, (nj as i64 + 2) * ku as i64 - 1);
                    let data_span = window_max(&map, x0, x1, y0, y1) - window_min(&map, x0, x1, y0, y1);
                    for (a, b) in [(i + 1, j), (i, j + 1)] {
                        if a < w && b < h && at(a, b).is_finite() {
                            let d = f64::from(at(a, b) - v).abs();
                            let tol = 1e-5 * (1.0 + f64::from(v.abs()));
                            prop_assert!(d <= f64::from(nhi - nlo) / f64::from(k) + tol,
                                "({}, {})->({}, {}): step {} > node span {} / {}", i, j, a, b, d, nhi - nlo, k);
                            prop_assert!(d <= f64::from(data_span) / f64::from(k) + tol);
                        }
                    }
                }
            }
        }

        #[test]
        fn factor_one_is_the_identity(map in arb_map()) {
            let g = continuous_over(&map, 1).expect("k=1");
            for (a, b) in g.data().iter().zip(map.data()) {
                prop_assert_eq!(a.to_bits(), data(*b).to_bits());
            }
            let c = block_max(&map, 1).expect("k=1");
            for (a, b) in c.data().iter().zip(map.data()) {
                prop_assert_eq!(a.to_bits(), data(*b).to_bits());
            }
        }
    }

    #[test]
    fn plane_and_constant_and_errors() {
        let meta = HeightMapMeta::new(13, 9, 0.5);
        let flat = HeightMap::filled(meta, 2.5).expect("map");
        for k in [1, 2, 4, 20] {
            assert!(continuous_over(&flat, k).expect("k").data().iter().all(|&z| z == 2.5));
            let b = block_max(&flat, k).expect("k");
            assert!(b.data().iter().all(|&z| z == 2.5));
        }
        // A ramp: the over-approximation is the ramp shifted up by less than 2k cells of slope.
        let ramp = HeightMap::from_fn(meta, |c, _| c as f32).expect("map");
        let g = continuous_over(&ramp, 4).expect("k");
        for (a, b) in g.data().iter().zip(ramp.data()) {
            assert!(*a >= *b && *a - *b <= 7.0, "{a} {b}");
        }
        // 20 > width: a single coarse cell.
        let b = block_max(&ramp, 20).expect("k");
        assert_eq!((b.width(), b.height(), b.data()), (1, 1, &[12.0f32][..]));
        assert_eq!(
            block_max(&ramp, 0).expect_err("k=0").to_string(),
            "invalid roughing factor k = 0: must be at least 1"
        );
        assert!(continuous_over(&ramp, 0).is_err());
        assert!(upsample_block(&b, &HeightMapMeta { width: 0, ..meta }).is_err());
    }

    #[test]
    fn isolated_spike_and_hole() {
        // One tall cell among zeros: the result is >= the spike at the spike, tapers linearly
        // over k cells, and reaches 0 at 2k cells.
        let meta = HeightMapMeta::new(21, 21, 1.0);
        let mut map = HeightMap::filled(meta, 0.0).expect("map");
        map.set(10, 10, 8.0).expect("set");
        map.set(3, 3, f32::NAN).expect("hole");
        let g = continuous_over(&map, 4).expect("k");
        assert!(g.get(10, 10).expect("cell") >= 8.0);
        assert_eq!(g.get(10, 18), Some(0.0));
        assert_eq!(g.get(17, 10), Some(0.0));
        // The hole is bridged by the over-approximation.
        assert_eq!(g.get(3, 3), Some(0.0));
        // Nodes 8 and 12 both see the spike at 10: flat top between them.
        assert_eq!((g.get(8, 8), g.get(12, 12)), (Some(8.0), Some(8.0)));
    }
}
