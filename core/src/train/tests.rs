//! Unit tests of the optimiser loop: configuration checks, windows, reproducibility, cancellation.

use super::*;
use crate::evidence::FEATURE_CAPACITY;

/// Synthetic trajectories: normal rows have small η and negative q; inside one attack interval per
/// trajectory η and q are large and the accumulator ã grows. About 5% of rows are invalid (ν = 0,
/// features zero), as after the evidence builder.
fn synthetic(rng: &mut Rng, count: usize, length: usize) -> Vec<Sequence> {
    (0..count)
        .map(|_| {
            let onset = length / 4 + rng.below(length / 2);
            let end = (onset + length / 8 + rng.below(length / 4)).min(length);
            let mut sequence = Sequence::default();
            let (mut accumulator, mut previous_eta) = (0.0f64, [0.0; 2]);
            for t in 0..length {
                let spoofed = (onset..end).contains(&t);
                let valid = t > 0 && rng.uniform() > 0.05;
                let mut x = [0.0; FEATURE_CAPACITY];
                if valid {
                    let bias = if spoofed { 1.5 } else { 0.0 };
                    let eta = [bias + 0.6 * rng.normal(), 0.6 * rng.normal() - bias];
                    let q = if spoofed { 2.0 } else { -0.4 } + 0.5 * rng.normal();
                    accumulator = (0.9 * accumulator + q).max(0.0);
                    x[0] = eta[0];
                    x[1] = eta[1];
                    x[2] = eta[0] - previous_eta[0];
                    x[3] = eta[1] - previous_eta[1];
                    x[6] = q;
                    x[8] = 1.0;
                    previous_eta = eta;
                } else {
                    accumulator *= 0.9;
                }
                x[7] = accumulator.ln_1p();
                sequence.features.push(x);
                sequence.deltas.push(if t == 0 { 0.0 } else { 1.0 });
                sequence.labels.push(spoofed);
                sequence.valid.push(valid);
            }
            sequence
        })
        .collect()
}

fn small_model() -> ModelConfig {
    ModelConfig {
        d_s: 6,
        d_zeta: 12,
        d_h: 10,
        ..ModelConfig::default()
    }
}

fn quick_config(seed: u64) -> TrainConfig {
    TrainConfig {
        seed,
        max_epochs: 2,
        window: 24,
        batch_size: 4,
        learning_rate: 5e-3,
        ..TrainConfig::default()
    }
}

fn no_cancel() -> AtomicBool {
    AtomicBool::new(false)
}

fn param_bits(model: &Model) -> Vec<u64> {
    model
        .params()
        .tensors()
        .iter()
        .flat_map(|(_, t)| t.data().iter().map(|v| v.to_bits()))
        .collect()
}

#[test]
fn class_weights_are_balanced_and_clipped() {
    let sequence = Sequence {
        features: vec![[0.0; FEATURE_CAPACITY]; 5],
        deltas: vec![1.0; 5],
        labels: vec![true, false, false, false, true],
        valid: vec![true, true, true, true, false],
    };
    // Valid rows: 1 spoofed, 3 normal → α_1 = 4/2 = 2, α_0 = 4/6.
    let weights =
        ClassWeights::balanced(std::slice::from_ref(&sequence), 0.05, 50.0).expect("both classes");
    assert_eq!(weights.spoofed, 2.0);
    assert!((weights.normal - 4.0 / 6.0).abs() < 1e-15);
    let clipped =
        ClassWeights::balanced(std::slice::from_ref(&sequence), 0.8, 1.5).expect("both classes");
    assert_eq!((clipped.normal, clipped.spoofed), (0.8, 1.5));
    let one_class = Sequence {
        labels: vec![false; 5],
        ..sequence
    };
    assert_eq!(ClassWeights::balanced(&[one_class], 0.05, 50.0), None);
}

#[test]
fn windows_tile_each_trajectory_and_skip_those_without_valid_rows() {
    let mut first = Sequence {
        features: vec![[0.0; FEATURE_CAPACITY]; 10],
        deltas: vec![1.0; 10],
        labels: vec![false; 10],
        valid: vec![true; 10],
    };
    first.valid[4..8].fill(false);
    let second = Sequence {
        features: vec![[0.0; FEATURE_CAPACITY]; 3],
        deltas: vec![1.0; 3],
        labels: vec![false; 3],
        valid: vec![false, false, true],
    };
    let spans = plan_windows(&[first, second], 4);
    let simple: Vec<_> = spans
        .iter()
        .map(|s| (s.sequence, s.index, s.start, s.end))
        .collect();
    assert_eq!(simple, vec![(0, 0, 0, 4), (0, 2, 8, 10), (1, 0, 0, 3)]);
}

#[test]
fn carried_start_states_equal_a_continuous_forward_pass() {
    let mut rng = Rng::seed_from_u64(3);
    let sequences = synthetic(&mut rng, 1, 50);
    let model = Model::init(small_model(), 9).expect("valid");
    let sequence = &sequences[0];
    let starts = window_start_states(&model, sequence, 16, &mut StepScratch::new(model.config()));
    assert_eq!(starts.len(), 4);
    for (index, start) in starts.iter().enumerate() {
        let mut state = LiquidState::zeros(model.config());
        let rows = 0..index * 16;
        model
            .forward_sequence(
                &sequence.features[rows.clone()],
                &sequence.deltas[rows],
                &mut state,
            )
            .expect("same lengths");
        assert_eq!(&state, start, "window {index}");
    }
    assert!(starts[3].h().iter().any(|&h| h != 0.0));
}

#[test]
fn training_is_bitwise_deterministic_and_seed_dependent() {
    let mut rng = Rng::seed_from_u64(1);
    let train_set = synthetic(&mut rng, 6, 60);
    let val_set = synthetic(&mut rng, 2, 60);
    let run = |config: &TrainConfig| {
        train(
            &train_set,
            &val_set,
            small_model(),
            config,
            &mut |_| {},
            &no_cancel(),
        )
        .expect("trains")
    };
    let a = run(&quick_config(5));
    let b = run(&quick_config(5));
    let single_thread = run(&TrainConfig {
        threads: 1,
        ..quick_config(5)
    });
    let other_seed = run(&quick_config(6));
    assert_eq!(param_bits(&a.model), param_bits(&b.model));
    assert_eq!(param_bits(&a.model), param_bits(&single_thread.model));
    assert_ne!(param_bits(&a.model), param_bits(&other_seed.model));
    let losses = |o: &TrainOutcome| {
        o.history
            .iter()
            .map(|e| (e.train_loss.to_bits(), e.val_loss.to_bits()))
            .collect::<Vec<_>>()
    };
    assert_eq!(losses(&a), losses(&single_thread));
    // The model moved away from its initialisation.
    let initial = Model::init(small_model(), 5).expect("valid");
    assert_ne!(param_bits(&a.model), param_bits(&initial));
}

#[test]
fn training_learns_a_synthetic_task() {
    let mut rng = Rng::seed_from_u64(11);
    let train_set = synthetic(&mut rng, 24, 120);
    let val_set = synthetic(&mut rng, 6, 120);
    let config = TrainConfig {
        seed: 3,
        max_epochs: 8,
        window: 32,
        batch_size: 8,
        learning_rate: 5e-3,
        ..TrainConfig::default()
    };
    let mut seen = Vec::new();
    let outcome = train(
        &train_set,
        &val_set,
        small_model(),
        &config,
        &mut |progress| seen.push(progress.clone()),
        &no_cancel(),
    )
    .expect("trains");
    assert_eq!(seen, outcome.history);
    let first = &outcome.history[0];
    let last = outcome.history.last().expect("at least one epoch");
    for epoch in &outcome.history {
        eprintln!(
            "epoch {}: train {:.4} val {:.4} auroc {:?} lr {}",
            epoch.epoch, epoch.train_loss, epoch.val_loss, epoch.val_auroc, epoch.learning_rate
        );
    }
    assert!(
        last.train_loss < 0.5 * first.train_loss,
        "{first:?} → {last:?}"
    );
    let best = &outcome.history[outcome.best_epoch - 1];
    assert!(best.val_auroc.is_some_and(|a| a > 0.95), "{best:?}");
    // The returned model is the checkpoint: re-evaluating it reproduces its validation loss exactly.
    let metrics = validation_metrics(&outcome.model, &val_set, outcome.class_weights, 1)
        .expect("valid split");
    assert_eq!(metrics.loss.to_bits(), best.val_loss.to_bits());
    assert_eq!(outcome.best_val_loss, best.val_loss);
    let min_val = outcome
        .history
        .iter()
        .map(|e| e.val_loss)
        .fold(f64::INFINITY, f64::min);
    assert_eq!(best.val_loss, min_val);
}

#[test]
fn early_stopping_ends_training_and_keeps_the_best_checkpoint() {
    let mut rng = Rng::seed_from_u64(4);
    let train_set = synthetic(&mut rng, 4, 60);
    let val_set = synthetic(&mut rng, 2, 60);
    // A huge learning rate and zero patience make the validation loss worsen quickly.
    let config = TrainConfig {
        max_epochs: 30,
        learning_rate: 0.3,
        early_stop_patience: 0,
        ..quick_config(2)
    };
    let outcome = train(
        &train_set,
        &val_set,
        small_model(),
        &config,
        &mut |_| {},
        &no_cancel(),
    )
    .expect("trains");
    assert!(outcome.stopped_early && !outcome.cancelled);
    assert!(outcome.history.len() < 30);
    // With patience 0 training stops at the first epoch that does not improve, right after the best.
    assert_eq!(outcome.best_epoch, outcome.history.len() - 1);
    let metrics = validation_metrics(&outcome.model, &val_set, outcome.class_weights, 2)
        .expect("valid split");
    assert_eq!(metrics.loss, outcome.best_val_loss);
}

#[test]
fn cancellation_returns_the_best_checkpoint_or_an_error() {
    let mut rng = Rng::seed_from_u64(8);
    let train_set = synthetic(&mut rng, 4, 60);
    let val_set = synthetic(&mut rng, 2, 60);
    let config = TrainConfig {
        max_epochs: 10,
        ..quick_config(1)
    };
    let cancelled = AtomicBool::new(true);
    let result = train(
        &train_set,
        &val_set,
        small_model(),
        &config,
        &mut |_| {},
        &cancelled,
    );
    assert_eq!(result.err(), Some(TrainError::Cancelled));

    let cancel = AtomicBool::new(false);
    let mut epochs = 0;
    let outcome = train(
        &train_set,
        &val_set,
        small_model(),
        &config,
        &mut |progress| {
            epochs = progress.epoch;
            if progress.epoch == 2 {
                cancel.store(true, Ordering::Relaxed);
            }
        },
        &cancel,
    )
    .expect("two epochs completed");
    assert!(outcome.cancelled && !outcome.stopped_early);
    assert_eq!((outcome.history.len(), epochs), (2, 2));
}

#[test]
fn invalid_inputs_are_reported_precisely() {
    let mut rng = Rng::seed_from_u64(2);
    let good = synthetic(&mut rng, 2, 40);
    let run = |train_set: &[Sequence], val_set: &[Sequence], config: &TrainConfig| {
        train(
            train_set,
            val_set,
            small_model(),
            config,
            &mut |_| {},
            &no_cancel(),
        )
        .err()
    };
    let config = quick_config(1);
    assert_eq!(
        run(&[], &good, &config),
        Some(TrainError::EmptySplit { split: "training" })
    );
    assert_eq!(
        run(&good, &[Sequence::default()], &config),
        Some(TrainError::EmptySplit {
            split: "validation"
        })
    );
    let mut short = good.clone();
    short[1].labels.pop();
    assert_eq!(
        run(&short, &good, &config),
        Some(TrainError::LengthMismatch {
            split: "training",
            sequence: 1,
            field: "labels",
            expected: 40,
            found: 39
        })
    );
    let mut nan = good.clone();
    nan[0].features[7][6] = f64::NAN;
    assert_eq!(
        run(&good, &nan, &config),
        Some(TrainError::NonFiniteFeature {
            split: "validation",
            sequence: 0,
            row: 7,
            feature: "q"
        })
    );
    let mut invalid = good.clone();
    for sequence in &mut invalid {
        sequence.valid.fill(false);
    }
    assert_eq!(
        run(&invalid, &good, &config),
        Some(TrainError::NoValidRows { split: "training" })
    );
    let mut normal_only = good.clone();
    for sequence in &mut normal_only {
        sequence.labels.fill(false);
    }
    assert_eq!(
        run(&normal_only, &good, &config),
        Some(TrainError::SingleClass { spoofed: false })
    );
    let bad_config = TrainConfig {
        window: 0,
        ..config.clone()
    };
    assert!(matches!(
        run(&good, &good, &bad_config),
        Some(TrainError::InvalidConfig {
            field: "window",
            ..
        })
    ));
    let bad_beta = TrainConfig {
        beta2: 1.0,
        ..config.clone()
    };
    assert!(matches!(
        run(&good, &good, &bad_beta),
        Some(TrainError::InvalidConfig { field: "beta2", .. })
    ));
    let bad_model = ModelConfig {
        d_h: 0,
        ..small_model()
    };
    assert!(matches!(
        train(&good, &good, bad_model, &config, &mut |_| {}, &no_cancel()),
        Err(TrainError::Model(ModelError::InvalidDimension {
            name: "d_h",
            ..
        }))
    ));
}
