//! A shadow beside the throughput phases (`--shadow MODEL`): before the phases, a shadow of the
//! model starts on every vehicle; after them, it stops and its counts follow the results table
//! (samples scored and shed, the candidate's scoring time per sample, vehicles). Needs the admin
//! role, and no other shadow running.

use anyhow::{Context, Result};
use spoofwatch_proto::v1;
use spoofwatch_proto::v1::model_service_client::ModelServiceClient;

use crate::connection::{AuthenticatedChannel, ConnectOptions, Connection};

/// A shadow started for the run.
pub struct BenchShadow {
    models: ModelServiceClient<AuthenticatedChannel>,
    name: String,
}

impl BenchShadow {
    /// Starts a shadow of `model` on every vehicle of the server at `url`.
    pub async fn start(url: &str, options: &ConnectOptions, model: &str) -> Result<Self> {
        let mut models = Connection::connect_with(url, options).await?.models();
        let shadow = models
            .start_shadow(v1::StartShadowRequest {
                model: model.to_string(),
                scope: Some(v1::start_shadow_request::Scope::AllVehicles(true)),
            })
            .await
            .with_context(|| format!("starting a shadow of {model} on every vehicle"))?
            .into_inner();
        Ok(Self {
            models,
            name: shadow.name,
        })
    }

    /// Stops the shadow; returns its counts as a table.
    pub async fn finish(mut self) -> Result<String> {
        let shadow = self
            .models
            .stop_shadow(v1::StopShadowRequest {
                name: self.name.clone(),
            })
            .await
            .with_context(|| format!("stopping {}", self.name))?
            .into_inner();
        let s = shadow.summary.unwrap_or_default();
        let offered = s.samples_scored + s.samples_shed;
        let shed_pct = if offered == 0 {
            0.0
        } else {
            100.0 * s.samples_shed as f64 / offered as f64
        };
        Ok(format!(
            "| shadow | scored | shed | shed % | µs per sample | vehicles |\n\
             |---|---:|---:|---:|---:|---:|\n\
             | shadow | {} | {} | {shed_pct:.2} | {:.2} | {} |\n",
            s.samples_scored, s.samples_shed, s.shadow_micros_per_sample, s.vehicles,
        ))
    }
}
