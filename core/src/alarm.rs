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
use crate::metrics::{self, EventRules, Metrics, MetricsError, RateGroup, ScoredRow};
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

/// Every (θ, lifecycle) of the lifecycle search, θ outermost (the search's order).
fn lifecycle_grid(thetas: &[f64]) -> impl Iterator<Item = (OperatingPoint, Lifecycle)> + '_ {
    thetas.iter().flat_map(|&theta| {
        ON_S_GRID.into_iter().flat_map(move |on_s| {
            OFF_S_GRID.into_iter().flat_map(move |off_s| {
                DECISIVE_S_GRID.into_iter().map(move |decisive_s| {
                    let lifecycle = Lifecycle {
                        on_s,
                        off_s,
                        decisive_s,
                    };
                    (OperatingPoint { theta, n_p: 1 }, lifecycle)
                })
            })
        })
    })
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
/// holds pooled, at each sample rate, and at each rate on open roads and in town
/// ([`metrics::rate_and_pace_groups`], from `speeds_mps`, each row's onboard speed), in every group
/// with room for one false alarm; a margin holds pooled and at each rate
/// ([`OperatingPointRule::allowed_onsets_in`]).
pub fn choose_lifecycle(
    rows: &[ScoredRow],
    offset: &[OffsetSignal],
    speeds_mps: &[f64],
    thetas: &[f64],
    rules: EventRules,
    rule: OperatingPointRule,
) -> Result<LifecycleSelection, AlarmError> {
    let budget = rule.budget();
    check_search(rows, thetas, 1)?;
    let normal_hours = metrics::normal_hours(rows);
    // The budget holds pooled and in every group of rate (and pace) where it binds.
    let groups: Vec<_> = metrics::rate_and_pace_groups(rows, speeds_mps)
        .into_iter()
        .filter(|g| rule.binds(g))
        .collect();
    let mut best: Option<(OperatingPoint, Lifecycle, Metrics)> = None;
    let mut fewest_onsets = u64::MAX;
    let mut alarms = Vec::with_capacity(rows.len());
    for (point, lifecycle) in lifecycle_grid(thetas) {
        fill_lifecycle_alarms(rows, offset, point.theta, &lifecycle, &mut alarms);
        let candidate = metrics::alarm_metrics(rows, &alarms, rules);
        fewest_onsets = fewest_onsets.min(candidate.false_alarm_onsets);
        let within_budget = budget.is_none_or(|_| {
            candidate.false_alarm_onsets as f64 <= rule.allowed_onsets(normal_hours)
                && groups.iter().all(|g| {
                    g.false_alarm_onsets(rows, &alarms) as f64 <= rule.allowed_onsets_in(g)
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
    let Some((point, lifecycle, _)) = best else {
        // Only on failure: score the grid again to find the group no point kept within, so
        // that the error names the drives to bring more of.
        let mut fewest_by_group = vec![u64::MAX; groups.len()];
        for (point, lifecycle) in lifecycle_grid(thetas) {
            fill_lifecycle_alarms(rows, offset, point.theta, &lifecycle, &mut alarms);
            for (fewest, g) in fewest_by_group.iter_mut().zip(&groups) {
                *fewest = (*fewest).min(g.false_alarm_onsets(rows, &alarms));
            }
        }
        let groups: Vec<&RateGroup> = groups.iter().collect();
        return Err(rule.over_budget_in_groups(
            normal_hours,
            fewest_onsets,
            &groups,
            &fewest_by_group,
        ));
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
    /// Every point of the grid raises more false alarms than the budget allows, in the drives
    /// `scope` names (all of them, or the group of one rate, or of one rate and pace, that no
    /// point kept within on its own).
    #[error(
        "no operating point stays within {per_hour} false alarms per hour on {scope} \
         ({normal_hours:.2} attack-free hours allow at most {allowed_onsets} false-alarm onsets; \
         the quietest point raised {fewest_onsets} there)"
    )]
    OverBudget {
        /// The budget, false-alarm events per attack-free hour.
        per_hour: f64,
        /// Which drives the numbers count: "all drives", "5 Hz open-road drives", …
        scope: String,
        /// Attack-free hours of those drives.
        normal_hours: f64,
        /// The most false-alarm onsets the rule allowed on them.
        allowed_onsets: u64,
        /// The fewest false-alarm onsets any point of the grid raised on them.
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

/// The scope of a budget counted over every drive of the selection rows.
const ALL_DRIVES: &str = "all drives";

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

    /// Whether the budget holds in `group` of its own: only where the group has room for at least
    /// one false alarm (a group with less attack-free time counts in the pooled budget only).
    pub(crate) fn binds(self, group: &RateGroup) -> bool {
        self.budget()
            .is_some_and(|per_hour| per_hour * group.normal_hours >= 1.0)
    }

    /// The most false-alarm onsets a point may raise in `group`. The margin guards the budget a
    /// fleet counts, at each sample rate; a group of one rate and pace guards the mix (open-road
    /// vehicles raising most of a rate's alarms) and holds the plain budget: with a margin there
    /// too, a fleet whose open-road driving sits just within one alarm per hour, on the few hours
    /// of it a validation part holds, could never be fitted.
    pub(crate) fn allowed_onsets_in(self, group: &RateGroup) -> f64 {
        match (self, group.pace) {
            (Self::WithinFalseAlarmBudgetWithMargin { per_hour }, Some(_)) => {
                Self::WithinFalseAlarmBudget { per_hour }.allowed_onsets(group.normal_hours)
            }
            _ => self.allowed_onsets(group.normal_hours),
        }
    }

    /// The error when no point of a search with this rule, the quietest raising `fewest_onsets`
    /// on all the drives' `normal_hours`, kept within it.
    pub(crate) fn over_budget(self, normal_hours: f64, fewest_onsets: u64) -> AlarmError {
        self.over_budget_on(
            ALL_DRIVES.to_owned(),
            (normal_hours, self.allowed_onsets(normal_hours)),
            fewest_onsets,
        )
    }

    /// The error when no point kept within this rule where the budget also holds in groups: all
    /// the drives if even their quietest point was over, else the first group whose quietest
    /// point (`fewest_by_group`, one per group) was over its own allowance, else all the drives
    /// "and each rate and pace at once" (each alone had a point within; none held them all).
    pub(crate) fn over_budget_in_groups(
        self,
        normal_hours: f64,
        fewest_onsets: u64,
        groups: &[&RateGroup],
        fewest_by_group: &[u64],
    ) -> AlarmError {
        if fewest_onsets as f64 > self.allowed_onsets(normal_hours) {
            return self.over_budget(normal_hours, fewest_onsets);
        }
        let over = groups
            .iter()
            .zip(fewest_by_group)
            .find(|(group, fewest)| **fewest as f64 > self.allowed_onsets_in(group));
        match over {
            Some((group, &fewest)) => self.over_budget_on(
                group.describe(),
                (group.normal_hours, self.allowed_onsets_in(group)),
                fewest,
            ),
            None => self.over_budget_on(
                format!("{ALL_DRIVES} and each rate and pace at once"),
                (normal_hours, self.allowed_onsets(normal_hours)),
                fewest_onsets,
            ),
        }
    }

    /// The error for the drives `scope` names, with their attack-free hours and the onsets the
    /// rule allowed on them.
    fn over_budget_on(
        self,
        scope: String,
        (normal_hours, allowed): (f64, f64),
        fewest_onsets: u64,
    ) -> AlarmError {
        AlarmError::OverBudget {
            per_hour: self.budget().unwrap_or(f64::INFINITY),
            scope,
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
mod tests;
