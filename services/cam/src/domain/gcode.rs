//! RS-274 (G-code) output for LinuxCNC and Fanuc/EMCO-style controls.
//!
//! Units: the program is metric (`G21`): coordinates, I/J and feeds in mm and mm/min, written with
//! exactly 4 decimals (0.0001 mm; the F1 steps 0.01 mm); A in degrees (4 decimals); S in whole
//! rpm; T/H tool numbers.
//!
//! Conservative by design:
//! - `%` first and last line; preamble `G21 G90 G17 G94 G40 G49 G80` (LinuxCNC adds `G64 P0.0100`,
//!   path blending within 0.01 mm; Fanuc gets `O0001` and `N10, N20, ...` on every block).
//! - Before every tool change, every A rotation and `M30`, Z goes to the machine's top
//!   (LinuxCNC `G53 G0 Z0.0000`; Fanuc `G91 G28 Z0.0000` then `G90`), unless it is already there.
//!   After that retract Z is unknown in work coordinates, so the next rapid moves X/Y first and
//!   Z second (the tool comes down only over its target).
//! - Modal words: G0/G1/G2/G3 and F only when they change (both restated after a tool change);
//!   X/Y/Z only for axes whose rounded value changed; arcs always carry X, Y, I and J.
//! - Arcs use I/J (incremental centre, `G90.1` is never used), never R. I/J are computed from the
//!   rounded start the control will actually be at: the centre is moved onto the perpendicular
//!   bisector of the rounded start and end and rounded to the 0.0001 grid; when the two radii then
//!   differ by 0.0001 mm or more, the grid neighbour (±2 units) giving the closest radii is used.
//!   The start and end radii differ by < 0.0005 mm (tested; LinuxCNC rejects mismatched radii).
//!   An arc whose ends round to the same XY point but was not meant as a full circle (its
//!   unrounded ends differ), or whose start is unknown, or whose radius rounds to zero, is
//!   written as a G1 to its end.
//! - Comments: `(...)` with `(`/`)` turned into `[`/`]`, non-printable or non-ASCII characters as
//!   `?`, `%` as `pct`, at most 100 characters, never in the form of a LinuxCNC active comment
//!   (`MSG,`, `DEBUG,`, `LOGOPEN,`, ... get a `- ` prefix); upper case for Fanuc.
//!
//! Non-finite coordinates, feeds, speeds or angles are refused: [`write_program_to`] returns an
//! `InvalidInput` error; [`write_program`] returns the text up to that point followed by an
//! `(error: ...)` line and without the closing `%`, which LinuxCNC refuses to run.

use std::io;

use super::feeds::CuttingData;
use super::path::Segment;
use super::tool::Tool;

/// Which control the program is for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Dialect {
    /// LinuxCNC: `G64 P`, `G43 H`, `G53` retracts, no block numbers.
    Linuxcnc,
    /// Fanuc / EMCO WinNC style: `O0001`, N numbers, `G28` retracts, no `G64`, no `G43`.
    Fanuc,
}

/// One tool's moves.
#[derive(Debug, Clone, PartialEq)]
pub struct Operation {
    pub tool: Tool,
    /// T and H number.
    pub tool_number: u32,
    pub data: CuttingData,
    /// Moves in the face's work coordinates, mm (see [`Segment`]).
    pub segments: Vec<Segment>,
    /// Names the strategy, e.g. `roughing-x with flat-6`.
    pub comment: String,
}

/// The operations of one face (one A angle).
#[derive(Debug, Clone, PartialEq)]
pub struct FaceProgram {
    /// A-axis angle (degrees) to rotate to before the face; `None` on a 3-axis set-up.
    pub a_deg: Option<f64>,
    pub operations: Vec<Operation>,
}

/// Program header.
#[derive(Debug, Clone, PartialEq)]
pub struct ProgramInfo {
    pub title: String,
    /// Comment lines after the title (tolerances, strategies, ...).
    pub lines: Vec<String>,
}

/// Path blending tolerance written as `G64 P` for LinuxCNC, mm.
pub const LINUXCNC_BLEND_TOLERANCE_MM: f64 = 0.01;
/// Largest start/end radius difference of a written arc, mm.
pub const ARC_RADIUS_MISMATCH_MAX_MM: f64 = 0.0005;

/// The whole program as a string (see the module documentation for the format).
pub fn write_program(info: &ProgramInfo, faces: &[FaceProgram], dialect: Dialect) -> String {
    let mut out = String::new();
    let mut sink = |line: &str| -> Result<(), std::convert::Infallible> {
        out.push_str(line);
        out.push('\n');
        Ok(())
    };
    let result = Writer::new(dialect).program(&mut sink, info, faces);
    if let Err(Fail::Invalid(message)) = result {
        out.push_str(&format!("(error: {})\n", sanitize(&message, dialect)));
    }
    out
}

/// The whole program, one line at a time into `w` (wrap files in a `BufWriter`).
pub fn write_program_to(
    w: &mut impl io::Write,
    info: &ProgramInfo,
    faces: &[FaceProgram],
    dialect: Dialect,
) -> io::Result<()> {
    let mut sink = |line: &str| -> io::Result<()> {
        w.write_all(line.as_bytes())?;
        w.write_all(b"\n")
    };
    match Writer::new(dialect).program(&mut sink, info, faces) {
        Ok(()) => Ok(()),
        Err(Fail::Sink(e)) => Err(e),
        Err(Fail::Invalid(m)) => Err(io::Error::new(io::ErrorKind::InvalidInput, m)),
    }
}

enum Fail<E> {
    Sink(E),
    Invalid(String),
}

/// Coordinates on the output grid: units of 0.0001 mm (or degree).
const GRID: f64 = 10_000.0;

fn quantize(x: f64, what: &str) -> Result<i64, String> {
    if x.is_finite() && x.abs() < 1e9 { Ok((x * GRID).round() as i64) } else { Err(format!("{what} is {x}")) }
}

/// `-12.3400` style: exactly 4 decimals, never `-0.0000`.
fn fmt_q(v: i64) -> String {
    let sign = if v < 0 { "-" } else { "" };
    let a = v.unsigned_abs();
    format!("{sign}{}.{:04}", a / 10_000, a % 10_000)
}

/// A comment's text, safe inside `( )` for both controls.
fn sanitize(text: &str, dialect: Dialect) -> String {
    let mut s: String = text
        .chars()
        .map(|c| match c {
            '(' => "[".to_string(),
            ')' => "]".to_string(),
            '%' => "pct".to_string(),
            c if c.is_ascii() && !c.is_ascii_control() => c.to_string(),
            _ => "?".to_string(),
        })
        .collect();
    if s.len() > 100 {
        s.truncate(100);
    }
    // LinuxCNC active comments are a word followed by a comma: (MSG,...), (DEBUG,...), (LOGOPEN,...).
    let head = s.trim_start();
    let word_len = head.chars().take_while(|c| c.is_ascii_alphanumeric() || *c == '_').count();
    if word_len > 0 && head[word_len..].trim_start().starts_with(',') {
        s = format!("- {s}");
    }
    if dialect == Dialect::Fanuc { s.to_ascii_uppercase() } else { s }
}

/// Modal state and block numbering.
struct Writer {
    dialect: Dialect,
    block: u64,
    /// Last motion word (0..=3), `None` when unknown.
    motion: Option<u8>,
    /// Last F (grid units).
    feed: Option<i64>,
    /// Rounded position per axis (grid units), `None` when unknown.
    pos: [Option<i64>; 3],
    /// Unrounded end of the last move.
    exact: Option<[f64; 3]>,
    /// Z is at the machine's top (retracted) and nothing moved since.
    retracted: bool,
    /// A block's words, its capacity kept from block to block.
    buf: String,
}

type Sink<'a, E> = dyn FnMut(&str) -> Result<(), E> + 'a;

impl Writer {
    fn new(dialect: Dialect) -> Self {
        Writer {
            dialect,
            block: 0,
            motion: None,
            feed: None,
            pos: [None; 3],
            exact: None,
            retracted: false,
            buf: String::new(),
        }
    }

    /// The empty words buffer (give it back with [`Writer::put_words`]).
    fn words(&mut self) -> String {
        let mut w = std::mem::take(&mut self.buf);
        w.clear();
        w
    }

    /// Writes `words` as a block and keeps the buffer.
    fn put_words<E>(&mut self, sink: &mut Sink<'_, E>, words: String) -> Result<(), Fail<E>> {
        let r = self.line(sink, &words);
        self.buf = words;
        r
    }

    /// A line without a block number (`%`, `O0001`).
    fn raw<E>(&mut self, sink: &mut Sink<'_, E>, text: &str) -> Result<(), Fail<E>> {
        sink(text).map_err(Fail::Sink)
    }

    /// A block (numbered for Fanuc).
    fn line<E>(&mut self, sink: &mut Sink<'_, E>, text: &str) -> Result<(), Fail<E>> {
        match self.dialect {
            Dialect::Fanuc => {
                // Sequence numbers are labels of at most five digits: a long program starts
                // over at N10 after N99990.
                self.block = if self.block >= 99_990 { 10 } else { self.block + 10 };
                sink(&format!("N{} {text}", self.block)).map_err(Fail::Sink)
            }
            Dialect::Linuxcnc => sink(text).map_err(Fail::Sink),
        }
    }

    fn comment<E>(&mut self, sink: &mut Sink<'_, E>, text: &str) -> Result<(), Fail<E>> {
        let t = format!("({})", sanitize(text, self.dialect));
        self.line(sink, &t)
    }

    fn retract<E>(&mut self, sink: &mut Sink<'_, E>) -> Result<(), Fail<E>> {
        if self.retracted {
            return Ok(());
        }
        match self.dialect {
            Dialect::Linuxcnc => self.line(sink, "G53 G0 Z0.0000")?,
            Dialect::Fanuc => {
                self.line(sink, "G91 G28 Z0.0000")?;
                self.line(sink, "G90")?;
            }
        }
        self.retracted = true;
        self.motion = None;
        self.pos[2] = None;
        self.exact = None;
        Ok(())
    }

    fn program<E>(
        &mut self,
        sink: &mut Sink<'_, E>,
        info: &ProgramInfo,
        faces: &[FaceProgram],
    ) -> Result<(), Fail<E>> {
        self.raw(sink, "%")?;
        match self.dialect {
            Dialect::Fanuc => {
                let t = format!("O0001 ({})", sanitize(&info.title, self.dialect));
                self.raw(sink, &t)?;
            }
            Dialect::Linuxcnc => self.comment(sink, &info.title)?,
        }
        for l in &info.lines {
            self.comment(sink, l)?;
        }
        self.line(sink, "G21 G90 G17 G94 G40 G49 G80")?;
        if self.dialect == Dialect::Linuxcnc {
            let p = fmt_q(quantize(LINUXCNC_BLEND_TOLERANCE_MM, "g64 p").map_err(Fail::Invalid)?);
            self.line(sink, &format!("G64 P{p}"))?;
        }
        for (fi, face) in faces.iter().enumerate() {
            if let Some(a) = face.a_deg {
                let q = quantize(a, &format!("face {} a_deg", fi + 1)).map_err(Fail::Invalid)?;
                self.comment(sink, &format!("face {} at A {} deg", fi + 1, fmt_q(q)))?;
                self.retract(sink)?;
                self.line(sink, &format!("G0 A{}", fmt_q(q)))?;
                self.motion = Some(0);
            }
            for (oi, op) in face.operations.iter().enumerate() {
                self.operation(sink, op).map_err(|e| match e {
                    Fail::Invalid(m) => Fail::Invalid(format!("face {} operation {}: {m}", fi + 1, oi + 1)),
                    other => other,
                })?;
            }
        }
        self.retract(sink)?;
        self.line(sink, "M30")?;
        self.raw(sink, "%")
    }

    fn operation<E>(&mut self, sink: &mut Sink<'_, E>, op: &Operation) -> Result<(), Fail<E>> {
        let t = &op.tool;
        let d = fmt_q(quantize(t.diameter_mm(), "tool diameter").map_err(Fail::Invalid)?);
        self.comment(
            sink,
            &format!(
                "T{} {}: {} D{d} mm, {} flutes - {}",
                op.tool_number,
                t.name,
                t.kind.as_str(),
                t.flutes,
                op.comment
            ),
        )?;
        self.retract(sink)?;
        let n = op.tool_number;
        self.line(sink, &format!("T{n} M6"))?;
        let rpm = op.data.spindle_rpm;
        if !(rpm.is_finite() && rpm > 0.0 && rpm < 1e6) {
            return Err(Fail::Invalid(format!("spindle_rpm is {rpm}")));
        }
        self.line(sink, &format!("S{} M3", rpm.round()))?;
        if op.data.coolant {
            self.line(sink, "M8")?;
        }
        if self.dialect == Dialect::Linuxcnc {
            self.line(sink, &format!("G43 H{n}"))?;
        }
        self.motion = None;
        self.feed = None;
        let feed = quantize(op.data.feed_mm_min, "feed_mm_min").map_err(Fail::Invalid)?;
        let plunge = quantize(op.data.plunge_mm_min, "plunge_mm_min").map_err(Fail::Invalid)?;
        if feed <= 0 || plunge <= 0 {
            return Err(Fail::Invalid(format!(
                "feeds must be positive, got feed {} and plunge {} mm/min",
                op.data.feed_mm_min, op.data.plunge_mm_min
            )));
        }
        for (k, seg) in op.segments.iter().enumerate() {
            self.segment(sink, seg, feed, plunge).map_err(|e| match e {
                Fail::Invalid(m) => Fail::Invalid(format!("segment {}: {m}", k + 1)),
                other => other,
            })?;
        }
        self.line(sink, "M5")?;
        self.line(sink, "M9")
    }

    /// Motion word if it changed.
    fn g_word(&mut self, words: &mut String, g: u8) {
        if self.motion != Some(g) {
            words.push('G');
            words.push(char::from(b'0' + g % 10));
            self.motion = Some(g);
        }
    }

    fn axis_words(&self, words: &mut String, q: [i64; 3], axes: [bool; 3]) {
        for (i, name) in ['X', 'Y', 'Z'].into_iter().enumerate() {
            if axes[i] && self.pos[i] != Some(q[i]) {
                push_q(words, name, q[i]);
            }
        }
    }

    fn feed_word(&mut self, words: &mut String, f: i64) {
        if self.feed != Some(f) {
            push_q(words, 'F', f);
            self.feed = Some(f);
        }
    }

    fn moved(&mut self, q: [i64; 3], exact: [f64; 3]) {
        self.pos = [Some(q[0]), Some(q[1]), Some(q[2])];
        self.exact = Some(exact);
        self.retracted = false;
    }

    fn segment<E>(
        &mut self,
        sink: &mut Sink<'_, E>,
        seg: &Segment,
        feed: i64,
        plunge: i64,
    ) -> Result<(), Fail<E>> {
        let end = seg.end();
        let exact = [end.x, end.y, end.z];
        let q = [
            quantize(end.x, "x").map_err(Fail::Invalid)?,
            quantize(end.y, "y").map_err(Fail::Invalid)?,
            quantize(end.z, "z").map_err(Fail::Invalid)?,
        ];
        let changed = (0..3).any(|i| self.pos[i] != Some(q[i]));
        match *seg {
            Segment::Rapid(_) => {
                if !changed {
                    return Ok(());
                }
                if self.pos[2].is_none() && (self.pos[0] != Some(q[0]) || self.pos[1] != Some(q[1])) {
                    // Z unknown (just retracted to the top): across first, then down.
                    let mut words = self.words();
                    self.g_word(&mut words, 0);
                    self.axis_words(&mut words, q, [true, true, false]);
                    self.put_words(sink, words)?;
                    self.pos[0] = Some(q[0]);
                    self.pos[1] = Some(q[1]);
                }
                let mut words = self.words();
                self.g_word(&mut words, 0);
                self.axis_words(&mut words, q, [true; 3]);
                self.put_words(sink, words)?;
                self.moved(q, exact);
                Ok(())
            }
            Segment::Linear(_) | Segment::Plunge(_) => {
                let f = if matches!(seg, Segment::Plunge(_)) { plunge } else { feed };
                self.linear(sink, q, exact, f, changed)
            }
            Segment::Arc { center, clockwise, .. } => {
                quantize(center[0], "arc centre x").map_err(Fail::Invalid)?;
                quantize(center[1], "arc centre y").map_err(Fail::Invalid)?;
                let (Some(sx), Some(sy), Some(_), Some(from)) =
                    (self.pos[0], self.pos[1], self.pos[2], self.exact)
                else {
                    return self.linear(sink, q, exact, feed, changed);
                };
                let same_xy = sx == q[0] && sy == q[1];
                let meant_full = (from[0] - exact[0]).hypot(from[1] - exact[1]) <= 1e-9;
                if same_xy && !meant_full {
                    return self.linear(sink, q, exact, feed, changed);
                }
                // Centre in grid units (f64), moved onto the bisector of the rounded ends.
                let (s, e) = ([sx as f64, sy as f64], [q[0] as f64, q[1] as f64]);
                let mut c = [center[0] * GRID, center[1] * GRID];
                if !same_xy {
                    let (ux, uy) = (e[0] - s[0], e[1] - s[1]);
                    let l = ux.hypot(uy);
                    let (ux, uy) = (ux / l, uy / l);
                    let (mx, my) = ((s[0] + e[0]) / 2.0, (s[1] + e[1]) / 2.0);
                    let along = (c[0] - mx) * ux + (c[1] - my) * uy;
                    c = [c[0] - along * ux, c[1] - along * uy];
                }
                let (i0, j0) = ((c[0] - s[0]).round() as i64, (c[1] - s[1]).round() as i64);
                let mismatch = |i: i64, j: i64| {
                    let rs = (i as f64).hypot(j as f64);
                    let re = (e[0] - (s[0] + i as f64)).hypot(e[1] - (s[1] + j as f64));
                    (rs - re).abs()
                };
                let mut best = (i0, j0, mismatch(i0, j0));
                // Plain rounding is kept when its radii agree within one grid unit (0.0001 mm).
                if !same_xy && best.2 >= 1.0 {
                    for di in -2..=2 {
                        for dj in -2..=2 {
                            let m = mismatch(i0 + di, j0 + dj);
                            if m < best.2 - 1e-9 {
                                best = (i0 + di, j0 + dj, m);
                            }
                        }
                    }
                }
                let (i, j, m) = best;
                if (i == 0 && j == 0) || m >= ARC_RADIUS_MISMATCH_MAX_MM * GRID {
                    return self.linear(sink, q, exact, feed, changed);
                }
                let mut words = self.words();
                self.g_word(&mut words, if clockwise { 2 } else { 3 });
                push_q(&mut words, 'X', q[0]);
                push_q(&mut words, 'Y', q[1]);
                self.axis_words(&mut words, q, [false, false, true]);
                push_q(&mut words, 'I', i);
                push_q(&mut words, 'J', j);
                self.feed_word(&mut words, feed);
                self.put_words(sink, words)?;
                self.moved(q, exact);
                Ok(())
            }
        }
    }

    fn linear<E>(
        &mut self,
        sink: &mut Sink<'_, E>,
        q: [i64; 3],
        exact: [f64; 3],
        f: i64,
        changed: bool,
    ) -> Result<(), Fail<E>> {
        if !changed {
            self.exact = Some(exact);
            return Ok(());
        }
        let mut words = self.words();
        self.g_word(&mut words, 1);
        self.axis_words(&mut words, q, [true; 3]);
        self.feed_word(&mut words, f);
        self.put_words(sink, words)?;
        self.moved(q, exact);
        Ok(())
    }
}

/// Appends the word `name` + [`fmt_q`]`(v)` (no allocation: a program has millions of them).
fn push_q(words: &mut String, name: char, v: i64) {
    if !words.is_empty() {
        words.push(' ');
    }
    words.push(name);
    if v < 0 {
        words.push('-');
    }
    let a = v.unsigned_abs();
    // The digits from the right: four decimals, the point, then the whole part (at least "0").
    let mut digits = [0u8; 24];
    let (mut at, mut rest) = (digits.len(), a);
    for k in 0.. {
        if k == 4 {
            at -= 1;
            digits[at] = b'.';
        }
        at -= 1;
        digits[at] = b'0' + (rest % 10) as u8;
        rest /= 10;
        if k >= 4 && rest == 0 {
            break;
        }
    }
    // ASCII digits and a point.
    words.push_str(std::str::from_utf8(&digits[at..]).unwrap_or_default());
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Point3;

    #[test]
    fn words_are_written_as_fmt_q_writes_them() {
        let mut values = vec![0i64, 1, -1, 9_999, -9_999, 10_000, -10_000, 123_456_789, -5, i64::MAX / 2];
        let mut x = 0x9e37_79b9_7f4a_7c15u64;
        for _ in 0..10_000 {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            values.push((x as i64) >> (x % 50));
        }
        for v in values {
            let mut words = String::from("G1");
            push_q(&mut words, 'X', v);
            assert_eq!(words, format!("G1 X{}", fmt_q(v)));
        }
    }
    use proptest::prelude::*;

    fn p(x: f64, y: f64, z: f64) -> Point3<f64> {
        Point3::new(x, y, z)
    }

    fn op(segments: Vec<Segment>, coolant: bool) -> Operation {
        Operation {
            tool: Tool::from_spec(&"ball-3".parse().expect("spec")).expect("tool"),
            tool_number: 2,
            data: CuttingData { spindle_rpm: 1999.6, feed_mm_min: 120.0, plunge_mm_min: 60.0, coolant },
            segments,
            comment: "finishing-raster-x with ball-3 (test)".into(),
        }
    }

    fn tiny() -> (ProgramInfo, Vec<FaceProgram>) {
        use Segment::*;
        let segs = vec![
            Rapid(p(1.0, 2.0, 10.0)),
            Plunge(p(1.0, 2.0, -1.0)),
            Linear(p(5.0, 2.0, -1.0)),
            Linear(p(5.0, 2.0, -1.0)),
            Arc { end: p(5.0, 6.0, -1.0), center: [5.0, 4.0], clockwise: false },
            Linear(p(5.0, 6.0, -0.5)),
            Linear(p(4.00001, 6.0, -0.5)),
            Rapid(p(4.0, 6.0, 10.0)),
        ];
        let info = ProgramInfo { title: "depthmill".into(), lines: vec!["tolerance 0.01 mm".into()] };
        (info, vec![FaceProgram { a_deg: Some(90.0), operations: vec![op(segs, true)] }])
    }

    #[test]
    fn fanuc_sequence_numbers_keep_to_five_digits() {
        let segs: Vec<Segment> =
            (0..12_000).map(|i| Segment::Linear(p(f64::from(i % 100), f64::from(i / 100), -1.0))).collect();
        let info = ProgramInfo { title: "long".into(), lines: Vec::new() };
        let text = write_program(
            &info,
            &[FaceProgram { a_deg: None, operations: vec![op(segs, false)] }],
            Dialect::Fanuc,
        );
        let numbers: Vec<u64> = text
            .lines()
            .filter_map(|l| l.strip_prefix('N'))
            .filter_map(|l| l.split_whitespace().next()?.parse().ok())
            .collect();
        assert!(numbers.len() > 10_000);
        assert!(numbers.iter().all(|&n| (10..=99_990).contains(&n)), "{:?}", numbers.iter().max());
        assert_eq!(numbers.iter().filter(|&&n| n == 10).count(), 2, "starts over once");
    }

    #[test]
    fn tiny_program_linuxcnc_exact_text() {
        let (info, faces) = tiny();
        let expected = "\
%
(depthmill)
(tolerance 0.01 mm)
G21 G90 G17 G94 G40 G49 G80
G64 P0.0100
(face 1 at A 90.0000 deg)
G53 G0 Z0.0000
G0 A90.0000
(T2 ball-3: ball D3.0000 mm, 2 flutes - finishing-raster-x with ball-3 [test])
T2 M6
S2000 M3
M8
G43 H2
G0 X1.0000 Y2.0000
Z10.0000
G1 Z-1.0000 F60.0000
X5.0000 F120.0000
G3 X5.0000 Y6.0000 I0.0000 J2.0000
G1 Z-0.5000
X4.0000
G0 Z10.0000
M5
M9
G53 G0 Z0.0000
M30
%
";
        assert_eq!(write_program(&info, &faces, Dialect::Linuxcnc), expected);
        let mut buf = Vec::new();
        write_program_to(&mut buf, &info, &faces, Dialect::Linuxcnc).expect("write");
        assert_eq!(String::from_utf8(buf).expect("utf8"), expected);
    }

    #[test]
    fn tiny_program_fanuc_exact_text() {
        let (info, faces) = tiny();
        let expected = "\
%
O0001 (DEPTHMILL)
N10 (TOLERANCE 0.01 MM)
N20 G21 G90 G17 G94 G40 G49 G80
N30 (FACE 1 AT A 90.0000 DEG)
N40 G91 G28 Z0.0000
N50 G90
N60 G0 A90.0000
N70 (T2 BALL-3: BALL D3.0000 MM, 2 FLUTES - FINISHING-RASTER-X WITH BALL-3 [TEST])
N80 T2 M6
N90 S2000 M3
N100 M8
N110 G0 X1.0000 Y2.0000
N120 Z10.0000
N130 G1 Z-1.0000 F60.0000
N140 X5.0000 F120.0000
N150 G3 X5.0000 Y6.0000 I0.0000 J2.0000
N160 G1 Z-0.5000
N170 X4.0000
N180 G0 Z10.0000
N190 M5
N200 M9
N210 G91 G28 Z0.0000
N220 G90
N230 M30
%
";
        assert_eq!(write_program(&info, &faces, Dialect::Fanuc), expected);
    }

    #[test]
    fn modal_words_are_suppressed_and_restated_after_tool_changes() {
        use Segment::*;
        let segs = vec![
            Rapid(p(0.0, 0.0, 5.0)),
            Plunge(p(0.0, 0.0, 0.0)),
            Linear(p(1.0, 0.0, 0.0)),
            Linear(p(2.0, 0.0, 0.0)),
            Linear(p(2.0, 1.0, 0.0)),
            Rapid(p(2.0, 1.0, 5.0)),
        ];
        let faces = [FaceProgram { a_deg: None, operations: vec![op(segs.clone(), false), op(segs, false)] }];
        let text =
            write_program(&ProgramInfo { title: "t".into(), lines: vec![] }, &faces, Dialect::Linuxcnc);
        let moves: Vec<&str> = text
            .lines()
            .filter(|l| l.starts_with(['G', 'X', 'Y', 'Z']) && !l.starts_with("G2") && !l.starts_with("G43"))
            .collect();
        let once = [
            "G0 X0.0000 Y0.0000",
            "Z5.0000",
            "G1 Z0.0000 F60.0000",
            "X1.0000 F120.0000",
            "X2.0000",
            "Y1.0000",
            "G0 Z5.0000",
        ];
        let mut expect = vec!["G64 P0.0100", "G53 G0 Z0.0000"];
        expect.extend(once);
        expect.push("G53 G0 Z0.0000");
        // Second operation: motion and F restated; X/Y known (only Z moved), so only X/Y that changed.
        expect.extend([
            "G0 X0.0000 Y0.0000",
            "Z5.0000",
            "G1 Z0.0000 F60.0000",
            "X1.0000 F120.0000",
            "X2.0000",
            "Y1.0000",
            "G0 Z5.0000",
        ]);
        expect.push("G53 G0 Z0.0000");
        assert_eq!(moves, expect, "{text}");
        assert!(!text.contains("M8") && !text.contains(" R"), "{text}");
    }

    #[test]
    fn comments_are_sanitized() {
        assert_eq!(sanitize("a (b) 5% é", Dialect::Linuxcnc), "a [b] 5pct ?");
        assert_eq!(sanitize("msg, hello", Dialect::Linuxcnc), "- msg, hello");
        assert_eq!(sanitize("LOGOPEN,/tmp/x", Dialect::Fanuc), "- LOGOPEN,/TMP/X");
        assert_eq!(sanitize("tolerance 0.01 mm, column", Dialect::Linuxcnc), "tolerance 0.01 mm, column");
        assert_eq!(sanitize(&"x".repeat(300), Dialect::Linuxcnc).len(), 100);
    }

    #[test]
    fn non_finite_input_is_refused() {
        let faces = [FaceProgram {
            a_deg: None,
            operations: vec![op(vec![Segment::Linear(p(f64::NAN, 0.0, 0.0))], false)],
        }];
        let info = ProgramInfo { title: "t".into(), lines: vec![] };
        let text = write_program(&info, &faces, Dialect::Linuxcnc);
        assert!(text.ends_with("(error: face 1 operation 1: segment 1: x is NaN)\n"), "{text}");
        assert!(!text.contains("M30"));
        let e = write_program_to(&mut Vec::new(), &info, &faces, Dialect::Fanuc).expect_err("nan");
        assert_eq!(e.kind(), io::ErrorKind::InvalidInput);
    }

    #[test]
    fn degenerate_arcs_fall_back_to_lines_and_full_circles_stay() {
        use Segment::*;
        let segs = vec![
            Rapid(p(0.0, 0.0, 1.0)),
            // Ends 0.00001 apart: would round to a full circle.
            Arc { end: p(0.00001, 0.0, 1.0), center: [5.0, 0.0], clockwise: true },
            // Genuine full circle.
            Arc { end: p(0.00001, 0.0, 1.0), center: [5.0, 0.0], clockwise: false },
        ];
        let faces = [FaceProgram { a_deg: None, operations: vec![op(segs, false)] }];
        let text =
            write_program(&ProgramInfo { title: "t".into(), lines: vec![] }, &faces, Dialect::Linuxcnc);
        assert!(text.contains("G3 X0.0000 Y0.0000 I5.0000 J0.0000 F120.0000"), "{text}");
        assert!(!text.contains("G2 "), "{text}");
    }

    #[test]
    fn linked_toolpath_to_program() {
        use crate::domain::cleanup::link;
        use crate::domain::feeds::{MachineLimits, cutting_data, estimate_time_s};
        use crate::domain::path::{Link, Pass, Toolpath};
        let ring = |r: f64, z: f64| -> Vec<Point3<f64>> {
            (0..=200)
                .map(|i| {
                    let a = i as f64 / 200.0 * 5.0;
                    p(20.0 + r * a.cos(), 20.0 + r * a.sin(), z)
                })
                .collect()
        };
        let tp = Toolpath {
            strategy: "finishing-iso-level".into(),
            tool: "ball-3".into(),
            passes: vec![
                Pass { link: Link::Retract, points: ring(10.0, -1.0) },
                Pass { link: Link::Direct, points: ring(9.0, -1.5) },
                Pass {
                    link: Link::Retract,
                    points: (0..50).map(|i| p(i as f64 * 0.2, 0.0, -0.01 * i as f64)).collect(),
                },
            ],
            safe_z_mm: 5.0,
        };
        let segs = link(&tp, 0.01, true);
        let lim = MachineLimits::emco_f1();
        let tool = Tool::from_spec(&"ball-3".parse().expect("spec")).expect("tool");
        let data = cutting_data(&tool, "aluminium", &lim).expect("data");
        let t = estimate_time_s(p(0.0, 0.0, 5.0), &segs, &data, &lim);
        let faces = [FaceProgram {
            a_deg: None,
            operations: vec![Operation {
                tool,
                tool_number: 1,
                data,
                segments: segs,
                comment: tp.strategy.clone(),
            }],
        }];
        let info = ProgramInfo { title: "ring".into(), lines: vec![] };
        for d in [Dialect::Linuxcnc, Dialect::Fanuc] {
            let text = write_program(&info, &faces, d);
            eprintln!("{text}estimated {t:.1} s");
            let (arcs, worst) = max_arc_mismatch(&text);
            assert!(arcs >= 2 && worst < ARC_RADIUS_MISMATCH_MAX_MM, "{arcs} {worst}");
            assert!(text.lines().count() < 40, "{text}");
        }
    }

    /// Replays the arcs of `text` as the control would and returns the largest radius mismatch.
    fn max_arc_mismatch(text: &str) -> (usize, f64) {
        let (mut x, mut y) = (f64::NAN, f64::NAN);
        let (mut arcs, mut worst) = (0, 0.0f64);
        for line in text.lines().filter(|l| !l.starts_with('(') && !l.starts_with('%') && !l.contains("G53"))
        {
            let word =
                |c: char| line.split(' ').find(|w| w.starts_with(c)).and_then(|w| w[1..].parse::<f64>().ok());
            let (nx, ny) = (word('X').unwrap_or(x), word('Y').unwrap_or(y));
            if let (Some(i), Some(j)) = (word('I'), word('J')) {
                let rs = i.hypot(j);
                let re = (nx - (x + i)).hypot(ny - (y + j));
                worst = worst.max((rs - re).abs());
                arcs += 1;
            }
            (x, y) = (nx, ny);
        }
        (arcs, worst)
    }

    proptest! {
        #[test]
        fn written_arcs_have_consistent_radii(
            arcs in prop::collection::vec((-100.0f64..100.0, -100.0f64..100.0, 0.01f64..500.0, -7.0f64..7.0,
                -7.0f64..7.0, -0.002f64..0.002, any::<bool>()), 1..20),
            fanuc in any::<bool>(),
        ) {
            use Segment::*;
            let mut segs = Vec::new();
            for &(cx, cy, r, a0, a1, wobble, cw) in &arcs {
                let start = p(cx + r * a0.cos(), cy + r * a0.sin(), 0.0);
                // The end slightly off the circle (an inconsistent caller) by up to 2 µm.
                let end = p(cx + (r + wobble) * a1.cos(), cy + (r + wobble) * a1.sin(), -1.0);
                segs.push(Rapid(start));
                segs.push(Arc { end, center: [cx, cy], clockwise: cw });
            }
            let faces = [FaceProgram { a_deg: None, operations: vec![op(segs, false)] }];
            let d = if fanuc { Dialect::Fanuc } else { Dialect::Linuxcnc };
            let text = write_program(&ProgramInfo { title: "t".into(), lines: vec![] }, &faces, d);
            let (n, worst) = max_arc_mismatch(&text);
            prop_assert!(worst < ARC_RADIUS_MISMATCH_MAX_MM, "mismatch {} in {}", worst, text);
            prop_assert!(n + 2 >= arcs.len(), "only {} of {} arcs written", n, arcs.len());
            prop_assert!(!text.contains(" R"));
        }

        #[test]
        fn fitted_arcs_round_trip_through_the_writer(
            cx in -50.0f64..50.0, cy in -50.0f64..50.0, r in 0.5f64..200.0, a0 in -3.2f64..3.2,
            sweep in -6.0f64..6.0, npts in 5usize..50, dz in -2.0f64..2.0,
        ) {
            let pts: Vec<_> = (0..npts).map(|i| {
                let t = i as f64 / (npts - 1) as f64;
                let a = a0 + sweep * t;
                p(cx + r * a.cos(), cy + r * a.sin(), dz * t)
            }).collect();
            let mut segs = vec![Segment::Rapid(pts[0])];
            segs.extend(super::super::cleanup::fit_arcs(&pts, 0.005));
            let faces = [FaceProgram { a_deg: Some(-45.0), operations: vec![op(segs, true)] }];
            let text = write_program(&ProgramInfo { title: "t".into(), lines: vec![] }, &faces, Dialect::Linuxcnc);
            let (_, worst) = max_arc_mismatch(&text);
            prop_assert!(worst < ARC_RADIUS_MISMATCH_MAX_MM, "{}", worst);
        }
    }
}
