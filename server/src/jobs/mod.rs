//! Training and evaluation jobs: persisted in SQLite, run off the async runtime on blocking threads,
//! at most N at a time (the rest queue), observable through watch channels, cooperatively cancellable.

mod runner;
mod service;

pub use runner::{JobManager, JobSettings};
pub use service::{Jobs, OperationsApi, TrainingApi};
