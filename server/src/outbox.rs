//! The session outbox: what detection sessions must store, alarm onsets, escalations and ends and
//! session snapshots, leaves the detection path at once (no database call while a session is locked), and
//! one background writer stores it in batches, one transaction per batch, retried with backoff
//! until the store accepts them, and drained at shutdown; after each commit it tells the live alarm
//! feed (`crate::alarms::feed`) to read the new rows. Each alarm event is counted and logged as it is
//! queued (`crate::alarms::event::emitted`). Only the latest unstored snapshot of each vehicle is kept, and it is stored in the same
//! transaction as, or after, every alarm event emitted before it, so a session continued from a
//! stored snapshot never emits a stored event again (the joint write is
//! `Store::write_alarms_and_snapshots`).
//!
//! Alarm ids and event seqs are assigned here. Each server start (a run, numbered by the store)
//! takes a block of both ([`first_seq_of_run`]), so processes sharing a database never collide, a
//! retried batch is idempotent and an escalation or end always names its own onset. Seqs increase in emission
//! order under the queue's lock, so the queue holds events in emission order. The WatchAlarms
//! cursor is not assigned here but by the database when an event is stored (its log position, in
//! commit order across every process sharing the database).
//!
//! The queue is bounded: when it is full a new onset is dropped (counted and logged; never sent or
//! stored, and its end neither) rather than stall detection; ends are always queued (one per open
//! alarm, so they are bounded by the session limit). A write the store would refuse by its values
//! (a non-finite time, a probability outside [0, 1]) is refused here, so it cannot block the queue.
//!
//! It owns the queue and the writer; it must not serve anything (the alarm API is `crate::alarms`)
//! nor know how a session decides when an alarm starts or ends (`crate::detection`).

use std::collections::{HashMap, VecDeque};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use tokio::sync::{Notify, oneshot};
// Tokio's clock, so that tests can advance it.
use tokio::time::Instant;
use tokio_util::sync::CancellationToken;

use spoofwatch_core::severity::Severity;

use crate::alarms::event::{self as alarm, Onset};
use crate::error_chain::error_chain;
use crate::fault_log::FaultLog;
use crate::store::{
    AlarmEvent, AlarmEventKind, AlarmEventRow, SnapshotRow, Store, StoreError, first_seq_of_run,
    now_unix_ms,
};
use crate::telemetry;

/// Most writes queued before new onsets are dropped.
pub const OUTBOX_CAPACITY: usize = 100_000;
/// Most writes per transaction.
const BATCH: usize = 512;
/// Most session snapshots per transaction (about 2 KB each).
const SNAPSHOT_BATCH: usize = 256;
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
    /// Session snapshots waiting to be stored (at most one per vehicle).
    pub snapshot_backlog: usize,
    /// Session snapshots stored so far.
    pub snapshots_written: u64,
    /// How long the oldest waiting snapshot has waited (zero when none waits): a vehicle handed
    /// over now continues from up to this much earlier, and resends the difference.
    pub snapshot_lag: Duration,
}

/// What the queue's lock guards.
#[derive(Debug)]
struct Pending {
    /// Emitted events not stored yet, in seq (emission) order.
    queue: VecDeque<Arc<AlarmEvent>>,
    /// Alarms whose onset was emitted and whose end was not: an end is emitted only for these.
    open: HashMap<i64, AlarmEventRow>,
    next_id: i64,
    next_seq: i64,
    /// The latest unstored snapshot of each vehicle's session.
    snapshots: HashMap<String, QueuedSnapshot>,
    next_generation: u64,
}

/// A session snapshot waiting for the writer.
#[derive(Debug)]
struct QueuedSnapshot {
    row: SnapshotRow,
    /// The latest seq emitted when it was taken: it is stored only with or after that event.
    emitted_through: i64,
    /// Tells a newer snapshot of the vehicle apart from the one a write in flight holds.
    generation: u64,
    /// Told once this snapshot (or a newer one of the vehicle) is stored.
    waiters: Vec<oneshot::Sender<()>>,
    /// When the vehicle's oldest unstored snapshot was queued (a newer one replacing it keeps
    /// this): what the lag counts from.
    waiting_since: Instant,
}

/// The queue between the sessions and the writer.
#[derive(Debug)]
pub struct SessionOutbox {
    pending: Mutex<Pending>,
    capacity: usize,
    wake: Notify,
    /// Told after each committed batch of events (the live feed reads the new rows).
    stored: Notify,
    written: AtomicU64,
    dropped_onsets: AtomicU64,
    invalid: AtomicU64,
    failed_batches: AtomicU64,
    failing: FaultLog,
    /// Why the last batch was refused, while batches are refused (for the storage health's log).
    failure: Mutex<Option<String>>,
    snapshots_written: AtomicU64,
    run: i64,
}

impl SessionOutbox {
    /// The outbox of a server starting on `store`: it starts a new run (a block of ids and
    /// seqs), and ends the alarms that were left open and that no stored session snapshot holds
    /// (a crash, or a drain that could not store them) with logged end events.
    pub async fn new(store: &Store, capacity: usize) -> Result<Self, StoreError> {
        let now = now_unix_ms();
        let run = store.start_alarm_run(now).await?;
        let first_seq = first_seq_of_run(run);
        let closed = store.close_open_alarms(now, first_seq).await?;
        for event in &closed {
            alarm::ended_at_start(event);
        }
        let next_seq = first_seq + i64::try_from(closed.len()).unwrap_or(i64::MAX);
        Ok(Self {
            pending: Mutex::new(Pending {
                queue: VecDeque::new(),
                open: HashMap::new(),
                next_id: first_seq,
                next_seq,
                snapshots: HashMap::new(),
                next_generation: 0,
            }),
            capacity,
            wake: Notify::new(),
            stored: Notify::new(),
            written: AtomicU64::new(0),
            dropped_onsets: AtomicU64::new(0),
            invalid: AtomicU64::new(0),
            failed_batches: AtomicU64::new(0),
            failing: FaultLog::default(),
            failure: Mutex::new(None),
            snapshots_written: AtomicU64::new(0),
            run,
        })
    }

    /// This server start's run number: unique among the processes sharing the database.
    pub fn run_id(&self) -> i64 {
        self.run
    }

    /// Told (one permit kept) after each batch of events the writer committed.
    pub fn stored_events(&self) -> &Notify {
        &self.stored
    }

    fn pending(&self) -> std::sync::MutexGuard<'_, Pending> {
        // Every update leaves the state consistent before it can panic, so a poisoned lock is usable.
        self.pending.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Queues an alarm onset (as a warning, or critical at once), with the explanation of its
    /// onset sample when there is one, and returns its id (also when the onset had to be dropped,
    /// so that the session's later escalation and end refer to it and stay no-ops).
    pub fn onset(&self, onset: &Onset<'_>) -> i64 {
        let mut pending = self.pending();
        let id = pending.next_id;
        pending.next_id += 1;
        let event = AlarmEvent {
            seq: 0, // assigned when queued
            kind: AlarmEventKind::Onset,
            alarm: alarm::opened(id, onset),
        };
        if pending.queue.len() >= self.capacity {
            drop(pending);
            let dropped = self.dropped_onsets.fetch_add(1, Ordering::Relaxed) + 1;
            tracing::error!(
                vehicle = onset.vehicle_id,
                alarm = id,
                dropped,
                "alarm queue full: an alarm onset was not stored (the database is not keeping up)"
            );
            alarm::not_queued(AlarmEventKind::Onset, onset.severity);
            return id;
        }
        if !self.acceptable(&event) {
            alarm::not_queued(AlarmEventKind::Onset, onset.severity);
            return id;
        }
        pending.open.insert(id, event.alarm.clone());
        let event = self.emit(&mut pending, event);
        drop(pending);
        alarm::emitted(&event);
        id
    }

    /// Queues the escalation of open alarm `id` to critical at sample time `timestamp_s` (server
    /// wall time `at_ms`), with its peak and samples then (nothing when its onset was dropped or
    /// refused, or it is critical already).
    pub fn escalate(&self, id: i64, timestamp_s: f64, at_ms: i64, peak: f64, samples: u32) {
        let mut pending = self.pending();
        let Some(open) = pending.open.get(&id) else {
            drop(pending);
            alarm::not_queued(AlarmEventKind::Escalated, Severity::Critical);
            return;
        };
        if open.severity.0 == Severity::Critical {
            return;
        }
        let event = AlarmEvent {
            seq: 0, // assigned when queued
            kind: AlarmEventKind::Escalated,
            alarm: alarm::escalated(open, timestamp_s, at_ms, peak, i64::from(samples)),
        };
        if !self.acceptable(&event) {
            drop(pending);
            alarm::not_queued(AlarmEventKind::Escalated, Severity::Critical);
            return;
        }
        pending.open.insert(id, event.alarm.clone());
        let event = self.emit(&mut pending, event);
        drop(pending);
        alarm::emitted(&event);
    }

    /// Queues the end of alarm `id` at its last alarming sample (nothing when its onset was
    /// dropped or refused; it is counted as an end of `severity` then).
    pub fn end(
        &self,
        id: i64,
        end_timestamp_s: f64,
        peak_probability: f64,
        samples: u32,
        severity: Severity,
    ) {
        self.end_at(
            id,
            Some(end_timestamp_s),
            peak_probability,
            i64::from(samples),
            severity,
        );
    }

    /// Takes over an alarm that a session restored from a snapshot holds open (its onset was
    /// emitted by the process that wrote the snapshot), so that its end is emitted here.
    pub fn adopt(&self, alarm: AlarmEventRow) {
        self.pending().open.insert(alarm.id, alarm);
    }

    /// Ends an alarm whose session will not continue it (its snapshot expired) at its last
    /// alarming sample's time, with its peak and samples as the snapshot held them (`None`: as
    /// stored at its onset, and without a sample time).
    pub fn end_abandoned(&self, alarm: AlarmEventRow, last: Option<(f64, f64, i64)>) {
        let (id, peak, samples) = (alarm.id, alarm.peak_probability, alarm.samples);
        let severity = alarm.severity.0;
        self.adopt(alarm);
        match last {
            Some((last_timestamp_s, peak, samples)) => {
                self.end_at(id, Some(last_timestamp_s), peak, samples, severity)
            }
            None => self.end_at(id, None, peak, samples, severity),
        }
    }

    /// Ends alarm `id`; `severity` is what it is counted as when it is not open here (its onset
    /// was dropped or refused).
    fn end_at(
        &self,
        id: i64,
        end_timestamp_s: Option<f64>,
        peak_probability: f64,
        samples: i64,
        severity: Severity,
    ) {
        let mut pending = self.pending();
        let Some(onset) = pending.open.remove(&id) else {
            // Its onset was dropped or refused: the end is not stored, but the alarm did end.
            drop(pending);
            alarm::not_queued(AlarmEventKind::End, severity);
            return;
        };
        let event = AlarmEvent {
            seq: 0, // assigned when queued
            kind: AlarmEventKind::End,
            alarm: alarm::ended(
                &onset,
                end_timestamp_s,
                now_unix_ms(),
                peak_probability,
                samples,
            ),
        };
        if self.acceptable(&event) {
            let event = self.emit(&mut pending, event);
            drop(pending);
            alarm::emitted(&event);
        } else {
            drop(pending);
            alarm::not_queued(AlarmEventKind::End, event.alarm.severity.0);
        }
    }

    /// Gives `event` the next seq and queues it for the writer, under the lock, so that the queue
    /// is in seq order.
    fn emit(&self, pending: &mut Pending, mut event: AlarmEvent) -> Arc<AlarmEvent> {
        event.seq = pending.next_seq;
        pending.next_seq += 1;
        let event = Arc::new(event);
        pending.queue.push_back(Arc::clone(&event));
        self.wake.notify_one();
        event
    }

    /// Queues `row` as its vehicle's latest session snapshot, replacing an unstored older one. The
    /// receiver completes once it (or a newer one of the vehicle) is stored; it is dropped
    /// unanswered when a shutdown could not store it.
    pub fn save_snapshot(&self, row: SnapshotRow) -> oneshot::Receiver<()> {
        let (told, receipt) = oneshot::channel();
        let mut pending = self.pending();
        let emitted_through = pending.next_seq - 1;
        let generation = pending.next_generation;
        pending.next_generation += 1;
        let (mut waiters, waiting_since) = pending.snapshots.remove(&row.vehicle_id).map_or_else(
            || (Vec::new(), Instant::now()),
            |older| (older.waiters, older.waiting_since),
        );
        waiters.push(told);
        pending.snapshots.insert(
            row.vehicle_id.clone(),
            QueuedSnapshot {
                row,
                emitted_through,
                generation,
                waiters,
                waiting_since,
            },
        );
        drop(pending);
        self.wake.notify_one();
        receipt
    }

    /// The vehicle's snapshot that is queued and not stored yet, if any.
    pub fn queued_snapshot(&self, vehicle_id: &str) -> Option<SnapshotRow> {
        self.pending()
            .snapshots
            .get(vehicle_id)
            .map(|queued| queued.row.clone())
    }

    /// Told once the vehicle's queued snapshot (or a newer one) is stored; `None` when none waits.
    pub fn snapshot_stored(&self, vehicle_id: &str) -> Option<oneshot::Receiver<()>> {
        let mut pending = self.pending();
        let queued = pending.snapshots.get_mut(vehicle_id)?;
        let (told, receipt) = oneshot::channel();
        queued.waiters.push(told);
        Some(receipt)
    }

    /// Whether the store will take `event`'s values; a refusal is counted and logged.
    fn acceptable(&self, event: &AlarmEvent) -> bool {
        let Err(error) = event.validate() else {
            return true;
        };
        self.invalid.fetch_add(1, Ordering::Relaxed);
        tracing::error!(%error, ?event, "an alarm event with invalid values was not stored");
        false
    }

    /// The counters as they are now.
    pub fn stats(&self) -> OutboxStats {
        let (backlog, snapshot_backlog, oldest_snapshot) = {
            let pending = self.pending();
            let oldest = pending.snapshots.values().map(|q| q.waiting_since).min();
            (pending.queue.len(), pending.snapshots.len(), oldest)
        };
        OutboxStats {
            backlog,
            written: self.written.load(Ordering::Relaxed),
            dropped_onsets: self.dropped_onsets.load(Ordering::Relaxed),
            invalid: self.invalid.load(Ordering::Relaxed),
            failed_batches: self.failed_batches.load(Ordering::Relaxed),
            failing: self.failing.is_failing(),
            snapshot_backlog,
            snapshots_written: self.snapshots_written.load(Ordering::Relaxed),
            snapshot_lag: oldest_snapshot.map_or(Duration::ZERO, |since| since.elapsed()),
        }
    }

    /// At a shutdown the database refuses: every write still queued goes to the log (up to
    /// [`MAX_LOGGED_UNSTORED`] of them), so an operator can restore them by hand.
    fn log_unstored(&self) {
        let pending = self.pending();
        tracing::error!(
            lost = pending.queue.len(),
            "shutting down with alarm events the database did not accept; they follow"
        );
        for event in pending.queue.iter().take(MAX_LOGGED_UNSTORED) {
            tracing::error!(?event, "alarm event not stored");
        }
        if !pending.snapshots.is_empty() {
            tracing::error!(
                sessions = pending.snapshots.len(),
                "shutting down with session snapshots the database did not accept: these \
                 vehicles continue from their previous snapshot, or afresh"
            );
        }
    }

    /// Why batches are being refused, while they are: the last refusal's error and its causes.
    pub fn failure(&self) -> Option<String> {
        self.failure
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .clone()
    }

    fn set_failure(&self, failure: Option<String>) {
        *self
            .failure
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner) = failure;
    }

    /// The next write: up to [`BATCH`] queued events and the snapshots that may be stored with
    /// them (every event emitted before each snapshot is in the batch or already stored).
    fn next_write(&self) -> (Vec<Arc<AlarmEvent>>, Vec<SnapshotRow>, Vec<u64>) {
        let pending = self.pending();
        let events: Vec<Arc<AlarmEvent>> = pending.queue.iter().take(BATCH).cloned().collect();
        let horizon = match events.last() {
            Some(last) if events.len() < pending.queue.len() => last.seq,
            _ => i64::MAX,
        };
        let (snapshots, generations) = pending
            .snapshots
            .values()
            .filter(|queued| queued.emitted_through <= horizon)
            .take(SNAPSHOT_BATCH)
            .map(|queued| (queued.row.clone(), queued.generation))
            .unzip();
        (events, snapshots, generations)
    }

    /// After a committed write: its events leave the queue; its snapshots leave the map unless a
    /// newer one of the vehicle arrived meanwhile, and their waiters are told.
    fn committed(&self, events: usize, snapshots: &[SnapshotRow], generations: &[u64]) {
        let mut pending = self.pending();
        // Removed only once committed: a failed write is retried from the queue.
        pending.queue.drain(..events);
        for (row, generation) in snapshots.iter().zip(generations) {
            if pending
                .snapshots
                .get(&row.vehicle_id)
                .is_some_and(|queued| queued.generation == *generation)
                && let Some(stored) = pending.snapshots.remove(&row.vehicle_id)
            {
                for waiter in stored.waiters {
                    let _ = waiter.send(());
                }
            }
        }
        drop(pending);
        self.written.fetch_add(events as u64, Ordering::Relaxed);
        self.snapshots_written
            .fetch_add(snapshots.len() as u64, Ordering::Relaxed);
    }

    /// Ends the alarm a snapshot holds open that the store did not take, because another process
    /// replaced its session (a roll-out) and ended the alarm from the copy it had read: at this
    /// copy's progress, which the store keeps if it got further.
    fn end_replaced_copy(&self, copy: &SnapshotRow) {
        let (Some(id), Some(last), Some(peak), Some(samples)) = (
            copy.open_alarm_id,
            copy.open_alarm_last_timestamp_s,
            copy.open_alarm_peak_probability,
            copy.open_alarm_samples,
        ) else {
            return;
        };
        tracing::info!(
            vehicle = %copy.vehicle_id,
            alarm_id = id,
            "a session snapshot was not stored: another process replaced the session; its alarm \
             ends at this copy's last alarming sample if that is later"
        );
        // Open here, it ends with the severity it has here; otherwise it ended here already and
        // this end is neither stored nor counted as more than a warning's.
        self.end_at(id, Some(last), peak, samples, Severity::Warning);
    }

    /// The writer: stores queued writes until `stop` is cancelled and the queue is empty, or until
    /// `grace` has passed after `stop` with the store still refusing (what is left is logged).
    pub async fn run(&self, store: Store, stop: CancellationToken, grace: Duration) {
        let mut backoff = BACKOFF.0;
        let mut deadline = None;
        loop {
            let (batch, snapshots, generations) = self.next_write();
            if batch.is_empty() && snapshots.is_empty() {
                if stop.is_cancelled() {
                    return;
                }
                tokio::select! {
                    _ = self.wake.notified() => {}
                    _ = stop.cancelled() => {}
                }
                continue;
            }
            let write = store.write_alarms_and_snapshots(&batch, &snapshots);
            match telemetry::db_timed("alarm_batch_write", write).await {
                Ok(replaced) => {
                    for index in replaced {
                        self.end_replaced_copy(&snapshots[index]);
                    }
                    self.committed(batch.len(), &snapshots, &generations);
                    if !batch.is_empty() {
                        self.stored.notify_one();
                    }
                    if self.failing.succeeded() {
                        self.set_failure(None);
                        tracing::info!(
                            failed_batches = self.failed_batches.load(Ordering::Relaxed),
                            "alarm writer recovered: the database accepts alarm events again"
                        );
                    }
                    backoff = BACKOFF.0;
                }
                Err(error) => {
                    let failed = self.failed_batches.fetch_add(1, Ordering::Relaxed) + 1;
                    let reason = error_chain(&error);
                    self.set_failure(Some(reason.clone()));
                    // Once when the refusals start (the recovery is logged above): the backlog
                    // and the failed batches go on in the metrics and storage health.
                    if self.failing.failed() {
                        tracing::error!(
                            reason,
                            detail = ?error,
                            failed_batches = failed,
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
            .write_alarms(&[AlarmEvent {
                seq: 1,
                kind: AlarmEventKind::Onset,
                alarm: alarm::opened(41, &Onset::warning("old", "m", 1.0, 1, 0.9)),
            }])
            .await
            .unwrap();
        let outbox = Arc::new(SessionOutbox::new(&store, 100).await.unwrap());
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

        let first = outbox.onset(&Onset::warning("car-1", "m", 10.0, 1, 0.9));
        let second = outbox.onset(&Onset::warning("car-2", "m", 11.0, 1, 0.8));
        outbox.end(first, 14.0, 0.95, 5, Severity::Warning);
        let base = first_seq_of_run(outbox.run_id());
        assert_eq!(
            (first, second),
            (base, base + 1),
            "each start takes its own block of ids, above every earlier one"
        );
        wait_until("two batches failed", || outbox.stats().failed_batches >= 2).await;
        assert_eq!(outbox.stats().backlog, 3);
        assert!(outbox.stats().failing);
        let failure = outbox.failure().expect("the refusal is kept");
        assert!(failure.contains("injected fault"), "{failure}");
        assert_eq!(store.list_alarm_events(None, 10).await.unwrap().len(), 1);

        store.execute_for_test("DROP TRIGGER refuse").await;
        wait_until("the backlog is stored", || outbox.stats().backlog == 0).await;
        assert!(!outbox.stats().failing);
        assert_eq!(outbox.failure(), None);
        let rows = store.list_alarm_events(None, 10).await.unwrap();
        let stored: Vec<_> = rows
            .iter()
            .map(|r| (r.id, r.vehicle_id.as_str(), r.end_timestamp_s, r.samples))
            .collect();
        assert_eq!(
            stored,
            [
                (base + 1, "car-2", None, 1),
                (base, "car-1", Some(14.0), 5),
                (41, "old", None, 1)
            ]
        );
        assert_eq!(outbox.stats().written, 3);
        stop.cancel();
        writer.await.unwrap();
    }

    #[tokio::test]
    async fn a_copy_of_a_session_another_process_replaced_moves_its_alarms_end_on() {
        let (_dir, store) = temp_store().await;
        let outbox = Arc::new(SessionOutbox::new(&store, 100).await.unwrap());
        let stop = CancellationToken::new();
        let writer = tokio::spawn({
            let (outbox, store, stop) = (Arc::clone(&outbox), store.clone(), stop.clone());
            async move { outbox.run(store, stop, Duration::from_secs(5)).await }
        });
        let id = outbox.onset(&Onset::warning("car-1", "m1", 100.0, 1, 0.5));
        let copy_at = |last: f64, samples: i64| SnapshotRow {
            open_alarm_id: Some(id),
            open_alarm_last_timestamp_s: Some(last),
            open_alarm_peak_probability: Some(0.9),
            open_alarm_samples: Some(samples),
            ..snapshot_of("car-1", samples)
        };
        outbox.save_snapshot(copy_at(150.0, 51)).await.unwrap();

        // Another process replaces the session from that copy: it ends the alarm at 150 s and
        // stores a session of another model.
        let mut from_copy = alarm::opened(id, &Onset::warning("car-1", "m1", 100.0, 1, 0.5));
        from_copy = alarm::ended(&from_copy, Some(150.0), 2, 0.9, 51);
        let replacement = SnapshotRow {
            model_id: "m2".into(),
            writer: "other".into(),
            ..snapshot_of("car-1", 0)
        };
        store
            .write_alarms_and_snapshots(
                &[AlarmEvent {
                    seq: 1,
                    kind: AlarmEventKind::End,
                    alarm: from_copy,
                }],
                std::slice::from_ref(&replacement),
            )
            .await
            .unwrap();

        // This process's later copy is not stored, and the alarm ends where that copy got.
        outbox.save_snapshot(copy_at(170.0, 71)).await.unwrap();
        wait_until("the alarm's end moved on", || outbox.stats().backlog == 0).await;
        let alarm = &store.list_alarm_events(Some("car-1"), 1).await.unwrap()[0];
        assert_eq!((alarm.end_timestamp_s, alarm.samples), (Some(170.0), 71));
        assert_eq!(
            store.load_snapshot("car-1").await.unwrap(),
            Some(replacement)
        );
        stop.cancel();
        writer.await.unwrap();
    }

    #[tokio::test]
    async fn an_escalation_makes_the_open_alarm_critical_once_and_its_end_stays_critical() {
        let (_dir, store) = temp_store().await;
        let outbox = SessionOutbox::new(&store, 10).await.unwrap();
        let id = outbox.onset(&Onset::warning("car", "m", 10.0, 1, 0.6));
        outbox.escalate(id, 14.0, 2, 0.99, 5);
        outbox.escalate(id, 15.0, 3, 0.99, 6); // critical already: nothing more
        outbox.end(id, 20.0, 0.99, 11, Severity::Warning);
        outbox.escalate(id, 21.0, 4, 0.99, 12); // ended: nothing
        let stop = CancellationToken::new();
        stop.cancel();
        outbox
            .run(store.clone(), stop, Duration::from_secs(5))
            .await;
        let logged = store
            .alarm_events_after(0, i64::MAX, None, 10)
            .await
            .unwrap();
        let logged: Vec<_> = logged
            .iter()
            .map(|e| {
                let a = &e.event.alarm;
                (
                    e.event.kind,
                    a.severity.0,
                    a.escalated_timestamp_s,
                    a.samples,
                )
            })
            .collect();
        assert_eq!(
            logged,
            [
                (AlarmEventKind::Onset, Severity::Warning, None, 1),
                (AlarmEventKind::Escalated, Severity::Critical, Some(14.0), 5),
                (AlarmEventKind::End, Severity::Critical, Some(14.0), 11),
            ]
        );
        let stored = &store.list_alarm_events(Some("car"), 1).await.unwrap()[0];
        assert_eq!(
            (
                stored.severity.0,
                stored.escalated_at_ms,
                stored.end_timestamp_s
            ),
            (Severity::Critical, Some(2), Some(20.0))
        );
    }

    #[tokio::test]
    async fn a_full_queue_drops_new_onsets_but_keeps_ends() {
        let (_dir, store) = temp_store().await;
        let outbox = SessionOutbox::new(&store, 2).await.unwrap();
        let ids: Vec<i64> = (0..3)
            .map(|i| outbox.onset(&Onset::warning("car", "m", f64::from(i), 1, 0.9)))
            .collect();
        let base = first_seq_of_run(outbox.run_id());
        assert_eq!(
            ids,
            [base, base + 1, base + 2],
            "a dropped onset still gets its own id"
        );
        outbox.end(ids[0], 5.0, 0.9, 2, Severity::Warning);
        let stats = outbox.stats();
        assert_eq!((stats.backlog, stats.dropped_onsets), (3, 1));
    }

    #[tokio::test]
    async fn invalid_values_are_refused_before_they_can_block_the_queue() {
        let (_dir, store) = temp_store().await;
        let outbox = SessionOutbox::new(&store, 10).await.unwrap();
        let refused = outbox.onset(&Onset::warning("car", "m", f64::NAN, 1, 0.9));
        outbox.end(refused, 2.0, 0.9, 2, Severity::Warning); // its onset was refused: nothing to end
        let id = outbox.onset(&Onset::warning("car", "m", 3.0, 1, 0.9));
        outbox.end(id, 4.0, f64::NAN, 2, Severity::Warning);
        let stats = outbox.stats();
        assert_eq!((stats.backlog, stats.invalid), (1, 2));
    }

    #[tokio::test]
    async fn a_restart_continues_above_every_earlier_seq_and_ends_the_alarms_left_open() {
        let (_dir, store) = temp_store().await;
        let before = SessionOutbox::new(&store, 10).await.unwrap();
        let left_open = before.onset(&Onset::warning("car", "m", 1.0, 1, 0.9));
        let stop = CancellationToken::new();
        stop.cancel();
        before
            .run(store.clone(), stop, Duration::from_secs(5))
            .await;
        // An event a crash kept from being stored: its seq is never reused.
        let unstored = before.onset(&Onset::warning("car-2", "m", 2.0, 1, 0.9));
        assert_ne!(unstored, left_open);

        let after = SessionOutbox::new(&store, 10).await.unwrap();
        assert!(first_seq_of_run(after.run_id()) > unstored);
        let logged = store
            .alarm_events_after(0, i64::MAX, None, 10)
            .await
            .unwrap();
        let logged: Vec<_> = logged
            .iter()
            .map(|e| (e.position, e.event.kind, e.event.alarm.id))
            .collect();
        assert_eq!(
            logged,
            [
                (1, AlarmEventKind::Onset, left_open),
                (2, AlarmEventKind::End, left_open)
            ],
            "the end is logged after the onset, with a seq of the new run"
        );
        let end = store.alarm_events_after(1, 2, None, 10).await.unwrap();
        assert_eq!(end[0].event.seq, first_seq_of_run(after.run_id()));
    }

    fn snapshot_of(vehicle_id: &str, samples: i64) -> SnapshotRow {
        SnapshotRow::opaque(vehicle_id, samples)
    }

    #[tokio::test]
    async fn the_snapshot_lag_is_the_wait_of_the_oldest_unstored_snapshot() {
        let (_dir, store) = temp_store().await;
        let outbox = SessionOutbox::new(&store, 10).await.unwrap();
        assert_eq!(outbox.stats().snapshot_lag, Duration::ZERO, "none waits");
        tokio::time::pause();
        let _first = outbox.save_snapshot(snapshot_of("car-1", 10));
        tokio::time::advance(Duration::from_secs(3)).await;
        // A newer snapshot of the same vehicle replaces the unstored one but not its wait.
        let _newer = outbox.save_snapshot(snapshot_of("car-1", 20));
        let _other = outbox.save_snapshot(snapshot_of("car-2", 5));
        tokio::time::advance(Duration::from_secs(2)).await;
        let stats = outbox.stats();
        assert_eq!(stats.snapshot_backlog, 2);
        assert_eq!(stats.snapshot_lag, Duration::from_secs(5));
        tokio::time::resume();
        let stop = CancellationToken::new();
        stop.cancel();
        outbox
            .run(store.clone(), stop, Duration::from_secs(5))
            .await;
        let stats = outbox.stats();
        assert_eq!(
            (stats.snapshot_backlog, stats.snapshot_lag),
            (0, Duration::ZERO)
        );
    }

    #[tokio::test]
    async fn stopping_the_writer_stores_what_is_queued_first() {
        let (_dir, store) = temp_store().await;
        let outbox = SessionOutbox::new(&store, 10_000).await.unwrap();
        for i in 0..1_500 {
            let id = outbox.onset(&Onset::warning(&format!("car-{i}"), "m", 1.0, 1, 0.9));
            outbox.end(id, 2.0, 0.9, 2, Severity::Warning);
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
