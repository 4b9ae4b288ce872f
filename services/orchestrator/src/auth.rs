//! Bearer tokens for the REST and gRPC APIs.
//!
//! A token is `dmt_` and 64 hex digits (256 random bits from the operating system's generator);
//! the store keeps only its SHA-256 (a fast hash is right for random secrets: there is nothing to
//! guess from), with a public id (`tok_...`), a name, scopes and an optional expiry. Scopes nest:
//! `admin` allows everything, `submit` allows submitting and cancelling jobs and uploading
//! artifacts and everything `read` allows, `read` allows looking at jobs, artifacts, reports and
//! events. Health, readiness, metrics and the API description stay open.
//!
//! [`AuthMode::Auto`] (the default) requires no token while both APIs listen on loopback only and
//! refuses to start on any other address; [`AuthMode::Tokens`] requires one everywhere;
//! [`AuthMode::Open`] serves any address without tokens (a network that does its own access
//! control), and says so at start.

use std::collections::HashMap;
use std::net::SocketAddr;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use depthmill_proto::ErrorCode;
use rand::TryRngCore as _;
use serde::{Deserialize, Serialize};
use sha2::{Digest as _, Sha256};

use crate::app::ApiError;
use crate::store::{JobStore, StoreError, TokenRecord};

/// What a token allows.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Scope {
    /// Jobs, artifacts, reports and events: look only.
    Read,
    /// Upload artifacts, submit and cancel jobs (and read).
    Submit,
    /// Everything.
    Admin,
}

impl Scope {
    pub const ALL: [Scope; 3] = [Scope::Read, Scope::Submit, Scope::Admin];

    pub fn as_str(self) -> &'static str {
        match self {
            Scope::Read => "read",
            Scope::Submit => "submit",
            Scope::Admin => "admin",
        }
    }
}

impl std::str::FromStr for Scope {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Self::ALL
            .into_iter()
            .find(|x| x.as_str() == s)
            .ok_or_else(|| format!("unknown scope '{s}' (expected read, submit or admin)"))
    }
}

/// Parses a scope list (`read submit`, `read,submit`): each named once, at least one.
pub fn parse_scopes(s: &str) -> Result<Vec<Scope>, String> {
    let mut out: Vec<Scope> = Vec::new();
    for word in s.split([',', ' ']).filter(|w| !w.is_empty()) {
        let scope: Scope = word.parse()?;
        if !out.contains(&scope) {
            out.push(scope);
        }
    }
    if out.is_empty() {
        return Err("no scope given (expected read, submit or admin)".into());
    }
    out.sort();
    Ok(out)
}

/// Whether holding `held` allows an operation that needs `needed` (scopes nest).
pub fn allows(held: &[Scope], needed: Scope) -> bool {
    held.iter().any(|h| *h >= needed)
}

/// How the APIs are guarded (`[auth]` of the orchestrator's configuration).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum AuthMode {
    /// No tokens while REST and gRPC listen on loopback only; any other address is refused.
    #[default]
    Auto,
    /// Every API call needs a token.
    Tokens,
    /// No tokens on any address.
    Open,
}

/// `[auth]` of the orchestrator's configuration.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct AuthConfig {
    pub mode: AuthMode,
    /// How long a checked token is trusted without asking the database again, in seconds: the
    /// longest a revoked token keeps working.
    pub cache_s: f64,
}

impl Default for AuthConfig {
    fn default() -> Self {
        Self { mode: AuthMode::Auto, cache_s: 5.0 }
    }
}

/// Why the configured mode cannot serve these addresses.
#[derive(Debug, thiserror::Error)]
#[error(
    "{api} listens on {addr}, which is not loopback, and no API token is required: set [auth] mode = \"tokens\" \
     (create tokens with `depthmill token create`) or mode = \"open\" for a network that controls access itself"
)]
pub struct OpenOnNetwork {
    pub api: &'static str,
    pub addr: SocketAddr,
}

/// Whether tokens are required for a server on `rest` and `grpc` in `mode`.
pub fn tokens_required(mode: AuthMode, rest: SocketAddr, grpc: SocketAddr) -> Result<bool, OpenOnNetwork> {
    match mode {
        AuthMode::Tokens => Ok(true),
        AuthMode::Open => {
            tracing::warn!(%rest, %grpc, "API tokens are not required ([auth] mode = \"open\")");
            Ok(false)
        }
        AuthMode::Auto => {
            for (api, addr) in [("REST", rest), ("gRPC", grpc)] {
                if !addr.ip().is_loopback() {
                    return Err(OpenOnNetwork { api, addr });
                }
            }
            tracing::info!(%rest, %grpc, "API tokens are not required: REST and gRPC listen on loopback only");
            Ok(false)
        }
    }
}

/// The SHA-256 of a token string, hex: what the store keeps.
pub fn secret_hash(token: &str) -> String {
    hex::encode(Sha256::digest(token.as_bytes()))
}

/// A new token: the string to hand out (shown once) and its record.
#[derive(Debug, Clone)]
pub struct IssuedToken {
    pub token: String,
    pub record: TokenRecord,
}

/// Why a token could not be issued.
#[derive(Debug, thiserror::Error)]
pub enum IssueError {
    #[error("token name must be 1 to 200 characters, got {0}")]
    Name(usize),
    #[error("{0}")]
    Scopes(String),
    #[error("token lifetime must be positive, got {0} s")]
    Lifetime(f64),
    #[error("the operating system's random generator failed")]
    Random(#[source] rand::rand_core::OsError),
    #[error("cannot store the token")]
    Store(#[from] StoreError),
}

/// 256 random bits from the operating system's generator, as 64 hex digits: API tokens, and the
/// service token of an embedded stack.
pub fn random_secret() -> Result<String, rand::rand_core::OsError> {
    let mut secret = [0u8; 32];
    rand::rngs::OsRng.try_fill_bytes(&mut secret)?;
    Ok(hex::encode(secret))
}

/// Creates and stores a token with `scopes` (a scope list), valid for `lifetime_s` (forever: `None`).
pub async fn issue(
    store: &dyn JobStore,
    name: &str,
    scopes: &str,
    lifetime_s: Option<f64>,
    now_ms: i64,
) -> Result<IssuedToken, IssueError> {
    let name = name.trim();
    if name.is_empty() || name.chars().count() > 200 {
        return Err(IssueError::Name(name.chars().count()));
    }
    let scopes = parse_scopes(scopes).map_err(IssueError::Scopes)?;
    if let Some(s) = lifetime_s.filter(|s| !(s.is_finite() && *s > 0.0)) {
        return Err(IssueError::Lifetime(s));
    }
    let token = format!("dmt_{}", random_secret().map_err(IssueError::Random)?);
    let record = TokenRecord {
        id: format!("tok_{}", uuid::Uuid::now_v7().simple()),
        name: name.to_string(),
        scopes: scopes.iter().map(|s| s.as_str()).collect::<Vec<_>>().join(" "),
        created_at_ms: now_ms,
        expires_at_ms: lifetime_s.map(|s| now_ms.saturating_add((s * 1000.0) as i64)),
        revoked_at_ms: None,
    };
    store.create_token(&record, &secret_hash(&token)).await?;
    Ok(IssuedToken { token, record })
}

/// Who makes an API call, as the limits count clients: `token:<id>` when tokens are required,
/// otherwise `addr:<ip>` (the peer's IP address, without the port). Put in the request's
/// extensions by the REST and gRPC token checks.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Client(pub String);

impl Client {
    /// The client of a call allowed by token `token_id` (when tokens are required) or else
    /// coming from `peer`; `None` when neither is known.
    pub fn of(token_id: Option<String>, peer: Option<SocketAddr>) -> Option<Client> {
        match (token_id, peer) {
            (Some(id), _) => Some(Client(format!("token:{id}"))),
            (None, Some(peer)) => Some(Client(format!("addr:{}", peer.ip()))),
            (None, None) => None,
        }
    }
}

/// Checks the bearer tokens of API calls against the store, with a short cache.
pub struct Authenticator {
    store: Arc<dyn JobStore>,
    required: bool,
    ttl: Duration,
    cache: Mutex<HashMap<String, (Instant, Option<TokenRecord>)>>,
}

/// Most cached lookups kept; beyond it the cache starts afresh.
const CACHE_CAPACITY: usize = 10_000;

impl Authenticator {
    pub fn new(store: Arc<dyn JobStore>, required: bool, cache_s: f64) -> Self {
        let ttl = Duration::from_secs_f64(if cache_s.is_finite() { cache_s.clamp(0.0, 3600.0) } else { 0.0 });
        Self { store, required, ttl, cache: Mutex::new(HashMap::new()) }
    }

    /// Whether calls need a token at all.
    pub fn required(&self) -> bool {
        self.required
    }

    /// Checks an `Authorization` header value for an operation that needs `needed`; the id of
    /// the token that allowed it (`None` when tokens are not required).
    pub async fn check(
        &self,
        authorization: Option<&str>,
        needed: Scope,
        now_ms: i64,
    ) -> Result<Option<String>, ApiError> {
        if !self.required {
            return Ok(None);
        }
        let unauthenticated = |m: &str| ApiError::new(ErrorCode::Unauthenticated, m);
        let Some(value) = authorization else {
            return Err(unauthenticated("an API token is required: send Authorization: Bearer <token>"));
        };
        let token = value
            .strip_prefix("Bearer ")
            .or_else(|| value.strip_prefix("bearer "))
            .map(str::trim)
            .filter(|t| !t.is_empty())
            .ok_or_else(|| unauthenticated("the Authorization header must be 'Bearer <token>'"))?;
        let hash = secret_hash(token);
        let record = self.lookup(&hash).await?;
        let Some(record) = record else { return Err(unauthenticated("unknown API token")) };
        if record.revoked_at_ms.is_some() {
            return Err(unauthenticated(&format!("API token {} was revoked", record.id)));
        }
        if record.expires_at_ms.is_some_and(|t| t <= now_ms) {
            return Err(unauthenticated(&format!("API token {} has expired", record.id)));
        }
        let held = parse_scopes(&record.scopes).unwrap_or_default();
        if !allows(&held, needed) {
            return Err(ApiError::new(
                ErrorCode::PermissionDenied,
                format!(
                    "API token {} has scope '{}'; this operation needs '{}'",
                    record.id,
                    record.scopes,
                    needed.as_str()
                ),
            ));
        }
        Ok(Some(record.id))
    }

    async fn lookup(&self, hash: &str) -> Result<Option<TokenRecord>, ApiError> {
        if let Ok(cache) = self.cache.lock()
            && let Some((at, record)) = cache.get(hash)
            && at.elapsed() < self.ttl
        {
            return Ok(record.clone());
        }
        let record = self.store.token_by_secret(hash).await?;
        if let Ok(mut cache) = self.cache.lock() {
            if cache.len() >= CACHE_CAPACITY {
                cache.clear();
            }
            cache.insert(hash.to_string(), (Instant::now(), record.clone()));
        }
        Ok(record)
    }
}

/// The scope a REST call needs; `None` for the open routes (health, metrics, API description).
pub fn rest_scope(method: &axum::http::Method, path: &str) -> Option<Scope> {
    if !path.starts_with("/v1/") {
        return None;
    }
    Some(match *method {
        axum::http::Method::GET | axum::http::Method::HEAD | axum::http::Method::OPTIONS => Scope::Read,
        _ => Scope::Submit,
    })
}

/// The scope a gRPC method of the orchestrator's service needs (by its path); a method not named
/// here needs `admin`, so a new one is closed until it is classified. `None`: health, reflection.
pub fn grpc_scope(path: &str) -> Option<Scope> {
    let method = path.strip_prefix("/depthmill.orchestrator.v1.OrchestratorService/")?;
    Some(match method {
        "GetJob" | "ListJobs" | "WatchJob" | "DownloadArtifact" | "GetCalibration" | "ListCalibrations" => {
            Scope::Read
        }
        "CreateJob" | "CancelJob" | "UploadArtifact" | "CreateCalibration" => Scope::Submit,
        _ => Scope::Admin,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scopes_parse_and_nest() {
        assert_eq!(parse_scopes("submit,read submit"), Ok(vec![Scope::Read, Scope::Submit]));
        assert!(parse_scopes("").is_err());
        assert!(parse_scopes("write").expect_err("unknown scope").contains("'write'"));
        assert!(allows(&[Scope::Admin], Scope::Submit));
        assert!(allows(&[Scope::Submit], Scope::Read));
        assert!(!allows(&[Scope::Read], Scope::Submit));
        assert!(!allows(&[], Scope::Read));
    }

    #[test]
    fn loopback_only_without_tokens() {
        let lo: SocketAddr = "127.0.0.1:8080".parse().expect("addr");
        let any: SocketAddr = "0.0.0.0:50050".parse().expect("addr");
        assert_eq!(tokens_required(AuthMode::Auto, lo, lo).ok(), Some(false));
        let refused = tokens_required(AuthMode::Auto, lo, any).expect_err("open on the network");
        assert!(refused.to_string().contains("0.0.0.0:50050"), "{refused}");
        assert_eq!(tokens_required(AuthMode::Open, any, any).ok(), Some(false));
        assert_eq!(tokens_required(AuthMode::Tokens, lo, lo).ok(), Some(true));
    }

    #[test]
    fn routes_need_the_scope_of_what_they_do() {
        use axum::http::Method;
        assert_eq!(rest_scope(&Method::GET, "/v1/jobs"), Some(Scope::Read));
        assert_eq!(rest_scope(&Method::POST, "/v1/jobs/x/cancel"), Some(Scope::Submit));
        assert_eq!(rest_scope(&Method::GET, "/healthz"), None);
        assert_eq!(rest_scope(&Method::GET, "/openapi.json"), None);
        let svc = "/depthmill.orchestrator.v1.OrchestratorService";
        assert_eq!(grpc_scope(&format!("{svc}/CreateJob")), Some(Scope::Submit));
        assert_eq!(grpc_scope(&format!("{svc}/WatchJob")), Some(Scope::Read));
        assert_eq!(grpc_scope(&format!("{svc}/DropEverything")), Some(Scope::Admin));
        assert_eq!(grpc_scope("/grpc.health.v1.Health/Check"), None);
    }
}
