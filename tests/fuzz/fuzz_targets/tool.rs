//! `.tool` files of the CAM tool library.
#![no_main]

use depthmill_cam::domain::tool::Tool;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else { return };
    if let Err(e) = Tool::parse(text, "fuzz.tool") {
        assert!(e.to_string().contains("fuzz.tool"), "{e}");
    }
});
