//! StreamDetectFleet, the gateway stream: many vehicles on one stream, one sample each per message,
//! give every vehicle exactly the detections its own StreamDetect stream gives (same sessions, same
//! alarms); a refused vehicle gets its own field-level status and leaves the others and its own
//! session untouched; a message over the limits is refused whole; shutdown ends the stream with
//! UNAVAILABLE.

use std::time::Duration;

use spoofwatch_client::FleetDetectStream;
use spoofwatch_core::scenario::AttackKind;
use spoofwatch_proto::v1;
use spoofwatch_tests::{
    Clients, attacked_drive, field_violations, normal_drive, start_server, start_stream,
    track_samples,
};
use tonic::Code;

fn entry(vehicle_id: &str, samples: Vec<v1::Sample>) -> v1::VehicleSamples {
    v1::VehicleSamples {
        vehicle_id: vehicle_id.to_string(),
        model: String::new(),
        samples,
        reset: false,
    }
}

/// The per-sample outputs a client acts on, for bit-exact comparison.
fn outputs(d: &v1::Detection) -> (u64, bool, bool, bool, bool) {
    (
        d.probability.to_bits(),
        d.positive,
        d.alarm,
        d.alarm_onset,
        d.alarm_end,
    )
}

async fn session(clients: &mut Clients, vehicle_id: &str) -> v1::Session {
    clients
        .detection
        .get_session(v1::GetSessionRequest {
            vehicle_id: vehicle_id.into(),
        })
        .await
        .expect("the session exists")
        .into_inner()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_gateway_stream_gives_each_vehicle_its_own_stream_s_detections() {
    let (_dir, server, mut clients) = start_server(|_| {}).await;
    let spoof = AttackKind::RampDrift { velocity_mps: 2.0 };
    let drives = [
        normal_drive("gw-a", 240.0, 11),
        attacked_drive("gw-b", 240.0, 12, spoof, 90.0, 120.0),
        normal_drive("gw-c", 180.0, 13),
    ];

    // Reference: each vehicle on its own stream (ids with a different prefix: fresh sessions).
    let mut expected = Vec::new();
    for drive in &drives {
        let (mut stream, _) =
            start_stream(&clients, &format!("own-{}", drive.vehicle_id), "").await;
        let mut outs = Vec::new();
        for (seq, chunk) in track_samples(drive).chunks(1).enumerate() {
            let detections = stream
                .detect(seq as u64 + 1, chunk.to_vec())
                .await
                .expect("own stream");
            outs.extend(detections.iter().map(outputs));
        }
        stream.finish().await.expect("the stream ends OK");
        expected.push(outs);
    }
    assert!(
        expected[1].iter().any(|o| o.3),
        "the attacked drive alarms on its own stream"
    );

    // The gateway: message k carries sample k of every vehicle that still has one.
    let samples: Vec<Vec<v1::Sample>> = drives.iter().map(track_samples).collect();
    let mut gateway = FleetDetectStream::open(&clients.connection)
        .await
        .expect("the call is accepted");
    let mut got: Vec<Vec<_>> = vec![Vec::new(); drives.len()];
    let longest = samples.iter().map(Vec::len).max().unwrap_or(0);
    for k in 0..longest {
        let present: Vec<usize> = (0..drives.len())
            .filter(|&v| k < samples[v].len())
            .collect();
        let message = present
            .iter()
            .map(|&v| entry(&drives[v].vehicle_id, vec![samples[v][k]]))
            .collect();
        let reply = tokio::time::timeout(
            Duration::from_secs(10),
            gateway.detect(k as u64 + 1, message),
        )
        .await
        .expect("a reply in time")
        .expect("the message is answered");
        for (&v, answer) in present.iter().zip(&reply) {
            assert!(answer.error.is_none(), "{answer:?}");
            assert_eq!(answer.model, "models/default");
            got[v].extend(answer.detections.iter().map(outputs));
        }
    }
    assert_eq!(
        got, expected,
        "the gateway equals one stream per vehicle, bit for bit"
    );
    gateway.finish().await.expect("the stream ends OK");

    // The gateway's vehicles are ordinary sessions, not held by a stream; last_seq is the message.
    let b = session(&mut clients, "gw-b").await;
    assert_eq!(
        (b.samples, b.last_seq, b.connected),
        (samples[1].len() as u64, samples[1].len() as u64, false),
        "{b:?}"
    );
    assert!(b.alarms_raised >= 1);
    drop(clients);
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_refused_vehicle_leaves_the_others_and_its_session_untouched() {
    let (_dir, server, mut clients) = start_server(|config| config.max_batch_samples = 20).await;
    let a = track_samples(&normal_drive("ok-a", 30.0, 3));
    let b = track_samples(&normal_drive("ok-b", 30.0, 4));
    let mut gateway = FleetDetectStream::open(&clients.connection)
        .await
        .expect("the call is accepted");
    let first = gateway
        .detect(
            1,
            vec![
                entry("ok-a", a[..5].to_vec()),
                entry("ok-b", b[..5].to_vec()),
            ],
        )
        .await
        .expect("answered");
    assert!(first.iter().all(|v| v.error.is_none()));

    // ok-b goes back in time; "bad id" is no vehicle id; ok-a asks for a model that does not exist.
    let mut unknown_model = entry("ok-a", a[5..6].to_vec());
    unknown_model.model = "models/nope".into();
    let reply = gateway
        .detect(
            2,
            vec![
                entry("ok-b", b[..2].to_vec()),
                entry("bad id", a[..1].to_vec()),
                unknown_model,
                entry("ok-c", Vec::new()),
            ],
        )
        .await
        .expect("answered vehicle by vehicle");
    let errors: Vec<(Code, Vec<String>)> = reply
        .iter()
        .map(|v| {
            let status = v.error.clone().expect("refused");
            let fields = field_violations(&status)
                .into_iter()
                .map(|(f, _)| f)
                .collect();
            (Code::from(status.code), fields)
        })
        .collect();
    assert_eq!(errors[0].0, Code::InvalidArgument);
    assert!(
        errors[0]
            .1
            .iter()
            .all(|f| f.starts_with("vehicles[0].samples[")),
        "{errors:?}"
    );
    assert_eq!(
        errors[1],
        (
            Code::InvalidArgument,
            vec!["vehicles[1].vehicle_id".to_string()]
        )
    );
    assert_eq!(errors[2].0, Code::NotFound, "{errors:?}");
    assert_eq!(errors[3].0, Code::InvalidArgument, "{errors:?}");
    assert!(reply.iter().all(|v| v.detections.is_empty()));

    // Over the limits (21 samples > 20): refused whole, nothing applied.
    let too_many = vec![
        entry("ok-a", a[5..16].to_vec()),
        entry("ok-b", b[5..15].to_vec()),
    ];
    let refused = gateway.detect(3, too_many).await;
    assert!(refused.is_err(), "{refused:?}");

    // Nothing of messages 2 and 3 reached the sessions: both continue at their 6th sample.
    let next = gateway
        .detect(
            4,
            vec![
                entry("ok-a", a[5..10].to_vec()),
                entry("ok-b", b[5..10].to_vec()),
            ],
        )
        .await
        .expect("answered");
    for v in &next {
        assert!(v.error.is_none(), "{v:?}");
        let evidence = v.detections[0].evidence.as_ref().expect("evidence");
        assert_eq!(evidence.trajectory, 0, "no new trajectory: {v:?}");
    }
    for id in ["ok-a", "ok-b"] {
        let s = session(&mut clients, id).await;
        assert_eq!((s.samples, s.last_seq), (10, 4), "{s:?}");
    }
    let listed = clients
        .detection
        .list_sessions(v1::ListSessionsRequest::default())
        .await
        .expect("listed")
        .into_inner();
    let ids: Vec<&str> = listed
        .sessions
        .iter()
        .map(|s| s.vehicle_id.as_str())
        .collect();
    assert_eq!(ids, ["ok-a", "ok-b"], "refused vehicles get no session");

    // `reset` starts a vehicle afresh, but only with samples that are accepted.
    let mut restart = entry("ok-a", a[..1].to_vec());
    restart.reset = true;
    let mut refused_restart = entry("ok-b", vec![b[5], b[0]]);
    refused_restart.reset = true;
    let reply = gateway
        .detect(5, vec![restart, refused_restart])
        .await
        .expect("answered");
    assert!(
        reply[0].error.is_none() && reply[1].error.is_some(),
        "{reply:?}"
    );
    let restarted = session(&mut clients, "ok-a").await;
    assert_eq!(
        (restarted.samples, restarted.last_seq),
        (1, 5),
        "{restarted:?}"
    );
    let kept = session(&mut clients, "ok-b").await;
    assert_eq!((kept.samples, kept.last_seq), (10, 4), "{kept:?}");

    // Shutdown ends the open gateway stream with UNAVAILABLE.
    let mut server = server;
    server.trigger_shutdown();
    let ended = tokio::time::timeout(Duration::from_secs(10), gateway.recv())
        .await
        .expect("the stream ends in time");
    match ended {
        Err(error) => assert_eq!(
            error.status().map(|s| s.code()),
            Some(Code::Unavailable),
            "{error}"
        ),
        Ok(other) => panic!("expected UNAVAILABLE, got {other:?}"),
    }
    drop(clients);
    server.stop().await;
}
