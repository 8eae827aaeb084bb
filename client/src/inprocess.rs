//! A Spoofwatch server running inside this process, on a loopback port with a temporary database:
//! for `spoofwatch demo`, `spoofwatch bench` without `--server`, and end-to-end tests.

use std::net::SocketAddr;

use spoofwatch_server::{Config, ServerError, serve};
use tokio::net::TcpListener;
use tokio::sync::oneshot;
use tokio::task::JoinHandle;

use crate::error::ClientError;

/// Seconds the in-process server waits for streams and jobs when shutting down.
const SHUTDOWN_GRACE_SECS: u64 = 2;

/// A running in-process server. Call [`InProcessServer::shutdown`] to stop it cleanly; dropping it
/// only signals the shutdown.
#[derive(Debug)]
pub struct InProcessServer {
    addr: SocketAddr,
    stop: Option<oneshot::Sender<()>>,
    task: Option<JoinHandle<Result<(), ServerError>>>,
    // Held so the database outlives the server; removed on drop.
    database_dir: tempfile::TempDir,
}

impl InProcessServer {
    /// Starts a server on 127.0.0.1 (an ephemeral port) with a fresh database in a temporary
    /// directory, no auth token and no data directory.
    pub async fn start() -> Result<Self, ClientError> {
        let database_dir = tempfile::Builder::new()
            .prefix("spoofwatch-")
            .tempdir()
            .map_err(|source| ClientError::Io {
                context: "creating a temporary database directory".into(),
                source,
            })?;
        let database = database_dir.path().join("spoofwatch.db");
        let mut config = Config::with_database(database.to_string_lossy().into_owned());
        // Environment fallbacks meant for a real deployment must not leak into a private server.
        config.auth_token = None;
        config.data_dir = None;
        config.shutdown_grace_secs = SHUTDOWN_GRACE_SECS;
        let listener = TcpListener::bind(("127.0.0.1", 0))
            .await
            .map_err(|source| ClientError::Io {
                context: "binding 127.0.0.1:0".into(),
                source,
            })?;
        let addr = listener.local_addr().map_err(|source| ClientError::Io {
            context: "reading the listening address".into(),
            source,
        })?;
        let (stop, stopped) = oneshot::channel::<()>();
        let task = tokio::spawn(serve(config, listener, async {
            let _ = stopped.await;
        }));
        Ok(Self {
            addr,
            stop: Some(stop),
            task: Some(task),
            database_dir,
        })
    }

    /// The server's URL, e.g. `http://127.0.0.1:40123`.
    pub fn url(&self) -> String {
        format!("http://{}", self.addr)
    }

    /// Where the server listens.
    pub fn addr(&self) -> SocketAddr {
        self.addr
    }

    /// The temporary directory holding the database.
    pub fn database_dir(&self) -> &std::path::Path {
        self.database_dir.path()
    }

    /// Signals the shutdown and waits for the server's drain to finish.
    pub async fn shutdown(mut self) -> Result<(), ClientError> {
        if let Some(stop) = self.stop.take() {
            let _ = stop.send(());
        }
        let Some(task) = self.task.take() else {
            return Ok(());
        };
        match task.await {
            Ok(Ok(())) => Ok(()),
            Ok(Err(error)) => Err(ClientError::Server(error.to_string())),
            Err(error) => Err(ClientError::Server(format!("server task failed: {error}"))),
        }
    }
}

impl Drop for InProcessServer {
    fn drop(&mut self) {
        if let Some(stop) = self.stop.take() {
            let _ = stop.send(());
        }
    }
}
