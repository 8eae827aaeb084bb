//! Training (labelled data or a fleet fit) and evaluation jobs as long-running operations. The
//! path of a job is linear:
//! [`service`] (the edge: validate, default, convert) → [`manager`] (admission, queue, cancel) →
//! [`runner`] (the use case on blocking threads, progress and end persisted) → `store`.
//! [`records`] holds the JSON shapes persisted along the way.

mod manager;
mod records;
mod runner;
mod service;

pub use manager::{JobError, JobManager, JobSettings};
pub use runner::{JobFailure, Runner};
pub use service::{Jobs, OperationsApi, TrainingApi};
