//! Evidence v3's offset channels (`docs/detector.md` §4.2): where GNSS puts the vehicle, against
//! where the vehicle's own motion says it is.
//!
//! Every rate channel sees the one-step residual r_t, a velocity: a jump of D metres is one large row
//! and then normal rows, and the offset it leaves is forgotten. Here each vehicle keeps
//! dead-reckoning *anchors*: the offset o = g − â of the GNSS fix g from the anchor â is the sum of
//! the residuals since a trusted fix, o_t = o_{t−1} + r_t. While the fix agrees, the anchor follows
//! GNSS slowly (o ← e^{−δ/T} o, one anchor per follow time T), so that normal dead-reckoning error
//! does not pile up; while the fix disagrees beyond a gate, the anchor stops following (it is frozen
//! at the last trusted fix) until the fix has agreed again for a while. The offset is tested
//! against its own uncertainty: a GNSS part R and a dead-reckoning part that grows with the net
//! distance the anchor has been carried (c²‖U‖², U the net dead-reckoned displacement, forgotten at
//! the same rate as o), plus, after a telemetry gap, the motion the gap may have hidden.
//!
//! A multipath spike goes out and comes back in one row; a jump goes out and stays. The channels
//! keep them apart by time: how long the offset has stayed beyond the decisive gate, and the share
//! of the last 10 s and 60 s it spent beyond the follow gate (a spoofer that toggles between the
//! false and the true position fills that share; one spike barely moves it).
//!
//! Owns the anchors, their uncertainty and the per-vehicle offset levels. Must not compute the
//! residual or the onboard calibration (the builder hands them in), scale features or alarm.

use serde::{Deserialize, Serialize};

use super::EvidenceError;
use crate::geo::LatLon;
use crate::sample::readable;

/// Anchors per vehicle, one per follow time constant.
pub const ANCHOR_COUNT: usize = 2;
/// Follow time constants T_k (s): the fast anchor forgets dead-reckoning error quickly and sees
/// steps at any speed; the slow one keeps offsets and drifts for minutes.
pub const FOLLOW_S: [f64; ANCHOR_COUNT] = [10.0, 120.0];
/// An anchor stops following when its normalised offset reaches this (a χ²₂ tail of 3.4e-4).
pub const FOLLOW_GATE: f64 = 16.0;
/// The offset counts as held ([`OffsetEvidence::held_s`]) beyond this (5σ, the autopilots' gate).
pub const DECISIVE_GATE: f64 = 25.0;
/// Seconds of agreement (below the follow gate) before a frozen anchor follows again.
pub const AGREEMENT_S: f64 = 5.0;
/// Seconds the fix and the onboard motion must agree after the anchors are placed before the
/// anchors are trusted: until then a disagreement places them again instead of freezing them.
pub const TRUST_S: f64 = 5.0;
/// A telemetry gap up to this long (s) carries the anchors across; a longer one re-anchors.
pub const MAX_CARRY_GAP_S: f64 = 300.0;
/// 1-σ of the unknown acceleration during a gap (m/s²): the motion a gap of δ seconds may hide is
/// ½·a·δ² per axis beyond the average of the velocities before and after it.
pub const GAP_ACCELERATION_MPS2: f64 = 0.5;
/// Time constants (s) of the share of time spent beyond the follow gate.
pub const SHARE_S: [f64; 2] = [10.0, 60.0];
/// The vehicle's offset level is taken from a snapshot at least this old (s of valid data), so
/// that a spoofer cannot teach the detector its own offsets quickly.
pub const LEVEL_DELAY_S: f64 = 120.0;
/// The vehicle's level is a running mean over about this long (s).
const LEVEL_MEMORY_S: f64 = 300.0;
/// Weight (s) of the population's level 1 in a vehicle's running mean.
const LEVEL_PRIOR_S: f64 = 120.0;
/// A vehicle's level stays within these multiples of the training population's. Until its own
/// level is known (the first snapshot old enough), a vehicle is taken to be as noisy as the bound
/// allows: a session's first minutes never alarm on a receiver noisier than the population's.
pub const LEVEL_RANGE: (f64, f64) = (0.25, 4.0);
/// A vehicle's level falls by at most a factor e every this many seconds.
const LEVEL_DECREASE_S: f64 = 60.0;
/// One row adds at most this much to the running mean of NIS/2 (so a spike cannot inflate it).
const LEVEL_ROW_CAP: f64 = 8.0;
/// A vehicle whose dead reckoning cannot carry an anchor (a poor compass, a reversing robot read
/// with an unsigned speed) shows anchor offsets far beyond the level bound for minutes on end. Its
/// misfit M is the level L whose NIS/2 ~ L·Exp(1) has the mean of ln(1 + NIS/2) seen on an anchor
/// that never freezes (a shadow), over the same memory and delay as the levels (a log mean, so one
/// jump barely moves it). Beyond the level's bound it scales the anchor's variance: the offset
/// channels stand down to what such a vehicle can support (a jump is still decisive on its row).
pub const MISFIT_MAX: f64 = 1e8;
/// Euler's γ: E₁(x) = −γ − ln x + Σ_{k≥1} (−1)^{k+1} x^k / (k·k!).
const EULER_GAMMA: f64 = 0.577_215_664_901_532_9;
/// The population's mean of ln(1 + NIS/2) (χ²₂ NIS: e·E₁(1)); the misfit's prior.
const POPULATION_LOG_LEVEL: f64 = 0.596_347_362_323_194;
/// Snapshot period of the levels (s of valid data).
const LEVEL_SNAPSHOT_S: f64 = 30.0;
const LEVEL_SNAPSHOTS: usize = (LEVEL_DELAY_S / LEVEL_SNAPSHOT_S) as usize + 2;
/// Levels per vehicle: one per anchor, then the one-row residual's (the step test's).
const LEVEL_COUNT: usize = ANCHOR_COUNT + 1;
const STEP_LEVEL: usize = ANCHOR_COUNT;
/// The step test's variance grows by one row's residual variance every this many seconds after
/// the freeze (the onboard noise accumulates; the GNSS part does not).
pub const STEP_GROWTH_S: f64 = 2.0;
/// Accepted range of the fitted GNSS part R (m² per axis).
pub const NOISE_RANGE_M2: (f64, f64) = (1e-4, 1e8);

/// Fitted on normal training rows; carried by the artifact inside the evidence parameters.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct OffsetParams {
    /// R_k: per-axis variance of anchor k's offset with no dead reckoning behind it (m²).
    pub noise_m2: [f64; ANCHOR_COUNT],
    /// c_k²: its growth per square metre of net dead-reckoned displacement, before the onboard
    /// calibration is warm (the raw onboard errors: a few degrees of heading bias).
    pub raw_growth: [f64; ANCHOR_COUNT],
    /// c_k² once the calibration is warm (the calibrated motion).
    pub calibrated_growth: [f64; ANCHOR_COUNT],
    /// Per-axis variance of one row's residual (m²): the step test's noise.
    pub step_noise_m2: f64,
    /// Normalise by the vehicle's own level; off only while fitting.
    pub vehicle_levels: bool,
}

impl OffsetParams {
    /// The widest noise and no growth, without vehicle levels: no anchor ever stops following, and
    /// the fit reads the raw offsets ([`OffsetEvidence::offset_norm_m`]) with it.
    pub fn unnormalised() -> Self {
        Self {
            noise_m2: [NOISE_RANGE_M2.1; ANCHOR_COUNT],
            raw_growth: [0.0; ANCHOR_COUNT],
            calibrated_growth: [0.0; ANCHOR_COUNT],
            step_noise_m2: NOISE_RANGE_M2.1,
            vehicle_levels: false,
        }
    }

    /// R ∈ [1e-4, 1e8] m² and c² ∈ [0, 1] (a dead-reckoning error as large as the distance is no
    /// onboard sensor); the error names the field.
    pub fn validate(&self) -> Result<(), EvidenceError> {
        let invalid =
            |field: &'static str, reason: String| EvidenceError::InvalidParams { field, reason };
        if let Some((field, &bad)) = self
            .noise_m2
            .iter()
            .map(|v| ("offset.noise_m2", v))
            .chain([("offset.step_noise_m2", &self.step_noise_m2)])
            .find(|(_, v)| !(NOISE_RANGE_M2.0..=NOISE_RANGE_M2.1).contains(*v))
        {
            return Err(invalid(
                field,
                format!(
                    "must be finite and in [{:e}, {:e}] m², got {}",
                    NOISE_RANGE_M2.0,
                    NOISE_RANGE_M2.1,
                    readable(bad)
                ),
            ));
        }
        for (field, growth) in [
            ("offset.raw_growth", &self.raw_growth),
            ("offset.calibrated_growth", &self.calibrated_growth),
        ] {
            if let Some(&bad) = growth.iter().find(|v| !(0.0..=1.0).contains(*v)) {
                return Err(invalid(
                    field,
                    format!("must be in [0, 1] per square metre, got {}", readable(bad)),
                ));
            }
        }
        Ok(())
    }
}

/// One step of the anchors, all east/north, from the last usable sample to this one.
#[derive(Clone, Copy, Debug)]
pub struct OffsetStep {
    /// GNSS displacement minus the (calibrated, once warm) onboard displacement (m).
    pub residual: [f64; 2],
    /// The onboard displacement (m).
    pub motion: [f64; 2],
    /// Seconds since the last usable sample, in (0, [`MAX_CARRY_GAP_S`]].
    pub delta_t: f64,
    /// The onboard calibration was warm (the residual is calibrated).
    pub calibrated: bool,
}

/// The offset channels of one sample.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct OffsetEvidence {
    /// o = g − â of the slow anchor, east/north (m): where GNSS puts the vehicle relative to where
    /// its own motion since the last trusted fix does.
    pub offset_m: [f64; 2],
    /// 1-σ per axis of that offset under normal driving (m).
    pub sigma_m: f64,
    /// ‖o_k‖²/σ_k² per anchor (fast, slow), in the vehicle's own level.
    pub nis: [f64; ANCHOR_COUNT],
    /// Seconds the larger NIS has stayed at or beyond [`DECISIVE_GATE`] without a break (0 on the
    /// row it first does, 0 below it).
    pub held_s: f64,
    /// Share of the last ~10 s and ~60 s (EWMAs) with a NIS at or beyond [`FOLLOW_GATE`].
    pub share: [f64; 2],
    /// Some anchor is frozen (the fix disagrees, or agreed again for less than [`AGREEMENT_S`]).
    pub frozen: bool,
    /// The offset now held reached the decisive gate within one step: a jump, not a build-up.
    pub arrived_by_step: bool,
    /// ‖U_k‖ per anchor: the net distance dead-reckoned with the warm calibration behind it (m).
    pub carried_m: [f64; ANCHOR_COUNT],
    /// The same for the distance dead-reckoned before the calibration was warm (m). Each part
    /// grows the uncertainty with its own c², and each is forgotten with the offset: an offset
    /// built from raw dead reckoning is still tested as one after the calibration warms up.
    pub raw_carried_m: [f64; ANCHOR_COUNT],
    /// ‖o_k‖ per anchor (m).
    pub offset_norm_m: [f64; ANCHOR_COUNT],
    /// The step was dead-reckoned with the warm onboard calibration.
    pub calibrated: bool,
    /// Seconds since the anchors were placed (at the stream's first fix, or after a long gap).
    pub anchor_age_s: f64,
    /// While a jump is held ([`StepHold`]): GNSS minus the dead reckoning from the last trusted
    /// fix before it, east/north (m).
    #[serde(default)]
    pub held_step_m: Option<[f64; 2]>,
}

impl OffsetEvidence {
    /// The channels before any usable sample.
    pub const EMPTY: Self = Self {
        offset_m: [0.0; 2],
        sigma_m: 0.0,
        nis: [0.0; ANCHOR_COUNT],
        held_s: 0.0,
        share: [0.0; 2],
        frozen: false,
        arrived_by_step: false,
        carried_m: [0.0; ANCHOR_COUNT],
        raw_carried_m: [0.0; ANCHOR_COUNT],
        offset_norm_m: [0.0; ANCHOR_COUNT],
        calibrated: false,
        anchor_age_s: 0.0,
        held_step_m: None,
    };

    /// The larger of the anchors' NIS.
    pub fn max_nis(&self) -> f64 {
        self.nis[0].max(self.nis[1])
    }

    /// The fix is displaced from an anchor beyond the follow gate, or a jump is still held.
    pub fn displaced(&self) -> bool {
        self.max_nis() >= FOLLOW_GATE || self.held_step_m.is_some()
    }
}

/// One anchor's state.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
struct Anchor {
    /// o: GNSS minus anchor (m).
    offset: [f64; 2],
    /// U: net displacement dead-reckoned with the warm calibration behind the anchor, forgotten
    /// with o (m).
    carried: [f64; 2],
    /// The same, dead-reckoned before the calibration was warm (m).
    carried_raw: [f64; 2],
    /// Variance a telemetry gap added (m² per axis), forgotten with o².
    gap_m2: f64,
    frozen: bool,
    /// Of `frozen_s`, the seconds of the row that froze it (a step's own row: one row's noise).
    step_row_s: f64,
    /// Seconds of agreement since the fix last disagreed (while frozen).
    agreement_s: f64,
    /// While frozen: o at the last trusted fix, and the time, motion and gap variance since.
    origin: [f64; 2],
    frozen_s: f64,
    carried_since_freeze: [f64; 2],
    gap_since_freeze_m2: f64,
}

impl Anchor {
    /// Moves the anchor by one step: U, the offset and the gaps' variance, each forgotten by
    /// `keep` (1 while frozen, the follow's share otherwise).
    fn advance(&mut self, step: &OffsetStep, keep: f64, gap_m2: f64) {
        self.carry(step, keep);
        for axis in 0..2 {
            self.offset[axis] = keep * (self.offset[axis] + step.residual[axis]);
        }
        self.gap_m2 = keep * keep * (self.gap_m2 + gap_m2);
    }

    /// Adds one step's onboard motion to the part of U it was dead-reckoned with, and forgets
    /// both parts by `keep`.
    fn carry(&mut self, step: &OffsetStep, keep: f64) {
        let (moved, kept) = if step.calibrated {
            (&mut self.carried, &mut self.carried_raw)
        } else {
            (&mut self.carried_raw, &mut self.carried)
        };
        for axis in 0..2 {
            moved[axis] = keep * (moved[axis] + step.motion[axis]);
            kept[axis] *= keep;
        }
    }

    /// The offset's per-axis variance under normal driving as anchor `k`, before the vehicle's
    /// level: R + c²_raw‖U_raw‖² + c²_cal‖U_cal‖² + the gaps' share (m²).
    fn variance(&self, params: &OffsetParams, k: usize) -> f64 {
        params.noise_m2[k]
            + params.raw_growth[k] * norm_squared(self.carried_raw)
            + params.calibrated_growth[k] * norm_squared(self.carried)
            + self.gap_m2
    }

    /// Stops following at the current offset (the last trusted fix).
    fn freeze(&mut self, step_row_s: f64) {
        self.frozen = true;
        self.step_row_s = step_row_s;
        self.agreement_s = 0.0;
        self.origin = self.offset;
        self.frozen_s = 0.0;
        self.carried_since_freeze = [0.0; 2];
        self.gap_since_freeze_m2 = 0.0;
    }
}

/// A held offset that one step brings back to within this share of itself ends: the spoofer let
/// go and the fix is back where the onboard motion puts the vehicle (a toggling spoofer's next
/// step away is a new jump from there).
pub const RETURN_SHARE: f64 = 0.25;

/// A jump is held at most this long (s) after it arrived: beyond it, the alarm rests on the
/// anchors' own test (a receiver that corrected itself by a step never steps back).
pub const MAX_STEP_HOLD_S: f64 = 600.0;

/// A jump that has not stepped back. The anchors test an offset against the dead-reckoning error
/// since the last trusted fix, which grows with the distance travelled: on a fast vehicle a held
/// 20 m offset is within it after a kilometre or two, and the anchors follow GNSS again. Whether
/// the fix is still displaced is then a choice between two places, not a test against zero: the
/// jump holds while GNSS, dead-reckoned from the fix before it, stays nearer the offset the jump
/// arrived with than the vehicle's own track. It ends when the fix steps back, when it drifts
/// nearer the track, after [`MAX_STEP_HOLD_S`], or when the anchors are placed again; a vehicle
/// whose dead reckoning misfits (beyond the level's bound) holds none.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
struct StepHold {
    /// The offset the jump arrived with (m).
    arrival: [f64; 2],
    /// GNSS minus the dead reckoning from the last trusted fix before the jump (m).
    offset: [f64; 2],
    /// Seconds since the jump.
    held_s: f64,
}

impl StepHold {
    /// Whether `offset` is nearer the vehicle's own track than the offset the jump arrived with.
    fn nearer_track(&self, offset: [f64; 2]) -> bool {
        let from_arrival = [offset[0] - self.arrival[0], offset[1] - self.arrival[1]];
        norm_squared(offset) <= norm_squared(from_arrival)
    }

    /// A one-row step that brings the fix nearer the track than the jump: the spoofer let go.
    fn stepped_back(&self, residual: [f64; 2]) -> bool {
        self.nearer_track([self.offset[0] + residual[0], self.offset[1] + residual[1]])
    }

    /// Adds one step's residual; returns whether the jump still holds.
    fn advance(&mut self, residual: [f64; 2], delta_t: f64) -> bool {
        for (offset, change) in self.offset.iter_mut().zip(residual) {
            *offset += change;
        }
        self.held_s += delta_t;
        self.held_s <= MAX_STEP_HOLD_S && !self.nearer_track(self.offset)
    }
}

/// The variance (m² per axis) of the motion a gap of `delta_t` seconds may hide: (½·a·δ²)².
fn gap_variance(delta_t: f64) -> f64 {
    let hidden = 0.5 * GAP_ACCELERATION_MPS2 * delta_t * delta_t;
    hidden * hidden
}

/// A level snapshot after `clock_s` seconds of valid data.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
struct LevelSnapshot {
    clock_s: f64,
    levels: [f64; LEVEL_COUNT],
    misfits: [f64; ANCHOR_COUNT],
}

/// The per-vehicle anchor state. Persists across the trajectory breaks of a stream (a gap up to
/// [`MAX_CARRY_GAP_S`] carries the anchors across); `push` never allocates.
///
/// Serialised (inside a session snapshot) it holds only the vehicle's state; the parameters come
/// back with [`OffsetTracker::restore`].
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct OffsetTracker {
    #[serde(skip, default = "OffsetParams::unnormalised")]
    params: OffsetParams,
    anchors: [Anchor; ANCHOR_COUNT],
    /// The same anchors never frozen: how far this vehicle's dead reckoning strays within each
    /// follow time, whatever the alarms did (the misfit learns from them).
    shadows: [Anchor; ANCHOR_COUNT],
    /// Seconds the larger NIS has been at or beyond the decisive gate (NaN below it).
    held_s: f64,
    arrived_by_step: bool,
    share: [f64; 2],
    /// Running mean of min(NIS/2, cap) per anchor, its clock, and the delayed snapshots.
    levels: [f64; LEVEL_COUNT],
    level_clock_s: f64,
    snapshots: [LevelSnapshot; LEVEL_SNAPSHOTS],
    snapshot_count: usize,
    levels_in_use: [f64; LEVEL_COUNT],
    /// Sum of δ·min(NIS/2, cap) of the one-row residual and its seconds, over the settled rows so
    /// far: the step level in use until the vehicle's delayed level is known.
    #[serde(default)]
    early_step: [f64; 2],
    #[serde(default)]
    step_hold: Option<StepHold>,
    /// Running mean of ln(1 + NIS/2) per shadow anchor, and the misfit in use (1 within the level's
    /// bound).
    log_levels: [f64; ANCHOR_COUNT],
    misfit_in_use: [f64; ANCHOR_COUNT],
    /// Seconds since the anchors were last placed.
    age_s: f64,
    /// Seconds the fix and the onboard motion have agreed since the anchors were placed, up to
    /// [`TRUST_S`]: from then on the anchors are trusted.
    agreed_s: f64,
    last: OffsetEvidence,
    /// The last usable sample the anchors moved to.
    point: Option<AnchorPoint>,
}

/// The last usable sample: where the next step starts.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct AnchorPoint {
    pub fix: LatLon,
    /// Onboard velocity east/north (m/s).
    pub velocity: [f64; 2],
    pub time_s: f64,
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
            log_levels: [POPULATION_LOG_LEVEL; ANCHOR_COUNT],
            misfit_in_use: [1.0; ANCHOR_COUNT],
            age_s: 0.0,
            agreed_s: 0.0,
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

    /// A new anchor at the current fix: the next offsets start from 0 with the GNSS noise as their
    /// uncertainty. The vehicle's levels are kept (they describe its receiver).
    pub fn re_anchor(&mut self) {
        self.share = [0.0; 2];
        self.agreed_s = 0.0;
        self.re_anchor_keeping_levels();
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
        let delta_t = step.delta_t;
        let growth = if step.calibrated {
            self.params.calibrated_growth
        } else {
            self.params.raw_growth
        };
        let levels = self.levels();
        let misfits = if self.params.vehicle_levels {
            self.misfit_in_use
        } else {
            [1.0; ANCHOR_COUNT]
        };
        if delta_t > super::MAX_GAP_S && self.reappears_as_expected(step, &levels) {
            // Back inside what the gap allows: a fresh anchor here (a tunnel is not a jump). Like
            // a session's first fix, the first fix after an outage is one unconfirmed fix (a
            // receiver reacquiring may be off by a reflection): it is trusted after TRUST_S of
            // agreement, and a disagreement before then places the anchors again.
            self.re_anchor_keeping_levels();
            self.agreed_s = 0.0;
            return self.last;
        }
        let gap_m2 = if delta_t > super::MAX_GAP_S {
            gap_variance(delta_t)
        } else {
            0.0
        };
        // A one-row outlier stops every anchor at the last trusted fix before it moves them: a
        // spike comes back within the agreement time, a jump stays and is tested from there.
        let step_test_m2 = self.params.step_noise_m2 * levels[STEP_LEVEL];
        let outlier = norm_squared(step.residual) >= FOLLOW_GATE * step_test_m2;
        if outlier
            && self
                .step_hold
                .is_some_and(|hold| hold.stepped_back(step.residual))
        {
            // The held jump stepped back to the track. A slow anchor still frozen kept the track
            // and goes on below; one that followed GNSS while the jump was held stands on the
            // false position: the anchors are placed again here.
            self.step_hold = None;
            if !self.anchors[ANCHOR_COUNT - 1].frozen {
                self.re_anchor_keeping_levels();
                return self.last;
            }
        }
        if outlier && self.returns(step) {
            // The fix stepped back to where the onboard motion says the vehicle is: the spoofer
            // let go. Trust GNSS again from here (the rest of the offset is dead-reckoning error).
            self.re_anchor_keeping_levels();
            return self.last;
        }
        // A held jump is tested against pure dead reckoning: on a vehicle whose dead reckoning
        // cannot carry an anchor (a misfit beyond the level's bound) it means nothing.
        let dead_reckoning_carries = misfits[ANCHOR_COUNT - 1] <= 1.0;
        if let Some(hold) = &mut self.step_hold
            && (!dead_reckoning_carries || !hold.advance(step.residual, delta_t))
        {
            self.step_hold = None;
        }
        let mut nis = [0.0; ANCHOR_COUNT];
        let mut population_nis = [0.0; LEVEL_COUNT];
        let mut sigma_m = 0.0;
        for (k, anchor) in self.anchors.iter_mut().enumerate() {
            if outlier && !anchor.frozen {
                anchor.freeze(delta_t);
            }
            let keep = if anchor.frozen {
                1.0
            } else {
                (-delta_t / FOLLOW_S[k]).exp()
            };
            anchor.advance(step, keep, gap_m2);
            for axis in 0..2 {
                anchor.carried_since_freeze[axis] += step.motion[axis];
            }
            anchor.gap_since_freeze_m2 += gap_m2;
            anchor.frozen_s += delta_t;
            let variance = anchor.variance(&self.params, k);
            population_nis[k] = norm_squared(anchor.offset) / variance;
            // While frozen, a misfit vehicle's dead-reckoning error beyond the population's (as its
            // shadow shows it over one follow time) keeps growing, like a bias, with the time
            // since the freeze (a step's own row stays one row's noise).
            let bias_m2 = if anchor.frozen {
                let excess_m2 = (misfits[k] - 1.0) * self.shadows[k].variance(&self.params, k);
                excess_m2 * ((anchor.frozen_s - anchor.step_row_s) / FOLLOW_S[k]).powi(2)
            } else {
                0.0
            };
            nis[k] = norm_squared(anchor.offset) / (variance * levels[k] + bias_m2);
            if anchor.frozen {
                // The change since the last trusted fix, against one row's noise growing with the
                // time and the distance since.
                let change = [
                    anchor.offset[0] - anchor.origin[0],
                    anchor.offset[1] - anchor.origin[1],
                ];
                let step_variance = step_test_m2 * (1.0 + anchor.frozen_s / STEP_GROWTH_S)
                    + misfits[k] * growth[k] * norm_squared(anchor.carried_since_freeze)
                    + bias_m2
                    + anchor.gap_since_freeze_m2;
                nis[k] = nis[k].max(norm_squared(change) / step_variance);
            }
            if k == ANCHOR_COUNT - 1 {
                sigma_m = (variance * levels[k]).sqrt();
            }
            if nis[k] >= FOLLOW_GATE {
                if !anchor.frozen {
                    anchor.freeze(0.0);
                }
                anchor.agreement_s = 0.0;
            } else if anchor.frozen {
                anchor.agreement_s += delta_t;
                if anchor.agreement_s >= AGREEMENT_S {
                    anchor.frozen = false;
                }
            }
        }
        population_nis[STEP_LEVEL] = norm_squared(step.residual) / self.params.step_noise_m2;
        let mut shadow_nis = [0.0; ANCHOR_COUNT];
        for (k, shadow) in self.shadows.iter_mut().enumerate() {
            shadow.advance(step, (-delta_t / FOLLOW_S[k]).exp(), gap_m2);
            shadow_nis[k] = norm_squared(shadow.offset) / shadow.variance(&self.params, k);
            shadow.agreement_s = if shadow_nis[k] < FOLLOW_GATE * levels[k] {
                shadow.agreement_s + delta_t
            } else {
                0.0
            };
            // An anchor frozen because its offset grew to the gate (not by a step) goes on from
            // its shadow once following would have agreed for the agreement time: the vehicle's
            // own dead reckoning, followed as usual, finds nothing held (a frozen offset that only
            // dead-reckoning error built, on a vehicle whose error the population's growth
            // understates). A drift still under way keeps the shadow beyond the gate.
            let anchor = &mut self.anchors[k];
            if anchor.frozen && anchor.step_row_s == 0.0 && shadow.agreement_s >= AGREEMENT_S {
                *anchor = Anchor {
                    agreement_s: 0.0,
                    ..*shadow
                };
            }
        }
        // A row counts towards the vehicle's levels unless an offset has already been held beyond
        // the decisive gate for the agreement time (something real, not the receiver's noise);
        // towards its misfit unless that offset arrived in one step (a jump, not dead reckoning).
        let held = !self.held_s.is_nan() && self.held_s >= AGREEMENT_S;
        if self.params.vehicle_levels && !(held && self.arrived_by_step) {
            self.update_levels(&population_nis, &shadow_nis, delta_t, !held);
        }
        self.age_s += delta_t;

        let max_nis = nis[0].max(nis[1]);
        if self.agreed_s < TRUST_S {
            if outlier || max_nis >= FOLLOW_GATE {
                // The fix and the onboard motion have not yet agreed since the anchors were placed
                // (a session's first fix or first onboard readings may be off): place them again
                // here rather than hold the disagreement as an offset.
                self.re_anchor_keeping_levels();
                self.agreed_s = 0.0;
                return self.last;
            }
            self.agreed_s = (self.agreed_s + delta_t).min(TRUST_S);
        }
        if max_nis >= DECISIVE_GATE {
            if self.held_s.is_nan() {
                self.held_s = 0.0;
                // Arrived in one step: beyond the gate now, and below the follow gate before.
                self.arrived_by_step = self.last.max_nis() < FOLLOW_GATE;
                if self.arrived_by_step && self.step_hold.is_none() && dead_reckoning_carries {
                    // The fix before this row was trusted (below the follow gate): the jump is
                    // this row's residual.
                    self.step_hold = Some(StepHold {
                        arrival: step.residual,
                        offset: step.residual,
                        held_s: 0.0,
                    });
                }
            } else {
                self.held_s += delta_t;
            }
        } else {
            self.held_s = f64::NAN;
            self.arrived_by_step = false;
        }
        let beyond = if max_nis >= FOLLOW_GATE { 1.0 } else { 0.0 };
        for (share, tau) in self.share.iter_mut().zip(SHARE_S) {
            let keep = (-delta_t / tau).exp();
            *share = keep * *share + (1.0 - keep) * beyond;
        }
        let slow = &self.anchors[ANCHOR_COUNT - 1];
        self.last = OffsetEvidence {
            offset_m: slow.offset,
            sigma_m,
            nis,
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
            held_step_m: self.step_hold.map(|hold| hold.offset),
        };
        self.last
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
            norm_squared(offset) / (variance * levels[k]) < FOLLOW_GATE
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

    /// A fresh anchor at the current point, keeping the vehicle's levels, the shares and the
    /// trust (the fix is where the motion allows it to be).
    fn re_anchor_keeping_levels(&mut self) {
        self.anchors = [Anchor::default(); ANCHOR_COUNT];
        self.shadows = [Anchor::default(); ANCHOR_COUNT];
        self.held_s = f64::NAN;
        self.arrived_by_step = false;
        self.step_hold = None;
        self.age_s = 0.0;
        self.last = OffsetEvidence {
            share: self.share,
            ..OffsetEvidence::EMPTY
        };
    }

    /// The multiples of the population's variance each level applies this row: the vehicle's
    /// level within the bounds, and for an anchor the larger of that and its misfit.
    fn levels(&self) -> [f64; LEVEL_COUNT] {
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
    fn update_levels(
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
fn early_level(sum: f64, seconds: f64) -> f64 {
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

/// E[ln(1 + L·X)] for X ~ Exp(1): e^{1/L}·E₁(1/L), for L ≥ the level's upper bound (1/L ≤ ¼,
/// where 20 terms of the series are exact to machine precision).
fn mean_log_level(level: f64) -> f64 {
    let x = 1.0 / level;
    let mut term = 1.0;
    let mut series = 0.0;
    for k in 1..=20 {
        term *= -x / k as f64;
        series -= term / k as f64;
    }
    x.exp() * (-EULER_GAMMA - x.ln() + series)
}

/// The misfit a running mean of ln(1 + NIS/2) asks for: the level L with that mean, by
/// bisection on ln L; 1 while L is within the level's bound, at most [`MISFIT_MAX`].
fn misfit(log_level: f64) -> f64 {
    if log_level.is_nan() || log_level <= mean_log_level(LEVEL_RANGE.1) {
        return 1.0;
    }
    if log_level >= mean_log_level(MISFIT_MAX) {
        return MISFIT_MAX;
    }
    let (mut low, mut high) = (LEVEL_RANGE.1.ln(), MISFIT_MAX.ln());
    for _ in 0..60 {
        let middle = 0.5 * (low + high);
        if mean_log_level(middle.exp()) < log_level {
            low = middle;
        } else {
            high = middle;
        }
    }
    (0.5 * (low + high)).exp()
}

fn norm_squared(v: [f64; 2]) -> f64 {
    v[0] * v[0] + v[1] * v[1]
}

/// One second of normal driving as one anchor saw it (the fit's input).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct OffsetPoint {
    /// ‖U_cal‖: net distance dead-reckoned with the warm calibration behind the anchor (m).
    pub carried_m: f64,
    /// ‖U_raw‖: the same before the calibration was warm (m).
    pub raw_carried_m: f64,
    /// ‖o‖ (m).
    pub offset_m: f64,
}

impl OffsetPoint {
    /// The calibration state whose growth this point measures: raw or calibrated when the other
    /// part of U is at most [`MIXED_SHARE`] of it; `None` for a mix of both.
    fn calibrated(&self) -> Option<bool> {
        if self.carried_m <= MIXED_SHARE * self.raw_carried_m {
            Some(false)
        } else if self.raw_carried_m <= MIXED_SHARE * self.carried_m {
            Some(true)
        } else {
            None
        }
    }

    /// ‖U‖ of its group.
    fn group_carried_m(&self) -> f64 {
        self.carried_m.max(self.raw_carried_m)
    }
}

/// A point measures one calibration state's growth when the other part of U is at most this share
/// of it (its variance then adds at most a few per cent).
const MIXED_SHARE: f64 = 0.05;

/// Fewest points per anchor and calibration state for a fit of that group.
pub const MIN_OFFSET_POINTS: usize = 30;
/// c² of uncalibrated dead reckoning when the data cannot tell: a heading bias of about 3° makes
/// an error of 5 % of the distance travelled.
pub const RAW_GROWTH_PRIOR: f64 = 0.05 * 0.05;
/// The least c² of calibrated dead reckoning: 1 % of the distance (a residual heading error of
/// half a degree and a speed scale off by half a per cent). An anchor that follows GNSS carries
/// short distances only, and a fit from them can extrapolate a growth near 0 to the kilometres a
/// frozen anchor carries.
pub const CALIBRATED_GROWTH_FLOOR: f64 = 0.01 * 0.01;
/// Equal-count bins of ‖U‖ per group of points.
const FIT_BINS: usize = 10;
/// The quantile the noise is matched at, and χ²₂'s value there (−2 ln 0.01). A bin's per-axis
/// variance is its 99 % quantile of ‖o‖² over this: the scale is matched where the gates work, in
/// the tail, and pooled over vehicles it is the scale of the noisier ones (receivers differ by 25×
/// in variance; a quieter vehicle's own level brings it down to a quarter of it).
pub const FIT_QUANTILE: f64 = 0.99;
pub const CHI2_2_AT_FIT_QUANTILE: f64 = 9.210_340_371_976_184;

/// Each anchor's R and c² (raw, calibrated) from its points: the points are grouped by the
/// calibration state their U was dead-reckoned in (mixed points are left out), binned by ‖U‖ (equal
/// counts, per group), each bin gives a variance v (its 99 % quantile of ‖o‖² / 9.21) at its median
/// ‖U‖², and v = R + c²_raw‖U‖²·[raw] + c²_cal‖U‖²·[calibrated] is fitted by least squares with
/// c² ≥ 0 (a negative slope is dropped and the rest refitted), each slope then raised to the bins'
/// upper envelope, the calibrated one at least [`CALIBRATED_GROWTH_FLOOR`]. Without calibrated
/// points the calibrated growth is the raw one; without raw points the raw growth is
/// [`RAW_GROWTH_PRIOR`].
pub fn offset_params_from_points(
    points: &[Vec<OffsetPoint>; ANCHOR_COUNT],
    step_noise_m2: f64,
) -> Result<OffsetParams, EvidenceError> {
    let mut params = OffsetParams {
        vehicle_levels: true,
        step_noise_m2: step_noise_m2.clamp(NOISE_RANGE_M2.0, NOISE_RANGE_M2.1),
        ..OffsetParams::unnormalised()
    };
    for (k, anchor_points) in points.iter().enumerate() {
        let group = |calibrated: bool| -> Vec<OffsetPoint> {
            anchor_points
                .iter()
                .copied()
                .filter(|p| p.calibrated() == Some(calibrated))
                .collect()
        };
        let (raw, calibrated) = (group(false), group(true));
        let has_raw = raw.len() >= MIN_OFFSET_POINTS;
        let has_calibrated = calibrated.len() >= MIN_OFFSET_POINTS;
        if !has_raw && !has_calibrated {
            return Err(EvidenceError::TooFewOffsetRows {
                rows: anchor_points.len(),
                minimum: MIN_OFFSET_POINTS,
            });
        }
        let mut rows: Vec<[f64; 3]> = Vec::new();
        if has_raw {
            rows.extend(binned(raw).map(|(x, v)| [x, 0.0, v]));
        }
        if has_calibrated {
            rows.extend(binned(calibrated).map(|(x, v)| [0.0, x, v]));
        }
        let [noise, raw_growth, calibrated_growth] = upper_envelope(
            &rows,
            non_negative_fit(&rows, [true, has_raw, has_calibrated]),
        );
        params.noise_m2[k] = noise.clamp(NOISE_RANGE_M2.0, NOISE_RANGE_M2.1);
        let calibrated_growth = calibrated_growth.clamp(CALIBRATED_GROWTH_FLOOR, 1.0);
        // An anchor that never ran long uncalibrated (the slow one settles after the warm-up)
        // takes the physical prior for raw onboard errors; calibration never makes them worse.
        let raw_growth = if has_raw {
            raw_growth.min(1.0)
        } else {
            RAW_GROWTH_PRIOR.max(calibrated_growth)
        };
        params.raw_growth[k] = raw_growth;
        params.calibrated_growth[k] = if has_calibrated {
            calibrated_growth
        } else {
            raw_growth
        };
    }
    params.validate()?;
    Ok(params)
}

/// (median ‖U‖², 99 % quantile of ‖o‖² / 9.21) per equal-count bin of ‖U‖.
fn binned(mut points: Vec<OffsetPoint>) -> impl Iterator<Item = (f64, f64)> {
    points.sort_by(|a, b| a.group_carried_m().total_cmp(&b.group_carried_m()));
    let size = points.len().div_ceil(FIT_BINS);
    let bins: Vec<(f64, f64)> = points
        .chunks(size)
        .map(|bin| {
            let carried = bin[bin.len() / 2].group_carried_m();
            let mut squared: Vec<f64> = bin.iter().map(|p| p.offset_m * p.offset_m).collect();
            squared.sort_by(f64::total_cmp);
            let tail = super::stats::quantile_sorted(&squared, FIT_QUANTILE).unwrap_or(0.0);
            (carried * carried, tail / CHI2_2_AT_FIT_QUANTILE)
        })
        .collect();
    bins.into_iter()
}

/// The fitted line raised to an upper envelope of the bins: each slope becomes large enough that
/// no bin of its group lies above R + c²x. Dead-reckoning error differs between vehicles (the
/// calibration leaves each its own residual heading error), so the population's growth must cover
/// the vehicles that drift most; a vehicle's own level brings it down for the others.
fn upper_envelope(rows: &[[f64; 3]], beta: [f64; 3]) -> [f64; 3] {
    let mut out = beta;
    for row in rows {
        for group in 0..2 {
            let x = row[group];
            if x > 0.0 {
                out[group + 1] = out[group + 1].max((row[2] - beta[0]) / x);
            }
        }
    }
    out
}

/// Least squares of v = β₀ + β₁x₁ + β₂x₂ over `rows` ([x₁, x₂, v]) on the `active` coefficients,
/// dropping a slope that comes out negative (and refitting) until none does. Inactive and dropped
/// coefficients are 0.
fn non_negative_fit(rows: &[[f64; 3]], mut active: [bool; 3]) -> [f64; 3] {
    loop {
        let beta = solve_normal_equations(rows, active);
        match (1..3).find(|&j| active[j] && beta[j] < 0.0) {
            Some(j) => active[j] = false,
            None => return beta,
        }
    }
}

/// The least-squares coefficients of the active columns [1, x₁, x₂] by Gaussian elimination with
/// partial pivoting on the normal equations; a singular system leaves the slopes 0 and the
/// intercept the mean.
fn solve_normal_equations(rows: &[[f64; 3]], active: [bool; 3]) -> [f64; 3] {
    let columns: Vec<usize> = (0..3).filter(|&j| active[j]).collect();
    let n = columns.len();
    let feature = |row: &[f64; 3], j: usize| if j == 0 { 1.0 } else { row[j - 1] };
    let mut a = vec![vec![0.0; n + 1]; n];
    for row in rows {
        for (i, &ci) in columns.iter().enumerate() {
            for (j, &cj) in columns.iter().enumerate() {
                a[i][j] += feature(row, ci) * feature(row, cj);
            }
            a[i][n] += feature(row, ci) * row[2];
        }
    }
    let mean = rows.iter().map(|r| r[2]).sum::<f64>() / rows.len().max(1) as f64;
    let fallback = [mean, 0.0, 0.0];
    for pivot in 0..n {
        let best = (pivot..n)
            .max_by(|&x, &y| a[x][pivot].abs().total_cmp(&a[y][pivot].abs()))
            .unwrap_or(pivot);
        if a[best][pivot].abs() < 1e-12 * (1.0 + a[best][n].abs()) {
            return fallback;
        }
        a.swap(pivot, best);
        let (upper, lower) = a.split_at_mut(pivot + 1);
        let pivot_row = &upper[pivot];
        for row in lower.iter_mut() {
            let factor = row[pivot] / pivot_row[pivot];
            for (cell, above) in row.iter_mut().zip(pivot_row).skip(pivot) {
                *cell -= factor * above;
            }
        }
    }
    let mut solution = vec![0.0; n];
    for i in (0..n).rev() {
        let tail: f64 = (i + 1..n).map(|j| a[i][j] * solution[j]).sum();
        solution[i] = (a[i][n] - tail) / a[i][i];
    }
    let mut beta = [0.0; 3];
    for (value, &column) in solution.iter().zip(&columns) {
        beta[column] = *value;
    }
    if beta.iter().all(|b| b.is_finite()) {
        beta
    } else {
        fallback
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Unit GNSS noise on both anchors, no growth, no vehicle levels.
    fn unit_params() -> OffsetParams {
        OffsetParams {
            noise_m2: [1.0; ANCHOR_COUNT],
            raw_growth: [0.0; ANCHOR_COUNT],
            calibrated_growth: [0.0; ANCHOR_COUNT],
            step_noise_m2: 1.0,
            vehicle_levels: false,
        }
    }

    fn step(residual: [f64; 2], delta_t: f64) -> OffsetStep {
        OffsetStep {
            residual,
            motion: [0.0, 10.0 * delta_t],
            delta_t,
            calibrated: false,
        }
    }

    /// A tracker whose anchors are trusted: TRUST_S seconds of agreement after the first fix.
    fn trusted(params: &OffsetParams) -> OffsetTracker {
        let mut tracker = OffsetTracker::new(params);
        for _ in 0..(TRUST_S as usize) {
            tracker.push(&step([0.0; 2], 1.0));
        }
        tracker
    }

    fn keep(delta_t: f64, k: usize) -> f64 {
        (-delta_t / FOLLOW_S[k]).exp()
    }

    #[test]
    fn an_anchor_follows_a_constant_dead_reckoning_error_to_its_steady_state() {
        // r = 0.1 m east every second: the fast anchor's o → 0.1·keep/(1 − keep) = 0.951 m, the
        // geometric sum, and it never stops following. The slow one would settle at 11.95 m: with
        // unit noise it stops following when its offset passes 4 m (NIS 16) and then keeps it.
        let mut tracker = OffsetTracker::new(&unit_params());
        let mut last = OffsetEvidence::EMPTY;
        let mut slow_froze_at = None;
        for i in 0..2000 {
            last = tracker.push(&step([0.1, 0.0], 1.0));
            if last.nis[1] >= FOLLOW_GATE && slow_froze_at.is_none() {
                slow_froze_at = Some(i);
            }
        }
        let a = keep(1.0, 0);
        assert!(
            (last.offset_norm_m[0] - 0.1 * a / (1.0 - a)).abs() < 1e-9,
            "{last:?}"
        );
        assert!(last.nis[0] < FOLLOW_GATE);
        // Σ 0.1·keep^j reaches 4 m after 50 rows (0.1·keep·(1 − keep^n)/(1 − keep) ≥ 4).
        let b = keep(1.0, 1);
        let rows = ((1.0 - 4.0 * (1.0 - b) / (0.1 * b)).ln() / b.ln()).ceil() as usize;
        assert_eq!(slow_froze_at, Some(rows - 1));
        assert!(last.frozen);
    }

    #[test]
    fn a_jump_freezes_the_anchors_and_is_held_while_a_spike_comes_back() {
        let mut tracker = OffsetTracker::new(&unit_params());
        for _ in 0..30 {
            tracker.push(&step([0.0; 2], 1.0));
        }
        // A 50 m jump north: a one-row outlier, so every anchor stops at the last trusted fix
        // before moving (o = 0 there) and holds the whole 50 m.
        let first = tracker.push(&step([0.0, 50.0], 1.0));
        assert!(first.frozen && first.arrived_by_step);
        assert_eq!(first.held_s, 0.0);
        assert_eq!(first.offset_m, [0.0, 50.0]);
        let mut last = first;
        for _ in 0..5 {
            last = tracker.push(&step([0.0; 2], 1.0));
        }
        assert_eq!(last.held_s, 5.0);
        assert_eq!(last.offset_m, [0.0, 50.0]);
        // Unit noise, no growth: the whole offset against R = 1 (the step test is below it).
        assert_eq!(last.nis, [2500.0, 2500.0]);

        // A 30 m spike on one row out and back: held for 0 s, and back to 0 m.
        let mut tracker = OffsetTracker::new(&unit_params());
        for _ in 0..30 {
            tracker.push(&step([0.0; 2], 1.0));
        }
        let out = tracker.push(&step([30.0, 0.0], 1.0));
        assert_eq!(out.held_s, 0.0);
        // Back to within a quarter of the held offset: the fix is where the motion puts it, and
        // the anchors are placed there again.
        let back = tracker.push(&step([-30.0, 0.0], 1.0));
        assert_eq!(back.nis, [0.0, 0.0]);
        assert!(!back.frozen && back.anchor_age_s == 0.0, "{back:?}");
        assert_eq!(back.held_s, 0.0);
        // The share of time beyond the follow gate: one row of the last 10 s.
        let share_after_out = 1.0 - keep(1.0, 0);
        assert!((out.share[0] - share_after_out).abs() < 1e-12);
    }

    #[test]
    fn after_a_freeze_the_change_is_tested_against_one_rows_noise() {
        // R = 100 m² hides a 20 m offset (NIS 4), but a 20 m step against one row's noise of
        // 1 m² is an outlier: the anchors stop, and the change since (20 m) is tested against
        // 1·(1 + t/2 s): NIS 400/1.5 on the step row, 400/2 a second later.
        let params = OffsetParams {
            noise_m2: [100.0; ANCHOR_COUNT],
            ..unit_params()
        };
        let mut tracker = trusted(&params);
        let jump = tracker.push(&step([20.0, 0.0], 1.0));
        assert!((jump.nis[0] - 400.0 / 1.5).abs() < 1e-9, "{jump:?}");
        let held = tracker.push(&step([0.0, 0.0], 1.0));
        assert!((held.nis[0] - 200.0).abs() < 1e-9, "{held:?}");
        assert_eq!(held.held_s, 1.0);
    }

    #[test]
    fn a_frozen_anchor_follows_again_after_the_agreement_time() {
        // 4.5 m out (NIS 20: beyond the follow gate, not the decisive one, so no return).
        let mut tracker = trusted(&unit_params());
        tracker.push(&step([4.5, 0.0], 1.0));
        // Back: o_fast = 4.5·keep − 4.5, NIS 0.2 (agreement); the slow anchor too.
        let mut frozen_rows = 0;
        for _ in 0..10 {
            let e = tracker.push(&step(
                [-4.5 * f64::from(u8::from(frozen_rows == 0)), 0.0],
                1.0,
            ));
            if e.frozen {
                frozen_rows += 1;
            }
        }
        // Agreement from the first row back: frozen for AGREEMENT_S − 1 more rows (5 s in all).
        assert_eq!(frozen_rows, 4);
    }

    #[test]
    fn a_held_jump_stays_displaced_after_the_anchors_lose_it_until_it_steps_back() {
        // Dead reckoning as poor as 10 % of the distance (c² = 0.01) at 10 m/s: 100 s after a
        // 20 m jump the frozen anchors' own σ is 100 m, and they follow GNSS again.
        let params = OffsetParams {
            raw_growth: [0.01; ANCHOR_COUNT],
            ..unit_params()
        };
        let jumped = |tracker: &mut OffsetTracker| {
            let first = tracker.push(&step([20.0, 0.0], 1.0));
            assert!(first.arrived_by_step && first.displaced());
            assert_eq!(first.held_step_m, Some([20.0, 0.0]));
        };
        let mut tracker = trusted(&params);
        jumped(&mut tracker);
        let mut lost_by_anchors = None;
        for row in 1..=150 {
            let e = tracker.push(&step([0.0; 2], 1.0));
            if e.max_nis() < FOLLOW_GATE && lost_by_anchors.is_none() {
                lost_by_anchors = Some(row);
            }
            assert!(e.displaced(), "row {row}: {e:?}");
            assert_eq!(e.held_step_m, Some([20.0, 0.0]));
        }
        assert!(
            lost_by_anchors.is_some_and(|row| row < 100),
            "{lost_by_anchors:?}"
        );
        // The spoofer lets go: one step back to the track ends the hold and re-anchors.
        let back = tracker.push(&step([-19.0, 0.0], 1.0));
        assert!(!back.displaced() && back.held_step_m.is_none() && back.anchor_age_s == 0.0);

        // The row after the jump on which the hold ends, with `residual` every second.
        let hold_ends = |residual: [f64; 2]| {
            let mut tracker = trusted(&params);
            jumped(&mut tracker);
            (1..=700).find(|_| tracker.push(&step(residual, 1.0)).held_step_m.is_none())
        };
        // Walked back 0.5 m per second: it ends on the row it is nearer the track (10 m).
        assert_eq!(hold_ends([-0.5, 0.0]), Some(20));
        // Never let go: held for MAX_STEP_HOLD_S, then the anchors alone decide.
        assert_eq!(hold_ends([0.0; 2]), Some(MAX_STEP_HOLD_S as usize + 1));
    }

    #[test]
    fn after_an_outage_a_plausible_reappearance_re_anchors_and_a_far_one_is_evidence() {
        // After a 30 s gap the hidden motion is ½·0.5·30² = 225 m per axis: 100 m off is inside
        // it (a fresh anchor, nothing displaced), 5 km is not (NIS 25e6 / (1 + 225²) = 494).
        let gap = 30.0;
        let hidden = 0.5 * GAP_ACCELERATION_MPS2 * gap * gap;
        let mut tracker = trusted(&unit_params());
        let inside = tracker.push(&step([100.0, 0.0], gap));
        assert_eq!(inside.nis, [0.0, 0.0]);
        assert_eq!(inside.anchor_age_s, 0.0);
        assert!(!inside.displaced());
        let mut tracker = trusted(&unit_params());
        let beyond = tracker.push(&step([5000.0, 0.0], gap));
        let expected = 5000.0_f64.powi(2) / (1.0 + hidden * hidden);
        assert!((beyond.nis[1] - expected).abs() < 1e-6, "{beyond:?}");
        assert!(beyond.max_nis() > DECISIVE_GATE);
        // Without the gap, the same 100 m is far beyond the gate.
        let mut tracker = trusted(&unit_params());
        assert!(tracker.push(&step([100.0, 0.0], 1.0)).max_nis() > DECISIVE_GATE);
    }

    #[test]
    fn the_first_fix_after_an_outage_is_trusted_only_after_agreement() {
        // The fix reappears inside what a 10 s gap allows, but 15 m off (a reflection as the
        // receiver reacquires); the next fix is back on the track. The anchors were placed on the
        // reappearance: the disagreement places them again instead of holding a 15 m jump.
        let mut tracker = trusted(&unit_params());
        tracker.push(&step([15.0, 0.0], 10.0));
        let back = tracker.push(&step([-15.0, 0.0], 1.0));
        assert_eq!((back.nis, back.anchor_age_s), ([0.0, 0.0], 0.0));
        assert!(!back.displaced());
        // After TRUST_S of agreement the same step is a jump again.
        for _ in 0..(TRUST_S as usize) {
            assert!(!tracker.push(&step([0.0; 2], 1.0)).displaced());
        }
        let jump = tracker.push(&step([-15.0, 0.0], 1.0));
        assert!(jump.max_nis() >= DECISIVE_GATE && jump.arrived_by_step);
    }

    #[test]
    fn until_the_fix_and_the_motion_agree_a_disagreement_places_the_anchors_again() {
        // A session whose first onboard readings are off: 30 m of disagreement on the second row
        // re-anchors there instead of being held; after TRUST_S of agreement the same step is a
        // jump.
        let mut tracker = OffsetTracker::new(&unit_params());
        let first = tracker.push(&step([30.0, 0.0], 1.0));
        assert_eq!((first.nis, first.anchor_age_s), ([0.0, 0.0], 0.0));
        for _ in 0..4 {
            assert!(!tracker.push(&step([0.0; 2], 1.0)).displaced());
        }
        let untrusted = tracker.push(&step([30.0, 0.0], 1.0));
        assert_eq!(
            untrusted.max_nis(),
            0.0,
            "4 s of agreement is not yet trust"
        );
        let mut tracker = trusted(&unit_params());
        let jump = tracker.push(&step([30.0, 0.0], 1.0));
        assert!(jump.max_nis() >= DECISIVE_GATE && jump.arrived_by_step);
    }

    #[test]
    fn the_uncertainty_grows_with_the_distance_carried() {
        // R = 4 m², c² = 0.01: after carrying 100 m north with no offset, a 10 m offset is
        // NIS = 100·keep² / (4 + 0.01·‖U‖²) with U the carried distance (decayed like o).
        // (One row's noise is wide, so the 10 m is no outlier and the anchors keep following.)
        let params = OffsetParams {
            noise_m2: [4.0; ANCHOR_COUNT],
            raw_growth: [0.01; ANCHOR_COUNT],
            calibrated_growth: [1e-4; ANCHOR_COUNT],
            step_noise_m2: 1e4,
            ..unit_params()
        };
        let mut tracker = OffsetTracker::new(&params);
        let e = tracker.push(&OffsetStep {
            residual: [10.0, 0.0],
            motion: [0.0, 100.0],
            delta_t: 1.0,
            calibrated: false,
        });
        for k in 0..ANCHOR_COUNT {
            let a = keep(1.0, k);
            let expected = (10.0 * a).powi(2) / (4.0 + 0.01 * (100.0 * a).powi(2));
            assert!((e.nis[k] - expected).abs() < 1e-12, "{k}: {e:?}");
            assert!((e.raw_carried_m[k] - 100.0 * a).abs() < 1e-12);
            assert_eq!(e.carried_m[k], 0.0);
        }
        // Then 100 m east with the warm calibration (c² = 0.0001): each part of U grows the
        // variance with its own c², and both are forgotten with the offset.
        let e = tracker.push(&OffsetStep {
            residual: [0.0, 0.0],
            motion: [100.0, 0.0],
            delta_t: 1.0,
            calibrated: true,
        });
        for k in 0..ANCHOR_COUNT {
            let a = keep(1.0, k);
            let (raw, calibrated) = (100.0 * a * a, 100.0 * a);
            let expected =
                (10.0 * a * a).powi(2) / (4.0 + 0.01 * raw * raw + 1e-4 * calibrated * calibrated);
            assert!((e.nis[k] - expected).abs() < 1e-12, "{k}: {e:?}");
            assert!((e.raw_carried_m[k] - raw).abs() < 1e-12);
            assert!((e.carried_m[k] - calibrated).abs() < 1e-12);
        }
    }

    /// One-row residuals of a receiver with white GNSS noise of σ per axis (each the difference of
    /// two such errors).
    fn receiver_residuals(sigma_m: f64, seed: u64) -> impl Iterator<Item = [f64; 2]> {
        let mut rng = crate::rng::Rng::seed_from_u64(seed);
        let mut previous = [0.0; 2];
        std::iter::repeat_with(move || {
            let noise = [sigma_m * rng.normal(), sigma_m * rng.normal()];
            let residual = [noise[0] - previous[0], noise[1] - previous[1]];
            previous = noise;
            residual
        })
    }

    fn with_levels() -> OffsetParams {
        OffsetParams {
            vehicle_levels: true,
            ..unit_params()
        }
    }

    #[test]
    fn the_vehicle_level_adapts_with_a_delay_and_within_bounds() {
        // A receiver 3× noisier (in σ) than the population. Its level rises towards 9, capped at
        // 4, but only from snapshots at least 120 s old.
        let mut tracker = OffsetTracker::new(&with_levels());
        let mut levels_at = Vec::new();
        for (i, residual) in receiver_residuals(3.0, 3).take(900).enumerate() {
            let e = tracker.push(&step(residual, 1.0));
            assert!(e.nis.iter().all(|n| n.is_finite()));
            if i == 100 || i == 899 {
                levels_at.push(tracker.levels_in_use);
            }
        }
        assert_eq!(levels_at[0], [LEVEL_RANGE.1; LEVEL_COUNT]);
        assert!(levels_at[1].iter().all(|&l| l > 3.0), "{levels_at:?}");
    }

    #[test]
    fn the_early_step_level_is_an_upper_confidence_bound_within_bounds() {
        // 15 s of NIS/2 summing to 30 (mean 2): χ²₃₀'s 5 % quantile is 18.49, so 60 / 18.49.
        assert!((early_level(30.0, 15.0) - 60.0 / 18.4927).abs() < 0.01);
        // A quiet receiver (mean 0.5) is never taken below the population's level.
        assert_eq!(early_level(7.5, 15.0), 1.0);
        // Before a second of rows, and for a very noisy receiver, the upper bound.
        assert_eq!(early_level(0.0, 0.5), LEVEL_RANGE.1);
        assert_eq!(early_level(150.0, 15.0), LEVEL_RANGE.1);
    }

    #[test]
    fn a_quiet_receiver_is_step_tested_as_one_from_its_first_minute() {
        // GNSS white noise of σ 0.5 m on unit parameters: the step level in use falls to the
        // population's within the first minute, while the anchors' levels wait for the delayed
        // snapshot.
        let mut tracker = OffsetTracker::new(&with_levels());
        for residual in receiver_residuals(0.5, 5).take(60) {
            tracker.push(&step(residual, 1.0));
        }
        assert_eq!(tracker.levels_in_use[STEP_LEVEL], 1.0);
        assert!(
            tracker.levels_in_use[..ANCHOR_COUNT]
                .iter()
                .all(|&l| l == LEVEL_RANGE.1)
        );
    }

    #[test]
    fn a_vehicle_whose_dead_reckoning_misfits_stands_its_anchors_down_and_still_sees_a_jump() {
        // Dead reckoning off by 0.5 m/s for good (a rover whose compass is useless): the slow
        // anchor would hold 60 m against 1 m of noise, and frozen, its offset grows for good. Its
        // misfit comes from snapshots at least 120 s old, whose own rows outweigh the prior: the
        // anchors follow again within ten minutes, and a 200 m jump is still decisive on its row.
        let params = OffsetParams {
            vehicle_levels: true,
            ..unit_params()
        };
        let mut tracker = trusted(&params);
        let mut e = OffsetEvidence::EMPTY;
        for i in 0..600 {
            e = tracker.push(&step([0.5, 0.0], 1.0));
            if i == 100 {
                assert_eq!(tracker.misfit_in_use, [1.0; ANCHOR_COUNT]);
                assert!(e.max_nis() >= DECISIVE_GATE, "{e:?}");
            }
        }
        assert!(
            tracker.misfit_in_use.iter().all(|&m| m > LEVEL_RANGE.1),
            "{tracker:?}"
        );
        assert!(tracker.anchors.iter().all(|a| !a.frozen), "{tracker:?}");
        assert!(e.max_nis() < FOLLOW_GATE, "{e:?}");
        let jump = tracker.push(&step([200.5, 0.0], 1.0));
        assert!(
            jump.max_nis() >= DECISIVE_GATE && jump.arrived_by_step,
            "{jump:?}"
        );
    }

    #[test]
    fn a_held_jump_does_not_teach_the_misfit() {
        // A 50 m jump held for ten minutes on a vehicle whose dead reckoning is perfect: the rows
        // of an offset that arrived in one step never count, so it stays held to the end.
        let params = OffsetParams {
            vehicle_levels: true,
            ..unit_params()
        };
        let mut tracker = trusted(&params);
        for _ in 0..300 {
            tracker.push(&step([0.0; 2], 1.0));
        }
        let mut e = tracker.push(&step([50.0, 0.0], 1.0));
        for _ in 0..600 {
            e = tracker.push(&step([0.0; 2], 1.0));
        }
        assert_eq!(tracker.misfit_in_use, [1.0; ANCHOR_COUNT]);
        assert!(e.held_s >= 599.0 && e.max_nis() >= DECISIVE_GATE, "{e:?}");
    }

    #[test]
    fn the_misfit_inverts_the_mean_log_level_beyond_the_level_bound() {
        // e·E₁(1) at L = 1 by the series is the population's prior (to the series' precision).
        assert!((POPULATION_LOG_LEVEL - 1.0f64.exp() * 0.219_383_934_395_520_3).abs() < 1e-12);
        // At L = 10: e^{0.1}·E₁(0.1), E₁(0.1) = 1.822 923 958 419 39.
        let expected = 0.1f64.exp() * 1.822_923_958_419_39;
        assert!((mean_log_level(10.0) - expected).abs() < 1e-12);
        assert!((misfit(expected) - 10.0).abs() < 1e-9);
        // Within the bound (the population's own mean included) the misfit is 1; it is capped.
        assert_eq!(misfit(POPULATION_LOG_LEVEL), 1.0);
        assert_eq!(misfit(mean_log_level(3.9)), 1.0);
        assert_eq!(misfit(f64::NAN), 1.0);
        assert_eq!(misfit(100.0), MISFIT_MAX);
    }

    #[test]
    fn the_fit_recovers_noise_and_growth_from_binned_quantiles() {
        // Ten distances, ten points each, all with ‖o‖² = 9.21·(2 + 0.01·x²): R = 2, c² = 0.01
        // (on the line, the upper envelope changes nothing).
        let mut points = Vec::new();
        for bin in 0..10 {
            let x = 50.0 * f64::from(bin);
            for _ in 0..10 {
                points.push(OffsetPoint {
                    carried_m: 0.0,
                    raw_carried_m: x,
                    offset_m: (CHI2_2_AT_FIT_QUANTILE * (2.0 + 0.01 * x * x)).sqrt(),
                });
            }
        }
        let params =
            offset_params_from_points(&[points.clone(), points], 2.0).expect("enough points");
        assert_eq!(params.step_noise_m2, 2.0);
        for k in 0..ANCHOR_COUNT {
            assert!((params.noise_m2[k] - 2.0).abs() < 1e-9, "{params:?}");
            assert!((params.raw_growth[k] - 0.01).abs() < 1e-12, "{params:?}");
            assert_eq!(params.calibrated_growth[k], params.raw_growth[k]);
        }
        assert!(params.vehicle_levels);
        let few = vec![
            OffsetPoint {
                carried_m: 0.0,
                raw_carried_m: 1.0,
                offset_m: 1.0,
            };
            5
        ];
        assert!(offset_params_from_points(&[few.clone(), few], 1.0).is_err());
    }

    #[test]
    fn validation_names_the_field() {
        let mut params = unit_params();
        params.noise_m2[1] = f64::NAN;
        let err = params.validate().expect_err("NaN noise");
        assert!(err.to_string().contains("offset.noise_m2"), "{err}");
        let mut params = unit_params();
        params.calibrated_growth[0] = 2.0;
        let err = params.validate().expect_err("growth");
        assert!(
            err.to_string().contains("offset.calibrated_growth"),
            "{err}"
        );
        let params = OffsetParams {
            step_noise_m2: 0.0,
            ..unit_params()
        };
        let err = params.validate().expect_err("step noise");
        assert!(err.to_string().contains("offset.step_noise_m2"), "{err}");
    }
}
