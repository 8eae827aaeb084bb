//! Conversions between core types and `spoofwatch.v1` messages. Pure data mapping: no validation
//! beyond what a core type cannot hold (an enum number this build does not know); the server
//! validates core values after converting. No knowledge of storage.

use prost_types::Timestamp;
use spoofwatch_core::alarm::OperatingPoint;
use spoofwatch_core::detector::Decision;
use spoofwatch_core::evidence::Evidence;
use spoofwatch_core::evidence::drift::DriftEvidence;
use spoofwatch_core::evidence::offset::OffsetEvidence;
use spoofwatch_core::explain::{EvidenceKind, Explanation};
use spoofwatch_core::metrics::Metrics;
use spoofwatch_core::sample::{FieldViolation, JammingState, ReceiverState, Sample, SpoofingState};
use spoofwatch_core::severity::{CriticalTest, HeldOffsetTest, Severity};

use crate::v1;

/// A wire sample as a core sample (its values are validated separately, on the core type). The
/// error names each receiver state whose number this build does not know (`spoofing_state`,
/// `jamming_state`).
pub fn sample_from_proto(s: &v1::Sample) -> Result<Sample, Vec<FieldViolation>> {
    let &v1::Sample {
        timestamp_s,
        latitude_deg,
        longitude_deg,
        speed_mps,
        heading_deg,
        position_std_m,
        speed_std_mps,
        heading_std_deg,
        spoofing_state,
        jamming_state,
        satellites_used,
        hdop,
    } = s;
    let spoofing = SpoofingState::from_code(i64::from(spoofing_state));
    let jamming = JammingState::from_code(i64::from(jamming_state));
    match (spoofing, jamming) {
        (Some(spoofing_state), Some(jamming_state)) => Ok(Sample {
            timestamp_s,
            latitude_deg,
            longitude_deg,
            speed_mps,
            heading_deg,
            position_std_m,
            speed_std_mps,
            heading_std_deg,
            spoofing_state,
            jamming_state,
            satellites_used,
            hdop,
        }),
        _ => {
            let unknown = |field: &'static str, number: i32, known: Option<_>| {
                known.is_none().then(|| FieldViolation {
                    field,
                    description: format!("must be a state number in [0, 3], got {number}"),
                })
            };
            Err(
                unknown("spoofing_state", spoofing_state, spoofing.map(|_| ()))
                    .into_iter()
                    .chain(unknown("jamming_state", jamming_state, jamming.map(|_| ())))
                    .collect(),
            )
        }
    }
}

/// A core sample on the wire.
pub fn sample_to_proto(s: &Sample) -> v1::Sample {
    let &Sample {
        timestamp_s,
        latitude_deg,
        longitude_deg,
        speed_mps,
        heading_deg,
        position_std_m,
        speed_std_mps,
        heading_std_deg,
        spoofing_state,
        jamming_state,
        satellites_used,
        hdop,
    } = s;
    v1::Sample {
        timestamp_s,
        latitude_deg,
        longitude_deg,
        speed_mps,
        heading_deg,
        position_std_m,
        speed_std_mps,
        heading_std_deg,
        spoofing_state: i32::from(spoofing_state.code()),
        jamming_state: i32::from(jamming_state.code()),
        satellites_used,
        hdop,
    }
}

/// The evidence behind a decision on the wire (a non-finite Δt, e.g. at a trajectory start, is 0).
pub fn evidence_to_proto(e: &Evidence) -> v1::Evidence {
    v1::Evidence {
        valid: e.valid,
        delta_t_s: if e.delta_t.is_finite() {
            e.delta_t
        } else {
            0.0
        },
        trajectory: e.trajectory,
        eta_east: e.eta[0],
        eta_north: e.eta[1],
        q: e.q,
        accum_log: e.accum_log,
        drift: e.drift.as_ref().map(drift_to_proto),
        offset: e.offset.as_ref().map(offset_to_proto),
    }
}

fn offset_to_proto(o: &OffsetEvidence) -> v1::OffsetEvidence {
    let [offset_east_m, offset_north_m] = o.offset_m;
    let [nis_fast, nis_slow] = o.nis;
    let [share_10s, share_60s] = o.share;
    v1::OffsetEvidence {
        offset_east_m,
        offset_north_m,
        sigma_m: o.sigma_m,
        nis_fast,
        nis_slow,
        held_s: o.held_s,
        share_10s,
        share_60s,
        frozen: o.frozen,
        arrived_by_step: o.arrived_by_step,
        anchor_age_s: o.anchor_age_s,
    }
}

fn drift_to_proto(d: &DriftEvidence) -> v1::DriftEvidence {
    let [speed_scale_error, heading_bias_deg, timing_offset_s] = d.calibration;
    let [calibrated_z_east, calibrated_z_north] = d.calibrated_z[2];
    v1::DriftEvidence {
        statistic: d.statistic,
        warm_up: d.warm_up,
        speed_scale_error,
        heading_bias_deg,
        timing_offset_s,
        raw_chi2: d.raw_chi2().to_vec(),
        calibrated_chi2: d.calibrated_chi2().to_vec(),
        calibrated_z_east,
        calibrated_z_north,
        stale_fix_s: d.stale_fix_s,
        residual_log: d.residual_log,
        rate_east_mps: d.rate_mps[0],
        rate_north_mps: d.rate_mps[1],
    }
}

/// An evidence kind on the wire.
pub fn evidence_kind_to_proto(kind: EvidenceKind) -> v1::EvidenceKind {
    match kind {
        EvidenceKind::None => v1::EvidenceKind::None,
        EvidenceKind::Jump => v1::EvidenceKind::Jump,
        EvidenceKind::HeldOffset => v1::EvidenceKind::HeldOffset,
        EvidenceKind::Drift => v1::EvidenceKind::Drift,
        EvidenceKind::FrozenFix => v1::EvidenceKind::FrozenFix,
        EvidenceKind::Energy => v1::EvidenceKind::Energy,
    }
}

/// A wire evidence kind as the core's (`None` for UNSPECIFIED or a value this build does not know).
pub fn evidence_kind_from_proto(kind: i32) -> Option<EvidenceKind> {
    match v1::EvidenceKind::try_from(kind).ok()? {
        v1::EvidenceKind::Unspecified => None,
        v1::EvidenceKind::None => Some(EvidenceKind::None),
        v1::EvidenceKind::Jump => Some(EvidenceKind::Jump),
        v1::EvidenceKind::HeldOffset => Some(EvidenceKind::HeldOffset),
        v1::EvidenceKind::Drift => Some(EvidenceKind::Drift),
        v1::EvidenceKind::FrozenFix => Some(EvidenceKind::FrozenFix),
        v1::EvidenceKind::Energy => Some(EvidenceKind::Energy),
    }
}

/// An explanation on the wire: the vectors as east/north and as magnitude and bearing.
pub fn explanation_to_proto(x: &Explanation) -> v1::Explanation {
    let (offset_m, offset_bearing_deg) = x.offset_polar();
    let (drift_mps, drift_bearing_deg) = x.drift_polar();
    v1::Explanation {
        dominant: evidence_kind_to_proto(x.dominant) as i32,
        offset_east_m: x.offset_m[0],
        offset_north_m: x.offset_m[1],
        offset_m,
        offset_bearing_deg,
        drift_east_mps: x.drift_rate_mps[0],
        drift_north_mps: x.drift_rate_mps[1],
        drift_mps,
        drift_bearing_deg,
    }
}

/// The detector's decision on the sample at `timestamp_s`, served by `model` (`models/{id}`).
pub fn detection_to_proto(timestamp_s: f64, d: &Decision, model: &str) -> v1::Detection {
    v1::Detection {
        timestamp_s,
        probability: d.probability,
        positive: d.positive,
        alarm: d.alarm,
        alarm_onset: d.alarm_onset,
        alarm_end: d.alarm_end,
        evidence: Some(evidence_to_proto(&d.evidence)),
        model: model.to_string(),
        why: Some(explanation_to_proto(&d.explanation)),
        severity: severity_to_proto(d.severity) as i32,
        alarm_escalated: d.escalation,
    }
}

/// A severity on the wire: UNSPECIFIED for none (no alarm open, or no filter).
pub fn severity_to_proto(severity: Option<Severity>) -> v1::AlarmSeverity {
    match severity {
        None => v1::AlarmSeverity::Unspecified,
        Some(Severity::Warning) => v1::AlarmSeverity::Warning,
        Some(Severity::Critical) => v1::AlarmSeverity::Critical,
    }
}

/// A wire severity as the core's: `Ok(None)` for UNSPECIFIED, `Err(number)` for a number this
/// build does not know.
pub fn severity_from_proto(number: i32) -> Result<Option<Severity>, i32> {
    match v1::AlarmSeverity::try_from(number) {
        Ok(v1::AlarmSeverity::Unspecified) => Ok(None),
        Ok(v1::AlarmSeverity::Warning) => Ok(Some(Severity::Warning)),
        Ok(v1::AlarmSeverity::Critical) => Ok(Some(Severity::Critical)),
        Err(_) => Err(number),
    }
}

/// A model's critical test on the wire.
pub fn critical_test_to_proto(test: &CriticalTest) -> v1::CriticalTest {
    v1::CriticalTest {
        reference_logit: test.reference_logit,
        threshold: test.threshold,
        gate: test.gate,
        decisive_s: test.decisive_s,
        frozen_fix_s: test.frozen_fix_s,
        held_jump: test.held_jump.map(held_offset_to_proto),
        held_offset: test.held_offset.map(held_offset_to_proto),
        held_step: test.held_step.map(held_offset_to_proto),
    }
}

/// A held-offset path of a critical test on the wire.
fn held_offset_to_proto(path: HeldOffsetTest) -> v1::HeldOffsetTest {
    v1::HeldOffsetTest {
        gate: path.gate,
        hold_s: path.hold_s,
    }
}

/// An operating point on the wire.
pub fn operating_point_to_proto(op: OperatingPoint) -> v1::OperatingPoint {
    v1::OperatingPoint {
        theta: op.theta,
        persistence: op.n_p,
    }
}

/// A wire operating point as the core's.
pub fn operating_point_from_proto(op: &v1::OperatingPoint) -> OperatingPoint {
    OperatingPoint {
        theta: op.theta,
        n_p: op.persistence,
    }
}

/// Metrics on the wire (the confusion counts and per-event delays stay behind).
pub fn metrics_to_proto(m: &Metrics) -> v1::Metrics {
    v1::Metrics {
        auroc: m.auroc,
        auprc: m.auprc,
        f1: m.f1,
        precision: m.precision,
        recall: m.recall,
        fpr: m.fpr,
        adr: m.adr,
        mean_delay_s: m.mean_delay_s,
        events: m.events,
        detected_events: m.detected_events,
        false_alarm_rows: m.false_alarm_rows,
        false_alarm_events: m.false_alarm_events,
        false_alarm_onsets: m.false_alarm_onsets,
        valid_rows: m.valid_rows,
    }
}

/// Wire metrics as the core's. What the wire does not carry is rebuilt where it is implied
/// (false positives are the false-alarm rows) and left at zero or empty otherwise.
pub fn metrics_from_proto(m: &v1::Metrics) -> Metrics {
    Metrics {
        auroc: m.auroc,
        auprc: m.auprc,
        precision: m.precision,
        recall: m.recall,
        f1: m.f1,
        fpr: m.fpr,
        true_positives: 0,
        false_positives: m.false_alarm_rows,
        true_negatives: 0,
        false_negatives: 0,
        valid_rows: m.valid_rows,
        events: m.events,
        detected_events: m.detected_events,
        adr: m.adr,
        delays_s: Vec::new(),
        mean_delay_s: m.mean_delay_s,
        false_alarm_rows: m.false_alarm_rows,
        false_alarm_events: m.false_alarm_events,
        false_alarm_onsets: m.false_alarm_onsets,
    }
}

/// Unix milliseconds as a protobuf timestamp.
pub fn timestamp_from_ms(ms: i64) -> Timestamp {
    Timestamp {
        seconds: ms.div_euclid(1000),
        nanos: (ms.rem_euclid(1000) * 1_000_000) as i32,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn timestamps_split_milliseconds_exactly() {
        let t = timestamp_from_ms(1_700_000_000_123);
        assert_eq!((t.seconds, t.nanos), (1_700_000_000, 123_000_000));
        let before_epoch = timestamp_from_ms(-1);
        assert_eq!(
            (before_epoch.seconds, before_epoch.nanos),
            (-1, 999_000_000)
        );
    }

    #[test]
    fn samples_round_trip() {
        let mut s = Sample::new(1.5, 32.2, -110.9, 3.0, 45.0);
        s.speed_std_mps = Some(0.1);
        assert_eq!(sample_from_proto(&sample_to_proto(&s)), Ok(s));
        s.spoofing_state = SpoofingState::Multiple;
        s.jamming_state = JammingState::Warning;
        s.satellites_used = Some(14);
        s.hdop = Some(0.9);
        let wire = sample_to_proto(&s);
        assert_eq!(wire.spoofing_state(), v1::SpoofingState::Multiple);
        assert_eq!(wire.jamming_state(), v1::JammingState::Warning);
        assert_eq!(sample_from_proto(&wire), Ok(s));
    }

    #[test]
    fn wire_states_are_the_u_blox_numbers_and_unknown_ones_are_named() {
        let wire = v1::Sample {
            spoofing_state: v1::SpoofingState::Indicated as i32,
            ..v1::Sample::default()
        };
        let sample = sample_from_proto(&wire).expect("known numbers");
        assert_eq!(sample.spoofing_state, SpoofingState::Indicated);
        assert_eq!(sample.jamming_state, JammingState::Unknown);
        let bad = v1::Sample {
            spoofing_state: 4,
            jamming_state: -1,
            ..v1::Sample::default()
        };
        let violations: Vec<(&str, String)> = sample_from_proto(&bad)
            .expect_err("unknown numbers")
            .into_iter()
            .map(|v| (v.field, v.description))
            .collect();
        assert_eq!(
            violations,
            [
                (
                    "spoofing_state",
                    "must be a state number in [0, 3], got 4".to_string()
                ),
                (
                    "jamming_state",
                    "must be a state number in [0, 3], got -1".to_string()
                ),
            ]
        );
    }

    #[test]
    fn explanations_carry_distance_and_bearing_by_hand() {
        let x = Explanation {
            dominant: EvidenceKind::Jump,
            // 300 m east, 400 m north: 500 m at atan(3/4) = 36.87° east of north.
            offset_m: [300.0, 400.0],
            // 1 m/s west, √3 m/s south: 2 m/s toward 180° + 30° = 210°.
            drift_rate_mps: [-1.0, -(3.0_f64.sqrt())],
        };
        let p = explanation_to_proto(&x);
        assert_eq!(p.dominant(), v1::EvidenceKind::Jump);
        assert_eq!((p.offset_east_m, p.offset_north_m), (300.0, 400.0));
        assert_eq!(p.offset_m, 500.0);
        assert!((p.offset_bearing_deg - 36.869_897_645_844_02).abs() < 1e-9);
        assert_eq!(
            (p.drift_east_mps, p.drift_north_mps),
            (-1.0, -(3.0_f64.sqrt()))
        );
        assert!((p.drift_mps - 2.0).abs() < 1e-12);
        assert!((p.drift_bearing_deg - 210.0).abs() < 1e-9);

        // No evidence: zero vectors, bearing 0 (north), kind NONE (not UNSPECIFIED).
        let p = explanation_to_proto(&Explanation::default());
        assert_eq!(p.dominant(), v1::EvidenceKind::None);
        assert_eq!((p.offset_m, p.offset_bearing_deg), (0.0, 0.0));
        assert_eq!((p.drift_mps, p.drift_bearing_deg), (0.0, 0.0));
    }

    #[test]
    fn evidence_kinds_round_trip_and_unspecified_is_none() {
        for kind in EvidenceKind::ALL {
            assert_eq!(
                evidence_kind_from_proto(evidence_kind_to_proto(kind) as i32),
                Some(kind)
            );
        }
        assert_eq!(evidence_kind_to_proto(EvidenceKind::HeldOffset) as i32, 3);
        assert_eq!(evidence_kind_from_proto(0), None);
        assert_eq!(evidence_kind_from_proto(99), None);
    }

    #[test]
    fn offset_evidence_maps_each_anchor_and_share() {
        let o = OffsetEvidence {
            offset_m: [-12.0, 5.0],
            sigma_m: 2.5,
            nis: [30.0, 18.0],
            held_s: 4.0,
            share: [0.6, 0.1],
            frozen: true,
            arrived_by_step: true,
            anchor_age_s: 90.0,
            ..OffsetEvidence::EMPTY
        };
        let p = offset_to_proto(&o);
        assert_eq!(
            (p.offset_east_m, p.offset_north_m, p.sigma_m),
            (-12.0, 5.0, 2.5)
        );
        assert_eq!((p.nis_fast, p.nis_slow, p.held_s), (30.0, 18.0, 4.0));
        assert_eq!((p.share_10s, p.share_60s), (0.6, 0.1));
        assert!(p.frozen && p.arrived_by_step);
        assert_eq!(p.anchor_age_s, 90.0);
    }

    #[test]
    fn severities_round_trip_and_unknown_numbers_are_kept() {
        for severity in [None, Some(Severity::Warning), Some(Severity::Critical)] {
            assert_eq!(
                severity_from_proto(severity_to_proto(severity) as i32),
                Ok(severity)
            );
        }
        assert_eq!(severity_to_proto(Some(Severity::Critical)) as i32, 2);
        assert_eq!(severity_from_proto(3), Err(3));
        assert_eq!(severity_from_proto(-1), Err(-1));
    }

    #[test]
    fn operating_points_round_trip() {
        let op = OperatingPoint { theta: 0.7, n_p: 3 };
        assert_eq!(
            operating_point_from_proto(&operating_point_to_proto(op)),
            op
        );
    }
}
