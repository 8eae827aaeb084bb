//! A restart on the same database keeps models (and which is active), datasets, finished jobs
//! and the alarm events recorded while streaming.

use spoofwatch_proto::longrunning;
use spoofwatch_proto::v1;
use spoofwatch_server::store::Store;
use spoofwatch_tests::{
    Clients, TestServer, database_path, metadata_of, start_server, start_stream, stored_episodes,
    stream_frozen_fix_drive, test_config, trained_model, training_fleet, training_request,
    upload_tracks, wait_done,
};

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
    let episodes = stream_frozen_fix_drive(&clients, "frozen-fix").await;
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

    // Read the alarm events from the database file while no server runs (ListAlarms serves them
    // too: tests/tests/alarm_consumption.rs).
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
    let recorded = stored_episodes(&events);
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
