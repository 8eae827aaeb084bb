//! DatasetService: labelled recordings stored in SQLite, uploaded by clients or imported from the
//! operator's data directory (and nowhere else).

use std::path::{Path, PathBuf};
use std::sync::Arc;

use spoofwatch_core::data::{Format, Recording, read};
use spoofwatch_core::sample::{Record, Sample, Track};
use spoofwatch_proto::v1;
use spoofwatch_proto::v1::dataset_service_server::DatasetService;
use spoofwatch_proto::v1::upload_dataset_request::Kind;
use tonic::{Request, Response, Status, Streaming};

use crate::convert::{
    page_request, sample_from_proto, sha256_hex, strip_collection, timestamp_from_ms,
};
use crate::error::{failed_precondition, internal, invalid_field, not_found};
use crate::registry::new_id;
use crate::store::{DatasetRow, NewDataset, Store};

/// Largest dataset accepted (bytes of CSV).
pub const MAX_DATASET_BYTES: usize = 256 << 20;

/// Parses CSV bytes (either format) off the async runtime.
pub async fn parse_dataset(bytes: Arc<Vec<u8>>, source: String) -> Result<Recording, Status> {
    tokio::task::spawn_blocking(move || read(bytes.as_slice(), &source))
        .await
        .map_err(|e| internal("parsing a dataset", &e))?
        .map_err(|e| invalid_field("csv_chunk", e.to_string()))
}

/// Loads a stored dataset's tracks.
pub async fn load_dataset(store: &Store, name: &str) -> Result<Vec<Track>, Status> {
    let id = strip_collection("datasets", name);
    let content = store
        .dataset_content(id)
        .await?
        .ok_or_else(|| not_found("dataset", &format!("datasets/{id}")))?;
    Ok(parse_dataset(Arc::new(content), id.to_string())
        .await?
        .tracks)
}

fn to_proto(row: &DatasetRow) -> v1::Dataset {
    v1::Dataset {
        name: format!("datasets/{}", row.id),
        display_name: row.display_name.clone(),
        source: row.source.clone(),
        format: row.format.clone(),
        rows: row.rows as u64,
        vehicles: row.vehicles as u32,
        labelled_rows: row.labelled_rows as u64,
        spoofed_rows: row.spoofed_rows as u64,
        size_bytes: row.size_bytes as u64,
        sha256: row.sha256.clone(),
        create_time: Some(timestamp_from_ms(row.created_at_ms)),
    }
}

/// Resolves `relative` inside `data_dir`, refusing anything that escapes it (`..`, absolute paths,
/// symlinks pointing outside).
pub fn resolve_inside(data_dir: &Path, relative: &str) -> Result<PathBuf, Status> {
    let denied = |why: &str| Status::permission_denied(format!("path {relative:?} {why}"));
    if relative.is_empty() {
        return Err(invalid_field("path", "required"));
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
        .map_err(|e| internal("opening the data directory", &e))?;
    let candidate = root.join(relative);
    let resolved = candidate
        .canonicalize()
        .map_err(|_| not_found("file", relative))?;
    if !resolved.starts_with(&root) {
        return Err(denied("is outside the server's data directory"));
    }
    if !resolved.is_file() {
        return Err(invalid_field("path", "is not a file"));
    }
    Ok(resolved)
}

/// The DatasetService implementation.
#[derive(Debug, Clone)]
pub struct DatasetApi {
    pub store: Store,
    pub data_dir: Option<PathBuf>,
}

impl DatasetApi {
    async fn store_recording(
        &self,
        display_name: String,
        source: String,
        content: Vec<u8>,
        recording: &Recording,
    ) -> Result<v1::Dataset, Status> {
        let records = || recording.tracks.iter().flat_map(|t| &t.records);
        let row = self
            .store
            .insert_dataset(NewDataset {
                id: new_id(),
                display_name,
                source,
                format: match recording.format {
                    Format::AvGps => "av-gps",
                    Format::Telemetry => "telemetry",
                }
                .to_string(),
                rows: records().count() as i64,
                vehicles: recording.tracks.len() as i64,
                labelled_rows: records().filter(|r| r.label.is_some()).count() as i64,
                spoofed_rows: records().filter(|r| r.label == Some(true)).count() as i64,
                sha256: sha256_hex(&content),
                content,
            })
            .await?;
        tracing::info!(dataset = %row.id, rows = row.rows, "stored dataset");
        Ok(to_proto(&row))
    }
}

/// Structured upload records as tracks (vehicles in first-appearance order).
fn tracks_from_records(records: Vec<v1::LabelledSample>) -> Result<Vec<Track>, Status> {
    let mut tracks: Vec<Track> = Vec::new();
    for (i, r) in records.into_iter().enumerate() {
        let sample: Sample = r
            .sample
            .as_ref()
            .map(sample_from_proto)
            .ok_or_else(|| invalid_field(format!("records[{i}].sample"), "required"))?;
        if r.vehicle_id.is_empty() {
            return Err(invalid_field(
                format!("records[{i}].vehicle_id"),
                "required",
            ));
        }
        let record = Record {
            sample,
            label: r.spoofed,
            comparator_alarm: None,
            line: i as u64 + 2,
            trajectory_break: false,
        };
        match tracks.iter_mut().find(|t| t.vehicle_id == r.vehicle_id) {
            Some(track) => track.records.push(record),
            None => tracks.push(Track {
                vehicle_id: r.vehicle_id,
                records: vec![record],
            }),
        }
    }
    Ok(tracks)
}

#[tonic::async_trait]
impl DatasetService for DatasetApi {
    async fn upload_dataset(
        &self,
        request: Request<Streaming<v1::UploadDatasetRequest>>,
    ) -> Result<Response<v1::Dataset>, Status> {
        let mut stream = request.into_inner();
        let header = match stream.message().await? {
            Some(v1::UploadDatasetRequest {
                kind: Some(Kind::Header(h)),
            }) => h,
            _ => {
                return Err(invalid_field(
                    "header",
                    "the first message must be a header",
                ));
            }
        };
        let mut csv = Vec::new();
        let mut structured = Vec::new();
        while let Some(message) = stream.message().await? {
            match message.kind {
                Some(Kind::CsvChunk(chunk)) if structured.is_empty() => {
                    if csv.len() + chunk.len() > MAX_DATASET_BYTES {
                        return Err(invalid_field(
                            "csv_chunk",
                            format!("dataset exceeds {MAX_DATASET_BYTES} bytes"),
                        ));
                    }
                    csv.extend_from_slice(&chunk);
                }
                Some(Kind::Records(batch)) if csv.is_empty() => {
                    structured.extend(batch.records);
                }
                Some(Kind::Header(_)) => {
                    return Err(invalid_field(
                        "header",
                        "only the first message may be a header",
                    ));
                }
                _ => {
                    return Err(invalid_field(
                        "kind",
                        "send either csv_chunk messages or records messages, not both",
                    ));
                }
            }
        }
        if !structured.is_empty() {
            let tracks = tracks_from_records(structured)?;
            spoofwatch_core::data::telemetry::write_tracks(&mut csv, &tracks)
                .map_err(|e| internal("encoding uploaded records", &e))?;
        }
        if csv.is_empty() {
            return Err(invalid_field("csv_chunk", "the upload holds no data"));
        }
        let name = if header.display_name.is_empty() {
            "upload".to_string()
        } else {
            header.display_name
        };
        let csv = Arc::new(csv);
        let recording = parse_dataset(Arc::clone(&csv), name.clone()).await?;
        let content = Arc::try_unwrap(csv).unwrap_or_else(|shared| (*shared).clone());
        let dataset = self
            .store_recording(name, "upload".into(), content, &recording)
            .await?;
        Ok(Response::new(dataset))
    }

    async fn import_dataset(
        &self,
        request: Request<v1::ImportDatasetRequest>,
    ) -> Result<Response<v1::Dataset>, Status> {
        let r = request.into_inner();
        let Some(data_dir) = &self.data_dir else {
            return Err(failed_precondition(
                "NO_DATA_DIR",
                "this server has no data directory (start it with --data-dir)",
            ));
        };
        let path = resolve_inside(data_dir, &r.path)?;
        let content = tokio::fs::read(&path)
            .await
            .map_err(|e| internal("reading an import file", &e))?;
        if content.len() > MAX_DATASET_BYTES {
            return Err(invalid_field(
                "path",
                format!("file exceeds {MAX_DATASET_BYTES} bytes"),
            ));
        }
        let stem = path
            .file_stem()
            .map_or_else(|| r.path.clone(), |s| s.to_string_lossy().to_string());
        let content = Arc::new(content);
        let recording = parse_dataset(Arc::clone(&content), stem.clone())
            .await
            .map_err(|s| invalid_field("path", s.message().to_string()))?;
        let display_name = if r.display_name.is_empty() {
            stem
        } else {
            r.display_name
        };
        let content = Arc::try_unwrap(content).unwrap_or_else(|shared| (*shared).clone());
        let dataset = self
            .store_recording(
                display_name,
                format!("import:{}", r.path),
                content,
                &recording,
            )
            .await?;
        Ok(Response::new(dataset))
    }

    async fn list_datasets(
        &self,
        request: Request<v1::ListDatasetsRequest>,
    ) -> Result<Response<v1::ListDatasetsResponse>, Status> {
        let r = request.into_inner();
        let page = self
            .store
            .list_datasets(&page_request(r.page_size, &r.page_token)?)
            .await?;
        Ok(Response::new(v1::ListDatasetsResponse {
            datasets: page.items.iter().map(to_proto).collect(),
            next_page_token: page.next_page_token.unwrap_or_default(),
        }))
    }

    async fn get_dataset(
        &self,
        request: Request<v1::GetDatasetRequest>,
    ) -> Result<Response<v1::Dataset>, Status> {
        let name = request.into_inner().name;
        let id = strip_collection("datasets", &name);
        let row = self
            .store
            .get_dataset(id)
            .await?
            .ok_or_else(|| not_found("dataset", &format!("datasets/{id}")))?;
        Ok(Response::new(to_proto(&row)))
    }

    async fn delete_dataset(
        &self,
        request: Request<v1::DeleteDatasetRequest>,
    ) -> Result<Response<()>, Status> {
        let name = request.into_inner().name;
        self.store
            .delete_dataset(strip_collection("datasets", &name))
            .await?;
        Ok(Response::new(()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn paths_must_stay_inside_the_data_directory() {
        let root = tempfile::tempdir().expect("tempdir");
        std::fs::write(root.path().join("a.csv"), "x").expect("write");
        std::fs::create_dir(root.path().join("sub")).expect("mkdir");
        std::fs::write(root.path().join("sub/b.csv"), "x").expect("write");
        assert!(resolve_inside(root.path(), "a.csv").is_ok());
        assert!(resolve_inside(root.path(), "sub/../a.csv").is_ok());
        assert!(resolve_inside(root.path(), "sub/b.csv").is_ok());
        let outside = resolve_inside(root.path(), "../../etc/passwd").unwrap_err();
        assert_eq!(outside.code(), tonic::Code::PermissionDenied);
        let absolute = resolve_inside(root.path(), "/etc/passwd").unwrap_err();
        assert_eq!(absolute.code(), tonic::Code::PermissionDenied);
        assert_eq!(
            resolve_inside(root.path(), "sub").unwrap_err().code(),
            tonic::Code::InvalidArgument
        );
        assert_eq!(
            resolve_inside(root.path(), "missing.csv")
                .unwrap_err()
                .code(),
            tonic::Code::NotFound
        );
    }
}
