//! Job requests (the JSON body of `POST /v1/jobs`): parsing, then validation.
#![no_main]

use depthmill_orchestrator::domain::JobSpec;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    match JobSpec::from_json(data) {
        Ok(spec) => {
            if let Err(e) = spec.validate() {
                assert!(!e.field.is_empty(), "a validation error names its field: {e}");
            }
        }
        Err(e) => assert!(!e.message.is_empty()),
    }
});
