//! HTML helpers: escaping, figures, notes, tables, the page shell and its CSS.

use std::fmt::Write as _;

/// Escapes text for HTML element content and quoted attribute values.
pub fn esc(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    for c in s.chars() {
        match c {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '"' => out.push_str("&quot;"),
            '\'' => out.push_str("&#39;"),
            c => out.push(c),
        }
    }
    out
}

/// A figure: an image (`src` is a data URI) with alt text and a caption (HTML, already escaped).
pub fn figure_img(src: &str, alt: &str, caption_html: &str, width: u32, height: u32) -> String {
    format!(
        r#"<figure><img src="{}" alt="{}" width="{width}" height="{height}"><figcaption>{caption_html}</figcaption></figure>"#,
        esc(src),
        esc(alt)
    )
}

/// A figure around inline SVG (generated here, never from input).
pub fn figure_svg(svg: &str, caption_html: &str) -> String {
    format!(r#"<figure>{svg}<figcaption>{caption_html}</figcaption></figure>"#)
}

/// The note shown instead of a picture (`text` is plain text).
pub fn missing(text: &str) -> String {
    format!(r#"<p class="missing">{}</p>"#, esc(text))
}

/// A two-column table of (label, value HTML) rows.
pub fn kv_table(rows: &[(String, String)]) -> String {
    let mut s = String::from(r#"<table class="kv">"#);
    for (k, v) in rows {
        let _ = write!(s, "<tr><th>{}</th><td>{v}</td></tr>", esc(k));
    }
    s.push_str("</table>");
    s
}

/// A table with a header row; cells are HTML.
pub fn table(head: &[&str], rows: &[Vec<String>]) -> String {
    let mut s = String::from("<table><thead><tr>");
    for h in head {
        let _ = write!(s, "<th>{}</th>", esc(h));
    }
    s.push_str("</tr></thead><tbody>");
    for r in rows {
        s.push_str("<tr>");
        for c in r {
            let _ = write!(s, "<td>{c}</td>");
        }
        s.push_str("</tr>");
    }
    s.push_str("</tbody></table>");
    s
}

/// A section with an id and a heading; `body` is HTML.
pub fn section(id: &str, title: &str, body: &str) -> String {
    format!(r#"<section id="{}"><h2>{}</h2>{body}</section>"#, esc(id), esc(title))
}

pub const CSS: &str = r#"
:root { color-scheme: light; }
body { font-family: system-ui, -apple-system, "Segoe UI", Roboto, sans-serif; margin: 0; background: #f4f5f7; color: #1d2330; line-height: 1.45; }
main { max-width: 1100px; margin: 0 auto; padding: 16px 24px 48px; background: #fff; min-height: 100vh; box-shadow: 0 0 8px rgba(0,0,0,.06); }
header { border-bottom: 2px solid #1f4e99; margin-bottom: 12px; padding-bottom: 8px; }
h1 { font-size: 1.6em; margin: 8px 0 4px; }
h2 { font-size: 1.25em; margin: 28px 0 10px; padding-top: 6px; border-top: 1px solid #dde1e8; color: #1f4e99; }
h3 { font-size: 1.05em; margin: 16px 0 6px; }
.sub { color: #5a6272; font-size: .95em; }
.status { display: inline-block; padding: 1px 8px; border-radius: 10px; font-weight: 600; font-size: .9em; background: #e3e7ee; }
.status.succeeded { background: #d7f0dd; color: #1c6b30; }
.status.failed { background: #f8d9d9; color: #8a1c1c; }
.status.cancelled { background: #efe6cc; color: #6b5313; }
.status.running, .status.queued { background: #dce8fa; color: #1f4e99; }
.error { background: #fdf0f0; border-left: 4px solid #c0392b; padding: 6px 10px; }
table { border-collapse: collapse; margin: 6px 0 12px; font-size: .92em; }
th, td { border: 1px solid #dde1e8; padding: 3px 8px; text-align: left; vertical-align: top; }
thead th { background: #eef1f6; }
table.kv th { background: #f6f7fa; font-weight: 600; white-space: nowrap; }
td.num, .num { text-align: right; font-variant-numeric: tabular-nums; }
.grid { display: flex; flex-wrap: wrap; gap: 16px; align-items: flex-start; }
.grid > * { flex: 1 1 320px; min-width: 0; }
figure { margin: 8px 0 16px; }
figure img, figure svg { max-width: 100%; height: auto; border: 1px solid #ccd2dc; background: #fff; image-rendering: auto; }
figure svg.legend, figure svg.chart { border: none; }
figcaption { font-size: .88em; color: #4a5263; margin-top: 4px; }
.missing { color: #7a5a00; background: #fff8e1; border-left: 4px solid #f0b400; padding: 6px 10px; font-size: .95em; }
.swatch { display: inline-block; width: 12px; height: 12px; border: 1px solid #777; vertical-align: middle; margin: 0 4px 0 10px; }
details pre { max-height: 320px; overflow: auto; background: #f6f7fa; padding: 8px; font-size: .85em; }
code { font-size: .92em; }
footer { margin-top: 32px; color: #7a8190; font-size: .85em; }
"#;
