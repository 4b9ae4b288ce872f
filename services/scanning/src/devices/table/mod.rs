//! The rotary table on a socket: [`server`] serves a simulated controller
//! ([`crate::domain::table::model::Table`]) speaking the ASCII protocol of DESIGN §6
//! ([`crate::domain::table::protocol`]); [`client`] is the driver the scanning service uses.

pub mod client;
pub mod server;

pub use client::{ClientOptions, TableClient, TableError};
pub use server::{SimulatedTable, serve_table};
