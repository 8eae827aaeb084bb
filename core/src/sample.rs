//! The input sample (SPEC §2) and labelled recorded rows.
//!
//! Owns the sample/record/track types and their validity checks. Must not depend on any other module of
//! the crate.

use serde::{Deserialize, Serialize};

/// Largest plausible ground speed (m/s); faster samples are invalid (SPEC §2, §4).
pub const MAX_SPEED_MPS: f64 = 80.0;
/// Largest reported 1-σ position error: a receiver that unsure has no fix worth comparing.
pub const MAX_POSITION_STD_M: f64 = 1_000.0;
/// Largest reported 1-σ speed error (the speed range itself).
pub const MAX_SPEED_STD_MPS: f64 = MAX_SPEED_MPS;
/// Largest reported 1-σ heading error: beyond half a turn the heading says nothing.
pub const MAX_HEADING_STD_DEG: f64 = 180.0;

/// One telemetry sample of one vehicle: a GNSS fix plus onboard motion.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Sample {
    /// Seconds; monotonic within a trajectory.
    pub timestamp_s: f64,
    pub latitude_deg: f64,
    pub longitude_deg: f64,
    /// Onboard (non-GNSS) ground speed.
    pub speed_mps: f64,
    /// Onboard heading, degrees clockwise from north.
    pub heading_deg: f64,
    /// Optional 1-sigma horizontal GNSS position error (m), per axis.
    pub position_std_m: Option<f64>,
    /// Optional 1-sigma onboard speed error (m/s).
    pub speed_std_mps: Option<f64>,
    /// Optional 1-sigma onboard heading error (degrees).
    pub heading_std_deg: Option<f64>,
}

/// A number as error messages print it: plain with up to three decimals in the everyday range,
/// scientific outside it (`1e301` is printed as `1.000e301`, not as 302 digits).
pub fn readable(value: f64) -> String {
    if !value.is_finite() {
        return value.to_string();
    }
    if value == 0.0 || (1e-3..1e9).contains(&value.abs()) {
        let text = format!("{value:.3}");
        text.trim_end_matches('0').trim_end_matches('.').to_string()
    } else {
        format!("{value:.3e}")
    }
}

/// A field-level problem with a sample, as reported by the API (`samples[i].<field>`).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct FieldViolation {
    pub field: &'static str,
    pub description: String,
}

impl Sample {
    /// A sample with the five required fields and no optional uncertainties.
    pub fn new(
        timestamp_s: f64,
        latitude_deg: f64,
        longitude_deg: f64,
        speed_mps: f64,
        heading_deg: f64,
    ) -> Self {
        Self {
            timestamp_s,
            latitude_deg,
            longitude_deg,
            speed_mps,
            heading_deg,
            position_std_m: None,
            speed_std_mps: None,
            heading_std_deg: None,
        }
    }

    /// Whether the reported uncertainties that are present are finite and within their documented
    /// ranges (an out-of-range one makes the sample unusable, like any other bad field).
    pub fn uncertainties_in_range(&self) -> bool {
        let in_range = |std: Option<f64>, max: f64| std.is_none_or(|s| (0.0..=max).contains(&s));
        in_range(self.position_std_m, MAX_POSITION_STD_M)
            && in_range(self.speed_std_mps, MAX_SPEED_STD_MPS)
            && in_range(self.heading_std_deg, MAX_HEADING_STD_DEG)
    }

    /// Every out-of-range or non-finite field. Recorded data keeps such samples (they get ν = 0);
    /// the API rejects them with these violations (SPEC §2).
    pub fn violations(&self) -> Vec<FieldViolation> {
        let mut out = Vec::new();
        let mut check = |field: &'static str, value: f64, ok: bool, expect: &str| {
            if !value.is_finite() {
                out.push(FieldViolation {
                    field,
                    description: format!("must be a finite number, got {}", readable(value)),
                });
            } else if !ok {
                out.push(FieldViolation {
                    field,
                    description: format!("must be {expect}, got {}", readable(value)),
                });
            }
        };
        let t = self.timestamp_s;
        check("timestamp_s", t, t >= 0.0, "non-negative seconds");
        let lat = self.latitude_deg;
        check(
            "latitude_deg",
            lat,
            (-90.0..=90.0).contains(&lat),
            "in [-90, 90]",
        );
        let lon = self.longitude_deg;
        check(
            "longitude_deg",
            lon,
            (-180.0..=180.0).contains(&lon),
            "in [-180, 180]",
        );
        let v = self.speed_mps;
        check("speed_mps", v, v.abs() <= MAX_SPEED_MPS, "in [-80, 80] m/s");
        let h = self.heading_deg;
        check(
            "heading_deg",
            h,
            (-360.0..=360.0).contains(&h),
            "in [-360, 360] degrees",
        );
        // The ranges spelt out as literals: nothing is formatted for a valid sample.
        let uncertainties = [
            (
                "position_std_m",
                self.position_std_m,
                MAX_POSITION_STD_M,
                "in [0, 1000] m",
            ),
            (
                "speed_std_mps",
                self.speed_std_mps,
                MAX_SPEED_STD_MPS,
                "in [0, 80] m/s",
            ),
            (
                "heading_std_deg",
                self.heading_std_deg,
                MAX_HEADING_STD_DEG,
                "in [0, 180] degrees",
            ),
        ];
        for (field, value, max, expect) in uncertainties {
            if let Some(value) = value {
                check(field, value, (0.0..=max).contains(&value), expect);
            }
        }
        out
    }
}

/// One recorded row: a sample with its provenance and, in labelled data, its ground truth.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Record {
    pub sample: Sample,
    /// Ground truth: `Some(true)` = spoofed, `Some(false)` = normal, `None` = unlabelled.
    pub label: Option<bool>,
    /// The source's own verdict for comparison (AV-GPS `EKF Detector`), never a model input.
    pub comparator_alarm: Option<bool>,
    /// 1-based line in the source file (for error messages and row outputs).
    pub line: u64,
    /// The source says a new trajectory starts here (AV-GPS date change, Run Time/Hobbs reset).
    /// Gaps and backward time are detected by the evidence builder itself.
    pub trajectory_break: bool,
    /// The row only warms a detector up: it runs through the evidence and the model, as the rows
    /// before a part of a longer recording did on the vehicle, but it is neither fitted on, learned
    /// from nor scored. Set by the experiments that score a part of a recording as the continuation
    /// of its vehicle's stream; every data reader leaves it false.
    #[serde(default)]
    pub warmup: bool,
}

/// The chronological records of one vehicle from one source.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Track {
    pub vehicle_id: String,
    pub records: Vec<Record>,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn numbers_in_messages_stay_short() {
        let cases = [
            (12.0, "12"),
            (0.25, "0.25"),
            (-4.56789, "-4.568"),
            (1e301, "1.000e301"),
            (-2.5e-7, "-2.500e-7"),
            (0.0, "0"),
            (f64::NAN, "NaN"),
            (f64::NEG_INFINITY, "-inf"),
        ];
        for (value, expected) in cases {
            assert_eq!(readable(value), expected);
        }
        let mut s = Sample::new(1e301, 32.0, -110.0, 2.0, 90.0);
        s.speed_std_mps = Some(-1e200);
        let descriptions: Vec<String> = s.violations().into_iter().map(|v| v.description).collect();
        assert_eq!(
            descriptions,
            ["must be in [0, 80] m/s, got -1.000e200"],
            "a finite, huge timestamp is valid for a sample alone"
        );
    }

    #[test]
    fn uncertainties_are_bounded_on_both_sides() {
        let mut s = Sample::new(1.0, 32.0, -110.0, 2.0, 90.0);
        s.position_std_m = Some(1e200);
        s.speed_std_mps = Some(80.5);
        s.heading_std_deg = Some(180.0);
        let violations: Vec<(&str, String)> = s
            .violations()
            .into_iter()
            .map(|v| (v.field, v.description))
            .collect();
        assert_eq!(
            violations,
            [
                (
                    "position_std_m",
                    "must be in [0, 1000] m, got 1.000e200".to_string()
                ),
                (
                    "speed_std_mps",
                    "must be in [0, 80] m/s, got 80.5".to_string()
                ),
            ]
        );
        assert!(!s.uncertainties_in_range());
        s.position_std_m = Some(0.0);
        s.speed_std_mps = Some(0.0);
        assert!(s.violations().is_empty() && s.uncertainties_in_range());
    }

    #[test]
    fn a_plausible_sample_has_no_violations() {
        assert!(
            Sample::new(12.0, 32.23, -110.9, 3.2, 359.0)
                .violations()
                .is_empty()
        );
    }

    #[test]
    fn each_bad_field_is_named() {
        let mut s = Sample::new(-1.0, f64::NAN, 181.0, 81.0, 400.0);
        s.position_std_m = Some(-1.0);
        let fields: Vec<_> = s.violations().iter().map(|v| v.field).collect();
        assert_eq!(
            fields,
            [
                "timestamp_s",
                "latitude_deg",
                "longitude_deg",
                "speed_mps",
                "heading_deg",
                "position_std_m"
            ]
        );
        assert!(s.violations()[1].description.contains("finite"));
    }
}
