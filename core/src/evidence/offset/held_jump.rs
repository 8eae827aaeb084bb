//! The held jump: an offset that arrived in one step and has not stepped back.
//!
//! Owns the choice between the jump's offset and the vehicle's own track, and when a hold ends.
//! Must not move the anchors or decide when a hold starts (the tracker does).

use serde::{Deserialize, Serialize};

use super::params::{OffsetStep, norm_squared};
use crate::evidence::drift::MOVING_MPS;

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
pub(super) struct StepHold {
    /// The offset the jump arrived with (m).
    pub(super) arrival: [f64; 2],
    /// GNSS minus the dead reckoning from the last trusted fix before the jump (m).
    pub(super) offset: [f64; 2],
    /// Seconds since the jump.
    pub(super) held_s: f64,
    /// Of them, the seconds that confirmed the jump: the vehicle moved (dead-reckoned at
    /// [`MOVING_MPS`] or faster), or the receiver computed a new fix. A receiver that latches a
    /// reflected fix as the vehicle stops repeats it exactly for as long as the stop lasts, which
    /// confirms nothing new; a receiver that keeps fixing a standing vehicle where it jumped does.
    #[serde(default)]
    pub(super) confirmed_s: f64,
    /// The arrival's one-row residual against the vehicle's one-row noise (the step test's NIS,
    /// with what a reacquiring receiver may still step): how far beyond a receiver's own step the
    /// jump was. 0 when the fix left no followed track, so that such a hold pages only on the
    /// anchors' NIS: when an anchor was frozen on the row before (inside an offset already held, a
    /// one-row dip back within the follow gate is no jump from the track); when the fix before
    /// was one the receiver held (a receiver that holds its fix at standstill steps to where the
    /// vehicle is once it moves off, by as far as its error wandered during the stop); when the
    /// row before was itself an outlier (a fix coming back from a multipath spike steps as far as
    /// the spike did, and one step cannot tell which of the two was the track); and once the fix
    /// has come back within the follow gate while the hold lasted (what arrives then is no longer
    /// the step this hold arrived with).
    #[serde(default)]
    pub(super) arrival_nis: f64,
}

impl StepHold {
    /// Whether `offset` is nearer the vehicle's own track than the offset the jump arrived with.
    pub(super) fn nearer_track(&self, offset: [f64; 2]) -> bool {
        let from_arrival = [offset[0] - self.arrival[0], offset[1] - self.arrival[1]];
        norm_squared(offset) <= norm_squared(from_arrival)
    }

    /// A one-row step that brings the fix nearer the track than the jump: the spoofer let go.
    pub(super) fn stepped_back(&self, residual: [f64; 2]) -> bool {
        self.nearer_track([self.offset[0] + residual[0], self.offset[1] + residual[1]])
    }

    /// Adds one step's residual and dead-reckoned motion; returns whether the jump still holds.
    pub(super) fn advance(&mut self, step: &OffsetStep) -> bool {
        for (offset, change) in self.offset.iter_mut().zip(step.residual) {
            *offset += change;
        }
        self.held_s += step.delta_t;
        if !step.repeats_fix || norm_squared(step.motion).sqrt() >= MOVING_MPS * step.delta_t {
            self.confirmed_s += step.delta_t;
        }
        self.held_s <= MAX_STEP_HOLD_S && !self.nearer_track(self.offset)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn step(motion: [f64; 2], delta_t: f64, repeats_fix: bool) -> OffsetStep {
        OffsetStep {
            residual: [0.0; 2],
            motion,
            delta_t,
            calibrated: false,
            calibration_error: [0.0; 3],
            reports_placements: false,
            leaves_held_fix: false,
            repeats_fix,
            velocity_change: [0.0; 2],
            theta_in_use: [0.0; 3],
        }
    }

    fn hold() -> StepHold {
        StepHold {
            arrival: [20.0, 0.0],
            offset: [20.0, 0.0],
            held_s: 0.0,
            confirmed_s: 0.0,
            arrival_nis: 400.0,
        }
    }

    #[test]
    fn a_held_jump_repeated_by_a_receiver_holding_its_fix_counts_only_the_seconds_moved() {
        let mut hold = hold();
        // 2 m in 1 s (moving), 0.3 m in 0.5 s (below 1 m/s), then standing for 3 s, every fix a
        // repeat of the one before.
        assert!(hold.advance(&step([0.0, 2.0], 1.0, true)));
        assert!(hold.advance(&step([0.3, 0.0], 0.5, true)));
        assert!(hold.advance(&step([0.0, 0.0], 3.0, true)));
        assert_eq!((hold.held_s, hold.confirmed_s), (4.5, 1.0));
        // Exactly 1 m/s counts as moving.
        assert!(hold.advance(&step([0.6, 0.8], 1.0, true)));
        assert_eq!(hold.confirmed_s, 2.0);
    }

    #[test]
    fn a_new_fix_confirms_a_held_jump_on_a_standing_vehicle() {
        let mut hold = hold();
        // Standing: two new fixes count, a repeated one does not.
        assert!(hold.advance(&step([0.0, 0.0], 1.0, false)));
        assert!(hold.advance(&step([0.0, 0.0], 0.5, true)));
        assert!(hold.advance(&step([0.1, 0.0], 2.0, false)));
        assert_eq!((hold.held_s, hold.confirmed_s), (3.5, 3.0));
    }
}
