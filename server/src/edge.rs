//! Request decoding shared by the gRPC service impls (the edge): resource names and paging fields
//! turned into validated domain values, with field-level INVALID_ARGUMENT errors. Owns no logic and
//! touches no storage.

use spoofwatch_proto::wire::limits::MAX_DISPLAY_NAME_CHARS;
use spoofwatch_proto::wire::{DatasetName, ModelName, NameError, OperationName};
use tonic::Status;

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
