//! Models, the one home of "model" in the server: the registry logic ([`registry`]), the wire
//! form of stored models ([`wire`]) and the ModelService edge ([`service`]; a deleted model's
//! sessions are ended through the [`service::ModelDeletion`] that detection provides). Storage
//! stays in `store`; conversions of core types stay in `spoofwatch_proto::wire`.

mod cache;
pub mod registry;
pub mod service;
pub mod wire;

pub use registry::{ACTIVE_MODEL_POLL, LoadedModel, Registry, RegistryError};
