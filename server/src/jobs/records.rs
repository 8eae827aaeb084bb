//! What a job is asked to do and what it reports, in the shapes persisted as the store's opaque
//! JSON columns (`request_json`, `metadata_json`, `result_json`). Plain data: no behaviour, no wire
//! messages, no SQL.

use std::fmt::Display;

use serde::{Deserialize, Serialize, Serializer};
use spoofwatch_core::evidence::FeatureSchema;
use spoofwatch_core::fleet_fit::FleetFitReport;
use spoofwatch_core::metrics::Metrics;
use spoofwatch_core::model::Ablation;
use spoofwatch_proto::wire::{DatasetName, ModelName};

/// A training job's parameters (validated and defaulted at the edge).
#[derive(Clone, Debug, Serialize)]
pub struct TrainingRequest {
    #[serde(serialize_with = "names")]
    pub datasets: Vec<DatasetName>,
    /// Empty: split `datasets` chronologically into train/validation/test.
    #[serde(serialize_with = "names")]
    pub validation_datasets: Vec<DatasetName>,
    pub seed: u64,
    pub max_epochs: u32,
    pub schema: FeatureSchema,
    pub ablation: Ablation,
    pub select_kappa_rho: bool,
    pub display_name: String,
    pub activate: bool,
    /// Set: a fleet fit of the datasets (attack-free recordings) instead of training on labels.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub fleet_fit: Option<FleetFitRequest>,
}

/// A fleet fit's parameters (the starting model fixed when the job is created).
#[derive(Clone, Debug, Serialize)]
pub struct FleetFitRequest {
    #[serde(serialize_with = "name")]
    pub starting_model: ModelName,
    pub from_scratch: bool,
    pub sample_rate_hz: Option<f64>,
    /// The feature schema the request named, if it named one: it must be the starting model's.
    pub schema: Option<FeatureSchema>,
}

/// An evaluation job's parameters (the model is fixed when the job is created).
#[derive(Clone, Debug, Serialize)]
pub struct EvaluationRequest {
    #[serde(serialize_with = "name")]
    pub model: ModelName,
    #[serde(serialize_with = "names")]
    pub datasets: Vec<DatasetName>,
}

/// What a job was asked to do (the `request_json` column; written, never read back).
#[derive(Clone, Debug, Serialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum JobRequest {
    Training(TrainingRequest),
    Evaluation(EvaluationRequest),
}

impl JobRequest {
    /// Every dataset the job reads, with the request field that names it.
    pub fn datasets(&self) -> impl Iterator<Item = (String, &DatasetName)> {
        let fields: Vec<(&str, &[DatasetName])> = match self {
            JobRequest::Training(t) => vec![
                ("datasets", &t.datasets),
                ("validation_datasets", &t.validation_datasets),
            ],
            JobRequest::Evaluation(e) => vec![("datasets", &e.datasets)],
        };
        fields.into_iter().flat_map(|(field, names)| {
            names
                .iter()
                .enumerate()
                .map(move |(i, name)| (format!("{field}[{i}]"), name))
        })
    }
}

fn name<S: Serializer, T: Display>(value: &T, s: S) -> Result<S::Ok, S::Error> {
    s.collect_str(value)
}

fn names<S: Serializer, T: Display>(values: &[T], s: S) -> Result<S::Ok, S::Error> {
    s.collect_seq(values.iter().map(ToString::to_string))
}

/// Live progress (the `metadata_json` column).
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct Progress {
    pub epoch: u32,
    pub max_epochs: u32,
    pub train_loss: f64,
    pub val_loss: f64,
    pub val_auroc: Option<f64>,
    pub eta_s: Option<f64>,
    pub message: String,
}

/// A finished job's result (the `result_json` column).
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum JobResult {
    Training {
        model_id: String,
        validation: Metrics,
        test: Option<Metrics>,
        /// A fleet fit's report.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        fleet_fit: Option<Box<FleetFitReport>>,
    },
    Evaluation {
        model: String,
        overall: Metrics,
        per_vehicle: Vec<(String, Metrics)>,
    },
}

/// JSON for the store's opaque columns. Our own types always serialise (no maps with non-string
/// keys, no failing serialisers), so the fallback is unreachable in practice.
pub fn to_json<T: Serialize>(value: &T) -> serde_json::Value {
    serde_json::to_value(value).unwrap_or_default()
}
