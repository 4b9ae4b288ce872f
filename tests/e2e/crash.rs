//! Crash campaign: the real `depthmill serve` (the embedded stack, `depthmill_cli::embedded`) runs
//! as a child process and is killed with SIGKILL at random moments while jobs of every kind (mesh,
//! point cloud, depth map, G-code) arrive, then restarted on the same data folder. After each
//! restart every accepted job is still there and the database passes `PRAGMA integrity_check`; at
//! the end every job has succeeded, each stage of its chain is recorded once, and every artifact's
//! bytes hash to its name.
//!
//! Size: `DEPTHMILL_CRASH_KILLS` (default 20) and `DEPTHMILL_CRASH_JOBS` (default 24); the documented
//! full run is 200 kills and 200 jobs (README, "Crash campaign").

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{Context as _, bail, ensure};
use rand::Rng as _;
use serde_json::{Value, json};
use sha2::{Digest as _, Sha256};
use sqlx::Connection as _;

use crate::children::{Proc, Role, env_usize, free_addr, tail};

/// An input file and what its job runs.
pub(crate) struct Input {
    pub(crate) kind: &'static str,
    pub(crate) media_type: &'static str,
    pub(crate) bytes: Vec<u8>,
    pub(crate) stages: Vec<&'static str>,
}

/// One input of each kind.
pub(crate) fn inputs() -> anyhow::Result<Vec<Input>> {
    let mut program = String::from("%\nG21 G90 G17 G94\nT1 M6\nS1500 M3\nG43 H1\nG0 X-5 Y5\nG0 Z12\n");
    for k in 0..20u32 {
        let _ = writeln!(program, "G1 Z{:.2} F200", 10.0 - 0.1 * f64::from(k));
        let _ = writeln!(program, "G1 X{} F300", if k.is_multiple_of(2) { 35 } else { -5 });
    }
    program.push_str("G0 Z15\nM30\n%\n");
    // A dome sampled every 0.5 mm over 24 x 20 mm, as a range scanner's XYZ file.
    let mut cloud = String::new();
    for r in 0..40 {
        for c in 0..48 {
            let (x, y) = (f64::from(c) * 0.5 - 12.0, f64::from(r) * 0.5 - 10.0);
            let d2 = x * x + y * y;
            let z = 2.0 + if d2 < 49.0 { (49.0 - d2).sqrt() } else { 0.0 };
            let _ = writeln!(cloud, "{x:.3} {y:.3} {z:.3}");
        }
    }
    let input = |kind, media_type, bytes, stages| Input { kind, media_type, bytes, stages };
    Ok(vec![
        input("gcode", "text/x-gcode", program.into_bytes(), vec!["execute", "report"]),
        input("depth_map", "image/png", crate::plan::dome_png()?, vec!["plan", "execute", "report"]),
        input(
            "point_cloud",
            "text/x-xyz",
            cloud.into_bytes(),
            vec!["reconstruct", "plan", "execute", "report"],
        ),
        input(
            "mesh",
            "model/stl",
            crate::scan::dome_stl(),
            vec!["scan", "reconstruct", "plan", "execute", "report"],
        ),
    ])
}

/// A job of `kind` with the sections of the stages it runs (a section for a stage it skips is
/// refused).
pub(crate) fn job(kind: &str, sha: &str, n: usize, stages: &[&str]) -> Value {
    let sections = json!({
        "scan": {"table_angles_deg": [0], "line_spacing_mm": 1.0},
        "reconstruct": {"pixel_mm": 0.5},
        "plan": {"stock": {"z_mm": 10}, "roughing": {"tool": "flat-6", "step_down_mm": 3.0},
                 "finishing": {"tool": "ball-6", "step_over_mm": 2.0}},
        "execute": {"machine": "emco-f1", "adaptive": "off", "compare": false, "cell_mm": 0.5}
    });
    let mut body = json!({"name": format!("crash-{n}-{kind}"), "input": {"kind": kind, "artifact": sha}});
    for stage in stages {
        if let Some(section) = sections.get(*stage) {
            body[*stage] = section.clone();
        }
    }
    body
}

async fn integrity(db: &std::path::Path) -> anyhow::Result<String> {
    let mut conn = sqlx::SqliteConnection::connect(&format!("sqlite://{}?mode=ro", db.display())).await?;
    let (answer,): (String,) = sqlx::query_as("PRAGMA integrity_check").fetch_one(&mut conn).await?;
    conn.close().await?;
    Ok(answer)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn serve_killed_at_random_loses_nothing() -> anyhow::Result<()> {
    let kills = env_usize("DEPTHMILL_CRASH_KILLS", 20);
    let jobs = env_usize("DEPTHMILL_CRASH_JOBS", 24);
    let root = tempfile::tempdir()?;
    let data_dir = root.path().join("data");
    let config = root.path().join("orchestrator.toml");
    std::fs::write(
        &config,
        "[worker]\nmax_attempts = 50\nbackoff_min_ms = 50\nbackoff_max_ms = 500\npoll_ms = 100\n",
    )?;
    let (rest, grpc) = (free_addr()?, free_addr()?);
    let role = Role::Serve { data_dir: data_dir.clone(), rest, grpc, config: Some(config) };
    let mut serve = Proc::new("serve", &role, rest, true, root.path().join("serve.log"))?;
    serve.start().await?;

    let http = depthmill_common::tls::http_client().timeout(Duration::from_secs(20)).build()?;
    let inputs = inputs()?;
    let mut shas = Vec::new();
    for input in &inputs {
        let up: Value = http
            .post(format!("http://{rest}/v1/artifacts"))
            .header("content-type", input.media_type)
            .body(input.bytes.clone())
            .send()
            .await?
            .json()
            .await?;
        shas.push(up["sha256"].as_str().context("upload")?.to_string());
    }

    // Submissions run beside the kills; a submission cut by a kill is retried with its key.
    let accepted: Arc<Mutex<Vec<(String, usize)>>> = Arc::default();
    let submitter = {
        let (accepted, http, shas) = (accepted.clone(), http.clone(), shas.clone());
        let kinds: Vec<(&'static str, Vec<&'static str>)> =
            inputs.iter().map(|i| (i.kind, i.stages.clone())).collect();
        tokio::spawn(async move {
            for n in 0..jobs {
                let k = n % kinds.len();
                let deadline = Instant::now() + Duration::from_secs(120);
                loop {
                    let resp = http
                        .post(format!("http://{rest}/v1/jobs"))
                        .header("Idempotency-Key", format!("crash-{n}"))
                        .json(&job(kinds[k].0, &shas[k], n, &kinds[k].1))
                        .send()
                        .await;
                    match resp {
                        Ok(r) if r.status().is_success() => {
                            let body: Value = r.json().await?;
                            let id = body["id"].as_str().context("id")?.to_string();
                            if let Ok(mut a) = accepted.lock() {
                                a.push((id, k));
                            }
                            break;
                        }
                        Ok(r) if r.status().is_client_error() => {
                            bail!("job {n} refused: {}", r.text().await?)
                        }
                        _ if Instant::now() > deadline => bail!("job {n} could not be submitted"),
                        _ => tokio::time::sleep(Duration::from_millis(100)).await,
                    }
                }
                tokio::time::sleep(Duration::from_millis(300)).await;
            }
            anyhow::Ok(())
        })
    };

    let db = data_dir.join("jobs.sqlite");
    let started = Instant::now();
    for _ in 0..kills {
        let pause = rand::rng().random_range(200..1500);
        tokio::time::sleep(Duration::from_millis(pause)).await;
        serve.kill()?;
        serve.start().await?;
        // Every job accepted so far is still there; the database is intact.
        let known: Vec<String> =
            accepted.lock().map(|a| a.iter().map(|(id, _)| id.clone()).collect()).unwrap_or_default();
        for id in &known {
            let status = http.get(format!("http://{rest}/v1/jobs/{id}")).send().await?.status();
            ensure!(status.is_success(), "accepted job {id} is gone after a restart ({status})");
        }
        let check = integrity(&db).await?;
        ensure!(check == "ok", "integrity_check after a restart: {check}");
    }
    submitter.await??;
    let accepted = accepted.lock().map(|a| a.clone()).unwrap_or_default();

    // Every job ends, succeeded.
    let deadline = Instant::now() + Duration::from_secs(600);
    let mut ended = BTreeMap::new();
    while ended.len() < accepted.len() {
        for (id, k) in &accepted {
            if ended.contains_key(id) {
                continue;
            }
            let job: Value = http.get(format!("http://{rest}/v1/jobs/{id}")).send().await?.json().await?;
            if matches!(job["status"].as_str(), Some("succeeded" | "failed" | "cancelled")) {
                ended.insert(id.clone(), (job, *k));
            }
        }
        if Instant::now() > deadline {
            bail!(
                "{} of {} jobs ended in time; serve's log:\n{}",
                ended.len(),
                accepted.len(),
                tail(&serve.log)
            );
        }
        tokio::time::sleep(Duration::from_millis(250)).await;
    }
    let wall = started.elapsed();

    let listed: Value = http.get(format!("http://{rest}/v1/jobs?limit=1000")).send().await?.json().await?;
    ensure!(
        listed["jobs"].as_array().map(Vec::len) == Some(accepted.len()),
        "{} jobs listed, {} accepted",
        listed["jobs"].as_array().map_or(0, Vec::len),
        accepted.len()
    );
    let store = depthmill_orchestrator::store::open(&format!("sqlite://{}", db.display())).await?;
    let mut extra_attempts = 0;
    for (id, (job, k)) in &ended {
        ensure!(job["status"] == "succeeded", "job {id} did not succeed: {job}");
        let stages: Vec<&str> = store.stage_results(id).await?.iter().map(|r| r.stage.as_str()).collect();
        ensure!(stages == inputs[*k].stages, "job {id} ({}): stages recorded {stages:?}", inputs[*k].kind);
        extra_attempts += job["attempts"].as_array().map_or(0, Vec::len).saturating_sub(stages.len());
        for (name, a) in job["artifacts"].as_object().context("artifacts")? {
            let sha = a["sha256"].as_str().context("sha256")?;
            let bytes = http.get(format!("http://{rest}/v1/artifacts/{sha}")).send().await?.bytes().await?;
            ensure!(
                hex::encode(Sha256::digest(&bytes)) == sha,
                "job {id}: artifact {name} does not match its hash"
            );
        }
    }
    drop(store);
    serve.kill()?;
    ensure!(integrity(&db).await? == "ok", "integrity_check at the end");
    println!(
        "crash: {kills} SIGKILLs of depthmill serve, {} jobs (every kind) in {:.1} s; lost 0, duplicated 0, \
         failed 0; {extra_attempts} extra attempts; integrity_check ok after every restart",
        accepted.len(),
        wall.as_secs_f64()
    );
    Ok(())
}
