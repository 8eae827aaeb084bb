//! Model speed: one streaming step, a fleet of 1,000 vehicles advanced one step each, and one training
//! epoch on ~5,000 synthetic rows. Run briefly with
//! `cargo bench -p spoofwatch-core --bench model -- --warm-up-time 1 --measurement-time 3`.

use std::hint::black_box;
use std::sync::atomic::AtomicBool;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use spoofwatch_core::evidence::{FeatureSchema, Features};
use spoofwatch_core::model::{LiquidState, Model, ModelConfig, StepScratch};
use spoofwatch_core::rng::Rng;
use spoofwatch_core::train::{Sequence, TrainConfig, train};

fn random_features(rng: &mut Rng, count: usize) -> Vec<Features> {
    spoofwatch_core::testdata::random_features(rng, count, 1.0, FeatureSchema::V2)
}

/// Trajectories with one attack interval each (large η and q inside it).
fn synthetic_sequences(rng: &mut Rng, count: usize, length: usize) -> Vec<Sequence> {
    (0..count)
        .map(|_| {
            let onset = length / 4 + rng.below(length / 2);
            let end = (onset + length / 6).min(length);
            let mut sequence = Sequence::default();
            for (t, mut x) in random_features(rng, length).into_iter().enumerate() {
                let spoofed = (onset..end).contains(&t);
                if spoofed {
                    x[0] += 2.0;
                    x[6] += 2.0;
                }
                sequence.features.push(x);
                sequence.deltas.push(if t == 0 { 0.0 } else { 1.0 });
                sequence.labels.push(spoofed);
                sequence.valid.push(t > 0);
            }
            sequence
        })
        .collect()
}

/// The configuration the committed kernel figures were measured on: the default widths with the v2
/// evidence's inputs.
fn bench_config() -> ModelConfig {
    ModelConfig {
        schema: FeatureSchema::V2,
        ..ModelConfig::default()
    }
}

fn bench_step(c: &mut Criterion) {
    let config = bench_config();
    let model = Model::init(config.clone(), 1).expect("default config is valid");
    let inputs = random_features(&mut Rng::seed_from_u64(2), 1024);

    c.bench_function("step/one_vehicle", |b| {
        let mut state = LiquidState::zeros(&config);
        let mut scratch = StepScratch::new(&config);
        let mut t = 0usize;
        b.iter(|| {
            t = (t + 1) % inputs.len();
            black_box(model.step(&mut state, black_box(&inputs[t]), 1.0, &mut scratch))
        });
    });

    let mut group = c.benchmark_group("step");
    group.throughput(Throughput::Elements(1000));
    group.bench_function("1000_vehicles", |b| {
        let mut states: Vec<LiquidState> = (0..1000).map(|_| LiquidState::zeros(&config)).collect();
        let mut scratch = StepScratch::new(&config);
        b.iter(|| {
            for (i, state) in states.iter_mut().enumerate() {
                let x = &inputs[i % inputs.len()];
                black_box(model.step(state, x, 1.0, &mut scratch));
            }
        });
    });
    group.finish();
}

fn bench_training_epoch(c: &mut Criterion) {
    let mut rng = Rng::seed_from_u64(3);
    let train_set = synthetic_sequences(&mut rng, 20, 250); // 5,000 rows
    let val_set = synthetic_sequences(&mut rng, 4, 250);
    let config = TrainConfig {
        max_epochs: 1,
        ..TrainConfig::default()
    };
    let mut group = c.benchmark_group("train");
    group.sample_size(10);
    group.throughput(Throughput::Elements(5000));
    group.bench_function("epoch_5000_rows", |b| {
        b.iter(|| {
            let outcome = train(
                &train_set,
                &val_set,
                bench_config(),
                &config,
                &mut |_| {},
                &AtomicBool::new(false),
            )
            .expect("synthetic data trains");
            black_box(outcome.best_val_loss)
        });
    });
    group.finish();
}

criterion_group!(benches, bench_step, bench_training_epoch);
criterion_main!(benches);
