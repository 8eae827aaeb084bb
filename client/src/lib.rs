//! Spoofwatch client library: a typed gRPC connection to the Spoofwatch service, one client-side
//! `StreamDetect` call ([`DetectStream`]), replay of recorded telemetry over it, an in-process
//! server for demos and benchmarks (feature `inprocess`), and the small helpers the `spoofwatch`
//! CLI shares between its offline and remote commands.
//!
//! The `spoofwatch` binary (`main.rs`) adds the clap command line on top; nothing here depends on
//! it. Only `inprocess` depends on the server crate.

pub mod connection;
pub mod detect_stream;
pub mod error;
#[cfg(feature = "inprocess")]
pub mod inprocess;
pub mod input;
pub mod progress;
pub mod replay;
pub mod report;
pub mod synthetic;

pub use connection::{AuthenticatedChannel, BearerAuth, Connection};
pub use detect_stream::DetectStream;
pub use error::{ClientError, RpcError};
pub use replay::replay_timestamps;
