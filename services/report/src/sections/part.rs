//! The machined part: shaded, its deviation from the target, and against the original part and the CAM's prediction.

use crate::*;

/// A cell counts as reached by the tool when the part opened by it stands at most this much over
/// the part, mm.
pub const REACH_TOLERANCE_MM: f64 = 0.01;

impl Ctx<'_> {
    pub(crate) fn machined(&mut self) -> Result<String, ReportError> {
        let mut all = String::new();
        let faces = self.face_suffixes();
        for (fi, suffix) in faces.iter().enumerate() {
            let stock_key = format!("final_stock{suffix}");
            if fi > 0 && !self.artifacts.contains_key(&stock_key) {
                continue;
            }
            let (key, note) = if self.artifacts.contains_key(&stock_key)
                || !self.artifacts.contains_key("toolpath_preview")
            {
                (stock_key, "")
            } else {
                (
                    "toolpath_preview".to_string(),
                    " This is the CAM's predicted surface: the machine stage has not produced a final stock.",
                )
            };
            let face = if faces.len() > 1 { format!(" Face {}.", fi + 1) } else { String::new() };
            let body = match self.decode(&key) {
                Err(e) => missing(&e),
                Ok(d) => {
                    let map = &d.map;
                    match (maps::map_view(map), maps::robust_range(map)) {
                        (Some(view), Some((lo, hi))) => {
                            let img = maps::shaded_image(map, &view, lo, hi);
                            let m = map.meta();
                            let caption = format!(
                                "Simulated machined part, lit from the top left: {}×{} mm, cells of {} mm, surface Z {}–{} mm.{note}{face}",
                                fmt_num(m.width_mm()),
                                fmt_num(m.height_mm()),
                                fmt_num(m.pixel_mm),
                                fmt_num(lo),
                                fmt_num(hi)
                            );
                            let file = format!("{}.png", key.replace('@', "_face"));
                            self.picture(&file, &img, "machined part", &esc(&caption))?
                        }
                        _ => missing(&format!("The {key} has no cell with data.")),
                    }
                }
            };
            all.push_str(&body);
        }
        Ok(section("final-stock", "Machined part", &all))
    }

    pub(crate) fn deviation(&mut self) -> Result<String, ReportError> {
        let mut body = String::new();
        let faces = self.face_suffixes();
        for (fi, suffix) in faces.iter().enumerate() {
            let dkey = format!("deviation_map{suffix}");
            if fi > 0 && !self.artifacts.contains_key(&dkey) {
                continue;
            }
            match self.decode(&dkey) {
                Err(e) => body.push_str(&missing(&e)),
                Ok(mut d) => {
                    let unseen = self.leave_out_assumed(&mut d.map, suffix);
                    let map = &d.map;
                    match (maps::map_view(map), maps::deviation_range(map)) {
                        (Some(view), Some((range, lo, hi))) => {
                            let img = maps::deviation_image(map, &view, range);
                            let legend = ColorMap::new(raster::RED_WHITE_BLUE).legend_svg(
                                &format!("lg-deviation{fi}"),
                                -range,
                                range,
                                "stock − target [mm]",
                                "gouge (too deep)",
                                "leftover (material left)",
                            );
                            let caption = format!(
                                "Machined part minus the target, per cell: red where the part was cut too deep, blue where material is left, white on target. Map values {}–{} mm; the scale saturates at ±{} mm (99.5 % of |deviation|).",
                                fmt_num(lo),
                                fmt_num(hi),
                                fmt_num(range)
                            );
                            let caption = if unseen > 0 {
                                format!(
                                    "{caption} Left out (grey): {} cells the scanner never saw, whose target height was assumed from around them.",
                                    fmt_count(unseen)
                                )
                            } else {
                                caption
                            };
                            let caption =
                                if faces.len() > 1 { format!("Face {}. {caption}", fi + 1) } else { caption };
                            let file = format!("{}.png", dkey.replace('@', "_face"));
                            body.push_str(&self.picture(&file, &img, "deviation map", &esc(&caption))?);
                            body.push_str(&figure_svg(&legend, "Colour scale of the deviation."));
                        }
                        _ => body.push_str(&missing("The deviation map has no cell with data.")),
                    }
                }
            }
        }
        let mr = self.machine_report.as_ref();
        let dev = |k: &str| mr.and_then(|m| m["deviation"][k].as_f64());
        let rows: Vec<(String, String)> = [
            ("Max gouge", self.metric("max_gouge_mm").or_else(|| dev("max_gouge_mm"))),
            ("Max leftover", self.metric("max_leftover_mm").or_else(|| dev("max_leftover_mm"))),
            ("Mean leftover", dev("mean_leftover_mm")),
            ("RMS deviation", self.metric("rms_deviation_mm").or_else(|| dev("rms_deviation_mm"))),
        ]
        .into_iter()
        .map(|(k, v)| (k.to_string(), esc(&v.map_or("—".into(), |v| format!("{v:.4} mm")))))
        .collect();
        body.push_str(&kv_table(&rows));
        body.push_str(&self.against_part()?);
        body.push_str(&self.against_preview()?);
        Ok(section("deviation", "Deviation from the original part", &body))
    }

    /// Leaves out (NaN) the deviation of the cells the face's coverage map marks as assumed
    /// (never seen by the scanner, given a height from around them): the target there is a
    /// guess, so a "gouge" there says nothing about the machining. Returns how many; none when
    /// the coverage map is missing or on another grid.
    fn leave_out_assumed(&self, map: &mut HeightMap, suffix: &str) -> usize {
        let Ok(c) = self.decode(&format!("coverage_map{suffix}")) else { return 0 };
        if c.map.width() != map.width() || c.map.height() != map.height() {
            return 0;
        }
        let mut n = 0;
        for (z, &cv) in map.data_mut().iter_mut().zip(c.map.data()) {
            if z.is_finite() && maps::CoverageClass::of(cv) == maps::CoverageClass::Assumed {
                *z = f32::NAN;
                n += 1;
            }
        }
        n
    }

    /// The machined part against the original part itself, when the job started from its mesh
    /// (a simulated scan): the mesh's top surface, seen as the first face sees it (turned to its
    /// view when that is not `+Z`), rasterised on the final stock's grid (exact z-buffer at cell
    /// centres). Only when the maps are in the mesh's own frame up to that turn and the point
    /// the map's frame is centred on: no `filters.transform` nor `filters.table`.
    pub(crate) fn against_part(&mut self) -> Result<String, ReportError> {
        let rec = &self.job["spec"]["reconstruct"];
        let same_frame = rec["filters"]["transform"].is_null() && rec["filters"]["table"].is_null();
        // The first face's view (chosen from the shape or named) and the part's point it is
        // centred on, as the depth map records them.
        let Ok(view_from_part) = self.decode("depth_map").map(|d| d.map.meta().view_from_part()) else {
            return Ok(String::new());
        };
        let Some(bytes) = self.artifacts.get("mesh").filter(|_| same_frame) else {
            return Ok(String::new());
        };
        let Ok(stock) = self.decode("final_stock") else { return Ok(String::new()) };
        let limits = depthmill_geometry::formats::ReadLimits::default();
        let mut mesh = match depthmill_geometry::formats::read_any_from(
            std::io::Cursor::new(bytes),
            "mesh",
            Some(bytes.len() as u64),
            &limits,
        ) {
            Ok((depthmill_geometry::formats::Geometry::Mesh(m), _)) => m,
            Ok(_) => return Ok(String::new()),
            Err(e) => {
                return Ok(missing(&format!("The original part could not be read to compare with: {e}.")));
            }
        };
        // The scan read the mesh in its units and scaled it to millimetres (its report says by how much).
        let scale = self
            .artifacts
            .get("scan_report")
            .and_then(|b| serde_json::from_slice::<serde_json::Value>(b).ok())
            .and_then(|r| r["units"]["scale_to_mm"].as_f64())
            .filter(|s| s.is_finite() && *s > 0.0)
            .unwrap_or(1.0);
        if scale != 1.0 {
            mesh.scale(scale);
        }
        if view_from_part != depthmill_geometry::nalgebra::Isometry3::identity() {
            mesh.transform(&view_from_part);
        }
        let meta = *stock.map.meta();
        let Ok((part, _)) = depthmill_geometry::mesh_raster::rasterize_mesh_with_stats(&mesh, &meta) else {
            return Ok(String::new());
        };
        // Cells within one depth-map pixel of a surface steeper than 75° or of the part's outline:
        // there a wall a fraction of a pixel off reads as a full step in Z, whichever way it is off.
        let depth_pixel = self
            .depth_maps
            .get("depth_map")
            .map(|m| m.meta().pixel_mm)
            .or_else(|| self.job["spec"]["reconstruct"]["pixel_mm"].as_f64())
            .unwrap_or(0.25);
        let walls = wall_zone(&part, depth_pixel);
        // The part opened by the program's smallest tool: the best surface it can leave.
        let tool = self.smallest_tool();
        let opened = tool.as_ref().and_then(|(_, t)| depthmill_geometry::compensate::opened(&part, t));
        let (mut op_gouge, mut op_sum, mut op_sq, mut op_n) = (0.0f64, 0.0f64, 0.0f64, 0usize);
        // The stock's cells whose centre lies in a cell the first face's coverage map marks
        // measured (the two grids share the face's frame; the stock's may be finer): the opened
        // figures over those alone say how close the cut comes where the target is a measurement,
        // not a hole's fill nor a lid over what nobody saw.
        let measured: Option<Vec<bool>> = self.decode("coverage_map").ok().map(|c| {
            let cm = *c.map.meta();
            let w = meta.width as usize;
            (0..w * meta.height as usize)
                .map(|i| {
                    let (x, y) = meta.cell_center((i % w) as u32, (i / w) as u32);
                    cm.cell_of(x, y)
                        .and_then(|(col, row)| c.map.get(col, row))
                        .is_some_and(|v| maps::CoverageClass::of(v) == maps::CoverageClass::Measured)
                })
                .collect()
        });
        let (mut ms_gouge, mut ms_sum, mut ms_sq, mut ms_n) = (0.0f64, 0.0f64, 0.0f64, 0usize);
        let mut op_where: Option<usize> = None;
        let mut data = vec![f32::NAN; part.data().len()];
        let (mut gouge, mut left, mut sum_left, mut sum, mut sq, mut n) =
            (0.0f64, 0.0f64, 0.0f64, 0.0f64, 0.0f64, 0usize);
        let (mut ow_gouge, mut ow_sum, mut ow_sq, mut ow_n) = (0.0f64, 0.0f64, 0.0f64, 0usize);
        for (i, (p, z)) in part.data().iter().zip(stock.map.data()).enumerate() {
            if !(p.is_finite() && z.is_finite()) {
                continue;
            }
            let d = f64::from(*z) - f64::from(*p);
            data[i] = d as f32;
            gouge = gouge.max(-d);
            left = left.max(d);
            sum_left += d.max(0.0);
            sum += d;
            sq += d * d;
            n += 1;
            if !walls[i] {
                ow_gouge = ow_gouge.max(-d);
                ow_sum += d;
                ow_sq += d * d;
                ow_n += 1;
                // Where the tool reaches the part: the opening leaves no material over it.
                if let Some(o) = opened.as_ref().and_then(|o| o.data().get(i)).filter(|o| o.is_finite())
                    && f64::from(*o) - f64::from(*p) <= REACH_TOLERANCE_MM
                {
                    let d = f64::from(*z) - f64::from(*o);
                    if -d > op_gouge {
                        op_gouge = -d;
                        op_where = Some(i);
                    }
                    op_sum += d;
                    op_sq += d * d;
                    op_n += 1;
                    if measured.as_ref().is_some_and(|m| m.get(i) == Some(&true)) {
                        ms_gouge = ms_gouge.max(-d);
                        ms_sum += d;
                        ms_sq += d * d;
                        ms_n += 1;
                    }
                }
            }
        }
        if ow_n > 0 {
            let m = ow_n as f64;
            for (k, v) in [
                ("part_off_walls_max_gouge_mm", ow_gouge),
                ("part_off_walls_mean_mm", ow_sum / m),
                ("part_off_walls_rms_mm", (ow_sq / m).sqrt()),
            ] {
                self.figures.insert(k.into(), v);
            }
        }
        if op_n > 0 {
            let m = op_n as f64;
            for (k, v) in [
                ("part_opened_max_gouge_mm", op_gouge),
                ("part_opened_mean_mm", op_sum / m),
                ("part_opened_rms_mm", (op_sq / m).sqrt()),
                ("part_opened_cells", m),
            ] {
                self.figures.insert(k.into(), v);
            }
            if ms_n > 0 {
                let m = ms_n as f64;
                for (k, v) in [
                    ("part_opened_measured_max_gouge_mm", ms_gouge),
                    ("part_opened_measured_mean_mm", ms_sum / m),
                    ("part_opened_measured_rms_mm", (ms_sq / m).sqrt()),
                    ("part_opened_measured_cells", m),
                ] {
                    self.figures.insert(k.into(), v);
                }
            }
            // Where the deepest gouge is (the centre of its cell, in the map's frame).
            if let Some(i) = op_where {
                let (x, y) =
                    meta.cell_center((i % meta.width as usize) as u32, (i / meta.width as usize) as u32);
                self.figures.insert("part_opened_max_gouge_x_mm".into(), x);
                self.figures.insert("part_opened_max_gouge_y_mm".into(), y);
            }
        }
        if n == 0 {
            return Ok(String::new());
        }
        let nf = n as f64;
        for (k, v) in [
            ("part_max_gouge_mm", gouge),
            ("part_max_leftover_mm", left),
            ("part_mean_leftover_mm", sum_left / nf),
            ("part_mean_mm", sum / nf),
            ("part_rms_mm", (sq / nf).sqrt()),
        ] {
            self.figures.insert(k.into(), v);
        }
        let range = gouge.max(left).max(0.005);
        let Ok(map) = HeightMap::new(HeightMapMeta { z_min_mm: -range, z_max_mm: range, ..meta }, data)
        else {
            return Ok(String::new());
        };
        let mut body = String::from("<h3>Against the original part</h3>");
        if let (Some(view), Some((r, _, _))) = (maps::map_view(&map), maps::deviation_range(&map)) {
            let img = maps::deviation_image(&map, &view, r);
            let caption = format!(
                "Machined part minus the original part (the input mesh's top surface at each cell): the whole chain, scan to mill. Cells on vertical walls read large either way (a wall a fraction of a cell off is a full step in Z); holes the tools cannot enter show as leftover. Scale ±{} mm.",
                fmt_num(r)
            );
            body.push_str(&self.picture(
                "deviation_from_part.png",
                &img,
                "deviation from the part",
                &esc(&caption),
            )?);
        }
        let mut rows = vec![
            ("Max gouge".to_string(), format!("{gouge:.4} mm")),
            ("Max leftover".to_string(), format!("{left:.4} mm")),
            ("Mean leftover".to_string(), format!("{:.4} mm", sum_left / nf)),
            ("Mean (signed)".to_string(), format!("{:+.4} mm", sum / nf)),
            ("RMS".to_string(), format!("{:.4} mm over {} cells", (sq / nf).sqrt(), n)),
            (
                "Off the walls".to_string(),
                if ow_n > 0 {
                    let m = ow_n as f64;
                    format!(
                        "max gouge {ow_gouge:.4} mm, mean {:+.4} mm, RMS {:.4} mm over {ow_n} cells (cells within one depth-map pixel, {} mm, of a surface steeper than 75° left out)",
                        ow_sum / m,
                        (ow_sq / m).sqrt(),
                        fmt_num(depth_pixel)
                    )
                } else {
                    "every cell is next to a wall".to_string()
                },
            ),
        ];
        if let Some((name, _)) = &tool {
            rows.push((
                format!("Against the part opened by {name}"),
                if op_n > 0 {
                    let m = op_n as f64;
                    format!(
                        "max gouge {op_gouge:.4} mm, mean {:+.4} mm, RMS {:.4} mm over {op_n} cells off the walls where {name} reaches the part (the opening leaves at most {} mm over it)",
                        op_sum / m,
                        (op_sq / m).sqrt(),
                        fmt_num(REACH_TOLERANCE_MM)
                    )
                } else {
                    format!("{name} reaches no cell off the walls")
                },
            ));
            if ms_n > 0 {
                let m = ms_n as f64;
                rows.push((
                    "... where the scan measured".to_string(),
                    format!(
                        "max gouge {ms_gouge:.4} mm, mean {:+.4} mm, RMS {:.4} mm over the {ms_n} of those cells the depth map measured (not filled between points nor lidded over what the scanner did not see)",
                        ms_sum / m,
                        (ms_sq / m).sqrt()
                    ),
                ));
            }
        }
        body.push_str(&kv_table(&rows));
        Ok(body)
    }

    /// The program's smallest tool by radius, from its tool comments (`T2 ball-3: ...`).
    fn smallest_tool(&self) -> Option<(String, depthmill_geometry::ToolProfile)> {
        let parsed;
        let program = match (self.digests.programs.get("gcode"), self.artifacts.get("gcode")) {
            (Some(p), _) => p,
            (None, Some(bytes)) => {
                parsed = gcode::parse(std::str::from_utf8(bytes).ok()?);
                &parsed
            }
            (None, None) => return None,
        };
        program
            .ops
            .iter()
            .filter_map(|op| {
                let name = op.label.split(':').next()?.split_whitespace().nth(1)?;
                let tool = name.parse::<depthmill_geometry::ToolProfile>().ok()?;
                Some((name.to_string(), tool))
            })
            .min_by(|a, b| a.1.radius_mm().total_cmp(&b.1.radius_mm()))
    }

    /// The machined part against the CAM's preview (`toolpath_preview`: the surface the program
    /// leaves, the part opened by the tools plus scallops). Leftover the tools cannot reach shows
    /// in the deviation from the part but not here; what shows here is the machine's doing (steps,
    /// the adaptive loop's feeds, the simulation's cells). Seen from the first face; on a part
    /// cut on several faces the prediction is what every face's program leaves together
    /// ([`depthmill_geometry::multi_face`]): the later faces cut what the first one's tools could
    /// not reach and what its scan only assumed.
    pub(crate) fn against_preview(&mut self) -> Result<String, ReportError> {
        let (Ok(stock), Ok(preview)) = (self.decode("final_stock"), self.decode("toolpath_preview")) else {
            return Ok(String::new());
        };
        let faces = self.face_suffixes();
        let preview_map = if faces.len() > 1 {
            let mut maps = vec![preview.map];
            for suffix in &faces[1..] {
                match self.decode(&format!("toolpath_preview{suffix}")) {
                    Ok(d) => maps.push(d.map),
                    Err(e) => {
                        return Ok(format!(
                            "<h3>Against the surface the program can leave</h3>{}",
                            missing(&format!(
                                "The part is cut on {} faces and the prediction needs every face's; {e}",
                                faces.len()
                            ))
                        ));
                    }
                }
            }
            // Each face's view as its depth map records it (the preview's own label otherwise).
            let surfaces: Vec<depthmill_geometry::multi_face::FaceSurface<'_>> = faces
                .iter()
                .zip(&maps)
                .map(|(suffix, map)| {
                    let face =
                        self.decode(&format!("depth_map{suffix}")).map_or(map.face(), |d| d.map.face());
                    depthmill_geometry::multi_face::FaceSurface { view_from_part: face.view_from_part(), map }
                })
                .collect();
            match depthmill_geometry::multi_face::surface_seen_from(&surfaces, 0, stock.map.meta().z_min_mm) {
                Ok(m) => m,
                Err(e) => return Ok(missing(&format!("The faces' predictions could not be combined: {e}."))),
            }
        } else {
            preview.map
        };
        let meta = *preview_map.meta();
        let mut data = vec![f32::NAN; preview_map.data().len()];
        let (mut lo, mut hi, mut sum, mut sq, mut n) = (0.0f64, 0.0f64, 0.0f64, 0.0f64, 0usize);
        for row in 0..meta.height {
            for col in 0..meta.width {
                let Some(p) = preview_map.get(col, row).filter(|v| v.is_finite()) else { continue };
                let (x, y) = meta.cell_center(col, row);
                let Some(z) =
                    stock.map.cell_of(x, y).and_then(|(c, r)| stock.map.get(c, r)).filter(|v| v.is_finite())
                else {
                    continue;
                };
                let d = f64::from(z) - f64::from(p);
                data[(row * meta.width + col) as usize] = d as f32;
                lo = lo.min(d);
                hi = hi.max(d);
                sum += d;
                sq += d * d;
                n += 1;
            }
        }
        if n == 0 {
            return Ok(String::new());
        }
        for (k, v) in [
            ("preview_max_below_mm", (-lo).max(0.0)),
            ("preview_max_above_mm", hi.max(0.0)),
            ("preview_mean_mm", sum / n as f64),
            ("preview_rms_mm", (sq / n as f64).sqrt()),
        ] {
            self.figures.insert(k.into(), v);
        }
        let range = (-lo).max(hi).max(0.005);
        let dev_meta = HeightMapMeta { z_min_mm: -range, z_max_mm: range, ..meta };
        let Ok(map) = HeightMap::new(dev_meta, data) else { return Ok(String::new()) };
        let mut body = String::from("<h3>Against the surface the program can leave</h3>");
        if let (Some(view), Some((r, _, _))) = (maps::map_view(&map), maps::deviation_range(&map)) {
            let img = maps::deviation_image(&map, &view, r);
            let caption = format!(
                "Machined part minus the CAM's predicted surface (the part opened by the tools, scallops included): what the machine itself added or left. Scale ±{} mm.{}",
                fmt_num(r),
                if faces.len() > 1 {
                    format!(
                        " Seen from the first face; the prediction is what the programs of all {} faces leave together.",
                        faces.len()
                    )
                } else {
                    String::new()
                }
            );
            body.push_str(&self.picture(
                "deviation_from_preview.png",
                &img,
                "deviation from the preview",
                &esc(&caption),
            )?);
        }
        let rows = vec![
            ("Deepest below the preview".to_string(), format!("{:.4} mm", (-lo).max(0.0))),
            ("Highest above the preview".to_string(), format!("{:.4} mm", hi.max(0.0))),
            ("RMS".to_string(), format!("{:.4} mm over {} cells", (sq / n as f64).sqrt(), n)),
        ];
        body.push_str(&kv_table(&rows));
        Ok(body)
    }
}

/// Cells of `part` (a mesh's top surface on a grid) within `radius_mm` of a surface steeper than
/// 75° or of the part's outline: where the height range over that neighbourhood exceeds what a
/// 75° slope rises over the radius, or the neighbourhood leaves the part.
pub(crate) fn wall_zone(part: &HeightMap, radius_mm: f64) -> Vec<bool> {
    let m = part.meta();
    let (w, h) = (m.width as usize, m.height as usize);
    let k = ((radius_mm / m.pixel_mm).ceil() as usize).max(1);
    let step = (radius_mm.max(m.pixel_mm) * 75f64.to_radians().tan()) as f32;
    let d = part.data();
    let mut out = vec![false; d.len()];
    for r in 0..h {
        for c in 0..w {
            let i = r * w + c;
            if !d[i].is_finite() {
                continue;
            }
            let (mut lo, mut hi, mut edge) = (d[i], d[i], false);
            for rr in r.saturating_sub(k)..=(r + k).min(h - 1) {
                for cc in c.saturating_sub(k)..=(c + k).min(w - 1) {
                    let v = d[rr * w + cc];
                    if v.is_finite() {
                        lo = lo.min(v);
                        hi = hi.max(v);
                    } else {
                        edge = true;
                    }
                }
            }
            out[i] = edge || hi - lo > step;
        }
    }
    out
}
