//! The session snapshot: a vehicle session's complete state as bytes, so that a stream starting on
//! any server process (another replica, or this one after a restart) continues the session exactly.
//!
//! Encoding: `SWSS` magic, the schema version (u16, little-endian), the postcard encoding of a
//! [`SessionSnapshot`] (f64s as their bit patterns, so a continued session is bit-exact), and the
//! first 8 bytes of the SHA-256 of everything before them. A snapshot that fails any of these is
//! refused with a [`SnapshotRefused`] naming why; the session then starts afresh.
//!
//! Older versions still read:
//! - version 7 is version 8 without the open alarm's credential ([`OpenAlarm::credential`]): its
//!   open alarm continues with none in memory (the stored alarm row keeps the one it opened with);
//! - version 6 is version 7 without the open alarm's escalation times ([`OpenAlarm::escalated`]):
//!   its open alarm continues as a warning (a server of version 6 stored no critical alarm);
//! - version 5 is version 6 without the detector's escalation (the last field of the detector's
//!   state, and of the snapshot): it continues as an episode that has not turned critical;
//! - version 4 is version 5 without the detector's receiver-flag memory: it continues as a session
//!   whose receiver has raised no flag either.

use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use spoofwatch_core::detector::{DetectorState, DetectorStateWithoutFlags, RestoreError};
use spoofwatch_core::severity::Escalation;

/// The encoding this server writes. Bump it when [`SessionSnapshot`] or anything inside
/// [`DetectorState`] changes shape: older snapshots are then refused (fresh sessions), never
/// misread, unless [`SessionSnapshot::decode`] is taught to read them.
pub const SNAPSHOT_SCHEMA: u16 = 8;
/// The version before the open alarm kept its credential, still read.
const SNAPSHOT_SCHEMA_WITHOUT_CREDENTIAL: u16 = 7;
/// The version before the open alarm kept its escalation, still read.
const SNAPSHOT_SCHEMA_WITHOUT_ESCALATED_ALARM: u16 = 6;
/// The version before alarm severities, still read.
const SNAPSHOT_SCHEMA_WITHOUT_SEVERITY: u16 = 5;
/// The version before the receiver-flag memory, still read.
const SNAPSHOT_SCHEMA_WITHOUT_FLAGS: u16 = 4;

/// Whether this server reads stored snapshots of schema version `version`.
pub fn reads_schema(version: i64) -> bool {
    (i64::from(SNAPSHOT_SCHEMA_WITHOUT_FLAGS)..=i64::from(SNAPSHOT_SCHEMA)).contains(&version)
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
    /// that another stream continues; `None` when a snapshot of version 7 or older held it.
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

/// An [`OpenAlarm`] as snapshots of version 6 and older keep it: a warning.
#[derive(Deserialize)]
#[cfg_attr(test, derive(Serialize))]
struct OpenWarning {
    id: i64,
    onset_timestamp_s: f64,
    onset_at_ms: i64,
    peak: f64,
    samples: u32,
    last_timestamp_s: f64,
}

/// An [`OpenAlarm`] as snapshots of version 7 keep it: without its credential. (Postcard
/// concatenates a nested struct's fields, so these are the bytes of the seven fields in order.)
#[derive(Deserialize)]
#[cfg_attr(test, derive(Serialize))]
struct OpenAlarmWithoutCredential {
    warning: OpenWarning,
    escalated: Option<Escalated>,
}

impl From<OpenAlarmWithoutCredential> for OpenAlarm {
    fn from(old: OpenAlarmWithoutCredential) -> Self {
        Self {
            escalated: old.escalated,
            ..old.warning.into()
        }
    }
}

impl From<OpenWarning> for OpenAlarm {
    fn from(old: OpenWarning) -> Self {
        Self {
            id: old.id,
            onset_timestamp_s: old.onset_timestamp_s,
            onset_at_ms: old.onset_at_ms,
            peak: old.peak,
            samples: old.samples,
            last_timestamp_s: old.last_timestamp_s,
            escalated: None,
            credential: None,
            credential_per_vehicle: false,
        }
    }
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
        "the stored session snapshot has schema version {found}; this server reads versions \
         {SNAPSHOT_SCHEMA_WITHOUT_FLAGS} to {SNAPSHOT_SCHEMA}"
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

/// A [`SessionSnapshot`] of schema versions 4 to 7: the same fields, the open alarm `A` and the
/// detector's state `D` as that version kept them.
#[derive(Deserialize)]
#[cfg_attr(test, derive(Serialize))]
struct OlderSessionSnapshot<A, D> {
    model_id: String,
    samples: u64,
    trajectories: u32,
    last_seq: u64,
    last_timestamp_s: Option<f64>,
    alarm_active: bool,
    alarms_raised: u64,
    open_alarm: Option<A>,
    detector: D,
}

/// A snapshot of versions 4 to 6: the open alarm a warning.
type SessionSnapshotOfWarnings<D> = OlderSessionSnapshot<OpenWarning, D>;

impl<A: Into<OpenAlarm>, D: Into<DetectorState>> From<OlderSessionSnapshot<A, D>>
    for SessionSnapshot
{
    fn from(old: OlderSessionSnapshot<A, D>) -> Self {
        Self {
            model_id: old.model_id,
            samples: old.samples,
            trajectories: old.trajectories,
            last_seq: old.last_seq,
            last_timestamp_s: old.last_timestamp_s,
            alarm_active: old.alarm_active,
            alarms_raised: old.alarms_raised,
            open_alarm: old.open_alarm.map(Into::into),
            detector: old.detector.into(),
        }
    }
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

    /// Decodes `bytes` written by [`SessionSnapshot::encode`] of this schema version or of an
    /// older one still read (see the module docs).
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
        let payload = &body[HEADER..];
        match version {
            SNAPSHOT_SCHEMA_WITHOUT_FLAGS => postcard::from_bytes::<
                SessionSnapshotOfWarnings<DetectorStateWithoutFlags>,
            >(payload)
            .map(Self::from)
            .map_err(undecodable),
            SNAPSHOT_SCHEMA_WITHOUT_SEVERITY => {
                // Cut short before the detector's escalation: the bytes of one that has not
                // escalated complete it.
                let mut payload = payload.to_vec();
                payload.extend(postcard::to_allocvec(&Escalation::default()).unwrap_or_default());
                postcard::from_bytes::<SessionSnapshotOfWarnings<DetectorState>>(&payload)
                    .map(Self::from)
                    .map_err(undecodable)
            }
            SNAPSHOT_SCHEMA_WITHOUT_ESCALATED_ALARM => {
                postcard::from_bytes::<SessionSnapshotOfWarnings<DetectorState>>(payload)
                    .map(Self::from)
                    .map_err(undecodable)
            }
            SNAPSHOT_SCHEMA_WITHOUT_CREDENTIAL => postcard::from_bytes::<
                OlderSessionSnapshot<OpenAlarmWithoutCredential, DetectorState>,
            >(payload)
            .map(Self::from)
            .map_err(undecodable),
            _ => postcard::from_bytes(payload).map_err(undecodable),
        }
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

    /// Bytes of an unescalated escalation at the end of the payload: a warning (0), no time (0),
    /// no evidence (eight zero bytes of 0.0) and no time fed (0).
    const NO_ESCALATION: [u8; 11] = [0; 11];
    /// Bytes of an empty receiver-flag memory before it: two absent times.
    const NO_FLAGS: [u8; 2] = [0; 2];

    /// `open` as snapshots of version 6 and older keep it.
    fn warning_of(open: &OpenAlarm) -> OpenWarning {
        OpenWarning {
            id: open.id,
            onset_timestamp_s: open.onset_timestamp_s,
            onset_at_ms: open.onset_at_ms,
            peak: open.peak,
            samples: open.samples,
            last_timestamp_s: open.last_timestamp_s,
        }
    }

    /// `snapshot` as a server of schema version 6 stored it (its open alarm a warning), cut short
    /// by `cut` bytes and labelled `version`: 6 uncut, 5 without the escalation, 4 without the
    /// flags too.
    fn as_version(snapshot: &SessionSnapshot, version: u16, cut: usize) -> Vec<u8> {
        let old = SessionSnapshotOfWarnings {
            model_id: snapshot.model_id.clone(),
            samples: snapshot.samples,
            trajectories: snapshot.trajectories,
            last_seq: snapshot.last_seq,
            last_timestamp_s: snapshot.last_timestamp_s,
            alarm_active: snapshot.alarm_active,
            alarms_raised: snapshot.alarms_raised,
            open_alarm: snapshot.open_alarm.as_ref().map(warning_of),
            detector: snapshot.detector.clone(),
        };
        let payload = postcard::to_allocvec(&old).expect("encodes");
        let mut bytes = b"SWSS".to_vec();
        bytes.extend_from_slice(&version.to_le_bytes());
        bytes.extend_from_slice(&payload[..payload.len() - cut]);
        let checksum = Sha256::digest(&bytes);
        bytes.extend_from_slice(&checksum[..CHECKSUM]);
        bytes
    }

    #[test]
    fn older_snapshots_continue_without_what_they_did_not_keep() {
        let original = snapshot();
        let bytes = original.encode();
        let payload = &bytes[HEADER..bytes.len() - CHECKSUM];
        let tail = [NO_FLAGS.as_slice(), NO_ESCALATION.as_slice()].concat();
        assert_eq!(
            payload[payload.len() - tail.len()..],
            tail[..],
            "no flag memory, then no escalation"
        );
        // What this version writes, with the open alarm a warning: what the older ones continue as.
        let as_warning = SessionSnapshot {
            open_alarm: original.open_alarm.clone().map(|open| OpenAlarm {
                escalated: None,
                credential: None,
                credential_per_vehicle: false,
                ..open
            }),
            ..original.clone()
        };
        for (version, cut) in [(6, 0), (5, NO_ESCALATION.len()), (4, tail.len())] {
            let old = as_version(&original, version, cut);
            let decoded = SessionSnapshot::decode(&old)
                .unwrap_or_else(|e| panic!("version {version} reads: {e}"));
            assert_eq!(decoded.encode(), as_warning.encode(), "version {version}");
            assert_eq!(decoded.open_alarm, as_warning.open_alarm);
        }
        assert!((4..=8).all(reads_schema));
        assert!(!reads_schema(3) && !reads_schema(9));
    }

    /// A session handed off by a server of version 7 continues its open alarm, critical as it was,
    /// without a credential in memory.
    #[test]
    fn a_version_7_snapshot_continues_its_alarm_without_a_credential() {
        let original = snapshot();
        let open = original.open_alarm.clone().expect("an open alarm");
        let old = OlderSessionSnapshot {
            model_id: original.model_id.clone(),
            samples: original.samples,
            trajectories: original.trajectories,
            last_seq: original.last_seq,
            last_timestamp_s: original.last_timestamp_s,
            alarm_active: original.alarm_active,
            alarms_raised: original.alarms_raised,
            open_alarm: Some(OpenAlarmWithoutCredential {
                warning: warning_of(&open),
                escalated: open.escalated,
            }),
            detector: original.detector.clone(),
        };
        // The nested struct is the bytes of version 7's seven fields in order.
        let flat = (
            open.id,
            open.onset_timestamp_s,
            open.onset_at_ms,
            open.peak,
            open.samples,
            open.last_timestamp_s,
            open.escalated,
        );
        assert_eq!(
            postcard::to_allocvec(old.open_alarm.as_ref().expect("open")).expect("encodes"),
            postcard::to_allocvec(&flat).expect("encodes")
        );
        let mut bytes = b"SWSS".to_vec();
        bytes.extend_from_slice(&7u16.to_le_bytes());
        bytes.extend(postcard::to_allocvec(&old).expect("encodes"));
        let checksum = Sha256::digest(&bytes);
        bytes.extend_from_slice(&checksum[..CHECKSUM]);
        let decoded = SessionSnapshot::decode(&bytes).expect("version 7 reads");
        let expected = OpenAlarm {
            credential: None,
            credential_per_vehicle: false,
            ..open
        };
        assert_eq!(decoded.open_alarm, Some(expected.clone()));
        let continued = SessionSnapshot {
            open_alarm: Some(expected),
            ..original
        };
        assert_eq!(decoded.encode(), continued.encode(), "the rest as it was");
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
                "the stored session snapshot has schema version 1; this server reads versions 4 to 8"
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
