//! The library half of the `depthmill` binary: the embedded stack `depthmill serve` runs, so tests
//! can run exactly that in a process of their own.

pub mod embedded;
