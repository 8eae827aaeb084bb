//! Evidence parameters: the training statistics Σ̂ and μ_e, κ, ρ and the projection (SPEC §4).
//!
//! Owns the evidence parameters and their validation. Must not build evidence.

use serde::{Deserialize, Serialize};

use super::EvidenceError;
use super::drift::{DriftParams, UncheckedDriftParams};
use super::linalg::{Mat2, add_diagonal, is_symmetric_positive_definite};
use super::offset::OffsetParams;
use crate::geo::Projection;
use crate::sample::readable;

/// ε added to every Σ before inversion (SPEC §4).
pub const SIGMA_EPSILON: f64 = 1e-6;
/// Default accumulator offset κ (SPEC §4).
pub const DEFAULT_KAPPA: f64 = 0.0;
/// Default accumulator forgetting factor ρ (SPEC §4).
pub const DEFAULT_RHO: f64 = 0.98;
/// Largest accepted μ_e. μ_e is the median of η'η on the very rows Σ̂ was fitted on, whose mean is
/// 2 + (mean residual in σ units)²; trained artifacts hold 0.03 and 0.27. 1e6 still admits a mean
/// residual of 1000 σ, far beyond normal driving, and refuses values that make every q hugely negative
/// (μ_e = 1e308 alarms on almost every clean sample).
pub const MAX_MU_E: f64 = 1e6;
/// Largest accepted |κ| (the same units as μ_e; the training grid uses 0).
pub const MAX_ABS_KAPPA: f64 = 1e6;
/// Largest accepted entry of Σ̂ (m²): a residual standard deviation of 100 km is no GNSS receiver
/// (trained artifacts hold 5–37 m²).
pub const MAX_SIGMA_M2: f64 = 1e10;

/// Everything the evidence builder needs besides the samples.
///
/// Deserialisation validates like [`EvidenceParams::new`]. The fields are public for reading; a value
/// built by hand that fails [`EvidenceParams::validate`] still never panics the builder (Σ's
/// eigenvalues are floored), but its evidence is meaningless.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "UncheckedParams")]
pub struct EvidenceParams {
    /// Σ̂: ddof-1 covariance of r on normal ν = 1 training rows (m²), WITHOUT ε (the builder adds it).
    pub sigma_hat: Mat2,
    /// μ_e: median normalised residual energy on the same rows.
    pub mu_e: f64,
    /// κ: accumulator offset, q = e − μ_e − κ.
    pub kappa: f64,
    /// ρ: accumulator forgetting factor in [0, 1].
    pub rho: f64,
    /// How GNSS fixes become east/north metres.
    pub projection: Projection,
    /// Evidence v2: the drift channels' parameters (`None` for the paper's ξ_t).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub drift: Option<DriftParams>,
    /// Evidence v3: the anchors' parameters (`None` before v3).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub offset: Option<OffsetParams>,
}

/// The serialised form, checked by `TryFrom` before it becomes [`EvidenceParams`] (the artifact
/// reader parses it first, so that a type error and a value error are told apart).
#[derive(Deserialize)]
pub(crate) struct UncheckedParams {
    sigma_hat: Mat2,
    mu_e: f64,
    #[serde(default = "default_kappa")]
    kappa: f64,
    #[serde(default = "default_rho")]
    rho: f64,
    #[serde(default)]
    projection: Projection,
    #[serde(default)]
    drift: Option<UncheckedDriftParams>,
    #[serde(default)]
    offset: Option<OffsetParams>,
}

fn default_kappa() -> f64 {
    DEFAULT_KAPPA
}

fn default_rho() -> f64 {
    DEFAULT_RHO
}

impl TryFrom<UncheckedParams> for EvidenceParams {
    type Error = EvidenceError;

    fn try_from(raw: UncheckedParams) -> Result<Self, EvidenceError> {
        let params = EvidenceParams {
            sigma_hat: raw.sigma_hat,
            mu_e: raw.mu_e,
            kappa: raw.kappa,
            rho: raw.rho,
            projection: raw.projection,
            drift: raw.drift.map(DriftParams::unchecked),
            offset: raw.offset,
        };
        params.validate()?;
        Ok(params)
    }
}

impl EvidenceParams {
    /// Validated parameters with the default κ = 0 and ρ = 0.98.
    pub fn new(sigma_hat: Mat2, mu_e: f64, projection: Projection) -> Result<Self, EvidenceError> {
        Self::with_accumulator(sigma_hat, mu_e, DEFAULT_KAPPA, DEFAULT_RHO, projection)
    }

    /// Validated parameters with an explicit κ and ρ (e.g. from the training job's grid).
    pub fn with_accumulator(
        sigma_hat: Mat2,
        mu_e: f64,
        kappa: f64,
        rho: f64,
        projection: Projection,
    ) -> Result<Self, EvidenceError> {
        let params = Self {
            sigma_hat,
            mu_e,
            kappa,
            rho,
            projection,
            drift: None,
            offset: None,
        };
        params.validate()?;
        Ok(params)
    }

    /// Identity Σ̂, μ_e = κ = ρ = 0 and no v2/v3 parameters: for passes that need only trajectory
    /// boundaries, ν and residuals (which do not depend on the statistics), or as the base the fits
    /// add their channels' parameters to.
    pub fn unnormalised(projection: Projection) -> Self {
        Self {
            sigma_hat: [[1.0, 0.0], [0.0, 1.0]],
            mu_e: 0.0,
            kappa: 0.0,
            rho: 0.0,
            projection,
            drift: None,
            offset: None,
        }
    }

    /// Checks Σ̂ + εI is symmetric positive definite with entries within ±[`MAX_SIGMA_M2`],
    /// μ_e ∈ [0, [`MAX_MU_E`]], |κ| ≤ [`MAX_ABS_KAPPA`], ρ ∈ [0, 1] and the drift parameters.
    pub fn validate(&self) -> Result<(), EvidenceError> {
        let invalid =
            |field: &'static str, reason: String| EvidenceError::InvalidParams { field, reason };
        let sigma = self.sigma_hat.iter().flatten();
        if let Some(&bad) = sigma
            .clone()
            .find(|v| !(-MAX_SIGMA_M2..=MAX_SIGMA_M2).contains(*v))
        {
            return Err(invalid(
                "sigma_hat",
                format!(
                    "every entry must be finite and within ±{MAX_SIGMA_M2:e} m², got {}",
                    readable(bad)
                ),
            ));
        }
        if !is_symmetric_positive_definite(&self.regularised_sigma()) {
            let entries: Vec<String> = sigma.map(|&v| readable(v)).collect();
            return Err(invalid(
                "sigma_hat",
                format!(
                    "Σ̂ + εI must be symmetric and positive definite, got [[{}, {}], [{}, {}]]",
                    entries[0], entries[1], entries[2], entries[3]
                ),
            ));
        }
        if !(0.0..=MAX_MU_E).contains(&self.mu_e) {
            return Err(invalid(
                "mu_e",
                format!(
                    "must be finite and in [0, {MAX_MU_E:e}] (a median energy), got {}",
                    readable(self.mu_e)
                ),
            ));
        }
        if !(-MAX_ABS_KAPPA..=MAX_ABS_KAPPA).contains(&self.kappa) {
            return Err(invalid(
                "kappa",
                format!(
                    "must be finite and within ±{MAX_ABS_KAPPA:e}, got {}",
                    readable(self.kappa)
                ),
            ));
        }
        if !(0.0..=1.0).contains(&self.rho) {
            return Err(invalid(
                "rho",
                format!("must be in [0, 1], got {}", readable(self.rho)),
            ));
        }
        if let Some(drift) = &self.drift {
            drift.validate()?;
        }
        if let Some(offset) = &self.offset {
            offset.validate()?;
        }
        Ok(())
    }

    /// Σ̂ + εI, the matrix the builder actually inverts.
    pub fn regularised_sigma(&self) -> Mat2 {
        add_diagonal(self.sigma_hat, SIGMA_EPSILON)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_and_validation() {
        let p = EvidenceParams::new([[2.0, 0.1], [0.1, 1.0]], 0.3, Projection::default())
            .expect("valid");
        assert_eq!((p.kappa, p.rho), (0.0, 0.98));
        // A zero covariance is fine: ε makes it positive definite.
        assert!(EvidenceParams::new([[0.0; 2]; 2], 0.0, Projection::Wgs84Local).is_ok());
        let err = EvidenceParams::new([[1.0, 2.0], [2.0, 1.0]], 0.3, Projection::Wgs84Local)
            .expect_err("indefinite");
        assert!(err.to_string().contains("sigma_hat"), "{err}");
        let err = EvidenceParams::with_accumulator(
            [[1.0, 0.0], [0.0, 1.0]],
            0.3,
            0.0,
            1.5,
            Projection::Wgs84Local,
        )
        .expect_err("rho");
        assert!(err.to_string().contains("rho"), "{err}");
        let err = EvidenceParams::new([[1.0, 0.0], [0.0, 1.0]], f64::NAN, Projection::Wgs84Local)
            .expect_err("mu_e");
        assert!(err.to_string().contains("mu_e"), "{err}");
    }

    #[test]
    fn deserialisation_validates_and_fills_defaults() {
        let p: EvidenceParams =
            serde_json::from_str(r#"{"sigma_hat":[[2.0,0.0],[0.0,1.0]],"mu_e":0.5}"#)
                .expect("valid json");
        assert_eq!(p.rho, DEFAULT_RHO);
        assert_eq!(p.projection, Projection::Wgs84Local);
        let round: EvidenceParams =
            serde_json::from_str(&serde_json::to_string(&p).expect("serialise")).expect("back");
        assert_eq!(round, p);
        let bad = serde_json::from_str::<EvidenceParams>(
            r#"{"sigma_hat":[[2.0,0.0],[0.0,1.0]],"mu_e":0.5,"rho":-1}"#,
        );
        assert!(bad.expect_err("rho").to_string().contains("rho"));
    }
}
