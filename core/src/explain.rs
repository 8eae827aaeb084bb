//! Why a detection says what it says: the dominant evidence of a sample, the offset from the
//! dead-reckoning anchor and the drift rate (`docs/detector.md` §7.2). Operators and autopilots act
//! on "a 480 m jump to the north-east", not on a bare probability.
//!
//! Owns the classification of a sample's evidence. Must not build evidence, score or alarm.

use serde::{Deserialize, Serialize};

use crate::evidence::Evidence;
use crate::evidence::offset::{DECISIVE_GATE, FOLLOW_GATE};

/// A fix repeated exactly for this long (s) is a frozen feed (a receiver's fix jitters).
pub const FROZEN_FIX_S: f64 = 2.0;

/// The dominant evidence of a sample, strongest claim first.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum EvidenceKind {
    /// Nothing stands out.
    #[default]
    None,
    /// The fix stepped away from the anchor in one sample and stays there.
    Jump,
    /// The fix is held away from the anchor (it got there gradually, or hops around).
    HeldOffset,
    /// GNSS and the onboard motion disagree in direction over 10–120 s.
    Drift,
    /// The fix repeats exactly while time goes on.
    FrozenFix,
    /// The residual energy is high without a held offset or a drift (the model's own reading).
    Energy,
}

impl EvidenceKind {
    /// Every kind.
    pub const ALL: [Self; 6] = [
        Self::None,
        Self::Jump,
        Self::HeldOffset,
        Self::Drift,
        Self::FrozenFix,
        Self::Energy,
    ];

    /// The kind of a [`Self::name`]; `None` for a name this build does not know.
    pub fn from_name(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|kind| kind.name() == name)
    }

    /// The snake_case name (logs, CSV, JSON).
    pub fn name(self) -> &'static str {
        match self {
            Self::None => "none",
            Self::Jump => "jump",
            Self::HeldOffset => "held_offset",
            Self::Drift => "drift",
            Self::FrozenFix => "frozen_fix",
            Self::Energy => "energy",
        }
    }
}

/// What a sample's evidence says, in a form an operator can act on.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Explanation {
    pub dominant: EvidenceKind,
    /// GNSS minus the slow anchor, east/north (m), or while a jump is held, minus the dead reckoning
    /// from the last trusted fix before it; 0 without offset evidence.
    pub offset_m: [f64; 2],
    /// The drift rate GNSS shows against the onboard motion, east/north (m/s); 0 without drift
    /// evidence.
    pub drift_rate_mps: [f64; 2],
}

impl Explanation {
    /// The explanation of `evidence`; `positive` is p̂ ≥ θ (the model's own verdict, the only
    /// reason left when no channel stands out).
    pub fn of(evidence: &Evidence, positive: bool) -> Self {
        let drift = evidence.drift.as_ref();
        let offset = evidence.offset.as_ref();
        let dominant = if drift.is_some_and(|d| d.stale_fix_s >= FROZEN_FIX_S) {
            EvidenceKind::FrozenFix
        } else if let Some(o) = offset.filter(|o| o.max_nis() >= DECISIVE_GATE) {
            if o.arrived_by_step {
                EvidenceKind::Jump
            } else {
                EvidenceKind::HeldOffset
            }
        } else if offset.is_some_and(|o| o.held_step_m.is_some()) {
            EvidenceKind::HeldOffset
        } else if drift.is_some_and(|d| d.statistic >= 1.0) {
            EvidenceKind::Drift
        } else if offset.is_some_and(|o| o.max_nis() >= FOLLOW_GATE) {
            EvidenceKind::HeldOffset
        } else if positive {
            EvidenceKind::Energy
        } else {
            EvidenceKind::None
        };
        Self {
            dominant,
            offset_m: offset.map_or([0.0; 2], |o| o.held_step_m.unwrap_or(o.offset_m)),
            drift_rate_mps: drift.map_or([0.0; 2], |d| d.rate_mps),
        }
    }

    /// Distance (m) and bearing (degrees clockwise from north, in [0, 360)) of the offset.
    pub fn offset_polar(&self) -> (f64, f64) {
        polar(self.offset_m)
    }

    /// Speed (m/s) and bearing (degrees) of the drift rate.
    pub fn drift_polar(&self) -> (f64, f64) {
        polar(self.drift_rate_mps)
    }
}

/// (‖v‖, bearing of v clockwise from north in [0, 360)) of an east/north vector.
fn polar(v: [f64; 2]) -> (f64, f64) {
    let bearing = v[0].atan2(v[1]).to_degrees();
    (
        v[0].hypot(v[1]),
        if bearing < 0.0 {
            bearing + 360.0
        } else {
            bearing
        },
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn polar_bearings_by_hand() {
        let (d, b) = polar([3.0, 4.0]);
        assert_eq!(d, 5.0);
        assert!((b - 36.869_897_645_844_02).abs() < 1e-12);
        assert_eq!(polar([0.0, -2.0]), (2.0, 180.0));
        assert_eq!(polar([-1.0, 0.0]), (1.0, 270.0));
    }
}
