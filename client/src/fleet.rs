//! The fleet summary of a replay (`spoofwatch detect`, and the clean-fleet check): vehicles,
//! samples, attack-free hours, reconnects and GNSS gaps, and every alarm onset on an attack-free
//! row classified by where it starts — within 30 s of a session (stream) start, within 30 s after
//! a GNSS gap, or elsewhere — so that alarm storms at reconnects and tunnels show up as such.
//! Onsets on attacked rows are counted apart, as detections. The alarms that turned critical (the
//! paging level: an onset that was critical at once, or an escalation) are counted the same way,
//! by where they turned critical.
//!
//! It owns the tally and the onset classification and reads nothing but [`ReplayEvent`]s. It must
//! not talk to the server, read files or print: the commands and tests do.

use std::collections::BTreeMap;

use serde::Serialize;
use spoofwatch_core::evidence::MAX_GAP_S;

use crate::replay::{ReplayEvent, ReplayedDetection};

/// An onset at most this long after a session (stream) start is "at the session start".
pub const SESSION_START_WINDOW_S: f64 = 30.0;
/// An onset at most this long after the first sample past a GNSS gap is "after the gap".
pub const AFTER_GAP_WINDOW_S: f64 = 30.0;
/// How many vehicles the summary lists as the worst.
pub const WORST_VEHICLES: usize = 10;

const SECONDS_PER_HOUR: f64 = 3600.0;

/// Where a false alarm starts.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum OnsetPlace {
    /// Within [`SESSION_START_WINDOW_S`] of the start of the stream that carried it.
    SessionStart,
    /// Within [`AFTER_GAP_WINDOW_S`] after a step of more than 5 s between samples.
    AfterGap,
    /// Anywhere else.
    Elsewhere,
}

/// Where an onset at replayed time `t` starts, given the vehicle's latest stream start and latest
/// gap end (its first sample after the gap), both at or before `t`. When both are within their
/// window the nearer one is the cause. A tie (a link that dropped during a GNSS gap reconnects on
/// the gap's first sample) goes to the gap: a reconnect resumes the session's detector, while a gap
/// always starts a new trajectory.
pub fn classify_onset(t: f64, stream_start_s: Option<f64>, gap_end_s: Option<f64>) -> OnsetPlace {
    let within = |since: Option<f64>, window: f64| {
        since
            .map(|s| t - s)
            .filter(|elapsed| (0.0..=window).contains(elapsed))
    };
    match (
        within(stream_start_s, SESSION_START_WINDOW_S),
        within(gap_end_s, AFTER_GAP_WINDOW_S),
    ) {
        (Some(after_start), Some(after_gap)) if after_gap <= after_start => OnsetPlace::AfterGap,
        (Some(_), _) => OnsetPlace::SessionStart,
        (None, Some(_)) => OnsetPlace::AfterGap,
        (None, None) => OnsetPlace::Elsewhere,
    }
}

/// False-alarm onsets by where they start.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
pub struct OnsetCounts {
    pub session_start: u64,
    pub after_gap: u64,
    pub elsewhere: u64,
}

impl OnsetCounts {
    pub fn total(&self) -> u64 {
        self.session_start + self.after_gap + self.elsewhere
    }

    fn add(&mut self, place: OnsetPlace) {
        match place {
            OnsetPlace::SessionStart => self.session_start += 1,
            OnsetPlace::AfterGap => self.after_gap += 1,
            OnsetPlace::Elsewhere => self.elsewhere += 1,
        }
    }

    fn add_all(&mut self, other: &OnsetCounts) {
        self.session_start += other.session_start;
        self.after_gap += other.after_gap;
        self.elsewhere += other.elsewhere;
    }
}

/// One false-alarm onset.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct FalseAlarm {
    /// 1-based line of its record.
    pub line: u64,
    /// The record's own timestamp.
    pub recorded_timestamp_s: f64,
    pub place: OnsetPlace,
    /// Which of the vehicle's streams carried it (0 = the first).
    pub stream: u32,
    /// That stream resumed the session: the detector went on as if no reconnect had happened, so
    /// an onset soon after it is not the reconnect's doing.
    pub on_resumed_stream: bool,
    /// Seconds since the start of the stream that carried it.
    pub after_stream_start_s: f64,
    /// Seconds since the latest gap ended, if the vehicle had one.
    pub after_gap_s: Option<f64>,
}

/// What one vehicle's replay showed.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct VehicleTally {
    pub vehicle_id: String,
    /// Samples with a detection.
    pub samples: u64,
    /// Sum of the steps of at most 5 s that end on an attack-free (label 0) row.
    pub attack_free_s: f64,
    /// Streams opened (1 + reconnects).
    pub streams: u32,
    /// Reconnects on which the server resumed the session.
    pub resumed_reconnects: u32,
    /// Streams reopened after a failure (a replica went away).
    pub failovers: u32,
    /// Of the failovers, those the server answered with the session started afresh under another
    /// model (a roll-out: `SessionAccepted.replaced_model`).
    pub failovers_onto_another_model: u32,
    /// Samples the server applied whose replies were lost with a failed stream.
    pub replies_lost: u64,
    /// Steps of more than 5 s between consecutive samples.
    pub gaps: u64,
    pub false_alarms: OnsetCounts,
    pub false_alarm_onsets: Vec<FalseAlarm>,
    /// Alarms that turned critical on attack-free rows, by where they turned critical.
    pub critical_false_alarms: OnsetCounts,
    /// Onsets on attacked (label 1) rows.
    pub detections: u64,
    /// Alarms that turned critical on attacked rows.
    pub critical_detections: u64,
    /// Onsets on unlabelled rows (neither false alarms nor detections).
    pub unlabelled_onsets: u64,
    #[serde(skip)]
    previous_t: Option<f64>,
    #[serde(skip)]
    stream_start_s: Option<f64>,
    #[serde(skip)]
    stream_resumed: bool,
    #[serde(skip)]
    gap_end_s: Option<f64>,
}

impl VehicleTally {
    fn new(vehicle_id: &str) -> Self {
        Self {
            vehicle_id: vehicle_id.to_string(),
            ..Self::default()
        }
    }

    /// Takes the vehicle's next detection (in sample order). Time is the replayed timestamp the
    /// server saw, so a recorded trajectory break counts as the gap it became.
    pub fn push(&mut self, d: &ReplayedDetection) {
        let t = d.detection.timestamp_s;
        self.samples += 1;
        if d.first_on_stream {
            self.stream_start_s = Some(t);
        }
        if let Some(previous) = self.previous_t {
            let step = t - previous;
            if step > MAX_GAP_S {
                self.gaps += 1;
                self.gap_end_s = Some(t);
            } else if d.label == Some(false) && step > 0.0 {
                self.attack_free_s += step;
            }
        }
        self.previous_t = Some(t);
        if d.detection.alarm_escalated {
            match d.label {
                Some(false) => self.critical_false_alarms.add(classify_onset(
                    t,
                    self.stream_start_s,
                    self.gap_end_s,
                )),
                Some(true) => self.critical_detections += 1,
                None => {}
            }
        }
        if !d.detection.alarm_onset {
            return;
        }
        match d.label {
            Some(false) => {
                let place = classify_onset(t, self.stream_start_s, self.gap_end_s);
                self.false_alarms.add(place);
                self.false_alarm_onsets.push(FalseAlarm {
                    line: d.line,
                    recorded_timestamp_s: d.recorded_timestamp_s,
                    place,
                    stream: d.stream,
                    on_resumed_stream: self.stream_resumed,
                    after_stream_start_s: self.stream_start_s.map_or(f64::NAN, |s| t - s),
                    after_gap_s: self.gap_end_s.map(|g| t - g),
                });
            }
            Some(true) => self.detections += 1,
            None => self.unlabelled_onsets += 1,
        }
    }

    /// Attack-free hours.
    pub fn attack_free_hours(&self) -> f64 {
        self.attack_free_s / SECONDS_PER_HOUR
    }
}

/// The running tally of a replay, one [`VehicleTally`] per vehicle id.
#[derive(Clone, Debug, Default)]
pub struct FleetTally {
    vehicles: BTreeMap<String, VehicleTally>,
}

impl FleetTally {
    /// Takes one replay event (events of one vehicle in the order the replay sent them).
    pub fn record(&mut self, event: &ReplayEvent) {
        match event {
            ReplayEvent::Accepted {
                vehicle_id,
                stream,
                accepted,
            } => {
                let vehicle = self.vehicle(vehicle_id);
                vehicle.streams += 1;
                vehicle.stream_resumed = *stream > 0 && accepted.resumed;
                vehicle.resumed_reconnects += u32::from(vehicle.stream_resumed);
            }
            ReplayEvent::Failover {
                vehicle_id,
                accepted,
                replies_lost,
                replies_recovered,
                ..
            } => {
                let vehicle = self.vehicle(vehicle_id);
                vehicle.replies_lost =
                    (vehicle.replies_lost + replies_lost).saturating_sub(*replies_recovered);
                vehicle.streams += 1;
                vehicle.failovers += 1;
                vehicle.failovers_onto_another_model +=
                    u32::from(!accepted.resumed && !accepted.replaced_model.is_empty());
                vehicle.stream_resumed = accepted.resumed;
                vehicle.resumed_reconnects += u32::from(accepted.resumed);
            }
            ReplayEvent::Detection(d) => self.vehicle(&d.vehicle_id).push(d),
            ReplayEvent::ItemError { .. } => {}
        }
    }

    fn vehicle(&mut self, vehicle_id: &str) -> &mut VehicleTally {
        self.vehicles
            .entry(vehicle_id.to_string())
            .or_insert_with(|| VehicleTally::new(vehicle_id))
    }

    /// The fleet's totals and its [`WORST_VEHICLES`] worst vehicles (most false alarms first).
    pub fn summary(&self) -> FleetSummary {
        let mut summary = FleetSummary {
            vehicles: self.vehicles.len(),
            session_start_window_s: SESSION_START_WINDOW_S,
            after_gap_window_s: AFTER_GAP_WINDOW_S,
            gap_step_s: MAX_GAP_S,
            ..FleetSummary::default()
        };
        let mut attack_free_s = 0.0;
        for v in self.vehicles.values() {
            summary.samples += v.samples;
            attack_free_s += v.attack_free_s;
            summary.streams += u64::from(v.streams);
            summary.reconnects += u64::from(v.streams.saturating_sub(1));
            summary.resumed_reconnects += u64::from(v.resumed_reconnects);
            summary.failovers += u64::from(v.failovers);
            summary.failovers_onto_another_model += u64::from(v.failovers_onto_another_model);
            summary.replies_lost += v.replies_lost;
            summary.gaps += v.gaps;
            summary.false_alarms.add_all(&v.false_alarms);
            summary.session_start_onsets_on_resumed_streams += v
                .false_alarm_onsets
                .iter()
                .filter(|o| o.place == OnsetPlace::SessionStart && o.on_resumed_stream)
                .count() as u64;
            summary.vehicles_with_false_alarms += usize::from(v.false_alarms.total() > 0);
            summary.detections += v.detections;
            summary.unlabelled_onsets += v.unlabelled_onsets;
            summary
                .critical_false_alarms
                .add_all(&v.critical_false_alarms);
            summary.critical_detections += v.critical_detections;
        }
        summary.attack_free_hours = attack_free_s / SECONDS_PER_HOUR;
        let per_hour = |count: &OnsetCounts| {
            (summary.attack_free_hours > 0.0)
                .then(|| count.total() as f64 / summary.attack_free_hours)
        };
        summary.false_alarms_per_attack_free_hour = per_hour(&summary.false_alarms);
        summary.critical_false_alarms_per_attack_free_hour =
            per_hour(&summary.critical_false_alarms);
        let mut worst: Vec<&VehicleTally> = self
            .vehicles
            .values()
            .filter(|v| v.false_alarms.total() > 0)
            .collect();
        // Most false alarms first; the BTreeMap order (vehicle id) breaks ties.
        worst.sort_by_key(|v| std::cmp::Reverse(v.false_alarms.total()));
        summary.worst_vehicles = worst
            .into_iter()
            .take(WORST_VEHICLES)
            .map(|v| WorstVehicle {
                vehicle_id: v.vehicle_id.clone(),
                attack_free_hours: v.attack_free_hours(),
                false_alarms: v.false_alarms,
                onsets: v.false_alarm_onsets.clone(),
            })
            .collect();
        summary
    }
}

/// A vehicle with false alarms.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct WorstVehicle {
    pub vehicle_id: String,
    pub attack_free_hours: f64,
    pub false_alarms: OnsetCounts,
    pub onsets: Vec<FalseAlarm>,
}

/// What a fleet replay showed (`detect --summary` writes it as JSON).
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct FleetSummary {
    pub vehicles: usize,
    /// Samples with a detection.
    pub samples: u64,
    /// Sum over vehicles of the steps of at most 5 s that end on an attack-free row.
    pub attack_free_hours: f64,
    /// Streams opened (one per vehicle plus reconnects).
    pub streams: u64,
    pub reconnects: u64,
    /// Reconnects on which the server resumed the vehicle's session.
    pub resumed_reconnects: u64,
    /// Streams reopened after a failure (included in `reconnects`).
    pub failovers: u64,
    /// Failovers onto a session started afresh under another model (a roll-out); the failovers
    /// neither resumed nor rolled over started the vehicle afresh (its session was lost).
    pub failovers_onto_another_model: u64,
    /// Samples the server applied whose replies were lost with a failed stream (no detection for
    /// them in the replay's output).
    pub replies_lost: u64,
    /// Steps of more than `gap_step_s` between a vehicle's consecutive samples.
    pub gaps: u64,
    /// Onsets on attack-free rows, by where they start.
    pub false_alarms: OnsetCounts,
    /// Of `false_alarms.session_start`, those soon after a reconnect that resumed the session
    /// (the detector saw no restart there).
    pub session_start_onsets_on_resumed_streams: u64,
    /// `false_alarms` in total per attack-free hour (`None` without attack-free time).
    pub false_alarms_per_attack_free_hour: Option<f64>,
    pub vehicles_with_false_alarms: usize,
    /// Onsets on attacked rows.
    pub detections: u64,
    /// Onsets on unlabelled rows.
    pub unlabelled_onsets: u64,
    /// Alarms that turned critical (the paging level) on attack-free rows, by where they turned
    /// critical; all zero for a model without a critical level.
    pub critical_false_alarms: OnsetCounts,
    /// `critical_false_alarms` in total per attack-free hour (`None` without attack-free time).
    pub critical_false_alarms_per_attack_free_hour: Option<f64>,
    /// Alarms that turned critical on attacked rows.
    pub critical_detections: u64,
    pub worst_vehicles: Vec<WorstVehicle>,
    /// The classification's windows and gap rule, so a summary file explains itself.
    pub session_start_window_s: f64,
    pub after_gap_window_s: f64,
    pub gap_step_s: f64,
}

#[cfg(test)]
mod tests {
    use spoofwatch_proto::v1;

    use super::*;

    /// A hand-made detection of `vehicle` at replayed time `t` (line = t + 1).
    fn detection(
        vehicle: &str,
        t: f64,
        label: Option<bool>,
        onset: bool,
        first_on_stream: bool,
    ) -> ReplayEvent {
        ReplayEvent::Detection(ReplayedDetection {
            vehicle_id: vehicle.to_string(),
            line: t as u64 + 1,
            recorded_timestamp_s: t,
            label,
            first_on_stream,
            detection: v1::Detection {
                timestamp_s: t,
                alarm_onset: onset,
                alarm: onset,
                ..v1::Detection::default()
            },
            ..ReplayedDetection::default()
        })
    }

    fn accepted(vehicle: &str, stream: u32, resumed: bool) -> ReplayEvent {
        ReplayEvent::Accepted {
            vehicle_id: vehicle.to_string(),
            stream,
            accepted: v1::SessionAccepted {
                resumed,
                ..v1::SessionAccepted::default()
            },
        }
    }

    #[test]
    fn an_onset_is_classified_by_the_nearest_start_or_gap_within_thirty_seconds() {
        let cases = [
            (
                "2 s into the session",
                2.0,
                Some(0.0),
                None,
                OnsetPlace::SessionStart,
            ),
            (
                "30 s is still within",
                30.0,
                Some(0.0),
                None,
                OnsetPlace::SessionStart,
            ),
            (
                "just past 30 s",
                30.5,
                Some(0.0),
                None,
                OnsetPlace::Elsewhere,
            ),
            (
                "2 s after a gap",
                102.0,
                Some(0.0),
                Some(100.0),
                OnsetPlace::AfterGap,
            ),
            (
                "a gap 40 s ago",
                140.0,
                Some(0.0),
                Some(100.0),
                OnsetPlace::Elsewhere,
            ),
            (
                "a reconnect nearer than the gap",
                115.0,
                Some(110.0),
                Some(100.0),
                OnsetPlace::SessionStart,
            ),
            (
                "a gap nearer than the reconnect",
                115.0,
                Some(100.0),
                Some(110.0),
                OnsetPlace::AfterGap,
            ),
            (
                "a reconnect on the gap's first sample",
                105.0,
                Some(100.0),
                Some(100.0),
                OnsetPlace::AfterGap,
            ),
            ("no start known", 5.0, None, None, OnsetPlace::Elsewhere),
        ];
        for (case, t, start, gap, expected) in cases {
            assert_eq!(classify_onset(t, start, gap), expected, "{case}");
        }
    }

    /// One vehicle: 1 Hz from 0 to 99 s, a 21 s gap, 1 Hz from 120 to 199 s with a reconnect at
    /// 150 s and attacked rows from 190 s; onsets at 5, 60, 122, 155, 185 and 192 s.
    fn one_vehicle_events() -> Vec<ReplayEvent> {
        let mut events = vec![accepted("car", 0, false)];
        let times = (0..100).chain(120..200);
        for t in times {
            let t = f64::from(t);
            if t == 150.0 {
                events.push(accepted("car", 1, true));
            }
            let onset = [5.0, 60.0, 122.0, 155.0, 185.0, 192.0].contains(&t);
            let label = Some(t >= 190.0);
            let mut event = detection("car", t, label, onset, t == 0.0 || t == 150.0);
            if let ReplayEvent::Detection(d) = &mut event {
                d.stream = u32::from(t >= 150.0);
            }
            events.push(event);
        }
        events
    }

    #[test]
    fn a_vehicle_tally_sorts_onsets_and_sums_attack_free_time_without_gaps_or_attacks() {
        let mut fleet = FleetTally::default();
        for event in one_vehicle_events() {
            fleet.record(&event);
        }
        let car = &fleet.vehicles["car"];
        assert_eq!(car.samples, 180);
        // 99 steps before the gap, 69 after it up to 189 s; the gap step and the steps onto
        // attacked rows do not count.
        assert_eq!(car.attack_free_s, 168.0);
        assert_eq!((car.streams, car.resumed_reconnects, car.gaps), (2, 1, 1));
        assert_eq!(
            car.false_alarms,
            OnsetCounts {
                session_start: 2,
                after_gap: 1,
                elsewhere: 2
            }
        );
        let places: Vec<(u64, OnsetPlace)> = car
            .false_alarm_onsets
            .iter()
            .map(|o| (o.line, o.place))
            .collect();
        assert_eq!(
            places,
            vec![
                (6, OnsetPlace::SessionStart),
                (61, OnsetPlace::Elsewhere),
                (123, OnsetPlace::AfterGap),
                (156, OnsetPlace::SessionStart),
                (186, OnsetPlace::Elsewhere),
            ]
        );
        assert_eq!(car.false_alarm_onsets[3].after_stream_start_s, 5.0);
        let streams: Vec<(u32, bool)> = car
            .false_alarm_onsets
            .iter()
            .map(|o| (o.stream, o.on_resumed_stream))
            .collect();
        assert_eq!(
            streams,
            vec![(0, false), (0, false), (0, false), (1, true), (1, true)]
        );
        assert_eq!(car.false_alarm_onsets[3].after_gap_s, Some(35.0));
        assert_eq!((car.detections, car.unlabelled_onsets), (1, 0));
    }

    #[test]
    fn the_fleet_summary_adds_vehicles_up_and_lists_the_worst_first() {
        let mut fleet = FleetTally::default();
        let mut events = one_vehicle_events();
        // A quiet vehicle over 3,600 s of attack-free 1 Hz samples, and one with a single onset
        // on an unlabelled row and one at its start.
        events.push(accepted("quiet", 0, false));
        events.extend(
            (0..=3600).map(|t| detection("quiet", f64::from(t), Some(false), false, t == 0)),
        );
        events.push(accepted("van", 0, false));
        events
            .extend((0..=10).map(|t| detection("van", f64::from(t), Some(false), t == 3, t == 0)));
        events.push(detection("van", 11.0, None, true, false));
        for event in &events {
            fleet.record(event);
        }
        let summary = fleet.summary();
        assert_eq!(summary.vehicles, 3);
        assert_eq!(summary.samples, 180 + 3601 + 12);
        assert_eq!(summary.attack_free_hours, (168.0 + 3600.0 + 10.0) / 3600.0);
        assert_eq!(
            (
                summary.streams,
                summary.reconnects,
                summary.resumed_reconnects
            ),
            (4, 1, 1)
        );
        assert_eq!(summary.gaps, 1);
        assert_eq!(summary.false_alarms.total(), 6);
        assert_eq!(summary.false_alarms.session_start, 3);
        assert_eq!(summary.session_start_onsets_on_resumed_streams, 1);
        assert_eq!(
            summary.false_alarms_per_attack_free_hour,
            Some(6.0 / summary.attack_free_hours)
        );
        assert_eq!(summary.vehicles_with_false_alarms, 2);
        assert_eq!((summary.detections, summary.unlabelled_onsets), (1, 1));
        let worst: Vec<(&str, u64)> = summary
            .worst_vehicles
            .iter()
            .map(|v| (v.vehicle_id.as_str(), v.false_alarms.total()))
            .collect();
        assert_eq!(worst, vec![("car", 5), ("van", 1)]);
        let json = serde_json::to_value(&summary).expect("the summary serialises");
        assert_eq!(json["false_alarms"]["after_gap"], 1);
        assert_eq!(
            json["worst_vehicles"][0]["onsets"][0]["place"],
            "session_start"
        );
    }

    #[test]
    fn alarms_that_turn_critical_are_counted_by_where_they_turned_critical() {
        let mut fleet = FleetTally::default();
        fleet.record(&accepted("car", 0, false));
        // Warnings from 5 s and 100 s; the first turns critical at 10 s (within 30 s of the
        // start), the second at 150 s; an attack from 200 s opens critical at once.
        for t in 0..=210 {
            let t = f64::from(t);
            let mut event = detection("car", t, Some(t >= 200.0), false, t == 0.0);
            if let ReplayEvent::Detection(d) = &mut event {
                d.detection.alarm_onset = [5.0, 100.0, 201.0].contains(&t);
                d.detection.alarm_escalated = [10.0, 150.0, 201.0].contains(&t);
            }
            fleet.record(&event);
        }
        let summary = fleet.summary();
        assert_eq!(summary.false_alarms.total(), 2);
        assert_eq!(
            summary.critical_false_alarms,
            OnsetCounts {
                session_start: 1,
                after_gap: 0,
                elsewhere: 1
            }
        );
        assert_eq!(
            summary.critical_false_alarms_per_attack_free_hour,
            Some(2.0 / summary.attack_free_hours)
        );
        assert_eq!((summary.detections, summary.critical_detections), (1, 1));
    }

    #[test]
    fn a_fleet_without_attack_free_time_has_no_false_alarm_rate() {
        let mut fleet = FleetTally::default();
        fleet.record(&detection("car", 0.0, Some(true), true, true));
        let summary = fleet.summary();
        assert_eq!(summary.attack_free_hours, 0.0);
        assert_eq!(summary.false_alarms_per_attack_free_hour, None);
        assert_eq!(summary.detections, 1);
    }

    fn failover(vehicle: &str, replies_lost: u64, replies_recovered: u64) -> ReplayEvent {
        ReplayEvent::Failover {
            vehicle_id: vehicle.to_string(),
            stream: 1,
            accepted: v1::SessionAccepted {
                resumed: true,
                ..v1::SessionAccepted::default()
            },
            resend_from: 0,
            replies_lost,
            replies_recovered,
        }
    }

    #[test]
    fn replies_lost_at_one_failover_and_resent_at_a_later_one_are_not_lost() {
        let mut fleet = FleetTally::default();
        // Five replies lost; a later failover finds the session further back and resends three
        // of them; then two more are lost.
        fleet.record(&failover("car", 5, 0));
        fleet.record(&failover("car", 0, 3));
        fleet.record(&failover("car", 2, 0));
        let summary = fleet.summary();
        assert_eq!(summary.replies_lost, 4);
        assert_eq!(summary.failovers, 3);
        assert_eq!(summary.resumed_reconnects, 3);
    }
}
