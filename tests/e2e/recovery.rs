//! Restart recovery: the orchestrator stops mid-stage; a new one on the same data finishes the job
//! once. On both job stores: SQLite in the data folder and a scratch PostgreSQL database.

use std::time::Duration;

use depthmill_orchestrator::store::scratch::ScratchDatabase;
use depthmill_tests::scripted::Script;
use depthmill_tests::{MachineBackend, StackOptions, TestStack};
use serde_json::Value;

use crate::{gcode_job, program};

#[tokio::test]
async fn a_job_interrupted_by_a_restart_finishes_once() -> anyhow::Result<()> {
    restart_mid_stage(None).await
}

#[tokio::test]
async fn a_job_interrupted_by_a_restart_finishes_once_on_postgres() -> anyhow::Result<()> {
    let db = ScratchDatabase::create().await?;
    restart_mid_stage(Some(db.url())).await
}

async fn restart_mid_stage(database_url: Option<String>) -> anyhow::Result<()> {
    let script = Script::default();
    script.hold(true);
    let mut stack = TestStack::start_with(StackOptions {
        machine: MachineBackend::Scripted(script.clone()),
        database_url,
        ..Default::default()
    })
    .await?;
    let sha = stack.upload("text/x-gcode", program()).await?;
    let (_, job) = stack.post_job(&gcode_job(&sha), None).await?;
    let id = job["id"].as_str().expect("id").to_string();
    let (_, queued) = stack.post_job(&gcode_job(&sha), Some("second")).await?;
    let queued_id = queued["id"].as_str().expect("id").to_string();
    // Both jobs in their stage (the stack's worker runs two at once; which call comes first is
    // a race, so wait for both).
    script.wait_for_calls(2, Duration::from_secs(20)).await?;

    // The orchestrator dies while the machine runs both jobs' stage.
    stack.stop_orchestrator().await?;
    script.hold(false);
    script.release();
    stack.restart_orchestrator().await?;

    let first = stack.wait_for_end(&id, Duration::from_secs(20)).await?;
    let second = stack.wait_for_end(&queued_id, Duration::from_secs(20)).await?;
    for job in [&first, &second] {
        assert_eq!(job["status"], "succeeded", "{job}");
        let stages: Vec<&str> = job["stage_timings_s"]
            .as_object()
            .map(|m| m.keys().map(String::as_str).collect())
            .unwrap_or_default();
        assert_eq!(stages, ["execute", "report"], "each stage recorded once");
    }
    let outcomes: Vec<(String, String)> = first["attempts"]
        .as_array()
        .expect("attempts")
        .iter()
        .map(|a: &Value| {
            (a["stage"].as_str().unwrap_or("").to_string(), a["outcome"].as_str().unwrap_or("").to_string())
        })
        .collect();
    let executes: Vec<&str> =
        outcomes.iter().filter(|(s, _)| s == "execute").map(|(_, o)| o.as_str()).collect();
    assert!(executes.len() >= 2, "{outcomes:?}");
    // The attempt the restart cut ends `interrupted` (the restarted orchestrator finds its lease)
    // or `retry` (the stopping one saw the call break first); on a loaded machine an earlier
    // attempt may also have ended `retry`. Then one attempt ran the stage, once.
    assert!(
        executes[..executes.len() - 1].iter().all(|o| *o == "interrupted" || *o == "retry"),
        "{outcomes:?}"
    );
    assert_eq!(executes.last().copied(), Some("ok"), "{outcomes:?}");
    assert_eq!(executes.iter().filter(|o| **o == "ok").count(), 1, "{outcomes:?}");
    assert_eq!(outcomes.iter().filter(|(s, o)| s == "report" && o == "ok").count(), 1);

    // Jobs listed once each.
    let list: Value = stack.http.get(stack.url("/v1/jobs")).send().await?.json().await?;
    assert_eq!(list["jobs"].as_array().map(Vec::len), Some(2));
    stack.shutdown().await
}
