//! The content-addressed artifact store.
//!
//! A blob's identity is the lowercase hex sha256 of its bytes. Messages between services carry an
//! [`ArtifactRef`] (uri, sha256, size, media type), never the bytes. [`ArtifactStore`] is the seam
//! an object store can implement; [`LocalStore`] keeps blobs in a folder:
//!
//! ```text
//! <root>/blobs/<first two hex digits>/<sha256>        the bytes, read-only once written
//! <root>/blobs/<first two hex digits>/<sha256>.json   {"media_type": "...", "size": N}
//! <root>/tmp/                                         uploads in progress (emptied at start-up)
//! ```
//!
//! Uploads are streamed to a temporary file while hashed, checked against a size limit and the
//! declared media type ([`MediaCheck`]), then renamed into place: a failed upload leaves nothing
//! behind and a reader never sees a partial blob.

use std::path::{Path, PathBuf};
use std::pin::Pin;

use depthmill_geometry::ArtifactRef;
use sha2::{Digest, Sha256};
use tokio::io::{AsyncRead, AsyncReadExt, AsyncWriteExt};

/// Media types the store accepts.
pub const ACCEPTED_MEDIA_TYPES: &[&str] = &[
    "model/stl",
    "application/x-ply",
    "text/x-xyz",
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

    /// A local file holding the blob, when the store has one (lets kernels memory-map or seek).
    fn local_path(&self, sha256: &str) -> Option<PathBuf>;
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
/// "text without NUL bytes" for text formats, and the size equation of binary STL at the end.
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

    fn is_text(&self) -> bool {
        matches!(
            self.media_type.as_str(),
            "text/x-xyz" | "text/x-gcode" | "application/json" | "text/html" | "text/csv" | "image/svg+xml"
        )
    }

    /// Feeds the next bytes; fails as soon as the head shows the wrong type.
    pub fn update(&mut self, chunk: &[u8]) -> Result<(), ArtifactError> {
        self.size += chunk.len() as u64;
        if self.is_text() && chunk.contains(&0) {
            return Err(self.mismatch("it contains NUL bytes, so it is not text"));
        }
        if self.head.len() < HEAD_LEN {
            let take = (HEAD_LEN - self.head.len()).min(chunk.len());
            self.head.extend_from_slice(&chunk[..take]);
            self.check_head(false)?;
        }
        Ok(())
    }

    /// Final check once every byte was seen.
    pub fn finish(&self) -> Result<(), ArtifactError> {
        if self.size == 0 {
            return Err(ArtifactError::Empty);
        }
        self.check_head(true)?;
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
    /// The disk (or the quota) under the store is full: nothing was stored, and the same request
    /// can work once space is freed.
    pub fn is_out_of_space(&self) -> bool {
        matches!(self, ArtifactError::Io { source, .. }
            if matches!(source.kind(), std::io::ErrorKind::StorageFull | std::io::ErrorKind::QuotaExceeded))
    }
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
        other => {
            tracing::error!(error = %crate::ErrorChain(&other), "artifact store failed");
            ErrorCode::Internal.status("the artifact store failed")
        }
    }
}

/// Age after which a temporary upload file is a leftover of an interrupted upload.
const STALE_UPLOAD: std::time::Duration = std::time::Duration::from_secs(3600);

/// Blobs in a local folder (the default store, and the one the embedded stack shares between
/// services).
#[derive(Debug, Clone)]
pub struct LocalStore {
    root: PathBuf,
}

fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> ArtifactError + '_ {
    move |source| ArtifactError::Io { path: path.display().to_string(), source }
}

impl LocalStore {
    /// Opens (creating if needed) a store under `root` and removes leftovers of interrupted uploads.
    pub async fn open(root: impl Into<PathBuf>) -> Result<Self, ArtifactError> {
        let root: PathBuf = root.into();
        let root = if root.is_absolute() {
            root
        } else {
            std::env::current_dir().map_err(io_err(&root))?.join(&root)
        };
        let tmp = root.join("tmp");
        tokio::fs::create_dir_all(&tmp).await.map_err(io_err(&tmp))?;
        // Several services share one store and open it concurrently, and another process may be
        // uploading right now: remove only leftovers older than an hour, and let a file that
        // someone else removed first be.
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
                match tokio::fs::remove_file(entry.path()).await {
                    Ok(()) => {}
                    Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
                    Err(e) => return Err(io_err(&entry.path())(e)),
                }
            }
        }
        let blobs = root.join("blobs");
        tokio::fs::create_dir_all(&blobs).await.map_err(io_err(&blobs))?;
        Ok(Self { root })
    }

    /// The folder this store lives in.
    pub fn root(&self) -> &Path {
        &self.root
    }

    fn blob_path(&self, sha256: &str) -> PathBuf {
        self.root.join("blobs").join(&sha256[..2]).join(sha256)
    }

    fn meta_path(&self, sha256: &str) -> PathBuf {
        self.root.join("blobs").join(&sha256[..2]).join(format!("{sha256}.json"))
    }

    fn reference(&self, sha256: &str, meta: BlobMeta) -> ArtifactRef {
        ArtifactRef {
            uri: format!("file://{}", self.blob_path(sha256).display()),
            sha256: sha256.to_string(),
            size: meta.size,
            media_type: meta.media_type,
        }
    }

    async fn write_meta(&self, sha256: &str, meta: &BlobMeta) -> Result<(), ArtifactError> {
        let path = self.meta_path(sha256);
        let tmp = self.root.join("tmp").join(format!("{sha256}.{}.json", uuid::Uuid::now_v7()));
        let json = serde_json::to_vec(meta)
            .map_err(|source| ArtifactError::Metadata { path: path.display().to_string(), source })?;
        tokio::fs::write(&tmp, json).await.map_err(io_err(&tmp))?;
        tokio::fs::rename(&tmp, &path).await.map_err(io_err(&path))
    }
}

#[async_trait::async_trait]
impl ArtifactStore for LocalStore {
    async fn put(
        &self,
        media_type: &str,
        body: &mut (dyn AsyncRead + Send + Unpin),
        limit: u64,
    ) -> Result<ArtifactRef, ArtifactError> {
        let mut check = MediaCheck::new(media_type)?;
        let tmp_path = self.root.join("tmp").join(uuid::Uuid::now_v7().to_string());
        // Removes the temporary file on every early return.
        struct TmpGuard(Option<PathBuf>);
        impl Drop for TmpGuard {
            fn drop(&mut self) {
                if let Some(p) = self.0.take() {
                    let _ = std::fs::remove_file(p);
                }
            }
        }
        let mut guard = TmpGuard(Some(tmp_path.clone()));
        let mut file = tokio::fs::File::create(&tmp_path).await.map_err(io_err(&tmp_path))?;
        let mut hasher = Sha256::new();
        let mut size: u64 = 0;
        let mut buf = vec![0u8; 64 * 1024];
        loop {
            let n = body.read(&mut buf).await.map_err(ArtifactError::Upload)?;
            if n == 0 {
                break;
            }
            size += n as u64;
            if size > limit {
                return Err(ArtifactError::TooLarge { limit });
            }
            let chunk = &buf[..n];
            check.update(chunk)?;
            hasher.update(chunk);
            file.write_all(chunk).await.map_err(io_err(&tmp_path))?;
        }
        check.finish()?;
        file.sync_all().await.map_err(io_err(&tmp_path))?;
        drop(file);
        let sha256 = hex::encode(hasher.finalize());
        let dest = self.blob_path(&sha256);
        if let Some(dir) = dest.parent() {
            tokio::fs::create_dir_all(dir).await.map_err(io_err(dir))?;
        }
        let meta = BlobMeta { media_type: check.media_type().to_string(), size };
        // Metadata first: a blob file without metadata is never visible (stat needs both).
        self.write_meta(&sha256, &meta).await?;
        if tokio::fs::try_exists(&dest).await.map_err(io_err(&dest))? {
            // Same bytes already stored; the temporary copy goes with the guard.
        } else {
            tokio::fs::rename(&tmp_path, &dest).await.map_err(io_err(&dest))?;
            guard.0 = None;
        }
        tracing::debug!(%sha256, size, media_type = %meta.media_type, "artifact stored");
        Ok(self.reference(&sha256, meta))
    }

    async fn stat(&self, sha256: &str) -> Result<Option<ArtifactRef>, ArtifactError> {
        validate_digest(sha256)?;
        let meta_path = self.meta_path(sha256);
        let bytes = match tokio::fs::read(&meta_path).await {
            Ok(b) => b,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(source) => return Err(ArtifactError::Io { path: meta_path.display().to_string(), source }),
        };
        let blob = self.blob_path(sha256);
        if !tokio::fs::try_exists(&blob).await.map_err(io_err(&blob))? {
            return Ok(None);
        }
        let meta: BlobMeta = serde_json::from_slice(&bytes)
            .map_err(|source| ArtifactError::Metadata { path: meta_path.display().to_string(), source })?;
        Ok(Some(self.reference(sha256, meta)))
    }

    async fn open(&self, sha256: &str) -> Result<(ArtifactRef, BlobReader), ArtifactError> {
        let aref =
            self.stat(sha256).await?.ok_or_else(|| ArtifactError::NotFound { sha256: sha256.into() })?;
        let path = self.blob_path(sha256);
        let file = tokio::fs::File::open(&path).await.map_err(io_err(&path))?;
        Ok((aref, Box::pin(file)))
    }

    fn local_path(&self, sha256: &str) -> Option<PathBuf> {
        validate_digest(sha256).ok()?;
        Some(self.blob_path(sha256))
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

    async fn store() -> (tempfile::TempDir, LocalStore) {
        let dir = tempfile::tempdir().expect("tempdir");
        let store = LocalStore::open(dir.path().join("artifacts")).await.expect("open");
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
        let tmp_entries = std::fs::read_dir(store.root().join("tmp")).expect("tmp").count();
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
        assert_eq!(std::fs::read_dir(store.root().join("tmp")).expect("tmp").count(), 0);
        assert_eq!(std::fs::read_dir(store.root().join("blobs")).expect("blobs").count(), 0);
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
        assert!(store.local_path("XYZ").is_none());
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
