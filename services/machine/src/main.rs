//! `depthmill-machine`: the machine service alone, as its own process.

use std::path::PathBuf;

use anyhow::Context as _;
use clap::Parser;

/// Runs the depthmill machine service (gRPC, with health and reflection).
///
/// Configuration: the TOML file given with --config (see deploy/config/machine.toml), then
/// environment overrides DEPTHMILL_MACHINE__<KEY> (e.g. DEPTHMILL_MACHINE__GRPC_ADDR=0.0.0.0:50051).
#[derive(Parser)]
#[command(version)]
struct Args {
    /// Configuration file (TOML).
    #[arg(long, env = "DEPTHMILL_MACHINE_CONFIG")]
    config: Option<PathBuf>,
    /// Log as JSON lines.
    #[arg(long)]
    log_json: bool,
}

fn main() -> anyhow::Result<()> {
    depthmill_common::process::run(run()).context("starting the runtime")?
}

async fn run() -> anyhow::Result<()> {
    let args = Args::parse();
    depthmill_common::telemetry::init_tracing(args.log_json);
    // Rendered at GET /metrics on the gRPC port.
    depthmill_common::metrics::install_prometheus()?;
    let config: depthmill_machine::Config =
        depthmill_common::config::load(args.config.as_deref(), "DEPTHMILL_MACHINE")
            .context("loading configuration")?;
    let listener = tokio::net::TcpListener::bind(config.grpc_addr)
        .await
        .with_context(|| format!("binding {}", config.grpc_addr))?;
    depthmill_machine::serve(listener, config, depthmill_common::shutdown::shutdown_signal()).await?;
    Ok(())
}
