//! The dataset catalog: labelled recordings parsed, summarised and stored, imported from the
//! operator's data directory (and nowhere else), and loaded back as tracks for jobs. It speaks domain
//! types and [`DatasetError`]; it must not know about gRPC (the edge is `datasets::service`) nor
//! write SQL (that is `store`).

use std::path::{Path, PathBuf};

use spoofwatch_core::data::{DataError, Format, read, summarize};
use spoofwatch_core::sample::Track;
use spoofwatch_proto::wire::DatasetName;
use spoofwatch_proto::wire::limits::MAX_DATASET_BYTES;

use super::content::Content;
use crate::fault::Fault;
use crate::identity::new_id;
use crate::store::{DatasetRow, NewDataset, Page, PageRequest, Store, StoreError};
use crate::work::HeavyWork;

/// Everything the catalog can fail with.
#[derive(Debug, thiserror::Error)]
pub enum DatasetError {
    /// No dataset has this name.
    #[error("dataset {0} not found")]
    NotFound(DatasetName),
    /// The data given is unusable (unparseable CSV, too large, not a file...).
    #[error("{field}: {reason}")]
    Invalid {
        /// The request field the data came from.
        field: &'static str,
        /// What is wrong.
        reason: String,
    },
    /// Imports need a data directory and this server has none.
    #[error("this server has no data directory (start it with --data-dir)")]
    NoDataDir,
    /// An import path escapes the data directory.
    #[error("path {path:?} {why}")]
    PathDenied {
        /// The path as requested.
        path: String,
        /// Why it is refused.
        why: &'static str,
    },
    /// An import path names no file.
    #[error("file {0:?} not found")]
    FileNotFound(String),
    /// A server-side fault (I/O on the data directory, a crashed parser thread).
    #[error(transparent)]
    Internal(#[from] Fault),
    /// The store failed.
    #[error(transparent)]
    Store(#[from] StoreError),
}

/// A parse error as the refusal of the request field the data came in.
fn unparseable(field: &'static str) -> impl Fn(DataError) -> DatasetError {
    move |e| DatasetError::Invalid {
        field,
        reason: e.to_string(),
    }
}

/// Longest import path accepted (it is echoed in errors, so it is bounded first).
const MAX_IMPORT_PATH_BYTES: usize = 1024;

/// Resolves `relative` inside `data_dir`, refusing anything that escapes it (`..`, absolute paths,
/// symlinks pointing outside).
pub fn resolve_inside(data_dir: &Path, relative: &str) -> Result<PathBuf, DatasetError> {
    let denied = |why: &'static str| DatasetError::PathDenied {
        path: relative.to_string(),
        why,
    };
    if relative.is_empty() || relative.len() > MAX_IMPORT_PATH_BYTES {
        return Err(DatasetError::Invalid {
            field: "path",
            reason: format!("required, at most {MAX_IMPORT_PATH_BYTES} bytes"),
        });
    }
    if Path::new(relative).is_absolute() {
        return Err(denied("must be relative to the server's data directory"));
    }
    // Lexical check first, so nothing outside is even looked at.
    let mut depth: i64 = 0;
    for component in Path::new(relative).components() {
        match component {
            std::path::Component::ParentDir => depth -= 1,
            std::path::Component::Normal(_) => depth += 1,
            _ => {}
        }
        if depth < 0 {
            return Err(denied("is outside the server's data directory"));
        }
    }
    let root = data_dir
        .canonicalize()
        .map_err(|e| Fault::new("opening the data directory", e))?;
    let resolved = root
        .join(relative)
        .canonicalize()
        .map_err(|_| DatasetError::FileNotFound(relative.to_string()))?;
    if !resolved.starts_with(&root) {
        return Err(denied("is outside the server's data directory"));
    }
    if !resolved.is_file() {
        return Err(DatasetError::Invalid {
            field: "path",
            reason: "is not a file".into(),
        });
    }
    Ok(resolved)
}

/// Datasets in the store, plus the directory imports may read from.
#[derive(Debug, Clone)]
pub struct Catalog {
    store: Store,
    data_dir: Option<PathBuf>,
    /// Parsing and encoding run there, never on the runtime's threads.
    heavy: HeavyWork,
}

impl Catalog {
    pub fn new(store: Store, data_dir: Option<PathBuf>, heavy: HeavyWork) -> Self {
        Self {
            store,
            data_dir,
            heavy,
        }
    }

    /// The bounded pool this catalog parses on (the edge converts uploaded records there too).
    pub fn heavy(&self) -> &HeavyWork {
        &self.heavy
    }

    /// Parses uploaded CSV and stores it (`field` names the request field it came in).
    pub async fn upload(
        &self,
        display_name: &str,
        csv: Content,
        field: &'static str,
    ) -> Result<DatasetRow, DatasetError> {
        let name = if display_name.is_empty() {
            "upload"
        } else {
            display_name
        };
        self.parse_and_store(name.to_string(), "upload".into(), csv, field)
            .await
    }

    /// Uploaded structured records: written as telemetry CSV, then stored like any upload.
    pub async fn upload_tracks(
        &self,
        display_name: &str,
        tracks: &[Track],
    ) -> Result<DatasetRow, DatasetError> {
        let mut csv = Content::default();
        self.heavy
            .run(|| spoofwatch_core::data::telemetry::write_tracks(&mut csv, tracks))
            .await
            .map_err(|e| Fault::new("encoding uploaded records", e))?;
        self.upload(display_name, csv.finish(), "records").await
    }

    /// Imports a CSV file from the data directory.
    pub async fn import(
        &self,
        relative_path: &str,
        display_name: &str,
    ) -> Result<DatasetRow, DatasetError> {
        let data_dir = self.data_dir.as_deref().ok_or(DatasetError::NoDataDir)?;
        let path = resolve_inside(data_dir, relative_path)?;
        let content = read_bounded(&path, MAX_DATASET_BYTES).await?;
        let stem = path.file_stem().map_or_else(
            || relative_path.to_string(),
            |s| s.to_string_lossy().to_string(),
        );
        let display_name = if display_name.is_empty() {
            stem
        } else {
            display_name.to_string()
        };
        self.parse_and_store(
            display_name,
            format!("import:{relative_path}"),
            content,
            "path",
        )
        .await
    }

    async fn parse_and_store(
        &self,
        display_name: String,
        source: String,
        content: Content,
        field: &'static str,
    ) -> Result<DatasetRow, DatasetError> {
        if content.is_empty() {
            return Err(DatasetError::Invalid {
                field,
                reason: "the upload holds no data".into(),
            });
        }
        // Counted, not built: the stored dataset is parsed in full only by the jobs that use it.
        let summary = self
            .heavy
            .run(|| summarize(content.reader(), &display_name))
            .await
            .map_err(unparseable(field))?;
        let count = |n: u64| i64::try_from(n).unwrap_or(i64::MAX);
        let row = self
            .store
            .insert_dataset(NewDataset {
                id: new_id(),
                display_name,
                source,
                format: match summary.format {
                    Format::AvGps => "av-gps",
                    Format::Telemetry => "telemetry",
                }
                .to_string(),
                rows: count(summary.rows),
                vehicles: count(summary.vehicles),
                labelled_rows: count(summary.labelled_rows),
                spoofed_rows: count(summary.spoofed_rows),
                sha256: content.sha256_hex(),
                content: content.into_pieces(),
            })
            .await?;
        tracing::info!(dataset = %row.id, rows = row.rows, "stored dataset");
        Ok(row)
    }

    /// A stored dataset's row.
    pub async fn get(&self, name: &DatasetName) -> Result<DatasetRow, DatasetError> {
        self.store
            .get_dataset(name.id())
            .await?
            .ok_or_else(|| DatasetError::NotFound(name.clone()))
    }

    /// One page of datasets, newest first.
    pub async fn list(&self, page: &PageRequest) -> Result<Page<DatasetRow>, DatasetError> {
        Ok(self.store.list_datasets(page).await?)
    }

    /// Deletes a dataset.
    pub async fn delete(&self, name: &DatasetName) -> Result<(), DatasetError> {
        Ok(self.store.delete_dataset(name.id()).await?)
    }

    /// Loads the tracks of every named dataset, in order (one dataset's bytes held at a time).
    pub async fn load_tracks(&self, names: &[DatasetName]) -> Result<Vec<Track>, DatasetError> {
        let mut tracks = Vec::new();
        for name in names {
            let content = Content::from_pieces(
                self.store
                    .dataset_content(name.id())
                    .await?
                    .ok_or_else(|| DatasetError::NotFound(name.clone()))?,
            );
            let recording = self
                .heavy
                .run(|| read(content.reader(), name.id()))
                .await
                .map_err(unparseable("datasets"))?;
            tracks.extend(recording.tracks);
        }
        Ok(tracks)
    }
}

/// A file of at most `limit` bytes: its size is checked before anything is read, and the read
/// stops past the limit (the file may grow in between), so an oversized file is never loaded.
async fn read_bounded(path: &Path, limit: usize) -> Result<Content, DatasetError> {
    use tokio::io::AsyncReadExt;
    let too_large = |size: u64| DatasetError::Invalid {
        field: "path",
        reason: format!("the file has {size} bytes; at most {limit} are accepted"),
    };
    let read_error = |e| Fault::new("reading an import file", e);
    let file = tokio::fs::File::open(path).await.map_err(read_error)?;
    let size = file.metadata().await.map_err(read_error)?.len();
    if size > limit as u64 {
        return Err(too_large(size));
    }
    let mut content = Content::default();
    let mut file = file.take(limit as u64 + 1);
    let mut buffer = vec![0; 1 << 16];
    loop {
        let read = file.read(&mut buffer).await.map_err(read_error)?;
        if read == 0 {
            break;
        }
        content.extend(&buffer[..read]);
    }
    if content.len() > limit {
        return Err(too_large(content.len() as u64));
    }
    Ok(content.finish())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn an_import_file_over_the_limit_is_refused_before_it_is_read() {
        let dir = tempfile::tempdir().expect("a temporary directory");
        let path = dir.path().join("big.csv");
        std::fs::write(&path, vec![b'x'; 100]).expect("written");
        assert_eq!(
            read_bounded(&path, 100).await.expect("at the limit").len(),
            100
        );
        match read_bounded(&path, 99).await {
            Err(DatasetError::Invalid { field, reason }) => {
                assert_eq!(field, "path");
                assert!(reason.contains("100 bytes; at most 99"), "{reason}");
            }
            other => panic!("expected a refusal, got {other:?}"),
        }
    }

    #[test]
    fn paths_must_stay_inside_the_data_directory() {
        let root = tempfile::tempdir().expect("tempdir");
        std::fs::write(root.path().join("a.csv"), "x").expect("write");
        std::fs::create_dir(root.path().join("sub")).expect("mkdir");
        std::fs::write(root.path().join("sub/b.csv"), "x").expect("write");
        assert!(resolve_inside(root.path(), "a.csv").is_ok());
        assert!(resolve_inside(root.path(), "sub/../a.csv").is_ok());
        assert!(resolve_inside(root.path(), "sub/b.csv").is_ok());
        let code = |e: DatasetError| tonic::Status::from(e).code();
        let outside = resolve_inside(root.path(), "../../etc/passwd").unwrap_err();
        assert_eq!(code(outside), tonic::Code::PermissionDenied);
        let absolute = resolve_inside(root.path(), "/etc/passwd").unwrap_err();
        assert_eq!(code(absolute), tonic::Code::PermissionDenied);
        assert_eq!(
            code(resolve_inside(root.path(), "sub").unwrap_err()),
            tonic::Code::InvalidArgument
        );
        assert_eq!(
            code(resolve_inside(root.path(), "missing.csv").unwrap_err()),
            tonic::Code::NotFound
        );
        // A 20,000-character path is refused without being echoed.
        let long = resolve_inside(root.path(), &"a/".repeat(10_000)).unwrap_err();
        let status = tonic::Status::from(long);
        assert_eq!(status.code(), tonic::Code::InvalidArgument);
        assert!(status.message().len() < 200, "{}", status.message());
    }
}
