//! The bad-input corpus (`tests/corpus/`, made by `tests/corpus/make.py`): every file goes through
//! the real REST and gRPC APIs as a user would send it (upload, then a job of the kind its reader
//! takes) and must be refused where `tests/corpus/corpus.toml` says (at upload, at submission, or
//! by the stage that reads it) with the code and the words it names: what is wrong and where
//! (line, byte, field, value, limit). Nothing is left of a refused upload or submission, no
//! service panics, and the next good request succeeds.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{Context as _, anyhow, bail, ensure};
use depthmill_proto::orchestrator::v1 as pb;
use depthmill_tests::{StackOptions, TestStack};
use serde_json::Value;

fn corpus_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("corpus")
}

/// One case of corpus.toml.
#[derive(Debug, serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct Case {
    /// Path under tests/corpus.
    file: String,
    /// Where it is refused: `upload`, `submit` or `job` (the stage reading it fails the job).
    refused_at: String,
    /// The error code (`invalid_argument`, `unsupported_media_type`, ...).
    code: String,
    /// Words the message must contain (case-sensitive).
    mentions: Vec<String>,
    /// The field the error names, when it names one.
    #[serde(default)]
    field: Option<String>,
    /// The stage that refuses it (for `job`).
    #[serde(default)]
    stage: Option<String>,
}

#[derive(Debug, serde::Deserialize)]
struct Corpus {
    case: Vec<Case>,
}

/// (media type, input kind) of a corpus folder.
fn reader_of(file: &str) -> anyhow::Result<(&'static str, &'static str)> {
    Ok(match file.split('/').next().unwrap_or_default() {
        "stl" => ("model/stl", "mesh"),
        "ply" => ("application/x-ply", "point_cloud"),
        "xyz" => ("text/x-xyz", "point_cloud"),
        "obj" => ("model/obj", "mesh"),
        "off" => ("model/x-off", "mesh"),
        "pcd" => ("application/x-pcd", "point_cloud"),
        "png" => ("image/png", "depth_map"),
        "npy" => ("application/x-npy", "depth_map"),
        "gcode" => ("text/x-gcode", "gcode"),
        "job" => ("application/json", "job"),
        other => bail!("no reader for folder {other}"),
    })
}

/// The job sections a job of `kind` needs (as the crash campaign submits them).
fn job_for(kind: &str, sha: &str) -> Value {
    let stages: &[&str] = match kind {
        "mesh" => &["scan", "reconstruct", "plan", "execute"],
        "point_cloud" => &["reconstruct", "plan", "execute"],
        "depth_map" => &["plan", "execute"],
        _ => &["execute"],
    };
    crate::crash::job(kind, sha, 0, stages)
}

/// What happened to one file: where it was refused, the code, the message, the field, the stage.
#[derive(Debug)]
struct Outcome {
    at: &'static str,
    code: String,
    message: String,
    field: Option<String>,
    stage: Option<String>,
}

fn error_of(body: &Value) -> (String, String, Option<String>) {
    let e = &body["error"];
    (
        e["code"].as_str().unwrap_or_default().to_string(),
        e["message"].as_str().unwrap_or_default().to_string(),
        e["field"].as_str().map(str::to_string),
    )
}

async fn run_file(stack: &TestStack, shas: &BTreeMap<&str, String>, file: &str) -> anyhow::Result<Outcome> {
    let bytes = std::fs::read(corpus_dir().join(file)).with_context(|| file.to_string())?;
    let (media_type, kind) = reader_of(file)?;
    let body: Value = if kind == "job" {
        // A job request: the corpus's placeholders name good artifacts.
        let mut text = String::from_utf8_lossy(&bytes).into_owned();
        for (name, sha) in shas {
            text = text.replace(&format!("@{name}@"), sha);
        }
        let resp = stack
            .http
            .post(stack.url("/v1/jobs"))
            .header("content-type", "application/json")
            .body(text)
            .send()
            .await?;
        let status = resp.status().as_u16();
        let body: Value = resp.json().await?;
        ensure!(status != 201, "{file}: accepted as a job: {body}");
        let (code, message, field) = error_of(&body);
        return Ok(Outcome { at: "submit", code, message, field, stage: None });
    } else {
        let resp = stack
            .http
            .post(stack.url("/v1/artifacts"))
            .header("content-type", media_type)
            .body(bytes)
            .send()
            .await?;
        let status = resp.status().as_u16();
        let body: Value = resp.json().await?;
        if status != 201 {
            let (code, message, field) = error_of(&body);
            return Ok(Outcome { at: "upload", code, message, field, stage: None });
        }
        body
    };
    let sha = body["sha256"].as_str().context("sha256")?;
    let (status, created) = stack.post_job(&job_for(kind, sha), None).await?;
    if status != 201 {
        let (code, message, field) = error_of(&created);
        return Ok(Outcome { at: "submit", code, message, field, stage: None });
    }
    let id = created["id"].as_str().context("id")?;
    let done = stack.wait_for_end(id, Duration::from_secs(120)).await?;
    ensure!(done["status"] == "failed", "{file}: the job did not fail: {done}");
    let e = &done["error"];
    Ok(Outcome {
        at: "job",
        code: e["code"].as_str().unwrap_or_default().to_string(),
        message: e["message"].as_str().unwrap_or_default().to_string(),
        field: None,
        stage: e["stage"].as_str().map(str::to_string),
    })
}

fn blob_count(dir: &Path) -> usize {
    let Ok(entries) = std::fs::read_dir(dir) else { return 0 };
    entries
        .filter_map(Result::ok)
        .map(|e| {
            let p = e.path();
            if p.is_dir() { blob_count(&p) } else { usize::from(!p.to_string_lossy().ends_with(".json")) }
        })
        .sum()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_corpus_file_is_refused_where_and_how_corpus_toml_says() -> anyhow::Result<()> {
    let corpus: Corpus = toml_from(&corpus_dir().join("corpus.toml"))?;
    let stack = TestStack::start_with(StackOptions { max_attempts: 2, ..Default::default() }).await?;
    // Good artifacts the job requests of the corpus refer to.
    let mut shas = BTreeMap::new();
    shas.insert("GCODE", stack.upload("text/x-gcode", crate::program()).await?);
    let cloud: Vec<u8> = (0..400).flat_map(|i| format!("{} {} 1\n", i % 20, i / 20).into_bytes()).collect();
    shas.insert("CLOUD", stack.upload("text/x-xyz", cloud).await?);

    // Every file of the corpus has a case, and every case a file.
    let mut on_disk = Vec::new();
    for dir in std::fs::read_dir(corpus_dir())? {
        let dir = dir?.path();
        if dir.is_dir() {
            for f in std::fs::read_dir(&dir)? {
                let f = f?.path();
                on_disk.push(f.strip_prefix(corpus_dir())?.display().to_string());
            }
        }
    }
    on_disk.sort();
    let mut listed: Vec<String> = corpus.case.iter().map(|c| c.file.clone()).collect();
    listed.sort();
    assert_eq!(listed, on_disk, "corpus.toml lists every file of tests/corpus");

    let blobs_before = blob_count(&stack.data_dir.join("artifacts/blobs"));
    let mut failures = Vec::new();
    let (mut uploads_kept, mut jobs_made) = (0usize, 0usize);
    for case in &corpus.case {
        let got = run_file(&stack, &shas, &case.file).await.with_context(|| case.file.clone())?;
        let mut wrong = Vec::new();
        if got.at != case.refused_at {
            wrong.push(format!("refused at {} (expected {})", got.at, case.refused_at));
        }
        if got.code != case.code {
            wrong.push(format!("code {} (expected {})", got.code, case.code));
        }
        for m in &case.mentions {
            if !got.message.contains(m.as_str()) {
                wrong.push(format!("message does not mention '{m}'"));
            }
        }
        if case.field.is_some() && got.field != case.field {
            wrong.push(format!("field {:?} (expected {:?})", got.field, case.field));
        }
        if case.stage.is_some() && got.stage != case.stage {
            wrong.push(format!("stage {:?} (expected {:?})", got.stage, case.stage));
        }
        if got.message.contains("panicked") || got.message.is_empty() {
            wrong.push("no clear message".into());
        }
        if got.at != "upload" && !case.file.starts_with("job/") {
            uploads_kept += 1;
        }
        if got.at == "job" {
            jobs_made += 1;
        }
        if !wrong.is_empty() {
            failures.push(format!("{}: {} — got {got:?}", case.file, wrong.join("; ")));
        }
    }
    if !failures.is_empty() {
        bail!("{} of {} corpus cases differ:\n{}", failures.len(), corpus.case.len(), failures.join("\n"));
    }

    // Nothing of a refused upload or submission is left: only accepted uploads are blobs, and
    // only jobs that a stage refused exist.
    let blobs_after = blob_count(&stack.data_dir.join("artifacts/blobs"));
    ensure!(
        blobs_after <= blobs_before + uploads_kept,
        "{blobs_after} blobs after the corpus, {blobs_before} before and {uploads_kept} uploads accepted"
    );
    let listed: Value = stack.http.get(stack.url("/v1/jobs?limit=1000")).send().await?.json().await?;
    let jobs = listed["jobs"].as_array().map_or(0, Vec::len);
    ensure!(jobs == jobs_made, "{jobs} jobs exist, {jobs_made} made it past submission");

    // gRPC: the same uploads refused the same way, and the same submissions refused.
    let mut client = stack.grpc().await?;
    for case in corpus.case.iter().filter(|c| c.refused_at == "upload") {
        let bytes = std::fs::read(corpus_dir().join(&case.file))?;
        let (media_type, _) = reader_of(&case.file)?;
        let chunks = vec![pb::UploadArtifactRequest { media_type: media_type.into(), data: bytes }];
        let status = client
            .upload_artifact(futures::stream::iter(chunks))
            .await
            .err()
            .ok_or_else(|| anyhow!("{}: accepted over gRPC", case.file))?;
        ensure!(
            status.code() != tonic::Code::Ok && status.code() != tonic::Code::Internal,
            "{}: {status:?}",
            case.file
        );
        for m in &case.mentions {
            ensure!(
                status.message().contains(m.as_str()),
                "{}: gRPC message {:?} lacks '{m}'",
                case.file,
                status.message()
            );
        }
    }

    // gRPC messages with fields out of range: refused with INVALID_ARGUMENT naming the field.
    use depthmill_proto::machine::v1 as machine;
    let gcode_input =
        |artifact: &str, kind: i32| pb::JobInput { kind, artifact: artifact.into(), ..Default::default() };
    let with_cell = |cell_mm: f64| pb::JobSpec {
        input: Some(gcode_input(&shas["GCODE"], pb::InputKind::Gcode as i32)),
        execute: Some(machine::ExecuteParams { cell_mm: Some(cell_mm), ..Default::default() }),
        ..Default::default()
    };
    let bad_specs: Vec<(Option<pb::JobSpec>, &str)> = vec![
        (None, "spec"),
        (Some(pb::JobSpec { input: Some(gcode_input(&shas["GCODE"], 99)), ..Default::default() }), "kind"),
        (
            Some(pb::JobSpec {
                input: Some(gcode_input("not-a-digest", pb::InputKind::Gcode as i32)),
                ..Default::default()
            }),
            "artifact",
        ),
        (Some(with_cell(f64::NAN)), "cell_mm"),
        (Some(with_cell(-1.0)), "cell_mm"),
        (Some(with_cell(1e300)), "cell_mm"),
    ];
    for (spec, names) in bad_specs {
        let status = client
            .create_job(pb::CreateJobRequest { spec, idempotency_key: String::new() })
            .await
            .err()
            .ok_or_else(|| anyhow!("a job with a bad {names} was accepted over gRPC"))?;
        ensure!(status.code() == tonic::Code::InvalidArgument, "{names}: {status:?}");
        ensure!(status.message().contains(names), "{names}: {:?}", status.message());
    }
    let listed: Value = stack.http.get(stack.url("/v1/jobs?limit=1000")).send().await?.json().await?;
    ensure!(listed["jobs"].as_array().map_or(0, Vec::len) == jobs_made, "a refused gRPC job was kept");

    // The next good request succeeds.
    let good = crate::crash::inputs()?.into_iter().find(|i| i.kind == "gcode").context("a G-code input")?;
    let sha = stack.upload(good.media_type, good.bytes).await?;
    let (status, job) = stack.post_job(&crate::crash::job("gcode", &sha, 1, &good.stages), None).await?;
    ensure!(status == 201, "{job}");
    let done = stack.wait_for_end(job["id"].as_str().context("id")?, Duration::from_secs(60)).await?;
    ensure!(done["status"] == "succeeded", "{done}");
    stack.shutdown().await
}

fn toml_from<T: serde::de::DeserializeOwned>(path: &Path) -> anyhow::Result<T> {
    let text = std::fs::read_to_string(path).with_context(|| path.display().to_string())?;
    toml::from_str(&text).with_context(|| path.display().to_string())
}
