//! The drift channels' own normalisation fit (`docs/detector.md` §4.1): from the drift rates of
//! settled normal rows, each scale's covariance (first pass) and its χ² threshold (second pass).
//!
//! Owns the two passes and what a settled row is. Must not run the streaming tracker (that is
//! `drift.rs`) or read tracks (the evidence fit in `fit.rs` computes the rows).

use super::EvidenceError;
use super::calibration::CalibrationTrust;
use super::drift::{
    DRIFT_SCALES_S, DriftEvidence, DriftParams, MIN_SETTLED_ROWS, SCALE_COUNT, SETTLE_SCALES,
    THRESHOLD_QUANTILE, norm_squared,
};
use super::stats::{covariance, quantile_sorted};

/// One normal row's drift channels as the fit sees them (computed with [`DriftParams::unwhitened`], so
/// the z's are the raw drift rates).
#[derive(Clone, Copy, Debug)]
pub struct SettledRates {
    /// Valid seconds since the trajectory started.
    pub elapsed_s: f64,
    pub drift: DriftEvidence,
}

/// Scale k's z-vectors of the rows at least 2τ_k into their trajectory (a zero-started EWMA then has
/// 98 % of its stationary variance); for the calibrated channel only warm rows, unless the
/// calibration is trusted by its information (`trust`), when the channel is always on.
fn settled_z(
    rows: &[SettledRates],
    k: usize,
    calibrated: bool,
    trust: CalibrationTrust,
) -> Vec<[f64; 2]> {
    let every_row = trust == CalibrationTrust::Information;
    rows.iter()
        .filter(|r| r.elapsed_s >= SETTLE_SCALES * DRIFT_SCALES_S[k])
        .filter(|r| !calibrated || every_row || r.drift.is_warm())
        .map(|r| {
            if calibrated {
                r.drift.calibrated_z[k]
            } else {
                r.drift.raw_z[k]
            }
        })
        .collect()
}

fn too_few_settled(k: usize, calibrated: bool, rows: usize) -> EvidenceError {
    EvidenceError::TooFewSettledRows {
        scale_s: DRIFT_SCALES_S[k],
        settle_s: SETTLE_SCALES * DRIFT_SCALES_S[k],
        warm: if calibrated {
            " with a warm calibration"
        } else {
            ""
        },
        rows,
        minimum: MIN_SETTLED_ROWS,
    }
}

/// First pass of the fit: covariances from rows computed with [`DriftParams::unwhitened`] (their z's
/// are the raw drift rates). Returns parameters that whiten with them and normalise by vehicle
/// levels, with unit thresholds: the second pass ([`thresholds_from_rates`]) sets those.
pub fn covariances_from_rates(
    residual_sigma_m: f64,
    rows: &[SettledRates],
) -> Result<DriftParams, EvidenceError> {
    let mut params = DriftParams::unwhitened(residual_sigma_m);
    params.vehicle_levels = true;
    for k in 0..SCALE_COUNT {
        for calibrated in [false, true] {
            let rates = settled_z(rows, k, calibrated, CalibrationTrust::Timers);
            if rates.len() < MIN_SETTLED_ROWS {
                return Err(too_few_settled(k, calibrated, rates.len()));
            }
            let target = if calibrated {
                &mut params.calibrated_covariance[k]
            } else {
                &mut params.raw_covariance[k]
            };
            *target = covariance(&rates);
        }
    }
    params.validate()?;
    Ok(params)
}

/// Second pass: each scale's threshold h_k is the 99.9 % quantile of its (whitened, level-normalised)
/// χ² on settled normal rows computed with `params` (unit thresholds).
pub fn thresholds_from_rates(
    mut params: DriftParams,
    rows: &[SettledRates],
) -> Result<DriftParams, EvidenceError> {
    for k in 0..SCALE_COUNT {
        for calibrated in [false, true] {
            let mut chi2: Vec<f64> = settled_z(rows, k, calibrated, params.trust)
                .into_iter()
                .map(norm_squared)
                .collect();
            if chi2.len() < MIN_SETTLED_ROWS {
                return Err(too_few_settled(k, calibrated, chi2.len()));
            }
            chi2.sort_unstable_by(f64::total_cmp);
            let threshold = quantile_sorted(&chi2, THRESHOLD_QUANTILE)
                .filter(|h| h.is_finite() && *h > 0.0)
                .unwrap_or(1.0);
            if calibrated {
                params.calibrated_threshold[k] = threshold;
            } else {
                params.raw_threshold[k] = threshold;
            }
        }
    }
    params.validate()?;
    Ok(params)
}
