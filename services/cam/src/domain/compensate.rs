//! Tool compensation: the surface C the tool tip follows so the tool touches the part A without
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

use depthmill_geometry::{HeightMap, ToolProfile};

use super::CamError;

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
pub fn compensate(
    map: &HeightMap,
    profile: &ToolProfile,
    opts: &CompensateOptions,
) -> Result<HeightMap, CamError> {
    let outside = opts.outside_z_mm.unwrap_or(map.z_min_mm());
    if !outside.is_finite() {
        return Err(CamError::param("outside_z_mm", format!("must be finite, got {outside}")));
    }
    let k = kernel(profile, map.pixel_mm(), opts.pixel_model);
    let data = compensate_reference(map, &k, outside as f32);
    HeightMap::new(map.meta().clone(), data).map_err(|e| CamError::InvalidMap { message: e.to_string() })
}
