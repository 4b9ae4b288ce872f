//! Height-map pictures: decoding the stored maps (16/8-bit PNG with depthmill metadata, `.npy`),
//! and drawing them: colour by height with a legend in mm, grey hill-shade (the base under the
//! toolpaths), Lambert-lit machined stock, coverage classes, signed deviation.

use std::io::Cursor;

use depthmill_geometry::{HeightMap, ImageMapping, npy::NPY_MAGIC};
use rayon::prelude::*;

use super::raster::{ColorMap, RgbImage, View};

const PNG_MAGIC: &[u8; 8] = b"\x89PNG\r\n\x1a\n";

/// Colour of cells without data.
pub const NO_DATA: [u8; 3] = [236, 238, 242];

/// A decoded map and a remark about how it was read (e.g. an assumed pixel size).
pub struct Decoded {
    pub map: HeightMap,
    pub note: Option<String>,
}

/// Decodes a stored height map (PNG with depthmill metadata, or `.npy`), sniffing the format from
/// the bytes. `fallback` supplies a pixel size and Z range a bare image lacks; without one, 1 mm
/// pixels are assumed and said so in the note.
pub fn decode_map(bytes: &[u8], fallback: Option<&ImageMapping>) -> Result<Decoded, String> {
    let read = |fb: Option<&ImageMapping>| -> Result<HeightMap, String> {
        if bytes.starts_with(PNG_MAGIC) {
            depthmill_geometry::read_png_from(Cursor::new(bytes), fb).map_err(|e| e.to_string())
        } else if bytes.starts_with(NPY_MAGIC) {
            depthmill_geometry::read_npy_from(bytes, None, fb).map_err(|e| e.to_string())
        } else {
            Err("neither a PNG nor a .npy file".into())
        }
    };
    match read(fallback) {
        Ok(map) => Ok(Decoded { map, note: None }),
        Err(first) => {
            let assumed = ImageMapping {
                pixel_mm: fallback.map_or(1.0, |f| f.pixel_mm),
                z_min_mm: fallback.and_then(|f| f.z_min_mm),
                z_max_mm: fallback.and_then(|f| f.z_max_mm),
            };
            match read(Some(&ImageMapping::pixel_only(1.0))).or_else(|_| read(Some(&assumed))) {
                Ok(map) => Ok(Decoded {
                    map,
                    note: Some(format!("the file lacks part of its metadata ({first}); 1 mm pixels assumed")),
                }),
                Err(_) => Err(first),
            }
        }
    }
}

/// The view of a map's whole extent.
pub fn map_view(map: &HeightMap) -> Option<View> {
    let m = map.meta();
    View::fit(
        m.origin_x_mm,
        m.origin_y_mm,
        m.origin_x_mm + m.width_mm(),
        m.origin_y_mm + m.height_mm(),
        f64::from(m.width.max(m.height)),
    )
}

/// The map's value at a work-plane point (nearest cell), `None` outside or without data.
fn sample(map: &HeightMap, x: f64, y: f64) -> Option<f32> {
    map.cell_of(x, y).and_then(|(c, r)| map.get(c, r)).filter(|z| z.is_finite())
}

/// Lambert shade in `[0, 1]` of cell `(c, r)`, light from the north-west at 45°; `z_scale`
/// exaggerates heights. NaN neighbours count as the centre value.
fn lambert(map: &HeightMap, c: u32, r: u32, z_scale: f64) -> f64 {
    let z = |c: i64, r: i64| -> Option<f64> {
        if c < 0 || r < 0 {
            return None;
        }
        map.get(c as u32, r as u32).filter(|v| v.is_finite()).map(f64::from)
    };
    let (ci, ri) = (i64::from(c), i64::from(r));
    let Some(z0) = z(ci, ri) else { return 1.0 };
    let p = map.pixel_mm();
    let dzdx = (z(ci + 1, ri).unwrap_or(z0) - z(ci - 1, ri).unwrap_or(z0)) / (2.0 * p) * z_scale;
    let dzdy = (z(ci, ri + 1).unwrap_or(z0) - z(ci, ri - 1).unwrap_or(z0)) / (2.0 * p) * z_scale;
    // Normal (-dz/dx, -dz/dy, 1); light from azimuth 315° (north-west, +Y up), altitude 45°.
    let (lx, ly, lz) = (-0.5f64, 0.5f64, std::f64::consts::FRAC_1_SQRT_2);
    let n = (dzdx * dzdx + dzdy * dzdy + 1.0).sqrt();
    ((-dzdx * lx - dzdy * ly + lz) / n).clamp(0.0, 1.0)
}

/// Paints `view` in parallel rows: `f(x_mm, y_mm)` gives each pixel's colour.
pub fn paint(view: &View, f: impl Fn(f64, f64) -> [u8; 3] + Sync) -> RgbImage {
    let mut img = RgbImage::new(view.width, view.height, [255, 255, 255]);
    let w = view.width as usize;
    img.data.par_chunks_mut(w * 3).enumerate().for_each(|(v, row)| {
        for (u, px) in row.chunks_mut(3).enumerate() {
            let (x, y) = view.center_mm(u as u32, v as u32);
            px.copy_from_slice(&f(x, y));
        }
    });
    img
}

/// Robust Z range of a map's data: the 0.5 and 99.5 percentiles of up to 200 000 sampled cells.
pub fn robust_range(map: &HeightMap) -> Option<(f64, f64)> {
    let d = map.data();
    let step = (d.len() / 200_000).max(1);
    let mut v: Vec<f32> = d.iter().step_by(step).copied().filter(|z| z.is_finite()).collect();
    if v.is_empty() {
        return None;
    }
    v.sort_unstable_by(f32::total_cmp);
    let q = |f: f64| f64::from(v[((v.len() - 1) as f64 * f).round() as usize]);
    let (lo, hi) = (q(0.005), q(0.995));
    Some(if hi > lo { (lo, hi) } else { (lo - 0.5, lo + 0.5) })
}

/// Depth map coloured by height over `[lo, hi]` mm (viridis), lightly hill-shaded.
pub fn depth_image(map: &HeightMap, view: &View, lo: f64, hi: f64) -> RgbImage {
    let cmap = ColorMap::new(super::raster::VIRIDIS);
    paint(view, |x, y| match map.cell_of(x, y) {
        Some((c, r)) => match map.get(c, r).filter(|z| z.is_finite()) {
            Some(z) => {
                let base = cmap.at((f64::from(z) - lo) / (hi - lo));
                let s = 0.72 + 0.28 * lambert(map, c, r, 1.0) / std::f64::consts::FRAC_1_SQRT_2;
                base.map(|v| (f64::from(v) * s.min(1.15)).round().clamp(0.0, 255.0) as u8)
            }
            None => NO_DATA,
        },
        None => [255, 255, 255],
    })
}

/// Grey hill-shade of a map with a faint height tint: the background for toolpaths.
pub fn grey_image(map: &HeightMap, view: &View, lo: f64, hi: f64) -> RgbImage {
    paint(view, |x, y| match map.cell_of(x, y) {
        Some((c, r)) => match map.get(c, r).filter(|z| z.is_finite()) {
            Some(z) => {
                let t = ((f64::from(z) - lo) / (hi - lo)).clamp(0.0, 1.0);
                let s = lambert(map, c, r, 2.0);
                let g = 150.0 + 60.0 * t + 45.0 * s;
                let g = g.clamp(0.0, 255.0) as u8;
                [g, g, g]
            }
            None => NO_DATA,
        },
        None => [250, 250, 250],
    })
}

/// Machined stock as a lit solid: Lambert shading (light from the north-west, 45° up) of an
/// aluminium grey, slightly warmer the higher the surface.
pub fn shaded_image(map: &HeightMap, view: &View, lo: f64, hi: f64) -> RgbImage {
    paint(view, |x, y| match map.cell_of(x, y) {
        Some((c, r)) => match map.get(c, r).filter(|z| z.is_finite()) {
            Some(z) => {
                let t = ((f64::from(z) - lo) / (hi - lo)).clamp(0.0, 1.0);
                let s = lambert(map, c, r, 1.0);
                let light = 0.18 + 0.95 * s;
                let base = [150.0 + 40.0 * t, 160.0 + 30.0 * t, 178.0 + 10.0 * t];
                base.map(|v| (v * light + 10.0).clamp(0.0, 255.0) as u8)
            }
            None => NO_DATA,
        },
        None => [255, 255, 255],
    })
}

/// Coverage classes (what the reconstruction writes: 1 measured, 0.5 filled, 0 hole, no data =
/// outside the footprint; 8-bit PNG reads back 0.502 for filled).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CoverageClass {
    Measured,
    Filled,
    Assumed,
    Hole,
    Outside,
}

impl CoverageClass {
    pub fn of(v: f32) -> Self {
        if !v.is_finite() {
            CoverageClass::Outside
        } else if v > 0.75 {
            CoverageClass::Measured
        } else if v > 0.375 {
            CoverageClass::Filled
        } else if v > 0.125 {
            // 0.25 (an 8-bit map reads 64/255).
            CoverageClass::Assumed
        } else {
            CoverageClass::Hole
        }
    }

    pub fn color(self) -> [u8; 3] {
        match self {
            CoverageClass::Measured => [44, 160, 44],
            CoverageClass::Filled => [255, 191, 0],
            CoverageClass::Assumed => [148, 103, 189],
            CoverageClass::Hole => [214, 39, 40],
            CoverageClass::Outside => [226, 229, 235],
        }
    }

    pub fn label(self) -> &'static str {
        match self {
            CoverageClass::Measured => "measured",
            CoverageClass::Filled => "filled",
            CoverageClass::Assumed => "assumed (never seen)",
            CoverageClass::Hole => "hole (not filled)",
            CoverageClass::Outside => "outside the part",
        }
    }
}

/// Cell counts per coverage class: measured, filled, assumed, hole, outside.
pub fn coverage_counts(map: &HeightMap) -> [usize; 5] {
    map.data()
        .par_iter()
        .fold(
            || [0usize; 5],
            |mut a, &v| {
                a[CoverageClass::of(v) as usize] += 1;
                a
            },
        )
        .reduce(|| [0; 5], |a, b| std::array::from_fn(|k| a[k] + b[k]))
}

/// The coverage map in its class colours.
pub fn coverage_image(map: &HeightMap, view: &View) -> RgbImage {
    paint(view, |x, y| match map.cell_of(x, y).and_then(|(c, r)| map.get(c, r)) {
        Some(v) => CoverageClass::of(v).color(),
        None => [255, 255, 255],
    })
}

/// Symmetric colour range of a deviation map: the 99.5th percentile of |d| (at least 0.005 mm),
/// so one outlier does not wash the picture out. Also the data's min and max.
pub fn deviation_range(map: &HeightMap) -> Option<(f64, f64, f64)> {
    let d = map.data();
    let step = (d.len() / 200_000).max(1);
    let mut v: Vec<f32> = d.iter().step_by(step).copied().filter(|z| z.is_finite()).map(f32::abs).collect();
    if v.is_empty() {
        return None;
    }
    v.sort_unstable_by(f32::total_cmp);
    let p = f64::from(v[((v.len() - 1) as f64 * 0.995).round() as usize]).max(0.005);
    let (lo, hi) = map.z_range_of_data().map_or((0.0, 0.0), |(a, b)| (f64::from(a), f64::from(b)));
    Some((p, lo, hi))
}

/// Signed deviation (stock − target) on a red (gouge) – white – blue (leftover) scale over
/// `[-range, range]` mm.
pub fn deviation_image(map: &HeightMap, view: &View, range: f64) -> RgbImage {
    let cmap = ColorMap::new(super::raster::RED_WHITE_BLUE);
    paint(view, |x, y| match map.cell_of(x, y) {
        Some(_) => match sample(map, x, y) {
            Some(d) => cmap.at((f64::from(d) + range) / (2.0 * range)),
            None => NO_DATA,
        },
        None => [255, 255, 255],
    })
}
