//! Holder collision: whether anything but the cutting part of the tool (the shank above the
//! cutting length, the holder above the stick-out) can touch the part while the tip follows the
//! program.
//!
//! The shank and the holder are flat-bottomed cylinders coaxial with the tool (see
//! [`Tool::body_profile`]): the shank of radius `rs` from `cutting_length_mm` above the tip, the
//! holder of radius `rh` from `stickout_mm` above the tip. A flat-bottomed cylinder of radius `r`
//! whose bottom is `b` above a tip at `(x, y, z)` clears the part exactly when
//! `D_r(x, y) <= z + b`, where `D_r` is the part A dilated by a flat disk of radius `r`
//! ([`max_filter_disk`]: the highest part point under the cylinder). So the check is two disk max
//! filters and one comparison per visited point, with `z = C(x, y)` (the compensated surface the
//! tip rides on; a program that stays above C is checked conservatively).
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
/// `map` or a non-finite `outside_z_mm`. Cost: two disk max filters of the map
/// (O(W·H·rows of the disk)) plus O(1) per visited point.
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
            let gap = z + tool.cutting_length_mm - f64::from(floor);
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
