//! The directional GLR comparator: the multi-scale directional drift test of evidence v2
//! by itself. Its statistic is the drift statistic G_t = max_k χ²_k / h_k of
//! [`crate::evidence::drift`] (calibrated channels once warm, uncalibrated before); an alarm is
//! G_t ≥ g for N_p consecutive valid steps, with (g, N_p) chosen on validation data by the same
//! operating-point rule as HO-LLN (usually a false-alarm budget per attack-free hour).
//!
//! It answers "does the learned model add anything over a plain statistical test on the same
//! evidence?". Must not train a model or define metrics (it reuses [`crate::alarm`] and
//! [`crate::evaluation`]).

use serde::{Deserialize, Serialize};

use crate::alarm::{
    self, AlarmError, N_P_GRID, OperatingPoint, OperatingPointRule, PersistenceAlarm,
};
use crate::cusum::threshold_grid;
use crate::evaluation::{Scored, trajectory_key};
use crate::evidence::{
    DEFAULT_KAPPA, DEFAULT_RHO, EvidenceFitError, EvidenceParams, FeatureSchema, build_track,
    fit_evidence,
};
use crate::geo::Projection;
use crate::metrics::{EventRules, ScoredRow};
use crate::sample::Track;

/// A fitted directional GLR comparator: the evidence parameters (with drift parameters) and its
/// operating point on the G scale (`theta` = g).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct GlrComparator {
    pub evidence: EvidenceParams,
    pub operating_point: OperatingPoint,
}

/// Why the comparator could not be fitted.
#[derive(Debug, thiserror::Error)]
pub enum GlrError {
    #[error(transparent)]
    Data(#[from] EvidenceFitError),
    #[error("the drift statistic is 0 on every valid validation row; no threshold to choose")]
    NoThresholds,
    #[error("no GLR operating point: {0}")]
    NoOperatingPoint(#[from] AlarmError),
}

/// Rows of tracks scored by G_t (held on ν = 0 rows, 0 at a trajectory start); warm-up rows only
/// carry the state forward.
fn statistic_rows(evidence: &EvidenceParams, tracks: &[Track]) -> Vec<ScoredRow> {
    tracks
        .iter()
        .enumerate()
        .flat_map(|(index, track)| {
            build_track(evidence, &track.records)
                .into_iter()
                .zip(&track.records)
                .filter(|(_, r)| !r.warmup)
                .map(move |(e, r)| ScoredRow {
                    trajectory: trajectory_key(index, e.trajectory),
                    time_s: r.sample.timestamp_s,
                    valid: e.valid,
                    label: r.label.unwrap_or(false),
                    score: e.drift.map_or(0.0, |d| d.statistic),
                })
        })
        .collect()
}

/// Fits the v2 evidence on `train` and (g, N_p) on `validation` by `rule`.
pub fn fit_glr_comparator(
    train: &[Track],
    validation: &[Track],
    projection: Projection,
    rule: OperatingPointRule,
) -> Result<GlrComparator, GlrError> {
    let (kappa, rho) = (DEFAULT_KAPPA, DEFAULT_RHO);
    let evidence = fit_evidence(train, projection, kappa, rho, FeatureSchema::V2)?.params;
    let rows = statistic_rows(&evidence, validation);
    let valid_statistics: Vec<f64> = rows.iter().filter(|r| r.valid).map(|r| r.score).collect();
    let thresholds = threshold_grid(&valid_statistics);
    if thresholds.is_empty() {
        return Err(GlrError::NoThresholds);
    }
    let selection =
        alarm::choose_operating_point(&rows, &thresholds, N_P_GRID, EventRules::Spec, rule)?;
    Ok(GlrComparator {
        evidence,
        operating_point: selection.point,
    })
}

impl GlrComparator {
    /// The comparator's scores (G) and confirmed alarms over tracks, fresh state per track.
    pub fn score_tracks(&self, tracks: &[Track]) -> Scored {
        let rows = statistic_rows(&self.evidence, tracks);
        let mut persistence = PersistenceAlarm::new(self.operating_point.n_p);
        let mut previous_trajectory = None;
        let alarms = rows
            .iter()
            .map(|row| {
                let start = previous_trajectory != Some(row.trajectory);
                previous_trajectory = Some(row.trajectory);
                let positive = row.score >= self.operating_point.theta;
                persistence.update(positive, row.valid, start)
            })
            .collect();
        Scored {
            rows,
            alarms,
            offset: Vec::new(),
            speed_mps: Vec::new(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geo::displace_fix;
    use crate::rng::Rng;
    use crate::sample::{Record, Sample};

    /// A vehicle driving a slalom (heading ±60°) at 8 m/s, 1 Hz, whose GNSS equals its motion plus
    /// white noise (0.5 m per axis) and, from `onset_s` on, an east drift of `drift_mps`.
    fn track(seed: u64, seconds: usize, onset_s: usize, drift_mps: f64) -> Track {
        let mut rng = Rng::seed_from_u64(seed);
        let (mut east, mut north) = (0.0, 0.0);
        let heading =
            |t: usize| 60f64.to_radians() * (t as f64 * std::f64::consts::TAU / 90.0).sin();
        let records = (0..seconds)
            .map(|t| {
                if t > 0 {
                    let (a, b) = (heading(t), heading(t - 1));
                    east += 4.0 * (a.sin() + b.sin());
                    north += 4.0 * (a.cos() + b.cos());
                }
                let offset = drift_mps * t.saturating_sub(onset_s) as f64;
                let (lat, lon) = displace_fix(
                    32.0,
                    -110.0,
                    east + offset + 0.5 * rng.normal(),
                    north + 0.5 * rng.normal(),
                );
                Record {
                    sample: Sample::new(
                        t as f64,
                        lat,
                        lon,
                        8.0,
                        heading(t).to_degrees().rem_euclid(360.0),
                    ),
                    label: Some(t >= onset_s),
                    comparator_alarm: None,
                    line: t as u64 + 1,
                    trajectory_break: false,
                    warmup: false,
                }
            })
            .collect();
        Track {
            vehicle_id: format!("slalom{seed}"),
            records,
        }
    }

    #[test]
    fn a_drift_on_hand_made_residuals_alarms_after_its_onset_and_clean_drives_stay_quiet() {
        let never = usize::MAX;
        let train: Vec<Track> = (0..3).map(|s| track(s, 900, never, 0.0)).collect();
        let validation: Vec<Track> = (10..13)
            .map(|s| track(s, 900, 600, 0.5))
            .chain((20..23).map(|s| track(s, 900, never, 0.0)))
            .collect();
        let rule = OperatingPointRule::WithinFalseAlarmBudget { per_hour: 1.0 };
        let glr =
            fit_glr_comparator(&train, &validation, Projection::Wgs84Local, rule).expect("fits");
        assert!(glr.operating_point.theta > 0.0);

        let attacked = glr.score_tracks(&[track(30, 900, 600, 0.5)]);
        let onset = attacked
            .alarms
            .iter()
            .position(|&a| a)
            .expect("the 0.5 m/s drift is detected");
        assert!((600..660).contains(&onset), "alarm at {onset}");
        let clean = glr.score_tracks(&[track(31, 900, never, 0.0)]);
        assert!(clean.alarms.iter().all(|&a| !a));
        // The score is the drift statistic, 0 at the start of the trajectory.
        assert_eq!(attacked.rows[0].score, 0.0);
    }
}
