//! Jobs through REST and gRPC: run, watch, list, idempotency, retries, rejection, cancel.

use std::time::Duration;

use depthmill_proto::orchestrator::v1 as pb;
use depthmill_tests::scripted::Script;
use depthmill_tests::{MachineBackend, StackOptions, TestStack};
use futures::StreamExt as _;
use serde_json::{Value, json};

use crate::{gcode_job, program};

const WAIT: Duration = Duration::from_secs(20);

fn scripted(script: &Script) -> StackOptions {
    StackOptions { machine: MachineBackend::Scripted(script.clone()), ..Default::default() }
}

fn outcomes(job: &Value) -> Vec<String> {
    job["attempts"]
        .as_array()
        .map(|a| {
            a.iter()
                .map(|x| {
                    format!("{}:{}", x["stage"].as_str().unwrap_or("?"), x["outcome"].as_str().unwrap_or("?"))
                })
                .collect()
        })
        .unwrap_or_default()
}

/// Reads server-sent events until the job ends; returns every job snapshot received.
async fn follow_events(stack: &TestStack, id: &str) -> anyhow::Result<Vec<Value>> {
    let resp = stack.http.get(stack.url(&format!("/v1/jobs/{id}/events"))).send().await?;
    assert_eq!(resp.status(), 200);
    assert!(resp.headers()["content-type"].to_str()?.starts_with("text/event-stream"));
    let mut stream = resp.bytes_stream();
    let mut buf = String::new();
    let mut seen = Vec::new();
    let result = tokio::time::timeout(WAIT, async {
        while let Some(chunk) = stream.next().await {
            buf.push_str(&String::from_utf8_lossy(&chunk?));
            while let Some(end) = buf.find("\n\n") {
                let event: String = buf.drain(..end + 2).collect();
                if let Some(data) = event.lines().find_map(|l| l.strip_prefix("data:")) {
                    seen.push(serde_json::from_str::<Value>(data.trim())?);
                }
            }
        }
        anyhow::Ok(())
    })
    .await;
    result??;
    Ok(seen)
}

#[tokio::test]
async fn a_gcode_job_runs_to_the_end_and_is_watched_and_listed() -> anyhow::Result<()> {
    let script = Script::default();
    script.set_delay(Duration::from_millis(200));
    let stack = TestStack::start_with(scripted(&script)).await?;
    let sha = stack.upload("text/x-gcode", program()).await?;
    let (status, job) = stack.post_job(&gcode_job(&sha), None).await?;
    assert_eq!(status, 201, "{job}");
    let id = job["id"].as_str().expect("id").to_string();
    assert_eq!(job["stage"], "execute");

    let events = follow_events(&stack, &id).await?;
    let last = events.last().expect("events");
    assert_eq!(last["status"], "succeeded", "{last}");
    // Progress only moves forward, and the stream saw the job before it ended.
    assert!(events.len() >= 2, "{events:?}");
    let progress: Vec<f64> = events.iter().map(|e| e["progress"].as_f64().unwrap_or(-1.0)).collect();
    assert!(progress.windows(2).all(|w| w[0] <= w[1]), "{progress:?}");
    assert_eq!(progress.last().copied(), Some(1.0));

    let job = stack.get_job(&id).await?;
    assert_eq!(job["status"], "succeeded");
    assert_eq!(job["stage"], "report");
    assert!(job["stage_timings_s"]["execute"].as_f64().unwrap_or(0.0) >= 0.2, "{job}");
    assert!(job["stage_timings_s"]["report"].is_number());
    for name in ["gcode", "telemetry", "report"] {
        assert!(job["artifacts"][name]["sha256"].is_string(), "{name} missing: {job}");
    }
    assert_eq!(job["metrics"]["cycle_time_s"].as_f64(), Some(0.9), "9 lines at 0.1 s each");
    assert_eq!(outcomes(&job), ["execute:ok", "report:ok"]);
    assert_eq!(script.completed(), 1);

    // The report is an HTML page naming the job, with a JSON summary beside it.
    let report_sha = job["artifacts"]["report"]["sha256"].as_str().expect("report");
    let page = stack.http.get(stack.url(&format!("/v1/artifacts/{report_sha}"))).send().await?.text().await?;
    assert!(
        page.starts_with("<!DOCTYPE html>") || page.starts_with("<!doctype html>"),
        "{}",
        &page[..page.len().min(200)]
    );
    assert!(page.contains(id.as_str()), "the report names the job");
    let summary_sha = job["artifacts"]["report_json"]["sha256"].as_str().expect("report_json");
    let summary: Value =
        stack.http.get(stack.url(&format!("/v1/artifacts/{summary_sha}"))).send().await?.json().await?;
    assert_eq!(summary["job"], id.as_str());

    // Listing: filter and pages.
    let (_, second) = stack.post_job(&gcode_job(&sha), None).await?;
    stack.wait_for_end(second["id"].as_str().expect("id"), WAIT).await?;
    let page: Value =
        stack.http.get(stack.url("/v1/jobs?status=succeeded&limit=1")).send().await?.json().await?;
    assert_eq!(page["jobs"].as_array().map(Vec::len), Some(1));
    assert_eq!(page["jobs"][0]["id"], second["id"], "newest first");
    let cursor = page["next_cursor"].as_str().expect("a second page");
    let page2: Value = stack
        .http
        .get(stack.url(&format!("/v1/jobs?status=succeeded&limit=1&cursor={cursor}")))
        .send()
        .await?
        .json()
        .await?;
    assert_eq!(page2["jobs"][0]["id"], id.as_str());
    assert!(page2.get("next_cursor").is_none(), "{page2}");
    let failed: Value = stack.http.get(stack.url("/v1/jobs?status=failed")).send().await?.json().await?;
    assert_eq!(failed["jobs"].as_array().map(Vec::len), Some(0));
    stack.shutdown().await
}

#[tokio::test]
async fn the_same_idempotency_key_gives_the_same_job() -> anyhow::Result<()> {
    let script = Script::default();
    let stack = TestStack::start_with(scripted(&script)).await?;
    let sha = stack.upload("text/x-gcode", program()).await?;
    let (s1, a) = stack.post_job(&gcode_job(&sha), Some("order-17")).await?;
    let (s2, b) = stack.post_job(&gcode_job(&sha), Some("order-17")).await?;
    assert_eq!((s1, s2), (201, 200));
    assert_eq!(a["id"], b["id"]);
    let mut other = gcode_job(&sha);
    other["name"] = json!("different");
    let (s3, c) = stack.post_job(&other, Some("order-17")).await?;
    assert_eq!(s3, 409, "{c}");
    assert_eq!(c["error"]["code"], "conflict");
    let list: Value = stack.http.get(stack.url("/v1/jobs")).send().await?.json().await?;
    assert_eq!(list["jobs"].as_array().map(Vec::len), Some(1));
    // gRPC shares the keys.
    let mut client = stack.grpc().await?;
    let spec = crate::gcode_spec_pb(&sha);
    let job = client
        .create_job(pb::CreateJobRequest { spec: Some(spec), idempotency_key: "order-17".into() })
        .await?
        .into_inner();
    assert_eq!(Some(job.id.as_str()), a["id"].as_str());
    stack.wait_for_end(&job.id, WAIT).await?;
    assert_eq!(script.completed(), 1, "one job, run once");
    stack.shutdown().await
}

#[tokio::test]
async fn transient_errors_are_retried_and_invalid_arguments_are_not() -> anyhow::Result<()> {
    let script = Script::default();
    script.fail_next(2);
    let stack = TestStack::start_with(scripted(&script)).await?;
    let sha = stack.upload("text/x-gcode", program()).await?;
    let (_, job) = stack.post_job(&gcode_job(&sha), None).await?;
    let job = stack.wait_for_end(job["id"].as_str().expect("id"), WAIT).await?;
    assert_eq!(job["status"], "succeeded", "{job}");
    assert_eq!(outcomes(&job), ["execute:retry", "execute:retry", "execute:ok", "report:ok"]);
    assert_eq!(job["attempts"][0]["error_code"], "unavailable");

    // More transient failures than attempts: the job fails, saying it gave up.
    script.fail_next(10);
    let (_, job) = stack.post_job(&gcode_job(&sha), None).await?;
    let job = stack.wait_for_end(job["id"].as_str().expect("id"), WAIT).await?;
    assert_eq!(job["status"], "failed");
    assert_eq!(job["error"]["code"], "unavailable");
    assert!(
        job["error"]["message"].as_str().unwrap_or_default().contains("gave up after 4 attempts"),
        "{job}"
    );
    script.fail_next(0);

    script.reject("line 3: feed F9000 is above the machine's 400 mm/min");
    let (_, job) = stack.post_job(&gcode_job(&sha), None).await?;
    let job = stack.wait_for_end(job["id"].as_str().expect("id"), WAIT).await?;
    assert_eq!(job["status"], "failed");
    assert_eq!(job["error"]["code"], "invalid_argument");
    assert_eq!(job["error"]["stage"], "execute");
    assert!(job["error"]["message"].as_str().unwrap_or_default().contains("F9000"));
    assert_eq!(outcomes(&job), ["execute:failed"]);
    stack.shutdown().await
}

/// A binary STL of one triangle.
fn one_triangle_stl() -> Vec<u8> {
    let mut b = vec![0u8; 80];
    b.extend_from_slice(&1u32.to_le_bytes());
    for v in [[0.0f32, 0.0, 1.0], [0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [0.0, 10.0, 0.0]] {
        for c in v {
            b.extend_from_slice(&c.to_le_bytes());
        }
    }
    b.extend_from_slice(&[0, 0]);
    b
}

#[tokio::test]
async fn a_stage_without_its_service_fails_the_job_clearly() -> anyhow::Result<()> {
    // A mesh goes to the scanning service, which this stack does not have.
    let stack = TestStack::start_with(StackOptions { scanning: false, ..StackOptions::default() }).await?;
    let sha = stack.upload("model/stl", one_triangle_stl()).await?;
    let (status, job) = stack.post_job(&json!({"input": {"kind": "mesh", "artifact": sha}}), None).await?;
    assert_eq!(status, 201, "{job}");
    let job = stack.wait_for_end(job["id"].as_str().expect("id"), WAIT).await?;
    assert_eq!(job["status"], "failed");
    assert_eq!(job["error"]["code"], "stage_not_available");
    assert_eq!(job["error"]["stage"], "scan");
    assert!(job["error"]["message"].as_str().unwrap_or_default().contains("scanning"), "{job}");
    assert_eq!(outcomes(&job), ["scan:failed"], "no retries for a missing stage");
    assert!(job["artifacts"].get("point_cloud").is_none(), "no fake results");
    stack.shutdown().await
}

#[tokio::test]
async fn cancel_stops_a_queued_job_at_once_and_a_running_one_through_its_service() -> anyhow::Result<()> {
    let script = Script::default();
    script.hold(true);
    let stack = TestStack::start_with(scripted(&script)).await?;
    let sha = stack.upload("text/x-gcode", program()).await?;
    let (_, job) = stack.post_job(&gcode_job(&sha), None).await?;
    let id = job["id"].as_str().expect("id").to_string();
    script.wait_for_calls(1, WAIT).await?;
    let resp = stack.http.post(stack.url(&format!("/v1/jobs/{id}/cancel"))).send().await?;
    assert_eq!(resp.status(), 200);
    let job = stack.wait_for_end(&id, WAIT).await?;
    assert_eq!(job["status"], "cancelled", "{job}");
    assert_eq!(job["error"]["code"], "cancelled");
    assert_eq!(job["error"]["stage"], "execute");
    assert_eq!(script.cancels(), 1, "the machine service was told to stop");
    assert_eq!(script.completed(), 0);
    assert!(job["artifacts"].get("report").is_none(), "no stage after the cancel");

    // Cancelling again changes nothing.
    let again: Value =
        stack.http.post(stack.url(&format!("/v1/jobs/{id}/cancel"))).send().await?.json().await?;
    assert_eq!(again["status"], "cancelled");

    // Over gRPC, watching the job end.
    let mut client = stack.grpc().await?;
    let (_, job) = stack.post_job(&gcode_job(&sha), None).await?;
    let id = job["id"].as_str().expect("id").to_string();
    script.wait_for_calls(2, WAIT).await?;
    let mut watch = client.watch_job(pb::WatchJobRequest { id: id.clone() }).await?.into_inner();
    let cancelled = client.cancel_job(pb::CancelJobRequest { id: id.clone() }).await?.into_inner();
    assert!(cancelled.cancel_requested);
    let mut last = None;
    while let Some(update) = tokio::time::timeout(WAIT, watch.next()).await? {
        last = Some(update?);
    }
    let last = last.expect("watch updates");
    assert_eq!(last.status, pb::JobStatus::Cancelled as i32);
    let unknown = client.cancel_job(pb::CancelJobRequest { id: "nope".into() }).await.expect_err("unknown");
    assert_eq!(unknown.code(), tonic::Code::NotFound);
    stack.shutdown().await
}

/// With two instances of the machine service behind the balanced endpoint list, cancelling a
/// running stage reaches the instance that runs it, whichever one that is: the orchestrator asks
/// every instance, and the one running the stage stops it. (Each call is started on a chosen
/// instance here; the cancels go through the two-instance list.)
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn cancel_reaches_the_instance_that_runs_the_stage() -> anyhow::Result<()> {
    use depthmill_common::artifacts::ArtifactStore as _;
    use depthmill_orchestrator::stages::{GrpcStages, StageCall, StageRunner as _};
    let dir = tempfile::tempdir()?;
    let store = depthmill_common::artifacts::ObjectArtifactStore::open_local(dir.path()).await?;
    let program = store.put_bytes("text/x-gcode", &crate::program()).await?;
    let (scripts, mut urls, mut stops) = (vec![Script::default(), Script::default()], Vec::new(), Vec::new());
    for script in &scripts {
        script.hold(true);
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
        urls.push(format!("http://{}", listener.local_addr()?));
        let stop = tokio_util::sync::CancellationToken::new();
        stops.push(stop.clone());
        tokio::spawn(script.clone().serve(listener, store.clone(), stop));
    }
    let stages_on = |machine: String| -> anyhow::Result<std::sync::Arc<GrpcStages>> {
        let mut endpoints = depthmill_orchestrator::Endpoints::none();
        endpoints.machine = machine;
        Ok(std::sync::Arc::new(GrpcStages::new(&endpoints)?))
    };
    let stages = stages_on(urls.join(", "))?;
    let single = [stages_on(urls[0].clone())?, stages_on(urls[1].clone())?];
    let spec: depthmill_orchestrator::domain::JobSpec =
        serde_json::from_value(json!({"input": {"kind": "gcode", "artifact": program.sha256}}))?;
    let call = |n: usize| StageCall {
        job_id: format!("job-{n}"),
        attempt: 1,
        stage: depthmill_orchestrator::domain::Stage::Execute,
        spec: spec.clone(),
        artifacts: [("gcode".to_string(), program.clone())].into_iter().collect(),
        calibration: None,
        calibrate_in_scan: false,
    };
    for round in 0..3 {
        // One call held on each instance.
        let mut running = Vec::new();
        for (i, n) in [2 * round, 2 * round + 1].into_iter().enumerate() {
            let before: u32 = scripts.iter().map(Script::calls).sum();
            let stages = single[i].clone();
            let call = call(n);
            running.push(tokio::spawn(async move {
                stages.run(&call, Duration::from_secs(30), &|_, _| {}).await
            }));
            let deadline = std::time::Instant::now() + Duration::from_secs(10);
            while scripts.iter().map(Script::calls).sum::<u32>() == before {
                anyhow::ensure!(std::time::Instant::now() < deadline, "no instance got call {n}");
                tokio::time::sleep(Duration::from_millis(10)).await;
            }
        }
        let busy: Vec<u32> = scripts.iter().map(Script::calls).collect();
        anyhow::ensure!(busy[0] == busy[1], "round {round}: calls per instance {busy:?}");
        for n in [2 * round, 2 * round + 1] {
            let stage = depthmill_orchestrator::domain::Stage::Execute;
            assert!(stages.cancel(stage, &format!("job-{n}")).await?, "call {n}: no instance knew the stage");
            let ended = tokio::time::timeout(Duration::from_secs(10), running.remove(0)).await??;
            assert!(ended.is_err(), "call {n} ran to the end after its cancel");
        }
        let cancels: Vec<u32> = scripts.iter().map(Script::cancels).collect();
        assert_eq!(cancels, vec![round as u32 + 1; 2], "each instance stopped the call it ran");
    }
    for stop in stops {
        stop.cancel();
    }
    Ok(())
}
