//! A restart on the same database keeps models (and which is active), datasets, finished jobs
//! and the alarm events recorded while streaming.

use spoofwatch_core::scenario::AttackKind;
use spoofwatch_proto::longrunning;
use spoofwatch_proto::v1;
use spoofwatch_server::store::Store;
use spoofwatch_tests::{
    Clients, TestServer, attacked_drive, database_path, metadata_of, start_server, start_stream,
    test_config, track_samples, trained_model, training_fleet, training_request, upload_tracks,
    wait_done,
};

/// One confirmed alarm as the detections show it: onset time, last alarming sample's time, peak
/// probability and number of alarming samples.
#[derive(Debug, PartialEq)]
struct Episode {
    onset_s: f64,
    last_s: f64,
    peak: f64,
    samples: i64,
}

/// Streams a drive whose fix freezes for 60 s through the bundled model; returns its alarm episodes.
async fn stream_attacked_drive(clients: &mut Clients, vehicle_id: &str) -> Vec<Episode> {
    let frozen = AttackKind::FrozenPosition;
    let track = attacked_drive(vehicle_id, 240.0, 21, frozen, 100.0, 60.0);
    let (mut stream, _) = start_stream(clients, vehicle_id, "models/default").await;
    let mut episodes: Vec<Episode> = Vec::new();
    for (seq, batch) in track_samples(&track).chunks(20).enumerate() {
        for d in stream
            .detect(seq as u64 + 1, batch.to_vec())
            .await
            .expect("one detection per sample, for this batch")
        {
            if d.alarm_onset {
                episodes.push(Episode {
                    onset_s: d.timestamp_s,
                    last_s: d.timestamp_s,
                    peak: d.probability,
                    samples: 1,
                });
            } else if d.alarm {
                let open = episodes.last_mut().expect("an alarm follows its onset");
                open.last_s = d.timestamp_s;
                open.peak = open.peak.max(d.probability);
                open.samples += 1;
            }
        }
    }
    drop(stream);
    episodes
}

/// What a restart must preserve, as seen through the API.
#[derive(Debug, PartialEq)]
struct Snapshot {
    models: Vec<(String, bool, String)>,
    datasets: Vec<(String, u64, String)>,
    operations: Vec<(String, i32, usize, bool)>,
}

async fn snapshot(clients: &mut Clients) -> Snapshot {
    let models = clients
        .models
        .list_models(v1::ListModelsRequest::default())
        .await
        .expect("ListModels")
        .into_inner()
        .models;
    let datasets = clients
        .datasets
        .list_datasets(v1::ListDatasetsRequest::default())
        .await
        .expect("ListDatasets")
        .into_inner()
        .datasets;
    let operations = clients
        .operations
        .list_operations(longrunning::ListOperationsRequest::default())
        .await
        .expect("ListOperations")
        .into_inner()
        .operations;
    Snapshot {
        models: models
            .into_iter()
            .map(|m| (m.name, m.active, m.sha256))
            .collect(),
        datasets: datasets
            .into_iter()
            .map(|d| (d.name, d.rows, d.sha256))
            .collect(),
        operations: operations
            .iter()
            .map(|o| {
                let metadata = metadata_of(o);
                (
                    o.name.clone(),
                    metadata.state,
                    metadata.history.len(),
                    o.done,
                )
            })
            .collect(),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_restart_on_the_same_database_keeps_models_datasets_jobs_and_alarms() {
    let (dir, server, mut clients) = start_server(|_| {}).await;
    let dataset = upload_tracks(&mut clients, "fleet to keep", &training_fleet()).await;
    let job = clients
        .training
        .create_training_job(training_request(&dataset.name, 1, true))
        .await
        .expect("the training job is accepted")
        .into_inner();
    let done = wait_done(&mut clients.operations, &job.name).await;
    let trained = trained_model(&done);
    let episodes = stream_attacked_drive(&mut clients, "frozen-fix").await;
    assert!(
        !episodes.is_empty(),
        "a frozen fix raises a confirmed alarm"
    );
    let before = snapshot(&mut clients).await;
    assert_eq!(
        before.models,
        vec![
            (trained.name.clone(), true, trained.sha256.clone()),
            (
                "models/default".to_string(),
                false,
                before.models[1].2.clone()
            ),
        ],
        "newest first; the job activated its model"
    );
    assert_eq!(before.datasets.len(), 1);
    assert_eq!(
        before.operations,
        vec![(job.name.clone(), v1::JobState::Succeeded as i32, 1, true)]
    );
    drop(clients);
    server.stop().await;

    // Alarm events have no RPC yet: read them from the database file while no server runs.
    let database = database_path(dir.path()).display().to_string();
    let store = Store::open(&database).await.expect("the database opens");
    let events = store
        .list_alarm_events(Some("frozen-fix"), 100)
        .await
        .expect("alarm events");
    store.close().await;
    assert!(
        events
            .iter()
            .all(|e| e.model_id == "default" && !e.is_open())
    );
    // Newest first in the store; each event matches its episode (end = last alarming sample).
    let recorded: Vec<Episode> = events
        .iter()
        .rev()
        .map(|e| Episode {
            onset_s: e.onset_timestamp_s,
            last_s: e
                .end_timestamp_s
                .expect("the alarm ended with a sample time"),
            peak: e.peak_probability,
            samples: e.samples,
        })
        .collect();
    assert_eq!(
        recorded, episodes,
        "one stored event per confirmed alarm episode"
    );

    let server = TestServer::start(test_config(dir.path())).await;
    let mut clients = Clients::of(&server).await;
    let after = snapshot(&mut clients).await;
    assert_eq!(
        after, before,
        "models, active flag, datasets and jobs survive the restart"
    );
    let model = clients
        .models
        .get_model(v1::GetModelRequest {
            name: trained.name.clone(),
        })
        .await
        .expect("the trained model is still there")
        .into_inner();
    assert_eq!(model.training_operation, job.name);
    let (_stream, accepted) = start_stream(&clients, "after-restart", "").await;
    assert_eq!(
        accepted.model, trained.name,
        "the active model is still the trained one"
    );
    drop((_stream, clients));
    server.stop().await;

    let store = Store::open(&database)
        .await
        .expect("the database opens again");
    let kept = store
        .list_alarm_events(Some("frozen-fix"), 100)
        .await
        .expect("alarm events");
    store.close().await;
    assert_eq!(kept, events, "alarm events survive the restart unchanged");
}
