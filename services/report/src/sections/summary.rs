//! Header, summary and parameters: who, what, how it went, and every setting of the job.

use crate::*;

impl Ctx<'_> {
    pub(crate) fn header(&self) -> String {
        let status = self.str_at("status").unwrap_or("unknown");
        let mut s = format!(
            r#"<header><h1>{}</h1><div class="sub">Job <code>{}</code> · <span class="status {}">{}</span>"#,
            esc(&self.name()),
            esc(self.str_at("id").unwrap_or("?")),
            esc(status),
            esc(status)
        );
        if let Some(st) = self.str_at("stage") {
            let _ = write!(s, " · stage {}", esc(st));
        }
        if let Some(p) = self.job["progress"].as_f64() {
            let _ = write!(s, " · {:.0} % done", (p * 100.0).clamp(0.0, 100.0));
        }
        for (k, label) in [("created_at_ms", "created"), ("updated_at_ms", "updated")] {
            if let Some(ms) = self.job[k].as_i64() {
                let _ = write!(s, " · {label} {}", esc(&utc(ms)));
            }
        }
        s.push_str("</div>");
        if let Some(e) = self.job.get("error").filter(|e| e.is_object()) {
            let _ = write!(
                s,
                r#"<p class="error"><strong>Error in the {} stage</strong> ({}): {}</p>"#,
                esc(e["stage"].as_str().unwrap_or("?")),
                esc(e["code"].as_str().unwrap_or("?")),
                esc(e["message"].as_str().unwrap_or(""))
            );
        }
        s.push_str("</header>");
        s
    }

    pub(crate) fn summary(&self) -> String {
        let mr = self.machine_report.as_ref();
        let mr_f = |path: &[&str]| {
            let mut v = mr?;
            for p in path {
                v = v.get(p)?;
            }
            v.as_f64().filter(|x| x.is_finite())
        };
        let mm = |v: Option<f64>| v.map_or("—".to_string(), |v| format!("{v:.3} mm"));
        let secs = |v: Option<f64>| v.map_or("—".to_string(), fmt_duration);
        let adaptive = self.metric("cycle_time_s").or_else(|| mr_f(&["cycle_time_s"]));
        let plain = self.metric("cycle_time_no_adaptive_s").or_else(|| mr_f(&["cycle_time_no_adaptive_s"]));
        let saving = match (adaptive, plain) {
            (Some(a), Some(p)) if p > 0.0 => format!("{:.1} %", (p - a) / p * 100.0),
            _ => "—".into(),
        };
        let rows = vec![
            (
                "Scan coverage".to_string(),
                self.metric("coverage_pct")
                    .map_or("—".into(), |v| format!("{v:.1} % of the part measured")),
            ),
            ("Max gouge (cut too deep)".into(), mm(self.metric("max_gouge_mm"))),
            ("Max leftover (material left)".into(), mm(self.metric("max_leftover_mm"))),
            ("Mean leftover".into(), mm(mr_f(&["deviation", "mean_leftover_mm"]))),
            ("RMS deviation".into(), mm(self.metric("rms_deviation_mm"))),
            ("Cycle time, adaptive".into(), secs(adaptive)),
            ("Cycle time, programmed feeds".into(), secs(plain)),
            ("Saved by the adaptive loop".into(), saving),
            (
                "CAM time estimate".into(),
                secs(
                    self.plan_report
                        .as_ref()
                        .and_then(|p| p["estimated_time_s"].as_f64())
                        .or_else(|| self.job["metrics"]["estimated_time_s"].as_f64()),
                ),
            ),
        ];
        let rows: Vec<(String, String)> = rows.into_iter().map(|(k, v)| (k, esc(&v))).collect();
        section("summary", "Summary", &kv_table(&rows))
    }

    /// What the stages' services said (the job's `diagnostics`): first what could not be done or
    /// is only assumed, with where, then the rest (choices and their reasons) folded. Nothing when
    /// the job has none.
    pub(crate) fn findings(&self) -> String {
        let Some(all) = self.job["diagnostics"].as_array().filter(|d| !d.is_empty()) else {
            return String::new();
        };
        let row = |d: &Value| {
            vec![
                esc(d["stage"].as_str().unwrap_or("?")),
                format!("<code>{}</code>", esc(d["code"].as_str().unwrap_or("?"))),
                esc(d["message"].as_str().unwrap_or("")),
            ]
        };
        let (attention, notes): (Vec<&Value>, Vec<&Value>) =
            all.iter().partition(|d| d["code"].as_str().is_some_and(needs_attention));
        let mut body = String::new();
        if attention.is_empty() {
            body.push_str("<p>No stage reported material it could not reach, surface it did not see or a run warning.</p>");
        } else {
            let _ = write!(
                body,
                r#"<p class="missing">{} finding(s) where the part will not be what the model shows: material the tools cannot reach, surface no orientation or scan saw, or warnings of the run.</p>"#,
                attention.len()
            );
            let rows: Vec<Vec<String>> = attention.iter().map(|d| row(d)).collect();
            body.push_str(&table(&["stage", "code", "what and where"], &rows));
        }
        if !notes.is_empty() {
            let rows: Vec<Vec<String>> = notes.iter().map(|d| row(d)).collect();
            let _ = write!(
                body,
                "<details><summary>{} further note(s) of the stages (choices and their reasons)</summary>",
                notes.len()
            );
            body.push_str(&table(&["stage", "code", "message"], &rows));
            body.push_str("</details>");
        }
        section("findings", "What the stages found", &body)
    }

    pub(crate) fn parameters(&self) -> String {
        let mut body = String::new();
        let spec = &self.job["spec"];
        if let Some(obj) = spec.as_object() {
            body.push_str(r#"<div class="grid">"#);
            let order = ["input", "scan", "reconstruct", "plan", "execute"];
            let mut keys: Vec<&String> = obj.keys().filter(|k| k.as_str() != "name").collect();
            keys.sort_by_key(|k| order.iter().position(|o| o == k).unwrap_or(order.len()));
            for k in keys {
                let mut rows = Vec::new();
                flatten("", &obj[k.as_str()], &mut rows);
                if rows.is_empty() {
                    rows.push(("(all defaults)".into(), String::new()));
                }
                let rows: Vec<(String, String)> =
                    rows.into_iter().map(|(a, b)| (a, format!("<code>{}</code>", esc(&b)))).collect();
                let _ = write!(body, "<div><h3>{}</h3>{}</div>", esc(k), kv_table(&rows));
            }
            body.push_str("</div>");
            let pretty = serde_json::to_string_pretty(spec).unwrap_or_default();
            let _ = write!(
                body,
                "<details><summary>Job request as JSON</summary><pre>{}</pre></details>",
                esc(&pretty)
            );
        } else {
            body.push_str(&missing("The job has no spec."));
        }
        // Stage timings.
        body.push_str("<h3>Time per stage</h3>");
        let timings = self.job["stage_timings_s"].as_object();
        let mut rows: Vec<(String, f64, &str)> = Vec::new();
        if let Some(t) = timings {
            let mut ks: Vec<&String> = t.keys().collect();
            ks.sort_by_key(|k| stage_index(k).unwrap_or(STAGES.len()));
            for k in ks {
                if let Some(v) = t[k.as_str()].as_f64() {
                    rows.push((k.clone(), v, "#4c78a8"));
                }
            }
        }
        if rows.is_empty() {
            body.push_str(&missing("No stage has finished yet, so there are no timings."));
        } else {
            let total: f64 = rows.iter().map(|r| r.1).sum();
            body.push_str(&figure_svg(
                &charts::hbars(&rows, "s"),
                &format!("Wall time of each completed stage; total {}.", esc(&fmt_duration(total))),
            ));
        }
        // Attempts.
        if let Some(att) = self.job["attempts"].as_array().filter(|a| !a.is_empty()) {
            let rows: Vec<Vec<String>> = att
                .iter()
                .map(|a| {
                    let dur = match (a["started_at_ms"].as_i64(), a["finished_at_ms"].as_i64()) {
                        (Some(s), Some(f)) => fmt_duration((f - s) as f64 / 1000.0),
                        _ => "—".into(),
                    };
                    vec![
                        esc(a["stage"].as_str().unwrap_or("?")),
                        esc(&a["attempt"].as_u64().map_or("?".into(), |n| n.to_string())),
                        esc(a["outcome"].as_str().unwrap_or("?")),
                        esc(&dur),
                        esc(&format!(
                            "{} {}",
                            a["error_code"].as_str().unwrap_or(""),
                            a["error_message"].as_str().unwrap_or("")
                        )),
                    ]
                })
                .collect();
            body.push_str("<details><summary>Stage attempts</summary>");
            body.push_str(&table(&["stage", "attempt", "outcome", "took", "error"], &rows));
            body.push_str("</details>");
        }
        // Artifacts.
        if let Some(arts) = self.job["artifacts"].as_object().filter(|a| !a.is_empty()) {
            let rows: Vec<Vec<String>> = arts
                .iter()
                .map(|(k, a)| {
                    let sha = a["sha256"].as_str().unwrap_or("?");
                    vec![
                        format!("<code>{}</code>", esc(k)),
                        esc(a["media_type"].as_str().unwrap_or("?")),
                        format!(
                            r#"<span class="num">{}</span>"#,
                            esc(&a["size"].as_u64().map_or("?".into(), fmt_bytes))
                        ),
                        format!("<code>{}</code>", esc(sha.get(..16).unwrap_or(sha))),
                    ]
                })
                .collect();
            body.push_str("<details><summary>Artifacts</summary>");
            body.push_str(&table(&["kind", "media type", "size", "sha256"], &rows));
            body.push_str("</details>");
        }
        section("parameters", "Job parameters and timings", &body)
    }
}

/// Diagnostic codes that say the part will differ from the model (as opposed to notes on what was
/// chosen): material left, surface not reached or not seen, a unit guess, a run warning.
fn needs_attention(code: &str) -> bool {
    matches!(
        code,
        "material_left"
            | "unreachable_surface"
            | "face_mostly_assumed"
            | "unseen_filled"
            | "units_warning"
            | "non_finite_points"
            | "silhouette_unseen"
            | "machine"
            | "rapid_cut"
            | "blocked"
            | "unreachable"
            | "out_of_reach"
            | "too_narrow"
            | "open_chains"
            | "layer_defects"
            | "mesh_not_closed"
            | "diagnostics_truncated"
    ) || code.ends_with("_warning")
}
