//! The orchestrator's gRPC API (`depthmill.orchestrator.v1.OrchestratorService`): the REST
//! operations plus `WatchJob`, over the same [`App`].

use std::pin::Pin;

use depthmill_proto::ErrorCode;
use depthmill_proto::orchestrator::v1 as pb;
use depthmill_proto::orchestrator::v1::orchestrator_service_server::{
    OrchestratorService, OrchestratorServiceServer,
};
use depthmill_proto::types::v1::ArtifactRef;
use futures::{Stream, StreamExt as _, TryStreamExt as _};
use tokio_util::io::{ReaderStream, StreamReader};
use tonic::{Request, Response, Status, Streaming};

use crate::app::{ApiError, App};
use crate::convert;

pub(crate) const SERVICE_NAME: &str = "depthmill.orchestrator.v1.OrchestratorService";

fn calibration_record(rec: crate::store::CalibrationRecord) -> pb::CellCalibrationRecord {
    pb::CellCalibrationRecord {
        id: rec.id,
        version: rec.version,
        created_at_ms: rec.created_at_ms,
        trigger: rec.trigger_kind,
        calibration_json: rec.calibration_json,
        report_json: rec.report_json,
    }
}

impl From<ApiError> for Status {
    fn from(e: ApiError) -> Self {
        let message = match &e.field {
            Some(f) if !e.message.starts_with(f.as_str()) => format!("{f}: {}", e.message),
            _ => e.message,
        };
        e.code.status(message)
    }
}

struct Api {
    app: App,
}

/// The service, behind the API-token check (health and reflection, added by the server, stay open).
pub(crate) fn routes(app: App) -> tonic::service::Routes {
    let auth = app.auth.clone();
    let router = tonic::service::Routes::new(
        OrchestratorServiceServer::new(Api { app })
            .max_decoding_message_size(8 << 20)
            .max_encoding_message_size(8 << 20),
    )
    .into_axum_router()
    .layer(axum::middleware::from_fn_with_state(auth, require_token));
    tonic::service::Routes::from(router)
}

/// Answers UNAUTHENTICATED / PERMISSION_DENIED before the call reaches the service when the
/// `authorization` metadata does not allow it.
/// Names the caller ([`crate::auth::Client`]) in the request's extensions for the methods.
async fn require_token(
    axum::extract::State(auth): axum::extract::State<std::sync::Arc<crate::auth::Authenticator>>,
    mut request: axum::extract::Request,
    next: axum::middleware::Next,
) -> axum::response::Response {
    if let Some(scope) = crate::auth::grpc_scope(request.uri().path()) {
        let header = request.headers().get("authorization").and_then(|v| v.to_str().ok());
        match auth.check(header, scope, crate::app::now_ms()).await {
            Ok(token_id) => {
                use tonic::transport::server::{TcpConnectInfo, TlsConnectInfo};
                let ext = request.extensions();
                let peer = ext.get::<TcpConnectInfo>().and_then(TcpConnectInfo::remote_addr).or_else(|| {
                    ext.get::<TlsConnectInfo<TcpConnectInfo>>().and_then(|t| t.get_ref().remote_addr())
                });
                if let Some(client) = crate::auth::Client::of(token_id, peer) {
                    request.extensions_mut().insert(client);
                }
            }
            Err(e) => return Status::from(e).into_http(),
        }
    }
    next.run(request).await
}

type Boxed<T> = Pin<Box<dyn Stream<Item = Result<T, Status>> + Send>>;

#[tonic::async_trait]
impl OrchestratorService for Api {
    async fn create_job(&self, request: Request<pb::CreateJobRequest>) -> Result<Response<pb::Job>, Status> {
        let client = request.extensions().get::<crate::auth::Client>().cloned();
        let r = request.into_inner();
        let spec =
            r.spec.ok_or_else(|| ApiError::field(ErrorCode::InvalidArgument, "spec", "is required"))?;
        let spec = convert::job_spec_from_pb(spec).map_err(ApiError::from)?;
        let key = (!r.idempotency_key.is_empty()).then_some(r.idempotency_key);
        let (job, _) = self.app.create_job(spec, key, client.as_ref()).await?;
        Ok(Response::new(convert::job(&job)))
    }

    async fn get_job(&self, request: Request<pb::GetJobRequest>) -> Result<Response<pb::Job>, Status> {
        Ok(Response::new(convert::job(&self.app.get_job(&request.get_ref().id).await?)))
    }

    async fn list_jobs(
        &self,
        request: Request<pb::ListJobsRequest>,
    ) -> Result<Response<pb::ListJobsResponse>, Status> {
        let r = request.into_inner();
        let status = convert::job_status_filter(r.status).map_err(ApiError::from)?;
        let limit = (r.limit != 0).then_some(r.limit);
        let page = self.app.list_jobs(status, limit, Some(r.cursor.as_str())).await?;
        Ok(Response::new(pb::ListJobsResponse {
            jobs: page.jobs.iter().map(convert::job).collect(),
            next_cursor: page.next_cursor.map(|c| c.to_string()).unwrap_or_default(),
        }))
    }

    async fn create_calibration(
        &self,
        request: Request<pb::CreateCalibrationRequest>,
    ) -> Result<Response<pb::CellCalibrationRecord>, Status> {
        let params = crate::http::parse_calibration_params(request.get_ref().params_json.as_bytes())?;
        Ok(Response::new(calibration_record(self.app.calibrate(&params, "api").await?)))
    }

    async fn get_calibration(
        &self,
        request: Request<pb::GetCalibrationRequest>,
    ) -> Result<Response<pb::CellCalibrationRecord>, Status> {
        let id = &request.get_ref().id;
        match self.app.store.get_calibration(id).await.map_err(ApiError::from)? {
            Some(rec) => Ok(Response::new(calibration_record(rec))),
            None => {
                Err(ApiError::new(depthmill_proto::ErrorCode::NotFound, format!("no calibration {id}"))
                    .into())
            }
        }
    }

    async fn list_calibrations(
        &self,
        request: Request<pb::ListCalibrationsRequest>,
    ) -> Result<Response<pb::ListCalibrationsResponse>, Status> {
        let limit = match request.get_ref().limit {
            0 => 20,
            l @ 1..=100 => l,
            l => {
                return Err(ApiError::field(
                    depthmill_proto::ErrorCode::InvalidArgument,
                    "limit",
                    format!("limit = {l}: 1 to 100"),
                )
                .into());
            }
        };
        let recs = self.app.store.list_calibrations(limit).await.map_err(ApiError::from)?;
        Ok(Response::new(pb::ListCalibrationsResponse {
            calibrations: recs.into_iter().map(calibration_record).collect(),
        }))
    }

    async fn cancel_job(&self, request: Request<pb::CancelJobRequest>) -> Result<Response<pb::Job>, Status> {
        Ok(Response::new(convert::job(&self.app.cancel_job(&request.get_ref().id).await?)))
    }

    type WatchJobStream = Boxed<pb::Job>;

    async fn watch_job(
        &self,
        request: Request<pb::WatchJobRequest>,
    ) -> Result<Response<Self::WatchJobStream>, Status> {
        let rx = self.app.watch_job(&request.get_ref().id).await?;
        let stream = tokio_stream::wrappers::ReceiverStream::new(rx)
            .map(|item| item.map(|job| convert::job(&job)).map_err(Status::from));
        Ok(Response::new(Box::pin(stream)))
    }

    async fn upload_artifact(
        &self,
        request: Request<Streaming<pb::UploadArtifactRequest>>,
    ) -> Result<Response<ArtifactRef>, Status> {
        let mut stream = request.into_inner();
        let first = stream
            .message()
            .await?
            .ok_or_else(|| ApiError::new(ErrorCode::InvalidArgument, "upload stream is empty"))?;
        if first.media_type.is_empty() {
            return Err(ApiError::field(
                ErrorCode::InvalidArgument,
                "media_type",
                "the first message must carry the media type",
            )
            .into());
        }
        let media_type = first.media_type.clone();
        let head = futures::stream::once(async move { Ok::<_, Status>(first.data) });
        let rest = stream.map_ok(|m| m.data);
        let bytes = Box::pin(
            head.chain(rest)
                .map_ok(bytes::Bytes::from)
                .map_err(|s| std::io::Error::other(s.message().to_string())),
        );
        let mut reader = StreamReader::new(bytes);
        let aref = self.app.upload(&media_type, &mut reader, None).await?;
        Ok(Response::new(aref.into()))
    }

    type DownloadArtifactStream = Boxed<pb::ArtifactChunk>;

    async fn download_artifact(
        &self,
        request: Request<pb::DownloadArtifactRequest>,
    ) -> Result<Response<Self::DownloadArtifactStream>, Status> {
        let (aref, reader) = self.app.download(&request.get_ref().sha256).await?;
        let mut first = Some(ArtifactRef::from(aref));
        let chunks = ReaderStream::with_capacity(reader, 256 * 1024).map(move |chunk| match chunk {
            Ok(data) => Ok(pb::ArtifactChunk { artifact: first.take(), data: data.to_vec() }),
            Err(e) => Err(Status::internal(format!("reading the artifact failed: {e}"))),
        });
        Ok(Response::new(Box::pin(chunks)))
    }
}
