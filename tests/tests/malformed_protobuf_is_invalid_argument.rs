//! Bytes that are not a protobuf message of the request type are the client's error: every kind of
//! RPC (unary, client-, server- and bidirectional streaming, google.longrunning included) answers
//! INVALID_ARGUMENT naming the request type, and the server keeps serving.

use crate::raw_grpc;

use std::time::Duration;

use raw_grpc::{Shape, call};
use spoofwatch_tests::{ServingStatus, health_of, start_server};
use tonic::Code;

/// Field 1, length-delimited, claiming 5 bytes where one follows: a truncated message.
const TRUNCATED: &[u8] = &[0x0a, 0x05, 0x01];
/// A key whose varint never ends.
const BAD_VARINT: &[u8] = &[
    0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff,
];

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn malformed_requests_are_invalid_argument_on_every_kind_of_rpc() {
    let (_dir, server, clients) = start_server(|_| {}).await;
    let channel = server.channel().await;
    let rpcs = [
        (
            "/spoofwatch.v1.DetectionService/Detect",
            Shape::Unary,
            "spoofwatch.v1.DetectRequest",
        ),
        (
            "/spoofwatch.v1.DetectionService/StreamDetect",
            Shape::Bidi,
            "spoofwatch.v1.StreamDetectRequest",
        ),
        (
            "/spoofwatch.v1.DetectionService/StreamDetectFleet",
            Shape::Bidi,
            "spoofwatch.v1.FleetBatch",
        ),
        (
            "/spoofwatch.v1.ModelService/ListModels",
            Shape::Unary,
            "spoofwatch.v1.ListModelsRequest",
        ),
        (
            "/spoofwatch.v1.ModelService/ImportModel",
            Shape::ClientStreaming,
            "spoofwatch.v1.ImportModelRequest",
        ),
        (
            "/spoofwatch.v1.ModelService/ExportModel",
            Shape::ServerStreaming,
            "spoofwatch.v1.ExportModelRequest",
        ),
        (
            "/spoofwatch.v1.DatasetService/UploadDataset",
            Shape::ClientStreaming,
            "spoofwatch.v1.UploadDatasetRequest",
        ),
        (
            "/spoofwatch.v1.TrainingService/CreateTrainingJob",
            Shape::Unary,
            "spoofwatch.v1.CreateTrainingJobRequest",
        ),
        (
            "/spoofwatch.v1.AlarmService/WatchAlarms",
            Shape::ServerStreaming,
            "spoofwatch.v1.WatchAlarmsRequest",
        ),
        (
            "/google.longrunning.Operations/GetOperation",
            Shape::Unary,
            "google.longrunning.GetOperationRequest",
        ),
    ];
    for (path, shape, type_name) in rpcs {
        for bytes in [TRUNCATED, BAD_VARINT] {
            let outcome = call(
                &channel,
                None,
                path,
                shape,
                vec![bytes.to_vec()],
                10,
                Duration::from_secs(30),
            )
            .await
            .unwrap_or_else(|| panic!("{path} answered within 30 s"));
            let status = outcome.expect_err("a malformed request is refused");
            assert_eq!(status.code(), Code::InvalidArgument, "{path}: {status:?}");
            let expected = format!("request is not a valid {type_name} protobuf message: ");
            assert!(
                status.message().starts_with(&expected),
                "{path}: {:?}",
                status.message()
            );
        }
    }
    assert_eq!(health_of(&server, "").await, ServingStatus::Serving);
    drop(clients);
    server.stop().await;
}
