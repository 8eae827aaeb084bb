//! Calibration trusted from information against trusted by timers, on the drift tracker and the
//! anchors: a clean vehicle that turns earns trust in seconds; a biased compass meets no cliff;
//! a receiver that holds its fix at standstill is not a frozen feed.

use super::calibration::{CalibrationTrust, WARM_UP_S};
use super::drift::{DriftInput, DriftParams, DriftTracker, SCALE_COUNT};
use super::linalg::IDENTITY;
use crate::rng::Rng;

/// Drift parameters whose calibrated rates have a population covariance of (0.1 m/s)² per axis
/// (a quiet fleet) and unit thresholds, trusted as `trust`.
fn params(trust: CalibrationTrust) -> DriftParams {
    let quiet = [[0.01, 0.0], [0.0, 0.01]];
    DriftParams {
        calibrated_covariance: [quiet; SCALE_COUNT],
        raw_covariance: [IDENTITY; SCALE_COUNT],
        trust,
        stale_fix_while_moving: true,
        ..DriftParams::unwhitened(0.1)
    }
}

/// Row `t` (1 Hz) of a vehicle at `speed` m/s whose heading swings ±90° every 40 s (`turning`), or
/// that drives due east: (motion, velocity change).
fn row(t: usize, speed: f64, turning: bool) -> ([f64; 2], [f64; 2]) {
    let velocity = |t: f64| {
        let heading = if turning {
            std::f64::consts::FRAC_PI_2 * (t * std::f64::consts::TAU / 40.0).sin()
        } else {
            std::f64::consts::FRAC_PI_2
        };
        [speed * heading.sin(), speed * heading.cos()]
    };
    let (now, before) = (velocity(t as f64), velocity(t as f64 - 1.0));
    (
        [0.5 * (now[0] + before[0]), 0.5 * (now[1] + before[1])],
        [now[0] - before[0], now[1] - before[1]],
    )
}

/// The residual a heading bias of `bias_deg` leaves on a step dead-reckoned as `motion`, plus
/// `noise` and a drift of `drift` m/s east: r = −β J u + noise + drift.
fn input(
    motion: [f64; 2],
    velocity_change: [f64; 2],
    bias_deg: f64,
    noise: [f64; 2],
    drift: f64,
) -> DriftInput {
    let beta = bias_deg.to_radians();
    DriftInput {
        residual: [
            -beta * motion[1] + noise[0] + drift,
            beta * motion[0] + noise[1],
        ],
        motion,
        velocity_change,
        delta_t: 1.0,
        fix_repeated: false,
        learn: true,
    }
}

#[test]
fn a_clean_vehicle_that_turns_earns_trust_in_seconds_and_catches_an_early_drift() {
    let mut rng = Rng::seed_from_u64(3);
    let mut information = DriftTracker::new(&params(CalibrationTrust::Information));
    let mut timers = DriftTracker::new(&params(CalibrationTrust::Timers));
    let mut first_alarm_s = None;
    for t in 1..=60 {
        let (motion, dv) = row(t, 10.0, true);
        let noise = [0.02 * rng.normal(), 0.02 * rng.normal()];
        // A 1 m/s drift east from 15 s on.
        let drift = if t >= 15 { 1.0 } else { 0.0 };
        let e = information.push(&input(motion, dv, 0.0, noise, drift));
        let old = timers.push(&input(motion, dv, 0.0, noise, drift));
        if t == 14 {
            assert!(
                e.warm_up > 0.9,
                "trust after 14 s of turning: {}",
                e.warm_up
            );
            assert!((old.warm_up - 14.0 / WARM_UP_S).abs() < 1e-12);
        }
        assert!(!old.is_warm(), "timers keep the calibrated channels off");
        if first_alarm_s.is_none() && e.statistic >= 1.0 && drift > 0.0 {
            first_alarm_s = Some(t);
        }
    }
    let first = first_alarm_s.expect("the calibrated channels see the drift");
    assert!(first <= 15 + 5, "seen {} s after its start", first - 15);
}

#[test]
fn a_biased_compass_on_a_straight_road_meets_no_cliff() {
    // 3° of heading bias at 27 m/s is 1.4 m/s across the track, 14 population sigmas.
    let mut rng = Rng::seed_from_u64(4);
    let mut tracker = DriftTracker::new(&params(CalibrationTrust::Information));
    let mut worst = 0.0f64;
    for t in 1..=900 {
        let (motion, dv) = row(t, 27.0, false);
        let noise = [0.05 * rng.normal(), 0.05 * rng.normal()];
        let e = tracker.push(&input(motion, dv, 3.0, noise, 0.0));
        if t > 20 {
            worst = worst.max(e.calibrated_chi2().into_iter().fold(0.0, f64::max));
        }
    }
    // The test covariance carries the calibration's error while it converges and while the
    // estimate in use lags it: the χ² of the calibrated rates stays below the anchors' follow gate
    // (a χ²₂ tail of 3.4·10⁻⁴), where without it the bias alone makes ≈ 196. What is left is the
    // 120 s rate's memory of rows cleaned with the older estimate when a newer one comes into use.
    assert!(worst < 16.0, "largest calibrated χ² {worst}");
}

#[test]
fn a_fix_held_at_standstill_is_not_stale_until_the_vehicle_moves() {
    let mut tracker = DriftTracker::new(&params(CalibrationTrust::Information));
    let mut stale = Vec::new();
    for t in 0..8 {
        // Standing for 4 s, then moving at 5 m/s; the fix repeats throughout.
        let speed = if t < 4 { 0.0 } else { 5.0 };
        let e = tracker.push(&DriftInput {
            residual: [-speed, 0.0],
            motion: [speed, 0.0],
            velocity_change: [0.0; 2],
            delta_t: 1.0,
            fix_repeated: t > 0,
            learn: true,
        });
        stale.push(e.stale_fix_s);
    }
    assert_eq!(stale, [0.0, 0.0, 0.0, 0.0, 1.0, 2.0, 3.0, 4.0]);
    // Without the rule (artifacts before it) every repeated row counts.
    let mut always = DriftTracker::new(&DriftParams {
        stale_fix_while_moving: false,
        ..params(CalibrationTrust::Timers)
    });
    let counted: Vec<f64> = (0..4)
        .map(|t| {
            always
                .push(&DriftInput {
                    residual: [0.0; 2],
                    motion: [0.0; 2],
                    velocity_change: [0.0; 2],
                    delta_t: 1.0,
                    fix_repeated: t > 0,
                    learn: true,
                })
                .stale_fix_s
        })
        .collect();
    assert_eq!(counted, [0.0, 1.0, 2.0, 3.0]);
}

#[test]
fn trust_and_the_stale_rule_are_written_only_when_they_differ_from_older_artifacts() {
    let old = serde_json::to_value(params(CalibrationTrust::Timers)).expect("serialises");
    assert_eq!(old["trust"], serde_json::Value::Null);
    let new = serde_json::to_value(params(CalibrationTrust::Information)).expect("serialises");
    assert_eq!(new["trust"], "information");
    assert_eq!(new["stale_fix_while_moving"], true);
    let back: DriftParams = serde_json::from_value(new).expect("reads back");
    assert_eq!(back.trust, CalibrationTrust::Information);
}

/// A vehicle that turns at `speed` m/s with a 3° compass bias, for `seconds`, then `twin` rows:
/// returns the tracker that saw the rows as they came (`learn: true`) and its twin that was told
/// not to learn from them. Equal trust afterwards means the rows taught the calibration nothing.
fn with_and_without_learning(
    params: &DriftParams,
    speed: f64,
    seconds: usize,
    rows: &[DriftInput],
) -> (DriftTracker, DriftTracker) {
    let mut rng = Rng::seed_from_u64(5);
    let mut seen = DriftTracker::new(params);
    for t in 1..=seconds {
        let (motion, dv) = row(t, speed, true);
        let noise = [0.05 * rng.normal(), 0.05 * rng.normal()];
        seen.push(&input(motion, dv, 3.0, noise, 0.0));
    }
    let mut told = seen.clone();
    for row in rows {
        seen.push(row);
        told.push(&DriftInput {
            learn: false,
            ..*row
        });
    }
    (seen, told)
}

/// ω and the calibration in use after one more ordinary row (both change only when the
/// calibration learns).
fn calibration_of(tracker: &mut DriftTracker) -> (u64, [u64; 3]) {
    let (motion, dv) = row(1000, 10.0, true);
    let e = tracker.push(&DriftInput {
        learn: false,
        ..input(motion, dv, 3.0, [0.0; 2], 0.0)
    });
    (e.warm_up.to_bits(), e.calibration.map(f64::to_bits))
}

#[test]
fn a_fix_that_freezes_while_the_vehicle_drives_teaches_the_calibration_nothing() {
    // 1.5 m/s under a noise σ of 1 m: each frozen row is within the consistency gate, so only
    // the stale rule keeps it out.
    let noisy = DriftParams {
        residual_sigma_m: 1.0,
        clip_m: 4.0,
        ..params(CalibrationTrust::Information)
    };
    let frozen: Vec<DriftInput> = (0..40)
        .map(|_| DriftInput {
            residual: [-1.5, 0.0],
            motion: [1.5, 0.0],
            velocity_change: [0.0; 2],
            delta_t: 1.0,
            fix_repeated: true,
            learn: true,
        })
        .collect();
    let (mut seen, mut told) = with_and_without_learning(&noisy, 10.0, 200, &frozen);
    assert_eq!(calibration_of(&mut seen), calibration_of(&mut told));
    // The same rows from a fix that moves (a slow vehicle's honest residual) do teach.
    let moving: Vec<DriftInput> = frozen
        .iter()
        .map(|row| DriftInput {
            fix_repeated: false,
            ..*row
        })
        .collect();
    let (mut seen, mut told) = with_and_without_learning(&noisy, 10.0, 200, &moving);
    assert_ne!(calibration_of(&mut seen), calibration_of(&mut told));
}

#[test]
fn a_displaced_fix_teaches_the_calibration_nothing_and_the_vehicle_keeps_its_trust() {
    let params = params(CalibrationTrust::Information);
    let (motion, dv) = row(201, 10.0, true);
    // One row 30 m away from where the vehicle drove: no calibration within its bound makes it.
    let jump = input(motion, dv, 3.0, [30.0, 0.0], 0.0);
    let (mut seen, mut told) = with_and_without_learning(&params, 10.0, 200, &[jump]);
    assert_eq!(calibration_of(&mut seen), calibration_of(&mut told));
    // A fix held for 40 s while the vehicle drives at 10 m/s: without the gate the calibration
    // would chase it to its bound and the error that move implies would cost the vehicle its trust.
    let held: Vec<DriftInput> = (201..241)
        .map(|t| {
            let (motion, dv) = row(t, 10.0, true);
            DriftInput {
                residual: [-motion[0], -motion[1]],
                fix_repeated: false,
                ..input(motion, dv, 3.0, [0.0; 2], 0.0)
            }
        })
        .collect();
    let (mut seen, mut told) = with_and_without_learning(&params, 10.0, 200, &held);
    let (trust, _) = calibration_of(&mut seen);
    assert_eq!(calibration_of(&mut seen), calibration_of(&mut told));
    assert!(
        f64::from_bits(trust) > 0.9,
        "trust {}",
        f64::from_bits(trust)
    );
    // An ordinary row does teach.
    let honest = input(motion, dv, 3.0, [0.05, -0.05], 0.0);
    let (mut seen, mut told) = with_and_without_learning(&params, 10.0, 200, &[honest]);
    assert_ne!(calibration_of(&mut seen), calibration_of(&mut told));
}
