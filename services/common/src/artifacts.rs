//! The content-addressed artifact store.
//!
//! A blob's identity is the lowercase hex sha256 of its bytes. Messages between services carry an
//! [`ArtifactRef`] (uri, sha256, size, media type), never the bytes. [`ArtifactStore`] is the seam
//! every service reads and writes through; [`ObjectArtifactStore`] implements it on the
//! `object_store` crate: a local folder by default (what the embedded stack shares), an
//! S3-compatible bucket for scale-out ([`ObjectStoreConfig`], [`open_store`]). The layout is the
//! same in both:
//!
//! ```text
//! blobs/<first two hex digits>/<sha256>        the bytes, never changed once written
//! blobs/<first two hex digits>/<sha256>.json   {"media_type": "...", "size": N}
//! tmp/<uuid>                                   large uploads in progress
//! ```
//!
//! Uploads are streamed: hashed, checked against a size limit and the declared media type
//! ([`MediaCheck`]) as the bytes arrive. A blob that ends within the first 8 MiB part goes to its
//! place in one write; a larger one is a multipart upload to `tmp/`, renamed into place once its
//! digest is known. A failed upload leaves nothing behind, a reader never sees a partial blob, and
//! no upload or read holds more than a few parts in memory whatever the blob's size.

use std::path::{Path, PathBuf};
use std::pin::Pin;

use depthmill_geometry::ArtifactRef;
use object_store::ObjectStoreExt as _;
use sha2::{Digest, Sha256};
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWriteExt};

/// Media types the store accepts.
pub const ACCEPTED_MEDIA_TYPES: &[&str] = &[
    "model/stl",
    "application/x-ply",
    "text/x-xyz",
    "model/obj",
    "model/x-off",
    "application/x-pcd",
    "image/png",
    "application/x-npy",
    "text/x-gcode",
    "application/json",
    "text/html",
    "text/csv",
    "image/svg+xml",
    "application/octet-stream",
];

/// Why an artifact could not be stored or read.
#[derive(Debug, thiserror::Error)]
pub enum ArtifactError {
    #[error("artifact {sha256} not found")]
    NotFound { sha256: String },
    #[error("'{value}' is not a sha256 (64 lowercase hex digits)")]
    BadDigest { value: String },
    #[error("artifact is larger than the limit of {limit} bytes")]
    TooLarge { limit: u64 },
    #[error("media type '{media_type}' is not accepted (accepted: {})", ACCEPTED_MEDIA_TYPES.join(", "))]
    UnsupportedMediaType { media_type: String },
    #[error("content is not {media_type}: {reason}")]
    ContentMismatch { media_type: String, reason: String },
    #[error("artifact is empty")]
    Empty,
    #[error("reading the upload failed")]
    Upload(#[source] std::io::Error),
    #[error("artifact store I/O failed on {path}")]
    Io {
        path: String,
        #[source]
        source: std::io::Error,
    },
    #[error("artifact store {location} failed")]
    Store {
        location: String,
        /// The store is reached over the network (a failure there is an outage, not a bug).
        remote: bool,
        #[source]
        source: object_store::Error,
    },
    #[error("artifact store '{url}': {reason}")]
    Config { url: String, reason: String },
    #[error(
        "artifact {sha256} read back from the store has sha256 {got} ({size} bytes): the stored copy is damaged"
    )]
    Corrupt { sha256: String, got: String, size: u64 },
    #[error("artifact metadata {path} is corrupt")]
    Metadata {
        path: String,
        #[source]
        source: serde_json::Error,
    },
}

/// A blob being read.
pub type BlobReader = Pin<Box<dyn AsyncRead + Send>>;

/// A store of content-addressed blobs.
#[async_trait::async_trait]
pub trait ArtifactStore: Send + Sync + 'static {
    /// Streams `body` into the store (at most `limit` bytes) as a blob of `media_type`, checking
    /// the bytes against the type. Storing bytes already present is cheap and returns the same ref.
    async fn put(
        &self,
        media_type: &str,
        body: &mut (dyn AsyncRead + Send + Unpin),
        limit: u64,
    ) -> Result<ArtifactRef, ArtifactError>;

    /// The reference of a stored blob, or `None`.
    async fn stat(&self, sha256: &str) -> Result<Option<ArtifactRef>, ArtifactError>;

    /// Opens a stored blob for streaming.
    async fn open(&self, sha256: &str) -> Result<(ArtifactRef, BlobReader), ArtifactError>;

    /// Stores an in-memory blob (results a service computed).
    async fn put_bytes(&self, media_type: &str, bytes: &[u8]) -> Result<ArtifactRef, ArtifactError> {
        let mut reader = bytes;
        self.put(media_type, &mut reader, u64::MAX).await
    }

    /// Reads a whole blob into memory, refusing blobs over `limit` bytes.
    async fn read_all(&self, sha256: &str, limit: u64) -> Result<Vec<u8>, ArtifactError> {
        let (aref, mut reader) = self.open(sha256).await?;
        if aref.size > limit {
            return Err(ArtifactError::TooLarge { limit });
        }
        let mut out = Vec::with_capacity(usize::try_from(aref.size).unwrap_or(0));
        reader.read_to_end(&mut out).await.map_err(|source| ArtifactError::Io { path: aref.uri, source })?;
        Ok(out)
    }

    /// A local file holding the blob's bytes (lets readers memory-map or seek): the blob itself
    /// in a local store, a copy checked against the digest for a remote one.
    async fn local_file(&self, sha256: &str) -> Result<PathBuf, ArtifactError>;
}

/// Checks that `s` is a sha256 in the store's spelling.
pub fn validate_digest(s: &str) -> Result<(), ArtifactError> {
    if depthmill_geometry::artifact::is_sha256_hex(s) {
        Ok(())
    } else {
        Err(ArtifactError::BadDigest { value: s.chars().take(80).collect() })
    }
}

/// Incremental check of bytes against a declared media type: magic numbers for binary formats,
/// "text without NUL bytes" for text formats, and the size equation of binary STL at the end. A
/// mesh or point cloud may be gzip-compressed (it starts with the gzip magic): its content is
/// checked by the reader that decompresses it.
#[derive(Debug)]
pub struct MediaCheck {
    media_type: String,
    head: Vec<u8>,
    size: u64,
}

const HEAD_LEN: usize = 512;

impl MediaCheck {
    /// Starts a check for `media_type` (parameters such as `; charset=utf-8` are ignored).
    pub fn new(media_type: &str) -> Result<Self, ArtifactError> {
        let essence = media_type.split(';').next().unwrap_or("").trim().to_ascii_lowercase();
        if !ACCEPTED_MEDIA_TYPES.contains(&essence.as_str()) {
            return Err(ArtifactError::UnsupportedMediaType { media_type: media_type.to_string() });
        }
        Ok(Self { media_type: essence, head: Vec::with_capacity(HEAD_LEN), size: 0 })
    }

    /// The media type without parameters.
    pub fn media_type(&self) -> &str {
        &self.media_type
    }

    /// Geometry sent gzip-compressed (a mesh or point cloud type whose bytes start with the gzip
    /// magic).
    fn is_gzip_geometry(&self) -> bool {
        self.is_geometry() && depthmill_geometry::formats::is_gzip(&self.head)
    }

    fn is_geometry(&self) -> bool {
        matches!(
            self.media_type.as_str(),
            "model/stl"
                | "application/x-ply"
                | "text/x-xyz"
                | "model/obj"
                | "model/x-off"
                | "application/x-pcd"
        )
    }

    fn is_text(&self) -> bool {
        if self.is_gzip_geometry() {
            return false;
        }
        matches!(
            self.media_type.as_str(),
            "text/x-xyz" | "text/x-gcode" | "application/json" | "text/html" | "text/csv" | "image/svg+xml"
        )
    }

    /// Feeds the next bytes; fails as soon as the head shows the wrong type.
    pub fn update(&mut self, chunk: &[u8]) -> Result<(), ArtifactError> {
        self.size += chunk.len() as u64;
        if self.head.len() < HEAD_LEN {
            let take = (HEAD_LEN - self.head.len()).min(chunk.len());
            self.head.extend_from_slice(&chunk[..take]);
            self.check_head(false)?;
        }
        if self.is_text() && chunk.contains(&0) {
            return Err(self.mismatch("it contains NUL bytes, so it is not text"));
        }
        Ok(())
    }

    /// Final check once every byte was seen.
    pub fn finish(&self) -> Result<(), ArtifactError> {
        if self.size == 0 {
            return Err(ArtifactError::Empty);
        }
        self.check_head(true)?;
        if self.is_gzip_geometry() {
            return Ok(());
        }
        use depthmill_geometry::formats::{InputFormat, sniff_format};
        // ASCII STL (`solid` in any case, after white space, with facets) is checked by the reader;
        // a binary one, even with a header that starts with `solid`, by its size.
        if self.media_type == "model/stl"
            && sniff_format(&self.head, Some(self.size)) != InputFormat::StlAscii
        {
            // Binary STL: 80-byte header, u32 triangle count, 50 bytes per triangle.
            if self.head.len() < 84 {
                return Err(self.mismatch("binary STL is shorter than its 84-byte header"));
            }
            let n = u32::from_le_bytes([self.head[80], self.head[81], self.head[82], self.head[83]]);
            let expected = 84 + 50 * u64::from(n);
            if expected != self.size {
                // An ASCII STL with a stray control byte reads as binary: say so.
                let trimmed = self.head.trim_ascii_start();
                let ascii_like = trimmed.len() >= 5 && trimmed[..5].eq_ignore_ascii_case(b"solid");
                let control = self
                    .head
                    .iter()
                    .position(|&b| b < 0x20 && !matches!(b, b'\t' | b'\n' | b'\r' | 0x0b | 0x0c));
                if let (true, Some(at)) = (ascii_like, control) {
                    return Err(self.mismatch(&format!(
                        "it starts like ASCII STL (`solid`) but byte {at} is a control character (0x{:02x}), and read as binary STL it declares {n} triangles ({expected} bytes) but has {} bytes",
                        self.head[at], self.size
                    )));
                }
                return Err(self.mismatch(&format!(
                    "binary STL declares {n} triangles ({expected} bytes) but has {} bytes",
                    self.size
                )));
            }
        }
        Ok(())
    }

    fn check_head(&self, complete: bool) -> Result<(), ArtifactError> {
        let head = &self.head;
        // Gzip, or its first byte so far.
        let magic = depthmill_geometry::formats::GZIP_MAGIC;
        if self.is_geometry()
            && (self.is_gzip_geometry() || (!complete && head[..] == magic[..head.len().min(1)]))
        {
            return Ok(());
        }
        let need = |magic: &[u8], what: &str| -> Result<(), ArtifactError> {
            let n = magic.len().min(head.len());
            if head[..n] != magic[..n] || (complete && head.len() < magic.len()) {
                Err(self.mismatch(&format!("it does not start with the {what} signature")))
            } else {
                Ok(())
            }
        };
        match self.media_type.as_str() {
            "image/png" => need(b"\x89PNG\r\n\x1a\n", "PNG"),
            "application/x-npy" => need(b"\x93NUMPY", ".npy"),
            "application/x-ply" => need(b"ply", "PLY"),
            "text/x-xyz" | "text/x-gcode" | "text/csv" | "application/json" | "text/html"
            | "image/svg+xml" => {
                // A multi-byte UTF-8 sequence may be cut at the end of the head: ignore that tail.
                match std::str::from_utf8(head) {
                    Ok(_) => Ok(()),
                    Err(e) if e.error_len().is_none() && !complete => Ok(()),
                    Err(e) if e.error_len().is_none() && head.len() == HEAD_LEN => Ok(()),
                    Err(e) => Err(self.mismatch(&format!("byte {} is not UTF-8 text", e.valid_up_to()))),
                }
            }
            _ => Ok(()),
        }
    }

    fn mismatch(&self, reason: &str) -> ArtifactError {
        ArtifactError::ContentMismatch { media_type: self.media_type.clone(), reason: reason.to_string() }
    }
}

#[derive(serde::Serialize, serde::Deserialize)]
struct BlobMeta {
    media_type: String,
    size: u64,
}

impl ArtifactError {
    fn store(location: &str, remote: bool, source: object_store::Error) -> Self {
        ArtifactError::Store { location: location.to_string(), remote, source }
    }

    /// The disk (or the quota) under the store is full: nothing was stored, and the same request
    /// can work once space is freed.
    pub fn is_out_of_space(&self) -> bool {
        let mut cause: Option<&(dyn std::error::Error + 'static)> = Some(self);
        while let Some(e) = cause {
            if let Some(io) = e.downcast_ref::<std::io::Error>()
                && matches!(io.kind(), std::io::ErrorKind::StorageFull | std::io::ErrorKind::QuotaExceeded)
            {
                return true;
            }
            cause = e.source();
        }
        false
    }

    /// The store cannot be used for now (full, or a remote store that does not answer): nothing
    /// was stored, and the same request can work later.
    pub fn is_unavailable(&self) -> bool {
        self.is_out_of_space()
            || matches!(self, ArtifactError::Store { remote: true, source, .. }
                if !matches!(source, object_store::Error::NotFound { .. }
                    | object_store::Error::InvalidPath { .. }
                    | object_store::Error::NotSupported { .. }
                    | object_store::Error::NotImplemented { .. }))
    }
}

/// A mesh or point cloud artifact read for a stage, in millimetres.
pub struct ReadGeometry {
    pub geometry: depthmill_geometry::formats::Geometry,
    /// How the unit was decided (`None`: no finite point to decide on).
    pub units: Option<depthmill_geometry::UnitsDecision>,
    /// The artifact as errors name it: `what <sha prefix> (<media type>)`.
    pub name: String,
}

/// Reads the mesh or cloud artifact `sha` (STL, PLY, XYZ) on a blocking thread and scales it to
/// millimetres: `units` is the request's wire unit (unspecified: the file's header, else its size),
/// `units_field` the request field errors name for an unknown one, `what` the artifact's role in
/// errors (`mesh`, `reference`). Unreadable content is `InvalidArgument` naming where.
pub async fn read_geometry<S: ArtifactStore + ?Sized>(
    store: &S,
    sha: &str,
    units: i32,
    units_field: &str,
    what: &str,
    limits: &depthmill_geometry::formats::ReadLimits,
) -> Result<ReadGeometry, tonic::Status> {
    use depthmill_proto::ErrorCode;
    let units = depthmill_proto::convert::units(units)
        .map_err(|v| ErrorCode::InvalidArgument.status(format!("{units_field}: unknown unit {v}")))?;
    let stat = store
        .stat(sha)
        .await
        .map_err(grpc_status)?
        .ok_or_else(|| ErrorCode::InvalidArgument.status(format!("{what}: no artifact {sha}")))?;
    let path = store.local_file(sha).await.map_err(grpc_status)?;
    let name = format!("{what} {} ({})", &sha[..12.min(sha.len())], stat.media_type);
    let limits = limits.clone();
    tokio::task::spawn_blocking(move || {
        let file = std::fs::File::open(&path)
            .map_err(|e| ErrorCode::Internal.status(format!("{name}: cannot open: {e}")))?;
        let (mut geometry, _) = depthmill_geometry::formats::read_any_from(
            std::io::BufReader::with_capacity(1 << 20, file),
            &name,
            Some(stat.size),
            &limits,
        )
        .map_err(|e| ErrorCode::InvalidArgument.status(e.to_string()))?;
        let head = depthmill_geometry::units::read_head(&path)
            .map_err(|e| ErrorCode::Internal.status(format!("{name}: cannot read: {e}")))?;
        let units = depthmill_geometry::units::normalise(&mut geometry, &head, units);
        Ok(ReadGeometry { geometry, units, name })
    })
    .await
    .map_err(|e| tonic::Status::internal(format!("reading the {what} failed: {e}")))?
}

/// The gRPC status a stage service answers when reading or writing an artifact fails: the
/// caller's fault (unknown digest, bad digest, too large) as `InvalidArgument` with the reason; a
/// full disk as `Unavailable` (the orchestrator retries); anything else logged with its cause
/// chain and answered as `Internal` without internals.
pub fn grpc_status(e: ArtifactError) -> tonic::Status {
    use depthmill_proto::ErrorCode;
    match e {
        ArtifactError::NotFound { .. } | ArtifactError::BadDigest { .. } | ArtifactError::TooLarge { .. } => {
            ErrorCode::InvalidArgument.status(e.to_string())
        }
        full if full.is_out_of_space() => {
            tracing::error!(error = %crate::ErrorChain(&full), "artifact store out of space");
            ErrorCode::Unavailable.status("the artifact store is out of space; nothing was stored")
        }
        down if down.is_unavailable() => {
            tracing::error!(error = %crate::ErrorChain(&down), "artifact store unavailable");
            ErrorCode::Unavailable.status("the artifact store does not answer; nothing was stored")
        }
        other => {
            tracing::error!(error = %crate::ErrorChain(&other), "artifact store failed");
            ErrorCode::Internal.status("the artifact store failed")
        }
    }
}

/// Age after which a temporary upload is a leftover of an interrupted one.
const STALE_UPLOAD: std::time::Duration = std::time::Duration::from_secs(3600);

/// Size of the parts an upload is streamed in: a blob that ends within the first part goes to its
/// place in one request; a larger one is a multipart upload of parts this size, at most
/// [`UPLOAD_PARTS_IN_FLIGHT`] of them in memory at once (S3 needs parts of at least 5 MiB).
const UPLOAD_PART: usize = 8 << 20;
const UPLOAD_PARTS_IN_FLIGHT: usize = 2;

/// `[artifact_store]` of a service's configuration: where the blobs live when they are not in the
/// local artifact folder.
#[derive(Debug, Clone, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ObjectStoreConfig {
    /// `s3://BUCKET[/PREFIX]` (an S3-compatible store: AWS, MinIO, Ceph, ...) or
    /// `file:///ABSOLUTE/FOLDER`.
    pub url: String,
    /// Options of the store by the names `object_store` gives them: for S3 `endpoint`,
    /// `region`, `access_key_id`, `secret_access_key`, `session_token`, `aws_allow_http`
    /// (`"true"` for an `http://` endpoint), ... The standard `AWS_*` environment variables fill in
    /// what is not given here.
    #[serde(default)]
    pub options: std::collections::BTreeMap<String, String>,
}

#[derive(Debug, Clone)]
enum Backend {
    /// Blobs are files under `root` (the default, and what the embedded stack shares).
    Local { root: PathBuf },
    /// Blobs in a remote object store at `url`; readers that need a file get a verified copy in
    /// the local `cache` folder.
    Remote { url: String, cache: PathBuf },
}

/// The artifact store on an [`ObjectStore`](object_store::ObjectStore): the local file system
/// by default, an S3-compatible store for scale-out. Keys under the store's root:
///
/// ```text
/// blobs/<first two hex digits>/<sha256>        the bytes, never changed once written
/// blobs/<first two hex digits>/<sha256>.json   {"media_type": "...", "size": N}
/// tmp/<uuid>                                   multipart uploads in progress
/// ```
#[derive(Debug, Clone)]
pub struct ObjectArtifactStore {
    inner: std::sync::Arc<dyn object_store::ObjectStore>,
    backend: Backend,
}

fn blob_key(sha256: &str) -> object_store::path::Path {
    object_store::path::Path::from(format!("blobs/{}/{sha256}", &sha256[..2]))
}

fn meta_key(sha256: &str) -> object_store::path::Path {
    object_store::path::Path::from(format!("blobs/{}/{sha256}.json", &sha256[..2]))
}

/// Opens the store a service is configured with: `store` when given, else the local folder `dir`
/// (which then also holds the local copies of remote blobs, under `cache/`).
pub async fn open_store(
    dir: &Path,
    store: Option<&ObjectStoreConfig>,
) -> Result<ObjectArtifactStore, ArtifactError> {
    match store {
        None => ObjectArtifactStore::open_local(dir).await,
        Some(cfg) => ObjectArtifactStore::open_url(&cfg.url, &cfg.options, &dir.join("cache")).await,
    }
}

/// Reads from `body` into `buf` until it holds `want` bytes or the body ends (then `true`),
/// feeding the check, the hash and the size limit.
async fn fill(
    body: &mut (dyn AsyncRead + Send + Unpin),
    buf: &mut Vec<u8>,
    want: usize,
    check: &mut MediaCheck,
    hasher: &mut Sha256,
    size: &mut u64,
    limit: u64,
) -> Result<bool, ArtifactError> {
    let mut chunk = vec![0u8; 64 * 1024];
    while buf.len() < want {
        let room = (want - buf.len()).min(chunk.len());
        let n = body.read(&mut chunk[..room]).await.map_err(ArtifactError::Upload)?;
        if n == 0 {
            return Ok(true);
        }
        *size += n as u64;
        if *size > limit {
            return Err(ArtifactError::TooLarge { limit });
        }
        check.update(&chunk[..n])?;
        hasher.update(&chunk[..n]);
        buf.extend_from_slice(&chunk[..n]);
    }
    Ok(false)
}

impl ObjectArtifactStore {
    /// Opens (creating if needed) a store in the local folder `root` and removes leftovers of
    /// uploads interrupted more than an hour ago.
    pub async fn open_local(root: impl Into<PathBuf>) -> Result<Self, ArtifactError> {
        let root: PathBuf = root.into();
        let root = if root.is_absolute() {
            root
        } else {
            std::env::current_dir().map_err(io_err(&root))?.join(&root)
        };
        for dir in [root.join("tmp"), root.join("blobs")] {
            tokio::fs::create_dir_all(&dir).await.map_err(io_err(&dir))?;
        }
        let fs = object_store::local::LocalFileSystem::new_with_prefix(&root)
            .map_err(|source| ArtifactError::store(&root.display().to_string(), false, source))?
            .with_fsync(true);
        let store = Self { inner: std::sync::Arc::new(fs), backend: Backend::Local { root } };
        store.remove_stale_uploads().await?;
        Ok(store)
    }

    /// Opens the store at `url` (`s3://BUCKET[/PREFIX]` or `file:///FOLDER`) with the store's
    /// `options`; `cache` is the local folder for copies of remote blobs.
    pub async fn open_url(
        url: &str,
        options: &std::collections::BTreeMap<String, String>,
        cache: &Path,
    ) -> Result<Self, ArtifactError> {
        let bad = |reason: String| ArtifactError::Config { url: url.to_string(), reason };
        if let Some(path) = url.strip_prefix("file://") {
            if !options.is_empty() {
                return Err(bad("a file:// store takes no options".into()));
            }
            if !path.starts_with('/') {
                return Err(bad("a file:// URL needs an absolute path (file:///folder)".into()));
            }
            return Self::open_local(path).await;
        }
        let Some(rest) = url.strip_prefix("s3://") else {
            return Err(bad("the scheme must be s3:// or file://".into()));
        };
        let (bucket, prefix) = rest.split_once('/').unwrap_or((rest, ""));
        if bucket.is_empty() {
            return Err(bad("no bucket name after s3://".into()));
        }
        crate::tls::install_crypto();
        let mut builder = object_store::aws::AmazonS3Builder::from_env().with_bucket_name(bucket).with_retry(
            object_store::RetryConfig {
                // A store that is down fails the request within seconds (503 with a retry
                // hint) rather than holding it for minutes.
                max_retries: 3,
                retry_timeout: std::time::Duration::from_secs(10),
                ..Default::default()
            },
        );
        for (key, value) in options {
            let key: object_store::aws::AmazonS3ConfigKey =
                key.parse().map_err(|_| bad(format!("unknown S3 option '{key}'")))?;
            builder = builder.with_config(key, value);
        }
        let s3 = builder.build().map_err(|e| bad(e.to_string()))?;
        let inner: std::sync::Arc<dyn object_store::ObjectStore> = if prefix.trim_matches('/').is_empty() {
            std::sync::Arc::new(s3)
        } else {
            std::sync::Arc::new(object_store::prefix::PrefixStore::new(s3, prefix.trim_matches('/')))
        };
        for dir in [cache.join("tmp"), cache.join("blobs")] {
            tokio::fs::create_dir_all(&dir).await.map_err(io_err(&dir))?;
        }
        let store = Self {
            inner,
            backend: Backend::Remote {
                url: url.trim_end_matches('/').to_string(),
                cache: cache.to_path_buf(),
            },
        };
        store.remove_stale_uploads().await?;
        Ok(store)
    }

    /// Where the store is, for messages: its folder or URL.
    pub fn location(&self) -> String {
        match &self.backend {
            Backend::Local { root } => root.display().to_string(),
            Backend::Remote { url, .. } => url.clone(),
        }
    }

    /// The folder of a local store.
    pub fn local_root(&self) -> Option<&Path> {
        match &self.backend {
            Backend::Local { root } => Some(root),
            Backend::Remote { .. } => None,
        }
    }

    fn err(&self, source: object_store::Error) -> ArtifactError {
        ArtifactError::store(&self.location(), matches!(self.backend, Backend::Remote { .. }), source)
    }

    /// Removes uploads left by a process that died more than [`STALE_UPLOAD`] ago. Several
    /// services share one store and another may be uploading right now: younger ones stay, and
    /// one that someone else removed first is no error.
    async fn remove_stale_uploads(&self) -> Result<(), ArtifactError> {
        // A bucket's `tmp/` through the store; a local folder (a local store's `tmp/` with the
        // staging files `<key>#<n>` the store's listing hides, or the local cache of a remote
        // store with its copies interrupted half-way) directly.
        let tmp = match &self.backend {
            Backend::Local { root } => root.join("tmp"),
            Backend::Remote { cache, .. } => {
                use futures::TryStreamExt as _;
                let prefix = object_store::path::Path::from("tmp");
                let listed: Vec<object_store::ObjectMeta> =
                    self.inner.list(Some(&prefix)).try_collect().await.map_err(|e| self.err(e))?;
                let now_ms = std::time::SystemTime::now()
                    .duration_since(std::time::UNIX_EPOCH)
                    .map_or(0, |d| i64::try_from(d.as_millis()).unwrap_or(i64::MAX));
                let stale_ms = i64::try_from(STALE_UPLOAD.as_millis()).unwrap_or(i64::MAX);
                for meta in listed {
                    if now_ms.saturating_sub(meta.last_modified.timestamp_millis()) > stale_ms {
                        match self.inner.delete(&meta.location).await {
                            Ok(()) | Err(object_store::Error::NotFound { .. }) => {}
                            Err(e) => return Err(self.err(e)),
                        }
                    }
                }
                cache.join("tmp")
            }
        };
        let mut entries = tokio::fs::read_dir(&tmp).await.map_err(io_err(&tmp))?;
        while let Some(entry) = entries.next_entry().await.map_err(io_err(&tmp))? {
            let stale = entry
                .metadata()
                .await
                .ok()
                .and_then(|m| m.modified().ok())
                .and_then(|t| t.elapsed().ok())
                .is_some_and(|age| age > STALE_UPLOAD);
            if stale {
                let _ = tokio::fs::remove_file(entry.path()).await;
            }
        }
        Ok(())
    }

    fn reference(&self, sha256: &str, meta: BlobMeta) -> ArtifactRef {
        let uri = match &self.backend {
            Backend::Local { root } => {
                format!("file://{}", root.join("blobs").join(&sha256[..2]).join(sha256).display())
            }
            Backend::Remote { url, .. } => format!("{url}/{}", blob_key(sha256)),
        };
        ArtifactRef { uri, sha256: sha256.to_string(), size: meta.size, media_type: meta.media_type }
    }

    /// Puts the metadata, then the blob: a blob without metadata is never visible (stat needs
    /// both), and a reader that sees the metadata finds the whole blob or none.
    async fn publish_small(
        &self,
        sha256: &str,
        meta: &BlobMeta,
        bytes: Vec<u8>,
    ) -> Result<(), ArtifactError> {
        self.put_meta(sha256, meta).await?;
        self.inner
            .put(&blob_key(sha256), object_store::PutPayload::from(bytes))
            .await
            .map_err(|e| self.err(e))?;
        Ok(())
    }

    async fn put_meta(&self, sha256: &str, meta: &BlobMeta) -> Result<(), ArtifactError> {
        let key = meta_key(sha256);
        let json = serde_json::to_vec(meta)
            .map_err(|source| ArtifactError::Metadata { path: key.to_string(), source })?;
        self.inner.put(&key, object_store::PutPayload::from(json)).await.map_err(|e| self.err(e))?;
        Ok(())
    }

    /// Streams the rest of a large upload (the first part is in `first`) to a temporary key as a
    /// multipart upload; returns the key, the digest and the size. Aborts the upload on failure.
    async fn put_large(
        &self,
        first: Vec<u8>,
        body: &mut (dyn AsyncRead + Send + Unpin),
        check: &mut MediaCheck,
        mut hasher: Sha256,
        mut size: u64,
        limit: u64,
    ) -> Result<(object_store::path::Path, String, u64), ArtifactError> {
        let tmp = object_store::path::Path::from(format!("tmp/{}", uuid::Uuid::now_v7()));
        let upload = self.inner.put_multipart(&tmp).await.map_err(|e| self.err(e))?;
        let mut writer = object_store::WriteMultipart::new_with_chunk_size(upload, UPLOAD_PART);
        writer.put(first.into());
        let streamed: Result<(), ArtifactError> = async {
            loop {
                writer.wait_for_capacity(UPLOAD_PARTS_IN_FLIGHT).await.map_err(|e| self.err(e))?;
                let mut part = Vec::with_capacity(UPLOAD_PART);
                let ended = fill(body, &mut part, UPLOAD_PART, check, &mut hasher, &mut size, limit).await?;
                if !part.is_empty() {
                    writer.put(part.into());
                }
                if ended {
                    return check.finish();
                }
            }
        }
        .await;
        match streamed {
            Ok(()) => {
                writer.finish().await.map_err(|e| self.err(e))?;
            }
            Err(e) => {
                if let Err(abort) = writer.abort().await {
                    tracing::warn!(error = %crate::ErrorChain(&abort), key = %tmp, "aborting an upload failed");
                }
                return Err(e);
            }
        }
        Ok((tmp, hex::encode(hasher.finalize()), size))
    }

    /// A verified local copy of a remote blob in the cache folder.
    async fn cached_copy(&self, cache: &Path, aref: &ArtifactRef) -> Result<PathBuf, ArtifactError> {
        let sha256 = &aref.sha256;
        let dest = cache.join("blobs").join(&sha256[..2]).join(sha256);
        if tokio::fs::try_exists(&dest).await.map_err(io_err(&dest))? {
            return Ok(dest);
        }
        let tmp = cache.join("tmp").join(uuid::Uuid::now_v7().to_string());
        struct TmpGuard(Option<PathBuf>);
        impl Drop for TmpGuard {
            fn drop(&mut self) {
                if let Some(p) = self.0.take() {
                    let _ = std::fs::remove_file(p);
                }
            }
        }
        let mut guard = TmpGuard(Some(tmp.clone()));
        let mut file = tokio::fs::File::create(&tmp).await.map_err(io_err(&tmp))?;
        let mut stream = self.inner.get(&blob_key(sha256)).await.map_err(|e| self.err(e))?.into_stream();
        let mut hasher = Sha256::new();
        let mut size = 0u64;
        use futures::StreamExt as _;
        while let Some(chunk) = stream.next().await {
            let chunk = chunk.map_err(|e| self.err(e))?;
            hasher.update(&chunk);
            size += chunk.len() as u64;
            file.write_all(&chunk).await.map_err(io_err(&tmp))?;
        }
        file.sync_all().await.map_err(io_err(&tmp))?;
        drop(file);
        let got = hex::encode(hasher.finalize());
        if got != *sha256 || size != aref.size {
            return Err(ArtifactError::Corrupt { sha256: sha256.clone(), got, size });
        }
        if let Some(dir) = dest.parent() {
            tokio::fs::create_dir_all(dir).await.map_err(io_err(dir))?;
        }
        tokio::fs::rename(&tmp, &dest).await.map_err(io_err(&dest))?;
        guard.0 = None;
        Ok(dest)
    }
}

fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> ArtifactError + '_ {
    move |source| ArtifactError::Io { path: path.display().to_string(), source }
}

#[async_trait::async_trait]
impl ArtifactStore for ObjectArtifactStore {
    async fn put(
        &self,
        media_type: &str,
        body: &mut (dyn AsyncRead + Send + Unpin),
        limit: u64,
    ) -> Result<ArtifactRef, ArtifactError> {
        let mut check = MediaCheck::new(media_type)?;
        let mut hasher = Sha256::new();
        let mut size: u64 = 0;
        let mut first = Vec::with_capacity(64 * 1024);
        let ended = fill(body, &mut first, UPLOAD_PART, &mut check, &mut hasher, &mut size, limit).await?;
        if ended {
            check.finish()?;
            let sha256 = hex::encode(hasher.finalize());
            if let Some(existing) = self.stat(&sha256).await? {
                return Ok(existing);
            }
            let meta = BlobMeta { media_type: check.media_type().to_string(), size };
            self.publish_small(&sha256, &meta, first).await?;
            tracing::debug!(%sha256, size, media_type = %meta.media_type, "artifact stored");
            return Ok(self.reference(&sha256, meta));
        }
        let (tmp, sha256, size) = self.put_large(first, body, &mut check, hasher, size, limit).await?;
        let meta = BlobMeta { media_type: check.media_type().to_string(), size };
        let placed: Result<(), ArtifactError> = async {
            if self.stat(&sha256).await?.is_none() {
                self.put_meta(&sha256, &meta).await?;
                self.inner.rename(&tmp, &blob_key(&sha256)).await.map_err(|e| self.err(e))?;
            }
            Ok(())
        }
        .await;
        // Whatever happened, the temporary object goes (gone already when it was renamed).
        match self.inner.delete(&tmp).await {
            Ok(()) | Err(object_store::Error::NotFound { .. }) => {}
            Err(e) => tracing::warn!(error = %crate::ErrorChain(&e), key = %tmp, "removing an upload failed"),
        }
        placed?;
        tracing::debug!(%sha256, size, media_type = %meta.media_type, "artifact stored");
        Ok(self.reference(&sha256, meta))
    }

    async fn stat(&self, sha256: &str) -> Result<Option<ArtifactRef>, ArtifactError> {
        validate_digest(sha256)?;
        let key = meta_key(sha256);
        let bytes = match self.inner.get(&key).await {
            Ok(got) => got.bytes().await.map_err(|e| self.err(e))?,
            Err(object_store::Error::NotFound { .. }) => return Ok(None),
            Err(e) => return Err(self.err(e)),
        };
        match self.inner.head(&blob_key(sha256)).await {
            Ok(_) => {}
            Err(object_store::Error::NotFound { .. }) => return Ok(None),
            Err(e) => return Err(self.err(e)),
        }
        let meta: BlobMeta = serde_json::from_slice(&bytes)
            .map_err(|source| ArtifactError::Metadata { path: key.to_string(), source })?;
        Ok(Some(self.reference(sha256, meta)))
    }

    async fn open(&self, sha256: &str) -> Result<(ArtifactRef, BlobReader), ArtifactError> {
        let aref =
            self.stat(sha256).await?.ok_or_else(|| ArtifactError::NotFound { sha256: sha256.into() })?;
        if let Backend::Local { root } = &self.backend {
            // The file itself: tokio reads it in the background, no copy through the store.
            let path = root.join("blobs").join(&sha256[..2]).join(sha256);
            let file = tokio::fs::File::open(&path).await.map_err(io_err(&path))?;
            return Ok((aref, Box::pin(file)));
        }
        use futures::TryStreamExt as _;
        let stream = self.inner.get(&blob_key(sha256)).await.map_err(|e| self.err(e))?.into_stream();
        let reader = tokio_util::io::StreamReader::new(stream.map_err(std::io::Error::other));
        Ok((aref, Box::pin(reader)))
    }

    async fn local_file(&self, sha256: &str) -> Result<PathBuf, ArtifactError> {
        let aref =
            self.stat(sha256).await?.ok_or_else(|| ArtifactError::NotFound { sha256: sha256.into() })?;
        match &self.backend {
            Backend::Local { root } => Ok(root.join("blobs").join(&sha256[..2]).join(sha256)),
            Backend::Remote { cache, .. } => self.cached_copy(cache, &aref).await,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_full_disk_is_unavailable_not_internal() {
        let full = |kind| ArtifactError::Io { path: "blobs/x".into(), source: std::io::Error::from(kind) };
        for kind in [std::io::ErrorKind::StorageFull, std::io::ErrorKind::QuotaExceeded] {
            assert!(full(kind).is_out_of_space());
            let status = grpc_status(full(kind));
            assert_eq!(status.code(), tonic::Code::Unavailable, "{status:?}");
            assert!(status.message().contains("out of space"), "{status:?}");
        }
        assert!(!full(std::io::ErrorKind::PermissionDenied).is_out_of_space());
        assert_eq!(grpc_status(full(std::io::ErrorKind::PermissionDenied)).code(), tonic::Code::Internal);
    }

    async fn store() -> (tempfile::TempDir, ObjectArtifactStore) {
        let dir = tempfile::tempdir().expect("tempdir");
        let store = ObjectArtifactStore::open_local(dir.path().join("artifacts")).await.expect("open");
        (dir, store)
    }

    #[tokio::test]
    async fn put_then_read_back_by_digest() {
        let (_dir, store) = store().await;
        let body = b"G21 G90\nG0 X1 Y2\n";
        let a = store.put_bytes("text/x-gcode", body).await.expect("put");
        assert_eq!(a.sha256, hex::encode(Sha256::digest(body)));
        assert_eq!(a.size, body.len() as u64);
        assert!(a.uri.starts_with("file:///"));
        assert_eq!(store.read_all(&a.sha256, 1 << 20).await.expect("read"), body);
        // Same bytes again: same reference, no second copy.
        let b = store.put_bytes("text/x-gcode", body).await.expect("put again");
        assert_eq!(a, b);
        let tmp_entries =
            std::fs::read_dir(store.local_root().expect("local").join("tmp")).expect("tmp").count();
        assert_eq!(tmp_entries, 0);
    }

    #[tokio::test]
    async fn oversized_and_mistyped_uploads_leave_nothing() {
        let (_dir, store) = store().await;
        let err = store.put("text/x-xyz", &mut &b"1 2 3\n4 5 6\n"[..], 5).await.expect_err("too large");
        assert!(matches!(err, ArtifactError::TooLarge { limit: 5 }));
        let err = store.put_bytes("image/png", b"not a png").await.expect_err("mismatch");
        assert!(err.to_string().contains("PNG signature"), "{err}");
        let err = store.put_bytes("image/gif", b"GIF89a").await.expect_err("unsupported");
        assert!(err.to_string().contains("image/gif"), "{err}");
        let err = store.put_bytes("text/x-gcode", b"G0\0X1").await.expect_err("nul in text");
        assert!(err.to_string().contains("NUL"), "{err}");
        let err = store.put_bytes("text/x-gcode", b"").await.expect_err("empty");
        assert!(matches!(err, ArtifactError::Empty));
        assert_eq!(
            std::fs::read_dir(store.local_root().expect("local").join("tmp")).expect("tmp").count(),
            0
        );
        assert_eq!(
            std::fs::read_dir(store.local_root().expect("local").join("blobs")).expect("blobs").count(),
            0
        );
    }

    #[tokio::test]
    async fn binary_stl_size_must_match_its_triangle_count() {
        let (_dir, store) = store().await;
        let mut stl = vec![0u8; 84 + 50];
        stl[80] = 1;
        store.put_bytes("model/stl", &stl).await.expect("one triangle");
        stl[80] = 2;
        let err = store.put_bytes("model/stl", &stl).await.expect_err("count mismatch");
        assert!(err.to_string().contains("declares 2 triangles"), "{err}");
        // ASCII STL as CAD systems write it: upper-case keywords, leading white space.
        let upper = b"  SOLID  Untitled1\n  FACET NORMAL 0 0 1\n    OUTER LOOP\n      VERTEX 0 0 0\n      VERTEX 1 0 0\n      VERTEX 0 1 0\n    ENDLOOP\n  ENDFACET\nENDSOLID\n";
        store.put_bytes("model/stl", upper).await.expect("upper-case ascii STL");
        // ASCII STL with a stray control byte: named as such.
        let mut broken = upper.to_vec();
        broken[60] = 0x01;
        let err = store.put_bytes("model/stl", &broken).await.expect_err("control byte");
        assert!(
            err.to_string()
                .contains("starts like ASCII STL (`solid`) but byte 60 is a control character (0x01)"),
            "{err}"
        );
    }

    #[tokio::test]
    async fn unknown_and_malformed_digests() {
        let (_dir, store) = store().await;
        let missing = "0".repeat(64);
        assert!(store.stat(&missing).await.expect("stat").is_none());
        assert!(matches!(store.open(&missing).await, Err(ArtifactError::NotFound { .. })));
        assert!(matches!(store.stat("../etc/passwd").await, Err(ArtifactError::BadDigest { .. })));
        assert!(matches!(store.local_file("XYZ").await, Err(ArtifactError::BadDigest { .. })));
    }

    #[tokio::test]
    async fn uploads_left_by_a_killed_process_go_at_the_next_open_and_young_ones_stay() {
        let (dir, store) = store().await;
        let tmp = store.local_root().expect("local").join("tmp");
        // A multipart upload's staging file an hour and more old, and one just begun.
        let old = tmp.join("0193a1b2-c3d4-7e5f-8a9b-0c1d2e3f4a5b#1");
        let young = tmp.join("0193a1b2-c3d4-7e5f-8a9b-0c1d2e3f4a5c#1");
        for p in [&old, &young] {
            std::fs::write(p, b"partial").expect("write");
        }
        let two_hours_ago = std::time::SystemTime::now() - std::time::Duration::from_secs(7200);
        std::fs::File::options()
            .write(true)
            .open(&old)
            .expect("open")
            .set_modified(two_hours_ago)
            .expect("mtime");
        drop(store);
        let _again = ObjectArtifactStore::open_local(dir.path().join("artifacts")).await.expect("reopen");
        assert!(!old.exists(), "the stale staging file is removed");
        assert!(young.exists(), "an upload in progress elsewhere is left alone");
    }

    /// Gzip-compressed meshes and clouds pass, also fed a byte at a time (their content is the
    /// reader's to check); a depth map or a program does not.
    #[test]
    fn gzip_geometry_is_accepted_under_its_content_type() {
        // A gzip member: magic, deflate, flags, then bytes with NULs in them.
        let gz: Vec<u8> =
            [0x1f, 0x8b, 0x08, 0x00, 0, 0, 0, 0, 0, 0xff].into_iter().chain(0..=255u8).collect();
        for media in
            ["model/stl", "application/x-ply", "text/x-xyz", "model/obj", "model/x-off", "application/x-pcd"]
        {
            let mut check = MediaCheck::new(media).expect("type");
            for b in &gz {
                check.update(std::slice::from_ref(b)).expect(media);
            }
            check.finish().expect(media);
        }
        for media in ["image/png", "text/x-gcode", "application/x-npy"] {
            let mut check = MediaCheck::new(media).expect("type");
            let fed = gz.chunks(7).try_for_each(|c| check.update(c));
            assert!(fed.is_err() || check.finish().is_err(), "{media}");
        }
        // A PLY that is neither: refused as before.
        let mut check = MediaCheck::new("application/x-ply").expect("type");
        assert!(check.update(b"\x1fnot ply").is_err());
    }

    #[test]
    fn utf8_cut_at_a_chunk_boundary_is_text() {
        let mut check = MediaCheck::new("text/x-xyz; charset=utf-8").expect("type");
        let s = "é".as_bytes();
        check.update(&s[..1]).expect("first half");
        check.update(&s[1..]).expect("second half");
        check.finish().expect("complete");
    }
}
