//! Toolpaths per face over the face's depth map.

use crate::*;

impl Ctx<'_> {
    pub(crate) fn toolpaths(&mut self) -> Result<String, ReportError> {
        let parsed;
        let (digests, artifacts) = (self.digests, self.artifacts);
        let program = match (digests.programs.get("gcode"), artifacts.get("gcode")) {
            (Some(p), _) => p,
            (None, Some(bytes)) => match std::str::from_utf8(bytes) {
                Ok(t) => {
                    parsed = gcode::parse(t);
                    &parsed
                }
                Err(e) => {
                    let e = format!("Not shown: the gcode artifact is not UTF-8 text: {e}.");
                    return Ok(section("toolpaths", "Toolpaths", &missing(&e)));
                }
            },
            (None, None) => {
                return Ok(section("toolpaths", "Toolpaths", &missing(&self.why_missing("gcode"))));
            }
        };
        let mut body = String::new();
        let _ = write!(
            body,
            r#"<p>{} blocks, {} operations on {} face(s). <span class="swatch" style="background:rgb({},{},{})"></span>roughing<span class="swatch" style="background:rgb({},{},{})"></span>finishing<span class="swatch" style="background:rgb({},{},{})"></span>other feed moves<span class="swatch" style="background:rgb({},{},{})"></span>rapids (thin)</p>"#,
            fmt_count(program.blocks),
            program.ops.len(),
            program.faces.len(),
            ROUGHING_RGB[0],
            ROUGHING_RGB[1],
            ROUGHING_RGB[2],
            FINISHING_RGB[0],
            FINISHING_RGB[1],
            FINISHING_RGB[2],
            OTHER_RGB[0],
            OTHER_RGB[1],
            OTHER_RGB[2],
            RAPID_RGB[0],
            RAPID_RGB[1],
            RAPID_RGB[2],
        );
        let final_stock = if self.depth_maps.is_empty() {
            self.artifacts.get("final_stock").and_then(|b| maps::decode_map(b, None).ok()).map(|d| d.map)
        } else {
            None
        };
        for face in 0..program.faces.len() {
            let key = if face == 0 { "depth_map".to_string() } else { format!("depth_map@{face}") };
            let (base, base_name) = match self.depth_maps.get(&key) {
                Some(m) => (Some(m), format!("the {key}")),
                None if face == 0 && final_stock.is_some() => {
                    (final_stock.as_ref(), "the final stock".into())
                }
                None => (None, "no map (none was available)".into()),
            };
            let Some(img) = toolpath_image(base, program, face) else {
                body.push_str(&missing(&format!("Face {}: no moves to draw.", face + 1)));
                continue;
            };
            let a = program
                .faces
                .get(face)
                .copied()
                .flatten()
                .map(|a| format!(" at A {} deg", fmt_num(a)))
                .unwrap_or_default();
            let caption = format!(
                "Face {}{a}: toolpaths over {base_name} in work coordinates (X right, Y up); roughing orange, finishing blue, rapids thin grey.",
                face + 1
            );
            let name = if face == 0 {
                "toolpaths.png".to_string()
            } else {
                format!("toolpaths_face{}.png", face + 1)
            };
            body.push_str(&self.picture(
                &name,
                &img,
                &format!("toolpaths of face {}", face + 1),
                &esc(&caption),
            )?);
        }
        let rows: Vec<Vec<String>> = program
            .ops
            .iter()
            .map(|o| {
                vec![
                    (o.face + 1).to_string(),
                    esc(o.kind.label()),
                    esc(&o.label),
                    format!(r#"<span class="num">{}</span>"#, fmt_num(o.feed_mm / 1000.0)),
                    format!(r#"<span class="num">{}</span>"#, fmt_num(o.rapid_mm / 1000.0)),
                    format!(r#"<span class="num">{}</span>"#, fmt_count(o.moves)),
                ]
            })
            .collect();
        body.push_str(&table(
            &["face", "kind", "tool and strategy", "feed path [m]", "rapids [m]", "moves"],
            &rows,
        ));
        // How the CAM chose the tools the job left unnamed, when the defaults could not reach.
        let choice: Vec<String> = self
            .artifacts
            .get("plan_report")
            .and_then(|b| serde_json::from_slice::<Value>(b).ok())
            .and_then(|r| r["tool_choice"].as_array().cloned())
            .unwrap_or_default()
            .iter()
            .filter_map(|v| v.as_str().map(esc))
            .collect();
        if !choice.is_empty() {
            let _ = write!(body, "<h3>Tool choice</h3><ul><li>{}</li></ul>", choice.join("</li><li>"));
        }
        if !program.warnings.is_empty() {
            let w: Vec<String> = program.warnings.iter().map(|w| esc(w)).collect();
            let _ = write!(
                body,
                "<details><summary>Lines the drawing skipped</summary><pre>{}</pre></details>",
                w.join("\n")
            );
        }
        Ok(section("toolpaths", "Toolpaths", &body))
    }
}

/// Toolpaths of `face` over `base` (grey hill-shade) or over white: finishing thin blue, then
/// roughing orange on top (it is sparser), rapids thin grey underneath, other feeds purple. The
/// view covers the map plus the program's feed moves (at most 15 % of the map beyond each side).
pub fn toolpath_image(base: Option<&HeightMap>, program: &Program, face: usize) -> Option<RgbImage> {
    let ext = program.feed_extent.get(face).copied().flatten();
    let (x0, y0, x1, y1) = match (base, ext) {
        (Some(m), e) => {
            let mm = m.meta();
            let (mx0, my0) = (mm.origin_x_mm, mm.origin_y_mm);
            let (mx1, my1) = (mx0 + mm.width_mm(), my0 + mm.height_mm());
            let (px, py) = (0.15 * (mx1 - mx0), 0.15 * (my1 - my0));
            match e {
                Some(e) => (
                    mx0.min(e[0].max(mx0 - px)),
                    my0.min(e[1].max(my0 - py)),
                    mx1.max(e[2].min(mx1 + px)),
                    my1.max(e[3].min(my1 + py)),
                ),
                None => (mx0, my0, mx1, my1),
            }
        }
        (None, Some(e)) => {
            let pad = 0.05 * (e[2] - e[0]).max(e[3] - e[1]).max(1.0);
            (e[0] - pad, e[1] - pad, e[2] + pad, e[3] + pad)
        }
        (None, None) => return None,
    };
    let side = base.map_or(800.0, |m| f64::from(m.width().max(m.height())).max(800.0));
    let view = View::fit(x0, y0, x1, y1, side)?;
    let mut img = match base.and_then(|m| maps::robust_range(m).map(|r| (m, r))) {
        Some((m, (lo, hi))) => maps::grey_image(m, &view, lo, hi),
        None => RgbImage::new(view.width, view.height, [255, 255, 255]),
    };
    let kind = |s: &gcode::Seg| program.ops.get(s.op as usize).map(|o| (o.face, o.kind));
    let draw = |img: &mut RgbImage, rapid: bool, k: OpKind, color: [u8; 3], alpha: f32, width: u32| {
        for s in &program.segs {
            let Some((f, k2)) = kind(s) else { continue };
            if f != face || s.rapid != rapid || (!rapid && k2 != k) {
                continue;
            }
            let a = view.to_px(f64::from(s.a[0]), f64::from(s.a[1]));
            let b = view.to_px(f64::from(s.b[0]), f64::from(s.b[1]));
            img.line(a, b, color, alpha, width);
        }
    };
    draw(&mut img, true, OpKind::Other, RAPID_RGB, 0.45, 1);
    draw(&mut img, false, OpKind::Other, OTHER_RGB, 0.85, 1);
    draw(&mut img, false, OpKind::Finishing, FINISHING_RGB, 0.85, 1);
    draw(&mut img, false, OpKind::Roughing, ROUGHING_RGB, 0.9, 2);
    Some(img)
}
