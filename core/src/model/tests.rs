//! Unit tests of the model: shapes, the step/sequence equivalence and the hand-derived gradients.

use super::*;
use crate::evidence::{DRIFT_FEATURES_START, FEATURE_CAPACITY, FeatureSchema, NU_INDEX};

/// A random sequence: ξ ~ N(0,1) (ν = 1 except on `invalid_rows`), δ_0 = 0 then δ ∈ (0.2, 3].
fn random_sequence(
    rng: &mut Rng,
    steps: usize,
    invalid_rows: &[usize],
) -> (Vec<Features>, Vec<f64>, Vec<bool>, Vec<bool>) {
    let mut xs = Vec::new();
    let mut deltas = Vec::new();
    let mut labels = Vec::new();
    let mut mask = Vec::new();
    for t in 0..steps {
        let valid = !invalid_rows.contains(&t);
        let mut x = [0.0; FEATURE_CAPACITY];
        for value in &mut x {
            *value = rng.normal();
        }
        x[NU_INDEX] = if valid { 1.0 } else { 0.0 };
        xs.push(x);
        deltas.push(if t == 0 {
            0.0
        } else {
            3.0 - rng.uniform_range(0.0, 2.8)
        });
        labels.push(rng.uniform() < 0.5);
        mask.push(valid);
    }
    (xs, deltas, labels, mask)
}

/// A paper-schema ξ (9 channels) padded with zeros for the drift channels.
fn padded(paper: [f64; 9]) -> Features {
    let mut x = [0.0; FEATURE_CAPACITY];
    x[..9].copy_from_slice(&paper);
    x
}

/// Every parameter (biases too) uniform in ±`scale`, so nothing saturates and bias paths are exercised.
fn randomise(model: &mut Model, rng: &mut Rng, scale: f64) {
    for (_, tensor) in model.params_mut().tensors_mut() {
        for value in tensor.data_mut() {
            *value = rng.uniform_range(-scale, scale);
        }
    }
}

fn small_config(ablation: Ablation) -> ModelConfig {
    ModelConfig {
        d_s: 5,
        d_zeta: 7,
        d_h: 6,
        ablation,
        ..ModelConfig::default()
    }
}

fn random_state(config: &ModelConfig, rng: &mut Rng) -> LiquidState {
    let h = (0..config.d_h)
        .map(|_| rng.uniform_range(-0.5, 0.5))
        .collect();
    let v = if config.ablation.first_order_cell {
        vec![0.0; config.d_h]
    } else {
        (0..config.d_h)
            .map(|_| rng.uniform_range(-0.5, 0.5))
            .collect()
    };
    LiquidState::from_parts(h, v).expect("same widths")
}

#[test]
fn step_by_step_and_sequence_outputs_are_bitwise_identical() {
    let config = ModelConfig::default();
    let model = Model::init(config.clone(), 11).expect("valid config");
    let mut rng = Rng::seed_from_u64(5);
    let (xs, deltas, _, _) = random_sequence(&mut rng, 40, &[7, 8, 30]);

    let mut stepped_state = LiquidState::zeros(&config);
    let mut scratch = StepScratch::new(&config);
    let stepped: Vec<f64> = xs
        .iter()
        .zip(&deltas)
        .map(|(x, &d)| model.step(&mut stepped_state, x, d, &mut scratch))
        .collect();

    // The same trajectory in two calls, carrying the state between them.
    let mut state = LiquidState::zeros(&config);
    let mut sequence = model
        .forward_sequence(&xs[..17], &deltas[..17], &mut state)
        .expect("same lengths");
    sequence.extend(
        model
            .forward_sequence(&xs[17..], &deltas[17..], &mut state)
            .expect("same lengths"),
    );
    let bits = |v: &[f64]| v.iter().map(|p| p.to_bits()).collect::<Vec<_>>();
    assert_eq!(bits(&stepped), bits(&sequence));
    assert_eq!(stepped_state, state);
    // And the logits path agrees with σ(logit).
    let mut logit_state = LiquidState::zeros(&config);
    let logits = model
        .forward_logits(&xs, &deltas, &mut logit_state)
        .expect("same lengths");
    let probabilities: Vec<f64> = logits.iter().map(|&z| probability_from_logit(z)).collect();
    assert_eq!(bits(&probabilities), bits(&stepped));
    assert!(stepped.iter().all(|p| (0.0..=1.0).contains(p)));
    // The outputs actually depend on the inputs (not a constant model).
    assert!(stepped.iter().any(|&p| (p - stepped[5]).abs() > 1e-6));
}

#[test]
fn tiny_model_matches_a_hand_computation() {
    // d_s = d_ζ = d_h = 1 with chosen weights; the expected value is computed here from the equations.
    let config = ModelConfig {
        d_s: 1,
        d_zeta: 1,
        d_h: 1,
        schema: FeatureSchema::Paper,
        ..ModelConfig::default()
    };
    let mut model = Model::init(config.clone(), 0).expect("valid config");
    let values: [(&str, &[f64]); 18] = [
        ("w_instant", &[0.5, -0.25, 1.0]),
        ("b_instant", &[0.1]),
        ("w_evolution", &[0.2, 0.2, -0.3, 0.4]),
        ("b_evolution", &[-0.2]),
        ("w_persistence", &[0.7, 0.3]),
        ("b_persistence", &[0.0]),
        ("w_conductance", &[1.5, -0.5]),
        ("b_conductance", &[0.25]),
        ("w_fusion", &[0.3, -0.6, 0.9, 2.0]),
        ("b_fusion", &[0.05]),
        ("w_candidate", &[1.2]),
        ("b_candidate", &[-0.1]),
        ("w_tau_h", &[0.8]),
        ("b_tau_h", &[-1.0]),
        ("w_tau_v", &[-0.4]),
        ("b_tau_v", &[0.5]),
        ("w_out", &[2.0, -1.5]),
        ("b_out", &[0.3]),
    ];
    for (name, tensor) in model.params_mut().tensors_mut() {
        let (_, v) = values.iter().find(|(n, _)| *n == name).expect("all named");
        tensor.data_mut().copy_from_slice(v);
    }
    let x = padded([0.4, -1.0, 0.3, 0.2, -0.5, 0.1, 2.0, 1.5, 1.0]);
    let (h0, v0, delta) = (0.2, -0.1, 1.5);

    let sig = |z: f64| 1.0 / (1.0 + (-z).exp());
    let (x0, x1) = (x[0], x[1]);
    let s_i = sig(0.5 * x0 - 0.25 * x1 + 1.0 * 2.0 + 0.1);
    let s_e = sig(0.2 * 0.3 + 0.2 * 0.2 - 0.3 * -0.5 + 0.4 * 0.1 - 0.2);
    let s_p = sig(0.7 * 1.5 + 0.3 * 1.0);
    let c = |a: f64, b: f64| sig(1.5 * (a - b).abs() - 0.5 * a * b + 0.25);
    let (c_ie, c_ip, c_ep) = (c(s_i, s_e), c(s_i, s_p), c(s_e, s_p));
    let bar_i = s_i + 0.5 * (c_ie * (s_e - s_i) + c_ip * (s_p - s_i));
    let bar_e = s_e + 0.5 * (c_ie * (s_i - s_e) + c_ep * (s_p - s_e));
    let bar_p = s_p + 0.5 * (c_ip * (s_i - s_p) + c_ep * (s_e - s_p));
    let zeta =
        (0.3 * bar_i - 0.6 * bar_e + 0.9 * bar_p + 2.0 * bar_i * bar_e * bar_p + 0.05).tanh();
    let candidate = (1.2 * zeta - 0.1).tanh();
    let tau_h = 0.05 + 9.95 * sig(0.8 * zeta - 1.0);
    let tau_v = 0.05 + 9.95 * sig(-0.4 * zeta + 0.5);
    let gamma = 1.0 - (-delta / tau_h).exp();
    let beta = (-delta / tau_v).exp();
    let v1 = beta * v0 + (1.0 - beta) * (candidate - h0);
    let h1 = h0 + gamma * v1;
    let expected = sig(2.0 * h1 - 1.5 * v1 + 0.3);

    let mut state = LiquidState::from_parts(vec![h0], vec![v0]).expect("same widths");
    let p = model.step(&mut state, &x, delta, &mut StepScratch::new(&config));
    assert!((p - expected).abs() < 1e-14, "{p} vs {expected}");
    assert!((state.h()[0] - h1).abs() < 1e-14 && (state.v()[0] - v1).abs() < 1e-14);
    assert!((bar_i + bar_e + bar_p - (s_i + s_e + s_p)).abs() < 1e-15);
}

#[test]
fn exchange_conserves_the_sum_of_role_states() {
    let config = ModelConfig::default();
    let mut model = Model::init(config.clone(), 2).expect("valid config");
    let mut rng = Rng::seed_from_u64(9);
    randomise(&mut model, &mut rng, 1.0);
    let (xs, _, _, _) = random_sequence(&mut rng, 5, &[]);
    let mut scratch = StepScratch::new(&config);
    let mut state = LiquidState::zeros(&config);
    for x in &xs {
        model.step(&mut state, x, 1.0, &mut scratch);
        assert!(scratch.conductance.iter().all(|&c| c > 0.0 && c < 1.0));
        let ds = config.d_s;
        for k in 0..ds {
            let before: f64 = scratch.s.iter().map(|s| s[k]).sum();
            let after: f64 = (0..3).map(|r| scratch.fusion_in[r * ds + k]).sum();
            assert!((before - after).abs() < 1e-14, "{before} vs {after}");
        }
    }
}

#[test]
fn zero_delta_leaves_the_state_unchanged_and_nan_delta_is_zero() {
    let config = ModelConfig::default();
    let model = Model::init(config.clone(), 4).expect("valid config");
    let mut rng = Rng::seed_from_u64(1);
    let start = random_state(&config, &mut rng);
    let x = padded([1.0, -2.0, 0.5, 0.1, 0.0, 0.3, 2.0, 1.0, 1.0]);
    let mut scratch = StepScratch::new(&config);
    for delta in [0.0, -3.0, f64::NAN] {
        let mut state = start.clone();
        model.step(&mut state, &x, delta, &mut scratch);
        assert_eq!(state, start, "delta {delta}");
    }
    // δ above the clamp behaves exactly like MAX_DELTA_S.
    let (mut a, mut b) = (start.clone(), start.clone());
    let pa = model.step(&mut a, &x, 60.0, &mut scratch);
    let pb = model.step(&mut b, &x, MAX_DELTA_S, &mut scratch);
    assert_eq!((pa.to_bits(), &a), (pb.to_bits(), &b));
    assert_ne!(a, start);
}

#[test]
fn non_finite_features_are_read_as_zero() {
    let config = ModelConfig::default();
    let model = Model::init(config.clone(), 4).expect("valid config");
    let mut scratch = StepScratch::new(&config);
    let clean = padded([0.0, -2.0, 0.5, 0.0, 0.0, 0.3, 2.0, 0.0, 1.0]);
    let mut dirty = padded([
        f64::NAN,
        -2.0,
        0.5,
        f64::INFINITY,
        0.0,
        0.3,
        2.0,
        f64::NEG_INFINITY,
        1.0,
    ]);
    dirty[DRIFT_FEATURES_START] = f64::NAN;
    let (mut a, mut b) = (LiquidState::zeros(&config), LiquidState::zeros(&config));
    for _ in 0..3 {
        let pa = model.step(&mut a, &clean, 1.0, &mut scratch);
        let pb = model.step(&mut b, &dirty, 1.0, &mut scratch);
        assert_eq!(pa.to_bits(), pb.to_bits());
        assert!(pb.is_finite());
    }
}

#[test]
fn removed_feature_groups_do_not_influence_the_output() {
    for (name, features) in FeatureGroups::NAMED {
        // The widest schema, so that every channel is read.
        let config = ModelConfig {
            ablation: Ablation {
                features,
                ..Ablation::default()
            },
            schema: FeatureSchema::V3,
            ..ModelConfig::default()
        };
        let model = Model::init(config.clone(), 8).expect("valid config");
        let mut scratch = StepScratch::new(&config);
        let mut base = [0.3; FEATURE_CAPACITY];
        base[NU_INDEX] = 1.0;
        let kept = features.kept();
        // Every removed input perturbed at once: no effect.
        let mut noisy = base;
        for (index, value) in noisy.iter_mut().enumerate() {
            if !kept[index] {
                *value = 5.0 + index as f64;
            }
        }
        let step = |x: &Features, scratch: &mut StepScratch| {
            model.step(&mut LiquidState::zeros(&config), x, 1.0, scratch)
        };
        let pa = step(&base, &mut scratch);
        assert_eq!(pa.to_bits(), step(&noisy, &mut scratch).to_bits(), "{name}");
        // …while each kept input does move it.
        for index in (0..FEATURE_CAPACITY).filter(|&i| kept[i] && i != NU_INDEX) {
            let mut moved = base;
            moved[index] = 3.0;
            assert_ne!(pa, step(&moved, &mut scratch), "{name}: input {index}");
        }
    }
    // A role with no input at all sits at σ(b): with zero init biases, 0.5.
    let config = ModelConfig {
        ablation: Ablation {
            features: FeatureGroups::LowOrderOnly,
            ..Ablation::default()
        },
        ..ModelConfig::default()
    };
    let model = Model::init(config.clone(), 8).expect("valid config");
    let mut scratch = StepScratch::new(&config);
    model.step(
        &mut LiquidState::zeros(&config),
        &[1.0; FEATURE_CAPACITY],
        1.0,
        &mut scratch,
    );
    assert!(scratch.s[1].iter().all(|&s| s == 0.5));
}

#[test]
fn first_order_cell_keeps_v_at_zero() {
    let config = ModelConfig {
        ablation: Ablation {
            first_order_cell: true,
            ..Ablation::default()
        },
        ..ModelConfig::default()
    };
    let model = Model::init(config.clone(), 8).expect("valid config");
    let mut rng = Rng::seed_from_u64(2);
    let (xs, deltas, _, _) = random_sequence(&mut rng, 10, &[]);
    let mut state = LiquidState::zeros(&config);
    model
        .forward_sequence(&xs, &deltas, &mut state)
        .expect("same lengths");
    assert!(state.v().iter().all(|&v| v == 0.0));
    assert!(state.h().iter().any(|&h| h != 0.0));
}

#[test]
fn bad_inputs_are_errors_or_documented_resets() {
    let config = ModelConfig::default();
    let model = Model::init(config.clone(), 1).expect("valid config");
    let x = [0.0; FEATURE_CAPACITY];
    assert_eq!(
        model.forward_sequence(&[x, x], &[1.0], &mut LiquidState::zeros(&config)),
        Err(ModelError::LengthMismatch {
            field: "deltas",
            expected: 2,
            found: 1
        })
    );
    // A state built for another width is reset (as a new trajectory) instead of panicking.
    let narrow = ModelConfig {
        d_h: 3,
        ..ModelConfig::default()
    };
    let mut state = LiquidState::zeros(&narrow);
    let mut scratch = StepScratch::new(&narrow);
    let p = model.step(&mut state, &x, 1.0, &mut scratch);
    let mut fresh = LiquidState::zeros(&config);
    let q = model.step(&mut fresh, &x, 1.0, &mut StepScratch::new(&config));
    assert_eq!((p.to_bits(), state), (q.to_bits(), fresh));
    for (bad, name) in [
        (
            ModelConfig {
                d_s: 0,
                ..ModelConfig::default()
            },
            "d_s",
        ),
        (
            ModelConfig {
                d_h: 5000,
                ..ModelConfig::default()
            },
            "d_h",
        ),
    ] {
        assert!(matches!(
            Model::init(bad, 0),
            Err(ModelError::InvalidDimension { name: n, .. }) if n == name
        ));
    }
    let inverted = ModelConfig {
        tau_min: 2.0,
        tau_max: 1.0,
        ..ModelConfig::default()
    };
    assert!(matches!(
        Model::init(inverted, 0),
        Err(ModelError::InvalidTimeConstants { .. })
    ));
}

#[test]
fn model_round_trips_through_json_and_rejects_bad_tensors() {
    let config = ModelConfig {
        d_s: 4,
        d_zeta: 5,
        d_h: 3,
        ablation: Ablation {
            no_third_order: true,
            features: FeatureGroups::NoEvolution,
            ..Ablation::default()
        },
        ..ModelConfig::default()
    };
    let model = Model::init(config, 21).expect("valid config");
    let json = serde_json::to_string(&model).expect("serialisable");
    let back: Model = serde_json::from_str(&json).expect("round trip");
    assert_eq!(back, model);
    assert!(json.contains("\"w_fusion\":{\"shape\":[5,12]"));
    assert!(json.contains("\"no_evolution\""));

    let mut value: serde_json::Value = serde_json::from_str(&json).expect("json");
    value["params"]["w_fusion"]["shape"] = serde_json::json!([5, 16]);
    let err = serde_json::from_value::<Model>(value).expect_err("shape mismatch");
    assert!(
        err.to_string().contains("w_fusion has shape [5, 16]"),
        "{err}"
    );

    let mut value: serde_json::Value = serde_json::from_str(&json).expect("json");
    value["params"]["w_extra"] = value["params"]["b_out"].clone();
    assert!(serde_json::from_value::<Model>(value).is_err());
}

#[test]
fn window_loss_is_the_masked_weighted_mean() {
    // Zero weights everywhere except b_out: every logit is b_out, so the loss is hand-computable.
    let config = small_config(Ablation::default());
    let mut model = Model::init(config.clone(), 3).expect("valid config");
    for (_, tensor) in model.params_mut().tensors_mut() {
        tensor.data_mut().fill(0.0);
    }
    model.params_mut().b_out.data_mut()[0] = 0.5;
    let xs = [[0.0; FEATURE_CAPACITY]; 4];
    let window = TrainingWindow {
        features: &xs,
        deltas: &[0.0, 1.0, 1.0, 1.0],
        labels: &[true, false, true, true],
        mask: &[true, true, false, true],
        weights: &[2.0, 0.5, 7.0, 2.0],
    };
    let result = model
        .loss_and_gradient(&window, &LiquidState::zeros(&config))
        .expect("valid window");
    let l1 = (1.0 + (-0.5f64).exp()).ln(); // −ln σ(0.5)
    let l0 = (1.0 + 0.5f64.exp()).ln(); // −ln(1 − σ(0.5))
    let expected = (2.0 * l1 + 0.5 * l0 + 2.0 * l1) / 3.0;
    assert_eq!(result.masked_rows, 3);
    assert!((result.loss - expected).abs() < 1e-15);
    let s = 1.0 / (1.0 + (-0.5f64).exp());
    let expected_b_out = (2.0 * (s - 1.0) + 0.5 * s + 2.0 * (s - 1.0)) / 3.0;
    let b_out = result.gradient.get("b_out").expect("present").data()[0];
    assert!((b_out - expected_b_out).abs() < 1e-15);
    // Large logits stay finite (log-sum-exp form).
    assert!((bce_with_logits(800.0, false, 1.0) - 800.0).abs() < 1e-9);
    assert_eq!(bce_with_logits(-800.0, false, 1.0), 0.0);
}

/// All variants the gradient check covers: the full model, each switch alone, each feature group.
fn ablation_variants() -> Vec<Ablation> {
    let mut variants = vec![
        Ablation::default(),
        Ablation {
            no_exchange: true,
            ..Ablation::default()
        },
        Ablation {
            no_third_order: true,
            ..Ablation::default()
        },
        Ablation {
            first_order_cell: true,
            ..Ablation::default()
        },
    ];
    for features in [
        FeatureGroups::NoAccumulation,
        FeatureGroups::NoEvolution,
        FeatureGroups::NoEvolutionNoQ,
        FeatureGroups::LowOrderOnly,
        FeatureGroups::ValidityOnly,
    ] {
        variants.push(Ablation {
            features,
            ..Ablation::default()
        });
    }
    variants
}

/// Smallest |s^a − s^b| over all pairs, components and steps (the |·| kink the check must avoid).
fn smallest_role_gap(model: &Model, xs: &[Features], deltas: &[f64], state: &LiquidState) -> f64 {
    let mut state = state.clone();
    let mut scratch = StepScratch::new(model.config());
    let mut gap = f64::INFINITY;
    for (x, &d) in xs.iter().zip(deltas) {
        model.step(&mut state, x, d, &mut scratch);
        for &(a, b) in &forward::PAIRS {
            for (sa, sb) in scratch.s[a].iter().zip(&scratch.s[b]) {
                gap = gap.min((sa - sb).abs());
            }
        }
    }
    gap
}

/// Finite-difference step for the gradient check.
const FD_STEP: f64 = 1e-4;

/// A randomised model, sequence and incoming state for the gradient check. Seeds are tried from
/// `seed` on until no role-state pair comes closer than a parameter perturbation could move it, so the
/// |s^a − s^b| kink is never crossed by the finite differences.
#[allow(clippy::type_complexity)]
fn gradient_check_case(
    config: &ModelConfig,
    seed: u64,
) -> (
    Model,
    Vec<Features>,
    Vec<f64>,
    Vec<bool>,
    Vec<bool>,
    LiquidState,
    Rng,
) {
    for attempt in 0..100 {
        let mut rng = Rng::seed_from_u64(seed + 1000 * attempt);
        let mut model = Model::init(config.clone(), seed).expect("valid config");
        randomise(&mut model, &mut rng, 0.5);
        let (xs, deltas, labels, mask) = random_sequence(&mut rng, 12, &[3, 4, 9]);
        let state = random_state(config, &mut rng);
        // An encoder weight moved by 2h moves s by at most ¼·2h·max|x| (σ' ≤ ¼).
        let max_input = xs.iter().flatten().fold(1.0f64, |m, v| m.max(v.abs()));
        let max_shift = 0.25 * 2.0 * FD_STEP * max_input;
        if config.ablation.no_exchange
            || smallest_role_gap(&model, &xs, &deltas, &state) > 3.0 * max_shift
        {
            return (model, xs, deltas, labels, mask, state, rng);
        }
    }
    panic!("no tie-free case found for {config:?}");
}

/// Central-difference check (fourth-order stencil) of every tensor; returns the worst relative error.
fn gradient_check(config: ModelConfig, seed: u64, subset: usize) -> f64 {
    let (model, xs, deltas, labels, mask, state, mut rng) = gradient_check_case(&config, seed);
    let weights: Vec<f64> = labels.iter().map(|&l| if l { 1.7 } else { 0.6 }).collect();
    let window = TrainingWindow {
        features: &xs,
        deltas: &deltas,
        labels: &labels,
        mask: &mask,
        weights: &weights,
    };
    let analytic = model.loss_and_gradient(&window, &state).expect("valid");
    assert_eq!(analytic.masked_rows, 9);
    // Forward-only loss (same arithmetic as the training loss) for the perturbed evaluations.
    let loss_at = |model: &Model| {
        let logits = model
            .forward_logits(&xs, &deltas, &mut state.clone())
            .expect("same lengths");
        let mut sum = 0.0;
        for t in (0..xs.len()).filter(|&t| mask[t]) {
            sum += bce_with_logits(logits[t], labels[t], weights[t]);
        }
        sum / 9.0
    };
    assert!((loss_at(&model) - analytic.loss).abs() < 1e-15);

    let mut worst: f64 = 0.0;
    let names: Vec<&'static str> = model.params().tensors().iter().map(|(n, _)| *n).collect();
    for name in names {
        let size = model.params().get(name).expect("present").data().len();
        let mut indices: Vec<usize> = (0..size).collect();
        if size > 64 {
            rng.shuffle(&mut indices);
            indices.truncate(subset);
        }
        for index in indices {
            let original = model.params().get(name).expect("present").data()[index];
            let h = FD_STEP;
            let eval = |offset: f64| {
                let mut perturbed = model.clone();
                for (n, tensor) in perturbed.params_mut().tensors_mut() {
                    if n == name {
                        tensor.data_mut()[index] = original + offset;
                    }
                }
                loss_at(&perturbed)
            };
            let numeric =
                (eval(-2.0 * h) - 8.0 * eval(-h) + 8.0 * eval(h) - eval(2.0 * h)) / (12.0 * h);
            let exact = analytic.gradient.get(name).expect("present").data()[index];
            // The loss itself carries ~1e-16 relative rounding noise, which the stencil amplifies to
            // ~1e-12 absolute at h = 1e-4. The floor keeps tiny entries from turning that noise into a
            // meaningless ratio: below |a| + |b| = 1e-5 the check demands |a − b| < 1e-11.
            let error = (numeric - exact).abs() / (numeric.abs() + exact.abs()).max(1e-5);
            assert!(
                error < 1e-6,
                "{:?} {name}[{index}]: analytic {exact:e} numeric {numeric:e} (rel {error:e})",
                config.ablation
            );
            worst = worst.max(error);
        }
    }
    worst
}

#[test]
fn gradients_match_finite_differences_for_every_tensor_and_variant() {
    for (i, ablation) in ablation_variants().into_iter().enumerate() {
        let worst = gradient_check(small_config(ablation), 100 + i as u64, 24);
        eprintln!("{ablation:?}: worst relative error {worst:e}");
    }
}

#[test]
fn gradients_match_finite_differences_for_every_feature_schema() {
    // The roles' widths follow the schema: v3's offset channels join the persistence role.
    for schema in [FeatureSchema::Paper, FeatureSchema::V2, FeatureSchema::V3] {
        let config = ModelConfig {
            schema,
            ..small_config(Ablation::default())
        };
        let worst = gradient_check(config, 300, 24);
        eprintln!("{schema:?}: worst relative error {worst:e}");
    }
}

#[test]
fn gradients_match_finite_differences_at_default_width() {
    let worst = gradient_check(ModelConfig::default(), 7, 24);
    eprintln!("default width: worst relative error {worst:e}");
}

#[test]
fn window_gradient_stops_at_the_incoming_state_and_reports_the_outgoing_one() {
    let config = small_config(Ablation::default());
    let mut model = Model::init(config.clone(), 5).expect("valid config");
    let mut rng = Rng::seed_from_u64(6);
    randomise(&mut model, &mut rng, 0.5);
    let (xs, deltas, labels, mask) = random_sequence(&mut rng, 8, &[2]);
    let weights = vec![1.0; 8];
    let state_in = random_state(&config, &mut rng);
    let window = TrainingWindow {
        features: &xs,
        deltas: &deltas,
        labels: &labels,
        mask: &mask,
        weights: &weights,
    };
    let result = model.loss_and_gradient(&window, &state_in).expect("valid");
    let mut expected_state = state_in.clone();
    model
        .forward_sequence(&xs, &deltas, &mut expected_state)
        .expect("same lengths");
    assert_eq!(result.state_out, expected_state);
    // A window with no masked row has zero loss and an all-zero gradient.
    let none = vec![false; 8];
    let empty = model
        .loss_and_gradient(
            &TrainingWindow {
                mask: &none,
                ..window
            },
            &state_in,
        )
        .expect("valid");
    assert_eq!(empty.loss, 0.0);
    assert_eq!(empty.gradient.l2_norm(), 0.0);
    // Mismatched lengths are errors.
    let short = [true; 3];
    assert!(matches!(
        model.loss_and_gradient(
            &TrainingWindow {
                labels: &short,
                ..window
            },
            &state_in
        ),
        Err(ModelError::LengthMismatch {
            field: "labels",
            ..
        })
    ));
}

#[test]
fn the_parameter_count_comes_from_the_shapes_and_is_bounded() {
    let default = ModelConfig::default();
    assert_eq!(
        Params::count_for(&default),
        Params::zeros(&default).scalar_count()
    );
    let ablated = ModelConfig {
        ablation: Ablation {
            no_exchange: true,
            first_order_cell: true,
            ..Ablation::default()
        },
        ..ModelConfig::default()
    };
    assert_eq!(
        Params::count_for(&ablated),
        Params::zeros(&ablated).scalar_count()
    );
    // Widths within MAX_DIMENSION but a cost far beyond the bound: refused before any tensor of
    // that size exists.
    let costly = ModelConfig {
        d_s: 1024,
        d_zeta: 1024,
        d_h: 1024,
        ..ModelConfig::default()
    };
    assert!(matches!(
        Model::init(costly, 0),
        Err(ModelError::TooManyParameters { parameters }) if parameters > MAX_PARAMETERS
    ));
}
