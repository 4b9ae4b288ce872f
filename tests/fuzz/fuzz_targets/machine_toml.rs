//! Machine profiles (TOML).
#![no_main]

use depthmill_machine::domain::profile::MachineProfile;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else { return };
    let _ = MachineProfile::parse(text, "fuzz.toml");
});
