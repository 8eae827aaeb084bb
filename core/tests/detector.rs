//! The serving path end to end on simulated data: the streaming detector equals the whole-trajectory
//! pass and the model's sequence forward; artifacts round-trip and refuse other schema versions;
//! chronological splitting and a small training job work together.

use std::sync::Arc;
use std::sync::atomic::AtomicBool;

use spoofwatch_core::alarm::{OperatingPoint, PersistenceAlarm};
use spoofwatch_core::detector::{
    Detector, DetectorState, RestoreError, offset_signal, run_records,
};
use spoofwatch_core::evaluation::{evaluate_tracks, score_tracks};
use spoofwatch_core::evidence::FeatureSchema;
use spoofwatch_core::evidence::build_track;
use spoofwatch_core::evidence::fit_evidence;
use spoofwatch_core::geo::Projection;
use spoofwatch_core::lifecycle::{AlarmLifecycle, Lifecycle, LifecycleInput};
use spoofwatch_core::metrics::EventRules;
use spoofwatch_core::model::artifact::{
    ARTIFACT_SCHEMA_VERSION, ArtifactError, ModelArtifact, Provenance,
};
use spoofwatch_core::model::{Ablation, LiquidState, Model, ModelConfig};
use spoofwatch_core::receiver::FlagSignal;
use spoofwatch_core::sample::Track;
use spoofwatch_core::scenario::{
    AttackKind, AttackSpec, DriveSpec, OnboardErrors, inject, simulate_drive,
};
use spoofwatch_core::severity::{CriticalTest, Escalation};
use spoofwatch_core::train::data::{
    sequences, split_chronologically, split_with_warmup, trajectory_ranges,
};
use spoofwatch_core::train::detector::{TrainDetectorError, TrainingData, train_detector};
use spoofwatch_core::train::spec::{AnchorRebase, SplitFractions, TrainingSpec};
use spoofwatch_core::train::{TrainConfig, TrainError};

fn drive(seed: u64, seconds: f64) -> Track {
    let spec = DriveSpec {
        duration_s: seconds,
        seed,
        ..DriveSpec::default()
    };
    simulate_drive(&spec, &format!("sim{seed}")).expect("valid drive")
}

fn attacked(seed: u64) -> Track {
    attacked_with(seed, AttackKind::RampDrift { velocity_mps: 2.0 })
}

fn attacked_with(seed: u64, kind: AttackKind) -> Track {
    let attack = AttackSpec {
        kind,
        direction_deg: 45.0,
        onset_s: 200.0,
        duration_s: 150.0,
        seed: None,
    };
    inject(&drive(seed, 500.0), &attack).expect("fits").track
}

/// An untrained (but valid) artifact: evidence fitted on normal drives, random weights.
fn artifact(op: OperatingPoint) -> Arc<ModelArtifact> {
    artifact_of(op, FeatureSchema::V3, ModelConfig::default())
}

fn artifact_of(
    op: OperatingPoint,
    schema: FeatureSchema,
    config: ModelConfig,
) -> Arc<ModelArtifact> {
    let normal: Vec<Track> = (0..2).map(|s| drive(s, 400.0)).collect();
    let fit =
        fit_evidence(&normal, Projection::Wgs84Local, 0.0, 0.98, schema).expect("enough rows");
    let config = ModelConfig { schema, ..config };
    Arc::new(ModelArtifact {
        schema_version: ARTIFACT_SCHEMA_VERSION,
        feature_names: ModelArtifact::feature_names_of(schema),
        model: Model::init(config, 7).expect("valid config"),
        evidence: fit.params,
        scaler: fit.scaler,
        operating_point: op,
        lifecycle: schema.has_offset().then_some(Lifecycle {
            on_s: 2.0,
            off_s: 5.0,
            decisive_s: 2.0,
        }),
        critical: schema.has_offset().then_some(CriticalTest {
            reference_logit: 0.0,
            threshold: 5.0,
            gate: 100.0,
            decisive_s: 3.0,
            frozen_fix_s: None,
            held_jump: None,
            held_step: None,
            held_offset: None,
        }),
        provenance: Provenance::default(),
    })
}

#[test]
fn streaming_detector_equals_the_whole_trajectory_pass_and_the_model_forward() {
    let op = OperatingPoint { theta: 0.5, n_p: 3 };
    let artifact = artifact(op);
    let mut track = attacked(11);
    // A source break in the middle: a second trajectory inside the same recording.
    track.records[300].trajectory_break = true;

    let offline = run_records(&artifact, &track.records);
    let mut detector = Detector::new(Arc::clone(&artifact));
    for (record, expected) in track.records.iter().zip(&offline) {
        let live = detector.step(&record.sample, record.trajectory_break);
        assert_eq!(live.probability.to_bits(), expected.probability.to_bits());
        assert_eq!(live.alarm, expected.alarm);
        assert_eq!(live.severity, expected.severity);
        assert_eq!(live.escalation, expected.escalation);
    }

    // The same probabilities from the model's sequence pass over the scaled features, trajectory by
    // trajectory from a zero state, and the same alarms from the lifecycle (v3, the default schema)
    // or the persistence rule.
    let mut alarm = PersistenceAlarm::new(op.n_p);
    let mut lifecycle = AlarmLifecycle::default();
    let mut escalation = Escalation::default();
    for range in trajectory_ranges(&track.records) {
        let records = &track.records[range.clone()];
        let decisions = &offline[range];
        let xs: Vec<_> = decisions.iter().map(|d| d.features).collect();
        let deltas: Vec<f64> = decisions.iter().map(|d| d.evidence.delta_t).collect();
        let mut state = LiquidState::zeros(artifact.model.config());
        let probabilities = artifact
            .model
            .forward_sequence(&xs, &deltas, &mut state)
            .expect("lengths match");
        for ((d, p), record) in decisions.iter().zip(probabilities).zip(records) {
            assert_eq!(d.probability.to_bits(), p.to_bits());
            let expected = match &artifact.lifecycle {
                Some(durations) => lifecycle.update_graded(
                    durations,
                    artifact.critical.as_ref(),
                    &mut escalation,
                    &LifecycleInput {
                        time_s: record.sample.timestamp_s,
                        valid: d.evidence.valid,
                        trajectory_start: d.evidence.trajectory_start,
                        positive: p >= op.theta,
                        probability: p,
                        offset: offset_signal(&d.evidence),
                        flag: FlagSignal::default(),
                    },
                ),
                None => alarm.update(p >= op.theta, d.evidence.valid, d.evidence.trajectory_start),
            };
            assert_eq!(d.alarm, expected);
            assert_eq!(d.severity, escalation.severity(expected));
        }
    }
    assert_eq!(offline[300].evidence.trajectory, 1);
}

/// The state through the session snapshot's encoding (postcard) and back.
fn through_bytes(state: &DetectorState) -> DetectorState {
    let bytes = postcard::to_allocvec(state).expect("encodes");
    postcard::from_bytes(&bytes).expect("decodes")
}

#[test]
fn a_detector_restored_from_its_saved_state_continues_bit_for_bit() {
    for schema in [FeatureSchema::Paper, FeatureSchema::V2, FeatureSchema::V3] {
        // A permissive θ so that the run crosses alarm onsets and ends.
        let artifact = artifact_of(
            OperatingPoint { theta: 0.3, n_p: 2 },
            schema,
            ModelConfig::default(),
        );
        let mut track = attacked(12);
        track.records[420].trajectory_break = true;
        let offline = run_records(&artifact, &track.records);
        assert!(
            offline.iter().any(|d| d.alarm_onset),
            "{schema:?}: the run alarms"
        );
        if schema == FeatureSchema::V3 {
            assert!(
                offline.iter().any(|d| d.escalation),
                "{schema:?}: the run escalates"
            );
        }
        // Hand-offs before the drift calibration is warm, during the attack, right after a
        // trajectory break, and at the very start.
        for cut in [0, 1, 150, 230, 260, 421, 499] {
            let mut before = Detector::new(Arc::clone(&artifact));
            for record in &track.records[..cut] {
                before.step(&record.sample, record.trajectory_break);
            }
            let mut after = Detector::restore(Arc::clone(&artifact), through_bytes(&before.save()))
                .expect("the same model takes its own state");
            for (record, expected) in track.records[cut..].iter().zip(&offline[cut..]) {
                let live = after.step(&record.sample, record.trajectory_break);
                let bits = |d: &spoofwatch_core::detector::Decision| {
                    let features: Vec<u64> = d.features.iter().map(|f| f.to_bits()).collect();
                    (
                        d.probability.to_bits(),
                        features,
                        d.alarm,
                        d.alarm_onset,
                        d.alarm_end,
                        d.severity,
                        d.escalation,
                    )
                };
                assert_eq!(bits(&live), bits(expected), "{schema:?}, restored at {cut}");
            }
        }
    }
}

#[test]
fn a_state_that_does_not_fit_the_model_is_refused() {
    let op = OperatingPoint { theta: 0.5, n_p: 3 };
    let v2 = artifact_of(op, FeatureSchema::V2, ModelConfig::default());
    let paper = artifact_of(op, FeatureSchema::Paper, ModelConfig::default());
    let narrow = artifact_of(
        op,
        FeatureSchema::V2,
        ModelConfig {
            d_h: 8,
            ..ModelConfig::default()
        },
    );
    let other_persistence = artifact_of(
        OperatingPoint { theta: 0.5, n_p: 4 },
        FeatureSchema::V2,
        ModelConfig::default(),
    );
    let saved = Detector::new(Arc::clone(&v2)).save();
    let refusal = |artifact: &Arc<ModelArtifact>, state: DetectorState| {
        Detector::restore(Arc::clone(artifact), state).err()
    };
    assert_eq!(
        refusal(&paper, saved.clone()),
        Some(RestoreError::DriftChannels { in_snapshot: true })
    );
    assert_eq!(
        refusal(&v2, Detector::new(Arc::clone(&paper)).save()),
        Some(RestoreError::DriftChannels { in_snapshot: false })
    );
    assert_eq!(
        refusal(&narrow, saved.clone()),
        Some(RestoreError::StateWidth {
            expected: 8,
            found: ModelConfig::default().d_h
        })
    );
    assert_eq!(
        refusal(&other_persistence, saved),
        Some(RestoreError::Persistence {
            expected: 4,
            found: 3
        })
    );
}

#[test]
fn alarm_onsets_and_ends_pair_up() {
    let artifact = artifact(OperatingPoint { theta: 0.5, n_p: 1 });
    let decisions = run_records(&artifact, &attacked(3).records);
    let onsets = decisions.iter().filter(|d| d.alarm_onset).count();
    let ends = decisions.iter().filter(|d| d.alarm_end).count();
    let still_on = usize::from(decisions.last().is_some_and(|d| d.alarm));
    assert_eq!(onsets, ends + still_on);
    for pair in decisions.windows(2) {
        assert_eq!(pair[1].alarm_onset, pair[1].alarm && !pair[0].alarm);
    }
}

#[test]
fn artifacts_round_trip_and_serve_identically() {
    let artifact = artifact(OperatingPoint {
        theta: 0.35,
        n_p: 2,
    });
    let bytes = artifact.to_vec().expect("serialises");
    let loaded = Arc::new(ModelArtifact::from_slice(&bytes).expect("parses"));
    assert_eq!(*loaded, *artifact);
    let track = attacked(5);
    let a = run_records(&artifact, &track.records);
    let b = run_records(&loaded, &track.records);
    for (x, y) in a.iter().zip(&b) {
        assert_eq!(x.probability.to_bits(), y.probability.to_bits());
    }
}

#[test]
fn other_schema_versions_and_foreign_documents_fail_clearly() {
    let artifact = artifact(OperatingPoint { theta: 0.5, n_p: 1 });
    let mut value: serde_json::Value =
        serde_json::from_slice(&artifact.to_vec().expect("serialises")).expect("json");
    value["schema_version"] = serde_json::json!(ARTIFACT_SCHEMA_VERSION + 1);
    let newer = ModelArtifact::from_slice(value.to_string().as_bytes()).unwrap_err();
    assert!(matches!(newer, ArtifactError::UnsupportedSchema { .. }));
    assert!(newer.to_string().contains("newer Spoofwatch"), "{newer}");

    value["schema_version"] = serde_json::json!(0);
    let older = ModelArtifact::from_slice(value.to_string().as_bytes()).unwrap_err();
    assert!(older.to_string().contains("retrain"), "{older}");

    let foreign = ModelArtifact::from_slice(br#"{"weights": [1, 2, 3]}"#).unwrap_err();
    assert!(matches!(foreign, ArtifactError::MissingSchemaVersion));
    assert!(matches!(
        ModelArtifact::from_slice(b"not json").unwrap_err(),
        ArtifactError::Json { .. }
    ));

    value["schema_version"] = serde_json::json!(ARTIFACT_SCHEMA_VERSION);
    value["feature_names"][0] = serde_json::json!("something_else");
    assert!(matches!(
        ModelArtifact::from_slice(value.to_string().as_bytes()).unwrap_err(),
        ArtifactError::FeatureMismatch { .. }
    ));
}

#[test]
fn chronological_split_keeps_order_and_fractions_per_trajectory() {
    let mut track = drive(1, 999.0); // 1000 rows
    track.records[600].trajectory_break = true; // two trajectories: 600 + 400 rows
    let split = split_chronologically(std::slice::from_ref(&track), SplitFractions::default());
    let lens = |ts: &[Track]| ts.iter().map(|t| t.records.len()).collect::<Vec<_>>();
    assert_eq!(lens(&split.train), [420, 280]);
    assert_eq!(lens(&split.validation), [90, 60]);
    assert_eq!(lens(&split.test), [90, 60]);
    assert_eq!(split.train[0].records[0].line, track.records[0].line);
    assert_eq!(split.validation[0].records[0].line, track.records[420].line);
    assert_eq!(split.test[1].records[59].line, track.records[999].line);
    let all = [&split.train[..], &split.validation[..], &split.test[..]].concat();
    assert!(all.iter().all(|t| t.records[0].trajectory_break));
}

#[test]
fn an_attack_the_anchors_hold_teaches_the_onboard_calibration_nothing() {
    // A 2 m/s ramp for 150 s on a slow drive: learned as onboard errors it would turn the heading
    // bias by degrees and carry the spoofer's drift into the drive after the attack.
    let spec = DriveSpec {
        duration_s: 360.0,
        onboard_errors: OnboardErrors {
            speed_scale_error: 0.03,
            heading_bias_deg: -2.0,
            timing_offset_s: 0.0,
        },
        seed: 7,
        ..DriveSpec::default()
    };
    let clean = simulate_drive(&spec, "calibrated").expect("valid drive");
    let attack = AttackSpec {
        kind: AttackKind::RampDrift { velocity_mps: 2.0 },
        direction_deg: 60.0,
        onset_s: 150.0,
        duration_s: 150.0,
        seed: None,
    };
    let attacked = inject(&clean, &attack).expect("fits").track;
    let normal: Vec<Track> = (0..2).map(|s| drive(s, 400.0)).collect();
    let calibration_shift = |schema| {
        let fit = fit_evidence(&normal, Projection::Wgs84Local, 0.0, 0.98, schema).expect("fits");
        let last = |track: &Track| {
            build_track(&fit.params, &track.records)
                .last()
                .and_then(|e| e.drift)
                .expect("drift evidence")
                .calibration
        };
        let (before, after) = (last(&clean), last(&attacked));
        ((after[0] - before[0]).abs(), (after[1] - before[1]).abs())
    };
    let (_, heading_v2) = calibration_shift(FeatureSchema::V2);
    let (scale_v3, heading_v3) = calibration_shift(FeatureSchema::V3);
    assert!(
        heading_v3 < 0.5 && scale_v3 < 0.005,
        "v3: {scale_v3}, {heading_v3}°"
    );
    assert!(
        heading_v2 > 2.0,
        "v2 has no anchors to hold its calibration: {heading_v2}°"
    );
}

#[test]
fn a_warm_split_precedes_validation_and_test_parts_with_their_earlier_rows() {
    let mut track = drive(1, 999.0); // 1000 rows at 1 Hz
    track.records[600].trajectory_break = true;
    let split = split_with_warmup(
        std::slice::from_ref(&track),
        SplitFractions::default(),
        50.5,
    );
    let lens = |ts: &[Track]| ts.iter().map(|t| t.records.len()).collect::<Vec<_>>();
    let warm = |ts: &[Track]| {
        ts.iter()
            .map(|t| t.records.iter().filter(|r| r.warmup).count())
            .collect::<Vec<_>>()
    };
    // The training parts start their trajectories; the others carry the 50 rows (50 s) before
    // them, never rows of an earlier trajectory.
    assert_eq!(lens(&split.train), [420, 280]);
    assert_eq!(warm(&split.train), [0, 0]);
    assert_eq!(lens(&split.validation), [140, 110]);
    assert_eq!(warm(&split.validation), [50, 50]);
    assert_eq!(warm(&split.test), [50, 50]);
    assert_eq!(split.validation[0].records[0].line, track.records[370].line);
    assert_eq!(
        split.validation[0].records[50].line,
        track.records[420].line
    );
    assert!(split.validation[0].records[..50].iter().all(|r| r.warmup));
    assert!(!split.validation[0].records[50].warmup);
    assert!(split.validation[0].records[0].trajectory_break);
    assert!(!split.validation[0].records[50].trajectory_break);
    // Without warm-up it is the plain chronological split.
    assert_eq!(
        split_with_warmup(std::slice::from_ref(&track), SplitFractions::default(), 0.0),
        split_chronologically(std::slice::from_ref(&track), SplitFractions::default())
    );
}

#[test]
fn warm_up_rows_carry_the_state_but_are_neither_scored_nor_learned() {
    let art = artifact(OperatingPoint { theta: 0.5, n_p: 2 });
    let mut track = attacked(3);
    let cold = Track {
        vehicle_id: track.vehicle_id.clone(),
        records: track.records[100..].to_vec(),
    };
    for record in &mut track.records[..100] {
        record.warmup = true;
    }
    let warm_scored = score_tracks(&art, std::slice::from_ref(&track));
    assert_eq!(warm_scored.rows.len(), track.records.len() - 100);
    assert_eq!(warm_scored.alarms.len(), warm_scored.rows.len());
    assert_eq!(warm_scored.offset.len(), warm_scored.rows.len());
    // The kept rows are the same rows, scored with the state the warm-up rows left: the whole
    // track's decisions from row 100 on.
    let whole = run_records(&art, &track.records);
    let probabilities: Vec<f64> = whole[100..].iter().map(|d| d.probability).collect();
    let kept: Vec<f64> = warm_scored.rows.iter().map(|r| r.score).collect();
    assert_eq!(kept, probabilities);
    assert_ne!(
        kept,
        score_tracks(&art, &[cold])
            .rows
            .iter()
            .map(|r| r.score)
            .collect::<Vec<_>>()
    );
    let rows = evaluate_tracks(&art, std::slice::from_ref(&track), EventRules::Spec).rows;
    assert_eq!(rows.first().map(|r| r.line), Some(track.records[100].line));
    // The loss never sees them.
    let normal: Vec<Track> = (0..2).map(|s| drive(s, 400.0)).collect();
    let fit = fit_evidence(
        &normal,
        Projection::Wgs84Local,
        0.0,
        0.98,
        FeatureSchema::V3,
    )
    .expect("fits");
    let sequence = &sequences(&fit, std::slice::from_ref(&track), true)[0];
    assert!(sequence.valid[..100].iter().all(|v| !v));
    assert!(sequence.valid[100..].iter().any(|&v| v));
}

#[test]
fn a_small_training_job_learns_a_frozen_position_attack_and_calibrates_an_operating_point() {
    let frozen = |seed| attacked_with(seed, AttackKind::FrozenPosition);
    let train: Vec<Track> = (20..24).map(frozen).collect();
    let validation: Vec<Track> = (30..32).map(frozen).collect();
    let spec = TrainingSpec {
        // The v2 evidence and its persistence N_p: these 400 s drives are attacked too early for the
        // offset anchors of the default schema.
        model: ModelConfig {
            d_s: 8,
            d_zeta: 8,
            d_h: 8,
            schema: FeatureSchema::V2,
            ..ModelConfig::default()
        },
        train: TrainConfig {
            max_epochs: 30,
            ..TrainConfig::default()
        },
        ..TrainingSpec::default()
    };
    let data = || TrainingData::Explicit {
        train: train.clone(),
        validation: validation.clone(),
    };
    let mut epochs = 0;
    let trained = train_detector(&spec, data(), &mut |_| epochs += 1, &AtomicBool::new(false))
        .expect("trains");
    assert_eq!(epochs, trained.history.len());
    // Cancelled, it ends as a cancellation without searching for an operating point.
    let cancelled = train_detector(&spec, data(), &mut |_| {}, &AtomicBool::new(true));
    assert!(
        matches!(
            cancelled,
            Err(TrainDetectorError::Train(TrainError::Cancelled))
        ),
        "{cancelled:?}"
    );
    let auroc = trained.validation.auroc.expect("both classes");
    assert!(auroc > 0.8, "validation AUROC {auroc}");
    let op = trained.artifact.operating_point;
    assert!(op.theta > 0.0 && op.theta < 1.0 && (1..=10).contains(&op.n_p));
    // The whole fit is reproducible.
    let again =
        train_detector(&spec, data(), &mut |_| {}, &AtomicBool::new(false)).expect("trains");
    assert_eq!(again.artifact.model, trained.artifact.model);
    let fit =
        fit_evidence(&train, Projection::Wgs84Local, 0.0, 0.98, FeatureSchema::V2).expect("fits");
    assert_eq!(sequences(&fit, &train, true).len(), train.len());
}

/// A small v3 detector trained for 2 epochs on 200 m jumps and a clean drive long enough for the
/// anchors' fit (three follow times after placement).
fn small_v3_detector(ablation: Ablation, anchor_rebase: AnchorRebase) -> ModelArtifact {
    let jump = |seed| attacked_with(seed, AttackKind::Jump { offset_m: 200.0 });
    let spec = TrainingSpec {
        model: ModelConfig {
            d_s: 4,
            d_zeta: 4,
            d_h: 4,
            schema: FeatureSchema::V3,
            ablation,
            ..ModelConfig::default()
        },
        train: TrainConfig {
            max_epochs: 2,
            ..TrainConfig::default()
        },
        anchor_rebase,
        ..TrainingSpec::default()
    };
    let data = TrainingData::Explicit {
        train: (40..43).map(jump).chain([drive(44, 900.0)]).collect(),
        validation: (50..52).map(jump).collect(),
    };
    train_detector(&spec, data, &mut |_| {}, &AtomicBool::new(false))
        .expect("trains")
        .artifact
}

#[test]
fn the_levels_and_lifecycle_ablations_train_what_they_name() {
    let trained = |ablation: Ablation| small_v3_detector(ablation, AnchorRebase::Off);
    let levels = |artifact: &ModelArtifact| {
        let evidence = &artifact.evidence;
        (
            evidence
                .drift
                .expect("v3 has drift channels")
                .vehicle_levels,
            evidence.offset.expect("v3 has offsets").vehicle_levels,
        )
    };
    let full = trained(Ablation::default());
    assert!(full.lifecycle.is_some());
    assert_eq!(levels(&full), (true, true));
    let ablated = trained(Ablation {
        no_vehicle_levels: true,
        rows_lifecycle: true,
        ..Ablation::default()
    });
    assert_eq!(ablated.lifecycle, None);
    assert!((1..=10).contains(&ablated.operating_point.n_p));
    assert_eq!(levels(&ablated), (false, false));
    // The ablations travel with the artifact.
    let bytes = ablated.to_vec().expect("serialises");
    let read = ModelArtifact::from_slice(&bytes).expect("parses");
    assert!(read.model.config().ablation.rows_lifecycle);
    assert!(read.model.config().ablation.no_vehicle_levels);
}

#[test]
fn anchor_rebase_served_only_keeps_the_training_and_marks_the_artifact() {
    let trained = |anchor_rebase| small_v3_detector(Ablation::default(), anchor_rebase);
    let rebases = |artifact: &ModelArtifact| {
        artifact
            .evidence
            .offset
            .expect("v3 has offsets")
            .rebase_on_calibration
    };
    let off = trained(AnchorRebase::Off);
    let served = trained(AnchorRebase::Serve);
    let throughout = trained(AnchorRebase::TrainAndServe);
    let margin = trained(AnchorRebase::Margin);
    assert!(!rebases(&off));
    assert!(rebases(&served) && rebases(&throughout) && rebases(&margin));
    // As a margin, the operating point is the one chosen without it: only the evidence's switch
    // differs from the model trained without it.
    let mut margin_off = margin.clone();
    margin_off.set_anchor_rebasing(false);
    assert_eq!(margin_off.model, off.model);
    assert_eq!(margin_off.operating_point, off.operating_point);
    assert_eq!(margin_off.lifecycle, off.lifecycle);
    assert_eq!(margin_off.evidence, off.evidence);
    // Served only, the network and its scaler are those trained without it.
    assert_eq!(served.model, off.model);
    assert_eq!(served.scaler, off.scaler);
    // An artifact without it keeps the bytes it had before the option existed; with it, the option
    // travels with the artifact.
    let off_json = String::from_utf8(off.to_vec().expect("serialises")).expect("utf-8");
    assert!(!off_json.contains("rebase_on_calibration"));
    let read = ModelArtifact::from_slice(&served.to_vec().expect("serialises")).expect("parses");
    assert!(rebases(&read));
}
