//! Scale-out under fire: three orchestrator replicas on one PostgreSQL database and two instances
//! of each stage service (scanning, reconstruction, cam, machine), each a separate process, with
//! every artifact in one S3 bucket (an `s3s-fs` server this test serves on loopback), killed with SIGKILL at random moments and restarted
//! while jobs of every kind (G-code, depth map, point cloud, mesh) arrive through REST and gRPC.
//! Every job must end once, succeeded, with each stage of its chain recorded once and every
//! artifact's bytes matching its hash.
//!
//! The processes are this test binary run again in a child role ([`crate::children`]), so the
//! suite stays one binary. Size: `DEPTHMILL_REPLICA_JOBS` (default 24) and `DEPTHMILL_REPLICA_KILLS` (default 8);
//! the documented full run is 200 jobs and 40 kills (README, "Several replicas").

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::net::SocketAddr;
use std::time::{Duration, Instant};

use anyhow::{Context as _, bail, ensure};
use depthmill_orchestrator::store::scratch::ScratchDatabase;
use depthmill_proto::orchestrator::v1 as pb;
use depthmill_proto::orchestrator::v1::orchestrator_service_client::OrchestratorServiceClient;

use crate::children::{Proc, Role, env_usize, free_addr, tail};
use rand::Rng as _;
use serde_json::{Value, json};
use sha2::{Digest as _, Sha256};

/// A short program: 30 slotting passes.
fn program() -> Vec<u8> {
    let mut s = String::from("%\nG21 G90 G17 G94\nT1 M6\nS1500 M3\nG43 H1\nG0 X-5 Y5\nG0 Z12\n");
    for k in 0..30u32 {
        let _ = writeln!(s, "G1 Z{:.2} F200", 10.0 - 0.1 * f64::from(k));
        let _ = writeln!(s, "G1 X{} F300", if k.is_multiple_of(2) { 35 } else { -5 });
    }
    s.push_str("G0 Z15\nM30\n%\n");
    s.into_bytes()
}

fn job_body(sha: &str, n: usize) -> Value {
    json!({"name": format!("replica-{n}"), "input": {"kind": "gcode", "artifact": sha},
           "execute": {"machine": "emco-f1", "adaptive": "off", "compare": false, "cell_mm": 0.5}})
}

/// [`job_body`] as the gRPC message.
fn job_pb(sha: &str, n: usize) -> pb::JobSpec {
    use depthmill_proto::machine::v1 as machine;
    pb::JobSpec {
        name: format!("replica-{n}"),
        input: Some(pb::JobInput {
            kind: pb::InputKind::Gcode as i32,
            artifact: sha.to_string(),
            ..Default::default()
        }),
        execute: Some(machine::ExecuteParams {
            machine: Some("emco-f1".into()),
            adaptive: machine::AdaptiveMode::Off as i32,
            compare: Some(false),
            cell_mm: Some(0.5),
            ..Default::default()
        }),
        ..Default::default()
    }
}

/// Submits job `n` through replica `n % replicas`, REST for even `n` (`body`) and gRPC for odd (a
/// G-code job of the program `sha`), retrying on the next replica while one is down; the
/// idempotency key makes retries return the same job.
async fn submit(
    rest: &[SocketAddr],
    grpc: &[SocketAddr],
    sha: &str,
    body: &Value,
    n: usize,
) -> anyhow::Result<String> {
    let key = format!("replica-job-{n}");
    let http = depthmill_common::tls::http_client().timeout(Duration::from_secs(10)).build()?;
    for attempt in 0..60 {
        let r = (n + attempt) % rest.len();
        let id = if n.is_multiple_of(2) {
            let resp = http
                .post(format!("http://{}/v1/jobs", rest[r]))
                .header("Idempotency-Key", &key)
                .json(body)
                .send()
                .await;
            match resp {
                Ok(resp) if resp.status().is_success() => {
                    resp.json::<Value>().await?["id"].as_str().map(String::from)
                }
                Ok(resp) if resp.status().is_client_error() => {
                    bail!("job {n} refused: {}", resp.text().await?)
                }
                _ => None,
            }
        } else {
            let spec = job_pb(sha, n);
            match OrchestratorServiceClient::connect(format!("http://{}", grpc[r])).await {
                Ok(mut client) => client
                    .create_job(pb::CreateJobRequest { spec: Some(spec), idempotency_key: key.clone() })
                    .await
                    .ok()
                    .map(|job| job.into_inner().id),
                Err(_) => None,
            }
        };
        if let Some(id) = id {
            return Ok(id);
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    bail!("job {n} could not be submitted to any replica")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn replicas_and_instances_survive_sigkill() -> anyhow::Result<()> {
    let jobs = env_usize("DEPTHMILL_REPLICA_JOBS", 24);
    let kills = env_usize("DEPTHMILL_REPLICA_KILLS", 8);
    let db = ScratchDatabase::create().await?;
    let root = tempfile::tempdir()?;
    let s3 = crate::objects::S3Server::start().await?;
    let bucket = s3.config(&s3.endpoint, "replicas");

    let mut procs = Vec::new();
    let mut urls: BTreeMap<&str, Vec<String>> = BTreeMap::new();
    for kind in ["scanning", "reconstruction", "cam", "machine"] {
        for i in 0..2 {
            let addr = free_addr()?;
            urls.entry(kind).or_default().push(format!("http://{addr}"));
            // Its local copies of the blobs it reads.
            let cache = root.path().join(format!("{kind}-{i}-cache"));
            let store = Some(bucket.clone());
            let token = Some("replica-test-token".to_string());
            let role = match kind {
                "scanning" => Role::Scanning(Box::new(depthmill_scanning::Config {
                    grpc_addr: addr,
                    artifacts_dir: cache,
                    artifact_store: store,
                    service_token: token,
                    ..Default::default()
                })),
                "reconstruction" => Role::Reconstruction(depthmill_reconstruction::Config {
                    grpc_addr: addr,
                    artifacts_dir: cache,
                    artifact_store: store,
                    service_token: token,
                    ..Default::default()
                }),
                "cam" => Role::Cam(depthmill_cam::Config {
                    grpc_addr: addr,
                    artifacts_dir: cache,
                    artifact_store: store,
                    service_token: token,
                    ..Default::default()
                }),
                _ => Role::Machine(depthmill_machine::Config {
                    grpc_addr: addr,
                    artifacts_dir: cache,
                    artifact_store: store,
                    service_token: token,
                }),
            };
            let log = root.path().join(format!("{kind}-{i}.log"));
            procs.push(Proc::new(&format!("{kind}-{i}"), &role, addr, false, log)?);
        }
    }
    let list = |kind: &str| urls.get(kind).map(|u| u.join(", ")).unwrap_or_default();
    let (mut rest, mut grpc) = (Vec::new(), Vec::new());
    for i in 0..3 {
        let (r, g) = (free_addr()?, free_addr()?);
        let mut services = depthmill_orchestrator::Endpoints::none();
        services.scanning = list("scanning");
        services.reconstruction = list("reconstruction");
        services.cam = list("cam");
        services.machine = list("machine");
        services.health_interval_ms = 250;
        services.token = Some("replica-test-token".into());
        let config = depthmill_orchestrator::Config {
            rest_addr: r,
            grpc_addr: g,
            data_dir: root.path().join(format!("replica-{i}")),
            artifact_store: Some(bucket.clone()),
            database_url: Some(db.url()),
            services,
            worker: depthmill_orchestrator::WorkerConfig {
                concurrency: 2,
                lease_s: 2.0,
                poll_ms: 100,
                max_attempts: 20,
                backoff_min_ms: 100,
                backoff_max_ms: 1000,
                stage_deadline_s: 60.0,
                cancel_grace_s: 2.0,
            },
            ..Default::default()
        };
        rest.push(r);
        grpc.push(g);
        let log = root.path().join(format!("replica-{i}.log"));
        procs.push(Proc::new(&format!("replica-{i}"), &Role::Orchestrator(Box::new(config)), r, true, log)?);
    }
    for p in &mut procs {
        p.start().await?;
    }

    let http = depthmill_common::tls::http_client().build()?;
    let upload = |media_type: &'static str, bytes: Vec<u8>| {
        let http = http.clone();
        let url = format!("http://{}/v1/artifacts", rest[0]);
        async move {
            let reply = http.post(url).header("content-type", media_type).body(bytes).send().await?;
            let body = reply.json::<Value>().await?;
            anyhow::Ok(body["sha256"].as_str().context("upload")?.to_string())
        }
    };
    let sha = upload("text/x-gcode", program()).await?;
    // REST jobs cycle through the kinds: (body maker input, its sha, its stage chain).
    let mut kinds = Vec::new();
    for input in crate::crash::inputs()? {
        let sha = upload(input.media_type, input.bytes.clone()).await?;
        kinds.push((input.kind, sha, input.stages.clone()));
    }
    // Job n: its body (REST) and its stage chain.
    let plan: Vec<(Value, Vec<&'static str>)> = (0..jobs)
        .map(|n| {
            if n.is_multiple_of(2) {
                let (kind, sha, stages) = &kinds[(n / 2) % kinds.len()];
                (crate::crash::job(kind, sha, n, stages), stages.clone())
            } else {
                (job_body(&sha, n), vec!["execute", "report"])
            }
        })
        .collect();

    // Submissions and kills at once.
    let started = Instant::now();
    let submitter = {
        let (rest, grpc, sha) = (rest.clone(), grpc.clone(), sha.clone());
        let bodies: Vec<Value> = plan.iter().map(|(b, _)| b.clone()).collect();
        tokio::spawn(async move {
            let mut ids = Vec::with_capacity(jobs);
            for (n, body) in bodies.iter().enumerate() {
                ids.push(submit(&rest, &grpc, &sha, body, n).await?);
                tokio::time::sleep(Duration::from_millis(50)).await;
            }
            anyhow::Ok(ids)
        })
    };
    let mut killed = BTreeMap::<String, usize>::new();
    for _ in 0..kills {
        let (pause, victim) = {
            let mut rng = rand::rng();
            (rng.random_range(300..1500), rng.random_range(0..procs.len()))
        };
        tokio::time::sleep(Duration::from_millis(pause)).await;
        let p = &mut procs[victim];
        p.kill()?;
        *killed.entry(p.name.clone()).or_default() += 1;
        tokio::time::sleep(Duration::from_millis(300)).await;
        p.start().await?;
    }
    let ids = submitter.await??;

    // Every job ends, succeeded.
    let deadline = Instant::now() + Duration::from_secs(300);
    let mut ended = BTreeMap::new();
    while ended.len() < ids.len() {
        for (n, id) in ids.iter().enumerate() {
            if ended.contains_key(id) {
                continue;
            }
            let r = rest[n % rest.len()];
            let job: Value = http.get(format!("http://{r}/v1/jobs/{id}")).send().await?.json().await?;
            if matches!(job["status"].as_str(), Some("succeeded" | "failed" | "cancelled")) {
                ended.insert(id.clone(), job);
            }
        }
        if Instant::now() > deadline {
            let logs: Vec<String> =
                procs.iter().map(|p| format!("== {}\n{}", p.name, tail(&p.log))).collect();
            bail!("{} of {} jobs ended in time\n{}", ended.len(), ids.len(), logs.join("\n"));
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    let wall = started.elapsed();

    // None lost, none twice: the replicas list exactly the jobs submitted, once each.
    let listed: Value =
        http.get(format!("http://{}/v1/jobs?limit=1000", rest[1])).send().await?.json().await?;
    let mut listed_ids: Vec<&str> =
        listed["jobs"].as_array().context("jobs")?.iter().filter_map(|j| j["id"].as_str()).collect();
    listed_ids.sort_unstable();
    let mut submitted: Vec<&str> = ids.iter().map(String::as_str).collect();
    submitted.sort_unstable();
    ensure!(listed_ids == submitted, "listed {listed_ids:?}, submitted {submitted:?}");

    let store = depthmill_orchestrator::store::open(&db.url()).await?;
    let (mut interrupted, mut retried) = (0, 0);
    let chains: BTreeMap<&str, &Vec<&str>> =
        ids.iter().map(String::as_str).zip(plan.iter().map(|(_, c)| c)).collect();
    for (id, job) in &ended {
        ensure!(job["status"] == "succeeded", "job {id} did not succeed: {job}");
        let results = store.stage_results(id).await?;
        let mut stages: Vec<&str> = results.iter().map(|r| r.stage.as_str()).collect();
        let mut chain: Vec<&str> = chains.get(id.as_str()).map(|c| c.to_vec()).unwrap_or_default();
        stages.sort_unstable();
        chain.sort_unstable();
        ensure!(stages == chain, "job {id}: stages recorded {stages:?}, its chain is {chain:?}");
        let attempts = job["attempts"].as_array().context("attempts")?;
        let ok_executes = attempts.iter().filter(|a| a["stage"] == "execute" && a["outcome"] == "ok").count();
        ensure!(ok_executes == 1, "job {id}: {ok_executes} successful execute attempts: {attempts:?}");
        interrupted += attempts.iter().filter(|a| a["outcome"] == "interrupted").count();
        retried += attempts.len().saturating_sub(chain.len());
        // Every artifact is complete: its bytes hash to its name.
        for (name, a) in job["artifacts"].as_object().context("artifacts")? {
            let sha = a["sha256"].as_str().context("sha256")?;
            let bytes =
                http.get(format!("http://{}/v1/artifacts/{sha}", rest[2])).send().await?.bytes().await?;
            ensure!(
                hex::encode(Sha256::digest(&bytes)) == sha,
                "job {id}: artifact {name} does not match its hash"
            );
        }
    }
    println!(
        "replicas: {} jobs (every kind) over 3 replicas and 2 instances of each stage service in {:.1} s; {} kills ({killed:?}); \
         lost 0, duplicated 0, failed 0; {interrupted} attempts interrupted, {retried} extra attempts",
        ids.len(),
        wall.as_secs_f64(),
        kills
    );
    for p in &mut procs {
        p.kill()?;
    }
    drop(store);
    drop(s3);
    Ok(())
}
