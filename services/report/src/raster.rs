//! Small raster toolkit for the report: an RGB image, PNG encoding, base64 `data:` URIs, colour
//! maps with their SVG legends, alpha-blended lines, and the [`View`] that places a rectangle of
//! the work plane (mm) on an image.

use std::fmt::Write as _;

use super::ReportError;
use super::html::esc;

/// An 8-bit RGB image, row-major, row 0 at the top.
#[derive(Debug, Clone, PartialEq)]
pub struct RgbImage {
    pub width: u32,
    pub height: u32,
    pub data: Vec<u8>,
}

impl RgbImage {
    /// A `width`×`height` image filled with `color`.
    pub fn new(width: u32, height: u32, color: [u8; 3]) -> Self {
        let n = width as usize * height as usize;
        let mut data = Vec::with_capacity(n * 3);
        for _ in 0..n {
            data.extend_from_slice(&color);
        }
        RgbImage { width, height, data }
    }

    /// The pixel at `(x, y)`, `None` outside.
    pub fn get(&self, x: u32, y: u32) -> Option<[u8; 3]> {
        if x >= self.width || y >= self.height {
            return None;
        }
        let i = (y as usize * self.width as usize + x as usize) * 3;
        self.data.get(i..i + 3).map(|p| [p[0], p[1], p[2]])
    }

    /// Blends `color` over the pixel at `(x, y)` with opacity `alpha` (0..=1); outside: nothing.
    pub fn blend(&mut self, x: i64, y: i64, color: [u8; 3], alpha: f32) {
        if x < 0 || y < 0 || x >= i64::from(self.width) || y >= i64::from(self.height) {
            return;
        }
        let i = (y as usize * self.width as usize + x as usize) * 3;
        if let Some(p) = self.data.get_mut(i..i + 3) {
            for k in 0..3 {
                let v = f32::from(p[k]) * (1.0 - alpha) + f32::from(color[k]) * alpha;
                p[k] = v.round().clamp(0.0, 255.0) as u8;
            }
        }
    }

    /// A line from `a` to `b` (pixel coordinates, pixel centres at `.5`), `width` 1 or more
    /// pixels, alpha-blended. The line is clipped to the image first, so far-away segments cost
    /// nothing.
    pub fn line(&mut self, a: [f64; 2], b: [f64; 2], color: [u8; 3], alpha: f32, width: u32) {
        let pad = f64::from(width) + 1.0;
        let Some((a, b)) = clip(a, b, -pad, -pad, f64::from(self.width) + pad, f64::from(self.height) + pad)
        else {
            return;
        };
        let (x0, y0) = (a[0].floor() as i64, a[1].floor() as i64);
        let (x1, y1) = (b[0].floor() as i64, b[1].floor() as i64);
        let (dx, dy) = ((x1 - x0).abs(), -(y1 - y0).abs());
        let (sx, sy) = (if x0 < x1 { 1 } else { -1 }, if y0 < y1 { 1 } else { -1 });
        let steep = -dy > dx;
        let (mut x, mut y, mut err) = (x0, y0, dx + dy);
        let w = i64::from(width.max(1));
        loop {
            for k in 0..w {
                let off = k - (w - 1) / 2;
                if steep {
                    self.blend(x + off, y, color, alpha)
                } else {
                    self.blend(x, y + off, color, alpha)
                }
            }
            if x == x1 && y == y1 {
                break;
            }
            let e2 = 2 * err;
            if e2 >= dy {
                err += dy;
                x += sx;
            }
            if e2 <= dx {
                err += dx;
                y += sy;
            }
        }
    }

    /// The image as PNG bytes (RGB, 8 bit).
    pub fn to_png(&self) -> Result<Vec<u8>, ReportError> {
        let mut out = Vec::new();
        {
            let mut enc = png::Encoder::new(&mut out, self.width, self.height);
            enc.set_color(png::ColorType::Rgb);
            enc.set_depth(png::BitDepth::Eight);
            enc.set_compression(png::Compression::Fast);
            let mut w = enc.write_header().map_err(ReportError::Png)?;
            w.write_image_data(&self.data).map_err(ReportError::Png)?;
            w.finish().map_err(ReportError::Png)?;
        }
        Ok(out)
    }
}

/// Liang–Barsky clipping of segment `a`-`b` to the box; `None` when it misses the box.
fn clip(a: [f64; 2], b: [f64; 2], x0: f64, y0: f64, x1: f64, y1: f64) -> Option<([f64; 2], [f64; 2])> {
    if !(a.iter().chain(b.iter()).all(|v| v.is_finite())) {
        return None;
    }
    let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
    let (mut t0, mut t1) = (0.0f64, 1.0f64);
    for (p, q) in [(-dx, a[0] - x0), (dx, x1 - a[0]), (-dy, a[1] - y0), (dy, y1 - a[1])] {
        if p == 0.0 {
            if q < 0.0 {
                return None;
            }
        } else {
            let r = q / p;
            if p < 0.0 {
                t0 = t0.max(r);
            } else {
                t1 = t1.min(r);
            }
            if t0 > t1 {
                return None;
            }
        }
    }
    Some(([a[0] + t0 * dx, a[1] + t0 * dy], [a[0] + t1 * dx, a[1] + t1 * dy]))
}

/// Standard base64 (RFC 4648, with padding).
pub fn base64(bytes: &[u8]) -> String {
    const T: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let mut out = String::with_capacity(bytes.len().div_ceil(3) * 4);
    for c in bytes.chunks(3) {
        let b = [c[0], c.get(1).copied().unwrap_or(0), c.get(2).copied().unwrap_or(0)];
        let n = (u32::from(b[0]) << 16) | (u32::from(b[1]) << 8) | u32::from(b[2]);
        for k in 0..4 {
            if k <= c.len() {
                out.push(T[((n >> (18 - 6 * k)) & 63) as usize] as char);
            } else {
                out.push('=');
            }
        }
    }
    out
}

/// `data:` URI of `bytes` with `media_type`.
pub fn data_uri(media_type: &str, bytes: &[u8]) -> String {
    format!("data:{media_type};base64,{}", base64(bytes))
}

/// A 256-entry colour lookup table built from evenly spaced stops.
#[derive(Debug, Clone)]
pub struct ColorMap {
    lut: Vec<[u8; 3]>,
    stops: &'static [[u8; 3]],
}

/// Perceptually uniform, colour-blind safe (matplotlib's viridis, 9 stops).
pub const VIRIDIS: &[[u8; 3]] = &[
    [68, 1, 84],
    [71, 44, 122],
    [59, 81, 139],
    [44, 113, 142],
    [33, 144, 141],
    [39, 173, 129],
    [92, 200, 99],
    [170, 220, 50],
    [253, 231, 37],
];

/// Diverging red (negative: gouge) – white – blue (positive: leftover), ColorBrewer RdBu.
pub const RED_WHITE_BLUE: &[[u8; 3]] = &[
    [178, 24, 43],
    [214, 96, 77],
    [244, 165, 130],
    [247, 247, 247],
    [146, 197, 222],
    [67, 147, 195],
    [33, 102, 172],
];

impl ColorMap {
    pub fn new(stops: &'static [[u8; 3]]) -> Self {
        let n = stops.len().max(2) - 1;
        let lut = (0..256)
            .map(|i| {
                let t = i as f64 / 255.0 * n as f64;
                let k = (t.floor() as usize).min(n.saturating_sub(1));
                let f = t - k as f64;
                let a = stops.get(k).copied().unwrap_or([0, 0, 0]);
                let b = stops.get(k + 1).copied().unwrap_or(a);
                [0, 1, 2].map(|c| (f64::from(a[c]) * (1.0 - f) + f64::from(b[c]) * f).round() as u8)
            })
            .collect();
        ColorMap { lut, stops }
    }

    /// Colour of `t` in `[0, 1]` (clamped; NaN gives the low end).
    pub fn at(&self, t: f64) -> [u8; 3] {
        let i = if t.is_finite() { (t.clamp(0.0, 1.0) * 255.0).round() as usize } else { 0 };
        self.lut.get(i).copied().unwrap_or([0, 0, 0])
    }

    /// An SVG colour bar from `lo` to `hi` with ticks and `unit`; `id` must be unique in the page.
    pub fn legend_svg(&self, id: &str, lo: f64, hi: f64, unit: &str, left: &str, right: &str) -> String {
        let (w, bar_h, x0, width) = (420.0, 14.0, 10.0, 400.0);
        let mut s = String::new();
        let _ = write!(
            s,
            r#"<svg class="legend" xmlns="http://www.w3.org/2000/svg" width="{w}" height="50" viewBox="0 0 {w} 50" font-family="sans-serif" font-size="11"><defs><linearGradient id="{id}">"#,
            id = esc(id)
        );
        let n = self.stops.len().max(2) - 1;
        for (k, c) in self.stops.iter().enumerate() {
            let _ = write!(
                s,
                r#"<stop offset="{:.4}" stop-color="rgb({},{},{})"/>"#,
                k as f64 / n as f64,
                c[0],
                c[1],
                c[2]
            );
        }
        let _ = write!(
            s,
            r##"</linearGradient></defs><rect x="{x0}" y="4" width="{width}" height="{bar_h}" fill="url(#{id})" stroke="#666"/>"##,
            id = esc(id)
        );
        if hi > lo && lo.is_finite() && hi.is_finite() {
            for t in crate::plot::nice_ticks(lo, hi, 6) {
                let x = x0 + (t - lo) / (hi - lo) * width;
                let _ = write!(
                    s,
                    r##"<line x1="{x:.1}" x2="{x:.1}" y1="{}" y2="{}" stroke="#333"/><text x="{x:.1}" y="32" text-anchor="middle">{}</text>"##,
                    4.0 + bar_h,
                    8.0 + bar_h,
                    fmt_num(t)
                );
            }
        }
        let _ = write!(
            s,
            r#"<text x="{x0}" y="46">{}</text><text x="{}" y="46" text-anchor="middle">{}</text><text x="{}" y="46" text-anchor="end">{}</text></svg>"#,
            esc(left),
            x0 + width / 2.0,
            esc(unit),
            x0 + width,
            esc(right)
        );
        s
    }
}

/// A number for labels: at most 3 decimals, no trailing zeros.
pub fn fmt_num(v: f64) -> String {
    if !v.is_finite() {
        return "–".into();
    }
    let s = if v.abs() >= 100.0 { format!("{v:.1}") } else { format!("{v:.3}") };
    let s = s.trim_end_matches('0').trim_end_matches('.');
    if s == "-0" { "0".into() } else { s.into() }
}

/// Where a rectangle of the work plane lands on an image: +X right, +Y up, `px_per_mm` pixels per
/// millimetre; image pixel `(u, v)` has its centre at `x = x_min + (u + ½)/s`, `y = y_max − (v + ½)/s`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct View {
    pub x_min_mm: f64,
    pub y_max_mm: f64,
    pub px_per_mm: f64,
    pub width: u32,
    pub height: u32,
}

/// Longest image side a report picture gets, pixels.
pub const MAX_SIDE_PX: f64 = 1000.0;
/// Shortest long side: small maps are enlarged to this many pixels.
pub const MIN_SIDE_PX: f64 = 480.0;

impl View {
    /// A view of `[x0, x1] × [y0, y1]` mm whose long side gets `side_px` pixels (clamped to
    /// [`MIN_SIDE_PX`], [`MAX_SIDE_PX`]).
    pub fn fit(x0: f64, y0: f64, x1: f64, y1: f64, side_px: f64) -> Option<View> {
        let (w_mm, h_mm) = (x1 - x0, y1 - y0);
        if !(w_mm.is_finite() && h_mm.is_finite() && w_mm > 0.0 && h_mm > 0.0) {
            return None;
        }
        let side = side_px.clamp(MIN_SIDE_PX, MAX_SIDE_PX);
        let s = side / w_mm.max(h_mm);
        let width = (w_mm * s).round().clamp(1.0, 4.0 * MAX_SIDE_PX) as u32;
        let height = (h_mm * s).round().clamp(1.0, 4.0 * MAX_SIDE_PX) as u32;
        Some(View { x_min_mm: x0, y_max_mm: y1, px_per_mm: s, width, height })
    }

    /// Work-plane point (mm) -> image coordinates (pixels, continuous).
    pub fn to_px(&self, x_mm: f64, y_mm: f64) -> [f64; 2] {
        [(x_mm - self.x_min_mm) * self.px_per_mm, (self.y_max_mm - y_mm) * self.px_per_mm]
    }

    /// Centre of image pixel `(u, v)` in the work plane, mm.
    pub fn center_mm(&self, u: u32, v: u32) -> (f64, f64) {
        (
            self.x_min_mm + (f64::from(u) + 0.5) / self.px_per_mm,
            self.y_max_mm - (f64::from(v) + 0.5) / self.px_per_mm,
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn base64_matches_rfc4648_vectors() {
        for (i, o) in [
            ("", ""),
            ("f", "Zg=="),
            ("fo", "Zm8="),
            ("foo", "Zm9v"),
            ("foob", "Zm9vYg=="),
            ("fooba", "Zm9vYmE="),
            ("foobar", "Zm9vYmFy"),
        ] {
            assert_eq!(base64(i.as_bytes()), o);
        }
    }

    #[test]
    fn clipped_lines_stay_inside_and_far_lines_cost_nothing() {
        let mut img = RgbImage::new(10, 10, [0, 0, 0]);
        img.line([-1e9, 5.5], [1e9, 5.5], [255, 0, 0], 1.0, 1);
        assert_eq!(img.get(0, 5), Some([255, 0, 0]));
        assert_eq!(img.get(9, 5), Some([255, 0, 0]));
        img.line([1e9, 1e9], [2e9, 2e9], [0, 255, 0], 1.0, 1);
        img.line([f64::NAN, 0.0], [1.0, 1.0], [0, 255, 0], 1.0, 1);
        assert!(img.data.chunks(3).all(|p| p[1] == 0));
    }
}
