//! Causal evidence ξ_t (SPEC §4). Owner: data/evidence work.

/// Number of model input features in ξ_t.
pub const FEATURE_COUNT: usize = 9;
/// ξ_t in the locked order of SPEC §4.
pub const FEATURE_NAMES: [&str; FEATURE_COUNT] = [
    "eta_e",
    "eta_n",
    "eta_dot_e",
    "eta_dot_n",
    "eta_ddot_e",
    "eta_ddot_n",
    "q",
    "accum_log",
    "nu",
];
/// One ξ_t vector (scaled, ν last).
pub type Features = [f64; FEATURE_COUNT];
