//! [`JobStore`] on SQLite through sqlx: WAL journal, one writer connection (SQLite serialises
//! writers anyway; one connection avoids lock retries) and a pool of readers. Several processes
//! may open the same file (SQLite's own locking, with a busy timeout); a server database serves
//! several replicas better ([`super::PostgresStore`]).
//!
//! Submissions are group-committed: [`JobStore::create`] hands its row to one task that inserts
//! every row waiting (up to [`MAX_BATCH`]) in one multi-row `INSERT ... RETURNING` statement, so a
//! burst of submissions costs one statement and one commit instead of one each, and waits behind
//! the worker's writes once per batch instead of once per job. A batch that fails is retried row
//! by row, so each caller gets its own row's answer (a conflict, a busy database) as before.

use std::path::Path;
use std::time::Duration;

use sqlx::SqlitePool;
use sqlx::sqlite::{SqliteConnectOptions, SqliteJournalMode, SqlitePoolOptions, SqliteSynchronous};

use super::rows::{self, AttemptRow, ClaimRow, JobRow, ResultRow, encode, job_columns};
use super::{
    CalibrationRecord, ClaimedJob, Created, JobPage, JobStore, LeaseState, NewJob, StoreError, TokenRecord,
};
use crate::domain::{AttemptOutcome, AttemptRecord, Job, JobError, JobStatus, Stage, StageResult};

static MIGRATOR: sqlx::migrate::Migrator = sqlx::migrate!("../../migrations/sqlite");

/// Most rows inserted by one statement (SQLite's default limit of 32766 bound parameters holds
/// over 3000 rows of 10).
const MAX_BATCH: usize = 256;

/// One submission waiting for the batch insert: the row and where its answer goes (`true`:
/// inserted; `false`: its idempotency key was taken).
struct PendingInsert {
    new: NewJob,
    spec_json: String,
    reply: tokio::sync::oneshot::Sender<Result<bool, StoreError>>,
}

/// SQLite-backed job store.
#[derive(Clone)]
pub struct SqliteStore {
    writer: SqlitePool,
    reader: SqlitePool,
    inserts: tokio::sync::mpsc::Sender<PendingInsert>,
}

/// Inserts `rows` with one statement; the ids it inserted.
async fn insert_rows(writer: &SqlitePool, rows: &[&PendingInsert]) -> Result<Vec<String>, sqlx::Error> {
    let mut q = sqlx::QueryBuilder::<sqlx::Sqlite>::new(
        "INSERT INTO jobs (id, name, spec, first_stage, status, stage, progress, idempotency_key, \
         client, created_at_ms, updated_at_ms) ",
    );
    q.push_values(rows, |mut b, p| {
        let first = p.new.spec.first_stage();
        b.push_bind(p.new.id.clone())
            .push_bind(p.new.spec.name.clone())
            .push_bind(p.spec_json.clone())
            .push_bind(first.as_str())
            .push_bind("queued")
            .push_bind(first.as_str())
            .push_bind(0.0f64)
            .push_bind(p.new.idempotency_key.clone())
            .push_bind(p.new.client.clone())
            .push_bind(p.new.now_ms)
            .push_bind(p.new.now_ms);
    });
    q.push(" ON CONFLICT (idempotency_key) DO NOTHING RETURNING id");
    q.build_query_scalar::<String>().fetch_all(writer).await
}

/// The group-commit task: takes every submission waiting, inserts them with one statement and
/// answers each. Ends when the store (every sender) is dropped.
async fn insert_batches(writer: SqlitePool, mut queue: tokio::sync::mpsc::Receiver<PendingInsert>) {
    let mut batch: Vec<PendingInsert> = Vec::with_capacity(MAX_BATCH);
    while queue.recv_many(&mut batch, MAX_BATCH).await > 0 {
        let rows: Vec<&PendingInsert> = batch.iter().collect();
        match insert_rows(&writer, &rows).await {
            Ok(ids) => {
                let ids: std::collections::HashSet<String> = ids.into_iter().collect();
                for p in batch.drain(..) {
                    let inserted = ids.contains(&p.new.id);
                    let _ = p.reply.send(Ok(inserted));
                }
            }
            Err(e) if batch.len() == 1 => {
                if let Some(p) = batch.pop() {
                    let _ = p.reply.send(Err(StoreError::from(e)));
                }
            }
            // Row by row: each caller gets its own row's answer.
            Err(_) => {
                for p in batch.drain(..) {
                    let answer =
                        insert_rows(&writer, &[&p]).await.map(|ids| !ids.is_empty()).map_err(Into::into);
                    let _ = p.reply.send(answer);
                }
            }
        }
    }
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
        let (inserts, queue) = tokio::sync::mpsc::channel(4 * MAX_BATCH);
        tokio::spawn(insert_batches(writer.clone(), queue));
        Ok(Self { writer, reader, inserts })
    }

    async fn job_from_row(&self, row: JobRow) -> Result<Job, StoreError> {
        let results = self.stage_results(&row.id).await?;
        let attempts = self.attempts(&row.id).await?;
        row.into_job(results, attempts)
    }

    async fn attempts(&self, id: &str) -> Result<Vec<AttemptRecord>, StoreError> {
        let rows: Vec<AttemptRow> = sqlx::query_as(
            "SELECT stage, attempt, started_at_ms, finished_at_ms, outcome, error_code, error_message \
             FROM attempts WHERE job_id = ? ORDER BY id",
        )
        .bind(id)
        .fetch_all(&self.reader)
        .await?;
        rows.into_iter().map(|r| r.into_record(id)).collect()
    }

    async fn get_from(&self, pool: &SqlitePool, id: &str) -> Result<Option<Job>, StoreError> {
        let sql = concat!("SELECT ", job_columns!(), " FROM jobs WHERE id = ?");
        match sqlx::query_as::<_, JobRow>(sql).bind(id).fetch_optional(pool).await? {
            Some(row) => Ok(Some(self.job_from_row(row).await?)),
            None => Ok(None),
        }
    }
}

#[async_trait::async_trait]
impl JobStore for SqliteStore {
    async fn create(&self, new: NewJob) -> Result<Created, StoreError> {
        let spec_json = encode("job spec", &new.spec)?;
        let (reply, answer) = tokio::sync::oneshot::channel();
        let pending = PendingInsert { new: new.clone(), spec_json: spec_json.clone(), reply };
        let closed = || StoreError::Db(sqlx::Error::PoolClosed);
        self.inserts.send(pending).await.map_err(|_| closed())?;
        if answer.await.map_err(|_| closed())?? {
            return Ok(Created::New(rows::inserted(new)));
        }
        // The key exists: same request -> same job; different request -> conflict.
        let key = new.idempotency_key.clone().unwrap_or_default();
        let (id, stored): (String, String) =
            sqlx::query_as("SELECT id, spec FROM jobs WHERE idempotency_key = ?")
                .bind(&key)
                .fetch_one(&self.writer)
                .await?;
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

    async fn active_jobs_of(&self, client: &str, at_most: u64) -> Result<u64, StoreError> {
        let n: i64 = sqlx::query_scalar(
            "SELECT count(*) FROM (SELECT 1 FROM jobs WHERE client = ? AND status IN ('queued', 'running') LIMIT ?)",
        )
        .bind(client)
        .bind(i64::try_from(at_most).unwrap_or(i64::MAX))
        .fetch_one(&self.reader)
        .await?;
        Ok(u64::try_from(n).unwrap_or(0))
    }

    async fn key_exists(&self, key: &str) -> Result<bool, StoreError> {
        let found: Option<i64> = sqlx::query_scalar("SELECT 1 FROM jobs WHERE idempotency_key = ?")
            .bind(key)
            .fetch_optional(&self.reader)
            .await?;
        Ok(found.is_some())
    }

    async fn list(
        &self,
        status: Option<JobStatus>,
        limit: u32,
        cursor: Option<i64>,
    ) -> Result<JobPage, StoreError> {
        let limit = i64::from(limit.clamp(1, 1000));
        let sql = concat!(
            "SELECT ",
            job_columns!(),
            " FROM jobs WHERE (?1 IS NULL OR status = ?1) AND (?2 IS NULL OR seq < ?2) \
             ORDER BY seq DESC LIMIT ?3"
        );
        let rows: Vec<JobRow> = sqlx::query_as(sql)
            .bind(status.map(|s| s.as_str()))
            .bind(cursor)
            .bind(limit + 1)
            .fetch_all(&self.reader)
            .await?;
        let more = rows.len() as i64 > limit;
        let mut jobs = Vec::with_capacity(rows.len());
        let mut last_seq = None;
        for row in rows.into_iter().take(limit as usize) {
            last_seq = Some(row.seq);
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
        let row: Option<ClaimRow> = sqlx::query_as(
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
        row.map(ClaimRow::into_claimed).transpose()
    }

    async fn renew(
        &self,
        id: &str,
        owner: &str,
        now_ms: i64,
        lease_ms: i64,
    ) -> Result<LeaseState, StoreError> {
        let row: Option<(bool,)> = sqlx::query_as(
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
            Some((cancel_requested,)) => LeaseState { held: true, cancel_requested },
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
        let (attempt,): (i64,) = sqlx::query_as(
            "INSERT INTO attempts (job_id, stage, attempt, owner, started_at_ms, outcome) \
             VALUES (?1, ?2, (SELECT COALESCE(MAX(attempt), 0) + 1 FROM attempts WHERE job_id = ?1 AND stage = ?2), \
                     ?3, ?4, 'running') RETURNING attempt",
        )
        .bind(id)
        .bind(stage.as_str())
        .bind(owner)
        .bind(now_ms)
        .fetch_one(&mut *tx)
        .await?;
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
        // The owner's running attempt of the stage is recorded as ok in the same transaction: a
        // stop between the two would leave an ok attempt of a stage that is run again.
        sqlx::query(
            "UPDATE attempts SET outcome = 'ok', finished_at_ms = ?3 \
             WHERE job_id = ?1 AND stage = ?2 AND owner = ?4 AND outcome = 'running'",
        )
        .bind(id)
        .bind(result.stage.as_str())
        .bind(now_ms)
        .bind(owner)
        .execute(&mut *tx)
        .await?;
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
        let rows: Vec<ResultRow> = sqlx::query_as(
            "SELECT stage, outputs, started_at_ms, finished_at_ms FROM stage_results WHERE job_id = ?",
        )
        .bind(id)
        .fetch_all(&self.reader)
        .await?;
        rows::results(id, rows)
    }

    async fn ping(&self) -> Result<(), StoreError> {
        sqlx::query("SELECT 1").execute(&self.reader).await?;
        Ok(())
    }

    async fn create_token(&self, token: &TokenRecord, secret_sha256: &str) -> Result<(), StoreError> {
        sqlx::query(
            "INSERT INTO api_tokens (id, name, secret_sha256, scopes, created_at_ms, expires_at_ms) \
             VALUES (?, ?, ?, ?, ?, ?)",
        )
        .bind(&token.id)
        .bind(&token.name)
        .bind(secret_sha256)
        .bind(&token.scopes)
        .bind(token.created_at_ms)
        .bind(token.expires_at_ms)
        .execute(&self.writer)
        .await?;
        Ok(())
    }

    async fn token_by_secret(&self, secret_sha256: &str) -> Result<Option<TokenRecord>, StoreError> {
        let sql = concat!("SELECT ", super::token_columns!(), " FROM api_tokens WHERE secret_sha256 = ?");
        Ok(sqlx::query_as(sql).bind(secret_sha256).fetch_optional(&self.reader).await?)
    }

    async fn list_tokens(&self) -> Result<Vec<TokenRecord>, StoreError> {
        let sql = concat!("SELECT ", super::token_columns!(), " FROM api_tokens ORDER BY created_at_ms, id");
        Ok(sqlx::query_as(sql).fetch_all(&self.reader).await?)
    }

    async fn revoke_token(&self, id: &str, now_ms: i64) -> Result<bool, StoreError> {
        let revoked =
            sqlx::query("UPDATE api_tokens SET revoked_at_ms = ?2 WHERE id = ?1 AND revoked_at_ms IS NULL")
                .bind(id)
                .bind(now_ms)
                .execute(&self.writer)
                .await?
                .rows_affected();
        Ok(revoked == 1)
    }

    async fn create_calibration(&self, rec: &CalibrationRecord) -> Result<CalibrationRecord, StoreError> {
        let sql = concat!(
            "INSERT INTO calibrations (id, version, created_at_ms, trigger_kind, calibration_json, report_json) \
             SELECT ?1, COALESCE(MAX(version), 0) + 1, ?2, ?3, ?4, ?5 FROM calibrations \
             RETURNING ",
            super::calibration_columns!()
        );
        Ok(sqlx::query_as(sql)
            .bind(&rec.id)
            .bind(rec.created_at_ms)
            .bind(&rec.trigger_kind)
            .bind(&rec.calibration_json)
            .bind(&rec.report_json)
            .fetch_one(&self.writer)
            .await?)
    }

    async fn get_calibration(&self, id: &str) -> Result<Option<CalibrationRecord>, StoreError> {
        let sql = concat!("SELECT ", super::calibration_columns!(), " FROM calibrations WHERE id = ?1");
        Ok(sqlx::query_as(sql).bind(id).fetch_optional(&self.reader).await?)
    }

    async fn latest_calibration(&self) -> Result<Option<CalibrationRecord>, StoreError> {
        let sql = concat!(
            "SELECT ",
            super::calibration_columns!(),
            " FROM calibrations ORDER BY version DESC LIMIT 1"
        );
        Ok(sqlx::query_as(sql).fetch_optional(&self.writer).await?)
    }

    async fn list_calibrations(&self, limit: u32) -> Result<Vec<CalibrationRecord>, StoreError> {
        let sql = concat!(
            "SELECT ",
            super::calibration_columns!(),
            " FROM calibrations ORDER BY version DESC LIMIT ?1"
        );
        Ok(sqlx::query_as(sql).bind(i64::from(limit)).fetch_all(&self.reader).await?)
    }
}
