//! The `x-vehicle-id` header that load balancers route by: the client library sends it on every
//! per-vehicle call, a single server accepts calls with or without it, and refuses (naming the
//! field and the header) a header that names another vehicle than the message, since such a call
//! would pin the vehicle's session to another vehicle's replica.

use spoofwatch_client::routing::for_vehicle;
use spoofwatch_proto::v1;
use spoofwatch_tests::{
    Clients, REPLY_TIMEOUT, normal_drive, start_request, start_server, track_samples,
};
use tokio_stream::StreamExt;
use tonic::Code;
use tonic_types::StatusExt;

/// The BadRequest field violations of a status, as (field, description).
fn violations(status: &tonic::Status) -> Vec<(String, String)> {
    status
        .get_details_bad_request()
        .map(|bad| {
            bad.field_violations
                .into_iter()
                .map(|v| (v.field, v.description))
                .collect()
        })
        .unwrap_or_default()
}

/// Opens StreamDetect for `vehicle` with `header` as its x-vehicle-id (none: no header) and
/// returns the first reply: SessionAccepted, or the call's status.
async fn first_reply(
    clients: &Clients,
    vehicle: &str,
    header: Option<&str>,
) -> Result<v1::StreamDetectResponse, tonic::Status> {
    let messages = tokio_stream::iter([start_request(vehicle, "", true)]);
    // Keep the request side open until the first reply is read.
    let messages = messages.chain(tokio_stream::pending());
    let request = match header {
        Some(header) => for_vehicle(header, messages),
        None => tonic::Request::new(messages),
    };
    let mut replies = clients
        .detection
        .clone()
        .stream_detect(request)
        .await?
        .into_inner();
    tokio::time::timeout(REPLY_TIMEOUT, replies.message())
        .await
        .expect("a reply in time")?
        .ok_or_else(|| tonic::Status::unknown("the call ended without a reply"))
}

fn is_accepted(reply: &v1::StreamDetectResponse) -> bool {
    matches!(
        reply.kind,
        Some(v1::stream_detect_response::Kind::Accepted(_))
    )
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_header_must_name_the_messages_vehicle_and_may_be_absent() {
    let (_dir, server, mut clients) = start_server(|_| {}).await;

    // Absent (a client talking to one server) and matching: accepted.
    let reply = first_reply(&clients, "car-1", None)
        .await
        .expect("no header");
    assert!(is_accepted(&reply), "{reply:?}");
    let reply = first_reply(&clients, "car-1", Some("car-1"))
        .await
        .expect("the same vehicle");
    assert!(is_accepted(&reply), "{reply:?}");

    // Another vehicle: refused on the stream's start, naming both.
    let status = first_reply(&clients, "car-1", Some("car-2"))
        .await
        .expect_err("a header naming another vehicle");
    assert_eq!(status.code(), Code::InvalidArgument, "{status:?}");
    let found = violations(&status);
    assert_eq!(found.len(), 1, "{found:?}");
    assert_eq!(found[0].0, "start.vehicle_id");
    assert!(
        found[0].1.contains("x-vehicle-id header \"car-2\""),
        "{found:?}"
    );

    // Detect: with the vehicle's own header, without, with another's, and on a stateless call.
    let samples = track_samples(&normal_drive("car-3", 5.0, 3));
    let detect = |vehicle: &str, samples: &[v1::Sample]| v1::DetectRequest {
        vehicle_id: vehicle.to_string(),
        samples: samples.to_vec(),
        ..v1::DetectRequest::default()
    };
    clients
        .detection
        .detect(for_vehicle("car-3", detect("car-3", &samples[..2])))
        .await
        .expect("the vehicle's own header");
    clients
        .detection
        .detect(detect("car-3", &samples[2..3]))
        .await
        .expect("no header");
    for (header, vehicle) in [("car-4", "car-3"), ("car-4", "")] {
        let status = clients
            .detection
            .detect(for_vehicle(header, detect(vehicle, &samples[3..])))
            .await
            .expect_err("a header naming another vehicle");
        assert_eq!(status.code(), Code::InvalidArgument, "{status:?}");
        assert_eq!(violations(&status)[0].0, "vehicle_id", "{status:?}");
    }

    // GetSession and ResetSession route by the vehicle too.
    let get = |vehicle: &str| v1::GetSessionRequest {
        vehicle_id: vehicle.to_string(),
    };
    let session = clients
        .detection
        .get_session(for_vehicle("car-3", get("car-3")))
        .await
        .expect("the vehicle's own header")
        .into_inner();
    assert_eq!(session.samples, 3);
    let status = clients
        .detection
        .get_session(for_vehicle("car-1", get("car-3")))
        .await
        .expect_err("another vehicle's header");
    assert_eq!(status.code(), Code::InvalidArgument);
    let status = clients
        .detection
        .reset_session(for_vehicle(
            "car-1",
            v1::ResetSessionRequest {
                vehicle_id: "car-3".into(),
            },
        ))
        .await
        .expect_err("another vehicle's header");
    assert_eq!(status.code(), Code::InvalidArgument);

    drop(clients);
    server.stop().await;
}
