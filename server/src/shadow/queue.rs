//! The shadow's bound: the queue between the request path and the shadow's worker, bounded in
//! samples, and the worker's CPU budget.
//!
//! The request path only offers a copy of a scored batch: it never waits. A batch that does not fit
//! is shed (counted), and the vehicle is marked: its next queued batch carries `after_gap`, so that
//! the worker starts that vehicle's shadow state afresh instead of scoring a sequence with a hole in
//! it as if it were whole. The worker spends at most its share of one core ([`Budget`]); when the
//! budget is spent it waits, the queue fills, and new work is shed. So a busy server sheds shadow
//! work first and the live replies never wait for it.
//!
//! Pure bookkeeping with a lock and a condition variable; no clocks are read here (the worker
//! passes its instants), so the bound is tested exactly.

use std::collections::{HashSet, VecDeque};
use std::sync::{Condvar, Mutex, PoisonError};
use std::time::{Duration, Instant};

use spoofwatch_core::sample::Sample;

/// What the live model said on one sample.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct LiveSignal {
    pub alarm: bool,
    pub onset: bool,
    /// The live alarm turned critical at this sample.
    pub escalation: bool,
    /// The sample lies inside an open incident's area (scored with the area prior, as live).
    pub in_incident_area: bool,
}

/// A batch the live model scored, for the candidate to score too.
#[derive(Clone, Debug)]
pub struct Job {
    pub shadow_id: i64,
    pub vehicle_id: String,
    pub samples: Vec<Sample>,
    /// One per sample.
    pub live: Vec<LiveSignal>,
    /// Work for this vehicle was shed since its previous queued batch.
    pub after_gap: bool,
}

/// What the worker is handed.
#[derive(Debug)]
pub enum Work {
    Batch(Job),
    /// The shadow stopped (or another one started): end and forget every vehicle's state.
    Stop {
        shadow_id: i64,
    },
}

/// Whether an offered batch was queued.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Offer {
    Queued,
    Shed,
}

/// The bounded queue.
#[derive(Debug)]
pub struct ShadowQueue {
    inner: Mutex<Inner>,
    ready: Condvar,
    /// Most samples queued at once.
    capacity: usize,
}

#[derive(Debug, Default)]
struct Inner {
    work: VecDeque<Work>,
    samples: usize,
    /// Vehicles whose work was shed since their last queued batch.
    gapped: HashSet<String>,
    closed: bool,
}

impl ShadowQueue {
    pub fn new(capacity: usize) -> Self {
        Self {
            inner: Mutex::new(Inner::default()),
            ready: Condvar::new(),
            capacity,
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Inner> {
        self.inner.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Queues `job` if its samples fit, else sheds it and marks its vehicle. Never waits for the
    /// worker.
    pub fn offer(&self, mut job: Job) -> Offer {
        let mut inner = self.lock();
        if inner.closed || inner.samples + job.samples.len() > self.capacity {
            inner.gapped.insert(job.vehicle_id);
            return Offer::Shed;
        }
        job.after_gap = inner.gapped.remove(&job.vehicle_id);
        inner.samples += job.samples.len();
        inner.work.push_back(Work::Batch(job));
        drop(inner);
        self.ready.notify_one();
        Offer::Queued
    }

    /// Queues a stop (always: it holds no samples) and forgets the gaps of the stopped shadow.
    pub fn stop(&self, shadow_id: i64) {
        let mut inner = self.lock();
        inner.gapped.clear();
        inner.work.push_back(Work::Stop { shadow_id });
        drop(inner);
        self.ready.notify_one();
    }

    /// The next work, waiting at most `timeout`; `None` on timeout or once closed and empty.
    pub fn next(&self, timeout: Duration) -> Option<Work> {
        let inner = self.lock();
        let (mut inner, _) = self
            .ready
            .wait_timeout_while(inner, timeout, |inner| {
                inner.work.is_empty() && !inner.closed
            })
            .unwrap_or_else(PoisonError::into_inner);
        let work = inner.work.pop_front()?;
        if let Work::Batch(job) = &work {
            inner.samples -= job.samples.len();
        }
        Some(work)
    }

    /// Samples queued now.
    pub fn samples(&self) -> usize {
        self.lock().samples
    }

    /// Refuses new batches and wakes the worker to finish (shutdown).
    pub fn close(&self) {
        self.lock().closed = true;
        self.ready.notify_all();
    }

    pub fn is_closed(&self) -> bool {
        self.lock().closed
    }
}

/// The worker's CPU budget: `share` of one core over time, with up to `burst` of scoring time
/// saved up. Time spent scoring is charged; while the credit is below zero the worker waits.
#[derive(Clone, Debug)]
pub struct Budget {
    share: f64,
    burst: f64,
    /// Seconds of scoring the worker may still spend.
    credit: f64,
    at: Instant,
}

impl Budget {
    pub fn new(share: f64, burst: Duration, now: Instant) -> Self {
        Self {
            share,
            burst: burst.as_secs_f64(),
            credit: burst.as_secs_f64(),
            at: now,
        }
    }

    /// Scoring took `spent`.
    pub fn charge(&mut self, spent: Duration) {
        self.credit -= spent.as_secs_f64();
    }

    /// How long to wait at `now` before scoring more (zero when there is credit left).
    pub fn wait(&mut self, now: Instant) -> Duration {
        let earned = now.saturating_duration_since(self.at).as_secs_f64() * self.share;
        self.credit = (self.credit + earned).min(self.burst);
        self.at = now;
        if self.credit >= 0.0 {
            Duration::ZERO
        } else {
            Duration::from_secs_f64(-self.credit / self.share)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn job(vehicle: &str, samples: usize) -> Job {
        Job {
            shadow_id: 1,
            vehicle_id: vehicle.to_string(),
            samples: vec![Sample::new(0.0, 32.0, -110.0, 1.0, 0.0); samples],
            live: vec![LiveSignal::default(); samples],
            after_gap: false,
        }
    }

    fn next_job(queue: &ShadowQueue) -> Job {
        match queue.next(Duration::ZERO) {
            Some(Work::Batch(job)) => job,
            other => panic!("expected a batch, got {other:?}"),
        }
    }

    #[test]
    fn the_queue_never_holds_more_samples_than_its_capacity() {
        let queue = ShadowQueue::new(10);
        assert_eq!(queue.offer(job("a", 4)), Offer::Queued);
        assert_eq!(queue.offer(job("b", 6)), Offer::Queued);
        assert_eq!(queue.samples(), 10);
        // Full: the next batch is shed, whatever its vehicle, however small.
        assert_eq!(queue.offer(job("a", 1)), Offer::Shed);
        assert_eq!(queue.samples(), 10);
        // A batch larger than the whole queue is always shed.
        let empty = ShadowQueue::new(10);
        assert_eq!(empty.offer(job("c", 11)), Offer::Shed);
        assert_eq!(empty.samples(), 0);
    }

    #[test]
    fn a_vehicle_whose_work_was_shed_starts_afresh_and_others_do_not() {
        let queue = ShadowQueue::new(5);
        assert_eq!(queue.offer(job("a", 5)), Offer::Queued);
        assert_eq!(queue.offer(job("a", 1)), Offer::Shed);
        assert_eq!(queue.offer(job("b", 1)), Offer::Shed);
        assert!(!next_job(&queue).after_gap, "queued before the gap");
        assert_eq!(queue.offer(job("a", 1)), Offer::Queued);
        assert_eq!(queue.offer(job("a", 1)), Offer::Queued);
        assert_eq!(queue.offer(job("c", 1)), Offer::Queued);
        let first = next_job(&queue);
        assert!(first.after_gap, "the first batch after the gap says so");
        assert!(!next_job(&queue).after_gap, "only the first");
        assert!(!next_job(&queue).after_gap, "a vehicle never shed");
        // A stop forgets the gaps: a new shadow starts every vehicle afresh anyway.
        assert_eq!(queue.offer(job("b", 1)), Offer::Queued);
        assert!(next_job(&queue).after_gap);
        queue.offer(job("d", 5));
        queue.offer(job("e", 1));
        queue.stop(1);
        next_job(&queue);
        assert!(matches!(
            queue.next(Duration::ZERO),
            Some(Work::Stop { shadow_id: 1 })
        ));
        assert_eq!(queue.offer(job("e", 1)), Offer::Queued);
        assert!(!next_job(&queue).after_gap);
    }

    #[test]
    fn a_closed_queue_sheds_everything() {
        let queue = ShadowQueue::new(10);
        queue.close();
        assert_eq!(queue.offer(job("a", 1)), Offer::Shed);
        assert!(queue.next(Duration::ZERO).is_none());
    }

    /// Milliseconds, rounded (the budget's arithmetic is in floating-point seconds).
    fn ms(wait: Duration) -> u64 {
        (wait.as_secs_f64() * 1000.0).round() as u64
    }

    #[test]
    fn the_budget_holds_scoring_to_its_share_of_a_core() {
        let t0 = Instant::now();
        let at = |ms: u64| t0 + Duration::from_millis(ms);
        let mut budget = Budget::new(0.5, Duration::from_millis(100), t0);
        assert_eq!(ms(budget.wait(t0)), 0);
        // 300 ms of scoring against 100 ms saved up: 200 ms in debt, repaid at half a second a
        // second.
        budget.charge(Duration::from_millis(300));
        assert_eq!(ms(budget.wait(t0)), 400);
        assert_eq!(ms(budget.wait(at(100))), 300);
        assert_eq!(ms(budget.wait(at(400))), 0);
        // Idle time saves up no more than the burst.
        assert_eq!(ms(budget.wait(at(100_000))), 0);
        budget.charge(Duration::from_millis(150));
        assert_eq!(ms(budget.wait(at(100_000))), 100);
    }
}
