//! The alarm rules' tests: persistence on hand-built rows, and the operating-point searches (F1, their
//! tie-breaks, the false-alarm budget per rate and its margin) on rows whose best point is known.

use super::*;
use crate::metrics::Pace;

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
    let mut rows = one_trajectory(&[(0, 0.7), (0, 0.6), (0, 0.2), (0, 0.9), (0, 0.9), (0, 0.9)]);
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
    let recomputed = metrics::try_evaluate(&rows, &alarms, EventRules::Spec).expect("valid rows");
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
    let free = choose_operating_point(&rows, &theta_grid(), N_P_GRID, EventRules::Spec, BEST_F1)
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

/// One valid row of `trajectory`.
fn valid_row(trajectory: u64, time_s: f64, label: bool, score: f64) -> ScoredRow {
    ScoredRow {
        trajectory,
        time_s,
        valid: true,
        label,
        score,
    }
}

#[test]
fn the_budget_holds_at_every_sample_rate_not_only_pooled() {
    // Trajectory 0 at 1 Hz: two attack-free hours, then a 60 s attack scored 0.85.
    // Trajectory 1 at 10 Hz: just over an attack-free hour (a rate with room for one false
    // alarm) with two 20 s bursts scored 0.9 (longer than any T_on). Pooled, two
    // false alarms in three hours would be within 1/h and buy the detection (θ ≤ 0.85); at
    // 10 Hz they are two in one hour, so only a θ above the bursts is within the budget.
    let mut rows: Vec<ScoredRow> = (0..7260)
        .map(|i| {
            let attacked = i >= 7200;
            valid_row(0, f64::from(i), attacked, if attacked { 0.85 } else { 0.0 })
        })
        .collect();
    rows.extend((0..36_100).map(|i| {
        let t = f64::from(i) / 10.0;
        let burst = (1000.0..1020.0).contains(&t) || (2000.0..2020.0).contains(&t);
        valid_row(1, t, false, if burst { 0.9 } else { 0.0 })
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
        &[],
        &theta_grid(),
        EventRules::Spec,
        OperatingPointRule::WithinFalseAlarmBudget { per_hour: 1.0 },
    )
    .expect("a point within the budget at both rates");
    assert!(chosen.point.theta > 0.9, "{chosen:?}");
    assert_eq!(chosen.metrics.false_alarm_onsets, 0);
    assert_eq!(chosen.metrics.detected_events, 0);
}

/// Two 1 Hz trajectories and their onboard speeds: in town (8 m/s) ten attack-free hours, then a
/// 60 s attack scored 0.85; on the open road (20 m/s) two attack-free hours with 20 s bursts scored
/// 0.9 starting at `bursts_s`.
fn town_and_open_road(bursts_s: &[f64]) -> (Vec<ScoredRow>, Vec<f64>) {
    let town_s = 36_000;
    let mut rows: Vec<ScoredRow> = (0..town_s + 60)
        .map(|i| {
            let attacked = i >= town_s;
            valid_row(0, f64::from(i), attacked, if attacked { 0.85 } else { 0.0 })
        })
        .collect();
    rows.extend((0..7201).map(|i| {
        let t = f64::from(i);
        let burst = bursts_s
            .iter()
            .any(|start| (*start..start + 20.0).contains(&t));
        valid_row(1, t, false, if burst { 0.9 } else { 0.0 })
    }));
    let speeds = rows
        .iter()
        .map(|r| if r.trajectory == 0 { 8.0 } else { 20.0 })
        .collect();
    (rows, speeds)
}

#[test]
fn the_budget_holds_on_open_roads_not_only_at_the_rate() {
    // Both trajectories at 1 Hz. Trajectory 0 in town (8 m/s): ten attack-free hours, then a 60 s
    // attack scored 0.85. Trajectory 1 on the open road (20 m/s): two attack-free hours with three
    // 20 s bursts scored 0.9. Pooled and at 1 Hz, three false alarms in twelve hours buy the
    // detection (θ ≤ 0.85); on the open road they are three in two hours, so with the speeds only a
    // θ above the bursts is within the budget.
    let (rows, speeds) = town_and_open_road(&[1000.0, 3000.0, 5000.0]);
    let groups = metrics::rate_and_pace_groups(&rows, &speeds);
    let summary: Vec<(u32, Option<Pace>, usize)> = groups
        .iter()
        .map(|g| (g.rate_hz, g.pace, g.trajectories.len()))
        .collect();
    assert_eq!(
        summary,
        vec![
            (1, None, 2),
            (1, Some(Pace::Town), 1),
            (1, Some(Pace::OpenRoad), 1)
        ]
    );
    let offset = vec![OffsetSignal::default(); rows.len()];
    let budget = OperatingPointRule::WithinFalseAlarmBudget { per_hour: 1.0 };
    let search = |speeds: &[f64]| {
        choose_lifecycle(
            &rows,
            &offset,
            speeds,
            &theta_grid(),
            EventRules::Spec,
            budget,
        )
        .expect("a point within the budget")
    };
    let pooled = search(&[]);
    assert!(pooled.point.theta <= 0.85, "{pooled:?}");
    assert_eq!(pooled.metrics.detected_events, 1);
    assert_eq!(pooled.metrics.false_alarm_onsets, 3);
    let by_pace = search(&speeds);
    assert!(by_pace.point.theta > 0.9, "{by_pace:?}");
    assert_eq!(by_pace.metrics.false_alarm_onsets, 0);
    assert_eq!(by_pace.metrics.detected_events, 0);

    // With no θ above the bursts, the pooled budget still holds (3 of 12 allowed) and the error
    // names the drives that fail it on their own.
    let thetas: Vec<f64> = theta_grid().into_iter().filter(|t| *t <= 0.85).collect();
    let error = choose_lifecycle(&rows, &offset, &speeds, &thetas, EventRules::Spec, budget)
        .expect_err("every θ alarms on the bursts");
    assert_eq!(
        error.to_string(),
        "no operating point stays within 1 false alarms per hour on 1 Hz open-road drives \
         (2.00 attack-free hours allow at most 2 false-alarm onsets; the quietest point raised 3 \
         there)"
    );
}

#[test]
fn the_margin_holds_at_each_rate_and_the_plain_budget_at_each_pace() {
    // At 1 Hz: a town trajectory of ten attack-free hours, then a 60 s attack scored 0.85, and an
    // open-road one of two attack-free hours with two 20 s bursts scored 0.9. Two onsets in twelve
    // hours keep the margin at the rate (12 − √12 = 8.5) and the plain budget on the open road
    // (2 in 2 hours); with the margin there too (2 − √2 = 0.6) no θ that detects would be taken.
    let (rows, speeds) = town_and_open_road(&[1000.0, 5000.0]);
    let rule = OperatingPointRule::WithinFalseAlarmBudgetWithMargin { per_hour: 1.0 };
    let groups = metrics::rate_and_pace_groups(&rows, &speeds);
    let allowed: Vec<f64> = groups
        .iter()
        .map(|g| (rule.allowed_onsets_in(g) * 100.0).round() / 100.0)
        .collect();
    assert_eq!(allowed, vec![8.54, 10.0, 2.0]);
    let offset = vec![OffsetSignal::default(); rows.len()];
    let chosen = choose_lifecycle(
        &rows,
        &offset,
        &speeds,
        &theta_grid(),
        EventRules::Spec,
        rule,
    )
    .expect("a point within the margin at the rate");
    assert!(chosen.point.theta <= 0.85, "{chosen:?}");
    assert_eq!(chosen.metrics.detected_events, 1);
    assert_eq!(chosen.metrics.false_alarm_onsets, 2);
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
    assert!(
        choose_lifecycle(&rows, &offset, &[], &theta_grid(), EventRules::Spec, budget).is_err()
    );
    let chosen = choose_lifecycle(
        &rows,
        &offset,
        &[],
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
            &[],
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
        &[],
        &theta_grid()[..10],
        EventRules::Spec,
        OperatingPointRule::WithinFalseAlarmBudgetWithMargin { per_hour: 1.0 },
    )
    .expect_err("θ ≤ 0.5 only");
    assert_eq!(
        error.to_string(),
        "no operating point stays within 1 false alarms per hour on all drives (11.00 \
         attack-free hours allow at most 7 false-alarm onsets; the quietest point raised 10 \
         there)"
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
