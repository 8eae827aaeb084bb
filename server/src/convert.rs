//! Conversions between the wire types (spoofwatch.v1) and core/store types.

use prost_types::Timestamp;
use spoofwatch_core::alarm::OperatingPoint;
use spoofwatch_core::detector::Decision;
use spoofwatch_core::metrics::Metrics;
use spoofwatch_core::sample::Sample;
use spoofwatch_proto::v1;

/// A wire sample as a core sample (validation happens separately, on the core type).
pub fn sample_from_proto(s: &v1::Sample) -> Sample {
    Sample {
        timestamp_s: s.timestamp_s,
        latitude_deg: s.latitude_deg,
        longitude_deg: s.longitude_deg,
        speed_mps: s.speed_mps,
        heading_deg: s.heading_deg,
        position_std_m: s.position_std_m,
        speed_std_mps: s.speed_std_mps,
        heading_std_deg: s.heading_std_deg,
    }
}

/// A core sample on the wire.
#[cfg(test)]
pub fn sample_to_proto(s: &Sample) -> v1::Sample {
    v1::Sample {
        timestamp_s: s.timestamp_s,
        latitude_deg: s.latitude_deg,
        longitude_deg: s.longitude_deg,
        speed_mps: s.speed_mps,
        heading_deg: s.heading_deg,
        position_std_m: s.position_std_m,
        speed_std_mps: s.speed_std_mps,
        heading_std_deg: s.heading_std_deg,
    }
}

/// The detector's decision on the wire.
pub fn detection_to_proto(timestamp_s: f64, d: &Decision, model: &str) -> v1::Detection {
    let e = &d.evidence;
    v1::Detection {
        timestamp_s,
        probability: d.probability,
        positive: d.positive,
        alarm: d.alarm,
        alarm_onset: d.alarm_onset,
        alarm_end: d.alarm_end,
        evidence: Some(v1::Evidence {
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
        }),
        model: model.to_string(),
    }
}

pub fn operating_point_to_proto(op: OperatingPoint) -> v1::OperatingPoint {
    v1::OperatingPoint {
        theta: op.theta,
        persistence: op.n_p,
    }
}

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
        valid_rows: m.valid_rows,
    }
}

/// Unix milliseconds as a protobuf timestamp.
pub fn timestamp_from_ms(ms: i64) -> Timestamp {
    Timestamp {
        seconds: ms.div_euclid(1000),
        nanos: (ms.rem_euclid(1000) * 1_000_000) as i32,
    }
}

/// A List* request's paging fields as a store page request.
pub fn page_request(size: i32, token: &str) -> Result<crate::store::PageRequest, tonic::Status> {
    if size < 0 {
        return Err(crate::error::invalid_field(
            "page_size",
            "must not be negative",
        ));
    }
    Ok(crate::store::PageRequest {
        page_size: size as u32,
        page_token: (!token.is_empty()).then(|| token.to_string()),
    })
}

/// Lower-case hex SHA-256 of stored blobs (models, datasets).
pub fn sha256_hex(bytes: &[u8]) -> String {
    use sha2::{Digest, Sha256};
    Sha256::digest(bytes)
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

/// `models/{id}` → `{id}` (a bare id is accepted too).
pub fn strip_collection<'a>(collection: &str, name: &'a str) -> &'a str {
    name.strip_prefix(collection)
        .and_then(|rest| rest.strip_prefix('/'))
        .unwrap_or(name)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn resource_names_accept_both_forms() {
        assert_eq!(strip_collection("models", "models/abc"), "abc");
        assert_eq!(strip_collection("models", "abc"), "abc");
        assert_eq!(strip_collection("operations", "operations/x/y"), "x/y");
    }

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
}
