//! One `StreamDetect` call seen from the client: open it on a [`Connection`], send sample batches
//! with a bounded number awaiting their reply, receive each batch's detections or `ItemError` in
//! order, then half-close and drain.
//!
//! Every client of the stream (`spoofwatch detect`, `bench`, `demo`, the black-box tests) drives it
//! through this type, so the protocol rules (SessionAccepted first, one reply per batch in order,
//! one detection per sample) are checked in one place. It must not know about recordings, pacing
//! or printing: those belong to its callers (e.g. [`crate::replay`]).

use std::collections::VecDeque;
use std::time::{Duration, Instant};

use spoofwatch_proto::v1;
use spoofwatch_proto::v1::stream_detect_request::Kind as RequestKind;
use spoofwatch_proto::v1::stream_detect_response::Kind as ResponseKind;
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tonic::Streaming;

use crate::connection::Connection;
use crate::error::{ClientError, reply, rpc};
use crate::routing::for_vehicle;

/// Batches sent but not yet answered, by default. Without a window, "as fast as possible" would
/// queue a whole recording in buffers and the measured latency would be mostly queueing.
pub const MAX_IN_FLIGHT_BATCHES: usize = 4;
/// Requests buffered between the caller and the HTTP/2 stream.
const REQUEST_BUFFER: usize = 16;
/// How long a call that refused a batch may take to deliver the status it ended with.
const STATUS_WAIT: Duration = Duration::from_secs(2);

/// The `SessionStart` message that opens a session for `vehicle_id` (`model` empty: the server's
/// active model; `reset`: start afresh even when the session exists).
pub fn start_request(vehicle_id: &str, model: &str, reset: bool) -> v1::StreamDetectRequest {
    v1::StreamDetectRequest {
        kind: Some(RequestKind::Start(v1::SessionStart {
            vehicle_id: vehicle_id.to_string(),
            model: model.to_string(),
            reset,
        })),
    }
}

/// A `SampleBatch` message.
pub fn batch_request(seq: u64, samples: Vec<v1::Sample>) -> v1::StreamDetectRequest {
    v1::StreamDetectRequest {
        kind: Some(RequestKind::Batch(v1::SampleBatch { seq, samples })),
    }
}

/// A batch that was sent and awaits its reply.
#[derive(Clone, Copy, Debug)]
pub struct SentBatch {
    /// The batch's sequence number.
    pub seq: u64,
    /// Samples in the batch.
    pub len: usize,
    /// When it was handed to the stream.
    pub sent_at: Instant,
}

/// What the server answered to one batch.
#[derive(Clone, Debug)]
pub enum BatchOutcome {
    /// One detection per sample, in sample order.
    Detections(Vec<v1::Detection>),
    /// The batch was refused (its samples changed nothing; the stream goes on).
    Rejected(tonic_types::Status),
    /// The batch's seq was already applied to the session (it was resent): acknowledged, not
    /// scored again, no detections.
    Duplicate,
}

/// One batch's reply, tied to the batch.
#[derive(Clone, Debug)]
pub struct BatchReply {
    /// The batch answered.
    pub batch: SentBatch,
    /// Round trip: sent → reply received.
    pub latency: Duration,
    /// Detections or the refusal.
    pub outcome: BatchOutcome,
}

/// An open `StreamDetect` call.
#[derive(Debug)]
pub struct DetectStream {
    requests: mpsc::Sender<v1::StreamDetectRequest>,
    replies: Streaming<v1::StreamDetectResponse>,
    in_flight: VecDeque<SentBatch>,
    window: usize,
    reply_timeout: Option<Duration>,
    context: String,
}

impl DetectStream {
    /// Opens a call whose first message is `first` (normally a [`start_request`], whose vehicle id
    /// the call's `x-vehicle-id` header names). `Err` when the call itself is refused; a refusal of the first message may also arrive as the first reply.
    pub async fn open(
        connection: &Connection,
        first: v1::StreamDetectRequest,
    ) -> Result<Self, ClientError> {
        let vehicle_id = match &first.kind {
            Some(RequestKind::Start(start)) => start.vehicle_id.clone(),
            _ => String::new(),
        };
        let context = if vehicle_id.is_empty() {
            "streaming detections".to_string()
        } else {
            format!("streaming detections for {vehicle_id}")
        };
        let (requests, outbound) = mpsc::channel(REQUEST_BUFFER);
        // The channel was just created with room for this message.
        requests
            .try_send(first)
            .map_err(|_| ClientError::Protocol("request channel closed before the start".into()))?;
        let mut detection = connection.detection();
        let opening =
            detection.stream_detect(for_vehicle(&vehicle_id, ReceiverStream::new(outbound)));
        let replies = reply(context.clone(), opening).await?;
        Ok(Self {
            requests,
            replies,
            in_flight: VecDeque::new(),
            window: MAX_IN_FLIGHT_BATCHES,
            reply_timeout: None,
            context,
        })
    }

    /// Opens a session stream and waits for its `SessionAccepted`.
    pub async fn start(
        connection: &Connection,
        vehicle_id: &str,
        model: &str,
        reset: bool,
    ) -> Result<(Self, v1::SessionAccepted), ClientError> {
        let mut stream = Self::open(connection, start_request(vehicle_id, model, reset)).await?;
        let accepted = stream.accepted().await?;
        Ok((stream, accepted))
    }

    /// At most `batches` (≥ 1) batches may await their reply.
    pub fn with_window(mut self, batches: usize) -> Self {
        self.window = batches.max(1);
        self
    }

    /// Waiting for any one reply fails with [`ClientError::Timeout`] after `timeout`.
    pub fn with_reply_timeout(mut self, timeout: Duration) -> Self {
        self.reply_timeout = Some(timeout);
        self
    }

    /// Reads the first reply, which must be `SessionAccepted`.
    pub async fn accepted(&mut self) -> Result<v1::SessionAccepted, ClientError> {
        match self.next().await? {
            Some(ResponseKind::Accepted(accepted)) => Ok(accepted),
            other => Err(ClientError::Protocol(format!(
                "{}: expected SessionAccepted as the first reply, got {other:?}",
                self.context
            ))),
        }
    }

    /// Whether another batch may be sent without exceeding the window.
    pub fn has_room(&self) -> bool {
        self.in_flight.len() < self.window
    }

    /// Batches sent and not yet answered.
    pub fn in_flight(&self) -> usize {
        self.in_flight.len()
    }

    /// Sends any message as it is, without tracking a reply (e.g. to test how the server treats
    /// one). Batches should go through [`DetectStream::send_batch`].
    pub async fn send(&self, request: v1::StreamDetectRequest) -> Result<(), ClientError> {
        self.requests.send(request).await.map_err(|_| {
            ClientError::StreamEnded(format!("{}: the stream is closed", self.context))
        })
    }

    /// Sends a batch whose reply [`DetectStream::recv`] will return. Refused when the window is full.
    pub async fn send_batch(
        &mut self,
        seq: u64,
        samples: Vec<v1::Sample>,
    ) -> Result<(), ClientError> {
        if !self.has_room() {
            return Err(ClientError::Protocol(format!(
                "{}: {} batches already await their reply",
                self.context, self.window
            )));
        }
        let len = samples.len();
        if let Err(closed) = self.send(batch_request(seq, samples)).await {
            return Err(self.why_closed(closed).await);
        }
        self.in_flight.push_back(SentBatch {
            seq,
            len,
            sent_at: Instant::now(),
        });
        Ok(())
    }

    /// Why the call refused a batch: it has ended. With no reply owed, what is left to read is the
    /// status the server ended it with (UNAVAILABLE when it drains, say), which tells the caller more
    /// than `closed`; replies still owed are left for [`DetectStream::recv`].
    async fn why_closed(&mut self, closed: ClientError) -> ClientError {
        if !self.in_flight.is_empty() {
            return closed;
        }
        match tokio::time::timeout(STATUS_WAIT, self.replies.message()).await {
            Ok(Err(status)) => rpc(self.context.clone())(status),
            _ => closed,
        }
    }

    /// The next reply as it is: `Ok(None)` when the call ended with OK, `Err` with its status
    /// when it failed.
    pub async fn next(&mut self) -> Result<Option<ResponseKind>, ClientError> {
        let message = match self.reply_timeout {
            None => self.replies.message().await,
            Some(after) => tokio::time::timeout(after, self.replies.message())
                .await
                .map_err(|_| ClientError::Timeout {
                    context: self.context.clone(),
                    after,
                })?,
        }
        .map_err(rpc(self.context.clone()))?;
        Ok(message.and_then(|m| m.kind))
    }

    /// The reply to the oldest batch awaiting one. Replies must come in order, one per batch,
    /// with one detection per sample.
    pub async fn recv(&mut self) -> Result<BatchReply, ClientError> {
        let Some(&batch) = self.in_flight.front() else {
            return Err(ClientError::Protocol(format!(
                "{}: no batch awaits a reply",
                self.context
            )));
        };
        let reply = self.next().await?;
        let latency = batch.sent_at.elapsed();
        self.in_flight.pop_front();
        let outcome = match reply {
            Some(ResponseKind::Detections(reply))
                if reply.seq == batch.seq && reply.duplicate && reply.detections.is_empty() =>
            {
                BatchOutcome::Duplicate
            }
            Some(ResponseKind::Detections(reply))
                if reply.seq == batch.seq && reply.detections.len() == batch.len =>
            {
                BatchOutcome::Detections(reply.detections)
            }
            Some(ResponseKind::Detections(reply)) => {
                return Err(ClientError::Protocol(format!(
                    "{}: expected {} detections for batch {}, got {} for batch {}",
                    self.context,
                    batch.len,
                    batch.seq,
                    reply.detections.len(),
                    reply.seq
                )));
            }
            Some(ResponseKind::ItemError(error)) if error.seq == batch.seq => {
                BatchOutcome::Rejected(error.status.unwrap_or_default())
            }
            None => {
                return Err(ClientError::StreamEnded(format!(
                    "{}: the stream ended with {} batches unanswered",
                    self.context,
                    self.in_flight.len() + 1
                )));
            }
            other => {
                return Err(ClientError::Protocol(format!(
                    "{}: unexpected reply to batch {}: {other:?}",
                    self.context, batch.seq
                )));
            }
        };
        Ok(BatchReply {
            batch,
            latency,
            outcome,
        })
    }

    /// Sends a batch and waits for its detections (a refusal is an error; a batch whose seq was
    /// already applied gets none).
    pub async fn detect(
        &mut self,
        seq: u64,
        samples: Vec<v1::Sample>,
    ) -> Result<Vec<v1::Detection>, ClientError> {
        self.send_batch(seq, samples).await?;
        // Replies come in order: answers to batches sent earlier come first.
        loop {
            let reply = self.recv().await?;
            match reply.outcome {
                BatchOutcome::Detections(detections) if reply.batch.seq == seq => {
                    return Ok(detections);
                }
                BatchOutcome::Duplicate if reply.batch.seq == seq => return Ok(Vec::new()),
                BatchOutcome::Rejected(status) if reply.batch.seq == seq => {
                    return Err(ClientError::Protocol(format!(
                        "{}: batch {seq} was rejected: {}",
                        self.context,
                        crate::error::describe_rpc_status(&status)
                    )));
                }
                _ => continue,
            }
        }
    }

    /// Half-closes the call and reads it to its end (the server then detaches the session): the
    /// replies to batches still in flight are received and checked, then the call must end with
    /// OK and nothing more.
    pub async fn finish(mut self) -> Result<(), ClientError> {
        // Replacing our only sender with one whose receiver is gone half-closes the request stream.
        drop(std::mem::replace(&mut self.requests, mpsc::channel(1).0));
        while !self.in_flight.is_empty() {
            self.recv().await?;
        }
        match self.next().await? {
            None => Ok(()),
            Some(reply) => Err(ClientError::Protocol(format!(
                "{}: unexpected reply after the last batch: {reply:?}",
                self.context
            ))),
        }
    }
}
