//! Validation of sample batches, declared once (checked by the session against its last
//! timestamp). Every problem becomes a field violation, and nothing is applied unless the whole
//! batch is valid. Owns no session state; vehicle ids are checked at the edge
//! (`spoofwatch_proto::wire::VehicleId`).

use spoofwatch_core::geo::{LatLon, wgs84_local_displacement};
use spoofwatch_core::sample::{Sample, readable};
use spoofwatch_proto::wire::limits::{BACKWARD_TOLERANCE_S, MAX_FORWARD_JUMP_S, MAX_TIMESTAMP_S};

/// At a session's start, pairs of consecutive samples at least this far apart (s) whose vehicle
/// reports at least [`MOVING_MPS`] are checked for a time unit 1,000 times too small.
const UNIT_CHECK_GAP_S: f64 = 50.0;
const MOVING_MPS: f64 = 2.0;
/// Fixes that moved less than 1/100 of what the reported speed covers in the gap, in every checked
/// pair (at least two): the times are milliseconds (the fixes moved 1/1000 of it).
const UNIT_CHECK_RATIO: f64 = 0.01;

/// Validates a batch that follows `last_timestamp_s` (the session's last accepted sample).
/// `prefix` names the repeated field, e.g. `batch.samples`.
pub fn validate_batch(
    samples: &[Sample],
    last_timestamp_s: Option<f64>,
    max_samples: usize,
    prefix: &str,
) -> Result<(), Vec<(String, String)>> {
    if samples.is_empty() || samples.len() > max_samples {
        return Err(vec![(
            prefix.to_string(),
            format!(
                "must hold 1 to {max_samples} samples, got {}",
                samples.len()
            ),
        )]);
    }
    // A first batch's time unit is checked before its samples' own fields (it reads the fixes'
    // geometry first) and reported after them.
    let unit = if last_timestamp_s.is_none() {
        milliseconds_at_start(samples, prefix)
    } else {
        None
    };
    let mut violations = Vec::new();
    let mut previous = last_timestamp_s;
    for (i, sample) in samples.iter().enumerate() {
        for v in sample.violations() {
            violations.push((format!("{prefix}[{i}].{}", v.field), v.description));
        }
        let t = sample.timestamp_s;
        if let Some(prev) = previous
            && t.is_finite()
        {
            let field = || format!("{prefix}[{i}].timestamp_s");
            if t < prev - BACKWARD_TOLERANCE_S {
                violations.push((
                    field(),
                    format!(
                        "goes backwards from {} to {} (more than {BACKWARD_TOLERANCE_S} s)",
                        readable(prev),
                        readable(t)
                    ),
                ));
            } else if t - prev > MAX_FORWARD_JUMP_S {
                violations.push((
                    field(),
                    format!(
                        "jumps {} s ahead of the previous sample at {} (more than \
                         {MAX_FORWARD_JUMP_S} s: wrong time unit?); reset the session to restart it \
                         at a later time",
                        readable(t - prev),
                        readable(prev)
                    ),
                ));
            }
        }
        if t.is_finite() {
            previous = Some(previous.map_or(t, |p| p.max(t)));
        }
    }
    violations.extend(unit);
    if violations.is_empty() {
        Ok(())
    } else {
        Err(violations)
    }
}

/// Times in milliseconds sent as seconds, caught at a session's start (`samples` is its first
/// batch): absolute times beyond [`MAX_TIMESTAMP_S`], or relative ones whose gaps are 1,000 times
/// what the fixes and the reported speed say. Accepted, they would turn every second of driving
/// into a 17-minute outage and hide any attack.
fn milliseconds_at_start(samples: &[Sample], prefix: &str) -> Option<(String, String)> {
    let relative = 'pairs: {
        let mut checked = 0;
        for pair in samples.windows(2) {
            let (a, b) = (&pair[0], &pair[1]);
            let gap = b.timestamp_s - a.timestamp_s;
            if !(gap >= UNIT_CHECK_GAP_S && a.speed_mps >= MOVING_MPS) {
                continue;
            }
            let [east, north] = wgs84_local_displacement(
                LatLon::new(a.latitude_deg, a.longitude_deg),
                LatLon::new(b.latitude_deg, b.longitude_deg),
            );
            if east.hypot(north) >= UNIT_CHECK_RATIO * a.speed_mps * gap {
                break 'pairs None;
            }
            checked += 1;
        }
        (checked >= 2).then(|| {
            (
                format!("{prefix}[1].timestamp_s"),
                "the samples are seconds apart by the fixes and the reported speed, but their \
                 times are 1,000 times further apart: send seconds (this looks like milliseconds)"
                    .to_string(),
            )
        })
    };
    // An absolute time beyond the bound is named first: it says which sample is wrong.
    if let Some(i) = samples.iter().position(|s| s.timestamp_s > MAX_TIMESTAMP_S) {
        return Some((
            format!("{prefix}[{i}].timestamp_s"),
            format!(
                "{} s is after the year 5000: send seconds (this looks like milliseconds)",
                readable(samples[i].timestamp_s)
            ),
        ));
    }
    relative
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample(t: f64, lat: f64) -> Sample {
        Sample::new(t, lat, -110.9, 2.0, 90.0)
    }

    #[test]
    fn a_good_batch_passes() {
        let batch = [sample(10.0, 32.0), sample(11.0, 32.0), sample(10.8, 32.0)];
        assert_eq!(validate_batch(&batch, Some(9.0), 10, "s"), Ok(()));
    }

    #[test]
    fn every_bad_field_and_backward_time_is_named() {
        let batch = [
            sample(10.0, f64::NAN),
            sample(12.0, 95.0),
            sample(11.0, 32.0),
        ];
        let errors = validate_batch(&batch, Some(10.2), 10, "batch.samples").unwrap_err();
        let fields: Vec<&str> = errors.iter().map(|(f, _)| f.as_str()).collect();
        assert_eq!(
            fields,
            [
                "batch.samples[0].latitude_deg",
                "batch.samples[1].latitude_deg",
                "batch.samples[2].timestamp_s"
            ]
        );
    }

    #[test]
    fn time_before_the_session_is_rejected() {
        let errors = validate_batch(&[sample(5.0, 32.0)], Some(10.0), 10, "s").unwrap_err();
        assert_eq!(errors[0].0, "s[0].timestamp_s");
    }

    #[test]
    fn a_far_jump_ahead_is_refused_and_does_not_blind_the_session() {
        // Milliseconds sent once into a seconds stream.
        let errors =
            validate_batch(&[sample(1_700_000_000_000.0, 32.0)], Some(100.0), 10, "s").unwrap_err();
        assert_eq!(errors[0].0, "s[0].timestamp_s");
        assert!(errors[0].1.contains("1.700e12 s ahead"), "{}", errors[0].1);
        // Nothing was applied, so the next sample follows the session's real last time.
        assert_eq!(
            validate_batch(&[sample(101.0, 32.0)], Some(100.0), 10, "s"),
            Ok(())
        );
        // A long pause within the bound, and a jump inside one batch.
        assert_eq!(
            validate_batch(&[sample(80_000.0, 32.0)], Some(100.0), 10, "s"),
            Ok(())
        );
        let inside = [sample(1.0, 32.0), sample(90_000.0, 32.0)];
        assert_eq!(
            validate_batch(&inside, None, 10, "s").unwrap_err()[0].0,
            "s[1].timestamp_s"
        );
    }

    #[test]
    fn milliseconds_are_caught_at_a_session_start() {
        // Epoch milliseconds.
        let errors = validate_batch(&[sample(1.7e12, 32.0)], None, 10, "s").unwrap_err();
        assert!(
            errors[0].1.contains("looks like milliseconds"),
            "{}",
            errors[0].1
        );
        // Relative milliseconds of a vehicle at 2 m/s moving 2 m per sample (1 s apart).
        let step = 2.0 / 111_000.0;
        let relative: Vec<_> = (0..5)
            .map(|i| sample(f64::from(i) * 1000.0, 32.0 + f64::from(i) * step))
            .collect();
        let errors = validate_batch(&relative, None, 10, "s").unwrap_err();
        assert_eq!(errors[0].0, "s[1].timestamp_s");
        // The same fixes in seconds pass, and so do real 100 s gaps of a moving vehicle.
        let seconds: Vec<_> = (0..5)
            .map(|i| sample(f64::from(i), 32.0 + f64::from(i) * step))
            .collect();
        assert_eq!(validate_batch(&seconds, None, 10, "s"), Ok(()));
        let outages: Vec<_> = (0..5)
            .map(|i| sample(f64::from(i) * 100.0, 32.0 + f64::from(i) * 100.0 * step))
            .collect();
        assert_eq!(validate_batch(&outages, None, 10, "s"), Ok(()));
    }

    #[test]
    fn backward_time_is_printed_readably() {
        let errors = validate_batch(&[sample(5.0, 32.0)], Some(1e301), 10, "s").unwrap_err();
        assert!(errors[0].1.len() < 100, "{}", errors[0].1);
        assert!(
            errors[0].1.contains("from 1.000e301 to 5"),
            "{}",
            errors[0].1
        );
    }

    #[test]
    fn batch_size_is_bounded() {
        assert!(validate_batch(&[], None, 10, "s").is_err());
        let big: Vec<_> = (0..11).map(|i| sample(f64::from(i), 32.0)).collect();
        assert_eq!(validate_batch(&big, None, 10, "s").unwrap_err()[0].0, "s");
    }

    #[test]
    fn receiver_status_out_of_range_is_named() {
        let mut bad = sample(10.0, 32.0);
        bad.satellites_used = Some(300);
        bad.hdop = Some(f64::NAN);
        let errors = validate_batch(&[sample(9.0, 32.0), bad], None, 10, "batch.samples")
            .expect_err("out of range");
        let fields: Vec<&str> = errors.iter().map(|(f, _)| f.as_str()).collect();
        assert_eq!(
            fields,
            ["batch.samples[1].hdop", "batch.samples[1].satellites_used"]
        );
    }
}
