//! The drive spec: what a simulated drive is (duration, rate, start, speed and turn behaviour, GNSS and
//! onboard noise, onboard errors and the GNSS impairments), its validation, and the kind of road it
//! describes.
//!
//! Owns the spec types, their ranges and the road-kind rule. Must not simulate (that is `drive.rs`) or
//! draw specs at random (that is `randomise.rs`).

use serde::{Deserialize, Serialize};

use super::ScenarioError;
use super::impairments::{
    HeadingBiasWander, Multipath, OnboardErrors, Outages, Reacquisition, StaticHold,
};
use crate::sample::MAX_SPEED_MPS;

/// Largest number of samples one drive may have (guards against absurd specs).
const MAX_DRIVE_SAMPLES: f64 = 10_000_000.0;
/// Largest onboard timing offset (s): enough for real loggers, and it bounds the kept truth history.
const MAX_TIMING_OFFSET_S: f64 = 1.0;
/// A drive whose highest cruise speed reaches this (m/s, 54 km/h) is a highway drive ([`RoadKind`]):
/// above the 50 km/h limit of most city streets.
pub const HIGHWAY_CRUISE_MAX_MPS: f64 = 15.0;

/// The kind of road a drive is on, so reports can group results by it. Rule
/// ([`DriveSpec::road_kind`]): [`RoadKind::Highway`] when the drive's highest cruise speed
/// (`speed.cruise_max_mps`) is at least [`HIGHWAY_CRUISE_MAX_MPS`] (15 m/s), else [`RoadKind::Urban`].
/// In `DriveDistribution::realistic()` and `fleet()` about a quarter of the drives are highway drives.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum RoadKind {
    /// City streets, car parks and test tracks: slow, with frequent stops and turns.
    Urban,
    /// Highways and rural roads: fast, long straights, few stops.
    Highway,
}

impl RoadKind {
    /// `"urban"` or `"highway"` (as serialised).
    pub fn name(self) -> &'static str {
        match self {
            Self::Urban => "urban",
            Self::Highway => "highway",
        }
    }
}

impl std::fmt::Display for RoadKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// Speed behaviour: log-uniform cruise speeds (slow driving dominates, like the AV-GPS test track), bounded
/// acceleration and braking, and stops.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SpeedProfile {
    /// Lowest cruise speed (m/s, > 0).
    pub cruise_min_mps: f64,
    /// Highest cruise speed (m/s, ≤ 80).
    pub cruise_max_mps: f64,
    /// Acceleration towards a higher target speed (m/s²).
    pub acceleration_mps2: f64,
    /// Deceleration towards a lower target speed (m/s²).
    pub braking_mps2: f64,
    /// Shortest cruise maneuver (s).
    pub maneuver_min_s: f64,
    /// Longest cruise maneuver (s).
    pub maneuver_max_s: f64,
    /// Probability that the next maneuver is a stop.
    pub stop_probability: f64,
    /// Shortest standstill (s, after braking).
    pub stop_min_s: f64,
    /// Longest standstill (s, after braking).
    pub stop_max_s: f64,
}

impl Default for SpeedProfile {
    fn default() -> Self {
        Self {
            cruise_min_mps: 0.5,
            cruise_max_mps: 12.0,
            acceleration_mps2: 0.8,
            braking_mps2: 1.5,
            maneuver_min_s: 10.0,
            maneuver_max_s: 60.0,
            stop_probability: 0.2,
            stop_min_s: 5.0,
            stop_max_s: 40.0,
        }
    }
}

/// Turning behaviour: random heading changes at bounded yaw rate and lateral acceleration; beyond the roam
/// radius the vehicle turns back towards its start (a small test area like the AV-GPS track).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TurnBehaviour {
    /// Probability that a cruise maneuver also turns.
    pub turn_probability: f64,
    /// Smallest heading change of a turn (degrees).
    pub turn_min_deg: f64,
    /// Largest heading change of a turn (degrees, ≤ 180).
    pub turn_max_deg: f64,
    /// Yaw-rate limit (degrees/s).
    pub max_yaw_rate_dps: f64,
    /// Lateral-acceleration limit (m/s²): fast vehicles turn more slowly.
    pub max_lateral_accel_mps2: f64,
    /// Distance from the start (m) beyond which maneuvers head back.
    pub roam_radius_m: f64,
}

impl Default for TurnBehaviour {
    fn default() -> Self {
        Self {
            turn_probability: 0.6,
            turn_min_deg: 15.0,
            turn_max_deg: 120.0,
            max_yaw_rate_dps: 20.0,
            max_lateral_accel_mps2: 2.0,
            roam_radius_m: 300.0,
        }
    }
}

/// GNSS error model per axis (east, north): white noise plus a first-order Gauss–Markov bias
/// b_k = φ·b_{k−1} + σ_b·√(1−φ²)·w, φ = exp(−δ/τ), started from its stationary distribution.
///
/// Defaults (0.5 m white, 1.5 m bias with τ = 120 s) give metre-level absolute errors and a median
/// step residual of ≈0.9 m, like the AV-GPS normal rows (0.92 m on Dataset-2's).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct GnssNoise {
    /// 1-sigma white noise per axis (m).
    pub white_std_m: f64,
    /// Stationary 1-sigma of the slowly varying bias per axis (m).
    pub bias_std_m: f64,
    /// Correlation time of the bias (s, > 0).
    pub bias_time_constant_s: f64,
}

impl Default for GnssNoise {
    fn default() -> Self {
        Self {
            white_std_m: 0.5,
            bias_std_m: 1.5,
            bias_time_constant_s: 120.0,
        }
    }
}

/// Onboard sensor noise: white noise on speed (clamped at 0; exactly 0 at standstill) and heading.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct OnboardNoise {
    /// 1-sigma speed noise (m/s).
    pub speed_std_mps: f64,
    /// 1-sigma heading noise (degrees).
    pub heading_std_deg: f64,
}

impl Default for OnboardNoise {
    fn default() -> Self {
        Self {
            speed_std_mps: 0.05,
            heading_std_deg: 1.0,
        }
    }
}

/// Everything that defines a simulated drive. `Default` resembles the AV-GPS test track in Tucson:
/// 30 min at 1 Hz, speeds 0–12 m/s with a median of a few m/s, staying within a few hundred metres.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct DriveSpec {
    /// Length of the drive (s); samples at 0, 1/rate, … ≤ duration.
    pub duration_s: f64,
    /// Output sample rate (Hz).
    pub rate_hz: f64,
    /// Start latitude (degrees, |lat| ≤ 85).
    pub start_lat_deg: f64,
    /// Start longitude (degrees).
    pub start_lon_deg: f64,
    /// Initial heading (degrees clockwise from north, [0, 360)).
    pub start_heading_deg: f64,
    /// Speed behaviour.
    pub speed: SpeedProfile,
    /// Turning behaviour.
    pub turns: TurnBehaviour,
    /// GNSS error model.
    pub gnss_noise: GnssNoise,
    /// Onboard sensor noise.
    pub onboard_noise: OnboardNoise,
    /// Onboard speed-scale, heading-bias and timing errors (default: none).
    pub onboard_errors: OnboardErrors,
    /// GNSS multipath outliers (default: none).
    pub multipath: Multipath,
    /// GNSS outages (default: none).
    pub outages: Outages,
    /// Slow wander of the onboard heading bias (default: none).
    #[serde(default, skip_serializing_if = "HeadingBiasWander::is_default")]
    pub heading_bias_wander: HeadingBiasWander,
    /// The receiver's static hold at standstill (default: none).
    #[serde(default, skip_serializing_if = "StaticHold::is_default")]
    pub static_hold: StaticHold,
    /// Offset first fixes after an outage (default: none).
    #[serde(default, skip_serializing_if = "Reacquisition::is_default")]
    pub reacquisition: Reacquisition,
    /// Seed of the maneuver, noise, multipath, outage, heading-bias wander and reacquisition streams.
    pub seed: u64,
}

impl Default for DriveSpec {
    fn default() -> Self {
        Self {
            duration_s: 1800.0,
            rate_hz: 1.0,
            start_lat_deg: 32.23,
            start_lon_deg: -110.91,
            start_heading_deg: 0.0,
            speed: SpeedProfile::default(),
            turns: TurnBehaviour::default(),
            gnss_noise: GnssNoise::default(),
            onboard_noise: OnboardNoise::default(),
            onboard_errors: OnboardErrors::default(),
            multipath: Multipath::default(),
            outages: Outages::default(),
            heading_bias_wander: HeadingBiasWander::default(),
            static_hold: StaticHold::default(),
            reacquisition: Reacquisition::default(),
            seed: 0,
        }
    }
}

impl DriveSpec {
    /// The kind of road this drive is on (see [`RoadKind`] for the rule).
    pub fn road_kind(&self) -> RoadKind {
        if self.speed.cruise_max_mps >= HIGHWAY_CRUISE_MAX_MPS {
            RoadKind::Highway
        } else {
            RoadKind::Urban
        }
    }

    /// Checks every field (finite, in range, min ≤ max); the first problem is reported.
    pub fn validate(&self) -> Result<(), ScenarioError> {
        let s = &self.speed;
        let t = &self.turns;
        let g = &self.gnss_noise;
        let o = &self.onboard_noise;
        let e = &self.onboard_errors;
        let m = &self.multipath;
        let gaps = &self.outages;
        let w = &self.heading_bias_wander;
        let hold = &self.static_hold;
        let r = &self.reacquisition;
        let samples = self.duration_s * self.rate_hz;
        let checks: [(&'static str, f64, bool, &str); 41] = [
            (
                "duration_s",
                self.duration_s,
                self.duration_s > 0.0,
                "> 0 s",
            ),
            (
                "rate_hz",
                self.rate_hz,
                self.rate_hz > 0.0 && self.rate_hz <= 100.0,
                "in (0, 100] Hz",
            ),
            (
                "duration_s * rate_hz",
                samples,
                samples <= MAX_DRIVE_SAMPLES,
                "at most 1e7 samples",
            ),
            (
                "start_lat_deg",
                self.start_lat_deg,
                self.start_lat_deg.abs() <= 85.0,
                "in [-85, 85]",
            ),
            (
                "start_lon_deg",
                self.start_lon_deg,
                self.start_lon_deg.abs() <= 180.0,
                "in [-180, 180]",
            ),
            (
                "start_heading_deg",
                self.start_heading_deg,
                (0.0..360.0).contains(&self.start_heading_deg),
                "in [0, 360)",
            ),
            (
                "speed.cruise_min_mps",
                s.cruise_min_mps,
                s.cruise_min_mps > 0.0,
                "> 0 m/s",
            ),
            (
                "speed.cruise_max_mps",
                s.cruise_max_mps,
                s.cruise_max_mps >= s.cruise_min_mps && s.cruise_max_mps <= MAX_SPEED_MPS,
                "in [cruise_min_mps, 80] m/s",
            ),
            (
                "speed.acceleration_mps2",
                s.acceleration_mps2,
                s.acceleration_mps2 > 0.0,
                "> 0 m/s²",
            ),
            (
                "speed.braking_mps2",
                s.braking_mps2,
                s.braking_mps2 > 0.0,
                "> 0 m/s²",
            ),
            (
                "speed.maneuver_min_s",
                s.maneuver_min_s,
                s.maneuver_min_s > 0.0,
                "> 0 s",
            ),
            (
                "speed.maneuver_max_s",
                s.maneuver_max_s,
                s.maneuver_max_s >= s.maneuver_min_s,
                ">= maneuver_min_s",
            ),
            (
                "speed.stop_probability",
                s.stop_probability,
                (0.0..=1.0).contains(&s.stop_probability),
                "in [0, 1]",
            ),
            (
                "speed.stop_min_s",
                s.stop_min_s,
                s.stop_min_s >= 0.0,
                ">= 0 s",
            ),
            (
                "speed.stop_max_s",
                s.stop_max_s,
                s.stop_max_s >= s.stop_min_s,
                ">= stop_min_s",
            ),
            (
                "turns.turn_probability",
                t.turn_probability,
                (0.0..=1.0).contains(&t.turn_probability),
                "in [0, 1]",
            ),
            (
                "turns.turn_min_deg",
                t.turn_min_deg,
                t.turn_min_deg >= 0.0,
                ">= 0 degrees",
            ),
            (
                "turns.turn_max_deg",
                t.turn_max_deg,
                t.turn_max_deg >= t.turn_min_deg && t.turn_max_deg <= 180.0,
                "in [turn_min_deg, 180] degrees",
            ),
            (
                "turns.max_yaw_rate_dps",
                t.max_yaw_rate_dps,
                t.max_yaw_rate_dps > 0.0,
                "> 0 degrees/s",
            ),
            (
                "turns.max_lateral_accel_mps2",
                t.max_lateral_accel_mps2,
                t.max_lateral_accel_mps2 > 0.0,
                "> 0 m/s²",
            ),
            (
                "turns.roam_radius_m",
                t.roam_radius_m,
                t.roam_radius_m > 0.0,
                "> 0 m",
            ),
            (
                "gnss_noise.white_std_m",
                g.white_std_m,
                g.white_std_m >= 0.0,
                ">= 0 m",
            ),
            (
                "gnss_noise.bias_std_m",
                g.bias_std_m,
                g.bias_std_m >= 0.0,
                ">= 0 m",
            ),
            (
                "gnss_noise.bias_time_constant_s",
                g.bias_time_constant_s,
                g.bias_time_constant_s > 0.0,
                "> 0 s",
            ),
            (
                "onboard_noise.speed_std_mps",
                o.speed_std_mps,
                o.speed_std_mps >= 0.0,
                ">= 0 m/s",
            ),
            (
                "onboard_noise.heading_std_deg",
                o.heading_std_deg,
                o.heading_std_deg >= 0.0,
                ">= 0 degrees",
            ),
            (
                "onboard_errors.speed_scale_error",
                e.speed_scale_error,
                e.speed_scale_error.abs() <= 0.5,
                "in [-0.5, 0.5]",
            ),
            (
                "onboard_errors.heading_bias_deg",
                e.heading_bias_deg,
                e.heading_bias_deg.abs() <= 180.0,
                "in [-180, 180] degrees",
            ),
            (
                "onboard_errors.timing_offset_s",
                e.timing_offset_s,
                e.timing_offset_s.abs() <= MAX_TIMING_OFFSET_S,
                "in [-1, 1] s",
            ),
            (
                "multipath.probability",
                m.probability,
                (0.0..=1.0).contains(&m.probability),
                "in [0, 1]",
            ),
            (
                "multipath.std_m",
                m.std_m,
                (0.0..=1000.0).contains(&m.std_m),
                "in [0, 1000] m",
            ),
            (
                "outages.mean_interval_s",
                gaps.mean_interval_s,
                gaps.mean_interval_s >= 0.0,
                ">= 0 s (0 = no outages)",
            ),
            ("outages.min_s", gaps.min_s, gaps.min_s >= 0.0, ">= 0 s"),
            (
                "outages.max_s",
                gaps.max_s,
                gaps.max_s >= gaps.min_s,
                ">= min_s",
            ),
            (
                "heading_bias_wander.std_deg",
                w.std_deg,
                (0.0..=30.0).contains(&w.std_deg),
                "in [0, 30] degrees (0 = no wander)",
            ),
            (
                "heading_bias_wander.time_constant_s",
                w.time_constant_s,
                time_constant_ok(w.time_constant_s, w.std_deg),
                "> 0 s (0 only without wander)",
            ),
            (
                "static_hold.engage_speed_mps",
                hold.engage_speed_mps,
                (0.0..=5.0).contains(&hold.engage_speed_mps),
                "in [0, 5] m/s (0 = no static hold)",
            ),
            (
                "static_hold.release_speed_mps",
                hold.release_speed_mps,
                hold.release_speed_mps >= hold.engage_speed_mps
                    && hold.release_speed_mps <= MAX_SPEED_MPS,
                "in [engage_speed_mps, 80] m/s",
            ),
            (
                "static_hold.release_distance_m",
                hold.release_distance_m,
                hold.release_distance_m >= 0.0,
                ">= 0 m",
            ),
            (
                "reacquisition.offset_std_m",
                r.offset_std_m,
                (0.0..=1000.0).contains(&r.offset_std_m),
                "in [0, 1000] m (0 = none)",
            ),
            (
                "reacquisition.time_constant_s",
                r.time_constant_s,
                time_constant_ok(r.time_constant_s, r.offset_std_m),
                "> 0 s (0 only without an offset)",
            ),
        ];
        for (field, value, ok, expected) in checks {
            if !value.is_finite() || !ok {
                return Err(ScenarioError::InvalidDrive {
                    field,
                    expected: format!("a finite number {expected}"),
                    value,
                });
            }
        }
        Ok(())
    }

    /// Number of output samples: 1 + ⌊duration·rate⌋.
    pub fn sample_count(&self) -> usize {
        // The small epsilon keeps e.g. 0.3 s at 10 Hz at 4 samples despite rounding.
        (self.duration_s * self.rate_hz + 1e-9).floor() as usize + 1
    }
}

/// A correlation or decay time of an error source of size `std`: > 0, or 0 when the source is off.
fn time_constant_ok(time_constant_s: f64, std: f64) -> bool {
    time_constant_s > 0.0 || (time_constant_s == 0.0 && std == 0.0)
}
