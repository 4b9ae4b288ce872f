//! The simulated part in 3-D: the machine's view mesh (`machined_part_view`, binary PLY with the
//! deviation from the original part per vertex) in an interactive viewer, with the figures the
//! machine measured on its one stock (`machine_report.part`).
//!
//! The viewer is the page's one script ([`VIEWER_JS`]): inline, no external request. It draws
//! on a 2-D canvas (painter's algorithm: back faces culled, triangles sorted far to near, flat
//! Lambert shading times the vertex colours), so it needs no WebGL and runs the same in headless
//! browsers, on tablets and in the report test. Drag (mouse, pen or touch) or the arrow keys
//! turn the part, the wheel or `+`/`-` zoom, `0` resets the view. The colours are computed
//! here, on the same diverging scale as the deviation maps (red gouge, blue leftover, grey where
//! the deviation was not measured).

use std::fmt::Write as _;

use crate::*;

/// The 3-D viewer (see the module docs). Reads every `figure.viewer3d`'s `data-pos` (f32 x y z
/// per vertex), `data-tri` (u32 indices), `data-rgb` (u8 r g b per vertex), base64, little-endian;
/// writes the view it shows back as `data-yaw`, `data-pitch`, `data-zoom` and `data-drawn` (the
/// triangles drawn).
pub const VIEWER_JS: &str = r#"
(function () {
  'use strict';
  function bytes(b64) {
    var s = atob(b64), a = new Uint8Array(s.length);
    for (var i = 0; i < s.length; i++) a[i] = s.charCodeAt(i);
    return a.buffer;
  }
  document.querySelectorAll('figure.viewer3d').forEach(function (fig) {
    var cv = fig.querySelector('canvas');
    var ctx = cv && cv.getContext('2d');
    if (!ctx) return;
    var P = new Float32Array(bytes(fig.dataset.pos));
    var T = new Uint32Array(bytes(fig.dataset.tri));
    var C = new Uint8Array(bytes(fig.dataset.rgb));
    var nv = P.length / 3, nt = T.length / 3;
    var lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity];
    for (var i = 0; i < nv; i++) for (var k = 0; k < 3; k++) {
      lo[k] = Math.min(lo[k], P[3 * i + k]); hi[k] = Math.max(hi[k], P[3 * i + k]);
    }
    var c = [0, 1, 2].map(function (k) { return 0.5 * (lo[k] + hi[k]); });
    var R = 0.5 * Math.hypot(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]) || 1;
    var home = { yaw: -0.5, pitch: -0.95, zoom: 1 };
    var st = { yaw: home.yaw, pitch: home.pitch, zoom: home.zoom };
    var X = new Float32Array(nv), Y = new Float32Array(nv), Z = new Float32Array(nv);
    var order = new Uint32Array(nt), depth = new Float32Array(nt);
    function draw() {
      var w = cv.width, h = cv.height, s = st.zoom * 0.48 * Math.min(w, h) / R;
      var cy = Math.cos(st.yaw), sy = Math.sin(st.yaw), cp = Math.cos(st.pitch), sp = Math.sin(st.pitch);
      for (var i = 0; i < nv; i++) {
        var x = P[3 * i] - c[0], y = P[3 * i + 1] - c[1], z = P[3 * i + 2] - c[2];
        var x1 = cy * x - sy * y, y1 = sy * x + cy * y;
        X[i] = x1; Y[i] = cp * y1 - sp * z; Z[i] = sp * y1 + cp * z;
      }
      var m = 0;
      for (var t = 0; t < nt; t++) {
        var a = T[3 * t], b = T[3 * t + 1], d = T[3 * t + 2];
        var cross = (X[b] - X[a]) * (Y[d] - Y[a]) - (Y[b] - Y[a]) * (X[d] - X[a]);
        if (cross <= 0) continue;
        order[m++] = t;
        depth[t] = Z[a] + Z[b] + Z[d];
      }
      var idx = Array.prototype.slice.call(order.subarray(0, m));
      idx.sort(function (p, q) { return depth[p] - depth[q]; });
      ctx.fillStyle = '#ffffff';
      ctx.fillRect(0, 0, w, h);
      ctx.lineWidth = 0.6;
      for (var n = 0; n < idx.length; n++) {
        var t = idx[n], a = T[3 * t], b = T[3 * t + 1], d = T[3 * t + 2];
        var ux = X[b] - X[a], uy = Y[b] - Y[a], uz = Z[b] - Z[a];
        var vx = X[d] - X[a], vy = Y[d] - Y[a], vz = Z[d] - Z[a];
        var nx = uy * vz - uz * vy, ny = uz * vx - ux * vz, nz = ux * vy - uy * vx;
        var shade = 0.3 + 0.7 * Math.abs(nz) / (Math.hypot(nx, ny, nz) || 1);
        var rgb = [0, 1, 2].map(function (k) {
          return Math.round(shade * (C[3 * a + k] + C[3 * b + k] + C[3 * d + k]) / 3);
        });
        var col = 'rgb(' + rgb[0] + ',' + rgb[1] + ',' + rgb[2] + ')';
        ctx.fillStyle = col;
        ctx.strokeStyle = col;
        ctx.beginPath();
        ctx.moveTo(w / 2 + s * X[a], h / 2 - s * Y[a]);
        ctx.lineTo(w / 2 + s * X[b], h / 2 - s * Y[b]);
        ctx.lineTo(w / 2 + s * X[d], h / 2 - s * Y[d]);
        ctx.closePath();
        ctx.fill();
        ctx.stroke();
      }
      fig.dataset.drawn = String(m);
      fig.dataset.yaw = st.yaw.toFixed(4);
      fig.dataset.pitch = st.pitch.toFixed(4);
      fig.dataset.zoom = st.zoom.toFixed(4);
    }
    var queued = false;
    function redraw() {
      fig.dataset.yaw = st.yaw.toFixed(4);
      fig.dataset.pitch = st.pitch.toFixed(4);
      fig.dataset.zoom = st.zoom.toFixed(4);
      if (queued) return;
      queued = true;
      requestAnimationFrame(function () { queued = false; draw(); });
    }
    function turn(dyaw, dpitch) {
      st.yaw += dyaw;
      st.pitch = Math.max(-Math.PI, Math.min(Math.PI, st.pitch + dpitch));
      redraw();
    }
    function zoom(f) { st.zoom = Math.max(0.2, Math.min(20, st.zoom * f)); redraw(); }
    var drag = null;
    cv.addEventListener('pointerdown', function (e) {
      drag = { x: e.clientX, y: e.clientY };
      try { cv.setPointerCapture(e.pointerId); } catch (err) { /* a synthetic pointer */ }
      cv.focus();
    });
    cv.addEventListener('pointermove', function (e) {
      if (!drag) return;
      turn(0.01 * (e.clientX - drag.x), 0.01 * (e.clientY - drag.y));
      drag = { x: e.clientX, y: e.clientY };
    });
    function end() { drag = null; }
    cv.addEventListener('pointerup', end);
    cv.addEventListener('pointercancel', end);
    cv.addEventListener('wheel', function (e) { e.preventDefault(); zoom(Math.exp(-0.0015 * e.deltaY)); }, { passive: false });
    cv.addEventListener('keydown', function (e) {
      var keys = {
        ArrowLeft: function () { turn(-0.1, 0); }, ArrowRight: function () { turn(0.1, 0); },
        ArrowUp: function () { turn(0, -0.1); }, ArrowDown: function () { turn(0, 0.1); },
        '+': function () { zoom(1.2); }, '=': function () { zoom(1.2); }, '-': function () { zoom(1 / 1.2); },
        '0': function () { st.yaw = home.yaw; st.pitch = home.pitch; st.zoom = home.zoom; redraw(); }
      };
      if (keys[e.key]) { e.preventDefault(); keys[e.key](); }
    });
    draw();
  });
})();
"#;

/// Most triangles the page embeds (a larger view mesh is refused with a note: the STL artifact has
/// the part at full resolution).
pub const MAX_VIEW_TRIANGLES: usize = 600_000;

/// Grey of vertices whose deviation was not measured.
const UNMEASURED_RGB: [u8; 3] = [170, 170, 170];

impl Ctx<'_> {
    pub(crate) fn solid(&mut self) -> Result<String, ReportError> {
        let Some(bytes) = self.artifacts.get("machined_part_view") else { return Ok(String::new()) };
        let body = match depthmill_geometry::formats::read_mesh_ply(bytes) {
            Err(e) => missing(&format!("The simulated part's view mesh could not be read: {e}.")),
            Ok((mesh, _, _)) if mesh.triangles.len() > MAX_VIEW_TRIANGLES => missing(&format!(
                "The simulated part's view mesh has {} triangles, more than the {MAX_VIEW_TRIANGLES} a page embeds: open the machined_part STL instead.",
                mesh.triangles.len()
            )),
            Ok((mesh, _, dev)) => self.viewer(&mesh, &dev),
        };
        Ok(section("part3d", "Simulated part in 3-D", &body))
    }

    fn viewer(&self, mesh: &depthmill_geometry::Mesh, dev: &[f32]) -> String {
        let finite: Vec<f64> = dev.iter().filter(|d| d.is_finite()).map(|&d| f64::from(d).abs()).collect();
        let range = finite.iter().copied().fold(0.0, f64::max).max(0.005);
        let cmap = ColorMap::new(raster::RED_WHITE_BLUE);
        let mut pos = Vec::with_capacity(12 * mesh.vertices.len());
        let mut rgb = Vec::with_capacity(3 * mesh.vertices.len());
        for (p, d) in mesh.vertices.iter().zip(dev) {
            for v in [p.x, p.y, p.z] {
                pos.extend_from_slice(&(v as f32).to_le_bytes());
            }
            let c = if d.is_finite() { cmap.at(0.5 + 0.5 * f64::from(*d) / range) } else { UNMEASURED_RGB };
            rgb.extend_from_slice(&c);
        }
        let tri: Vec<u8> = mesh.triangles.iter().flatten().flat_map(|i| i.to_le_bytes()).collect();
        let mut s = String::new();
        let _ = write!(
            s,
            r#"<figure class="viewer3d" data-pos="{}" data-tri="{}" data-rgb="{}"><canvas width="880" height="560" tabindex="0" role="img" aria-label="Simulated machined part in 3-D, coloured by its deviation from the original part. Drag or use the arrow keys to turn it, the wheel or plus and minus to zoom, 0 to reset."></canvas><figcaption>The simulated part as cut on its one stock ({} triangles), coloured by the deviation of the nearest measured point of the original part: red where the cut went into the part, blue where material is left, grey where no face measured it. Drag or arrow keys: turn; wheel or +/−: zoom; 0: reset.</figcaption>"#,
            raster::base64(&pos),
            raster::base64(&tri),
            raster::base64(&rgb),
            mesh.triangles.len()
        );
        s.push_str(&cmap.legend_svg(
            "part3d-legend",
            -range,
            range,
            "deviation from the original part [mm]",
            "gouge (too deep)",
            "leftover (material left)",
        ));
        s.push_str("</figure>");
        let _ = write!(s, "<script>{VIEWER_JS}</script>");
        if let Some(part) = self.machine_report.as_ref().and_then(|r| r.get("part")).filter(|p| p.is_object())
        {
            s.push_str(&part_table(part));
        }
        s
    }
}

/// The machine's figures against the original part and the opened part, overall and per face.
fn part_table(part: &serde_json::Value) -> String {
    let mm = |v: &serde_json::Value, k: &str| v[k].as_f64().map_or("–".to_string(), |x| format!("{x:.4}"));
    let row = |label: String, f: &serde_json::Value| {
        vec![
            esc(&label),
            f["points"].as_u64().map_or("–".into(), |n| n.to_string()),
            mm(f, "max_gouge_mm"),
            mm(f, "max_leftover_mm"),
            mm(f, "mean_leftover_mm"),
            mm(f, "rms_deviation_mm"),
        ]
    };
    let mut rows = vec![row("Original part".into(), &part["against_part"])];
    if part["against_opened"].is_object() {
        let by = part["opened_by"].as_str().unwrap_or("the smallest tool");
        rows.push(row(format!("Part opened by {by}"), &part["against_opened"]));
    }
    for f in part["faces"].as_array().into_iter().flatten() {
        let a = f["a_deg"].as_f64().unwrap_or(0.0);
        rows.push(row(format!("Face A={}°: original part", fmt_num(a)), &f["against_part"]));
        if f["against_opened"].is_object() {
            rows.push(row(format!("Face A={}°: opened part", fmt_num(a)), &f["against_opened"]));
        }
    }
    let mut s = String::from("<h3>The simulated part measured on its one stock</h3>");
    let _ = write!(
        s,
        "<p>{} reference points of the original part ({}); {} that no face looks at are left out. Distances to the simulated surface, searched up to {} mm.</p>",
        part["points"].as_u64().unwrap_or(0),
        esc(part["source"].as_str().unwrap_or("?")),
        part["unseen"].as_u64().unwrap_or(0),
        fmt_num(part["max_search_mm"].as_f64().unwrap_or(0.0))
    );
    s.push_str(&table(
        &["against", "points", "max gouge mm", "max leftover mm", "mean leftover mm", "RMS mm"],
        &rows,
    ));
    s
}
