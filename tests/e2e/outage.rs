//! The job database goes away (a network cut between the orchestrator and PostgreSQL): requests
//! fail with 503 `unavailable` and a Retry-After, nothing is half-made, and when the database is
//! reachable again the service carries on by itself and the jobs finish.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use anyhow::{Context as _, bail};
use depthmill_orchestrator::store::scratch::ScratchDatabase;
use depthmill_tests::{StackOptions, TestStack};
use serde_json::{Value, json};
use tokio::net::{TcpListener, TcpStream};
use tokio_util::sync::CancellationToken;

/// A TCP proxy that can cut every connection through it and refuse new ones, like a network
/// partition.
pub(crate) struct Partition {
    up: Arc<AtomicBool>,
    cut: std::sync::Mutex<CancellationToken>,
}

impl Partition {
    pub(crate) async fn start(target: String) -> anyhow::Result<(Arc<Self>, u16)> {
        let listener = TcpListener::bind("127.0.0.1:0").await?;
        let port = listener.local_addr()?.port();
        let me = Arc::new(Self { up: Arc::new(AtomicBool::new(true)), cut: Default::default() });
        let proxy = me.clone();
        tokio::spawn(async move {
            while let Ok((mut client, _)) = listener.accept().await {
                if !proxy.up.load(Ordering::SeqCst) {
                    continue; // dropped: the client sees the connection close at once
                }
                let cut = proxy.cut.lock().map(|c| c.clone()).unwrap_or_default();
                let target = target.clone();
                tokio::spawn(async move {
                    let Ok(mut server) = TcpStream::connect(&target).await else { return };
                    tokio::select! {
                        _ = tokio::io::copy_bidirectional(&mut client, &mut server) => {}
                        () = cut.cancelled() => {}
                    }
                });
            }
        });
        Ok((me, port))
    }

    pub(crate) fn down(&self) {
        self.up.store(false, Ordering::SeqCst);
        if let Ok(mut cut) = self.cut.lock() {
            cut.cancel();
            *cut = CancellationToken::new();
        }
    }

    pub(crate) fn restore(&self) {
        self.up.store(true, Ordering::SeqCst);
    }
}

fn program() -> Vec<u8> {
    b"%\nG21 G90\nT1 M6\nS1500 M3\nG43 H1\nG0 X-5 Y5\nG0 Z12\nG1 Z9.5 F100\nG1 X35 F300\nG0 Z15\nM30\n%\n"
        .to_vec()
}

fn job(sha: &str) -> Value {
    json!({"input": {"kind": "gcode", "artifact": sha},
           "execute": {"machine": "emco-f1", "adaptive": "off", "compare": false, "cell_mm": 0.5}})
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_database_outage_is_503_and_the_service_recovers_by_itself() -> anyhow::Result<()> {
    let db = ScratchDatabase::create().await?;
    let mut url = reqwest::Url::parse(&db.url())?;
    let target = format!("{}:{}", url.host_str().context("host")?, url.port().unwrap_or(5432));
    let (partition, port) = Partition::start(target).await?;
    url.set_port(Some(port)).map_err(|()| anyhow::anyhow!("cannot set the port"))?;
    let stack =
        TestStack::start_with(StackOptions { database_url: Some(url.to_string()), ..Default::default() })
            .await?;
    let sha = stack.upload("text/x-gcode", program()).await?;
    let (status, before) = stack.post_job(&job(&sha), Some("before")).await?;
    assert_eq!(status, 201, "{before}");

    partition.down();
    for (what, request) in [
        ("list", stack.http.get(stack.url("/v1/jobs"))),
        ("ready", stack.http.get(stack.url("/readyz"))),
        (
            "submit",
            stack.http.post(stack.url("/v1/jobs")).header("Idempotency-Key", "during").json(&job(&sha)),
        ),
    ] {
        let resp = request.send().await?;
        assert_eq!(resp.status().as_u16(), 503, "{what}");
        assert!(resp.headers().contains_key("retry-after"), "{what}");
        let body: Value = resp.json().await?;
        assert_eq!(body["error"]["code"], "unavailable", "{what}: {body}");
    }
    // The process keeps serving what does not need the database.
    assert_eq!(stack.http.get(stack.url("/healthz")).send().await?.status().as_u16(), 200);

    partition.restore();
    let deadline = Instant::now() + Duration::from_secs(30);
    while stack.http.get(stack.url("/readyz")).send().await?.status().as_u16() != 200 {
        if Instant::now() > deadline {
            bail!("the orchestrator did not recover after the database came back");
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let (status, after) = stack.post_job(&job(&sha), Some("after")).await?;
    assert_eq!(status, 201, "{after}");
    for created in [&before, &after] {
        let id = created["id"].as_str().context("id")?;
        let done = stack.wait_for_end(id, Duration::from_secs(60)).await?;
        assert_eq!(done["status"], "succeeded", "{done}");
    }
    // The refused submission made nothing.
    let listed: Value = stack.http.get(stack.url("/v1/jobs")).send().await?.json().await?;
    assert_eq!(listed["jobs"].as_array().map(Vec::len), Some(2), "{listed}");
    stack.shutdown().await
}

/// Another process holds the SQLite file's write lock: a submission waits out the busy timeout
/// and fails with 503 and Retry-After (nothing made), reads keep working (WAL), and once the lock
/// is gone submissions succeed again.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_locked_sqlite_file_is_503_for_writes_and_reads_go_on() -> anyhow::Result<()> {
    use sqlx::{Connection as _, Executor as _};
    let stack = TestStack::start().await?;
    let sha = stack.upload("text/x-gcode", program()).await?;
    let db = stack.data_dir.join("jobs.sqlite");
    let mut locker = sqlx::SqliteConnection::connect(&format!("sqlite://{}", db.display())).await?;
    locker.execute("BEGIN EXCLUSIVE").await?;

    let resp = stack
        .http
        .post(stack.url("/v1/jobs"))
        .header("Idempotency-Key", "locked")
        .json(&job(&sha))
        .send()
        .await?;
    assert_eq!(resp.status().as_u16(), 503, "submission while locked");
    assert!(resp.headers().contains_key("retry-after"));
    let body: Value = resp.json().await?;
    assert_eq!(body["error"]["code"], "unavailable", "{body}");
    let listed = stack.http.get(stack.url("/v1/jobs")).send().await?;
    assert_eq!(listed.status().as_u16(), 200, "reads go on under a write lock");

    locker.execute("ROLLBACK").await?;
    locker.close().await?;
    let (status, created) = stack.post_job(&job(&sha), Some("locked")).await?;
    assert_eq!(status, 201, "{created}");
    let listed: Value = stack.http.get(stack.url("/v1/jobs")).send().await?.json().await?;
    assert_eq!(
        listed["jobs"].as_array().map(Vec::len),
        Some(1),
        "the refused submission made nothing: {listed}"
    );
    stack.shutdown().await
}

/// A size-limited tmpfs for one test, unmounted when dropped.
struct SmallDisk {
    path: std::path::PathBuf,
    _dir: tempfile::TempDir,
}

impl SmallDisk {
    /// `None` when this machine cannot mount one (not root) and `DEPTHMILL_REQUIRE_TMPFS` is unset.
    fn mount(size: &str) -> anyhow::Result<Option<Self>> {
        let dir = tempfile::tempdir()?;
        let path = dir.path().join("disk");
        std::fs::create_dir(&path)?;
        let out = std::process::Command::new("mount")
            .args(["-t", "tmpfs", "-o", &format!("size={size}"), "tmpfs"])
            .arg(&path)
            .output();
        match out {
            Ok(o) if o.status.success() => Ok(Some(Self { path, _dir: dir })),
            other => {
                let why = match other {
                    Ok(o) => String::from_utf8_lossy(&o.stderr).into_owned(),
                    Err(e) => e.to_string(),
                };
                if std::env::var_os("DEPTHMILL_REQUIRE_TMPFS").is_some() {
                    bail!("DEPTHMILL_REQUIRE_TMPFS is set but a tmpfs cannot be mounted: {why}");
                }
                eprintln!("cannot mount a tmpfs ({why}): skipping the full-disk test");
                Ok(None)
            }
        }
    }
}

impl Drop for SmallDisk {
    fn drop(&mut self) {
        let _ = std::process::Command::new("umount").arg("-l").arg(&self.path).status();
    }
}

fn bytes_under(dir: &std::path::Path) -> u64 {
    let Ok(entries) = std::fs::read_dir(dir) else { return 0 };
    entries
        .filter_map(Result::ok)
        .map(|e| match e.file_type() {
            Ok(t) if t.is_dir() => bytes_under(&e.path()),
            _ => e.metadata().map(|m| m.len()).unwrap_or(0),
        })
        .sum()
}

/// The artifact store's disk fills up during an upload: 503 naming the full store, no partial
/// file left behind, and the service goes on with what fits.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_full_artifact_disk_is_503_and_leaves_nothing_half_written() -> anyhow::Result<()> {
    let Some(disk) = SmallDisk::mount("8m")? else { return Ok(()) };
    let artifacts = disk.path.join("artifacts");
    let stack = TestStack::start_with(StackOptions {
        artifacts_dir: Some(artifacts.clone()),
        max_upload_bytes: 64 << 20,
        ..Default::default()
    })
    .await?;
    let before = bytes_under(&artifacts);
    let big = "G0 X0 Y0\n".repeat(1_500_000).into_bytes(); // 13.5 MB on an 8 MB disk
    let resp = stack
        .http
        .post(stack.url("/v1/artifacts"))
        .header("content-type", "text/x-gcode")
        .body(big)
        .send()
        .await?;
    assert_eq!(resp.status().as_u16(), 503);
    assert!(resp.headers().contains_key("retry-after"));
    let body: Value = resp.json().await?;
    assert_eq!(body["error"]["code"], "unavailable", "{body}");
    assert!(body["error"]["message"].as_str().unwrap_or_default().contains("out of space"), "{body}");
    let after = bytes_under(&artifacts);
    assert!(after <= before + 4096, "{after} bytes under the store after a refused upload ({before} before)");

    // What fits still goes in, and a job runs.
    let sha = stack.upload("text/x-gcode", program()).await?;
    let (status, created) = stack.post_job(&job(&sha), None).await?;
    assert_eq!(status, 201, "{created}");
    let done = stack.wait_for_end(created["id"].as_str().context("id")?, Duration::from_secs(60)).await?;
    assert_eq!(done["status"], "succeeded", "{done}");
    stack.shutdown().await?;
    drop(disk);
    Ok(())
}
