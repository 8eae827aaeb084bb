//! Error statuses stay small whatever the request held: a batch with a thousand invalid samples
//! lists the first violations and counts the rest, and a model file with a 5,000-character string
//! where a number belongs is refused at its field with only part of the string quoted. Clients
//! with a 16 KiB trailer limit (grpcio) read these errors instead of RESOURCE_EXHAUSTED.

use spoofwatch_proto::v1;
use spoofwatch_proto::wire::limits::MAX_BATCH_SAMPLES;
use spoofwatch_tests::{normal_drive, start_server, track_samples};
use tonic::Code;
use tonic_types::StatusExt;

/// What a status adds to its trailer: the message and the encoded details.
fn status_bytes(status: &tonic::Status) -> usize {
    status.message().len() + status.details().len()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_thousand_invalid_samples_list_the_first_violations_and_count_the_rest() {
    let (_dir, server, mut clients) = start_server(|_| {}).await;
    let track = normal_drive("many-bad", (MAX_BATCH_SAMPLES - 1) as f64, 3);
    let mut samples = track_samples(&track);
    assert_eq!(samples.len(), MAX_BATCH_SAMPLES);
    for sample in &mut samples {
        sample.latitude_deg = f64::NAN;
        sample.speed_mps = -1.0;
    }
    let status = clients
        .detection
        .detect(v1::DetectRequest {
            samples,
            ..Default::default()
        })
        .await
        .expect_err("invalid samples are refused");
    assert_eq!(status.code(), Code::InvalidArgument, "{status:?}");
    assert!(
        status_bytes(&status) <= 8 * 1024,
        "{}",
        status_bytes(&status)
    );
    let violations = status
        .get_details_bad_request()
        .expect("BadRequest details")
        .field_violations;
    assert_eq!(
        violations.len(),
        11,
        "ten violations and a count of the rest"
    );
    assert!(
        violations[0].field.starts_with("samples[0]."),
        "{}",
        violations[0].field
    );
    let last = &violations[10];
    assert!(
        last.description.contains("more violations not shown"),
        "{}",
        last.description
    );
    assert!(
        status.message().contains("more violations not shown"),
        "{}",
        status.message()
    );
    drop(clients);
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_long_string_in_a_model_file_is_not_echoed_whole() {
    use v1::import_model_request::Kind;
    let (_dir, server, mut clients) = start_server(|_| {}).await;
    let bundled = spoofwatch_tests::export_model(&mut clients.models, "models/default").await;
    let artifact = with_long_string_as_mu_e(&bundled);
    let messages = [
        Kind::Header(v1::ImportModelHeader {
            display_name: "long string".into(),
            activate: false,
        }),
        Kind::Chunk(artifact.into_bytes()),
    ]
    .map(|kind| v1::ImportModelRequest { kind: Some(kind) });
    let status = clients
        .models
        .import_model(tokio_stream::iter(messages))
        .await
        .expect_err("a string is not a number");
    assert_eq!(status.code(), Code::InvalidArgument, "{status:?}");
    assert!(status_bytes(&status) < 1024, "{}", status_bytes(&status));
    let violations = status
        .get_details_bad_request()
        .expect("BadRequest details")
        .field_violations;
    assert_eq!(violations[0].field, "artifact.evidence.mu_e");
    assert!(
        violations[0].description.contains("(5000 chars)"),
        "{}",
        violations[0].description
    );
    drop(clients);
    server.stop().await;
}

/// The artifact with a 5,000-character string as `evidence.mu_e` (the only `mu_e` key; a number).
fn with_long_string_as_mu_e(artifact: &[u8]) -> String {
    let text = std::str::from_utf8(artifact).expect("an artifact is UTF-8 JSON");
    let key = "\"mu_e\": ";
    let start = text.find(key).expect("the artifact has mu_e") + key.len();
    let end = start + text[start..].find(',').expect("mu_e is followed by kappa");
    format!(
        "{}\"{}\"{}",
        &text[..start],
        "9".repeat(5_000),
        &text[end..]
    )
}
