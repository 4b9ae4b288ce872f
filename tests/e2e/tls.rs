//! TLS on the orchestrator's public APIs: REST (HTTPS) and gRPC with the configured certificate;
//! clients that do not trust it, or speak plain TCP, get nothing; bad files stop the start.

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use anyhow::Context as _;
use depthmill_common::tls::TlsFiles;
use depthmill_proto::orchestrator::v1 as pb;
use depthmill_proto::orchestrator::v1::orchestrator_service_client::OrchestratorServiceClient;
use rustls::pki_types::ServerName;
use tokio::io::{AsyncReadExt as _, AsyncWriteExt as _};
use tokio_util::sync::CancellationToken;

fn connector(trusted: Option<&rcgen::Certificate>) -> anyhow::Result<tokio_rustls::TlsConnector> {
    let mut roots = rustls::RootCertStore::empty();
    if let Some(cert) = trusted {
        roots.add(cert.der().clone())?;
    }
    let config =
        rustls::ClientConfig::builder_with_provider(Arc::new(rustls::crypto::ring::default_provider()))
            .with_safe_default_protocol_versions()?
            .with_root_certificates(roots)
            .with_no_client_auth();
    Ok(tokio_rustls::TlsConnector::from(Arc::new(config)))
}

/// `GET path` over HTTPS; the whole response as text.
async fn https_get(
    connector: &tokio_rustls::TlsConnector,
    addr: SocketAddr,
    path: &str,
) -> anyhow::Result<String> {
    let tcp = tokio::net::TcpStream::connect(addr).await?;
    let mut tls = connector.connect(ServerName::try_from("localhost")?, tcp).await?;
    tls.write_all(format!("GET {path} HTTP/1.1\r\nHost: localhost\r\nConnection: close\r\n\r\n").as_bytes())
        .await?;
    let mut out = Vec::new();
    tls.read_to_end(&mut out).await?;
    Ok(String::from_utf8_lossy(&out).into_owned())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn rest_and_grpc_speak_tls_with_the_configured_certificate() -> anyhow::Result<()> {
    let dir = tempfile::tempdir()?;
    let key = rcgen::generate_simple_self_signed(vec!["localhost".into()])?;
    let files = TlsFiles { cert: dir.path().join("cert.pem"), key: dir.path().join("key.pem") };
    std::fs::write(&files.cert, key.cert.pem())?;
    std::fs::write(&files.key, key.signing_key.serialize_pem())?;
    let rest = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
    let grpc = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
    let (rest_addr, grpc_addr) = (rest.local_addr()?, grpc.local_addr()?);
    let config = depthmill_orchestrator::Config {
        data_dir: dir.path().join("data"),
        services: depthmill_orchestrator::Endpoints::none(),
        tls: Some(files),
        ..Default::default()
    };
    let token = CancellationToken::new();
    let server = tokio::spawn(depthmill_orchestrator::serve(
        rest,
        grpc,
        config,
        None,
        token.clone().cancelled_owned(),
    ));

    let trusting = connector(Some(&key.cert))?;
    let mut ready = String::new();
    for _ in 0..100 {
        ready = https_get(&trusting, rest_addr, "/readyz").await.unwrap_or_default();
        if ready.starts_with("HTTP/1.1 200") {
            break;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    assert!(ready.starts_with("HTTP/1.1 200"), "{ready}");
    let jobs = https_get(&trusting, rest_addr, "/v1/jobs").await?;
    assert!(jobs.starts_with("HTTP/1.1 200") && jobs.contains("\"jobs\""), "{jobs}");

    // A client that does not trust the certificate, or that speaks plain HTTP, gets nothing.
    assert!(
        https_get(&connector(None)?, rest_addr, "/readyz").await.is_err(),
        "untrusted certificate accepted"
    );
    let plain = depthmill_common::tls::http_client().timeout(Duration::from_secs(5)).build()?;
    let answer = plain.get(format!("http://{rest_addr}/readyz")).send().await;
    assert!(answer.is_err() || answer.is_ok_and(|r| !r.status().is_success()), "plain HTTP served");

    // gRPC over TLS.
    let tls = tonic::transport::ClientTlsConfig::new()
        .ca_certificate(tonic::transport::Certificate::from_pem(key.cert.pem()))
        .domain_name("localhost");
    let channel = tonic::transport::Channel::from_shared(format!("https://{grpc_addr}"))?
        .tls_config(tls)?
        .connect()
        .await?;
    let listed = OrchestratorServiceClient::new(channel).list_jobs(pb::ListJobsRequest::default()).await?;
    assert!(listed.into_inner().jobs.is_empty());
    let untrusted = tonic::transport::Channel::from_shared(format!("https://{grpc_addr}"))?
        .tls_config(tonic::transport::ClientTlsConfig::new().domain_name("localhost"))?
        .connect()
        .await;
    let refused = match untrusted {
        Err(_) => true,
        Ok(ch) => OrchestratorServiceClient::new(ch).list_jobs(pb::ListJobsRequest::default()).await.is_err(),
    };
    assert!(refused, "a client without the CA got an answer");

    token.cancel();
    server.await.context("server task")??;
    Ok(())
}

#[tokio::test]
async fn a_certificate_without_its_key_stops_the_start() -> anyhow::Result<()> {
    let dir = tempfile::tempdir()?;
    let a = rcgen::generate_simple_self_signed(vec!["localhost".into()])?;
    let b = rcgen::generate_simple_self_signed(vec!["localhost".into()])?;
    let files = TlsFiles { cert: dir.path().join("cert.pem"), key: dir.path().join("key.pem") };
    std::fs::write(&files.cert, a.cert.pem())?;
    std::fs::write(&files.key, b.signing_key.serialize_pem())?;
    let config = depthmill_orchestrator::Config {
        data_dir: dir.path().join("data"),
        tls: Some(files),
        ..Default::default()
    };
    let rest = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
    let grpc = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
    let err = depthmill_orchestrator::serve(rest, grpc, config, None, std::future::pending())
        .await
        .expect_err("mismatched key");
    let chain = depthmill_common::ErrorChain(&err).to_string();
    assert!(chain.contains("cert.pem") && chain.contains("key.pem"), "{chain}");
    assert!(!dir.path().join("data").exists(), "refused before touching anything");
    Ok(())
}
