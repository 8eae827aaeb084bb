//! Attack kinds, attack specs and injection into a normal track.
//!
//! Owns attack kinds and their injection. Must not plan scenario sets (that is `plan.rs`).

use serde::{Deserialize, Serialize};

use super::{
    DRIFT_ACCELERATION_RANGE_MPS2, JUMP_OFFSET_RANGE_M, MAX_STEP_S, RAMP_VELOCITY_RANGE_MPS,
    ScenarioError, bearing_unit, compact,
};
use crate::geo::displace_fix;
use crate::sample::{Record, Track};

/// What the spoofer does to the GNSS position during the attack window (SPEC §9).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case", deny_unknown_fields)]
pub enum AttackKind {
    /// The spoofed fix drifts away from the truth at a constant velocity: offset = v·τ.
    RampDrift {
        /// Drift velocity v (m/s, 0.05–2).
        velocity_mps: f64,
    },
    /// The drift itself accelerates: offset = ½·a·τ².
    AcceleratingDrift {
        /// Drift acceleration a (m/s², 0.01–0.5).
        acceleration_mps2: f64,
    },
    /// The true fix at onset is replayed for the whole window.
    FrozenPosition,
    /// A constant offset from the first attacked row on.
    Jump {
        /// Offset (m, > 0, ≤ 1000 km).
        offset_m: f64,
    },
    /// A ramp drift whose fix shows the true position for one second every `period_s` seconds:
    /// a spoofer that toggles between the false and the true fix, so that a detector which clears
    /// on agreement re-trusts GNSS while the drift goes on.
    TogglingDrift {
        /// Drift velocity v (m/s, 0.05–2).
        velocity_mps: f64,
        /// Seconds between the toggles to the truth (2–600).
        period_s: f64,
    },
    /// The fix teleports every `hold_s` seconds to a new place between ½ and 1 × `offset_m` from the
    /// true position at onset, and repeats exactly in between: the hopping attack of AV-GPS
    /// Dataset-2's third trajectory (jumps of tens of km every ~4 s, the fix frozen between them).
    Hopping {
        /// Largest hop distance (m, > 0, ≤ 1000 km).
        offset_m: f64,
        /// Seconds between hops (1–60).
        hold_s: f64,
    },
}

/// Hop `k` of a hopping attack turns by the golden angle from the previous one and lands at
/// ½ + ½·frac(k·φ⁻¹) of the largest distance: spread out, never repeating, and deterministic.
const GOLDEN_ANGLE_DEG: f64 = 137.507_764_050_037_85;
const INVERSE_GOLDEN_RATIO: f64 = 0.618_033_988_749_894_9;
/// Seconds between hops accepted by [`AttackKind::Hopping`] (inclusive).
const HOP_HOLD_RANGE_S: (f64, f64) = (1.0, 60.0);
/// Seconds between toggles accepted by [`AttackKind::TogglingDrift`] (inclusive).
const TOGGLE_PERIOD_RANGE_S: (f64, f64) = (2.0, 600.0);
/// How long a toggling spoofer shows the true position (s).
const TOGGLE_LENGTH_S: f64 = 1.0;

impl AttackKind {
    /// Stable snake_case family name (the serde tag), for grouping results per attack type.
    pub fn family(&self) -> &'static str {
        match self {
            Self::RampDrift { .. } => "ramp_drift",
            Self::TogglingDrift { .. } => "toggling_drift",
            Self::AcceleratingDrift { .. } => "accelerating_drift",
            Self::FrozenPosition => "frozen_position",
            Self::Jump { .. } => "jump",
            Self::Hopping { .. } => "hopping",
        }
    }

    /// The magnitude (m/s, m/s² or m), or `None` for a frozen position.
    pub fn magnitude(&self) -> Option<f64> {
        match *self {
            Self::RampDrift { velocity_mps } | Self::TogglingDrift { velocity_mps, .. } => {
                Some(velocity_mps)
            }
            Self::AcceleratingDrift { acceleration_mps2 } => Some(acceleration_mps2),
            Self::FrozenPosition => None,
            Self::Jump { offset_m } | Self::Hopping { offset_m, .. } => Some(offset_m),
        }
    }

    /// Whether the spoofed fix is placed relative to the fix at onset (frozen position, hopping)
    /// instead of following the true position.
    pub fn follows_onset_fix(&self) -> bool {
        matches!(self, Self::FrozenPosition | Self::Hopping { .. })
    }

    /// Short name for vehicle ids and reports: `ramp-0.25mps`, `accel-0.1mps2`, `frozen`, `jump-50m`.
    pub fn describe(&self) -> String {
        match *self {
            Self::RampDrift { velocity_mps } => format!("ramp-{}mps", compact(velocity_mps)),
            Self::TogglingDrift {
                velocity_mps,
                period_s,
            } => format!("toggle-{}mps-{}s", compact(velocity_mps), compact(period_s)),
            Self::AcceleratingDrift { acceleration_mps2 } => {
                format!("accel-{}mps2", compact(acceleration_mps2))
            }
            Self::FrozenPosition => "frozen".to_owned(),
            Self::Jump { offset_m } => format!("jump-{}m", compact(offset_m)),
            Self::Hopping { offset_m, hold_s } => {
                format!("hop-{}m-{}s", compact(offset_m), compact(hold_s))
            }
        }
    }

    /// Checks the magnitude against the SPEC §9 ranges.
    pub fn validate(&self) -> Result<(), ScenarioError> {
        let (field, value, (low, high), low_inclusive, unit) = match *self {
            Self::RampDrift { velocity_mps } => (
                "velocity_mps",
                velocity_mps,
                RAMP_VELOCITY_RANGE_MPS,
                true,
                "m/s",
            ),
            Self::AcceleratingDrift { acceleration_mps2 } => (
                "acceleration_mps2",
                acceleration_mps2,
                DRIFT_ACCELERATION_RANGE_MPS2,
                true,
                "m/s²",
            ),
            Self::TogglingDrift {
                velocity_mps,
                period_s,
            } => {
                if !(period_s.is_finite()
                    && (TOGGLE_PERIOD_RANGE_S.0..=TOGGLE_PERIOD_RANGE_S.1).contains(&period_s))
                {
                    return Err(ScenarioError::InvalidAttack {
                        field: "period_s",
                        expected: format!(
                            "a finite number in [{}, {}] s",
                            TOGGLE_PERIOD_RANGE_S.0, TOGGLE_PERIOD_RANGE_S.1
                        ),
                        value: period_s,
                    });
                }
                (
                    "velocity_mps",
                    velocity_mps,
                    RAMP_VELOCITY_RANGE_MPS,
                    true,
                    "m/s",
                )
            }
            Self::FrozenPosition => return Ok(()),
            Self::Jump { offset_m } => ("offset_m", offset_m, JUMP_OFFSET_RANGE_M, false, "m"),
            Self::Hopping { offset_m, hold_s } => {
                if !(hold_s.is_finite()
                    && (HOP_HOLD_RANGE_S.0..=HOP_HOLD_RANGE_S.1).contains(&hold_s))
                {
                    return Err(ScenarioError::InvalidAttack {
                        field: "hold_s",
                        expected: format!(
                            "a finite number in [{}, {}] s",
                            HOP_HOLD_RANGE_S.0, HOP_HOLD_RANGE_S.1
                        ),
                        value: hold_s,
                    });
                }
                ("offset_m", offset_m, JUMP_OFFSET_RANGE_M, false, "m")
            }
        };
        let above_low = if low_inclusive {
            value >= low
        } else {
            value > low
        };
        if value.is_finite() && above_low && value <= high {
            return Ok(());
        }
        let open = if low_inclusive { "[" } else { "(" };
        Err(ScenarioError::InvalidAttack {
            field,
            expected: format!("a finite number in {open}{low}, {high}] {unit}"),
            value,
        })
    }

    /// Offset magnitude (m) from the true position τ seconds after onset; `None` for the kinds that
    /// place the fix relative to the onset fix instead (frozen position, hopping).
    fn offset_m(&self, tau_s: f64) -> Option<f64> {
        match *self {
            Self::RampDrift { velocity_mps } => Some(velocity_mps * tau_s),
            Self::TogglingDrift {
                velocity_mps,
                period_s,
            } => {
                let showing_truth = tau_s >= period_s && tau_s % period_s < TOGGLE_LENGTH_S;
                Some(if showing_truth {
                    0.0
                } else {
                    velocity_mps * tau_s
                })
            }
            Self::AcceleratingDrift { acceleration_mps2 } => {
                Some(0.5 * acceleration_mps2 * tau_s * tau_s)
            }
            Self::FrozenPosition | Self::Hopping { .. } => None,
            Self::Jump { offset_m } => Some(offset_m),
        }
    }

    /// Where the fix sits relative to the onset fix τ seconds after onset (east, north, m): zero for a
    /// frozen position, the current hop for hopping; `None` for the kinds that follow the true position.
    fn onset_offset_en_m(&self, direction_deg: f64, tau_s: f64) -> Option<(f64, f64)> {
        match *self {
            Self::FrozenPosition => Some((0.0, 0.0)),
            Self::Hopping { offset_m, hold_s } => {
                let hop = (tau_s / hold_s).floor().max(0.0);
                let distance = offset_m * (0.5 + 0.5 * (hop * INVERSE_GOLDEN_RATIO).fract());
                let (unit_e, unit_n) = bearing_unit(direction_deg + hop * GOLDEN_ANGLE_DEG);
                Some((distance * unit_e, distance * unit_n))
            }
            _ => None,
        }
    }
}

/// One attack to inject: kind and magnitude, direction and time window.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AttackSpec {
    /// What the spoofer does.
    pub kind: AttackKind,
    /// Direction in which the spoofed fix moves away from the truth, degrees clockwise from north,
    /// in [0, 360). Irrelevant (but still validated) for a frozen position.
    pub direction_deg: f64,
    /// Attack start, seconds after the track's first sample.
    pub onset_s: f64,
    /// Attack length in seconds (> 0); rows with onset ≤ t − t0 < onset + duration are attacked.
    pub duration_s: f64,
    /// Provenance only: the seed of the scenario plan that placed this attack (shown in names).
    /// Injection itself is deterministic and does not draw random numbers.
    #[serde(default)]
    pub seed: Option<u64>,
}

impl AttackSpec {
    /// Checks every field: magnitude in range, direction in [0, 360), onset ≥ 0, duration > 0, all finite.
    pub fn validate(&self) -> Result<(), ScenarioError> {
        self.kind.validate()?;
        let invalid = |field, expected: &str, value| ScenarioError::InvalidAttack {
            field,
            expected: expected.to_owned(),
            value,
        };
        let d = self.direction_deg;
        if !(d.is_finite() && (0.0..360.0).contains(&d)) {
            return Err(invalid(
                "direction_deg",
                "a finite bearing in [0, 360) degrees",
                d,
            ));
        }
        let onset = self.onset_s;
        if !(onset.is_finite() && onset >= 0.0) {
            return Err(invalid(
                "onset_s",
                "a finite, non-negative number of seconds",
                onset,
            ));
        }
        let duration = self.duration_s;
        if !(duration.is_finite() && duration > 0.0) {
            return Err(invalid(
                "duration_s",
                "a finite, positive number of seconds",
                duration,
            ));
        }
        Ok(())
    }

    /// Short name, e.g. `ramp-0.25mps-dir90-on120s-dur60s-s7` (the seed part only when recorded).
    pub fn describe(&self) -> String {
        let mut name = format!(
            "{}-dir{}-on{}s-dur{}s",
            self.kind.describe(),
            compact(self.direction_deg),
            compact(self.onset_s),
            compact(self.duration_s)
        );
        if let Some(seed) = self.seed {
            name.push_str(&format!("-s{seed}"));
        }
        name
    }

    /// Offset (east, north) in metres from the true position at τ seconds after onset; `None` for the
    /// kinds placed relative to the onset fix (frozen position, hopping).
    pub fn offset_en_m(&self, tau_s: f64) -> Option<(f64, f64)> {
        let magnitude = self.kind.offset_m(tau_s)?;
        let (unit_e, unit_n) = bearing_unit(self.direction_deg);
        Some((magnitude * unit_e, magnitude * unit_n))
    }
}

/// A track with one injected attack, and where that attack is.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct InjectedTrack {
    /// The attacked track: vehicle id `<base>#<attack description>`, every row labelled.
    pub track: Track,
    /// Vehicle id of the normal track the attack was injected into.
    pub base_vehicle_id: String,
    /// The attack as injected.
    pub attack: AttackSpec,
    /// Index of the first attacked (label = spoofed) row.
    pub first_attack_row: usize,
    /// Index of the last attacked row (inclusive).
    pub last_attack_row: usize,
}

impl InjectedTrack {
    /// Indices of the attacked rows.
    pub fn attack_rows(&self) -> std::ops::RangeInclusive<usize> {
        self.first_attack_row..=self.last_attack_row
    }

    /// Number of attacked rows.
    pub fn attack_row_count(&self) -> usize {
        self.last_attack_row - self.first_attack_row + 1
    }

    /// Absolute timestamp (s) of the attack onset: first sample's timestamp + `onset_s`.
    pub fn onset_timestamp_s(&self) -> f64 {
        self.track
            .records
            .first()
            .map_or(f64::NAN, |r| r.sample.timestamp_s)
            + self.attack.onset_s
    }
}

/// Returns a copy of a normal `track` with `attack` injected (see the module docs for the geodesy).
///
/// Rows with onset ≤ t − t0 < onset + duration get a displaced GNSS fix and `label = Some(true)`;
/// every other row keeps its fix and label, except that `None` becomes `Some(false)`. Onboard speed and
/// heading are untouched (the spoofer does not control them). `comparator_alarm` is cleared on every row:
/// a source detector never saw the injected positions.
pub fn inject(track: &Track, attack: &AttackSpec) -> Result<InjectedTrack, ScenarioError> {
    attack.validate()?;
    let (first, last) = locate_attack_rows(track, attack)?;
    let vehicle_id = &track.vehicle_id;
    if let Some(row) = (first..=last).find(|&i| track.records[i].label == Some(true)) {
        return Err(ScenarioError::OverlapsSpoofed {
            vehicle_id: vehicle_id.clone(),
            row,
        });
    }
    let t0 = track.records[0].sample.timestamp_s;
    let onset_fix = &track.records[first].sample;
    if attack.kind.follows_onset_fix()
        && !is_valid_fix(onset_fix.latitude_deg, onset_fix.longitude_deg)
    {
        return Err(ScenarioError::InvalidOnsetFix {
            vehicle_id: vehicle_id.clone(),
            row: first,
        });
    }
    let held_fix = (onset_fix.latitude_deg, onset_fix.longitude_deg);

    let mut records = Vec::with_capacity(track.records.len());
    for (row, record) in track.records.iter().enumerate() {
        let mut out = Record {
            label: Some(record.label.unwrap_or(false)),
            comparator_alarm: None,
            ..record.clone()
        };
        if (first..=last).contains(&row) {
            let s = &record.sample;
            let tau_s = s.timestamp_s - t0 - attack.onset_s;
            let (lat, lon) = match attack.offset_en_m(tau_s) {
                Some((east, north)) => displace_fix(s.latitude_deg, s.longitude_deg, east, north),
                None => {
                    let (east, north) = attack
                        .kind
                        .onset_offset_en_m(attack.direction_deg, tau_s)
                        .unwrap_or_default();
                    displace_fix(held_fix.0, held_fix.1, east, north)
                }
            };
            if lat.abs() > 90.0 {
                return Err(ScenarioError::DisplacedOutOfRange {
                    vehicle_id: vehicle_id.clone(),
                    row,
                    latitude_deg: lat,
                });
            }
            out.sample.latitude_deg = lat;
            out.sample.longitude_deg = lon;
            out.label = Some(true);
        }
        records.push(out);
    }
    Ok(InjectedTrack {
        track: Track {
            vehicle_id: format!("{vehicle_id}#{}", attack.describe()),
            records,
        },
        base_vehicle_id: vehicle_id.clone(),
        attack: *attack,
        first_attack_row: first,
        last_attack_row: last,
    })
}

/// First and last row (inclusive) inside the attack window, after checking that the window lies in the
/// track, holds a contiguous run of rows, and does not straddle a trajectory break.
fn locate_attack_rows(track: &Track, attack: &AttackSpec) -> Result<(usize, usize), ScenarioError> {
    let vehicle_id = || track.vehicle_id.clone();
    let (Some(first_record), Some(last_record)) = (track.records.first(), track.records.last())
    else {
        return Err(ScenarioError::EmptyTrack {
            vehicle_id: vehicle_id(),
        });
    };
    let t0 = first_record.sample.timestamp_s;
    if !t0.is_finite() {
        return Err(ScenarioError::InvalidStartTime {
            vehicle_id: vehicle_id(),
            timestamp_s: t0,
        });
    }
    let start_s = attack.onset_s;
    let end_s = attack.onset_s + attack.duration_s;
    let span_s = last_record.sample.timestamp_s - t0;
    if span_s.is_nan() || end_s > span_s {
        return Err(ScenarioError::AttackOutsideTrack {
            vehicle_id: vehicle_id(),
            start_s,
            end_s,
            span_s,
        });
    }
    let in_window = |record: &Record| {
        let tau = record.sample.timestamp_s - t0;
        tau >= start_s && tau < end_s
    };
    let rows = &track.records;
    let (Some(first), Some(last)) = (
        rows.iter().position(in_window),
        rows.iter().rposition(in_window),
    ) else {
        return Err(ScenarioError::NoRowsInWindow {
            vehicle_id: vehicle_id(),
            start_s,
            end_s,
        });
    };
    if let Some(row) = (first..=last).find(|&i| !in_window(&rows[i])) {
        return Err(ScenarioError::NonContiguousWindow {
            vehicle_id: vehicle_id(),
            row,
        });
    }
    let starts_trajectory = |i: usize| {
        let step_s = rows[i].sample.timestamp_s - rows[i - 1].sample.timestamp_s;
        rows[i].trajectory_break || step_s > MAX_STEP_S
    };
    if let Some(row) = (first + 1..=last).find(|&i| starts_trajectory(i)) {
        return Err(ScenarioError::SpansTrajectoryBreak {
            vehicle_id: vehicle_id(),
            row,
        });
    }
    Ok((first, last))
}

fn is_valid_fix(latitude_deg: f64, longitude_deg: f64) -> bool {
    latitude_deg.is_finite()
        && longitude_deg.is_finite()
        && latitude_deg.abs() <= 90.0
        && longitude_deg.abs() <= 180.0
}
