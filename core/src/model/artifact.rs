//! The self-contained model artifact: everything needed to serve (SPEC §5), as one JSON document
//! with a versioned schema — the trained model plus its evidence statistics, scaler, operating point
//! and provenance.
//!
//! Owns the artifact's schema, (de)serialisation and field checks (the documented ranges of
//! `docs/detector.md` §5.1, with errors that name the field). The public ways in and out
//! (`from_slice`, `read`, `write`, `to_vec`, `validate`) add the canary drive to these checks and live
//! in [`crate::canary`], above the detector the canary runs. Must not run the model on data (that is
//! [`crate::detector`]) nor produce artifacts (that is [`crate::train::detector`]).

use std::io::Write;

use serde::{Deserialize, Serialize};

use super::{
    MAX_ABS_PARAMETER, MAX_DIMENSION, MAX_TAU_S, MIN_TAU_S, Model, ModelError, ModelParts,
};
use crate::alarm::{AlarmError, OperatingPoint};
use crate::evidence::{
    EvidenceError, EvidenceParams, FeatureSchema, RobustScaler, UncheckedParams, UncheckedScaler,
};
use crate::lifecycle::Lifecycle;
use crate::metrics::Metrics;
use crate::sample::readable;
use crate::severity::CriticalTest;

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
    /// The alarm lifecycle in seconds (`None`: the persistence N_p of the operating point, in rows).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lifecycle: Option<Lifecycle>,
    /// When an alarm turns critical (`docs/detector.md` §7.4); `None`: warnings only (artifacts
    /// made before severities existed, and models without a lifecycle).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub critical: Option<CriticalTest>,
    pub provenance: Provenance,
}

/// Longest free-text field of the provenance (`created_by`, `notes`, each `training_data` entry), in
/// bytes. Real artifacts hold under 300 bytes per field; the bound keeps a model's description well
/// inside one gRPC message (`GetModel`) however many models the registry holds.
pub const MAX_PROVENANCE_TEXT_BYTES: usize = 4096;
/// Most `training_data` entries (one per training dataset or data source).
pub const MAX_TRAINING_DATA_ENTRIES: usize = 256;

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

impl Provenance {
    /// A training-data description within the bounds: at most [`MAX_TRAINING_DATA_ENTRIES`] entries
    /// (the last one then says how many were left out), each cut to [`MAX_PROVENANCE_TEXT_BYTES`].
    pub fn bounded_training_data(entries: Vec<String>) -> Vec<String> {
        let total = entries.len();
        let mut bounded: Vec<String> = entries
            .into_iter()
            .take(MAX_TRAINING_DATA_ENTRIES)
            .map(|entry| truncate(entry, MAX_PROVENANCE_TEXT_BYTES))
            .collect();
        if total > MAX_TRAINING_DATA_ENTRIES {
            bounded.truncate(MAX_TRAINING_DATA_ENTRIES - 1);
            let shown = bounded.len();
            bounded.push(format!("... and {} more", total - shown));
        }
        bounded
    }

    /// Checks the free-text bounds; the error names the field (`notes`, `training_data[3]`...).
    fn validate(&self) -> Result<(), (String, String)> {
        let too_long = |text: &str| text.len() > MAX_PROVENANCE_TEXT_BYTES;
        let reason = |text: &str| {
            format!(
                "must be at most {MAX_PROVENANCE_TEXT_BYTES} bytes, got {}",
                text.len()
            )
        };
        for (field, text) in [("created_by", &self.created_by), ("notes", &self.notes)] {
            if too_long(text) {
                return Err((field.to_string(), reason(text)));
            }
        }
        if self.training_data.len() > MAX_TRAINING_DATA_ENTRIES {
            return Err((
                "training_data".to_string(),
                format!(
                    "must have at most {MAX_TRAINING_DATA_ENTRIES} entries, got {}",
                    self.training_data.len()
                ),
            ));
        }
        if let Some((i, text)) = (self.training_data.iter().enumerate()).find(|(_, t)| too_long(t))
        {
            return Err((format!("training_data[{i}]"), reason(text)));
        }
        Ok(())
    }
}

/// Provenance free text cut to [`MAX_PROVENANCE_TEXT_BYTES`] (on a character boundary), e.g. for
/// showing text stored before the bound existed.
pub fn bounded_provenance_text(text: String) -> String {
    truncate(text, MAX_PROVENANCE_TEXT_BYTES)
}

/// `text` cut to at most `max_bytes` on a character boundary.
fn truncate(mut text: String, max_bytes: usize) -> String {
    if text.len() > max_bytes {
        let mut end = max_bytes;
        while !text.is_char_boundary(end) {
            end -= 1;
        }
        text.truncate(end);
    }
    text
}

/// Why an artifact cannot be loaded or saved. Every refusal of the artifact's content names the field
/// ([`ArtifactError::field`]), as a JSON path such as `evidence.mu_e` or `model.params.w_out`.
#[derive(Debug, thiserror::Error)]
pub enum ArtifactError {
    #[error("reading the model artifact: {0}")]
    Io(#[from] std::io::Error),
    /// A JSON syntax error (or a number beyond f64); `path` is where the parser was, when known.
    #[error("the model artifact is not valid JSON{}: {source}", path.as_ref().map(|p| format!(" in {p}")).unwrap_or_default())]
    Json {
        source: serde_json::Error,
        path: Option<String>,
    },
    #[error("writing the model artifact: {0}")]
    Write(serde_json::Error),
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
    /// A field is missing, has the wrong type or a value outside its documented range.
    #[error("{field}: {reason}")]
    Field { field: String, reason: String },
}

impl ArtifactError {
    /// The JSON path of the offending field (`evidence.mu_e`, `model.params.w_out`...), when the error
    /// is about the artifact's content and the place is known.
    pub fn field(&self) -> Option<String> {
        match self {
            Self::Io(_) | Self::Write(_) => None,
            Self::Json { path, .. } => path.clone(),
            Self::MissingSchemaVersion | Self::UnsupportedSchema { .. } => {
                Some("schema_version".to_string())
            }
            Self::FeatureMismatch { .. } => Some("feature_names".to_string()),
            Self::Field { field, .. } => Some(field.clone()),
        }
    }

    pub(crate) fn field_error(field: impl Into<String>, reason: impl Into<String>) -> Self {
        Self::Field {
            field: field.into(),
            reason: reason.into(),
        }
    }

    /// An evidence or scaler refusal; `prefix` is the path of the validated part (`evidence.`, or ``
    /// for the scaler, whose fields are named `scaler.center`/`scaler.scale` already).
    fn from_evidence(prefix: &str, error: EvidenceError) -> Self {
        match error {
            EvidenceError::InvalidParams { field, reason } => {
                Self::field_error(format!("{prefix}{field}"), reason)
            }
            other => Self::field_error(prefix.trim_end_matches('.'), other.to_string()),
        }
    }

    /// A model refusal, at the path of the configuration value or tensor it is about.
    fn from_model(error: ModelError) -> Self {
        let tensor = |name: &str| format!("model.params.{name}");
        match error {
            ModelError::TooManyParameters { .. } => {
                Self::field_error("model.config", error.to_string())
            }
            ModelError::InvalidDimension { name, value } => Self::field_error(
                format!("model.config.{name}"),
                format!("must be in 1..={MAX_DIMENSION}, got {value}"),
            ),
            ModelError::InvalidTimeConstants { tau_min, .. } => {
                let field = if (MIN_TAU_S..MAX_TAU_S).contains(&tau_min) {
                    "model.config.tau_max"
                } else {
                    "model.config.tau_min"
                };
                Self::field_error(field, error.to_string())
            }
            ModelError::TensorLength {
                ref name,
                expected,
                found,
            } => Self::field_error(
                format!("{}.data", tensor(name)),
                format!("has {found} values, its shape needs {expected}"),
            ),
            ModelError::MissingParameter { name } => {
                Self::field_error(tensor(name), "is missing for this model configuration")
            }
            ModelError::UnexpectedParameter { name } => {
                Self::field_error(tensor(name), "is not used by this model configuration")
            }
            ModelError::ShapeMismatch {
                name,
                expected,
                found,
            } => Self::field_error(
                format!("{}.shape", tensor(name)),
                format!("expected {expected:?}, got {found:?}"),
            ),
            ModelError::NonFiniteParameter { name, index } => Self::field_error(
                tensor(name),
                format!("value at flat index {index} must be finite"),
            ),
            ModelError::ParameterOutOfRange { name, index, value } => Self::field_error(
                tensor(name),
                format!(
                    "value at flat index {index} must be within ±{MAX_ABS_PARAMETER:e}, got {}",
                    readable(value)
                ),
            ),
            other @ (ModelError::LengthMismatch { .. } | ModelError::StateWidth { .. }) => {
                Self::field_error("model", other.to_string())
            }
        }
    }

    /// A type or presence error found while parsing, at its JSON path. serde reports a missing field
    /// at the enclosing object, so its name is moved into the path.
    fn from_parse(error: serde_path_to_error::Error<serde_json::Error>) -> Self {
        let path = path_text(error.path());
        let message = error.inner().to_string();
        let join = |name: &str| {
            if path.is_empty() {
                name.to_string()
            } else {
                format!("{path}.{name}")
            }
        };
        let quoted = |prefix: &str| {
            message
                .strip_prefix(prefix)
                .and_then(|rest| rest.split_once('`'))
                .map(|(name, rest)| {
                    (
                        name.to_string(),
                        rest.trim_start_matches(',').trim().to_string(),
                    )
                })
        };
        if let Some((name, _)) = quoted("missing field `") {
            return Self::field_error(join(&name), "is required");
        }
        if let Some((name, rest)) = quoted("unknown field `") {
            // The path already ends at the unknown key.
            let field = if path.is_empty() { name } else { path };
            return Self::field_error(field, format!("is not a known field ({rest})"));
        }
        Self::field_error(
            if path.is_empty() { "." } else { &path },
            shorten_quoted(&shorten_quoted(&message, '"'), '`'),
        )
    }
}

/// Most characters of a value from the artifact that an error quotes: serde quotes an offending
/// string whole, and the error travels back to whoever sent it.
const MAX_QUOTED_CHARS: usize = 80;

/// `message` with each value between two `quote`s longer than [`MAX_QUOTED_CHARS`] cut, saying how
/// long it was (`"abc…" (5000 chars)`). A backslash escapes a quote inside a value.
fn shorten_quoted(message: &str, quote: char) -> String {
    let mut shortened = String::with_capacity(message.len().min(1024));
    let mut rest = message;
    while let Some(open) = rest.find(quote) {
        shortened.push_str(&rest[..open + quote.len_utf8()]);
        let value = &rest[open + quote.len_utf8()..];
        let mut escaped = false;
        let close = value.char_indices().find_map(|(at, c)| {
            let closes = c == quote && !escaped;
            escaped = c == '\\' && !escaped;
            closes.then_some(at)
        });
        let Some(close) = close else {
            rest = value;
            break;
        };
        let quoted = &value[..close];
        let chars = quoted.chars().count();
        if chars > MAX_QUOTED_CHARS {
            shortened.extend(quoted.chars().take(MAX_QUOTED_CHARS));
            shortened.push_str(&format!("…{quote} ({chars} chars)"));
        } else {
            shortened.push_str(quoted);
            shortened.push(quote);
        }
        rest = &value[close + quote.len_utf8()..];
    }
    shortened.push_str(rest);
    shortened
}

/// A parse path as `model.params.w_out.data[3]` (empty at the root).
fn path_text(path: &serde_path_to_error::Path) -> String {
    if path.iter().next().is_none() {
        String::new()
    } else {
        path.to_string()
    }
}

/// The artifact as parsed, before any value is checked: what lets a type error (here) and a value
/// error ([`RawArtifact::into_checked`]) each name their field.
#[derive(Deserialize)]
struct RawArtifact {
    schema_version: u32,
    feature_names: Vec<String>,
    model: ModelParts,
    evidence: UncheckedParams,
    scaler: UncheckedScaler,
    operating_point: OperatingPoint,
    #[serde(default)]
    lifecycle: Option<Lifecycle>,
    #[serde(default)]
    critical: Option<CriticalTest>,
    provenance: Provenance,
}

impl RawArtifact {
    /// The parts built and validated one by one (their cross-checks are
    /// [`ModelArtifact::check_fields`]).
    fn into_checked(self) -> Result<ModelArtifact, ArtifactError> {
        let model = Model::from_parts(self.model.config, self.model.params)
            .map_err(ArtifactError::from_model)?;
        let evidence = EvidenceParams::try_from(self.evidence)
            .map_err(|e| ArtifactError::from_evidence("evidence.", e))?;
        let scaler =
            RobustScaler::try_from(self.scaler).map_err(|e| ArtifactError::from_evidence("", e))?;
        Ok(ModelArtifact {
            schema_version: self.schema_version,
            feature_names: self.feature_names,
            model,
            evidence,
            scaler,
            operating_point: self.operating_point,
            lifecycle: self.lifecycle,
            critical: self.critical,
            provenance: self.provenance,
        })
    }
}

/// What a JSON value is, for "expected ..., got ..." messages.
fn describe(value: &serde_json::Value) -> String {
    use serde_json::Value;
    match value {
        Value::Null => "null".to_string(),
        Value::Bool(_) => "a boolean".to_string(),
        Value::Number(n) => n.to_string(),
        Value::String(_) => "a string".to_string(),
        Value::Array(_) => "an array".to_string(),
        Value::Object(_) => "an object".to_string(),
    }
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

    /// Switches the offset anchors' re-basing on a calibration change on or off (`docs/detector.md`
    /// §4.2); a model without offset evidence has none to switch.
    pub fn set_anchor_rebasing(&mut self, on: bool) {
        if let Some(offset) = self.evidence.offset.as_mut() {
            offset.rebase_on_calibration = on;
        }
    }

    /// Parses an artifact: JSON syntax, then the schema version (before anything else, so a newer
    /// artifact gets a clear message instead of a field-level parse error), then every field's type
    /// and each part's own ranges. The parts' cross-checks and the canary drive are left to
    /// [`ModelArtifact::validate`], which [`ModelArtifact::from_slice`] runs next.
    pub(crate) fn parse(bytes: &[u8]) -> Result<Self, ArtifactError> {
        let value: serde_json::Value =
            serde_json::from_slice(bytes).map_err(|source| ArtifactError::Json {
                path: syntax_error_path(bytes),
                source,
            })?;
        let version = value
            .get("schema_version")
            .ok_or(ArtifactError::MissingSchemaVersion)?;
        let found = version.as_u64().ok_or_else(|| {
            ArtifactError::field_error(
                "schema_version",
                format!("expected an unsigned integer, got {}", describe(version)),
            )
        })?;
        let readable_versions =
            u64::from(OLDEST_READABLE_SCHEMA_VERSION)..=u64::from(ARTIFACT_SCHEMA_VERSION);
        if !readable_versions.contains(&found) {
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
        let raw: RawArtifact =
            serde_path_to_error::deserialize(&value).map_err(ArtifactError::from_parse)?;
        raw.into_checked()
    }

    /// Writes the artifact as pretty JSON, unchecked (the public [`ModelArtifact::write`] validates
    /// first).
    pub(crate) fn write_json<W: Write>(&self, writer: W) -> Result<(), ArtifactError> {
        serde_json::to_writer_pretty(writer, self).map_err(ArtifactError::Write)
    }

    /// Checks every value is in its documented range (`docs/detector.md` §5.1) and the parts fit
    /// together: feature order, scaler and evidence parameters against the model's schema, weights
    /// against the configuration, operating point, provenance bounds. [`ModelArtifact::validate`]
    /// runs these checks, then the canary drive.
    pub(crate) fn check_fields(&self) -> Result<(), ArtifactError> {
        let schema = self.schema();
        let expected = Self::feature_names_of(schema);
        if self.feature_names != expected {
            return Err(ArtifactError::FeatureMismatch {
                found: self.feature_names.clone(),
                expected,
            });
        }
        let config = self.model.config();
        config.validate().map_err(ArtifactError::from_model)?;
        // Training changes the weights in place, so they are checked again here.
        self.model
            .params()
            .validate(config)
            .map_err(ArtifactError::from_model)?;
        if self.schema_version < 2 && schema != FeatureSchema::legacy() {
            return Err(ArtifactError::field_error(
                "model.config.schema",
                format!(
                    "schema_version {} artifacts can only hold paper-schema models",
                    self.schema_version
                ),
            ));
        }
        self.evidence
            .validate()
            .map_err(|e| ArtifactError::from_evidence("evidence.", e))?;
        let scaler_schema = self
            .scaler
            .schema()
            .map_err(|e| ArtifactError::from_evidence("", e))?;
        if scaler_schema != schema {
            return Err(ArtifactError::field_error(
                "scaler.center",
                format!(
                    "the scaler has {} components, the {} feature schema needs {}",
                    self.scaler.center.len(),
                    schema.name(),
                    schema.feature_count() - 1
                ),
            ));
        }
        if self.evidence.drift.is_some() != schema.has_drift() {
            return Err(ArtifactError::field_error(
                "evidence.drift",
                format!(
                    "the {} feature schema {} drift parameters",
                    schema.name(),
                    if schema.has_drift() {
                        "needs"
                    } else {
                        "has no use for"
                    }
                ),
            ));
        }
        if self.evidence.offset.is_some() != schema.has_offset() {
            return Err(ArtifactError::field_error(
                "evidence.offset",
                format!(
                    "the {} feature schema {} offset parameters",
                    schema.name(),
                    if schema.has_offset() {
                        "needs"
                    } else {
                        "has no use for"
                    }
                ),
            ));
        }
        self.operating_point.validate().map_err(|e| match e {
            AlarmError::InvalidOperatingPoint { field, reason } => {
                ArtifactError::field_error(format!("operating_point.{field}"), reason)
            }
            other => ArtifactError::field_error("operating_point", other.to_string()),
        })?;
        if let Some(lifecycle) = &self.lifecycle {
            lifecycle.validate().map_err(|(field, reason)| {
                ArtifactError::field_error(format!("lifecycle.{field}"), reason)
            })?;
        }
        if let Some(critical) = &self.critical {
            if self.lifecycle.is_none() {
                return Err(ArtifactError::field_error(
                    "critical",
                    "a critical test needs the alarm lifecycle in seconds (`lifecycle`)",
                ));
            }
            critical.validate().map_err(|(field, reason)| {
                ArtifactError::field_error(format!("critical.{field}"), reason)
            })?;
        }
        self.provenance.validate().map_err(|(field, reason)| {
            ArtifactError::field_error(format!("provenance.{field}"), reason)
        })
    }
}

/// Where a JSON syntax error sits (`model.params.w_out.data[7]`), found by parsing again with the path
/// tracked; `None` when the second parse stops for another reason first (then the place is not known).
fn syntax_error_path(bytes: &[u8]) -> Option<String> {
    let mut deserializer = serde_json::Deserializer::from_slice(bytes);
    let error = serde_path_to_error::deserialize::<_, RawArtifact>(&mut deserializer).err()?;
    let inner = error.inner();
    let path = path_text(error.path());
    ((inner.is_syntax() || inner.is_eof()) && !path.is_empty()).then_some(path)
}
