//! The receiver's own spoofing and jamming states on a simulated or attacked track.
//!
//! A receiver that detects spoofing raises its flag mostly at the moment of take-over, sometimes
//! throughout an attack, and sometimes on a clean drive (an SBAS correction switching). A
//! [`FlagWindow`] says when the simulated receiver reports which states; [`raise_flags`] writes
//! them onto a track. Tracks without windows keep `unknown` states, so every existing scenario is
//! unchanged.
//!
//! Owns the flag windows. Must not move fixes or labels (that is `attack.rs`).

use serde::{Deserialize, Serialize};

use super::ScenarioError;
use super::attack::AttackSpec;
use crate::sample::{JammingState, SpoofingState, Track};

/// Seconds from the track's first sample during which the receiver reports the given states.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FlagWindow {
    /// Start, seconds after the track's first sample (≥ 0).
    pub onset_s: f64,
    /// Length in seconds (> 0); rows with onset ≤ t − t0 < onset + duration are flagged.
    pub duration_s: f64,
    /// The spoofing state reported inside the window.
    pub spoofing_state: SpoofingState,
    /// The jamming state reported inside the window (`unknown`: left as it is).
    #[serde(default)]
    pub jamming_state: JammingState,
}

impl FlagWindow {
    /// The receiver indicating spoofing for the first `duration_s` seconds of `attack` (at most
    /// the whole attack): the take-over.
    pub fn at_take_over(attack: &AttackSpec, duration_s: f64) -> Self {
        Self {
            onset_s: attack.onset_s,
            duration_s: duration_s.min(attack.duration_s),
            spoofing_state: SpoofingState::Indicated,
            jamming_state: JammingState::Unknown,
        }
    }

    /// The receiver indicating spoofing for the whole of `attack`.
    pub fn throughout(attack: &AttackSpec) -> Self {
        Self::at_take_over(attack, attack.duration_s)
    }

    /// Checks every field: onset finite and ≥ 0, duration finite and > 0.
    pub fn validate(&self) -> Result<(), ScenarioError> {
        let invalid = |field, expected: &str, value| ScenarioError::InvalidFlagWindow {
            field,
            expected: expected.to_owned(),
            value,
        };
        if !(self.onset_s.is_finite() && self.onset_s >= 0.0) {
            return Err(invalid(
                "onset_s",
                "a finite, non-negative number of seconds",
                self.onset_s,
            ));
        }
        if !(self.duration_s.is_finite() && self.duration_s > 0.0) {
            return Err(invalid(
                "duration_s",
                "a finite, positive number of seconds",
                self.duration_s,
            ));
        }
        Ok(())
    }

    fn contains(&self, since_start_s: f64) -> bool {
        (self.onset_s..self.onset_s + self.duration_s).contains(&since_start_s)
    }
}

/// A copy of `track` whose rows inside each window report that window's states (a later window
/// wins where windows overlap; an `unknown` jamming state leaves the row's own). Fixes, motion and
/// labels are untouched.
pub fn raise_flags(track: &Track, windows: &[FlagWindow]) -> Result<Track, ScenarioError> {
    for window in windows {
        window.validate()?;
    }
    let Some(first) = track.records.first() else {
        return Err(ScenarioError::EmptyTrack {
            vehicle_id: track.vehicle_id.clone(),
        });
    };
    let t0 = first.sample.timestamp_s;
    let mut flagged = track.clone();
    for record in &mut flagged.records {
        let since_start_s = record.sample.timestamp_s - t0;
        for window in windows.iter().filter(|w| w.contains(since_start_s)) {
            record.sample.spoofing_state = window.spoofing_state;
            if window.jamming_state != JammingState::Unknown {
                record.sample.jamming_state = window.jamming_state;
            }
        }
    }
    Ok(flagged)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sample::{Record, Sample};
    use crate::scenario::AttackKind;

    fn track(seconds: u32) -> Track {
        Track {
            vehicle_id: "v".into(),
            records: (0..seconds)
                .map(|t| Record {
                    sample: Sample::new(100.0 + f64::from(t), 32.0, -110.0, 3.0, 90.0),
                    label: Some(false),
                    comparator_alarm: None,
                    line: u64::from(t) + 2,
                    trajectory_break: false,
                    warmup: false,
                })
                .collect(),
        }
    }

    fn states(track: &Track) -> Vec<(u8, u8)> {
        use crate::sample::ReceiverState;
        track
            .records
            .iter()
            .map(|r| {
                (
                    r.sample.spoofing_state.code(),
                    r.sample.jamming_state.code(),
                )
            })
            .collect()
    }

    #[test]
    fn windows_flag_their_rows_only() {
        let windows = [
            FlagWindow {
                onset_s: 1.0,
                duration_s: 3.0,
                spoofing_state: SpoofingState::None,
                jamming_state: JammingState::Warning,
            },
            FlagWindow {
                onset_s: 3.0,
                duration_s: 1.5,
                spoofing_state: SpoofingState::Multiple,
                jamming_state: JammingState::Unknown,
            },
        ];
        let flagged = raise_flags(&track(6), &windows).expect("valid windows");
        assert_eq!(
            states(&flagged),
            [(0, 0), (1, 2), (1, 2), (3, 2), (3, 0), (0, 0)]
        );
        let original = track(6);
        for (a, b) in original.records.iter().zip(&flagged.records) {
            assert_eq!(a.label, b.label);
            assert_eq!(
                a.sample.latitude_deg.to_bits(),
                b.sample.latitude_deg.to_bits()
            );
        }
        assert_eq!(raise_flags(&original, &[]).expect("no windows"), original);
    }

    #[test]
    fn attack_windows_start_at_the_take_over() {
        let attack = AttackSpec {
            kind: AttackKind::RampDrift { velocity_mps: 1.0 },
            direction_deg: 0.0,
            onset_s: 2.0,
            duration_s: 3.0,
            seed: None,
        };
        let take_over = FlagWindow::at_take_over(&attack, 10.0);
        assert_eq!((take_over.onset_s, take_over.duration_s), (2.0, 3.0));
        assert_eq!(FlagWindow::throughout(&attack), take_over);
        let flagged = raise_flags(&track(6), &[FlagWindow::at_take_over(&attack, 1.0)])
            .expect("valid window");
        assert_eq!(
            states(&flagged),
            [(0, 0), (0, 0), (2, 0), (0, 0), (0, 0), (0, 0)]
        );
    }

    #[test]
    fn a_bad_window_is_refused_by_field() {
        let bad = FlagWindow {
            onset_s: 0.0,
            duration_s: f64::NAN,
            spoofing_state: SpoofingState::Indicated,
            jamming_state: JammingState::Unknown,
        };
        let error = raise_flags(&track(3), &[bad]).expect_err("NaN duration");
        assert!(
            matches!(
                error,
                ScenarioError::InvalidFlagWindow {
                    field: "duration_s",
                    ..
                }
            ),
            "{error:?}"
        );
        let early = FlagWindow {
            onset_s: -1.0,
            duration_s: 1.0,
            ..bad
        };
        assert!(raise_flags(&track(3), &[early]).is_err());
        let empty = Track {
            vehicle_id: "e".into(),
            records: Vec::new(),
        };
        assert!(raise_flags(&empty, &[]).is_err());
    }
}
