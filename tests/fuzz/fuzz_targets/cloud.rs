//! Any cloud or mesh input as the services read an upload: the format sniffed from its first
//! bytes (PLY, STL ascii/binary, OBJ, OFF, PCD, XYZ), the production limits.
#![no_main]

use std::io::Cursor;

use depthmill_geometry::formats::{ReadLimits, read_any_from};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let limits = ReadLimits::default();
    let size = Some(data.len() as u64);
    if let Err(e) = read_any_from(Cursor::new(data), "fuzz-input", size, &limits) {
        // Every error names the input.
        assert!(e.to_string().contains("fuzz-input"), "{e}");
    }
    // Streamed (size unknown), as a body read from a socket.
    let _ = read_any_from(Cursor::new(data), "fuzz-input", None, &limits);
});
