//! Service plumbing shared by every depthmill service and binary.
//!
//! Libraries of the services use this crate only in their adapters (`grpc.rs`, `http/`) and
//! binaries; their `domain/` modules never import it.
//!
//! # Layout
//! - [`process`]: the allocator's tuning (one malloc arena per core), set first by every binary,
//!   and the service binaries' runtime.
//! - [`config`]: layered configuration (TOML file, then `DEPTHMILL_<SVC>__SECTION__KEY` env overrides).
//! - [`telemetry`]: the tracing subscriber, installed by binaries only.
//! - [`tls`]: TLS of the public APIs: certificate files, the REST server over TLS, the gRPC identity.
//! - [`grpc`]: serving tonic routes on a bound listener, with health, reflection and `/metrics`.
//! - [`metrics`]: the process-global Prometheus recorder (installed once) and gRPC call metrics.
//! - [`shutdown`]: SIGINT/SIGTERM as a future.
//! - [`artifacts`]: the content-addressed artifact store (trait + local-disk implementation).
//! - [`stage`]: the registry of running stage calls that `CancelStage` uses.
//! - [`ErrorChain`]: displays an error with all its sources, for logs.

pub mod artifacts;
pub mod config;
pub mod grpc;
pub mod metrics;
pub mod process;
pub mod shutdown;
pub mod stage;
pub mod telemetry;
pub mod tls;

/// Displays an error and its chain of sources as `outer: inner: innermost`, for logs.
pub struct ErrorChain<'a>(pub &'a (dyn std::error::Error + 'static));

impl std::fmt::Display for ErrorChain<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}", self.0)?;
        let mut source = self.0.source();
        while let Some(s) = source {
            write!(f, ": {s}")?;
            source = s.source();
        }
        Ok(())
    }
}
