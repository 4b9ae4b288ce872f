//! [`JobStore`] on SQLite through sqlx: WAL journal, one writer connection (SQLite serialises
//! writers anyway; one connection avoids lock retries) and a pool of readers.

use std::collections::BTreeMap;
use std::path::Path;
use std::str::FromStr;
use std::time::Duration;

use sqlx::sqlite::{
    SqliteConnectOptions, SqliteJournalMode, SqlitePoolOptions, SqliteRow, SqliteSynchronous,
};
use sqlx::{Row, SqlitePool};

use super::{ClaimedJob, Created, JobPage, JobStore, LeaseState, NewJob, StoreError};
use crate::domain::{
    AttemptOutcome, AttemptRecord, Job, JobError, JobMetrics, JobSpec, JobStatus, Stage, StageOutputs,
    StageResult,
};

static MIGRATOR: sqlx::migrate::Migrator = sqlx::migrate!("../../migrations");

/// SQLite-backed job store.
#[derive(Clone)]
pub struct SqliteStore {
    writer: SqlitePool,
    reader: SqlitePool,
}

impl SqliteStore {
    /// Opens (creating if missing) the database file at `path` and applies pending migrations.
    pub async fn open(path: &Path) -> Result<Self, StoreError> {
        let options = SqliteConnectOptions::new()
            .filename(path)
            .create_if_missing(true)
            .journal_mode(SqliteJournalMode::Wal)
            .synchronous(SqliteSynchronous::Normal)
            .foreign_keys(true)
            .busy_timeout(Duration::from_secs(10));
        let writer = SqlitePoolOptions::new().max_connections(1).connect_with(options.clone()).await?;
        MIGRATOR.run(&writer).await?;
        let reader =
            SqlitePoolOptions::new().max_connections(4).connect_with(options.read_only(true)).await?;
        Ok(Self { writer, reader })
    }

    async fn job_from_row(&self, row: &SqliteRow) -> Result<Job, StoreError> {
        let id: String = row.try_get("id")?;
        let corrupt =
            |what: &'static str, detail: String| StoreError::Corrupt { id: id.clone(), what, detail };
        let spec: JobSpec = serde_json::from_str(&row.try_get::<String, _>("spec")?)
            .map_err(|e| corrupt("spec", e.to_string()))?;
        let status =
            JobStatus::from_str(&row.try_get::<String, _>("status")?).map_err(|e| corrupt("status", e))?;
        let stage = Stage::from_str(&row.try_get::<String, _>("stage")?).map_err(|e| corrupt("stage", e))?;
        let error = match row.try_get::<Option<String>, _>("error_code")? {
            Some(code) => Some(JobError {
                code,
                message: row.try_get::<Option<String>, _>("error_message")?.unwrap_or_default(),
                stage: row
                    .try_get::<Option<String>, _>("error_stage")?
                    .map(|s| Stage::from_str(&s))
                    .transpose()
                    .map_err(|e| corrupt("error stage", e))?
                    .unwrap_or(stage),
            }),
            None => None,
        };
        let results = self.stage_results(&id).await?;
        // The input's reference is added by the application layer, which knows the artifact store.
        let mut artifacts = BTreeMap::new();
        let mut stage_timings_s = BTreeMap::new();
        let mut metrics = JobMetrics::default();
        for r in &results {
            stage_timings_s
                .insert(r.stage.as_str().to_string(), (r.finished_at_ms - r.started_at_ms) as f64 / 1000.0);
            artifacts.extend(r.outputs.artifacts.clone());
            metrics.absorb(&r.outputs.metrics);
        }
        let attempts = self.attempts(&id).await?;
        // A stage without a result (failed, cancelled, running) shows the time its finished
        // attempts took, retries included.
        for a in &attempts {
            let Some(end) = a.finished_at_ms else { continue };
            if results.iter().any(|r| r.stage == a.stage) {
                continue;
            }
            *stage_timings_s.entry(a.stage.as_str().to_string()).or_insert(0.0) +=
                (end - a.started_at_ms).max(0) as f64 / 1000.0;
        }
        Ok(Job {
            name: row.try_get("name")?,
            status,
            stage,
            progress: row.try_get("progress")?,
            error,
            stage_timings_s,
            artifacts,
            metrics,
            spec,
            cancel_requested: row.try_get::<i64, _>("cancel_requested")? != 0,
            created_at_ms: row.try_get("created_at_ms")?,
            updated_at_ms: row.try_get("updated_at_ms")?,
            attempts,
            id,
        })
    }

    async fn attempts(&self, id: &str) -> Result<Vec<AttemptRecord>, StoreError> {
        let rows = sqlx::query(
            "SELECT stage, attempt, started_at_ms, finished_at_ms, outcome, error_code, error_message \
             FROM attempts WHERE job_id = ? ORDER BY id",
        )
        .bind(id)
        .fetch_all(&self.reader)
        .await?;
        rows.iter()
            .map(|r| {
                let corrupt = |what, detail| StoreError::Corrupt { id: id.to_string(), what, detail };
                Ok(AttemptRecord {
                    stage: Stage::from_str(&r.try_get::<String, _>("stage")?)
                        .map_err(|e| corrupt("attempt", e))?,
                    attempt: u32::try_from(r.try_get::<i64, _>("attempt")?).unwrap_or(0),
                    started_at_ms: r.try_get("started_at_ms")?,
                    finished_at_ms: r.try_get("finished_at_ms")?,
                    outcome: AttemptOutcome::from_str(&r.try_get::<String, _>("outcome")?)
                        .map_err(|e| corrupt("attempt", e))?,
                    error_code: r.try_get("error_code")?,
                    error_message: r.try_get("error_message")?,
                })
            })
            .collect()
    }

    async fn get_from(&self, pool: &SqlitePool, id: &str) -> Result<Option<Job>, StoreError> {
        let sql = "SELECT id, name, spec, first_stage, status, stage, progress, error_code, error_message, \
                   error_stage, cancel_requested, created_at_ms, updated_at_ms, seq FROM jobs WHERE id = ?";
        match sqlx::query(sql).bind(id).fetch_optional(pool).await? {
            Some(row) => Ok(Some(self.job_from_row(&row).await?)),
            None => Ok(None),
        }
    }
}

fn encode<T: serde::Serialize>(what: &'static str, v: &T) -> Result<String, StoreError> {
    serde_json::to_string(v).map_err(|source| StoreError::Encode { what, source })
}

#[async_trait::async_trait]
impl JobStore for SqliteStore {
    async fn create(&self, new: NewJob) -> Result<Created, StoreError> {
        let spec_json = encode("job spec", &new.spec)?;
        let first = new.spec.first_stage();
        let inserted = sqlx::query(
            "INSERT INTO jobs (id, name, spec, first_stage, status, stage, progress, idempotency_key, \
             created_at_ms, updated_at_ms) VALUES (?, ?, ?, ?, 'queued', ?, 0, ?, ?, ?) \
             ON CONFLICT (idempotency_key) DO NOTHING",
        )
        .bind(&new.id)
        .bind(&new.spec.name)
        .bind(&spec_json)
        .bind(first.as_str())
        .bind(first.as_str())
        .bind(&new.idempotency_key)
        .bind(new.now_ms)
        .bind(new.now_ms)
        .execute(&self.writer)
        .await?
        .rows_affected();
        if inserted == 1 {
            // Everything about a new job is known: no need to read it back.
            return Ok(Created::New(Job {
                id: new.id,
                name: new.spec.name.clone(),
                status: JobStatus::Queued,
                stage: first,
                progress: 0.0,
                error: None,
                stage_timings_s: BTreeMap::new(),
                artifacts: BTreeMap::new(),
                metrics: JobMetrics::default(),
                spec: new.spec,
                cancel_requested: false,
                created_at_ms: new.now_ms,
                updated_at_ms: new.now_ms,
                attempts: Vec::new(),
            }));
        }
        // The key exists: same request -> same job; different request -> conflict.
        let key = new.idempotency_key.clone().unwrap_or_default();
        let row = sqlx::query("SELECT id, spec FROM jobs WHERE idempotency_key = ?")
            .bind(&key)
            .fetch_one(&self.writer)
            .await?;
        let id: String = row.try_get("id")?;
        let stored: String = row.try_get("spec")?;
        if stored != spec_json {
            return Err(StoreError::IdempotencyConflict { key, job_id: id });
        }
        let job = self.get_from(&self.writer, &id).await?.ok_or_else(|| StoreError::Corrupt {
            id: id.clone(),
            what: "row",
            detail: "job of idempotency key vanished".into(),
        })?;
        Ok(Created::Existing(job))
    }

    async fn get(&self, id: &str) -> Result<Option<Job>, StoreError> {
        self.get_from(&self.reader, id).await
    }

    async fn list(
        &self,
        status: Option<JobStatus>,
        limit: u32,
        cursor: Option<i64>,
    ) -> Result<JobPage, StoreError> {
        let limit = i64::from(limit.clamp(1, 1000));
        let rows = sqlx::query(
            "SELECT id, name, spec, first_stage, status, stage, progress, error_code, error_message, \
             error_stage, cancel_requested, created_at_ms, updated_at_ms, seq FROM jobs \
             WHERE (?1 IS NULL OR status = ?1) AND (?2 IS NULL OR seq < ?2) ORDER BY seq DESC LIMIT ?3",
        )
        .bind(status.map(|s| s.as_str()))
        .bind(cursor)
        .bind(limit + 1)
        .fetch_all(&self.reader)
        .await?;
        let more = rows.len() as i64 > limit;
        let mut jobs = Vec::with_capacity(rows.len());
        let mut last_seq = None;
        for row in rows.iter().take(limit as usize) {
            last_seq = Some(row.try_get::<i64, _>("seq")?);
            jobs.push(self.job_from_row(row).await?);
        }
        Ok(JobPage { jobs, next_cursor: if more { last_seq } else { None } })
    }

    async fn request_cancel(&self, id: &str, now_ms: i64) -> Result<Option<Job>, StoreError> {
        let mut tx = self.writer.begin().await?;
        sqlx::query(
            "UPDATE jobs SET status = 'cancelled', cancel_requested = 1, updated_at_ms = ?2, \
             error_code = 'cancelled', error_message = 'cancelled before it started', error_stage = stage, \
             lease_owner = NULL, lease_expires_ms = NULL WHERE id = ?1 AND status = 'queued' \
             AND lease_owner IS NULL",
        )
        .bind(id)
        .bind(now_ms)
        .execute(&mut *tx)
        .await?;
        sqlx::query(
            "UPDATE jobs SET cancel_requested = 1, updated_at_ms = ?2 WHERE id = ?1 \
             AND status IN ('queued', 'running')",
        )
        .bind(id)
        .bind(now_ms)
        .execute(&mut *tx)
        .await?;
        tx.commit().await?;
        self.get_from(&self.writer, id).await
    }

    async fn claim(&self, owner: &str, now_ms: i64, lease_ms: i64) -> Result<Option<ClaimedJob>, StoreError> {
        let row = sqlx::query(
            "UPDATE jobs SET lease_owner = ?1, lease_expires_ms = ?2 + ?3 WHERE seq = ( \
                 SELECT seq FROM jobs WHERE status IN ('queued', 'running') \
                 AND (lease_owner IS NULL OR lease_expires_ms < ?2) ORDER BY seq LIMIT 1) \
             RETURNING id, spec, stage, cancel_requested",
        )
        .bind(owner)
        .bind(now_ms)
        .bind(lease_ms)
        .fetch_optional(&self.writer)
        .await?;
        let Some(row) = row else { return Ok(None) };
        let id: String = row.try_get("id")?;
        let spec = serde_json::from_str(&row.try_get::<String, _>("spec")?)
            .map_err(|e| StoreError::Corrupt { id: id.clone(), what: "spec", detail: e.to_string() })?;
        let stage = Stage::from_str(&row.try_get::<String, _>("stage")?)
            .map_err(|e| StoreError::Corrupt { id: id.clone(), what: "stage", detail: e })?;
        Ok(Some(ClaimedJob {
            id,
            spec,
            stage,
            cancel_requested: row.try_get::<i64, _>("cancel_requested")? != 0,
        }))
    }

    async fn renew(
        &self,
        id: &str,
        owner: &str,
        now_ms: i64,
        lease_ms: i64,
    ) -> Result<LeaseState, StoreError> {
        let row = sqlx::query(
            "UPDATE jobs SET lease_expires_ms = ?3 + ?4 WHERE id = ?1 AND lease_owner = ?2 \
             RETURNING cancel_requested",
        )
        .bind(id)
        .bind(owner)
        .bind(now_ms)
        .bind(lease_ms)
        .fetch_optional(&self.writer)
        .await?;
        Ok(match row {
            Some(r) => {
                LeaseState { held: true, cancel_requested: r.try_get::<i64, _>("cancel_requested")? != 0 }
            }
            None => LeaseState { held: false, cancel_requested: false },
        })
    }

    async fn recover_owner(&self, owner: &str, now_ms: i64) -> Result<u64, StoreError> {
        let mut tx = self.writer.begin().await?;
        sqlx::query(
            "UPDATE attempts SET outcome = 'interrupted', finished_at_ms = ?2, \
             error_message = 'the orchestrator stopped while this attempt ran' \
             WHERE owner = ?1 AND outcome = 'running'",
        )
        .bind(owner)
        .bind(now_ms)
        .execute(&mut *tx)
        .await?;
        let released = sqlx::query(
            "UPDATE jobs SET lease_owner = NULL, lease_expires_ms = NULL WHERE lease_owner = ?1 \
             AND status IN ('queued', 'running')",
        )
        .bind(owner)
        .execute(&mut *tx)
        .await?
        .rows_affected();
        tx.commit().await?;
        Ok(released)
    }

    async fn begin_attempt(
        &self,
        id: &str,
        owner: &str,
        stage: Stage,
        now_ms: i64,
    ) -> Result<u32, StoreError> {
        let mut tx = self.writer.begin().await?;
        let updated = sqlx::query(
            "UPDATE jobs SET status = 'running', stage = ?3, updated_at_ms = ?4 WHERE id = ?1 AND lease_owner = ?2",
        )
        .bind(id)
        .bind(owner)
        .bind(stage.as_str())
        .bind(now_ms)
        .execute(&mut *tx)
        .await?
        .rows_affected();
        if updated == 0 {
            return Err(StoreError::LeaseLost { id: id.to_string() });
        }
        let attempt: i64 = sqlx::query(
            "INSERT INTO attempts (job_id, stage, attempt, owner, started_at_ms, outcome) \
             VALUES (?1, ?2, (SELECT COALESCE(MAX(attempt), 0) + 1 FROM attempts WHERE job_id = ?1 AND stage = ?2), \
                     ?3, ?4, 'running') RETURNING attempt",
        )
        .bind(id)
        .bind(stage.as_str())
        .bind(owner)
        .bind(now_ms)
        .fetch_one(&mut *tx)
        .await?
        .try_get("attempt")?;
        tx.commit().await?;
        Ok(u32::try_from(attempt).unwrap_or(u32::MAX))
    }

    async fn finish_attempt(
        &self,
        id: &str,
        stage: Stage,
        attempt: u32,
        outcome: AttemptOutcome,
        error: Option<(&str, &str)>,
        now_ms: i64,
    ) -> Result<(), StoreError> {
        sqlx::query(
            "UPDATE attempts SET outcome = ?4, error_code = ?5, error_message = ?6, finished_at_ms = ?7 \
             WHERE job_id = ?1 AND stage = ?2 AND attempt = ?3",
        )
        .bind(id)
        .bind(stage.as_str())
        .bind(i64::from(attempt))
        .bind(outcome.as_str())
        .bind(error.map(|e| e.0))
        .bind(error.map(|e| e.1))
        .bind(now_ms)
        .execute(&self.writer)
        .await?;
        Ok(())
    }

    async fn complete_stage(
        &self,
        id: &str,
        owner: &str,
        result: &StageResult,
        next: Option<Stage>,
        progress: f64,
        now_ms: i64,
    ) -> Result<(), StoreError> {
        let outputs = encode("stage outputs", &result.outputs)?;
        let mut tx = self.writer.begin().await?;
        let (status, stage) = match next {
            Some(n) => ("running", n),
            None => ("succeeded", result.stage),
        };
        let updated = sqlx::query(
            "UPDATE jobs SET status = ?3, stage = ?4, progress = ?5, updated_at_ms = ?6, \
             lease_owner = CASE WHEN ?3 = 'succeeded' THEN NULL ELSE lease_owner END \
             WHERE id = ?1 AND lease_owner = ?2",
        )
        .bind(id)
        .bind(owner)
        .bind(status)
        .bind(stage.as_str())
        .bind(progress)
        .bind(now_ms)
        .execute(&mut *tx)
        .await?
        .rows_affected();
        if updated == 0 {
            return Err(StoreError::LeaseLost { id: id.to_string() });
        }
        sqlx::query(
            "INSERT INTO stage_results (job_id, stage, outputs, started_at_ms, finished_at_ms) VALUES (?, ?, ?, ?, ?)",
        )
        .bind(id)
        .bind(result.stage.as_str())
        .bind(outputs)
        .bind(result.started_at_ms)
        .bind(result.finished_at_ms)
        .execute(&mut *tx)
        .await?;
        tx.commit().await?;
        Ok(())
    }

    async fn set_progress(
        &self,
        id: &str,
        owner: &str,
        progress: f64,
        now_ms: i64,
    ) -> Result<(), StoreError> {
        sqlx::query("UPDATE jobs SET progress = ?3, updated_at_ms = ?4 WHERE id = ?1 AND lease_owner = ?2")
            .bind(id)
            .bind(owner)
            .bind(progress)
            .bind(now_ms)
            .execute(&self.writer)
            .await?;
        Ok(())
    }

    async fn end(
        &self,
        id: &str,
        owner: &str,
        status: JobStatus,
        error: Option<&JobError>,
        now_ms: i64,
    ) -> Result<(), StoreError> {
        let updated = sqlx::query(
            "UPDATE jobs SET status = ?3, error_code = ?4, error_message = ?5, error_stage = ?6, \
             updated_at_ms = ?7, lease_owner = NULL, lease_expires_ms = NULL WHERE id = ?1 AND lease_owner = ?2",
        )
        .bind(id)
        .bind(owner)
        .bind(status.as_str())
        .bind(error.map(|e| e.code.as_str()))
        .bind(error.map(|e| e.message.as_str()))
        .bind(error.map(|e| e.stage.as_str()))
        .bind(now_ms)
        .execute(&self.writer)
        .await?
        .rows_affected();
        if updated == 0 {
            return Err(StoreError::LeaseLost { id: id.to_string() });
        }
        Ok(())
    }

    async fn stage_results(&self, id: &str) -> Result<Vec<StageResult>, StoreError> {
        let rows = sqlx::query(
            "SELECT stage, outputs, started_at_ms, finished_at_ms FROM stage_results WHERE job_id = ? \
             ORDER BY started_at_ms",
        )
        .bind(id)
        .fetch_all(&self.reader)
        .await?;
        let mut out = Vec::with_capacity(rows.len());
        for r in rows {
            let corrupt = |detail| StoreError::Corrupt { id: id.to_string(), what: "stage result", detail };
            let stage = Stage::from_str(&r.try_get::<String, _>("stage")?).map_err(corrupt)?;
            let outputs: StageOutputs =
                serde_json::from_str(&r.try_get::<String, _>("outputs")?).map_err(|e| {
                    StoreError::Corrupt { id: id.to_string(), what: "stage result", detail: e.to_string() }
                })?;
            out.push(StageResult {
                stage,
                outputs,
                started_at_ms: r.try_get("started_at_ms")?,
                finished_at_ms: r.try_get("finished_at_ms")?,
            });
        }
        out.sort_by_key(|r| r.stage);
        Ok(out)
    }

    async fn ping(&self) -> Result<(), StoreError> {
        sqlx::query("SELECT 1").execute(&self.reader).await?;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::domain::spec::{InputKind, JobInput};

    fn spec(name: &str) -> JobSpec {
        JobSpec {
            name: name.into(),
            input: JobInput {
                kind: InputKind::Gcode,
                artifact: "a".repeat(64),
                pixel_mm: None,
                z_min_mm: None,
                z_max_mm: None,
                units: None,
            },
            scan: None,
            reconstruct: None,
            plan: None,
            execute: None,
        }
    }

    async fn store() -> (tempfile::TempDir, SqliteStore) {
        let dir = tempfile::tempdir().expect("tempdir");
        let store = SqliteStore::open(&dir.path().join("jobs.sqlite")).await.expect("open");
        (dir, store)
    }

    fn new(id: &str, key: Option<&str>) -> NewJob {
        NewJob { id: id.into(), spec: spec(id), idempotency_key: key.map(Into::into), now_ms: 1 }
    }

    #[tokio::test]
    async fn leases_fence_writers_and_a_stage_is_recorded_once() {
        let (_dir, s) = store().await;
        assert!(matches!(s.create(new("j1", None)).await.expect("create"), Created::New(_)));
        let claimed = s.claim("a", 100, 1000).await.expect("claim").expect("a job");
        assert_eq!((claimed.id.as_str(), claimed.stage), ("j1", Stage::Execute));
        // Leased: nobody else gets it until the lease expires.
        assert!(s.claim("b", 500, 1000).await.expect("claim").is_none());
        let attempt = s.begin_attempt("j1", "a", Stage::Execute, 200).await.expect("begin");
        assert_eq!(attempt, 1);
        // The lease expires; b takes over; a can no longer write.
        let taken = s.claim("b", 5000, 1000).await.expect("claim").expect("expired lease");
        assert_eq!(taken.id, "j1");
        let result = StageResult {
            stage: Stage::Execute,
            outputs: StageOutputs::default(),
            started_at_ms: 1,
            finished_at_ms: 2,
        };
        let lost = s.complete_stage("j1", "a", &result, Some(Stage::Report), 0.5, 5001).await;
        assert!(matches!(lost, Err(StoreError::LeaseLost { .. })), "{lost:?}");
        assert!(!s.renew("j1", "a", 5002, 1000).await.expect("renew").held);
        s.complete_stage("j1", "b", &result, Some(Stage::Report), 0.5, 5003).await.expect("b completes");
        // A second record of the same stage is refused by the schema.
        let again = s.complete_stage("j1", "b", &result, Some(Stage::Report), 0.5, 5004).await;
        assert!(again.is_err(), "recorded twice");
        let job = s.get("j1").await.expect("get").expect("job");
        assert_eq!(job.stage, Stage::Report);
        assert_eq!(job.stage_timings_s.len(), 1);
        assert_eq!(job.progress, 0.5, "the refused write changed nothing");
    }

    #[tokio::test]
    async fn recovery_releases_the_owner_s_jobs_and_marks_attempts_interrupted() {
        let (_dir, s) = store().await;
        s.create(new("j1", None)).await.expect("create");
        s.claim("node-1", 0, 60_000).await.expect("claim").expect("job");
        s.begin_attempt("j1", "node-1", Stage::Execute, 1).await.expect("begin");
        assert_eq!(s.recover_owner("node-2", 2).await.expect("recover"), 0, "another node's lease stays");
        assert_eq!(s.recover_owner("node-1", 2).await.expect("recover"), 1);
        let job = s.get("j1").await.expect("get").expect("job");
        assert_eq!(job.attempts[0].outcome, AttemptOutcome::Interrupted);
        let again = s.claim("node-1", 3, 60_000).await.expect("claim").expect("released");
        assert_eq!(again.stage, Stage::Execute);
        assert_eq!(s.begin_attempt("j1", "node-1", Stage::Execute, 4).await.expect("begin"), 2);
    }

    #[tokio::test]
    async fn idempotency_keys_and_cancel_and_pages() {
        let (_dir, s) = store().await;
        assert!(matches!(s.create(new("j1", Some("k"))).await.expect("create"), Created::New(_)));
        let mut same = new("j2", Some("k"));
        same.spec = spec("j1");
        match s.create(same).await.expect("same request") {
            Created::Existing(job) => assert_eq!(job.id, "j1"),
            Created::New(_) => panic!("a second job for the same key"),
        }
        assert!(matches!(s.create(new("j3", Some("k"))).await, Err(StoreError::IdempotencyConflict { .. })));
        for i in 4..9 {
            s.create(new(&format!("j{i}"), None)).await.expect("create");
        }
        let job = s.request_cancel("j4", 10).await.expect("cancel").expect("job");
        assert_eq!(job.status, JobStatus::Cancelled, "a queued job is cancelled at once");
        assert!(s.request_cancel("nope", 10).await.expect("cancel").is_none());
        let mut seen = Vec::new();
        let mut cursor = None;
        loop {
            let page = s.list(Some(JobStatus::Queued), 2, cursor).await.expect("list");
            seen.extend(page.jobs.into_iter().map(|j| j.id));
            match page.next_cursor {
                Some(c) => cursor = Some(c),
                None => break,
            }
        }
        assert_eq!(seen, ["j8", "j7", "j6", "j5", "j1"]);
    }
}
