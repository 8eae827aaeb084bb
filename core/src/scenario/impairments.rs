//! Sensor errors of real vehicles beyond white noise: onboard speed-scale, heading-bias and timing errors,
//! GNSS multipath outliers and GNSS outages. Onboard errors look like drift (SUBTLE-DRIFT §2), so detectors
//! must be trained and tested on drives that have them.
//!
//! Owns these error specs and the seeded models that draw multipath outliers and outage gaps, each from a
//! stream of its own so that turning them on leaves every other stream (truth, GNSS and onboard noise)
//! unchanged. Range checks live with the rest of the spec in `DriveSpec::validate`. Must not integrate the
//! truth or apply white noise (that is `drive.rs`).

use serde::{Deserialize, Serialize};

use crate::rng::Rng;

/// Mixed into the seed for the multipath stream.
const MULTIPATH_STREAM: u64 = 0x6D75_6C74_6970_6174;
/// Mixed into the seed for the outage stream.
const OUTAGE_STREAM: u64 = 0x6F75_7461_6765_5F31;

/// Onboard sensor errors that look like drift: they live in the body frame and rotate with the vehicle.
/// `Default` is error-free.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct OnboardErrors {
    /// Speed-scale error ε (fraction): reported speed = (1 + ε)·true speed (|ε| ≤ 0.5).
    pub speed_scale_error: f64,
    /// Heading bias β (degrees): reported heading = true heading + β (|β| ≤ 180).
    pub heading_bias_deg: f64,
    /// Timing offset τ_L (s, |τ_L| ≤ 1): onboard speed and heading are the truth at t − τ_L (negative: the
    /// onboard sample leads); the GNSS fix stays at t. Before the drive starts the vehicle stands at its
    /// start.
    pub timing_offset_s: f64,
}

/// GNSS multipath: now and then one fix carries a large outlier. `Default` has none.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Multipath {
    /// Probability that a fix carries an outlier.
    pub probability: f64,
    /// 1-sigma of the outlier per axis (m, ≤ 1000).
    pub std_m: f64,
}

/// GNSS outages: fixes inside a gap are dropped from the track (the truth continues underneath), so the
/// detector sees a time gap. `Default` has none.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Outages {
    /// Mean clean time between gaps (s; exponential, but at least one sample interval so gaps never
    /// merge and the first fix is kept); 0 = no outages.
    pub mean_interval_s: f64,
    /// Shortest gap (s).
    pub min_s: f64,
    /// Longest gap (s).
    pub max_s: f64,
}

/// One GNSS outage that dropped fixes: those with `start_s ≤ t < end_s` (seconds from the drive start).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct GnssOutage {
    pub start_s: f64,
    pub end_s: f64,
}

/// Draws multipath outliers. Every fix draws one uniform and two normals whether it is hit or not, so the
/// probability only moves a threshold and the std only scales the same draws.
pub(super) struct MultipathModel {
    rng: Rng,
    spec: Multipath,
}

impl MultipathModel {
    pub(super) fn new(spec: Multipath, seed: u64) -> Self {
        Self {
            rng: Rng::seed_from_u64(seed ^ MULTIPATH_STREAM),
            spec,
        }
    }

    /// The outlier (east, north metres) of the next fix, if it has one.
    pub(super) fn next_outlier(&mut self) -> Option<(f64, f64)> {
        let hit = self.rng.uniform() < self.spec.probability;
        let east_m = self.spec.std_m * self.rng.normal();
        let north_m = self.spec.std_m * self.rng.normal();
        hit.then_some((east_m, north_m))
    }
}

/// The outage schedule: clean stretches exponential with the mean interval but at least one sample interval
/// long (so consecutive gaps never merge and the first fix is always kept), gaps uniform in [min_s, max_s].
pub(super) struct OutageSchedule {
    rng: Rng,
    spec: Outages,
    min_clean_s: f64,
    /// The current or next gap; `None` without outages.
    next_gap: Option<GnssOutage>,
    /// Whether the current gap has dropped a fix yet.
    next_gap_dropped: bool,
    /// Gaps that dropped fixes, in time order.
    dropped_gaps: Vec<GnssOutage>,
}

impl OutageSchedule {
    pub(super) fn new(spec: Outages, seed: u64, sample_interval_s: f64) -> Self {
        let mut schedule = Self {
            rng: Rng::seed_from_u64(seed ^ OUTAGE_STREAM),
            spec,
            min_clean_s: sample_interval_s,
            next_gap: None,
            next_gap_dropped: false,
            dropped_gaps: Vec::new(),
        };
        if spec.mean_interval_s > 0.0 {
            schedule.next_gap = Some(schedule.gap_after(0.0));
        }
        schedule
    }

    fn gap_after(&mut self, clean_from_s: f64) -> GnssOutage {
        // 1 − u lies in (0, 1], so the logarithm is finite.
        let clean_s =
            (-self.spec.mean_interval_s * (1.0 - self.rng.uniform()).ln()).max(self.min_clean_s);
        let start_s = clean_from_s + clean_s;
        let length_s = self.rng.uniform_range(self.spec.min_s, self.spec.max_s);
        GnssOutage {
            start_s,
            end_s: start_s + length_s,
        }
    }

    /// Whether the fix at `time_s` is lost; times must be asked in increasing order.
    pub(super) fn drops(&mut self, time_s: f64) -> bool {
        while let Some(gap) = self.next_gap
            && time_s >= gap.end_s
        {
            self.next_gap = Some(self.gap_after(gap.end_s));
            self.next_gap_dropped = false;
        }
        let Some(gap) = self.next_gap else {
            return false;
        };
        let dropped = time_s >= gap.start_s;
        if dropped && !self.next_gap_dropped {
            self.dropped_gaps.push(gap);
            self.next_gap_dropped = true;
        }
        dropped
    }

    /// The gaps that dropped fixes so far.
    pub(super) fn into_dropped_gaps(self) -> Vec<GnssOutage> {
        self.dropped_gaps
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geo::{LatLon, wgs84_local_displacement};
    use crate::scenario::{DriveSpec, ScenarioError, SimulatedDrive, simulate_drive_with_truth};

    fn simulate(spec: &DriveSpec) -> SimulatedDrive {
        simulate_drive_with_truth(spec, "v").expect("a valid spec")
    }

    fn drive(duration_s: f64, rate_hz: f64, seed: u64) -> DriveSpec {
        DriveSpec {
            duration_s,
            rate_hz,
            seed,
            ..DriveSpec::default()
        }
    }

    fn mean(values: &[f64]) -> f64 {
        values.iter().sum::<f64>() / values.len() as f64
    }

    /// (east, north) metres from the truth to the fix of one record.
    fn fix_error_m(drive: &SimulatedDrive, row: usize) -> [f64; 2] {
        let (t, s) = (&drive.truth[row], &drive.track.records[row].sample);
        wgs84_local_displacement(
            LatLon::new(t.latitude_deg, t.longitude_deg),
            LatLon::new(s.latitude_deg, s.longitude_deg),
        )
    }

    /// Reported/true speed over the samples moving faster than 1 m/s.
    fn mean_speed_ratio(drive: &SimulatedDrive) -> f64 {
        let ratios: Vec<f64> = drive
            .track
            .records
            .iter()
            .zip(&drive.truth)
            .filter(|(_, t)| t.speed_mps > 1.0)
            .map(|(r, t)| r.sample.speed_mps / t.speed_mps)
            .collect();
        assert!(ratios.len() > 500, "{} moving samples", ratios.len());
        mean(&ratios)
    }

    /// Mean of reported − true heading (degrees, wrapped) over moving samples.
    fn mean_heading_error_deg(drive: &SimulatedDrive) -> f64 {
        let errors: Vec<f64> = drive
            .track
            .records
            .iter()
            .zip(&drive.truth)
            .filter(|(_, t)| t.speed_mps > 1.0)
            .map(|(r, t)| (r.sample.heading_deg - t.heading_deg + 180.0).rem_euclid(360.0) - 180.0)
            .collect();
        mean(&errors)
    }

    #[test]
    fn a_speed_scale_error_scales_the_reported_speed() {
        let clean = drive(1800.0, 1.0, 4);
        let mut scaled = clean;
        scaled.onboard_errors.speed_scale_error = 0.03;
        let (clean, scaled) = (simulate(&clean), simulate(&scaled));
        assert_eq!(scaled.truth, clean.truth);
        let (without, with) = (mean_speed_ratio(&clean), mean_speed_ratio(&scaled));
        assert!((without - 1.0).abs() < 0.003, "{without}");
        assert!((with - 1.03).abs() < 0.003, "{with}");
    }

    #[test]
    fn a_heading_bias_shifts_the_reported_heading() {
        let clean = drive(1800.0, 1.0, 5);
        let mut biased = clean;
        biased.onboard_errors.heading_bias_deg = 4.0;
        let (clean, biased) = (simulate(&clean), simulate(&biased));
        let (without, with) = (
            mean_heading_error_deg(&clean),
            mean_heading_error_deg(&biased),
        );
        assert!(without.abs() < 0.1, "{without}");
        assert!((with - 4.0).abs() < 0.1, "{with}");
        // Headings near north wrap: the bias is added before wrapping into [0, 360).
        assert!(
            biased
                .track
                .records
                .iter()
                .all(|r| (0.0..360.0).contains(&r.sample.heading_deg))
        );
    }

    /// A spec without onboard noise, so onboard values are exactly the (shifted) truth.
    fn noiseless_onboard(duration_s: f64, rate_hz: f64, timing_offset_s: f64) -> DriveSpec {
        let mut spec = drive(duration_s, rate_hz, 6);
        spec.onboard_noise.speed_std_mps = 0.0;
        spec.onboard_noise.heading_std_deg = 0.0;
        spec.onboard_errors.timing_offset_s = timing_offset_s;
        spec
    }

    #[test]
    fn a_timing_offset_reports_the_truth_of_that_much_earlier_or_later() {
        // τ = 0.5 s at 2 Hz and τ = 0.3 s at 10 Hz lag by one and three samples; τ = −1 s at 1 Hz leads by one.
        for (rate_hz, timing_offset_s, lag_rows) in
            [(2.0, 0.5, 1_isize), (10.0, 0.3, 3), (1.0, -1.0, -1)]
        {
            let spec = noiseless_onboard(600.0, rate_hz, timing_offset_s);
            let shifted = simulate(&spec);
            let unshifted = simulate(&noiseless_onboard(600.0, rate_hz, 0.0));
            assert_eq!(shifted.truth, unshifted.truth);
            let records = &shifted.track.records;
            let mut motion_changes = 0;
            for (row, record) in records.iter().enumerate() {
                let Some(source) = row.checked_add_signed(-lag_rows) else {
                    continue;
                };
                let Some(truth) = shifted.truth.get(source) else {
                    continue;
                };
                let context = format!("τ = {timing_offset_s} s, row {row}");
                assert!(
                    (record.sample.speed_mps - truth.speed_mps).abs() < 1e-9,
                    "{context}"
                );
                let heading_error = (record.sample.heading_deg - truth.heading_deg).abs();
                assert!(heading_error.min(360.0 - heading_error) < 1e-9, "{context}");
                // The GNSS fix stays at t.
                assert_eq!(
                    record.sample.latitude_deg,
                    unshifted.track.records[row].sample.latitude_deg
                );
                let now = &shifted.truth[row];
                if truth.speed_mps != now.speed_mps || truth.heading_deg != now.heading_deg {
                    motion_changes += 1;
                }
            }
            // The comparison above can tell a shifted sample from an unshifted one.
            eprintln!(
                "τ = {timing_offset_s} s: {motion_changes} of {} rows",
                records.len()
            );
            assert!(motion_changes >= 30, "{motion_changes}");
        }
    }

    #[test]
    fn multipath_outliers_hit_about_the_given_share_of_fixes_and_nothing_else() {
        let clean = drive(1800.0, 1.0, 8);
        let mut spec = clean;
        spec.multipath = Multipath {
            probability: 0.05,
            std_m: 20.0,
        };
        let (clean, hit) = (simulate(&clean), simulate(&spec));
        let rows = hit.multipath_rows.clone();
        // 1801 fixes × 5 % = 90 expected, binomial std 9.2.
        assert!((60..=120).contains(&rows.len()), "{} outliers", rows.len());
        let mut outlier_axes = Vec::new();
        for (row, (with, without)) in hit
            .track
            .records
            .iter()
            .zip(&clean.track.records)
            .enumerate()
        {
            assert_eq!(with.sample.speed_mps, without.sample.speed_mps);
            assert_eq!(with.sample.heading_deg, without.sample.heading_deg);
            if rows.contains(&row) {
                let [e1, n1] = fix_error_m(&hit, row);
                let [e0, n0] = fix_error_m(&clean, row);
                outlier_axes.extend([e1 - e0, n1 - n0]);
            } else {
                assert_eq!(with.sample, without.sample, "row {row}");
            }
        }
        let rms = mean(&outlier_axes.iter().map(|x| x * x).collect::<Vec<_>>()).sqrt();
        assert!((15.0..25.0).contains(&rms), "outlier rms {rms} m per axis");
    }

    #[test]
    fn outages_drop_gaps_of_the_given_length_and_nothing_else() {
        let rate_hz = 2.0;
        let interval_s = 1.0 / rate_hz;
        let full = drive(3600.0, rate_hz, 9);
        let mut spec = full;
        spec.outages = Outages {
            mean_interval_s: 120.0,
            min_s: 6.0,
            max_s: 30.0,
        };
        let (full, gappy) = (simulate(&full), simulate(&spec));
        // ≈ 3600 / (120 + 18) = 26 gaps expected.
        assert!(
            (12..=45).contains(&gappy.outages.len()),
            "{} outages",
            gappy.outages.len()
        );
        for outage in &gappy.outages {
            let length_s = outage.end_s - outage.start_s;
            assert!((6.0..=30.0).contains(&length_s), "{outage:?}");
        }
        // Every kept row is the full drive's row of that sample; exactly the samples inside outages are gone.
        let in_outage = |t: f64| {
            gappy
                .outages
                .iter()
                .any(|o| (o.start_s..o.end_s).contains(&t))
        };
        let mut kept = gappy.track.records.iter().zip(&gappy.truth).peekable();
        for (full_record, full_truth) in full.track.records.iter().zip(&full.truth) {
            let t = full_record.sample.timestamp_s;
            if in_outage(t) {
                assert_ne!(kept.peek().map(|(r, _)| r.line), Some(full_record.line));
                continue;
            }
            let (record, truth) = kept
                .next()
                .expect("a kept row for every sample outside outages");
            assert_eq!(record, full_record);
            assert_eq!(truth, full_truth);
        }
        assert!(kept.next().is_none());
        // What the detector sees: time steps of one interval, or one gap of [6, 30] s (± one interval).
        let mut gaps = 0;
        for pair in gappy.track.records.windows(2) {
            let missing_s = pair[1].sample.timestamp_s - pair[0].sample.timestamp_s - interval_s;
            if missing_s > 1e-9 {
                gaps += 1;
                assert!(
                    (6.0 - interval_s..=30.0 + interval_s).contains(&missing_s),
                    "{missing_s} s missing before line {}",
                    pair[1].line
                );
            }
            assert!(!pair[1].trajectory_break);
        }
        assert_eq!(gaps, gappy.outages.len());
    }

    #[test]
    fn invalid_error_fields_are_named() {
        let mut specs = Vec::new();
        let mut add = |field: &'static str, edit: &dyn Fn(&mut DriveSpec)| {
            let mut spec = DriveSpec::default();
            edit(&mut spec);
            specs.push((field, spec));
        };
        add("onboard_errors.speed_scale_error", &|s| {
            s.onboard_errors.speed_scale_error = f64::NAN;
        });
        add("onboard_errors.heading_bias_deg", &|s| {
            s.onboard_errors.heading_bias_deg = -181.0;
        });
        add("onboard_errors.timing_offset_s", &|s| {
            s.onboard_errors.timing_offset_s = 1.5;
        });
        add("multipath.probability", &|s| s.multipath.probability = 1.2);
        add("multipath.std_m", &|s| s.multipath.std_m = -1.0);
        add("outages.mean_interval_s", &|s| {
            s.outages.mean_interval_s = f64::INFINITY;
        });
        add("outages.min_s", &|s| s.outages.min_s = -6.0);
        add("outages.max_s", &|s| {
            s.outages = Outages {
                mean_interval_s: 120.0,
                min_s: 30.0,
                max_s: 6.0,
            };
        });
        for (field, spec) in specs {
            match spec.validate() {
                Err(ScenarioError::InvalidDrive { field: named, .. }) => {
                    assert_eq!(named, field);
                }
                other => panic!("{field}: {other:?}"),
            }
        }
    }

    #[test]
    fn specs_written_before_these_errors_existed_still_read_as_error_free() {
        let spec: DriveSpec =
            serde_json::from_str(r#"{"duration_s": 60.0, "seed": 3}"#).expect("old spec JSON");
        assert_eq!(spec.onboard_errors, OnboardErrors::default());
        assert_eq!(spec.multipath, Multipath::default());
        assert_eq!(spec.outages, Outages::default());
        let json = serde_json::to_string(&DriveSpec {
            onboard_errors: OnboardErrors {
                timing_offset_s: -0.2,
                ..OnboardErrors::default()
            },
            ..spec
        })
        .expect("serialises");
        let back: DriveSpec = serde_json::from_str(&json).expect("round trip");
        assert_eq!(back.onboard_errors.timing_offset_s, -0.2);
    }
}
