//! Invalid input gets its documented code, and harms neither a healthy stream running at the same
//! time nor stored data; oversized messages are refused and the server keeps serving.

use spoofwatch_proto::v1;
use spoofwatch_tests::{
    Clients, TestServer, active_model, batch_request, code_of, expect_item_error, field_violations,
    final_code, normal_drive, open_stream, start_request, start_server, start_stream, test_config,
    track_samples,
};
use tokio::task::JoinHandle;
use tonic::Code;
use tonic_types::StatusExt;

/// Samples the healthy stream sends, in batches of [`HEALTHY_BATCH`].
const HEALTHY_SAMPLES: usize = 300;
const HEALTHY_BATCH: usize = 10;

/// Streams a normal drive and returns every detection's timestamp, checking seqs on the way.
fn spawn_healthy_stream(clients: &Clients) -> JoinHandle<Vec<f64>> {
    let clients = clients.clone();
    tokio::spawn(async move {
        let track = normal_drive("healthy", (HEALTHY_SAMPLES - 1) as f64, 99);
        let (mut stream, _) = start_stream(&clients, "healthy", "").await;
        let mut timestamps = Vec::new();
        for (seq, batch) in track_samples(&track).chunks(HEALTHY_BATCH).enumerate() {
            let detections = stream
                .detect(seq as u64 + 1, batch.to_vec())
                .await
                .expect("one detection per sample, for this batch");
            timestamps.extend(detections.iter().map(|d| d.timestamp_s));
            // Interleave with the bad calls of the other tasks.
            tokio::task::yield_now().await;
        }
        stream.finish().await.expect("ends with OK");
        timestamps
    })
}

/// `n` consecutive one-second samples of a drive starting at `t0`.
fn samples(t0: f64, n: usize) -> Vec<v1::Sample> {
    let track = normal_drive("bad", (n - 1) as f64, 5);
    let mut samples = track_samples(&track);
    for s in &mut samples {
        s.timestamp_s += t0;
    }
    samples
}

async fn bad_samples_are_refused_per_batch_and_the_stream_goes_on(clients: &mut Clients) {
    let (mut stream, _) = start_stream(clients, "bad-samples", "").await;
    let good = samples(0.0, 30);
    stream
        .detect(1, good[..10].to_vec())
        .await
        .expect("one detection per sample, for this batch");

    let mut nan = good[10..15].to_vec();
    nan[2].latitude_deg = f64::NAN;
    let status = expect_item_error(&mut stream, 2, nan).await;
    assert_eq!(status.code, Code::InvalidArgument as i32, "{status:?}");
    let fields: Vec<String> = field_violations(&status)
        .into_iter()
        .map(|(f, _)| f)
        .collect();
    assert_eq!(fields, ["batch.samples[2].latitude_deg"]);

    let mut out_of_range = good[10..15].to_vec();
    out_of_range[4].latitude_deg = 91.0;
    let status = expect_item_error(&mut stream, 3, out_of_range).await;
    assert_eq!(status.code, Code::InvalidArgument as i32);
    let fields: Vec<String> = field_violations(&status)
        .into_iter()
        .map(|(f, _)| f)
        .collect();
    assert_eq!(fields, ["batch.samples[4].latitude_deg"]);

    // Timestamps going backwards (t = 3, 4 s after t = 9 s) are refused too, each one named.
    let status = expect_item_error(&mut stream, 4, good[3..5].to_vec()).await;
    assert_eq!(status.code, Code::InvalidArgument as i32);
    let fields: Vec<String> = field_violations(&status)
        .into_iter()
        .map(|(f, _)| f)
        .collect();
    assert_eq!(
        fields,
        [
            "batch.samples[0].timestamp_s",
            "batch.samples[1].timestamp_s"
        ]
    );

    // Milliseconds sent once into a seconds stream: refused with a short, readable reason.
    let mut millis = good[10..11].to_vec();
    millis[0].timestamp_s = 1_700_000_000_000.0;
    let status = expect_item_error(&mut stream, 4, millis).await;
    let violations = field_violations(&status);
    assert_eq!(violations[0].0, "batch.samples[0].timestamp_s");
    assert!(
        violations[0].1.contains("1.700e12 s ahead") && violations[0].1.len() < 200,
        "{violations:?}"
    );

    // The rejected batches changed nothing: the next good batch continues the same trajectory.
    let detections = stream
        .detect(5, good[10..20].to_vec())
        .await
        .expect("one detection per sample, for this batch");
    let evidence = detections[0].evidence.as_ref().expect("evidence");
    assert_eq!(evidence.trajectory, 0, "no new trajectory was started");
    assert!(
        (evidence.delta_t_s - 1.0).abs() < 1e-12,
        "δ_t continues from t = 9 s"
    );
    let session = clients
        .detection
        .get_session(v1::GetSessionRequest {
            vehicle_id: "bad-samples".into(),
        })
        .await
        .expect("the session exists")
        .into_inner();
    assert_eq!((session.samples, session.last_seq), (20, 5));
    drop(stream);
}

/// Names and free text are bounded before they are stored or echoed: a 20,000-character vehicle id
/// or display name gets a short INVALID_ARGUMENT, not a grpc-message too large for the client.
async fn long_names_are_refused_without_being_echoed(clients: &mut Clients) {
    let long = "x".repeat(20_000);
    let status = clients
        .detection
        .get_session(v1::GetSessionRequest {
            vehicle_id: long.clone(),
        })
        .await
        .expect_err("too long");
    assert_eq!(status.code(), Code::InvalidArgument, "{status:?}");
    assert!(status.message().len() < 200, "{}", status.message());
    let header = v1::UploadDatasetRequest {
        kind: Some(v1::upload_dataset_request::Kind::Header(
            v1::UploadDatasetHeader { display_name: long },
        )),
    };
    let chunk = v1::UploadDatasetRequest {
        kind: Some(v1::upload_dataset_request::Kind::CsvChunk(
            b"vehicle_id,timestamp,latitude,longitude,speed_mps,heading_deg\nv,0,32,-110,1,0\n"
                .to_vec(),
        )),
    };
    let status = clients
        .datasets
        .upload_dataset(tokio_stream::iter(vec![header, chunk]))
        .await
        .expect_err("too long");
    assert_eq!(status.code(), Code::InvalidArgument, "{status:?}");
    assert_eq!(first_violated_field(&status), "header.display_name");
    assert!(status.message().len() < 200, "{}", status.message());
}

async fn a_stream_must_start_with_session_start(clients: &mut Clients) {
    let result = open_stream(clients, batch_request(1, samples(0.0, 3))).await;
    let code = match result {
        Ok(mut stream) => final_code(&mut stream).await,
        Err(error) => code_of(&error),
    };
    assert_eq!(code, Code::InvalidArgument);
}

async fn unknown_models_are_not_found(clients: &mut Clients) {
    let result = open_stream(clients, start_request("ghost-car", "models/nope", false)).await;
    let status = match result {
        Ok(mut stream) => stream.next().await.expect_err("the call fails"),
        Err(error) => error,
    };
    assert_eq!(code_of(&status), Code::NotFound, "{status:?}");
    let status = clients
        .models
        .get_model(v1::GetModelRequest {
            name: "models/nope".into(),
        })
        .await
        .expect_err("no such model");
    assert_eq!(status.code(), Code::NotFound);
    let status = clients
        .detection
        .detect(v1::DetectRequest {
            model: "nope".into(),
            samples: samples(0.0, 2),
            ..v1::DetectRequest::default()
        })
        .await
        .expect_err("no such model");
    assert_eq!(status.code(), Code::NotFound);
}

async fn unary_bad_samples_carry_field_violations(clients: &mut Clients) {
    let mut bad = samples(0.0, 4);
    bad[1].speed_mps = f64::INFINITY;
    let status = clients
        .detection
        .detect(v1::DetectRequest {
            samples: bad,
            ..v1::DetectRequest::default()
        })
        .await
        .expect_err("an infinite speed is refused");
    assert_eq!(status.code(), Code::InvalidArgument);
    assert_eq!(first_violated_field(&status), "samples[1].speed_mps");
}

async fn imports_outside_the_data_directory_are_denied(clients: &mut Clients, outside: &str) {
    for path in ["../outside.csv", outside, "link-to-outside.csv"] {
        let status = clients
            .datasets
            .import_dataset(v1::ImportDatasetRequest {
                path: path.to_string(),
                display_name: String::new(),
            })
            .await
            .expect_err("a path outside the data directory is refused");
        assert_eq!(status.code(), Code::PermissionDenied, "{path}: {status:?}");
    }
}

async fn malformed_uploads_are_refused_and_nothing_is_stored(clients: &mut Clients) {
    use v1::import_model_request::Kind as ModelKind;
    use v1::upload_dataset_request::Kind as DatasetKind;
    let header = v1::ImportModelRequest {
        kind: Some(ModelKind::Header(v1::ImportModelHeader {
            display_name: "garbage".into(),
            activate: true,
        })),
    };
    let garbage = v1::ImportModelRequest {
        kind: Some(ModelKind::Chunk(b"{\"not\": \"a model\"}".to_vec())),
    };
    let status = clients
        .models
        .import_model(tokio_stream::iter([header, garbage]))
        .await
        .expect_err("a malformed artifact is refused");
    assert_eq!(status.code(), Code::InvalidArgument, "{status:?}");
    assert_eq!(first_violated_field(&status), "artifact.schema_version");

    let csv = "vehicle_id,timestamp,latitude,longitude,speed_mps,heading_deg\n\
               car,0,32.2,-110.9,1.0,0\n\
               car,1,north,-110.9,1.0,0\n";
    let messages = [
        DatasetKind::Header(v1::UploadDatasetHeader {
            display_name: "broken".into(),
        }),
        DatasetKind::CsvChunk(csv.as_bytes().to_vec()),
    ]
    .map(|kind| v1::UploadDatasetRequest { kind: Some(kind) });
    let status = clients
        .datasets
        .upload_dataset(tokio_stream::iter(messages))
        .await
        .expect_err("a CSV with a bad field is refused");
    assert_eq!(status.code(), Code::InvalidArgument, "{status:?}");
    assert!(
        status.message().contains(":3:") && status.message().contains("latitude"),
        "the error names line 3 and the column: {}",
        status.message()
    );
}

async fn the_active_model_cannot_be_deleted(clients: &mut Clients) {
    let active = active_model(&mut clients.models).await;
    let status = clients
        .models
        .delete_model(v1::DeleteModelRequest {
            name: active.name.clone(),
        })
        .await
        .expect_err("the active model cannot be deleted");
    assert_eq!(status.code(), Code::FailedPrecondition);
    assert_eq!(active_model(&mut clients.models).await.name, active.name);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_input_gets_its_code_without_harming_other_streams_or_data() {
    let dir = tempfile::tempdir().expect("temp dir");
    let data_dir = dir.path().join("data");
    std::fs::create_dir(&data_dir).expect("data dir");
    let outside = dir.path().join("outside.csv");
    std::fs::write(&outside, "not,a,dataset\n").expect("outside file");
    std::os::unix::fs::symlink(&outside, data_dir.join("link-to-outside.csv")).expect("symlink");
    let mut config = test_config(dir.path());
    config.data_dir = Some(data_dir);
    let server = TestServer::start(config).await;
    let mut clients = Clients::of(&server).await;
    let models_before = clients
        .models
        .list_models(v1::ListModelsRequest::default())
        .await
        .expect("ListModels")
        .into_inner();

    let healthy = spawn_healthy_stream(&clients);
    bad_samples_are_refused_per_batch_and_the_stream_goes_on(&mut clients).await;
    a_stream_must_start_with_session_start(&mut clients).await;
    long_names_are_refused_without_being_echoed(&mut clients).await;
    unknown_models_are_not_found(&mut clients).await;
    unary_bad_samples_carry_field_violations(&mut clients).await;
    imports_outside_the_data_directory_are_denied(&mut clients, &outside.display().to_string())
        .await;
    malformed_uploads_are_refused_and_nothing_is_stored(&mut clients).await;
    the_active_model_cannot_be_deleted(&mut clients).await;

    let timestamps = healthy.await.expect("the healthy stream task succeeds");
    let expected: Vec<f64> = (0..HEALTHY_SAMPLES).map(|i| i as f64).collect();
    assert_eq!(
        timestamps, expected,
        "the healthy stream got every detection, in order"
    );

    let models_after = clients
        .models
        .list_models(v1::ListModelsRequest::default())
        .await
        .expect("ListModels")
        .into_inner();
    assert_eq!(models_after, models_before, "stored models are untouched");
    let datasets = clients
        .datasets
        .list_datasets(v1::ListDatasetsRequest::default())
        .await
        .expect("ListDatasets")
        .into_inner();
    assert!(datasets.datasets.is_empty(), "nothing was imported");
    drop(clients);
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn oversized_messages_are_refused_and_the_server_keeps_serving() {
    let (_dir, server, mut clients) = start_server(|config| config.max_message_bytes = 2048).await;
    let big = samples(0.0, 200); // ~10 KB encoded

    let status = clients
        .detection
        .detect(v1::DetectRequest {
            samples: big.clone(),
            ..v1::DetectRequest::default()
        })
        .await
        .expect_err("a message above max_message_bytes is refused");
    // tonic reports a decode-limit violation as OUT_OF_RANGE, naming the size and the limit (what
    // every client sees, and what the API guide documents: not RESOURCE_EXHAUSTED, which clients
    // retry, as the same message would be refused again).
    assert_eq!(status.code(), Code::OutOfRange, "{status:?}");
    assert!(
        status.message().contains("the limit is: 2048 bytes"),
        "{status:?}"
    );

    let (mut stream, _) = start_stream(&clients, "oversized", "").await;
    stream
        .detect(1, big[..10].to_vec())
        .await
        .expect("one detection per sample, for this batch");
    stream
        .send_batch(2, big[10..].to_vec())
        .await
        .expect("the request stream is open");
    assert_eq!(final_code(&mut stream).await, Code::OutOfRange);

    // Small messages still work, on the same connection.
    let response = clients
        .detection
        .detect(v1::DetectRequest {
            samples: big[..5].to_vec(),
            ..v1::DetectRequest::default()
        })
        .await
        .expect("a small batch is fine")
        .into_inner();
    assert_eq!(response.detections.len(), 5);
    let (mut again, accepted) = start_stream(&clients, "oversized", "").await;
    assert!(
        accepted.resumed,
        "the session survived its stream's failure"
    );
    assert_eq!(
        accepted.samples_seen, 10,
        "the oversized batch changed nothing"
    );
    let next = again
        .detect(3, big[10..12].to_vec())
        .await
        .expect("one detection per sample, for this batch");
    assert!(matches!(next[0].evidence, Some(ref e) if e.trajectory == 0));
    drop(again);
    drop(clients);
    server.stop().await;
}

/// The field of a refusal's first BadRequest violation.
fn first_violated_field(status: &tonic::Status) -> String {
    let bad_request = status
        .get_details_bad_request()
        .expect("BadRequest details");
    bad_request.field_violations[0].field.clone()
}
