//! [`TableClient`]: the driver the scanning service uses to command the rotary table.
//!
//! It speaks the protocol of [`crate::domain::table::protocol`] over any `AsyncRead + AsyncWrite + Unpin` stream:
//! a TCP socket to the simulator ([`TableClient::connect`]), or a serial port wrapped as a tokio
//! stream for a real table (then use [`ClientOptions::expect_header`] `= false` if the controller
//! was powered up before the port was opened, since the header is only printed at power-up).
//!
//! The robot is the master: the client sends one command and waits for its reply, with a timeout
//! ([`ClientOptions::reply_timeout`]). After a timeout, an I/O error or a reply it cannot parse, the
//! client no longer knows which reply belongs to which command, so every later call returns
//! [`TableError::Desynchronized`]; reconnect. An `ERR` reply is an ordinary error
//! ([`TableError::Rejected`], with the controller's reason) and the connection stays usable.
//!
//! The client mirrors the controller's last target (from its own `P` and `R` commands, as the
//! controller parses them) so that [`TableClient::wait_settled`] knows where the table should stop.
//! A fresh connection does not know the controller's last target until the first `P`; until then
//! `wait_settled` only waits for the table to stand still.

use std::time::Duration;

use tokio::io::{AsyncBufReadExt, AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt, BufStream};
use tokio::net::{TcpStream, ToSocketAddrs};
use tokio::time::Instant;

use crate::domain::table::model::{COUNTS_PER_TURN, quantized_target_deg, shortest_delta_deg, wrap_deg};
use crate::domain::table::protocol::{
    Command, MAX_LINE_LEN, MAX_REPLY_LEN, Reply, decode_counts, escape_bytes, parse_reply_line, wire_value,
};

/// Errors of the table driver.
#[derive(Debug, thiserror::Error)]
pub enum TableError {
    /// The controller answered `ERR <reason>`; the connection is still usable.
    #[error("table refused '{command}': {reason}")]
    Rejected {
        /// The command as sent (`P 90.0000`, `connect` for a refused connection).
        command: String,
        /// The controller's reason.
        reason: String,
    },
    /// No (complete) reply in time.
    #[error("no reply to '{command}' within {timeout_ms} ms")]
    Timeout {
        /// The command.
        command: String,
        /// The timeout.
        timeout_ms: u128,
    },
    /// A reply that does not fit the command.
    #[error("malformed reply to '{command}': {detail}")]
    MalformedReply {
        /// The command.
        command: String,
        /// What was wrong, with the reply's bytes escaped.
        detail: String,
    },
    /// The table did not stop at the target in time.
    #[error(
        "table not settled within {timeout_ms} ms: at {last_deg:?} deg, target {target_deg:?} deg, tolerance {tol_deg} deg"
    )]
    NotSettled {
        /// The timeout.
        timeout_ms: u128,
        /// Last position read (degrees), if any.
        last_deg: Option<f64>,
        /// The count-quantised target (degrees), if known.
        target_deg: Option<f64>,
        /// The tolerance asked for.
        tol_deg: f64,
    },
    /// A value the driver will not send.
    #[error("invalid {what} '{value}': {reason}")]
    InvalidArgument {
        /// Which argument.
        what: &'static str,
        /// Its value.
        value: String,
        /// Why.
        reason: &'static str,
    },
    /// The peer closed the connection.
    #[error("table connection closed")]
    Closed,
    /// An earlier timeout, I/O error or malformed reply left the stream out of step.
    #[error("table connection out of step after an earlier failure; reconnect")]
    Desynchronized,
    /// I/O failure.
    #[error("table i/o failed")]
    Io(#[source] std::io::Error),
}

impl From<std::io::Error> for TableError {
    fn from(e: std::io::Error) -> Self {
        if e.kind() == std::io::ErrorKind::UnexpectedEof { TableError::Closed } else { TableError::Io(e) }
    }
}

/// Driver settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ClientOptions {
    /// Longest wait for one reply (and for the header, and for the TCP connect).
    pub reply_timeout: Duration,
    /// Time between position reads in [`TableClient::wait_settled`].
    pub poll_interval: Duration,
    /// Consecutive identical readings within tolerance that count as settled (>= 1).
    pub settle_polls: u32,
    /// Read the power-up header when the stream opens.
    pub expect_header: bool,
}

impl Default for ClientOptions {
    fn default() -> Self {
        Self {
            reply_timeout: Duration::from_secs(1),
            poll_interval: Duration::from_millis(20),
            settle_polls: 3,
            expect_header: true,
        }
    }
}

/// The rotary table driver; see the module doc.
#[derive(Debug)]
pub struct TableClient<S> {
    io: BufStream<S>,
    options: ClientOptions,
    header: Option<String>,
    target_deg: Option<f64>,
    broken: bool,
}

impl TableClient<TcpStream> {
    /// Connects over TCP with default options and reads the header.
    pub async fn connect(addr: impl ToSocketAddrs) -> Result<Self, TableError> {
        Self::connect_with(addr, ClientOptions::default()).await
    }

    /// Connects over TCP with `options`.
    pub async fn connect_with(addr: impl ToSocketAddrs, options: ClientOptions) -> Result<Self, TableError> {
        let stream = tokio::time::timeout(options.reply_timeout, TcpStream::connect(addr))
            .await
            .map_err(|_| timeout_error("connect", options.reply_timeout))??;
        stream.set_nodelay(true)?;
        Self::new(stream, options).await
    }
}

fn timeout_error(command: &str, timeout: Duration) -> TableError {
    TableError::Timeout { command: command.to_string(), timeout_ms: timeout.as_millis() }
}

impl<S: AsyncRead + AsyncWrite + Unpin> TableClient<S> {
    /// Wraps an open stream; reads the header if `options.expect_header`. A controller that
    /// answers `ERR` instead (the simulator when another client holds the line) gives
    /// [`TableError::Rejected`] with command `connect`.
    pub async fn new(stream: S, options: ClientOptions) -> Result<Self, TableError> {
        let mut client = Self {
            io: BufStream::new(stream),
            options: ClientOptions { settle_polls: options.settle_polls.max(1), ..options },
            header: None,
            target_deg: None,
            broken: false,
        };
        if options.expect_header {
            let line = tokio::time::timeout(options.reply_timeout, client.read_line())
                .await
                .map_err(|_| timeout_error("header", options.reply_timeout))??;
            if let Ok(Reply::Error(reason)) = parse_reply_line(&line) {
                return Err(TableError::Rejected { command: "connect".into(), reason });
            }
            client.header = Some(escape_bytes(&line));
        }
        Ok(client)
    }

    /// The power-up header, if one was read.
    pub fn header(&self) -> Option<&str> {
        self.header.as_deref()
    }

    /// The controller's last target as this client knows it (`[0, 360)` degrees, unquantised).
    pub fn target_deg(&self) -> Option<f64> {
        self.target_deg
    }

    /// Reads one reply line (up to `\n`, `\r` stripped), at most [`MAX_REPLY_LEN`] bytes.
    async fn read_line(&mut self) -> Result<Vec<u8>, TableError> {
        let mut line = Vec::new();
        loop {
            let buf = self.io.fill_buf().await?;
            if buf.is_empty() {
                return Err(TableError::Closed);
            }
            let (take, done) = match buf.iter().position(|&b| b == b'\n') {
                Some(i) => (i + 1, true),
                None => (buf.len(), false),
            };
            line.extend_from_slice(&buf[..take]);
            self.io.consume(take);
            if done {
                line.pop();
                if line.last() == Some(&b'\r') {
                    line.pop();
                }
                return Ok(line);
            }
            if line.len() > MAX_REPLY_LEN {
                return Err(TableError::MalformedReply {
                    command: "read".into(),
                    detail: format!("reply line longer than {MAX_REPLY_LEN} bytes"),
                });
            }
        }
    }

    /// Sends `bytes` and reads one reply (2 binary bytes when `binary`, else a line).
    async fn exchange(&mut self, bytes: &[u8], binary: bool, command: &str) -> Result<Reply, TableError> {
        if self.broken {
            return Err(TableError::Desynchronized);
        }
        let timeout = self.options.reply_timeout;
        let result = tokio::time::timeout(timeout, async {
            self.io.write_all(bytes).await?;
            self.io.flush().await?;
            if binary {
                let mut two = [0u8; 2];
                self.io.read_exact(&mut two).await?;
                Ok(Reply::Counts(decode_counts(two)))
            } else {
                let line = self.read_line().await?;
                parse_reply_line(&line).map_err(|e| TableError::MalformedReply {
                    command: command.to_string(),
                    detail: e.to_string(),
                })
            }
        })
        .await
        .unwrap_or_else(|_| Err(timeout_error(command, timeout)));
        match result {
            Ok(Reply::Error(reason)) => Err(TableError::Rejected { command: command.to_string(), reason }),
            Ok(reply) => Ok(reply),
            Err(e) => {
                self.broken = true;
                Err(e)
            }
        }
    }

    async fn request(&mut self, cmd: Command) -> Result<Reply, TableError> {
        let name = cmd.describe();
        self.exchange(&cmd.encode(), cmd == Command::ReadCounts, &name).await
    }

    async fn expect_ok(&mut self, cmd: Command) -> Result<(), TableError> {
        match self.request(cmd).await? {
            Reply::Ok => Ok(()),
            other => Err(self.unexpected(cmd, other, "OK")),
        }
    }

    fn unexpected(&mut self, cmd: Command, got: Reply, want: &str) -> TableError {
        self.broken = true;
        TableError::MalformedReply {
            command: cmd.describe(),
            detail: format!("expected {want}, got '{}'", escape_bytes(&got.encode())),
        }
    }

    /// Sends one raw text command line (no line end; `\r\n` is added) and returns the reply, for
    /// debugging as with a terminal. `ERR` replies become [`TableError::Rejected`].
    pub async fn raw_command(&mut self, line: &str) -> Result<Reply, TableError> {
        if line.len() > MAX_LINE_LEN
            || line.bytes().any(|b| b == b'\r' || b == b'\n')
            || line.starts_with('h')
        {
            return Err(TableError::InvalidArgument {
                what: "raw command",
                value: escape_bytes(line.as_bytes()),
                reason: "must be one text line of at most 64 bytes, not the binary h",
            });
        }
        let bytes = format!("{line}\r\n");
        self.exchange(bytes.as_bytes(), false, line).await
    }

    /// `H`: the table angle in degrees, as the controller reports it (encoder resolution 0.03125°).
    pub async fn position_deg(&mut self) -> Result<f64, TableError> {
        match self.request(Command::ReadDegrees).await? {
            Reply::Degrees(deg) => Ok(deg),
            other => Err(self.unexpected(Command::ReadDegrees, other, "H <degrees>")),
        }
    }

    /// `h` (binary): the encoder count, `0..11520`.
    pub async fn position_counts(&mut self) -> Result<u16, TableError> {
        match self.request(Command::ReadCounts).await? {
            Reply::Counts(c) if u32::from(c) < COUNTS_PER_TURN => Ok(c),
            other => Err(self.unexpected(Command::ReadCounts, other, "a count below 11520")),
        }
    }

    fn wire(what: &'static str, value: f64) -> Result<f64, TableError> {
        wire_value(value).ok_or_else(|| TableError::InvalidArgument {
            what,
            value: value.to_string(),
            reason: "must be finite and fit a 64-byte line",
        })
    }

    /// `P`: absolute move to `deg` (any finite angle; sent wrapped into `[0, 360)`), the shortest way.
    /// Returns when the controller accepted it; the move runs on (see [`Self::wait_settled`]).
    pub async fn move_to(&mut self, deg: f64) -> Result<(), TableError> {
        let sent = Self::wire("angle", if deg.is_finite() { wrap_deg(deg) } else { deg })?;
        self.expect_ok(Command::MoveAbsolute { deg: sent }).await?;
        self.target_deg = Some(wrap_deg(sent));
        Ok(())
    }

    /// `R`: move by `deg` from the last target (not from where the table is now).
    pub async fn move_by(&mut self, deg: f64) -> Result<(), TableError> {
        let sent = Self::wire("increment", deg)?;
        self.expect_ok(Command::MoveRelative { deg: sent }).await?;
        self.target_deg = self.target_deg.map(|t| wrap_deg(t + sent));
        Ok(())
    }

    /// `S`: maximum speed (°/s) for the next moves.
    pub async fn set_speed(&mut self, deg_s: f64) -> Result<(), TableError> {
        let sent = Self::wire("speed", deg_s)?;
        self.expect_ok(Command::SetSpeed { deg_s: sent }).await
    }

    /// `A`: acceleration (°/s²) for the next moves.
    pub async fn set_accel(&mut self, deg_s2: f64) -> Result<(), TableError> {
        let sent = Self::wire("acceleration", deg_s2)?;
        self.expect_ok(Command::SetAccel { deg_s2: sent }).await
    }

    /// Polls `H` every [`ClientOptions::poll_interval`] until [`ClientOptions::settle_polls`]
    /// consecutive readings are identical and within `tol_deg` of the target's encoder count (the
    /// count nearest the target, which is where the controller stops; with no known target, any
    /// position). Returns the settled reading, or [`TableError::NotSettled`] after `timeout`.
    pub async fn wait_settled(&mut self, tol_deg: f64, timeout: Duration) -> Result<f64, TableError> {
        let deadline = Instant::now() + timeout;
        let goal = self.target_deg.map(quantized_target_deg);
        let mut last: Option<f64> = None;
        let mut stable = 0u32;
        loop {
            let pos = self.position_deg().await?;
            let near = goal.is_none_or(|g| shortest_delta_deg(g, pos).abs() <= tol_deg);
            stable = match (near, last == Some(pos)) {
                (false, _) => 0,
                (true, true) => stable + 1,
                (true, false) => 1,
            };
            last = Some(pos);
            if stable >= self.options.settle_polls {
                return Ok(pos);
            }
            let now = Instant::now();
            if now >= deadline {
                return Err(TableError::NotSettled {
                    timeout_ms: timeout.as_millis(),
                    last_deg: last,
                    target_deg: goal,
                    tol_deg,
                });
            }
            tokio::time::sleep(self.options.poll_interval.min(deadline - now)).await;
        }
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)] // tests may unwrap
mod tests {
    use super::super::server::{SimulatedTable, serve_table};
    use super::*;
    use crate::domain::table::model::TableConfig;
    use tokio::io::duplex;

    /// Starts a TCP server on 127.0.0.1:0; returns its address and a stopper.
    async fn start_server()
    -> (std::net::SocketAddr, tokio::sync::oneshot::Sender<()>, tokio::task::JoinHandle<()>) {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap();
        let (tx, rx) = tokio::sync::oneshot::channel::<()>();
        let task = tokio::spawn(async move {
            serve_table(listener, TableConfig::default(), async {
                let _ = rx.await;
            })
            .await
            .unwrap();
        });
        (addr, tx, task)
    }

    #[tokio::test]
    async fn tcp_move_settle_and_read_back() {
        let (addr, stop, server) = start_server().await;
        let mut table = TableClient::connect(addr).await.unwrap();
        assert_eq!(table.header(), Some(crate::domain::table::protocol::HEADER));
        assert_eq!(table.position_counts().await.unwrap(), 0);
        table.set_speed(45.0).await.unwrap();
        table.set_accel(240.0).await.unwrap();
        table.move_to(30.0).await.unwrap();
        let settled = table.wait_settled(0.01, Duration::from_secs(5)).await.unwrap();
        assert!((settled - 30.0).abs() <= 0.01, "{settled}");
        let h = table.position_deg().await.unwrap();
        assert!((h - 30.0).abs() <= 0.01);
        let counts = table.position_counts().await.unwrap();
        assert_eq!(f64::from(counts) * 0.03125, h, "h agrees with H");
        // Relative to the last target, wrapping through 0 the short way.
        table.move_by(-40.5).await.unwrap();
        assert_eq!(table.target_deg(), Some(349.5));
        let settled = table.wait_settled(0.01, Duration::from_secs(5)).await.unwrap();
        assert_eq!(settled, 349.5);
        assert_eq!(table.position_counts().await.unwrap(), 11184);
        stop.send(()).unwrap();
        server.await.unwrap();
    }

    #[tokio::test]
    async fn tcp_err_reply_is_an_error_and_the_line_keeps_working() {
        let (addr, stop, server) = start_server().await;
        let mut table = TableClient::connect(addr).await.unwrap();
        match table.raw_command("P abc").await {
            Err(TableError::Rejected { command, reason }) => {
                assert_eq!(command, "P abc");
                assert_eq!(reason, "malformed number 'abc' for P");
            }
            other => panic!("{other:?}"),
        }
        let e = table.set_speed(100.0).await.unwrap_err();
        assert_eq!(e.to_string(), "table refused 'S 100.0000': speed 100 deg/s out of range (0, 45]");
        assert_eq!(table.position_deg().await.unwrap(), 0.0);
        assert_eq!(table.raw_command("S 10").await.unwrap(), Reply::Ok);
        assert!(matches!(table.raw_command("h").await, Err(TableError::InvalidArgument { .. })));
        assert!(matches!(table.move_to(f64::NAN).await, Err(TableError::InvalidArgument { .. })));
        stop.send(()).unwrap();
        server.await.unwrap();
    }

    #[tokio::test]
    async fn tcp_second_client_after_the_first_disconnects() {
        let (addr, stop, server) = start_server().await;
        let mut first = TableClient::connect(addr).await.unwrap();
        first.set_speed(45.0).await.unwrap();
        first.set_accel(240.0).await.unwrap();
        first.move_to(10.0).await.unwrap();
        first.wait_settled(0.01, Duration::from_secs(5)).await.unwrap();
        drop(first);
        let mut second = TableClient::connect(addr).await.unwrap();
        // The table kept its state; the new client does not know the target yet.
        assert_eq!(second.target_deg(), None);
        assert_eq!(second.wait_settled(0.01, Duration::from_secs(2)).await.unwrap(), 10.0);
        // R is relative to the controller's last target (10), set by the first client.
        second.move_by(5.5).await.unwrap();
        assert_eq!(second.wait_settled(0.01, Duration::from_secs(5)).await.unwrap(), 15.5);
        // A third while the second is connected is refused after the busy wait.
        let e = TableClient::connect_with(
            addr,
            ClientOptions { reply_timeout: Duration::from_secs(3), ..Default::default() },
        )
        .await
        .unwrap_err();
        assert!(matches!(e, TableError::Rejected { ref command, .. } if command == "connect"), "{e}");
        stop.send(()).unwrap();
        server.await.unwrap();
    }

    #[tokio::test(start_paused = true)]
    async fn long_moves_in_paused_time_over_a_duplex() {
        let sim = SimulatedTable::new(TableConfig::default()).unwrap();
        let (ours, theirs) = duplex(4096);
        let s = sim.clone();
        tokio::spawn(async move { s.serve_connection(theirs, std::future::pending()).await });
        let mut table = TableClient::new(ours, ClientOptions::default()).await.unwrap();
        table.set_speed(30.0).await.unwrap();
        table.set_accel(60.0).await.unwrap();
        let t0 = Instant::now();
        table.move_to(90.0).await.unwrap();
        // Interrupt half way with a move back; it continues from its position and velocity.
        tokio::time::sleep(Duration::from_millis(1500)).await;
        table.move_to(300.0).await.unwrap(); // shortest way: -97.5 from ~37.5
        let at = table.wait_settled(0.01, Duration::from_secs(20)).await.unwrap();
        assert_eq!(at, 300.0);
        assert!(sim.with_table(|t| t.position_unwrapped_deg()) < 0.0, "went clockwise");
        let elapsed = t0.elapsed().as_secs_f64();
        assert!(elapsed > 5.0 && elapsed < 12.0, "{elapsed}");
        let truth = sim.with_table(|t| t.position_deg());
        assert!((300.0..300.03125).contains(&truth));
        // 12 moves by R accumulate exactly on the target.
        for _ in 0..12 {
            table.move_by(2.5).await.unwrap();
        }
        assert_eq!(table.wait_settled(0.01, Duration::from_secs(20)).await.unwrap(), 330.0);
    }

    #[tokio::test(start_paused = true)]
    async fn silent_peer_times_out_and_desynchronizes() {
        let (ours, _theirs) = duplex(64);
        let opts = ClientOptions { expect_header: false, ..Default::default() };
        let mut table = TableClient::new(ours, opts).await.unwrap();
        assert!(matches!(table.position_deg().await, Err(TableError::Timeout { .. })));
        assert!(matches!(table.position_deg().await, Err(TableError::Desynchronized)));
    }

    #[tokio::test(start_paused = true)]
    async fn malformed_and_closed_replies() {
        let (ours, mut theirs) = duplex(256);
        let opts = ClientOptions { expect_header: false, ..Default::default() };
        let mut table = TableClient::new(ours, opts).await.unwrap();
        theirs.write_all(b"WHAT\r\n").await.unwrap();
        let e = table.position_deg().await.unwrap_err();
        assert!(matches!(e, TableError::MalformedReply { .. }), "{e}");
        let (ours, mut theirs) = duplex(256);
        let mut table = TableClient::new(ours, opts).await.unwrap();
        theirs.write_all(b"OK\r\n").await.unwrap();
        let e = table.position_deg().await.unwrap_err();
        assert_eq!(e.to_string(), "malformed reply to 'H': expected H <degrees>, got 'OK\\r\\n'");
        let (ours, theirs) = duplex(256);
        let mut table = TableClient::new(ours, opts).await.unwrap();
        drop(theirs);
        assert!(matches!(table.position_counts().await, Err(TableError::Closed) | Err(TableError::Io(_))));
    }
}
