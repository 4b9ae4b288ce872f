//! Block parsing: one line of G-code into a [`Block`] of words, with no allocation.
//!
//! Rules (LinuxCNC's, checked against `rs274`):
//! - Letters are case-insensitive; spaces and tabs are ignored outside comments, also inside a
//!   number (`X1 2.5` is `X12.5`, `Y2 .5` is `Y2.5`).
//! - Numbers: optional sign, digits with at most one decimal point (`1`, `-.5`, `+2.`), no
//!   exponent. Parsed exactly (correctly rounded): the common case of at most 15 significant digits
//!   is one integer accumulation and one division by an exact power of ten; longer numbers fall back
//!   to the standard library's parser.
//! - `( ... )` comments may not nest and must close on their line; `;` starts a comment to the end
//!   of the line (a `;` inside `( )` is part of that comment). Comments are ignored.
//! - `%` alone (with spaces) on a line; `/` as the first character marks a block-delete line;
//!   `N` (integer or fractional) only as the first word (after `/`).
//! - `O1234` alone (with comments) on a line is a Fanuc program number and is ignored; any other
//!   `O` word is a LinuxCNC O-word and refused.
//! - G codes are kept as ten times their number (`G90.1` is 901); each G and M code is sorted
//!   into its modal group here, so two codes of one group or an unknown or unsupported code are
//!   refused with the column of the word.

use super::error::{ErrorKind, GcodeError};

/// Letters whose value the block keeps (G, M, N, O are handled apart).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(u8)]
pub enum Letter {
    /// A axis, degrees.
    A = 0,
    /// C axis, degrees.
    C,
    /// Feed rate.
    F,
    /// Tool length offset index.
    H,
    /// Arc centre, X.
    I,
    /// Arc centre, Y.
    J,
    /// Arc centre, Z.
    K,
    /// Dwell time, arc turns, G64 tolerance, M52 switch.
    P,
    /// G64 naive CAM tolerance.
    Q,
    /// Arc radius.
    R,
    /// Spindle speed.
    S,
    /// Tool number.
    T,
    /// X axis.
    X,
    /// Y axis.
    Y,
    /// Z axis.
    Z,
}

/// Number of [`Letter`]s.
pub const LETTER_COUNT: usize = 15;

impl Letter {
    /// All letters, in index order.
    pub const ALL: [Letter; LETTER_COUNT] = [
        Letter::A,
        Letter::C,
        Letter::F,
        Letter::H,
        Letter::I,
        Letter::J,
        Letter::K,
        Letter::P,
        Letter::Q,
        Letter::R,
        Letter::S,
        Letter::T,
        Letter::X,
        Letter::Y,
        Letter::Z,
    ];

    /// The upper-case character.
    pub const fn as_char(self) -> char {
        match self {
            Letter::A => 'A',
            Letter::C => 'C',
            Letter::F => 'F',
            Letter::H => 'H',
            Letter::I => 'I',
            Letter::J => 'J',
            Letter::K => 'K',
            Letter::P => 'P',
            Letter::Q => 'Q',
            Letter::R => 'R',
            Letter::S => 'S',
            Letter::T => 'T',
            Letter::X => 'X',
            Letter::Y => 'Y',
            Letter::Z => 'Z',
        }
    }

    const fn bit(self) -> u16 {
        1 << self as u8
    }
}

/// Bits of the axis letters X, Y, Z, A, C.
const AXIS_BITS: u16 =
    Letter::X.bit() | Letter::Y.bit() | Letter::Z.bit() | Letter::A.bit() | Letter::C.bit();

/// Modal groups of G codes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(u8)]
pub enum GGroup {
    /// LinuxCNC group 0: G4, G28, G53.
    NonModal = 0,
    /// LinuxCNC group 1: G0, G1, G2, G3, G80.
    Motion,
    /// LinuxCNC group 2: G17, G18, G19.
    Plane,
    /// LinuxCNC group 3: G90, G91.
    Distance,
    /// LinuxCNC group 4: G90.1, G91.1.
    ArcDistance,
    /// LinuxCNC group 5: G93, G94, G95.
    FeedMode,
    /// LinuxCNC group 6: G20, G21.
    Units,
    /// LinuxCNC group 7: G40.
    CutterComp,
    /// LinuxCNC group 8: G43, G49.
    ToolLength,
    /// LinuxCNC group 10: G98, G99.
    ReturnMode,
    /// LinuxCNC group 12: G54-G59.
    CoordSystem,
    /// LinuxCNC group 13: G61, G61.1, G64.
    PathControl,
    /// LinuxCNC group 14: G97.
    SpindleMode,
}

/// Number of [`GGroup`]s.
pub const G_GROUP_COUNT: usize = 13;

impl GGroup {
    /// The group's name in messages.
    pub const fn name(self) -> &'static str {
        match self {
            GGroup::NonModal => "non-modal (G4, G28, G53)",
            GGroup::Motion => "motion (G0-G3, G80)",
            GGroup::Plane => "plane (G17-G19)",
            GGroup::Distance => "distance (G90/G91)",
            GGroup::ArcDistance => "arc centre distance (G90.1/G91.1)",
            GGroup::FeedMode => "feed mode (G93/G94/G95)",
            GGroup::Units => "units (G20/G21)",
            GGroup::CutterComp => "cutter compensation (G40)",
            GGroup::ToolLength => "tool length offset (G43/G49)",
            GGroup::ReturnMode => "return mode (G98/G99)",
            GGroup::CoordSystem => "coordinate system (G54-G59)",
            GGroup::PathControl => "path control (G61/G61.1/G64)",
            GGroup::SpindleMode => "spindle speed mode (G97)",
        }
    }
}

/// Modal groups of M codes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[repr(u8)]
pub enum MGroup {
    /// M0, M1, M2, M30.
    Stop = 0,
    /// M6.
    ToolChange,
    /// M3, M4, M5.
    Spindle,
    /// M7, M8, M9.
    Coolant,
    /// M52.
    Override,
}

/// Number of [`MGroup`]s.
pub const M_GROUP_COUNT: usize = 5;

impl MGroup {
    /// The group's name in messages.
    pub const fn name(self) -> &'static str {
        match self {
            MGroup::Stop => "stop (M0, M1, M2, M30)",
            MGroup::ToolChange => "tool change (M6)",
            MGroup::Spindle => "spindle (M3, M4, M5)",
            MGroup::Coolant => "coolant (M7, M8, M9)",
            MGroup::Override => "override (M52)",
        }
    }
}

/// The G code `code10` (ten times its number) is supported: its group; otherwise why not.
pub fn g_group(code10: u32) -> Result<GGroup, ErrorKind> {
    use ErrorKind::{CannedCycle, CutterCompensation, UnknownG, UnsupportedG};
    let unsupported = |reason| Err(UnsupportedG { reason });
    match code10 {
        0 | 10 | 20 | 30 | 800 => Ok(GGroup::Motion),
        40 | 280 | 530 => Ok(GGroup::NonModal),
        170 | 180 | 190 => Ok(GGroup::Plane),
        200 | 210 => Ok(GGroup::Units),
        400 => Ok(GGroup::CutterComp),
        430 | 490 => Ok(GGroup::ToolLength),
        540 | 550 | 560 | 570 | 580 | 590 => Ok(GGroup::CoordSystem),
        610 | 611 | 640 => Ok(GGroup::PathControl),
        900 | 910 => Ok(GGroup::Distance),
        901 | 911 => Ok(GGroup::ArcDistance),
        930 | 940 | 950 => Ok(GGroup::FeedMode),
        980 | 990 => Ok(GGroup::ReturnMode),
        970 => Ok(GGroup::SpindleMode),
        410 | 411 | 420 | 421 => Err(CutterCompensation),
        730 | 740 | 760 | 810 | 820 | 830 | 840 | 841 | 850 | 860 | 870 | 880 | 890 => Err(CannedCycle),
        50..=52 => unsupported("G5/G5.1/G5.2 splines are not supported"),
        70 | 80 => unsupported("G7/G8 lathe diameter/radius modes are not supported"),
        100 => unsupported("G10 (writing offsets or tool data from the program) is not supported"),
        150 | 160 => unsupported("G15/G16 polar coordinates are not supported"),
        281 | 300 | 301 => unsupported("G28.1/G30/G30.1 are not supported (G28 to the configured home is)"),
        330 | 331 => unsupported("spindle-synchronized motion (G33, G33.1) is not supported"),
        382..=385 => unsupported("probing (G38.x) is not supported"),
        431..=433 => {
            unsupported("G43.1/G43.2/G43.3 dynamic tool length offsets are not supported (G43 H is)")
        }
        500 | 510 | 520 => unsupported("G50/G51 scaling and G52 local offsets are not supported"),
        591..=593 => unsupported("G59.1-G59.3 are not supported (G54-G59 are)"),
        680 | 690 => unsupported("G68/G69 coordinate rotation is not supported"),
        700 | 710 | 720 => unsupported(
            "G70-G72 (lathe cycles, or inch/metric on old Fanuc controls: use G20/G21) are not supported",
        ),
        920..=923 => unsupported("G92 offsets are not supported (use G54-G59)"),
        960 => unsupported("constant surface speed (G96) is not supported (G97 rpm mode is)"),
        _ => Err(UnknownG),
    }
}

/// The M code is supported: its group; otherwise why not.
pub fn m_group(code: u32) -> Result<MGroup, ErrorKind> {
    use ErrorKind::{UnknownM, UnsupportedM};
    let unsupported = |reason| Err(UnsupportedM { reason });
    match code {
        0 | 1 | 2 | 30 => Ok(MGroup::Stop),
        6 => Ok(MGroup::ToolChange),
        3..=5 => Ok(MGroup::Spindle),
        7..=9 => Ok(MGroup::Coolant),
        52 => Ok(MGroup::Override),
        19 => unsupported("M19 spindle orientation is not supported"),
        48..=53 => unsupported("M48-M51 and M53 override switches are not supported (M52 adaptive feed is)"),
        60 => unsupported("M60 pallet change is not supported"),
        61 => unsupported("M61 (set the loaded tool number) is not supported (use T M6)"),
        62..=68 => unsupported("M62-M68 digital/analog I/O is not supported"),
        70..=73 => unsupported("M70-M73 modal state save/restore is not supported"),
        100..=199 => unsupported("user M codes (M100-M199) are not supported"),
        _ => Err(UnknownM),
    }
}

/// What a line is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum BlockKind {
    /// Empty or spaces only.
    #[default]
    Blank,
    /// A bare `%`.
    Percent,
    /// Starts with `/` and block delete is on: skipped unread.
    Deleted,
    /// A Fanuc program number `O1234` (ignored).
    ProgramNumber,
    /// Words and/or comments (possibly comments only).
    Words,
}

/// One parsed line. Reused from line to line: [`parse_line`] resets it in O(1).
#[derive(Debug, Clone, Default)]
pub struct Block {
    kind: BlockKind,
    line_number: Option<f64>,
    words: u16,
    values: [f64; LETTER_COUNT],
    cols: [u32; LETTER_COUNT],
    g_mask: u16,
    g_codes: [u16; G_GROUP_COUNT],
    g_cols: [u32; G_GROUP_COUNT],
    m_mask: u8,
    m_codes: [u8; M_GROUP_COUNT],
    m_cols: [u32; M_GROUP_COUNT],
    first_col: u32,
}

impl Block {
    /// An empty block.
    pub fn new() -> Block {
        Block::default()
    }

    fn clear(&mut self) {
        self.kind = BlockKind::Blank;
        self.line_number = None;
        self.words = 0;
        self.g_mask = 0;
        self.m_mask = 0;
        self.first_col = 0;
    }

    /// What the line is.
    pub fn kind(&self) -> BlockKind {
        self.kind
    }

    /// The N number, if any.
    pub fn line_number(&self) -> Option<f64> {
        self.line_number
    }

    /// The value of a letter (as written, program units).
    #[inline]
    pub fn get(&self, l: Letter) -> Option<f64> {
        if self.words & l.bit() != 0 { Some(self.values[l as usize]) } else { None }
    }

    /// The letter is present.
    #[inline]
    pub fn has(&self, l: Letter) -> bool {
        self.words & l.bit() != 0
    }

    /// 1-based column of a letter (0 if absent).
    pub fn column(&self, l: Letter) -> u32 {
        if self.has(l) { self.cols[l as usize] } else { 0 }
    }

    /// Any of X, Y, Z, A.
    #[inline]
    pub fn has_axis_words(&self) -> bool {
        self.words & AXIS_BITS != 0
    }

    /// No words but X, Y, Z, A (G and M codes aside).
    #[inline]
    pub fn has_only_axis_words(&self) -> bool {
        self.words & !AXIS_BITS == 0
    }

    /// The G code of a group, ten times its number.
    #[inline]
    pub fn g(&self, group: GGroup) -> Option<u16> {
        if self.g_mask & (1 << group as u8) != 0 { Some(self.g_codes[group as usize]) } else { None }
    }

    /// 1-based column of a group's G word (0 if absent).
    pub fn g_column(&self, group: GGroup) -> u32 {
        if self.g(group).is_some() { self.g_cols[group as usize] } else { 0 }
    }

    /// The M code of a group.
    #[inline]
    pub fn m(&self, group: MGroup) -> Option<u8> {
        if self.m_mask & (1 << group as u8) != 0 { Some(self.m_codes[group as usize]) } else { None }
    }

    /// 1-based column of a group's M word (0 if absent).
    pub fn m_column(&self, group: MGroup) -> u32 {
        if self.m(group).is_some() { self.m_cols[group as usize] } else { 0 }
    }

    /// Any G or M word.
    #[inline]
    pub fn has_codes(&self) -> bool {
        self.g_mask != 0 || self.m_mask != 0
    }

    /// 1-based column of the first word after N (0 if none).
    pub fn first_column(&self) -> u32 {
        self.first_col
    }

    /// Column of the first axis word present (X, Y, Z, A, C order of appearance), 0 if none.
    pub fn first_axis_column(&self) -> u32 {
        [Letter::X, Letter::Y, Letter::Z, Letter::A, Letter::C]
            .into_iter()
            .filter(|&l| self.has(l))
            .map(|l| self.cols[l as usize])
            .min()
            .unwrap_or(0)
    }
}

// Character classes.
const C_OTHER: u8 = 255;
const C_G: u8 = 20;
const C_M: u8 = 21;
const C_N: u8 = 22;
const C_O: u8 = 23;
const C_OPEN: u8 = 24;
const C_SEMI: u8 = 25;
const C_CLOSE: u8 = 26;
const C_HASH: u8 = 27;
const C_BRACKET: u8 = 28;
const C_BAD_LETTER: u8 = 29;
const C_SLASH: u8 = 30;
const C_PERCENT: u8 = 31;

const fn class_table() -> [u8; 256] {
    let mut t = [C_OTHER; 256];
    let mut i = 0;
    while i < LETTER_COUNT {
        let c = Letter::ALL[i].as_char() as u8;
        t[c as usize] = i as u8;
        t[(c | 0x20) as usize] = i as u8;
        i += 1;
    }
    let specials: [(u8, u8); 4] = [(b'G', C_G), (b'M', C_M), (b'N', C_N), (b'O', C_O)];
    let mut k = 0;
    while k < specials.len() {
        let (c, v) = specials[k];
        t[c as usize] = v;
        t[(c | 0x20) as usize] = v;
        k += 1;
    }
    let bad = *b"BDELUVW";
    let mut k = 0;
    while k < bad.len() {
        t[bad[k] as usize] = C_BAD_LETTER;
        t[(bad[k] | 0x20) as usize] = C_BAD_LETTER;
        k += 1;
    }
    t[b'(' as usize] = C_OPEN;
    t[b';' as usize] = C_SEMI;
    t[b')' as usize] = C_CLOSE;
    t[b'#' as usize] = C_HASH;
    t[b'[' as usize] = C_BRACKET;
    t[b'/' as usize] = C_SLASH;
    t[b'%' as usize] = C_PERCENT;
    t
}

static CLASS: [u8; 256] = class_table();

fn bad_letter_reason(c: u8) -> &'static str {
    match c.to_ascii_uppercase() {
        b'B' => "the B axis is not supported (axes X, Y, Z, A, C)",
        b'U' | b'V' | b'W' => "U, V and W axes are not supported (axes X, Y, Z, A, C)",
        b'D' => "D word (cutter compensation) is not supported",
        b'E' => "E word is not supported",
        _ => "L word (G10, canned-cycle repeats) is not supported",
    }
}

#[inline]
fn skip_ws(s: &[u8], mut i: usize) -> usize {
    while i < s.len() && (s[i] == b' ' || s[i] == b'\t') {
        i += 1;
    }
    i
}

/// Exact powers of ten representable in f64.
const POW10: [f64; 23] = [
    1e0, 1e1, 1e2, 1e3, 1e4, 1e5, 1e6, 1e7, 1e8, 1e9, 1e10, 1e11, 1e12, 1e13, 1e14, 1e15, 1e16, 1e17, 1e18,
    1e19, 1e20, 1e21, 1e22,
];

/// Longest number text accepted (sign, digits and point, spaces not counted).
const MAX_NUMBER_CHARS: usize = 64;

/// Reads a number starting at `*i` (spaces allowed anywhere in it); `*i` ends after it.
///
/// Exact: with at most 2^53 as the integer of all digits and at most 22 decimals, the value is
/// `digits / 10^decimals` with both operands exact, so one IEEE division rounds it correctly.
pub fn parse_number(s: &[u8], i: &mut usize) -> Result<f64, &'static str> {
    let mut p = skip_ws(s, *i);
    let start = p;
    let mut neg = false;
    if p < s.len() && (s[p] == b'-' || s[p] == b'+') {
        neg = s[p] == b'-';
        p += 1;
    }
    let mut mant: u64 = 0;
    let mut decimals: u32 = 0;
    let mut digits = 0u32;
    let mut dot = false;
    let mut fits = true;
    loop {
        p = skip_ws(s, p);
        let Some(&c) = s.get(p) else { break };
        if c.is_ascii_digit() {
            digits += 1;
            if fits && mant < 100_000_000_000_000_000 {
                mant = mant * 10 + u64::from(c - b'0');
                if dot {
                    decimals += 1;
                }
            } else {
                fits = false;
            }
            p += 1;
        } else if c == b'.' && !dot {
            dot = true;
            p += 1;
        } else {
            break;
        }
    }
    if digits == 0 {
        return Err("no digits after the letter");
    }
    if let Some(&c) = s.get(p)
        && matches!(c, b'.' | b'+' | b'-')
    {
        return Err("trailing characters after the number");
    }
    *i = p;
    if fits && mant <= (1u64 << 53) && (decimals as usize) < POW10.len() {
        let v = mant as f64 / POW10[decimals as usize];
        return Ok(if neg { -v } else { v });
    }
    // Rare: more than 17 significant digits or more than 22 decimals.
    let mut buf = [0u8; MAX_NUMBER_CHARS];
    let mut n = 0;
    for &c in &s[start..p] {
        if c == b' ' || c == b'\t' {
            continue;
        }
        if n == buf.len() {
            return Err("too many digits");
        }
        buf[n] = c;
        n += 1;
    }
    std::str::from_utf8(&buf[..n]).ok().and_then(|t| t.parse::<f64>().ok()).ok_or("not a decimal number")
}

/// The word at byte `at` as written, for messages (at most 40 characters).
pub fn word_text(s: &[u8], at: usize) -> String {
    let Some(&first) = s.get(at) else { return String::new() };
    let mut end = at + 1;
    if first.is_ascii_alphabetic() {
        while end < s.len() && matches!(s[end], b'0'..=b'9' | b'.' | b'+' | b'-' | b' ' | b'\t') {
            end += 1;
        }
    } else if first == b'(' {
        while end < s.len() && s[end] != b')' {
            end += 1;
        }
        end = (end + 1).min(s.len());
    } else if first == b'%' {
        end = s.len();
    }
    let text = String::from_utf8_lossy(&s[at..end.min(at + 40)]);
    text.trim_end().to_string()
}

fn col(i: usize) -> u32 {
    u32::try_from(i + 1).unwrap_or(u32::MAX)
}

/// The error for a bad number after the letter at `at`: a `#` or `[` in its place is reported as
/// the unsupported parameter or expression it starts.
fn number_error(s: &[u8], line_no: u64, at: usize, detail: &'static str) -> GcodeError {
    let next = skip_ws(s, at + 1);
    match s.get(next) {
        Some(b'#') => error_at(s, line_no, next, ErrorKind::Parameter),
        Some(b'[') => error_at(s, line_no, next, ErrorKind::Expression),
        _ => error_at(s, line_no, at, ErrorKind::BadNumber { detail }),
    }
}

/// The error for the word at byte `at` of line `line_no`.
pub fn error_at(s: &[u8], line_no: u64, at: usize, kind: ErrorKind) -> GcodeError {
    GcodeError::Invalid { line: line_no, column: col(at), word: word_text(s, at), kind }
}

/// Parses one line (a trailing `\n` / `\r\n` is ignored) into `block`.
///
/// `block_delete`: the block-delete switch; when on, a line starting with `/` is
/// [`BlockKind::Deleted`] and not read further; when off, the `/` is ignored.
pub fn parse_line(
    line: &[u8],
    line_no: u64,
    block_delete: bool,
    block: &mut Block,
) -> Result<(), GcodeError> {
    block.clear();
    let mut n = line.len();
    while n > 0 && matches!(line[n - 1], b'\n' | b'\r') {
        n -= 1;
    }
    let s = &line[..n];
    let mut i = skip_ws(s, 0);
    if i == n {
        return Ok(());
    }
    match s[i] {
        b'%' => {
            if skip_ws(s, i + 1) != n {
                return Err(error_at(s, line_no, i, ErrorKind::MisplacedPercent));
            }
            block.kind = BlockKind::Percent;
            return Ok(());
        }
        b'/' => {
            if block_delete {
                block.kind = BlockKind::Deleted;
                return Ok(());
            }
            i = skip_ws(s, i + 1);
        }
        _ => {}
    }
    block.kind = BlockKind::Words;
    if i < n && CLASS[s[i] as usize] == C_O {
        return program_number(s, line_no, i, block);
    }
    if i < n && CLASS[s[i] as usize] == C_N {
        let at = i;
        i += 1;
        let v = parse_number(s, &mut i).map_err(|d| number_error(s, line_no, at, d))?;
        block.line_number = Some(v);
    }
    loop {
        i = skip_ws(s, i);
        if i >= n {
            return Ok(());
        }
        let at = i;
        let c = s[i];
        let class = CLASS[c as usize];
        if (class as usize) < LETTER_COUNT {
            i += 1;
            let v = parse_number(s, &mut i).map_err(|d| number_error(s, line_no, at, d))?;
            let bit = 1u16 << class;
            if block.words & bit != 0 {
                return Err(error_at(s, line_no, at, ErrorKind::RepeatedWord));
            }
            block.words |= bit;
            block.values[class as usize] = v;
            block.cols[class as usize] = col(at);
            if block.first_col == 0 {
                block.first_col = col(at);
            }
            continue;
        }
        match class {
            C_G => {
                i += 1;
                let v = parse_number(s, &mut i).map_err(|d| number_error(s, line_no, at, d))?;
                let tenths = v * 10.0;
                let code = tenths.round();
                if !(0.0..=10_000.0).contains(&code) || (tenths - code).abs() > 1e-6 {
                    return Err(error_at(s, line_no, at, ErrorKind::UnknownG));
                }
                let code = code as u16;
                let group = g_group(u32::from(code)).map_err(|k| error_at(s, line_no, at, k))?;
                let g = group as usize;
                if block.g_mask & (1 << g) != 0 {
                    let other = word_text(s, block.g_cols[g] as usize - 1);
                    let kind = ErrorKind::ModalGroupConflict { group: group.name(), other };
                    return Err(error_at(s, line_no, at, kind));
                }
                block.g_mask |= 1 << g;
                block.g_codes[g] = code;
                block.g_cols[g] = col(at);
            }
            C_M => {
                i += 1;
                let v = parse_number(s, &mut i).map_err(|d| number_error(s, line_no, at, d))?;
                if v.fract() != 0.0 {
                    return Err(error_at(
                        s,
                        line_no,
                        at,
                        ErrorKind::NotAnInteger { what: "M code", value: v },
                    ));
                }
                if !(0.0..=1000.0).contains(&v) {
                    return Err(error_at(s, line_no, at, ErrorKind::UnknownM));
                }
                let group = m_group(v as u32).map_err(|k| error_at(s, line_no, at, k))?;
                let g = group as usize;
                if block.m_mask & (1 << g) != 0 {
                    let other = word_text(s, block.m_cols[g] as usize - 1);
                    let kind = ErrorKind::ModalGroupConflict { group: group.name(), other };
                    return Err(error_at(s, line_no, at, kind));
                }
                block.m_mask |= 1 << g;
                block.m_codes[g] = v as u8;
                block.m_cols[g] = col(at);
            }
            C_OPEN => i = skip_comment(s, line_no, i)?,
            C_SEMI => return Ok(()),
            C_N => return Err(error_at(s, line_no, at, ErrorKind::LineNumberNotFirst)),
            C_O => return Err(error_at(s, line_no, at, ErrorKind::OWord)),
            C_CLOSE => return Err(error_at(s, line_no, at, ErrorKind::StrayCommentEnd)),
            C_HASH => return Err(error_at(s, line_no, at, ErrorKind::Parameter)),
            C_BRACKET => return Err(error_at(s, line_no, at, ErrorKind::Expression)),
            C_SLASH => return Err(error_at(s, line_no, at, ErrorKind::MisplacedBlockDelete)),
            C_PERCENT => return Err(error_at(s, line_no, at, ErrorKind::MisplacedPercent)),
            C_BAD_LETTER => {
                let kind = ErrorKind::UnsupportedLetter { reason: bad_letter_reason(c) };
                return Err(error_at(s, line_no, at, kind));
            }
            _ => {
                let kind = if matches!(c, b'0'..=b'9' | b'.' | b'+' | b'-') {
                    ErrorKind::BadNumber { detail: "a number without a letter" }
                } else {
                    ErrorKind::UnexpectedChar { found: char::from(c) }
                };
                return Err(error_at(s, line_no, at, kind));
            }
        }
    }
}

/// Skips the comment opening at `i`; returns the index after its `)`.
fn skip_comment(s: &[u8], line_no: u64, i: usize) -> Result<usize, GcodeError> {
    let mut j = i + 1;
    while j < s.len() {
        match s[j] {
            b')' => return Ok(j + 1),
            b'(' => return Err(error_at(s, line_no, j, ErrorKind::NestedComment)),
            _ => j += 1,
        }
    }
    Err(error_at(s, line_no, i, ErrorKind::UnclosedComment))
}

/// `O1234` followed only by comments: a program number. Anything else with O is an O-word.
fn program_number(s: &[u8], line_no: u64, at: usize, block: &mut Block) -> Result<(), GcodeError> {
    let mut i = skip_ws(s, at + 1);
    let digits_start = i;
    while i < s.len() && s[i].is_ascii_digit() {
        i += 1;
    }
    if i == digits_start {
        return Err(error_at(s, line_no, at, ErrorKind::OWord));
    }
    loop {
        i = skip_ws(s, i);
        match s.get(i) {
            None | Some(b';') => break,
            Some(b'(') => i = skip_comment(s, line_no, i)?,
            Some(_) => return Err(error_at(s, line_no, at, ErrorKind::OWord)),
        }
    }
    block.kind = BlockKind::ProgramNumber;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn parse(line: &str) -> Result<Block, GcodeError> {
        let mut b = Block::new();
        parse_line(line.as_bytes(), 1, true, &mut b).map(|()| b)
    }

    fn err(line: &str) -> (u32, String, ErrorKind) {
        match parse(line) {
            Err(GcodeError::Invalid { column, word, kind, .. }) => (column, word, kind),
            other => panic!("{line:?}: expected an error, got {other:?}"),
        }
    }

    #[test]
    fn words_spaces_case_and_comments() {
        let b = parse("n10.5 g1x1 Y 2 .5 z-.5 (a;b) f+300. ; c (d").expect("parse");
        assert_eq!(b.kind(), BlockKind::Words);
        assert_eq!(b.line_number(), Some(10.5));
        assert_eq!(b.g(GGroup::Motion), Some(10));
        assert_eq!(b.get(Letter::X), Some(1.0));
        assert_eq!(b.get(Letter::Y), Some(2.5));
        assert_eq!(b.get(Letter::Z), Some(-0.5));
        assert_eq!(b.get(Letter::F), Some(300.0));
        assert_eq!(b.column(Letter::Y), 12);
        assert!(!b.has(Letter::A));
        assert_eq!(parse("X1 2").expect("x").get(Letter::X), Some(12.0));
    }

    #[test]
    fn g_codes_in_tenths_and_groups() {
        let b = parse("G21 G90 G17 G94 G40 G49 G80 G91.1 G64 G54 G97 G98").expect("parse");
        assert_eq!(b.g(GGroup::Units), Some(210));
        assert_eq!(b.g(GGroup::Motion), Some(800));
        assert_eq!(b.g(GGroup::ArcDistance), Some(911));
        assert_eq!(b.g(GGroup::CoordSystem), Some(540));
        assert_eq!(parse("G01").expect("g01").g(GGroup::Motion), Some(10));
        assert_eq!(parse("G90.10").expect("g").g(GGroup::ArcDistance), Some(901));
        let b = parse("M3 M8 M6 M52 M30").expect("m");
        assert_eq!(b.m(MGroup::Spindle), Some(3));
        assert_eq!(b.m(MGroup::Stop), Some(30));
    }

    #[test]
    fn special_lines() {
        assert_eq!(parse("  %  ").expect("%").kind(), BlockKind::Percent);
        assert_eq!(parse(" /G1 X5 X6").expect("/").kind(), BlockKind::Deleted);
        let mut b = Block::new();
        parse_line(b"/G1 X5", 1, false, &mut b).expect("/ off");
        assert_eq!((b.kind(), b.get(Letter::X)), (BlockKind::Words, Some(5.0)));
        assert_eq!(parse("O0001 (DEPTHMILL)").expect("o").kind(), BlockKind::ProgramNumber);
        assert_eq!(parse("\r\n").expect("blank").kind(), BlockKind::Blank);
        let b = parse("(only a comment)").expect("comment");
        assert_eq!(b.kind(), BlockKind::Words);
        assert!(!b.has_codes() && !b.has_axis_words());
    }

    #[test]
    fn errors_name_the_column_and_word() {
        assert_eq!(err("G0 X1 (abc"), (7, "(abc".into(), ErrorKind::UnclosedComment));
        assert_eq!(err("G0 (a (b) c)").2, ErrorKind::NestedComment);
        assert_eq!(err("G0 (a (b) c)").0, 7);
        assert_eq!(err("G0 X1 ) Y1"), (7, ")".into(), ErrorKind::StrayCommentEnd));
        assert_eq!(
            err("G0 X"),
            (4, "X".into(), ErrorKind::BadNumber { detail: "no digits after the letter" })
        );
        assert_eq!(err("G0 X1.2.3").0, 4);
        assert_eq!(err("G0 X1.2.3").1, "X1.2.3");
        assert_eq!(err("G0 X#1"), (5, "#".into(), ErrorKind::Parameter));
        assert_eq!(err("G0 X[1+2]"), (5, "[".into(), ErrorKind::Expression));
        assert_eq!(err("G1 G41 D1"), (4, "G41".into(), ErrorKind::CutterCompensation));
        assert_eq!(err("N5 G81 X1 Y1 Z-1 R1").2, ErrorKind::CannedCycle);
        assert_eq!(err("o100 sub"), (1, "o100".into(), ErrorKind::OWord));
        assert_eq!(err("G0 X1 O5").2, ErrorKind::OWord);
        assert_eq!(err("G0 N10 X1"), (4, "N10".into(), ErrorKind::LineNumberNotFirst));
        assert_eq!(err("G0 X1 /Y2").2, ErrorKind::MisplacedBlockDelete);
        assert_eq!(err("G0 X1 X2"), (7, "X2".into(), ErrorKind::RepeatedWord));
        assert_eq!(err("G1.5 X1"), (1, "G1.5".into(), ErrorKind::UnknownG));
        assert_eq!(err("M6.5").2, ErrorKind::NotAnInteger { what: "M code", value: 6.5 });
        assert!(matches!(err("G0 X1 E5").2, ErrorKind::UnsupportedLetter { .. }));
        assert!(matches!(err("G0 B5").2, ErrorKind::UnsupportedLetter { .. }));
        assert_eq!(err("G0 X1 $1").2, ErrorKind::UnexpectedChar { found: '$' });
        assert_eq!(err("% (x)").2, ErrorKind::MisplacedPercent);
        assert_eq!(err("G0 X1 %").2, ErrorKind::MisplacedPercent);
        let (c, w, k) = err("G0 X1 G1 Y1");
        assert_eq!((c, w.as_str()), (7, "G1"));
        assert_eq!(k, ErrorKind::ModalGroupConflict { group: GGroup::Motion.name(), other: "G0".into() });
        assert!(matches!(err("M3 M8 M9").2, ErrorKind::ModalGroupConflict { .. }));
        assert!(matches!(err("M62 P1").2, ErrorKind::UnsupportedM { .. }));
        assert_eq!(err("M77").2, ErrorKind::UnknownM);
        assert_eq!(
            err("G0 X1 -2").2,
            ErrorKind::BadNumber { detail: "trailing characters after the number" }
        );
    }

    #[test]
    fn long_numbers_fall_back_exactly() {
        for t in ["0.000000000000000000000000123", "123456789012345678901234", "-9007199254740993", "1.5"] {
            let mut i = 0;
            let v = parse_number(t.as_bytes(), &mut i).expect(t);
            assert_eq!(v, t.parse::<f64>().expect("std"), "{t}");
            assert_eq!(i, t.len());
        }
        let long = format!("1.{}", "0".repeat(80));
        assert_eq!(parse_number(long.as_bytes(), &mut 0), Err("too many digits"));
    }

    /// Reference: the obvious way (strip comments and spaces, split at letters, std float parser).
    fn reference_words(line: &str) -> Vec<(char, f64)> {
        let mut clean = String::new();
        let mut in_comment = false;
        for c in line.chars() {
            match (in_comment, c) {
                (false, ';') => break,
                (false, '(') => in_comment = true,
                (true, ')') => in_comment = false,
                (false, c) if !c.is_whitespace() => clean.push(c.to_ascii_uppercase()),
                _ => {}
            }
        }
        let mut out = Vec::new();
        let mut letter = None;
        let mut num = String::new();
        for c in clean.chars().chain(std::iter::once('@')) {
            if c.is_ascii_alphabetic() || c == '@' {
                if let Some(l) = letter.take() {
                    out.push((l, num.parse::<f64>().expect("reference number")));
                }
                letter = Some(c);
                num.clear();
            } else {
                num.push(c);
            }
        }
        out
    }

    fn number_text() -> impl Strategy<Value = String> {
        (any::<bool>(), 0u64..10_000_000_000_000_000_000, 0usize..25).prop_map(|(neg, m, d)| {
            let digits = m.to_string();
            let d = d.min(digits.len());
            let (int, frac) = digits.split_at(digits.len() - d);
            let sign = if neg { "-" } else { "" };
            if d == 0 { format!("{sign}{int}") } else { format!("{sign}{int}.{frac}") }
        })
    }

    proptest! {
        #[test]
        fn numbers_match_std_parse(t in number_text()) {
            let mut i = 0;
            let v = parse_number(t.as_bytes(), &mut i).expect("parse");
            let want = t.parse::<f64>().expect("std");
            prop_assert_eq!(v.to_bits(), want.to_bits(), "{}", t);
        }

        #[test]
        fn lexer_matches_reference(
            words in prop::collection::vec(
                (prop::sample::select(vec!['X', 'Y', 'Z', 'A', 'F', 'S', 'I', 'J', 'K', 'R', 'P', 'Q', 'T', 'H']),
                 number_text(), any::<bool>(), 0usize..4), 1..8),
            trailing in prop::option::of("[a-z ;()]{0,10}"),
        ) {
            let mut seen = std::collections::HashSet::new();
            let mut line = String::new();
            for (l, num, lower, style) in &words {
                if !seen.insert(*l) { continue; }
                let l = if *lower { l.to_ascii_lowercase() } else { *l };
                match style {
                    0 => line.push_str(&format!("{l}{num}")),
                    1 => line.push_str(&format!(" {l} {num} ")),
                    2 => line.push_str(&format!("{l}{num}(c;x)")),
                    _ => line.push_str(&format!("\t{l}{num}")),
                }
            }
            if let Some(t) = trailing {
                line.push_str(&format!(";{t}"));
            }
            let mut b = Block::new();
            parse_line(line.as_bytes(), 1, true, &mut b).expect("parse");
            let want = reference_words(&line);
            let got: Vec<(char, f64)> =
                Letter::ALL.iter().filter_map(|&l| b.get(l).map(|v| (l.as_char(), v))).collect();
            let mut want_sorted = want.clone();
            want_sorted.sort_by_key(|w| w.0);
            let mut got_sorted = got.clone();
            got_sorted.sort_by_key(|w| w.0);
            prop_assert_eq!(got_sorted, want_sorted, "{}", line);
        }
    }
}
