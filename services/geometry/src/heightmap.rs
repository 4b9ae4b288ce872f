//! [`HeightMap`]: a depth map z = f(x, y) on a square grid, in millimetres.
//!
//! # Grid convention
//!
//! Cell `(col, row)` covers `[x0 + col·p, x0 + (col+1)·p) × [y0 + row·p, y0 + (row+1)·p)` where
//! `p = pixel_mm` and `(x0, y0) = (origin_x_mm, origin_y_mm)` is the corner of cell `(0, 0)`.
//! Row 0 lies at minimum Y, column 0 at minimum X; data is row-major (`index = row·width + col`).
//! The cell's value is a point sample at the cell centre `(x0 + (col+½)·p, y0 + (row+½)·p)`.
//! `NaN` means "no data"; only finite values count as data.
//!
//! `z_min_mm`/`z_max_mm` is the range used when the map is exchanged as an image (black = `z_min`,
//! white = `z_max`). Heights in memory may lie outside it; image export clamps them.

use serde::{Deserialize, Serialize};

use crate::error::{GeometryError, Result};
use crate::face::Face;

/// Largest number of cells a height map may have (2^28, i.e. 1 GiB of f32).
pub const MAX_CELLS: u64 = 1 << 28;

/// Everything about a height map but its heights: grid size, placement, Z range and view.
///
/// Serialised as the `.npy` sidecar (`MAP.npy.json`) and mirrored by the PNG text chunks.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct HeightMapMeta {
    /// Number of columns (X direction).
    pub width: u32,
    /// Number of rows (Y direction).
    pub height: u32,
    /// Edge length of a square cell.
    pub pixel_mm: f64,
    /// X of the corner of cell (0, 0) (its minimum X).
    pub origin_x_mm: f64,
    /// Y of the corner of cell (0, 0) (its minimum Y).
    pub origin_y_mm: f64,
    /// Height shown as black when exchanged as an image.
    pub z_min_mm: f64,
    /// Height shown as white when exchanged as an image.
    pub z_max_mm: f64,
    /// View the map looks from.
    #[serde(default)]
    pub face: Face,
    /// The point of the part frame at the origin of the map's frame: a part-frame point `p`
    /// lies at `R·(p − part_origin_mm)` in the map's frame, `R` the face's rotation
    /// ([`Face::view_from_part`]). Zero for a part milled where it lies; a turned set-up puts
    /// the part's centre on the A axis, and every face of it carries that centre.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub part_origin_mm: [f64; 3],
}

fn is_zero(v: &[f64; 3]) -> bool {
    *v == [0.0; 3]
}

impl HeightMapMeta {
    /// A `width`×`height` grid of `pixel_mm` cells at the origin, Z range `[0, 1]` mm, view `+Z`.
    /// Call [`HeightMapMeta::validate`] (or build a map) to check it.
    pub fn new(width: u32, height: u32, pixel_mm: f64) -> Self {
        HeightMapMeta {
            width,
            height,
            pixel_mm,
            origin_x_mm: 0.0,
            origin_y_mm: 0.0,
            z_min_mm: 0.0,
            z_max_mm: 1.0,
            face: Face::PosZ,
            part_origin_mm: [0.0; 3],
        }
    }

    /// The rigid motion from the part frame to the map's frame: `p ↦ R·(p − part_origin_mm)`.
    pub fn view_from_part(&self) -> nalgebra::Isometry3<f64> {
        let [x, y, z] = self.part_origin_mm;
        self.face.view_from_part_pose() * nalgebra::Translation3::new(-x, -y, -z)
    }

    /// Checks: nonzero dimensions, at most [`MAX_CELLS`] cells, finite positive `pixel_mm`, finite
    /// origin, finite `z_min_mm < z_max_mm`, finite A angle.
    pub fn validate(&self) -> Result<()> {
        if self.width == 0 {
            return Err(GeometryError::invalid("width", self.width, "a positive cell count"));
        }
        if self.height == 0 {
            return Err(GeometryError::invalid("height", self.height, "a positive cell count"));
        }
        if self.cell_count() > MAX_CELLS {
            return Err(GeometryError::TooManyCells {
                width: self.width.into(),
                height: self.height.into(),
                limit: MAX_CELLS,
            });
        }
        if !(self.pixel_mm.is_finite() && self.pixel_mm > 0.0) {
            return Err(GeometryError::invalid("pixel_mm", self.pixel_mm, "a finite positive size"));
        }
        check_finite("origin_x_mm", self.origin_x_mm)?;
        check_finite("origin_y_mm", self.origin_y_mm)?;
        check_finite("z_min_mm", self.z_min_mm)?;
        check_finite("z_max_mm", self.z_max_mm)?;
        if self.z_min_mm >= self.z_max_mm {
            return Err(GeometryError::invalid("z_max_mm", self.z_max_mm, "a value greater than z_min_mm"));
        }
        for (key, v) in
            ["part_origin_mm x", "part_origin_mm y", "part_origin_mm z"].iter().zip(self.part_origin_mm)
        {
            check_finite(key, v)?;
        }
        match self.face {
            Face::A { angle_deg } => check_finite("face angle_deg", angle_deg)?,
            Face::Normal { x, y, z } => {
                let norm = (x * x + y * y + z * z).sqrt();
                if !norm.is_finite() || (norm - 1.0).abs() > 1e-6 {
                    return Err(GeometryError::invalid("face normal length", norm, "a unit vector"));
                }
            }
            _ => {}
        }
        Ok(())
    }

    /// `width · height`.
    pub fn cell_count(&self) -> u64 {
        u64::from(self.width) * u64::from(self.height)
    }

    /// Centre `(x_mm, y_mm)` of cell `(col, row)` (also for indices outside the grid).
    pub fn cell_center(&self, col: u32, row: u32) -> (f64, f64) {
        (
            self.origin_x_mm + (f64::from(col) + 0.5) * self.pixel_mm,
            self.origin_y_mm + (f64::from(row) + 0.5) * self.pixel_mm,
        )
    }

    /// The cell whose half-open square contains `(x_mm, y_mm)`, or `None` outside the grid or for
    /// non-finite input.
    pub fn cell_of(&self, x_mm: f64, y_mm: f64) -> Option<(u32, u32)> {
        let c = ((x_mm - self.origin_x_mm) / self.pixel_mm).floor();
        let r = ((y_mm - self.origin_y_mm) / self.pixel_mm).floor();
        // NaN fails both comparisons.
        let inside = |v: f64, n: u32| v >= 0.0 && v < f64::from(n);
        (inside(c, self.width) && inside(r, self.height)).then_some((c as u32, r as u32))
    }

    /// Extent of the grid along X (`width · pixel_mm`).
    pub fn width_mm(&self) -> f64 {
        f64::from(self.width) * self.pixel_mm
    }

    /// Extent of the grid along Y (`height · pixel_mm`).
    pub fn height_mm(&self) -> f64 {
        f64::from(self.height) * self.pixel_mm
    }
}

fn check_finite(field: &'static str, v: f64) -> Result<()> {
    if v.is_finite() { Ok(()) } else { Err(GeometryError::invalid(field, v, "a finite value")) }
}

/// A height map: f32 heights in millimetres on the grid described by [`HeightMapMeta`]
/// (see the module docs for the grid convention).
///
/// Invariant: the metadata is valid and `data.len() == width · height`.
/// `PartialEq` follows f32 semantics (a map with NaN cells is not equal to itself); use
/// [`HeightMap::bitwise_eq`] to compare bit for bit.
#[derive(Debug, Clone, PartialEq)]
pub struct HeightMap {
    meta: HeightMapMeta,
    data: Vec<f32>,
}

impl HeightMap {
    /// Builds a map from row-major `data` (row 0 at minimum Y), validating `meta` and the length.
    pub fn new(meta: HeightMapMeta, data: Vec<f32>) -> Result<Self> {
        meta.validate()?;
        if data.len() as u64 != meta.cell_count() {
            return Err(GeometryError::DataLength {
                width: meta.width,
                height: meta.height,
                expected: meta.cell_count(),
                len: data.len(),
            });
        }
        Ok(HeightMap { meta, data })
    }

    /// A map with every cell set to `z_mm` (NaN for an empty map).
    pub fn filled(meta: HeightMapMeta, z_mm: f32) -> Result<Self> {
        meta.validate()?;
        let n = usize::try_from(meta.cell_count())
            .map_err(|_| GeometryError::invalid("width*height", meta.cell_count(), "an addressable size"))?;
        Ok(HeightMap { meta, data: vec![z_mm; n] })
    }

    /// A map whose cell `(col, row)` holds `f(col, row)`; use [`HeightMapMeta::cell_center`] for
    /// the cell's XY.
    pub fn from_fn(meta: HeightMapMeta, mut f: impl FnMut(u32, u32) -> f32) -> Result<Self> {
        let mut map = HeightMap::filled(meta, f32::NAN)?;
        let w = meta.width as usize;
        for (i, z) in map.data.iter_mut().enumerate() {
            *z = f((i % w) as u32, (i / w) as u32);
        }
        Ok(map)
    }

    /// The grid, placement, Z range and view.
    pub fn meta(&self) -> &HeightMapMeta {
        &self.meta
    }
    pub fn width(&self) -> u32 {
        self.meta.width
    }
    pub fn height(&self) -> u32 {
        self.meta.height
    }
    pub fn pixel_mm(&self) -> f64 {
        self.meta.pixel_mm
    }
    pub fn origin_x_mm(&self) -> f64 {
        self.meta.origin_x_mm
    }
    pub fn origin_y_mm(&self) -> f64 {
        self.meta.origin_y_mm
    }
    pub fn z_min_mm(&self) -> f64 {
        self.meta.z_min_mm
    }
    pub fn z_max_mm(&self) -> f64 {
        self.meta.z_max_mm
    }
    pub fn face(&self) -> Face {
        self.meta.face
    }

    /// Sets the image-exchange Z range (finite, `z_min_mm < z_max_mm`).
    pub fn set_z_range(&mut self, z_min_mm: f64, z_max_mm: f64) -> Result<()> {
        let meta = HeightMapMeta { z_min_mm, z_max_mm, ..self.meta };
        meta.validate()?;
        self.meta = meta;
        Ok(())
    }

    /// Moves the grid so cell (0, 0)'s corner is at `(origin_x_mm, origin_y_mm)` (finite).
    pub fn set_origin(&mut self, origin_x_mm: f64, origin_y_mm: f64) -> Result<()> {
        let meta = HeightMapMeta { origin_x_mm, origin_y_mm, ..self.meta };
        meta.validate()?;
        self.meta = meta;
        Ok(())
    }

    /// Sets the view (an A angle must be finite).
    pub fn set_face(&mut self, face: Face) -> Result<()> {
        let meta = HeightMapMeta { face, ..self.meta };
        meta.validate()?;
        self.meta = meta;
        Ok(())
    }

    /// The part-frame point at the origin of the map's frame ([`HeightMapMeta::part_origin_mm`]).
    pub fn part_origin_mm(&self) -> [f64; 3] {
        self.meta.part_origin_mm
    }

    /// Sets [`HeightMapMeta::part_origin_mm`] (finite).
    pub fn set_part_origin(&mut self, part_origin_mm: [f64; 3]) -> Result<()> {
        let meta = HeightMapMeta { part_origin_mm, ..self.meta };
        meta.validate()?;
        self.meta = meta;
        Ok(())
    }

    /// Row-major heights, row 0 at minimum Y.
    pub fn data(&self) -> &[f32] {
        &self.data
    }

    /// Mutable row-major heights (the length cannot change).
    pub fn data_mut(&mut self) -> &mut [f32] {
        &mut self.data
    }

    /// The heights, consuming the map.
    pub fn into_data(self) -> Vec<f32> {
        self.data
    }

    /// One row (`width` cells), or `None` past the last row.
    pub fn row(&self, row: u32) -> Option<&[f32]> {
        let w = self.meta.width as usize;
        let start = (row as usize).checked_mul(w)?;
        self.data.get(start..start + w)
    }

    /// Index into [`HeightMap::data`] of cell `(col, row)`, or `None` outside the grid.
    pub fn index(&self, col: u32, row: u32) -> Option<usize> {
        (col < self.meta.width && row < self.meta.height)
            .then(|| row as usize * self.meta.width as usize + col as usize)
    }

    /// Height of cell `(col, row)` (possibly NaN), or `None` outside the grid.
    pub fn get(&self, col: u32, row: u32) -> Option<f32> {
        self.index(col, row).map(|i| self.data[i])
    }

    /// Sets the height of cell `(col, row)`.
    pub fn set(&mut self, col: u32, row: u32, z_mm: f32) -> Result<()> {
        let i = self.index(col, row).ok_or(GeometryError::OutOfBounds {
            col,
            row,
            width: self.meta.width,
            height: self.meta.height,
        })?;
        self.data[i] = z_mm;
        Ok(())
    }

    /// Centre `(x_mm, y_mm)` of cell `(col, row)`.
    pub fn cell_center(&self, col: u32, row: u32) -> (f64, f64) {
        self.meta.cell_center(col, row)
    }

    /// The cell containing `(x_mm, y_mm)`, or `None` outside the grid.
    pub fn cell_of(&self, x_mm: f64, y_mm: f64) -> Option<(u32, u32)> {
        self.meta.cell_of(x_mm, y_mm)
    }

    /// The height at `(x_mm, y_mm)` interpolated bilinearly between the four cell centres around
    /// it: exact on any plane. `None` where one of the four is outside the grid or holds no data,
    /// or where two neighbours among them differ by more than `max_slope` times the pixel (a wall
    /// between them, which interpolation would turn into a ramp).
    pub fn interpolated(&self, x_mm: f64, y_mm: f64, max_slope: f64) -> Option<f64> {
        let m = &self.meta;
        let u = (x_mm - m.origin_x_mm) / m.pixel_mm - 0.5;
        let v = (y_mm - m.origin_y_mm) / m.pixel_mm - 0.5;
        let (c0, r0) = (u.floor(), v.floor());
        // NaN fails the comparisons.
        if !(c0 >= 0.0 && r0 >= 0.0 && c0 + 1.0 < f64::from(m.width) && r0 + 1.0 < f64::from(m.height)) {
            return None;
        }
        let (c, r) = (c0 as u32, r0 as u32);
        let z = |dc: u32, dr: u32| self.get(c + dc, r + dr).map(f64::from).filter(|z| z.is_finite());
        let (z00, z10, z01, z11) = (z(0, 0)?, z(1, 0)?, z(0, 1)?, z(1, 1)?);
        let rise = max_slope * m.pixel_mm;
        if [z10 - z00, z11 - z01, z01 - z00, z11 - z10].iter().any(|d| d.abs() > rise) {
            return None;
        }
        let (s, t) = (u - c0, v - r0);
        Some((z00 * (1.0 - s) + z10 * s) * (1.0 - t) + (z01 * (1.0 - s) + z11 * s) * t)
    }

    /// Number of cells holding data (finite values).
    pub fn valid_count(&self) -> usize {
        self.data.iter().filter(|z| z.is_finite()).count()
    }

    /// `(min, max)` of the finite heights, or `None` if no cell holds data.
    pub fn z_range_of_data(&self) -> Option<(f32, f32)> {
        self.data.iter().filter(|z| z.is_finite()).fold(None, |acc, &z| match acc {
            None => Some((z, z)),
            Some((lo, hi)) => Some((lo.min(z), hi.max(z))),
        })
    }

    /// Same metadata and the same heights bit for bit (NaN payloads included).
    pub fn bitwise_eq(&self, other: &HeightMap) -> bool {
        self.meta == other.meta
            && self.data.len() == other.data.len()
            && self.data.iter().zip(&other.data).all(|(a, b)| a.to_bits() == b.to_bits())
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// A hemisphere of radius `r_mm` centred on the grid, on a base at z = 0; cells outside the
    /// sphere's footprint are NaN when `holes` is set.
    pub(crate) fn hemisphere(n: u32, pixel_mm: f64, r_mm: f64, holes: bool) -> HeightMap {
        let mut meta = HeightMapMeta::new(n, n, pixel_mm);
        meta.origin_x_mm = -f64::from(n) * pixel_mm / 2.0;
        meta.origin_y_mm = meta.origin_x_mm;
        meta.z_max_mm = r_mm;
        HeightMap::from_fn(meta, |c, r| {
            let (x, y) = meta.cell_center(c, r);
            let d2 = r_mm * r_mm - x * x - y * y;
            if d2 >= 0.0 {
                d2.sqrt() as f32
            } else if holes {
                f32::NAN
            } else {
                0.0
            }
        })
        .expect("valid hemisphere")
    }

    #[test]
    fn interpolation_is_exact_on_planes_and_refuses_walls_holes_and_the_border() {
        let mut meta = HeightMapMeta::new(30, 20, 0.25);
        meta.origin_x_mm = -3.0;
        meta.origin_y_mm = 1.0;
        let plane = |x: f64, y: f64| 0.7 * x - 0.4 * y + 2.0;
        let mut map = HeightMap::from_fn(meta, |c, r| {
            let (x, y) = meta.cell_center(c, r);
            plane(x, y) as f32
        })
        .expect("plane");
        let mut seed = 7u64;
        let mut next = || {
            seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            (seed >> 11) as f64 / (1u64 << 53) as f64
        };
        for _ in 0..500 {
            // Anywhere between the outer cells' centres.
            let x = -3.0 + 0.125 + next() * (7.5 - 0.25);
            let y = 1.0 + 0.125 + next() * (5.0 - 0.25);
            let z = map.interpolated(x, y, 1.0).expect("inside");
            assert!((z - plane(x, y)).abs() < 1e-5, "({x}, {y}): {z}");
        }
        // Outside the centres of the outer cells, or with a slope over the limit: none.
        assert!(map.interpolated(-3.0 + 0.1, 2.0, 1.0).is_none());
        assert!(map.interpolated(0.0, 2.0, 0.5).is_none());
        assert!(map.interpolated(f64::NAN, 2.0, 1.0).is_none());
        // A hole or a wall next to the point: none; farther away it does not matter.
        map.set(12, 4, f32::NAN).expect("cell");
        let (x, y) = map.cell_center(12, 4);
        assert!(map.interpolated(x + 0.1, y + 0.1, 1.0).is_none());
        assert!(map.interpolated(x + 0.3, y + 0.1, 1.0).is_some());
        map.set(20, 10, 9.0).expect("cell");
        let (x, y) = map.cell_center(20, 10);
        assert!(map.interpolated(x - 0.1, y - 0.1, 1.0).is_none());
        assert!(map.interpolated(x - 0.1, y - 0.1, 40.0).is_some());
    }

    #[test]
    fn hemisphere_grid_convention() {
        let map = hemisphere(40, 0.5, 8.0, true);
        assert_eq!(map.cell_center(0, 0), (-9.75, -9.75));
        assert_eq!(map.cell_of(-10.0, -10.0), Some((0, 0)));
        assert_eq!(map.cell_of(-9.5, -10.0), Some((1, 0)));
        assert_eq!(map.cell_of(10.0, 0.0), None);
        assert_eq!(map.cell_of(-10.0001, 0.0), None);
        assert_eq!(map.cell_of(f64::NAN, 0.0), None);
        assert_eq!(map.cell_of(0.1, 0.1), Some((20, 20)));
        // Peak: the four centre cells are at (±0.25, ±0.25).
        let (lo, hi) = map.z_range_of_data().expect("data");
        assert!((f64::from(hi) - (64.0f64 - 0.125).sqrt()).abs() < 1e-5, "{hi}");
        assert!(lo >= 0.0);
        // Footprint area ≈ π r² within a few cells.
        let area = map.valid_count() as f64 * 0.25;
        assert!((area - std::f64::consts::PI * 64.0).abs() < 5.0, "{area}");
        assert_eq!(map.get(0, 0).map(f32::is_nan), Some(true));
        assert_eq!(map.get(40, 0), None);
        assert_eq!(map.row(39).map(<[f32]>::len), Some(40));
        assert!(map.row(40).is_none());
        assert!(map.bitwise_eq(&map.clone()));
    }

    #[test]
    fn validation_names_field_and_value() {
        let ok = HeightMapMeta::new(4, 3, 0.1);
        let cases: Vec<(HeightMapMeta, &str)> = vec![
            (HeightMapMeta { width: 0, ..ok }, "invalid width 0"),
            (HeightMapMeta { pixel_mm: -1.0, ..ok }, "invalid pixel_mm -1"),
            (HeightMapMeta { pixel_mm: f64::NAN, ..ok }, "invalid pixel_mm NaN"),
            (HeightMapMeta { z_max_mm: 0.0, ..ok }, "invalid z_max_mm 0"),
            (HeightMapMeta { origin_y_mm: f64::INFINITY, ..ok }, "invalid origin_y_mm inf"),
            (HeightMapMeta { width: 1 << 16, height: 1 << 13, ..ok }, "more than 268435456 cells"),
        ];
        for (meta, msg) in cases {
            let e = HeightMap::filled(meta, 0.0).expect_err(msg).to_string();
            assert!(e.contains(msg), "{e} / {msg}");
        }
        let e = HeightMap::new(ok, vec![0.0; 11]).expect_err("length").to_string();
        assert_eq!(e, "height map data has 11 cells but 4x3 needs 12");
        let mut map = HeightMap::filled(ok, 1.0).expect("ok");
        assert!(map.set(4, 0, 1.0).is_err());
        map.set(3, 2, 7.0).expect("inside");
        assert_eq!(map.data()[11], 7.0);
        assert!(map.set_z_range(2.0, 2.0).is_err());
        assert_eq!(map.z_max_mm(), 1.0);
    }
}
