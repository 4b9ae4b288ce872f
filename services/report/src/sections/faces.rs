//! Depth and coverage maps, one pair per face, with their statistics.

use crate::*;

impl Ctx<'_> {
    /// Suffixes of the faces (`""`, `"@1"`, ...) by the depth/coverage maps present.
    pub(crate) fn face_suffixes(&self) -> Vec<String> {
        let mut n: Vec<u32> = Vec::new();
        let keys =
            self.artifacts.keys().chain(self.job["artifacts"].as_object().into_iter().flat_map(|o| o.keys()));
        for k in keys {
            for base in ["depth_map", "coverage_map"] {
                if let Some(rest) = k.strip_prefix(base) {
                    if rest.is_empty() {
                        n.push(0);
                    } else if let Some(i) = rest.strip_prefix('@').and_then(|i| i.parse().ok()) {
                        n.push(i);
                    }
                }
            }
        }
        n.push(0);
        n.sort_unstable();
        n.dedup();
        n.into_iter().map(|i| if i == 0 { String::new() } else { format!("@{i}") }).collect()
    }

    /// The reconstruction's face choice, when the job asked for one: what each chosen face adds
    /// and where no orientation reaches.
    pub(crate) fn face_choice(&self) -> String {
        let rep = ["reconstruct_report", "reconstruction_report"]
            .iter()
            .find_map(|k| self.artifacts.get(*k))
            .and_then(|b| serde_json::from_slice::<Value>(b).ok());
        let Some(fc) = rep.as_ref().map(|r| &r["face_choice"]).filter(|c| c.is_object()) else {
            return String::new();
        };
        let f = |v: &Value| v.as_f64().map_or("—".into(), |x| format!("{x:.1} %"));
        let rows: Vec<Vec<String>> = fc["chosen"]
            .as_array()
            .into_iter()
            .flatten()
            .enumerate()
            .map(|(i, c)| {
                vec![
                    format!("{}", i + 1),
                    esc(c["face"].as_str().unwrap_or("?")),
                    f(&c["gain_pct"]),
                    f(&c["cumulative_pct"]),
                ]
            })
            .collect();
        let mut body = String::from(
            "<h3>Faces chosen from the shape</h3><p>The fewest turns of the part about the A axis from which \
             a tool of the reach radius gets at the surface; each face adds what the ones before it leave.</p>",
        );
        body.push_str(&table(&["Face", "Orientation", "Adds", "Reached so far"], &rows));
        let settings = &fc["settings"];
        let kv = vec![
            ("Reached by the chosen faces".to_string(), f(&fc["covered_pct"])),
            (
                "Reachable but left (each other face adds too little)".to_string(),
                f(&fc["left_reachable_pct"]),
            ),
            ("Reached from no orientation".to_string(), f(&fc["unreached_pct"])),
            (
                "Candidates, reach radius".to_string(),
                esc(&format!(
                    "every {} deg about A, {} mm",
                    settings["step_deg"].as_f64().unwrap_or(0.0),
                    settings["reach_radius_mm"].as_f64().unwrap_or(0.0)
                )),
            ),
        ];
        body.push_str(&kv_table(&kv));
        let regions: Vec<Vec<String>> = fc["unreached_regions"]
            .as_array()
            .into_iter()
            .flatten()
            .map(|r| {
                let v = |k: &str| -> Vec<f64> {
                    r[k].as_array().into_iter().flatten().filter_map(Value::as_f64).collect()
                };
                let (c, sz) = (v("center_mm"), v("size_mm"));
                let three = |a: &[f64]| a.iter().map(|x| format!("{x:.1}")).collect::<Vec<_>>().join(", ");
                vec![
                    esc(&format!("({})", three(&c))),
                    esc(&three(&sz).replace(", ", " x ")),
                    fmt_num(r["area_mm2"].as_f64().unwrap_or(0.0)),
                ]
            })
            .collect();
        if !regions.is_empty() {
            body.push_str(
                "<p>Surface no orientation reaches (undercuts, pockets narrower than the tool, \
                 faces along the A axis): it is left as the faces' cuts leave it.</p>",
            );
            body.push_str(&table(&["Centre, mm", "Size, mm", "Area, mm²"], &regions));
        }
        body
    }

    /// The reconstruction's warnings about faces whose maps are more assumed than measured.
    pub(crate) fn face_warnings(&self) -> String {
        let rep = ["reconstruct_report", "reconstruction_report"]
            .iter()
            .find_map(|k| self.artifacts.get(*k))
            .and_then(|b| serde_json::from_slice::<Value>(b).ok());
        let warnings: Vec<String> = rep
            .as_ref()
            .and_then(|r| r["faces"].as_array())
            .into_iter()
            .flatten()
            .filter_map(|f| f["warning"].as_str())
            .map(|w| format!(r#"<p class="missing">{}</p>"#, esc(w)))
            .collect();
        warnings.concat()
    }

    pub(crate) fn maps(&mut self) -> Result<String, ReportError> {
        let mut body = self.face_choice();
        body.push_str(&self.face_warnings());
        let faces = self.face_suffixes();
        for (fi, suffix) in faces.iter().enumerate() {
            let dkey = format!("depth_map{suffix}");
            let ckey = format!("coverage_map{suffix}");
            let label = format!("Face {}", fi + 1);
            let mut s = String::from(r#"<div class="grid">"#);
            let mut face_name = String::new();
            match self.decode(&dkey) {
                Err(e) => s.push_str(&format!("<div>{}</div>", missing(&e))),
                Ok(d) => {
                    face_name = format!(" ({})", d.map.face());
                    s.push_str(&self.depth_figure(&d, &dkey, &label)?);
                    self.depth_maps.insert(dkey.clone(), d.map);
                }
            }
            match self.decode(&ckey) {
                Err(e) => s.push_str(&format!("<div>{}</div>", missing(&e))),
                Ok(d) => s.push_str(&self.coverage_figure(&d.map, &ckey, &label, fi)?),
            }
            s.push_str("</div>");
            if faces.len() > 1 {
                let _ = write!(body, "<h3>{}{}</h3>", esc(&label), esc(&face_name));
            }
            body.push_str(&s);
        }
        Ok(section("depth-map", "Depth map and scan coverage", &body))
    }

    pub(crate) fn depth_figure(
        &mut self,
        d: &maps::Decoded,
        key: &str,
        label: &str,
    ) -> Result<String, ReportError> {
        let map = &d.map;
        let Some(view) = maps::map_view(map) else {
            return Ok(missing(&format!("The {key} has an empty extent.")));
        };
        let Some((lo, hi)) = maps::robust_range(map) else {
            return Ok(missing(&format!("The {key} has no cell with data.")));
        };
        let img = maps::depth_image(map, &view, lo, hi);
        let m = map.meta();
        let legend = ColorMap::new(raster::VIRIDIS).legend_svg(
            &format!("lg-{}", key.replace('@', "-")),
            lo,
            hi,
            "height Z [mm]",
            "low",
            "high",
        );
        let caption = format!(
            "{label} depth map, {}×{} cells of {} mm = {}×{} mm, origin ({}, {}) mm, view {}; {} of {} cells hold data; image Z range {}–{} mm.{}",
            m.width,
            m.height,
            fmt_num(m.pixel_mm),
            fmt_num(m.width_mm()),
            fmt_num(m.height_mm()),
            fmt_num(m.origin_x_mm),
            fmt_num(m.origin_y_mm),
            m.face,
            fmt_count(map.valid_count()),
            fmt_count(map.data().len()),
            fmt_num(m.z_min_mm),
            fmt_num(m.z_max_mm),
            d.note.as_ref().map(|n| format!(" Note: {n}.")).unwrap_or_default()
        );
        let fig =
            self.picture(&file_name(key, "png"), &img, &format!("{label} depth map"), &esc(&caption))?;
        Ok(format!(
            "<div>{fig}{}</div>",
            figure_svg(&legend, "Colour scale (0.5–99.5 % of the heights); grey: no data.")
        ))
    }

    pub(crate) fn coverage_figure(
        &mut self,
        map: &HeightMap,
        key: &str,
        label: &str,
        face: usize,
    ) -> Result<String, ReportError> {
        let Some(view) = maps::map_view(map) else {
            return Ok(missing(&format!("The {key} has an empty extent.")));
        };
        let img = maps::coverage_image(map, &view);
        let counts = maps::coverage_counts(map);
        let footprint = counts[0] + counts[1] + counts[2] + counts[3];
        let pct = |n: usize| if footprint > 0 { n as f64 / footprint as f64 * 100.0 } else { 0.0 };
        let area = |n: usize| n as f64 * map.pixel_mm() * map.pixel_mm();
        let mut legend = String::from("<p>");
        for (k, c) in [
            maps::CoverageClass::Measured,
            maps::CoverageClass::Filled,
            maps::CoverageClass::Assumed,
            maps::CoverageClass::Hole,
            maps::CoverageClass::Outside,
        ]
        .into_iter()
        .enumerate()
        {
            let col = c.color();
            let share = if k < 4 { format!(" {:.1} %", pct(counts[k])) } else { String::new() };
            let _ = write!(
                legend,
                r#"<span class="swatch" style="background:rgb({},{},{})"></span>{}{}"#,
                col[0],
                col[1],
                col[2],
                esc(c.label()),
                esc(&share)
            );
        }
        legend.push_str("</p>");
        let mut rows = vec![
            (
                "Footprint".to_string(),
                format!("{} cells, {} mm²", fmt_count(footprint), fmt_num(area(footprint))),
            ),
            ("Measured".into(), format!("{} cells ({:.1} %)", fmt_count(counts[0]), pct(counts[0]))),
            (
                "Filled from neighbours".into(),
                format!("{} cells ({:.1} %)", fmt_count(counts[1]), pct(counts[1])),
            ),
            (
                "Assumed, never seen (a height from around them)".into(),
                format!("{} cells ({:.1} %)", fmt_count(counts[2]), pct(counts[2])),
            ),
            (
                "Holes left".into(),
                format!("{} cells, {} mm²", fmt_count(counts[3]), fmt_num(area(counts[3]))),
            ),
        ];
        if face == 0
            && let Some(c) = self.metric("coverage_pct")
        {
            rows.push(("Coverage (job metric)".into(), format!("{c:.2} %")));
        }
        // The reconstruction's own report, when the job stored it.
        let rep = ["reconstruct_report", "reconstruction_report"]
            .iter()
            .find_map(|k| self.artifacts.get(*k))
            .and_then(|b| serde_json::from_slice::<Value>(b).ok());
        if let Some(cov) = rep.as_ref().map(|r| &r["faces"][face]["coverage"]).filter(|c| c.is_object()) {
            if let Some(h) = cov["holes"].as_u64() {
                rows.push(("Holes in the raw scan".into(), h.to_string()));
            }
            if let Some(h) = cov["unfilled_holes"].as_u64() {
                rows.push(("Holes left after filling".into(), h.to_string()));
            }
            let big = &cov["largest_unfilled_hole"];
            if let (Some(a), Some(x), Some(y)) =
                (big["area_mm2"].as_f64(), big["center_x_mm"].as_f64(), big["center_y_mm"].as_f64())
            {
                rows.push((
                    "Largest hole left".into(),
                    format!("{} mm² at ({}, {}) mm", fmt_num(a), fmt_num(x), fmt_num(y)),
                ));
            }
        }
        let rows: Vec<(String, String)> = rows.into_iter().map(|(k, v)| (k, esc(&v))).collect();
        let caption = format!(
            "{label} coverage map: what the scan measured, what was filled from neighbours, and the holes a rescan should cover."
        );
        let fig =
            self.picture(&file_name(key, "png"), &img, &format!("{label} coverage map"), &esc(&caption))?;
        Ok(format!("<div>{fig}{legend}{}</div>", kv_table(&rows)))
    }
}
