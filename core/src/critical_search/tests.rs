//! The critical search's tests: which test and which paths it chooses on hand-built rows whose
//! best test is known, and the guard band's twin.

use super::*;

const LIFECYCLE: Lifecycle = Lifecycle {
    on_s: 2.0,
    off_s: 5.0,
    decisive_s: 2.0,
};

fn logistic(logit: f64) -> f64 {
    1.0 / (1.0 + (-logit).exp())
}

/// One trajectory of `seconds` at 1 Hz with p̂ = logistic(`logit(t)`), labelled attacked per
/// `attacked(t)`.
fn trajectory(
    key: u64,
    seconds: u32,
    logit: impl Fn(f64) -> f64,
    attacked: impl Fn(f64) -> bool,
) -> Vec<ScoredRow> {
    (0..seconds)
        .map(f64::from)
        .map(|t| ScoredRow {
            trajectory: key,
            time_s: t,
            valid: true,
            label: attacked(t),
            score: logistic(logit(t)),
        })
        .collect()
}

/// Ten attacked trajectories of 300 s whose attack begins at `onset`, p̂ weak (logit 2.5) from
/// then and quiet before; `signal` gives each row's offset evidence from the seconds since the
/// onset (`None` before it).
fn weak_attacks(
    onset: f64,
    signal: impl Fn(Option<f64>) -> OffsetSignal,
) -> (Vec<ScoredRow>, Vec<OffsetSignal>) {
    let mut rows = Vec::new();
    let mut offset = Vec::new();
    for key in 0..10 {
        let attack = trajectory(
            key,
            300,
            |t| if t >= onset { 2.5 } else { -6.0 },
            |t| t >= onset,
        );
        offset.extend(
            attack
                .iter()
                .map(|row| signal((row.time_s >= onset).then_some(row.time_s - onset))),
        );
        rows.extend(attack);
    }
    (rows, offset)
}

#[test]
fn the_chosen_test_escalates_attacks_and_keeps_clean_hours_within_the_budget() {
    // Attacks: p̂ at logit 6 for 60 s. Clean hours: a false alarm every ten minutes at logit
    // 3 for 20 s, which a quiet test never escalates, and one at logit 6 for 4 s per hour.
    let mut rows = Vec::new();
    for key in 0..10 {
        rows.extend(trajectory(
            key,
            300,
            |t| {
                if (100.0..160.0).contains(&t) {
                    6.0
                } else {
                    -6.0
                }
            },
            |t| (100.0..160.0).contains(&t),
        ));
    }
    for key in 100..103 {
        rows.extend(trajectory(
            key,
            3600,
            |t| {
                if t % 600.0 >= 300.0 && t % 600.0 < 320.0 {
                    3.0
                } else if (1000.0..1004.0).contains(&t) {
                    6.0
                } else {
                    -6.0
                }
            },
            |_| false,
        ));
    }
    // A budget of 1 per hour allows the three strong blips; 0.01 per hour allows none.
    let offset = Vec::new();
    let loose =
        choose_critical(&rows, &offset, 0.8, &LIFECYCLE, 1.0, EventRules::Spec).expect("a test");
    let strict =
        choose_critical(&rows, &offset, 0.8, &LIFECYCLE, 0.01, EventRules::Spec).expect("a test");
    for selection in [&loose, &strict] {
        assert_eq!(selection.metrics.detected_events, 10, "{selection:?}");
    }
    assert!(loose.metrics.false_alarm_onsets <= 3, "{loose:?}");
    assert_eq!(strict.metrics.false_alarm_onsets, 0, "{strict:?}");
    // The strict test waits for more than four seconds of logit 6 above its k.
    let strict_rows = critical_rows(&rows, &offset, 0.8, &LIFECYCLE, &strict.test);
    let clean_start = 10 * 300;
    assert!(!strict_rows[clean_start..].iter().any(|&c| c));
    assert!(
        strict.metrics.mean_delay_s.expect("detected")
            >= loose.metrics.mean_delay_s.expect("detected")
    );
    let by_rate: Vec<(u32, u64)> = strict
        .false_onsets_by_rate
        .iter()
        .map(|&(rate, onsets, _)| (rate, onsets))
        .collect();
    assert_eq!(by_rate, vec![(1, 0)]);
}

#[test]
fn a_frozen_fix_path_is_added_when_it_escalates_more_within_the_budget() {
    // Attacks: a fix frozen from 100 s on a moving vehicle while p̂ stays weak (logit 2.5) and the
    // NIS below every gate;
    // clean hours: blips at logit 3 for 20 s every ten minutes, so no k that escalates the
    // attacks on p̂ keeps the clean hours quiet.
    let (mut rows, mut offset) = weak_attacks(100.0, |held| OffsetSignal {
        held_s: held,
        displaced: held.is_some(),
        anchored: true,
        nis: if held.is_some() { 20.0 } else { 0.0 },
        anchors_age_s: 3600.0,
        offset_m: [0.0, 0.0],
        frozen_fix_s: held,
        held_jump_s: None,
        held_step_nis: 0.0,
        reacquiring: false,
        disputed: false,
    });
    for key in 100..103 {
        let clean = trajectory(
            key,
            3600,
            |t| {
                if t % 600.0 >= 300.0 && t % 600.0 < 320.0 {
                    3.0
                } else {
                    -6.0
                }
            },
            |_| false,
        );
        offset.extend(clean.iter().map(|_| OffsetSignal {
            anchored: true,
            ..OffsetSignal::default()
        }));
        rows.extend(clean);
    }
    let chosen =
        choose_critical(&rows, &offset, 0.8, &LIFECYCLE, 0.01, EventRules::Spec).expect("a test");
    assert_eq!(chosen.metrics.detected_events, 10, "{chosen:?}");
    assert_eq!(chosen.metrics.false_alarm_onsets, 0, "{chosen:?}");
    assert!(
        chosen.test.frozen_fix_s.is_some_and(|hold| hold <= 2.0),
        "{:?}",
        chosen.test
    );
    // Without frozen fixes in the data the path adds nothing, and the quieter test (none) wins.
    let plain: Vec<OffsetSignal> = offset
        .iter()
        .map(|o| OffsetSignal {
            frozen_fix_s: None,
            ..*o
        })
        .collect();
    let without =
        choose_critical(&rows, &plain, 0.8, &LIFECYCLE, 0.01, EventRules::Spec).expect("a test");
    assert_eq!(without.test.frozen_fix_s, None, "{:?}", without.test);
}

#[test]
fn a_held_jump_path_that_fires_once_on_clean_hours_is_declined_even_within_the_budget() {
    // Attacks: a jump at 100 s held with a NIS of 60. Clean hours: one honest jump (a
    // reflection a receiver latched) held with the same NIS for 20 s, p̂ quiet. A budget of
    // one per hour would allow that one onset; decisive evidence must be silent instead.
    let jump_at = 100.0;
    let signal = |held: Option<f64>, jump: bool| OffsetSignal {
        held_s: held,
        displaced: held.is_some(),
        anchored: true,
        nis: if held.is_some() { 60.0 } else { 0.0 },
        anchors_age_s: 3600.0,
        offset_m: [0.0, 0.0],
        frozen_fix_s: None,
        held_jump_s: held.filter(|_| jump),
        held_step_nis: 0.0,
        reacquiring: false,
        disputed: false,
    };
    let (mut rows, mut offset) = weak_attacks(jump_at, |held| signal(held, true));
    // Besides, every ten minutes an offset that builds up to the same NIS for 20 s (dead
    // reckoning), so that no plain gate escalates the jumps within the budget.
    let honest = |t: f64| (1000.0..1020.0).contains(&t).then_some(t - 1000.0);
    let built_up = |t: f64| (t % 600.0 >= 300.0 && t % 600.0 < 320.0).then_some(t % 600.0 - 300.0);
    for key in 100..103 {
        let clean = trajectory(key, 3600, |_| -6.0, |_| false);
        offset.extend(
            clean
                .iter()
                .map(|row| match honest(row.time_s).filter(|_| key == 100) {
                    Some(held) => signal(Some(held), true),
                    None => signal(built_up(row.time_s), false),
                }),
        );
        rows.extend(clean);
    }
    let chosen =
        choose_critical(&rows, &offset, 0.8, &LIFECYCLE, 1.0, EventRules::Spec).expect("a test");
    assert_eq!(chosen.test.held_jump, None, "{:?}", chosen.test);
    // The same honest jump below every gate of the grid: the path is taken.
    let quiet: Vec<OffsetSignal> = offset
        .iter()
        .zip(&rows)
        .map(|(o, row)| OffsetSignal {
            nis: if !row.label && o.held_jump_s.is_some() {
                20.0
            } else {
                o.nis
            },
            ..*o
        })
        .collect();
    let chosen =
        choose_critical(&rows, &quiet, 0.8, &LIFECYCLE, 1.0, EventRules::Spec).expect("a test");
    assert!(chosen.test.held_jump.is_some(), "{:?}", chosen.test);
}

#[test]
fn a_held_jump_path_is_added_when_it_escalates_more_within_the_budget() {
    // Attacks: a jump at 100 s, held with a NIS of 60 while p̂ stays weak (logit 2.5). Clean
    // hours: every ten minutes an offset that builds up to the same NIS for 20 s (dead
    // reckoning), so no plain gate that escalates the jumps keeps the clean hours quiet.
    let (mut rows, mut offset) = weak_attacks(100.0, |held| OffsetSignal {
        held_s: held,
        displaced: held.is_some(),
        anchored: true,
        nis: if held.is_some() { 60.0 } else { 0.0 },
        anchors_age_s: 3600.0,
        offset_m: [0.0, 0.0],
        frozen_fix_s: None,
        held_jump_s: held,
        held_step_nis: 0.0,
        reacquiring: false,
        disputed: false,
    });
    let built_up = |t: f64| (t % 600.0 >= 300.0 && t % 600.0 < 320.0).then_some(t % 600.0 - 300.0);
    for key in 100..103 {
        let clean = trajectory(
            key,
            3600,
            |t| if built_up(t).is_some() { 3.0 } else { -6.0 },
            |_| false,
        );
        offset.extend(clean.iter().map(|row| {
            let held = built_up(row.time_s);
            OffsetSignal {
                held_s: held,
                displaced: held.is_some(),
                anchored: true,
                nis: if held.is_some() { 60.0 } else { 0.0 },
                anchors_age_s: 3600.0,
                offset_m: [0.0, 0.0],
                frozen_fix_s: None,
                held_jump_s: None,
                held_step_nis: 0.0,
                reacquiring: false,
                disputed: false,
            }
        }));
        rows.extend(clean);
    }
    let chosen =
        choose_critical(&rows, &offset, 0.8, &LIFECYCLE, 0.01, EventRules::Spec).expect("a test");
    assert_eq!(chosen.metrics.detected_events, 10, "{chosen:?}");
    assert_eq!(chosen.metrics.false_alarm_onsets, 0, "{chosen:?}");
    let jump = chosen.test.held_jump.expect("a held-jump path");
    assert!(jump.gate <= 60.0 && jump.hold_s <= 8.0, "{jump:?}");
    // Of the paths that catch every jump as soon, the quietest: the highest gate below 60.
    assert_eq!(jump.gate, 49.0, "{jump:?}");
    // Without held jumps in the data the path adds nothing, and no path (the quietest) wins.
    let plain: Vec<OffsetSignal> = offset
        .iter()
        .map(|o| OffsetSignal {
            held_jump_s: None,
            reacquiring: false,
            disputed: false,
            ..*o
        })
        .collect();
    let without =
        choose_critical(&rows, &plain, 0.8, &LIFECYCLE, 0.01, EventRules::Spec).expect("a test");
    assert_eq!(without.test.held_jump, None, "{:?}", without.test);
}

#[test]
fn a_held_step_path_is_added_at_the_quietest_gate_that_catches_every_jump() {
    // Attacks: a jump at 100 s that arrived with a step NIS of 150, held while the anchors'
    // NIS (levels at their bound) stays at 20 and p̂ weak. Clean hours: every ten minutes a
    // receiver's own step of NIS 60, held 20 s, with the same anchors' NIS.
    let signal = |held: Option<f64>, arrival: f64| OffsetSignal {
        held_s: held,
        displaced: held.is_some(),
        anchored: true,
        nis: if held.is_some() { 20.0 } else { 0.0 },
        anchors_age_s: 3600.0,
        offset_m: [0.0, 0.0],
        frozen_fix_s: None,
        held_jump_s: held,
        held_step_nis: if held.is_some() { arrival } else { 0.0 },
        reacquiring: false,
        disputed: false,
    };
    let (mut rows, mut offset) = weak_attacks(100.0, |held| signal(held, 150.0));
    let honest = |t: f64| (t % 600.0 >= 300.0 && t % 600.0 < 320.0).then_some(t % 600.0 - 300.0);
    for key in 100..103 {
        let clean = trajectory(key, 3600, |_| -6.0, |_| false);
        offset.extend(clean.iter().map(|row| signal(honest(row.time_s), 60.0)));
        rows.extend(clean);
    }
    let chosen =
        choose_critical(&rows, &offset, 0.8, &LIFECYCLE, 0.01, EventRules::Spec).expect("a test");
    assert_eq!(chosen.metrics.detected_events, 10, "{chosen:?}");
    assert_eq!(chosen.metrics.false_alarm_onsets, 0, "{chosen:?}");
    assert_eq!(chosen.test.held_jump, None, "{:?}", chosen.test);
    let step = chosen.test.held_step.expect("a held-step path");
    // 49 pages on the receiver's own steps; of the gates that catch every jump as soon, the
    // highest below 150.
    assert_eq!((step.gate, step.hold_s), (144.0, 1.0), "{step:?}");
}

#[test]
fn with_the_margin_a_test_is_taken_only_if_its_twice_as_sensitive_twin_is_quiet_too() {
    // Attacks: p̂ at logit 6 for 90 s. Clean hours: once an hour, a 15 s blip at logit 6. The
    // budget alone takes the quickest test the blips leave quiet; with the margin its twin (half
    // the threshold) must leave them quiet too.
    let mut rows = Vec::new();
    for key in 0..10 {
        let attacked = |t: f64| (100.0..190.0).contains(&t);
        rows.extend(trajectory(
            key,
            300,
            |t| if attacked(t) { 6.0 } else { -6.0 },
            attacked,
        ));
    }
    for key in 100..103 {
        let blip = |t: f64| (1800.0..1815.0).contains(&t);
        rows.extend(trajectory(
            key,
            3600,
            |t| if blip(t) { 6.0 } else { -6.0 },
            |_| false,
        ));
    }
    let search = |budget| {
        choose_critical_within(&rows, &[], 0.8, &LIFECYCLE, budget, EventRules::Spec)
            .expect("a test")
    };
    let plain = search(OperatingPointRule::WithinFalseAlarmBudget { per_hour: 0.01 });
    let guarded = search(OperatingPointRule::WithinFalseAlarmBudgetWithMargin { per_hour: 0.01 });
    let clean_start = 10 * 300;
    let clean_onsets = |test: &CriticalTest| {
        let critical = critical_rows(&rows, &[], 0.8, &LIFECYCLE, test);
        critical[clean_start..].iter().filter(|&&c| c).count()
    };
    for selection in [&plain, &guarded] {
        assert_eq!(selection.metrics.detected_events, 10, "{selection:?}");
        assert_eq!(clean_onsets(&selection.test), 0, "{selection:?}");
    }
    assert!(clean_onsets(&sensitive_twin(&plain.test)) > 0, "{plain:?}");
    assert_eq!(
        clean_onsets(&sensitive_twin(&guarded.test)),
        0,
        "{guarded:?}"
    );
    assert!(
        guarded.metrics.mean_delay_s.expect("detected")
            > plain.metrics.mean_delay_s.expect("detected"),
        "the guard band costs delay: {guarded:?} against {plain:?}"
    );
}

#[test]
fn with_the_margin_no_test_whose_twin_fires_is_taken_and_the_error_counts_the_twin() {
    // A clean hour with a 200 s blip at logit 8: the quietest tests (k = 5, 6 at h = 640) keep
    // quiet, their twins (h = 320) do not.
    let mut rows = trajectory(
        0,
        3600,
        |t| {
            if (1800.0..2000.0).contains(&t) {
                8.0
            } else {
                -6.0
            }
        },
        |_| false,
    );
    rows.extend(
        trajectory(1, 300, |_| 8.0, |t| t >= 100.0)
            .into_iter()
            .map(|row| ScoredRow {
                trajectory: 1,
                ..row
            }),
    );
    let search =
        |budget| choose_critical_within(&rows, &[], 0.8, &LIFECYCLE, budget, EventRules::Spec);
    let plain = search(OperatingPointRule::WithinFalseAlarmBudget { per_hour: 0.01 })
        .expect("a test at the edge");
    assert_eq!(plain.test.threshold, 640.0, "{plain:?}");
    let error = search(OperatingPointRule::WithinFalseAlarmBudgetWithMargin { per_hour: 0.01 })
        .expect_err("every quiet test's twin fires");
    assert!(
        matches!(
            error,
            AlarmError::OverBudget {
                allowed_onsets: 0,
                fewest_onsets: 1,
                ..
            }
        ),
        "{error}"
    );
}

#[test]
fn the_twin_halves_every_threshold_gate_and_hold_and_keeps_k() {
    let test = CriticalTest {
        held_step: None,
        reference_logit: 3.0,
        threshold: 80.0,
        gate: 1600.0,
        decisive_s: 2.0,
        frozen_fix_s: Some(0.0),
        held_jump: Some(HeldOffsetTest {
            gate: 400.0,
            hold_s: 2.0,
        }),
        held_offset: None,
    };
    let twin = sensitive_twin(&test);
    assert_eq!(
        twin,
        CriticalTest {
            held_step: None,
            reference_logit: 3.0,
            threshold: 40.0,
            gate: 800.0,
            decisive_s: 1.0,
            frozen_fix_s: Some(0.0),
            held_jump: Some(HeldOffsetTest {
                gate: 200.0,
                hold_s: 1.0,
            }),
            held_offset: None,
        }
    );
}

#[test]
fn no_test_within_the_budget_is_an_error() {
    // Every clean minute looks like an attack.
    let rows = trajectory(0, 3600, |_| 8.0, |_| false);
    let error = choose_critical(&rows, &[], 0.8, &LIFECYCLE, 0.01, EventRules::Spec)
        .expect_err("over budget");
    assert!(matches!(error, AlarmError::OverBudget { .. }), "{error}");
}

#[test]
fn the_error_names_the_rate_no_test_keeps_within() {
    // Ten quiet hours at 1 Hz, and an hour and a half at 10 Hz with three 400 s blips at logit 8
    // that every test escalates (the quietest accumulates 2 logits a second up to 640). Pooled,
    // three onsets in 11.5 hours are within 1 per hour; at 10 Hz they are three where 1.5 hours
    // allow one.
    let mut rows = trajectory(0, 36_000, |_| -6.0, |_| false);
    rows.extend(
        trajectory(
            1,
            54_000,
            |t| {
                let s = t / 10.0;
                if [600.0, 2400.0, 4200.0]
                    .iter()
                    .any(|start| (*start..start + 400.0).contains(&s))
                {
                    8.0
                } else {
                    -6.0
                }
            },
            |_| false,
        )
        .into_iter()
        .map(|row| ScoredRow {
            time_s: row.time_s / 10.0,
            ..row
        }),
    );
    let error = choose_critical(&rows, &[], 0.8, &LIFECYCLE, 1.0, EventRules::Spec)
        .expect_err("every test escalates the blips");
    assert_eq!(
        error.to_string(),
        "no operating point stays within 1 false alarms per hour on 10 Hz drives (1.50 \
         attack-free hours allow at most 1 false-alarm onsets; the quietest point raised 3 there)"
    );
}
