//! The `depthmill` binary as a library ([`cli::main_from`]), so tests can run exactly its verbs
//! and its embedded stack (`depthmill serve`, [`embedded`]) in processes of their own.

mod cam;
pub mod cli;
pub mod client;
mod demo;
pub mod embedded;
mod machine;
pub mod out;
mod raster;
mod robot;
mod scan;
mod slice;
mod token;
