//! The one scoring path of every detector (SPEC §8): tracks → per-row scores and confirmed alarms
//! ([`Scored`]) → metrics. HO-LLN is scored here ([`score_tracks`], [`evaluate_tracks`]); the CUSUM
//! comparator produces the same [`Scored`] shape in [`crate::cusum`], and both use
//! [`trajectory_key`], so the metrics see both detectors identically.
//!
//! Must not choose operating points (that is [`crate::alarm`]) or train anything.

use std::sync::Arc;

use crate::detector::{Decision, offset_signal, run_records};
use crate::lifecycle::OffsetSignal;
use crate::metrics::{EventRules, Metrics, ScoredRow, evaluate};
use crate::model::artifact::ModelArtifact;
use crate::sample::{Record, Track};
use crate::severity::Severity;

/// The metrics' trajectory key of trajectory `trajectory` of the `track_index`-th track: unique per
/// (track, trajectory), so trajectories of different tracks never merge.
pub fn trajectory_key(track_index: usize, trajectory: u32) -> u64 {
    ((track_index as u64) << 32) | u64::from(trajectory)
}

/// A detector's per-row scores and confirmed alarms over some tracks, row for row.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Scored {
    pub rows: Vec<ScoredRow>,
    pub alarms: Vec<bool>,
    /// The offset evidence of each row, for the lifecycle search (empty for detectors without it).
    pub offset: Vec<OffsetSignal>,
    /// Each row's onboard speed (m/s), for the lifecycle search's budget per pace (empty for
    /// detectors that do not keep it).
    pub speed_mps: Vec<f64>,
}

impl Scored {
    /// The SPEC §8 metrics of these alarms.
    pub fn metrics(&self, rules: EventRules) -> Metrics {
        evaluate(&self.rows, &self.alarms, rules)
    }

    /// These scores, made row for row over `records`, without the warm-up rows
    /// ([`Record::warmup`]): those only carried the detector's state forward.
    pub fn without_warmup(self, records: &[Record]) -> Scored {
        if !records.iter().any(|r| r.warmup) {
            return self;
        }
        fn scored<T>(values: Vec<T>, records: &[Record]) -> Vec<T> {
            values
                .into_iter()
                .zip(records)
                .filter(|(_, r)| !r.warmup)
                .map(|(value, _)| value)
                .collect()
        }
        Scored {
            rows: scored(self.rows, records),
            alarms: scored(self.alarms, records),
            offset: scored(self.offset, records),
            speed_mps: scored(self.speed_mps, records),
        }
    }

    /// Appends `other`'s rows and alarms.
    pub fn append(&mut self, other: Scored) {
        self.rows.extend(other.rows);
        self.alarms.extend(other.alarms);
        self.offset.extend(other.offset);
        self.speed_mps.extend(other.speed_mps);
    }
}

/// One evaluated row.
#[derive(Clone, Debug, PartialEq)]
pub struct RowResult {
    pub vehicle_id: String,
    /// 1-based source line.
    pub line: u64,
    pub time_s: f64,
    pub label: Option<bool>,
    pub decision: Decision,
}

/// Metrics overall and per vehicle, plus every row.
#[derive(Clone, Debug, PartialEq)]
pub struct Evaluation {
    pub overall: Metrics,
    /// The same metrics with the critical episodes as the alarms (§7.4: each from its escalation
    /// to its end); `None` when the model has no critical test (warnings only).
    pub critical: Option<Metrics>,
    /// In track order; only filled when there are several vehicles.
    pub per_vehicle: Vec<(String, Metrics)>,
    pub rows: Vec<RowResult>,
}

/// The HO-LLN decisions of one track as scores (p̂) and alarms. Unlabelled rows count as normal;
/// warm-up rows ([`Record::warmup`]) are left out.
fn scored_track(track_index: usize, records: &[Record], decisions: &[Decision]) -> Scored {
    let rows = records
        .iter()
        .zip(decisions)
        .map(|(record, d)| ScoredRow {
            trajectory: trajectory_key(track_index, d.evidence.trajectory),
            time_s: record.sample.timestamp_s,
            valid: d.evidence.valid,
            label: record.label.unwrap_or(false),
            score: d.probability,
        })
        .collect();
    Scored {
        rows,
        alarms: decisions.iter().map(|d| d.alarm).collect(),
        offset: decisions
            .iter()
            .map(|d| offset_signal(&d.evidence))
            .collect(),
        speed_mps: records.iter().map(|r| r.sample.speed_mps).collect(),
    }
    .without_warmup(records)
}

/// Runs the detector over every track (a fresh session each) and scores it with `rules`.
/// Unlabelled rows count as normal; warm-up rows are neither scored nor listed.
pub fn evaluate_tracks(
    artifact: &Arc<ModelArtifact>,
    tracks: &[Track],
    rules: EventRules,
) -> Evaluation {
    let mut rows = Vec::new();
    let mut scored = Scored::default();
    let mut critical_alarms = Vec::new();
    let mut per_vehicle = Vec::new();
    for (index, track) in tracks.iter().enumerate() {
        let decisions = run_records(artifact, &track.records);
        let track_scored = scored_track(index, &track.records, &decisions);
        critical_alarms.extend(
            track
                .records
                .iter()
                .zip(&decisions)
                .filter(|(r, _)| !r.warmup)
                .map(|(_, d)| d.severity == Some(Severity::Critical)),
        );
        if tracks.len() > 1 {
            per_vehicle.push((track.vehicle_id.clone(), track_scored.metrics(rules)));
        }
        rows.extend(
            track
                .records
                .iter()
                .zip(&decisions)
                .filter(|(r, _)| !r.warmup)
                .map(|(r, d)| RowResult {
                    vehicle_id: track.vehicle_id.clone(),
                    line: r.line,
                    time_s: r.sample.timestamp_s,
                    label: r.label,
                    decision: *d,
                }),
        );
        scored.append(track_scored);
    }
    Evaluation {
        overall: scored.metrics(rules),
        critical: artifact
            .critical
            .is_some()
            .then(|| evaluate(&scored.rows, &critical_alarms, rules)),
        per_vehicle,
        rows,
    }
}

/// The detector's scores (p̂) and alarms (at the artifact's operating point) over tracks.
pub fn score_tracks(artifact: &Arc<ModelArtifact>, tracks: &[Track]) -> Scored {
    let mut scored = Scored::default();
    for (index, track) in tracks.iter().enumerate() {
        let decisions = run_records(artifact, &track.records);
        scored.append(scored_track(index, &track.records, &decisions));
    }
    scored
}
