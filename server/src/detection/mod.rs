//! Detection: per-vehicle in-memory sessions ([`sessions`], the logic), with the pure decisions it
//! carries out kept apart: alarm episodes ([`episodes`]) and where a new stream's session continues
//! from ([`resume`]) and the coalesced reads of stored snapshots ([`snapshot_reads`]); what a session knows ([`state`]) and its snapshot ([`handoff`]); which batch
//! sequence numbers it applied ([`sequence`]); batch validation declared once
//! ([`validate`]) and the DetectionService RPCs ([`service`], the edge). Models come from `models`;
//! alarm persistence goes through `store`.

mod episodes;
mod handoff;
mod resume;
mod sequence;
mod service;
mod sessions;
mod snapshot_reads;
mod state;
mod validate;

pub use service::DetectionApi;
pub use sessions::{SessionError, SessionLimits, SessionManager, SnapshotPolicy};
