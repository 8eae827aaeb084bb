//! Training jobs: upload a dataset, train and watch a job, export/import and activate its model
//! for new sessions (running sessions keep theirs), and cancel a second, queued job while it runs.

use std::time::Duration;

use spoofwatch_core::sample::Track;
use spoofwatch_proto::longrunning::{self, operation};
use spoofwatch_proto::v1;
use spoofwatch_tests::{
    Clients, active_model, export_model, import_model, metadata_of, normal_drive, start_server,
    start_stream, track_samples, trained_model, training_fleet, training_request, upload_tracks,
    wait_done,
};
use tonic::Code;

fn rows_and_spoofed(tracks: &[Track]) -> (u64, u64) {
    let records = || tracks.iter().flat_map(|t| &t.records);
    let spoofed = records().filter(|r| r.label == Some(true)).count();
    (records().count() as u64, spoofed as u64)
}

fn state_of(metadata: &v1::JobMetadata) -> v1::JobState {
    v1::JobState::try_from(metadata.state).expect("a known job state")
}

/// Opens a WatchJob stream.
async fn watch_job(clients: &mut Clients, name: &str) -> tonic::Streaming<v1::JobMetadata> {
    clients
        .training
        .watch_job(v1::WatchJobRequest {
            name: name.to_string(),
        })
        .await
        .expect("WatchJob is accepted")
        .into_inner()
}

/// Reads a WatchJob stream to its end.
async fn watch_to_end(clients: &mut Clients, name: &str) -> Vec<v1::JobMetadata> {
    let mut stream = watch_job(clients, name).await;
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
    let mut stream = watch_job(clients, name).await;
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
    let (_dir, server, mut clients) = start_server(|config| config.max_running_jobs = 1).await;

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
    let (mut before, accepted) = start_stream(&clients, "before-activation", "").await;
    assert_eq!(accepted.model, "models/default");
    let drive = track_samples(&normal_drive("before-activation", 40.0, 3));
    before
        .detect(1, drive[..20].to_vec())
        .await
        .expect("one detection per sample, for this batch");

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
    let imported = import_model(&mut clients, artifact, "re-imported").await;
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
    let (mut after, accepted) = start_stream(&clients, "after-activation", "").await;
    assert_eq!(accepted.model, model.name);
    let samples = track_samples(&normal_drive("after-activation", 20.0, 4));
    let detections = after
        .detect(1, samples)
        .await
        .expect("one detection per sample, for this batch");
    assert!(detections.iter().all(|d| d.model == model.name));
    // ... while a running session keeps the model it started with.
    let detections = before
        .detect(2, drive[20..].to_vec())
        .await
        .expect("one detection per sample, for this batch");
    assert!(detections.iter().all(|d| d.model == "models/default"));
    drop((after, before));

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
