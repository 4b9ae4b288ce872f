//! G-code interpreter of the machine service: RS-274 text in, canonical machine commands out.
//!
//! The simulated EMCO mill (and the adaptive loop) consume [`Canon`] commands; this module turns
//! the programs the CAM service writes (LinuxCNC and Fanuc dialects) and hand-written ones into
//! them, the way LinuxCNC's interpreter does, and refuses everything else with the line and
//! column of the offending word.
//!
//! # Use
//! - [`run`]: a whole program from a `BufRead`, pushing commands into a closure; returns a
//!   [`RunSummary`]. [`Canons`]: the same as an iterator. [`Interpreter::execute_line`]: one line
//!   at a time.
//! - Streaming: one reused line buffer and one reused [`Block`]; the state is a few scalars.
//!   Memory is flat in program length (lines longer than [`InterpConfig::max_line_bytes`] are
//!   refused before they are read whole), and no allocation happens per line.
//!
//! # Language
//! - Lines: `%` alone on the first non-blank line starts a program that the next `%` ends;
//!   otherwise M2/M30 ends it (a file ending before either is an error). Lines after the end are
//!   not read. `/` first: block delete ([`InterpConfig::block_delete`]). `N` first (integer or
//!   fractional). `O1234` alone: a Fanuc program number, ignored. Comments `( )` and `;` (a `;`
//!   inside `( )` belongs to the comment). Case and spaces do not matter. See [`lexer`].
//! - Words: X Y Z A C (axes; A and C in degrees), F S T H P Q R I J K, G, M. Values are f64.
//! - G codes by modal group (one per group and block):
//!   motion G0 G1 G2 G3 G80 · non-modal G4 G28 G53 · plane G17 G18 G19 · units G20 G21 ·
//!   distance G90 G91 · arc centres G90.1 G91.1 · feed G93 G94 G95 · G40 · G43 (H) G49 ·
//!   G54-G59 · G61 G61.1 G64 (P, Q) · G97, G98, G99 (accepted; nothing depends on them).
//! - M codes: M0 M1 (pause) · M2 M30 (end) · M3 M4 M5 · M6 · M7 M8 M9 · M52 (P1/no P on, P0 off).
//! - Modal blocks without a G word repeat the motion mode; axis words with G80 (the start
//!   state) are an error. G1/G2/G3 need a feed: F starts at 0 and G93/G94/G95 reset it to 0 (G95
//!   also needs S; G93, inverse time, needs F on every feed move: the move takes 1/F minutes). Arcs: I/J/K (incremental, or absolute with G90.1) or R (negative R: the long
//!   way round); I/J/K without end words is a full circle; P is the number of turns; the axis
//!   normal to the plane makes a helix. Centre-format arcs whose radii differ are checked with
//!   LinuxCNC's rule ([`ArcTolerance`]).
//! - G28 rapids to the point given by its axis words (if any), then to [`InterpConfig::home`]
//!   for the named axes (all axes without words). G53 (with G0/G1, absolute only): the words are
//!   machine coordinates for this block.
//!
//! Not supported, each a [`GcodeError`] naming line, column and word, never skipped silently:
//! cutter compensation G41/G42, canned cycles G73-G89, O-words, `#` parameters, `[ ]`
//! expressions, G10, G30, G33, G38, G92, G96, B/U/V/W axes, D/E/L words, and every code
//! not listed above.
//!
//! # Conventions
//! Canonical positions are machine coordinates of the controlled point in mm (A and C in degrees):
//! `machine = program x units + work offset + tool length offset (Z)` — see [`canon`]. LinuxCNC's
//! `rs274` prints program coordinates in program units and the offsets as separate calls;
//! [`rs274::parse_output`] adds them back so the two can be compared move by move
//! ([`rs274::compare`]).
//!
//! Execution order within a block follows LinuxCNC (see [`interp`]).

pub mod canon;
pub mod error;
pub mod interp;
pub mod lexer;
pub mod rs274;

pub use canon::{Canon, Coolant, FeedMode, PathMode, Plane, Pos, SpindleDir, arc_sweep};
pub use error::{ErrorKind, GcodeError};
pub use interp::{ArcTolerance, Canons, EndReason, InterpConfig, Interpreter, MM_PER_INCH, RunSummary, run};
pub use lexer::{Block, BlockKind, Letter};
