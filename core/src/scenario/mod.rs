//! Labelled subtle-attack scenarios (SPEC §9).
//!
//! The AV-GPS attacks are not subtle (frozen fixes while stopped, jumps of hundreds of km), so the detector
//! is trained and judged on attacks injected here: into real normal trajectories ([`inject`], [`generate`])
//! and into simulated drives ([`simulate_drive`]), whose specs can be drawn at random from a
//! [`DriveDistribution`]. Fleet scenes ([`generate_fleet`]) put many such drives in one area with a
//! regional spoofer that captures every receiver in its radius. Everything is deterministic from seeds.
//!
//! Geodesy (metres east/north → latitude/longitude) is [`crate::geo::displace_fix`]. This module owns
//! attack kinds, injection, scenario plans, simulated drives, their distributions, fleet scenes and the
//! receiver flags a simulated receiver raises ([`raise_flags`]); it must not compute evidence or run a
//! detector (tests and experiments do that with the scenarios it returns).

mod attack;
mod drive;
mod fleet;
mod impairments;
mod mix;
mod pieces;
mod plan;
mod randomise;
mod receiver_flags;
mod spec;

pub use attack::{AttackKind, AttackSpec, InjectedTrack, inject};
pub use drive::{SimulatedDrive, TrueState, simulate_drive, simulate_drive_with_truth};
pub use fleet::{
    CaptureEpisode, CapturedFix, FleetScene, FleetSpec, FleetTruth, RegionalAttack, Spoofer,
    VehicleTruth, generate_fleet, offset_from_spoofer_m,
};
pub use impairments::{
    GnssOutage, HeadingBiasWander, Multipath, OnboardErrors, Outages, Reacquisition, StaticHold,
};
pub use mix::{log_uniform, training_attack};
pub use pieces::{Piece, pieces, with_warmup};
pub use plan::{AttackDuration, RAMP_SWEEP_VELOCITIES_MPS, ScenarioPlan, generate};
pub use randomise::{ClippedNormal, DriveDistribution, Range, UrbanToRural};
pub use receiver_flags::{FlagWindow, raise_flags};
pub use spec::{
    DriveSpec, GnssNoise, HIGHWAY_CRUISE_MAX_MPS, OnboardNoise, RoadKind, SpeedProfile,
    TurnBehaviour,
};

/// Ramp drift velocities accepted by [`AttackKind::RampDrift`] (m/s, inclusive; SPEC §9).
pub const RAMP_VELOCITY_RANGE_MPS: (f64, f64) = (0.05, 2.0);
/// Accelerations accepted by [`AttackKind::AcceleratingDrift`] (m/s², inclusive; SPEC §9).
pub const DRIFT_ACCELERATION_RANGE_MPS2: (f64, f64) = (0.01, 0.5);
/// Offsets accepted by [`AttackKind::Jump`] (m; lower bound exclusive). The upper bound keeps the
/// local-radii conversion meaningful while still covering the AV-GPS-style teleports of hundreds of km.
pub const JUMP_OFFSET_RANGE_M: (f64, f64) = (0.0, 1_000_000.0);
/// A step longer than this starts a new trajectory (SPEC §3); an attack must not span one.
pub const MAX_STEP_S: f64 = 5.0;

/// Everything that can go wrong when building scenarios.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ScenarioError {
    /// A field of an [`AttackSpec`] is non-finite or out of range.
    #[error("attack {field} must be {expected}, got {value}")]
    InvalidAttack {
        field: &'static str,
        expected: String,
        value: f64,
    },
    /// A field of a [`DriveSpec`] is non-finite or out of range.
    #[error("drive spec {field} must be {expected}, got {value}")]
    InvalidDrive {
        field: &'static str,
        expected: String,
        value: f64,
    },
    /// A field of a [`DriveDistribution`] is non-finite or out of range.
    #[error("drive distribution {field} must be {expected}, got {value}")]
    InvalidDistribution {
        field: &'static str,
        expected: String,
        value: f64,
    },
    /// A field of a [`FleetSpec`] is non-finite or out of range.
    #[error("fleet scene {field} must be {expected}, got {value}")]
    InvalidFleet {
        field: &'static str,
        expected: String,
        value: f64,
    },
    /// A field of a [`FlagWindow`] is non-finite or out of range.
    #[error("receiver flag window {field} must be {expected}, got {value}")]
    InvalidFlagWindow {
        field: &'static str,
        expected: String,
        value: f64,
    },
    /// A [`ScenarioPlan`] is unusable.
    #[error("scenario plan {field}: {problem}")]
    InvalidPlan {
        field: &'static str,
        problem: String,
    },
    /// The base track has no records.
    #[error("track `{vehicle_id}` has no records")]
    EmptyTrack { vehicle_id: String },
    /// The first timestamp, from which the onset is measured, is not finite.
    #[error("track `{vehicle_id}` starts with a non-finite timestamp {timestamp_s}")]
    InvalidStartTime {
        vehicle_id: String,
        timestamp_s: f64,
    },
    /// The attack window does not lie inside the track's time span.
    #[error(
        "attack window [{start_s}, {end_s}) s after the first sample does not fit inside track `{vehicle_id}`, \
         which spans {span_s} s"
    )]
    AttackOutsideTrack {
        vehicle_id: String,
        start_s: f64,
        end_s: f64,
        span_s: f64,
    },
    /// No row has a timestamp inside the attack window (e.g. the window falls in a gap).
    #[error("attack window [{start_s}, {end_s}) s of track `{vehicle_id}` contains no rows")]
    NoRowsInWindow {
        vehicle_id: String,
        start_s: f64,
        end_s: f64,
    },
    /// Rows inside the window are not one contiguous run (time is not monotonic around the window).
    #[error(
        "attack window of track `{vehicle_id}` is not a contiguous run of rows: row {row} lies outside it \
         between attacked rows (timestamps must increase; split the track into trajectories first)"
    )]
    NonContiguousWindow { vehicle_id: String, row: usize },
    /// The attack would straddle a trajectory start (gap > 5 s, or a source break flag).
    #[error(
        "attack window of track `{vehicle_id}` spans a trajectory break at row {row}; an attack event must lie \
         inside one trajectory"
    )]
    SpansTrajectoryBreak { vehicle_id: String, row: usize },
    /// A row inside the window is already spoofed: injection is for normal data only.
    #[error(
        "row {row} of track `{vehicle_id}` inside the attack window is already labelled spoofed; inject only \
         into normal data"
    )]
    OverlapsSpoofed { vehicle_id: String, row: usize },
    /// A frozen-position attack needs a valid fix to hold.
    #[error(
        "frozen attack on track `{vehicle_id}`: the fix at onset row {row} is not a valid position"
    )]
    InvalidOnsetFix { vehicle_id: String, row: usize },
    /// The displaced fix leaves the valid latitude range.
    #[error(
        "attack on track `{vehicle_id}` moves row {row} to latitude {latitude_deg}, outside [-90, 90]"
    )]
    DisplacedOutOfRange {
        vehicle_id: String,
        row: usize,
        latitude_deg: f64,
    },
    /// The plan's attack cannot be placed in the middle part of a base track.
    #[error(
        "cannot place a {duration_s} s attack in the middle part (margins {margin_fraction} of the span) of track \
         `{vehicle_id}`, which spans {span_s} s"
    )]
    AttackDoesNotFit {
        vehicle_id: String,
        duration_s: f64,
        span_s: f64,
        margin_fraction: f64,
    },
}

/// Unit vector (east, north) of a bearing in degrees clockwise from north.
fn bearing_unit(direction_deg: f64) -> (f64, f64) {
    let rad = direction_deg.to_radians();
    (rad.sin(), rad.cos())
}

/// Formats a number compactly for names: shortest round-trip form (`0.25`, `90`, `1000`).
fn compact(value: f64) -> String {
    format!("{value}")
}

/// The normal (not spoofed) stretches of a labelled track as separate tracks
/// (`<vehicle>/normal<k>`, each starting a trajectory), ready to be injection bases.
pub fn normal_runs(track: &crate::sample::Track) -> Vec<crate::sample::Track> {
    use crate::sample::Track;
    let mut out: Vec<Track> = Vec::new();
    let mut current: Vec<crate::sample::Record> = Vec::new();
    let flush = |records: Vec<crate::sample::Record>, out: &mut Vec<Track>| {
        let mut records = records;
        if let Some(first) = records.first_mut() {
            first.trajectory_break = true;
            out.push(Track {
                vehicle_id: format!("{}/normal{}", track.vehicle_id, out.len()),
                records,
            });
        }
    };
    for record in &track.records {
        if record.label == Some(true) {
            flush(std::mem::take(&mut current), &mut out);
        } else {
            current.push(record.clone());
        }
    }
    flush(current, &mut out);
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn normal_runs_split_at_spoofed_rows_and_start_trajectories() {
        use crate::sample::{Record, Sample, Track};
        let labels = [
            Some(false),
            None,
            Some(true),
            Some(true),
            Some(false),
            Some(false),
        ];
        let records = labels
            .iter()
            .enumerate()
            .map(|(i, &label)| Record {
                sample: Sample::new(i as f64, 32.0, -110.0, 1.0, 0.0),
                label,
                comparator_alarm: None,
                line: i as u64 + 2,
                trajectory_break: false,
                warmup: false,
            })
            .collect();
        let track = Track {
            vehicle_id: "v".into(),
            records,
        };
        let runs = normal_runs(&track);
        let lines: Vec<Vec<u64>> = runs
            .iter()
            .map(|t| t.records.iter().map(|r| r.line).collect())
            .collect();
        assert_eq!(lines, vec![vec![2, 3], vec![6, 7]]);
        assert_eq!(runs[1].vehicle_id, "v/normal1");
        assert!(runs.iter().all(|t| t.records[0].trajectory_break));
    }
}
