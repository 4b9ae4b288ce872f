//! tonic adapter of the reconstruction service: reads the cloud or mesh from the artifact store
//! (streaming, on a blocking thread), runs [`reconstruct`], streams progress and stores the maps
//! (16-bit PNG with depthmill metadata; the coverage map as 8-bit PNG) and a JSON report.

use std::io::BufReader;
use std::pin::Pin;
use std::sync::Arc;

use depthmill_common::artifacts::{ArtifactError, ArtifactStore, ObjectArtifactStore};
use depthmill_common::stage::StageRegistry;
use depthmill_geometry::{HeightMap, PngDepth};
use depthmill_proto::ErrorCode;
use depthmill_proto::reconstruction::v1 as pb;
use depthmill_proto::types::v1::{
    CancelStageRequest, CancelStageResponse, Diagnostic, FieldViolation, Progress, ValidateParamsResponse,
    Vec3,
};
use tokio::sync::mpsc;
use tonic::{Request, Response, Status};

use crate::domain::error::ReconError;
use crate::domain::face_choice::FaceChoiceOptions;
use crate::domain::pipeline::{
    FaceFrame, FaceOptions, FillOptions, FilterOptions, IntensityOptions, RadiusOptions, ReconstructOptions,
    RoiOptions, ScanSpace, StatisticalOptions, TableOptions, reconstruct_with_free_space,
};
use depthmill_geometry::formats::{FormatError, ReadLimits, read_any_from, read_ply_cloud_with_label};

pub(crate) const SERVICE_NAME: &str = "depthmill.reconstruction.v1.ReconstructionService";

struct ReconstructionServiceImpl {
    running: StageRegistry,
    store: Arc<ObjectArtifactStore>,
    limits: ReadLimits,
}

pub(crate) fn routes(store: ObjectArtifactStore, limits: ReadLimits) -> tonic::service::Routes {
    tonic::service::Routes::new(pb::reconstruction_service_server::ReconstructionServiceServer::new(
        ReconstructionServiceImpl { running: StageRegistry::default(), store: Arc::new(store), limits },
    ))
}

impl From<ReconError> for Status {
    fn from(e: ReconError) -> Self {
        let code = match &e {
            ReconError::Cancelled => ErrorCode::Cancelled,
            e if !e.is_invalid_input() => ErrorCode::Internal,
            _ => ErrorCode::InvalidArgument,
        };
        code.status(e.to_string())
    }
}

fn artifact_status(e: ArtifactError) -> Status {
    depthmill_common::artifacts::grpc_status(e)
}

fn vec3(v: &Vec3) -> [f64; 3] {
    [v.x, v.y, v.z]
}

/// Wire parameters -> the options of a job's `reconstruct` object.
pub(crate) fn options(p: pb::ReconstructParams) -> Result<ReconstructOptions, Status> {
    let faces = p
        .faces
        .iter()
        .enumerate()
        .map(|(i, f)| {
            let mut o = FaceOptions { origin: f.origin.as_ref().map(vec3), ..Default::default() };
            match &f.face {
                Some(pb::face_spec::Face::View(v)) => o.view = Some(v.clone()),
                Some(pb::face_spec::Face::ADeg(a)) => o.a_deg = Some(*a),
                Some(pb::face_spec::Face::Normal(n)) => o.normal = Some(vec3(n)),
                None => {
                    return Err(ErrorCode::InvalidArgument
                        .status(format!("reconstruct.faces[{i}]: give one of view, a_deg and normal")));
                }
            }
            Ok(o)
        })
        .collect::<Result<Vec<_>, Status>>()?;
    let fill = p.fill.map(|f| FillOptions {
        method: match pb::FillMethod::try_from(f.method) {
            Ok(pb::FillMethod::Idw) => Some("idw".into()),
            Ok(pb::FillMethod::Max) => Some("max".into()),
            _ => None,
        },
        max_hole_mm: f.max_hole_mm,
        radius_mm: f.radius_mm,
        power: f.power,
    });
    let filters = match p.filters {
        None => None,
        Some(f) => {
            let transform = depthmill_proto::convert::matrix4_row_major(&f.transform).map_err(|n| {
                ErrorCode::InvalidArgument.status(format!(
                    "reconstruct.filters.transform: needs 16 numbers (a row-major 4x4 matrix), got {n}"
                ))
            })?;
            Some(FilterOptions {
                intensity: f.intensity.map(|w| IntensityOptions { min: w.min, max: w.max }),
                voxel_mm: f.voxel_mm,
                statistical: f.statistical.map(|s| StatisticalOptions {
                    k: s.k as usize,
                    n_sigma: s.n_sigma,
                    keep_surface: s.keep_surface,
                }),
                radius: f.radius.map(|r| RadiusOptions {
                    radius_mm: r.radius_mm,
                    min_neighbours: r.min_neighbours as usize,
                }),
                transform,
                table: f.table.map(|t| TableOptions {
                    tolerance_mm: t.tolerance_mm,
                    largest_only: t.largest_only,
                    gap_mm: t.gap_mm,
                }),
            })
        }
    };
    Ok(ReconstructOptions {
        pixel_mm: p.pixel_mm,
        faces: if faces.is_empty() { None } else { Some(faces) },
        face_choice: p.face_choice.map(|c| FaceChoiceOptions {
            step_deg: c.step_deg,
            max_faces: c.max_faces,
            min_gain_pct: c.min_gain_pct,
            cell_mm: c.cell_mm,
            reach_radius_mm: c.reach_radius_mm,
            tolerance_mm: c.tolerance_mm,
        }),
        fill,
        roi: p.roi.map(|r| RoiOptions {
            x_min_mm: r.x_min_mm,
            y_min_mm: r.y_min_mm,
            x_max_mm: r.x_max_mm,
            y_max_mm: r.y_max_mm,
        }),
        margin_mm: p.margin_mm,
        z_min_mm: p.z_min_mm,
        z_max_mm: p.z_max_mm,
        filters,
        roughing_factor: p.roughing_factor,
        estimator: match pb::CellEstimator::try_from(p.estimator) {
            Ok(pb::CellEstimator::Unspecified) => None,
            Ok(pb::CellEstimator::Max) => Some("max".into()),
            Ok(pb::CellEstimator::Median) => Some("median".into()),
            Ok(pb::CellEstimator::MedianBilateral) => Some("median_bilateral".into()),
            Ok(pb::CellEstimator::Fit) => Some("fit".into()),
            Err(_) => {
                return Err(ErrorCode::InvalidArgument
                    .status(format!("reconstruct.estimator: unknown value {}", p.estimator)));
            }
        },
    })
}

/// The first problem BuildDepthMaps would find in the job's `reconstruct` section before reading
/// any input, named by its field in the job JSON.
pub(crate) fn check_params(p: pb::ReconstructParams) -> Option<FieldViolation> {
    let opts = match options(p) {
        Ok(o) => o,
        Err(status) => {
            return Some(FieldViolation { field: "reconstruct".into(), message: status.message().into() });
        }
    };
    match opts.resolve() {
        Ok(_) => None,
        Err(ReconError::InvalidParameter { field, value, reason }) => {
            Some(FieldViolation { field, message: format!("{reason} (got {value})") })
        }
        Err(other) => Some(FieldViolation { field: "reconstruct".into(), message: other.to_string() }),
    }
}

fn face_spec(frame: &FaceFrame) -> pb::FaceSpec {
    use depthmill_geometry::Face;
    let face = match frame.face {
        Face::A { angle_deg } => pb::face_spec::Face::ADeg(angle_deg),
        Face::Normal { x, y, z } => pb::face_spec::Face::Normal(Vec3 { x, y, z }),
        named => pb::face_spec::Face::View(named.to_string()),
    };
    pb::FaceSpec { face: Some(face), origin: frame.origin.map(|o| Vec3 { x: o.x, y: o.y, z: o.z }) }
}

type UpdateStream =
    Pin<Box<dyn tokio_stream::Stream<Item = Result<pb::BuildDepthMapsUpdate, Status>> + Send>>;

fn progress_update(fraction: f64, message: &str) -> pb::BuildDepthMapsUpdate {
    pb::BuildDepthMapsUpdate {
        update: Some(pb::build_depth_maps_update::Update::Progress(Progress {
            fraction,
            message: message.to_string(),
        })),
    }
}

fn png(map: &HeightMap, depth: PngDepth) -> Result<Vec<u8>, Status> {
    let mut out = Vec::new();
    depthmill_geometry::write_png_to(map, &mut out, depth)
        .map_err(|e| ErrorCode::Internal.status(format!("encoding a map failed: {e}")))?;
    Ok(out)
}

#[tonic::async_trait]
impl pb::reconstruction_service_server::ReconstructionService for ReconstructionServiceImpl {
    type BuildDepthMapsStream = UpdateStream;

    #[tracing::instrument(skip_all, fields(job_id))]
    async fn build_depth_maps(
        &self,
        request: Request<pb::BuildDepthMapsRequest>,
    ) -> Result<Response<Self::BuildDepthMapsStream>, Status> {
        let req = request.into_inner();
        let job_id = req.context.as_ref().map(|c| c.job_id.clone()).unwrap_or_default();
        tracing::Span::current().record("job_id", job_id.as_str());
        let input =
            req.input.ok_or_else(|| ErrorCode::InvalidArgument.status("input: an artifact is required"))?;
        let opts = options(req.params.unwrap_or_default())?;
        let units = depthmill_proto::convert::units(req.units)
            .map_err(|v| ErrorCode::InvalidArgument.status(format!("input.units: unknown unit {v}")))?;
        // Check the options before reading a possibly large file.
        opts.resolve()?;
        let stat = self.store.stat(&input.sha256).await.map_err(artifact_status)?.ok_or_else(|| {
            ErrorCode::InvalidArgument.status(format!("input: no artifact {}", input.sha256))
        })?;
        let path = self.store.local_file(&input.sha256).await.map_err(artifact_status)?;
        let name = format!("input {} ({})", &input.sha256[..12.min(input.sha256.len())], stat.media_type);
        // The scanner's free-space evidence, when the job's scan gave one.
        let free_path = match &req.free_space {
            Some(f) => Some(self.store.local_file(&f.sha256).await.map_err(|e| match e {
                ArtifactError::NotFound { .. } => {
                    ErrorCode::InvalidArgument.status(format!("free_space: no artifact {}", f.sha256))
                }
                other => artifact_status(other),
            })?),
            None => None,
        };
        let guard = self.running.start(&job_id);
        let (tx, rx) = mpsc::channel(32);
        let store = self.store.clone();
        let limits = self.limits.clone();
        let span = tracing::Span::current();
        tokio::spawn(async move {
            let token = guard.token().clone();
            let progress_tx = tx.clone();
            let _ = progress_tx.try_send(Ok(progress_update(0.0, "reading the input")));
            let worked = tokio::task::spawn_blocking(move || {
                span.in_scope(|| {
                    let file = std::fs::File::open(&path)
                        .map_err(|source| ReconError::from(FormatError::Io { file: name.clone(), source }))?;
                    let (mut geometry, stats) = read_any_from(
                        BufReader::with_capacity(1 << 20, file),
                        &name,
                        Some(stat.size),
                        &limits,
                    )
                    .map_err(ReconError::from)?;
                    let head = depthmill_geometry::units::read_head(&path)
                        .map_err(|source| ReconError::from(FormatError::Io { file: name.clone(), source }))?;
                    let units = depthmill_geometry::units::normalise(&mut geometry, &head, units);
                    if let Some(u) = &units {
                        tracing::info!(unit = %u.unit, source = u.source, "input units");
                    }
                    tracing::info!(points = stats.points, triangles = stats.triangles, "input read");
                    let progress = move |f: f64, m: &str| {
                        let _ = progress_tx.try_send(Ok(progress_update(0.1 + 0.8 * f, m)));
                    };
                    let cancelled = move || token.is_cancelled();
                    let free = match &free_path {
                        Some(p) => {
                            let fname = "free_space".to_string();
                            let file = std::fs::File::open(p).map_err(|source| {
                                ReconError::from(FormatError::Io { file: fname.clone(), source })
                            })?;
                            let (cloud, kind, _) = read_ply_cloud_with_label(
                                BufReader::with_capacity(1 << 20, file),
                                &fname,
                                depthmill_geometry::cloud::FREE_KIND,
                                &limits,
                            )
                            .map_err(ReconError::from)?;
                            Some(ScanSpace::from_labelled(cloud.points, kind)?)
                        }
                        None => None,
                    };
                    let mut out =
                        reconstruct_with_free_space(geometry, &opts, free.as_ref(), &progress, &cancelled)?;
                    out.report.units = units;
                    // Encode on this thread too; the async side only stores bytes.
                    let mut encoded = Vec::with_capacity(out.faces.len());
                    for f in &out.faces {
                        encoded.push((
                            png(&f.depth_map, PngDepth::Bits16)?,
                            png(&f.coverage_map, PngDepth::Bits8)?,
                            png(&f.roughing_map, PngDepth::Bits16)?,
                        ));
                    }
                    Ok::<_, Status>((stats, out, encoded))
                })
            })
            .await;
            let (stats, out, encoded) = match worked {
                Ok(Ok(v)) => v,
                Ok(Err(status)) => {
                    tracing::info!(error = %status.message(), "reconstruction failed");
                    let _ = tx.send(Err(status)).await;
                    return;
                }
                Err(e) => {
                    let _ = tx.send(Err(Status::internal(format!("reconstruction panicked: {e}")))).await;
                    return;
                }
            };
            let result = async {
                let mut faces = Vec::with_capacity(out.faces.len());
                for (f, (depth, cov, rough)) in out.faces.iter().zip(encoded) {
                    let c = &f.stats.coverage;
                    faces.push(pb::FaceMaps {
                        face: Some(face_spec(&f.face)),
                        depth_map: Some(store.put_bytes("image/png", &depth).await?.into()),
                        coverage_map: Some(store.put_bytes("image/png", &cov).await?.into()),
                        roughing_map: Some(store.put_bytes("image/png", &rough).await?.into()),
                        coverage_pct: c.covered_pct,
                        // What is still missing after filling: what a rescan should aim at.
                        largest_hole_mm2: c.largest_unfilled_hole.as_ref().map_or(0.0, |h| h.area_mm2),
                        holes: c.unfilled_holes as u64,
                        largest_hole_x_mm: c.largest_unfilled_hole.as_ref().map_or(0.0, |h| h.center_x_mm),
                        largest_hole_y_mm: c.largest_unfilled_hole.as_ref().map_or(0.0, |h| h.center_y_mm),
                        cells_filled: f.stats.fill.filled as u64,
                    });
                }
                let report_json = serde_json::to_vec_pretty(&out.report).unwrap_or_default();
                let report = store.put_bytes("application/json", &report_json).await?;
                let mut diagnostics = Vec::new();
                if let Some(u) = &out.report.units {
                    diagnostics.push(Diagnostic {
                        code: "units".into(),
                        message: format!("input read in {} ({}: {})", u.unit, u.source, u.reason),
                    });
                    if let Some(w) = &u.warning {
                        diagnostics.push(Diagnostic { code: "units_warning".into(), message: w.clone() });
                    }
                }
                if stats.dropped_non_finite > 0 {
                    diagnostics.push(Diagnostic {
                        code: "non_finite_points".into(),
                        message: format!(
                            "{} points with NaN or infinite coordinates dropped",
                            stats.dropped_non_finite
                        ),
                    });
                }
                for f in &out.faces {
                    if let Some(message) = &f.stats.warning {
                        diagnostics.push(Diagnostic { code: "face_mostly_assumed".into(), message: message.clone() });
                    }
                    if f.stats.unseen_filled > 0 {
                        diagnostics.push(Diagnostic { code: "unseen_filled".into(), message: f.stats.unseen_message() });
                    }
                }
                if let Some(fc) = &out.report.face_choice {
                    let faces: Vec<String> =
                        fc.chosen.iter().map(|c| format!("{} (+{:.1} %)", c.face, c.gain_pct)).collect();
                    diagnostics.push(Diagnostic {
                        code: "face_choice".into(),
                        message: format!(
                            "faces chosen from the shape: {}; {:.1} % of the surface reached, {:.1} % from no orientation",
                            faces.join(", "),
                            fc.covered_pct,
                            fc.unreached_pct
                        ),
                    });
                    for e in &fc.excluded {
                        diagnostics.push(Diagnostic {
                            code: "face_excluded".into(),
                            message: format!(
                                "face {} was left out of the choice: its map came out {:.1} % measured (the scan hardly saw the part from that side), so the faces were chosen again without it and nothing is cut blind from there",
                                e.face, e.measured_pct
                            ),
                        });
                    }
                    for d in fc.diagnostics() {
                        diagnostics.push(Diagnostic { code: "unreachable_surface".into(), message: d });
                    }
                }
                for r in &out.report.filters {
                    diagnostics.push(Diagnostic {
                        code: format!("filter_{}", r.filter),
                        message: format!("{}: kept {}, removed {}", r.filter, r.kept, r.removed),
                    });
                }
                Ok::<_, ArtifactError>(pb::BuildDepthMapsResult {
                    faces,
                    points_in: out.report.points_in as u64,
                    points_kept: out.report.points_kept as u64,
                    diagnostics,
                    report: Some(report.into()),
                })
            }
            .await;
            let msg = match result {
                Ok(r) => Ok(pb::BuildDepthMapsUpdate {
                    update: Some(pb::build_depth_maps_update::Update::Result(r)),
                }),
                Err(e) => Err(artifact_status(e)),
            };
            let _ = tx.send(msg).await;
            drop(guard);
        });
        Ok(Response::new(Box::pin(tokio_stream::wrappers::ReceiverStream::new(rx))))
    }

    async fn validate_params(
        &self,
        request: Request<pb::ReconstructParams>,
    ) -> Result<Response<ValidateParamsResponse>, Status> {
        let violations = check_params(request.into_inner()).into_iter().collect();
        Ok(Response::new(ValidateParamsResponse { violations }))
    }

    async fn cancel_stage(
        &self,
        request: Request<CancelStageRequest>,
    ) -> Result<Response<CancelStageResponse>, Status> {
        let found = self.running.cancel(&request.get_ref().job_id);
        Ok(Response::new(CancelStageResponse { found }))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn validate_params_names_the_field_as_the_job_json_does() {
        assert_eq!(check_params(pb::ReconstructParams::default()), None, "the defaults are valid");
        let view = pb::ReconstructParams {
            faces: vec![pb::FaceSpec { face: Some(pb::face_spec::Face::View("up".into())), origin: None }],
            ..Default::default()
        };
        let v = check_params(view).expect("refused");
        assert_eq!(v.field, "reconstruct.faces[0].view");
        assert!(v.message.contains("up"), "{}", v.message);
        let pixel = pb::ReconstructParams { pixel_mm: Some(-0.1), ..Default::default() };
        assert_eq!(check_params(pixel).expect("refused").field, "reconstruct.pixel_mm");
        // A value only the rasteriser knows is named under `reconstruct.` too.
        let fill = pb::ReconstructParams {
            fill: Some(pb::FillParams {
                method: pb::FillMethod::Idw as i32,
                power: Some(-1.0),
                ..Default::default()
            }),
            ..Default::default()
        };
        assert_eq!(check_params(fill).expect("refused").field, "reconstruct.fill.power");
        let face = pb::ReconstructParams { faces: vec![pb::FaceSpec::default()], ..Default::default() };
        let v = check_params(face).expect("refused");
        assert_eq!(v.field, "reconstruct");
        assert!(v.message.contains("reconstruct.faces[0]"), "{}", v.message);
    }
}
