//! STL, binary and ASCII, read into an indexed [`Mesh`]; [`write_stl`] writes binary STL.
//!
//! Binary: an 80-byte header, a little-endian `u32` triangle count, then 50-byte records (normal,
//! three corners as `f32`, a 2-byte attribute). The count is checked against
//! [`ReadLimits::max_triangles`] and, when the input's size is known, against the size equation
//! `size = 84 + 50·n`; records are decoded a block at a time straight out of the reader's buffer.
//!
//! ASCII: `solid name`, then per facet `facet normal nx ny nz`, `outer loop`, `vertex x y z` (three
//! times), `endloop`, `endfacet`, and finally `endsolid name`. Keywords are matched without regard
//! to case and may be laid out over lines in any way (the parser is a state machine over tokens);
//! the rest of a `solid` or `endsolid` line is the solid's name. Several solids in one file are
//! read into one mesh. A loop of more than three vertices is fan-triangulated. Coordinates are
//! single precision in both encodings, as STL specifies: ASCII values are parsed straight to `f32`,
//! so the ASCII and binary forms of a model weld alike.
//!
//! Welding: corners are merged into one vertex when their coordinates are bit-for-bit equal (a
//! hash map on the `f64` bit patterns; `-0.0` counts as `0.0`). Triangles with a non-finite corner
//! or zero area (edge cross product exactly zero in `f64`, which includes repeated corners) are
//! dropped and counted before welding, so they leave no unused vertices. The facet normals are
//! ignored (the winding gives the orientation).

use std::collections::HashMap;
use std::collections::hash_map::Entry;
use std::io::{BufRead, Write};

use nalgebra::{Point3, Vector3};

use super::error::{FormatError, Location, Result};
use super::{
    InputFormat, Lines, ReadLimits, ReadStats, Src, check_size, io_error, is_space, parse_error, parse_f32,
    show_token, sniff, tokens, too_large,
};
use crate::mesh::Mesh;

/// Writes `mesh` as binary STL: an 80-byte header starting with `header` (cut to 80 bytes), the
/// triangle count, then one record per triangle with its facet normal from the vertex order (the
/// zero vector for a degenerate triangle) and the corners rounded to `f32`, as STL stores them.
///
/// Errors: more than `u32::MAX` triangles ([`FormatError::TooLarge`]) and write failures
/// ([`FormatError::Io`] with file `STL output`).
pub fn write_stl<W: Write>(mut w: W, mesh: &Mesh, header: &str) -> Result<()> {
    let name = "STL output";
    let io = |source| FormatError::Io { file: name.to_string(), source };
    let count = u32::try_from(mesh.triangles.len())
        .map_err(|_| too_large(name, "triangles", mesh.triangles.len() as u64, u64::from(u32::MAX)))?;
    let mut head = [0u8; 80];
    let text = &header.as_bytes()[..header.len().min(80)];
    head[..text.len()].copy_from_slice(text);
    w.write_all(&head).map_err(io)?;
    w.write_all(&count.to_le_bytes()).map_err(io)?;
    let mut buf = Vec::with_capacity(50 * mesh.triangles.len());
    for t in &mesh.triangles {
        let [a, b, c] = t.map(|i| mesh.vertices[i as usize]);
        let nrm = (b - a).cross(&(c - a));
        let nrm = if nrm.norm() > 0.0 { nrm.normalize() } else { Vector3::zeros() };
        for v in [nrm.x, nrm.y, nrm.z, a.x, a.y, a.z, b.x, b.y, b.z, c.x, c.y, c.z] {
            buf.extend_from_slice(&(v as f32).to_le_bytes());
        }
        buf.extend_from_slice(&0u16.to_le_bytes());
    }
    w.write_all(&buf).map_err(io)?;
    w.flush().map_err(io)
}

/// Reads an STL mesh from `r`: ASCII when [`sniff_format`](super::sniff_format) says
/// [`InputFormat::StlAscii`], binary otherwise. `size` (the input's length, when known) enables
/// the size-equation check and exact pre-allocation; `name` names the input in errors.
pub fn read_stl_from<R: BufRead>(
    r: R,
    name: &str,
    size: Option<u64>,
    limits: &ReadLimits,
) -> Result<(Mesh, ReadStats)> {
    check_size(name, size, limits)?;
    let (format, r) = sniff(r, name, size)?;
    let mut src = Src::new(r, limits.max_bytes);
    if format == InputFormat::StlAscii {
        read_stl_ascii_src(&mut src, name, limits)
    } else {
        read_stl_binary_src(&mut src, name, size, limits)
    }
}

/// Merges bit-identical corners into indexed vertices.
struct Welder {
    map: HashMap<[u64; 3], u32>,
    vertices: Vec<Point3<f64>>,
    triangles: Vec<[u32; 3]>,
    dropped: u64,
    max_points: u64,
}

impl Welder {
    fn new(triangles: usize, max_points: u64) -> Self {
        // A closed mesh has about half as many vertices as triangles.
        Welder {
            map: HashMap::with_capacity(triangles / 2 + 1),
            vertices: Vec::with_capacity(triangles / 2 + 1),
            triangles: Vec::with_capacity(triangles),
            dropped: 0,
            max_points,
        }
    }

    /// Adds a triangle, or counts it as dropped (non-finite or zero area).
    #[inline]
    fn add(&mut self, c: [[f64; 3]; 3], name: &str) -> Result<()> {
        if c.iter().flatten().any(|v| !v.is_finite()) {
            self.dropped += 1;
            return Ok(());
        }
        let [a, b, d] = c.map(Point3::from);
        if (b - a).cross(&(d - a)) == Vector3::zeros() {
            self.dropped += 1;
            return Ok(());
        }
        let tri = [self.vertex(c[0], name)?, self.vertex(c[1], name)?, self.vertex(c[2], name)?];
        self.triangles.push(tri);
        Ok(())
    }

    #[inline]
    fn vertex(&mut self, v: [f64; 3], name: &str) -> Result<u32> {
        // `+ 0.0` turns -0.0 into 0.0 and leaves every other value alone.
        let key = v.map(|x| (x + 0.0).to_bits());
        match self.map.entry(key) {
            Entry::Occupied(e) => Ok(*e.get()),
            Entry::Vacant(e) => {
                let i = self.vertices.len() as u64;
                let limit = self.max_points.min(u64::from(u32::MAX));
                if i >= limit {
                    return Err(too_large(name, "points", i + 1, limit));
                }
                self.vertices.push(Point3::from(v));
                e.insert(i as u32);
                Ok(i as u32)
            }
        }
    }

    fn finish(self, format: InputFormat, bytes: u64) -> (Mesh, ReadStats) {
        let mut stats = ReadStats::new(format);
        stats.bytes = bytes;
        stats.points = self.vertices.len() as u64;
        stats.triangles = self.triangles.len() as u64;
        stats.dropped_triangles = self.dropped;
        (Mesh { vertices: self.vertices, triangles: self.triangles }, stats)
    }
}

/// Reads a binary STL from `src` (positioned at its start).
pub(crate) fn read_stl_binary_src<R: BufRead>(
    src: &mut Src<R>,
    name: &str,
    size: Option<u64>,
    limits: &ReadLimits,
) -> Result<(Mesh, ReadStats)> {
    let mut head = [0u8; 84];
    if !src.read_bytes(&mut head).map_err(|e| io_error(name, e))? {
        return Err(parse_error(
            name,
            Location::Byte(src.pos()),
            "binary STL: the file ends inside the 84-byte header",
        ));
    }
    let n = u64::from(u32::from_le_bytes([head[80], head[81], head[82], head[83]]));
    if n > limits.max_triangles {
        return Err(too_large(name, "triangles", n, limits.max_triangles));
    }
    let want = 84 + 50 * n;
    if let Some(size) = size
        && size != want
    {
        return Err(parse_error(
            name,
            Location::Byte(80),
            format!("binary STL: the count {n} needs 84 + 50 × {n} = {want} bytes, but the file has {size}"),
        ));
    }
    let reserve = n.min(if size.is_some() { n } else { 1 << 20 }) as usize;
    let mut w = Welder::new(reserve, limits.max_points);
    let done = src.records(50, n, name, |chunk| {
        for rec in chunk.chunks_exact(50) {
            let f = |k: usize| f64::from(f32::from_le_bytes([rec[k], rec[k + 1], rec[k + 2], rec[k + 3]]));
            let corner = |c: usize| [f(12 + 12 * c), f(16 + 12 * c), f(20 + 12 * c)];
            w.add([corner(0), corner(1), corner(2)], name)?;
        }
        Ok(())
    })?;
    if done < n {
        return Err(parse_error(
            name,
            Location::Byte(src.pos()),
            format!("binary STL: the file ends after {done} of {n} triangles"),
        ));
    }
    Ok(w.finish(InputFormat::StlBinary, src.pos()))
}

/// Where the ASCII parser is: what it expects next.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum State {
    Start,
    Solid,
    Normal,
    NormalValue(usize),
    Outer,
    Loop,
    Vertex,
    Coord(usize),
    EndFacet,
}

impl State {
    fn expected(self) -> &'static str {
        match self {
            State::Start => "\"solid\"",
            State::Solid => "\"facet\" or \"endsolid\"",
            State::Normal => "\"normal\"",
            State::NormalValue(_) => "a normal component",
            State::Outer => "\"outer\"",
            State::Loop => "\"loop\"",
            State::Vertex => "\"vertex\" or \"endloop\"",
            State::Coord(_) => "a vertex coordinate",
            State::EndFacet => "\"endfacet\"",
        }
    }
}

/// Most vertices accepted in one ASCII loop.
const MAX_LOOP: usize = 1024;

/// Reads an ASCII STL from `src` (positioned at its start).
pub(crate) fn read_stl_ascii_src<R: BufRead>(
    src: &mut Src<R>,
    name: &str,
    limits: &ReadLimits,
) -> Result<(Mesh, ReadStats)> {
    let mut lines = Lines::new(0);
    let mut w = Welder::new(1024, limits.max_points);
    let mut state = State::Start;
    let mut solids = 0u64;
    let mut corners: Vec<[f64; 3]> = Vec::with_capacity(3);
    let mut corner = [0f64; 3];
    let mut facets = 0u64;
    'lines: while lines.next(src, name)? {
        let at = Location::Line(lines.line);
        for tok in tokens(&lines.buf, is_space) {
            let is = |word: &str| tok.eq_ignore_ascii_case(word.as_bytes());
            let single = |what: &str| {
                parse_f32(tok).ok_or_else(|| {
                    parse_error(name, at, format!("cannot parse {} as a {what}", show_token(tok)))
                })
            };
            state = match state {
                State::Start if is("solid") => {
                    solids += 1;
                    state = State::Solid;
                    continue 'lines;
                }
                State::Solid if is("facet") => State::Normal,
                State::Solid if is("endsolid") => {
                    state = State::Start;
                    continue 'lines;
                }
                State::Normal if is("normal") => State::NormalValue(0),
                State::NormalValue(k) => {
                    single("normal component")?;
                    if k == 2 { State::Outer } else { State::NormalValue(k + 1) }
                }
                State::Outer if is("outer") => State::Loop,
                State::Loop if is("loop") => {
                    corners.clear();
                    State::Vertex
                }
                State::Vertex if is("vertex") => {
                    if corners.len() == MAX_LOOP {
                        return Err(parse_error(
                            name,
                            at,
                            format!("a loop of more than {MAX_LOOP} vertices"),
                        ));
                    }
                    State::Coord(0)
                }
                State::Vertex if is("endloop") => {
                    if corners.len() < 3 {
                        return Err(parse_error(
                            name,
                            at,
                            format!("a facet of {} vertices; expected 3", corners.len()),
                        ));
                    }
                    facets += corners.len() as u64 - 2;
                    if facets > limits.max_triangles {
                        return Err(too_large(name, "triangles", facets, limits.max_triangles));
                    }
                    for k in 2..corners.len() {
                        w.add([corners[0], corners[k - 1], corners[k]], name)?;
                    }
                    State::EndFacet
                }
                State::Coord(k) => {
                    corner[k] = f64::from(single("vertex coordinate")?);
                    if k == 2 {
                        corners.push(corner);
                        State::Vertex
                    } else {
                        State::Coord(k + 1)
                    }
                }
                State::EndFacet if is("endfacet") => State::Solid,
                _ => {
                    return Err(parse_error(
                        name,
                        at,
                        format!("expected {}, found {}", state.expected(), show_token(tok)),
                    ));
                }
            };
        }
    }
    let end = Location::Line(lines.line.max(1));
    if state != State::Start {
        return Err(parse_error(name, end, format!("the file ends where {} was expected", state.expected())));
    }
    if solids == 0 {
        return Err(parse_error(name, end, "no solid in the file"));
    }
    Ok(w.finish(InputFormat::StlAscii, src.pos()))
}

#[cfg(test)]
mod tests {
    use std::io::Cursor;

    use proptest::prelude::*;

    use super::*;

    /// The 12 triangles of the unit cube, outward-facing.
    fn cube() -> Vec<[[f32; 3]; 3]> {
        let v = |i: usize| [(i & 1) as f32, ((i >> 1) & 1) as f32, ((i >> 2) & 1) as f32];
        let quads = [[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2], [1, 3, 7, 5]];
        quads.iter().flat_map(|q| [[v(q[0]), v(q[1]), v(q[2])], [v(q[0]), v(q[2]), v(q[3])]]).collect()
    }

    fn binary(tris: &[[[f32; 3]; 3]]) -> Vec<u8> {
        let mut out = b"solid binary header that looks like ascii facet".to_vec();
        out.resize(80, b' ');
        out.extend_from_slice(&(tris.len() as u32).to_le_bytes());
        for t in tris {
            out.extend_from_slice(&[0u8; 12]);
            for c in t {
                for v in c {
                    out.extend_from_slice(&v.to_le_bytes());
                }
            }
            out.extend_from_slice(&[0, 0]);
        }
        out
    }

    fn ascii(tris: &[[[f32; 3]; 3]]) -> String {
        let mut s = String::from("solid cube\n");
        for t in tris {
            s.push_str("  facet normal 0 0 0\n    outer loop\n");
            for c in t {
                s.push_str(&format!("      vertex {} {} {}\n", c[0], c[1], c[2]));
            }
            s.push_str("    endloop\n  endfacet\n");
        }
        s + "endsolid cube\n"
    }

    fn read(bytes: &[u8], size: bool) -> Result<(Mesh, ReadStats)> {
        let size = size.then_some(bytes.len() as u64);
        read_stl_from(Cursor::new(bytes.to_vec()), "part.stl", size, &ReadLimits::default())
    }

    fn err(bytes: &[u8]) -> String {
        read(bytes, true).expect_err("malformed").to_string()
    }

    /// Each triangle's corners, as coordinates.
    fn soup(m: &Mesh) -> Vec<[[f64; 3]; 3]> {
        (0..m.triangles.len()).map(|t| m.triangle(t).map(|p| [p.x, p.y, p.z])).collect()
    }

    fn widen(tris: &[[[f32; 3]; 3]]) -> Vec<[[f64; 3]; 3]> {
        tris.iter().map(|t| t.map(|c| c.map(f64::from))).collect()
    }

    #[test]
    fn cube_binary_and_ascii_weld_to_8_vertices() {
        let tris = cube();
        for (bytes, format) in
            [(binary(&tris), InputFormat::StlBinary), (ascii(&tris).into_bytes(), InputFormat::StlAscii)]
        {
            for size in [true, false] {
                let (m, s) = read(&bytes, size).expect("cube");
                assert_eq!((m.vertices.len(), m.triangles.len()), (8, 12), "{format}");
                assert_eq!(soup(&m), widen(&tris));
                assert_eq!((s.format, s.points, s.triangles, s.dropped_triangles), (format, 8, 12, 0));
                assert_eq!(s.bytes, bytes.len() as u64);
            }
        }
    }

    #[test]
    fn degenerate_and_non_finite_triangles_dropped_and_counted() {
        let mut tris = cube();
        tris.push([[0.0; 3], [0.0; 3], [1.0, 0.0, 0.0]]); // repeated corner
        tris.push([[0.0; 3], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]]); // collinear
        tris.push([[f32::NAN, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]);
        tris.push([[0.0; 3], [f32::INFINITY, 0.0, 0.0], [0.0, 1.0, 0.0]]);
        tris.push([[-0.0, 0.0, 0.0], [0.0, 0.0, 5.0], [0.0, 5.0, 0.0]]); // -0.0 welds with 0.0
        for bytes in [binary(&tris), ascii(&tris).into_bytes()] {
            let (m, s) = read(&bytes, true).expect("read");
            assert_eq!((s.triangles, s.dropped_triangles), (13, 4));
            assert_eq!(m.vertices.len(), 10); // 8 cube corners + (0,0,5) + (0,5,0)
            assert_eq!(m.triangles[12][0], m.triangles[0][0]);
        }
    }

    #[test]
    fn ascii_layouts_and_several_solids() {
        let text = "SOLID a b c\nFACET NORMAL 0 0 1 OUTER LOOP\nVERTEX 0 0 0 VERTEX 1 0 0\nvertex 0 1 0 endloop endfacet\r\nendsolid a\n\
                    solid second\nfacet normal 0 0 1\nouter loop\nvertex 0 0 1\nvertex 1 0 1\nvertex 1 1 1\nvertex 0 1 1\nendloop\nendfacet\nendsolid\n";
        let (m, s) = read(text.as_bytes(), false).expect("read");
        assert_eq!((m.vertices.len(), m.triangles.len()), (7, 3)); // the quad is fan-triangulated
        assert_eq!(s.format, InputFormat::StlAscii);
        assert_eq!(m.triangles[1..], [[3, 4, 5], [3, 5, 6]]);
    }

    #[test]
    fn malformed_ascii_names_the_line() {
        let good = ascii(&cube());
        let cases = [
            (
                good.replacen("outer loop", "outer lop", 1),
                "part.stl: line 3: expected \"loop\", found \"lop\"",
            ),
            (
                good.replacen("vertex 0 0 0", "vertex 0 x 0", 1),
                "part.stl: line 4: cannot parse \"x\" as a vertex coordinate",
            ),
            (
                good.replacen("endfacet", "endfacets", 1),
                "part.stl: line 8: expected \"endfacet\", found \"endfacets\"",
            ),
            (
                good.replacen("facet normal 0 0 0", "facet normal 0 0", 1),
                "part.stl: line 3: cannot parse \"outer\" as a normal component",
            ),
            (
                good.lines().take(5).collect::<Vec<_>>().join("\n"),
                "part.stl: line 5: the file ends where \"vertex\" or \"endloop\" was expected",
            ),
            (
                good.replacen("endsolid cube\n", "", 1),
                "part.stl: line 85: the file ends where \"facet\" or \"endsolid\" was expected",
            ),
            (
                "solid x\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 1 1\nendloop\n".to_string(),
                "part.stl: line 6: a facet of 2 vertices; expected 3",
            ),
        ];
        for (text, want) in cases {
            assert_eq!(err(text.as_bytes()), want);
        }
    }

    #[test]
    fn malformed_binary_names_the_byte() {
        let bytes = binary(&cube());
        // Truncated with the size unknown: the byte where it ends and the count.
        let cut = &bytes[..bytes.len() - 60];
        let e = read(cut, false).expect_err("truncated").to_string();
        assert_eq!(
            e,
            format!("part.stl: byte {}: binary STL: the file ends after 10 of 12 triangles", cut.len())
        );
        // With the size known, the size equation catches it up front.
        let e = read_stl_from(
            Cursor::new(cut.to_vec()),
            "part.stl",
            Some(cut.len() as u64),
            &ReadLimits::default(),
        )
        .expect_err("size");
        assert_eq!(
            e.to_string(),
            format!(
                "part.stl: byte 80: binary STL: the count 12 needs 84 + 50 × 12 = 684 bytes, but the file has {}",
                cut.len()
            )
        );
        let e = read(&[0u8; 50], false).expect_err("header").to_string();
        assert_eq!(e, "part.stl: byte 50: binary STL: the file ends inside the 84-byte header");
        let tight = ReadLimits { max_triangles: 11, ..Default::default() };
        let e = read_stl_from(Cursor::new(bytes.clone()), "part.stl", None, &tight).expect_err("limit");
        assert_eq!(e.to_string(), "part.stl: triangles 12 exceeds the limit of 11");
        let tight = ReadLimits { max_points: 7, ..Default::default() };
        let e = read_stl_from(Cursor::new(bytes), "part.stl", None, &tight).expect_err("limit");
        assert_eq!(e.to_string(), "part.stl: points 8 exceeds the limit of 7");
        // A hostile count with no data: an error, not a huge allocation.
        let mut hostile = vec![0u8; 80];
        hostile.extend_from_slice(&u32::MAX.to_le_bytes());
        let generous = ReadLimits { max_triangles: u64::MAX, ..Default::default() };
        let e = read_stl_from(Cursor::new(hostile), "h.stl", None, &generous).expect_err("hostile");
        assert_eq!(
            e.to_string(),
            "h.stl: byte 84: binary STL: the file ends after 0 of 4294967295 triangles"
        );
    }

    /// The slow reference weld: linear search for an equal corner.
    fn reference(tris: &[[[f64; 3]; 3]]) -> (Vec<[f64; 3]>, Vec<[u32; 3]>, u64) {
        let mut verts: Vec<[f64; 3]> = Vec::new();
        let mut out = Vec::new();
        let mut dropped = 0;
        for t in tris {
            let [a, b, c] = t.map(Point3::from);
            let finite = t.iter().flatten().all(|v| v.is_finite());
            if !finite || (b - a).cross(&(c - a)) == Vector3::zeros() {
                dropped += 1;
                continue;
            }
            let mut idx = [0u32; 3];
            for (k, corner) in t.iter().enumerate() {
                idx[k] = match verts.iter().position(|v| v == corner) {
                    Some(i) => i as u32,
                    None => {
                        verts.push(*corner);
                        verts.len() as u32 - 1
                    }
                };
            }
            out.push(idx);
        }
        (verts, out, dropped)
    }

    proptest! {
        #[test]
        fn weld_matches_the_reference(
            picks in prop::collection::vec(prop::array::uniform3(0usize..12), 0..60),
            pool in prop::collection::vec(prop::array::uniform3(prop_oneof![Just(0.0f32), Just(1.0), Just(-2.5), Just(f32::NAN), -10f32..10.0]), 12),
        ) {
            let tris: Vec<[[f32; 3]; 3]> = picks.iter().map(|p| p.map(|i| pool[i])).collect();
            let (m, s) = read(&binary(&tris), true).expect("read");
            let (verts, idx, dropped) = reference(&widen(&tris));
            prop_assert_eq!(m.vertices.iter().map(|p| [p.x, p.y, p.z]).collect::<Vec<_>>(), verts);
            prop_assert_eq!(&m.triangles, &idx);
            prop_assert_eq!(s.dropped_triangles, dropped);
            // The ASCII route agrees.
            let (ma, _) = read(ascii(&tris).as_bytes(), true).expect("ascii");
            prop_assert_eq!(ma, m);
        }
    }
}
