//! Errors of the G-code interpreter.
//!
//! Every refusal names the 1-based line, the 1-based byte column of the offending word, the word as
//! written and the reason ([`ErrorKind`]). The interpreter stops at the first error: a program is
//! either run completely or refused at a known place, never partly skipped.

use std::io;

/// Why a line was refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum ErrorKind {
    // ----- lexical -----
    /// `(` without a closing `)` on the same line.
    #[error("unclosed comment: `(` without `)` on the same line")]
    UnclosedComment,
    /// `(` inside a `( )` comment.
    #[error("nested comment: `(` inside a comment")]
    NestedComment,
    /// `)` outside a comment.
    #[error("`)` outside a comment")]
    StrayCommentEnd,
    /// The number after a letter is missing or malformed.
    #[error("bad number: {detail}")]
    BadNumber {
        /// What is wrong with it.
        detail: &'static str,
    },
    /// A word whose value must be a whole number is not.
    #[error("{what} must be a whole number, got {value}")]
    NotAnInteger {
        /// The word's role (`T tool number`, `M code`, ...).
        what: &'static str,
        /// The value as read.
        value: f64,
    },
    /// A value outside its allowed range.
    #[error("{what} is {value}, allowed {allowed}")]
    OutOfRange {
        /// The word's role.
        what: &'static str,
        /// The value as read.
        value: f64,
        /// The allowed range, in words.
        allowed: &'static str,
    },
    /// A character that starts no word.
    #[error("unexpected character {found:?}")]
    UnexpectedChar {
        /// The character (bytes >= 0x80 are shown as U+0080..U+00FF).
        found: char,
    },
    /// A letter this interpreter does not know.
    #[error("{reason}")]
    UnsupportedLetter {
        /// Which letter and why.
        reason: &'static str,
    },
    /// The same letter twice in one block.
    #[error("the same letter appears twice in one block")]
    RepeatedWord,
    /// `N` elsewhere than at the start of the block.
    #[error("N (block number) must be the first word of the block")]
    LineNumberNotFirst,
    /// `/` elsewhere than at the start of the line.
    #[error("`/` (block delete) must be the first character of the line")]
    MisplacedBlockDelete,
    /// A line longer than the configured limit.
    #[error("line longer than {max} bytes")]
    LineTooLong {
        /// The limit.
        max: usize,
    },
    /// `%` that is not a bare first or last line.
    #[error("`%` is only allowed alone on the first non-blank line and on the line ending the program")]
    MisplacedPercent,

    // ----- unsupported language -----
    /// G41/G42.
    #[error("cutter radius compensation (G41/G42) is not supported")]
    CutterCompensation,
    /// G73, G74, G76, G81-G89.
    #[error("canned cycles (G73, G74, G76, G81-G89) are not supported")]
    CannedCycle,
    /// LinuxCNC O-words (subroutines, loops, conditionals); a bare Fanuc program number `O1234` is fine.
    #[error(
        "O-words (subroutines, loops, conditionals) are not supported; only a bare program number `O1234`"
    )]
    OWord,
    /// `#` parameters.
    #[error("parameters (`#`) are not supported")]
    Parameter,
    /// `[` expressions.
    #[error("expressions (`[...]`) are not supported")]
    Expression,
    /// A known G code outside the supported language.
    #[error("{reason}")]
    UnsupportedG {
        /// Which code and why.
        reason: &'static str,
    },
    /// A known M code outside the supported language.
    #[error("{reason}")]
    UnsupportedM {
        /// Which code and why.
        reason: &'static str,
    },
    /// A G code no control defines.
    #[error("unknown G code")]
    UnknownG,
    /// An M code no control defines.
    #[error("unknown M code")]
    UnknownM,

    // ----- block semantics -----
    /// Two codes of one modal group in a block.
    #[error("two codes of modal group `{group}` in one block (the other is `{other}`)")]
    ModalGroupConflict {
        /// The group's name.
        group: &'static str,
        /// The other word.
        other: String,
    },
    /// Axis words with G80 or before any motion mode.
    #[error("axis words without a motion mode (G80 or no G0/G1/G2/G3 in effect)")]
    AxisWordsWithoutMotion,
    /// G28 and G0-G3 in one block both want the axis words.
    #[error("G28 and a motion code in one block both use the axis words")]
    AxisWordsClaimedTwice,
    /// A word no code of the block uses.
    #[error("{letter} word with no {needs} to use it")]
    UnusedWord {
        /// The letter.
        letter: char,
        /// What would use it.
        needs: &'static str,
    },
    /// A feed move with F = 0 (LinuxCNC: F starts at 0, and G94/G95 reset it).
    #[error("feed move with zero feed rate (give F; G94/G95 reset F to 0)")]
    ZeroFeedRate,
    /// A feed move in G95 with S = 0.
    #[error("feed per revolution (G95) with zero spindle speed (give S)")]
    ZeroSpindleSpeedPerRev,
    /// A feed move in G93 without its F word.
    #[error("inverse time feed (G93): every feed move needs its own F word (1 / minutes to take)")]
    InverseTimeWithoutF,
    /// G53 in G91.
    #[error("G53 (machine coordinates) cannot be used in incremental mode G91")]
    G53Incremental,
    /// G53 with something other than a G0/G1 move.
    #[error("G53 (machine coordinates) needs a G0 or G1 move in the same block")]
    G53NeedsLinearMove,
    /// T or H naming a tool that is not in the tool table.
    #[error("tool {tool} is not in the tool table")]
    UnknownTool {
        /// The tool number.
        tool: u32,
    },
    /// G4 without P.
    #[error("G4 (dwell) needs P, the time in seconds")]
    DwellWithoutP,
    /// G2/G3 with neither R nor I/J/K.
    #[error("arc with neither R nor I/J/K (the centre)")]
    ArcWithoutCenter,
    /// G2/G3 with both R and I/J/K.
    #[error("arc with both R and I/J/K")]
    ArcMixedFormat,
    /// R-format arc without in-plane axis words.
    #[error("R-format arc without an end point in the plane ({axes} words missing)")]
    ArcWithoutEnd {
        /// The plane's axes, e.g. `X and Y`.
        axes: &'static str,
    },
    /// I/J/K word for the axis normal to the plane.
    #[error("{letter} word is not in the arc plane {plane}")]
    ArcOffsetOutOfPlane {
        /// The letter.
        letter: char,
        /// The plane (`G17 XY`, ...).
        plane: &'static str,
    },
    /// R-format arc whose end is its start.
    #[error("R-format arc whose end point is its start (a full circle needs I/J/K)")]
    ArcRFullCircle,
    /// R too small to reach the end point.
    #[error(
        "arc radius {radius_mm:.4} mm is too small to reach the end point: half the chord is {half_chord_mm:.4} mm (tolerance {tolerance_mm} mm)"
    )]
    ArcRadiusTooSmall {
        /// |R| in mm.
        radius_mm: f64,
        /// Half the start-end distance, mm.
        half_chord_mm: f64,
        /// Allowed shortfall, mm.
        tolerance_mm: f64,
    },
    /// Centre on the start or end point.
    #[error(
        "zero-radius arc: start radius {start_radius_mm:.5} mm, end radius {end_radius_mm:.5} mm (minimum {min_mm} mm)"
    )]
    ArcZeroRadius {
        /// Centre-start distance, mm.
        start_radius_mm: f64,
        /// Centre-end distance, mm.
        end_radius_mm: f64,
        /// Smallest radius accepted, mm.
        min_mm: f64,
    },
    /// Start and end radii of a centre-format arc differ too much.
    #[error(
        "arc radius mismatch: start radius {start_radius_mm:.4} mm, end radius {end_radius_mm:.4} mm, difference {difference_mm:.4} mm ({relative_pct:.4} %); allowed {tolerance_mm:.4} mm, or up to {hard_limit_mm:.4} mm while within {relative_tolerance_pct} %"
    )]
    ArcRadiusMismatch {
        /// Centre-start distance, mm.
        start_radius_mm: f64,
        /// Centre-end distance, mm.
        end_radius_mm: f64,
        /// |start - end|, mm.
        difference_mm: f64,
        /// Difference relative to the larger radius, percent.
        relative_pct: f64,
        /// Absolute tolerance, mm.
        tolerance_mm: f64,
        /// Hard limit (never accepted beyond), mm.
        hard_limit_mm: f64,
        /// Relative tolerance, percent.
        relative_tolerance_pct: f64,
    },

    // ----- program structure -----
    /// End of file before M2/M30 (program not started with `%`).
    #[error("file ended without M2/M30")]
    MissingProgramEnd,
    /// End of file before the closing `%` (program started with `%`).
    #[error("file ended without M2/M30 or the closing `%`")]
    MissingClosingPercent,
}

/// A refused program.
#[derive(Debug, thiserror::Error)]
pub enum GcodeError {
    /// A line was refused.
    #[error("line {line}, column {column}{}: {kind}", word_suffix(.word))]
    Invalid {
        /// 1-based line number in the file.
        line: u64,
        /// 1-based byte column of the offending word (1 for whole-line or end-of-file errors).
        column: u32,
        /// The word as written (empty for end-of-file errors).
        word: String,
        /// Why.
        kind: ErrorKind,
    },
    /// Reading the program failed.
    #[error("failed to read the program at line {line}")]
    Io {
        /// The line being read.
        line: u64,
        /// The read error.
        #[source]
        source: io::Error,
    },
}

fn word_suffix(word: &str) -> String {
    if word.is_empty() { String::new() } else { format!(" (`{word}`)") }
}

impl GcodeError {
    /// The 1-based line number.
    pub fn line(&self) -> u64 {
        match self {
            GcodeError::Invalid { line, .. } | GcodeError::Io { line, .. } => *line,
        }
    }

    /// The 1-based byte column, `None` for read errors.
    pub fn column(&self) -> Option<u32> {
        match self {
            GcodeError::Invalid { column, .. } => Some(*column),
            GcodeError::Io { .. } => None,
        }
    }

    /// The reason, `None` for read errors.
    pub fn kind(&self) -> Option<&ErrorKind> {
        match self {
            GcodeError::Invalid { kind, .. } => Some(kind),
            GcodeError::Io { .. } => None,
        }
    }

    /// The offending word as written, `None` for read errors.
    pub fn word(&self) -> Option<&str> {
        match self {
            GcodeError::Invalid { word, .. } => Some(word),
            GcodeError::Io { .. } => None,
        }
    }
}
