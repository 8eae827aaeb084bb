//! The shadow's worker: one OS thread, off the async runtime and at idle CPU priority
//! (`super::priority`), that takes queued batches, scores them with the candidate within its CPU
//! budget, follows each vehicle's would-be alarm and hands what
//! to store to the writer (`super::writer`) in order.
//!
//! A vehicle's shadow state starts afresh, and says why, when its work was shed (a gapped sequence
//! is never scored as if whole), when its live session's time line went back (a reset), and after
//! it sat idle (it was let go). Its first state on this process is a start too: after a restart or
//! a hand-off from another replica, the state is rebuilt from the next samples. Every start is
//! stored (`Write::VehicleStarted`), so the shadow reports how many restarts its vehicles had.

use std::collections::HashMap;
use std::sync::Arc;
use std::time::{Duration, Instant};

use spoofwatch_core::detector::Detector;
use tokio::sync::mpsc;

use super::Running;
use super::queue::{Budget, Job, ShadowQueue, Work};
use super::tally::Tally;
use super::vehicle::{Change, Episode, ShadowSignal, VehicleShadow};
use super::{SharedTally, metrics};

/// The worker's share of one core, and the scoring time it may save up.
pub const CPU_SHARE: f64 = 0.5;
pub const CPU_BURST: Duration = Duration::from_millis(200);
/// How often idle vehicle states are looked for.
const IDLE_CHECK: Duration = Duration::from_secs(5);

/// What the writer stores, in the order the worker decided it.
#[derive(Debug)]
pub enum Write {
    VehicleStarted {
        shadow_id: i64,
        vehicle_id: String,
    },
    Onset {
        shadow_id: i64,
        model_id: String,
        vehicle_id: String,
        episode: Episode,
    },
    Escalated {
        shadow_id: i64,
        vehicle_id: String,
        onset_timestamp_s: f64,
        timestamp_s: f64,
    },
    Ended {
        shadow_id: i64,
        vehicle_id: String,
        episode: Episode,
        reason: &'static str,
    },
}

/// Whether `job` starts before the last sample its vehicle's state scored: the live session's time
/// line went back (a reset), so the state cannot continue.
fn went_back(job: &Job, state: &VehicleShadow) -> bool {
    match (job.samples.first(), state.last_timestamp_s) {
        (Some(first), Some(last)) => first.timestamp_s < last,
        _ => false,
    }
}

/// What the worker needs.
pub struct Worker {
    pub queue: Arc<ShadowQueue>,
    /// The running shadow (its candidate), as the service last saw it.
    pub running: Arc<std::sync::RwLock<Option<Arc<Running>>>>,
    pub tally: Arc<SharedTally>,
    pub writes: mpsc::Sender<Write>,
    /// Vehicle states not scored for this long are let go.
    pub idle: Duration,
}

/// The states of the vehicles of one shadow.
struct Vehicles {
    shadow: Arc<Running>,
    states: HashMap<String, VehicleShadow>,
}

impl Worker {
    /// Runs until the queue is closed and empty.
    pub fn run(self) {
        super::priority::lower_this_thread();
        let mut budget = Budget::new(CPU_SHARE, CPU_BURST, Instant::now());
        let mut vehicles: Option<Vehicles> = None;
        let mut idle_checked = Instant::now();
        loop {
            let wait = budget.wait(Instant::now());
            if !wait.is_zero() {
                std::thread::sleep(wait);
            }
            match self.queue.next(IDLE_CHECK) {
                Some(Work::Batch(job)) => {
                    let started = Instant::now();
                    self.score(&mut vehicles, job);
                    let spent = started.elapsed();
                    budget.charge(spent);
                    let hours = self.tally.add_scoring_time(spent);
                    crate::telemetry::shadow_batch(spent, self.queue.samples(), hours);
                }
                // The stop ended the open would-be alarms in the store.
                Some(Work::Stop { shadow_id })
                    if vehicles.as_ref().is_some_and(|v| v.shadow.id == shadow_id) =>
                {
                    vehicles = None;
                }
                Some(Work::Stop { .. }) => {}
                None if self.queue.is_closed() => return,
                None => {}
            }
            if idle_checked.elapsed() >= IDLE_CHECK {
                idle_checked = Instant::now();
                if let Some(vehicles) = vehicles.as_mut() {
                    self.let_go_idle(vehicles);
                }
            }
        }
    }

    fn send(&self, write: Write) {
        // The writer stops last, at shutdown; a write it can no longer take is lost with the
        // process, and the vehicle's next start ends what was left open.
        let _ = self.writes.blocking_send(write);
    }

    /// Scores one batch of the running shadow (a batch of a shadow that no longer runs is
    /// dropped).
    fn score(&self, vehicles: &mut Option<Vehicles>, job: Job) {
        let running = self
            .running
            .read()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .clone();
        let Some(running) = running.filter(|r| r.id == job.shadow_id) else {
            return;
        };
        if vehicles.as_ref().is_none_or(|v| v.shadow.id != running.id) {
            *vehicles = Some(Vehicles {
                shadow: Arc::clone(&running),
                states: HashMap::new(),
            });
        }
        let Some(vehicles) = vehicles.as_mut() else {
            return;
        };
        let mut delta = Tally::default();
        let now = Instant::now();
        let restart = match vehicles.states.get(&job.vehicle_id) {
            None => Some(("first", None)),
            Some(_) if job.after_gap => Some(("shed", Some("shed"))),
            Some(state) if went_back(&job, state) => Some(("reset", Some("reset"))),
            Some(_) => None,
        };
        if let Some((reason, ended_as)) = restart {
            if let (Some(ended_as), Some(old)) = (ended_as, vehicles.states.remove(&job.vehicle_id))
            {
                self.end_open(&running, &job.vehicle_id, old, ended_as);
            }
            match reason {
                "shed" => delta.starts_after_shed += 1,
                "reset" => delta.starts_after_reset += 1,
                _ => {}
            }
            metrics::vehicle_started(reason);
            let detector = Detector::new(Arc::clone(&running.model.artifact));
            vehicles
                .states
                .insert(job.vehicle_id.clone(), VehicleShadow::new(detector, now));
            self.send(Write::VehicleStarted {
                shadow_id: running.id,
                vehicle_id: job.vehicle_id.clone(),
            });
        }
        let Some(state) = vehicles.states.get_mut(&job.vehicle_id) else {
            return;
        };
        state.seen = now;
        let mut changes = Vec::new();
        for (sample, live) in job.samples.iter().zip(&job.live) {
            let decision = state
                .detector
                .step_with_prior(sample, false, live.in_incident_area);
            let signal = ShadowSignal::of(&decision);
            if let Some(change) = state.follow(sample.timestamp_s, signal, *live, &mut delta) {
                changes.push(change);
            }
        }
        metrics::counted(&delta);
        self.tally.add(running.id, &delta);
        for change in changes {
            self.send(match change {
                Change::Onset(episode) => Write::Onset {
                    shadow_id: running.id,
                    model_id: running.model.name.id().to_string(),
                    vehicle_id: job.vehicle_id.clone(),
                    episode,
                },
                Change::Escalated {
                    onset_timestamp_s,
                    timestamp_s,
                } => Write::Escalated {
                    shadow_id: running.id,
                    vehicle_id: job.vehicle_id.clone(),
                    onset_timestamp_s,
                    timestamp_s,
                },
                Change::Ended(episode) => Write::Ended {
                    shadow_id: running.id,
                    vehicle_id: job.vehicle_id.clone(),
                    episode,
                    reason: "cleared",
                },
            });
        }
    }

    /// Ends the would-be alarm a state let go of holds open, as `reason`.
    fn end_open(
        &self,
        running: &Running,
        vehicle_id: &str,
        state: VehicleShadow,
        reason: &'static str,
    ) {
        if let Some(episode) = state.episode {
            self.send(Write::Ended {
                shadow_id: running.id,
                vehicle_id: vehicle_id.to_string(),
                episode,
                reason,
            });
        }
    }

    /// Lets go of the vehicle states idle longer than the limit (a vehicle that returns starts
    /// afresh; one that went to another replica started there).
    fn let_go_idle(&self, vehicles: &mut Vehicles) {
        let idle: Vec<String> = vehicles
            .states
            .iter()
            .filter(|(_, state)| state.seen.elapsed() >= self.idle)
            .map(|(id, _)| id.clone())
            .collect();
        if idle.is_empty() {
            return;
        }
        let mut delta = Tally::default();
        for vehicle_id in idle {
            if let Some(state) = vehicles.states.remove(&vehicle_id) {
                self.end_open(&vehicles.shadow, &vehicle_id, state, "idle");
                delta.starts_after_idle += 1;
                metrics::vehicle_started("idle");
            }
        }
        self.tally.add(vehicles.shadow.id, &delta);
    }
}
