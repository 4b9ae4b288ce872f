//! tonic adapter of the reconstruction service.

use std::pin::Pin;

use depthmill_common::stage::StageRegistry;
use depthmill_proto::ErrorCode;
use depthmill_proto::reconstruction::v1 as pb;
use depthmill_proto::types::v1::{CancelStageRequest, CancelStageResponse};
use tonic::{Request, Response, Status};

pub(crate) const SERVICE_NAME: &str = "depthmill.reconstruction.v1.ReconstructionService";

#[derive(Default)]
struct ReconstructionServiceImpl {
    running: StageRegistry,
}

pub(crate) fn routes() -> tonic::service::Routes {
    tonic::service::Routes::new(pb::reconstruction_service_server::ReconstructionServiceServer::new(
        ReconstructionServiceImpl::default(),
    ))
}

type UpdateStream =
    Pin<Box<dyn tokio_stream::Stream<Item = Result<pb::BuildDepthMapsUpdate, Status>> + Send>>;

#[tonic::async_trait]
impl pb::reconstruction_service_server::ReconstructionService for ReconstructionServiceImpl {
    type BuildDepthMapsStream = UpdateStream;

    async fn build_depth_maps(
        &self,
        request: Request<pb::BuildDepthMapsRequest>,
    ) -> Result<Response<Self::BuildDepthMapsStream>, Status> {
        let job_id = request.get_ref().context.as_ref().map(|c| c.job_id.clone()).unwrap_or_default();
        tracing::warn!(%job_id, "reconstruction stage requested but not available");
        Err(ErrorCode::StageNotAvailable.status(
            "stage not available: the reconstruction service does not implement BuildDepthMaps yet (see issue #4)",
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
