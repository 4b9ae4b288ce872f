//! `/v1/artifacts`: streamed upload and download of content-addressed files.

use axum::body::Body;
use axum::extract::{Path, State};
use axum::http::{HeaderMap, HeaderValue, header};
use axum::response::{IntoResponse, Response};
use depthmill_proto::ErrorCode;
use futures::TryStreamExt as _;
use tokio_util::io::{ReaderStream, StreamReader};

use super::ErrorBody;
use crate::app::{ApiError, App};

/// Uploads a file: the body is its bytes, `Content-Type` its media type (`model/stl`,
/// `application/x-ply`, `text/x-xyz`, `image/png`, `application/x-npy`, `text/x-gcode`, ...).
/// The body is streamed to disk while hashed; it must be within the size limit and its bytes must
/// be of the declared type.
#[utoipa::path(post, path = "/v1/artifacts", tag = "artifacts",
    request_body(content = Vec<u8>, content_type = "application/octet-stream", description = "the file's bytes"),
    responses(
        (status = 201, description = "stored", body = crate::domain::job::ArtifactRefSchema),
        (status = 400, body = ErrorBody), (status = 413, body = ErrorBody), (status = 415, body = ErrorBody)))]
pub(crate) async fn upload_artifact(
    State(app): State<App>,
    headers: HeaderMap,
    body: Body,
) -> Result<Response, ApiError> {
    let media_type = headers
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .ok_or_else(|| {
            ApiError::field(
                ErrorCode::UnsupportedMediaType,
                "Content-Type",
                "an upload needs a Content-Type: its media type",
            )
        })?
        .to_string();
    let declared =
        headers.get(header::CONTENT_LENGTH).and_then(|v| v.to_str().ok()).and_then(|v| v.parse().ok());
    let stream = body.into_data_stream().map_err(std::io::Error::other);
    let mut reader = StreamReader::new(stream);
    let aref = app.upload(&media_type, &mut reader, declared).await?;
    let body = serde_json::json!({"sha256": aref.sha256, "size": aref.size, "media_type": aref.media_type, "uri": aref.uri});
    Ok(super::created(body))
}

/// Downloads a file by its sha256, streamed, with its media type.
#[utoipa::path(get, path = "/v1/artifacts/{sha256}", tag = "artifacts", params(("sha256" = String, Path)),
    responses((status = 200, description = "the bytes", content_type = "application/octet-stream"),
              (status = 400, body = ErrorBody), (status = 404, body = ErrorBody)))]
pub(crate) async fn download_artifact(
    State(app): State<App>,
    Path(sha256): Path<String>,
) -> Result<Response, ApiError> {
    let (aref, reader) = app.download(&sha256).await?;
    let content_type = HeaderValue::from_str(&aref.media_type)
        .unwrap_or(HeaderValue::from_static("application/octet-stream"));
    let headers = [
        (header::CONTENT_TYPE, content_type),
        (header::CONTENT_LENGTH, HeaderValue::from(aref.size)),
        (
            header::ETAG,
            HeaderValue::from_str(&format!("\"{}\"", aref.sha256))
                .unwrap_or(HeaderValue::from_static("\"\"")),
        ),
        (header::CACHE_CONTROL, HeaderValue::from_static("public, max-age=31536000, immutable")),
    ];
    let body = Body::from_stream(ReaderStream::with_capacity(reader, 64 * 1024));
    Ok((headers, body).into_response())
}
