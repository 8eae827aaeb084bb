//! The wire form of stored models (`v1::Model`), shared by the ModelService and the jobs that
//! return a trained model. It converts only; it must not call the registry or the store.

use spoofwatch_core::model::artifact::{Provenance, bounded_provenance_text};
use spoofwatch_proto::v1;
use spoofwatch_proto::wire::ModelName;
use spoofwatch_proto::wire::convert::{
    critical_test_to_proto, metrics_to_proto, operating_point_to_proto, timestamp_from_ms,
};

use super::registry::ModelMetadata;
use crate::store::{ModelRow, ModelSource};

/// The wire form of a stored model, as GetModel returns it. The provenance text is cut to the
/// artifact bounds (`MAX_TRAINING_DATA_ENTRIES` × `MAX_PROVENANCE_TEXT_BYTES`, and that for the
/// notes) even for a row stored before they existed, so one model always fits a default message.
pub fn model_to_proto(row: &ModelRow) -> v1::Model {
    let source = match row.source {
        ModelSource::Bundled => "bundled",
        ModelSource::Training => "training",
        ModelSource::Import => "import",
    };
    let mut model = v1::Model {
        name: ModelName::from_id(row.id.as_str()).to_string(),
        display_name: row.display_name.clone(),
        active: row.active,
        create_time: Some(timestamp_from_ms(row.created_at_ms)),
        source: source.to_string(),
        training_operation: row.training_operation.clone().unwrap_or_default(),
        schema_version: row.schema_version as u32,
        size_bytes: row.size_bytes as u64,
        sha256: row.sha256.clone(),
        ..v1::Model::default()
    };
    if let Some(m) = ModelMetadata::of_row(row) {
        model.operating_point = Some(operating_point_to_proto(m.operating_point));
        model.validation_metrics = m.validation_metrics.as_ref().map(metrics_to_proto);
        model.architecture = m.architecture;
        model.parameter_count = m.parameter_count;
        model.seed = m.seed;
        model.training_data = Provenance::bounded_training_data(m.training_data);
        model.train_wall_time_s = m.train_wall_time_s;
        model.epochs_run = m.epochs_run;
        model.notes = bounded_provenance_text(m.notes);
        model.critical = m.critical.as_ref().map(critical_test_to_proto);
    }
    model
}

/// The wire form of a stored model in a ListModels page: without the provenance free text, so that
/// a page of `MAX_PAGE_SIZE` models stays far below the default 4 MiB message limit.
pub fn model_summary_to_proto(row: &ModelRow) -> v1::Model {
    v1::Model {
        training_data: Vec::new(),
        notes: String::new(),
        ..model_to_proto(row)
    }
}

#[cfg(test)]
mod tests {
    use prost::Message;
    use spoofwatch_core::alarm::OperatingPoint;
    use spoofwatch_core::model::artifact::{MAX_PROVENANCE_TEXT_BYTES, MAX_TRAINING_DATA_ENTRIES};
    use spoofwatch_proto::wire::limits::{
        MAX_DISPLAY_NAME_CHARS, MAX_MESSAGE_BYTES, MAX_PAGE_SIZE, MAX_RESOURCE_ID_LEN,
    };

    use super::*;
    use crate::models::registry::BUNDLED_MODEL;

    /// A stored model with every field at its largest: ids and names at their bounds in 4-byte
    /// characters where free text is allowed, and provenance text far beyond the artifact bounds (as
    /// a row stored before them could hold).
    fn worst_case_row() -> ModelRow {
        let artifact = spoofwatch_core::model::artifact::ModelArtifact::from_slice(BUNDLED_MODEL)
            .expect("the bundled model");
        let mut metadata = ModelMetadata::of(&artifact);
        metadata.operating_point = OperatingPoint {
            theta: 0.123_456_789,
            n_p: u32::MAX,
        };
        metadata.training_data =
            vec!["𝔡".repeat(MAX_PROVENANCE_TEXT_BYTES); 10 * MAX_TRAINING_DATA_ENTRIES];
        metadata.notes = "𝔫".repeat(10 * MAX_PROVENANCE_TEXT_BYTES);
        metadata.architecture = "a".repeat(1024);
        ModelRow {
            id: "i".repeat(MAX_RESOURCE_ID_LEN),
            display_name: "𝔪".repeat(MAX_DISPLAY_NAME_CHARS),
            source: ModelSource::Training,
            training_operation: Some(format!("operations/{}", "o".repeat(MAX_RESOURCE_ID_LEN))),
            created_at_ms: i64::MAX,
            schema_version: i64::from(u32::MAX),
            sha256: "f".repeat(64),
            size_bytes: i64::MAX,
            metadata: serde_json::to_value(metadata).expect("metadata serialises"),
            active: true,
        }
    }

    #[test]
    fn a_full_page_of_the_largest_models_fits_the_default_message_limit() {
        let row = worst_case_row();
        let page = v1::ListModelsResponse {
            models: vec![model_summary_to_proto(&row); MAX_PAGE_SIZE as usize],
            next_page_token: "t".repeat(1024),
        };
        let page_bytes = page.encoded_len();
        // Half the limit (about 2.6 KB a model): room for the gRPC framing and for fields added later.
        assert!(
            page_bytes < MAX_MESSAGE_BYTES / 2,
            "{page_bytes} bytes for {MAX_PAGE_SIZE} models"
        );

        let one = model_to_proto(&row);
        assert_eq!(one.training_data.len(), MAX_TRAINING_DATA_ENTRIES);
        assert!(one.notes.len() <= MAX_PROVENANCE_TEXT_BYTES);
        let one_bytes = one.encoded_len();
        assert!(
            one_bytes < MAX_MESSAGE_BYTES / 2,
            "{one_bytes} bytes for one model"
        );
    }
}
