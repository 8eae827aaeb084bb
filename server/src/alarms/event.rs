//! The alarm's domain: its transitions (it opens, it turns critical, it ends), why it was raised,
//! and the one place where an emitted transition is counted and logged.
//!
//! The transitions build the alarm's row as each event leaves it: [`opened`] (one sample, its peak
//! the onset probability, with why and where it started, as a warning or already critical),
//! [`escalated`] (an open warning turns critical: one alarm whose severity rises, never a second
//! alarm) and [`ended`]. Why an alarm was raised is mapped between the core's [`Explanation`] of
//! the onset sample and the row's [`StoredWhy`]. [`emitted`] is called once for each event the
//! outbox emits: it counts it by severity (`crate::telemetry`) and logs it.
//!
//! Owns those rules and that mapping. Must not queue, store or serve anything: the outbox
//! (`crate::outbox`) queues, the store keeps the rows and their write guards, and `super::wire`
//! maps an alarm to protobuf.

use spoofwatch_core::explain::{EvidenceKind, Explanation};
use spoofwatch_core::geo::LatLon;
use spoofwatch_core::severity::Severity;
use spoofwatch_proto::wire::convert::timestamp_from_ms;

use crate::store::{
    AlarmEvent, AlarmEventKind, AlarmEventRow, StoredCredential, StoredPlace, StoredSeverity,
    StoredWhy,
};
use crate::telemetry;

/// Why and where an alarm started: its onset sample's explanation and fix.
#[derive(Clone, Copy, Debug)]
pub struct OnsetWhy<'a> {
    pub explanation: &'a Explanation,
    pub fix: LatLon,
}

/// No credential recorded (an alarm stored before alarms kept theirs).
#[cfg(test)]
pub static NO_CREDENTIAL: StoredCredential = StoredCredential {
    credential: None,
    credential_per_vehicle: false,
};

/// An alarm's first sample: whose, which model raised it, when (sample time and server wall
/// time), its probability, its severity then, why and where it started (when the onset has an
/// explanation), and the credential whose call sent it.
#[derive(Clone, Copy, Debug)]
pub struct Onset<'a> {
    pub vehicle_id: &'a str,
    pub model_id: &'a str,
    pub timestamp_s: f64,
    pub at_ms: i64,
    pub probability: f64,
    /// Critical when the onset sample is already critical (decisive evidence): the alarm then
    /// escalated at its onset.
    pub severity: Severity,
    pub why: Option<OnsetWhy<'a>>,
    pub credential: &'a StoredCredential,
}

#[cfg(test)]
impl<'a> Onset<'a> {
    /// A warning onset without an explanation.
    pub fn warning(
        vehicle_id: &'a str,
        model_id: &'a str,
        timestamp_s: f64,
        at_ms: i64,
        probability: f64,
    ) -> Self {
        Self {
            vehicle_id,
            model_id,
            timestamp_s,
            at_ms,
            probability,
            severity: Severity::Warning,
            why: None,
            credential: &NO_CREDENTIAL,
        }
    }
}

/// A new open alarm `id` of one sample whose peak is its onset probability, with why and where it
/// started when the onset has an explanation; one that opens critical escalated at its onset.
pub fn opened(id: i64, onset: &Onset<'_>) -> AlarmEventRow {
    let critical = onset.severity == Severity::Critical;
    AlarmEventRow {
        id,
        vehicle_id: onset.vehicle_id.to_string(),
        model_id: onset.model_id.to_string(),
        onset_timestamp_s: onset.timestamp_s,
        end_timestamp_s: None,
        onset_at_ms: onset.at_ms,
        ended_at_ms: None,
        peak_probability: onset.probability,
        samples: 1,
        why: onset.why.map(|w| stored(w.explanation)).unwrap_or_default(),
        place: onset.why.map(|w| place(w.fix)).unwrap_or_default(),
        severity: StoredSeverity(onset.severity),
        escalated_timestamp_s: critical.then_some(onset.timestamp_s),
        escalated_at_ms: critical.then_some(onset.at_ms),
        credential: onset.credential.clone(),
    }
}

/// Open `alarm` turned critical at sample time `timestamp_s` (server wall time `at_ms`), with its
/// peak and samples then. An alarm already critical keeps its first escalation.
pub fn escalated(
    alarm: &AlarmEventRow,
    timestamp_s: f64,
    at_ms: i64,
    peak_probability: f64,
    samples: i64,
) -> AlarmEventRow {
    AlarmEventRow {
        severity: StoredSeverity(Severity::Critical),
        escalated_timestamp_s: alarm.escalated_timestamp_s.or(Some(timestamp_s)),
        escalated_at_ms: alarm.escalated_at_ms.or(Some(at_ms)),
        peak_probability,
        samples,
        ..alarm.clone()
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

/// An event the outbox emitted (queued for the store): counted by severity, and logged as one
/// structured line (one per onset, escalation and end), which carries the severity. An onset's
/// line says why: the dominant evidence, the offset's distance and bearing, the drift's speed and
/// bearing (left out when the onset has no explanation).
pub fn emitted(event: &AlarmEvent) {
    not_queued(event.kind, event.alarm.severity.0);
    log(event);
}

/// An onset, escalation or end of an alarm of `severity` the outbox could not queue (the queue was
/// full, the event was invalid, or its onset was never queued): counted all the same, because the
/// vehicle's alarm did turn on, critical or off; the outbox logs why it was not stored.
pub fn not_queued(kind: AlarmEventKind, severity: Severity) {
    match kind {
        AlarmEventKind::Onset => telemetry::alarm_onset(severity),
        AlarmEventKind::Escalated => telemetry::alarm_escalated(),
        AlarmEventKind::End => telemetry::alarm_end(severity),
    }
}

/// An alarm a previous run left open, ended by the store as this process starts: logged, not
/// counted (this process never counted it open).
pub fn ended_at_start(event: &AlarmEvent) {
    log(event);
}

fn log(event: &AlarmEvent) {
    let alarm = &event.alarm;
    let severity = alarm.severity.0.name();
    let escalated_at = alarm.escalated_at_ms.map(timestamp_from_ms);
    match event.kind {
        AlarmEventKind::Onset => {
            let why = explanation(&alarm.why);
            let offset = why.map(|x| x.offset_polar());
            let drift = why.map(|x| x.drift_polar());
            tracing::info!(
                vehicle_id = %alarm.vehicle_id,
                model = %alarm.model_id,
                alarm_id = alarm.id,
                severity,
                probability = alarm.peak_probability,
                onset_timestamp_s = alarm.onset_timestamp_s,
                onset_at = %timestamp_from_ms(alarm.onset_at_ms),
                why = why.map(|x| x.dominant.name()),
                offset_m = offset.map(|o| o.0),
                offset_bearing_deg = offset.map(|o| o.1),
                drift_mps = drift.map(|d| d.0),
                drift_bearing_deg = drift.map(|d| d.1),
                credential = alarm.credential.credential.as_deref(),
                "alarm onset"
            )
        }
        AlarmEventKind::Escalated => tracing::info!(
            vehicle_id = %alarm.vehicle_id,
            model = %alarm.model_id,
            alarm_id = alarm.id,
            severity,
            peak_probability = alarm.peak_probability,
            samples = alarm.samples,
            onset_timestamp_s = alarm.onset_timestamp_s,
            escalated_timestamp_s = alarm.escalated_timestamp_s,
            escalated_at = escalated_at.map(tracing::field::display),
            "alarm escalated"
        ),
        AlarmEventKind::End => tracing::info!(
            vehicle_id = %alarm.vehicle_id,
            model = %alarm.model_id,
            alarm_id = alarm.id,
            severity,
            peak_probability = alarm.peak_probability,
            samples = alarm.samples,
            onset_timestamp_s = alarm.onset_timestamp_s,
            end_timestamp_s = alarm.end_timestamp_s,
            onset_at = %timestamp_from_ms(alarm.onset_at_ms),
            ended_at = %timestamp_from_ms(alarm.ended_at_ms.unwrap_or_default()),
            escalated_timestamp_s = alarm.escalated_timestamp_s,
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
        let onset = Onset {
            why: Some(why),
            ..Onset::warning("car-7", "m", 100.0, 5_000, 0.8)
        };
        let open = opened(7, &onset);
        assert!(open.is_open());
        assert_eq!(open.severity, StoredSeverity(Severity::Warning));
        assert_eq!(
            (open.escalated_timestamp_s, open.escalated_at_ms),
            (None, None)
        );
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
        let bare = opened(8, &Onset::warning("car-8", "m", 1.0, 1, 0.5));
        assert_eq!((bare.why, bare.place), Default::default());
    }

    #[test]
    fn an_alarm_turns_critical_once_and_keeps_its_first_escalation() {
        let open = opened(7, &Onset::warning("car-7", "m", 100.0, 5_000, 0.8));
        let critical = escalated(&open, 104.0, 9_000, 0.99, 5);
        assert_eq!(critical.severity, StoredSeverity(Severity::Critical));
        assert_eq!(
            (critical.escalated_timestamp_s, critical.escalated_at_ms),
            (Some(104.0), Some(9_000))
        );
        assert_eq!((critical.peak_probability, critical.samples), (0.99, 5));
        assert_eq!((critical.id, critical.onset_timestamp_s), (7, 100.0));
        let again = escalated(&critical, 110.0, 15_000, 0.999, 11);
        assert_eq!(again.escalated_timestamp_s, Some(104.0));
        // Opened critical: escalated at the onset, and it stays critical when it ends.
        let at_once = opened(
            8,
            &Onset {
                severity: Severity::Critical,
                ..Onset::warning("car-8", "m", 50.0, 2_000, 0.9)
            },
        );
        assert_eq!(
            (at_once.escalated_timestamp_s, at_once.escalated_at_ms),
            (Some(50.0), Some(2_000))
        );
        let closed = ended(&at_once, Some(60.0), 3_000, 0.95, 11);
        assert_eq!(closed.severity, StoredSeverity(Severity::Critical));
    }
}
