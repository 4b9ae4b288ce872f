//! XYZ text: one point per line, columns separated by any white space or commas.
//!
//! Columns: 3 (`x y z`), 4 (`x y z intensity`), 6 (`x y z nx ny nz`) or 7
//! (`x y z intensity nx ny nz`); the first data line fixes the count for the whole file. Blank
//! lines, lines starting with `#` or `//` and the rest of a line from a `#` (or from a token
//! starting with `//`) are ignored. Coordinates are parsed to `f64`, intensity and normals straight
//! to `f32`. Lines are read one at a time into a reused buffer (at most
//! [`MAX_LINE_LEN`](super::MAX_LINE_LEN) bytes each), so reading allocates only the growing point
//! arrays. Each number is parsed in place by `fast-float2` (`parse_partial`, which also finds where
//! the number ends), and must be followed by a separator, a `#` or the end of the line; a byte-class
//! table skips the separators. Measured on 10^6 lines of `x y z intensity`, `fast-float2` took about
//! 0.6 times as long as `str::from_utf8` + `str::parse` for tokenising and parsing.

use std::io::BufRead;

use crate::PointCloud;

use super::error::{Location, Result};
use super::{
    CloudSink, InputFormat, Lines, ReadLimits, ReadStats, Src, is_space, parse_error, parse_f32_prefix,
    parse_f64_prefix, show_token, too_large,
};

/// Reads an XYZ text cloud from `r`; `name` names the input in errors.
pub fn read_xyz_from<R: BufRead>(r: R, name: &str, limits: &ReadLimits) -> Result<(PointCloud, ReadStats)> {
    read_xyz_src(&mut Src::new(r, limits.max_bytes), name, limits, None)
}

/// Byte classes of XYZ text: part of a token, a column separator (white space or comma), or the
/// start of a comment (`#`, which ends the line's data).
const DATA: u8 = 0;
const SEP: u8 = 1;
const END: u8 = 2;
const CLASS: [u8; 256] = {
    let mut t = [DATA; 256];
    let mut b = 0;
    while b < 256 {
        if is_space(b as u8) || b as u8 == b',' {
            t[b] = SEP;
        }
        b += 1;
    }
    t[b'#' as usize] = END;
    t
};

fn bad_token(name: &str, line: u64, column: usize, tok: &[u8]) -> super::error::FormatError {
    parse_error(
        name,
        Location::Line(line),
        format!("column {}: cannot parse {} as a number", column + 1, show_token(tok)),
    )
}

pub(crate) fn read_xyz_src<R: BufRead>(
    src: &mut Src<R>,
    name: &str,
    limits: &ReadLimits,
    keep: Option<usize>,
) -> Result<(PointCloud, ReadStats)> {
    let mut lines = Lines::new(0);
    // (column count, line that fixed it)
    let mut layout: Option<(usize, u64)> = None;
    let mut sink = CloudSink::new(false, false, false, false, 0);
    while lines.next(src, name)? {
        let line = lines.line;
        let text = lines.buf.as_slice();
        let mut cols = 0usize;
        let mut xyz = [0f64; 3];
        let mut rest = [0f32; 4];
        let mut i = 0;
        'tokens: loop {
            while let Some(&b) = text.get(i) {
                match CLASS[b as usize] {
                    SEP => i += 1,
                    END => break 'tokens,
                    _ => break,
                }
            }
            if i >= text.len() || text[i..].starts_with(b"//") {
                break;
            }
            // Parse straight from the line (the parser finds the number's end), then check that
            // a separator, a comment or the line's end follows.
            let parsed = if cols < 3 {
                parse_f64_prefix(&text[i..]).map(|(v, n)| {
                    xyz[cols] = v;
                    n
                })
            } else if cols < 7 {
                parse_f32_prefix(&text[i..]).map(|(v, n)| {
                    rest[cols - 3] = v;
                    n
                })
            } else {
                Some(0)
            };
            let token_end = |from: usize| {
                text[from..].iter().position(|&b| CLASS[b as usize] != DATA).map_or(text.len(), |k| from + k)
            };
            match parsed {
                Some(n) if n > 0 && text.get(i + n).is_none_or(|&b| CLASS[b as usize] != DATA) => i += n,
                Some(_) if cols >= 7 => i = token_end(i),
                _ => return Err(bad_token(name, line, cols, &text[i..token_end(i)])),
            }
            cols += 1;
        }
        if cols == 0 {
            continue;
        }
        let ncols = match layout {
            Some((n, first)) if n != cols => {
                return Err(parse_error(
                    name,
                    Location::Line(line),
                    format!("found {cols} columns but the first data line (line {first}) has {n}"),
                ));
            }
            Some((n, _)) => n,
            None => {
                if !matches!(cols, 3 | 4 | 6 | 7) {
                    return Err(parse_error(
                        name,
                        Location::Line(line),
                        format!(
                            "found {cols} columns; expected 3 (x y z), 4 (x y z intensity), \
                             6 (x y z nx ny nz) or 7 (x y z intensity nx ny nz)"
                        ),
                    ));
                }
                layout = Some((cols, line));
                sink = CloudSink::new(cols == 4 || cols == 7, cols >= 6, false, false, 1024).sampled(keep);
                cols
            }
        };
        match ncols {
            3 => sink.push(xyz, 0.0, [0.0; 3], 0),
            4 => sink.push(xyz, rest[0], [0.0; 3], 0),
            6 => sink.push(xyz, 0.0, [rest[0], rest[1], rest[2]], 0),
            _ => sink.push(xyz, rest[0], [rest[1], rest[2], rest[3]], 0),
        }
        if sink.len() > limits.max_points {
            return Err(too_large(name, "points", sink.len(), limits.max_points));
        }
    }
    let mut stats = ReadStats::new(InputFormat::Xyz);
    stats.bytes = src.pos();
    stats.points = sink.len();
    stats.dropped_non_finite = sink.dropped;
    Ok((sink.into_cloud().0, stats))
}

#[cfg(test)]
mod tests {
    use std::io::Cursor;

    use nalgebra::{Point3, Vector3};
    use proptest::prelude::*;

    use super::*;

    fn read(text: &str) -> Result<(PointCloud, ReadStats)> {
        read_xyz_from(Cursor::new(text.as_bytes().to_vec()), "scan.xyz", &ReadLimits::default())
    }

    fn err(text: &str) -> String {
        read(text).expect_err("malformed").to_string()
    }

    #[test]
    fn three_columns_with_comments_commas_tabs() {
        let text = "# exported by something\n// another comment\n\n1 2 3\n4,5,6 # trailing\n\t7\t8 , 9\r\n  -1e1 .5 +2.25 // note\n";
        let (cloud, stats) = read(text).expect("read");
        assert_eq!(
            cloud.points,
            vec![
                Point3::new(1.0, 2.0, 3.0),
                Point3::new(4.0, 5.0, 6.0),
                Point3::new(7.0, 8.0, 9.0),
                Point3::new(-10.0, 0.5, 2.25)
            ]
        );
        assert_eq!((cloud.intensity, cloud.normals), (None, None));
        assert_eq!((stats.points, stats.dropped_non_finite, stats.format), (4, 0, InputFormat::Xyz));
        assert_eq!(stats.bytes, text.len() as u64);
    }

    #[test]
    fn four_six_seven_columns() {
        let (c, _) = read("1 2 3 0.5\n4 5 6 0.25\n").expect("4");
        assert_eq!(c.intensity, Some(vec![0.5, 0.25]));
        assert_eq!(c.normals, None);
        let (c, _) = read("1 2 3 0 0 1\n").expect("6");
        assert_eq!((c.intensity, c.normals), (None, Some(vec![Vector3::new(0.0, 0.0, 1.0)])));
        let (c, _) = read("1,2,3,7.5,0,1,0\n").expect("7");
        assert_eq!(c.points, vec![Point3::new(1.0, 2.0, 3.0)]);
        assert_eq!((c.intensity, c.normals), (Some(vec![7.5]), Some(vec![Vector3::new(0.0, 1.0, 0.0)])));
        // Intensity and normals parse straight to f32 (one rounding).
        let (c, _) = read("0 0 0 0.1 0.3 0.6 0.7\n").expect("f32");
        assert_eq!(c.intensity, Some(vec![0.1f32]));
        assert_eq!(c.normals, Some(vec![Vector3::new(0.3f32, 0.6, 0.7)]));
    }

    #[test]
    fn non_finite_points_dropped_and_counted() {
        let (c, s) =
            read("1 2 3 1\nnan 0 0 1\n0 inf 0 1\n4 5 6 NaN\n7 8 9 2\n0 0 -infinity 1\n").expect("read");
        assert_eq!(c.points, vec![Point3::new(1.0, 2.0, 3.0), Point3::new(7.0, 8.0, 9.0)]);
        assert_eq!(c.intensity, Some(vec![1.0, 2.0]));
        assert_eq!((s.points, s.dropped_non_finite), (2, 4));
        // A non-finite normal is "unknown": zero, and the point stays.
        let (c, s) = read("1 2 3 nan 0 1\n").expect("normal");
        assert_eq!((c.normals, s.dropped_non_finite), (Some(vec![Vector3::zeros()]), 0));
    }

    #[test]
    fn empty_and_comment_only_inputs_give_an_empty_cloud() {
        for text in ["", "\n\n", "# nothing\n// here\n"] {
            let (c, s) = read(text).expect("empty");
            assert!(c.is_empty() && s.points == 0);
        }
    }

    #[test]
    fn malformed_inputs_name_file_line_and_problem() {
        assert_eq!(
            err("1 2 3\n4 5 6\n# c\n7 8 9 10\n"),
            "scan.xyz: line 4: found 4 columns but the first data line (line 1) has 3"
        );
        assert_eq!(
            err("\n1 2 3 4\n1 2 3\n"),
            "scan.xyz: line 3: found 3 columns but the first data line (line 2) has 4"
        );
        assert_eq!(err("1 2 3\n1 2 abc\n"), "scan.xyz: line 2: column 3: cannot parse \"abc\" as a number");
        assert_eq!(err("x y z\n"), "scan.xyz: line 1: column 1: cannot parse \"x\" as a number");
        let long = format!("1 2 {}\n", "9".repeat(30) + &"q".repeat(30));
        assert!(err(&long).starts_with("scan.xyz: line 1: column 3: cannot parse \"999"));
        assert!(err(&long).ends_with("…\" as a number"));
        assert!(err("1 2 3 4 5\n").starts_with("scan.xyz: line 1: found 5 columns; expected 3 (x y z)"));
        assert!(err("1 2\n").starts_with("scan.xyz: line 1: found 2 columns;"));
        assert!(err("1 2 3 4 5 6 7 8\n").starts_with("scan.xyz: line 1: found 8 columns;"));
        assert_eq!(err("1 2 3\n1;2;3\n"), "scan.xyz: line 2: column 1: cannot parse \"1;2;3\" as a number");
    }

    #[test]
    fn limits() {
        let text = "1 2 3\n4 5 6\n7 8 9\n";
        let tight = ReadLimits { max_points: 2, ..Default::default() };
        let e = read_xyz_from(Cursor::new(text), "scan.xyz", &tight).expect_err("points");
        assert_eq!(e.to_string(), "scan.xyz: points 3 exceeds the limit of 2");
        // Dropped points do not count against the limit.
        let with_nan = "1 2 3\nnan 0 0\n4 5 6\n";
        assert!(read_xyz_from(Cursor::new(with_nan), "scan.xyz", &tight).is_ok());
        let tight = ReadLimits { max_bytes: 10, ..Default::default() };
        let e = read_xyz_from(Cursor::new(text), "scan.xyz", &tight).expect_err("bytes");
        assert_eq!(e.to_string(), "scan.xyz: bytes 11 exceeds the limit of 10");
    }

    /// Points, the extra columns of each, and the count of dropped points.
    type Parsed = (Vec<[f64; 3]>, Vec<Vec<f32>>, u64);

    /// The slow reference: `str` splitting and `str::parse`, on the same rules.
    fn reference(text: &str) -> Option<Parsed> {
        let mut pts = Vec::new();
        let mut extra = Vec::new();
        let mut dropped = 0;
        let mut ncols = None;
        for line in text.lines() {
            let line = line.split('#').next().unwrap_or("");
            let mut toks: Vec<&str> = line
                .split(|c: char| c == ',' || " \t\r\x0b\x0c".contains(c))
                .filter(|t| !t.is_empty())
                .collect();
            if let Some(i) = toks.iter().position(|t| t.starts_with("//")) {
                toks.truncate(i);
            }
            if toks.is_empty() {
                continue;
            }
            if *ncols.get_or_insert(toks.len()) != toks.len() || ![3, 4, 6, 7].contains(&toks.len()) {
                return None;
            }
            let p: Vec<f64> = toks[..3].iter().map(|t| t.parse().ok()).collect::<Option<_>>()?;
            let e: Vec<f32> = toks[3..].iter().map(|t| t.parse().ok()).collect::<Option<_>>()?;
            let intensity_bad = matches!(toks.len(), 4 | 7) && !e[0].is_finite();
            if p.iter().any(|c| !c.is_finite()) || intensity_bad {
                dropped += 1;
                continue;
            }
            pts.push([p[0], p[1], p[2]]);
            extra.push(e);
        }
        Some((pts, extra, dropped))
    }

    fn value() -> impl Strategy<Value = String> {
        prop_oneof![
            8 => any::<f32>().prop_map(|v| v.to_string()),
            8 => (-1e6f64..1e6).prop_map(|v| format!("{v:.5}")),
            1 => Just("nan".to_string()),
            1 => Just("-inf".to_string()),
            1 => (1e-30f64..1e30).prop_map(|v| format!("{v:e}")),
        ]
    }

    fn line(cols: usize) -> impl Strategy<Value = String> {
        (
            prop::collection::vec(value(), cols),
            prop::collection::vec(
                prop_oneof![Just(" "), Just("\t"), Just(", "), Just(","), Just("  ")],
                cols,
            ),
            prop_oneof![Just(""), Just(" # c"), Just(" // d"), Just("\r")],
        )
            .prop_map(|(vals, seps, tail)| {
                let mut s = String::new();
                for (i, v) in vals.iter().enumerate() {
                    if i > 0 {
                        s.push_str(seps[i]);
                    }
                    s.push_str(v);
                }
                s + tail
            })
    }

    fn file() -> impl Strategy<Value = String> {
        prop_oneof![Just(3usize), Just(4), Just(6), Just(7)].prop_flat_map(|cols| {
            prop::collection::vec(
                prop_oneof![6 => line(cols), 1 => Just("# comment".to_string()), 1 => Just(String::new())],
                0..40,
            )
            .prop_map(|lines| lines.join("\n"))
        })
    }

    proptest! {
        #[test]
        fn matches_the_reference(text in file()) {
            let (cloud, stats) = read(&text).expect("generated files are valid");
            let (pts, extra, dropped) = reference(&text).expect("reference");
            let got: Vec<[f32; 3]> = cloud.points.iter().map(|p| [p.x, p.y, p.z]).collect();
            let want: Vec<[f32; 3]> = pts.iter().map(|p| p.map(|v| v as f32)).collect();
            prop_assert_eq!(got, want);
            prop_assert_eq!(stats.dropped_non_finite, dropped);
            for (i, e) in extra.iter().enumerate() {
                match e.len() {
                    1 => prop_assert_eq!(cloud.intensity.as_ref().map(|v| v[i]), Some(e[0])),
                    3 | 4 => {
                        let n = cloud.normals.as_ref().map(|v| v[i]).expect("normals");
                        let want = &e[e.len() - 3..];
                        for k in 0..3 {
                            let w = if want.iter().all(|c| c.is_finite()) { want[k] } else { 0.0 };
                            prop_assert_eq!(n[k], w);
                        }
                        if e.len() == 4 {
                            prop_assert_eq!(cloud.intensity.as_ref().map(|v| v[i]), Some(e[0]));
                        }
                    }
                    _ => {}
                }
            }
        }

        #[test]
        fn random_text_never_panics(bytes in prop::collection::vec(any::<u8>(), 0..300)) {
            let _ = read_xyz_from(Cursor::new(bytes), "x", &ReadLimits::default());
        }
    }
}
