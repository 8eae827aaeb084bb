//! Spoofwatch gRPC service over `spoofwatch-core`: detection sessions, the model registry, datasets,
//! training/evaluation jobs as long-running operations, health and reflection.
//!
//! [`serve`] is the whole server; the `spoofwatch-server` binary only parses the configuration, sets
//! up logging, binds and waits for a signal; [`inprocess`] runs it inside another process.
//!
//! Layout, one home per concept: `models` (registry + ModelService), `datasets` (catalog +
//! DatasetService), `detection` (sessions + DetectionService), `alarms` (the outbox and background
//! writer of alarm events, the live feed that follows the stored event log + AlarmService), `jobs` (service → manager → runner),
//! `store` (the only SQL, on SQLite or PostgreSQL), `watch` (database file and alarm-writer health), `error` (the one error → status mapping), `fault` (a server-side fault
//! inside a subsystem's error), `edge` (request decoding shared by the services), `identity` (ids
//! and digests), `telemetry` (every Prometheus metric and the `/metrics` endpoint). Wire
//! conversions live in `spoofwatch_proto::wire`.
//!
//! Transport: `incoming` (connections vetted for a first message), `tls` (the TLS files read and
//! checked at startup), `idle` (the stream idle timeout); bearer auth is [`BearerAuth`] below.

mod alarms;
pub mod config;
mod datasets;
mod detection;
mod edge;
mod error;
mod fault;
mod identity;
mod idle;
mod incoming;
pub mod inprocess;
mod jobs;
pub mod models;
mod status;
pub mod store;
mod telemetry;
pub mod tls;
mod watch;

use std::future::Future;
use std::sync::Arc;
use std::time::Duration;

use spoofwatch_proto::longrunning::operations_server::OperationsServer;
use spoofwatch_proto::v1::alarm_service_server::AlarmServiceServer;
use spoofwatch_proto::v1::dataset_service_server::DatasetServiceServer;
use spoofwatch_proto::v1::detection_service_server::DetectionServiceServer;
use spoofwatch_proto::v1::model_service_server::ModelServiceServer;
use spoofwatch_proto::v1::training_service_server::TrainingServiceServer;
use tokio::net::TcpListener;
use tokio_util::sync::CancellationToken;
use tonic::codec::CompressionEncoding;
use tonic::server::NamedService;
use tonic::service::Interceptor;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::Server;
use tonic::{Request, Status};
use tonic_health::ServingStatus;

pub use config::Config;

use crate::alarms::feed::AlarmFeed;
use crate::alarms::service::AlarmApi;
use crate::alarms::{AlarmOutbox, OUTBOX_CAPACITY};
use crate::datasets::{Catalog, DatasetApi};
use crate::detection::{DetectionApi, SessionLimits, SessionManager};
use crate::idle::StreamIdle;
use crate::jobs::{JobManager, JobSettings, OperationsApi, Runner, TrainingApi};
use crate::models::{ModelApi, Registry, RegistryError};
use crate::store::{Store, StoreError, StoreOptions};
use crate::tls::TlsError;

/// Why the server could not start or run.
#[derive(Debug, thiserror::Error)]
pub enum ServerError {
    #[error("opening the database: {0}")]
    Store(#[from] StoreError),
    #[error("preparing the model registry: {0}")]
    Registry(#[from] RegistryError),
    #[error("reflection service: {0}")]
    Reflection(#[from] tonic_reflection::server::Error),
    #[error("TLS: {0}")]
    Tls(#[from] TlsError),
    #[error("serving: {0}")]
    Transport(#[from] tonic::transport::Error),
    #[error("listening for metrics on {addr}: {source}")]
    MetricsListen {
        addr: std::net::SocketAddr,
        source: std::io::Error,
    },
    #[error("installing the metrics recorder: {0}")]
    Metrics(#[from] metrics_exporter_prometheus::BuildError),
    #[error("configuration: {0}")]
    Config(String),
}

/// A generated service server that accepts gzip-compressed requests and compresses its replies
/// with gzip for clients that accept it (`grpc-accept-encoding`).
macro_rules! gzip {
    ($server:expr) => {
        $server
            .accept_compressed(CompressionEncoding::Gzip)
            .send_compressed(CompressionEncoding::Gzip)
    };
}

/// Checks `authorization: Bearer <token>` when a token is configured: the scheme in any case, the
/// token in constant time. Ours rather than tower-http's `ValidateRequestHeaderLayer::bearer`,
/// which matches the header with `==` (case-sensitive scheme, time depending on the token).
///
/// Health and reflection stay open on purpose: health is for load balancers and orchestrators that
/// hold no token, and reflection serves only the public schema (the `.proto` files of this
/// repository), no data. Whoever must not even reach them is kept out by mutual TLS.
#[derive(Clone)]
struct BearerAuth {
    expected: Option<Arc<str>>,
}

impl BearerAuth {
    /// `service` behind this check (every API service is; health and reflection are not).
    fn guard<S>(&self, service: S) -> InterceptedService<S, BearerAuth> {
        InterceptedService::new(service, self.clone())
    }
}

impl Interceptor for BearerAuth {
    fn call(&mut self, request: Request<()>) -> Result<Request<()>, Status> {
        let Some(expected) = &self.expected else {
            return Ok(request);
        };
        let presented = request
            .metadata()
            .get("authorization")
            .and_then(|v| v.to_str().ok())
            .and_then(bearer_token);
        match presented {
            Some(token) if tokens_match(token, expected) => Ok(request),
            _ => {
                telemetry::unauthenticated();
                Err(Status::unauthenticated("missing or wrong bearer token"))
            }
        }
    }
}

/// The token of an `authorization` value `Bearer <token>` (the scheme is case-insensitive, RFC
/// 9110 §11.1); `None` for another scheme or an empty token.
fn bearer_token(value: &str) -> Option<&str> {
    let (scheme, token) = value.trim().split_once(' ')?;
    let token = token.trim();
    (scheme.eq_ignore_ascii_case("bearer") && !token.is_empty()).then_some(token)
}

/// Compares in time independent of where the tokens differ (their length is not secret).
fn tokens_match(presented: &str, expected: &str) -> bool {
    use subtle::ConstantTimeEq;
    bool::from(presented.as_bytes().ct_eq(expected.as_bytes()))
}

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
    let metrics_handle = match metrics_listener {
        Some(_) => Some(telemetry::install()?),
        None => None,
    };
    // First, so that a wrong TLS file (or a key that is not the certificate's) stops the server
    // before it touches the database.
    let builder = tls::configure(Server::builder(), &config)?;
    let snapshot_policy = config.snapshot_policy().map_err(ServerError::Config)?;
    tracing::info!(
        transport = tls::transport(&config).as_str(),
        auth = if config.auth_token.is_some() {
            "bearer token"
        } else {
            "none"
        },
        stream_idle_s = config.stream_idle_secs,
        "transport settings"
    );
    let store = Store::open_with(
        &config.database,
        StoreOptions {
            max_bytes: config.database_max_bytes(),
        },
    )
    .await?;
    let instance = config.instance();
    tracing::info!(%instance, backend = ?store.kind(), "database opened");
    let registry = Arc::new(Registry::new(store.clone(), config.model_cache_bytes));
    registry.ensure_default_model().await?;
    let catalog = Catalog::new(store.clone(), config.data_dir.clone());

    let grace = config.shutdown_grace();
    // Also ends the alarms a previous run left open.
    let alarms = Arc::new(AlarmOutbox::new(&store, OUTBOX_CAPACITY).await?);
    let stop_alarm_writer = CancellationToken::new();
    let alarm_writer = {
        let alarms = Arc::clone(&alarms);
        let store = store.clone();
        let stop = stop_alarm_writer.clone();
        tokio::spawn(async move { alarms.run(store, stop, grace).await })
    };
    // WatchAlarms' live events: the stored event log of every replica, read after each local
    // commit and every 200 ms.
    let alarm_feed = Arc::new(AlarmFeed::new(&store).await?);
    let stop_alarm_feed = CancellationToken::new();
    let alarm_follower = {
        let (feed, alarms, store) = (Arc::clone(&alarm_feed), Arc::clone(&alarms), store.clone());
        let stop = stop_alarm_feed.clone();
        tokio::spawn(async move { feed.follow(store, alarms.stored_events(), stop).await })
    };

    let draining = CancellationToken::new();
    let sessions = Arc::new(SessionManager::new(
        Arc::clone(&registry),
        Arc::clone(&alarms),
        store.clone(),
        SessionLimits {
            max_sessions: config.max_sessions,
            idle: config.session_idle(),
            max_batch_samples: config.max_batch_samples,
        },
        snapshot_policy,
    ));
    let jobs = JobManager::new(
        Runner {
            store: store.clone(),
            registry: Arc::clone(&registry),
            catalog: catalog.clone(),
        },
        JobSettings {
            max_running: config.max_running_jobs,
            max_pending: config.max_pending_jobs,
        },
        instance.clone(),
    );
    let interrupted = jobs.fail_abandoned_at_start().await?;
    if interrupted > 0 {
        tracing::warn!(
            interrupted,
            "marked jobs left over by a previous run (or a stopped replica) as failed"
        );
    }
    let job_services = jobs::Jobs {
        manager: Arc::clone(&jobs),
        registry: Arc::clone(&registry),
    };

    let (health_reporter, health_service) = tonic_health::server::health_reporter();
    let health_service = gzip!(health_service);
    let reflection_v1 = tonic_reflection::server::Builder::configure()
        .register_encoded_file_descriptor_set(spoofwatch_proto::FILE_DESCRIPTOR_SET)
        .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
        // google.rpc error details (BadRequest, ...), so grpcurl can print ItemError statuses.
        .register_encoded_file_descriptor_set(tonic_types::pb::FILE_DESCRIPTOR_SET)
        .build_v1()?;
    let reflection_v1 = gzip!(reflection_v1);
    let reflection_v1alpha = tonic_reflection::server::Builder::configure()
        .register_encoded_file_descriptor_set(spoofwatch_proto::FILE_DESCRIPTOR_SET)
        .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
        .register_encoded_file_descriptor_set(tonic_types::pb::FILE_DESCRIPTOR_SET)
        .build_v1alpha()?;
    let reflection_v1alpha = gzip!(reflection_v1alpha);

    let auth = BearerAuth {
        expected: config.auth_token.as_deref().map(Arc::from),
    };
    let limit = config.max_message_bytes;
    let stream_idle = StreamIdle(config.stream_idle());
    let detection = gzip!(DetectionServiceServer::new(DetectionApi {
        sessions: Arc::clone(&sessions),
        shutdown: draining.clone(),
        stream_idle,
    }))
    .max_decoding_message_size(limit);
    let models = gzip!(ModelServiceServer::new(ModelApi {
        registry: Arc::clone(&registry),
        sessions: Arc::clone(&sessions),
        stream_idle,
    }))
    .max_decoding_message_size(limit);
    let datasets = gzip!(DatasetServiceServer::new(DatasetApi {
        catalog,
        stream_idle,
    }))
    .max_decoding_message_size(limit);
    let training = gzip!(TrainingServiceServer::new(TrainingApi {
        jobs: job_services.clone(),
    }))
    .max_decoding_message_size(limit);
    let operations = gzip!(OperationsServer::new(OperationsApi { jobs: job_services }))
        .max_decoding_message_size(limit);
    let alarm_service = gzip!(AlarmServiceServer::new(AlarmApi {
        store: store.clone(),
        feed: Arc::clone(&alarm_feed),
        shutdown: draining.clone(),
    }))
    .max_decoding_message_size(limit);

    let served = [
        DetectionServiceServer::<DetectionApi>::NAME,
        ModelServiceServer::<ModelApi>::NAME,
        DatasetServiceServer::<DatasetApi>::NAME,
        TrainingServiceServer::<TrainingApi>::NAME,
        OperationsServer::<OperationsApi>::NAME,
        // Listing, replay and live alarm events all read the database.
        AlarmServiceServer::<AlarmApi>::NAME,
    ];
    for service in served.iter().copied().chain([watch::STORAGE_HEALTH]) {
        health_reporter
            .set_service_status(service, ServingStatus::Serving)
            .await;
    }
    let storage_watch = tokio::spawn(watch::watch_storage(
        store.clone(),
        Arc::clone(&alarms),
        health_reporter.clone(),
        // Detection runs from memory; everything else needs the database.
        served[1..].to_vec(),
        draining.clone(),
    ));

    // Job leases: renewed, and other replicas' abandoned jobs failed, until the drain starts (the
    // drain is far shorter than a lease).
    let job_leases = tokio::spawn(Arc::clone(&jobs).keep_leases(draining.clone()));

    // Idle sessions without a stream are evicted in the background.
    let evictor = {
        let sessions = Arc::clone(&sessions);
        let draining = draining.clone();
        let period =
            (config.session_idle() / 4).clamp(Duration::from_secs(1), Duration::from_secs(30));
        tokio::spawn(async move {
            let mut tick = tokio::time::interval(period);
            loop {
                tokio::select! {
                    _ = draining.cancelled() => break,
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
        })
    };

    let stop_metrics = CancellationToken::new();
    let metrics_endpoint = match (metrics_listener, metrics_handle) {
        (Some(metrics_listener), Some(handle)) => {
            match metrics_listener.local_addr() {
                Ok(addr) => tracing::info!(%addr, "metrics listening (GET /metrics)"),
                Err(error) => tracing::warn!(%error, "metrics listening (address unknown)"),
            }
            let sources = telemetry::Sources {
                sessions: Arc::clone(&sessions),
                alarms: Arc::clone(&alarms),
                jobs: Arc::clone(&jobs),
                registry: Arc::clone(&registry),
            };
            Some(tokio::spawn(telemetry::serve_metrics(
                metrics_listener,
                handle,
                sources,
                stop_metrics.clone(),
            )))
        }
        _ => None,
    };

    // The drain: health first, then streams, then jobs, then alarms; tonic stops accepting after
    // this resolves.
    let (stop_tx, stop_rx) = tokio::sync::oneshot::channel::<()>();
    {
        let draining = draining.clone();
        let health = health_reporter.clone();
        let jobs = Arc::clone(&jobs);
        let sessions = Arc::clone(&sessions);
        let stop_alarm_writer = stop_alarm_writer.clone();
        tokio::spawn(async move {
            shutdown.await;
            tracing::info!("shutting down: health NOT_SERVING, draining streams and jobs");
            health
                .set_service_status("", tonic_health::ServingStatus::NotServing)
                .await;
            health
                .set_not_serving::<DetectionServiceServer<DetectionApi>>()
                .await;
            health
                .set_not_serving::<AlarmServiceServer<AlarmApi>>()
                .await;
            draining.cancel();
            jobs.shutdown(grace).await;
            sessions.save_all().await;
            stop_alarm_writer.cancel();
            let _ = stop_tx.send(());
        });
    }

    let incoming = incoming::vetted(listener, config.handshake_timeout());
    let router = builder
        .http2_keepalive_interval(Some(Duration::from_secs(30)))
        .http2_keepalive_timeout(Some(Duration::from_secs(10)))
        .add_service(health_service)
        .add_service(reflection_v1)
        .add_service(reflection_v1alpha)
        .add_service(auth.guard(detection))
        .add_service(auth.guard(models))
        .add_service(auth.guard(datasets))
        .add_service(auth.guard(training))
        .add_service(auth.guard(operations))
        .add_service(auth.guard(alarm_service));
    let server = router.serve_with_incoming_shutdown(incoming, async {
        let _ = stop_rx.await;
    });
    tokio::pin!(server);
    // Bounded drain: once draining starts, connections get `grace` to close.
    let result = tokio::select! {
        result = &mut server => result.map_err(ServerError::from),
        _ = async { draining.cancelled().await; tokio::time::sleep(grace + Duration::from_secs(1)).await } => {
            tracing::warn!("drain timed out; closing remaining connections");
            Ok(())
        }
    };
    evictor.abort();
    storage_watch.abort();
    stop_alarm_feed.cancel();
    let _ = alarm_follower.await;
    job_leases.abort();
    // The writer stores what is queued (bounded by the grace while the database refuses).
    stop_alarm_writer.cancel();
    if let Err(error) = alarm_writer.await {
        tracing::error!(%error, "the alarm writer failed");
    }
    store.close().await;
    // Scrapes are answered through the drain; an open scrape connection gets a second to finish.
    stop_metrics.cancel();
    if let Some(mut endpoint) = metrics_endpoint
        && tokio::time::timeout(Duration::from_secs(1), &mut endpoint)
            .await
            .is_err()
    {
        endpoint.abort();
    }
    tracing::info!("server stopped");
    result
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_bearer_scheme_is_case_insensitive_and_an_empty_token_is_none() {
        assert_eq!(bearer_token("Bearer abc"), Some("abc"));
        assert_eq!(bearer_token("bearer abc"), Some("abc"));
        assert_eq!(bearer_token("BEARER   abc "), Some("abc"));
        assert_eq!(bearer_token("Bearer "), None);
        assert_eq!(bearer_token("Bearer"), None);
        assert_eq!(bearer_token("Basic abc"), None);
        assert!(tokens_match("abc", "abc"));
        assert!(!tokens_match("abd", "abc"));
        assert!(!tokens_match("", "abc"));
        assert!(!tokens_match("abcd", "abc"));
    }
}
