//! The XYZ text reader.
#![no_main]

use std::io::Cursor;

use depthmill_geometry::formats::ReadLimits;
use depthmill_geometry::formats::xyz::read_xyz_from;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok((cloud, _)) = read_xyz_from(Cursor::new(data), "fuzz.xyz", &ReadLimits::default()) {
        // Non-finite points are dropped, never kept.
        assert!(cloud.points.iter().all(|p| p.iter().all(|c| c.is_finite())));
    }
});
