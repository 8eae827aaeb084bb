//! Detection: per-vehicle in-memory sessions and the DetectionService RPCs.

mod service;
mod sessions;
mod validate;

pub use service::DetectionApi;
pub use sessions::{SessionLimits, SessionManager};
