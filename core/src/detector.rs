//! The streaming per-vehicle detector: evidence → scaled ξ → HO-LLN step → persistence alarm.
//! The offline whole-trajectory pass (`run_records`) is this same step in a loop.
//!
//! Owns running a model artifact on a stream (one vehicle, one sample at a time), and the stream's
//! state as a value ([`DetectorState`]) that can be stored and continued elsewhere, bit for bit.
//! Must not train, score metrics or choose operating points.

use std::cell::RefCell;
use std::sync::Arc;

use serde::{Deserialize, Serialize};

use crate::alarm::PersistenceAlarm;
use crate::evidence::offset::DECISIVE_GATE;
use crate::evidence::{DriftChannelsDiffer, Evidence, EvidenceBuilder, Features};
use crate::explain::{Explanation, FROZEN_FIX_S};
use crate::lifecycle::{AlarmLifecycle, LifecycleInput, OffsetSignal};
use crate::model::artifact::ModelArtifact;
use crate::model::{LiquidState, StepScratch};
use crate::receiver::{FlagCorroboration, FlagSignal};
use crate::sample::{Record, Sample};
use crate::severity::{Escalation, Severity};

/// The detector's verdict on one sample.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Decision {
    pub evidence: Evidence,
    /// Scaled ξ_t fed to the model.
    pub features: Features,
    /// Spoofing probability p̂_t.
    pub probability: f64,
    /// c_t = 1[p̂_t ≥ θ].
    pub positive: bool,
    /// Persistence-confirmed alarm c̄_t.
    pub alarm: bool,
    /// The confirmed alarm started at this sample (0 → 1).
    pub alarm_onset: bool,
    /// The confirmed alarm ended at this sample (1 → 0).
    pub alarm_end: bool,
    /// The open alarm's severity (§7.4); `None` while no alarm is open. Models without a
    /// critical test raise warnings only.
    pub severity: Option<Severity>,
    /// The alarm turned critical at this sample (at its onset, or later in the episode).
    pub escalation: bool,
    /// Why: the dominant evidence, the offset from the anchor and the drift rate.
    pub explanation: Explanation,
}

thread_local! {
    /// One step's intermediate activations, shared by every detector stepped on this thread: a
    /// vehicle's detector keeps only what carries over between samples (a server holds one per
    /// vehicle, and the activations would be most of its memory). Every buffer is written before
    /// it is read within a step, and [`Model::step`](crate::model::Model::step) resizes it per
    /// model, so sharing cannot change a result.
    static SCRATCH: RefCell<StepScratch> = RefCell::new(StepScratch::default());
}

/// Per-vehicle detector state over a shared, immutable model.
#[derive(Clone, Debug)]
pub struct Detector {
    artifact: Arc<ModelArtifact>,
    evidence: EvidenceBuilder,
    state: LiquidState,
    alarm: PersistenceAlarm,
    lifecycle: AlarmLifecycle,
    escalation: Escalation,
    flags: FlagCorroboration,
    alarm_on: bool,
    /// The previous sample's severity, to mark an escalation.
    severity: Option<Severity>,
}

impl Detector {
    pub fn new(artifact: Arc<ModelArtifact>) -> Self {
        Self {
            evidence: EvidenceBuilder::new(artifact.evidence),
            state: LiquidState::zeros(artifact.model.config()),
            alarm: PersistenceAlarm::new(artifact.operating_point.n_p),
            lifecycle: AlarmLifecycle::default(),
            escalation: Escalation::default(),
            flags: FlagCorroboration::default(),
            alarm_on: false,
            severity: None,
            artifact,
        }
    }

    /// Advances by one sample. `trajectory_break` forces a new trajectory (recorded sources only).
    pub fn step(&mut self, sample: &Sample, trajectory_break: bool) -> Decision {
        self.step_with_prior(sample, trajectory_break, false)
    }

    /// [`Detector::step`] with the fleet's prior: `in_incident_area` says the sample lies inside an
    /// open area incident (§11). The incident then counts as the receiver's spoofing flag does
    /// (§7.3), and p̂ ≥ θ opens the alarm after [`AREA_ON_S`](crate::lifecycle::AREA_ON_S) instead
    /// of T_on: evidence beside the vehicle's own, never a verdict.
    pub fn step_with_prior(
        &mut self,
        sample: &Sample,
        trajectory_break: bool,
        in_incident_area: bool,
    ) -> Decision {
        let evidence = self.evidence.push(sample, trajectory_break);
        if evidence.trajectory_start {
            // State resets once per trajectory (SPEC §1).
            self.state = LiquidState::zeros(self.artifact.model.config());
        }
        let features = self.artifact.scaler.transform(&evidence);
        let probability = SCRATCH.with_borrow_mut(|scratch| {
            self.artifact
                .model
                .step(&mut self.state, &features, evidence.delta_t, scratch)
        });
        let positive = probability >= self.artifact.operating_point.theta;
        let alarm = match &self.artifact.lifecycle {
            Some(lifecycle) => {
                let offset = offset_signal(&evidence);
                let flag = FlagSignal {
                    in_incident_area: in_incident_area && evidence.valid,
                    ..self.flags.update(
                        sample.timestamp_s,
                        evidence.valid,
                        evidence.trajectory_start,
                        sample.spoofing_state.flagged() || in_incident_area,
                        offset.displaced,
                    )
                };
                self.lifecycle.update_graded(
                    lifecycle,
                    self.artifact.critical.as_ref(),
                    &mut self.escalation,
                    &LifecycleInput {
                        time_s: sample.timestamp_s,
                        valid: evidence.valid,
                        trajectory_start: evidence.trajectory_start,
                        positive,
                        probability,
                        offset,
                        flag,
                    },
                )
            }
            None => self
                .alarm
                .update(positive, evidence.valid, evidence.trajectory_start),
        };
        let severity = match &self.artifact.lifecycle {
            Some(_) => self.escalation.severity(alarm),
            None => alarm.then_some(Severity::Warning),
        };
        let decision = Decision {
            evidence,
            features,
            probability,
            positive,
            alarm,
            alarm_onset: alarm && !self.alarm_on,
            alarm_end: !alarm && self.alarm_on,
            severity,
            escalation: severity == Some(Severity::Critical)
                && self.severity != Some(Severity::Critical),
            explanation: Explanation::of(&evidence, positive),
        };
        self.alarm_on = alarm;
        self.severity = severity;
        decision
    }
}

/// Seconds after an outage (a new trajectory) during which an offset that begins to be held cannot
/// open an alarm or page on its hold, however long it lasts: a receiver reacquiring converges over
/// seconds, by steps of metres that the young anchors, with little dead reckoning behind them, test
/// as held jumps. p̂, the decisive gate and the frozen-fix path still alarm and page.
pub const REACQUISITION_S: f64 = 30.0;

/// Seconds the track the anchors stand on must have lasted before a jump for its hold to page
/// (`OffsetEvidence::track_age_s`): twice the agreement that makes a first fix trusted
/// ([`TRUST_S`](crate::evidence::offset::TRUST_S)).
pub const JUMP_SETTLED_S: f64 = 10.0;

/// The lifecycle's reading of the offset evidence (nothing without offset channels). A fix that
/// has repeated exactly for [`FROZEN_FIX_S`] while the vehicle's own motion carried it beyond the
/// follow gate counts as an offset held from then on: a frozen feed on a moving vehicle is as
/// decisive as a jump, however slowly the vehicle moves away from it.
pub fn offset_signal(evidence: &Evidence) -> OffsetSignal {
    evidence.offset.map_or(OffsetSignal::default(), |o| {
        let beyond_gate = (o.max_nis() >= DECISIVE_GATE).then_some(o.held_s);
        let frozen_fix = evidence
            .drift
            .filter(|d| d.stale_fix_s >= FROZEN_FIX_S && o.displaced())
            .map(|d| d.stale_fix_s - FROZEN_FIX_S);
        OffsetSignal {
            held_s: match (beyond_gate, frozen_fix) {
                (Some(a), Some(b)) => Some(a.max(b)),
                (a, b) => a.or(b),
            },
            displaced: o.displaced(),
            anchored: true,
            nis: o.max_nis(),
            anchors_age_s: o.anchor_age_s,
            offset_m: o.offset_m,
            frozen_fix_s: frozen_fix,
            // A held jump pages only from a track the anchors had stood on for a while before it
            // (a fix placed on a reflection makes the next true fix look like a jump; anchors
            // placed by a spike that came back resume the track once they agree), and counts only
            // the seconds that confirmed it, moving or with a new fix (a receiver that latches a
            // reflected fix as the vehicle stops repeats it for the whole stop).
            held_jump_s: (o.arrived_by_step
                && o.held_step_m.is_some()
                && o.track_age_s - o.held_s >= JUMP_SETTLED_S)
                .then_some(beyond_gate.map(|held| held.min(o.held_step_confirmed_s)))
                .flatten(),
            held_step_nis: o.held_step_nis,
            // When the offset now held began: the track's age less its hold.
            reacquiring: evidence.trajectory > 0 && o.track_age_s - o.held_s < REACQUISITION_S,
            disputed: o.disputed,
        }
    })
}

/// Everything a [`Detector`] carries from one sample to the next, without the model: evidence
/// builder (drift calibration included), liquid state (h, v), persistence run, lifecycle, the
/// receiver flag's memory and alarm flag. Continuing from it with [`Detector::restore`] gives the
/// outputs of an uninterrupted detector. Its encoding is positional (a session snapshot's): a new
/// field anywhere inside it is a new snapshot schema.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct DetectorState {
    evidence: EvidenceBuilder,
    liquid: LiquidState,
    alarm: PersistenceAlarm,
    #[serde(default)]
    lifecycle: AlarmLifecycle,
    alarm_on: bool,
    #[serde(default)]
    flags: FlagCorroboration,
    #[serde(default)]
    escalation: Escalation,
}

/// Why a [`DetectorState`] cannot continue under a model.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum RestoreError {
    /// The state was made by a model with (or without) the drift channels, and this one differs.
    #[error(
        "the state {} drift evidence, the model {}",
        if *.in_snapshot { "has" } else { "has no" },
        if *.in_snapshot { "has none" } else { "needs it" }
    )]
    DriftChannels { in_snapshot: bool },
    /// The liquid state's width is not the model's d_h.
    #[error("the liquid state has width {found}, the model needs {expected}")]
    StateWidth { expected: usize, found: usize },
    /// The persistence N_p differs from the model's operating point.
    #[error("the alarm persistence is N_p = {found}, the model's is {expected}")]
    Persistence { expected: u32, found: u32 },
}

impl From<DriftChannelsDiffer> for RestoreError {
    fn from(differ: DriftChannelsDiffer) -> Self {
        Self::DriftChannels {
            in_snapshot: differ.in_snapshot,
        }
    }
}

impl Detector {
    /// The state to continue from (see [`DetectorState`]).
    pub fn save(&self) -> DetectorState {
        DetectorState {
            evidence: self.evidence.clone(),
            liquid: self.state.clone(),
            alarm: self.alarm.clone(),
            lifecycle: self.lifecycle,
            alarm_on: self.alarm_on,
            flags: self.flags,
            escalation: self.escalation,
        }
    }

    /// A detector of `artifact` continuing from `saved`. The state must fit the model (drift
    /// channels, d_h, N_p); the caller checks that it is the same model.
    pub fn restore(
        artifact: Arc<ModelArtifact>,
        saved: DetectorState,
    ) -> Result<Self, RestoreError> {
        let config = artifact.model.config();
        if !saved.liquid.fits(config) {
            return Err(RestoreError::StateWidth {
                expected: config.d_h,
                found: saved.liquid.h().len().max(saved.liquid.v().len()),
            });
        }
        let n_p = artifact.operating_point.n_p;
        if saved.alarm.n_p() != n_p {
            return Err(RestoreError::Persistence {
                expected: n_p,
                found: saved.alarm.n_p(),
            });
        }
        let severity = match &artifact.lifecycle {
            Some(_) => saved.escalation.severity(saved.alarm_on),
            None => saved.alarm_on.then_some(Severity::Warning),
        };
        Ok(Self {
            evidence: EvidenceBuilder::restore(artifact.evidence, saved.evidence)?,
            state: saved.liquid,
            alarm: saved.alarm,
            lifecycle: saved.lifecycle,
            escalation: saved.escalation,
            flags: saved.flags,
            alarm_on: saved.alarm_on,
            severity,
            artifact,
        })
    }
}

/// Runs a fresh detector over recorded rows (one vehicle), honouring the rows' trajectory breaks.
pub fn run_records(artifact: &Arc<ModelArtifact>, records: &[Record]) -> Vec<Decision> {
    let mut detector = Detector::new(Arc::clone(artifact));
    records
        .iter()
        .map(|r| detector.step(&r.sample, r.trajectory_break))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::evidence::drift::DriftEvidence;
    use crate::evidence::offset::{FOLLOW_GATE, OffsetEvidence};

    /// A valid sample's evidence with the given fix age and the larger anchor NIS.
    fn evidence(stale_fix_s: f64, nis: f64, held_s: f64) -> Evidence {
        Evidence {
            valid: true,
            offset: Some(OffsetEvidence {
                nis: [nis, 0.0],
                held_s,
                ..OffsetEvidence::EMPTY
            }),
            ..Evidence::invalid(
                0,
                false,
                1.0,
                Some(DriftEvidence {
                    stale_fix_s,
                    ..DriftEvidence::EMPTY
                }),
            )
        }
    }

    #[test]
    fn a_frozen_fix_carried_beyond_the_follow_gate_is_held_from_two_seconds() {
        // Beyond the decisive gate: the offset's own hold.
        let held = offset_signal(&evidence(0.0, DECISIVE_GATE, 3.0));
        assert_eq!(held.held_s, Some(3.0));
        assert!(held.displaced);
        // Repeated for 5 s and beyond the follow gate: held for 5 − 2 = 3 s, the larger of both.
        let frozen = offset_signal(&evidence(5.0, FOLLOW_GATE, 0.0));
        assert_eq!(frozen.held_s, Some(5.0 - FROZEN_FIX_S));
        assert_eq!(
            offset_signal(&evidence(5.0, DECISIVE_GATE, 1.0)).held_s,
            Some(3.0)
        );
        // A repeated fix the vehicle's motion has not carried beyond the gate (a standing vehicle),
        // or one repeated for less than 2 s (a logger faster than its receiver), is no evidence.
        assert_eq!(offset_signal(&evidence(60.0, 1.0, 0.0)).held_s, None);
        assert_eq!(offset_signal(&evidence(1.5, FOLLOW_GATE, 0.0)).held_s, None);
    }

    #[test]
    fn only_an_offset_that_arrived_in_one_step_and_is_held_counts_as_a_held_jump() {
        let with = |arrived_by_step: bool, held_step_m: Option<[f64; 2]>, nis: f64| {
            let mut e = evidence(0.0, nis, 4.0);
            if let Some(offset) = e.offset.as_mut() {
                offset.arrived_by_step = arrived_by_step;
                offset.held_step_m = held_step_m;
                offset.held_step_confirmed_s = 4.0;
                offset.track_age_s = 60.0;
            }
            offset_signal(&e)
        };
        let jump = with(true, Some([20.0, 0.0]), 64.0);
        assert_eq!((jump.held_jump_s, jump.held_s), (Some(4.0), Some(4.0)));
        // Built up, not a jump: held as an offset only.
        let built_up = with(false, None, 64.0);
        assert_eq!((built_up.held_jump_s, built_up.held_s), (None, Some(4.0)));
        // Arrived in one step on a vehicle whose dead reckoning cannot carry a held jump.
        assert_eq!(with(true, None, 64.0).held_jump_s, None);
        // Back below the decisive gate.
        assert_eq!(with(true, Some([20.0, 0.0]), 20.0).held_jump_s, None);
    }

    #[test]
    fn a_held_jump_counts_the_seconds_moved_from_anchors_that_had_stood() {
        let jump = |track_age_s: f64, confirmed_s: f64| {
            let mut e = evidence(0.0, 400.0, 6.0);
            if let Some(offset) = e.offset.as_mut() {
                offset.arrived_by_step = true;
                offset.held_step_m = Some([20.0, 0.0]);
                offset.held_step_confirmed_s = confirmed_s;
                offset.track_age_s = track_age_s;
                // The anchors themselves were placed again since (a spike that came back): the
                // track they stand on is what counts.
                offset.anchor_age_s = 1.0;
            }
            offset_signal(&e)
        };
        // Held 6 s, the vehicle moving for 5 of them, from anchors placed 14 s before the jump.
        assert_eq!(jump(20.0, 5.0).held_jump_s, Some(5.0));
        // The jump arrived 10 s after the anchors were placed: it counts; 9 s: it does not (the
        // anchors may stand on a reflected fix). The offset's own hold counts either way.
        assert_eq!(jump(16.0, 6.0).held_jump_s, Some(6.0));
        assert_eq!(jump(15.0, 6.0).held_jump_s, None);
        assert_eq!(jump(15.0, 6.0).held_s, Some(6.0));
        // A vehicle standing since the jump: held, but never for a page.
        assert_eq!(jump(60.0, 0.0).held_jump_s, Some(0.0));
    }

    #[test]
    fn an_offset_that_began_while_the_receiver_reacquired_cannot_page_on_its_hold() {
        let at = |trajectory: u32, track_age_s: f64, held_s: f64| {
            let mut e = evidence(0.0, 64.0, held_s);
            e.trajectory = trajectory;
            if let Some(offset) = e.offset.as_mut() {
                offset.track_age_s = track_age_s;
                offset.anchor_age_s = 1.0;
            }
            offset_signal(&e).reacquiring
        };
        // The session's first anchors: a jump 15 s into the session pages on its hold.
        assert!(!at(0, 20.0, 5.0));
        // After an outage: the offset began 15 s after the anchors were placed there, and it still
        // cannot page 40 s later; one that began 30 s after them can.
        assert!(at(1, 20.0, 5.0));
        assert!(at(1, 55.0, 40.0));
        assert!(!at(1, 50.0, 20.0));
    }

    #[test]
    fn a_held_jump_keeps_the_fix_displaced_and_explains_itself_with_its_own_offset() {
        let mut e = evidence(0.0, 1.0, 0.0);
        if let Some(offset) = e.offset.as_mut() {
            offset.offset_m = [3.0, 0.0];
            offset.held_step_m = Some([20.0, -1.0]);
        }
        assert!(offset_signal(&e).displaced);
        // Below the decisive gate the held jump keeps the fix displaced but has no hold to page on.
        assert_eq!(offset_signal(&e).held_jump_s, None);
        let why = Explanation::of(&e, false);
        assert_eq!(why.dominant, crate::explain::EvidenceKind::HeldOffset);
        assert_eq!(why.offset_m, [20.0, -1.0]);
    }
}
