//! Paced one-vehicle StreamDetect streams driven straight on HTTP/2 (the `h2` crate), for the
//! fleet rows of `bench`: the load generator must stay cheaper than the server it measures.
//!
//! Through tonic each stream costs a task with its own timer, a channel into the request body and
//! the body's own task, per message. Here one task drives all the streams of a connection: it
//! sends every due message on one timer, encoding the gRPC frame itself, and reads the replies as
//! they arrive. Messages that fall due together on one connection leave in one write. The protocol
//! checks are those of `DetectStream`: `SessionAccepted` first, then one reply per batch, in
//! order, with one detection per sample, and the call ends with OK.
//!
//! It owns only driving the streams; the phase's shape and measurements are `super`'s. Plaintext
//! only: a phase over TLS goes through tonic.

use std::pin::Pin;
use std::task::{Context, Poll, ready};
use std::time::{Duration, Instant};

use bytes::{Buf, BufMut, Bytes, BytesMut};
use futures_util::FutureExt;
use futures_util::stream::{SelectAll, Stream, StreamExt};
use h2::client::SendRequest;
use h2::{RecvStream, SendStream};
use prost::Message;
use spoofwatch_proto::v1;
use spoofwatch_proto::v1::stream_detect_response::Kind as ResponseKind;
use spoofwatch_proto::wire::routing::VEHICLE_ID_HEADER;
use tokio::net::TcpStream;

use super::{PhaseTiming, StreamResult, scheduled_batches};
use crate::connection::{ConnectOptions, bearer_value, server_url};
use crate::detect_stream::{batch_request, start_request};
use crate::synthetic::LoopDriver;

/// Where the streams go: the server's address and what every request carries.
#[derive(Clone, Debug)]
pub struct Target {
    /// `host:port`.
    pub authority: String,
    /// `authorization` header value (`Bearer …`), if any.
    pub authorization: Option<String>,
}

impl Target {
    /// The target for `url` with `options`, when the streams can go straight on HTTP/2: plaintext,
    /// uncompressed, with a token (if any) that can be a header. `None`: through tonic, which
    /// handles the rest (and reports what is wrong with it).
    pub fn plaintext(url: &str, options: &ConnectOptions) -> Option<Self> {
        if options.gzip {
            return None;
        }
        let uri: http::Uri = server_url(url, options.wants_tls()).parse().ok()?;
        if uri.scheme_str() != Some("http") {
            return None;
        }
        let authority = uri.authority()?;
        let authorization = options
            .token
            .as_deref()
            .map(bearer_value)
            .transpose()
            .ok()?;
        Some(Self {
            authority: format!(
                "{}:{}",
                authority.host(),
                authority.port_u16().unwrap_or(80)
            ),
            authorization,
        })
    }
}

/// HTTP/2 flow-control windows of a stream and of the connection.
const STREAM_WINDOW: u32 = 2 * 1024 * 1024;
const CONNECTION_WINDOW: u32 = 5 * 1024 * 1024;

/// The stream's gRPC method.
const PATH: &str = "/spoofwatch.v1.DetectionService/StreamDetect";

/// `message` as one gRPC frame: uncompressed flag, big-endian length, the protobuf encoding.
pub fn grpc_frame(message: &impl Message) -> Bytes {
    let len = message.encoded_len();
    let mut frame = BytesMut::with_capacity(5 + len);
    frame.put_u8(0);
    frame.put_u32(len as u32);
    // The buffer was sized for the message.
    message
        .encode(&mut frame)
        .expect("the frame buffer holds the message");
    frame.freeze()
}

/// Takes the next whole gRPC message off `buffer`, if it holds one.
pub fn next_message(buffer: &mut BytesMut) -> Result<Option<v1::StreamDetectResponse>, String> {
    if buffer.len() < 5 {
        return Ok(None);
    }
    if buffer[0] != 0 {
        return Err("a compressed reply (none was asked for)".to_string());
    }
    let len = u32::from_be_bytes([buffer[1], buffer[2], buffer[3], buffer[4]]) as usize;
    if buffer.len() < 5 + len {
        return Ok(None);
    }
    buffer.advance(5);
    let body = buffer.split_to(len);
    v1::StreamDetectResponse::decode(body)
        .map(Some)
        .map_err(|e| format!("a reply that is not a StreamDetectResponse: {e}"))
}

/// What one stream's response body yields.
enum Arrival {
    Data(Bytes),
    /// The call ended: OK, or why not, as its trailers tell.
    End(Result<(), String>),
    Failed(String),
}

/// A response body as a stream of arrivals tagged with the stream's index; flow-control capacity
/// is given back as data is read.
struct Replies {
    index: usize,
    body: RecvStream,
    ended: bool,
}

impl Stream for Replies {
    type Item = (usize, Arrival);

    fn poll_next(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<Self::Item>> {
        if self.ended {
            return Poll::Ready(None);
        }
        let index = self.index;
        let arrival = match ready!(self.body.poll_data(cx)) {
            Some(Ok(data)) => {
                let _ = self.body.flow_control().release_capacity(data.len());
                Arrival::Data(data)
            }
            Some(Err(error)) => {
                self.ended = true;
                Arrival::Failed(error.to_string())
            }
            None => {
                self.ended = true;
                match ready!(self.body.poll_trailers(cx)) {
                    Ok(trailers) => Arrival::End(grpc_status(trailers.as_ref())),
                    Err(error) => Arrival::Failed(error.to_string()),
                }
            }
        };
        Poll::Ready(Some((index, arrival)))
    }
}

/// The call's outcome from its trailers (or trailers-only response headers).
fn grpc_status(headers: Option<&http::HeaderMap>) -> Result<(), String> {
    let Some(headers) = headers else {
        return Err("the call ended without a grpc-status".to_string());
    };
    let field = |name: &str| headers.get(name).and_then(|v| v.to_str().ok());
    match field("grpc-status") {
        Some("0") => Ok(()),
        Some(code) => Err(format!(
            "the call ended with status {code}: {}",
            field("grpc-message").unwrap_or("")
        )),
        None => Err("the call ended without a grpc-status".to_string()),
    }
}

/// One vehicle's stream on the connection.
struct VehicleStream {
    vehicle_id: String,
    send: SendStream<Bytes>,
    driver: LoopDriver,
    /// Samples per message.
    batch: usize,
    received: BytesMut,
    /// The session's `SessionAccepted` has arrived.
    accepted: bool,
    /// Next message's seq and its slot.
    seq: u64,
    slot: tokio::time::Instant,
    /// The message awaiting its reply: its seq, when it was sent, whether it is measured.
    awaiting: Option<(u64, Instant, bool)>,
    /// The call ended (OK after the last reply, or failed).
    ended: bool,
    result: StreamResult,
}

impl VehicleStream {
    fn fail(&mut self, why: String) {
        if self.result.error.is_none() {
            self.result.error = Some(format!(
                "streaming detections for {}: {why}",
                self.vehicle_id
            ));
        }
        self.ended = true;
        self.awaiting = None;
        self.send.send_reset(h2::Reason::CANCEL);
    }
}

/// Drives the streams of `vehicles` (id, seed) on one new connection through a phase timed by
/// `timing`, each sending one batch per `pace` from its offset on: opens them (each session
/// afresh), waits at the phase's barrier, sends and times, waits for every connection to have sent
/// its last message, then ends the calls. One result per vehicle, in order.
pub async fn drive_connection(
    target: &Target,
    load: &PhaseTiming,
    vehicles: Vec<(String, u64)>,
    (pace, offsets): (Duration, Vec<Duration>),
) -> Vec<StreamResult> {
    let count = vehicles.len();
    let opened = open(target, load.batch, vehicles).await;
    load.barrier.wait().await;
    let (mut streams, replies): (Vec<VehicleStream>, Vec<Replies>) = match opened {
        Ok(opened) => opened.into_iter().unzip(),
        Err(error) => {
            load.sent_all.wait().await;
            return (0..count)
                .map(|_| StreamResult {
                    error: Some(error.clone()),
                    ..StreamResult::default()
                })
                .collect();
        }
    };
    let mut replies: SelectAll<Replies> = replies.into_iter().collect();
    let started = tokio::time::Instant::now();
    let measured_from = started + load.warmup;
    let deadline = measured_from + load.length;
    for (stream, offset) in streams.iter_mut().zip(offsets) {
        stream.slot = started + offset;
        stream.result.scheduled = scheduled_batches(load.warmup + load.length, pace, offset)
            - scheduled_batches(load.warmup, pace, offset);
    }
    // Sending: every slot due before the deadline is sent, late when its reply came late.
    let timer = tokio::time::sleep_until(deadline);
    tokio::pin!(timer);
    loop {
        let now = tokio::time::Instant::now();
        let mut next_wake: Option<tokio::time::Instant> = None;
        let mut busy = false;
        for stream in streams.iter_mut().filter(|s| !s.ended) {
            if stream.awaiting.is_none() && stream.slot < deadline && stream.slot <= now {
                send_next(stream, pace, measured_from);
            }
            if stream.awaiting.is_some() {
                busy = true;
            } else if stream.slot < deadline {
                next_wake = Some(next_wake.map_or(stream.slot, |w| w.min(stream.slot)));
            }
        }
        if !busy && next_wake.is_none() {
            break;
        }
        if let Some(wake) = next_wake
            && wake != timer.deadline()
        {
            timer.as_mut().reset(wake);
        }
        tokio::select! {
            _ = &mut timer, if next_wake.is_some() => {}
            arrival = replies.next() => match arrival {
                Some((index, arrival)) => receive(&mut streams[index], arrival),
                None => break,
            },
        }
        // Whatever else has arrived meanwhile, before the streams are looked at again.
        while let Some(Some((index, arrival))) = replies.next().now_or_never() {
            receive(&mut streams[index], arrival);
        }
    }
    load.sent_all.wait().await;
    // Half-close every call, then read each to its end: it must end with OK and nothing more.
    for stream in streams.iter_mut().filter(|s| !s.ended) {
        if let Err(error) = stream.send.send_data(Bytes::new(), true) {
            stream.fail(error.to_string());
        }
    }
    while streams.iter().any(|s| !s.ended) {
        match replies.next().await {
            Some((index, arrival)) => receive(&mut streams[index], arrival),
            None => break,
        }
    }
    streams.into_iter().map(|s| s.result).collect()
}

/// Sends the stream's next batch (one per slot).
fn send_next(stream: &mut VehicleStream, pace: Duration, measured_from: tokio::time::Instant) {
    let measured = stream.slot >= measured_from;
    stream.slot += pace;
    stream.seq += 1;
    let frame = grpc_frame(&batch_request(
        stream.seq,
        stream.driver.next_batch(stream.batch),
    ));
    match stream.send.send_data(frame, false) {
        Ok(()) => stream.awaiting = Some((stream.seq, Instant::now(), measured)),
        Err(error) => stream.fail(error.to_string()),
    }
}

/// Handles what arrived for a stream: its replies, checked, timed and counted; or its end.
fn receive(stream: &mut VehicleStream, arrival: Arrival) {
    match arrival {
        Arrival::Data(data) => {
            stream.received.extend_from_slice(&data);
            loop {
                match next_message(&mut stream.received) {
                    Ok(Some(reply)) => {
                        if let Err(why) = check_reply(stream, reply) {
                            stream.fail(why);
                            return;
                        }
                    }
                    Ok(None) => return,
                    Err(why) => {
                        stream.fail(why);
                        return;
                    }
                }
            }
        }
        Arrival::End(status) => {
            let unanswered = stream.awaiting.is_some();
            stream.ended = true;
            match status {
                Err(why) => stream.fail(why),
                Ok(()) if unanswered => stream.fail("the call ended before a batch's reply".into()),
                Ok(()) => {}
            }
        }
        Arrival::Failed(why) => stream.fail(why),
    }
}

/// One reply: the first must accept the session, each later one answers the batch awaiting it.
fn check_reply(stream: &mut VehicleStream, reply: v1::StreamDetectResponse) -> Result<(), String> {
    let batch_len = stream.batch;
    match (reply.kind, stream.awaiting) {
        (Some(ResponseKind::Accepted(_)), None) if !stream.accepted => {
            stream.accepted = true;
            Ok(())
        }
        (Some(ResponseKind::Detections(d)), Some((seq, sent, measured)))
            if stream.accepted && d.seq == seq && d.detections.len() == batch_len =>
        {
            stream.awaiting = None;
            if measured {
                stream.result.latencies.push(sent.elapsed());
                stream.result.samples += batch_len as u64;
            }
            Ok(())
        }
        (Some(ResponseKind::ItemError(error)), Some((seq, ..))) if error.seq == seq => {
            Err(format!(
                "batch {seq} was rejected: {}",
                crate::error::describe_rpc_status(&error.status.unwrap_or_default())
            ))
        }
        (other, awaiting) => Err(format!(
            "unexpected reply {other:?} (awaiting {:?})",
            awaiting.map(|(seq, ..)| seq)
        )),
    }
}

/// Opens one connection and a stream for each vehicle, each starting its session afresh, and
/// waits for every session to be accepted.
async fn open(
    target: &Target,
    batch: usize,
    vehicles: Vec<(String, u64)>,
) -> Result<Vec<(VehicleStream, Replies)>, String> {
    let tcp = TcpStream::connect(&target.authority)
        .await
        .map_err(|e| format!("connecting to {}: {e}", target.authority))?;
    tcp.set_nodelay(true)
        .map_err(|e| format!("setting TCP_NODELAY: {e}"))?;
    // Windows as large as hyper's, so that the replies of many streams arriving together are
    // read whole (h2 also budgets small frames buffered unread by the connection's window).
    let (mut client, connection) = h2::client::Builder::new()
        .initial_window_size(STREAM_WINDOW)
        .initial_connection_window_size(CONNECTION_WINDOW)
        .handshake(tcp)
        .await
        .map_err(|e| format!("the HTTP/2 handshake with {}: {e}", target.authority))?;
    tokio::spawn(async move {
        // Its failure reaches every stream of the connection as theirs.
        let _ = connection.await;
    });
    let mut opened = Vec::with_capacity(vehicles.len());
    let mut responses = Vec::with_capacity(vehicles.len());
    for (vehicle_id, seed) in vehicles {
        let (response, mut send) = start_call(&mut client, target, &vehicle_id).await?;
        send.send_data(grpc_frame(&start_request(&vehicle_id, "", true)), false)
            .map_err(|e| format!("starting the session of {vehicle_id}: {e}"))?;
        responses.push(response);
        opened.push(VehicleStream {
            vehicle_id,
            send,
            driver: LoopDriver::new(seed),
            batch,
            received: BytesMut::new(),
            accepted: false,
            seq: 0,
            slot: tokio::time::Instant::now(),
            awaiting: None,
            ended: false,
            result: StreamResult::default(),
        });
    }
    let mut streams = Vec::with_capacity(opened.len());
    for (index, (mut stream, response)) in opened.into_iter().zip(responses).enumerate() {
        let response = response
            .await
            .map_err(|e| format!("streaming detections for {}: {e}", stream.vehicle_id))?;
        if response.status() != http::StatusCode::OK {
            return Err(format!("the server answered HTTP {}", response.status()));
        }
        // A call refused at once ends in its response headers (trailers-only).
        if response.headers().contains_key("grpc-status") {
            grpc_status(Some(response.headers()))
                .map_err(|why| format!("streaming detections for {}: {why}", stream.vehicle_id))?;
        }
        let mut replies = Replies {
            index,
            body: response.into_body(),
            ended: false,
        };
        // The first reply: SessionAccepted.
        while !stream.accepted && !stream.ended {
            match replies.next().await {
                Some((_, arrival)) => receive(&mut stream, arrival),
                None => stream.fail("the call ended before SessionAccepted".into()),
            }
        }
        if let Some(error) = stream.result.error.take() {
            return Err(error);
        }
        streams.push((stream, replies));
    }
    Ok(streams)
}

/// Opens a StreamDetect call for `vehicle_id` (waiting for the server's room for another stream).
async fn start_call(
    client: &mut SendRequest<Bytes>,
    target: &Target,
    vehicle_id: &str,
) -> Result<(h2::client::ResponseFuture, SendStream<Bytes>), String> {
    let mut request = http::Request::builder()
        .method(http::Method::POST)
        .uri(format!("http://{}{PATH}", target.authority))
        .header("content-type", "application/grpc")
        .header("te", "trailers")
        .header(VEHICLE_ID_HEADER, vehicle_id);
    if let Some(authorization) = &target.authorization {
        request = request.header("authorization", authorization);
    }
    let request = request
        .body(())
        .map_err(|e| format!("a request for {vehicle_id}: {e}"))?;
    let ready = std::future::poll_fn(|cx| client.poll_ready(cx));
    ready
        .await
        .map_err(|e| format!("opening a stream for {vehicle_id}: {e}"))?;
    client
        .send_request(request, false)
        .map_err(|e| format!("opening a stream for {vehicle_id}: {e}"))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn reply(seq: u64) -> v1::StreamDetectResponse {
        v1::StreamDetectResponse {
            kind: Some(ResponseKind::Detections(v1::DetectionBatch {
                seq,
                ..Default::default()
            })),
        }
    }

    #[test]
    fn replies_split_and_joined_across_data_frames_are_read_whole_and_in_order() {
        let frames: Vec<u8> = [grpc_frame(&reply(1)), grpc_frame(&reply(2))].concat();
        // Cut everywhere: before the header ends, inside a body, between messages.
        for cut in 0..frames.len() {
            let mut buffer = BytesMut::from(&frames[..cut]);
            let mut seqs = Vec::new();
            while let Some(message) = next_message(&mut buffer).unwrap() {
                seqs.push(message);
            }
            buffer.extend_from_slice(&frames[cut..]);
            while let Some(message) = next_message(&mut buffer).unwrap() {
                seqs.push(message);
            }
            assert_eq!(seqs, [reply(1), reply(2)], "cut at {cut}");
            assert!(buffer.is_empty());
        }
    }

    #[test]
    fn a_frame_is_the_flag_the_length_and_the_encoding() {
        let message = reply(7);
        let frame = grpc_frame(&message);
        assert_eq!(frame[0], 0);
        assert_eq!(
            u32::from_be_bytes([frame[1], frame[2], frame[3], frame[4]]) as usize,
            message.encoded_len()
        );
        assert_eq!(&frame[5..], message.encode_to_vec().as_slice());
    }

    #[test]
    fn a_compressed_or_foreign_reply_is_an_error() {
        let mut compressed = BytesMut::from(&[1u8, 0, 0, 0, 0][..]);
        assert!(next_message(&mut compressed).is_err());
        let mut foreign = BytesMut::from(&[0u8, 0, 0, 0, 2, 0xff, 0xff][..]);
        assert!(next_message(&mut foreign).is_err());
    }

    #[test]
    fn the_status_comes_from_the_trailers() {
        let mut ok = http::HeaderMap::new();
        ok.insert("grpc-status", "0".parse().unwrap());
        assert_eq!(grpc_status(Some(&ok)), Ok(()));
        let mut refused = http::HeaderMap::new();
        refused.insert("grpc-status", "8".parse().unwrap());
        refused.insert("grpc-message", "too many sessions".parse().unwrap());
        assert_eq!(
            grpc_status(Some(&refused)),
            Err("the call ended with status 8: too many sessions".to_string())
        );
        assert!(grpc_status(None).is_err());
    }
}
