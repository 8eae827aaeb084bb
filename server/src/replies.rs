//! The reply buffer of one streaming detection call (StreamDetect, StreamDetectFleet): the call's
//! task hands each reply to it and reads the client's next message only once the reply is in, so a
//! client that does not read its replies (grants no HTTP/2 window) stops being read as soon as the
//! buffer is full. The buffer holds at most [`OUTBOUND_REPLIES`] replies and [`OUTBOUND_BYTES`]
//! bytes of encoded replies, whichever comes first: replies to batches of a thousand samples are
//! hundreds of kilobytes each, and a count alone let a stream that nobody read hold megabytes. A
//! reply larger than the whole byte budget is taken alone, once the buffer is empty. Beyond the
//! buffer, tonic holds the reply it is encoding and HTTP/2 at most the client's window for the
//! stream: what a silent client costs the server is bounded per stream, and the idle limit
//! (`crate::idle`) ends the stream after `--stream-idle-secs`.
//!
//! The bytes held by every stream's buffer together are the gauge
//! `spoofwatch_stream_reply_bytes_queued`.
//!
//! It owns the buffer and its accounting. It must not decide what a reply says, nor when a stream
//! ends.

use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll};

use tokio::sync::mpsc::error::TrySendError;
use tokio::sync::{OwnedSemaphorePermit, Semaphore, TryAcquireError, mpsc};
use tokio_stream::Stream;
use tonic::Status;

use crate::telemetry;

/// Most replies buffered per stream.
pub const OUTBOUND_REPLIES: usize = 16;
/// Most bytes of encoded replies buffered per stream (512 KiB).
pub const OUTBOUND_BYTES: u32 = 512 * 1024;

/// What a reply weighs in the buffer: its encoded size.
pub trait ReplyBytes {
    fn reply_bytes(&self) -> usize;
}

impl<M: prost::Message> ReplyBytes for Result<M, Status> {
    fn reply_bytes(&self) -> usize {
        match self {
            Ok(message) => message.encoded_len(),
            Err(status) => status.message().len() + status.details().len(),
        }
    }
}

/// A reply with the share of the byte budget it holds until the client's side takes it.
struct Held<T> {
    reply: T,
    _bytes: Bytes,
}

/// Budget permits, counted in the gauge while held.
struct Bytes(OwnedSemaphorePermit);

impl Bytes {
    fn new(permit: OwnedSemaphorePermit) -> Self {
        telemetry::reply_bytes_queued(f64::from(permit.num_permits() as u32));
        Self(permit)
    }
}

impl Drop for Bytes {
    fn drop(&mut self) {
        telemetry::reply_bytes_queued(-f64::from(self.0.num_permits() as u32));
    }
}

/// The sending half: the call's task.
#[derive(Debug)]
pub struct ReplySender<T> {
    tx: mpsc::Sender<Held<T>>,
    budget: Arc<Semaphore>,
}

/// The receiving half: the call's response stream, read by tonic as the client's window allows.
#[derive(Debug)]
pub struct ReplyStream<T> {
    rx: mpsc::Receiver<Held<T>>,
}

impl<T> std::fmt::Debug for Held<T> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Held")
    }
}

/// A new, empty buffer.
pub fn channel<T>() -> (ReplySender<T>, ReplyStream<T>) {
    let (tx, rx) = mpsc::channel(OUTBOUND_REPLIES);
    let budget = Arc::new(Semaphore::new(OUTBOUND_BYTES as usize));
    (ReplySender { tx, budget }, ReplyStream { rx })
}

/// The permits a reply of `bytes` takes: all of the budget at most.
fn permits(bytes: usize) -> u32 {
    bytes.clamp(1, OUTBOUND_BYTES as usize) as u32
}

impl<T: ReplyBytes> ReplySender<T> {
    /// Buffers `reply` if there is room for it now.
    pub fn try_send(&self, reply: T) -> Result<(), TrySendError<T>> {
        let permit =
            match Arc::clone(&self.budget).try_acquire_many_owned(permits(reply.reply_bytes())) {
                Ok(permit) => permit,
                Err(TryAcquireError::NoPermits) => return Err(TrySendError::Full(reply)),
                Err(TryAcquireError::Closed) => return Err(TrySendError::Closed(reply)),
            };
        self.tx
            .try_send(Held {
                reply,
                _bytes: Bytes::new(permit),
            })
            .map_err(|error| match error {
                TrySendError::Full(held) => TrySendError::Full(held.reply),
                TrySendError::Closed(held) => TrySendError::Closed(held.reply),
            })
    }

    /// Buffers `reply` once there is room; `Err` when the call's response stream is gone.
    pub async fn send(&self, reply: T) -> Result<(), T> {
        let needed = permits(reply.reply_bytes());
        let Ok(permit) = Arc::clone(&self.budget).acquire_many_owned(needed).await else {
            return Err(reply);
        };
        self.tx
            .send(Held {
                reply,
                _bytes: Bytes::new(permit),
            })
            .await
            .map_err(|error| error.0.reply)
    }
}

impl<T> Stream for ReplyStream<T> {
    type Item = T;

    fn poll_next(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<T>> {
        // The reply's bytes go back to the budget as tonic takes it to encode.
        self.rx
            .poll_recv(cx)
            .map(|held| held.map(|held| held.reply))
    }
}

#[cfg(test)]
mod tests {
    use std::future::poll_fn;

    use super::*;

    /// A reply of a given encoded size.
    struct Weighing(usize);

    impl ReplyBytes for Weighing {
        fn reply_bytes(&self) -> usize {
            self.0
        }
    }

    fn next(stream: &mut ReplyStream<Weighing>) -> Option<usize> {
        let waker = std::task::Waker::noop();
        match Pin::new(stream).poll_next(&mut Context::from_waker(waker)) {
            Poll::Ready(reply) => reply.map(|r| r.0),
            Poll::Pending => None,
        }
    }

    #[test]
    fn the_buffer_holds_at_most_its_bytes_and_its_count() {
        let (tx, mut rx) = channel();
        let large = OUTBOUND_BYTES as usize / 4;
        for _ in 0..4 {
            assert!(tx.try_send(Weighing(large)).is_ok());
        }
        assert!(
            matches!(tx.try_send(Weighing(1)), Err(TrySendError::Full(_))),
            "the bytes are taken"
        );
        assert_eq!(next(&mut rx), Some(large), "the client's side takes one");
        assert!(
            tx.try_send(Weighing(large)).is_ok(),
            "its bytes are free again"
        );
        for _ in 0..4 {
            assert_eq!(next(&mut rx), Some(large));
        }
        for _ in 0..OUTBOUND_REPLIES {
            assert!(tx.try_send(Weighing(10)).is_ok());
        }
        assert!(
            matches!(tx.try_send(Weighing(10)), Err(TrySendError::Full(_))),
            "so is the count"
        );
    }

    #[tokio::test]
    async fn a_reply_larger_than_the_budget_waits_for_an_empty_buffer() {
        let (tx, mut rx) = channel();
        let huge = OUTBOUND_BYTES as usize * 3;
        assert!(tx.try_send(Weighing(10)).is_ok());
        assert!(matches!(
            tx.try_send(Weighing(huge)),
            Err(TrySendError::Full(_))
        ));
        let mut send = std::pin::pin!(tx.send(Weighing(huge)));
        assert!(
            poll_fn(|cx| Poll::Ready(send.as_mut().poll(cx).is_pending())).await,
            "it waits while another reply is held"
        );
        assert_eq!(next(&mut rx), Some(10));
        assert!(send.await.is_ok(), "then it is taken alone");
        assert_eq!(next(&mut rx), Some(huge));
        drop(rx);
        assert!(tx.send(Weighing(1)).await.is_err(), "the stream is gone");
    }
}
