//! The wire layer: everything that translates between `spoofwatch.v1` messages and the rest of the
//! code base, in one place.
//!
//! - [`convert`]: core types (samples, decisions, metrics, operating points) to and from messages.
//! - [`fit`]: a fleet fit's report as its message.
//! - [`names`]: resource names (`models/{id}`, `datasets/{id}`, `operations/{id}`) as newtypes.
//! - [`limits`]: the bounds both the server's validation and well-behaved clients respect.
//! - [`routing`]: the `x-vehicle-id` metadata a load balancer hashes on.
//! - [`vehicle`]: the vehicle-id rule as the [`VehicleId`] newtype.
//!
//! It owns no behaviour of its own: no I/O, no validation policy beyond the shared limits and the
//! name and vehicle-id rules, and it must not depend on the server or the client (both depend on it).

pub mod convert;
pub mod fit;
pub mod limits;
pub mod names;
pub mod routing;
pub mod vehicle;

pub use names::{DatasetName, ModelName, NameError, OperationName};
pub use vehicle::{VehicleId, VehicleIdError, is_vehicle_id_char};
