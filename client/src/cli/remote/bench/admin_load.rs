//! Administrative load beside the throughput phases of `spoofwatch bench` (`--admin-load`): what an
//! administrator's uploads, imports and heavy scoring do to detection and health while a fleet
//! streams. From the start of each phase to its end, on connections of their own:
//!
//! - [`UPLOADERS`] clients upload datasets of [`UPLOAD_RECORDS`] structured records, every record
//!   its own vehicle, back to back (each dataset deleted once stored);
//! - one client imports a model of nearly [`HEAVY_MODEL_PARAMETERS`] parameters, back to back (each
//!   deleted once stored);
//! - [`HEAVY_DETECT_CLIENTS`] clients score 1,000-sample `Detect` calls on such a model without pause;
//! - a prober sends a health check every [`HEALTH_PERIOD`] and times its answer.
//!
//! Needs the admin role (uploads and imports). The heavy model's widths are the active model's
//! widths grown until the next step would pass [`HEAVY_MODEL_PARAMETERS`]; the rest of the artifact
//! (evidence, scaler, operating point) is the active model's.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use spoofwatch_core::model::artifact::ModelArtifact;
use spoofwatch_core::model::{Model, Params};
use spoofwatch_proto::v1;
use spoofwatch_proto::v1::upload_dataset_request::Kind as UploadKind;
use tokio::task::JoinSet;
use tonic_health::pb::HealthCheckRequest;

use super::{ms, percentile};
use crate::cli::remote::models::import_requests;
use crate::connection::{ConnectOptions, Connection};
use crate::synthetic::LoopDriver;

/// Concurrent dataset uploaders.
pub const UPLOADERS: usize = 2;
/// Records per uploaded dataset, each its own vehicle.
pub const UPLOAD_RECORDS: usize = 100_000;
/// Records per upload message.
const RECORDS_PER_MESSAGE: usize = 5_000;
/// The heavy model's size: near the server's bound of 350,000 parameters.
pub const HEAVY_MODEL_PARAMETERS: usize = 300_000;
/// Concurrent clients scoring 1,000-sample calls on the heavy model.
pub const HEAVY_DETECT_CLIENTS: usize = 4;
/// Samples per heavy `Detect` call (the most one call may carry).
const HEAVY_DETECT_SAMPLES: usize = 1_000;
/// Time between health checks.
pub const HEALTH_PERIOD: Duration = Duration::from_millis(50);
/// Longest one piece of admin work may take before the run fails.
const WORK_LIMIT: Duration = Duration::from_secs(300);

/// The administrative load, running until [`AdminLoad::finish`].
pub struct AdminLoad {
    stop: Arc<AtomicBool>,
    tasks: JoinSet<Result<Timings>>,
    started: Instant,
    /// Where the heavy model lives and its name, to delete it at the end.
    connection: Connection,
    heavy_model: String,
}

/// What one admin client did: which kind of work, how long each piece took.
struct Timings {
    kind: Work,
    durations: Vec<Duration>,
}

#[derive(Clone, Copy, PartialEq, Eq, Debug)]
enum Work {
    Health,
    Upload,
    Import,
    HeavyDetect,
}

impl Work {
    fn label(self) -> &'static str {
        match self {
            Work::Health => "health check",
            Work::Upload => "dataset upload (100,000 records)",
            Work::Import => "model import (heavy)",
            Work::HeavyDetect => "Detect, 1,000 samples, heavy model",
        }
    }
}

impl AdminLoad {
    /// Imports the heavy model the scoring clients use, then starts every admin client.
    pub async fn start(url: &str, options: &ConnectOptions) -> Result<Self> {
        let connection = Connection::connect_with(url, options).await?;
        let artifact = heavy_artifact(&connection).await?;
        let heavy_model = import(&connection, &artifact, "bench heavy model")
            .await
            .context("importing the heavy model (--admin-load needs the admin role)")?;
        let stop = Arc::new(AtomicBool::new(false));
        let mut tasks = JoinSet::new();
        let artifact = Arc::new(artifact);
        for uploader in 0..UPLOADERS {
            let connection = Connection::connect_with(url, options).await?;
            let stop = Arc::clone(&stop);
            tasks.spawn(repeat(Work::Upload, stop, move |round| {
                let connection = connection.clone();
                async move { upload_and_delete(&connection, uploader, round).await }
            }));
        }
        {
            let connection = Connection::connect_with(url, options).await?;
            let stop = Arc::clone(&stop);
            tasks.spawn(repeat(Work::Import, stop, move |_| {
                let (connection, artifact) = (connection.clone(), Arc::clone(&artifact));
                async move {
                    let name = import(&connection, &artifact, "bench import").await?;
                    let request = v1::DeleteModelRequest { name };
                    connection.models().delete_model(request).await?;
                    Ok(())
                }
            }));
        }
        for client in 0..HEAVY_DETECT_CLIENTS {
            let connection = Connection::connect_with(url, options).await?;
            let (stop, model) = (Arc::clone(&stop), heavy_model.clone());
            let mut driver = LoopDriver::new(9_000 + client as u64);
            tasks.spawn(repeat(Work::HeavyDetect, stop, move |_| {
                // Stateless calls: the samples are scored, no session is kept.
                let request = v1::DetectRequest {
                    vehicle_id: String::new(),
                    model: model.clone(),
                    samples: driver.next_batch(HEAVY_DETECT_SAMPLES),
                };
                let mut detection = connection.detection();
                async move {
                    detection.detect(request).await?;
                    Ok(())
                }
            }));
        }
        {
            let connection = Connection::connect_with(url, options).await?;
            let stop = Arc::clone(&stop);
            tasks.spawn(async move {
                let mut health = connection.health();
                let mut durations = Vec::new();
                let mut ticks = tokio::time::interval(HEALTH_PERIOD);
                while !stop.load(Ordering::Relaxed) {
                    ticks.tick().await;
                    let asked = Instant::now();
                    tokio::time::timeout(WORK_LIMIT, health.check(HealthCheckRequest::default()))
                        .await
                        .context("a health check was not answered in 300 s")??;
                    durations.push(asked.elapsed());
                }
                Ok(Timings {
                    kind: Work::Health,
                    durations,
                })
            });
        }
        Ok(Self {
            stop,
            tasks,
            started: Instant::now(),
            connection,
            heavy_model,
        })
    }

    /// Stops the clients (each finishes the piece of work it is doing) and returns their table.
    pub async fn finish(mut self) -> Result<String> {
        self.stop.store(true, Ordering::Relaxed);
        let mut by_kind: Vec<(Work, Vec<Duration>)> = Vec::new();
        while let Some(joined) = self.tasks.join_next().await {
            let timings = joined.context("an admin client panicked")??;
            match by_kind.iter_mut().find(|(kind, _)| *kind == timings.kind) {
                Some((_, all)) => all.extend(timings.durations),
                None => by_kind.push((timings.kind, timings.durations)),
            }
        }
        let elapsed = self.started.elapsed();
        let request = v1::DeleteModelRequest {
            name: self.heavy_model,
        };
        self.connection.models().delete_model(request).await?;
        by_kind.sort_by_key(|(kind, _)| *kind as u8);
        let mut out = format!(
            "admin load for {:.0} s: {UPLOADERS} uploaders, 1 importer, {HEAVY_DETECT_CLIENTS} \
             heavy Detect clients, a health check every {} ms\n\n\
             | work | done | p50 (ms) | p99 (ms) | max (ms) |\n|---|---:|---:|---:|---:|\n",
            elapsed.as_secs_f64(),
            HEALTH_PERIOD.as_millis()
        );
        for (kind, mut durations) in by_kind {
            durations.sort_unstable();
            out.push_str(&format!(
                "| {} | {} | {} | {} | {} |\n",
                kind.label(),
                durations.len(),
                ms(percentile(&durations, 0.5)),
                ms(percentile(&durations, 0.99)),
                ms(durations.last().copied()),
            ));
        }
        Ok(out)
    }
}

/// Runs `work` round after round until `stop`, timing each round.
async fn repeat<F, Fut>(kind: Work, stop: Arc<AtomicBool>, mut work: F) -> Result<Timings>
where
    F: FnMut(u64) -> Fut,
    Fut: Future<Output = Result<()>>,
{
    let mut durations = Vec::new();
    let mut round = 0;
    while !stop.load(Ordering::Relaxed) {
        let started = Instant::now();
        tokio::time::timeout(WORK_LIMIT, work(round))
            .await
            .with_context(|| format!("a {} took over 300 s", kind.label()))?
            .with_context(|| format!("a {} failed", kind.label()))?;
        durations.push(started.elapsed());
        round += 1;
    }
    Ok(Timings { kind, durations })
}

/// The active model's artifact with its widths grown to just under [`HEAVY_MODEL_PARAMETERS`].
async fn heavy_artifact(connection: &Connection) -> Result<ModelArtifact> {
    let mut models = connection.models();
    let mut page_token = String::new();
    let active = loop {
        let page = models
            .list_models(v1::ListModelsRequest {
                page_size: 100,
                page_token: page_token.clone(),
            })
            .await?
            .into_inner();
        if let Some(active) = page.models.into_iter().find(|m| m.active) {
            break active;
        }
        if page.next_page_token.is_empty() {
            bail!("the server has no active model to base the heavy model on");
        }
        page_token = page.next_page_token;
    };
    let mut chunks = models
        .export_model(v1::ExportModelRequest { name: active.name })
        .await?
        .into_inner();
    let mut bytes = Vec::new();
    while let Some(chunk) = chunks.message().await? {
        bytes.extend_from_slice(&chunk.data);
    }
    let mut artifact = ModelArtifact::from_slice(&bytes).context("the active model's artifact")?;
    let mut config = artifact.model.config().clone();
    loop {
        let mut wider = config.clone();
        wider.d_s += 8;
        wider.d_zeta += 8;
        wider.d_h += 8;
        if Params::count_for(&wider) > HEAVY_MODEL_PARAMETERS {
            break;
        }
        config = wider;
    }
    artifact.model = Model::init(config, 1).context("the heavy model's widths")?;
    Ok(artifact)
}

/// Imports `artifact` (not activated) and returns its name.
async fn import(connection: &Connection, artifact: &ModelArtifact, name: &str) -> Result<String> {
    let bytes = artifact.to_vec().context("writing the heavy model")?;
    let requests = import_requests(name.to_string(), false, &bytes);
    let model = connection
        .models()
        .import_model(tokio_stream::iter(requests))
        .await?
        .into_inner();
    Ok(model.name)
}

/// Uploads one dataset of [`UPLOAD_RECORDS`] one-sample vehicles, then deletes it.
async fn upload_and_delete(connection: &Connection, uploader: usize, round: u64) -> Result<()> {
    let prefix = format!("admin-{uploader}-{round}");
    let header = UploadKind::Header(v1::UploadDatasetHeader {
        display_name: prefix.clone(),
    });
    let mut driver = LoopDriver::new(uploader as u64);
    let records: Vec<v1::LabelledSample> = (0..UPLOAD_RECORDS)
        .map(|i| v1::LabelledSample {
            vehicle_id: format!("{prefix}-{i}"),
            sample: Some(driver.next_sample()),
            spoofed: Some(false),
        })
        .collect();
    let messages: Vec<v1::UploadDatasetRequest> = std::iter::once(header)
        .chain(records.chunks(RECORDS_PER_MESSAGE).map(|chunk| {
            UploadKind::Records(v1::RecordBatch {
                records: chunk.to_vec(),
            })
        }))
        .map(|kind| v1::UploadDatasetRequest { kind: Some(kind) })
        .collect();
    let mut datasets = connection.datasets();
    let dataset = datasets
        .upload_dataset(tokio_stream::iter(messages))
        .await?
        .into_inner();
    if dataset.rows != UPLOAD_RECORDS as u64 {
        bail!(
            "an upload of {UPLOAD_RECORDS} records stored {} rows",
            dataset.rows
        );
    }
    datasets
        .delete_dataset(v1::DeleteDatasetRequest { name: dataset.name })
        .await?;
    Ok(())
}
