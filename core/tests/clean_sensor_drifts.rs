//! A vehicle with clean sensors: fixes good to a few centimetres a step, no onboard bias, at 10 Hz.
//! Trust comes from the calibration's information, not from a timer, so a 1 m/s drift that starts
//! 10–30 s into the session must be found within 30 s, and a spoofer that toggles the whole offset
//! back to the truth now and then must not shake the alarm off: with the bundled default, and with
//! the calibration prior a fit to a fleet of such cars gives it.

use std::sync::Arc;

use spoofwatch_core::detector::Detector;
use spoofwatch_core::evidence::calibration::CalibrationPrior;
use spoofwatch_core::fleet_fit::prior::SPREAD_FLOOR;
use spoofwatch_core::model::artifact::ModelArtifact;
use spoofwatch_core::rng::Rng;
use spoofwatch_core::scenario::{
    AttackKind, AttackSpec, DriveSpec, GnssNoise, OnboardNoise, inject, simulate_drive,
};

const BUNDLED_MODEL: &[u8] = include_bytes!("../../models/default.json");
const RATE_HZ: f64 = 10.0;
const ATTACK_S: f64 = 60.0;
const DRIVES: u64 = 20;

/// A 10 Hz drive of the test track with clean sensors: GNSS white noise and bias of 5 cm per axis,
/// onboard speed good to 1 cm/s and heading to 0.1°, no onboard errors.
fn clean_drive(seed: u64) -> DriveSpec {
    DriveSpec {
        duration_s: 180.0,
        rate_hz: RATE_HZ,
        gnss_noise: GnssNoise {
            white_std_m: 0.05,
            bias_std_m: 0.05,
            bias_time_constant_s: 120.0,
        },
        onboard_noise: OnboardNoise {
            speed_std_mps: 0.01,
            heading_std_deg: 0.1,
        },
        seed,
        ..DriveSpec::default()
    }
}

/// What the bundled model did with one attack: the seconds from its first row to the first alarm
/// (within the attack), and the share of its rows alarmed.
struct Outcome {
    delay_s: Option<f64>,
    coverage: f64,
}

fn run(
    artifact: &Arc<ModelArtifact>,
    seed: u64,
    kind: AttackKind,
    onset_s: f64,
    direction_deg: f64,
) -> Outcome {
    let artifact = Arc::clone(artifact);
    let clean = simulate_drive(&clean_drive(seed), &format!("clean{seed}")).expect("a valid drive");
    let attack = AttackSpec {
        kind,
        direction_deg,
        onset_s,
        duration_s: ATTACK_S,
        seed: None,
    };
    let injected = inject(&clean, &attack).expect("the attack fits the drive");
    let mut detector = Detector::new(artifact);
    let (first, last) = (injected.first_attack_row, injected.last_attack_row);
    let t_first = injected.track.records[first].sample.timestamp_s;
    let (mut delay_s, mut covered) = (None, 0usize);
    for (i, record) in injected.track.records.iter().enumerate() {
        let decision = detector.step(&record.sample, record.trajectory_break);
        if (first..=last).contains(&i) && decision.alarm {
            covered += 1;
            delay_s.get_or_insert(record.sample.timestamp_s - t_first);
        }
    }
    Outcome {
        delay_s,
        coverage: covered as f64 / (last - first + 1) as f64,
    }
}

/// Each drive's onset (10–30 s into the session), direction and toggle period (3–15 s), drawn from
/// its seed.
fn draw(seed: u64) -> (f64, f64, f64) {
    let mut rng = Rng::seed_from_u64(seed ^ 0xC1EA_5E45);
    (
        rng.uniform_range(10.0, 30.0).round(),
        rng.uniform_range(0.0, 360.0).floor(),
        rng.uniform_range(3.0, 15.0).round(),
    )
}

/// The drives whose attack was alarmed within `within_s`, and the mean share of attacked rows alarmed.
fn score(outcomes: &[Outcome], within_s: f64) -> (usize, f64) {
    let found = outcomes
        .iter()
        .filter(|o| o.delay_s.is_some_and(|d| d <= within_s))
        .count();
    let coverage = outcomes.iter().map(|o| o.coverage).sum::<f64>() / outcomes.len() as f64;
    (found, coverage)
}

/// The bundled model with the calibration prior a fit to a fleet of such cars gives: the fitted
/// spread's floor (speed scale 1 %, heading 1°, lag 0.2 s) around no error.
fn fitted_to_clean_cars() -> ModelArtifact {
    let mut artifact = ModelArtifact::from_slice(BUNDLED_MODEL).expect("the bundled model");
    let drift = artifact.evidence.drift.as_mut().expect("v3 evidence");
    drift.calibration_prior = Some(CalibrationPrior {
        mean: [0.0; 3],
        std: SPREAD_FLOOR,
    });
    artifact
}

/// Early 1 m/s drifts on every drive, plain and toggling: (found within 30 s, mean coverage) each.
/// The drives themselves, without an attack, raise no alarm.
fn early_drifts(artifact: ModelArtifact) -> ((usize, f64), (usize, f64)) {
    let artifact = Arc::new(artifact);
    let (mut ramps, mut toggling) = (Vec::new(), Vec::new());
    for seed in 0..DRIVES {
        let clean = simulate_drive(&clean_drive(seed), "clean").expect("a valid drive");
        let mut detector = Detector::new(Arc::clone(&artifact));
        for record in &clean.records {
            let decision = detector.step(&record.sample, record.trajectory_break);
            assert!(
                !decision.alarm,
                "drive {seed} alarmed at {} s without an attack",
                record.sample.timestamp_s
            );
        }
        let (onset_s, direction_deg, period_s) = draw(seed);
        let ramp = AttackKind::RampDrift { velocity_mps: 1.0 };
        ramps.push(run(&artifact, seed, ramp, onset_s, direction_deg));
        let toggles = AttackKind::TogglingDrift {
            velocity_mps: 1.0,
            period_s,
        };
        toggling.push(run(&artifact, seed, toggles, onset_s, direction_deg));
    }
    let (ramps, toggling) = (score(&ramps, 30.0), score(&toggling, 30.0));
    eprintln!(
        "ramps: {} of {DRIVES} within 30 s, coverage {:.3}; toggling: {}, coverage {:.3}",
        ramps.0, ramps.1, toggling.0, toggling.1
    );
    (ramps, toggling)
}

#[test]
fn early_drifts_on_clean_sensors_are_found_and_toggles_do_not_shake_the_alarm_off() {
    let bundled = ModelArtifact::from_slice(BUNDLED_MODEL).expect("the bundled model");
    let ((ramp_found, ramp_coverage), (toggling_found, toggling_coverage)) = early_drifts(bundled);
    // Measured: 16 of 20 ramps within 30 s, covering 0.55 of their rows on average (the bundled
    // prior's 5° of compass doubt hides a drift the vehicle drives along or across until it turns,
    // and the warning point holds its budget on open roads too, θ 0.95 held 4 s); the same drifts
    // with toggles to the truth every 3–15 s, 16 of 20 and 0.58.
    assert!(
        ramp_found >= 15,
        "{ramp_found} of {DRIVES} early 1 m/s drifts alarmed within 30 s"
    );
    assert!(ramp_coverage >= 0.5, "coverage {ramp_coverage:.2}");
    assert!(
        toggling_found + 1 >= ramp_found && toggling_coverage >= ramp_coverage - 0.05,
        "toggles shook the alarm off: {toggling_found} found, coverage {toggling_coverage:.2}, \
         against {ramp_found} and {ramp_coverage:.2} without them"
    );
}

#[test]
fn a_fleet_prior_for_clean_cars_finds_every_early_drift_within_30_s() {
    let ((ramp_found, ramp_coverage), (toggling_found, toggling_coverage)) =
        early_drifts(fitted_to_clean_cars());
    // Measured: 20 of 20 and 0.73 (a 60 s attack found in 10–15 s covers at most 0.75–0.83, less
    // the 4 s the warning's p̂ is held before it opens), the toggling drifts alike (0.72).
    assert_eq!(
        ramp_found, DRIVES as usize,
        "early 1 m/s drifts within 30 s"
    );
    assert!(ramp_coverage >= 0.72, "coverage {ramp_coverage:.2}");
    assert!(
        toggling_found + 1 >= ramp_found && toggling_coverage >= ramp_coverage - 0.05,
        "toggles shook the alarm off: {toggling_found} found, coverage {toggling_coverage:.2}"
    );
}
