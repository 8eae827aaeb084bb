//! The stream idle timeout (`--stream-idle-secs`): a client stream (StreamDetect,
//! StreamDetectFleet, the uploads) that sends nothing for that long ends with DEADLINE_EXCEEDED.
//! HTTP/2 keepalive only finds dead peers; this ends live ones that stopped talking, so they cannot
//! hold a session's stream (and a task) forever.
//!
//! The same limit ends a stream whose client stops reading: a reply that cannot be handed on
//! within it (the client grants no HTTP/2 window, so the call's small reply buffer stays full)
//! ends the stream, which would otherwise hold its task, session and buffers for as long as the
//! client keeps the connection open. A WatchAlarms watcher that leaves an event unread that long
//! is let go too (it resumes with its cursor).
//!
//! DEADLINE_EXCEEDED rather than CANCELLED: a time limit expired, and nobody cancelled anything.
//! The stream's end is like any other: a detection session detaches and stays resumable.

use std::time::Duration;

use tonic::{Status, Streaming};

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

    /// Hands `reply` to the call's reply buffer; `false` when the client went away or did not
    /// read for the whole limit (the stream must end).
    pub async fn send<T>(&self, tx: &tokio::sync::mpsc::Sender<T>, reply: T) -> bool {
        match tokio::time::timeout(self.0, tx.send(reply)).await {
            Ok(sent) => sent.is_ok(),
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
