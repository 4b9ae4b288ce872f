//! The stage services as seen from the worker: the [`StageRunner`] port and its gRPC adapter
//! [`GrpcStages`]. Each stage is one streaming call (progress updates, then one result) to one
//! service, with a deadline.

use std::collections::BTreeMap;
use std::time::Duration;

use depthmill_geometry::ArtifactRef;
use depthmill_proto::ErrorCode;
use depthmill_proto::cam::v1 as cam;
use depthmill_proto::machine::v1 as machine;
use depthmill_proto::reconstruction::v1 as rec;
use depthmill_proto::scanning::v1 as scan;
use depthmill_proto::types::v1 as types;
use tonic::transport::{Channel, Endpoint};

use crate::convert;
use crate::domain::{JobSpec, SpecError, Stage, StageOutputs};

/// How long a submission waits for a stage service's parameter check.
pub const CHECK_PARAMS_TIMEOUT: Duration = Duration::from_secs(5);

/// Everything a stage call needs.
#[derive(Debug, Clone)]
pub struct StageCall {
    pub job_id: String,
    pub attempt: u32,
    pub stage: Stage,
    pub spec: JobSpec,
    /// The job's artifacts so far: its input (under its kind's name) and earlier stages' outputs.
    pub artifacts: BTreeMap<String, ArtifactRef>,
    /// The scanning cell's calibration in force (the scan stage places its points with it).
    pub calibration: Option<crate::store::CalibrationRecord>,
    /// No calibration is in force: the scan calibrates the cell (at its own stations when it can)
    /// and returns it in [`StageOutputs::calibration_made`].
    pub calibrate_in_scan: bool,
}

/// The calibration routine's options (`POST /v1/calibrations`); unset fields take the defaults.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize, serde::Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
pub struct CalibrationParams {
    /// Table angles the reference sphere and the top are scanned at, degrees (default 0, 90, 180,
    /// 270; at least 3 over at least 90°).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub table_angles_deg: Option<Vec<f64>>,
    /// Radius of the reference sphere, mm (default 12.7).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sphere_radius_mm: Option<f64>,
    /// Centre of the sphere in the table's frame, mm (default [100, 0, 32.7]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sphere_at_mm: Option<[f64; 3]>,
    /// Distance between scanner lines, mm (default 0.5).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub line_spacing_mm: Option<f64>,
    /// Noise seed.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub seed: Option<u64>,
}

/// A calibration the scanning service made: its parameters and its report, JSON.
#[derive(Debug, Clone, PartialEq)]
pub struct CalibrationRun {
    pub calibration_json: String,
    pub report_json: String,
}

/// The stored calibration's parameters (the scanning service's JSON form).
#[derive(Debug, Clone, Copy, serde::Serialize, serde::Deserialize)]
struct CalibrationJson {
    table: TableJson,
    scanner_mount: OffsetJson,
}

#[derive(Debug, Clone, Copy, serde::Serialize, serde::Deserialize)]
struct TableJson {
    axis_x_mm: f64,
    axis_y_mm: f64,
    top_z_mm: f64,
    axis_tilt_x_deg: f64,
    axis_tilt_y_deg: f64,
    zero_deg: f64,
    top_tilt_x_deg: f64,
    top_tilt_y_deg: f64,
}

#[derive(Debug, Clone, Copy, serde::Serialize, serde::Deserialize)]
struct OffsetJson {
    translation_mm: [f64; 3],
    rotation_deg: [f64; 3],
}

fn v3(v: [f64; 3]) -> Option<types::Vec3> {
    Some(types::Vec3 { x: v[0], y: v[1], z: v[2] })
}

fn v3_of(v: Option<types::Vec3>) -> [f64; 3] {
    v.map_or([0.0; 3], |v| [v.x, v.y, v.z])
}

/// A stored calibration on the wire.
fn calibration_to_wire(rec: &crate::store::CalibrationRecord) -> Result<scan::CellCalibration, StageError> {
    let c: CalibrationJson = serde_json::from_str(&rec.calibration_json).map_err(|e| {
        StageError::new(ErrorCode::Internal, format!("stored calibration {} is corrupt: {e}", rec.id))
    })?;
    let t = c.table;
    Ok(scan::CellCalibration {
        id: rec.id.clone(),
        version: u32::try_from(rec.version).unwrap_or(u32::MAX),
        table: Some(scan::TableModel {
            axis_x_mm: t.axis_x_mm,
            axis_y_mm: t.axis_y_mm,
            top_z_mm: t.top_z_mm,
            axis_tilt_x_deg: t.axis_tilt_x_deg,
            axis_tilt_y_deg: t.axis_tilt_y_deg,
            zero_deg: t.zero_deg,
            top_tilt_x_deg: t.top_tilt_x_deg,
            top_tilt_y_deg: t.top_tilt_y_deg,
        }),
        scanner_mount: Some(scan::RigidOffset {
            translation_mm: v3(c.scanner_mount.translation_mm),
            rotation_deg: v3(c.scanner_mount.rotation_deg),
        }),
        report_json: rec.report_json.clone(),
    })
}

/// A wire calibration as the stored JSON.
fn calibration_json_of(c: &scan::CellCalibration) -> Result<String, StageError> {
    let t = c.table.unwrap_or_default();
    let m = c.scanner_mount.unwrap_or_default();
    let j = CalibrationJson {
        table: TableJson {
            axis_x_mm: t.axis_x_mm,
            axis_y_mm: t.axis_y_mm,
            top_z_mm: t.top_z_mm,
            axis_tilt_x_deg: t.axis_tilt_x_deg,
            axis_tilt_y_deg: t.axis_tilt_y_deg,
            zero_deg: t.zero_deg,
            top_tilt_x_deg: t.top_tilt_x_deg,
            top_tilt_y_deg: t.top_tilt_y_deg,
        },
        scanner_mount: OffsetJson {
            translation_mm: v3_of(m.translation_mm),
            rotation_deg: v3_of(m.rotation_deg),
        },
    };
    serde_json::to_string(&j)
        .map_err(|e| StageError::new(ErrorCode::Internal, format!("encoding the calibration: {e}")))
}

/// A failed stage call, classified.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{message}")]
pub struct StageError {
    pub code: ErrorCode,
    pub message: String,
}

impl StageError {
    pub fn new(code: ErrorCode, message: impl Into<String>) -> Self {
        Self { code, message: message.into() }
    }

    fn from_status(stage: Stage, status: &tonic::Status) -> Self {
        let code = match status.code() {
            // Made here from a transport error (a status the service sent has no source): the
            // connection broke mid-call, the instance died or restarted, or the balancer dropped
            // an instance that failed its health check (its calls end as CANCELLED, h2's reset,
            // though no one cancelled the job). Another attempt may work.
            tonic::Code::Unknown | tonic::Code::Internal | tonic::Code::Cancelled
                if std::error::Error::source(status).is_some() =>
            {
                ErrorCode::Unavailable
            }
            code => ErrorCode::from_grpc(code),
        };
        let message = match code {
            ErrorCode::StageNotAvailable if status.message().starts_with("stage not available") => {
                status.message().to_string()
            }
            ErrorCode::StageNotAvailable => format!("stage not available: {}", status.message()),
            _ => format!("{stage} service answered {:?}: {}", status.code(), status.message()),
        };
        Self { code, message }
    }
}

/// Progress reports from a running stage: fraction of the stage done (0..=1) and a message.
pub type ProgressFn<'a> = &'a (dyn Fn(f64, &str) + Send + Sync);

/// Runs stages on the services that provide them.
#[async_trait::async_trait]
pub trait StageRunner: Send + Sync + 'static {
    /// Runs one attempt of `call.stage`, within `deadline`.
    async fn run(
        &self,
        call: &StageCall,
        deadline: Duration,
        progress: ProgressFn<'_>,
    ) -> Result<StageOutputs, StageError>;
    /// Tells the service running `stage` for `job_id` to stop. True when it was running it.
    async fn cancel(&self, stage: Stage, job_id: &str) -> Result<bool, StageError>;
    /// Asks the services that own sections of `spec` to check them before the job is accepted
    /// (the scanning service its `scan` section, the reconstruction service its `reconstruct`
    /// section, the CAM service its `plan` section). `Err` names the first field a service refuses. A service that cannot be asked
    /// (not configured, down, slow past [`CHECK_PARAMS_TIMEOUT`], or too old to know the call)
    /// is skipped: the stage checks the same values when it starts, before any work, and fails
    /// the job naming the field. The machine service checks the `execute` section.
    async fn check_params(&self, spec: &JobSpec) -> Result<(), SpecError>;
    /// Asks the machine service whether a part of `part_size_mm` (mm) fits the travel of the
    /// job's machine; `Err` with field `input` and both sizes when it does not. Skipped like
    /// [`StageRunner::check_params`] when the service cannot be asked.
    async fn check_part(&self, spec: &JobSpec, part_size_mm: [f64; 3]) -> Result<(), SpecError>;
    /// The CAM service's tool library (the built-in tools and its `tools_dir`), by name.
    async fn list_tools(&self) -> Result<Vec<ToolSummary>, StageError>;
    /// The CAM service's cutting table.
    async fn list_materials(&self) -> Result<Vec<MaterialSummary>, StageError>;
    /// The machine service's profiles and the materials of its cutting model.
    async fn list_machines(&self) -> Result<(Vec<MachineSummary>, Vec<String>), StageError>;
    /// Runs the scanning cell's calibration routine; `current` is the calibration in force (the
    /// calibration scans are placed with it and the report compares).
    async fn calibrate(
        &self,
        run_id: &str,
        params: &CalibrationParams,
        current: Option<&crate::store::CalibrationRecord>,
        deadline: Duration,
    ) -> Result<CalibrationRun, StageError>;
}

/// A work material, as `GET /v1/materials` lists it.
#[derive(Debug, Clone, PartialEq, serde::Serialize, utoipa::ToSchema)]
pub struct MaterialSummary {
    /// The name a job's `plan.stock.material` and `execute.material` use, e.g. `aluminium`.
    pub name: String,
    /// Surface speed the CAM's feeds and speeds start from, m/min.
    pub surface_speed_m_min: f64,
    /// Flood coolant (M8) when cutting it.
    pub coolant: bool,
    /// Other spellings accepted for it.
    pub aliases: Vec<String>,
    /// Whether the machine's cutting-force model knows it (an `execute` stage can cut it);
    /// absent when the machine service could not be asked.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub simulated: Option<bool>,
}

/// Travel of one axis: mm for X, Y, Z; degrees for A and C (`min = max = 0`: continuous).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, utoipa::ToSchema)]
pub struct Travel {
    pub min: f64,
    pub max: f64,
}

/// A machine profile, as `GET /v1/machines` lists it.
#[derive(Debug, Clone, PartialEq, serde::Serialize, utoipa::ToSchema)]
pub struct MachineSummary {
    /// The name a job's `execute.machine` uses, e.g. `emco-f1`.
    pub name: String,
    pub description: String,
    pub x: Travel,
    pub y: Travel,
    pub z: Travel,
    pub a: Travel,
    /// The C table of a table-table machine; absent on a 4-axis one.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub c: Option<Travel>,
    pub feed_min_mm_min: f64,
    pub feed_max_mm_min: f64,
    pub rapid_mm_min: f64,
    pub rpm_min: f64,
    pub rpm_max: f64,
    pub spindle_power_w: f64,
}

/// A tool of the CAM service's library, as `GET /v1/tools` lists it.
#[derive(Debug, Clone, PartialEq, serde::Serialize, utoipa::ToSchema)]
pub struct ToolSummary {
    /// The name a job's `plan` section uses, e.g. `ball-6`.
    pub name: String,
    /// `flat`, `ball`, `bull` or `v`.
    pub kind: String,
    pub diameter_mm: f64,
    /// Length of the flutes.
    pub cutting_length_mm: f64,
}

/// The first violation of a `ValidateParams` answer, or `Ok` when the service could not be asked.
fn first_violation(
    service: &'static str,
    answer: Result<tonic::Response<types::ValidateParamsResponse>, tonic::Status>,
) -> Result<(), SpecError> {
    match answer {
        Ok(r) => match r.into_inner().violations.into_iter().next() {
            None => Ok(()),
            Some(v) => Err(SpecError { field: v.field, message: v.message }),
        },
        Err(status) => {
            tracing::warn!(
                service,
                code = ?status.code(),
                message = status.message(),
                "parameter check skipped: the stage will check when it starts"
            );
            Ok(())
        }
    }
}

/// Service endpoints (URLs such as `http://127.0.0.1:50053`). An empty URL means the deployment has
/// no such service: its stage fails with `stage_not_available`. A key left out keeps its default
/// (the service's default port on loopback).
#[derive(Debug, Clone, serde::Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct Endpoints {
    pub scanning: String,
    pub reconstruction: String,
    pub cam: String,
    pub machine: String,
    /// With several instances of a service (URLs separated by commas): how often each is
    /// health-checked, in milliseconds; one that fails is not called until it passes again.
    pub health_interval_ms: u64,
    /// Shared secret sent with every call to a stage service (`authorization: Bearer <token>`),
    /// the `service_token` the services are configured with. Unset: none sent.
    pub token: Option<String>,
}

impl Default for Endpoints {
    fn default() -> Self {
        Self {
            scanning: "http://127.0.0.1:50051".into(),
            reconstruction: "http://127.0.0.1:50052".into(),
            cam: "http://127.0.0.1:50053".into(),
            machine: "http://127.0.0.1:50054".into(),
            health_interval_ms: 2000,
            token: None,
        }
    }
}

impl Endpoints {
    /// No stage service at all: every stage but the report fails with `stage_not_available`.
    pub fn none() -> Self {
        Self {
            scanning: String::new(),
            reconstruction: String::new(),
            cam: String::new(),
            machine: String::new(),
            ..Self::default()
        }
    }
}

/// [`StageRunner`] over tonic clients. Channels connect lazily, so start-up order does not matter
/// and a service that comes back after a restart is reached again.
#[derive(Clone)]
pub struct GrpcStages {
    scanning: Option<ServiceChannels>,
    reconstruction: Option<ServiceChannels>,
    cam: Option<ServiceChannels>,
    machine: Option<ServiceChannels>,
    /// `Bearer <service token>`, sent with every call.
    authorization: Option<tonic::metadata::MetadataValue<tonic::metadata::Ascii>>,
}

/// An endpoint URL that cannot be used.
#[derive(Debug, thiserror::Error)]
#[error("invalid {service} endpoint '{url}'")]
pub struct EndpointError {
    service: &'static str,
    url: String,
    #[source]
    source: Box<dyn std::error::Error + Send + Sync>,
}

/// The channels to one stage service.
#[derive(Clone)]
struct ServiceChannels {
    /// Stage calls: the one instance, or the instances balanced with health checks.
    calls: Channel,
    /// Each instance alone: `CancelStage` goes to every one, since only the instance running the
    /// stage knows it.
    instances: Vec<Channel>,
}

/// The channels to a service at `urls`: none when empty, one lazily connected endpoint, or several
/// instances (comma-separated) balanced with health checks every `health_interval`.
fn channel(
    service: &'static str,
    urls: &str,
    health_interval: Duration,
) -> Result<Option<ServiceChannels>, EndpointError> {
    let mut endpoints = Vec::new();
    for url in urls.split(',').map(str::trim).filter(|u| !u.is_empty()) {
        let endpoint = Channel::from_shared(url.to_string())
            .map_err(|e| EndpointError { service, url: url.to_string(), source: Box::new(e) })?
            .connect_timeout(Duration::from_secs(5))
            .tcp_nodelay(true);
        endpoints.push(endpoint);
    }
    let instances: Vec<Channel> = endpoints.iter().map(Endpoint::connect_lazy).collect();
    Ok(match endpoints.len() {
        0 => None,
        1 => Some(ServiceChannels { calls: instances[0].clone(), instances }),
        _ => Some(ServiceChannels {
            calls: crate::balance::balanced(service, endpoints, health_interval),
            instances,
        }),
    })
}

impl GrpcStages {
    /// Channels to the services; needs a tokio runtime when a service lists several instances.
    pub fn new(endpoints: &Endpoints) -> Result<Self, EndpointError> {
        let every = Duration::from_millis(endpoints.health_interval_ms.clamp(50, 3_600_000));
        let authorization = match endpoints.token.as_deref().filter(|t| !t.is_empty()) {
            Some(token) => Some(format!("Bearer {token}").parse().map_err(|e| EndpointError {
                service: "every",
                url: "(services.token)".into(),
                source: Box::new(e),
            })?),
            None => None,
        };
        Ok(Self {
            authorization,
            scanning: channel("scanning", &endpoints.scanning, every)?,
            reconstruction: channel("reconstruction", &endpoints.reconstruction, every)?,
            cam: channel("cam", &endpoints.cam, every)?,
            machine: channel("machine", &endpoints.machine, every)?,
        })
    }

    fn channel_for(&self, stage: Stage) -> Result<Channel, StageError> {
        let (ch, service) = match stage {
            Stage::Scan => (&self.scanning, "scanning"),
            Stage::Reconstruct => (&self.reconstruction, "reconstruction"),
            Stage::Plan => (&self.cam, "cam"),
            Stage::Execute => (&self.machine, "machine"),
            Stage::Report => {
                return Err(StageError::new(
                    ErrorCode::Internal,
                    "the report stage runs in the orchestrator",
                ));
            }
        };
        ch.as_ref().map(|c| c.calls.clone()).ok_or_else(|| {
            StageError::new(
                ErrorCode::StageNotAvailable,
                format!("stage not available: no {service} service is configured for the {stage} stage"),
            )
        })
    }
}

fn context(call: &StageCall) -> Option<types::StageContext> {
    Some(types::StageContext { job_id: call.job_id.clone(), attempt: call.attempt })
}

fn need(call: &StageCall, name: &str) -> Result<types::ArtifactRef, StageError> {
    call.artifacts.get(name).cloned().map(Into::into).ok_or_else(|| {
        StageError::new(
            ErrorCode::Internal,
            format!("the {} stage needs a {name} artifact, none was produced", call.stage),
        )
    })
}

impl GrpcStages {
    /// A call to a stage service: its deadline and the service token.
    fn request<T>(&self, msg: T, deadline: Duration) -> tonic::Request<T> {
        let mut req = tonic::Request::new(msg);
        req.set_timeout(deadline);
        if let Some(auth) = &self.authorization {
            req.metadata_mut().insert("authorization", auth.clone());
        }
        req
    }
}

/// Keeps what the stage's service said (bounded: [`StageOutputs::set_diagnostics`]).
fn keep_diagnostics(out: &mut StageOutputs, diagnostics: Vec<types::Diagnostic>) {
    out.set_diagnostics(diagnostics.into_iter().map(|d| (d.code, d.message)));
}

fn put(out: &mut StageOutputs, name: &str, a: Option<types::ArtifactRef>) {
    if let Some(a) = a {
        out.artifacts.insert(name.to_string(), a.into());
    }
}

/// Drains a stage's update stream: reports progress, returns the one result.
async fn drain<U, R>(
    stage: Stage,
    mut stream: tonic::Streaming<U>,
    progress: ProgressFn<'_>,
    split: impl Fn(U) -> Option<Result<R, types::Progress>>,
) -> Result<R, StageError> {
    loop {
        match stream.message().await {
            Ok(Some(update)) => match split(update) {
                Some(Ok(result)) => return Ok(result),
                Some(Err(p)) => progress(p.fraction, &p.message),
                None => {}
            },
            Ok(None) => {
                return Err(StageError::new(
                    ErrorCode::Unavailable,
                    format!("{stage} service closed its stream without a result"),
                ));
            }
            Err(status) => return Err(StageError::from_status(stage, &status)),
        }
    }
}

impl GrpcStages {
    /// The machine service's `ValidateParams` on the job's execute section and the part's size.
    async fn ask_machine(&self, spec: &JobSpec, part_size_mm: Option<[f64; 3]>) -> Result<(), SpecError> {
        let Some(ch) = &self.machine else { return Ok(()) };
        let mut client = machine::machine_service_client::MachineServiceClient::new(ch.calls.clone());
        let msg = machine::ValidateExecuteRequest {
            params: Some(convert::execute_params_for_job(spec)),
            part_size_mm: part_size_mm.map(|[x, y, z]| types::Vec3 { x, y, z }),
        };
        let answer = client.validate_params(self.request(msg, CHECK_PARAMS_TIMEOUT)).await;
        first_violation("machine", answer)
    }
}

#[async_trait::async_trait]
impl StageRunner for GrpcStages {
    async fn check_params(&self, spec: &JobSpec) -> Result<(), SpecError> {
        if let (Some(p), Some(ch)) = (&spec.scan, &self.scanning) {
            let mut client = scan::scanning_service_client::ScanningServiceClient::new(ch.calls.clone());
            let answer =
                client.validate_params(self.request(convert::scan_params(p), CHECK_PARAMS_TIMEOUT)).await;
            first_violation("scanning", answer)?;
        }
        if let (Some(p), Some(ch)) = (&spec.reconstruct, &self.reconstruction) {
            let mut client =
                rec::reconstruction_service_client::ReconstructionServiceClient::new(ch.calls.clone());
            let answer = client
                .validate_params(self.request(convert::reconstruct_params(p), CHECK_PARAMS_TIMEOUT))
                .await;
            first_violation("reconstruction", answer)?;
        }
        if let (Some(_), Some(ch)) = (&spec.plan, &self.cam) {
            let mut client = cam::cam_service_client::CamServiceClient::new(ch.calls.clone());
            let answer = client
                .validate_params(self.request(convert::plan_params_for_job(spec), CHECK_PARAMS_TIMEOUT))
                .await;
            first_violation("cam", answer)?;
        }
        if let (true, Some(ch)) = (spec.is_robot(), &self.cam) {
            let mut client = cam::cam_service_client::CamServiceClient::new(ch.calls.clone());
            let params = convert::robot_params(&spec.robot.clone().unwrap_or_default());
            let answer = client.validate_robot_params(self.request(params, CHECK_PARAMS_TIMEOUT)).await;
            first_violation("cam", answer)?;
        }
        // A robot job's execute section is its dexel cell alone, checked with the spec.
        if spec.execute.is_some() && !spec.is_robot() {
            self.ask_machine(spec, None).await?;
        }
        Ok(())
    }

    async fn check_part(&self, spec: &JobSpec, part_size_mm: [f64; 3]) -> Result<(), SpecError> {
        self.ask_machine(spec, Some(part_size_mm)).await
    }

    async fn run(
        &self,
        call: &StageCall,
        deadline: Duration,
        progress: ProgressFn<'_>,
    ) -> Result<StageOutputs, StageError> {
        let stage = call.stage;
        let channel = self.channel_for(stage)?;
        let status = |s: tonic::Status| StageError::from_status(stage, &s);
        let work = async {
            let mut out = StageOutputs::default();
            match stage {
                Stage::Scan => {
                    let msg = scan::ScanPartRequest {
                        context: context(call),
                        mesh: Some(need(call, "mesh")?),
                        params: Some(convert::scan_params(&call.spec.scan.clone().unwrap_or_default())),
                        units: convert::input_units(call.spec.input.units) as i32,
                        calibration: call.calibration.as_ref().map(calibration_to_wire).transpose()?,
                        calibrate: call.calibrate_in_scan.then(scan::CalibrationParams::default),
                    };
                    let mut client = scan::scanning_service_client::ScanningServiceClient::new(channel);
                    let stream =
                        client.scan_part(self.request(msg, deadline)).await.map_err(status)?.into_inner();
                    let r = drain(stage, stream, progress, |u| match u.update? {
                        scan::scan_part_update::Update::Progress(p) => Some(Err(p)),
                        scan::scan_part_update::Update::Result(r) => Some(Ok(r)),
                    })
                    .await?;
                    put(&mut out, "point_cloud", r.point_cloud);
                    keep_diagnostics(&mut out, r.diagnostics);
                    put(&mut out, "scan_report", r.report);
                    put(&mut out, "free_space", r.free_space);
                    out.metrics.insert("scan_points".into(), r.points as f64);
                    out.metrics.insert("scan_frames".into(), r.frames as f64);
                    out.metrics.insert("scan_time_s".into(), r.scan_time_s);
                    out.metrics.insert("scan_coverage_pct".into(), r.coverage_pct);
                    out.metrics.insert("scan_registration_rms_mm".into(), r.registration_rms_mm);
                    out.metrics.insert("scan_registration_merge_rms_mm".into(), r.registration_merge_rms_mm);
                    if let Some(c) = &r.new_calibration {
                        out.calibration_made = Some(crate::domain::job::CalibrationMade {
                            calibration_json: calibration_json_of(c)?,
                            report_json: r.new_calibration_report_json.clone(),
                        });
                    }
                    if r.calibration_version > 0 {
                        out.metrics
                            .insert("scan_calibration_version".into(), f64::from(r.calibration_version));
                    }
                    if let Some(pct) = r.silhouette_coverage_pct {
                        out.metrics.insert("scan_silhouette_coverage_pct".into(), pct);
                    }
                }
                Stage::Reconstruct => {
                    let input = need(call, "point_cloud").or_else(|_| need(call, "mesh"))?;
                    let msg = rec::BuildDepthMapsRequest {
                        context: context(call),
                        input: Some(input),
                        params: Some(convert::reconstruct_params(
                            &call.spec.reconstruct.clone().unwrap_or_default(),
                        )),
                        // The job's own input in its units; a scanned cloud is in millimetres.
                        units: if call.spec.first_stage() == Stage::Reconstruct {
                            convert::input_units(call.spec.input.units)
                        } else {
                            types::LengthUnit::Mm
                        } as i32,
                        free_space: call.artifacts.get("free_space").cloned().map(Into::into),
                    };
                    let mut client =
                        rec::reconstruction_service_client::ReconstructionServiceClient::new(channel);
                    let stream = client
                        .build_depth_maps(self.request(msg, deadline))
                        .await
                        .map_err(status)?
                        .into_inner();
                    let r = drain(stage, stream, progress, |u| match u.update? {
                        rec::build_depth_maps_update::Update::Progress(p) => Some(Err(p)),
                        rec::build_depth_maps_update::Update::Result(r) => Some(Ok(r)),
                    })
                    .await?;
                    put(&mut out, "reconstruct_report", r.report);
                    keep_diagnostics(&mut out, r.diagnostics);
                    for (i, f) in r.faces.into_iter().enumerate() {
                        // The first face's maps under the plain names, further faces suffixed `@<i>`.
                        let suffix = if i == 0 { String::new() } else { format!("@{i}") };
                        put(&mut out, &format!("depth_map{suffix}"), f.depth_map);
                        put(&mut out, &format!("coverage_map{suffix}"), f.coverage_map);
                        put(&mut out, &format!("roughing_map{suffix}"), f.roughing_map);
                        if i == 0 {
                            out.metrics.insert("coverage_pct".into(), f.coverage_pct);
                        }
                    }
                }
                Stage::Plan if call.spec.is_robot() => {
                    let msg = cam::PlanRobotRequest {
                        context: context(call),
                        mesh: Some(need(call, "mesh")?),
                        units: convert::input_units(call.spec.input.units) as i32,
                        params: Some(convert::robot_params(&call.spec.robot.clone().unwrap_or_default())),
                    };
                    let mut client = cam::cam_service_client::CamServiceClient::new(channel);
                    let stream =
                        client.plan_robot(self.request(msg, deadline)).await.map_err(status)?.into_inner();
                    let r = drain(stage, stream, progress, |u| match u.update? {
                        cam::plan_robot_update::Update::Progress(p) => Some(Err(p)),
                        cam::plan_robot_update::Update::Result(r) => Some(Ok(r)),
                    })
                    .await?;
                    put(&mut out, "gcode", r.gcode);
                    put(&mut out, "joint_trajectory", r.joint_trajectory);
                    keep_diagnostics(&mut out, r.diagnostics);
                    put(&mut out, "plan_report", r.plan_report);
                    out.metrics.insert("estimated_time_s".into(), r.estimated_time_s);
                    for (k, v) in [
                        ("robot_layers", r.layers),
                        ("robot_positions", r.positions),
                        ("robot_colliding_upright", r.colliding),
                        ("robot_tilted", r.tilted),
                        ("robot_blocked", r.blocked),
                        ("robot_unreachable_stretches", r.unreachable_stretches),
                    ] {
                        out.metrics.insert(k.into(), v as f64);
                    }
                    out.metrics.insert("robot_max_tilt_deg".into(), r.max_tilt_deg);
                }
                Stage::Plan => {
                    let mut faces = Vec::new();
                    let mut i = 0;
                    loop {
                        let suffix = if i == 0 { String::new() } else { format!("@{i}") };
                        let Some(map) = call.artifacts.get(&format!("depth_map{suffix}")) else { break };
                        faces.push(cam::FaceInput {
                            face: suffix.trim_start_matches('@').to_string(),
                            depth_map: Some(map.clone().into()),
                            roughing_map: call
                                .artifacts
                                .get(&format!("roughing_map{suffix}"))
                                .cloned()
                                .map(Into::into),
                        });
                        i += 1;
                    }
                    if faces.is_empty() {
                        need(call, "depth_map")?;
                    }
                    let msg = cam::PlanToolpathsRequest {
                        context: context(call),
                        faces,
                        params: Some(convert::plan_params_for_job(&call.spec)),
                        pixel_mm: call.spec.input.pixel_mm,
                        z_min_mm: call.spec.input.z_min_mm,
                        z_max_mm: call.spec.input.z_max_mm,
                    };
                    let mut client = cam::cam_service_client::CamServiceClient::new(channel);
                    let stream = client
                        .plan_toolpaths(self.request(msg, deadline))
                        .await
                        .map_err(status)?
                        .into_inner();
                    let r = drain(stage, stream, progress, |u| match u.update? {
                        cam::plan_toolpaths_update::Update::Progress(p) => Some(Err(p)),
                        cam::plan_toolpaths_update::Update::Result(r) => Some(Ok(r)),
                    })
                    .await?;
                    put(&mut out, "gcode", r.gcode);
                    put(&mut out, "toolpath_preview", r.toolpath_preview);
                    keep_diagnostics(&mut out, r.diagnostics);
                    // Further faces under the suffixes of their depth maps.
                    for (i, p) in r.face_previews.into_iter().enumerate() {
                        put(&mut out, &format!("toolpath_preview@{}", i + 1), Some(p));
                    }
                    put(&mut out, "plan_report", r.plan_report);
                    put(&mut out, "leftover_map", r.leftover_map);
                    out.metrics.insert("estimated_time_s".into(), r.estimated_time_s);
                    out.metrics.insert("plan_max_gouge_mm".into(), r.max_gouge_mm);
                    out.metrics.insert("plan_max_leftover_mm".into(), r.max_leftover_mm);
                    out.metrics.insert("plan_mean_leftover_mm".into(), r.mean_leftover_mm);
                }
                Stage::Execute if call.spec.is_robot() => {
                    let msg = machine::ExecuteRobotRequest {
                        context: context(call),
                        trajectory: Some(need(call, "joint_trajectory")?),
                        reference: Some(need(call, "mesh")?),
                        reference_units: convert::input_units(call.spec.input.units) as i32,
                        cell_mm: call.spec.execute.as_ref().and_then(|e| e.cell_mm),
                    };
                    let mut client = machine::machine_service_client::MachineServiceClient::new(channel);
                    let stream =
                        client.execute_robot(self.request(msg, deadline)).await.map_err(status)?.into_inner();
                    let r = drain(stage, stream, progress, |u| match u.update? {
                        machine::execute_robot_update::Update::Progress(p) => Some(Err(p)),
                        machine::execute_robot_update::Update::Result(r) => Some(Ok(r)),
                    })
                    .await?;
                    put(&mut out, "machined_part", r.part_mesh);
                    put(&mut out, "machined_part_view", r.part_view);
                    put(&mut out, "machine_report", r.machine_report);
                    out.metrics.insert("cycle_time_s".into(), r.cycle_time_s);
                    keep_diagnostics(&mut out, r.diagnostics);
                    out.metrics.insert("robot_removed_mm3".into(), r.removed_mm3);
                    out.metrics.insert("robot_rapid_removed_mm3".into(), r.rapid_removed_mm3);
                    if let Some(f) = r.against_part {
                        // The robot's part is measured against the original mesh only: those
                        // figures are the job's.
                        out.metrics.insert("original_points".into(), f.points as f64);
                        for (k, v) in part_figures(&f) {
                            out.metrics.insert(k.into(), v);
                            out.metrics.insert(format!("original_{k}"), v);
                        }
                    }
                }
                Stage::Execute => {
                    let multi_face = call.artifacts.contains_key("depth_map@1");
                    let msg = machine::ExecuteProgramRequest {
                        context: context(call),
                        gcode: Some(need(call, "gcode")?),
                        target_map: call.artifacts.get("depth_map").cloned().map(Into::into),
                        // Several faces: every face's map (the machine turns the A axis to each).
                        face_maps: if multi_face {
                            (0..)
                                .map_while(|i| {
                                    let key = if i == 0 {
                                        "depth_map".to_string()
                                    } else {
                                        format!("depth_map@{i}")
                                    };
                                    call.artifacts.get(&key).cloned().map(Into::into)
                                })
                                .collect()
                        } else {
                            Vec::new()
                        },
                        params: Some(convert::execute_params_for_job(&call.spec)),
                        // The original part a multi-axis part is measured against: the input mesh,
                        // else the cloud (the job's own in its units, a scanned one in millimetres).
                        reference: call
                            .artifacts
                            .get("mesh")
                            .or_else(|| call.artifacts.get("point_cloud"))
                            .cloned()
                            .map(Into::into),
                        reference_units: if call.artifacts.contains_key("mesh")
                            || call.spec.first_stage() == Stage::Reconstruct
                        {
                            convert::input_units(call.spec.input.units)
                        } else {
                            types::LengthUnit::Mm
                        } as i32,
                        pixel_mm: call.spec.input.pixel_mm,
                        z_min_mm: call.spec.input.z_min_mm,
                        z_max_mm: call.spec.input.z_max_mm,
                    };
                    let mut client = machine::machine_service_client::MachineServiceClient::new(channel);
                    let stream = client
                        .execute_program(self.request(msg, deadline))
                        .await
                        .map_err(status)?
                        .into_inner();
                    let r = drain(stage, stream, progress, |u| match u.update? {
                        machine::execute_program_update::Update::Progress(p) => Some(Err(p)),
                        machine::execute_program_update::Update::Telemetry(_) => None,
                        machine::execute_program_update::Update::Result(r) => Some(Ok(r)),
                    })
                    .await?;
                    put(&mut out, "final_stock", r.final_stock);
                    keep_diagnostics(&mut out, r.diagnostics);
                    put(&mut out, "deviation_map", r.deviation_map);
                    // Further faces under the suffixes of their depth maps.
                    for (i, f) in r.faces.into_iter().enumerate().skip(1) {
                        put(&mut out, &format!("final_stock@{i}"), f.final_stock);
                        put(&mut out, &format!("deviation_map@{i}"), f.deviation_map);
                    }
                    put(&mut out, "telemetry", r.telemetry);
                    put(&mut out, "telemetry_plot", r.telemetry_plot);
                    put(&mut out, "machine_report", r.machine_report);
                    put(&mut out, "machined_part", r.part_mesh);
                    put(&mut out, "machined_part_view", r.part_view);
                    if let Some(m) = r.metrics {
                        for (prefix, f) in [("original", &m.against_part), ("opened", &m.against_opened)] {
                            let Some(f) = f else { continue };
                            out.metrics.insert(format!("{prefix}_points"), f.points as f64);
                            for (k, v) in part_figures(f) {
                                out.metrics.insert(format!("{prefix}_{k}"), v);
                            }
                        }
                        if let Some(other) = m.cycle_time_other_s {
                            out.metrics.insert("cycle_time_other_policy_s".into(), other);
                        }
                        out.metrics.insert("removed_mm3".into(), m.removed_mm3);
                        let map_figures = [
                            ("max_gouge_mm", m.max_gouge_mm),
                            ("max_leftover_mm", m.max_leftover_mm),
                            ("mean_leftover_mm", m.mean_leftover_mm),
                            ("rms_deviation_mm", m.rms_deviation_mm),
                        ];
                        match (&m.against_part, multi_face) {
                            // A multi-face part is measured against the original part: those
                            // figures are the job's; the depth maps' (whose unseen cells hold
                            // assumed heights) keep a `map_` prefix.
                            (Some(f), true) => {
                                for (k, v) in map_figures {
                                    out.metrics.insert(format!("map_{k}"), v);
                                }
                                for (k, v) in part_figures(f) {
                                    out.metrics.insert(k.into(), v);
                                }
                            }
                            _ => {
                                for (k, v) in map_figures {
                                    out.metrics.insert(k.into(), v);
                                }
                            }
                        }
                        for (k, v) in [
                            ("cycle_time_s", m.cycle_time_s),
                            ("cycle_time_no_adaptive_s", m.cycle_time_no_adaptive_s),
                        ] {
                            out.metrics.insert(k.into(), v);
                        }
                    }
                }
                Stage::Report => unreachable_report()?,
            }
            Ok(out)
        };
        match tokio::time::timeout(deadline, work).await {
            Ok(r) => r,
            Err(_) => Err(StageError::new(
                ErrorCode::DeadlineExceeded,
                format!("{stage} stage did not finish within its deadline of {} s", deadline.as_secs_f64()),
            )),
        }
    }

    async fn list_tools(&self) -> Result<Vec<ToolSummary>, StageError> {
        let ch = self.channel_for(Stage::Plan)?;
        let mut client = cam::cam_service_client::CamServiceClient::new(ch);
        let answer = client
            .list_tools(self.request(cam::ListToolsRequest {}, CHECK_PARAMS_TIMEOUT))
            .await
            .map_err(|s| StageError::from_status(Stage::Plan, &s))?;
        let mut tools: Vec<ToolSummary> = answer
            .into_inner()
            .tools
            .into_iter()
            .map(|t| ToolSummary {
                name: t.name,
                kind: t.kind,
                diameter_mm: t.diameter_mm,
                cutting_length_mm: t.cutting_length_mm,
            })
            .collect();
        tools.sort_by(|a, b| a.name.cmp(&b.name));
        Ok(tools)
    }

    async fn list_materials(&self) -> Result<Vec<MaterialSummary>, StageError> {
        let ch = self.channel_for(Stage::Plan)?;
        let mut client = cam::cam_service_client::CamServiceClient::new(ch);
        let answer = client
            .list_materials(self.request(cam::ListMaterialsRequest {}, CHECK_PARAMS_TIMEOUT))
            .await
            .map_err(|s| StageError::from_status(Stage::Plan, &s))?;
        Ok(answer
            .into_inner()
            .materials
            .into_iter()
            .map(|m| MaterialSummary {
                name: m.name,
                surface_speed_m_min: m.surface_speed_m_min,
                coolant: m.coolant,
                aliases: m.aliases,
                simulated: None,
            })
            .collect())
    }

    async fn list_machines(&self) -> Result<(Vec<MachineSummary>, Vec<String>), StageError> {
        let ch = self.channel_for(Stage::Execute)?;
        let mut client = machine::machine_service_client::MachineServiceClient::new(ch);
        let answer = client
            .list_machines(self.request(machine::ListMachinesRequest {}, CHECK_PARAMS_TIMEOUT))
            .await
            .map_err(|s| StageError::from_status(Stage::Execute, &s))?
            .into_inner();
        let travel = |t: Option<machine::AxisTravel>| {
            let t = t.unwrap_or_default();
            Travel { min: t.min, max: t.max }
        };
        let machines = answer
            .machines
            .into_iter()
            .map(|m| MachineSummary {
                name: m.name,
                description: m.description,
                x: travel(m.x),
                y: travel(m.y),
                z: travel(m.z),
                a: travel(m.a),
                c: m.c.map(|c| Travel { min: c.min, max: c.max }),
                feed_min_mm_min: m.feed_min_mm_min,
                feed_max_mm_min: m.feed_max_mm_min,
                rapid_mm_min: m.rapid_mm_min,
                rpm_min: m.rpm_min,
                rpm_max: m.rpm_max,
                spindle_power_w: m.spindle_power_w,
            })
            .collect();
        Ok((machines, answer.materials))
    }

    async fn calibrate(
        &self,
        run_id: &str,
        params: &CalibrationParams,
        current: Option<&crate::store::CalibrationRecord>,
        deadline: Duration,
    ) -> Result<CalibrationRun, StageError> {
        let ch = self.channel_for(Stage::Scan)?;
        let mut client = scan::scanning_service_client::ScanningServiceClient::new(ch);
        let msg = scan::CalibrateCellRequest {
            context: Some(types::StageContext { job_id: run_id.to_string(), attempt: 0 }),
            params: Some(scan::CalibrationParams {
                table_angles_deg: params.table_angles_deg.clone().unwrap_or_default(),
                sphere_radius_mm: params.sphere_radius_mm,
                sphere_at_mm: params.sphere_at_mm.and_then(v3),
                line_spacing_mm: params.line_spacing_mm,
                seed: params.seed,
            }),
            current: current.map(calibration_to_wire).transpose()?,
        };
        let stream = client
            .calibrate_cell(self.request(msg, deadline))
            .await
            .map_err(|s| StageError::from_status(Stage::Scan, &s))?
            .into_inner();
        let r = drain(Stage::Scan, stream, &|_, _| {}, |u| match u.update? {
            scan::calibrate_cell_update::Update::Progress(p) => Some(Err(p)),
            scan::calibrate_cell_update::Update::Result(r) => Some(Ok(r)),
        })
        .await?;
        let cal = r.calibration.ok_or_else(|| {
            StageError::new(ErrorCode::Internal, "the scanning service returned no calibration")
        })?;
        Ok(CalibrationRun { calibration_json: calibration_json_of(&cal)?, report_json: r.report_json })
    }

    /// Asks every instance of the stage's service (only the one running the stage knows it):
    /// found when any found it; an error only when none could be asked.
    async fn cancel(&self, stage: Stage, job_id: &str) -> Result<bool, StageError> {
        let service = match stage {
            Stage::Scan => &self.scanning,
            Stage::Reconstruct => &self.reconstruction,
            Stage::Plan => &self.cam,
            Stage::Execute => &self.machine,
            Stage::Report => return Ok(false),
        };
        let Some(service) = service else { return Ok(false) };
        let answers = futures::future::join_all(
            service.instances.iter().map(|channel| self.cancel_on(channel.clone(), stage, job_id)),
        )
        .await;
        let (mut error, mut answered, mut found) = (None, 0, false);
        for answer in answers {
            match answer {
                Ok(f) => {
                    answered += 1;
                    found |= f;
                }
                Err(e) => {
                    tracing::warn!(%stage, job = job_id, error = %e, "an instance could not be asked to cancel");
                    error = Some(e);
                }
            }
        }
        match error {
            Some(e) if answered == 0 => Err(e),
            _ => Ok(found),
        }
    }
}

impl GrpcStages {
    async fn cancel_on(&self, channel: Channel, stage: Stage, job_id: &str) -> Result<bool, StageError> {
        let msg = types::CancelStageRequest { job_id: job_id.to_string() };
        let deadline = Duration::from_secs(5);
        let status = |s: tonic::Status| StageError::from_status(stage, &s);
        let r = match stage {
            Stage::Scan => scan::scanning_service_client::ScanningServiceClient::new(channel)
                .cancel_stage(self.request(msg, deadline))
                .await
                .map_err(status)?,
            Stage::Reconstruct => {
                rec::reconstruction_service_client::ReconstructionServiceClient::new(channel)
                    .cancel_stage(self.request(msg, deadline))
                    .await
                    .map_err(status)?
            }
            Stage::Plan => cam::cam_service_client::CamServiceClient::new(channel)
                .cancel_stage(self.request(msg, deadline))
                .await
                .map_err(status)?,
            Stage::Execute => machine::machine_service_client::MachineServiceClient::new(channel)
                .cancel_stage(self.request(msg, deadline))
                .await
                .map_err(status)?,
            Stage::Report => return Ok(false),
        };
        Ok(r.into_inner().found)
    }
}

fn unreachable_report() -> Result<(), StageError> {
    Err(StageError::new(ErrorCode::Internal, "the report stage runs in the orchestrator, not in a service"))
}

/// A part measured against a reference: its figures under the metric names they take.
fn part_figures(f: &machine::PartFigures) -> [(&'static str, f64); 4] {
    [
        ("max_gouge_mm", f.max_gouge_mm),
        ("max_leftover_mm", f.max_leftover_mm),
        ("mean_leftover_mm", f.mean_leftover_mm),
        ("rms_deviation_mm", f.rms_deviation_mm),
    ]
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A CANCELLED the service sent (a CancelStage took effect) ends the job as cancelled; one the
    /// client transport made (h2 reset: an instance left the balancer or died mid-call, nobody
    /// cancelled) is retried like any broken connection.
    #[test]
    fn a_cancel_made_by_the_transport_is_retried_and_one_sent_by_the_service_is_not() {
        let sent = tonic::Status::cancelled("the stage was cancelled");
        assert_eq!(StageError::from_status(Stage::Execute, &sent).code, ErrorCode::Cancelled);
        let mut local = tonic::Status::cancelled("operation was canceled");
        local.set_source(std::sync::Arc::new(std::io::Error::other("stream reset")));
        assert_eq!(StageError::from_status(Stage::Execute, &local).code, ErrorCode::Unavailable);
        let mut broken = tonic::Status::unknown("transport error");
        broken.set_source(std::sync::Arc::new(std::io::Error::other("connection reset")));
        assert_eq!(StageError::from_status(Stage::Reconstruct, &broken).code, ErrorCode::Unavailable);
        assert_eq!(
            StageError::from_status(Stage::Plan, &tonic::Status::internal("bug")).code,
            ErrorCode::Internal
        );
    }
}
