//! OFF (Object File Format, Geomview; the format of CGAL's and many research data sets), ASCII.
//!
//! Layout: a keyword line `[ST][C][N][4][n]OFF` (the prefixes announce per-vertex texture
//! coordinates, colours, normals, homogeneous coordinates and a dimension), the counts
//! `vertices faces [edges]` (on the keyword's line or the next), then one vertex per line (`x y z`
//! and whatever the prefixes add, which is ignored; `x y z w` divided by `w` for `4OFF`), then one
//! face per line (`k i0 … i(k-1)` and an optional colour, ignored). `#` starts a comment anywhere;
//! blank lines are skipped. Faces of more than three corners are fan-triangulated; faces of fewer
//! and degenerate triangles are dropped and counted, as are non-finite vertices and the faces that
//! use them. Reading stops after the last face, as the counts say. Binary OFF (`OFF BINARY`) is
//! refused with [`FormatError::UnsupportedFormat`](super::FormatError::UnsupportedFormat).
//! Errors name the line: a count or index that is not a whole number, a vertex with fewer than
//! three coordinates, an index out of range, a file that ends before its counts are met.

use std::io::BufRead;

use super::error::{FormatError, Location, Result};
use super::polygon::PolygonSink;
use super::{
    Geometry, InputFormat, Lines, ReadLimits, ReadStats, Src, before_comment, is_space, parse_error,
    parse_f64, show_token, tokens, too_large,
};

/// True when `tok` is an OFF keyword: `OFF` after any of the prefixes `ST`, `C`, `N`, `4`, `n`.
pub(crate) fn is_off_keyword(tok: &[u8]) -> bool {
    tok.strip_suffix(b"OFF").is_some_and(|prefix| prefix.iter().all(|b| b"STCN4n".contains(b)))
}

/// Reads the next line with data; its tokens' line number is `lines.line`.
fn next_data<R: BufRead>(src: &mut Src<R>, lines: &mut Lines, name: &str) -> Result<bool> {
    while lines.next(src, name)? {
        if tokens(before_comment(&lines.buf), is_space).next().is_some() {
            return Ok(true);
        }
    }
    Ok(false)
}

fn whole(tok: &[u8], what: &str, name: &str, line: u64) -> Result<u64> {
    match parse_f64(tok) {
        Some(v) if v >= 0.0 && v.fract() == 0.0 && v <= u32::MAX as f64 => Ok(v as u64),
        _ => Err(parse_error(
            name,
            Location::Line(line),
            format!("{what}: {} is not a whole number", show_token(tok)),
        )),
    }
}

pub(crate) fn read_off_src<R: BufRead>(
    src: &mut Src<R>,
    name: &str,
    limits: &ReadLimits,
    cloud: bool,
    keep: Option<usize>,
) -> Result<(Geometry, ReadStats)> {
    let mut lines = Lines::new(0);
    if !next_data(src, &mut lines, name)? {
        return Err(parse_error(name, Location::Line(lines.line), "OFF: the file has no header"));
    }
    let head: Vec<Vec<u8>> = tokens(before_comment(&lines.buf), is_space).map(<[u8]>::to_vec).collect();
    let keyword = head.first().cloned().unwrap_or_default();
    if !is_off_keyword(&keyword) {
        return Err(parse_error(
            name,
            Location::Line(lines.line),
            format!(
                "OFF: expected the keyword OFF (or COFF, NOFF, 4OFF, ...), found {}",
                show_token(&keyword)
            ),
        ));
    }
    if head.get(1).is_some_and(|t| t.eq_ignore_ascii_case(b"binary")) {
        return Err(FormatError::UnsupportedFormat {
            file: name.to_string(),
            reason: "binary OFF is not read; write it as ASCII OFF, PLY or STL".into(),
        });
    }
    let prefix = &keyword[..keyword.len() - 3];
    let homogeneous = prefix.contains(&b'4');
    // The counts (and for nOFF the dimension first), on the keyword's line or the following.
    let mut numbers: Vec<(Vec<u8>, u64)> = head[1..].iter().map(|t| (t.clone(), lines.line)).collect();
    let want = if prefix.contains(&b'n') { 3 } else { 2 };
    while numbers.len() < want {
        if !next_data(src, &mut lines, name)? {
            return Err(parse_error(
                name,
                Location::Line(lines.line),
                "OFF: the file ends before the vertex and face counts",
            ));
        }
        numbers.extend(tokens(before_comment(&lines.buf), is_space).map(|t| (t.to_vec(), lines.line)));
    }
    let mut it = numbers.iter();
    if prefix.contains(&b'n') {
        let (tok, line) = it.next().map(|(t, l)| (t.as_slice(), *l)).unwrap_or_default();
        let dim = whole(tok, "dimension", name, line)?;
        if dim != 3 {
            return Err(parse_error(
                name,
                Location::Line(line),
                format!("OFF: dimension {dim}; only 3 is read"),
            ));
        }
    }
    let mut count = |what: &str| -> Result<u64> {
        let (tok, line) = it.next().map(|(t, l)| (t.as_slice(), *l)).unwrap_or_default();
        whole(tok, what, name, line)
    };
    let nv = count("vertex count")?;
    let nf = count("face count")?;
    if nv > limits.max_points {
        return Err(too_large(name, "points", nv, limits.max_points));
    }
    if nf > limits.max_triangles {
        return Err(too_large(name, "triangles", nf, limits.max_triangles));
    }

    let reserve = nv.min(keep.map_or(1 << 20, |k| k as u64)) as usize;
    let mut sink = PolygonSink::new(cloud, limits, reserve, keep);
    let coords = if homogeneous { 4 } else { 3 };
    for v in 0..nv {
        if !next_data(src, &mut lines, name)? {
            return Err(parse_error(
                name,
                Location::Line(lines.line),
                format!("OFF: the file ends after {v} of {nv} vertices"),
            ));
        }
        let mut c = [0f64; 4];
        let mut k = 0;
        for tok in tokens(before_comment(&lines.buf), is_space).take(coords) {
            c[k] = parse_f64(tok).ok_or_else(|| {
                parse_error(
                    name,
                    Location::Line(lines.line),
                    format!("vertex {v}: cannot parse {} as a number", show_token(tok)),
                )
            })?;
            k += 1;
        }
        if k < coords {
            return Err(parse_error(
                name,
                Location::Line(lines.line),
                format!("vertex {v}: expected {coords} coordinates, found {k}"),
            ));
        }
        let p = if homogeneous { [c[0] / c[3], c[1] / c[3], c[2] / c[3]] } else { [c[0], c[1], c[2]] };
        sink.vertex(p, name)?;
    }
    let mut corners: Vec<u32> = Vec::new();
    // A cloud needs no faces; OFF with no faces is a point set (as CGAL writes them).
    let nf = if cloud { 0 } else { nf };
    for f in 0..nf {
        if !next_data(src, &mut lines, name)? {
            return Err(parse_error(
                name,
                Location::Line(lines.line),
                format!("OFF: the file ends after {f} of {nf} faces"),
            ));
        }
        let line = lines.line;
        let mut toks = tokens(before_comment(&lines.buf), is_space);
        let k = whole(toks.next().unwrap_or_default(), &format!("face {f}: corner count"), name, line)?;
        corners.clear();
        for _ in 0..k {
            let tok = toks.next().ok_or_else(|| {
                parse_error(
                    name,
                    Location::Line(line),
                    format!("face {f}: {k} corners announced, {} given", corners.len()),
                )
            })?;
            let i = whole(tok, &format!("face {f}: vertex index"), name, line)?;
            if i >= nv {
                return Err(parse_error(
                    name,
                    Location::Line(line),
                    format!("face {f}: vertex index {i} out of range (the file has {nv} vertices)"),
                ));
            }
            corners.push(i as u32);
        }
        sink.face(&corners, name)?;
    }
    Ok(sink.finish(InputFormat::Off, src.pos(), Vec::new()))
}
