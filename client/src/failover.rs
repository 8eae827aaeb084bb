//! When a vehicle's stream fails because its replica (or the connection to it) went away, and how
//! long to keep reconnecting: [`is_failover_error`] tells such failures from refusals, and a
//! [`FailoverEpisode`] paces the reconnect attempts (bounded backoff) within a total deadline.
//!
//! What is resent after a reconnect is the replay's business (`crate::replay`): it must not know
//! about recordings or sessions.

use std::time::Duration;

use tokio::time::Instant;
use tonic::Code;

use crate::error::ClientError;

/// Default total time a vehicle keeps reconnecting after its stream failed (`--failover-secs`):
/// long enough for a balancer to notice a dead replica (about 1–2 s) or for a restarted server to
/// come back, short enough that an operator sees a real outage.
pub const DEFAULT_FAILOVER_S: f64 = 30.0;
/// First wait between reconnect attempts; doubled on each further attempt up to [`MAX_BACKOFF`].
const FIRST_BACKOFF: Duration = Duration::from_millis(100);
/// Longest wait between two reconnect attempts.
const MAX_BACKOFF: Duration = Duration::from_secs(2);

/// Whether `error` ended a stream because the server or the path to it went away, so that the
/// same call on a new stream (to the same replica restarted, or another one) may succeed:
/// UNAVAILABLE (draining, unreachable), ABORTED (the session moved), CANCELLED, UNKNOWN and
/// INTERNAL (what HTTP/2 resets and proxies turn into), a stream that ended with batches
/// unanswered, or a connection that could not be made. Refusals of what was sent
/// (INVALID_ARGUMENT, NOT_FOUND, …) are not: they would fail again.
pub fn is_failover_error(error: &ClientError) -> bool {
    match error {
        ClientError::Rpc(rpc) => matches!(
            rpc.code(),
            Code::Unavailable | Code::Aborted | Code::Cancelled | Code::Unknown | Code::Internal
        ),
        ClientError::Connect { .. } | ClientError::StreamEnded(_) => true,
        _ => false,
    }
}

/// The wait after `attempts` earlier attempts of an episode.
fn backoff(attempts: u32) -> Duration {
    FIRST_BACKOFF
        .saturating_mul(1 << attempts.min(16))
        .min(MAX_BACKOFF)
}

/// One stretch of failed attempts: from the failure that started it until a stream makes progress
/// again or the deadline passes.
#[derive(Debug)]
pub struct FailoverEpisode {
    total: Duration,
    deadline: Instant,
    attempts: u32,
}

impl FailoverEpisode {
    /// An episode that gives up `total` after now.
    pub fn new(total: Duration) -> Self {
        Self {
            total,
            deadline: Instant::now() + total,
            attempts: 0,
        }
    }

    /// Waits before the next attempt after `error`; `Err(error)` (explained) when the error is not
    /// one to fail over on or the deadline would pass.
    pub async fn wait_before_retry(&mut self, error: ClientError) -> Result<(), ClientError> {
        if !is_failover_error(&error) {
            return Err(error);
        }
        let wake = Instant::now() + backoff(self.attempts);
        self.attempts += 1;
        if wake > self.deadline {
            return Err(ClientError::FailoverExhausted {
                after: self.total,
                attempts: self.attempts,
                last: Box::new(error),
            });
        }
        tokio::time::sleep_until(wake).await;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::error::RpcError;

    fn rpc(code: Code) -> ClientError {
        ClientError::Rpc(RpcError::new("streaming", tonic::Status::new(code, "x")))
    }

    #[test]
    fn a_lost_replica_fails_over_and_a_refusal_does_not() {
        for code in [
            Code::Unavailable,
            Code::Aborted,
            Code::Cancelled,
            Code::Unknown,
            Code::Internal,
        ] {
            assert!(is_failover_error(&rpc(code)), "{code:?}");
        }
        for code in [
            Code::InvalidArgument,
            Code::NotFound,
            Code::FailedPrecondition,
            Code::Unauthenticated,
            Code::ResourceExhausted,
            Code::DeadlineExceeded,
        ] {
            assert!(!is_failover_error(&rpc(code)), "{code:?}");
        }
        assert!(is_failover_error(&ClientError::StreamEnded(
            "streaming detections for car-1: the stream ended with 3 batches unanswered".into()
        )));
        assert!(!is_failover_error(&ClientError::Protocol(
            "expected 5 detections for batch 2, got 4".into()
        )));
    }

    #[test]
    fn the_backoff_doubles_up_to_its_bound() {
        let ms: Vec<u128> = (0..7).map(|a| backoff(a).as_millis()).collect();
        assert_eq!(ms, vec![100, 200, 400, 800, 1_600, 2_000, 2_000]);
    }

    #[tokio::test]
    async fn attempts_stop_at_the_deadline_and_a_refusal_at_once() {
        // 100 ms fits in 250 ms; 100 + 200 does not.
        let total = Duration::from_millis(250);
        let mut episode = FailoverEpisode::new(total);
        episode
            .wait_before_retry(rpc(Code::Unavailable))
            .await
            .expect("the first attempt is within the deadline");
        let error = episode
            .wait_before_retry(rpc(Code::Unavailable))
            .await
            .expect_err("the second would pass the deadline");
        assert!(
            error.to_string().contains("gave up failing over"),
            "{error}"
        );
        let refused = FailoverEpisode::new(total)
            .wait_before_retry(rpc(Code::InvalidArgument))
            .await
            .expect_err("a refusal is final");
        assert!(matches!(refused, ClientError::Rpc(_)));
    }
}
