//! The STL reader (ascii and binary).
#![no_main]

use std::io::Cursor;

use depthmill_geometry::formats::ReadLimits;
use depthmill_geometry::formats::stl::read_stl_from;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let limits = ReadLimits::default();
    if let Ok((mesh, _)) = read_stl_from(Cursor::new(data), "fuzz.stl", Some(data.len() as u64), &limits) {
        // Every kept triangle refers to a kept vertex.
        let n = mesh.vertices.len();
        assert!(mesh.triangles.iter().all(|t| t.iter().all(|&i| (i as usize) < n)));
    }
    let _ = read_stl_from(Cursor::new(data), "fuzz.stl", None, &limits);
});
