//! The vehicle's onboard calibration (`docs/detector.md` §4.1): speed scale ε, heading bias β and
//! GNSS/onboard lag τ_L, learnt by recursive least squares, and how far the detector may trust it.
//!
//! Two ways of trusting it ([`CalibrationTrust`]):
//! - **Timers** (artifacts written before information-driven trust): the calibrated channels switch on
//!   after 240 s of valid data, and the anchors test raw dead reckoning against a raw growth until
//!   then.
//! - **Information**: every residual is cleaned with the calibration in use from the first row, and
//!   tested against a covariance that includes what is still unknown about it. The calibration in
//!   use is a snapshot at least two minutes old (a fresh drift is not absorbed); its mean squared
//!   error under the current posterior is M = P + (θ − θ_in_use)(θ − θ_in_use)ᵀ, so a vehicle that
//!   has turned (P small) and whose calibration has not moved since the snapshot is trusted within
//!   seconds, and one whose estimate is still converging, or whose compass wanders, is tested
//!   against the disagreement it carries instead of meeting a cliff at minute four.
//!
//! Owns the regressors H, one least-squares step, the calibration's prior, its bound and the
//! predictive covariance H M Hᵀ. Must not keep a vehicle's state (the drift tracker does) or build
//! channels.

use serde::{Deserialize, Serialize};

use super::linalg::Mat2;

/// Memory of the calibration (s): forgetting λ = exp(−δ/600) per row.
pub const CALIBRATION_MEMORY_S: f64 = 600.0;
/// The calibration in use is a snapshot at least this old (s of valid data).
pub const CALIBRATION_DELAY_S: f64 = 120.0;
/// With timers: seconds of valid data before the calibrated channels switch on (ω_t reaches 1).
pub const WARM_UP_S: f64 = 240.0;
/// Prior (and cap) of the calibration's standard deviations when the model carries no fleet prior:
/// speed scale 5 %, heading bias 5°, timing 1 s.
pub const CALIBRATION_PRIOR_STD: [f64; 3] = [0.05, 5.0 * std::f64::consts::PI / 180.0, 1.0];
/// The widest prior a fleet may fit: speed scale 20 %, heading bias 30°, timing 3 s. Beyond it the
/// first-order model of the onboard errors (r = −H θ) no longer holds.
pub const CALIBRATION_PRIOR_STD_MAX: [f64; 3] = [0.2, 30.0 * std::f64::consts::PI / 180.0, 3.0];
/// The narrowest: 0.2 % speed scale, 0.2°, 0.05 s. A tighter prior would refuse to learn the
/// vehicle's own errors at all.
pub const CALIBRATION_PRIOR_STD_MIN: [f64; 3] = [0.002, 0.2 * std::f64::consts::PI / 180.0, 0.05];
/// The calibration learns from blocks of consecutive valid rows at least this long (s): GNSS white
/// noise telescopes in a block's summed residual while the onboard errors add up, so every block
/// carries the same information at 1 Hz and at 10 Hz (row by row, a 10 Hz stream would calibrate
/// ten times more slowly).
pub const CALIBRATION_BLOCK_S: f64 = 1.0;
/// With information-driven trust: how fast a compass's bias may wander, as a random walk
/// (rad²/s). (0.05°)²/s wanders by about 0.9° in five minutes and 2.1° in half an hour, the
/// range a mounted compass or an INS heading drifts by in service.
pub const HEADING_WANDER_RAD2_PER_S: f64 = 7.615e-7;
/// With information-driven trust: θ stays within this many prior standard deviations of the prior
/// (0): ±15 % speed scale, ±15° heading bias, ±3 s lag. A spoofer who teaches the calibrator
/// cannot move it further, and no vehicle in service is off by more.
pub const THETA_BOUND_PRIORS: f64 = 3.0;
/// With information-driven trust: a row teaches the calibration only if its squared Mahalanobis
/// innovation is at most this (χ²₂ at a 10⁻⁴ false-rejection rate).
pub const CALIBRATION_GATE: f64 = 18.420_680_743_952_364;
/// With information-driven trust: a calibration whose remaining uncertainty is at most this share
/// of the prior's counts as known where the fits need calibrated rows only.
pub const FIT_TRUST: f64 = 0.75;

/// The fleet's prior on a vehicle's onboard calibration θ = (speed scale error, heading bias [rad],
/// lag [s]): where a new vehicle's calibration starts (`mean`) and how uncertain it is (`std`, the
/// prior covariance P₀ = diag(std²), also the cap on P). With information-driven trust θ stays
/// within [`THETA_BOUND_PRIORS`] standard deviations of the mean. A model without one uses
/// [`CalibrationPrior::default`], a mean of 0 and [`CALIBRATION_PRIOR_STD`].
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CalibrationPrior {
    pub mean: [f64; 3],
    pub std: [f64; 3],
}

impl Default for CalibrationPrior {
    fn default() -> Self {
        Self {
            mean: [0.0; 3],
            std: CALIBRATION_PRIOR_STD,
        }
    }
}

impl CalibrationPrior {
    /// Why the prior cannot be used, naming the component: every std within
    /// [`CALIBRATION_PRIOR_STD_MIN`]..=[`CALIBRATION_PRIOR_STD_MAX`], every mean finite and within
    /// the widest bound (three of the widest std).
    pub fn problem(&self) -> Option<(&'static str, String)> {
        const NAMES: [&str; 3] = ["speed_scale", "heading_bias", "lag"];
        for i in 0..3 {
            let (std, mean) = (self.std[i], self.mean[i]);
            let (low, high) = (CALIBRATION_PRIOR_STD_MIN[i], CALIBRATION_PRIOR_STD_MAX[i]);
            if !(std.is_finite() && (low..=high).contains(&std)) {
                return Some((
                    NAMES[i],
                    format!("std must be within {low} to {high}, got {std}"),
                ));
            }
            let bound = THETA_BOUND_PRIORS * high;
            if !(mean.is_finite() && mean.abs() <= bound) {
                return Some((
                    NAMES[i],
                    format!("mean must be within ±{bound}, got {mean}"),
                ));
            }
        }
        None
    }

    /// P₀ = diag(std²).
    pub(super) fn covariance(&self) -> [[f64; 3]; 3] {
        let mut p = [[0.0; 3]; 3];
        for (i, std) in self.std.iter().enumerate() {
            p[i][i] = std * std;
        }
        p
    }
}

/// How the detector decides how far to trust the vehicle's onboard calibration.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CalibrationTrust {
    /// The calibrated channels switch on after [`WARM_UP_S`] of valid data (artifacts written
    /// before information-driven trust).
    #[default]
    Timers,
    /// Residuals, drift rates and offsets are cleaned with the calibration in use from the first
    /// row and tested against a covariance that includes its uncertainty.
    Information,
}

impl CalibrationTrust {
    /// Its name in artifacts and on the command line.
    pub fn name(self) -> &'static str {
        match self {
            Self::Timers => "timers",
            Self::Information => "information",
        }
    }

    /// The trust of a [`Self::name`].
    pub fn from_name(name: &str) -> Option<Self> {
        [Self::Timers, Self::Information]
            .into_iter()
            .find(|trust| trust.name() == name)
    }

    pub(crate) fn is_timers(&self) -> bool {
        *self == Self::Timers
    }
}

/// Columns of H_t = [u, J u, −Δv], J(x, y) = (y, −x): to first order a speed scale error ε, a heading
/// bias β and an onboard lag τ_L make r = −ε u − β J u + τ_L Δv = −H θ.
pub(crate) fn regressors(u: [f64; 2], dv: [f64; 2]) -> [[f64; 2]; 3] {
    [u, [u[1], -u[0]], [-dv[0], -dv[1]]]
}

/// H θ.
pub(crate) fn apply(h: &[[f64; 2]; 3], theta: &[f64; 3]) -> [f64; 2] {
    [
        h[0][0] * theta[0] + h[1][0] * theta[1] + h[2][0] * theta[2],
        h[0][1] * theta[0] + h[1][1] * theta[1] + h[2][1] * theta[2],
    ]
}

pub(super) fn add(a: [f64; 2], b: [f64; 2]) -> [f64; 2] {
    [a[0] + b[0], a[1] + b[1]]
}

fn inverse(m: &Mat2) -> Option<Mat2> {
    let det = m[0][0] * m[1][1] - m[0][1] * m[1][0];
    (det.is_finite() && det > 0.0).then(|| {
        [
            [m[1][1] / det, -m[0][1] / det],
            [-m[1][0] / det, m[0][0] / det],
        ]
    })
}

fn symmetrised(p: [[f64; 3]; 3]) -> [[f64; 3]; 3] {
    std::array::from_fn(|i| std::array::from_fn(|j| 0.5 * (p[i][j] + p[j][i])))
}

/// D P D with D_ii = min(1, prior_i/√P_ii): no variance exceeds the prior, so directions the drive
/// does not excite (a straight road) cannot wind the gain up; the congruence keeps P positive definite.
fn cap_covariance(p: [[f64; 3]; 3], prior: &CalibrationPrior) -> [[f64; 3]; 3] {
    let d: [f64; 3] = std::array::from_fn(|i| {
        let std = p[i][i].max(0.0).sqrt();
        if std > prior.std[i] {
            prior.std[i] / std
        } else {
            1.0
        }
    });
    std::array::from_fn(|i| std::array::from_fn(|j| d[i] * p[i][j] * d[j]))
}

/// How a vehicle's calibration learns: the GNSS noise variance per axis, the trust and the fleet's
/// prior.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub(super) struct Learning {
    pub noise_variance: f64,
    pub trust: CalibrationTrust,
    pub prior: CalibrationPrior,
}

/// One recursive-least-squares step with exponential forgetting on the model r^c = −H θ + noise
/// (`learning.noise_variance` per axis) over `delta_t` seconds. With information-driven trust the
/// heading bias may also have wandered since the last step, and θ stays within its bound around the
/// prior's mean. `None` when the step would not be finite (θ and P are then kept).
pub(super) fn least_squares_step(
    theta: &[f64; 3],
    covariance: &[[f64; 3]; 3],
    h: &[[f64; 2]; 3],
    clipped: [f64; 2],
    delta_t: f64,
    learning: &Learning,
) -> Option<([f64; 3], [[f64; 3]; 3])> {
    let Learning {
        noise_variance,
        trust,
        prior,
    } = *learning;
    let p = predicted_covariance(covariance, delta_t, trust);
    // With A = −H: S = H P Hᵀ + σ²I, K = −P Hᵀ S⁻¹, innovation = r^c + H θ.
    let ph = p_h_transposed(&p, h);
    let s_inv = inverse(&innovation_covariance(&ph, h, noise_variance))?;
    let innovation = add(clipped, apply(h, theta));
    // G = P Hᵀ S⁻¹ (3×2); θ −= G·innovation; P −= G H P.
    let gain: [[f64; 2]; 3] = std::array::from_fn(|i| {
        std::array::from_fn(|b| ph[i][0] * s_inv[0][b] + ph[i][1] * s_inv[1][b])
    });
    let mut next = *theta;
    for (i, value) in next.iter_mut().enumerate() {
        *value -= gain[i][0] * innovation[0] + gain[i][1] * innovation[1];
    }
    let mut updated = p;
    for (i, row) in updated.iter_mut().enumerate() {
        for (j, cell) in row.iter_mut().enumerate() {
            *cell -= gain[i][0] * ph[j][0] + gain[i][1] * ph[j][1];
        }
    }
    if !(next.iter().all(|x| x.is_finite()) && updated.iter().flatten().all(|x| x.is_finite())) {
        return None;
    }
    if trust == CalibrationTrust::Information {
        for ((value, std), mean) in next.iter_mut().zip(prior.std).zip(prior.mean) {
            *value = value.clamp(
                mean - THETA_BOUND_PRIORS * std,
                mean + THETA_BOUND_PRIORS * std,
            );
        }
    }
    Some((next, cap_covariance(symmetrised(updated), &prior)))
}

/// P before a block's update: forgotten over `delta_t`, and with information-driven trust the
/// heading bias's wander added.
fn predicted_covariance(
    covariance: &[[f64; 3]; 3],
    delta_t: f64,
    trust: CalibrationTrust,
) -> [[f64; 3]; 3] {
    let forgetting = (-delta_t / CALIBRATION_MEMORY_S).exp();
    let mut p: [[f64; 3]; 3] = covariance.map(|row| row.map(|x| x / forgetting));
    if trust == CalibrationTrust::Information {
        p[1][1] += HEADING_WANDER_RAD2_PER_S * delta_t;
    }
    p
}

/// P Hᵀ (3×2).
fn p_h_transposed(p: &[[f64; 3]; 3], h: &[[f64; 2]; 3]) -> [[f64; 2]; 3] {
    std::array::from_fn(|i| std::array::from_fn(|a| (0..3).map(|j| p[i][j] * h[j][a]).sum()))
}

/// S = H P Hᵀ + σ²I, from P Hᵀ.
fn innovation_covariance(ph: &[[f64; 2]; 3], h: &[[f64; 2]; 3], noise_variance: f64) -> Mat2 {
    let mut s: Mat2 =
        std::array::from_fn(|a| std::array::from_fn(|b| (0..3).map(|i| h[i][a] * ph[i][b]).sum()));
    s[0][0] += noise_variance;
    s[1][1] += noise_variance;
    s
}

/// Whether a row may teach the calibration under information-driven trust: its unclipped residual
/// `residual`, cleaned with the current θ, lies within [`CALIBRATION_GATE`] of what the
/// calibration's uncertainty (H P Hᵀ) and the GNSS noise explain. A displaced fix, a fix held
/// while the vehicle drives away, or one multipath row is a disagreement no onboard calibration
/// makes; learning it would move θ, widen every test by the error that move implies, and so hide
/// the very attack it came from.
pub(super) fn residual_is_consistent(
    theta: &[f64; 3],
    covariance: &[[f64; 3]; 3],
    h: &[[f64; 2]; 3],
    residual: [f64; 2],
    noise_variance: f64,
) -> bool {
    let ph = p_h_transposed(covariance, h);
    let Some(s_inv) = inverse(&innovation_covariance(&ph, h, noise_variance)) else {
        return false;
    };
    let v = add(residual, apply(h, theta));
    let d2 = v[0] * (s_inv[0][0] * v[0] + s_inv[0][1] * v[1])
        + v[1] * (s_inv[1][0] * v[0] + s_inv[1][1] * v[1]);
    d2 <= CALIBRATION_GATE
}

/// The mean squared error of the calibration in use for speed scale and heading bias, as
/// (M_εε, M_εβ, M_ββ): M = P + (θ − θ_in_use)(θ − θ_in_use)ᵀ, the current posterior's spread
/// around the delayed estimate.
pub(super) fn in_use_error(
    covariance: &[[f64; 3]; 3],
    theta: &[f64; 3],
    in_use: &[f64; 3],
) -> [f64; 3] {
    let d = [theta[0] - in_use[0], theta[1] - in_use[1]];
    [
        covariance[0][0] + d[0] * d[0],
        0.5 * (covariance[0][1] + covariance[1][0]) + d[0] * d[1],
        covariance[1][1] + d[1] * d[1],
    ]
}

/// The covariance (m²) that a calibration error with mean squared error `error` (from
/// [`in_use_error`]) leaves in a displacement dead-reckoned as `u`: [u, J u] M [u, J u]ᵀ.
/// (The lag's share, τ_L·Δv, is left out: a velocity change is short and the lag small.)
pub fn calibration_covariance(u: [f64; 2], error: &[f64; 3]) -> Mat2 {
    let [m_ss, m_sh, m_hh] = *error;
    let ju = [u[1], -u[0]];
    std::array::from_fn(|a| {
        std::array::from_fn(|b| {
            m_ss * u[a] * u[b] + m_sh * (u[a] * ju[b] + ju[a] * u[b]) + m_hh * ju[a] * ju[b]
        })
    })
}

/// ω: how well the calibration in use is known, 1 − (its root mean squared error as a share of the
/// prior's, speed scale and heading bias together), within [0, 1]. 0 at the prior; 1 when known
/// exactly.
pub(super) fn information_trust(error: &[f64; 3], prior: &CalibrationPrior) -> f64 {
    let [p_ss, p_hh] = [prior.std[0] * prior.std[0], prior.std[1] * prior.std[1]];
    let share = (0.5 * (error[0] / p_ss + error[2] / p_hh)).sqrt();
    (1.0 - share).clamp(0.0, 1.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_known_calibration_leaves_no_covariance_and_full_trust() {
        let error = in_use_error(&[[0.0; 3]; 3], &[0.01, 0.02, 0.1], &[0.01, 0.02, 0.3]);
        assert_eq!(error, [0.0; 3], "the lag does not enter");
        assert_eq!(calibration_covariance([10.0, 0.0], &error), [[0.0; 2]; 2]);
        let prior = CalibrationPrior::default();
        assert_eq!(information_trust(&error, &prior), 1.0);
        assert_eq!(
            information_trust(
                &in_use_error(&prior.covariance(), &[0.0; 3], &[0.0; 3]),
                &prior
            ),
            0.0
        );
    }

    #[test]
    fn a_heading_error_widens_only_across_the_track() {
        // 1° of heading uncertainty at 20 m east: 20·(π/180) ≈ 0.349 m across (north), 0 along.
        let beta = 1f64.to_radians();
        let c = calibration_covariance([20.0, 0.0], &[0.0, 0.0, beta * beta]);
        assert!(c[0][0].abs() < 1e-15 && c[0][1].abs() < 1e-15);
        assert!((c[1][1] - (20.0 * beta).powi(2)).abs() < 1e-12, "{c:?}");
        // A speed scale error of 2 % widens along it: (0.4 m)².
        let c = calibration_covariance([20.0, 0.0], &[0.02 * 0.02, 0.0, 0.0]);
        assert!((c[0][0] - 0.16).abs() < 1e-12 && c[1][1].abs() < 1e-15);
    }

    #[test]
    fn the_error_of_a_delayed_estimate_adds_its_distance_from_the_current_one() {
        // P = diag(1e-4, 4e-4); θ moved by (0.01, 0.02) since the snapshot in use.
        let p = [[1e-4, 0.0, 0.0], [0.0, 4e-4, 0.0], [0.0, 0.0, 1.0]];
        let error = in_use_error(&p, &[0.01, 0.02, 0.0], &[0.0, 0.0, 0.5]);
        let expected = [1e-4 + 1e-4, 2e-4, 4e-4 + 4e-4];
        for (got, want) in error.iter().zip(expected) {
            assert!((got - want).abs() < 1e-18, "{error:?}");
        }
        // Trust: 1 − √(½(2e-4/0.0025 + 8e-4/(5°)²)).
        let share = (0.5 * (2e-4 / 0.0025 + 8e-4 / 5f64.to_radians().powi(2))).sqrt();
        assert!(
            (information_trust(&error, &CalibrationPrior::default()) - (1.0 - share)).abs() < 1e-12
        );
    }

    #[test]
    fn information_trust_bounds_theta_and_lets_the_heading_wander() {
        // A residual that would teach a 40° heading bias in one step stops at 15°.
        let h = regressors([10.0, 0.0], [0.0, 0.0]);
        let huge = [0.0, 10.0 * 40f64.to_radians()];
        let p = CalibrationPrior::default().covariance();
        let learning = |noise_variance, trust| Learning {
            noise_variance,
            trust,
            prior: CalibrationPrior::default(),
        };
        let (timers, _) = least_squares_step(
            &[0.0; 3],
            &p,
            &h,
            huge,
            1.0,
            &learning(1e-6, CalibrationTrust::Timers),
        )
        .expect("finite");
        let (information, _) = least_squares_step(
            &[0.0; 3],
            &p,
            &h,
            huge,
            1.0,
            &learning(1e-6, CalibrationTrust::Information),
        )
        .expect("finite");
        assert!(timers[1].to_degrees().abs() > 30.0, "{timers:?}");
        assert!(
            (information[1].abs() - 15f64.to_radians()).abs() < 1e-12,
            "{information:?}"
        );
        // With no information in the step (u = 0), P grows by the forgetting, and with
        // information trust by the wander too.
        let tiny = [[1e-8, 0.0, 0.0], [0.0, 1e-8, 0.0], [0.0, 0.0, 1e-8]];
        let still = regressors([0.0, 0.0], [0.0, 0.0]);
        let step = |trust| {
            least_squares_step(
                &[0.0; 3],
                &tiny,
                &still,
                [0.0; 2],
                1.0,
                &learning(1.0, trust),
            )
            .expect("finite")
            .1
        };
        let forgetting = (-1.0f64 / CALIBRATION_MEMORY_S).exp();
        assert!((step(CalibrationTrust::Timers)[1][1] - 1e-8 / forgetting).abs() < 1e-20);
        assert!(
            (step(CalibrationTrust::Information)[1][1]
                - (1e-8 / forgetting + HEADING_WANDER_RAD2_PER_S))
                .abs()
                < 1e-20
        );
    }

    #[test]
    fn a_row_is_consistent_within_the_gate_of_what_noise_and_calibration_explain() {
        // A known calibration (P = 0, θ = 0) and σ² = 1: d² = ‖r‖², gate 18.42.
        let known = [[0.0; 3]; 3];
        let h = regressors([10.0, 0.0], [0.0; 2]);
        assert!(residual_is_consistent(
            &[0.0; 3],
            &known,
            &h,
            [3.0, 3.0],
            1.0
        )); // 18
        assert!(!residual_is_consistent(
            &[0.0; 3],
            &known,
            &h,
            [3.0, 3.1],
            1.0
        )); // 18.61
        // θ cleans the residual first: a 2 % speed scale over 10 m east explains 0.2 m of it
        // (r^c = −H θ), so r = (−0.2 + 4.29, 0) is cleaned to 4.29 (d² = 18.40).
        assert!(residual_is_consistent(
            &[0.02, 0.0, 0.0],
            &known,
            &h,
            [4.09, 0.0],
            1.0
        ));
        assert!(!residual_is_consistent(
            &[0.0; 3],
            &known,
            &h,
            [4.3, 0.0],
            1.0
        ));
        // The calibration's own uncertainty widens the gate along the motion: P_εε = 0.01 over
        // 10 m adds 1 m² east, so S = diag(2, 1) and (6, 0) gives d² = 18.
        let mut scale_unknown = [[0.0; 3]; 3];
        scale_unknown[0][0] = 0.01;
        assert!(residual_is_consistent(
            &[0.0; 3],
            &scale_unknown,
            &h,
            [6.0, 0.0],
            1.0
        ));
        assert!(!residual_is_consistent(
            &[0.0; 3],
            &scale_unknown,
            &h,
            [0.0, 6.0],
            1.0
        ));
    }

    #[test]
    fn trust_names_round_trip() {
        for trust in [CalibrationTrust::Timers, CalibrationTrust::Information] {
            assert_eq!(CalibrationTrust::from_name(trust.name()), Some(trust));
        }
        assert_eq!(CalibrationTrust::from_name("clock"), None);
    }
}
