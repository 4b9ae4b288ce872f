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

/// Telemetry columns the report reads (the machine service's CSV header names).
pub struct Telemetry {
    pub time_s: Vec<f64>,
    pub feed: Vec<f64>,
    pub rpm: Vec<f64>,
    pub torque_adc: Vec<f64>,
    pub torque_current: Vec<f64>,
    pub torque_true: Vec<f64>,
    pub power: Vec<f64>,
    pub rows: usize,
    /// Rows per active-limit name (`torque`, `power`, ... from the `active` column).
    pub active: Vec<(String, usize)>,
}

/// Parses the machine's telemetry CSV (header line, comma-separated; columns found by name, any
/// of them may be missing). `Err` when there is no `time_s` column.
pub fn parse_telemetry(text: &str) -> Result<Telemetry, String> {
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().ok_or("empty file")?.split(',').map(str::trim).collect();
    let col = |name: &str| header.iter().position(|h| *h == name);
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
    let mut t = Telemetry {
        time_s: Vec::new(),
        feed: Vec::new(),
        rpm: Vec::new(),
        torque_adc: Vec::new(),
        torque_current: Vec::new(),
        torque_true: Vec::new(),
        power: Vec::new(),
        rows: 0,
        active: Vec::new(),
    };
    for line in lines {
        if line.trim().is_empty() {
            continue;
        }
        let f: Vec<&str> = line.split(',').collect();
        let num = |c: Option<usize>| c.and_then(|c| f.get(c)).and_then(|v| v.trim().parse::<f64>().ok());
        let Some(time) = num(Some(t_col)) else { continue };
        t.rows += 1;
        t.time_s.push(time);
        let vals = cols.map(num);
        for (dst, v) in [
            &mut t.feed,
            &mut t.rpm,
            &mut t.torque_adc,
            &mut t.torque_current,
            &mut t.torque_true,
            &mut t.power,
        ]
        .into_iter()
        .zip(vals)
        {
            dst.push(v.unwrap_or(f64::NAN));
        }
        if let Some(a) = active_col.and_then(|c| f.get(c)) {
            for name in a.split('|').map(str::trim).filter(|s| !s.is_empty()) {
                match t.active.iter_mut().find(|(n, _)| n == name) {
                    Some(e) => e.1 += 1,
                    None => t.active.push((name.to_string(), 1)),
                }
            }
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
