//! The alarm's domain: its transitions (it opens, it ends), why it was raised, and the one place
//! where an emitted transition is counted and logged.
//!
//! The transitions build the alarm's row as each event leaves it: [`opened`] (one sample, its peak
//! the onset probability, with why and where it started) and [`ended`]. A later severity adds its
//! transition here, beside them (an alarm that escalates). Why an alarm was raised is mapped between
//! the core's [`Explanation`] of the onset sample and the row's [`StoredWhy`]. [`emitted`] is called
//! once for each event the outbox emits: it counts it (`crate::telemetry`) and logs it.
//!
//! Owns those rules and that mapping. Must not queue, store or serve anything: the outbox
//! (`crate::outbox`) queues, the store keeps the rows and their write guards, and `super::wire`
//! maps an alarm to protobuf.

use spoofwatch_core::explain::{EvidenceKind, Explanation};
use spoofwatch_core::geo::LatLon;
use spoofwatch_proto::wire::convert::timestamp_from_ms;

use crate::store::{AlarmEvent, AlarmEventKind, AlarmEventRow, StoredPlace, StoredWhy};
use crate::telemetry;

/// Why and where an alarm started: its onset sample's explanation and fix.
#[derive(Clone, Copy, Debug)]
pub struct OnsetWhy<'a> {
    pub explanation: &'a Explanation,
    pub fix: LatLon,
}

/// A new open alarm of one sample whose peak is its onset probability, with why and where it
/// started when the onset has an explanation.
pub fn opened(
    id: i64,
    vehicle_id: &str,
    model_id: &str,
    onset_timestamp_s: f64,
    onset_at_ms: i64,
    probability: f64,
    why: Option<OnsetWhy<'_>>,
) -> AlarmEventRow {
    AlarmEventRow {
        id,
        vehicle_id: vehicle_id.to_string(),
        model_id: model_id.to_string(),
        onset_timestamp_s,
        end_timestamp_s: None,
        onset_at_ms,
        ended_at_ms: None,
        peak_probability: probability,
        samples: 1,
        why: why.map(|w| stored(w.explanation)).unwrap_or_default(),
        place: why.map(|w| place(w.fix)).unwrap_or_default(),
    }
}

/// `alarm` closed at wall time `ended_at_ms` after its last alarming sample (`None` when its
/// session or the server stopped while it was on), with its peak and samples then.
pub fn ended(
    alarm: &AlarmEventRow,
    end_timestamp_s: Option<f64>,
    ended_at_ms: i64,
    peak_probability: f64,
    samples: i64,
) -> AlarmEventRow {
    AlarmEventRow {
        end_timestamp_s,
        ended_at_ms: Some(ended_at_ms),
        peak_probability,
        samples,
        ..alarm.clone()
    }
}

/// The onset's explanation as the alarm row stores it.
pub fn stored(x: &Explanation) -> StoredWhy {
    StoredWhy {
        why_kind: Some(x.dominant.name().to_string()),
        why_offset_east_m: Some(x.offset_m[0]),
        why_offset_north_m: Some(x.offset_m[1]),
        why_drift_east_mps: Some(x.drift_rate_mps[0]),
        why_drift_north_mps: Some(x.drift_rate_mps[1]),
    }
}

/// The onset's fix as the alarm row stores it.
pub fn place(fix: LatLon) -> StoredPlace {
    StoredPlace {
        onset_latitude_deg: Some(fix.lat_deg),
        onset_longitude_deg: Some(fix.lon_deg),
    }
}

/// A stored explanation back as the core's: `None` for a row without one (stored before schema
/// version 6) or with a kind this build does not know; a missing vector component reads as 0.
pub fn explanation(why: &StoredWhy) -> Option<Explanation> {
    let name = why.why_kind.as_deref()?;
    let dominant = EvidenceKind::from_name(name)?;
    let or_zero = |v: Option<f64>| v.unwrap_or(0.0);
    Some(Explanation {
        dominant,
        offset_m: [
            or_zero(why.why_offset_east_m),
            or_zero(why.why_offset_north_m),
        ],
        drift_rate_mps: [
            or_zero(why.why_drift_east_mps),
            or_zero(why.why_drift_north_mps),
        ],
    })
}

/// An event the outbox emitted (queued for the store): counted, and logged as one structured line
/// (one per onset, one per end). An onset's line says why: the dominant evidence, the offset's
/// distance and bearing, the drift's speed and bearing (left out when the onset has no
/// explanation).
pub fn emitted(event: &AlarmEvent) {
    match event.kind {
        AlarmEventKind::Onset => telemetry::alarm_onset(),
        AlarmEventKind::End => telemetry::alarm_end(),
    }
    log(event);
}

/// An onset or end the outbox could not queue (the queue was full, the event was invalid, or its
/// onset was never queued): counted all the same, because the vehicle's alarm did turn on or off;
/// the outbox logs why it was not stored.
pub fn not_queued(kind: AlarmEventKind) {
    match kind {
        AlarmEventKind::Onset => telemetry::alarm_onset(),
        AlarmEventKind::End => telemetry::alarm_end(),
    }
}

/// An alarm a previous run left open, ended by the store as this process starts: logged, not
/// counted (this process never counted it open).
pub fn ended_at_start(event: &AlarmEvent) {
    log(event);
}

fn log(event: &AlarmEvent) {
    let alarm = &event.alarm;
    match event.kind {
        AlarmEventKind::Onset => {
            let why = explanation(&alarm.why);
            let offset = why.map(|x| x.offset_polar());
            let drift = why.map(|x| x.drift_polar());
            tracing::info!(
                vehicle_id = %alarm.vehicle_id,
                model = %alarm.model_id,
                alarm_id = alarm.id,
                probability = alarm.peak_probability,
                onset_timestamp_s = alarm.onset_timestamp_s,
                onset_at = %timestamp_from_ms(alarm.onset_at_ms),
                why = why.map(|x| x.dominant.name()),
                offset_m = offset.map(|o| o.0),
                offset_bearing_deg = offset.map(|o| o.1),
                drift_mps = drift.map(|d| d.0),
                drift_bearing_deg = drift.map(|d| d.1),
                "alarm onset"
            )
        }
        AlarmEventKind::End => tracing::info!(
            vehicle_id = %alarm.vehicle_id,
            model = %alarm.model_id,
            alarm_id = alarm.id,
            peak_probability = alarm.peak_probability,
            samples = alarm.samples,
            onset_timestamp_s = alarm.onset_timestamp_s,
            end_timestamp_s = alarm.end_timestamp_s,
            onset_at = %timestamp_from_ms(alarm.onset_at_ms),
            ended_at = %timestamp_from_ms(alarm.ended_at_ms.unwrap_or_default()),
            "alarm end"
        ),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_kind_survives_the_store() {
        for dominant in EvidenceKind::ALL {
            let x = Explanation {
                dominant,
                offset_m: [-30.0, 40.0],
                drift_rate_mps: [0.5, -0.25],
            };
            assert_eq!(explanation(&stored(&x)), Some(x));
        }
    }

    #[test]
    fn an_alarm_opens_with_one_sample_at_its_onset_probability_and_ends_with_its_peak() {
        let x = Explanation {
            dominant: EvidenceKind::Jump,
            offset_m: [3.0, 4.0],
            drift_rate_mps: [0.0, 0.0],
        };
        let why = OnsetWhy {
            explanation: &x,
            fix: LatLon::new(32.0, -110.0),
        };
        let open = opened(7, "car-7", "m", 100.0, 5_000, 0.8, Some(why));
        assert!(open.is_open());
        assert_eq!((open.samples, open.peak_probability), (1, 0.8));
        assert_eq!(explanation(&open.why), Some(x));
        assert_eq!(open.place.onset_latitude_deg, Some(32.0));
        let closed = ended(&open, Some(130.0), 6_000, 0.95, 31);
        assert!(!closed.is_open());
        assert_eq!(closed.end_timestamp_s, Some(130.0));
        assert_eq!((closed.samples, closed.peak_probability), (31, 0.95));
        assert_eq!(
            (closed.id, closed.onset_at_ms, closed.why),
            (7, 5_000, open.why)
        );
        let bare = opened(8, "car-8", "m", 1.0, 1, 0.5, None);
        assert_eq!((bare.why, bare.place), Default::default());
    }
}
