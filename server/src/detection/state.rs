//! What one vehicle's session knows, and its snapshot: a fresh state, the state continued from a
//! stored snapshot (refused when it belongs to another model or does not fit the model's
//! detector), and the state as a snapshot again.
//!
//! Pure: it must not lock, queue or store anything (the session manager, `super::sessions`, guards
//! the state and decides when to snapshot it).

use std::sync::Arc;
use std::time::Instant;

use spoofwatch_core::detector::Detector;

use super::episodes::AlarmTrack;
use super::handoff::{SessionSnapshot, SnapshotRefused};
use super::resume::{Held, Progress};
use super::sequence::AppliedSeqs;
use crate::models::LoadedModel;

/// Everything a session knows; guarded by the slot's async mutex (batches of a vehicle serialise).
#[derive(Debug)]
pub(super) struct SessionState {
    pub(super) model: LoadedModel,
    pub(super) detector: Detector,
    pub(super) samples: u64,
    pub(super) trajectories: u32,
    /// The batch sequence numbers applied (the last one is `last_seq`).
    pub(super) seqs: AppliedSeqs,
    pub(super) last_timestamp_s: Option<f64>,
    pub(super) alarm: AlarmTrack,
    /// Samples since the last snapshot, and when it was taken.
    pub(super) since_snapshot: u64,
    pub(super) snapshot_taken: Instant,
}

impl SessionState {
    pub(super) fn new(model: LoadedModel) -> Self {
        Self {
            detector: Detector::new(Arc::clone(&model.artifact)),
            model,
            samples: 0,
            trajectories: 0,
            seqs: AppliedSeqs::default(),
            last_timestamp_s: None,
            alarm: AlarmTrack::default(),
            since_snapshot: 0,
            snapshot_taken: Instant::now(),
        }
    }

    /// The session continuing from `snapshot` under `model` (the snapshot's model, checked).
    pub(super) fn restore(
        model: LoadedModel,
        snapshot: SessionSnapshot,
    ) -> Result<Self, SnapshotRefused> {
        if snapshot.model_id != model.name.id() {
            return Err(SnapshotRefused::Model {
                snapshot: snapshot.model_id,
                session: model.name.id().to_string(),
            });
        }
        let detector = Detector::restore(Arc::clone(&model.artifact), snapshot.detector).map_err(
            |reason| SnapshotRefused::Unfit {
                model: model.name.to_string(),
                reason,
            },
        )?;
        Ok(Self {
            detector,
            samples: snapshot.samples,
            trajectories: snapshot.trajectories,
            seqs: AppliedSeqs::resumed(snapshot.last_seq),
            last_timestamp_s: snapshot.last_timestamp_s,
            alarm: AlarmTrack {
                active: snapshot.alarm_active,
                raised: snapshot.alarms_raised,
                open: snapshot.open_alarm,
            },
            ..Self::new(model)
        })
    }

    /// This session as a snapshot.
    pub(super) fn snapshot(&self) -> SessionSnapshot {
        SessionSnapshot {
            model_id: self.model.name.id().to_string(),
            samples: self.samples,
            trajectories: self.trajectories,
            last_seq: self.seqs.last(),
            last_timestamp_s: self.last_timestamp_s,
            alarm_active: self.alarm.active,
            alarms_raised: self.alarm.raised,
            open_alarm: self.alarm.open.clone(),
            detector: self.detector.save(),
        }
    }

    /// What a new stream or batch under `model` finds this session to be.
    pub(super) fn held(&self) -> Held {
        Held {
            model: self.model.name.clone(),
            progress: Progress {
                last_timestamp_s: self.last_timestamp_s,
                last_seq: self.seqs.last(),
                samples: self.samples,
            },
        }
    }
}

/// The bundled model under the id `id`, for the detection tests.
#[cfg(test)]
pub(super) fn test_model(id: &str) -> LoadedModel {
    use spoofwatch_core::model::artifact::ModelArtifact;
    use spoofwatch_proto::wire::ModelName;

    use crate::models::registry::BUNDLED_MODEL;

    LoadedModel {
        name: ModelName::from_id(id),
        artifact: Arc::new(ModelArtifact::from_slice(BUNDLED_MODEL).expect("the bundled model")),
    }
}

#[cfg(test)]
mod tests {
    use spoofwatch_core::sample::Sample;
    use spoofwatch_proto::wire::ModelName;

    use super::*;

    fn model(id: &str) -> LoadedModel {
        test_model(id)
    }

    fn sample(t: f64) -> Sample {
        Sample::new(t, 32.2318 + t * 1e-5, -110.9092, 1.1, 0.0)
    }

    #[test]
    fn a_restored_session_is_the_session_that_was_snapshotted() {
        let mut state = SessionState::new(model("m"));
        for t in 0..5 {
            state.detector.step(&sample(f64::from(t)), false);
        }
        state.samples = 5;
        state.trajectories = 1;
        state.seqs.apply(3);
        state.last_timestamp_s = Some(4.0);
        state.alarm.raised = 2;
        let snapshot = state.snapshot();
        let restored = SessionState::restore(model("m"), snapshot.clone()).expect("restores");
        let again = restored.snapshot();
        assert_eq!(again.samples, 5);
        assert_eq!(again.trajectories, 1);
        assert_eq!(again.last_seq, 3);
        assert_eq!(again.last_timestamp_s, Some(4.0));
        assert_eq!(again.alarms_raised, 2);
        assert_eq!(again.model_id, "m");
        // The detector continues exactly where it was.
        let (mut a, mut b) = (state, restored);
        let (da, db) = (
            a.detector.step(&sample(5.0), false),
            b.detector.step(&sample(5.0), false),
        );
        assert_eq!(da.probability.to_bits(), db.probability.to_bits());
        assert_eq!(b.held().model, ModelName::from_id("m"));
    }

    #[test]
    fn a_snapshot_of_another_model_is_refused() {
        let snapshot = SessionState::new(model("old")).snapshot();
        let refused = SessionState::restore(model("new"), snapshot).expect_err("another model");
        assert!(
            matches!(&refused, SnapshotRefused::Model { snapshot, session } if snapshot == "old" && session == "new"),
            "{refused:?}"
        );
    }
}
