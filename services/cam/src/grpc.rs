//! tonic adapter of the cam service.

use std::pin::Pin;

use depthmill_common::stage::StageRegistry;
use depthmill_proto::ErrorCode;
use depthmill_proto::cam::v1 as pb;
use depthmill_proto::types::v1::{CancelStageRequest, CancelStageResponse};
use tonic::{Request, Response, Status};

pub(crate) const SERVICE_NAME: &str = "depthmill.cam.v1.CamService";

#[derive(Default)]
struct CamServiceImpl {
    running: StageRegistry,
}

pub(crate) fn routes() -> tonic::service::Routes {
    tonic::service::Routes::new(pb::cam_service_server::CamServiceServer::new(CamServiceImpl::default()))
}

type UpdateStream = Pin<Box<dyn tokio_stream::Stream<Item = Result<pb::PlanToolpathsUpdate, Status>> + Send>>;

#[tonic::async_trait]
impl pb::cam_service_server::CamService for CamServiceImpl {
    type PlanToolpathsStream = UpdateStream;

    async fn plan_toolpaths(
        &self,
        request: Request<pb::PlanToolpathsRequest>,
    ) -> Result<Response<Self::PlanToolpathsStream>, Status> {
        let job_id = request.get_ref().context.as_ref().map(|c| c.job_id.clone()).unwrap_or_default();
        tracing::warn!(%job_id, "cam stage requested but not available");
        Err(ErrorCode::StageNotAvailable.status(
            "stage not available: the cam service does not implement PlanToolpaths yet (see issue #3)",
        ))
    }

    async fn cancel_stage(
        &self,
        request: Request<CancelStageRequest>,
    ) -> Result<Response<CancelStageResponse>, Status> {
        let found = self.running.cancel(&request.get_ref().job_id);
        Ok(Response::new(CancelStageResponse { found }))
    }

    async fn list_tools(
        &self,
        _request: Request<pb::ListToolsRequest>,
    ) -> Result<Response<pb::ListToolsResponse>, Status> {
        Err(ErrorCode::StageNotAvailable
            .status("stage not available: the cam service has no tool library yet"))
    }
}
