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
/// Largest number of satellites used in a fix: the receivers' own fields (u-blox `numSV`, PX4
/// `satellites_used`) are 8-bit.
pub const MAX_SATELLITES_USED: u32 = 255;
/// Largest horizontal dilution of precision: NMEA's "no fix" value is 99.99, and a geometry that
/// poor places no fix worth comparing.
pub const MAX_HDOP: f64 = 100.0;

/// The receiver's own spoofing detection. The numbers are u-blox UBX-NAV-STATUS `spoofDetState`
/// and PX4 `sensor_gps.spoofing_state` alike (0 unknown, 1 none, 2 indicated, 3 multiple).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SpoofingState {
    /// Not reported (or the receiver cannot tell).
    #[default]
    Unknown,
    /// The receiver sees no sign of spoofing.
    None,
    /// The receiver indicates spoofing.
    Indicated,
    /// The receiver has several indications of spoofing.
    Multiple,
}

/// The receiver's own jamming detection. The numbers are u-blox UBX-MON-RF `jammingState` and PX4
/// `sensor_gps.jamming_state` alike (0 unknown, 1 ok, 2 warning, 3 critical).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum JammingState {
    /// Not reported (or the receiver cannot tell).
    #[default]
    Unknown,
    /// No significant interference.
    Ok,
    /// Interference visible, the fix still fine.
    Warning,
    /// Interference visible, no fix or a degraded one.
    Critical,
}

/// A receiver state's names and numbers, shared by both states: the name of every variant (as the
/// telemetry CSV writes it) and the u-blox/PX4 number, in the order of the numbers.
pub trait ReceiverState: Copy + Default + PartialEq + 'static {
    /// Every state with its readable name, by number (the u-blox/PX4 code is the index).
    const NAMED: [(Self, &'static str); 4];

    /// The u-blox/PX4 number of the state.
    fn code(self) -> u8 {
        Self::NAMED
            .iter()
            .position(|(state, _)| *state == self)
            .map_or(0, |i| i as u8)
    }

    /// The state of a u-blox/PX4 number; `None` for a number beyond the known ones.
    fn from_code(code: i64) -> Option<Self> {
        let index = usize::try_from(code).ok()?;
        Self::NAMED.get(index).map(|(state, _)| *state)
    }

    /// The readable name (`unknown`, `none`, `indicated`, …).
    fn name(self) -> &'static str {
        Self::NAMED[usize::from(self.code())].1
    }

    /// The state of a readable name (ASCII case ignored); `None` for another word.
    fn from_name(name: &str) -> Option<Self> {
        Self::NAMED
            .iter()
            .find(|(_, known)| known.eq_ignore_ascii_case(name))
            .map(|(state, _)| *state)
    }
}

impl ReceiverState for SpoofingState {
    const NAMED: [(Self, &'static str); 4] = [
        (Self::Unknown, "unknown"),
        (Self::None, "none"),
        (Self::Indicated, "indicated"),
        (Self::Multiple, "multiple"),
    ];
}

impl ReceiverState for JammingState {
    const NAMED: [(Self, &'static str); 4] = [
        (Self::Unknown, "unknown"),
        (Self::Ok, "ok"),
        (Self::Warning, "warning"),
        (Self::Critical, "critical"),
    ];
}

impl SpoofingState {
    /// The receiver raises its spoofing flag (one indication or several).
    pub fn flagged(self) -> bool {
        matches!(self, Self::Indicated | Self::Multiple)
    }
}

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
    /// The receiver's own spoofing detection (`Unknown` when not reported). Evidence for the alarm
    /// lifecycle, never a verdict (`docs/detector.md` §7.3).
    #[serde(default)]
    pub spoofing_state: SpoofingState,
    /// The receiver's own jamming detection (`Unknown` when not reported). Carried, not used.
    #[serde(default)]
    pub jamming_state: JammingState,
    /// Optional number of satellites used in the fix. Carried, not used.
    #[serde(default)]
    pub satellites_used: Option<u32>,
    /// Optional horizontal dilution of precision of the fix. Carried, not used.
    #[serde(default)]
    pub hdop: Option<f64>,
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
    /// A sample with the five required fields, no optional uncertainties and no receiver status.
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
            spoofing_state: SpoofingState::Unknown,
            jamming_state: JammingState::Unknown,
            satellites_used: None,
            hdop: None,
        }
    }

    /// Whether the sample carries any of the receiver's status fields (flags, satellites, HDOP).
    pub fn has_receiver_status(&self) -> bool {
        self.spoofing_state != SpoofingState::Unknown
            || self.jamming_state != JammingState::Unknown
            || self.satellites_used.is_some()
            || self.hdop.is_some()
    }

    /// Whether the reported uncertainties that are present are finite and within their documented
    /// ranges (an out-of-range one makes the sample unusable, like any other bad field).
    pub fn uncertainties_in_range(&self) -> bool {
        let in_range = |std: Option<f64>, max: f64| std.is_none_or(|s| (0.0..=max).contains(&s));
        in_range(self.position_std_m, MAX_POSITION_STD_M)
            && in_range(self.speed_std_mps, MAX_SPEED_STD_MPS)
            && in_range(self.heading_std_deg, MAX_HEADING_STD_DEG)
    }

    /// Every out-of-range or non-finite field. Recorded data keeps such samples (they get ν = 0,
    /// except for a bad satellite count or HDOP, which no evidence reads); the API rejects them
    /// with these violations (SPEC §2).
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
        if let Some(hdop) = self.hdop {
            check(
                "hdop",
                hdop,
                (0.0..=MAX_HDOP).contains(&hdop),
                "in [0, 100]",
            );
        }
        if let Some(satellites) = self.satellites_used
            && satellites > MAX_SATELLITES_USED
        {
            out.push(FieldViolation {
                field: "satellites_used",
                description: format!("must be in [0, 255], got {satellites}"),
            });
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
    fn receiver_status_is_bounded_and_named() {
        let mut s = Sample::new(1.0, 32.0, -110.0, 2.0, 90.0);
        assert!(!s.has_receiver_status());
        s.spoofing_state = SpoofingState::Multiple;
        s.jamming_state = JammingState::Critical;
        s.satellites_used = Some(255);
        s.hdop = Some(100.0);
        assert!(s.violations().is_empty() && s.has_receiver_status());
        s.satellites_used = Some(256);
        s.hdop = Some(f64::INFINITY);
        let violations: Vec<(&str, String)> = s
            .violations()
            .into_iter()
            .map(|v| (v.field, v.description))
            .collect();
        assert_eq!(
            violations,
            [
                ("hdop", "must be a finite number, got inf".to_string()),
                (
                    "satellites_used",
                    "must be in [0, 255], got 256".to_string()
                ),
            ]
        );
        s.hdop = Some(-0.5);
        assert_eq!(
            s.violations()[0].description,
            "must be in [0, 100], got -0.5"
        );
        assert!(s.uncertainties_in_range(), "no evidence reads them");
    }

    #[test]
    fn receiver_states_map_the_u_blox_and_px4_numbers() {
        let spoofing: Vec<_> = (0..5).map(SpoofingState::from_code).collect();
        assert_eq!(
            spoofing,
            [
                Some(SpoofingState::Unknown),
                Some(SpoofingState::None),
                Some(SpoofingState::Indicated),
                Some(SpoofingState::Multiple),
                None
            ]
        );
        assert_eq!(JammingState::from_code(2), Some(JammingState::Warning));
        assert_eq!(JammingState::from_code(-1), None);
        assert_eq!(JammingState::Critical.code(), 3);
        assert_eq!(SpoofingState::Indicated.name(), "indicated");
        assert_eq!(
            SpoofingState::from_name("Multiple"),
            Some(SpoofingState::Multiple)
        );
        assert_eq!(JammingState::from_name("ok"), Some(JammingState::Ok));
        assert_eq!(JammingState::from_name("none"), None);
        let flagged: Vec<bool> = SpoofingState::NAMED
            .iter()
            .map(|(s, _)| s.flagged())
            .collect();
        assert_eq!(flagged, [false, false, true, true]);
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
