//! Routing metadata shared by the server and the clients. A load balancer in front of several
//! replicas hashes on [`VEHICLE_ID_HEADER`] so that every call of one vehicle lands on the replica
//! that holds its session; the server checks that the header, when sent, names the vehicle the
//! message does (a mismatch would pin the vehicle to the wrong replica).

/// The gRPC metadata key (an HTTP/2 header) of per-vehicle calls: `x-vehicle-id: <vehicle id>`.
pub const VEHICLE_ID_HEADER: &str = "x-vehicle-id";
