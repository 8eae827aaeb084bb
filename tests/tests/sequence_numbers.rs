//! Batch sequence numbers: a resent batch is acknowledged without being scored again (the
//! detections after it equal an uninterrupted stream's bit for bit), a number that goes backwards
//! is refused on its `seq` field, and `last_seq` never regresses; the same per vehicle on
//! StreamDetectFleet.

use spoofwatch_proto::v1;
use spoofwatch_tests::{
    BatchOutcome, Clients, field_violations, fingerprint, normal_drive, start_server, start_stream,
    track_samples,
};
use tokio_stream::StreamExt;
use tonic::Code;

async fn last_seq(clients: &Clients, vehicle: &str) -> u64 {
    clients
        .detection
        .clone()
        .get_session(v1::GetSessionRequest {
            vehicle_id: vehicle.into(),
        })
        .await
        .expect("the session exists")
        .into_inner()
        .last_seq
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_resent_batch_is_not_scored_twice_and_a_backwards_seq_is_refused() {
    let (_dir, server, clients) = start_server(|_| {}).await;
    let samples = track_samples(&normal_drive("car", 40.0, 3));
    let batches: Vec<_> = samples.chunks(10).map(<[_]>::to_vec).collect();

    // The reference: batches 1, 2, 3 once each.
    let (mut reference, _) = start_stream(&clients, "reference", "").await;
    let mut expected = Vec::new();
    for (seq, batch) in (1..).zip(&batches[..3]) {
        expected = reference.detect(seq, batch.clone()).await.expect("scored");
    }

    let (mut stream, _) = start_stream(&clients, "car-1", "").await;
    stream.detect(1, batches[0].clone()).await.expect("scored");
    stream.detect(2, batches[1].clone()).await.expect("scored");
    // Resent: acknowledged as duplicates, nothing scored.
    for seq in [2, 1] {
        let batch = batches[seq as usize - 1].clone();
        stream.send_batch(seq, batch).await.expect("sent");
        let reply = stream.recv().await.expect("a reply");
        let outcome = reply.outcome;
        assert!(matches!(outcome, BatchOutcome::Duplicate), "{outcome:?}");
    }
    // The next batch is scored as if the resends never came.
    let third = stream.detect(3, batches[2].clone()).await.expect("scored");
    assert_eq!(fingerprint(&third), fingerprint(&expected));

    // Seq 5 skips 4; 4 arriving late goes backwards and is refused on its seq field.
    stream.detect(5, batches[3].clone()).await.expect("scored");
    stream
        .send_batch(4, batches[3].clone())
        .await
        .expect("sent");
    let reply = stream.recv().await.expect("a reply");
    let BatchOutcome::Rejected(status) = reply.outcome else {
        panic!("a backwards seq was accepted: {:?}", reply.outcome);
    };
    assert_eq!(Code::from(status.code), Code::InvalidArgument);
    let violations = field_violations(&status);
    assert_eq!(violations[0].0, "batch.seq", "{violations:?}");
    assert!(
        violations[0].1.contains("last applied seq 5"),
        "{violations:?}"
    );
    // Seq 0 is not sequenced: scored, and last_seq stays.
    stream
        .detect(
            0,
            batches[3]
                .iter()
                .map(|s| v1::Sample {
                    timestamp_s: s.timestamp_s + 100.0,
                    ..*s
                })
                .collect(),
        )
        .await
        .expect("scored");
    assert_eq!(
        last_seq(&clients, "car-1").await,
        5,
        "last_seq never regresses"
    );
    drop((stream, reference, clients));
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_resent_fleet_message_is_acknowledged_per_vehicle() {
    let (_dir, server, clients) = start_server(|_| {}).await;
    let samples = track_samples(&normal_drive("truck", 30.0, 4));
    let message = |seq: u64, part: usize| v1::FleetBatch {
        seq,
        vehicles: vec![v1::VehicleSamples {
            vehicle_id: "truck-1".into(),
            samples: samples[part * 10..part * 10 + 10].to_vec(),
            ..Default::default()
        }],
    };
    let messages = vec![message(7, 0), message(7, 0), message(9, 1), message(8, 2)];
    let replies: Vec<_> = clients
        .detection
        .clone()
        .stream_detect_fleet(tokio_stream::iter(messages))
        .await
        .expect("the call is accepted")
        .into_inner()
        .collect::<Result<Vec<_>, _>>()
        .await
        .expect("every reply");
    let vehicle = |i: usize| &replies[i].vehicles[0];
    assert_eq!(vehicle(0).detections.len(), 10);
    assert!(!vehicle(0).duplicate);
    assert!(vehicle(1).duplicate && vehicle(1).detections.is_empty() && vehicle(1).error.is_none());
    assert_eq!(vehicle(2).detections.len(), 10);
    let refused = vehicle(3).error.as_ref().expect("8 goes backwards after 9");
    assert_eq!(Code::from(refused.code), Code::InvalidArgument);
    assert_eq!(field_violations(refused)[0].0, "vehicles[0].seq");
    assert_eq!(last_seq(&clients, "truck-1").await, 9);
    drop(clients);
    server.stop().await;
}
