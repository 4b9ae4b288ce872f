//! Device I/O (tokio): the simulated devices served on sockets, and the drivers that talk to
//! them. The models and wire formats they use are pure code in [`crate::domain`].
//!
//! - [`table`]: the rotary table controller on TCP ([`table::server`]) and its client driver
//!   ([`table::client`]), which would drive a real table on a serial line the same way.

pub mod table;
