//! Small SVG line charts for reports: stacked panels sharing one X axis (e.g. feed, speed,
//! torque and power over time), with "nice" tick values, a title and units per panel.
//!
//! Long series are reduced for drawing to at most `2 × width` points by keeping, per horizontal
//! pixel column, the minimum and maximum (so spikes stay visible), never by dropping samples
//! blindly.

use std::fmt::Write as _;

/// One line of a panel.
#[derive(Debug, Clone)]
pub struct Series {
    pub label: String,
    /// CSS colour.
    pub color: String,
    /// `(x, y)` samples, x ascending. Non-finite values break the line.
    pub points: Vec<(f64, f64)>,
}

/// One panel: a Y axis with its title and unit.
#[derive(Debug, Clone)]
pub struct Panel {
    pub title: String,
    pub unit: String,
    pub series: Vec<Series>,
}

/// A chart: panels stacked vertically over one X axis.
#[derive(Debug, Clone)]
pub struct Chart {
    pub title: String,
    pub x_label: String,
    pub panels: Vec<Panel>,
    pub width: u32,
    pub panel_height: u32,
}

/// Tick values covering `[lo, hi]` at a 1/2/5 × 10^k step, about `n` of them.
pub fn nice_ticks(lo: f64, hi: f64, n: usize) -> Vec<f64> {
    if !(lo.is_finite() && hi.is_finite()) || hi <= lo || n == 0 {
        return vec![lo];
    }
    let raw = (hi - lo) / n as f64;
    let exp = raw.log10().floor() as i32;
    let mag = 10f64.powi(exp);
    let mult = [1.0, 2.0, 5.0, 10.0].into_iter().find(|m| m * mag >= raw).unwrap_or(10.0);
    let step = mult * mag;
    // k·mult scaled by an exact power of ten, so 3 × 0.2 prints as 0.6.
    let value = |k: f64| if exp < 0 { k * mult / 10f64.powi(-exp) } else { k * mult * mag };
    let mut k = (lo / step).ceil();
    let mut out = Vec::new();
    while value(k) <= hi + step * 1e-9 && out.len() < 100 {
        let v = value(k);
        out.push(if v.abs() < step * 1e-9 { 0.0 } else { v });
        k += 1.0;
    }
    out
}

fn fmt_tick(v: f64) -> String {
    let s = format!("{v:.4}");
    let s = s.trim_end_matches('0').trim_end_matches('.');
    if s == "-0" { "0".to_string() } else { s.to_string() }
}

fn escape(s: &str) -> String {
    s.replace('&', "&amp;").replace('<', "&lt;").replace('>', "&gt;").replace('"', "&quot;")
}

/// Min/max per pixel column, in x order.
fn reduce(points: &[(f64, f64)], x0: f64, x1: f64, columns: usize) -> Vec<(f64, f64)> {
    if points.len() <= 2 * columns || columns == 0 || x1 <= x0 {
        return points.to_vec();
    }
    let mut out = Vec::with_capacity(2 * columns + 2);
    let mut i = 0;
    while i < points.len() {
        let col = (((points[i].0 - x0) / (x1 - x0)) * columns as f64).floor();
        let mut j = i;
        let (mut lo, mut hi) = (i, i);
        while j < points.len() && (((points[j].0 - x0) / (x1 - x0)) * columns as f64).floor() == col {
            if points[j].1 < points[lo].1 {
                lo = j;
            }
            if points[j].1 > points[hi].1 {
                hi = j;
            }
            j += 1;
        }
        let (a, b) = if lo <= hi { (lo, hi) } else { (hi, lo) };
        out.push(points[a]);
        if b != a {
            out.push(points[b]);
        }
        i = j;
    }
    out
}

impl Chart {
    /// The chart as a standalone SVG document.
    pub fn to_svg(&self) -> String {
        let (left, right, top, gap, bottom) = (70.0, 20.0, 36.0, 28.0, 40.0);
        let w = f64::from(self.width.max(200));
        let ph = f64::from(self.panel_height.max(60));
        let n = self.panels.len().max(1) as f64;
        let h = top + n * ph + (n - 1.0) * gap + bottom;
        let all_x =
            self.panels.iter().flat_map(|p| p.series.iter().flat_map(|s| s.points.iter().map(|q| q.0)));
        let (x0, x1) = all_x
            .filter(|x| x.is_finite())
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), x| (a.min(x), b.max(x)));
        let (x0, x1) = if x0.is_finite() && x1 > x0 { (x0, x1) } else { (0.0, 1.0) };
        let plot_w = w - left - right;
        let sx = |x: f64| left + (x - x0) / (x1 - x0) * plot_w;
        let mut svg = String::new();
        let _ = write!(
            svg,
            r#"<svg xmlns="http://www.w3.org/2000/svg" width="{w}" height="{h}" viewBox="0 0 {w} {h}" font-family="sans-serif" font-size="11">"#
        );
        let _ = write!(svg, r#"<rect width="{w}" height="{h}" fill="white"/>"#);
        let _ = write!(
            svg,
            r#"<text x="{}" y="20" font-size="14" font-weight="bold">{}</text>"#,
            left,
            escape(&self.title)
        );
        for (k, panel) in self.panels.iter().enumerate() {
            let py = top + k as f64 * (ph + gap);
            let ys = panel.series.iter().flat_map(|s| s.points.iter().map(|q| q.1)).filter(|y| y.is_finite());
            let (mut y0, mut y1) =
                ys.fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), y| (a.min(y), b.max(y)));
            if !y0.is_finite() {
                (y0, y1) = (0.0, 1.0);
            }
            if y1 - y0 < 1e-12 {
                (y0, y1) = (y0 - 0.5 * y0.abs().max(1.0), y1 + 0.5 * y1.abs().max(1.0));
            }
            let pad = (y1 - y0) * 0.05;
            let (y0, y1) = (y0 - pad, y1 + pad);
            let sy = |y: f64| py + ph - (y - y0) / (y1 - y0) * ph;
            let _ = write!(
                svg,
                r##"<rect x="{left}" y="{py}" width="{plot_w}" height="{ph}" fill="#fafafa" stroke="#999"/>"##
            );
            for t in nice_ticks(y0, y1, 4) {
                let y = sy(t);
                let _ = write!(
                    svg,
                    r##"<line x1="{left}" x2="{}" y1="{y:.1}" y2="{y:.1}" stroke="#e0e0e0"/><text x="{}" y="{:.1}" text-anchor="end">{}</text>"##,
                    left + plot_w,
                    left - 4.0,
                    y + 4.0,
                    fmt_tick(t)
                );
            }
            let _ = write!(
                svg,
                r#"<text x="{}" y="{}" font-weight="bold">{} [{}]</text>"#,
                left + 4.0,
                py - 4.0,
                escape(&panel.title),
                escape(&panel.unit)
            );
            let mut legend_x = left + plot_w;
            for s in panel.series.iter().rev() {
                legend_x -= 8.0 + 7.0 * s.label.len() as f64;
                let _ = write!(
                    svg,
                    r#"<text x="{legend_x:.1}" y="{}" fill="{}">{}</text>"#,
                    py - 4.0,
                    escape(&s.color),
                    escape(&s.label)
                );
            }
            for s in &panel.series {
                let pts = reduce(&s.points, x0, x1, plot_w as usize);
                let mut d = String::new();
                let mut pen_down = false;
                for (x, y) in pts {
                    if !(x.is_finite() && y.is_finite()) {
                        pen_down = false;
                        continue;
                    }
                    let _ = write!(d, "{}{:.1},{:.1} ", if pen_down { "L" } else { "M" }, sx(x), sy(y));
                    pen_down = true;
                }
                let _ = write!(
                    svg,
                    r#"<path d="{}" fill="none" stroke="{}" stroke-width="1.2"/>"#,
                    d.trim_end(),
                    escape(&s.color)
                );
            }
        }
        let base = top + n * ph + (n - 1.0) * gap;
        for t in nice_ticks(x0, x1, 8) {
            let x = sx(t);
            let _ = write!(
                svg,
                r##"<line x1="{x:.1}" x2="{x:.1}" y1="{base}" y2="{}" stroke="#999"/><text x="{x:.1}" y="{}" text-anchor="middle">{}</text>"##,
                base + 4.0,
                base + 16.0,
                fmt_tick(t)
            );
        }
        let _ = write!(
            svg,
            r#"<text x="{}" y="{}" text-anchor="middle">{}</text></svg>"#,
            left + plot_w / 2.0,
            base + 32.0,
            escape(&self.x_label)
        );
        svg
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ticks_are_round_numbers_covering_the_range() {
        assert_eq!(nice_ticks(0.0, 10.0, 5), vec![0.0, 2.0, 4.0, 6.0, 8.0, 10.0]);
        assert_eq!(nice_ticks(0.13, 0.91, 4), vec![0.2, 0.4, 0.6, 0.8]);
        assert_eq!(nice_ticks(-3.0, 3.0, 3), vec![-2.0, 0.0, 2.0]);
        assert_eq!(nice_ticks(1.0, 1.0, 3), vec![1.0]);
        assert_eq!(fmt_tick(0.30000000000000004), "0.3");
    }

    #[test]
    fn reduction_keeps_extremes_per_column() {
        let pts: Vec<(f64, f64)> =
            (0..10_000).map(|i| (f64::from(i), if i == 5_000 { 100.0 } else { 0.0 })).collect();
        let r = reduce(&pts, 0.0, 9_999.0, 100);
        assert!(r.len() <= 200 && r.len() >= 100, "{}", r.len());
        assert!(r.iter().any(|p| p.1 == 100.0), "the spike survives");
        assert!(r.windows(2).all(|w| w[0].0 <= w[1].0), "x order kept");
    }

    #[test]
    fn svg_has_every_panel_and_escapes_text() {
        let chart = Chart {
            title: "feed & speed".into(),
            x_label: "time [s]".into(),
            width: 600,
            panel_height: 100,
            panels: vec![
                Panel {
                    title: "feed".into(),
                    unit: "mm/min".into(),
                    series: vec![Series {
                        label: "aco".into(),
                        color: "#c00".into(),
                        points: vec![(0.0, 100.0), (1.0, f64::NAN), (2.0, 300.0)],
                    }],
                },
                Panel { title: "empty".into(), unit: "-".into(), series: vec![] },
            ],
        };
        let svg = chart.to_svg();
        assert!(svg.starts_with("<svg") && svg.ends_with("</svg>"));
        assert!(svg.contains("feed &amp; speed"));
        assert!(svg.contains("feed [mm/min]") && svg.contains("empty [-]"));
        assert_eq!(svg.matches("<path").count(), 1);
        assert!(svg.contains("M") && !svg.contains("NaN"));
    }
}
