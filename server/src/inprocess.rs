//! A Spoofwatch server running inside this process on a loopback port: the one used by the CLI's
//! `demo`/`bench`, the client's end-to-end tests and the black-box test crate. It only starts and
//! stops [`crate::serve`]; it must not configure anything beyond what its caller asks.

use std::net::SocketAddr;

use tokio::net::TcpListener;
use tokio::sync::oneshot;
use tokio::task::JoinHandle;

use crate::{Config, ServerError, serve_with_metrics};

/// Seconds the in-process server waits for streams and jobs when shutting down.
const SHUTDOWN_GRACE_SECS: u64 = 2;

/// Why an in-process server could not start or stopped with an error.
#[derive(Debug, thiserror::Error)]
pub enum InProcessError {
    /// Creating the temporary directory or binding the loopback port failed.
    #[error("{context}: {source}")]
    Io {
        /// What was being done.
        context: &'static str,
        /// The I/O error.
        #[source]
        source: std::io::Error,
    },
    /// The server failed.
    #[error(transparent)]
    Server(#[from] ServerError),
    /// The server task panicked or was aborted.
    #[error("server task failed: {0}")]
    Task(#[from] tokio::task::JoinError),
}

/// A running in-process server. Call [`InProcessServer::shutdown`] to stop it cleanly; dropping it
/// only signals the shutdown.
#[derive(Debug)]
pub struct InProcessServer {
    addr: SocketAddr,
    metrics_addr: Option<SocketAddr>,
    stop: Option<oneshot::Sender<()>>,
    task: Option<JoinHandle<Result<(), ServerError>>>,
    // Held so a temporary database outlives the server; removed on drop.
    database_dir: Option<tempfile::TempDir>,
}

impl InProcessServer {
    /// Starts a server on 127.0.0.1 (an ephemeral port) with a fresh database in a temporary
    /// directory, from [`Config::default`] (no environment, no auth token, no data directory) as
    /// changed by `config_tweak`.
    pub async fn start(config_tweak: impl FnOnce(&mut Config)) -> Result<Self, InProcessError> {
        let database_dir = tempfile::Builder::new()
            .prefix("spoofwatch-")
            .tempdir()
            .map_err(|source| InProcessError::Io {
                context: "creating a temporary database directory",
                source,
            })?;
        let database = database_dir.path().join("spoofwatch.db");
        let mut config = Config::with_database(database.to_string_lossy().into_owned());
        config.shutdown_grace_secs = SHUTDOWN_GRACE_SECS;
        config_tweak(&mut config);
        Self::serve_on_loopback(config, Some(database_dir), 0).await
    }

    /// Starts a server with exactly `config` (its own database; e.g. one a test reopens after a
    /// restart) on 127.0.0.1, an ephemeral port; `config.listen` is not used, and metrics (when
    /// `config.metrics_listen` is set) are served on another ephemeral loopback port.
    pub async fn start_with(config: Config) -> Result<Self, InProcessError> {
        Self::serve_on_loopback(config, None, 0).await
    }

    /// [`InProcessServer::start_with`] on 127.0.0.1:`port`, e.g. the port of a server that just
    /// stopped, so that its clients reconnect to the restarted one.
    pub async fn start_on_port(config: Config, port: u16) -> Result<Self, InProcessError> {
        Self::serve_on_loopback(config, None, port).await
    }

    async fn serve_on_loopback(
        config: Config,
        database_dir: Option<tempfile::TempDir>,
        port: u16,
    ) -> Result<Self, InProcessError> {
        let listener = TcpListener::bind(("127.0.0.1", port))
            .await
            .map_err(|source| InProcessError::Io {
                context: "binding a loopback port",
                source,
            })?;
        let addr = listener.local_addr().map_err(|source| InProcessError::Io {
            context: "reading the listening address",
            source,
        })?;
        let metrics_listener = match config.metrics_listen {
            Some(_) => Some(
                TcpListener::bind(("127.0.0.1", 0))
                    .await
                    .map_err(|source| InProcessError::Io {
                        context: "binding 127.0.0.1:0 for metrics",
                        source,
                    })?,
            ),
            None => None,
        };
        let metrics_addr = match &metrics_listener {
            Some(listener) => Some(listener.local_addr().map_err(|source| InProcessError::Io {
                context: "reading the metrics address",
                source,
            })?),
            None => None,
        };
        let (stop, stopped) = oneshot::channel::<()>();
        let task = tokio::spawn(serve_with_metrics(
            config,
            listener,
            metrics_listener,
            async {
                // A dropped sender also means "stop".
                let _ = stopped.await;
            },
        ));
        Ok(Self {
            addr,
            metrics_addr,
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

    /// Where the server answers `GET /metrics` (when started with `config.metrics_listen`).
    pub fn metrics_addr(&self) -> Option<SocketAddr> {
        self.metrics_addr
    }

    /// The temporary directory holding the database of a server from [`Self::start`].
    pub fn database_dir(&self) -> Option<&std::path::Path> {
        self.database_dir.as_ref().map(tempfile::TempDir::path)
    }

    /// Signals the shutdown and waits for the server's drain to finish.
    pub async fn shutdown(mut self) -> Result<(), InProcessError> {
        self.trigger_shutdown();
        match self.task.take() {
            Some(task) => Ok(task.await??),
            None => Ok(()),
        }
    }

    /// Signals the shutdown (the server starts draining) without waiting; idempotent.
    pub fn trigger_shutdown(&mut self) {
        if let Some(stop) = self.stop.take() {
            // The server may already have stopped on its own; then there is nobody to tell.
            let _ = stop.send(());
        }
    }
}

impl Drop for InProcessServer {
    fn drop(&mut self) {
        self.trigger_shutdown();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn starts_on_loopback_and_shuts_down_cleanly() {
        let server = InProcessServer::start(|config| config.max_sessions = 10)
            .await
            .expect("the server starts");
        assert!(server.addr().ip().is_loopback());
        assert_eq!(server.url(), format!("http://{}", server.addr()));
        assert!(server.database_dir().is_some_and(std::path::Path::exists));
        server.shutdown().await.expect("a clean shutdown");
    }
}
