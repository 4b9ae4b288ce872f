//! Robot milling as a job (`"process": "robot"`): submitted over REST and gRPC from a mesh, planned
//! by the CAM service (layers, tilts, the arm's joints), replayed by the machine service on a
//! dexel stock, measured against the mesh and reported; bad robot jobs are refused naming the
//! field, and the services keep working after them.

use std::time::Duration;

use anyhow::Context as _;
use depthmill_geometry::Mesh;
use depthmill_tests::{StackOptions, TestStack};
use serde_json::{Value, json};

/// A closed block `x` x `y` x `z` mm, corner at the origin, as binary STL.
fn block_stl(x: f64, y: f64, z: f64) -> Vec<u8> {
    let mut bytes = Vec::new();
    depthmill_geometry::formats::write_stl(&mut bytes, &Mesh::cuboid(x, y, z), "robot block")
        .expect("writing to memory");
    bytes
}

fn metric(job: &Value, k: &str) -> anyhow::Result<f64> {
    job["metrics"][k].as_f64().with_context(|| format!("metric {k} in {}", job["metrics"]))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_robot_job_cuts_a_mesh_on_the_arm_and_reports_it() -> anyhow::Result<()> {
    let stack = TestStack::start_with(StackOptions { stage_deadline_s: 600.0, ..Default::default() }).await?;
    // A tall block: the holder and spindle hit it when the tool runs along its walls upright.
    let sha = stack.upload("model/stl", block_stl(20.0, 20.0, 60.0)).await?;

    // Bad robot jobs: refused at submission, naming the field, leaving no job behind.
    let cases = [
        (json!({"input": {"kind": "depth_map", "artifact": sha}, "process": "robot"}), "process"),
        (json!({"input": {"kind": "mesh", "artifact": sha}, "process": "robot", "plan": {}}), "plan"),
        (json!({"input": {"kind": "mesh", "artifact": sha}, "robot": {"step_mm": 5}}), "robot"),
        (
            json!({"input": {"kind": "mesh", "artifact": sha}, "process": "robot", "robot": {"tool": "flat-66x"}}),
            "robot.tool",
        ),
        (
            json!({"input": {"kind": "mesh", "artifact": sha}, "process": "robot", "robot": {"step_mm": 60}}),
            "robot.step_mm",
        ),
        (
            json!({"input": {"kind": "mesh", "artifact": sha}, "process": "robot", "robot": {"max_tilt_deg": 95}}),
            "robot.max_tilt_deg",
        ),
        (
            json!({"input": {"kind": "mesh", "artifact": sha}, "process": "robot", "execute": {"adaptive": "off"}}),
            "execute.adaptive",
        ),
    ];
    for (body, field) in &cases {
        let (status, reply) = stack.post_job(body, None).await?;
        assert_eq!(status, 400, "{body}: {reply}");
        assert_eq!(reply["error"]["field"], json!(field), "{body}: {reply}");
    }
    let listed: Value = stack.http.get(stack.url("/v1/jobs?limit=100")).send().await?.json().await?;
    assert_eq!(listed["jobs"].as_array().map_or(0, Vec::len), 0, "{listed}");

    // The good job.
    let body = json!({
        "name": "robot block",
        "input": {"kind": "mesh", "artifact": sha, "units": "mm"},
        "process": "robot",
        "robot": {"tool": "flat-6", "step_mm": 10},
        "execute": {"cell_mm": 0.3}
    });
    let (status, job) = stack.post_job(&body, None).await?;
    assert_eq!(status, 201, "{job}");
    assert_eq!(job["stage"], json!("plan"), "a robot job starts at the plan: {job}");
    let id = job["id"].as_str().context("id")?.to_string();
    let job = stack.wait_for_end(&id, Duration::from_secs(600)).await?;
    assert_eq!(job["status"], json!("succeeded"), "{job}");
    let timings = job["stage_timings_s"].as_object().context("timings")?;
    assert!(!timings.contains_key("scan") && !timings.contains_key("reconstruct"), "{timings:?}");
    for k in [
        "gcode",
        "joint_trajectory",
        "plan_report",
        "machined_part",
        "machined_part_view",
        "machine_report",
        "report",
    ] {
        assert!(job["artifacts"].get(k).is_some(), "no {k} artifact: {}", job["artifacts"]);
    }
    // The plan tilted the tool where the upright body collides, and the arm followed it.
    assert!(metric(&job, "robot_positions")? > 100.0);
    assert!(metric(&job, "robot_colliding_upright")? > 0.0, "{}", job["metrics"]);
    assert!(metric(&job, "robot_tilted")? > 0.0, "{}", job["metrics"]);
    assert_eq!(metric(&job, "robot_unreachable_stretches")?, 0.0);
    assert!(metric(&job, "robot_max_tilt_deg")? > 5.0, "{}", job["metrics"]);
    // The run: nothing cut by rapids, no gouge beyond the dexel resolution, time from the arm.
    assert_eq!(metric(&job, "robot_rapid_removed_mm3")?, 0.0);
    assert!(metric(&job, "robot_removed_mm3")? > 1000.0, "{}", job["metrics"]);
    let gouge = metric(&job, "max_gouge_mm")?;
    assert!(gouge <= 0.5, "max gouge {gouge} mm");
    assert_eq!(metric(&job, "original_max_gouge_mm")?, gouge);
    assert!(metric(&job, "cycle_time_s")? > 10.0);
    // The replay takes the time the plan's timing gave the arm.
    assert!((metric(&job, "estimated_time_s")? - metric(&job, "cycle_time_s")?).abs() < 1e-6);

    // The Cartesian program leans the tool (A/B words) and the report shows the robot's plan and run.
    let gcode_sha = job["artifacts"]["gcode"]["sha256"].as_str().context("gcode")?;
    let gcode = stack.http.get(stack.url(&format!("/v1/artifacts/{gcode_sha}"))).send().await?.text().await?;
    assert!(gcode.lines().any(|l| l.starts_with("G1 ") && l.contains(" A") && l.contains(" B")));
    let plan_sha = job["artifacts"]["plan_report"]["sha256"].as_str().context("plan report")?;
    let plan: Value =
        stack.http.get(stack.url(&format!("/v1/artifacts/{plan_sha}"))).send().await?.json().await?;
    assert_eq!(plan["layers"], json!(6), "{plan}");
    assert_eq!(plan["units"]["unit"], json!("mm"), "{}", plan["units"]);
    let html = stack.http.get(stack.url(&format!("/v1/jobs/{id}/report"))).send().await?.text().await?;
    for needle in
        ["Robot milling", "Tip path from above", "Simulated run against the part", "Simulated part in 3-D"]
    {
        assert!(html.contains(needle), "the report lacks {needle}");
    }
    assert!(!html.contains("Depth and coverage"), "a robot job has no depth maps to show");

    // Over gRPC: the same job model, process and settings kept.
    use depthmill_proto::cam::v1 as cam;
    use depthmill_proto::orchestrator::v1 as pb;
    let mut client = stack.grpc().await?;
    let small = stack.upload("model/stl", block_stl(20.0, 20.0, 15.0)).await?;
    let spec = pb::JobSpec {
        name: "robot over grpc".into(),
        input: Some(pb::JobInput { kind: pb::InputKind::Mesh as i32, artifact: small, ..Default::default() }),
        process: pb::Process::Robot as i32,
        robot: Some(cam::RobotParams { step_mm: Some(12.0), max_tilt_deg: Some(30.0), ..Default::default() }),
        ..Default::default()
    };
    let created = client
        .create_job(pb::CreateJobRequest { spec: Some(spec.clone()), idempotency_key: String::new() })
        .await?
        .into_inner();
    let back = created.spec.context("spec")?;
    assert_eq!(back.process, pb::Process::Robot as i32);
    assert_eq!(back.robot.and_then(|r| r.step_mm), Some(12.0));
    let bad = pb::JobSpec { robot: Some(cam::RobotParams { rpm: Some(-1.0), ..Default::default() }), ..spec };
    let status = client
        .create_job(pb::CreateJobRequest { spec: Some(bad), idempotency_key: String::new() })
        .await
        .expect_err("a negative spindle speed");
    assert_eq!(status.code(), tonic::Code::InvalidArgument);
    assert!(status.message().contains("robot.rpm"), "{}", status.message());
    let done = stack.wait_for_end(&created.id, Duration::from_secs(600)).await?;
    assert_eq!(done["status"], json!("succeeded"), "{done}");
    stack.shutdown().await
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_running_robot_plan_is_cancelled_and_parts_out_of_reach_fail_or_are_lifted_over()
-> anyhow::Result<()> {
    let stack = TestStack::start_with(StackOptions { stage_deadline_s: 600.0, ..Default::default() }).await?;
    let sha = stack.upload("model/stl", block_stl(20.0, 20.0, 60.0)).await?;
    // 1 mm layers: a plan long enough to be stopped in the clearance check.
    let body =
        json!({"input": {"kind": "mesh", "artifact": sha}, "process": "robot", "robot": {"step_mm": 1}});
    let (status, job) = stack.post_job(&body, None).await?;
    assert_eq!(status, 201, "{job}");
    let id = job["id"].as_str().context("id")?.to_string();
    let deadline = tokio::time::Instant::now() + Duration::from_secs(120);
    loop {
        let j = stack.get_job(&id).await?;
        if j["stage"] == json!("plan") && j["progress"].as_f64().unwrap_or(0.0) > 0.0 {
            break;
        }
        anyhow::ensure!(j["status"] != json!("succeeded"), "the plan ended before it could be cancelled");
        anyhow::ensure!(tokio::time::Instant::now() < deadline, "the plan never started: {j}");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let asked = std::time::Instant::now();
    let resp = stack.http.post(stack.url(&format!("/v1/jobs/{id}/cancel"))).send().await?;
    assert!(resp.status().is_success());
    let job = stack.wait_for_end(&id, Duration::from_secs(120)).await?;
    assert_eq!(job["status"], json!("cancelled"), "{job}");
    assert_eq!(job["error"]["stage"], json!("plan"), "{job}");
    // The CAM service stopped the plan itself (the orchestrator's grace period is longer).
    assert!(asked.elapsed() < Duration::from_secs(20), "cancelled after {:?}", asked.elapsed());

    // A part placed beyond the arm's reach: the job fails in the plan, saying so.
    let far = json!({"input": {"kind": "mesh", "artifact": sha}, "process": "robot",
                     "robot": {"step_mm": 10, "part_at_mm": [3000, 0, 0]}});
    let (status, job) = stack.post_job(&far, None).await?;
    assert_eq!(status, 201, "{job}");
    let id = job["id"].as_str().context("id")?.to_string();
    let job = stack.wait_for_end(&id, Duration::from_secs(300)).await?;
    assert_eq!(job["status"], json!("failed"), "{job}");
    assert_eq!(job["error"]["code"], json!("invalid_argument"), "{job}");
    assert_eq!(job["error"]["stage"], json!("plan"), "{job}");
    let msg = job["error"]["message"].as_str().unwrap_or_default();
    assert!(msg.contains("the arm reaches none"), "{msg}");

    // A part at the edge of the arm's reach: the positions it cannot follow are lifted over,
    // not cut by an arm that holds its joints and then sweeps the tool through the part to
    // rejoin the path (which gouged this part 4.5 mm).
    let edge_sha = stack.upload("model/stl", block_stl(40.0, 40.0, 20.0)).await?;
    let edge = json!({"input": {"kind": "mesh", "artifact": edge_sha}, "process": "robot",
                      "robot": {"step_mm": 5, "part_at_mm": [700, -20, 0]}, "execute": {"cell_mm": 0.3}});
    let (status, job) = stack.post_job(&edge, None).await?;
    assert_eq!(status, 201, "{job}");
    let id = job["id"].as_str().context("id")?.to_string();
    let job = stack.wait_for_end(&id, Duration::from_secs(300)).await?;
    assert_eq!(job["status"], json!("succeeded"), "{job}");
    assert!(metric(&job, "robot_blocked")? > 100.0, "{}", job["metrics"]);
    assert_eq!(metric(&job, "robot_unreachable_stretches")?, 0.0, "{}", job["metrics"]);
    let gouge = metric(&job, "max_gouge_mm")?;
    assert!(gouge <= 0.3, "max gouge {gouge} mm at the edge of reach");
    assert_eq!(metric(&job, "robot_rapid_removed_mm3")?, 0.0);
    let plan_sha = job["artifacts"]["plan_report"]["sha256"].as_str().context("plan report")?;
    let plan: Value =
        stack.http.get(stack.url(&format!("/v1/artifacts/{plan_sha}"))).send().await?.json().await?;
    let warned =
        plan["warnings"].as_array().into_iter().flatten().any(|w| w["code"] == json!("out_of_reach"));
    assert!(warned, "{}", plan["warnings"]);
    stack.shutdown().await
}
