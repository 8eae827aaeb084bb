//! The session table: one slot per vehicle held in memory, the sessions each identity created, and
//! admission within the table's bounds (a full table makes room by evicting the session idle longest
//! without a stream).
//!
//! Owns the map of slots, the per-identity counts, admission, eviction and the limits, and a
//! slot's stream owner. Must not run a detector, snapshot a session or touch the store: a slot that
//! leaves is handed back to the caller, who saves it (`super::persistence`).

use std::collections::HashMap;
use std::sync::atomic::{AtomicI64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, PoisonError};
use std::time::Duration;

use spoofwatch_proto::wire::VehicleId;
use tokio_util::sync::CancellationToken;

use super::error::SessionError;
use super::state::SessionState;
use crate::models::LoadedModel;
use crate::store::now_unix_ms;
use crate::telemetry;

/// Bounds on the in-memory session table.
#[derive(Clone, Copy, Debug)]
pub struct SessionLimits {
    pub max_sessions: usize,
    /// Most sessions one identity (a token or certificate) may create.
    pub max_per_identity: usize,
    /// A session with no stream attached is evicted after this long without activity.
    pub idle: Duration,
    /// Most samples in one batch.
    pub max_batch_samples: usize,
}

#[derive(Debug)]
struct StreamOwner {
    id: u64,
    evicted: CancellationToken,
}

/// One vehicle's session.
#[derive(Debug)]
pub struct SessionSlot {
    pub(super) vehicle_id: VehicleId,
    /// The identity whose call created it (it counts against that identity's quota).
    created_by: Arc<str>,
    pub(super) state: tokio::sync::Mutex<SessionState>,
    owner: Mutex<Option<StreamOwner>>,
    last_activity_ms: AtomicI64,
    /// Cancelled when the session's model is deleted: the session is gone and its stream ends.
    pub model_deleted: CancellationToken,
}

impl SessionSlot {
    pub(super) fn touch(&self) {
        self.last_activity_ms
            .store(now_unix_ms(), Ordering::Relaxed);
    }

    pub(super) fn connected(&self) -> bool {
        self.owner.lock().map(|o| o.is_some()).unwrap_or(false)
    }

    pub(super) fn last_activity_ms(&self) -> i64 {
        self.last_activity_ms.load(Ordering::Relaxed)
    }

    /// Stream `id` owns the session from now on; whether an older stream held it (that stream is
    /// told to end through its `evicted` token).
    pub(super) fn take_over(&self, id: u64, evicted: CancellationToken) -> bool {
        if let Ok(mut owner) = self.owner.lock()
            && let Some(previous) = owner.replace(StreamOwner { id, evicted })
        {
            previous.evicted.cancel();
            return true;
        }
        false
    }

    /// Stream `id` lets go of the session; whether it still held it.
    pub(super) fn release(&self, id: u64) -> bool {
        match self.owner.lock() {
            Ok(mut owner) if owner.as_ref().is_some_and(|o| o.id == id) => {
                *owner = None;
                true
            }
            _ => false,
        }
    }
}

/// A session found or made for a vehicle: `existed` before; `made_room`, the session evicted to
/// make room for it (to be snapshotted).
pub(super) struct Admitted {
    pub(super) slot: Arc<SessionSlot>,
    pub(super) existed: bool,
    pub(super) made_room: Option<Arc<SessionSlot>>,
}

/// The table of sessions held in memory.
#[derive(Debug)]
pub(super) struct SessionTable {
    slots: Mutex<HashMap<VehicleId, Arc<SessionSlot>>>,
    /// Sessions in the table by the identity that created them (the quota's count).
    per_identity: Mutex<HashMap<Arc<str>, usize>>,
    limits: SessionLimits,
}

impl SessionTable {
    pub(super) fn new(limits: SessionLimits) -> Self {
        Self {
            slots: Mutex::new(HashMap::new()),
            per_identity: Mutex::new(HashMap::new()),
            limits,
        }
    }

    /// The limits the table was made with.
    pub(super) fn limits(&self) -> SessionLimits {
        self.limits
    }

    fn slots(&self) -> MutexGuard<'_, HashMap<VehicleId, Arc<SessionSlot>>> {
        // A panic while holding this lock cannot leave the map inconsistent (single inserts/removes).
        self.slots.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn per_identity(&self) -> MutexGuard<'_, HashMap<Arc<str>, usize>> {
        self.per_identity
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
    }

    pub(super) fn lookup(&self, vehicle_id: &VehicleId) -> Option<Arc<SessionSlot>> {
        self.slots().get(vehicle_id).cloned()
    }

    /// Whether the table holds the session of `vehicle` (a stored vehicle id).
    pub(super) fn holds(&self, vehicle: &str) -> bool {
        VehicleId::parse(vehicle).is_ok_and(|id| self.slots().contains_key(&id))
    }

    /// Every session held.
    pub(super) fn all(&self) -> Vec<Arc<SessionSlot>> {
        self.slots().values().cloned().collect()
    }

    /// Sessions held, and how many of them have a live stream (one pass under the table's lock).
    pub(super) fn counts(&self) -> (usize, usize) {
        let slots = self.slots();
        let connected = slots.values().filter(|s| s.connected()).count();
        (slots.len(), connected)
    }

    /// Up to `size` sessions ordered by vehicle id, after `page_token` (a vehicle id, or empty),
    /// and whether more follow.
    pub(super) fn page(&self, size: usize, page_token: &str) -> (Vec<Arc<SessionSlot>>, bool) {
        let mut slots: Vec<Arc<SessionSlot>> = self
            .slots()
            .values()
            .filter(|s| page_token.is_empty() || s.vehicle_id.as_str() > page_token)
            .cloned()
            .collect();
        slots.sort_by(|a, b| a.vehicle_id.cmp(&b.vehicle_id));
        let more = slots.len() > size;
        slots.truncate(size);
        (slots, more)
    }

    /// Finds or creates the slot of a vehicle (on `model`), within the caller's quota; a full
    /// table makes room by evicting the session idle longest without a stream (returned, to be
    /// snapshotted).
    pub(super) fn admit(
        &self,
        vehicle_id: &VehicleId,
        model: &LoadedModel,
        identity: &Arc<str>,
    ) -> Result<Admitted, SessionError> {
        let mut slots = self.slots();
        if let Some(slot) = slots.get(vehicle_id) {
            return Ok(Admitted {
                slot: Arc::clone(slot),
                existed: true,
                made_room: None,
            });
        }
        let mut per_identity = self.per_identity();
        let created = per_identity.get(identity).copied().unwrap_or(0);
        if created >= self.limits.max_per_identity {
            telemetry::session_refused();
            return Err(SessionError::Quota {
                identity: identity.to_string(),
                limit: self.limits.max_per_identity,
            });
        }
        let mut evicted = None;
        if slots.len() >= self.limits.max_sessions {
            // Under pressure the session idle longest without a stream makes room: it leaves
            // memory, not the fleet (the caller snapshots it, as at idle eviction).
            let oldest = slots
                .values()
                .filter(|slot| !slot.connected())
                .min_by_key(|slot| slot.last_activity_ms())
                .map(|slot| slot.vehicle_id.clone());
            let Some(oldest) = oldest.and_then(|id| slots.remove(&id)) else {
                telemetry::session_refused();
                return Err(SessionError::Full(self.limits.max_sessions));
            };
            forget_creator(&mut per_identity, &oldest.created_by);
            telemetry::sessions_evicted(1);
            evicted = Some(oldest);
        }
        *per_identity.entry(Arc::clone(identity)).or_insert(0) += 1;
        let slot = Arc::new(SessionSlot {
            created_by: Arc::clone(identity),
            vehicle_id: vehicle_id.clone(),
            state: tokio::sync::Mutex::new(SessionState::new(model.clone())),
            owner: Mutex::new(None),
            last_activity_ms: AtomicI64::new(now_unix_ms()),
            model_deleted: CancellationToken::new(),
        });
        slots.insert(vehicle_id.clone(), Arc::clone(&slot));
        Ok(Admitted {
            slot,
            existed: false,
            made_room: evicted,
        })
    }

    /// Takes `slot` out of the table if the table still holds that very slot (not a newer one of
    /// the vehicle); one session fewer for the identity that created it. Whether it was removed.
    pub(super) fn remove(&self, slot: &Arc<SessionSlot>) -> bool {
        let removed = {
            let mut table = self.slots();
            let ours = table
                .get(&slot.vehicle_id)
                .is_some_and(|held| Arc::ptr_eq(held, slot));
            ours && table.remove(&slot.vehicle_id).is_some()
        };
        if removed {
            forget_creator(&mut self.per_identity(), &slot.created_by);
        }
        removed
    }

    /// Takes out the sessions without a stream that were idle longer than the limit (counted as
    /// evicted), to be snapshotted by the caller.
    pub(super) fn take_idle(&self) -> Vec<Arc<SessionSlot>> {
        let cutoff = now_unix_ms() - self.limits.idle.as_millis() as i64;
        let idle: Vec<Arc<SessionSlot>> = {
            let mut slots = self.slots();
            let ids: Vec<VehicleId> = slots
                .values()
                .filter(|s| !s.connected() && s.last_activity_ms() < cutoff)
                .map(|s| s.vehicle_id.clone())
                .collect();
            ids.iter().filter_map(|id| slots.remove(id)).collect()
        };
        let mut per_identity = self.per_identity();
        for slot in &idle {
            forget_creator(&mut per_identity, &slot.created_by);
        }
        drop(per_identity);
        telemetry::sessions_evicted(idle.len());
        idle
    }
}

/// One session fewer for `identity`.
fn forget_creator(per_identity: &mut HashMap<Arc<str>, usize>, identity: &Arc<str>) {
    if let Some(count) = per_identity.get_mut(identity) {
        *count = count.saturating_sub(1);
        if *count == 0 {
            per_identity.remove(identity);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::super::state::test_model;
    use super::*;

    fn model() -> LoadedModel {
        test_model("m")
    }

    fn limits(max_sessions: usize, max_per_identity: usize) -> SessionLimits {
        SessionLimits {
            max_sessions,
            max_per_identity,
            idle: Duration::ZERO,
            max_batch_samples: 10,
        }
    }

    fn vehicle(id: &str) -> VehicleId {
        VehicleId::parse(id).expect("a vehicle id")
    }

    #[test]
    fn a_vehicle_is_admitted_once_and_an_identity_within_its_quota() {
        let table = SessionTable::new(limits(10, 1));
        let (alice, bob): (Arc<str>, Arc<str>) = (Arc::from("alice"), Arc::from("bob"));
        let first = table
            .admit(&vehicle("car-1"), &model(), &alice)
            .expect("admitted");
        assert!(!first.existed && first.made_room.is_none());
        let again = table
            .admit(&vehicle("car-1"), &model(), &alice)
            .expect("found");
        assert!(again.existed && Arc::ptr_eq(&again.slot, &first.slot));
        let refused = table.admit(&vehicle("car-2"), &model(), &alice);
        assert!(
            matches!(&refused, Err(SessionError::Quota { identity, limit: 1 }) if identity == "alice"),
            "{:?}",
            refused.err()
        );
        table
            .admit(&vehicle("car-2"), &model(), &bob)
            .expect("bob's own quota");
        assert_eq!(table.counts(), (2, 0));
        assert!(table.holds("car-2") && !table.holds("car-3") && !table.holds("not a vehicle!"));
    }

    #[test]
    fn a_full_table_evicts_the_session_idle_longest_without_a_stream() {
        let table = SessionTable::new(limits(2, 10));
        let caller: Arc<str> = Arc::from("fleet");
        let old = table
            .admit(&vehicle("car-1"), &model(), &caller)
            .expect("admitted")
            .slot;
        let streaming = table
            .admit(&vehicle("car-2"), &model(), &caller)
            .expect("admitted")
            .slot;
        old.last_activity_ms.store(1, Ordering::Relaxed);
        streaming.last_activity_ms.store(0, Ordering::Relaxed);
        assert!(!streaming.take_over(1, CancellationToken::new()));
        let admitted = table
            .admit(&vehicle("car-3"), &model(), &caller)
            .expect("room made");
        let evicted = admitted.made_room.expect("an eviction");
        assert!(Arc::ptr_eq(&evicted, &old), "the streaming session stays");
        assert_eq!(table.counts(), (2, 1));
        // With every session streaming there is no room to make.
        assert!(!admitted.slot.take_over(2, CancellationToken::new()));
        let full = table.admit(&vehicle("car-4"), &model(), &caller);
        assert!(
            matches!(full, Err(SessionError::Full(2))),
            "{:?}",
            full.err()
        );
    }

    #[test]
    fn a_newer_stream_takes_over_and_only_the_owner_releases() {
        let table = SessionTable::new(limits(2, 2));
        let slot = table
            .admit(&vehicle("car-1"), &model(), &Arc::from("a"))
            .expect("admitted")
            .slot;
        let first = CancellationToken::new();
        assert!(!slot.take_over(1, first.clone()));
        assert!(slot.take_over(2, CancellationToken::new()));
        assert!(first.is_cancelled(), "the older stream is told to end");
        assert!(!slot.release(1) && slot.connected());
        assert!(slot.release(2) && !slot.connected());
    }

    #[test]
    fn a_removed_or_idle_session_frees_its_creator_s_quota() {
        let table = SessionTable::new(limits(10, 1));
        let caller: Arc<str> = Arc::from("a");
        let slot = table
            .admit(&vehicle("car-1"), &model(), &caller)
            .expect("admitted")
            .slot;
        assert!(table.remove(&slot));
        assert!(!table.remove(&slot), "a slot leaves once");
        let slot = table
            .admit(&vehicle("car-2"), &model(), &caller)
            .expect("quota freed")
            .slot;
        slot.last_activity_ms.store(0, Ordering::Relaxed);
        let idle = table.take_idle();
        assert_eq!(idle.len(), 1);
        assert_eq!(table.counts(), (0, 0));
        table
            .admit(&vehicle("car-3"), &model(), &caller)
            .expect("quota freed again");
    }
}
