//! The PLY reader (ascii, binary little- and big-endian; clouds and meshes).
#![no_main]

use std::io::Cursor;

use depthmill_geometry::formats::ReadLimits;
use depthmill_geometry::formats::ply::read_ply_from;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = read_ply_from(Cursor::new(data), "fuzz.ply", &ReadLimits::default());
});
