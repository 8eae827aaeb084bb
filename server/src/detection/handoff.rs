//! The session snapshot: a vehicle session's complete state as bytes, so that a stream starting on
//! any server process (another replica, or this one after a restart) continues the session exactly.
//!
//! Encoding: `SWSS` magic, the schema version (u16, little-endian), the postcard encoding of a
//! [`SessionSnapshot`] (f64s as their bit patterns, so a continued session is bit-exact), and the
//! first 8 bytes of the SHA-256 of everything before them. A snapshot that fails any of these is
//! refused with a [`SnapshotRefused`] naming why; the session then starts afresh.
//!
//! Only this schema version is read. Every version nests the detector's state, and a change of its
//! shape (a new field anywhere inside it) bumps the version: postcard is positional, so bytes of an
//! older shape would be misread, not refused. A snapshot of another version is refused and its
//! session starts afresh, as after a restart without a snapshot.

use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use spoofwatch_core::detector::{DetectorState, RestoreError};

/// The encoding this server writes, and the only one it reads. Bump it when [`SessionSnapshot`] or
/// anything inside [`DetectorState`] changes shape: other versions are refused (fresh sessions),
/// never misread. Version 9: a held jump keeps the test of the step it arrived with. Version 10:
/// the offset tracker knows whether the last fix repeated the one before it and whether the last row
/// was an outlier. Version 11: it knows how long the track its anchors stand on has lasted. Version
/// 12: the critical test keeps the last sample's offset. Version 13: the offset tracker counts
/// the anchors' placements on a disagreement before trust, and its last evidence says whether they
/// are disputed. Version 14: each anchor keeps the calibration its offset is expressed in and the
/// velocity change behind it.
pub const SNAPSHOT_SCHEMA: u16 = 14;

/// Whether this server reads stored snapshots of schema version `version`.
pub fn reads_schema(version: i64) -> bool {
    version == i64::from(SNAPSHOT_SCHEMA)
}

const MAGIC: &[u8; 4] = b"SWSS";
const HEADER: usize = MAGIC.len() + 2;
const CHECKSUM: usize = 8;

/// An alarm a session holds open (its onset emitted, its end not yet).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct OpenAlarm {
    pub id: i64,
    pub onset_timestamp_s: f64,
    pub onset_at_ms: i64,
    pub peak: f64,
    pub samples: u32,
    /// Sample time of the latest alarming sample: the event's end time (`alarm_events` semantics).
    pub last_timestamp_s: f64,
    /// When it turned critical (the onset's times when it opened critical); `None`: a warning.
    pub escalated: Option<Escalated>,
    /// The credential of the stream that raised it (`alarm_events.credential`), kept by a session
    /// that another stream continues.
    pub credential: Option<String>,
    /// Each vehicle of that credential is its own source (`alarm_events.credential_per_vehicle`).
    pub credential_per_vehicle: bool,
}

/// When an open alarm turned critical: sample time and server wall time (unix ms).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Escalated {
    pub timestamp_s: f64,
    pub at_ms: i64,
}

/// Everything a session carries besides its model.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct SessionSnapshot {
    /// The model id the session ran; it continues only under that model.
    pub model_id: String,
    pub samples: u64,
    pub trajectories: u32,
    pub last_seq: u64,
    pub last_timestamp_s: Option<f64>,
    pub alarm_active: bool,
    pub alarms_raised: u64,
    pub open_alarm: Option<OpenAlarm>,
    pub detector: DetectorState,
}

/// Why a stored snapshot was not used (the session started afresh).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SnapshotRefused {
    #[error("the stored session snapshot is corrupt ({0})")]
    Corrupt(String),
    #[error(
        "the stored session snapshot has schema version {found}; this server reads version \
         {SNAPSHOT_SCHEMA}"
    )]
    Schema { found: i64 },
    #[error("the stored session snapshot ran model {snapshot}, this stream runs {session}")]
    Model { snapshot: String, session: String },
    #[error("the stored session snapshot does not fit model {model}: {reason}")]
    Unfit { model: String, reason: RestoreError },
    /// `retry`: the fault may pass and the vehicle has not waited long for it, so its stream is
    /// refused, to be retried, rather than start afresh (see `super::snapshot_reads`).
    #[error("the session store could not be read ({why})")]
    Unreadable { why: String, retry: bool },
}

impl SessionSnapshot {
    /// The snapshot's bytes (see the module docs).
    pub fn encode(&self) -> Vec<u8> {
        let mut bytes = Vec::with_capacity(2048);
        bytes.extend_from_slice(MAGIC);
        bytes.extend_from_slice(&SNAPSHOT_SCHEMA.to_le_bytes());
        // Serialising plain structs of numbers, strings and vectors into a Vec cannot fail.
        let payload = postcard::to_extend(self, bytes).unwrap_or_default();
        let mut bytes = payload;
        let checksum = Sha256::digest(&bytes);
        bytes.extend_from_slice(&checksum[..CHECKSUM]);
        bytes
    }

    /// Decodes `bytes` written by [`SessionSnapshot::encode`] of this schema version (see the
    /// module docs).
    pub fn decode(bytes: &[u8]) -> Result<Self, SnapshotRefused> {
        let corrupt = |why: &str| SnapshotRefused::Corrupt(why.to_string());
        if bytes.len() < HEADER + CHECKSUM || !bytes.starts_with(MAGIC) {
            return Err(corrupt("not a Spoofwatch session snapshot"));
        }
        let version = u16::from_le_bytes([bytes[4], bytes[5]]);
        if !reads_schema(i64::from(version)) {
            return Err(SnapshotRefused::Schema {
                found: i64::from(version),
            });
        }
        let (body, checksum) = bytes.split_at(bytes.len() - CHECKSUM);
        if Sha256::digest(body)[..CHECKSUM] != *checksum {
            return Err(corrupt("checksum mismatch"));
        }
        let undecodable = |error: postcard::Error| corrupt(&format!("undecodable: {error}"));
        postcard::from_bytes(&body[HEADER..]).map_err(undecodable)
    }
}

#[cfg(test)]
mod tests {
    use std::sync::Arc;

    use spoofwatch_core::detector::Detector;
    use spoofwatch_core::model::artifact::ModelArtifact;

    use super::*;

    fn snapshot() -> SessionSnapshot {
        let artifact: Arc<ModelArtifact> = Arc::new(
            ModelArtifact::from_slice(crate::models::registry::BUNDLED_MODEL)
                .expect("the bundled model"),
        );
        SessionSnapshot {
            model_id: "default".to_string(),
            samples: 42,
            trajectories: 2,
            last_seq: 7,
            last_timestamp_s: Some(1_700_000_000.5),
            alarm_active: true,
            alarms_raised: 1,
            open_alarm: Some(OpenAlarm {
                id: 5 << 32,
                onset_timestamp_s: 1_700_000_000.0,
                onset_at_ms: 1_700_000_000_123,
                peak: 0.97,
                samples: 3,
                last_timestamp_s: 1_700_000_000.5,
                escalated: Some(Escalated {
                    timestamp_s: 1_700_000_000.25,
                    at_ms: 1_700_000_000_400,
                }),
                credential: Some("token bridge sha256:0123456789abcdef".to_string()),
                credential_per_vehicle: true,
            }),
            detector: Detector::new(artifact).save(),
        }
    }

    #[test]
    fn a_snapshot_decodes_to_what_was_encoded() {
        let original = snapshot();
        let bytes = original.encode();
        let mut header = b"SWSS".to_vec();
        header.extend_from_slice(&SNAPSHOT_SCHEMA.to_le_bytes());
        assert!(bytes.starts_with(&header), "magic, then the schema version");
        let decoded = SessionSnapshot::decode(&bytes).expect("decodes");
        // The detector state has no PartialEq (NaNs inside); its re-encoding must be identical.
        assert_eq!(decoded.encode(), bytes);
        assert_eq!(decoded.open_alarm, original.open_alarm);
        assert_eq!(
            (decoded.samples, decoded.last_seq, decoded.model_id.as_str()),
            (42, 7, "default")
        );
    }

    /// A session handed off by a server of an older version starts afresh: the detector's state
    /// inside it had another shape.
    #[test]
    fn only_this_version_is_read() {
        assert!(reads_schema(i64::from(SNAPSHOT_SCHEMA)));
        assert!((0..SNAPSHOT_SCHEMA).all(|v| !reads_schema(i64::from(v))));
        let mut older = snapshot().encode();
        older[4..6].copy_from_slice(&(SNAPSHOT_SCHEMA - 1).to_le_bytes());
        assert_eq!(
            SessionSnapshot::decode(&older).err(),
            Some(SnapshotRefused::Schema {
                found: i64::from(SNAPSHOT_SCHEMA - 1)
            })
        );
    }

    #[test]
    fn corrupt_and_foreign_snapshots_are_refused_with_their_reason() {
        let bytes = snapshot().encode();
        let refusal = |bytes: &[u8]| SessionSnapshot::decode(bytes).err().map(|e| e.to_string());

        let mut flipped = bytes.clone();
        flipped[40] ^= 0x10;
        assert_eq!(
            refusal(&flipped).as_deref(),
            Some("the stored session snapshot is corrupt (checksum mismatch)")
        );
        assert_eq!(
            refusal(&bytes[..bytes.len() - 1]).as_deref(),
            Some("the stored session snapshot is corrupt (checksum mismatch)")
        );
        assert_eq!(
            refusal(b"{\"vehicle\": 1}").as_deref(),
            Some("the stored session snapshot is corrupt (not a Spoofwatch session snapshot)")
        );
        assert_eq!(
            refusal(&[]).as_deref(),
            Some("the stored session snapshot is corrupt (not a Spoofwatch session snapshot)")
        );

        // A snapshot of another version (here the one before the offset evidence) is refused.
        let mut older = bytes.clone();
        older[4] = 1;
        assert_eq!(
            refusal(&older).as_deref(),
            Some(
                format!(
                    "the stored session snapshot has schema version 1; this server reads version \
                     {SNAPSHOT_SCHEMA}"
                )
                .as_str()
            )
        );

        // A well-formed envelope around a payload of another shape (checksum recomputed).
        let mut foreign = b"SWSS".to_vec();
        foreign.extend_from_slice(&SNAPSHOT_SCHEMA.to_le_bytes());
        foreign.extend_from_slice(&[0xff; 12]);
        let checksum = Sha256::digest(&foreign);
        foreign.extend_from_slice(&checksum[..CHECKSUM]);
        let reason = refusal(&foreign).expect("refused");
        assert!(
            reason.starts_with("the stored session snapshot is corrupt (undecodable"),
            "{reason}"
        );
    }
}
