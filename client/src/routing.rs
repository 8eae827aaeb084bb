//! The routing header of per-vehicle calls. Every call that belongs to one vehicle (StreamDetect,
//! Detect with a vehicle id, GetSession, ResetSession) carries `x-vehicle-id: <vehicle id>`, so that
//! a load balancer hashing on it sends all of a vehicle's calls to the replica holding its session.
//! A single server without a balancer ignores it, apart from checking that it names the message's
//! vehicle.

use spoofwatch_proto::wire::routing::VEHICLE_ID_HEADER;
use tonic::Request;
use tonic::metadata::AsciiMetadataValue;

/// `message` as a request routed by `vehicle_id`. An empty id (a stateless call) or one that cannot
/// be a header value goes without the header: the server refuses such an id by its field anyway.
pub fn for_vehicle<T>(vehicle_id: &str, message: T) -> Request<T> {
    let mut request = Request::new(message);
    if !vehicle_id.is_empty()
        && let Ok(value) = AsciiMetadataValue::try_from(vehicle_id)
    {
        request.metadata_mut().insert(VEHICLE_ID_HEADER, value);
    }
    request
}

#[cfg(test)]
mod tests {
    use super::*;

    fn header<T>(request: &Request<T>) -> Option<&str> {
        request
            .metadata()
            .get(VEHICLE_ID_HEADER)
            .map(|v| v.to_str().expect("ascii"))
    }

    #[test]
    fn a_vehicle_call_carries_its_vehicle_id_and_a_stateless_one_does_not() {
        assert_eq!(header(&for_vehicle("car-1", ())), Some("car-1"));
        assert_eq!(header(&for_vehicle("", ())), None);
        assert_eq!(header(&for_vehicle("caf\u{e9}\n", ())), None);
    }
}
