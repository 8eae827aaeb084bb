//! The gRPC router: every API service with gzip both ways, the request size limit and the
//! access guard (`crate::access`); health and reflection open; HTTP/2 keep-alive. Health starts SERVING for every
//! API service and for the storage health name.
//!
//! It owns what is served and how, not what a service does (each lives with its subsystem) nor
//! when health changes later (`crate::storage_health`, `crate::drain`).

use std::sync::Arc;
use std::time::Duration;

use spoofwatch_proto::longrunning::operations_server::OperationsServer;
use spoofwatch_proto::v1::alarm_service_server::AlarmServiceServer;
use spoofwatch_proto::v1::dataset_service_server::DatasetServiceServer;
use spoofwatch_proto::v1::detection_service_server::DetectionServiceServer;
use spoofwatch_proto::v1::model_service_server::ModelServiceServer;
use spoofwatch_proto::v1::training_service_server::TrainingServiceServer;
use tonic::codec::CompressionEncoding;
use tonic::server::NamedService;
use tonic::transport::Server;
use tonic::transport::server::Router;
use tonic_health::ServingStatus;
use tonic_health::server::HealthReporter;

use crate::access::Guarded;
use crate::alarms::service::AlarmApi;
use crate::app::App;
use crate::config::Config;
use crate::datasets::DatasetApi;
use crate::detection::DetectionApi;
use crate::idle::StreamIdle;
use crate::jobs::{Jobs, OperationsApi, TrainingApi};
use crate::models::service::ModelApi;
use crate::server_error::ServerError;
use crate::storage_health;

/// The detection service's health name: it runs from memory, so it stays SERVING while the
/// database is down.
pub const DETECTION_SERVICE: &str = DetectionServiceServer::<DetectionApi>::NAME;
/// The alarm service's health name.
pub const ALARM_SERVICE: &str = AlarmServiceServer::<AlarmApi>::NAME;
/// The API services that need the database (listing, replay and live alarm events all read it).
pub const DATABASE_SERVICES: [&str; 5] = [
    ModelServiceServer::<ModelApi>::NAME,
    DatasetServiceServer::<DatasetApi>::NAME,
    TrainingServiceServer::<TrainingApi>::NAME,
    OperationsServer::<OperationsApi>::NAME,
    ALARM_SERVICE,
];

/// A generated service server that accepts gzip-compressed requests and compresses its replies
/// with gzip for clients that accept it (`grpc-accept-encoding`).
macro_rules! gzip {
    ($server:expr) => {
        $server
            .accept_compressed(CompressionEncoding::Gzip)
            .send_compressed(CompressionEncoding::Gzip)
    };
}

/// The router of every service, and the health reporter that sets their status.
pub struct Routes {
    pub router: Router,
    pub health: HealthReporter,
}

/// Routes `app`'s services on `server` (already configured for TLS).
pub async fn build(server: Server, app: &App, config: &Config) -> Result<Routes, ServerError> {
    let (health, health_service) = tonic_health::server::health_reporter();
    for service in [DETECTION_SERVICE]
        .into_iter()
        .chain(DATABASE_SERVICES)
        .chain([storage_health::STORAGE_HEALTH])
    {
        health
            .set_service_status(service, ServingStatus::Serving)
            .await;
    }
    let reflection_v1 = tonic_reflection::server::Builder::configure()
        .register_encoded_file_descriptor_set(spoofwatch_proto::FILE_DESCRIPTOR_SET)
        .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
        // google.rpc error details (BadRequest, ...), so grpcurl can print ItemError statuses.
        .register_encoded_file_descriptor_set(tonic_types::pb::FILE_DESCRIPTOR_SET)
        .build_v1()?;
    let reflection_v1alpha = tonic_reflection::server::Builder::configure()
        .register_encoded_file_descriptor_set(spoofwatch_proto::FILE_DESCRIPTOR_SET)
        .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
        .register_encoded_file_descriptor_set(tonic_types::pb::FILE_DESCRIPTOR_SET)
        .build_v1alpha()?;

    let limit = config.max_message_bytes;
    let stream_idle = StreamIdle(config.stream_idle());
    let jobs = Jobs {
        manager: Arc::clone(&app.jobs),
        registry: Arc::clone(&app.registry),
    };
    let detection = gzip!(DetectionServiceServer::new(DetectionApi {
        sessions: Arc::clone(&app.sessions),
        shutdown: app.draining.clone(),
        stream_idle,
    }))
    .max_decoding_message_size(limit);
    let models = gzip!(ModelServiceServer::new(ModelApi {
        registry: Arc::clone(&app.registry),
        deletion: Arc::clone(&app.sessions) as _,
        stream_idle,
        shadows: Arc::clone(&app.shadows),
    }))
    .max_decoding_message_size(limit);
    let datasets = gzip!(DatasetServiceServer::new(DatasetApi {
        catalog: app.catalog.clone(),
        stream_idle,
        upload_budget: Arc::new(tokio::sync::Semaphore::new(
            config.upload_memory_mib as usize * 1024,
        )),
    }))
    .max_decoding_message_size(limit);
    let training = gzip!(TrainingServiceServer::new(TrainingApi {
        jobs: jobs.clone()
    }))
    .max_decoding_message_size(limit);
    let operations =
        gzip!(OperationsServer::new(OperationsApi { jobs })).max_decoding_message_size(limit);
    let alarms = gzip!(AlarmServiceServer::new(AlarmApi {
        store: app.store.clone(),
        feed: Arc::clone(&app.alarm_feed),
        incident_feed: Arc::clone(&app.incident_feed),
        incidents_stored: Arc::clone(&app.incidents_stored),
        incident_areas: Arc::clone(&app.incident_areas),
        incident_timeline: app.incident_settings.timeline,
        shutdown: app.draining.clone(),
        stream_idle,
    }))
    .max_decoding_message_size(limit);

    let router = server
        .max_concurrent_streams(Some(config.max_streams_per_connection))
        .http2_keepalive_interval(Some(Duration::from_secs(30)))
        .http2_keepalive_timeout(Some(Duration::from_secs(10)))
        .add_service(gzip!(health_service))
        .add_service(gzip!(reflection_v1))
        .add_service(gzip!(reflection_v1alpha))
        .add_service(Guarded::new(detection, Arc::clone(&app.access)))
        .add_service(Guarded::new(models, Arc::clone(&app.access)))
        .add_service(Guarded::new(datasets, Arc::clone(&app.access)))
        .add_service(Guarded::new(training, Arc::clone(&app.access)))
        .add_service(Guarded::new(operations, Arc::clone(&app.access)))
        .add_service(Guarded::new(alarms, Arc::clone(&app.access)));
    Ok(Routes { router, health })
}
