//! The API surface: artifacts, validation, health, reflection, OpenAPI.

use depthmill_proto::orchestrator::v1 as pb;
use depthmill_tests::TestStack;
use futures::StreamExt as _;
use serde_json::{Value, json};

use crate::{gcode_job, program};

#[tokio::test]
async fn artifacts_round_trip_over_rest_and_grpc() -> anyhow::Result<()> {
    let stack = TestStack::start().await?;
    let bytes = program();
    let sha = stack.upload("text/x-gcode", bytes.clone()).await?;
    let resp = stack.http.get(stack.url(&format!("/v1/artifacts/{sha}"))).send().await?;
    assert_eq!(resp.status(), 200);
    assert_eq!(resp.headers()["content-type"], "text/x-gcode");
    assert_eq!(resp.bytes().await?.to_vec(), bytes);

    // gRPC: upload in chunks, download in chunks, same digest and bytes.
    let mut client = stack.grpc().await?;
    let big: Vec<u8> =
        (0..60_000u32).flat_map(|i| format!("{} {} {}\n", i % 97, i % 89, i % 83).into_bytes()).collect();
    let chunks: Vec<pb::UploadArtifactRequest> = big
        .chunks(64 * 1024)
        .enumerate()
        .map(|(i, c)| pb::UploadArtifactRequest {
            media_type: if i == 0 { "text/x-xyz".into() } else { String::new() },
            data: c.to_vec(),
        })
        .collect();
    let aref = client.upload_artifact(futures::stream::iter(chunks)).await?.into_inner();
    assert_eq!(aref.size, big.len() as u64);
    let mut stream = client
        .download_artifact(pb::DownloadArtifactRequest { sha256: aref.sha256.clone() })
        .await?
        .into_inner();
    let mut got = Vec::new();
    let mut first = true;
    while let Some(chunk) = stream.next().await {
        let chunk = chunk?;
        assert_eq!(chunk.artifact.is_some(), first, "only the first chunk carries the reference");
        first = false;
        got.extend(chunk.data);
    }
    assert_eq!(got, big);
    // The REST side sees the gRPC upload.
    let resp = stack.http.get(stack.url(&format!("/v1/artifacts/{}", aref.sha256))).send().await?;
    assert_eq!(resp.bytes().await?.len(), big.len());
    stack.shutdown().await
}

async fn expect_error(
    resp: reqwest::Response,
    status: u16,
    code: &str,
    mention: &str,
) -> anyhow::Result<Value> {
    assert_eq!(resp.status().as_u16(), status);
    let body: Value = resp.json().await?;
    assert_eq!(body["error"]["code"], code, "{body}");
    let message = body["error"]["message"].as_str().unwrap_or_default();
    assert!(message.contains(mention), "'{message}' should mention '{mention}'");
    Ok(body)
}

#[tokio::test]
async fn bad_input_is_rejected_with_the_problem_named_and_the_server_keeps_serving() -> anyhow::Result<()> {
    let stack = TestStack::start().await?;
    let sha = stack.upload("text/x-gcode", program()).await?;
    let post = |body: String| {
        stack.http.post(stack.url("/v1/jobs")).header("content-type", "application/json").body(body).send()
    };

    // Malformed JSON.
    expect_error(post("{\"input\": ".into()).await?, 400, "invalid_argument", "malformed JSON").await?;
    // Unknown field, named with its path.
    let body = json!({"input": {"kind": "gcode", "artifact": sha}, "execute": {"machine": "emco-f1", "adaptve": "off"}});
    let e = expect_error(post(body.to_string()).await?, 400, "invalid_argument", "adaptve").await?;
    assert_eq!(e["error"]["field"], "execute.adaptve");
    // Unknown value of an enum.
    let body = json!({"input": {"kind": "gcode", "artifact": sha}, "execute": {"adaptive": "turbo"}});
    let e = expect_error(post(body.to_string()).await?, 400, "invalid_argument", "turbo").await?;
    assert_eq!(e["error"]["field"], "execute.adaptive");
    // A stage parameter the job never reaches.
    let body = json!({"input": {"kind": "gcode", "artifact": sha}, "plan": {"roughing": {"tool": "flat-6"}}});
    let e = expect_error(post(body.to_string()).await?, 400, "invalid_argument", "never runs plan").await?;
    assert_eq!(e["error"]["field"], "plan");
    // A value out of range.
    let body = json!({"input": {"kind": "point_cloud", "artifact": sha}, "reconstruct": {"pixel_mm": -0.1}});
    let e = expect_error(post(body.to_string()).await?, 400, "invalid_argument", "positive").await?;
    assert_eq!(e["error"]["field"], "reconstruct.pixel_mm");
    // Unknown artifact.
    let missing = "f".repeat(64);
    let body = json!({"input": {"kind": "gcode", "artifact": missing}});
    let e = expect_error(post(body.to_string()).await?, 400, "invalid_argument", "not found").await?;
    assert_eq!(e["error"]["field"], "input.artifact");
    // Input of the wrong kind for its artifact.
    let body = json!({"input": {"kind": "depth_map", "artifact": sha}});
    expect_error(post(body.to_string()).await?, 400, "invalid_argument", "text/x-gcode").await?;

    // Oversized upload (the stack's limit is 1 MiB).
    let big = vec![b'1'; 2 << 20];
    let resp = stack
        .http
        .post(stack.url("/v1/artifacts"))
        .header("content-type", "text/x-xyz")
        .body(big)
        .send()
        .await?;
    expect_error(resp, 413, "payload_too_large", "limit").await?;
    // Bytes that are not of the declared type, and a type not accepted.
    let resp = stack
        .http
        .post(stack.url("/v1/artifacts"))
        .header("content-type", "image/png")
        .body("G0 X1")
        .send()
        .await?;
    expect_error(resp, 415, "unsupported_media_type", "PNG").await?;
    let resp = stack
        .http
        .post(stack.url("/v1/artifacts"))
        .header("content-type", "image/gif")
        .body("GIF89a")
        .send()
        .await?;
    expect_error(resp, 415, "unsupported_media_type", "image/gif").await?;
    // A job request over the 2 MiB a request may be: the API's error, naming the limit.
    let huge = format!("{{\"name\": \"{}\"}}", "x".repeat(3 << 20));
    let resp = post(huge).await?;
    expect_error(resp, 413, "payload_too_large", "2 MiB").await?;
    // Malformed digest and unknown job.
    let resp = stack.http.get(stack.url("/v1/artifacts/not-a-digest")).send().await?;
    expect_error(resp, 400, "invalid_argument", "sha256").await?;
    let resp = stack.http.get(stack.url("/v1/jobs/nope")).send().await?;
    expect_error(resp, 404, "not_found", "nope").await?;
    let resp = stack.http.get(stack.url("/v1/jobs?status=sleeping")).send().await?;
    expect_error(resp, 400, "invalid_argument", "sleeping").await?;

    // Nothing was created by any of that, and the server still works.
    let list: Value = stack.http.get(stack.url("/v1/jobs")).send().await?.json().await?;
    assert_eq!(list["jobs"].as_array().map(Vec::len), Some(0));
    let (status, job) = stack.post_job(&gcode_job(&sha), None).await?;
    assert_eq!(status, 201, "{job}");
    assert_eq!(stack.http.get(stack.url("/healthz")).send().await?.status(), 200);

    // gRPC answers INVALID_ARGUMENT naming the field.
    let mut client = stack.grpc().await?;
    let err = client
        .create_job(pb::CreateJobRequest {
            spec: Some(pb::JobSpec::default()),
            idempotency_key: String::new(),
        })
        .await
        .expect_err("no input");
    assert_eq!(err.code(), tonic::Code::InvalidArgument);
    assert!(err.message().contains("input"), "{}", err.message());
    stack.shutdown().await
}

#[tokio::test]
async fn every_server_serves_health_and_reflection() -> anyhow::Result<()> {
    use tonic_health::pb::health_check_response::ServingStatus;
    use tonic_health::pb::{HealthCheckRequest, health_client::HealthClient};
    use tonic_reflection::pb::v1::ServerReflectionRequest;
    use tonic_reflection::pb::v1::server_reflection_client::ServerReflectionClient;
    use tonic_reflection::pb::v1::server_reflection_request::MessageRequest;
    use tonic_reflection::pb::v1::server_reflection_response::MessageResponse;

    let stack = TestStack::start().await?;
    let endpoints = stack.service_urls();
    // The orchestrator, scanning (the stage and its two device services), reconstruction, cam, machine.
    assert_eq!(endpoints.len(), 7);
    for (service, url) in endpoints {
        let channel = tonic::transport::Channel::from_shared(url.clone())?.connect().await?;
        let mut health = HealthClient::new(channel.clone());
        let resp = health.check(HealthCheckRequest { service: service.clone() }).await?.into_inner();
        assert_eq!(resp.status, ServingStatus::Serving as i32, "{service}");
        let mut reflection = ServerReflectionClient::new(channel);
        let req = ServerReflectionRequest {
            host: String::new(),
            message_request: Some(MessageRequest::ListServices(String::new())),
        };
        let mut stream =
            reflection.server_reflection_info(futures::stream::iter(vec![req])).await?.into_inner();
        let resp = stream.next().await.expect("a reply")?;
        let Some(MessageResponse::ListServicesResponse(list)) = resp.message_response else {
            anyhow::bail!("unexpected reflection reply from {url}");
        };
        let names: Vec<String> = list.service.into_iter().map(|s| s.name).collect();
        assert!(names.contains(&service), "{url} lists {names:?}");
        assert!(names.iter().any(|n| n == "grpc.health.v1.Health"), "{names:?}");
    }
    stack.shutdown().await
}

#[tokio::test]
async fn openapi_document_and_docs_are_served() -> anyhow::Result<()> {
    let stack = TestStack::start().await?;
    let doc: Value = stack.http.get(stack.url("/openapi.json")).send().await?.json().await?;
    for path in [
        "/v1/jobs",
        "/v1/jobs/{id}",
        "/v1/jobs/{id}/cancel",
        "/v1/jobs/{id}/events",
        "/v1/jobs/{id}/report",
        "/v1/artifacts",
        "/v1/artifacts/{sha256}",
        "/healthz",
        "/readyz",
    ] {
        assert!(doc["paths"][path].is_object(), "{path} missing from the OpenAPI document");
    }
    assert!(doc["components"]["schemas"]["JobSpec"].is_object());
    let docs = stack.http.get(stack.url("/docs/")).send().await?;
    assert_eq!(docs.status(), 200);
    assert!(docs.text().await?.contains("swagger"));
    let ready = stack.http.get(stack.url("/readyz")).send().await?;
    assert_eq!(ready.status(), 200);
    stack.shutdown().await
}

#[tokio::test]
async fn the_catalog_is_listed_over_rest() -> anyhow::Result<()> {
    let mut stack = TestStack::start().await?;
    let resp = stack.http.get(stack.url("/v1/tools")).send().await?;
    assert_eq!(resp.status().as_u16(), 200);
    let body: Value = resp.json().await?;
    let tools = body["tools"].as_array().cloned().unwrap_or_default();
    let names: Vec<&str> = tools.iter().filter_map(|t| t["name"].as_str()).collect();
    for expected in ["ball-6", "flat-6"] {
        assert!(names.contains(&expected), "{expected} missing from {names:?}");
    }
    assert!(names.windows(2).all(|w| w[0] <= w[1]), "sorted by name: {names:?}");
    assert!(tools.iter().all(|t| t["diameter_mm"].as_f64().is_some_and(|d| d > 0.0)), "{body}");
    // Documented in the API description.
    let api: Value = stack.http.get(stack.url("/openapi.json")).send().await?.json().await?;
    for path in ["/v1/tools", "/v1/materials", "/v1/machines", "/v1/strategies"] {
        assert!(api["paths"][path]["get"].is_object(), "{path} documented");
    }

    // Materials: the CAM's cutting table, marked with what the machine's model cuts.
    let body: Value = stack.http.get(stack.url("/v1/materials")).send().await?.json().await?;
    let materials = body["materials"].as_array().cloned().unwrap_or_default();
    let al = materials.iter().find(|m| m["name"] == "aluminium").expect("aluminium listed");
    assert!(al["surface_speed_m_min"].as_f64().is_some_and(|v| v > 0.0), "{al}");
    assert_eq!(al["simulated"], true, "{al}");
    assert!(al["aliases"].as_array().is_some_and(|a| a.iter().any(|x| x == "aluminum")), "{al}");
    // Machines: the shipped profiles with their travel.
    let body: Value = stack.http.get(stack.url("/v1/machines")).send().await?.json().await?;
    let machines = body["machines"].as_array().cloned().unwrap_or_default();
    let names: Vec<&str> = machines.iter().filter_map(|m| m["name"].as_str()).collect();
    assert_eq!(names, ["emco-f1", "emco-f1-tt"], "{body}");
    let f1 = &machines[0];
    assert!(f1["x"]["max"].as_f64() > f1["x"]["min"].as_f64(), "{f1}");
    assert!(f1.get("c").is_none() && machines[1]["c"].is_object(), "only the table-table has C: {body}");
    // Strategies: every value a job request takes.
    let body: Value = stack.http.get(stack.url("/v1/strategies")).send().await?.json().await?;
    let finishing: Vec<&str> =
        body["finishing"].as_array().into_iter().flatten().filter_map(|c| c["name"].as_str()).collect();
    assert_eq!(finishing, ["raster_x", "raster_y", "raster_angle", "iso_level"], "{body}");

    // The machine service down: materials still listed, without the mark; machines 503.
    stack.stop_service("machine").await?;
    let body: Value = stack.http.get(stack.url("/v1/materials")).send().await?.json().await?;
    assert!(body["materials"][0].get("simulated").is_none(), "{body}");
    let resp = stack.http.get(stack.url("/v1/machines")).send().await?;
    assert_eq!(resp.status().as_u16(), 503);
    // The CAM service down: 503, not an empty list.
    stack.stop_service("cam").await?;
    for path in ["/v1/tools", "/v1/materials"] {
        let resp = stack.http.get(stack.url(path)).send().await?;
        assert_eq!(resp.status().as_u16(), 503, "{path}");
        let body: Value = resp.json().await?;
        assert_eq!(body["error"]["code"], "unavailable", "{body}");
    }
    stack.shutdown().await
}
