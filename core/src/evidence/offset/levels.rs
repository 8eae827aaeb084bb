//! The vehicle's own levels: how noisy its receiver and its dead reckoning are against the
//! training population, learnt with a delay so that a spoofer cannot teach them quickly.
//!
//! Owns the running means, their delayed snapshots and the levels and misfits in use. Must not
//! move an anchor or test an offset (the tracker hands in each row's NIS).

use super::misfit::misfit;
use super::params::{ANCHOR_COUNT, LEVEL_COUNT, LEVEL_DELAY_S, LEVEL_RANGE, STEP_LEVEL};
use super::state::{LEVEL_SNAPSHOT_S, LEVEL_SNAPSHOTS, LevelSnapshot, OffsetTracker};

/// The vehicle's level is a running mean over about this long (s).
const LEVEL_MEMORY_S: f64 = 300.0;
/// Weight (s) of the population's level 1 in a vehicle's running mean.
const LEVEL_PRIOR_S: f64 = 120.0;
/// A vehicle's level falls by at most a factor e every this many seconds.
const LEVEL_DECREASE_S: f64 = 60.0;
/// One row adds at most this much to the running mean of NIS/2 (so a spike cannot inflate it).
const LEVEL_ROW_CAP: f64 = 8.0;

impl OffsetTracker {
    /// The multiples of the population's variance each level applies this row: the vehicle's
    /// level within the bounds, and for an anchor the larger of that and its misfit.
    pub(super) fn levels(&self) -> [f64; LEVEL_COUNT] {
        if !self.params.vehicle_levels {
            return [1.0; LEVEL_COUNT];
        }
        let mut levels = self
            .levels_in_use
            .map(|l| l.clamp(LEVEL_RANGE.0, LEVEL_RANGE.1));
        for (level, misfit) in levels.iter_mut().zip(self.misfit_in_use) {
            *level = level.max(misfit);
        }
        levels
    }

    /// Running mean of min(NIS/2, cap) per anchor and of the one-row residual's (E = 1 for a
    /// vehicle like the population; only for `settled` rows), and of ln(1 + NIS/2) per shadow
    /// anchor (the misfit), priors the population's with the weight of `LEVEL_PRIOR_S` seconds, memory
    /// `LEVEL_MEMORY_S`; the levels and misfits in use follow the newest snapshot at least
    /// `LEVEL_DELAY_S` old (one whose own rows outweigh the prior), rising at once and falling by
    /// at most e per `LEVEL_DECREASE_S`.
    pub(super) fn update_levels(
        &mut self,
        population_nis: &[f64; LEVEL_COUNT],
        shadow_nis: &[f64; ANCHOR_COUNT],
        delta_t: f64,
        settled: bool,
    ) {
        self.level_clock_s += delta_t;
        let weight = delta_t / (LEVEL_PRIOR_S + self.level_clock_s.min(LEVEL_MEMORY_S));
        if settled {
            for (level, nis) in self.levels.iter_mut().zip(population_nis) {
                if nis.is_finite() {
                    *level += weight * ((0.5 * nis).min(LEVEL_ROW_CAP) - *level);
                }
            }
            let step_nis = population_nis[STEP_LEVEL];
            if step_nis.is_finite() {
                self.early_step[0] += delta_t * (0.5 * step_nis).min(LEVEL_ROW_CAP);
                self.early_step[1] += delta_t;
            }
        }
        for (log_level, nis) in self.log_levels.iter_mut().zip(shadow_nis) {
            if nis.is_finite() {
                *log_level += weight * ((0.5 * nis).ln_1p() - *log_level);
            }
        }
        let newest = self
            .snapshot_count
            .checked_sub(1)
            .map(|i| self.snapshots[i]);
        if newest.is_none_or(|s| self.level_clock_s - s.clock_s >= LEVEL_SNAPSHOT_S) {
            if self.snapshot_count == LEVEL_SNAPSHOTS {
                self.snapshots.copy_within(1.., 0);
                self.snapshot_count -= 1;
            }
            self.snapshots[self.snapshot_count] = LevelSnapshot {
                clock_s: self.level_clock_s,
                levels: self.levels,
                misfits: self.log_levels.map(misfit),
            };
            self.snapshot_count += 1;
        }
        // A snapshot is used once it is old enough, and only if the vehicle's own rows weighed at
        // least as much as the prior in it: before that it says "like the population", not what
        // this receiver is.
        let due = self.level_clock_s - LEVEL_DELAY_S;
        if let Some(snapshot) = self.snapshots[..self.snapshot_count]
            .iter()
            .rev()
            .find(|s| s.clock_s <= due && s.clock_s >= LEVEL_PRIOR_S)
        {
            // A noisier level applies at once; a quieter one comes in gradually, so that offsets
            // the vehicle had under the old level do not all cross the gates in one row.
            let fade = (-delta_t / LEVEL_DECREASE_S).exp();
            let follow = |in_use: &mut f64, target: f64| {
                *in_use = if target >= *in_use {
                    target
                } else {
                    (*in_use * fade).max(target)
                };
            };
            for (in_use, &target) in self.levels_in_use.iter_mut().zip(&snapshot.levels) {
                follow(in_use, target);
            }
            for (in_use, &target) in self.misfit_in_use.iter_mut().zip(&snapshot.misfits) {
                follow(in_use, target);
            }
        } else {
            // Until then the step test uses an upper confidence bound of the vehicle's own
            // one-row noise so far, never below the population's: a quiet receiver is tested as
            // one from its first seconds, a noisy one as noisy as it has shown itself.
            let [sum, seconds] = self.early_step;
            self.levels_in_use[STEP_LEVEL] = early_level(sum, seconds);
        }
    }
}

/// One-sided 95 % upper bound of a level L from `seconds` of rows whose NIS/2 ~ L·Exp(1) summed to
/// `sum` (one independent sample per second; 2·Σ/L ~ χ²₂ₙ, its 5 % quantile by Wilson–Hilferty),
/// within [1, the level's upper bound].
pub(super) fn early_level(sum: f64, seconds: f64) -> f64 {
    let k = 2.0 * seconds;
    if k < 2.0 {
        return LEVEL_RANGE.1;
    }
    let a = 2.0 / (9.0 * k);
    let quantile = k * (1.0 - a - 1.644_853_626_951_472_2 * a.sqrt()).powi(3);
    if quantile <= 0.0 {
        return LEVEL_RANGE.1;
    }
    (2.0 * sum / quantile).clamp(1.0, LEVEL_RANGE.1)
}
