//! CPU-heavy work kept off the async runtime's threads, bounded, and yielding to them: scoring
//! large batches, parsing and checking model artifacts, parsing datasets and converting uploaded
//! records run here, at most [`HeavyWork::slots`] at once, on threads of the lowest CPU priority
//! ([`at_low_priority`], which training and evaluation jobs use too). So health checks and the
//! small detection messages of a fleet are answered promptly even when the machine's cores are
//! busy with an admin's uploads, imports or jobs. It owns the bound and the priority, not the
//! work.

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

    /// Runs `work` once a slot is free, [`at_low_priority`], while the calling task's thread
    /// waits outside the runtime (its worker hands its tasks to another first). On a
    /// single-threaded runtime (unit tests) the wait happens in place.
    pub async fn run<T: Send>(&self, work: impl FnOnce() -> T + Send) -> T {
        // The semaphore is never closed, so a permit always comes.
        let _permit = self.permits.acquire().await;
        match Handle::current().runtime_flavor() {
            RuntimeFlavor::MultiThread => tokio::task::block_in_place(|| at_low_priority(work)),
            _ => at_low_priority(work),
        }
    }
}

/// The nice value of heavy work: the lowest priority, so that a core shared with the runtime's
/// threads goes to them whenever they have something to do.
pub const HEAVY_NICE: i32 = 19;

/// Runs `work` on a thread of its own at nice [`HEAVY_NICE`] and waits for it. The thread is
/// scoped, so `work` may borrow from the caller. Should no thread be available, `work` runs on
/// the calling thread.
pub fn at_low_priority<T: Send>(work: impl FnOnce() -> T + Send) -> T {
    let mut work = Some(work);
    let outcome = std::thread::scope(|scope| {
        let spawned = std::thread::Builder::new()
            .name("heavy-work".into())
            .spawn_scoped(scope, || {
                lower_this_threads_priority();
                work.take().map(|work| work())
            });
        spawned.ok().map(|thread| {
            thread
                .join()
                .unwrap_or_else(|panic| std::panic::resume_unwind(panic))
        })
    });
    match (outcome.flatten(), work) {
        (Some(done), _) => done,
        (None, Some(work)) => work(),
        (None, None) => unreachable!("the work ran or is still here"),
    }
}

/// Gives the calling thread the nice value [`HEAVY_NICE`]. On Linux the nice value belongs to
/// the thread, not the process, so the runtime's threads keep theirs. Failing is harmless: the
/// work then runs at the process's priority.
fn lower_this_threads_priority() {
    let thread = rustix::thread::gettid();
    if let Err(error) = rustix::process::setpriority_process(Some(thread), HEAVY_NICE) {
        tracing::debug!(%error, "heavy work runs at the process's priority");
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

    /// The nice value of the calling thread, read from `/proc/thread-self/stat` (field 19).
    fn this_threads_nice() -> i32 {
        let stat = std::fs::read_to_string("/proc/thread-self/stat").expect("thread stat");
        let after_name = &stat[stat.rfind(')').expect("the name's end") + 2..];
        after_name
            .split(' ')
            .nth(16)
            .and_then(|nice| nice.parse().ok())
            .expect("the nice field")
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn heavy_work_runs_at_the_lowest_priority_and_the_runtime_keeps_its_own() {
        let before = this_threads_nice();
        let mut borrowed = vec![1, 2, 3];
        let nice = HeavyWork::new(1)
            .run(|| {
                borrowed.push(4);
                this_threads_nice()
            })
            .await;
        assert_eq!(nice, HEAVY_NICE);
        assert_eq!(borrowed, [1, 2, 3, 4]);
        assert_eq!(this_threads_nice(), before);
    }

    #[test]
    fn a_panic_in_heavy_work_reaches_the_caller() {
        let caught = std::panic::catch_unwind(|| at_low_priority(|| panic!("bad input")));
        let panic = caught.expect_err("the panic is passed on");
        assert_eq!(panic.downcast_ref::<&str>(), Some(&"bad input"));
    }
}
