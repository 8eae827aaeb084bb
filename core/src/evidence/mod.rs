//! Causal evidence ξ_t (SPEC §4): the streaming builder, training statistics and the robust scaler.
//!
//! Owns evidence ξ_t (SPEC §4): builder, parameters, statistics, scaler. Must not know about models,
//! alarms or training.

mod builder;
pub mod linalg;
mod params;
mod scaler;
mod stats;

#[cfg(test)]
mod tests;

pub use builder::{Evidence, EvidenceBuilder, MAX_BACKWARD_S, MAX_GAP_S, build_track};
pub use params::{DEFAULT_KAPPA, DEFAULT_RHO, EvidenceParams, SIGMA_EPSILON};
pub use scaler::{CLIP, RobustScaler, SCALED_COUNT};
pub use stats::{
    MIN_NORMAL_ROWS, NormalStats, fit_normal_stats, median, quantile_sorted, stats_from_residuals,
};

/// Number of model input features in ξ_t.
pub const FEATURE_COUNT: usize = 9;
/// ξ_t in the locked order of SPEC §4.
pub const FEATURE_NAMES: [&str; FEATURE_COUNT] = [
    "eta_e",
    "eta_n",
    "eta_dot_e",
    "eta_dot_n",
    "eta_ddot_e",
    "eta_ddot_n",
    "q",
    "accum_log",
    "nu",
];
/// One ξ_t vector (scaled, ν last).
pub type Features = [f64; FEATURE_COUNT];

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
    /// A fit was given no rows at all.
    #[error("no evidence rows to fit on")]
    NoRows,
}
