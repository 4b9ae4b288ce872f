//! The limit on active jobs per client (`max_active_jobs_per_client`): a client is refused past
//! it over REST (429 `quota_exceeded`) and gRPC (RESOURCE_EXHAUSTED) alike, with nothing stored;
//! a repeat of an accepted submission is still answered; an ended job frees its place; clients
//! (token ids, or addresses without tokens) are counted apart.

use std::time::Duration;

use depthmill_orchestrator::auth::{AuthConfig, AuthMode};
use depthmill_proto::orchestrator::v1 as pb;
use depthmill_tests::scripted::Script;
use depthmill_tests::{MachineBackend, StackOptions, TestStack};
use serde_json::Value;

use crate::{gcode_job, gcode_spec_pb, program};

const WAIT: Duration = Duration::from_secs(20);

async fn job_count(stack: &TestStack) -> anyhow::Result<usize> {
    let list: Value = stack.http.get(stack.url("/v1/jobs?limit=1000")).send().await?.json().await?;
    Ok(list["jobs"].as_array().map(Vec::len).unwrap_or(0))
}

#[tokio::test]
async fn a_client_past_its_active_jobs_is_refused_until_one_ends() -> anyhow::Result<()> {
    // The machine holds every job it gets: jobs stay running or queued.
    let script = Script::default();
    script.hold(true);
    let stack = TestStack::start_with(StackOptions {
        machine: MachineBackend::Scripted(script.clone()),
        max_active_jobs_per_client: 3,
        ..Default::default()
    })
    .await?;
    let sha = stack.upload("text/x-gcode", program()).await?;
    let mut ids = Vec::new();
    for i in 0..3 {
        let (status, job) = stack.post_job(&gcode_job(&sha), Some(&format!("order-{i}"))).await?;
        assert_eq!(status, 201, "{job}");
        ids.push(job["id"].as_str().unwrap_or_default().to_string());
    }
    // The fourth: refused, naming the client, the count and the setting.
    let (status, body) = stack.post_job(&gcode_job(&sha), Some("order-3")).await?;
    assert_eq!(status, 429, "{body}");
    assert_eq!(body["error"]["code"], "quota_exceeded");
    let message = body["error"]["message"].as_str().unwrap_or_default();
    assert!(
        message.contains("addr:127.0.0.1")
            && message.contains("limit is 3")
            && message.contains("max_active_jobs_per_client"),
        "{message}"
    );
    // The same client over gRPC (by its address).
    let mut grpc = stack.grpc().await?;
    let refused = grpc
        .create_job(pb::CreateJobRequest { spec: Some(gcode_spec_pb(&sha)), idempotency_key: String::new() })
        .await
        .expect_err("past the limit");
    assert_eq!(refused.code(), tonic::Code::ResourceExhausted, "{refused:?}");
    assert!(refused.message().contains("limit is 3"), "{}", refused.message());
    assert_eq!(job_count(&stack).await?, 3, "nothing stored for a refused submission");
    // A repeat of an accepted submission is answered with its job, limit or not.
    let (status, again) = stack.post_job(&gcode_job(&sha), Some("order-1")).await?;
    assert_eq!((status, again["id"].as_str()), (200, Some(ids[1].as_str())), "{again}");
    // A refused key was never used: the same key is accepted once there is room.
    let resp = stack.http.post(stack.url(&format!("/v1/jobs/{}/cancel", ids[2]))).send().await?;
    assert_eq!(resp.status(), 200);
    stack.wait_for_end(&ids[2], WAIT).await?;
    let (status, job) = stack.post_job(&gcode_job(&sha), Some("order-3")).await?;
    assert_eq!(status, 201, "{job}");
    assert_eq!(job_count(&stack).await?, 4);
    // Full again; the held jobs finish and the client may submit once more.
    let (status, _) = stack.post_job(&gcode_job(&sha), None).await?;
    assert_eq!(status, 429);
    script.hold(false);
    script.release();
    for id in &ids[..2] {
        let job = stack.wait_for_end(id, WAIT).await?;
        assert_eq!(job["status"], "succeeded", "{job}");
    }
    let job = grpc
        .create_job(pb::CreateJobRequest { spec: Some(gcode_spec_pb(&sha)), idempotency_key: String::new() })
        .await?
        .into_inner();
    assert_eq!(stack.wait_for_end(&job.id, WAIT).await?["status"], "succeeded");
    stack.shutdown().await
}

/// Twenty submissions at once against a limit of five: never more than five accepted; what is
/// stored is what was accepted; the client can then fill up to exactly five.
#[tokio::test]
async fn a_burst_of_concurrent_submissions_does_not_pass_the_limit() -> anyhow::Result<()> {
    let script = Script::default();
    script.hold(true);
    let stack = TestStack::start_with(StackOptions {
        machine: MachineBackend::Scripted(script.clone()),
        max_active_jobs_per_client: 5,
        ..Default::default()
    })
    .await?;
    let sha = stack.upload("text/x-gcode", program()).await?;
    let body = gcode_job(&sha);
    let burst = (0..20).map(|_| {
        let req = stack.http.post(stack.url("/v1/jobs")).json(&body);
        async move { anyhow::Ok(req.send().await?.status().as_u16()) }
    });
    let codes = futures::future::try_join_all(burst).await?;
    let accepted = codes.iter().filter(|c| **c == 201).count();
    assert!(codes.iter().all(|c| *c == 201 || *c == 429), "{codes:?}");
    assert!((1..=5).contains(&accepted), "{accepted} accepted: {codes:?}");
    assert_eq!(job_count(&stack).await?, accepted, "stored = accepted");
    // One at a time, up to the limit exactly.
    let mut more = 0;
    while stack.post_job(&body, None).await?.0 == 201 {
        more += 1;
        assert!(more <= 5, "past the limit");
    }
    assert_eq!(accepted + more, 5);
    script.hold(false);
    script.release();
    stack.shutdown().await
}

#[tokio::test]
async fn each_api_token_is_a_client_of_its_own() -> anyhow::Result<()> {
    let script = Script::default();
    script.hold(true);
    let stack = TestStack::start_with(StackOptions {
        machine: MachineBackend::Scripted(script.clone()),
        max_active_jobs_per_client: 1,
        auth: AuthConfig { mode: AuthMode::Tokens, cache_s: 0.0 },
        ..Default::default()
    })
    .await?;
    let cell_a = stack.issue_token("cell A", "submit").await?;
    let cell_b = stack.issue_token("cell B", "submit").await?;
    let http = depthmill_common::tls::http_client().build()?;
    let bearer = |t: &str| format!("Bearer {t}");
    let upload = http
        .post(stack.url("/v1/artifacts"))
        .header("authorization", bearer(&cell_a.token))
        .header("content-type", "text/x-gcode")
        .body(program())
        .send()
        .await?;
    assert_eq!(upload.status(), 201);
    let sha = upload.json::<Value>().await?["sha256"].as_str().unwrap_or_default().to_string();
    let submit = |token: String| {
        let req =
            http.post(stack.url("/v1/jobs")).header("authorization", bearer(&token)).json(&gcode_job(&sha));
        async move { anyhow::Ok(req.send().await?) }
    };
    assert_eq!(submit(cell_a.token.clone()).await?.status(), 201);
    let refused = submit(cell_a.token.clone()).await?;
    assert_eq!(refused.status(), 429);
    let body: Value = refused.json().await?;
    let message = body["error"]["message"].as_str().unwrap_or_default();
    assert!(message.contains(&format!("token:{}", cell_a.record.id)), "{message}");
    // Cell B has its own place.
    assert_eq!(submit(cell_b.token.clone()).await?.status(), 201);
    script.hold(false);
    script.release();
    stack.shutdown().await
}
