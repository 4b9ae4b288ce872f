//! The report's G-code reader (the toolpath picture of a job's program).
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = depthmill_report::gcode::parse_reader(std::io::Cursor::new(data));
});
