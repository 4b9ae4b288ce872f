//! Prometheus metrics: the process-global recorder, installed once, and per-call gRPC metrics.
//!
//! The `metrics` recorder is global to the process. A process that runs several services (the
//! embedded `depthmill serve`, the test binary) installs it once through [`install_prometheus`];
//! every later call returns the same [`PrometheusHandle`]. Libraries only emit (`metrics::counter!`)
//! and never install: a binary calls [`install_prometheus`] before serving. Every server started
//! with [`crate::grpc::serve_grpc`] renders the handle at `GET /metrics` on its gRPC port (HTTP/1.1,
//! Prometheus text format), and answers 404 when the process installed no recorder.
//!
//! [`GrpcMetricsLayer`] records every gRPC call a server answers:
//! - `depthmill_grpc_requests_total{service, method, status}`: a counter, incremented when the call
//!   ends (its response body is finished or dropped);
//! - `depthmill_grpc_request_duration_seconds{service, method, status}`: a histogram (buckets in
//!   [`DURATION_BUCKETS_S`]) of the time from the request to the end of the response, so a
//!   streaming call counts its whole stream.
//!
//! `service` is the full gRPC service name (`depthmill.cam.v1.CamService`, `grpc.health.v1.Health`),
//! `method` the RPC name (`Check`), `status` the gRPC code name as tonic spells it (`Ok`,
//! `NotFound`, `Unimplemented`, ...), `Cancelled` when the client went away before the end.
//! Calls to services the server does not serve are counted under `service="unknown"`,
//! `method="unknown"`, so stray paths cannot grow the label set.

use std::future::Future;
use std::pin::Pin;
use std::sync::{Arc, OnceLock};
use std::task::{Context, Poll};
use std::time::{Duration, Instant};

use metrics_exporter_prometheus::{Matcher, PrometheusBuilder, PrometheusHandle};

/// Name of the gRPC call counter.
pub const GRPC_REQUESTS_TOTAL: &str = "depthmill_grpc_requests_total";
/// Name of the gRPC call duration histogram.
pub const GRPC_REQUEST_DURATION_SECONDS: &str = "depthmill_grpc_request_duration_seconds";

/// Histogram buckets, in seconds, of every metric whose name ends in `_seconds` (gRPC calls,
/// the orchestrator's stage durations). Stage calls may last up to an hour.
pub const DURATION_BUCKETS_S: &[f64] =
    &[0.001, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0, 300.0, 900.0, 3600.0];

/// How often the recorder drains histogram samples into their buckets.
const UPKEEP_INTERVAL: Duration = Duration::from_secs(5);

/// Why the Prometheus recorder could not be installed.
#[derive(Debug, Clone, thiserror::Error)]
#[error("cannot install the Prometheus metrics recorder: {reason}")]
pub struct MetricsError {
    reason: String,
}

static RECORDER: OnceLock<Result<PrometheusHandle, MetricsError>> = OnceLock::new();

/// Installs the process-global Prometheus recorder on the first call and returns its handle;
/// later calls (from any thread) return the same handle, or the same error.
///
/// Histograms of metrics named `*_seconds` get [`DURATION_BUCKETS_S`]. A background thread runs
/// the recorder's upkeep every few seconds, so histogram samples do not pile up between scrapes.
/// Fails when another recorder was installed in this process without this function.
pub fn install_prometheus() -> Result<PrometheusHandle, MetricsError> {
    RECORDER.get_or_init(install).clone()
}

/// The handle of the recorder [`install_prometheus`] installed, if it did.
pub fn prometheus_handle() -> Option<PrometheusHandle> {
    RECORDER.get().and_then(|r| r.as_ref().ok()).cloned()
}

fn install() -> Result<PrometheusHandle, MetricsError> {
    let err = |e: &dyn std::fmt::Display| MetricsError { reason: e.to_string() };
    let handle = PrometheusBuilder::new()
        .set_buckets_for_metric(Matcher::Suffix("_seconds".into()), DURATION_BUCKETS_S)
        .map_err(|e| err(&e))?
        .install_recorder()
        .map_err(|e| err(&e))?;
    let upkeep = handle.clone();
    let spawned = std::thread::Builder::new().name("metrics-upkeep".into()).spawn(move || {
        loop {
            std::thread::sleep(UPKEEP_INTERVAL);
            upkeep.run_upkeep();
        }
    });
    if let Err(e) = spawned {
        // Rendering drains histograms too; without upkeep they only grow between scrapes.
        tracing::warn!(error = %e, "cannot start the metrics upkeep thread");
    }
    Ok(handle)
}

/// The `GET /metrics` handler: the process's metrics in the Prometheus text format, or 404 when
/// the process installed no recorder.
pub async fn render_metrics() -> axum::response::Response {
    use axum::response::IntoResponse as _;
    match prometheus_handle() {
        Some(handle) => {
            ([(http::header::CONTENT_TYPE, "text/plain; version=0.0.4; charset=utf-8")], handle.render())
                .into_response()
        }
        None => (http::StatusCode::NOT_FOUND, "this process exports no metrics\n").into_response(),
    }
}

/// A tower layer that records [`GRPC_REQUESTS_TOTAL`] and [`GRPC_REQUEST_DURATION_SECONDS`] for
/// every gRPC call (requests whose content type is `application/grpc*`); other requests, such as
/// `GET /metrics`, pass through unrecorded.
#[derive(Debug, Clone)]
pub struct GrpcMetricsLayer {
    services: Arc<[String]>,
}

impl GrpcMetricsLayer {
    /// Records calls to `services` (full gRPC service names) under their own names; calls to any
    /// other service under `unknown`.
    pub fn new<S: AsRef<str>>(services: impl IntoIterator<Item = S>) -> Self {
        Self { services: services.into_iter().map(|s| s.as_ref().to_string()).collect() }
    }
}

impl<S> tower::Layer<S> for GrpcMetricsLayer {
    type Service = GrpcMetrics<S>;

    fn layer(&self, inner: S) -> Self::Service {
        GrpcMetrics { inner, services: self.services.clone() }
    }
}

/// The service of [`GrpcMetricsLayer`].
#[derive(Debug, Clone)]
pub struct GrpcMetrics<S> {
    inner: S,
    services: Arc<[String]>,
}

impl<S, ReqBody> tower::Service<http::Request<ReqBody>> for GrpcMetrics<S>
where
    S: tower::Service<http::Request<ReqBody>, Response = http::Response<tonic::body::Body>>,
    S::Future: Send + 'static,
    S::Error: Send + 'static,
{
    type Response = http::Response<tonic::body::Body>;
    type Error = S::Error;
    type Future = Pin<Box<dyn Future<Output = Result<Self::Response, Self::Error>> + Send>>;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), Self::Error>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, request: http::Request<ReqBody>) -> Self::Future {
        let labels = CallLabels::of(&request, &self.services);
        let start = Instant::now();
        let response = self.inner.call(request);
        Box::pin(async move {
            let result = response.await;
            let Some(labels) = labels else { return result };
            match result {
                Ok(response) => {
                    // A trailers-only response (most errors) carries its status in the headers.
                    let status = grpc_status(response.headers());
                    let tracker = CallTracker { labels, start, status, ended: false };
                    Ok(response.map(|body| {
                        tonic::body::Body::new(TrackedBody { inner: body, tracker: Some(tracker) })
                    }))
                }
                Err(e) => {
                    drop(CallTracker { labels, start, status: Some(tonic::Code::Internal), ended: true });
                    Err(e)
                }
            }
        })
    }
}

/// The `service` and `method` labels of one gRPC call.
struct CallLabels {
    service: String,
    method: String,
}

impl CallLabels {
    /// The labels of `request` when it is a gRPC call (`None` otherwise).
    fn of<B>(request: &http::Request<B>, services: &[String]) -> Option<Self> {
        let is_grpc = request
            .headers()
            .get(http::header::CONTENT_TYPE)
            .and_then(|v| v.to_str().ok())
            .is_some_and(|v| v.starts_with("application/grpc"));
        if !is_grpc {
            return None;
        }
        let path = request.uri().path().trim_start_matches('/');
        let known = path
            .split_once('/')
            .filter(|(service, method)| !method.is_empty() && services.iter().any(|s| s == service));
        Some(match known {
            Some((service, method)) => Self { service: service.to_string(), method: method.to_string() },
            None => Self { service: "unknown".into(), method: "unknown".into() },
        })
    }
}

fn grpc_status(headers: &http::HeaderMap) -> Option<tonic::Code> {
    headers.get("grpc-status").map(|v| tonic::Code::from_bytes(v.as_bytes()))
}

/// One call in flight; records its metrics once, when dropped.
struct CallTracker {
    labels: CallLabels,
    start: Instant,
    status: Option<tonic::Code>,
    /// The response body reached its end (a call dropped before that was cancelled).
    ended: bool,
}

impl Drop for CallTracker {
    fn drop(&mut self) {
        let status = match (self.status, self.ended) {
            (Some(code), _) => format!("{code:?}"),
            (None, true) => "Unknown".to_string(),
            (None, false) => "Cancelled".to_string(),
        };
        let labels = [
            ("service", self.labels.service.clone()),
            ("method", self.labels.method.clone()),
            ("status", status),
        ];
        metrics::counter!(GRPC_REQUESTS_TOTAL, &labels).increment(1);
        metrics::histogram!(GRPC_REQUEST_DURATION_SECONDS, &labels)
            .record(self.start.elapsed().as_secs_f64());
    }
}

/// A response body that watches for the `grpc-status` trailer and records the call at its end.
struct TrackedBody {
    inner: tonic::body::Body,
    tracker: Option<CallTracker>,
}

impl http_body::Body for TrackedBody {
    type Data = bytes::Bytes;
    type Error = tonic::Status;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<http_body::Frame<Self::Data>, Self::Error>>> {
        let polled = Pin::new(&mut self.inner).poll_frame(cx);
        match &polled {
            Poll::Ready(Some(Ok(frame))) => {
                if let (Some(trailers), Some(tracker)) = (frame.trailers_ref(), self.tracker.as_mut())
                    && let Some(code) = grpc_status(trailers)
                {
                    tracker.status = Some(code);
                }
            }
            Poll::Ready(None) => {
                if let Some(mut tracker) = self.tracker.take() {
                    tracker.ended = true;
                    drop(tracker);
                }
            }
            Poll::Ready(Some(Err(_))) | Poll::Pending => {}
        }
        polled
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> http_body::SizeHint {
        self.inner.size_hint()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn request(path: &str, content_type: &str) -> http::Request<()> {
        http::Request::builder()
            .uri(path)
            .header(http::header::CONTENT_TYPE, content_type)
            .body(())
            .expect("valid request")
    }

    #[test]
    fn labels_name_known_services_and_hide_others() {
        let services = ["grpc.health.v1.Health".to_string()];
        let known = CallLabels::of(&request("/grpc.health.v1.Health/Check", "application/grpc"), &services)
            .expect("a gRPC call");
        assert_eq!((known.service.as_str(), known.method.as_str()), ("grpc.health.v1.Health", "Check"));
        let other =
            CallLabels::of(&request("/x.Y/Z", "application/grpc+proto"), &services).expect("a gRPC call");
        assert_eq!((other.service.as_str(), other.method.as_str()), ("unknown", "unknown"));
        assert!(CallLabels::of(&request("/metrics", "text/plain"), &services).is_none(), "not gRPC");
    }
}
