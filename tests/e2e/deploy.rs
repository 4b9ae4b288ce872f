//! The shipped configuration files load into the real configuration types.

use std::path::PathBuf;

fn config(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../deploy/config").join(name)
}

#[test]
fn shipped_configs_load_and_agree_on_ports_and_folders() -> anyhow::Result<()> {
    let prefix = "DEPTHMILL_TEST_UNUSED_PREFIX";
    let orch: depthmill_orchestrator::Config =
        depthmill_common::config::load(Some(&config("orchestrator.toml")), prefix)?;
    let scanning: depthmill_scanning::Config =
        depthmill_common::config::load(Some(&config("scanning.toml")), prefix)?;
    let reconstruction: depthmill_reconstruction::Config =
        depthmill_common::config::load(Some(&config("reconstruction.toml")), prefix)?;
    let cam: depthmill_cam::Config = depthmill_common::config::load(Some(&config("cam.toml")), prefix)?;
    let machine: depthmill_machine::Config =
        depthmill_common::config::load(Some(&config("machine.toml")), prefix)?;
    let artifacts = orch.data_dir.join("artifacts");
    for (url, addr, dir) in [
        (&orch.services.scanning, scanning.grpc_addr, &scanning.artifacts_dir),
        (&orch.services.reconstruction, reconstruction.grpc_addr, &reconstruction.artifacts_dir),
        (&orch.services.cam, cam.grpc_addr, &cam.artifacts_dir),
        (&orch.services.machine, machine.grpc_addr, &machine.artifacts_dir),
    ] {
        assert_eq!(url, &format!("http://{addr}"), "the orchestrator reaches each service where it listens");
        assert_eq!(dir, &artifacts, "services share the orchestrator's artifact folder");
    }
    // The compose file names the same binaries and ports.
    let compose =
        std::fs::read_to_string(PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../docker-compose.yml"))?;
    for (svc, port) in [("scanning", 50051), ("reconstruction", 50052), ("cam", 50053), ("machine", 50054)] {
        assert!(
            compose.contains(&format!("depthmill-{svc}")),
            "{svc} binary missing from docker-compose.yml"
        );
        assert!(
            compose.contains(&format!("http://{svc}:{port}")),
            "{svc} URL missing from docker-compose.yml"
        );
    }
    Ok(())
}
