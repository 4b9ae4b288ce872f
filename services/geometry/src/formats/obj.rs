//! Wavefront OBJ, the geometry of it: `v x y z` vertices and `f` faces.
//!
//! A face's corners are `i`, `i/t`, `i//n` or `i/t/n`; only the vertex index `i` is used:
//! 1-based, or negative for relative to the last vertex defined (`-1` is the last). Faces of more
//! than three corners are fan-triangulated; faces of fewer and degenerate triangles are dropped and
//! counted, as are non-finite vertices and the faces that use them. Extra vertex values (`w`, or
//! the colours some writers append) are ignored. Every other statement (`vt`, `vn`, `o`, `g`, `s`,
//! `usemtl`, `mtllib`, `l`, `p`, free-form geometry) is skipped and its keyword listed in
//! [`ReadStats::ignored_properties`]. `#` starts a comment; a line continued with `\` is joined to
//! the next. An OBJ without faces is a point cloud (scanners export vertex-only OBJ).
//! Errors name the line: a coordinate or index that does not parse, a vertex with fewer than three
//! coordinates, a zero index, an index out of range (checked at the end, so forward references
//! work), a file that is not OBJ.

use std::io::BufRead;

use super::error::{Location, Result};
use super::polygon::PolygonSink;
use super::{
    Geometry, InputFormat, Lines, MAX_LINE_LEN, ReadLimits, ReadStats, Src, before_comment, is_space,
    parse_error, parse_f64, show_token, tokens,
};

/// OBJ statements a file may start with (after comments), for sniffing.
pub(crate) const OBJ_KEYWORDS: [&[u8]; 14] =
    [b"v", b"vt", b"vn", b"vp", b"f", b"o", b"g", b"s", b"l", b"p", b"mtllib", b"usemtl", b"cstype", b"deg"];

/// Most distinct skipped keywords listed in the statistics.
const MAX_IGNORED: usize = 32;

pub(crate) fn read_obj_src<R: BufRead>(
    src: &mut Src<R>,
    name: &str,
    limits: &ReadLimits,
    cloud: bool,
    keep: Option<usize>,
) -> Result<(Geometry, ReadStats)> {
    let mut lines = Lines::new(0);
    let mut sink = PolygonSink::new(cloud, limits, keep.unwrap_or(1 << 16).min(1 << 16), keep);
    let mut ignored: Vec<String> = Vec::new();
    let mut corners: Vec<u32> = Vec::new();
    // The largest vertex index a face used (0-based) and its line: checked against the vertex
    // count at the end.
    let mut highest: Option<(u32, u64)> = None;
    // A line continued with `\`, and the line it started on.
    let mut joined: Vec<u8> = Vec::new();
    let mut start = 0u64;
    while lines.next(src, name)? {
        let owned: Vec<u8>;
        let buf: &[u8] = if let Some(head) = lines.buf.strip_suffix(b"\\") {
            if joined.is_empty() {
                start = lines.line;
            }
            joined.extend_from_slice(head);
            joined.push(b' ');
            if joined.len() > MAX_LINE_LEN {
                return Err(parse_error(
                    name,
                    Location::Line(start),
                    format!("a line continued with \\ grows longer than {MAX_LINE_LEN} bytes"),
                ));
            }
            continue;
        } else if !joined.is_empty() {
            joined.extend_from_slice(&lines.buf);
            owned = std::mem::take(&mut joined);
            &owned
        } else {
            start = lines.line;
            &lines.buf
        };
        let line = start;
        let mut toks = tokens(before_comment(buf), is_space);
        match toks.next() {
            None => {}
            Some(b"v") => {
                let mut c = [0f64; 3];
                let mut k = 0;
                for tok in toks.take(3) {
                    c[k] = parse_f64(tok).ok_or_else(|| {
                        parse_error(
                            name,
                            Location::Line(line),
                            format!("v: cannot parse {} as a number", show_token(tok)),
                        )
                    })?;
                    k += 1;
                }
                if k < 3 {
                    return Err(parse_error(
                        name,
                        Location::Line(line),
                        format!("v: expected 3 coordinates, found {k}"),
                    ));
                }
                sink.vertex(c, name)?;
            }
            Some(b"f") if !cloud => {
                corners.clear();
                let count = sink.seen();
                for tok in toks {
                    let index = tok.split(|&b| b == b'/').next().unwrap_or_default();
                    let bad = |why: &str| {
                        parse_error(
                            name,
                            Location::Line(line),
                            format!("f: vertex reference {}: {why}", show_token(tok)),
                        )
                    };
                    let i = std::str::from_utf8(index)
                        .ok()
                        .and_then(|s| s.parse::<i64>().ok())
                        .ok_or_else(|| bad("not an integer"))?;
                    let zero_based = match i {
                        0 => return Err(bad("indices start at 1")),
                        i if i > 0 => i - 1,
                        i => {
                            let at = count as i64 + i;
                            if at < 0 {
                                return Err(bad(&format!("only {count} vertices precede it")));
                            }
                            at
                        }
                    };
                    let zero_based = u32::try_from(zero_based).map_err(|_| bad("out of range"))?;
                    if highest.is_none_or(|(h, _)| zero_based > h) {
                        highest = Some((zero_based, line));
                    }
                    corners.push(zero_based);
                }
                sink.face(&corners, name)?;
            }
            Some(b"f") => sink.has_faces = true,
            Some(keyword) => {
                let k = String::from_utf8_lossy(keyword).into_owned();
                if ignored.len() < MAX_IGNORED && !ignored.contains(&k) {
                    ignored.push(k);
                }
            }
        }
    }
    if let Some((h, line)) = highest
        && u64::from(h) >= sink.seen()
    {
        return Err(parse_error(
            name,
            Location::Line(line),
            format!(
                "f: vertex index {} out of range (the file has {} vertices)",
                u64::from(h) + 1,
                sink.seen()
            ),
        ));
    }
    Ok(sink.finish(InputFormat::Obj, src.pos(), ignored))
}
