//! The application handle both APIs (REST and gRPC) call: job submission, queries, cancel, watch,
//! artifact upload and download. Validation happens here, once, for both.

use std::sync::Arc;
use std::time::Duration;

use depthmill_common::artifacts::{ArtifactError, ArtifactStore, BlobReader};
use depthmill_geometry::ArtifactRef;
use depthmill_proto::ErrorCode;
use tokio::io::AsyncRead;
use tokio::sync::mpsc;

use crate::domain::spec::InputUnits;
use crate::domain::{Job, JobSpec, JobStatus, SpecError};
use depthmill_geometry::{LengthUnit, Units};

/// Largest artifact read into a report (a cloud of about 20 million points).
pub const REPORT_ARTIFACT_LIMIT: u64 = 512 << 20;
use crate::events::EventHub;
use crate::store::{Created, JobPage, JobStore, NewJob, StoreError};

/// An error as clients see it: a kind, a message, and the offending field when there is one.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{message}")]
pub struct ApiError {
    pub code: ErrorCode,
    pub message: String,
    pub field: Option<String>,
}

/// A new calibration's id.
pub fn new_calibration_id() -> String {
    format!("cal_{}", uuid::Uuid::now_v7().simple())
}

/// Longest a calibration routine may take (table turns in real time, scans, fit).
pub const CALIBRATION_DEADLINE: std::time::Duration = std::time::Duration::from_secs(600);

impl ApiError {
    pub fn new(code: ErrorCode, message: impl Into<String>) -> Self {
        Self { code, message: message.into(), field: None }
    }

    pub fn field(code: ErrorCode, field: impl Into<String>, message: impl Into<String>) -> Self {
        Self { code, message: message.into(), field: Some(field.into()) }
    }
}

impl From<SpecError> for ApiError {
    fn from(e: SpecError) -> Self {
        ApiError::field(ErrorCode::InvalidArgument, e.field.clone(), e.to_string())
    }
}

impl From<StoreError> for ApiError {
    fn from(e: StoreError) -> Self {
        match e {
            StoreError::IdempotencyConflict { .. } => {
                ApiError::field(ErrorCode::Conflict, "Idempotency-Key", e.to_string())
            }
            ref unavailable if unavailable.is_unavailable() => {
                tracing::warn!(error = %depthmill_common::ErrorChain(unavailable), "job store unavailable");
                ApiError::new(
                    ErrorCode::Unavailable,
                    "the job database cannot be reached or is busy; nothing was changed, retry later",
                )
            }
            other => {
                tracing::error!(error = %depthmill_common::ErrorChain(&other), "job store failed");
                ApiError::new(ErrorCode::Internal, "the job store failed; see the server log")
            }
        }
    }
}

impl From<ArtifactError> for ApiError {
    fn from(e: ArtifactError) -> Self {
        let code = match &e {
            ArtifactError::NotFound { .. } => ErrorCode::NotFound,
            ArtifactError::BadDigest { .. } | ArtifactError::Empty | ArtifactError::Upload(_) => {
                ErrorCode::InvalidArgument
            }
            ArtifactError::TooLarge { .. } => ErrorCode::PayloadTooLarge,
            ArtifactError::UnsupportedMediaType { .. } | ArtifactError::ContentMismatch { .. } => {
                ErrorCode::UnsupportedMediaType
            }
            full if full.is_out_of_space() => {
                tracing::error!(error = %depthmill_common::ErrorChain(full), "artifact store out of space");
                return ApiError::new(
                    ErrorCode::Unavailable,
                    "the artifact store is out of space; nothing was stored, retry once space is freed",
                );
            }
            down if down.is_unavailable() => {
                tracing::error!(error = %depthmill_common::ErrorChain(down), "artifact store unavailable");
                return ApiError::new(
                    ErrorCode::Unavailable,
                    "the artifact store does not answer; nothing was stored, retry later",
                );
            }
            ArtifactError::Io { .. }
            | ArtifactError::Metadata { .. }
            | ArtifactError::Store { .. }
            | ArtifactError::Config { .. }
            | ArtifactError::Corrupt { .. } => {
                tracing::error!(error = %depthmill_common::ErrorChain(&e), "artifact store failed");
                return ApiError::new(ErrorCode::Internal, "the artifact store failed; see the server log");
            }
        };
        ApiError::new(code, e.to_string())
    }
}

/// Limits and defaults of the API.
#[derive(Debug, Clone)]
pub struct ApiLimits {
    /// Largest artifact upload, bytes.
    pub max_upload_bytes: u64,
    /// Most jobs one client may have queued or running; 0: no limit.
    pub max_active_jobs_per_client: u32,
    /// Page size when the client gives none.
    pub default_page: u32,
    /// Largest page.
    pub max_page: u32,
}

/// Shared state of the orchestrator's APIs.
#[derive(Clone)]
pub struct App {
    pub(crate) store: Arc<dyn JobStore>,
    pub(crate) artifacts: Arc<dyn ArtifactStore>,
    pub(crate) events: Arc<EventHub>,
    pub(crate) limits: ApiLimits,
    /// Local cancel signals for jobs this process runs.
    pub(crate) running: depthmill_common::stage::StageRegistry,
    /// The stage services, asked to check the sections they own before a job is accepted.
    pub(crate) stages: Arc<dyn crate::stages::StageRunner>,
    /// Checks the API token of each call (when tokens are required).
    pub(crate) auth: Arc<crate::auth::Authenticator>,
    /// Submissions being inserted, by client: counted with the client's stored active jobs so
    /// that concurrent ones cannot all pass the limit together.
    pub(crate) in_flight: Arc<InFlight>,
}

/// Submissions of each client between their limit check and their insert (entries of clients
/// with none are removed, so the map holds at most the submissions in progress).
#[derive(Default)]
pub struct InFlight(std::sync::Mutex<std::collections::HashMap<String, u64>>);

/// One submission counted in [`InFlight`] until dropped.
struct InFlightGuard<'a> {
    map: &'a InFlight,
    client: String,
}

impl InFlight {
    /// Counts a submission of `client`; the number of its other submissions in flight.
    fn enter(&self, client: &str) -> (InFlightGuard<'_>, u64) {
        let before = match self.0.lock() {
            Ok(mut map) => {
                let n = map.entry(client.to_string()).or_insert(0);
                *n += 1;
                *n - 1
            }
            Err(_) => 0,
        };
        (InFlightGuard { map: self, client: client.to_string() }, before)
    }
}

impl Drop for InFlightGuard<'_> {
    fn drop(&mut self) {
        if let Ok(mut map) = self.map.0.lock()
            && let Some(n) = map.get_mut(&self.client)
        {
            *n -= 1;
            if *n == 0 {
                map.remove(&self.client);
            }
        }
    }
}

/// Milliseconds since the Unix epoch: the clock of every stored time.
pub fn now_ms() -> i64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| i64::try_from(d.as_millis()).unwrap_or(i64::MAX))
        .unwrap_or(0)
}

impl App {
    /// Validates and submits a job for `client` (`token:<id>` or `addr:<ip>`, see
    /// [`crate::auth::Client`]; `None`: not counted). Returns the job and whether it is new
    /// (false: the idempotency key was used before for the same request).
    pub async fn create_job(
        &self,
        spec: JobSpec,
        idempotency_key: Option<String>,
        client: Option<&crate::auth::Client>,
    ) -> Result<(Job, bool), ApiError> {
        spec.validate()?;
        // The sections a stage service owns, checked by that service, before anything else about
        // the request, as if the job model knew them.
        self.stages.check_params(&spec).await?;
        if let Some(k) = &idempotency_key
            && (k.is_empty() || k.len() > 256)
        {
            return Err(ApiError::field(
                ErrorCode::InvalidArgument,
                "Idempotency-Key",
                format!("must be 1 to 256 characters, got {}", k.len()),
            ));
        }
        let input = self.artifacts.stat(&spec.input.artifact).await?.ok_or_else(|| {
            ApiError::field(
                ErrorCode::InvalidArgument,
                "input.artifact",
                format!(
                    "artifact {} not found: upload it with POST /v1/artifacts first",
                    spec.input.artifact
                ),
            )
        })?;
        let kind = spec.input.kind;
        if !kind.media_types().contains(&input.media_type.as_str()) {
            return Err(ApiError::field(
                ErrorCode::InvalidArgument,
                "input.kind",
                format!(
                    "input kind {} needs an artifact of type {}, artifact {} is {}",
                    kind.as_str(),
                    kind.media_types().join(" or "),
                    input.sha256,
                    input.media_type
                ),
            ));
        }
        // A mesh is read now: a file that cannot be read or a part the machine cannot hold is
        // refused before the job exists (a robot job's reach is the CAM's to check: the arm's
        // work space is not the mill's travel).
        if let Some(size) = self.part_size_mm(&spec).await?
            && !spec.is_robot()
        {
            self.stages.check_part(&spec, size).await?;
        }
        let limit = self.limits.max_active_jobs_per_client;
        let client = client.map(|c| c.0.as_str());
        // Held until the job is inserted (or refused). Counted before the stored jobs are, so
        // that a concurrent submission is seen either in flight or stored (at worst both, which
        // refuses at the edge rather than passing the limit).
        let _in_flight = match client {
            Some(client) if limit > 0 => {
                let (guard, others) = self.in_flight.enter(client);
                let active = self.store.active_jobs_of(client, u64::from(limit)).await? + others;
                // A repeat of an accepted submission (same idempotency key) is answered as before.
                let repeat = match &idempotency_key {
                    Some(key) if active >= u64::from(limit) => self.store.key_exists(key).await?,
                    _ => false,
                };
                if active >= u64::from(limit) && !repeat {
                    metrics::counter!("depthmill_jobs_refused_quota_total").increment(1);
                    return Err(ApiError::new(
                        ErrorCode::QuotaExceeded,
                        format!(
                            "client {client} has {active} jobs queued or running, the limit is {limit} \
                             (orchestrator max_active_jobs_per_client); submit again when one ends"
                        ),
                    ));
                }
                Some(guard)
            }
            _ => None,
        };
        let new = NewJob {
            id: uuid::Uuid::now_v7().to_string(),
            spec,
            idempotency_key,
            client: client.map(str::to_string),
            now_ms: now_ms(),
        };
        let created = self.store.create(new).await?;
        let (mut job, is_new) = match created {
            Created::New(job) => (job, true),
            Created::Existing(job) => (job, false),
        };
        job.artifacts.entry(kind.as_str().to_string()).or_insert(input);
        if is_new {
            metrics::counter!("depthmill_jobs_created_total").increment(1);
            self.events.job_changed(&job.id);
            self.events.work_available();
        }
        Ok((job, is_new))
    }

    /// The size of a mesh input in millimetres (its units decided as the scan will), as the
    /// machine sees it: as it lies for a job with one `+Z` face, its bounding cylinder about X
    /// (length, diameter, diameter) when the job turns the A axis. `None` for other inputs. A mesh
    /// that cannot be read is refused here, naming the file's problem.
    async fn part_size_mm(&self, spec: &JobSpec) -> Result<Option<[f64; 3]>, ApiError> {
        if spec.input.kind != crate::domain::spec::InputKind::Mesh {
            return Ok(None);
        }
        let path = self.artifacts.local_file(&spec.input.artifact).await?;
        let units = match spec.input.units {
            None | Some(InputUnits::Auto) => Units::Auto,
            Some(InputUnits::Mm) => Units::Given(LengthUnit::Millimetre),
            Some(InputUnits::M) => Units::Given(LengthUnit::Metre),
            Some(InputUnits::In) => Units::Given(LengthUnit::Inch),
        };
        let name = format!("mesh {}", &spec.input.artifact[..12.min(spec.input.artifact.len())]);
        let read = tokio::task::spawn_blocking(move || {
            use depthmill_geometry::formats::{ReadLimits, read_any_from};
            let file = std::fs::File::open(&path).map_err(|e| format!("{name}: cannot open: {e}"))?;
            let size = file.metadata().ok().map(|m| m.len());
            let (mut geometry, stats) = read_any_from(
                std::io::BufReader::with_capacity(1 << 20, file),
                &name,
                size,
                &ReadLimits::default(),
            )
            .map_err(|e| e.to_string())?;
            let head = depthmill_geometry::units::read_head(&path).map_err(|e| format!("{name}: {e}"))?;
            depthmill_geometry::units::normalise(&mut geometry, &head, units);
            let bounds = match &geometry {
                depthmill_geometry::formats::Geometry::Mesh(m) => m.bounds(),
                depthmill_geometry::formats::Geometry::Cloud(_) => {
                    return Err(format!(
                        "{name}: is a point cloud without faces; submit it as kind point_cloud"
                    ));
                }
            };
            bounds.map(|b| b.extent()).ok_or_else(|| match stats.dropped_triangles {
                0 => format!("{name}: has no triangles"),
                n => format!(
                    "{name}: has no usable triangles: all {n} are degenerate (zero area) or have a NaN or infinite corner"
                ),
            })
        })
        .await
        .map_err(|e| ApiError::new(ErrorCode::Internal, format!("reading the mesh failed: {e}")))?;
        let e = read.map_err(|m| ApiError::field(ErrorCode::InvalidArgument, "input.artifact", m))?;
        // Faces other than +Z turn the part about the A (X) axis. Faces still to be chosen are
        // checked as the part stands (it must at least fit that way); a chosen turn that leaves
        // the travel is refused by the machine before any motion, with the line.
        let turns = spec.reconstruct.as_ref().and_then(|r| r.faces.as_ref()).is_some_and(|f| {
            f.iter().any(|f| {
                f.a_deg.is_some() || f.normal.is_some() || f.view.as_deref().is_some_and(|v| v != "+Z")
            })
        });
        Ok(Some(if turns {
            let d = e.y.hypot(e.z);
            [e.x, d, d]
        } else {
            [e.x, e.y, e.z]
        }))
    }

    /// Adds the input artifact's reference to a job's artifacts.
    async fn with_input(&self, mut job: Job) -> Job {
        if let Ok(Some(input)) = self.artifacts.stat(&job.spec.input.artifact).await {
            job.artifacts.entry(job.spec.input.kind.as_str().to_string()).or_insert(input);
        }
        job
    }

    /// The job's HTML report as it stands now (any status), rendered by
    /// [`depthmill_report::render`] on a blocking thread. The artifacts that grow with the job
    /// (the scanned cloud, the program) are streamed from the store into bounded digests
    /// ([`depthmill_report::digest`]), so memory stays flat in their size; the others (maps,
    /// JSON reports, the mesh) are read whole, up to [`REPORT_ARTIFACT_LIMIT`] each. An artifact
    /// that cannot be read is left out, and its section says so.
    pub async fn render_report(&self, id: &str) -> Result<depthmill_report::ReportOutput, ApiError> {
        use depthmill_report::digest::{self, Reading};
        let job = self.get_job(id).await?;
        let mut artifacts = std::collections::BTreeMap::new();
        let mut digests = digest::Digests::default();
        for (name, aref) in &job.artifacts {
            let reading = digest::reading(name);
            let read = match reading {
                Reading::Unused => continue,
                Reading::Bytes => self
                    .artifacts
                    .read_all(&aref.sha256, REPORT_ARTIFACT_LIMIT)
                    .await
                    .map(|bytes| {
                        artifacts.insert(name.clone(), bytes);
                    })
                    .map_err(|e| e.to_string()),
                Reading::Cloud | Reading::Program | Reading::Telemetry => {
                    enum Streamed {
                        Cloud(digest::SampledCloud),
                        Program(depthmill_report::Program),
                        Telemetry(Box<depthmill_report::charts::Telemetry>),
                    }
                    match self.artifacts.open(&aref.sha256).await {
                        Err(e) => Err(e.to_string()),
                        Ok((stored, reader)) => {
                            let label = name.clone();
                            let streamed = tokio::task::spawn_blocking(move || {
                                let bridge = tokio_util::io::SyncIoBridge::new(reader);
                                let r = std::io::BufReader::with_capacity(1 << 20, bridge);
                                match reading {
                                    Reading::Cloud => {
                                        digest::cloud(r, &label, Some(stored.size)).map(Streamed::Cloud)
                                    }
                                    Reading::Program => {
                                        digest::program(r).map(Streamed::Program).map_err(|e| e.to_string())
                                    }
                                    _ => digest::telemetry(r).map(|t| Streamed::Telemetry(Box::new(t))),
                                }
                            })
                            .await
                            .map_err(|e| format!("reading failed: {e}"))
                            .and_then(|r| r);
                            streamed.map(|s| match s {
                                Streamed::Cloud(c) => {
                                    digests.clouds.insert(name.clone(), c);
                                }
                                Streamed::Program(p) => {
                                    digests.programs.insert(name.clone(), p);
                                }
                                Streamed::Telemetry(t) => digests.telemetry = Some(*t),
                            })
                        }
                    }
                }
            };
            if let Err(e) = read {
                tracing::warn!(job = id, artifact = name.as_str(), error = %e, "artifact left out of the report");
            }
        }
        let value = serde_json::to_value(&job)
            .map_err(|e| ApiError::new(ErrorCode::Internal, format!("encoding the job: {e}")))?;
        tokio::task::spawn_blocking(move || {
            depthmill_report::render(&depthmill_report::ReportInput {
                job: &value,
                artifacts: &artifacts,
                digests: &digests,
            })
        })
        .await
        .map_err(|e| ApiError::new(ErrorCode::Internal, format!("rendering the report failed: {e}")))?
        .map_err(|e| ApiError::new(ErrorCode::Internal, format!("rendering the report failed: {e}")))
    }

    pub async fn get_job(&self, id: &str) -> Result<Job, ApiError> {
        match self.store.get(id).await? {
            Some(job) => Ok(self.with_input(job).await),
            None => Err(ApiError::new(ErrorCode::NotFound, format!("job {id} not found"))),
        }
    }

    pub async fn list_jobs(
        &self,
        status: Option<JobStatus>,
        limit: Option<u32>,
        cursor: Option<&str>,
    ) -> Result<JobPage, ApiError> {
        let limit = limit.unwrap_or(self.limits.default_page);
        if limit == 0 || limit > self.limits.max_page {
            return Err(ApiError::field(
                ErrorCode::InvalidArgument,
                "limit",
                format!("must be 1 to {}, got {limit}", self.limits.max_page),
            ));
        }
        let cursor = match cursor.filter(|c| !c.is_empty()) {
            None => None,
            Some(c) => Some(c.parse::<i64>().ok().filter(|v| *v > 0).ok_or_else(|| {
                ApiError::field(
                    ErrorCode::InvalidArgument,
                    "cursor",
                    format!("'{c}' is not a cursor this API returned"),
                )
            })?),
        };
        let mut page = self.store.list(status, limit, cursor).await?;
        let mut jobs = Vec::with_capacity(page.jobs.len());
        for job in page.jobs.drain(..) {
            jobs.push(self.with_input(job).await);
        }
        page.jobs = jobs;
        Ok(page)
    }

    /// Asks a job to stop. A queued job is cancelled at once; a running job stops at its next stage
    /// boundary, and the service running its current stage is told to stop. Cancelling an ended job
    /// changes nothing and returns it.
    pub async fn cancel_job(&self, id: &str) -> Result<Job, ApiError> {
        let job = self
            .store
            .request_cancel(id, now_ms())
            .await?
            .ok_or_else(|| ApiError::new(ErrorCode::NotFound, format!("job {id} not found")))?;
        self.running.cancel(id);
        self.events.job_changed(id);
        Ok(self.with_input(job).await)
    }

    /// The job now, then the job after each change of status, stage or progress, until it ends.
    /// The channel closes after the terminal state was sent.
    pub async fn watch_job(&self, id: &str) -> Result<mpsc::Receiver<Result<Job, ApiError>>, ApiError> {
        let mut changes = self.events.subscribe();
        let first = self.get_job(id).await?;
        let (tx, rx) = mpsc::channel(16);
        let app = self.clone();
        let id = id.to_string();
        tokio::spawn(async move {
            let mut last = (first.status, first.stage, first.progress);
            let done = first.status.is_terminal();
            if tx.send(Ok(first)).await.is_err() || done {
                return;
            }
            loop {
                // A periodic re-read covers changes made by other orchestrator instances.
                let woke = tokio::time::timeout(Duration::from_secs(2), changes.recv()).await;
                if tx.is_closed() {
                    // The watcher went away.
                    return;
                }
                match woke {
                    Ok(Ok(changed)) if changed != id => continue,
                    Ok(Err(tokio::sync::broadcast::error::RecvError::Closed)) => return,
                    _ => {}
                }
                let job = match app.get_job(&id).await {
                    Ok(j) => j,
                    Err(e) => {
                        let _ = tx.send(Err(e)).await;
                        return;
                    }
                };
                let now = (job.status, job.stage, job.progress);
                if now == last {
                    continue;
                }
                last = now;
                let done = job.status.is_terminal();
                if tx.send(Ok(job)).await.is_err() || done {
                    return;
                }
            }
        });
        Ok(rx)
    }

    /// Streams an upload into the artifact store, within the configured size limit.
    pub async fn upload(
        &self,
        media_type: &str,
        body: &mut (dyn AsyncRead + Send + Unpin),
        declared_len: Option<u64>,
    ) -> Result<ArtifactRef, ApiError> {
        if let Some(len) = declared_len
            && len > self.limits.max_upload_bytes
        {
            return Err(ApiError::new(
                ErrorCode::PayloadTooLarge,
                format!(
                    "upload of {len} bytes is larger than the limit of {} bytes",
                    self.limits.max_upload_bytes
                ),
            ));
        }
        let aref = self.artifacts.put(media_type, body, self.limits.max_upload_bytes).await?;
        metrics::counter!("depthmill_artifacts_uploaded_total").increment(1);
        Ok(aref)
    }

    /// Opens an artifact for download.
    pub async fn download(&self, sha256: &str) -> Result<(ArtifactRef, BlobReader), ApiError> {
        Ok(self.artifacts.open(sha256).await?)
    }

    /// Runs the scanning cell's calibration routine and stores the result as the next version
    /// (the one in force from now on), with trigger `api`. A job's scan calibrates the cell
    /// itself when none is in force (trigger `scan`, [`App::store_calibration`]).
    pub async fn calibrate(
        &self,
        params: &crate::stages::CalibrationParams,
        trigger: &str,
    ) -> Result<crate::store::CalibrationRecord, ApiError> {
        let current = self.store.latest_calibration().await?;
        let id = new_calibration_id();
        let run = self
            .stages
            .calibrate(&id, params, current.as_ref(), CALIBRATION_DEADLINE)
            .await
            .map_err(|e| ApiError::new(e.code, e.message))?;
        Ok(self.store_calibration(id, run.calibration_json, run.report_json, trigger).await?)
    }

    /// Stores a calibration of the scanning cell as the next version, in force from now on.
    pub async fn store_calibration(
        &self,
        id: String,
        calibration_json: String,
        report_json: String,
        trigger: &str,
    ) -> Result<crate::store::CalibrationRecord, crate::store::StoreError> {
        let rec = crate::store::CalibrationRecord {
            id,
            version: 0,
            created_at_ms: now_ms(),
            trigger_kind: trigger.to_string(),
            calibration_json,
            report_json,
        };
        let stored = self.store.create_calibration(&rec).await?;
        tracing::info!(id = %stored.id, version = stored.version, trigger, "cell calibration stored");
        Ok(stored)
    }

    /// The CAM service's tool library.
    pub async fn list_tools(&self) -> Result<Vec<crate::stages::ToolSummary>, ApiError> {
        self.stages.list_tools().await.map_err(|e| ApiError::new(e.code, e.message))
    }

    /// The CAM service's cutting table, each material marked with whether the machine's
    /// cutting model knows it (when the machine service answers).
    pub async fn list_materials(&self) -> Result<Vec<crate::stages::MaterialSummary>, ApiError> {
        let mut materials =
            self.stages.list_materials().await.map_err(|e| ApiError::new(e.code, e.message))?;
        match self.stages.list_machines().await {
            Ok((_, simulated)) => {
                for m in &mut materials {
                    m.simulated = Some(simulated.contains(&m.name));
                }
            }
            Err(e) => tracing::debug!(error = %e.message, "materials listed without the machine's model"),
        }
        Ok(materials)
    }

    /// The machine service's profiles.
    pub async fn list_machines(&self) -> Result<Vec<crate::stages::MachineSummary>, ApiError> {
        let (machines, _) =
            self.stages.list_machines().await.map_err(|e| ApiError::new(e.code, e.message))?;
        Ok(machines)
    }

    /// Readiness: the database answers.
    pub async fn ready(&self) -> Result<(), ApiError> {
        self.store.ping().await?;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_unreachable_database_or_a_full_disk_is_503_and_says_nothing_was_changed() {
        let full = ArtifactError::Io {
            path: "blobs/x".into(),
            source: std::io::Error::from(std::io::ErrorKind::StorageFull),
        };
        let e = ApiError::from(full);
        assert_eq!(e.code, ErrorCode::Unavailable);
        assert!(
            e.message.contains("out of space") && e.message.contains("nothing was stored"),
            "{}",
            e.message
        );
        let down = StoreError::Db(sqlx::Error::PoolTimedOut);
        let e = ApiError::from(down);
        assert_eq!(e.code, ErrorCode::Unavailable);
        assert!(e.message.contains("nothing was changed"), "{}", e.message);
        let other = ArtifactError::Io {
            path: "blobs/x".into(),
            source: std::io::Error::from(std::io::ErrorKind::PermissionDenied),
        };
        assert_eq!(ApiError::from(other).code, ErrorCode::Internal);
    }
}
