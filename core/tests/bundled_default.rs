//! The bundled default model on attacks that end: the alarm a frozen fix raised ends soon after the
//! fix moves again, at every sample rate, on drives of the fleet distribution and on drives with
//! clean onboard sensors. An alarm held open after its attack keeps paging someone for nothing; the
//! detector must hand the vehicle back once its fix and its own motion agree again.

use std::sync::Arc;

use spoofwatch_core::detector::Detector;
use spoofwatch_core::model::artifact::ModelArtifact;
use spoofwatch_core::scenario::{
    AttackKind, AttackSpec, DriveDistribution, DriveSpec, inject, simulate_drive,
};

const BUNDLED_MODEL: &[u8] = include_bytes!("../../models/default.json");
const ONSET_S: f64 = 100.0;
const DURATION_S: f64 = 60.0;
/// Seconds after the fix moves again by which the alarm open then has ended.
const END_WITHIN_S: f64 = 20.0;

/// The drive of `seed` at `rate_hz`: every third one the simulator's default drive (clean onboard
/// sensors), the others drawn from the fleet distribution (every error source of a fleet in service).
fn drive_spec(seed: u64, rate_hz: f64) -> DriveSpec {
    let base = if seed.is_multiple_of(3) {
        DriveSpec {
            seed,
            ..DriveSpec::default()
        }
    } else {
        DriveDistribution::fleet().draw(seed)
    };
    DriveSpec {
        duration_s: 300.0,
        rate_hz,
        ..base
    }
}

#[test]
fn a_frozen_fix_alarm_ends_once_the_fix_moves_again() {
    let artifact = Arc::new(ModelArtifact::from_slice(BUNDLED_MODEL).expect("the bundled model"));
    let (mut runs, mut alarmed, mut still_open) = (0, 0, Vec::new());
    for seed in 20..32 {
        for rate_hz in [1.0, 5.0, 10.0] {
            let clean = simulate_drive(&drive_spec(seed, rate_hz), &format!("drive{seed}"))
                .expect("a valid drive");
            let attack = AttackSpec {
                kind: AttackKind::FrozenPosition,
                direction_deg: 0.0,
                onset_s: ONSET_S,
                duration_s: DURATION_S,
                seed: None,
            };
            // A drive whose outage breaks the trajectory during the attack is not this test's case.
            let Ok(injected) = inject(&clean, &attack) else {
                continue;
            };
            let track = injected.track;
            let t0 = track.records[0].sample.timestamp_s;
            let mut detector = Detector::new(Arc::clone(&artifact));
            let end_s = ONSET_S + DURATION_S;
            let (mut during, mut ended_at) = (false, None);
            for record in &track.records {
                let t = record.sample.timestamp_s - t0;
                let decision = detector.step(&record.sample, record.trajectory_break);
                if decision.alarm && (ONSET_S..end_s).contains(&t) {
                    during = true;
                }
                if !decision.alarm && t >= end_s {
                    ended_at.get_or_insert(t);
                }
            }
            runs += 1;
            alarmed += usize::from(during);
            // The episode open when the fix moves again must end; a later onset is a new alarm.
            if ended_at.is_none_or(|t| t > end_s + END_WITHIN_S) {
                still_open.push(format!(
                    "seed {seed} at {rate_hz} Hz: ended at {ended_at:?} s"
                ));
            }
        }
    }
    assert!(
        still_open.is_empty(),
        "alarms not ended {END_WITHIN_S} s after the fix moved again: {still_open:?}"
    );
    // A frozen fix on a vehicle that stands is where the vehicle is; most of these drive on.
    assert!(
        2 * alarmed >= runs,
        "{alarmed} of {runs} frozen fixes alarmed"
    );
}
