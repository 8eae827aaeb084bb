//! Retries of unary calls: UNAVAILABLE and RESOURCE_EXHAUSTED are tried again, after the delay the
//! server asks for in `google.rpc.RetryInfo`, a bounded number of times within a bounded total
//! wait. Streams are never retried here: once messages have flowed, only the caller knows how to
//! resume (detection sessions resume by `seq`).
//!
//! Which failures are retried, and when:
//! - with RetryInfo (the server refused before doing anything: draining, queue or database full,
//!   database unavailable): after that delay, for every call;
//! - UNAVAILABLE without RetryInfo (the connection failed; the request may or may not have been
//!   done): with exponential backoff, only for idempotent calls;
//! - RESOURCE_EXHAUSTED without RetryInfo (e.g. a message over the size limit): never, it would
//!   fail again.

use std::time::Duration;

use tonic::{Code, Status};
use tonic_types::StatusExt;

use crate::error::{ClientError, code_name, rpc};

/// Whether running a call twice has the same effect as running it once.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Idempotency {
    /// Reads, deletes, activations, cancellations: safe to repeat after a lost reply.
    Idempotent,
    /// Creations: repeated only when the server said it refused the request.
    NotIdempotent,
}

/// How persistent the retries are.
#[derive(Clone, Copy, Debug)]
pub struct RetryPolicy {
    /// Most attempts, the first included.
    pub max_attempts: u32,
    /// Most time spent waiting between attempts, in total; a delay that would pass it ends the
    /// retries instead of being shortened (the server asked for that long).
    pub max_total_wait: Duration,
    /// First backoff when the server gave no delay; doubled on each further attempt.
    pub first_backoff: Duration,
}

/// Four attempts within 30 s: rides out a restart or a full job queue's few seconds, and still
/// fails a command while its operator is watching.
pub const DEFAULT_POLICY: RetryPolicy = RetryPolicy {
    max_attempts: 4,
    max_total_wait: Duration::from_secs(30),
    first_backoff: Duration::from_millis(500),
};

impl RetryPolicy {
    /// The wait before trying again after attempt number `attempt` (1 = the first) failed with
    /// `status`, having waited `waited` so far; `None` when the failure is final.
    pub fn delay(
        &self,
        status: &Status,
        idempotency: Idempotency,
        attempt: u32,
        waited: Duration,
    ) -> Option<Duration> {
        if attempt >= self.max_attempts {
            return None;
        }
        let asked = status
            .get_details_retry_info()
            .and_then(|info| info.retry_delay);
        let delay = match (status.code(), asked) {
            (Code::Unavailable | Code::ResourceExhausted, Some(asked)) => asked,
            (Code::Unavailable, None) if idempotency == Idempotency::Idempotent => self
                .first_backoff
                .saturating_mul(1 << (attempt - 1).min(16)),
            _ => return None,
        };
        (waited + delay <= self.max_total_wait).then_some(delay)
    }
}

/// Runs the unary call `call` until it succeeds or fails for good under [`DEFAULT_POLICY`]; a
/// final failure becomes an [`crate::RpcError`] naming `context`. Each retry is announced on
/// stderr, so that a wait is never silent.
pub async fn unary<T>(
    context: impl Into<String>,
    idempotency: Idempotency,
    call: impl AsyncFnMut() -> Result<tonic::Response<T>, Status>,
) -> Result<T, ClientError> {
    unary_with(&DEFAULT_POLICY, context, idempotency, call).await
}

/// [`unary`] under `policy`.
pub async fn unary_with<T>(
    policy: &RetryPolicy,
    context: impl Into<String>,
    idempotency: Idempotency,
    mut call: impl AsyncFnMut() -> Result<tonic::Response<T>, Status>,
) -> Result<T, ClientError> {
    let context = context.into();
    let mut waited = Duration::ZERO;
    let mut attempt = 1;
    loop {
        let status = match call().await {
            Ok(response) => return Ok(response.into_inner()),
            Err(status) => status,
        };
        let Some(delay) = policy.delay(&status, idempotency, attempt, waited) else {
            return Err(rpc(context)(status));
        };
        eprintln!(
            "{context}: {} ({}); retrying in {:.1} s (attempt {} of {})",
            code_name(status.code()),
            status.message(),
            delay.as_secs_f64(),
            attempt + 1,
            policy.max_attempts
        );
        tokio::time::sleep(delay).await;
        waited += delay;
        attempt += 1;
    }
}

#[cfg(test)]
mod tests {
    use std::sync::atomic::{AtomicU32, Ordering};

    use tonic_types::ErrorDetails;

    use super::*;

    fn with_retry_info(code: Code, delay: Duration) -> Status {
        Status::with_error_details(code, "busy", ErrorDetails::with_retry_info(Some(delay)))
    }

    const POLICY: RetryPolicy = RetryPolicy {
        max_attempts: 4,
        max_total_wait: Duration::from_secs(30),
        first_backoff: Duration::from_millis(500),
    };
    use Idempotency::{Idempotent, NotIdempotent};

    #[test]
    fn the_servers_retry_delay_is_honoured_for_every_call() {
        let full = with_retry_info(Code::ResourceExhausted, Duration::from_secs(5));
        let draining = with_retry_info(Code::Unavailable, Duration::from_secs(1));
        for idempotency in [Idempotent, NotIdempotent] {
            assert_eq!(
                POLICY.delay(&full, idempotency, 1, Duration::ZERO),
                Some(Duration::from_secs(5))
            );
            assert_eq!(
                POLICY.delay(&draining, idempotency, 3, Duration::from_secs(2)),
                Some(Duration::from_secs(1))
            );
        }
    }

    #[test]
    fn a_lost_connection_backs_off_exponentially_for_idempotent_calls_only() {
        let lost = Status::unavailable("connection reset");
        let delays: Vec<_> = (1..=3)
            .map(|attempt| POLICY.delay(&lost, Idempotent, attempt, Duration::ZERO))
            .collect();
        assert_eq!(
            delays,
            [
                Some(Duration::from_millis(500)),
                Some(Duration::from_secs(1)),
                Some(Duration::from_secs(2))
            ]
        );
        assert_eq!(POLICY.delay(&lost, NotIdempotent, 1, Duration::ZERO), None);
    }

    #[test]
    fn other_codes_a_size_refusal_and_spent_budgets_are_final() {
        for status in [
            Status::invalid_argument("bad"),
            Status::not_found("gone"),
            Status::internal("oops"),
            with_retry_info(Code::FailedPrecondition, Duration::from_secs(1)),
            Status::resource_exhausted("message length too large"),
        ] {
            assert_eq!(
                POLICY.delay(&status, Idempotent, 1, Duration::ZERO),
                None,
                "{status:?}"
            );
        }
        let draining = with_retry_info(Code::Unavailable, Duration::from_secs(1));
        assert_eq!(
            POLICY.delay(&draining, Idempotent, 4, Duration::ZERO),
            None,
            "the last attempt"
        );
        let later = with_retry_info(Code::ResourceExhausted, Duration::from_secs(31));
        assert_eq!(
            POLICY.delay(&later, Idempotent, 1, Duration::ZERO),
            None,
            "a delay beyond the budget is not shortened"
        );
        assert_eq!(
            POLICY.delay(&draining, Idempotent, 2, Duration::from_millis(29_500)),
            None,
            "the budget is spent"
        );
    }

    #[tokio::test]
    async fn a_call_is_repeated_until_it_succeeds_and_a_final_failure_names_the_context() {
        let calls = AtomicU32::new(0);
        let answer = unary("listing models", Idempotent, async || {
            match calls.fetch_add(1, Ordering::SeqCst) {
                0 => Err(with_retry_info(
                    Code::Unavailable,
                    Duration::from_millis(10),
                )),
                _ => Ok(tonic::Response::new(7)),
            }
        })
        .await
        .expect("the second attempt succeeds");
        assert_eq!((answer, calls.load(Ordering::SeqCst)), (7, 2));

        let calls = AtomicU32::new(0);
        let error = unary("creating a job", NotIdempotent, async || {
            calls.fetch_add(1, Ordering::SeqCst);
            Err::<tonic::Response<()>, _>(Status::unavailable("reset"))
        })
        .await
        .expect_err("not retried");
        assert_eq!(calls.load(Ordering::SeqCst), 1);
        assert!(
            error
                .to_string()
                .starts_with("creating a job: UNAVAILABLE: reset"),
            "{error}"
        );
    }
}
