//! The stream idle timeout (`--stream-idle-secs`): a client stream (StreamDetect,
//! StreamDetectFleet, the uploads) that sends nothing for that long ends with DEADLINE_EXCEEDED.
//! HTTP/2 keepalive only finds dead peers; this ends live ones that stopped talking, so they cannot
//! hold a session's stream (and a task) forever.
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
