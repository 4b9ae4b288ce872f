//! Persistence of jobs behind [`JobStore`], with [`SqliteStore`] (sqlx, WAL mode) as the embedded
//! default. A server database can implement the same trait for deployments that outgrow one machine.
//!
//! Concurrency model: a worker *claims* a runnable job by taking a lease (`lease_owner`,
//! `lease_expires_ms`) and renews it while it works; every write a worker makes is fenced by the
//! lease, so a worker that lost its lease cannot record anything. A stage result is keyed by
//! `(job_id, stage)`, so it is recorded at most once whatever happens.

mod sqlite;

pub use sqlite::SqliteStore;

use crate::domain::{AttemptOutcome, Job, JobError, JobSpec, JobStatus, Stage, StageResult};

/// Why the store could not do what was asked.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
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

/// A job to insert.
#[derive(Debug, Clone)]
pub struct NewJob {
    pub id: String,
    pub spec: JobSpec,
    pub idempotency_key: Option<String>,
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

/// Job persistence.
#[async_trait::async_trait]
pub trait JobStore: Send + Sync + 'static {
    /// Inserts a queued job, or returns the job an earlier request with the same idempotency key made.
    async fn create(&self, new: NewJob) -> Result<Created, StoreError>;
    async fn get(&self, id: &str) -> Result<Option<Job>, StoreError>;
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
    /// Records a stage's result and moves the job to `next` (or to succeeded when `None`), atomically.
    /// Recording the same stage twice is refused by the schema.
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
}
