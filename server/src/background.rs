//! The tasks that run beside the server: the session outbox's writer, the alarm and incident
//! feeds' followers, the incident correlator, the storage watch, the shadow's follower, job leases, idle-session eviction,
//! following the active model, the identity files' reload and the metrics endpoint. They start once
//! the server is assembled and stop, in order, after it has drained.
//!
//! It owns their lifetimes, not their work: each loop lives with its subsystem (idle eviction,
//! which only calls the session manager, excepted).

use std::sync::Arc;
use std::time::Duration;

use metrics_exporter_prometheus::PrometheusHandle;
use tokio::net::TcpListener;
use tokio::task::JoinHandle;
use tokio_util::sync::CancellationToken;
use tonic_health::server::HealthReporter;

use crate::access;
use crate::app::App;
use crate::config::Config;
use crate::detection::SessionManager;
use crate::incidents::correlator::IncidentCorrelator;
use crate::metrics_endpoint::{self, Sources};
use crate::models::ACTIVE_MODEL_POLL;
use crate::router::DATABASE_SERVICES;
use crate::storage_health;
use crate::store::Store;

/// The metrics endpoint's listener and the installed recorder it renders.
pub type MetricsEndpoint = (TcpListener, PrometheusHandle);

/// The running background tasks.
pub struct Background {
    outbox_writer: JoinHandle<()>,
    /// Tells the writer to store what is queued and stop (the drain cancels it once sessions are
    /// saved).
    pub stop_outbox_writer: CancellationToken,
    alarm_follower: JoinHandle<()>,
    incident_follower: JoinHandle<()>,
    stop_alarm_feed: CancellationToken,
    incident_correlator: JoinHandle<()>,
    storage_watch: JoinHandle<()>,
    job_leases: JoinHandle<()>,
    evictor: JoinHandle<()>,
    active_model: JoinHandle<()>,
    /// Follows the stored shadow and stores its counts; finishes the shadow's work at the drain.
    shadows: JoinHandle<()>,
    identity_files: JoinHandle<()>,
    metrics: Option<JoinHandle<()>>,
    stop_metrics: CancellationToken,
}

impl Background {
    /// Starts every task of `app`; the loops that must end with the drain follow `app.draining`.
    pub fn start(
        app: &App,
        config: &Config,
        health: HealthReporter,
        metrics: Option<MetricsEndpoint>,
    ) -> Self {
        let stop_outbox_writer = CancellationToken::new();
        let outbox_writer = {
            let (outbox, store) = (Arc::clone(&app.outbox), app.store.clone());
            let (stop, grace) = (stop_outbox_writer.clone(), config.shutdown_grace());
            tokio::spawn(async move { outbox.run(store, stop, grace).await })
        };
        // WatchAlarms' live events: the stored event log of every replica, read after each local
        // commit and every 200 ms.
        let stop_alarm_feed = CancellationToken::new();
        let alarm_follower = {
            let (feed, outbox, store) = (
                Arc::clone(&app.alarm_feed),
                Arc::clone(&app.outbox),
                app.store.clone(),
            );
            let stop = stop_alarm_feed.clone();
            tokio::spawn(async move { feed.follow(store, outbox.stored_events(), stop).await })
        };
        let incident_follower = {
            let (feed, stored, store) = (
                Arc::clone(&app.incident_feed),
                Arc::clone(&app.incidents_stored),
                app.store.clone(),
            );
            let stop = stop_alarm_feed.clone();
            tokio::spawn(async move { feed.follow(store, &stored, stop).await })
        };
        // Area incidents: computed by one server of the database at a time (by lease), until the
        // drain starts; the lease is then given up so that another server takes over at once.
        let incident_correlator = tokio::spawn(
            IncidentCorrelator::new(
                app.store.clone(),
                app.incident_settings,
                &app.instance,
                Arc::clone(&app.incidents_stored),
                Arc::clone(&app.incident_areas),
            )
            .run(app.draining.clone()),
        );
        let storage_watch = tokio::spawn(storage_health::watch_storage(
            app.store.clone(),
            Arc::clone(&app.outbox),
            health,
            DATABASE_SERVICES.to_vec(),
            app.draining.clone(),
        ));
        // Job leases: renewed, and other replicas' abandoned jobs failed, until the drain starts (the
        // drain is far shorter than a lease).
        let job_leases = tokio::spawn(Arc::clone(&app.jobs).keep_leases(app.draining.clone()));
        let period =
            (config.session_idle() / 4).clamp(Duration::from_secs(1), Duration::from_secs(30));
        let evictor = tokio::spawn(evict_idle_sessions(
            Arc::clone(&app.sessions),
            period,
            app.draining.clone(),
        ));
        let active_model = tokio::spawn({
            let registry = Arc::clone(&app.registry);
            let stop = app.draining.clone();
            async move {
                registry
                    .keep_following_active_model(ACTIVE_MODEL_POLL, stop)
                    .await
            }
        });
        let shadows = tokio::spawn({
            let shadows = Arc::clone(&app.shadows);
            let stop = app.draining.clone();
            async move { shadows.keep_following(stop).await }
        });
        let identity_files = tokio::spawn(access::keep_current(
            Arc::clone(&app.access),
            app.draining.clone(),
        ));
        let stop_metrics = CancellationToken::new();
        let metrics = metrics.map(|(listener, handle)| {
            match listener.local_addr() {
                Ok(addr) => tracing::info!(%addr, "metrics listening (GET /metrics)"),
                Err(error) => tracing::warn!(%error, "metrics listening (address unknown)"),
            }
            let sources = Sources {
                sessions: Arc::clone(&app.sessions),
                outbox: Arc::clone(&app.outbox),
                jobs: Arc::clone(&app.jobs),
                registry: Arc::clone(&app.registry),
            };
            tokio::spawn(metrics_endpoint::serve_metrics(
                listener,
                handle,
                sources,
                stop_metrics.clone(),
            ))
        });
        Self {
            outbox_writer,
            stop_outbox_writer,
            alarm_follower,
            incident_follower,
            stop_alarm_feed,
            incident_correlator,
            storage_watch,
            job_leases,
            evictor,
            active_model,
            shadows,
            identity_files,
            metrics,
            stop_metrics,
        }
    }

    /// Stops every task once the server has drained: the writer stores what is queued (bounded by
    /// the grace while the database refuses), then the store closes; scrapes are answered until
    /// the end, and an open scrape connection gets a second to finish.
    pub async fn stop(self, store: &Store) {
        self.evictor.abort();
        self.active_model.abort();
        self.identity_files.abort();
        self.storage_watch.abort();
        self.stop_alarm_feed.cancel();
        let _ = self.alarm_follower.await;
        let _ = self.incident_follower.await;
        // It stops with the drain (giving its lease up); bounded, as a database that does not
        // answer must not hold the shutdown.
        let mut correlator = self.incident_correlator;
        if tokio::time::timeout(Duration::from_secs(2), &mut correlator)
            .await
            .is_err()
        {
            correlator.abort();
        }
        self.job_leases.abort();
        // Bounded like the correlator: the shadow's queue is short, its writes are not waited for
        // beyond this.
        let mut shadows = self.shadows;
        if tokio::time::timeout(Duration::from_secs(2), &mut shadows)
            .await
            .is_err()
        {
            shadows.abort();
        }
        self.stop_outbox_writer.cancel();
        if let Err(error) = self.outbox_writer.await {
            tracing::error!(%error, "the alarm writer failed");
        }
        store.close().await;
        self.stop_metrics.cancel();
        if let Some(mut endpoint) = self.metrics
            && tokio::time::timeout(Duration::from_secs(1), &mut endpoint)
                .await
                .is_err()
        {
            endpoint.abort();
        }
    }
}

/// Evicts idle sessions without a stream every `period`, and ends the alarms of session snapshots
/// that expired, until `stop` is cancelled.
async fn evict_idle_sessions(
    sessions: Arc<SessionManager>,
    period: Duration,
    stop: CancellationToken,
) {
    let mut tick = tokio::time::interval(period);
    loop {
        tokio::select! {
            _ = stop.cancelled() => break,
            _ = tick.tick() => {
                let evicted = sessions.evict_idle().await;
                if evicted > 0 {
                    tracing::info!(evicted, "evicted idle sessions");
                }
                let abandoned = sessions.expire_snapshots().await;
                if abandoned > 0 {
                    tracing::info!(abandoned, "ended the alarms of session snapshots that expired");
                }
            }
        }
    }
}
