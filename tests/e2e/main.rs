//! End-to-end tests: every service in-process on ephemeral ports, driven through REST and gRPC.

mod api;
mod auth;
mod children;
mod cli;
mod console;
mod corpus;
mod crash;
mod deploy;
mod faces;
mod faults;
mod jobs;
mod layering;
mod limits;
mod machine;
mod metrics;
mod objects;
mod outage;
mod parts;
mod plan;
mod reconstruct;
mod recovery;
mod replicas;
mod robot;
mod rs274;
mod scan;
mod tls;
mod whole;

use serde_json::{Value, json};

/// A small G-code program.
pub fn program() -> Vec<u8> {
    b"%\nG21 G90 G17\nG0 Z5\nG0 X0 Y0\nG1 Z-1 F100\nG1 X10 F200\nG1 Y10\nM30\n%\n".to_vec()
}

/// [`gcode_job`] as the gRPC API's message.
pub fn gcode_spec_pb(sha: &str) -> depthmill_proto::orchestrator::v1::JobSpec {
    use depthmill_proto::machine::v1::{AdaptiveMode, ExecuteParams};
    use depthmill_proto::orchestrator::v1::{InputKind, JobInput, JobSpec};
    JobSpec {
        name: "e2e".into(),
        input: Some(JobInput { kind: InputKind::Gcode as i32, artifact: sha.into(), ..Default::default() }),
        execute: Some(ExecuteParams {
            machine: Some("emco-f1".into()),
            adaptive: AdaptiveMode::Off as i32,
            ..Default::default()
        }),
        ..Default::default()
    }
}

/// A job that starts from the uploaded G-code.
pub fn gcode_job(sha: &str) -> Value {
    json!({"name": "e2e", "input": {"kind": "gcode", "artifact": sha}, "execute": {"machine": "emco-f1", "adaptive": "off"}})
}
