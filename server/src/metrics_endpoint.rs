//! The `GET /metrics` endpoint on `--metrics-listen`: installs the recorder of
//! [`crate::telemetry`], sets the gauges that mirror the server's state (sessions, the outbox,
//! jobs, the active model) at each scrape, and renders every metric.
//!
//! It sits above the subsystems it reads and owns no metric of its own: names, help texts and
//! recording calls live in `crate::telemetry`. Nothing below the server's assembly imports it.
//!
//! Its port is open to anyone who can reach it, so it serves HTTP/1 with bounds of its own: at
//! most [`MAX_CONNECTIONS`] connections at once (more wait in the listen backlog, holding no
//! descriptor of the server's), and a connection that sends no complete request headers within
//! [`HEADER_READ_TIMEOUT`] (silent, or idle after a scrape) is closed. Silent connections
//! therefore cannot take the descriptors the gRPC port needs.

use std::sync::{Arc, Mutex, PoisonError};
use std::time::Duration;

use hyper::server::conn::http1;
use hyper_util::rt::{TokioIo, TokioTimer};
use hyper_util::service::TowerToHyperService;
use metrics::{counter, gauge};
use metrics_exporter_prometheus::{BuildError, PrometheusHandle};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::Semaphore;
use tokio_util::sync::CancellationToken;

use crate::detection::SessionManager;
use crate::jobs::JobManager;
use crate::models::Registry;
use crate::outbox::SessionOutbox;
use crate::store::FaultKind;
use crate::telemetry::{
    self, ACTIVE_MODEL_INFO, ALARM_BACKLOG, ALARM_DROPPED_ONSETS, ALARM_FAILED_BATCHES,
    ALARM_INVALID, ALARM_STORED, JOBS, SESSIONS_CONNECTED, SESSIONS_OPEN, SNAPSHOT_BACKLOG,
    SNAPSHOT_LAG, SNAPSHOT_STORED,
};

/// How often histogram samples are folded into their buckets between scrapes.
const UPKEEP_PERIOD: Duration = Duration::from_secs(5);

/// Longest a connection may take to send a request's headers, counted from when the server
/// starts waiting for it: a scraper sends at once, so this also ends idle keep-alive connections.
pub const HEADER_READ_TIMEOUT: Duration = Duration::from_secs(10);

/// Most connections served at once (a Prometheus server or two need one each).
pub const MAX_CONNECTIONS: usize = 64;

/// Pause after a failed accept (e.g. out of descriptors) before the next one.
const ACCEPT_RETRY: Duration = Duration::from_millis(100);

/// Installs the process-wide recorder (see [`telemetry::install`]) with every store fault kind
/// counted from zero.
pub fn install() -> Result<PrometheusHandle, BuildError> {
    telemetry::install(FaultKind::ALL.map(FaultKind::label))
}

/// The server state the scrape-time gauges mirror.
#[derive(Debug, Clone)]
pub struct Sources {
    pub sessions: Arc<SessionManager>,
    pub outbox: Arc<SessionOutbox>,
    pub jobs: Arc<JobManager>,
    pub registry: Arc<Registry>,
}

/// What the endpoint holds: the recorder's handle, the sources, and the last active model shown
/// (so that a change sets the old model's series to 0).
#[derive(Debug)]
struct Endpoint {
    handle: PrometheusHandle,
    sources: Sources,
    shown_model: Mutex<Option<String>>,
}

impl Endpoint {
    /// Sets the mirrored gauges from the server's state, then renders every metric.
    fn scrape(&self) -> String {
        let Sources {
            sessions,
            outbox,
            jobs,
            registry,
        } = &self.sources;
        let (open, connected) = sessions.counts();
        gauge!(SESSIONS_OPEN).set(open as f64);
        gauge!(SESSIONS_CONNECTED).set(connected as f64);
        let outbox = outbox.stats();
        gauge!(ALARM_BACKLOG).set(outbox.backlog as f64);
        counter!(ALARM_STORED).absolute(outbox.written);
        counter!(ALARM_FAILED_BATCHES).absolute(outbox.failed_batches);
        counter!(ALARM_DROPPED_ONSETS).absolute(outbox.dropped_onsets);
        counter!(ALARM_INVALID).absolute(outbox.invalid);
        gauge!(SNAPSHOT_BACKLOG).set(outbox.snapshot_backlog as f64);
        gauge!(SNAPSHOT_LAG).set(outbox.snapshot_lag.as_secs_f64());
        counter!(SNAPSHOT_STORED).absolute(outbox.snapshots_written);
        let (queued, running) = jobs.counts();
        gauge!(JOBS, "state" => "queued").set(queued as f64);
        gauge!(JOBS, "state" => "running").set(running as f64);
        let active = registry.active_name().map(|name| name.to_string());
        let mut shown = self
            .shown_model
            .lock()
            .unwrap_or_else(PoisonError::into_inner);
        if *shown != active {
            if let Some(old) = shown.take() {
                gauge!(ACTIVE_MODEL_INFO, "model" => old).set(0);
            }
            if let Some(new) = &active {
                gauge!(ACTIVE_MODEL_INFO, "model" => new.clone()).set(1);
            }
            *shown = active;
        }
        drop(shown);
        self.handle.render()
    }
}

async fn metrics_page(
    axum::extract::State(endpoint): axum::extract::State<Arc<Endpoint>>,
) -> impl axum::response::IntoResponse {
    (
        [(
            axum::http::header::CONTENT_TYPE,
            "text/plain; version=0.0.4; charset=utf-8",
        )],
        endpoint.scrape(),
    )
}

/// Serves `GET /metrics` on `listener` until `stop` is cancelled, and folds histogram samples into
/// their buckets every few seconds meanwhile.
pub async fn serve_metrics(
    listener: TcpListener,
    handle: PrometheusHandle,
    sources: Sources,
    stop: CancellationToken,
) {
    let upkeep = {
        let (handle, stop) = (handle.clone(), stop.clone());
        tokio::spawn(async move {
            let mut tick = tokio::time::interval(UPKEEP_PERIOD);
            loop {
                tokio::select! {
                    _ = stop.cancelled() => break,
                    _ = tick.tick() => handle.run_upkeep(),
                }
            }
        })
    };
    let endpoint = Arc::new(Endpoint {
        handle,
        sources,
        shown_model: Mutex::new(None),
    });
    let app = axum::Router::new()
        .route("/metrics", axum::routing::get(metrics_page))
        .with_state(endpoint);
    let connections = Arc::new(Semaphore::new(MAX_CONNECTIONS));
    loop {
        // A free slot first: beyond the cap, connections wait in the kernel's backlog.
        let permit = tokio::select! {
            _ = stop.cancelled() => break,
            permit = Arc::clone(&connections).acquire_owned() => match permit {
                Ok(permit) => permit,
                Err(_) => break,
            },
        };
        let stream = tokio::select! {
            _ = stop.cancelled() => break,
            accepted = listener.accept() => match accepted {
                Ok((stream, _)) => stream,
                Err(error) => {
                    tracing::warn!(%error, "accepting a metrics connection");
                    tokio::time::sleep(ACCEPT_RETRY).await;
                    continue;
                }
            },
        };
        let app = app.clone();
        let stop = stop.clone();
        tokio::spawn(async move {
            serve_connection(stream, app, stop).await;
            drop(permit);
        });
    }
    // Every connection has ended once all the slots are free again.
    let _ = connections.acquire_many(MAX_CONNECTIONS as u32).await;
    upkeep.abort();
}

/// Serves one connection until it closes, times out, or `stop` ends it after its current request.
async fn serve_connection(stream: TcpStream, app: axum::Router, stop: CancellationToken) {
    let mut builder = http1::Builder::new();
    builder
        .timer(TokioTimer::new())
        .header_read_timeout(HEADER_READ_TIMEOUT);
    let connection = builder.serve_connection(TokioIo::new(stream), TowerToHyperService::new(app));
    let mut connection = std::pin::pin!(connection);
    let served = tokio::select! {
        served = connection.as_mut() => served,
        _ = stop.cancelled() => {
            connection.as_mut().graceful_shutdown();
            connection.await
        }
    };
    if let Err(error) = served {
        // A client gone or too slow: its business, not the server's.
        tracing::debug!(%error, "metrics connection ended");
    }
}
