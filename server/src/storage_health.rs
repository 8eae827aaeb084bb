//! The storage watch: once a second, checks that the database file is still the one opened and
//! whether alarm events are being stored, and reports both through gRPC health:
//! - `spoofwatch.storage` is NOT_SERVING while alarm events cannot be stored or the file is lost;
//! - a deleted or replaced database file also turns the overall status ("") and every service that
//!   needs the database NOT_SERVING, for good: detection keeps running from memory, but the server
//!   must be restarted on a restored database.
//!
//! Every change is logged with its reason (health itself carries none).

use std::sync::Arc;
use std::time::Duration;

use tokio_util::sync::CancellationToken;
use tonic_health::ServingStatus;
use tonic_health::server::HealthReporter;

use crate::outbox::SessionOutbox;
use crate::store::Store;

/// The health service name that reports the database's state.
pub const STORAGE_HEALTH: &str = "spoofwatch.storage";

/// How often the file and the alarm writer are checked.
const PERIOD: Duration = Duration::from_secs(1);

/// Watches until `stop` is cancelled. `store_services` are the health names of the services that
/// cannot work without the database.
pub async fn watch_storage(
    store: Store,
    outbox: Arc<SessionOutbox>,
    health: HealthReporter,
    store_services: Vec<&'static str>,
    stop: CancellationToken,
) {
    let mut tick = tokio::time::interval(PERIOD);
    let mut serving = true;
    let mut lost = false;
    loop {
        tokio::select! {
            _ = stop.cancelled() => return,
            _ = tick.tick() => {}
        }
        if !lost && let Err(fault) = store.check_file() {
            lost = true;
            tracing::error!(
                cause = fault.cause,
                "{}; health is NOT_SERVING until a restart",
                fault.kind.describe()
            );
            for service in std::iter::once("").chain(store_services.iter().copied()) {
                health
                    .set_service_status(service, ServingStatus::NotServing)
                    .await;
            }
        }
        let stats = outbox.stats();
        let now_serving = !lost && !stats.failing;
        if now_serving != serving {
            serving = now_serving;
            let status = if serving {
                tracing::info!("storage healthy again: alarm events are being stored");
                ServingStatus::Serving
            } else {
                if !lost {
                    tracing::error!(
                        backlog = stats.backlog,
                        reason = outbox.failure().unwrap_or_default(),
                        "storage NOT_SERVING: alarm events are waiting for the database"
                    );
                }
                ServingStatus::NotServing
            };
            health.set_service_status(STORAGE_HEALTH, status).await;
        }
    }
}
