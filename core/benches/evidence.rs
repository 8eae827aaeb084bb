//! Throughput of one vehicle's evidence builder over Dataset-3-like synthetic data (1 Hz, a small
//! test track, speeds 0–12 m/s, GNSS noise ~1 m, a few invalid samples). No shared data needed.

use std::hint::black_box;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use spoofwatch_core::evidence::calibration::CalibrationTrust;
use spoofwatch_core::evidence::drift::DriftParams;
use spoofwatch_core::evidence::offset::OffsetParams;
use spoofwatch_core::evidence::{EvidenceBuilder, EvidenceParams};
use spoofwatch_core::geo::Projection;
use spoofwatch_core::rng::Rng;
use spoofwatch_core::sample::Sample;

const SAMPLES: usize = 10_000;
const METRES_PER_DEGREE: f64 = 111_320.0;

fn synthetic_drive(seed: u64, with_uncertainty: bool) -> Vec<Sample> {
    let mut rng = Rng::seed_from_u64(seed);
    let (mut east, mut north) = (0.0, 0.0);
    let mut heading: f64 = 166.0;
    let mut speed: f64 = 1.0;
    (0..SAMPLES)
        .map(|i| {
            heading = (heading + rng.normal() * 5.0).rem_euclid(360.0);
            speed = (speed + rng.normal() * 0.3).clamp(0.0, 12.0);
            let (sin, cos) = heading.to_radians().sin_cos();
            east += speed * sin;
            north += speed * cos;
            let lat = 32.2314 + (north + rng.normal()) / METRES_PER_DEGREE;
            let lon = -110.9079 + (east + rng.normal()) / (METRES_PER_DEGREE * 0.846);
            let reported_speed = if rng.uniform() < 0.005 {
                f64::NAN
            } else {
                speed
            };
            let mut sample = Sample::new(i as f64, lat, lon, reported_speed, heading.round());
            if with_uncertainty {
                sample.position_std_m = Some(1.5);
                sample.speed_std_mps = Some(0.1);
                sample.heading_std_deg = Some(2.0);
            }
            sample
        })
        .collect()
}

fn params(
    projection: Projection,
    drift: bool,
    offset: bool,
    trust: CalibrationTrust,
) -> EvidenceParams {
    let paper = EvidenceParams::new([[3.936, 0.183], [0.183, 2.150]], 0.294, projection)
        .expect("valid parameters");
    // Evidence v2: the drift tracker with per-vehicle levels (whitening values do not change the cost).
    let drift = drift.then(|| DriftParams {
        vehicle_levels: true,
        trust,
        stale_fix_while_moving: true,
        ..DriftParams::unwhitened(1.2)
    });
    // Evidence v3: the anchors with the trained default's scale (values do not change the cost).
    let offset = offset.then_some(OffsetParams {
        noise_m2: [1.28, 3.72],
        raw_growth: [1.5e-3, 2.5e-3],
        calibrated_growth: [7.5e-4, 1e-4],
        step_noise_m2: 2.36,
        vehicle_levels: true,
        rebase_on_calibration: false,
    });
    EvidenceParams {
        drift,
        offset,
        ..paper
    }
}

fn bench_builder(c: &mut Criterion) {
    let mut group = c.benchmark_group("evidence_builder");
    group.throughput(Throughput::Elements(SAMPLES as u64));
    let (timers, information) = (CalibrationTrust::Timers, CalibrationTrust::Information);
    let cases = [
        (
            "wgs84_local",
            Projection::Wgs84Local,
            false,
            false,
            false,
            timers,
        ),
        (
            "equirectangular",
            Projection::Equirectangular,
            false,
            false,
            false,
            timers,
        ),
        (
            "per_step_sigma",
            Projection::Wgs84Local,
            true,
            false,
            false,
            timers,
        ),
        (
            "v2_drift_channels",
            Projection::Wgs84Local,
            false,
            true,
            false,
            timers,
        ),
        (
            "v3_offset_channels",
            Projection::Wgs84Local,
            false,
            true,
            true,
            timers,
        ),
        // The calibration trusted from its uncertainty: the covariance of every test carries it.
        (
            "v3_offset_channels_information_trust",
            Projection::Wgs84Local,
            false,
            true,
            true,
            information,
        ),
    ];
    for (name, projection, with_uncertainty, drift, offset, trust) in cases {
        let samples = synthetic_drive(3, with_uncertainty);
        let mut builder = EvidenceBuilder::new(params(projection, drift, offset, trust));
        group.bench_function(name, |b| {
            b.iter(|| {
                builder.reset();
                let mut sum = 0.0;
                for sample in &samples {
                    sum += builder.push(black_box(sample), false).accum_log;
                }
                black_box(sum)
            });
        });
    }
    group.finish();
}

criterion_group!(benches, bench_builder);
criterion_main!(benches);
