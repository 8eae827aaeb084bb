//! One vehicle's shadow state: the candidate's detector, its would-be alarm episode, and the
//! comparison with the live model sample by sample (what each said, episodes of one without the
//! other, onsets at each level, vehicle time).
//!
//! Pure: the worker steps the detector and hands each sample's two verdicts to
//! [`VehicleShadow::follow`], which reports the would-be alarm's changes and counts into a
//! [`Tally`]; nothing here locks, stores or reads a clock.

use std::time::Instant;

use spoofwatch_core::detector::{Decision, Detector};

use super::queue::LiveSignal;
use super::tally::{MAX_COUNTED_GAP_S, Tally};

/// What the candidate said on one sample.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ShadowSignal {
    pub alarm: bool,
    pub onset: bool,
    pub escalation: bool,
    pub probability: f64,
}

impl ShadowSignal {
    pub fn of(decision: &Decision) -> Self {
        Self {
            alarm: decision.alarm,
            onset: decision.alarm_onset,
            escalation: decision.escalation,
            probability: decision.probability,
        }
    }
}

/// The candidate's open would-be alarm.
#[derive(Clone, Debug, PartialEq)]
pub struct Episode {
    pub onset_timestamp_s: f64,
    pub critical: bool,
    pub peak: f64,
    /// Its last alarming sample.
    pub last_timestamp_s: f64,
    /// The live model alarmed on at least one of its samples.
    pub live_alarmed: bool,
}

/// A change of the would-be alarm for the store.
#[derive(Clone, Debug, PartialEq)]
pub enum Change {
    Onset(Episode),
    Escalated {
        onset_timestamp_s: f64,
        timestamp_s: f64,
    },
    /// Ended at its last alarming sample.
    Ended(Episode),
}

/// The live model's episode, as far as the shadow saw it begin.
#[derive(Clone, Copy, Debug, PartialEq)]
struct LiveEpisode {
    critical: bool,
    shadow_alarmed: bool,
}

/// A vehicle's shadow state.
#[derive(Debug)]
pub struct VehicleShadow {
    pub detector: Detector,
    pub last_timestamp_s: Option<f64>,
    pub episode: Option<Episode>,
    live: Option<LiveEpisode>,
    /// When it last scored (idle states are let go).
    pub seen: Instant,
}

impl VehicleShadow {
    pub fn new(detector: Detector, now: Instant) -> Self {
        Self {
            detector,
            last_timestamp_s: None,
            episode: None,
            live: None,
            seen: now,
        }
    }

    /// Follows one sample at `timestamp_s` on which the candidate said `shadow` and the live model
    /// `live`; counts into `tally` and returns the would-be alarm's change.
    pub fn follow(
        &mut self,
        timestamp_s: f64,
        shadow: ShadowSignal,
        live: LiveSignal,
        tally: &mut Tally,
    ) -> Option<Change> {
        tally.samples_scored += 1;
        if let Some(last) = self.last_timestamp_s {
            let gap = timestamp_s - last;
            if gap > 0.0 && gap <= MAX_COUNTED_GAP_S {
                tally.vehicle_seconds += gap;
            }
        }
        self.last_timestamp_s = Some(timestamp_s);
        match (live.alarm, shadow.alarm) {
            (true, true) => tally.agree_alarm += 1,
            (false, false) => tally.agree_quiet += 1,
            (true, false) => tally.live_only += 1,
            (false, true) => tally.shadow_only += 1,
        }
        self.follow_live(live, shadow.alarm, tally);
        self.follow_shadow(timestamp_s, shadow, live.alarm, tally)
    }

    fn follow_live(&mut self, live: LiveSignal, shadow_alarm: bool, tally: &mut Tally) {
        if live.onset {
            tally.live_warning += 1;
            self.live = Some(LiveEpisode {
                critical: false,
                shadow_alarmed: false,
            });
        }
        if !live.alarm {
            if let Some(ended) = self.live.take()
                && !ended.shadow_alarmed
            {
                tally.live_episodes_without_shadow += 1;
            }
            return;
        }
        if let Some(episode) = self.live.as_mut() {
            episode.shadow_alarmed |= shadow_alarm;
            if live.escalation && !episode.critical {
                episode.critical = true;
                tally.live_critical += 1;
            }
        }
    }

    fn follow_shadow(
        &mut self,
        timestamp_s: f64,
        shadow: ShadowSignal,
        live_alarm: bool,
        tally: &mut Tally,
    ) -> Option<Change> {
        if shadow.onset {
            tally.shadow_warning += 1;
            tally.shadow_critical += u64::from(shadow.escalation);
            let episode = Episode {
                onset_timestamp_s: timestamp_s,
                critical: shadow.escalation,
                peak: shadow.probability,
                last_timestamp_s: timestamp_s,
                live_alarmed: live_alarm,
            };
            self.episode = Some(episode.clone());
            return Some(Change::Onset(episode));
        }
        if !shadow.alarm {
            let ended = self.episode.take()?;
            if !ended.live_alarmed {
                tally.shadow_episodes_without_live += 1;
            }
            return Some(Change::Ended(ended));
        }
        let episode = self.episode.as_mut()?;
        episode.peak = episode.peak.max(shadow.probability);
        episode.last_timestamp_s = timestamp_s;
        episode.live_alarmed |= live_alarm;
        if shadow.escalation && !episode.critical {
            episode.critical = true;
            tally.shadow_critical += 1;
            return Some(Change::Escalated {
                onset_timestamp_s: episode.onset_timestamp_s,
                timestamp_s,
            });
        }
        None
    }
}

#[cfg(test)]
mod tests {
    use std::sync::Arc;

    use spoofwatch_core::model::artifact::ModelArtifact;

    use super::*;
    use crate::models::registry::BUNDLED_MODEL;

    fn vehicle() -> VehicleShadow {
        let artifact =
            Arc::new(ModelArtifact::from_slice(BUNDLED_MODEL).expect("the bundled model"));
        VehicleShadow::new(Detector::new(artifact), Instant::now())
    }

    fn shadow(alarm: bool, onset: bool, escalation: bool) -> ShadowSignal {
        ShadowSignal {
            alarm,
            onset,
            escalation,
            probability: if alarm { 0.9 } else { 0.1 },
        }
    }

    fn live(alarm: bool, onset: bool) -> LiveSignal {
        LiveSignal {
            alarm,
            onset,
            ..LiveSignal::default()
        }
    }

    #[test]
    fn a_would_be_alarm_opens_escalates_and_ends_at_its_last_alarming_sample() {
        let (mut v, mut tally) = (vehicle(), Tally::default());
        assert_eq!(
            v.follow(
                0.0,
                shadow(false, false, false),
                live(false, false),
                &mut tally
            ),
            None
        );
        assert!(matches!(
            v.follow(
                1.0,
                shadow(true, true, false),
                live(false, false),
                &mut tally
            ),
            Some(Change::Onset(Episode {
                onset_timestamp_s: 1.0,
                critical: false,
                ..
            }))
        ));
        assert_eq!(
            v.follow(
                2.0,
                shadow(true, false, true),
                live(false, false),
                &mut tally
            ),
            Some(Change::Escalated {
                onset_timestamp_s: 1.0,
                timestamp_s: 2.0
            })
        );
        let Some(Change::Ended(ended)) = v.follow(
            3.0,
            shadow(false, false, false),
            live(false, false),
            &mut tally,
        ) else {
            panic!("the episode ends");
        };
        assert_eq!(
            (ended.last_timestamp_s, ended.critical, ended.live_alarmed),
            (2.0, true, false)
        );
        assert_eq!((tally.shadow_warning, tally.shadow_critical), (1, 1));
        assert_eq!(tally.shadow_episodes_without_live, 1);
        assert_eq!((tally.agree_quiet, tally.shadow_only), (2, 2));
        assert_eq!((tally.samples_scored, tally.vehicle_seconds), (4, 3.0));
    }

    #[test]
    fn agreement_is_counted_per_sample_and_per_episode() {
        let (mut v, mut tally) = (vehicle(), Tally::default());
        v.follow(0.0, shadow(true, true, false), live(true, true), &mut tally);
        v.follow(
            1.0,
            shadow(false, false, false),
            live(true, false),
            &mut tally,
        );
        v.follow(
            2.0,
            shadow(false, false, false),
            live(false, false),
            &mut tally,
        );
        // A live episode the candidate never joined.
        v.follow(
            100.0,
            shadow(false, false, false),
            live(true, true),
            &mut tally,
        );
        v.follow(
            101.0,
            shadow(false, false, false),
            live(false, false),
            &mut tally,
        );
        assert_eq!(
            (tally.agree_alarm, tally.live_only, tally.agree_quiet),
            (1, 2, 2)
        );
        assert_eq!(tally.live_warning, 2);
        assert_eq!(tally.live_episodes_without_shadow, 1);
        assert_eq!(tally.shadow_episodes_without_live, 0);
        // The 98 s gap is not driving time.
        assert_eq!(tally.vehicle_seconds, 3.0);
    }
}
