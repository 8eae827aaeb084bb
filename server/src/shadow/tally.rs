//! A shadow's counts: what one server process counted for it (stored whole, as JSON, every few
//! seconds) and their sum over every process, the summary GetShadow reports.
//!
//! Pure arithmetic: no locks, no I/O.

use serde::{Deserialize, Serialize};

/// Gaps between a vehicle's consecutive scored samples longer than this are not driving time.
pub const MAX_COUNTED_GAP_S: f64 = 60.0;

/// One process's counts for one shadow (cumulative).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct Tally {
    pub samples_scored: u64,
    pub samples_shed: u64,
    /// Sample time covered by the scored samples ([`MAX_COUNTED_GAP_S`]).
    pub vehicle_seconds: f64,
    /// Vehicle shadow states started afresh, by why.
    pub starts_after_shed: u64,
    pub starts_after_idle: u64,
    pub starts_after_reset: u64,
    /// Episodes begun while both models scored: every one is a warning onset; `*_critical` are
    /// those that were or turned critical.
    pub live_warning: u64,
    pub live_critical: u64,
    pub shadow_warning: u64,
    pub shadow_critical: u64,
    /// Samples by what each model said.
    pub agree_alarm: u64,
    pub agree_quiet: u64,
    pub live_only: u64,
    pub shadow_only: u64,
    /// Ended episodes of one model during which the other never alarmed.
    pub live_episodes_without_shadow: u64,
    pub shadow_episodes_without_live: u64,
    /// The candidate's scoring time.
    pub scoring_seconds: f64,
}

impl Tally {
    /// Adds `other`'s counts.
    pub fn add(&mut self, other: &Tally) {
        self.samples_scored += other.samples_scored;
        self.samples_shed += other.samples_shed;
        self.vehicle_seconds += other.vehicle_seconds;
        self.starts_after_shed += other.starts_after_shed;
        self.starts_after_idle += other.starts_after_idle;
        self.starts_after_reset += other.starts_after_reset;
        self.live_warning += other.live_warning;
        self.live_critical += other.live_critical;
        self.shadow_warning += other.shadow_warning;
        self.shadow_critical += other.shadow_critical;
        self.agree_alarm += other.agree_alarm;
        self.agree_quiet += other.agree_quiet;
        self.live_only += other.live_only;
        self.shadow_only += other.shadow_only;
        self.live_episodes_without_shadow += other.live_episodes_without_shadow;
        self.shadow_episodes_without_live += other.shadow_episodes_without_live;
        self.scoring_seconds += other.scoring_seconds;
    }

    /// The sum of stored tallies; an entry that does not decode (a newer server's) counts as
    /// nothing rather than failing the whole summary.
    pub fn sum(stored: &[serde_json::Value]) -> Tally {
        let mut total = Tally::default();
        for value in stored {
            match serde_json::from_value::<Tally>(value.clone()) {
                Ok(tally) => total.add(&tally),
                Err(error) => tracing::warn!(%error, "a stored shadow tally was not read"),
            }
        }
        total
    }

    pub fn vehicle_hours(&self) -> f64 {
        self.vehicle_seconds / 3600.0
    }

    /// `count` per vehicle-hour (0 when no time was covered).
    pub fn per_vehicle_hour(&self, count: u64) -> f64 {
        let hours = self.vehicle_hours();
        if hours > 0.0 {
            count as f64 / hours
        } else {
            0.0
        }
    }

    /// Scoring time per scored sample, in microseconds.
    pub fn micros_per_sample(&self) -> f64 {
        if self.samples_scored == 0 {
            0.0
        } else {
            self.scoring_seconds * 1e6 / self.samples_scored as f64
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tallies_sum_over_processes_and_skip_what_does_not_decode() {
        let one = Tally {
            samples_scored: 10,
            vehicle_seconds: 1800.0,
            shadow_warning: 1,
            ..Tally::default()
        };
        let stored = vec![
            serde_json::to_value(&one).unwrap(),
            serde_json::to_value(&one).unwrap(),
            serde_json::json!("not a tally"),
        ];
        let total = Tally::sum(&stored);
        assert_eq!(total.samples_scored, 20);
        assert_eq!(total.vehicle_hours(), 1.0);
        assert_eq!(total.per_vehicle_hour(total.shadow_warning), 2.0);
        assert_eq!(Tally::default().per_vehicle_hour(3), 0.0);
    }
}
