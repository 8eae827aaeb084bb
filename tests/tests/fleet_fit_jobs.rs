//! Fleet-fit jobs through the server, on SQLite and on PostgreSQL: a fleet's attack-free recordings
//! uploaded, the detector fitted to them as a training job (progress watched, the fitted model
//! registered with the fit's report), the fitted model activated and scoring new sessions; a fit
//! cancelled while it runs ends CANCELLED and registers nothing; a fit running when its server
//! stops ends as every training job does (CANCELLED by a clean stop, ABORTED by the restart after
//! a kill); and recordings that cannot support a fit refused with the field at fault. The
//! PostgreSQL variants need `SPOOFWATCH_TEST_POSTGRES_URL` (skipped without it, failed without it
//! under `SPOOFWATCH_REQUIRE_POSTGRES=1`).

use std::time::{Duration, Instant};

use prost::Message;
use spoofwatch_core::sample::Track;
use spoofwatch_core::scenario::{DriveDistribution, Outages, simulate_drive};
use spoofwatch_proto::longrunning::{self, operation};
use spoofwatch_proto::v1;
use spoofwatch_server::store::test_database::TestDatabase;
use spoofwatch_tests::replica_process::ReplicaProcess;
use spoofwatch_tests::{
    Clients, TestServer, metadata_of, start_server, stream_batches, test_config, track_samples,
    trained_model, upload_tracks, wait_done,
};
use tonic::Code;

/// `vehicles` attack-free drives of `duration_s` at 1 Hz of the realistic distribution (they turn and
/// stop, so they teach the onboard calibration), one per vehicle, unlabelled as a fleet's
/// recordings are.
fn recordings(vehicles: usize, duration_s: f64, first_seed: u64) -> Vec<Track> {
    (0..vehicles)
        .map(|i| {
            let mut spec = DriveDistribution::realistic().draw(first_seed + i as u64);
            spec.duration_s = duration_s;
            spec.rate_hz = 1.0;
            spec.outages = Outages::default();
            let mut track = simulate_drive(&spec, &format!("van-{i}")).expect("a valid drive");
            for record in &mut track.records {
                record.label = None;
            }
            track
        })
        .collect()
}

fn fit_request(dataset: &str, fit: v1::FleetFit) -> v1::CreateTrainingJobRequest {
    v1::CreateTrainingJobRequest {
        datasets: vec![dataset.to_string()],
        spec: Some(v1::TrainingSpec {
            seed: 5,
            max_epochs: 1,
            ..v1::TrainingSpec::default()
        }),
        display_name: "fitted to the vans".to_string(),
        fleet_fit: Some(fit),
        ..v1::CreateTrainingJobRequest::default()
    }
}

fn fit_result(operation: &spoofwatch_proto::longrunning::Operation) -> v1::TrainingJobResult {
    let Some(operation::Result::Response(any)) = &operation.result else {
        panic!("a succeeded fit has a response: {operation:?}");
    };
    v1::TrainingJobResult::decode(any.value.as_slice()).expect("decodable result")
}

fn failure(operation: &spoofwatch_proto::longrunning::Operation) -> (i32, String) {
    let Some(operation::Result::Error(status)) = &operation.result else {
        panic!("the fit failed: {operation:?}");
    };
    (status.code, status.message.clone())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_fleet_fit_registers_a_fitted_model_with_its_report_and_serves_once_active() {
    let (_dir, _server, mut clients) = start_server(|_| {}).await;
    fit_report_and_activate(&mut clients).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_fleet_fit_on_postgresql_registers_its_model_and_serves_once_active() {
    let Some(database) = TestDatabase::create("fleet_fit_jobs").await else {
        return;
    };
    let server = TestServer::start(on_postgresql(&database.url)).await;
    let mut clients = Clients::of(&server).await;
    fit_report_and_activate(&mut clients).await;
    drop(clients);
    server.stop().await;
    database.drop_database().await;
}

/// A server on the PostgreSQL database at `url`.
fn on_postgresql(url: &str) -> spoofwatch_server::Config {
    let mut config = spoofwatch_server::Config::with_database(url);
    config.shutdown_grace_secs = 2;
    config
}

/// Reads a WatchJob stream to its end: every state and epoch the job went through.
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
        let next = tokio::time::timeout(Duration::from_secs(600), stream.message())
            .await
            .expect("progress within 10 minutes")
            .expect("the watch stream ends cleanly");
        match next {
            Some(update) => updates.push(update),
            None => return updates,
        }
    }
}

/// Upload, fit (progress watched), report, activate, and detection on the fitted model.
async fn fit_report_and_activate(clients: &mut Clients) {
    let fleet = recordings(4, 1_200.0, 31);
    let dataset = upload_tracks(clients, "four vans", &fleet).await;
    assert_eq!(
        dataset.labelled_rows, 0,
        "a fleet's recordings carry no labels"
    );

    let created = clients
        .training
        .create_training_job(fit_request(&dataset.name, v1::FleetFit::default()))
        .await
        .expect("the fit is accepted")
        .into_inner();
    // Progress: the job is seen running and finishing its epoch before it succeeds.
    let updates = watch_to_end(clients, &created.name).await;
    let states: Vec<v1::JobState> = updates
        .iter()
        .map(|u| v1::JobState::try_from(u.state).expect("a known state"))
        .collect();
    assert!(states.contains(&v1::JobState::Running), "{states:?}");
    assert_eq!(states.last(), Some(&v1::JobState::Succeeded), "{states:?}");
    let last = updates.last().expect("the final update");
    assert_eq!((last.epoch, last.max_epochs), (1, 1));
    assert_eq!(last.history.len(), 1, "one epoch recorded");
    let done = wait_done(&mut clients.operations, &created.name).await;
    let model = trained_model(&done);
    let report = fit_result(&done).fleet_fit.expect("a fit reports");
    // Four drives of 20 minutes split by time: two fit, one validates, one tests.
    let part = |p: &Option<v1::FitPart>| {
        let p = p.expect("part");
        (p.drives, p.vehicles)
    };
    assert_eq!(part(&report.fit), (2, 2));
    assert_eq!(part(&report.validation), (1, 1));
    assert_eq!(part(&report.test), (1, 1));
    assert_eq!(report.rates_hz, vec![1.0]);
    assert_eq!(report.calibration_prior_mean.len(), 3);
    assert_eq!(report.critical_choice, "kept", "{}", report.critical_reason);
    assert!(
        report.critical_reason.contains("validation hours"),
        "{}",
        report.critical_reason
    );
    // The fitted and the starting (bundled) model are scored on the same test drive and attacks.
    let (fitted, starting) = (
        report.fitted.expect("fitted score"),
        report.starting.expect("starting score"),
    );
    // One test drive: the rate's row, then the same drive again under its road kind.
    assert_eq!(fitted.clean.len(), 2, "{:?}", fitted.clean);
    let (rate, road) = (&fitted.clean[0], &fitted.clean[1]);
    assert!((rate.hours - 1_200.0 / 3_600.0).abs() < 0.01);
    assert_eq!(rate.road, "");
    assert!(
        ["town", "open-road"].contains(&road.road.as_str()),
        "{road:?}"
    );
    assert_eq!(
        (road.drives, road.hours, road.warning_onsets),
        (rate.drives, rate.hours, rate.warning_onsets)
    );
    assert_eq!(starting.clean.len(), 2);
    assert_eq!(starting.clean[1].road, road.road);
    let injected: Vec<u64> = fitted.detection.iter().map(|d| d.injected).collect();
    assert_eq!(
        injected,
        starting
            .detection
            .iter()
            .map(|d| d.injected)
            .collect::<Vec<_>>()
    );
    // A test part this small carries every kind of the grid on each of its four pieces.
    assert_eq!(
        injected,
        vec![4; fitted.detection.len()],
        "four pieces of the test drive"
    );
    assert_eq!(fitted.detection.len(), 8, "the detection grid's kinds");

    // The fitted model is stored and carries the fitted GNSS noise.
    let stored = clients
        .models
        .get_model(v1::GetModelRequest {
            name: model.name.clone(),
        })
        .await
        .expect("the fitted model is registered")
        .into_inner();
    assert_eq!(stored.display_name, "fitted to the vans");

    // Activated, it scores the sessions that start without naming a model; the same drive scored
    // by the starting model reads differently.
    clients
        .models
        .set_active_model(v1::SetActiveModelRequest {
            name: model.name.clone(),
        })
        .await
        .expect("the fitted model is activated");
    let drive = track_samples(&recordings(1, 120.0, 77)[0]);
    let batches: Vec<Vec<v1::Sample>> = drive.chunks(20).map(<[_]>::to_vec).collect();
    let (accepted, fitted_run) = stream_batches(clients, ("new-van", ""), &batches, 1).await;
    assert_eq!(
        accepted.model, model.name,
        "a new session runs the active model"
    );
    assert_eq!(fitted_run.len(), drive.len());
    assert!(fitted_run.iter().all(|d| d.model == model.name));
    let (_, starting_run) =
        stream_batches(clients, ("other-van", "models/default"), &batches, 1).await;
    assert!(starting_run.iter().all(|d| d.model == "models/default"));
    let probabilities =
        |run: &[v1::Detection]| run.iter().map(|d| d.probability).collect::<Vec<_>>();
    assert_ne!(
        probabilities(&fitted_run),
        probabilities(&starting_run),
        "the fitted model is another detector"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn recordings_that_cannot_support_a_fit_are_refused_naming_the_field() {
    let (_dir, _server, mut clients) = start_server(|_| {}).await;

    // A claimed rate out of range is refused when the job is created.
    let status = clients
        .training
        .create_training_job(fit_request(
            "datasets/any",
            v1::FleetFit {
                sample_rate_hz: -1.0,
                ..v1::FleetFit::default()
            },
        ))
        .await
        .expect_err("a negative rate");
    assert_eq!(status.code(), Code::InvalidArgument);
    assert!(
        status.message().contains("fleet_fit.sample_rate_hz"),
        "{}",
        status.message()
    );

    // One vehicle's recordings, more than an hour of them: no fleet to fit priors to.
    let one = upload_tracks(&mut clients, "one van", &recordings(1, 4_000.0, 7)).await;
    let created = clients
        .training
        .create_training_job(fit_request(&one.name, v1::FleetFit::default()))
        .await
        .expect("accepted: the data is read by the job")
        .into_inner();
    let (code, message) = failure(&wait_done(&mut clients.operations, &created.name).await);
    assert_eq!(code, Code::InvalidArgument as i32);
    assert!(
        message.contains("datasets") && message.contains("at least 2"),
        "{message}"
    );

    // Four vans at 1 Hz said to be sampled at 5 Hz.
    let four = upload_tracks(&mut clients, "four vans", &recordings(4, 1_200.0, 11)).await;
    let created = clients
        .training
        .create_training_job(fit_request(
            &four.name,
            v1::FleetFit {
                sample_rate_hz: 5.0,
                ..v1::FleetFit::default()
            },
        ))
        .await
        .expect("accepted")
        .into_inner();
    let (code, message) = failure(&wait_done(&mut clients.operations, &created.name).await);
    assert_eq!(code, Code::InvalidArgument as i32);
    assert!(message.contains("fleet_fit.sample_rate_hz"), "{message}");
    assert!(message.contains("5 Hz was claimed"), "{message}");
}

/// Twelve vehicles' 30-minute recordings: a fit on them trains for many epochs (early stopping
/// waits 12 epochs without progress), so a cancellation or a stop sent once the first epoch is done
/// reaches the job while it trains.
fn long_fleet() -> Vec<Track> {
    recordings(12, 1_800.0, 51)
}

fn long_fit(dataset: &str) -> v1::CreateTrainingJobRequest {
    let mut request = fit_request(dataset, v1::FleetFit::default());
    if let Some(spec) = request.spec.as_mut() {
        spec.max_epochs = 200;
    }
    request
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

fn state_of(operation: &longrunning::Operation) -> v1::JobState {
    v1::JobState::try_from(metadata_of(operation).state).expect("a known job state")
}

/// Polls until the job has finished its first epoch (it trains now); panics if it ends first.
async fn wait_for_first_epoch(clients: &mut Clients, name: &str) {
    let deadline = Instant::now() + Duration::from_secs(600);
    loop {
        let operation = get(clients, name).await;
        assert!(
            !operation.done,
            "the fit ended before it was interrupted: {operation:?}"
        );
        if metadata_of(&operation).epoch >= 1 {
            return;
        }
        assert!(Instant::now() < deadline, "{name} never finished an epoch");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// The registered models' names, sorted.
async fn model_names(clients: &mut Clients) -> Vec<String> {
    let mut names: Vec<String> = clients
        .models
        .list_models(v1::ListModelsRequest::default())
        .await
        .expect("ListModels works")
        .into_inner()
        .models
        .into_iter()
        .map(|m| m.name)
        .collect();
    names.sort();
    names
}

fn error_of(operation: &longrunning::Operation) -> (i32, String) {
    let Some(operation::Result::Error(status)) = &operation.result else {
        panic!("the job ended with an error: {operation:?}");
    };
    (status.code, status.message.clone())
}

/// Cancels a fit while it trains: CANCELLED, no model registered, and the store consistent (the
/// job listed done, deletable, its slot free for the next fit, which succeeds).
async fn cancel_a_running_fit(clients: &mut Clients) {
    let before = model_names(clients).await;
    let dataset = upload_tracks(clients, "twelve vans", &long_fleet()).await;
    let job = clients
        .training
        .create_training_job(long_fit(&dataset.name))
        .await
        .expect("the fit is accepted")
        .into_inner();
    wait_for_first_epoch(clients, &job.name).await;
    clients
        .operations
        .cancel_operation(longrunning::CancelOperationRequest {
            name: job.name.clone(),
        })
        .await
        .expect("CancelOperation works");
    let cancelled = wait_done(&mut clients.operations, &job.name).await;
    assert_eq!(error_of(&cancelled).0, Code::Cancelled as i32);
    assert_eq!(state_of(&cancelled), v1::JobState::Cancelled);
    let metadata = metadata_of(&cancelled);
    assert!(
        metadata.epoch >= 1 && metadata.epoch < 200,
        "cancelled mid-way: {metadata:?}"
    );
    assert_eq!(model_names(clients).await, before, "no model is registered");

    let done: Vec<String> = clients
        .operations
        .list_operations(longrunning::ListOperationsRequest {
            filter: "kind=training AND done=true".to_string(),
            ..longrunning::ListOperationsRequest::default()
        })
        .await
        .expect("ListOperations works")
        .into_inner()
        .operations
        .into_iter()
        .map(|o| o.name)
        .collect();
    assert_eq!(done, std::slice::from_ref(&job.name));
    clients
        .operations
        .delete_operation(longrunning::DeleteOperationRequest {
            name: job.name.clone(),
        })
        .await
        .expect("a cancelled job can be deleted");

    // The only job slot is free again: the next fit runs and registers its model (on the four
    // vans of the fit test, which hold an operating point).
    let vans = upload_tracks(clients, "four vans", &recordings(4, 1_200.0, 31)).await;
    let next = clients
        .training
        .create_training_job(fit_request(&vans.name, v1::FleetFit::default()))
        .await
        .expect("the next fit is accepted")
        .into_inner();
    let model = trained_model(&wait_done(&mut clients.operations, &next.name).await);
    assert_eq!(model_names(clients).await.len(), before.len() + 1);
    assert!(model_names(clients).await.contains(&model.name));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_fit_cancelled_while_it_runs_registers_nothing() {
    let (_dir, _server, mut clients) = start_server(|config| config.max_running_jobs = 1).await;
    cancel_a_running_fit(&mut clients).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_fit_cancelled_while_it_runs_on_postgresql_registers_nothing() {
    let Some(database) = TestDatabase::create("fleet_fit_jobs_cancel").await else {
        return;
    };
    let mut config = on_postgresql(&database.url);
    config.max_running_jobs = 1;
    let server = TestServer::start(config).await;
    let mut clients = Clients::of(&server).await;
    cancel_a_running_fit(&mut clients).await;
    drop(clients);
    server.stop().await;
    database.drop_database().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_fit_running_when_its_server_stops_cleanly_is_cancelled_and_stays_so() {
    let dir = tempfile::tempdir().expect("temp dir");
    // A cancelled fit stops at its next batch: the server's default grace of 10 s leaves it the
    // time to record the cancellation.
    let config = || {
        let mut config = test_config(dir.path());
        config.shutdown_grace_secs = 10;
        config
    };
    let server = TestServer::start(config()).await;
    let mut clients = Clients::of(&server).await;
    let before = model_names(&mut clients).await;
    let dataset = upload_tracks(&mut clients, "twelve vans", &long_fleet()).await;
    let job = clients
        .training
        .create_training_job(long_fit(&dataset.name))
        .await
        .expect("the fit is accepted")
        .into_inner();
    wait_for_first_epoch(&mut clients, &job.name).await;
    drop(clients);
    // The shutdown cancels the running jobs and waits (within its grace) for them to record it.
    server
        .stop_within(Duration::from_secs(60))
        .await
        .expect("the server stops cleanly");

    let server = TestServer::start(config()).await;
    let mut clients = Clients::of(&server).await;
    let after = get(&mut clients, &job.name).await;
    assert!(after.done, "{after:?}");
    assert_eq!(state_of(&after), v1::JobState::Cancelled);
    assert_eq!(error_of(&after).0, Code::Cancelled as i32);
    assert_eq!(
        model_names(&mut clients).await,
        before,
        "no model is registered"
    );
    drop(clients);
    server.stop().await;
}

/// Kills the server (SIGKILL) while a fit trains and starts it again on the same database: the
/// restart fails the job it left, ABORTED, as it does every training job, and nothing is
/// registered.
async fn a_fit_killed_mid_way_is_aborted_by_the_restart(database: &str) {
    let server = ReplicaProcess::start(
        env!("CARGO_BIN_EXE_spoofwatch-test-replica"),
        database,
        "fitter",
    );
    let mut clients = server.clients().await;
    let before = model_names(&mut clients).await;
    let dataset = upload_tracks(&mut clients, "twelve vans", &long_fleet()).await;
    let job = clients
        .training
        .create_training_job(long_fit(&dataset.name))
        .await
        .expect("the fit is accepted")
        .into_inner();
    wait_for_first_epoch(&mut clients, &job.name).await;
    drop(clients);
    drop(server);

    let server = ReplicaProcess::start(
        env!("CARGO_BIN_EXE_spoofwatch-test-replica"),
        database,
        "fitter",
    );
    let mut clients = server.clients().await;
    let after = get(&mut clients, &job.name).await;
    assert!(after.done, "the restart ends the job it left: {after:?}");
    assert_eq!(state_of(&after), v1::JobState::Failed);
    let (code, message) = error_of(&after);
    assert_eq!(code, Code::Aborted as i32, "{message}");
    assert!(message.contains("server restarted"), "{message}");
    assert_eq!(
        model_names(&mut clients).await,
        before,
        "no model is registered"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_fit_killed_mid_way_is_aborted_by_the_restart_on_sqlite() {
    let dir = tempfile::tempdir().expect("temp dir");
    let database = dir.path().join("spoofwatch.db");
    a_fit_killed_mid_way_is_aborted_by_the_restart(&database.display().to_string()).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_fit_killed_mid_way_is_aborted_by_the_restart_on_postgresql() {
    let Some(database) = TestDatabase::create("fleet_fit_jobs_kill").await else {
        return;
    };
    a_fit_killed_mid_way_is_aborted_by_the_restart(&database.url).await;
    database.drop_database().await;
}
