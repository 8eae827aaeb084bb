//! Alarm severities (`docs/detector.md` §7.4): an open alarm is a *warning* (shown on dashboards,
//! about one false alarm per vehicle-hour) until its evidence is strong enough to page someone,
//! then *critical* (at most one false alarm per hundred vehicle-hours). One episode, whose
//! severity only rises: it is not two alarms.
//!
//! An episode turns critical
//! - at once on decisive evidence: the fix displaced from the dead-reckoning anchors with a NIS of
//!   at least [`CriticalTest::gate`], held for [`CriticalTest::decisive_s`] (a jump or a hop far
//!   beyond the vehicle's own noise, or a fix frozen on a moving vehicle, whose offset grows with
//!   every metre driven), or a fix frozen on a moving vehicle and displaced beyond the follow gate,
//!   held for [`CriticalTest::frozen_fix_s`] (a receiver's fix jitters; a slow vehicle takes long
//!   to carry a frozen fix to a large NIS), or a jump that arrived in one step and has been held
//!   ([`CriticalTest::held_jump`]: a dead-reckoning error builds up, it does not step). Their
//!   likelihood ratios are enormous, so the stricter budget costs them little;
//! - when an offset, however it arrived, has been held beyond the decisive gate for tens of
//!   seconds with a NIS still at a gate ([`CriticalTest::held_offset`]): a drift that has grown
//!   past the dead-reckoning error it is tested against;
//! - when a sequential test on p̂ crosses its threshold: S ← max(0, S + δ·(x − k)), x the logit of
//!   p̂ capped at ±[`LOGIT_CAP`] (at most 0 while a trajectory settles and nothing vouches for p̂,
//!   as for the warning), critical once S ≥ h. A CUSUM in seconds: the same drive at 1 Hz and at
//!   10 Hz accumulates the same evidence, and a strong p̂ escalates sooner than a marginal one.
//!   k and h are chosen on attack-free validation hours at every sample rate
//!   ([`crate::critical_search`]).
//!
//! Neither the receiver's spoofing flag nor an area incident makes an episode critical: they open
//! alarms sooner, but a page must rest on the vehicle's own evidence.
//!
//! Owns the critical test's parameters and its per-vehicle state. Must not decide when an alarm
//! opens or clears (that is `lifecycle.rs`) or choose the test's parameters.

use serde::{Deserialize, Serialize};

use crate::sample::readable;

/// |logit p̂| counts up to this: one saturated probability (p̂ = 1 − 10⁻¹²) must not weigh as much
/// as minutes of strong evidence.
pub const LOGIT_CAP: f64 = 10.0;
/// Longest accepted decisive hold (s): an hour, as the lifecycle's durations.
pub const MAX_HOLD_S: f64 = 3600.0;
/// Largest accepted threshold h (logit·s): an hour at the cap.
pub const MAX_THRESHOLD: f64 = LOGIT_CAP * MAX_HOLD_S;
/// Accepted NIS gates of the decisive path: from the follow gate to a 1 km offset of a metre's
/// noise.
pub const GATE_RANGE: (f64, f64) = (16.0, 1e6);
/// Longest step the test integrates over (s), as the liquid cell clamps δ.
const MAX_STEP_S: f64 = 5.0;
/// Durations compare with this slack (s), as in the lifecycle.
const TIME_SLACK_S: f64 = 1e-6;

/// How loud an alarm is.
#[derive(
    Clone, Copy, Debug, Default, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize,
)]
#[serde(rename_all = "snake_case")]
pub enum Severity {
    /// Shown on dashboards and in alarm watches; not paged.
    #[default]
    Warning,
    /// Pages an operator.
    Critical,
}

impl Severity {
    /// Both, from the lower.
    pub const ALL: [Severity; 2] = [Severity::Warning, Severity::Critical];

    /// The name used in logs, metrics labels, CSV columns and the CLI.
    pub fn name(self) -> &'static str {
        match self {
            Severity::Warning => "warning",
            Severity::Critical => "critical",
        }
    }

    /// The severity called `name`, if any.
    pub fn from_name(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|s| s.name() == name)
    }
}

/// When an episode turns critical; chosen on validation data and carried by the artifact
/// (`critical`). An artifact without it raises warnings only.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CriticalTest {
    /// k: the logit of p̂ above which evidence accumulates (per second).
    pub reference_logit: f64,
    /// h: the accumulated evidence (logit·s above k) at which the episode turns critical.
    pub threshold: f64,
    /// The NIS (the larger anchor's, §4.2) beyond which an offset is decisive for a page.
    pub gate: f64,
    /// Seconds the NIS must stay at or beyond the gate to be critical at once.
    pub decisive_s: f64,
    /// Seconds a frozen fix on a moving vehicle must be held beyond its onset (the lifecycle's
    /// frozen-fix reading, `docs/detector.md` §7.1) to be critical at once; `None`: a frozen fix
    /// escalates only through the gate or the accumulated evidence (artifacts before this path).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub frozen_fix_s: Option<f64>,
    /// A jump that arrived in one step (the offset went from within the follow gate to beyond the
    /// decisive gate in one row, `docs/detector.md` §4.2) and has been held since: critical at once
    /// when it has been held this long and its NIS is still at or beyond this gate. `None`: jumps
    /// escalate only through [`CriticalTest::gate`] or the accumulated evidence (artifacts before
    /// this path).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub held_jump: Option<HeldOffsetTest>,
    /// The same held jump tested by its arrival: critical at once when it has been held this long
    /// and the step it arrived with was at least this gate against the vehicle's one-row noise
    /// (the step test's NIS, `docs/detector.md` §4.2). The anchors' NIS of a jump is in their
    /// levels, which start at their upper bound and learn a vehicle's noise over minutes; the step
    /// test knows a quiet receiver from its first seconds. `None`: no such path (artifacts
    /// before it).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub held_step: Option<HeldOffsetTest>,
    /// An offset held beyond the decisive gate however it arrived (a drift's, once it has grown
    /// past the dead-reckoning error): critical at once when held this long with its NIS still at or
    /// beyond this gate. Its holds are a drift's, tens of seconds, where [`CriticalTest::gate`]'s
    /// are a jump's. `None`: no such path (artifacts before it).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub held_offset: Option<HeldOffsetTest>,
}

/// A held-offset path of the critical test: the offset has stayed beyond the decisive gate for
/// `hold_s` and its NIS is still at or beyond `gate`. On the held-jump path the gate may sit far
/// below [`CriticalTest::gate`]: the NIS of an honest vehicle grows past it only by building up,
/// as dead-reckoning error does, and a receiver's reflection steps back within seconds.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct HeldOffsetTest {
    /// The NIS (the larger anchor's) the held offset must still have.
    pub gate: f64,
    /// Seconds the offset must have stayed beyond the decisive gate (for a jump: since it arrived).
    pub hold_s: f64,
}

impl HeldOffsetTest {
    /// The gate within [`GATE_RANGE`], the hold within [0, an hour]; the error names `fields`
    /// (the gate's, the hold's).
    fn validate(&self, fields: [&'static str; 2]) -> Result<(), (&'static str, String)> {
        if !(GATE_RANGE.0..=GATE_RANGE.1).contains(&self.gate) {
            return Err((
                fields[0],
                format!(
                    "must be in [{}, {}] (a NIS), got {}",
                    GATE_RANGE.0,
                    GATE_RANGE.1,
                    readable(self.gate)
                ),
            ));
        }
        if !(0.0..=MAX_HOLD_S).contains(&self.hold_s) {
            return Err((
                fields[1],
                format!(
                    "must be finite and in [0, {MAX_HOLD_S}] s, got {}",
                    readable(self.hold_s)
                ),
            ));
        }
        Ok(())
    }

    /// Whether an offset held `held_s` (`None`: none held) with NIS `nis` passes this path.
    fn passes(&self, held_s: Option<f64>, nis: f64) -> bool {
        held_s.is_some_and(|held| held + TIME_SLACK_S >= self.hold_s) && nis >= self.gate
    }
}

impl CriticalTest {
    /// k within ±[`LOGIT_CAP`], h in (0, [`MAX_THRESHOLD`]], the hold in [0, an hour]; the error
    /// names the field.
    pub fn validate(&self) -> Result<(), (&'static str, String)> {
        if !(-LOGIT_CAP..=LOGIT_CAP).contains(&self.reference_logit) {
            return Err((
                "reference_logit",
                format!(
                    "must be finite and within ±{LOGIT_CAP} (a logit of p̂), got {}",
                    readable(self.reference_logit)
                ),
            ));
        }
        if !(self.threshold > 0.0 && self.threshold <= MAX_THRESHOLD) {
            return Err((
                "threshold",
                format!(
                    "must be in (0, {MAX_THRESHOLD}] (logit seconds), got {}",
                    readable(self.threshold)
                ),
            ));
        }
        if !(GATE_RANGE.0..=GATE_RANGE.1).contains(&self.gate) {
            return Err((
                "gate",
                format!(
                    "must be in [{}, {}] (a NIS), got {}",
                    GATE_RANGE.0,
                    GATE_RANGE.1,
                    readable(self.gate)
                ),
            ));
        }
        if let Some(hold) = self.frozen_fix_s
            && !(0.0..=MAX_HOLD_S).contains(&hold)
        {
            return Err((
                "frozen_fix_s",
                format!(
                    "must be finite and in [0, {MAX_HOLD_S}] s, got {}",
                    readable(hold)
                ),
            ));
        }
        for (path, field) in [
            (self.held_jump, ["held_jump.gate", "held_jump.hold_s"]),
            (self.held_step, ["held_step.gate", "held_step.hold_s"]),
            (self.held_offset, ["held_offset.gate", "held_offset.hold_s"]),
        ] {
            if let Some(path) = path {
                path.validate(field)?;
            }
        }
        if !(0.0..=MAX_HOLD_S).contains(&self.decisive_s) {
            return Err((
                "decisive_s",
                format!(
                    "must be finite and in [0, {MAX_HOLD_S}] s, got {}",
                    readable(self.decisive_s)
                ),
            ));
        }
        Ok(())
    }
}

/// One sample's inputs to the critical test.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CriticalInput {
    pub time_s: f64,
    /// p̂_t.
    pub probability: f64,
    /// p̂ may count: the trajectory has settled, or the fix is displaced from an anchor.
    pub probability_counts: bool,
    /// The larger anchor NIS of the sample (0 without offset evidence).
    pub nis: f64,
    /// Seconds the anchors that NIS is measured from have stood
    /// ([`OffsetEvidence::anchor_age_s`](crate::evidence::OffsetEvidence::anchor_age_s)).
    pub anchors_age_s: f64,
    /// The offset from the slow anchor (east, north metres; 0 without offset evidence).
    pub offset_m: [f64; 2],
    /// Seconds a frozen fix on a moving vehicle has been held (`None`: no frozen fix).
    pub frozen_fix_s: Option<f64>,
    /// Seconds since a jump that arrived in one step, while it is held beyond the decisive gate
    /// (`None`: no such jump).
    pub held_jump_s: Option<f64>,
    /// That jump's arrival step against the vehicle's one-row noise (0 without one).
    pub held_step_nis: f64,
    /// Seconds the offset has stayed beyond the decisive gate, however it arrived (`None`: below
    /// it).
    pub held_offset_s: Option<f64>,
}

/// The test's per-vehicle state: the accumulated evidence S, the time it was last fed, since
/// when the NIS has stayed at or beyond the gate, and the last sample's offset.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct CriticalEvidence {
    accumulated: f64,
    last_time_s: Option<f64>,
    beyond_gate_since: Option<f64>,
    last_offset_m: [f64; 2],
}

impl CriticalEvidence {
    /// The accumulated evidence S (logit·s above k).
    pub fn accumulated(&self) -> f64 {
        self.accumulated
    }

    /// Feeds one valid sample; returns whether the evidence is critical now.
    pub fn update(&mut self, test: &CriticalTest, input: &CriticalInput) -> bool {
        let delta_s = self
            .last_time_s
            .map_or(0.0, |last| (input.time_s - last).clamp(0.0, MAX_STEP_S));
        self.last_time_s = Some(input.time_s);
        let logit = capped_logit(input.probability);
        let counted = if input.probability_counts {
            logit
        } else {
            logit.min(0.0)
        };
        self.accumulated = (self.accumulated + delta_s * (counted - test.reference_logit)).max(0.0);
        // Before the anchors are trusted, a fix that disagrees places them on itself, and the next
        // row is measured from there. A fix that keeps running away from the vehicle's motion
        // holds its offset through such placements; one that points back, against the offset
        // that placed them, came back to the track it left (a one-row multipath spike as a
        // receiver reacquires): a new offset, and the hold starts again with it.
        let came_back =
            input.anchors_age_s < 1.5 * delta_s && dot(input.offset_m, self.last_offset_m) < 0.0;
        self.last_offset_m = input.offset_m;
        let since = match self.beyond_gate_since {
            Some(since) if !came_back => since,
            _ => input.time_s,
        };
        self.beyond_gate_since = (input.nis >= test.gate).then_some(since);
        let decisive = self
            .beyond_gate_since
            .is_some_and(|since| input.time_s - since + TIME_SLACK_S >= test.decisive_s);
        let frozen = matches!(
            (test.frozen_fix_s, input.frozen_fix_s),
            (Some(hold), Some(held)) if held + TIME_SLACK_S >= hold
        );
        let jump = test
            .held_jump
            .is_some_and(|path| path.passes(input.held_jump_s, input.nis));
        let step = test
            .held_step
            .is_some_and(|path| path.passes(input.held_jump_s, input.held_step_nis));
        let held = test
            .held_offset
            .is_some_and(|path| path.passes(input.held_offset_s, input.nis));
        decisive || frozen || jump || step || held || self.accumulated >= test.threshold
    }

    /// Forgets the evidence (an episode ended); the clock goes on.
    pub fn clear(&mut self) {
        self.accumulated = 0.0;
    }
}

fn dot(a: [f64; 2], b: [f64; 2]) -> f64 {
    a[0] * b[0] + a[1] * b[1]
}

/// An alarm episode's severity and the critical test's evidence, per vehicle. Kept apart from the
/// lifecycle's runs (and after them in a saved detector state), so that a state saved before
/// severities existed is this one cut short.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Escalation {
    /// Critical once the open episode escalated; warning otherwise.
    severity: Severity,
    /// When the open episode turned critical.
    escalated_at: Option<f64>,
    evidence: CriticalEvidence,
}

impl Escalation {
    /// The severity of an episode that is open (`open`), else `None`.
    pub fn severity(&self, open: bool) -> Option<Severity> {
        open.then_some(self.severity)
    }

    /// When the open episode turned critical; `None` while it is a warning.
    pub fn escalated_at(&self) -> Option<f64> {
        self.escalated_at
    }

    /// The critical test's accumulated evidence S.
    pub fn evidence(&self) -> f64 {
        self.evidence.accumulated()
    }

    /// Feeds one valid sample to the test; whether the evidence is critical now.
    pub fn observe(&mut self, test: &CriticalTest, input: &CriticalInput) -> bool {
        self.evidence.update(test, input)
    }

    /// The open episode is critical from `time_s` on (no change once it is).
    pub fn escalate(&mut self, time_s: f64) {
        if self.severity == Severity::Warning {
            self.severity = Severity::Critical;
            self.escalated_at = Some(time_s);
        }
    }

    /// The episode cleared: the next one starts as a warning and escalates on its own evidence.
    pub fn episode_ended(&mut self) {
        self.severity = Severity::Warning;
        self.escalated_at = None;
        self.evidence.clear();
    }
}

/// ln(p / (1 − p)) within ±[`LOGIT_CAP`]; a NaN probability carries no evidence for an attack.
pub fn capped_logit(probability: f64) -> f64 {
    if probability.is_nan() {
        return -LOGIT_CAP;
    }
    (probability.ln() - (-probability).ln_1p()).clamp(-LOGIT_CAP, LOGIT_CAP)
}

#[cfg(test)]
mod tests {
    use super::*;

    const TEST: CriticalTest = CriticalTest {
        reference_logit: 2.0,
        threshold: 20.0,
        gate: 100.0,
        decisive_s: 3.0,
        frozen_fix_s: None,
        held_jump: None,
        held_step: None,
        held_offset: None,
    };

    fn input(time_s: f64, probability: f64) -> CriticalInput {
        CriticalInput {
            time_s,
            probability,
            probability_counts: true,
            nis: 0.0,
            // Anchors that have stood for an hour: every offset is held against them.
            anchors_age_s: 3600.0,
            offset_m: [0.0, 0.0],
            frozen_fix_s: None,
            held_jump_s: None,
            held_step_nis: 0.0,
            held_offset_s: None,
        }
    }

    /// Runs the test on samples every `step_s` of p̂ = `probability(t)`; the first time it is
    /// critical.
    fn first_critical(step_s: f64, end_s: f64, probability: impl Fn(f64) -> f64) -> Option<f64> {
        let mut evidence = CriticalEvidence::default();
        let steps = (end_s / step_s).round() as usize;
        (0..=steps)
            .map(|i| i as f64 * step_s)
            .find(|&t| evidence.update(&TEST, &input(t, probability(t))))
    }

    #[test]
    fn the_logit_is_capped_and_symmetric() {
        assert!((capped_logit(0.5)).abs() < 1e-15);
        // logit(0.9) = ln 9.
        assert!((capped_logit(0.9) - 9f64.ln()).abs() < 1e-12);
        assert!((capped_logit(0.1) + 9f64.ln()).abs() < 1e-12);
        assert_eq!(capped_logit(1.0), LOGIT_CAP);
        assert_eq!(capped_logit(0.0), -LOGIT_CAP);
        assert_eq!(capped_logit(f64::NAN), -LOGIT_CAP);
    }

    #[test]
    fn evidence_accumulates_in_seconds_whatever_the_rate() {
        // p̂ with logit 7 from t = 10 s: 5 per second above k = 2, counted over the step that
        // ends on each sample, so S reaches 20 after four seconds' worth of samples from t = 10.
        let strong = |t: f64| {
            if t >= 10.0 {
                1.0 / (1.0 + (-7.0f64).exp())
            } else {
                0.01
            }
        };
        for step_s in [1.0, 0.2, 0.1] {
            let at = first_critical(step_s, 60.0, strong).expect("critical");
            // 14 − step exactly, or one step later when the sum rounds just below 20.
            assert!(
                at > 14.0 - step_s - 1e-6 && at < 14.0 + 1e-6,
                "{step_s}: critical at {at}"
            );
        }
    }

    #[test]
    fn a_marginal_probability_never_escalates() {
        // logit 1.9 < k = 2: an hour of it accumulates nothing.
        let marginal = |_| 1.0 / (1.0 + (-1.9f64).exp());
        assert_eq!(first_critical(1.0, 3600.0, marginal), None);
    }

    #[test]
    fn a_dip_costs_evidence_but_does_not_restart_the_test() {
        // 3 s at logit 7 (15 in S), 1 s at p̂ = 0.5 (−2), then logit 7 again: 20 is reached
        // 1.4 s into the second run, sooner than the 4 s a fresh start needs.
        let p7 = 1.0 / (1.0 + (-7.0f64).exp());
        let mut evidence = CriticalEvidence::default();
        let mut critical_at = None;
        for i in 0..=200 {
            let t = i as f64 * 0.1;
            let p = if (3.0..4.0).contains(&(t - 0.05)) {
                0.5
            } else {
                p7
            };
            if evidence.update(&TEST, &input(t, p)) {
                critical_at = Some(t);
                break;
            }
        }
        let at = critical_at.expect("critical");
        assert!((at - 5.4).abs() < 0.11, "critical at {at}");
    }

    #[test]
    fn a_probability_that_does_not_count_only_lowers_the_evidence() {
        let mut evidence = CriticalEvidence::default();
        for i in 0..100 {
            let critical = evidence.update(
                &TEST,
                &CriticalInput {
                    probability_counts: false,
                    ..input(f64::from(i), 0.999_999)
                },
            );
            assert!(!critical);
        }
        assert_eq!(evidence.accumulated(), 0.0);
    }

    #[test]
    fn decisive_evidence_is_critical_once_held_beyond_the_gate_long_enough() {
        let mut evidence = CriticalEvidence::default();
        let at = |time_s, nis| CriticalInput {
            nis,
            ..input(time_s, 0.0)
        };
        // Beyond the gate from 10 s, a dip below it at 12 s restarts the hold: critical at 16 s.
        let critical: Vec<bool> = [(9.0, 99.0), (10.0, 100.0), (11.0, 400.0), (12.0, 50.0)]
            .into_iter()
            .chain((13..=16).map(|t| (f64::from(t), 150.0)))
            .map(|(t, nis)| evidence.update(&TEST, &at(t, nis)))
            .collect();
        assert_eq!(
            critical,
            [false, false, false, false, false, false, false, true]
        );
    }

    #[test]
    fn a_fix_that_came_back_to_the_track_it_left_starts_a_new_hold() {
        // Rows at 1 Hz beyond the gate (decisive after 3 s), each measured from anchors the row
        // before placed (age 1 s), as before the anchors are trusted.
        let at = |time_s: f64, offset_m| CriticalInput {
            nis: 2800.0,
            anchors_age_s: 1.0,
            offset_m,
            ..input(time_s, 0.0)
        };
        let run = |offsets: &[[f64; 2]]| {
            let mut evidence = CriticalEvidence::default();
            (0..offsets.len())
                .map(|i| evidence.update(&TEST, &at(10.0 + i as f64, offsets[i])))
                .collect::<Vec<_>>()
        };
        // A fix running away from the vehicle holds its offset through the placements.
        let away = [[60.0, 190.0], [40.0, 120.0], [65.0, 180.0], [30.0, 95.0]];
        assert_eq!(run(&away), [false, false, false, true]);
        // A fix that swings back and forth is back on its track every other row: never held.
        let swinging = [
            [59.0, 0.0],
            [-59.0, 0.0],
            [58.0, 1.0],
            [-58.0, -1.0],
            [59.0, 0.0],
        ];
        assert_eq!(run(&swinging), [false; 5]);
        // Anchors that stood through the hold keep it, whichever way the offset turns.
        let mut evidence = CriticalEvidence::default();
        let standing: Vec<bool> = swinging
            .iter()
            .enumerate()
            .map(|(i, &offset_m)| {
                let time_s = 10.0 + i as f64;
                let input = CriticalInput {
                    anchors_age_s: 60.0 + i as f64,
                    ..at(time_s, offset_m)
                };
                evidence.update(&TEST, &input)
            })
            .collect();
        assert_eq!(standing, [false, false, false, true, true]);
    }

    #[test]
    fn clearing_forgets_the_evidence_but_not_the_clock() {
        let mut evidence = CriticalEvidence::default();
        let p7 = 1.0 / (1.0 + (-7.0f64).exp());
        for t in 0..3 {
            evidence.update(&TEST, &input(f64::from(t), p7));
        }
        assert!(evidence.accumulated() > 9.0);
        evidence.clear();
        assert_eq!(evidence.accumulated(), 0.0);
        evidence.update(&TEST, &input(3.0, p7));
        assert!((evidence.accumulated() - 5.0).abs() < 1e-2);
    }

    #[test]
    fn validation_names_the_field() {
        let bad = |test: CriticalTest| test.validate().unwrap_err().0;
        assert_eq!(
            bad(CriticalTest {
                reference_logit: f64::NAN,
                ..TEST
            }),
            "reference_logit"
        );
        assert_eq!(
            bad(CriticalTest {
                threshold: 0.0,
                ..TEST
            }),
            "threshold"
        );
        assert_eq!(
            bad(CriticalTest {
                decisive_s: -1.0,
                ..TEST
            }),
            "decisive_s"
        );
        assert_eq!(bad(CriticalTest { gate: 4.0, ..TEST }), "gate");
        assert_eq!(
            bad(CriticalTest {
                frozen_fix_s: Some(f64::NAN),
                ..TEST
            }),
            "frozen_fix_s"
        );
        let jump = |gate, hold_s| CriticalTest {
            held_jump: Some(HeldOffsetTest { gate, hold_s }),
            ..TEST
        };
        assert_eq!(bad(jump(4.0, 2.0)), "held_jump.gate");
        assert_eq!(bad(jump(100.0, f64::INFINITY)), "held_jump.hold_s");
        assert!(jump(100.0, 2.0).validate().is_ok());
        let held = CriticalTest {
            held_offset: Some(HeldOffsetTest {
                gate: 100.0,
                hold_s: -1.0,
            }),
            ..TEST
        };
        assert_eq!(bad(held), "held_offset.hold_s");
        assert!(TEST.validate().is_ok());
    }

    #[test]
    fn a_held_jump_is_critical_once_held_long_enough_beyond_its_gate() {
        // p̂ weak and the NIS far below the decisive path's gate: only the held jump can escalate.
        let test = CriticalTest {
            gate: 1600.0,
            held_jump: Some(HeldOffsetTest {
                gate: 49.0,
                hold_s: 2.0,
            }),
            ..TEST
        };
        let jump = |held: Option<f64>, nis: f64| CriticalInput {
            nis,
            held_jump_s: held,
            ..input(0.0, 0.5)
        };
        let critical = |input| CriticalEvidence::default().update(&test, &input);
        assert!(!critical(jump(Some(1.9), 64.0)), "not held long enough");
        assert!(critical(jump(Some(2.0), 64.0)));
        assert!(critical(jump(Some(2.0), 49.0)));
        assert!(
            !critical(jump(Some(30.0), 48.9)),
            "no longer beyond its gate"
        );
        assert!(!critical(jump(None, 64.0)), "built up, not a jump");
        // Without the path (artifacts before it) the same jump escalates nothing.
        assert!(!CriticalEvidence::default().update(&TEST, &jump(Some(600.0), 99.0)));
        let json = serde_json::to_value(TEST).expect("serialises");
        assert!(json.get("held_jump").is_none());
        let json = serde_json::to_value(test).expect("serialises");
        assert_eq!(json["held_jump"]["gate"], 49.0);
        assert_eq!(json["held_jump"]["hold_s"], 2.0);
    }

    #[test]
    fn a_held_jump_is_critical_by_its_arrival_step_where_the_test_has_that_path() {
        // The anchors' NIS (in levels still at their upper bound) is below every gate; the step
        // the jump arrived with, against the receiver's one-row noise, is not.
        let test = CriticalTest {
            gate: 1600.0,
            held_step: Some(HeldOffsetTest {
                gate: 100.0,
                hold_s: 2.0,
            }),
            ..TEST
        };
        let jump = |held: Option<f64>, arrival: f64| CriticalInput {
            nis: 30.0,
            held_jump_s: held,
            held_step_nis: arrival,
            ..input(0.0, 0.5)
        };
        let critical = |input| CriticalEvidence::default().update(&test, &input);
        assert!(critical(jump(Some(2.0), 100.0)));
        assert!(!critical(jump(Some(1.9), 400.0)), "not held long enough");
        assert!(!critical(jump(Some(8.0), 99.9)), "a step a receiver makes");
        assert!(!critical(jump(None, 400.0)), "no longer held");
        // The anchors' held-jump path does not read the arrival, nor this path the anchors' NIS.
        let anchors_only = CriticalTest {
            held_jump: Some(HeldOffsetTest {
                gate: 100.0,
                hold_s: 2.0,
            }),
            ..TEST
        };
        assert!(!CriticalEvidence::default().update(&anchors_only, &jump(Some(8.0), 400.0)));
        assert!(!critical(CriticalInput {
            nis: 400.0,
            ..jump(Some(8.0), 0.0)
        }));
        let json = serde_json::to_value(test).expect("serialises");
        assert_eq!(json["held_step"]["gate"], 100.0);
        assert!(
            serde_json::to_value(TEST)
                .expect("serialises")
                .get("held_step")
                .is_none()
        );
        let bad = CriticalTest {
            held_step: Some(HeldOffsetTest {
                gate: 4.0,
                hold_s: 2.0,
            }),
            ..TEST
        };
        assert_eq!(
            bad.validate().map_err(|(field, _)| field),
            Err("held_step.gate")
        );
    }

    #[test]
    fn a_frozen_fix_held_long_enough_is_critical_at_once_where_the_test_has_the_path() {
        // p̂ weak, NIS below the gate: only the frozen fix's hold can make the sample critical.
        let frozen = |held: f64| CriticalInput {
            nis: 30.0,
            frozen_fix_s: Some(held),
            ..input(0.0, 0.5)
        };
        let with_path = CriticalTest {
            frozen_fix_s: Some(2.0),
            ..TEST
        };
        let mut evidence = CriticalEvidence::default();
        assert!(!evidence.update(&with_path, &frozen(1.9)));
        assert!(evidence.update(&with_path, &frozen(2.0)));
        assert!(
            !evidence.update(&with_path, &input(0.0, 0.5)),
            "no frozen fix"
        );
        // Without the path (artifacts before it) the same hold escalates nothing.
        assert!(!CriticalEvidence::default().update(&TEST, &frozen(600.0)));
        // The path is written only when the test has it.
        let json = serde_json::to_value(TEST).expect("serialises");
        assert!(json.get("frozen_fix_s").is_none());
        assert_eq!(
            serde_json::to_value(with_path).expect("serialises")["frozen_fix_s"],
            2.0
        );
    }

    #[test]
    fn an_offset_held_long_enough_is_critical_however_it_arrived() {
        let test = CriticalTest {
            gate: 1600.0,
            held_offset: Some(HeldOffsetTest {
                gate: 100.0,
                hold_s: 30.0,
            }),
            ..TEST
        };
        let held = |held: Option<f64>, nis: f64| CriticalInput {
            nis,
            held_offset_s: held,
            ..input(0.0, 0.5)
        };
        let critical = |input| CriticalEvidence::default().update(&test, &input);
        assert!(!critical(held(Some(29.0), 400.0)), "not held long enough");
        assert!(critical(held(Some(30.0), 100.0)));
        assert!(!critical(held(Some(60.0), 99.0)), "below its gate now");
        assert!(
            !critical(held(None, 400.0)),
            "not held beyond the decisive gate"
        );
        // The held-jump path does not count a built-up offset, nor this path a jump's own hold.
        assert!(!critical(CriticalInput {
            held_jump_s: Some(60.0),
            ..held(None, 400.0)
        }));
        assert!(!CriticalEvidence::default().update(&TEST, &held(Some(600.0), 99.0)));
    }

    #[test]
    fn names_round_trip() {
        for severity in Severity::ALL {
            assert_eq!(Severity::from_name(severity.name()), Some(severity));
        }
        assert_eq!(Severity::from_name("page"), None);
        assert!(Severity::Critical > Severity::Warning);
    }
}
