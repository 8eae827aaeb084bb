//! The model registry: models in the store, parsed artifacts cached in memory, the bundled default
//! model registered on first start. It speaks domain types ([`ModelName`], [`ModelArtifact`], store
//! rows) and [`RegistryError`]; it must not know about gRPC (the edge is `crate::model_service`) nor
//! write SQL (that is `store`).

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use serde::{Deserialize, Serialize};
use spoofwatch_core::alarm::OperatingPoint;
use spoofwatch_core::metrics::Metrics;
use spoofwatch_core::model::artifact::{ARTIFACT_SCHEMA_VERSION, ArtifactError, ModelArtifact};
use spoofwatch_core::severity::CriticalTest;
use spoofwatch_proto::wire::{ModelName, OperationName};
use tokio_util::sync::CancellationToken;

use super::cache::ModelCache;
use crate::fault::Fault;
use crate::fault_log::FaultLog;
use crate::identity::{new_id, sha256_hex};
use crate::store::{ModelRow, ModelSource, NewModel, Page, PageRequest, Store, StoreError};
use crate::work::HeavyWork;

/// The artifact bundled into the binary: the `v3` model of `spoofwatch-lab experiment offsets` (see
/// `docs/getting-started.md`, "Bundled models").
pub const BUNDLED_MODEL: &[u8] = include_bytes!("../../../models/default.json");
/// Id of the bundled model in the registry.
pub const BUNDLED_MODEL_ID: &str = "default";
/// How often a server reads which model is active, to follow an activation made through another
/// server on the same database.
pub const ACTIVE_MODEL_POLL: Duration = Duration::from_secs(2);

/// Everything the registry can fail with.
#[derive(Debug, thiserror::Error)]
pub enum RegistryError {
    /// No model has this name.
    #[error("model {0} not found")]
    NotFound(ModelName),
    /// A request asked for the active model and none is set.
    #[error("no model is active")]
    NoActiveModel,
    /// Uploaded bytes are not a model artifact this server can load (the error names the field).
    #[error("not a usable model artifact: {0}")]
    InvalidArtifact(ArtifactError),
    /// A stored or bundled artifact could not be (de)serialised: a server-side fault.
    #[error(transparent)]
    Internal(#[from] Fault),
    /// The store failed or refused (e.g. deleting the active model).
    #[error(transparent)]
    Store(#[from] StoreError),
}

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
    /// The artifact's critical test; `None`: the model raises warnings only. Absent (so `None`) in
    /// metadata stored by servers before alarm severities were served.
    #[serde(default)]
    pub critical: Option<CriticalTest>,
}

impl ModelMetadata {
    pub(crate) fn of(artifact: &ModelArtifact) -> Self {
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
            critical: artifact.critical,
        }
    }

    /// The metadata of a stored model; `None` (logged) for a row written by an older, different
    /// format, so the model still lists without its details.
    pub fn of_row(row: &ModelRow) -> Option<Self> {
        serde_json::from_value(row.metadata.clone())
            .inspect_err(|error| {
                tracing::warn!(%error, model = %row.id, "unreadable model metadata");
            })
            .ok()
    }
}

/// Logs that `name` now serves as the active model, and says so when its alarms can only be
/// warnings (the artifact has no critical level: nothing it raises pages anyone).
fn announce_active(name: &ModelName, artifact: &ModelArtifact, how: &'static str) {
    tracing::info!(model = %name, "{how}");
    if artifact.critical.is_none() {
        tracing::warn!(
            model = %name,
            "the active model has no critical level: its alarms are warnings only, none is critical"
        );
    }
}

/// A parsed model ready to serve.
#[derive(Clone, Debug)]
pub struct LoadedModel {
    pub name: ModelName,
    pub artifact: Arc<ModelArtifact>,
}

/// Models in the store plus the active model and a byte-bounded LRU cache of other parsed
/// artifacts, so that starting a stream never waits for the database once the model has been
/// served, and importing many models cannot grow memory without bound.
#[derive(Debug)]
pub struct Registry {
    store: Store,
    /// Artifacts are parsed and checked (the canary drive included) there, off the runtime.
    heavy: HeavyWork,
    /// Parsed artifacts other than the active one, within the `--model-cache-bytes` budget.
    cache: Mutex<ModelCache>,
    /// The active model, as last read or set by this server (`None` until then). Held apart from
    /// the cache, so it is never evicted. This server is the only writer of the activation, so it
    /// is set where it activates.
    active: Mutex<Option<LoadedModel>>,
    /// Activations made by this server, counted under the `active` lock: a follow of the store
    /// that read the activation before one of them must not put its older model back.
    activations: AtomicU64,
}

impl Registry {
    /// A registry over `store` caching at most `cache_bytes` of (serialised) artifacts besides the
    /// active model.
    pub fn new(store: Store, cache_bytes: usize, heavy: HeavyWork) -> Self {
        Self {
            heavy,
            store,
            cache: Mutex::new(ModelCache::new(cache_bytes)),
            active: Mutex::new(None),
            activations: AtomicU64::new(0),
        }
    }

    fn cache(&self) -> std::sync::MutexGuard<'_, ModelCache> {
        // Each cache operation completes its bookkeeping before it can panic (it does not), and a
        // stale entry is only a cache miss, so a poisoned lock is usable.
        self.cache.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn active(&self) -> std::sync::MutexGuard<'_, Option<LoadedModel>> {
        // A single assignment cannot leave it inconsistent, so a poisoned lock is usable.
        self.active.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// The active model's name as this server knows it in memory (`None` before it is first read).
    pub fn active_name(&self) -> Option<ModelName> {
        self.active().as_ref().map(|model| model.name.clone())
    }

    /// The active model: from memory (kept current by [`Self::follow_active_model`]), or read
    /// from the store the first time.
    async fn active_model(&self) -> Result<LoadedModel, RegistryError> {
        if let Some(active) = self.active().clone() {
            return Ok(active);
        }
        let row = self
            .store
            .active_model()
            .await?
            .ok_or(RegistryError::NoActiveModel)?;
        let name = ModelName::from_id(row.id);
        let loaded = self.load(name).await?;
        announce_active(&loaded.name, &loaded.artifact, "serving the active model");
        *self.active() = Some(loaded.clone());
        Ok(loaded)
    }

    /// A model other than the known active one: from the cache, or parsed from the store.
    async fn load(&self, name: ModelName) -> Result<LoadedModel, RegistryError> {
        if let Some(artifact) = self.cache().get(name.id()) {
            return Ok(LoadedModel { name, artifact });
        }
        let bytes = self.artifact_bytes(&name).await?;
        let artifact = Arc::new(
            self.heavy
                .run(|| ModelArtifact::from_slice(&bytes))
                .await
                .map_err(|e| Fault::new("loading a stored model", e))?,
        );
        self.cache()
            .insert(name.id(), Arc::clone(&artifact), bytes.len());
        Ok(LoadedModel { name, artifact })
    }

    /// On an empty registry, registers and activates the bundled default model.
    pub async fn ensure_default_model(&self) -> Result<(), RegistryError> {
        if self.store.model_count().await? > 0 {
            return Ok(());
        }
        let artifact = ModelArtifact::from_slice(BUNDLED_MODEL)
            .map_err(|e| Fault::new("loading the bundled default model", e))?;
        let artifact = Arc::new(artifact);
        let registered = self
            .register(
                BUNDLED_MODEL_ID,
                "bundled default (fleet drives, v3 evidence)",
                ModelSource::Bundled,
                None,
                &artifact,
                true,
            )
            .await;
        match registered {
            Ok(_) => {}
            // A replica starting at the same moment on the same database registered (and
            // activated) it first: the active model is then read from the store like any other.
            Err(RegistryError::Store(StoreError::AlreadyExists { .. })) => return Ok(()),
            Err(error) => return Err(error),
        }
        tracing::info!("registered and activated the bundled default model");
        Ok(())
    }

    /// Stores an artifact under `id`; with `activate`, it becomes the active model in the same
    /// transaction, so a failure or a crash never leaves it stored but inactive.
    pub async fn register(
        &self,
        id: &str,
        display_name: &str,
        source: ModelSource,
        training_operation: Option<&OperationName>,
        artifact: &ModelArtifact,
        activate: bool,
    ) -> Result<ModelRow, RegistryError> {
        let bytes = artifact
            .to_vec()
            .map_err(|e| Fault::new("serialising a model artifact", e))?;
        let size = bytes.len();
        let metadata = serde_json::to_value(ModelMetadata::of(artifact))
            .map_err(|e| Fault::new("serialising model metadata", e))?;
        let model = NewModel {
            id: id.to_string(),
            display_name: display_name.to_string(),
            source,
            training_operation: training_operation.map(ToString::to_string),
            schema_version: i64::from(ARTIFACT_SCHEMA_VERSION),
            sha256: sha256_hex(&bytes),
            metadata,
            artifact: bytes,
        };
        let artifact = Arc::new(artifact.clone());
        if activate {
            let row = self.store.insert_active_model(model).await?;
            let name = ModelName::from_id(id);
            announce_active(&name, &artifact, "activated model");
            *self.active() = Some(LoadedModel { name, artifact });
            return Ok(row);
        }
        let row = self.store.insert_model(model).await?;
        self.cache().insert(id, artifact, size);
        Ok(row)
    }

    /// Registers uploaded artifact bytes under a fresh id (activating them if asked).
    pub async fn import(
        &self,
        bytes: &[u8],
        display_name: &str,
        activate: bool,
    ) -> Result<ModelRow, RegistryError> {
        let artifact = self
            .heavy
            .run(|| ModelArtifact::from_slice(bytes))
            .await
            .map_err(RegistryError::InvalidArtifact)?;
        let artifact = Arc::new(artifact);
        let id = new_id();
        let display_name = if display_name.is_empty() {
            format!("imported {id}")
        } else {
            display_name.to_string()
        };
        let row = self
            .register(
                &id,
                &display_name,
                ModelSource::Import,
                None,
                &artifact,
                activate,
            )
            .await?;
        tracing::info!(model = %id, "imported model");
        Ok(row)
    }

    /// The model to serve: the named one, or the active model for `None`.
    pub async fn resolve(
        &self,
        requested: Option<&ModelName>,
    ) -> Result<LoadedModel, RegistryError> {
        let Some(name) = requested else {
            return self.active_model().await;
        };
        let active = self.active().clone();
        match active {
            Some(active) if active.name == *name => Ok(active),
            _ => self.load(name.clone()).await,
        }
    }

    /// Whether `name` is the active model as this server knows it (`false` until it is first read).
    pub fn is_active(&self, name: &ModelName) -> bool {
        self.active().as_ref().is_some_and(|a| a.name == *name)
    }

    /// A stored model's row.
    pub async fn get(&self, name: &ModelName) -> Result<ModelRow, RegistryError> {
        self.store
            .get_model(name.id())
            .await?
            .ok_or_else(|| RegistryError::NotFound(name.clone()))
    }

    /// One page of models, newest first.
    pub async fn list(&self, page: &PageRequest) -> Result<Page<ModelRow>, RegistryError> {
        Ok(self.store.list_models(page).await?)
    }

    /// A stored model's serialised artifact.
    pub async fn artifact_bytes(&self, name: &ModelName) -> Result<Vec<u8>, RegistryError> {
        self.store
            .model_artifact(name.id())
            .await?
            .ok_or_else(|| RegistryError::NotFound(name.clone()))
    }

    /// Makes a model active (it must load).
    pub async fn activate(&self, name: &ModelName) -> Result<ModelRow, RegistryError> {
        let loaded = self.resolve(Some(name)).await?;
        let row = self.store.set_active_model(name.id()).await?;
        announce_active(name, &loaded.artifact, "activated model");
        {
            let mut active = self.active();
            *active = Some(loaded);
            self.activations.fetch_add(1, Ordering::Relaxed);
        }
        Ok(row)
    }

    /// Follows the store's active model: when another process sharing the database activated
    /// another model, this one serves it from now on too (sessions already running keep theirs,
    /// as with an activation here). Returns the newly followed model's name.
    pub async fn follow_active_model(&self) -> Result<Option<ModelName>, RegistryError> {
        let activations = self.activations.load(Ordering::Relaxed);
        let Some(row) = self.store.active_model().await? else {
            return Ok(None);
        };
        let name = ModelName::from_id(row.id);
        if self.is_active(&name) {
            return Ok(None);
        }
        let loaded = self.load(name.clone()).await?;
        let mut active = self.active();
        if self.activations.load(Ordering::Relaxed) != activations {
            // This server activated a model after the store was read: that one stands.
            return Ok(None);
        }
        announce_active(
            &name,
            &loaded.artifact,
            "following the active model set by another server",
        );
        *active = Some(loaded);
        Ok(Some(name))
    }

    /// Keeps following the store's active model ([`Self::follow_active_model`]) every `period`
    /// until `stop` is cancelled; an unreadable store keeps the model this process knows.
    pub async fn keep_following_active_model(&self, period: Duration, stop: CancellationToken) {
        let mut tick = tokio::time::interval(period);
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        let reading = FaultLog::default();
        loop {
            tokio::select! {
                () = stop.cancelled() => break,
                _ = tick.tick() => match self.follow_active_model().await {
                    Ok(_) => {
                        if reading.succeeded() {
                            tracing::info!("the active model can be read again");
                        }
                    }
                    Err(error) => {
                        if reading.failed() {
                            tracing::warn!(%error, "could not read the active model; keeping this one until it can");
                        }
                    }
                },
            }
        }
    }

    /// Deletes a model that is not active.
    pub async fn delete(&self, name: &ModelName) -> Result<(), RegistryError> {
        self.store.delete_model(name.id()).await?;
        self.cache().remove(name.id());
        tracing::info!(model = %name, "deleted model");
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn the_active_model_is_served_from_memory_and_follows_activation() {
        let dir = tempfile::tempdir().expect("temp dir");
        let path = dir.path().join("spoofwatch.db");
        let store = Store::open(&path.to_string_lossy()).await.expect("open");
        // A cache too small for any artifact: the active model is held apart from it.
        let registry = Registry::new(store.clone(), 1, HeavyWork::new(1));
        registry.ensure_default_model().await.unwrap();
        assert_eq!(registry.resolve(None).await.unwrap().name.id(), "default");

        let artifact = ModelArtifact::from_slice(BUNDLED_MODEL).unwrap();
        registry
            .register(
                "second",
                "second",
                ModelSource::Import,
                None,
                &artifact,
                false,
            )
            .await
            .unwrap();
        registry
            .activate(&ModelName::from_id("second"))
            .await
            .unwrap();
        assert_eq!(registry.resolve(None).await.unwrap().name.id(), "second");

        // With the database gone, a stream start still gets the active model.
        store.close().await;
        assert!(store.active_model().await.is_err(), "the store is closed");
        assert_eq!(registry.resolve(None).await.unwrap().name.id(), "second");
    }

    #[tokio::test]
    async fn an_import_whose_activation_fails_stores_nothing() {
        let dir = tempfile::tempdir().expect("temp dir");
        let path = dir.path().join("spoofwatch.db");
        let store = Store::open(&path.to_string_lossy()).await.expect("open");
        let registry = Registry::new(store.clone(), 1 << 20, HeavyWork::new(1));
        registry.ensure_default_model().await.unwrap();
        // Activating anything but the bundled model fails inside the database.
        store
            .execute_for_test(
                "CREATE TRIGGER fail_activation BEFORE UPDATE OF active ON models \
                 WHEN NEW.active AND NEW.id <> 'default' \
                 BEGIN SELECT RAISE(ABORT, 'injected failure'); END",
            )
            .await;
        registry
            .import(BUNDLED_MODEL, "imported", true)
            .await
            .expect_err("the activation fails");
        assert_eq!(
            store.model_count().await.expect("count"),
            1,
            "nothing stored"
        );
        assert_eq!(registry.resolve(None).await.unwrap().name.id(), "default");
    }

    #[tokio::test]
    async fn a_poisoned_import_is_refused_at_its_field_and_nothing_is_stored() {
        use tonic_types::StatusExt;
        let dir = tempfile::tempdir().expect("temp dir");
        let path = dir.path().join("spoofwatch.db");
        let store = Store::open(&path.to_string_lossy()).await.expect("open");
        let registry = Registry::new(store.clone(), 1 << 20, HeavyWork::new(1));
        let mut value: serde_json::Value = serde_json::from_slice(BUNDLED_MODEL).expect("json");
        value["evidence"]["mu_e"] = serde_json::json!(1e308);
        let error = registry
            .import(value.to_string().as_bytes(), "poisoned", true)
            .await
            .expect_err("mu_e = 1e308 is refused");
        let status = tonic::Status::from(error);
        assert_eq!(status.code(), tonic::Code::InvalidArgument);
        let bad = status
            .get_details_bad_request()
            .expect("BadRequest details");
        assert_eq!(bad.field_violations[0].field, "artifact.evidence.mu_e");
        assert!(
            bad.field_violations[0].description.contains("1.000e308"),
            "{}",
            bad.field_violations[0].description
        );
        assert_eq!(store.model_count().await.expect("count"), 0);
    }
}
