//! Exact-bit fingerprints of the model arithmetic: the bundled model's outputs and a short training
//! run, hashed bit for bit. They pin what no other test can: that a change of compiler flags (the
//! x86-64-v3 build of `.cargo/config.toml` versus a portable build), of kernels or of dependencies
//! leaves every result unchanged to the last bit. If a deliberate change of the arithmetic moves them,
//! re-derive the constants and say so in the commit.

use std::sync::atomic::AtomicBool;

use spoofwatch_core::evidence::FeatureSchema;
use spoofwatch_core::evidence::Features;
use spoofwatch_core::model::artifact::ModelArtifact;
use spoofwatch_core::model::{LiquidState, ModelConfig};
use spoofwatch_core::rng::Rng;
use spoofwatch_core::train::{Sequence, TrainConfig, train};

/// FNV-1a over the bit patterns.
fn fingerprint(values: impl IntoIterator<Item = f64>) -> u64 {
    let mut hash = 0xcbf2_9ce4_8422_2325u64;
    for value in values {
        for byte in value.to_bits().to_le_bytes() {
            hash ^= u64::from(byte);
            hash = hash.wrapping_mul(0x0100_0000_01b3);
        }
    }
    hash
}

fn seeded_features(rng: &mut Rng, count: usize) -> Vec<Features> {
    spoofwatch_core::testdata::random_features(rng, count, 2.0, FeatureSchema::Paper)
}

#[test]
fn bundled_model_outputs_are_bit_exact() {
    let bytes = include_bytes!("../../models/paper.json");
    let artifact = ModelArtifact::from_slice(bytes).expect("bundled model loads");
    let model = &artifact.model;
    let xs = seeded_features(&mut Rng::seed_from_u64(7), 2000);
    let deltas: Vec<f64> = (0..xs.len()).map(|t| 0.5 + (t % 3) as f64).collect();
    let mut state = LiquidState::zeros(model.config());
    let probabilities = model
        .forward_sequence(&xs, &deltas, &mut state)
        .expect("lengths match");
    assert_eq!(
        fingerprint(
            probabilities
                .iter()
                .copied()
                .chain(state.h().iter().copied())
        ),
        0xf41a_4b4d_c42a_5393,
        "bundled model outputs changed bits"
    );
}

#[test]
fn a_short_training_run_is_bit_exact() {
    let mut rng = Rng::seed_from_u64(11);
    let sequence = |rng: &mut Rng| {
        let xs = seeded_features(rng, 120);
        let labels: Vec<bool> = (0..xs.len()).map(|t| (60..90).contains(&t)).collect();
        let features = xs
            .into_iter()
            .zip(&labels)
            .map(|(mut x, &spoofed)| {
                if spoofed {
                    x[0] += 3.0;
                }
                x
            })
            .collect();
        Sequence {
            features,
            deltas: vec![1.0; 120],
            labels,
            valid: vec![true; 120],
        }
    };
    let train_set: Vec<Sequence> = (0..4).map(|_| sequence(&mut rng)).collect();
    let val_set = vec![sequence(&mut rng)];
    let config = TrainConfig {
        max_epochs: 2,
        window: 40,
        batch_size: 2,
        ..TrainConfig::default()
    };
    let model_config = ModelConfig {
        d_s: 8,
        d_zeta: 12,
        d_h: 10,
        // The pinned run is the paper's model; a v2 model has a wider persistence encoder.
        schema: FeatureSchema::Paper,
        ..ModelConfig::default()
    };
    let outcome = train(
        &train_set,
        &val_set,
        model_config,
        &config,
        &mut |_| {},
        &AtomicBool::new(false),
    )
    .expect("synthetic data trains");
    let tensors = outcome.model.params().tensors();
    let values = tensors
        .iter()
        .flat_map(|(_, tensor)| tensor.data().iter().copied());
    assert_eq!(
        fingerprint(values),
        0x6f4a_f743_7a61_3384,
        "trained parameters changed bits"
    );
}
