//! Fleet-fit jobs through the server: a fleet's attack-free recordings uploaded, the detector fitted
//! to them as a training job (progress watched, the fitted model registered with the fit's report),
//! and recordings that cannot support a fit refused with the field at fault.

use prost::Message;
use spoofwatch_core::sample::Track;
use spoofwatch_core::scenario::{DriveDistribution, Outages, simulate_drive};
use spoofwatch_proto::longrunning::operation;
use spoofwatch_proto::v1;
use spoofwatch_tests::{start_server, trained_model, upload_tracks, wait_done};
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
async fn a_fleet_fit_registers_a_fitted_model_with_its_report() {
    let (_dir, _server, mut clients) = start_server(|_| {}).await;
    let fleet = recordings(4, 1_200.0, 31);
    let dataset = upload_tracks(&mut clients, "four vans", &fleet).await;
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
    assert_eq!(fitted.clean.len(), 1);
    assert!((fitted.clean[0].hours - 1_200.0 / 3_600.0).abs() < 0.01);
    let injected: Vec<u64> = fitted.detection.iter().map(|d| d.injected).collect();
    assert_eq!(
        injected,
        starting
            .detection
            .iter()
            .map(|d| d.injected)
            .collect::<Vec<_>>()
    );
    assert_eq!(
        injected.iter().sum::<u64>(),
        4,
        "four pieces of the test drive"
    );

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
