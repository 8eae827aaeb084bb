//! Heavy work does not starve the server: while two uploads of 100,000 structured records (each
//! record its own vehicle) are converted, parsed and stored, health checks are still answered
//! promptly. Uploaded records are grouped by vehicle in time linear in their number, and the
//! conversion and parsing run on the bounded pool of heavy work, off the runtime's threads. A
//! model whose cost per sample exceeds the bound is refused at import, and a job whose datasets
//! hold more than running jobs may read at once is refused at creation.

use std::time::{Duration, Instant};

use spoofwatch_proto::v1;
use spoofwatch_proto::v1::upload_dataset_request::Kind;
use spoofwatch_tests::{Clients, normal_drive, start_server, upload_tracks, wait_done};
use tonic_health::pb::HealthCheckRequest;

const RECORDS: usize = 100_000;
/// Far above a health check's cost even on a loaded CI machine, far below the stall an upload
/// that held the runtime would cause (seconds to minutes).
const HEALTH_BOUND: Duration = Duration::from_secs(2);

/// An upload of `RECORDS` one-sample vehicles named `{prefix}-{i}`.
fn one_sample_vehicles(prefix: &str) -> Vec<v1::UploadDatasetRequest> {
    let header = Kind::Header(v1::UploadDatasetHeader {
        display_name: prefix.to_string(),
    });
    let record = |i: usize| v1::LabelledSample {
        vehicle_id: format!("{prefix}-{i}"),
        sample: Some(v1::Sample {
            timestamp_s: 1.0,
            latitude_deg: 45.0 + i as f64 * 1e-6,
            longitude_deg: 7.0,
            speed_mps: 10.0,
            heading_deg: 90.0,
            ..Default::default()
        }),
        spoofed: Some(false),
    };
    let batches = (0..RECORDS).step_by(5_000).map(|start| {
        Kind::Records(v1::RecordBatch {
            records: (start..start + 5_000).map(record).collect(),
        })
    });
    std::iter::once(header)
        .chain(batches)
        .map(|kind| v1::UploadDatasetRequest { kind: Some(kind) })
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn health_is_answered_while_large_record_uploads_are_stored() {
    let (_dir, _server, clients) = start_server(|_| {}).await;
    let uploads: Vec<_> = ["fleet-a", "fleet-b"]
        .into_iter()
        .map(|prefix| {
            let mut datasets = clients.datasets.clone();
            let messages = one_sample_vehicles(prefix);
            tokio::spawn(async move {
                datasets
                    .upload_dataset(tokio_stream::iter(messages))
                    .await
                    .map(tonic::Response::into_inner)
            })
        })
        .collect();

    let mut health = clients.health.clone();
    let mut slowest = Duration::ZERO;
    let mut checks = 0;
    while uploads.iter().any(|upload| !upload.is_finished()) {
        let asked = Instant::now();
        tokio::time::timeout(
            Duration::from_secs(60),
            health.check(HealthCheckRequest::default()),
        )
        .await
        .expect("health answers within a minute")
        .expect("health answers");
        slowest = slowest.max(asked.elapsed());
        checks += 1;
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    for upload in uploads {
        let dataset = upload.await.expect("joined").expect("the upload is stored");
        assert_eq!(dataset.rows, RECORDS as u64);
        assert_eq!(dataset.vehicles, RECORDS as u32);
    }
    assert!(checks > 0);
    assert!(
        slowest < HEALTH_BOUND,
        "a health check waited {slowest:?} during the uploads ({checks} checks)"
    );
    drop::<Clients>(clients);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_model_too_costly_per_sample_is_refused_at_import() {
    let (_dir, server, mut clients) = start_server(|_| {}).await;
    let mut artifact: serde_json::Value =
        serde_json::from_slice(spoofwatch_server::models::registry::BUNDLED_MODEL).expect("JSON");
    // Widths within every per-layer limit whose product is a model 100 times the bundled one.
    for width in ["d_s", "d_zeta", "d_h"] {
        artifact["model"]["config"][width] = serde_json::json!(1024);
    }
    let bytes = serde_json::to_vec(&artifact).expect("JSON");
    use v1::import_model_request::Kind;
    let messages = [
        Kind::Header(v1::ImportModelHeader::default()),
        Kind::Chunk(bytes),
    ]
    .map(|kind| v1::ImportModelRequest { kind: Some(kind) });
    let refused = clients
        .models
        .import_model(tokio_stream::iter(messages))
        .await
        .expect_err("too costly a model");
    assert_eq!(refused.code(), tonic::Code::InvalidArgument);
    assert!(
        refused.message().contains("model.config"),
        "{}",
        refused.message()
    );
    assert!(
        refused.message().contains("parameters"),
        "{}",
        refused.message()
    );
    drop(clients);
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn uploads_together_hold_at_most_the_upload_memory() {
    let (_dir, server, mut clients) = start_server(|config| config.upload_memory_mib = 1).await;
    use v1::upload_dataset_request::Kind as Upload;
    let upload = |chunks: usize| {
        std::iter::once(Upload::Header(v1::UploadDatasetHeader::default()))
            .chain((0..chunks).map(|_| Upload::CsvChunk(vec![b'x'; 512 * 1024])))
            .map(|kind| v1::UploadDatasetRequest { kind: Some(kind) })
            .collect::<Vec<_>>()
    };
    let refused = clients
        .datasets
        .upload_dataset(tokio_stream::iter(upload(4)))
        .await
        .expect_err("2 MiB against a 1 MiB budget");
    assert_eq!(refused.code(), tonic::Code::ResourceExhausted);
    assert!(
        refused.message().contains("--upload-memory-mib"),
        "{}",
        refused.message()
    );
    // The refused upload gave its part back: one within the budget is read (and refused only
    // for not being CSV).
    let read = clients
        .datasets
        .upload_dataset(tokio_stream::iter(upload(1)))
        .await
        .expect_err("not CSV");
    assert_eq!(read.code(), tonic::Code::InvalidArgument);
    drop(clients);
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_job_whose_datasets_exceed_the_job_input_is_refused() {
    let (_dir, server, mut clients) = start_server(|config| config.job_input_mib = 1).await;
    let fleet: Vec<_> = (0..10)
        .map(|i| normal_drive(&format!("long-{i}"), 1_800.0, i))
        .collect();
    let large = upload_tracks(&mut clients, "large", &fleet).await;
    assert!(large.size_bytes > 1 << 20, "{} bytes", large.size_bytes);
    let small = upload_tracks(&mut clients, "small", &fleet[..1]).await;
    let evaluate = |dataset: &v1::Dataset| v1::CreateEvaluationJobRequest {
        model: String::new(),
        datasets: vec![dataset.name.clone()],
    };

    let refused = clients
        .training
        .create_evaluation_job(evaluate(&large))
        .await
        .expect_err("more than 1 MiB of input");
    assert_eq!(refused.code(), tonic::Code::InvalidArgument);
    let violations = tonic_types::StatusExt::get_details_bad_request(&refused)
        .expect("field violations")
        .field_violations;
    assert_eq!(violations.len(), 1, "{violations:?}");
    assert_eq!(violations[0].field, "datasets");
    assert!(
        violations[0].description.contains("--job-input-mib"),
        "{violations:?}"
    );

    let job = clients
        .training
        .create_evaluation_job(evaluate(&small))
        .await
        .expect("a job within the input budget is accepted")
        .into_inner();
    let done = wait_done(&mut clients.operations, &job.name).await;
    assert!(
        matches!(
            done.result,
            Some(spoofwatch_proto::longrunning::operation::Result::Response(
                _
            ))
        ),
        "{done:?}"
    );
    drop(clients);
    server.stop().await;
}
