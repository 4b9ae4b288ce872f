//! PCD, the Point Cloud Library's format (versions 0.5 to 0.7): `ascii`, `binary` and
//! `binary_compressed` bodies.
//!
//! The header is text: `VERSION`, `FIELDS` (or 0.6's `COLUMNS`), `SIZE` (bytes per element: 1, 2,
//! 4 or 8), `TYPE` (`F` float, `I` signed, `U` unsigned), `COUNT` (elements per field, 1 when
//! absent), `WIDTH`, `HEIGHT`, `VIEWPOINT`, `POINTS` and finally `DATA`; `#` lines are comments.
//! The points are `x y z` (required), the intensity from the first field named as PLY's
//! ([`INTENSITY_NAMES`]) and the normals from `normal_x normal_y normal_z`; every other field
//! (`rgb`, `curvature`, a scanner's `distance` or `sid`) is skipped and listed in
//! [`ReadStats::ignored_properties`]. A field of several elements contributes its first.
//! An organised cloud's invalid pixels (NaN coordinates) are dropped and counted, as every reader
//! drops non-finite points; the viewpoint is not applied (PCL keeps points in the sensor frame
//! and the viewpoint beside them, and so do the clouds read here).
//!
//! Bodies: `ascii` is a point per line, the fields' elements in order; `binary` is packed
//! little-endian records (PCL writes the host's order; every platform it runs on is
//! little-endian), decoded a block at a time straight out of the reader's buffer; `binary_compressed`
//! is the compressed and uncompressed sizes (`u32` each) and an LZF block holding the fields one
//! after the other (all points' `x`, then all `y`, ...), decompressed whole ([`lzf_decompress`];
//! the compressed block is freed once decoded) and read point by point where each field lies.
//! Errors name the line (header, ascii body) or byte offset (binary body) and the field or count
//! at fault.

use std::io::BufRead;

use super::error::{FormatError, Location, Result};
use super::ply::INTENSITY_NAMES;
use super::{
    CloudSink, InputFormat, Lines, ReadLimits, ReadStats, Src, before_comment, io_error, is_space,
    parse_error, parse_f32, parse_f64, show_token, tokens, too_large,
};
use crate::PointCloud;

/// Largest point record accepted, bytes (a point's values: x y z, a few attributes, a descriptor
/// histogram of a few hundred bins at most).
const MAX_RECORD_BYTES: usize = 1 << 16;

/// Header lines read before `DATA` is required.
const MAX_HEADER_LINES: u64 = 1024;

/// Header keywords a PCD starts with (after comments), for sniffing.
pub(crate) const PCD_KEYWORDS: [&[u8]; 3] = [b"VERSION", b"FIELDS", b"COLUMNS"];

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Kind {
    Float,
    Signed,
    Unsigned,
}

#[derive(Debug, Clone)]
struct Field {
    name: String,
    size: usize,
    kind: Kind,
    count: usize,
    /// Byte offset of the field in a binary record.
    offset: usize,
    /// Element index of the field's first value in an ascii line.
    column: usize,
}

impl Field {
    /// The first element of the field in `rec` (little-endian).
    #[inline]
    fn decode(&self, b: &[u8]) -> f64 {
        let at = |n: usize| -> [u8; 8] {
            let mut a = [0u8; 8];
            a[..n].copy_from_slice(&b[..n]);
            a
        };
        match (self.kind, self.size) {
            (Kind::Float, 4) => f64::from(f32::from_le_bytes([b[0], b[1], b[2], b[3]])),
            (Kind::Float, _) => f64::from_le_bytes(at(8)),
            (Kind::Unsigned, n) => u64::from_le_bytes(at(n)) as f64,
            (Kind::Signed, n) => {
                let shift = 64 - 8 * n as u32;
                ((i64::from_le_bytes(at(n)) << shift) >> shift) as f64
            }
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Data {
    Ascii,
    Binary,
    Compressed,
}

struct Header {
    fields: Vec<Field>,
    points: u64,
    data: Data,
    /// Bytes per binary record.
    record: usize,
    /// Elements per ascii line.
    columns: usize,
    /// The FIELDS line.
    fields_line: u64,
}

/// Which fields give what: indices into `Header::fields`.
struct Plan {
    xyz: [usize; 3],
    intensity: Option<usize>,
    normals: Option<[usize; 3]>,
}

fn header_error(name: &str, line: u64, problem: impl Into<String>) -> FormatError {
    parse_error(name, Location::Line(line), problem)
}

fn read_header<R: BufRead>(src: &mut Src<R>, name: &str, lines: &mut Lines) -> Result<Header> {
    let mut names: Option<(Vec<String>, u64)> = None;
    let mut sizes: Option<(Vec<u64>, u64)> = None;
    let mut kinds: Option<(Vec<Kind>, u64)> = None;
    let mut counts: Option<(Vec<u64>, u64)> = None;
    let (mut width, mut height, mut points) = (None::<u64>, None::<u64>, None::<u64>);
    let data = loop {
        if lines.line >= MAX_HEADER_LINES {
            return Err(header_error(
                name,
                lines.line,
                format!("PCD: no DATA line in the first {MAX_HEADER_LINES} lines"),
            ));
        }
        if !lines.next(src, name)? {
            return Err(header_error(name, lines.line, "PCD: the file ends before the DATA line"));
        }
        let line = lines.line;
        let mut toks = tokens(before_comment(&lines.buf), is_space);
        let Some(key) = toks.next() else { continue };
        let rest: Vec<&[u8]> = toks.collect();
        let whole = |tok: &[u8], what: &str| -> Result<u64> {
            std::str::from_utf8(tok).ok().and_then(|s| s.parse::<u64>().ok()).ok_or_else(|| {
                header_error(name, line, format!("PCD: {what}: {} is not a whole number", show_token(tok)))
            })
        };
        let one = |what: &str| -> Result<u64> {
            match rest.as_slice() {
                [tok] => whole(tok, what),
                _ => Err(header_error(
                    name,
                    line,
                    format!("PCD: {what} takes one number, found {}", rest.len()),
                )),
            }
        };
        match key.to_ascii_uppercase().as_slice() {
            b"VERSION" | b"VIEWPOINT" => {}
            b"FIELDS" | b"COLUMNS" => {
                names = Some((rest.iter().map(|t| String::from_utf8_lossy(t).into_owned()).collect(), line));
            }
            b"SIZE" => {
                let v = rest.iter().map(|t| whole(t, "SIZE")).collect::<Result<Vec<_>>>()?;
                if let Some(s) = v.iter().find(|s| !matches!(s, 1 | 2 | 4 | 8)) {
                    return Err(header_error(
                        name,
                        line,
                        format!("PCD: SIZE {s}: a field is 1, 2, 4 or 8 bytes"),
                    ));
                }
                sizes = Some((v, line));
            }
            b"TYPE" => {
                let v = rest
                    .iter()
                    .map(|t| match t.to_ascii_uppercase().as_slice() {
                        b"F" => Ok(Kind::Float),
                        b"I" => Ok(Kind::Signed),
                        b"U" => Ok(Kind::Unsigned),
                        _ => Err(header_error(
                            name,
                            line,
                            format!("PCD: TYPE {}: expected F, I or U", show_token(t)),
                        )),
                    })
                    .collect::<Result<Vec<_>>>()?;
                kinds = Some((v, line));
            }
            b"COUNT" => {
                let v = rest.iter().map(|t| whole(t, "COUNT")).collect::<Result<Vec<_>>>()?;
                if v.contains(&0) {
                    return Err(header_error(name, line, "PCD: COUNT 0: a field has at least one element"));
                }
                counts = Some((v, line));
            }
            b"WIDTH" => width = Some(one("WIDTH")?),
            b"HEIGHT" => height = Some(one("HEIGHT")?),
            b"POINTS" => points = Some(one("POINTS")?),
            b"DATA" => {
                break match rest.first().map(|t| t.to_ascii_lowercase()) {
                    Some(t) if t == b"ascii" => Data::Ascii,
                    Some(t) if t == b"binary" => Data::Binary,
                    Some(t) if t == b"binary_compressed" => Data::Compressed,
                    _ => {
                        return Err(header_error(
                            name,
                            line,
                            format!(
                                "PCD: DATA {}: expected ascii, binary or binary_compressed",
                                show_token(rest.first().copied().unwrap_or_default())
                            ),
                        ));
                    }
                };
            }
            other => {
                return Err(header_error(
                    name,
                    line,
                    format!("PCD: unknown header line {}", show_token(other)),
                ));
            }
        }
    };
    let at = lines.line;
    let (names, names_line) =
        names.ok_or_else(|| header_error(name, at, "PCD: no FIELDS line before DATA"))?;
    let n = names.len();
    let (sizes, sizes_line) = sizes.ok_or_else(|| header_error(name, at, "PCD: no SIZE line before DATA"))?;
    let (kinds, kinds_line) = kinds.ok_or_else(|| header_error(name, at, "PCD: no TYPE line before DATA"))?;
    let (counts, counts_line) = counts.unwrap_or_else(|| (vec![1; n], names_line));
    for (what, len, line) in [
        ("SIZE", sizes.len(), sizes_line),
        ("TYPE", kinds.len(), kinds_line),
        ("COUNT", counts.len(), counts_line),
    ] {
        if len != n {
            return Err(header_error(
                name,
                line,
                format!("PCD: {what} has {len} entries but FIELDS names {n}"),
            ));
        }
    }
    let mut fields = Vec::with_capacity(n);
    let (mut offset, mut column) = (0usize, 0usize);
    for i in 0..n {
        let (size, kind, count) = (sizes[i] as usize, kinds[i], counts[i]);
        if kind == Kind::Float && !matches!(size, 4 | 8) {
            return Err(header_error(
                name,
                sizes_line,
                format!("PCD: field {}: a float is 4 or 8 bytes, not {size}", names[i]),
            ));
        }
        let count = usize::try_from(count).ok().filter(|&c| c <= 1 << 20).ok_or_else(|| {
            header_error(name, counts_line, format!("PCD: field {}: COUNT {count} is too large", names[i]))
        })?;
        fields.push(Field { name: names[i].clone(), size, kind, count, offset, column });
        offset += size * count;
        column += count;
        if offset > MAX_RECORD_BYTES {
            return Err(header_error(
                name,
                counts_line,
                format!("PCD: a point of {offset} bytes or more, over the limit of {MAX_RECORD_BYTES}"),
            ));
        }
    }
    let points = match (points, width, height) {
        (Some(p), _, _) => p,
        (None, Some(w), h) => w.saturating_mul(h.unwrap_or(1)),
        (None, None, _) => return Err(header_error(name, at, "PCD: neither POINTS nor WIDTH before DATA")),
    };
    Ok(Header { fields, points, data, record: offset, columns: column, fields_line: names_line })
}

fn plan(h: &Header, name: &str) -> Result<(Plan, Vec<String>)> {
    let find = |want: &str| h.fields.iter().position(|f| f.name == want);
    let need = |want: &str| {
        find(want).ok_or_else(|| {
            let have: Vec<&str> = h.fields.iter().map(|f| f.name.as_str()).collect();
            parse_error(
                name,
                Location::Line(h.fields_line),
                format!("PCD: no field {want} (the fields are {})", have.join(" ")),
            )
        })
    };
    let xyz = [need("x")?, need("y")?, need("z")?];
    let intensity = INTENSITY_NAMES.iter().find_map(|n| find(n));
    let normals = match (find("normal_x"), find("normal_y"), find("normal_z")) {
        (Some(a), Some(b), Some(c)) => Some([a, b, c]),
        _ => None,
    };
    let used: Vec<usize> =
        xyz.iter().copied().chain(intensity).chain(normals.into_iter().flatten()).collect();
    let ignored =
        (0..h.fields.len()).filter(|i| !used.contains(i)).map(|i| h.fields[i].name.clone()).collect();
    Ok((Plan { xyz, intensity, normals }, ignored))
}

pub(crate) fn read_pcd_src<R: BufRead>(
    src: &mut Src<R>,
    name: &str,
    limits: &ReadLimits,
    keep: Option<usize>,
) -> Result<(PointCloud, ReadStats)> {
    let mut lines = Lines::new(0);
    let h = read_header(src, name, &mut lines)?;
    let (plan, ignored) = plan(&h, name)?;
    if h.points > limits.max_points {
        return Err(too_large(name, "points", h.points, limits.max_points));
    }
    let reserve = h.points.min(keep.map_or(1 << 20, |k| k as u64)) as usize;
    let mut sink =
        CloudSink::new(plan.intensity.is_some(), plan.normals.is_some(), false, false, reserve).sampled(keep);
    let push = |sink: &mut CloudSink, value: &dyn Fn(usize) -> f64| {
        let [x, y, z] = plan.xyz.map(value);
        let intensity = plan.intensity.map_or(0.0, |f| value(f) as f32);
        let normal = plan.normals.map_or([0.0; 3], |n| n.map(|f| value(f) as f32));
        sink.push([x, y, z], intensity, normal, 0);
    };
    match h.data {
        Data::Ascii => {
            let mut values = vec![0f64; h.columns];
            let mut read = 0u64;
            while read < h.points {
                if !lines.next(src, name)? {
                    return Err(parse_error(
                        name,
                        Location::Line(lines.line),
                        format!("PCD: the file ends after {read} of {} points", h.points),
                    ));
                }
                let mut k = 0;
                for tok in tokens(&lines.buf, is_space) {
                    if k == h.columns {
                        return Err(parse_error(
                            name,
                            Location::Line(lines.line),
                            format!("PCD: more than the {} values the fields hold", h.columns),
                        ));
                    }
                    values[k] =
                        parse_f64(tok).or_else(|| parse_f32(tok).map(f64::from)).ok_or_else(|| {
                            parse_error(
                                name,
                                Location::Line(lines.line),
                                format!("cannot parse {} as a number", show_token(tok)),
                            )
                        })?;
                    k += 1;
                }
                if k == 0 {
                    continue;
                }
                if k < h.columns {
                    return Err(parse_error(
                        name,
                        Location::Line(lines.line),
                        format!("PCD: {k} values, the fields hold {}", h.columns),
                    ));
                }
                push(&mut sink, &|f| values[h.fields[f].column]);
                read += 1;
            }
        }
        Data::Binary => {
            let done = src.records(h.record, h.points, name, |chunk| {
                for rec in chunk.chunks_exact(h.record) {
                    push(&mut sink, &|f| {
                        let field = &h.fields[f];
                        field.decode(&rec[field.offset..])
                    });
                }
                Ok(())
            })?;
            if done < h.points {
                return Err(parse_error(
                    name,
                    Location::Byte(src.pos()),
                    format!("PCD: the file ends after {done} of {} points", h.points),
                ));
            }
        }
        Data::Compressed => {
            let start = src.pos();
            let mut sizes = [0u8; 8];
            if !src.read_bytes(&mut sizes).map_err(|e| io_error(name, e))? {
                return Err(parse_error(
                    name,
                    Location::Byte(start),
                    "PCD: the file ends before the compressed sizes",
                ));
            }
            let packed = u64::from(u32::from_le_bytes([sizes[0], sizes[1], sizes[2], sizes[3]]));
            let unpacked = u64::from(u32::from_le_bytes([sizes[4], sizes[5], sizes[6], sizes[7]]));
            let want = h.points * h.record as u64;
            if unpacked != want {
                return Err(parse_error(
                    name,
                    Location::Byte(start + 4),
                    format!(
                        "PCD: the uncompressed size {unpacked} is not {} points of {} bytes ({want})",
                        h.points, h.record
                    ),
                ));
            }
            for size in [packed, unpacked] {
                if size > limits.max_bytes {
                    return Err(too_large(name, "bytes", size, limits.max_bytes));
                }
            }
            let mut input = vec![0u8; packed as usize];
            if !src.read_bytes(&mut input).map_err(|e| io_error(name, e))? {
                return Err(parse_error(
                    name,
                    Location::Byte(src.pos()),
                    format!("PCD: the file ends inside the {packed}-byte compressed block"),
                ));
            }
            let raw = lzf_decompress(&input, unpacked as usize).map_err(|why| {
                parse_error(name, Location::Byte(start + 8), format!("PCD: compressed block: {why}"))
            })?;
            drop(input);
            let n = h.points as usize;
            // Fields one after the other: field f's elements start at points × its offset. Each
            // point's fields are decoded where they lie (one sequential stream per field used),
            // so nothing but the decompressed block is held beside the cloud.
            let at = |f: usize, i: usize| -> f64 {
                let field = &h.fields[f];
                let stride = field.size * field.count;
                let s = n * field.offset + i * stride;
                field.decode(&raw[s..s + stride])
            };
            for i in 0..n {
                let [xf, yf, zf] = plan.xyz;
                sink.push(
                    [at(xf, i), at(yf, i), at(zf, i)],
                    plan.intensity.map_or(0.0, |f| at(f, i) as f32),
                    plan.normals.map_or([0.0; 3], |c| c.map(|f| at(f, i) as f32)),
                    0,
                );
            }
        }
    }
    let mut stats = ReadStats::new(InputFormat::Pcd);
    stats.bytes = src.pos();
    stats.points = sink.len();
    stats.dropped_non_finite = sink.dropped;
    stats.ignored_properties = ignored;
    Ok((sink.into_cloud().0, stats))
}

/// Decompresses an LZF block (liblzf's format, as PCL writes it) into exactly `len` bytes.
///
/// The block is a sequence of runs: a control byte `c < 32` is followed by `c + 1` literal bytes;
/// otherwise the top three bits give a length (7 means one more length byte is added) and the low
/// five bits with the next byte a back reference: `len + 2` bytes copied from `offset + 1` bytes
/// back in the output (overlapping copies repeat, as in every LZ77 decoder).
pub fn lzf_decompress(input: &[u8], len: usize) -> Result<Vec<u8>, String> {
    let mut out: Vec<u8> = Vec::with_capacity(len);
    let mut i = 0;
    while i < input.len() {
        let ctrl = usize::from(input[i]);
        i += 1;
        if ctrl < 32 {
            let run = ctrl + 1;
            let lit = input
                .get(i..i + run)
                .ok_or_else(|| format!("a literal run of {run} bytes at {} passes the block's end", i - 1))?;
            if out.len() + run > len {
                return Err(format!("the data holds more than the {len} bytes announced"));
            }
            out.extend_from_slice(lit);
            i += run;
        } else {
            let mut run = ctrl >> 5;
            if run == 7 {
                run += usize::from(*input.get(i).ok_or("a back reference passes the block's end")?);
                i += 1;
            }
            let low = usize::from(*input.get(i).ok_or("a back reference passes the block's end")?);
            i += 1;
            let back = ((ctrl & 0x1f) << 8) + low + 1;
            let run = run + 2;
            if back > out.len() {
                return Err(format!(
                    "a back reference {back} bytes back, {} bytes into the output",
                    out.len()
                ));
            }
            if out.len() + run > len {
                return Err(format!("the data holds more than the {len} bytes announced"));
            }
            let from = out.len() - back;
            if back >= run {
                out.extend_from_within(from..from + run);
            } else {
                // Overlapping: the run repeats the last `back` bytes.
                for k in 0..run {
                    let b = out[from + k];
                    out.push(b);
                }
            }
        }
    }
    if out.len() != len {
        return Err(format!("the data holds {} bytes, {len} announced", out.len()));
    }
    Ok(out)
}
