//! The offset channels' parameters and constants, the step handed in and the channels handed out.
//!
//! Owns the gates, the time constants, [`OffsetParams`] and its validation, [`OffsetStep`] and
//! [`OffsetEvidence`]. Must not move an anchor or learn a level (the files above do).

use serde::{Deserialize, Serialize};

use crate::evidence::EvidenceError;
use crate::evidence::linalg::Mat2;
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
/// Placements again on a disagreement, without trust earned in between, that make the anchors
/// disputed ([`OffsetEvidence::disputed`]): one settles a reflected first fix; a second means the
/// fix disagreed again with anchors placed on itself.
pub const DISPUTED_PLACEMENTS: u32 = 2;
/// Per-axis variance (m²) of a receiver's first fixes after an outage beyond its usual noise: a
/// receiver reacquiring starts metres off (1–5 m per axis) and converges over seconds, so anchors
/// placed on its first fix start this unsure of where they stand (3 m per axis, 1-σ). A jump of
/// 20 m from them is still beyond the decisive gate; a reconverging receiver is not.
pub const REACQUISITION_M2: f64 = 9.0;
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
/// A vehicle's level stays within these multiples of the training population's. Until its own
/// level is known (the first snapshot old enough), a vehicle is taken to be as noisy as the bound
/// allows: a session's first minutes never alarm on a receiver noisier than the population's.
pub const LEVEL_RANGE: (f64, f64) = (0.25, 4.0);
/// Levels per vehicle: one per anchor, then the one-row residual's (the step test's).
pub(super) const LEVEL_COUNT: usize = ANCHOR_COUNT + 1;
pub(super) const STEP_LEVEL: usize = ANCHOR_COUNT;
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
    /// Re-express the motion carried behind each anchor in the calibration now in use whenever it
    /// changes ([`OffsetStep::theta_in_use`]), so that an offset the dead reckoning built under an
    /// earlier calibration (the fleet's prior mean, before the vehicle's own was learnt) is not
    /// then tested against the new calibration's smaller error. Off unless a training asks for it
    /// ([`AnchorRebase`](crate::train::spec::AnchorRebase)); absent from artifacts without it, which
    /// keep their bytes.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub rebase_on_calibration: bool,
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
            rebase_on_calibration: false,
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
    /// The onboard calibration was in use (the residual is calibrated).
    pub calibrated: bool,
    /// The calibration in use's mean squared error of speed scale and heading bias
    /// (`calibration::in_use_error`); 0 when the calibration is trusted by the clock. With it,
    /// every offset is tested against what that error makes of the distance it carries.
    pub calibration_error: [f64; 3],
    /// A row that places the anchors again reports what it found (the calibration is trusted from
    /// its information); otherwise it reports the fresh anchors' empty channels.
    pub reports_placements: bool,
    /// The step starts from a fix the receiver was holding (it repeated the one before): a jump
    /// here is where the receiver catches up with a vehicle that moved off, not a jump from a
    /// track the anchors followed.
    pub leaves_held_fix: bool,
    /// The step's fix repeats the one before exactly (a receiver holding its fix): a held jump
    /// that it repeats is not confirmed by it.
    pub repeats_fix: bool,
    /// The onboard velocity's change over the step (m/s): the lag's regressor.
    pub velocity_change: [f64; 2],
    /// The calibration θ whose correction `residual` holds (speed scale, heading bias in radians,
    /// lag in seconds); 0 while none is in use.
    pub theta_in_use: [f64; 3],
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
    /// Seconds since the track the anchors stand on began: since they were last placed on a fix
    /// that nothing before it vouched for (a session's first, one after an outage or a break, one
    /// placed again before trust or after a held jump let go). Anchors placed by a fix that
    /// returned to where the vehicle's motion puts it stay on the track they came back to when a
    /// one-row spike's next fix is back where the fix before it was; after any other return they
    /// resume it once they have agreed for [`TRUST_S`]. Either way this goes on counting from it.
    #[serde(default)]
    pub track_age_s: f64,
    /// While a jump is held (`held_jump`): GNSS minus the dead reckoning from the last trusted
    /// fix before it, east/north (m).
    #[serde(default)]
    pub held_step_m: Option<[f64; 2]>,
    /// While a jump is held: the seconds since it arrived that confirmed it, moving or with a new
    /// fix (0 without one).
    #[serde(default)]
    pub held_step_confirmed_s: f64,
    /// While a jump is held: its arrival step's NIS against the vehicle's one-row noise (0
    /// without one).
    #[serde(default)]
    pub held_step_nis: f64,
    /// The anchors have been placed again on a disagreement [`DISPUTED_PLACEMENTS`] times or more
    /// without earning trust in between: the fix keeps moving unlike the vehicle from where they
    /// were placed (a drift from the moment of reacquisition), not one reflected fix, which the
    /// first placement again settles.
    #[serde(default)]
    pub disputed: bool,
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
        track_age_s: 0.0,
        held_step_m: None,
        held_step_confirmed_s: 0.0,
        held_step_nis: 0.0,
        disputed: false,
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

/// ‖v‖² of an east/north vector.
pub(super) fn norm_squared(v: [f64; 2]) -> f64 {
    v[0] * v[0] + v[1] * v[1]
}

/// vᵀ (a·I + C)⁻¹ v: `v`'s squared distance against a per-axis variance `a` (m²) and the
/// calibration's share `c`; ‖v‖²/a exactly when C = 0 (the calibration trusted by the clock).
pub(super) fn nis(v: [f64; 2], a: f64, c: &Mat2) -> f64 {
    if *c == [[0.0; 2]; 2] {
        return norm_squared(v) / a;
    }
    let (xx, xy, yy) = (a + c[0][0], 0.5 * (c[0][1] + c[1][0]), a + c[1][1]);
    let det = xx * yy - xy * xy;
    (yy * v[0] * v[0] - 2.0 * xy * v[0] * v[1] + xx * v[1] * v[1]) / det
}

/// The variance (m²) of a per-axis variance `a` plus the calibration's share `c` along `v`'s
/// direction (`a` alone for a zero `v`).
pub(super) fn along(v: [f64; 2], a: f64, c: &Mat2) -> f64 {
    let n = norm_squared(v);
    if n == 0.0 {
        return a;
    }
    a + (v[0] * (c[0][0] * v[0] + c[0][1] * v[1]) + v[1] * (c[1][0] * v[0] + c[1][1] * v[1])) / n
}
