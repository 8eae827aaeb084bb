//! Request decoding shared by the gRPC service impls (the edge): resource names, vehicle ids, paging
//! fields and the `x-vehicle-id` routing header turned into validated domain values, with
//! field-level INVALID_ARGUMENT errors. Owns no logic and touches no storage.

use spoofwatch_proto::wire::limits::MAX_DISPLAY_NAME_CHARS;
use spoofwatch_proto::wire::routing::VEHICLE_ID_HEADER;
use spoofwatch_proto::wire::{DatasetName, ModelName, NameError, OperationName, VehicleId};
use tonic::Status;
use tonic::metadata::MetadataMap;

use crate::status::invalid_field;
use crate::store::PageRequest;

/// A required `models/{id}` field.
pub fn model_name(field: &str, name: &str) -> Result<ModelName, Status> {
    ModelName::parse(name).map_err(|e| name_error(field, e))
}

/// An optional `models/{id}` field: empty means "the active model".
pub fn optional_model_name(field: &str, name: &str) -> Result<Option<ModelName>, Status> {
    if name.is_empty() {
        return Ok(None);
    }
    model_name(field, name).map(Some)
}

/// A required vehicle id field (see [`VehicleId::parse`]).
pub fn vehicle_id(field: &str, id: &str) -> Result<VehicleId, Status> {
    VehicleId::parse(id).map_err(|e| invalid_field(field, e.to_string()))
}

/// An optional vehicle id field: empty means none (a stateless call, or every vehicle).
pub fn optional_vehicle_id(field: &str, id: &str) -> Result<Option<VehicleId>, Status> {
    if id.is_empty() {
        return Ok(None);
    }
    vehicle_id(field, id).map(Some)
}

/// A free-text display name (may be empty), at most [`MAX_DISPLAY_NAME_CHARS`] characters: it is
/// stored, listed and echoed, so its length is bounded before anything else looks at it.
pub fn display_name<'a>(field: &str, name: &'a str) -> Result<&'a str, Status> {
    let chars = name.chars().count();
    if chars > MAX_DISPLAY_NAME_CHARS {
        return Err(invalid_field(
            field,
            format!("at most {MAX_DISPLAY_NAME_CHARS} characters, got {chars}"),
        ));
    }
    Ok(name)
}

/// A required `datasets/{id}` field.
pub fn dataset_name(field: &str, name: &str) -> Result<DatasetName, Status> {
    DatasetName::parse(name).map_err(|e| name_error(field, e))
}

/// A repeated `datasets/{id}` field (each entry named `field[i]` in errors).
pub fn dataset_names(field: &str, names: &[String]) -> Result<Vec<DatasetName>, Status> {
    names
        .iter()
        .enumerate()
        .map(|(i, name)| dataset_name(&format!("{field}[{i}]"), name))
        .collect()
}

/// A required `operations/{id}` field.
pub fn operation_name(field: &str, name: &str) -> Result<OperationName, Status> {
    OperationName::parse(name).map_err(|e| name_error(field, e))
}

fn name_error(field: &str, error: NameError) -> Status {
    invalid_field(field, error.to_string())
}

/// A List* request's paging fields as a store page request.
pub fn page_request(size: i32, token: &str) -> Result<PageRequest, Status> {
    let page_size =
        u32::try_from(size).map_err(|_| invalid_field("page_size", "must not be negative"))?;
    Ok(PageRequest {
        page_size,
        page_token: (!token.is_empty()).then(|| token.to_string()),
    })
}

/// The vehicle a per-vehicle call was routed by: its `x-vehicle-id` header values (usually one; none
/// when the client talks to one server directly). A value that is not printable ASCII is refused.
pub fn routed_vehicle_ids(metadata: &MetadataMap) -> Result<Vec<String>, Status> {
    metadata
        .get_all(VEHICLE_ID_HEADER)
        .iter()
        .map(|value| {
            value.to_str().map(str::to_string).map_err(|_| {
                invalid_field(
                    format!("{VEHICLE_ID_HEADER} header"),
                    "must be printable ASCII (the vehicle id)",
                )
            })
        })
        .collect()
}

/// Checks that the `x-vehicle-id` header values (see [`routed_vehicle_ids`]) name `vehicle_id`, the
/// message's `field`. A balancer hashes on the header: a different id would pin this vehicle's
/// session to another vehicle's replica, where its next stream would not find it.
pub fn check_routed_vehicle(
    routed: &[String],
    field: &str,
    vehicle_id: &str,
) -> Result<(), Status> {
    match routed.iter().find(|routed| routed.as_str() != vehicle_id) {
        None => Ok(()),
        Some(routed) => Err(invalid_field(
            field,
            format!(
                "{vehicle_id:?} differs from the {VEHICLE_ID_HEADER} header {routed:?} the call was \
                 routed by; send the same vehicle id in both"
            ),
        )),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn metadata(values: &[&str]) -> MetadataMap {
        let mut metadata = MetadataMap::new();
        for value in values {
            metadata.append(
                VEHICLE_ID_HEADER,
                value.parse().expect("an ASCII metadata value"),
            );
        }
        metadata
    }

    #[test]
    fn an_absent_or_matching_header_passes() {
        let none = routed_vehicle_ids(&metadata(&[])).expect("no header");
        assert!(none.is_empty());
        check_routed_vehicle(&none, "start.vehicle_id", "car-1").expect("absent is fine");
        let same = routed_vehicle_ids(&metadata(&["car-1"])).expect("one header");
        check_routed_vehicle(&same, "start.vehicle_id", "car-1").expect("the same vehicle");
    }

    #[test]
    fn a_header_naming_another_vehicle_is_refused_naming_the_field_and_the_header() {
        let routed = routed_vehicle_ids(&metadata(&["car-1", "car-2"])).expect("two headers");
        let status = check_routed_vehicle(&routed, "start.vehicle_id", "car-1")
            .expect_err("one header names another vehicle");
        assert_eq!(status.code(), tonic::Code::InvalidArgument);
        assert!(
            status.message().starts_with(
                "start.vehicle_id: \"car-1\" differs from the x-vehicle-id header \"car-2\""
            ),
            "{}",
            status.message()
        );
    }
}
