//! Length units of an input model or cloud, and how they are told when the file does not say.
//!
//! depthmill works in millimetres. A part's mesh or a range scan may come in metres (most range
//! scanners and scan repositories), inches (CAD exports for imperial shops) or millimetres.
//! [`Units::Auto`] decides, in this order:
//! 1. a unit named in the file's header text ([`header_hint`]: an STL `solid` line or binary
//!    header, PLY `comment`/`obj_info` lines, an OBJ's, OFF's or PCD's `#` comment lines, saying `units mm`, `unit: inch`, `metres`, ...);
//! 2. the size: a model whose largest extent is under [`METRE_BELOW`] units is read as metres
//!    (nothing that small in millimetres can be scanned or milled here, and every part this cell
//!    can hold is under 2 m);
//! 3. millimetres otherwise. Inches cannot be told from the size (a 4-unit model is a 4-inch part
//!    or a 4 mm one), so a model in inches without a header saying so needs `units: "in"`; the
//!    decision says so when the size is in the range where both readings are plausible.

use std::fmt;

use serde::{Deserialize, Serialize};

use crate::formats::InputFormat;

/// A model whose largest extent is below this many units is read as metres by [`Units::Auto`].
pub const METRE_BELOW: f64 = 2.0;

/// Below this largest extent (and at or above [`METRE_BELOW`]) a model read as millimetres could
/// as well be in inches; the decision carries a warning.
pub const INCH_AMBIGUOUS_BELOW: f64 = 16.0;

/// A length unit of an input file.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum LengthUnit {
    /// Millimetres (`mm`).
    #[serde(rename = "mm")]
    Millimetre,
    /// Metres (`m`).
    #[serde(rename = "m")]
    Metre,
    /// Inches (`in`).
    #[serde(rename = "in")]
    Inch,
}

impl LengthUnit {
    /// Millimetres in one unit.
    pub fn mm_per_unit(self) -> f64 {
        match self {
            LengthUnit::Millimetre => 1.0,
            LengthUnit::Metre => 1000.0,
            LengthUnit::Inch => 25.4,
        }
    }

    /// The wire name (`mm`, `m`, `in`).
    pub fn as_str(self) -> &'static str {
        match self {
            LengthUnit::Millimetre => "mm",
            LengthUnit::Metre => "m",
            LengthUnit::Inch => "in",
        }
    }

    /// Parses a wire name.
    pub fn parse(s: &str) -> Option<Self> {
        match s {
            "mm" => Some(LengthUnit::Millimetre),
            "m" => Some(LengthUnit::Metre),
            "in" => Some(LengthUnit::Inch),
            _ => None,
        }
    }
}

impl fmt::Display for LengthUnit {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

/// The units a job says its input is in.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Units {
    /// Decide from the header and the size (module documentation).
    #[default]
    Auto,
    /// As given.
    Given(LengthUnit),
}

/// How the units of an input were decided, for the stage's report.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct UnitsDecision {
    /// The unit the input was read in.
    pub unit: LengthUnit,
    /// Millimetres per input unit: coordinates were multiplied by this.
    pub scale_to_mm: f64,
    /// `given`, `header` or `size`.
    pub source: &'static str,
    /// Why, in words (the header text or the extent that decided).
    pub reason: String,
    /// Set when the decision could be wrong (a size where inches are as plausible as mm).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub warning: Option<String>,
}

impl Units {
    /// Decides the unit of an input whose first bytes are `head` and whose largest bounding-box
    /// extent, in its own units, is `extent`.
    pub fn decide(self, head: &[u8], extent: f64) -> UnitsDecision {
        let make = |unit: LengthUnit, source, reason: String, warning| UnitsDecision {
            unit,
            scale_to_mm: unit.mm_per_unit(),
            source,
            reason,
            warning,
        };
        if let Units::Given(unit) = self {
            return make(unit, "given", format!("input.units = \"{unit}\""), None);
        }
        if let Some((unit, words)) = header_hint(head) {
            return make(unit, "header", format!("the file's header says \"{words}\""), None);
        }
        if extent < METRE_BELOW {
            return make(
                LengthUnit::Metre,
                "size",
                format!(
                    "largest extent {extent:.4} units: under {METRE_BELOW} mm nothing can be scanned or milled, so the model is read as metres ({:.1} mm)",
                    extent * 1000.0
                ),
                None,
            );
        }
        let warning = (extent < INCH_AMBIGUOUS_BELOW).then(|| {
            format!(
                "largest extent {extent:.3} units read as millimetres; if the model is in inches ({:.1} mm), set input.units to \"in\"",
                extent * 25.4
            )
        });
        make(
            LengthUnit::Millimetre,
            "size",
            format!("largest extent {extent:.3} units: read as millimetres"),
            warning,
        )
    }
}

/// Decides the units of `geometry` (first bytes of its file in `head`) and scales it to
/// millimetres in place; `None` for an input without a finite point (nothing to decide on).
pub fn normalise(
    geometry: &mut crate::formats::Geometry,
    head: &[u8],
    units: Units,
) -> Option<UnitsDecision> {
    use crate::formats::Geometry;
    let bounds = match geometry {
        Geometry::Cloud(c) => c.bounds(),
        Geometry::Mesh(m) => m.bounds(),
    }?;
    let decision = units.decide(head, bounds.extent().max());
    if decision.scale_to_mm != 1.0 {
        match geometry {
            Geometry::Cloud(c) => c.scale(decision.scale_to_mm),
            Geometry::Mesh(m) => m.scale(decision.scale_to_mm),
        }
    }
    Some(decision)
}

/// Reads the first bytes of a file for [`Units::decide`] (up to 4 KiB: any header that names a
/// unit is in there); of a gzip-compressed file, the first bytes of its content.
pub fn read_head(path: &std::path::Path) -> std::io::Result<Vec<u8>> {
    use std::io::Read as _;
    let mut head = Vec::with_capacity(4096);
    let mut file = std::io::BufReader::new(std::fs::File::open(path)?);
    let mut magic = Vec::with_capacity(2);
    (&mut file).take(2).read_to_end(&mut magic)?;
    let rest = std::io::Cursor::new(magic.clone()).chain(file);
    if crate::formats::is_gzip(&magic) {
        flate2::bufread::MultiGzDecoder::new(std::io::BufReader::new(rest))
            .take(4096)
            .read_to_end(&mut head)?;
    } else {
        rest.take(4096).read_to_end(&mut head)?;
    }
    Ok(head)
}

/// A unit named in the header text of an STL, PLY, OBJ, OFF or PCD file: the ASCII STL `solid` line or the
/// binary STL's 80-byte header, PLY `comment`/`obj_info` lines. Looks only at the header (the
/// text before the first facet, `end_header`, or 80 bytes of a binary STL); returns the unit and
/// the words that named it. Words: `mm`/`millimetre(s)`/`millimeter(s)`, `m`/`metre(s)`/`meter(s)`
/// (only after `unit`/`units`, since a lone `m` is common in names), `in`/`inch`/`inches`.
pub fn header_hint(head: &[u8]) -> Option<(LengthUnit, String)> {
    let text = header_text(head);
    let lower = text.to_ascii_lowercase();
    let words: Vec<&str> =
        lower.split(|c: char| !c.is_ascii_alphanumeric()).filter(|w| !w.is_empty()).collect();
    for (i, w) in words.iter().enumerate() {
        let long = match *w {
            "millimetre" | "millimetres" | "millimeter" | "millimeters" => Some(LengthUnit::Millimetre),
            "metre" | "metres" | "meter" | "meters" => Some(LengthUnit::Metre),
            "inch" | "inches" => Some(LengthUnit::Inch),
            _ => None,
        };
        if let Some(u) = long {
            return Some((u, (*w).to_string()));
        }
        if matches!(*w, "unit" | "units")
            && let Some(next) = words.get(i + 1)
            && let Some(u) = LengthUnit::parse(next)
        {
            return Some((u, format!("{w} {next}")));
        }
    }
    None
}

/// The header part of `head` as text (lossy).
fn header_text(head: &[u8]) -> String {
    let s = String::from_utf8_lossy(head);
    let t = s.trim_start();
    if t.starts_with("ply") {
        let end = t.find("end_header").unwrap_or(t.len());
        // Only comment and obj_info lines: element and property names are not units.
        return t[..end]
            .lines()
            .filter_map(|l| l.trim().strip_prefix("comment").or_else(|| l.trim().strip_prefix("obj_info")))
            .collect::<Vec<_>>()
            .join("\n");
    }
    let format = crate::formats::sniff_format(head, None);
    if matches!(format, InputFormat::Obj | InputFormat::Off | InputFormat::Pcd) {
        // The comment lines (`# units: mm`); a PCD's `# .PCD v0.7` line says nothing.
        return t
            .lines()
            .filter_map(|l| l.trim().strip_prefix('#'))
            .filter(|l| !l.trim_start().starts_with(".PCD"))
            .collect::<Vec<_>>()
            .join("\n");
    }
    if t.len() >= 5 && t[..5].eq_ignore_ascii_case("solid") && !head.iter().take(84).any(|&b| b == 0) {
        // ASCII STL: the solid line.
        return t.lines().next().unwrap_or("").to_string();
    }
    // Binary STL: the 80-byte header, up to its first NUL.
    let h = &head[..head.len().min(80)];
    let h = h.split(|&b| b == 0).next().unwrap_or(&[]);
    String::from_utf8_lossy(h).into_owned()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn headers_that_name_a_unit_decide_it() {
        let cases: &[(&[u8], Option<LengthUnit>)] = &[
            (b"solid bracket units=inch\nfacet normal 0 0 1\n", Some(LengthUnit::Inch)),
            (b"solid part_mm_units mm\n facet", Some(LengthUnit::Millimetre)),
            (
                b"ply\nformat ascii 1.0\ncomment units: meters\nelement vertex 3\nend_header\n",
                Some(LengthUnit::Metre),
            ),
            (b"ply\nformat ascii 1.0\ncomment Unit m\nend_header\n", Some(LengthUnit::Metre)),
            // `m` alone, or an element named like a unit, says nothing.
            (b"ply\nformat ascii 1.0\ncomment made by m scanner\nelement inch 3\nend_header\n", None),
            (b"solid m\nfacet", None),
            (b"Exported from CAD, UNITS = MM\0\0\0\0", Some(LengthUnit::Millimetre)),
            (b"binary header without units\0\0\0\0\0inch after the NUL", None),
            // OBJ, OFF and PCD: their `#` comment lines; vertex data and names say nothing.
            (b"# Blender export\n# units: inches\nmtllib a.mtl\nv 1 2 3\n", Some(LengthUnit::Inch)),
            (b"OFF\n# unit mm\n3 1 0\n", Some(LengthUnit::Millimetre)),
            (b"# .PCD v0.7 - Point Cloud Data file format\n# metres\nVERSION 0.7\n", Some(LengthUnit::Metre)),
            (b"# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z\n", None),
            (b"o inch_bracket\nv 1 2 3\n", None),
        ];
        for (head, want) in cases {
            assert_eq!(header_hint(head).map(|h| h.0), *want, "{}", String::from_utf8_lossy(head));
        }
    }

    #[test]
    fn size_decides_metres_and_warns_where_inches_are_plausible() {
        let d = Units::Auto.decide(b"solid x\n", 0.155);
        assert_eq!((d.unit, d.source, d.scale_to_mm), (LengthUnit::Metre, "size", 1000.0));
        let d = Units::Auto.decide(b"solid x\n", 4.0);
        assert_eq!(d.unit, LengthUnit::Millimetre);
        assert!(d.warning.as_deref().is_some_and(|w| w.contains("input.units")), "{d:?}");
        let d = Units::Auto.decide(b"solid x\n", 80.0);
        assert_eq!((d.unit, d.warning), (LengthUnit::Millimetre, None));
        let d = Units::Given(LengthUnit::Inch).decide(b"solid units mm\n", 0.1);
        assert_eq!((d.unit, d.source, d.scale_to_mm), (LengthUnit::Inch, "given", 25.4));
    }
}
