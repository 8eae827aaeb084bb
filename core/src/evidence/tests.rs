//! Hand-computed checks of the evidence builder.

use super::*;
use crate::geo::{EQUIRECTANGULAR_RADIUS_M, Projection};
use crate::rng::Rng;
use crate::sample::{Record, Sample};

/// Metres per degree on the reference sphere (at the equator, cos(lat_ref) = 1).
fn metres_per_degree() -> f64 {
    EQUIRECTANGULAR_RADIUS_M.to_radians()
}

/// A sample at (east, north) metres from (0°, 0°).
fn at(t: f64, east: f64, north: f64, speed: f64, heading: f64) -> Sample {
    Sample::new(
        t,
        north / metres_per_degree(),
        east / metres_per_degree(),
        speed,
        heading,
    )
}

/// Σ̂ + εI = diag(4, 1) → Σ^{-1/2} = diag(1/2, 1); μ_e = 0.5, κ = 0.25, ρ = 0.5.
fn params() -> EvidenceParams {
    EvidenceParams::with_accumulator(
        [[4.0 - SIGMA_EPSILON, 0.0], [0.0, 1.0 - SIGMA_EPSILON]],
        0.5,
        0.25,
        0.5,
        Projection::Equirectangular,
    )
    .expect("valid params")
}

fn close(a: f64, b: f64) -> bool {
    (a - b).abs() <= 1e-9 * (1.0 + b.abs())
}

fn push_all(samples: &[Sample]) -> Vec<Evidence> {
    let mut builder = EvidenceBuilder::new(params());
    samples.iter().map(|s| builder.push(s, false)).collect()
}

#[test]
fn eta_differences_and_accumulator_by_hand() {
    // Stationary vehicle (Δp^u = 0), GNSS moving east: r_E = 2, 4, 2 → η_E = 1, 2, 1.
    let samples = [
        at(0.0, 0.0, 0.0, 0.0, 0.0),
        at(1.0, 2.0, 0.0, 0.0, 0.0),
        at(2.0, 6.0, 0.0, 0.0, 0.0),
        at(4.0, 8.0, 0.0, 0.0, 0.0),
        at(5.0, 8.0, 0.0, f64::NAN, 0.0), // unusable speed → ν = 0
        at(6.0, 8.0, 0.0, 0.0, 0.0),      // previous unusable → ν = 0
        at(7.0, 8.0, 0.0, 0.0, 0.0),      // r = 0 → e = 0, q = −0.75
    ];
    let e = push_all(&samples);
    let valid: Vec<bool> = e.iter().map(|x| x.valid).collect();
    assert_eq!(valid, [false, true, true, true, false, false, true]);
    let eta: Vec<f64> = e.iter().map(|x| x.eta[0]).collect();
    for (got, want) in eta.iter().zip([0.0, 1.0, 2.0, 1.0, 0.0, 0.0, 0.0]) {
        assert!(close(*got, want), "η_E {eta:?}");
    }
    assert!(e.iter().all(|x| x.eta[1].abs() < 1e-9));
    // η̇: row 2 = (2 − 1)/1 = 1; row 3 = (1 − 2)/2 = −0.5; row 6: previous ν = 0 → 0.
    let eta_dot: Vec<f64> = e.iter().map(|x| x.eta_dot[0]).collect();
    for (got, want) in eta_dot.iter().zip([0.0, 0.0, 1.0, -0.5, 0.0, 0.0, 0.0]) {
        assert!(close(*got, want), "η̇_E {eta_dot:?}");
    }
    // η̈: row 3 = (−0.5 − 1)/((2 + 1)/2) = −1; row 2 has no η̇_{t−1} → 0.
    let eta_ddot: Vec<f64> = e.iter().map(|x| x.eta_ddot[0]).collect();
    for (got, want) in eta_ddot.iter().zip([0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0]) {
        assert!(close(*got, want), "η̈_E {eta_ddot:?}");
    }
    // e = 1, 4, 1 → q = e − 0.5 − 0.25; a = max(0, 0.5a + q) when valid, else 0.5a.
    let q: Vec<f64> = e.iter().map(|x| x.q).collect();
    for (got, want) in q.iter().zip([0.0, 0.25, 3.25, 0.25, 0.0, 0.0, -0.75]) {
        assert!(close(*got, want), "q {q:?}");
    }
    let accum: Vec<f64> = e.iter().map(|x| x.accum).collect();
    let expected = [0.0, 0.25, 3.375, 1.9375, 0.96875, 0.484375, 0.0];
    for (got, want) in accum.iter().zip(expected) {
        assert!(close(*got, want), "a {accum:?}");
    }
    for x in &e {
        assert!(close(x.accum_log, (1.0 + x.accum).ln()));
    }
    assert!(e[0].delta_t.is_nan() && e[0].trajectory_start);
    assert!(e[4].residual[0].is_nan(), "no residual when ν = 0");
    assert!(close(e[3].delta_t, 2.0));
    assert_eq!(e[3].raw_features()[0..2], [e[3].eta[0], e[3].eta[1]]);
    assert_eq!(e[3].raw_features()[8], 1.0);
    assert_eq!(e[4].raw_features()[8], 0.0);
}

#[test]
fn motion_displacement_is_the_trapezoid_of_heading_velocities() {
    // 2 m/s heading 90° (east) then 4 m/s heading 0° (north), δ = 2:
    // Δp^u = ½((2, 0) + (0, 4))·2 = (2, 4). GNSS moved (3, 3) → r = (1, −1) → η = (0.5, −1).
    let e = push_all(&[at(0.0, 0.0, 0.0, 2.0, 90.0), at(2.0, 3.0, 3.0, 4.0, 0.0)]);
    assert!(e[1].valid);
    assert!(
        close(e[1].residual[0], 1.0) && close(e[1].residual[1], -1.0),
        "{:?}",
        e[1]
    );
    assert!(
        close(e[1].eta[0], 0.5) && close(e[1].eta[1], -1.0),
        "{:?}",
        e[1]
    );
    assert!(close(e[1].energy, 1.25));
}

#[test]
fn gaps_backward_time_and_breaks_start_trajectories() {
    let mut builder = EvidenceBuilder::new(params());
    let mut push = |t: f64, brk: bool| builder.push(&at(t, 0.0, 0.0, 0.0, 0.0), brk);
    let rows = [
        push(0.0, false),  // first sample
        push(5.0, false),  // gap of exactly 5 s: same trajectory, valid
        push(11.0, false), // gap 6 s → new trajectory
        push(12.0, false),
        push(11.4, false), // 0.6 s backwards → new trajectory
        push(11.0, false), // 0.4 s backwards: same trajectory, invalid
        push(11.0, false), // δ = 0: invalid
        push(12.0, true),  // the source's break flag
        push(13.0, false),
    ];
    let starts: Vec<bool> = rows.iter().map(|e| e.trajectory_start).collect();
    assert_eq!(
        starts,
        [true, false, true, false, true, false, false, true, false]
    );
    let index: Vec<u32> = rows.iter().map(|e| e.trajectory).collect();
    assert_eq!(index, [0, 0, 1, 1, 2, 2, 2, 3, 3]);
    let valid: Vec<bool> = rows.iter().map(|e| e.valid).collect();
    assert_eq!(
        valid,
        [false, true, false, true, false, false, false, false, true]
    );
    assert!(
        rows.iter()
            .filter(|e| e.trajectory_start)
            .all(|e| e.delta_t.is_nan())
    );
    assert!(close(rows[5].delta_t, -0.4) && close(rows[6].delta_t, 0.0));

    builder.reset();
    let e = builder.push(&at(100.0, 0.0, 0.0, 0.0, 0.0), false);
    assert!(
        e.trajectory_start && e.trajectory == 0,
        "reset forgets the stream"
    );
}

#[test]
fn a_trajectory_start_resets_the_accumulator_and_differences() {
    // A big residual builds up a_t; after a 10 s gap everything sequential starts from zero.
    let e = push_all(&[
        at(0.0, 0.0, 0.0, 0.0, 0.0),
        at(1.0, 20.0, 0.0, 0.0, 0.0),  // η_E = 10, e = 100
        at(11.0, 20.0, 0.0, 0.0, 0.0), // gap → start
        at(12.0, 22.0, 0.0, 0.0, 0.0), // η_E = 1; η̇ not computed (previous ν = 0)
    ]);
    assert!(e[1].accum > 99.0);
    assert!(e[2].trajectory_start && e[2].accum == 0.0 && !e[2].valid);
    assert!(
        close(e[3].accum, 0.25),
        "a = max(0, 0 + 1 − 0.75): {:?}",
        e[3]
    );
    assert_eq!(e[3].eta_dot, [0.0, 0.0]);
}

#[test]
fn the_equirectangular_origin_is_reset_per_trajectory() {
    // Trajectory 0 near the equator, trajectory 1 at 60° N: 0.001° of longitude is R·cos(60°)·rad there.
    let params = EvidenceParams::new([[1.0, 0.0], [0.0, 1.0]], 0.0, Projection::Equirectangular)
        .expect("valid");
    let mut builder = EvidenceBuilder::new(params);
    builder.push(&Sample::new(0.0, 0.0, 0.0, 0.0, 0.0), false);
    builder.push(&Sample::new(1.0, 0.0, 0.0, 0.0, 0.0), false);
    builder.push(&Sample::new(2.0, 60.0, 20.0, 0.0, 0.0), true);
    let e = builder.push(&Sample::new(3.0, 60.0, 20.001, 0.0, 0.0), false);
    let want = EQUIRECTANGULAR_RADIUS_M * 0.5 * 0.001_f64.to_radians();
    assert!(
        (e.residual[0] - want).abs() < 1e-6,
        "{} vs {want}",
        e.residual[0]
    );
}

#[test]
fn validity_rules() {
    let base = |t: f64| at(t, 0.0, 0.0, 1.0, 0.0);
    let check = |mutate: &dyn Fn(&mut Sample), want: bool, why: &str| {
        let mut second = base(1.0);
        second = at(1.0, 0.0, 1.0, second.speed_mps, second.heading_deg);
        mutate(&mut second);
        let e = push_all(&[base(0.0), second]);
        assert_eq!(e[1].valid, want, "{why}: {:?}", e[1]);
    };
    check(&|_| {}, true, "plain");
    check(&|s| s.speed_mps = 80.0, true, "|speed| = 80 is allowed");
    check(&|s| s.speed_mps = -80.5, false, "|speed| > 80");
    check(&|s| s.speed_mps = f64::INFINITY, false, "infinite speed");
    check(&|s| s.heading_deg = f64::NAN, false, "NaN heading");
    check(&|s| s.heading_deg = 361.0, false, "heading out of range");
    check(&|s| s.latitude_deg = 90.5, false, "latitude out of range");
    check(&|s| s.longitude_deg = f64::NAN, false, "NaN longitude");
    check(&|s| s.position_std_m = Some(-1.0), false, "negative std");
    check(&|s| s.speed_std_mps = Some(f64::NAN), false, "NaN std");
    check(&|s| s.timestamp_s = 0.0, false, "δ = 0");
    check(&|s| s.timestamp_s = f64::NAN, false, "NaN timestamp");
    // A bad first sample also invalidates the second (the displacement needs both).
    let mut bad = base(0.0);
    bad.latitude_deg = f64::NAN;
    let e = push_all(&[
        bad,
        at(1.0, 0.0, 1.0, 1.0, 0.0),
        at(2.0, 0.0, 2.0, 1.0, 0.0),
    ]);
    assert_eq!([e[0].valid, e[1].valid, e[2].valid], [false, false, true]);
    // NaN timestamps never start a trajectory by themselves.
    let mut nan_time = base(1.0);
    nan_time.timestamp_s = f64::NAN;
    let e = push_all(&[base(0.0), nan_time, base(2.0)]);
    assert!(!e[1].trajectory_start && !e[2].trajectory_start);
    assert!(!e[1].valid && !e[2].valid);
}

#[test]
fn per_step_sigma_branch() {
    // Both samples: σ_p = 1 m, σ_s = 0.5 m/s, σ_ψ = 10°, speed 2 m/s heading 90° (east), δ = 1.
    // Σ^Δg = (1 + 1)·I. Cov(v) = σ_s²·uuᵀ + (sσ_ψ)²·wwᵀ with u = (1, 0), w = (0, −1)
    //       = diag(0.25, (2·0.17453…)²) = diag(0.25, 0.121847); Σ^Δu = ¼·2·Cov(v) = diag(0.125, 0.0609235).
    // GNSS moved 3 m east, motion 2 m east → r = (1, 0) → η_E = 1/√(2.125 + ε).
    let with_std = |mut s: Sample| {
        s.position_std_m = Some(1.0);
        s.speed_std_mps = Some(0.5);
        s.heading_std_deg = Some(10.0);
        s
    };
    let first = with_std(at(0.0, 0.0, 0.0, 2.0, 90.0));
    let second = with_std(at(1.0, 3.0, 0.5, 2.0, 90.0));
    let e = push_all(&[first, second]);
    assert!(e[1].valid && e[1].sigma_per_step);
    let sigma_n = 2.0 + 0.5 * (2.0 * 10.0_f64.to_radians()).powi(2) + SIGMA_EPSILON;
    // Σ_t is never tighter than the training Σ̂ = diag(4, 1): east 2.125 < 4 is raised to 4 (η_E
    // as in the Σ̂ branch below), north 2.06 > 1 is kept. Unfloored, η_E would be 1/√2.125.
    assert!(close(e[1].eta[0], 0.5), "{:?}", e[1]);
    assert!(close(e[1].eta[1], 0.5 / sigma_n.sqrt()), "{:?}", e[1]);
    // Wider than Σ̂ in both directions (σ_p = 2 m: 8 + 0.125 east): Σ_t applies as it is.
    let wide = |mut s: Sample| {
        s.position_std_m = Some(2.0);
        s
    };
    let e = push_all(&[wide(first), wide(second)]);
    let wide_e = 8.0 + 0.125 + SIGMA_EPSILON;
    assert!(close(e[1].eta[0], 1.0 / wide_e.sqrt()), "{:?}", e[1]);
    // Zero uncertainty (a receiver claiming perfection) cannot blow η up: exactly the Σ̂ values.
    let perfect = |mut s: Sample| {
        s.position_std_m = Some(0.0);
        s.speed_std_mps = Some(0.0);
        s.heading_std_deg = Some(0.0);
        s
    };
    let e = push_all(&[perfect(first), perfect(second)]);
    assert!(e[1].sigma_per_step);
    assert!(
        close(e[1].eta[0], 0.5) && close(e[1].eta[1], 0.5),
        "{:?}",
        e[1]
    );
    // Without the previous sample's stds the training Σ̂ = diag(4, 1) applies.
    let e = push_all(&[at(0.0, 0.0, 0.0, 2.0, 90.0), second]);
    assert!(e[1].valid && !e[1].sigma_per_step);
    assert!(
        close(e[1].eta[0], 0.5) && close(e[1].eta[1], 0.5),
        "{:?}",
        e[1]
    );
}

/// Debug text compares NaN fields too (`Evidence` has NaN δ at starts).
fn same(a: &[Evidence], b: &[Evidence]) -> bool {
    format!("{a:?}") == format!("{b:?}")
}

fn random_records(seed: u64, n: usize) -> Vec<Record> {
    let mut rng = Rng::seed_from_u64(seed);
    let mut t = 0.0;
    let (mut lat, mut lon) = (32.23, -110.9);
    (0..n)
        .map(|i| {
            t += if rng.uniform() < 0.02 { 8.0 } else { 1.0 };
            lat += rng.normal() * 1e-5;
            lon += rng.normal() * 1e-5;
            let speed = if rng.uniform() < 0.02 {
                f64::NAN
            } else {
                rng.uniform_range(0.0, 10.0)
            };
            Record {
                sample: Sample::new(t, lat, lon, speed, rng.uniform_range(0.0, 360.0)),
                label: Some(false),
                comparator_alarm: None,
                line: i as u64 + 2,
                trajectory_break: rng.uniform() < 0.01,
                warmup: false,
            }
        })
        .collect()
}

#[test]
fn build_track_equals_pushing_one_by_one() {
    let records = random_records(7, 2000);
    let v2 = EvidenceParams {
        drift: Some(drift::DriftParams::unwhitened(1.0)),
        ..params()
    };
    for params in [params(), v2] {
        let whole = build_track(&params, &records);
        let mut builder = EvidenceBuilder::new(params);
        let streamed: Vec<Evidence> = records
            .iter()
            .map(|r| builder.push(&r.sample, r.trajectory_break))
            .collect();
        assert!(same(&whole, &streamed));
        assert!(whole.iter().filter(|e| e.trajectory_start).count() > 10);
        assert!(whole.iter().filter(|e| e.valid).count() > 1500);
        // A reset builder (drift calibration included) replays the same stream identically.
        builder.reset();
        let replay: Vec<Evidence> = records
            .iter()
            .map(|r| builder.push(&r.sample, r.trajectory_break))
            .collect();
        assert!(same(&whole, &replay));
    }
}

#[test]
fn a_fix_repeated_exactly_is_stale_and_its_features_are_the_v2_tail() {
    let params = EvidenceParams {
        drift: Some(drift::DriftParams::unwhitened(1.0)),
        ..params()
    };
    let mut builder = EvidenceBuilder::new(params);
    // Standing still with a frozen fix for 3 s, then the fix jitters by 1 cm.
    let samples = [
        at(0.0, 5.0, 5.0, 0.0, 0.0),
        at(1.0, 5.0, 5.0, 0.0, 0.0),
        at(2.0, 5.0, 5.0, 0.0, 0.0),
        at(3.0, 5.0, 5.0, 0.0, 0.0),
        at(4.0, 5.01, 5.0, 0.0, 0.0),
    ];
    let stale: Vec<f64> = samples
        .iter()
        .map(|s| builder.push(s, false).drift.expect("v2").stale_fix_s)
        .collect();
    assert_eq!(stale, [0.0, 1.0, 2.0, 3.0, 0.0]);
    let mut builder = EvidenceBuilder::new(params);
    let features: Vec<Features> = samples[..4]
        .iter()
        .map(|s| builder.push(s, false).raw_features())
        .collect();
    let names = FeatureSchema::V2.feature_names();
    let index = |name: &str| names.iter().position(|n| *n == name).expect("named");
    assert_eq!(features[3][index("stale_fix")], 3f64.ln_1p());
    assert_eq!(
        features[3][index("residual_log")],
        0.0,
        "no residual at rest"
    );
}

#[test]
fn the_calibration_recovers_a_simulated_drives_onboard_errors() {
    use crate::scenario::{DriveSpec, OnboardErrors, simulate_drive};
    // Reported speed (1 + ε)·v and heading + β, both sampled τ_L late: to first order the residual
    // is −H θ with θ = (ε/(1 + ε), β, τ_L) (docs/detector.md §4.1).
    let errors = OnboardErrors {
        speed_scale_error: 0.04,
        heading_bias_deg: -3.0,
        timing_offset_s: 0.3,
    };
    let spec = DriveSpec {
        duration_s: 900.0,
        onboard_errors: errors,
        seed: 11,
        ..DriveSpec::default()
    };
    let track = simulate_drive(&spec, "calibrated").expect("a valid drive");
    let params = EvidenceParams {
        drift: Some(drift::DriftParams::unwhitened(1.0)),
        ..EvidenceParams::with_accumulator(
            [[1.0, 0.0], [0.0, 1.0]],
            2.0,
            0.0,
            0.98,
            Projection::Wgs84Local,
        )
        .expect("valid params")
    };
    let evidence = build_track(&params, &track.records);
    let last = evidence.last().and_then(|e| e.drift).expect("v2 evidence");
    let [scale, heading_deg, timing_s] = last.calibration;
    assert!((scale - 0.04 / 1.04).abs() < 0.004, "scale {scale}");
    assert!((heading_deg + 3.0).abs() < 0.3, "heading {heading_deg}");
    assert!((timing_s - 0.3).abs() < 0.1, "timing {timing_s}");
    assert!(last.is_warm());
}

#[test]
fn anchors_fit_on_vehicles_that_never_teach_their_calibration() {
    // Gently turning 400 s drives never make the calibration known (ω < 0.75): under
    // information-driven trust the anchors are fitted on every normal row instead of refusing.
    let tracks: Vec<crate::sample::Track> = (0..2)
        .map(|seed| {
            let spec = crate::scenario::DriveSpec {
                duration_s: 400.0,
                seed,
                ..crate::scenario::DriveSpec::default()
            };
            crate::scenario::simulate_drive(&spec, "slow").expect("drive")
        })
        .collect();
    let projection = Projection::default();
    let drift = fit_drift_params(
        &tracks,
        projection,
        calibration::CalibrationTrust::Information,
        None,
    )
    .expect("drift parameters");
    let offset = fit_offset_params(&tracks, projection, drift).expect("anchors fitted");
    assert!(offset.validate().is_ok(), "{offset:?}");
}
