//! The table controller's ASCII protocol (DESIGN §6, seed 002 §2.1.2): command decoding from a byte
//! stream, reply encoding, and the client side (command encoding, reply decoding).
//!
//! Pure: no IO. The server feeds received bytes to a [`Decoder`]; the client encodes with
//! [`Command::encode`] and decodes reply lines with [`parse_reply_line`] and the binary position
//! with [`decode_counts`].
//!
//! # Framing
//! - A text command is one line: `<letter>[spaces][number]` ended by `\r\n`, `\n` or `\r` alone.
//!   Both `\r` and `\n` end a line, so `\r\n` is a line and then a blank line; blank lines are
//!   ignored and get no reply. Leading and trailing spaces and tabs are ignored.
//! - Letters are upper case (`H P R S A`); the seed defines commands as one character `A`..`Z`.
//! - A line is at most [`MAX_LINE_LEN`] (64) bytes without its terminator. The 65th byte makes the
//!   decoder report [`ParseError::LineTooLong`] at once and drop the rest of that line, so exactly one
//!   `ERR` answers an over-long line.
//! - The binary read `h` (0x68) is recognised **only at the start of a line** (nothing of a text
//!   line buffered). It is answered at once, without waiting for a line end; a `\r`/`\n` after it is
//!   just a blank line. Inside a text line an `h` is an ordinary (invalid) character.
//! - Numbers: `[+-]? digits [. digits?]` or `[+-]? . digits`, decimal only. Exponents, `inf`, `nan`,
//!   hex and empty numbers are rejected, so every accepted number is finite.
//!
//! # Replies
//! `OK\r\n`; `H nn.nnnn\r\n` (degrees, 4 decimals, no padding: `H 5.5000`; an odd count loses its
//! last digit, 0.03125 → `0.0312`, so use `h` for exact counts); `ERR <reason>\r\n` (printable
//! ASCII); for `h`, two bytes holding the count 0..11519, **big-endian** (most significant byte
//! first; the seed only says "16 bits", this is our choice), no line end.

use std::fmt::Write as _;

/// Header the simulated controller prints at power-up (each time a client connects), without its
/// `\r\n`.
pub const HEADER: &str = "DEPTHMILL ROTARY TABLE SIM v1 11520 CPR";

/// Longest accepted command line in bytes, excluding its terminator.
pub const MAX_LINE_LEN: usize = 64;

/// The one-byte binary position read.
pub const BINARY_READ: u8 = b'h';

/// Longest reply line the client accepts (bytes before `\n`), so a babbling peer cannot grow memory.
pub const MAX_REPLY_LEN: usize = 128;

/// One decoded command.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Command {
    /// `H`: position in degrees.
    ReadDegrees,
    /// `h` (binary): position in encoder counts.
    ReadCounts,
    /// `P deg`: absolute move the shortest way.
    MoveAbsolute {
        /// Target angle in degrees (any finite value; the model checks its range).
        deg: f64,
    },
    /// `R deg`: move relative to the last target.
    MoveRelative {
        /// Increment in degrees, positive counter-clockwise seen from above.
        deg: f64,
    },
    /// `S deg_s`: maximum speed for the next moves.
    SetSpeed {
        /// Degrees per second.
        deg_s: f64,
    },
    /// `A deg_s2`: acceleration for the next moves.
    SetAccel {
        /// Degrees per second squared.
        deg_s2: f64,
    },
}

impl Command {
    /// The bytes a master sends for this command: `h` alone for [`Command::ReadCounts`], otherwise
    /// a line such as `P 90.0000\r\n` (numbers with 4 decimals, as in the protocol table).
    pub fn encode(&self) -> Vec<u8> {
        match self {
            Command::ReadCounts => vec![BINARY_READ],
            Command::ReadDegrees => b"H\r\n".to_vec(),
            Command::MoveAbsolute { deg } => format!("P {}\r\n", fmt4(*deg)).into_bytes(),
            Command::MoveRelative { deg } => format!("R {}\r\n", fmt4(*deg)).into_bytes(),
            Command::SetSpeed { deg_s } => format!("S {}\r\n", fmt4(*deg_s)).into_bytes(),
            Command::SetAccel { deg_s2 } => format!("A {}\r\n", fmt4(*deg_s2)).into_bytes(),
        }
    }

    /// Short printable form for error messages (`P 90.0000`, `h`).
    pub fn describe(&self) -> String {
        let bytes = self.encode();
        String::from_utf8_lossy(&bytes).trim_end().to_string()
    }
}

/// The value a controller parses from `v` as [`Command::encode`] sends it (rounded to 4 decimals);
/// `None` when `v` is not finite or its text would make the line longer than [`MAX_LINE_LEN`].
pub fn wire_value(v: f64) -> Option<f64> {
    let text = fmt4(v);
    if text.len() + 2 > MAX_LINE_LEN { None } else { parse_number(&text) }
}

/// Formats with 4 decimals and never prints `-0.0000`.
fn fmt4(v: f64) -> String {
    let s = format!("{v:.4}");
    if s == "-0.0000" { "0.0000".to_string() } else { s }
}

/// One reply of the controller.
#[derive(Debug, Clone, PartialEq)]
pub enum Reply {
    /// `H nn.nnnn\r\n`.
    Degrees(f64),
    /// Two bytes, big-endian.
    Counts(u16),
    /// `OK\r\n`.
    Ok,
    /// `ERR <reason>\r\n`.
    Error(String),
}

impl Reply {
    /// The exact bytes on the wire. Error reasons are reduced to printable ASCII (others become `?`)
    /// and cut to 100 characters.
    pub fn encode(&self) -> Vec<u8> {
        match self {
            Reply::Degrees(deg) => format!("H {}\r\n", fmt4(*deg)).into_bytes(),
            Reply::Counts(c) => c.to_be_bytes().to_vec(),
            Reply::Ok => b"OK\r\n".to_vec(),
            Reply::Error(reason) => {
                let clean: String = reason
                    .chars()
                    .take(100)
                    .map(|c| if c.is_ascii_graphic() || c == ' ' { c } else { '?' })
                    .collect();
                format!("ERR {clean}\r\n").into_bytes()
            }
        }
    }
}

/// Why a command line was refused; its `Display` is the reason after `ERR `.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ParseError {
    /// More than [`MAX_LINE_LEN`] bytes before the line end.
    #[error("line longer than {limit} bytes")]
    LineTooLong {
        /// The limit.
        limit: usize,
    },
    /// A byte outside printable ASCII (tab allowed) in a text line.
    #[error("bad byte 0x{byte:02x} at offset {offset}")]
    BadByte {
        /// The byte.
        byte: u8,
        /// Its offset in the line.
        offset: usize,
    },
    /// The first character is not a known command letter.
    #[error("unknown command '{found}'")]
    UnknownCommand {
        /// The offending character (printable ASCII).
        found: char,
    },
    /// `H` followed by something.
    #[error("{command} takes no argument, got '{text}'")]
    UnexpectedArgument {
        /// The command letter.
        command: char,
        /// What followed it.
        text: String,
    },
    /// `P`, `R`, `S` or `A` without a number.
    #[error("{command} needs a number")]
    MissingArgument {
        /// The command letter.
        command: char,
    },
    /// The argument is not a plain decimal number.
    #[error("malformed number '{text}' for {command}")]
    BadNumber {
        /// The command letter.
        command: char,
        /// The text that failed.
        text: String,
    },
}

/// Parses a plain decimal number (`[+-]? digits [. digits?] | [+-]? . digits`); `None` otherwise.
/// The result is always finite (at most 64 digits fit a line, far below `f64::MAX`).
pub fn parse_number(text: &str) -> Option<f64> {
    let b = text.as_bytes();
    let mut i = 0;
    if i < b.len() && (b[i] == b'+' || b[i] == b'-') {
        i += 1;
    }
    let int_start = i;
    while i < b.len() && b[i].is_ascii_digit() {
        i += 1;
    }
    let int_digits = i - int_start;
    let mut frac_digits = 0;
    if i < b.len() && b[i] == b'.' {
        i += 1;
        let frac_start = i;
        while i < b.len() && b[i].is_ascii_digit() {
            i += 1;
        }
        frac_digits = i - frac_start;
    }
    if i != b.len() || int_digits + frac_digits == 0 || text.len() > MAX_REPLY_LEN {
        return None;
    }
    text.parse::<f64>().ok().filter(|v| v.is_finite())
}

/// Parses one text line (terminator removed). `Ok(None)` for a blank line.
pub fn parse_line(line: &[u8]) -> Result<Option<Command>, ParseError> {
    if line.len() > MAX_LINE_LEN {
        return Err(ParseError::LineTooLong { limit: MAX_LINE_LEN });
    }
    if let Some((offset, &byte)) =
        line.iter().enumerate().find(|&(_, &b)| !(b == b'\t' || (0x20..0x7f).contains(&b)))
    {
        return Err(ParseError::BadByte { byte, offset });
    }
    // Printable ASCII only from here, so `from_utf8` cannot fail; stay total anyway.
    let text = String::from_utf8_lossy(line);
    let text = text.trim_matches([' ', '\t']);
    let mut chars = text.chars();
    let Some(letter) = chars.next() else { return Ok(None) };
    let rest = chars.as_str().trim_start_matches([' ', '\t']);
    let number = |ctor: fn(f64) -> Command| -> Result<Option<Command>, ParseError> {
        if rest.is_empty() {
            return Err(ParseError::MissingArgument { command: letter });
        }
        parse_number(rest)
            .map(|v| Some(ctor(v)))
            .ok_or_else(|| ParseError::BadNumber { command: letter, text: rest.to_string() })
    };
    match letter {
        'H' if rest.is_empty() => Ok(Some(Command::ReadDegrees)),
        'H' => Err(ParseError::UnexpectedArgument { command: 'H', text: rest.to_string() }),
        'P' => number(|deg| Command::MoveAbsolute { deg }),
        'R' => number(|deg| Command::MoveRelative { deg }),
        'S' => number(|deg_s| Command::SetSpeed { deg_s }),
        'A' => number(|deg_s2| Command::SetAccel { deg_s2 }),
        other => Err(ParseError::UnknownCommand { found: other }),
    }
}

/// Incremental command decoder for the controller side of the line; see the module doc for the
/// framing rules. Feed every received byte to [`Decoder::push`] in order.
#[derive(Debug, Default, Clone)]
pub struct Decoder {
    line: Vec<u8>,
    /// Dropping the rest of an over-long line until its terminator.
    discarding: bool,
}

impl Decoder {
    /// A decoder at the start of a line.
    pub fn new() -> Self {
        Self::default()
    }

    /// Consumes one byte; returns a command or a parse error when one is complete.
    pub fn push(&mut self, byte: u8) -> Option<Result<Command, ParseError>> {
        if byte == b'\r' || byte == b'\n' {
            if std::mem::take(&mut self.discarding) {
                self.line.clear();
                return None;
            }
            let line = std::mem::take(&mut self.line);
            return parse_line(&line).transpose();
        }
        if self.discarding {
            return None;
        }
        if self.line.is_empty() && byte == BINARY_READ {
            return Some(Ok(Command::ReadCounts));
        }
        if self.line.len() == MAX_LINE_LEN {
            self.line.clear();
            self.discarding = true;
            return Some(Err(ParseError::LineTooLong { limit: MAX_LINE_LEN }));
        }
        self.line.push(byte);
        None
    }

    /// Feeds a slice and collects every completed command or error, in order.
    pub fn feed(&mut self, bytes: &[u8]) -> Vec<Result<Command, ParseError>> {
        bytes.iter().filter_map(|&b| self.push(b)).collect()
    }
}

/// Why a reply line could not be understood (client side).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ReplyParseError {
    /// Not `OK`, `ERR ...` or `H <number>`.
    #[error("unexpected reply '{text}'")]
    Unexpected {
        /// The line, made printable.
        text: String,
    },
}

/// Parses one reply line (terminator `\n` and an optional `\r` before it already removed) into
/// [`Reply::Ok`], [`Reply::Error`] or [`Reply::Degrees`].
pub fn parse_reply_line(line: &[u8]) -> Result<Reply, ReplyParseError> {
    let printable: String =
        line.iter().map(|&b| if (0x20..0x7f).contains(&b) { b as char } else { '?' }).collect();
    let unexpected = || ReplyParseError::Unexpected { text: printable.clone() };
    if line.len() > MAX_REPLY_LEN || printable.as_bytes() != line {
        return Err(unexpected());
    }
    let text = printable.trim_end_matches([' ', '\t']);
    if text == "OK" {
        return Ok(Reply::Ok);
    }
    if let Some(reason) = text.strip_prefix("ERR")
        && (reason.is_empty() || reason.starts_with(' '))
    {
        return Ok(Reply::Error(reason.trim_start().to_string()));
    }
    if let Some(rest) = text.strip_prefix('H') {
        return parse_number(rest.trim_start_matches([' ', '\t'])).map(Reply::Degrees).ok_or_else(unexpected);
    }
    Err(unexpected())
}

/// Decodes the 2-byte answer to `h` (big-endian).
pub fn decode_counts(bytes: [u8; 2]) -> u16 {
    u16::from_be_bytes(bytes)
}

/// Renders bytes for logs and error messages: printable ASCII as is, others as `\xNN`.
pub fn escape_bytes(bytes: &[u8]) -> String {
    let mut s = String::with_capacity(bytes.len());
    for &b in bytes {
        match b {
            b'\r' => s.push_str("\\r"),
            b'\n' => s.push_str("\\n"),
            0x20..0x7f => s.push(b as char),
            _ => {
                let _ = write!(s, "\\x{b:02x}");
            }
        }
    }
    s
}

#[cfg(test)]
#[allow(clippy::unwrap_used)] // tests may unwrap
mod tests {
    use super::*;

    fn decode(bytes: &[u8]) -> Vec<Result<Command, ParseError>> {
        Decoder::new().feed(bytes)
    }

    #[test]
    fn every_command_form_decodes() {
        assert_eq!(decode(b"H\r\n"), vec![Ok(Command::ReadDegrees)]);
        assert_eq!(decode(b"H\n"), vec![Ok(Command::ReadDegrees)]);
        assert_eq!(decode(b"h"), vec![Ok(Command::ReadCounts)]);
        assert_eq!(decode(b"P 90.0000\r\n"), vec![Ok(Command::MoveAbsolute { deg: 90.0 })]);
        assert_eq!(decode(b"P90\r\n"), vec![Ok(Command::MoveAbsolute { deg: 90.0 })]);
        assert_eq!(
            decode(b"R10\r\nR5.5\r\n"),
            vec![Ok(Command::MoveRelative { deg: 10.0 }), Ok(Command::MoveRelative { deg: 5.5 })]
        );
        assert_eq!(decode(b"R -12.25\n"), vec![Ok(Command::MoveRelative { deg: -12.25 })]);
        assert_eq!(decode(b"S 30\r\n"), vec![Ok(Command::SetSpeed { deg_s: 30.0 })]);
        assert_eq!(decode(b"A\t60.5 \r\n"), vec![Ok(Command::SetAccel { deg_s2: 60.5 })]);
        assert_eq!(decode(b"P .5\r\n"), vec![Ok(Command::MoveAbsolute { deg: 0.5 })]);
        assert_eq!(decode(b"P 7.\r\n"), vec![Ok(Command::MoveAbsolute { deg: 7.0 })]);
        assert_eq!(decode(b"P +7\r\n"), vec![Ok(Command::MoveAbsolute { deg: 7.0 })]);
        // A lone CR ends a line too; the LF after it is a blank line.
        assert_eq!(decode(b"H\rH\r"), vec![Ok(Command::ReadDegrees), Ok(Command::ReadDegrees)]);
        // Blank lines get no reply.
        assert_eq!(decode(b"\r\n\n  \r\n"), vec![]);
    }

    #[test]
    fn binary_h_only_at_line_start() {
        // Between text commands, at a line start: binary.
        assert_eq!(
            decode(b"S 10\r\nhH\r\n"),
            vec![Ok(Command::SetSpeed { deg_s: 10.0 }), Ok(Command::ReadCounts), Ok(Command::ReadDegrees)]
        );
        assert_eq!(decode(b"hhh"), vec![Ok(Command::ReadCounts); 3]);
        // Inside a text line it is just a (bad) character.
        assert_eq!(decode(b"Ph\r\n"), vec![Err(ParseError::BadNumber { command: 'P', text: "h".into() })]);
        assert_eq!(decode(b" h\r\n"), vec![Err(ParseError::UnknownCommand { found: 'h' })]);
        // Answered at once, before any line end arrives.
        let mut d = Decoder::new();
        assert_eq!(d.push(b'h'), Some(Ok(Command::ReadCounts)));
        // `h` right after the CR of a CRLF: the LF is then a blank line.
        assert_eq!(decode(b"H\rh\n"), vec![Ok(Command::ReadDegrees), Ok(Command::ReadCounts)]);
    }

    #[test]
    fn malformed_lines_are_errors_and_decoding_goes_on() {
        let cases: &[(&[u8], ParseError)] = &[
            (b"P abc\r\n", ParseError::BadNumber { command: 'P', text: "abc".into() }),
            (b"P\r\n", ParseError::MissingArgument { command: 'P' }),
            (b"S \r\n", ParseError::MissingArgument { command: 'S' }),
            (b"P inf\r\n", ParseError::BadNumber { command: 'P', text: "inf".into() }),
            (b"P NaN\r\n", ParseError::BadNumber { command: 'P', text: "NaN".into() }),
            (b"P 1e3\r\n", ParseError::BadNumber { command: 'P', text: "1e3".into() }),
            (b"P 0x10\r\n", ParseError::BadNumber { command: 'P', text: "0x10".into() }),
            (b"P 1.2.3\r\n", ParseError::BadNumber { command: 'P', text: "1.2.3".into() }),
            (b"P -\r\n", ParseError::BadNumber { command: 'P', text: "-".into() }),
            (b"P 1 2\r\n", ParseError::BadNumber { command: 'P', text: "1 2".into() }),
            (b"H 5\r\n", ParseError::UnexpectedArgument { command: 'H', text: "5".into() }),
            (b"X\r\n", ParseError::UnknownCommand { found: 'X' }),
            (b"p 10\r\n", ParseError::UnknownCommand { found: 'p' }),
            (b"P \x0710\r\n", ParseError::BadByte { byte: 0x07, offset: 2 }),
            (b"P 1\xc3\xa9\r\n", ParseError::BadByte { byte: 0xc3, offset: 3 }),
        ];
        for (bytes, err) in cases {
            let mut d = Decoder::new();
            let mut all = bytes.to_vec();
            all.extend_from_slice(b"H\r\n");
            assert_eq!(
                d.feed(&all),
                vec![Err(err.clone()), Ok(Command::ReadDegrees)],
                "{}",
                escape_bytes(bytes)
            );
        }
    }

    #[test]
    fn line_length_limit() {
        // 64 bytes is fine.
        let mut ok = b"P 1.".to_vec();
        ok.resize(MAX_LINE_LEN, b'0');
        ok.extend_from_slice(b"\r\n");
        assert_eq!(decode(&ok), vec![Ok(Command::MoveAbsolute { deg: 1.0 })]);
        // 65 bytes: one error, reported when the 65th byte arrives, the rest dropped.
        let mut long = b"P 1.".to_vec();
        long.resize(200, b'0');
        let mut d = Decoder::new();
        let first = d.feed(&long[..MAX_LINE_LEN + 1]);
        assert_eq!(first, vec![Err(ParseError::LineTooLong { limit: MAX_LINE_LEN })]);
        assert_eq!(d.feed(&long[MAX_LINE_LEN + 1..]), vec![]);
        // An `h` inside the dropped tail is not a binary read.
        assert_eq!(d.feed(b"hh"), vec![]);
        assert_eq!(d.feed(b"\r\nH\r\n"), vec![Ok(Command::ReadDegrees)]);
        assert_eq!(
            parse_line(&[b'H'; MAX_LINE_LEN + 1]),
            Err(ParseError::LineTooLong { limit: MAX_LINE_LEN })
        );
    }

    #[test]
    fn replies_are_byte_exact() {
        assert_eq!(Reply::Ok.encode(), b"OK\r\n");
        assert_eq!(Reply::Degrees(90.0).encode(), b"H 90.0000\r\n");
        assert_eq!(Reply::Degrees(5.5).encode(), b"H 5.5000\r\n");
        assert_eq!(Reply::Degrees(359.96875).encode(), b"H 359.9688\r\n");
        assert_eq!(Reply::Degrees(0.03125).encode(), b"H 0.0312\r\n");
        assert_eq!(Reply::Degrees(-0.0).encode(), b"H 0.0000\r\n");
        assert_eq!(Reply::Counts(0).encode(), [0u8, 0]);
        assert_eq!(Reply::Counts(11519).encode(), [0x2c, 0xff]);
        assert_eq!(Reply::Counts(258).encode(), [1, 2]);
        assert_eq!(
            Reply::Error("malformed number 'abc' for P".into()).encode(),
            b"ERR malformed number 'abc' for P\r\n"
        );
        assert_eq!(Reply::Error("a\r\nb\u{b0}".into()).encode(), b"ERR a??b?\r\n");
        let parse_err = ParseError::BadNumber { command: 'P', text: "abc".into() };
        assert_eq!(Reply::Error(parse_err.to_string()).encode(), b"ERR malformed number 'abc' for P\r\n");
    }

    #[test]
    fn commands_encode_byte_exact_and_round_trip() {
        let cases: &[(Command, &[u8])] = &[
            (Command::ReadDegrees, b"H\r\n"),
            (Command::ReadCounts, b"h"),
            (Command::MoveAbsolute { deg: 90.0 }, b"P 90.0000\r\n"),
            (Command::MoveRelative { deg: -5.5 }, b"R -5.5000\r\n"),
            (Command::MoveRelative { deg: -0.00001 }, b"R 0.0000\r\n"),
            (Command::SetSpeed { deg_s: 30.0 }, b"S 30.0000\r\n"),
            (Command::SetAccel { deg_s2: 60.0 }, b"A 60.0000\r\n"),
        ];
        for (cmd, bytes) in cases {
            assert_eq!(cmd.encode(), *bytes, "{cmd:?}");
            let back = decode(bytes);
            assert_eq!(back.len(), 1);
        }
        assert_eq!(Command::MoveAbsolute { deg: 12.5 }.describe(), "P 12.5000");
        assert_eq!(Command::ReadCounts.describe(), "h");
        assert_eq!(wire_value(12.345678), Some(12.3457));
        assert_eq!(wire_value(-0.00001), Some(0.0));
        assert_eq!(wire_value(f64::NAN), None);
        assert_eq!(wire_value(1e80), None);
    }

    #[test]
    fn reply_lines_parse() {
        assert_eq!(parse_reply_line(b"OK"), Ok(Reply::Ok));
        assert_eq!(parse_reply_line(b"H 90.0000"), Ok(Reply::Degrees(90.0)));
        assert_eq!(parse_reply_line(b"H12.5"), Ok(Reply::Degrees(12.5)));
        assert_eq!(parse_reply_line(b"ERR bad thing"), Ok(Reply::Error("bad thing".into())));
        assert_eq!(parse_reply_line(b"ERR"), Ok(Reply::Error(String::new())));
        for bad in [&b"OKAY"[..], b"H", b"H abc", b"ERRx", b"", b"H 1e5", b"\xff"] {
            assert!(parse_reply_line(bad).is_err(), "{}", escape_bytes(bad));
        }
        assert_eq!(decode_counts([0x2c, 0xff]), 11519);
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig {
            failure_persistence: None,
            ..proptest::prelude::ProptestConfig::default()
        })]
        #[test]
        fn decoder_never_panics_and_recovers(bytes in proptest::collection::vec(proptest::num::u8::ANY, 0..300)) {
            let mut d = Decoder::new();
            let _ = d.feed(&bytes);
            // After any garbage, a line end then a command always works (the garbage line itself may
            // get its own error first).
            let out = d.feed(b"\nS 12.5\r\n");
            proptest::prop_assert!(out.len() <= 2);
            proptest::prop_assert_eq!(out.last(), Some(&Ok(Command::SetSpeed { deg_s: 12.5 })));
        }

        #[test]
        fn numbers_round_trip(v in -1.0e6f64..1.0e6) {
            let cmd = Command::MoveRelative { deg: v };
            let back = decode(&cmd.encode());
            let want: f64 = format!("{v:.4}").parse().unwrap_or(f64::NAN);
            proptest::prop_assert_eq!(back, vec![Ok(Command::MoveRelative { deg: if want == 0.0 { 0.0 } else { want } })]);
        }
    }
}
