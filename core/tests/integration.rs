//! Core's integration tests, one module per subject, linked into one test binary (one link
//! instead of one per file).

mod artifact_validation;
mod avgps_data;
mod bundled_default;
mod clean_sensor_drifts;
mod detector;
mod ekf_comparator;
mod evidence_parity;
mod fleet_scene;
mod golden_bits;
mod poisoned_samples;
mod receiver_flags;
mod scenario;
mod shared_scratch;
