//! The DetectionService RPCs. Each StreamDetect call runs in its own task that reads the inbound
//! stream and writes replies into a small bounded channel: a slow client fills only its own
//! channel, which pauses only its own task.

use std::sync::Arc;

use spoofwatch_proto::v1;
use spoofwatch_proto::v1::detection_service_server::DetectionService;
use spoofwatch_proto::v1::stream_detect_request::Kind as RequestKind;
use spoofwatch_proto::v1::stream_detect_response::Kind as ResponseKind;
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use tokio_util::sync::CancellationToken;
use tonic::{Request, Response, Status, Streaming};

use super::sessions::SessionManager;
use crate::error::{invalid_field, shutting_down, to_rpc_status};

/// Replies buffered per stream before the stream's reader waits for the client.
const OUTBOUND_BUFFER: usize = 16;

type Reply = Result<v1::StreamDetectResponse, Status>;

/// The DetectionService implementation.
#[derive(Debug, Clone)]
pub struct DetectionApi {
    pub sessions: Arc<SessionManager>,
    /// Cancelled when the server starts draining.
    pub shutdown: CancellationToken,
}

fn reply(kind: ResponseKind) -> Reply {
    Ok(v1::StreamDetectResponse { kind: Some(kind) })
}

fn item_error(seq: u64, status: &Status) -> Reply {
    reply(ResponseKind::ItemError(v1::ItemError {
        seq,
        status: Some(to_rpc_status(status)),
    }))
}

/// Drives one StreamDetect call to its end.
async fn run_stream(
    sessions: Arc<SessionManager>,
    shutdown: CancellationToken,
    mut inbound: Streaming<v1::StreamDetectRequest>,
    tx: mpsc::Sender<Reply>,
) {
    let first = tokio::select! {
        _ = shutdown.cancelled() => Err(shutting_down()),
        message = inbound.message() => message,
    };
    let start = match first {
        Ok(Some(v1::StreamDetectRequest {
            kind: Some(RequestKind::Start(start)),
        })) => start,
        Ok(Some(_)) => {
            let _ = tx
                .send(Err(invalid_field(
                    "start",
                    "the first message of a stream must be a SessionStart",
                )))
                .await;
            return;
        }
        Ok(None) => return,
        Err(status) => {
            let _ = tx.send(Err(status)).await;
            return;
        }
    };
    let attachment = match sessions.attach(&start).await {
        Ok(a) => a,
        Err(status) => {
            let _ = tx.send(Err(status)).await;
            return;
        }
    };
    tracing::debug!(vehicle = %start.vehicle_id, resumed = attachment.accepted.resumed, "stream attached");
    if tx
        .send(reply(ResponseKind::Accepted(attachment.accepted.clone())))
        .await
        .is_ok()
    {
        loop {
            let message = tokio::select! {
                biased;
                _ = shutdown.cancelled() => {
                    let _ = tx.send(Err(shutting_down())).await;
                    break;
                }
                _ = attachment.evicted.cancelled() => {
                    let _ = tx.send(Err(Status::aborted(
                        "another stream for this vehicle took the session over",
                    ))).await;
                    break;
                }
                message = inbound.message() => message,
            };
            let outcome = match message {
                Ok(Some(v1::StreamDetectRequest {
                    kind: Some(RequestKind::Batch(batch)),
                })) => match sessions
                    .process(&attachment.slot, batch.seq, &batch.samples, "batch.samples")
                    .await
                {
                    Ok(detections) => reply(ResponseKind::Detections(v1::DetectionBatch {
                        seq: batch.seq,
                        detections,
                    })),
                    Err(status) => item_error(batch.seq, &status),
                },
                Ok(Some(v1::StreamDetectRequest {
                    kind: Some(RequestKind::Start(_)),
                })) => item_error(
                    0,
                    &invalid_field("start", "the session has already started on this stream"),
                ),
                Ok(Some(v1::StreamDetectRequest { kind: None })) => {
                    item_error(0, &invalid_field("kind", "empty message: send a batch"))
                }
                // The client closed its side: the call ends with OK.
                Ok(None) => break,
                Err(status) => {
                    // e.g. an oversized message: report it as the call's status.
                    let _ = tx.send(Err(status)).await;
                    break;
                }
            };
            if tx.send(outcome).await.is_err() {
                break; // the client went away
            }
        }
    }
    sessions.detach(&attachment);
    tracing::debug!(vehicle = %start.vehicle_id, "stream detached");
}

#[tonic::async_trait]
impl DetectionService for DetectionApi {
    type StreamDetectStream = ReceiverStream<Reply>;

    async fn stream_detect(
        &self,
        request: Request<Streaming<v1::StreamDetectRequest>>,
    ) -> Result<Response<Self::StreamDetectStream>, Status> {
        if self.shutdown.is_cancelled() {
            return Err(shutting_down());
        }
        let (tx, rx) = mpsc::channel(OUTBOUND_BUFFER);
        tokio::spawn(run_stream(
            Arc::clone(&self.sessions),
            self.shutdown.clone(),
            request.into_inner(),
            tx,
        ));
        Ok(Response::new(ReceiverStream::new(rx)))
    }

    async fn detect(
        &self,
        request: Request<v1::DetectRequest>,
    ) -> Result<Response<v1::DetectResponse>, Status> {
        if self.shutdown.is_cancelled() {
            return Err(shutting_down());
        }
        let response = self.sessions.detect_unary(request.get_ref()).await?;
        Ok(Response::new(response))
    }

    async fn list_sessions(
        &self,
        request: Request<v1::ListSessionsRequest>,
    ) -> Result<Response<v1::ListSessionsResponse>, Status> {
        let r = request.into_inner();
        Ok(Response::new(
            self.sessions.list(r.page_size, &r.page_token).await?,
        ))
    }

    async fn get_session(
        &self,
        request: Request<v1::GetSessionRequest>,
    ) -> Result<Response<v1::Session>, Status> {
        Ok(Response::new(
            self.sessions.get(&request.into_inner().vehicle_id).await?,
        ))
    }

    async fn reset_session(
        &self,
        request: Request<v1::ResetSessionRequest>,
    ) -> Result<Response<v1::Session>, Status> {
        Ok(Response::new(
            self.sessions
                .reset(&request.into_inner().vehicle_id)
                .await?,
        ))
    }
}
