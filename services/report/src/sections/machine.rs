//! Telemetry of the adaptive loop and the cycle time with and without it.

use crate::*;

impl Ctx<'_> {
    pub(crate) fn telemetry(&mut self) -> String {
        let mut body = String::new();
        let plot = self.artifacts.get("telemetry_plot").filter(|b| {
            let head = String::from_utf8_lossy(&b[..b.len().min(512)]).to_ascii_lowercase();
            head.contains("<svg")
        });
        let csv = match self.digests.telemetry.as_ref() {
            Some(t) => Some(Ok(t.clone())),
            None => {
                self.artifacts.get("telemetry").map(|b| charts::parse_telemetry(&String::from_utf8_lossy(b)))
            }
        };
        let svg: Option<(Vec<u8>, &str)> = match (plot, &csv) {
            (Some(p), _) => Some((p.clone(), "the machine service's telemetry plot")),
            (None, Some(Ok(t))) if t.rows > 0 => {
                Some((charts::telemetry_chart(t).to_svg().into_bytes(), "drawn from the telemetry CSV"))
            }
            _ => None,
        };
        match svg {
            Some((bytes, source)) => {
                let _ = write!(
                    body,
                    r#"<figure><img src="{}" alt="feed, speed, torque and power over time"><figcaption>Feed, spindle speed, torque and cutting power over the run under the adaptive loop ({}).</figcaption></figure>"#,
                    esc(&data_uri("image/svg+xml", &bytes)),
                    esc(source)
                );
                self.files.push(("telemetry.svg".into(), bytes));
            }
            None => {
                let why = match &csv {
                    Some(Err(e)) => format!("Not shown: the telemetry CSV could not be read: {e}."),
                    Some(Ok(_)) => "Not shown: the telemetry CSV has no rows.".into(),
                    None => self.why_missing("telemetry"),
                };
                body.push_str(&missing(&why));
            }
        }
        if let Some(Ok(t)) = &csv
            && t.rows > 0
        {
            let dur = t.time_span.map_or(0.0, |(a, b)| b - a);
            let mut rows = vec![
                ("Samples".to_string(), format!("{} over {}", fmt_count(t.rows), fmt_duration(dur))),
                (
                    "Feed, mean / max".into(),
                    format!("{} / {} mm/min", fmt_num(t.feed_stat.mean()), fmt_num(t.feed_stat.max())),
                ),
                (
                    "Spindle, mean / max".into(),
                    format!("{} / {} rpm", fmt_num(t.rpm_stat.mean()), fmt_num(t.rpm_stat.max())),
                ),
                ("Torque from current, max".into(), format!("{} N·m", fmt_num(t.torque_current_stat.max()))),
                ("Cutting power, max".into(), format!("{} W", fmt_num(t.power_stat.max()))),
            ];
            for (name, n) in &t.active {
                rows.push((
                    format!("Limit '{name}' active"),
                    format!("{:.1} % of samples", *n as f64 / t.rows as f64 * 100.0),
                ));
            }
            let rows: Vec<(String, String)> = rows.into_iter().map(|(k, v)| (k, esc(&v))).collect();
            body.push_str(&kv_table(&rows));
        }
        section("telemetry", "Feed, speed, torque and power", &body)
    }

    pub(crate) fn cycle_time(&mut self) -> String {
        let mr = self.machine_report.as_ref();
        let mr_f = |k: &str| mr.and_then(|m| m[k].as_f64()).filter(|v| v.is_finite());
        let adaptive = self.metric("cycle_time_s").or_else(|| mr_f("cycle_time_s"));
        let plain = self.metric("cycle_time_no_adaptive_s").or_else(|| mr_f("cycle_time_no_adaptive_s"));
        let policy = mr
            .and_then(|m| m["run"]["policy"].as_str())
            .or_else(|| self.job["spec"]["execute"]["adaptive"].as_str())
            .unwrap_or("adaptive");
        let body = match (adaptive, plain) {
            (Some(a), Some(p)) => {
                let mut rows = vec![
                    ("programmed feeds".to_string(), p, "#9aa5b5"),
                    (format!("with the loop ({policy})"), a, "#2ca02c"),
                ];
                if let (Some(o), Some(name)) =
                    (mr_f("cycle_time_other_s"), mr.and_then(|m| m["other_policy"].as_str()))
                {
                    rows.push((format!("other policy ({name})"), o, "#7fb0d8"));
                }
                let svg = charts::hbars(&rows, "s");
                self.files.push(("cycle_time.svg".into(), svg.clone().into_bytes()));
                let saving = if p > 0.0 { (p - a) / p * 100.0 } else { 0.0 };
                let verdict = if saving >= 0.0 {
                    format!("The adaptive loop saved {} ({saving:.1} %).", fmt_duration(p - a))
                } else {
                    format!("The adaptive loop took {} longer ({:.1} %).", fmt_duration(a - p), -saving)
                };
                figure_svg(
                    &svg,
                    &esc(&format!(
                        "Simulated cycle time of the program with its programmed feeds and speeds and under the adaptive loop. {verdict}"
                    )),
                )
            }
            (Some(a), None) => missing(&format!(
                "Cycle time {} with the loop; the run without adaptation was not measured.",
                fmt_duration(a)
            )),
            _ => missing(&self.why_missing("machine_report")),
        };
        section("cycle-time", "Cycle time with and without the adaptive loop", &body)
    }
}
