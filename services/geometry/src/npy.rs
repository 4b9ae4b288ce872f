//! Height maps as NumPy `.npy` arrays plus a JSON sidecar with the metadata.
//!
//! # Format
//!
//! Written: version 1.0, dtype `<f4`, C order, shape `(height, width)`, array row 0 = map row 0
//! (minimum Y), so `np.load` gives `a[row, col]` in millimetres with NaN for "no data". The header
//! is padded with spaces to a multiple of 64 bytes, as NumPy does. The metadata NumPy cannot hold
//! goes to a sidecar `MAP.npy.json` ([`HeightMapMeta`] plus `"format": 1`).
//!
//! Read: versions 1.0, 2.0 and 3.0; dtypes `<f4`, `>f4`, `<f8`, `>f8` (f8 is rounded to the
//! nearest f32); C or Fortran order; 2-D shapes only. Data is streamed from the reader straight
//! into the result (one pass, no intermediate copy of the array), Fortran order included.
//! f4 values, NaN payloads included, are kept bit for bit.
//!
//! Metadata on read: the sidecar if present, else the caller's [`ImageMapping`] (pixel size
//! required; Z range from the mapping, or else from the data: `[min, max]` of the finite values,
//! widened to `[min, min + 1]` when flat and `[0, 1]` when there is no data; origin `(0, 0)`,
//! face `+Z`).

use std::fs::File;
use std::io::{BufReader, BufWriter, ErrorKind, Read, Write};
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::error::{GeometryError, Result};
use crate::heightmap::{HeightMap, HeightMapMeta, MAX_CELLS};
use crate::png_io::ImageMapping;

/// The six bytes every `.npy` file starts with.
pub const NPY_MAGIC: &[u8; 6] = b"\x93NUMPY";

/// Value of `"format"` in sidecars written by this version.
pub const SIDECAR_FORMAT_VERSION: u32 = 1;

/// Largest header accepted on read (NumPy itself caps headers far below this).
const MAX_HEADER_LEN: usize = 1 << 20;

/// The sidecar JSON: the map's metadata and a format version.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NpySidecar {
    pub format: u32,
    #[serde(flatten)]
    pub meta: HeightMapMeta,
}

/// A raw 2-D array as read from a `.npy` stream, row-major, converted to f32.
#[derive(Debug, Clone, PartialEq)]
pub struct NpyArray {
    pub width: u32,
    pub height: u32,
    pub data: Vec<f32>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Dtype {
    F4 { big_endian: bool },
    F8 { big_endian: bool },
}

impl Dtype {
    fn size(self) -> usize {
        match self {
            Dtype::F4 { .. } => 4,
            Dtype::F8 { .. } => 8,
        }
    }

    fn decode(self, b: &[u8]) -> f32 {
        match self {
            Dtype::F4 { big_endian } => {
                let a = [b[0], b[1], b[2], b[3]];
                if big_endian { f32::from_be_bytes(a) } else { f32::from_le_bytes(a) }
            }
            Dtype::F8 { big_endian } => {
                let a = [b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]];
                (if big_endian { f64::from_be_bytes(a) } else { f64::from_le_bytes(a) }) as f32
            }
        }
    }
}

/// Path of the sidecar of `npy_path`: the same name with `.json` appended (`MAP.npy.json`).
pub fn sidecar_path(npy_path: &Path) -> PathBuf {
    let mut s = npy_path.as_os_str().to_owned();
    s.push(".json");
    PathBuf::from(s)
}

/// Writes the heights of `map` as a version 1.0 `<f4` C-order `(height, width)` array to `w`.
/// The metadata is not written (see [`write_npy`] for the sidecar).
pub fn write_npy_to<W: Write>(map: &HeightMap, mut w: W) -> Result<()> {
    let dict =
        format!("{{'descr': '<f4', 'fortran_order': False, 'shape': ({}, {}), }}", map.height(), map.width());
    // magic (6) + version (2) + header length (2) + dict + padding + '\n' is a multiple of 64.
    let unpadded = 10 + dict.len() + 1;
    let header_len = dict.len() + 1 + (64 - unpadded % 64) % 64;
    let header_len_u16 = u16::try_from(header_len)
        .map_err(|_| GeometryError::invalid("npy header length", header_len, "at most 65535 bytes"))?;
    w.write_all(NPY_MAGIC)?;
    w.write_all(&[1, 0])?;
    w.write_all(&header_len_u16.to_le_bytes())?;
    w.write_all(dict.as_bytes())?;
    w.write_all(&vec![b' '; header_len - dict.len() - 1])?;
    w.write_all(b"\n")?;
    let mut buf = Vec::with_capacity(1 << 16);
    for chunk in map.data().chunks(1 << 14) {
        buf.clear();
        for z in chunk {
            buf.extend_from_slice(&z.to_le_bytes());
        }
        w.write_all(&buf)?;
    }
    Ok(())
}

/// Writes `map` to `path` as `.npy` and its metadata to the sidecar [`sidecar_path`]`(path)`.
pub fn write_npy(map: &HeightMap, path: impl AsRef<Path>) -> Result<()> {
    let path = path.as_ref();
    let run = || -> Result<()> {
        let mut w = BufWriter::new(File::create(path)?);
        write_npy_to(map, &mut w)?;
        w.flush()?;
        Ok(())
    };
    run().map_err(|e| e.in_file(path))?;
    let side = sidecar_path(path);
    let sidecar = NpySidecar { format: SIDECAR_FORMAT_VERSION, meta: *map.meta() };
    let run = || -> Result<()> {
        let json =
            serde_json::to_vec_pretty(&sidecar).map_err(|e| GeometryError::Json { reason: e.to_string() })?;
        std::fs::write(&side, json)?;
        Ok(())
    };
    run().map_err(|e| e.in_file(&side))
}

/// Reads a 2-D `.npy` array from `r` (see the module docs for what is accepted).
///
/// Errors: [`GeometryError::NpyBadMagic`], [`GeometryError::NpyVersion`],
/// [`GeometryError::NpyHeader`], [`GeometryError::NpyDtype`], [`GeometryError::Truncated`] (with
/// the byte offset where the input ended), [`GeometryError::TooManyCells`].
pub fn read_npy_array<R: Read>(r: R) -> Result<NpyArray> {
    let mut r = BufReader::with_capacity(1 << 16, r);
    let mut offset = 0u64;
    let mut preamble = [0u8; 8];
    read_exact_at(&mut r, &mut preamble, &mut offset, 10)?;
    if &preamble[..6] != NPY_MAGIC {
        return Err(GeometryError::NpyBadMagic);
    }
    let (major, minor) = (preamble[6], preamble[7]);
    let header_len = match (major, minor) {
        (1, 0) => {
            let mut b = [0u8; 2];
            read_exact_at(&mut r, &mut b, &mut offset, 10)?;
            usize::from(u16::from_le_bytes(b))
        }
        (2 | 3, 0) => {
            let mut b = [0u8; 4];
            read_exact_at(&mut r, &mut b, &mut offset, 12)?;
            u32::from_le_bytes(b) as usize
        }
        _ => return Err(GeometryError::NpyVersion { major, minor }),
    };
    if header_len > MAX_HEADER_LEN {
        return Err(GeometryError::NpyHeader {
            reason: format!("header length {header_len} exceeds {MAX_HEADER_LEN}"),
        });
    }
    let mut header = vec![0u8; header_len];
    let header_end = offset + header_len as u64;
    read_exact_at(&mut r, &mut header, &mut offset, header_end)?;
    let header = String::from_utf8(header)
        .map_err(|_| GeometryError::NpyHeader { reason: "header is not utf-8 text".into() })?;
    let (dtype, fortran, height, width) = parse_header(&header)?;

    let cells = u64::from(width) * u64::from(height);
    if cells > MAX_CELLS {
        return Err(GeometryError::TooManyCells {
            width: width.into(),
            height: height.into(),
            limit: MAX_CELLS,
        });
    }
    let n = cells as usize;
    let total = offset + cells * dtype.size() as u64;
    let mut data = vec![0f32; n];
    let mut buf = vec![0u8; (1 << 16) / dtype.size() * dtype.size()];
    let (w, h) = (width as usize, height as usize);
    let mut k = 0usize;
    while k < n {
        let take = (n - k).min(buf.len() / dtype.size());
        let bytes = &mut buf[..take * dtype.size()];
        read_exact_at(&mut r, bytes, &mut offset, total)?;
        for (j, b) in bytes.chunks_exact(dtype.size()).enumerate() {
            let idx = k + j;
            // Fortran order: stream index idx = col·h + row.
            let dst = if fortran { (idx % h) * w + idx / h } else { idx };
            data[dst] = dtype.decode(b);
        }
        k += take;
    }
    Ok(NpyArray { width, height, data })
}

/// Fills `buf`, advancing `offset`; a short read is [`GeometryError::Truncated`] at the offset
/// where the input ended, `expected` being the total length the input should have had.
fn read_exact_at<R: Read>(r: &mut R, buf: &mut [u8], offset: &mut u64, expected: u64) -> Result<()> {
    let mut filled = 0;
    while filled < buf.len() {
        match r.read(&mut buf[filled..]) {
            Ok(0) => return Err(GeometryError::Truncated { offset: *offset + filled as u64, expected }),
            Ok(m) => filled += m,
            Err(e) if e.kind() == ErrorKind::Interrupted => {}
            Err(e) => return Err(e.into()),
        }
    }
    *offset += buf.len() as u64;
    Ok(())
}

/// A Python literal of the subset `.npy` headers use.
#[derive(Debug, Clone, PartialEq)]
enum Lit {
    Str(String),
    Bool(bool),
    Tuple(Vec<u64>),
}

/// Parses `{'descr': '<f4', 'fortran_order': False, 'shape': (h, w), }` (keys in any order,
/// either quote style, trailing commas allowed) into (dtype, fortran, height, width).
fn parse_header(text: &str) -> Result<(Dtype, bool, u32, u32)> {
    let bad = |reason: String| GeometryError::NpyHeader { reason };
    let mut p = Parser { s: text.trim().as_bytes(), i: 0 };
    let mut descr = None;
    let mut fortran = None;
    let mut shape = None;
    p.expect(b'{').map_err(bad)?;
    loop {
        p.ws();
        if p.eat(b'}') {
            break;
        }
        let key = match p.literal().map_err(bad)? {
            Lit::Str(k) => k,
            other => return Err(bad(format!("dictionary key {other:?} is not a string"))),
        };
        p.ws();
        p.expect(b':').map_err(bad)?;
        let value = p.literal().map_err(bad)?;
        match (key.as_str(), value) {
            ("descr", Lit::Str(d)) => descr = Some(d),
            ("fortran_order", Lit::Bool(b)) => fortran = Some(b),
            ("shape", Lit::Tuple(t)) => shape = Some(t),
            (k @ ("descr" | "fortran_order" | "shape"), v) => {
                return Err(bad(format!("'{k}' has the wrong type: {v:?}")));
            }
            (k, _) => return Err(bad(format!("unexpected key '{k}'"))),
        }
        p.ws();
        if !p.eat(b',') {
            p.ws();
            p.expect(b'}').map_err(bad)?;
            break;
        }
    }
    p.ws();
    if p.i != p.s.len() {
        return Err(bad(format!("unexpected text after the dictionary at offset {}", p.i)));
    }
    let descr = descr.ok_or_else(|| bad("missing key 'descr'".into()))?;
    let fortran = fortran.ok_or_else(|| bad("missing key 'fortran_order'".into()))?;
    let shape = shape.ok_or_else(|| bad("missing key 'shape'".into()))?;
    let dtype = match descr.as_str() {
        "<f4" => Dtype::F4 { big_endian: false },
        ">f4" => Dtype::F4 { big_endian: true },
        "<f8" => Dtype::F8 { big_endian: false },
        ">f8" => Dtype::F8 { big_endian: true },
        _ => return Err(GeometryError::NpyDtype { dtype: descr }),
    };
    let shape_text = format!("({})", shape.iter().map(u64::to_string).collect::<Vec<_>>().join(", "));
    let [h, w] = shape[..] else {
        return Err(GeometryError::ShapeMismatch {
            expected: "a 2-d shape (height, width)".into(),
            found: shape_text,
        });
    };
    let dim = |v: u64| u32::try_from(v).ok().filter(|&d| d > 0);
    match (dim(h), dim(w)) {
        (Some(h), Some(w)) => Ok((dtype, fortran, h, w)),
        _ => Err(GeometryError::ShapeMismatch {
            expected: "nonzero dimensions below 2^32".into(),
            found: shape_text,
        }),
    }
}

struct Parser<'a> {
    s: &'a [u8],
    i: usize,
}

impl Parser<'_> {
    fn ws(&mut self) {
        while self.s.get(self.i).is_some_and(u8::is_ascii_whitespace) {
            self.i += 1;
        }
    }

    fn eat(&mut self, c: u8) -> bool {
        let hit = self.s.get(self.i) == Some(&c);
        if hit {
            self.i += 1;
        }
        hit
    }

    fn expect(&mut self, c: u8) -> Result<(), String> {
        if self.eat(c) { Ok(()) } else { Err(format!("expected '{}' at offset {}", c as char, self.i)) }
    }

    fn literal(&mut self) -> Result<Lit, String> {
        self.ws();
        match self.s.get(self.i) {
            Some(&q @ (b'\'' | b'"')) => {
                let start = self.i + 1;
                let len = self.s[start..].iter().position(|&c| c == q).ok_or("unterminated string")?;
                self.i = start + len + 1;
                Ok(Lit::Str(String::from_utf8_lossy(&self.s[start..start + len]).into_owned()))
            }
            Some(b'(') => {
                self.i += 1;
                let mut items = Vec::new();
                loop {
                    self.ws();
                    if self.eat(b')') {
                        break;
                    }
                    let start = self.i;
                    while self.s.get(self.i).is_some_and(u8::is_ascii_digit) {
                        self.i += 1;
                    }
                    let digits = std::str::from_utf8(&self.s[start..self.i]).unwrap_or_default();
                    let v = digits.parse().map_err(|_| format!("expected a dimension at offset {start}"))?;
                    items.push(v);
                    self.eat(b'L'); // Python 2 long suffix
                    self.ws();
                    if !self.eat(b',') {
                        self.ws();
                        self.expect(b')')?;
                        break;
                    }
                }
                Ok(Lit::Tuple(items))
            }
            _ if self.s[self.i..].starts_with(b"True") => {
                self.i += 4;
                Ok(Lit::Bool(true))
            }
            _ if self.s[self.i..].starts_with(b"False") => {
                self.i += 5;
                Ok(Lit::Bool(false))
            }
            _ => Err(format!("expected a string, tuple or boolean at offset {}", self.i)),
        }
    }
}

/// Reads a `.npy` height map from `r`; the metadata comes from `sidecar` if given, else from
/// `fallback` (see the module docs). A sidecar whose size differs from the array's shape is
/// [`GeometryError::ShapeMismatch`].
pub fn read_npy_from<R: Read>(
    r: R,
    sidecar: Option<&HeightMapMeta>,
    fallback: Option<&ImageMapping>,
) -> Result<HeightMap> {
    let NpyArray { width, height, data } = read_npy_array(r)?;
    let meta = match sidecar {
        Some(meta) => {
            if (meta.width, meta.height) != (width, height) {
                return Err(GeometryError::ShapeMismatch {
                    expected: format!("({}, {}) from the metadata", meta.height, meta.width),
                    found: format!("({height}, {width}) in the array"),
                });
            }
            *meta
        }
        None => {
            let fb = fallback.ok_or(GeometryError::MissingMetadata { key: "pixel_mm" })?;
            let (lo, hi) = data_z_range(&data);
            let mut meta = HeightMapMeta::new(width, height, fb.pixel_mm);
            (meta.z_min_mm, meta.z_max_mm) = match (fb.z_min_mm, fb.z_max_mm) {
                (Some(z0), Some(z1)) => (z0, z1),
                (Some(z0), None) => (z0, if hi > z0 { hi } else { z0 + 1.0 }),
                (None, Some(z1)) => (if lo < z1 { lo } else { z1 - 1.0 }, z1),
                (None, None) => (lo, hi),
            };
            meta
        }
    };
    HeightMap::new(meta, data)
}

/// `[min, max]` of the finite values; `[min, min+1]` when flat; `[0, 1]` without data.
fn data_z_range(data: &[f32]) -> (f64, f64) {
    let mut it = data.iter().filter(|z| z.is_finite()).map(|&z| f64::from(z));
    let Some(first) = it.next() else { return (0.0, 1.0) };
    let (lo, hi) = it.fold((first, first), |(lo, hi), z| (lo.min(z), hi.max(z)));
    if hi > lo { (lo, hi) } else { (lo, lo + 1.0) }
}

/// Reads a `.npy` height map file with its sidecar `MAP.npy.json` if present, else with
/// `fallback`; errors name the file concerned.
pub fn read_npy(path: impl AsRef<Path>, fallback: Option<&ImageMapping>) -> Result<HeightMap> {
    let path = path.as_ref();
    let side = sidecar_path(path);
    let sidecar = match std::fs::read(&side) {
        Ok(bytes) => {
            let s: NpySidecar = serde_json::from_slice(&bytes)
                .map_err(|e| GeometryError::Json { reason: e.to_string() }.in_file(&side))?;
            if s.format != SIDECAR_FORMAT_VERSION {
                let e = GeometryError::InvalidMetadata {
                    key: "format".into(),
                    value: s.format.to_string(),
                    reason: format!("expected {SIDECAR_FORMAT_VERSION}"),
                };
                return Err(e.in_file(&side));
            }
            Some(s.meta)
        }
        Err(e) if e.kind() == ErrorKind::NotFound => None,
        Err(e) => return Err(GeometryError::from(e).in_file(&side)),
    };
    let run = || read_npy_from(File::open(path)?, sidecar.as_ref(), fallback);
    run().map_err(|e| e.in_file(path))
}

#[cfg(test)]
mod tests {
    use std::io::Cursor;

    use proptest::prelude::*;

    use super::*;
    use crate::face::Face;
    use crate::heightmap::tests::hemisphere;

    fn npy_bytes(version: u8, dict: &str, payload: &[u8]) -> Vec<u8> {
        let mut out = NPY_MAGIC.to_vec();
        out.extend_from_slice(&[version, 0]);
        if version == 1 {
            out.extend_from_slice(&(dict.len() as u16).to_le_bytes());
        } else {
            out.extend_from_slice(&(dict.len() as u32).to_le_bytes());
        }
        out.extend_from_slice(dict.as_bytes());
        out.extend_from_slice(payload);
        out
    }

    fn map_from(sidecar: Option<&HeightMapMeta>, bytes: &[u8]) -> Result<HeightMap> {
        read_npy_from(Cursor::new(bytes), sidecar, Some(&ImageMapping::pixel_only(0.5)))
    }

    #[test]
    fn written_header_is_aligned_and_numpy_shaped() {
        let map = hemisphere(5, 1.0, 2.0, true);
        let mut bytes = Vec::new();
        write_npy_to(&map, &mut bytes).expect("write");
        let header_len = usize::from(u16::from_le_bytes([bytes[8], bytes[9]]));
        assert_eq!((10 + header_len) % 64, 0);
        let header = std::str::from_utf8(&bytes[10..10 + header_len]).expect("ascii");
        assert!(header.starts_with("{'descr': '<f4', 'fortran_order': False, 'shape': (5, 5), }"));
        assert!(header.ends_with('\n'));
        assert_eq!(bytes.len(), 10 + header_len + 25 * 4);
        let back = read_npy_from(Cursor::new(&bytes), Some(map.meta()), None).expect("read");
        assert!(back.bitwise_eq(&map));
    }

    #[test]
    fn fortran_order_big_endian_f8_version_2() {
        // 2 rows x 3 cols; column-major stream: a00 a10 a01 a11 a02 a12.
        let values = [0.0f64, 10.0, 1.0, 11.0, 2.0, f64::NAN];
        let payload: Vec<u8> = values.iter().flat_map(|v| v.to_be_bytes()).collect();
        let bytes =
            npy_bytes(2, "{\"shape\": (2L, 3L), \"fortran_order\": True, \"descr\": \">f8\"}\n", &payload);
        let map = map_from(None, &bytes).expect("read");
        assert_eq!((map.width(), map.height()), (3, 2));
        assert_eq!(&map.data()[..5], &[0.0, 1.0, 2.0, 10.0, 11.0]);
        assert!(map.data()[5].is_nan());
        assert_eq!((map.z_min_mm(), map.z_max_mm(), map.pixel_mm()), (0.0, 11.0, 0.5));
    }

    #[test]
    fn other_dtypes_and_versions() {
        let le8: Vec<u8> = [1.5f64, -2.0].iter().flat_map(|v| v.to_le_bytes()).collect();
        let map = map_from(None, &npy_bytes(3, "{'descr':'<f8','fortran_order':False,'shape':(1,2)}", &le8))
            .expect("f8");
        assert_eq!(map.data(), &[1.5, -2.0]);
        let be4: Vec<u8> = [3.25f32, 4.0].iter().flat_map(|v| v.to_be_bytes()).collect();
        let map = map_from(
            None,
            &npy_bytes(1, "{'descr': '>f4', 'fortran_order': False, 'shape': (2, 1), }", &be4),
        )
        .expect("be f4");
        assert_eq!(map.data(), &[3.25, 4.0]);
        assert_eq!((map.z_min_mm(), map.z_max_mm()), (3.25, 4.0));
        // Flat data gets a unit range.
        let flat = map_from(
            None,
            &npy_bytes(1, "{'descr':'<f4','fortran_order':False,'shape':(1,1)}", &[0, 0, 128, 63]),
        )
        .expect("flat");
        assert_eq!((flat.z_min_mm(), flat.z_max_mm()), (1.0, 2.0));
    }

    #[test]
    fn malformed_inputs_name_the_problem() {
        let ok = "{'descr': '<f4', 'fortran_order': False, 'shape': (2, 2), }";
        let end = 10 + ok.len();
        let truncated = format!("truncated data at byte {}: expected {} bytes in total", end + 13, end + 16);
        let cases: Vec<(Vec<u8>, &str)> = vec![
            (b"\x93NUMPX\x01\x00".to_vec(), "not an npy file: bad magic"),
            (b"\x93NUM".to_vec(), "truncated data at byte 4: expected 10 bytes in total"),
            (npy_bytes(4, ok, &[]), "unsupported npy version 4.0"),
            (npy_bytes(1, &ok.replace("<f4", "<i2"), &[0; 8]), "unsupported npy dtype '<i2'"),
            (npy_bytes(1, &ok.replace("(2, 2)", "(4,)"), &[0; 16]), "shape mismatch: (4) found"),
            (npy_bytes(1, &ok.replace("(2, 2)", "(0, 2)"), &[]), "shape mismatch: (0, 2) found"),
            (npy_bytes(1, &ok.replace("False", "0"), &[0; 16]), "malformed npy header: expected a string"),
            (npy_bytes(1, &ok.replace("'shape'", "'shap'"), &[0; 16]), "unexpected key 'shap'"),
            (npy_bytes(1, &ok.replace(", 'shape': (2, 2)", ""), &[0; 16]), "missing key 'shape'"),
            (npy_bytes(1, ok, &[0; 13]), &truncated),
        ];
        for (bytes, msg) in cases {
            let e = map_from(None, &bytes).expect_err(msg).to_string();
            assert!(e.contains(msg), "{e} / {msg}");
        }
        let bytes = npy_bytes(1, ok, &[0; 16]);
        let e = read_npy_from(Cursor::new(&bytes), None, None).expect_err("no fallback");
        assert!(e.to_string().contains("'pixel_mm'"), "{e}");
        let e = map_from(Some(&HeightMapMeta::new(3, 2, 1.0)), &bytes).expect_err("sidecar shape");
        assert_eq!(
            e.to_string(),
            "shape mismatch: (2, 2) in the array found but (2, 3) from the metadata expected"
        );
    }

    #[test]
    fn file_with_sidecar_and_without() {
        let dir = tempfile::tempdir().expect("tempdir");
        let path = dir.path().join("map.npy");
        let mut map = hemisphere(7, 0.3, 1.0, true);
        map.set_face(Face::A { angle_deg: 30.0 }).expect("face");
        map.set_part_origin([1.5, -20.25, -176.0]).expect("part origin");
        write_npy(&map, &path).expect("write");
        assert!(dir.path().join("map.npy.json").exists());
        assert!(read_npy(&path, None).expect("read").bitwise_eq(&map));
        std::fs::remove_file(sidecar_path(&path)).expect("rm");
        let e = read_npy(&path, None).expect_err("no metadata");
        assert!(e.to_string().contains("map.npy: missing metadata key 'pixel_mm'"), "{e}");
        let bare = read_npy(&path, Some(&ImageMapping::new(0.3, -1.0, 2.0))).expect("fallback");
        assert_eq!((bare.z_min_mm(), bare.z_max_mm(), bare.face()), (-1.0, 2.0, Face::PosZ));
    }

    proptest! {
        #[test]
        fn npy_round_trip_is_bit_exact(
            w in 1u32..9, h in 1u32..9,
            bits in prop::collection::vec(any::<u32>(), 64),
        ) {
            let meta = HeightMapMeta::new(w, h, 0.25);
            // Arbitrary bit patterns: NaNs with payloads, infinities, subnormals.
            let data: Vec<f32> = bits.iter().take((w * h) as usize).map(|&b| f32::from_bits(b)).collect();
            let map = HeightMap::new(meta, data).expect("map");
            let mut bytes = Vec::new();
            write_npy_to(&map, &mut bytes).expect("write");
            let back = read_npy_from(Cursor::new(bytes), Some(&meta), None).expect("read");
            prop_assert!(back.bitwise_eq(&map));
        }
    }
}
