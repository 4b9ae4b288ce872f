//! TLS for the public APIs (rustls on ring): the certificate files of a server, the REST server
//! over TLS, and the identity tonic serves gRPC with.

use std::future::Future;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use rustls::pki_types::pem::PemObject as _;
use rustls::pki_types::{CertificateDer, PrivateKeyDer};
use serde::{Deserialize, Serialize};
use tokio::net::TcpListener;
use tokio_rustls::TlsAcceptor;

/// Installs ring as the process's rustls crypto provider (once; later calls do nothing). Every
/// TLS user in the process shares it: the HTTP clients ([`http_client`], the object store's S3
/// client), the REST server and tonic.
pub fn install_crypto() {
    // Err means a provider is installed already (this one, by an earlier call): nothing to do.
    let _ = rustls::crypto::ring::default_provider().install_default();
}

/// A builder of the HTTP client every depthmill program uses (the CLI, the benches, the tests):
/// reqwest with rustls on ring, which [`install_crypto`] makes the process's provider first.
pub fn http_client() -> reqwest::ClientBuilder {
    install_crypto();
    reqwest::Client::builder()
}

/// `[tls]` of a server's configuration: PEM files.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TlsFiles {
    /// The certificate chain, leaf first (PEM).
    pub cert: PathBuf,
    /// Its private key (PEM: PKCS#8, PKCS#1 or SEC1).
    pub key: PathBuf,
}

/// Why the certificate or key cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum TlsError {
    #[error("cannot read {path}")]
    Read {
        path: String,
        #[source]
        source: std::io::Error,
    },
    #[error("{path} holds no {what} in PEM form")]
    Missing { path: String, what: &'static str },
    #[error("{path}: {detail}")]
    Pem { path: String, detail: String },
    #[error("the certificate in {cert} and the key in {key} do not make a TLS identity")]
    Identity {
        cert: String,
        key: String,
        #[source]
        source: rustls::Error,
    },
}

fn read(path: &Path) -> Result<Vec<u8>, TlsError> {
    std::fs::read(path).map_err(|source| TlsError::Read { path: path.display().to_string(), source })
}

/// The parsed files, checked to make a server identity.
#[derive(Debug)]
pub struct Identity {
    cert_pem: Vec<u8>,
    key_pem: Vec<u8>,
    chain: Vec<CertificateDer<'static>>,
    key: PrivateKeyDer<'static>,
}

impl Identity {
    /// Reads and checks the files: they must hold a certificate chain and the key matching its leaf.
    pub fn load(files: &TlsFiles) -> Result<Self, TlsError> {
        let cert_pem = read(&files.cert)?;
        let key_pem = read(&files.key)?;
        let cert_path = files.cert.display().to_string();
        let key_path = files.key.display().to_string();
        let chain = CertificateDer::pem_slice_iter(&cert_pem)
            .collect::<Result<Vec<_>, _>>()
            .map_err(|e| TlsError::Pem { path: cert_path.clone(), detail: e.to_string() })?;
        if chain.is_empty() {
            return Err(TlsError::Missing { path: cert_path, what: "certificate" });
        }
        let key = PrivateKeyDer::from_pem_slice(&key_pem).map_err(|e| match e {
            rustls::pki_types::pem::Error::NoItemsFound => {
                TlsError::Missing { path: key_path.clone(), what: "private key" }
            }
            other => TlsError::Pem { path: key_path.clone(), detail: other.to_string() },
        })?;
        let me = Self { cert_pem, key_pem, chain, key };
        me.server_config(Vec::new()).map_err(|source| TlsError::Identity {
            cert: cert_path,
            key: key_path,
            source,
        })?;
        Ok(me)
    }

    /// A rustls server configuration offering `alpn` protocols.
    fn server_config(&self, alpn: Vec<Vec<u8>>) -> Result<rustls::ServerConfig, rustls::Error> {
        let provider = Arc::new(rustls::crypto::ring::default_provider());
        let mut config = rustls::ServerConfig::builder_with_provider(provider)
            .with_safe_default_protocol_versions()?
            .with_no_client_auth()
            .with_single_cert(self.chain.clone(), self.key.clone_key())?;
        config.alpn_protocols = alpn;
        Ok(config)
    }

    /// What tonic serves gRPC with.
    pub fn grpc(&self) -> tonic::transport::ServerTlsConfig {
        tonic::transport::ServerTlsConfig::new()
            .identity(tonic::transport::Identity::from_pem(&self.cert_pem, &self.key_pem))
    }

    /// An acceptor for HTTP/1.1 over TLS.
    pub fn http1_acceptor(&self) -> Result<TlsAcceptor, rustls::Error> {
        Ok(TlsAcceptor::from(Arc::new(self.server_config(vec![b"http/1.1".to_vec()])?)))
    }
}

/// Serves `router` over HTTP/1.1 on TLS until `shutdown` completes. A client that fails the
/// handshake is dropped; the others are served each on its own task.
pub async fn serve_https(
    listener: TcpListener,
    router: axum::Router,
    acceptor: TlsAcceptor,
    shutdown: impl Future<Output = ()> + Send,
) -> std::io::Result<()> {
    tokio::pin!(shutdown);
    loop {
        let (tcp, peer) = tokio::select! {
            accepted = listener.accept() => match accepted {
                Ok(a) => a,
                // Out of file descriptors and the like: keep serving the connections we have.
                Err(e) => {
                    tracing::warn!(error = %e, "accepting a connection failed");
                    tokio::time::sleep(std::time::Duration::from_millis(50)).await;
                    continue;
                }
            },
            () = &mut shutdown => return Ok(()),
        };
        let acceptor = acceptor.clone();
        // The peer's address, as `axum::serve` with connect info gives it to handlers.
        let routed = router.clone().layer(axum::Extension(axum::extract::ConnectInfo(peer)));
        let service = hyper_util::service::TowerToHyperService::new(routed);
        tokio::spawn(async move {
            let tls = match acceptor.accept(tcp).await {
                Ok(tls) => tls,
                Err(e) => {
                    tracing::debug!(%peer, error = %e, "TLS handshake failed");
                    return;
                }
            };
            let io = hyper_util::rt::TokioIo::new(tls);
            if let Err(e) = hyper::server::conn::http1::Builder::new().serve_connection(io, service).await {
                tracing::debug!(%peer, error = %e, "connection ended with an error");
            }
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn files(dir: &Path, cert: &str, key: &str) -> TlsFiles {
        let (c, k) = (dir.join("cert.pem"), dir.join("key.pem"));
        std::fs::write(&c, cert).expect("write");
        std::fs::write(&k, key).expect("write");
        TlsFiles { cert: c, key: k }
    }

    #[test]
    fn a_matching_pair_loads_and_a_wrong_one_is_named() {
        let dir = tempfile::tempdir().expect("tempdir");
        let a = rcgen::generate_simple_self_signed(vec!["localhost".into()]).expect("cert");
        let b = rcgen::generate_simple_self_signed(vec!["localhost".into()]).expect("cert");
        let good = files(dir.path(), &a.cert.pem(), &a.signing_key.serialize_pem());
        assert!(Identity::load(&good).is_ok());
        let mixed = files(dir.path(), &a.cert.pem(), &b.signing_key.serialize_pem());
        assert!(matches!(Identity::load(&mixed), Err(TlsError::Identity { .. })));
        let empty = files(dir.path(), "not a certificate", &a.signing_key.serialize_pem());
        let err = Identity::load(&empty).expect_err("no certificate");
        assert!(err.to_string().contains("cert.pem holds no certificate"), "{err}");
        let missing = TlsFiles { cert: dir.path().join("nope.pem"), key: good.key.clone() };
        assert!(matches!(Identity::load(&missing), Err(TlsError::Read { .. })));
    }
}
