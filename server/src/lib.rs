//! Spoofwatch gRPC service over `spoofwatch-core`. For now: the SQLite storage layer.

pub mod store;
