//! Model roll-out reaches live vehicles: a session started or resumed without a model follows the
//! active model (afresh, reported in SessionAccepted.replaced_model), Detect and fleet batches
//! without a model follow it too, open streams keep theirs, and deleting a model ends the sessions
//! that run it (streams with ABORTED, open alarms closed) so they come back on the active model. An
//! activation through one server reaches the others on its database.

use spoofwatch_core::scenario::AttackKind;
use spoofwatch_proto::v1;
use spoofwatch_server::store::Store;
use spoofwatch_tests::{
    Clients, TestServer, attacked_drive, code_of, database_path, export_model, final_code,
    import_model, normal_drive, start_server, start_stream, test_config, track_samples,
};
use tonic::Code;

/// A second model: the bundled artifact imported under a new name (not active).
async fn second_model(clients: &mut Clients) -> String {
    let artifact = export_model(&mut clients.models, "models/default").await;
    import_model(clients, artifact, "candidate").await.name
}

async fn activate(clients: &mut Clients, name: &str) {
    clients
        .models
        .set_active_model(v1::SetActiveModelRequest { name: name.into() })
        .await
        .expect("the model activates");
}

/// One unary Detect for `vehicle` without a model; returns the model that scored it.
async fn detect(clients: &mut Clients, vehicle: &str, samples: &[v1::Sample]) -> String {
    clients
        .detection
        .detect(v1::DetectRequest {
            vehicle_id: vehicle.into(),
            model: String::new(),
            samples: samples.to_vec(),
        })
        .await
        .expect("Detect works")
        .into_inner()
        .model
}

async fn session(clients: &mut Clients, vehicle: &str) -> Result<v1::Session, tonic::Status> {
    clients
        .detection
        .get_session(v1::GetSessionRequest {
            vehicle_id: vehicle.into(),
        })
        .await
        .map(tonic::Response::into_inner)
}

#[tokio::test]
async fn sessions_without_a_model_follow_the_active_model() {
    let (_dir, _server, mut clients) = start_server(|_| {}).await;
    let candidate = second_model(&mut clients).await;
    let drive = track_samples(&normal_drive("rollout", 60.0, 5));

    // Before the roll-out: a stream that comes back later, one that stays open, a Detect caller.
    let (mut returning, accepted) = start_stream(&clients, "returning", "").await;
    assert_eq!(accepted.model, "models/default");
    returning
        .detect(1, drive[..20].to_vec())
        .await
        .expect("scored");
    drop(returning);
    let (mut open, _) = start_stream(&clients, "open", "").await;
    open.detect(1, drive[..20].to_vec()).await.expect("scored");
    assert_eq!(
        detect(&mut clients, "gateway", &drive[..20]).await,
        "models/default"
    );

    activate(&mut clients, &candidate).await;

    // The returning vehicle starts afresh on the active model and is told what it replaced.
    let (mut returning, accepted) = start_stream(&clients, "returning", "").await;
    assert_eq!(accepted.model, candidate);
    assert!(!accepted.resumed);
    assert_eq!(accepted.replaced_model, "models/default");
    assert_eq!(accepted.samples_seen, 0, "a fresh detector");
    let scored = returning
        .detect(2, drive[..20].to_vec())
        .await
        .expect("scored");
    assert!(scored.iter().all(|d| d.model == candidate));
    // Reconnecting again resumes: nothing was replaced this time.
    drop(returning);
    let (_returning, accepted) = start_stream(&clients, "returning", "").await;
    assert!(accepted.resumed);
    assert!(accepted.replaced_model.is_empty());

    // The Detect caller's next batch runs on the active model, afresh.
    assert_eq!(
        detect(&mut clients, "gateway", &drive[20..40]).await,
        candidate
    );
    let gateway = session(&mut clients, "gateway").await.expect("the session");
    assert_eq!(
        (gateway.model.as_str(), gateway.samples),
        (candidate.as_str(), 20)
    );

    // An open stream keeps the model it started with until it ends.
    let scored = open
        .detect(2, drive[20..40].to_vec())
        .await
        .expect("scored");
    assert!(scored.iter().all(|d| d.model == "models/default"));

    // A vehicle that names its model keeps it, whatever is active.
    let (_pinned, accepted) = start_stream(&clients, "pinned", "models/default").await;
    assert_eq!(accepted.model, "models/default");
}

#[tokio::test]
async fn deleting_a_model_ends_the_sessions_that_run_it() {
    let (dir, server, mut clients) = start_server(|_| {}).await;
    let candidate = second_model(&mut clients).await;

    // A streaming vehicle in the middle of an alarm on the candidate model ...
    let attacked = attacked_drive(
        "alarming",
        240.0,
        21,
        AttackKind::FrozenPosition,
        100.0,
        60.0,
    );
    let samples = track_samples(&attacked);
    let (mut alarming, _) = start_stream(&clients, "alarming", &candidate).await;
    let mut alarm_open = false;
    for (seq, batch) in samples.chunks(20).enumerate() {
        let scored = alarming
            .detect(seq as u64 + 1, batch.to_vec())
            .await
            .expect("scored");
        alarm_open = scored.last().is_some_and(|d| d.alarm);
        if alarm_open {
            break;
        }
    }
    assert!(
        alarm_open,
        "the frozen fix raises an alarm within the attack"
    );
    // ... a gateway vehicle on the candidate, and a stream on the active model.
    clients
        .detection
        .detect(v1::DetectRequest {
            vehicle_id: "gateway".into(),
            model: candidate.clone(),
            samples: samples[..20].to_vec(),
        })
        .await
        .expect("Detect works");
    let (mut unaffected, _) = start_stream(&clients, "unaffected", "").await;

    clients
        .models
        .delete_model(v1::DeleteModelRequest {
            name: candidate.clone(),
        })
        .await
        .expect("a model that is not active can be deleted while sessions use it");

    // The stream on the deleted model ends with ABORTED naming the model; its session is gone.
    assert_eq!(final_code(&mut alarming).await, Code::Aborted);
    for vehicle in ["alarming", "gateway"] {
        let status = session(&mut clients, vehicle)
            .await
            .expect_err("the session ended");
        assert_eq!(status.code(), Code::NotFound, "{vehicle}");
    }
    // The other vehicle goes on.
    let clean = track_samples(&normal_drive("unaffected", 30.0, 6));
    unaffected
        .detect(1, clean.clone())
        .await
        .expect("still scored");

    // Coming back without a model lands on the active one; naming the deleted one is NOT_FOUND.
    let (_back, accepted) = start_stream(&clients, "alarming", "").await;
    assert_eq!(
        (accepted.model.as_str(), accepted.resumed),
        ("models/default", false)
    );
    let refused = spoofwatch_tests::open_stream(
        &clients,
        spoofwatch_tests::start_request("elsewhere", &candidate, false),
    )
    .await;
    let code = match refused {
        Err(error) => code_of(&error),
        Ok(mut stream) => final_code(&mut stream).await,
    };
    assert_eq!(code, Code::NotFound);

    // The alarm that was open when the model went away was closed and stored.
    drop((clients, unaffected));
    server.stop().await;
    let store = Store::open(&database_path(dir.path()).display().to_string())
        .await
        .expect("the database opens");
    let events = store
        .list_alarm_events(Some("alarming"), 100)
        .await
        .expect("alarm events");
    store.close().await;
    assert_eq!(events.len(), 1, "{events:?}");
    assert!(!events[0].is_open(), "closed when its model was deleted");
    assert_eq!(events[0].model_id, candidate.trim_start_matches("models/"));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_activation_through_one_server_reaches_the_others_on_its_database() {
    let dir = tempfile::tempdir().expect("temp dir");
    let first = TestServer::start(test_config(dir.path())).await;
    let second = TestServer::start(test_config(dir.path())).await;
    let (mut first_clients, second_clients) =
        (Clients::of(&first).await, Clients::of(&second).await);
    let candidate = second_model(&mut first_clients).await;
    // The second server knows the active model before the roll-out.
    let (_before, accepted) = start_stream(&second_clients, "before", "").await;
    assert_eq!(accepted.model, "models/default");

    activate(&mut first_clients, &candidate).await;
    // Within a few of the second server's polls of the database, its new sessions run the
    // candidate (bounded: a hang guard, not a timing).
    let mut followed = None;
    for attempt in 0..100 {
        let (_stream, accepted) =
            start_stream(&second_clients, &format!("after-{attempt}"), "").await;
        if accepted.model == candidate {
            followed = Some(attempt);
            break;
        }
        tokio::time::sleep(std::time::Duration::from_millis(200)).await;
    }
    assert!(
        followed.is_some(),
        "the second server never followed the activation"
    );
    drop((first_clients, second_clients));
    second.stop().await;
    first.stop().await;
}
