//! Examples for integrators, in the style of tonic's: each is one short module over the generated
//! API (`spoofwatch_proto::v1`) and tonic alone, with a binary that runs it.
//!
//! - [`fleet_backend`]: streams one vehicle's samples and prints each detection.
//! - [`alarm_watcher`]: follows the fleet's alarm events from a cursor.
//!
//! They own nothing of the service: what they show is the wire API as a client sees it.

pub mod alarm_watcher;
pub mod fleet_backend;

/// The error of an example: whatever went wrong, as text.
pub type Error = Box<dyn std::error::Error + Send + Sync>;
