//! Property tests of sample validation and of the evidence it guards: whatever numbers a client
//! sends, validation names each bad field with a short message; every sample it accepts, in any
//! order and with any reported uncertainty, gives a finite probability in [0, 1] and finite
//! evidence on the wire; and a reported uncertainty can only widen the noise model, never make η
//! larger than the training Σ̂ would.

use std::sync::Arc;

use proptest::prelude::*;
use spoofwatch_core::detector::Detector;
use spoofwatch_core::evidence::EvidenceBuilder;
use spoofwatch_core::model::artifact::ModelArtifact;
use spoofwatch_core::sample::{MAX_HEADING_STD_DEG, MAX_POSITION_STD_M, MAX_SPEED_STD_MPS, Sample};
use spoofwatch_core::scenario::{DriveSpec, simulate_drive};

fn bundled_model() -> Arc<ModelArtifact> {
    let bytes = include_bytes!("../../models/default.json");
    Arc::new(ModelArtifact::from_slice(bytes).expect("the bundled model loads"))
}

/// The samples of a 90 s clean drive.
fn clean_drive(seed: u64) -> Vec<Sample> {
    let spec = DriveSpec {
        duration_s: 90.0,
        seed,
        ..DriveSpec::default()
    };
    let track = simulate_drive(&spec, "v").expect("a valid drive");
    track.records.into_iter().map(|r| r.sample).collect()
}

/// Any f64, weighted towards the values that break arithmetic.
fn any_number() -> impl Strategy<Value = f64> {
    prop_oneof![
        Just(f64::NAN),
        Just(f64::INFINITY),
        Just(f64::NEG_INFINITY),
        Just(f64::MAX),
        Just(-f64::MAX),
        Just(f64::MIN_POSITIVE),
        Just(1e-300),
        Just(0.0),
        Just(-0.0),
        -1e6..1e6,
        any::<f64>(),
    ]
}

/// A reported 1-σ uncertainty inside its documented range, weighted to the ends.
fn std_in(max: f64) -> impl Strategy<Value = Option<f64>> {
    prop_oneof![
        Just(None),
        Just(Some(0.0)),
        Just(Some(1e-300)),
        Just(Some(max)),
        (0.0..=max).prop_map(Some),
    ]
}

fn uncertainties() -> impl Strategy<Value = (Option<f64>, Option<f64>, Option<f64>)> {
    (
        std_in(MAX_POSITION_STD_M),
        std_in(MAX_SPEED_STD_MPS),
        std_in(MAX_HEADING_STD_DEG),
    )
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(256))]

    #[test]
    fn every_bad_field_is_named_with_a_short_message(
        fields in proptest::collection::vec(any_number(), 8),
        present in proptest::collection::vec(any::<bool>(), 3),
    ) {
        let mut sample = Sample::new(fields[0], fields[1], fields[2], fields[3], fields[4]);
        sample.position_std_m = present[0].then_some(fields[5]);
        sample.speed_std_mps = present[1].then_some(fields[6]);
        sample.heading_std_deg = present[2].then_some(fields[7]);
        let violations = sample.violations();
        for violation in &violations {
            prop_assert!(!violation.field.is_empty());
            prop_assert!(
                violation.description.len() <= 60,
                "{}: {}", violation.field, violation.description
            );
        }
        if violations.is_empty() {
            prop_assert!(sample.uncertainties_in_range());
        }
    }

    #[test]
    fn accepted_samples_give_finite_probabilities_and_evidence(
        seed in 0u64..1_000,
        edits in proptest::collection::vec(
            (0usize..91, any_number(), any_number(), uncertainties()), 0..30),
    ) {
        let mut samples: Vec<Sample> = clean_drive(seed);
        for (index, speed, heading, (position_std, speed_std, heading_std)) in edits {
            let last = samples.len() - 1;
            let sample = &mut samples[index.min(last)];
            sample.speed_mps = speed;
            sample.heading_deg = heading;
            sample.position_std_m = position_std;
            sample.speed_std_mps = speed_std;
            sample.heading_std_deg = heading_std;
        }
        let mut detector = Detector::new(bundled_model());
        for sample in samples.iter().filter(|s| s.violations().is_empty()) {
            let decision = detector.step(sample, false);
            let p = decision.probability;
            prop_assert!((0.0..=1.0).contains(&p), "probability {p} at t={}", sample.timestamp_s);
            let e = &decision.evidence;
            let wire = [e.eta[0], e.eta[1], e.q, e.accum_log];
            prop_assert!(wire.iter().all(|x| x.is_finite()), "{e:?}");
            if let Some(drift) = &e.drift {
                prop_assert!(drift.statistic.is_finite() && drift.residual_log.is_finite());
            }
        }
    }

    #[test]
    fn reported_uncertainty_never_makes_eta_larger_than_the_training_covariance(
        seed in 0u64..1_000,
        reported in proptest::collection::vec(uncertainties(), 91),
    ) {
        let plain = clean_drive(seed);
        let params = bundled_model().evidence;
        let (mut with_std, mut without) = (EvidenceBuilder::new(params), EvidenceBuilder::new(params));
        for (sample, (position_std, speed_std, heading_std)) in plain.iter().zip(reported) {
            let mut reporting = *sample;
            reporting.position_std_m = position_std;
            reporting.speed_std_mps = speed_std;
            reporting.heading_std_deg = heading_std;
            let tightest = without.push(sample, false).energy;
            let e = with_std.push(&reporting, false);
            if e.valid {
                prop_assert!(
                    e.energy <= tightest * (1.0 + 1e-9) + 1e-12,
                    "energy {} above the Σ̂ energy {tightest} at t={}", e.energy, sample.timestamp_s
                );
            }
        }
    }
}
