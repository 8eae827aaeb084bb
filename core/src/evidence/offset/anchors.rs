//! One dead-reckoning anchor: its offset from GNSS, the distance carried behind it, and its freeze.
//!
//! Owns an anchor's motion, its variance under normal driving, its freeze at the follow gate and
//! its following again, and the variance a telemetry gap adds. Must not test an offset (the
//! tracker hands in its NIS) nor know the vehicle's levels.

use serde::{Deserialize, Serialize};

use super::params::{
    AGREEMENT_S, FOLLOW_GATE, GAP_ACCELERATION_MPS2, OffsetParams, OffsetStep, norm_squared,
};
use crate::evidence::calibration::{apply, calibration_covariance, regressors};
use crate::evidence::linalg::Mat2;

/// One anchor's state.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub(super) struct Anchor {
    /// o: GNSS minus anchor (m).
    pub(super) offset: [f64; 2],
    /// U: net displacement dead-reckoned with the warm calibration behind the anchor, forgotten
    /// with o (m).
    pub(super) carried: [f64; 2],
    /// The same, dead-reckoned before the calibration was warm (m).
    pub(super) carried_raw: [f64; 2],
    /// Variance a telemetry gap added (m² per axis): the motion it may hide, or the error of the
    /// fix a receiver reacquired after it that the anchor was placed on. Forgotten with o².
    pub(super) gap_m2: f64,
    pub(super) frozen: bool,
    /// Of `frozen_s`, the seconds of the row that froze it (a step's own row: one row's noise).
    pub(super) step_row_s: f64,
    /// Seconds of agreement since the fix last disagreed (while frozen).
    pub(super) agreement_s: f64,
    /// While frozen: o at the last trusted fix, and the time, motion and gap variance since.
    pub(super) origin: [f64; 2],
    pub(super) frozen_s: f64,
    pub(super) carried_since_freeze: [f64; 2],
    pub(super) gap_since_freeze_m2: f64,
    /// Σ keep·Δv behind the anchor, forgotten with U (m/s): the lag's share of a re-basing.
    pub(super) velocity_change: [f64; 2],
    /// The calibration θ the offset's dead reckoning is expressed in (when re-based).
    pub(super) theta: [f64; 3],
}

impl Anchor {
    /// Moves the anchor by one step: U, the offset and the gaps' variance, each forgotten by
    /// `keep` (1 while frozen, the follow's share otherwise).
    pub(super) fn advance(
        &mut self,
        params: &OffsetParams,
        step: &OffsetStep,
        keep: f64,
        gap_m2: f64,
    ) {
        if params.rebase_on_calibration {
            self.rebase(step.theta_in_use);
        }
        self.carry(step, keep);
        for axis in 0..2 {
            self.velocity_change[axis] =
                keep * (self.velocity_change[axis] + step.velocity_change[axis]);
        }
        for axis in 0..2 {
            self.offset[axis] = keep * (self.offset[axis] + step.residual[axis]);
        }
        self.gap_m2 = keep * keep * (self.gap_m2 + gap_m2);
    }

    /// Re-expresses the dead reckoning carried behind the anchor in calibration `theta`. The
    /// correction a calibration adds to the residual is linear in the motion and the velocity
    /// change (H θ), so the offset under `theta` is the offset under the old θ plus H(U, ΣΔv)·Δθ,
    /// U and ΣΔv forgotten as the offset is. A frozen anchor's origin moves by the share of the
    /// motion carried before the freeze, so that the change since the freeze keeps its own.
    pub(super) fn rebase(&mut self, theta: [f64; 3]) {
        if theta == self.theta {
            return;
        }
        let change = [
            theta[0] - self.theta[0],
            theta[1] - self.theta[1],
            theta[2] - self.theta[2],
        ];
        let motion = [
            self.carried[0] + self.carried_raw[0],
            self.carried[1] + self.carried_raw[1],
        ];
        let shift = apply(&regressors(motion, self.velocity_change), &change);
        let before_freeze = [
            motion[0] - self.carried_since_freeze[0],
            motion[1] - self.carried_since_freeze[1],
        ];
        let origin_shift = apply(&regressors(before_freeze, [0.0; 2]), &change);
        for axis in 0..2 {
            self.offset[axis] += shift[axis];
            if self.frozen {
                self.origin[axis] += origin_shift[axis];
            }
        }
        self.theta = theta;
    }

    /// Adds one step's onboard motion to the part of U it was dead-reckoned with, and forgets
    /// both parts by `keep`.
    pub(super) fn carry(&mut self, step: &OffsetStep, keep: f64) {
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
    pub(super) fn variance(&self, params: &OffsetParams, k: usize) -> f64 {
        params.noise_m2[k]
            + params.raw_growth[k] * norm_squared(self.carried_raw)
            + params.calibrated_growth[k] * norm_squared(self.carried)
            + self.gap_m2
    }

    /// What the calibration's error (`calibration::in_use_error`) makes of the distance
    /// carried behind the anchor (m²); 0 when the calibration is trusted by the clock.
    pub(super) fn calibration_share(&self, error: &[f64; 3]) -> Mat2 {
        calibration_covariance(self.carried, error)
    }

    /// The same for the distance carried since the freeze.
    pub(super) fn calibration_share_since_freeze(&self, error: &[f64; 3]) -> Mat2 {
        calibration_covariance(self.carried_since_freeze, error)
    }

    /// Stops following at the current offset (the last trusted fix).
    pub(super) fn freeze(&mut self, step_row_s: f64) {
        self.frozen = true;
        self.step_row_s = step_row_s;
        self.agreement_s = 0.0;
        self.origin = self.offset;
        self.frozen_s = 0.0;
        self.carried_since_freeze = [0.0; 2];
        self.gap_since_freeze_m2 = 0.0;
    }

    /// After this row's test (`nis` in the vehicle's level): at the follow gate the anchor stops
    /// following; while frozen, it follows again after [`AGREEMENT_S`] of agreement.
    pub(super) fn gate(&mut self, nis: f64, delta_t: f64) {
        if nis >= FOLLOW_GATE {
            if !self.frozen {
                self.freeze(0.0);
            }
            self.agreement_s = 0.0;
        } else if self.frozen {
            self.agreement_s += delta_t;
            if self.agreement_s >= AGREEMENT_S {
                self.frozen = false;
            }
        }
    }
}

/// The variance (m² per axis) of the motion a gap of `delta_t` seconds may hide: (½·a·δ²)².
pub(super) fn gap_variance(delta_t: f64) -> f64 {
    let hidden = 0.5 * GAP_ACCELERATION_MPS2 * delta_t * delta_t;
    hidden * hidden
}
