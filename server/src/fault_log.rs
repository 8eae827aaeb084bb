//! Logging a lasting fault once when it starts and once when it clears, however often the work that
//! meets it is retried: the background loops that read or write the database (the alarm writer, the
//! feeds, the correlator, job leases, snapshot expiry, the active model's poll) retry every second
//! or so, and a database that is down for an hour must not write thousands of identical lines. What
//! goes on meanwhile is in the metrics and in storage health.
//!
//! It owns only the started/cleared state of one fault. It must not log (the caller writes its own
//! line, with its own fields) nor decide what counts as a fault.

use std::sync::atomic::{AtomicBool, Ordering};

/// Whether one kind of fault is going on, shared by the attempts that may meet it.
#[derive(Debug, Default)]
pub struct FaultLog {
    failing: AtomicBool,
}

impl FaultLog {
    /// An attempt failed: true when this starts the fault (log it), false while it goes on.
    pub fn failed(&self) -> bool {
        !self.failing.swap(true, Ordering::Relaxed)
    }

    /// An attempt succeeded: true when this clears the fault (log the recovery), false otherwise.
    pub fn succeeded(&self) -> bool {
        self.failing.swap(false, Ordering::Relaxed)
    }

    /// Whether the fault is going on.
    pub fn is_failing(&self) -> bool {
        self.failing.load(Ordering::Relaxed)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_fault_is_reported_once_when_it_starts_and_once_when_it_clears() {
        let log = FaultLog::default();
        assert!(!log.succeeded(), "nothing to clear before any failure");
        assert!(log.failed(), "the first failure starts the fault");
        for _ in 0..3_600 {
            assert!(!log.failed(), "an hour of retries logs nothing more");
        }
        assert!(log.is_failing());
        assert!(log.succeeded(), "the first success clears it");
        assert!(!log.succeeded());
        assert!(!log.is_failing());
        assert!(log.failed(), "a new fault is a new start");
    }
}
