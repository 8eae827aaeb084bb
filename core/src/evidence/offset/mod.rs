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
//!
//! Inside, each file uses only those listed before it: `params` (the gates, the parameters, the
//! step in and the channels out), `misfit`, `anchors` (one anchor), `held_jump`, `state` (the
//! per-vehicle fields, the snapshot's layout), `levels` (the vehicle's levels), `tracker` (the
//! step, `push`, in named steps), and `fit` (the parameters from training points).

mod anchors;
mod fit;
mod held_jump;
mod levels;
mod misfit;
mod params;
mod state;
mod tracker;

#[cfg(test)]
mod tests;

pub use fit::{
    CALIBRATED_GROWTH_FLOOR, CHI2_2_AT_FIT_QUANTILE, FIT_QUANTILE, MIN_OFFSET_POINTS, OffsetPoint,
    RAW_GROWTH_PRIOR, offset_params_from_points,
};
pub use held_jump::{MAX_STEP_HOLD_S, RETURN_SHARE};
pub use misfit::MISFIT_MAX;
pub use params::{
    AGREEMENT_S, ANCHOR_COUNT, DECISIVE_GATE, FOLLOW_GATE, FOLLOW_S, GAP_ACCELERATION_MPS2,
    LEVEL_DELAY_S, LEVEL_RANGE, MAX_CARRY_GAP_S, NOISE_RANGE_M2, OffsetEvidence, OffsetParams,
    OffsetStep, REACQUISITION_M2, SHARE_S, STEP_GROWTH_S, TRUST_S,
};
pub use state::{AnchorPoint, OffsetTracker};
