//! The drain: once the shutdown signal resolves, health turns NOT_SERVING, streams end with
//! UNAVAILABLE, running jobs are cancelled and recorded, sessions are saved, and the outbox writer
//! is told to finish; then the server stops accepting, and open connections get the grace period
//! to close.
//!
//! It owns the order of the drain and its bound, not what each step does (each subsystem drains
//! itself).

use std::future::Future;
use std::time::Duration;

use tokio::sync::oneshot;
use tokio_util::sync::CancellationToken;
use tonic_health::ServingStatus;
use tonic_health::server::HealthReporter;

use crate::app::App;
use crate::router::{ALARM_SERVICE, DETECTION_SERVICE};
use crate::server_error::ServerError;

/// Waits for `shutdown` in the background, then drains `app`: health first, then streams, then
/// jobs, then sessions and the alarm writer (`stop_outbox_writer`). The receiver completes when
/// the server may stop accepting.
pub fn on_shutdown(
    shutdown: impl Future<Output = ()> + Send + 'static,
    app: &App,
    health: HealthReporter,
    stop_outbox_writer: CancellationToken,
    grace: Duration,
) -> oneshot::Receiver<()> {
    let (drained_tx, drained) = oneshot::channel();
    let (draining, jobs, sessions) = (
        app.draining.clone(),
        std::sync::Arc::clone(&app.jobs),
        std::sync::Arc::clone(&app.sessions),
    );
    tokio::spawn(async move {
        shutdown.await;
        tracing::info!("shutting down: health NOT_SERVING, draining streams and jobs");
        for service in ["", DETECTION_SERVICE, ALARM_SERVICE] {
            health
                .set_service_status(service, ServingStatus::NotServing)
                .await;
        }
        draining.cancel();
        jobs.shutdown(grace).await;
        sessions.save_all().await;
        stop_outbox_writer.cancel();
        let _ = drained_tx.send(());
    });
    drained
}

/// Runs `server` until it stops, or until `grace` (and a second) after the drain started:
/// connections that are still open then are closed.
pub async fn serve_bounded(
    server: impl Future<Output = Result<(), tonic::transport::Error>>,
    draining: &CancellationToken,
    grace: Duration,
) -> Result<(), ServerError> {
    tokio::pin!(server);
    tokio::select! {
        result = &mut server => result.map_err(ServerError::from),
        _ = async { draining.cancelled().await; tokio::time::sleep(grace + Duration::from_secs(1)).await } => {
            tracing::warn!("drain timed out; closing remaining connections");
            Ok(())
        }
    }
}
