//! The offset channels' behaviour: the anchors, the held jump, the levels, the misfit and the fit.

use super::levels::early_level;
use super::misfit::{POPULATION_LOG_LEVEL, mean_log_level, misfit};
use super::params::{LEVEL_COUNT, STEP_LEVEL};
use super::*;

/// Unit GNSS noise on both anchors, no growth, no vehicle levels.
fn unit_params() -> OffsetParams {
    OffsetParams {
        noise_m2: [1.0; ANCHOR_COUNT],
        raw_growth: [0.0; ANCHOR_COUNT],
        calibrated_growth: [0.0; ANCHOR_COUNT],
        step_noise_m2: 1.0,
        vehicle_levels: false,
        rebase_on_calibration: false,
    }
}

fn step(residual: [f64; 2], delta_t: f64) -> OffsetStep {
    OffsetStep {
        residual,
        motion: [0.0, 10.0 * delta_t],
        delta_t,
        calibrated: false,
        calibration_error: [0.0; 3],
        reports_placements: false,
        leaves_held_fix: false,
        repeats_fix: false,
        velocity_change: [0.0; 2],
        theta_in_use: [0.0; 3],
    }
}

/// A tracker whose anchors are trusted: TRUST_S seconds of agreement after the first fix.
fn trusted(params: &OffsetParams) -> OffsetTracker {
    let mut tracker = OffsetTracker::new(params);
    for _ in 0..(TRUST_S as usize) {
        tracker.push(&step([0.0; 2], 1.0));
    }
    tracker
}

fn keep(delta_t: f64, k: usize) -> f64 {
    (-delta_t / FOLLOW_S[k]).exp()
}

#[test]
fn an_anchor_follows_a_constant_dead_reckoning_error_to_its_steady_state() {
    // r = 0.1 m east every second: the fast anchor's o → 0.1·keep/(1 − keep) = 0.951 m, the
    // geometric sum, and it never stops following. The slow one would settle at 11.95 m: with
    // unit noise it stops following when its offset passes 4 m (NIS 16) and then keeps it.
    let mut tracker = OffsetTracker::new(&unit_params());
    let mut last = OffsetEvidence::EMPTY;
    let mut slow_froze_at = None;
    for i in 0..2000 {
        last = tracker.push(&step([0.1, 0.0], 1.0));
        if last.nis[1] >= FOLLOW_GATE && slow_froze_at.is_none() {
            slow_froze_at = Some(i);
        }
    }
    let a = keep(1.0, 0);
    assert!(
        (last.offset_norm_m[0] - 0.1 * a / (1.0 - a)).abs() < 1e-9,
        "{last:?}"
    );
    assert!(last.nis[0] < FOLLOW_GATE);
    // Σ 0.1·keep^j reaches 4 m after 50 rows (0.1·keep·(1 − keep^n)/(1 − keep) ≥ 4).
    let b = keep(1.0, 1);
    let rows = ((1.0 - 4.0 * (1.0 - b) / (0.1 * b)).ln() / b.ln()).ceil() as usize;
    assert_eq!(slow_froze_at, Some(rows - 1));
    assert!(last.frozen);
}

#[test]
fn a_jump_freezes_the_anchors_and_is_held_while_a_spike_comes_back() {
    let mut tracker = OffsetTracker::new(&unit_params());
    for _ in 0..30 {
        tracker.push(&step([0.0; 2], 1.0));
    }
    // A 50 m jump north: a one-row outlier, so every anchor stops at the last trusted fix
    // before moving (o = 0 there) and holds the whole 50 m.
    let first = tracker.push(&step([0.0, 50.0], 1.0));
    assert!(first.frozen && first.arrived_by_step);
    assert_eq!(first.held_s, 0.0);
    assert_eq!(first.offset_m, [0.0, 50.0]);
    let mut last = first;
    for _ in 0..5 {
        last = tracker.push(&step([0.0; 2], 1.0));
    }
    assert_eq!(last.held_s, 5.0);
    assert_eq!(last.offset_m, [0.0, 50.0]);
    // Unit noise, no growth: the whole offset against R = 1 (the step test is below it).
    assert_eq!(last.nis, [2500.0, 2500.0]);

    // A 30 m spike on one row out and back: held for 0 s, and back to 0 m.
    let mut tracker = OffsetTracker::new(&unit_params());
    for _ in 0..30 {
        tracker.push(&step([0.0; 2], 1.0));
    }
    let out = tracker.push(&step([30.0, 0.0], 1.0));
    assert_eq!(out.held_s, 0.0);
    // The anchors' and the track's age at a 20 m jump `rows` rows after a fix that came back
    // `back_m` short of the spike.
    let ages_at_jump_after = |back_m: f64, rows: usize| {
        let mut tracker = tracker.clone();
        let back = tracker.push(&step([-back_m, 0.0], 1.0));
        // Back to within a quarter of the held offset: the fix is where the motion puts it, and
        // the anchors are placed there again.
        assert_eq!((back.nis, back.held_s), ([0.0, 0.0], 0.0));
        assert!(!back.frozen && back.anchor_age_s == 0.0, "{back:?}");
        for _ in 0..rows {
            tracker.push(&step([0.0; 2], 1.0));
        }
        let jump = tracker.push(&step([0.0, 20.0], 1.0));
        assert!(
            jump.arrived_by_step && jump.held_step_m.is_some(),
            "{jump:?}"
        );
        (jump.anchor_age_s, jump.track_age_s)
    };
    // Back where the fix before the spike was: the track goes on at once, and a jump 3 s later
    // comes from the track of the 31 rows before the return.
    assert_eq!(ages_at_jump_after(30.0, 2), (3.0, 34.0));
    // Back to 6 m off (NIS 36): within a quarter of the spike, but a multipath burst's return
    // may be metres off. The anchors it places start a track of their own, and a jump 3 s
    // later comes from a track 3 s old; after TRUST_S of agreement they are back on the track
    // they returned to.
    assert_eq!(ages_at_jump_after(24.0, 2), (3.0, 3.0));
    assert_eq!(ages_at_jump_after(24.0, 5), (6.0, 37.0));
    // Back exactly, but after the offset was held for 2 s: not a one-row spike, and its anchors
    // start a track of their own too.
    let mut held = tracker.clone();
    for _ in 0..2 {
        held.push(&step([0.0; 2], 1.0));
    }
    let back = held.push(&step([-30.0, 0.0], 1.0));
    assert_eq!((back.nis, back.anchor_age_s), ([0.0, 0.0], 0.0));
    for _ in 0..2 {
        held.push(&step([0.0; 2], 1.0));
    }
    let jump = held.push(&step([0.0, 20.0], 1.0));
    assert_eq!((jump.anchor_age_s, jump.track_age_s), (3.0, 3.0));
    // The share of time beyond the follow gate: one row of the last 10 s.
    let share_after_out = 1.0 - keep(1.0, 0);
    assert!((out.share[0] - share_after_out).abs() < 1e-12);
}

#[test]
fn after_a_freeze_the_change_is_tested_against_one_rows_noise() {
    // R = 100 m² hides a 20 m offset (NIS 4), but a 20 m step against one row's noise of
    // 1 m² is an outlier: the anchors stop, and the change since (20 m) is tested against
    // 1·(1 + t/2 s): NIS 400/1.5 on the step row, 400/2 a second later.
    let params = OffsetParams {
        noise_m2: [100.0; ANCHOR_COUNT],
        ..unit_params()
    };
    let mut tracker = trusted(&params);
    let jump = tracker.push(&step([20.0, 0.0], 1.0));
    assert!((jump.nis[0] - 400.0 / 1.5).abs() < 1e-9, "{jump:?}");
    let held = tracker.push(&step([0.0, 0.0], 1.0));
    assert!((held.nis[0] - 200.0).abs() < 1e-9, "{held:?}");
    assert_eq!(held.held_s, 1.0);
}

#[test]
fn a_frozen_anchor_follows_again_after_the_agreement_time() {
    // 4.5 m out (NIS 20: beyond the follow gate, not the decisive one, so no return).
    let mut tracker = trusted(&unit_params());
    tracker.push(&step([4.5, 0.0], 1.0));
    // Back: o_fast = 4.5·keep − 4.5, NIS 0.2 (agreement); the slow anchor too.
    let mut frozen_rows = 0;
    for _ in 0..10 {
        let e = tracker.push(&step(
            [-4.5 * f64::from(u8::from(frozen_rows == 0)), 0.0],
            1.0,
        ));
        if e.frozen {
            frozen_rows += 1;
        }
    }
    // Agreement from the first row back: frozen for AGREEMENT_S − 1 more rows (5 s in all).
    assert_eq!(frozen_rows, 4);
}

#[test]
fn a_held_jump_stays_displaced_after_the_anchors_lose_it_until_it_steps_back() {
    // Dead reckoning as poor as 10 % of the distance (c² = 0.01) at 10 m/s: 100 s after a
    // 20 m jump the frozen anchors' own σ is 100 m, and they follow GNSS again.
    let params = OffsetParams {
        raw_growth: [0.01; ANCHOR_COUNT],
        ..unit_params()
    };
    let jumped = |tracker: &mut OffsetTracker| {
        let first = tracker.push(&step([20.0, 0.0], 1.0));
        assert!(first.arrived_by_step && first.displaced());
        assert_eq!(first.held_step_m, Some([20.0, 0.0]));
    };
    let mut tracker = trusted(&params);
    jumped(&mut tracker);
    let mut lost_by_anchors = None;
    for row in 1..=150 {
        let e = tracker.push(&step([0.0; 2], 1.0));
        if e.max_nis() < FOLLOW_GATE && lost_by_anchors.is_none() {
            lost_by_anchors = Some(row);
        }
        assert!(e.displaced(), "row {row}: {e:?}");
        assert_eq!(e.held_step_m, Some([20.0, 0.0]));
    }
    assert!(
        lost_by_anchors.is_some_and(|row| row < 100),
        "{lost_by_anchors:?}"
    );
    // The spoofer lets go: one step back to the track ends the hold and re-anchors.
    let back = tracker.push(&step([-19.0, 0.0], 1.0));
    assert!(!back.displaced() && back.held_step_m.is_none() && back.anchor_age_s == 0.0);
    // Where the track is after 150 s of dead reckoning at 10 % is a guess: the anchors placed
    // here start a track of their own, and agreement does not resume the old one.
    for _ in 0..10 {
        tracker.push(&step([0.0; 2], 1.0));
    }
    let later = tracker.push(&step([0.0; 2], 1.0));
    assert_eq!((later.anchor_age_s, later.track_age_s), (11.0, 11.0));

    // The row after the jump on which the hold ends, with `residual` every second.
    let hold_ends = |residual: [f64; 2]| {
        let mut tracker = trusted(&params);
        jumped(&mut tracker);
        (1..=700).find(|_| tracker.push(&step(residual, 1.0)).held_step_m.is_none())
    };
    // Walked back 0.5 m per second: it ends on the row it is nearer the track (10 m).
    assert_eq!(hold_ends([-0.5, 0.0]), Some(20));
    // Never let go: held for MAX_STEP_HOLD_S, then the anchors alone decide.
    assert_eq!(hold_ends([0.0; 2]), Some(MAX_STEP_HOLD_S as usize + 1));
}

#[test]
fn after_an_outage_a_plausible_reappearance_re_anchors_and_a_far_one_is_evidence() {
    // After a 30 s gap the hidden motion is ½·0.5·30² = 225 m per axis: 100 m off is inside
    // it (a fresh anchor, nothing displaced), 5 km is not (NIS 25e6 / (1 + 225²) = 494).
    let gap = 30.0;
    let hidden = 0.5 * GAP_ACCELERATION_MPS2 * gap * gap;
    let mut tracker = trusted(&unit_params());
    let inside = tracker.push(&step([100.0, 0.0], gap));
    assert_eq!(inside.nis, [0.0, 0.0]);
    assert_eq!(inside.anchor_age_s, 0.0);
    assert!(!inside.displaced());
    let mut tracker = trusted(&unit_params());
    let beyond = tracker.push(&step([5000.0, 0.0], gap));
    let expected = 5000.0_f64.powi(2) / (1.0 + hidden * hidden);
    assert!((beyond.nis[1] - expected).abs() < 1e-6, "{beyond:?}");
    assert!(beyond.max_nis() > DECISIVE_GATE);
    // Without the gap, the same 100 m is far beyond the gate.
    let mut tracker = trusted(&unit_params());
    assert!(tracker.push(&step([100.0, 0.0], 1.0)).max_nis() > DECISIVE_GATE);
}

#[test]
fn the_first_fix_after_an_outage_is_trusted_only_after_agreement() {
    // The fix reappears inside what a 10 s gap allows, but 15 m off (a reflection as the
    // receiver reacquires); the next fix is back on the track. The anchors were placed on the
    // reappearance: the disagreement places them again instead of holding a 15 m jump.
    let mut tracker = trusted(&unit_params());
    tracker.push(&step([15.0, 0.0], 10.0));
    let back = tracker.push(&step([-15.0, 0.0], 1.0));
    assert_eq!((back.nis, back.anchor_age_s), ([0.0, 0.0], 0.0));
    assert!(!back.displaced());
    // The fix moved 15 m unlike the vehicle, more than a receiver converging closes: the anchors
    // placed again carry none of the reacquisition's allowance, and after TRUST_S of agreement
    // the same 15 m is a jump, NIS 15² / 1, as from a session's first anchors.
    for _ in 0..(TRUST_S as usize) {
        assert!(!tracker.push(&step([0.0; 2], 1.0)).displaced());
    }
    let jump = tracker.push(&step([-15.0, 0.0], 1.0));
    assert_eq!(jump.nis, [225.0, 225.0]);
    assert!(jump.arrived_by_step);
}

/// A trusted tracker through a 10 s outage, whose receiver reappears `first_m` east of the track
/// and converges back to it as exp(−t/τ) over 1 s rows; returns each row's channels.
fn reacquiring(first_m: f64, tau_s: f64, rows: usize) -> (OffsetTracker, Vec<OffsetEvidence>) {
    let mut tracker = trusted(&unit_params());
    tracker.push(&step([first_m, 0.0], 10.0));
    let error = |t: f64| first_m * (-t / tau_s).exp();
    let found = (1..=rows)
        .map(|t| {
            let t = t as f64;
            tracker.push(&step([error(t) - error(t - 1.0), 0.0], 1.0))
        })
        .collect();
    (tracker, found)
}

#[test]
fn a_receiver_reconverging_after_an_outage_is_not_held_as_an_offset() {
    // 8 m off on reappearing, back on the track with τ = 5 s: the slow anchor, placed on the
    // first fix, ends up holding most of those 8 m (GNSS noise alone, 1 m per axis, would make
    // that a NIS of about 50, a decisive offset). Its placement's uncertainty (3 m per axis,
    // forgotten as it follows) keeps it below the follow gate throughout.
    let (_, rows) = reacquiring(8.0, 5.0, 60);
    let most_m = rows.iter().map(|r| r.offset_norm_m[1]).fold(0.0, f64::max);
    assert!(most_m > 5.0, "the slow anchor holds {most_m} m");
    for (t, row) in rows.iter().enumerate() {
        assert!(
            row.max_nis() < FOLLOW_GATE && !row.displaced(),
            "{t} s: {row:?}"
        );
    }
    // The first row tests what each anchor kept of 8·(1 − e^(−1/5)) m against the GNSS noise and
    // the receiver's 9 m², which no anchor has begun to forget at the row's start.
    let moved = 8.0 * (1.0 - (-1.0_f64 / 5.0).exp());
    for k in 0..ANCHOR_COUNT {
        let kept = keep(1.0, k);
        let expected = (kept * moved).powi(2) / (1.0 + REACQUISITION_M2);
        assert!(
            (rows[0].nis[k] - expected).abs() < 1e-9,
            "{k}: {:?}",
            rows[0]
        );
    }
}

#[test]
fn a_receiver_converging_by_a_large_step_keeps_its_allowance() {
    // 12 m off on reappearing, back with τ = 1.5 s: its first step, 12·(1 − e^(−2/3)) = 5.84 m,
    // is a one-row NIS of 34 against the GNSS noise alone, an outlier that would place the
    // untrusted anchors again without the receiver's 9 m² and leave them to hold the 6.16 m still
    // to converge (a NIS of up to 38). Tested with the allowance, as every other test is, the
    // step is 3.4 and the whole convergence stays below the follow gate.
    let (_, rows) = reacquiring(12.0, 1.5, 60);
    assert!(
        rows.iter().all(|row| row.anchor_age_s > 0.0),
        "placed again"
    );
    for (t, row) in rows.iter().enumerate() {
        assert!(
            row.max_nis() < FOLLOW_GATE && !row.displaced(),
            "{t} s: {row:?}"
        );
    }
}

#[test]
fn a_jump_from_anchors_placed_on_a_reacquired_fix_is_still_decisive() {
    // 10 s after reappearing 3 m off, a 20 m jump: beyond the decisive gate from anchors whose
    // placement was 3 m per axis unsure.
    let (mut tracker, _) = reacquiring(3.0, 2.0, 10);
    let jump = tracker.push(&step([0.0, 20.0], 1.0));
    assert!(
        jump.max_nis() >= DECISIVE_GATE && jump.arrived_by_step,
        "{jump:?}"
    );
    // A session's first anchors carry no such uncertainty: the same 8 m build-up is held there.
    let mut tracker = trusted(&unit_params());
    let error = |t: f64| 8.0 * (-t / 5.0).exp();
    let most_nis = (1..=60)
        .map(|t| {
            let t = t as f64;
            tracker
                .push(&step([error(t) - error(t - 1.0), 0.0], 1.0))
                .max_nis()
        })
        .fold(0.0, f64::max);
    assert!(most_nis >= DECISIVE_GATE, "{most_nis}");
}

#[test]
fn until_the_fix_and_the_motion_agree_a_disagreement_places_the_anchors_again() {
    // A session whose first onboard readings are off: 30 m of disagreement on the second row
    // re-anchors there instead of being held; after TRUST_S of agreement the same step is a
    // jump.
    let mut tracker = OffsetTracker::new(&unit_params());
    let first = tracker.push(&step([30.0, 0.0], 1.0));
    assert_eq!((first.nis, first.anchor_age_s), ([0.0, 0.0], 0.0));
    // A fix that disagreed before trust starts a track of its own.
    assert_eq!(first.track_age_s, 0.0);
    for _ in 0..4 {
        assert!(!tracker.push(&step([0.0; 2], 1.0)).displaced());
    }
    let untrusted = tracker.push(&step([30.0, 0.0], 1.0));
    assert_eq!(
        untrusted.max_nis(),
        0.0,
        "4 s of agreement is not yet trust"
    );
    let mut tracker = trusted(&unit_params());
    let jump = tracker.push(&step([30.0, 0.0], 1.0));
    assert!(jump.max_nis() >= DECISIVE_GATE && jump.arrived_by_step);
}

#[test]
fn under_trust_from_information_a_row_that_places_the_anchors_again_reports_its_disagreement() {
    // A fix that moves 6 m a second unlike the vehicle from its first row never earns the
    // anchors' trust: every row disagrees and places them again. Reporting what each row found,
    // the rows show the disagreement (displaced, counted in the shares) while the anchors still
    // start again from each of them; the clock's trust reports empty channels instead.
    let informed = |residual| OffsetStep {
        reports_placements: true,
        ..step(residual, 1.0)
    };
    let (mut reporting, mut silent) = (
        OffsetTracker::new(&unit_params()),
        OffsetTracker::new(&unit_params()),
    );
    reporting.push(&informed([0.0; 2]));
    silent.push(&step([0.0; 2], 1.0));
    for row in 0..10 {
        let found = reporting.push(&informed([6.0, 0.0]));
        let empty = silent.push(&step([6.0, 0.0], 1.0));
        // One row of 6 m against unit noise (an outlier stops both anchors first): NIS 36.
        assert_eq!(
            (found.nis, found.offset_m),
            ([36.0; 2], [6.0, 0.0]),
            "{row}"
        );
        assert!(found.displaced(), "{row}: {found:?}");
        assert_eq!((empty.max_nis(), empty.share), (0.0, [0.0; 2]), "{row}");
        // The anchors were placed again: nothing is held, and the next row starts from here.
        assert!(!reporting.frozen() && found.held_s == 0.0);
        let expected = 1.0 - (-(f64::from(row) + 1.0) / SHARE_S[0]).exp();
        assert!(
            (found.share[0] - expected).abs() < 1e-12,
            "{row}: {found:?}"
        );
    }
    // Both trackers hold the same anchors: reporting changes what the rows say, not the anchors.
    let (a, b) = (
        reporting.push(&informed([0.0; 2])),
        silent.push(&step([0.0; 2], 1.0)),
    );
    assert_eq!((a.offset_m, a.nis), (b.offset_m, b.nis));
}

#[test]
fn a_fix_that_disagrees_again_with_anchors_placed_on_it_disputes_them_until_trust_is_earned() {
    // Under trust from information: one disagreement before trust (a reflected first fix) places
    // the anchors again and is not a dispute; a second before trust is. The agreeing rows between
    // placements stay disputed, and TRUST_S of agreement ends it. The clock's trust never disputes.
    let informed = |residual| OffsetStep {
        reports_placements: true,
        ..step(residual, 1.0)
    };
    let mut tracker = OffsetTracker::new(&unit_params());
    tracker.push(&informed([0.0; 2]));
    let reflected = tracker.push(&informed([6.0, 0.0]));
    assert!(reflected.displaced() && !reflected.disputed);
    assert!(!tracker.push(&informed([0.0; 2])).disputed);
    let again = tracker.push(&informed([6.0, 0.0]));
    assert!(again.displaced() && again.disputed);
    let agreeing: Vec<_> = (0..6).map(|_| tracker.push(&informed([0.0; 2]))).collect();
    let disputed: Vec<bool> = agreeing.iter().map(|e| e.disputed).collect();
    assert_eq!(disputed, [true, true, true, true, false, false]);
    assert!(agreeing.iter().all(|e| !e.displaced()));
    // Trusted now: the same disagreement is held as an offset, not a placement.
    let held = tracker.push(&informed([6.0, 0.0]));
    assert!(held.displaced() && !held.disputed && tracker.frozen());

    let mut clock = OffsetTracker::new(&unit_params());
    for residual in [[0.0; 2], [6.0, 0.0], [0.0; 2], [6.0, 0.0], [0.0; 2]] {
        assert!(!clock.push(&step(residual, 1.0)).disputed);
    }
    // An outage's break starts a fresh track: a dispute does not carry over it.
    let mut broken = OffsetTracker::new(&unit_params());
    for residual in [[0.0; 2], [6.0, 0.0], [6.0, 0.0]] {
        broken.push(&informed(residual));
    }
    assert!(broken.push(&informed([0.0; 2])).disputed);
    broken.re_anchor();
    broken.push(&informed([0.0; 2]));
    assert!(!broken.push(&informed([0.0; 2])).disputed);
}

#[test]
fn the_uncertainty_grows_with_the_distance_carried() {
    // R = 4 m², c² = 0.01: after carrying 100 m north with no offset, a 10 m offset is
    // NIS = 100·keep² / (4 + 0.01·‖U‖²) with U the carried distance (decayed like o).
    // (One row's noise is wide, so the 10 m is no outlier and the anchors keep following.)
    let params = OffsetParams {
        noise_m2: [4.0; ANCHOR_COUNT],
        raw_growth: [0.01; ANCHOR_COUNT],
        calibrated_growth: [1e-4; ANCHOR_COUNT],
        step_noise_m2: 1e4,
        ..unit_params()
    };
    let mut tracker = OffsetTracker::new(&params);
    let e = tracker.push(&OffsetStep {
        motion: [0.0, 100.0],
        ..step([10.0, 0.0], 1.0)
    });
    for k in 0..ANCHOR_COUNT {
        let a = keep(1.0, k);
        let expected = (10.0 * a).powi(2) / (4.0 + 0.01 * (100.0 * a).powi(2));
        assert!((e.nis[k] - expected).abs() < 1e-12, "{k}: {e:?}");
        assert!((e.raw_carried_m[k] - 100.0 * a).abs() < 1e-12);
        assert_eq!(e.carried_m[k], 0.0);
    }
    // Then 100 m east with the warm calibration (c² = 0.0001): each part of U grows the
    // variance with its own c², and both are forgotten with the offset.
    let e = tracker.push(&OffsetStep {
        motion: [100.0, 0.0],
        calibrated: true,
        ..step([0.0, 0.0], 1.0)
    });
    for k in 0..ANCHOR_COUNT {
        let a = keep(1.0, k);
        let (raw, calibrated) = (100.0 * a * a, 100.0 * a);
        let expected =
            (10.0 * a * a).powi(2) / (4.0 + 0.01 * raw * raw + 1e-4 * calibrated * calibrated);
        assert!((e.nis[k] - expected).abs() < 1e-12, "{k}: {e:?}");
        assert!((e.raw_carried_m[k] - raw).abs() < 1e-12);
        assert!((e.carried_m[k] - calibrated).abs() < 1e-12);
    }
}

/// One-row residuals of a receiver with white GNSS noise of σ per axis (each the difference of
/// two such errors).
fn receiver_residuals(sigma_m: f64, seed: u64) -> impl Iterator<Item = [f64; 2]> {
    let mut rng = crate::rng::Rng::seed_from_u64(seed);
    let mut previous = [0.0; 2];
    std::iter::repeat_with(move || {
        let noise = [sigma_m * rng.normal(), sigma_m * rng.normal()];
        let residual = [noise[0] - previous[0], noise[1] - previous[1]];
        previous = noise;
        residual
    })
}

fn with_levels() -> OffsetParams {
    OffsetParams {
        vehicle_levels: true,
        ..unit_params()
    }
}

#[test]
fn the_vehicle_level_adapts_with_a_delay_and_within_bounds() {
    // A receiver 3× noisier (in σ) than the population. Its level rises towards 9, capped at
    // 4, but only from snapshots at least 120 s old.
    let mut tracker = OffsetTracker::new(&with_levels());
    let mut levels_at = Vec::new();
    for (i, residual) in receiver_residuals(3.0, 3).take(900).enumerate() {
        let e = tracker.push(&step(residual, 1.0));
        assert!(e.nis.iter().all(|n| n.is_finite()));
        if i == 100 || i == 899 {
            levels_at.push(tracker.levels_in_use);
        }
    }
    assert_eq!(levels_at[0], [LEVEL_RANGE.1; LEVEL_COUNT]);
    assert!(levels_at[1].iter().all(|&l| l > 3.0), "{levels_at:?}");
}

#[test]
fn the_early_step_level_is_an_upper_confidence_bound_within_bounds() {
    // 15 s of NIS/2 summing to 30 (mean 2): χ²₃₀'s 5 % quantile is 18.49, so 60 / 18.49.
    assert!((early_level(30.0, 15.0) - 60.0 / 18.4927).abs() < 0.01);
    // A quiet receiver (mean 0.5) is never taken below the population's level.
    assert_eq!(early_level(7.5, 15.0), 1.0);
    // Before a second of rows, and for a very noisy receiver, the upper bound.
    assert_eq!(early_level(0.0, 0.5), LEVEL_RANGE.1);
    assert_eq!(early_level(150.0, 15.0), LEVEL_RANGE.1);
}

#[test]
fn a_quiet_receiver_is_step_tested_as_one_from_its_first_minute() {
    // GNSS white noise of σ 0.5 m on unit parameters: the step level in use falls to the
    // population's within the first minute, while the anchors' levels wait for the delayed
    // snapshot.
    let mut tracker = OffsetTracker::new(&with_levels());
    for residual in receiver_residuals(0.5, 5).take(60) {
        tracker.push(&step(residual, 1.0));
    }
    assert_eq!(tracker.levels_in_use[STEP_LEVEL], 1.0);
    assert!(
        tracker.levels_in_use[..ANCHOR_COUNT]
            .iter()
            .all(|&l| l == LEVEL_RANGE.1)
    );
}

#[test]
fn a_vehicle_whose_dead_reckoning_misfits_stands_its_anchors_down_and_still_sees_a_jump() {
    // Dead reckoning off by 0.5 m/s for good (a rover whose compass is useless): the slow
    // anchor would hold 60 m against 1 m of noise, and frozen, its offset grows for good. Its
    // misfit comes from snapshots at least 120 s old, whose own rows outweigh the prior: the
    // anchors follow again within ten minutes, and a 200 m jump is still decisive on its row.
    let params = OffsetParams {
        vehicle_levels: true,
        ..unit_params()
    };
    let mut tracker = trusted(&params);
    let mut e = OffsetEvidence::EMPTY;
    for i in 0..600 {
        e = tracker.push(&step([0.5, 0.0], 1.0));
        if i == 100 {
            assert_eq!(tracker.misfit_in_use, [1.0; ANCHOR_COUNT]);
            assert!(e.max_nis() >= DECISIVE_GATE, "{e:?}");
        }
    }
    assert!(
        tracker.misfit_in_use.iter().all(|&m| m > LEVEL_RANGE.1),
        "{tracker:?}"
    );
    assert!(tracker.anchors.iter().all(|a| !a.frozen), "{tracker:?}");
    assert!(e.max_nis() < FOLLOW_GATE, "{e:?}");
    let jump = tracker.push(&step([200.5, 0.0], 1.0));
    assert!(
        jump.max_nis() >= DECISIVE_GATE && jump.arrived_by_step,
        "{jump:?}"
    );
}

#[test]
fn a_held_jump_does_not_teach_the_misfit() {
    // A 50 m jump held for ten minutes on a vehicle whose dead reckoning is perfect: the rows
    // of an offset that arrived in one step never count, so it stays held to the end.
    let params = OffsetParams {
        vehicle_levels: true,
        ..unit_params()
    };
    let mut tracker = trusted(&params);
    for _ in 0..300 {
        tracker.push(&step([0.0; 2], 1.0));
    }
    let mut e = tracker.push(&step([50.0, 0.0], 1.0));
    for _ in 0..600 {
        e = tracker.push(&step([0.0; 2], 1.0));
    }
    assert_eq!(tracker.misfit_in_use, [1.0; ANCHOR_COUNT]);
    assert!(e.held_s >= 599.0 && e.max_nis() >= DECISIVE_GATE, "{e:?}");
}

#[test]
fn the_misfit_inverts_the_mean_log_level_beyond_the_level_bound() {
    // e·E₁(1) at L = 1 by the series is the population's prior (to the series' precision).
    assert!((POPULATION_LOG_LEVEL - 1.0f64.exp() * 0.219_383_934_395_520_3).abs() < 1e-12);
    // At L = 10: e^{0.1}·E₁(0.1), E₁(0.1) = 1.822 923 958 419 39.
    let expected = 0.1f64.exp() * 1.822_923_958_419_39;
    assert!((mean_log_level(10.0) - expected).abs() < 1e-12);
    assert!((misfit(expected) - 10.0).abs() < 1e-9);
    // Within the bound (the population's own mean included) the misfit is 1; it is capped.
    assert_eq!(misfit(POPULATION_LOG_LEVEL), 1.0);
    assert_eq!(misfit(mean_log_level(3.9)), 1.0);
    assert_eq!(misfit(f64::NAN), 1.0);
    assert_eq!(misfit(100.0), MISFIT_MAX);
}

#[test]
fn the_fit_recovers_noise_and_growth_from_binned_quantiles() {
    // Ten distances, ten points each, all with ‖o‖² = 9.21·(2 + 0.01·x²): R = 2, c² = 0.01
    // (on the line, the upper envelope changes nothing).
    let mut points = Vec::new();
    for bin in 0..10 {
        let x = 50.0 * f64::from(bin);
        for _ in 0..10 {
            points.push(OffsetPoint {
                carried_m: 0.0,
                raw_carried_m: x,
                offset_m: (CHI2_2_AT_FIT_QUANTILE * (2.0 + 0.01 * x * x)).sqrt(),
            });
        }
    }
    let params = offset_params_from_points(&[points.clone(), points], 2.0).expect("enough points");
    assert_eq!(params.step_noise_m2, 2.0);
    for k in 0..ANCHOR_COUNT {
        assert!((params.noise_m2[k] - 2.0).abs() < 1e-9, "{params:?}");
        assert!((params.raw_growth[k] - 0.01).abs() < 1e-12, "{params:?}");
        assert_eq!(params.calibrated_growth[k], params.raw_growth[k]);
    }
    assert!(params.vehicle_levels);
    let few = vec![
        OffsetPoint {
            carried_m: 0.0,
            raw_carried_m: 1.0,
            offset_m: 1.0,
        };
        5
    ];
    assert!(offset_params_from_points(&[few.clone(), few], 1.0).is_err());
}

#[test]
fn validation_names_the_field() {
    let mut params = unit_params();
    params.noise_m2[1] = f64::NAN;
    let err = params.validate().expect_err("NaN noise");
    assert!(err.to_string().contains("offset.noise_m2"), "{err}");
    let mut params = unit_params();
    params.calibrated_growth[0] = 2.0;
    let err = params.validate().expect_err("growth");
    assert!(
        err.to_string().contains("offset.calibrated_growth"),
        "{err}"
    );
    let params = OffsetParams {
        step_noise_m2: 0.0,
        ..unit_params()
    };
    let err = params.validate().expect_err("step noise");
    assert!(err.to_string().contains("offset.step_noise_m2"), "{err}");
}

#[test]
fn the_calibration_share_enters_the_test_as_a_covariance() {
    use super::params::{along, nis};
    // (3, 4) against a·I + diag(0, 3) with a = 1: 3²/1 + 4²/4 = 13.
    let c = [[0.0, 0.0], [0.0, 3.0]];
    assert!((nis([3.0, 4.0], 1.0, &c) - 13.0).abs() < 1e-12);
    // Without a share, ‖v‖²/a exactly.
    assert_eq!(nis([3.0, 4.0], 2.0, &[[0.0; 2]; 2]), 12.5);
    // Along north the share adds 3, along east nothing; a zero vector sees a alone.
    assert_eq!(along([0.0, 2.0], 1.0, &c), 4.0);
    assert_eq!(along([5.0, 0.0], 1.0, &c), 1.0);
    assert_eq!(along([0.0, 0.0], 1.0, &c), 1.0);
}

#[test]
fn an_offset_the_calibration_error_explains_is_not_held() {
    // North at 10 m/s with a 2° heading error left in the calibration in use: 0.35 m east per
    // step. Tested against the GNSS noise alone the anchors freeze on it; with the calibration's
    // error in the test, the offset is what that error makes of the distance carried.
    let beta = 2f64.to_radians();
    let run = |error: [f64; 3]| {
        let mut tracker = trusted(&unit_params());
        let mut worst = 0.0f64;
        for _ in 0..300 {
            let e = tracker.push(&OffsetStep {
                residual: [10.0 * beta, 0.0],
                calibrated: true,
                calibration_error: error,
                ..step([0.0; 2], 1.0)
            });
            worst = worst.max(e.max_nis());
        }
        worst
    };
    let without = run([0.0; 3]);
    let with = run([0.0, 0.0, beta * beta]);
    assert!(without >= FOLLOW_GATE, "{without}");
    assert!(with < 4.0, "{with}");
}

#[test]
fn a_break_before_any_fix_places_the_anchors_as_a_fresh_session_does() {
    // A stream that opens with the source's "new trajectory" flag must be tested exactly as one
    // without it (offline passes honour the flag on a recording's first row, a live session's
    // first sample may not carry it); after a fix, a break places the anchors with the
    // reacquisition's allowance, and a second break before the next fix keeps it.
    let fresh = OffsetTracker::new(&unit_params());
    let mut broken = fresh.clone();
    broken.re_anchor();
    assert_eq!(format!("{broken:?}"), format!("{fresh:?}"));
    let mut tracker = trusted(&unit_params());
    tracker.set_point(AnchorPoint {
        fix: crate::geo::LatLon {
            lat_deg: 0.0,
            lon_deg: 0.0,
        },
        velocity: [0.0; 2],
        time_s: 0.0,
        repeated: false,
    });
    tracker.re_anchor();
    assert_eq!(tracker.anchors[ANCHOR_COUNT - 1].gap_m2, REACQUISITION_M2);
    tracker.re_anchor();
    assert_eq!(tracker.anchors[ANCHOR_COUNT - 1].gap_m2, REACQUISITION_M2);
}

#[test]
fn a_held_jump_keeps_its_arrival_step_test_only_when_it_left_a_followed_track() {
    // Unit step noise, no levels: a 20 m jump from anchors that follow GNSS is a step NIS of 400,
    // kept for as long as the jump is held.
    let params = unit_params();
    let mut tracker = trusted(&params);
    let jump = tracker.push(&step([20.0, 0.0], 1.0));
    assert_eq!(jump.held_step_m, Some([20.0, 0.0]));
    assert_eq!(jump.held_step_nis, 400.0);
    let held = tracker.push(&step([0.0; 2], 1.0));
    assert_eq!(
        (held.held_step_m, held.held_step_nis),
        (Some([20.0, 0.0]), 400.0)
    );

    // An offset that built up froze the anchors, and came back: while the anchors wait out their
    // agreement, a jump leaves a track they were not following. It is held, but with no arrival
    // test (inside an offset already held, a fix that dipped back for one row and out again is no
    // jump from the track either).
    let mut tracker = trusted(&params);
    for _ in 0..10 {
        tracker.push(&step([1.0, 0.0], 1.0));
    }
    tracker.push(&step([-3.4, 0.0], 1.0));
    tracker.push(&step([-3.3, 0.0], 1.0));
    let back = tracker.push(&step([-3.3, 0.0], 1.0));
    assert!(back.frozen && back.max_nis() < FOLLOW_GATE, "{back:?}");
    let jump = tracker.push(&step([20.0, 0.0], 1.0));
    assert_eq!(jump.held_step_m, Some([20.0, 0.0]), "{jump:?}");
    assert_eq!(jump.held_step_nis, 0.0);
    assert_eq!(OffsetEvidence::EMPTY.held_step_nis, 0.0);

    // A receiver that held its fix while the vehicle stood steps to where the vehicle is once it
    // moves off: the same 20 m jump, leaving a held fix, is held with no arrival test.
    let mut tracker = trusted(&params);
    let caught_up = tracker.push(&OffsetStep {
        leaves_held_fix: true,
        ..step([20.0, 0.0], 1.0)
    });
    assert_eq!(caught_up.held_step_m, Some([20.0, 0.0]), "{caught_up:?}");
    assert_eq!(caught_up.held_step_nis, 0.0);

    // A row whose one-row residual is an outlier marks the next row as after a spike, and a row
    // within the step noise clears it.
    let mut tracker = trusted(&params);
    tracker.push(&step([10.0, 0.0], 1.0));
    assert!(tracker.after_spike);
    tracker.push(&step([0.0; 2], 1.0));
    assert!(!tracker.after_spike);

    // A fix coming back from a spike steps as far as the spike did: the same 20 m jump right after
    // an outlier row is held with no arrival test.
    let mut tracker = trusted(&params);
    tracker.after_spike = true;
    let back_from_spike = tracker.push(&step([20.0, 0.0], 1.0));
    assert_eq!(back_from_spike.held_step_m, Some([20.0, 0.0]));
    assert_eq!(back_from_spike.held_step_nis, 0.0);

    // A held jump whose offset came back within the follow gate and arrived again keeps its hold
    // but no longer its arrival test: what is held now is not the step it arrived with.
    let mut tracker = trusted(&params);
    assert_eq!(tracker.push(&step([20.0, 0.0], 1.0)).held_step_nis, 400.0);
    tracker.last = OffsetEvidence::EMPTY;
    tracker.held_s = f64::NAN;
    let again = tracker.push(&step([0.0; 2], 1.0));
    assert!(again.arrived_by_step, "{again:?}");
    assert_eq!(
        (again.held_step_m, again.held_step_nis),
        (Some([20.0, 0.0]), 0.0)
    );
}

mod rebase;
