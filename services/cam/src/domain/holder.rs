//! Holder collision: whether anything but the cutting part of the tool (the shank above the
//! cutting length, the holder above the stick-out) can touch the part while the tip follows the
//! program.
//!
//! The shank and the holder are flat-bottomed cylinders coaxial with the tool (see
//! [`Tool::body_profile`]): the shank of radius `rs` from `cutting_length_mm` above the tip, the
//! holder of radius `rh` from `stickout_mm` above the tip. A flat-bottomed cylinder of radius `r`
//! whose bottom is `b` above a tip at `(x, y, z)` clears the part exactly when
//! `D_r(x, y) <= z + b`, where `D_r` is the part A dilated by a flat disk of radius `r`
//! ([`max_filter_disk`]: the highest part point under the cylinder). So the check is the largest
//! `D_r - z` over the visited points, with `z = C(x, y)` (the compensated surface the tip rides on;
//! a program that stays above C is checked conservatively). `D_r` is not filtered over the whole
//! map: it is bounded above and below on a grid of block maxima (up to 8 x 8), and computed
//! exactly only at the visited points whose upper bound can still hold the largest value (a branch
//! and bound with the same result, tested against the full filters).
//!
//! - Holder: needs `stickout >= D_rh - C` at every visited point; the largest such value is the
//!   minimum stick-out reported.
//! - Shank: needs `cutting_length >= D_rs - C` (a deep, narrow pocket the flutes cannot reach the
//!   bottom of without the shank rubbing its walls). A longer stick-out does not help: the tool
//!   needs longer flutes, and the reported minimum stick-out is at least that cutting length.
//!
//! Disks use the point reading of the cells: a cell is under a cylinder when its centre lies within
//! the radius of the axis, the axis passing through the centre of the tip's cell. Visited points
//! outside the map use their own Z and a map padded with the floor by the holder radius.

use depthmill_geometry::{HeightMap, ToolProfile};
use nalgebra::Point3;

use rayon::prelude::*;

use super::CamError;
use super::compensate::{PixelModel, dilate, kernel};
use super::tool::Tool;

/// Tolerance of the comparisons (mm): a body part that touches the part within it is clear.
const TOUCH_MM: f64 = 1e-6;

/// Result of a passing [`check_holder`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HolderCheck {
    /// The shortest stick-out with which neither the holder nor the shank touches the part
    /// (at least the cutting length), rounded up to 0.01 mm.
    pub min_stickout_mm: f64,
    /// Smallest vertical gap between the shank or holder bottom and the part under it, over the
    /// visited points (mm; `f64::INFINITY` without visited points).
    pub clearance_mm: f64,
    /// Where that smallest gap occurs (tip XY, mm).
    pub worst_xy_mm: [f64; 2],
}

/// Checks that only the cutting part of `tool` can touch the part `map` while the tip visits
/// `visited` (XY used; the tip's Z there is `tip`, the compensated surface of the cutting profile on
/// `map`'s grid; points off the map use their own Z). `outside_z_mm` is the height of the part
/// outside the map and of cells without data.
///
/// Ok with the smallest clearance when the shank and the holder stay clear; otherwise
/// [`CamError::HolderCollision`] naming the place, the part of the tool and the minimum stick-out
/// (the shank case also names the cutting length needed). Errors on a `tip` of another size than
/// `map` or a non-finite `outside_z_mm`. Cost: the map's block maxima (O(W·H), blocks up to 8 x 8),
/// four disk max filters of those coarse grids, O(1) bounds per visited point, and an exact disk maximum
/// (O(disk cells)) only at the points whose upper bound can still beat the largest need found
/// (see `DiskMax`): the same result as two full disk filters of the map (tested against them).
pub fn check_holder(
    map: &HeightMap,
    tool: &Tool,
    tip: &HeightMap,
    visited: &[Point3<f64>],
    outside_z_mm: f64,
) -> Result<HolderCheck, CamError> {
    if tip.width() != map.width() || tip.height() != map.height() {
        return Err(CamError::param(
            "tip",
            format!(
                "grid {}x{} differs from the map's {}x{}",
                tip.width(),
                tip.height(),
                map.width(),
                map.height()
            ),
        ));
    }
    if !outside_z_mm.is_finite() {
        return Err(CamError::param("outside_z_mm", format!("must be finite, got {outside_z_mm}")));
    }
    let floor = outside_z_mm as f32;
    // Points up to the larger radius (and a cell) off the map still see it.
    let reach = (tool.shank_diameter_mm / 2.0).max(tool.holder_diameter_mm / 2.0);
    let pad = (reach / map.pixel_mm()).ceil() as i64 + 1;
    let shank = DiskMax::new(map, tool.shank_diameter_mm / 2.0, pad, floor)?;
    let holder = DiskMax::new(map, tool.holder_diameter_mm / 2.0, pad, floor)?;

    // The tip's height at each visited point, and its cell when the padded map holds it.
    let at: Vec<(f64, Option<(i64, i64)>)> = visited
        .par_iter()
        .map(|v| {
            let z = match tip.cell_of(v.x, v.y) {
                Some((c, r)) => tip.get(c, r).map(f64::from).unwrap_or(v.z),
                None => v.z,
            };
            let z = if z.is_finite() { z } else { v.z };
            let c = ((v.x - map.origin_x_mm()) / map.pixel_mm()).floor();
            let r = ((v.y - map.origin_y_mm()) / map.pixel_mm()).floor();
            let inside = |k: f64, n: u32| k >= -(pad as f64) && k < f64::from(n) + pad as f64;
            (z, (inside(c, map.width()) && inside(r, map.height())).then_some((c as i64, r as i64)))
        })
        .collect();
    // Off the padded map only the floor is under the tool: the shank needs `floor - z`.
    let mut off = Best::default();
    for (i, &(z, cell)) in at.iter().enumerate() {
        if cell.is_none() {
            off.offer(f64::from(floor) - z, i);
        }
    }
    let shank_best = shank.max_need(&at).merge(off);
    let holder_best = holder.max_need(&at);
    let (need_shank, need_holder) = (shank_best.value, holder_best.value);
    let at_xy = |b: Best| b.index.map_or([f64::NAN; 2], |i| [visited[i].x, visited[i].y]);
    let (shank_at, holder_at) = (at_xy(shank_best), at_xy(holder_best));
    // The smallest gap is the shank's or the holder's at its own worst point (the first visited
    // point where it occurs).
    let (gap_shank, gap_holder) = (tool.cutting_length_mm - need_shank, tool.stickout_mm - need_holder);
    let (clearance, worst) = match (shank_best.index, holder_best.index) {
        (Some(i), Some(j)) if gap_holder < gap_shank || (gap_holder == gap_shank && j < i) => {
            (gap_holder, holder_at)
        }
        (Some(_), _) => (gap_shank, shank_at),
        (None, Some(_)) => (gap_holder, holder_at),
        (None, None) => (f64::INFINITY, [f64::NAN; 2]),
    };
    verdict(tool, (need_shank, shank_at), (need_holder, holder_at), clearance, worst)
}

/// The check's result from the largest needs of the shank and the holder (mm above the tip, and
/// where), and the smallest gap with where it is: an error naming the part of the tool that
/// touches, else the minimum stick-out and the clearance.
fn verdict(
    tool: &Tool,
    (need_shank, shank_at): (f64, [f64; 2]),
    (need_holder, holder_at): (f64, [f64; 2]),
    clearance: f64,
    worst: [f64; 2],
) -> Result<HolderCheck, CamError> {
    let round_up = |x: f64| (x * 100.0 - 1e-9).ceil() / 100.0;
    let min_stickout_mm = round_up(need_holder.max(need_shank).max(tool.cutting_length_mm));
    if need_shank > tool.cutting_length_mm + TOUCH_MM {
        return Err(CamError::HolderCollision {
            message: format!(
                "tool {}: the shank (diameter {} mm) touches the part at x {:.3} mm, y {:.3} mm: \
                 the part rises {:.3} mm above the tip there, cutting_length_mm {} is too short; \
                 use a tool with at least {:.2} mm of cutting length and a stick-out of at least {:.2} mm",
                tool.name,
                tool.shank_diameter_mm,
                shank_at[0],
                shank_at[1],
                need_shank,
                tool.cutting_length_mm,
                round_up(need_shank),
                min_stickout_mm
            ),
            min_stickout_mm,
        });
    }
    if need_holder > tool.stickout_mm + TOUCH_MM {
        return Err(CamError::HolderCollision {
            message: format!(
                "tool {}: the holder (diameter {} mm) touches the part at x {:.3} mm, y {:.3} mm: \
                 the part rises {:.3} mm above the tip there, stickout_mm {} is too short; \
                 the minimum stick-out is {:.2} mm",
                tool.name,
                tool.holder_diameter_mm,
                holder_at[0],
                holder_at[1],
                need_holder,
                tool.stickout_mm,
                min_stickout_mm
            ),
            min_stickout_mm,
        });
    }
    Ok(HolderCheck { min_stickout_mm, clearance_mm: clearance, worst_xy_mm: worst })
}

/// Most cells of a block of the coarse grid [`DiskMax`] bounds on (per side).
const MAX_BLOCK: i64 = 8;

/// The largest of the candidates offered, and the first (lowest index) visited point where it
/// occurs.
#[derive(Debug, Clone, Copy)]
struct Best {
    value: f64,
    index: Option<usize>,
}

impl Default for Best {
    fn default() -> Self {
        Best { value: f64::NEG_INFINITY, index: None }
    }
}

impl Best {
    fn offer(&mut self, value: f64, index: usize) {
        if value.is_nan() {
            return;
        }
        match self.index {
            Some(i) if value < self.value || (value == self.value && index > i) => {}
            _ => *self = Best { value, index: Some(index) },
        }
    }

    fn merge(mut self, other: Best) -> Best {
        if let Some(i) = other.index {
            self.offer(other.value, i);
        }
        self
    }
}

/// The highest part point under a flat-bottomed cylinder of one radius whose axis passes through
/// the centre of a tip cell (cells outside the map and NaN cells read as the floor): exact on
/// demand, and bounded from above and below on a coarse grid of block maxima so that only the
/// visited points that can hold the largest value are evaluated exactly.
///
/// Bounds: a block of `s` x `s` cells (`s` up to [`MAX_BLOCK`], small enough that the bounds'
/// slack `2·hd` stays within a quarter of the radius) has its centre within `hd` (half its diagonal of cell
/// centres) of each of its cells. A cell within `r` of the tip's cell lies in a block whose centre
/// is within `r + 2·hd` of the centre of the tip's block, so the coarse disk maximum of that radius
/// is an upper bound; every cell of a block whose centre is within `r - 2·hd` of the tip's block
/// centre lies within `r` of the tip's cell, so the coarse disk maximum of that radius (and the tip's
/// own cell) is a lower bound. Both radii carry one cell of slack for rounding. The exact values are
/// the same f32 maxima as the full disk filter ([`max_filter_disk`]).
struct DiskMax<'a> {
    map: &'a HeightMap,
    floor: f32,
    /// The disk's rows (point reading): `ext[dy + reach] = (dx0, len)`, `None` for a row it
    /// misses.
    ext: Vec<Option<(i64, i64)>>,
    reach: i64,
    blocks: Blocks,
    upper: Vec<f32>,
    lower: Vec<f32>,
}

/// The map's block maxima (floor outside), on a grid that starts `off` cells before the map on
/// both axes.
struct Blocks {
    map: HeightMap,
    off: i64,
    /// Cells per block side.
    s: i64,
}

impl Blocks {
    /// Blocks of `s` x `s` cells covering the map grown by `pad` cells on every side.
    fn new(map: &HeightMap, s: i64, pad: i64, floor: f32) -> Result<Self, CamError> {
        let ceil_blocks = |n: i64| (n.max(0) + s - 1) / s;
        let off = ceil_blocks(pad) * s;
        let (w, h) = (i64::from(map.width()), i64::from(map.height()));
        let (bw, bh) = (ceil_blocks(w + 2 * off), ceil_blocks(h + 2 * off));
        let data = map.data();
        let mut out = vec![f32::NEG_INFINITY; (bw * bh) as usize];
        out.par_chunks_mut(bw as usize).enumerate().for_each(|(br, acc)| {
            for y in (br as i64 * s - off)..((br as i64 + 1) * s - off) {
                if y < 0 || y >= h {
                    acc.iter_mut().for_each(|a| *a = a.max(floor));
                    continue;
                }
                let row = &data[(y * w) as usize..((y + 1) * w) as usize];
                for (b, a) in acc.iter_mut().enumerate() {
                    let x0 = b as i64 * s - off;
                    let (lo, hi) = (x0.max(0), (x0 + s).min(w));
                    let mut m = *a;
                    if lo > x0 || hi < x0 + s {
                        m = m.max(floor);
                    }
                    if lo < hi {
                        for &z in &row[lo as usize..hi as usize] {
                            m = m.max(if z.is_nan() { floor } else { z });
                        }
                    }
                    *a = m;
                }
            }
        });
        let p = map.pixel_mm() * s as f64;
        let meta = depthmill_geometry::HeightMapMeta {
            origin_x_mm: map.origin_x_mm() - off as f64 * map.pixel_mm(),
            origin_y_mm: map.origin_y_mm() - off as f64 * map.pixel_mm(),
            z_min_mm: map.z_min_mm(),
            z_max_mm: map.z_max_mm(),
            ..depthmill_geometry::HeightMapMeta::new(bw as u32, bh as u32, p)
        };
        let map = HeightMap::new(meta, out).map_err(|e| CamError::InvalidMap { message: e.to_string() })?;
        Ok(Blocks { map, off, s })
    }

    /// Index of the block holding cell `(c, r)` (map cells; must lie on the block grid).
    fn index(&self, c: i64, r: i64) -> usize {
        let (bc, br) = ((c + self.off) / self.s, (r + self.off) / self.s);
        (br * i64::from(self.map.width()) + bc) as usize
    }
}

impl<'a> DiskMax<'a> {
    /// The disk of `radius_mm` over `map`, for tip cells up to `pad` cells off the map.
    fn new(map: &'a HeightMap, radius_mm: f64, pad: i64, floor: f32) -> Result<Self, CamError> {
        let p = map.pixel_mm();
        let disk = (radius_mm.is_finite() && radius_mm > 0.0)
            .then(|| ToolProfile::flat(2.0 * radius_mm).ok())
            .flatten();
        let rows: Vec<(i64, i64, i64)> = match &disk {
            Some(d) => kernel(d, p, PixelModel::Point)
                .rows
                .iter()
                .map(|r| (i64::from(r.dy), i64::from(r.dx0), r.heights.len() as i64))
                .collect(),
            None => vec![(0, 0, 1)],
        };
        let reach =
            rows.iter().map(|&(dy, dx0, len)| dy.abs().max(dx0.abs()).max(dx0 + len - 1)).max().unwrap_or(0);
        let mut ext = vec![None; (2 * reach + 1) as usize];
        for &(dy, dx0, len) in &rows {
            ext[(dy + reach) as usize] = Some((dx0, len));
        }
        let r = disk.map_or(0.0, |_| radius_mm);
        let half_diagonal = |s: i64| (s - 1) as f64 / 2.0 * p * std::f64::consts::SQRT_2;
        let mut s = MAX_BLOCK;
        while s > 1 && 2.0 * half_diagonal(s) > r / 4.0 {
            s /= 2;
        }
        let blocks = Blocks::new(map, s, pad, floor)?;
        let hd = half_diagonal(s);
        let upper = max_filter_disk(&blocks.map, r + 2.0 * hd + p, floor);
        let low_r = r - 2.0 * hd - p;
        let lower = if low_r > 0.0 {
            max_filter_disk(&blocks.map, low_r, floor)
        } else {
            vec![f32::NEG_INFINITY; upper.len()]
        };
        Ok(DiskMax { map, floor, ext, reach, blocks, upper, lower })
    }

    fn cell(&self, c: i64, r: i64) -> f32 {
        let (w, h) = (i64::from(self.map.width()), i64::from(self.map.height()));
        if c < 0 || r < 0 || c >= w || r >= h {
            return self.floor;
        }
        let z = self.map.data()[(r * w + c) as usize];
        if z.is_nan() { self.floor } else { z }
    }

    /// The exact highest point under the disk centred on cell `(c, r)`: the block maximum of every
    /// block whose four corner cells lie in the disk (then all its cells do: the disk is convex),
    /// the cells themselves in the blocks its edge crosses.
    fn exact(&self, c: i64, r: i64) -> f32 {
        let (w, h) = (i64::from(self.map.width()), i64::from(self.map.height()));
        let data = self.map.data();
        let reach = self.reach;
        // The disk's cells on row y: [lo, hi).
        let span = |y: i64| -> Option<(i64, i64)> {
            let k = y - r + reach;
            if k < 0 || k >= self.ext.len() as i64 {
                return None;
            }
            self.ext[k as usize].map(|(dx0, len)| (c + dx0, c + dx0 + len))
        };
        let inside = |x: i64, y: i64| span(y).is_some_and(|(lo, hi)| x >= lo && x < hi);
        let b = &self.blocks;
        let bw = i64::from(b.map.width());
        let mut best = f32::NEG_INFINITY;
        let first = |v: i64| (v + b.off).div_euclid(b.s);
        for br in first(r - reach)..=first(r + reach) {
            let (y0, y1) = (br * b.s - b.off, (br + 1) * b.s - b.off);
            for bc in first(c - reach)..=first(c + reach) {
                let (x0, x1) = (bc * b.s - b.off, (bc + 1) * b.s - b.off);
                let on_grid = br >= 0 && bc >= 0 && bc < bw && br < i64::from(b.map.height());
                if on_grid
                    && inside(x0, y0)
                    && inside(x1 - 1, y0)
                    && inside(x0, y1 - 1)
                    && inside(x1 - 1, y1 - 1)
                {
                    best = best.max(b.map.data()[(br * bw + bc) as usize]);
                    continue;
                }
                for y in y0..y1 {
                    let Some((lo, hi)) = span(y) else { continue };
                    let (lo, hi) = (lo.max(x0), hi.min(x1));
                    if lo >= hi {
                        continue;
                    }
                    if y < 0 || y >= h || lo < 0 || hi > w {
                        best = best.max(self.floor);
                    }
                    let (a, z) = (lo.max(0), hi.min(w));
                    if y < 0 || y >= h || a >= z {
                        continue;
                    }
                    for &v in &data[(y * w + a) as usize..(y * w + z) as usize] {
                        let v = if v.is_nan() { self.floor } else { v };
                        if v > best {
                            best = v;
                        }
                    }
                }
            }
        }
        best
    }

    /// The largest `highest point under the disk - z` over the visited points with a cell
    /// (`(z, cell)`), and the first point where it occurs: every point's bounds, then exact values
    /// in decreasing order of their upper bounds until no upper bound can beat the best found.
    fn max_need(&self, at: &[(f64, Option<(i64, i64)>)]) -> Best {
        // The point with the best lower bound, evaluated exactly, sets the bar.
        let seed = at
            .par_iter()
            .enumerate()
            .filter_map(|(i, &(z, cell))| {
                let (c, r) = cell?;
                let lo = f64::from(self.lower[self.blocks.index(c, r)].max(self.cell(c, r))) - z;
                (!lo.is_nan()).then_some((lo, i))
            })
            .reduce_with(|a, b| if b.0 > a.0 || (b.0 == a.0 && b.1 < a.1) { b } else { a });
        let mut best = Best::default();
        let Some((_, first)) = seed else { return best };
        let mut cache = std::collections::HashMap::new();
        let mut exact = |i: usize, best: &mut Best| {
            if let (z, Some((c, r))) = at[i] {
                let e = *cache.entry((c, r)).or_insert_with(|| self.exact(c, r));
                best.offer(f64::from(e) - z, i);
            }
        };
        exact(first, &mut best);
        let bar = best.value;
        let mut candidates: Vec<(f64, usize)> = at
            .par_iter()
            .enumerate()
            .filter_map(|(i, &(z, cell))| {
                let (c, r) = cell?;
                let up = f64::from(self.upper[self.blocks.index(c, r)]) - z;
                (up >= bar).then_some((up, i))
            })
            .collect();
        candidates.sort_unstable_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
        for (up, i) in candidates {
            if up < best.value {
                break;
            }
            exact(i, &mut best);
        }
        best
    }
}

/// Flat disk dilation of `map`: each cell gets the highest value among the cells whose centres lie
/// within `radius_mm` of its centre (NaN cells and cells outside the map read as `outside_z`). A
/// radius below one cell (or not finite and positive) leaves each cell alone (NaN -> `outside_z`).
///
/// Algorithm: the disk's rows with the same half-width share one maximum of their source rows, then
/// one running maximum along the row: doubling for windows up to 128 cells, van Herk/Gil-Werman
/// (O(1) per cell whatever the width) beyond; parallel over output rows. Exact (maxima only).
pub fn max_filter_disk(map: &HeightMap, radius_mm: f64, outside_z: f32) -> Vec<f32> {
    let cells = || map.data().iter().map(|&z| if z.is_nan() { outside_z } else { z }).collect();
    if !(radius_mm.is_finite() && radius_mm > 0.0) {
        return cells();
    }
    match ToolProfile::flat(2.0 * radius_mm) {
        Ok(disk) => dilate(map, &kernel(&disk, map.pixel_mm(), PixelModel::Point), outside_z),
        Err(_) => cells(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::domain::compensate::{CompensateOptions, compensate};
    use depthmill_geometry::HeightMapMeta;
    use proptest::prelude::*;

    /// The check as the full disk filters of the padded map give it, every visited point looked up
    /// (the obviously right reference of [`check_holder`]).
    fn reference(
        map: &HeightMap,
        tool: &Tool,
        tip: &HeightMap,
        visited: &[Point3<f64>],
        outside_z_mm: f64,
    ) -> Result<HolderCheck, CamError> {
        if tip.width() != map.width() || tip.height() != map.height() {
            return Err(CamError::param(
                "tip",
                format!(
                    "grid {}x{} differs from the map's {}x{}",
                    tip.width(),
                    tip.height(),
                    map.width(),
                    map.height()
                ),
            ));
        }
        if !outside_z_mm.is_finite() {
            return Err(CamError::param("outside_z_mm", format!("must be finite, got {outside_z_mm}")));
        }
        let floor = outside_z_mm as f32;
        let shank_r = tool.shank_diameter_mm / 2.0;
        let holder_r = tool.holder_diameter_mm / 2.0;
        // Pad the map by the larger radius so points just off the map still see it.
        let p = map.pixel_mm();
        let pad = (shank_r.max(holder_r) / p).ceil() as u32 + 1;
        let big = padded(map, pad, floor)?;
        let shank = max_filter_disk(&big, shank_r, floor);
        let holder = max_filter_disk(&big, holder_r, floor);
        let bw = big.width() as usize;

        let mut need_holder = f64::NEG_INFINITY;
        let mut need_shank = f64::NEG_INFINITY;
        let (mut holder_at, mut shank_at) = ([0.0; 2], [0.0; 2]);
        let mut clearance = f64::INFINITY;
        let mut worst = [f64::NAN; 2];
        for v in visited {
            let z = match tip.cell_of(v.x, v.y) {
                Some((c, r)) => tip.get(c, r).map(f64::from).unwrap_or(v.z),
                None => v.z,
            };
            let z = if z.is_finite() { z } else { v.z };
            let Some((c, r)) = big.cell_of(v.x, v.y) else {
                // Farther off the map than either radius: only the floor is under the tool.
                let gap = tool.cutting_length_mm - (f64::from(floor) - z);
                if gap < clearance {
                    clearance = gap;
                    worst = [v.x, v.y];
                }
                let need = f64::from(floor) - z;
                if need > need_shank {
                    need_shank = need;
                    shank_at = [v.x, v.y];
                }
                continue;
            };
            let i = r as usize * bw + c as usize;
            let (ds, dh) = (f64::from(shank[i]) - z, f64::from(holder[i]) - z);
            if ds > need_shank {
                need_shank = ds;
                shank_at = [v.x, v.y];
            }
            if dh > need_holder {
                need_holder = dh;
                holder_at = [v.x, v.y];
            }
            let gap = (tool.cutting_length_mm - ds).min(tool.stickout_mm - dh);
            if gap < clearance {
                clearance = gap;
                worst = [v.x, v.y];
            }
        }
        verdict(tool, (need_shank, shank_at), (need_holder, holder_at), clearance, worst)
    }

    /// `map` grown by `pad` floor cells on every side (same cells, origin moved).
    fn padded(map: &HeightMap, pad: u32, floor: f32) -> Result<HeightMap, CamError> {
        let mut meta = *map.meta();
        meta.width += 2 * pad;
        meta.height += 2 * pad;
        meta.origin_x_mm -= f64::from(pad) * map.pixel_mm();
        meta.origin_y_mm -= f64::from(pad) * map.pixel_mm();
        let (w, bw) = (map.width() as usize, meta.width as usize);
        let mut data = vec![floor; bw * meta.height as usize];
        for (r, src) in map.data().chunks_exact(w).enumerate() {
            let start = (r + pad as usize) * bw + pad as usize;
            data[start..start + w].copy_from_slice(src);
        }
        HeightMap::new(meta, data).map_err(|e| CamError::InvalidMap { message: e.to_string() })
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(96))]
        #[test]
        fn the_bounded_check_equals_the_full_filters(
            (w, h, data) in (1u32..70, 1u32..70).prop_flat_map(|(w, h)| {
                (Just(w), Just(h), prop::collection::vec(prop_oneof![12 => 0.0f32..30.0, 1 => Just(f32::NAN), 2 => Just(5.0f32)], (w * h) as usize))
            }),
            pixel in prop_oneof![Just(0.1f64), Just(0.25), Just(0.5), 0.05f64..1.0],
            shank_d in 0.5f64..12.0,
            holder_d in 0.5f64..40.0,
            cutting in 1.0f64..20.0,
            extra in 0.0f64..30.0,
            floor in -5.0f32..10.0,
            pts in prop::collection::vec((-0.3f64..1.3, -0.3f64..1.3, -10.0f64..40.0), 0..80),
            far in prop::collection::vec((-50.0f64..50.0, -50.0f64..50.0, -10.0f64..40.0), 0..4),
        ) {
            let mut meta = HeightMapMeta::new(w, h, pixel);
            meta.z_max_mm = 30.0;
            let map = HeightMap::new(meta, data.clone()).expect("map");
            // A tip surface with holes and values unrelated to the map: the check reads it as given.
            let tip_data: Vec<f32> = data.iter().enumerate()
                .map(|(i, z)| if i % 7 == 3 { f32::NAN } else { z - (i % 5) as f32 * 0.5 })
                .collect();
            let tip = HeightMap::new(meta, tip_data).expect("tip");
            let mut t = tool("ball-3", None);
            t.shank_diameter_mm = shank_d;
            t.holder_diameter_mm = holder_d;
            t.cutting_length_mm = cutting;
            t.stickout_mm = cutting + extra;
            let (wm, hm) = (meta.width_mm(), meta.height_mm());
            let visited: Vec<Point3<f64>> = pts.iter()
                .map(|&(u, v, z)| Point3::new(u * wm, v * hm, z))
                .chain(far.iter().map(|&(x, y, z)| Point3::new(x, y, z)))
                .collect();
            let fast = check_holder(&map, &t, &tip, &visited, f64::from(floor));
            let slow = reference(&map, &t, &tip, &visited, f64::from(floor));
            match (fast, slow) {
                (Ok(a), Ok(b)) => {
                    prop_assert_eq!(a.min_stickout_mm, b.min_stickout_mm);
                    prop_assert!(a.clearance_mm == b.clearance_mm, "{:?} vs {:?}", a, b);
                    prop_assert!(
                        a.worst_xy_mm.iter().zip(&b.worst_xy_mm).all(|(x, y)| x == y || (x.is_nan() && y.is_nan())),
                        "{:?} vs {:?}", a, b
                    );
                }
                (Err(a), Err(b)) => prop_assert_eq!(a.to_string(), b.to_string()),
                (a, b) => prop_assert!(false, "{:?} vs {:?}", a, b),
            }
        }
    }

    fn map_fn(w: u32, h: u32, pixel: f64, f: impl Fn(f64, f64) -> f32) -> HeightMap {
        let mut meta = HeightMapMeta::new(w, h, pixel);
        meta.z_min_mm = 0.0;
        meta.z_max_mm = 60.0;
        HeightMap::from_fn(meta, |c, r| {
            let (x, y) = meta.cell_center(c, r);
            f(x, y)
        })
        .expect("map")
    }

    fn brute_disk(map: &HeightMap, radius_mm: f64, outside: f32) -> Vec<f32> {
        let (w, h) = (i64::from(map.width()), i64::from(map.height()));
        let p = map.pixel_mm();
        let n = (radius_mm / p).ceil() as i64 + 1;
        let mut out = Vec::new();
        for y in 0..h {
            for x in 0..w {
                let mut best = f32::NEG_INFINITY;
                for dy in -n..=n {
                    for dx in -n..=n {
                        if p * ((dx * dx + dy * dy) as f64).sqrt() > radius_mm {
                            continue;
                        }
                        let (xx, yy) = (x + dx, y + dy);
                        let z = if xx < 0 || yy < 0 || xx >= w || yy >= h {
                            outside
                        } else {
                            map.data()[(yy * w + xx) as usize]
                        };
                        best = best.max(if z.is_nan() { outside } else { z });
                    }
                }
                out.push(best);
            }
        }
        out
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]
        #[test]
        fn disk_filter_matches_brute_force(
            (w, h, data) in (1u32..30, 1u32..30).prop_flat_map(|(w, h)| {
                (Just(w), Just(h), prop::collection::vec(prop_oneof![9 => -5.0f32..5.0, 1 => Just(f32::NAN)], (w * h) as usize))
            }),
            radius in 0.0f64..2.5,
            outside in -6.0f32..6.0,
        ) {
            let mut meta = HeightMapMeta::new(w, h, 0.1);
            meta.z_max_mm = 5.0;
            let map = HeightMap::new(meta, data).expect("map");
            let fast = max_filter_disk(&map, radius, outside);
            let slow = brute_disk(&map, radius, outside);
            prop_assert_eq!(fast, slow);
        }
    }

    #[test]
    fn wide_disks_use_the_running_maximum_and_stay_exact() {
        let map = map_fn(90, 40, 0.1, |x, y| ((x * 3.1).sin() * (y * 1.7).cos()) as f32);
        assert_eq!(max_filter_disk(&map, 8.0, -2.0), brute_disk(&map, 8.0, -2.0));
    }

    /// A floor at 0 with a 50 mm wall for x >= 25 mm; a 4 mm wide, 20 mm deep slot at x 5 mm.
    fn part() -> HeightMap {
        map_fn(300, 100, 0.1, |x, _| {
            if x >= 25.0 {
                50.0
            } else if (3.0..7.0).contains(&x) {
                -20.0
            } else {
                0.0
            }
        })
    }

    fn tool(name: &str, stickout: Option<f64>) -> Tool {
        let mut t = Tool::from_spec(&name.parse().expect("spec")).expect("tool");
        if let Some(s) = stickout {
            t.stickout_mm = s;
        }
        t.validate().expect("valid");
        t
    }

    fn surface(map: &HeightMap, tool: &Tool) -> HeightMap {
        let opts = CompensateOptions { pixel_model: PixelModel::Point, outside_z_mm: Some(0.0) };
        compensate(map, &tool.profile, &opts).expect("compensate")
    }

    #[test]
    fn holder_beside_a_tall_wall_needs_the_reported_stickout() {
        let map = part();
        let short = tool("ball-6", Some(34.0));
        let tip = surface(&map, &short);
        // On the floor 10 mm from the wall: the 32 mm holder (radius 16) reaches over the wall.
        let visited = [Point3::new(15.0, 5.0, 0.0), Point3::new(13.05, 5.05, 0.0)];
        let e = check_holder(&map, &short, &tip, &visited, 0.0).expect_err("collides");
        let CamError::HolderCollision { message, min_stickout_mm } = e else { panic!("{e:?}") };
        assert!(
            message.contains("holder") && message.contains("x 15.") && message.contains("stickout_mm 34")
        );
        assert!((min_stickout_mm - 50.0).abs() < 0.02, "{min_stickout_mm}");
        let long = tool("ball-6", Some(min_stickout_mm));
        let ok = check_holder(&map, &long, &tip, &visited, 0.0).expect("clear");
        assert!(ok.clearance_mm >= -1e-6 && ok.clearance_mm < 0.02, "{ok:?}");
        assert_eq!(ok.worst_xy_mm, [15.0, 5.0]);
        // Far from the wall (more than 16 mm + the cell) nothing collides.
        let ok = check_holder(&map, &short, &tip, &[Point3::new(1.0, 5.0, 0.0)], 0.0);
        assert!(ok.is_ok(), "{ok:?}");
    }

    #[test]
    fn shank_in_a_deep_narrow_slot_needs_longer_flutes() {
        let map = part();
        // A 3 mm ball (cutting length 9 mm) on a 6 mm shank at the bottom of the 4 mm slot.
        let mut t = tool("ball-3", Some(60.0));
        t.shank_diameter_mm = 6.0;
        let tip = surface(&map, &t);
        let visited = [Point3::new(5.0, 5.0, -20.0)];
        let e = check_holder(&map, &t, &tip, &visited, 0.0).expect_err("shank collides");
        let CamError::HolderCollision { message, min_stickout_mm } = e else { panic!("{e:?}") };
        assert!(message.contains("shank") && message.contains("cutting length"), "{message}");
        assert!((min_stickout_mm - 20.0).abs() < 0.05, "{min_stickout_mm}");
        // A tool with flutes as long as the slot is deep and that stick-out passes.
        let mut long = t.clone();
        long.cutting_length_mm = min_stickout_mm;
        long.stickout_mm = min_stickout_mm.max(long.stickout_mm);
        assert!(check_holder(&map, &long, &tip, &visited, 0.0).is_ok());
    }

    #[test]
    fn points_off_the_map_and_bad_input() {
        let map = part();
        let t = tool("ball-6", None);
        let tip = surface(&map, &t);
        // Just off the map beside the wall: the padded map still sees it.
        let off = [Point3::new(31.0, -2.0, 0.0)];
        assert!(check_holder(&map, &t, &tip, &off, 0.0).is_err());
        let far = [Point3::new(-100.0, -100.0, 0.0)];
        assert!(check_holder(&map, &t, &tip, &far, 0.0).is_ok());
        assert!(check_holder(&map, &t, &tip, &far, f64::NAN).is_err());
        let other = map_fn(3, 3, 0.1, |_, _| 0.0);
        assert!(check_holder(&map, &t, &other, &far, 0.0).is_err());
    }
}
