//! The alarm lifecycle in seconds, with hysteresis (`docs/detector.md` §7.1).
//!
//! An alarm opens after p̂ has stayed at or above θ for `on_s` seconds, or at once on decisive
//! evidence: an offset held beyond the decisive gate for `decisive_s` seconds (unless it began as
//! the receiver reacquired after an outage), or the receiver's spoofing flag corroborated by a
//! displaced fix (`receiver.rs`, §7.3). For the first
//! [`SETTLE_S`] of a trajectory (a session's start, or the end of an outage) p̂ counts only where the
//! fix is also displaced from the anchors, or the anchors are disputed (the fix keeps disagreeing
//! with anchors placed again on it): the rate channels' averages are still filling and the
//! vehicle's noise levels are the population's, while the anchors were placed on the fix itself
//! and are at their sharpest. It stays open while
//! p̂ ≥ θ or the fix stays displaced from the anchors, and clears only after `off_s` seconds with
//! neither. Inside an open area incident p̂ needs only [`AREA_ON_S`]. Every duration is measured on the samples' own timestamps, so a 1 Hz and a 10 Hz
//! stream of the same drive open and clear at the same times, and one false-alarm budget holds for
//! both. (The paper's persistence N_p counts rows: 4 rows are 4 s at 1 Hz and 0.4 s at 10 Hz.)
//!
//! Owns when a confirmed alarm opens and clears, from per-sample flags. Must not build evidence,
//! score samples or choose the lifecycle's durations (that is `alarm.rs`'s search).

use serde::{Deserialize, Serialize};

use crate::receiver::FlagSignal;
use crate::sample::readable;
use crate::severity::{CriticalInput, CriticalTest, Escalation};

/// Longest accepted duration of the lifecycle (s): an hour.
pub const MAX_LIFECYCLE_S: f64 = 3600.0;
/// Timestamps of a 10 Hz stream are not exact multiples of 0.1 s in binary; durations compare with
/// this slack (s).
const TIME_SLACK_S: f64 = 1e-6;
/// Inside an open area incident (§11) p̂ ≥ θ opens the alarm after this many seconds, or after T_on
/// if that is shorter: the incident says the area is spoofed, and its vehicles' own evidence needs
/// less persistence than a vehicle alone.
pub const AREA_ON_S: f64 = 2.0;
/// Seconds after a trajectory starts during which p̂ ≥ θ counts towards T_on only on a sample whose
/// fix is displaced from the anchors, or whose anchors are disputed (models with offset evidence
/// only).
pub const SETTLE_S: f64 = 30.0;

/// The lifecycle's durations, chosen on validation data with θ.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Lifecycle {
    /// T_on: seconds p̂ must stay ≥ θ before an alarm opens.
    pub on_s: f64,
    /// T_off: seconds without support (p̂ < θ and the fix agreeing with the anchors) before an open
    /// alarm clears.
    pub off_s: f64,
    /// Seconds an offset must stay beyond the decisive gate to open an alarm at once.
    pub decisive_s: f64,
}

impl Lifecycle {
    /// Every duration finite and in [0, [`MAX_LIFECYCLE_S`]]; the error names the field.
    pub fn validate(&self) -> Result<(), (&'static str, String)> {
        for (field, value) in [
            ("on_s", self.on_s),
            ("off_s", self.off_s),
            ("decisive_s", self.decisive_s),
        ] {
            if !(0.0..=MAX_LIFECYCLE_S).contains(&value) {
                return Err((
                    field,
                    format!(
                        "must be finite and in [0, {MAX_LIFECYCLE_S}] s, got {}",
                        readable(value)
                    ),
                ));
            }
        }
        Ok(())
    }
}

/// What the offset evidence says about one sample, for the lifecycle.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct OffsetSignal {
    /// Seconds the offset has stayed beyond the decisive gate; `None` below it.
    pub held_s: Option<f64>,
    /// The fix is displaced from an anchor beyond the follow gate.
    pub displaced: bool,
    /// The sample has offset evidence (the model has the offset channels), so `displaced` can
    /// vouch for p̂ while a trajectory settles.
    pub anchored: bool,
    /// The larger anchor NIS (§4.2), for the critical test's gate; 0 without offset evidence.
    #[serde(default)]
    pub nis: f64,
    /// Seconds the anchors that NIS is measured from have stood, and the offset from the slow
    /// one (east, north metres): a fix that came back to the track it left, measured from anchors
    /// placed on the fix before it, does not hold the gate. 0 without offset evidence.
    #[serde(default)]
    pub anchors_age_s: f64,
    #[serde(default)]
    pub offset_m: [f64; 2],
    /// Seconds a fix frozen on a moving vehicle and displaced beyond the follow gate has been held
    /// beyond [`FROZEN_FIX_S`](crate::explain::FROZEN_FIX_S); `None` without one. For the
    /// critical test's frozen-fix path.
    #[serde(default)]
    pub frozen_fix_s: Option<f64>,
    /// Seconds since a jump that arrived in one step, while it is held beyond the decisive gate
    /// and the vehicle's dead reckoning can carry it (§4.2's held jump); `None` without one. For
    /// the critical test's held-jump path.
    #[serde(default)]
    pub held_jump_s: Option<f64>,
    /// That jump's arrival step against the vehicle's one-row noise (§4.2's step test), for the
    /// critical test's held-step path; 0 without one.
    #[serde(default)]
    pub held_step_nis: f64,
    /// The offset held now began less than [`REACQUISITION_S`](crate::detector::REACQUISITION_S)
    /// after the anchors' track began in a trajectory after an outage, while the receiver's fixes
    /// may still have been converging: neither the decisive hold nor the critical test's held
    /// paths count it.
    #[serde(default)]
    pub reacquiring: bool,
    /// The fix keeps disagreeing with anchors placed again on it before they earned trust
    /// (`OffsetEvidence::disputed`): while a trajectory settles, p̂ counts on such a row as on a
    /// displaced one, so a drift that starts as the receiver reacquires is not hidden by the
    /// rows that follow each placement.
    #[serde(default)]
    pub disputed: bool,
}

/// One sample's inputs to the lifecycle.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LifecycleInput {
    pub time_s: f64,
    /// ν_t.
    pub valid: bool,
    pub trajectory_start: bool,
    /// p̂_t ≥ θ.
    pub positive: bool,
    /// p̂_t, for the critical test (§7.4).
    pub probability: f64,
    pub offset: OffsetSignal,
    /// What the receiver's spoofing flag says (§7.3): while it counts, p̂ ≥ θ counts towards T_on
    /// during the settling seconds as on a displaced fix; corroborated by a displaced fix, it opens
    /// the alarm at once. It holds nothing open.
    pub flag: FlagSignal,
}

/// One vehicle's alarm state under a [`Lifecycle`].
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct AlarmLifecycle {
    open: bool,
    /// Start of the current run of positive samples.
    positive_since: Option<f64>,
    /// Start of the current run without support, while open.
    quiet_since: Option<f64>,
    /// Time of the current trajectory's first sample; `None` in a state saved before it was kept,
    /// which is long settled.
    #[serde(default)]
    trajectory_since: Option<f64>,
}

impl AlarmLifecycle {
    /// Whether the alarm is open.
    pub fn is_open(&self) -> bool {
        self.open
    }

    /// Feeds one sample; returns whether the alarm is open after it. A trajectory start closes the
    /// alarm and forgets the runs (as the persistence N_p does); a ν = 0 sample changes nothing.
    /// Without a critical test every episode stays a warning.
    pub fn update(&mut self, lifecycle: &Lifecycle, input: &LifecycleInput) -> bool {
        self.update_graded(lifecycle, None, &mut Escalation::default(), input)
    }

    /// [`AlarmLifecycle::update`] with the critical test (§7.4) and its state, kept apart from
    /// the lifecycle's: an episode turns critical, or opens as critical, once the test says so,
    /// and stays critical until it clears.
    pub fn update_graded(
        &mut self,
        lifecycle: &Lifecycle,
        critical: Option<&CriticalTest>,
        escalation: &mut Escalation,
        input: &LifecycleInput,
    ) -> bool {
        if input.trajectory_start {
            *self = Self {
                trajectory_since: Some(input.time_s),
                ..Self::default()
            };
            *escalation = Escalation::default();
        }
        if !input.valid {
            return self.open;
        }
        let time = input.time_s;
        let settling = input.offset.anchored
            && self
                .trajectory_since
                .is_some_and(|since| time - since + TIME_SLACK_S < SETTLE_S);
        let vouched = input.offset.displaced || input.offset.disputed || input.flag.counts;
        if input.positive && (!settling || vouched) {
            self.positive_since.get_or_insert(time);
        } else {
            self.positive_since = None;
        }
        // An offset that began while the receiver reacquired is a receiver converging as often as
        // a spoofer: neither level opens on its hold alone (p̂ and the critical gates still can).
        let decisive = input
            .offset
            .held_s
            .filter(|_| !input.offset.reacquiring)
            .is_some_and(|held| held + TIME_SLACK_S >= lifecycle.decisive_s);
        let on_s = if input.flag.in_incident_area {
            lifecycle.on_s.min(AREA_ON_S)
        } else {
            lifecycle.on_s
        };
        let sustained = self
            .positive_since
            .is_some_and(|since| time - since + TIME_SLACK_S >= on_s);
        // The vehicle's own evidence only: neither the flag nor an area incident pages.
        let critical_now = critical.is_some_and(|test| {
            escalation.observe(
                test,
                &CriticalInput {
                    time_s: time,
                    probability: input.probability,
                    probability_counts: !settling || input.offset.displaced,
                    nis: input.offset.nis,
                    anchors_age_s: input.offset.anchors_age_s,
                    offset_m: input.offset.offset_m,
                    frozen_fix_s: input.offset.frozen_fix_s,
                    held_jump_s: input
                        .offset
                        .held_jump_s
                        .filter(|_| !input.offset.reacquiring),
                    held_step_nis: input.offset.held_step_nis,
                    held_offset_s: input.offset.held_s.filter(|_| !input.offset.reacquiring),
                },
            )
        });
        if !self.open {
            if decisive || sustained || input.flag.corroborated || critical_now {
                self.open = true;
                self.quiet_since = None;
            }
        } else if input.positive || decisive || input.offset.displaced {
            self.quiet_since = None;
        } else {
            let since = *self.quiet_since.get_or_insert(time);
            if time - since + TIME_SLACK_S >= lifecycle.off_s {
                self.open = false;
                self.quiet_since = None;
                escalation.episode_ended();
            }
        }
        if self.open && critical_now {
            escalation.escalate(time);
        }
        self.open
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const LIFECYCLE: Lifecycle = Lifecycle {
        on_s: 3.0,
        off_s: 5.0,
        decisive_s: 2.0,
    };

    /// How a hand-made stream is sampled: whether it has offset evidence, when its trajectory
    /// starts again (an outage) besides at 0, and from when its anchors are disputed.
    #[derive(Clone, Copy)]
    struct Stream {
        anchored: bool,
        restart_s: f64,
        disputed_since: f64,
    }

    const PLAIN: Stream = Stream {
        anchored: false,
        restart_s: f64::INFINITY,
        disputed_since: f64::INFINITY,
    };

    /// Runs the lifecycle over samples every `step_s` from 0 to `end_s`; `positive(t)`,
    /// `held(t)` and `displaced(t)` describe the drive. Returns (onset times, clear times).
    fn run(
        step_s: f64,
        end_s: f64,
        positive: impl Fn(f64) -> bool,
        held_since: Option<f64>,
        displaced: impl Fn(f64) -> bool,
    ) -> (Vec<f64>, Vec<f64>) {
        run_stream(PLAIN, step_s, end_s, positive, held_since, displaced)
    }

    fn run_stream(
        stream: Stream,
        step_s: f64,
        end_s: f64,
        positive: impl Fn(f64) -> bool,
        held_since: Option<f64>,
        displaced: impl Fn(f64) -> bool,
    ) -> (Vec<f64>, Vec<f64>) {
        // The offset is held beyond the decisive gate from `held_since` while it is displaced.
        let mut alarm = AlarmLifecycle::default();
        let (mut onsets, mut clears) = (Vec::new(), Vec::new());
        let steps = (end_s / step_s).round() as usize;
        for i in 0..=steps {
            let time_s = i as f64 * step_s;
            let held_s = held_since
                .filter(|&since| time_s >= since && displaced(time_s))
                .map(|since| time_s - since);
            let was = alarm.is_open();
            let open = alarm.update(
                &LIFECYCLE,
                &LifecycleInput {
                    time_s,
                    valid: true,
                    trajectory_start: i == 0 || (time_s - stream.restart_s).abs() < 1e-9,
                    positive: positive(time_s),
                    probability: 0.5,
                    offset: OffsetSignal {
                        held_s,
                        displaced: displaced(time_s),
                        anchored: stream.anchored,
                        nis: 0.0,
                        anchors_age_s: 3600.0,
                        offset_m: [0.0, 0.0],
                        frozen_fix_s: None,
                        held_jump_s: None,
                        held_step_nis: 0.0,
                        reacquiring: false,
                        disputed: time_s >= stream.disputed_since,
                    },
                    flag: FlagSignal::default(),
                },
            );
            if open && !was {
                onsets.push(time_s);
            }
            if was && !open {
                clears.push(time_s);
            }
        }
        (onsets, clears)
    }

    fn rounded(times: Vec<f64>) -> Vec<f64> {
        times.into_iter().map(|t| (t * 1e6).round() / 1e6).collect()
    }

    #[test]
    fn one_hz_and_ten_hz_open_and_clear_at_the_same_times() {
        // p̂ ≥ θ from 10 s to 20 s: opens at 10 + T_on = 13 s; support ends after 20 s, so the
        // first quiet sample is 21 s (1 Hz) or 20.1 s (10 Hz) and it clears T_off later.
        let positive = |t: f64| (10.0 - 1e-9..=20.0 + 1e-9).contains(&t);
        let (on_1, off_1) = run(1.0, 40.0, positive, None, |_| false);
        let (on_10, off_10) = run(0.1, 40.0, positive, None, |_| false);
        assert_eq!(rounded(on_1), vec![13.0]);
        assert_eq!(rounded(on_10), vec![13.0]);
        assert_eq!(rounded(off_1), vec![26.0]);
        assert_eq!(rounded(off_10), vec![25.1]);
    }

    #[test]
    fn a_short_positive_run_never_opens() {
        let (onsets, _) = run(1.0, 30.0, |t| (10.0..=12.0).contains(&t), None, |_| false);
        assert!(onsets.is_empty(), "{onsets:?}");
        let (onsets, _) = run(0.1, 30.0, |t| (10.0..=12.5).contains(&t), None, |_| false);
        assert!(onsets.is_empty(), "{onsets:?}");
    }

    #[test]
    fn a_held_offset_opens_at_once_and_keeps_it_open_while_displaced() {
        // Beyond the decisive gate from 50 s: opens at 52 s whatever p̂ does; displaced until
        // 100 s, so it clears at 100 + T_off (1 Hz: first quiet sample at 101 s).
        let (onsets, clears) = run(1.0, 150.0, |_| false, Some(50.0), |t| t <= 100.0);
        assert_eq!(onsets, vec![52.0]);
        assert_eq!(clears, vec![106.0]);
    }

    #[test]
    fn toggles_back_to_the_truth_do_not_clear_an_open_alarm() {
        // Displaced, except on every fourth second (the spoofer shows the true position).
        let displaced = |t: f64| t >= 20.0 && (t as i64) % 4 != 0;
        let (onsets, clears) = run(1.0, 100.0, |t| (20.0..=30.0).contains(&t), None, displaced);
        assert_eq!(onsets, vec![23.0]);
        assert!(clears.is_empty(), "{clears:?}");
    }

    #[test]
    fn invalid_samples_change_nothing_and_a_trajectory_start_closes() {
        let mut alarm = AlarmLifecycle::default();
        let input = |time_s: f64, valid: bool, start: bool| LifecycleInput {
            time_s,
            valid,
            trajectory_start: start,
            positive: true,
            probability: 0.5,
            offset: OffsetSignal::default(),
            flag: FlagSignal::default(),
        };
        for t in 0..4 {
            alarm.update(&LIFECYCLE, &input(f64::from(t), true, t == 0));
        }
        assert!(alarm.is_open());
        assert!(alarm.update(&LIFECYCLE, &input(4.0, false, false)));
        assert!(!alarm.update(&LIFECYCLE, &input(20.0, true, true)));
    }

    /// Onset times of an anchored stream with p̂ ≥ θ throughout, displaced per `displaced(t)`,
    /// whose trajectory starts at 0 and again at `restart_s`.
    fn anchored_onsets(
        step_s: f64,
        end_s: f64,
        restart_s: f64,
        displaced: impl Fn(f64) -> bool,
    ) -> Vec<f64> {
        let stream = Stream {
            anchored: true,
            restart_s,
            ..PLAIN
        };
        let (onsets, _) = run_stream(stream, step_s, end_s, |_| true, None, displaced);
        rounded(onsets)
    }

    #[test]
    fn while_a_trajectory_settles_p_counts_only_on_a_displaced_fix() {
        // p̂ ≥ θ from the first sample, the fix agreeing with the anchors: T_on (3 s) counts from
        // SETTLE_S (30 s) on, at 1 Hz and at 10 Hz alike; an outage restarts the trajectory at
        // 100 s, which closes the alarm and settles again (opens at 133 s).
        let agreeing = |_: f64| false;
        assert_eq!(
            anchored_onsets(1.0, 150.0, 100.0, agreeing),
            vec![33.0, 133.0]
        );
        assert_eq!(
            anchored_onsets(0.1, 150.0, 100.0, agreeing),
            vec![33.0, 133.0]
        );
        // Displaced from 10 s: the run counts from there and opens T_on later.
        let displaced = |t: f64| t >= 10.0;
        assert_eq!(anchored_onsets(1.0, 50.0, 1e9, displaced), vec![13.0]);
        assert_eq!(anchored_onsets(0.1, 50.0, 1e9, displaced), vec![13.0]);
        // Without offset evidence (no anchors) nothing settles: opens at T_on.
        let (onsets, _) = run(1.0, 50.0, |_| true, None, |_| false);
        assert_eq!(onsets, vec![3.0]);
    }

    #[test]
    fn while_a_trajectory_settles_p_counts_on_rows_whose_anchors_are_disputed() {
        // p̂ ≥ θ throughout, the fix displaced only on every other second (the anchors placed
        // again on each displaced row): while settling the runs last a second and nothing opens
        // before SETTLE_S + T_on; disputed from 10 s, p̂ counts on every row and opens T_on later.
        let every_other = |t: f64| t >= 10.0 && (t as i64) % 2 == 0;
        let alternating = Stream {
            anchored: true,
            ..PLAIN
        };
        let (onsets, _) = run_stream(alternating, 1.0, 50.0, |_| true, None, every_other);
        assert_eq!(rounded(onsets), vec![33.0]);
        let disputed = Stream {
            disputed_since: 10.0,
            ..alternating
        };
        let (onsets, _) = run_stream(disputed, 1.0, 50.0, |_| true, None, every_other);
        assert_eq!(rounded(onsets), vec![13.0]);
    }

    #[test]
    fn a_state_saved_without_the_trajectory_start_is_settled() {
        let mut alarm = AlarmLifecycle::default();
        let positive_agreeing = |time_s: f64| LifecycleInput {
            time_s,
            valid: true,
            trajectory_start: false,
            positive: true,
            probability: 0.5,
            offset: OffsetSignal {
                held_s: None,
                displaced: false,
                anchored: true,
                nis: 0.0,
                anchors_age_s: 3600.0,
                offset_m: [0.0, 0.0],
                frozen_fix_s: None,
                held_jump_s: None,
                held_step_nis: 0.0,
                reacquiring: false,
                disputed: false,
            },
            flag: FlagSignal::default(),
        };
        let onset = (0..10)
            .map(f64::from)
            .find(|&t| alarm.update(&LIFECYCLE, &positive_agreeing(500.0 + t)));
        assert_eq!(onset, Some(3.0), "T_on after the first sample, no settling");
    }

    #[test]
    fn a_corroborated_flag_opens_at_once_and_holds_nothing() {
        let mut alarm = AlarmLifecycle::default();
        let input = |time_s: f64, displaced: bool, corroborated: bool| LifecycleInput {
            time_s,
            valid: true,
            trajectory_start: time_s == 0.0,
            positive: false,
            probability: 0.5,
            offset: OffsetSignal {
                held_s: None,
                displaced,
                anchored: true,
                nis: 0.0,
                anchors_age_s: 3600.0,
                offset_m: [0.0, 0.0],
                frozen_fix_s: None,
                held_jump_s: None,
                held_step_nis: 0.0,
                reacquiring: false,
                disputed: false,
            },
            flag: FlagSignal {
                counts: true,
                corroborated,
                in_incident_area: false,
            },
        };
        assert!(!alarm.update(&LIFECYCLE, &input(0.0, false, false)));
        assert!(!alarm.update(&LIFECYCLE, &input(1.0, true, false)));
        assert!(
            alarm.update(&LIFECYCLE, &input(2.0, true, true)),
            "opens at once"
        );
        // Held while displaced, cleared T_off (5 s) after the fix agrees again.
        assert!(alarm.update(&LIFECYCLE, &input(10.0, true, false)));
        let clear = (11..20)
            .map(f64::from)
            .find(|&t| !alarm.update(&LIFECYCLE, &input(t, false, false)));
        assert_eq!(clear, Some(16.0));
    }

    #[test]
    fn a_counting_flag_lets_p_count_while_the_trajectory_settles() {
        // Anchored, p̂ ≥ θ from the start, the fix agreeing: without the flag T_on counts from
        // SETTLE_S (opens at 33 s); with the flag counting from 5 s on it opens at 5 + T_on = 8 s.
        let onset = |flag_from_s: f64| {
            let mut alarm = AlarmLifecycle::default();
            (0..60).map(f64::from).find(|&t| {
                alarm.update(
                    &LIFECYCLE,
                    &LifecycleInput {
                        time_s: t,
                        valid: true,
                        trajectory_start: t == 0.0,
                        positive: true,
                        probability: 0.5,
                        offset: OffsetSignal {
                            held_s: None,
                            displaced: false,
                            anchored: true,
                            nis: 0.0,
                            anchors_age_s: 3600.0,
                            offset_m: [0.0, 0.0],
                            frozen_fix_s: None,
                            held_jump_s: None,
                            held_step_nis: 0.0,
                            reacquiring: false,
                            disputed: false,
                        },
                        flag: FlagSignal {
                            counts: t >= flag_from_s,
                            corroborated: false,
                            in_incident_area: false,
                        },
                    },
                )
            })
        };
        assert_eq!(onset(f64::INFINITY), Some(33.0));
        assert_eq!(onset(5.0), Some(8.0));
    }

    #[test]
    fn inside_an_incident_area_p_needs_only_the_area_persistence() {
        // Settled, p̂ ≥ θ from 100 s: T_on (3 s) outside an incident area, AREA_ON_S (2 s) inside
        // one, and never longer than T_on.
        let onset = |lifecycle: &Lifecycle, in_incident_area: bool| {
            let mut alarm = AlarmLifecycle::default();
            (0..400).map(|t| f64::from(t) * 0.5).find(|&t| {
                alarm.update(
                    lifecycle,
                    &LifecycleInput {
                        time_s: t,
                        valid: true,
                        trajectory_start: t == 0.0,
                        positive: t >= 100.0,
                        probability: 0.5,
                        offset: OffsetSignal::default(),
                        flag: FlagSignal {
                            in_incident_area,
                            ..FlagSignal::default()
                        },
                    },
                )
            })
        };
        assert_eq!(onset(&LIFECYCLE, false), Some(103.0));
        assert_eq!(onset(&LIFECYCLE, true), Some(102.0));
        let quick = Lifecycle {
            on_s: 1.0,
            ..LIFECYCLE
        };
        assert_eq!(onset(&quick, true), Some(101.0));
    }

    #[test]
    fn validation_names_the_field() {
        let bad = Lifecycle {
            off_s: f64::NAN,
            ..LIFECYCLE
        };
        assert_eq!(bad.validate().expect_err("NaN").0, "off_s");
        let bad = Lifecycle {
            on_s: 1e9,
            ..LIFECYCLE
        };
        assert_eq!(bad.validate().expect_err("too long").0, "on_s");
        assert!(LIFECYCLE.validate().is_ok());
    }

    const CRITICAL: CriticalTest = CriticalTest {
        reference_logit: 2.0,
        threshold: 20.0,
        gate: 100.0,
        decisive_s: 3.0,
        frozen_fix_s: None,
        held_jump: None,
        held_step: None,
        held_offset: None,
    };

    /// Feeds samples every second from 0 to `end_s` with p̂ = `probability(t)` (positive at
    /// p̂ ≥ 0.8), the offset held beyond the decisive gate from `held_since` and the receiver's
    /// flag corroborated per `flag(t)`; returns per second (open, severity).
    fn graded(
        end_s: u32,
        probability: impl Fn(f64) -> f64,
        held_since: Option<f64>,
        flag: impl Fn(f64) -> bool,
    ) -> Vec<(bool, Option<crate::severity::Severity>)> {
        let mut alarm = AlarmLifecycle::default();
        let mut escalation = Escalation::default();
        (0..=end_s)
            .map(f64::from)
            .map(|t| {
                let held_s = held_since.filter(|&s| t >= s).map(|s| t - s);
                let open = alarm.update_graded(
                    &LIFECYCLE,
                    Some(&CRITICAL),
                    &mut escalation,
                    &LifecycleInput {
                        time_s: t,
                        valid: true,
                        trajectory_start: t == 0.0,
                        positive: probability(t) >= 0.8,
                        probability: probability(t),
                        offset: OffsetSignal {
                            held_s,
                            displaced: held_s.is_some() || flag(t),
                            anchored: false,
                            nis: if held_s.is_some() { 400.0 } else { 0.0 },
                            anchors_age_s: 3600.0,
                            offset_m: [0.0, 0.0],
                            frozen_fix_s: None,
                            held_jump_s: None,
                            held_step_nis: 0.0,
                            reacquiring: false,
                            disputed: false,
                        },
                        flag: FlagSignal {
                            counts: flag(t),
                            corroborated: flag(t),
                            in_incident_area: flag(t),
                        },
                    },
                );
                (open, escalation.severity(open))
            })
            .collect()
    }

    fn logistic(logit: f64) -> f64 {
        1.0 / (1.0 + (-logit).exp())
    }

    #[test]
    fn an_episode_turns_critical_once_its_evidence_crosses_the_threshold_and_stays_so() {
        use crate::severity::Severity::{Critical, Warning};
        // p̂ at logit 5 from 10 s to 40 s: the warning opens after T_on (13 s); S grows by 3 a
        // second, counted over the step ending on each sample from 10 s, and reaches 20 at 16 s;
        // the episode stays critical until it clears T_off after p̂ falls (45 s).
        let run = graded(
            60,
            |t| logistic(if (10.0..40.0).contains(&t) { 5.0 } else { -5.0 }),
            None,
            |_| false,
        );
        assert_eq!(run[12], (false, None));
        assert_eq!(run[13], (true, Some(Warning)));
        assert_eq!(run[15], (true, Some(Warning)));
        assert_eq!(run[16], (true, Some(Critical)));
        assert_eq!(run[44], (true, Some(Critical)));
        assert_eq!(run[45], (false, None));
        // A marginal p̂ (logit 1.5 < k) opens a warning that never escalates.
        let run = graded(
            600,
            |t| logistic(if t >= 10.0 { 1.5 } else { -5.0 }),
            None,
            |_| false,
        );
        assert!(run[13..].iter().all(|&step| step == (true, Some(Warning))));
    }

    #[test]
    fn decisive_evidence_escalates_after_the_critical_hold() {
        use crate::severity::Severity::{Critical, Warning};
        // An offset held from 100 s: decisive for the warning after 2 s, critical after 3 s.
        let run = graded(120, |_| 0.01, Some(100.0), |_| false);
        assert_eq!(run[101], (false, None));
        assert_eq!(run[102], (true, Some(Warning)));
        assert_eq!(run[103], (true, Some(Critical)));
    }

    #[test]
    fn neither_a_flag_nor_an_area_incident_escalates() {
        use crate::severity::Severity::Warning;
        // Corroborated from 50 s, p̂ low: the alarm opens at once and stays a warning.
        let run = graded(120, |_| 0.01, None, |t| t >= 50.0);
        assert_eq!(run[50], (true, Some(Warning)));
        assert!(run[50..].iter().all(|&step| step == (true, Some(Warning))));
    }

    #[test]
    fn a_held_jump_alarms_unless_it_began_while_the_receiver_reacquired() {
        use crate::severity::{HeldOffsetTest, Severity, Severity::Critical, Severity::Warning};
        // A jump held from 10 s with a NIS of 64, far below the decisive gate of 100, and p̂ weak:
        // only the held-jump path (gate 49, 2 s) can page it.
        let test = CriticalTest {
            held_jump: Some(HeldOffsetTest {
                gate: 49.0,
                hold_s: 2.0,
            }),
            ..CRITICAL
        };
        // The first warning and the first page.
        let first_alarms = |reacquiring: bool| {
            let mut alarm = AlarmLifecycle::default();
            let mut escalation = Escalation::default();
            let severities: Vec<_> = (0..=30)
                .map(f64::from)
                .map(|t| {
                    let held = (t >= 10.0).then_some(t - 10.0);
                    let open = alarm.update_graded(
                        &LIFECYCLE,
                        Some(&test),
                        &mut escalation,
                        &LifecycleInput {
                            time_s: t,
                            valid: true,
                            trajectory_start: t == 0.0,
                            positive: false,
                            probability: 0.5,
                            offset: OffsetSignal {
                                held_s: held,
                                displaced: held.is_some(),
                                anchored: true,
                                nis: if held.is_some() { 64.0 } else { 0.0 },
                                anchors_age_s: 3600.0,
                                held_jump_s: held,
                                reacquiring,
                                ..OffsetSignal::default()
                            },
                            flag: FlagSignal::default(),
                        },
                    );
                    (t, escalation.severity(open))
                })
                .collect();
            let first_from = |level: Severity| {
                severities
                    .iter()
                    .find(|(_, s)| s.is_some_and(|s| s >= level))
                    .map(|(t, _)| *t)
            };
            (first_from(Warning), first_from(Critical))
        };
        // Decisive for the warning after 2 s, and paged by the held jump's hold at the same time.
        assert_eq!(first_alarms(false), (Some(12.0), Some(12.0)));
        // Begun while the receiver reacquired: a receiver converging holds offsets like this, and
        // neither level opens on the hold alone.
        assert_eq!(first_alarms(true), (None, None));
    }
}
