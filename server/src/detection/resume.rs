//! The resume decision: where a new stream's session continues from (the stored snapshot, the
//! session this process holds, or a fresh start), given what the stream asked for and what was
//! found, and what the stream is told about it; also whether a batch sent without a stream
//! continues the held session.
//!
//! Pure: it must not take locks, read the store, restore detectors or queue anything. The session
//! manager gathers the inputs ([`Start`], the stored copy) and carries the decision out.

use spoofwatch_proto::wire::ModelName;

use super::handoff::SnapshotRefused;
use crate::store::SnapshotRow;

/// The session this process holds for a vehicle, as a new stream or batch finds it.
#[derive(Clone, Debug)]
pub struct Held {
    /// The model it runs.
    pub model: ModelName,
    /// How far it got.
    pub progress: Progress,
}

/// How far a session got, by the vehicle's own clock and sequence numbers: what decides which of
/// two copies of a session is the newer, whatever the servers' wall clocks say.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Progress {
    /// Its last sample's time (`None`: no sample yet).
    pub last_timestamp_s: Option<f64>,
    pub last_seq: u64,
    pub samples: u64,
}

impl Progress {
    /// Whether this copy got further than `other`: a later last sample, or the same one with a
    /// later seq or more samples.
    pub fn is_ahead_of(&self, other: &Progress) -> bool {
        let time = |p: &Progress| p.last_timestamp_s.unwrap_or(f64::NEG_INFINITY);
        match time(self).total_cmp(&time(other)) {
            std::cmp::Ordering::Greater => true,
            std::cmp::Ordering::Less => false,
            std::cmp::Ordering::Equal => {
                (self.last_seq, self.samples) > (other.last_seq, other.samples)
            }
        }
    }
}

/// A new stream or batch for a vehicle.
#[derive(Clone, Debug)]
pub struct Start {
    /// The model it runs (resolved: the active one when it named none).
    pub model: ModelName,
    /// It asked for a fresh session.
    pub reset: bool,
    /// The session this process holds for the vehicle, if any.
    pub held: Option<Held>,
}

/// Where a stream's session continues from.
#[derive(Debug, PartialEq)]
pub enum Origin {
    /// The stored snapshot, to be restored (it may still be refused, see [`Start::afresh`]).
    Snapshot(SnapshotRow),
    /// The session this process holds, as it is.
    Memory,
    /// A fresh session; why the stored copy was not used, if one was found and refused.
    Fresh(Option<SnapshotRefused>),
    /// None yet: the store could not be read (the reason), the fault may pass, and nothing held
    /// goes on. The stream is refused, to be retried, rather than start afresh behind a snapshot
    /// nobody could see.
    Unreadable(String),
}

/// What a stream is told about where its session continues from.
#[derive(Debug, PartialEq)]
pub struct Resumption {
    pub resumed: bool,
    pub from_snapshot: bool,
    /// The model the session ran before it started afresh under another.
    pub replaced_model: Option<ModelName>,
    /// Why the vehicle's stored snapshot was not used.
    pub snapshot_refused: Option<SnapshotRefused>,
}

impl Resumption {
    /// Continued from the stored snapshot.
    pub fn from_snapshot() -> Self {
        Self {
            resumed: true,
            from_snapshot: true,
            replaced_model: None,
            snapshot_refused: None,
        }
    }

    /// Continued from this process's memory.
    pub fn in_memory() -> Self {
        Self {
            resumed: true,
            from_snapshot: false,
            replaced_model: None,
            snapshot_refused: None,
        }
    }
}

impl Start {
    /// Whether the held session goes on as it is: there is one, no reset, and it runs the model.
    pub fn held_continues(&self) -> bool {
        !self.reset
            && self
                .held
                .as_ref()
                .is_some_and(|held| held.model == self.model)
    }

    /// Whether a stored copy written by `writer` that got to `progress` is newer than the held
    /// session (with none held, any stored copy is): only a copy another process wrote that got
    /// further. Replicas' wall clocks are never compared: they may disagree by any amount.
    fn stored_is_newer(&self, writer: &str, progress: &Progress, this_writer: &str) -> bool {
        self.held
            .as_ref()
            .is_none_or(|held| writer != this_writer && progress.is_ahead_of(&held.progress))
    }

    /// Where the session continues from, given the vehicle's stored copy and how far it got
    /// (`Ok(None)`: none; a reset reads none) and this process's snapshot writer id. An unreadable
    /// store does not stop a held session from going on; it stops any other start.
    pub fn origin(
        &self,
        stored: Result<Option<(SnapshotRow, Progress)>, SnapshotRefused>,
        this_writer: &str,
    ) -> Origin {
        if self.reset {
            return Origin::Fresh(None);
        }
        match stored {
            Ok(Some((row, progress)))
                if self.stored_is_newer(&row.writer, &progress, this_writer) =>
            {
                Origin::Snapshot(row)
            }
            Err(SnapshotRefused::Unreadable { why, retry: true }) if !self.held_continues() => {
                Origin::Unreadable(why)
            }
            Err(refused) if !self.held_continues() => Origin::Fresh(Some(refused)),
            _ if self.held_continues() => Origin::Memory,
            _ => Origin::Fresh(None),
        }
    }

    /// What the stream is told when its session starts afresh; `refused` says why the stored copy
    /// was not used. The replaced model is the held session's, when it ran another; else that of a
    /// snapshot refused for its model.
    pub fn afresh(&self, refused: Option<SnapshotRefused>) -> Resumption {
        let held_model = self
            .held
            .as_ref()
            .map(|held| &held.model)
            .filter(|model| **model != self.model);
        let replaced_model = match (held_model, &refused) {
            (Some(model), _) => Some(model.clone()),
            (None, Some(SnapshotRefused::Model { snapshot, .. })) => {
                ModelName::parse(snapshot).ok()
            }
            (None, _) => None,
        };
        Resumption {
            resumed: false,
            from_snapshot: false,
            replaced_model,
            snapshot_refused: refused,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const THIS: &str = "1";
    const OTHER: &str = "2";

    fn model(id: &str) -> ModelName {
        ModelName::from_id(id)
    }

    /// A session whose last sample came at `t` s.
    fn at(t: i64) -> Progress {
        Progress {
            last_timestamp_s: Some(t as f64),
            last_seq: 3,
            samples: 10,
        }
    }

    fn start(reset: bool, held: Option<(&str, i64)>) -> Start {
        Start {
            model: model("a"),
            reset,
            held: held.map(|(id, t)| Held {
                model: model(id),
                progress: at(t),
            }),
        }
    }

    /// A stored copy by `writer` whose last sample came at `t` s (written, by its own clock, an
    /// hour before anything held here).
    fn row(writer: &str, t: i64) -> (SnapshotRow, Progress) {
        (stored_row(writer), at(t))
    }

    fn stored_row(writer: &str) -> SnapshotRow {
        SnapshotRow {
            model_id: "a".to_string(),
            last_seq: 3,
            writer: writer.to_string(),
            updated_at_ms: -3_600_000,
            ..SnapshotRow::opaque("car-1", 10)
        }
    }

    /// The store could not be read; the vehicle may wait for it.
    fn unreadable() -> SnapshotRefused {
        SnapshotRefused::Unreadable {
            why: "down".to_string(),
            retry: true,
        }
    }

    /// The store could not be read and waiting will not help (or the vehicle waited long enough).
    fn lost() -> SnapshotRefused {
        SnapshotRefused::Unreadable {
            why: "lost".to_string(),
            retry: false,
        }
    }

    #[test]
    fn the_held_session_continues_only_unreset_on_its_model() {
        assert!(start(false, Some(("a", 0))).held_continues());
        assert!(!start(true, Some(("a", 0))).held_continues());
        assert!(!start(false, Some(("b", 0))).held_continues());
        assert!(!start(false, None).held_continues());
    }

    #[test]
    fn a_reset_starts_afresh_whatever_was_found() {
        let reset = start(true, Some(("a", 0)));
        assert_eq!(reset.origin(Ok(None), THIS), Origin::Fresh(None));
        assert_eq!(
            reset.origin(Ok(Some(row(OTHER, 100))), THIS),
            Origin::Fresh(None)
        );
        assert_eq!(reset.origin(Err(unreadable()), THIS), Origin::Fresh(None));
    }

    #[test]
    fn with_nothing_held_any_stored_copy_is_restored() {
        let new = start(false, None);
        assert_eq!(
            new.origin(Ok(Some(row(OTHER, 5))), THIS),
            Origin::Snapshot(stored_row(OTHER))
        );
        // Also this process's own copy (e.g. of a session it evicted).
        assert_eq!(
            new.origin(Ok(Some(row(THIS, 5))), THIS),
            Origin::Snapshot(stored_row(THIS))
        );
        assert_eq!(new.origin(Ok(None), THIS), Origin::Fresh(None));
        // A copy that may exist but cannot be read: not yet, rather than afresh.
        assert_eq!(
            new.origin(Err(unreadable()), THIS),
            Origin::Unreadable("down".to_string())
        );
        // A store that will not answer soon: afresh, saying why.
        assert_eq!(new.origin(Err(lost()), THIS), Origin::Fresh(Some(lost())));
        // A copy read but refused (corrupt, another schema): afresh, saying why.
        let corrupt = SnapshotRefused::Corrupt("truncated".to_string());
        assert_eq!(
            new.origin(Err(corrupt.clone()), THIS),
            Origin::Fresh(Some(corrupt))
        );
    }

    #[test]
    fn progress_is_the_vehicle_clock_then_seq_then_samples() {
        let base = at(10);
        assert!(at(11).is_ahead_of(&base));
        assert!(!at(9).is_ahead_of(&base));
        assert!(!base.is_ahead_of(&base));
        let later_seq = Progress {
            last_seq: 4,
            ..base
        };
        assert!(later_seq.is_ahead_of(&base));
        assert!(
            base.is_ahead_of(&Progress::default()),
            "any sample beats none"
        );
    }

    #[test]
    fn a_held_session_yields_only_to_a_newer_copy_from_another_process() {
        let held = start(false, Some(("a", 100)));
        assert_eq!(
            held.origin(Ok(Some(row(OTHER, 101))), THIS),
            Origin::Snapshot(stored_row(OTHER))
        );
        assert_eq!(held.origin(Ok(Some(row(OTHER, 100))), THIS), Origin::Memory);
        assert_eq!(held.origin(Ok(Some(row(OTHER, 99))), THIS), Origin::Memory);
        assert_eq!(held.origin(Ok(Some(row(THIS, 500))), THIS), Origin::Memory);
        assert_eq!(held.origin(Ok(None), THIS), Origin::Memory);
        // An unreadable store does not stop it.
        assert_eq!(held.origin(Err(unreadable()), THIS), Origin::Memory);
        assert_eq!(held.origin(Err(lost()), THIS), Origin::Memory);
    }

    #[test]
    fn a_held_session_on_another_model_starts_afresh_unless_a_newer_copy_exists() {
        let other_model = start(false, Some(("b", 100)));
        assert_eq!(
            other_model.origin(Ok(Some(row(OTHER, 101))), THIS),
            Origin::Snapshot(stored_row(OTHER))
        );
        assert_eq!(
            other_model.origin(Ok(Some(row(OTHER, 99))), THIS),
            Origin::Fresh(None)
        );
        assert_eq!(other_model.origin(Ok(None), THIS), Origin::Fresh(None));
        // A newer copy under the new model may exist on another replica: not yet.
        assert_eq!(
            other_model.origin(Err(unreadable()), THIS),
            Origin::Unreadable("down".to_string())
        );
    }

    #[test]
    fn resumptions_say_where_the_session_came_from() {
        let snapshot = Resumption::from_snapshot();
        assert!(snapshot.resumed && snapshot.from_snapshot);
        let memory = Resumption::in_memory();
        assert!(memory.resumed && !memory.from_snapshot);
        assert_eq!(
            (snapshot.replaced_model, snapshot.snapshot_refused),
            (None, None)
        );
        assert_eq!(
            (memory.replaced_model, memory.snapshot_refused),
            (None, None)
        );
    }

    #[test]
    fn a_fresh_start_names_the_model_it_replaced() {
        let refused_model = SnapshotRefused::Model {
            snapshot: "c".to_string(),
            session: "a".to_string(),
        };
        // Nothing held, nothing refused.
        assert_eq!(
            start(false, None).afresh(None),
            Resumption {
                resumed: false,
                from_snapshot: false,
                replaced_model: None,
                snapshot_refused: None,
            }
        );
        // The held session ran another model: that one, even if a snapshot named a third.
        assert_eq!(
            start(false, Some(("b", 0)))
                .afresh(Some(refused_model.clone()))
                .replaced_model,
            Some(model("b"))
        );
        // The held session ran this model: the refused snapshot's model.
        let fresh = start(false, Some(("a", 0))).afresh(Some(refused_model.clone()));
        assert_eq!(fresh.replaced_model, Some(model("c")));
        assert_eq!(fresh.snapshot_refused, Some(refused_model));
        // A snapshot model that is no model name, or a refusal for another reason: none.
        let unnamed = SnapshotRefused::Model {
            snapshot: "no/name".to_string(),
            session: "a".to_string(),
        };
        assert_eq!(
            start(false, None).afresh(Some(unnamed)).replaced_model,
            None
        );
        let fresh = start(false, None).afresh(Some(unreadable()));
        assert_eq!(fresh.replaced_model, None);
        assert_eq!(fresh.snapshot_refused, Some(unreadable()));
        assert!(!fresh.resumed && !fresh.from_snapshot);
    }
}
