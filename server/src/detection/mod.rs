//! Detection: per-vehicle in-memory sessions ([`sessions`], the logic), request validation declared
//! once ([`validate`]) and the DetectionService RPCs ([`service`], the edge). Models come from
//! `models`; alarm persistence goes through `store`.

mod handoff;
mod service;
mod sessions;
mod validate;

pub use service::DetectionApi;
pub use sessions::{SessionError, SessionLimits, SessionManager, SnapshotPolicy};
pub use validate::vehicle_id_violation;
