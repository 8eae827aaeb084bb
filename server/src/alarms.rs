//! The alarm outbox: alarm onsets and ends leave the detection path at once (no database call while
//! a session is locked) and one background writer stores them in batches, one transaction per batch,
//! retried with backoff until the store accepts them, and drained at shutdown.
//!
//! Ids are assigned here, continuing after the largest stored id, so a retried batch is idempotent
//! and an end always names its own onset. The queue is bounded: when it is full a new onset is
//! dropped (counted and logged) rather than stall detection; ends are always queued (one per open
//! alarm, so they are bounded by the session limit). A write the store would refuse by its values
//! (a non-finite time, a probability outside [0, 1]) is refused here, so it cannot block the queue.

use std::collections::VecDeque;
use std::sync::Mutex;
use std::sync::atomic::{AtomicBool, AtomicI64, AtomicU64, Ordering};
use std::time::Duration;

use tokio::sync::Notify;
use tokio_util::sync::CancellationToken;

use crate::store::{AlarmWrite, Store, StoreError, now_unix_ms};
use crate::telemetry;

/// Most writes queued before new onsets are dropped.
pub const OUTBOX_CAPACITY: usize = 100_000;
/// Most writes per transaction.
const BATCH: usize = 512;
/// Most unstored writes logged one by one at shutdown.
const MAX_LOGGED_UNSTORED: usize = 10_000;
/// Retry delays after a failed batch: doubling from the first to the last.
const BACKOFF: (Duration, Duration) = (Duration::from_millis(50), Duration::from_secs(5));

/// Counters of the outbox, for logs, tests and metrics.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct OutboxStats {
    /// Writes waiting to be stored.
    pub backlog: usize,
    /// Writes stored so far.
    pub written: u64,
    /// Onsets dropped because the queue was full.
    pub dropped_onsets: u64,
    /// Writes refused for their values (they would never be stored).
    pub invalid: u64,
    /// Batches the store refused (each retried).
    pub failed_batches: u64,
    /// The last batch was refused: writes wait for the database to accept them again.
    pub failing: bool,
}

/// The queue between the sessions and the writer.
#[derive(Debug)]
pub struct AlarmOutbox {
    queue: Mutex<VecDeque<AlarmWrite>>,
    capacity: usize,
    wake: Notify,
    next_id: AtomicI64,
    written: AtomicU64,
    dropped_onsets: AtomicU64,
    invalid: AtomicU64,
    failed_batches: AtomicU64,
    failing: AtomicBool,
}

impl AlarmOutbox {
    /// An outbox whose ids continue after the largest one in `store`.
    pub async fn new(store: &Store, capacity: usize) -> Result<Self, StoreError> {
        Ok(Self {
            queue: Mutex::new(VecDeque::new()),
            capacity,
            wake: Notify::new(),
            next_id: AtomicI64::new(store.max_alarm_id().await? + 1),
            written: AtomicU64::new(0),
            dropped_onsets: AtomicU64::new(0),
            invalid: AtomicU64::new(0),
            failed_batches: AtomicU64::new(0),
            failing: AtomicBool::new(false),
        })
    }

    fn queue(&self) -> std::sync::MutexGuard<'_, VecDeque<AlarmWrite>> {
        // Pushes and pops cannot leave the queue inconsistent, so a poisoned lock is usable.
        self.queue.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Queues an alarm onset and returns its id (also when the onset had to be dropped, so that the
    /// session's later end refers to it and stays a no-op).
    pub fn onset(
        &self,
        vehicle_id: &str,
        model_id: &str,
        timestamp_s: f64,
        probability: f64,
    ) -> i64 {
        let id = self.next_id.fetch_add(1, Ordering::Relaxed);
        let write = AlarmWrite::Onset {
            id,
            vehicle_id: vehicle_id.to_string(),
            model_id: model_id.to_string(),
            onset_timestamp_s: timestamp_s,
            onset_at_ms: now_unix_ms(),
            probability,
        };
        if !self.acceptable(&write) {
            return id;
        }
        let mut queue = self.queue();
        if queue.len() >= self.capacity {
            drop(queue);
            let dropped = self.dropped_onsets.fetch_add(1, Ordering::Relaxed) + 1;
            tracing::error!(
                vehicle = vehicle_id,
                alarm = id,
                dropped,
                "alarm queue full: an alarm onset was not stored (the database is not keeping up)"
            );
            return id;
        }
        queue.push_back(write);
        drop(queue);
        self.wake.notify_one();
        id
    }

    /// Queues the end of alarm `id` at its last alarming sample.
    pub fn end(&self, id: i64, end_timestamp_s: f64, peak_probability: f64, samples: u32) {
        let write = AlarmWrite::End {
            id,
            end_timestamp_s,
            ended_at_ms: now_unix_ms(),
            peak_probability,
            samples,
        };
        if self.acceptable(&write) {
            self.queue().push_back(write);
            self.wake.notify_one();
        }
    }

    /// Whether the store will take `write`'s values; a refusal is counted and logged.
    fn acceptable(&self, write: &AlarmWrite) -> bool {
        let Err(error) = write.validate() else {
            return true;
        };
        self.invalid.fetch_add(1, Ordering::Relaxed);
        tracing::error!(%error, ?write, "an alarm event with invalid values was not stored");
        false
    }

    /// The counters as they are now.
    pub fn stats(&self) -> OutboxStats {
        OutboxStats {
            backlog: self.queue().len(),
            written: self.written.load(Ordering::Relaxed),
            dropped_onsets: self.dropped_onsets.load(Ordering::Relaxed),
            invalid: self.invalid.load(Ordering::Relaxed),
            failed_batches: self.failed_batches.load(Ordering::Relaxed),
            failing: self.failing.load(Ordering::Relaxed),
        }
    }

    /// At a shutdown the database refuses: every write still queued goes to the log (up to
    /// [`MAX_LOGGED_UNSTORED`] of them), so an operator can restore them by hand.
    fn log_unstored(&self) {
        let queue = self.queue();
        tracing::error!(
            lost = queue.len(),
            "shutting down with alarm events the database did not accept; they follow"
        );
        for write in queue.iter().take(MAX_LOGGED_UNSTORED) {
            tracing::error!(?write, "alarm event not stored");
        }
    }

    /// The writer: stores queued writes until `stop` is cancelled and the queue is empty, or until
    /// `grace` has passed after `stop` with the store still refusing (what is left is logged).
    pub async fn run(&self, store: Store, stop: CancellationToken, grace: Duration) {
        let mut backoff = BACKOFF.0;
        let mut deadline = None;
        loop {
            let batch: Vec<AlarmWrite> = self.queue().iter().take(BATCH).cloned().collect();
            if batch.is_empty() {
                if stop.is_cancelled() {
                    return;
                }
                tokio::select! {
                    _ = self.wake.notified() => {}
                    _ = stop.cancelled() => {}
                }
                continue;
            }
            match telemetry::db_timed("alarm_batch_write", store.write_alarms(&batch)).await {
                Ok(()) => {
                    self.queue().drain(..batch.len());
                    self.written
                        .fetch_add(batch.len() as u64, Ordering::Relaxed);
                    if self.failing.swap(false, Ordering::Relaxed) {
                        tracing::info!(
                            failed_batches = self.failed_batches.load(Ordering::Relaxed),
                            "alarm writer recovered: the database accepts alarm events again"
                        );
                    }
                    backoff = BACKOFF.0;
                }
                Err(error) => {
                    self.failed_batches.fetch_add(1, Ordering::Relaxed);
                    if !self.failing.swap(true, Ordering::Relaxed) {
                        tracing::error!(
                            %error,
                            detail = ?error,
                            backlog = self.stats().backlog,
                            "could not store alarm events; retrying until the database accepts them"
                        );
                    }
                    if stop.is_cancelled() {
                        let deadline =
                            *deadline.get_or_insert_with(|| tokio::time::Instant::now() + grace);
                        if tokio::time::Instant::now() >= deadline {
                            self.log_unstored();
                            return;
                        }
                    }
                    tokio::select! {
                        _ = tokio::time::sleep(backoff) => {}
                        _ = stop.cancelled(), if deadline.is_none() => {}
                    }
                    backoff = (backoff * 2).min(BACKOFF.1);
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use std::sync::Arc;

    use super::*;

    async fn temp_store() -> (tempfile::TempDir, Store) {
        let dir = tempfile::tempdir().expect("temp dir");
        let path = dir.path().join("spoofwatch.db");
        let store = Store::open(&path.to_string_lossy()).await.expect("open");
        (dir, store)
    }

    /// Polls `done` every 10 ms; fails after 10 s (a hang guard, not a timing assertion).
    async fn wait_until(what: &str, done: impl Fn() -> bool) {
        for _ in 0..1_000 {
            if done() {
                return;
            }
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
        panic!("timed out waiting until {what}");
    }

    #[tokio::test]
    async fn alarms_queued_while_the_database_refuses_are_stored_once_it_accepts() {
        let (_dir, store) = temp_store().await;
        store
            .write_alarms(&[AlarmWrite::Onset {
                id: 41,
                vehicle_id: "old".into(),
                model_id: "m".into(),
                onset_timestamp_s: 1.0,
                onset_at_ms: 1,
                probability: 0.9,
            }])
            .await
            .unwrap();
        let outbox = Arc::new(AlarmOutbox::new(&store, 100).await.unwrap());
        // The fault: every insert into alarm_events aborts (no root or full disk needed).
        store
            .execute_for_test(
                "CREATE TRIGGER refuse BEFORE INSERT ON alarm_events \
                 BEGIN SELECT RAISE(ABORT, 'injected fault'); END",
            )
            .await;
        let stop = CancellationToken::new();
        let writer = tokio::spawn({
            let (outbox, store, stop) = (Arc::clone(&outbox), store.clone(), stop.clone());
            async move { outbox.run(store, stop, Duration::from_secs(5)).await }
        });

        let first = outbox.onset("car-1", "m", 10.0, 0.9);
        let second = outbox.onset("car-2", "m", 11.0, 0.8);
        outbox.end(first, 14.0, 0.95, 5);
        assert_eq!(
            (first, second),
            (42, 43),
            "ids continue after the stored ones"
        );
        wait_until("two batches failed", || outbox.stats().failed_batches >= 2).await;
        assert_eq!(outbox.stats().backlog, 3);
        assert!(outbox.stats().failing);
        assert_eq!(store.list_alarm_events(None, 10).await.unwrap().len(), 1);

        store.execute_for_test("DROP TRIGGER refuse").await;
        wait_until("the backlog is stored", || outbox.stats().backlog == 0).await;
        assert!(!outbox.stats().failing);
        let rows = store.list_alarm_events(None, 10).await.unwrap();
        let stored: Vec<_> = rows
            .iter()
            .map(|r| (r.id, r.vehicle_id.as_str(), r.end_timestamp_s, r.samples))
            .collect();
        assert_eq!(
            stored,
            [
                (43, "car-2", None, 1),
                (42, "car-1", Some(14.0), 5),
                (41, "old", None, 1)
            ]
        );
        assert_eq!(outbox.stats().written, 3);
        stop.cancel();
        writer.await.unwrap();
    }

    #[tokio::test]
    async fn a_full_queue_drops_new_onsets_but_keeps_ends() {
        let (_dir, store) = temp_store().await;
        let outbox = AlarmOutbox::new(&store, 2).await.unwrap();
        let ids: Vec<i64> = (0..3)
            .map(|i| outbox.onset("car", "m", f64::from(i), 0.9))
            .collect();
        assert_eq!(ids, [1, 2, 3], "a dropped onset still gets its own id");
        outbox.end(ids[0], 5.0, 0.9, 2);
        let stats = outbox.stats();
        assert_eq!((stats.backlog, stats.dropped_onsets), (3, 1));
    }

    #[tokio::test]
    async fn invalid_values_are_refused_before_they_can_block_the_queue() {
        let (_dir, store) = temp_store().await;
        let outbox = AlarmOutbox::new(&store, 10).await.unwrap();
        let id = outbox.onset("car", "m", f64::NAN, 0.9);
        outbox.end(id, 2.0, f64::NAN, 2);
        outbox.onset("car", "m", 3.0, 0.9);
        let stats = outbox.stats();
        assert_eq!((stats.backlog, stats.invalid), (1, 2));
    }

    #[tokio::test]
    async fn stopping_the_writer_stores_what_is_queued_first() {
        let (_dir, store) = temp_store().await;
        let outbox = AlarmOutbox::new(&store, 10_000).await.unwrap();
        for i in 0..1_500 {
            let id = outbox.onset(&format!("car-{i}"), "m", 1.0, 0.9);
            outbox.end(id, 2.0, 0.9, 2);
        }
        let stop = CancellationToken::new();
        stop.cancel();
        outbox
            .run(store.clone(), stop, Duration::from_secs(5))
            .await;
        assert_eq!(outbox.stats().backlog, 0);
        let rows = store.list_alarm_events(None, 5_000).await.unwrap();
        assert_eq!(rows.len(), 1_500);
        assert!(rows.iter().all(|r| r.end_timestamp_s == Some(2.0)));
    }
}
