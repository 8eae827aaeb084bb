//! Model artifacts are validated by meaning: a poisoned-artifact corpus, each case refused
//! with the field it poisons named, and property tests over random mutations of real artifacts (no
//! panic; every refusal names its field; everything accepted serves finite probabilities in [0, 1]).

use std::sync::Arc;

use proptest::prelude::*;
use serde_json::{Value, json};
use spoofwatch_core::canary::canary_drive;
use spoofwatch_core::detector::Detector;
use spoofwatch_core::model::artifact::{ArtifactError, ModelArtifact};

const DEFAULT_MODEL: &[u8] = include_bytes!("../../models/default.json");
const PAPER_MODEL: &[u8] = include_bytes!("../../models/paper.json");

fn base(bytes: &[u8]) -> Value {
    serde_json::from_slice(bytes).expect("a bundled model is JSON")
}

/// The refusal of `value`, which must name `field` and say `says` in its message.
fn refused(value: &Value, field: &str, says: &str) -> ArtifactError {
    let error = ModelArtifact::from_slice(value.to_string().as_bytes())
        .expect_err(&format!("{field} must be refused"));
    assert_eq!(error.field().as_deref(), Some(field), "{error}");
    assert!(error.to_string().contains(says), "{error}");
    error
}

/// Every probability of the streaming detector over the canary drive.
fn canary_probabilities(artifact: ModelArtifact) -> Vec<f64> {
    let mut detector = Detector::new(Arc::new(artifact));
    canary_drive()
        .iter()
        .map(|sample| detector.step(sample, false).probability)
        .collect()
}

#[test]
fn the_bundled_models_pass_every_check_and_the_canary() {
    for bytes in [DEFAULT_MODEL, PAPER_MODEL] {
        let artifact = ModelArtifact::from_slice(bytes).expect("a bundled model loads");
        let probabilities = canary_probabilities(artifact);
        assert!(probabilities.iter().all(|p| (0.0..=1.0).contains(p)));
    }
}

#[test]
fn extreme_weights_are_refused_at_the_tensor() {
    let mut value = base(DEFAULT_MODEL);
    value["model"]["params"]["w_fusion"]["data"][5] = json!(1e308);
    let error = refused(&value, "model.params.w_fusion", "1.000e308");
    assert!(error.to_string().contains("flat index 5"), "{error}");
    let mut value = base(DEFAULT_MODEL);
    value["model"]["params"]["w_out"]["data"][0] = json!(-1e308);
    refused(&value, "model.params.w_out", "-1.000e308");
    // Just beyond the bound.
    let mut value = base(PAPER_MODEL);
    value["model"]["params"]["b_out"]["data"][0] = json!(10_001.0);
    refused(&value, "model.params.b_out", "1e4");
}

#[test]
fn evidence_statistics_outside_their_ranges_are_refused() {
    let mut value = base(DEFAULT_MODEL);
    value["evidence"]["mu_e"] = json!(1e308);
    let error = refused(&value, "evidence.mu_e", "got 1.000e308");
    assert!(error.to_string().len() < 200, "readable: {error}");
    value["evidence"]["mu_e"] = json!(-0.5);
    refused(&value, "evidence.mu_e", "got -0.5");

    let mut value = base(DEFAULT_MODEL);
    value["evidence"]["sigma_hat"] = json!([[1.0, 2.0], [2.0, 1.0]]);
    refused(&value, "evidence.sigma_hat", "positive definite");
    value["evidence"]["sigma_hat"] = json!([[1.0, 0.5], [0.0, 1.0]]);
    refused(&value, "evidence.sigma_hat", "symmetric");
    value["evidence"]["sigma_hat"] = json!([[1e300, 0.0], [0.0, 1e300]]);
    refused(&value, "evidence.sigma_hat", "1.000e300");

    let mut value = base(DEFAULT_MODEL);
    value["evidence"]["kappa"] = json!(-1e9);
    refused(&value, "evidence.kappa", "-1.000e9");
    let mut value = base(DEFAULT_MODEL);
    value["evidence"]["drift"]["clip_m"] = json!(-3.0);
    refused(&value, "evidence.drift.clip_m", "got -3");
}

#[test]
fn scaler_values_outside_their_ranges_are_refused() {
    let mut value = base(DEFAULT_MODEL);
    value["scaler"]["scale"][3] = json!(-0.5);
    let error = refused(&value, "scaler.scale", "got -0.5");
    assert!(error.to_string().contains("eta_dot_n"), "{error}");
    let mut value = base(DEFAULT_MODEL);
    value["scaler"]["center"][0] = json!(-1e200);
    refused(&value, "scaler.center", "-1.000e200");
    let mut value = base(DEFAULT_MODEL);
    value["scaler"]["center"]
        .as_array_mut()
        .expect("array")
        .pop();
    refused(&value, "scaler.center", "fit no feature schema");
}

#[test]
fn operating_points_outside_their_ranges_are_refused() {
    let mut value = base(DEFAULT_MODEL);
    value["operating_point"]["n_p"] = json!(u32::MAX);
    refused(&value, "operating_point.n_p", "4294967295");
    value["operating_point"]["n_p"] = json!(0);
    refused(&value, "operating_point.n_p", "1..=3600");
    value["operating_point"]["n_p"] = json!(3600);
    ModelArtifact::from_slice(value.to_string().as_bytes()).expect("an hour is the bound");
    for theta in [0.0, 1.0, -0.2, 7.0] {
        value["operating_point"]["theta"] = json!(theta);
        refused(&value, "operating_point.theta", "strictly between 0 and 1");
    }
}

#[test]
fn shapes_configurations_and_types_are_refused_by_path() {
    let mut value = base(DEFAULT_MODEL);
    value["model"]["params"]["w_instant"]["shape"] = json!([32, 2]);
    let data = value["model"]["params"]["w_instant"]["data"]
        .as_array_mut()
        .expect("array");
    data.truncate(64);
    refused(
        &value,
        "model.params.w_instant.shape",
        "expected [32, 3], got [32, 2]",
    );

    let mut value = base(DEFAULT_MODEL);
    value["model"]["config"]["tau_min"] = json!(0.0);
    refused(&value, "model.config.tau_min", "tau_min");
    let mut value = base(DEFAULT_MODEL);
    value["model"]["config"]["tau_max"] = json!(1e300);
    refused(&value, "model.config.tau_max", "1.000e300");

    let mut value = base(DEFAULT_MODEL);
    value["model"]["config"]["d_h"] = json!("64");
    refused(&value, "model.config.d_h", "invalid type: string");

    let mut value = base(DEFAULT_MODEL);
    value["evidence"]
        .as_object_mut()
        .expect("object")
        .remove("mu_e");
    refused(&value, "evidence.mu_e", "is required");

    let mut value = base(DEFAULT_MODEL);
    value["model"]["params"]["w_bogus"] = json!({"shape": [1], "data": [0.0]});
    refused(&value, "model.params.w_bogus", "not a known field");
}

#[test]
fn a_long_string_where_a_number_belongs_is_quoted_only_in_part() {
    let mut value = base(DEFAULT_MODEL);
    value["evidence"]["mu_e"] = json!("7".repeat(5_000));
    let error = refused(&value, "evidence.mu_e", "(5000 chars)");
    assert!(error.to_string().len() < 300, "{error}");
    assert!(error.to_string().contains("expected"), "{error}");
}

#[test]
fn a_wrongly_typed_schema_version_is_named_as_such() {
    let mut value = base(DEFAULT_MODEL);
    value["schema_version"] = json!("2");
    let error = refused(&value, "schema_version", "expected an unsigned integer");
    assert!(error.to_string().contains("got a string"), "{error}");
    value["schema_version"] = json!(-1);
    refused(&value, "schema_version", "got -1");
    value
        .as_object_mut()
        .expect("object")
        .remove("schema_version");
    let error = ModelArtifact::from_slice(value.to_string().as_bytes()).expect_err("missing");
    assert!(
        matches!(error, ArtifactError::MissingSchemaVersion),
        "{error}"
    );
}

#[test]
fn oversized_provenance_text_is_refused() {
    let mut value = base(DEFAULT_MODEL);
    value["provenance"]["notes"] = json!("n".repeat(50 << 20));
    refused(
        &value,
        "provenance.notes",
        "at most 4096 bytes, got 52428800",
    );

    let mut value = base(DEFAULT_MODEL);
    value["provenance"]["training_data"][0] = json!("é".repeat(3000));
    refused(&value, "provenance.training_data[0]", "got 6000");
    value["provenance"]["training_data"] = json!(vec!["d"; 257]);
    refused(&value, "provenance.training_data", "at most 256 entries");
    let mut value = base(DEFAULT_MODEL);
    value["provenance"]["created_by"] = json!("x".repeat(4097));
    refused(&value, "provenance.created_by", "4097");
}

#[test]
fn a_nan_smuggled_as_a_huge_exponent_is_refused_where_it_sits() {
    let text = base(DEFAULT_MODEL).to_string();
    let mu_e = text.find("\"mu_e\":").expect("mu_e") + "\"mu_e\":".len();
    let end = mu_e + text[mu_e..].find(',').expect("a following field");
    let poisoned = format!("{}1e999{}", &text[..mu_e], &text[end..]);
    let error = ModelArtifact::from_slice(poisoned.as_bytes()).expect_err("out of range");
    assert!(matches!(error, ArtifactError::Json { .. }), "{error}");
    assert_eq!(error.field().as_deref(), Some("evidence.mu_e"), "{error}");
    assert!(error.to_string().contains("number out of range"), "{error}");
    // A truncated artifact is a syntax error with its line and column.
    let error = ModelArtifact::from_slice(&DEFAULT_MODEL[..1000]).expect_err("truncated");
    assert!(error.to_string().contains("line"), "{error}");
}

/// One way to damage an artifact's JSON.
#[derive(Clone, Debug)]
enum Mutation {
    /// Replace the leaf `index` (among every leaf, tensors or not) by `Value`.
    Replace {
        tensor: bool,
        index: usize,
        with: Value,
    },
    /// Remove the leaf `index` from its object (or array).
    Drop { tensor: bool, index: usize },
    /// Keep only this fraction of the text.
    Truncate { fraction: f64 },
}

fn replacement() -> impl Strategy<Value = Value> {
    prop_oneof![
        prop::sample::select(vec![
            1e308,
            -1e308,
            1e30,
            -1e30,
            1e6 + 1.0,
            -1.0,
            0.0,
            -0.0,
            1.0,
            5e-324,
            f64::from(u32::MAX),
            18_446_744_073_709_551_615.0,
        ])
        .prop_map(|x| json!(x)),
        any::<f64>()
            .prop_filter("JSON numbers are finite", |x| x.is_finite())
            .prop_map(|x| json!(x)),
        any::<i64>().prop_map(|x| json!(x)),
        Just(json!(u64::MAX)),
        Just(json!("NaN")),
        Just(json!("1e999")),
        Just(Value::Null),
        Just(json!(true)),
        Just(json!([])),
        Just(json!({})),
        Just(json!([1.0, 2.0])),
    ]
}

fn mutation() -> impl Strategy<Value = Mutation> {
    prop_oneof![
        6 => (any::<bool>(), any::<usize>(), replacement())
            .prop_map(|(tensor, index, with)| Mutation::Replace { tensor, index, with }),
        2 => (any::<bool>(), any::<usize>()).prop_map(|(tensor, index)| Mutation::Drop { tensor, index }),
        1 => (0.0..1.0f64).prop_map(|fraction| Mutation::Truncate { fraction }),
    ]
}

/// JSON pointers of every leaf, split into tensor values and the rest (so both get picked often).
fn leaves(value: &Value, pointer: String, tensors: &mut Vec<String>, others: &mut Vec<String>) {
    match value {
        Value::Object(map) => {
            for (key, child) in map {
                leaves(child, format!("{pointer}/{key}"), tensors, others);
            }
        }
        Value::Array(items) => {
            for (i, child) in items.iter().enumerate() {
                leaves(child, format!("{pointer}/{i}"), tensors, others);
            }
        }
        _ if pointer.contains("/params/") => tensors.push(pointer),
        _ => others.push(pointer),
    }
}

fn apply(bytes: &[u8], mutation: &Mutation) -> Vec<u8> {
    let mut value = base(bytes);
    let (mut tensors, mut others) = (Vec::new(), Vec::new());
    leaves(&value, String::new(), &mut tensors, &mut others);
    let pick = |tensor: bool, index: usize| {
        let pool = if tensor { &tensors } else { &others };
        pool[index % pool.len()].clone()
    };
    match mutation {
        Mutation::Replace {
            tensor,
            index,
            with,
        } => {
            if let Some(leaf) = value.pointer_mut(&pick(*tensor, *index)) {
                *leaf = with.clone();
            }
        }
        Mutation::Drop { tensor, index } => {
            let pointer = pick(*tensor, *index);
            let (parent, key) = pointer.rsplit_once('/').expect("a leaf has a parent");
            match value.pointer_mut(parent) {
                Some(Value::Object(map)) => {
                    map.remove(key);
                }
                Some(Value::Array(items)) => {
                    let i: usize = key.parse().expect("an array index");
                    items.remove(i);
                }
                _ => {}
            }
        }
        Mutation::Truncate { fraction } => {
            let text = value.to_string();
            let end = (text.len() as f64 * fraction) as usize;
            return text.as_bytes()[..end].to_vec();
        }
    }
    value.to_string().into_bytes()
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(128))]

    #[test]
    fn mutated_artifacts_are_refused_by_field_or_serve_sane_probabilities(
        paper in any::<bool>(),
        mutation in mutation(),
    ) {
        let bytes = apply(if paper { PAPER_MODEL } else { DEFAULT_MODEL }, &mutation);
        match ModelArtifact::from_slice(&bytes) {
            Ok(artifact) => {
                let probabilities = canary_probabilities(artifact);
                prop_assert!(
                    probabilities.iter().all(|p| (0.0..=1.0).contains(p)),
                    "accepted after {:?}", mutation
                );
            }
            // Only a syntax error may lack a field (truncation); it then gives line and column.
            Err(error @ ArtifactError::Json { .. }) => {
                prop_assert!(error.to_string().contains("line"), "{}", error);
            }
            Err(error) => {
                let field = error.field().unwrap_or_default();
                prop_assert!(!field.is_empty() && field != ".", "{} after {:?}", error, mutation);
            }
        }
    }
}
