//! Spoofwatch client library: a typed gRPC connection to the Spoofwatch service (TLS, token, gzip),
//! retries of unary calls ([`retry`]), one client-side
//! `StreamDetect` call ([`DetectStream`], routed by the `x-vehicle-id` header of [`routing`]) and
//! one gateway `StreamDetectFleet` call
//! ([`FleetDetectStream`]), a resumable alarm feed ([`AlarmWatch`]), replay of recorded telemetry over it
//! (failing over to a new stream when a server goes away: [`failover`]; its final rows: [`replay_log`])
//! and its fleet summary ([`fleet`]), the small helpers the commands share (input, progress bars,
//! metrics tables), and the commands themselves ([`cli`]).
//!
//! The `spoofwatch` binary (`main.rs`) only runs [`cli`]; the research binary (`spoofwatch-lab`)
//! reuses [`cli`] and adds its own commands. Nothing here depends on the server crate, the learned
//! baselines or a plotting library: the operator's binary links none of them.

pub mod alarm_watch;
pub mod cli;
pub mod connection;
pub mod detect_stream;
pub mod error;
pub mod failover;
pub mod fleet;
pub mod fleet_stream;
pub mod input;
pub mod progress;
pub mod reconnects;
pub mod replay;
pub mod replay_log;
pub mod report;
pub mod retry;
pub mod routing;
pub mod synthetic;
pub mod timeline;

pub use alarm_watch::{AlarmWatch, IncidentWatch, ResumableWatch, WatchOptions};
pub use connection::{AuthenticatedChannel, BearerAuth, ConnectOptions, Connection};
pub use detect_stream::DetectStream;
pub use error::{ClientError, RpcError};
pub use fleet_stream::FleetDetectStream;
pub use replay::replay_timestamps;
