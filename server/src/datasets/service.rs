//! The DatasetService RPCs: the edge between the wire and the [`Catalog`]. Decodes the upload
//! stream protocol, converts wire records to core tracks, validates names and paging, and maps
//! [`super::DatasetError`] once (through `crate::error`); it must not parse CSV or touch the store.

use std::collections::HashMap;
use std::sync::Arc;

use prost::Message;
use tokio::sync::{OwnedSemaphorePermit, Semaphore};

use spoofwatch_core::sample::{Record, Track};
use spoofwatch_proto::v1;
use spoofwatch_proto::v1::dataset_service_server::DatasetService;
use spoofwatch_proto::v1::upload_dataset_request::Kind;
use spoofwatch_proto::wire::DatasetName;
use spoofwatch_proto::wire::convert::{sample_from_proto, timestamp_from_ms};
use spoofwatch_proto::wire::limits::{MAX_DATASET_BYTES, MAX_DATASET_RECORDS};
use tonic::{Request, Response, Status, Streaming};

use super::catalog::Catalog;
use super::content::Content;
use crate::access::Caller;
use crate::edge::{dataset_name, display_name, page_request};
use crate::idle::StreamIdle;
use crate::status::{
    header_first, header_not_first, invalid_argument, invalid_field, resource_exhausted,
};
use crate::store::DatasetRow;

/// The wire form of a stored dataset.
pub fn dataset_to_proto(row: &DatasetRow) -> v1::Dataset {
    v1::Dataset {
        name: DatasetName::from_id(row.id.as_str()).to_string(),
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

/// Structured upload records as tracks (vehicles in first-appearance order), in time linear in
/// the records (each vehicle's track found by its id).
fn tracks_from_records(records: Vec<v1::LabelledSample>) -> Result<Vec<Track>, Status> {
    let mut tracks: Vec<Track> = Vec::new();
    let mut track_of: HashMap<String, usize> = HashMap::new();
    for (i, r) in records.into_iter().enumerate() {
        let sample = r
            .sample
            .as_ref()
            .ok_or_else(|| invalid_field(format!("records[{i}].sample"), "required"))?;
        let sample = sample_from_proto(sample).map_err(|unknown| {
            invalid_argument(
                unknown
                    .into_iter()
                    .map(|v| (format!("records[{i}].sample.{}", v.field), v.description))
                    .collect(),
            )
        })?;
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
            warmup: false,
        };
        match track_of.get(&r.vehicle_id) {
            Some(&index) => tracks[index].records.push(record),
            None => {
                track_of.insert(r.vehicle_id.clone(), tracks.len());
                tracks.push(Track {
                    vehicle_id: r.vehicle_id,
                    records: vec![record],
                });
            }
        }
    }
    Ok(tracks)
}

/// The DatasetService implementation.
#[derive(Debug, Clone)]
pub struct DatasetApi {
    pub catalog: Catalog,
    /// How long an upload may send nothing.
    pub stream_idle: StreamIdle,
    /// KiB of upload bytes all uploads together may buffer (`--upload-memory-mib`).
    pub upload_budget: Arc<Semaphore>,
}

/// The part of the upload memory budget an upload holds, grown as its bytes arrive.
struct UploadHold {
    budget: Arc<Semaphore>,
    held: Option<OwnedSemaphorePermit>,
}

impl UploadHold {
    /// Takes `bytes` more of the budget, or refuses the upload (RESOURCE_EXHAUSTED) when the
    /// uploads in progress hold it all: an upload never waits for memory, so it never holds part
    /// of the budget while it waits for the rest.
    fn grow(&mut self, bytes: usize) -> Result<(), Status> {
        let kib = u32::try_from(bytes.div_ceil(1024)).unwrap_or(u32::MAX);
        let more = Arc::clone(&self.budget)
            .try_acquire_many_owned(kib)
            .map_err(|_| {
                resource_exhausted(
                    "the uploads in progress hold the server's upload memory (--upload-memory-mib); retry later",
                )
            })?;
        match &mut self.held {
            Some(held) => held.merge(more),
            None => self.held = Some(more),
        }
        Ok(())
    }
}

#[tonic::async_trait]
impl DatasetService for DatasetApi {
    async fn upload_dataset(
        &self,
        request: Request<Streaming<v1::UploadDatasetRequest>>,
    ) -> Result<Response<v1::Dataset>, Status> {
        // An upload may take minutes: a change of the identity files that no longer admits the
        // caller ends it, and nothing is stored.
        let mut caller = Caller::of(&request)?;
        let mut stream = request.into_inner();
        let idle = self.stream_idle;
        let header = match caller.unless_revoked(None, idle.next(&mut stream)).await? {
            Some(v1::UploadDatasetRequest {
                kind: Some(Kind::Header(h)),
            }) => h,
            _ => return Err(header_first()),
        };
        let mut csv = Content::default();
        let mut structured = Vec::new();
        let mut hold = UploadHold {
            budget: Arc::clone(&self.upload_budget),
            held: None,
        };
        while let Some(message) = caller.unless_revoked(None, idle.next(&mut stream)).await? {
            hold.grow(message.encoded_len())?;
            match message.kind {
                Some(Kind::CsvChunk(chunk)) if structured.is_empty() => {
                    if csv.len() + chunk.len() > MAX_DATASET_BYTES {
                        return Err(invalid_field(
                            "csv_chunk",
                            format!("dataset exceeds {MAX_DATASET_BYTES} bytes"),
                        ));
                    }
                    csv.extend(&chunk);
                }
                Some(Kind::Records(batch)) if csv.is_empty() => {
                    if structured.len() + batch.records.len() > MAX_DATASET_RECORDS {
                        return Err(invalid_field(
                            "records",
                            format!("more than {MAX_DATASET_RECORDS} records"),
                        ));
                    }
                    structured.extend(batch.records);
                }
                Some(Kind::Header(_)) => return Err(header_not_first()),
                _ => {
                    return Err(invalid_field(
                        "kind",
                        "send either csv_chunk messages or records messages, not both",
                    ));
                }
            }
        }
        let name = display_name("header.display_name", &header.display_name)?;
        caller.check_standing(None)?;
        let row = if structured.is_empty() {
            self.catalog.upload(name, csv.finish(), "csv_chunk").await?
        } else {
            let tracks = self
                .catalog
                .heavy()
                .run(|| tracks_from_records(structured))
                .await?;
            self.catalog.upload_tracks(name, &tracks).await?
        };
        Ok(Response::new(dataset_to_proto(&row)))
    }

    async fn import_dataset(
        &self,
        request: Request<v1::ImportDatasetRequest>,
    ) -> Result<Response<v1::Dataset>, Status> {
        let r = request.into_inner();
        let name = display_name("display_name", &r.display_name)?;
        let row = self.catalog.import(&r.path, name).await?;
        Ok(Response::new(dataset_to_proto(&row)))
    }

    async fn list_datasets(
        &self,
        request: Request<v1::ListDatasetsRequest>,
    ) -> Result<Response<v1::ListDatasetsResponse>, Status> {
        let r = request.into_inner();
        let page = self
            .catalog
            .list(&page_request(r.page_size, &r.page_token)?)
            .await?;
        Ok(Response::new(v1::ListDatasetsResponse {
            datasets: page.items.iter().map(dataset_to_proto).collect(),
            next_page_token: page.next_page_token.unwrap_or_default(),
        }))
    }

    async fn get_dataset(
        &self,
        request: Request<v1::GetDatasetRequest>,
    ) -> Result<Response<v1::Dataset>, Status> {
        let name = dataset_name("name", &request.into_inner().name)?;
        Ok(Response::new(dataset_to_proto(
            &self.catalog.get(&name).await?,
        )))
    }

    async fn delete_dataset(
        &self,
        request: Request<v1::DeleteDatasetRequest>,
    ) -> Result<Response<()>, Status> {
        let name = dataset_name("name", &request.into_inner().name)?;
        self.catalog.delete(&name).await?;
        Ok(Response::new(()))
    }
}
