//! The ModelService RPCs: the edge between the wire and the [`Registry`]. Decodes and validates
//! requests, calls the registry and maps its errors once (through `crate::error`); it must not hold
//! registry logic or touch the store directly.

use std::pin::Pin;
use std::sync::Arc;

use spoofwatch_core::model::artifact::{Provenance, bounded_provenance_text};
use spoofwatch_proto::v1;
use spoofwatch_proto::v1::model_service_server::ModelService;
use spoofwatch_proto::wire::ModelName;
use spoofwatch_proto::wire::convert::{
    metrics_to_proto, operating_point_to_proto, timestamp_from_ms,
};
use spoofwatch_proto::wire::limits::{EXPORT_CHUNK_BYTES, MAX_ARTIFACT_BYTES};
use tokio_stream::Stream;
use tonic::{Request, Response, Status, Streaming};

use super::registry::{ModelMetadata, Registry};
use crate::detection::SessionManager;
use crate::edge::{display_name, model_name, page_request};
use crate::idle::StreamIdle;
use crate::status::invalid_field;
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

/// The ModelService implementation.
#[derive(Debug, Clone)]
pub struct ModelApi {
    pub registry: Arc<Registry>,
    /// Deleting a model ends the sessions that use it.
    pub sessions: Arc<SessionManager>,
    /// How long an import may send nothing.
    pub stream_idle: StreamIdle,
}

type ChunkStream = Pin<Box<dyn Stream<Item = Result<v1::ModelChunk, Status>> + Send>>;

#[tonic::async_trait]
impl ModelService for ModelApi {
    async fn list_models(
        &self,
        request: Request<v1::ListModelsRequest>,
    ) -> Result<Response<v1::ListModelsResponse>, Status> {
        let r = request.into_inner();
        let page = self
            .registry
            .list(&page_request(r.page_size, &r.page_token)?)
            .await?;
        Ok(Response::new(v1::ListModelsResponse {
            models: page.items.iter().map(model_summary_to_proto).collect(),
            next_page_token: page.next_page_token.unwrap_or_default(),
        }))
    }

    async fn get_model(
        &self,
        request: Request<v1::GetModelRequest>,
    ) -> Result<Response<v1::Model>, Status> {
        let name = model_name("name", &request.into_inner().name)?;
        Ok(Response::new(model_to_proto(
            &self.registry.get(&name).await?,
        )))
    }

    async fn set_active_model(
        &self,
        request: Request<v1::SetActiveModelRequest>,
    ) -> Result<Response<v1::Model>, Status> {
        let name = model_name("name", &request.into_inner().name)?;
        Ok(Response::new(model_to_proto(
            &self.registry.activate(&name).await?,
        )))
    }

    async fn delete_model(
        &self,
        request: Request<v1::DeleteModelRequest>,
    ) -> Result<Response<()>, Status> {
        let name = model_name("name", &request.into_inner().name)?;
        self.sessions.delete_model(&name).await?;
        Ok(Response::new(()))
    }

    type ExportModelStream = ChunkStream;

    async fn export_model(
        &self,
        request: Request<v1::ExportModelRequest>,
    ) -> Result<Response<Self::ExportModelStream>, Status> {
        let name = model_name("name", &request.into_inner().name)?;
        let bytes = self.registry.artifact_bytes(&name).await?;
        let chunks: Vec<Result<v1::ModelChunk, Status>> = bytes
            .chunks(EXPORT_CHUNK_BYTES)
            .map(|c| Ok(v1::ModelChunk { data: c.to_vec() }))
            .collect();
        Ok(Response::new(Box::pin(tokio_stream::iter(chunks))))
    }

    async fn import_model(
        &self,
        request: Request<Streaming<v1::ImportModelRequest>>,
    ) -> Result<Response<v1::Model>, Status> {
        use v1::import_model_request::Kind;
        let mut stream = request.into_inner();
        let header = match self.stream_idle.next(&mut stream).await? {
            Some(v1::ImportModelRequest {
                kind: Some(Kind::Header(h)),
            }) => h,
            _ => return Err(crate::status::header_first()),
        };
        let mut bytes = Vec::new();
        while let Some(message) = self.stream_idle.next(&mut stream).await? {
            match message.kind {
                Some(Kind::Chunk(chunk)) => {
                    // Refused before the chunk is buffered: memory per import stays bounded.
                    if bytes.len() + chunk.len() > MAX_ARTIFACT_BYTES {
                        return Err(invalid_field(
                            "artifact",
                            format!(
                                "must be at most {} MiB; the upload went past it",
                                MAX_ARTIFACT_BYTES >> 20
                            ),
                        ));
                    }
                    bytes.extend_from_slice(&chunk);
                }
                _ => return Err(crate::status::header_not_first()),
            }
        }
        let name = display_name("header.display_name", &header.display_name)?;
        let row = self.registry.import(&bytes, name, header.activate).await?;
        Ok(Response::new(model_to_proto(&row)))
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
