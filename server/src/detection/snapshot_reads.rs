//! Reads of stored session snapshots, coalesced: the reads that arrive while a query runs are
//! answered together by the next one, so a burst of vehicles failing over at once (a replica
//! lost) costs a few queries rather than a pooled connection each, and the pool stays free for
//! the alarm writer.
//!
//! While the store cannot be read, [`UnreadSince`] tells how long each vehicle has waited for it:
//! a vehicle waits (its streams are refused, to be retried) only through a fault that may pass,
//! and only for [`UNREAD_GRACE`].
//!
//! It owns its reader tasks, their queue and the waits; it must not decide what a read's outcome
//! means for a session (`sessions` and `resume` do).

use std::collections::HashMap;
use std::sync::{Arc, PoisonError};
use std::time::Duration;

use tokio::sync::{Mutex, mpsc, oneshot};
use tokio::time::Instant;

use crate::store::{FaultKind, SnapshotRow, Store, StoreError};

/// Most vehicles one query reads.
const MAX_BATCH: usize = 500;
/// Queries in flight at once: while they run, the next batches gather.
const READERS: usize = 4;

/// How long a vehicle's streams are refused while its stored session cannot be read, before it
/// starts afresh without it: a burst of failovers clears well within it, and a longer outage
/// must not leave vehicles unwatched.
pub const UNREAD_GRACE: Duration = Duration::from_secs(15);

/// A vehicle's stored snapshot (`None`: it has none), or why the store could not be read.
pub type SnapshotRead = Result<Option<SnapshotRow>, Unread>;

/// Why the store could not be read, and whether the fault may pass (the database busy or out of
/// reach, rather than its file lost or damaged).
#[derive(Clone, Debug, PartialEq)]
pub struct Unread {
    pub why: String,
    pub may_pass: bool,
}

impl Unread {
    fn of(error: &StoreError) -> Self {
        let may_pass = matches!(
            error,
            StoreError::Unavailable(fault)
                if matches!(fault.kind, FaultKind::Busy | FaultKind::Unreachable | FaultKind::Closed)
        );
        Self {
            why: error.to_string(),
            may_pass,
        }
    }

    /// No answer within `wait`: the store is slow or out of reach, which may pass.
    pub fn no_answer_within(wait: Duration) -> Self {
        Self {
            why: format!("no answer within {} s", wait.as_secs_f64()),
            may_pass: true,
        }
    }
}

struct Read {
    vehicle_id: String,
    answer: oneshot::Sender<SnapshotRead>,
}

/// The queue of snapshot reads. Its length is bounded by the streams starting at once (each
/// waits for its answer).
#[derive(Debug, Clone)]
pub struct SnapshotReads {
    queue: mpsc::UnboundedSender<Read>,
}

impl SnapshotReads {
    /// Starts the readers on the current runtime; they stop when the last handle is dropped.
    pub fn start(store: Store) -> Self {
        let (queue, reads) = mpsc::unbounded_channel();
        let reads = Arc::new(Mutex::new(reads));
        for _ in 0..READERS {
            tokio::spawn(answer_batches(store.clone(), Arc::clone(&reads)));
        }
        Self { queue }
    }

    /// The vehicle's stored snapshot, read with the others asked for meanwhile.
    pub async fn read(&self, vehicle_id: &str) -> SnapshotRead {
        let stopped = || Unread {
            why: "the snapshot readers stopped".to_string(),
            may_pass: false,
        };
        let (answer, answered) = oneshot::channel();
        self.queue
            .send(Read {
                vehicle_id: vehicle_id.to_string(),
                answer,
            })
            .map_err(|_| stopped())?;
        answered.await.map_err(|_| stopped())?
    }
}

/// One reader: takes what is queued (up to [`MAX_BATCH`]), reads it in one query and answers each.
async fn answer_batches(store: Store, reads: Arc<Mutex<mpsc::UnboundedReceiver<Read>>>) {
    let mut batch = Vec::with_capacity(MAX_BATCH);
    loop {
        if reads.lock().await.recv_many(&mut batch, MAX_BATCH).await == 0 {
            return;
        }
        // A caller that stopped waiting is not read for.
        batch.retain(|read: &Read| !read.answer.is_closed());
        if batch.is_empty() {
            continue;
        }
        let ids: Vec<&str> = batch.iter().map(|read| read.vehicle_id.as_str()).collect();
        match store.load_snapshots(&ids).await {
            Ok(rows) => {
                let by_vehicle: HashMap<&str, &SnapshotRow> = rows
                    .iter()
                    .map(|row| (row.vehicle_id.as_str(), row))
                    .collect();
                for read in batch.drain(..) {
                    let row = by_vehicle.get(read.vehicle_id.as_str()).copied().cloned();
                    let _ = read.answer.send(Ok(row));
                }
            }
            Err(error) => {
                let unread = Unread::of(&error);
                for read in batch.drain(..) {
                    let _ = read.answer.send(Err(unread.clone()));
                }
            }
        }
    }
}

/// When each vehicle first found the store unreadable, while it waits for it.
#[derive(Debug)]
pub struct UnreadSince {
    first: std::sync::Mutex<HashMap<String, Instant>>,
    pruned: std::sync::Mutex<Instant>,
}

impl Default for UnreadSince {
    fn default() -> Self {
        Self {
            first: std::sync::Mutex::default(),
            pruned: std::sync::Mutex::new(Instant::now()),
        }
    }
}

impl UnreadSince {
    /// Whether the vehicle, which found the store unreadable now, may still wait for it: it first
    /// did less than [`UNREAD_GRACE`] ago (or just now).
    pub fn may_wait(&self, vehicle_id: &str) -> bool {
        let now = Instant::now();
        let mut first = self.first.lock().unwrap_or_else(PoisonError::into_inner);
        // Vehicles that stopped retrying are forgotten (at most once per grace period), once past
        // twice the grace: one that retries late still learns it waited long enough.
        let mut pruned = self.pruned.lock().unwrap_or_else(PoisonError::into_inner);
        if now - *pruned >= UNREAD_GRACE {
            first.retain(|_, since| now - *since < 2 * UNREAD_GRACE);
            *pruned = now;
        }
        let since = *first.entry(vehicle_id.to_string()).or_insert(now);
        let waits = now - since < UNREAD_GRACE;
        if !waits {
            first.remove(vehicle_id);
        }
        waits
    }

    /// The vehicle's stored session was read: it waits no more.
    pub fn read(&self, vehicle_id: &str) {
        let mut first = self.first.lock().unwrap_or_else(PoisonError::into_inner);
        if !first.is_empty() {
            first.remove(vehicle_id);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::store::AlarmEvent;

    fn snapshot(vehicle_id: &str) -> SnapshotRow {
        SnapshotRow::opaque(vehicle_id, 1)
    }

    /// A read started at once on its own task (so that many wait together).
    fn read_on_a_task(
        reads: &SnapshotReads,
        vehicle_id: &str,
    ) -> tokio::task::JoinHandle<SnapshotRead> {
        let (reads, vehicle_id) = (reads.clone(), vehicle_id.to_string());
        tokio::spawn(async move { reads.read(&vehicle_id).await })
    }

    #[tokio::test]
    async fn a_burst_of_reads_gets_each_vehicle_its_own_snapshot() {
        let store = Store::open("sqlite::memory:").await.unwrap();
        let stored: Vec<SnapshotRow> = (0..300).map(|i| snapshot(&format!("car-{i}"))).collect();
        store
            .write_alarms_and_snapshots::<AlarmEvent>(&[], &stored)
            .await
            .unwrap();
        let reads = SnapshotReads::start(store);
        // Every stored vehicle, one twice, and vehicles without a snapshot, all at once.
        let asked: Vec<String> = (0..300)
            .chain([7])
            .map(|i| format!("car-{i}"))
            .chain((0..50).map(|i| format!("new-{i}")))
            .collect();
        let answers: Vec<_> = asked
            .iter()
            .map(|vehicle| read_on_a_task(&reads, vehicle))
            .collect();
        for (vehicle, answer) in asked.iter().zip(answers) {
            let row = answer.await.unwrap().unwrap();
            match vehicle.strip_prefix("car-") {
                Some(i) => assert_eq!(row.as_ref(), Some(&stored[i.parse::<usize>().unwrap()])),
                None => assert_eq!(row, None, "{vehicle}"),
            }
        }
    }

    #[tokio::test]
    async fn a_store_that_cannot_be_read_answers_every_read_with_why() {
        let store = Store::open("sqlite::memory:").await.unwrap();
        let reads = SnapshotReads::start(store.clone());
        store.close().await;
        let answers: Vec<_> = (0..3).map(|_| read_on_a_task(&reads, "car-1")).collect();
        for answer in answers {
            let unread = answer.await.unwrap().unwrap_err();
            assert!(unread.why.contains("closed"), "{unread:?}");
            assert!(
                unread.may_pass,
                "a closed pool (shutting down): another replica may answer"
            );
        }
    }

    #[tokio::test(start_paused = true)]
    async fn a_vehicle_waits_for_the_store_only_through_the_grace() {
        let since = UnreadSince::default();
        assert!(since.may_wait("car-1"));
        tokio::time::advance(UNREAD_GRACE - Duration::from_millis(1)).await;
        assert!(since.may_wait("car-1"), "still within the grace");
        assert!(since.may_wait("car-2"), "another vehicle's wait starts now");
        tokio::time::advance(Duration::from_millis(1)).await;
        assert!(!since.may_wait("car-1"), "waited long enough: afresh");
        // Its wait ended; a later fault starts a new one.
        assert!(since.may_wait("car-1"));
        // A vehicle whose snapshot was read waits afresh next time.
        tokio::time::advance(UNREAD_GRACE - Duration::from_millis(1)).await;
        since.read("car-2");
        tokio::time::advance(Duration::from_millis(1)).await;
        assert!(since.may_wait("car-2"));
    }

    #[tokio::test(start_paused = true)]
    async fn vehicles_that_stopped_retrying_are_forgotten() {
        let since = UnreadSince::default();
        for i in 0..1_000 {
            since.may_wait(&format!("car-{i}"));
        }
        tokio::time::advance(2 * UNREAD_GRACE).await;
        since.may_wait("car-new");
        assert_eq!(since.first.lock().unwrap().len(), 1);
    }
}
