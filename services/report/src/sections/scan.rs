//! The point cloud seen from above and from the front, and the scan's stations, frames, registration error and coverage.

use crate::*;

impl Ctx<'_> {
    pub(crate) fn point_cloud(&mut self) -> Result<String, ReportError> {
        let (digests, artifacts) = (self.digests, self.artifacts);
        let has = |k: &str| artifacts.contains_key(k) || digests.clouds.contains_key(k);
        let key = if has("point_cloud") || !has("mesh") { "point_cloud" } else { "mesh" };
        let read = match (digests.clouds.get(key), artifacts.get(key)) {
            (Some(sampled), _) => Some(Ok(std::borrow::Cow::Borrowed(sampled))),
            (None, Some(bytes)) => Some(cloud::read_cloud(bytes, key).map(std::borrow::Cow::Owned)),
            (None, None) => None,
        };
        let body = match read {
            None => missing(&self.why_missing(key)),
            Some(read) => match read {
                Err(e) => missing(&format!("Not shown: the {key} artifact could not be read: {e}.")),
                Ok(c) if c.cloud.is_empty() => missing(&format!("The {key} artifact holds no points.")),
                Ok(sampled) => {
                    let c = &sampled.cloud;
                    let (top, side) = cloud::views(c);
                    let sample = if (c.len() as u64) < sampled.points {
                        format!(", drawn from a uniform sample of {}", fmt_count(c.len()))
                    } else {
                        String::new()
                    };
                    let mut s = format!(
                        "<p>{} points{}{sample}.</p><div class=\"grid\">",
                        fmt_count(usize::try_from(sampled.points).unwrap_or(usize::MAX)),
                        if key == "mesh" { " (the mesh's vertices)" } else { "" }
                    );
                    for (v, name, title, axes, colour) in [
                        (top, "point_cloud_top.png", "Top view", ("X", "Y"), "Z (height)"),
                        (side, "point_cloud_side.png", "Front view", ("X", "Z"), "Y (nearer is brighter)"),
                    ] {
                        let Some(v) = v else { continue };
                        let caption = format!(
                            "{title}: {} {}–{} mm across, {} {}–{} mm up; colour = {colour}, {}–{} mm. {} of the points in view.",
                            axes.0,
                            fmt_num(v.h_range.0),
                            fmt_num(v.h_range.1),
                            axes.1,
                            fmt_num(v.v_range.0),
                            fmt_num(v.v_range.1),
                            fmt_num(v.c_range.0),
                            fmt_num(v.c_range.1),
                            fmt_count(v.drawn),
                        );
                        s.push_str(&self.picture(name, &v.image, title, &esc(&caption))?);
                    }
                    s.push_str("</div>");
                    s
                }
            },
        };
        let body = body + &self.scan_summary();
        Ok(section("point-cloud", "Point cloud", &body))
    }

    /// The scan's report (`scan_report`), when the job was scanned: stations, passes, frames,
    /// registration error, rays lost by reason, coverage before and after the rescan.
    pub(crate) fn scan_summary(&self) -> String {
        let Some(r) = self.artifacts.get("scan_report").and_then(|b| serde_json::from_slice::<Value>(b).ok())
        else {
            return String::new();
        };
        let f = |v: &Value, d: usize| v.as_f64().map_or("—".to_string(), |x| format!("{x:.d$}"));
        let calibration = |c: &Value| {
            if !c.is_object() {
                return if r["calibrated"] == Value::Bool(false) {
                    "none: the points were placed with the cell's drawing".to_string()
                } else {
                    "—".to_string()
                };
            }
            // A calibration the scan made has its version from the job (stored after the scan).
            let head = if c["made_for_this_scan"] == Value::Bool(true) {
                let version =
                    self.metric("scan_calibration_version").map_or("—".to_string(), |v| format!("{v:.0}"));
                match c["why_not_during_scan"].as_str() {
                    Some(why) => format!(
                        "version {version}, made for this scan by the routine before it ({})",
                        esc(why)
                    ),
                    None => format!("version {version}, made for this scan at its own stations"),
                }
            } else {
                format!("version {} ({})", c["version"], esc(c["id"].as_str().unwrap_or("?")))
            };
            let mut s = format!(
                "{head}: sphere fit RMS {} mm, table fit RMS {} mm",
                f(&c["sphere_rms_mm"], 4),
                f(&c["table_fit_rms_mm"], 4)
            );
            if c["registration_after"].is_object() {
                s.push_str(&format!(
                    "; merge error of its scans {} mm before, {} mm after",
                    f(&c["registration_before"]["merge_rms_mm"], 4),
                    f(&c["registration_after"]["merge_rms_mm"], 4)
                ));
            }
            if c["truth"].is_object() {
                s.push_str(&format!(
                    "; against the simulated cell's truth: table {} mm, scanner mount {} mm",
                    f(&c["truth"]["table_error_mm"], 4),
                    f(&c["truth"]["mount_error_mm"], 4)
                ));
            }
            s
        };
        let cov = |v: &Value| {
            if v.is_object() {
                format!(
                    "{} % ({} holes, {} mm²)",
                    f(&v["covered_pct"], 2),
                    v["holes"],
                    f(&v["hole_area_mm2"], 1)
                )
            } else {
                "—".to_string()
            }
        };
        let d = &r["dropped"];
        let rows: Vec<(String, String)> = vec![
            ("Mode".into(), esc(r["mode"].as_str().unwrap_or("?"))),
            ("Frames / points".into(), format!("{} / {}", r["frames"], r["points"])),
            (
                "Simulated scan time".into(),
                format!(
                    "{} s (the table's wall time {} s)",
                    f(&r["scan_time_s"], 1),
                    f(&r["table_wait_s"], 1)
                ),
            ),
            (
                "Registration error (placed vs true)".into(),
                format!(
                    "RMS {} mm, max {} mm",
                    f(&r["registration_rms_mm"], 4),
                    f(&r["registration_max_mm"], 4)
                ),
            ),
            (
                "Merge error (after the best rigid fit)".into(),
                if r["registration_merge_rms_mm"].is_number() {
                    format!("RMS {} mm", f(&r["registration_merge_rms_mm"], 4))
                } else {
                    "—".into()
                },
            ),
            ("Cell calibration".into(), calibration(&r["calibration"])),
            (
                "Rays without a point".into(),
                format!(
                    "{} out of the window, {} beyond the incidence limit, {} occluded, {} missing the part",
                    d["out_of_window"], d["incidence"], d["occluded"], d["miss"]
                ),
            ),
            ("Coverage after the first scan".into(), cov(&r["coverage_before_rescan"])),
            ("Coverage after the rescan".into(), cov(&r["coverage_after_rescan"])),
        ];
        let mut rows = rows;
        let sil = &r["silhouette"];
        if sil.is_object() {
            let regions: Vec<String> = sil["unseen_regions"]
                .as_array()
                .into_iter()
                .flatten()
                .take(3)
                .map(|g| {
                    format!(
                        "{} mm² at ({}, {})",
                        f(&g["area_mm2"], 1),
                        f(&g["center_x_mm"], 1),
                        f(&g["center_y_mm"], 1)
                    )
                })
                .collect();
            rows.push((
                "Part's silhouette seen (from its mesh)".into(),
                format!(
                    "{} %, {} mm² unseen{}",
                    f(&sil["covered_pct"], 2),
                    f(&sil["unseen_area_mm2"], 1),
                    if regions.is_empty() {
                        String::new()
                    } else {
                        format!("; largest: {}", regions.join(", "))
                    }
                ),
            ));
        }
        let u = &r["units"];
        if u.is_object() {
            rows.push((
                "Units of the mesh".into(),
                esc(&format!(
                    "{} ({}: {}){}",
                    u["unit"].as_str().unwrap_or("?"),
                    u["source"].as_str().unwrap_or("?"),
                    u["reason"].as_str().unwrap_or(""),
                    u["warning"].as_str().map(|w| format!("; {w}")).unwrap_or_default()
                )),
            ));
        }
        let stations: Vec<Vec<String>> = r["stations"]
            .as_array()
            .into_iter()
            .flatten()
            .map(|st| {
                let passes = st["passes"].as_array().cloned().unwrap_or_default();
                let frames: u64 = passes.iter().filter_map(|p| p["frames"].as_u64()).sum();
                let points: u64 = passes.iter().filter_map(|p| p["points"].as_u64()).sum();
                // Seed 002's posture criteria, the worst pass of the station.
                let worst = |get: &dyn Fn(&serde_json::Value) -> Option<f64>| {
                    passes.iter().filter_map(get).reduce(f64::min)
                };
                let quality = worst(&|p| p["quality"].as_f64());
                let dex = worst(&|p| p["min_dexterity"].as_f64());
                let wrist = worst(&|p| p["min_margins"]["wrist_deg"].as_f64());
                let elbow = worst(&|p| p["min_margins"]["elbow_deg"].as_f64());
                let shoulder = worst(&|p| p["min_margins"]["shoulder_mm"].as_f64());
                let opt = |v: Option<f64>, fmt: &dyn Fn(f64) -> String| v.map_or("—".to_string(), fmt);
                let mv = &st["table_move"];
                vec![
                    format!("{}°", f(&st["table_deg_commanded"], 1)),
                    format!("{}°", f(&st["table_deg_measured"], 4)),
                    if st["rescan"].as_bool() == Some(true) { "rescan".into() } else { "first scan".into() },
                    passes.len().to_string(),
                    frames.to_string(),
                    points.to_string(),
                    opt(st["table_offset_deg"].as_f64(), &|v| format!("{v:+.0}°")),
                    opt(quality, &|v| format!("{v:.2}")),
                    opt(dex, &|v| format!("{v:.2e}")),
                    match (wrist, elbow, shoulder) {
                        (Some(w), Some(e), Some(sh)) => format!("{w:.1}° / {e:.1}° / {sh:.0} mm"),
                        _ => "—".into(),
                    },
                    if mv.is_object() {
                        format!(
                            "{}° at up to {} °/s, {} s",
                            f(&mv["turn_deg"], 1),
                            f(&mv["peak_speed_deg_s"], 1),
                            f(&mv["time_s"], 2)
                        )
                    } else {
                        "—".into()
                    },
                ]
            })
            .collect();
        let mut s = String::from("<h3>Scan</h3>");
        s.push_str(&kv_table(&rows));
        if !stations.is_empty() {
            s.push_str(&table(
                &[
                    "table angle",
                    "encoder",
                    "kind",
                    "passes",
                    "frames",
                    "points",
                    "turned for the arm",
                    "worst posture",
                    "min dexterity",
                    "wrist / elbow / shoulder",
                    "table index",
                ],
                &stations,
            ));
        }
        s
    }
}
