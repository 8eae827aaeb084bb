//! The whole per-sample cost of one vehicle, as a session pays it: the evidence builder, the model
//! step and the alarm lifecycle with its severities, through `Detector::step` with the bundled model
//! (`models/default.json` of the tree being built). It uses only `Detector::new` and `Detector::step`,
//! which have not changed, so the same file measures an earlier commit's step beside this one's
//! (`scripts/benchmarks.py compare --only vehicle-step --before CHECKOUT`). Run briefly with
//! `cargo bench -p spoofwatch-core --bench vehicle_step -- --warm-up-time 1 --measurement-time 3`.

use std::hint::black_box;
use std::sync::Arc;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use spoofwatch_core::detector::Detector;
use spoofwatch_core::model::artifact::ModelArtifact;
use spoofwatch_core::rng::Rng;
use spoofwatch_core::sample::Sample;

const SAMPLES: usize = 4_000;
const METRES_PER_DEGREE: f64 = 111_320.0;
const START: (f64, f64) = (32.2314, -110.9079);

/// A drive at `hz` wandering at up to 12 m/s, with 1 m of GNSS noise and whole-degree headings.
fn drive(hz: f64) -> Vec<Sample> {
    let mut rng = Rng::seed_from_u64(11);
    let dt = 1.0 / hz;
    let (mut east, mut north) = (0.0, 0.0);
    let mut heading: f64 = 40.0;
    let mut speed: f64 = 8.0;
    (0..SAMPLES)
        .map(|i| {
            heading = (heading + rng.normal() * 5.0 * dt).rem_euclid(360.0);
            speed = (speed + rng.normal() * 0.3 * dt).clamp(0.0, 12.0);
            let (sin, cos) = heading.to_radians().sin_cos();
            east += speed * sin * dt;
            north += speed * cos * dt;
            let lat = START.0 + (north + rng.normal()) / METRES_PER_DEGREE;
            let lon = START.1 + (east + rng.normal()) / (METRES_PER_DEGREE * 0.846);
            Sample::new(i as f64 * dt, lat, lon, speed, heading.round())
        })
        .collect()
}

fn bench_vehicle_step(c: &mut Criterion) {
    let artifact = Arc::new(
        ModelArtifact::from_slice(include_bytes!("../../models/default.json"))
            .expect("the bundled model loads"),
    );
    let mut group = c.benchmark_group("vehicle_step");
    group.throughput(Throughput::Elements(1));
    for hz in [1.0, 10.0] {
        let samples = drive(hz);
        group.bench_function(format!("{hz}hz"), |b| {
            let mut detector = Detector::new(Arc::clone(&artifact));
            let mut t = 0usize;
            b.iter(|| {
                t = (t + 1) % samples.len();
                // Each pass over the drive starts a new trajectory, as a new session would.
                black_box(detector.step(black_box(&samples[t]), t == 0))
            });
        });
    }
    group.finish();
}

criterion_group!(benches, bench_vehicle_step);
criterion_main!(benches);
