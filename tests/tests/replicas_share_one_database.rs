//! Two replicas on one PostgreSQL database: a job admitted by one is seen through the other, a
//! replica that starts leaves the other's running job alone, and a cancellation and a wait through
//! the other replica reach the job where it runs; a WatchAlarms call on one replica follows both
//! replicas' alarms, and its cursors resume on the other. Needs `SPOOFWATCH_TEST_POSTGRES_URL` (skipped
//! without it, failed without it under `SPOOFWATCH_REQUIRE_POSTGRES=1`).

use std::time::Duration;

use spoofwatch_core::sample::Track;
use spoofwatch_core::scenario::AttackKind;
use spoofwatch_proto::longrunning::{self, operation};
use spoofwatch_proto::v1;
use spoofwatch_server::Config;
use spoofwatch_server::store::test_database::TestDatabase;
use spoofwatch_tests::{
    Clients, REPLY_TIMEOUT, TestServer, attacked_drive, metadata_of, normal_drive,
    stream_frozen_fix_drive, training_request, upload_tracks, wait_done,
};
use tonic::Code;
use tonic::codec::Streaming;

/// Twenty-four 20-minute drives (about 28,800 rows), half of them attacked early, mid-way or late,
/// so that training runs several times longer than a lease renewal (measured: about 8 s after the cancellation point here, against at most a second or two for the cancellation to arrive) and
/// the cancellation through the other replica reaches the job while it runs (a job on the small
/// `training_fleet` can finish first).
fn long_training_fleet() -> Vec<Track> {
    let ramp = AttackKind::RampDrift { velocity_mps: 1.5 };
    (0..24u64)
        .map(|i| {
            let vehicle = format!("long-{i}");
            if i % 2 == 0 {
                normal_drive(&vehicle, 1200.0, 100 + i)
            } else {
                let onset = [300.0, 600.0, 880.0][(i as usize / 2) % 3];
                attacked_drive(&vehicle, 1200.0, 100 + i, ramp, onset, 120.0)
            }
        })
        .collect()
}

/// A replica named `instance` on the database at `url`.
fn replica(url: &str, instance: &str) -> Config {
    let mut config = Config::with_database(url);
    config.shutdown_grace_secs = 2;
    config.instance_id = Some(instance.to_string());
    config
}

fn state_of(operation: &longrunning::Operation) -> v1::JobState {
    v1::JobState::try_from(metadata_of(operation).state).expect("a known job state")
}

async fn get(clients: &mut Clients, name: &str) -> longrunning::Operation {
    clients
        .operations
        .get_operation(longrunning::GetOperationRequest {
            name: name.to_string(),
        })
        .await
        .expect("GetOperation works")
        .into_inner()
}

/// Polls until the job leaves QUEUED (bounded generously for debug builds on shared cores).
async fn wait_until_started(clients: &mut Clients, name: &str) -> v1::JobState {
    for _ in 0..3_000 {
        let state = state_of(&get(clients, name).await);
        if state != v1::JobState::Queued {
            return state;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    panic!("{name} never started");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_job_on_one_replica_is_seen_cancelled_and_awaited_through_another() {
    let Some(database) = TestDatabase::create("replicas_share_one_database").await else {
        return;
    };
    let first = TestServer::start(replica(&database.url, "replica-a")).await;
    let mut on_first = Clients::of(&first).await;
    let dataset = upload_tracks(&mut on_first, "long fleet", &long_training_fleet()).await;
    let job = on_first
        .training
        .create_training_job(training_request(&dataset.name, 200, false))
        .await
        .expect("the training job is accepted")
        .into_inner();
    assert_eq!(
        wait_until_started(&mut on_first, &job.name).await,
        v1::JobState::Running
    );

    // A second replica starts on the same database: the first's job keeps running, and the
    // second sees it, alone and in listings.
    let second = TestServer::start(replica(&database.url, "replica-b")).await;
    let mut on_second = Clients::of(&second).await;
    let seen = get(&mut on_second, &job.name).await;
    assert_eq!(
        (state_of(&seen), seen.done),
        (v1::JobState::Running, false),
        "starting a replica must not fail another replica's running job"
    );
    let listed = on_second
        .operations
        .list_operations(longrunning::ListOperationsRequest {
            filter: "done=false".to_string(),
            ..longrunning::ListOperationsRequest::default()
        })
        .await
        .expect("ListOperations works")
        .into_inner();
    let names: Vec<_> = listed.operations.iter().map(|o| o.name.as_str()).collect();
    assert_eq!(names, [job.name.as_str()]);

    // Cancelled and awaited through the second replica; the first, which ran it, agrees.
    on_second
        .operations
        .cancel_operation(longrunning::CancelOperationRequest {
            name: job.name.clone(),
        })
        .await
        .expect("CancelOperation works");
    let cancelled = wait_done(&mut on_second.operations, &job.name).await;
    let Some(operation::Result::Error(error)) = &cancelled.result else {
        panic!("a cancelled operation ends with an error: {cancelled:?}");
    };
    assert_eq!(error.code, Code::Cancelled as i32);
    assert_eq!(state_of(&cancelled), v1::JobState::Cancelled);
    assert_eq!(get(&mut on_first, &job.name).await, cancelled);

    drop((on_first, on_second));
    first.stop().await;
    second.stop().await;
    database.drop_database().await;
}

const ONSET: i32 = v1::AlarmEventKind::Onset as i32;
const END: i32 = v1::AlarmEventKind::End as i32;
const CAUGHT_UP: i32 = v1::AlarmEventKind::CaughtUp as i32;

async fn watch_alarms(
    clients: &Clients,
    after_cursor: Option<i64>,
    stop_when_caught_up: bool,
) -> Streaming<v1::AlarmEvent> {
    let request = v1::WatchAlarmsRequest {
        vehicle_id: String::new(),
        after_cursor,
        stop_when_caught_up,
        ..Default::default()
    };
    clients
        .alarms
        .clone()
        .watch_alarms(request)
        .await
        .expect("WatchAlarms works")
        .into_inner()
}

async fn next_event(watch: &mut Streaming<v1::AlarmEvent>) -> Option<v1::AlarmEvent> {
    tokio::time::timeout(REPLY_TIMEOUT, watch.message())
        .await
        .expect("an alarm event within the reply timeout")
        .expect("the watch goes on")
}

/// The events after `cursor` up to CAUGHT_UP (left out), through `clients`' replica.
async fn stored_after(clients: &Clients, cursor: i64) -> Vec<v1::AlarmEvent> {
    let mut watch = watch_alarms(clients, Some(cursor), true).await;
    let mut events = Vec::new();
    while let Some(event) = next_event(&mut watch).await {
        events.push(event);
    }
    assert_eq!(events.pop().map(|e| e.kind), Some(CAUGHT_UP));
    events
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_watcher_on_one_replica_follows_both_and_resumes_on_the_other() {
    let Some(database) = TestDatabase::create("replicas_watch_alarms").await else {
        return;
    };
    let first = TestServer::start(replica(&database.url, "replica-a")).await;
    let second = TestServer::start(replica(&database.url, "replica-b")).await;
    let (mut on_first, on_second) = (Clients::of(&first).await, Clients::of(&second).await);
    let mut live = watch_alarms(&on_first, None, false).await;
    let start = next_event(&mut live).await.expect("CAUGHT_UP");
    assert_eq!(start.kind, CAUGHT_UP);

    // One vehicle on each replica, at the same time.
    let (episodes_a, episodes_b) = tokio::join!(
        stream_frozen_fix_drive(&on_first, "on-a"),
        stream_frozen_fix_drive(&on_second, "on-b")
    );
    assert!(!episodes_a.is_empty() && !episodes_b.is_empty());
    let mut seen = Vec::new();
    while seen.len() < 2 * (episodes_a.len() + episodes_b.len()) {
        let event = next_event(&mut live).await.expect("the watch goes on");
        assert_ne!(event.kind, CAUGHT_UP, "one CAUGHT_UP per call");
        seen.push(event);
    }
    assert!(
        seen.windows(2).all(|w| w[0].cursor < w[1].cursor),
        "strictly increasing cursors: {seen:?}"
    );
    assert!(seen[0].cursor > start.cursor);
    for (vehicle, episodes) in [("on-a", &episodes_a), ("on-b", &episodes_b)] {
        let of_vehicle: Vec<_> = seen
            .iter()
            .filter(|e| e.alarm.as_ref().is_some_and(|a| a.vehicle_id == vehicle))
            .collect();
        let shown: Vec<_> = of_vehicle
            .iter()
            .map(|e| (e.kind, e.alarm.as_ref().map(|a| a.onset_timestamp_s)))
            .collect();
        let expected: Vec<_> = episodes
            .iter()
            .flat_map(|e| [(ONSET, Some(e.onset_s)), (END, Some(e.onset_s))])
            .collect();
        assert_eq!(shown, expected, "every onset and end of {vehicle}, once");
    }

    // Everything stored is what the watcher saw, and a cursor from the first replica resumes on
    // the second with exactly the events after it.
    assert_eq!(stored_after(&on_second, start.cursor).await, seen);
    let middle = seen.len() / 2;
    assert_eq!(
        stored_after(&on_second, seen[middle].cursor).await,
        seen[middle + 1..]
    );
    let listed = on_first
        .alarms
        .list_alarms(v1::ListAlarmsRequest::default())
        .await
        .expect("ListAlarms works")
        .into_inner();
    let mut ended: Vec<_> = seen
        .iter()
        .filter(|e| e.kind == END)
        .filter_map(|e| e.alarm.clone())
        .collect();
    ended.sort_by_key(|a| a.id);
    assert_eq!(listed.alarms, ended, "the alarms as their ends showed them");

    drop((live, on_first, on_second));
    first.stop().await;
    second.stop().await;
    database.drop_database().await;
}
