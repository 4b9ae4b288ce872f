//! Job submission load: POST /v1/jobs at a fixed rate against loopback, on SQLite in WAL mode (the
//! default) or PostgreSQL, through one orchestrator or several replicas sharing the database.
//!
//! ```text
//! cargo bench -p depthmill-orchestrator --bench submit_load -- [--rate 1000] [--duration 30] [--connections 64]
//!     [--url URL | [--postgres | --database-url URL] [--replicas N]]
//! ```
//!
//! `--postgres` makes a scratch database on the server at `DEPTHMILL_TEST_POSTGRES_URL` (default
//! `postgres://postgres@127.0.0.1:5432/postgres`) and drops it afterwards; `--replicas N` starts N
//! orchestrators on the one database and spreads the requests over them round-robin (as a load
//! balancer would).
//!
//! Open loop: requests are scheduled at `rate` per second whatever the server does, and each
//! latency is measured from its scheduled time, so a stalled server shows up in the percentiles
//! instead of slowing the generator down (no coordinated omission). Without `--url` the bench
//! starts an orchestrator in this process (its own runtime and data directory in a temporary
//! folder, worker running; jobs reach a stage whose service is not configured and fail, so the
//! worker writes to the database during the run like it would in production).
//!
//! Baseline, measured in the same run at the same rate: `GET /healthz` (HTTP stack only, no
//! database). The report gives both and their ratio.

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use anyhow::{Context as _, bail};
use serde_json::json;

struct Args {
    rate: f64,
    duration: f64,
    connections: usize,
    url: Option<String>,
    database_url: Option<String>,
    postgres: bool,
    replicas: usize,
}

fn parse_args() -> anyhow::Result<Args> {
    let mut a = Args {
        rate: 1000.0,
        duration: 30.0,
        connections: 64,
        url: None,
        database_url: None,
        postgres: false,
        replicas: 1,
    };
    let mut it = std::env::args().skip(1);
    while let Some(arg) = it.next() {
        let mut value = || it.next().with_context(|| format!("{arg} needs a value"));
        match arg.as_str() {
            "--rate" => a.rate = value()?.parse()?,
            "--duration" => a.duration = value()?.parse()?,
            "--connections" => a.connections = value()?.parse()?,
            "--url" => a.url = Some(value()?),
            "--database-url" => a.database_url = Some(value()?),
            "--postgres" => a.postgres = true,
            "--replicas" => a.replicas = value()?.parse()?,
            "--bench" => {}
            other => bail!(
                "unknown argument {other} (expected --rate, --duration, --connections, --url, --database-url, \
                 --postgres, --replicas)"
            ),
        }
    }
    if a.rate <= 0.0 || a.duration <= 0.0 || a.connections == 0 || a.replicas == 0 {
        bail!("rate, duration, connections and replicas must be positive");
    }
    if a.url.is_some() && (a.postgres || a.database_url.is_some() || a.replicas > 1) {
        bail!("--url measures a running server: --postgres, --database-url and --replicas start one here");
    }
    Ok(a)
}

struct Phase {
    sent: u64,
    errors: u64,
    latencies_us: Vec<u64>,
    wall_s: f64,
}

impl Phase {
    fn pct(&self, p: f64) -> f64 {
        if self.latencies_us.is_empty() {
            return f64::NAN;
        }
        let i = ((self.latencies_us.len() - 1) as f64 * p).round() as usize;
        self.latencies_us[i] as f64 / 1000.0
    }

    fn print(&self, name: &str) {
        println!(
            "{name:<10} sent {:>7}  ok {:>7}  errors {:>4}  rate {:>7.1}/s  p50 {:>6.2} ms  p90 {:>6.2} ms  p99 {:>6.2} ms  max {:>7.2} ms",
            self.sent,
            self.latencies_us.len(),
            self.errors,
            self.latencies_us.len() as f64 / self.wall_s,
            self.pct(0.50),
            self.pct(0.90),
            self.pct(0.99),
            self.pct(1.0),
        );
    }
}

/// Sends `make(i)` requests at `rate`/s for `duration` s with at most `connections` in flight.
async fn run_phase<F, Fut>(rate: f64, duration: f64, connections: usize, make: F) -> Phase
where
    F: Fn(u64) -> Fut + Send + Sync + 'static,
    Fut: std::future::Future<Output = bool> + Send + 'static,
{
    let make = Arc::new(make);
    let total = (rate * duration) as u64;
    let interval = Duration::from_secs_f64(1.0 / rate);
    let permits = Arc::new(tokio::sync::Semaphore::new(connections));
    let errors = Arc::new(AtomicU64::new(0));
    let (tx, mut rx) = tokio::sync::mpsc::unbounded_channel::<u64>();
    let start = Instant::now();
    for i in 0..total {
        let scheduled = start + interval.mul_f64(i as f64);
        tokio::time::sleep_until(scheduled.into()).await;
        let Ok(permit) = permits.clone().acquire_owned().await else { break };
        let make = make.clone();
        let tx = tx.clone();
        let errors = errors.clone();
        tokio::spawn(async move {
            let ok = make(i).await;
            let us = scheduled.elapsed().as_micros() as u64;
            if ok {
                let _ = tx.send(us);
            } else {
                errors.fetch_add(1, Ordering::Relaxed);
            }
            drop(permit);
        });
    }
    drop(tx);
    let mut latencies_us = Vec::with_capacity(total as usize);
    while let Some(us) = rx.recv().await {
        latencies_us.push(us);
    }
    let wall_s = start.elapsed().as_secs_f64();
    latencies_us.sort_unstable();
    Phase { sent: total, errors: errors.load(Ordering::Relaxed), latencies_us, wall_s }
}

fn start_server(dir: &std::path::Path, database_url: Option<String>) -> anyhow::Result<String> {
    let std_listener = std::net::TcpListener::bind("127.0.0.1:0")?;
    let grpc_listener = std::net::TcpListener::bind("127.0.0.1:0")?;
    std_listener.set_nonblocking(true)?;
    grpc_listener.set_nonblocking(true)?;
    let url = format!("http://{}", std_listener.local_addr()?);
    let config = depthmill_orchestrator::Config {
        data_dir: dir.to_path_buf(),
        database_url,
        services: depthmill_orchestrator::Endpoints::none(),
        // Off: the bench is one client flooding the queue faster than the worker empties it, so
        // the product's default (1000 waiting jobs) would refuse most of it (README: Limits).
        max_active_jobs_per_client: 0,
        ..Default::default()
    };
    std::thread::spawn(move || {
        let rt = match tokio::runtime::Builder::new_multi_thread().enable_all().build() {
            Ok(rt) => rt,
            Err(e) => {
                eprintln!("server runtime: {e}");
                return;
            }
        };
        rt.block_on(async move {
            let rest = tokio::net::TcpListener::from_std(std_listener);
            let grpc = tokio::net::TcpListener::from_std(grpc_listener);
            match (rest, grpc) {
                (Ok(rest), Ok(grpc)) => {
                    if let Err(e) =
                        depthmill_orchestrator::serve(rest, grpc, config, None, std::future::pending()).await
                    {
                        eprintln!("server: {e}");
                    }
                }
                _ => eprintln!("server: cannot adopt listeners"),
            }
        });
    });
    Ok(url)
}

fn main() -> anyhow::Result<()> {
    let args = parse_args()?;
    let rt = tokio::runtime::Builder::new_multi_thread().enable_all().build()?;
    let scratch = match args.postgres {
        true => Some(rt.block_on(depthmill_orchestrator::store::scratch::ScratchDatabase::create())?),
        false => None,
    };
    let database_url = scratch.as_ref().map(|db| db.url()).or(args.database_url.clone());
    let dirs = (0..args.replicas).map(|_| tempfile::tempdir()).collect::<Result<Vec<_>, _>>()?;
    let urls: Vec<String> = match &args.url {
        Some(u) => vec![u.trim_end_matches('/').to_string()],
        None => {
            dirs.iter().map(|d| start_server(d.path(), database_url.clone())).collect::<Result<_, _>>()?
        }
    };
    let store = match (&args.url, &database_url) {
        (Some(_), _) => "the server's",
        (None, Some(_)) => "PostgreSQL",
        (None, None) => "SQLite",
    };
    rt.block_on(async move {
        let client = depthmill_common::tls::http_client()
            .pool_max_idle_per_host(args.connections)
            .tcp_nodelay(true)
            .build()?;
        let mut sha = String::new();
        for url in &urls {
            for _ in 0..200 {
                if client.get(format!("{url}/readyz")).send().await.is_ok_and(|r| r.status().is_success()) {
                    break;
                }
                tokio::time::sleep(Duration::from_millis(25)).await;
            }
            // Each replica keeps its own artifact folder here: the program goes to each.
            let upload = client
                .post(format!("{url}/v1/artifacts"))
                .header("content-type", "text/x-gcode")
                .body("G21 G90\nG0 X0 Y0 Z5\nG1 Z-1 F100\nG1 X10 F200\nM30\n")
                .send()
                .await?;
            sha = upload.json::<serde_json::Value>().await?["sha256"]
                .as_str()
                .context("upload failed")?
                .to_string();
        }
        let run_id = std::process::id();
        println!(
            "target {}  job store {store}  rate {}/s  duration {} s  max in flight {}",
            urls.join(", "),
            args.rate,
            args.duration,
            args.connections
        );
        let urls = Arc::new(urls);

        let base_duration = args.duration.min(10.0);
        let c = client.clone();
        let us = urls.clone();
        let baseline = run_phase(args.rate, base_duration, args.connections, move |i| {
            let (c, u) = (c.clone(), us[i as usize % us.len()].clone());
            async move { c.get(format!("{u}/healthz")).send().await.is_ok_and(|r| r.status().is_success()) }
        })
        .await;

        let c = client.clone();
        let us = urls.clone();
        let submit = run_phase(args.rate, args.duration, args.connections, move |i| {
            let (c, u, sha) = (c.clone(), us[i as usize % us.len()].clone(), sha.clone());
            async move {
                let body = json!({"name": format!("load-{i}"), "input": {"kind": "gcode", "artifact": sha}});
                c.post(format!("{u}/v1/jobs"))
                    .header("Idempotency-Key", format!("load-{run_id}-{i}"))
                    .json(&body)
                    .send()
                    .await
                    .is_ok_and(|r| r.status().as_u16() == 201)
            }
        })
        .await;
        baseline.print("healthz");
        submit.print("submit");
        println!(
            "submit/healthz: p50 x{:.2}  p99 x{:.2}   sustained {:.0} submissions/s over {:.1} s, {} errors",
            submit.pct(0.5) / baseline.pct(0.5),
            submit.pct(0.99) / baseline.pct(0.99),
            submit.latencies_us.len() as f64 / submit.wall_s,
            submit.wall_s,
            submit.errors
        );
        anyhow::Ok(())
    })?;
    // The servers' threads still run: leave without waiting for them (the scratch database is
    // dropped with FORCE, which closes their connections).
    drop(scratch);
    drop(dirs);
    Ok(())
}
