//! Alarm severities end to end: on a model with a critical level, a large jump gives detections
//! whose severity turns CRITICAL and one alarm (never two) whose events are its onset (a warning,
//! or critical at once), its escalation when it opened as a warning (a drift does), and its end,
//! critical;
//! ListAlarms and WatchAlarms filtered by CRITICAL return it, and an unknown severity filter is
//! INVALID_ARGUMENT naming `severity`. An alarm held over a session hand-off keeps its severity
//! and escalation. A model without a critical level (the bundled model without its own, as every
//! model made before severities existed) raises warnings only, and says so (Model.critical is
//! absent).
//!
//! The critical level under test is the bundled model with a made-up critical test in place of its
//! own ([`spoofwatch_tests::TEST_CRITICAL`]): the server's path is under test, not the test's
//! choice.

use std::time::Duration;

use spoofwatch_core::scenario::AttackKind;
use spoofwatch_proto::v1;
use spoofwatch_tests::{
    Clients, TEST_CRITICAL, TestServer, artifact_with_critical_level,
    artifact_without_critical_level, attacked_drive, import_model, listed_alarms,
    replayed_alarm_events, start_server, start_stream, stream_batches, test_config, track_samples,
};
use tonic::Code;
use tonic_types::StatusExt;

const WARNING: i32 = v1::AlarmSeverity::Warning as i32;
const CRITICAL: i32 = v1::AlarmSeverity::Critical as i32;
const ONSET: i32 = v1::AlarmEventKind::Onset as i32;
const ESCALATED: i32 = v1::AlarmEventKind::Escalated as i32;
const END: i32 = v1::AlarmEventKind::End as i32;

/// A 300 s drive attacked by `attack` from 100 s for 120 s, through `model`, 50 samples per
/// batch; the detections.
async fn stream_attack(
    clients: &Clients,
    vehicle: &str,
    model: &str,
    attack: AttackKind,
) -> Vec<v1::Detection> {
    let track = attacked_drive(vehicle, 300.0, 41, attack, 100.0, 120.0);
    let (mut stream, _) = start_stream(clients, vehicle, model).await;
    let mut detections = Vec::new();
    for (seq, batch) in track_samples(&track).chunks(50).enumerate() {
        detections.extend(
            stream
                .detect(seq as u64 + 1, batch.to_vec())
                .await
                .expect("one detection per sample"),
        );
    }
    stream.finish().await.expect("the stream ends with OK");
    detections
}

/// Every stored event of `vehicle` of at least `severity`, replayed from the start, as (kind,
/// alarm id, alarm severity).
async fn watched(clients: &mut Clients, vehicle: &str, severity: i32) -> Vec<(i32, i64, i32)> {
    let events = replayed_alarm_events(clients, vehicle, severity).await;
    events
        .into_iter()
        .map(|event| {
            let alarm = event.alarm.expect("an alarm event carries its alarm");
            (event.kind, alarm.id, alarm.severity)
        })
        .collect()
}

/// The stored alarms of `vehicle` once every one has ended (they are stored in the background;
/// polled every 50 ms, failing after 30 s: a hang guard, not a timing assertion).
async fn ended_alarms(clients: &mut Clients, vehicle: &str) -> Vec<v1::Alarm> {
    for _ in 0..600 {
        let alarms = listed_alarms(clients, vehicle, 0).await;
        if !alarms.is_empty() && alarms.iter().all(|a| !a.open) {
            return alarms;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    panic!("the alarms of {vehicle} were not stored as ended");
}

/// The detections' severities are those of one episode: UNSPECIFIED while no alarm is on, set
/// while one is, never falling within an episode; returns the episodes' (onset, escalation)
/// sample times.
fn episodes(detections: &[v1::Detection]) -> Vec<(f64, Option<f64>)> {
    let mut episodes: Vec<(f64, Option<f64>)> = Vec::new();
    let mut previous = 0;
    for d in detections {
        assert_eq!(
            d.alarm,
            d.severity != v1::AlarmSeverity::Unspecified as i32,
            "a severity exactly while the alarm is on, at {} s",
            d.timestamp_s
        );
        if d.alarm_onset {
            episodes.push((d.timestamp_s, None));
            previous = 0;
        }
        assert!(
            !d.alarm || d.severity >= previous,
            "the severity never falls within an episode, at {} s",
            d.timestamp_s
        );
        if d.alarm_escalated {
            assert_eq!(d.severity, CRITICAL, "an escalation is critical");
            let open = episodes.last_mut().expect("an escalation is in an episode");
            assert_eq!(open.1, None, "one escalation per episode");
            open.1 = Some(d.timestamp_s);
        }
        if d.severity == CRITICAL {
            assert!(
                episodes.last().is_some_and(|e| e.1.is_some()),
                "critical only after the escalation, at {} s",
                d.timestamp_s
            );
        }
        previous = if d.alarm { d.severity } else { 0 };
    }
    episodes
}

/// The one alarm of `vehicle` whose onset the detections show in `window` (s), checked against
/// the detections and the stored events: critical, escalated when the detections say, its events
/// the onset (critical at once, or a warning and then the escalation) and the end, critical; and
/// WatchAlarms filtered by CRITICAL sends exactly those that page. Returns (opened critical?).
async fn check_the_alarm_that_turned_critical(
    clients: &mut Clients,
    vehicle: &str,
    detections: &[v1::Detection],
    window: std::ops::Range<f64>,
) -> bool {
    let episodes = episodes(detections);
    let in_window: Vec<_> = episodes
        .iter()
        .filter(|(onset, _)| window.contains(onset))
        .collect();
    assert_eq!(in_window.len(), 1, "one alarm opens: {episodes:?}");
    let (onset_s, escalated_s) = *in_window[0];
    let escalated_s = escalated_s.expect("the alarm turns critical");

    let alarms = ended_alarms(clients, vehicle).await;
    let alarm = alarms
        .iter()
        .find(|a| a.onset_timestamp_s == onset_s)
        .expect("the alarm is stored");
    assert_eq!(alarm.severity, CRITICAL);
    assert_eq!(alarm.escalated_timestamp_s, Some(escalated_s));
    assert!(alarm.escalated_time.is_some());

    let of_alarm = |events: Vec<(i32, i64, i32)>| -> Vec<(i32, i64, i32)> {
        events.into_iter().filter(|e| e.1 == alarm.id).collect()
    };
    let opened_critical = escalated_s == onset_s;
    let expected = if opened_critical {
        vec![(ONSET, alarm.id, CRITICAL), (END, alarm.id, CRITICAL)]
    } else {
        vec![
            (ONSET, alarm.id, WARNING),
            (ESCALATED, alarm.id, CRITICAL),
            (END, alarm.id, CRITICAL),
        ]
    };
    assert_eq!(of_alarm(watched(clients, vehicle, 0).await), expected);
    // What pages: a critical onset, or the escalation; and the end.
    assert_eq!(
        of_alarm(watched(clients, vehicle, CRITICAL).await),
        expected[expected.len() - 2..]
    );
    let critical_alarms = listed_alarms(clients, vehicle, CRITICAL).await;
    assert!(critical_alarms.iter().all(|a| a.severity == CRITICAL));
    assert!(critical_alarms.iter().any(|a| a.id == alarm.id));
    let warnings = alarms.iter().filter(|a| a.severity == WARNING).count();
    assert_eq!(critical_alarms.len() + warnings, alarms.len());
    opened_critical
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn on_a_model_with_a_critical_level_an_alarm_turns_critical_as_one_alarm() {
    let (_dir, server, mut clients) = start_server(|_| {}).await;
    let model = import_model(&mut clients, artifact_with_critical_level(), "paging").await;
    let critical = model.critical.expect("the model lists its critical level");
    assert_eq!(
        (critical.reference_logit, critical.threshold),
        (TEST_CRITICAL.reference_logit, TEST_CRITICAL.threshold)
    );
    assert_eq!(
        (critical.gate, critical.decisive_s),
        (TEST_CRITICAL.gate, TEST_CRITICAL.decisive_s)
    );

    // A 500 m jump is decisive: critical within 10 s of the jump (here at the onset itself).
    let jump = AttackKind::Jump { offset_m: 500.0 };
    let detections = stream_attack(&clients, "jumper", &model.name, jump).await;
    check_the_alarm_that_turned_critical(&mut clients, "jumper", &detections, 100.0..110.0).await;
    let turned = detections.iter().find(|d| d.alarm_escalated);
    assert!(turned.is_some_and(|d| d.timestamp_s < 110.0));

    // A 2 m/s drift opens as a warning and turns critical as its evidence grows: one alarm,
    // escalated.
    let drift = AttackKind::RampDrift { velocity_mps: 2.0 };
    let detections = stream_attack(&clients, "drifter", &model.name, drift).await;
    let opened_critical =
        check_the_alarm_that_turned_critical(&mut clients, "drifter", &detections, 100.0..130.0)
            .await;
    assert!(!opened_critical, "the drift's alarm opens as a warning");

    // An unknown severity is refused, naming the field.
    for refused in [
        clients
            .alarms
            .list_alarms(v1::ListAlarmsRequest {
                severity: 7,
                ..Default::default()
            })
            .await
            .expect_err("an unknown severity"),
        clients
            .alarms
            .watch_alarms(v1::WatchAlarmsRequest {
                severity: -1,
                ..Default::default()
            })
            .await
            .expect_err("an unknown severity"),
    ] {
        assert_eq!(refused.code(), Code::InvalidArgument);
        let fields: Vec<_> = refused
            .get_details_bad_request()
            .expect("BadRequest details")
            .field_violations
            .into_iter()
            .map(|v| v.field)
            .collect();
        assert_eq!(fields, ["severity"]);
    }

    drop(clients);
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_alarm_held_over_a_hand_off_keeps_its_severity_and_escalation() {
    let vehicle = "handed-over";
    let drift = AttackKind::RampDrift { velocity_mps: 2.0 };
    let track = attacked_drive(vehicle, 300.0, 41, drift, 100.0, 120.0);
    let batches: Vec<Vec<v1::Sample>> = track_samples(&track)
        .chunks(10)
        .map(<[v1::Sample]>::to_vec)
        .collect();
    let cut = 20; // batches: 200 s, inside the drift, after its alarm turned critical

    let dir = tempfile::tempdir().expect("temp dir");
    let first = TestServer::start(test_config(dir.path())).await;
    let mut clients = Clients::of(&first).await;
    let model = import_model(&mut clients, artifact_with_critical_level(), "paging").await;
    let on = (vehicle, model.name.as_str());
    let (_, before) = stream_batches(&clients, on, &batches[..cut], 1).await;
    let last = before.last().expect("detections");
    assert_eq!(
        (last.alarm, last.severity),
        (true, CRITICAL),
        "the alarm is critical at the cut"
    );
    let escalated_s = before
        .iter()
        .find(|d| d.alarm_escalated)
        .map(|d| d.timestamp_s);
    assert!(
        before
            .iter()
            .any(|d| d.alarm_onset && d.severity == WARNING),
        "it opened as a warning"
    );
    drop(clients);
    first.stop().await;

    // The next server on the database continues the session, and the alarm, from the snapshot.
    let second = TestServer::start(test_config(dir.path())).await;
    let mut clients = Clients::of(&second).await;
    let (accepted, after) = stream_batches(&clients, on, &batches[cut..], cut as u64 + 1).await;
    assert!(accepted.from_snapshot, "{accepted:?}");
    let first_after = after.first().expect("detections");
    assert_eq!((first_after.alarm, first_after.severity), (true, CRITICAL));
    assert!(
        after
            .iter()
            .take_while(|d| d.alarm)
            .all(|d| !d.alarm_onset && !d.alarm_escalated && d.severity == CRITICAL),
        "the alarm held over goes on, critical: no second onset, no second escalation"
    );

    let alarms = ended_alarms(&mut clients, vehicle).await;
    let alarm = &alarms[0];
    assert_eq!(
        (alarm.severity, alarm.escalated_timestamp_s),
        (CRITICAL, escalated_s)
    );
    let events: Vec<_> = watched(&mut clients, vehicle, 0)
        .await
        .into_iter()
        .filter(|e| e.1 == alarm.id)
        .collect();
    assert_eq!(
        events,
        [
            (ONSET, alarm.id, WARNING),
            (ESCALATED, alarm.id, CRITICAL),
            (END, alarm.id, CRITICAL)
        ]
    );
    drop(clients);
    second.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_model_without_a_critical_level_raises_warnings_only() {
    let (_dir, server, mut clients) = start_server(|_| {}).await;
    let default = clients
        .models
        .get_model(v1::GetModelRequest {
            name: "models/default".to_string(),
        })
        .await
        .expect("GetModel")
        .into_inner();
    assert!(
        default.critical.is_some(),
        "the bundled model has a critical level"
    );
    let older = import_model(&mut clients, artifact_without_critical_level(), "older").await;
    assert_eq!(older.critical, None, "imported without a critical level");

    let jump = AttackKind::Jump { offset_m: 500.0 };
    let detections = stream_attack(&clients, "warned", &older.name, jump).await;
    let episodes = episodes(&detections);
    assert!(!episodes.is_empty(), "the jump raises an alarm");
    assert!(episodes.iter().all(|(_, escalated)| escalated.is_none()));
    assert!(detections.iter().all(|d| !d.alarm || d.severity == WARNING));

    let alarms = ended_alarms(&mut clients, "warned").await;
    assert_eq!(alarms.len(), episodes.len());
    assert!(
        alarms
            .iter()
            .all(|a| a.severity == WARNING && a.escalated_timestamp_s.is_none())
    );
    assert!(
        listed_alarms(&mut clients, "warned", CRITICAL)
            .await
            .is_empty()
    );
    assert!(watched(&mut clients, "warned", CRITICAL).await.is_empty());
    let events = watched(&mut clients, "warned", WARNING).await;
    assert_eq!(events.len(), 2 * alarms.len(), "an onset and an end each");
    assert!(
        events
            .iter()
            .all(|&(kind, _, severity)| kind != ESCALATED && severity == WARNING)
    );

    drop(clients);
    server.stop().await;
}
