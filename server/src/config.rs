//! Server configuration: flags with `SPOOFWATCH_*` environment fallbacks, defaults that work on a
//! fresh machine.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

/// Everything the server needs to start.
#[derive(Clone, Debug, clap::Parser)]
#[command(
    name = "spoofwatch-server",
    version,
    about = "Spoofwatch GNSS-spoofing detection gRPC service"
)]
pub struct Config {
    /// Address to listen on.
    #[arg(long, env = "SPOOFWATCH_LISTEN", default_value = "127.0.0.1:50051")]
    pub listen: SocketAddr,
    /// SQLite database (file path or sqlite:// URL); created and migrated on first start.
    #[arg(long, env = "SPOOFWATCH_DATABASE", default_value = "spoofwatch.db")]
    pub database: String,
    /// Directory ImportDataset may read CSV files from (nothing outside it). Unset: imports refused.
    #[arg(long, env = "SPOOFWATCH_DATA_DIR")]
    pub data_dir: Option<PathBuf>,
    /// Most vehicle sessions held in memory.
    #[arg(long, env = "SPOOFWATCH_MAX_SESSIONS", default_value_t = 100_000)]
    pub max_sessions: usize,
    /// Seconds after which a session without a stream is evicted.
    #[arg(long, env = "SPOOFWATCH_SESSION_IDLE_SECS", default_value_t = 900)]
    pub session_idle_secs: u64,
    /// Most samples in one batch.
    #[arg(long, env = "SPOOFWATCH_MAX_BATCH_SAMPLES", default_value_t = 1000)]
    pub max_batch_samples: usize,
    /// Largest gRPC message accepted (bytes).
    #[arg(long, env = "SPOOFWATCH_MAX_MESSAGE_BYTES", default_value_t = 4 << 20)]
    pub max_message_bytes: usize,
    /// Training/evaluation jobs running at once (the rest queue).
    #[arg(long, env = "SPOOFWATCH_MAX_RUNNING_JOBS", default_value_t = 1)]
    pub max_running_jobs: usize,
    /// Jobs queued or running at once; more are refused.
    #[arg(long, env = "SPOOFWATCH_MAX_PENDING_JOBS", default_value_t = 16)]
    pub max_pending_jobs: usize,
    /// Seconds the shutdown waits for streams and jobs before closing anyway.
    #[arg(long, env = "SPOOFWATCH_SHUTDOWN_GRACE_SECS", default_value_t = 10)]
    pub shutdown_grace_secs: u64,
    /// Require `authorization: Bearer <token>` on every call except health checks.
    #[arg(long, env = "SPOOFWATCH_AUTH_TOKEN", hide_env_values = true)]
    pub auth_token: Option<String>,
}

impl Config {
    /// Defaults for a database path (tests, the demo).
    pub fn with_database(database: impl Into<String>) -> Self {
        use clap::Parser;
        let mut config = Self::parse_from(["spoofwatch-server"]);
        config.database = database.into();
        config
    }

    pub fn session_idle(&self) -> Duration {
        Duration::from_secs(self.session_idle_secs)
    }

    pub fn shutdown_grace(&self) -> Duration {
        Duration::from_secs(self.shutdown_grace_secs)
    }
}
