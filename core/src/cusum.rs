//! The classical χ²/CUSUM comparator (SPEC §9) on the normalised residual energy e_t = ‖η_t‖²: the
//! streaming statistic, its fit on validation rows, and the comparator wired to the evidence builder
//! (Σ̂ and μ_e from the training normal rows, scored through the same [`Scored`] path as HO-LLN).
//!
//! S_t = max(0, S_{t−1} + e_t − μ_e − k) on ν = 1 steps, held on ν = 0 steps, reset to 0 at trajectory
//! starts; c_t = 1[S_t ≥ h], then the same persistence confirmation N_p as the learned detector.
//! (k, h, N_p) are chosen on validation data with the operating-point objective of SPEC §7.
//!
//! Must not score or threshold HO-LLN probabilities, nor define metrics (it reuses [`crate::alarm`]
//! and [`crate::evaluation`]).

use std::ops::RangeInclusive;

use serde::{Deserialize, Serialize};

use crate::alarm::{
    self, AlarmError, N_P_GRID, OperatingPoint, OperatingPointRule, PersistenceAlarm,
};
use crate::evaluation::{Scored, trajectory_key};
use crate::evidence::{
    DEFAULT_KAPPA, DEFAULT_RHO, EvidenceFitError, EvidenceParams, FeatureSchema, build_track,
    fit_evidence,
};
use crate::geo::Projection;
use crate::metrics::{EventRules, Metrics, ScoredRow};
use crate::sample::Track;

/// The fitted comparator's parameters.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CusumParams {
    /// Median training energy μ_e (the expected energy of a normal step).
    pub mu_e: f64,
    /// Drift allowance k subtracted each valid step, in energy units.
    pub drift_k: f64,
    /// Alarm threshold h on S_t.
    pub threshold_h: f64,
    /// Persistence: consecutive valid steps with S ≥ h for a confirmed alarm.
    pub n_p: u32,
}

/// One step's outcome.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CusumStep {
    /// S_t after this step.
    pub statistic: f64,
    /// Confirmed alarm c̄_t.
    pub alarm: bool,
}

/// Streaming CUSUM of one vehicle.
#[derive(Clone, Debug, PartialEq)]
pub struct CusumDetector {
    params: CusumParams,
    statistic: f64,
    persistence: PersistenceAlarm,
}

impl CusumDetector {
    /// A detector at S = 0 with no alarm run.
    pub fn new(params: CusumParams) -> Self {
        let persistence = PersistenceAlarm::new(params.n_p);
        Self {
            params,
            statistic: 0.0,
            persistence,
        }
    }

    /// The parameters this detector runs with.
    pub fn params(&self) -> &CusumParams {
        &self.params
    }

    /// Feeds one step. A non-finite energy is treated like a ν = 0 step (S held, no alarm), because
    /// one bad value would otherwise poison S for the rest of the trajectory.
    pub fn step(&mut self, valid: bool, energy: f64, trajectory_start: bool) -> CusumStep {
        if trajectory_start {
            self.statistic = 0.0;
        }
        let valid = valid && energy.is_finite();
        if valid {
            let increment = energy - self.params.mu_e - self.params.drift_k;
            self.statistic = (self.statistic + increment).max(0.0);
        }
        let positive = self.statistic >= self.params.threshold_h;
        let alarm = self.persistence.update(positive, valid, trajectory_start);
        CusumStep {
            statistic: self.statistic,
            alarm,
        }
    }

    /// Forgets all history (S = 0, no alarm run).
    pub fn reset(&mut self) {
        self.statistic = 0.0;
        self.persistence.reset();
    }
}

/// One labelled validation/evaluation row for the comparator.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct CusumRow {
    /// Opaque trajectory key (contiguous rows).
    pub trajectory: u64,
    /// Seconds.
    pub time_s: f64,
    /// ν_t.
    pub valid: bool,
    /// Ground truth: `true` = spoofed.
    pub label: bool,
    /// e_t = ‖η_t‖² from the evidence builder.
    pub energy: f64,
    /// First row of a trajectory.
    pub trajectory_start: bool,
}

/// Runs a fresh detector over the rows (their `trajectory_start` flags reset S).
pub fn run_cusum(params: &CusumParams, rows: &[CusumRow]) -> Vec<CusumStep> {
    let mut detector = CusumDetector::new(params.clone());
    rows.iter()
        .map(|row| detector.step(row.valid, row.energy, row.trajectory_start))
        .collect()
}

/// The rows as metric rows with the CUSUM statistic as the score (for `metrics::evaluate` and for
/// thresholding). `steps` must come from [`run_cusum`] on the same rows; extra entries are ignored.
pub fn scored_rows(rows: &[CusumRow], steps: &[CusumStep]) -> Vec<ScoredRow> {
    rows.iter()
        .zip(steps)
        .map(|(row, step)| ScoredRow {
            trajectory: row.trajectory,
            time_s: row.time_s,
            valid: row.valid,
            label: row.label,
            score: step.statistic,
        })
        .collect()
}

/// The drift grid k (energy units) the comparator searches.
pub const DRIFT_GRID: [f64; 6] = [0.0, 0.5, 1.0, 2.0, 4.0, 8.0];
/// Number of evenly spaced quantile levels of S in the threshold grid.
pub const THRESHOLD_QUANTILES: usize = 40;
/// Number of log-spaced thresholds between the smallest positive S and the largest S.
pub const THRESHOLD_LOG_STEPS: usize = 20;

/// A fitted comparator and its validation metrics at the chosen parameters.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CusumFit {
    /// Chosen (μ_e, k, h, N_p).
    pub params: CusumParams,
    /// Metrics of the confirmed alarms on the validation rows (score = S).
    pub metrics: Metrics,
}

/// Why the comparator cannot be fitted.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum CusumError {
    /// μ_e must be a finite energy.
    #[error("mu_e must be finite, got {0}")]
    NonFiniteMean(f64),
    /// Drifts must be finite.
    #[error("drift k at grid index {index} must be finite, got {value}")]
    NonFiniteDrift {
        /// Position in the drift grid.
        index: usize,
        /// The offending drift.
        value: f64,
    },
    /// The drift grid is empty.
    #[error("the drift grid is empty")]
    EmptyDriftGrid,
    /// S would not reset where the metrics start a new trajectory (or vice versa).
    #[error(
        "row {row}: trajectory_start is {flag} but the trajectory key {}",
        if *flag { "does not change" } else { "changes" }
    )]
    InconsistentTrajectoryStart {
        /// 0-based row index.
        row: usize,
        /// The row's `trajectory_start`.
        flag: bool,
    },
    /// For every drift, S stayed 0 on all valid rows: no threshold h > 0 exists.
    #[error(
        "the CUSUM statistic is 0 on every valid validation row for every drift; no threshold to choose"
    )]
    NoThresholds,
    /// The operating-point search failed.
    #[error("choosing the threshold: {0}")]
    Selection(#[from] AlarmError),
}

/// For each drift k: S on the validation rows, thresholds h from [`threshold_grid`], then the
/// operating-point search of SPEC §7 (F1, ADR, delay, FPR, recall, lower N_p, higher h) with S as the
/// score. Across drifts the same objective decides; remaining ties go to the smaller k. With a
/// false-alarm budget `rule`, only points within it compete, as for HO-LLN.
pub fn fit_cusum(
    validation: &[CusumRow],
    mu_e: f64,
    drifts: &[f64],
    n_ps: RangeInclusive<u32>,
    rules: EventRules,
    rule: OperatingPointRule,
) -> Result<CusumFit, CusumError> {
    if !mu_e.is_finite() {
        return Err(CusumError::NonFiniteMean(mu_e));
    }
    if let Some(index) = drifts.iter().position(|k| !k.is_finite()) {
        return Err(CusumError::NonFiniteDrift {
            index,
            value: drifts[index],
        });
    }
    if drifts.is_empty() {
        return Err(CusumError::EmptyDriftGrid);
    }
    check_trajectory_starts(validation)?;
    let mut best: Option<CusumFit> = None;
    let mut over_budget = None;
    for &drift_k in drifts {
        let unthresholded = CusumParams {
            mu_e,
            drift_k,
            threshold_h: f64::INFINITY,
            n_p: 1,
        };
        let scored = scored_rows(validation, &run_cusum(&unthresholded, validation));
        let valid_statistics: Vec<f64> =
            scored.iter().filter(|r| r.valid).map(|r| r.score).collect();
        let thresholds = threshold_grid(&valid_statistics);
        if thresholds.is_empty() {
            continue;
        }
        let selection =
            match alarm::choose_operating_point(&scored, &thresholds, n_ps.clone(), rules, rule) {
                Ok(selection) => selection,
                // Another drift may fit the budget.
                Err(error @ AlarmError::OverBudget { .. }) => {
                    over_budget = Some(error);
                    continue;
                }
                Err(error) => return Err(error.into()),
            };
        let candidate = CusumFit {
            params: CusumParams {
                mu_e,
                drift_k,
                threshold_h: selection.point.theta,
                n_p: selection.point.n_p,
            },
            metrics: selection.metrics,
        };
        // Strictly better only: on a full tie the earlier (smaller, for a sorted grid) k stays.
        let improves = best.as_ref().is_none_or(|incumbent| {
            alarm::compare_candidates(
                (&operating_point(&candidate.params), &candidate.metrics),
                (&operating_point(&incumbent.params), &incumbent.metrics),
            )
            .is_gt()
        });
        if improves {
            best = Some(candidate);
        }
    }
    match (best, over_budget) {
        (Some(fit), _) => Ok(fit),
        (None, Some(error)) => Err(error.into()),
        (None, None) => Err(CusumError::NoThresholds),
    }
}

/// (h, N_p) as an operating point on the S scale.
fn operating_point(params: &CusumParams) -> OperatingPoint {
    OperatingPoint {
        theta: params.threshold_h,
        n_p: params.n_p,
    }
}

/// The statistic resets exactly where the metrics see a new trajectory: at the first row and at every
/// change of trajectory key.
fn check_trajectory_starts(rows: &[CusumRow]) -> Result<(), CusumError> {
    for (row, current) in rows.iter().enumerate() {
        let key_changes = row == 0 || rows[row - 1].trajectory != current.trajectory;
        if current.trajectory_start != key_changes {
            return Err(CusumError::InconsistentTrajectoryStart {
                row,
                flag: current.trajectory_start,
            });
        }
    }
    Ok(())
}

/// Candidate thresholds h > 0 from the statistic on valid rows: the distinct positive quantiles at
/// levels i/40 (i = 1..=40, linear interpolation as numpy's default) plus 20 log-spaced values from
/// the smallest positive S to the largest, sorted ascending. Empty when no S is positive.
pub fn threshold_grid(valid_statistics: &[f64]) -> Vec<f64> {
    let mut sorted: Vec<f64> = valid_statistics
        .iter()
        .copied()
        .filter(|s| s.is_finite())
        .collect();
    sorted.sort_by(f64::total_cmp);
    let Some(&largest) = sorted.last() else {
        return Vec::new();
    };
    let Some(&smallest_positive) = sorted.iter().find(|&&s| s > 0.0) else {
        return Vec::new();
    };
    let mut grid: Vec<f64> = (1..=THRESHOLD_QUANTILES)
        .map(|i| quantile_sorted(&sorted, i as f64 / THRESHOLD_QUANTILES as f64))
        .collect();
    let ratio = largest / smallest_positive;
    let last = (THRESHOLD_LOG_STEPS - 1) as f64;
    grid.extend((0..THRESHOLD_LOG_STEPS).map(|i| smallest_positive * ratio.powf(i as f64 / last)));
    grid.retain(|&h| h > 0.0 && h.is_finite());
    grid.sort_by(f64::total_cmp);
    grid.dedup();
    grid
}

/// Quantile of ascending, non-empty `sorted` at `level` ∈ [0, 1] (numpy "linear", pandas type 7).
fn quantile_sorted(sorted: &[f64], level: f64) -> f64 {
    let position = level * (sorted.len() - 1) as f64;
    let lower = position.floor() as usize;
    let upper = (lower + 1).min(sorted.len() - 1);
    let fraction = position - lower as f64;
    sorted[lower] + fraction * (sorted[upper] - sorted[lower])
}

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
    Data(#[from] EvidenceFitError),
    #[error("no CUSUM operating point: {0}")]
    NoOperatingPoint(#[from] CusumError),
}

/// Energy rows of the `track_index`-th track under fixed evidence parameters.
fn track_rows(evidence: &EvidenceParams, track_index: usize, track: &Track) -> Vec<CusumRow> {
    // Warm-up rows are left out; S_t has no state that they would warm, so the first scored row
    // starts the statistic afresh.
    let mut first = true;
    build_track(evidence, &track.records)
        .iter()
        .zip(&track.records)
        .filter(|(_, r)| !r.warmup)
        .map(|(e, r)| {
            let trajectory_start = e.trajectory_start || first;
            first = false;
            CusumRow {
                trajectory: trajectory_key(track_index, e.trajectory),
                time_s: r.sample.timestamp_s,
                valid: e.valid,
                label: r.label.unwrap_or(false),
                energy: e.energy,
                trajectory_start,
            }
        })
        .collect()
}

/// Energy rows of tracks under fixed evidence parameters.
fn cusum_rows(evidence: &EvidenceParams, tracks: &[Track]) -> Vec<CusumRow> {
    tracks
        .iter()
        .enumerate()
        .flat_map(|(index, track)| track_rows(evidence, index, track))
        .collect()
}

/// Fits Σ̂, μ_e on `train` (at the default κ, ρ) and the CUSUM drift, threshold and persistence on
/// `validation` by `rule` (a false-alarm budget counts events per attack-free hour of `validation`).
pub fn fit_cusum_comparator(
    train: &[Track],
    validation: &[Track],
    projection: Projection,
    rule: OperatingPointRule,
) -> Result<CusumComparator, ComparatorError> {
    let (kappa, rho) = (DEFAULT_KAPPA, DEFAULT_RHO);
    let fit = fit_evidence(train, projection, kappa, rho, FeatureSchema::Paper)?;
    let rows = cusum_rows(&fit.params, validation);
    let cusum = fit_cusum(
        &rows,
        fit.params.mu_e,
        &DRIFT_GRID,
        N_P_GRID,
        EventRules::Spec,
        rule,
    )?
    .params;
    Ok(CusumComparator {
        evidence: fit.params,
        cusum,
    })
}

impl CusumComparator {
    /// The comparator's scores (S) and confirmed alarms over tracks, a fresh detector per track.
    pub fn score_tracks(&self, tracks: &[Track]) -> Scored {
        let mut scored = Scored::default();
        for (index, track) in tracks.iter().enumerate() {
            let rows = track_rows(&self.evidence, index, track);
            let steps = run_cusum(&self.cusum, &rows);
            scored.append(Scored {
                rows: scored_rows(&rows, &steps),
                alarms: steps.iter().map(|s| s.alarm).collect(),
                offset: Vec::new(),
                speed_mps: Vec::new(),
            });
        }
        scored
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::metrics::try_evaluate;

    const BEST_F1: OperatingPointRule = OperatingPointRule::BestValidationF1;

    fn params(mu_e: f64, drift_k: f64, threshold_h: f64, n_p: u32) -> CusumParams {
        CusumParams {
            mu_e,
            drift_k,
            threshold_h,
            n_p,
        }
    }

    #[test]
    fn statistic_follows_the_hand_computed_recursion() {
        // μ_e = 1, k = 0.5 → increment e − 1.5.
        // e: 3 → S 1.5; 0 → max(0, 0) = 0; 0 → 0 (floored); 4 → 2.5; 2 → 3.0; 1 → 2.5.
        let mut detector = CusumDetector::new(params(1.0, 0.5, 2.5, 1));
        let energies = [3.0, 0.0, 0.0, 4.0, 2.0, 1.0];
        let steps: Vec<CusumStep> = energies
            .iter()
            .map(|&e| detector.step(true, e, false))
            .collect();
        let statistics: Vec<f64> = steps.iter().map(|s| s.statistic).collect();
        assert_eq!(statistics, vec![1.5, 0.0, 0.0, 2.5, 3.0, 2.5]);
        let alarms: Vec<bool> = steps.iter().map(|s| s.alarm).collect();
        assert_eq!(alarms, vec![false, false, false, true, true, true]);
    }

    #[test]
    fn statistic_holds_on_invalid_steps_and_resets_at_trajectory_starts() {
        let mut detector = CusumDetector::new(params(0.0, 0.0, 5.0, 2));
        assert_eq!(detector.step(true, 4.0, false).statistic, 4.0);
        // ν = 0: S held at 4 even with a large energy; no alarm even if S ≥ h.
        assert_eq!(detector.step(false, 100.0, false).statistic, 4.0);
        let held = detector.step(true, 2.0, false);
        assert_eq!(
            held,
            CusumStep {
                statistic: 6.0,
                alarm: false
            }
        );
        // Second consecutive valid step with S ≥ h → confirmed (N_p = 2).
        assert_eq!(
            detector.step(true, 0.0, false),
            CusumStep {
                statistic: 6.0,
                alarm: true
            }
        );
        // A non-finite energy counts as invalid: held, and the persistence run restarts.
        assert_eq!(
            detector.step(true, f64::NAN, false),
            CusumStep {
                statistic: 6.0,
                alarm: false
            }
        );
        // Trajectory start: S restarts from 0 before adding this step's increment.
        assert_eq!(
            detector.step(true, 1.0, true),
            CusumStep {
                statistic: 1.0,
                alarm: false
            }
        );
        detector.reset();
        assert_eq!(detector.step(true, 0.5, false).statistic, 0.5);
    }

    /// Valid rows of one trajectory at 1 Hz: normal energy 0.3/0.5 alternating, then an attack with
    /// energy 3 from row 30 for 20 rows, then normal again.
    fn shifted_sequence() -> Vec<CusumRow> {
        (0..70)
            .map(|i| {
                let attack = (30..50).contains(&i);
                let energy = if attack {
                    3.0
                } else if i % 2 == 0 {
                    0.3
                } else {
                    0.5
                };
                CusumRow {
                    trajectory: 1,
                    time_s: f64::from(i),
                    valid: i != 0,
                    label: attack,
                    energy,
                    trajectory_start: i == 0,
                }
            })
            .collect()
    }

    #[test]
    fn fitting_finds_a_separating_threshold_on_a_clear_shift() {
        // Hand computation with μ_e = 0.4 (increments: normal −0.1/+0.1 − k, attack 2.6 − k):
        // k = 0: S ≈ 52 after the attack and stays there → every later row alarms (F1 ≤ 2/3);
        // k = 0.5, 1: S decays by ~k per step after the attack → all 20 later rows alarm;
        // k = 2: S = 0 on normal rows, 0.6, 1.2, …, 12 during the attack, then 9.9, 8.0, 5.9, 4.0, 1.9, 0
        //   → with h ≤ 0.6 and N_p = 1: TP 20, FP 5, FN 0, F1 40/45 (best);
        // k = 4, 8: S ≡ 0 → no threshold. Among h ∈ (0, 0.6] (identical alarms) the highest wins: the
        // first attack statistic itself.
        let rows = shifted_sequence();
        let fit = fit_cusum(&rows, 0.4, &DRIFT_GRID, N_P_GRID, EventRules::Spec, BEST_F1)
            .expect("fittable");
        assert_eq!(fit.params.drift_k, 2.0);
        assert_eq!(fit.params.n_p, 1);
        let first_attack_statistic =
            run_cusum(&params(0.4, 2.0, f64::INFINITY, 1), &rows)[30].statistic;
        assert!((first_attack_statistic - 0.6).abs() < 1e-12);
        assert_eq!(fit.params.threshold_h, first_attack_statistic);
        let m = &fit.metrics;
        assert_eq!(
            (m.true_positives, m.false_positives, m.false_negatives),
            (20, 5, 0)
        );
        assert_eq!(m.f1, 8.0 / 9.0);
        assert_eq!(m.delays_s, vec![Some(0.0)]);
        assert_eq!((m.false_alarm_rows, m.false_alarm_events), (5, 1));
        let default_grids = fit_cusum(&rows, 0.4, &DRIFT_GRID, N_P_GRID, EventRules::Spec, BEST_F1);
        assert_eq!(default_grids.map(|f| f.params), Ok(fit.params));
    }

    #[test]
    fn an_alarm_that_outlasts_the_attack_is_not_a_false_alarm_for_the_budget() {
        // The best-F1 fit above stays alarmed for 5 s after the attack (S decays): one false-alarm
        // event, but no alarm raised on normal rows, so even a zero budget admits it.
        let rows = shifted_sequence();
        let free = fit_cusum(&rows, 0.4, &DRIFT_GRID, N_P_GRID, EventRules::Spec, BEST_F1)
            .expect("fittable");
        assert_eq!(
            (
                free.metrics.false_alarm_events,
                free.metrics.false_alarm_onsets
            ),
            (1, 0)
        );
        let quiet = fit_cusum(
            &rows,
            0.4,
            &DRIFT_GRID,
            N_P_GRID,
            EventRules::Spec,
            OperatingPointRule::WithinFalseAlarmBudget { per_hour: 0.0 },
        )
        .expect("the best-F1 point is within the budget");
        assert_eq!(quiet, free);
    }

    #[test]
    fn fitted_detector_agrees_with_thresholding_its_statistic_and_scores_with_evaluate() {
        let rows = shifted_sequence();
        let fit = fit_cusum(&rows, 0.4, &DRIFT_GRID, N_P_GRID, EventRules::Spec, BEST_F1)
            .expect("fittable");
        let steps = run_cusum(&fit.params, &rows);
        let scored = scored_rows(&rows, &steps);
        let alarms: Vec<bool> = steps.iter().map(|s| s.alarm).collect();
        let by_threshold = alarm::confirmed_alarms(&scored, operating_point(&fit.params));
        assert_eq!(alarms, by_threshold);
        let metrics = try_evaluate(&scored, &alarms, EventRules::Spec).expect("valid rows");
        assert_eq!(metrics, fit.metrics);
        // The attack rows' statistics (0.6 … 12) rank above the normal rows before the attack (0) but
        // not above the post-attack decay (9.9, 8.0, 5.9, 4.0, 1.9): AUROC strictly between 0.5 and 1.
        let auroc = metrics.auroc.expect("both classes");
        assert!(auroc > 0.9 && auroc < 1.0, "{auroc}");
    }

    #[test]
    fn threshold_grid_holds_distinct_positive_quantiles_and_a_log_range() {
        assert!(threshold_grid(&[]).is_empty());
        assert!(threshold_grid(&[0.0, 0.0]).is_empty());
        // Values 0, 1, 2, 3, 4: quantile at i/40 is 4i/40 = i/10 → 0.1 … 4.0 (40 values); log range 1 … 4.
        let grid = threshold_grid(&[3.0, 0.0, 4.0, 1.0, 2.0]);
        assert!(grid.windows(2).all(|w| w[0] < w[1]), "sorted and distinct");
        assert_eq!(grid.first(), Some(&0.1));
        assert_eq!(grid.last(), Some(&4.0));
        assert!(grid.contains(&1.0) && grid.contains(&2.0));
        let log_2 = 1.0 * 4.0_f64.powf(1.0 / 19.0);
        assert!(grid.iter().any(|&h| (h - log_2).abs() < 1e-12));
    }

    #[test]
    fn fitting_rejects_unusable_input() {
        let rows = shifted_sequence();
        let fit = |rows: &[CusumRow], mu_e: f64, drifts: &[f64]| {
            fit_cusum(rows, mu_e, drifts, N_P_GRID, EventRules::Spec, BEST_F1)
        };
        assert!(matches!(
            fit(&rows, f64::NAN, &DRIFT_GRID),
            Err(CusumError::NonFiniteMean(_))
        ));
        assert!(matches!(
            fit(&rows, 0.4, &[0.0, f64::INFINITY]),
            Err(CusumError::NonFiniteDrift { index: 1, .. })
        ));
        assert_eq!(fit(&rows, 0.4, &[]), Err(CusumError::EmptyDriftGrid));
        // Drift so large that S never leaves 0.
        assert_eq!(fit(&rows, 0.4, &[100.0]), Err(CusumError::NoThresholds));
        assert!(fit(&rows, f64::NAN, &DRIFT_GRID).is_err());
        // A trajectory start without a key change, and a key change without a start flag.
        let mut extra_start = rows.clone();
        extra_start[10].trajectory_start = true;
        assert_eq!(
            fit(&extra_start, 0.4, &DRIFT_GRID),
            Err(CusumError::InconsistentTrajectoryStart {
                row: 10,
                flag: true
            })
        );
        let mut silent_change = rows.clone();
        silent_change
            .iter_mut()
            .skip(10)
            .for_each(|row| row.trajectory = 2);
        assert_eq!(
            fit(&silent_change, 0.4, &DRIFT_GRID),
            Err(CusumError::InconsistentTrajectoryStart {
                row: 10,
                flag: false
            })
        );
        // No valid rows at all.
        let mut invalid = rows.clone();
        invalid.iter_mut().for_each(|row| row.valid = false);
        assert_eq!(
            fit(&invalid, 0.4, &DRIFT_GRID),
            Err(CusumError::NoThresholds)
        );
    }

    #[test]
    fn params_round_trip_through_json() {
        let p = params(0.294, 2.0, 3.5, 4);
        let json = serde_json::to_string(&p).expect("serialisable");
        assert_eq!(
            serde_json::from_str::<CusumParams>(&json).expect("deserialisable"),
            p
        );
    }
}
