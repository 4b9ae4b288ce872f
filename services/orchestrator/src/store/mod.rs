//! Persistence of jobs behind [`JobStore`]: [`SqliteStore`] (sqlx, WAL mode) is the embedded
//! default; [`PostgresStore`] serves several orchestrator replicas sharing one database. [`open`]
//! picks one by the database URL (`sqlite://PATH` or `postgres://...`).
//!
//! Concurrency model: a worker *claims* a runnable job by taking a lease (`lease_owner`,
//! `lease_expires_ms`) and renews it while it works; every write a worker makes is fenced by the
//! lease, so a worker that lost its lease cannot record anything. A stage result is keyed by
//! `(job_id, stage)`, so it is recorded at most once whatever happens.

mod postgres;
mod rows;
pub mod scratch;
mod sqlite;
#[cfg(test)]
mod tests;

use std::path::Path;
use std::sync::Arc;

pub use postgres::PostgresStore;
pub use sqlite::SqliteStore;

/// The columns of `api_tokens` a [`TokenRecord`] is read from.
macro_rules! token_columns {
    () => {
        "id, name, scopes, created_at_ms, expires_at_ms, revoked_at_ms"
    };
}
use token_columns;

/// The columns of `calibrations` a [`CalibrationRecord`] is read from.
macro_rules! calibration_columns {
    () => {
        "id, version, created_at_ms, trigger_kind, calibration_json, report_json"
    };
}
use calibration_columns;

use crate::domain::{AttemptOutcome, Job, JobError, JobSpec, JobStatus, Stage, StageResult};

/// Why the store could not do what was asked.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    #[error("unsupported database URL '{url}': {reason}")]
    BadUrl { url: String, reason: &'static str },
    #[error("database error")]
    Db(#[from] sqlx::Error),
    #[error("database migration failed")]
    Migrate(#[from] sqlx::migrate::MigrateError),
    #[error("stored {what} of job {id} is corrupt: {detail}")]
    Corrupt { id: String, what: &'static str, detail: String },
    #[error("idempotency key '{key}' was already used for a different job request (job {job_id})")]
    IdempotencyConflict { key: String, job_id: String },
    #[error("job {id} is no longer leased by this worker")]
    LeaseLost { id: String },
    #[error("cannot encode {what}")]
    Encode {
        what: &'static str,
        #[source]
        source: serde_json::Error,
    },
}

impl StoreError {
    /// The database could not be reached or is too busy: the request may work when retried (HTTP
    /// 503, gRPC UNAVAILABLE) and nothing was changed.
    pub fn is_unavailable(&self) -> bool {
        let StoreError::Db(e) = self else { return false };
        match e {
            sqlx::Error::Io(_)
            | sqlx::Error::Tls(_)
            | sqlx::Error::PoolTimedOut
            | sqlx::Error::PoolClosed
            | sqlx::Error::WorkerCrashed => true,
            sqlx::Error::Database(db) => db.code().is_some_and(|code| {
                // PostgreSQL: connection exceptions (08xxx), shutting down or starting (57P01-57P03),
                // too many connections (53300). SQLite: busy (5) or locked (6) past the busy timeout.
                code.starts_with("08") || matches!(&*code, "57P01" | "57P02" | "57P03" | "53300" | "5" | "6")
            }),
            _ => false,
        }
    }
}

/// Opens the job store a database URL names: `sqlite://PATH` (created if missing) or
/// `postgres://USER@HOST:PORT/DB` (`postgresql://` too); applies pending migrations either way.
pub async fn open(url: &str) -> Result<Arc<dyn JobStore>, StoreError> {
    let bad = |reason| StoreError::BadUrl { url: redact(url), reason };
    if let Some(path) = url.strip_prefix("sqlite://").or_else(|| url.strip_prefix("sqlite:")) {
        let path = path.split('?').next().unwrap_or_default();
        if path.is_empty() {
            return Err(bad("no file path after sqlite://"));
        }
        Ok(Arc::new(SqliteStore::open(Path::new(path)).await?))
    } else if url.starts_with("postgres://") || url.starts_with("postgresql://") {
        Ok(Arc::new(PostgresStore::connect(url).await?))
    } else {
        Err(bad("expected sqlite://PATH or postgres://USER@HOST:PORT/DB"))
    }
}

/// `url` without its password, for logs and errors.
pub fn redact(url: &str) -> String {
    let Some((scheme, rest)) = url.split_once("://") else { return url.to_string() };
    let (authority, tail) = match rest.find('/') {
        Some(i) => rest.split_at(i),
        None => (rest, ""),
    };
    match authority.rsplit_once('@') {
        Some((userinfo, host)) => match userinfo.split_once(':') {
            Some((user, _password)) => format!("{scheme}://{user}:***@{host}{tail}"),
            None => url.to_string(),
        },
        None => url.to_string(),
    }
}

/// A job to insert.
#[derive(Debug, Clone)]
pub struct NewJob {
    pub id: String,
    pub spec: JobSpec,
    pub idempotency_key: Option<String>,
    /// Who submits it (`token:<id>` or `addr:<ip>`); counted by [`JobStore::active_jobs_of`].
    pub client: Option<String>,
    pub now_ms: i64,
}

/// The outcome of [`JobStore::create`].
#[derive(Debug, Clone)]
pub enum Created {
    /// A new job was inserted.
    New(Job),
    /// The idempotency key was already used for the same request: this is that job.
    Existing(Job),
}

/// A job a worker holds the lease of.
#[derive(Debug, Clone)]
pub struct ClaimedJob {
    pub id: String,
    pub spec: JobSpec,
    pub stage: Stage,
    pub cancel_requested: bool,
}

/// What a lease renewal found.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct LeaseState {
    /// The lease is still this worker's.
    pub held: bool,
    pub cancel_requested: bool,
}

/// A page of jobs.
#[derive(Debug, Clone)]
pub struct JobPage {
    pub jobs: Vec<Job>,
    /// Pass back as `cursor` for the next page; `None` on the last page.
    pub next_cursor: Option<i64>,
}

/// A bearer token as stored: everything but its secret, of which only a hash is kept.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize, sqlx::FromRow)]
pub struct TokenRecord {
    /// Public handle (`tok_...`), for listing and revoking.
    pub id: String,
    /// Who or what holds it.
    pub name: String,
    /// Space-separated scopes (`read`, `submit`, `admin`).
    pub scopes: String,
    pub created_at_ms: i64,
    pub expires_at_ms: Option<i64>,
    pub revoked_at_ms: Option<i64>,
}

/// A stored calibration of the scanning cell (the newest is in force).
#[derive(Debug, Clone, PartialEq, Eq, sqlx::FromRow)]
pub struct CalibrationRecord {
    /// Public handle (`cal_...`).
    pub id: String,
    /// 1, 2, ... in the order they were made.
    pub version: i64,
    pub created_at_ms: i64,
    /// `api` (asked for) or `auto` (made before a scan when none was in force).
    pub trigger_kind: String,
    /// The parameters, JSON.
    pub calibration_json: String,
    /// The fit's report, JSON.
    pub report_json: String,
}

/// Job persistence, and the API tokens that guard it.
#[async_trait::async_trait]
pub trait JobStore: Send + Sync + 'static {
    /// Inserts a queued job, or returns the job an earlier request with the same idempotency key made.
    async fn create(&self, new: NewJob) -> Result<Created, StoreError>;
    async fn get(&self, id: &str) -> Result<Option<Job>, StoreError>;
    /// Jobs of `client` that are queued or running, counted up to `at_most` (the limit being
    /// checked: the count costs at most that many index entries, whatever the queue holds).
    async fn active_jobs_of(&self, client: &str, at_most: u64) -> Result<u64, StoreError>;
    /// Whether a job was submitted with this idempotency key.
    async fn key_exists(&self, key: &str) -> Result<bool, StoreError>;
    /// Jobs newest first, optionally only those with `status`, after `cursor`.
    async fn list(
        &self,
        status: Option<JobStatus>,
        limit: u32,
        cursor: Option<i64>,
    ) -> Result<JobPage, StoreError>;
    /// Asks a job to stop: a queued job is cancelled at once, a running one at its next stage boundary.
    /// `None` when there is no such job.
    async fn request_cancel(&self, id: &str, now_ms: i64) -> Result<Option<Job>, StoreError>;
    /// Takes the lease of the oldest runnable job (queued, or running with an expired lease).
    async fn claim(&self, owner: &str, now_ms: i64, lease_ms: i64) -> Result<Option<ClaimedJob>, StoreError>;
    async fn renew(
        &self,
        id: &str,
        owner: &str,
        now_ms: i64,
        lease_ms: i64,
    ) -> Result<LeaseState, StoreError>;
    /// After a restart of `owner`: releases its leases and marks its running attempts interrupted.
    /// Returns how many jobs were released.
    async fn recover_owner(&self, owner: &str, now_ms: i64) -> Result<u64, StoreError>;
    /// Records the start of an attempt at `stage` and marks the job running there. Returns the attempt number.
    async fn begin_attempt(
        &self,
        id: &str,
        owner: &str,
        stage: Stage,
        now_ms: i64,
    ) -> Result<u32, StoreError>;
    async fn finish_attempt(
        &self,
        id: &str,
        stage: Stage,
        attempt: u32,
        outcome: AttemptOutcome,
        error: Option<(&str, &str)>,
        now_ms: i64,
    ) -> Result<(), StoreError>;
    /// Records a stage's result, marks its running attempt ok and moves the job to `next` (or to
    /// succeeded when `None`), atomically. Recording the same stage twice is refused by the schema.
    async fn complete_stage(
        &self,
        id: &str,
        owner: &str,
        result: &StageResult,
        next: Option<Stage>,
        progress: f64,
        now_ms: i64,
    ) -> Result<(), StoreError>;
    async fn set_progress(&self, id: &str, owner: &str, progress: f64, now_ms: i64)
    -> Result<(), StoreError>;
    /// Ends a job as failed or cancelled and releases its lease.
    async fn end(
        &self,
        id: &str,
        owner: &str,
        status: JobStatus,
        error: Option<&JobError>,
        now_ms: i64,
    ) -> Result<(), StoreError>;
    async fn stage_results(&self, id: &str) -> Result<Vec<StageResult>, StoreError>;
    /// Cheap liveness check for `/readyz`.
    async fn ping(&self) -> Result<(), StoreError>;
    /// Stores a new token under the SHA-256 of its secret.
    async fn create_token(&self, token: &TokenRecord, secret_sha256: &str) -> Result<(), StoreError>;
    /// The token whose secret hashes to `secret_sha256`, revoked or expired ones included.
    async fn token_by_secret(&self, secret_sha256: &str) -> Result<Option<TokenRecord>, StoreError>;
    /// Every token, oldest first.
    async fn list_tokens(&self) -> Result<Vec<TokenRecord>, StoreError>;
    /// Revokes a token; `false` when there is no such token or it was already revoked.
    async fn revoke_token(&self, id: &str, now_ms: i64) -> Result<bool, StoreError>;
    /// Stores a calibration as the next version (the record's `version` is ignored) and returns
    /// it as stored.
    async fn create_calibration(&self, rec: &CalibrationRecord) -> Result<CalibrationRecord, StoreError>;
    async fn get_calibration(&self, id: &str) -> Result<Option<CalibrationRecord>, StoreError>;
    /// The newest calibration: the one in force.
    async fn latest_calibration(&self) -> Result<Option<CalibrationRecord>, StoreError>;
    /// Calibrations newest first, at most `limit`.
    async fn list_calibrations(&self, limit: u32) -> Result<Vec<CalibrationRecord>, StoreError>;
}
