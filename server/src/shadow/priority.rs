//! The shadow worker's CPU priority. On Linux the worker thread runs under `SCHED_IDLE`: the
//! kernel gives it a core only when nothing else of normal priority wants that core, so a busy
//! server runs its live replies, health checks and heavy work first, the shadow's queue fills and
//! the shadow sheds (`super::queue`). Its CPU budget (`super::worker::CPU_SHARE`) still holds on an
//! idle machine.
//!
//! Setting the policy can fail (a seccomp profile that refuses `sched_setscheduler`, another
//! operating system). The server then goes on: the worker falls back to the lowest nice value (as
//! heavy work runs), says so once in the log, and `spoofwatch_shadow_worker_idle_priority` reads 0.
//! It owns the calling thread's scheduling, nothing else.

use crate::work::HEAVY_NICE;

/// The priority the calling thread ended up with.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Priority {
    /// `SCHED_IDLE`.
    Idle,
    /// The policy could not be set (why); the thread runs at the lowest nice value, or at the
    /// process's priority if even that failed.
    Fallback(String),
}

/// Puts the calling thread under `SCHED_IDLE` (or the fallback), logs a fallback and sets the
/// gauge.
pub fn lower_this_thread() -> Priority {
    let priority = set_idle();
    match &priority {
        Priority::Idle => {
            tracing::debug!("the shadow's worker runs at idle CPU priority (SCHED_IDLE)");
        }
        Priority::Fallback(reason) => {
            let niced =
                rustix::process::setpriority_process(Some(rustix::thread::gettid()), HEAVY_NICE)
                    .is_ok();
            tracing::warn!(
                reason = %reason,
                niced,
                "the shadow's worker could not be given idle CPU priority (SCHED_IDLE); it runs at the lowest nice value instead (at the process's if `niced` is false), so on a busy server it competes a little with the live replies before it sheds"
            );
        }
    }
    crate::telemetry::shadow_worker_idle_priority(priority == Priority::Idle);
    priority
}

#[cfg(target_os = "linux")]
fn set_idle() -> Priority {
    use thread_priority::ThreadPriority;
    use thread_priority::unix::{
        NormalThreadSchedulePolicy, ThreadSchedulePolicy, set_thread_priority_and_policy,
        thread_native_id, thread_schedule_policy,
    };

    let idle = ThreadSchedulePolicy::Normal(NormalThreadSchedulePolicy::Idle);
    let set = set_thread_priority_and_policy(thread_native_id(), ThreadPriority::Min, idle);
    // The call sets the policy, then the nice value (which SCHED_IDLE ignores); a refused nice
    // value leaves the policy set, so what counts is the policy read back.
    match (thread_schedule_policy(), set) {
        (Ok(policy), _) if policy == idle => Priority::Idle,
        (_, Err(error)) => Priority::Fallback(format!("{error:?}")),
        (Ok(policy), Ok(())) => Priority::Fallback(format!("the policy read back is {policy:?}")),
        (Err(error), Ok(())) => {
            Priority::Fallback(format!("the policy read back failed: {error:?}"))
        }
    }
}

#[cfg(not(target_os = "linux"))]
fn set_idle() -> Priority {
    Priority::Fallback("SCHED_IDLE exists on Linux only".to_string())
}

#[cfg(all(test, target_os = "linux"))]
mod tests {
    use super::*;

    /// The scheduling policy of the calling thread, read from `/proc/thread-self/stat` (field 41;
    /// 5 is SCHED_IDLE, 0 SCHED_OTHER).
    fn this_threads_policy() -> u32 {
        let stat = std::fs::read_to_string("/proc/thread-self/stat").expect("thread stat");
        let after_name = &stat[stat.rfind(')').expect("the name's end") + 2..];
        after_name
            .split(' ')
            .nth(38)
            .and_then(|policy| policy.parse().ok())
            .expect("the policy field")
    }

    #[test]
    fn the_worker_thread_runs_under_sched_idle_and_others_keep_theirs() {
        let before = this_threads_policy();
        let (priority, policy) =
            std::thread::spawn(|| (lower_this_thread(), this_threads_policy()))
                .join()
                .expect("the thread ran");
        assert_eq!(priority, Priority::Idle);
        assert_eq!(policy, 5, "SCHED_IDLE, as the kernel reports it");
        assert_eq!(
            this_threads_policy(),
            before,
            "only the calling thread changed"
        );
    }
}
