//! The receiver's own spoofing flag as evidence for the alarm lifecycle (`docs/detector.md` §7.3).
//!
//! A receiver raises its spoofing flag mostly at the moment a spoofer takes over, and also on
//! benign events (an SBAS correction switching, a constellation dropping out). Alone it is no
//! verdict. Together with the detector's own evidence it is: the flag says the receiver saw
//! something, the evidence says the position went wrong. While a flag raised within the last
//! [`FLAG_MEMORY_S`] seconds counts, a fix displaced beyond the follow gate for
//! [`CORROBORATION_S`] opens an alarm at once, and p̂ ≥ θ counts towards T_on while a trajectory
//! settles (as it does on a displaced fix). The flag never opens or holds an alarm by itself.
//!
//! An open area incident (§11) is the same kind of evidence, from the fleet instead of the
//! receiver: a sample inside its area is treated as flagged.
//!
//! Owns when the flag is corroborated, from per-sample flags and displacement. Must not build
//! evidence, score samples or decide when an alarm clears (that is `lifecycle.rs`).

use serde::{Deserialize, Serialize};

/// Seconds a raised spoofing flag keeps counting after the receiver last reported it: a spoofer
/// that takes over slowly (a drift of 1 m/s) displaces the fix beyond the follow gate some tens of
/// seconds after the receiver noticed the take-over and cleared its flag again.
pub const FLAG_MEMORY_S: f64 = 60.0;
/// Seconds the fix must stay displaced beyond the follow gate while the flag counts before the
/// alarm opens: longer than a multipath spike, shorter than the decisive hold the lifecycle's
/// search allows (1–5 s) plus the time an offset takes from the follow gate to the decisive one.
pub const CORROBORATION_S: f64 = 1.0;
/// Durations compare with this slack (s), as in the lifecycle.
const TIME_SLACK_S: f64 = 1e-6;

/// What the receiver's flag says about one sample, for the lifecycle.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct FlagSignal {
    /// The receiver raised its spoofing flag within the last [`FLAG_MEMORY_S`] seconds of this
    /// trajectory: p̂ ≥ θ counts towards T_on while the trajectory settles, as on a displaced fix.
    pub counts: bool,
    /// The flag counts and the fix has been displaced beyond the follow gate for
    /// [`CORROBORATION_S`]: the alarm opens at once.
    pub corroborated: bool,
    /// The sample lies inside an open area incident (§11): besides counting as flagged, p̂ ≥ θ
    /// needs only [`AREA_ON_S`](crate::lifecycle::AREA_ON_S) to open the alarm.
    pub in_incident_area: bool,
}

/// One vehicle's memory of its receiver's spoofing flag.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct FlagCorroboration {
    /// Time of the latest sample of this trajectory whose receiver raised the flag.
    flagged_at: Option<f64>,
    /// Start of the current run of displaced samples while the flag counts.
    corroborated_since: Option<f64>,
}

impl FlagCorroboration {
    /// Feeds one sample and says what the flag means for it. A trajectory start forgets the flag
    /// (as the lifecycle forgets its runs); a ν = 0 sample changes nothing and says nothing.
    /// `flagged`: the receiver reports spoofing on this sample (or the fleet does: the sample lies
    /// inside an open area incident, §11).
    pub fn update(
        &mut self,
        time_s: f64,
        valid: bool,
        trajectory_start: bool,
        flagged: bool,
        displaced: bool,
    ) -> FlagSignal {
        if trajectory_start {
            *self = Self::default();
        }
        if !valid {
            return FlagSignal::default();
        }
        if flagged {
            self.flagged_at = Some(time_s);
        }
        let counts = self
            .flagged_at
            .is_some_and(|at| time_s - at <= FLAG_MEMORY_S + TIME_SLACK_S);
        let corroborated = if counts && displaced {
            let since = *self.corroborated_since.get_or_insert(time_s);
            time_s - since + TIME_SLACK_S >= CORROBORATION_S
        } else {
            self.corroborated_since = None;
            false
        };
        FlagSignal {
            counts,
            corroborated,
            in_incident_area: false,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sample::SpoofingState;

    /// Runs samples every `step_s` from 0 to `end_s` (a trajectory starting at 0); returns the
    /// times at which the flag is corroborated.
    fn corroborated(
        step_s: f64,
        end_s: f64,
        flagged: impl Fn(f64) -> bool,
        displaced: impl Fn(f64) -> bool,
    ) -> Vec<f64> {
        let mut memory = FlagCorroboration::default();
        let steps = (end_s / step_s).round() as usize;
        (0..=steps)
            .map(|i| i as f64 * step_s)
            .filter(|&t| {
                memory
                    .update(t, true, t == 0.0, flagged(t), displaced(t))
                    .corroborated
            })
            .map(|t| (t * 1e6).round() / 1e6)
            .collect()
    }

    #[test]
    fn a_flag_alone_or_a_displacement_alone_corroborates_nothing() {
        assert!(corroborated(1.0, 600.0, |_| true, |_| false).is_empty());
        assert!(corroborated(1.0, 600.0, |_| false, |_| true).is_empty());
    }

    #[test]
    fn a_displacement_held_while_the_flag_counts_corroborates_after_a_second() {
        // Flagged from 10 s on, displaced from 20 s: corroborated from 21 s, at 1 Hz and 10 Hz.
        let flagged = |t: f64| t >= 10.0;
        let displaced = |t: f64| t >= 20.0;
        assert_eq!(corroborated(1.0, 25.0, flagged, displaced)[0], 21.0);
        assert_eq!(corroborated(0.1, 25.0, flagged, displaced)[0], 21.0);
        // A one-row spike at 10 Hz (0.1 s) or 1 Hz corroborates nothing.
        assert!(corroborated(0.1, 25.0, flagged, |t| (20.0..20.15).contains(&t)).is_empty());
        assert!(corroborated(1.0, 25.0, flagged, |t| t == 20.0).is_empty());
    }

    #[test]
    fn a_flag_at_take_over_counts_for_a_minute() {
        // Flagged for 5 s at 100 s (last at 104 s), so it counts until 164 s.
        let flagged = |t: f64| (100.0..105.0).contains(&t);
        let late = corroborated(1.0, 300.0, flagged, |t| t >= 160.0);
        assert_eq!(late, [161.0, 162.0, 163.0, 164.0]);
        assert!(corroborated(1.0, 300.0, flagged, |t| t >= 164.0).is_empty());
    }

    #[test]
    fn a_broken_displacement_and_a_new_trajectory_start_over() {
        // Displaced at 20 s, agreeing at 21 s, displaced again from 22 s: corroborated from 23 s.
        let displaced = |t: f64| t >= 20.0 && (t - 21.0).abs() > 0.5;
        assert_eq!(
            corroborated(1.0, 25.0, |_| true, displaced),
            [23.0, 24.0, 25.0]
        );
        let mut memory = FlagCorroboration::default();
        let mut update = |time_s: f64, valid: bool, start: bool, state: SpoofingState| {
            let signal = memory.update(time_s, valid, start, state.flagged(), true);
            (signal.counts, signal.corroborated)
        };
        assert_eq!(
            update(0.0, true, true, SpoofingState::Multiple),
            (true, false)
        );
        assert_eq!(update(1.0, true, false, SpoofingState::None), (true, true));
        assert_eq!(
            update(3.0, false, false, SpoofingState::None),
            (false, false),
            "ν = 0"
        );
        assert_eq!(update(4.0, true, false, SpoofingState::None), (true, true));
        assert_eq!(
            update(5.0, true, true, SpoofingState::Unknown),
            (false, false),
            "a trajectory start forgets the flag"
        );
        assert_eq!(
            update(9.0, true, false, SpoofingState::Unknown),
            (false, false)
        );
    }
}
