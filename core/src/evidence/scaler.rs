//! The label-free robust scaler of every ξ component except ν (SPEC §4).
//!
//! Owns the robust feature scaler. Must not build evidence.

use serde::{Deserialize, Serialize};

use super::builder::Evidence;
use super::stats::quantile_sorted;
use super::{EvidenceError, FEATURE_CAPACITY, FEATURE_NAMES, FeatureSchema, Features, NU_INDEX};
use crate::sample::readable;

/// Scaled values are clipped to ±this.
pub const CLIP: f64 = 20.0;
/// An IQR (or std) below this is treated as zero spread; it is also the smallest scale a fit produces,
/// and so the smallest an artifact may hold.
const ZERO_SPREAD: f64 = 1e-8;
/// Largest accepted |center| and scale. Trained scalers hold values below 25 (whitened residuals and
/// their rates, log energies, drift statistics); 1e12 admits rates of finely sampled data (η̈ grows as
/// 1/δ²) with a wide margin, and refuses values that only a corrupted artifact holds.
pub const MAX_SCALER_VALUE: f64 = 1e12;

/// Per-component median/IQR scaling of ξ (every component of the schema but ν, in order); ν passes
/// through. The paper schema has 8 scaled components, v2 has 18.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "UncheckedScaler")]
pub struct RobustScaler {
    /// Medians.
    pub center: Vec<f64>,
    /// IQR, else population std, else 1 (never zero).
    pub scale: Vec<f64>,
}

/// The serialised form, checked by `TryFrom` (the artifact reader parses it first).
#[derive(Deserialize)]
pub(crate) struct UncheckedScaler {
    center: Vec<f64>,
    scale: Vec<f64>,
}

impl TryFrom<UncheckedScaler> for RobustScaler {
    type Error = EvidenceError;

    fn try_from(raw: UncheckedScaler) -> Result<Self, EvidenceError> {
        let scaler = RobustScaler {
            center: raw.center,
            scale: raw.scale,
        };
        scaler.schema()?;
        Ok(scaler)
    }
}

/// Feature index of the `k`-th scaled component (ν is skipped).
fn feature_index(k: usize) -> usize {
    if k < NU_INDEX { k } else { k + 1 }
}

impl RobustScaler {
    /// Fits on ALL given rows (valid or not, any label), with pandas type-7 quantiles. Non-finite
    /// values are skipped as pandas skips NaN; a component with no finite value gets center 0, scale 1.
    pub fn fit(rows: &[Evidence], schema: FeatureSchema) -> Result<Self, EvidenceError> {
        if rows.is_empty() {
            return Err(EvidenceError::NoRows);
        }
        let scaled = schema.feature_count() - 1;
        let mut center = vec![0.0; scaled];
        let mut scale = vec![1.0; scaled];
        let mut column = Vec::with_capacity(rows.len());
        for k in 0..scaled {
            let index = feature_index(k);
            column.clear();
            column.extend(
                rows.iter()
                    .map(|e| e.raw_features()[index])
                    .filter(|x| x.is_finite()),
            );
            column.sort_unstable_by(f64::total_cmp);
            let (Some(q25), Some(q50), Some(q75)) = (
                quantile_sorted(&column, 0.25),
                quantile_sorted(&column, 0.5),
                quantile_sorted(&column, 0.75),
            ) else {
                continue;
            };
            center[k] = q50;
            scale[k] = spread(&column, q75 - q25);
        }
        Ok(Self { center, scale })
    }

    /// The schema this scaler was fitted for (from its length); checks every center is finite within
    /// ±[`MAX_SCALER_VALUE`] and every scale within [`ZERO_SPREAD`], [`MAX_SCALER_VALUE`]].
    pub fn schema(&self) -> Result<FeatureSchema, EvidenceError> {
        let invalid =
            |field: &'static str, reason: String| EvidenceError::InvalidParams { field, reason };
        let schema = FeatureSchema::NAMED
            .iter()
            .map(|(_, schema)| *schema)
            .find(|schema| schema.feature_count() - 1 == self.center.len())
            .ok_or_else(|| {
                invalid(
                    "scaler.center",
                    format!(
                        "{} centers fit no feature schema (paper: 8, v2: 20)",
                        self.center.len()
                    ),
                )
            })?;
        if self.scale.len() != self.center.len() {
            return Err(invalid(
                "scaler.scale",
                format!(
                    "{} scales for {} centers",
                    self.scale.len(),
                    self.center.len()
                ),
            ));
        }
        let component = |k: usize| FEATURE_NAMES[feature_index(k)];
        if let Some((k, bad)) = (self.center.iter().enumerate())
            .find(|(_, c)| !(-MAX_SCALER_VALUE..=MAX_SCALER_VALUE).contains(*c))
        {
            return Err(invalid(
                "scaler.center",
                format!(
                    "every center must be finite and within ±{MAX_SCALER_VALUE:e}, got {} for {}",
                    readable(*bad),
                    component(k)
                ),
            ));
        }
        if let Some((k, bad)) = (self.scale.iter().enumerate())
            .find(|(_, s)| !(ZERO_SPREAD..=MAX_SCALER_VALUE).contains(*s))
        {
            return Err(invalid(
                "scaler.scale",
                format!(
                    "every scale must be in [{ZERO_SPREAD:e}, {MAX_SCALER_VALUE:e}], got {} for {}",
                    readable(*bad),
                    component(k)
                ),
            ));
        }
        Ok(schema)
    }

    /// Scaled ξ_t of one evidence row.
    pub fn transform(&self, evidence: &Evidence) -> Features {
        self.transform_features(&evidence.raw_features())
    }

    /// Scales raw ξ: NaN/±inf → 0, then (x − center)/scale clipped to ±20; ν unchanged; entries
    /// beyond the scaler's schema are 0.
    pub fn transform_features(&self, raw: &Features) -> Features {
        let mut out: Features = [0.0; FEATURE_CAPACITY];
        out[NU_INDEX] = raw[NU_INDEX];
        for (k, (center, scale)) in self.center.iter().zip(&self.scale).enumerate() {
            let index = feature_index(k);
            let x = if raw[index].is_finite() {
                raw[index]
            } else {
                0.0
            };
            out[index] = ((x - center) / scale).clamp(-CLIP, CLIP);
        }
        out
    }
}

/// The IQR, or the population std when the IQR is ~0, or 1 when that is ~0 too.
fn spread(values: &[f64], iqr: f64) -> f64 {
    if iqr.abs() >= ZERO_SPREAD {
        return iqr;
    }
    let n = values.len() as f64;
    let mean = values.iter().sum::<f64>() / n;
    let std = (values.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n).sqrt();
    if std >= ZERO_SPREAD { std } else { 1.0 }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn row(q: f64, eta_e: f64, valid: bool) -> Evidence {
        Evidence {
            trajectory: 0,
            trajectory_start: false,
            delta_t: 1.0,
            valid,
            sigma_per_step: false,
            residual: [0.0; 2],
            eta: [eta_e, 0.0],
            eta_dot: [0.0; 2],
            eta_ddot: [0.0; 2],
            energy: 0.0,
            q,
            accum: 0.0,
            accum_log: 0.0,
            drift: None,
            offset: None,
        }
    }

    #[test]
    fn fit_by_hand() {
        // q = 1, 2, 3, 4, 10: median 3, Q25 2, Q75 4 → scale 2.
        // η_E = 0, 0, 0, 0, 5: IQR 0 → population std = √(mean x² − mean²) = √(5 − 1) = 2.
        // η_N and the rest are all 0 → std 0 → scale 1.
        let rows = [
            row(1.0, 0.0, true),
            row(2.0, 0.0, true),
            row(3.0, 0.0, false),
            row(4.0, 0.0, true),
            row(10.0, 5.0, true),
        ];
        let scaler = RobustScaler::fit(&rows, FeatureSchema::Paper).expect("rows");
        assert_eq!(scaler.center[6], 3.0);
        assert_eq!(scaler.scale[6], 2.0);
        assert_eq!(scaler.center[0], 0.0);
        assert!((scaler.scale[0] - 2.0).abs() < 1e-15);
        assert_eq!(scaler.scale[1], 1.0);
        assert_eq!(scaler.center[7], 0.0);

        let z = scaler.transform(&row(8.0, 100.0, true));
        assert_eq!(z[6], 2.5); // (8 − 3)/2
        assert_eq!(z[0], 20.0); // 100/2 = 50, clipped
        assert_eq!(z[8], 1.0); // ν unscaled
        let z = scaler.transform(&row(f64::NAN, f64::NEG_INFINITY, false));
        assert_eq!(z[6], -1.5); // NaN → 0 → (0 − 3)/2
        assert_eq!(z[0], 0.0); // −inf → 0
        assert_eq!(z[8], 0.0);
    }

    #[test]
    fn empty_fit_is_an_error() {
        assert!(matches!(
            RobustScaler::fit(&[], FeatureSchema::Paper),
            Err(EvidenceError::NoRows)
        ));
    }
}
