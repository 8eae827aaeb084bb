//! The stream idle timeout (`--stream-idle-secs`): a client stream (StreamDetect,
//! StreamDetectFleet, the uploads) that sends nothing for that long ends with DEADLINE_EXCEEDED.
//! HTTP/2 keepalive only finds dead peers; this ends live ones that stopped talking, so they cannot
//! hold a session's stream (and a task) forever.
//!
//! The same limit ends a stream whose client stops reading: a reply that cannot be handed on
//! within it (the client grants no HTTP/2 window, so the call's reply buffer stays full)
//! ends the stream, which would otherwise hold its task, session and buffers for as long as the
//! client keeps the connection open. A WatchAlarms watcher that leaves an event unread that long
//! is let go too (it resumes with its cursor).
//!
//! DEADLINE_EXCEEDED rather than CANCELLED: a time limit expired, and nobody cancelled anything.
//! The stream's end is like any other: a detection session detaches and stays resumable.

use std::pin::Pin;
use std::time::Duration;

use tokio::sync::mpsc::{Sender, error::TrySendError};
use tokio::time::{Instant, Sleep};
use tonic::{Status, Streaming};

use crate::replies::{ReplyBytes, ReplySender};

/// A call's reply buffer, as [`StreamIdle::send`] hands replies to it: a channel, or a detection
/// stream's buffer bounded in bytes too ([`ReplySender`]).
pub trait Outbound<T> {
    /// Buffers `reply` if there is room now.
    fn try_put(&self, reply: T) -> Result<(), TrySendError<T>>;
    /// Buffers `reply` once there is room; `false` when the receiving side is gone.
    fn put(&self, reply: T) -> impl Future<Output = bool> + Send;
}

impl<T: Send> Outbound<T> for Sender<T> {
    fn try_put(&self, reply: T) -> Result<(), TrySendError<T>> {
        self.try_send(reply)
    }

    async fn put(&self, reply: T) -> bool {
        self.send(reply).await.is_ok()
    }
}

impl<T: ReplyBytes + Send> Outbound<T> for ReplySender<T> {
    fn try_put(&self, reply: T) -> Result<(), TrySendError<T>> {
        self.try_send(reply)
    }

    async fn put(&self, reply: T) -> bool {
        self.send(reply).await.is_ok()
    }
}

/// The longest a client stream may stay silent.
#[derive(Clone, Copy, Debug)]
pub struct StreamIdle(pub Duration);

impl StreamIdle {
    /// The stream's next message, its end (`None`), its error, or the idle status when nothing
    /// arrives within the limit. Cancel-safe like [`Streaming::message`].
    pub async fn next<T>(&self, stream: &mut Streaming<T>) -> Result<Option<T>, Status> {
        match tokio::time::timeout(self.0, stream.message()).await {
            Ok(message) => message,
            Err(_) => Err(self.status()),
        }
    }

    /// A clock for one long-lived stream, whose messages come far more often than the limit.
    pub fn clock(&self) -> IdleClock {
        IdleClock {
            idle: *self,
            last_message: Instant::now(),
            timer: Box::pin(tokio::time::sleep(self.0)),
        }
    }

    /// Hands `reply` to the call's reply buffer; `false` when the client went away or did not
    /// read for the whole limit (the stream must end). A buffer with room takes it at once,
    /// without arming a timer.
    pub async fn send<T>(&self, tx: &impl Outbound<T>, reply: T) -> bool {
        let reply = match tx.try_put(reply) {
            Ok(()) => return true,
            Err(TrySendError::Closed(_)) => return false,
            Err(TrySendError::Full(reply)) => reply,
        };
        match tokio::time::timeout(self.0, tx.put(reply)).await {
            Ok(sent) => sent,
            Err(_) => {
                tracing::info!(
                    limit_s = self.0.as_secs(),
                    "ended a stream whose client stopped reading its replies"
                );
                false
            }
        }
    }

    /// DEADLINE_EXCEEDED naming the limit and what to do.
    pub fn status(&self) -> Status {
        Status::deadline_exceeded(format!(
            "no message for {} s (--stream-idle-secs); resume with a new stream",
            self.0.as_secs()
        ))
    }
}

/// The idle limit of one stream that receives many messages: a single timer, re-armed only when
/// it fires (to the last message's time plus the limit), so a message costs a clock read and no
/// timer of its own.
#[derive(Debug)]
pub struct IdleClock {
    idle: StreamIdle,
    last_message: Instant,
    timer: Pin<Box<Sleep>>,
}

impl IdleClock {
    /// As [`StreamIdle::next`]. Cancel-safe.
    pub async fn next<T>(&mut self, stream: &mut Streaming<T>) -> Result<Option<T>, Status> {
        loop {
            tokio::select! {
                biased;
                message = stream.message() => {
                    self.last_message = Instant::now();
                    return message;
                }
                () = self.timer.as_mut() => {
                    let due = self.last_message + self.idle.0;
                    if Instant::now() >= due {
                        return Err(self.idle.status());
                    }
                    self.timer.as_mut().reset(due);
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_idle_status_names_the_limit_and_the_remedy() {
        let status = StreamIdle(Duration::from_secs(300)).status();
        assert_eq!(status.code(), tonic::Code::DeadlineExceeded);
        assert_eq!(
            status.message(),
            "no message for 300 s (--stream-idle-secs); resume with a new stream"
        );
    }
}
