//! Every detection and every alarm says why: a `v3` model's detections carry an explanation, a
//! 500 m jump's alarm opens as a JUMP with an offset of about 500 m toward the jump's direction,
//! and ListAlarms and WatchAlarms return that explanation from the database, also after a restart.
//!
//! No `v3` model is bundled, so the test imports an untrained one (evidence fitted on normal
//! drives, random weights, a lifecycle that opens on a decisive offset): what is under test is
//! the explanation's path through the server, not the model's skill.

use std::time::Duration;

use spoofwatch_core::alarm::OperatingPoint;
use spoofwatch_core::evidence::FeatureSchema;
use spoofwatch_core::evidence::fit_evidence;
use spoofwatch_core::geo::Projection;
use spoofwatch_core::lifecycle::Lifecycle;
use spoofwatch_core::model::artifact::{ARTIFACT_SCHEMA_VERSION, ModelArtifact, Provenance};
use spoofwatch_core::model::{Model, ModelConfig};
use spoofwatch_core::scenario::AttackKind;
use spoofwatch_proto::v1;
use spoofwatch_tests::{
    Clients, TestServer, attacked_drive, import_model, listed_alarms, normal_drive,
    replayed_alarm_events, start_server, start_stream, test_config, track_samples,
};

const VEHICLE: &str = "jumper";
/// The jump: 500 m toward 45° (the direction `attacked_drive` uses), from 200 s for 150 s.
const JUMP_M: f64 = 500.0;
const ATTACK_ONSET_S: f64 = 200.0;

/// An untrained `v3` artifact: the evidence fitted on two normal drives, random weights, θ so high
/// the model itself never alarms, and a lifecycle that opens on an offset held 2 s beyond the
/// decisive gate.
fn untrained_v3_artifact() -> Vec<u8> {
    let normal = [
        normal_drive("sim0", 400.0, 0),
        normal_drive("sim1", 400.0, 1),
    ];
    let schema = FeatureSchema::V3;
    let fit = fit_evidence(&normal, Projection::Wgs84Local, 0.0, 0.98, schema)
        .expect("enough normal rows");
    let config = ModelConfig {
        schema,
        ..ModelConfig::default()
    };
    let artifact = ModelArtifact {
        schema_version: ARTIFACT_SCHEMA_VERSION,
        feature_names: ModelArtifact::feature_names_of(schema),
        model: Model::init(config, 7).expect("a valid config"),
        evidence: fit.params,
        scaler: fit.scaler,
        operating_point: OperatingPoint {
            theta: 0.999_999,
            n_p: 3,
        },
        lifecycle: Some(Lifecycle {
            on_s: 2.0,
            off_s: 5.0,
            decisive_s: 2.0,
        }),
        critical: None,
        provenance: Provenance::default(),
    };
    artifact.to_vec().expect("the artifact is valid")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_jump_alarm_says_jump_with_its_offset_also_after_a_restart() {
    let (dir, server, mut clients) = start_server(|_| {}).await;
    let model = import_model(&mut clients, untrained_v3_artifact(), "untrained v3").await;
    let jump = AttackKind::Jump { offset_m: JUMP_M };
    let track = attacked_drive(VEHICLE, 400.0, 31, jump, ATTACK_ONSET_S, 150.0);
    let (mut stream, _) = start_stream(&clients, VEHICLE, &model.name).await;
    let mut detections = Vec::new();
    for (seq, batch) in track_samples(&track).chunks(50).enumerate() {
        detections.extend(
            stream
                .detect(seq as u64 + 1, batch.to_vec())
                .await
                .expect("one detection per sample"),
        );
    }
    drop(stream);

    assert!(
        detections.iter().all(|d| d.why.is_some()),
        "every detection carries its explanation"
    );
    let onsets: Vec<&v1::Detection> = detections.iter().filter(|d| d.alarm_onset).collect();
    let first = *onsets.first().expect("the jump raises an alarm");
    assert!(
        (ATTACK_ONSET_S..ATTACK_ONSET_S + 10.0).contains(&first.timestamp_s),
        "the first alarm opens soon after the jump, at {} s",
        first.timestamp_s
    );
    let why = first.why.expect("explained");
    assert_eq!(why.dominant(), v1::EvidenceKind::Jump, "{why:?}");
    assert!(
        (why.offset_m - JUMP_M).abs() < 0.1 * JUMP_M,
        "the offset is about the jump's {JUMP_M} m: {why:?}"
    );
    assert!(
        (why.offset_bearing_deg - 45.0).abs() < 10.0,
        "toward the jump's direction: {why:?}"
    );
    let onset_evidence = first.evidence.as_ref().expect("evidence");
    let offset = onset_evidence.offset.as_ref().expect("v3 offset evidence");
    // The explanation gives the held jump (GNSS against dead reckoning from the fix before it); the
    // slow anchor, frozen at that fix, holds the same plus the little it had followed before.
    let apart = (offset.offset_east_m - why.offset_east_m)
        .hypot(offset.offset_north_m - why.offset_north_m);
    assert!(
        apart < 5.0,
        "the explanation's offset is the held jump's, {apart} m from the slow anchor's: {why:?}"
    );
    assert!(offset.arrived_by_step && offset.nis_slow.max(offset.nis_fast) >= 25.0);
    assert!(
        onset_evidence.drift.is_some(),
        "v3 includes the drift channels"
    );

    // The alarm is stored in the background: wait until it is listed.
    let mut stored = Vec::new();
    for _ in 0..600 {
        stored = listed_alarms(&mut clients, VEHICLE, 0).await;
        if stored
            .iter()
            .any(|a| a.onset_timestamp_s == first.timestamp_s)
        {
            break;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let alarm = stored
        .iter()
        .find(|a| a.onset_timestamp_s == first.timestamp_s)
        .expect("the alarm is stored");
    assert_eq!(
        alarm.why.as_ref(),
        Some(&why),
        "the stored alarm says what its onset said"
    );
    let replayed = replayed_alarm_events(&mut clients, VEHICLE, 0).await;
    assert!(
        replayed
            .iter()
            .filter(|e| e.alarm.as_ref().map(|a| a.id) == Some(alarm.id))
            .all(|e| e.alarm.as_ref().and_then(|a| a.why.as_ref()) == Some(&why)),
        "WatchAlarms carries it on the onset and on the end: {replayed:?}"
    );
    drop(clients);
    server.stop().await;

    let server = TestServer::start(test_config(dir.path())).await;
    let mut clients = Clients::of(&server).await;
    let after = listed_alarms(&mut clients, VEHICLE, 0).await;
    let restored = after
        .iter()
        .find(|a| a.id == alarm.id)
        .expect("the alarm is still listed");
    assert_eq!(
        restored.why.as_ref(),
        Some(&why),
        "the explanation survives a restart"
    );
    assert!(
        replayed_alarm_events(&mut clients, VEHICLE, 0)
            .await
            .iter()
            .any(|e| e.alarm.as_ref().and_then(|a| a.why.as_ref()) == Some(&why))
    );
    drop(clients);
    server.stop().await;
}
