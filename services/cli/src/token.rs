//! `depthmill token`: API tokens, managed on the server's job database directly (the operator of
//! the machine that runs the orchestrator holds this power; the APIs do not hand out tokens).

use std::path::PathBuf;

use anyhow::{Context as _, bail};
use depthmill_orchestrator::auth;
use depthmill_orchestrator::store;

/// Which job database.
#[derive(clap::Args)]
pub struct Database {
    /// Job database: sqlite://PATH or postgres://USER@HOST:PORT/DB.
    #[arg(long, env = "DEPTHMILL_DATABASE_URL")]
    database_url: Option<String>,
    /// Without --database-url: the serve command's data folder (its jobs.sqlite).
    #[arg(long, default_value = "data")]
    data_dir: PathBuf,
}

impl Database {
    async fn open(&self) -> anyhow::Result<std::sync::Arc<dyn store::JobStore>> {
        let url = match &self.database_url {
            Some(url) => url.clone(),
            None => {
                let path = self.data_dir.join("jobs.sqlite");
                if !path.exists() {
                    bail!(
                        "no job database at {} (give the serve command's --data-dir, or --database-url)",
                        path.display()
                    );
                }
                format!("sqlite://{}", path.display())
            }
        };
        store::open(&url).await.with_context(|| format!("opening the job database {}", store::redact(&url)))
    }
}

#[derive(clap::Subcommand)]
pub enum TokenCommand {
    /// Create a token and print it (once: only its hash is kept).
    Create {
        /// Who or what holds it, e.g. "cell-3 MES".
        #[arg(long)]
        name: String,
        /// read, submit or admin (several with commas); submit includes read, admin everything.
        #[arg(long, default_value = "submit")]
        scope: String,
        /// Lifetime in days (default: until revoked).
        #[arg(long)]
        expires_in_days: Option<f64>,
        #[command(flatten)]
        db: Database,
    },
    /// List tokens (never their secrets).
    List {
        #[command(flatten)]
        db: Database,
    },
    /// Revoke a token by its id (tok_...); servers stop accepting it within [auth] cache_s.
    Revoke {
        id: String,
        #[command(flatten)]
        db: Database,
    },
}

pub async fn run(command: TokenCommand) -> anyhow::Result<()> {
    let now = depthmill_orchestrator::app::now_ms();
    match command {
        TokenCommand::Create { name, scope, expires_in_days, db } => {
            let store = db.open().await?;
            let issued =
                auth::issue(&*store, &name, &scope, expires_in_days.map(|d| d * 86_400.0), now).await?;
            crate::outln!("{}", issued.token);
            eprintln!(
                "token {} ({}) with scope '{}'{}; send it as 'Authorization: Bearer <token>' \
                 (the client verbs: --token or DEPTHMILL_TOKEN). It is not shown again.",
                issued.record.id,
                issued.record.name,
                issued.record.scopes,
                match issued.record.expires_at_ms {
                    Some(t) => format!(", expires in {:.1} days", (t - now) as f64 / 86_400_000.0),
                    None => String::new(),
                }
            );
        }
        TokenCommand::List { db } => {
            let store = db.open().await?;
            crate::outln!("{:<40}  {:<16}  {:<8}  name", "id", "scope", "state");
            for t in store.list_tokens().await? {
                let state = match (t.revoked_at_ms, t.expires_at_ms) {
                    (Some(_), _) => "revoked",
                    (None, Some(e)) if e <= now => "expired",
                    _ => "active",
                };
                crate::outln!("{:<40}  {:<16}  {state:<8}  {}", t.id, t.scopes, t.name);
            }
        }
        TokenCommand::Revoke { id, db } => {
            let store = db.open().await?;
            if !store.revoke_token(&id, now).await? {
                bail!("no active token {id} (see `depthmill token list`)");
            }
            crate::outln!("revoked {id}");
        }
    }
    Ok(())
}
