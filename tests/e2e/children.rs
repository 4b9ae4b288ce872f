//! Child processes for the campaigns that kill them (`replicas`, `crash`): this test binary run
//! again in a role (`child_process`, an ignored test that does nothing unless
//! `DEPTHMILL_E2E_CHILD` describes the role), so the suite stays one binary. SIGKILL is the only
//! way they stop.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::Stdio;
use std::time::{Duration, Instant};

use anyhow::{Context as _, bail};
use serde::{Deserialize, Serialize};

/// What a child process runs.
#[derive(Serialize, Deserialize)]
pub enum Role {
    Orchestrator(Box<depthmill_orchestrator::Config>),
    Scanning(Box<depthmill_scanning::Config>),
    Reconstruction(depthmill_reconstruction::Config),
    Cam(depthmill_cam::Config),
    Machine(depthmill_machine::Config),
    /// `depthmill serve`: the embedded stack, every service in the process.
    Serve {
        data_dir: PathBuf,
        rest: SocketAddr,
        grpc: SocketAddr,
        config: Option<PathBuf>,
    },
    /// The `depthmill` command line with these arguments (the program name first); the process
    /// exits with its code. With `after_stdin`, it first waits for standard input to close.
    Cli {
        args: Vec<String>,
        after_stdin: bool,
    },
}

/// Child-process entry.
#[test]
#[ignore = "the child processes of the kill campaigns run this; alone it does nothing"]
fn child_process() -> anyhow::Result<()> {
    let Ok(spec) = std::env::var("DEPTHMILL_E2E_CHILD") else { return Ok(()) };
    let role: Role = serde_json::from_str(&spec).context("DEPTHMILL_E2E_CHILD")?;
    if let Role::Cli { args, after_stdin } = role {
        if after_stdin {
            let _ = std::io::Read::read_to_end(&mut std::io::stdin(), &mut Vec::new());
        }
        std::process::exit(i32::from(depthmill_cli::cli::main_from(args)));
    }
    depthmill_common::telemetry::init_tracing(false);
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build()?;
    rt.block_on(async move {
        match role {
            Role::Orchestrator(config) => {
                let rest = tokio::net::TcpListener::bind(config.rest_addr).await?;
                let grpc = tokio::net::TcpListener::bind(config.grpc_addr).await?;
                depthmill_orchestrator::serve(rest, grpc, *config, None, std::future::pending()).await?;
            }
            Role::Scanning(config) => {
                let listener = tokio::net::TcpListener::bind(config.grpc_addr).await?;
                depthmill_scanning::serve(listener, *config, std::future::pending()).await?;
            }
            Role::Reconstruction(config) => {
                let listener = tokio::net::TcpListener::bind(config.grpc_addr).await?;
                depthmill_reconstruction::serve(listener, config, std::future::pending()).await?;
            }
            Role::Cam(config) => {
                let listener = tokio::net::TcpListener::bind(config.grpc_addr).await?;
                depthmill_cam::serve(listener, config, std::future::pending()).await?;
            }
            Role::Machine(config) => {
                let listener = tokio::net::TcpListener::bind(config.grpc_addr).await?;
                depthmill_machine::serve(listener, config, std::future::pending()).await?;
            }
            Role::Serve { data_dir, rest, grpc, config } => {
                depthmill_cli::embedded::serve(data_dir, None, rest, grpc, config).await?;
            }
            Role::Cli { .. } => {}
        }
        anyhow::Ok(())
    })
}

/// A child process and how to start it again.
pub struct Proc {
    pub name: String,
    role: String,
    /// REST address of an orchestrator (ready when `/readyz` answers), gRPC address of a service.
    ready: SocketAddr,
    rest: bool,
    pub log: PathBuf,
    child: Option<std::process::Child>,
}

impl Proc {
    /// `role`, ready when `ready` answers (`/readyz` when `rest`, a TCP connection otherwise);
    /// output appended to `log`.
    pub fn new(name: &str, role: &Role, ready: SocketAddr, rest: bool, log: PathBuf) -> anyhow::Result<Self> {
        Ok(Self { name: name.into(), role: serde_json::to_string(role)?, ready, rest, log, child: None })
    }

    /// Starts it and waits until it is ready.
    pub async fn start(&mut self) -> anyhow::Result<()> {
        let exe = std::env::current_exe()?;
        let log = std::fs::OpenOptions::new().create(true).append(true).open(&self.log)?;
        let child = std::process::Command::new(exe)
            .args(["--ignored", "--exact", "children::child_process", "--nocapture", "--test-threads=1"])
            .env("DEPTHMILL_E2E_CHILD", &self.role)
            .env("RUST_LOG", "info")
            .stdin(Stdio::null())
            .stdout(log.try_clone()?)
            .stderr(log)
            .spawn()
            .with_context(|| format!("starting {}", self.name))?;
        self.child = Some(child);
        let deadline = Instant::now() + Duration::from_secs(30);
        let http = depthmill_common::tls::http_client().build()?;
        loop {
            let up = if self.rest {
                http.get(format!("http://{}/readyz", self.ready))
                    .send()
                    .await
                    .is_ok_and(|r| r.status().is_success())
            } else {
                tokio::net::TcpStream::connect(self.ready).await.is_ok()
            };
            if up {
                return Ok(());
            }
            if Instant::now() > deadline {
                bail!("{} did not come up; its log:\n{}", self.name, tail(&self.log));
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    }

    /// SIGKILL: no shutdown, no flush, no goodbye.
    pub fn kill(&mut self) -> anyhow::Result<()> {
        if let Some(mut child) = self.child.take() {
            child.kill()?;
            child.wait()?;
        }
        Ok(())
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        let _ = self.kill();
    }
}

/// The last 40 lines of a log.
pub fn tail(path: &Path) -> String {
    let text = std::fs::read_to_string(path).unwrap_or_default();
    // Backtrace frames bury the message: say why first (a panic and the lines after it, an
    // error line), then the last lines that are not frames.
    let lines: Vec<&str> = text.lines().collect();
    let frame = |l: &str| {
        let t = l.trim_start();
        t.starts_with("at ") || t.split_once(':').is_some_and(|(n, _)| n.chars().all(|c| c.is_ascii_digit()))
    };
    let mut why = Vec::new();
    for (i, l) in lines.iter().enumerate() {
        if l.contains("panicked at") {
            why.extend(lines[i..(i + 3).min(lines.len())].iter().copied());
        } else if l.starts_with("Error") || l.contains(" ERROR ") {
            why.push(l);
        }
    }
    let rest: Vec<&str> = lines.iter().copied().filter(|l| !frame(l)).collect();
    let mut out: Vec<&str> = why.into_iter().take(30).collect();
    out.push("...");
    out.extend(&rest[rest.len().saturating_sub(30)..]);
    out.join("\n")
}

/// A loopback address nothing listens on now.
///
/// The port comes from below the kernel's ephemeral range (`ip_local_port_range`, 32768-60999 by
/// default): a port taken from that range and released could be handed to another test's outgoing
/// connection or `:0` listener before the child binds it. Below it only explicit binds compete,
/// and ports handed out here are not handed out again by this process.
pub fn free_addr() -> anyhow::Result<SocketAddr> {
    use std::sync::atomic::{AtomicU32, Ordering};
    static NEXT: AtomicU32 = AtomicU32::new(0);
    let ephemeral_lo = std::fs::read_to_string("/proc/sys/net/ipv4/ip_local_port_range")
        .ok()
        .and_then(|s| s.split_whitespace().next().and_then(|v| v.parse::<u32>().ok()))
        .unwrap_or(32768);
    let (lo, hi) = (10_000u32, ephemeral_lo.min(65_536));
    if hi > lo + 1000 {
        let span = hi - lo;
        // Spread processes apart (several suites may run at once), then step through the span.
        let base = (std::process::id().wrapping_mul(7919)) % span;
        for _ in 0..span.min(4000) {
            let port = lo + (base + NEXT.fetch_add(1, Ordering::Relaxed)) % span;
            let Ok(port) = u16::try_from(port) else { continue };
            if let Ok(l) = std::net::TcpListener::bind(("127.0.0.1", port)) {
                return Ok(l.local_addr()?);
            }
        }
    }
    Ok(std::net::TcpListener::bind("127.0.0.1:0")?.local_addr()?)
}

/// A size from the environment, `default` when unset or not a number.
pub fn env_usize(name: &str, default: usize) -> usize {
    std::env::var(name).ok().and_then(|v| v.parse().ok()).unwrap_or(default)
}
