//! NumPy `.npy` depth maps (every dtype and byte order the reader takes).
#![no_main]

use std::io::Cursor;

use depthmill_geometry::{ImageMapping, read_npy_from};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = read_npy_from(Cursor::new(data), None, Some(&ImageMapping::pixel_only(0.1)));
    let _ = read_npy_from(Cursor::new(data), None, None);
});
