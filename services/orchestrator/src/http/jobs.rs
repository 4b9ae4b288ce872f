//! `/v1/jobs`: submit, list, get, cancel, and server-sent events of a job's progress.

use std::convert::Infallible;

use axum::Json;
use axum::body::Bytes;
use axum::extract::{Path, Query, State};
use axum::http::{HeaderMap, StatusCode, header};
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use depthmill_proto::ErrorCode;
use serde::{Deserialize, Serialize};
use utoipa::{IntoParams, ToSchema};

use super::ErrorBody;
use crate::app::{ApiError, App};
use crate::domain::{Job, JobSpec, JobStatus};

/// Parses a job request, naming the offending field of any error.
pub fn parse_job_spec(body: &[u8]) -> Result<JobSpec, ApiError> {
    JobSpec::from_json(body).map_err(|e| ApiError {
        code: ErrorCode::InvalidArgument,
        message: e.message,
        field: e.field,
    })
}

/// Submits a job. The body is the job request of DESIGN.md §7; unknown fields are rejected.
/// With an `Idempotency-Key` header, repeating the request returns the job the first one made (200).
#[utoipa::path(post, path = "/v1/jobs", tag = "jobs",
    request_body(content = JobSpec, content_type = "application/json"),
    params(("Idempotency-Key" = Option<String>, Header, description = "same key, same job")),
    responses(
        (status = 201, description = "job created", body = Job),
        (status = 200, description = "the job an earlier request with this Idempotency-Key created", body = Job),
        (status = 400, description = "malformed or invalid request", body = ErrorBody),
        (status = 409, description = "Idempotency-Key reused with a different request", body = ErrorBody),
        (status = 413, description = "the request is larger than the 2 MiB a job request may be", body = ErrorBody),
        (status = 429, description = "the client has as many jobs queued or running as it may (`max_active_jobs_per_client`)", body = ErrorBody)))]
pub(crate) async fn create_job(
    State(app): State<App>,
    client: Option<axum::Extension<crate::auth::Client>>,
    headers: HeaderMap,
    body: Result<Bytes, axum::extract::rejection::BytesRejection>,
) -> Result<Response, ApiError> {
    // axum's default body limit (2 MiB) for a job request, answered as the API's error.
    let body = body.map_err(|e| match e.status() {
        axum::http::StatusCode::PAYLOAD_TOO_LARGE => ApiError::new(
            ErrorCode::PayloadTooLarge,
            "the job request is larger than the limit of 2 MiB (2097152 bytes); large inputs go in artifacts",
        ),
        _ => ApiError::new(ErrorCode::InvalidArgument, format!("reading the request failed: {e}")),
    })?;
    if let Some(ct) = headers.get(header::CONTENT_TYPE) {
        let ct = ct.to_str().unwrap_or("");
        if !ct.starts_with("application/json") {
            return Err(ApiError::new(
                ErrorCode::UnsupportedMediaType,
                format!("a job request is application/json, got '{ct}'"),
            ));
        }
    }
    let key = match headers.get("idempotency-key") {
        Some(v) => Some(
            v.to_str()
                .map_err(|_| {
                    ApiError::field(ErrorCode::InvalidArgument, "Idempotency-Key", "must be visible ASCII")
                })?
                .to_string(),
        ),
        None => None,
    };
    let spec = parse_job_spec(&body)?;
    let (job, is_new) = app.create_job(spec, key, client.as_ref().map(|c| &c.0)).await?;
    if is_new { Ok(super::created(job)) } else { Ok((StatusCode::OK, Json(job)).into_response()) }
}

/// Query of `GET /v1/jobs`.
#[derive(Deserialize, IntoParams)]
#[serde(deny_unknown_fields)]
pub(crate) struct ListQuery {
    /// Only jobs with this status.
    status: Option<String>,
    /// Page size, 1 to 1000 (default 50).
    limit: Option<u32>,
    /// `next_cursor` of the previous page.
    cursor: Option<String>,
}

/// A page of jobs, newest first.
#[derive(Serialize, ToSchema)]
pub struct JobList {
    pub jobs: Vec<Job>,
    /// Pass as `cursor` for the next page; absent on the last page.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub next_cursor: Option<String>,
}

/// Lists jobs, newest first, optionally by status, a page at a time.
#[utoipa::path(get, path = "/v1/jobs", tag = "jobs", params(ListQuery),
    responses((status = 200, body = JobList), (status = 400, body = ErrorBody)))]
pub(crate) async fn list_jobs(
    State(app): State<App>,
    query: Result<Query<ListQuery>, axum::extract::rejection::QueryRejection>,
) -> Result<Json<JobList>, ApiError> {
    let Query(q) = query.map_err(|e| ApiError::new(ErrorCode::InvalidArgument, e.body_text()))?;
    let status = q
        .status
        .as_deref()
        .map(str::parse::<JobStatus>)
        .transpose()
        .map_err(|e| ApiError::field(ErrorCode::InvalidArgument, "status", e))?;
    let page = app.list_jobs(status, q.limit, q.cursor.as_deref()).await?;
    Ok(Json(JobList { jobs: page.jobs, next_cursor: page.next_cursor.map(|c| c.to_string()) }))
}

/// A job: status, stage, progress, error, stage timings, artifacts, metrics and every attempt.
#[utoipa::path(get, path = "/v1/jobs/{id}", tag = "jobs", params(("id" = String, Path)),
    responses((status = 200, body = Job), (status = 404, body = ErrorBody)))]
pub(crate) async fn get_job(State(app): State<App>, Path(id): Path<String>) -> Result<Json<Job>, ApiError> {
    Ok(Json(app.get_job(&id).await?))
}

/// The job's report, an HTML page (DESIGN §7): the stored one once the job has been through its
/// report stage, otherwise rendered now from what the job has so far (any status).
#[utoipa::path(get, path = "/v1/jobs/{id}/report", tag = "jobs", params(("id" = String, Path)),
    responses((status = 200, description = "the HTML report", content_type = "text/html"),
              (status = 404, body = ErrorBody)))]
pub(crate) async fn job_report(State(app): State<App>, Path(id): Path<String>) -> Result<Response, ApiError> {
    let job = app.get_job(&id).await?;
    let stored = match job.artifacts.get("report") {
        Some(a) if a.media_type == "text/html" && job.status == crate::domain::JobStatus::Succeeded => {
            app.artifacts.read_all(&a.sha256, crate::app::REPORT_ARTIFACT_LIMIT).await.ok()
        }
        _ => None,
    };
    let html = match stored {
        Some(bytes) => bytes,
        None => app.render_report(&id).await?.html.into_bytes(),
    };
    Ok((
        [(
            axum::http::header::CONTENT_TYPE,
            axum::http::HeaderValue::from_static("text/html; charset=utf-8"),
        )],
        html,
    )
        .into_response())
}

/// Cancels a job: at once when queued, at the next stage boundary when running (the service
/// running the current stage is told to stop). An ended job is returned unchanged.
#[utoipa::path(post, path = "/v1/jobs/{id}/cancel", tag = "jobs", params(("id" = String, Path)),
    responses((status = 200, body = Job), (status = 404, body = ErrorBody)))]
pub(crate) async fn cancel_job(
    State(app): State<App>,
    Path(id): Path<String>,
) -> Result<Json<Job>, ApiError> {
    Ok(Json(app.cancel_job(&id).await?))
}

/// Server-sent events: a `job` event with the job now, then one per change of status, stage or
/// progress; the stream ends after the job ends.
#[utoipa::path(get, path = "/v1/jobs/{id}/events", tag = "jobs", params(("id" = String, Path)),
    responses((status = 200, description = "text/event-stream of `job` events, each the job as JSON", content_type = "text/event-stream"),
              (status = 404, body = ErrorBody)))]
pub(crate) async fn job_events(State(app): State<App>, Path(id): Path<String>) -> Result<Response, ApiError> {
    let rx = app.watch_job(&id).await?;
    let stream = futures::stream::unfold(rx, |mut rx| async move {
        let item = rx.recv().await?;
        let event = match item {
            Ok(job) => Event::default()
                .event("job")
                .json_data(&job)
                .unwrap_or_else(|e| Event::default().event("error").data(format!("cannot encode job: {e}"))),
            Err(e) => Event::default().event("error").data(e.message),
        };
        Some((Ok::<_, Infallible>(event), rx))
    });
    Ok(Sse::new(stream).keep_alive(KeepAlive::default()).into_response())
}
