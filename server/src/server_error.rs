//! Why a server could not start or stopped serving: the one error of [`crate::serve`], for the
//! binary's exit status and for embedders. Errors of single requests are not here (they map to
//! gRPC statuses in `crate::error`).

use crate::models::RegistryError;
use crate::store::StoreError;
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
    #[error("starting the shadow worker thread: {0}")]
    ShadowWorker(std::io::Error),
}
