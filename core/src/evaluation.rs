//! Scoring a trained detector on labelled tracks: per-row decisions and the metrics of SPEC §8.

use std::sync::Arc;

use crate::alarm::OperatingPoint;
use crate::artifact::ModelArtifact;
use crate::detector::{Decision, run_records};
use crate::metrics::{EventRules, Metrics, ScoredRow, evaluate};
use crate::sample::{Record, Track};

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
    /// In track order; only filled when there are several vehicles.
    pub per_vehicle: Vec<(String, Metrics)>,
    pub rows: Vec<RowResult>,
}

/// The rows of one track as metric inputs. Trajectory keys are unique per (track, trajectory).
pub fn scored_rows(
    track_index: usize,
    records: &[Record],
    decisions: &[Decision],
) -> Vec<ScoredRow> {
    records
        .iter()
        .zip(decisions)
        .map(|(record, d)| ScoredRow {
            trajectory: ((track_index as u64) << 32) | u64::from(d.evidence.trajectory),
            time_s: record.sample.timestamp_s,
            valid: d.evidence.valid,
            label: record.label.unwrap_or(false),
            score: d.probability,
        })
        .collect()
}

/// Runs the detector over every track (a fresh session each) and scores it with `rules`.
/// Unlabelled rows count as normal.
pub fn evaluate_tracks(
    artifact: &Arc<ModelArtifact>,
    tracks: &[Track],
    rules: EventRules,
) -> Evaluation {
    let mut rows = Vec::new();
    let mut scored = Vec::new();
    let mut alarms = Vec::new();
    let mut per_vehicle = Vec::new();
    for (index, track) in tracks.iter().enumerate() {
        let decisions = run_records(artifact, &track.records);
        let track_scored = scored_rows(index, &track.records, &decisions);
        let track_alarms: Vec<bool> = decisions.iter().map(|d| d.alarm).collect();
        if tracks.len() > 1 {
            per_vehicle.push((
                track.vehicle_id.clone(),
                evaluate(&track_scored, &track_alarms, rules),
            ));
        }
        rows.extend(
            track
                .records
                .iter()
                .zip(&decisions)
                .map(|(r, d)| RowResult {
                    vehicle_id: track.vehicle_id.clone(),
                    line: r.line,
                    time_s: r.sample.timestamp_s,
                    label: r.label,
                    decision: *d,
                }),
        );
        scored.extend(track_scored);
        alarms.extend(track_alarms);
    }
    Evaluation {
        overall: evaluate(&scored, &alarms, rules),
        per_vehicle,
        rows,
    }
}

/// Probabilities of a detector over tracks as metric rows (the operating point does not matter).
pub fn score_tracks(artifact: &Arc<ModelArtifact>, tracks: &[Track]) -> Vec<ScoredRow> {
    tracks
        .iter()
        .enumerate()
        .flat_map(|(i, t)| scored_rows(i, &t.records, &run_records(artifact, &t.records)))
        .collect()
}

/// Metrics of already-scored rows at an operating point.
pub fn metrics_at(rows: &[ScoredRow], op: OperatingPoint, rules: EventRules) -> Metrics {
    let alarms = crate::alarm::confirmed_alarms(rows, op);
    evaluate(rows, &alarms, rules)
}
