//! `spoofwatch datasets`: upload, import, list, get and delete labelled recordings on the server.
//!
//! It owns how datasets are described and uploaded; paging and tables come from `remote`.

use std::path::PathBuf;

use crate::error::reply;
use crate::retry::{self, Idempotency};
use anyhow::Result;
use spoofwatch_proto::v1;
use spoofwatch_proto::v1::upload_dataset_request::Kind as UploadKind;

use super::{
    ResourceArgs, UPLOAD_CHUNK_BYTES, all_pages, bytes, display_name, print_table, read_upload,
    time,
};

/// `spoofwatch {resource} <command>` with the server flags.
pub type Args = ResourceArgs<Command>;

#[derive(Debug, clap::Subcommand)]
pub enum Command {
    /// Upload a CSV file (AV-GPS or telemetry format) in 1 MiB chunks.
    Upload {
        /// The CSV file.
        #[arg(long)]
        file: PathBuf,
        /// Display name (default: the file name).
        #[arg(long)]
        name: Option<String>,
    },
    /// Import a CSV file from the server's data directory.
    Import {
        /// Path relative to the server's data directory, e.g. `AV-GPS-Dataset-2.csv`.
        #[arg(long)]
        path: String,
        /// Display name (default: chosen by the server).
        #[arg(long)]
        name: Option<String>,
    },
    /// List datasets, newest first.
    List,
    /// Show one dataset.
    Get {
        /// `datasets/{id}` or `{id}`.
        name: String,
    },
    /// Delete a dataset.
    Delete {
        /// `datasets/{id}` or `{id}`.
        name: String,
    },
}

/// The upload messages: the header, then the file in chunks of at most 1 MiB.
pub fn upload_requests(display_name: String, content: &[u8]) -> Vec<v1::UploadDatasetRequest> {
    let header = v1::UploadDatasetRequest {
        kind: Some(UploadKind::Header(v1::UploadDatasetHeader { display_name })),
    };
    std::iter::once(header)
        .chain(
            content
                .chunks(UPLOAD_CHUNK_BYTES)
                .map(|chunk| v1::UploadDatasetRequest {
                    kind: Some(UploadKind::CsvChunk(chunk.to_vec())),
                }),
        )
        .collect()
}

fn describe(d: &v1::Dataset) -> String {
    format!(
        "{}\n  display name  {}\n  source        {}\n  format        {}\n  rows          {} ({} labelled, {} spoofed)\n  \
         vehicles      {}\n  size          {}\n  sha256        {}\n  created       {}",
        d.name,
        d.display_name,
        d.source,
        d.format,
        d.rows,
        d.labelled_rows,
        d.spoofed_rows,
        d.vehicles,
        bytes(d.size_bytes),
        d.sha256,
        time(d.create_time.as_ref()),
    )
}

pub async fn run(args: Args) -> Result<()> {
    let connection = args.server.connect().await?;
    let mut client = connection.datasets();
    match args.command {
        Command::Upload { file, name } => {
            let content = read_upload(&file)?;
            let requests = upload_requests(display_name(name.as_deref(), &file), &content);
            let upload = client.upload_dataset(tokio_stream::iter(requests));
            let dataset = reply(format!("uploading {}", file.display()), upload).await?;
            println!("uploaded {}", describe(&dataset));
        }
        Command::Import { path, name } => {
            let request = v1::ImportDatasetRequest {
                path: path.clone(),
                display_name: name.unwrap_or_default(),
            };
            // Not idempotent (each import makes a dataset): retried only when refused.
            let dataset = retry::unary(
                format!("importing {path}"),
                Idempotency::NotIdempotent,
                async || client.import_dataset(request.clone()).await,
            )
            .await?;
            println!("imported {}", describe(&dataset));
        }
        Command::List => {
            let datasets = all_pages(
                "listing datasets",
                // Page size 0: the server's default.
                async |page_token| {
                    let request = v1::ListDatasetsRequest {
                        page_token,
                        ..Default::default()
                    };
                    client.list_datasets(request).await
                },
                |page| (page.datasets, page.next_page_token),
            )
            .await?;
            print_table(
                &[
                    "name", "display", "format", "rows", "vehicles", "spoofed", "size", "created",
                ],
                &datasets,
                |d| {
                    vec![
                        d.name.clone(),
                        d.display_name.clone(),
                        d.format.clone(),
                        d.rows.to_string(),
                        d.vehicles.to_string(),
                        d.spoofed_rows.to_string(),
                        bytes(d.size_bytes),
                        time(d.create_time.as_ref()),
                    ]
                },
            );
        }
        Command::Get { name } => {
            let request = v1::GetDatasetRequest { name: name.clone() };
            let dataset = retry::unary(
                format!("getting {name}"),
                Idempotency::Idempotent,
                async || client.get_dataset(request.clone()).await,
            )
            .await?;
            println!("{}", describe(&dataset));
        }
        Command::Delete { name } => {
            let request = v1::DeleteDatasetRequest { name: name.clone() };
            retry::unary(
                format!("deleting {name}"),
                Idempotency::Idempotent,
                async || client.delete_dataset(request.clone()).await,
            )
            .await?;
            println!("deleted {name}");
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_upload_is_a_header_then_one_mebibyte_chunks() {
        let content = vec![b'x'; 2 * UPLOAD_CHUNK_BYTES + 5];
        let requests = upload_requests("d".into(), &content);
        assert_eq!(requests.len(), 4);
        assert!(matches!(
            &requests[0].kind,
            Some(UploadKind::Header(h)) if h.display_name == "d"
        ));
        let sizes: Vec<usize> = requests[1..]
            .iter()
            .map(|r| match &r.kind {
                Some(UploadKind::CsvChunk(c)) => c.len(),
                other => panic!("expected a chunk, got {other:?}"),
            })
            .collect();
        assert_eq!(sizes, vec![UPLOAD_CHUNK_BYTES, UPLOAD_CHUNK_BYTES, 5]);
    }
}
