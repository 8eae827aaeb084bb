//! The alarm on the wire: a stored alarm, its events and the CAUGHT_UP marker as protobuf, for
//! ListAlarms and WatchAlarms (as `crate::models::wire` is for models).
//!
//! Owns the mapping to protobuf. Must not read the store or decide anything about an alarm (its
//! rules and its explanation are `super::event`'s).

use spoofwatch_proto::v1;
use spoofwatch_proto::wire::ModelName;
use spoofwatch_proto::wire::convert::{explanation_to_proto, severity_to_proto, timestamp_from_ms};

use super::event::explanation;
use crate::store::{AlarmEventKind, AlarmEventRow, LoggedAlarmEvent, StoredWhy};

/// A stored or emitted alarm on the wire.
pub fn alarm_to_proto(alarm: &AlarmEventRow) -> v1::Alarm {
    let why = why_to_proto(&alarm.why);
    v1::Alarm {
        id: alarm.id,
        vehicle_id: alarm.vehicle_id.clone(),
        model: ModelName::from_id(&alarm.model_id).to_string(),
        onset_timestamp_s: alarm.onset_timestamp_s,
        end_timestamp_s: alarm.end_timestamp_s,
        onset_time: Some(timestamp_from_ms(alarm.onset_at_ms)),
        end_time: alarm.ended_at_ms.map(timestamp_from_ms),
        peak_probability: alarm.peak_probability,
        samples: u64::try_from(alarm.samples).unwrap_or(0),
        open: alarm.is_open(),
        why,
        onset_latitude_deg: alarm.place.onset_latitude_deg,
        onset_longitude_deg: alarm.place.onset_longitude_deg,
        severity: severity_to_proto(Some(alarm.severity.0)) as i32,
        escalated_timestamp_s: alarm.escalated_timestamp_s,
        escalated_time: alarm.escalated_at_ms.map(timestamp_from_ms),
        credential: alarm.credential.credential.clone(),
    }
}

/// A logged alarm event on the wire, with its cursor.
pub fn event_to_proto(logged: &LoggedAlarmEvent) -> v1::AlarmEvent {
    let kind = match logged.event.kind {
        AlarmEventKind::Onset => v1::AlarmEventKind::Onset,
        AlarmEventKind::Escalated => v1::AlarmEventKind::Escalated,
        AlarmEventKind::End => v1::AlarmEventKind::End,
    };
    v1::AlarmEvent {
        cursor: logged.position,
        kind: kind as i32,
        alarm: Some(alarm_to_proto(&logged.event.alarm)),
    }
}

/// The marker after the replay: every event through `cursor` was sent.
pub fn caught_up(cursor: i64) -> v1::AlarmEvent {
    v1::AlarmEvent {
        cursor,
        kind: v1::AlarmEventKind::CaughtUp as i32,
        alarm: None,
    }
}

/// A stored explanation on the wire (absent when the row has none).
pub fn why_to_proto(why: &StoredWhy) -> Option<v1::Explanation> {
    explanation(why).as_ref().map(explanation_to_proto)
}

#[cfg(test)]
mod tests {
    use spoofwatch_core::explain::{EvidenceKind, Explanation};

    use super::*;
    use crate::alarms::event::stored;

    #[test]
    fn a_stored_jump_reads_as_distance_and_bearing_on_the_wire() {
        let why = stored(&Explanation {
            dominant: EvidenceKind::Jump,
            // 400 m west, 300 m south: 500 m toward 270° − atan(3/4) = 233.13°.
            offset_m: [-400.0, -300.0],
            drift_rate_mps: [0.0, 0.0],
        });
        assert_eq!(why.why_kind.as_deref(), Some("jump"));
        let wire = why_to_proto(&why).expect("stored");
        assert_eq!(wire.dominant(), v1::EvidenceKind::Jump);
        assert_eq!(wire.offset_m, 500.0);
        assert!((wire.offset_bearing_deg - 233.130_102_354_155_98).abs() < 1e-9);
        assert_eq!((wire.drift_mps, wire.drift_bearing_deg), (0.0, 0.0));
    }

    #[test]
    fn rows_without_an_explanation_have_none_on_the_wire() {
        assert_eq!(why_to_proto(&StoredWhy::default()), None);
        let unknown = StoredWhy {
            why_kind: Some("telepathy".to_string()),
            ..StoredWhy::default()
        };
        assert_eq!(why_to_proto(&unknown), None);
    }
}
