//! Evidence parameters: the training statistics Σ̂ and μ_e, κ, ρ and the projection (SPEC §4).
//!
//! Owns the evidence parameters and their validation. Must not build evidence.

use serde::{Deserialize, Serialize};

use super::EvidenceError;
use super::drift::DriftParams;
use super::linalg::{Mat2, add_diagonal, is_symmetric_positive_definite};
use crate::geo::Projection;

/// ε added to every Σ before inversion (SPEC §4).
pub const SIGMA_EPSILON: f64 = 1e-6;
/// Default accumulator offset κ (SPEC §4).
pub const DEFAULT_KAPPA: f64 = 0.0;
/// Default accumulator forgetting factor ρ (SPEC §4).
pub const DEFAULT_RHO: f64 = 0.98;

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
}

/// The serialised form, checked by `TryFrom` before it becomes [`EvidenceParams`].
#[derive(Deserialize)]
struct UncheckedParams {
    sigma_hat: Mat2,
    mu_e: f64,
    #[serde(default = "default_kappa")]
    kappa: f64,
    #[serde(default = "default_rho")]
    rho: f64,
    #[serde(default)]
    projection: Projection,
    #[serde(default)]
    drift: Option<DriftParams>,
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
            drift: raw.drift,
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
        };
        params.validate()?;
        Ok(params)
    }

    /// Checks Σ̂ + εI is finite, symmetric and positive definite, μ_e and κ are finite and ρ ∈ [0, 1].
    pub fn validate(&self) -> Result<(), EvidenceError> {
        let invalid =
            |field: &'static str, reason: String| EvidenceError::InvalidParams { field, reason };
        if !is_symmetric_positive_definite(&self.regularised_sigma()) {
            return Err(invalid(
                "sigma_hat",
                format!(
                    "Σ̂ + εI must be finite, symmetric and positive definite, got {:?}",
                    self.sigma_hat
                ),
            ));
        }
        if !self.mu_e.is_finite() {
            return Err(invalid(
                "mu_e",
                format!("must be finite, got {}", self.mu_e),
            ));
        }
        if !self.kappa.is_finite() {
            return Err(invalid(
                "kappa",
                format!("must be finite, got {}", self.kappa),
            ));
        }
        if !(0.0..=1.0).contains(&self.rho) {
            return Err(invalid(
                "rho",
                format!("must be in [0, 1], got {}", self.rho),
            ));
        }
        if let Some(drift) = &self.drift {
            drift.validate()?;
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
