//! Spoofwatch core: the pure, synchronous heart of the HO-LLN GNSS-spoofing detector.
//!
//! Everything here is streaming-first: per-vehicle builders are fed one sample at a time, and whole
//! recorded trajectories go through the very same code. No async, no I/O beyond readers handed in.
//!
//! "SPEC §n" in this crate refers to section n of the detector specification, `docs/detector.md` in
//! this repository.
//!
//! Where things live: samples and their parsing ([`sample`], [`data`]) → evidence ([`evidence`],
//! [`geo`]) → the model and its artifact ([`model`], [`model::artifact`]) → running it on a stream
//! ([`detector`]) → alarms ([`lifecycle`], [`severity`], [`explain`]), area incidents across
//! vehicles ([`incident`]) and operating points ([`alarm`], [`critical_search`]) → scoring and
//! metrics ([`evaluation`], [`metrics`]). Training is one use case ([`train::detector::train_detector`]); the classical
//! comparator is [`cusum`]; labelled attack scenarios are [`scenario`].
//!
//! Layers, from the top down: glr, cusum, gate, fleet_fit, train | canary, evaluation | detector | model |
//! alarm, critical_search, data, explain, testdata | evidence, incident, lifecycle, scenario | geo,
//! metrics, receiver, rng, sample, severity. A module imports only from its own layer's others or from below
//! (`scripts/fence.py` holds CI to it).

pub mod alarm;
pub mod canary;
pub mod critical_search;
pub mod cusum;
pub mod data;
pub mod detector;
pub mod evaluation;
pub mod evidence;
pub mod explain;
pub mod fleet_fit;
pub mod gate;
pub mod geo;
pub mod glr;
pub mod incident;
pub mod lifecycle;
pub mod metrics;
pub mod model;
pub mod receiver;
pub mod rng;
pub mod sample;
pub mod scenario;
pub mod severity;
#[cfg(feature = "test-support")]
pub mod testdata;
pub mod train;
