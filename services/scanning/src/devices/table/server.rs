//! The simulated table controller on a socket.
//!
//! One [`Table`] is powered up when the server starts and lives as long as it does; connections
//! share it, and its state (position, last target, S and A) survives disconnects, as a controller
//! does when the serial cable is unplugged.
//!
//! **One client at a time**, like a serial port: a connection arriving while another is active
//! waits up to [`BUSY_WAIT`] for it to end (so a client that reconnects right after closing is not
//! refused while the server has not yet seen the close), then gets `ERR busy: ...` and is closed.
//! Each accepted session starts with the power-up header.
//!
//! The model is advanced lazily: at each command to the time elapsed since power-up on tokio's
//! clock ([`tokio::time::Instant`], so tests can pause and advance time), then the command runs
//! and its reply is written back. Replies to all commands found in one read are written together.

use std::future::Future;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;

use tokio::io::{AsyncRead, AsyncReadExt, AsyncWrite, AsyncWriteExt};
use tokio::net::TcpListener;
use tokio::sync::watch;
use tokio::task::JoinSet;
use tokio::time::Instant;

use crate::domain::table::model::{Table, TableConfig, TableConfigError};
use crate::domain::table::protocol::{Command, Decoder, HEADER, Reply};

/// How long a new connection waits for the active one to end before it is refused.
pub const BUSY_WAIT: Duration = Duration::from_secs(1);

/// A powered-up simulated table that connections can be served against.
#[derive(Debug, Clone)]
pub struct SimulatedTable {
    table: Arc<Mutex<Table>>,
    power_up: Instant,
    line: Arc<tokio::sync::Mutex<()>>,
}

impl SimulatedTable {
    /// Powers up a table now (on tokio's clock; must be called inside a runtime).
    pub fn new(config: TableConfig) -> Result<Self, TableConfigError> {
        Ok(Self {
            table: Arc::new(Mutex::new(Table::new(config)?)),
            power_up: Instant::now(),
            line: Arc::new(tokio::sync::Mutex::new(())),
        })
    }

    /// Seconds since power-up.
    pub fn elapsed_s(&self) -> f64 {
        self.power_up.elapsed().as_secs_f64()
    }

    fn lock(&self) -> MutexGuard<'_, Table> {
        // The model never panics while locked; if it did, its state is still usable.
        self.table.lock().unwrap_or_else(|poisoned| poisoned.into_inner())
    }

    /// Runs `f` on the model advanced to now (inspection in tests, e.g. the true angle).
    pub fn with_table<R>(&self, f: impl FnOnce(&mut Table) -> R) -> R {
        let now = self.elapsed_s();
        let mut table = self.lock();
        table.advance_to(now);
        f(&mut table)
    }

    /// Executes one command now.
    pub fn execute(&self, cmd: Command) -> Reply {
        let now = self.elapsed_s();
        self.lock().command(cmd, now)
    }

    /// Serves one connection (any byte stream: TCP, an in-memory duplex in tests) until the peer
    /// closes it or `shutdown` completes. Waits for the line as described in the module doc.
    pub async fn serve_connection<S>(
        &self,
        mut stream: S,
        shutdown: impl Future<Output = ()>,
    ) -> std::io::Result<()>
    where
        S: AsyncRead + AsyncWrite + Unpin,
    {
        tokio::pin!(shutdown);
        let guard = tokio::select! {
            guard = tokio::time::timeout(BUSY_WAIT, self.line.clone().lock_owned()) => guard.ok(),
            () = &mut shutdown => return Ok(()),
        };
        let Some(_line) = guard else {
            tracing::info!("table busy, refusing a second client");
            stream.write_all(&Reply::Error("busy: another client is connected".into()).encode()).await?;
            let _ = stream.shutdown().await;
            return Ok(());
        };
        stream.write_all(format!("{HEADER}\r\n").as_bytes()).await?;
        stream.flush().await?;
        let mut decoder = Decoder::new();
        let mut buf = [0u8; 512];
        let mut out = Vec::new();
        loop {
            let n = tokio::select! {
                read = stream.read(&mut buf) => read?,
                () = &mut shutdown => break,
            };
            if n == 0 {
                break;
            }
            for item in decoder.feed(&buf[..n]) {
                let reply = match item {
                    Ok(cmd) => self.execute(cmd),
                    Err(e) => Reply::Error(e.to_string()),
                };
                if let Reply::Error(reason) = &reply {
                    tracing::debug!(%reason, "table command refused");
                }
                out.extend_from_slice(&reply.encode());
            }
            if !out.is_empty() {
                stream.write_all(&out).await?;
                stream.flush().await?;
                out.clear();
            }
        }
        let _ = stream.shutdown().await;
        Ok(())
    }

    /// Accepts connections on `listener` until `shutdown` completes, then closes every session.
    /// Accept errors are logged and retried after 100 ms.
    pub async fn serve(self, listener: TcpListener, shutdown: impl Future<Output = ()>) {
        let (stop_tx, stop_rx) = watch::channel(false);
        let mut sessions = JoinSet::new();
        tokio::pin!(shutdown);
        loop {
            tokio::select! {
                () = &mut shutdown => break,
                accepted = listener.accept() => match accepted {
                    Ok((stream, peer)) => {
                        let _ = stream.set_nodelay(true);
                        let sim = self.clone();
                        let mut stop = stop_rx.clone();
                        sessions.spawn(async move {
                            tracing::info!(%peer, "table client connected");
                            let stopped = async move {
                                let _ = stop.wait_for(|s| *s).await;
                            };
                            match sim.serve_connection(stream, stopped).await {
                                Ok(()) => tracing::info!(%peer, "table client disconnected"),
                                Err(error) => tracing::info!(%peer, %error, "table client dropped"),
                            }
                        });
                    }
                    Err(error) => {
                        tracing::warn!(%error, "table accept failed");
                        tokio::time::sleep(Duration::from_millis(100)).await;
                    }
                },
                Some(_) = sessions.join_next(), if !sessions.is_empty() => {}
            }
        }
        let _ = stop_tx.send(true);
        while sessions.join_next().await.is_some() {}
    }
}

/// Serves a simulated table built from `config` on `listener` until `shutdown` completes; see the
/// module doc. Fails only on an invalid `config`.
pub async fn serve_table(
    listener: TcpListener,
    config: TableConfig,
    shutdown: impl Future<Output = ()>,
) -> Result<(), TableConfigError> {
    SimulatedTable::new(config)?.serve(listener, shutdown).await;
    Ok(())
}

#[cfg(test)]
#[allow(clippy::unwrap_used)] // tests may unwrap
mod tests {
    use super::*;
    use tokio::io::duplex;

    async fn read_some(s: &mut (impl AsyncRead + Unpin), n: usize) -> Vec<u8> {
        let mut buf = vec![0u8; n];
        s.read_exact(&mut buf).await.unwrap();
        buf
    }

    #[tokio::test(start_paused = true)]
    async fn session_speaks_the_protocol_byte_exact() {
        let sim = SimulatedTable::new(TableConfig::default()).unwrap();
        let (mut client, server) = duplex(1024);
        let s = sim.clone();
        let task = tokio::spawn(async move { s.serve_connection(server, std::future::pending()).await });
        let header = format!("{HEADER}\r\n");
        assert_eq!(read_some(&mut client, header.len()).await, header.as_bytes());
        client.write_all(b"H\r\n").await.unwrap();
        assert_eq!(read_some(&mut client, 10).await, b"H 0.0000\r\n");
        client.write_all(b"h").await.unwrap();
        assert_eq!(read_some(&mut client, 2).await, [0, 0]);
        client.write_all(b"S 30\r\nA60\nP 90\r\n").await.unwrap();
        assert_eq!(read_some(&mut client, 12).await, b"OK\r\nOK\r\nOK\r\n");
        client.write_all(b"P abc\r\nH 1\r\nQ\r\n").await.unwrap();
        let want = b"ERR malformed number 'abc' for P\r\nERR H takes no argument, got '1'\r\nERR unknown command 'Q'\r\n";
        assert_eq!(read_some(&mut client, want.len()).await, want);
        // Simulated seconds pass instantly with the paused clock.
        tokio::time::sleep(Duration::from_secs(5)).await;
        client.write_all(b"H\r\nh").await.unwrap();
        assert_eq!(read_some(&mut client, 11).await, b"H 90.0000\r\n");
        assert_eq!(read_some(&mut client, 2).await, 2880u16.to_be_bytes());
        let truth = sim.with_table(|t| t.position_deg());
        assert!((90.0..90.03125).contains(&truth));
        drop(client);
        task.await.unwrap().unwrap();
    }

    #[tokio::test(start_paused = true)]
    async fn second_client_waits_then_is_refused() {
        let sim = SimulatedTable::new(TableConfig::default()).unwrap();
        let (mut first, server1) = duplex(1024);
        let s = sim.clone();
        tokio::spawn(async move { s.serve_connection(server1, std::future::pending()).await });
        let header = format!("{HEADER}\r\n");
        assert_eq!(read_some(&mut first, header.len()).await, header.as_bytes());
        let (mut second, server2) = duplex(1024);
        let s = sim.clone();
        tokio::spawn(async move { s.serve_connection(server2, std::future::pending()).await });
        let refusal = b"ERR busy: another client is connected\r\n";
        assert_eq!(read_some(&mut second, refusal.len()).await, refusal);
        // A third one that arrives while the first is closing gets the line.
        let (mut third, server3) = duplex(1024);
        let s = sim.clone();
        tokio::spawn(async move { s.serve_connection(server3, std::future::pending()).await });
        tokio::time::sleep(Duration::from_millis(100)).await;
        drop(first);
        assert_eq!(read_some(&mut third, header.len()).await, header.as_bytes());
    }

    #[tokio::test(start_paused = true)]
    async fn shutdown_ends_the_session() {
        let sim = SimulatedTable::new(TableConfig::default()).unwrap();
        let (_client, server) = duplex(1024);
        let (tx, rx) = tokio::sync::oneshot::channel::<()>();
        let task = tokio::spawn(async move {
            sim.serve_connection(server, async {
                let _ = rx.await;
            })
            .await
        });
        tokio::time::sleep(Duration::from_millis(10)).await;
        tx.send(()).unwrap();
        task.await.unwrap().unwrap();
    }
}
