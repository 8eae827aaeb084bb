//! A replay's final output per vehicle: its events with every failover applied, so that each
//! recorded row has exactly one detection, in order. A [`ReplayEvent::Failover`] says that the
//! detections from record `resend_from` on will come again; the detections and refusals received
//! before for those records are dropped here. Stream openings and failovers stay: they happened
//! (and the fleet tally counts them).
//!
//! The replay itself forwards everything as it arrives (for live output); whoever needs the final
//! rows (CSV output, the fleet tally, tests) keeps them here.

use std::collections::BTreeMap;

use crate::replay::{ReplayEvent, ReplayedDetection};

/// Every vehicle's events, failovers applied.
#[derive(Debug, Default)]
pub struct ReplayLog {
    vehicles: BTreeMap<String, Vec<ReplayEvent>>,
}

impl ReplayLog {
    /// Takes the next event (a vehicle's events in the order the replay sent them).
    pub fn record(&mut self, event: ReplayEvent) {
        let vehicle_id = match &event {
            ReplayEvent::Accepted { vehicle_id, .. }
            | ReplayEvent::Failover { vehicle_id, .. }
            | ReplayEvent::ItemError { vehicle_id, .. } => vehicle_id,
            ReplayEvent::Detection(d) => &d.vehicle_id,
        };
        let events = self.vehicles.entry(vehicle_id.clone()).or_default();
        if let ReplayEvent::Failover { resend_from, .. } = &event {
            events.retain(|e| row_index(e).is_none_or(|index| index < *resend_from));
        }
        events.push(event);
    }

    /// Each vehicle's final events (by vehicle id).
    pub fn vehicles(&self) -> impl Iterator<Item = (&str, &[ReplayEvent])> {
        self.vehicles
            .iter()
            .map(|(id, events)| (id.as_str(), events.as_slice()))
    }

    /// A vehicle's final detections, one per row that got one, in row order.
    pub fn detections<'a>(
        &'a self,
        vehicle_id: &str,
    ) -> impl Iterator<Item = &'a ReplayedDetection> + 'a {
        self.vehicles
            .get(vehicle_id)
            .into_iter()
            .flatten()
            .filter_map(|event| match event {
                ReplayEvent::Detection(d) => Some(d),
                _ => None,
            })
    }
}

/// The record an event is about, for detections and refusals.
fn row_index(event: &ReplayEvent) -> Option<usize> {
    match event {
        ReplayEvent::Detection(d) => Some(d.index),
        ReplayEvent::ItemError { index, .. } => Some(*index),
        ReplayEvent::Accepted { .. } | ReplayEvent::Failover { .. } => None,
    }
}

#[cfg(test)]
mod tests {
    use spoofwatch_proto::v1;

    use super::*;

    fn detection(index: usize, probability: f64) -> ReplayEvent {
        ReplayEvent::Detection(ReplayedDetection {
            vehicle_id: "car".into(),
            index,
            detection: v1::Detection {
                probability,
                ..v1::Detection::default()
            },
            ..ReplayedDetection::default()
        })
    }

    fn failover(resend_from: usize) -> ReplayEvent {
        ReplayEvent::Failover {
            vehicle_id: "car".into(),
            stream: 1,
            accepted: v1::SessionAccepted::default(),
            resend_from,
            replies_lost: 0,
            replies_recovered: 0,
        }
    }

    fn final_rows(log: &ReplayLog) -> Vec<(usize, f64)> {
        log.detections("car")
            .map(|d| (d.index, d.detection.probability))
            .collect()
    }

    #[test]
    fn resent_rows_replace_the_ones_received_before() {
        let mut log = ReplayLog::default();
        for event in [
            detection(0, 0.1),
            detection(1, 0.2),
            detection(2, 0.3),
            // Resumed at row 1: rows 1 and 2 come again.
            failover(1),
            detection(1, 0.4),
            detection(2, 0.5),
            detection(3, 0.6),
            // A fresh replica: everything again.
            failover(0),
            detection(0, 0.7),
        ] {
            log.record(event);
        }
        assert_eq!(final_rows(&log), vec![(0, 0.7)]);
        log.record(detection(1, 0.8));
        assert_eq!(final_rows(&log), vec![(0, 0.7), (1, 0.8)]);
        let failovers = log
            .vehicles()
            .flat_map(|(_, events)| events.iter())
            .filter(|e| matches!(e, ReplayEvent::Failover { .. }))
            .count();
        assert_eq!(failovers, 2, "failovers stay in the log");
    }

    #[test]
    fn a_failover_after_every_row_was_answered_drops_nothing() {
        let mut log = ReplayLog::default();
        log.record(detection(0, 0.1));
        log.record(failover(1));
        assert_eq!(final_rows(&log), vec![(0, 0.1)]);
    }
}
