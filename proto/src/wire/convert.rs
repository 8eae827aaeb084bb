//! Conversions between core types and `spoofwatch.v1` messages. Pure data mapping: no validation
//! (the server validates core values after converting) and no knowledge of storage.

use prost_types::Timestamp;
use spoofwatch_core::alarm::OperatingPoint;
use spoofwatch_core::detector::Decision;
use spoofwatch_core::evidence::Evidence;
use spoofwatch_core::evidence::drift::DriftEvidence;
use spoofwatch_core::metrics::Metrics;
use spoofwatch_core::sample::Sample;

use crate::v1;

/// A wire sample as a core sample (validation happens separately, on the core type).
pub fn sample_from_proto(s: &v1::Sample) -> Sample {
    let &v1::Sample {
        timestamp_s,
        latitude_deg,
        longitude_deg,
        speed_mps,
        heading_deg,
        position_std_m,
        speed_std_mps,
        heading_std_deg,
    } = s;
    Sample {
        timestamp_s,
        latitude_deg,
        longitude_deg,
        speed_mps,
        heading_deg,
        position_std_m,
        speed_std_mps,
        heading_std_deg,
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
        assert_eq!(sample_from_proto(&sample_to_proto(&s)), s);
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
