//! Streaming readers for point clouds (XYZ text, PLY, PCD, vertex-only OBJ) and meshes (STL, OBJ,
//! OFF, PLY with faces), and the PLY writer of the format the scanning service produces.
//!
//! # Formats
//! - [`xyz`]: ASCII columns `x y z [intensity] [nx ny nz]`, separated by any whitespace or commas.
//! - [`ply`]: PLY in all three encodings (ascii, binary little- and big-endian), any scalar type
//!   for any property; faces (`property list … vertex_indices`) make a mesh. [`write_ply`] writes
//!   the scanning service's format: binary little-endian, `float x y z [intensity] [nx ny nz]`,
//!   `ushort pass`.
//! - [`stl`]: binary and ASCII STL, vertices welded bit-exactly into an indexed [`Mesh`].
//! - [`obj`]: Wavefront OBJ's `v` and `f` statements (the rest skipped and listed).
//! - [`off`]: ASCII OFF and its variants (`COFF`, `NOFF`, `4OFF`, `nOFF`, ...).
//! - [`pcd`]: PCL's PCD, ascii, binary and LZF-compressed bodies.
//!
//! [`read_any_from`] sniffs the format from the first [`SNIFF_LEN`] bytes ([`sniff_format`]) and
//! hands the stream to the right reader; [`read_any`], [`read_cloud`] and [`read_mesh`] open a file.
//!
//! Any of these formats may come gzip-compressed (`part.stl.gz`, `scan.ply.gz`: a stream starting
//! with the gzip magic `1f 8b`, whatever its name): it is decompressed as it is read and the
//! content sniffed and read as above, with the limits applying to the decompressed bytes (a
//! small archive cannot expand past `max_bytes`). Errors of the compressed stream name the file
//! and say `gzip`; a gzip stream inside another is refused.
//!
//! # Conventions
//! - **Streaming.** Nothing reads a whole file into memory: text is read line by line into one
//!   reused buffer, binary records are decoded straight out of the reader's buffer in large
//!   blocks (fixed record layouts with per-property offsets precomputed from the header, decoded
//!   with `from_le_bytes`/`from_be_bytes`, no allocation per point). Give the readers a large
//!   buffer ([`read_any`] uses a [`BufReader`] of [`BUF_LEN`] = 1 MiB).
//! - **Errors** are [`FormatError::Parse`] naming the file (the `name` argument), the 1-based line
//!   (text) or the 0-based byte offset (binary) and the problem; I/O errors are
//!   [`FormatError::Io`]; an input over a [`ReadLimits`] limit is [`FormatError::TooLarge`].
//! - **Non-finite values.** A point with a NaN or infinite coordinate or intensity is dropped and
//!   counted ([`ReadStats::dropped_non_finite`]); a non-finite normal becomes the zero vector (the
//!   cloud's "unknown normal"). Triangles with a non-finite or dropped corner and degenerate
//!   triangles (zero area: the cross product of two edges is exactly zero in `f64`) are dropped
//!   and counted ([`ReadStats::dropped_triangles`]).
//! - **Limits.** Counts announced by a header are checked against [`ReadLimits`] before anything
//!   is allocated, and pre-allocation is further capped by what the input's size can hold, so a
//!   hostile header cannot make the reader reserve more memory than the file justifies.
//!   `max_bytes` is checked against the size when it is known and enforced on the stream as well.

pub mod error;
pub mod mesh_ply;
pub mod obj;
pub mod off;
pub mod pcd;
pub mod ply;
mod polygon;
pub mod stl;
pub mod xyz;

use std::fmt;
use std::fs::File;
use std::io::{self, BufRead, BufReader, Cursor, Read};
use std::path::Path;

use crate::cloud::{CloudPoint, PointCloud};
use nalgebra::{Point3, Vector3};

use crate::mesh::Mesh;
pub use error::{FormatError, Location, Result};

pub use mesh_ply::{read_mesh_ply, write_mesh_ply};
pub use ply::{
    PlyEncoding, read_ply_cloud_with_label, read_ply_cloud_with_pass, read_ply_from, write_ply,
    write_ply_labelled,
};
pub use stl::{read_stl_from, write_stl};
pub use xyz::read_xyz_from;

/// Bytes examined by [`sniff_format`].
pub const SNIFF_LEN: usize = 4096;

/// Capacity of the [`BufReader`] the path functions open files with.
pub const BUF_LEN: usize = 1 << 20;

/// Longest line accepted in a text input (XYZ, ASCII PLY body, ASCII STL).
pub const MAX_LINE_LEN: usize = 1 << 16;

/// Upper bounds on what a reader accepts, so that an input cannot exhaust memory.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ReadLimits {
    /// Largest input, in bytes.
    pub max_bytes: u64,
    /// Most points (cloud) or vertices (mesh) kept; a header announcing more is rejected at once.
    pub max_points: u64,
    /// Most triangles (after fan triangulation of PLY faces).
    pub max_triangles: u64,
}

impl Default for ReadLimits {
    /// 8 GiB, 200 000 000 points, 50 000 000 triangles.
    fn default() -> Self {
        ReadLimits { max_bytes: 8 << 30, max_points: 200_000_000, max_triangles: 50_000_000 }
    }
}

/// The input formats the readers recognise.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum InputFormat {
    /// ASCII columns `x y z [intensity] [nx ny nz]`.
    Xyz,
    /// PLY, `format ascii 1.0`.
    PlyAscii,
    /// PLY, `format binary_little_endian 1.0`.
    PlyBinaryLe,
    /// PLY, `format binary_big_endian 1.0`.
    PlyBinaryBe,
    /// ASCII STL (`solid` … `facet normal` … `endsolid`).
    StlAscii,
    /// Binary STL (80-byte header, `u32` count, 50-byte records).
    StlBinary,
    /// ASCII OFF (`OFF`, `COFF`, `NOFF`, `4OFF`, ... then counts, vertices, faces).
    Off,
    /// Wavefront OBJ (`v` and `f` statements).
    Obj,
    /// PCD, the Point Cloud Library's format (ascii, binary or binary_compressed body).
    Pcd,
}

impl fmt::Display for InputFormat {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            InputFormat::Xyz => "XYZ text",
            InputFormat::PlyAscii => "PLY (ascii)",
            InputFormat::PlyBinaryLe => "PLY (binary little-endian)",
            InputFormat::PlyBinaryBe => "PLY (binary big-endian)",
            InputFormat::StlAscii => "STL (ascii)",
            InputFormat::StlBinary => "STL (binary)",
            InputFormat::Off => "OFF",
            InputFormat::Obj => "OBJ",
            InputFormat::Pcd => "PCD",
        })
    }
}

/// What a read found, beyond the geometry itself.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ReadStats {
    /// The format read.
    pub format: InputFormat,
    /// Bytes consumed from the input (a PLY reader stops after the last element it needs).
    pub bytes: u64,
    /// Points (cloud) or vertices (mesh) read and kept ([`sample_cloud_from`]: read, of which a
    /// sample is kept).
    pub points: u64,
    /// Points dropped for a NaN or infinite coordinate or intensity.
    pub dropped_non_finite: u64,
    /// Triangles kept.
    pub triangles: u64,
    /// Triangles dropped: degenerate (zero area, repeated corner, PLY face of fewer than 3
    /// vertices) or with a non-finite corner.
    pub dropped_triangles: u64,
    /// Properties present in the input but not used: PLY vertex properties by name (`red`),
    /// properties of other elements as `element.property` (`face.flags`).
    pub ignored_properties: Vec<String>,
}

impl ReadStats {
    /// Empty statistics for `format`.
    pub fn new(format: InputFormat) -> Self {
        ReadStats {
            format,
            bytes: 0,
            points: 0,
            dropped_non_finite: 0,
            triangles: 0,
            dropped_triangles: 0,
            ignored_properties: Vec::new(),
        }
    }
}

/// What an input holds: a point cloud or a triangle mesh.
#[derive(Debug, Clone, PartialEq)]
pub enum Geometry {
    /// XYZ, PCD, or PLY, OBJ or OFF without faces.
    Cloud(PointCloud),
    /// STL, OBJ or OFF with faces, or PLY with a non-empty face element.
    Mesh(Mesh),
}

impl Geometry {
    /// The cloud, or a mesh's vertices as a cloud.
    pub fn into_cloud(self) -> PointCloud {
        match self {
            Geometry::Cloud(c) => c,
            Geometry::Mesh(m) => PointCloud::from_points(m.vertices),
        }
    }
}

/// Guesses the format from the first bytes of an input (`head`, up to [`SNIFF_LEN`] bytes) and its
/// total size when known, in this order:
/// 1. `ply` on the first line: PLY (the encoding from the `format` line when it is in `head`,
///    otherwise [`InputFormat::PlyAscii`]; the PLY reader takes the encoding from the header).
/// 2. `size` known, at least 84 bytes and equal to 84 + 50·n with n the `u32` at byte 80: binary
///    STL (even when its header starts with `solid`, as many binary writers' do).
/// 3. A first line `# .PCD`, or a first line with data (past blank lines and `#` comments)
///    starting with a PCD header keyword (`VERSION`, `FIELDS`, `COLUMNS`) and `FIELDS` (or
///    `COLUMNS`) and `DATA` lines further on: PCD (whose binary body follows a text header).
/// 4. At least 84 bytes, some of which text never holds (NUL or control characters other than
///    white space): binary STL (the reader then reports how the input fails the binary layout).
/// 5. `solid` at the start (after white space, any case) and `facet` or `endsolid` further on:
///    ASCII STL.
/// 6. The first line with data starting with an OFF keyword (`OFF`, `COFF`, `NOFF`, `4OFF`, ...):
///    OFF; with a PCD header keyword: PCD (a header cut short); with an OBJ statement (`v`, `vt`,
///    `vn`, `f`, `o`, `g`, `s`, `mtllib`, `usemtl`, ...): OBJ.
/// 7. Otherwise XYZ text.
pub fn sniff_format(head: &[u8], size: Option<u64>) -> InputFormat {
    let first_line = head.split(|&b| b == b'\n').next().unwrap_or_default();
    if first_line.strip_suffix(b"\r").unwrap_or(first_line) == b"ply" {
        return sniff_ply_encoding(head);
    }
    if let (Some(size), Some(count)) = (size, head.get(80..84)) {
        let n = u32::from_le_bytes([count[0], count[1], count[2], count[3]]);
        if size == 84 + 50 * u64::from(n) {
            return InputFormat::StlBinary;
        }
    }
    let first_data = head.split(|&b| b == b'\n').find_map(|l| tokens(before_comment(l), is_space).next());
    // A binary PCD body follows a text header: its first line, or a header keyword first with the
    // FIELDS (COLUMNS) and DATA lines in the head (a binary STL's header may start with any word).
    let line_starts = |word: &[u8]| head.split(|&b| b == b'\n').any(|l| l.starts_with(word));
    if head.trim_ascii_start().starts_with(b"# .PCD")
        || (first_data.is_some_and(|t| pcd::PCD_KEYWORDS.contains(&t))
            && (line_starts(b"FIELDS ") || line_starts(b"COLUMNS "))
            && line_starts(b"DATA "))
    {
        return InputFormat::Pcd;
    }
    if head.len() >= 84 && head.iter().any(|&b| b < 0x20 && !matches!(b, b'\t' | b'\n' | b'\r' | 0x0b | 0x0c))
    {
        return InputFormat::StlBinary;
    }
    let trimmed = head.trim_ascii_start();
    if trimmed.len() >= 5 && trimmed[..5].eq_ignore_ascii_case(b"solid") {
        let lower = trimmed.to_ascii_lowercase();
        let has = |word: &[u8]| lower.windows(word.len()).any(|w| w == word);
        if has(b"facet") || has(b"endsolid") {
            return InputFormat::StlAscii;
        }
    }
    match first_data {
        Some(tok) if off::is_off_keyword(tok) => InputFormat::Off,
        Some(tok) if pcd::PCD_KEYWORDS.contains(&tok) => InputFormat::Pcd,
        Some(tok) if obj::OBJ_KEYWORDS.contains(&tok) => InputFormat::Obj,
        _ => InputFormat::Xyz,
    }
}

fn sniff_ply_encoding(head: &[u8]) -> InputFormat {
    for line in head.split(|&b| b == b'\n').take(64) {
        let mut words = line.split(|b| b.is_ascii_whitespace()).filter(|w| !w.is_empty());
        if words.next() == Some(b"format") {
            return match words.next() {
                Some(b"binary_little_endian") => InputFormat::PlyBinaryLe,
                Some(b"binary_big_endian") => InputFormat::PlyBinaryBe,
                _ => InputFormat::PlyAscii,
            };
        }
    }
    InputFormat::PlyAscii
}

/// What the caller wants from an input.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Want {
    /// A mesh when the input is one, a cloud otherwise.
    Any,
    /// A cloud: a PLY's faces are not read (its vertex attributes are kept), an STL's welded
    /// vertices become the cloud.
    Cloud,
    /// A mesh: a cloud input is an error, detected before the body is read.
    Mesh,
}

/// Reads a point cloud or a mesh from `r`, sniffing the format ([`sniff_format`]) from its first
/// bytes. `name` names the input in errors (the file name); `size` is the input's total size when
/// known: it enables the binary-STL size test, the `max_bytes` check before reading, and exact
/// pre-allocation.
pub fn read_any_from<R: BufRead>(
    r: R,
    name: &str,
    size: Option<u64>,
    limits: &ReadLimits,
) -> Result<(Geometry, ReadStats)> {
    read_with(r, name, size, limits, Want::Any, None)
}

/// Reads the point cloud or mesh in the file at `path` (see [`read_any_from`]); errors name the
/// path as given.
pub fn read_any(path: &Path, limits: &ReadLimits) -> Result<(Geometry, ReadStats)> {
    read_path(path, limits, Want::Any)
}

/// Reads a point cloud from `path`. A mesh input is accepted: a PLY mesh's vertices come with their
/// intensity and normals (the faces are not read), an STL's welded vertices become bare points.
pub fn read_cloud(path: &Path, limits: &ReadLimits) -> Result<(PointCloud, ReadStats)> {
    read_path(path, limits, Want::Cloud).map(|(g, s)| (g.into_cloud(), s))
}

/// Reads a mesh from `path`: STL, OBJ or OFF with faces, or PLY with a non-empty face element.
/// Anything else is [`FormatError::UnsupportedFormat`] naming the file, reported before the body is
/// read (an OBJ or OFF without faces once it is read).
pub fn read_mesh(path: &Path, limits: &ReadLimits) -> Result<(Mesh, ReadStats)> {
    let name = path.display().to_string();
    match read_path(path, limits, Want::Mesh)? {
        (Geometry::Mesh(m), s) => Ok((m, s)),
        (Geometry::Cloud(_), _) => Err(not_a_mesh(&name, "the input is a point cloud")),
    }
}

fn read_path(path: &Path, limits: &ReadLimits, want: Want) -> Result<(Geometry, ReadStats)> {
    let name = path.display().to_string();
    let file = File::open(path).map_err(|source| FormatError::Io { file: name.clone(), source })?;
    let size = file.metadata().map_err(|source| FormatError::Io { file: name.clone(), source })?.len();
    read_with(BufReader::with_capacity(BUF_LEN, file), &name, Some(size), limits, want, None)
}

pub(crate) fn not_a_mesh(name: &str, why: &str) -> FormatError {
    FormatError::UnsupportedFormat {
        file: name.to_string(),
        reason: format!("{why}; a mesh needs STL, OBJ or OFF with faces, or PLY with a face element"),
    }
}

/// A stream whose first bytes, read for sniffing, are replayed from memory.
pub(crate) type Replay<R> = io::Chain<Cursor<Vec<u8>>, R>;

/// Reads the first [`SNIFF_LEN`] bytes of `r` and returns the format they show with a stream that
/// replays them.
pub(crate) fn sniff<R: BufRead>(r: R, name: &str, size: Option<u64>) -> Result<(InputFormat, Replay<R>)> {
    let (head, r) = read_head(r, name)?;
    Ok((sniff_format(&head, size), r))
}

/// Reads the first [`SNIFF_LEN`] bytes of `r` and returns them with a stream that replays them.
fn read_head<R: BufRead>(mut r: R, name: &str) -> Result<(Vec<u8>, Replay<R>)> {
    let mut head = Vec::with_capacity(SNIFF_LEN);
    r.by_ref().take(SNIFF_LEN as u64).read_to_end(&mut head).map_err(|e| io_error(name, e))?;
    Ok((head.clone(), Cursor::new(head).chain(r)))
}

pub(crate) fn check_size(name: &str, size: Option<u64>, limits: &ReadLimits) -> Result<()> {
    match size {
        Some(s) if s > limits.max_bytes => Err(too_large(name, "bytes", s, limits.max_bytes)),
        _ => Ok(()),
    }
}

/// Reads a point cloud from `r` (XYZ, PLY: a mesh's vertices, STL: its welded vertices) keeping
/// a uniform sample of at most `keep` points, for a picture of a cloud of any size: XYZ, PLY, OBJ
/// and OFF are read in one streaming pass in memory flat in the input's size (every `2^k`-th point,
/// `k` growing as the points arrive), PCD too but for a compressed body's block; an STL is read
/// whole, then sampled. [`ReadStats::points`] is
/// the number of points the input holds.
pub fn sample_cloud_from<R: BufRead>(
    r: R,
    name: &str,
    size: Option<u64>,
    limits: &ReadLimits,
    keep: usize,
) -> Result<(PointCloud, ReadStats)> {
    read_with(r, name, size, limits, Want::Cloud, Some(keep)).map(|(g, s)| {
        let mut cloud = g.into_cloud();
        if cloud.points.len() > keep {
            // STL: the mesh's vertices, read whole.
            let stride = cloud.points.len().div_ceil(keep);
            cloud.points = cloud.points.into_iter().step_by(stride).collect();
            cloud.intensity = None;
            cloud.normals = None;
        }
        (cloud, s)
    })
}

fn read_with<R: BufRead>(
    r: R,
    name: &str,
    size: Option<u64>,
    limits: &ReadLimits,
    want: Want,
    keep: Option<usize>,
) -> Result<(Geometry, ReadStats)> {
    check_size(name, size, limits)?;
    let (head, r) = read_head(r, name)?;
    if is_gzip(&head) {
        // The decompressed size is not known up front: the readers stream and `Src` enforces
        // `max_bytes` on what comes out.
        let decoder = flate2::bufread::MultiGzDecoder::new(Counted { inner: r, taken: 0 });
        let inner = BufReader::with_capacity(BUF_LEN, Gunzip(decoder));
        let (head, inner) = read_head(inner, name)?;
        if is_gzip(&head) {
            return Err(parse_error(name, Location::Byte(0), "gzip: a gzip stream inside a gzip stream"));
        }
        return read_sniffed(sniff_format(&head, None), inner, name, None, limits, want, keep);
    }
    read_sniffed(sniff_format(&head, size), r, name, size, limits, want, keep)
}

/// The gzip member header's first two bytes.
pub const GZIP_MAGIC: [u8; 2] = [0x1f, 0x8b];

/// Whether `head` (the first bytes of an input) starts a gzip stream.
pub fn is_gzip(head: &[u8]) -> bool {
    head.starts_with(&GZIP_MAGIC)
}

/// A compressed stream that counts the bytes its decoder takes.
struct Counted<R> {
    inner: R,
    taken: u64,
}

impl<R: BufRead> Read for Counted<R> {
    fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
        let n = self.inner.read(buf)?;
        self.taken += n as u64;
        Ok(n)
    }
}

impl<R: BufRead> BufRead for Counted<R> {
    fn fill_buf(&mut self) -> io::Result<&[u8]> {
        self.inner.fill_buf()
    }
    fn consume(&mut self, amt: usize) {
        self.taken += amt as u64;
        self.inner.consume(amt);
    }
}

/// A fault of the compressed stream, carried through `io::Error` to [`io_error`].
#[derive(Debug)]
struct GzipFault {
    at: u64,
    problem: String,
}

impl fmt::Display for GzipFault {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "gzip: {} (after {} compressed bytes)", self.problem, self.at)
    }
}

impl std::error::Error for GzipFault {}

/// A gzip decoder whose faults of the compressed data (corrupt, cut short, a checksum that does
/// not match: the decoder's invalid-data and end-of-file errors) are [`GzipFault`]s; errors of
/// the stream under it pass through as they are.
struct Gunzip<R: BufRead>(flate2::bufread::MultiGzDecoder<Counted<R>>);

impl<R: BufRead> Read for Gunzip<R> {
    fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
        self.0.read(buf).map_err(|e| match e.kind() {
            io::ErrorKind::InvalidInput | io::ErrorKind::InvalidData | io::ErrorKind::UnexpectedEof => {
                let at = self.0.get_ref().taken;
                io::Error::new(io::ErrorKind::InvalidData, GzipFault { at, problem: e.to_string() })
            }
            _ => e,
        })
    }
}

#[allow(clippy::too_many_arguments)]
fn read_sniffed<R: BufRead>(
    format: InputFormat,
    r: R,
    name: &str,
    size: Option<u64>,
    limits: &ReadLimits,
    want: Want,
    keep: Option<usize>,
) -> Result<(Geometry, ReadStats)> {
    let mut src = Src::new(r, limits.max_bytes);
    match format {
        InputFormat::Xyz => {
            if want == Want::Mesh {
                return Err(not_a_mesh(name, "the input is XYZ text, a point cloud"));
            }
            xyz::read_xyz_src(&mut src, name, limits, keep).map(|(c, s)| (Geometry::Cloud(c), s))
        }
        InputFormat::PlyAscii | InputFormat::PlyBinaryLe | InputFormat::PlyBinaryBe => {
            let opts = ply::Options { want, pass: None, force_var: false, keep };
            ply::read_ply_src(&mut src, name, size, limits, opts).map(|o| (o.geometry, o.stats))
        }
        InputFormat::StlAscii | InputFormat::StlBinary => {
            let (mesh, stats) = if format == InputFormat::StlAscii {
                stl::read_stl_ascii_src(&mut src, name, limits)?
            } else {
                stl::read_stl_binary_src(&mut src, name, size, limits)?
            };
            Ok(match want {
                Want::Cloud => (Geometry::Cloud(PointCloud::from_points(mesh.vertices)), stats),
                _ => (Geometry::Mesh(mesh), stats),
            })
        }
        InputFormat::Off | InputFormat::Obj => {
            let read = if format == InputFormat::Off { off::read_off_src } else { obj::read_obj_src };
            let (geometry, stats) = read(&mut src, name, limits, want == Want::Cloud, keep)?;
            if want == Want::Mesh && matches!(geometry, Geometry::Cloud(_)) {
                return Err(not_a_mesh(name, &format!("the {format} file has no faces, a point cloud")));
            }
            Ok((geometry, stats))
        }
        InputFormat::Pcd => {
            if want == Want::Mesh {
                return Err(not_a_mesh(name, "the input is PCD, a point cloud"));
            }
            pcd::read_pcd_src(&mut src, name, limits, keep).map(|(c, s)| (Geometry::Cloud(c), s))
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Errors.

/// [`FormatError::Parse`].
pub(crate) fn parse_error(name: &str, at: Location, problem: impl Into<String>) -> FormatError {
    FormatError::Parse { file: name.to_string(), at, problem: problem.into() }
}

/// [`FormatError::TooLarge`].
pub(crate) fn too_large(name: &str, what: &'static str, value: u64, limit: u64) -> FormatError {
    FormatError::TooLarge { file: name.to_string(), what, value, limit }
}

/// The stream went past `max_bytes` ([`Src`] reports it through `io::Error`).
#[derive(Debug)]
struct ByteLimit {
    limit: u64,
}

impl fmt::Display for ByteLimit {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "input longer than {} bytes", self.limit)
    }
}

impl std::error::Error for ByteLimit {}

/// Maps an I/O error to [`FormatError::Io`], or [`FormatError::TooLarge`] when it is [`Src`]'s
/// byte limit.
pub(crate) fn io_error(name: &str, e: io::Error) -> FormatError {
    if let Some(limit) = e.get_ref().and_then(|inner| inner.downcast_ref::<ByteLimit>()).map(|b| b.limit) {
        return too_large(name, "bytes", limit.saturating_add(1), limit);
    }
    if let Some(g) = e.get_ref().and_then(|inner| inner.downcast_ref::<GzipFault>()) {
        return FormatError::Gzip { file: name.to_string(), at: g.at, problem: g.problem.clone() };
    }
    FormatError::Io { file: name.to_string(), source: e }
}

/// A token for an error message: lossy UTF-8, at most 40 characters, quoted and escaped.
pub(crate) fn show_token(tok: &[u8]) -> String {
    let text = String::from_utf8_lossy(tok);
    let mut short: String = text.chars().take(40).collect();
    if text.chars().nth(40).is_some() {
        short.push('…');
    }
    format!("{short:?}")
}

// ---------------------------------------------------------------------------------------------
// The byte source.

/// A [`BufRead`] wrapper that counts the bytes consumed (the offset errors name) and fails with
/// [`ByteLimit`] once more than `max` bytes would be consumed.
pub(crate) struct Src<R> {
    inner: R,
    pos: u64,
    max: u64,
}

impl<R: BufRead> Src<R> {
    pub(crate) fn new(inner: R, max: u64) -> Self {
        Src { inner, pos: 0, max }
    }

    /// Bytes consumed so far: the 0-based offset of the next byte.
    pub(crate) fn pos(&self) -> u64 {
        self.pos
    }

    /// Fills `out` completely; `Ok(false)` when the input ends first (`pos` is then the end).
    pub(crate) fn read_bytes(&mut self, out: &mut [u8]) -> io::Result<bool> {
        let mut filled = 0;
        while filled < out.len() {
            let buf = self.fill_buf()?;
            if buf.is_empty() {
                return Ok(false);
            }
            let k = (out.len() - filled).min(buf.len());
            out[filled..filled + k].copy_from_slice(&buf[..k]);
            self.consume(k);
            filled += k;
        }
        Ok(true)
    }

    /// Skips up to `n` bytes; returns how many were skipped (fewer at the end of the input).
    pub(crate) fn skip(&mut self, n: u64) -> io::Result<u64> {
        let mut left = n;
        while left > 0 {
            let buf = self.fill_buf()?;
            if buf.is_empty() {
                break;
            }
            let k = (buf.len() as u64).min(left) as usize;
            self.consume(k);
            left -= k as u64;
        }
        Ok(n - left)
    }

    /// Feeds up to `n` records of `rec` bytes to `f`, many at a time, straight from the reader's
    /// buffer (a record split across two buffer fills is assembled in a small carry buffer).
    /// Returns how many records were fed: fewer than `n` means the input ended.
    pub(crate) fn records(
        &mut self,
        rec: usize,
        n: u64,
        name: &str,
        mut f: impl FnMut(&[u8]) -> Result<()>,
    ) -> Result<u64> {
        let rec = rec.max(1);
        let mut done = 0u64;
        let mut carry: Vec<u8> = Vec::new();
        while done < n {
            let buf = self.fill_buf().map_err(|e| io_error(name, e))?;
            if buf.is_empty() {
                break;
            }
            if !carry.is_empty() {
                let k = (rec - carry.len()).min(buf.len());
                carry.extend_from_slice(&buf[..k]);
                self.consume(k);
                if carry.len() == rec {
                    f(&carry)?;
                    carry.clear();
                    done += 1;
                }
                continue;
            }
            let whole = ((buf.len() / rec) as u64).min(n - done) as usize;
            if whole == 0 {
                let k = buf.len();
                carry.extend_from_slice(buf);
                self.consume(k);
                continue;
            }
            let bytes = whole * rec;
            f(&buf[..bytes])?;
            self.consume(bytes);
            done += whole as u64;
        }
        Ok(done)
    }
}

impl<R: BufRead> Read for Src<R> {
    fn read(&mut self, out: &mut [u8]) -> io::Result<usize> {
        let buf = self.fill_buf()?;
        let k = buf.len().min(out.len());
        out[..k].copy_from_slice(&buf[..k]);
        self.consume(k);
        Ok(k)
    }
}

impl<R: BufRead> BufRead for Src<R> {
    fn fill_buf(&mut self) -> io::Result<&[u8]> {
        let (pos, max) = (self.pos, self.max);
        let buf = self.inner.fill_buf()?;
        if buf.is_empty() {
            return Ok(buf);
        }
        if pos >= max {
            return Err(io::Error::other(ByteLimit { limit: max }));
        }
        let allowed = (max - pos).min(buf.len() as u64) as usize;
        Ok(&buf[..allowed])
    }

    fn consume(&mut self, amt: usize) {
        self.pos += amt as u64;
        self.inner.consume(amt);
    }
}

/// Line-by-line reading of a text body into one reused buffer, counting lines.
pub(crate) struct Lines {
    /// The current line, without its `\n` or `\r\n`.
    pub(crate) buf: Vec<u8>,
    /// 1-based number of the current line (0 before the first).
    pub(crate) line: u64,
}

impl Lines {
    /// Starts counting after `lines_before` lines (e.g. a PLY header).
    pub(crate) fn new(lines_before: u64) -> Self {
        Lines { buf: Vec::with_capacity(256), line: lines_before }
    }

    /// Reads the next line; `false` at the end of the input. A line longer than
    /// [`MAX_LINE_LEN`] is an error.
    pub(crate) fn next<R: BufRead>(&mut self, src: &mut Src<R>, name: &str) -> Result<bool> {
        self.buf.clear();
        let n = src
            .by_ref()
            .take(MAX_LINE_LEN as u64 + 1)
            .read_until(b'\n', &mut self.buf)
            .map_err(|e| io_error(name, e))?;
        if n == 0 {
            return Ok(false);
        }
        self.line += 1;
        if self.buf.last() == Some(&b'\n') {
            self.buf.pop();
        } else if self.buf.len() > MAX_LINE_LEN {
            return Err(parse_error(
                name,
                Location::Line(self.line),
                format!("line longer than {MAX_LINE_LEN} bytes"),
            ));
        }
        if self.buf.last() == Some(&b'\r') {
            self.buf.pop();
        }
        Ok(true)
    }
}

/// Separators between text tokens: white space (and commas, for XYZ).
#[inline]
pub(crate) const fn is_space(b: u8) -> bool {
    matches!(b, b' ' | b'\t' | b'\r' | 0x0b | 0x0c)
}

/// The data of a text line: what comes before its `#` (OBJ, OFF and PCD comments).
pub(crate) fn before_comment(line: &[u8]) -> &[u8] {
    line.iter().position(|&b| b == b'#').map_or(line, |k| &line[..k])
}

/// Splits `line` into tokens separated by bytes for which `sep` is true, without allocating.
pub(crate) fn tokens(line: &[u8], sep: impl Fn(u8) -> bool + Copy) -> impl Iterator<Item = &[u8]> {
    line.split(move |&b| sep(b)).filter(|t| !t.is_empty())
}

/// Parses a decimal floating-point token (`1`, `-2.5`, `3e-4`, `.5`, `nan`, `inf`) to `f64`.
///
/// Uses `fast-float2` (Eisel–Lemire, straight on bytes): in this crate's measurement about twice as
/// fast as `str::parse` plus the UTF-8 check a `&str` needs, with the same results.
#[inline]
pub(crate) fn parse_f64(tok: &[u8]) -> Option<f64> {
    fast_float2::parse::<f64, _>(tok).ok()
}

/// Parses the number at the start of `text`: its value and length in bytes (`None` if `text`
/// does not start with one).
#[inline]
pub(crate) fn parse_f64_prefix(text: &[u8]) -> Option<(f64, usize)> {
    fast_float2::parse_partial::<f64, _>(text).ok()
}

/// As [`parse_f64_prefix`], straight to `f32`.
#[inline]
pub(crate) fn parse_f32_prefix(text: &[u8]) -> Option<(f32, usize)> {
    fast_float2::parse_partial::<f32, _>(text).ok()
}

/// As [`parse_f64`], rounding the decimal once, straight to `f32` (no double rounding).
#[inline]
pub(crate) fn parse_f32(tok: &[u8]) -> Option<f32> {
    fast_float2::parse::<f32, _>(tok).ok()
}

// ---------------------------------------------------------------------------------------------
// The cloud being built.

/// A sink's points: single precision for a cloud, double for a mesh's vertices.
pub(crate) enum SinkPoints {
    Single(Vec<Point3<f32>>),
    Double(Vec<Point3<f64>>),
}

impl SinkPoints {
    fn len(&self) -> usize {
        match self {
            SinkPoints::Single(v) => v.len(),
            SinkPoints::Double(v) => v.len(),
        }
    }
}

/// Parallel arrays of a cloud under construction, applying the non-finite rule on push.
pub(crate) struct CloudSink {
    pub(crate) points: SinkPoints,
    pub(crate) intensity: Option<Vec<f32>>,
    pub(crate) normals: Option<Vec<Vector3<f32>>>,
    pub(crate) pass: Option<Vec<u16>>,
    /// Points dropped for non-finite values.
    pub(crate) dropped: u64,
    /// Input indices of the dropped points, when tracked (a mesh needs them to renumber faces).
    pub(crate) dropped_at: Option<Vec<u64>>,
    /// Points pushed so far, kept or not.
    pub(crate) seen: u64,
    /// Finite points pushed so far (what the input holds; more than `points` when sampling).
    accepted: u64,
    /// Sampling: at most this many points are kept, every `stride_mask + 1`-th finite point (a
    /// power of two, so the test in [`CloudSink::push`] is a mask, not a division).
    keep: Option<usize>,
    stride_mask: u64,
}

impl CloudSink {
    /// An empty sink with the given arrays, reserving `reserve` points. `track_dropped` is for
    /// a mesh's vertices: they are kept in double precision, with the indices of those dropped.
    pub(crate) fn new(
        intensity: bool,
        normals: bool,
        pass: bool,
        track_dropped: bool,
        reserve: usize,
    ) -> Self {
        CloudSink {
            points: if track_dropped {
                SinkPoints::Double(Vec::with_capacity(reserve))
            } else {
                SinkPoints::Single(Vec::with_capacity(reserve))
            },
            intensity: intensity.then(|| Vec::with_capacity(reserve)),
            normals: normals.then(|| Vec::with_capacity(reserve)),
            pass: pass.then(|| Vec::with_capacity(reserve)),
            dropped: 0,
            dropped_at: track_dropped.then(Vec::new),
            seen: 0,
            accepted: 0,
            keep: None,
            stride_mask: 0,
        }
    }

    /// Keeps a uniform sample of at most `keep` points (every k-th finite point, k a power of
    /// two that doubles each time the sample fills up), so memory stays flat whatever the
    /// input's size. Not for a mesh: its faces index every vertex. (Reserve at most `keep`.)
    pub(crate) fn sampled(mut self, keep: Option<usize>) -> Self {
        self.keep = keep.map(|k| k.max(2));
        self
    }

    /// Drops every other kept point: the sample is then every `2 * (stride_mask + 1)`-th finite
    /// point.
    fn halve(&mut self) {
        fn odd_out<T: Copy>(v: &mut Vec<T>) {
            let mut i = 0;
            v.retain(|_| {
                i += 1;
                i % 2 == 1
            });
        }
        match &mut self.points {
            SinkPoints::Single(v) => odd_out(v),
            SinkPoints::Double(v) => odd_out(v),
        }
        if let Some(v) = &mut self.intensity {
            odd_out(v);
        }
        if let Some(v) = &mut self.normals {
            odd_out(v);
        }
        if let Some(v) = &mut self.pass {
            odd_out(v);
        }
        self.stride_mask = self.stride_mask * 2 + 1;
    }

    /// Adds one point; the arrays the sink does not have ignore their argument. A cloud's point
    /// is rounded to single precision first: one beyond its range (about 3.4e38) counts as not
    /// finite.
    #[inline(always)]
    pub(crate) fn push(&mut self, p: [f64; 3], intensity: f32, normal: [f32; 3], pass: u16) {
        let index = self.seen;
        self.seen += 1;
        let intensity_ok = self.intensity.is_none() || intensity.is_finite();
        let single = Point3::new(p[0] as f32, p[1] as f32, p[2] as f32);
        let finite = match self.points {
            SinkPoints::Single(_) => single.x.is_finite() && single.y.is_finite() && single.z.is_finite(),
            SinkPoints::Double(_) => p[0].is_finite() && p[1].is_finite() && p[2].is_finite(),
        };
        if !(finite && intensity_ok) {
            self.dropped += 1;
            if let Some(d) = &mut self.dropped_at {
                d.push(index);
            }
            return;
        }
        let k = self.accepted;
        self.accepted += 1;
        if k & self.stride_mask != 0 {
            return;
        }
        match &mut self.points {
            SinkPoints::Single(v) => v.push(single),
            SinkPoints::Double(v) => v.push(Point3::new(p[0], p[1], p[2])),
        }
        if let Some(v) = &mut self.intensity {
            v.push(intensity);
        }
        if let Some(v) = &mut self.normals {
            let n = if normal.iter().all(|c| c.is_finite()) { normal } else { [0.0; 3] };
            v.push(Vector3::new(n[0], n[1], n[2]));
        }
        if let Some(v) = &mut self.pass {
            v.push(pass);
        }
        if self.keep.is_some_and(|keep| self.points.len() >= keep) {
            self.halve();
        }
    }

    /// Finite points read so far (all kept, unless sampling).
    pub(crate) fn len(&self) -> u64 {
        self.accepted
    }

    /// The cloud and the pass ids.
    pub(crate) fn into_cloud(self) -> (PointCloud, Option<Vec<u16>>) {
        let points = match self.points {
            SinkPoints::Single(v) => v,
            SinkPoints::Double(v) => v.iter().map(crate::cloud::single).collect(),
        };
        (PointCloud { points, intensity: self.intensity, normals: self.normals }, self.pass)
    }

    /// A mesh's vertices, in double precision.
    pub(crate) fn into_vertices(self) -> Vec<Point3<f64>> {
        match self.points {
            SinkPoints::Single(v) => v.iter().map(CloudPoint::at).collect(),
            SinkPoints::Double(v) => v,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sniff_formats() {
        assert_eq!(sniff_format(b"ply\nformat ascii 1.0\n", None), InputFormat::PlyAscii);
        assert_eq!(
            sniff_format(b"ply\r\nformat binary_little_endian 1.0\r\n", None),
            InputFormat::PlyBinaryLe
        );
        assert_eq!(sniff_format(b"ply\nformat binary_big_endian 1.0\n", None), InputFormat::PlyBinaryBe);
        assert_eq!(sniff_format(b"solid cube\n facet normal 0 0 1\n", None), InputFormat::StlAscii);
        assert_eq!(sniff_format(b"  SOLID x\nendsolid x\n", None), InputFormat::StlAscii);
        assert_eq!(sniff_format(b"1 2 3\n4 5 6\n", None), InputFormat::Xyz);
        assert_eq!(sniff_format(b"# solid facet\n1 2 3\n", None), InputFormat::Xyz);
        assert_eq!(sniff_format(b"", None), InputFormat::Xyz);
        // A binary STL whose header starts with "solid" and has text in it, told by its size.
        let mut stl = b"solid binary facet".to_vec();
        stl.resize(80, b' ');
        stl.extend_from_slice(&2u32.to_le_bytes());
        stl.resize(84 + 100, b'x');
        assert_eq!(sniff_format(&stl, Some(184)), InputFormat::StlBinary);
        // Without the right size, its binary bytes give it away.
        assert_eq!(sniff_format(&stl, Some(185)), InputFormat::StlBinary);
        assert_eq!(sniff_format(&stl, None), InputFormat::StlBinary);
        // A long ASCII STL with the size known is not mistaken for binary.
        let mut text = b"solid x\n".to_vec();
        while text.len() < 200 {
            text.extend_from_slice(b"facet normal 0 0 1\n");
        }
        assert_eq!(sniff_format(&text, Some(text.len() as u64)), InputFormat::StlAscii);
        let mut bin = vec![0u8; 84];
        bin.extend_from_slice(&[0x80, 0x3f, 0, 0]);
        assert_eq!(sniff_format(&bin, None), InputFormat::StlBinary);
    }

    #[test]
    fn src_counts_and_limits() {
        let data = b"0123456789".to_vec();
        let mut src = Src::new(BufReader::with_capacity(3, Cursor::new(data.clone())), 100);
        let mut out = [0u8; 4];
        assert!(src.read_bytes(&mut out).expect("read"));
        assert_eq!((&out, src.pos()), (b"0123", 4));
        assert_eq!(src.skip(3).expect("skip"), 3);
        let mut got = Vec::new();
        let n = src
            .records(2, 10, "t", |c| {
                got.extend_from_slice(c);
                Ok(())
            })
            .expect("records");
        assert_eq!((n, got.as_slice(), src.pos()), (1, &b"78"[..], 10));
        assert!(!src.read_bytes(&mut out).expect("eof"));

        // The limit: exactly `max` bytes are fine, one more is TooLarge.
        let mut src = Src::new(Cursor::new(data.clone()), 10);
        assert_eq!(src.skip(20).expect("exactly max"), 10);
        let mut src = Src::new(Cursor::new(data), 9);
        let e = io_error("f.xyz", src.skip(20).expect_err("over"));
        assert_eq!(e.to_string(), "f.xyz: bytes 10 exceeds the limit of 9");
    }

    #[test]
    fn records_assembles_split_records() {
        // Random buffer sizes and record sizes: the bytes fed equal the input, in order.
        for cap in 1..12 {
            for rec in 1..9 {
                let data: Vec<u8> = (0..100u8).collect();
                let mut src = Src::new(BufReader::with_capacity(cap, Cursor::new(data.clone())), 1000);
                let mut got = Vec::new();
                let n = src
                    .records(rec, 7, "t", |c| {
                        assert_eq!(c.len() % rec, 0);
                        got.extend_from_slice(c);
                        Ok(())
                    })
                    .expect("records");
                assert_eq!(n, 7);
                assert_eq!(got, data[..7 * rec]);
                assert_eq!(src.pos(), 7 * rec as u64);
            }
        }
    }

    #[test]
    fn lines_strip_terminators_and_limit_length() {
        let mut src = Src::new(Cursor::new(b"a b\r\nc\n\nlast".to_vec()), 1000);
        let mut lines = Lines::new(0);
        let mut got = Vec::new();
        while lines.next(&mut src, "t").expect("line") {
            got.push((lines.line, String::from_utf8_lossy(&lines.buf).into_owned()));
        }
        let want: Vec<(u64, String)> =
            vec![(1, "a b".into()), (2, "c".into()), (3, "".into()), (4, "last".into())];
        assert_eq!(got, want);
        let long = vec![b'1'; MAX_LINE_LEN + 10];
        let mut src = Src::new(Cursor::new(long), u64::MAX);
        let e = Lines::new(0).next(&mut src, "big.xyz").expect_err("long");
        assert_eq!(e.to_string(), format!("big.xyz: line 1: line longer than {MAX_LINE_LEN} bytes"));
    }

    #[test]
    fn show_token_truncates_and_escapes() {
        assert_eq!(show_token(b"abc"), "\"abc\"");
        assert_eq!(show_token(&[b'x'; 50]), format!("\"{}…\"", "x".repeat(40)));
        assert_eq!(show_token(b"a\0\xff"), "\"a\\0\u{fffd}\"");
    }

    #[test]
    fn parse_numbers() {
        assert_eq!(parse_f64(b"-2.5e1"), Some(-25.0));
        assert_eq!(parse_f64(b".5"), Some(0.5));
        assert!(parse_f64(b"nan").is_some_and(f64::is_nan));
        assert_eq!(parse_f64(b"-inf"), Some(f64::NEG_INFINITY));
        assert_eq!(parse_f64(b"1,5"), None);
        assert_eq!(parse_f64(b""), None);
        assert_eq!(parse_f32(b"0.1"), Some(0.1f32));
    }

    /// A binary STL of one triangle.
    fn one_triangle_stl() -> Vec<u8> {
        let mut v = vec![0u8; 80];
        v.extend_from_slice(&1u32.to_le_bytes());
        v.extend_from_slice(&[0u8; 12]);
        for f in [0f32, 0., 0., 1., 0., 0., 0., 1., 0.] {
            v.extend_from_slice(&f.to_le_bytes());
        }
        v.extend_from_slice(&[0, 0]);
        v
    }

    fn gzip(bytes: &[u8]) -> Vec<u8> {
        use std::io::Write as _;
        let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::default());
        e.write_all(bytes).expect("compress");
        e.finish().expect("compress")
    }

    /// Every format reads the same compressed as plain (sniffed by content, not by name); the
    /// limits count decompressed bytes; a cut, corrupt or nested stream is refused naming the file.
    #[test]
    fn gzip_inputs_read_as_their_content() {
        let limits = ReadLimits::default();
        let read = |bytes: &[u8], limits: &ReadLimits| {
            read_any_from(Cursor::new(bytes.to_vec()), "part.gz", Some(bytes.len() as u64), limits)
        };
        let mut big_stl = vec![0u8; 80];
        big_stl.extend_from_slice(&300u32.to_le_bytes());
        for t in 0..300u32 {
            big_stl.extend_from_slice(&[0u8; 12]);
            let x = t as f32;
            for f in [x, 0., 0., x + 1., 0., 0., x, 1., 0.] {
                big_stl.extend_from_slice(&f.to_le_bytes());
            }
            big_stl.extend_from_slice(&[0, 0]);
        }
        let inputs: Vec<Vec<u8>> = vec![
            b"1 2 3\n4 5 6.5\n".to_vec(),
            one_triangle_stl(),
            big_stl.clone(),
            b"solid t\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 0 0\nvertex 0 1 0\nendloop\nendfacet\nendsolid t\n".to_vec(),
            b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\nend_header\n4 5 6\n1 1 1\n".to_vec(),
            b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n".to_vec(),
            b"OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n".to_vec(),
            b"VERSION .7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 1\nHEIGHT 1\nPOINTS 1\nDATA ascii\n1 2 3\n".to_vec(),
        ];
        for plain in &inputs {
            let (g, s) = read(plain, &limits).expect("plain");
            let packed = gzip(plain);
            assert!(is_gzip(&packed));
            let (gz, sz) = read(&packed, &limits).expect("gzip");
            assert_eq!(gz, g);
            assert_eq!((sz.format, sz.points, sz.triangles), (s.format, s.points, s.triangles));
        }
        // Two members one after the other (`cat a.gz b.gz`) are one stream, as gunzip reads them.
        let mut two = gzip(b"1 2 3\n");
        two.extend_from_slice(&gzip(b"4 5 6\n"));
        let (g, _) = read(&two, &limits).expect("two members");
        assert!(matches!(g, Geometry::Cloud(ref c) if c.points.len() == 2));
        // The byte limit holds on what comes out, however small the archive.
        let zeros = gzip(&b"0 0 0\n".repeat(200_000));
        assert!(zeros.len() < 10_000);
        let tight = ReadLimits { max_bytes: 100_000, ..ReadLimits::default() };
        let e = read(&zeros, &tight).expect_err("expands past the limit").to_string();
        assert!(e.contains("part.gz") && e.contains("100000"), "{e}");
        // Cut short, corrupt, nested: errors naming the file and the gzip stream.
        let packed = gzip(&big_stl);
        let e = read(&packed[..packed.len() / 2], &limits).expect_err("cut").to_string();
        assert!(e.contains("part.gz") && e.contains("gzip"), "{e}");
        let mut bad = packed.clone();
        for b in &mut bad[20..60] {
            *b ^= 0x5a;
        }
        let e = read(&bad, &limits).expect_err("corrupt").to_string();
        assert!(e.contains("part.gz") && e.contains("gzip"), "{e}");
        let e = read(&gzip(&gzip(b"1 2 3\n")), &limits).expect_err("nested").to_string();
        assert!(e.contains("part.gz") && e.contains("gzip stream inside"), "{e}");
        // The unit sniffing reads the content's header.
        let dir = tempfile::tempdir().expect("dir");
        let path = dir.path().join("part.ply.gz");
        std::fs::write(&path, gzip(b"ply\nformat ascii 1.0\ncomment units mm\nend_header\n")).expect("write");
        let head = crate::units::read_head(&path).expect("head");
        assert!(head.starts_with(b"ply\nformat ascii"), "{}", String::from_utf8_lossy(&head));
    }

    #[test]
    fn read_any_dispatches_on_the_sniffed_format() {
        let limits = ReadLimits::default();
        let any = |bytes: &[u8]| {
            read_any_from(Cursor::new(bytes.to_vec()), "in", Some(bytes.len() as u64), &limits)
        };
        let (g, s) = any(b"1 2 3\n").expect("xyz");
        assert_eq!(
            (g, s.format),
            (Geometry::Cloud(PointCloud::from_points(vec![Point3::new(1.0, 2.0, 3.0)])), InputFormat::Xyz)
        );
        let (g, s) = any(&one_triangle_stl()).expect("stl");
        assert!(matches!(g, Geometry::Mesh(ref m) if m.triangles == vec![[0, 1, 2]]));
        assert_eq!(s.format, InputFormat::StlBinary);
        let ascii = b"solid t\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 0 0\nvertex 0 1 0\nendloop\nendfacet\nendsolid t\n";
        let (g2, s) = any(ascii).expect("ascii stl");
        assert_eq!((g2, s.format), (g, InputFormat::StlAscii));
        let ply = b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nend_header\n4 5 6\n";
        let (g, s) = any(ply).expect("ply");
        assert_eq!(
            (g.into_cloud().points, s.format),
            (vec![Point3::new(4.0, 5.0, 6.0)], InputFormat::PlyAscii)
        );
        // The size limit is checked against the known size before anything is read.
        let tight = ReadLimits { max_bytes: 5, ..limits };
        let e = read_any_from(Cursor::new(b"1 2 3\n".to_vec()), "in", Some(6), &tight).expect_err("size");
        assert_eq!(e.to_string(), "in: bytes 6 exceeds the limit of 5");
    }

    #[test]
    fn path_readers() {
        let dir = tempfile::tempdir().expect("tempdir");
        let limits = ReadLimits::default();
        let xyz = dir.path().join("cloud.xyz");
        std::fs::write(&xyz, "1 2 3 0.5\n").expect("write");
        let stl = dir.path().join("tri.stl");
        std::fs::write(&stl, one_triangle_stl()).expect("write");
        let ply = dir.path().join("mesh.ply");
        std::fs::write(
            &ply,
            "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n\
             property float intensity\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n\
             0 0 0 1\n1 0 0 2\n0 1 0 3\n3 0 1 2\n",
        )
        .expect("write");

        let (c, s) = read_cloud(&xyz, &limits).expect("xyz cloud");
        assert_eq!((c.intensity, s.points), (Some(vec![0.5]), 1));
        let e = read_mesh(&xyz, &limits).expect_err("xyz is no mesh");
        assert!(matches!(e, FormatError::UnsupportedFormat { .. }));
        assert!(
            e.to_string()
                .starts_with(&format!("{}: unsupported format: the input is XYZ text", xyz.display())),
            "{e}"
        );

        let (m, s) = read_mesh(&stl, &limits).expect("stl mesh");
        assert_eq!((m.vertices.len(), s.triangles), (3, 1));
        let (c, _) = read_cloud(&stl, &limits).expect("stl cloud");
        assert_eq!(c.len(), 3);

        let (m, s) = read_mesh(&ply, &limits).expect("ply mesh");
        assert_eq!((m.triangles, s.ignored_properties), (vec![[0, 1, 2]], vec!["intensity".to_string()]));
        // As a cloud, a PLY mesh keeps its vertex attributes.
        let (c, _) = read_cloud(&ply, &limits).expect("ply cloud");
        assert_eq!(c.intensity, Some(vec![1.0, 2.0, 3.0]));
        assert!(matches!(read_any(&ply, &limits), Ok((Geometry::Mesh(_), _))));

        let missing = dir.path().join("missing.ply");
        let e = read_any(&missing, &limits).expect_err("missing");
        assert!(matches!(e, FormatError::Io { ref file, .. } if file.ends_with("missing.ply")));
    }

    proptest::proptest! {
        #[test]
        fn random_bytes_never_panic(bytes in proptest::collection::vec(proptest::num::u8::ANY, 0..2000),
                                    prefix in 0usize..5, known in proptest::bool::ANY) {
            let mut input = [&b""[..], b"ply\n", b"solid x\nfacet ", b"ply\nformat binary_little_endian 1.0\nelement vertex 9\nproperty float x\nproperty float y\nproperty float z\nend_header\n",
                             b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\nelement face 3\nproperty list uchar int vertex_indices\nend_header\n"][prefix].to_vec();
            input.extend_from_slice(&bytes);
            let size = known.then_some(input.len() as u64);
            let limits = ReadLimits { max_bytes: 1 << 20, max_points: 1 << 16, max_triangles: 1 << 16 };
            let _ = read_any_from(Cursor::new(input.clone()), "fuzz", size, &limits);
            let _ = read_stl_from(Cursor::new(input), "fuzz", size, &limits);
        }
    }

    proptest::proptest! {
        /// The streaming sample against the obvious reference: every `s`-th finite point for the
        /// smallest power of two `s` that keeps fewer than `keep`, in XYZ, OBJ, OFF and every PLY
        /// encoding, with the input's point count reported.
        #[test]
        fn sampling_keeps_every_power_of_two_th_point(
            n in 0usize..3000,
            keep in 2usize..300,
            holes in proptest::collection::vec(0usize..3000, 0..20),
            encoding in 0usize..3,
        ) {
            let all: Vec<[f64; 3]> = (0..n)
                .map(|i| {
                    let t = i as f64;
                    if holes.contains(&i) { [f64::NAN, t, 0.0] } else { [t, (t * 0.37).sin(), (t * 0.11).cos()] }
                })
                .collect();
            let finite: Vec<[f64; 3]> = all.iter().copied().filter(|p| p[0].is_finite()).collect();
            let mut stride = 1usize;
            while finite.len().div_ceil(stride) >= keep {
                stride *= 2;
            }
            let expected: Vec<[f64; 3]> = finite.iter().copied().step_by(stride).collect();
            let inputs: Vec<Vec<u8>> = {
                let text: String = all.iter().map(|p| format!("{} {} {}\n", p[0], p[1], p[2])).collect();
                let cloud = PointCloud::from_points(all.iter().map(|p| Point3::new(p[0], p[1], p[2])));
                let enc = [PlyEncoding::Ascii, PlyEncoding::BinaryLittleEndian, PlyEncoding::BinaryBigEndian][encoding];
                let mut ply_bytes = Vec::new();
                ply::write_ply(&mut ply_bytes, &cloud, None, enc, &[]).expect("write");
                let obj: String = all.iter().map(|p| format!("v {} {} {}\n", p[0], p[1], p[2])).collect();
                let off = format!("OFF\n{n} 0 0\n{text}");
                vec![text.into_bytes(), ply_bytes, obj.into_bytes(), off.into_bytes()]
            };
            for input in inputs {
                if n == 0 && !input.starts_with(b"ply") && !input.starts_with(b"OFF") {
                    continue; // empty XYZ (or OBJ) text is not a cloud
                }
                let size = Some(input.len() as u64);
                let (c, stats) = sample_cloud_from(Cursor::new(input), "sample", size, &ReadLimits::default(), keep)
                    .expect("sample");
                let got: Vec<[f64; 3]> = c.points.iter().map(|p| [p.x, p.y, p.z].map(f64::from)).collect();
                proptest::prop_assert_eq!(stats.points, finite.len() as u64);
                proptest::prop_assert!(got.len() < keep.max(2));
                // PLY stores f32 coordinates when it writes a cloud of f64: compare loosely.
                proptest::prop_assert_eq!(got.len(), expected.len());
                for (g, e) in got.iter().zip(&expected) {
                    for k in 0..3 {
                        proptest::prop_assert!((g[k] - e[k]).abs() <= 1e-3 * e[k].abs().max(1.0), "{:?} vs {:?}", g, e);
                    }
                }
            }
        }
    }

    #[test]
    fn limits_default() {
        let l = ReadLimits::default();
        assert_eq!((l.max_bytes, l.max_points, l.max_triangles), (8 << 30, 200_000_000, 50_000_000));
    }
}

#[cfg(test)]
mod text_formats_tests;
