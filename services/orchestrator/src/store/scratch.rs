//! Throwaway PostgreSQL databases, for the test suites of this crate and of the workspace: each one
//! is created on the server at `DEPTHMILL_TEST_POSTGRES_URL` (default
//! `postgres://postgres@127.0.0.1:5432/postgres`) and dropped, with its data, when dropped.

use sqlx::{Connection as _, Executor as _, PgConnection};

use super::{StoreError, redact};

/// The server the scratch databases are made on.
pub fn admin_url() -> String {
    std::env::var("DEPTHMILL_TEST_POSTGRES_URL")
        .unwrap_or_else(|_| "postgres://postgres@127.0.0.1:5432/postgres".into())
}

/// A database that exists until this value is dropped.
#[derive(Debug)]
pub struct ScratchDatabase {
    admin: String,
    name: String,
}

/// Why a scratch database could not be made.
#[derive(Debug, thiserror::Error)]
#[error(
    "cannot create a scratch database on {server} (set DEPTHMILL_TEST_POSTGRES_URL to a server that allows it)"
)]
pub struct ScratchError {
    server: String,
    #[source]
    source: StoreError,
}

impl ScratchDatabase {
    /// Creates a new, empty database with a unique name.
    pub async fn create() -> Result<Self, ScratchError> {
        let admin = admin_url();
        let name = format!("depthmill_scratch_{}", uuid::Uuid::now_v7().simple());
        let made = async {
            let mut conn = PgConnection::connect(&admin).await?;
            // The name is ours (a UUID), not user input.
            conn.execute(sqlx::AssertSqlSafe(format!("CREATE DATABASE {name}"))).await?;
            conn.close().await?;
            Ok::<_, sqlx::Error>(())
        };
        made.await.map_err(|e| ScratchError { server: redact(&admin), source: e.into() })?;
        Ok(Self { admin, name })
    }

    /// Its URL, for [`super::open`] or an orchestrator's `database_url`.
    pub fn url(&self) -> String {
        let base = self.admin.split('?').next().unwrap_or_default();
        match base.rsplit_once('/') {
            Some((server, _)) if server.contains("://") && !server.ends_with('/') => {
                format!("{server}/{}", self.name)
            }
            _ => format!("{}/{}", base.trim_end_matches('/'), self.name),
        }
    }
}

impl Drop for ScratchDatabase {
    fn drop(&mut self) {
        let (admin, name) = (self.admin.clone(), self.name.clone());
        // Drop may run inside an async runtime: drop the database from a thread of its own.
        let dropped = std::thread::spawn(move || {
            let rt = tokio::runtime::Builder::new_current_thread().enable_all().build()?;
            rt.block_on(async {
                let mut conn = PgConnection::connect(&admin).await.map_err(std::io::Error::other)?;
                // FORCE: stores still holding connections (a test that panicked) do not keep it.
                conn.execute(sqlx::AssertSqlSafe(format!("DROP DATABASE IF EXISTS {name} WITH (FORCE)")))
                    .await
                    .map_err(std::io::Error::other)?;
                Ok::<_, std::io::Error>(())
            })
        })
        .join();
        if !matches!(dropped, Ok(Ok(()))) {
            tracing::warn!(database = %self.name, ?dropped, "could not drop a scratch database");
        }
    }
}
