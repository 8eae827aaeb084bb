//! Confirmed alarms and the operating point (SPEC §7).
//!
//! c_t = 1[score_t ≥ θ]; the confirmed alarm c̄_t = 1 when the last N_p valid steps all had c = 1. A ν = 0
//! step or a new trajectory resets the run, and c̄ = 0 on a ν = 0 step. The alarm is not latched.
//! (θ, N_p) is chosen on validation rows by maximising F1 of c̄ with a fixed tie-break order.
//!
//! Owns thresholds, persistence and the operating-point search for every detector. Must not run a
//! detector or build evidence (it sees only [`ScoredRow`]s).

use std::cmp::Ordering;
use std::ops::RangeInclusive;

use serde::{Deserialize, Serialize};

use crate::lifecycle::{AlarmLifecycle, Lifecycle, LifecycleInput, OffsetSignal};
use crate::metrics::{self, EventRules, Metrics, MetricsError, ScoredRow};
use crate::receiver::FlagSignal;

/// The alarm threshold θ on the score and the persistence N_p (consecutive valid steps).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct OperatingPoint {
    /// c_t = 1[score_t ≥ θ].
    pub theta: f64,
    /// Consecutive valid steps with c = 1 needed for c̄ = 1 (0 behaves as 1).
    pub n_p: u32,
}

/// The N_p grid of SPEC §7.
pub const N_P_GRID: RangeInclusive<u32> = 1..=10;

/// Largest N_p a served operating point may ask for: an hour of consecutive positive steps at 1 Hz.
/// The search grid stops at 10; a persistence beyond an hour can never confirm an attack in time (and
/// N_p = 2³²−1 never alarms at all).
pub const MAX_PERSISTENCE: u32 = 3600;

impl OperatingPoint {
    /// Checks θ ∈ (0, 1) (θ = 0 alarms on everything, θ = 1 on nothing but p̂ = 1) and
    /// N_p ∈ 1..=[`MAX_PERSISTENCE`]; the error names the field (`theta`, `n_p`).
    pub fn validate(&self) -> Result<(), AlarmError> {
        if !(self.theta > 0.0 && self.theta < 1.0) {
            return Err(AlarmError::InvalidOperatingPoint {
                field: "theta",
                reason: format!(
                    "must be strictly between 0 and 1, got {}",
                    crate::sample::readable(self.theta)
                ),
            });
        }
        if !(1..=MAX_PERSISTENCE).contains(&self.n_p) {
            return Err(AlarmError::InvalidOperatingPoint {
                field: "n_p",
                reason: format!("must be in 1..={MAX_PERSISTENCE}, got {}", self.n_p),
            });
        }
        Ok(())
    }
}

/// The θ grid of SPEC §7: k/20 for k = 1..=19 (0.05, 0.10, …, 0.95), computed exactly that way.
pub fn theta_grid() -> Vec<f64> {
    (1..=19).map(|k| f64::from(k) / 20.0).collect()
}

/// Streaming persistence confirmation of one vehicle's raw alarms c_t.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct PersistenceAlarm {
    n_p: u32,
    /// Consecutive valid steps with c = 1 so far in this trajectory.
    run: u32,
}

impl PersistenceAlarm {
    /// A confirmer needing `n_p` consecutive valid positive steps. `n_p = 0` behaves as 1: a confirmed
    /// alarm always needs the current step to be positive.
    pub fn new(n_p: u32) -> Self {
        Self { n_p, run: 0 }
    }

    /// The persistence N_p this confirmer was built with.
    pub fn n_p(&self) -> u32 {
        self.n_p
    }

    /// Feeds one step: `positive` = c_t, `valid` = ν_t, `trajectory_start` = first step of a trajectory.
    /// Returns c̄_t.
    pub fn update(&mut self, positive: bool, valid: bool, trajectory_start: bool) -> bool {
        if trajectory_start {
            self.run = 0;
        }
        if !valid || !positive {
            self.run = 0;
            return false;
        }
        self.run = self.run.saturating_add(1);
        self.run >= self.n_p.max(1)
    }

    /// Forgets the current run (as at a trajectory start).
    pub fn reset(&mut self) {
        self.run = 0;
    }
}

/// Confirmed alarms c̄ of `rows` at `op`, streamed through [`PersistenceAlarm`]; a change of trajectory
/// key starts a new trajectory. A NaN score is never positive.
pub fn confirmed_alarms(rows: &[ScoredRow], op: OperatingPoint) -> Vec<bool> {
    let mut alarms = Vec::with_capacity(rows.len());
    fill_confirmed_alarms(rows, op, &mut alarms);
    alarms
}

/// [`confirmed_alarms`] into a reused buffer (the grid search calls it 190+ times).
fn fill_confirmed_alarms(rows: &[ScoredRow], op: OperatingPoint, alarms: &mut Vec<bool>) {
    alarms.clear();
    let mut persistence = PersistenceAlarm::new(op.n_p);
    for (i, row) in rows.iter().enumerate() {
        let trajectory_start = i == 0 || rows[i - 1].trajectory != row.trajectory;
        alarms.push(persistence.update(row.score >= op.theta, row.valid, trajectory_start));
    }
}

/// The lifecycle search's θ grid: [`theta_grid`] and a tail towards 1. Under a false-alarm budget
/// per vehicle-hour a model confident on a few clean stretches needs a threshold above 0.95; the
/// tail lets the search find it instead of reporting no operating point.
pub fn lifecycle_theta_grid() -> Vec<f64> {
    let mut grid = theta_grid();
    grid.extend([0.97, 0.98, 0.99]);
    grid
}

/// T_on grid of the lifecycle search (s).
pub const ON_S_GRID: [f64; 7] = [0.0, 1.0, 2.0, 4.0, 8.0, 12.0, 16.0];
/// T_off grid (s).
pub const OFF_S_GRID: [f64; 3] = [2.0, 5.0, 10.0];
/// Grid of the seconds an offset must be held beyond the decisive gate (s). A jump must be alarmed
/// within 10 s; a hold restarted once by a sample back inside the gate takes twice the hold and a
/// sample, so no hold is longer than 3 s.
pub const DECISIVE_S_GRID: [f64; 3] = [1.0, 2.0, 3.0];

/// Confirmed alarms of `rows` under θ and `lifecycle`, with the offset evidence of each row
/// (`offset` empty: none); a change of trajectory key starts a new trajectory. A NaN score is never
/// positive.
pub fn lifecycle_alarms(
    rows: &[ScoredRow],
    offset: &[OffsetSignal],
    theta: f64,
    lifecycle: &Lifecycle,
) -> Vec<bool> {
    let mut alarms = Vec::with_capacity(rows.len());
    fill_lifecycle_alarms(rows, offset, theta, lifecycle, &mut alarms);
    alarms
}

fn fill_lifecycle_alarms(
    rows: &[ScoredRow],
    offset: &[OffsetSignal],
    theta: f64,
    lifecycle: &Lifecycle,
    alarms: &mut Vec<bool>,
) {
    alarms.clear();
    let mut state = AlarmLifecycle::default();
    for i in 0..rows.len() {
        alarms.push(state.update(lifecycle, &lifecycle_input(rows, offset, theta, i)));
    }
}

/// Row `i` of scored `rows` as the lifecycle's input under θ: a change of trajectory key starts a
/// new trajectory, and no receiver flag is read (the searches choose the durations of p̂ and the
/// offset; the flag's rule is fixed, §7.3, and it never escalates, §7.4).
pub(crate) fn lifecycle_input(
    rows: &[ScoredRow],
    offset: &[OffsetSignal],
    theta: f64,
    i: usize,
) -> LifecycleInput {
    let row = &rows[i];
    LifecycleInput {
        time_s: row.time_s,
        valid: row.valid,
        trajectory_start: i == 0 || rows[i - 1].trajectory != row.trajectory,
        positive: row.score >= theta,
        probability: row.score,
        offset: offset.get(i).copied().unwrap_or_default(),
        flag: FlagSignal::default(),
    }
}

/// A chosen θ and lifecycle with the validation metrics they achieve.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LifecycleSelection {
    /// θ (N_p is 1: the lifecycle replaces it).
    pub point: OperatingPoint,
    pub lifecycle: Lifecycle,
    pub metrics: Metrics,
}

/// Chooses θ from `thetas` and the lifecycle from [`ON_S_GRID`] × [`OFF_S_GRID`] ×
/// [`DECISIVE_S_GRID`] by `rule`, with the objective and tie-breaks of [`choose_operating_point`]
/// (then the shorter T_on, the longer decisive hold and the shorter T_off). A false-alarm budget
/// holds pooled and at each sample rate ([`metrics::rate_groups`]) with room for one false alarm.
pub fn choose_lifecycle(
    rows: &[ScoredRow],
    offset: &[OffsetSignal],
    thetas: &[f64],
    rules: EventRules,
    rule: OperatingPointRule,
) -> Result<LifecycleSelection, AlarmError> {
    let budget = rule.budget();
    check_search(rows, thetas, 1)?;
    let normal_hours = metrics::normal_hours(rows);
    // The budget holds pooled and at every sample rate with room for at least one false alarm
    // (a rate with less attack-free time counts in the pooled budget only).
    let rate_groups: Vec<_> = metrics::rate_groups(rows)
        .into_iter()
        .filter(|g| budget.is_some_and(|per_hour| per_hour * g.normal_hours >= 1.0))
        .collect();
    let mut best: Option<(OperatingPoint, Lifecycle, Metrics)> = None;
    let mut fewest_onsets = u64::MAX;
    let mut alarms = Vec::with_capacity(rows.len());
    for &theta in thetas {
        for on_s in ON_S_GRID {
            for off_s in OFF_S_GRID {
                for decisive_s in DECISIVE_S_GRID {
                    let point = OperatingPoint { theta, n_p: 1 };
                    let lifecycle = Lifecycle {
                        on_s,
                        off_s,
                        decisive_s,
                    };
                    fill_lifecycle_alarms(rows, offset, theta, &lifecycle, &mut alarms);
                    let candidate = metrics::alarm_metrics(rows, &alarms, rules);
                    fewest_onsets = fewest_onsets.min(candidate.false_alarm_onsets);
                    let within_budget = budget.is_none_or(|_| {
                        candidate.false_alarm_onsets as f64 <= rule.allowed_onsets(normal_hours)
                            && rate_groups.iter().all(|g| {
                                g.false_alarm_onsets(rows, &alarms) as f64
                                    <= rule.allowed_onsets(g.normal_hours)
                            })
                    });
                    let improves = best.as_ref().is_none_or(|(b_point, b_life, b_metrics)| {
                        compare_candidates((&point, &candidate), (b_point, b_metrics))
                            .then(b_life.on_s.total_cmp(&lifecycle.on_s))
                            .then(lifecycle.decisive_s.total_cmp(&b_life.decisive_s))
                            .then(b_life.off_s.total_cmp(&lifecycle.off_s))
                            == Ordering::Greater
                    });
                    if within_budget && improves {
                        best = Some((point, lifecycle, candidate));
                    }
                }
            }
        }
    }
    let Some((point, lifecycle, _)) = best else {
        return Err(rule.over_budget(normal_hours, fewest_onsets));
    };
    let metrics = metrics::evaluate(
        rows,
        &lifecycle_alarms(rows, offset, point.theta, &lifecycle),
        rules,
    );
    Ok(LifecycleSelection {
        point,
        lifecycle,
        metrics,
    })
}

/// A chosen operating point with the validation metrics it achieves (AUROC/AUPRC included).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Selection {
    /// The chosen (θ, N_p).
    pub point: OperatingPoint,
    /// Metrics of the confirmed alarms at `point` on the selection rows.
    pub metrics: Metrics,
}

/// Why no operating point can be chosen.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum AlarmError {
    /// The rows cannot be evaluated.
    #[error("invalid rows: {0}")]
    Rows(#[from] MetricsError),
    /// F1 on ν = 1 rows is meaningless without them.
    #[error("no valid (ν = 1) rows to choose an operating point on")]
    NoValidRows,
    /// The θ grid or the N_p range is empty.
    #[error("the operating-point grid is empty ({thetas} thresholds, {n_ps} persistence values)")]
    EmptyGrid {
        /// Number of thresholds given.
        thetas: usize,
        /// Number of N_p values given.
        n_ps: usize,
    },
    /// Every point of the grid raises more false alarms than the budget allows.
    #[error(
        "no operating point stays within {per_hour} false alarms per hour ({normal_hours:.2} \
         attack-free hours allow at most {allowed_onsets} false-alarm onsets; the quietest point \
         raised {fewest_onsets})"
    )]
    OverBudget {
        /// The budget, false-alarm events per attack-free hour.
        per_hour: f64,
        /// Attack-free hours of the selection rows.
        normal_hours: f64,
        /// The most false-alarm onsets the rule allowed on them (pooled).
        allowed_onsets: u64,
        /// The fewest false-alarm onsets any point of the grid raised (pooled).
        fewest_onsets: u64,
    },
    /// A served operating point is out of its range.
    #[error("operating point {field}: {reason}")]
    InvalidOperatingPoint {
        /// `theta` or `n_p`.
        field: &'static str,
        /// What is wrong with it.
        reason: String,
    },
    /// A NaN threshold compares false with every score.
    #[error("threshold {index} of the grid is NaN")]
    NanThreshold {
        /// Position in the θ grid.
        index: usize,
    },
}

/// How (θ, N_p) is chosen on validation rows (SPEC §7 and the false-alarm budget of the subtle
/// experiment). Used for the HO-LLN threshold and the CUSUM comparator's alike.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(tag = "rule", rename_all = "snake_case")]
pub enum OperatingPointRule {
    /// Best F1 of c̄ on ν = 1 rows, then the tie-breaks of [`choose_operating_point`].
    #[default]
    BestValidationF1,
    /// Best F1 among the points raising at most `per_hour` false-alarm events per hour of
    /// attack-free time on the rows ([`metrics::normal_hours`]).
    WithinFalseAlarmBudget { per_hour: f64 },
    /// As `WithinFalseAlarmBudget`, with a margin for the search's optimism: of hundreds of points,
    /// the one chosen is the one the validation hours happened to flatter most, so a point whose
    /// true rate is at the budget passes about half the time. Here its onsets must stay one Poisson
    /// standard deviation below the budget's count (λ − √λ for λ = `per_hour` × attack-free hours),
    /// which such a point passes about one time in six. For validation parts of a few hours to a
    /// few dozen, as a fleet's own recordings give.
    WithinFalseAlarmBudgetWithMargin { per_hour: f64 },
}

impl OperatingPointRule {
    /// The false-alarm budget, if any.
    pub fn budget(self) -> Option<f64> {
        match self {
            Self::BestValidationF1 => None,
            Self::WithinFalseAlarmBudget { per_hour }
            | Self::WithinFalseAlarmBudgetWithMargin { per_hour } => Some(per_hour),
        }
    }

    /// The most false-alarm onsets a point may raise in `normal_hours` attack-free hours.
    pub fn allowed_onsets(self, normal_hours: f64) -> f64 {
        match self {
            Self::BestValidationF1 => f64::INFINITY,
            Self::WithinFalseAlarmBudget { per_hour } => per_hour * normal_hours,
            Self::WithinFalseAlarmBudgetWithMargin { per_hour } => {
                let expected = per_hour * normal_hours;
                (expected - expected.sqrt()).max(0.0)
            }
        }
    }

    /// The error when no point of a search with this rule, the quietest raising `fewest_onsets`,
    /// kept within it on `normal_hours`.
    pub(crate) fn over_budget(self, normal_hours: f64, fewest_onsets: u64) -> AlarmError {
        let allowed = self.allowed_onsets(normal_hours);
        AlarmError::OverBudget {
            per_hour: self.budget().unwrap_or(f64::INFINITY),
            normal_hours,
            allowed_onsets: if allowed.is_finite() {
                allowed.floor() as u64
            } else {
                u64::MAX
            },
            fewest_onsets,
        }
    }
}

/// Chooses (θ, N_p) from `thetas` × `n_ps` by `rule` and reports the metrics there: maximise F1 of c̄
/// on ν = 1 rows; ties go to higher ADR, lower mean delay (no detection = worst), lower FPR, higher
/// recall, lower N_p, higher θ. `thetas` may be on any scale (the CUSUM thresholds its own
/// statistic); SPEC §7's grid is [`theta_grid`] × [`N_P_GRID`]. `rules` defines events (ADR, delay).
/// Duplicate thresholds are harmless.
pub fn choose_operating_point(
    rows: &[ScoredRow],
    thetas: &[f64],
    n_ps: RangeInclusive<u32>,
    rules: EventRules,
    rule: OperatingPointRule,
) -> Result<Selection, AlarmError> {
    let budget = rule.budget();
    check_search(rows, thetas, n_ps.clone().count())?;
    let normal_hours = metrics::normal_hours(rows);
    let mut best: Option<(OperatingPoint, Metrics)> = None;
    let mut fewest_onsets = u64::MAX;
    let mut alarms = Vec::with_capacity(rows.len());
    for &theta in thetas {
        for n_p in n_ps.clone() {
            let point = OperatingPoint { theta, n_p };
            fill_confirmed_alarms(rows, point, &mut alarms);
            let candidate = metrics::alarm_metrics(rows, &alarms, rules);
            fewest_onsets = fewest_onsets.min(candidate.false_alarm_onsets);
            let within_budget = budget.is_none_or(|_| {
                candidate.false_alarm_onsets as f64 <= rule.allowed_onsets(normal_hours)
            });
            let improves = best.as_ref().is_none_or(|(best_point, best_metrics)| {
                compare_candidates((&point, &candidate), (best_point, best_metrics))
                    == Ordering::Greater
            });
            if within_budget && improves {
                best = Some((point, candidate));
            }
        }
    }
    let Some((point, _)) = best else {
        return Err(rule.over_budget(normal_hours, fewest_onsets));
    };
    // AUROC/AUPRC do not depend on the alarms: computed once, for the winner only.
    let metrics = metrics::evaluate(rows, &confirmed_alarms(rows, point), rules);
    Ok(Selection { point, metrics })
}

/// What every operating-point search needs: rows that can be evaluated, some of them valid, and a
/// non-empty grid without NaN thresholds (`n_ps` persistence values, or 1 for the lifecycle).
fn check_search(rows: &[ScoredRow], thetas: &[f64], n_ps: usize) -> Result<(), AlarmError> {
    metrics::check_rows(rows)?;
    if !rows.iter().any(|row| row.valid) {
        return Err(AlarmError::NoValidRows);
    }
    if let Some(index) = thetas.iter().position(|theta| theta.is_nan()) {
        return Err(AlarmError::NanThreshold { index });
    }
    if thetas.is_empty() || n_ps == 0 {
        return Err(AlarmError::EmptyGrid {
            thetas: thetas.len(),
            n_ps,
        });
    }
    Ok(())
}

/// SPEC §7's objective as an ordering: `Greater` when `a` is the better operating point.
pub(crate) fn compare_candidates(
    a: (&OperatingPoint, &Metrics),
    b: (&OperatingPoint, &Metrics),
) -> Ordering {
    let ((a_point, a_metrics), (b_point, b_metrics)) = (a, b);
    a_metrics
        .f1
        .total_cmp(&b_metrics.f1)
        .then(a_metrics.adr.total_cmp(&b_metrics.adr))
        .then(compare_mean_delay(
            a_metrics.mean_delay_s,
            b_metrics.mean_delay_s,
        ))
        .then(b_metrics.fpr.total_cmp(&a_metrics.fpr))
        .then(a_metrics.recall.total_cmp(&b_metrics.recall))
        .then(b_point.n_p.cmp(&a_point.n_p))
        .then(a_point.theta.total_cmp(&b_point.theta))
}

/// Lower delay is better; no detection at all is worst.
pub(crate) fn compare_mean_delay(a: Option<f64>, b: Option<f64>) -> Ordering {
    match (a, b) {
        (Some(a), Some(b)) => b.total_cmp(&a),
        (Some(_), None) => Ordering::Greater,
        (None, Some(_)) => Ordering::Less,
        (None, None) => Ordering::Equal,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const BEST_F1: OperatingPointRule = OperatingPointRule::BestValidationF1;

    /// One trajectory at 1 Hz, all rows valid: (label, score) pairs.
    fn one_trajectory(pairs: &[(u8, f64)]) -> Vec<ScoredRow> {
        pairs
            .iter()
            .enumerate()
            .map(|(i, &(label, score))| ScoredRow {
                trajectory: 0,
                time_s: i as f64,
                valid: true,
                label: label == 1,
                score,
            })
            .collect()
    }

    fn bits(values: &[u8]) -> Vec<bool> {
        values.iter().map(|&v| v == 1).collect()
    }

    #[test]
    fn theta_grid_is_k_over_20() {
        let grid = theta_grid();
        assert_eq!(grid.len(), 19);
        assert_eq!(grid[0], 0.05);
        assert_eq!(grid[11], 0.6);
        assert_eq!(grid[18], 0.95);
        assert_eq!(N_P_GRID.count(), 10);
    }

    #[test]
    fn persistence_needs_n_p_consecutive_valid_positives_and_is_not_latched() {
        let mut alarm = PersistenceAlarm::new(3);
        let positives = bits(&[1, 1, 1, 1, 0, 1, 1, 1]);
        let confirmed: Vec<bool> = positives
            .iter()
            .map(|&p| alarm.update(p, true, false))
            .collect();
        assert_eq!(confirmed, bits(&[0, 0, 1, 1, 0, 0, 0, 1]));
    }

    #[test]
    fn persistence_resets_on_invalid_steps_and_trajectory_starts() {
        let mut alarm = PersistenceAlarm::new(2);
        assert!(!alarm.update(true, true, false));
        assert!(alarm.update(true, true, false));
        // ν = 0: c̄ = 0 even though c = 1, and the run restarts.
        assert!(!alarm.update(true, false, false));
        assert!(!alarm.update(true, true, false));
        assert!(alarm.update(true, true, false));
        // A trajectory start resets the run; a valid start step counts as the first of the new run.
        assert!(!alarm.update(true, true, true));
        assert!(alarm.update(true, true, false));
        alarm.reset();
        assert!(!alarm.update(true, true, false));
    }

    #[test]
    fn persistence_of_zero_behaves_as_one() {
        let mut alarm = PersistenceAlarm::new(0);
        assert!(!alarm.update(false, true, false));
        assert!(alarm.update(true, true, false));
        assert!(!alarm.update(true, false, false));
    }

    #[test]
    fn confirmed_alarms_threshold_scores_and_restart_per_trajectory() {
        let mut rows =
            one_trajectory(&[(0, 0.7), (0, 0.6), (0, 0.2), (0, 0.9), (0, 0.9), (0, 0.9)]);
        rows[4].trajectory = 1;
        rows[5].trajectory = 1;
        rows[5].score = f64::NAN;
        let op = OperatingPoint { theta: 0.6, n_p: 2 };
        // Row 1: 0.6 ≥ θ (inclusive) → second positive. Row 4 starts a new trajectory; row 5 is NaN.
        assert_eq!(confirmed_alarms(&rows, op), bits(&[0, 1, 0, 0, 0, 0]));
        let op1 = OperatingPoint { theta: 0.6, n_p: 1 };
        assert_eq!(confirmed_alarms(&rows, op1), bits(&[1, 1, 0, 1, 1, 0]));
    }

    #[test]
    fn selection_maximises_f1() {
        // Attack rows score 0.8, normal rows 0.3 except one normal spike at 0.5.
        let rows = one_trajectory(&[
            (0, 0.3),
            (0, 0.5),
            (0, 0.3),
            (1, 0.8),
            (1, 0.8),
            (1, 0.8),
            (0, 0.3),
        ]);
        let selection =
            choose_operating_point(&rows, &theta_grid(), N_P_GRID, EventRules::Spec, BEST_F1)
                .expect("valid rows");
        // Any θ in (0.5, 0.8] with N_p = 1 gives F1 = 1; tie-breaks: lower N_p, then higher θ → 0.8.
        assert_eq!(selection.point, OperatingPoint { theta: 0.8, n_p: 1 });
        assert_eq!(selection.metrics.f1, 1.0);
        assert_eq!(selection.metrics.auroc, Some(1.0));
        assert_eq!(selection.metrics.delays_s, vec![Some(0.0)]);
    }

    /// Runs the selection on `rows` with an explicit grid.
    fn choose(rows: &[ScoredRow], thetas: &[f64], n_ps: RangeInclusive<u32>) -> OperatingPoint {
        choose_operating_point(rows, thetas, n_ps, EventRules::Spec, BEST_F1)
            .expect("valid rows")
            .point
    }

    #[test]
    fn selection_end_to_end_higher_adr_breaks_an_f1_tie() {
        // θ = 0.7 alarms on event A only: TP 1, FN 1, FP 0 → F1 2/3, ADR 1/2.
        // θ = 0.5 alarms on A, B and two normal rows: TP 2, FP 2 → F1 4/6 (the same double), ADR 1.
        // FPR and higher θ would prefer 0.7; ADR comes first.
        let rows = one_trajectory(&[(1, 0.8), (0, 0.0), (1, 0.6), (0, 0.0), (0, 0.6), (0, 0.6)]);
        assert_eq!(
            choose(&rows, &[0.5, 0.7], 1..=1),
            OperatingPoint { theta: 0.5, n_p: 1 }
        );
    }

    #[test]
    fn selection_end_to_end_lower_delay_breaks_an_f1_and_adr_tie() {
        // One event (rows 0, 1). θ = 0.7: onset at row 1 (delay 1 s), TP 1 FN 1 FP 0, F1 2/3.
        // θ = 0.5: onset at row 0 (delay 0 s), TP 2 FP 2, F1 2/3. ADR 1 for both. FPR prefers 0.7.
        let rows = one_trajectory(&[(1, 0.6), (1, 0.8), (0, 0.0), (0, 0.6), (0, 0.6)]);
        assert_eq!(
            choose(&rows, &[0.5, 0.7], 1..=1),
            OperatingPoint { theta: 0.5, n_p: 1 }
        );
    }

    #[test]
    fn selection_end_to_end_identical_alarms_prefer_lower_n_p_then_higher_theta() {
        // Scores are 0 or 1: every θ in the grid gives the same alarms, and runs of one positive row make
        // N_p = 1 strictly best; among the 19 equivalent θ the highest wins.
        let rows = one_trajectory(&[(1, 1.0), (0, 0.0), (1, 1.0), (0, 0.0)]);
        assert_eq!(
            choose(&rows, &theta_grid(), N_P_GRID),
            OperatingPoint {
                theta: 0.95,
                n_p: 1
            }
        );
        // No positive score at all: every grid point gives identical (empty) alarms → N_p 1, θ 0.95.
        let rows = one_trajectory(&[(1, 0.0), (0, 0.0)]);
        let selection =
            choose_operating_point(&rows, &theta_grid(), N_P_GRID, EventRules::Spec, BEST_F1)
                .expect("valid rows");
        assert_eq!(
            selection.point,
            OperatingPoint {
                theta: 0.95,
                n_p: 1
            }
        );
        assert_eq!(selection.metrics.f1, 0.0);
    }

    #[test]
    fn selection_respects_persistence_when_it_removes_false_alarms() {
        // Attack runs last 3 rows; the normal spikes last 1 row. N_p = 2 drops the spikes and keeps 2 of 3
        // attack rows per event: TP 4 FN 2 FP 0 → F1 8/10, better than N_p = 1 (TP 6 FP 4 → F1 12/16).
        let rows = one_trajectory(&[
            (0, 0.9),
            (0, 0.0),
            (1, 0.9),
            (1, 0.9),
            (1, 0.9),
            (0, 0.0),
            (0, 0.9),
            (0, 0.0),
            (0, 0.9),
            (0, 0.0),
            (0, 0.9),
            (0, 0.0),
            (1, 0.9),
            (1, 0.9),
            (1, 0.9),
        ]);
        let selection =
            choose_operating_point(&rows, &theta_grid(), N_P_GRID, EventRules::Spec, BEST_F1)
                .expect("valid rows");
        assert_eq!(selection.point, OperatingPoint { theta: 0.9, n_p: 2 });
        assert_eq!(selection.metrics.f1, 0.8);
        assert_eq!(selection.metrics.delays_s, vec![Some(1.0), Some(1.0)]);
    }

    /// A candidate whose every objective component is better (+1), equal (0) or worse (−1) than a
    /// baseline, in tie-break order: F1, ADR, mean delay, FPR, recall, N_p, θ.
    fn candidate(quality: [i32; 7]) -> (OperatingPoint, Metrics) {
        let q = quality.map(f64::from);
        let point = OperatingPoint {
            theta: 0.5 + 0.1 * q[6],
            n_p: u32::try_from(3 - quality[5]).expect("small"),
        };
        let metrics = Metrics {
            auroc: None,
            auprc: None,
            precision: 0.5,
            recall: 0.5 + 0.1 * q[4],
            f1: 0.5 + 0.1 * q[0],
            fpr: 0.1 - 0.05 * q[3],
            true_positives: 0,
            false_positives: 0,
            true_negatives: 0,
            false_negatives: 0,
            valid_rows: 0,
            events: 0,
            detected_events: 0,
            adr: 0.5 + 0.1 * q[1],
            delays_s: Vec::new(),
            mean_delay_s: Some(3.0 - q[2]),
            false_alarm_rows: 0,
            false_alarm_events: 0,
            false_alarm_onsets: 0,
        };
        (point, metrics)
    }

    #[test]
    fn each_tie_breaker_decides_in_order() {
        let baseline = candidate([0; 7]);
        for level in 0..7 {
            // Equal before `level`, better at `level`, worse at every later tie-breaker.
            let mut quality = [0; 7];
            quality[level] = 1;
            quality.iter_mut().skip(level + 1).for_each(|q| *q = -1);
            let (bp, bm) = candidate(quality);
            assert_eq!(
                compare_candidates((&bp, &bm), (&baseline.0, &baseline.1)),
                Ordering::Greater,
                "level {level}"
            );
            assert_eq!(
                compare_candidates((&baseline.0, &baseline.1), (&bp, &bm)),
                Ordering::Less,
                "level {level}"
            );
        }
        assert_eq!(
            compare_candidates((&baseline.0, &baseline.1), (&baseline.0, &baseline.1)),
            Ordering::Equal
        );
    }

    #[test]
    fn missing_mean_delay_is_the_worst_delay() {
        let (point, mut slow) = candidate([0; 7]);
        slow.mean_delay_s = Some(1e9);
        let (_, mut missed) = candidate([0; 7]);
        missed.mean_delay_s = None;
        assert_eq!(
            compare_candidates((&point, &slow), (&point, &missed)),
            Ordering::Greater
        );
    }

    #[test]
    fn selection_rejects_unusable_input() {
        let choose_spec = |rows: &[ScoredRow], thetas: &[f64]| {
            choose_operating_point(rows, thetas, N_P_GRID, EventRules::Spec, BEST_F1)
        };
        let mut invalid = one_trajectory(&[(1, 0.9), (0, 0.1)]);
        invalid.iter_mut().for_each(|row| row.valid = false);
        assert_eq!(
            choose_spec(&invalid, &theta_grid()),
            Err(AlarmError::NoValidRows)
        );
        assert!(choose_spec(&invalid, &theta_grid()).is_err());
        let good = one_trajectory(&[(1, 0.9), (0, 0.1)]);
        assert_eq!(
            choose_spec(&good, &[]),
            Err(AlarmError::EmptyGrid {
                thetas: 0,
                n_ps: 10
            })
        );
        assert!(choose_spec(&good, &[]).is_err());
        assert_eq!(
            choose_spec(&good, &[0.5, f64::NAN]),
            Err(AlarmError::NanThreshold { index: 1 })
        );
        let mut bad_time = good.clone();
        bad_time[0].time_s = f64::INFINITY;
        assert!(matches!(
            choose_spec(&bad_time, &theta_grid()),
            Err(AlarmError::Rows(MetricsError::NonFiniteTime { row: 0, .. }))
        ));
    }

    #[test]
    fn selection_agrees_with_evaluating_its_point() {
        let rows = one_trajectory(&[
            (0, 0.2),
            (0, 0.55),
            (1, 0.65),
            (1, 0.9),
            (1, 0.4),
            (1, 0.7),
            (0, 0.3),
        ]);
        let selection =
            choose_operating_point(&rows, &theta_grid(), N_P_GRID, EventRules::Spec, BEST_F1)
                .expect("valid rows");
        let alarms = confirmed_alarms(&rows, selection.point);
        let recomputed =
            metrics::try_evaluate(&rows, &alarms, EventRules::Spec).expect("valid rows");
        assert_eq!(selection.metrics, recomputed);
        assert_eq!(choose(&rows, &theta_grid(), N_P_GRID), selection.point);
    }

    /// 1,900 s at 1 Hz: a 100 s attack scored 0.7 and a 12 s normal stretch scored 0.75 (too long for
    /// any N_p to hide), so every point that detects the attack raises one false alarm.
    fn attack_and_one_false_alarm() -> Vec<ScoredRow> {
        let pairs: Vec<(u8, f64)> = (0..1900)
            .map(|i| match i {
                500..600 => (1, 0.7),
                1200..1212 => (0, 0.75),
                _ => (0, 0.1),
            })
            .collect();
        one_trajectory(&pairs)
    }

    #[test]
    fn a_false_alarm_budget_excludes_points_that_exceed_it() {
        let rows = attack_and_one_false_alarm();
        let normal_hours = metrics::normal_hours(&rows);
        assert!((normal_hours - 1799.0 / 3600.0).abs() < 1e-12);
        let free =
            choose_operating_point(&rows, &theta_grid(), N_P_GRID, EventRules::Spec, BEST_F1)
                .expect("valid rows");
        assert_eq!(free.point.theta, 0.7);
        assert_eq!(free.metrics.false_alarm_events, 1);
        // One event in ~0.5 h is 2 per hour: allowed by a budget of 2/h, not by 1/h.
        let within = |per_hour| {
            choose_operating_point(
                &rows,
                &theta_grid(),
                N_P_GRID,
                EventRules::Spec,
                OperatingPointRule::WithinFalseAlarmBudget { per_hour },
            )
        };
        assert_eq!(within(2.1).expect("within budget").point, free.point);
        let strict = within(1.0).expect("a quiet point exists");
        assert_eq!(strict.metrics.false_alarm_events, 0);
        assert!(strict.point.theta > 0.75);
        assert_eq!(strict.metrics.detected_events, 0);
    }

    #[test]
    fn the_budget_holds_at_every_sample_rate_not_only_pooled() {
        // Trajectory 0 at 1 Hz: two attack-free hours, then a 60 s attack scored 0.85.
        // Trajectory 1 at 10 Hz: just over an attack-free hour (a rate with room for one false
        // alarm) with two 20 s bursts scored 0.9 (longer than any T_on). Pooled, two
        // false alarms in three hours would be within 1/h and buy the detection (θ ≤ 0.85); at
        // 10 Hz they are two in one hour, so only a θ above the bursts is within the budget.
        let row = |trajectory, time_s, label, score| ScoredRow {
            trajectory,
            time_s,
            valid: true,
            label,
            score,
        };
        let mut rows: Vec<ScoredRow> = (0..7260)
            .map(|i| {
                let attacked = i >= 7200;
                row(0, f64::from(i), attacked, if attacked { 0.85 } else { 0.0 })
            })
            .collect();
        rows.extend((0..36_100).map(|i| {
            let t = f64::from(i) / 10.0;
            let burst = (1000.0..1020.0).contains(&t) || (2000.0..2020.0).contains(&t);
            row(1, t, false, if burst { 0.9 } else { 0.0 })
        }));
        let groups = metrics::rate_groups(&rows);
        let summary: Vec<(u32, f64)> = groups
            .iter()
            .map(|g| (g.rate_hz, (g.normal_hours * 1e6).round() / 1e6))
            .collect();
        assert_eq!(summary, vec![(1, 1.999722), (10, 1.002750)]);
        let offset = vec![OffsetSignal::default(); rows.len()];
        let chosen = choose_lifecycle(
            &rows,
            &offset,
            &theta_grid(),
            EventRules::Spec,
            OperatingPointRule::WithinFalseAlarmBudget { per_hour: 1.0 },
        )
        .expect("a point within the budget at both rates");
        assert!(chosen.point.theta > 0.9, "{chosen:?}");
        assert_eq!(chosen.metrics.false_alarm_onsets, 0);
        assert_eq!(chosen.metrics.detected_events, 0);
    }

    #[test]
    fn the_lifecycle_search_finds_a_point_above_0_95_when_the_budget_needs_one() {
        // An attack-free hour at 1 Hz with a 30 s stretch scored 0.96 (longer than any T_on), then
        // a 60 s attack scored 0.995: only θ = 0.97, 0.98 or 0.99 keeps the hour quiet and catches
        // the attack, and none of them is in the k/20 grid.
        let row = |time_s: f64, label, score| ScoredRow {
            trajectory: 0,
            time_s,
            valid: true,
            label,
            score,
        };
        let rows: Vec<ScoredRow> = (0..3660)
            .map(|i| {
                let t = f64::from(i);
                let (label, score) = match i {
                    1000..1030 => (false, 0.96),
                    3600.. => (true, 0.995),
                    _ => (false, 0.0),
                };
                row(t, label, score)
            })
            .collect();
        let offset = vec![OffsetSignal::default(); rows.len()];
        let budget = OperatingPointRule::WithinFalseAlarmBudget { per_hour: 0.5 };
        assert!(choose_lifecycle(&rows, &offset, &theta_grid(), EventRules::Spec, budget).is_err());
        let chosen = choose_lifecycle(
            &rows,
            &offset,
            &lifecycle_theta_grid(),
            EventRules::Spec,
            budget,
        )
        .expect("a point in the tail");
        assert!(chosen.point.theta > 0.96, "{chosen:?}");
        assert_eq!(chosen.metrics.false_alarm_onsets, 0);
        assert_eq!(chosen.metrics.detected_events, 1);
    }

    #[test]
    fn the_margin_keeps_one_poisson_deviation_below_the_budgets_count() {
        let plain = OperatingPointRule::WithinFalseAlarmBudget { per_hour: 1.0 };
        let margin = OperatingPointRule::WithinFalseAlarmBudgetWithMargin { per_hour: 1.0 };
        assert_eq!(plain.allowed_onsets(16.0), 16.0);
        assert_eq!(margin.allowed_onsets(16.0), 12.0, "16 − √16");
        assert_eq!(margin.allowed_onsets(0.27), 0.0, "never below none");
        let paging = OperatingPointRule::WithinFalseAlarmBudgetWithMargin { per_hour: 0.01 };
        assert_eq!(
            paging.allowed_onsets(100.0),
            0.0,
            "1 − √1: silent on 100 hours"
        );
        assert!((paging.allowed_onsets(900.0) - 6.0).abs() < 1e-12, "9 − 3");
        assert_eq!(
            OperatingPointRule::BestValidationF1.allowed_onsets(1.0),
            f64::INFINITY
        );
        assert_eq!(margin.budget(), Some(1.0));
    }

    #[test]
    fn with_the_margin_the_search_takes_a_quieter_point_than_the_budget_alone() {
        // 11 attack-free hours at 1 Hz with ten 20 s stretches (longer than any T_on): eight scored
        // 0.8 and two 0.93; then a 600 s attack scored 0.82 and then 0.95. θ ≤ 0.8 catches all of
        // the attack with 10 false onsets, within 11 but not within 11 − √11 = 7.7; above it, 2 or
        // none, and half the attack.
        let stretch = |i: u32| (1_000..1_020).contains(&(i % 3_600)) && i / 3_600 < 10;
        let rows: Vec<ScoredRow> = (0..40_200)
            .map(|i| {
                let (label, score) = match i {
                    39_600..39_900 => (true, 0.82),
                    39_900.. => (true, 0.95),
                    _ if stretch(i) && i / 3_600 < 8 => (false, 0.8),
                    _ if stretch(i) => (false, 0.93),
                    _ => (false, 0.0),
                };
                ScoredRow {
                    trajectory: 0,
                    time_s: f64::from(i),
                    valid: true,
                    label,
                    score,
                }
            })
            .collect();
        assert!((metrics::normal_hours(&rows) - 11.0).abs() < 0.01);
        let offset = vec![OffsetSignal::default(); rows.len()];
        let search = |rule| {
            choose_lifecycle(
                &rows,
                &offset,
                &lifecycle_theta_grid(),
                EventRules::Spec,
                rule,
            )
            .expect("a point")
        };
        let plain = search(OperatingPointRule::WithinFalseAlarmBudget { per_hour: 1.0 });
        assert!(plain.point.theta <= 0.8, "{plain:?}");
        assert_eq!(plain.metrics.false_alarm_onsets, 10);
        let margin = search(OperatingPointRule::WithinFalseAlarmBudgetWithMargin { per_hour: 1.0 });
        assert!(margin.point.theta > 0.8, "{margin:?}");
        assert!(margin.metrics.false_alarm_onsets <= 2, "{margin:?}");
        assert_eq!(margin.metrics.detected_events, 1);
        // Where no point keeps the margin, the error says what was allowed and the quietest.
        let error = choose_lifecycle(
            &rows,
            &offset,
            &theta_grid()[..10],
            EventRules::Spec,
            OperatingPointRule::WithinFalseAlarmBudgetWithMargin { per_hour: 1.0 },
        )
        .expect_err("θ ≤ 0.5 only");
        assert_eq!(
            error.to_string(),
            "no operating point stays within 1 false alarms per hour (11.00 attack-free hours \
             allow at most 7 false-alarm onsets; the quietest point raised 10)"
        );
    }

    #[test]
    fn an_unreachable_budget_is_an_error() {
        let mut rows = attack_and_one_false_alarm();
        for row in &mut rows[1200..1212] {
            row.score = 0.99; // above every θ of the grid
        }
        let result = choose_operating_point(
            &rows,
            &theta_grid(),
            N_P_GRID,
            EventRules::Spec,
            OperatingPointRule::WithinFalseAlarmBudget { per_hour: 0.0 },
        );
        assert!(matches!(
            result,
            Err(AlarmError::OverBudget { per_hour, .. }) if per_hour == 0.0
        ));
    }
}
