//! Rest finishing: a smaller ball where the finishing tool left material, found on the stock
//! model (the preview's machined surface after roughing and finishing), not guessed from the
//! geometry.
//!
//! 1. The rest tool's tip surface `C'` ([`super::compensate::compensate`]) and its **envelope**
//!    `E(y) = min over kernel cells d of C'(y + d) + B(d)`: what the rest tool leaves if it visits
//!    every position (an erosion of `C'` by the tool, computed as `−dilate(−C')`).
//! 2. The **region**: cells where the stock after finishing stands more than `min_leftover_mm`
//!    above the target and the rest tool would take at least `min_leftover_mm` more off
//!    (`stock − E > min_leftover_mm`). Material no tool of the library gets at is left alone and
//!    reported, not chased.
//! 3. The **positions**: tip positions whose footprint covers a region cell (the region dilated by
//!    the tool's footprint).
//! 4. A finishing raster on `C'` cut to the runs of points over those positions, each run a pass
//!    entered from the safe height: the tip stays on `C'`, so the rest pass cannot gouge.

use depthmill_geometry::HeightMap;
use depthmill_geometry::raster::raster_cell;
use serde::Serialize;

use super::compensate::{Kernel, dilate};
use super::path::{Link, Pass, Toolpath};

/// Default least leftover a rest pass goes after, mm.
pub const DEFAULT_MIN_LEFTOVER_MM: f64 = 0.05;
/// Smallest region worth a tool change, in cells.
pub const MIN_REGION_CELLS: usize = 4;

/// What the rest tool leaves visiting every tip position of `tip` (module docs, step 1); the tool
/// goes nowhere off the map. The kernel is the tool's (symmetric).
pub fn envelope(tip: &HeightMap, kernel: &Kernel) -> Vec<f32> {
    let neg: Vec<f32> = tip.data().iter().map(|z| -z).collect();
    match HeightMap::new(*tip.meta(), neg) {
        Ok(neg) => dilate(&neg, kernel, f32::NEG_INFINITY).into_iter().map(|z| -z).collect(),
        // The tip's own grid: cannot fail; an empty result marks nothing for rest.
        Err(_) => vec![f32::INFINITY; tip.data().len()],
    }
}

/// Cells worth a rest pass (module docs, step 2): `surface` is the stock after the previous
/// operations, `env` the rest tool's [`envelope`], both on `target`'s grid.
pub fn region(surface: &[f32], target: &HeightMap, env: &[f32], min_leftover_mm: f64) -> Vec<bool> {
    let thr = min_leftover_mm as f32;
    target
        .data()
        .iter()
        .zip(surface)
        .zip(env)
        .map(|((t, s), e)| t.is_finite() && s - t > thr && s - e > thr)
        .collect()
}

/// Tip positions whose footprint covers a cell of `region` (module docs, step 3).
pub fn positions(region: &[bool], width: usize, height: usize, kernel: &Kernel) -> Vec<bool> {
    let mut out = vec![false; region.len()];
    for (i, _) in region.iter().enumerate().filter(|(_, r)| **r) {
        let (x, y) = ((i % width) as i64, (i / width) as i64);
        for row in &kernel.rows {
            let yy = y - i64::from(row.dy);
            if yy < 0 || yy >= height as i64 {
                continue;
            }
            for k in 0..row.heights.len() as i64 {
                let xx = x - i64::from(row.dx0) - k;
                if xx >= 0 && xx < width as i64 {
                    out[yy as usize * width + xx as usize] = true;
                }
            }
        }
    }
    out
}

/// `path` cut to its runs of consecutive points over `positions` (module docs, step 4), its
/// straight moves first cut at half a pixel; each run of two points or more becomes a pass
/// entered from the safe height.
pub fn restrict(path: Toolpath, positions: &[bool], tip: &HeightMap, strategy: &str) -> Toolpath {
    let meta = tip.meta();
    let w = meta.width as usize;
    let over = |p: &nalgebra::Point3<f64>| {
        raster_cell(meta, p.x, p.y).is_some_and(|(c, r)| positions[r as usize * w + c as usize])
    };
    let step = meta.pixel_mm / 2.0;
    let mut passes = Vec::new();
    for pass in path.passes {
        // The moves between a pass's points are straight: cut them at half a pixel so a long
        // stretch (a flat drawn with two points) is kept where it crosses the positions.
        let mut dense: Vec<nalgebra::Point3<f64>> = Vec::with_capacity(pass.points.len());
        for (i, &b) in pass.points.iter().enumerate() {
            if let Some(&a) = i.checked_sub(1).and_then(|j| pass.points.get(j)) {
                let n = ((b.xy() - a.xy()).norm() / step).ceil().clamp(1.0, 1e6) as usize;
                for k in 1..n {
                    dense.push(a + (b - a) * (k as f64 / n as f64));
                }
            }
            dense.push(b);
        }
        let mut run: Vec<nalgebra::Point3<f64>> = Vec::new();
        for p in dense {
            if over(&p) {
                run.push(p);
            } else if !run.is_empty() {
                if run.len() >= 2 {
                    passes.push(Pass { link: Link::Retract, points: std::mem::take(&mut run) });
                }
                run.clear();
            }
        }
        if run.len() >= 2 {
            passes.push(Pass { link: Link::Retract, points: run });
        }
    }
    Toolpath { strategy: strategy.into(), tool: path.tool, passes, safe_z_mm: path.safe_z_mm }
}

/// The rest operation of one face, in the plan report.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct RestReport {
    pub tool: String,
    /// Area the rest tool was sent to, mm².
    pub region_mm2: f64,
    /// The preview's leftover before the rest pass (after finishing), mm.
    pub max_leftover_before_mm: f64,
    pub mean_leftover_before_mm: f64,
}

/// Material left above the target after every operation, in connected groups.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct LeftRegion {
    /// Centre of the group's bounding box in the face frame, mm.
    pub center_mm: [f64; 2],
    pub area_mm2: f64,
    pub max_leftover_mm: f64,
}

/// Connected groups (8-neighbour) of cells whose `leftover` exceeds `min_mm`, largest first
/// (at most `limit`).
pub fn left_regions(leftover: &HeightMap, min_mm: f64, limit: usize) -> Vec<LeftRegion> {
    let (w, h) = (leftover.width() as usize, leftover.height() as usize);
    let d = leftover.data();
    let thr = min_mm as f32;
    let mut seen = vec![false; d.len()];
    let p = leftover.pixel_mm();
    let mut out = Vec::new();
    for start in 0..d.len() {
        if seen[start] || d[start].is_nan() || d[start] <= thr {
            continue;
        }
        seen[start] = true;
        let mut stack = vec![start];
        let (mut n, mut max) = (0usize, 0f32);
        let (mut c0, mut c1, mut r0, mut r1) = (usize::MAX, 0, usize::MAX, 0);
        while let Some(i) = stack.pop() {
            n += 1;
            max = max.max(d[i]);
            let (c, r) = (i % w, i / w);
            (c0, c1, r0, r1) = (c0.min(c), c1.max(c), r0.min(r), r1.max(r));
            for dr in -1i64..=1 {
                for dc in -1i64..=1 {
                    let (cc, rr) = (c as i64 + dc, r as i64 + dr);
                    if cc < 0 || rr < 0 || cc >= w as i64 || rr >= h as i64 {
                        continue;
                    }
                    let j = rr as usize * w + cc as usize;
                    if !seen[j] && d[j] > thr {
                        seen[j] = true;
                        stack.push(j);
                    }
                }
            }
        }
        let (x, _) = leftover.cell_center(c0 as u32, r0 as u32);
        let (x1, _) = leftover.cell_center(c1 as u32, r0 as u32);
        let (_, y) = leftover.cell_center(c0 as u32, r0 as u32);
        let (_, y1) = leftover.cell_center(c0 as u32, r1 as u32);
        out.push(LeftRegion {
            center_mm: [(x + x1) / 2.0, (y + y1) / 2.0],
            area_mm2: n as f64 * p * p,
            max_leftover_mm: f64::from(max),
        });
    }
    out.sort_by(|a, b| b.area_mm2.total_cmp(&a.area_mm2));
    out.truncate(limit);
    out
}

#[cfg(test)]
mod tests {
    use depthmill_geometry::{HeightMapMeta, ToolProfile};
    use rand::rngs::StdRng;
    use rand::{Rng, SeedableRng};

    use super::*;
    use crate::domain::compensate::{CompensateOptions, PixelModel, compensate, kernel};

    /// The obviously right envelope: every cell, every kernel cell.
    fn envelope_reference(tip: &HeightMap, k: &Kernel, outside_z: f32) -> Vec<f32> {
        let (w, h) = (tip.width() as i64, tip.height() as i64);
        let at = |x: i64, y: i64| {
            if x < 0 || y < 0 || x >= w || y >= h { outside_z } else { tip.data()[(y * w + x) as usize] }
        };
        let mut out = vec![f32::INFINITY; tip.data().len()];
        for y in 0..h {
            for x in 0..w {
                let mut best = f32::INFINITY;
                for row in &k.rows {
                    for (j, b) in row.heights.iter().enumerate() {
                        best = best.min(at(x + i64::from(row.dx0) + j as i64, y + i64::from(row.dy)) + b);
                    }
                }
                out[(y * w + x) as usize] = best;
            }
        }
        out
    }

    fn random_map(rng: &mut StdRng, w: u32, h: u32) -> HeightMap {
        let meta = HeightMapMeta::new(w, h, 0.25);
        HeightMap::from_fn(meta, |_, _| rng.random_range(0.0f32..3.0)).expect("map")
    }

    #[test]
    fn envelope_equals_the_reference_and_never_cuts_into_the_target() {
        let mut rng = StdRng::seed_from_u64(5);
        for d in [0.5, 1.0, 2.0] {
            let profile = ToolProfile::ball(d).expect("ball");
            let k = kernel(&profile, 0.25, PixelModel::Column);
            let map = random_map(&mut rng, 17, 13);
            let tip = compensate(
                &map,
                &profile,
                &CompensateOptions { pixel_model: PixelModel::Column, outside_z_mm: Some(0.0) },
            )
            .expect("tip");
            let fast = envelope(&tip, &k);
            assert_eq!(fast, envelope_reference(&tip, &k, f32::INFINITY), "ball {d}");
            // The tool on its tip surface never goes below the target.
            for (e, t) in fast.iter().zip(map.data()) {
                assert!(*e >= *t - 1e-5, "ball {d}: envelope {e} below target {t}");
            }
        }
    }

    #[test]
    fn a_fillet_the_big_ball_leaves_is_the_region_and_the_passes_stay_over_it() {
        // A step: floor at 0 for x < 5 mm, wall up to 3 mm beyond. A 3 mm ball leaves a fillet of
        // about its radius in the corner; a 1 mm ball takes most of it.
        let meta = HeightMapMeta::new(40, 20, 0.25);
        let target = HeightMap::from_fn(meta, |c, _| if c < 20 { 0.0 } else { 3.0 }).expect("map");
        let opts = CompensateOptions { pixel_model: PixelModel::Column, outside_z_mm: Some(0.0) };
        let big = ToolProfile::ball(3.0).expect("ball");
        let small = ToolProfile::ball(1.0).expect("ball");
        let kb = kernel(&big, 0.25, PixelModel::Column);
        let ks = kernel(&small, 0.25, PixelModel::Column);
        let after_big = envelope(&compensate(&target, &big, &opts).expect("tip"), &kb);
        let small_tip = compensate(&target, &small, &opts).expect("tip");
        let env = envelope(&small_tip, &ks);
        let reg = region(&after_big, &target, &env, 0.05);
        let cols: Vec<usize> = (0..40).filter(|&c| reg[10 * 40 + c]).collect();
        assert!(!cols.is_empty(), "no rest region in the corner");
        // Only in the corner: within the big ball's radius of the wall.
        assert!(cols.iter().all(|&c| (14..20).contains(&c)), "{cols:?}");
        let pos = positions(&reg, 40, 20, &ks);
        assert!(pos.iter().filter(|p| **p).count() >= reg.iter().filter(|r| **r).count());
        let path = Toolpath {
            strategy: "finishing-raster-x".into(),
            tool: "ball-1".into(),
            passes: (0..20)
                .map(|r| Pass {
                    link: Link::Direct,
                    points: (0..40)
                        .map(|c| {
                            let (x, y) = meta.cell_center(c, r);
                            nalgebra::Point3::new(x, y, f64::from(small_tip.get(c, r).unwrap_or(0.0)))
                        })
                        .collect(),
                })
                .collect(),
            safe_z_mm: 10.0,
        };
        let rest = restrict(path, &pos, &small_tip, "rest-raster-x");
        assert!(!rest.passes.is_empty());
        for pass in &rest.passes {
            assert_eq!(pass.link, Link::Retract);
            assert!(pass.points.len() >= 2);
            for p in &pass.points {
                let (c, r) = raster_cell(&meta, p.x, p.y).expect("on the grid");
                assert!(pos[r as usize * 40 + c as usize]);
            }
        }
    }

    #[test]
    fn left_regions_are_grouped_and_sized() {
        let meta = HeightMapMeta::new(10, 10, 0.5);
        let left = HeightMap::from_fn(meta, |c, r| match (c, r) {
            (1..=2, 1..=2) => 0.3,
            (7, 7) => 0.1,
            _ => 0.0,
        })
        .expect("map");
        let g = left_regions(&left, 0.05, 8);
        assert_eq!(g.len(), 2);
        assert!((g[0].area_mm2 - 1.0).abs() < 1e-9 && (g[0].max_leftover_mm - 0.3).abs() < 1e-6, "{g:?}");
        assert!((g[0].center_mm[0] - 1.0).abs() < 1e-9 && (g[0].center_mm[1] - 1.0).abs() < 1e-9, "{g:?}");
        assert!((g[1].area_mm2 - 0.25).abs() < 1e-9);
    }
}
