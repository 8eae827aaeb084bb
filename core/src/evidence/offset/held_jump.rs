//! The held jump: an offset that arrived in one step and has not stepped back.
//!
//! Owns the choice between the jump's offset and the vehicle's own track, and when a hold ends.
//! Must not move the anchors or decide when a hold starts (the tracker does).

use serde::{Deserialize, Serialize};

use super::params::norm_squared;

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

    /// Adds one step's residual; returns whether the jump still holds.
    pub(super) fn advance(&mut self, residual: [f64; 2], delta_t: f64) -> bool {
        for (offset, change) in self.offset.iter_mut().zip(residual) {
            *offset += change;
        }
        self.held_s += delta_t;
        self.held_s <= MAX_STEP_HOLD_S && !self.nearer_track(self.offset)
    }
}
