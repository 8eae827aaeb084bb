//! The commands that talk gRPC to a Spoofwatch server, and what they share: the runtime, uploads,
//! paging and listing output.
//!
//! They reach the server only through this library's connection (`Connection`, `DetectStream`);
//! nothing here may depend on the server crate. `demo` and `bench` without `--server` need an
//! in-process server, which only the research binary adds.

pub mod alarms;
pub mod bench;
pub mod datasets;
pub mod demo;
pub mod detect;
pub mod evaluate;
pub mod health;
pub mod incidents;
pub mod jobs;
pub mod models;
pub mod sessions;
pub mod shadow;
pub mod train;

use std::future::Future;
use std::path::Path;
use std::time::Duration;

use crate::cli::server_flags::ServerArgs;
use crate::retry::{self, Idempotency};
use anyhow::{Context, Result};

/// Upload chunk size for datasets and model artifacts (the server's documented chunk size).
pub const UPLOAD_CHUNK_BYTES: usize = 1 << 20;

/// A resource command (`datasets`, `jobs`, `models`): the server flags and one subcommand.
#[derive(Debug, clap::Args)]
pub struct ResourceArgs<C: clap::Subcommand> {
    #[command(flatten)]
    pub server: ServerArgs,
    #[command(subcommand)]
    pub command: C,
}

/// Why `demo` or `bench` without `--server` does not run here: it needs an in-process server,
/// which only the research binary links.
pub fn needs_server(command: &str) -> anyhow::Error {
    anyhow::anyhow!(
        "`spoofwatch {command}` needs --server URL (a running Spoofwatch server); \
         `spoofwatch-lab {command}` runs it against an in-process server"
    )
}

/// Runs a future on a fresh multi-threaded runtime. A short shutdown timeout keeps a pending
/// blocking read (e.g. an unanswered prompt) from holding the process open.
pub fn block_on<F: Future>(future: F) -> F::Output {
    let runtime = match tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
    {
        Ok(runtime) => runtime,
        Err(error) => {
            // Without a runtime no remote command can run; say why and stop.
            eprintln!("error: cannot start the async runtime: {error}");
            std::process::exit(1);
        }
    };
    let output = runtime.block_on(future);
    runtime.shutdown_timeout(Duration::from_millis(200));
    output
}

/// Reads a whole file for a chunked upload. Uploads read the file up front so that an I/O error
/// can never end the request stream early and store a truncated upload.
pub fn read_upload(path: &Path) -> Result<Vec<u8>> {
    std::fs::read(path).with_context(|| format!("reading {}", path.display()))
}

/// The display name of an upload: `--name`, else the file name.
pub fn display_name(name: Option<&str>, path: &Path) -> String {
    name.map(str::to_string).unwrap_or_else(|| {
        path.file_name().map_or_else(
            || path.display().to_string(),
            |n| n.to_string_lossy().into_owned(),
        )
    })
}

/// A protobuf timestamp as RFC 3339, `-` when absent.
pub fn time(timestamp: Option<&prost_types::Timestamp>) -> String {
    timestamp.map_or_else(|| "-".to_string(), |t| t.to_string())
}

/// An optional number with `digits` decimals, `-` when absent.
pub fn opt(value: Option<f64>, digits: usize) -> String {
    value.map_or_else(|| "-".to_string(), |v| format!("{v:.digits$}"))
}

/// A byte count in KiB/MiB.
pub fn bytes(n: u64) -> String {
    match n {
        n if n >= 1 << 20 => format!("{:.1} MiB", n as f64 / f64::from(1u32 << 20)),
        n if n >= 1 << 10 => format!("{:.1} KiB", n as f64 / 1024.0),
        n => format!("{n} B"),
    }
}

/// Every item of a paged listing, fetched page after page under one error `context` (each page
/// retried as [`retry::unary`] does). `fetch(page_token)` makes one List call; `split` takes its
/// page apart into the items and the next page token, which is empty after the last page.
pub async fn all_pages<P, T>(
    context: &str,
    fetch: impl AsyncFnMut(String) -> Result<tonic::Response<P>, tonic::Status>,
    split: impl Fn(P) -> (Vec<T>, String),
) -> Result<Vec<T>> {
    pages_up_to(context, usize::MAX, fetch, split).await
}

/// [`all_pages`], stopping once `limit` items came (and keeping only `limit`).
pub async fn pages_up_to<P, T>(
    context: &str,
    limit: usize,
    mut fetch: impl AsyncFnMut(String) -> Result<tonic::Response<P>, tonic::Status>,
    split: impl Fn(P) -> (Vec<T>, String),
) -> Result<Vec<T>> {
    let mut items = Vec::new();
    let mut page_token = String::new();
    while items.len() < limit {
        let page = retry::unary(context, Idempotency::Idempotent, async || {
            fetch(page_token.clone()).await
        })
        .await?;
        let (page, next_page_token) = split(page);
        items.extend(page);
        if next_page_token.is_empty() {
            break;
        }
        page_token = next_page_token;
    }
    items.truncate(limit);
    Ok(items)
}

/// Prints a listing: one row per item under `header`.
pub fn print_table<T>(header: &[&str], items: &[T], row: impl Fn(&T) -> Vec<String>) {
    let rows: Vec<Vec<String>> = items.iter().map(row).collect();
    print!("{}", text_table(header, &rows));
}

/// Left-aligned text columns, two spaces apart, for listings.
pub fn text_table(header: &[&str], rows: &[Vec<String>]) -> String {
    let mut widths: Vec<usize> = header.iter().map(|h| h.chars().count()).collect();
    for row in rows {
        for (width, cell) in widths.iter_mut().zip(row) {
            *width = (*width).max(cell.chars().count());
        }
    }
    let line = |cells: &mut dyn Iterator<Item = &str>| {
        let padded: Vec<String> = cells
            .zip(&widths)
            .map(|(cell, width)| format!("{cell:<width$}"))
            .collect();
        padded.join("  ").trim_end().to_string() + "\n"
    };
    let mut out = line(&mut header.iter().copied());
    for row in rows {
        out.push_str(&line(&mut row.iter().map(String::as_str)));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn text_tables_align_columns() {
        let table = text_table(
            &["name", "rows"],
            &[
                vec!["datasets/a".into(), "12".into()],
                vec!["b".into(), "3456".into()],
            ],
        );
        assert_eq!(
            table,
            "name        rows\ndatasets/a  12\nb           3456\n"
        );
    }

    #[test]
    fn byte_counts_use_binary_units() {
        assert_eq!(bytes(512), "512 B");
        assert_eq!(bytes(1536), "1.5 KiB");
        assert_eq!(bytes(3 << 20), "3.0 MiB");
    }

    #[test]
    fn the_display_name_defaults_to_the_file_name() {
        let path = Path::new("/data/AV-GPS-Dataset-3.csv");
        assert_eq!(display_name(None, path), "AV-GPS-Dataset-3.csv");
        assert_eq!(display_name(Some("mine"), path), "mine");
    }
}
