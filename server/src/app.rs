//! App assembly: opens the store and builds every subsystem of one server from its configuration,
//! in dependency order (model registry, dataset catalog, session outbox, alarm and incident feeds,
//! sessions, shadows, jobs), and recovers what a previous run left behind (open alarms, abandoned jobs).
//!
//! It owns construction only: what is served is `crate::router`, the tasks that run beside the
//! server `crate::background`, and the shutdown `crate::drain`.

use std::sync::Arc;

use tokio::sync::Notify;
use tokio_util::sync::CancellationToken;

use crate::access::{self, Access};
use crate::alarms::feed::AlarmFeed;
use crate::config::Config;
use crate::datasets::Catalog;
use crate::detection::{Beside, SessionLimits, SessionManager};
use crate::incidents::areas::IncidentAreas;
use crate::incidents::service::IncidentFeed;
use crate::incidents::settings::IncidentSettings;
use crate::jobs::{JobManager, JobSettings, Runner};
use crate::models::Registry;
use crate::outbox::{OUTBOX_CAPACITY, SessionOutbox};
use crate::server_error::ServerError;
use crate::shadow::Shadows;
use crate::store::{Store, StoreOptions};
use crate::tls;
use crate::work::HeavyWork;

/// Every subsystem of one running server.
pub struct App {
    /// Who may do what (the identity files as last read).
    pub access: Arc<Access>,
    pub store: Store,
    pub registry: Arc<Registry>,
    pub catalog: Catalog,
    pub outbox: Arc<SessionOutbox>,
    pub alarm_feed: Arc<AlarmFeed>,
    /// WatchIncidents' live events.
    pub incident_feed: Arc<IncidentFeed>,
    /// Told when this server's correlator stored incident events.
    pub incidents_stored: Arc<Notify>,
    pub incident_settings: IncidentSettings,
    /// The open incidents' areas, refreshed by the correlator loop, read by the sessions.
    pub incident_areas: Arc<IncidentAreas>,
    /// This server's instance id (job ownership, the incident correlator's lease).
    pub instance: String,
    pub sessions: Arc<SessionManager>,
    /// Shadow evaluation of a candidate model beside the live one.
    pub shadows: Arc<Shadows>,
    pub jobs: Arc<JobManager>,
    /// Cancelled when the drain starts: streams end and the background loops stop.
    pub draining: CancellationToken,
}

impl App {
    /// Opens the database named by `config` and builds every subsystem on it.
    pub async fn assemble(config: &Config) -> Result<Self, ServerError> {
        let snapshot_policy = config.snapshot_policy().map_err(ServerError::Config)?;
        let incident_settings = config.incident_settings().map_err(ServerError::Config)?;
        let transport = tls::transport(config);
        let access = Arc::new(
            Access::load(access::Sources {
                token: config.auth_token.clone(),
                token_file: config.auth_token_file.clone(),
                roles_file: config.roles_file.clone(),
                mutual_tls: transport == tls::Transport::MutualTls,
            })
            .map_err(ServerError::Config)?,
        );
        tracing::info!(
            transport = transport.as_str(),
            identities = %access.describe(),
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
        let heavy = HeavyWork::for_this_machine();
        tracing::info!(
            slots = heavy.slots(),
            "heavy work (parsing, large batches) runs off the runtime"
        );
        let registry = Arc::new(Registry::new(
            store.clone(),
            config.model_cache_bytes,
            heavy.clone(),
        ));
        registry.ensure_default_model().await?;
        let catalog = Catalog::new(store.clone(), config.data_dir.clone(), heavy.clone());

        // Also ends the alarms a previous run left open.
        let outbox = Arc::new(SessionOutbox::new(&store, OUTBOX_CAPACITY).await?);
        // WatchAlarms' live events: the stored event log of every replica.
        let alarm_feed = Arc::new(AlarmFeed::new(&store).await?);
        let incident_feed = Arc::new(IncidentFeed::new(&store).await?);
        let incident_areas = Arc::new(IncidentAreas::new(incident_settings.prior));
        let shadows = Arc::new(
            Shadows::new(
                store.clone(),
                Arc::clone(&registry),
                &instance,
                config.session_idle(),
            )
            .map_err(ServerError::ShadowWorker)?,
        );
        // A shadow stored as running (started before a restart, or through another replica)
        // runs here too; a shadow that cannot be read is retried by the follower.
        if let Err(error) = shadows.follow().await {
            tracing::warn!(%error, "the stored shadow was not read; retried");
        }
        let sessions = Arc::new(SessionManager::new(
            Arc::clone(&registry),
            Arc::clone(&outbox),
            store.clone(),
            SessionLimits {
                max_sessions: config.max_sessions,
                max_per_identity: config.max_sessions_per_identity,
                idle: config.session_idle(),
                max_batch_samples: config.max_batch_samples,
            },
            snapshot_policy,
            heavy.clone(),
            Beside {
                areas: Arc::clone(&incident_areas),
                shadows: Arc::clone(&shadows),
            },
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
                input_kib: config.job_input_mib as usize * 1024,
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
        Ok(Self {
            access,
            store,
            registry,
            catalog,
            outbox,
            alarm_feed,
            incident_feed,
            incidents_stored: Arc::new(Notify::new()),
            incident_settings,
            incident_areas,
            instance,
            sessions,
            shadows,
            jobs,
            draining: CancellationToken::new(),
        })
    }
}
