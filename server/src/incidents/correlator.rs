//! The server's incident correlator: while this process holds the database's correlator lease, it
//! reads the alarm event log (every replica's alarms) after the correlator's place, feeds each
//! onset and end to the core's [`AreaCorrelator`], and stores every step fenced on the lease
//! (`Store::write_correlation_step`). Every process runs one; one computes at a time, and when it
//! stops (or is killed) another takes the lease over within [`LEASE`] and continues from the stored
//! place and state, exactly.
//!
//! Alarms are placed on the incident timeline (`super::settings::IncidentTimeline`): the servers' wall clock at onset and
//! end by default, or the vehicles' own sample times for replays of recordings on one common clock.
//! Alarms stored before onsets kept their place (schema version 8) take no part.
//!
//! An incident an admin ended by hand (`super::service::end`, stored outside the lease) leaves the
//! correlator's state at the start of its next step ([`AreaCorrelator::forget`]); the store never
//! lets a step write to it again, so a step computed before the end cannot reopen it.
//!
//! It owns the lease loop and the mapping from stored alarm events to the correlator's input. It
//! must not serve the API (`super::service`) nor decide what makes an incident (the core does).

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use spoofwatch_core::geo::LatLon;
use spoofwatch_core::incident::{
    AlarmEnd, AlarmOnset, AreaCorrelator, AreaState, ChangeKind, Incident, IncidentChange,
};
use tokio::sync::Notify;
use tokio::time::MissedTickBehavior;
use tokio_util::sync::CancellationToken;

use super::areas::IncidentAreas;
use super::settings::{IncidentSettings, IncidentTimeline as Timeline};
use crate::store::{
    AlarmEventKind, AlarmEventRow, CorrelationStep, CorrelatorPlace, IncidentEventKind,
    IncidentWrite, LoggedAlarmEvent, Store, StoreError, StoredCredential, now_unix_ms,
};
use crate::telemetry;

/// How often the holder correlates new alarm events and renews its lease.
pub const TICK: Duration = Duration::from_secs(1);
/// A holder that has not renewed the lease for this long has lost it to any other process.
pub const LEASE: Duration = Duration::from_secs(10);
/// Alarm events read per step.
const PAGE: u32 = 1_000;

/// The correlator loop of one server process.
pub struct IncidentCorrelator {
    store: Store,
    settings: IncidentSettings,
    /// This process's lease holder name: the instance id plus what tells apart two servers of one
    /// host (or one test process).
    owner: String,
    /// While holding: the latest alarm time seen and the wall clock when it was seen, so that the
    /// timeline goes on between alarms.
    latest: Option<(f64, i64)>,
    /// Told after a step stored incident events (the live feed reads them at once).
    stored: Arc<Notify>,
    /// The open incidents' areas this server's sessions score with (refreshed every tick, held or
    /// not).
    areas: Arc<IncidentAreas>,
    /// [`LEASE`] (shorter in tests).
    lease: Duration,
}

/// The input an alarm event gives the correlator.
enum Input {
    Onset(AlarmOnset),
    End(AlarmEnd),
}

impl IncidentCorrelator {
    pub fn new(
        store: Store,
        settings: IncidentSettings,
        instance: &str,
        stored: Arc<Notify>,
        areas: Arc<IncidentAreas>,
    ) -> Self {
        static STARTED: AtomicU64 = AtomicU64::new(0);
        let owner = format!(
            "{instance}#{}.{}",
            std::process::id(),
            STARTED.fetch_add(1, Ordering::Relaxed)
        );
        Self {
            store,
            settings,
            owner,
            latest: None,
            stored,
            areas,
            lease: LEASE,
        }
    }

    /// Correlates every [`TICK`] until `stop`, then gives the lease up. A failed step is logged
    /// once per outage and retried on the next tick.
    pub async fn run(mut self, stop: CancellationToken) {
        let mut tick = tokio::time::interval(TICK);
        tick.set_missed_tick_behavior(MissedTickBehavior::Delay);
        let mut failing = false;
        loop {
            tokio::select! {
                biased;
                _ = stop.cancelled() => break,
                _ = tick.tick() => {}
            }
            // Every server reads the open incidents' areas, whether it holds the lease or not.
            let result = match self.step().await {
                Ok(()) => self.refresh_areas().await,
                Err(error) => Err(error),
            };
            match result {
                Ok(()) if failing => {
                    failing = false;
                    tracing::info!("incident correlation recovered");
                }
                Ok(()) => {}
                Err(error) if !failing => {
                    failing = true;
                    tracing::warn!(%error, "incident correlation failed; retrying every second");
                }
                Err(_) => {}
            }
        }
        if self.latest.is_some()
            && let Err(error) = self.store.release_incident_correlator(&self.owner).await
        {
            tracing::warn!(%error, "could not give the incident correlator's lease up");
        }
    }

    /// Reads the open incidents into the areas the sessions score with.
    async fn refresh_areas(&self) -> Result<(), StoreError> {
        refresh_areas(&self.store, &self.areas).await
    }

    /// Drops from `correlator` the open incidents an admin ended by hand since its state was
    /// stored (`super::service::end`): the store already holds their end.
    async fn forget_closed(&self, correlator: &mut AreaCorrelator) -> Result<(), StoreError> {
        let open = correlator.open_incidents();
        let (Some(first), Some(last)) = (open.first(), open.last()) else {
            return Ok(());
        };
        let id = |incident: &Incident| i64::try_from(incident.id).unwrap_or(i64::MAX);
        let closed: Vec<u64> = self
            .store
            .closed_incidents_among(id(first), id(last))
            .await?
            .into_iter()
            .filter_map(|id| u64::try_from(id).ok())
            .collect();
        for incident in correlator.forget(&closed) {
            tracing::debug!(
                incident = incident.id,
                "the correlator let go of an incident ended by hand"
            );
        }
        Ok(())
    }

    /// One step: claim (or renew) the lease; if held, correlate the alarm events stored since the
    /// correlator's place and store the result.
    pub async fn step(&mut self) -> Result<(), StoreError> {
        let now_ms = now_unix_ms();
        let lease_ms = self.lease.as_millis() as i64;
        let Some(place) = self
            .store
            .claim_incident_correlator(&self.owner, now_ms, lease_ms)
            .await?
        else {
            self.lose_lease();
            return Ok(());
        };
        let state = match place.state {
            Some(json) => serde_json::from_value::<AreaState>(json).map_err(|error| {
                StoreError::InvalidValue {
                    field: "incident_correlator.state_json",
                    reason: error.to_string(),
                }
            })?,
            None => AreaCorrelator::new(self.settings.area).state().clone(),
        };
        let mut correlator = AreaCorrelator::resume(self.settings.area, state);
        self.forget_closed(&mut correlator).await?;
        if self.latest.is_none() {
            tracing::info!(
                owner = %self.owner,
                alarm_position = place.alarm_position,
                open_incidents = correlator.open_incidents().len(),
                "this server now correlates area incidents"
            );
            telemetry::incident_correlator_held(true);
            self.latest = Some((correlator.state().now_s, now_ms));
        }
        let events = self
            .store
            .alarm_events_after(place.alarm_position, i64::MAX, None, PAGE)
            .await?;
        let mut position = place.alarm_position;
        let mut changes = Vec::new();
        for logged in &events {
            position = logged.position;
            match self.input(logged, now_ms) {
                Some(Input::Onset(onset)) => changes.extend(correlator.onset(onset)),
                Some(Input::End(end)) => changes.extend(correlator.end(&end)),
                None => {}
            }
        }
        changes.extend(correlator.advance(self.timeline_now(now_ms)));
        let step = CorrelationStep {
            incidents: changes.iter().map(write_of).collect::<Result<_, _>>()?,
            place: CorrelatorPlace {
                alarm_position: position,
                state: Some(serde_json::to_value(correlator.state()).map_err(|error| {
                    StoreError::InvalidValue {
                        field: "incident_correlator.state_json",
                        reason: error.to_string(),
                    }
                })?),
            },
        };
        if !self
            .store
            .write_correlation_step(&self.owner, now_unix_ms(), &step)
            .await?
        {
            self.lose_lease();
            return Ok(());
        }
        if step.incidents.iter().any(|write| write.event.is_some()) {
            self.stored.notify_one();
        }
        for change in &changes {
            report(change);
        }
        Ok(())
    }

    fn lose_lease(&mut self) {
        if self.latest.take().is_some() {
            tracing::info!(owner = %self.owner, "another server correlates area incidents now");
            telemetry::incident_correlator_held(false);
        }
    }

    /// Where "now" is on the timeline: the wall clock, or the latest alarm's sample time moved on
    /// by the wall-clock time since it was seen.
    fn timeline_now(&self, now_ms: i64) -> f64 {
        match self.settings.timeline {
            Timeline::Wall => now_ms as f64 / 1000.0,
            Timeline::Samples => {
                let (time_s, seen_ms) = self.latest.unwrap_or((0.0, now_ms));
                time_s + (now_ms - seen_ms).max(0) as f64 / 1000.0
            }
        }
    }

    /// `logged` as the correlator's input, on the timeline; `None` for an onset stored without its
    /// place or explanation, and for an escalation (an area incident rests on where alarms start
    /// and end; how loud one became is no evidence of where).
    fn input(&mut self, logged: &LoggedAlarmEvent, now_ms: i64) -> Option<Input> {
        let alarm = &logged.event.alarm;
        let timeline = self.settings.timeline;
        let time_s = match (logged.event.kind, timeline) {
            (AlarmEventKind::Escalated, _) => return None,
            (AlarmEventKind::Onset, Timeline::Wall) => alarm.onset_at_ms as f64 / 1000.0,
            (AlarmEventKind::Onset, Timeline::Samples) => alarm.onset_timestamp_s,
            (AlarmEventKind::End, Timeline::Wall) => {
                alarm.ended_at_ms.unwrap_or(now_ms) as f64 / 1000.0
            }
            // An alarm closed because its session stopped has no end sample: it ends now.
            (AlarmEventKind::End, Timeline::Samples) => alarm
                .end_timestamp_s
                .unwrap_or_else(|| self.timeline_now(now_ms)),
        };
        if timeline == Timeline::Samples && self.latest.is_some_and(|(t, _)| time_s > t) {
            self.latest = Some((time_s, now_ms));
        }
        match logged.event.kind {
            AlarmEventKind::Onset => {
                let why = &alarm.why;
                let place = &alarm.place;
                Some(Input::Onset(AlarmOnset {
                    vehicle_id: alarm.vehicle_id.clone(),
                    alarm_id: alarm.id,
                    time_s,
                    fix: LatLon::new(place.onset_latitude_deg?, place.onset_longitude_deg?),
                    offset_m: [why.why_offset_east_m?, why.why_offset_north_m?],
                    drift_mps: [why.why_drift_east_mps?, why.why_drift_north_mps?],
                    credential: alarm.credential.credential.clone(),
                    source: source_of(alarm),
                }))
            }
            AlarmEventKind::End => Some(Input::End(AlarmEnd {
                vehicle_id: alarm.vehicle_id.clone(),
                alarm_id: alarm.id,
                time_s,
            })),
            AlarmEventKind::Escalated => None,
        }
    }
}

/// Reads the store's open incidents into `areas` (the area prior every session scores with): each
/// server's correlator loop once a tick, and the server that ended an incident by hand at once.
pub async fn refresh_areas(store: &Store, areas: &IncidentAreas) -> Result<(), StoreError> {
    let open = store.open_incidents().await?;
    let incidents = open
        .into_iter()
        .map(|row| {
            serde_json::from_value::<Incident>(row.body).map_err(|error| StoreError::InvalidValue {
                field: "incidents.body_json",
                reason: error.to_string(),
            })
        })
        .collect::<Result<Vec<_>, _>>()?;
    areas.replace(&incidents);
    Ok(())
}

/// A change as the store writes it.
fn write_of(change: &IncidentChange) -> Result<IncidentWrite, StoreError> {
    let event = match change.kind {
        ChangeKind::Opened => Some(IncidentEventKind::Opened),
        ChangeKind::Joined => Some(IncidentEventKind::Joined),
        ChangeKind::Evidence => None,
        ChangeKind::Ended => Some(IncidentEventKind::Ended),
    };
    Ok(IncidentWrite {
        id: i64::try_from(change.incident.id).unwrap_or(i64::MAX),
        event,
        ended: !change.incident.is_open(),
        body: serde_json::to_value(&change.incident).map_err(|error| StoreError::InvalidValue {
            field: "incidents.body_json",
            reason: error.to_string(),
        })?,
    })
}

/// The independent source an alarm counts as: its credential, or its vehicle under that
/// credential when each of the credential's vehicles is its own source (a gateway forwarding
/// independent receivers, a server without identities); its vehicle alone when it was stored
/// without a credential.
fn source_of(alarm: &AlarmEventRow) -> String {
    match &alarm.credential {
        StoredCredential {
            credential: Some(credential),
            credential_per_vehicle: false,
        } => credential.clone(),
        StoredCredential {
            credential: Some(credential),
            credential_per_vehicle: true,
        } => format!("{credential} / vehicle {}", alarm.vehicle_id),
        StoredCredential {
            credential: None, ..
        } => format!("vehicle {}", alarm.vehicle_id),
    }
}

/// The log line and metrics of a stored change.
fn report(change: &IncidentChange) {
    let incident = &change.incident;
    let vehicles = incident.vehicles.len();
    let latest = incident.vehicles.last().map(|v| v.vehicle_id.as_str());
    match change.kind {
        ChangeKind::Opened => {
            telemetry::incident_opened();
            tracing::warn!(
                incident = incident.id,
                spoofing = incident.spoofing.name(),
                vehicles,
                sources = incident.source_count(),
                credentials = ?incident.credentials(),
                centre_lat = incident.centre.lat_deg,
                centre_lon = incident.centre.lon_deg,
                radius_m = incident.radius_m.round(),
                confidence = incident.confidence,
                "area incident opened: vehicles nearby are spoofed alike"
            );
        }
        ChangeKind::Joined => {
            telemetry::incident_vehicle_joined();
            tracing::info!(
                incident = incident.id,
                vehicle = latest,
                vehicles,
                "a vehicle joined an area incident"
            );
        }
        ChangeKind::Evidence => {}
        ChangeKind::Ended => {
            telemetry::incident_ended();
            tracing::info!(
                incident = incident.id,
                vehicles,
                "area incident ended: no vehicle of it has alarmed for the quiet time"
            );
        }
    }
}

#[cfg(test)]
mod tests {
    use spoofwatch_core::explain::{EvidenceKind, Explanation};
    use spoofwatch_core::geo::displace_fix;
    use spoofwatch_core::incident::AreaConfig;
    use spoofwatch_proto::v1;

    use super::*;
    use crate::alarms::event::{Onset, OnsetWhy};
    use crate::incidents::service;
    use crate::outbox::SessionOutbox;

    /// Queues the onset of a vehicle `east_m` east of a city centre whose fix is displaced 150 m
    /// north, and stores it.
    async fn displaced_onset(store: &Store, vehicle: &str, east_m: f64) {
        let outbox = SessionOutbox::new(store, 10).await.expect("outbox");
        let (lat, lon) = displace_fix(32.2, -110.9, east_m, 150.0);
        let explanation = Explanation {
            dominant: EvidenceKind::Jump,
            offset_m: [0.0, 150.0],
            drift_rate_mps: [0.0, 0.0],
        };
        outbox.onset(&Onset {
            why: Some(OnsetWhy {
                explanation: &explanation,
                fix: LatLon::new(lat, lon),
            }),
            ..Onset::warning(vehicle, "m", 1.0, now_unix_ms(), 0.9)
        });
        let stop = CancellationToken::new();
        stop.cancel();
        outbox
            .run(store.clone(), stop, Duration::from_secs(1))
            .await;
    }

    fn correlator(store: &Store, instance: &str) -> IncidentCorrelator {
        let settings = IncidentSettings {
            area: AreaConfig::default(),
            timeline: Timeline::Wall,
            prior: true,
        };
        let mut correlator = IncidentCorrelator::new(
            store.clone(),
            settings,
            instance,
            Arc::new(Notify::new()),
            Arc::new(IncidentAreas::new(true)),
        );
        correlator.lease = Duration::from_millis(200);
        correlator
    }

    async fn incidents(store: &Store) -> Vec<(i64, i32, usize)> {
        let listed = service::list(store, &v1::ListIncidentsRequest::default())
            .await
            .expect("listed");
        listed
            .incidents
            .iter()
            .map(|i| (i.id, i.kind, i.vehicles.len()))
            .collect()
    }

    /// Three replicas' worth of alarms (stored by three outboxes) open one incident on the lease
    /// holder; another server does nothing while the lease is held, and once the holder is gone
    /// (dropped without giving the lease up, as a killed process) it continues the same incident.
    #[tokio::test]
    async fn one_holder_correlates_and_another_continues_after_it_is_gone() {
        let dir = tempfile::tempdir().expect("temp dir");
        let store = Store::open(&dir.path().join("i.db").to_string_lossy())
            .await
            .expect("open");
        let translation = v1::IncidentKind::Translation as i32;
        let mut first = correlator(&store, "first");
        let mut second = correlator(&store, "second");
        for (vehicle, east_m) in [("car-1", 0.0), ("car-2", 2_000.0)] {
            displaced_onset(&store, vehicle, east_m).await;
        }
        first.step().await.expect("step");
        assert!(
            incidents(&store).await.is_empty(),
            "two vehicles are not an incident"
        );
        displaced_onset(&store, "car-3", 4_000.0).await;
        second.step().await.expect("step");
        assert!(
            incidents(&store).await.is_empty(),
            "the second does not hold the lease"
        );
        first.step().await.expect("step");
        assert_eq!(incidents(&store).await, [(1, translation, 3)]);
        // Every server reads the open incident's area (centre 2 km east, radius 3 km), holder or
        // not: its sessions score with the area prior there.
        second.refresh_areas().await.expect("areas");
        assert!(second.areas.contains(32.2, -110.9), "inside the area");
        let (lat, lon) = displace_fix(32.2, -110.9, 6_000.0, 0.0);
        assert!(!second.areas.contains(lat, lon), "4 km from its centre");

        drop(first);
        tokio::time::sleep(Duration::from_millis(250)).await;
        displaced_onset(&store, "car-4", 6_000.0).await;
        second.step().await.expect("step");
        assert_eq!(incidents(&store).await, [(1, translation, 4)]);
        let kinds: Vec<_> = store
            .incident_events_after(0, i64::MAX, 10)
            .await
            .expect("events")
            .iter()
            .map(|e| e.kind)
            .collect();
        assert_eq!(
            kinds,
            [IncidentEventKind::Opened, IncidentEventKind::Joined]
        );
    }

    /// An admin ends the open incident through another server: its area leaves that server's
    /// prior before the call returns; the holder's next step forgets it and writes nothing more
    /// to it; the same vehicles' new alarms (new evidence) open a new incident.
    #[tokio::test]
    async fn an_incident_ended_by_hand_is_forgotten_and_new_alarms_open_another() {
        let dir = tempfile::tempdir().expect("temp dir");
        let store = Store::open(&dir.path().join("e.db").to_string_lossy())
            .await
            .expect("open");
        let translation = v1::IncidentKind::Translation as i32;
        let mut holder = correlator(&store, "holder");
        let other = correlator(&store, "other");
        let vehicles = [("car-1", 0.0), ("car-2", 2_000.0), ("car-3", 4_000.0)];
        for (vehicle, east_m) in vehicles {
            displaced_onset(&store, vehicle, east_m).await;
        }
        holder.step().await.expect("step");
        assert_eq!(incidents(&store).await, [(1, translation, 3)]);
        other.refresh_areas().await.expect("areas");
        assert!(other.areas.contains(32.2, -110.9));

        let ender = service::Ender {
            by: "token ops sha256:0123456789abcdef",
            timeline: Timeline::Wall,
            areas: &other.areas,
            stored: &Notify::new(),
        };
        let request = v1::EndIncidentRequest {
            id: 1,
            reason: "  the jammer was switched off ".into(),
            dismiss: false,
        };
        let ended = service::end(&store, &request, &ender).await.expect("ended");
        assert!(!ended.open && ended.ended_s.is_some(), "{ended:?}");
        let closure = ended.closure.clone().expect("a closure");
        assert_eq!(
            (
                closure.kind(),
                closure.reason.as_str(),
                closure.closed_by.as_str()
            ),
            (
                v1::IncidentClosureKind::Ended,
                "the jammer was switched off",
                "token ops sha256:0123456789abcdef"
            )
        );
        assert!(
            !other.areas.contains(32.2, -110.9),
            "the prior stops at once"
        );
        let refused = service::end(&store, &request, &ender)
            .await
            .expect_err("already ended");
        assert_eq!(refused.code(), tonic::Code::FailedPrecondition);

        holder.step().await.expect("step");
        let get = async |id| {
            service::get(&store, &v1::GetIncidentRequest { id })
                .await
                .expect("stored")
        };
        assert_eq!(get(1).await, ended, "nothing more is written");
        for (vehicle, east_m) in vehicles {
            displaced_onset(&store, vehicle, east_m).await;
        }
        holder.step().await.expect("step");
        assert_eq!(
            incidents(&store).await,
            [(1, translation, 3), (2, translation, 3)]
        );
        assert!(get(2).await.open);
    }
}
