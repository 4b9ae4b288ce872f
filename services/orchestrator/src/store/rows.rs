//! Rows as both backends return them, and their conversion into the job model: one place that
//! knows how a stored job reads, whichever database holds it.

use std::collections::BTreeMap;
use std::str::FromStr;

use super::{ClaimedJob, NewJob, StoreError};
use crate::domain::{
    AttemptOutcome, AttemptRecord, Job, JobDiagnostic, JobError, JobMetrics, JobSpec, JobStatus, Stage,
    StageOutputs, StageResult,
};

/// The columns of `jobs` a job is read from ([`job_columns!`]).
#[derive(sqlx::FromRow)]
pub(super) struct JobRow {
    pub id: String,
    pub name: String,
    pub spec: String,
    pub status: String,
    pub stage: String,
    pub progress: f64,
    pub error_code: Option<String>,
    pub error_message: Option<String>,
    pub error_stage: Option<String>,
    pub cancel_requested: bool,
    pub created_at_ms: i64,
    pub updated_at_ms: i64,
    pub seq: i64,
}

/// The column list matching [`JobRow`], as a literal for `concat!` (sqlx takes static SQL only).
macro_rules! job_columns {
    () => {
        "id, name, spec, status, stage, progress, error_code, error_message, error_stage, \
         cancel_requested, created_at_ms, updated_at_ms, seq"
    };
}
pub(super) use job_columns;

#[derive(sqlx::FromRow)]
pub(super) struct AttemptRow {
    pub stage: String,
    pub attempt: i64,
    pub started_at_ms: i64,
    pub finished_at_ms: Option<i64>,
    pub outcome: String,
    pub error_code: Option<String>,
    pub error_message: Option<String>,
}

#[derive(sqlx::FromRow)]
pub(super) struct ResultRow {
    pub stage: String,
    pub outputs: String,
    pub started_at_ms: i64,
    pub finished_at_ms: i64,
}

#[derive(sqlx::FromRow)]
pub(super) struct ClaimRow {
    pub id: String,
    pub spec: String,
    pub stage: String,
    pub cancel_requested: bool,
}

fn corrupt(id: &str, what: &'static str, detail: impl Into<String>) -> StoreError {
    StoreError::Corrupt { id: id.to_string(), what, detail: detail.into() }
}

pub(super) fn encode<T: serde::Serialize>(what: &'static str, v: &T) -> Result<String, StoreError> {
    serde_json::to_string(v).map_err(|source| StoreError::Encode { what, source })
}

fn spec(id: &str, json: &str) -> Result<JobSpec, StoreError> {
    serde_json::from_str(json).map_err(|e| corrupt(id, "spec", e.to_string()))
}

fn stage(id: &str, what: &'static str, s: &str) -> Result<Stage, StoreError> {
    Stage::from_str(s).map_err(|e| corrupt(id, what, e))
}

impl AttemptRow {
    pub fn into_record(self, id: &str) -> Result<AttemptRecord, StoreError> {
        Ok(AttemptRecord {
            stage: stage(id, "attempt", &self.stage)?,
            attempt: u32::try_from(self.attempt).unwrap_or(0),
            started_at_ms: self.started_at_ms,
            finished_at_ms: self.finished_at_ms,
            outcome: AttemptOutcome::from_str(&self.outcome).map_err(|e| corrupt(id, "attempt", e))?,
            error_code: self.error_code,
            error_message: self.error_message,
        })
    }
}

impl ResultRow {
    pub fn into_result(self, id: &str) -> Result<StageResult, StoreError> {
        let outputs: StageOutputs =
            serde_json::from_str(&self.outputs).map_err(|e| corrupt(id, "stage result", e.to_string()))?;
        Ok(StageResult {
            stage: stage(id, "stage result", &self.stage)?,
            outputs,
            started_at_ms: self.started_at_ms,
            finished_at_ms: self.finished_at_ms,
        })
    }
}

/// Stage results in stage order.
pub(super) fn results(id: &str, rows: Vec<ResultRow>) -> Result<Vec<StageResult>, StoreError> {
    let mut out = rows.into_iter().map(|r| r.into_result(id)).collect::<Result<Vec<_>, _>>()?;
    out.sort_by_key(|r| r.stage);
    Ok(out)
}

impl ClaimRow {
    pub fn into_claimed(self) -> Result<ClaimedJob, StoreError> {
        Ok(ClaimedJob {
            spec: spec(&self.id, &self.spec)?,
            stage: stage(&self.id, "stage", &self.stage)?,
            cancel_requested: self.cancel_requested,
            id: self.id,
        })
    }
}

impl JobRow {
    /// The job, with its stage results and attempts (read by the caller from the same database).
    pub fn into_job(
        self,
        mut results: Vec<StageResult>,
        attempts: Vec<AttemptRecord>,
    ) -> Result<Job, StoreError> {
        let id = self.id;
        let spec = spec(&id, &self.spec)?;
        let status = JobStatus::from_str(&self.status).map_err(|e| corrupt(&id, "status", e))?;
        let current = stage(&id, "stage", &self.stage)?;
        let error = match self.error_code {
            Some(code) => Some(JobError {
                code,
                message: self.error_message.unwrap_or_default(),
                stage: match self.error_stage {
                    Some(s) => stage(&id, "error stage", &s)?,
                    None => current,
                },
            }),
            None => None,
        };
        // The input's reference is added by the application layer, which knows the artifact store.
        let mut artifacts = BTreeMap::new();
        let mut stage_timings_s = BTreeMap::new();
        let mut metrics = JobMetrics::default();
        let mut diagnostics = Vec::new();
        results.sort_by_key(|r| r.stage);
        for r in &results {
            stage_timings_s
                .insert(r.stage.as_str().to_string(), (r.finished_at_ms - r.started_at_ms) as f64 / 1000.0);
            artifacts.extend(r.outputs.artifacts.clone());
            metrics.absorb(&r.outputs.metrics);
            diagnostics.extend(r.outputs.diagnostics.iter().map(|d| JobDiagnostic {
                stage: r.stage,
                code: d.code.clone(),
                message: d.message.clone(),
            }));
        }
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
            name: self.name,
            status,
            stage: current,
            progress: self.progress,
            error,
            stage_timings_s,
            artifacts,
            metrics,
            diagnostics,
            spec,
            cancel_requested: self.cancel_requested,
            created_at_ms: self.created_at_ms,
            updated_at_ms: self.updated_at_ms,
            attempts,
            id,
        })
    }
}

/// The job a successful insert of `new` made: everything about it is known, no need to read it back.
pub(super) fn inserted(new: NewJob) -> Job {
    Job {
        id: new.id,
        name: new.spec.name.clone(),
        status: JobStatus::Queued,
        stage: new.spec.first_stage(),
        progress: 0.0,
        error: None,
        stage_timings_s: BTreeMap::new(),
        artifacts: BTreeMap::new(),
        metrics: JobMetrics::default(),
        diagnostics: Vec::new(),
        spec: new.spec,
        cancel_requested: false,
        created_at_ms: new.now_ms,
        updated_at_ms: new.now_ms,
        attempts: Vec::new(),
    }
}
