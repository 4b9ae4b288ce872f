//! The process-wide tracing subscriber. Binaries call [`init_tracing`] once; libraries only emit.

use tracing_subscriber::{EnvFilter, fmt, prelude::*};

/// Installs a `fmt` subscriber filtered by `RUST_LOG` (default `info`), as JSON lines when `json`.
/// A second call is a no-op, so the in-process test harness may call it freely.
pub fn init_tracing(json: bool) {
    init_tracing_with_default(json, "info");
}

/// Like [`init_tracing`], with `default` as the filter when `RUST_LOG` is unset (a command that
/// draws its own progress keeps the logs down to warnings).
pub fn init_tracing_with_default(json: bool, default: &str) {
    let filter = EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new(default));
    let registry = tracing_subscriber::registry().with(filter);
    let _ = if json {
        registry.with(fmt::layer().json().with_writer(std::io::stderr)).try_init()
    } else {
        registry.with(fmt::layer().with_writer(std::io::stderr)).try_init()
    };
}
