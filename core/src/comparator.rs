//! The classical χ²/CUSUM comparator wired to the evidence pipeline (SPEC §9): Σ̂ and μ_e from the
//! training normal rows, (k, h, N_p) chosen on validation, scored with the same metrics.

use serde::{Deserialize, Serialize};

use crate::alarm::N_P_GRID;
use crate::cusum::{
    CusumDetector, CusumError, CusumParams, CusumRow, DRIFT_GRID, fit_cusum_on_grid,
};
use crate::evidence::{EvidenceParams, build_track};
use crate::geo::Projection;
use crate::metrics::EventRules;
use crate::metrics::ScoredRow;
use crate::pipeline::{PipelineError, fit_evidence};
use crate::sample::Track;

/// A fitted comparator.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CusumComparator {
    pub evidence: EvidenceParams,
    pub cusum: CusumParams,
}

/// Why the comparator could not be fitted.
#[derive(Debug, thiserror::Error)]
pub enum ComparatorError {
    #[error(transparent)]
    Pipeline(#[from] PipelineError),
    #[error("no CUSUM operating point: {0}")]
    NoOperatingPoint(#[from] CusumError),
}

/// Energy rows of tracks under fixed evidence parameters (trajectory keys unique per track).
fn cusum_rows(evidence: &EvidenceParams, tracks: &[Track]) -> Vec<CusumRow> {
    let mut rows = Vec::new();
    for (index, track) in tracks.iter().enumerate() {
        for (e, r) in build_track(evidence, &track.records)
            .iter()
            .zip(&track.records)
        {
            rows.push(CusumRow {
                trajectory: ((index as u64) << 32) | u64::from(e.trajectory),
                time_s: r.sample.timestamp_s,
                valid: e.valid,
                label: r.label.unwrap_or(false),
                energy: e.energy,
                trajectory_start: e.trajectory_start,
            });
        }
    }
    rows
}

/// Fits Σ̂, μ_e on `train` and the CUSUM drift, threshold and persistence on `validation`, within a
/// false-alarm `budget` (events per attack-free hour of `validation`) when one is given.
pub fn fit_cusum_comparator(
    train: &[Track],
    validation: &[Track],
    projection: Projection,
    budget: Option<f64>,
) -> Result<CusumComparator, ComparatorError> {
    let fit = fit_evidence(train, projection, 0.0, 0.98)?;
    let rows = cusum_rows(&fit.params, validation);
    let cusum = fit_cusum_on_grid(
        &rows,
        fit.params.mu_e,
        &DRIFT_GRID,
        N_P_GRID,
        EventRules::Spec,
        budget,
    )?
    .params;
    Ok(CusumComparator {
        evidence: fit.params,
        cusum,
    })
}

/// Runs the comparator over tracks: metric rows (score = CUSUM statistic) and confirmed alarms.
pub fn score_cusum(comparator: &CusumComparator, tracks: &[Track]) -> (Vec<ScoredRow>, Vec<bool>) {
    let mut scored = Vec::new();
    let mut alarms = Vec::new();
    let rows = cusum_rows(&comparator.evidence, tracks);
    let mut detector = CusumDetector::new(comparator.cusum.clone());
    let mut current_track = None;
    for row in rows {
        let track = row.trajectory >> 32;
        if current_track != Some(track) {
            detector = CusumDetector::new(comparator.cusum.clone());
            current_track = Some(track);
        }
        let step = detector.step(row.valid, row.energy, row.trajectory_start);
        scored.push(ScoredRow {
            trajectory: row.trajectory,
            time_s: row.time_s,
            valid: row.valid,
            label: row.label,
            score: step.statistic,
        });
        alarms.push(step.alarm);
    }
    (scored, alarms)
}
