//! tonic adapter of the scanning service.

use std::pin::Pin;

use depthmill_common::stage::StageRegistry;
use depthmill_proto::ErrorCode;
use depthmill_proto::scanning::v1 as pb;
use depthmill_proto::types::v1::{CancelStageRequest, CancelStageResponse};
use tonic::{Request, Response, Status};

pub(crate) const SERVICE_NAME: &str = "depthmill.scanning.v1.ScanningService";

#[derive(Default)]
struct ScanningServiceImpl {
    running: StageRegistry,
}

pub(crate) fn routes() -> tonic::service::Routes {
    tonic::service::Routes::new(pb::scanning_service_server::ScanningServiceServer::new(
        ScanningServiceImpl::default(),
    ))
}

type UpdateStream = Pin<Box<dyn tokio_stream::Stream<Item = Result<pb::ScanPartUpdate, Status>> + Send>>;

#[tonic::async_trait]
impl pb::scanning_service_server::ScanningService for ScanningServiceImpl {
    type ScanPartStream = UpdateStream;

    async fn scan_part(
        &self,
        request: Request<pb::ScanPartRequest>,
    ) -> Result<Response<Self::ScanPartStream>, Status> {
        let job_id = request.get_ref().context.as_ref().map(|c| c.job_id.clone()).unwrap_or_default();
        tracing::warn!(%job_id, "scanning stage requested but not available");
        Err(ErrorCode::StageNotAvailable.status(
            "stage not available: the scanning service does not implement ScanPart yet (see issue #6)",
        ))
    }

    async fn cancel_stage(
        &self,
        request: Request<CancelStageRequest>,
    ) -> Result<Response<CancelStageResponse>, Status> {
        let found = self.running.cancel(&request.get_ref().job_id);
        Ok(Response::new(CancelStageResponse { found }))
    }
}
