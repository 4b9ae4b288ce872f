//! PLY: reader (ascii, binary little- and big-endian; any scalar type; clouds and meshes) and
//! writer (the scanning service's format).
//!
//! # Reading
//! The header is parsed into elements and properties (`char`/`int8` … `double`/`float64`, and
//! `list <count type> <item type>`); `comment` and `obj_info` lines are skipped. The `vertex`
//! element gives the points: `x y z` (required, any scalar type, kept as `f64`), the intensity
//! from the first property named `intensity`, `scalar_intensity`, `scalar_Intensity` or
//! `reflectance`, normals from `nx ny nz` (all three), and with [`read_ply_cloud_with_pass`] the
//! scan pass from `pass`. Every other property is skipped and listed in
//! [`ReadStats::ignored_properties`]. A non-empty `face` element with a `vertex_indices` (or
//! `vertex_index`) list makes a mesh; faces of more than 3 vertices are fan-triangulated
//! (`v0 v1 v2`, `v0 v2 v3`, …). Elements are read in header order (other elements before the
//! vertices are skipped, their records parsed only as far as needed to know their length);
//! reading stops after the last element needed.
//!
//! Binary vertices whose properties are all scalars have a fixed record layout: per-property
//! offsets are computed once from the header and records are decoded straight out of the reader's
//! buffer, a block at a time, with `from_le_bytes`/`from_be_bytes` (monomorphised per byte order;
//! contiguous `float x y z` and `double x y z` have their own fast decoders). Vertices with list
//! properties, and faces, are parsed field by field. ASCII bodies are read a line (= one element
//! instance) at a time; blank lines are skipped.
//!
//! Locations in errors: header and ASCII body problems give the 1-based line, binary body
//! problems the 0-based byte offset. Element instances are numbered from 0 (as face indices are).
//!
//! # Writing
//! [`write_ply`] writes `float x y z`, `float intensity` when the cloud has it, `float nx ny nz`
//! when it has normals, `ushort pass` when pass ids are given, with the comment
//! `depthmill point cloud`. Coordinates are rounded to `f32` (0.06 µm at 1 m).

use std::io::{BufRead, Write};

use crate::PointCloud;
use nalgebra::Point3;

use super::error::{FormatError, Location, Result};
use super::{
    CloudSink, Geometry, InputFormat, Lines, ReadLimits, ReadStats, Src, Want, io_error, is_space,
    not_a_mesh, parse_error, parse_f32, parse_f64, show_token, tokens, too_large,
};
use crate::mesh::Mesh;

/// Longest PLY header accepted.
pub const MAX_HEADER_LEN: u64 = 1 << 20;

/// Names of the intensity property, any of which is accepted (the first present is used).
pub const INTENSITY_NAMES: [&str; 4] = ["intensity", "scalar_intensity", "scalar_Intensity", "reflectance"];

/// The body encoding of a PLY file.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum PlyEncoding {
    /// `format ascii 1.0`.
    Ascii,
    /// `format binary_little_endian 1.0` (the scanning service's choice).
    BinaryLittleEndian,
    /// `format binary_big_endian 1.0`.
    BinaryBigEndian,
}

impl PlyEncoding {
    /// The header keyword (`ascii`, `binary_little_endian`, `binary_big_endian`).
    pub fn keyword(self) -> &'static str {
        match self {
            PlyEncoding::Ascii => "ascii",
            PlyEncoding::BinaryLittleEndian => "binary_little_endian",
            PlyEncoding::BinaryBigEndian => "binary_big_endian",
        }
    }

    /// The matching [`InputFormat`].
    pub fn input_format(self) -> InputFormat {
        match self {
            PlyEncoding::Ascii => InputFormat::PlyAscii,
            PlyEncoding::BinaryLittleEndian => InputFormat::PlyBinaryLe,
            PlyEncoding::BinaryBigEndian => InputFormat::PlyBinaryBe,
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Writer.

/// Writes `cloud` as PLY: the format the scanning service writes and reconstruction reads
/// (binary little-endian in production). Properties: `float x y z`, `float intensity` if the
/// cloud has intensity, `float nx ny nz` if it has normals, `ushort pass` if `pass` is given (one
/// id per point: the scan pass). Header comments: `comment depthmill point cloud`, then one
/// `comment` line per entry of `extra_comments`. Coordinates are rounded to `f32`. Buffers
/// internally (64 KiB), so `w` need not be buffered; flushes `w` at the end.
///
/// Errors: parallel arrays of the wrong length ([`FormatError::Geometry`]), a `pass` slice of the
/// wrong length or a comment with a line break ([`FormatError::InvalidParameter`]), and write
/// failures ([`FormatError::Io`] with file `PLY output`).
pub fn write_ply<W: Write>(
    w: W,
    cloud: &PointCloud,
    pass: Option<&[u16]>,
    encoding: PlyEncoding,
    extra_comments: &[String],
) -> Result<()> {
    write_ply_labelled(w, cloud, pass.map(|p| ("pass", p)), encoding, extra_comments)
}

/// [`write_ply`] with the per-point `ushort` property named by `label` (`pass` in
/// [`write_ply`]; a lower-case ASCII name) instead of the scan pass.
///
/// Errors: those of [`write_ply`], and a label name that is not lower-case ASCII letters and
/// underscores or is one of the other properties ([`FormatError::InvalidParameter`]).
pub fn write_ply_labelled<W: Write>(
    mut w: W,
    cloud: &PointCloud,
    label: Option<(&str, &[u16])>,
    encoding: PlyEncoding,
    extra_comments: &[String],
) -> Result<()> {
    cloud.validate()?;
    if let Some((name, _)) = label
        && (name.is_empty()
            || !name.bytes().all(|b| b.is_ascii_lowercase() || b == b'_')
            || ["x", "y", "z", "intensity", "nx", "ny", "nz"].contains(&name))
    {
        return Err(FormatError::param(
            "label",
            format!("{name:?}"),
            "a label property is named by lower-case letters and underscores, not as another property",
        ));
    }
    if let Some((name, p)) = label
        && p.len() != cloud.len()
    {
        return Err(FormatError::param(
            name,
            format!("{} ids", p.len()),
            format!("one {name} id per point is needed; the cloud has {} points", cloud.len()),
        ));
    }
    let pass = label.map(|(_, p)| p);
    if let Some(bad) = extra_comments.iter().find(|c| c.contains(['\n', '\r'])) {
        return Err(FormatError::param("extra_comments", format!("{bad:?}"), "a comment must be one line"));
    }
    let io = |source| FormatError::Io { file: "PLY output".to_string(), source };
    let mut head = format!("ply\nformat {} 1.0\ncomment depthmill point cloud\n", encoding.keyword());
    for c in extra_comments {
        head.push_str(&format!("comment {c}\n"));
    }
    head.push_str(&format!(
        "element vertex {}\nproperty float x\nproperty float y\nproperty float z\n",
        cloud.len()
    ));
    if cloud.intensity.is_some() {
        head.push_str("property float intensity\n");
    }
    if cloud.normals.is_some() {
        head.push_str("property float nx\nproperty float ny\nproperty float nz\n");
    }
    if let Some((name, _)) = label {
        head.push_str(&format!("property ushort {name}\n"));
    }
    head.push_str("end_header\n");
    w.write_all(head.as_bytes()).map_err(io)?;

    let mut buf: Vec<u8> = Vec::with_capacity(1 << 16);
    for (i, p) in cloud.points.iter().enumerate() {
        let mut floats = [0f32; 7];
        let mut nf = 3;
        floats[..3].copy_from_slice(&[p.x, p.y, p.z]);
        if let Some(v) = &cloud.intensity {
            floats[nf] = v[i];
            nf += 1;
        }
        if let Some(v) = &cloud.normals {
            floats[nf..nf + 3].copy_from_slice(&[v[i].x, v[i].y, v[i].z]);
            nf += 3;
        }
        let id = pass.map(|p| p[i]);
        match encoding {
            PlyEncoding::Ascii => {
                for (k, f) in floats[..nf].iter().enumerate() {
                    let sep = if k == 0 { "" } else { " " };
                    write!(buf, "{sep}{f}").map_err(io)?;
                }
                if let Some(id) = id {
                    write!(buf, " {id}").map_err(io)?;
                }
                buf.push(b'\n');
            }
            PlyEncoding::BinaryLittleEndian => {
                for f in &floats[..nf] {
                    buf.extend_from_slice(&f.to_le_bytes());
                }
                if let Some(id) = id {
                    buf.extend_from_slice(&id.to_le_bytes());
                }
            }
            PlyEncoding::BinaryBigEndian => {
                for f in &floats[..nf] {
                    buf.extend_from_slice(&f.to_be_bytes());
                }
                if let Some(id) = id {
                    buf.extend_from_slice(&id.to_be_bytes());
                }
            }
        }
        if buf.len() >= (1 << 16) - 128 {
            w.write_all(&buf).map_err(io)?;
            buf.clear();
        }
    }
    w.write_all(&buf).map_err(io)?;
    w.flush().map_err(io)
}

// ---------------------------------------------------------------------------------------------
// Public readers.

/// Reads a PLY cloud or mesh from `r` (a mesh when it has a non-empty face element with a
/// `vertex_indices` list; the vertices' intensity and normals are then not kept). `name` names
/// the input in errors. A `pass` property is skipped (listed as ignored): see
/// [`read_ply_cloud_with_pass`].
pub fn read_ply_from<R: BufRead>(r: R, name: &str, limits: &ReadLimits) -> Result<(Geometry, ReadStats)> {
    let mut src = Src::new(r, limits.max_bytes);
    let opts = Options { want: Want::Any, pass: None, force_var: false, keep: None };
    read_ply_src(&mut src, name, None, limits, opts).map(|o| (o.geometry, o.stats))
}

/// Reads a PLY as a point cloud (faces, if any, are not read) together with its per-point scan
/// pass ids: the `pass` vertex property (any integer type with values in `0..=65535`), `None`
/// when the file has none. The pass ids run parallel to the cloud's points (dropped points drop
/// their id too).
pub fn read_ply_cloud_with_pass<R: BufRead>(
    r: R,
    name: &str,
    limits: &ReadLimits,
) -> Result<(PointCloud, Option<Vec<u16>>, ReadStats)> {
    let mut src = Src::new(r, limits.max_bytes);
    let opts = Options { want: Want::Cloud, pass: Some("pass"), force_var: false, keep: None };
    let out = read_ply_src(&mut src, name, None, limits, opts)?;
    Ok((out.geometry.into_cloud(), out.pass, out.stats))
}

/// [`read_ply_cloud_with_pass`] for the per-point label property named `label` (an integer in
/// `0..=65535`), as [`write_ply_labelled`] writes it.
pub fn read_ply_cloud_with_label<R: BufRead>(
    r: R,
    name: &str,
    label: &'static str,
    limits: &ReadLimits,
) -> Result<(PointCloud, Option<Vec<u16>>, ReadStats)> {
    let mut src = Src::new(r, limits.max_bytes);
    let opts = Options { want: Want::Cloud, pass: Some(label), force_var: false, keep: None };
    let out = read_ply_src(&mut src, name, None, limits, opts)?;
    Ok((out.geometry.into_cloud(), out.pass, out.stats))
}

// ---------------------------------------------------------------------------------------------
// Header.

/// A PLY scalar type.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Scalar {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl Scalar {
    fn from_name(s: &str) -> Option<Scalar> {
        Some(match s {
            "char" | "int8" => Scalar::I8,
            "uchar" | "uint8" => Scalar::U8,
            "short" | "int16" => Scalar::I16,
            "ushort" | "uint16" => Scalar::U16,
            "int" | "int32" => Scalar::I32,
            "uint" | "uint32" => Scalar::U32,
            "float" | "float32" => Scalar::F32,
            "double" | "float64" => Scalar::F64,
            _ => return None,
        })
    }

    fn size(self) -> usize {
        match self {
            Scalar::I8 | Scalar::U8 => 1,
            Scalar::I16 | Scalar::U16 => 2,
            Scalar::I32 | Scalar::U32 | Scalar::F32 => 4,
            Scalar::F64 => 8,
        }
    }

    fn is_float(self) -> bool {
        matches!(self, Scalar::F32 | Scalar::F64)
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Kind {
    Scalar(Scalar),
    List { count: Scalar, item: Scalar },
}

#[derive(Debug, Clone)]
struct Property {
    name: String,
    kind: Kind,
}

impl Property {
    fn scalar(&self) -> Option<Scalar> {
        match self.kind {
            Kind::Scalar(t) => Some(t),
            Kind::List { .. } => None,
        }
    }

    fn is_index_list(&self) -> bool {
        matches!(self.kind, Kind::List { .. })
            && (self.name == "vertex_indices" || self.name == "vertex_index")
    }
}

#[derive(Debug, Clone)]
struct Element {
    name: String,
    count: u64,
    props: Vec<Property>,
    /// Header line that declared it.
    line: u64,
}

impl Element {
    /// Record size when every property is a scalar.
    fn fixed_size(&self) -> Option<usize> {
        self.props.iter().map(|p| p.scalar().map(Scalar::size)).sum()
    }

    /// Smallest binary record: scalars plus list counts.
    fn min_size(&self) -> usize {
        self.props
            .iter()
            .map(|p| match p.kind {
                Kind::Scalar(t) => t.size(),
                Kind::List { count, .. } => count.size(),
            })
            .sum()
    }

    /// "vertices", "faces", "`name` elements".
    fn plural(&self) -> String {
        match self.name.as_str() {
            "vertex" => "vertices".to_string(),
            "face" => "faces".to_string(),
            other => format!("{other} elements"),
        }
    }
}

struct Header {
    encoding: PlyEncoding,
    elements: Vec<Element>,
}

fn read_header<R: BufRead>(src: &mut Src<R>, name: &str, lines: &mut Lines) -> Result<Header> {
    let mut encoding = None;
    let mut elements: Vec<Element> = Vec::new();
    loop {
        if !lines.next(src, name)? {
            let problem = if lines.line == 0 {
                "empty input: not a PLY file"
            } else {
                "the header has no end_header line"
            };
            return Err(parse_error(name, Location::Line(lines.line.max(1)), problem));
        }
        let at = Location::Line(lines.line);
        if src.pos() > MAX_HEADER_LEN {
            return Err(parse_error(name, at, format!("header longer than {MAX_HEADER_LEN} bytes")));
        }
        let Ok(text) = std::str::from_utf8(&lines.buf) else {
            return Err(parse_error(name, at, "header line is not UTF-8 text"));
        };
        let words: Vec<&str> = text.split_ascii_whitespace().collect();
        if lines.line == 1 {
            if words != ["ply"] {
                return Err(parse_error(
                    name,
                    at,
                    format!(
                        "not a PLY file: the first line is {} instead of \"ply\"",
                        show_token(&lines.buf)
                    ),
                ));
            }
            continue;
        }
        match words.first().copied() {
            None | Some("comment") | Some("obj_info") => {}
            Some("format") => {
                if encoding.is_some() {
                    return Err(parse_error(name, at, "second format line"));
                }
                encoding = Some(match words.get(1).copied() {
                    Some("ascii") => PlyEncoding::Ascii,
                    Some("binary_little_endian") => PlyEncoding::BinaryLittleEndian,
                    Some("binary_big_endian") => PlyEncoding::BinaryBigEndian,
                    other => {
                        return Err(parse_error(
                            name,
                            at,
                            format!(
                                "unknown format {:?}; expected ascii, binary_little_endian or binary_big_endian",
                                other.unwrap_or("")
                            ),
                        ));
                    }
                });
                match words.get(2) {
                    Some(v) if (*v == "1" || v.starts_with("1.")) && words.len() == 3 => {}
                    _ => return Err(parse_error(name, at, format!("unsupported format line {text:?}"))),
                }
            }
            Some("element") => {
                let [_, el, count] = words[..] else {
                    return Err(parse_error(
                        name,
                        at,
                        format!("expected `element <name> <count>`, found {text:?}"),
                    ));
                };
                let Ok(count) = count.parse::<u64>() else {
                    return Err(parse_error(
                        name,
                        at,
                        format!(
                            "element {el}: count {} is not a non-negative integer",
                            show_token(count.as_bytes())
                        ),
                    ));
                };
                if elements.iter().any(|e| e.name == el) {
                    return Err(parse_error(name, at, format!("second element named {el:?}")));
                }
                elements.push(Element { name: el.to_string(), count, props: Vec::new(), line: lines.line });
            }
            Some("property") => {
                let Some(elem) = elements.last_mut() else {
                    return Err(parse_error(name, at, "property before any element"));
                };
                let ty = |t: &str| {
                    Scalar::from_name(t).ok_or_else(|| {
                        parse_error(name, at, format!("unknown property type {}", show_token(t.as_bytes())))
                    })
                };
                let (kind, pname) = match words[..] {
                    [_, "list", count, item, pname] => {
                        let count = ty(count)?;
                        if count.is_float() {
                            return Err(parse_error(
                                name,
                                at,
                                format!("list {pname}: the count type must be an integer type"),
                            ));
                        }
                        (Kind::List { count, item: ty(item)? }, pname)
                    }
                    [_, "list", ..] => {
                        return Err(parse_error(
                            name,
                            at,
                            format!(
                                "expected `property list <count type> <item type> <name>`, found {text:?}"
                            ),
                        ));
                    }
                    [_, t, pname] => (Kind::Scalar(ty(t)?), pname),
                    _ => {
                        return Err(parse_error(
                            name,
                            at,
                            format!("expected `property <type> <name>`, found {text:?}"),
                        ));
                    }
                };
                if elem.props.iter().any(|p| p.name == pname) {
                    return Err(parse_error(
                        name,
                        at,
                        format!("second property named {pname:?} in element {}", elem.name),
                    ));
                }
                elem.props.push(Property { name: pname.to_string(), kind });
            }
            Some("end_header") => break,
            Some(other) => {
                return Err(parse_error(
                    name,
                    at,
                    format!("unknown header keyword {}", show_token(other.as_bytes())),
                ));
            }
        }
    }
    let Some(encoding) = encoding else {
        return Err(parse_error(name, Location::Line(lines.line), "the header has no format line"));
    };
    Ok(Header { encoding, elements })
}

// ---------------------------------------------------------------------------------------------
// Reading plan.

/// Internal reading options.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Options {
    pub(crate) want: Want,
    /// Read this per-point label property (`pass`: the scan pass).
    pub(crate) pass: Option<&'static str>,
    /// Decode fixed-layout binary vertices with the field-by-field path (tests compare the two).
    pub(crate) force_var: bool,
    /// Keep a uniform sample of at most this many points (a cloud only).
    pub(crate) keep: Option<usize>,
}

/// Which vertex properties feed which output (property indices).
#[derive(Debug, Clone, Copy)]
struct Plan {
    xyz: [usize; 3],
    intensity: Option<usize>,
    normal: Option<[usize; 3]>,
    pass: Option<usize>,
}

impl Plan {
    fn uses(&self, i: usize) -> bool {
        self.xyz.contains(&i)
            || self.intensity == Some(i)
            || self.normal.is_some_and(|n| n.contains(&i))
            || self.pass == Some(i)
    }
}

fn plan_vertex(elem: &Element, name: &str, attributes: bool, pass: Option<&str>) -> Result<Plan> {
    let find = |want: &str| elem.props.iter().position(|p| p.name == want);
    let scalar_at = |i: usize| -> Result<usize> {
        match elem.props[i].kind {
            Kind::Scalar(_) => Ok(i),
            Kind::List { .. } => Err(parse_error(
                name,
                Location::Line(elem.line),
                format!("property {} of element vertex is a list; expected a scalar", elem.props[i].name),
            )),
        }
    };
    let mut xyz = [0; 3];
    for (k, axis) in ["x", "y", "z"].iter().enumerate() {
        let Some(i) = find(axis) else {
            return Err(parse_error(
                name,
                Location::Line(elem.line),
                format!("element vertex has no property {axis}"),
            ));
        };
        xyz[k] = scalar_at(i)?;
    }
    let scalar = |i: &usize| elem.props[*i].scalar().is_some();
    let intensity = if attributes {
        elem.props.iter().position(|p| INTENSITY_NAMES.contains(&p.name.as_str())).filter(scalar)
    } else {
        None
    };
    let normal = match (find("nx"), find("ny"), find("nz")) {
        (Some(a), Some(b), Some(c)) if attributes && [a, b, c].iter().all(scalar) => Some([a, b, c]),
        _ => None,
    };
    let pass = pass.and_then(|label| find(label).filter(scalar));
    Ok(Plan { xyz, intensity, normal, pass })
}

/// Points to reserve: the announced count, capped by the limit and by what the remaining input
/// can hold (`min_record` bytes per point at least), or by 2^20 when the size is unknown (the
/// arrays then grow as the points arrive).
fn reserve(count: u64, limits: &ReadLimits, size: Option<u64>, pos: u64, min_record: usize) -> usize {
    let cap = match size {
        Some(s) => s.saturating_sub(pos) / (min_record.max(1) as u64),
        None => 1 << 20,
    };
    count.min(limits.max_points).min(cap) as usize
}

/// What [`read_ply_src`] returns.
pub(crate) struct PlyOutput {
    pub(crate) geometry: Geometry,
    pub(crate) pass: Option<Vec<u16>>,
    pub(crate) stats: ReadStats,
}

/// Triangles under construction, in the file's vertex numbering.
struct Faces {
    tris: Vec<[u32; 3]>,
    /// Faces of fewer than 3 vertices.
    short: u64,
    vertex_count: u64,
    max_triangles: u64,
}

impl Faces {
    /// Adds a face of `k` corners read one by one from `next`, fan-triangulated.
    fn add(
        &mut self,
        k: u64,
        mut next: impl FnMut() -> Result<f64>,
        face: u64,
        at: Location,
        name: &str,
    ) -> Result<()> {
        if k < 3 {
            for _ in 0..k {
                next()?;
            }
            self.short += 1;
            return Ok(());
        }
        let total = self.tris.len() as u64 + (k - 2);
        if total > self.max_triangles {
            return Err(too_large(name, "triangles", total, self.max_triangles));
        }
        let n = self.vertex_count;
        let mut index = || -> Result<u32> {
            let v = next()?;
            if v >= 0.0 && v.fract() == 0.0 && v < n as f64 {
                Ok(v as u32)
            } else {
                Err(parse_error(
                    name,
                    at,
                    format!("face {face}: vertex index {v} out of range (the file has {n} vertices)"),
                ))
            }
        };
        let first = index()?;
        let mut prev = index()?;
        for _ in 2..k {
            let v = index()?;
            self.tris.push([first, prev, v]);
            prev = v;
        }
        Ok(())
    }
}

fn list_len(v: f64, what: &str, name: &str, at: Location) -> Result<u64> {
    if v >= 0.0 && v.fract() == 0.0 && v <= u32::MAX as f64 {
        Ok(v as u64)
    } else {
        Err(parse_error(name, at, format!("{what}: invalid list length {v}")))
    }
}

fn pass_id(v: f64, index: u64, name: &str, at: Location) -> Result<u16> {
    if (0.0..=65535.0).contains(&v) && v.fract() == 0.0 {
        Ok(v as u16)
    } else {
        Err(parse_error(name, at, format!("vertex {index}: pass {v} is not an integer in 0..=65535")))
    }
}

fn truncated(name: &str, at: Location, done: u64, elem: &Element) -> FormatError {
    parse_error(name, at, format!("file ends after {done} of {} {}", elem.count, elem.plural()))
}

/// Reads a PLY from `src` (positioned at its start). `size` is the whole input's size if known.
pub(crate) fn read_ply_src<R: BufRead>(
    src: &mut Src<R>,
    name: &str,
    size: Option<u64>,
    limits: &ReadLimits,
    opts: Options,
) -> Result<PlyOutput> {
    let mut lines = Lines::new(0);
    let header = read_header(src, name, &mut lines)?;
    let els = &header.elements;
    let Some(vi) = els.iter().position(|e| e.name == "vertex") else {
        return Err(parse_error(name, Location::Line(lines.line), "the header has no vertex element"));
    };
    let vertex = &els[vi];
    let fi = els.iter().position(|e| e.name == "face");
    let face_list = fi.and_then(|fi| els[fi].props.iter().position(Property::is_index_list));
    let mesh = match (fi, face_list) {
        (Some(fi), Some(_)) => opts.want != Want::Cloud && els[fi].count > 0,
        _ => false,
    };
    if opts.want == Want::Mesh && !mesh {
        return Err(not_a_mesh(
            name,
            "the PLY has no faces (no non-empty face element with a vertex_indices list)",
        ));
    }
    if vertex.count > limits.max_points {
        return Err(too_large(name, "points", vertex.count, limits.max_points));
    }
    if mesh && vertex.count > u64::from(u32::MAX) {
        return Err(too_large(name, "vertices", vertex.count, u64::from(u32::MAX)));
    }
    let (fi, face_list) = match (fi, face_list) {
        (Some(f), Some(l)) if mesh => (f, l),
        _ => (usize::MAX, usize::MAX),
    };
    if mesh && els[fi].count > limits.max_triangles {
        return Err(too_large(name, "faces", els[fi].count, limits.max_triangles));
    }
    let plan = plan_vertex(vertex, name, !mesh, opts.pass)?;

    let mut stats = ReadStats::new(header.encoding.input_format());
    for (ei, e) in els.iter().enumerate() {
        for (pi, p) in e.props.iter().enumerate() {
            if ei == vi && !plan.uses(pi) {
                stats.ignored_properties.push(p.name.clone());
            } else if ei != vi && !(ei == fi && pi == face_list) {
                stats.ignored_properties.push(format!("{}.{}", e.name, p.name));
            }
        }
    }

    let min_record = match header.encoding {
        PlyEncoding::Ascii => 2 * vertex.props.len(),
        _ => vertex.min_size(),
    };
    let keep = if mesh { None } else { opts.keep };
    let reserve = reserve(vertex.count, limits, size, src.pos(), min_record).min(keep.unwrap_or(usize::MAX));
    let mut sink =
        CloudSink::new(plan.intensity.is_some(), plan.normal.is_some(), plan.pass.is_some(), mesh, reserve)
            .sampled(keep);
    let mut faces =
        Faces { tris: Vec::new(), short: 0, vertex_count: vertex.count, max_triangles: limits.max_triangles };
    if mesh {
        faces.tris.reserve(els[fi].count.min(1 << 20) as usize);
    }

    let last = if mesh { vi.max(fi) } else { vi };
    for (ei, elem) in els.iter().enumerate().take(last + 1) {
        let role = if ei == vi {
            Role::Vertex(&plan, &mut sink)
        } else if ei == fi {
            Role::Face(face_list, &mut faces)
        } else {
            Role::Skip
        };
        match header.encoding {
            PlyEncoding::Ascii => read_ascii(src, name, &mut lines, elem, role)?,
            PlyEncoding::BinaryLittleEndian => read_binary::<Le, R>(src, name, elem, role, opts.force_var)?,
            PlyEncoding::BinaryBigEndian => read_binary::<Be, R>(src, name, elem, role, opts.force_var)?,
        }
    }

    stats.bytes = src.pos();
    stats.points = sink.len();
    stats.dropped_non_finite = sink.dropped;
    let dropped_at = sink.dropped_at.take().unwrap_or_default();
    let (geometry, pass) = if mesh {
        let pass = sink.pass.take();
        let vertices = sink.into_vertices();
        let mut tris = faces.tris;
        let dropped = finish_triangles(&vertices, &mut tris, &dropped_at, vertex.count);
        stats.triangles = tris.len() as u64;
        stats.dropped_triangles = dropped + faces.short;
        (Geometry::Mesh(Mesh { vertices, triangles: tris }), pass)
    } else {
        let (cloud, pass) = sink.into_cloud();
        (Geometry::Cloud(cloud), pass)
    };
    Ok(PlyOutput { geometry, pass, stats })
}

/// Renumbers triangles past the dropped vertices (`dropped_at`, ascending input indices) and
/// removes those with a dropped corner, a repeated corner or zero area; returns how many went.
pub(crate) fn finish_triangles(
    points: &[Point3<f64>],
    tris: &mut Vec<[u32; 3]>,
    dropped_at: &[u64],
    count: u64,
) -> u64 {
    let remap: Option<Vec<u32>> = (!dropped_at.is_empty()).then(|| {
        let mut map = Vec::with_capacity(count as usize);
        let mut gone = dropped_at.iter().peekable();
        let mut next = 0u32;
        for i in 0..count {
            if gone.peek() == Some(&&i) {
                gone.next();
                map.push(u32::MAX);
            } else {
                map.push(next);
                next += 1;
            }
        }
        map
    });
    let mut dropped = 0;
    tris.retain_mut(|t| {
        if let Some(map) = &remap {
            for v in t.iter_mut() {
                *v = map[*v as usize];
            }
        }
        let keep = !t.contains(&u32::MAX) && !degenerate(points, *t);
        dropped += u64::from(!keep);
        keep
    });
    dropped
}

/// True for a triangle with a repeated corner or zero area (edge cross product exactly zero).
pub(crate) fn degenerate(points: &[Point3<f64>], [a, b, c]: [u32; 3]) -> bool {
    if a == b || b == c || a == c {
        return true;
    }
    let (pa, pb, pc) = (points[a as usize], points[b as usize], points[c as usize]);
    (pb - pa).cross(&(pc - pa)) == nalgebra::Vector3::zeros()
}

/// What an element is read for.
enum Role<'a> {
    Vertex(&'a Plan, &'a mut CloudSink),
    /// The face element, with the index of its vertex-index list property.
    Face(usize, &'a mut Faces),
    Skip,
}

// ---------------------------------------------------------------------------------------------
// ASCII bodies.

/// Reads the next non-blank line; `false` at the end of the input.
fn next_instance<R: BufRead>(src: &mut Src<R>, name: &str, lines: &mut Lines) -> Result<bool> {
    while lines.next(src, name)? {
        if !lines.buf.iter().all(|&b| is_space(b)) {
            return Ok(true);
        }
    }
    Ok(false)
}

fn parse_typed(tok: &[u8], ty: Scalar) -> Option<f64> {
    match ty {
        Scalar::F32 => parse_f32(tok).map(f64::from),
        _ => parse_f64(tok),
    }
}

fn read_ascii<R: BufRead>(
    src: &mut Src<R>,
    name: &str,
    lines: &mut Lines,
    elem: &Element,
    mut role: Role<'_>,
) -> Result<()> {
    let mut vals = vec![0f64; elem.props.len()];
    for i in 0..elem.count {
        if !next_instance(src, name, lines)? {
            return Err(truncated(name, Location::Line(lines.line), i, elem));
        }
        let at = Location::Line(lines.line);
        if matches!(role, Role::Skip) {
            continue;
        }
        let mut toks = tokens(&lines.buf, is_space);
        let mut next_tok = |prop: &Property| {
            toks.next().ok_or_else(|| {
                parse_error(
                    name,
                    at,
                    format!("{} {i}: the line ends before property {}", elem.name, prop.name),
                )
            })
        };
        let number = |tok: &[u8], ty: Scalar, prop: &Property| {
            parse_typed(tok, ty).ok_or_else(|| {
                parse_error(
                    name,
                    at,
                    format!(
                        "{} {i}: property {}: cannot parse {} as a number",
                        elem.name,
                        prop.name,
                        show_token(tok)
                    ),
                )
            })
        };
        for (pi, prop) in elem.props.iter().enumerate() {
            match (prop.kind, &mut role) {
                (Kind::Scalar(ty), Role::Vertex(plan, _)) => {
                    let tok = next_tok(prop)?;
                    if plan.uses(pi) {
                        vals[pi] = number(tok, ty, prop)?;
                    }
                }
                (Kind::Scalar(_), _) => {
                    next_tok(prop)?;
                }
                (Kind::List { count, item }, role) => {
                    let what = format!("{} {i}: property {}", elem.name, prop.name);
                    let k = list_len(number(next_tok(prop)?, count, prop)?, &what, name, at)?;
                    match role {
                        Role::Face(list, faces) if *list == pi => {
                            faces.add(k, || number(next_tok(prop)?, item, prop), i, at, name)?;
                        }
                        _ => {
                            for _ in 0..k {
                                next_tok(prop)?;
                            }
                        }
                    }
                }
            }
        }
        if toks.next().is_some() {
            return Err(parse_error(
                name,
                at,
                format!("{} {i}: more values than the element's {} properties", elem.name, elem.props.len()),
            ));
        }
        if let Role::Vertex(plan, sink) = &mut role {
            push_vertex(sink, plan, &vals, i, name, at)?;
        }
    }
    Ok(())
}

/// Pushes one vertex from its property values.
#[inline]
fn push_vertex(
    sink: &mut CloudSink,
    plan: &Plan,
    vals: &[f64],
    i: u64,
    name: &str,
    at: Location,
) -> Result<()> {
    let p = plan.xyz.map(|k| vals[k]);
    let intensity = plan.intensity.map_or(0.0, |k| vals[k] as f32);
    let normal = plan.normal.map_or([0.0; 3], |n| n.map(|k| vals[k] as f32));
    let pass = match plan.pass {
        Some(k) => pass_id(vals[k], i, name, at)?,
        None => 0,
    };
    sink.push(p, intensity, normal, pass);
    Ok(())
}

// ---------------------------------------------------------------------------------------------
// Binary bodies.

/// Byte order of a binary body.
trait Order {
    fn u16(b: [u8; 2]) -> u16;
    fn u32(b: [u8; 4]) -> u32;
    fn u64(b: [u8; 8]) -> u64;
}

enum Le {}
enum Be {}

impl Order for Le {
    #[inline(always)]
    fn u16(b: [u8; 2]) -> u16 {
        u16::from_le_bytes(b)
    }
    #[inline(always)]
    fn u32(b: [u8; 4]) -> u32 {
        u32::from_le_bytes(b)
    }
    #[inline(always)]
    fn u64(b: [u8; 8]) -> u64 {
        u64::from_le_bytes(b)
    }
}

impl Order for Be {
    #[inline(always)]
    fn u16(b: [u8; 2]) -> u16 {
        u16::from_be_bytes(b)
    }
    #[inline(always)]
    fn u32(b: [u8; 4]) -> u32 {
        u32::from_be_bytes(b)
    }
    #[inline(always)]
    fn u64(b: [u8; 8]) -> u64 {
        u64::from_be_bytes(b)
    }
}

/// `N` bytes of `rec` from `off` (zeros past the end, which fixed layouts never reach).
#[inline(always)]
fn bytes<const N: usize>(rec: &[u8], off: usize) -> [u8; N] {
    let mut a = [0u8; N];
    if let Some(s) = rec.get(off..off + N) {
        a.copy_from_slice(s);
    }
    a
}

/// The scalar of type `ty` at `off` in `rec`, as `f64` (exact for every PLY type).
#[inline(always)]
fn decode<O: Order>(rec: &[u8], off: usize, ty: Scalar) -> f64 {
    match ty {
        Scalar::I8 => f64::from(bytes::<1>(rec, off)[0] as i8),
        Scalar::U8 => f64::from(bytes::<1>(rec, off)[0]),
        Scalar::I16 => f64::from(O::u16(bytes(rec, off)) as i16),
        Scalar::U16 => f64::from(O::u16(bytes(rec, off))),
        Scalar::I32 => f64::from(O::u32(bytes(rec, off)) as i32),
        Scalar::U32 => f64::from(O::u32(bytes(rec, off))),
        Scalar::F32 => f64::from(f32::from_bits(O::u32(bytes(rec, off)))),
        Scalar::F64 => f64::from_bits(O::u64(bytes(rec, off))),
    }
}

/// As [`decode`], to `f32` (a `float` property without a detour).
#[inline(always)]
fn decode_f32<O: Order>(rec: &[u8], f: Field) -> f32 {
    match f.ty {
        Scalar::F32 => f32::from_bits(O::u32(bytes(rec, f.off))),
        ty => decode::<O>(rec, f.off, ty) as f32,
    }
}

/// A scalar property at a fixed offset of a record.
#[derive(Debug, Clone, Copy)]
struct Field {
    off: usize,
    ty: Scalar,
}

/// A fixed vertex record layout.
#[derive(Debug, Clone, Copy)]
struct Layout {
    rec: usize,
    xyz: [Field; 3],
    intensity: Option<Field>,
    normal: Option<[Field; 3]>,
    pass: Option<Field>,
}

impl Layout {
    /// The layout of an all-scalar element, `None` if it has a list.
    fn new(elem: &Element, plan: &Plan) -> Option<Layout> {
        let mut offs = Vec::with_capacity(elem.props.len());
        let mut off = 0;
        for p in &elem.props {
            offs.push((off, p.scalar()?));
            off += p.scalar()?.size();
        }
        let field = |i: usize| Field { off: offs[i].0, ty: offs[i].1 };
        Some(Layout {
            rec: off,
            xyz: plan.xyz.map(field),
            intensity: plan.intensity.map(field),
            normal: plan.normal.map(|n| n.map(field)),
            pass: plan.pass.map(field),
        })
    }

    /// `x y z` are contiguous scalars of type `ty`.
    fn contiguous(&self, ty: Scalar) -> bool {
        let [x, y, z] = self.xyz;
        [x.ty, y.ty, z.ty] == [ty; 3] && y.off == x.off + ty.size() && z.off == y.off + ty.size()
    }
}

/// How the coordinates of a fixed layout are decoded.
trait Coords {
    fn xyz<O: Order>(rec: &[u8], l: &Layout) -> [f64; 3];
}

/// Contiguous `float x y z`.
enum XyzF32 {}
/// Contiguous `double x y z`.
enum XyzF64 {}
/// Anything else.
enum XyzAny {}

impl Coords for XyzF32 {
    #[inline(always)]
    fn xyz<O: Order>(rec: &[u8], l: &Layout) -> [f64; 3] {
        let b: [u8; 12] = bytes(rec, l.xyz[0].off);
        let f = |k: usize| f64::from(f32::from_bits(O::u32([b[k], b[k + 1], b[k + 2], b[k + 3]])));
        [f(0), f(4), f(8)]
    }
}

impl Coords for XyzF64 {
    #[inline(always)]
    fn xyz<O: Order>(rec: &[u8], l: &Layout) -> [f64; 3] {
        let b: [u8; 24] = bytes(rec, l.xyz[0].off);
        let f = |k: usize| {
            f64::from_bits(O::u64([
                b[k],
                b[k + 1],
                b[k + 2],
                b[k + 3],
                b[k + 4],
                b[k + 5],
                b[k + 6],
                b[k + 7],
            ]))
        };
        [f(0), f(8), f(16)]
    }
}

impl Coords for XyzAny {
    #[inline(always)]
    fn xyz<O: Order>(rec: &[u8], l: &Layout) -> [f64; 3] {
        l.xyz.map(|f| decode::<O>(rec, f.off, f.ty))
    }
}

/// Decodes a block of whole fixed-layout vertex records; `start` is the byte offset of the
/// element's first record (for error locations).
fn decode_block<O: Order, C: Coords>(
    chunk: &[u8],
    l: &Layout,
    sink: &mut CloudSink,
    start: u64,
    name: &str,
) -> Result<()> {
    for rec in chunk.chunks_exact(l.rec) {
        let p = C::xyz::<O>(rec, l);
        let intensity = match l.intensity {
            Some(f) => decode_f32::<O>(rec, f),
            None => 0.0,
        };
        let normal = match l.normal {
            Some(n) => n.map(|f| decode_f32::<O>(rec, f)),
            None => [0.0; 3],
        };
        let pass = match l.pass {
            Some(f) if f.ty == Scalar::U16 => O::u16(bytes(rec, f.off)),
            Some(f) => {
                let index = sink.seen;
                let at = Location::Byte(start + index * l.rec as u64);
                pass_id(decode::<O>(rec, f.off, f.ty), index, name, at)?
            }
            None => 0,
        };
        sink.push(p, intensity, normal, pass);
    }
    Ok(())
}

/// Reads one scalar of type `ty`; `None` at the end of the input.
fn read_value<O: Order, R: BufRead>(src: &mut Src<R>, ty: Scalar, name: &str) -> Result<Option<f64>> {
    let mut b = [0u8; 8];
    let ok = src.read_bytes(&mut b[..ty.size()]).map_err(|e| io_error(name, e))?;
    Ok(ok.then(|| decode::<O>(&b, 0, ty)))
}

fn read_binary<O: Order, R: BufRead>(
    src: &mut Src<R>,
    name: &str,
    elem: &Element,
    role: Role<'_>,
    force_var: bool,
) -> Result<()> {
    match role {
        Role::Vertex(plan, sink) => match Layout::new(elem, plan) {
            Some(layout) if !force_var => {
                let start = src.pos();
                let f32_xyz = layout.contiguous(Scalar::F32);
                let f64_xyz = layout.contiguous(Scalar::F64);
                let done = src.records(layout.rec, elem.count, name, |chunk| {
                    if f32_xyz {
                        decode_block::<O, XyzF32>(chunk, &layout, sink, start, name)
                    } else if f64_xyz {
                        decode_block::<O, XyzF64>(chunk, &layout, sink, start, name)
                    } else {
                        decode_block::<O, XyzAny>(chunk, &layout, sink, start, name)
                    }
                })?;
                if done < elem.count {
                    return Err(truncated(name, Location::Byte(src.pos()), done, elem));
                }
                Ok(())
            }
            _ => read_binary_var::<O, R>(src, name, elem, Role::Vertex(plan, sink)),
        },
        Role::Skip => match elem.fixed_size() {
            Some(size) => {
                let want = elem.count.saturating_mul(size as u64);
                let got = src.skip(want).map_err(|e| io_error(name, e))?;
                if got < want {
                    let done = got / size.max(1) as u64;
                    return Err(truncated(name, Location::Byte(src.pos()), done, elem));
                }
                Ok(())
            }
            None => read_binary_var::<O, R>(src, name, elem, Role::Skip),
        },
        role @ Role::Face(..) => read_binary_var::<O, R>(src, name, elem, role),
    }
}

/// Field-by-field reading of a binary element (records with lists, faces, and the reference
/// path for vertices).
fn read_binary_var<O: Order, R: BufRead>(
    src: &mut Src<R>,
    name: &str,
    elem: &Element,
    mut role: Role<'_>,
) -> Result<()> {
    let mut vals = vec![0f64; elem.props.len()];
    for i in 0..elem.count {
        let at = Location::Byte(src.pos());
        for (pi, prop) in elem.props.iter().enumerate() {
            let end = |src: &Src<R>| truncated(name, Location::Byte(src.pos()), i, elem);
            match prop.kind {
                Kind::Scalar(ty) => {
                    vals[pi] = read_value::<O, R>(src, ty, name)?.ok_or_else(|| end(src))?;
                }
                Kind::List { count, item } => {
                    let what = format!("{} {i}: property {}", elem.name, prop.name);
                    let k = read_value::<O, R>(src, count, name)?.ok_or_else(|| end(src))?;
                    let k = list_len(k, &what, name, at)?;
                    match &mut role {
                        Role::Face(list, faces) if *list == pi => {
                            let mut next = || read_value::<O, R>(src, item, name)?.ok_or_else(|| end(src));
                            faces.add(k, &mut next, i, at, name)?;
                        }
                        _ => {
                            let want = k * item.size() as u64;
                            if src.skip(want).map_err(|e| io_error(name, e))? < want {
                                return Err(end(src));
                            }
                        }
                    }
                }
            }
        }
        if let Role::Vertex(plan, sink) = &mut role {
            push_vertex(sink, plan, &vals, i, name, at)?;
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use std::io::Cursor;

    use nalgebra::Vector3;
    use proptest::prelude::*;
    use rand::rngs::StdRng;
    use rand::{Rng, SeedableRng};

    use super::*;
    use crate::formats::read_any_from;

    const ENCODINGS: [PlyEncoding; 3] =
        [PlyEncoding::Ascii, PlyEncoding::BinaryLittleEndian, PlyEncoding::BinaryBigEndian];

    fn sample_cloud(n: usize, intensity: bool, normals: bool) -> PointCloud {
        let mut rng = StdRng::seed_from_u64(n as u64);
        let points = (0..n)
            .map(|_| {
                Point3::new(
                    rng.random_range(-500.0f32..500.0),
                    rng.random_range(-500.0f32..500.0),
                    rng.random::<f32>() * 1e-3,
                )
            })
            .collect();
        let intensity = intensity.then(|| (0..n).map(|_| rng.random::<f32>() * 4000.0).collect());
        let normals = normals.then(|| {
            (0..n)
                .map(|_| Vector3::new(rng.random(), rng.random(), rng.random::<f32>()).normalize())
                .collect()
        });
        PointCloud { points, intensity, normals }
    }

    fn write(cloud: &PointCloud, pass: Option<&[u16]>, enc: PlyEncoding) -> Vec<u8> {
        let mut out = Vec::new();
        write_ply(&mut out, cloud, pass, enc, &["scan 7".to_string()]).expect("write");
        out
    }

    fn read(bytes: &[u8]) -> Result<(Geometry, ReadStats)> {
        read_ply_from(Cursor::new(bytes.to_vec()), "part.ply", &ReadLimits::default())
    }

    fn read_cloud(bytes: &[u8]) -> (PointCloud, ReadStats) {
        match read(bytes).expect("read") {
            (Geometry::Cloud(c), s) => (c, s),
            (Geometry::Mesh(_), _) => panic!("expected a cloud"),
        }
    }

    fn read_mesh(bytes: &[u8]) -> (Mesh, ReadStats) {
        match read(bytes).expect("read") {
            (Geometry::Mesh(m), s) => (m, s),
            (Geometry::Cloud(_), _) => panic!("expected a mesh"),
        }
    }

    fn err(bytes: &[u8]) -> String {
        read(bytes).expect_err("malformed").to_string()
    }

    #[test]
    fn round_trip_all_encodings_and_attributes() {
        for enc in ENCODINGS {
            for (intensity, normals, with_pass) in
                (0..8).map(|m| (m & 1 != 0, m & 2 != 0, m & 4 != 0)).collect::<Vec<_>>()
            {
                let cloud = sample_cloud(257, intensity, normals);
                let pass: Vec<u16> = (0..257).map(|i| (i * 37 % 65536) as u16).collect();
                let bytes = write(&cloud, with_pass.then_some(&pass[..]), enc);
                let header = String::from_utf8_lossy(&bytes[..200]).into_owned();
                assert!(header.contains("comment depthmill point cloud\ncomment scan 7\n"), "{header}");
                let (got, got_pass, stats) =
                    read_ply_cloud_with_pass(Cursor::new(&bytes), "p.ply", &ReadLimits::default())
                        .expect("read");
                assert_eq!(got, cloud, "{enc:?} {intensity} {normals} {with_pass}");
                assert_eq!(got_pass, with_pass.then(|| pass.clone()));
                assert_eq!(
                    (stats.points, stats.bytes, stats.format),
                    (257, bytes.len() as u64, enc.input_format())
                );
                assert!(stats.ignored_properties.is_empty());
                // The plain reader gives the same cloud and lists `pass` as ignored.
                let (c, s) = read_cloud(&bytes);
                assert_eq!(c, cloud);
                assert_eq!(s.ignored_properties, if with_pass { vec!["pass".to_string()] } else { vec![] });
                // And so does read_any_from, sniffing the encoding.
                let (g, s) = read_any_from(
                    Cursor::new(&bytes),
                    "p.ply",
                    Some(bytes.len() as u64),
                    &ReadLimits::default(),
                )
                .expect("any");
                assert_eq!((g, s.format), (Geometry::Cloud(cloud.clone()), enc.input_format()));
            }
        }
    }

    #[test]
    fn scanning_format_header_is_exact() {
        let cloud = sample_cloud(2, true, true);
        let bytes = write(&cloud, Some(&[1, 2]), PlyEncoding::BinaryLittleEndian);
        let head = "ply\nformat binary_little_endian 1.0\ncomment depthmill point cloud\ncomment scan 7\n\
                    element vertex 2\nproperty float x\nproperty float y\nproperty float z\n\
                    property float intensity\nproperty float nx\nproperty float ny\nproperty float nz\n\
                    property ushort pass\nend_header\n";
        assert_eq!(&bytes[..head.len()], head.as_bytes());
        assert_eq!(bytes.len(), head.len() + 2 * (7 * 4 + 2));
    }

    #[test]
    fn writer_rejects_bad_arguments() {
        let cloud = sample_cloud(3, false, false);
        let e = write_ply(Vec::new(), &cloud, Some(&[1]), PlyEncoding::Ascii, &[]).expect_err("pass");
        assert!(e.to_string().contains("the cloud has 3 points"), "{e}");
        // A label of another name: written under it, read back by it, not taken for the pass.
        let kind = [0u16, 1, 0];
        for enc in [PlyEncoding::Ascii, PlyEncoding::BinaryLittleEndian, PlyEncoding::BinaryBigEndian] {
            let mut bytes = Vec::new();
            write_ply_labelled(&mut bytes, &cloud, Some(("kind", &kind)), enc, &[]).expect("labelled");
            let (got, label, _) =
                read_ply_cloud_with_label(Cursor::new(&bytes), "k.ply", "kind", &ReadLimits::default())
                    .expect("read");
            assert_eq!((got, label), (cloud.clone(), Some(kind.to_vec())), "{enc:?}");
            let (_, pass, _) =
                read_ply_cloud_with_pass(Cursor::new(&bytes), "k.ply", &ReadLimits::default()).expect("read");
            assert_eq!(pass, None);
        }
        for bad in ["", "Kind", "x", "intensity", "a b"] {
            let e = write_ply_labelled(Vec::new(), &cloud, Some((bad, &kind)), PlyEncoding::Ascii, &[])
                .expect_err("bad label");
            assert!(e.to_string().contains("label"), "{e}");
        }
        let e = write_ply_labelled(Vec::new(), &cloud, Some(("kind", &kind[..2])), PlyEncoding::Ascii, &[])
            .expect_err("short");
        assert!(e.to_string().contains("one kind id per point"), "{e}");
        let e =
            write_ply(Vec::new(), &cloud, None, PlyEncoding::Ascii, &["a\nb".into()]).expect_err("comment");
        assert!(e.to_string().contains("one line"), "{e}");
        let mut bad = cloud.clone();
        bad.intensity = Some(vec![1.0]);
        assert!(write_ply(Vec::new(), &bad, None, PlyEncoding::Ascii, &[]).is_err());
    }

    /// A PLY writer for tests: header text plus body bytes.
    fn ply(enc: &str, header: &str, body: &[u8]) -> Vec<u8> {
        let mut v = format!("ply\nformat {enc} 1.0\n{header}end_header\n").into_bytes();
        v.extend_from_slice(body);
        v
    }

    fn le_f64(vals: &[f64]) -> Vec<u8> {
        vals.iter().flat_map(|v| v.to_le_bytes()).collect()
    }

    #[test]
    fn doubles_in_all_encodings() {
        let vals = [0.1, 1e-300, -123_456.789_012_345_67, 2.0f64.powi(60) + 1.0, 7.25, -0.0];
        let header = "element vertex 2\nproperty double x\nproperty double y\nproperty double z\n";
        let le = ply("binary_little_endian", header, &le_f64(&vals));
        let be_body: Vec<u8> = vals.iter().flat_map(|v| v.to_be_bytes()).collect();
        let be = ply("binary_big_endian", header, &be_body);
        let ascii_body =
            format!("{} {} {}\n{} {} {}\n", vals[0], vals[1], vals[2], vals[3], vals[4], vals[5]);
        let ascii = ply("ascii", header, ascii_body.as_bytes());
        // A cloud keeps them in single precision, rounded to nearest.
        let want: Vec<Point3<f32>> =
            [Point3::new(vals[0], vals[1], vals[2]), Point3::new(vals[3], vals[4], vals[5])]
                .iter()
                .map(crate::cloud::single)
                .collect();
        for bytes in [le, be, ascii] {
            let (c, _) = read_cloud(&bytes);
            assert_eq!(c.points, want);
            assert!(c.points[1].z.is_sign_negative());
        }
    }

    #[test]
    fn big_endian_mixed_types() {
        // short x, int y, uchar z, double intensity, float nx ny nz
        let header = "element vertex 1\nproperty short x\nproperty int y\nproperty uchar z\n\
                      property double reflectance\nproperty float nx\nproperty float ny\nproperty float nz\n";
        let mut body = Vec::new();
        body.extend_from_slice(&(-300i16).to_be_bytes());
        body.extend_from_slice(&(-70000i32).to_be_bytes());
        body.push(200);
        body.extend_from_slice(&0.5f64.to_be_bytes());
        for f in [0.0f32, -1.0, 0.0] {
            body.extend_from_slice(&f.to_be_bytes());
        }
        let (c, s) = read_cloud(&ply("binary_big_endian", header, &body));
        assert_eq!(c.points, vec![Point3::new(-300.0, -70000.0, 200.0)]);
        assert_eq!(c.intensity, Some(vec![0.5]));
        assert_eq!(c.normals, Some(vec![Vector3::new(0.0, -1.0, 0.0)]));
        assert_eq!(s.format, InputFormat::PlyBinaryBe);
    }

    #[test]
    fn cloudcompare_style_header() {
        let header = "comment Created by CloudCompare v2.12.4\nobj_info Generated by CloudCompare!\n\
                      element vertex 2\nproperty float x\nproperty float y\nproperty float z\n\
                      property uchar red\nproperty uchar green\nproperty uchar blue\n\
                      property float scalar_Intensity\n";
        let mut body = Vec::new();
        for (p, rgb, i) in
            [([1.0f32, 2.0, 3.0], [255u8, 0, 0], 0.25f32), ([4.0, 5.0, 6.0], [0, 255, 0], 0.75)]
        {
            for f in p {
                body.extend_from_slice(&f.to_le_bytes());
            }
            body.extend_from_slice(&rgb);
            body.extend_from_slice(&i.to_le_bytes());
        }
        let (c, s) = read_cloud(&ply("binary_little_endian", header, &body));
        assert_eq!(c.points, vec![Point3::new(1.0, 2.0, 3.0), Point3::new(4.0, 5.0, 6.0)]);
        assert_eq!(c.intensity, Some(vec![0.25, 0.75]));
        assert_eq!(s.ignored_properties, ["red", "green", "blue"]);
        // ASCII of the same, with a MeshLab-style empty face element: still a cloud.
        let ascii = ply(
            "ascii",
            &format!("{header}element face 0\nproperty list uchar int vertex_indices\n"),
            b"1 2 3 255 0 0 0.25\n\n4 5 6 0 255 0 0.75\n",
        );
        let (c2, s2) = read_cloud(&ascii);
        assert_eq!(c2, c);
        assert_eq!(s2.ignored_properties, ["red", "green", "blue", "face.vertex_indices"]);
    }

    #[test]
    fn intensity_is_the_first_named_property() {
        let header = "element vertex 1\nproperty float x\nproperty float y\nproperty float z\n\
                      property float reflectance\nproperty float intensity\n";
        let (c, s) = read_cloud(&ply("ascii", header, b"0 0 0 1.5 2.5\n"));
        assert_eq!(c.intensity, Some(vec![1.5]));
        assert_eq!(s.ignored_properties, ["intensity"]);
        // Only two of the three normal components: no normals, both listed.
        let header = "element vertex 1\nproperty float x\nproperty float y\nproperty float z\n\
                      property float nx\nproperty float ny\n";
        let (c, s) = read_cloud(&ply("ascii", header, b"0 0 0 1 0\n"));
        assert_eq!((c.normals, s.ignored_properties), (None, vec!["nx".to_string(), "ny".to_string()]));
    }

    #[test]
    fn other_elements_before_and_after_the_vertices_are_skipped() {
        // A fixed-size element, a variable-size one (with a list), then vertices, then junk.
        let header = "element camera 2\nproperty float view_px\nproperty double view_py\n\
                      element material 2\nproperty list uchar float coeffs\nproperty uchar id\n\
                      element vertex 2\nproperty float x\nproperty float y\nproperty list uint8 int32 tags\nproperty float z\n\
                      element tail 1000000\nproperty double junk\n";
        for enc in ["binary_little_endian", "ascii"] {
            let body: Vec<u8> = if enc == "ascii" {
                b"1 2\n3 4\n2 0.5 0.25 7\n0 9\n1 2 0 3\n4 5 3 9 9 9 6\n".to_vec()
            } else {
                let mut b = Vec::new();
                for _ in 0..2 {
                    b.extend_from_slice(&1f32.to_le_bytes());
                    b.extend_from_slice(&2f64.to_le_bytes());
                }
                b.push(2);
                b.extend_from_slice(&0.5f32.to_le_bytes());
                b.extend_from_slice(&0.25f32.to_le_bytes());
                b.push(7);
                b.push(0);
                b.push(9);
                for (x, y, tags, z) in [(1f32, 2f32, vec![], 3f32), (4.0, 5.0, vec![9i32, 9, 9], 6.0)] {
                    b.extend_from_slice(&x.to_le_bytes());
                    b.extend_from_slice(&y.to_le_bytes());
                    b.push(tags.len() as u8);
                    for t in tags {
                        b.extend_from_slice(&t.to_le_bytes());
                    }
                    b.extend_from_slice(&z.to_le_bytes());
                }
                b
            };
            let bytes = ply(enc, header, &body);
            let (c, s) = read_cloud(&bytes);
            assert_eq!(c.points, vec![Point3::new(1.0, 2.0, 3.0), Point3::new(4.0, 5.0, 6.0)], "{enc}");
            assert_eq!(
                s.ignored_properties,
                ["camera.view_px", "camera.view_py", "material.coeffs", "material.id", "tags", "tail.junk"]
            );
            // Reading stopped after the vertices: the million-record tail is not there at all.
            assert_eq!(s.bytes, bytes.len() as u64);
        }
    }

    fn cube_ply(enc: &str) -> Vec<u8> {
        // 8 corners and 6 quads (fan-triangulated to 12 triangles), each face with an extra
        // property before its index list.
        let corners =
            [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]];
        let quads: [[i32; 4]; 6] =
            [[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]];
        let header = "element vertex 8\nproperty float x\nproperty float y\nproperty float z\n\
                      element face 6\nproperty uchar flags\nproperty list uchar int vertex_indices\n";
        let mut body = Vec::new();
        if enc == "ascii" {
            for c in corners {
                body.extend_from_slice(format!("{} {} {}\n", c[0], c[1], c[2]).as_bytes());
            }
            for q in quads {
                body.extend_from_slice(format!("0 4 {} {} {} {}\n", q[0], q[1], q[2], q[3]).as_bytes());
            }
        } else {
            let be = enc == "binary_big_endian";
            for c in corners {
                for v in c {
                    let f = v as f32;
                    body.extend_from_slice(&if be { f.to_be_bytes() } else { f.to_le_bytes() });
                }
            }
            for q in quads {
                body.extend_from_slice(&[0, 4]);
                for v in q {
                    body.extend_from_slice(&if be { v.to_be_bytes() } else { v.to_le_bytes() });
                }
            }
        }
        ply(enc, header, &body)
    }

    #[test]
    fn face_lists_make_a_mesh() {
        for enc in ["ascii", "binary_little_endian", "binary_big_endian"] {
            let (m, s) = read_mesh(&cube_ply(enc));
            assert_eq!((m.vertices.len(), m.triangles.len()), (8, 12), "{enc}");
            assert_eq!(m.triangles[0], [0, 3, 2]);
            assert_eq!(m.triangles[1], [0, 2, 1]);
            assert_eq!((s.triangles, s.dropped_triangles, s.points), (12, 0, 8));
            assert_eq!(s.ignored_properties, ["face.flags"]);
            // Wanted as a cloud, the faces are not read.
            let bytes = cube_ply(enc);
            let (c, _, s) = read_ply_cloud_with_pass(Cursor::new(&bytes), "cube.ply", &ReadLimits::default())
                .expect("cloud");
            assert_eq!((c.len(), s.triangles), (8, 0));
            assert!(s.ignored_properties.contains(&"face.vertex_indices".to_string()));
        }
    }

    #[test]
    fn face_variants_and_degenerate_faces() {
        // Faces before vertices, `vertex_index` with uint8/int32 names, a NaN vertex, a repeated
        // corner, a collinear triangle and a 2-vertex face.
        let header = "element face 5\nproperty list uint8 int32 vertex_index\n\
                      element vertex 5\nproperty float x\nproperty float y\nproperty float z\n";
        let body = "3 0 1 2\n3 0 1 3\n3 0 0 2\n3 0 1 4\n2 1 2\n\
                    0 0 0\n1 0 0\n0 1 0\nnan 0 0\n2 0 0\n";
        let (m, s) = read_mesh(&ply("ascii", header, body.as_bytes()));
        assert_eq!(m.vertices.len(), 4);
        assert_eq!(m.vertices[3], Point3::new(2.0, 0.0, 0.0));
        assert_eq!(m.triangles, vec![[0, 1, 2]]);
        assert_eq!((s.points, s.dropped_non_finite, s.triangles, s.dropped_triangles), (4, 1, 1, 4));
    }

    #[test]
    fn non_finite_binary_points_dropped_and_counted() {
        let cloud = PointCloud {
            points: vec![
                Point3::new(1.0, 2.0, 3.0),
                Point3::new(f32::NAN, 0.0, 0.0),
                Point3::new(0.0, f32::INFINITY, 0.0),
                Point3::new(4.0, 5.0, 6.0),
                Point3::new(7.0, 8.0, 9.0),
            ],
            intensity: Some(vec![1.0, 1.0, 1.0, f32::NAN, 2.0]),
            normals: Some(vec![
                Vector3::z(),
                Vector3::z(),
                Vector3::z(),
                Vector3::z(),
                Vector3::new(f32::NAN, 0.0, 0.0),
            ]),
        };
        for enc in ENCODINGS {
            let (c, s) = read_cloud(&write(&cloud, None, enc));
            assert_eq!(c.points, vec![Point3::new(1.0, 2.0, 3.0), Point3::new(7.0, 8.0, 9.0)], "{enc:?}");
            assert_eq!(c.intensity, Some(vec![1.0, 2.0]));
            assert_eq!(c.normals, Some(vec![Vector3::z(), Vector3::zeros()]));
            assert_eq!((s.points, s.dropped_non_finite), (2, 3));
        }
    }

    #[test]
    fn truncated_binary_names_the_byte_and_the_count() {
        let cloud = sample_cloud(10, true, false);
        let bytes = write(&cloud, None, PlyEncoding::BinaryLittleEndian);
        let head = bytes.len() - 160;
        let cut = &bytes[..bytes.len() - 20];
        assert_eq!(err(cut), format!("part.ply: byte {}: file ends after 8 of 10 vertices", head + 140));
        // Big-endian faces.
        let cube = cube_ply("binary_big_endian");
        let e = err(&cube[..cube.len() - 3]);
        assert_eq!(e, format!("part.ply: byte {}: file ends after 5 of 6 faces", cube.len() - 3));
        // ASCII: the last line.
        let e = err(&ply(
            "ascii",
            "element vertex 3\nproperty float x\nproperty float y\nproperty float z\n",
            b"1 2 3\n",
        ));
        assert_eq!(e, "part.ply: line 8: file ends after 1 of 3 vertices");
    }

    #[test]
    fn malformed_headers() {
        let xyz = "element vertex 1\nproperty float x\nproperty float y\nproperty float z\n";
        let cases: Vec<(Vec<u8>, &str)> = vec![
            (
                b"plx\n".to_vec(),
                "part.ply: line 1: not a PLY file: the first line is \"plx\" instead of \"ply\"",
            ),
            (b"".to_vec(), "part.ply: line 1: empty input: not a PLY file"),
            (
                b"ply\nelement vertex 1\nend_header\n".to_vec(),
                "part.ply: line 3: the header has no format line",
            ),
            (
                b"ply\nformat ascii 1.0\nelement vertex 1\n".to_vec(),
                "part.ply: line 3: the header has no end_header line",
            ),
            (
                ply("binary_middle_endian", xyz, b""),
                "part.ply: line 2: unknown format \"binary_middle_endian\"; expected ascii, binary_little_endian or binary_big_endian",
            ),
            (ply("ascii", "property float x\n", b""), "part.ply: line 3: property before any element"),
            (
                ply("ascii", "element vertex -1\n", b""),
                "part.ply: line 3: element vertex: count \"-1\" is not a non-negative integer",
            ),
            (
                ply("ascii", "element vertex 1\nproperty flt x\n", b""),
                "part.ply: line 4: unknown property type \"flt\"",
            ),
            (
                ply("ascii", "element vertex 1\nproperty list float int x\n", b""),
                "part.ply: line 4: list x: the count type must be an integer type",
            ),
            (
                ply("ascii", "element vertex 1\nproperty float\n", b""),
                "part.ply: line 4: expected `property <type> <name>`, found \"property float\"",
            ),
            (
                ply("ascii", "element vertex 1\nproperty float x\nproperty float x\n", b""),
                "part.ply: line 5: second property named \"x\" in element vertex",
            ),
            (ply("ascii", "elephant 3\n", b""), "part.ply: line 3: unknown header keyword \"elephant\""),
            (ply("ascii", "element face 0\n", b""), "part.ply: line 4: the header has no vertex element"),
            (
                ply("ascii", "element vertex 1\nproperty float x\nproperty float y\n", b"1 2\n"),
                "part.ply: line 3: element vertex has no property z",
            ),
            (
                ply(
                    "ascii",
                    "element vertex 1\nproperty float x\nproperty float y\nproperty list uchar float z\n",
                    b"",
                ),
                "part.ply: line 3: property z of element vertex is a list; expected a scalar",
            ),
        ];
        for (bytes, want) in cases {
            assert_eq!(err(&bytes), want);
        }
        let mut huge = b"ply\nformat ascii 1.0\n".to_vec();
        while huge.len() < (MAX_HEADER_LEN + 100) as usize {
            huge.extend_from_slice(b"comment padding padding padding padding padding\n");
        }
        assert!(err(&huge).contains(&format!("header longer than {MAX_HEADER_LEN} bytes")));
    }

    #[test]
    fn malformed_bodies() {
        let xyz = "element vertex 2\nproperty float x\nproperty float y\nproperty float z\n";
        assert_eq!(
            err(&ply("ascii", xyz, b"1 2 3\n1 2 zz\n")),
            "part.ply: line 9: vertex 1: property z: cannot parse \"zz\" as a number"
        );
        assert_eq!(
            err(&ply("ascii", xyz, b"1 2 3\n1 2\n")),
            "part.ply: line 9: vertex 1: the line ends before property z"
        );
        assert_eq!(
            err(&ply("ascii", xyz, b"1 2 3 4\n")),
            "part.ply: line 8: vertex 0: more values than the element's 3 properties"
        );
        let faces = format!("{xyz}element face 1\nproperty list uchar int vertex_indices\n");
        assert_eq!(
            err(&ply("ascii", &faces, b"0 0 0\n1 1 1\n3 0 1 2\n")),
            "part.ply: line 12: face 0: vertex index 2 out of range (the file has 2 vertices)"
        );
        let pass =
            "element vertex 1\nproperty float x\nproperty float y\nproperty float z\nproperty int pass\n";
        let e = read_ply_cloud_with_pass(
            Cursor::new(ply("ascii", pass, b"0 0 0 70000\n")),
            "p.ply",
            &ReadLimits::default(),
        )
        .expect_err("pass");
        assert_eq!(e.to_string(), "p.ply: line 9: vertex 0: pass 70000 is not an integer in 0..=65535");
        // Binary: the byte offset of the vertex's record (the second one here).
        let mut body = vec![0u8; 12];
        body.extend_from_slice(&7i32.to_le_bytes());
        body.extend_from_slice(&[0u8; 12]);
        body.extend_from_slice(&(-1i32).to_le_bytes());
        let pass2 = pass.replace("vertex 1", "vertex 2");
        let bytes = ply("binary_little_endian", &pass2, &body);
        let e =
            read_ply_cloud_with_pass(Cursor::new(&bytes), "p.ply", &ReadLimits::default()).expect_err("pass");
        let at = bytes.len() - 16;
        assert_eq!(
            e.to_string(),
            format!("p.ply: byte {at}: vertex 1: pass -1 is not an integer in 0..=65535")
        );
    }

    #[test]
    fn counts_beyond_the_limits() {
        let xyz = "property float x\nproperty float y\nproperty float z\n";
        let hostile = ply("binary_little_endian", &format!("element vertex 1000000000000\n{xyz}"), &[0; 12]);
        assert_eq!(err(&hostile), "part.ply: points 1000000000000 exceeds the limit of 200000000");
        // Within a generous limit, the count is still not trusted for allocation: the reader
        // reserves what the input can hold and reports the truncation.
        let generous = ReadLimits { max_points: u64::MAX, ..Default::default() };
        let e = read_ply_from(Cursor::new(hostile.clone()), "h.ply", &generous).expect_err("truncated");
        assert!(e.to_string().ends_with("file ends after 1 of 1000000000000 vertices"), "{e}");
        let e = read_any_from(Cursor::new(&hostile), "h.ply", Some(hostile.len() as u64), &generous)
            .expect_err("t");
        assert!(e.to_string().ends_with("file ends after 1 of 1000000000000 vertices"), "{e}");
        let faces = ply(
            "ascii",
            &format!("element vertex 3\n{xyz}element face 100\nproperty list uchar int vertex_indices\n"),
            b"",
        );
        let tight = ReadLimits { max_triangles: 10, ..Default::default() };
        let e = read_ply_from(Cursor::new(faces), "f.ply", &tight).expect_err("faces");
        assert_eq!(e.to_string(), "f.ply: faces 100 exceeds the limit of 10");
        // A single huge face.
        let big_face = ply(
            "ascii",
            &format!("element vertex 3\n{xyz}element face 1\nproperty list uint int vertex_indices\n"),
            b"0 0 0\n1 0 0\n0 1 0\n4000000000 0 1 2\n",
        );
        let e = read_ply_from(Cursor::new(big_face), "f.ply", &tight).expect_err("big face");
        assert_eq!(e.to_string(), "f.ply: triangles 3999999998 exceeds the limit of 10");
        let bytes = write(&sample_cloud(100, false, false), None, PlyEncoding::BinaryLittleEndian);
        let small = ReadLimits { max_bytes: 1000, ..Default::default() };
        let e = read_ply_from(Cursor::new(bytes), "b.ply", &small).expect_err("bytes");
        assert_eq!(e.to_string(), "b.ply: bytes 1001 exceeds the limit of 1000");
    }

    /// A random PLY: random scalar types for x y z and the attributes, random extra properties
    /// (scalars and, in the vertex element, possibly lists, which force the field-by-field path),
    /// random elements around the vertices, random encoding; with the values it holds.
    #[derive(Debug, Clone)]
    struct Random {
        bytes: Vec<u8>,
        points: Vec<[f64; 3]>,
        intensity: Option<Vec<f32>>,
        normals: Option<Vec<[f32; 3]>>,
    }

    const TYPES: [&str; 8] = ["char", "uchar", "short", "ushort", "int", "uint", "float", "double"];

    /// A value exactly representable in type `t` (index into TYPES).
    fn value_for(t: usize, rng: &mut StdRng) -> f64 {
        match t {
            0 => f64::from(rng.random::<i8>()),
            1 => f64::from(rng.random::<u8>()),
            2 => f64::from(rng.random::<i16>()),
            3 => f64::from(rng.random::<u16>()),
            4 => f64::from(rng.random::<i32>()),
            5 => f64::from(rng.random::<u32>()),
            6 => f64::from(rng.random_range(-1e4f32..1e4)),
            _ => rng.random_range(-1e4..1e4),
        }
    }

    fn encode(t: usize, v: f64, enc: usize, out: &mut Vec<u8>) {
        macro_rules! put {
            ($x:expr) => {
                match enc {
                    1 => out.extend_from_slice(&$x.to_le_bytes()),
                    2 => out.extend_from_slice(&$x.to_be_bytes()),
                    _ => out.extend_from_slice(format!("{} ", $x).as_bytes()),
                }
            };
        }
        match t {
            0 => put!(v as i8),
            1 => put!(v as u8),
            2 => put!(v as i16),
            3 => put!(v as u16),
            4 => put!(v as i32),
            5 => put!(v as u32),
            6 => put!(v as f32),
            _ => put!(v),
        }
    }

    fn random_ply(seed: u64) -> Random {
        let mut rng = StdRng::seed_from_u64(seed);
        let enc = rng.random_range(0..3usize);
        let n = rng.random_range(0..60usize);
        // Vertex properties: (name, type, is_list)
        let mut props: Vec<(String, usize, bool)> =
            ["x", "y", "z"].iter().map(|a| (a.to_string(), rng.random_range(0..8), false)).collect();
        let with_i = rng.random_bool(0.5);
        let with_n = rng.random_bool(0.5);
        if with_i {
            props.push((INTENSITY_NAMES[rng.random_range(0..4)].to_string(), rng.random_range(6..8), false));
        }
        if with_n {
            for a in ["nx", "ny", "nz"] {
                props.push((a.to_string(), 6, false));
            }
        }
        for k in 0..rng.random_range(0..3) {
            props.push((format!("extra{k}"), rng.random_range(0..8), rng.random_bool(0.3)));
        }
        // Shuffle.
        for i in (1..props.len()).rev() {
            let j = rng.random_range(0..=i);
            props.swap(i, j);
        }
        let mut header = String::new();
        let mut body = Vec::new();
        let before = rng.random_bool(0.5);
        let other = |header: &mut String, body: &mut Vec<u8>, rng: &mut StdRng| {
            let m = rng.random_range(0..4);
            header
                .push_str(&format!("element other {m}\nproperty list uchar short ids\nproperty double w\n"));
            for _ in 0..m {
                let k = rng.random_range(0..4u8);
                encode(1, f64::from(k), enc, body);
                for _ in 0..k {
                    encode(2, value_for(2, rng), enc, body);
                }
                encode(7, value_for(7, rng), enc, body);
                if enc == 0 {
                    body.push(b'\n');
                }
            }
        };
        if before {
            other(&mut header, &mut body, &mut rng);
        }
        header.push_str(&format!("element vertex {n}\n"));
        for (name, t, list) in &props {
            if *list {
                header.push_str(&format!("property list uchar {} {name}\n", TYPES[*t]));
            } else {
                header.push_str(&format!("property {} {name}\n", TYPES[*t]));
            }
        }
        let mut r = Random {
            bytes: Vec::new(),
            points: Vec::new(),
            intensity: with_i.then(Vec::new),
            normals: with_n.then(Vec::new),
        };
        for _ in 0..n {
            let mut p = [0.0; 3];
            let mut nrm = [0.0f32; 3];
            for (name, t, list) in &props {
                if *list {
                    let k = rng.random_range(0..3u8);
                    encode(1, f64::from(k), enc, &mut body);
                    for _ in 0..k {
                        encode(*t, value_for(*t, &mut rng), enc, &mut body);
                    }
                    continue;
                }
                let v = value_for(*t, &mut rng);
                encode(*t, v, enc, &mut body);
                match name.as_str() {
                    "x" => p[0] = v,
                    "y" => p[1] = v,
                    "z" => p[2] = v,
                    "nx" => nrm[0] = v as f32,
                    "ny" => nrm[1] = v as f32,
                    "nz" => nrm[2] = v as f32,
                    s if INTENSITY_NAMES.contains(&s) => {
                        if let Some(i) = &mut r.intensity {
                            i.push(v as f32)
                        }
                    }
                    _ => {}
                }
            }
            if enc == 0 {
                body.push(b'\n');
            }
            r.points.push(p);
            if let Some(ns) = &mut r.normals {
                ns.push(nrm);
            }
        }
        if !before {
            other(&mut header, &mut body, &mut rng);
        }
        let enc_name = ["ascii", "binary_little_endian", "binary_big_endian"][enc];
        r.bytes = ply(enc_name, &header, &body);
        r
    }

    #[test]
    fn random_layouts_match_the_values_written() {
        for seed in 0..300 {
            let r = random_ply(seed);
            let (c, s) = read_cloud(&r.bytes);
            let got: Vec<[f32; 3]> = c.points.iter().map(|p| [p.x, p.y, p.z]).collect();
            let want: Vec<[f32; 3]> = r.points.iter().map(|p| p.map(|v| v as f32)).collect();
            assert_eq!(got, want, "seed {seed}");
            assert_eq!(c.intensity, r.intensity, "seed {seed}");
            assert_eq!(
                c.normals,
                r.normals.map(|v| v.iter().map(|n| Vector3::new(n[0], n[1], n[2])).collect())
            );
            assert_eq!(s.points as usize, r.points.len());
            // The block decoder and the field-by-field reference agree.
            let opts = Options { want: Want::Any, pass: None, force_var: true, keep: None };
            let mut src = Src::new(Cursor::new(&r.bytes), u64::MAX);
            let slow = read_ply_src(&mut src, "r.ply", None, &ReadLimits::default(), opts).expect("slow");
            assert_eq!(slow.geometry, Geometry::Cloud(c), "seed {seed}");
            assert_eq!(slow.stats, s);
        }
    }

    #[test]
    fn tiny_reader_buffers_split_records() {
        // Records straddling every possible buffer boundary decode the same.
        let cloud = sample_cloud(50, true, true);
        let bytes = write(&cloud, None, PlyEncoding::BinaryBigEndian);
        for cap in [1, 3, 7, 13, 64] {
            let r = std::io::BufReader::with_capacity(cap, Cursor::new(&bytes));
            let (g, _) = read_ply_from(r, "s.ply", &ReadLimits::default()).expect("read");
            assert_eq!(g, Geometry::Cloud(cloud.clone()), "cap {cap}");
        }
    }

    proptest! {
        #[test]
        fn mutated_plys_never_panic(seed in 0u64..1000, flips in prop::collection::vec((any::<usize>(), any::<u8>()), 1..8),
                                    cut in any::<usize>()) {
            let mut bytes = random_ply(seed).bytes;
            for (at, b) in flips {
                let n = bytes.len();
                bytes[at % n] = b;
            }
            bytes.truncate(cut % (bytes.len() + 1));
            let limits = ReadLimits { max_points: 100_000, max_triangles: 100_000, max_bytes: 1 << 20 };
            let _ = read_ply_from(Cursor::new(bytes), "m.ply", &limits);
        }
    }
}
