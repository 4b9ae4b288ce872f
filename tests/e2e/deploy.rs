//! The shipped deployment files agree with the code.
//!
//! No container engine or cluster runs here, so the files are checked as far as parsing allows:
//! the configuration files load into the real configuration types; docker-compose.yml, the
//! Kubernetes manifests of deploy/k8s and both Prometheus scrape configurations name binaries
//! the Dockerfile builds, the ports the services listen on (the environment a manifest sets is
//! loaded through the real `Config` types), the gRPC service names the servers register in their
//! health service, and volumes mounted where the data and artifact folders are.

use std::collections::{BTreeMap, BTreeSet};
use std::net::SocketAddr;
use std::path::{Path, PathBuf};

use anyhow::{Context as _, anyhow, bail, ensure};
use serde::Deserialize as _;
use yaml_serde::Value;

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..")
}

fn config(name: &str) -> PathBuf {
    root().join("deploy/config").join(name)
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
    Ok(())
}

// ---------------------------------------------------------------------------------------------
// What the code says: one entry per service, from the shipped TOML files and the crates.

const ORCHESTRATOR: &str = "orchestrator";
const STAGE_SERVICES: [&str; 4] = ["scanning", "reconstruction", "cam", "machine"];

/// One service as the code and deploy/config describe it.
struct Service {
    /// Deployment, Service, container and compose service name; the binary is `depthmill-<name>`.
    name: &'static str,
    env_prefix: &'static str,
    /// The gRPC port of deploy/config/<name>.toml.
    grpc_port: u16,
    /// The orchestrator's REST port (deploy/config/orchestrator.toml).
    rest_port: Option<u16>,
    /// The names the server reports in its health service (besides "").
    health_names: &'static [&'static str],
}

impl Service {
    /// The port that serves `GET /metrics`: the orchestrator's REST port; a stage service's gRPC
    /// port (HTTP/1.1 beside gRPC, see `depthmill_common::grpc::serve_grpc`).
    fn metrics_port(&self) -> u16 {
        self.rest_port.unwrap_or(self.grpc_port)
    }

    fn binary(&self) -> String {
        format!("depthmill-{}", self.name)
    }
}

fn services() -> anyhow::Result<Vec<Service>> {
    let prefix = "DEPTHMILL_TEST_UNUSED_PREFIX";
    let orch: depthmill_orchestrator::Config =
        depthmill_common::config::load(Some(&config("orchestrator.toml")), prefix)?;
    let mut out = vec![Service {
        name: ORCHESTRATOR,
        env_prefix: "DEPTHMILL_ORCHESTRATOR",
        grpc_port: orch.grpc_addr.port(),
        rest_port: Some(orch.rest_addr.port()),
        health_names: depthmill_orchestrator::SERVICE_NAMES,
    }];
    for name in STAGE_SERVICES {
        let toml = config(&format!("{name}.toml"));
        let loaded = ContainerConfig::load(name, Some(&toml), prefix, [])?;
        let health_names = match name {
            "scanning" => depthmill_scanning::SERVICE_NAMES,
            "reconstruction" => depthmill_reconstruction::SERVICE_NAMES,
            "cam" => depthmill_cam::SERVICE_NAMES,
            _ => depthmill_machine::SERVICE_NAMES,
        };
        let env_prefix = match name {
            "scanning" => "DEPTHMILL_SCANNING",
            "reconstruction" => "DEPTHMILL_RECONSTRUCTION",
            "cam" => "DEPTHMILL_CAM",
            _ => "DEPTHMILL_MACHINE",
        };
        out.push(Service {
            name,
            env_prefix,
            grpc_port: loaded.grpc_addr.port(),
            rest_port: None,
            health_names,
        });
    }
    Ok(out)
}

/// The configuration a service's process loads, through its real `Config` type.
struct ContainerConfig {
    grpc_addr: SocketAddr,
    rest_addr: Option<SocketAddr>,
    /// The orchestrator's data_dir.
    data_dir: Option<PathBuf>,
    /// A stage service's artifacts_dir, or the orchestrator's `<data_dir>/artifacts`.
    artifacts_dir: PathBuf,
    /// The orchestrator's stage service URLs, by service name.
    service_urls: BTreeMap<&'static str, String>,
}

impl ContainerConfig {
    fn load(
        name: &str,
        file: Option<&Path>,
        prefix: &str,
        env: impl IntoIterator<Item = (String, String)>,
    ) -> anyhow::Result<Self> {
        use depthmill_common::config::load_with_env;
        let stage = |grpc_addr, artifacts_dir| Self {
            grpc_addr,
            rest_addr: None,
            data_dir: None,
            artifacts_dir,
            service_urls: BTreeMap::new(),
        };
        Ok(match name {
            ORCHESTRATOR => {
                let c: depthmill_orchestrator::Config = load_with_env(file, prefix, env)?;
                // It starts where it listens: beyond loopback, an auth mode that allows it.
                depthmill_orchestrator::auth::tokens_required(c.auth.mode, c.rest_addr, c.grpc_addr)?;
                Self {
                    grpc_addr: c.grpc_addr,
                    rest_addr: Some(c.rest_addr),
                    artifacts_dir: c.data_dir.join("artifacts"),
                    data_dir: Some(c.data_dir),
                    service_urls: BTreeMap::from([
                        ("scanning", c.services.scanning),
                        ("reconstruction", c.services.reconstruction),
                        ("cam", c.services.cam),
                        ("machine", c.services.machine),
                    ]),
                }
            }
            "scanning" => {
                let c: depthmill_scanning::Config = load_with_env(file, prefix, env)?;
                stage(c.grpc_addr, c.artifacts_dir)
            }
            "reconstruction" => {
                let c: depthmill_reconstruction::Config = load_with_env(file, prefix, env)?;
                stage(c.grpc_addr, c.artifacts_dir)
            }
            "cam" => {
                let c: depthmill_cam::Config = load_with_env(file, prefix, env)?;
                stage(c.grpc_addr, c.artifacts_dir)
            }
            "machine" => {
                let c: depthmill_machine::Config = load_with_env(file, prefix, env)?;
                stage(c.grpc_addr, c.artifacts_dir)
            }
            other => bail!("no such service {other}"),
        })
    }

    /// What the container loads: no config file (the image's commands pass none), `env` only.
    fn of_container(svc: &Service, env: &BTreeMap<String, String>) -> anyhow::Result<Self> {
        let env = env.iter().map(|(k, v)| (k.clone(), v.clone()));
        Self::load(svc.name, None, svc.env_prefix, env)
            .with_context(|| format!("{}'s configuration", svc.name))
    }

    /// The process listens on every interface, at the ports deploy/config names.
    fn check_listens_like(&self, svc: &Service) -> anyhow::Result<()> {
        ensure!(
            self.grpc_addr.ip().is_unspecified(),
            "{}: gRPC must listen on 0.0.0.0, not {}",
            svc.name,
            self.grpc_addr
        );
        ensure!(
            self.grpc_addr.port() == svc.grpc_port,
            "{}: gRPC port {} is not deploy/config's {}",
            svc.name,
            self.grpc_addr.port(),
            svc.grpc_port
        );
        if let Some(rest) = svc.rest_port {
            let addr = self.rest_addr.ok_or_else(|| anyhow!("{}: no REST address", svc.name))?;
            ensure!(addr.ip().is_unspecified(), "{}: REST must listen on 0.0.0.0, not {addr}", svc.name);
            ensure!(
                addr.port() == rest,
                "{}: REST port {} is not deploy/config's {rest}",
                svc.name,
                addr.port()
            );
        }
        Ok(())
    }
}

/// The binaries deploy/Dockerfile copies into the image.
fn dockerfile_binaries() -> anyhow::Result<BTreeSet<String>> {
    let text = std::fs::read_to_string(root().join("deploy/Dockerfile"))?;
    let binaries: BTreeSet<String> = text
        .split_whitespace()
        .filter_map(|word| word.strip_prefix("target/release/"))
        .map(str::to_string)
        .collect();
    ensure!(!binaries.is_empty(), "the Dockerfile copies no binary out of target/release");
    Ok(binaries)
}

// ---------------------------------------------------------------------------------------------
// YAML access.

/// Every document of a YAML stream (`---` separated), empty ones left out.
fn yaml_documents(path: &Path) -> anyhow::Result<Vec<Value>> {
    let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    parse_documents(&text).with_context(|| format!("parsing {}", path.display()))
}

fn parse_documents(text: &str) -> anyhow::Result<Vec<Value>> {
    let mut docs = Vec::new();
    for doc in yaml_serde::Deserializer::from_str(text) {
        let value = Value::deserialize(doc)?;
        if !value.is_null() {
            docs.push(value);
        }
    }
    Ok(docs)
}

/// The value at a dotted path of mapping keys (`spec.template.spec`).
fn at<'a>(v: &'a Value, path: &str) -> Option<&'a Value> {
    path.split('.').try_fold(v, |v, key| v.get(key))
}

fn str_at<'a>(v: &'a Value, path: &str) -> anyhow::Result<&'a str> {
    at(v, path).and_then(Value::as_str).ok_or_else(|| anyhow!("{path} is missing or not a string"))
}

fn seq_at<'a>(v: &'a Value, path: &str) -> anyhow::Result<&'a [Value]> {
    at(v, path)
        .and_then(Value::as_sequence)
        .map(Vec::as_slice)
        .ok_or_else(|| anyhow!("{path} is missing or not a list"))
}

fn port_of(v: &Value) -> Option<u16> {
    v.as_u64().and_then(|p| u16::try_from(p).ok())
}

/// `http://host:port` as (host, port).
fn host_port(url: &str) -> anyhow::Result<(&str, u16)> {
    let rest = url.strip_prefix("http://").ok_or_else(|| anyhow!("{url} is not an http:// URL"))?;
    let (host, port) =
        rest.trim_end_matches('/').rsplit_once(':').ok_or_else(|| anyhow!("{url} has no port"))?;
    Ok((host, port.parse().with_context(|| format!("the port of {url}"))?))
}

/// A Kubernetes object of deploy/k8s.
struct Object {
    file: String,
    kind: String,
    name: String,
    doc: Value,
}

fn k8s_dir() -> PathBuf {
    root().join("deploy/k8s")
}

/// Every object of every YAML file under deploy/k8s, and the file names.
fn k8s_objects() -> anyhow::Result<(Vec<Object>, BTreeSet<String>)> {
    let mut objects = Vec::new();
    let mut files = BTreeSet::new();
    for entry in std::fs::read_dir(k8s_dir())? {
        let path = entry?.path();
        let Some(file) = path.file_name().and_then(|n| n.to_str()).map(str::to_string) else { continue };
        if !(file.ends_with(".yaml") || file.ends_with(".yml")) {
            continue;
        }
        for doc in yaml_documents(&path)? {
            let kind = str_at(&doc, "kind").with_context(|| file.clone())?.to_string();
            // Every object but the Kustomization has a name.
            let name = str_at(&doc, "metadata.name").unwrap_or_default().to_string();
            objects.push(Object { file: file.clone(), kind, name, doc });
        }
        files.insert(file);
    }
    Ok((objects, files))
}

fn find<'a>(objects: &'a [Object], kind: &str, name: &str) -> anyhow::Result<&'a Object> {
    objects
        .iter()
        .find(|o| o.kind == kind && o.name == name)
        .ok_or_else(|| anyhow!("deploy/k8s has no {kind} named {name}"))
}

/// A container's ports by name.
fn container_ports(container: &Value) -> anyhow::Result<BTreeMap<String, u16>> {
    let mut ports = BTreeMap::new();
    for p in seq_at(container, "ports")? {
        let name = str_at(p, "name")?.to_string();
        let port = at(p, "containerPort")
            .and_then(port_of)
            .ok_or_else(|| anyhow!("port {name} has no containerPort"))?;
        ports.insert(name, port);
    }
    Ok(ports)
}

/// A probe's or Service's port: a number, or the name of a container port.
fn resolve_port(port: &Value, ports: &BTreeMap<String, u16>) -> Option<u16> {
    port_of(port).or_else(|| port.as_str().and_then(|name| ports.get(name).copied()))
}

fn env_of(container: &Value) -> anyhow::Result<BTreeMap<String, String>> {
    let mut env = BTreeMap::new();
    for e in seq_at(container, "env")? {
        env.insert(str_at(e, "name")?.to_string(), str_at(e, "value")?.to_string());
    }
    Ok(env)
}

// ---------------------------------------------------------------------------------------------
// Kubernetes.

#[test]
fn kubernetes_manifests_match_the_code() -> anyhow::Result<()> {
    let services = services()?;
    let binaries = dockerfile_binaries()?;
    let (objects, files) = k8s_objects()?;

    // kustomization.yaml lists every other manifest, and names the one namespace.
    let kustomization = find(&objects, "Kustomization", "")?;
    let listed: BTreeSet<String> = seq_at(&kustomization.doc, "resources")?
        .iter()
        .filter_map(Value::as_str)
        .map(str::to_string)
        .collect();
    let manifests: BTreeSet<String> = files.iter().filter(|f| *f != &kustomization.file).cloned().collect();
    assert_eq!(listed, manifests, "kustomization.yaml lists every manifest of deploy/k8s");
    let namespace = str_at(&kustomization.doc, "namespace")?;
    find(&objects, "Namespace", namespace)?;

    // The claims: the artifact store is shared by every pod (ReadWriteMany).
    let claim_modes = |name: &str| -> anyhow::Result<Vec<String>> {
        let pvc = find(&objects, "PersistentVolumeClaim", name)?;
        Ok(seq_at(&pvc.doc, "spec.accessModes")?
            .iter()
            .filter_map(Value::as_str)
            .map(str::to_string)
            .collect())
    };

    let mut artifact_claims = BTreeSet::new();
    for svc in &services {
        let check = || -> anyhow::Result<String> {
            let deployment = find(&objects, "Deployment", svc.name)?;
            let service = find(&objects, "Service", svc.name)?;
            let pod = at(&deployment.doc, "spec.template").ok_or_else(|| anyhow!("no pod template"))?;
            let containers = seq_at(pod, "spec.containers")?;
            ensure!(containers.len() == 1, "one container per pod");
            let container = &containers[0];
            ensure!(str_at(container, "image")? == "depthmill:latest", "the image is depthmill:latest");
            let command = seq_at(container, "command")?;
            let binary = command.first().and_then(Value::as_str).ok_or_else(|| anyhow!("no command"))?;
            ensure!(binary == svc.binary(), "the command runs {binary}, not {}", svc.binary());
            ensure!(binaries.contains(binary), "the Dockerfile builds no {binary} (it builds {binaries:?})");

            // The environment, loaded through the real Config type, listens where the ports say.
            let env = env_of(container)?;
            let loaded = ContainerConfig::of_container(svc, &env)?;
            loaded.check_listens_like(svc)?;
            let ports = container_ports(container)?;
            ensure!(
                ports.get("grpc") == Some(&svc.grpc_port),
                "container port grpc is {:?}, not {}",
                ports.get("grpc"),
                svc.grpc_port
            );
            if let Some(rest) = svc.rest_port {
                ensure!(
                    ports.get("http") == Some(&rest),
                    "container port http is {:?}, not {rest}",
                    ports.get("http")
                );
            }

            // Probes: readiness and liveness; every gRPC probe asks the gRPC port for a name the
            // server registers; every HTTP probe asks the REST port for /readyz or /healthz.
            let mut grpc_probes = 0;
            for kind in ["startupProbe", "readinessProbe", "livenessProbe"] {
                let Some(probe) = container.get(kind) else {
                    ensure!(kind == "startupProbe", "no {kind}");
                    continue;
                };
                if let Some(grpc) = probe.get("grpc") {
                    grpc_probes += 1;
                    let port = grpc.get("port").and_then(port_of);
                    ensure!(
                        port == Some(svc.grpc_port),
                        "{kind}: gRPC probe on port {port:?}, not {}",
                        svc.grpc_port
                    );
                    let name = str_at(grpc, "service")?;
                    ensure!(
                        svc.health_names.contains(&name),
                        "{kind}: {name} is not registered (the server registers {:?})",
                        svc.health_names
                    );
                } else if let Some(get) = probe.get("httpGet") {
                    let rest =
                        svc.rest_port.ok_or_else(|| anyhow!("{kind}: an HTTP probe, but no REST port"))?;
                    let port = get.get("port").and_then(|p| resolve_port(p, &ports));
                    ensure!(port == Some(rest), "{kind}: HTTP probe on port {port:?}, not REST {rest}");
                    let path = str_at(get, "path")?;
                    let expected = if kind == "livenessProbe" { "/healthz" } else { "/readyz" };
                    ensure!(path == expected, "{kind}: HTTP probe of {path}, not {expected}");
                } else {
                    bail!("{kind} is neither grpc nor httpGet");
                }
            }
            ensure!(grpc_probes > 0, "no probe asks the gRPC health service");

            // Volumes: the artifact folder (and the orchestrator's data folder) on claims.
            let claims: BTreeMap<String, String> = seq_at(pod, "spec.volumes")?
                .iter()
                .filter_map(|v| {
                    Some((
                        str_at(v, "name").ok()?.to_string(),
                        str_at(v, "persistentVolumeClaim.claimName").ok()?.to_string(),
                    ))
                })
                .collect();
            let mut mounted = BTreeMap::new();
            for m in seq_at(container, "volumeMounts")? {
                let volume = str_at(m, "name")?;
                if let Some(claim) = claims.get(volume) {
                    mounted.insert(PathBuf::from(str_at(m, "mountPath")?), claim.clone());
                }
            }
            let artifacts_claim = mounted.get(&loaded.artifacts_dir).ok_or_else(|| {
                anyhow!("no claim mounted at the artifact folder {}", loaded.artifacts_dir.display())
            })?;
            let modes = claim_modes(artifacts_claim)?;
            ensure!(
                modes.iter().any(|m| m == "ReadWriteMany"),
                "the artifact claim {artifacts_claim} is shared by all pods: it must be ReadWriteMany, not {modes:?}"
            );
            if let Some(data_dir) = &loaded.data_dir {
                let claim = mounted
                    .get(data_dir)
                    .ok_or_else(|| anyhow!("no claim mounted at data_dir {}", data_dir.display()))?;
                claim_modes(claim)?;
                ensure!(
                    deployment.doc.get("spec").and_then(|s| s.get("replicas")).and_then(Value::as_u64)
                        == Some(1),
                    "one orchestrator replica (SQLite)"
                );
            }

            // The Service selects this pod and exposes its ports by name.
            let labels = at(pod, "metadata.labels")
                .and_then(Value::as_mapping)
                .ok_or_else(|| anyhow!("pod has no labels"))?;
            let selector = at(&service.doc, "spec.selector")
                .and_then(Value::as_mapping)
                .ok_or_else(|| anyhow!("Service has no selector"))?;
            ensure!(
                !selector.is_empty() && selector.iter().all(|(k, v)| labels.get(k) == Some(v)),
                "the Service's selector does not select the pod"
            );
            let mut service_ports = BTreeMap::new();
            for p in seq_at(&service.doc, "spec.ports")? {
                let name = str_at(p, "name")?;
                ensure!(
                    ["grpc", "http", "metrics"].contains(&name),
                    "Service port {name} is not grpc, http or metrics"
                );
                let port = p
                    .get("port")
                    .and_then(port_of)
                    .ok_or_else(|| anyhow!("Service port {name} has no port"))?;
                let target = p.get("targetPort").map_or(Some(port), |t| resolve_port(t, &ports));
                ensure!(
                    target == ports.get(name).copied(),
                    "Service port {name} targets {target:?}, not the container's {name} port"
                );
                service_ports.insert(name.to_string(), port);
            }
            ensure!(
                service_ports.get("grpc") == Some(&svc.grpc_port),
                "the Service has no grpc port {}",
                svc.grpc_port
            );
            if let Some(rest) = svc.rest_port {
                ensure!(service_ports.get("http") == Some(&rest), "the Service has no http port {rest}");
            }

            // Prometheus: the pod asks to be scraped at /metrics on a port that serves it.
            let annotation =
                |key: &str| at(pod, "metadata.annotations").and_then(|a| a.get(key)).and_then(Value::as_str);
            ensure!(
                annotation("prometheus.io/scrape") == Some("true"),
                "pod not annotated prometheus.io/scrape: \"true\""
            );
            ensure!(
                annotation("prometheus.io/path") == Some("/metrics"),
                "pod not annotated prometheus.io/path: /metrics"
            );
            let port: Option<u16> = annotation("prometheus.io/port").and_then(|p| p.parse().ok());
            ensure!(
                port == Some(svc.metrics_port()),
                "prometheus.io/port is {port:?}, but /metrics is served on {}",
                svc.metrics_port()
            );
            ensure!(ports.values().any(|p| Some(*p) == port), "prometheus.io/port is not a container port");

            // The orchestrator reaches every stage service through its Service.
            for (stage, url) in &loaded.service_urls {
                let (host, port) = host_port(url)?;
                ensure!(host == *stage, "the {stage} URL {url} does not name the {stage} Service");
                let target = find(&objects, "Service", host)?;
                let exposed = seq_at(&target.doc, "spec.ports")?.iter().any(|p| {
                    str_at(p, "name").ok() == Some("grpc") && p.get("port").and_then(port_of) == Some(port)
                });
                ensure!(exposed, "the {stage} Service has no grpc port {port} ({url})");
                let stage_svc = services
                    .iter()
                    .find(|s| s.name == *stage)
                    .ok_or_else(|| anyhow!("no service {stage}"))?;
                ensure!(port == stage_svc.grpc_port, "{url}: {stage} listens on {}", stage_svc.grpc_port);
            }
            if svc.name == ORCHESTRATOR {
                ensure!(
                    loaded.service_urls.len() == STAGE_SERVICES.len(),
                    "the orchestrator has a URL per stage service"
                );
            }
            Ok(artifacts_claim.clone())
        };
        let claim = check().with_context(|| format!("deploy/k8s: {}", svc.name))?;
        artifact_claims.insert(claim);
    }
    assert_eq!(artifact_claims.len(), 1, "every pod mounts the same artifact claim: {artifact_claims:?}");

    check_k8s_prometheus(&objects, namespace)
}

/// The Prometheus configuration discovers the annotated pods of the namespace, and Prometheus
/// loads it.
fn check_k8s_prometheus(objects: &[Object], namespace: &str) -> anyhow::Result<()> {
    let config_map = find(objects, "ConfigMap", "prometheus-config")?;
    let text = at(&config_map.doc, "data")
        .and_then(|d| d.get("prometheus.yml"))
        .and_then(Value::as_str)
        .ok_or_else(|| anyhow!("prometheus-config has no data prometheus.yml"))?;
    let config = parse_documents(text)?.into_iter().next().ok_or_else(|| anyhow!("empty prometheus.yml"))?;
    let jobs = seq_at(&config, "scrape_configs")?;
    let pod_job = jobs
        .iter()
        .find(|job| {
            job.get("kubernetes_sd_configs").and_then(Value::as_sequence).is_some_and(|sds| {
                sds.iter().any(|sd| {
                    sd.get("role").and_then(Value::as_str) == Some("pod")
                        && at(sd, "namespaces.names")
                            .and_then(Value::as_sequence)
                            .is_some_and(|n| n.iter().any(|n| n.as_str() == Some(namespace)))
                })
            })
        })
        .ok_or_else(|| anyhow!("no scrape job discovers the pods of namespace {namespace}"))?;
    let relabels = seq_at(pod_job, "relabel_configs")?;
    let uses = |label: &str, action: Option<&str>, target: Option<&str>| {
        relabels.iter().any(|r| {
            r.get("source_labels")
                .and_then(Value::as_sequence)
                .is_some_and(|s| s.iter().any(|l| l.as_str() == Some(label)))
                && action.is_none_or(|a| r.get("action").and_then(Value::as_str) == Some(a))
                && target.is_none_or(|t| r.get("target_label").and_then(Value::as_str) == Some(t))
        })
    };
    ensure!(
        uses("__meta_kubernetes_pod_annotation_prometheus_io_scrape", Some("keep"), None),
        "the pod job keeps pods annotated prometheus.io/scrape"
    );
    ensure!(
        uses("__meta_kubernetes_pod_annotation_prometheus_io_path", None, Some("__metrics_path__")),
        "the pod job scrapes prometheus.io/path"
    );
    ensure!(
        uses("__meta_kubernetes_pod_annotation_prometheus_io_port", None, Some("__address__")),
        "the pod job scrapes prometheus.io/port"
    );
    ensure!(
        !uses("__meta_kubernetes_pod_label_app_kubernetes_io_name", None, Some("service")),
        "target label `service` would clash with the gRPC metrics' label"
    );

    // A Prometheus Deployment mounts the ConfigMap where its --config.file points.
    let prometheus = find(objects, "Deployment", "prometheus")?;
    let pod = at(&prometheus.doc, "spec.template.spec").ok_or_else(|| anyhow!("no pod spec"))?;
    let volume = seq_at(pod, "volumes")?
        .iter()
        .find(|v| str_at(v, "configMap.name").ok() == Some(config_map.name.as_str()))
        .and_then(|v| str_at(v, "name").ok())
        .ok_or_else(|| anyhow!("Prometheus mounts no prometheus-config volume"))?;
    let container = seq_at(pod, "containers")?.first().ok_or_else(|| anyhow!("no Prometheus container"))?;
    let mount = seq_at(container, "volumeMounts")?
        .iter()
        .find(|m| str_at(m, "name").ok() == Some(volume))
        .and_then(|m| str_at(m, "mountPath").ok())
        .ok_or_else(|| anyhow!("the Prometheus container does not mount {volume}"))?;
    let config_file = format!("--config.file={mount}/prometheus.yml");
    ensure!(
        seq_at(container, "args")?.iter().any(|a| a.as_str() == Some(config_file.as_str())),
        "Prometheus runs without {config_file}"
    );
    Ok(())
}

// ---------------------------------------------------------------------------------------------
// docker-compose.

#[test]
fn compose_file_and_its_prometheus_match_the_code() -> anyhow::Result<()> {
    let services = services()?;
    let binaries = dockerfile_binaries()?;
    let compose = yaml_documents(&root().join("docker-compose.yml"))?
        .into_iter()
        .next()
        .ok_or_else(|| anyhow!("docker-compose.yml is empty"))?;
    let prometheus = yaml_documents(&root().join("deploy/prometheus.yml"))?
        .into_iter()
        .next()
        .ok_or_else(|| anyhow!("deploy/prometheus.yml is empty"))?;
    let mut targets = BTreeSet::new();
    for job in seq_at(&prometheus, "scrape_configs")? {
        let path = job.get("metrics_path").and_then(Value::as_str).unwrap_or("/metrics");
        for sc in
            job.get("static_configs").and_then(Value::as_sequence).map(Vec::as_slice).unwrap_or_default()
        {
            for t in seq_at(sc, "targets")?.iter().filter_map(Value::as_str) {
                targets.insert((t.to_string(), path.to_string()));
            }
        }
    }

    for svc in &services {
        let check = || -> anyhow::Result<()> {
            let entry = at(&compose, &format!("services.{}", svc.name))
                .ok_or_else(|| anyhow!("no such compose service"))?;
            ensure!(str_at(entry, "image")? == "depthmill:latest", "the image is depthmill:latest");
            let binary = seq_at(entry, "command")?
                .first()
                .and_then(Value::as_str)
                .ok_or_else(|| anyhow!("no command"))?;
            ensure!(binary == svc.binary(), "the command runs {binary}, not {}", svc.binary());
            ensure!(binaries.contains(binary), "the Dockerfile builds no {binary}");
            let env: BTreeMap<String, String> = entry
                .get("environment")
                .and_then(Value::as_mapping)
                .ok_or_else(|| anyhow!("no environment mapping"))?
                .iter()
                .filter_map(|(k, v)| Some((k.as_str()?.to_string(), v.as_str()?.to_string())))
                .collect();
            let loaded = ContainerConfig::of_container(svc, &env)?;
            loaded.check_listens_like(svc)?;
            for (stage, url) in &loaded.service_urls {
                let stage_svc = services
                    .iter()
                    .find(|s| s.name == *stage)
                    .ok_or_else(|| anyhow!("no service {stage}"))?;
                ensure!(
                    url == &format!("http://{stage}:{}", stage_svc.grpc_port),
                    "the {stage} URL {url} is not its compose service and port"
                );
            }
            // The shared volume holds the artifact folder (and the orchestrator's data folder).
            let volumes: Vec<&str> = seq_at(entry, "volumes")?.iter().filter_map(Value::as_str).collect();
            let under_volume = |dir: &Path| {
                volumes.iter().any(|v| {
                    v.split_once(':')
                        .is_some_and(|(name, mount)| name == "depthmill-data" && dir.starts_with(mount))
                })
            };
            ensure!(
                under_volume(&loaded.artifacts_dir),
                "{} is not on the depthmill-data volume",
                loaded.artifacts_dir.display()
            );
            if let Some(data_dir) = &loaded.data_dir {
                ensure!(under_volume(data_dir), "{} is not on the depthmill-data volume", data_dir.display());
            }
            // Prometheus scrapes the port that serves /metrics.
            let target = (format!("{}:{}", svc.name, svc.metrics_port()), "/metrics".to_string());
            ensure!(
                targets.contains(&target),
                "deploy/prometheus.yml does not scrape {}{}",
                target.0,
                target.1
            );
            Ok(())
        };
        check().with_context(|| format!("docker-compose.yml: {}", svc.name))?;
    }
    ensure!(at(&compose, "volumes.depthmill-data").is_some(), "the depthmill-data volume is declared");
    Ok(())
}

// The scale-out override: two orchestrator replicas on PostgreSQL, two machine instances.

#[test]
fn the_scale_out_compose_file_runs_replicas_on_postgres_and_balanced_instances() -> anyhow::Result<()> {
    use depthmill_common::config::load_with_env;
    let first = |path: &str| -> anyhow::Result<Value> {
        yaml_documents(&root().join(path))?.into_iter().next().ok_or_else(|| anyhow!("{path} is empty"))
    };
    let (base, over) = (first("docker-compose.yml")?, first("deploy/compose.scale-out.yml")?);
    let env_map = |v: Option<&Value>| -> BTreeMap<String, String> {
        v.and_then(Value::as_mapping)
            .map(|m| {
                m.iter()
                    .filter_map(|(k, v)| Some((k.as_str()?.to_string(), v.as_str()?.to_string())))
                    .collect()
            })
            .unwrap_or_default()
    };
    // Compose merges an override's environment into the base service's, key by key.
    let env_of = |name: &str| -> BTreeMap<String, String> {
        let mut env = env_map(at(&base, &format!("services.{name}.environment")));
        env.extend(env_map(at(&over, &format!("services.{name}.environment"))));
        env
    };
    let exists = |name: &str| {
        at(&base, &format!("services.{name}")).is_some() || at(&over, &format!("services.{name}")).is_some()
    };
    ensure!(exists("postgres"), "no postgres service");
    let mut data_dirs = BTreeSet::new();
    // Every replica and stage service on one object store, its endpoint a service of the stack.
    let mut stores = BTreeSet::new();
    let mut store_of = |who: &str, store: Option<depthmill_common::artifacts::ObjectStoreConfig>| {
        let store = store.ok_or_else(|| anyhow!("{who} has no artifact_store"))?;
        ensure!(store.url.starts_with("s3://"), "{who}: artifact store {}", store.url);
        let endpoint = store.options.get("endpoint").cloned().unwrap_or_default();
        let host = endpoint.trim_start_matches("http://").split(':').next().unwrap_or_default().to_string();
        ensure!(exists(&host), "{who}: store endpoint {endpoint} names no compose service");
        stores.insert(format!("{store:?}"));
        anyhow::Ok(())
    };
    for replica in ["orchestrator", "orchestrator-2"] {
        let mut check = || -> anyhow::Result<()> {
            let entry = at(&base, &format!("services.{replica}"))
                .or_else(|| at(&over, &format!("services.{replica}")))
                .ok_or_else(|| anyhow!("no such service"))?;
            let binary = seq_at(entry, "command")?.first().and_then(Value::as_str).unwrap_or_default();
            ensure!(binary == "depthmill-orchestrator", "runs {binary}");
            let c: depthmill_orchestrator::Config =
                load_with_env(None, "DEPTHMILL_ORCHESTRATOR", env_of(replica))?;
            depthmill_orchestrator::auth::tokens_required(c.auth.mode, c.rest_addr, c.grpc_addr)?;
            let url = c.database_url.clone().unwrap_or_default();
            ensure!(url.starts_with("postgres://") && url.contains("@postgres:5432/"), "database {url}");
            ensure!(
                data_dirs.insert(c.data_dir.clone()),
                "{} is another replica's data folder",
                c.data_dir.display()
            );
            store_of(replica, c.artifact_store.clone())?;
            let machines: Vec<&str> = c.services.machine.split(',').map(str::trim).collect();
            ensure!(machines.len() == 2, "machine instances {machines:?}");
            for m in machines {
                let host = m.trim_start_matches("http://").split(':').next().unwrap_or_default();
                ensure!(exists(host), "{m} names no compose service");
                ensure!(m.ends_with(":50054"), "{m} is not the machine port");
            }
            Ok(())
        };
        check().with_context(|| format!("deploy/compose.scale-out.yml: {replica}"))?;
    }
    store_of(
        "scanning",
        load_with_env::<depthmill_scanning::Config>(None, "DEPTHMILL_SCANNING", env_of("scanning"))?
            .artifact_store,
    )?;
    store_of(
        "reconstruction",
        load_with_env::<depthmill_reconstruction::Config>(
            None,
            "DEPTHMILL_RECONSTRUCTION",
            env_of("reconstruction"),
        )?
        .artifact_store,
    )?;
    store_of(
        "cam",
        load_with_env::<depthmill_cam::Config>(None, "DEPTHMILL_CAM", env_of("cam"))?.artifact_store,
    )?;
    for m in ["machine", "machine-2"] {
        store_of(
            m,
            load_with_env::<depthmill_machine::Config>(None, "DEPTHMILL_MACHINE", env_of(m))?.artifact_store,
        )?;
    }
    ensure!(stores.len() == 1, "every service on one artifact store: {stores:?}");
    ensure!(exists("minio") && exists("minio-bucket"), "no S3 store in the stack");
    Ok(())
}

// ---------------------------------------------------------------------------------------------
// The Kubernetes scale-out overlay (deploy/k8s/scale-out): what kustomize would make of it, applied
// here (its patches are RFC 6902 JSON patches of named objects and `$patch: delete` of whole
// objects), then loaded through the real configuration types.

/// Applies one RFC 6902 operation (`add`, `replace`, `remove`) to `doc`.
fn json_patch(doc: &mut Value, op: &Value) -> anyhow::Result<()> {
    let kind = str_at(op, "op")?;
    let path = str_at(op, "path")?;
    let mut keys: Vec<&str> = path.split('/').skip(1).collect();
    let last = keys.pop().ok_or_else(|| anyhow!("empty path"))?;
    let mut node = &mut *doc;
    for key in keys {
        node = match node {
            Value::Sequence(s) => {
                s.get_mut(key.parse::<usize>()?).ok_or_else(|| anyhow!("{path}: no {key}"))?
            }
            Value::Mapping(m) => m.get_mut(key).ok_or_else(|| anyhow!("{path}: no {key}"))?,
            _ => bail!("{path}: {key} is not in a list or a mapping"),
        };
    }
    let value = || op.get("value").cloned().ok_or_else(|| anyhow!("{path}: {kind} without a value"));
    match (node, kind) {
        (Value::Sequence(s), "add") if last == "-" => s.push(value()?),
        (Value::Sequence(s), "add") => s.insert(last.parse()?, value()?),
        (Value::Sequence(s), "replace") => {
            *s.get_mut(last.parse::<usize>()?).ok_or_else(|| anyhow!("{path}: no {last}"))? = value()?
        }
        (Value::Sequence(s), "remove") => {
            s.remove(last.parse()?);
        }
        (Value::Mapping(m), "add") => {
            m.insert(Value::String(last.into()), value()?);
        }
        (Value::Mapping(m), "replace") => {
            ensure!(m.contains_key(last), "{path}: replace of a missing key");
            m.insert(Value::String(last.into()), value()?);
        }
        (Value::Mapping(m), "remove") => {
            m.remove(last).ok_or_else(|| anyhow!("{path}: remove of a missing key"))?;
        }
        (_, other) => bail!("{path}: cannot {other} there"),
    }
    Ok(())
}

#[test]
fn the_kubernetes_scale_out_overlay_runs_replicas_on_postgres_and_s3() -> anyhow::Result<()> {
    let dir = k8s_dir().join("scale-out");
    let kustomization = yaml_documents(&dir.join("kustomization.yaml"))?
        .into_iter()
        .next()
        .ok_or_else(|| anyhow!("empty kustomization"))?;
    // The base's objects (the `../` resource) plus the overlay's own.
    let (mut objects, _) = k8s_objects()?;
    objects.retain(|o| o.kind != "Kustomization");
    let mut used_files = BTreeSet::from(["kustomization.yaml".to_string()]);
    for r in seq_at(&kustomization, "resources")?.iter().filter_map(Value::as_str) {
        if r == "../" {
            continue;
        }
        used_files.insert(r.to_string());
        for doc in yaml_documents(&dir.join(r))? {
            let kind = str_at(&doc, "kind")?.to_string();
            let name = str_at(&doc, "metadata.name")?.to_string();
            objects.push(Object { file: r.to_string(), kind, name, doc });
        }
    }
    for p in seq_at(&kustomization, "patches")? {
        let file = str_at(p, "path")?;
        used_files.insert(file.to_string());
        let docs = yaml_documents(&dir.join(file))?;
        match p.get("target") {
            Some(target) => {
                let (kind, name) = (str_at(target, "kind")?, str_at(target, "name")?);
                let object = objects
                    .iter_mut()
                    .find(|o| o.kind == kind && o.name == name)
                    .ok_or_else(|| anyhow!("{file}: no {kind} {name} to patch"))?;
                for op in docs.iter().flat_map(|d| d.as_sequence().cloned().unwrap_or_default()) {
                    json_patch(&mut object.doc, &op).with_context(|| file.to_string())?;
                }
            }
            None => {
                for d in docs {
                    ensure!(str_at(&d, "$patch")? == "delete", "{file}: only `$patch: delete` patches here");
                    let (kind, name) = (str_at(&d, "kind")?, str_at(&d, "metadata.name")?);
                    let before = objects.len();
                    objects.retain(|o| !(o.kind == kind && o.name == name));
                    ensure!(objects.len() + 1 == before, "{file}: no {kind} {name} to delete");
                }
            }
        }
    }
    let on_disk: BTreeSet<String> = std::fs::read_dir(&dir)?
        .filter_map(|e| e.ok()?.file_name().to_str().map(str::to_string))
        .filter(|f| f.ends_with(".yaml"))
        .collect();
    assert_eq!(used_files, on_disk, "the kustomization uses every file of deploy/k8s/scale-out");

    // Secrets' values, for env entries that take theirs from one.
    let secret = |name: &str, key: &str| -> anyhow::Result<String> {
        let s = find(&objects, "Secret", name)?;
        Ok(str_at(&s.doc, &format!("stringData.{key}"))?.to_string())
    };
    let service_exists = |host: &str| objects.iter().any(|o| o.kind == "Service" && o.name == host);
    let claims: BTreeSet<&str> =
        objects.iter().filter(|o| o.kind == "PersistentVolumeClaim").map(|o| o.name.as_str()).collect();
    let mut stores = BTreeSet::new();
    let mut orchestrators = 0;
    for o in objects.iter().filter(|o| o.kind == "Deployment") {
        let mut check = || -> anyhow::Result<()> {
            let spec = at(&o.doc, "spec.template.spec").ok_or_else(|| anyhow!("no pod spec"))?;
            for v in seq_at(spec, "volumes").unwrap_or_default() {
                if let Some(claim) = at(v, "persistentVolumeClaim.claimName").and_then(Value::as_str) {
                    ensure!(claims.contains(claim), "mounts the claim {claim}, which the overlay removed");
                }
            }
            let container = seq_at(spec, "containers")?.first().ok_or_else(|| anyhow!("no container"))?;
            // Only depthmill's own binaries (Prometheus runs its image's entry point).
            let command = at(container, "command").and_then(Value::as_sequence);
            let Some(binary) = command.and_then(|c| c.first()).and_then(Value::as_str) else { return Ok(()) };
            let Some(service) = binary.strip_prefix("depthmill-") else { return Ok(()) };
            let mut env = BTreeMap::new();
            for e in seq_at(container, "env")? {
                let name = str_at(e, "name")?.to_string();
                let value = match (at(e, "value"), at(e, "valueFrom.secretKeyRef")) {
                    (Some(v), _) => v.as_str().map(str::to_string).unwrap_or_else(|| format!("{v:?}")),
                    (None, Some(r)) => secret(str_at(r, "name")?, str_at(r, "key")?)?,
                    (None, None) => bail!("env {name} has no value"),
                };
                ensure!(env.insert(name.clone(), value).is_none(), "env {name} twice");
            }
            use depthmill_common::config::load_with_env;
            let prefix = format!("DEPTHMILL_{}", service.to_ascii_uppercase());
            let store = match service {
                "orchestrator" => {
                    let c: depthmill_orchestrator::Config = load_with_env(None, &prefix, env)?;
                    let replicas = at(&o.doc, "spec.replicas").and_then(Value::as_u64).unwrap_or(1);
                    ensure!(replicas >= 2, "{replicas} orchestrator replica(s)");
                    orchestrators += replicas;
                    let url = c.database_url.clone().unwrap_or_default();
                    let host =
                        url.rsplit_once('@').and_then(|(_, h)| h.split(':').next()).unwrap_or_default();
                    ensure!(url.starts_with("postgres://") && service_exists(host), "database {url}");
                    c.artifact_store
                }
                "scanning" => load_with_env::<depthmill_scanning::Config>(None, &prefix, env)?.artifact_store,
                "reconstruction" => {
                    load_with_env::<depthmill_reconstruction::Config>(None, &prefix, env)?.artifact_store
                }
                "cam" => load_with_env::<depthmill_cam::Config>(None, &prefix, env)?.artifact_store,
                "machine" => load_with_env::<depthmill_machine::Config>(None, &prefix, env)?.artifact_store,
                other => bail!("unknown binary depthmill-{other}"),
            };
            let store = store.ok_or_else(|| anyhow!("no artifact_store"))?;
            let endpoint = store.options.get("endpoint").cloned().unwrap_or_default();
            let host = endpoint.trim_start_matches("http://").split(':').next().unwrap_or_default();
            ensure!(store.url.starts_with("s3://") && service_exists(host), "store {store:?}");
            ensure!(store.options.contains_key("secret_access_key"), "store without credentials");
            stores.insert(format!("{store:?}"));
            Ok(())
        };
        check().with_context(|| format!("deploy/k8s/scale-out: Deployment {}", o.name))?;
    }
    ensure!(orchestrators >= 2, "{orchestrators} orchestrator pods");
    ensure!(stores.len() == 1, "every service on one artifact store: {stores:?}");
    Ok(())
}
