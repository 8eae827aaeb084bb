//! The server as a process: flags, logging, binding, and serving until SIGINT or SIGTERM. The
//! `spoofwatch-server` binary is this plus its allocator; the black-box tests that kill a server
//! (`kill -9`) run it as a process of their own.

use clap::Parser;
use tracing_subscriber::EnvFilter;

use crate::config::LogFormat;
use crate::{Config, serve};

async fn shutdown_signal() {
    let ctrl_c = async {
        let _ = tokio::signal::ctrl_c().await;
    };
    #[cfg(unix)]
    let terminate = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut signal) => {
                signal.recv().await;
            }
            Err(_) => std::future::pending::<()>().await,
        }
    };
    #[cfg(not(unix))]
    let terminate = std::future::pending::<()>();
    tokio::select! {
        _ = ctrl_c => {},
        _ = terminate => {},
    }
}

/// Logs to stderr, filtered by `SPOOFWATCH_LOG` (default `info`), as text or JSON lines.
fn init_logging(format: LogFormat) {
    let logs = tracing_subscriber::fmt()
        .with_env_filter(
            EnvFilter::try_from_env("SPOOFWATCH_LOG").unwrap_or_else(|_| EnvFilter::new("info")),
        )
        .with_writer(std::io::stderr)
        // With a closed stderr, reporting a failed log write would itself panic (eprintln!) and
        // kill the server; a lost log line must not.
        .log_internal_errors(false);
    match format {
        LogFormat::Text => logs
            .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
            .init(),
        // Fields at the top level ({"timestamp","level","message","addr",...,"target"}), no
        // colour codes inside the strings.
        LogFormat::Json => logs.json().flatten_event(true).with_ansi(false).init(),
    }
}

/// Connections the kernel queues before the server accepts them. A balancer opens its connections to
/// a replica all at once when thousands of vehicles start (or reconnect) together, while the
/// replica is busy attaching their sessions; a connect dropped from a full queue is retried only
/// after a second, beyond a balancer's connect timeout. The kernel caps it at
/// `net.core.somaxconn`.
const LISTEN_BACKLOG: u32 = 4096;

/// The detection listener, with [`LISTEN_BACKLOG`].
fn listen(addr: std::net::SocketAddr) -> std::io::Result<tokio::net::TcpListener> {
    let socket = if addr.is_ipv4() {
        tokio::net::TcpSocket::new_v4()?
    } else {
        tokio::net::TcpSocket::new_v6()?
    };
    socket.set_reuseaddr(true)?;
    socket.bind(addr)?;
    socket.listen(LISTEN_BACKLOG)
}

/// The whole `spoofwatch-server` process: parses the flags, sets up logging, binds, logs the
/// address (`spoofwatch-server listening addr=...`) and serves until SIGINT or SIGTERM.
pub async fn run() -> std::process::ExitCode {
    // Parsed first so that the log format applies to every line (clap prints its own errors).
    let config = Config::parse();
    init_logging(config.log_format);
    let listener = match listen(config.listen) {
        Ok(listener) => listener,
        Err(error) => {
            tracing::error!(%error, listen = %config.listen, "cannot listen");
            return std::process::ExitCode::FAILURE;
        }
    };
    match listener.local_addr() {
        Ok(addr) => {
            tracing::info!(%addr, database = %config.database, "spoofwatch-server listening")
        }
        Err(error) => tracing::warn!(%error, "listening (address unknown)"),
    }
    match serve(config, listener, shutdown_signal()).await {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(error) => {
            tracing::error!(%error, "server failed");
            std::process::ExitCode::FAILURE
        }
    }
}
