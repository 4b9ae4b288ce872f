//! A drawing-only reading of G-code: the XY path of every move, which operation it belongs to
//! and on which face, and how long each operation's feed and rapid paths are.
//!
//! Operations come from the CAM service's header comment before each tool change,
//! `(T1 flat-6: flat D6.0000 mm, 2 flutes - roughing-x with flat-6)` (upper case with `N` numbers
//! for the Fanuc dialect): the strategy after ` - ` starting with `roughing` or `finishing`
//! decides the kind. Faces come from `(face 2 at A 90.0000 deg)` comments. A `T` word without
//! such a comment starts an operation of kind [`OpKind::Other`], so hand-written programs draw
//! too. Moves are in the face's work coordinates, which the CAM service puts in the depth map's
//! frame (the map's `origin_x_mm`/`origin_y_mm` are work coordinates), so they overlay the map
//! without any offset.
//!
//! Understood: G0-G3 (I/J incremental or with G90.1 absolute, or R; arcs flattened in 5°
//! steps, G17 only, other planes drawn as chords), G20/G21, G90/G91, G53 and G28 blocks (their
//! axes become unknown: the next move is not drawn from a guessed point), G92 (ignored, with a
//! warning), comments `( )` and `;`, block delete `/`, `N` numbers, `%`. Anything else is skipped:
//! this is a picture, not an interpreter (the machine service checks the program).

/// What an operation does.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum OpKind {
    Roughing,
    Finishing,
    Other,
}

impl OpKind {
    pub fn label(self) -> &'static str {
        match self {
            OpKind::Roughing => "roughing",
            OpKind::Finishing => "finishing",
            OpKind::Other => "other",
        }
    }
}

/// One tool's part of the program.
#[derive(Debug, Clone, PartialEq)]
pub struct Operation {
    pub face: usize,
    pub kind: OpKind,
    pub tool_number: Option<u32>,
    /// The tool and strategy as the comment gives them (or `T<n>`).
    pub label: String,
    /// 3D length of feed moves, mm.
    pub feed_mm: f64,
    /// 3D length of rapid moves, mm.
    pub rapid_mm: f64,
    pub moves: usize,
}

/// One straight piece of a move in XY (arcs are split into pieces).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Seg {
    pub op: u32,
    pub rapid: bool,
    pub a: [f32; 2],
    pub b: [f32; 2],
}

/// The program as drawn.
#[derive(Debug, Clone, Default)]
pub struct Program {
    pub ops: Vec<Operation>,
    pub segs: Vec<Seg>,
    /// A angle of each face (`None`: a 3-axis program, one face).
    pub faces: Vec<Option<f64>>,
    pub blocks: usize,
    /// XY extent of the feed moves per face: `[x_min, y_min, x_max, y_max]`.
    pub feed_extent: Vec<Option<[f64; 4]>>,
    pub warnings: Vec<String>,
}

impl Program {
    /// Operations (indices) of `face`.
    pub fn ops_of(&self, face: usize) -> impl Iterator<Item = (usize, &Operation)> {
        self.ops.iter().enumerate().filter(move |(_, o)| o.face == face)
    }
}

fn kind_of(strategy: &str) -> OpKind {
    let s = strategy.trim_start();
    if s.starts_with("roughing") {
        OpKind::Roughing
    } else if s.starts_with("finishing") || s.starts_with("rest-finishing") {
        OpKind::Finishing
    } else {
        OpKind::Other
    }
}

/// `t<n> <name>: ... - <strategy>` (lower-cased) -> (n, label, kind).
fn tool_header(c: &str) -> Option<(u32, String, OpKind)> {
    let rest = c.trim().strip_prefix('t')?;
    let digits: String = rest.chars().take_while(char::is_ascii_digit).collect();
    let n: u32 = digits.parse().ok()?;
    let after = rest.get(digits.len()..)?;
    if !after.starts_with(' ') {
        return None;
    }
    let (_, strategy) = after.split_once(" - ")?;
    let name = after.trim().split(':').next().unwrap_or("").trim().to_string();
    Some((n, format!("T{n} {name}: {}", strategy.trim()), kind_of(strategy)))
}

/// `face <n> at a <deg> deg` (lower-cased) -> deg.
fn face_header(c: &str) -> Option<f64> {
    let rest = c.trim().strip_prefix("face ")?;
    let (_, a) = rest.split_once(" at a ")?;
    a.trim().trim_end_matches("deg").trim().parse().ok()
}

struct State {
    pos: [Option<f64>; 3],
    motion: u8,
    inches: bool,
    incremental: bool,
    ij_absolute: bool,
    plane_xy: bool,
    op: Option<usize>,
    face: usize,
}

/// Parses `text` for drawing (see the module documentation). Never fails: what it cannot read it
/// skips, counting the first few problems in [`Program::warnings`].
pub fn parse(text: &str) -> Program {
    let mut parser = Parser::new();
    for line in text.lines() {
        parser.line(line);
    }
    parser.finish()
}

/// Parses a program read line by line from `r` (see [`parse`]), in memory flat in the program's
/// length: at most [`MAX_SEGS`] pieces are kept (see [`Parser`]). Invalid UTF-8 is read lossily.
pub fn parse_reader<R: std::io::BufRead>(mut r: R) -> std::io::Result<Program> {
    let mut parser = Parser::new();
    let mut buf = Vec::with_capacity(256);
    loop {
        buf.clear();
        // A line longer than any program's is cut (and its rest read as further lines).
        let n = std::io::BufRead::read_until(&mut std::io::Read::take(&mut r, 1 << 16), b'\n', &mut buf)?;
        if n == 0 {
            break;
        }
        let text = String::from_utf8_lossy(&buf);
        parser.line(text.trim_end_matches(['\n', '\r']));
    }
    Ok(parser.finish())
}

/// Most drawing pieces a [`Parser`] keeps. Past it, neighbouring pieces of one operation that
/// continue each other are joined where the joint lies within a tolerance of the joined chord
/// (1/4000 of the drawing's extent, a fraction of a pixel of the report's pictures, doubled each
/// time the pieces fill up again), so a program of any length is drawn from bounded memory.
pub const MAX_SEGS: usize = 1 << 20;

/// An incremental [`parse`]: feed lines, then [`finish`](Parser::finish).
pub struct Parser {
    p: Program,
    st: State,
    seen_face_comment: bool,
    lines: usize,
    max_segs: usize,
    /// Join tolerance, mm (0 until the pieces first fill up).
    tol: f64,
    /// Pieces at which the next join pass runs.
    next_join: usize,
}

impl Default for Parser {
    fn default() -> Self {
        Self::new()
    }
}

impl Parser {
    pub fn new() -> Self {
        Self::with_max_segs(MAX_SEGS)
    }

    /// A parser keeping at most about `max_segs` pieces (tests use small ones).
    pub fn with_max_segs(max_segs: usize) -> Self {
        let max_segs = max_segs.max(16);
        Parser {
            p: Program { faces: vec![None], feed_extent: vec![None], ..Program::default() },
            st: State {
                pos: [None; 3],
                motion: 0,
                inches: false,
                incremental: false,
                ij_absolute: false,
                plane_xy: true,
                op: None,
                face: 0,
            },
            seen_face_comment: false,
            lines: 0,
            max_segs,
            tol: 0.0,
            next_join: max_segs,
        }
    }

    /// The program read so far.
    pub fn finish(self) -> Program {
        self.p
    }

    /// Joins neighbouring pieces (see [`MAX_SEGS`]) in place.
    fn join(&mut self) {
        let segs = &mut self.p.segs;
        let (mut lo, mut hi) = ([f32::INFINITY; 2], [f32::NEG_INFINITY; 2]);
        for s in segs.iter() {
            for q in [s.a, s.b] {
                for k in 0..2 {
                    lo[k] = lo[k].min(q[k]);
                    hi[k] = hi[k].max(q[k]);
                }
            }
        }
        let diag = f64::from((hi[0] - lo[0]).hypot(hi[1] - lo[1])).max(1e-3);
        self.tol = if self.tol == 0.0 { diag / 4000.0 } else { self.tol * 2.0 };
        let tol = self.tol;
        let before = segs.len();
        let (mut w, mut r) = (0, 0);
        while r < segs.len() {
            let s = segs[r];
            if let Some(n) = segs.get(r + 1).copied()
                && n.op == s.op
                && n.rapid == s.rapid
                && n.a == s.b
                && off_chord(s.a, s.b, n.b) <= tol
            {
                segs[w] = Seg { b: n.b, ..s };
                r += 2;
            } else {
                segs[w] = s;
                r += 1;
            }
            w += 1;
        }
        segs.truncate(w);
        // A pass that joined little (pieces that do not continue each other) waits for more.
        self.next_join = if w * 4 > before * 3 { w + self.max_segs / 2 } else { self.max_segs };
    }

    /// Reads one line (block) of the program.
    pub fn line(&mut self, raw: &str) {
        if self.p.segs.len() >= self.next_join {
            self.join();
        }
        let Parser { p, st, seen_face_comment, lines, .. } = self;
        let ln = *lines;
        *lines += 1;
        p.blocks += 1;
        let line = raw.trim();
        if line.is_empty() || line.starts_with('%') || line.starts_with('/') {
            return;
        }
        // Comments.
        let mut code = String::with_capacity(line.len());
        let mut chars = line.chars();
        let mut comments = Vec::new();
        while let Some(ch) = chars.next() {
            match ch {
                '(' => {
                    let c: String = chars.by_ref().take_while(|&x| x != ')').collect();
                    comments.push(c.to_ascii_lowercase());
                }
                ';' => {
                    comments.push(chars.by_ref().collect::<String>().to_ascii_lowercase());
                }
                c if c.is_whitespace() => {}
                c => code.push(c.to_ascii_uppercase()),
            }
        }
        for c in &comments {
            if let Some(a) = face_header(c) {
                if *seen_face_comment {
                    p.faces.push(Some(a));
                    p.feed_extent.push(None);
                    st.face = p.faces.len() - 1;
                } else if let Some(f) = p.faces.first_mut() {
                    *f = Some(a);
                }
                *seen_face_comment = true;
                st.op = None;
                // The part turned: where the tool was is a point of the last face's frame, and a
                // line from it would cross this face's picture (the move there is a retracted
                // rapid anyway). The first move of the face starts the drawing afresh.
                st.pos = [None; 3];
            } else if let Some((n, label, kind)) = tool_header(c) {
                p.ops.push(Operation {
                    face: st.face,
                    kind,
                    tool_number: Some(n),
                    label,
                    feed_mm: 0.0,
                    rapid_mm: 0.0,
                    moves: 0,
                });
                st.op = Some(p.ops.len() - 1);
            }
        }
        // Words.
        let mut words: Vec<(char, f64)> = Vec::new();
        let b = code.as_bytes();
        let mut i = 0;
        let mut bad = false;
        while i < b.len() {
            let letter = b[i] as char;
            i += 1;
            let start = i;
            while i < b.len() && (b[i].is_ascii_digit() || b[i] == b'.' || b[i] == b'-' || b[i] == b'+') {
                i += 1;
            }
            match code.get(start..i).and_then(|s| s.parse::<f64>().ok()) {
                Some(v) if letter.is_ascii_alphabetic() => words.push((letter, v)),
                _ => bad = true,
            }
        }
        if bad && p.warnings.len() < 5 {
            p.warnings.push(format!("line {}: words not understood, skipped: {}", ln + 1, raw.trim()));
        }
        let word = |l: char| words.iter().rev().find(|(c, _)| *c == l).map(|w| w.1);
        let mut machine_coords = false;
        let mut skip_motion = false;
        for &(c, v) in &words {
            if c != 'G' {
                continue;
            }
            let g = (v * 10.0).round() as i64;
            match g {
                0 | 10 | 20 | 30 => st.motion = (g / 10) as u8,
                170 => st.plane_xy = true,
                180 | 190 => st.plane_xy = false,
                200 => st.inches = true,
                210 => st.inches = false,
                900 => st.incremental = false,
                910 => st.incremental = true,
                901 => st.ij_absolute = true,
                911 => st.ij_absolute = false,
                530 | 280 | 300 => machine_coords = true,
                920 | 100 => {
                    skip_motion = true;
                    if p.warnings.len() < 5 {
                        p.warnings.push(format!("line {}: G{v} ignored for drawing", ln + 1));
                    }
                }
                40 => skip_motion = true,
                _ => {}
            }
        }
        if let Some(t) = word('T') {
            let n = t.round().max(0.0) as u32;
            let same = st.op.and_then(|k| p.ops.get(k)).is_some_and(|o| o.tool_number == Some(n));
            if !same {
                p.ops.push(Operation {
                    face: st.face,
                    kind: OpKind::Other,
                    tool_number: Some(n),
                    label: format!("T{n}"),
                    feed_mm: 0.0,
                    rapid_mm: 0.0,
                    moves: 0,
                });
                st.op = Some(p.ops.len() - 1);
            }
        }
        let axes = [word('X'), word('Y'), word('Z')];
        if skip_motion || axes.iter().all(Option::is_none) {
            return;
        }
        if machine_coords {
            // Machine coordinates (G53) or a reference return (G28/G30): the named axes end
            // somewhere this reading does not know.
            for (k, a) in axes.iter().enumerate() {
                if a.is_some() {
                    st.pos[k] = None;
                }
            }
            return;
        }
        let unit = if st.inches { 25.4 } else { 1.0 };
        let mut to = st.pos;
        for k in 0..3 {
            if let Some(v) = axes[k] {
                to[k] = if st.incremental { st.pos[k].map(|p| p + v * unit) } else { Some(v * unit) };
            }
        }
        let op = match st.op {
            Some(k) => k,
            None => {
                p.ops.push(Operation {
                    face: st.face,
                    kind: OpKind::Other,
                    tool_number: None,
                    label: "moves before any tool change".into(),
                    feed_mm: 0.0,
                    rapid_mm: 0.0,
                    moves: 0,
                });
                st.op = Some(p.ops.len() - 1);
                p.ops.len() - 1
            }
        };
        let rapid = st.motion == 0;
        // A rapid whose start height is unknown begins at the top of the machine (after a G53 or
        // G28 retract, a tool change): it passes over everything, and drawn in the top view it
        // would be a line straight across the part. It moves the tool, it is not drawn.
        let over_all = rapid && st.pos[2].is_none();
        let mut pts: Vec<[f64; 3]> = Vec::new();
        if let (Some(x0), Some(y0), Some(x1), Some(y1)) = (st.pos[0], st.pos[1], to[0], to[1]) {
            let z0 = st.pos[2].unwrap_or(0.0);
            let z1 = to[2].unwrap_or(z0);
            pts.push([x0, y0, z0]);
            if (st.motion == 2 || st.motion == 3) && st.plane_xy {
                arc_points(&mut pts, [x0, y0, z0], [x1, y1, z1], &words, st, unit);
            }
            pts.push([x1, y1, z1]);
        }
        let mut len = 0.0;
        for w in pts.windows(2) {
            let (a, b) = (w[0], w[1]);
            len += ((b[0] - a[0]).powi(2) + (b[1] - a[1]).powi(2) + (b[2] - a[2]).powi(2)).sqrt();
            if (a[0], a[1]) != (b[0], b[1]) && !over_all {
                p.segs.push(Seg {
                    op: op as u32,
                    rapid,
                    a: [a[0] as f32, a[1] as f32],
                    b: [b[0] as f32, b[1] as f32],
                });
            }
            if !rapid && let Some(ext) = p.feed_extent.get_mut(st.face) {
                let e = ext.get_or_insert([a[0], a[1], a[0], a[1]]);
                for q in [a, b] {
                    e[0] = e[0].min(q[0]);
                    e[1] = e[1].min(q[1]);
                    e[2] = e[2].max(q[0]);
                    e[3] = e[3].max(q[1]);
                }
            }
        }
        if let Some(o) = p.ops.get_mut(op) {
            if rapid {
                o.rapid_mm += len;
            } else {
                o.feed_mm += len;
            }
            o.moves += 1;
        }
        st.pos = to;
    }
}

/// Distance of `m` from the segment `a`-`b`, mm.
fn off_chord(a: [f32; 2], m: [f32; 2], b: [f32; 2]) -> f64 {
    let (a, m, b) = (a.map(f64::from), m.map(f64::from), b.map(f64::from));
    let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
    let len2 = dx * dx + dy * dy;
    let t = if len2 > 0.0 { (((m[0] - a[0]) * dx + (m[1] - a[1]) * dy) / len2).clamp(0.0, 1.0) } else { 0.0 };
    (m[0] - a[0] - t * dx).hypot(m[1] - a[1] - t * dy)
}

/// Intermediate points of a G2/G3 arc in XY from `a` to `b` (ends excluded), centre from I/J or R.
fn arc_points(
    out: &mut Vec<[f64; 3]>,
    a: [f64; 3],
    b: [f64; 3],
    words: &[(char, f64)],
    st: &State,
    unit: f64,
) {
    let word = |l: char| words.iter().rev().find(|(c, _)| *c == l).map(|w| w.1 * unit);
    let cw = st.motion == 2;
    let center = match (word('I'), word('J'), word('R')) {
        (i, j, _) if i.is_some() || j.is_some() => {
            let (i, j) = (i.unwrap_or(0.0), j.unwrap_or(0.0));
            if st.ij_absolute { [i, j] } else { [a[0] + i, a[1] + j] }
        }
        (_, _, Some(r)) => {
            let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
            let d = (dx * dx + dy * dy).sqrt();
            if d == 0.0 || d > 2.0 * r.abs() + 1e-9 {
                return;
            }
            let h = (r * r - d * d / 4.0).max(0.0).sqrt();
            // Left of the chord for G3 with R > 0 (the short arc), right for G2; R < 0: the long arc.
            let side = if cw == (r > 0.0) { -1.0 } else { 1.0 };
            [(a[0] + b[0]) / 2.0 - side * h * dy / d, (a[1] + b[1]) / 2.0 + side * h * dx / d]
        }
        _ => return,
    };
    let r = ((a[0] - center[0]).powi(2) + (a[1] - center[1]).powi(2)).sqrt();
    if !(r.is_finite() && r > 0.0) {
        return;
    }
    let a0 = (a[1] - center[1]).atan2(a[0] - center[0]);
    let a1 = (b[1] - center[1]).atan2(b[0] - center[0]);
    let tau = std::f64::consts::TAU;
    let mut sweep = if cw { a0 - a1 } else { a1 - a0 };
    sweep = sweep.rem_euclid(tau);
    if sweep < 1e-9 {
        sweep = tau;
    }
    let n = ((sweep / 5f64.to_radians()).ceil() as usize).clamp(2, 720);
    for k in 1..n {
        let t = k as f64 / n as f64;
        let ang = if cw { a0 - sweep * t } else { a0 + sweep * t };
        out.push([center[0] + r * ang.cos(), center[1] + r * ang.sin(), a[2] + (b[2] - a[2]) * t]);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cam_headers_make_operations_and_faces() {
        let text = "%\n(depthmill)\nG21 G90 G17 G94 G40 G49 G80\n(face 1 at A 0.0000 deg)\nG53 G0 Z0.0000\nG0 A0.0000\n\
(T1 flat-6: flat D6.0000 mm, 2 flutes - roughing-x with flat-6)\nT1 M6\nS2000 M3\nG43 H1\nG0 X0.0000 Y0.0000\nZ5.0000\nG1 Z-1.0000 F100.0000\nX10.0000\n\
(face 2 at A 90.0000 deg)\nG53 G0 Z0.0000\nG0 A90.0000\n\
N70 (T2 BALL-3: BALL D3.0000 MM, 2 FLUTES - FINISHING-RASTER-X WITH BALL-3)\nN80 T2 M6\nG0 X0 Y0\nG3 X0 Y0 I5 J0 F120\nM30\n%\n";
        let p = parse(text);
        assert_eq!(p.faces, vec![Some(0.0), Some(90.0)]);
        assert_eq!(p.ops.len(), 2, "{:?}", p.ops);
        assert_eq!((p.ops[0].kind, p.ops[0].face), (OpKind::Roughing, 0));
        assert_eq!((p.ops[1].kind, p.ops[1].face), (OpKind::Finishing, 1));
        assert!((p.ops[0].feed_mm - 16.0).abs() < 1e-9, "{}", p.ops[0].feed_mm);
        // A full circle of radius 5.
        assert!((p.ops[1].feed_mm - std::f64::consts::TAU * 5.0).abs() < 0.1, "{}", p.ops[1].feed_mm);
        let ext = p.feed_extent[1].expect("extent");
        assert!((ext[2] - 10.0).abs() < 0.01 && (ext[1] + 5.0).abs() < 0.01, "{ext:?}");
        // No line from where face 1 ended (10, 0) across face 2's picture.
        let face2: Vec<&Seg> =
            p.segs.iter().filter(|s| p.ops.get(s.op as usize).is_some_and(|o| o.face == 1)).collect();
        assert!(!face2.is_empty());
        assert!(face2.iter().all(|s| s.a != [10.0, 0.0] && s.b != [10.0, 0.0]), "{face2:?}");
        assert_eq!(p.ops[1].rapid_mm, 0.0, "no rapid from the last face's position");
    }

    /// The repositioning rapid after a tool change's retract to the machine's top is not drawn
    /// across the part; the moves at known heights are.
    #[test]
    fn a_rapid_from_the_retract_height_is_not_drawn() {
        let text = "(T1 flat-6: flat D6 mm - roughing-x with flat-6)\nG53 G0 Z0\nT1 M6\nG0 X0 Y0\nZ5\nG1 Z-1 F100\nX40 Y30\n\
G0 Z19\n(T2 ball-3: ball D3 mm - finishing-raster-x with ball-3)\nG53 G0 Z0\nT2 M6\nG0 X-6 Y-6\nZ19\nG1 Z-1 F60\nX40\nG0 Z19\nX0 Y30\nM30\n";
        let p = parse(text);
        let from_corner = |s: &&Seg| s.a == [40.0, 30.0] && s.b == [-6.0, -6.0];
        assert!(!p.segs.iter().any(|s| from_corner(&s)), "no line across the part: {:?}", p.segs);
        // The rapid at Z19 from (40, -6) to (0, 30), at a known height, is drawn as a rapid.
        assert!(p.segs.iter().any(|s| s.rapid && s.a == [40.0, -6.0] && s.b == [0.0, 30.0]), "{:?}", p.segs);
        assert_eq!(p.segs.iter().filter(|s| !s.rapid).count(), 2, "the two cuts: {:?}", p.segs);
        // Its length still counts.
        assert!(p.ops[1].rapid_mm > 60.0, "{}", p.ops[1].rapid_mm);
    }

    #[test]
    fn r_arcs_and_incremental_moves() {
        let p = parse("T5 M6\nG0 X0 Y0 Z1\nG2 X10 Y0 R5 F100\nG91 G1 X-10\n");
        assert_eq!(p.ops[0].label, "T5");
        // A half circle of radius 5 (clockwise from (0,0) to (10,0) passes through y = +5).
        let top = p.segs.iter().map(|s| s.a[1].max(s.b[1])).fold(f32::MIN, f32::max);
        assert!((top - 5.0).abs() < 0.05, "{top}");
        let last = p.segs.last().expect("seg");
        assert_eq!((last.a, last.b), ([10.0, 0.0], [0.0, 0.0]));
    }
}
