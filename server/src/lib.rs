//! Spoofwatch gRPC service over `spoofwatch-core`: detection sessions, the model registry, datasets,
//! training/evaluation jobs as long-running operations, health and reflection.
//!
//! [`serve`] is the whole server; [`process`] is the `spoofwatch-server` binary's (flags, logging,
//! binding, signals); [`inprocess`] runs it inside another process.
//!
//! Layout, one home per duty, from the top down:
//! - the server's life: `app` (assembly of every subsystem), `router` (what is served, with gzip,
//!   limits and the `access` guard), `background` (the tasks beside the server), `drain` (the ordered,
//!   bounded shutdown), `metrics_endpoint` (`GET /metrics`), `server_error`;
//! - the subsystems, each a logic type with its own error and a gRPC service at the edge:
//!   `detection` (sessions + DetectionService), `models` (registry + ModelService), `datasets`
//!   (catalog + DatasetService), `jobs` (service → manager → runner), `alarms` (ListAlarms and
//!   WatchAlarms), `incidents` (the area-incident correlator, by lease, and ListIncidents,
//!   GetIncident, WatchIncidents, EndIncident);
//! - below them: `event_log` (the live feed and resumable watch of a stored event log, for alarms
//!   and incidents), `outbox` (the session outbox: alarm events and session snapshots on their way
//!   to the store), `storage_health` (database file and outbox health, reported through gRPC
//!   health), `store` (the only SQL, on SQLite or PostgreSQL), `telemetry` (every metric's recording), `error` (the one error → status
//!   mapping), `fault` (a server-side fault inside a subsystem's error), `edge` (request decoding
//!   shared by the services), `status`, `identity` (ids and digests), `work` (the bounded pool
//!   of CPU-heavy work, off the runtime's threads);
//! - transport: `incoming` (connections vetted for a first message), `tls` (the TLS files read and
//!   checked at startup), `idle` (the stream idle timeout).
//!
//! Wire conversions live in `spoofwatch_proto::wire`.
//!
//! Layers, from the top down: background, drain | router | app, error, metrics_endpoint |
//! detection, server_error, storage_health | outbox, process, tls | alarms, config, jobs | datasets, incidents | access, edge, event_log, incoming, models | coalesce, error_chain, fault,
//! identity, idle, inprocess, status, store, telemetry, work. A module imports only from its own
//! layer's others or from below (`scripts/fence.py` holds CI to it).

mod access;
mod alarms;
mod app;
mod background;
mod coalesce;
pub mod config;
mod datasets;
mod detection;
mod drain;
mod edge;
mod error;
mod error_chain;
mod event_log;
mod fault;
mod fault_log;
mod identity;
mod idle;
mod incidents;
mod incoming;
pub mod inprocess;
mod jobs;
mod metrics_endpoint;
pub mod models;
mod outbox;
pub mod process;
mod replies;
mod router;
mod server_error;
mod shadow;
mod status;
mod storage_health;
pub mod store;
mod telemetry;
pub mod tls;
mod work;

use std::future::Future;

use tokio::net::TcpListener;
use tonic::transport::Server;

pub use config::Config;
pub use server_error::ServerError;

use crate::app::App;
use crate::background::Background;

/// Runs the server on `listener` until `shutdown` resolves, then drains: health turns NOT_SERVING,
/// streams end with UNAVAILABLE, running jobs are cancelled and recorded, open alarms are closed, and
/// the whole drain is bounded by `config.shutdown_grace_secs`. With `config.metrics_listen`, metrics
/// are served there too (see [`serve_with_metrics`]).
pub async fn serve(
    config: Config,
    listener: TcpListener,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> Result<(), ServerError> {
    let metrics = match config.metrics_listen {
        Some(addr) => Some(
            TcpListener::bind(addr)
                .await
                .map_err(|source| ServerError::MetricsListen { addr, source })?,
        ),
        None => None,
    };
    serve_with_metrics(config, listener, metrics, shutdown).await
}

/// [`serve`], with Prometheus metrics at `GET /metrics` on `metrics_listener` when given (instead
/// of binding `config.metrics_listen`); the metrics endpoint stops when the server has drained.
pub async fn serve_with_metrics(
    config: Config,
    listener: TcpListener,
    metrics_listener: Option<TcpListener>,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> Result<(), ServerError> {
    // Installed before anything is counted (a store fault at startup included).
    let metrics = match metrics_listener {
        Some(listener) => Some((listener, metrics_endpoint::install()?)),
        None => None,
    };
    // First, so that a wrong TLS file (or a key that is not the certificate's) stops the server
    // before it touches the database.
    let server = tls::configure(Server::builder(), &config)?;
    let app = App::assemble(&config).await?;
    let routes = router::build(server, &app, &config).await?;
    let background = Background::start(&app, &config, routes.health.clone(), metrics);
    let grace = config.shutdown_grace();
    let drained = drain::on_shutdown(
        shutdown,
        &app,
        routes.health,
        background.stop_outbox_writer.clone(),
        grace,
    );
    let incoming = incoming::vetted(listener, config.handshake_timeout());
    let server = routes.router.serve_with_incoming_shutdown(incoming, async {
        let _ = drained.await;
    });
    let result = drain::serve_bounded(server, &app.draining, grace).await;
    background.stop(&app.store).await;
    tracing::info!("server stopped");
    result
}
