//! CPU-heavy work kept off the async runtime's threads, and bounded: scoring large batches,
//! parsing and checking model artifacts, parsing datasets and converting uploaded records run
//! here, at most [`HeavyWork::slots`] at once, so that health checks and the small detection
//! messages of a fleet are answered while an admin uploads, imports or evaluates. It owns the
//! bound, not the work.

use std::sync::Arc;

use tokio::runtime::{Handle, RuntimeFlavor};
use tokio::sync::Semaphore;

/// The bounded pool of heavy work (cheap to clone: one semaphore).
#[derive(Clone, Debug)]
pub struct HeavyWork {
    permits: Arc<Semaphore>,
    slots: usize,
}

impl HeavyWork {
    /// At most `slots` pieces of heavy work at once (at least one).
    pub fn new(slots: usize) -> Self {
        let slots = slots.max(1);
        HeavyWork {
            permits: Arc::new(Semaphore::new(slots)),
            slots,
        }
    }

    /// One slot fewer than the machine has cores (at least one): a core stays for the runtime.
    pub fn for_this_machine() -> Self {
        let cores = std::thread::available_parallelism().map_or(1, usize::from);
        HeavyWork::new(cores.saturating_sub(1))
    }

    pub fn slots(&self) -> usize {
        self.slots
    }

    /// Runs `work` once a slot is free, on a thread the runtime no longer schedules tasks on (the
    /// current worker hands its tasks to another first). On a single-threaded runtime (unit
    /// tests) it runs in place.
    pub async fn run<T>(&self, work: impl FnOnce() -> T) -> T {
        // The semaphore is never closed, so a permit always comes.
        let _permit = self.permits.acquire().await;
        match Handle::current().runtime_flavor() {
            RuntimeFlavor::MultiThread => tokio::task::block_in_place(work),
            _ => work(),
        }
    }
}

#[cfg(test)]
mod tests {
    use std::sync::atomic::{AtomicUsize, Ordering};
    use std::time::Duration;

    use super::*;

    #[tokio::test(flavor = "multi_thread", worker_threads = 4)]
    async fn no_more_than_its_slots_run_at_once_and_the_runtime_goes_on() {
        let work = HeavyWork::new(2);
        let running = Arc::new(AtomicUsize::new(0));
        let most = Arc::new(AtomicUsize::new(0));
        let tasks: Vec<_> = (0..6)
            .map(|_| {
                let (work, running, most) = (work.clone(), Arc::clone(&running), Arc::clone(&most));
                tokio::spawn(async move {
                    work.run(|| {
                        let now = running.fetch_add(1, Ordering::SeqCst) + 1;
                        most.fetch_max(now, Ordering::SeqCst);
                        std::thread::sleep(Duration::from_millis(50));
                        running.fetch_sub(1, Ordering::SeqCst);
                    })
                    .await
                })
            })
            .collect();
        // A plain task is scheduled while the heavy ones block their threads.
        tokio::time::timeout(Duration::from_secs(5), tokio::spawn(async {}))
            .await
            .expect("the runtime schedules other tasks")
            .expect("the task ran");
        for task in tasks {
            task.await.expect("ran");
        }
        assert_eq!(most.load(Ordering::SeqCst), 2);
        assert_eq!(HeavyWork::new(0).slots(), 1);
    }
}
