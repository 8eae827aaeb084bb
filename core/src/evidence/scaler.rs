//! The label-free robust scaler of ξ's first 8 components (SPEC §4, REFERENCE-NOTES §2.9).
//!
//! Owns the robust feature scaler. Must not build evidence.

use serde::{Deserialize, Serialize};

use super::builder::Evidence;
use super::stats::quantile_sorted;
use super::{EvidenceError, FEATURE_COUNT, Features};

/// Number of scaled components (all of ξ except ν).
pub const SCALED_COUNT: usize = FEATURE_COUNT - 1;
/// Scaled values are clipped to ±this.
pub const CLIP: f64 = 20.0;
/// An IQR (or std) below this is treated as zero spread.
const ZERO_SPREAD: f64 = 1e-8;

/// Per-component median/IQR scaling of ξ's first 8 components; ν passes through.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RobustScaler {
    /// Medians.
    pub center: [f64; SCALED_COUNT],
    /// IQR, else population std, else 1 (never zero).
    pub scale: [f64; SCALED_COUNT],
}

impl RobustScaler {
    /// Fits on ALL given rows (valid or not, any label), with pandas type-7 quantiles. Non-finite
    /// values are skipped as pandas skips NaN; a component with no finite value gets center 0, scale 1.
    pub fn fit(rows: &[Evidence]) -> Result<Self, EvidenceError> {
        if rows.is_empty() {
            return Err(EvidenceError::NoRows);
        }
        let mut center = [0.0; SCALED_COUNT];
        let mut scale = [1.0; SCALED_COUNT];
        let mut column = Vec::with_capacity(rows.len());
        for k in 0..SCALED_COUNT {
            column.clear();
            column.extend(
                rows.iter()
                    .map(|e| e.raw_features()[k])
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

    /// Scaled ξ_t of one evidence row.
    pub fn transform(&self, evidence: &Evidence) -> Features {
        self.transform_features(&evidence.raw_features())
    }

    /// Scales raw ξ: NaN/±inf → 0, then (x − center)/scale clipped to ±20; ν unchanged.
    pub fn transform_features(&self, raw: &Features) -> Features {
        let mut out = *raw;
        for k in 0..SCALED_COUNT {
            let x = if raw[k].is_finite() { raw[k] } else { 0.0 };
            out[k] = ((x - self.center[k]) / self.scale[k]).clamp(-CLIP, CLIP);
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
        let scaler = RobustScaler::fit(&rows).expect("rows");
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
        assert!(matches!(RobustScaler::fit(&[]), Err(EvidenceError::NoRows)));
    }
}
