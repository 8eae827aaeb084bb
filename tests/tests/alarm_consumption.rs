//! Alarms out: replayed drives with a frozen GNSS fix raise alarms that ListAlarms lists
//! with each filter and page by page, and that WatchAlarms streams live; a watcher that reconnects
//! with its last cursor gets exactly the events it missed, also across a server restart on the same
//! database; invalid filters are refused field by field; the service needs the token like the
//! others.

use std::sync::{Arc, Mutex};
use std::time::Duration;

use prost_types::Timestamp;
use spoofwatch_client::{AlarmWatch, WatchOptions};
use spoofwatch_core::scenario::AttackKind;
use spoofwatch_proto::v1;
use spoofwatch_tests::{
    Clients, Episode, REPLY_TIMEOUT, ServingStatus, TestServer, attacked_drive, health_of,
    start_server, start_stream, stream_frozen_fix_drive, test_config, track_samples,
};
use tonic::Code;
use tonic_types::StatusExt;

const ONSET: i32 = v1::AlarmEventKind::Onset as i32;
const END: i32 = v1::AlarmEventKind::End as i32;
const CAUGHT_UP: i32 = v1::AlarmEventKind::CaughtUp as i32;

/// A watch that reconnects for up to a minute.
fn watch(clients: &Clients, vehicle_id: &str, after_cursor: Option<i64>) -> AlarmWatch {
    AlarmWatch::new(
        clients.connection.clone(),
        WatchOptions {
            vehicle_id: vehicle_id.to_string(),
            after_cursor,
            reconnect_for: Duration::from_secs(60),
            ..WatchOptions::default()
        },
    )
}

async fn next_event(watch: &mut AlarmWatch) -> v1::AlarmEvent {
    tokio::time::timeout(REPLY_TIMEOUT, watch.next())
        .await
        .expect("an alarm event within the reply timeout")
        .expect("the watch goes on")
}

/// The next `n` onsets and ends (CAUGHT_UP events are skipped).
async fn alarm_events(watch: &mut AlarmWatch, n: usize) -> Vec<v1::AlarmEvent> {
    let mut events = Vec::new();
    while events.len() < n {
        let event = next_event(watch).await;
        if event.kind != CAUGHT_UP {
            events.push(event);
        }
    }
    events
}

/// The events up to the next CAUGHT_UP (which is left out).
async fn until_caught_up(watch: &mut AlarmWatch) -> Vec<v1::AlarmEvent> {
    let mut events = Vec::new();
    loop {
        let event = next_event(watch).await;
        if event.kind == CAUGHT_UP {
            return events;
        }
        events.push(event);
    }
}

/// Every event stored so far: a watch after cursor 0 that stops when caught up (CAUGHT_UP is
/// left out).
async fn history(clients: &Clients, vehicle_id: &str) -> Vec<v1::AlarmEvent> {
    let request = v1::WatchAlarmsRequest {
        vehicle_id: vehicle_id.to_string(),
        after_cursor: Some(0),
        stop_when_caught_up: true,
        ..Default::default()
    };
    let mut stream = clients
        .alarms
        .clone()
        .watch_alarms(request)
        .await
        .expect("WatchAlarms works")
        .into_inner();
    let mut events = Vec::new();
    while let Some(event) = tokio::time::timeout(REPLY_TIMEOUT, stream.message())
        .await
        .expect("an event within the reply timeout")
        .expect("the watch ends with OK")
    {
        events.push(event);
    }
    let last = events.pop().expect("at least CAUGHT_UP");
    assert_eq!(last.kind, CAUGHT_UP, "the call ends right after CAUGHT_UP");
    events
}

/// Checks that `events` are the onset and end of each episode, in order.
fn assert_events_match(events: &[v1::AlarmEvent], vehicle_id: &str, episodes: &[Episode]) {
    assert_eq!(events.len(), 2 * episodes.len(), "{events:?}");
    for (pair, episode) in events.chunks(2).zip(episodes) {
        let (onset, end) = (&pair[0], &pair[1]);
        assert_eq!((onset.kind, end.kind), (ONSET, END));
        assert!(onset.cursor < end.cursor);
        let opened = onset.alarm.as_ref().expect("an onset carries its alarm");
        let closed = end.alarm.as_ref().expect("an end carries its alarm");
        assert_eq!(opened.id, closed.id);
        assert_eq!(opened.vehicle_id, vehicle_id);
        assert_eq!(opened.model, "models/default");
        assert_eq!(opened.onset_timestamp_s, episode.onset_s);
        assert!(opened.open && opened.end_time.is_none() && opened.end_timestamp_s.is_none());
        assert_eq!(opened.samples, 1);
        assert_eq!(closed.onset_timestamp_s, episode.onset_s);
        assert_eq!(closed.end_timestamp_s, Some(episode.last_s));
        assert_eq!(closed.peak_probability, episode.peak);
        assert_eq!(closed.samples, episode.samples as u64);
        assert!(!closed.open && closed.end_time.is_some());
        assert_eq!(closed.onset_time, opened.onset_time);
    }
}

/// The alarms a ListAlarms request returns, every page of `page_size`.
async fn list_all(clients: &mut Clients, request: v1::ListAlarmsRequest) -> Vec<v1::Alarm> {
    let mut request = v1::ListAlarmsRequest {
        page_size: request.page_size,
        ..request
    };
    let mut alarms = Vec::new();
    loop {
        let page = clients
            .alarms
            .list_alarms(request.clone())
            .await
            .expect("ListAlarms works")
            .into_inner();
        alarms.extend(page.alarms);
        if page.next_page_token.is_empty() {
            return alarms;
        }
        request.page_token = page.next_page_token;
    }
}

/// Polls ListAlarms until `count` closed alarms are stored (the writer stores in the background);
/// panics after 30 s.
async fn wait_until_stored(clients: &mut Clients, count: usize) {
    let closed = v1::ListAlarmsRequest {
        state: v1::AlarmStateFilter::Closed as i32,
        ..v1::ListAlarmsRequest::default()
    };
    for _ in 0..600 {
        if list_all(clients, closed.clone()).await.len() == count {
            return;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    panic!("{count} closed alarms were never listed");
}

/// The fields a refusal's BadRequest names.
fn violated_fields(status: &tonic::Status) -> Vec<String> {
    status
        .get_details_bad_request()
        .expect("BadRequest details")
        .field_violations
        .into_iter()
        .map(|v| v.field)
        .collect()
}

fn ids(alarms: &[v1::Alarm]) -> Vec<i64> {
    alarms.iter().map(|a| a.id).collect()
}

fn at(seconds: i64) -> Option<Timestamp> {
    Some(Timestamp { seconds, nanos: 0 })
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn alarms_are_watched_live_and_listed_with_each_filter_and_page() {
    let (_dir, server, mut clients) = start_server(|_| {}).await;
    assert_eq!(
        health_of(&server, "spoofwatch.v1.AlarmService").await,
        ServingStatus::Serving
    );
    let mut live = watch(&clients, "", None);
    let start = next_event(&mut live).await;
    assert_eq!(
        start.kind, CAUGHT_UP,
        "a watch without a cursor starts caught up"
    );
    assert!(start.alarm.is_none());
    let mut only_b = watch(&clients, "frozen-b", None);
    assert_eq!(next_event(&mut only_b).await.kind, CAUGHT_UP);

    let episodes_a = stream_frozen_fix_drive(&clients, "frozen-a").await;
    assert!(!episodes_a.is_empty(), "a frozen fix raises an alarm");
    let seen_a = alarm_events(&mut live, 2 * episodes_a.len()).await;
    assert_events_match(&seen_a, "frozen-a", &episodes_a);
    let episodes_b = stream_frozen_fix_drive(&clients, "frozen-b").await;
    let seen_b = alarm_events(&mut live, 2 * episodes_b.len()).await;
    assert_events_match(&seen_b, "frozen-b", &episodes_b);
    assert!(seen_a.last().unwrap().cursor < seen_b[0].cursor);
    let filtered = alarm_events(&mut only_b, 2 * episodes_b.len()).await;
    assert_eq!(filtered, seen_b, "a vehicle's watch gets its events only");
    // Stored history replays exactly what was seen live.
    let everything: Vec<_> = seen_a.iter().chain(&seen_b).cloned().collect();
    let total = episodes_a.len() + episodes_b.len();
    wait_until_stored(&mut clients, total).await;
    assert_eq!(history(&clients, "").await, everything);
    assert_eq!(history(&clients, "frozen-b").await, seen_b);

    let all = list_all(&mut clients, v1::ListAlarmsRequest::default()).await;
    let ended: Vec<v1::Alarm> = everything
        .iter()
        .filter(|e| e.kind == END)
        .map(|e| e.alarm.clone().unwrap())
        .collect();
    assert_eq!(
        all, ended,
        "the stored alarms, in id order, as their ends showed them"
    );
    for page_size in [1, 2] {
        let paged = list_all(
            &mut clients,
            v1::ListAlarmsRequest {
                page_size,
                ..v1::ListAlarmsRequest::default()
            },
        )
        .await;
        assert_eq!(paged, all, "pages of {page_size} add up to the listing");
    }
    let listed = async |clients: &mut Clients, request: v1::ListAlarmsRequest| {
        ids(&list_all(clients, request).await)
    };
    let of = |vehicle: &str| {
        ids(&all
            .iter()
            .filter(|a| a.vehicle_id == vehicle)
            .cloned()
            .collect::<Vec<_>>())
    };
    let request = v1::ListAlarmsRequest::default;
    let vehicle = |v: &str| v1::ListAlarmsRequest {
        vehicle_id: v.to_string(),
        ..request()
    };
    assert_eq!(
        listed(&mut clients, vehicle("frozen-a")).await,
        of("frozen-a")
    );
    assert_eq!(
        listed(&mut clients, vehicle("frozen-b")).await,
        of("frozen-b")
    );
    assert!(listed(&mut clients, vehicle("nobody")).await.is_empty());
    for (model, expected) in [
        ("models/default", ids(&all)),
        ("default", ids(&all)),
        ("other", vec![]),
    ] {
        let request = v1::ListAlarmsRequest {
            model: model.to_string(),
            ..request()
        };
        assert_eq!(listed(&mut clients, request).await, expected, "{model}");
    }
    for (state, expected) in [
        (v1::AlarmStateFilter::Closed, ids(&all)),
        (v1::AlarmStateFilter::Open, vec![]),
    ] {
        let request = v1::ListAlarmsRequest {
            state: state as i32,
            ..request()
        };
        assert_eq!(listed(&mut clients, request).await, expected, "{state:?}");
    }
    // Onset times: from the first one (inclusive) to just after the last one.
    let first = all[0].onset_time.unwrap();
    let last = all.last().unwrap().onset_time.unwrap();
    let window = |after: Option<Timestamp>, before: Option<Timestamp>| v1::ListAlarmsRequest {
        onset_after: after,
        onset_before: before,
        ..request()
    };
    assert_eq!(
        listed(&mut clients, window(Some(first), at(last.seconds + 1))).await,
        ids(&all)
    );
    assert!(
        listed(&mut clients, window(at(last.seconds + 1), None))
            .await
            .is_empty()
    );
    assert!(
        listed(&mut clients, window(None, Some(first)))
            .await
            .is_empty(),
        "the end of the window is exclusive"
    );

    drop((live, only_b, clients));
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn invalid_filters_and_cursors_are_refused_field_by_field() {
    let (_dir, server, mut clients) = start_server(|_| {}).await;
    let request = v1::ListAlarmsRequest::default;
    let cases = [
        (
            v1::ListAlarmsRequest {
                vehicle_id: "no spaces".into(),
                ..request()
            },
            "vehicle_id",
        ),
        (
            v1::ListAlarmsRequest {
                model: "datasets/x".into(),
                ..request()
            },
            "model",
        ),
        (
            v1::ListAlarmsRequest {
                onset_after: at(100),
                onset_before: at(100),
                ..request()
            },
            "onset_before",
        ),
        (
            v1::ListAlarmsRequest {
                onset_after: Some(Timestamp {
                    seconds: 1,
                    nanos: -1,
                }),
                ..request()
            },
            "onset_after.nanos",
        ),
        (
            v1::ListAlarmsRequest {
                onset_before: at(i64::MAX),
                ..request()
            },
            "onset_before.seconds",
        ),
        (
            v1::ListAlarmsRequest {
                state: 7,
                ..request()
            },
            "state",
        ),
        (
            v1::ListAlarmsRequest {
                page_size: -1,
                ..request()
            },
            "page_size",
        ),
        (
            v1::ListAlarmsRequest {
                page_token: "zz".into(),
                ..request()
            },
            "page_token",
        ),
    ];
    for (bad, field) in cases {
        let status = clients
            .alarms
            .list_alarms(bad.clone())
            .await
            .expect_err("an invalid filter is refused");
        assert_eq!(status.code(), Code::InvalidArgument, "{bad:?}");
        let violations = violated_fields(&status);
        assert_eq!(violations, [field], "{bad:?}");
    }

    let head = match clients
        .alarms
        .watch_alarms(v1::WatchAlarmsRequest::default())
        .await
        .expect("WatchAlarms works")
        .into_inner()
        .message()
        .await
    {
        Ok(Some(event)) => event.cursor,
        other => panic!("expected CAUGHT_UP, got {other:?}"),
    };
    for (bad, field) in [
        (
            v1::WatchAlarmsRequest {
                vehicle_id: "a/b".into(),
                ..v1::WatchAlarmsRequest::default()
            },
            "vehicle_id",
        ),
        (
            v1::WatchAlarmsRequest {
                after_cursor: Some(-1),
                ..v1::WatchAlarmsRequest::default()
            },
            "after_cursor",
        ),
        (
            v1::WatchAlarmsRequest {
                after_cursor: Some(head + 1),
                ..v1::WatchAlarmsRequest::default()
            },
            "after_cursor",
        ),
    ] {
        let status = clients
            .alarms
            .watch_alarms(bad.clone())
            .await
            .expect_err("an invalid watch is refused");
        assert_eq!(status.code(), Code::InvalidArgument, "{bad:?}");
        assert_eq!(violated_fields(&status), [field], "{bad:?}");
    }
    drop(clients);
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_alarm_service_needs_the_token() {
    let (_dir, server, mut clients) =
        start_server(|config| config.auth_token = Some("s3cret".into())).await;
    let refused = clients
        .alarms
        .list_alarms(v1::ListAlarmsRequest::default())
        .await
        .expect_err("no token");
    assert_eq!(refused.code(), Code::Unauthenticated);
    let refused = clients
        .alarms
        .watch_alarms(v1::WatchAlarmsRequest::default())
        .await
        .expect_err("no token");
    assert_eq!(refused.code(), Code::Unauthenticated);
    let authorised = Clients::new(server.connection(Some("s3cret")).await);
    let mut alarms = authorised.alarms.clone();
    alarms
        .list_alarms(v1::ListAlarmsRequest::default())
        .await
        .expect("with the token");
    drop((clients, authorised, alarms));
    server.stop().await;
}

/// Streams the frozen-fix drive of `vehicle_id` until a batch ends with the alarm on, then closes
/// the stream: the session keeps its alarm open.
async fn stream_until_alarming(clients: &Clients, vehicle_id: &str) {
    let track = attacked_drive(
        vehicle_id,
        240.0,
        21,
        AttackKind::FrozenPosition,
        100.0,
        60.0,
    );
    let (mut stream, _) = start_stream(clients, vehicle_id, "models/default").await;
    for (seq, batch) in track_samples(&track).chunks(5).enumerate() {
        let detections = stream
            .detect(seq as u64 + 1, batch.to_vec())
            .await
            .expect("one detection per sample");
        if detections.last().is_some_and(|d| d.alarm) {
            return;
        }
    }
    panic!("the frozen fix never raised an alarm");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_watcher_resumes_after_its_last_cursor_without_gaps_or_duplicates_also_across_a_restart()
{
    let dir = tempfile::tempdir().expect("temp dir");
    let server = TestServer::start(test_config(dir.path())).await;
    let mut clients = Clients::of(&server).await;
    let mut seen = Vec::new();

    // Connected while the first vehicle alarms.
    let mut first = watch(&clients, "", None);
    assert_eq!(next_event(&mut first).await.kind, CAUGHT_UP);
    let episodes = stream_frozen_fix_drive(&clients, "car-1").await;
    seen.extend(alarm_events(&mut first, 2 * episodes.len()).await);
    let cursor = first.cursor().expect("a cursor after events");
    drop(first);

    // Away while the second one alarms; back with the last cursor: exactly what was missed (once
    // the writer has stored it: a watcher sees only stored events).
    let missed = stream_frozen_fix_drive(&clients, "car-2").await;
    wait_until_stored(&mut clients, episodes.len() + missed.len()).await;
    let mut second = watch(&clients, "", Some(cursor));
    let replayed = until_caught_up(&mut second).await;
    assert_events_match(&replayed, "car-2", &missed);
    seen.extend(replayed);

    // The second watcher stays connected through a restart: the drain ends its call with
    // UNAVAILABLE and the watcher resumes on the restarted server (same port, same database). The
    // alarm still on stays open: car-3's session snapshot holds it, to be continued (and ended)
    // wherever car-3 reconnects.
    let notices = Arc::new(Mutex::new(Vec::new()));
    let second = second.with_reconnect_notice(Box::new({
        let notices = Arc::clone(&notices);
        move |status, cursor| {
            notices
                .lock()
                .unwrap()
                .push((status.code(), status.message().to_string(), cursor));
        }
    }));
    stream_until_alarming(&clients, "car-3").await;
    let (events_tx, mut events) = tokio::sync::mpsc::unbounded_channel();
    let follower = tokio::spawn(async move {
        let mut watch = second;
        loop {
            match watch.next().await {
                Ok(event) => {
                    if events_tx.send(event).is_err() {
                        return;
                    }
                }
                Err(error) => panic!("the watch gave up: {error}"),
            }
        }
    });
    let receive = async |events: &mut tokio::sync::mpsc::UnboundedReceiver<v1::AlarmEvent>| {
        tokio::time::timeout(REPLY_TIMEOUT, events.recv())
            .await
            .expect("an event in time")
            .expect("the follower is running")
    };
    let onset = receive(&mut events).await;
    assert_eq!(onset.kind, ONSET);
    assert_eq!(onset.alarm.as_ref().unwrap().vehicle_id, "car-3");
    seen.push(onset);
    let port = server.addr.port();
    drop(clients);
    server.stop().await;
    let server = TestServer::start_on_port(test_config(dir.path()), port).await;
    let clients = Clients::of(&server).await;

    assert_eq!(
        receive(&mut events).await.kind,
        CAUGHT_UP,
        "nothing happened while the watcher was away: the drain did not end car-3's alarm"
    );
    let still_open = history(&clients, "car-3").await;
    assert_eq!(still_open.len(), 1);
    assert!(still_open[0].alarm.as_ref().unwrap().open);
    {
        let notices = notices.lock().unwrap();
        let (code, message, _) = notices.first().expect("the drain ended the call");
        assert_eq!(*code, Code::Unavailable);
        assert!(message.contains("resume with after_cursor"), "{message}");
    }
    let after_restart = stream_frozen_fix_drive(&clients, "car-4").await;
    let mut live = Vec::new();
    for _ in 0..2 * after_restart.len() {
        live.push(receive(&mut events).await);
    }
    assert_events_match(&live, "car-4", &after_restart);
    assert!(live[0].cursor > seen.last().unwrap().cursor);
    seen.extend(live);

    // Everything the two watchers saw is the whole stored history, once each and in cursor order.
    let stored = history(&clients, "").await;
    assert_eq!(seen, stored);
    follower.abort();
    drop(clients);
    server.stop().await;
}
