//! The machine service on its own contract: stop and emergency stop during a run, and the next
//! job afterwards.

use std::fmt::Write as _;
use std::time::Duration;

use depthmill_proto::machine::v1 as pb;
use depthmill_proto::machine::v1::machine_service_client::MachineServiceClient;
use depthmill_tests::TestStack;
use serde_json::json;

/// A long slotting program: 200 passes across a 30 x 20 mm block, 0.2 mm deeper each time.
fn long_program() -> Vec<u8> {
    let mut s = String::from("%\nG21 G90 G17 G94\nT1 M6\nS1500 M3\nG43 H1\nG0 X-5 Y5\nG0 Z12\n");
    // Long enough (2400 passes, about 2 s of simulation) that the run is still going when the
    // test looks, after a pause of up to 400 ms.
    for k in 0..2400 {
        let z = 10.0 - 0.0042 * f64::from(k);
        let _ = writeln!(s, "G1 Z{z:.3} F100");
        let _ = writeln!(s, "G1 X{} F300", if k % 2 == 0 { 35 } else { -5 });
    }
    s.push_str("G0 Z15\nM30\n%\n");
    s.into_bytes()
}

fn job(sha: &str) -> serde_json::Value {
    json!({"input": {"kind": "gcode", "artifact": sha},
           "execute": {"machine": "emco-f1", "adaptive": "off", "compare": false, "cell_mm": 0.2}})
}

async fn machine(stack: &TestStack) -> anyhow::Result<MachineServiceClient<depthmill_tests::ServiceChannel>> {
    let url = stack
        .service_urls()
        .into_iter()
        .find(|(name, _)| name == "depthmill.machine.v1.MachineService")
        .map(|(_, url)| url)
        .ok_or_else(|| anyhow::anyhow!("no machine service"))?;
    Ok(MachineServiceClient::new(depthmill_tests::service_channel(url).await?))
}

async fn wait_running(
    m: &mut MachineServiceClient<depthmill_tests::ServiceChannel>,
) -> anyhow::Result<pb::MachineStatus> {
    for _ in 0..3000 {
        let s = m.get_status(pb::GetStatusRequest {}).await?.into_inner();
        if s.state == "running" && s.line > 20 {
            return Ok(s);
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    anyhow::bail!("the machine never got going")
}

#[tokio::test]
async fn stop_and_emergency_stop_end_a_run_and_the_next_job_runs_normally() -> anyhow::Result<()> {
    let stack = TestStack::start().await?;
    let mut m = machine(&stack).await?;
    assert_eq!(m.get_status(pb::GetStatusRequest {}).await?.into_inner().state, "idle");
    let sha = stack.upload("text/x-gcode", long_program()).await?;

    // Stop: feed hold and end of program at the next line.
    let (_, created) = stack.post_job(&job(&sha), None).await?;
    let running = wait_running(&mut m).await?;
    assert!(!running.job_id.is_empty());
    m.stop(pb::StopRequest {}).await?;
    let done = stack.wait_for_end(created["id"].as_str().expect("id"), Duration::from_secs(120)).await?;
    assert_eq!(done["status"], "cancelled", "{done}");
    assert_eq!(done["error"]["code"], "cancelled", "{done}");
    assert!(done["error"]["message"].as_str().unwrap_or_default().contains("stopped at line"), "{done}");
    let s = m.get_status(pb::GetStatusRequest {}).await?.into_inner();
    assert_eq!(s.state, "stopped");
    assert!(s.line >= running.line, "the status keeps where it stopped");

    // Emergency stop during the next run: latched until the next program starts.
    let (_, created) = stack.post_job(&job(&sha), None).await?;
    wait_running(&mut m).await?;
    let s = m.reset(pb::ResetRequest {}).await?.into_inner();
    assert_eq!(s.state, "estop");
    let done = stack.wait_for_end(created["id"].as_str().expect("id"), Duration::from_secs(120)).await?;
    assert_eq!(done["status"], "cancelled", "{done}");
    assert!(done["error"]["message"].as_str().unwrap_or_default().contains("emergency stop"), "{done}");
    assert_eq!(m.get_status(pb::GetStatusRequest {}).await?.into_inner().state, "estop");

    // The next job runs to the end.
    let short = b"%\nG21 G90\nT1 M6\nS1500 M3\nG43 H1\nG0 X-5 Y5\nG0 Z12\nG1 Z9.5 F100\nG1 X35 F300\nG0 Z15\nM30\n%\n";
    let sha = stack.upload("text/x-gcode", short.to_vec()).await?;
    let (_, created) = stack.post_job(&job(&sha), None).await?;
    let done = stack.wait_for_end(created["id"].as_str().expect("id"), Duration::from_secs(120)).await?;
    assert_eq!(done["status"], "succeeded", "{done}");
    assert!(done["artifacts"]["final_stock"]["sha256"].is_string());
    assert_eq!(m.get_status(pb::GetStatusRequest {}).await?.into_inner().state, "idle");
    stack.shutdown().await
}

#[tokio::test]
async fn a_program_sent_while_another_runs_waits_for_the_machine_instead_of_failing() -> anyhow::Result<()> {
    let stack = TestStack::start().await?;
    let mut m = machine(&stack).await?;
    let sha = stack.upload("text/x-gcode", long_program()).await?;
    let (_, first) = stack.post_job(&job(&sha), None).await?;
    wait_running(&mut m).await?;
    // The worker runs two jobs at once: the second reaches the machine while the first runs.
    let (_, second) = stack.post_job(&job(&sha), None).await?;
    let second_id = second["id"].as_str().expect("id").to_string();
    let mut waited = false;
    for _ in 0..500 {
        let j = stack.get_job(&second_id).await?;
        if j["stage"] == "execute"
            && m.get_status(pb::GetStatusRequest {}).await?.into_inner().job_id != second_id
        {
            waited = true;
            break;
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    assert!(waited, "the second job never reached the machine while the first ran");
    for id in [first["id"].as_str().expect("id"), second_id.as_str()] {
        let done = stack.wait_for_end(id, Duration::from_secs(300)).await?;
        assert_eq!(done["status"], "succeeded", "{done}");
        // One attempt each: the machine queued the second program, nothing was retried.
        let attempts: Vec<&serde_json::Value> =
            done["attempts"].as_array().into_iter().flatten().filter(|a| a["stage"] == "execute").collect();
        assert_eq!(attempts.len(), 1, "{done}");
    }
    stack.shutdown().await
}

/// Emergency stop at random moments of a run: each time the job ends cancelled naming the
/// emergency stop, keeps no half-made result (no final stock), the machine reports the latched
/// stop, and the next job runs to the end from a clean state.
#[tokio::test]
async fn emergency_stops_at_random_moments_leave_a_consistent_machine() -> anyhow::Result<()> {
    use rand::Rng as _;
    let stack = TestStack::start().await?;
    let mut m = machine(&stack).await?;
    let long = stack.upload("text/x-gcode", long_program()).await?;
    let short = b"%\nG21 G90\nT1 M6\nS1500 M3\nG43 H1\nG0 X-5 Y5\nG0 Z12\nG1 Z9.5 F100\nG1 X35 F300\nG0 Z15\nM30\n%\n";
    let short = stack.upload("text/x-gcode", short.to_vec()).await?;
    for round in 0..4 {
        let (_, created) = stack.post_job(&job(&long), None).await?;
        wait_running(&mut m).await?;
        let pause = rand::rng().random_range(0..400);
        tokio::time::sleep(Duration::from_millis(pause)).await;
        let s = m.reset(pb::ResetRequest {}).await?.into_inner();
        assert_eq!(s.state, "estop", "round {round}");
        let done = stack.wait_for_end(created["id"].as_str().expect("id"), Duration::from_secs(120)).await?;
        assert_eq!(done["status"], "cancelled", "round {round} after {pause} ms: {done}");
        assert!(done["error"]["message"].as_str().unwrap_or_default().contains("emergency stop"), "{done}");
        assert!(
            done["artifacts"].get("final_stock").is_none(),
            "round {round}: a stopped run left a result: {done}"
        );
        assert_eq!(m.get_status(pb::GetStatusRequest {}).await?.into_inner().state, "estop");

        let (_, created) = stack.post_job(&job(&short), None).await?;
        let done = stack.wait_for_end(created["id"].as_str().expect("id"), Duration::from_secs(120)).await?;
        assert_eq!(done["status"], "succeeded", "round {round}: {done}");
        assert!(done["artifacts"]["final_stock"]["sha256"].is_string());
        assert_eq!(m.get_status(pb::GetStatusRequest {}).await?.into_inner().state, "idle");
    }
    stack.shutdown().await
}
