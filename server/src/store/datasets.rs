//! Uploaded or imported datasets: summary rows, and their content as ordered pieces (one row each,
//! so no statement ever carries a whole large dataset).

use super::error::{byte_length, insert_error};
use super::paging::PagePlan;
use super::{Page, PageRequest, Store, StoreError, now_unix_ms};

/// A dataset to store; `size_bytes` is the total length of the content's pieces.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct NewDataset {
    /// Caller-chosen unique id.
    pub id: String,
    /// Human-readable name.
    pub display_name: String,
    /// Where it came from (e.g. "upload", "avgps-import"); free text chosen by the caller.
    pub source: String,
    /// Content format (e.g. "telemetry-csv"); free text chosen by the caller.
    pub format: String,
    /// Number of samples.
    pub rows: i64,
    /// Number of distinct vehicles.
    pub vehicles: i64,
    /// Samples carrying a spoofing label.
    pub labelled_rows: i64,
    /// Labelled samples marked spoofed.
    pub spoofed_rows: i64,
    /// Hex SHA-256 of the content, computed by the caller.
    pub sha256: String,
    /// The dataset bytes: their concatenation in order, stored one row per piece.
    pub content: Vec<Vec<u8>>,
}

/// A stored dataset without its content.
#[derive(Debug, Clone, PartialEq, Eq, sqlx::FromRow)]
pub struct DatasetRow {
    /// Unique id.
    pub id: String,
    /// Human-readable name.
    pub display_name: String,
    /// Where it came from.
    pub source: String,
    /// Content format.
    pub format: String,
    /// Number of samples.
    pub rows: i64,
    /// Number of distinct vehicles.
    pub vehicles: i64,
    /// Samples carrying a spoofing label.
    pub labelled_rows: i64,
    /// Labelled samples marked spoofed.
    pub spoofed_rows: i64,
    /// Content length in bytes.
    pub size_bytes: i64,
    /// Hex SHA-256 of the content.
    pub sha256: String,
    /// Creation time, unix epoch milliseconds.
    #[sqlx(rename = "created_at")]
    pub created_at_ms: i64,
}

/// Listing name inside page tokens.
const LISTING: &str = "datasets";

impl Store {
    /// Stores a dataset and its content atomically.
    ///
    /// Fails with [`StoreError::AlreadyExists`] if the id is taken and [`StoreError::InvalidValue`] for
    /// a negative count.
    pub async fn insert_dataset(&self, dataset: NewDataset) -> Result<DatasetRow, StoreError> {
        self.insert_dataset_at(dataset, now_unix_ms()).await
    }

    /// [`Store::insert_dataset`] with an explicit creation time (tests pin ordering with it).
    pub(crate) async fn insert_dataset_at(
        &self,
        dataset: NewDataset,
        created_at_ms: i64,
    ) -> Result<DatasetRow, StoreError> {
        validate_counts(&dataset)?;
        let size_bytes = dataset.content.iter().try_fold(0i64, |total, piece| {
            byte_length("content", piece).map(|len| total.saturating_add(len))
        })?;
        in_write_tx!(self, |tx| {
            let inserted = sqlx::query(
                "INSERT INTO datasets (id, display_name, source, format, rows, vehicles, \
                 labelled_rows, spoofed_rows, size_bytes, sha256, created_at) \
                 VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9, $10, $11)",
            )
            .bind(&dataset.id)
            .bind(&dataset.display_name)
            .bind(&dataset.source)
            .bind(&dataset.format)
            .bind(dataset.rows)
            .bind(dataset.vehicles)
            .bind(dataset.labelled_rows)
            .bind(dataset.spoofed_rows)
            .bind(size_bytes)
            .bind(&dataset.sha256)
            .bind(created_at_ms)
            .execute(&mut *tx)
            .await;
            inserted.map_err(|error| insert_error(error, "dataset", &dataset.id))?;
            for (index, piece) in dataset.content.iter().enumerate() {
                sqlx::query(
                    "INSERT INTO dataset_pieces (dataset_id, piece, content) VALUES ($1, $2, $3)",
                )
                .bind(&dataset.id)
                .bind(index as i64)
                .bind(piece)
                .execute(&mut *tx)
                .await?;
            }
            tx.commit().await?;
        });
        Ok(DatasetRow {
            id: dataset.id,
            display_name: dataset.display_name,
            source: dataset.source,
            format: dataset.format,
            rows: dataset.rows,
            vehicles: dataset.vehicles,
            labelled_rows: dataset.labelled_rows,
            spoofed_rows: dataset.spoofed_rows,
            size_bytes,
            sha256: dataset.sha256,
            created_at_ms,
        })
    }

    /// The dataset with this id, without its content.
    pub async fn get_dataset(&self, id: &str) -> Result<Option<DatasetRow>, StoreError> {
        Ok(on_pool!(self, |pool| {
            sqlx::query_as::<_, DatasetRow>(
                "SELECT id, display_name, source, format, rows, vehicles, labelled_rows, \
                 spoofed_rows, size_bytes, sha256, created_at FROM datasets WHERE id = $1",
            )
            .bind(id)
            .fetch_optional(pool)
            .await?
        }))
    }

    /// One page of datasets, newest first.
    ///
    /// Fails with [`StoreError::InvalidPageToken`] for a token not issued by this listing.
    pub async fn list_datasets(
        &self,
        request: &PageRequest,
    ) -> Result<Page<DatasetRow>, StoreError> {
        let plan = PagePlan::new(LISTING, request)?;
        let rows = on_pool!(self, |pool| {
            sqlx::query_as::<_, DatasetRow>(
                "SELECT id, display_name, source, format, rows, vehicles, labelled_rows, \
                 spoofed_rows, size_bytes, sha256, created_at FROM datasets \
                 WHERE $1 IS NULL OR (created_at, id) < ($1, $2) \
                 ORDER BY created_at DESC, id DESC LIMIT $3",
            )
            .bind(plan.after_created_at())
            .bind(plan.after_id())
            .bind(plan.fetch_limit())
            .fetch_all(pool)
            .await?
        });
        Ok(plan.finish(LISTING, rows, |row: &DatasetRow| {
            (row.created_at_ms, row.id.as_str())
        }))
    }

    /// The dataset bytes as their stored pieces, in order, or `None` if no dataset has this id.
    pub async fn dataset_content(&self, id: &str) -> Result<Option<Vec<Vec<u8>>>, StoreError> {
        let pieces: Vec<Vec<u8>> = on_pool!(self, |pool| {
            sqlx::query_scalar(
                "SELECT content FROM dataset_pieces WHERE dataset_id = $1 ORDER BY piece",
            )
            .bind(id)
            .fetch_all(pool)
            .await?
        });
        if pieces.is_empty() && self.get_dataset(id).await?.is_none() {
            return Ok(None);
        }
        Ok(Some(pieces))
    }

    /// Deletes a dataset and its content; [`StoreError::NotFound`] for an unknown id.
    pub async fn delete_dataset(&self, id: &str) -> Result<(), StoreError> {
        // One statement (the content goes by ON DELETE CASCADE), so no explicit transaction.
        let deleted = on_pool!(self, |pool| {
            sqlx::query("DELETE FROM datasets WHERE id = $1")
                .bind(id)
                .execute(pool)
                .await?
                .rows_affected()
        });
        if deleted == 0 {
            return Err(StoreError::NotFound {
                kind: "dataset",
                id: id.to_owned(),
            });
        }
        Ok(())
    }
}

/// Counts must be non-negative; checked here so the caller gets a precise error, not a CHECK failure.
fn validate_counts(dataset: &NewDataset) -> Result<(), StoreError> {
    let counts = [
        ("rows", dataset.rows),
        ("vehicles", dataset.vehicles),
        ("labelled_rows", dataset.labelled_rows),
        ("spoofed_rows", dataset.spoofed_rows),
    ];
    for (field, value) in counts {
        if value < 0 {
            return Err(StoreError::InvalidValue {
                field,
                reason: format!("must not be negative, got {value}"),
            });
        }
    }
    Ok(())
}
