//! `spoofwatch health`: the grpc.health.v1 check of the whole server (used by compose.yaml).
//!
//! It must not check individual services: compose.yaml relies on the whole-server status.

use std::time::Duration;

use crate::retry::{self, Idempotency};
use anyhow::{Result, bail};
use tonic_health::pb::HealthCheckRequest;
use tonic_health::pb::health_check_response::ServingStatus;

use crate::cli::server_flags::ServerArgs;

/// How long the check may take once connected.
const CHECK_TIMEOUT: Duration = Duration::from_secs(5);

#[derive(Debug, clap::Args)]
pub struct Args {
    #[command(flatten)]
    pub server: ServerArgs,
}

/// Checks service "" (the server as a whole); succeeds only when it is SERVING.
pub async fn run(args: Args) -> Result<()> {
    let connection = args.server.connect().await?;
    let mut health = connection.health();
    let answer = retry::unary("checking health", Idempotency::Idempotent, async || {
        let mut request = tonic::Request::new(HealthCheckRequest {
            service: String::new(),
        });
        request.set_timeout(CHECK_TIMEOUT);
        health.check(request).await
    })
    .await?;
    let status = ServingStatus::try_from(answer.status).unwrap_or(ServingStatus::Unknown);
    println!("{}: {}", connection.url(), status.as_str_name());
    if status != ServingStatus::Serving {
        bail!("the server is not serving ({})", status.as_str_name());
    }
    Ok(())
}
