//! LinuxCNC's standalone interpreter `rs274` (Debian package `linuxcnc-uspace`) as a reference.
//!
//! [`run_rs274`] runs `rs274 -t tool.tbl [-v params.var] [-b] -g program` and parses its canonical
//! output, lines like
//!
//! ```text
//!    29 N..... STRAIGHT_TRAVERSE(1.0000, 2.0000, -508.0000, 90.0000, 0.0000, 0.0000)
//!    35 N..... ARC_FEED(5.0000, 6.0000, 5.0000, 4.0000, 1, -1.0000, 90.0000, 0.0000, 0.0000)
//! ```
//!
//! into [`Rs274Canon`]s in **our** frame ([`super::canon`]): rs274 prints positions in the current
//! work frame and program units (4 decimals) and reports the frame apart (`USE_LENGTH_UNITS`,
//! `SET_G5X_OFFSET`, `SET_G92_OFFSET`, `USE_TOOL_LENGTH_OFFSET`, all in program units at the time
//! of the call), so the parser tracks those and adds them back:
//! `machine = printed x units + G5x offset + G92 offset + tool offset`.
//! `ARC_FEED(first_end, second_end, first_centre, second_centre, rotation, axis_end, a, b, c)`
//! uses the axes of the last `SELECT_PLANE` (XY; XZ = first Z, second X; YZ = first Y, second Z).
//!
//! Notes on the standalone `rs274`: without an INI file its tool table (`-t`) and parameter file
//! (`-v`, e.g. G54-G59 origins 5221.., G28 position 5161..) are read in **inches**; the program
//! starts in G21. Block delete is off unless `-b` is given; [`Rs274Options::default`] gives `-b`,
//! matching [`super::InterpConfig::default`].
//!
//! [`compare`] checks that two runs made the same moves, in order.

use std::io::{self, BufRead, BufReader, Read};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::atomic::{AtomicU64, Ordering};

use super::canon::{Canon, Plane, Pos};
use super::interp::MM_PER_INCH;

/// How to run `rs274`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Rs274Options {
    /// Parameter file (`-v`), values in inches.
    pub var_file: Option<PathBuf>,
    /// Block-delete switch on (`-b`).
    pub block_delete: bool,
    /// The executable; `None`: `rs274` found on `PATH`.
    pub executable: Option<PathBuf>,
}

impl Default for Rs274Options {
    fn default() -> Self {
        Rs274Options { var_file: None, block_delete: true, executable: None }
    }
}

/// One canonical call of `rs274` that matters for comparison, converted to our frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Rs274Call {
    /// `STRAIGHT_TRAVERSE`.
    Traverse {
        /// End point (machine, mm / degrees).
        to: Pos,
    },
    /// `STRAIGHT_FEED`.
    Feed {
        /// End point (machine).
        to: Pos,
    },
    /// `ARC_FEED`.
    Arc {
        /// End point (machine).
        end: Pos,
        /// Plane of the last `SELECT_PLANE`.
        plane: Plane,
        /// Centre in the plane's first and second axis (machine).
        center: [f64; 2],
        /// Signed turns.
        rotation: i32,
    },
    /// `DWELL`.
    Dwell {
        /// Seconds.
        seconds: f64,
    },
    /// `CHANGE_TOOL`.
    ToolChange {
        /// Tool number.
        tool: u32,
    },
    /// `ENABLE_ADAPTIVE_FEED` / `DISABLE_ADAPTIVE_FEED`.
    AdaptiveFeed {
        /// On.
        enabled: bool,
    },
    /// `PROGRAM_END` (M2/M30) or `FINISH` (closing `%`).
    ProgramEnd,
}

/// A parsed call with its sequence number and the uncertainty of its printed coordinates.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Rs274Canon {
    /// rs274's call counter (first column).
    pub seq: u64,
    /// The call.
    pub call: Rs274Call,
    /// Half a unit of the last printed digit of the position and of the offsets added to it, mm:
    /// how far the printed numbers may be from the exact ones.
    pub slack_mm: f64,
}

/// Running or reading `rs274` failed.
#[derive(Debug, thiserror::Error)]
pub enum Rs274Error {
    /// `rs274` is not on `PATH`.
    #[error("`rs274` was not found on PATH (Debian package linuxcnc-uspace)")]
    NotFound,
    /// The process could not be started.
    #[error("failed to start `{executable}`")]
    Spawn {
        /// The executable.
        executable: String,
        /// Why.
        #[source]
        source: io::Error,
    },
    /// Reading its output failed.
    #[error("failed to read the output of rs274")]
    Io(#[source] io::Error),
    /// It refused the program.
    #[error("rs274 refused the program ({status}): {message}")]
    Refused {
        /// Exit status.
        status: String,
        /// Its error message (stderr).
        message: String,
        /// How many calls it printed before stopping.
        calls_before: usize,
    },
    /// An output line we cannot read.
    #[error("rs274 output line {line}: {reason}: {text:?}")]
    Parse {
        /// 1-based output line.
        line: u64,
        /// The line.
        text: String,
        /// What is wrong.
        reason: &'static str,
    },
}

/// `rs274` on `PATH`, if any.
pub fn find_rs274() -> Option<PathBuf> {
    let path = std::env::var_os("PATH")?;
    std::env::split_paths(&path).map(|d| d.join("rs274")).find(|p| p.is_file())
}

/// Runs `rs274 -t tool_table -b -g program` and parses its output.
pub fn run_rs274(program: &Path, tool_table: &Path) -> Result<Vec<Rs274Canon>, Rs274Error> {
    run_rs274_with(program, tool_table, &Rs274Options::default())
}

/// [`run_rs274`] with options.
pub fn run_rs274_with(
    program: &Path,
    tool_table: &Path,
    options: &Rs274Options,
) -> Result<Vec<Rs274Canon>, Rs274Error> {
    let exe = match &options.executable {
        Some(e) => e.clone(),
        None => find_rs274().ok_or(Rs274Error::NotFound)?,
    };
    let mut cmd = Command::new(&exe);
    cmd.arg("-t").arg(tool_table);
    if let Some(v) = &options.var_file {
        cmd.arg("-v").arg(v);
    }
    if options.block_delete {
        cmd.arg("-b");
    }
    cmd.arg("-g").arg(program);
    // rs274 keeps its tool table in a memory-mapped `$HOME/.tool.mmap`: concurrent runs sharing
    // one HOME corrupt each other (SIGBUS), so every run gets its own.
    let home = PrivateHome::new().map_err(Rs274Error::Io)?;
    cmd.env("HOME", &home.0);
    cmd.stdin(Stdio::null()).stdout(Stdio::piped()).stderr(Stdio::piped());
    let spawn_err = |source| Rs274Error::Spawn { executable: exe.display().to_string(), source };
    let mut child = cmd.spawn().map_err(spawn_err)?;
    let parsed = match child.stdout.take() {
        Some(out) => parse_output(BufReader::new(out)),
        None => Ok(Vec::new()),
    };
    let mut stderr = String::new();
    if let Some(mut e) = child.stderr.take() {
        e.read_to_string(&mut stderr).map_err(Rs274Error::Io)?;
    }
    let status = child.wait().map_err(Rs274Error::Io)?;
    let calls = parsed?;
    if !status.success() {
        let message = stderr
            .lines()
            .filter(|l| l.trim() != "executing" && !l.trim().is_empty())
            .collect::<Vec<_>>()
            .join(" | ");
        return Err(Rs274Error::Refused { status: status.to_string(), message, calls_before: calls.len() });
    }
    Ok(calls)
}

/// A fresh directory, removed on drop.
struct PrivateHome(PathBuf);

impl PrivateHome {
    fn new() -> io::Result<PrivateHome> {
        static NEXT: AtomicU64 = AtomicU64::new(0);
        let n = NEXT.fetch_add(1, Ordering::Relaxed);
        let dir = std::env::temp_dir().join(format!("depthmill-rs274-{}-{n}", std::process::id()));
        std::fs::create_dir_all(&dir)?;
        Ok(PrivateHome(dir))
    }
}

impl Drop for PrivateHome {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// Frame state while reading the output.
#[derive(Debug, Clone, Copy)]
struct Frame {
    scale: f64,
    plane: Plane,
    /// G5x + G92 + tool offsets, mm / degrees.
    g5x: [f64; 5],
    g92: [f64; 5],
    tool: [f64; 5],
    /// Print uncertainty of the offsets, mm.
    offset_slack: f64,
}

impl Frame {
    fn origin(&self, k: usize) -> f64 {
        self.g5x[k] + self.g92[k] + self.tool[k]
    }

    fn point(&self, p: [f64; 5]) -> Pos {
        Pos::from_array(
            [0, 1, 2, 3, 4].map(|k| if k < 3 { p[k] * self.scale } else { p[k] } + self.origin(k)),
        )
    }

    fn slack(&self) -> f64 {
        0.5e-4 * self.scale + self.offset_slack
    }
}

/// Parses `rs274`'s output (all of it: a bad line is reported after the rest has been read).
pub fn parse_output<R: BufRead>(reader: R) -> Result<Vec<Rs274Canon>, Rs274Error> {
    let mut fr = Frame {
        scale: 1.0,
        plane: Plane::Xy,
        g5x: [0.0; 5],
        g92: [0.0; 5],
        tool: [0.0; 5],
        offset_slack: 0.0,
    };
    let mut out = Vec::new();
    let mut first_err = None;
    let mut args: Vec<f64> = Vec::with_capacity(12);
    for (k, line) in reader.lines().enumerate() {
        let text = line.map_err(Rs274Error::Io)?;
        if first_err.is_some() {
            continue;
        }
        let line_no = k as u64 + 1;
        if let Err(reason) = parse_call(&text, &mut fr, &mut args, &mut out) {
            first_err = Some(Rs274Error::Parse { line: line_no, text, reason });
        }
    }
    match first_err {
        Some(e) => Err(e),
        None => Ok(out),
    }
}

fn numbers(s: &str, args: &mut Vec<f64>) -> Result<(), &'static str> {
    args.clear();
    for t in s.split([',', ' ']).filter(|t| !t.is_empty()) {
        args.push(t.parse::<f64>().map_err(|_| "argument is not a number")?);
    }
    Ok(())
}

fn parse_call(
    text: &str,
    fr: &mut Frame,
    args: &mut Vec<f64>,
    out: &mut Vec<Rs274Canon>,
) -> Result<(), &'static str> {
    let t = text.trim();
    if t.is_empty() {
        return Ok(());
    }
    let (seq, rest) = t.split_once(char::is_whitespace).ok_or("no call after the sequence number")?;
    let seq: u64 = seq.parse().map_err(|_| "no sequence number")?;
    let open = rest.find('(').ok_or("no `(`")?;
    let name = rest[..open].split_whitespace().last().ok_or("no call name")?;
    let inner = rest[open + 1..].strip_suffix(')').ok_or("no closing `)`")?;
    let mut push = |call, slack_mm| out.push(Rs274Canon { seq, call, slack_mm });
    match name {
        "USE_LENGTH_UNITS" => {
            fr.scale = match inner.trim() {
                "CANON_UNITS_MM" => 1.0,
                "CANON_UNITS_INCHES" => MM_PER_INCH,
                _ => return Err("unknown length units"),
            }
        }
        "SELECT_PLANE" => {
            fr.plane = match inner.trim() {
                "CANON_PLANE_XY" => Plane::Xy,
                "CANON_PLANE_XZ" => Plane::Zx,
                "CANON_PLANE_YZ" => Plane::Yz,
                _ => return Err("unsupported plane"),
            }
        }
        "SET_G5X_OFFSET" | "SET_G92_OFFSET" => {
            numbers(inner, args)?;
            let v = if name == "SET_G5X_OFFSET" { args.get(1..) } else { args.get(..) };
            let v = v.filter(|v| v.len() >= 4).ok_or("too few offset values")?;
            // x y z a b c: B is not on the machine.
            let o =
                [v[0] * fr.scale, v[1] * fr.scale, v[2] * fr.scale, v[3], v.get(5).copied().unwrap_or(0.0)];
            if name == "SET_G5X_OFFSET" {
                fr.g5x = o;
            } else {
                fr.g92 = o;
            }
            fr.offset_slack = 1.5e-4 * fr.scale;
        }
        "USE_TOOL_LENGTH_OFFSET" => {
            numbers(inner, args)?;
            if args.len() < 4 {
                return Err("too few tool offset values");
            }
            fr.tool = [
                args[0] * fr.scale,
                args[1] * fr.scale,
                args[2] * fr.scale,
                args[3],
                args.get(5).copied().unwrap_or(0.0),
            ];
            fr.offset_slack = 1.5e-4 * fr.scale;
        }
        "SET_XY_ROTATION" => {
            numbers(inner, args)?;
            if args.first().is_some_and(|&r| r != 0.0) {
                return Err("XY rotation is not supported");
            }
        }
        "STRAIGHT_TRAVERSE" | "STRAIGHT_FEED" => {
            numbers(inner, args)?;
            if args.len() < 4 {
                return Err("too few coordinates");
            }
            // x y z a b c
            let to = fr.point([args[0], args[1], args[2], args[3], args.get(5).copied().unwrap_or(0.0)]);
            let call =
                if name == "STRAIGHT_FEED" { Rs274Call::Feed { to } } else { Rs274Call::Traverse { to } };
            push(call, fr.slack());
        }
        "ARC_FEED" => {
            numbers(inner, args)?;
            if args.len() < 7 {
                return Err("too few arc values");
            }
            let [i0, i1, n] = fr.plane.axes();
            let mut p = [0.0; 5];
            p[i0] = args[0];
            p[i1] = args[1];
            p[n] = args[5];
            // a b c after the axis end point
            p[3] = args[6];
            p[4] = args.get(8).copied().unwrap_or(0.0);
            let rotation = args[4];
            if rotation.fract() != 0.0 || rotation.abs() > 1e6 {
                return Err("rotation is not an integer");
            }
            let center = [args[2] * fr.scale + fr.origin(i0), args[3] * fr.scale + fr.origin(i1)];
            let call =
                Rs274Call::Arc { end: fr.point(p), plane: fr.plane, center, rotation: rotation as i32 };
            push(call, fr.slack());
        }
        "DWELL" => {
            numbers(inner, args)?;
            let seconds = *args.first().ok_or("no dwell time")?;
            push(Rs274Call::Dwell { seconds }, 0.0);
        }
        "CHANGE_TOOL" => {
            numbers(inner, args)?;
            let tool = *args.first().ok_or("no tool number")?;
            push(Rs274Call::ToolChange { tool: tool as u32 }, 0.0);
        }
        "ENABLE_ADAPTIVE_FEED" => push(Rs274Call::AdaptiveFeed { enabled: true }, 0.0),
        "DISABLE_ADAPTIVE_FEED" => push(Rs274Call::AdaptiveFeed { enabled: false }, 0.0),
        "PROGRAM_END" | "FINISH" => push(Rs274Call::ProgramEnd, 0.0),
        _ => {}
    }
    Ok(())
}

/// Two runs differ.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("move {index}: {reason}\n  ours:  {ours}\n  rs274: {theirs}")]
pub struct Mismatch {
    /// 0-based index among the moves (traverses, feeds, arcs).
    pub index: usize,
    /// Our move (`-` if none).
    pub ours: String,
    /// rs274's move (`-` if none).
    pub theirs: String,
    /// What differs.
    pub reason: String,
}

/// Compares the moves (traverses, feeds, arcs) of both runs in order: same kind, end points and
/// arc centres within `tol_mm` plus the print slack of rs274's numbers, same plane and rotation.
/// Returns the number of moves compared.
pub fn compare(ours: &[Canon], theirs: &[Rs274Canon], tol_mm: f64) -> Result<usize, Mismatch> {
    let mut a = ours.iter().filter(|c| c.is_motion());
    let mut b = theirs.iter().filter(|c| {
        matches!(c.call, Rs274Call::Traverse { .. } | Rs274Call::Feed { .. } | Rs274Call::Arc { .. })
    });
    let mut index = 0;
    loop {
        match (a.next(), b.next()) {
            (None, None) => return Ok(index),
            (x, y) => {
                let mismatch = |reason: String| Mismatch {
                    index,
                    ours: x.map_or("-".into(), |c| format!("{c:?}")),
                    theirs: y.map_or("-".into(), |c| format!("{c:?}")),
                    reason,
                };
                let (Some(x), Some(y)) = (x, y) else {
                    return Err(mismatch("one run has more moves".into()));
                };
                if let Some(reason) = differ(x, y, tol_mm) {
                    return Err(mismatch(reason));
                }
            }
        }
        index += 1;
    }
}

fn differ(x: &Canon, y: &Rs274Canon, tol_mm: f64) -> Option<String> {
    let tol = tol_mm + y.slack_mm;
    let far = |p: Pos, q: Pos, what: &str| {
        let d = p.max_abs_diff(q);
        (d > tol).then(|| format!("{what} differ by {d:.6} (allowed {tol:.6})"))
    };
    match (*x, y.call) {
        (Canon::Traverse { to, .. }, Rs274Call::Traverse { to: t })
        | (Canon::Feed { to, .. }, Rs274Call::Feed { to: t }) => far(to, t, "end points"),
        (
            Canon::Arc { end, plane, center, rotation, .. },
            Rs274Call::Arc { end: e, plane: p, center: c, rotation: r },
        ) => {
            if plane != p {
                return Some(format!("planes {plane:?} and {p:?}"));
            }
            if rotation != r {
                return Some(format!("rotations {rotation} and {r}"));
            }
            far(end, e, "end points").or_else(|| {
                let d = (center[0] - c[0]).abs().max((center[1] - c[1]).abs());
                (d > tol).then(|| format!("centres differ by {d:.6} (allowed {tol:.6})"))
            })
        }
        _ => Some("different kinds of move".into()),
    }
}

#[cfg(test)]
mod tests {
    use super::super::{ErrorKind, GcodeError, InterpConfig, run};
    use super::*;
    use std::collections::BTreeMap;
    use std::fmt::Write as _;

    #[test]
    fn parses_rs274_output_into_the_machine_frame() {
        let text = "\
    1 N..... USE_LENGTH_UNITS(CANON_UNITS_MM)
    2 N..... SET_G5X_OFFSET(1, 0.0000, 0.0000, 0.0000, 0.0000, 0.0000, 0.0000)
    7 N..... COMMENT(\"a;b (c)\")
   28 N..... USE_TOOL_LENGTH_OFFSET(0.0000 0.0000 508.0000, 0.0000 0.0000 0.0000, 0.0000 0.0000 0.0000)
   29 N..... STRAIGHT_TRAVERSE(1.0000, 2.0000, -508.0000, 90.0000, 0.0000, 0.0000)
   35 N10    ARC_FEED(5.0000, 6.0000, 5.0000, 4.0000, 1, -1.0000, 90.0000, 0.0000, 0.0000)
   40 N..... SET_G5X_OFFSET(2, 25.4000, 50.8000, -12.7000, 10.0000, 0.0000, 0.0000)
   41 N..... SELECT_PLANE(CANON_PLANE_XZ)
   42 N..... USE_LENGTH_UNITS(CANON_UNITS_INCHES)
   43 N..... ARC_FEED(1.0000, 0.5000, 0.0000, 0.0000, -2, 0.1000, 0.0000, 0.0000, 0.0000)
   44 N..... STRAIGHT_FEED(1.0000, 0.0000, 0.0000, 0.0000, 0.0000, 0.0000)
   45 N..... DWELL(1.5000)
   46 N..... CHANGE_TOOL(2)
   47 N..... ENABLE_ADAPTIVE_FEED()
   48 N..... PROGRAM_END()
";
        let calls = parse_output(text.as_bytes()).expect("parse");
        assert_eq!(calls.len(), 8);
        assert_eq!(calls[0].call, Rs274Call::Traverse { to: Pos::new(1.0, 2.0, 0.0, 90.0) });
        assert_eq!(
            calls[1].call,
            Rs274Call::Arc {
                end: Pos::new(5.0, 6.0, -1.0 + 508.0, 90.0),
                plane: Plane::Xy,
                center: [5.0, 4.0],
                rotation: 1
            }
        );
        // G18 in inches with G55 and the tool offset: first axis Z, second X.
        let Rs274Call::Arc { end, plane, center, rotation } = calls[2].call else { panic!("{:?}", calls[2]) };
        assert_eq!((plane, rotation), (Plane::Zx, -2));
        assert!(
            end.max_abs_diff(Pos::new(0.5 * 25.4 + 25.4, 0.1 * 25.4 + 50.8, 25.4 - 12.7 + 508.0, 10.0))
                < 1e-9
        );
        assert!((center[0] - (-12.7 + 508.0)).abs() < 1e-9 && (center[1] - 25.4).abs() < 1e-9);
        assert!(calls[3].slack_mm > 0.00127);
        assert_eq!(calls[4].call, Rs274Call::Dwell { seconds: 1.5 });
        assert_eq!(calls[5].call, Rs274Call::ToolChange { tool: 2 });
        assert_eq!(calls[6].call, Rs274Call::AdaptiveFeed { enabled: true });
        assert_eq!(calls[7].call, Rs274Call::ProgramEnd);
        let bad = parse_output("   3 N..... STRAIGHT_FEED(1.0, x)\n".as_bytes());
        assert!(matches!(bad, Err(Rs274Error::Parse { line: 1, .. })), "{bad:?}");
    }

    #[test]
    fn compare_reports_the_first_difference() {
        let theirs = parse_output(
            "1 N..... STRAIGHT_TRAVERSE(1.0000, 2.0000, 3.0000, 0.0000, 0.0000, 0.0000)\n\
             2 N..... ARC_FEED(1.0000, 2.0000, 0.0000, 0.0000, -1, 3.0000, 0.0000, 0.0000, 0.0000)\n"
                .as_bytes(),
        )
        .expect("parse");
        let t = Canon::Traverse { line: 1, to: Pos::new(1.00004, 2.0, 3.0, 0.0) };
        let arc = |rotation| Canon::Arc {
            line: 2,
            end: Pos::new(1.0, 2.0, 3.0, 0.0),
            plane: Plane::Xy,
            center: [0.0, 0.0],
            rotation,
        };
        assert_eq!(compare(&[t, Canon::Dwell { line: 2, seconds: 1.0 }, arc(-1)], &theirs, 1e-4), Ok(2));
        let e = compare(&[t, arc(1)], &theirs, 1e-4).expect_err("rotation");
        assert_eq!((e.index, e.reason.as_str()), (1, "rotations 1 and -1"));
        let far = Canon::Traverse { line: 1, to: Pos::new(1.0003, 2.0, 3.0, 0.0) };
        assert!(compare(&[far, arc(-1)], &theirs, 1e-4).expect_err("far").reason.starts_with("end points"));
        assert_eq!(compare(&[t], &theirs, 1e-4).expect_err("short").reason, "one run has more moves");
        let feed = Canon::Feed { line: 1, to: Pos::new(1.0, 2.0, 3.0, 0.0) };
        assert_eq!(
            compare(&[feed, arc(-1)], &theirs, 1e-4).expect_err("kind").reason,
            "different kinds of move"
        );
    }

    // ----- side by side with rs274 -----

    /// Tool table in inches (the standalone rs274 has no INI file): T1 25.4 mm, T2 50.8 mm, T3 12.7 mm.
    const TOOL_TABLE: &str = "T1 P1 Z1.0 D0.25 ;flat-6\nT2 P2 Z2.0 D0.125 ;ball-3\nT3 P3 Z0.5 D0.125 ;ball\n";
    /// Parameters in inches: G28 position, G54 current, G55 origin.
    const VAR_FILE: &str =
        "5161 2.0\n5162 1.0\n5163 0.0\n5164 0.0\n5220 1.0\n5241 1.0\n5242 -0.5\n5243 0.25\n5244 15.0\n";

    fn config() -> InterpConfig {
        let mut c = InterpConfig {
            tools: BTreeMap::from([(1, 25.4), (2, 50.8), (3, 12.7)]),
            home: Pos::new(50.8, 25.4, 0.0, 0.0),
            ..InterpConfig::default()
        };
        c.work_offsets[1] = Pos::new(25.4, -12.7, 6.35, 15.0);
        c
    }

    fn ours(text: &str) -> Result<Vec<Canon>, GcodeError> {
        let mut v = Vec::new();
        run(text.as_bytes(), config(), |c| v.push(c)).map(|_| v)
    }

    /// `None` when rs274 is not installed (and not required).
    fn rs274(text: &str) -> Option<Result<Vec<Rs274Canon>, Rs274Error>> {
        if find_rs274().is_none() {
            assert!(
                std::env::var("DEPTHMILL_REQUIRE_RS274").as_deref() != Ok("1"),
                "DEPTHMILL_REQUIRE_RS274=1 but rs274 is not on PATH"
            );
            eprintln!("note: rs274 not on PATH (apt-get install linuxcnc-uspace); comparison skipped");
            return None;
        }
        let dir = tempfile::tempdir().expect("tempdir");
        let prog = dir.path().join("prog.ngc");
        let tbl = dir.path().join("tool.tbl");
        let var = dir.path().join("params.var");
        std::fs::write(&prog, text).expect("write");
        std::fs::write(&tbl, TOOL_TABLE).expect("write");
        std::fs::write(&var, VAR_FILE).expect("write");
        let opts = Rs274Options { var_file: Some(var), ..Rs274Options::default() };
        Some(run_rs274_with(&prog, &tbl, &opts))
    }

    fn agree(name: &str, text: &str) -> usize {
        let mine = ours(text).unwrap_or_else(|e| panic!("{name}: ours refused: {e}\n{text}"));
        let Some(theirs) = rs274(text) else { return 0 };
        let theirs = theirs.unwrap_or_else(|e| panic!("{name}: rs274 refused: {e}\n{text}"));
        let n = compare(&mine, &theirs, 1e-4).unwrap_or_else(|e| panic!("{name}: {e}\n{text}"));
        // Dwell, tool change and adaptive feed calls agree too.
        let events = |c: &Canon| match *c {
            Canon::Dwell { seconds, .. } => Some(Rs274Call::Dwell { seconds }),
            Canon::ToolChange { tool, .. } => Some(Rs274Call::ToolChange { tool }),
            Canon::AdaptiveFeed { enabled, .. } => Some(Rs274Call::AdaptiveFeed { enabled }),
            Canon::ProgramEnd { .. } => Some(Rs274Call::ProgramEnd),
            _ => None,
        };
        let a: Vec<_> = mine.iter().filter_map(events).collect();
        let b: Vec<_> = theirs
            .iter()
            .map(|c| c.call)
            .filter(|c| {
                !matches!(c, Rs274Call::Traverse { .. } | Rs274Call::Feed { .. } | Rs274Call::Arc { .. })
            })
            .collect();
        assert_eq!(a, b, "{name}");
        n
    }

    fn both_refuse(name: &str, text: &str) -> ErrorKind {
        let e = ours(text).expect_err(name);
        if let Some(theirs) = rs274(text) {
            assert!(matches!(theirs, Err(Rs274Error::Refused { .. })), "{name}: rs274 accepted it");
        }
        e.kind().cloned().unwrap_or_else(|| panic!("{name}: {e}"))
    }

    /// The CAM service's LinuxCNC output for its `tiny` test program (services/cam gcode.rs).
    const CAM_LINUXCNC: &str = "%\n(depthmill)\n(tolerance 0.01 mm)\nG21 G90 G17 G94 G40 G49 G80\nG64 P0.0100\n\
(face 1 at A 90.0000 deg)\nG53 G0 Z0.0000\nG0 A90.0000\n\
(T2 ball-3: ball D3.0000 mm, 2 flutes - finishing-raster-x with ball-3 [test])\nT2 M6\nS2000 M3\nM8\nG43 H2\n\
G0 X1.0000 Y2.0000\nZ10.0000\nG1 Z-1.0000 F60.0000\nX5.0000 F120.0000\nG3 X5.0000 Y6.0000 I0.0000 J2.0000\n\
G1 Z-0.5000\nX4.0000\nG0 Z10.0000\nM5\nM9\nG53 G0 Z0.0000\nM30\n%\n";

    /// The same for Fanuc.
    const CAM_FANUC: &str = "%\nO0001 (DEPTHMILL)\nN10 (TOLERANCE 0.01 MM)\nN20 G21 G90 G17 G94 G40 G49 G80\n\
N30 (FACE 1 AT A 90.0000 DEG)\nN40 G91 G28 Z0.0000\nN50 G90\nN60 G0 A90.0000\n\
N70 (T2 BALL-3: BALL D3.0000 MM, 2 FLUTES - FINISHING-RASTER-X WITH BALL-3 [TEST])\nN80 T2 M6\nN90 S2000 M3\n\
N100 M8\nN110 G0 X1.0000 Y2.0000\nN120 Z10.0000\nN130 G1 Z-1.0000 F60.0000\nN140 X5.0000 F120.0000\n\
N150 G3 X5.0000 Y6.0000 I0.0000 J2.0000\nN160 G1 Z-0.5000\nN170 X4.0000\nN180 G0 Z10.0000\nN190 M5\nN200 M9\n\
N210 G91 G28 Z0.0000\nN220 G90\nN230 M30\n%\n";

    /// A CAM-style finishing program as the CAM writer formats it: raster passes with arcs at the
    /// turns, 4 decimals, modal words, two tools, A rotations, both dialects.
    fn cam_program(fanuc: bool, passes: usize) -> String {
        let mut lines: Vec<String> = vec![];
        let retract = |lines: &mut Vec<String>| {
            if fanuc {
                lines.push("G91 G28 Z0.0000".into());
                lines.push("G90".into());
            } else {
                lines.push("G53 G0 Z0.0000".into());
            }
        };
        lines.push("G21 G90 G17 G94 G40 G49 G80".into());
        if !fanuc {
            lines.push("G64 P0.0100".into());
        }
        for (face, a) in [(1, 0.0), (2, -45.0)] {
            lines.push(format!("(face {face} at A {a:.4} deg)"));
            retract(&mut lines);
            lines.push(format!("G0 A{a:.4}"));
            let tool = face;
            lines.push(format!("T{tool} M6"));
            lines.push("S1800 M3".into());
            if !fanuc {
                lines.push(format!("G43 H{tool}"));
            }
            lines.push("G0 X0.0000 Y0.0000".into());
            lines.push("Z5.0000".into());
            lines.push("G1 Z-0.5000 F100.0000".into());
            let mut motion = 1;
            let mut f_set = false;
            for p in 0..passes {
                let y = p as f64 * 1.2;
                let (x0, x1) = if p.is_multiple_of(2) { (0.0, 30.0) } else { (30.0, 0.0) };
                let n = 40;
                for i in 1..=n {
                    let x = x0 + (x1 - x0) * i as f64 / n as f64;
                    let z = -0.5 + 0.3 * (x * 0.2).sin() * (y * 0.3).cos();
                    let mut w = String::new();
                    if motion != 1 {
                        w.push_str("G1 ");
                        motion = 1;
                    }
                    write!(w, "X{x:.4} Z{z:.4}").expect("fmt");
                    if !f_set {
                        w.push_str(" F300.0000");
                        f_set = true;
                    }
                    lines.push(w);
                }
                // Semicircular turn to the next pass (radius 0.6), clockwise or not by direction.
                let (g, x) = if p.is_multiple_of(2) { (3, 30.0) } else { (2, 0.0) };
                lines.push(format!("G{g} X{x:.4} Y{:.4} I0.0000 J0.6000", y + 1.2));
                motion = g;
            }
            lines.push("G0 Z5.0000".into());
            lines.push("M5".into());
        }
        retract(&mut lines);
        lines.push("M30".into());
        let mut out = String::from("%\n");
        if fanuc {
            out.push_str("O0001 (DEPTHMILL)\n");
        } else {
            out.push_str("(depthmill)\n");
        }
        for (k, l) in lines.iter().enumerate() {
            if fanuc {
                writeln!(out, "N{} {l}", (k + 1) * 10).expect("fmt");
            } else {
                writeln!(out, "{l}").expect("fmt");
            }
        }
        out.push_str("%\n");
        out
    }

    #[test]
    fn cam_programs_agree_with_rs274() {
        agree("cam linuxcnc", CAM_LINUXCNC);
        agree("cam fanuc", CAM_FANUC);
        for fanuc in [false, true] {
            let text = cam_program(fanuc, 12);
            let n = agree(if fanuc { "generated fanuc" } else { "generated linuxcnc" }, &text);
            assert!(find_rs274().is_none() || n > 900, "{n} moves compared");
        }
    }

    #[test]
    fn hand_written_programs_agree_with_rs274() {
        let programs: &[(&str, &str)] = &[
            (
                "modal, comments, N, block delete",
                "N1 G21 G90 G17 G94 (units; mm)\nN2.5 G0 X1 Y2 Z3 ; rapid (x\n\
             /G0 X99\n g1 x 4 y 5 .5 f 200\nX6\nY-7.25 Z-1 (a;b)\nG0 Z5\nM2\n",
            ),
            (
                "incremental and A axis",
                "G90 G0 X0 Y0 Z0 A0\nG91 G1 X1 Y1 F100\nX1 A10\nZ-0.5 A-5\nG90 G0 A90\nG91 A-30\nM2\n",
            ),
            ("inches", "G21 G0 X1 Y1\nG20 G0 X1\nG1 Y0.5 F10\nG2 X1.5 Y1 I0.5 J0 (in)\nG21 G1 X10\nM2\n"),
            (
                "arcs all formats",
                "G21 G90 G0 X0 Y0 Z0\nF500\nG2 X10 Y0 I5 J0\nG3 X0 Y0 R5\nG2 X10 Y0 R-7\n\
             G3 X0 Y0 R7\nG2 X0 Y0 I10 J0 Z-1\nG3 I-2 J0 P3 Z-4\nG90.1 G2 X20 Y0 I10 J0\nG91.1\nG3 X30 Y0 I5 J0\nM2\n",
            ),
            (
                "planes",
                "G0 X1 Y2 Z3\nF100\nG18 G2 X3 Z5 I1 K1\nG3 X1 Z3 R2\nG19 G3 Y4 Z5 J1 K1 X9\nG2 Y2 Z5 R-2\n\
             G17 G2 X11 Y2 I1 J0\nM2\n",
            ),
            (
                "helix with turns and A",
                "G0 X10 Y0 Z0\nG1 F300\nG3 X10 Y0 Z-3 I-10 J0 P3 A30\nG2 X0 Y10 Z-4 I-10 A45\nM2\n",
            ),
            (
                "tools and offsets",
                "T1 M6\nG43\nG0 X1 Y1 Z1\nT3 M6\nG43 H3\nG0 Z1\nG43 H2 G0 Z2\nG49\nG0 Z0\n\
             G55 G0 X0 Y0 Z0 A0\nG1 X5 F50\nG2 X10 Y0 I2.5 J0\nG90.1 G3 X5 Y0 I7.5 J0\nG54 G0 X0\nM2\n",
            ),
            (
                "G53 and G28",
                "G55\nG0 X1 Y1 Z1\nG53 G0 Z0\nG53 G1 X2 Y-3 F100\nG28\nG0 X5 Y5 Z-2\nG28 Z1\nG91 G28 Z0\nG90\n\
             G28 X3 Y4\nT2 M6 G43\nG0 Z-10\nG28\nM30\n",
            ),
            (
                "feed modes, dwell, M52, stops",
                "S1000 M3\nG95 F0.1\nG1 X1\nG94 F100\nG1 X2\nG4 P0.5\nM52 P1\nG1 Y1\n\
             M52 P0\nM52\nM1\nG64 P0.05 Q0.02\nG61\nG61.1\nG1 Y2\nM7\nM8\nM9\nM4 S500\nM5\nM0\nM2\nG0 X77\n",
            ),
            ("percent ends", "\n%\nG0 X1\nG1 X2 F100\n%\nG0 X9 (never read)\n"),
        ];
        for (name, text) in programs {
            agree(name, text);
        }
    }

    #[test]
    fn programs_both_refuse() {
        let mismatch = both_refuse("arc radius", "G0 X0 Y0\nG2 X20.05 Y0 I10 J0 F100\nM2\n");
        assert!(matches!(mismatch, ErrorKind::ArcRadiusMismatch { .. }));
        assert_eq!(both_refuse("zero feed", "G1 X1\nM2\n"), ErrorKind::ZeroFeedRate);
        assert_eq!(both_refuse("G95 zero speed", "G95 F0.1\nG1 X1\nM2\n"), ErrorKind::ZeroSpindleSpeedPerRev);
        assert_eq!(both_refuse("G80 axes", "G80\nX1\nM2\n"), ErrorKind::AxisWordsWithoutMotion);
        assert_eq!(both_refuse("R full circle", "G0 X1\nG2 X1 Y0 R1 F100\nM2\n"), ErrorKind::ArcRFullCircle);
        assert!(matches!(
            both_refuse("R too small", "G2 X2 Y0 R0.9985 F100\nM2\n"),
            ErrorKind::ArcRadiusTooSmall { .. }
        ));
        assert_eq!(both_refuse("G53 G91", "G91 G53 G0 X1\nM2\n"), ErrorKind::G53Incremental);
        assert_eq!(both_refuse("G53 G2", "G53 G2 X1 I1 F100\nM2\n"), ErrorKind::G53NeedsLinearMove);
        assert_eq!(both_refuse("unknown tool", "T7 M6\nM2\n"), ErrorKind::UnknownTool { tool: 7 });
        assert_eq!(both_refuse("no end", "G0 X1\n"), ErrorKind::MissingProgramEnd);
        assert_eq!(both_refuse("no closing %", "%\nG0 X1\n"), ErrorKind::MissingClosingPercent);
        assert_eq!(both_refuse("% inside", "G0 X1\n%\nM2\n"), ErrorKind::MisplacedPercent);
        assert_eq!(
            both_refuse("two motions", "G0 X1 G1 Y1\nM2\n"),
            ErrorKind::ModalGroupConflict {
                group: super::super::lexer::GGroup::Motion.name(),
                other: "G0".into()
            }
        );
        assert_eq!(both_refuse("G4 without P", "G4\nM2\n"), ErrorKind::DwellWithoutP);
        assert!(matches!(
            both_refuse("K in G17", "G2 X2 I1 K1 F100\nM2\n"),
            ErrorKind::ArcOffsetOutOfPlane { .. }
        ));
    }

    #[test]
    fn arc_tolerance_matches_rs274_on_the_boundary() {
        // Accepted by both: within 0.0283 mm, or within 0.1 % up to 2.83 mm.
        for end in ["X200.05 Y0 I100 J0", "X200.02 Y0 I100 J0", "X2.0015 Y0 I1 J0", "X20002.5 Y0 I10000 J0"] {
            agree(end, &format!("G0 X0 Y0\nF100\nG2 {end}\nM2\n"));
        }
        for end in ["X20.05 Y0 I10 J0", "X202.8 Y0 I100 J0", "X2003 Y0 I1000 J0"] {
            let k = both_refuse(end, &format!("G0 X0 Y0\nF100\nG2 {end}\nM2\n"));
            assert!(matches!(k, ErrorKind::ArcRadiusMismatch { .. }), "{end}: {k:?}");
        }
    }
}
