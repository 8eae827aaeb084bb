//! Evaluation jobs agree with the offline evaluation; their operations can be filtered and
//! deleted, and a deleted dataset can no longer be evaluated.

use std::sync::Arc;

use prost::Message;
use spoofwatch_core::data::read;
use spoofwatch_core::evaluation::evaluate_tracks;
use spoofwatch_core::metrics::EventRules;
use spoofwatch_core::model::artifact::ModelArtifact;
use spoofwatch_core::scenario::AttackKind;
use spoofwatch_proto::longrunning::{self, operation};
use spoofwatch_proto::v1;
use spoofwatch_tests::{
    attacked_drive, export_model, normal_drive, start_server, telemetry_csv, upload_tracks,
    wait_done,
};
use tonic::Code;

const TOLERANCE: f64 = 1e-12;

fn close(a: f64, b: f64) -> bool {
    (a - b).abs() <= TOLERANCE
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_evaluation_job_matches_the_offline_evaluation() {
    let (_dir, server, mut clients) = start_server(|_| {}).await;
    let ramp = AttackKind::RampDrift { velocity_mps: 2.0 };
    let fleet = vec![
        normal_drive("eval-0", 200.0, 31),
        attacked_drive("eval-1", 200.0, 32, ramp, 80.0, 60.0),
        attacked_drive("eval-2", 200.0, 33, ramp, 120.0, 50.0),
    ];
    let dataset = upload_tracks(&mut clients, "evaluation fleet", &fleet).await;

    let job = clients
        .training
        .create_evaluation_job(v1::CreateEvaluationJobRequest {
            model: String::new(),
            datasets: vec![dataset.name.clone()],
        })
        .await
        .expect("the evaluation job is accepted")
        .into_inner();
    let done = wait_done(&mut clients.operations, &job.name).await;
    assert!(done.done);
    let Some(operation::Result::Response(any)) = &done.result else {
        panic!("the evaluation succeeded: {done:?}");
    };
    assert_eq!(
        any.type_url,
        "type.googleapis.com/spoofwatch.v1.EvaluationJobResult"
    );
    let result = v1::EvaluationJobResult::decode(any.value.as_slice()).expect("decodable");
    assert_eq!(
        result.model, "models/default",
        "empty model = the active one"
    );

    // The same evaluation offline, on the tracks as the server parsed them from the CSV.
    let artifact = export_model(&mut clients.models, "models/default").await;
    let artifact = Arc::new(ModelArtifact::from_slice(&artifact).expect("an artifact"));
    let tracks = read(telemetry_csv(&fleet).as_slice(), "fleet")
        .expect("the CSV parses")
        .tracks;
    let offline = evaluate_tracks(&artifact, &tracks, EventRules::Spec);
    let overall = result.overall.as_ref().expect("overall metrics");
    let expected = &offline.overall;
    assert_eq!(overall.events, 2, "one event per attacked drive");
    assert_eq!(
        (overall.events, overall.detected_events, overall.valid_rows),
        (
            expected.events,
            expected.detected_events,
            expected.valid_rows
        )
    );
    assert!(close(overall.f1, expected.f1) && close(overall.fpr, expected.fpr));
    assert!(close(overall.recall, expected.recall) && close(overall.adr, expected.adr));
    match (overall.auroc, expected.auroc) {
        (Some(a), Some(b)) => assert!(close(a, b), "AUROC {a} vs {b}"),
        (a, b) => assert_eq!(a, b),
    }
    let mut vehicles: Vec<&String> = result.per_vehicle.keys().collect();
    vehicles.sort();
    assert_eq!(vehicles, ["eval-0", "eval-1", "eval-2"]);

    // Filters, deletion of a finished operation, deletion of a dataset.
    for (filter, count) in [
        ("kind=evaluation", 1),
        ("kind=training", 0),
        ("done=true", 1),
    ] {
        let listed = clients
            .operations
            .list_operations(longrunning::ListOperationsRequest {
                filter: filter.into(),
                ..longrunning::ListOperationsRequest::default()
            })
            .await
            .expect("ListOperations")
            .into_inner();
        assert_eq!(listed.operations.len(), count, "filter {filter}");
    }
    let status = clients
        .operations
        .list_operations(longrunning::ListOperationsRequest {
            filter: "state=running".into(),
            ..longrunning::ListOperationsRequest::default()
        })
        .await
        .expect_err("an unsupported filter is refused");
    assert_eq!(status.code(), Code::InvalidArgument);
    clients
        .operations
        .delete_operation(longrunning::DeleteOperationRequest {
            name: job.name.clone(),
        })
        .await
        .expect("a finished operation can be deleted");
    let status = clients
        .operations
        .get_operation(longrunning::GetOperationRequest { name: job.name })
        .await
        .expect_err("the operation is gone");
    assert_eq!(status.code(), Code::NotFound);
    clients
        .datasets
        .delete_dataset(v1::DeleteDatasetRequest {
            name: dataset.name.clone(),
        })
        .await
        .expect("DeleteDataset");
    let status = clients
        .training
        .create_evaluation_job(v1::CreateEvaluationJobRequest {
            model: String::new(),
            datasets: vec![dataset.name],
        })
        .await
        .expect_err("the dataset is gone");
    assert_eq!(status.code(), Code::NotFound);
    drop(clients);
    server.stop().await;
}
