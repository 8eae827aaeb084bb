//! Spoofwatch client library: a typed gRPC connection to the Spoofwatch service, replay of recorded
//! telemetry over `StreamDetect`, an in-process server for demos and benchmarks, and the small
//! helpers the `spoofwatch` CLI shares between its offline and remote commands.
//!
//! The `spoofwatch` binary (`main.rs`) adds the clap command line on top; nothing here depends on it.

pub mod connection;
pub mod error;
pub mod inprocess;
pub mod input;
pub mod progress;
pub mod replay;
pub mod report;
pub mod synthetic;

pub use connection::{AuthenticatedChannel, BearerAuth, Connection};
pub use error::{ClientError, RpcError};
pub use replay::replay_timestamps;
