//! tonic adapter of the cam service: reads depth maps from the artifact store, plans on a blocking
//! thread (rayon inside), streams progress, stores the program, report and preview.

use std::io::Cursor;
use std::pin::Pin;
use std::sync::Arc;

use depthmill_common::artifacts::{ArtifactError, ArtifactStore, ObjectArtifactStore};
use depthmill_common::stage::StageRegistry;
use depthmill_geometry::{HeightMap, ImageMapping, PngDepth};
use depthmill_proto::ErrorCode;
use depthmill_proto::cam::v1 as pb;
use depthmill_proto::types::v1::{CancelStageRequest, CancelStageResponse, Progress};
use tokio::sync::mpsc;
use tonic::{Request, Response, Status};

use crate::domain::CamError;
use crate::domain::feeds::MachineLimits;
use crate::domain::plan::{
    FaceInput, FinishingOptions, PlanOptions, RestOptions, RoughingOptions, StockOptions, plan,
};
use crate::domain::tool::ToolLibrary;

pub(crate) const SERVICE_NAME: &str = "depthmill.cam.v1.CamService";

/// Largest depth map accepted (bytes of the stored artifact).
const MAX_MAP_BYTES: u64 = 1 << 30;

struct CamServiceImpl {
    running: StageRegistry,
    store: Arc<ObjectArtifactStore>,
    library: Arc<ToolLibrary>,
}

pub(crate) fn routes(store: ObjectArtifactStore, library: ToolLibrary) -> tonic::service::Routes {
    let svc = CamServiceImpl {
        running: StageRegistry::default(),
        store: Arc::new(store),
        library: Arc::new(library),
    };
    tonic::service::Routes::new(pb::cam_service_server::CamServiceServer::new(svc))
}

impl From<CamError> for Status {
    fn from(e: CamError) -> Self {
        let code = match &e {
            CamError::InvalidParameter { .. }
            | CamError::InvalidTool { .. }
            | CamError::InvalidMap { .. }
            | CamError::HolderCollision { .. } => ErrorCode::InvalidArgument,
            CamError::Cancelled => ErrorCode::Cancelled,
            CamError::Io { .. } => ErrorCode::Internal,
        };
        code.status(e.to_string())
    }
}

fn artifact_status(e: ArtifactError) -> Status {
    depthmill_common::artifacts::grpc_status(e)
}

/// Decodes a stored depth map by its media type.
fn decode_map(
    bytes: Vec<u8>,
    media_type: &str,
    fallback: Option<&ImageMapping>,
    what: &str,
) -> Result<HeightMap, Status> {
    let map = match media_type {
        "image/png" => depthmill_geometry::read_png_from(Cursor::new(bytes), fallback),
        "application/x-npy" => depthmill_geometry::read_npy_from(Cursor::new(bytes), None, fallback),
        other => {
            return Err(ErrorCode::InvalidArgument
                .status(format!("{what}: a depth map is image/png or application/x-npy, got {other}")));
        }
    };
    map.map_err(|e| ErrorCode::InvalidArgument.status(format!("{what}: {e}")))
}

fn enum_name<T: TryFrom<i32> + std::fmt::Debug>(
    v: i32,
    names: fn(T) -> Option<&'static str>,
) -> Result<Option<String>, Status> {
    match T::try_from(v) {
        Ok(t) => Ok(names(t).map(str::to_string)),
        Err(_) => Err(ErrorCode::InvalidArgument.status(format!("unknown enum value {v}"))),
    }
}

/// The first problem of a job's plan section, named by its field; `None` when it is accepted.
pub(crate) fn check_params(
    p: pb::PlanParams,
    library: &ToolLibrary,
) -> Option<depthmill_proto::types::v1::FieldViolation> {
    let violation = |field: &str, message: String| depthmill_proto::types::v1::FieldViolation {
        field: field.into(),
        message,
    };
    let opts = match options(p) {
        Ok(o) => o,
        Err(status) => return Some(violation("plan", status.message().into())),
    };
    match crate::domain::plan::check_options(&opts, library, &MachineLimits::emco_f1()) {
        Ok(()) => None,
        Err(CamError::InvalidParameter { field, message }) => Some(violation(&field, message)),
        Err(other) => Some(violation("plan", other.to_string())),
    }
}

/// What the job should hear about the plan: how unnamed tools were chosen, each face's rest pass
/// (or why there is none) and the material no tool of the plan gets at, with where it is.
fn plan_diagnostics(r: &crate::domain::plan::PlanReport) -> Vec<depthmill_proto::types::v1::Diagnostic> {
    let d =
        |code: &str, message: String| depthmill_proto::types::v1::Diagnostic { code: code.into(), message };
    let mut out: Vec<_> = r.tool_choice.iter().map(|m| d("tool_choice", m.clone())).collect();
    for (i, f) in r.faces.iter().enumerate() {
        let face = i + 1;
        if let Some(rest) = &f.rest {
            out.push(d(
                "rest_finishing",
                format!(
                    "face {face}: {} went over {:.1} mm² where finishing left material: leftover max {:.3} -> {:.3} mm, mean {:.4} -> {:.4} mm",
                    rest.tool,
                    rest.region_mm2,
                    rest.max_leftover_before_mm,
                    f.max_leftover_mm,
                    rest.mean_leftover_before_mm,
                    f.mean_leftover_mm
                ),
            ));
        }
        if let Some(note) = &f.rest_note {
            out.push(d("rest_finishing", format!("face {face}: {note}")));
        }
        let smallest = f.operations.last().map_or("the finishing tool", |o| o.tool.as_str());
        for g in f.left_regions.iter().filter(|g| g.area_mm2 >= 1.0) {
            out.push(d(
                "material_left",
                format!(
                    "face {face}: {:.1} mm² around ({:.1}, {:.1}) mm stay up to {:.3} mm above the part: a feature narrower than {smallest} (or out of its reach)",
                    g.area_mm2, g.center_mm[0], g.center_mm[1], g.max_leftover_mm
                ),
            ));
        }
    }
    out
}

/// Wire parameters -> the plan options of a job request.
fn options(p: pb::PlanParams) -> Result<PlanOptions, Status> {
    Ok(PlanOptions {
        rest: p.rest.map(|r| RestOptions {
            enabled: r.enabled,
            tool: r.tool,
            min_leftover_mm: r.min_leftover_mm,
        }),
        stock: p.stock.map(|s| StockOptions {
            x_mm: s.x_mm,
            y_mm: s.y_mm,
            z_mm: s.z_mm,
            material: s.material,
        }),
        roughing: p
            .roughing
            .map(|r| -> Result<RoughingOptions, Status> {
                Ok(RoughingOptions {
                    tool: r.tool,
                    step_down_mm: r.step_down_mm,
                    stock_to_leave_mm: r.stock_to_leave_mm,
                    direction: enum_name::<pb::RasterDirection>(r.direction, |d| match d {
                        pb::RasterDirection::Unspecified => None,
                        pb::RasterDirection::X => Some("x"),
                        pb::RasterDirection::Y => Some("y"),
                        pb::RasterDirection::Contour => Some("contour"),
                    })?,
                })
            })
            .transpose()?,
        finishing: p
            .finishing
            .map(|f| -> Result<FinishingOptions, Status> {
                Ok(FinishingOptions {
                    tool: f.tool,
                    strategy: enum_name::<pb::FinishingStrategy>(f.strategy, |s| match s {
                        pb::FinishingStrategy::Unspecified => None,
                        pb::FinishingStrategy::RasterX => Some("raster_x"),
                        pb::FinishingStrategy::RasterY => Some("raster_y"),
                        pb::FinishingStrategy::RasterAngle => Some("raster_angle"),
                        pb::FinishingStrategy::IsoLevel => Some("iso_level"),
                    })?,
                    angle_deg: f.angle_deg,
                    step_over_mm: f.step_over_mm,
                    tolerance_mm: f.tolerance_mm,
                    arcs: f.arcs,
                    pixel_model: f.pixel_model.clone(),
                })
            })
            .transpose()?,
        dialect: enum_name::<pb::Dialect>(p.dialect, |d| match d {
            pb::Dialect::Unspecified => None,
            pb::Dialect::Linuxcnc => Some("linuxcnc"),
            pb::Dialect::Fanuc => Some("fanuc"),
        })?,
    })
}

fn face_angle(face: &str) -> Result<Option<f64>, Status> {
    let f = face.trim();
    if f.is_empty() || f == "+Z" || f.chars().all(|c| c.is_ascii_digit()) {
        return Ok(None);
    }
    match f.strip_prefix("A=").map(str::parse::<f64>) {
        Some(Ok(a)) if a.is_finite() => Ok(Some(a)),
        _ => Err(ErrorCode::InvalidArgument.status(format!("face '{face}' is not +Z or A=<degrees>"))),
    }
}

/// Faces without an explicit `A=` take their angle from the view recorded in the depth map:
/// `A=a` is `a`; with several faces `+Z`, `+Y`, `-Z`, `-Y` are 0, 90, 180, -90 (one program turns
/// the part between them) and a view the A axis cannot reach (`±X`, other normals) is an error.
/// A single named-view face is a plain 3-axis job (the part clamped with that face up).
fn resolve_angles(faces: &mut [FaceInput]) -> Result<(), Status> {
    use depthmill_geometry::Face;
    let several = faces.len() > 1;
    for (i, f) in faces.iter_mut().enumerate() {
        if f.a_deg.is_some() {
            continue;
        }
        let view = f.map.face();
        f.a_deg = match view {
            Face::A { angle_deg } => Some(angle_deg),
            _ if !several => None,
            Face::PosZ => Some(0.0),
            Face::PosY => Some(90.0),
            Face::NegZ => Some(180.0),
            Face::NegY => Some(-90.0),
            other => {
                return Err(ErrorCode::InvalidArgument.status(format!(
                    "faces[{i}]: the view {other} cannot be reached by turning the part about the A axis; \
                     plan it as a job of its own (the part re-clamped)"
                )));
            }
        };
    }
    Ok(())
}

type UpdateStream = Pin<Box<dyn tokio_stream::Stream<Item = Result<pb::PlanToolpathsUpdate, Status>> + Send>>;

fn progress_update(fraction: f64, message: &str) -> pb::PlanToolpathsUpdate {
    pb::PlanToolpathsUpdate {
        update: Some(pb::plan_toolpaths_update::Update::Progress(Progress {
            fraction,
            message: message.to_string(),
        })),
    }
}

type RobotStream = Pin<Box<dyn tokio_stream::Stream<Item = Result<pb::PlanRobotUpdate, Status>> + Send>>;

#[tonic::async_trait]
impl pb::cam_service_server::CamService for CamServiceImpl {
    type PlanToolpathsStream = UpdateStream;
    type PlanRobotStream = RobotStream;

    #[tracing::instrument(skip_all, fields(job_id))]
    async fn plan_robot(
        &self,
        request: Request<pb::PlanRobotRequest>,
    ) -> Result<Response<Self::PlanRobotStream>, Status> {
        let req = request.into_inner();
        let job_id = req.context.as_ref().map(|c| c.job_id.clone()).unwrap_or_default();
        tracing::Span::current().record("job_id", job_id.as_str());
        let call = crate::grpc_robot::RobotCall {
            store: self.store.clone(),
            library: self.library.clone(),
            guard: self.running.start(&job_id),
        };
        let rx = crate::grpc_robot::plan(req, call).await?;
        Ok(Response::new(Box::pin(tokio_stream::wrappers::ReceiverStream::new(rx))))
    }

    async fn validate_robot_params(
        &self,
        request: Request<pb::RobotParams>,
    ) -> Result<Response<depthmill_proto::types::v1::ValidateParamsResponse>, Status> {
        Ok(Response::new(depthmill_proto::types::v1::ValidateParamsResponse {
            violations: crate::grpc_robot::check(request.into_inner(), &self.library).into_iter().collect(),
        }))
    }

    #[tracing::instrument(skip_all, fields(job_id))]
    async fn plan_toolpaths(
        &self,
        request: Request<pb::PlanToolpathsRequest>,
    ) -> Result<Response<Self::PlanToolpathsStream>, Status> {
        let req = request.into_inner();
        let job_id = req.context.as_ref().map(|c| c.job_id.clone()).unwrap_or_default();
        tracing::Span::current().record("job_id", job_id.as_str());
        if req.faces.is_empty() {
            return Err(ErrorCode::InvalidArgument.status("faces: at least one depth map is needed"));
        }
        let fallback = req.pixel_mm.map(|p| ImageMapping {
            pixel_mm: p,
            z_min_mm: req.z_min_mm,
            z_max_mm: req.z_max_mm,
        });
        let mut faces = Vec::with_capacity(req.faces.len());
        for (i, f) in req.faces.iter().enumerate() {
            let load = |a: &depthmill_proto::types::v1::ArtifactRef, what: String| {
                let store = self.store.clone();
                let a = a.clone();
                async move {
                    let bytes = store.read_all(&a.sha256, MAX_MAP_BYTES).await.map_err(artifact_status)?;
                    let media = store
                        .stat(&a.sha256)
                        .await
                        .map_err(artifact_status)?
                        .map(|r| r.media_type)
                        .unwrap_or(a.media_type);
                    tokio::task::spawn_blocking(move || decode_map(bytes, &media, fallback.as_ref(), &what))
                        .await
                        .map_err(|e| Status::internal(format!("decoding failed: {e}")))?
                }
            };
            let map_ref = f.depth_map.as_ref().ok_or_else(|| {
                ErrorCode::InvalidArgument.status(format!("faces[{i}].depth_map is required"))
            })?;
            let map = load(map_ref, format!("faces[{i}].depth_map")).await?;
            let roughing_map = match &f.roughing_map {
                Some(r) => Some(load(r, format!("faces[{i}].roughing_map")).await?),
                None => None,
            };
            let explicit = face_angle(&f.face)?;
            faces.push(FaceInput { a_deg: explicit, map, roughing_map });
        }
        resolve_angles(&mut faces)?;
        let opts = options(req.params.unwrap_or_default())?;
        let guard = self.running.start(&job_id);
        let (tx, rx) = mpsc::channel(32);
        let library = self.library.clone();
        let store = self.store.clone();
        let span = tracing::Span::current();
        tokio::spawn(async move {
            let token = guard.token().clone();
            let progress_tx = tx.clone();
            let planned = tokio::task::spawn_blocking(move || {
                span.in_scope(|| {
                    let progress = move |f: f64, m: &str| {
                        let _ = progress_tx.try_send(Ok(progress_update(f, m)));
                    };
                    let cancelled = move || token.is_cancelled();
                    plan(&faces, &opts, &library, &MachineLimits::emco_f1(), &progress, &cancelled)
                })
            })
            .await;
            let out = match planned {
                Ok(Ok(out)) => out,
                Ok(Err(e)) => {
                    tracing::info!(error = %e, "planning failed");
                    let _ = tx.send(Err(Status::from(e))).await;
                    return;
                }
                Err(e) => {
                    let _ = tx.send(Err(Status::internal(format!("planning panicked: {e}")))).await;
                    return;
                }
            };
            let result = async {
                let gcode = store.put_bytes("text/x-gcode", out.gcode.as_bytes()).await?;
                let report_json = serde_json::to_vec_pretty(&out.report).unwrap_or_default();
                let report = store.put_bytes("application/json", &report_json).await?;
                let mut surface_png = Vec::new();
                let mut leftover_png = Vec::new();
                let encoded = depthmill_geometry::write_png_to(
                    &out.preview.final_surface,
                    &mut surface_png,
                    PngDepth::Bits16,
                )
                .and_then(|()| {
                    depthmill_geometry::write_png_to(
                        &out.preview.leftover,
                        &mut leftover_png,
                        PngDepth::Bits8,
                    )
                });
                let (preview, leftover) = match encoded {
                    Ok(()) => (
                        Some(store.put_bytes("image/png", &surface_png).await?.into()),
                        Some(store.put_bytes("image/png", &leftover_png).await?.into()),
                    ),
                    Err(e) => {
                        tracing::warn!(error = %e, "preview images not written");
                        (None, None)
                    }
                };
                let mut face_previews = Vec::with_capacity(out.later_surfaces.len());
                for surface in &out.later_surfaces {
                    let mut bytes = Vec::new();
                    match depthmill_geometry::write_png_to(surface, &mut bytes, PngDepth::Bits16) {
                        Ok(()) => face_previews.push(store.put_bytes("image/png", &bytes).await?.into()),
                        Err(e) => {
                            tracing::warn!(error = %e, "a face's preview image not written");
                            face_previews.clear();
                            break;
                        }
                    }
                }
                Ok::<_, ArtifactError>(pb::PlanToolpathsResult {
                    face_previews,
                    gcode: Some(gcode.into()),
                    toolpath_preview: preview,
                    plan_report: Some(report.into()),
                    estimated_time_s: out.report.estimated_time_s,
                    blocks: out.report.blocks as u64,
                    diagnostics: plan_diagnostics(&out.report),
                    leftover_map: leftover,
                    max_gouge_mm: out.preview.max_gouge_mm,
                    max_leftover_mm: out.preview.max_leftover_mm,
                    mean_leftover_mm: out.preview.mean_leftover_mm,
                })
            }
            .await;
            let msg = match result {
                Ok(r) => {
                    Ok(pb::PlanToolpathsUpdate { update: Some(pb::plan_toolpaths_update::Update::Result(r)) })
                }
                Err(e) => Err(artifact_status(e)),
            };
            let _ = tx.send(msg).await;
            drop(guard);
        });
        Ok(Response::new(Box::pin(tokio_stream::wrappers::ReceiverStream::new(rx))))
    }

    async fn cancel_stage(
        &self,
        request: Request<CancelStageRequest>,
    ) -> Result<Response<CancelStageResponse>, Status> {
        let found = self.running.cancel(&request.get_ref().job_id);
        Ok(Response::new(CancelStageResponse { found }))
    }

    async fn validate_params(
        &self,
        request: Request<pb::PlanParams>,
    ) -> Result<Response<depthmill_proto::types::v1::ValidateParamsResponse>, Status> {
        Ok(Response::new(depthmill_proto::types::v1::ValidateParamsResponse {
            violations: check_params(request.into_inner(), &self.library).into_iter().collect(),
        }))
    }

    async fn list_tools(
        &self,
        _request: Request<pb::ListToolsRequest>,
    ) -> Result<Response<pb::ListToolsResponse>, Status> {
        let tools = self
            .library
            .tools()
            .map(|t| pb::Tool {
                name: t.name.clone(),
                kind: t.kind.as_str().to_string(),
                diameter_mm: t.diameter_mm(),
                cutting_length_mm: t.cutting_length_mm,
            })
            .collect();
        Ok(Response::new(pb::ListToolsResponse { tools }))
    }

    async fn list_materials(
        &self,
        _request: Request<pb::ListMaterialsRequest>,
    ) -> Result<Response<pb::ListMaterialsResponse>, Status> {
        let materials = crate::domain::feeds::materials()
            .into_iter()
            .map(|m| pb::Material {
                name: m.name.to_string(),
                surface_speed_m_min: m.surface_speed_m_min,
                coolant: m.coolant,
                aliases: m.aliases.into_iter().map(str::to_string).collect(),
            })
            .collect();
        Ok(Response::new(pb::ListMaterialsResponse { materials }))
    }
}
