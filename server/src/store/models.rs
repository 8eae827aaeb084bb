//! Detector models: metadata rows, artifact blobs, and the single active model.

use serde_json::Value;
use sqlx::types::Json;

use super::error::{byte_length, insert_error};
use super::paging::PagePlan;
use super::{Page, PageRequest, Store, StoreError, now_unix_ms};

/// Where a model came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ModelSource {
    /// Shipped with the server and registered on first start.
    Bundled,
    /// Produced by a training job.
    Training,
    /// Uploaded through `ImportModel`.
    Import,
}

impl ModelSource {
    /// The lowercase name stored in the database.
    pub fn as_str(self) -> &'static str {
        match self {
            ModelSource::Bundled => "bundled",
            ModelSource::Training => "training",
            ModelSource::Import => "import",
        }
    }

    fn from_str_opt(name: &str) -> Option<Self> {
        match name {
            "bundled" => Some(ModelSource::Bundled),
            "training" => Some(ModelSource::Training),
            "import" => Some(ModelSource::Import),
            _ => None,
        }
    }
}

text_enum!(ModelSource);

/// A model to register; `size_bytes` is taken from the artifact.
#[derive(Debug, Clone, PartialEq)]
pub struct NewModel {
    /// Caller-chosen unique id.
    pub id: String,
    /// Human-readable name.
    pub display_name: String,
    /// Where the model came from.
    pub source: ModelSource,
    /// The training operation that produced it, if any.
    pub training_operation: Option<String>,
    /// Version of the artifact format.
    pub schema_version: i64,
    /// Hex SHA-256 of `artifact`, computed by the caller.
    pub sha256: String,
    /// Opaque metadata (operating point, metrics, provenance summary).
    pub metadata: Value,
    /// The serialized model.
    pub artifact: Vec<u8>,
}

/// A stored model without its artifact.
#[derive(Debug, Clone, PartialEq, sqlx::FromRow)]
pub struct ModelRow {
    /// Unique id.
    pub id: String,
    /// Human-readable name.
    pub display_name: String,
    /// Where the model came from.
    pub source: ModelSource,
    /// The training operation that produced it, if any.
    pub training_operation: Option<String>,
    /// Registration time, unix epoch milliseconds.
    #[sqlx(rename = "created_at")]
    pub created_at_ms: i64,
    /// Version of the artifact format.
    pub schema_version: i64,
    /// Hex SHA-256 of the artifact.
    pub sha256: String,
    /// Artifact length in bytes.
    pub size_bytes: i64,
    /// Opaque metadata (operating point, metrics, provenance summary).
    #[sqlx(json, rename = "metadata_json")]
    pub metadata: Value,
    /// Whether this is the active model (at most one is).
    pub active: bool,
}

/// Listing name inside page tokens.
const LISTING: &str = "models";

const SELECT_MODEL_BY_ID: &str = "SELECT id, display_name, source, training_operation, created_at, \
     schema_version, sha256, size_bytes, metadata_json, active FROM models WHERE id = $1";

impl Store {
    /// Registers a model and its artifact atomically. The new model is not active.
    ///
    /// Fails with [`StoreError::AlreadyExists`] if the id is taken.
    pub async fn insert_model(&self, model: NewModel) -> Result<ModelRow, StoreError> {
        self.insert_model_at(model, now_unix_ms()).await
    }

    /// Registers a model and its artifact and makes it the active model (deactivating the
    /// previous one), in one transaction: a failure at any step, or a crash, stores nothing.
    ///
    /// Fails with [`StoreError::AlreadyExists`] if the id is taken.
    pub async fn insert_active_model(&self, model: NewModel) -> Result<ModelRow, StoreError> {
        self.insert(model, now_unix_ms(), true).await
    }

    /// [`Store::insert_model`] with an explicit creation time (tests pin ordering with it).
    pub(crate) async fn insert_model_at(
        &self,
        model: NewModel,
        created_at_ms: i64,
    ) -> Result<ModelRow, StoreError> {
        self.insert(model, created_at_ms, false).await
    }

    /// Inserts the model and its artifact, then activates it when asked, all in one transaction.
    async fn insert(
        &self,
        model: NewModel,
        created_at_ms: i64,
        activate: bool,
    ) -> Result<ModelRow, StoreError> {
        let size_bytes = byte_length("artifact", &model.artifact)?;
        in_write_tx!(self, |tx| {
            let inserted = sqlx::query(
                "INSERT INTO models (id, display_name, source, training_operation, created_at, \
                 schema_version, sha256, size_bytes, metadata_json, active) \
                 VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9, FALSE)",
            )
            .bind(&model.id)
            .bind(&model.display_name)
            .bind(model.source)
            .bind(&model.training_operation)
            .bind(created_at_ms)
            .bind(model.schema_version)
            .bind(&model.sha256)
            .bind(size_bytes)
            .bind(Json(&model.metadata))
            .execute(&mut *tx)
            .await;
            inserted.map_err(|error| insert_error(error, "model", &model.id))?;
            sqlx::query("INSERT INTO model_artifacts (model_id, artifact) VALUES ($1, $2)")
                .bind(&model.id)
                .bind(&model.artifact)
                .execute(&mut *tx)
                .await?;
            if activate {
                // Deactivate first: the partial unique index allows one active row at any moment.
                sqlx::query("UPDATE models SET active = FALSE WHERE active AND id <> $1")
                    .bind(&model.id)
                    .execute(&mut *tx)
                    .await?;
                sqlx::query("UPDATE models SET active = TRUE WHERE id = $1")
                    .bind(&model.id)
                    .execute(&mut *tx)
                    .await?;
            }
            tx.commit().await?;
        });
        Ok(ModelRow {
            id: model.id,
            display_name: model.display_name,
            source: model.source,
            training_operation: model.training_operation,
            created_at_ms,
            schema_version: model.schema_version,
            sha256: model.sha256,
            size_bytes,
            metadata: model.metadata,
            active: activate,
        })
    }

    /// The model with this id, without its artifact.
    pub async fn get_model(&self, id: &str) -> Result<Option<ModelRow>, StoreError> {
        Ok(on_pool!(self, |pool| {
            sqlx::query_as::<_, ModelRow>(SELECT_MODEL_BY_ID)
                .bind(id)
                .fetch_optional(pool)
                .await?
        }))
    }

    /// One page of models, newest first.
    ///
    /// Fails with [`StoreError::InvalidPageToken`] for a token not issued by this listing.
    pub async fn list_models(&self, request: &PageRequest) -> Result<Page<ModelRow>, StoreError> {
        let plan = PagePlan::new(LISTING, request)?;
        let rows = on_pool!(self, |pool| {
            sqlx::query_as::<_, ModelRow>(
                "SELECT id, display_name, source, training_operation, created_at, \
                 schema_version, sha256, size_bytes, metadata_json, active FROM models \
                 WHERE $1 IS NULL OR (created_at, id) < ($1, $2) \
                 ORDER BY created_at DESC, id DESC LIMIT $3",
            )
            .bind(plan.after_created_at())
            .bind(plan.after_id())
            .bind(plan.fetch_limit())
            .fetch_all(pool)
            .await?
        });
        Ok(plan.finish(LISTING, rows, |row: &ModelRow| {
            (row.created_at_ms, row.id.as_str())
        }))
    }

    /// The serialized model, or `None` if no model has this id.
    pub async fn model_artifact(&self, id: &str) -> Result<Option<Vec<u8>>, StoreError> {
        Ok(on_pool!(self, |pool| {
            sqlx::query_scalar("SELECT artifact FROM model_artifacts WHERE model_id = $1")
                .bind(id)
                .fetch_optional(pool)
                .await?
        }))
    }

    /// The active model, if one is set.
    pub async fn active_model(&self) -> Result<Option<ModelRow>, StoreError> {
        Ok(on_pool!(self, |pool| {
            sqlx::query_as::<_, ModelRow>(
                "SELECT id, display_name, source, training_operation, created_at, \
                 schema_version, sha256, size_bytes, metadata_json, active FROM models \
                 WHERE active",
            )
            .fetch_optional(pool)
            .await?
        }))
    }

    /// Makes `id` the active model and deactivates the previous one, atomically.
    ///
    /// Fails with [`StoreError::NotFound`] (and changes nothing) if no model has this id.
    pub async fn set_active_model(&self, id: &str) -> Result<ModelRow, StoreError> {
        in_write_tx!(self, |tx| {
            let Some(mut model) = sqlx::query_as::<_, ModelRow>(SELECT_MODEL_BY_ID)
                .bind(id)
                .fetch_optional(&mut *tx)
                .await?
            else {
                return Err(not_found(id));
            };
            // Deactivate first: the partial unique index allows one active row at any moment.
            sqlx::query("UPDATE models SET active = FALSE WHERE active AND id <> $1")
                .bind(id)
                .execute(&mut *tx)
                .await?;
            sqlx::query("UPDATE models SET active = TRUE WHERE id = $1")
                .bind(id)
                .execute(&mut *tx)
                .await?;
            tx.commit().await?;
            model.active = true;
            Ok(model)
        })
    }

    /// Deletes a model and its artifact.
    ///
    /// Fails with [`StoreError::ModelActive`] for the active model and [`StoreError::NotFound`] for an
    /// unknown id; nothing is deleted in either case.
    pub async fn delete_model(&self, id: &str) -> Result<(), StoreError> {
        in_write_tx!(self, |tx| {
            let active = sqlx::query_scalar::<_, bool>("SELECT active FROM models WHERE id = $1")
                .bind(id)
                .fetch_optional(&mut *tx)
                .await?;
            match active {
                None => return Err(not_found(id)),
                Some(true) => return Err(StoreError::ModelActive { id: id.to_owned() }),
                Some(false) => {}
            }
            // The artifact row goes with it (ON DELETE CASCADE).
            sqlx::query("DELETE FROM models WHERE id = $1")
                .bind(id)
                .execute(&mut *tx)
                .await?;
            tx.commit().await?;
            Ok(())
        })
    }

    /// How many models are registered.
    pub async fn model_count(&self) -> Result<u64, StoreError> {
        let count = on_pool!(self, |pool| {
            sqlx::query_scalar::<_, i64>("SELECT COUNT(*) FROM models")
                .fetch_one(pool)
                .await?
        });
        Ok(u64::try_from(count).unwrap_or(0))
    }
}

fn not_found(id: &str) -> StoreError {
    StoreError::NotFound {
        kind: "model",
        id: id.to_owned(),
    }
}
