//! `depthmill-orchestrator`: the orchestrator alone, as its own process.

use std::path::PathBuf;

use anyhow::Context as _;
use clap::Parser;

/// Runs the depthmill orchestrator: REST and gRPC APIs, the job database and the job worker.
///
/// Configuration: the TOML file given with --config (see deploy/config/orchestrator.toml), then
/// environment overrides DEPTHMILL_ORCHESTRATOR__<KEY>, with __ between levels
/// (e.g. DEPTHMILL_ORCHESTRATOR__SERVICES__CAM=http://cam:50053).
#[derive(Parser)]
#[command(version)]
struct Args {
    /// Configuration file (TOML).
    #[arg(long, env = "DEPTHMILL_ORCHESTRATOR_CONFIG")]
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
    let metrics = depthmill_common::metrics::install_prometheus()?;
    let config: depthmill_orchestrator::Config =
        depthmill_common::config::load(args.config.as_deref(), "DEPTHMILL_ORCHESTRATOR")
            .context("loading configuration")?;
    let rest = tokio::net::TcpListener::bind(config.rest_addr)
        .await
        .with_context(|| format!("binding REST {}", config.rest_addr))?;
    let grpc = tokio::net::TcpListener::bind(config.grpc_addr)
        .await
        .with_context(|| format!("binding gRPC {}", config.grpc_addr))?;
    depthmill_orchestrator::serve(
        rest,
        grpc,
        config,
        Some(metrics),
        depthmill_common::shutdown::shutdown_signal(),
    )
    .await?;
    Ok(())
}
