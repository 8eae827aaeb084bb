//! The self-contained model artifact: everything needed to serve (SPEC §5), as one JSON document
//! with a versioned schema — the trained model plus its evidence statistics, scaler, operating point
//! and provenance.
//!
//! Owns the artifact's schema, (de)serialisation and validation. Must not run the model on data
//! (that is [`crate::detector`]) nor produce artifacts (that is [`crate::train::detector`]).

use std::io::{Read, Write};

use serde::{Deserialize, Serialize};

use super::Model;
use crate::alarm::OperatingPoint;
use crate::evidence::{EvidenceParams, FeatureSchema, RobustScaler};
use crate::metrics::Metrics;

/// Version of the artifact schema (weights layout, evidence definition, feature order).
/// Bump it whenever an older artifact would be served differently by this code.
/// Version 2 added named feature schemas (`model.config.schema`) and evidence v2's drift parameters.
pub const ARTIFACT_SCHEMA_VERSION: u32 = 2;
/// The oldest version this build still reads: version 1 artifacts are `paper`-schema models, served
/// exactly as before.
pub const OLDEST_READABLE_SCHEMA_VERSION: u32 = 1;

/// A trained detector ready to serve.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ModelArtifact {
    pub schema_version: u32,
    /// ξ feature order the weights expect; checked on load.
    pub feature_names: Vec<String>,
    pub model: Model,
    pub evidence: EvidenceParams,
    pub scaler: RobustScaler,
    pub operating_point: OperatingPoint,
    pub provenance: Provenance,
}

/// How an artifact was made.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Provenance {
    /// Tool and version that trained it, e.g. `spoofwatch 0.1.0`.
    pub created_by: String,
    /// Free-form description of the training data (file names, splits, injected scenarios).
    pub training_data: Vec<String>,
    pub seed: u64,
    pub training_rows: u64,
    pub epochs_run: u32,
    pub best_epoch: u32,
    pub train_wall_time_s: f64,
    /// Metrics on the validation data at the chosen operating point.
    pub validation_metrics: Option<Metrics>,
    pub notes: String,
}

/// Why an artifact cannot be loaded or saved.
#[derive(Debug, thiserror::Error)]
pub enum ArtifactError {
    #[error("reading the model artifact: {0}")]
    Io(#[from] std::io::Error),
    #[error("the model artifact is not valid JSON: {0}")]
    Json(#[from] serde_json::Error),
    #[error("the model artifact has no schema_version field; is this a Spoofwatch model?")]
    MissingSchemaVersion,
    #[error(
        "model artifact schema version {found} is not supported (this build reads version {supported}){hint}"
    )]
    UnsupportedSchema {
        found: u64,
        supported: u32,
        hint: &'static str,
    },
    #[error("the model artifact's feature order {found:?} differs from this build's {expected:?}")]
    FeatureMismatch {
        found: Vec<String>,
        expected: Vec<String>,
    },
    #[error("the model artifact is inconsistent: {0}")]
    Invalid(String),
}

impl ModelArtifact {
    /// The feature order a model of `schema` is stored with.
    pub fn feature_names_of(schema: FeatureSchema) -> Vec<String> {
        schema
            .feature_names()
            .iter()
            .map(|s| s.to_string())
            .collect()
    }

    /// The feature schema the model reads.
    pub fn schema(&self) -> FeatureSchema {
        self.model.config().schema
    }

    /// Reads and validates an artifact. The schema version is checked before anything else, so a
    /// newer artifact gets a clear message instead of a field-level parse error.
    pub fn read<R: Read>(reader: R) -> Result<Self, ArtifactError> {
        let value: serde_json::Value = serde_json::from_reader(reader)?;
        let found = value
            .get("schema_version")
            .and_then(serde_json::Value::as_u64)
            .ok_or(ArtifactError::MissingSchemaVersion)?;
        let readable =
            u64::from(OLDEST_READABLE_SCHEMA_VERSION)..=u64::from(ARTIFACT_SCHEMA_VERSION);
        if !readable.contains(&found) {
            let hint = if found > u64::from(ARTIFACT_SCHEMA_VERSION) {
                "; it was written by a newer Spoofwatch: upgrade to load it"
            } else {
                "; retrain the model with this version"
            };
            return Err(ArtifactError::UnsupportedSchema {
                found,
                supported: ARTIFACT_SCHEMA_VERSION,
                hint,
            });
        }
        let artifact: ModelArtifact = serde_json::from_value(value)?;
        artifact.validate()?;
        Ok(artifact)
    }

    /// Parses an artifact from bytes (e.g. a database blob).
    pub fn from_slice(bytes: &[u8]) -> Result<Self, ArtifactError> {
        Self::read(bytes)
    }

    /// Writes the artifact as pretty JSON.
    pub fn write<W: Write>(&self, writer: W) -> Result<(), ArtifactError> {
        self.validate()?;
        serde_json::to_writer_pretty(writer, self)?;
        Ok(())
    }

    /// The artifact as JSON bytes.
    pub fn to_vec(&self) -> Result<Vec<u8>, ArtifactError> {
        let mut out = Vec::new();
        self.write(&mut out)?;
        Ok(out)
    }

    /// Checks the parts fit together: feature order, scaler and evidence parameters against the
    /// model's schema, weights against the configuration, operating point.
    pub fn validate(&self) -> Result<(), ArtifactError> {
        let schema = self.schema();
        let expected = Self::feature_names_of(schema);
        if self.feature_names != expected {
            return Err(ArtifactError::FeatureMismatch {
                found: self.feature_names.clone(),
                expected,
            });
        }
        let scaler_schema = self
            .scaler
            .schema()
            .map_err(|e| ArtifactError::Invalid(e.to_string()))?;
        if scaler_schema != schema {
            return Err(ArtifactError::Invalid(format!(
                "the scaler has {} components, the {} feature schema needs {}",
                self.scaler.center.len(),
                schema.name(),
                schema.feature_count() - 1
            )));
        }
        if self.evidence.drift.is_some() != schema.has_drift() {
            return Err(ArtifactError::Invalid(format!(
                "the {} feature schema {} drift parameters in the evidence",
                schema.name(),
                if schema.has_drift() {
                    "needs"
                } else {
                    "has no use for"
                }
            )));
        }
        if self.schema_version < 2 && schema != FeatureSchema::legacy() {
            return Err(ArtifactError::Invalid(format!(
                "schema_version {} artifacts can only hold paper-schema models",
                self.schema_version
            )));
        }
        // The model's weights were checked against its configuration when it was built or parsed.
        let op = self.operating_point;
        if !(op.theta > 0.0 && op.theta < 1.0) || op.n_p == 0 {
            return Err(ArtifactError::Invalid(format!(
                "operating point theta={} n_p={} (need 0 < theta < 1 and n_p >= 1)",
                op.theta, op.n_p
            )));
        }
        Ok(())
    }
}
