//! Subtle-attack scenarios: injection, simulated drives and scenario sets (SPEC §9).

use spoofwatch_core::data::telemetry::write_tracks;
use spoofwatch_core::metrics::Pace;
use spoofwatch_core::sample::{Record, Sample, Track};
use spoofwatch_core::scenario::{
    AttackDuration, AttackKind, AttackSpec, DriveDistribution, DriveSpec,
    RAMP_SWEEP_VELOCITIES_MPS, RoadKind, ScenarioError, ScenarioPlan, generate, inject,
    simulate_drive, simulate_drive_with_truth,
};

// ---- independent geodesy for the checks (WGS-84 local radii; the library keeps its own private copy) ----

fn wgs84_radii_m(latitude_deg: f64) -> (f64, f64) {
    let a = 6_378_137.0;
    let f = 1.0 / 298.257_223_563;
    let e2 = f * (2.0 - f);
    let s2 = latitude_deg.to_radians().sin().powi(2);
    let w = (1.0 - e2 * s2).sqrt();
    (a * (1.0 - e2) / (w * w * w), a / w)
}

/// Flat-earth (east, north) metres from `from` to `to`, radii at `from`.
fn offset_m(from: &Sample, to: &Sample) -> (f64, f64) {
    let (meridian, prime_vertical) = wgs84_radii_m(from.latitude_deg);
    let east = (to.longitude_deg - from.longitude_deg).to_radians()
        * prime_vertical
        * from.latitude_deg.to_radians().cos();
    let north = (to.latitude_deg - from.latitude_deg).to_radians() * meridian;
    (east, north)
}

/// Per step t ≥ 1: GNSS displacement minus the trapezoid motion displacement ½(v_t + v_{t−1})·δ_t.
fn residuals_m(track: &Track) -> Vec<(f64, f64)> {
    track
        .records
        .windows(2)
        .map(|pair| {
            let (prev, cur) = (&pair[0].sample, &pair[1].sample);
            let (ge, gn) = offset_m(prev, cur);
            let dt = cur.timestamp_s - prev.timestamp_s;
            let velocity = |s: &Sample| {
                let h = s.heading_deg.to_radians();
                (s.speed_mps * h.sin(), s.speed_mps * h.cos())
            };
            let (ve0, vn0) = velocity(prev);
            let (ve1, vn1) = velocity(cur);
            (ge - 0.5 * (ve0 + ve1) * dt, gn - 0.5 * (vn0 + vn1) * dt)
        })
        .collect()
}

fn median(mut values: Vec<f64>) -> f64 {
    values.sort_by(f64::total_cmp);
    let n = values.len();
    if n % 2 == 1 {
        values[n / 2]
    } else {
        0.5 * (values[n / 2 - 1] + values[n / 2])
    }
}

/// 100 unlabelled rows at 1 Hz, driving north at 2 m/s from Tucson, GNSS = truth.
fn straight_track() -> Track {
    let (meridian, _) = wgs84_radii_m(32.23);
    let records = (0..100)
        .map(|i| {
            let t = i as f64;
            let lat = 32.23 + (2.0 * t / meridian).to_degrees();
            Record {
                sample: Sample::new(t, lat, -110.91, 2.0, 0.0),
                label: None,
                comparator_alarm: Some(false),
                line: i + 2,
                trajectory_break: false,
                warmup: false,
            }
        })
        .collect();
    Track {
        vehicle_id: "base".into(),
        records,
    }
}

fn spec(kind: AttackKind, direction_deg: f64, onset_s: f64, duration_s: f64) -> AttackSpec {
    AttackSpec {
        kind,
        direction_deg,
        onset_s,
        duration_s,
        seed: None,
    }
}

fn ramp(velocity_mps: f64) -> AttackKind {
    AttackKind::RampDrift { velocity_mps }
}

fn assert_close(actual: (f64, f64), expected: (f64, f64), tolerance: f64, context: &str) {
    assert!(
        (actual.0 - expected.0).abs() < tolerance && (actual.1 - expected.1).abs() < tolerance,
        "{context}: got {actual:?}, expected {expected:?}"
    );
}

// ---- injection ----

#[test]
fn ramp_offsets_match_hand_computed_values() {
    let base = straight_track();
    let injected = inject(&base, &spec(ramp(0.5), 90.0, 10.0, 20.0)).unwrap();
    let offset_at = |row: usize| {
        offset_m(
            &base.records[row].sample,
            &injected.track.records[row].sample,
        )
    };
    // τ = t − onset: 0 at row 10, 4 s at row 14 (0.5 m/s · 4 s = 2 m east), 19 s at row 29.
    assert_close(offset_at(10), (0.0, 0.0), 1e-3, "row 10");
    assert_close(offset_at(14), (2.0, 0.0), 1e-3, "row 14");
    assert_close(offset_at(29), (9.5, 0.0), 1e-3, "row 29");
    // Outside the window the fix is untouched, bit for bit.
    for row in [0, 9, 30, 99] {
        assert_eq!(injected.track.records[row].sample, base.records[row].sample);
    }
}

#[test]
fn accelerating_drift_and_jump_offsets_match_hand_computed_values() {
    let base = straight_track();
    let accel = AttackKind::AcceleratingDrift {
        acceleration_mps2: 0.2,
    };
    // Onset between samples: first attacked row 21 has τ = 0.5 s; row 31 has τ = 10.5 s.
    let injected = inject(&base, &spec(accel, 225.0, 20.5, 30.0)).unwrap();
    assert_eq!(
        (injected.first_attack_row, injected.last_attack_row),
        (21, 50)
    );
    let diagonal = -std::f64::consts::FRAC_1_SQRT_2;
    for (row, tau) in [(21, 0.5), (31, 10.5), (50, 29.5)] {
        let magnitude = 0.5 * 0.2 * tau * tau;
        let got = offset_m(
            &base.records[row].sample,
            &injected.track.records[row].sample,
        );
        let want = (magnitude * diagonal, magnitude * diagonal);
        assert_close(got, want, 1e-3, &format!("accelerating row {row}"));
    }

    let jump = AttackKind::Jump { offset_m: 150.0 };
    let injected = inject(&base, &spec(jump, 0.0, 40.0, 10.0)).unwrap();
    for row in 40..50 {
        let got = offset_m(
            &base.records[row].sample,
            &injected.track.records[row].sample,
        );
        assert_close(got, (0.0, 150.0), 1e-3, &format!("jump row {row}"));
    }
    // After the attack GNSS returns to the truth.
    assert_eq!(injected.track.records[50].sample, base.records[50].sample);
}

#[test]
fn labels_are_exactly_the_attack_rows() {
    let mut base = straight_track();
    base.records[70].label = Some(true); // an existing spoofed row outside the window keeps its label
    let injected = inject(&base, &spec(ramp(1.0), 45.0, 10.0, 20.0)).unwrap();
    assert_eq!(injected.attack_rows(), 10..=29);
    assert_eq!(injected.attack_row_count(), 20);
    assert_eq!(injected.onset_timestamp_s(), 10.0);
    assert_eq!(injected.base_vehicle_id, "base");
    for (row, record) in injected.track.records.iter().enumerate() {
        let expected = (10..30).contains(&row) || row == 70;
        assert_eq!(record.label, Some(expected), "row {row}");
        // The source comparator never saw injected positions.
        assert_eq!(record.comparator_alarm, None);
        assert_eq!(record.line, base.records[row].line);
    }
}

#[test]
fn onboard_speed_and_heading_are_untouched() {
    let base = straight_track();
    let injected = inject(&base, &spec(ramp(2.0), 270.0, 5.0, 50.0)).unwrap();
    for (out, orig) in injected.track.records.iter().zip(&base.records) {
        assert_eq!(out.sample.timestamp_s, orig.sample.timestamp_s);
        assert_eq!(out.sample.speed_mps, orig.sample.speed_mps);
        assert_eq!(out.sample.heading_deg, orig.sample.heading_deg);
    }
}

#[test]
fn frozen_position_holds_the_onset_fix() {
    let base = straight_track();
    let injected = inject(&base, &spec(AttackKind::FrozenPosition, 0.0, 30.0, 15.0)).unwrap();
    let onset_fix = &base.records[30].sample;
    for row in 30..45 {
        let s = &injected.track.records[row].sample;
        assert_eq!(
            (s.latitude_deg, s.longitude_deg),
            (onset_fix.latitude_deg, onset_fix.longitude_deg),
            "row {row}"
        );
    }
    // The vehicle kept moving 2 m/s north: at the last frozen row the truth is 28 m ahead.
    let lag = offset_m(&injected.track.records[44].sample, &base.records[44].sample);
    assert_close(lag, (0.0, 28.0), 1e-3, "frozen lag");
    assert_eq!(injected.track.records[45].sample, base.records[45].sample);
}

#[test]
fn hopping_teleports_every_hold_and_repeats_the_fix_in_between() {
    let base = straight_track();
    let hopping = AttackKind::Hopping {
        offset_m: 10_000.0,
        hold_s: 4.0,
    };
    assert_eq!(hopping.describe(), "hop-10000m-4s");
    assert_eq!(hopping.family(), "hopping");
    let injected = inject(&base, &spec(hopping, 90.0, 20.0, 20.0)).unwrap();
    let onset_fix = &base.records[20].sample;
    // Hop k lands at ½ + ½·frac(k/φ) of 10 km, turned k golden angles (137.5077…°) from east.
    for (hop, fraction) in [(0.0, 0.5), (1.0, 0.809_017), (4.0, 0.736_068)] {
        let bearing = (90.0_f64 + hop * 137.507_764_05).to_radians();
        let want = (
            10_000.0 * fraction * bearing.sin(),
            10_000.0 * fraction * bearing.cos(),
        );
        let first = 20 + 4 * hop as usize;
        let landed = &injected.track.records[first].sample;
        assert_close(
            offset_m(onset_fix, landed),
            want,
            0.5,
            &format!("hop {hop}"),
        );
        // The fix repeats exactly until the next hop.
        for row in first + 1..first + 4 {
            let s = &injected.track.records[row].sample;
            assert_eq!(
                (s.latitude_deg, s.longitude_deg),
                (landed.latitude_deg, landed.longitude_deg),
                "row {row}"
            );
        }
    }
    assert_eq!(injected.track.records[40].sample, base.records[40].sample);
    let too_fast = AttackKind::Hopping {
        offset_m: 10_000.0,
        hold_s: 0.5,
    };
    let err = inject(&base, &spec(too_fast, 0.0, 20.0, 20.0)).unwrap_err();
    assert!(err.to_string().contains("hold_s"), "{err}");
}

#[test]
fn vehicle_id_describes_the_attack() {
    let base = straight_track();
    let mut attack = spec(ramp(0.25), 90.0, 10.0, 20.0);
    attack.seed = Some(7);
    let injected = inject(&base, &attack).unwrap();
    assert_eq!(
        injected.track.vehicle_id,
        "base#ramp-0.25mps-dir90-on10s-dur20s-s7"
    );
    let accel = AttackKind::AcceleratingDrift {
        acceleration_mps2: 0.1,
    };
    assert_eq!(accel.describe(), "accel-0.1mps2");
    assert_eq!(AttackKind::FrozenPosition.describe(), "frozen");
    assert_eq!(AttackKind::Jump { offset_m: 50.0 }.describe(), "jump-50m");
    assert_eq!(accel.family(), "accelerating_drift");
    assert_eq!(accel.magnitude(), Some(0.1));
}

#[test]
fn attack_spec_round_trips_through_tagged_json() {
    let attack = spec(ramp(0.5), 90.0, 10.0, 20.0);
    let json = serde_json::to_string(&attack).unwrap();
    assert!(
        json.contains(r#""kind":{"type":"ramp_drift","velocity_mps":0.5}"#),
        "{json}"
    );
    let back: AttackSpec = serde_json::from_str(&json).unwrap();
    assert_eq!(back, attack);
    let frozen: AttackSpec = serde_json::from_str(
        r#"{"kind":{"type":"frozen_position"},"direction_deg":0,"onset_s":1,"duration_s":2}"#,
    )
    .unwrap();
    assert_eq!(frozen.kind, AttackKind::FrozenPosition);
    assert_eq!(frozen.seed, None);
    let typo =
        r#"{"kind":{"type":"jump","offset":5},"direction_deg":0,"onset_s":1,"duration_s":2}"#;
    assert!(serde_json::from_str::<AttackSpec>(typo).is_err());
}

#[test]
fn out_of_range_attack_fields_are_rejected_with_the_field_name() {
    let base = straight_track();
    let cases = [
        (
            spec(ramp(0.04), 0.0, 10.0, 10.0),
            "velocity_mps",
            "[0.05, 2] m/s",
        ),
        (
            spec(ramp(2.5), 0.0, 10.0, 10.0),
            "velocity_mps",
            "[0.05, 2] m/s",
        ),
        (
            spec(ramp(f64::NAN), 0.0, 10.0, 10.0),
            "velocity_mps",
            "finite",
        ),
        (
            spec(
                AttackKind::AcceleratingDrift {
                    acceleration_mps2: 0.6,
                },
                0.0,
                10.0,
                10.0,
            ),
            "acceleration_mps2",
            "[0.01, 0.5] m/s²",
        ),
        (
            spec(AttackKind::Jump { offset_m: 0.0 }, 0.0, 10.0, 10.0),
            "offset_m",
            "(0, 1000000] m",
        ),
        (
            spec(ramp(1.0), 360.0, 10.0, 10.0),
            "direction_deg",
            "[0, 360)",
        ),
        (
            spec(ramp(1.0), -1.0, 10.0, 10.0),
            "direction_deg",
            "[0, 360)",
        ),
        (spec(ramp(1.0), 0.0, -1.0, 10.0), "onset_s", "non-negative"),
        (spec(ramp(1.0), 0.0, 10.0, 0.0), "duration_s", "positive"),
        (
            spec(ramp(1.0), 0.0, 10.0, f64::INFINITY),
            "duration_s",
            "finite",
        ),
    ];
    for (attack, field, expected_text) in cases {
        let err = inject(&base, &attack).unwrap_err();
        assert!(
            matches!(&err, ScenarioError::InvalidAttack { field: f, .. } if *f == field),
            "{attack:?}: {err:?}"
        );
        assert!(err.to_string().contains(expected_text), "{err}");
    }
}

#[test]
fn attacks_outside_the_track_are_rejected() {
    let base = straight_track(); // spans 99 s
    let err = inject(&base, &spec(ramp(1.0), 0.0, 95.0, 10.0)).unwrap_err();
    assert_eq!(
        err,
        ScenarioError::AttackOutsideTrack {
            vehicle_id: "base".into(),
            start_s: 95.0,
            end_s: 105.0,
            span_s: 99.0
        }
    );
    assert!(err.to_string().contains("spans 99 s"), "{err}");
    // Ending exactly at the last sample is inside (the window is half-open).
    let ok = inject(&base, &spec(ramp(1.0), 0.0, 89.0, 10.0)).unwrap();
    assert_eq!(ok.attack_rows(), 89..=98);
    let empty = Track {
        vehicle_id: "empty".into(),
        records: Vec::new(),
    };
    assert_eq!(
        inject(&empty, &spec(ramp(1.0), 0.0, 0.0, 1.0)).unwrap_err(),
        ScenarioError::EmptyTrack {
            vehicle_id: "empty".into()
        }
    );
}

#[test]
fn overlap_with_spoofed_rows_is_rejected() {
    let mut base = straight_track();
    base.records[15].label = Some(true);
    let err = inject(&base, &spec(ramp(1.0), 0.0, 10.0, 20.0)).unwrap_err();
    assert_eq!(
        err,
        ScenarioError::OverlapsSpoofed {
            vehicle_id: "base".into(),
            row: 15
        }
    );
    assert!(
        err.to_string().contains("already labelled spoofed"),
        "{err}"
    );
}

#[test]
fn attacks_must_not_span_a_trajectory_break_or_a_gap() {
    let mut base = straight_track();
    for record in &mut base.records[50..] {
        record.sample.timestamp_s += 10.0; // a 11 s step between rows 49 and 50
    }
    let err = inject(&base, &spec(ramp(1.0), 0.0, 45.0, 20.0)).unwrap_err();
    assert!(
        matches!(err, ScenarioError::SpansTrajectoryBreak { row: 50, .. }),
        "{err:?}"
    );
    // Starting right at the new trajectory is fine.
    assert!(inject(&base, &spec(ramp(1.0), 0.0, 60.0, 20.0)).is_ok());
    // A window inside the gap holds no rows.
    let err = inject(&base, &spec(ramp(1.0), 0.0, 50.0, 5.0)).unwrap_err();
    assert!(
        matches!(err, ScenarioError::NoRowsInWindow { .. }),
        "{err:?}"
    );

    let mut flagged = straight_track();
    flagged.records[20].trajectory_break = true;
    let err = inject(&flagged, &spec(ramp(1.0), 0.0, 10.0, 20.0)).unwrap_err();
    assert!(
        matches!(err, ScenarioError::SpansTrajectoryBreak { row: 20, .. }),
        "{err:?}"
    );
}

#[test]
fn time_going_backwards_inside_the_window_is_rejected() {
    let mut base = straight_track();
    base.records[20].sample.timestamp_s = 3.0;
    let err = inject(&base, &spec(ramp(1.0), 0.0, 10.0, 20.0)).unwrap_err();
    assert!(
        matches!(err, ScenarioError::NonContiguousWindow { row: 20, .. }),
        "{err:?}"
    );
}

// ---- simulated drives ----

#[test]
fn same_seed_gives_the_same_drive_and_another_seed_differs() {
    let spec = DriveSpec {
        duration_s: 600.0,
        seed: 11,
        ..DriveSpec::default()
    };
    let a = simulate_drive(&spec, "sim").unwrap();
    let b = simulate_drive(&spec, "sim").unwrap();
    assert_eq!(a, b);
    let c = simulate_drive(&DriveSpec { seed: 12, ..spec }, "sim").unwrap();
    assert_eq!(c.records.len(), a.records.len());
    assert_ne!(a, c);
}

#[test]
fn simulated_drive_has_the_documented_shape() {
    let spec = DriveSpec {
        duration_s: 3600.0,
        seed: 3,
        ..DriveSpec::default()
    };
    let drive = simulate_drive_with_truth(&spec, "sim-3").unwrap();
    let records = &drive.track.records;
    assert_eq!(drive.track.vehicle_id, "sim-3");
    assert_eq!(records.len(), 3601);
    assert_eq!(drive.truth.len(), 3601);
    for (i, record) in records.iter().enumerate() {
        assert_eq!(record.sample.timestamp_s, i as f64);
        assert_eq!(record.label, Some(false));
        assert!(record.sample.violations().is_empty(), "row {i}");
        assert!((0.0..360.0).contains(&record.sample.heading_deg));
    }
    let speeds: Vec<f64> = drive.truth.iter().map(|s| s.speed_mps).collect();
    let max_speed = speeds.iter().copied().fold(0.0, f64::max);
    let median_speed = median(speeds.clone());
    let stopped = speeds.iter().filter(|&&v| v == 0.0).count();
    let origin = &records[0].sample;
    let farthest_m = records
        .iter()
        .map(|r| {
            let (e, n) = offset_m(origin, &r.sample);
            e.hypot(n)
        })
        .fold(0.0, f64::max);
    eprintln!(
        "simulated drive: median speed {median_speed:.2} m/s, max {max_speed:.2} m/s, \
         {stopped} stopped rows, farthest {farthest_m:.0} m"
    );
    assert!(max_speed <= 12.0 && max_speed > 6.0, "{max_speed}");
    assert!((0.5..=3.5).contains(&median_speed), "{median_speed}");
    assert!(stopped > 60, "{stopped}");
    assert!(farthest_m < 1500.0, "{farthest_m}");
}

#[test]
fn noise_free_drive_is_kinematically_consistent() {
    let mut spec = DriveSpec {
        duration_s: 1800.0,
        seed: 5,
        ..DriveSpec::default()
    };
    spec.gnss_noise.white_std_m = 0.0;
    spec.gnss_noise.bias_std_m = 0.0;
    spec.onboard_noise.speed_std_mps = 0.0;
    spec.onboard_noise.heading_std_deg = 0.0;
    let track = simulate_drive(&spec, "clean").unwrap();
    let magnitudes: Vec<f64> = residuals_m(&track)
        .iter()
        .map(|(e, n)| e.hypot(*n))
        .collect();
    let worst = magnitudes.iter().copied().fold(0.0, f64::max);
    // Only the trapezoid's own error remains: zero on steady steps, up to ~b·δ²/8 where braking or
    // acceleration ends mid-step, plus v·δ·θ²/12 on turns.
    let typical = median(magnitudes);
    eprintln!("noise-free residual: median {typical:.2e} m, worst {worst:.3} m");
    assert!(
        typical < 0.01 && worst < 0.5,
        "median {typical}, worst {worst}"
    );
}

#[test]
fn changing_the_noise_keeps_the_ground_truth() {
    let spec = DriveSpec {
        duration_s: 300.0,
        seed: 9,
        ..DriveSpec::default()
    };
    let mut quiet = spec;
    quiet.gnss_noise.white_std_m = 0.0;
    quiet.gnss_noise.bias_std_m = 0.0;
    let noisy = simulate_drive_with_truth(&spec, "v").unwrap();
    let clean = simulate_drive_with_truth(&quiet, "v").unwrap();
    assert_eq!(noisy.truth, clean.truth);
    for (record, truth) in clean.track.records.iter().zip(&clean.truth) {
        assert_eq!(record.sample.latitude_deg, truth.latitude_deg);
        assert_eq!(record.sample.longitude_deg, truth.longitude_deg);
    }
}

#[test]
fn gnss_errors_follow_the_documented_noise_model() {
    // Defaults: white 0.5 m, Gauss–Markov bias 1.5 m with τ = 120 s, per axis.
    let spec = DriveSpec {
        duration_s: 4.0 * 3600.0,
        seed: 21,
        ..DriveSpec::default()
    };
    let drive = simulate_drive_with_truth(&spec, "v").unwrap();
    let errors: Vec<(f64, f64)> = drive
        .track
        .records
        .iter()
        .zip(&drive.truth)
        .map(|(r, t)| {
            let truth = Sample::new(t.timestamp_s, t.latitude_deg, t.longitude_deg, 0.0, 0.0);
            offset_m(&truth, &r.sample)
        })
        .collect();
    let rms =
        |values: &[f64]| (values.iter().map(|v| v * v).sum::<f64>() / values.len() as f64).sqrt();
    let east: Vec<f64> = errors.iter().map(|e| e.0).collect();
    let step_east: Vec<f64> = east.windows(2).map(|w| w[1] - w[0]).collect();
    // Total per-axis std √(0.5² + 1.5²) = 1.581 m; step std √(2·0.5² + 2(1 − e^(−1/120))·1.5²) = 0.733 m.
    let (total, step) = (rms(&east), rms(&step_east));
    eprintln!("GNSS east error rms {total:.3} m, step rms {step:.3} m");
    assert!((total - 1.581).abs() < 0.3, "{total}");
    assert!((step - 0.733).abs() < 0.04, "{step}");
}

#[test]
fn simulated_residuals_are_metre_level_and_a_one_mps_ramp_adds_a_metre_per_step() {
    let spec = DriveSpec {
        duration_s: 1800.0,
        seed: 1,
        ..DriveSpec::default()
    };
    let base = simulate_drive(&spec, "sim-1").unwrap();
    let clean = residuals_m(&base);
    let clean_median = median(clean.iter().map(|(e, n)| e.hypot(*n)).collect());
    eprintln!("simulated normal residual median |r| = {clean_median:.3} m");
    assert!((0.3..=3.0).contains(&clean_median), "{clean_median}");

    let injected = inject(&base, &spec_at(ramp(1.0), 60.0, 600.0, 300.0)).unwrap();
    let attacked = residuals_m(&injected.track);
    let (unit_e, unit_n) = (60f64.to_radians().sin(), 60f64.to_radians().cos());
    // Residual index i is the step into row i + 1. Steps between two attacked rows gain v·δ = 1 m along
    // the attack direction; the step out of the attack loses the whole 299 m offset.
    for row in 601..=899 {
        let (i, (ce, cn)) = (row - 1, clean[row - 1]);
        let added = (attacked[i].0 - ce, attacked[i].1 - cn);
        assert_close(
            added,
            (unit_e, unit_n),
            0.01,
            &format!("step into row {row}"),
        );
    }
    let mean_along: f64 = (601..=899)
        .map(|row| attacked[row - 1].0 * unit_e + attacked[row - 1].1 * unit_n)
        .sum::<f64>()
        / 299.0;
    assert!((mean_along - 1.0).abs() < 0.2, "{mean_along}");
    let recovery = (
        attacked[899].0 - clean[899].0,
        attacked[899].1 - clean[899].1,
    );
    assert_close(
        recovery,
        (-299.0 * unit_e, -299.0 * unit_n),
        0.5,
        "recovery step",
    );
}

fn spec_at(kind: AttackKind, direction_deg: f64, onset_s: f64, duration_s: f64) -> AttackSpec {
    spec(kind, direction_deg, onset_s, duration_s)
}

#[test]
fn invalid_drive_specs_are_errors_not_panics() {
    let bad = DriveSpec {
        duration_s: -1.0,
        ..DriveSpec::default()
    };
    let err = simulate_drive(&bad, "x").unwrap_err();
    assert!(err.to_string().contains("duration_s"), "{err}");
    let huge = DriveSpec {
        duration_s: 1e12,
        ..DriveSpec::default()
    };
    assert!(simulate_drive(&huge, "x").is_err());
}

// ---- scenario sets ----

fn bases() -> Vec<Track> {
    (0..2)
        .map(|seed| {
            let spec = DriveSpec {
                duration_s: 900.0,
                seed,
                ..DriveSpec::default()
            };
            simulate_drive(&spec, &format!("sim-{seed}")).expect("the default drive spec is valid")
        })
        .collect()
}

#[test]
fn generate_yields_one_labelled_track_per_base_and_grid_point() {
    let bases = bases();
    let plan = ScenarioPlan::ramp_sweep(
        &RAMP_SWEEP_VELOCITIES_MPS,
        AttackDuration::Seconds(120.0),
        2,
        7,
    );
    let scenarios = generate(&bases, &plan).unwrap();
    assert_eq!(scenarios.len(), 2 * 6 * 2);
    assert_eq!(plan.scenario_count(2), 24);
    let mut names: Vec<&str> = scenarios
        .iter()
        .map(|s| s.track.vehicle_id.as_str())
        .collect();
    names.sort_unstable();
    names.dedup();
    assert_eq!(names.len(), 24, "vehicle ids must be unique");
    // Order: base → kind → repeat.
    assert_eq!(scenarios[0].base_vehicle_id, "sim-0");
    assert_eq!(scenarios[12].base_vehicle_id, "sim-1");
    assert_eq!(scenarios[2].attack.kind, ramp(0.1));
    for (index, s) in scenarios.iter().enumerate() {
        let span = 900.0;
        assert_eq!(s.attack.duration_s, 120.0);
        assert!(s.attack.onset_s >= 0.2 * span && s.attack.onset_s + 120.0 <= 0.8 * span);
        assert_eq!(s.attack.onset_s.fract(), 0.0, "onset on a sample");
        assert_eq!(s.attack.direction_deg.fract(), 0.0);
        assert_eq!(s.attack_row_count(), 120);
        let spoofed = s
            .track
            .records
            .iter()
            .filter(|r| r.label == Some(true))
            .count();
        assert_eq!(spoofed, 120);
        let expected_id = format!(
            "{}#{}-r{}",
            s.base_vehicle_id,
            s.attack.describe(),
            index % 2
        );
        assert_eq!(s.track.vehicle_id, expected_id);
        assert!(expected_id.contains("-s7-r"), "{expected_id}");
    }
    let directions: Vec<f64> = scenarios.iter().map(|s| s.attack.direction_deg).collect();
    assert!(
        directions.iter().any(|&d| d != directions[0]),
        "directions are drawn"
    );
}

#[test]
fn generate_is_deterministic_and_the_seed_matters() {
    let bases = bases();
    let plan = ScenarioPlan {
        kinds: vec![
            ramp(0.5),
            AttackKind::AcceleratingDrift {
                acceleration_mps2: 0.05,
            },
            AttackKind::FrozenPosition,
            AttackKind::Jump { offset_m: 20.0 },
        ],
        directions_deg: vec![0.0, 135.0],
        duration: AttackDuration::TrackFraction(0.2),
        onset_s: None,
        margin_fraction: 0.1,
        repeats: 1,
        seed: 42,
    };
    let a = generate(&bases, &plan).unwrap();
    let b = generate(&bases, &plan).unwrap();
    assert_eq!(a, b);
    assert_eq!(a.len(), 2 * 4 * 2);
    assert_eq!(a[0].attack.direction_deg, 0.0);
    assert_eq!(a[1].attack.direction_deg, 135.0);
    assert!(a.iter().all(|s| s.attack.duration_s == 0.2 * 900.0));
    let other = generate(
        &bases,
        &ScenarioPlan {
            seed: 43,
            ..plan.clone()
        },
    )
    .unwrap();
    let onsets = |v: &[spoofwatch_core::scenario::InjectedTrack]| {
        v.iter().map(|s| s.attack.onset_s).collect::<Vec<_>>()
    };
    assert_ne!(onsets(&a), onsets(&other));
    // A fixed onset is used as given, for every base.
    let fixed = ScenarioPlan {
        onset_s: Some(100.0),
        ..plan.clone()
    };
    let fixed = generate(&bases, &fixed).unwrap();
    assert!(
        fixed
            .iter()
            .all(|s| s.attack.onset_s == 100.0 && s.first_attack_row == 100)
    );
    // A base's scenarios do not depend on the other bases.
    let first_only = generate(&bases[..1], &plan).unwrap();
    assert_eq!(first_only[..], a[..8]);
}

#[test]
fn generate_reports_attacks_that_do_not_fit_and_bad_plans() {
    let bases = bases();
    let too_long = ScenarioPlan::ramp_sweep(&[1.0], AttackDuration::Seconds(600.0), 1, 0);
    let err = generate(&bases, &too_long).unwrap_err();
    assert!(
        matches!(err, ScenarioError::AttackDoesNotFit { .. }),
        "{err:?}"
    );
    assert!(err.to_string().contains("sim-0"), "{err}");

    let mut bad = ScenarioPlan::ramp_sweep(&[1.0], AttackDuration::Seconds(60.0), 0, 0);
    assert!(matches!(
        generate(&bases, &bad),
        Err(ScenarioError::InvalidPlan {
            field: "repeats",
            ..
        })
    ));
    bad.repeats = 1;
    bad.margin_fraction = 0.5;
    assert!(matches!(
        generate(&bases, &bad),
        Err(ScenarioError::InvalidPlan {
            field: "margin_fraction",
            ..
        })
    ));
    bad.margin_fraction = 0.2;
    bad.directions_deg = vec![400.0];
    assert!(matches!(
        generate(&bases, &bad),
        Err(ScenarioError::InvalidPlan {
            field: "directions_deg",
            ..
        })
    ));
    bad.directions_deg.clear();
    bad.kinds = vec![ramp(3.0)];
    assert!(matches!(
        generate(&bases, &bad),
        Err(ScenarioError::InvalidAttack { .. })
    ));
    bad.kinds.clear();
    assert!(matches!(
        generate(&bases, &bad),
        Err(ScenarioError::InvalidPlan { field: "kinds", .. })
    ));
    bad.kinds = vec![ramp(1.0)];
    bad.onset_s = Some(f64::NAN);
    assert!(matches!(
        generate(&bases, &bad),
        Err(ScenarioError::InvalidPlan {
            field: "onset_s",
            ..
        })
    ));
    let fraction = ScenarioPlan::ramp_sweep(&[1.0], AttackDuration::TrackFraction(0.7), 1, 0);
    assert!(matches!(
        generate(&bases, &fraction),
        Err(ScenarioError::InvalidPlan {
            field: "duration",
            ..
        })
    ));
}

#[test]
fn ramp_sweep_covers_the_standard_velocities_and_describes_itself() {
    let plan = ScenarioPlan::ramp_sweep(
        &RAMP_SWEEP_VELOCITIES_MPS,
        AttackDuration::Seconds(120.0),
        3,
        7,
    );
    assert_eq!(plan.validate(), Ok(()));
    let velocities: Vec<f64> = plan
        .kinds
        .iter()
        .filter_map(AttackKind::magnitude)
        .collect();
    assert_eq!(velocities, [0.05, 0.1, 0.25, 0.5, 1.0, 2.0]);
    assert_eq!(
        plan.describe(),
        "ramp-0.05mps,ramp-0.1mps,ramp-0.25mps,ramp-0.5mps,ramp-1mps,ramp-2mps × dir random × 120 s × \
         margin 0.2 × 3 repeats, seed 7"
    );
}

#[test]
fn written_csv_has_the_documented_header_and_one_row_per_record() {
    let base = straight_track();
    let injected = inject(&base, &spec(ramp(1.0), 90.0, 10.0, 5.0)).unwrap();
    let mut out = Vec::new();
    write_tracks(&mut out, std::slice::from_ref(&injected.track)).unwrap();
    let text = String::from_utf8(out).unwrap();
    let lines: Vec<&str> = text.lines().collect();
    assert_eq!(
        lines[0],
        "vehicle_id,timestamp,latitude,longitude,speed_mps,heading_deg,label"
    );
    assert_eq!(lines.len(), 1 + base.records.len());
    let labels: Vec<&str> = lines[1..]
        .iter()
        .map(|l| l.rsplit(',').next().unwrap())
        .collect();
    let spoofed: Vec<usize> = (0..labels.len()).filter(|&i| labels[i] == "1").collect();
    assert_eq!(spoofed, (10..15).collect::<Vec<_>>());
    assert!(labels.iter().all(|&l| l == "0" || l == "1"));
    assert!(
        lines[12].starts_with("base#ramp-1mps-dir90-on10s-dur5s,11,"),
        "{}",
        lines[12]
    );
}

#[test]
fn the_pace_of_a_fleet_drive_agrees_with_its_road_kind() {
    // The warning budget's groups read a trajectory's pace from its onboard speeds alone; on the
    // fleet distribution's half-hour drives it names the simulator's road kind on at least 95 %.
    let drives = 300_u64;
    let mut agree = 0;
    for i in 0..drives {
        let mut spec = DriveDistribution::fleet().draw(777_000 + i);
        spec.duration_s = 1800.0;
        spec.rate_hz = 1.0;
        let track = simulate_drive(&spec, "pace").expect("a fleet drive simulates");
        let speeds: Vec<f64> = track.records.iter().map(|r| r.sample.speed_mps).collect();
        let open_road = Pace::of(&speeds) == Pace::OpenRoad;
        agree += u64::from(open_road == (spec.road_kind() == RoadKind::Highway));
    }
    assert!(agree * 100 >= drives * 95, "{agree} of {drives} agree");
}
