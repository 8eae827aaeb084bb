//! Spoofwatch core: the pure, synchronous heart of the HO-LLN GNSS-spoofing detector.
//!
//! Everything here is streaming-first: per-vehicle builders are fed one sample at a time, and whole
//! recorded trajectories go through the very same code. No async, no I/O beyond readers handed in.
//! `../shared/docs/SPEC.md` (in the repository's sibling `shared/`) is the specification.

pub mod alarm;
pub mod artifact;
pub mod comparator;
pub mod cusum;
pub mod data;
pub mod detector;
pub mod evaluation;
pub mod evidence;
pub mod geo;
pub mod metrics;
pub mod model;
pub mod pipeline;
pub mod rng;
pub mod sample;
pub mod scenario;
pub mod testdata;
pub mod train;
