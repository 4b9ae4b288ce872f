//! The REST API (axum), exactly the contract of DESIGN.md §7, with its OpenAPI document generated
//! from the handlers (utoipa) at `/openapi.json` and Swagger UI at `/docs`.

mod artifacts;
mod calibrations;

pub use calibrations::parse_calibration_params;
mod console;
mod jobs;

use axum::Json;
use axum::extract::State;
use axum::http::{HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use depthmill_proto::ErrorCode;
use metrics_exporter_prometheus::PrometheusHandle;
use serde::Serialize;
use utoipa::{OpenApi, ToSchema};
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;
use utoipa_swagger_ui::SwaggerUi;

use crate::app::{ApiError, App};

/// The error body of every failed request.
#[derive(Serialize, ToSchema)]
pub struct ErrorBody {
    pub error: ErrorDetail,
}

/// What went wrong.
#[derive(Serialize, ToSchema)]
pub struct ErrorDetail {
    /// `invalid_argument`, `not_found`, `conflict`, `payload_too_large`, `unsupported_media_type`, `internal`, ...
    pub code: String,
    pub message: String,
    /// Dotted path of the offending field, e.g. `plan.finishing.step_over_mm`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub field: Option<String>,
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let status = self.code.http();
        if status.is_server_error() {
            tracing::warn!(code = %self.code, message = %self.message, "request failed");
        }
        let body = ErrorBody {
            error: ErrorDetail { code: self.code.as_str().into(), message: self.message, field: self.field },
        };
        let mut response = (status, Json(body)).into_response();
        if status == StatusCode::SERVICE_UNAVAILABLE {
            // A dependency is down: tell clients when to try again.
            response.headers_mut().insert(header::RETRY_AFTER, HeaderValue::from_static("2"));
        }
        response
    }
}

#[derive(OpenApi)]
#[openapi(
    info(title = "depthmill", description = "Scan-to-part jobs: upload a mesh, point cloud, depth map or G-code, submit a job, watch it, fetch its results."),
    tags((name = "jobs", description = "Scan-to-part jobs"), (name = "artifacts", description = "Content-addressed files"), (name = "calibrations", description = "Calibrations of the scanning cell"), (name = "catalog", description = "What a job can name: tools, materials, machines, strategies"), (name = "ops", description = "Health and metrics")),
    components(schemas(ErrorBody, ErrorDetail))
)]
struct ApiDoc;

/// The OpenAPI document of the REST API.
pub fn openapi() -> utoipa::openapi::OpenApi {
    router_parts().1
}

fn router_parts() -> (axum::Router<App>, utoipa::openapi::OpenApi) {
    OpenApiRouter::with_openapi(ApiDoc::openapi())
        .routes(routes!(jobs::create_job, jobs::list_jobs))
        .routes(routes!(jobs::get_job))
        .routes(routes!(jobs::cancel_job))
        .routes(routes!(jobs::job_events))
        .routes(routes!(jobs::job_report))
        .routes(routes!(artifacts::upload_artifact))
        .routes(routes!(artifacts::download_artifact))
        .routes(routes!(calibrations::create_calibration, calibrations::list_calibrations))
        .routes(routes!(calibrations::get_calibration))
        .routes(routes!(list_tools))
        .routes(routes!(list_materials))
        .routes(routes!(list_machines))
        .routes(routes!(list_strategies))
        .routes(routes!(healthz))
        .routes(routes!(readyz))
        .split_for_parts()
}

/// The REST router. `metrics` renders `/metrics` when the process installed a Prometheus recorder.
pub fn router(app: App, metrics: Option<PrometheusHandle>) -> axum::Router {
    let (router, api) = router_parts();
    let metrics_route = get(move || {
        let handle = metrics.clone();
        async move {
            match handle {
                Some(h) => (
                    [(header::CONTENT_TYPE, HeaderValue::from_static("text/plain; version=0.0.4"))],
                    h.render(),
                )
                    .into_response(),
                None => ApiError::new(ErrorCode::NotFound, "this process exports no metrics").into_response(),
            }
        }
    });
    router
        .route("/", get(console::index))
        .route("/console/{*path}", get(console::asset))
        .route("/metrics", metrics_route)
        .merge(SwaggerUi::new("/docs").url("/openapi.json", api))
        .fallback(|uri: axum::http::Uri| async move {
            ApiError::new(ErrorCode::NotFound, format!("no route for {}", uri.path()))
        })
        .layer(axum::middleware::from_fn_with_state(app.clone(), require_token))
        .layer(tower_http::trace::TraceLayer::new_for_http())
        .with_state(app)
}

/// Refuses a call under `/v1/` whose bearer token does not allow it (401 with
/// `WWW-Authenticate: Bearer`, or 403), when the server requires tokens.
/// Names the caller ([`crate::auth::Client`]) in the request's extensions for the handlers.
async fn require_token(
    State(app): State<App>,
    mut request: axum::extract::Request,
    next: axum::middleware::Next,
) -> Response {
    if let Some(scope) = crate::auth::rest_scope(request.method(), request.uri().path()) {
        let header = request.headers().get(header::AUTHORIZATION).and_then(|v| v.to_str().ok());
        match app.auth.check(header, scope, crate::app::now_ms()).await {
            Ok(token_id) => {
                let peer = request
                    .extensions()
                    .get::<axum::extract::ConnectInfo<std::net::SocketAddr>>()
                    .map(|c| c.0);
                if let Some(client) = crate::auth::Client::of(token_id, peer) {
                    request.extensions_mut().insert(client);
                }
            }
            Err(e) => {
                let mut response = e.into_response();
                if response.status() == StatusCode::UNAUTHORIZED {
                    response
                        .headers_mut()
                        .insert(header::WWW_AUTHENTICATE, HeaderValue::from_static("Bearer"));
                }
                return response;
            }
        }
    }
    next.run(request).await
}

/// The tools a job's `plan` section can name: the CAM service's library (built-in tools and its
/// `tools_dir`), sorted by name.
#[utoipa::path(get, path = "/v1/tools", tag = "catalog", responses(
    (status = 200, description = "the tool library", body = ToolList),
    (status = 501, description = "no CAM service is configured", body = ErrorBody),
    (status = 503, description = "the CAM service cannot be reached", body = ErrorBody)))]
async fn list_tools(State(app): State<App>) -> Result<Json<ToolList>, ApiError> {
    Ok(Json(ToolList { tools: app.list_tools().await? }))
}

/// `GET /v1/tools`.
#[derive(Serialize, ToSchema)]
pub struct ToolList {
    pub tools: Vec<crate::stages::ToolSummary>,
}

/// The work materials a job can name: the CAM service's cutting table, each marked with whether
/// the machine's cutting model knows it.
#[utoipa::path(get, path = "/v1/materials", tag = "catalog", responses(
    (status = 200, description = "the cutting table", body = MaterialList),
    (status = 501, description = "no CAM service is configured", body = ErrorBody),
    (status = 503, description = "the CAM service cannot be reached", body = ErrorBody)))]
async fn list_materials(State(app): State<App>) -> Result<Json<MaterialList>, ApiError> {
    Ok(Json(MaterialList { materials: app.list_materials().await? }))
}

/// `GET /v1/materials`.
#[derive(Serialize, ToSchema)]
pub struct MaterialList {
    pub materials: Vec<crate::stages::MaterialSummary>,
}

/// The machine profiles a job's `execute.machine` can name, with their travel and ranges.
#[utoipa::path(get, path = "/v1/machines", tag = "catalog", responses(
    (status = 200, description = "the machine profiles", body = MachineList),
    (status = 501, description = "no machine service is configured", body = ErrorBody),
    (status = 503, description = "the machine service cannot be reached", body = ErrorBody)))]
async fn list_machines(State(app): State<App>) -> Result<Json<MachineList>, ApiError> {
    Ok(Json(MachineList { machines: app.list_machines().await? }))
}

/// `GET /v1/machines`.
#[derive(Serialize, ToSchema)]
pub struct MachineList {
    pub machines: Vec<crate::stages::MachineSummary>,
}

/// One choice of a job section's strategy field.
#[derive(Serialize, ToSchema)]
pub struct Choice {
    /// The value the job request uses.
    pub name: &'static str,
    pub description: &'static str,
}

/// `GET /v1/strategies`.
#[derive(Serialize, ToSchema)]
pub struct StrategyList {
    /// `plan.roughing.direction`.
    pub roughing: Vec<Choice>,
    /// `plan.finishing.strategy`.
    pub finishing: Vec<Choice>,
    /// `execute.adaptive`.
    pub adaptive: Vec<Choice>,
    /// `plan.dialect`.
    pub dialects: Vec<Choice>,
}

fn strategies() -> StrategyList {
    let c = |name, description| Choice { name, description };
    StrategyList {
        roughing: vec![
            c("x", "raster clearing along X, level by level (default)"),
            c("y", "raster clearing along Y, level by level"),
            c("contour", "offset rings following each level's outline"),
        ],
        finishing: vec![
            c("raster_x", "ball-nose raster along X (default)"),
            c("raster_y", "ball-nose raster along Y"),
            c("raster_angle", "raster at plan.finishing.angle_deg"),
            c("iso_level", "constant-Z contours (waterline), for steep walls"),
        ],
        adaptive: vec![
            c("aco", "feed and spindle speed both adapt to the measured load (default)"),
            c("feed_only", "the feed adapts, the spindle speed stays as programmed"),
            c("off", "the program's feeds and speeds as written"),
        ],
        dialects: vec![
            c("linuxcnc", "LinuxCNC / RS-274NGC (default)"),
            c("fanuc", "Fanuc / EMCO WinNC style: O number, N words, G28 retracts"),
        ],
    }
}

/// The strategies and modes a job's `plan` and `execute` sections can choose, with what each does.
#[utoipa::path(get, path = "/v1/strategies", tag = "catalog", responses(
    (status = 200, description = "the choices", body = StrategyList)))]
async fn list_strategies() -> Json<StrategyList> {
    Json(strategies())
}

/// Liveness: the process serves requests.
#[utoipa::path(get, path = "/healthz", tag = "ops", responses((status = 200, description = "alive")))]
async fn healthz() -> &'static str {
    "ok"
}

/// Readiness: the job database answers.
#[utoipa::path(get, path = "/readyz", tag = "ops", responses(
    (status = 200, description = "ready"),
    (status = 503, description = "not ready: the job database cannot be reached (Retry-After)", body = ErrorBody),
    (status = 500, description = "not ready", body = ErrorBody)))]
async fn readyz(State(app): State<App>) -> Result<&'static str, ApiError> {
    app.ready().await?;
    Ok("ready")
}

pub(crate) fn created<T: Serialize>(body: T) -> Response {
    (StatusCode::CREATED, Json(body)).into_response()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::domain::spec::{AdaptiveMode, Dialect, FinishingStrategy, RoughingDirection};

    /// Every listed choice is a value the job request takes, and every value is listed.
    #[test]
    fn the_strategies_listed_are_the_job_request_s() {
        fn names<T: serde::de::DeserializeOwned>(choices: &[Choice]) -> Vec<T> {
            choices
                .iter()
                .map(|c| serde_json::from_value(serde_json::Value::from(c.name)).expect(c.name))
                .collect()
        }
        let s = strategies();
        assert_eq!(names::<RoughingDirection>(&s.roughing).len(), 3);
        assert_eq!(
            names::<FinishingStrategy>(&s.finishing),
            [
                FinishingStrategy::RasterX,
                FinishingStrategy::RasterY,
                FinishingStrategy::RasterAngle,
                FinishingStrategy::IsoLevel
            ]
        );
        assert_eq!(
            names::<AdaptiveMode>(&s.adaptive),
            [AdaptiveMode::Aco, AdaptiveMode::FeedOnly, AdaptiveMode::Off]
        );
        assert_eq!(names::<Dialect>(&s.dialects), [Dialect::Linuxcnc, Dialect::Fanuc]);
        // An exhaustive match: a new roughing direction fails to compile here until it is listed.
        let listed = |d: RoughingDirection| match d {
            RoughingDirection::X | RoughingDirection::Y | RoughingDirection::Contour => true,
        };
        assert!(names::<RoughingDirection>(&s.roughing).into_iter().all(listed));
    }
}
