//! `/v1/calibrations`: calibrate the scanning cell, list and read its stored calibrations.

use axum::Json;
use axum::body::Bytes;
use axum::extract::{Path, Query, State};
use axum::http::StatusCode;
use depthmill_proto::ErrorCode;
use serde::{Deserialize, Serialize};
use utoipa::{IntoParams, ToSchema};

use super::ErrorBody;
use crate::app::{ApiError, App};
use crate::stages::CalibrationParams;
use crate::store::CalibrationRecord;

/// A stored calibration of the scanning cell.
#[derive(Debug, Serialize, ToSchema)]
pub struct CalibrationView {
    /// `cal_...`
    pub id: String,
    /// 1, 2, ... in the order they were made; the highest is in force.
    pub version: i64,
    pub created_at_ms: i64,
    /// `api` (asked for) or `scan` (made by the first scan job when none was in force; `auto` in
    /// stores from before, made by the routine ahead of that scan).
    pub trigger: String,
    /// The parameters: the table model (axis position and tilt, encoder zero, top runout) and
    /// the scanner's mount correction.
    #[schema(value_type = Object)]
    pub calibration: serde_json::Value,
    /// The fit's report: residuals per station, the merge and registration error before and
    /// after, the result against the simulated cell's truth, the options.
    #[schema(value_type = Object)]
    pub report: serde_json::Value,
}

impl CalibrationView {
    fn of(rec: CalibrationRecord) -> Result<Self, ApiError> {
        let parse = |what: &str, s: &str| {
            serde_json::from_str(s).map_err(|e| {
                ApiError::new(
                    ErrorCode::Internal,
                    format!("stored calibration {} has a corrupt {what}: {e}", rec.id),
                )
            })
        };
        Ok(Self {
            calibration: parse("calibration", &rec.calibration_json)?,
            report: parse("report", &rec.report_json)?,
            id: rec.id,
            version: rec.version,
            created_at_ms: rec.created_at_ms,
            trigger: rec.trigger_kind,
        })
    }
}

/// `GET /v1/calibrations`.
#[derive(Debug, Serialize, ToSchema)]
pub struct CalibrationList {
    /// Newest first.
    pub calibrations: Vec<CalibrationView>,
}

#[derive(Debug, Deserialize, IntoParams)]
pub(crate) struct ListQuery {
    /// At most this many (1..=100, default 20).
    limit: Option<u32>,
}

/// The calibration routine's options from a JSON body (empty: the defaults), naming a bad field.
pub fn parse_calibration_params(body: &[u8]) -> Result<CalibrationParams, ApiError> {
    if body.iter().all(u8::is_ascii_whitespace) {
        return Ok(CalibrationParams::default());
    }
    let de = &mut serde_json::Deserializer::from_slice(body);
    serde_path_to_error::deserialize(de).map_err(|e| {
        let path = e.path().to_string();
        ApiError::field(ErrorCode::InvalidArgument, path, format!("calibration options: {}", e.inner()))
    })
}

/// Calibrates the scanning cell: scans of the table top and the reference sphere at several
/// table angles, the fit of the table and the scanner mount; stored as the next version, in
/// force for every scan from now on. The body (optional) sets the routine's options; the
/// previous calibration stays in force when the routine fails.
#[utoipa::path(post, path = "/v1/calibrations", tag = "calibrations",
    request_body(content = CalibrationParams, content_type = "application/json"),
    responses(
        (status = 201, description = "calibrated and stored", body = CalibrationView),
        (status = 400, description = "bad options or degenerate calibration data", body = ErrorBody),
        (status = 501, description = "no scanning service is configured", body = ErrorBody),
        (status = 503, description = "the scanning service cannot be reached", body = ErrorBody)))]
pub(crate) async fn create_calibration(
    State(app): State<App>,
    body: Bytes,
) -> Result<(StatusCode, Json<CalibrationView>), ApiError> {
    let params = parse_calibration_params(&body)?;
    let rec = app.calibrate(&params, "api").await?;
    Ok((StatusCode::CREATED, Json(CalibrationView::of(rec)?)))
}

/// The stored calibrations, newest (in force) first.
#[utoipa::path(get, path = "/v1/calibrations", tag = "calibrations", params(ListQuery),
    responses((status = 200, body = CalibrationList), (status = 400, body = ErrorBody)))]
pub(crate) async fn list_calibrations(
    State(app): State<App>,
    Query(q): Query<ListQuery>,
) -> Result<Json<CalibrationList>, ApiError> {
    let limit = q.limit.unwrap_or(20);
    if !(1..=100).contains(&limit) {
        return Err(ApiError::field(
            ErrorCode::InvalidArgument,
            "limit",
            format!("limit = {limit}: 1 to 100"),
        ));
    }
    let recs = app.store.list_calibrations(limit).await?;
    Ok(Json(CalibrationList {
        calibrations: recs.into_iter().map(CalibrationView::of).collect::<Result<_, _>>()?,
    }))
}

/// One stored calibration.
#[utoipa::path(get, path = "/v1/calibrations/{id}", tag = "calibrations", params(("id" = String, Path)),
    responses((status = 200, body = CalibrationView), (status = 404, body = ErrorBody)))]
pub(crate) async fn get_calibration(
    State(app): State<App>,
    Path(id): Path<String>,
) -> Result<Json<CalibrationView>, ApiError> {
    match app.store.get_calibration(&id).await? {
        Some(rec) => Ok(Json(CalibrationView::of(rec)?)),
        None => Err(ApiError::new(ErrorCode::NotFound, format!("no calibration {id}"))),
    }
}
