//! Datasets, the one home of "dataset" in the server: the catalog logic ([`catalog`]: parse, store,
//! import from the operator's data directory, load for jobs) and its gRPC edge, the DatasetService
//! ([`service`]), and the bytes held in pieces ([`content`]). Storage stays in `store`.

pub mod catalog;
pub mod content;
pub mod service;

pub use catalog::{Catalog, DatasetError};
pub use service::DatasetApi;
