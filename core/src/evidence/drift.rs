//! Evidence v2 (`docs/detector.md` §4.1): directional drift-rate channels on a clipped
//! residual that is cleaned, online, of the vehicle's own onboard-sensor errors.
//!
//! Every energy in the paper's ξ_t is blind to direction, and the liquid cell forgets within ~10 s, so
//! a spoofer who drags the fix at 0.5 m/s stays below them. The signed residual, averaged over 10–120 s,
//! grows as the drift velocity instead. Onboard errors (speed scale, heading bias, GNSS/onboard timing)
//! also look like drift, but they live in the vehicle's body frame and rotate with it; a spoofed drift
//! stays fixed in east/north. A slow, *delayed* least-squares calibration learns them from rows at
//! least two minutes old, so a drift that has just started is not absorbed.
//!
//! Two integrity channels ride along: how long the fix has repeated exactly (a frozen feed the
//! residual cannot show at standstill) and the residual's log size (a kilometre jump is no multipath).
//!
//! Owns the per-vehicle drift tracker (clip → calibration → EWMA drift rates → whitened χ²; the
//! integrity channels), its parameters and their fit on normal rows. Must not build the paper's channels (that is `builder.rs`)
//! or scale features.

use serde::{Deserialize, Serialize};

use super::EvidenceError;
use super::calibration::{
    CALIBRATION_BLOCK_S, CALIBRATION_DELAY_S, CalibrationPrior, CalibrationTrust, Learning,
    WARM_UP_S, add, apply, calibration_covariance, in_use_error, information_trust,
    least_squares_step, regressors, residual_is_consistent,
};
use super::linalg::{
    IDENTITY, Mat2, add_diagonal, inverse_sqrt_positive_definite, inverse_sqrt_symmetric,
    is_symmetric_positive_definite, mul_vec,
};
use crate::sample::readable;

/// Number of drift-rate time scales.
pub const SCALE_COUNT: usize = 4;
/// EWMA time constants τ_k of the drift-rate channels (s): 10 s catches fast ramps, 120 s slow ones.
pub const DRIFT_SCALES_S: [f64; SCALE_COUNT] = [10.0, 30.0, 60.0, 120.0];
/// The scale whose drift rate is reported ([`DriftEvidence::rate_mps`]): 30 s.
const REPORTED_SCALE: usize = 1;
/// The clip radius in robust residual sigmas: c = 4 σ̂_r.
pub const CLIP_SIGMAS: f64 = 4.0;
/// Memory of a vehicle's own χ² level (s): vehicles differ ten-fold in how noisy their drift rates
/// are (GNSS bias dynamics, heading noise at speed), so each χ² is divided by the vehicle's level,
/// learned like the calibration from data at least `CALIBRATION_DELAY_S` old.
pub const LEVEL_MEMORY_S: f64 = 300.0;
/// Weight of the population prior (level 1) in seconds of data.
const LEVEL_PRIOR_S: f64 = 120.0;
/// Levels are kept within [1, 16] of the population's: a noisy vehicle is quieted, a very noisy one
/// not made blind, and a quiet one is never made more sensitive than the population. Its level would
/// settle below 1 only after half an hour, later than any training drive lasts, and a model that never
/// saw those inputs alarms on them.
const LEVEL_RANGE: (f64, f64) = (1.0, 16.0);
/// Snapshot spacing of the calibration (s of valid data).
const SNAPSHOT_PERIOD_S: f64 = 30.0;
/// Snapshots kept: enough to always hold one that is `CALIBRATION_DELAY_S` old.
const SNAPSHOTS: usize = (CALIBRATION_DELAY_S / SNAPSHOT_PERIOD_S) as usize + 2;
/// Quantile of χ² on normal rows that normalises each scale in the drift statistic.
pub(super) const THRESHOLD_QUANTILE: f64 = 0.999;
/// ε added to the drift-rate covariances before whitening (m²/s²).
const RATE_EPSILON: f64 = 1e-9;
/// A row is settled for scale τ_k this many τ_k into its trajectory.
pub(super) const SETTLE_SCALES: f64 = 2.0;
/// The onboard speed (m/s) at and above which a vehicle moves, for the stale-fix channel: a
/// receiver's static hold pins the fix below walking pace.
pub const MOVING_MPS: f64 = 1.0;
/// Fewest settled normal rows per scale for a drift-rate covariance.
pub const MIN_SETTLED_ROWS: usize = 30;

/// Fitted on normal training rows; carried by the artifact inside the evidence parameters.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "UncheckedDriftParams")]
pub struct DriftParams {
    /// σ̂_r: root mean square of the per-axis robust σ (1.4826·MAD) of r on normal rows (m).
    pub residual_sigma_m: f64,
    /// Clip radius c = 4 σ̂_r (m).
    pub clip_m: f64,
    /// Covariance of the uncalibrated drift rate per scale on settled normal rows (m²/s²).
    pub raw_covariance: [Mat2; SCALE_COUNT],
    /// The same for the calibrated drift rate, on warm rows.
    pub calibrated_covariance: [Mat2; SCALE_COUNT],
    /// 99.9 % quantile of each scale's uncalibrated χ² on those rows.
    pub raw_threshold: [f64; SCALE_COUNT],
    /// The same for the calibrated χ².
    pub calibrated_threshold: [f64; SCALE_COUNT],
    /// Normalise each χ² by the vehicle's own level (see [`VehicleLevels`]); off only while fitting
    /// the covariances.
    #[serde(default)]
    pub vehicle_levels: bool,
    /// How far the onboard calibration is trusted: by the clock (artifacts written before
    /// information-driven trust), or by its own uncertainty.
    #[serde(default, skip_serializing_if = "CalibrationTrust::is_timers")]
    pub trust: CalibrationTrust,
    /// The stale-fix channel counts only the seconds the onboard motion says the vehicle moved: a
    /// receiver that holds its fix at standstill is where the vehicle is.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub stale_fix_while_moving: bool,
    /// The fleet's prior on the onboard calibration, fitted on its attack-free recordings; `None`:
    /// the default prior ([`CalibrationPrior::default`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub calibration_prior: Option<CalibrationPrior>,
}

/// The serialised form, checked by `TryFrom` (or by [`super::EvidenceParams::validate`] when it is
/// parsed as part of them).
#[derive(Deserialize)]
pub(crate) struct UncheckedDriftParams {
    residual_sigma_m: f64,
    clip_m: f64,
    raw_covariance: [Mat2; SCALE_COUNT],
    calibrated_covariance: [Mat2; SCALE_COUNT],
    raw_threshold: [f64; SCALE_COUNT],
    calibrated_threshold: [f64; SCALE_COUNT],
    #[serde(default)]
    vehicle_levels: bool,
    #[serde(default)]
    trust: CalibrationTrust,
    #[serde(default)]
    stale_fix_while_moving: bool,
    #[serde(default)]
    calibration_prior: Option<CalibrationPrior>,
}

impl TryFrom<UncheckedDriftParams> for DriftParams {
    type Error = EvidenceError;

    fn try_from(raw: UncheckedDriftParams) -> Result<Self, EvidenceError> {
        let params = DriftParams::unchecked(raw);
        params.validate()?;
        Ok(params)
    }
}

impl DriftParams {
    /// The parsed values as they are; the caller validates.
    pub(crate) fn unchecked(raw: UncheckedDriftParams) -> Self {
        Self {
            residual_sigma_m: raw.residual_sigma_m,
            clip_m: raw.clip_m,
            raw_covariance: raw.raw_covariance,
            calibrated_covariance: raw.calibrated_covariance,
            raw_threshold: raw.raw_threshold,
            calibrated_threshold: raw.calibrated_threshold,
            vehicle_levels: raw.vehicle_levels,
            trust: raw.trust,
            stale_fix_while_moving: raw.stale_fix_while_moving,
            calibration_prior: raw.calibration_prior,
        }
    }

    /// Parameters that whiten nothing (identity covariances, unit thresholds, the calibration
    /// trusted by the clock): the fit runs with them to read the raw drift rates.
    pub fn unwhitened(residual_sigma_m: f64) -> Self {
        Self {
            residual_sigma_m,
            clip_m: CLIP_SIGMAS * residual_sigma_m,
            raw_covariance: [IDENTITY; SCALE_COUNT],
            calibrated_covariance: [IDENTITY; SCALE_COUNT],
            raw_threshold: [1.0; SCALE_COUNT],
            calibrated_threshold: [1.0; SCALE_COUNT],
            vehicle_levels: false,
            trust: CalibrationTrust::Timers,
            stale_fix_while_moving: false,
            calibration_prior: None,
        }
    }

    /// Checks every value: σ̂_r and c positive and finite, covariances symmetric positive definite,
    /// thresholds positive and finite.
    pub fn validate(&self) -> Result<(), EvidenceError> {
        let invalid =
            |field: &'static str, reason: String| EvidenceError::InvalidParams { field, reason };
        let positive = |x: f64| x.is_finite() && x > 0.0;
        if !positive(self.residual_sigma_m) {
            return Err(invalid(
                "drift.residual_sigma_m",
                format!(
                    "must be positive and finite, got {}",
                    readable(self.residual_sigma_m)
                ),
            ));
        }
        if !positive(self.clip_m) {
            return Err(invalid(
                "drift.clip_m",
                format!("must be positive and finite, got {}", readable(self.clip_m)),
            ));
        }
        for (field, covariances) in [
            ("drift.raw_covariance", &self.raw_covariance),
            ("drift.calibrated_covariance", &self.calibrated_covariance),
        ] {
            if let Some(bad) = covariances
                .iter()
                .find(|c| !is_symmetric_positive_definite(c))
            {
                return Err(invalid(
                    field,
                    format!("every scale must be symmetric positive definite, got {bad:?}"),
                ));
            }
        }
        for (field, thresholds) in [
            ("drift.raw_threshold", &self.raw_threshold),
            ("drift.calibrated_threshold", &self.calibrated_threshold),
        ] {
            if let Some(bad) = thresholds.iter().find(|&&h| !positive(h)) {
                return Err(invalid(
                    field,
                    format!(
                        "every scale must be positive and finite, got {}",
                        readable(*bad)
                    ),
                ));
            }
        }
        if let Some((component, reason)) = self.calibration_prior.and_then(|p| p.problem()) {
            return Err(invalid(
                "drift.calibration_prior",
                format!("{component}: {reason}"),
            ));
        }
        Ok(())
    }
}

/// The drift channels of one sample.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct DriftEvidence {
    /// r^c = r·min(1, c/‖r‖) (m); NaN when ν = 0.
    pub clipped_residual: [f64; 2],
    /// r̃ = r^c + H θ: the clipped residual cleaned of the onboard errors in use (m); NaN when ν = 0.
    pub cleaned_residual: [f64; 2],
    /// The onboard errors in use (a snapshot ≥ 120 s old): speed scale error (fraction), heading bias
    /// (degrees), GNSS/onboard timing offset (s).
    pub calibration: [f64; 3],
    /// ω_t, how far the calibration in use is trusted, in [0, 1]. With timers, min(1, valid
    /// seconds seen / 240 s), the calibrated channels on at 1; with information-driven trust,
    /// 1 − its remaining error as a share of the prior's (the calibrated channels always on).
    pub warm_up: f64,
    /// Whitened EWMA of r^c/δ per scale (east, north); 0 at a trajectory start.
    pub raw_z: [[f64; 2]; SCALE_COUNT],
    /// Whitened EWMA of r̃/δ per scale; 0 until warm.
    pub calibrated_z: [[f64; 2]; SCALE_COUNT],
    /// The drift statistic: max over scales of χ²_k / h_k, calibrated when warm, else uncalibrated.
    pub statistic: f64,
    /// How long (s) the GNSS fix has repeated exactly in this trajectory; 0 when it last moved. A
    /// receiver's fix jitters at centimetres even at standstill, so a repeated fix is a frozen or
    /// stale feed (AV-GPS's spoofer freezes it while the vehicle stands).
    #[serde(default)]
    pub stale_fix_s: f64,
    /// ln(1 + ‖r‖/c): the residual's size in clip radii, log-compressed rather than clipped, so that
    /// a jump of kilometres (no receiver error is that large) stays apart from a multipath spike of
    /// metres; 0 when ν = 0.
    #[serde(default)]
    pub residual_log: f64,
    /// The drift rate GNSS shows against the onboard motion, east/north (m/s): the 30 s EWMA of
    /// r̃/δ once warm, else of r^c/δ; 0 at a trajectory start.
    #[serde(default)]
    pub rate_mps: [f64; 2],
}

impl DriftEvidence {
    /// The channels at the very start of a stream (nothing seen yet).
    pub const EMPTY: Self = Self {
        clipped_residual: [f64::NAN; 2],
        cleaned_residual: [f64::NAN; 2],
        calibration: [0.0; 3],
        warm_up: 0.0,
        raw_z: [[0.0; 2]; SCALE_COUNT],
        calibrated_z: [[0.0; 2]; SCALE_COUNT],
        statistic: 0.0,
        stale_fix_s: 0.0,
        residual_log: 0.0,
        rate_mps: [0.0; 2],
    };

    /// χ²_k = ‖z_k‖² of the uncalibrated channel per scale.
    pub fn raw_chi2(&self) -> [f64; SCALE_COUNT] {
        self.raw_z.map(norm_squared)
    }

    /// χ²_k of the calibrated channel per scale.
    pub fn calibrated_chi2(&self) -> [f64; SCALE_COUNT] {
        self.calibrated_z.map(norm_squared)
    }

    /// The calibrated channels are on.
    pub fn is_warm(&self) -> bool {
        self.warm_up >= 1.0
    }
}

/// z / √level, the level clamped to [`LEVEL_RANGE`].
fn scaled(z: [f64; 2], level: f64) -> [f64; 2] {
    let factor = 1.0 / level.clamp(LEVEL_RANGE.0, LEVEL_RANGE.1).sqrt();
    [z[0] * factor, z[1] * factor]
}

/// The onboard motion says the vehicle moves (at [`MOVING_MPS`] or faster).
fn moving(input: &DriftInput) -> bool {
    input.motion[0].hypot(input.motion[1]) / input.delta_t >= MOVING_MPS
}

pub(super) fn norm_squared(z: [f64; 2]) -> f64 {
    z[0] * z[0] + z[1] * z[1]
}

/// One row's inputs to the tracker, all east/north.
#[derive(Clone, Copy, Debug)]
pub struct DriftInput {
    /// r_t = Δp^g − Δp^u (m).
    pub residual: [f64; 2],
    /// Δp^u = ½(v_t + v_{t−1})δ_t (m).
    pub motion: [f64; 2],
    /// v_t − v_{t−1} (m/s).
    pub velocity_change: [f64; 2],
    /// δ_t (s), in (0, 5].
    pub delta_t: f64,
    /// The GNSS fix equals the previous one exactly.
    pub fix_repeated: bool,
    /// The row may teach the calibration and the levels. False while the offset evidence holds an
    /// anchor frozen: the rows of a possible attack must not be learned as the vehicle's own onboard
    /// errors, or the calibration carries the spoofer's drift into the drive after the attack.
    pub learn: bool,
}

/// A calibration snapshot: θ after `clock_s` seconds of valid data.
#[derive(Clone, Copy, Debug, Default, Serialize, Deserialize)]
struct Snapshot {
    clock_s: f64,
    theta: [f64; 3],
    levels: Levels,
}

/// A vehicle's χ² level per scale, uncalibrated and calibrated (1 = the training population's).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
struct Levels {
    raw: [f64; SCALE_COUNT],
    calibrated: [f64; SCALE_COUNT],
}

impl Default for Levels {
    fn default() -> Self {
        Self {
            raw: [1.0; SCALE_COUNT],
            calibrated: [1.0; SCALE_COUNT],
        }
    }
}

/// The per-vehicle drift state: calibration (θ, P, snapshots) that persists across trajectories of a
/// stream, and EWMAs that restart with every trajectory. `push` never allocates.
///
/// Serialised (inside a session snapshot) it holds only the vehicle's state; the constants come
/// from the parameters again ([`DriftTracker::restore`]).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct DriftTracker {
    #[serde(skip)]
    constants: TrackerConstants,
    /// The block being summed for the calibration: Σ r^c, Σ H and Σ δ.
    block_residual: [f64; 2],
    block_regressors: [[f64; 2]; 3],
    block_s: f64,
    /// θ = (ε, β [rad], τ_L [s]) estimated from every complete block so far.
    theta: [f64; 3],
    covariance: [[f64; 3]; 3],
    /// Valid seconds absorbed by the calibration.
    clock_s: f64,
    snapshots: [Snapshot; SNAPSHOTS],
    snapshot_count: usize,
    /// The calibration in use (the newest snapshot at least `CALIBRATION_DELAY_S` old).
    theta_in_use: [f64; 3],
    /// The vehicle's levels so far, and those in use (from the same snapshot as `theta_in_use`).
    levels: Levels,
    levels_in_use: Levels,
    /// Seconds of valid data behind `levels`, and in the current trajectory.
    level_clock_s: f64,
    trajectory_s: f64,
    raw_rate: [[f64; 2]; SCALE_COUNT],
    calibrated_rate: [[f64; 2]; SCALE_COUNT],
    /// e^{−δ/τ_k} for the last δ (1 Hz streams reuse it).
    decay_delta: f64,
    decay: [f64; SCALE_COUNT],
    last: DriftEvidence,
}

/// What a tracker derives from its [`DriftParams`] once; a tracker keeps only these, not the
/// parameters (a server holds one tracker per vehicle).
#[derive(Clone, Copy, Debug, Default)]
struct TrackerConstants {
    clip_m: f64,
    noise_variance: f64,
    raw_whitening: [Mat2; SCALE_COUNT],
    calibrated_whitening: [Mat2; SCALE_COUNT],
    /// Σ_k + εI of the calibrated rates (information-driven trust adds the calibration's share).
    calibrated_covariance: [Mat2; SCALE_COUNT],
    raw_threshold: [f64; SCALE_COUNT],
    calibrated_threshold: [f64; SCALE_COUNT],
    /// Whether χ² are divided by the vehicle's level.
    vehicle_levels: bool,
    trust: CalibrationTrust,
    stale_fix_while_moving: bool,
    prior: CalibrationPrior,
}

impl DriftTracker {
    /// A tracker at the start of a stream.
    pub fn new(params: &DriftParams) -> Self {
        Self::fresh(TrackerConstants {
            clip_m: params.clip_m,
            noise_variance: params.residual_sigma_m * params.residual_sigma_m,
            raw_whitening: params.raw_covariance.map(|c| whitening(&c)),
            calibrated_whitening: params.calibrated_covariance.map(|c| whitening(&c)),
            calibrated_covariance: params
                .calibrated_covariance
                .map(|c| add_diagonal(c, RATE_EPSILON)),
            raw_threshold: params.raw_threshold,
            calibrated_threshold: params.calibrated_threshold,
            vehicle_levels: params.vehicle_levels,
            trust: params.trust,
            stale_fix_while_moving: params.stale_fix_while_moving,
            prior: params.calibration_prior.unwrap_or_default(),
        })
    }

    /// `saved` (a deserialised tracker, without constants) with the constants of `fresh`, a new
    /// tracker of the parameters it continues under.
    pub fn restore(fresh: &DriftTracker, saved: DriftTracker) -> DriftTracker {
        DriftTracker {
            constants: fresh.constants,
            ..saved
        }
    }

    /// Forgets the stream (calibration included), as a new tracker of the same parameters.
    pub fn reset(&mut self) {
        *self = Self::fresh(self.constants);
    }

    fn fresh(constants: TrackerConstants) -> Self {
        Self {
            constants,
            block_residual: [0.0; 2],
            block_regressors: [[0.0; 2]; 3],
            block_s: 0.0,
            theta: constants.prior.mean,
            covariance: constants.prior.covariance(),
            clock_s: 0.0,
            snapshots: [Snapshot::default(); SNAPSHOTS],
            snapshot_count: 0,
            theta_in_use: constants.prior.mean,
            levels: Levels::default(),
            levels_in_use: Levels::default(),
            level_clock_s: 0.0,
            trajectory_s: 0.0,
            raw_rate: [[0.0; 2]; SCALE_COUNT],
            calibrated_rate: [[0.0; 2]; SCALE_COUNT],
            decay_delta: f64::NAN,
            decay: [0.0; SCALE_COUNT],
            last: DriftEvidence::EMPTY,
        }
    }

    /// A new trajectory: the drift rates restart from 0 (the residual's history is broken); the
    /// onboard errors are the vehicle's and are kept.
    pub fn start_trajectory(&mut self) {
        self.trajectory_s = 0.0;
        self.clear_block();
        self.raw_rate = [[0.0; 2]; SCALE_COUNT];
        self.calibrated_rate = [[0.0; 2]; SCALE_COUNT];
        self.last = DriftEvidence {
            clipped_residual: [f64::NAN; 2],
            cleaned_residual: [f64::NAN; 2],
            raw_z: [[0.0; 2]; SCALE_COUNT],
            calibrated_z: [[0.0; 2]; SCALE_COUNT],
            statistic: 0.0,
            stale_fix_s: 0.0,
            rate_mps: [0.0; 2],
            ..self.last
        };
    }

    /// The calibration in use for a step with onboard displacement `motion` and velocity change
    /// `velocity_change`: H θ (added to the raw residual it gives the calibrated one) and the
    /// mean squared error of speed scale and heading bias ([`in_use_error`]; 0 with timers).
    /// `None` while timers keep the calibration out of use.
    pub fn calibration_in_use(
        &self,
        motion: [f64; 2],
        velocity_change: [f64; 2],
    ) -> Option<([f64; 2], [f64; 3])> {
        let correction = apply(&regressors(motion, velocity_change), &self.theta_in_use);
        match self.constants.trust {
            CalibrationTrust::Timers => {
                (self.clock_s >= WARM_UP_S).then_some((correction, [0.0; 3]))
            }
            CalibrationTrust::Information => Some((correction, self.in_use_error())),
        }
    }

    /// θ in use.
    pub fn theta_in_use(&self) -> [f64; 3] {
        self.theta_in_use
    }

    /// The calibration is trusted from its own information, not by the clock.
    pub fn trusts_information(&self) -> bool {
        self.constants.trust == CalibrationTrust::Information
    }

    /// [`in_use_error`] of this vehicle's calibration now.
    fn in_use_error(&self) -> [f64; 3] {
        in_use_error(&self.covariance, &self.theta, &self.theta_in_use)
    }

    /// ω_t, whether the calibrated channels are on, and the calibration's error in use.
    fn trust_now(&self) -> (f64, bool, [f64; 3]) {
        match self.constants.trust {
            CalibrationTrust::Timers => {
                let warm_up = (self.clock_s / WARM_UP_S).min(1.0);
                (warm_up, warm_up >= 1.0, [0.0; 3])
            }
            CalibrationTrust::Information => {
                let error = self.in_use_error();
                (
                    information_trust(&error, &self.constants.prior),
                    true,
                    error,
                )
            }
        }
    }

    /// The channels of a row with ν = 0: everything held, residuals undefined.
    pub fn hold(&self) -> DriftEvidence {
        DriftEvidence {
            clipped_residual: [f64::NAN; 2],
            cleaned_residual: [f64::NAN; 2],
            residual_log: 0.0,
            ..self.last
        }
    }

    /// The channels of a valid row (ν = 1, finite inputs, 0 < δ ≤ 5 s).
    pub fn push(&mut self, input: &DriftInput) -> DriftEvidence {
        let regressors = regressors(input.motion, input.velocity_change);
        let input = &DriftInput {
            learn: input.learn && self.may_teach(input, &regressors),
            ..*input
        };
        let clipped = clip(input.residual, self.constants.clip_m);
        let cleaned = add(clipped, apply(&regressors, &self.theta_in_use));
        if input.learn {
            self.add_to_block(&regressors, clipped, input.delta_t);
        } else {
            // A block never mixes rows that may teach with rows that may not.
            self.clear_block();
        }
        self.update_rates(clipped, cleaned, input.delta_t);

        let (warm_up, calibrated_on, error) = self.trust_now();
        // Information-driven trust tests the calibrated rates against Σ_k plus what the
        // calibration's error makes of the vehicle's current velocity.
        let uncertainty = (self.constants.trust == CalibrationTrust::Information).then(|| {
            let velocity = [
                input.motion[0] / input.delta_t,
                input.motion[1] / input.delta_t,
            ];
            calibration_covariance(velocity, &error)
        });
        let population_raw: [[f64; 2]; SCALE_COUNT] =
            std::array::from_fn(|k| mul_vec(&self.constants.raw_whitening[k], self.raw_rate[k]));
        let population_calibrated: [[f64; 2]; SCALE_COUNT] =
            std::array::from_fn(|k| self.whitened_calibrated(k, 1.0, uncertainty.as_ref()));
        if self.constants.vehicle_levels {
            self.update_levels(
                &population_raw,
                &population_calibrated,
                calibrated_on,
                input,
            );
        }
        let used = self.levels_in_use;
        let raw_z = std::array::from_fn(|k| scaled(population_raw[k], used.raw[k]));
        let calibrated_z = if !calibrated_on {
            [[0.0; 2]; SCALE_COUNT]
        } else if let Some(uncertainty) = &uncertainty {
            std::array::from_fn(|k| {
                self.whitened_calibrated(k, used.calibrated[k], Some(uncertainty))
            })
        } else {
            std::array::from_fn(|k| scaled(population_calibrated[k], used.calibrated[k]))
        };
        let statistic = if calibrated_on {
            normalised_max(&calibrated_z, &self.constants.calibrated_threshold)
        } else {
            normalised_max(&raw_z, &self.constants.raw_threshold)
        };
        let [scale, heading, timing] = self.theta_in_use;
        self.last = DriftEvidence {
            clipped_residual: clipped,
            cleaned_residual: cleaned,
            calibration: [scale, heading.to_degrees(), timing],
            warm_up,
            raw_z,
            calibrated_z,
            statistic,
            stale_fix_s: self.stale_fix_s(input),
            residual_log: (input.residual[0].hypot(input.residual[1]) / self.constants.clip_m)
                .ln_1p(),
            rate_mps: if calibrated_on {
                self.calibrated_rate[REPORTED_SCALE]
            } else {
                self.raw_rate[REPORTED_SCALE]
            },
        };
        self.last
    }

    /// Scale k's calibrated drift rate whitened by the population's covariance; with
    /// `uncertainty` (information-driven trust), by `level`·Σ_k plus it, else by Σ_k alone (the
    /// caller divides by the level).
    fn whitened_calibrated(&self, k: usize, level: f64, uncertainty: Option<&Mat2>) -> [f64; 2] {
        let rate = self.calibrated_rate[k];
        match uncertainty {
            None => mul_vec(&self.constants.calibrated_whitening[k], rate),
            Some(c) => {
                let level = level.clamp(LEVEL_RANGE.0, LEVEL_RANGE.1);
                let sigma = &self.constants.calibrated_covariance[k];
                let total: Mat2 =
                    std::array::from_fn(|a| std::array::from_fn(|b| level * sigma[a][b] + c[a][b]));
                mul_vec(&inverse_sqrt_positive_definite(&total), rate)
            }
        }
    }

    /// How long the fix has repeated: 0 on a row whose fix moved; otherwise one more step, unless
    /// the stale-fix channel counts only while moving and the onboard motion says the vehicle
    /// stood (a receiver holding its fix at standstill is where the vehicle is).
    fn stale_fix_s(&self, input: &DriftInput) -> f64 {
        if !input.fix_repeated {
            return 0.0;
        }
        if self.constants.stale_fix_while_moving && !moving(input) {
            self.last.stale_fix_s
        } else {
            self.last.stale_fix_s + input.delta_t
        }
    }

    /// Running mean of χ²/2 per scale (E = 1 for a vehicle like the population), starting from the
    /// population's level with the weight of `LEVEL_PRIOR_S` seconds and turning into an EWMA with
    /// memory `LEVEL_MEMORY_S`. Only settled rows (≥ 2τ into the trajectory) that may teach count.
    fn update_levels(
        &mut self,
        raw: &[[f64; 2]; SCALE_COUNT],
        calibrated: &[[f64; 2]; SCALE_COUNT],
        warm: bool,
        input: &DriftInput,
    ) {
        let delta_t = input.delta_t;
        self.trajectory_s += delta_t;
        if !input.learn {
            return;
        }
        self.level_clock_s += delta_t;
        let weight = delta_t / (LEVEL_PRIOR_S + self.level_clock_s.min(LEVEL_MEMORY_S));
        for k in 0..SCALE_COUNT {
            if self.trajectory_s < SETTLE_SCALES * DRIFT_SCALES_S[k] {
                continue;
            }
            let level = &mut self.levels.raw[k];
            *level += weight * (0.5 * norm_squared(raw[k]) - *level);
            if warm {
                let level = &mut self.levels.calibrated[k];
                *level += weight * (0.5 * norm_squared(calibrated[k]) - *level);
            }
        }
    }

    /// Whether a row may teach the calibration and the levels: with timers every row; with
    /// information-driven trust not a repeated fix on a moving vehicle (it measures no motion), nor
    /// a residual no calibration within its uncertainty explains ([`residual_is_consistent`]).
    fn may_teach(&self, input: &DriftInput, h: &[[f64; 2]; 3]) -> bool {
        let (theta, p, noise) = (&self.theta, &self.covariance, self.constants.noise_variance);
        self.constants.trust == CalibrationTrust::Timers
            || (!(input.fix_repeated && moving(input))
                && residual_is_consistent(theta, p, h, input.residual, noise))
    }

    /// Empties the block being summed.
    fn clear_block(&mut self) {
        self.block_residual = [0.0; 2];
        self.block_regressors = [[0.0; 2]; 3];
        self.block_s = 0.0;
    }

    /// Sums the row into the current block; a complete block updates the calibration.
    fn add_to_block(&mut self, h: &[[f64; 2]; 3], clipped: [f64; 2], delta_t: f64) {
        for axis in 0..2 {
            self.block_residual[axis] += clipped[axis];
            for (column, regressor) in self.block_regressors.iter_mut().zip(h) {
                column[axis] += regressor[axis];
            }
        }
        self.block_s += delta_t;
        if self.block_s >= CALIBRATION_BLOCK_S {
            let (h, residual, block_s) = (self.block_regressors, self.block_residual, self.block_s);
            self.clear_block();
            self.update_calibration(&h, residual, block_s);
        }
    }

    /// One recursive-least-squares step ([`least_squares_step`]), then the snapshot bookkeeping
    /// that delays what is used by ≥ `CALIBRATION_DELAY_S`.
    fn update_calibration(&mut self, h: &[[f64; 2]; 3], clipped: [f64; 2], delta_t: f64) {
        let Some((theta, covariance)) = least_squares_step(
            &self.theta,
            &self.covariance,
            h,
            clipped,
            delta_t,
            &Learning {
                noise_variance: self.constants.noise_variance,
                trust: self.constants.trust,
                prior: self.constants.prior,
            },
        ) else {
            return;
        };
        self.theta = theta;
        self.covariance = covariance;
        self.clock_s += delta_t;
        self.take_snapshot();
    }

    /// Keeps a snapshot every `SNAPSHOT_PERIOD_S` and moves `theta_in_use` to the newest one that is
    /// at least `CALIBRATION_DELAY_S` old.
    fn take_snapshot(&mut self) {
        let newest = self
            .snapshot_count
            .checked_sub(1)
            .map(|i| self.snapshots[i]);
        if newest.is_none_or(|s| self.clock_s - s.clock_s >= SNAPSHOT_PERIOD_S) {
            if self.snapshot_count == SNAPSHOTS {
                self.snapshots.copy_within(1.., 0);
                self.snapshot_count -= 1;
            }
            self.snapshots[self.snapshot_count] = Snapshot {
                clock_s: self.clock_s,
                theta: self.theta,
                levels: self.levels,
            };
            self.snapshot_count += 1;
        }
        let due = self.clock_s - CALIBRATION_DELAY_S;
        if let Some(snapshot) = self.snapshots[..self.snapshot_count]
            .iter()
            .rev()
            .find(|s| s.clock_s <= due)
        {
            self.theta_in_use = snapshot.theta;
            self.levels_in_use = snapshot.levels;
        }
    }

    /// m_k ← e^{−δ/τ_k} m_k + (1 − e^{−δ/τ_k}) r/δ for both residuals.
    fn update_rates(&mut self, clipped: [f64; 2], cleaned: [f64; 2], delta_t: f64) {
        if delta_t != self.decay_delta {
            self.decay = DRIFT_SCALES_S.map(|tau| (-delta_t / tau).exp());
            self.decay_delta = delta_t;
        }
        for k in 0..SCALE_COUNT {
            let a = self.decay[k];
            for axis in 0..2 {
                self.raw_rate[k][axis] =
                    a * self.raw_rate[k][axis] + (1.0 - a) * (clipped[axis] / delta_t);
                self.calibrated_rate[k][axis] =
                    a * self.calibrated_rate[k][axis] + (1.0 - a) * (cleaned[axis] / delta_t);
            }
        }
    }
}

/// r·min(1, c/‖r‖).
pub fn clip(residual: [f64; 2], clip_m: f64) -> [f64; 2] {
    let norm = residual[0].hypot(residual[1]);
    if norm > clip_m {
        let factor = clip_m / norm;
        [residual[0] * factor, residual[1] * factor]
    } else {
        residual
    }
}

/// (Σ + εI)^{-1/2}.
fn whitening(covariance: &Mat2) -> Mat2 {
    inverse_sqrt_symmetric(&super::linalg::add_diagonal(*covariance, RATE_EPSILON))
}

/// max_k ‖z_k‖² / h_k.
fn normalised_max(z: &[[f64; 2]; SCALE_COUNT], thresholds: &[f64; SCALE_COUNT]) -> f64 {
    z.iter()
        .zip(thresholds)
        .map(|(&z, &h)| norm_squared(z) / h)
        .fold(0.0, f64::max)
}

#[cfg(test)]
mod tests {
    use super::super::fit::robust_residual_sigma;
    use super::*;
    use crate::rng::Rng;

    #[test]
    fn clip_scales_long_residuals_onto_the_circle() {
        assert_eq!(clip([3.0, 4.0], 2.5), [1.5, 2.0]);
        assert_eq!(clip([0.3, -0.4], 2.5), [0.3, -0.4]);
        assert_eq!(clip([0.0, 0.0], 2.5), [0.0, 0.0]);
    }

    #[test]
    fn robust_sigma_is_the_mad_based_rms_over_axes() {
        // East: ±1 → median 0, MAD 1; north: ±2 → MAD 2. σ̂ = 1.4826·√((1 + 4)/2).
        let residuals: Vec<[f64; 2]> = (0..40)
            .map(|i| if i % 2 == 0 { [1.0, 2.0] } else { [-1.0, -2.0] })
            .collect();
        let sigma = robust_residual_sigma(&residuals).expect("spread");
        assert!((sigma - 1.4826 * 2.5f64.sqrt()).abs() < 1e-12, "{sigma}");
        assert!(robust_residual_sigma(&[[0.0, 0.0]; 40]).is_err());
    }

    /// A vehicle around `speed` m/s (±30 %) whose heading swings ±90° (so the body frame rotates and
    /// speed and yaw rate vary independently), sampled at 1 Hz. Returns (motion, velocity change) per
    /// row, as the builder sees them.
    fn turning_rows(rows: usize, speed: f64) -> Vec<([f64; 2], [f64; 2])> {
        let velocity = |t: f64| {
            let heading = std::f64::consts::FRAC_PI_2 * (t * std::f64::consts::TAU / 170.0).sin();
            let speed = speed * (1.0 + 0.3 * (t * std::f64::consts::TAU / 61.0).sin());
            [speed * heading.sin(), speed * heading.cos()]
        };
        (1..=rows)
            .map(|t| {
                let (now, before) = (velocity(t as f64), velocity(t as f64 - 1.0));
                let motion = [0.5 * (now[0] + before[0]), 0.5 * (now[1] + before[1])];
                (motion, [now[0] - before[0], now[1] - before[1]])
            })
            .collect()
    }

    /// r = −H θ_true + N(0, noise²) + a drift of `drift` m/s east from row `drift_from` on.
    fn input(
        row: (usize, &([f64; 2], [f64; 2])),
        theta_true: [f64; 3],
        noise: [f64; 2],
        drift: (usize, f64),
    ) -> DriftInput {
        let (t, &(motion, velocity_change)) = row;
        let h = regressors(motion, velocity_change);
        let onboard = apply(&h, &theta_true);
        let east_drift = if t >= drift.0 { drift.1 } else { 0.0 };
        DriftInput {
            residual: [-onboard[0] + noise[0] + east_drift, -onboard[1] + noise[1]],
            motion,
            velocity_change,
            delta_t: 1.0,
            fix_repeated: false,
            learn: true,
        }
    }

    fn tracker() -> DriftTracker {
        DriftTracker::new(&DriftParams::unwhitened(0.7))
    }

    #[test]
    fn calibration_recovers_a_known_scale_heading_and_timing_error() {
        let theta_true = [0.03, 3f64.to_radians(), 0.2];
        let mut rng = Rng::seed_from_u64(5);
        let mut drift = tracker();
        let mut last = DriftEvidence::EMPTY;
        for row in turning_rows(900, 10.0).iter().enumerate() {
            let noise = [0.5 * rng.normal(), 0.5 * rng.normal()];
            last = drift.push(&input(row, theta_true, noise, (usize::MAX, 0.0)));
        }
        let [scale, heading_deg, timing_s] = last.calibration;
        assert!((scale - 0.03).abs() < 0.003, "scale {scale}");
        assert!((heading_deg - 3.0).abs() < 0.2, "heading {heading_deg}");
        assert!((timing_s - 0.2).abs() < 0.05, "timing {timing_s}");
        assert!(last.is_warm());
        // Cleaned of those errors, the residual is the noise again (small), the raw one is not.
        let raw = last.raw_z[3][0].hypot(last.raw_z[3][1]);
        let calibrated = last.calibrated_z[3][0].hypot(last.calibrated_z[3][1]);
        assert!(
            calibrated < 0.05 && raw > 0.2,
            "raw {raw}, calibrated {calibrated}"
        );
    }

    #[test]
    fn the_calibration_in_use_is_at_least_two_minutes_old() {
        let theta_true = [0.0, 4f64.to_radians(), 0.0];
        let mut drift = tracker();
        let rows = turning_rows(200, 10.0);
        for (t, row) in rows.iter().enumerate() {
            let e = drift.push(&input((t, row), theta_true, [0.0; 2], (usize::MAX, 0.0)));
            let clock = (t + 1) as f64;
            // The first snapshot is taken after the first row (clock 1 s).
            if clock <= CALIBRATION_DELAY_S {
                assert_eq!(e.calibration, [0.0; 3], "row {t}");
            } else {
                assert_ne!(e.calibration, [0.0; 3], "row {t}");
            }
            assert_eq!(e.warm_up, (clock / WARM_UP_S).min(1.0));
        }
    }

    #[test]
    fn a_drift_that_starts_after_warm_up_is_not_absorbed_and_stands_out() {
        let theta_true = [0.02, 3f64.to_radians(), 0.1];
        let rows = turning_rows(700, 10.0);
        let onset = 600;
        let mut rng = Rng::seed_from_u64(8);
        let noise: Vec<[f64; 2]> = rows
            .iter()
            .map(|_| [0.5 * rng.normal(), 0.5 * rng.normal()])
            .collect();
        let run = |drift_mps: f64| {
            let mut drift = tracker();
            rows.iter()
                .enumerate()
                .map(|row| drift.push(&input(row, theta_true, noise[row.0], (onset, drift_mps))))
                .collect::<Vec<_>>()
        };
        let clean = run(0.0);
        let spoofed = run(0.5);
        // For 120 s after the onset the calibration in use is exactly the drift-free one.
        for t in onset..onset + CALIBRATION_DELAY_S as usize - SNAPSHOT_PERIOD_S as usize {
            assert_eq!(spoofed[t].calibration, clean[t].calibration, "row {t}");
        }
        // 60 s in, the 60 s calibrated drift rate points east at most of the 0.5 m/s.
        let rate = |e: &DriftEvidence| e.calibrated_z[2];
        let at = onset + 60;
        let (clean_rate, spoofed_rate) = (rate(&clean[at]), rate(&spoofed[at]));
        assert!(
            spoofed_rate[0] - clean_rate[0] > 0.3,
            "{spoofed_rate:?} vs {clean_rate:?}"
        );
        assert!((spoofed_rate[1] - clean_rate[1]).abs() < 0.05);
    }

    #[test]
    fn drift_rates_are_ewmas_by_hand_and_restart_with_a_trajectory() {
        let mut drift = tracker();
        let step = DriftInput {
            residual: [0.5, 0.0],
            motion: [0.0; 2],
            velocity_change: [0.0; 2],
            delta_t: 0.5,
            fix_repeated: false,
            learn: true,
        };
        let mut e = DriftEvidence::EMPTY;
        for _ in 0..3 {
            e = drift.push(&step);
        }
        // r/δ = 1 m/s east; m = 1 − a³ with a = e^{−0.5/τ} (identity whitening up to 1e-9).
        for (k, tau) in DRIFT_SCALES_S.iter().enumerate() {
            let expected = 1.0 - (-0.5 / tau).exp().powi(3);
            assert!((e.raw_z[k][0] - expected).abs() < 1e-8, "scale {k}");
            assert_eq!(e.raw_z[k][1], 0.0);
        }
        assert_eq!(e.clipped_residual, [0.5, 0.0]);
        assert_eq!(e.statistic, e.raw_chi2()[0]);
        drift.start_trajectory();
        let held = drift.hold();
        assert_eq!(held.raw_z, [[0.0; 2]; SCALE_COUNT]);
        assert_eq!(held.warm_up, e.warm_up);
        assert!(held.clipped_residual[0].is_nan());
    }

    #[test]
    fn a_spike_is_clipped_before_it_reaches_the_channels() {
        let mut drift = tracker();
        let clip_m = CLIP_SIGMAS * 0.7;
        let e = drift.push(&DriftInput {
            residual: [350.0, 0.0],
            motion: [10.0, 0.0],
            velocity_change: [0.0; 2],
            delta_t: 1.0,
            fix_repeated: false,
            learn: true,
        });
        assert!((e.clipped_residual[0] - clip_m).abs() < 1e-12 && e.clipped_residual[1] == 0.0);
        let m = 1.0 - (-1.0 / DRIFT_SCALES_S[0]).exp();
        assert!((e.raw_z[0][0] - m * clip_m).abs() < 1e-8);
    }

    #[test]
    fn a_repeated_fix_counts_stale_seconds_until_it_moves_or_the_trajectory_restarts() {
        let mut drift = tracker();
        let row = |fix_repeated: bool, delta_t: f64| DriftInput {
            residual: [0.0; 2],
            motion: [0.0; 2],
            velocity_change: [0.0; 2],
            delta_t,
            fix_repeated,
            learn: true,
        };
        let stale: Vec<f64> = [
            row(true, 1.0),
            row(true, 0.5),
            row(false, 1.0),
            row(true, 2.0),
        ]
        .iter()
        .map(|r| drift.push(r).stale_fix_s)
        .collect();
        assert_eq!(stale, [1.0, 1.5, 0.0, 2.0]);
        assert_eq!(drift.hold().stale_fix_s, 2.0, "a ν = 0 row holds it");
        drift.start_trajectory();
        assert_eq!(drift.hold().stale_fix_s, 0.0);
        assert_eq!(drift.push(&row(true, 1.0)).stale_fix_s, 1.0);
    }

    #[test]
    fn the_residual_size_is_log_compressed_in_clip_radii() {
        let mut drift = tracker();
        let clip_m = CLIP_SIGMAS * 0.7;
        for (residual, expected) in [
            ([0.0, 0.0], 0.0),
            ([3.0 * clip_m, 4.0 * clip_m], 6f64.ln()),
            ([0.0, -40_000.0], (1.0 + 40_000.0 / clip_m).ln()),
        ] {
            let e = drift.push(&DriftInput {
                residual,
                motion: [0.0; 2],
                velocity_change: [0.0; 2],
                delta_t: 1.0,
                fix_repeated: false,
                learn: true,
            });
            assert!((e.residual_log - expected).abs() < 1e-12, "{residual:?}");
        }
        assert_eq!(drift.hold().residual_log, 0.0, "undefined when ν = 0");
    }

    #[test]
    fn a_vehicle_noisier_than_the_population_is_normalised_by_its_own_level() {
        // Identity whitening, so at 1 Hz with white residuals of σ m per axis the 10 s drift rate has
        // χ²/2 = σ²(1 − a)/(1 + a) ≈ 0.05 σ² (a = e^{−0.1}): ≈ 1.8 for σ = 6 m, ≈ 0.01 for σ = 0.5 m.
        // The level moves from the population's 1 towards that, from data ≥ 120 s old.
        let params = DriftParams {
            vehicle_levels: true,
            ..DriftParams::unwhitened(5.0)
        };
        let run = |noise_m: f64| {
            let mut drift = DriftTracker::new(&params);
            let mut rng = Rng::seed_from_u64(3);
            let mut levels = Vec::new();
            for _ in 0..900 {
                drift.push(&DriftInput {
                    residual: [noise_m * rng.normal(), noise_m * rng.normal()],
                    motion: [0.0; 2],
                    velocity_change: [0.0; 2],
                    delta_t: 1.0,
                    fix_repeated: false,
                    learn: true,
                });
                levels.push(drift.levels_in_use);
            }
            levels
        };
        let quiet = run(0.5);
        let noisy = run(6.0);
        // Nothing is used before the first snapshot is 120 s old.
        assert_eq!(noisy[100], Levels::default());
        let (q, n) = (quiet[899].raw[0], noisy[899].raw[0]);
        assert!(n > 1.3 && n < 2.3, "noisy {n}");
        assert!(q < 0.3, "quiet {q}");
        // The χ² seen by the detector are clamped to [1, 16] of the population's level: a quiet
        // vehicle is never made more sensitive than the population.
        assert_eq!(scaled([2.0, 0.0], 100.0), [0.5, 0.0]);
        assert_eq!(scaled([2.0, 0.0], 0.01), [2.0, 0.0]);
        assert_eq!(scaled([2.0, 0.0], 4.0), [1.0, 0.0]);
    }

    #[test]
    fn params_validate_and_round_trip() {
        let params = DriftParams::unwhitened(1.0);
        let json = serde_json::to_string(&params).expect("serialise");
        let back: DriftParams = serde_json::from_str(&json).expect("valid");
        assert_eq!(back, params);
        let bad = json.replace("\"clip_m\":4.0", "\"clip_m\":-1.0");
        let err = serde_json::from_str::<DriftParams>(&bad).expect_err("negative clip");
        assert!(err.to_string().contains("drift.clip_m"), "{err}");
        let mut indefinite = params;
        indefinite.raw_covariance[2] = [[1.0, 2.0], [2.0, 1.0]];
        let err = indefinite.validate().expect_err("indefinite");
        assert!(err.to_string().contains("drift.raw_covariance"), "{err}");
    }
}
