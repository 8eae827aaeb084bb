//! The per-vehicle state of the offset channels, as a session snapshot carries it.
//!
//! Owns the fields of [`OffsetTracker`] (their order is the snapshot's layout) and of the level
//! snapshots. Must not hold behaviour: the anchors' step is in `tracker`, the levels' in `levels`.

use serde::{Deserialize, Serialize};

use super::anchors::Anchor;
use super::held_jump::StepHold;
use super::params::{ANCHOR_COUNT, LEVEL_COUNT, LEVEL_DELAY_S, OffsetEvidence, OffsetParams};
use crate::geo::LatLon;

/// Snapshot period of the levels (s of valid data).
pub(super) const LEVEL_SNAPSHOT_S: f64 = 30.0;
pub(super) const LEVEL_SNAPSHOTS: usize = (LEVEL_DELAY_S / LEVEL_SNAPSHOT_S) as usize + 2;

/// A level snapshot after `clock_s` seconds of valid data.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub(super) struct LevelSnapshot {
    pub(super) clock_s: f64,
    pub(super) levels: [f64; LEVEL_COUNT],
    pub(super) misfits: [f64; ANCHOR_COUNT],
}

/// The per-vehicle anchor state. Persists across the trajectory breaks of a stream (a gap up to
/// [`MAX_CARRY_GAP_S`] carries the anchors across); `push` never allocates.
///
/// Serialised (inside a session snapshot) it holds only the vehicle's state; the parameters come
/// back with [`OffsetTracker::restore`].
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct OffsetTracker {
    #[serde(skip, default = "OffsetParams::unnormalised")]
    pub(super) params: OffsetParams,
    pub(super) anchors: [Anchor; ANCHOR_COUNT],
    /// The same anchors never frozen: how far this vehicle's dead reckoning strays within each
    /// follow time, whatever the alarms did (the misfit learns from them).
    pub(super) shadows: [Anchor; ANCHOR_COUNT],
    /// Seconds the larger NIS has been at or beyond the decisive gate (NaN below it).
    pub(super) held_s: f64,
    pub(super) arrived_by_step: bool,
    pub(super) share: [f64; 2],
    /// Running mean of min(NIS/2, cap) per anchor, its clock, and the delayed snapshots.
    pub(super) levels: [f64; LEVEL_COUNT],
    pub(super) level_clock_s: f64,
    pub(super) snapshots: [LevelSnapshot; LEVEL_SNAPSHOTS],
    pub(super) snapshot_count: usize,
    pub(super) levels_in_use: [f64; LEVEL_COUNT],
    /// Sum of δ·min(NIS/2, cap) of the one-row residual and its seconds, over the settled rows so
    /// far: the step level in use until the vehicle's delayed level is known.
    #[serde(default)]
    pub(super) early_step: [f64; 2],
    #[serde(default)]
    pub(super) step_hold: Option<StepHold>,
    /// The row before was an outlier (its one-row residual at or beyond the follow gate): a jump
    /// that arrives now may be the fix coming back from that spike, which its step cannot tell.
    #[serde(default)]
    pub(super) after_spike: bool,
    /// Running mean of ln(1 + NIS/2) per shadow anchor, and the misfit in use (1 within the level's
    /// bound).
    pub(super) log_levels: [f64; ANCHOR_COUNT],
    pub(super) misfit_in_use: [f64; ANCHOR_COUNT],
    /// Seconds since the anchors were last placed.
    pub(super) age_s: f64,
    /// Seconds since the track they stand on began ([`OffsetEvidence::track_age_s`]).
    #[serde(default)]
    pub(super) track_age_s: f64,
    /// Anchors placed by a return, not yet confirmed by agreement: the age of the track they
    /// returned to.
    #[serde(default)]
    pub(super) returned_from_track_s: Option<f64>,
    /// Seconds the fix and the onboard motion have agreed since the anchors were placed, up to
    /// [`TRUST_S`]: from then on the anchors are trusted.
    pub(super) agreed_s: f64,
    /// Times the anchors were placed again on a disagreement since they last earned trust or
    /// the track began at a break ([`OffsetEvidence::disputed`]).
    #[serde(default)]
    pub(super) disputes: u32,
    pub(super) last: OffsetEvidence,
    /// The last usable sample the anchors moved to.
    pub(super) point: Option<AnchorPoint>,
}

/// The last usable sample: where the next step starts.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct AnchorPoint {
    pub fix: LatLon,
    /// Onboard velocity east/north (m/s).
    pub velocity: [f64; 2],
    pub time_s: f64,
    /// The fix repeated the previous usable sample's exactly: the receiver was holding it (at
    /// standstill, most receivers do), so a step away from it is the receiver catching up.
    #[serde(default)]
    pub repeated: bool,
}
