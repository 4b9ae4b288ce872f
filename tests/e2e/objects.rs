//! The artifact store on both of its backends: the local folder (the default) and an S3 bucket
//! served on loopback by a real S3-protocol server (`s3s-fs`, the `s3s` project's file-system
//! S3 implementation). One suite runs on both: small and multipart uploads streamed and read back,
//! deduplication, failed uploads that leave nothing, local copies checked against the digest, an
//! S3 server that goes away (503, then recovery), and whole jobs with every service on the bucket.

use std::time::Duration;

use anyhow::Context as _;
use depthmill_common::artifacts::{
    ArtifactError, ArtifactStore, ObjectArtifactStore, ObjectStoreConfig, open_store,
};
use depthmill_tests::{StackOptions, TestStack};
use futures::TryStreamExt as _;
use object_store::ObjectStore as _;
use serde_json::json;
use sha2::Digest as _;
use tokio::io::AsyncReadExt as _;

use crate::outage::Partition;

const ACCESS_KEY: &str = "depthmill-test";
const SECRET_KEY: &str = "depthmill-test-secret";
const BUCKET: &str = "artifacts";

/// An S3 server (s3s-fs) on a loopback port, storing under a temporary folder.
pub struct S3Server {
    pub endpoint: String,
    pub root: tempfile::TempDir,
    stop: tokio_util::sync::CancellationToken,
}

impl S3Server {
    pub async fn start() -> anyhow::Result<Self> {
        let root = tempfile::tempdir()?;
        // A bucket of s3s-fs is a folder under its root.
        std::fs::create_dir_all(root.path().join(BUCKET))?;
        let fs = s3s_fs::FileSystem::new(root.path()).map_err(|e| anyhow::anyhow!("s3s-fs: {e:?}"))?;
        let mut builder = s3s::service::S3ServiceBuilder::new(fs);
        builder.set_auth(s3s::auth::SimpleAuth::from_single(ACCESS_KEY, SECRET_KEY));
        let service = builder.build();
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
        let endpoint = format!("http://{}", listener.local_addr()?);
        let stop = tokio_util::sync::CancellationToken::new();
        let stopped = stop.clone();
        tokio::spawn(async move {
            loop {
                let socket = tokio::select! {
                    accepted = listener.accept() => match accepted {
                        Ok((socket, _)) => socket,
                        Err(_) => continue,
                    },
                    () = stopped.cancelled() => return,
                };
                let service = service.clone();
                tokio::spawn(async move {
                    let io = hyper_util::rt::TokioIo::new(socket);
                    let _ = hyper::server::conn::http1::Builder::new().serve_connection(io, service).await;
                });
            }
        });
        Ok(Self { endpoint, root, stop })
    }

    /// The store configuration of a client of this server at `endpoint` (this server's own, or a
    /// proxy in front of it), keys under `prefix`.
    pub fn config(&self, endpoint: &str, prefix: &str) -> ObjectStoreConfig {
        let options = [
            ("endpoint", endpoint),
            ("access_key_id", ACCESS_KEY),
            ("secret_access_key", SECRET_KEY),
            ("region", "us-east-1"),
            ("aws_allow_http", "true"),
        ];
        ObjectStoreConfig {
            url: format!("s3://{BUCKET}/{prefix}"),
            options: options.iter().map(|(k, v)| (k.to_string(), v.to_string())).collect(),
        }
    }

    /// Every key in the bucket, through a plain S3 client.
    async fn keys(&self) -> anyhow::Result<Vec<String>> {
        let s3 = object_store::aws::AmazonS3Builder::new()
            .with_bucket_name(BUCKET)
            .with_endpoint(&self.endpoint)
            .with_access_key_id(ACCESS_KEY)
            .with_secret_access_key(SECRET_KEY)
            .with_region("us-east-1")
            .with_allow_http(true)
            .build()?;
        let listed: Vec<object_store::ObjectMeta> = s3.list(None).try_collect().await?;
        let mut keys: Vec<String> = listed.into_iter().map(|m| m.location.to_string()).collect();
        keys.sort();
        Ok(keys)
    }
}

impl Drop for S3Server {
    fn drop(&mut self) {
        self.stop.cancel();
    }
}

/// The backends the suite runs on.
enum Backend {
    Local(tempfile::TempDir),
    S3(S3Server, tempfile::TempDir),
}

impl Backend {
    async fn open(&self) -> anyhow::Result<ObjectArtifactStore> {
        Ok(match self {
            Backend::Local(dir) => open_store(&dir.path().join("artifacts"), None).await?,
            Backend::S3(server, cache) => {
                open_store(cache.path(), Some(&server.config(&server.endpoint, "site-a"))).await?
            }
        })
    }

    /// Every stored key (blobs, metadata, uploads in progress), relative to the store's root.
    async fn keys(&self) -> anyhow::Result<Vec<String>> {
        match self {
            Backend::Local(dir) => {
                let root = dir.path().join("artifacts");
                let mut keys = Vec::new();
                let mut stack = vec![root.clone()];
                while let Some(d) = stack.pop() {
                    for entry in std::fs::read_dir(&d)? {
                        let path = entry?.path();
                        if path.is_dir() {
                            stack.push(path);
                        } else {
                            keys.push(path.strip_prefix(&root)?.display().to_string());
                        }
                    }
                }
                keys.sort();
                Ok(keys)
            }
            Backend::S3(server, _) => Ok(server
                .keys()
                .await?
                .into_iter()
                .filter_map(|k| k.strip_prefix("site-a/").map(str::to_string))
                .collect()),
        }
    }

    fn name(&self) -> &'static str {
        match self {
            Backend::Local(_) => "local",
            Backend::S3(..) => "s3",
        }
    }
}

async fn backends() -> anyhow::Result<Vec<Backend>> {
    Ok(vec![
        Backend::Local(tempfile::tempdir()?),
        Backend::S3(S3Server::start().await?, tempfile::tempdir()?),
    ])
}

/// `n` bytes of XYZ text that differ from run to run of `seed`.
fn xyz(n: usize, seed: u32) -> Vec<u8> {
    let mut out = Vec::with_capacity(n + 64);
    let mut i = 0u64;
    while out.len() < n {
        out.extend_from_slice(format!("{seed} {i} {}\n", i.wrapping_mul(2654435761) % 1000).as_bytes());
        i += 1;
    }
    out.truncate(n);
    out.push(b'\n');
    out
}

async fn read_back(store: &ObjectArtifactStore, sha: &str) -> anyhow::Result<Vec<u8>> {
    let (_, mut reader) = store.open(sha).await?;
    let mut out = Vec::new();
    reader.read_to_end(&mut out).await?;
    Ok(out)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn blobs_small_and_multipart_round_trip_on_both_backends() -> anyhow::Result<()> {
    for backend in backends().await? {
        let name = backend.name();
        let store = backend.open().await?;
        // Small: one write.
        let small = b"G21 G90\nG0 X1 Y2\n".to_vec();
        let a = store.put_bytes("text/x-gcode", &small).await?;
        assert_eq!(a.sha256, hex::encode(sha2::Sha256::digest(&small)), "{name}");
        assert_eq!(a.size, small.len() as u64);
        assert_eq!(read_back(&store, &a.sha256).await?, small, "{name}");
        assert_eq!(store.put_bytes("text/x-gcode", &small).await?, a, "{name}: same bytes, same ref");
        // Large: streamed in parts (8 MiB) through a multipart upload, from a reader that hands
        // out odd-sized pieces.
        let large = xyz(21 * 1024 * 1024 + 333, 1);
        let mut body = tokio::io::BufReader::with_capacity(7777, &large[..]);
        let b = store.put("text/x-xyz", &mut body, u64::MAX).await?;
        assert_eq!(b.sha256, hex::encode(sha2::Sha256::digest(&large)), "{name}");
        assert_eq!(b.size, large.len() as u64, "{name}");
        assert_eq!(store.stat(&b.sha256).await?.as_ref(), Some(&b), "{name}");
        assert!(read_back(&store, &b.sha256).await? == large, "{name}: large blob read back differs");
        // A local file with the bytes (the blob itself, or a checked copy of the remote one).
        let path = store.local_file(&b.sha256).await?;
        assert_eq!(std::fs::read(&path)?.len(), large.len(), "{name}");
        // Storing the large blob again leaves one copy and no upload behind.
        let again = store.put("text/x-xyz", &mut &large[..], u64::MAX).await?;
        assert_eq!(again, b);
        let keys = backend.keys().await?;
        let expected: Vec<String> = {
            let mut k = Vec::new();
            for sha in [&a.sha256, &b.sha256] {
                k.push(format!("blobs/{}/{sha}", &sha[..2]));
                k.push(format!("blobs/{}/{sha}.json", &sha[..2]));
            }
            k.sort();
            k
        };
        assert_eq!(keys, expected, "{name}: exactly the two blobs and their metadata");
        // A missing digest.
        let missing = "0".repeat(64);
        assert!(store.stat(&missing).await?.is_none(), "{name}");
        assert!(matches!(store.open(&missing).await, Err(ArtifactError::NotFound { .. })), "{name}");
        assert!(matches!(store.local_file(&missing).await, Err(ArtifactError::NotFound { .. })), "{name}");
    }
    Ok(())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_failed_upload_leaves_nothing_on_either_backend() -> anyhow::Result<()> {
    for backend in backends().await? {
        let name = backend.name();
        let store = backend.open().await?;
        // Over the limit after the first part: the multipart upload is aborted.
        let large = xyz(20 * 1024 * 1024, 2);
        let err = store.put("text/x-xyz", &mut &large[..], 12 << 20).await.expect_err("too large");
        assert!(matches!(err, ArtifactError::TooLarge { limit } if limit == 12 << 20), "{name}: {err}");
        // Not text past the first part (a NUL at 9 MiB).
        let mut bad = xyz(10 * 1024 * 1024, 3);
        bad[9 * 1024 * 1024] = 0;
        let err = store.put("text/x-xyz", &mut &bad[..], u64::MAX).await.expect_err("NUL");
        assert!(err.to_string().contains("NUL"), "{name}: {err}");
        // Wrong type in the first bytes, and empty.
        assert!(store.put_bytes("image/png", b"not a png").await.is_err(), "{name}");
        assert!(matches!(store.put_bytes("text/x-xyz", b"").await, Err(ArtifactError::Empty)), "{name}");
        // A body that fails half-way (the client went away).
        struct Broken(usize);
        impl tokio::io::AsyncRead for Broken {
            fn poll_read(
                mut self: std::pin::Pin<&mut Self>,
                _: &mut std::task::Context<'_>,
                buf: &mut tokio::io::ReadBuf<'_>,
            ) -> std::task::Poll<std::io::Result<()>> {
                if self.0 == 0 {
                    return std::task::Poll::Ready(Err(std::io::ErrorKind::ConnectionReset.into()));
                }
                let n = self.0.min(buf.remaining()).min(4096);
                buf.put_slice(&vec![b'7'; n]);
                self.0 -= n;
                std::task::Poll::Ready(Ok(()))
            }
        }
        let err = store.put("text/x-xyz", &mut Broken(9 << 20), u64::MAX).await.expect_err("broken");
        assert!(matches!(err, ArtifactError::Upload(_)), "{name}: {err}");
        let keys: Vec<String> =
            backend.keys().await?.into_iter().filter(|k| !k.starts_with("tmp/")).collect();
        assert!(keys.is_empty(), "{name}: nothing stored: {keys:?}");
        let uploads: Vec<String> =
            backend.keys().await?.into_iter().filter(|k| k.starts_with("tmp/")).collect();
        assert!(uploads.is_empty(), "{name}: no upload left behind: {uploads:?}");
    }
    Ok(())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_remote_blob_damaged_in_the_bucket_is_refused_not_read() -> anyhow::Result<()> {
    let server = S3Server::start().await?;
    let cache = tempfile::tempdir()?;
    let store = open_store(cache.path(), Some(&server.config(&server.endpoint, "site-b"))).await?;
    let blob = xyz(4096, 4);
    let a = store.put_bytes("text/x-xyz", &blob).await?;
    // s3s-fs keeps an object as a file under <root>/<bucket>/<key>.
    let file = server.root.path().join(BUCKET).join(format!("site-b/blobs/{}/{}", &a.sha256[..2], a.sha256));
    let mut damaged = std::fs::read(&file).with_context(|| format!("{}", file.display()))?;
    damaged[100] ^= 1;
    std::fs::write(&file, &damaged)?;
    let err = store.local_file(&a.sha256).await.expect_err("damaged copy");
    assert!(matches!(err, ArtifactError::Corrupt { .. }), "{err}");
    assert!(err.to_string().contains("damaged"), "{err}");
    // Nothing was kept in the cache (`cache/` of the service's artifact folder).
    let copies = cache.path().join("cache");
    assert!(!copies.join("blobs").join(&a.sha256[..2]).join(&a.sha256).exists());
    assert_eq!(std::fs::read_dir(copies.join("tmp"))?.count(), 0);
    Ok(())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_store_urls_and_options_are_named() -> anyhow::Result<()> {
    let dir = tempfile::tempdir()?;
    for (url, options, says) in [
        ("ftp://bucket", vec![], "s3:// or file://"),
        ("s3://", vec![], "no bucket"),
        ("s3://b/p", vec![("endpointt", "http://x")], "unknown S3 option 'endpointt'"),
        ("file://relative/dir", vec![], "absolute path"),
    ] {
        let cfg = ObjectStoreConfig {
            url: url.into(),
            options: options.into_iter().map(|(k, v): (&str, &str)| (k.to_string(), v.to_string())).collect(),
        };
        let err = open_store(dir.path(), Some(&cfg)).await.expect_err(url);
        assert!(matches!(err, ArtifactError::Config { .. }), "{url}: {err}");
        assert!(err.to_string().contains(says) && err.to_string().contains(url), "{url}: {err}");
    }
    Ok(())
}

/// Every service on one bucket: a mesh job (scan, reconstruct, plan, execute: every stage service
/// reads its inputs from the bucket) runs to the end, its artifacts are in the bucket and download
/// through the REST API byte for byte, and the report renders.
/// Then the S3 server becomes unreachable: uploads are 503 with a retry hint and nothing is made;
/// once it is back, the next upload and job succeed.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn jobs_run_on_a_bucket_and_an_unreachable_bucket_is_503_then_recovers() -> anyhow::Result<()> {
    let server = S3Server::start().await?;
    let target = server.endpoint.trim_start_matches("http://").to_string();
    let (partition, port) = Partition::start(target).await?;
    let store = server.config(&format!("http://127.0.0.1:{port}"), "plant-1");
    let stack =
        TestStack::start_with(StackOptions { artifact_store: Some(store), ..Default::default() }).await?;

    let sha = stack.upload("model/stl", crate::scan::dome_stl()).await?;
    let job = json!({
        "input": {"kind": "mesh", "artifact": sha},
        "scan": {"table_angles_deg": [0], "line_spacing_mm": 1.0},
        "reconstruct": {"pixel_mm": 0.5},
        "plan": {"stock": {"z_mm": 7}, "roughing": {"tool": "flat-6", "step_down_mm": 3.0},
                 "finishing": {"tool": "ball-6", "step_over_mm": 2.0}},
        "execute": {"adaptive": "off", "compare": false}
    });
    let (status, created) = stack.post_job(&job, Some("s3-1")).await?;
    assert_eq!(status, 201, "{created}");
    let id = created["id"].as_str().context("id")?.to_string();
    let done = stack.wait_for_end(&id, Duration::from_secs(300)).await?;
    assert_eq!(done["status"], "succeeded", "{done}");
    let artifacts = done["artifacts"].as_object().context("artifacts")?;
    assert!(artifacts.len() >= 6, "{done}");
    let keys = server.keys().await?;
    for (kind, a) in artifacts {
        let sha = a["sha256"].as_str().context("sha256")?;
        assert!(keys.contains(&format!("plant-1/blobs/{}/{sha}", &sha[..2])), "{kind} not in the bucket");
        let bytes = stack.http.get(stack.url(&format!("/v1/artifacts/{sha}"))).send().await?.bytes().await?;
        assert_eq!(hex::encode(sha2::Sha256::digest(&bytes)), sha, "{kind} downloads byte for byte");
    }
    assert!(keys.iter().all(|k| !k.contains("/tmp/")), "no upload left: {keys:?}");
    let report = stack.http.get(stack.url(&format!("/v1/jobs/{id}/report"))).send().await?;
    assert_eq!(report.status().as_u16(), 200);
    assert!(report.text().await?.contains("<html"));

    // The bucket goes away.
    partition.down();
    let resp = stack
        .http
        .post(stack.url("/v1/artifacts"))
        .header("content-type", "text/x-gcode")
        .body(b"G0 X1\n".to_vec())
        .send()
        .await?;
    assert_eq!(resp.status().as_u16(), 503);
    assert!(resp.headers().contains_key("retry-after"));
    let body: serde_json::Value = resp.json().await?;
    assert_eq!(body["error"]["code"], "unavailable", "{body}");
    assert_eq!(stack.http.get(stack.url("/healthz")).send().await?.status().as_u16(), 200);

    partition.restore();
    let program = b"%\n(after the outage)\nG21 G90\nT1 M6\nS1500 M3\nG43 H1\nG0 X-5 Y5\nG0 Z12\nG1 Z9.5 F100\nG1 X35 F300\nG0 Z15\nM30\n%\n";
    let sha2 = stack.upload("text/x-gcode", program.to_vec()).await?;
    let job2 = json!({"input": {"kind": "gcode", "artifact": sha2},
                      "execute": {"machine": "emco-f1", "adaptive": "off", "compare": false, "cell_mm": 0.5}});
    let (status, created) = stack.post_job(&job2, Some("s3-2")).await?;
    assert_eq!(status, 201, "{created}");
    let done = stack.wait_for_end(created["id"].as_str().context("id")?, Duration::from_secs(90)).await?;
    assert_eq!(done["status"], "succeeded", "{done}");
    stack.shutdown().await
}
