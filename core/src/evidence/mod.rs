//! Causal evidence ξ_t (SPEC §4): the streaming builder, training statistics and the robust scaler.
//!
//! Owns evidence ξ_t (SPEC §4): builder, parameters, statistics, scaler. Must not know about models,
//! alarms or training.
//!
//! Inside, each file uses only those listed before it: `linalg` and `stats` (pure numerics),
//! `calibration` (the onboard calibration's numerics and trust), `drift` (the v2 channels), `drift_fit` (their normalisation fit), `offset` (the v3 anchors), `params`, `builder` (the streaming builder), `scaler`, then `fit` (the fits from
//! training tracks, which run the builder).

mod builder;
pub mod calibration;
pub mod drift;
pub mod drift_fit;
mod fit;
pub mod linalg;
pub mod offset;
mod params;
mod scaler;
mod stats;

#[cfg(test)]
mod tests;
#[cfg(test)]
mod trust_tests;

use serde::{Deserialize, Serialize};

pub use builder::{
    DriftChannelsDiffer, Evidence, EvidenceBuilder, MAX_BACKWARD_S, MAX_GAP_S, build_track,
};
pub use fit::{
    EvidenceFit, EvidenceFitError, EvidenceOptions, MIN_NORMAL_ROWS, NormalStats, fit_drift_params,
    fit_evidence, fit_evidence_with, fit_normal_stats, fit_offset_params, normal_residuals,
    robust_residual_sigma, stats_from_residuals,
};
pub(crate) use params::UncheckedParams;
pub use params::{
    DEFAULT_KAPPA, DEFAULT_RHO, EvidenceParams, MAX_ABS_KAPPA, MAX_MU_E, MAX_SIGMA_M2,
    SIGMA_EPSILON,
};
pub(crate) use scaler::UncheckedScaler;
pub use scaler::{CLIP, MAX_SCALER_VALUE, RobustScaler};
pub use stats::{median, quantile_sorted};

/// ξ_t in the locked order of SPEC §4 (the `paper` schema), then the drift channels of evidence v2
/// (`docs/detector.md` §4.1), then the offset channels of evidence v3 (§4.2). A schema reads a prefix
/// of this list.
pub const FEATURE_NAMES: [&str; FEATURE_CAPACITY] = [
    "eta_e",
    "eta_n",
    "eta_dot_e",
    "eta_dot_n",
    "eta_ddot_e",
    "eta_ddot_n",
    "q",
    "accum_log",
    "nu",
    "raw_drift_10s",
    "raw_drift_30s",
    "raw_drift_60s",
    "raw_drift_120s",
    "calibrated_drift_10s",
    "calibrated_drift_30s",
    "calibrated_drift_60s",
    "calibrated_drift_120s",
    "drift_statistic",
    "warm_up",
    "stale_fix",
    "residual_log",
    "offset_fast",
    "offset_slow",
    "offset_held",
    "offset_share_10s",
    "offset_share_60s",
];
/// Length of the longest schema's ξ_t.
pub const FEATURE_CAPACITY: usize = 26;
/// Index of ν in every schema (it is never scaled).
pub const NU_INDEX: usize = 8;
/// First index of the drift channels (v2).
pub const DRIFT_FEATURES_START: usize = 9;
/// First index of the offset channels (v3).
pub const OFFSET_FEATURES_START: usize = 21;
/// One ξ_t vector (scaled, order of [`FEATURE_NAMES`]); entries beyond the schema's count are 0.
pub type Features = [f64; FEATURE_CAPACITY];

/// Which evidence channels a model reads: a prefix of [`FEATURE_NAMES`].
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FeatureSchema {
    /// The paper's 9-channel ξ_t, for the faithful reproduction and the paper's tables.
    Paper,
    /// The paper's ξ_t plus the directional drift channels.
    V2,
    /// v2 plus the offset channels of the dead-reckoning anchors: the bundled default's, and the
    /// default of every training path (without offsets a model never alarms on a jump).
    #[default]
    V3,
}

impl FeatureSchema {
    /// Every schema with its name on the command line and on the wire.
    pub const NAMED: [(&'static str, FeatureSchema); 3] =
        [("paper", Self::Paper), ("v2", Self::V2), ("v3", Self::V3)];

    /// The schema's name in [`Self::NAMED`].
    pub fn name(self) -> &'static str {
        match self {
            Self::Paper => "paper",
            Self::V2 => "v2",
            Self::V3 => "v3",
        }
    }

    /// The schema named `name` in [`Self::NAMED`].
    pub fn from_name(name: &str) -> Option<Self> {
        Self::NAMED
            .iter()
            .find(|(n, _)| *n == name)
            .map(|(_, schema)| *schema)
    }

    /// Artifacts written before schemas were named (artifact schema version 1) are `paper`.
    pub fn legacy() -> Self {
        Self::Paper
    }

    /// Number of ξ channels.
    pub fn feature_count(self) -> usize {
        match self {
            Self::Paper => DRIFT_FEATURES_START,
            Self::V2 => OFFSET_FEATURES_START,
            Self::V3 => FEATURE_CAPACITY,
        }
    }

    /// The channel names, in order.
    pub fn feature_names(self) -> &'static [&'static str] {
        &FEATURE_NAMES[..self.feature_count()]
    }

    /// Whether the evidence needs the drift tracker.
    pub fn has_drift(self) -> bool {
        matches!(self, Self::V2 | Self::V3)
    }

    /// Whether the evidence needs the dead-reckoning anchors.
    pub fn has_offset(self) -> bool {
        self == Self::V3
    }
}

/// Problems with evidence parameters or statistics.
#[derive(Debug, thiserror::Error)]
pub enum EvidenceError {
    /// A parameter is out of its domain.
    #[error("invalid evidence parameter {field}: {reason}")]
    InvalidParams {
        /// The parameter's field name.
        field: &'static str,
        /// What is wrong with it.
        reason: String,
    },
    /// Not enough normal valid rows to estimate Σ̂ and μ_e.
    #[error(
        "too few normal valid rows for the residual statistics: {rows} (label 0, ν = 1), need at least {minimum}"
    )]
    TooFewNormalRows {
        /// Rows found.
        rows: usize,
        /// Rows required.
        minimum: usize,
    },
    /// Too few normal rows deep enough into a trajectory to fit a drift channel's normalisation.
    #[error(
        "the v2 feature schema needs longer normal driving: {rows} normal rows are at least {settle_s} s \
         into a trajectory{warm} for the {scale_s} s drift channel, need at least {minimum} (each \
         training trajectory should hold 4+ minutes of normal driving); train with the paper feature \
         schema for short recordings"
    )]
    TooFewSettledRows {
        /// The channel's time scale τ_k (s).
        scale_s: f64,
        /// How deep into a trajectory a row must be (s).
        settle_s: f64,
        /// " with a warm calibration" for the calibrated channels, else "".
        warm: &'static str,
        /// Rows found.
        rows: usize,
        /// Rows required.
        minimum: usize,
    },
    /// Too few normal rows to fit the anchors' noise and growth.
    #[error(
        "the v3 feature schema needs more normal driving for the offset anchors: {rows} normal \
         seconds before any attack, need at least {minimum}"
    )]
    TooFewOffsetRows {
        /// Points found.
        rows: usize,
        /// Points required.
        minimum: usize,
    },
    /// A fit was given no rows at all.
    #[error("no evidence rows to fit on")]
    NoRows,
}
