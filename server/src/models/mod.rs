//! Models, the one home of "model" in the server: the registry logic ([`registry`]) and the wire
//! form of stored models ([`wire`]). Storage stays in `store`; conversions of core types stay in
//! `spoofwatch_proto::wire`. The ModelService edge is `crate::model_service`: it also ends the
//! sessions of a deleted model, so it sits above detection.

mod cache;
pub mod registry;
pub mod wire;

pub use registry::{ACTIVE_MODEL_POLL, LoadedModel, Registry, RegistryError};
