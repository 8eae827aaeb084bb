//! Models, the one home of "model" in the server: the registry logic ([`registry`]) and its gRPC
//! edge, the ModelService ([`service`]). Storage stays in `store`; conversions of core types stay in
//! `spoofwatch_proto::wire`.

mod cache;
pub mod registry;
pub mod service;

pub use registry::{LoadedModel, Registry, RegistryError};
pub use service::ModelApi;
