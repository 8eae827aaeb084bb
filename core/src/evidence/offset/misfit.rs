//! The misfit: how far beyond the level's bound a vehicle's own dead reckoning strays, read from a
//! running mean of ln(1 + NIS/2) on anchors that never freeze.
//!
//! Owns the inversion from that log mean to a misfit. Must not hold per-vehicle state (the tracker
//! keeps the running means) or test an offset.

use super::params::LEVEL_RANGE;

/// A vehicle whose dead reckoning cannot carry an anchor (a poor compass, a reversing robot read
/// with an unsigned speed) shows anchor offsets far beyond the level bound for minutes on end. Its
/// misfit M is the level L whose NIS/2 ~ L·Exp(1) has the mean of ln(1 + NIS/2) seen on an anchor
/// that never freezes (a shadow), over the same memory and delay as the levels (a log mean, so one
/// jump barely moves it). Beyond the level's bound it scales the anchor's variance: the offset
/// channels stand down to what such a vehicle can support (a jump is still decisive on its row).
pub const MISFIT_MAX: f64 = 1e8;
/// Euler's γ: E₁(x) = −γ − ln x + Σ_{k≥1} (−1)^{k+1} x^k / (k·k!).
const EULER_GAMMA: f64 = 0.577_215_664_901_532_9;
/// The population's mean of ln(1 + NIS/2) (χ²₂ NIS: e·E₁(1)); the misfit's prior.
pub(super) const POPULATION_LOG_LEVEL: f64 = 0.596_347_362_323_194;

/// E[ln(1 + L·X)] for X ~ Exp(1): e^{1/L}·E₁(1/L), for L ≥ the level's upper bound (1/L ≤ ¼,
/// where 20 terms of the series are exact to machine precision).
pub(super) fn mean_log_level(level: f64) -> f64 {
    let x = 1.0 / level;
    let mut term = 1.0;
    let mut series = 0.0;
    for k in 1..=20 {
        term *= -x / k as f64;
        series -= term / k as f64;
    }
    x.exp() * (-EULER_GAMMA - x.ln() + series)
}

/// The misfit a running mean of ln(1 + NIS/2) asks for: the level L with that mean, by
/// bisection on ln L; 1 while L is within the level's bound, at most [`MISFIT_MAX`].
pub(super) fn misfit(log_level: f64) -> f64 {
    if log_level.is_nan() || log_level <= mean_log_level(LEVEL_RANGE.1) {
        return 1.0;
    }
    if log_level >= mean_log_level(MISFIT_MAX) {
        return MISFIT_MAX;
    }
    let (mut low, mut high) = (LEVEL_RANGE.1.ln(), MISFIT_MAX.ln());
    for _ in 0..60 {
        let middle = 0.5 * (low + high);
        if mean_log_level(middle.exp()) < log_level {
            low = middle;
        } else {
            high = middle;
        }
    }
    (0.5 * (low + high)).exp()
}
