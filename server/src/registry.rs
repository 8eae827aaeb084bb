//! The model registry: models in SQLite, parsed artifacts cached in memory, the bundled default
//! model registered on first start, and the ModelService RPCs.

use std::collections::HashMap;
use std::pin::Pin;
use std::sync::{Arc, Mutex};

use serde::{Deserialize, Serialize};
use spoofwatch_core::alarm::OperatingPoint;
use spoofwatch_core::metrics::Metrics;
use spoofwatch_core::model::artifact::{ARTIFACT_SCHEMA_VERSION, ModelArtifact};
use spoofwatch_proto::v1;
use spoofwatch_proto::v1::model_service_server::ModelService;
use tokio_stream::Stream;
use tonic::{Request, Response, Status, Streaming};

use crate::convert::{
    metrics_to_proto, operating_point_to_proto, page_request, sha256_hex, strip_collection,
    timestamp_from_ms,
};
use crate::error::{failed_precondition, internal, invalid_field, not_found};
use crate::store::{ModelRow, ModelSource, NewModel, Store};

/// The artifact bundled into the binary: trained by `spoofwatch experiment av-gps` (see README).
pub const BUNDLED_MODEL: &[u8] = include_bytes!("../../models/default.json");
/// Id of the bundled model in the registry.
pub const BUNDLED_MODEL_ID: &str = "default";
/// Largest artifact accepted by ImportModel.
pub const MAX_ARTIFACT_BYTES: usize = 64 << 20;
const EXPORT_CHUNK_BYTES: usize = 1 << 20;

/// What the registry stores beside an artifact (the `metadata_json` column).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ModelMetadata {
    pub operating_point: OperatingPoint,
    pub validation_metrics: Option<Metrics>,
    pub architecture: String,
    pub parameter_count: u64,
    pub seed: u64,
    pub training_data: Vec<String>,
    pub train_wall_time_s: f64,
    pub epochs_run: u32,
    pub notes: String,
}

impl ModelMetadata {
    fn of(artifact: &ModelArtifact) -> Self {
        let config = artifact.model.config();
        let a = &config.ablation;
        let mut ablations = Vec::new();
        if a.no_exchange {
            ablations.push("no-exchange".to_string());
        }
        if a.no_third_order {
            ablations.push("no-third-order".to_string());
        }
        if a.first_order_cell {
            ablations.push("first-order-cell".to_string());
        }
        ablations.push(format!("features={:?}", a.features));
        let p = &artifact.provenance;
        Self {
            operating_point: artifact.operating_point,
            validation_metrics: p.validation_metrics.clone(),
            architecture: format!(
                "d_s={} d_zeta={} d_h={} {}",
                config.d_s,
                config.d_zeta,
                config.d_h,
                ablations.join(" ")
            ),
            parameter_count: artifact.model.parameter_count() as u64,
            seed: p.seed,
            training_data: p.training_data.clone(),
            train_wall_time_s: p.train_wall_time_s,
            epochs_run: p.epochs_run,
            notes: p.notes.clone(),
        }
    }
}

/// A parsed model ready to serve.
#[derive(Clone, Debug)]
pub struct LoadedModel {
    pub id: String,
    pub artifact: Arc<ModelArtifact>,
}

impl LoadedModel {
    /// `models/{id}`.
    pub fn name(&self) -> String {
        format!("models/{}", self.id)
    }
}

/// Models in the store plus a cache of parsed artifacts.
#[derive(Debug)]
pub struct Registry {
    store: Store,
    cache: Mutex<HashMap<String, Arc<ModelArtifact>>>,
}

/// A fresh short random id (48 bits of a v4 UUID, hex).
pub fn new_id() -> String {
    uuid::Uuid::new_v4().simple().to_string()[..12].to_string()
}

impl Registry {
    pub fn new(store: Store) -> Self {
        Self {
            store,
            cache: Mutex::new(HashMap::new()),
        }
    }

    /// On an empty registry, registers and activates the bundled default model.
    pub async fn ensure_default_model(&self) -> Result<(), Status> {
        if self.store.model_count().await? > 0 {
            return Ok(());
        }
        let artifact = ModelArtifact::from_slice(BUNDLED_MODEL)
            .map_err(|e| internal("loading the bundled default model", &e))?;
        self.register(
            BUNDLED_MODEL_ID,
            "bundled default (av-gps experiment)",
            ModelSource::Bundled,
            None,
            &artifact,
        )
        .await?;
        self.store.set_active_model(BUNDLED_MODEL_ID).await?;
        tracing::info!("registered and activated the bundled default model");
        Ok(())
    }

    /// Stores an artifact under `id`.
    pub async fn register(
        &self,
        id: &str,
        display_name: &str,
        source: ModelSource,
        training_operation: Option<String>,
        artifact: &ModelArtifact,
    ) -> Result<ModelRow, Status> {
        let bytes = artifact
            .to_vec()
            .map_err(|e| internal("serialising a model artifact", &e))?;
        let metadata = serde_json::to_value(ModelMetadata::of(artifact))
            .map_err(|e| internal("serialising model metadata", &e))?;
        let row = self
            .store
            .insert_model(NewModel {
                id: id.to_string(),
                display_name: display_name.to_string(),
                source,
                training_operation,
                schema_version: i64::from(ARTIFACT_SCHEMA_VERSION),
                sha256: sha256_hex(&bytes),
                metadata,
                artifact: bytes,
            })
            .await?;
        self.cache_insert(id, Arc::new(artifact.clone()));
        Ok(row)
    }

    fn cache_insert(&self, id: &str, artifact: Arc<ModelArtifact>) {
        if let Ok(mut cache) = self.cache.lock() {
            cache.insert(id.to_string(), artifact);
        }
    }

    fn cached(&self, id: &str) -> Option<Arc<ModelArtifact>> {
        self.cache.lock().ok()?.get(id).cloned()
    }

    /// The model to serve for a request: `models/{id}`, `{id}`, or empty for the active model.
    pub async fn resolve(&self, requested: &str) -> Result<LoadedModel, Status> {
        let id = if requested.is_empty() {
            self.store
                .active_model()
                .await?
                .ok_or_else(|| failed_precondition("NO_ACTIVE_MODEL", "no model is active"))?
                .id
        } else {
            strip_collection("models", requested).to_string()
        };
        if let Some(artifact) = self.cached(&id) {
            return Ok(LoadedModel { id, artifact });
        }
        let bytes = self
            .store
            .model_artifact(&id)
            .await?
            .ok_or_else(|| not_found("model", &format!("models/{id}")))?;
        let artifact = Arc::new(
            ModelArtifact::from_slice(&bytes)
                .map_err(|e| internal("loading a stored model", &e))?,
        );
        self.cache_insert(&id, Arc::clone(&artifact));
        Ok(LoadedModel { id, artifact })
    }

    fn to_proto(row: &ModelRow) -> v1::Model {
        let metadata: Option<ModelMetadata> = serde_json::from_value(row.metadata.clone()).ok();
        let source = match row.source {
            ModelSource::Bundled => "bundled",
            ModelSource::Training => "training",
            ModelSource::Import => "import",
        };
        let mut model = v1::Model {
            name: format!("models/{}", row.id),
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
        if let Some(m) = metadata {
            model.operating_point = Some(operating_point_to_proto(m.operating_point));
            model.validation_metrics = m.validation_metrics.as_ref().map(metrics_to_proto);
            model.architecture = m.architecture;
            model.parameter_count = m.parameter_count;
            model.seed = m.seed;
            model.training_data = m.training_data;
            model.train_wall_time_s = m.train_wall_time_s;
            model.epochs_run = m.epochs_run;
            model.notes = m.notes;
        }
        model
    }

    /// The wire form of a stored model.
    pub async fn get_proto(&self, id: &str) -> Result<v1::Model, Status> {
        let row = self
            .store
            .get_model(id)
            .await?
            .ok_or_else(|| not_found("model", &format!("models/{id}")))?;
        Ok(Self::to_proto(&row))
    }

    /// Makes a model active (it must load).
    pub async fn activate(&self, id: &str) -> Result<v1::Model, Status> {
        self.resolve(id).await?;
        let row = self.store.set_active_model(id).await?;
        tracing::info!(model = id, "activated model");
        Ok(Self::to_proto(&row))
    }
}

/// The ModelService RPCs.
#[derive(Debug, Clone)]
pub struct ModelApi {
    pub registry: Arc<Registry>,
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
            .store
            .list_models(&page_request(r.page_size, &r.page_token)?)
            .await?;
        Ok(Response::new(v1::ListModelsResponse {
            models: page.items.iter().map(Registry::to_proto).collect(),
            next_page_token: page.next_page_token.unwrap_or_default(),
        }))
    }

    async fn get_model(
        &self,
        request: Request<v1::GetModelRequest>,
    ) -> Result<Response<v1::Model>, Status> {
        let name = request.into_inner().name;
        let id = strip_collection("models", &name);
        Ok(Response::new(self.registry.get_proto(id).await?))
    }

    async fn set_active_model(
        &self,
        request: Request<v1::SetActiveModelRequest>,
    ) -> Result<Response<v1::Model>, Status> {
        let name = request.into_inner().name;
        if name.is_empty() {
            return Err(invalid_field("name", "required"));
        }
        let id = strip_collection("models", &name);
        Ok(Response::new(self.registry.activate(id).await?))
    }

    async fn delete_model(
        &self,
        request: Request<v1::DeleteModelRequest>,
    ) -> Result<Response<()>, Status> {
        let name = request.into_inner().name;
        let id = strip_collection("models", &name).to_string();
        self.registry.store.delete_model(&id).await?;
        if let Ok(mut cache) = self.registry.cache.lock() {
            cache.remove(&id);
        }
        tracing::info!(model = %id, "deleted model");
        Ok(Response::new(()))
    }

    type ExportModelStream = ChunkStream;

    async fn export_model(
        &self,
        request: Request<v1::ExportModelRequest>,
    ) -> Result<Response<Self::ExportModelStream>, Status> {
        let name = request.into_inner().name;
        let id = strip_collection("models", &name);
        let bytes = self
            .registry
            .store
            .model_artifact(id)
            .await?
            .ok_or_else(|| not_found("model", &format!("models/{id}")))?;
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
        let header = match stream.message().await? {
            Some(v1::ImportModelRequest {
                kind: Some(Kind::Header(h)),
            }) => h,
            _ => {
                return Err(invalid_field(
                    "header",
                    "the first message must be a header",
                ));
            }
        };
        let mut bytes = Vec::new();
        while let Some(message) = stream.message().await? {
            match message.kind {
                Some(Kind::Chunk(chunk)) => {
                    if bytes.len() + chunk.len() > MAX_ARTIFACT_BYTES {
                        return Err(invalid_field(
                            "chunk",
                            format!("artifact exceeds {MAX_ARTIFACT_BYTES} bytes"),
                        ));
                    }
                    bytes.extend_from_slice(&chunk);
                }
                _ => {
                    return Err(invalid_field(
                        "header",
                        "only the first message may be a header",
                    ));
                }
            }
        }
        let artifact = ModelArtifact::from_slice(&bytes)
            .map_err(|e| invalid_field("chunk", format!("not a usable model artifact: {e}")))?;
        let id = new_id();
        let display_name = if header.display_name.is_empty() {
            format!("imported {id}")
        } else {
            header.display_name
        };
        self.registry
            .register(&id, &display_name, ModelSource::Import, None, &artifact)
            .await?;
        let model = if header.activate {
            self.registry.activate(&id).await?
        } else {
            self.registry.get_proto(&id).await?
        };
        tracing::info!(model = %id, "imported model");
        Ok(Response::new(model))
    }
}
