//! tonic adapter of the machine service.

use std::pin::Pin;

use depthmill_common::stage::StageRegistry;
use depthmill_proto::ErrorCode;
use depthmill_proto::machine::v1 as pb;
use depthmill_proto::types::v1::{CancelStageRequest, CancelStageResponse};
use tonic::{Request, Response, Status};

pub(crate) const SERVICE_NAME: &str = "depthmill.machine.v1.MachineService";

#[derive(Default)]
struct MachineServiceImpl {
    running: StageRegistry,
}

pub(crate) fn routes() -> tonic::service::Routes {
    tonic::service::Routes::new(pb::machine_service_server::MachineServiceServer::new(
        MachineServiceImpl::default(),
    ))
}

type UpdateStream =
    Pin<Box<dyn tokio_stream::Stream<Item = Result<pb::ExecuteProgramUpdate, Status>> + Send>>;

#[tonic::async_trait]
impl pb::machine_service_server::MachineService for MachineServiceImpl {
    type ExecuteProgramStream = UpdateStream;

    async fn execute_program(
        &self,
        request: Request<pb::ExecuteProgramRequest>,
    ) -> Result<Response<Self::ExecuteProgramStream>, Status> {
        let job_id = request.get_ref().context.as_ref().map(|c| c.job_id.clone()).unwrap_or_default();
        tracing::warn!(%job_id, "machine stage requested but not available");
        Err(ErrorCode::StageNotAvailable.status(
            "stage not available: the machine service does not implement ExecuteProgram yet (see issue #5)",
        ))
    }

    async fn cancel_stage(
        &self,
        request: Request<CancelStageRequest>,
    ) -> Result<Response<CancelStageResponse>, Status> {
        let found = self.running.cancel(&request.get_ref().job_id);
        Ok(Response::new(CancelStageResponse { found }))
    }

    async fn get_status(
        &self,
        _request: Request<pb::GetStatusRequest>,
    ) -> Result<Response<pb::MachineStatus>, Status> {
        Err(ErrorCode::StageNotAvailable
            .status("stage not available: the machine service has no machine yet"))
    }

    async fn stop(&self, _request: Request<pb::StopRequest>) -> Result<Response<pb::MachineStatus>, Status> {
        Err(ErrorCode::StageNotAvailable
            .status("stage not available: the machine service has no machine yet"))
    }

    async fn reset(
        &self,
        _request: Request<pb::ResetRequest>,
    ) -> Result<Response<pb::MachineStatus>, Status> {
        Err(ErrorCode::StageNotAvailable
            .status("stage not available: the machine service has no machine yet"))
    }
}
