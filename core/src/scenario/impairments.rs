//! Sensor errors of real vehicles beyond white noise: onboard speed-scale, heading-bias and timing errors,
//! the slow wander of the heading bias, GNSS multipath outliers, GNSS outages, the offset first fixes of a
//! receiver reacquiring after an outage and a receiver's static hold at standstill. Onboard errors look like
//! drift (SUBTLE-DRIFT §2), so detectors must be trained and tested on drives that have them.
//!
//! Owns these error specs and the seeded models that draw heading-bias wander, multipath outliers, outage
//! gaps and reacquisition offsets, each from a stream of its own so that turning one on leaves every other
//! stream (truth, GNSS and onboard noise, the other errors) unchanged; static hold draws nothing. Range
//! checks live with the rest of the spec in `DriveSpec::validate`. Must not integrate the truth or apply
//! white noise (that is `drive.rs`).

use serde::{Deserialize, Serialize};

use crate::geo::{LatLon, wgs84_local_displacement};
use crate::rng::Rng;

/// Mixed into the seed for the multipath stream.
const MULTIPATH_STREAM: u64 = 0x6D75_6C74_6970_6174;
/// Mixed into the seed for the outage stream.
const OUTAGE_STREAM: u64 = 0x6F75_7461_6765_5F31;
/// Mixed into the seed for the heading-bias wander stream.
const WANDER_STREAM: u64 = 0x7761_6E64_6572_5F31;
/// Mixed into the seed for the reacquisition-offset stream.
const REACQUISITION_STREAM: u64 = 0x7265_6163_7175_6972;
/// A reacquisition offset is applied for this many time constants (then it is below 0.005 % of its start
/// and stops, so later fixes are exactly those of a receiver without it).
const REACQUISITION_TIME_CONSTANTS: f64 = 10.0;

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

/// Slow wander of the onboard heading bias (temperature, magnetic surroundings, gyro alignment): the
/// reported heading carries the constant [`OnboardErrors::heading_bias_deg`] plus a first-order
/// Gauss–Markov process w_k = φ·w_{k−1} + σ·√(1−φ²)·n, φ = exp(−δ/τ), started from its stationary
/// distribution. `Default` has none.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct HeadingBiasWander {
    /// Stationary 1-sigma of the wander (degrees, ≤ 30); 0 = no wander.
    pub std_deg: f64,
    /// Correlation time of the wander (s; > 0 when `std_deg` > 0).
    pub time_constant_s: f64,
}

impl HeadingBiasWander {
    /// Whether this is the default (no wander); such a spec serialises without the field.
    pub fn is_default(&self) -> bool {
        *self == Self::default()
    }
}

/// Static hold: the receiver pins its fix while the vehicle stands still. When the true speed at a fix is
/// below `engage_speed_mps` that fix is reported as usual and every later fix repeats it exactly, until the
/// true speed exceeds `release_speed_mps` or the true position has moved more than `release_distance_m`
/// from where the hold engaged; that fix is reported as usual again. A dropped fix (outage) ends the hold.
/// `Default` has none.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct StaticHold {
    /// The hold engages below this true speed (m/s, ≤ 5); 0 = no static hold.
    pub engage_speed_mps: f64,
    /// The hold releases above this true speed (m/s, ≥ `engage_speed_mps`).
    pub release_speed_mps: f64,
    /// The hold releases when the true position is farther than this from where it engaged (m, ≥ 0).
    pub release_distance_m: f64,
}

impl StaticHold {
    /// Whether this is the default (no static hold); such a spec serialises without the field.
    pub fn is_default(&self) -> bool {
        *self == Self::default()
    }
}

/// Reacquisition after an outage: the first fix after a gap carries an extra offset (east and north, each
/// normal with `offset_std_m`) that decays as exp(−Δt/τ) over the following fixes, a receiver
/// reconverging. It is applied for 10 τ and then stops. `Default` has none.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Reacquisition {
    /// 1-sigma of the first fix's extra offset per axis (m, ≤ 1000); 0 = none.
    pub offset_std_m: f64,
    /// Time constant τ of its decay (s; > 0 when `offset_std_m` > 0).
    pub time_constant_s: f64,
}

impl Reacquisition {
    /// Whether this is the default (no reacquisition offset); such a spec serialises without the field.
    pub fn is_default(&self) -> bool {
        *self == Self::default()
    }
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

/// Draws the heading-bias wander, one normal per sample while it is on.
pub(super) struct HeadingWanderModel {
    rng: Rng,
    spec: HeadingBiasWander,
    /// Gauss–Markov factor φ per sample.
    decay: f64,
    /// The wander of the last sample; `None` before the first.
    wander_deg: Option<f64>,
}

impl HeadingWanderModel {
    pub(super) fn new(spec: HeadingBiasWander, seed: u64, rate_hz: f64) -> Self {
        let decay = if spec.std_deg > 0.0 {
            (-1.0 / (rate_hz * spec.time_constant_s)).exp()
        } else {
            0.0
        };
        Self {
            rng: Rng::seed_from_u64(seed ^ WANDER_STREAM),
            spec,
            decay,
            wander_deg: None,
        }
    }

    /// The heading bias of the next sample: `constant_deg` plus the wander (exactly `constant_deg`
    /// without wander).
    pub(super) fn next_bias_deg(&mut self, constant_deg: f64) -> f64 {
        if self.spec.std_deg == 0.0 {
            return constant_deg;
        }
        let sigma = self.spec.std_deg;
        let wander_deg = match self.wander_deg {
            None => sigma * self.rng.normal(),
            Some(previous) => {
                self.decay * previous
                    + sigma * (1.0 - self.decay * self.decay).sqrt() * self.rng.normal()
            }
        };
        self.wander_deg = Some(wander_deg);
        constant_deg + wander_deg
    }
}

/// A fix pinned by static hold and the true position where the hold engaged.
#[derive(Clone, Copy, Debug)]
struct HeldFix {
    fix: LatLon,
    true_position: LatLon,
}

/// Applies static hold to the kept fixes (draws nothing).
pub(super) struct StaticHoldModel {
    spec: StaticHold,
    held: Option<HeldFix>,
}

impl StaticHoldModel {
    pub(super) fn new(spec: StaticHold) -> Self {
        Self { spec, held: None }
    }

    /// The fix to report for a kept sample measured as `fix`: `Some(held fix)` while the hold pins it,
    /// `None` to report `fix` itself (which engages the hold when the true speed is below the threshold).
    pub(super) fn pinned(
        &mut self,
        true_speed_mps: f64,
        true_position: LatLon,
        fix: LatLon,
    ) -> Option<LatLon> {
        if let Some(held) = self.held {
            let [east_m, north_m] = wgs84_local_displacement(held.true_position, true_position);
            let moved_m = east_m.hypot(north_m);
            if true_speed_mps <= self.spec.release_speed_mps
                && moved_m <= self.spec.release_distance_m
            {
                return Some(held.fix);
            }
            self.held = None;
        }
        if true_speed_mps < self.spec.engage_speed_mps {
            self.held = Some(HeldFix { fix, true_position });
        }
        None
    }

    /// A dropped fix: the receiver lost its solution, so the hold ends.
    pub(super) fn lose_fix(&mut self) {
        self.held = None;
    }
}

/// Draws the offset of the first fix after each outage and decays it.
pub(super) struct ReacquisitionModel {
    rng: Rng,
    spec: Reacquisition,
    /// Time (s) of the first fix after the last outage and its offset (east, north metres).
    current: Option<(f64, [f64; 2])>,
}

impl ReacquisitionModel {
    pub(super) fn new(spec: Reacquisition, seed: u64) -> Self {
        Self {
            rng: Rng::seed_from_u64(seed ^ REACQUISITION_STREAM),
            spec,
            current: None,
        }
    }

    /// The first fix after an outage, at `time_s`: draws its offset (two normals per outage, so the std
    /// only scales the same draws).
    pub(super) fn reacquire(&mut self, time_s: f64) {
        if self.spec.offset_std_m == 0.0 {
            return;
        }
        let east_m = self.spec.offset_std_m * self.rng.normal();
        let north_m = self.spec.offset_std_m * self.rng.normal();
        self.current = Some((time_s, [east_m, north_m]));
    }

    /// The extra offset (east, north metres) of the fix at `time_s`, if one applies.
    pub(super) fn offset_m(&self, time_s: f64) -> Option<[f64; 2]> {
        let (start_s, [east_m, north_m]) = self.current?;
        let elapsed_time_constants = (time_s - start_s) / self.spec.time_constant_s;
        if !(0.0..REACQUISITION_TIME_CONSTANTS).contains(&elapsed_time_constants) {
            return None;
        }
        let factor = (-elapsed_time_constants).exp();
        Some([factor * east_m, factor * north_m])
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
        add("heading_bias_wander.std_deg", &|s| {
            s.heading_bias_wander.std_deg = 31.0;
        });
        add("heading_bias_wander.time_constant_s", &|s| {
            s.heading_bias_wander = HeadingBiasWander {
                std_deg: 1.0,
                time_constant_s: 0.0,
            };
        });
        add("static_hold.engage_speed_mps", &|s| {
            s.static_hold.engage_speed_mps = f64::NAN;
        });
        add("static_hold.release_speed_mps", &|s| {
            s.static_hold = StaticHold {
                engage_speed_mps: 0.5,
                release_speed_mps: 0.2,
                release_distance_m: 3.0,
            };
        });
        add("static_hold.release_distance_m", &|s| {
            s.static_hold.release_distance_m = -1.0;
        });
        add("reacquisition.offset_std_m", &|s| {
            s.reacquisition.offset_std_m = -2.0;
        });
        add("reacquisition.time_constant_s", &|s| {
            s.reacquisition = Reacquisition {
                offset_std_m: 3.0,
                time_constant_s: f64::INFINITY,
            };
        });
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
        assert_eq!(spec.heading_bias_wander, HeadingBiasWander::default());
        assert_eq!(spec.static_hold, StaticHold::default());
        assert_eq!(spec.reacquisition, Reacquisition::default());
        // A spec without them writes no field for them, so it reads where they are unknown.
        let written = serde_json::to_string(&spec).expect("serialises");
        for field in ["heading_bias_wander", "static_hold", "reacquisition"] {
            assert!(!written.contains(field), "{written}");
        }
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
        let with_all = DriveSpec {
            heading_bias_wander: HeadingBiasWander {
                std_deg: 1.0,
                time_constant_s: 600.0,
            },
            static_hold: StaticHold {
                engage_speed_mps: 0.3,
                release_speed_mps: 0.5,
                release_distance_m: 3.0,
            },
            reacquisition: Reacquisition {
                offset_std_m: 3.0,
                time_constant_s: 5.0,
            },
            ..spec
        };
        let json = serde_json::to_string(&with_all).expect("serialises");
        let back: DriveSpec = serde_json::from_str(&json).expect("round trip");
        assert_eq!(back, with_all);
    }

    #[test]
    fn the_static_hold_model_pins_the_engaging_fix_until_speed_or_distance_releases_it() {
        let mut hold = StaticHoldModel::new(StaticHold {
            engage_speed_mps: 0.3,
            release_speed_mps: 0.5,
            release_distance_m: 2.0,
        });
        let at = |north_m: f64| {
            let (lat, lon) = crate::geo::displace_fix(32.0, -110.0, 0.0, north_m);
            LatLon::new(lat, lon)
        };
        let fix = |k: f64| LatLon::new(32.0 + k * 1e-6, -110.0);
        // Moving: reported as measured; slowing below 0.3 m/s engages on this fix, reported as measured.
        assert_eq!(hold.pinned(2.0, at(0.0), fix(0.0)), None);
        assert_eq!(hold.pinned(0.2, at(1.0), fix(1.0)), None);
        // Standing, and creeping at up to 0.5 m/s within 2 m: the engaging fix, exactly.
        assert_eq!(hold.pinned(0.0, at(1.0), fix(2.0)), Some(fix(1.0)));
        assert_eq!(hold.pinned(0.5, at(2.9), fix(3.0)), Some(fix(1.0)));
        // Moving off faster than 0.5 m/s releases: the new fix is reported.
        assert_eq!(hold.pinned(0.6, at(3.0), fix(4.0)), None);
        assert_eq!(hold.pinned(0.6, at(3.5), fix(5.0)), None);
        // Engaged again; more than 2 m of true motion at low speed releases it too.
        assert_eq!(hold.pinned(0.1, at(10.0), fix(6.0)), None);
        assert_eq!(hold.pinned(0.4, at(11.9), fix(7.0)), Some(fix(6.0)));
        assert_eq!(hold.pinned(0.4, at(12.1), fix(8.0)), None);
        // That fix (0.4 m/s) does not engage; the next standing fix does. A lost fix ends a hold.
        assert_eq!(hold.pinned(0.0, at(12.1), fix(9.0)), None);
        assert_eq!(hold.pinned(0.0, at(12.1), fix(10.0)), Some(fix(9.0)));
        hold.lose_fix();
        assert_eq!(hold.pinned(0.0, at(12.1), fix(11.0)), None);
        // Off (the default): never pins.
        let mut off = StaticHoldModel::new(StaticHold::default());
        assert_eq!(off.pinned(0.0, at(0.0), fix(0.0)), None);
        assert_eq!(off.pinned(0.0, at(0.0), fix(1.0)), None);
    }

    #[test]
    fn static_hold_repeats_one_fix_while_standing_and_leaves_moving_rows_alone() {
        let clean = drive(3600.0, 2.0, 11);
        let mut spec = clean;
        spec.static_hold = StaticHold {
            engage_speed_mps: 0.3,
            release_speed_mps: 0.5,
            release_distance_m: 3.0,
        };
        let (clean, held) = (simulate(&clean), simulate(&spec));
        assert_eq!(held.truth, clean.truth);
        assert!(clean.held_rows.is_empty());
        let rows = &held.held_rows;
        // The test track stops every few maneuvers for 5–40 s.
        assert!(rows.len() > 200, "{} held rows", rows.len());
        let records = &held.track.records;
        let mut standing_rows = 0;
        for (row, (with, without)) in records.iter().zip(&clean.track.records).enumerate() {
            let (s, truth) = (&with.sample, &held.truth[row]);
            // Onboard values and time are never touched.
            assert_eq!(
                (s.timestamp_s, s.speed_mps, s.heading_deg),
                (
                    without.sample.timestamp_s,
                    without.sample.speed_mps,
                    without.sample.heading_deg
                )
            );
            if rows.contains(&row) {
                // A pinned fix repeats the previous row's fix exactly: one fix for the whole standstill.
                let previous = &records[row - 1].sample;
                assert_eq!(
                    (s.latitude_deg, s.longitude_deg),
                    (previous.latitude_deg, previous.longitude_deg),
                    "row {row}"
                );
                assert!(truth.speed_mps <= 0.5, "row {row}");
            } else {
                // Every other row, moving or engaging, is the row without static hold, bit for bit.
                assert_eq!(with, without, "row {row}");
                if row > 0 && rows.contains(&(row - 1)) {
                    // A release: moving off faster than the release speed (or 3 m from the engaging
                    // position, not reached at these speeds).
                    assert!(truth.speed_mps > 0.5, "row {row}: {truth:?}");
                }
            }
            if row > 0 && held.truth[row - 1].speed_mps < 0.3 && truth.speed_mps <= 0.5 {
                standing_rows += 1;
                assert!(rows.contains(&row), "row {row} stands but is not held");
            }
        }
        assert_eq!(standing_rows, rows.len());
        // Without static hold a standing receiver's fix jitters.
        let jittering = rows
            .iter()
            .filter(|&&row| {
                let (a, b) = (&clean.track.records[row - 1], &clean.track.records[row]);
                a.sample.latitude_deg != b.sample.latitude_deg
            })
            .count();
        assert_eq!(jittering, rows.len());
    }

    /// Reported − true heading (degrees, wrapped into [−180, 180)) of every row.
    fn heading_errors_deg(drive: &SimulatedDrive) -> Vec<f64> {
        drive
            .track
            .records
            .iter()
            .zip(&drive.truth)
            .map(|(r, t)| (r.sample.heading_deg - t.heading_deg + 180.0).rem_euclid(360.0) - 180.0)
            .collect()
    }

    #[test]
    fn heading_bias_wander_moves_the_bias_slowly_with_the_given_std() {
        // Ten hours at 1 Hz without onboard noise or timing offset: reported − true heading is the bias.
        let mut clean = noiseless_onboard(36_000.0, 1.0, 0.0);
        clean.onboard_errors.heading_bias_deg = 2.0;
        let mut spec = clean;
        spec.heading_bias_wander = HeadingBiasWander {
            std_deg: 1.0,
            time_constant_s: 300.0,
        };
        let (clean, wandering) = (simulate(&clean), simulate(&spec));
        assert_eq!(wandering.truth, clean.truth);
        for (with, without) in wandering.track.records.iter().zip(&clean.track.records) {
            // GNSS fixes and speeds are unchanged; only the heading moves.
            assert_eq!(with.sample.latitude_deg, without.sample.latitude_deg);
            assert_eq!(with.sample.longitude_deg, without.sample.longitude_deg);
            assert_eq!(with.sample.speed_mps, without.sample.speed_mps);
        }
        let constant = heading_errors_deg(&clean);
        assert!(constant.iter().all(|e| (e - 2.0).abs() < 1e-9));
        let biases = heading_errors_deg(&wandering);
        let mean_bias = mean(&biases);
        let std = mean(
            &biases
                .iter()
                .map(|b| (b - mean_bias).powi(2))
                .collect::<Vec<_>>(),
        )
        .sqrt();
        // 120 correlation times: the mean is 2° within a few tenths, the std 1° within a few tenths.
        assert!((mean_bias - 2.0).abs() < 0.4, "mean {mean_bias}");
        assert!((0.75..1.25).contains(&std), "std {std}");
        // Slow: one second moves it by σ·√(2/τ) ≈ 0.08° rms.
        let steps: Vec<f64> = biases.windows(2).map(|w| (w[1] - w[0]).powi(2)).collect();
        let step_rms = mean(&steps).sqrt();
        assert!((0.06..0.1).contains(&step_rms), "step rms {step_rms}");
        // Over an hour it wanders far from where it started.
        let spread = biases[..3600]
            .iter()
            .fold(0.0_f64, |most, b| most.max((b - biases[0]).abs()));
        assert!(spread > 0.5, "{spread}");
    }

    #[test]
    fn the_first_fix_after_an_outage_is_offset_and_the_offset_decays() {
        let tau_s = 4.0;
        let mut clean = drive(7200.0, 1.0, 13);
        clean.outages = Outages {
            mean_interval_s: 120.0,
            min_s: 6.0,
            max_s: 30.0,
        };
        let mut spec = clean;
        spec.reacquisition = Reacquisition {
            offset_std_m: 3.0,
            time_constant_s: tau_s,
        };
        let (clean, reacquiring) = (simulate(&clean), simulate(&spec));
        assert_eq!(reacquiring.truth, clean.truth);
        assert_eq!(reacquiring.outages, clean.outages);
        assert!(clean.outages.len() >= 30, "{} outages", clean.outages.len());
        let records = &reacquiring.track.records;
        // The row where each reconvergence starts: the first kept row after a gap.
        let first_after_gap = |row: usize| row > 0 && records[row].line > records[row - 1].line + 1;
        let mut first_offsets = Vec::new();
        let mut start: Option<(f64, [f64; 2])> = None;
        for (row, (with, without)) in records.iter().zip(&clean.track.records).enumerate() {
            let t = with.sample.timestamp_s;
            assert_eq!(with.sample.speed_mps, without.sample.speed_mps);
            assert_eq!(with.sample.heading_deg, without.sample.heading_deg);
            let offset = wgs84_local_displacement(
                LatLon::new(without.sample.latitude_deg, without.sample.longitude_deg),
                LatLon::new(with.sample.latitude_deg, with.sample.longitude_deg),
            );
            if first_after_gap(row) {
                assert!(offset[0].hypot(offset[1]) > 0.0, "row {row}");
                first_offsets.extend(offset);
                start = Some((t, offset));
            }
            match start {
                Some((start_s, [east_m, north_m])) if t - start_s < 10.0 * tau_s => {
                    let factor = (-(t - start_s) / tau_s).exp();
                    assert!((offset[0] - factor * east_m).abs() < 1e-3, "row {row}");
                    assert!((offset[1] - factor * north_m).abs() < 1e-3, "row {row}");
                }
                // Before the first outage and once reconverged: exactly the fix without it.
                _ => assert_eq!(with, without, "row {row}"),
            }
        }
        assert_eq!(first_offsets.len(), 2 * clean.outages.len());
        let rms = mean(&first_offsets.iter().map(|x| x * x).collect::<Vec<_>>()).sqrt();
        assert!(
            (2.0..4.0).contains(&rms),
            "first-fix offset rms {rms} m per axis"
        );
    }
}
