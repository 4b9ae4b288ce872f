//! The rotary table (DESIGN §6, seed 002 §2.1-2.3): a simulated controller that speaks the table's
//! ASCII protocol over a socket, and the driver the scanning service uses to talk to it (or to a
//! real table on a serial line).
//!
//! # Layout
//! - [`model`]: the physics and the controller, pure and deterministic ([`Table`]).
//! - [`protocol`]: command decoding, reply encoding and the client-side codec, pure.
//! - `crate::devices::table::server`: the simulated controller on a TCP listener (tokio).
//! - `crate::devices::table::client`: the driver over any `AsyncRead + AsyncWrite` stream (tokio).
//!
//! # Model and units
//! Angles in degrees, positive counter-clockwise seen from above ("trigonometric", as the seed's
//! `R`), `[0, 360)` where wrapped; speeds in °/s, accelerations in °/s², time in seconds since
//! power-up. A 12 V DC motor drives the 400 mm disc through a 1:480 gearbox; its quadrature encoder
//! gives 24 counts per motor turn, **11520 counts per table turn (0.03125° per count)**. A PID loop
//! at 1 kHz on the counts (one gain set on the ramps, one at constant speed or at rest, plus
//! feed-forward) follows a symmetric trapezoidal profile. See [`model`] for the equations.
//!
//! # Protocol (one command, one reply; the master waits for each reply)
//!
//! | command | reply | meaning |
//! |---|---|---|
//! | `H\r\n` | `H nn.nnnn\r\n` | encoder angle in degrees (`count · 0.03125`, 4 decimals) |
//! | `h` (one byte, no line end) | 2 bytes, big-endian | encoder count 0..11519 |
//! | `P x\r\n` | `OK\r\n` | absolute move to `x` ∈ [-360, 360], the shortest way |
//! | `R x\r\n` | `OK\r\n` | move to the last target + `x` (R10 then R5.5: target 15.5) |
//! | `S x\r\n` | `OK\r\n` | max speed (0, 45] °/s for the next moves |
//! | `A x\r\n` | `OK\r\n` | acceleration (0, 240] °/s² for the next moves |
//!
//! At power-up, which for the simulator is every time a client connects, the controller prints
//! [`protocol::HEADER`] and `\r\n`. A malformed, unknown or out-of-range command gets
//! `ERR <reason>\r\n` and changes nothing; the next command works as usual. `\n` or `\r` alone also
//! end a line, a space between letter and number is optional, lines are at most 64 bytes, and the
//! binary `h` is only recognised at the start of a line (see [`protocol`]). The 2-byte count is sent
//! **big-endian** (high byte first). Moves run asynchronously: `P`/`R` answer `OK` at once, and a
//! new move interrupts the running one, continuing from the reference's position and velocity.
//!
//! # Timing
//! The simulator has no clock of its own: at every command it advances [`Table`] to the wall-clock
//! time since power-up (tokio's clock, so tests may pause it), then executes the command. The model
//! is deterministic given the command times. Transmission delays are not modelled; on the real
//! 115200 bps line an `h` exchange (3 bytes of 10 bits) takes about 0.26 ms (the seed's
//! 2.6·10⁻⁵ s is a factor ten short), still well under a 6.7 ms scanner frame.
//! Advancing costs one step per 0.1 ms of simulated motion (idle time is skipped), all inside the
//! command that triggers it.

pub mod model;
pub mod protocol;

pub use model::{
    COUNTS_PER_TURN, ControllerParams, DEG_PER_COUNT, LoadParams, MotionLimits, MotorParams, PidGains, Table,
    TableConfig, TableConfigError, Trapezoid,
};
pub use protocol::{Command, Decoder, ParseError, Reply};
