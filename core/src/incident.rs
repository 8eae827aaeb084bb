//! Area incidents: the spoofing of a region, seen across vehicles (`docs/detector.md` §11).
//!
//! One transmitter pulls every receiver in its range the same way: to one false position, by one
//! translation, or along one drift. Vehicles whose confirmed alarms start close in time, whose true
//! positions (the fix minus the offset from the dead-reckoning anchor) are near each other, and whose
//! alarms' explanations agree on one of those three, are one incident: an operator acts on "this
//! area is spoofed" rather than on a dozen alarms. Independent false alarms do not agree: their
//! offsets and drifts point anywhere, and an incident needs [`AreaConfig::min_vehicles`] of them to
//! agree within a few tens of metres (or of m/s) at once.
//!
//! Time is one fleet timeline in seconds, given with every event (the server maps each alarm to
//! it). The correlator's state ([`AreaState`]) is a value: it can be stored after every event and
//! continued elsewhere, with the same result.
//!
//! Owns correlating alarm onsets and ends into incidents, and ending them. Must not run detectors,
//! read storage, or know which server saw which vehicle.

use serde::{Deserialize, Serialize};

use crate::geo::{LatLon, displace_fix, wgs84_local_displacement};
use crate::sample::readable;

pub mod areas;

/// Offsets shorter than this (m) say nothing about a false position or a translation: the dead
/// reckoning alone is off by a few metres after a minute, and a false alarm's offset is that small.
pub const MIN_OFFSET_M: f64 = 30.0;
/// Drift rates slower than this (m/s) say nothing about a common drift: the fleet's false alarms
/// read up to about 0.3 m/s, in every direction. (A rate measured at an alarm soon after capture
/// reads a fraction of the spoofer's, its 30 s scale still filling, so agreement is by direction.)
pub const MIN_DRIFT_MPS: f64 = 0.4;
/// A vehicle joins an open drift incident it lies in with a rate of at least this (m/s) pointing
/// the incident's way: alarmed a few seconds into the drift (as the area prior allows), it reads a
/// fraction of the spoofer's. It takes no part in the estimate.
pub const MIN_JOIN_DRIFT_MPS: f64 = 0.15;
/// Fixes that agree on one false position lie within this of each other (m): receiver noise.
pub const POSITION_TOLERANCE_M: f64 = 50.0;
/// Offsets agree on one translation within the larger of this (m) ...
pub const TRANSLATION_TOLERANCE_M: f64 = 20.0;
/// ... and this share of the longer one (the anchor's own error grows with the distance driven).
pub const TRANSLATION_TOLERANCE_SHARE: f64 = 0.2;
/// Drift rates agree on one drift when their directions differ by at most this (degrees).
pub const DRIFT_ANGLE_DEG: f64 = 20.0;

/// How incidents are formed and ended; chosen by the operator.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AreaConfig {
    /// Vehicles correlate when their true positions are within this of each other (m): about the
    /// range of a spoofer.
    pub radius_m: f64,
    /// Alarm onsets correlate when they start within this of each other (s).
    pub window_s: f64,
    /// Vehicles whose onsets must agree before an incident opens.
    pub min_vehicles: u32,
    /// Independent sources (credentials, see [`AlarmOnset::source`]) those vehicles' alarms must
    /// come from: whoever can raise alarms for many vehicle ids under one credential cannot open an
    /// incident alone.
    #[serde(default = "default_min_sources")]
    pub min_sources: u32,
    /// Open incidents one source may take part in at once: beyond it, its onsets join no other
    /// incident and open none (its alarms still alarm), so that one credential cannot spread
    /// incidents, and their area prior, over the fleet.
    #[serde(default = "default_max_incidents_per_source")]
    pub max_incidents_per_source: u32,
    /// An incident ends once none of its vehicles has shown evidence (an open alarm) for this long
    /// (s).
    pub quiet_s: f64,
    /// An incident's area reaches this far beyond its farthest vehicle (m).
    pub margin_m: f64,
}

impl Default for AreaConfig {
    fn default() -> Self {
        Self {
            radius_m: 10_000.0,
            window_s: 300.0,
            min_vehicles: 3,
            min_sources: default_min_sources(),
            max_incidents_per_source: default_max_incidents_per_source(),
            quiet_s: 600.0,
            margin_m: 1_000.0,
        }
    }
}

fn default_min_sources() -> u32 {
    2
}

fn default_max_incidents_per_source() -> u32 {
    3
}

impl AreaConfig {
    /// Every field in its documented range; the error names the field.
    pub fn validate(&self) -> Result<(), (&'static str, String)> {
        let ranges = [
            ("radius_m", self.radius_m, 100.0, 200_000.0, "m"),
            ("window_s", self.window_s, 1.0, 3_600.0, "s"),
            ("quiet_s", self.quiet_s, 0.0, 86_400.0, "s"),
            ("margin_m", self.margin_m, 0.0, 100_000.0, "m"),
        ];
        for (field, value, min, max, unit) in ranges {
            if !(min..=max).contains(&value) {
                return Err((
                    field,
                    format!(
                        "must be finite and in [{min}, {max}] {unit}, got {}",
                        readable(value)
                    ),
                ));
            }
        }
        if !(2..=1_000).contains(&self.min_vehicles) {
            return Err((
                "min_vehicles",
                format!("must be in [2, 1000], got {}", self.min_vehicles),
            ));
        }
        if !(1..=1_000).contains(&self.max_incidents_per_source) {
            return Err((
                "max_incidents_per_source",
                format!(
                    "must be in [1, 1000], got {}",
                    self.max_incidents_per_source
                ),
            ));
        }
        if !(1..=self.min_vehicles).contains(&self.min_sources) {
            return Err((
                "min_sources",
                format!(
                    "must be in [1, min_vehicles = {}], got {}",
                    self.min_vehicles, self.min_sources
                ),
            ));
        }
        Ok(())
    }
}

/// A vehicle's confirmed alarm as it opened.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct AlarmOnset {
    pub vehicle_id: String,
    pub alarm_id: i64,
    /// On the fleet timeline (s).
    pub time_s: f64,
    /// The onset sample's reported fix.
    pub fix: LatLon,
    /// GNSS minus the dead-reckoning anchor, east/north (m): the onset's explanation.
    pub offset_m: [f64; 2],
    /// The drift rate GNSS shows against the onboard motion, east/north (m/s).
    pub drift_mps: [f64; 2],
    /// The credential whose call sent the samples that raised the alarm, as the operator sees it;
    /// `None` when it is not known.
    #[serde(default)]
    pub credential: Option<String>,
    /// The independent source the onset counts as: all onsets of one source are one piece of
    /// evidence, however many vehicle ids they carry. Empty: the vehicle is its own source.
    #[serde(default)]
    pub source: String,
}

impl AlarmOnset {
    /// The independent source it counts as ([`Self::source`], else its vehicle).
    pub fn source_key(&self) -> &str {
        source_key(&self.source, &self.vehicle_id)
    }

    /// Where the vehicle's own motion puts it: the fix moved back by the offset.
    pub fn anchor(&self) -> LatLon {
        let (lat, lon) = displace_fix(
            self.fix.lat_deg,
            self.fix.lon_deg,
            -self.offset_m[0],
            -self.offset_m[1],
        );
        LatLon::new(lat, lon)
    }
}

/// A vehicle's confirmed alarm as it ended.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct AlarmEnd {
    pub vehicle_id: String,
    pub alarm_id: i64,
    /// On the fleet timeline (s).
    pub time_s: f64,
}

/// What the vehicles of an incident agree on.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Spoofing {
    /// Every receiver reports (about) this position, wherever its vehicle is.
    FalsePosition { position: LatLon },
    /// Every fix is displaced by (about) this east/north vector (m).
    Translation { offset_m: [f64; 2] },
    /// Every fix is pulled away at (about) this east/north velocity (m/s).
    Drift { drift_mps: [f64; 2] },
}

impl Spoofing {
    /// The snake_case name (logs, API).
    pub fn name(&self) -> &'static str {
        match self {
            Spoofing::FalsePosition { .. } => "false_position",
            Spoofing::Translation { .. } => "translation",
            Spoofing::Drift { .. } => "drift",
        }
    }
}

/// One vehicle of an incident: its latest alarm and the evidence it joined with.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct IncidentVehicle {
    pub vehicle_id: String,
    /// Its latest alarm inside the incident.
    pub alarm_id: i64,
    /// When its first alarm inside the incident opened (fleet timeline, s).
    pub onset_s: f64,
    /// That alarm's onset fix, offset and drift.
    pub fix: LatLon,
    pub offset_m: [f64; 2],
    pub drift_mps: [f64; 2],
    /// Its latest alarm is still open.
    pub alarm_open: bool,
    /// When it last showed evidence: its latest onset or, once that alarm ended, its end.
    pub last_evidence_s: f64,
    /// The credential of the alarm it joined with ([`AlarmOnset::credential`]).
    #[serde(default)]
    pub credential: Option<String>,
    /// The independent source it counts as ([`AlarmOnset::source`]).
    #[serde(default)]
    pub source: String,
}

impl IncidentVehicle {
    /// Its true position at the onset it joined with.
    pub fn anchor(&self) -> LatLon {
        self.onset().anchor()
    }

    /// The independent source it counts as ([`Self::source`], else its vehicle).
    pub fn source_key(&self) -> &str {
        source_key(&self.source, &self.vehicle_id)
    }

    fn onset(&self) -> AlarmOnset {
        AlarmOnset {
            vehicle_id: self.vehicle_id.clone(),
            alarm_id: self.alarm_id,
            time_s: self.onset_s,
            fix: self.fix,
            offset_m: self.offset_m,
            drift_mps: self.drift_mps,
            credential: self.credential.clone(),
            source: self.source.clone(),
        }
    }
}

/// A spoofed area: where, since when, which vehicles, and what they agree on.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Incident {
    /// Assigned by the correlator: 1, 2, 3, ...
    pub id: u64,
    /// The estimate: the members' median.
    pub spoofing: Spoofing,
    /// The mean of the true positions of the vehicles that opened it: fixed from then on, so that
    /// joins cannot walk the incident across a region (a vehicle joins only within
    /// [`AreaConfig::radius_m`] of it).
    pub centre: LatLon,
    /// The farthest vehicle's distance from the centre plus the margin (m): at most
    /// [`AreaConfig::radius_m`] plus [`AreaConfig::margin_m`].
    pub radius_m: f64,
    /// The earliest member onset (s).
    pub onset_s: f64,
    /// The onset that opened the incident (s).
    pub confirmed_s: f64,
    /// The latest evidence of any member (s).
    pub last_evidence_s: f64,
    /// When it ended (s); `None` while open.
    pub ended_s: Option<f64>,
    /// A score in (0, 1) that grows with the number of agreeing vehicles and the tightness of their
    /// agreement; not a calibrated probability.
    pub confidence: f64,
    /// In joining order.
    pub vehicles: Vec<IncidentVehicle>,
}

impl Incident {
    /// Whether `point` lies inside the incident's area.
    pub fn contains(&self, point: LatLon) -> bool {
        distance_m(self.centre, point) <= self.radius_m
    }

    pub fn is_open(&self) -> bool {
        self.ended_s.is_none()
    }

    /// Ends it by hand at `time_s` (never before its latest evidence): an admin said the threat is
    /// over or was never real. The correlator then [forgets](AreaCorrelator::forget) it.
    pub fn end_by_hand(&mut self, time_s: f64) {
        self.ended_s = Some(time_s.max(self.last_evidence_s));
    }

    /// The distinct credentials behind its members, in joining order (members whose credential is
    /// not known are left out).
    pub fn credentials(&self) -> Vec<&str> {
        let mut credentials: Vec<&str> = Vec::new();
        for credential in self.vehicles.iter().filter_map(|v| v.credential.as_deref()) {
            if !credentials.contains(&credential) {
                credentials.push(credential);
            }
        }
        credentials
    }

    /// How many independent sources its members come from.
    pub fn source_count(&self) -> usize {
        distinct(self.vehicles.iter().map(IncidentVehicle::source_key))
    }
}

/// What happened to an incident.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ChangeKind {
    /// Enough vehicles agreed: it opened.
    Opened,
    /// A vehicle more joined it.
    Joined,
    /// A member's alarm opened again or ended (no new vehicle).
    Evidence,
    /// No member showed evidence for the quiet time.
    Ended,
}

/// An incident as a change left it.
#[derive(Clone, Debug, PartialEq)]
pub struct IncidentChange {
    pub kind: ChangeKind,
    pub incident: Incident,
}

/// The correlator's state: stored after every event and continued elsewhere.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct AreaState {
    /// The next incident's id.
    pub next_id: u64,
    /// The latest time seen (s).
    pub now_s: f64,
    /// Recent onsets not (yet) in an incident, at most one per vehicle (its latest).
    pub pending: Vec<AlarmOnset>,
    /// Open incidents, in id order.
    pub open: Vec<Incident>,
}

/// Correlates the fleet's alarm events into incidents.
#[derive(Clone, Debug)]
pub struct AreaCorrelator {
    config: AreaConfig,
    state: AreaState,
}

/// The three ways of agreeing, tried in this order (the most specific first).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Hypothesis {
    FalsePosition,
    Translation,
    Drift,
}

const HYPOTHESES: [Hypothesis; 3] = [
    Hypothesis::FalsePosition,
    Hypothesis::Translation,
    Hypothesis::Drift,
];

impl Hypothesis {
    /// The onset's value under this hypothesis, as an east/north vector (positions relative to
    /// `reference`); `None` when the onset is too small to say anything about it.
    fn vector(self, onset: &AlarmOnset, reference: LatLon) -> Option<[f64; 2]> {
        match self {
            Hypothesis::FalsePosition | Hypothesis::Translation
                if norm(onset.offset_m) < MIN_OFFSET_M =>
            {
                None
            }
            Hypothesis::FalsePosition => Some(wgs84_local_displacement(reference, onset.fix)),
            Hypothesis::Translation => Some(onset.offset_m),
            Hypothesis::Drift if norm(onset.drift_mps) < MIN_DRIFT_MPS => None,
            Hypothesis::Drift => Some(onset.drift_mps),
        }
    }

    /// As [`Self::vector`], for joining an open incident: a drift needs only
    /// [`MIN_JOIN_DRIFT_MPS`].
    fn joining_vector(self, onset: &AlarmOnset, reference: LatLon) -> Option<[f64; 2]> {
        match self {
            Hypothesis::Drift if norm(onset.drift_mps) >= MIN_JOIN_DRIFT_MPS => {
                Some(onset.drift_mps)
            }
            _ => self.vector(onset, reference),
        }
    }

    /// How far apart `a` and `b` are as a share of what still agrees: at most 1 agrees. Positions
    /// and translations by distance, drifts by direction.
    fn misfit(self, a: [f64; 2], b: [f64; 2]) -> f64 {
        let apart = norm([a[0] - b[0], a[1] - b[1]]);
        match self {
            Hypothesis::FalsePosition => apart / POSITION_TOLERANCE_M,
            Hypothesis::Translation => {
                let longer = norm(a).max(norm(b));
                apart / TRANSLATION_TOLERANCE_M.max(TRANSLATION_TOLERANCE_SHARE * longer)
            }
            Hypothesis::Drift => angle_deg(a, b) / DRIFT_ANGLE_DEG,
        }
    }

    fn of(spoofing: &Spoofing) -> Self {
        match spoofing {
            Spoofing::FalsePosition { .. } => Hypothesis::FalsePosition,
            Spoofing::Translation { .. } => Hypothesis::Translation,
            Spoofing::Drift { .. } => Hypothesis::Drift,
        }
    }

    /// The estimate `vector` (relative to `reference` for a position) as a [`Spoofing`].
    fn spoofing(self, vector: [f64; 2], reference: LatLon) -> Spoofing {
        match self {
            Hypothesis::FalsePosition => {
                let (lat, lon) =
                    displace_fix(reference.lat_deg, reference.lon_deg, vector[0], vector[1]);
                Spoofing::FalsePosition {
                    position: LatLon::new(lat, lon),
                }
            }
            Hypothesis::Translation => Spoofing::Translation { offset_m: vector },
            Hypothesis::Drift => Spoofing::Drift { drift_mps: vector },
        }
    }
}

impl AreaCorrelator {
    /// A correlator with no history.
    pub fn new(config: AreaConfig) -> Self {
        Self::resume(
            config,
            AreaState {
                next_id: 1,
                ..AreaState::default()
            },
        )
    }

    /// Continues from a stored state (under the configuration in force now).
    pub fn resume(config: AreaConfig, state: AreaState) -> Self {
        Self { config, state }
    }

    pub fn state(&self) -> &AreaState {
        &self.state
    }

    /// The open incidents, in id order.
    pub fn open_incidents(&self) -> &[Incident] {
        &self.state.open
    }

    /// A vehicle's alarm opened: it joins an open incident it agrees with, or opens one with the
    /// recent onsets it agrees with, or waits for others. An onset whose source takes part in
    /// [`AreaConfig::max_incidents_per_source`] open incidents joins only those.
    pub fn onset(&mut self, onset: AlarmOnset) -> Vec<IncidentChange> {
        self.state.now_s = self.state.now_s.max(onset.time_s);
        if let Some(change) = self.join(&onset) {
            return vec![change];
        }
        self.state
            .pending
            .retain(|p| p.vehicle_id != onset.vehicle_id);
        if let Some(change) = self.form(&onset) {
            return vec![change];
        }
        self.state.pending.push(onset);
        Vec::new()
    }

    /// A vehicle's alarm ended: a member's evidence stops at `end.time_s`.
    pub fn end(&mut self, end: &AlarmEnd) -> Vec<IncidentChange> {
        self.state.now_s = self.state.now_s.max(end.time_s);
        let mut changes = Vec::new();
        for incident in &mut self.state.open {
            let Some(member) = incident
                .vehicles
                .iter_mut()
                .find(|v| v.vehicle_id == end.vehicle_id && v.alarm_id == end.alarm_id)
            else {
                continue;
            };
            member.alarm_open = false;
            member.last_evidence_s = member.last_evidence_s.max(end.time_s);
            incident.last_evidence_s = incident.last_evidence_s.max(end.time_s);
            changes.push(IncidentChange {
                kind: ChangeKind::Evidence,
                incident: incident.clone(),
            });
        }
        changes
    }

    /// Time has reached `now_s`: incidents quiet for [`AreaConfig::quiet_s`] end, and onsets
    /// older than the window are forgotten.
    pub fn advance(&mut self, now_s: f64) -> Vec<IncidentChange> {
        let now = self.state.now_s.max(now_s);
        self.state.now_s = now;
        let window = self.config.window_s;
        self.state.pending.retain(|p| p.time_s >= now - window);
        let quiet = self.config.quiet_s;
        let mut changes = Vec::new();
        self.state.open.retain_mut(|incident| {
            let quiet_long_enough = !incident.vehicles.iter().any(|v| v.alarm_open)
                && now - incident.last_evidence_s >= quiet;
            if quiet_long_enough {
                incident.ended_s = Some(now);
                changes.push(IncidentChange {
                    kind: ChangeKind::Ended,
                    incident: incident.clone(),
                });
            }
            !quiet_long_enough
        });
        changes
    }

    /// The open incidents `ids` were ended by hand ([`Incident::end_by_hand`], stored outside the
    /// correlator): they leave its state with no change of their own, and are returned. Their
    /// vehicles' alarms are spent (each alarm is evidence once: an onset that formed or joined an
    /// incident never waits again), so only alarms that open afterwards, new evidence, can form
    /// or join an incident, as any other onset.
    pub fn forget(&mut self, ids: &[u64]) -> Vec<Incident> {
        let (forgotten, open) = std::mem::take(&mut self.state.open)
            .into_iter()
            .partition(|incident| ids.contains(&incident.id));
        self.state.open = open;
        forgotten
    }

    /// Adds `onset` to the open incident it lies in and agrees with. A vehicle already in an open
    /// incident nearby stays in it whatever its new alarm says: a spoofed vehicle alarms again as
    /// the spoofer lets it go (its fix steps back), and that is the same incident's evidence, not a
    /// new one.
    fn join(&mut self, onset: &AlarmOnset) -> Option<IncidentChange> {
        let anchor = onset.anchor();
        let radius = self.config.radius_m;
        let margin = self.config.margin_m;
        let near = |incident: &Incident| distance_m(incident.centre, anchor) <= radius;
        let member = self.state.open.iter().position(|incident| {
            near(incident)
                && incident
                    .vehicles
                    .iter()
                    .any(|v| v.vehicle_id == onset.vehicle_id)
        });
        let at_bound = self.at_bound(onset.source_key());
        let agreeing = || {
            self.state.open.iter().position(|incident| {
                let hypothesis = Hypothesis::of(&incident.spoofing);
                near(incident)
                    && (!at_bound || has_source(incident, onset.source_key()))
                    && hypothesis
                        .joining_vector(onset, incident.centre)
                        .is_some_and(|v| hypothesis.misfit(estimate_vector(incident), v) <= 1.0)
            })
        };
        let index = member.or_else(agreeing)?;
        let incident = &mut self.state.open[index];
        let kind = match incident
            .vehicles
            .iter_mut()
            .find(|v| v.vehicle_id == onset.vehicle_id)
        {
            Some(member) => {
                member.alarm_id = onset.alarm_id;
                member.alarm_open = true;
                member.last_evidence_s = member.last_evidence_s.max(onset.time_s);
                ChangeKind::Evidence
            }
            None => {
                incident.vehicles.push(member_of(onset));
                ChangeKind::Joined
            }
        };
        incident.last_evidence_s = incident.last_evidence_s.max(onset.time_s);
        incident.onset_s = incident.onset_s.min(onset.time_s);
        refit(incident, margin, Centre::Kept);
        Some(IncidentChange {
            kind,
            incident: incident.clone(),
        })
    }

    /// Whether `source` takes part in [`AreaConfig::max_incidents_per_source`] open incidents.
    fn at_bound(&self, source: &str) -> bool {
        let taking_part = self
            .state
            .open
            .iter()
            .filter(|incident| has_source(incident, source))
            .count();
        taking_part >= self.config.max_incidents_per_source as usize
    }

    /// Opens an incident of `onset` and the pending onsets that agree with it, if there are enough
    /// (none of a source at its bound of open incidents).
    fn form(&mut self, onset: &AlarmOnset) -> Option<IncidentChange> {
        let config = self.config;
        if self.at_bound(onset.source_key()) {
            return None;
        }
        let anchor = onset.anchor();
        let reference = onset.fix;
        let nearby: Vec<&AlarmOnset> = self
            .state
            .pending
            .iter()
            .filter(|p| {
                (p.time_s - onset.time_s).abs() <= config.window_s
                    && distance_m(p.anchor(), anchor) <= config.radius_m
                    && !self.at_bound(p.source_key())
            })
            .collect();
        let needed = config.min_vehicles as usize;
        for hypothesis in HYPOTHESES {
            let Some(own) = hypothesis.vector(onset, reference) else {
                continue;
            };
            let agreeing: Vec<(&AlarmOnset, [f64; 2])> = std::iter::once((onset, own))
                .chain(nearby.iter().filter_map(|p| {
                    let v = hypothesis.vector(p, reference)?;
                    (hypothesis.misfit(own, v) <= 1.0).then_some((*p, v))
                }))
                .collect();
            if agreeing.len() < needed {
                continue;
            }
            // The median is robust to the one member that agreed with the founder only at the
            // edge; every member must then agree with it, the founder included.
            let estimate = median(agreeing.iter().map(|(_, v)| *v));
            let members: Vec<&AlarmOnset> = agreeing
                .iter()
                .filter(|(_, v)| hypothesis.misfit(estimate, *v) <= 1.0)
                .map(|(p, _)| *p)
                .collect();
            if members.len() < needed
                || !std::ptr::eq(members[0], onset)
                || distinct(members.iter().map(|m| m.source_key())) < config.min_sources as usize
            {
                continue;
            }
            let vehicles: Vec<IncidentVehicle> = members.iter().map(|m| member_of(m)).collect();
            let joined: Vec<String> = vehicles.iter().map(|v| v.vehicle_id.clone()).collect();
            let mut incident = Incident {
                id: self.state.next_id,
                spoofing: hypothesis.spoofing(estimate, reference),
                centre: anchor,
                radius_m: 0.0,
                onset_s: vehicles
                    .iter()
                    .map(|v| v.onset_s)
                    .fold(f64::INFINITY, f64::min),
                confirmed_s: onset.time_s,
                last_evidence_s: vehicles
                    .iter()
                    .map(|v| v.last_evidence_s)
                    .fold(f64::NEG_INFINITY, f64::max),
                ended_s: None,
                confidence: 0.0,
                vehicles,
            };
            refit(&mut incident, config.margin_m, Centre::OfMembers);
            self.state.next_id += 1;
            self.state
                .pending
                .retain(|p| !joined.contains(&p.vehicle_id));
            self.state.open.push(incident.clone());
            return Some(IncidentChange {
                kind: ChangeKind::Opened,
                incident,
            });
        }
        None
    }
}

fn member_of(onset: &AlarmOnset) -> IncidentVehicle {
    IncidentVehicle {
        vehicle_id: onset.vehicle_id.clone(),
        alarm_id: onset.alarm_id,
        onset_s: onset.time_s,
        fix: onset.fix,
        offset_m: onset.offset_m,
        drift_mps: onset.drift_mps,
        alarm_open: true,
        last_evidence_s: onset.time_s,
        credential: onset.credential.clone(),
        source: onset.source.clone(),
    }
}

/// `source`, or `vehicle_id` when it is empty (an onset stored before sources were kept, or one
/// whose vehicle is its own source).
fn source_key<'a>(source: &'a str, vehicle_id: &'a str) -> &'a str {
    if source.is_empty() {
        vehicle_id
    } else {
        source
    }
}

/// Whether a member of `incident` counts as `source`.
fn has_source(incident: &Incident, source: &str) -> bool {
    incident.vehicles.iter().any(|v| v.source_key() == source)
}

/// How many distinct values `keys` holds.
fn distinct<'a>(keys: impl Iterator<Item = &'a str>) -> usize {
    let mut seen: Vec<&str> = Vec::new();
    for key in keys {
        if !seen.contains(&key) {
            seen.push(key);
        }
    }
    seen.len()
}

/// Where [`refit`] puts an incident's centre.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Centre {
    /// The mean of its members' true positions: as it opens.
    OfMembers,
    /// Where it is: once open, the centre stays where its first members were captured.
    Kept,
}

/// The incident's estimate as a vector (a false position relative to the centre).
fn estimate_vector(incident: &Incident) -> [f64; 2] {
    match incident.spoofing {
        Spoofing::FalsePosition { position } => wgs84_local_displacement(incident.centre, position),
        Spoofing::Translation { offset_m } => offset_m,
        Spoofing::Drift { drift_mps } => drift_mps,
    }
}

/// Recomputes the estimate (the members' median), the centre (as `centre` says) and the radius
/// (the farthest member from it) and the confidence, after the members changed.
fn refit(incident: &mut Incident, margin_m: f64, centre: Centre) {
    let hypothesis = Hypothesis::of(&incident.spoofing);
    let centre = match centre {
        Centre::OfMembers => mean_anchor(&incident.vehicles),
        Centre::Kept => incident.centre,
    };
    let reference = incident.centre;
    let vectors: Vec<[f64; 2]> = incident
        .vehicles
        .iter()
        .filter_map(|v| hypothesis.vector(&v.onset(), reference))
        .collect();
    let estimate = median(vectors.iter().copied());
    incident.spoofing = hypothesis.spoofing(estimate, reference);
    incident.radius_m = incident
        .vehicles
        .iter()
        .map(|v| distance_m(centre, v.anchor()))
        .fold(0.0, f64::max)
        + margin_m;
    incident.centre = centre;
    let misfit = vectors
        .iter()
        .map(|v| hypothesis.misfit(estimate, *v).min(1.0))
        .sum::<f64>()
        / vectors.len().max(1) as f64;
    incident.confidence = confidence(incident.vehicles.len(), misfit);
}

/// The mean of the members' true positions.
fn mean_anchor(vehicles: &[IncidentVehicle]) -> LatLon {
    let origin = vehicles[0].anchor();
    let anchors: Vec<[f64; 2]> = vehicles
        .iter()
        .map(|v| wgs84_local_displacement(origin, v.anchor()))
        .collect();
    let count = anchors.len() as f64;
    let mean = [
        anchors.iter().map(|a| a[0]).sum::<f64>() / count,
        anchors.iter().map(|a| a[1]).sum::<f64>() / count,
    ];
    let (lat, lon) = displace_fix(origin.lat_deg, origin.lon_deg, mean[0], mean[1]);
    LatLon::new(lat, lon)
}

/// 1 − 2^(−(n − 1)(1 − m̄)): three vehicles in exact agreement 0.75, ten 0.998; a mean misfit m̄
/// at the tolerance's edge counts for nothing.
fn confidence(vehicles: usize, mean_misfit: f64) -> f64 {
    let weight = (vehicles.saturating_sub(1)) as f64 * (1.0 - mean_misfit.clamp(0.0, 1.0));
    1.0 - 0.5f64.powf(weight)
}

/// The component-wise median (the mean of the middle two for an even count).
fn median(vectors: impl Iterator<Item = [f64; 2]>) -> [f64; 2] {
    let (mut east, mut north): (Vec<f64>, Vec<f64>) = vectors.map(|v| (v[0], v[1])).unzip();
    [median_of(&mut east), median_of(&mut north)]
}

fn median_of(values: &mut [f64]) -> f64 {
    if values.is_empty() {
        return 0.0;
    }
    values.sort_by(f64::total_cmp);
    let middle = values.len() / 2;
    if values.len() % 2 == 1 {
        values[middle]
    } else {
        0.5 * (values[middle - 1] + values[middle])
    }
}

/// The angle between two vectors (degrees, in [0, 180]).
fn angle_deg(a: [f64; 2], b: [f64; 2]) -> f64 {
    let cross = a[0] * b[1] - a[1] * b[0];
    let dot = a[0] * b[0] + a[1] * b[1];
    cross.abs().atan2(dot).to_degrees()
}

fn norm(v: [f64; 2]) -> f64 {
    v[0].hypot(v[1])
}

/// Distance between two points (m), on the local WGS-84 plane at `a` (exact enough within the
/// few tens of km incidents span).
pub fn distance_m(a: LatLon, b: LatLon) -> f64 {
    norm(wgs84_local_displacement(a, b))
}

#[cfg(test)]
mod tests;
