//! Plausible synthetic telemetry for load tests: a vehicle circling a loop at constant speed, 1 Hz,
//! with metre-level GNSS noise and consistent onboard speed and heading (so the detector sees
//! ordinary valid evidence, not a stream of rejected or degenerate samples).

use spoofwatch_core::rng::Rng;
use spoofwatch_proto::v1;

/// Metres per degree of latitude (spherical approximation; plenty for a test loop).
const METRES_PER_DEGREE: f64 = 111_320.0;

/// One synthetic vehicle driving clockwise around a circle.
#[derive(Clone, Debug)]
pub struct LoopDriver {
    centre_lat_deg: f64,
    centre_lon_deg: f64,
    radius_m: f64,
    speed_mps: f64,
    /// Bearing of the vehicle from the centre (radians clockwise from north).
    bearing_rad: f64,
    timestamp_s: f64,
    gnss_noise_m: f64,
    rng: Rng,
}

impl LoopDriver {
    /// A driver whose start point, speed (5–15 m/s) and loop (200–600 m radius) derive from `seed`,
    /// near Tucson like the AV-GPS data.
    pub fn new(seed: u64) -> Self {
        let mut rng = Rng::seed_from_u64(seed);
        Self {
            centre_lat_deg: 32.23 + rng.uniform_range(-0.05, 0.05),
            centre_lon_deg: -110.91 + rng.uniform_range(-0.05, 0.05),
            radius_m: rng.uniform_range(200.0, 600.0),
            speed_mps: rng.uniform_range(5.0, 15.0),
            bearing_rad: rng.uniform_range(0.0, std::f64::consts::TAU),
            timestamp_s: 1_000.0,
            gnss_noise_m: 0.5,
            rng,
        }
    }

    /// The next sample (one second after the previous one).
    pub fn next_sample(&mut self) -> v1::Sample {
        let east = self.radius_m * self.bearing_rad.sin() + self.gnss_noise_m * self.rng.normal();
        let north = self.radius_m * self.bearing_rad.cos() + self.gnss_noise_m * self.rng.normal();
        let latitude_deg = self.centre_lat_deg + north / METRES_PER_DEGREE;
        let longitude_deg = self.centre_lon_deg
            + east / (METRES_PER_DEGREE * self.centre_lat_deg.to_radians().cos());
        // Driving clockwise, the direction of travel is 90° right of the bearing from the centre.
        let heading_deg = (self.bearing_rad.to_degrees() + 90.0).rem_euclid(360.0);
        let sample = v1::Sample {
            timestamp_s: self.timestamp_s,
            latitude_deg,
            longitude_deg,
            speed_mps: self.speed_mps,
            heading_deg,
            ..v1::Sample::default()
        };
        self.timestamp_s += 1.0;
        self.bearing_rad =
            (self.bearing_rad + self.speed_mps / self.radius_m).rem_euclid(std::f64::consts::TAU);
        sample
    }

    /// The next `n` samples.
    pub fn next_batch(&mut self, n: usize) -> Vec<v1::Sample> {
        (0..n).map(|_| self.next_sample()).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Distance in metres between two nearby fixes (local flat-earth approximation).
    fn distance_m(a: &v1::Sample, b: &v1::Sample) -> f64 {
        let north = (b.latitude_deg - a.latitude_deg) * METRES_PER_DEGREE;
        let east = (b.longitude_deg - a.longitude_deg)
            * METRES_PER_DEGREE
            * a.latitude_deg.to_radians().cos();
        north.hypot(east)
    }

    #[test]
    fn samples_are_one_second_apart_and_move_at_the_reported_speed() {
        let mut driver = LoopDriver::new(7);
        let samples = driver.next_batch(200);
        for pair in samples.windows(2) {
            assert_eq!(pair[1].timestamp_s - pair[0].timestamp_s, 1.0);
            // Chord ≈ arc for these radii; noise of 0.5 m per axis on each fix bounds the error.
            let moved = distance_m(&pair[0], &pair[1]);
            assert!(
                (moved - pair[0].speed_mps).abs() < 4.0,
                "{moved} vs {}",
                pair[0].speed_mps
            );
        }
    }

    #[test]
    fn the_heading_matches_the_direction_of_travel() {
        let mut driver = LoopDriver::new(3);
        driver.gnss_noise_m = 0.0;
        let a = driver.next_sample();
        let b = driver.next_sample();
        let north = b.latitude_deg - a.latitude_deg;
        let east = (b.longitude_deg - a.longitude_deg) * a.latitude_deg.to_radians().cos();
        let travel_deg = east.atan2(north).to_degrees().rem_euclid(360.0);
        // The chord direction lies half a step's turn past the heading at `a`.
        let half_turn_deg = (a.speed_mps / driver.radius_m).to_degrees() / 2.0;
        let difference =
            (travel_deg - a.heading_deg - half_turn_deg + 540.0).rem_euclid(360.0) - 180.0;
        assert!(difference.abs() < 0.01, "{travel_deg} vs {}", a.heading_deg);
    }

    #[test]
    fn every_sample_passes_the_api_checks() {
        let mut driver = LoopDriver::new(11);
        for sample in driver.next_batch(2_000) {
            let core = spoofwatch_core::sample::Sample::new(
                sample.timestamp_s,
                sample.latitude_deg,
                sample.longitude_deg,
                sample.speed_mps,
                sample.heading_deg,
            );
            assert!(core.violations().is_empty(), "{sample:?}");
        }
    }
}
