//! A client that never reads its replies costs the server a bounded buffer, black-box: a StreamDetect
//! client whose HTTP/2 window is the protocol's default (64 KiB) and is never refreshed sends 40
//! batches of 1,000 samples, whose replies are far larger than the window, and reads nothing. The
//! server scores batches only until the stream's reply buffer (512 KiB of encoded replies) is full:
//! then it stops reading the stream, so the batches it scored are those the buffer, tonic's encoder
//! and the client's window hold, not all 40. Once the client reads, every reply arrives in order
//! and the buffer empties (`spoofwatch_stream_reply_bytes_queued` back to 0).
//!
//! Its own test binary, with one server and one test: the gauge counts every stream of the process.

use std::net::SocketAddr;
use std::time::{Duration, Instant};

use prost::Message;
use spoofwatch_proto::v1;
use spoofwatch_proto::v1::detection_service_client::DetectionServiceClient;
use spoofwatch_proto::v1::stream_detect_request::Kind as RequestKind;
use spoofwatch_proto::v1::stream_detect_response::Kind as ResponseKind;
use spoofwatch_tests::{normal_drive, scrape, start_server, track_samples};
use tokio_stream::wrappers::ReceiverStream;
use tonic::transport::Endpoint;

const BATCHES: usize = 40;
const BATCH_SAMPLES: usize = 1_000;
/// The server's reply buffer per stream (`server/src/replies.rs`).
const OUTBOUND_BYTES: f64 = 512.0 * 1024.0;
/// The HTTP/2 default window, which this client never refreshes while it does not read.
const WINDOW: u32 = 65_535;
const BOUND: Duration = Duration::from_secs(120);

/// A metric's value in the exposition text (0 when absent); `label` narrows it to one series.
fn metric(text: &str, name: &str, label: &str) -> f64 {
    text.lines()
        .filter(|line| line.starts_with(name) && line.contains(label))
        .filter_map(|line| line.rsplit(' ').next()?.parse::<f64>().ok())
        .sum()
}

async fn queued_and_scored(metrics: SocketAddr) -> (f64, f64) {
    let text = scrape(metrics).await;
    (
        metric(&text, "spoofwatch_stream_reply_bytes_queued", ""),
        metric(
            &text,
            "spoofwatch_detection_batches_total",
            "rpc=\"StreamDetect\"",
        ),
    )
}

fn request(kind: RequestKind) -> v1::StreamDetectRequest {
    v1::StreamDetectRequest { kind: Some(kind) }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_client_that_does_not_read_holds_a_bounded_reply_buffer() {
    let (_dir, server, _clients) = start_server(|config| {
        config.metrics_listen = Some(SocketAddr::from(([127, 0, 0, 1], 0)));
    })
    .await;
    let metrics = server.metrics_addr().expect("metrics listen");
    let samples = track_samples(&normal_drive("silent", (BATCHES * BATCH_SAMPLES) as f64, 7));
    let batches: Vec<Vec<v1::Sample>> = samples
        .chunks(BATCH_SAMPLES)
        .take(BATCHES)
        .map(<[v1::Sample]>::to_vec)
        .collect();
    assert_eq!(batches.len(), BATCHES);

    let channel = Endpoint::from_shared(server.url())
        .expect("a valid URI")
        .initial_stream_window_size(Some(WINDOW))
        .initial_connection_window_size(Some(WINDOW))
        .connect()
        .await
        .expect("connect");
    let (requests, outbound) = tokio::sync::mpsc::channel(BATCHES + 1);
    requests
        .send(request(RequestKind::Start(v1::SessionStart {
            vehicle_id: "silent".into(),
            model: String::new(),
            reset: false,
        })))
        .await
        .expect("queued");
    for (seq, batch) in (1..).zip(&batches) {
        let batch = v1::SampleBatch {
            seq,
            samples: batch.clone(),
        };
        requests
            .send(request(RequestKind::Batch(batch)))
            .await
            .expect("queued");
    }
    drop(requests);
    let mut replies = DetectionServiceClient::new(channel)
        .stream_detect(ReceiverStream::new(outbound))
        .await
        .expect("the call is accepted")
        .into_inner();

    // Read nothing until the server's buffer for the stream is nearly full: then it waits for
    // the client and reads no further batch.
    let deadline = Instant::now() + BOUND;
    let (queued, scored) = loop {
        let (queued, scored) = queued_and_scored(metrics).await;
        if queued >= OUTBOUND_BYTES / 2.0 {
            break (queued, scored);
        }
        assert!(
            Instant::now() < deadline,
            "queued {queued} B, scored {scored}"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    };
    assert!(queued <= OUTBOUND_BYTES, "{queued} B queued");

    // Now read every reply, in order, and weigh them.
    let mut sizes = Vec::new();
    let mut seqs = Vec::new();
    while let Some(reply) = tokio::time::timeout(BOUND, replies.message())
        .await
        .expect("replies flow once read")
        .expect("no error")
    {
        match reply.kind {
            Some(ResponseKind::Accepted(_)) => {}
            Some(ResponseKind::Detections(detections)) => {
                sizes.push(reply_len(&detections));
                seqs.push(detections.seq);
            }
            other => panic!("unexpected reply {other:?}"),
        }
    }
    assert_eq!(
        seqs,
        (1..=BATCHES as u64).collect::<Vec<_>>(),
        "every reply, in order"
    );
    let smallest = sizes.iter().copied().min().expect("replies") as f64;
    assert!(
        smallest * 4.0 > f64::from(WINDOW),
        "the replies are large against the window ({smallest} B)"
    );
    // While the client read nothing: the buffer's replies, the one HTTP/2 holds for the client's
    // window, one taken by tonic's encoder, one scored and waiting for room, and two more for the
    // moment of the scrape. (A buffer of 16 replies alone, without its byte bound, let about 19
    // of these 380 KB replies be scored.)
    let at_most = (OUTBOUND_BYTES / smallest).floor() + 5.0;
    assert!(
        scored <= at_most,
        "{scored} batches scored while the client read nothing (at most {at_most})"
    );
    assert!(scored < BATCHES as f64, "the server stopped reading");
    let (queued, _) = queued_and_scored(metrics).await;
    assert_eq!(queued, 0.0, "the buffer is empty once the client has read");
    server.stop().await;
}

fn reply_len(detections: &v1::DetectionBatch) -> usize {
    v1::StreamDetectResponse {
        kind: Some(ResponseKind::Detections(detections.clone())),
    }
    .encoded_len()
}
