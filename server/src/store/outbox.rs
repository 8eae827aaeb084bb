//! The joint write of the session outbox (`crate::outbox`): alarm events and session snapshots in
//! one transaction, so that a stored alarm event is never newer than the stored snapshot of its
//! session, and a session continued from that snapshot never emits it again.
//!
//! It owns only the transaction; each table's statements stay with their table (`super::alarms`,
//! `super::snapshots`), which must not import each other for it.

use std::borrow::Borrow;

use super::alarms::{AlarmEvent, AlarmEventKind, apply_event};
use super::snapshots::{SnapshotRow, upsert_snapshot};
use super::{Store, StoreError};

impl Store {
    /// Applies `events` in order in one transaction, all or nothing: an onset inserts its alarm, an
    /// end closes it, and each is appended to the event log. Idempotent, so a batch whose outcome
    /// is unknown can be retried: an onset or log entry already stored is skipped, and an end only
    /// touches its alarm (and is only logged) while the alarm is open or when it moves the alarm's
    /// end later (see `apply_event!`).
    ///
    /// [`StoreError::InvalidValue`] (before anything is written) for the values
    /// [`AlarmEvent::validate`] refuses.
    pub async fn write_alarms<E: Borrow<AlarmEvent>>(
        &self,
        events: &[E],
    ) -> Result<(), StoreError> {
        self.write_alarms_and_snapshots(events, &[]).await?;
        Ok(())
    }

    /// [`Store::write_alarms`], then `snapshots` (each its vehicle's latest), in the same
    /// transaction: a stored alarm event is never newer than the stored snapshot of its session,
    /// so a session continued from that snapshot never emits it again.
    ///
    /// Returns the indices of the snapshots not stored because they are copies of a session that
    /// another process replaced, holding open the alarm it ended (see `upsert_snapshot!`): the
    /// caller ends that alarm at the copy's progress.
    pub async fn write_alarms_and_snapshots<E: Borrow<AlarmEvent>>(
        &self,
        events: &[E],
        snapshots: &[SnapshotRow],
    ) -> Result<Vec<usize>, StoreError> {
        for event in events {
            event.borrow().validate()?;
        }
        in_write_tx!(self, |tx| {
            for event in events {
                apply_event!(tx, event.borrow());
            }
            let mut replaced = Vec::new();
            for (index, snapshot) in snapshots.iter().enumerate() {
                if !upsert_snapshot!(tx, snapshot) {
                    replaced.push(index);
                }
            }
            tx.commit().await?;
            Ok(replaced)
        })
    }
}
