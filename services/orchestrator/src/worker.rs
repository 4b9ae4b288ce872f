//! The worker: claims runnable jobs and advances them stage by stage.
//!
//! Per stage: record an attempt, call the stage's service (deadline), record the outcome; on a
//! transient error (UNAVAILABLE, DEADLINE_EXCEEDED) back off exponentially and try again, up to a
//! limit; on any other error fail the job. A completed stage's result and the move to the next
//! stage are one transaction, so after a crash the job resumes at the first stage without a
//! result, and no stage is recorded twice. While a stage runs the worker renews its lease, and a
//! cancel request (local, or seen in the database) is passed on to the service; the job then ends
//! as cancelled at that stage boundary.

use std::sync::Arc;
use std::time::Duration;

use backon::BackoffBuilder as _;
use depthmill_common::ErrorChain;
use depthmill_proto::ErrorCode;
use serde::Deserialize;
use tokio_util::sync::CancellationToken;

use crate::app::{App, now_ms};
use crate::domain::job::overall_progress;
use crate::domain::{AttemptOutcome, JobError, JobStatus, Stage, StageOutputs, StageResult};
use crate::stages::{StageCall, StageError, StageRunner};
use crate::store::{ClaimedJob, StoreError};

/// Worker settings (`[worker]` in the orchestrator's config).
#[derive(Debug, Clone, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct WorkerConfig {
    /// Jobs run at once by this process.
    pub concurrency: usize,
    /// Lease on a running job; another orchestrator may take the job over after it expires.
    pub lease_s: f64,
    /// How often idle workers look for work that no local event announced.
    pub poll_ms: u64,
    /// Attempts per stage, the first included, for transient errors.
    pub max_attempts: u32,
    pub backoff_min_ms: u64,
    pub backoff_max_ms: u64,
    /// Deadline of one stage call.
    pub stage_deadline_s: f64,
    /// After a cancel request, how long the service gets to stop before the job is marked cancelled.
    pub cancel_grace_s: f64,
}

impl Default for WorkerConfig {
    fn default() -> Self {
        Self {
            concurrency: 4,
            lease_s: 30.0,
            poll_ms: 1000,
            max_attempts: 5,
            backoff_min_ms: 200,
            backoff_max_ms: 10_000,
            stage_deadline_s: 3600.0,
            cancel_grace_s: 10.0,
        }
    }
}

fn secs(s: f64) -> Duration {
    Duration::try_from_secs_f64(s.max(0.001)).unwrap_or(Duration::from_secs(3600))
}

/// Runs jobs with a [`StageRunner`].
pub struct Worker {
    app: App,
    stages: Arc<dyn StageRunner>,
    cfg: WorkerConfig,
    /// This process's identity in leases; stable across restarts of the same data directory.
    owner: String,
}

enum Ended {
    /// The job reached a terminal state (or another worker owns it now).
    Done,
    /// This process is shutting down; the job stays leased and resumes after restart.
    Shutdown,
}

impl Worker {
    pub fn new(app: App, stages: Arc<dyn StageRunner>, cfg: WorkerConfig, owner: String) -> Self {
        Self { app, stages, cfg, owner }
    }

    fn lease_ms(&self) -> i64 {
        (self.cfg.lease_s * 1000.0) as i64
    }

    /// Recovers this owner's interrupted jobs, then runs `concurrency` worker loops until `shutdown`.
    pub async fn run(self: Arc<Self>, shutdown: CancellationToken) -> Result<(), StoreError> {
        let released = self.app.store.recover_owner(&self.owner, now_ms()).await?;
        if released > 0 {
            tracing::info!(released, owner = %self.owner, "resuming jobs interrupted by a restart");
        }
        let mut tasks = tokio::task::JoinSet::new();
        for n in 0..self.cfg.concurrency.max(1) {
            let me = self.clone();
            let shutdown = shutdown.clone();
            tasks.spawn(async move { me.worker_loop(n, shutdown).await });
        }
        while tasks.join_next().await.is_some() {}
        Ok(())
    }

    async fn worker_loop(&self, n: usize, shutdown: CancellationToken) {
        let poll = Duration::from_millis(self.cfg.poll_ms.max(10));
        while !shutdown.is_cancelled() {
            match self.app.store.claim(&self.owner, now_ms(), self.lease_ms()).await {
                Ok(Some(job)) => {
                    // More work may be waiting: let another idle worker look too.
                    self.app.events.work_available();
                    let id = job.id.clone();
                    if let Ended::Shutdown = self.run_job(job, &shutdown).await {
                        tracing::info!(job_id = %id, "left job for the next start");
                        return;
                    }
                }
                Ok(None) => {
                    tokio::select! {
                        () = shutdown.cancelled() => return,
                        () = self.app.events.wait_for_work() => {}
                        () = tokio::time::sleep(poll) => {}
                    }
                }
                Err(e) => {
                    tracing::error!(worker = n, error = %ErrorChain(&e), "claiming a job failed");
                    tokio::select! {
                        () = shutdown.cancelled() => return,
                        () = tokio::time::sleep(poll) => {}
                    }
                }
            }
        }
    }

    async fn run_job(&self, job: ClaimedJob, shutdown: &CancellationToken) -> Ended {
        let id = job.id.clone();
        match self.advance(job, shutdown).await {
            Ok(ended) => ended,
            Err(StoreError::LeaseLost { .. }) => {
                tracing::warn!(job_id = %id, "lost the job's lease; another worker has it");
                Ended::Done
            }
            Err(e) => {
                // The store failed: leave the job leased; it is retried when the lease expires.
                tracing::error!(job_id = %id, error = %ErrorChain(&e), "job store failed while running a job");
                Ended::Done
            }
        }
    }

    async fn end(&self, id: &str, status: JobStatus, error: Option<JobError>) -> Result<Ended, StoreError> {
        self.app.store.end(id, &self.owner, status, error.as_ref(), now_ms()).await?;
        metrics::counter!("depthmill_jobs_finished_total", "status" => status.as_str()).increment(1);
        match &error {
            Some(e) => tracing::info!(job_id = %id, %status, code = %e.code, error = %e.message, "job ended"),
            None => tracing::info!(job_id = %id, %status, "job ended"),
        }
        self.app.events.job_changed(id);
        Ok(Ended::Done)
    }

    async fn advance(&self, job: ClaimedJob, shutdown: &CancellationToken) -> Result<Ended, StoreError> {
        let id = job.id.as_str();
        let guard = self.app.running.start(id);
        let cancel = guard.token().clone();
        if job.cancel_requested {
            cancel.cancel();
        }
        let first = job.spec.first_stage();
        let mut stage = job.stage;
        loop {
            let lease = self.app.store.renew(id, &self.owner, now_ms(), self.lease_ms()).await?;
            if !lease.held {
                return Err(StoreError::LeaseLost { id: id.to_string() });
            }
            if lease.cancel_requested || cancel.is_cancelled() {
                let error = JobError {
                    code: ErrorCode::Cancelled.as_str().into(),
                    message: format!("cancelled on request before the {stage} stage"),
                    stage,
                };
                return self.end(id, JobStatus::Cancelled, Some(error)).await;
            }
            let results = self.app.store.stage_results(id).await?;
            let mut artifacts = std::collections::BTreeMap::new();
            if let Ok(Some(input)) = self.app.artifacts.stat(&job.spec.input.artifact).await {
                artifacts.insert(job.spec.input.kind.as_str().to_string(), input);
            }
            for r in &results {
                artifacts.extend(r.outputs.artifacts.clone());
            }
            // The scan stage's attempts find the cell's calibration in force first.
            let call = StageCall {
                job_id: id.to_string(),
                attempt: 0,
                stage,
                spec: job.spec.clone(),
                artifacts,
                calibration: None,
                calibrate_in_scan: false,
            };
            let started = now_ms();
            let outcome = if stage == Stage::Report {
                let attempt = self.app.store.begin_attempt(id, &self.owner, stage, started).await?;
                let r = self.report(id).await;
                let (o, err) = match &r {
                    Ok(_) => (AttemptOutcome::Ok, None),
                    Err(e) => (AttemptOutcome::Failed, Some((e.code.as_str(), e.message.as_str()))),
                };
                // An ok attempt is recorded with the stage's result (`complete_stage`).
                if o != AttemptOutcome::Ok {
                    self.app.store.finish_attempt(id, stage, attempt, o, err, now_ms()).await?;
                }
                r
            } else {
                match self.run_with_retries(call, first, &cancel, shutdown).await? {
                    Some(r) => r,
                    None => return Ok(Ended::Shutdown),
                }
            };
            match outcome {
                Ok(outputs) => {
                    let next = stage.next();
                    let result =
                        StageResult { stage, outputs, started_at_ms: started, finished_at_ms: now_ms() };
                    let progress = next.map_or(1.0, |n| overall_progress(first, n, 0.0));
                    self.app.store.complete_stage(id, &self.owner, &result, next, progress, now_ms()).await?;
                    metrics::histogram!("depthmill_stage_duration_seconds", "stage" => stage.as_str())
                        .record((result.finished_at_ms - result.started_at_ms) as f64 / 1000.0);
                    tracing::info!(job_id = %id, %stage, "stage completed");
                    self.app.events.job_changed(id);
                    match next {
                        Some(n) => stage = n,
                        None => {
                            metrics::counter!("depthmill_jobs_finished_total", "status" => "succeeded")
                                .increment(1);
                            tracing::info!(job_id = %id, "job succeeded");
                            return Ok(Ended::Done);
                        }
                    }
                }
                Err(e) if e.code == ErrorCode::Cancelled => {
                    let error = JobError { code: e.code.as_str().into(), message: e.message, stage };
                    return self.end(id, JobStatus::Cancelled, Some(error)).await;
                }
                Err(e) => {
                    let error = JobError { code: e.code.as_str().into(), message: e.message, stage };
                    return self.end(id, JobStatus::Failed, Some(error)).await;
                }
            }
        }
    }

    /// Runs one stage with retries. `Ok(None)`: shutting down mid-stage.
    async fn run_with_retries(
        &self,
        mut call: StageCall,
        first: Stage,
        cancel: &CancellationToken,
        shutdown: &CancellationToken,
    ) -> Result<Option<Result<StageOutputs, StageError>>, StoreError> {
        let id = call.job_id.clone();
        let stage = call.stage;
        let mut backoff = backon::ExponentialBuilder::default()
            .with_min_delay(Duration::from_millis(self.cfg.backoff_min_ms))
            .with_max_delay(Duration::from_millis(self.cfg.backoff_max_ms.max(self.cfg.backoff_min_ms)))
            .with_max_times(self.cfg.max_attempts.saturating_sub(1) as usize)
            .with_jitter()
            .build();
        loop {
            let attempt = self.app.store.begin_attempt(&id, &self.owner, stage, now_ms()).await?;
            call.attempt = attempt;
            self.app.events.job_changed(&id);
            // The scan places its points with the cell's calibration in force; with none yet
            // (a new cell), it calibrates the cell itself, at its own stations when it can.
            if stage == Stage::Scan && (call.calibration.is_none() || call.calibrate_in_scan) {
                call.calibration = self.app.store.latest_calibration().await?;
                call.calibrate_in_scan = call.calibration.is_none();
            }
            let result = match self.attempt(&call, first, cancel, shutdown).await? {
                Some(r) => r,
                None => return Ok(None),
            };
            // A calibration the scan made is stored as the next version, in force from now on.
            let result = match result {
                Ok(mut out) => match out.calibration_made.take() {
                    Some(made) => {
                        let stored = self
                            .app
                            .store_calibration(
                                crate::app::new_calibration_id(),
                                made.calibration_json,
                                made.report_json,
                                "scan",
                            )
                            .await?;
                        out.metrics.insert("scan_calibration_version".into(), stored.version as f64);
                        Ok(out)
                    }
                    None => Ok(out),
                },
                Err(e) => Err(e),
            };
            let (outcome, delay) = match &result {
                Ok(_) => (AttemptOutcome::Ok, None),
                Err(e) if e.code == ErrorCode::Cancelled => (AttemptOutcome::Cancelled, None),
                Err(e) if e.code.is_transient() && !cancel.is_cancelled() => match backoff.next() {
                    Some(d) => (AttemptOutcome::Retry, Some(d)),
                    None => (AttemptOutcome::Failed, None),
                },
                Err(_) => (AttemptOutcome::Failed, None),
            };
            let err = result.as_ref().err().map(|e| (e.code.as_str(), e.message.as_str()));
            // An ok attempt is recorded with the stage's result (`complete_stage`, one transaction),
            // so a stop in between runs the stage again without an ok attempt left behind.
            if outcome != AttemptOutcome::Ok {
                self.app.store.finish_attempt(&id, stage, attempt, outcome, err, now_ms()).await?;
            }
            metrics::counter!("depthmill_stage_attempts_total", "stage" => stage.as_str(), "outcome" => outcome.as_str())
                .increment(1);
            let Some(delay) = delay else {
                return Ok(Some(match result {
                    Err(e) if outcome == AttemptOutcome::Failed && e.code.is_transient() => Err(
                        StageError::new(e.code, format!("{} (gave up after {attempt} attempts)", e.message)),
                    ),
                    other => other,
                }));
            };
            if let Err(e) = &result {
                tracing::warn!(job_id = %id, %stage, attempt, error = %e.message, delay_ms = delay.as_millis() as u64, "transient stage error, retrying");
            }
            // The lease must outlast the wait.
            let wait_ms = i64::try_from(delay.as_millis()).unwrap_or(i64::MAX / 2);
            let lease = self
                .app
                .store
                .renew(&id, &self.owner, now_ms(), self.lease_ms().saturating_add(wait_ms))
                .await?;
            if !lease.held {
                return Err(StoreError::LeaseLost { id: id.clone() });
            }
            if lease.cancel_requested {
                cancel.cancel();
            }
            tokio::select! {
                () = tokio::time::sleep(delay) => {}
                () = cancel.cancelled() => {
                    return Ok(Some(Err(StageError::new(ErrorCode::Cancelled, format!("cancelled on request during the {stage} stage")))));
                }
                () = shutdown.cancelled() => return Ok(None),
            }
        }
    }

    /// One call of the stage's service, with lease renewal, progress and cancel forwarding.
    /// `Ok(None)`: shutting down.
    async fn attempt(
        &self,
        call: &StageCall,
        first: Stage,
        cancel: &CancellationToken,
        shutdown: &CancellationToken,
    ) -> Result<Option<Result<StageOutputs, StageError>>, StoreError> {
        let id = call.job_id.as_str();
        let stage = call.stage;
        let (progress_tx, mut progress_rx) = tokio::sync::watch::channel(0.0f64);
        let report = move |fraction: f64, _message: &str| {
            let _ = progress_tx.send(fraction);
        };
        // A scan that calibrates the cell has the calibration's own budget on top of the stage's.
        let mut deadline = secs(self.cfg.stage_deadline_s);
        if call.calibrate_in_scan {
            deadline += crate::app::CALIBRATION_DEADLINE;
        }
        let run = self.stages.run(call, deadline, &report);
        tokio::pin!(run);
        // The first tick is at once: the lease is renewed (and a cancel in the database seen) as
        // each attempt starts, not only a third of a lease into it (attempts cut short by a
        // deadline under that would never renew it, and another worker could claim the job).
        let mut ticker = tokio::time::interval(secs(self.cfg.lease_s / 3.0));
        let mut grace: Option<std::pin::Pin<Box<tokio::time::Sleep>>> = None;
        loop {
            tokio::select! {
                r = &mut run => {
                    if grace.is_some() {
                        // The service stopped (or finished) after being told to cancel.
                        return Ok(Some(match r {
                            Ok(outputs) => Ok(outputs),
                            Err(_) => Err(StageError::new(ErrorCode::Cancelled, format!("cancelled on request during the {stage} stage"))),
                        }));
                    }
                    return Ok(Some(r));
                }
                _ = ticker.tick() => {
                    let lease = self.app.store.renew(id, &self.owner, now_ms(), self.lease_ms()).await?;
                    if !lease.held {
                        return Err(StoreError::LeaseLost { id: id.to_string() });
                    }
                    if lease.cancel_requested {
                        cancel.cancel();
                    }
                }
                Ok(()) = progress_rx.changed() => {
                    let fraction = *progress_rx.borrow_and_update();
                    self.app.store.set_progress(id, &self.owner, overall_progress(first, stage, fraction), now_ms()).await?;
                    self.app.events.job_changed(id);
                }
                () = cancel.cancelled(), if grace.is_none() => {
                    match self.stages.cancel(stage, id).await {
                        Ok(found) => tracing::info!(job_id = %id, %stage, found, "told the service to cancel"),
                        Err(e) => tracing::warn!(job_id = %id, %stage, error = %e, "could not tell the service to cancel"),
                    }
                    grace = Some(Box::pin(tokio::time::sleep(secs(self.cfg.cancel_grace_s))));
                }
                () = async { match grace.as_mut() { Some(g) => g.await, None => std::future::pending().await } } => {
                    return Ok(Some(Err(StageError::new(
                        ErrorCode::Cancelled,
                        format!("cancelled on request during the {stage} stage (the service did not stop within the grace period)"),
                    ))));
                }
                () = shutdown.cancelled() => return Ok(None),
            }
        }
    }

    /// The report stage: the HTML report (`report`, see [`depthmill_report`]) and a JSON summary of
    /// the job (`report_json`: parameters, timings, artifacts, metrics, attempts).
    async fn report(&self, id: &str) -> Result<StageOutputs, StageError> {
        let internal = |what: &str, e: &dyn std::fmt::Display| {
            StageError::new(ErrorCode::Internal, format!("writing the report failed: {what}: {e}"))
        };
        let job = self.app.get_job(id).await.map_err(|e| internal("reading the job", &e.message))?;
        let html = self.app.render_report(id).await.map_err(|e| internal("rendering", &e.message))?;
        let summary = serde_json::json!({
            "job": job.id,
            "name": job.name,
            "spec": job.spec,
            "stage_timings_s": job.stage_timings_s,
            "artifacts": job.artifacts,
            "metrics": job.metrics,
            "attempts": job.attempts,
            "figures": html.figures,
        });
        let bytes = serde_json::to_vec_pretty(&summary).map_err(|e| internal("encoding", &e))?;
        let json_ref = self
            .app
            .artifacts
            .put_bytes("application/json", &bytes)
            .await
            .map_err(|e| internal("storing", &e))?;
        let aref = self
            .app
            .artifacts
            .put_bytes("text/html", html.html.as_bytes())
            .await
            .map_err(|e| internal("storing", &e))?;
        let mut out = StageOutputs::default();
        // The report's own measurements become job metrics (`part_rms_mm`, ...).
        out.metrics.extend(html.figures);
        out.artifacts.insert("report".into(), aref);
        out.artifacts.insert("report_json".into(), json_ref);
        Ok(out)
    }
}
