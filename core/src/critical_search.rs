//! Choosing the critical test (`docs/detector.md` §7.4) on validation data, after the warning's
//! θ and lifecycle: the stricter budget (critical onsets per attack-free hour, counted as the
//! warning's are) must hold pooled and at every sample rate with room for one; among the tests
//! within it, the one that escalates the most attacks, soonest.
//!
//! Owns the critical test's search grid and objective. Must not run the model, build evidence or
//! choose the warning's operating point (that is `alarm.rs`).

use std::cmp::Ordering;

use serde::{Deserialize, Serialize};

use crate::alarm::{AlarmError, OperatingPointRule, compare_mean_delay, lifecycle_input};
use crate::lifecycle::{AlarmLifecycle, Lifecycle, OffsetSignal};
use crate::metrics::{self, EventRules, Metrics, RateGroup, ScoredRow};
use crate::severity::{CriticalTest, Escalation, HeldOffsetTest, Severity};

/// Grid of k, the logit of p̂ above which evidence accumulates: p̂ from 0.5 to 0.9975.
pub const REFERENCE_LOGIT_GRID: [f64; 6] = [1.0, 2.0, 3.0, 4.0, 5.0, 6.0];
/// Grid of h (logit·s): from a few seconds of strong evidence to minutes of it.
pub const THRESHOLD_GRID: [f64; 7] = [10.0, 20.0, 40.0, 80.0, 160.0, 320.0, 640.0];
/// Grid of the NIS gate of the decisive path: from the decisive gate of §4.2 (5σ) to 20σ.
pub const GATE_GRID: [f64; 4] = [25.0, 100.0, 400.0, 1600.0];
/// Grid of the seconds the NIS must stay beyond the gate: within the 10 s a jump must be paged in.
pub const CRITICAL_DECISIVE_S_GRID: [f64; 5] = [1.0, 2.0, 3.0, 5.0, 8.0];
/// Grid of the seconds a frozen fix on a moving vehicle must be held (after the 2 s that make it
/// frozen) to be critical at once, tried on the test chosen from the other grids: 2–10 s of a
/// repeated fix, within the 10 s a frozen fix must be paged in.
pub const FROZEN_FIX_S_GRID: [f64; 4] = [0.0, 2.0, 4.0, 8.0];
/// Grid of the held-jump path's gate, tried on the test chosen with its frozen-fix path: from the
/// decisive gate of §4.2 (5σ) to the decisive path's lowest alternative (20σ).
pub const HELD_JUMP_GATE_GRID: [f64; 5] = [25.0, 49.0, 100.0, 225.0, 400.0];
/// Grid of the held-step path's gate (the arrival step's NIS against the vehicle's one-row noise),
/// tried on the test chosen with its held-jump path: 7σ to 15σ of one row's noise, so that a 20 m
/// jump on a receiver like the population's (about 1.4 m per axis and row) passes the lower ones.
pub const HELD_STEP_GATE_GRID: [f64; 5] = [49.0, 64.0, 100.0, 144.0, 225.0];
/// Grid of the seconds a jump must have been held, on the held-jump and held-step paths: within
/// the 10 s a jump must be paged in.
pub const HELD_JUMP_S_GRID: [f64; 4] = [1.0, 2.0, 4.0, 8.0];
/// Grid of the held-offset path's gate, tried last: from the decisive gate of §4.2 to 20σ.
pub const HELD_OFFSET_GATE_GRID: [f64; 5] = [25.0, 49.0, 100.0, 225.0, 400.0];
/// Grid of the seconds an offset must have been held beyond the decisive gate: a drift's, within
/// the 45 s a 1 m/s ramp must be paged in and the 90 s of a 0.5 m/s one.
pub const HELD_OFFSET_S_GRID: [f64; 4] = [10.0, 20.0, 30.0, 60.0];

/// The chosen test and what it achieves on the validation rows.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CriticalSelection {
    pub test: CriticalTest,
    /// Metrics of the critical rows (an episode from its escalation to its end) as alarms.
    pub metrics: Metrics,
    /// Critical onsets on attack-free rows, per sample rate: (rate in Hz, onsets, attack-free
    /// hours).
    pub false_onsets_by_rate: Vec<(u32, u64, f64)>,
}

/// Whether each row is inside a critical episode, under θ, `lifecycle` and `test`, with the
/// offset evidence of each row (`offset` empty: none). A change of trajectory key starts a new
/// trajectory; a NaN score is never positive.
pub fn critical_rows(
    rows: &[ScoredRow],
    offset: &[OffsetSignal],
    theta: f64,
    lifecycle: &Lifecycle,
    test: &CriticalTest,
) -> Vec<bool> {
    let mut critical = Vec::with_capacity(rows.len());
    fill_critical_rows(rows, offset, (theta, lifecycle, test), &mut critical);
    critical
}

fn fill_critical_rows(
    rows: &[ScoredRow],
    offset: &[OffsetSignal],
    (theta, lifecycle, test): (f64, &Lifecycle, &CriticalTest),
    critical: &mut Vec<bool>,
) {
    critical.clear();
    let mut state = AlarmLifecycle::default();
    let mut escalation = Escalation::default();
    for i in 0..rows.len() {
        let input = lifecycle_input(rows, offset, theta, i);
        let open = state.update_graded(lifecycle, Some(test), &mut escalation, &input);
        critical.push(escalation.severity(open) == Some(Severity::Critical));
    }
}

/// Chooses the critical test from [`REFERENCE_LOGIT_GRID`] × [`THRESHOLD_GRID`] × [`GATE_GRID`] ×
/// [`CRITICAL_DECISIVE_S_GRID`], then its frozen-fix path from [`FROZEN_FIX_S_GRID`] (or none), then
/// its held-jump path from [`HELD_JUMP_GATE_GRID`] × [`HELD_JUMP_S_GRID`] (or none), then its
/// held-offset path from [`HELD_OFFSET_GATE_GRID`] × [`HELD_OFFSET_S_GRID`] (or none), for the
/// warning's θ and `lifecycle`: at most `per_hour` critical
/// onsets per attack-free hour, pooled and at each sample rate with room for one; then the most
/// attack events escalated, the shortest mean delay to escalation, the best F1 of the critical rows,
/// the lowest FPR; ties go to the larger k, the larger h, the higher gate, the longer hold and the
/// longer frozen-fix hold or none, then each held path's higher gate, longer hold or none (the
/// quieter test).
pub fn choose_critical(
    rows: &[ScoredRow],
    offset: &[OffsetSignal],
    theta: f64,
    lifecycle: &Lifecycle,
    per_hour: f64,
    rules: EventRules,
) -> Result<CriticalSelection, AlarmError> {
    let budget = OperatingPointRule::WithinFalseAlarmBudget { per_hour };
    choose_critical_within(rows, offset, theta, lifecycle, budget, rules)
}

/// [`choose_critical`] with the budget's rule given. With a margin
/// ([`OperatingPointRule::WithinFalseAlarmBudgetWithMargin`]), besides the margin on its count, a
/// test is taken only if its [`sensitive_twin`] passes the same rule too: a guard band for
/// validation parts too short to see the budget's rate (a hundred hours bound nothing below about
/// 0.03 per hour). A sequential test's mean time between false alarms grows about exponentially
/// with its threshold, so a test whose twin at half the threshold is already quiet sits well
/// inside the budget rather than at the edge of what the hours can tell.
pub fn choose_critical_within(
    rows: &[ScoredRow],
    offset: &[OffsetSignal],
    theta: f64,
    lifecycle: &Lifecycle,
    budget: OperatingPointRule,
    rules: EventRules,
) -> Result<CriticalSelection, AlarmError> {
    let rate_groups: Vec<RateGroup> = metrics::rate_groups(rows);
    let mut search = Search::new(
        rows,
        offset,
        (theta, lifecycle),
        budget,
        rules,
        &rate_groups,
    );
    for test in grid() {
        search.consider(test, None);
    }
    // Decisive evidence has an enormous likelihood ratio, so a path for it must be silent on the
    // attack-free validation hours: it may add escalations, never a false onset, to the test
    // chosen so far (and, guarded, its twin none to the chosen test's twin). (Within the budget
    // alone, the search would take the lowest gate that a hundred-odd validation hours happen to
    // leave quiet, at the edge of what they can tell.) First the frozen-fix path on the chosen test.
    if let Some(chosen) = search.chosen() {
        let ceilings = search.silent_ceilings(&chosen);
        for hold in FROZEN_FIX_S_GRID {
            let test = CriticalTest {
                frozen_fix_s: Some(hold),
                ..chosen
            };
            search.consider(test, Some(&ceilings));
        }
    }
    // The held jump on the test chosen so far, likewise: by the anchors' NIS, then by the step it
    // arrived with.
    let held_jump_paths: [(&[f64], WithPath); 2] = [
        (&HELD_JUMP_GATE_GRID, |test, path| CriticalTest {
            held_jump: Some(path),
            ..test
        }),
        (&HELD_STEP_GATE_GRID, |test, path| CriticalTest {
            held_step: Some(path),
            ..test
        }),
    ];
    for (gates, with_path) in held_jump_paths {
        if let Some(chosen) = search.chosen() {
            let ceilings = search.silent_ceilings(&chosen);
            for &gate in gates {
                for hold_s in HELD_JUMP_S_GRID {
                    let test = with_path(chosen, HeldOffsetTest { gate, hold_s });
                    search.consider(test, Some(&ceilings));
                }
            }
        }
    }
    // The held-offset path (a drift's, tens of seconds) on the test chosen so far: within the
    // budget.
    if let Some(chosen) = search.chosen() {
        for gate in HELD_OFFSET_GATE_GRID {
            for hold_s in HELD_OFFSET_S_GRID {
                let test = CriticalTest {
                    held_offset: Some(HeldOffsetTest { gate, hold_s }),
                    ..chosen
                };
                search.consider(test, None);
            }
        }
    }
    let Some(test) = search.chosen() else {
        return Err(budget.over_budget_in_groups(
            search.normal_hours,
            search.fewest_onsets,
            &search.binding,
            &search.fewest_by_rate,
        ));
    };
    let critical = critical_rows(rows, offset, theta, lifecycle, &test);
    Ok(CriticalSelection {
        test,
        metrics: metrics::evaluate(rows, &critical, rules),
        false_onsets_by_rate: rate_groups
            .iter()
            .map(|g| {
                (
                    g.rate_hz,
                    g.false_alarm_onsets(rows, &critical),
                    g.normal_hours,
                )
            })
            .collect(),
    })
}

/// A test with one held path set.
type WithPath = fn(CriticalTest, HeldOffsetTest) -> CriticalTest;

/// One critical search: the validation rows under the warning's θ and lifecycle, the budget, and
/// the best test found so far.
struct Search<'a> {
    rows: &'a [ScoredRow],
    offset: &'a [OffsetSignal],
    theta: f64,
    lifecycle: &'a Lifecycle,
    budget: OperatingPointRule,
    rules: EventRules,
    /// With a margin, a test must keep its [`sensitive_twin`] within the rule too.
    guarded: bool,
    normal_hours: f64,
    /// The rates with attack-free time for at least one onset of the budget.
    binding: Vec<&'a RateGroup>,
    /// Scratch: whether each row is critical under the test being scored.
    critical: Vec<bool>,
    /// The fewest false onsets any test raised (guarded: the more of a test's and its twin's).
    fewest_onsets: u64,
    /// The same at each binding rate, for the error that names the rate no test kept within.
    fewest_by_rate: Vec<u64>,
    best: Option<(CriticalTest, Metrics)>,
}

impl<'a> Search<'a> {
    fn new(
        rows: &'a [ScoredRow],
        offset: &'a [OffsetSignal],
        (theta, lifecycle): (f64, &'a Lifecycle),
        budget: OperatingPointRule,
        rules: EventRules,
        rate_groups: &'a [RateGroup],
    ) -> Self {
        let binding: Vec<&RateGroup> = rate_groups.iter().filter(|g| budget.binds(g)).collect();
        Self {
            rows,
            offset,
            theta,
            lifecycle,
            budget,
            rules,
            guarded: matches!(
                budget,
                OperatingPointRule::WithinFalseAlarmBudgetWithMargin { .. }
            ),
            normal_hours: metrics::normal_hours(rows),
            fewest_by_rate: vec![u64::MAX; binding.len()],
            binding,
            critical: Vec::with_capacity(rows.len()),
            fewest_onsets: u64::MAX,
            best: None,
        }
    }

    fn chosen(&self) -> Option<CriticalTest> {
        self.best.as_ref().map(|(test, _)| *test)
    }

    /// The critical rows' metrics under `test`, and its false onsets per binding rate.
    fn false_onsets(&mut self, test: &CriticalTest) -> (Metrics, Vec<u64>) {
        fill_critical_rows(
            self.rows,
            self.offset,
            (self.theta, self.lifecycle, test),
            &mut self.critical,
        );
        let candidate = metrics::alarm_metrics(self.rows, &self.critical, self.rules);
        let by_rate = self
            .binding
            .iter()
            .map(|g| g.false_alarm_onsets(self.rows, &self.critical))
            .collect();
        (candidate, by_rate)
    }

    /// Whether onsets (pooled, per binding rate) keep within `ceiling` (for a decisive path: what
    /// the test chosen so far raised), or within the budget without one.
    fn within(&self, pooled: u64, by_rate: &[u64], ceiling: Option<&Onsets>) -> bool {
        match ceiling {
            None => {
                pooled as f64 <= self.budget.allowed_onsets(self.normal_hours)
                    && self.binding.iter().zip(by_rate).all(|(g, &onsets)| {
                        onsets as f64 <= self.budget.allowed_onsets(g.normal_hours)
                    })
            }
            Some((most_pooled, most_by_rate)) => {
                pooled <= *most_pooled
                    && by_rate
                        .iter()
                        .zip(most_by_rate)
                        .all(|(onsets, most)| onsets <= most)
            }
        }
    }

    /// Scores `test` and keeps it if it is within `ceilings` (the false onsets a test and its
    /// twin may have; `None`, the budget) and better than the best so far. Guarded, a test within
    /// them counts its twin's onsets towards the quietest the error reports.
    fn consider(&mut self, test: CriticalTest, ceilings: Option<&Ceilings>) {
        let (candidate, by_rate) = self.false_onsets(&test);
        let pooled = candidate.false_alarm_onsets;
        if !self.within(pooled, &by_rate, ceilings.map(|c| &c.test)) {
            self.count_quietest(pooled, &by_rate);
            return;
        }
        if self.guarded {
            let (twin, twin_by_rate) = self.false_onsets(&sensitive_twin(&test));
            let louder: Vec<u64> = by_rate
                .iter()
                .zip(&twin_by_rate)
                .map(|(test, twin)| *test.max(twin))
                .collect();
            self.count_quietest(pooled.max(twin.false_alarm_onsets), &louder);
            if !self.within(
                twin.false_alarm_onsets,
                &twin_by_rate,
                ceilings.and_then(|c| c.twin.as_ref()),
            ) {
                return;
            }
        } else {
            self.count_quietest(pooled, &by_rate);
        }
        let improves = self.best.as_ref().is_none_or(|(b_test, b_metrics)| {
            compare((&test, &candidate), (b_test, b_metrics)) == Ordering::Greater
        });
        if improves {
            self.best = Some((test, candidate));
        }
    }

    /// Keeps the fewest onsets seen, pooled and at each binding rate.
    fn count_quietest(&mut self, pooled: u64, by_rate: &[u64]) {
        self.fewest_onsets = self.fewest_onsets.min(pooled);
        for (fewest, &onsets) in self.fewest_by_rate.iter_mut().zip(by_rate) {
            *fewest = (*fewest).min(onsets);
        }
    }

    /// What a decisive path added to `chosen` may not exceed: its false onsets, and (guarded) its
    /// twin's.
    fn silent_ceilings(&mut self, chosen: &CriticalTest) -> Ceilings {
        let guarded = self.guarded;
        let mut onsets = |test: &CriticalTest| {
            let (metrics, by_rate) = self.false_onsets(test);
            (metrics.false_alarm_onsets, by_rate)
        };
        let test = onsets(chosen);
        let twin = guarded.then(|| onsets(&sensitive_twin(chosen)));
        Ceilings { test, twin }
    }
}

/// False onsets pooled and per binding rate.
type Onsets = (u64, Vec<u64>);

/// The false onsets a decisive path may add nothing to: the chosen test's, and (guarded only) its
/// twin's.
struct Ceilings {
    test: Onsets,
    twin: Option<Onsets>,
}

/// The test twice as sensitive on every path: half the accumulated evidence, half the NIS of each
/// gate, half of each hold. Its k stays (k is where evidence starts to count, not how much).
pub fn sensitive_twin(test: &CriticalTest) -> CriticalTest {
    let half = |path: HeldOffsetTest| HeldOffsetTest {
        gate: path.gate / 2.0,
        hold_s: path.hold_s / 2.0,
    };
    CriticalTest {
        reference_logit: test.reference_logit,
        threshold: test.threshold / 2.0,
        gate: test.gate / 2.0,
        decisive_s: test.decisive_s / 2.0,
        frozen_fix_s: test.frozen_fix_s.map(|hold| hold / 2.0),
        held_jump: test.held_jump.map(half),
        held_step: test.held_step.map(half),
        held_offset: test.held_offset.map(half),
    }
}

/// Every test of the grid.
fn grid() -> impl Iterator<Item = CriticalTest> {
    REFERENCE_LOGIT_GRID
        .into_iter()
        .flat_map(|reference_logit| {
            THRESHOLD_GRID.into_iter().flat_map(move |threshold| {
                GATE_GRID.into_iter().flat_map(move |gate| {
                    CRITICAL_DECISIVE_S_GRID
                        .into_iter()
                        .map(move |decisive_s| CriticalTest {
                            reference_logit,
                            threshold,
                            gate,
                            decisive_s,
                            frozen_fix_s: None,
                            held_jump: None,
                            held_step: None,
                            held_offset: None,
                        })
                })
            })
        })
}

/// The search's order: greater is better.
fn compare(a: (&CriticalTest, &Metrics), b: (&CriticalTest, &Metrics)) -> Ordering {
    let ((a_test, a_metrics), (b_test, b_metrics)) = (a, b);
    a_metrics
        .detected_events
        .cmp(&b_metrics.detected_events)
        .then(compare_mean_delay(
            a_metrics.mean_delay_s,
            b_metrics.mean_delay_s,
        ))
        .then(a_metrics.f1.total_cmp(&b_metrics.f1))
        .then(b_metrics.fpr.total_cmp(&a_metrics.fpr))
        .then(a_test.reference_logit.total_cmp(&b_test.reference_logit))
        .then(a_test.threshold.total_cmp(&b_test.threshold))
        .then(a_test.gate.total_cmp(&b_test.gate))
        .then(a_test.decisive_s.total_cmp(&b_test.decisive_s))
        .then(frozen_fix_hold(a_test).total_cmp(&frozen_fix_hold(b_test)))
        .then(compare_quietness(a_test.held_jump, b_test.held_jump))
        .then(compare_quietness(a_test.held_step, b_test.held_step))
        .then(compare_quietness(a_test.held_offset, b_test.held_offset))
}

/// The frozen-fix path's hold, infinite without the path (the quietest).
fn frozen_fix_hold(test: &CriticalTest) -> f64 {
    test.frozen_fix_s.unwrap_or(f64::INFINITY)
}

/// A held path's quietness: a higher gate is quieter, then a longer hold; no path is the quietest.
fn compare_quietness(a: Option<HeldOffsetTest>, b: Option<HeldOffsetTest>) -> Ordering {
    let order = |path: Option<HeldOffsetTest>| {
        path.map_or((f64::INFINITY, f64::INFINITY), |p| (p.gate, p.hold_s))
    };
    let (a, b) = (order(a), order(b));
    a.0.total_cmp(&b.0).then(a.1.total_cmp(&b.1))
}

#[cfg(test)]
mod tests;
