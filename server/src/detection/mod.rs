//! Detection: per-vehicle in-memory sessions ([`sessions`]: attach, detach, process) over the
//! session table ([`table`]: slots, quotas, eviction), their snapshots and alarm events through the
//! keeper ([`persistence`]), one error ([`error`]), with the pure decisions they
//! carry out kept apart: alarm episodes ([`episodes`]) and where a new stream's session continues
//! from ([`resume`]) and the coalesced reads of stored snapshots ([`snapshot_reads`]); what a session knows ([`state`]) and its snapshot ([`handoff`]); which batch
//! sequence numbers it applied ([`sequence`]); batch validation declared once
//! ([`validate`]) and the DetectionService RPCs ([`service`], the edge). Models come from `models`;
//! alarm persistence goes through `store`.

mod episodes;
mod error;
mod handoff;
mod persistence;
mod resume;
mod sequence;
mod service;
mod sessions;
mod snapshot_reads;
mod state;
mod table;
mod validate;

pub use error::SessionError;
pub use persistence::{SnapshotPolicy, StoredReset};
pub use service::DetectionApi;
pub use sessions::{Beside, SessionManager};
pub use table::SessionLimits;
