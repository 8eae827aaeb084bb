//! Fleet scenes: many simulated vehicles in one city-sized area and one regional spoofer that captures
//! every receiver within its radius while it is active (SPEC §9).
//!
//! Real spoofing is regional: one transmitter pulls every receiver in range towards the same false
//! position or the same false motion. A scene is N drives of [`simulate_drive_with_truth`] whose specs are
//! drawn from a [`DriveDistribution`] (speed profile, noise and errors differ per vehicle; every vehicle
//! samples at the scene's rate), placed so that about K of them pass through the spoofed circle while the
//! spoofer is active, and a ground truth that says exactly who was captured, when and where.
//!
//! - **Routing.** K of the N vehicles (chosen at random) are routed through the circle: the vehicle's drive
//!   is simulated once to learn its path relative to its start, one of its fixes inside the active window
//!   is picked at random, and the start is placed so that the true position at that fix lies at a random
//!   point within 0.7 × the radius of the spoofer. The others start at uniform points of the square area
//!   whose path during the active window stays at least the radius + 50 m + 1 % of the radius from the
//!   spoofer (up to 100 draws; if none does, the draw whose path stays farthest away is kept and that
//!   vehicle may be captured by chance). A routed vehicle without a fix in the window (all lost in a GNSS
//!   outage) is placed like the others. Outside the active window every vehicle drives anywhere.
//! - **Capture.** A row is captured when the spoofer is active at its time (`[start_s, start_s +
//!   duration_s)`) and the vehicle's TRUE position lies within the radius (east/north metres with the WGS-84
//!   radii at the spoofer). A captured row is labelled spoofed and its fix is replaced as the attack says;
//!   every other row keeps its measured fix and is labelled normal. On leaving the circle (or when the
//!   spoofer stops) the receiver re-acquires the true signals, so the fix steps back to the truth; a vehicle
//!   that drives back in is captured again (a new capture episode, a drift restarting from zero).
//! - **Onboard motion** (speed, heading) is never touched: the spoofer only reaches the GNSS receiver.
//!
//! Owns the fleet scene spec, vehicle placement, capture and the scene's ground truth. Must not simulate a
//! drive itself (that is `drive.rs`) or draw drive specs (that is `randomise.rs`).

use serde::{Deserialize, Serialize};

use super::ScenarioError;
use super::drive::{TrueState, simulate_drive_with_truth};
use super::randomise::DriveDistribution;
use super::spec::DriveSpec;
use crate::geo::{LatLon, displace_fix, wgs84_local_displacement};
use crate::rng::Rng;
use crate::sample::{MAX_SPEED_MPS, Sample, SpoofingState, Track};

/// How long a captured receiver flags spoofing after its capture starts (s), with `flag_on_capture`.
pub const FLAG_AT_CAPTURE_S: f64 = 10.0;
/// Mixed into the scene seed for the stream the vehicles' drive seeds come from.
const VEHICLE_STREAM: u64 = 0x666C_6565_745F_7631;
/// Mixed into the scene seed for the choice of the routed vehicles.
const ROUTING_STREAM: u64 = 0x726F_7574_655F_7631;
/// Mixed into a vehicle's drive seed for its placement draws.
const PLACEMENT_STREAM: u64 = 0x706C_6163_655F_7631;
/// A routed vehicle's true position at its chosen fix lies within this share of the radius.
const ROUTED_TARGET_SHARE: f64 = 0.7;
/// Start draws for a vehicle that must stay outside the circle while the spoofer is active.
const MAX_OUTSIDE_DRAWS: usize = 100;
/// Clearance beyond the radius kept by the other vehicles' paths: fixed part (m) and share of the radius,
/// enough to cover the flat-earth approximation of the placement.
const OUTSIDE_CLEARANCE_M: f64 = 50.0;
const OUTSIDE_CLEARANCE_SHARE: f64 = 0.01;
/// Largest number of rows of one scene (all vehicles together; about 150 bytes each in memory).
const MAX_SCENE_ROWS: f64 = 20_000_000.0;
/// Largest number of vehicles.
const MAX_VEHICLES: usize = 100_000;
/// Area side lengths accepted (m, inclusive).
const AREA_SIZE_RANGE_M: (f64, f64) = (100.0, 200_000.0);
/// Spoofer radii accepted (m, inclusive).
const RADIUS_RANGE_M: (f64, f64) = (1.0, 100_000.0);
/// Largest translation (m), as for a jump attack.
const MAX_TRANSLATION_M: f64 = 1_000_000.0;
/// Largest |latitude| of the area centre, the spoofer and a false position (degrees): leaves room for the
/// drives around them inside the simulator's ±85°.
const MAX_LATITUDE_DEG: f64 = 80.0;

/// What a regional spoofer does to every receiver it captures.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case", deny_unknown_fields)]
pub enum RegionalAttack {
    /// Every captured receiver reports the same false position, with its own metre-level GNSS error
    /// (the measured fix's error from the truth, moved to the false position).
    Position {
        /// False latitude (degrees, |lat| ≤ 80).
        lat_deg: f64,
        /// False longitude (degrees, [-180, 180]).
        lon_deg: f64,
    },
    /// Every captured fix is displaced by the same east/north vector (length in (0, 1000 km]).
    Translation { east_m: f64, north_m: f64 },
    /// Every captured fix is displaced by velocity × time since that vehicle's capture (speed in
    /// (0, 80] m/s): the same false motion for the whole region.
    Drift { east_mps: f64, north_mps: f64 },
}

impl Default for RegionalAttack {
    fn default() -> Self {
        Self::Drift {
            east_mps: 1.0,
            north_mps: 0.0,
        }
    }
}

/// A regional spoofer: where, how far, when and what.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Spoofer {
    /// Transmitter latitude (degrees, |lat| ≤ 80).
    pub lat_deg: f64,
    /// Transmitter longitude (degrees, [-180, 180]).
    pub lon_deg: f64,
    /// Capture radius (m, 1–100,000).
    pub radius_m: f64,
    /// Switch-on time (s from the scene start, in [0, scene duration)).
    pub start_s: f64,
    /// Active time (s, > 0; the window must end by the scene's end).
    pub duration_s: f64,
    /// What captured receivers report.
    pub attack: RegionalAttack,
}

impl Default for Spoofer {
    /// At the default area's centre, 1.5 km radius, active from 15 to 35 minutes, a 1 m/s eastward drift.
    fn default() -> Self {
        Self {
            lat_deg: 32.23,
            lon_deg: -110.91,
            radius_m: 1_500.0,
            start_s: 900.0,
            duration_s: 1_200.0,
            attack: RegionalAttack::default(),
        }
    }
}

/// Everything that defines a fleet scene; deterministic from `seed`. `Default`: 200 vehicles, 30 routed
/// through the spoofed area, a 20 km square around Tucson, one hour at 1 Hz, [`Spoofer::default`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct FleetSpec {
    /// Number of vehicles N (1–100,000).
    pub vehicles: usize,
    /// Vehicles routed through the spoofed circle while it is active, K ≤ N.
    pub pass_through: usize,
    /// Centre of the square area (degrees, |lat| ≤ 80).
    pub centre_lat_deg: f64,
    /// Centre of the square area (degrees, [-180, 180]).
    pub centre_lon_deg: f64,
    /// Side of the square area the other vehicles start in (m, 100–200,000).
    pub area_size_m: f64,
    /// Length of every drive (s, > 0).
    pub duration_s: f64,
    /// Sample rate of every vehicle (Hz, (0, 100]); the distribution's rates are not used.
    pub rate_hz: f64,
    /// The regional spoofer.
    pub spoofer: Spoofer,
    /// The distribution every vehicle's speed profile, noise and errors are drawn from.
    pub distribution: DriveDistribution,
    /// Whether captured receivers raise their own spoofing flag (`spoofing_state` indicated) for the
    /// first [`FLAG_AT_CAPTURE_S`] of each capture: receivers notice a take-over mostly as it happens.
    pub flag_on_capture: bool,
    /// Seed of the drives, the routing and the placement.
    pub seed: u64,
}

impl Default for FleetSpec {
    fn default() -> Self {
        Self {
            vehicles: 200,
            pass_through: 30,
            centre_lat_deg: 32.23,
            centre_lon_deg: -110.91,
            area_size_m: 20_000.0,
            duration_s: 3_600.0,
            rate_hz: 1.0,
            spoofer: Spoofer::default(),
            distribution: DriveDistribution::realistic(),
            flag_on_capture: false,
            seed: 1,
        }
    }
}

impl FleetSpec {
    /// Checks every field (finite, in range, K ≤ N, the active window inside the scene) and the
    /// distribution; the first problem is reported with the field's name.
    pub fn validate(&self) -> Result<(), ScenarioError> {
        let s = &self.spoofer;
        let rows = self.vehicles as f64 * (self.duration_s * self.rate_hz + 1.0);
        let window_end_s = s.start_s + s.duration_s;
        let latitude = |v: f64| v.abs() <= MAX_LATITUDE_DEG;
        let longitude = |v: f64| v.abs() <= 180.0;
        let mut checks: Vec<(&'static str, f64, bool, String)> = vec![
            (
                "vehicles",
                self.vehicles as f64,
                (1..=MAX_VEHICLES).contains(&self.vehicles),
                format!("a whole number in [1, {MAX_VEHICLES}]"),
            ),
            (
                "pass_through",
                self.pass_through as f64,
                self.pass_through <= self.vehicles,
                format!("a whole number <= vehicles ({})", self.vehicles),
            ),
            (
                "centre_lat_deg",
                self.centre_lat_deg,
                latitude(self.centre_lat_deg),
                "a finite number in [-80, 80]".into(),
            ),
            (
                "centre_lon_deg",
                self.centre_lon_deg,
                longitude(self.centre_lon_deg),
                "a finite number in [-180, 180]".into(),
            ),
            (
                "area_size_m",
                self.area_size_m,
                (AREA_SIZE_RANGE_M.0..=AREA_SIZE_RANGE_M.1).contains(&self.area_size_m),
                "a finite number in [100, 200000] m".into(),
            ),
            (
                "duration_s",
                self.duration_s,
                self.duration_s > 0.0,
                "a finite number > 0 s".into(),
            ),
            (
                "rate_hz",
                self.rate_hz,
                self.rate_hz > 0.0 && self.rate_hz <= 100.0,
                "a finite number in (0, 100] Hz".into(),
            ),
            (
                "vehicles * duration_s * rate_hz",
                rows,
                rows <= MAX_SCENE_ROWS,
                "at most 2e7 rows in all".into(),
            ),
            (
                "spoofer.lat_deg",
                s.lat_deg,
                latitude(s.lat_deg),
                "a finite number in [-80, 80]".into(),
            ),
            (
                "spoofer.lon_deg",
                s.lon_deg,
                longitude(s.lon_deg),
                "a finite number in [-180, 180]".into(),
            ),
            (
                "spoofer.radius_m",
                s.radius_m,
                (RADIUS_RANGE_M.0..=RADIUS_RANGE_M.1).contains(&s.radius_m),
                "a finite number in [1, 100000] m".into(),
            ),
            (
                "spoofer.start_s",
                s.start_s,
                s.start_s >= 0.0 && s.start_s < self.duration_s,
                format!("a finite number in [0, duration_s = {}) s", self.duration_s),
            ),
            (
                "spoofer.duration_s",
                s.duration_s,
                s.duration_s > 0.0 && window_end_s <= self.duration_s,
                format!(
                    "a finite number > 0 s with start_s + duration_s <= duration_s = {} s",
                    self.duration_s
                ),
            ),
        ];
        match s.attack {
            RegionalAttack::Position { lat_deg, lon_deg } => {
                checks.push((
                    "spoofer.attack.lat_deg",
                    lat_deg,
                    latitude(lat_deg),
                    "a finite number in [-80, 80]".into(),
                ));
                checks.push((
                    "spoofer.attack.lon_deg",
                    lon_deg,
                    longitude(lon_deg),
                    "a finite number in [-180, 180]".into(),
                ));
            }
            RegionalAttack::Translation { east_m, north_m } => {
                checks.push((
                    "spoofer.attack.east_m",
                    east_m,
                    true,
                    "a finite number (m)".into(),
                ));
                checks.push((
                    "spoofer.attack.north_m",
                    north_m,
                    true,
                    "a finite number (m)".into(),
                ));
                let length_m = east_m.hypot(north_m);
                checks.push((
                    "spoofer.attack",
                    length_m,
                    length_m > 0.0 && length_m <= MAX_TRANSLATION_M,
                    "an offset whose length √(east_m² + north_m²) is in (0, 1000000] m".into(),
                ));
            }
            RegionalAttack::Drift {
                east_mps,
                north_mps,
            } => {
                checks.push((
                    "spoofer.attack.east_mps",
                    east_mps,
                    true,
                    "a finite number (m/s)".into(),
                ));
                checks.push((
                    "spoofer.attack.north_mps",
                    north_mps,
                    true,
                    "a finite number (m/s)".into(),
                ));
                let speed_mps = east_mps.hypot(north_mps);
                checks.push((
                    "spoofer.attack",
                    speed_mps,
                    speed_mps > 0.0 && speed_mps <= MAX_SPEED_MPS,
                    "a velocity whose speed √(east_mps² + north_mps²) is in (0, 80] m/s".into(),
                ));
            }
        }
        for (field, value, ok, expected) in checks {
            if !value.is_finite() || !ok {
                return Err(ScenarioError::InvalidFleet {
                    field,
                    expected,
                    value,
                });
            }
        }
        self.distribution.validate()
    }

    /// End of the spoofer's active window (s from the scene start, exclusive).
    fn window_end_s(&self) -> f64 {
        self.spoofer.start_s + self.spoofer.duration_s
    }

    /// Whether the spoofer is active at `time_s`.
    fn spoofer_active(&self, time_s: f64) -> bool {
        time_s >= self.spoofer.start_s && time_s < self.window_end_s()
    }
}

/// A captured fix: its time, where the vehicle truly was and what its receiver reported.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct CapturedFix {
    pub timestamp_s: f64,
    pub true_lat_deg: f64,
    pub true_lon_deg: f64,
    pub reported_lat_deg: f64,
    pub reported_lon_deg: f64,
}

/// One capture of one vehicle: a maximal run of consecutive captured rows (rows missing in a GNSS outage
/// do not end it).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CaptureEpisode {
    /// The first captured row.
    pub start: CapturedFix,
    /// The last captured row (the next row, if any, is the receiver back on the true signals).
    pub end: CapturedFix,
    /// Captured rows (all labelled spoofed).
    pub rows: usize,
}

/// The ground truth of one vehicle.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct VehicleTruth {
    pub vehicle_id: String,
    /// The seed its drive spec was drawn and simulated with (`distribution.draw(drive_seed)`).
    pub drive_seed: u64,
    /// Whether it was one of the K vehicles routed through the circle.
    pub routed_through: bool,
    /// Whether any of its rows was captured.
    pub captured: bool,
    /// Its captures in time order (empty when not captured).
    pub captures: Vec<CaptureEpisode>,
}

/// The ground truth of a scene: its spec (with the spoofer) and who was captured, when and where.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FleetTruth {
    pub spec: FleetSpec,
    /// Vehicles with at least one captured row (routed or by chance).
    pub captured_vehicles: usize,
    /// Captured rows in all (the rows labelled spoofed).
    pub spoofed_rows: usize,
    /// One per vehicle, in the order of the tracks.
    pub vehicles: Vec<VehicleTruth>,
}

/// A generated scene: the labelled tracks, the true state behind every row and the ground truth.
#[derive(Clone, Debug, PartialEq)]
pub struct FleetScene {
    /// One labelled track per vehicle (label 1 = captured row).
    pub tracks: Vec<Track>,
    /// The true states, one per record of the track with the same index.
    pub true_states: Vec<Vec<TrueState>>,
    pub truth: FleetTruth,
}

/// Generates a fleet scene (see the module docs); deterministic for a spec (including its seed).
pub fn generate_fleet(spec: &FleetSpec) -> Result<FleetScene, ScenarioError> {
    spec.validate()?;
    let mut seeds = Rng::seed_from_u64(spec.seed ^ VEHICLE_STREAM);
    let drive_seeds: Vec<u64> = (0..spec.vehicles).map(|_| seeds.next_u64()).collect();
    let mut order: Vec<usize> = (0..spec.vehicles).collect();
    Rng::seed_from_u64(spec.seed ^ ROUTING_STREAM).shuffle(&mut order);
    let mut routed = vec![false; spec.vehicles];
    for &vehicle in &order[..spec.pass_through] {
        routed[vehicle] = true;
    }
    let id_width = (spec.vehicles - 1).to_string().len().max(3);
    let mut tracks = Vec::with_capacity(spec.vehicles);
    let mut true_states = Vec::with_capacity(spec.vehicles);
    let mut vehicles = Vec::with_capacity(spec.vehicles);
    for (index, (&drive_seed, &routed_through)) in drive_seeds.iter().zip(&routed).enumerate() {
        let vehicle_id = format!("veh-{index:0id_width$}");
        let drawn = DriveSpec {
            duration_s: spec.duration_s,
            rate_hz: spec.rate_hz,
            start_lat_deg: spec.centre_lat_deg,
            start_lon_deg: spec.centre_lon_deg,
            ..spec.distribution.draw(drive_seed)
        };
        let start = place(spec, &drawn, routed_through, &vehicle_id)?;
        let drive_spec = DriveSpec {
            start_lat_deg: start.lat_deg,
            start_lon_deg: start.lon_deg,
            ..drawn
        };
        let drive = simulate_drive_with_truth(&drive_spec, &vehicle_id)?;
        let mut track = drive.track;
        let captures = capture(spec, &mut track, &drive.truth)?;
        vehicles.push(VehicleTruth {
            vehicle_id,
            drive_seed,
            routed_through,
            captured: !captures.is_empty(),
            captures,
        });
        tracks.push(track);
        true_states.push(drive.truth);
    }
    let captured_vehicles = vehicles.iter().filter(|v| v.captured).count();
    let spoofed_rows = vehicles
        .iter()
        .flat_map(|v| &v.captures)
        .map(|c| c.rows)
        .sum();
    Ok(FleetScene {
        tracks,
        true_states,
        truth: FleetTruth {
            spec: spec.clone(),
            captured_vehicles,
            spoofed_rows,
            vehicles,
        },
    })
}

/// East/north metres of a true position from the spoofer (WGS-84 radii at the spoofer): the frame in
/// which capture is decided.
pub fn offset_from_spoofer_m(spoofer: &Spoofer, lat_deg: f64, lon_deg: f64) -> [f64; 2] {
    wgs84_local_displacement(
        LatLon::new(spoofer.lat_deg, spoofer.lon_deg),
        LatLon::new(lat_deg, lon_deg),
    )
}

/// Whether a true position lies within the spoofer's radius.
fn within_radius(spoofer: &Spoofer, lat_deg: f64, lon_deg: f64) -> bool {
    let [east_m, north_m] = offset_from_spoofer_m(spoofer, lat_deg, lon_deg);
    east_m.hypot(north_m) <= spoofer.radius_m
}

/// The start of a vehicle's drive. `drawn` starts at the area centre; its path relative to its start does
/// not depend on where it starts (the simulator plans in a local frame), so one simulation up to the
/// window's end tells where the vehicle will be during the active window.
fn place(
    spec: &FleetSpec,
    drawn: &DriveSpec,
    routed_through: bool,
    vehicle_id: &str,
) -> Result<LatLon, ScenarioError> {
    let probe_spec = DriveSpec {
        duration_s: spec.window_end_s(),
        ..*drawn
    };
    let probe = simulate_drive_with_truth(&probe_spec, vehicle_id)?;
    let centre = LatLon::new(drawn.start_lat_deg, drawn.start_lon_deg);
    // The path during the active window, in metres from the start.
    let path: Vec<[f64; 2]> = probe
        .truth
        .iter()
        .filter(|t| spec.spoofer_active(t.timestamp_s))
        .map(|t| wgs84_local_displacement(centre, LatLon::new(t.latitude_deg, t.longitude_deg)))
        .collect();
    let mut rng = Rng::seed_from_u64(drawn.seed ^ PLACEMENT_STREAM);
    let spoofer = &spec.spoofer;
    if routed_through && !path.is_empty() {
        // A random fix of the window lands at a random point within 0.7 radius of the spoofer.
        let [path_east_m, path_north_m] = path[rng.below(path.len())];
        let distance_m = ROUTED_TARGET_SHARE * spoofer.radius_m * rng.uniform().sqrt();
        let angle = rng.uniform_range(0.0, std::f64::consts::TAU);
        let (lat_deg, lon_deg) = displace_fix(
            spoofer.lat_deg,
            spoofer.lon_deg,
            distance_m * angle.sin() - path_east_m,
            distance_m * angle.cos() - path_north_m,
        );
        return Ok(LatLon::new(lat_deg, lon_deg));
    }
    // Uniform starts in the square until the window's path keeps clear of the circle.
    let clearance_m =
        spoofer.radius_m + OUTSIDE_CLEARANCE_M + OUTSIDE_CLEARANCE_SHARE * spoofer.radius_m;
    let half_side_m = 0.5 * spec.area_size_m;
    let mut best: Option<(f64, LatLon)> = None;
    for _ in 0..MAX_OUTSIDE_DRAWS {
        let (lat_deg, lon_deg) = displace_fix(
            centre.lat_deg,
            centre.lon_deg,
            rng.uniform_range(-half_side_m, half_side_m),
            rng.uniform_range(-half_side_m, half_side_m),
        );
        let [start_east_m, start_north_m] = offset_from_spoofer_m(spoofer, lat_deg, lon_deg);
        let closest_m = path
            .iter()
            .map(|[east_m, north_m]| (start_east_m + east_m).hypot(start_north_m + north_m))
            .fold(f64::INFINITY, f64::min);
        let start = LatLon::new(lat_deg, lon_deg);
        if closest_m >= clearance_m {
            return Ok(start);
        }
        if best.is_none_or(|(farthest_m, _)| closest_m > farthest_m) {
            best = Some((closest_m, start));
        }
    }
    Ok(best.map(|(_, start)| start).unwrap_or(centre))
}

/// Applies the spoofer to a simulated track: captured rows get the attacked fix and label 1, the others
/// label 0. Returns the capture episodes.
fn capture(
    spec: &FleetSpec,
    track: &mut Track,
    truth: &[TrueState],
) -> Result<Vec<CaptureEpisode>, ScenarioError> {
    let spoofer = &spec.spoofer;
    let mut episodes = Vec::new();
    let mut current: Option<CaptureEpisode> = None;
    for (row, (record, state)) in track.records.iter_mut().zip(truth).enumerate() {
        let captured = spec.spoofer_active(state.timestamp_s)
            && within_radius(spoofer, state.latitude_deg, state.longitude_deg);
        if !captured {
            record.label = Some(false);
            episodes.extend(current.take());
            continue;
        }
        let since_capture_s = current
            .as_ref()
            .map_or(0.0, |episode| state.timestamp_s - episode.start.timestamp_s);
        record.sample = captured_sample(&record.sample, state, &spoofer.attack, since_capture_s);
        if spec.flag_on_capture && since_capture_s < FLAG_AT_CAPTURE_S {
            record.sample.spoofing_state = SpoofingState::Indicated;
        }
        record.label = Some(true);
        if !(-90.0..=90.0).contains(&record.sample.latitude_deg) {
            return Err(ScenarioError::DisplacedOutOfRange {
                vehicle_id: track.vehicle_id.clone(),
                row,
                latitude_deg: record.sample.latitude_deg,
            });
        }
        let fix = CapturedFix {
            timestamp_s: state.timestamp_s,
            true_lat_deg: state.latitude_deg,
            true_lon_deg: state.longitude_deg,
            reported_lat_deg: record.sample.latitude_deg,
            reported_lon_deg: record.sample.longitude_deg,
        };
        let episode = current.get_or_insert(CaptureEpisode {
            start: fix,
            end: fix,
            rows: 0,
        });
        episode.end = fix;
        episode.rows += 1;
    }
    episodes.extend(current);
    Ok(episodes)
}

/// The sample a captured receiver reports: the fix replaced as the attack says, the onboard speed and
/// heading untouched (the receiver flag raised on capture is set by its caller).
fn captured_sample(
    measured: &Sample,
    truth: &TrueState,
    attack: &RegionalAttack,
    since_capture_s: f64,
) -> Sample {
    let (latitude_deg, longitude_deg) = match *attack {
        RegionalAttack::Position { lat_deg, lon_deg } => {
            // The receiver's own error from the truth, carried to the false position.
            let [error_east_m, error_north_m] = wgs84_local_displacement(
                LatLon::new(truth.latitude_deg, truth.longitude_deg),
                LatLon::new(measured.latitude_deg, measured.longitude_deg),
            );
            displace_fix(lat_deg, lon_deg, error_east_m, error_north_m)
        }
        RegionalAttack::Translation { east_m, north_m } => displace_fix(
            measured.latitude_deg,
            measured.longitude_deg,
            east_m,
            north_m,
        ),
        RegionalAttack::Drift {
            east_mps,
            north_mps,
        } => displace_fix(
            measured.latitude_deg,
            measured.longitude_deg,
            east_mps * since_capture_s,
            north_mps * since_capture_s,
        ),
    };
    Sample {
        latitude_deg,
        longitude_deg,
        ..*measured
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// At the equator the WGS-84 radii are M = a(1 − e²) = 6,335,439.327 m and N = a = 6,378,137 m,
    /// so 1 m north is 1/M rad and 1 m east 1/N rad (values below by hand from those).
    fn at_equator(measured: Sample) -> TrueState {
        TrueState {
            timestamp_s: measured.timestamp_s,
            latitude_deg: 0.0,
            longitude_deg: 0.0,
            speed_mps: measured.speed_mps,
            heading_deg: measured.heading_deg,
        }
    }

    fn assert_close(actual: (f64, f64), expected: (f64, f64)) {
        assert!(
            (actual.0 - expected.0).abs() < 1e-12 && (actual.1 - expected.1).abs() < 1e-12,
            "got {actual:?}, expected {expected:?}"
        );
    }

    #[test]
    fn captured_samples_match_hand_computed_fixes_and_keep_the_onboard_motion() {
        let measured = Sample::new(60.0, 0.0, 0.0, 7.5, 123.0);
        let truth = at_equator(measured);
        let reported = |attack: RegionalAttack, since_capture_s: f64| {
            let sample = captured_sample(&measured, &truth, &attack, since_capture_s);
            assert_eq!(
                (sample.timestamp_s, sample.speed_mps, sample.heading_deg),
                (60.0, 7.5, 123.0)
            );
            (sample.latitude_deg, sample.longitude_deg)
        };
        // 200 m north = 200/M rad, 100 m east = 100/N rad.
        let translation = RegionalAttack::Translation {
            east_m: 100.0,
            north_m: 200.0,
        };
        assert_close(
            reported(translation, 42.0),
            (0.001_808_738_954_100_764, 0.000_898_315_284_119_521_5),
        );
        // 50 s at (2, −1) m/s: 100 m east, 50 m south; at capture itself no offset yet.
        let drift = RegionalAttack::Drift {
            east_mps: 2.0,
            north_mps: -1.0,
        };
        assert_close(
            reported(drift, 50.0),
            (-0.000_452_184_738_525_191_1, 0.000_898_315_284_119_521_5),
        );
        assert_close(reported(drift, 0.0), (0.0, 0.0));
        // A receiver 3 m east and 4 m north of the truth reports 3 m east and 4 m north of the false
        // position (0°, 10°).
        let (lat_deg, lon_deg) = displace_fix(0.0, 0.0, 3.0, 4.0);
        let noisy = Sample::new(60.0, lat_deg, lon_deg, 7.5, 123.0);
        let position = RegionalAttack::Position {
            lat_deg: 0.0,
            lon_deg: 10.0,
        };
        let sample = captured_sample(&noisy, &truth, &position, 5.0);
        assert_close(
            (sample.latitude_deg, sample.longitude_deg),
            (3.617_477_908_201_529e-5, 10.000_026_949_458_524),
        );
    }

    #[test]
    fn the_spoofer_is_active_in_its_half_open_window_and_captures_within_its_radius() {
        let spec = FleetSpec::default();
        assert!(!spec.spoofer_active(899.999));
        assert!(spec.spoofer_active(900.0));
        assert!(spec.spoofer_active(2_099.9));
        assert!(!spec.spoofer_active(2_100.0));
        let spoofer = Spoofer {
            lat_deg: 0.0,
            lon_deg: 0.0,
            radius_m: 1_000.0,
            ..Spoofer::default()
        };
        // 999 m and 1001 m north of the spoofer at the equator (1/M rad per metre).
        let north_deg = |metres: f64| (metres / 6_335_439.327_292_82_f64).to_degrees();
        assert!(within_radius(&spoofer, north_deg(999.0), 0.0));
        assert!(!within_radius(&spoofer, north_deg(1_001.0), 0.0));
        // 600 m east and 799.999 m north lies just within 1 km.
        let (lat_deg, lon_deg) = displace_fix(0.0, 0.0, 600.0, 799.999);
        assert!(within_radius(&spoofer, lat_deg, lon_deg));
    }

    #[test]
    fn vehicle_ids_are_zero_padded_to_sort_in_order() {
        let spec = FleetSpec {
            vehicles: 3,
            pass_through: 1,
            duration_s: 120.0,
            spoofer: Spoofer {
                start_s: 30.0,
                duration_s: 60.0,
                ..Spoofer::default()
            },
            ..FleetSpec::default()
        };
        let scene = generate_fleet(&spec).expect("valid");
        let ids: Vec<&str> = scene.tracks.iter().map(|t| t.vehicle_id.as_str()).collect();
        assert_eq!(ids, ["veh-000", "veh-001", "veh-002"]);
        assert_eq!(scene.truth.captured_vehicles, 1);
    }
}
