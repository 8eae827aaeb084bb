//! A session's alarm episodes: how the detector's confirmed alarm, decision by decision, opens,
//! extends, escalates (a warning turns critical: the same episode) and ends the episode a session
//! holds open, and that episode as a stored alarm row.
//!
//! Pure bookkeeping over [`AlarmTrack`]: it must not queue events, read clocks, take locks or touch
//! the store. The session manager records what a step reports (an onset gets its id from the alarm
//! outbox, then opens here; an escalation gets its wall time there, then is recorded here).

use spoofwatch_core::detector::Decision;
use spoofwatch_core::severity::Severity;

use super::handoff::{Escalated, OpenAlarm};
use crate::alarms::event::{self as alarm, Onset};
use crate::store::{AlarmEventRow, StoredCredential};

/// What one decision says about the confirmed alarm.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum AlarmSignal {
    /// The alarm starts at this sample.
    Onset,
    /// The alarm goes on.
    On,
    /// The alarm stopped at this sample (the first one not alarming).
    End,
    /// No alarm.
    Off,
}

impl AlarmSignal {
    /// The signal of a decision (the detector never sets onset without alarm, nor end with it).
    pub fn of(decision: &Decision) -> Self {
        if decision.alarm_onset {
            Self::Onset
        } else if decision.alarm {
            Self::On
        } else if decision.alarm_end {
            Self::End
        } else {
            Self::Off
        }
    }
}

/// What a step asks the session manager to record.
#[derive(Debug, PartialEq)]
pub enum EpisodeChange {
    /// An episode starts at this sample with this severity (critical on decisive evidence):
    /// record its onset, then [`AlarmTrack::open`] it under the onset's id.
    Onset(Severity),
    /// The open episode, a warning, turned critical at this sample: [`AlarmTrack::escalate`] it
    /// and record the escalation.
    Escalated,
    /// This episode ended at its last alarming sample: record its end.
    Ended(OpenAlarm),
}

/// A session's alarm state.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct AlarmTrack {
    /// The latest decision alarms.
    pub active: bool,
    /// Episodes started over the session's life.
    pub raised: u64,
    /// The episode whose onset was recorded and whose end was not yet.
    pub open: Option<OpenAlarm>,
}

impl AlarmTrack {
    /// Follows one decision on a sample at `timestamp_s` with spoofing probability `probability`;
    /// `escalation`: the alarm turned critical at this sample (the decision's).
    pub fn step(
        &mut self,
        signal: AlarmSignal,
        timestamp_s: f64,
        probability: f64,
        escalation: bool,
    ) -> Option<EpisodeChange> {
        self.active = matches!(signal, AlarmSignal::Onset | AlarmSignal::On);
        match signal {
            AlarmSignal::Onset => {
                self.raised += 1;
                Some(EpisodeChange::Onset(if escalation {
                    Severity::Critical
                } else {
                    Severity::Warning
                }))
            }
            AlarmSignal::On => {
                let open = self.open.as_mut()?;
                open.peak = open.peak.max(probability);
                open.samples += 1;
                open.last_timestamp_s = timestamp_s;
                (escalation && open.escalated.is_none()).then_some(EpisodeChange::Escalated)
            }
            AlarmSignal::End => self.close().map(EpisodeChange::Ended),
            AlarmSignal::Off => None,
        }
    }

    /// Opens the episode an [`EpisodeChange::Onset`] announced, under the id its onset was
    /// recorded with (`onset_at_ms`: the wall time recorded with it, `credential` the one the onset
    /// recorded); one that opens critical escalated at its onset.
    pub fn open(
        &mut self,
        id: i64,
        (timestamp_s, onset_at_ms): (f64, i64),
        probability: f64,
        severity: Severity,
        credential: &StoredCredential,
    ) {
        self.open = Some(OpenAlarm {
            id,
            onset_timestamp_s: timestamp_s,
            onset_at_ms,
            peak: probability,
            samples: 1,
            last_timestamp_s: timestamp_s,
            escalated: (severity == Severity::Critical).then_some(Escalated {
                timestamp_s,
                at_ms: onset_at_ms,
            }),
            credential: credential.credential.clone(),
            credential_per_vehicle: credential.credential_per_vehicle,
        });
    }

    /// Makes the open episode critical from sample time `timestamp_s` (wall time `at_ms`), as an
    /// [`EpisodeChange::Escalated`] announced; returns it as it is now (`None` when none is open).
    pub fn escalate(&mut self, timestamp_s: f64, at_ms: i64) -> Option<&OpenAlarm> {
        let open = self.open.as_mut()?;
        open.escalated
            .get_or_insert(Escalated { timestamp_s, at_ms });
        Some(open)
    }

    /// Takes the open episode out, to record its end (also when the session ends, resets or
    /// changes model while alarming).
    pub fn close(&mut self) -> Option<OpenAlarm> {
        self.open.take()
    }

    /// Whether replacing this track by `next` ends this track's open episode: it does unless
    /// `next` holds the same one (a session restored from a snapshot of itself).
    pub fn ends_when_replaced_by(&self, next: &AlarmTrack) -> bool {
        self.open.is_some() && self.open_id() != next.open_id()
    }

    fn open_id(&self) -> Option<i64> {
        self.open.as_ref().map(|open| open.id)
    }

    /// The open episode as the stored alarm row the outbox knows it by.
    pub fn open_row(&self, vehicle_id: &str, model_id: &str) -> Option<AlarmEventRow> {
        self.open
            .as_ref()
            .map(|open| open.row(vehicle_id, model_id))
    }
}

impl OpenAlarm {
    /// Warning, or critical once it escalated.
    pub fn severity(&self) -> Severity {
        if self.escalated.is_some() {
            Severity::Critical
        } else {
            Severity::Warning
        }
    }

    /// The episode as the stored alarm row the outbox knows it by.
    pub fn row(&self, vehicle_id: &str, model_id: &str) -> AlarmEventRow {
        let credential = StoredCredential {
            credential: self.credential.clone(),
            credential_per_vehicle: self.credential_per_vehicle,
        };
        AlarmEventRow {
            peak_probability: self.peak,
            samples: i64::from(self.samples),
            escalated_timestamp_s: self.escalated.map(|e| e.timestamp_s),
            escalated_at_ms: self.escalated.map(|e| e.at_ms),
            ..alarm::opened(
                self.id,
                &Onset {
                    vehicle_id,
                    model_id,
                    timestamp_s: self.onset_timestamp_s,
                    at_ms: self.onset_at_ms,
                    probability: self.peak,
                    severity: self.severity(),
                    why: None,
                    credential: &credential,
                },
            )
        }
    }
}

#[cfg(test)]
mod tests {
    use std::sync::Arc;

    use spoofwatch_core::detector::Detector;
    use spoofwatch_core::model::artifact::ModelArtifact;
    use spoofwatch_core::sample::Sample;

    use super::*;

    /// A real decision with the alarm flags set by hand.
    fn decision(alarm: bool, alarm_onset: bool, alarm_end: bool) -> Decision {
        let artifact = ModelArtifact::from_slice(crate::models::registry::BUNDLED_MODEL)
            .expect("the bundled model");
        let base = Detector::new(Arc::new(artifact))
            .step(&Sample::new(10.0, 32.0, -110.9, 2.0, 90.0), false);
        Decision {
            alarm,
            alarm_onset,
            alarm_end,
            ..base
        }
    }

    #[test]
    fn a_decision_signals_onset_before_alarm_before_end() {
        assert_eq!(
            AlarmSignal::of(&decision(true, true, false)),
            AlarmSignal::Onset
        );
        assert_eq!(
            AlarmSignal::of(&decision(true, false, false)),
            AlarmSignal::On
        );
        assert_eq!(
            AlarmSignal::of(&decision(false, false, true)),
            AlarmSignal::End
        );
        assert_eq!(
            AlarmSignal::of(&decision(false, false, false)),
            AlarmSignal::Off
        );
    }

    fn open_alarm(id: i64) -> OpenAlarm {
        OpenAlarm {
            id,
            onset_timestamp_s: 10.0,
            onset_at_ms: 1_000,
            peak: 0.9,
            samples: 2,
            last_timestamp_s: 11.0,
            escalated: None,
            credential: None,
            credential_per_vehicle: false,
        }
    }

    fn track_with(open: Option<OpenAlarm>) -> AlarmTrack {
        AlarmTrack {
            active: open.is_some(),
            raised: 3,
            open,
        }
    }

    #[test]
    fn an_onset_counts_the_episode_and_asks_for_it_to_be_recorded() {
        let mut track = AlarmTrack::default();
        assert_eq!(
            track.step(AlarmSignal::Onset, 10.0, 0.8, false),
            Some(EpisodeChange::Onset(Severity::Warning))
        );
        assert!(track.active);
        assert_eq!(track.raised, 1);
        assert_eq!(
            track.open, None,
            "opened only under the recorded onset's id"
        );
        let credential = StoredCredential {
            credential: Some("token bridge sha256:0123456789abcdef".to_string()),
            credential_per_vehicle: false,
        };
        track.open(7, (10.0, 1_000), 0.8, Severity::Warning, &credential);
        assert_eq!(
            track.open,
            Some(OpenAlarm {
                id: 7,
                onset_timestamp_s: 10.0,
                onset_at_ms: 1_000,
                peak: 0.8,
                samples: 1,
                last_timestamp_s: 10.0,
                escalated: None,
                credential: credential.credential.clone(),
                credential_per_vehicle: false,
            })
        );
        // The row a continued session's outbox adopts keeps the credential the onset recorded.
        let row = track.open_row("car-1", "m").expect("open");
        assert_eq!(row.credential, credential);
    }

    #[test]
    fn a_critical_onset_opens_an_episode_that_escalated_at_its_onset() {
        let mut track = AlarmTrack::default();
        assert_eq!(
            track.step(AlarmSignal::Onset, 10.0, 0.99, true),
            Some(EpisodeChange::Onset(Severity::Critical))
        );
        track.open(
            7,
            (10.0, 1_000),
            0.99,
            Severity::Critical,
            &alarm::NO_CREDENTIAL,
        );
        let open = track.open.clone().expect("open");
        assert_eq!(open.severity(), Severity::Critical);
        assert_eq!(
            open.escalated,
            Some(Escalated {
                timestamp_s: 10.0,
                at_ms: 1_000
            })
        );
        // Nothing more to escalate.
        assert_eq!(track.step(AlarmSignal::On, 11.0, 0.99, true), None);
    }

    #[test]
    fn a_warning_escalates_once_as_the_same_episode() {
        let mut track = track_with(Some(open_alarm(7)));
        assert_eq!(track.step(AlarmSignal::On, 12.0, 0.97, false), None);
        assert_eq!(
            track.step(AlarmSignal::On, 13.0, 0.99, true),
            Some(EpisodeChange::Escalated)
        );
        let open = track.escalate(13.0, 5_000).expect("open").clone();
        assert_eq!((open.id, open.samples, open.peak), (7, 4, 0.99));
        assert_eq!(open.severity(), Severity::Critical);
        // A second escalation keeps the first time.
        track.escalate(14.0, 6_000);
        assert_eq!(
            track.open.as_ref().and_then(|o| o.escalated),
            Some(Escalated {
                timestamp_s: 13.0,
                at_ms: 5_000
            })
        );
        let row = track.open_row("car-1", "m").expect("open");
        assert_eq!(
            (
                row.severity.0,
                row.escalated_timestamp_s,
                row.escalated_at_ms
            ),
            (Severity::Critical, Some(13.0), Some(5_000))
        );
        assert_eq!(track.escalate(15.0, 7_000).map(|o| o.id), Some(7));
        track.close();
        assert_eq!(track.escalate(15.0, 7_000), None);
    }

    #[test]
    fn an_ongoing_alarm_extends_the_open_episode() {
        let mut track = track_with(Some(open_alarm(7)));
        assert_eq!(track.step(AlarmSignal::On, 12.0, 0.95, false), None);
        assert_eq!(track.step(AlarmSignal::On, 13.0, 0.85, false), None);
        let open = track.open.clone().expect("still open");
        assert_eq!(
            (open.peak, open.samples, open.last_timestamp_s),
            (0.95, 4, 13.0)
        );
        assert_eq!((open.onset_timestamp_s, open.onset_at_ms), (10.0, 1_000));
        assert!(track.active);
        assert_eq!(track.raised, 3);
    }

    #[test]
    fn an_ongoing_alarm_without_an_open_episode_changes_only_the_flag() {
        let mut track = track_with(None);
        assert_eq!(track.step(AlarmSignal::On, 12.0, 0.95, false), None);
        assert_eq!(
            track,
            AlarmTrack {
                active: true,
                raised: 3,
                open: None
            }
        );
    }

    #[test]
    fn an_end_hands_back_the_episode_at_its_last_alarming_sample() {
        let mut track = track_with(Some(open_alarm(7)));
        assert_eq!(
            track.step(AlarmSignal::End, 12.0, 0.1, false),
            Some(EpisodeChange::Ended(open_alarm(7)))
        );
        assert_eq!(track, track_with(None).with_active(false));
        // Nothing open: nothing to record.
        assert_eq!(track.step(AlarmSignal::End, 13.0, 0.1, false), None);
    }

    #[test]
    fn no_alarm_changes_nothing_but_the_flag() {
        let mut track = track_with(Some(open_alarm(7)));
        assert_eq!(track.step(AlarmSignal::Off, 12.0, 0.1, false), None);
        assert_eq!(track, track_with(Some(open_alarm(7))).with_active(false));
    }

    #[test]
    fn closing_takes_the_open_episode_once() {
        let mut track = track_with(Some(open_alarm(7)));
        assert_eq!(track.close(), Some(open_alarm(7)));
        assert_eq!(track.close(), None);
    }

    #[test]
    fn a_replacement_ends_the_episode_unless_it_holds_the_same_one() {
        let open = track_with(Some(open_alarm(7)));
        assert!(open.ends_when_replaced_by(&AlarmTrack::default()));
        assert!(open.ends_when_replaced_by(&track_with(Some(open_alarm(8)))));
        assert!(!open.ends_when_replaced_by(&track_with(Some(open_alarm(7)))));
        assert!(!AlarmTrack::default().ends_when_replaced_by(&AlarmTrack::default()));
        assert!(!AlarmTrack::default().ends_when_replaced_by(&open));
    }

    #[test]
    fn the_open_row_carries_the_episode_so_far() {
        assert_eq!(AlarmTrack::default().open_row("car-1", "m"), None);
        let row = track_with(Some(open_alarm(7)))
            .open_row("car-1", "m")
            .expect("an open episode");
        assert_eq!(
            row,
            AlarmEventRow {
                peak_probability: 0.9,
                samples: 2,
                ..alarm::opened(7, &Onset::warning("car-1", "m", 10.0, 1_000, 0.9))
            }
        );
        assert_eq!((row.end_timestamp_s, row.ended_at_ms), (None, None));
    }

    impl AlarmTrack {
        fn with_active(self, active: bool) -> Self {
            Self { active, ..self }
        }
    }
}
