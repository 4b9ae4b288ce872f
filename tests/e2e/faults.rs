//! Fault campaign on a stage service (the machine, scripted): slowed past the stage deadline, and
//! failing mid-stage after it started and reported progress, transiently and for good. Each job
//! ends succeeded or failed with a named error, within what the deadlines and the attempt budget
//! allow (no hang), and the service keeps serving the next job. (A service that is stopped is
//! `whole::a_job_outlives_a_stage_service_going_down_and_coming_back` and
//! `jobs::a_stage_without_its_service_fails_the_job_clearly`; errors at the start of a call are
//! `jobs::transient_errors_are_retried_and_invalid_arguments_are_not`.)

use std::time::Duration;

use anyhow::Context as _;
use depthmill_tests::scripted::Script;
use depthmill_tests::{MachineBackend, StackOptions, TestStack};
use serde_json::Value;

use crate::{gcode_job, program};

fn outcomes(job: &Value) -> Vec<String> {
    job["attempts"]
        .as_array()
        .into_iter()
        .flatten()
        .map(|a| format!("{}:{}", a["stage"].as_str().unwrap_or("?"), a["outcome"].as_str().unwrap_or("?")))
        .collect()
}

/// A stack whose machine takes 30 s per program, with `attempts` attempts of `deadline_s` each,
/// and a G-code job run on it to its end: it must fail `deadline_exceeded` at the execute stage with
/// every attempt ended by the deadline, not by the service (nor taken for a cancel). Returns the
/// stack, its script, the program's digest and the ended job.
async fn job_slowed_past_its_deadline(
    deadline_s: f64,
    attempts: u32,
) -> anyhow::Result<(TestStack, Script, String, Value)> {
    let script = Script::default();
    let stack = TestStack::start_with(StackOptions {
        machine: MachineBackend::Scripted(script.clone()),
        stage_deadline_s: deadline_s,
        max_attempts: attempts,
        ..Default::default()
    })
    .await?;
    let sha = stack.upload("text/x-gcode", program()).await?;
    script.set_delay(Duration::from_secs(30));
    let (_, job) = stack.post_job(&gcode_job(&sha), None).await?;
    let id = job["id"].as_str().context("id")?.to_string();
    let done = stack.wait_for_end(&id, Duration::from_secs(60)).await?;
    assert_eq!(done["status"], "failed", "{done}");
    assert_eq!(done["error"]["code"], "deadline_exceeded", "{done}");
    assert_eq!(done["error"]["stage"], "execute", "{done}");
    assert_eq!(done["cancel_requested"], false, "{done}");
    assert_eq!(outcomes(&done).len(), attempts as usize, "{done}");
    let codes: Vec<&str> =
        done["attempts"].as_array().into_iter().flatten().filter_map(|a| a["error_code"].as_str()).collect();
    assert_eq!(codes, vec!["deadline_exceeded"; attempts as usize], "{done}");
    Ok((stack, script, sha, done))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stage_slowed_past_its_deadline_fails_in_bounded_time_and_the_service_goes_on() -> anyhow::Result<()>
{
    // Slower than the deadline: every attempt times out, and the job ends well inside the wait.
    let (stack, script, sha, done) = job_slowed_past_its_deadline(1.0, 3).await?;
    let message = done["error"]["message"].as_str().unwrap_or_default();
    assert!(message.contains("gave up after 3 attempts"), "{message}");

    // Back to normal speed: the next job runs.
    script.set_delay(Duration::ZERO);
    let (_, job) = stack.post_job(&gcode_job(&sha), None).await?;
    let done = stack.wait_for_end(job["id"].as_str().context("id")?, Duration::from_secs(30)).await?;
    assert_eq!(done["status"], "succeeded", "{done}");
    stack.shutdown().await
}

/// Attempts cut short by a deadline under a third of the lease (the lease's renewal period), more of
/// them than one lease lasts: the worker must renew its lease as each attempt starts and across the
/// waits between them, or a second worker loop claims the job and the first one's run is taken for a
/// cancel (the job ended `cancelled` with nobody cancelling it).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn retries_longer_than_a_lease_keep_the_job() -> anyhow::Result<()> {
    // Lease 3 s (the test stack's), deadline 0.4 s, 12 attempts: about 5 s of attempts.
    let (stack, ..) = job_slowed_past_its_deadline(0.4, 12).await?;
    stack.shutdown().await
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn errors_in_the_middle_of_a_stage_are_retried_or_named_and_the_service_goes_on() -> anyhow::Result<()>
{
    let script = Script::default();
    let stack = TestStack::start_with(StackOptions {
        machine: MachineBackend::Scripted(script.clone()),
        ..Default::default()
    })
    .await?;
    let sha = stack.upload("text/x-gcode", program()).await?;

    // Two runs drop out after they started: retried, the third finishes.
    script.fail_mid_next(2);
    let (_, job) = stack.post_job(&gcode_job(&sha), None).await?;
    let done = stack.wait_for_end(job["id"].as_str().context("id")?, Duration::from_secs(30)).await?;
    assert_eq!(done["status"], "succeeded", "{done}");
    assert_eq!(outcomes(&done), ["execute:retry", "execute:retry", "execute:ok", "report:ok"], "{done}");
    assert_eq!(done["attempts"][0]["error_code"], "unavailable");
    assert!(
        done["attempts"][0]["error_message"].as_str().unwrap_or_default().contains("dropped out mid-run"),
        "{done}"
    );

    // A fault the service reports as internal mid-run: the job fails at once with it, named.
    script.fault_mid(Some("scripted: axis amplifier fault"));
    let (_, job) = stack.post_job(&gcode_job(&sha), None).await?;
    let done = stack.wait_for_end(job["id"].as_str().context("id")?, Duration::from_secs(30)).await?;
    assert_eq!(done["status"], "failed", "{done}");
    assert_eq!(done["error"]["stage"], "execute");
    assert!(done["error"]["message"].as_str().unwrap_or_default().contains("axis amplifier fault"), "{done}");

    // The fault cleared: the next job runs.
    script.fault_mid(None);
    let (_, job) = stack.post_job(&gcode_job(&sha), None).await?;
    let done = stack.wait_for_end(job["id"].as_str().context("id")?, Duration::from_secs(30)).await?;
    assert_eq!(done["status"], "succeeded", "{done}");
    stack.shutdown().await
}
