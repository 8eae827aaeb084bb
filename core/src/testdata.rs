//! Test support: where the shared AV-GPS data and the reference fixtures are.
//!
//! Tests that need them call [`data_file`]. When the environment variable is unset they are skipped
//! (a line on stderr says so); when it is set, a missing file fails the test. A relative directory is
//! resolved against the workspace root, because cargo runs tests with the crate directory as cwd.
//!
//! Compiled only with the `test-support` feature (tests' dev-dependencies); must not be used by
//! production code.

use std::path::PathBuf;

/// Directory of `AV-GPS-Dataset-{2,3}.csv`.
pub const AVGPS_DIR_VAR: &str = "SPOOFWATCH_AVGPS_DIR";
/// Directory of the reference-evidence fixtures.
pub const REFERENCE_DIR_VAR: &str = "SPOOFWATCH_REFERENCE_DIR";

/// The directory named by `var`, resolved against the workspace root; `None` (after printing a
/// "skipped" line) when the variable is unset or empty.
pub fn data_dir(var: &str) -> Option<PathBuf> {
    let value = std::env::var_os(var).filter(|v| !v.is_empty());
    let Some(value) = value else {
        eprintln!("skipped: set {var} to run this test (see README \"Data\")");
        return None;
    };
    let path = PathBuf::from(value);
    Some(if path.is_absolute() {
        path
    } else {
        PathBuf::from(env!("CARGO_MANIFEST_DIR"))
            .join("..")
            .join(path)
    })
}

/// `name` inside the directory of `var`; `None` when the variable is unset (test skipped).
///
/// # Panics
/// When the variable is set but the file does not exist: a configured test must not pass silently.
pub fn data_file(var: &str, name: &str) -> Option<PathBuf> {
    let path = data_dir(var)?.join(name);
    assert!(
        path.is_file(),
        "{var} is set but {} does not exist",
        path.display()
    );
    Some(path)
}

/// `count` synthetic ξ rows for model tests and benchmarks: every scaled channel of `schema` (the
/// paper's first 8, then v2's drift channels) `scale` × N(0, 1) from `rng`, ν = 1.
pub fn random_features(
    rng: &mut crate::rng::Rng,
    count: usize,
    scale: f64,
    schema: crate::evidence::FeatureSchema,
) -> Vec<crate::evidence::Features> {
    use crate::evidence::{FEATURE_CAPACITY, NU_INDEX};
    (0..count)
        .map(|_| {
            let mut x = [0.0; FEATURE_CAPACITY];
            for (index, value) in x[..schema.feature_count()].iter_mut().enumerate() {
                *value = if index == NU_INDEX {
                    1.0
                } else {
                    scale * rng.normal()
                };
            }
            x
        })
        .collect()
}
