//! Issue 4, tests 2 and 3: upload a dataset, train and watch a job, activate its model for new
//! sessions, cancel a second job; then restart on the same database and find everything again.

use std::time::Duration;

use prost::Message;
use spoofwatch_core::sample::Track;
use spoofwatch_core::scenario::AttackKind;
use spoofwatch_proto::longrunning::{self, operation};
use spoofwatch_proto::v1;
use spoofwatch_server::store::Store;
use spoofwatch_tests::{
    Clients, DetectStream, TestServer, active_model, attacked_drive, database_path, export_model,
    normal_drive, test_config, track_samples, upload_tracks,
};
use tonic::Code;
use tonic::transport::Channel;

/// Five 400 s drives (2,005 rows): two normal, three with ramp attacks placed so that the
/// chronological 70/15/15 split has both classes in training and in validation.
fn training_fleet() -> Vec<Track> {
    let ramp = AttackKind::RampDrift { velocity_mps: 1.5 };
    vec![
        normal_drive("sim-0", 400.0, 11),
        attacked_drive("sim-1", 400.0, 12, ramp, 150.0, 100.0),
        attacked_drive("sim-2", 400.0, 13, ramp, 250.0, 100.0),
        normal_drive("sim-3", 400.0, 14),
        attacked_drive("sim-4", 400.0, 15, ramp, 300.0, 80.0),
    ]
}

fn rows_and_spoofed(tracks: &[Track]) -> (u64, u64) {
    let records = || tracks.iter().flat_map(|t| &t.records);
    let spoofed = records().filter(|r| r.label == Some(true)).count();
    (records().count() as u64, spoofed as u64)
}

fn training_request(
    dataset: &str,
    max_epochs: u32,
    activate: bool,
) -> v1::CreateTrainingJobRequest {
    v1::CreateTrainingJobRequest {
        datasets: vec![dataset.to_string()],
        spec: Some(v1::TrainingSpec {
            seed: 7,
            max_epochs,
            ..v1::TrainingSpec::default()
        }),
        display_name: format!("tiny {max_epochs}-epoch model"),
        activate,
        ..v1::CreateTrainingJobRequest::default()
    }
}

fn metadata_of(operation: &longrunning::Operation) -> v1::JobMetadata {
    let any = operation
        .metadata
        .as_ref()
        .expect("an operation carries metadata");
    assert_eq!(
        any.type_url,
        "type.googleapis.com/spoofwatch.v1.JobMetadata"
    );
    v1::JobMetadata::decode(any.value.as_slice()).expect("decodable JobMetadata")
}

fn state_of(metadata: &v1::JobMetadata) -> v1::JobState {
    v1::JobState::try_from(metadata.state).expect("a known job state")
}

/// Waits (server side, at most 60 s per call) until the operation is done.
async fn wait_done(
    operations: &mut longrunning::operations_client::OperationsClient<Channel>,
    name: &str,
) -> longrunning::Operation {
    for _ in 0..5 {
        let operation = operations
            .wait_operation(longrunning::WaitOperationRequest {
                name: name.to_string(),
                timeout: Some(prost_types::Duration {
                    seconds: 60,
                    nanos: 0,
                }),
            })
            .await
            .expect("WaitOperation works")
            .into_inner();
        if operation.done {
            return operation;
        }
    }
    panic!("{name} did not finish within 5 minutes");
}

/// The model a finished training operation registered.
fn trained_model(operation: &longrunning::Operation) -> v1::Model {
    let Some(operation::Result::Response(any)) = &operation.result else {
        panic!("a succeeded training operation has a response: {operation:?}");
    };
    assert_eq!(
        any.type_url,
        "type.googleapis.com/spoofwatch.v1.TrainingJobResult"
    );
    let result = v1::TrainingJobResult::decode(any.value.as_slice()).expect("decodable result");
    assert!(
        result.validation.is_some(),
        "validation metrics are reported"
    );
    result.model.expect("the result names the registered model")
}

/// Uploads an artifact in two chunks (not activated).
async fn import_model(clients: &mut Clients, artifact: Vec<u8>) -> v1::Model {
    use v1::import_model_request::Kind;
    let (head, tail) = artifact.split_at(artifact.len() / 2);
    let messages = [
        Kind::Header(v1::ImportModelHeader {
            display_name: "re-imported".into(),
            activate: false,
        }),
        Kind::Chunk(head.to_vec()),
        Kind::Chunk(tail.to_vec()),
    ]
    .map(|kind| v1::ImportModelRequest { kind: Some(kind) });
    clients
        .models
        .import_model(tokio_stream::iter(messages))
        .await
        .expect("ImportModel accepts an exported artifact")
        .into_inner()
}

/// Reads a WatchJob stream to its end.
async fn watch_to_end(clients: &mut Clients, name: &str) -> Vec<v1::JobMetadata> {
    let mut stream = clients
        .training
        .watch_job(v1::WatchJobRequest {
            name: name.to_string(),
        })
        .await
        .expect("WatchJob is accepted")
        .into_inner();
    let mut updates = Vec::new();
    loop {
        let next = tokio::time::timeout(Duration::from_secs(300), stream.message())
            .await
            .expect("progress within 5 minutes")
            .expect("the watch stream ends cleanly");
        match next {
            Some(update) => updates.push(update),
            None => return updates,
        }
    }
}

/// Reads a WatchJob stream until the job reports RUNNING (or ends).
async fn watch_until_running(clients: &mut Clients, name: &str) -> v1::JobState {
    let mut stream = clients
        .training
        .watch_job(v1::WatchJobRequest {
            name: name.to_string(),
        })
        .await
        .expect("WatchJob is accepted")
        .into_inner();
    loop {
        let update = tokio::time::timeout(Duration::from_secs(300), stream.message())
            .await
            .expect("progress within 5 minutes")
            .expect("the watch stream works")
            .expect("the watch stream lasts until the job ends");
        let state = state_of(&update);
        if state != v1::JobState::Queued {
            return state;
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_trained_model_serves_new_sessions_and_a_second_job_can_be_cancelled() {
    let dir = tempfile::tempdir().expect("temp dir");
    let mut config = test_config(dir.path());
    config.max_running_jobs = 1;
    let server = TestServer::start(config).await;
    let mut clients = Clients::of(&server).await;

    let fleet = training_fleet();
    let (rows, spoofed) = rows_and_spoofed(&fleet);
    let dataset = upload_tracks(&mut clients, "simulated fleet", &fleet).await;
    assert_eq!(dataset.format, "telemetry");
    assert_eq!(dataset.source, "upload");
    assert_eq!((dataset.rows, dataset.vehicles), (rows, 5));
    assert_eq!(
        (dataset.labelled_rows, dataset.spoofed_rows),
        (rows, spoofed)
    );

    // The first job runs; the second (long) one queues behind it (one job at a time).
    let first = clients
        .training
        .create_training_job(training_request(&dataset.name, 2, false))
        .await
        .expect("the training job is accepted")
        .into_inner();
    assert!(!first.done);
    assert_eq!(metadata_of(&first).kind, "training");
    let second = clients
        .training
        .create_training_job(training_request(&dataset.name, 200, false))
        .await
        .expect("a second job is accepted")
        .into_inner();

    // A session opened before the new model is activated keeps the bundled one.
    let (mut before, accepted) =
        DetectStream::start(&mut clients.detection, "before-activation", "").await;
    assert_eq!(accepted.model, "models/default");
    let drive = track_samples(&normal_drive("before-activation", 40.0, 3));
    before.detect(1, drive[..20].to_vec()).await;

    let updates = watch_to_end(&mut clients, &first.name).await;
    assert!(
        updates.iter().any(|u| u.epoch > 0 && u.max_epochs == 2),
        "at least one progress message reports a finished epoch: {updates:?}"
    );
    let last = updates.last().expect("at least one update");
    assert_eq!(state_of(last), v1::JobState::Succeeded, "{last:?}");
    assert_eq!(last.epoch, 2);
    assert_eq!(last.history.len(), 2, "one history record per epoch");

    let done = clients
        .operations
        .get_operation(longrunning::GetOperationRequest {
            name: first.name.clone(),
        })
        .await
        .expect("GetOperation works")
        .into_inner();
    assert!(done.done);
    let registered = trained_model(&done);
    let model = clients
        .models
        .get_model(v1::GetModelRequest {
            name: registered.name.clone(),
        })
        .await
        .expect("the trained model is registered")
        .into_inner();
    assert_eq!(model.source, "training");
    assert_eq!(model.training_operation, first.name);
    assert_eq!(model.epochs_run, 2);
    assert_eq!(model.seed, 7);
    assert!(!model.active, "not activated by the job (activate = false)");
    assert!(model.operating_point.is_some() && model.validation_metrics.is_some());

    // Export and re-import give the same artifact under a new name.
    let artifact = export_model(&mut clients.models, &model.name).await;
    let imported = import_model(&mut clients, artifact).await;
    assert_ne!(imported.name, model.name);
    assert_eq!(
        (imported.source.as_str(), imported.active),
        ("import", false)
    );
    assert_eq!(
        imported.sha256, model.sha256,
        "the artifact survives export/import bit for bit"
    );

    let activated = clients
        .models
        .set_active_model(v1::SetActiveModelRequest {
            name: model.name.clone(),
        })
        .await
        .expect("the trained model can be activated")
        .into_inner();
    assert!(activated.active);
    assert_eq!(active_model(&mut clients.models).await.name, model.name);

    // New sessions use the newly active model ...
    let (mut after, accepted) =
        DetectStream::start(&mut clients.detection, "after-activation", "").await;
    assert_eq!(accepted.model, model.name);
    let samples = track_samples(&normal_drive("after-activation", 20.0, 4));
    let detections = after.detect(1, samples).await;
    assert!(detections.iter().all(|d| d.model == model.name));
    // ... while a running session keeps the model it started with.
    let detections = before.detect(2, drive[20..].to_vec()).await;
    assert!(detections.iter().all(|d| d.model == "models/default"));
    drop((after.close(), before.close()));

    // The second job starts once the first is done; cancel it while it runs.
    let state = watch_until_running(&mut clients, &second.name).await;
    assert_eq!(state, v1::JobState::Running);
    clients
        .operations
        .cancel_operation(longrunning::CancelOperationRequest {
            name: second.name.clone(),
        })
        .await
        .expect("CancelOperation works");
    let cancelled = wait_done(&mut clients.operations, &second.name).await;
    let Some(operation::Result::Error(error)) = &cancelled.result else {
        panic!("a cancelled operation ends with an error: {cancelled:?}");
    };
    assert_eq!(error.code, Code::Cancelled as i32);
    assert_eq!(state_of(&metadata_of(&cancelled)), v1::JobState::Cancelled);

    drop(clients);
    server.stop().await;
}

/// One confirmed alarm as the detections show it: onset time, last alarming sample's time, peak
/// probability and number of alarming samples.
#[derive(Debug, PartialEq)]
struct Episode {
    onset_s: f64,
    last_s: f64,
    peak: f64,
    samples: i64,
}

/// Streams a drive with a 300 m jump through the bundled model; returns its alarm episodes.
async fn stream_attacked_drive(clients: &mut Clients, vehicle_id: &str) -> Vec<Episode> {
    let jump = AttackKind::Jump { offset_m: 300.0 };
    let track = attacked_drive(vehicle_id, 240.0, 21, jump, 100.0, 60.0);
    let (mut stream, _) =
        DetectStream::start(&mut clients.detection, vehicle_id, "models/default").await;
    let mut episodes: Vec<Episode> = Vec::new();
    for (seq, batch) in track_samples(&track).chunks(20).enumerate() {
        for d in stream.detect(seq as u64 + 1, batch.to_vec()).await {
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
    drop(stream.close());
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
    let dir = tempfile::tempdir().expect("temp dir");
    let server = TestServer::start(test_config(dir.path())).await;
    let mut clients = Clients::of(&server).await;
    let dataset = upload_tracks(&mut clients, "fleet to keep", &training_fleet()).await;
    let job = clients
        .training
        .create_training_job(training_request(&dataset.name, 1, true))
        .await
        .expect("the training job is accepted")
        .into_inner();
    let done = wait_done(&mut clients.operations, &job.name).await;
    let trained = trained_model(&done);
    let episodes = stream_attacked_drive(&mut clients, "jumpy").await;
    assert!(
        !episodes.is_empty(),
        "a 300 m jump raises a confirmed alarm"
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
        .list_alarm_events(Some("jumpy"), 100)
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
    let (_stream, accepted) =
        DetectStream::start(&mut clients.detection, "after-restart", "").await;
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
        .list_alarm_events(Some("jumpy"), 100)
        .await
        .expect("alarm events");
    store.close().await;
    assert_eq!(kept, events, "alarm events survive the restart unchanged");
}
