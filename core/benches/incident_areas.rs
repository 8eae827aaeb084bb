//! The per-sample cost of the area prior's lookup (§11): one vehicle's detection step together with
//! the question "is this fix inside an open incident's area?", with 0, 10 and 10,000 open incidents,
//! and the lookup alone (through the grid index, and by testing every area as the server once did).
//! The incidents lie around the drive, densely (10,000 areas of the correlator's sizes within
//! ±3° of it, so the drive's cells hold candidates), but none holds a fix of the drive: every case
//! scores the same samples the same way and differs only in the lookup. Run briefly with
//! `cargo bench -p spoofwatch-core --bench incident_areas -- --warm-up-time 1 --measurement-time 3`.

use std::hint::black_box;
use std::sync::Arc;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use spoofwatch_core::detector::Detector;
use spoofwatch_core::geo::LatLon;
use spoofwatch_core::incident::areas::{Area, AreaIndex};
use spoofwatch_core::model::artifact::ModelArtifact;
use spoofwatch_core::rng::Rng;
use spoofwatch_core::sample::Sample;

const SAMPLES: usize = 4_000;
const METRES_PER_DEGREE: f64 = 111_320.0;
const START: (f64, f64) = (32.2314, -110.9079);

/// A 1 Hz drive wandering at up to 12 m/s.
fn drive() -> Vec<Sample> {
    let mut rng = Rng::seed_from_u64(11);
    let (mut east, mut north) = (0.0, 0.0);
    let mut heading: f64 = 40.0;
    let mut speed: f64 = 8.0;
    (0..SAMPLES)
        .map(|i| {
            heading = (heading + rng.normal() * 5.0).rem_euclid(360.0);
            speed = (speed + rng.normal() * 0.3).clamp(0.0, 12.0);
            let (sin, cos) = heading.to_radians().sin_cos();
            east += speed * sin;
            north += speed * cos;
            let lat = START.0 + (north + rng.normal()) / METRES_PER_DEGREE;
            let lon = START.1 + (east + rng.normal()) / (METRES_PER_DEGREE * 0.846);
            Sample::new(i as f64, lat, lon, speed, heading.round())
        })
        .collect()
}

/// `count` areas of radius 1.1 to 11 km within ±3° of the drive's start, none holding a fix of it.
fn areas_around(samples: &[Sample], count: usize) -> Vec<Area> {
    let mut rng = Rng::seed_from_u64(54);
    let fixes: Vec<LatLon> = samples
        .iter()
        .map(|s| LatLon::new(s.latitude_deg, s.longitude_deg))
        .collect();
    let mut areas = Vec::with_capacity(count);
    while areas.len() < count {
        let area = Area {
            centre: LatLon::new(
                START.0 + rng.uniform_range(-3.0, 3.0),
                START.1 + rng.uniform_range(-3.0, 3.0),
            ),
            radius_m: rng.uniform_range(1_100.0, 11_000.0),
        };
        if !fixes.iter().any(|&fix| area.contains(fix)) {
            areas.push(area);
        }
    }
    areas
}

fn bench_areas(c: &mut Criterion) {
    let artifact = Arc::new(
        ModelArtifact::from_slice(include_bytes!("../../models/default.json"))
            .expect("the bundled model loads"),
    );
    let samples = drive();
    let points: Vec<LatLon> = samples
        .iter()
        .map(|s| LatLon::new(s.latitude_deg, s.longitude_deg))
        .collect();
    let mut step = c.benchmark_group("incident_areas_step");
    step.throughput(Throughput::Elements(1));
    let indexes: Vec<(usize, AreaIndex)> = [0, 10, 10_000]
        .into_iter()
        .map(|count| (count, AreaIndex::new(areas_around(&samples, count))))
        .collect();
    for (count, index) in &indexes {
        step.bench_function(count.to_string(), |b| {
            let mut detector = Detector::new(Arc::clone(&artifact));
            let mut t = 0usize;
            b.iter(|| {
                t = (t + 1) % samples.len();
                let sample = &samples[t];
                let inside = index.contains(LatLon::new(sample.latitude_deg, sample.longitude_deg));
                black_box(detector.step_with_prior(black_box(sample), t == 0, inside))
            });
        });
    }
    step.finish();

    let mut lookup = c.benchmark_group("incident_areas_lookup");
    lookup.throughput(Throughput::Elements(1));
    for (count, index) in &indexes {
        lookup.bench_function(count.to_string(), |b| {
            let mut t = 0usize;
            b.iter(|| {
                t = (t + 1) % points.len();
                black_box(index.contains(black_box(points[t])))
            });
        });
    }
    let (_, largest) = &indexes[indexes.len() - 1];
    lookup.bench_function("10000_linear", |b| {
        let mut t = 0usize;
        b.iter(|| {
            t = (t + 1) % points.len();
            black_box(largest.linear_contains(black_box(points[t])))
        });
    });
    lookup.finish();
}

criterion_group!(benches, bench_areas);
criterion_main!(benches);
