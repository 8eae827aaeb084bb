//! Simulated drives: kinematically consistent ground truth, noisy GNSS fixes and onboard motion.
//!
//! The truth is integrated at `SUBSTEPS_PER_SAMPLE` (10) substeps per sample from a speed and a heading that
//! move towards targets at bounded rates (acceleration, braking, yaw rate, lateral acceleration), so both
//! evolve smoothly. Targets come from a seeded maneuver planner (cruise at a new speed, turn, stop).
//! The planner, the sensor noise, multipath, outages, heading-bias wander and reacquisition offsets draw
//! from separate streams of the seed, so changing a noise level or turning on an error keeps the same ground
//! truth and the same other errors.
//!
//! Owns simulating a drive from its spec (`spec.rs`). Must not inject attacks (that is `attack.rs`) or
//! draw specs at random (that is `randomise.rs`).

use std::collections::VecDeque;

use serde::{Deserialize, Serialize};

use super::impairments::{
    GnssOutage, HeadingWanderModel, MultipathModel, OnboardErrors, OutageSchedule,
    ReacquisitionModel, StaticHoldModel,
};
use super::spec::{DriveSpec, GnssNoise, OnboardNoise, SpeedProfile, TurnBehaviour};
use super::{ScenarioError, bearing_unit};
use crate::geo::{LatLon, displace_fix};
use crate::rng::Rng;
use crate::sample::{Record, Sample, Track};

/// Truth integration substeps per output sample (smooth motion between fixes).
const SUBSTEPS_PER_SAMPLE: usize = 10;
/// Mixed into the seed for the sensor-noise stream (kept apart from the maneuver stream).
const NOISE_STREAM: u64 = 0x6E6F_6973_655F_7631;
/// Below this speed the vehicle does not turn (no turning on the spot).
const MIN_TURNING_SPEED_MPS: f64 = 0.1;
/// When heading home from beyond the roam radius, the aim is jittered by up to this much.
const HOMING_JITTER_DEG: f64 = 30.0;

/// The true vehicle state at one output sample.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct TrueState {
    /// Seconds from the drive start.
    pub timestamp_s: f64,
    /// True latitude (degrees).
    pub latitude_deg: f64,
    /// True longitude (degrees).
    pub longitude_deg: f64,
    /// True ground speed (m/s).
    pub speed_mps: f64,
    /// True heading (degrees clockwise from north, [0, 360)).
    pub heading_deg: f64,
}

/// A simulated drive: the measured track, the ground truth behind each of its rows and where the GNSS
/// misbehaved.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SimulatedDrive {
    /// Measured samples, labelled normal; fixes inside outages are missing.
    pub track: Track,
    /// Ground truth, one per record.
    pub truth: Vec<TrueState>,
    /// Indices into `track.records` of the fixes that carry a multipath outlier.
    pub multipath_rows: Vec<usize>,
    /// The GNSS outages that dropped fixes, in time order.
    pub outages: Vec<GnssOutage>,
    /// Indices into `track.records` of the fixes pinned by [`StaticHold`]: each repeats the fix of the
    /// row where its hold engaged (not listed itself).
    #[serde(default)]
    pub held_rows: Vec<usize>,
}

/// Simulates a drive (see [`simulate_drive_with_truth`]) and returns the measured track only.
pub fn simulate_drive(spec: &DriveSpec, vehicle_id: &str) -> Result<Track, ScenarioError> {
    simulate_drive_with_truth(spec, vehicle_id).map(|drive| drive.track)
}

/// Simulates a drive: timestamps 0, 1/rate, …; GNSS fix = truth + [`GnssNoise`] (+ a [`Multipath`]
/// outlier now and then, + the decaying [`Reacquisition`] offset after an outage), pinned while
/// [`StaticHold`] holds it; onboard speed/heading = truth at t − τ_L with the [`OnboardErrors`] (the
/// heading bias plus its [`HeadingBiasWander`]) + [`OnboardNoise`]; fixes inside [`Outages`] dropped;
/// every label `Some(false)`; `line` = 1-based sample number (so it skips over outages). Deterministic for
/// a spec (including its seed).
pub fn simulate_drive_with_truth(
    spec: &DriveSpec,
    vehicle_id: &str,
) -> Result<SimulatedDrive, ScenarioError> {
    spec.validate()?;
    let sample_interval_s = 1.0 / spec.rate_hz;
    // The onboard samples look this many substeps back (forward when negative).
    let onboard_lag_substeps =
        spec.onboard_errors.timing_offset_s * spec.rate_hz * SUBSTEPS_PER_SAMPLE as f64;
    let mut truth_stream = TruthStream::new(spec);
    let mut sensors = Sensors::new(spec);
    let mut outages = OutageSchedule::new(spec.outages, spec.seed, sample_interval_s);
    let mut reacquisition = ReacquisitionModel::new(spec.reacquisition, spec.seed);
    let mut static_hold = StaticHoldModel::new(spec.static_hold);
    let count = spec.sample_count();
    let mut records = Vec::with_capacity(count);
    let mut truth = Vec::with_capacity(count);
    let mut multipath_rows = Vec::new();
    let mut held_rows = Vec::new();
    let mut previous_dropped = false;
    for index in 0..count {
        let fix_substep = index * SUBSTEPS_PER_SAMPLE;
        let at_fix = truth_stream.at(fix_substep);
        let state = TrueState {
            timestamp_s: index as f64 * sample_interval_s,
            latitude_deg: at_fix.latitude_deg,
            longitude_deg: at_fix.longitude_deg,
            speed_mps: at_fix.speed_mps,
            heading_deg: at_fix.heading_deg,
        };
        let onboard_motion = truth_stream.motion_at(fix_substep as f64 - onboard_lag_substeps);
        truth_stream.forget_before(fix_substep as f64 - onboard_lag_substeps.max(0.0));
        let dropped = outages.drops(state.timestamp_s);
        if previous_dropped && !dropped {
            reacquisition.reacquire(state.timestamp_s);
        }
        previous_dropped = dropped;
        let extra_offset_m = reacquisition.offset_m(state.timestamp_s);
        // Every sample is measured, even a dropped one, so an outage does not shift the noise streams.
        let mut measured = sensors.measure(&state, onboard_motion, index > 0, extra_offset_m);
        if dropped {
            static_hold.lose_fix();
            continue;
        }
        let fix = LatLon::new(measured.sample.latitude_deg, measured.sample.longitude_deg);
        let true_position = LatLon::new(state.latitude_deg, state.longitude_deg);
        if let Some(held) = static_hold.pinned(state.speed_mps, true_position, fix) {
            measured.sample.latitude_deg = held.lat_deg;
            measured.sample.longitude_deg = held.lon_deg;
            held_rows.push(records.len());
        } else if measured.has_multipath {
            multipath_rows.push(records.len());
        }
        records.push(Record {
            sample: measured.sample,
            label: Some(false),
            comparator_alarm: None,
            line: index as u64 + 1,
            trajectory_break: false,
            warmup: false,
        });
        truth.push(state);
    }
    Ok(SimulatedDrive {
        track: Track {
            vehicle_id: vehicle_id.to_owned(),
            records,
        },
        truth,
        multipath_rows,
        outages: outages.into_dropped_gaps(),
        held_rows,
    })
}

/// The true state after some substep.
#[derive(Clone, Copy, Debug)]
struct SubstepState {
    latitude_deg: f64,
    longitude_deg: f64,
    speed_mps: f64,
    heading_deg: f64,
}

/// True speed and heading at some instant, as the onboard sensors see it.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Motion {
    speed_mps: f64,
    heading_deg: f64,
}

impl Motion {
    fn of(state: SubstepState) -> Self {
        Self {
            speed_mps: state.speed_mps,
            heading_deg: state.heading_deg,
        }
    }

    /// Linear interpolation towards `other` (`fraction` in [0, 1]), the heading along the shorter arc.
    fn towards(self, other: Self, fraction: f64) -> Self {
        Self {
            speed_mps: self.speed_mps + fraction * (other.speed_mps - self.speed_mps),
            heading_deg: wrap_degrees(
                self.heading_deg
                    + fraction * signed_angle_deg(other.heading_deg - self.heading_deg),
            ),
        }
    }
}

/// The truth at substep resolution: integrated ahead on demand and kept back only as far as the onboard
/// timing offset looks, so onboard samples can be taken at t − τ_L on either side of t.
struct TruthStream {
    vehicle: Vehicle,
    planner: Planner,
    speed: SpeedProfile,
    turns: TurnBehaviour,
    substep_s: f64,
    /// States after substeps `first_substep`, `first_substep + 1`, …; substep 0 is the start.
    states: VecDeque<SubstepState>,
    first_substep: usize,
}

impl TruthStream {
    fn new(spec: &DriveSpec) -> Self {
        let vehicle = Vehicle::at_start(spec);
        let start = vehicle.state();
        Self {
            vehicle,
            planner: Planner::new(spec),
            speed: spec.speed,
            turns: spec.turns,
            substep_s: 1.0 / (spec.rate_hz * SUBSTEPS_PER_SAMPLE as f64),
            states: VecDeque::from([start]),
            first_substep: 0,
        }
    }

    /// The state after `substep` substeps, integrating ahead as needed. Panics if it was forgotten
    /// (a bug of this module, not of the spec).
    fn at(&mut self, substep: usize) -> SubstepState {
        while self.first_substep + self.states.len() <= substep {
            self.planner.update(&mut self.vehicle);
            self.vehicle
                .advance(self.substep_s, &self.speed, &self.turns);
            self.states.push_back(self.vehicle.state());
        }
        let offset = substep
            .checked_sub(self.first_substep)
            .expect("truth states are forgotten only once no sample needs them");
        self.states[offset]
    }

    /// Speed and heading at a fractional substep, linearly interpolated; before the start the vehicle
    /// stands at its start.
    fn motion_at(&mut self, substep: f64) -> Motion {
        let before = substep.max(0.0).floor();
        let fraction = substep.max(0.0) - before;
        let at_before = Motion::of(self.at(before as usize));
        if fraction == 0.0 {
            // Exactly on a substep (always so without a timing offset): the state itself, bit for bit.
            return at_before;
        }
        at_before.towards(Motion::of(self.at(before as usize + 1)), fraction)
    }

    /// Drops the states before `substep` (fractional; no later sample asks for them).
    fn forget_before(&mut self, substep: f64) {
        let keep_from = substep.max(0.0).floor() as usize;
        let forgotten = keep_from
            .saturating_sub(self.first_substep)
            .min(self.states.len());
        self.states.drain(..forgotten);
        self.first_substep += forgotten;
    }
}

/// True kinematic state, advanced in substeps.
struct Vehicle {
    time_s: f64,
    latitude_deg: f64,
    longitude_deg: f64,
    /// Position relative to the start in a flat local frame, only for the roam radius.
    east_m: f64,
    north_m: f64,
    speed_mps: f64,
    heading_deg: f64,
    target_speed_mps: f64,
    target_heading_deg: f64,
}

impl Vehicle {
    fn at_start(spec: &DriveSpec) -> Self {
        Self {
            time_s: 0.0,
            latitude_deg: spec.start_lat_deg,
            longitude_deg: spec.start_lon_deg,
            east_m: 0.0,
            north_m: 0.0,
            speed_mps: 0.0,
            heading_deg: spec.start_heading_deg,
            target_speed_mps: 0.0,
            target_heading_deg: spec.start_heading_deg,
        }
    }

    fn state(&self) -> SubstepState {
        SubstepState {
            latitude_deg: self.latitude_deg,
            longitude_deg: self.longitude_deg,
            speed_mps: self.speed_mps,
            heading_deg: self.heading_deg,
        }
    }

    /// One substep: speed and heading move towards their targets at bounded rates; the position moves by
    /// the mean speed along the mean heading (second-order accurate).
    fn advance(&mut self, dt_s: f64, speed: &SpeedProfile, turns: &TurnBehaviour) {
        let old_speed = self.speed_mps;
        self.speed_mps = if self.target_speed_mps > old_speed {
            (old_speed + speed.acceleration_mps2 * dt_s).min(self.target_speed_mps)
        } else {
            (old_speed - speed.braking_mps2 * dt_s).max(self.target_speed_mps)
        };
        let mut heading_change_deg = 0.0;
        if self.speed_mps > MIN_TURNING_SPEED_MPS {
            let rate_limit_dps = turns
                .max_yaw_rate_dps
                .min((turns.max_lateral_accel_mps2 / self.speed_mps).to_degrees());
            let max_change = rate_limit_dps * dt_s;
            let wanted = signed_angle_deg(self.target_heading_deg - self.heading_deg);
            heading_change_deg = wanted.clamp(-max_change, max_change);
        }
        let mean_heading_deg = self.heading_deg + 0.5 * heading_change_deg;
        let distance_m = 0.5 * (old_speed + self.speed_mps) * dt_s;
        let (unit_e, unit_n) = bearing_unit(mean_heading_deg);
        let (east_m, north_m) = (distance_m * unit_e, distance_m * unit_n);
        (self.latitude_deg, self.longitude_deg) =
            displace_fix(self.latitude_deg, self.longitude_deg, east_m, north_m);
        self.east_m += east_m;
        self.north_m += north_m;
        self.heading_deg = wrap_degrees(self.heading_deg + heading_change_deg);
        self.time_s += dt_s;
    }
}

/// Draws maneuvers (new speed/heading targets) from the seeded maneuver stream.
struct Planner {
    rng: Rng,
    speed: SpeedProfile,
    turns: TurnBehaviour,
    maneuver_end_s: f64,
}

impl Planner {
    fn new(spec: &DriveSpec) -> Self {
        Self {
            rng: Rng::seed_from_u64(spec.seed),
            speed: spec.speed,
            turns: spec.turns,
            maneuver_end_s: 0.0,
        }
    }

    /// Starts the next maneuver when the current one has ended.
    fn update(&mut self, vehicle: &mut Vehicle) {
        if vehicle.time_s < self.maneuver_end_s {
            return;
        }
        let s = self.speed;
        if self.rng.uniform() < s.stop_probability {
            vehicle.target_speed_mps = 0.0;
            let braking_s = vehicle.speed_mps / s.braking_mps2;
            self.maneuver_end_s =
                vehicle.time_s + braking_s + self.rng.uniform_range(s.stop_min_s, s.stop_max_s);
            return;
        }
        // Log-uniform: slow driving dominates while fast stretches still occur.
        let log_speed = self
            .rng
            .uniform_range(s.cruise_min_mps.ln(), s.cruise_max_mps.ln());
        vehicle.target_speed_mps = log_speed.exp().clamp(s.cruise_min_mps, s.cruise_max_mps);
        vehicle.target_heading_deg = self.next_heading(vehicle);
        self.maneuver_end_s =
            vehicle.time_s + self.rng.uniform_range(s.maneuver_min_s, s.maneuver_max_s);
    }

    fn next_heading(&mut self, vehicle: &Vehicle) -> f64 {
        let t = self.turns;
        let distance_from_start_m = vehicle.east_m.hypot(vehicle.north_m);
        if distance_from_start_m > t.roam_radius_m {
            let home_bearing_deg = (-vehicle.east_m).atan2(-vehicle.north_m).to_degrees();
            let jitter = self
                .rng
                .uniform_range(-HOMING_JITTER_DEG, HOMING_JITTER_DEG);
            return wrap_degrees(home_bearing_deg + jitter);
        }
        if self.rng.uniform() >= t.turn_probability {
            return vehicle.heading_deg;
        }
        let angle = self.rng.uniform_range(t.turn_min_deg, t.turn_max_deg);
        let sign = if self.rng.uniform() < 0.5 { -1.0 } else { 1.0 };
        wrap_degrees(vehicle.heading_deg + sign * angle)
    }
}

/// One measured sample and whether its fix carries a multipath outlier.
struct Measurement {
    sample: Sample,
    has_multipath: bool,
}

/// GNSS and onboard measurement models, drawing from the seeded noise stream (multipath and heading-bias
/// wander from their own).
struct Sensors {
    rng: Rng,
    gnss: GnssNoise,
    onboard: OnboardNoise,
    errors: OnboardErrors,
    multipath: MultipathModel,
    heading_wander: HeadingWanderModel,
    /// Gauss–Markov factor φ per sample.
    bias_decay: f64,
    bias_east_m: f64,
    bias_north_m: f64,
}

impl Sensors {
    fn new(spec: &DriveSpec) -> Self {
        let mut rng = Rng::seed_from_u64(spec.seed ^ NOISE_STREAM);
        let gnss = spec.gnss_noise;
        let bias_east_m = gnss.bias_std_m * rng.normal();
        let bias_north_m = gnss.bias_std_m * rng.normal();
        Self {
            rng,
            gnss,
            onboard: spec.onboard_noise,
            errors: spec.onboard_errors,
            multipath: MultipathModel::new(spec.multipath, spec.seed),
            heading_wander: HeadingWanderModel::new(
                spec.heading_bias_wander,
                spec.seed,
                spec.rate_hz,
            ),
            bias_decay: (-1.0 / (spec.rate_hz * gnss.bias_time_constant_s)).exp(),
            bias_east_m,
            bias_north_m,
        }
    }

    /// Measures the fix at one truth state (plus `extra_offset_m`, east and north, if given) and the
    /// onboard motion (the truth at t − τ_L); `advance_bias` is false for the first sample (bias already
    /// stationary). Always draws the same count of deviates, so noise levels only scale the same stream.
    fn measure(
        &mut self,
        truth: &TrueState,
        onboard: Motion,
        advance_bias: bool,
        extra_offset_m: Option<[f64; 2]>,
    ) -> Measurement {
        if advance_bias {
            let innovation_std = self.gnss.bias_std_m * (1.0 - self.bias_decay.powi(2)).sqrt();
            self.bias_east_m =
                self.bias_decay * self.bias_east_m + innovation_std * self.rng.normal();
            self.bias_north_m =
                self.bias_decay * self.bias_north_m + innovation_std * self.rng.normal();
        }
        let mut error_east_m = self.bias_east_m + self.gnss.white_std_m * self.rng.normal();
        let mut error_north_m = self.bias_north_m + self.gnss.white_std_m * self.rng.normal();
        let outlier = self.multipath.next_outlier();
        if let Some((east_m, north_m)) = outlier {
            error_east_m += east_m;
            error_north_m += north_m;
        }
        if let Some([east_m, north_m]) = extra_offset_m {
            error_east_m += east_m;
            error_north_m += north_m;
        }
        let (latitude_deg, longitude_deg) = displace_fix(
            truth.latitude_deg,
            truth.longitude_deg,
            error_east_m,
            error_north_m,
        );
        let speed_noise = self.onboard.speed_std_mps * self.rng.normal();
        let heading_noise = self.onboard.heading_std_deg * self.rng.normal();
        // A wheel-speed sensor reads exactly zero at standstill.
        let speed_mps = if onboard.speed_mps > 0.0 {
            ((1.0 + self.errors.speed_scale_error) * onboard.speed_mps + speed_noise).max(0.0)
        } else {
            0.0
        };
        let heading_bias_deg = self
            .heading_wander
            .next_bias_deg(self.errors.heading_bias_deg);
        let heading_deg = wrap_degrees(onboard.heading_deg + heading_bias_deg + heading_noise);
        Measurement {
            sample: Sample::new(
                truth.timestamp_s,
                latitude_deg,
                longitude_deg,
                speed_mps,
                heading_deg,
            ),
            has_multipath: outlier.is_some(),
        }
    }
}

/// Angle wrapped into [0, 360).
fn wrap_degrees(angle_deg: f64) -> f64 {
    let wrapped = angle_deg.rem_euclid(360.0);
    // rem_euclid can round up to exactly 360 for tiny negative inputs.
    if wrapped >= 360.0 { 0.0 } else { wrapped }
}

/// Angle wrapped into [-180, 180).
fn signed_angle_deg(angle_deg: f64) -> f64 {
    (angle_deg + 180.0).rem_euclid(360.0) - 180.0
}

#[cfg(test)]
mod tests {
    use super::super::spec::RoadKind;
    use super::*;

    #[test]
    fn angles_wrap_into_their_ranges() {
        assert_eq!(wrap_degrees(-90.0), 270.0);
        assert_eq!(wrap_degrees(720.5), 0.5);
        assert_eq!(wrap_degrees(-1e-20), 0.0);
        assert_eq!(signed_angle_deg(350.0), -10.0);
        assert_eq!(signed_angle_deg(-190.0), 170.0);
    }

    #[test]
    fn onboard_motion_between_substeps_is_interpolated_and_clamped_at_the_start() {
        let (a, b) = (
            Motion {
                speed_mps: 2.0,
                heading_deg: 359.0,
            },
            Motion {
                speed_mps: 4.0,
                heading_deg: 3.0,
            },
        );
        let quarter = a.towards(b, 0.25);
        assert_eq!(quarter.speed_mps, 2.5);
        assert!((quarter.heading_deg - 0.0).abs() < 1e-12, "{quarter:?}");
        assert!((b.towards(a, 0.5).heading_deg - 1.0).abs() < 1e-12);

        let spec = DriveSpec {
            duration_s: 60.0,
            seed: 2,
            ..DriveSpec::default()
        };
        let mut stream = TruthStream::new(&spec);
        let start = Motion::of(stream.at(0));
        assert_eq!(stream.motion_at(-7.5), start);
        // The first substep after which the vehicle moves (it starts at rest).
        let n = (1..)
            .find(|&n| stream.at(n).speed_mps > 0.0)
            .expect("the vehicle sets off");
        let (before, after) = (Motion::of(stream.at(n)), Motion::of(stream.at(n + 1)));
        assert!(after.speed_mps > before.speed_mps);
        assert_eq!(stream.motion_at(n as f64), before);
        let between = stream.motion_at(n as f64 + 0.25);
        assert_eq!(between, before.towards(after, 0.25));
        assert!(before.speed_mps < between.speed_mps && between.speed_mps < after.speed_mps);
        stream.forget_before(n as f64 + 0.5);
        assert_eq!(stream.first_substep, n);
        assert_eq!(Motion::of(stream.at(n + 1)), after);
    }

    #[test]
    fn the_road_kind_follows_the_highest_cruise_speed() {
        let with_top_speed = |cruise_max_mps| {
            let mut spec = DriveSpec::default();
            spec.speed.cruise_max_mps = cruise_max_mps;
            spec.road_kind()
        };
        assert_eq!(DriveSpec::default().road_kind(), RoadKind::Urban);
        assert_eq!(with_top_speed(14.9), RoadKind::Urban);
        assert_eq!(with_top_speed(15.0), RoadKind::Highway);
        assert_eq!(with_top_speed(30.0), RoadKind::Highway);
        assert_eq!(RoadKind::Highway.to_string(), "highway");
        assert_eq!(
            serde_json::to_string(&[RoadKind::Urban, RoadKind::Highway]).expect("serialises"),
            r#"["urban","highway"]"#
        );
    }

    #[test]
    fn sample_count_covers_the_duration_inclusive() {
        let spec = |duration_s, rate_hz| DriveSpec {
            duration_s,
            rate_hz,
            ..DriveSpec::default()
        };
        assert_eq!(spec(10.0, 1.0).sample_count(), 11);
        assert_eq!(spec(0.3, 10.0).sample_count(), 4);
        assert_eq!(spec(10.5, 1.0).sample_count(), 11);
    }

    #[test]
    fn the_default_spec_is_valid_and_bad_fields_are_named() {
        assert_eq!(DriveSpec::default().validate(), Ok(()));
        let bad = DriveSpec {
            rate_hz: 0.0,
            ..DriveSpec::default()
        };
        let err = bad.validate().unwrap_err();
        assert!(err.to_string().contains("rate_hz"), "{err}");
        let mut bad = DriveSpec::default();
        bad.gnss_noise.white_std_m = f64::NAN;
        let err = bad.validate().unwrap_err().to_string();
        assert!(
            err.contains("gnss_noise.white_std_m") && err.contains("NaN"),
            "{err}"
        );
        let mut bad = DriveSpec::default();
        bad.speed.cruise_max_mps = 0.1;
        assert!(matches!(
            bad.validate(),
            Err(ScenarioError::InvalidDrive {
                field: "speed.cruise_max_mps",
                ..
            })
        ));
    }

    /// FNV-1a over the bit patterns of every sample and truth field (and the line numbers).
    fn drive_fingerprint(drive: &SimulatedDrive) -> u64 {
        let mut hash = 0xcbf2_9ce4_8422_2325u64;
        let mut eat = |value: f64| {
            for byte in value.to_bits().to_le_bytes() {
                hash ^= u64::from(byte);
                hash = hash.wrapping_mul(0x0100_0000_01b3);
            }
        };
        for record in &drive.track.records {
            let s = &record.sample;
            for value in [
                s.timestamp_s,
                s.latitude_deg,
                s.longitude_deg,
                s.speed_mps,
                s.heading_deg,
                record.line as f64,
            ] {
                eat(value);
            }
        }
        for t in &drive.truth {
            for value in [
                t.timestamp_s,
                t.latitude_deg,
                t.longitude_deg,
                t.speed_mps,
                t.heading_deg,
            ] {
                eat(value);
            }
        }
        hash
    }

    /// Specs whose drives were pinned before onboard errors, multipath and outages existed: their
    /// defaults must leave these drives unchanged bit for bit.
    fn pinned_specs() -> [DriveSpec; 3] {
        let mut ten_hz = DriveSpec {
            duration_s: 120.0,
            rate_hz: 10.0,
            start_heading_deg: 45.0,
            seed: 7,
            ..DriveSpec::default()
        };
        ten_hz.gnss_noise = GnssNoise {
            white_std_m: 0.8,
            bias_std_m: 2.0,
            bias_time_constant_s: 90.0,
        };
        ten_hz.onboard_noise = OnboardNoise {
            speed_std_mps: 0.1,
            heading_std_deg: 2.0,
        };
        let mut fast = DriveSpec {
            duration_s: 600.0,
            seed: 12_345,
            ..DriveSpec::default()
        };
        fast.speed.cruise_min_mps = 2.0;
        fast.speed.cruise_max_mps = 25.0;
        fast.turns.roam_radius_m = 1000.0;
        [DriveSpec::default(), ten_hz, fast]
    }

    #[test]
    fn drives_without_the_new_errors_are_unchanged_bit_for_bit() {
        // Computed on the simulator as it was before onboard errors, multipath and outages existed.
        let pinned: [(usize, u64, [f64; 4]); 3] = [
            (
                1801,
                0x343c_cfa3_bbc5_9091,
                [
                    32.22772038615564,
                    -110.91269911298151,
                    4.786362304136636,
                    266.9499750022632,
                ],
            ),
            (
                1201,
                0xe013_adb6_12eb_0c84,
                [
                    32.23064242127337,
                    -110.90936210217251,
                    0.0,
                    16.422280913632758,
                ],
            ),
            (
                601,
                0x36d6_37b4_6c36_3d86,
                [
                    32.223850520351164,
                    -110.91259880373845,
                    2.357380971017422,
                    251.35200170902345,
                ],
            ),
        ];
        for (spec, (rows, fingerprint, last_values)) in pinned_specs().iter().zip(pinned) {
            let drive = simulate_drive_with_truth(spec, "v").expect("valid spec");
            let last = drive.track.records.last().expect("rows").sample;
            assert_eq!(drive.track.records.len(), rows, "seed {}", spec.seed);
            assert_eq!(
                [
                    last.latitude_deg,
                    last.longitude_deg,
                    last.speed_mps,
                    last.heading_deg
                ],
                last_values,
                "seed {}",
                spec.seed
            );
            assert_eq!(
                drive_fingerprint(&drive),
                fingerprint,
                "seed {}: {:#018x}",
                spec.seed,
                drive_fingerprint(&drive)
            );
        }
    }

    #[test]
    fn realistic_drives_are_unchanged_bit_for_bit() {
        // Drives of `realistic().draw(seed)` (10 Hz; 5 Hz; 1 Hz with outages and multipath) simulated
        // before the fleet error sources existed.
        let pinned: [(u64, f64, usize, usize, usize, u64); 3] = [
            (0, 900.0, 9001, 0, 32, 0xcac2_0353_b7e6_8ca7),
            (1, 900.0, 4501, 0, 7, 0x793b_fe0c_4c0e_a6d1),
            (42, 3600.0, 3480, 6, 28, 0x2707_5716_caf3_7455),
        ];
        let distribution = super::super::DriveDistribution::realistic();
        for (seed, duration_s, rows, outages, multipath, fingerprint) in pinned {
            let spec = DriveSpec {
                duration_s,
                ..distribution.draw(seed)
            };
            let drive = simulate_drive_with_truth(&spec, "v").expect("a drawn spec is valid");
            assert_eq!(drive.track.records.len(), rows, "seed {seed}");
            assert_eq!(drive.outages.len(), outages, "seed {seed}");
            assert_eq!(drive.multipath_rows.len(), multipath, "seed {seed}");
            assert_eq!(
                drive_fingerprint(&drive),
                fingerprint,
                "seed {seed}: {:#018x}",
                drive_fingerprint(&drive)
            );
        }
    }
}
