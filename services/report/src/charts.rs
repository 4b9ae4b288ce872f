//! Small inline SVG charts: horizontal bars (stage timings, cycle times) and the telemetry chart
//! rebuilt from the machine's CSV with `crate::plot`.

use std::fmt::Write as _;

use crate::plot::{Chart, Panel, Series};

use super::html::esc;
use super::raster::fmt_num;

/// Horizontal bars: one per `(label, value, colour)`, values in `unit`, longest bar full width.
pub fn hbars(rows: &[(String, f64, &str)], unit: &str) -> String {
    let (label_w, bar_w, row_h) = (150.0, 520.0, 26.0);
    let w = label_w + bar_w + 110.0;
    let h = row_h * rows.len().max(1) as f64 + 8.0;
    let max = rows.iter().map(|r| r.1).filter(|v| v.is_finite()).fold(0.0f64, f64::max);
    let mut s = String::new();
    let _ = write!(
        s,
        r#"<svg class="chart" xmlns="http://www.w3.org/2000/svg" width="{w}" height="{h}" viewBox="0 0 {w} {h}" font-family="sans-serif" font-size="12">"#
    );
    for (k, (label, v, color)) in rows.iter().enumerate() {
        let y = 4.0 + k as f64 * row_h;
        let len = if max > 0.0 && v.is_finite() { (v / max * bar_w).max(1.0) } else { 0.0 };
        let _ = write!(
            s,
            r##"<text x="{}" y="{:.1}" text-anchor="end">{}</text><rect x="{label_w}" y="{:.1}" width="{len:.1}" height="{:.1}" fill="{}" rx="2"/><text x="{:.1}" y="{:.1}">{} {}</text>"##,
            label_w - 8.0,
            y + row_h * 0.62,
            esc(label),
            y + 3.0,
            row_h - 8.0,
            esc(color),
            label_w + len + 6.0,
            y + row_h * 0.62,
            fmt_num(*v),
            esc(unit)
        );
    }
    s.push_str("</svg>");
    s
}

/// Telemetry columns the report reads (the machine service's CSV header names): a uniform sample
/// of the rows for drawing (every row up to [`TELEMETRY_SAMPLE`], then every 2^k-th), and the
/// statistics of every row.
#[derive(Debug, Clone, Default)]
pub struct Telemetry {
    pub time_s: Vec<f64>,
    pub feed: Vec<f64>,
    pub rpm: Vec<f64>,
    pub torque_adc: Vec<f64>,
    pub torque_current: Vec<f64>,
    pub torque_true: Vec<f64>,
    pub power: Vec<f64>,
    /// Rows read (all of them, not only the sample).
    pub rows: usize,
    /// Rows per active-limit name (`torque`, `power`, ... from the `active` column).
    pub active: Vec<(String, usize)>,
    /// Time of the first and the last row read.
    pub time_span: Option<(f64, f64)>,
    /// Over every row: feed, spindle speed, torque from current, power.
    pub feed_stat: ColumnStat,
    pub rpm_stat: ColumnStat,
    pub torque_current_stat: ColumnStat,
    pub power_stat: ColumnStat,
}

impl Telemetry {
    /// The drawn series, time first, in one order for every row.
    fn series_mut(&mut self) -> [&mut Vec<f64>; 7] {
        [
            &mut self.time_s,
            &mut self.feed,
            &mut self.rpm,
            &mut self.torque_adc,
            &mut self.torque_current,
            &mut self.torque_true,
            &mut self.power,
        ]
    }
}

/// Mean and maximum of a column's finite values.
#[derive(Debug, Clone, Copy, Default)]
pub struct ColumnStat {
    sum: f64,
    n: u64,
    max: Option<f64>,
}

impl ColumnStat {
    fn add(&mut self, v: f64) {
        if v.is_finite() {
            self.sum += v;
            self.n += 1;
            self.max = Some(self.max.map_or(v, |m| m.max(v)));
        }
    }

    /// NaN when the column had no finite value.
    pub fn mean(&self) -> f64 {
        if self.n == 0 { f64::NAN } else { self.sum / self.n as f64 }
    }

    /// NaN when the column had no finite value.
    pub fn max(&self) -> f64 {
        self.max.unwrap_or(f64::NAN)
    }
}

/// Rows of telemetry drawn at most (the chart has a few hundred pixels across; the statistics
/// use every row).
pub const TELEMETRY_SAMPLE: usize = 1 << 18;

/// Parses the machine's telemetry CSV (header line, comma-separated; columns found by name, any
/// of them may be missing). `Err` when there is no `time_s` column.
pub fn parse_telemetry(text: &str) -> Result<Telemetry, String> {
    read_telemetry(text.as_bytes(), TELEMETRY_SAMPLE)
}

/// [`parse_telemetry`] reading `r` line by line, keeping at most `keep` rows of the series (a
/// uniform sample) whatever the file's length; the statistics cover every row.
pub fn read_telemetry<R: std::io::BufRead>(mut r: R, keep: usize) -> Result<Telemetry, String> {
    let keep = keep.max(2);
    let mut line = String::new();
    let read = |r: &mut R, line: &mut String| -> Result<usize, String> {
        line.clear();
        // A line longer than any telemetry row is cut; its rest reads as further lines.
        std::io::BufRead::read_line(&mut std::io::Read::take(&mut *r, 1 << 16), line)
            .map_err(|e| format!("reading failed: {e}"))
    };
    if read(&mut r, &mut line)? == 0 {
        return Err("empty file".into());
    }
    let header: Vec<String> = line.trim_end().split(',').map(|h| h.trim().to_string()).collect();
    let col = |name: &str| header.iter().position(|h| h == name);
    let t_col = col("time_s").ok_or("no time_s column in the header")?;
    let cols = [
        col("feed_mm_min"),
        col("spindle_rpm"),
        col("torque_adc_nm"),
        col("torque_from_current_nm"),
        col("torque_true_nm"),
        col("power_w"),
    ];
    let active_col = col("active");
    let mut t = Telemetry::default();
    let mut stride_mask = 0usize;
    while read(&mut r, &mut line)? > 0 {
        let text = line.trim_end();
        if text.trim().is_empty() {
            continue;
        }
        let f: Vec<&str> = text.split(',').collect();
        let num = |c: Option<usize>| c.and_then(|c| f.get(c)).and_then(|v| v.trim().parse::<f64>().ok());
        let Some(time) = num(Some(t_col)) else { continue };
        let index = t.rows;
        t.rows += 1;
        t.time_span = Some(t.time_span.map_or((time, time), |(a, _)| (a, time)));
        let vals = cols.map(|c| num(c).unwrap_or(f64::NAN));
        t.feed_stat.add(vals[0]);
        t.rpm_stat.add(vals[1]);
        t.torque_current_stat.add(vals[3]);
        t.power_stat.add(vals[5]);
        if let Some(a) = active_col.and_then(|c| f.get(c)) {
            for name in a.split('|').map(str::trim).filter(|s| !s.is_empty()) {
                match t.active.iter_mut().find(|(n, _)| n == name) {
                    Some(e) => e.1 += 1,
                    None => t.active.push((name.to_string(), 1)),
                }
            }
        }
        if index & stride_mask != 0 {
            continue;
        }
        for (dst, v) in t.series_mut().into_iter().zip(std::iter::once(time).chain(vals)) {
            dst.push(v);
        }
        if t.time_s.len() >= keep {
            // Every other kept row goes: the sample is every 2^(k+1)-th row from now on.
            for v in t.series_mut() {
                let mut i = 0;
                v.retain(|_| {
                    i += 1;
                    i % 2 == 1
                });
            }
            stride_mask = stride_mask * 2 + 1;
        }
    }
    Ok(t)
}

/// The same chart the machine service draws (feed, speed, torque, power over time).
pub fn telemetry_chart(t: &Telemetry) -> Chart {
    let series = |label: &str, color: &str, ys: &[f64]| Series {
        label: label.into(),
        color: color.into(),
        points: t.time_s.iter().copied().zip(ys.iter().copied()).collect(),
    };
    let has = |ys: &[f64]| ys.iter().any(|v| v.is_finite());
    let mut torque = Vec::new();
    for (label, color, ys) in [
        ("ADC (0.139 N·m/count)", "#bbbbbb", &t.torque_adc),
        ("from current", "#d62728", &t.torque_current),
        ("model", "#000000", &t.torque_true),
    ] {
        if has(ys) {
            torque.push(series(label, color, ys));
        }
    }
    Chart {
        title: "Spindle and feed over time (from the telemetry CSV)".into(),
        x_label: "time [s]".into(),
        width: 900,
        panel_height: 120,
        panels: vec![
            Panel {
                title: "feed".into(),
                unit: "mm/min".into(),
                series: vec![series("feed", "#1f77b4", &t.feed)],
            },
            Panel {
                title: "spindle speed".into(),
                unit: "rpm".into(),
                series: vec![series("speed", "#2ca02c", &t.rpm)],
            },
            Panel { title: "torque".into(), unit: "N·m".into(), series: torque },
            Panel {
                title: "cutting power".into(),
                unit: "W".into(),
                series: vec![series("power", "#ff7f0e", &t.power)],
            },
        ],
    }
}
