//! Fitting the evidence parameters on labelled training tracks (SPEC §4): Σ̂ and
//! μ_e from normal rows, and evidence v2's drift parameters from their settled drift rates. Both run
//! the streaming builder over the tracks. [`fit_evidence`] is a model's whole evidence fit (Σ̂, μ_e,
//! the channels' parameters and the scaler): training and the comparators share it.
//!
//! Owns the fits from tracks and residuals. Must not build evidence (that is `builder.rs`), define the
//! drift channels' own normalisation fit (that is `drift.rs`) or scale features (that is `scaler.rs`).

use serde::{Deserialize, Serialize};

use super::builder::build_track;
use super::calibration::{CalibrationPrior, CalibrationTrust, FIT_TRUST};
use super::drift::DriftParams;
use super::drift_fit::{SettledRates, covariances_from_rates, thresholds_from_rates};
use super::linalg::{Mat2, inverse_sqrt_symmetric, mul_vec};
use super::offset::{
    ANCHOR_COUNT, CHI2_2_AT_FIT_QUANTILE, FIT_QUANTILE, FOLLOW_S, OffsetParams, OffsetPoint,
    offset_params_from_points,
};
use super::params::{EvidenceParams, SIGMA_EPSILON};
use super::scaler::RobustScaler;
use super::stats::{covariance, median, quantile_sorted};
use super::{EvidenceError, FeatureSchema};
use crate::geo::Projection;
use crate::sample::Track;

/// σ̂ = this × MAD for a normal distribution.
const MAD_TO_SIGMA: f64 = 1.4826;
/// Fewest normal ν = 1 rows accepted for Σ̂ and μ_e. A 2×2 covariance and a median from fewer rows are
/// too noisy to normalise residuals with; the reference demands 100, we allow smaller test sets
/// (e.g. a few injected-attack trajectories) but not tiny ones.
pub const MIN_NORMAL_ROWS: usize = 30;

/// Σ̂ and μ_e fitted on normal, valid training rows.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct NormalStats {
    /// ddof-1 covariance of r (m²), without ε.
    pub sigma_hat: Mat2,
    /// Median of rᵀ(Σ̂ + εI)^{-1} r on the same rows.
    pub mu_e: f64,
    /// How many rows (label 0, ν = 1) the statistics come from.
    pub rows: usize,
}

impl NormalStats {
    /// Validated evidence parameters with these statistics and the default κ, ρ.
    pub fn params(&self, projection: Projection) -> Result<EvidenceParams, EvidenceError> {
        EvidenceParams::new(self.sigma_hat, self.mu_e, projection)
    }
}

/// Fits Σ̂ and μ_e on the label-0, ν = 1 rows of `tracks`. Unlabelled, attack and warm-up rows are
/// ignored.
pub fn fit_normal_stats(
    tracks: &[Track],
    projection: Projection,
) -> Result<NormalStats, EvidenceError> {
    stats_from_residuals(&normal_residuals(tracks, projection))
}

/// r_t of the label-0, ν = 1 rows of `tracks`.
pub fn normal_residuals(tracks: &[Track], projection: Projection) -> Vec<[f64; 2]> {
    // ν and r do not depend on Σ̂ or μ_e, so any placeholder statistics give the same residuals.
    let placeholder = EvidenceParams::unnormalised(projection);
    let mut residuals = Vec::new();
    for track in tracks {
        let evidence = build_track(&placeholder, &track.records);
        for (record, e) in track.records.iter().zip(&evidence) {
            if record.label == Some(false) && e.valid && !record.warmup {
                residuals.push(e.residual);
            }
        }
    }
    residuals
}

/// Evidence v2's drift parameters from the label-0 rows of `tracks` (`params` gives the projection):
/// the clip from the robust σ of r, then the drift-rate covariances (calibrated: on rows after the
/// clock's warm-up, where the calibration has converged on a training drive) and per-scale
/// thresholds on settled rows under `trust` (a row of an attacked track counts once it is normal
/// and valid; its EWMAs may still carry an earlier attack, which only widens the normalisation).
/// The stale-fix channel counts only while the vehicle moves.
pub fn fit_drift_params(
    tracks: &[Track],
    projection: Projection,
    trust: CalibrationTrust,
    calibration_prior: Option<CalibrationPrior>,
) -> Result<DriftParams, EvidenceError> {
    let residual_sigma = robust_residual_sigma(&normal_residuals(tracks, projection))?;
    let unwhitened = DriftParams {
        calibration_prior,
        ..DriftParams::unwhitened(residual_sigma)
    };
    let whitened = DriftParams {
        trust,
        stale_fix_while_moving: true,
        calibration_prior,
        ..covariances_from_rates(
            residual_sigma,
            &settled_rates(tracks, projection, unwhitened),
        )?
    };
    thresholds_from_rates(whitened, &settled_rates(tracks, projection, whitened))
}

/// The drift channels of label-0 valid rows under `drift`, one row per second of driving (so a
/// 10 Hz vehicle weighs as much as a 1 Hz one), with their depth into the trajectory.
fn settled_rates(
    tracks: &[Track],
    projection: Projection,
    drift: DriftParams,
) -> Vec<SettledRates> {
    let params = EvidenceParams {
        drift: Some(drift),
        ..EvidenceParams::unnormalised(projection)
    };
    let mut rows = Vec::new();
    for track in tracks {
        let mut elapsed_s = 0.0;
        for (record, e) in track
            .records
            .iter()
            .zip(build_track(&params, &track.records))
        {
            if e.trajectory_start {
                elapsed_s = 0.0;
            }
            if e.valid {
                let new_second = (elapsed_s + e.delta_t).floor() > elapsed_s.floor();
                elapsed_s += e.delta_t;
                if let (true, Some(false), Some(drift), false) =
                    (new_second, record.label, e.drift, record.warmup)
                {
                    rows.push(SettledRates { elapsed_s, drift });
                }
            }
        }
    }
    rows
}

/// Evidence v3's anchor parameters from the label-0 rows of `tracks`, with `drift` (the fitted drift
/// parameters) for the onboard calibration: the anchors run without ever stopping to follow, and
/// each anchor's offsets, one row per second of driving, give its noise and growth
/// ([`offset_params_from_points`]); one row's residual, matched at the same quantile, gives the
/// step test's noise. Only normal rows before a track's first attacked row count: an attack leaves
/// an offset in an anchor that follows it. Under information-driven trust only rows whose
/// calibration is known count, unless too few are: then every normal row does.
pub fn fit_offset_params(
    tracks: &[Track],
    projection: Projection,
    drift: DriftParams,
) -> Result<OffsetParams, EvidenceError> {
    let params = EvidenceParams {
        drift: Some(drift),
        offset: Some(OffsetParams::unnormalised()),
        ..EvidenceParams::unnormalised(projection)
    };
    let known = drift.trust == CalibrationTrust::Information;
    let step_noise_m2 = step_noise_m2(tracks, projection)?;
    match offset_params_from_points(&offset_points(tracks, &params, known), step_noise_m2) {
        // A fleet whose vehicles never teach their calibration within a drive (slow rovers, straight
        // roads) still gets anchors: fitted on every normal row, the growth already holds the
        // calibration's error, which the test then adds again, so its gates are wider, never
        // narrower.
        Err(EvidenceError::TooFewOffsetRows { .. }) if known => {
            offset_params_from_points(&offset_points(tracks, &params, false), step_noise_m2)
        }
        fitted => fitted,
    }
}

/// The settled anchors' offsets of the normal rows of `tracks`, one per second; with
/// `known_calibration`, only rows whose calibration is known (information-driven trust).
fn offset_points(
    tracks: &[Track],
    params: &EvidenceParams,
    known_calibration: bool,
) -> [Vec<OffsetPoint>; ANCHOR_COUNT] {
    let mut points: [Vec<OffsetPoint>; ANCHOR_COUNT] = Default::default();
    for track in tracks {
        let mut clock_s = 0.0;
        let mut last_time: Option<f64> = None;
        let mut attacked = false;
        for (record, e) in track
            .records
            .iter()
            .zip(build_track(params, &track.records))
        {
            let time = record.sample.timestamp_s;
            let delta = last_time.map_or(0.0, |last| (time - last).clamp(0.0, 60.0));
            last_time = Some(time);
            attacked |= record.label == Some(true);
            let Some(offset) = e.offset else { continue };
            // Under information-driven trust, offsets enter the fit once the calibration is
            // known: the test adds what is still unknown about it on top of this growth.
            let unknown = e.drift.is_some_and(|d| d.warm_up < FIT_TRUST);
            if known_calibration && unknown {
                continue;
            }
            let new_second = (clock_s + delta).floor() > clock_s;
            clock_s += delta;
            if !new_second || attacked || record.label != Some(false) || record.warmup {
                continue;
            }
            for (k, anchor_points) in points.iter_mut().enumerate() {
                // Settled: the anchor has run for three follow times, so that the GNSS error has
                // had time to move it as far as it ever does.
                if offset.anchor_age_s >= SETTLED_FOLLOWS * FOLLOW_S[k] {
                    anchor_points.push(OffsetPoint {
                        carried_m: offset.carried_m[k],
                        raw_carried_m: offset.raw_carried_m[k],
                        offset_m: offset.offset_norm_m[k],
                    });
                }
            }
        }
    }
    points
}

/// The GNSS step noise of the anchors: the fit quantile of the normal rows' squared residuals.
fn step_noise_m2(tracks: &[Track], projection: Projection) -> Result<f64, EvidenceError> {
    let mut residuals: Vec<f64> = normal_residuals(tracks, projection)
        .iter()
        .map(|r| r[0] * r[0] + r[1] * r[1])
        .collect();
    residuals.sort_by(f64::total_cmp);
    Ok(
        quantile_sorted(&residuals, FIT_QUANTILE).ok_or(EvidenceError::NoRows)?
            / CHI2_2_AT_FIT_QUANTILE,
    )
}

/// An anchor's offsets enter the fit this many follow times after it was placed.
const SETTLED_FOLLOWS: f64 = 3.0;

/// Σ̂ (ddof 1) and μ_e (numpy median energy) from residuals; at least [`MIN_NORMAL_ROWS`] of them.
pub fn stats_from_residuals(residuals: &[[f64; 2]]) -> Result<NormalStats, EvidenceError> {
    if residuals.len() < MIN_NORMAL_ROWS {
        return Err(EvidenceError::TooFewNormalRows {
            rows: residuals.len(),
            minimum: MIN_NORMAL_ROWS,
        });
    }
    let sigma_hat = covariance(residuals);
    let mut regularised = sigma_hat;
    regularised[0][0] += SIGMA_EPSILON;
    regularised[1][1] += SIGMA_EPSILON;
    let inv_sqrt = inverse_sqrt_symmetric(&regularised);
    let mut energies: Vec<f64> = residuals
        .iter()
        .map(|r| {
            let eta = mul_vec(&inv_sqrt, *r);
            eta[0] * eta[0] + eta[1] * eta[1]
        })
        .collect();
    let mu_e = median(&mut energies).ok_or(EvidenceError::NoRows)?;
    Ok(NormalStats {
        sigma_hat,
        mu_e,
        rows: residuals.len(),
    })
}

/// Evidence settings chosen for a model: statistics from training normal rows plus κ, ρ.
#[derive(Clone, Debug, PartialEq)]
pub struct EvidenceFit {
    pub params: EvidenceParams,
    pub scaler: RobustScaler,
    /// Normal ν = 1 training rows behind Σ̂ and μ_e.
    pub normal_rows: usize,
}

/// Why the evidence could not be fitted on training tracks.
#[derive(Debug, thiserror::Error)]
pub enum EvidenceFitError {
    #[error("fitting the evidence statistics: {0}")]
    Evidence(#[from] EvidenceError),
    #[error("no training rows")]
    NoTrainingRows,
}

/// Fits Σ̂, μ_e (and, for the v2 schema, the drift parameters) on the training tracks' normal rows
/// and the robust scaler on all their rows.
pub fn fit_evidence(
    train: &[Track],
    projection: Projection,
    kappa: f64,
    rho: f64,
    schema: FeatureSchema,
) -> Result<EvidenceFit, EvidenceFitError> {
    fit_evidence_with(
        train,
        projection,
        kappa,
        rho,
        schema,
        EvidenceOptions::default(),
    )
}

/// The choices a retrained ablation makes in the evidence fit.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EvidenceOptions {
    /// The per-vehicle levels of the drift and offset channels (off: the ablation
    /// [`Ablation::no_vehicle_levels`](crate::model::Ablation)).
    pub vehicle_levels: bool,
    /// How far the onboard calibration is trusted (timers: the ablation
    /// [`Ablation::timer_trust`](crate::model::Ablation)).
    pub trust: CalibrationTrust,
    /// The fleet's prior on the onboard calibration (`None`: the default prior).
    pub calibration_prior: Option<CalibrationPrior>,
    /// The anchors re-base their dead reckoning when the calibration in use changes
    /// ([`OffsetParams::rebase_on_calibration`]), in the scaler's fit and in the fitted evidence;
    /// their noise and growth are fitted without it either way.
    pub rebase_anchors: bool,
}

impl Default for EvidenceOptions {
    fn default() -> Self {
        Self {
            vehicle_levels: true,
            trust: CalibrationTrust::Information,
            calibration_prior: None,
            rebase_anchors: false,
        }
    }
}

/// [`fit_evidence`] with `options`: the scaler is fitted on the channels as that model will see
/// them.
pub fn fit_evidence_with(
    train: &[Track],
    projection: Projection,
    kappa: f64,
    rho: f64,
    schema: FeatureSchema,
    options: EvidenceOptions,
) -> Result<EvidenceFit, EvidenceFitError> {
    let vehicle_levels = options.vehicle_levels;
    let stats = fit_normal_stats(train, projection)?;
    let drift = schema
        .has_drift()
        .then(|| fit_drift_params(train, projection, options.trust, options.calibration_prior))
        .transpose()?;
    let offset = match drift {
        Some(drift) if schema.has_offset() => Some(OffsetParams {
            rebase_on_calibration: options.rebase_anchors,
            ..fit_offset_params(train, projection, drift)?
        }),
        _ => None,
    };
    let drift = drift.map(|d| DriftParams {
        vehicle_levels: d.vehicle_levels && vehicle_levels,
        ..d
    });
    let offset = offset.map(|o| OffsetParams {
        vehicle_levels: o.vehicle_levels && vehicle_levels,
        ..o
    });
    let params = EvidenceParams {
        drift,
        offset,
        ..EvidenceParams::with_accumulator(stats.sigma_hat, stats.mu_e, kappa, rho, projection)?
    };
    params.validate()?;
    let evidence: Vec<_> = train
        .iter()
        .flat_map(|t| build_track(&params, &t.records))
        .collect();
    if evidence.is_empty() {
        return Err(EvidenceFitError::NoTrainingRows);
    }
    Ok(EvidenceFit {
        scaler: RobustScaler::fit(&evidence, schema)?,
        params,
        normal_rows: stats.rows,
    })
}

/// The robust residual σ̂_r (m): RMS over the axes of 1.4826·MAD of r on normal valid rows.
pub fn robust_residual_sigma(residuals: &[[f64; 2]]) -> Result<f64, EvidenceError> {
    let mut axis_variance = 0.0;
    for axis in 0..2 {
        let mut values: Vec<f64> = residuals.iter().map(|r| r[axis]).collect();
        let center = median(&mut values).ok_or(EvidenceError::NoRows)?;
        let mut deviations: Vec<f64> = values.iter().map(|x| (x - center).abs()).collect();
        let mad = median(&mut deviations).ok_or(EvidenceError::NoRows)?;
        axis_variance += 0.5 * (MAD_TO_SIGMA * mad).powi(2);
    }
    let sigma = axis_variance.sqrt();
    if sigma.is_finite() && sigma > 0.0 {
        Ok(sigma)
    } else {
        Err(EvidenceError::InvalidParams {
            field: "drift.residual_sigma_m",
            reason: format!(
                "the normal residuals have no spread (robust sigma {sigma}); cannot set the clip"
            ),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sample::{Record, Sample};

    /// 32 residuals: (±1, 0) × 8, (0, ±2) × 8. Mean 0; Σ̂ = diag(16/31, 64/31).
    fn cross_residuals() -> Vec<[f64; 2]> {
        let mut rows = Vec::new();
        for _ in 0..8 {
            rows.extend([[1.0, 0.0], [-1.0, 0.0], [0.0, 2.0], [0.0, -2.0]]);
        }
        rows
    }

    #[test]
    fn stats_from_residuals_by_hand() {
        let stats = stats_from_residuals(&cross_residuals()).expect("32 rows");
        assert_eq!(stats.rows, 32);
        assert!((stats.sigma_hat[0][0] - 16.0 / 31.0).abs() < 1e-14);
        assert!((stats.sigma_hat[1][1] - 64.0 / 31.0).abs() < 1e-14);
        assert!(stats.sigma_hat[0][1].abs() < 1e-15);
        // Every energy is 1/(16/31 + ε) or 4/(64/31 + ε); both ≈ 31/16 = 1.9375.
        let e1: f64 = 1.0 / (16.0 / 31.0 + 1e-6);
        let e2: f64 = 4.0 / (64.0 / 31.0 + 1e-6);
        assert!((stats.mu_e - 0.5 * (e1.min(e2) + e1.max(e2))).abs() < 1e-12);
        assert!((stats.mu_e - 1.9375).abs() < 1e-5);
    }

    #[test]
    fn too_few_rows_is_an_error() {
        let err = stats_from_residuals(&cross_residuals()[..29]).expect_err("29 rows");
        assert!(err.to_string().contains("29"), "{err}");
    }

    #[test]
    fn fit_normal_stats_uses_only_normal_valid_rows() {
        // A vehicle heading north at 1 m/s whose GNSS reports 1 m/s north plus a residual pattern;
        // rows labelled 1 carry huge residuals that must be ignored, as must the invalid first row.
        let metres_per_degree = crate::geo::EQUIRECTANGULAR_RADIUS_M.to_radians();
        let pattern = [[1.0, 0.0], [-1.0, 0.0], [0.0, 2.0], [0.0, -2.0]];
        let mut records = Vec::new();
        let (mut east, mut north) = (0.0, 0.0);
        for i in 0..80u32 {
            let attack = i >= 60;
            let r = if attack {
                [500.0, 0.0]
            } else {
                pattern[(i as usize) % 4]
            };
            if i > 0 {
                east += r[0];
                north += 1.0 + r[1];
            }
            let lat = north / metres_per_degree;
            let lon = east / metres_per_degree; // cos(0°) = 1 at the equator
            records.push(Record {
                sample: Sample::new(f64::from(i), lat, lon, 1.0, 0.0),
                label: Some(attack),
                comparator_alarm: None,
                line: u64::from(i) + 2,
                trajectory_break: false,
                warmup: false,
            });
        }
        let track = Track {
            vehicle_id: "v".into(),
            records,
        };
        let stats = fit_normal_stats(&[track], Projection::Equirectangular).expect("59 rows");
        // Rows 1..=59: pattern index 1,2,3,0,… → 15 × (−1,0), 15 × (0,2), 15 × (0,−2), 14 × (1,0).
        assert_eq!(stats.rows, 59);
        let n: f64 = 59.0;
        let mean_e = (14.0 - 15.0) / n;
        let mean_n = (30.0 - 30.0) / n;
        let var_e = (14.0 * (1.0 - mean_e).powi(2)
            + 15.0 * (-1.0 - mean_e).powi(2)
            + 30.0 * mean_e.powi(2))
            / (n - 1.0);
        let var_n = (30.0 * 4.0 + 29.0 * mean_n.powi(2)) / (n - 1.0);
        assert!((stats.sigma_hat[0][0] - var_e).abs() < 1e-9, "{stats:?}");
        assert!((stats.sigma_hat[1][1] - var_n).abs() < 1e-9, "{stats:?}");
        assert!(stats.sigma_hat[0][1].abs() < 1e-9, "{stats:?}");
    }
}
