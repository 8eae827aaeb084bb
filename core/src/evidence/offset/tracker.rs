//! The offset channels' step: moves a vehicle's anchors by one step and tests the offsets.
//!
//! Owns [`OffsetTracker`]'s behaviour: `push` as its named steps (the reappearance after a gap,
//! a jump let go, the anchors' test, the shadows, the levels' row, the trust, the held offset,
//! the shares), and the anchors' placing. Must not compute the residual or the onboard
//! calibration (the builder hands them in), scale features or alarm.

use super::anchors::{Anchor, gap_variance};
use super::held_jump::{RETURN_SHARE, StepHold};
use super::misfit::POPULATION_LOG_LEVEL;
use super::params::{
    AGREEMENT_S, ANCHOR_COUNT, DECISIVE_GATE, DISPUTED_PLACEMENTS, FOLLOW_GATE, FOLLOW_S,
    LEVEL_COUNT, LEVEL_RANGE, OffsetEvidence, OffsetParams, OffsetStep, REACQUISITION_M2, SHARE_S,
    STEP_GROWTH_S, STEP_LEVEL, TRUST_S, along, nis, norm_squared,
};
use super::state::{AnchorPoint, LEVEL_SNAPSHOTS, LevelSnapshot, OffsetTracker};
use crate::evidence::MAX_GAP_S;
use crate::evidence::calibration::calibration_covariance;
use crate::evidence::linalg::Mat2;

/// What one row is tested against, fixed before any anchor moves.
struct Row {
    /// c² of the step's calibration state, per anchor.
    growth: [f64; ANCHOR_COUNT],
    /// The levels this row applies ([`OffsetTracker::levels`]).
    levels: [f64; LEVEL_COUNT],
    /// The misfits in use (1 without vehicle levels).
    misfits: [f64; ANCHOR_COUNT],
    /// The variance a telemetry gap before this row adds (m² per axis).
    gap_m2: f64,
    /// One row's residual variance in the vehicle's level: the step test's noise (m²).
    step_test_m2: f64,
    /// The calibration in use's error (`OffsetStep::calibration_error`), and its share of this
    /// one step's residual (m²).
    calibration_error: [f64; 3],
    step_share: Mat2,
    /// The residual is a one-row outlier.
    outlier: bool,
    /// The vehicle's dead reckoning can carry an anchor (its misfit is within the level's bound).
    dead_reckoning_carries: bool,
    /// How far a receiver that reacquired may still be off, or step (m² per axis): what the slow
    /// anchor has not yet forgotten of its placement's uncertainty, up to [`REACQUISITION_M2`].
    /// Every anchor's test and the change since a freeze allow for it.
    reacquisition_m2: f64,
}

/// The anchors' test of one row.
struct AnchorTest {
    /// In the vehicle's level, per anchor.
    nis: [f64; ANCHOR_COUNT],
    /// In the population's level, per anchor and for the one-row residual (the levels learn them).
    population_nis: [f64; LEVEL_COUNT],
    /// 1-σ of the slow anchor's offset under normal driving (m).
    sigma_m: f64,
}

impl OffsetTracker {
    /// A tracker at the start of a stream.
    pub fn new(params: &OffsetParams) -> Self {
        Self {
            params: *params,
            anchors: [Anchor::default(); ANCHOR_COUNT],
            shadows: [Anchor::default(); ANCHOR_COUNT],
            held_s: f64::NAN,
            arrived_by_step: false,
            share: [0.0; 2],
            levels: [1.0; LEVEL_COUNT],
            level_clock_s: 0.0,
            snapshots: [LevelSnapshot::default(); LEVEL_SNAPSHOTS],
            snapshot_count: 0,
            levels_in_use: [LEVEL_RANGE.1; LEVEL_COUNT],
            early_step: [0.0; 2],
            step_hold: None,
            after_spike: false,
            log_levels: [POPULATION_LOG_LEVEL; ANCHOR_COUNT],
            misfit_in_use: [1.0; ANCHOR_COUNT],
            age_s: 0.0,
            track_age_s: 0.0,
            returned_from_track_s: None,
            agreed_s: 0.0,
            disputes: 0,
            last: OffsetEvidence::EMPTY,
            point: None,
        }
    }

    /// `saved` (deserialised, without parameters) continuing under `params`.
    pub fn restore(params: &OffsetParams, saved: OffsetTracker) -> OffsetTracker {
        OffsetTracker {
            params: *params,
            ..saved
        }
    }

    /// Forgets the stream, as a new tracker of the same parameters.
    pub fn reset(&mut self) {
        *self = Self::new(&self.params);
    }

    /// A new anchor at the current fix after a break in the stream (a long outage, the source's
    /// new trajectory, time going backwards): the next offsets start from 0, with the GNSS noise
    /// and a reacquiring receiver's error ([`REACQUISITION_M2`]) as their uncertainty. The
    /// vehicle's levels are kept (they describe its receiver). Before any usable fix there is
    /// nothing to break from: the anchors keep what they were placed with (a session's first
    /// carry none), so a stream that opens with the source's break is tested as one without it.
    pub fn re_anchor(&mut self) {
        let placement_m2 = if self.point.is_some() {
            REACQUISITION_M2
        } else {
            self.reacquisition_m2()
        };
        self.share = [0.0; 2];
        self.agreed_s = 0.0;
        self.disputes = 0;
        self.re_anchor_keeping_levels(placement_m2);
        self.point = None;
    }

    /// Where the next step starts (`None` before the first usable sample and after a re-anchor).
    pub fn point(&self) -> Option<AnchorPoint> {
        self.point
    }

    /// The next step starts at `point` (the current usable sample).
    pub fn set_point(&mut self, point: AnchorPoint) {
        self.point = Some(point);
    }

    /// Some anchor is frozen: the fix disagrees with the vehicle's own motion, or agreed again for
    /// less than [`AGREEMENT_S`].
    pub fn frozen(&self) -> bool {
        self.anchors.iter().any(|a| a.frozen)
    }

    /// The channels of a sample that moves no anchor (unusable, or not later than the last one).
    pub fn hold(&self) -> OffsetEvidence {
        self.last
    }

    /// Moves the anchors by one step and tests the offsets.
    pub fn push(&mut self, step: &OffsetStep) -> OffsetEvidence {
        let levels = self.levels();
        if step.delta_t > MAX_GAP_S && self.reappears_as_expected(step, &levels) {
            // Back inside what the gap allows: a fresh anchor here (a tunnel is not a jump). Like
            // a session's first fix, the first fix after an outage is one unconfirmed fix (a
            // receiver reacquiring may be off by a reflection): it is trusted after TRUST_S of
            // agreement, and a disagreement before then places the anchors again. Its error, still
            // converging, stays in the anchors' uncertainty until they have followed it away.
            self.re_anchor_keeping_levels(REACQUISITION_M2);
            self.agreed_s = 0.0;
            self.disputes = 0;
            return self.last;
        }
        let row = self.row(step, levels);
        let after_spike = std::mem::replace(&mut self.after_spike, row.outlier);
        if row.outlier && self.let_go(step, &row, after_spike) {
            return self.last;
        }
        self.advance_step_hold(step, &row);
        let test = self.test_anchors(step, &row);
        let shadow_nis = self.follow_shadows(step, &row);
        self.learn_levels(&test.population_nis, &shadow_nis, step.delta_t);
        self.age_s += step.delta_t;
        self.track_age_s += step.delta_t;

        let max_nis = test.nis[0].max(test.nis[1]);
        self.resume_track(row.outlier, max_nis);
        if self.agreed_s < TRUST_S && (row.outlier || max_nis >= FOLLOW_GATE) {
            return self.place_again(step, &test, max_nis);
        }
        self.agreed_s = (self.agreed_s + step.delta_t).min(TRUST_S);
        if self.agreed_s >= TRUST_S {
            self.disputes = 0;
        }
        self.hold_decisive(step, max_nis, &row, after_spike);
        self.count_share(max_nis, step.delta_t);
        self.last = self.evidence(step, &test);
        self.last
    }

    /// What this row is tested against.
    fn row(&self, step: &OffsetStep, levels: [f64; LEVEL_COUNT]) -> Row {
        let growth = if step.calibrated {
            self.params.calibrated_growth
        } else {
            self.params.raw_growth
        };
        let misfits = if self.params.vehicle_levels {
            self.misfit_in_use
        } else {
            [1.0; ANCHOR_COUNT]
        };
        let gap_m2 = if step.delta_t > MAX_GAP_S {
            gap_variance(step.delta_t)
        } else {
            0.0
        };
        // A one-row outlier stops every anchor at the last trusted fix before it moves them: a
        // spike comes back within the agreement time, a jump stays and is tested from there.
        let step_test_m2 = self.params.step_noise_m2 * levels[STEP_LEVEL];
        let step_share = calibration_covariance(step.motion, &step.calibration_error);
        // A receiver that reacquired converges by steps of up to its remaining error: such a step
        // is not an outlier (which would place untrusted anchors again, without the allowance).
        let reacquisition_m2 = self.reacquisition_m2();
        Row {
            growth,
            levels,
            misfits,
            gap_m2,
            step_test_m2,
            calibration_error: step.calibration_error,
            step_share,
            outlier: nis(step.residual, step_test_m2 + reacquisition_m2, &step_share)
                >= FOLLOW_GATE,
            // A held jump is tested against pure dead reckoning: on a vehicle whose dead
            // reckoning cannot carry an anchor (a misfit beyond the level's bound) it means
            // nothing.
            dead_reckoning_carries: misfits[ANCHOR_COUNT - 1] <= 1.0,
            // A receiver that held its first, unconverged fix while the vehicle stood releases it
            // in one step once the vehicle moves: the change since a freeze allows for it.
            reacquisition_m2,
        }
    }

    /// On an outlier row: whether the fix let go of a jump, so that the anchors were placed again
    /// here and the row tests nothing.
    fn let_go(&mut self, step: &OffsetStep, row: &Row, after_spike: bool) -> bool {
        let spike_came_back = after_spike && self.spike_came_back(step, row);
        if self
            .step_hold
            .is_some_and(|hold| hold.stepped_back(step.residual))
        {
            // The held jump stepped back to the track. A slow anchor still frozen kept the track
            // and goes on below; one that followed GNSS while the jump was held stands on the
            // false position: the anchors are placed again here.
            self.step_hold = None;
            if !self.anchors[ANCHOR_COUNT - 1].frozen {
                self.re_anchor_keeping_levels(0.0);
                return true;
            }
        }
        if self.returns(step) {
            // The fix stepped back to where the onboard motion says the vehicle is: the spoofer
            // let go. Trust GNSS again from here (the rest of the offset is dead-reckoning error).
            self.re_anchor_on_return(spike_came_back);
            return true;
        }
        false
    }

    /// Carries a held jump by this row's residual, and ends it where it no longer holds.
    fn advance_step_hold(&mut self, step: &OffsetStep, row: &Row) {
        if let Some(hold) = &mut self.step_hold
            && (!row.dead_reckoning_carries || !hold.advance(step))
        {
            self.step_hold = None;
        }
    }

    /// Moves each anchor (an outlier freezes it first) and tests its offset; an anchor at the
    /// follow gate freezes, a frozen one follows again after the agreement time.
    fn test_anchors(&mut self, step: &OffsetStep, row: &Row) -> AnchorTest {
        let delta_t = step.delta_t;
        let mut test = AnchorTest {
            nis: [0.0; ANCHOR_COUNT],
            population_nis: [0.0; LEVEL_COUNT],
            sigma_m: 0.0,
        };
        for (k, anchor) in self.anchors.iter_mut().enumerate() {
            if row.outlier && !anchor.frozen {
                anchor.freeze(delta_t);
            }
            let keep = if anchor.frozen {
                1.0
            } else {
                (-delta_t / FOLLOW_S[k]).exp()
            };
            anchor.advance(&self.params, step, keep, row.gap_m2);
            for axis in 0..2 {
                anchor.carried_since_freeze[axis] += step.motion[axis];
            }
            anchor.gap_since_freeze_m2 += row.gap_m2;
            anchor.frozen_s += delta_t;
            // The receiver's own unconverged error counts against every anchor, however quickly
            // this one forgot the fix it was placed on.
            let variance =
                anchor.variance(&self.params, k) + (row.reacquisition_m2 - anchor.gap_m2).max(0.0);
            let share = anchor.calibration_share(&row.calibration_error);
            test.population_nis[k] = nis(anchor.offset, variance, &share);
            // While frozen, a misfit vehicle's dead-reckoning error beyond the population's (as its
            // shadow shows it over one follow time) keeps growing, like a bias, with the time
            // since the freeze (a step's own row stays one row's noise).
            let bias_m2 = if anchor.frozen {
                let excess_m2 = (row.misfits[k] - 1.0) * self.shadows[k].variance(&self.params, k);
                excess_m2 * ((anchor.frozen_s - anchor.step_row_s) / FOLLOW_S[k]).powi(2)
            } else {
                0.0
            };
            test.nis[k] = nis(anchor.offset, variance * row.levels[k] + bias_m2, &share);
            if anchor.frozen {
                test.nis[k] = test.nis[k].max(change_nis(anchor, k, row, bias_m2));
            }
            if k == ANCHOR_COUNT - 1 {
                test.sigma_m = along(anchor.offset, variance * row.levels[k], &share).sqrt();
            }
            anchor.gate(test.nis[k], delta_t);
        }
        test.population_nis[STEP_LEVEL] =
            nis(step.residual, self.params.step_noise_m2, &row.step_share);
        test
    }

    /// Moves the never-frozen shadows and returns their NIS in the population's level. An anchor
    /// frozen because its offset grew to the gate (not by a step) goes on from its shadow once
    /// following would have agreed for the agreement time: the vehicle's own dead reckoning,
    /// followed as usual, finds nothing held (a frozen offset that only dead-reckoning error
    /// built, on a vehicle whose error the population's growth understates). A drift still under
    /// way keeps the shadow beyond the gate.
    fn follow_shadows(&mut self, step: &OffsetStep, row: &Row) -> [f64; ANCHOR_COUNT] {
        let delta_t = step.delta_t;
        let mut shadow_nis = [0.0; ANCHOR_COUNT];
        for (k, shadow) in self.shadows.iter_mut().enumerate() {
            shadow.advance(
                &self.params,
                step,
                (-delta_t / FOLLOW_S[k]).exp(),
                row.gap_m2,
            );
            shadow_nis[k] = nis(
                shadow.offset,
                shadow.variance(&self.params, k),
                &shadow.calibration_share(&row.calibration_error),
            );
            shadow.agreement_s = if shadow_nis[k] < FOLLOW_GATE * row.levels[k] {
                shadow.agreement_s + delta_t
            } else {
                0.0
            };
            let anchor = &mut self.anchors[k];
            if anchor.frozen && anchor.step_row_s == 0.0 && shadow.agreement_s >= AGREEMENT_S {
                *anchor = Anchor {
                    agreement_s: 0.0,
                    ..*shadow
                };
            }
        }
        shadow_nis
    }

    /// A row counts towards the vehicle's levels unless an offset has already been held beyond
    /// the decisive gate for the agreement time (something real, not the receiver's noise);
    /// towards its misfit unless that offset arrived in one step (a jump, not dead reckoning).
    fn learn_levels(
        &mut self,
        population_nis: &[f64; LEVEL_COUNT],
        shadow_nis: &[f64; ANCHOR_COUNT],
        delta_t: f64,
    ) {
        let held = !self.held_s.is_nan() && self.held_s >= AGREEMENT_S;
        if self.params.vehicle_levels && !(held && self.arrived_by_step) {
            self.update_levels(population_nis, shadow_nis, delta_t, !held);
        }
    }

    /// Before the anchors are trusted, a disagreement places them again here rather than hold it
    /// as an offset: a session's first fix, or the first after an outage, may be off (a
    /// reflection, a receiver still reacquiring). The row then reports either nothing (under
    /// calibration trust by the clock, as before) or, under trust from information, what it
    /// found: a fix that keeps moving unlike the vehicle (a drift from the moment of
    /// reacquisition) never earns the anchors' trust, and its rows must still show the
    /// disagreement, each counted beyond the follow gate in the shares, and the anchors are
    /// disputed once it disagreed again with anchors placed on itself.
    fn place_again(
        &mut self,
        step: &OffsetStep,
        test: &AnchorTest,
        max_nis: f64,
    ) -> OffsetEvidence {
        if step.reports_placements {
            self.disputes = self.disputes.saturating_add(1);
        }
        let found = step.reports_placements.then(|| {
            self.count_share(max_nis.max(FOLLOW_GATE), step.delta_t);
            self.evidence(step, test)
        });
        self.re_anchor_keeping_levels(0.0);
        self.agreed_s = 0.0;
        found.unwrap_or(self.last)
    }

    /// Counts the time beyond the decisive gate, and holds a jump that arrived in one step.
    fn hold_decisive(&mut self, step: &OffsetStep, max_nis: f64, row: &Row, after_spike: bool) {
        if max_nis < DECISIVE_GATE {
            self.held_s = f64::NAN;
            self.arrived_by_step = false;
            return;
        }
        if !self.held_s.is_nan() {
            self.held_s += step.delta_t;
            return;
        }
        self.held_s = 0.0;
        // Arrived in one step: beyond the gate now, and below the follow gate before.
        self.arrived_by_step = self.last.max_nis() < FOLLOW_GATE;
        if !self.arrived_by_step {
            return;
        }
        if let Some(hold) = &mut self.step_hold {
            // The fix came back within the follow gate since that jump arrived: the offset held
            // now is not the step it arrived with.
            hold.arrival_nis = 0.0;
        } else if row.dead_reckoning_carries {
            // The fix before this row was trusted (below the follow gate): the jump is this
            // row's residual, tested as the step test tests one row, unless the fix before it
            // left no followed track (see `StepHold::arrival_nis`).
            let left_track = !(self.last.frozen || step.leaves_held_fix || after_spike);
            self.step_hold = Some(StepHold {
                arrival: step.residual,
                offset: step.residual,
                held_s: 0.0,
                confirmed_s: 0.0,
                arrival_nis: if left_track {
                    nis(
                        step.residual,
                        row.step_test_m2 + row.reacquisition_m2,
                        &row.step_share,
                    )
                } else {
                    0.0
                },
            });
        }
    }

    /// The shares of the last ~10 s and ~60 s spent beyond the follow gate.
    fn count_share(&mut self, max_nis: f64, delta_t: f64) {
        let beyond = if max_nis >= FOLLOW_GATE { 1.0 } else { 0.0 };
        for (share, tau) in self.share.iter_mut().zip(SHARE_S) {
            let keep = (-delta_t / tau).exp();
            *share = keep * *share + (1.0 - keep) * beyond;
        }
    }

    /// The channels of this row.
    fn evidence(&self, step: &OffsetStep, test: &AnchorTest) -> OffsetEvidence {
        let slow = &self.anchors[ANCHOR_COUNT - 1];
        OffsetEvidence {
            offset_m: slow.offset,
            sigma_m: test.sigma_m,
            nis: test.nis,
            held_s: if self.held_s.is_nan() {
                0.0
            } else {
                self.held_s
            },
            share: self.share,
            frozen: self.anchors.iter().any(|a| a.frozen),
            arrived_by_step: self.arrived_by_step,
            carried_m: self.anchors.map(|a| norm_squared(a.carried).sqrt()),
            raw_carried_m: self.anchors.map(|a| norm_squared(a.carried_raw).sqrt()),
            offset_norm_m: self.anchors.map(|a| norm_squared(a.offset).sqrt()),
            calibrated: step.calibrated,
            anchor_age_s: self.age_s,
            track_age_s: self.track_age_s,
            held_step_m: self.step_hold.map(|hold| hold.offset),
            held_step_confirmed_s: self.step_hold.map_or(0.0, |hold| hold.confirmed_s),
            held_step_nis: self.step_hold.map_or(0.0, |hold| hold.arrival_nis),
            disputed: self.disputes >= DISPUTED_PLACEMENTS,
        }
    }

    /// After a gap: whether the fix reappears, on every anchor, inside the uncertainty the gap
    /// adds (the motion it may hide). Such a reappearance re-anchors; one far outside is evidence.
    fn reappears_as_expected(&self, step: &OffsetStep, levels: &[f64; LEVEL_COUNT]) -> bool {
        let gap_m2 = gap_variance(step.delta_t);
        self.anchors.iter().enumerate().all(|(k, anchor)| {
            let offset = [
                anchor.offset[0] + step.residual[0],
                anchor.offset[1] + step.residual[1],
            ];
            let mut moved = *anchor;
            moved.carry(step, 1.0);
            let variance = moved.variance(&self.params, k) + gap_m2;
            let share = moved.calibration_share(&step.calibration_error);
            nis(offset, variance * levels[k], &share) < FOLLOW_GATE
        })
    }

    /// Whether a one-row step brings a held offset back to within [`RETURN_SHARE`] of the frozen
    /// slow anchor: the fix returned to where the vehicle's own motion puts it.
    fn returns(&self, step: &OffsetStep) -> bool {
        let slow = &self.anchors[ANCHOR_COUNT - 1];
        let after = [
            slow.offset[0] + step.residual[0],
            slow.offset[1] + step.residual[1],
        ];
        !self.held_s.is_nan()
            && slow.frozen
            && norm_squared(after) <= RETURN_SHARE * RETURN_SHARE * norm_squared(slow.offset)
    }

    /// How far a receiver that reacquired after an outage may still be off (m² per axis): what
    /// the slow anchor has not yet forgotten of the uncertainty it was placed with, up to
    /// [`REACQUISITION_M2`]; 0 in a trajectory that began with the session. Every test allows
    /// for it. Anchors placed again within the trajectory start without it: what places them
    /// again (a NIS of 16 or more against a variance that includes it, so an offset of at least
    /// twice its 1-σ, 6 m at first) is more than a converging receiver closes, and a drift that
    /// starts as the receiver reacquires must not keep it.
    fn reacquisition_m2(&self) -> f64 {
        self.anchors[ANCHOR_COUNT - 1].gap_m2.min(REACQUISITION_M2)
    }

    /// Fresh anchors, trusted, at a fix that returned to where the frozen anchors' motion puts
    /// the vehicle. A one-row spike whose next fix is back where the fix before it was leaves
    /// no doubt about the track, and it goes on at once. Otherwise, within a quarter of the
    /// offset is not on the track: a multipath burst's return can still be metres off, and the
    /// next true fix then steps like a jump. So such anchors start a track of their own, which
    /// resumes the one they came back to once they have agreed for [`TRUST_S`]
    /// ([`OffsetTracker::resume_track`]).
    fn re_anchor_on_return(&mut self, on_track: bool) {
        let track_age_s = self.track_age_s;
        self.re_anchor_keeping_levels(0.0);
        if on_track {
            self.track_age_s = track_age_s;
        } else {
            self.returned_from_track_s = Some(track_age_s);
        }
    }

    /// Right after a one-row spike that arrived as a jump: whether this fix is back where the fix
    /// before the spike, carried by the vehicle's motion, puts it. The two rows' residuals are
    /// tested together as the step test tests one row: a reflection gone back, not a fix that
    /// lands nearer the dead reckoning than the track GNSS was on.
    fn spike_came_back(&self, step: &OffsetStep, row: &Row) -> bool {
        self.step_hold.is_some_and(|hold| {
            let over_both = [
                hold.offset[0] + step.residual[0],
                hold.offset[1] + step.residual[1],
            ];
            hold.held_s == 0.0
                && nis(
                    over_both,
                    row.step_test_m2 + row.reacquisition_m2,
                    &row.step_share,
                ) < FOLLOW_GATE
        })
    }

    /// After a return: a disagreement before [`TRUST_S`] leaves the anchors on a track of their
    /// own; that much agreement puts them back on the track they returned to, whose age goes on.
    fn resume_track(&mut self, outlier: bool, max_nis: f64) {
        let Some(track_age_s) = self.returned_from_track_s else {
            return;
        };
        if outlier || max_nis >= FOLLOW_GATE {
            self.returned_from_track_s = None;
        } else if self.age_s >= TRUST_S {
            self.track_age_s = track_age_s + self.age_s;
            self.returned_from_track_s = None;
        }
    }

    /// A fresh anchor at the current point, keeping the vehicle's levels, the shares and the
    /// trust (the fix is where the motion allows it to be). `placement_m2` (per axis) is how far
    /// the fix it stands on may be from the truth beyond the GNSS noise; like a gap's variance it is
    /// forgotten as the anchor follows.
    fn re_anchor_keeping_levels(&mut self, placement_m2: f64) {
        let placed = Anchor {
            gap_m2: placement_m2,
            ..Anchor::default()
        };
        self.anchors = [placed; ANCHOR_COUNT];
        self.shadows = [placed; ANCHOR_COUNT];
        self.held_s = f64::NAN;
        self.arrived_by_step = false;
        self.step_hold = None;
        self.after_spike = false;
        self.age_s = 0.0;
        self.track_age_s = 0.0;
        self.returned_from_track_s = None;
        self.last = OffsetEvidence {
            share: self.share,
            ..OffsetEvidence::EMPTY
        };
    }
}

/// A frozen anchor's change since the last trusted fix, against one row's noise growing with the
/// time and the distance since, and what a receiver that reacquired may still step.
fn change_nis(anchor: &Anchor, k: usize, row: &Row, bias_m2: f64) -> f64 {
    let change = [
        anchor.offset[0] - anchor.origin[0],
        anchor.offset[1] - anchor.origin[1],
    ];
    let step_variance = row.step_test_m2 * (1.0 + anchor.frozen_s / STEP_GROWTH_S)
        + row.misfits[k] * row.growth[k] * norm_squared(anchor.carried_since_freeze)
        + bias_m2
        + anchor.gap_since_freeze_m2
        + row.reacquisition_m2;
    nis(
        change,
        step_variance,
        &anchor.calibration_share_since_freeze(&row.calibration_error),
    )
}
