//! The client verbs: REST calls to a running orchestrator.

use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{Context as _, bail};
use futures::StreamExt as _;
use serde_json::Value;

/// Where the orchestrator is.
#[derive(clap::Args)]
pub struct Server {
    /// Orchestrator REST base URL.
    #[arg(long, env = "DEPTHMILL_URL", default_value = "http://127.0.0.1:8080")]
    url: String,
    /// API token, when the server requires one (see `depthmill token create`).
    #[arg(long, env = "DEPTHMILL_TOKEN", hide_env_values = true)]
    token: Option<String>,
    /// For an https:// URL: trust only this CA certificate (PEM), e.g. a private CA or the
    /// server's self-signed certificate. Default: the system's trusted roots.
    #[arg(long, env = "DEPTHMILL_CA_CERT")]
    ca_cert: Option<PathBuf>,
}

impl Server {
    fn url(&self, path: &str) -> String {
        format!("{}{path}", self.url.trim_end_matches('/'))
    }

    /// An HTTP client that sends the token with every request.
    fn http(&self) -> anyhow::Result<reqwest::Client> {
        let mut headers = reqwest::header::HeaderMap::new();
        if let Some(token) = &self.token {
            let mut value = reqwest::header::HeaderValue::from_str(&format!("Bearer {}", token.trim()))
                .context("the API token has characters a header cannot carry")?;
            value.set_sensitive(true);
            headers.insert(reqwest::header::AUTHORIZATION, value);
        }
        let mut builder = depthmill_common::tls::http_client()
            .connect_timeout(Duration::from_secs(10))
            .default_headers(headers);
        if let Some(path) = &self.ca_cert {
            let pem = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
            let cert = reqwest::Certificate::from_pem(&pem)
                .with_context(|| format!("{} holds no PEM certificate", path.display()))?;
            builder = builder.tls_certs_only([cert]);
        }
        builder.build().context("building the HTTP client")
    }
}

/// Turns an error reply into a readable error: `{"error": {"code", "message", "field"}}`.
async fn check(resp: reqwest::Response, what: &str) -> anyhow::Result<reqwest::Response> {
    if resp.status().is_success() {
        return Ok(resp);
    }
    let status = resp.status();
    let body = resp.text().await.unwrap_or_default();
    let detail = serde_json::from_str::<Value>(&body)
        .ok()
        .and_then(|v| {
            v.get("error").and_then(|e| e.get("message")).and_then(Value::as_str).map(str::to_string)
        })
        .unwrap_or(body);
    bail!("{what} failed ({status}): {detail}")
}

pub struct Submit {
    pub file: PathBuf,
    pub kind: Option<String>,
    pub options: Option<PathBuf>,
    pub name: Option<String>,
    pub pixel_mm: Option<f64>,
    pub z_min_mm: Option<f64>,
    pub z_max_mm: Option<f64>,
    pub units: Option<String>,
    pub idempotency_key: Option<String>,
    /// Sets `"process": "robot"`.
    pub robot: bool,
}

/// Kind and media type of an input file, by extension; a PLY file is a mesh when its header
/// declares faces, a point cloud otherwise. A mesh or cloud may be gzip-compressed (`.stl.gz`,
/// `.ply.gz`, ...): it is sent as it is, under its content's type, and read decompressed.
pub fn classify(path: &Path) -> Option<(&'static str, &'static str)> {
    let mut ext = path.extension()?.to_str()?.to_ascii_lowercase();
    let gz = ext == "gz";
    if gz {
        ext = Path::new(path.file_stem()?).extension()?.to_str()?.to_ascii_lowercase();
    }
    let (kind, media) = classify_ext(&ext, path)?;
    (!gz || matches!(kind, "mesh" | "point_cloud")).then_some((kind, media))
}

fn classify_ext(ext: &str, path: &Path) -> Option<(&'static str, &'static str)> {
    Some(match ext {
        "stl" => ("mesh", "model/stl"),
        "off" => ("mesh", "model/x-off"),
        "obj" => ("mesh", "model/obj"),
        "pcd" => ("point_cloud", "application/x-pcd"),
        "xyz" | "txt" | "asc" => ("point_cloud", "text/x-xyz"),
        "ply" if ply_has_faces(path) => ("mesh", "application/x-ply"),
        "ply" => ("point_cloud", "application/x-ply"),
        "png" => ("depth_map", "image/png"),
        "npy" => ("depth_map", "application/x-npy"),
        "ngc" | "nc" | "gcode" | "tap" | "cnc" => ("gcode", "text/x-gcode"),
        _ => return None,
    })
}

/// True when the PLY header of `path` declares a non-empty `face` element.
fn ply_has_faces(path: &Path) -> bool {
    let Ok(head) = depthmill_geometry::units::read_head(path) else { return false };
    let text = String::from_utf8_lossy(&head);
    text.lines()
        .take_while(|l| l.trim() != "end_header")
        .filter_map(|l| l.trim().strip_prefix("element face "))
        .any(|n| n.trim().parse::<u64>().is_ok_and(|n| n > 0))
}

pub async fn submit(server: &Server, s: Submit) -> anyhow::Result<String> {
    let (guess_kind, media_type) = classify(&s.file).with_context(|| {
        format!(
            "cannot tell the type of {} from its extension (stl, obj, off, ply, pcd, xyz, each also .gz; png, npy, ngc)",
            s.file.display()
        )
    })?;
    let kind = s.kind.unwrap_or_else(|| guess_kind.to_string());
    let mut job: Value = match &s.options {
        Some(p) => {
            let text = std::fs::read_to_string(p).with_context(|| format!("reading {}", p.display()))?;
            serde_json::from_str(&text).with_context(|| format!("{} is not JSON", p.display()))?
        }
        None => serde_json::json!({}),
    };
    let obj = job.as_object_mut().with_context(|| "the options file must hold a JSON object")?;

    let file =
        tokio::fs::File::open(&s.file).await.with_context(|| format!("opening {}", s.file.display()))?;
    let len = file.metadata().await?.len();
    let body = reqwest::Body::wrap_stream(tokio_util::io::ReaderStream::new(file));
    let client = server.http()?;
    let resp = client
        .post(server.url("/v1/artifacts"))
        .header(reqwest::header::CONTENT_TYPE, media_type)
        .header(reqwest::header::CONTENT_LENGTH, len)
        .body(body)
        .send()
        .await
        .with_context(|| format!("uploading to {}", server.url))?;
    let artifact: Value = check(resp, "upload").await?.json().await?;
    let sha =
        artifact.get("sha256").and_then(Value::as_str).context("upload reply has no sha256")?.to_string();

    let mut input = serde_json::json!({"kind": kind, "artifact": sha});
    for (k, v) in [("pixel_mm", s.pixel_mm), ("z_min_mm", s.z_min_mm), ("z_max_mm", s.z_max_mm)] {
        if let Some(v) = v {
            input[k] = serde_json::json!(v);
        }
    }
    if let Some(u) = &s.units {
        input["units"] = serde_json::json!(u);
    }
    obj.insert("input".into(), input);
    if s.robot {
        obj.insert("process".into(), Value::String("robot".into()));
    }
    let name = s
        .name
        .unwrap_or_else(|| s.file.file_stem().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default());
    obj.entry("name").or_insert(Value::String(name));
    let mut req = client.post(server.url("/v1/jobs")).json(&job);
    if let Some(k) = &s.idempotency_key {
        req = req.header("Idempotency-Key", k);
    }
    let created: Value = check(req.send().await?, "submit").await?.json().await?;
    created.get("id").and_then(Value::as_str).map(str::to_string).context("job reply has no id")
}

async fn get_job(server: &Server, id: &str) -> anyhow::Result<Value> {
    let resp = server.http()?.get(server.url(&format!("/v1/jobs/{id}"))).send().await?;
    Ok(check(resp, "status").await?.json().await?)
}

fn summary(job: &Value) -> String {
    let s = |k: &str| job.get(k).and_then(Value::as_str).unwrap_or("?").to_string();
    let progress = job.get("progress").and_then(Value::as_f64).unwrap_or(0.0);
    let mut line =
        format!("{} {} stage={} progress={:.0}%", s("id"), s("status"), s("stage"), progress * 100.0);
    if let Some(e) = job.get("error").filter(|e| !e.is_null()) {
        let code = e.get("code").and_then(Value::as_str).unwrap_or("");
        let msg = e.get("message").and_then(Value::as_str).unwrap_or("");
        line.push_str(&format!(" error={code}: {msg}"));
    }
    line
}

pub async fn status(server: &Server, id: &str, json: bool) -> anyhow::Result<()> {
    let job = get_job(server, id).await?;
    if json {
        crate::outln!("{}", serde_json::to_string_pretty(&job)?);
    } else {
        crate::outln!("{}", summary(&job));
        if let Some(t) = job.get("stage_timings_s").and_then(Value::as_object) {
            for (stage, secs) in t {
                crate::outln!("  {stage:<12} {:>8.2} s", secs.as_f64().unwrap_or(0.0));
            }
        }
        // What the stages said about the part: what could not be done and where, what was chosen.
        for d in job.get("diagnostics").and_then(Value::as_array).into_iter().flatten() {
            let s = |k: &str| d.get(k).and_then(Value::as_str).unwrap_or("?");
            crate::outln!("  {} {}: {}", s("stage"), s("code"), s("message"));
        }
    }
    Ok(())
}

/// Follows the job's server-sent events with a progress bar.
pub async fn watch(server: &Server, id: &str) -> anyhow::Result<()> {
    let bar = indicatif::ProgressBar::new(1000);
    bar.set_style(
        indicatif::ProgressStyle::with_template("{spinner} [{elapsed_precise}] {bar:40} {percent:>3}% {msg}")
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    let resp = server.http()?.get(server.url(&format!("/v1/jobs/{id}/events"))).send().await?;
    let mut stream = check(resp, "watch").await?.bytes_stream();
    let mut buf = String::new();
    let mut last: Option<Value> = None;
    while let Some(chunk) = stream.next().await {
        buf.push_str(&String::from_utf8_lossy(&chunk.context("reading events")?));
        while let Some(end) = buf.find("\n\n") {
            let event: String = buf.drain(..end + 2).collect();
            let data: String = event
                .lines()
                .filter_map(|l| l.strip_prefix("data:"))
                .map(str::trim_start)
                .collect::<Vec<_>>()
                .join("\n");
            if data.is_empty() {
                continue;
            }
            let Ok(job) = serde_json::from_str::<Value>(&data) else { continue };
            let progress = job.get("progress").and_then(Value::as_f64).unwrap_or(0.0);
            bar.set_position((progress * 1000.0) as u64);
            let stage = job.get("stage").and_then(Value::as_str).unwrap_or("?");
            let status = job.get("status").and_then(Value::as_str).unwrap_or("?");
            bar.set_message(format!("{status} {stage}"));
            last = Some(job);
        }
    }
    bar.finish();
    let job = match last {
        Some(j) => j,
        None => get_job(server, id).await?,
    };
    crate::outln!("{}", summary(&job));
    match job.get("status").and_then(Value::as_str) {
        Some("succeeded") => Ok(()),
        Some(s) => bail!("job {id} ended {s}"),
        None => bail!("job {id} has no status"),
    }
}

/// The file name an artifact is written under: its name (characters other than letters, digits,
/// `_` and `-` replaced by `_`) and the extension of its media type.
pub fn artifact_file_name(name: &str, media_type: &str) -> String {
    let ext = match media_type {
        "model/stl" => "stl",
        "application/x-ply" => "ply",
        "text/x-xyz" => "xyz",
        "model/obj" => "obj",
        "model/x-off" => "off",
        "application/x-pcd" => "pcd",
        "image/png" => "png",
        "application/x-npy" => "npy",
        "text/x-gcode" => "ngc",
        "application/json" => "json",
        "text/html" => "html",
        "text/csv" => "csv",
        "image/svg+xml" => "svg",
        _ => "bin",
    };
    let safe: String = name
        .chars()
        .map(|c| if c.is_ascii_alphanumeric() || c == '_' || c == '-' { c } else { '_' })
        .collect();
    format!("{safe}.{ext}")
}

/// Writes `job.json` and every artifact (named `<artifact name>.<ext>`) into `output`.
pub async fn fetch(server: &Server, id: &str, output: &Path) -> anyhow::Result<()> {
    let job = get_job(server, id).await?;
    tokio::fs::create_dir_all(output).await.with_context(|| format!("creating {}", output.display()))?;
    tokio::fs::write(output.join("job.json"), serde_json::to_vec_pretty(&job)?).await?;
    let client = server.http()?;
    let artifacts = job.get("artifacts").and_then(Value::as_object).cloned().unwrap_or_default();
    for (name, a) in artifacts {
        let sha = a.get("sha256").and_then(Value::as_str).context("artifact without sha256")?;
        let media = a.get("media_type").and_then(Value::as_str).unwrap_or("");
        let path = output.join(artifact_file_name(&name, media));
        let resp = client.get(server.url(&format!("/v1/artifacts/{sha}"))).send().await?;
        let mut stream = check(resp, "download").await?.bytes_stream();
        let mut file =
            tokio::fs::File::create(&path).await.with_context(|| format!("creating {}", path.display()))?;
        while let Some(chunk) = stream.next().await {
            tokio::io::AsyncWriteExt::write_all(&mut file, &chunk?).await?;
        }
        crate::outln!("{}", path.display());
    }
    crate::outln!("{}", output.join("job.json").display());
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The client verbs speak HTTPS: with `--ca-cert` naming the server's (self-signed)
    /// certificate they reach it; without, the certificate is refused with a clear error.
    #[tokio::test]
    async fn client_verbs_reach_an_https_server_that_the_given_ca_vouches_for() -> anyhow::Result<()> {
        let dir = tempfile::tempdir()?;
        let cert = rcgen::generate_simple_self_signed(vec!["localhost".into()])?;
        let files = depthmill_common::tls::TlsFiles {
            cert: dir.path().join("cert.pem"),
            key: dir.path().join("key.pem"),
        };
        std::fs::write(&files.cert, cert.cert.pem())?;
        std::fs::write(&files.key, cert.signing_key.serialize_pem())?;
        let acceptor = depthmill_common::tls::Identity::load(&files)?.http1_acceptor()?;
        let router = axum::Router::new().route(
            "/v1/jobs/{id}",
            axum::routing::get(|axum::extract::Path(id): axum::extract::Path<String>| async move {
                axum::Json(
                    serde_json::json!({"id": id, "status": "succeeded", "stage": "report", "progress": 1.0}),
                )
            }),
        );
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
        let port = listener.local_addr()?.port();
        let stop = tokio_util::sync::CancellationToken::new();
        let stopped = stop.clone();
        let server_task = tokio::spawn(async move {
            depthmill_common::tls::serve_https(listener, router, acceptor, async move {
                stopped.cancelled().await
            })
            .await
        });
        let url = format!("https://localhost:{port}");
        let trusted = Server { url: url.clone(), token: None, ca_cert: Some(files.cert.clone()) };
        status(&trusted, "job-1", true).await?;
        let untrusted = Server { url, token: None, ca_cert: None };
        let err = status(&untrusted, "job-1", true).await.expect_err("self-signed without --ca-cert");
        let chain = format!("{err:#}");
        assert!(chain.contains("certificate") || chain.contains("error sending request"), "{chain}");
        let wrong = Server {
            url: "https://localhost:1".into(),
            token: None,
            ca_cert: Some(dir.path().join("nope.pem")),
        };
        let err = status(&wrong, "job-1", true).await.expect_err("missing CA file");
        assert!(format!("{err:#}").contains("nope.pem"), "{err:#}");
        stop.cancel();
        server_task.await??;
        Ok(())
    }
}
