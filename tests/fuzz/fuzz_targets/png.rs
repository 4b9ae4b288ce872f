//! Depth-map PNGs (8- and 16-bit grey, with or without depthmill's metadata).
#![no_main]

use std::io::Cursor;

use depthmill_geometry::{ImageMapping, read_png_from};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = read_png_from(Cursor::new(data), None);
    let _ = read_png_from(Cursor::new(data), Some(&ImageMapping::new(0.1, -10.0, 0.0)));
});
