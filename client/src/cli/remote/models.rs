//! `spoofwatch models`: the server's model registry.
//!
//! It owns how models are described and imported/exported; paging and tables come from `remote`.

use std::io::Write;
use std::path::PathBuf;

use crate::error::{reply, rpc};
use crate::retry::{self, Idempotency};
use anyhow::{Context, Result};
use spoofwatch_proto::v1;
use spoofwatch_proto::v1::import_model_request::Kind as ImportKind;

use super::{
    ResourceArgs, UPLOAD_CHUNK_BYTES, all_pages, bytes, display_name, print_table, read_upload,
    time,
};
use crate::report::metrics_table;

/// `spoofwatch {resource} <command>` with the server flags.
pub type Args = ResourceArgs<Command>;

#[derive(Debug, clap::Subcommand)]
pub enum Command {
    /// List models, newest first (`*` marks the active one).
    List,
    /// Show a model's metadata, operating point, metrics and provenance.
    Get {
        /// `models/{id}` or `{id}`.
        name: String,
    },
    /// Make a model the active one: sessions started or resumed without a model run it.
    Activate {
        /// `models/{id}` or `{id}`.
        name: String,
    },
    /// Delete a model (not the active one); the sessions that run it end.
    Delete {
        /// `models/{id}` or `{id}`.
        name: String,
    },
    /// Download a model artifact (JSON).
    Export {
        /// `models/{id}` or `{id}`.
        name: String,
        /// File to write.
        #[arg(long)]
        out: PathBuf,
    },
    /// Upload a model artifact in 1 MiB chunks.
    Import {
        /// The artifact (JSON, as written by `spoofwatch train` or `models export`).
        #[arg(long)]
        file: PathBuf,
        /// Display name (default: the file name).
        #[arg(long)]
        name: Option<String>,
        /// Make it the active model once stored.
        #[arg(long)]
        activate: bool,
    },
    /// Try a candidate beside the live model before it pages anyone (start, status, stop, alarms).
    #[command(subcommand)]
    Shadow(super::shadow::Command),
}

/// The import messages: the header, then the artifact in chunks of at most 1 MiB.
pub fn import_requests(
    display_name: String,
    activate: bool,
    content: &[u8],
) -> Vec<v1::ImportModelRequest> {
    let header = v1::ImportModelRequest {
        kind: Some(ImportKind::Header(v1::ImportModelHeader {
            display_name,
            activate,
        })),
    };
    std::iter::once(header)
        .chain(
            content
                .chunks(UPLOAD_CHUNK_BYTES)
                .map(|chunk| v1::ImportModelRequest {
                    kind: Some(ImportKind::Chunk(chunk.to_vec())),
                }),
        )
        .collect()
}

/// A model's details with its validation metrics, several lines.
pub fn describe(m: &v1::Model) -> String {
    let mut out = describe_without_metrics(m);
    if let Some(metrics) = &m.validation_metrics {
        out.push_str(&metrics_table(&[("validation", metrics)]));
    }
    out
}

/// The alarm levels a model raises: `warning, critical (...)` with its critical test, or
/// `warning only (no critical level: nothing it raises pages)`.
pub fn severities(m: &v1::Model) -> String {
    match &m.critical {
        Some(c) => format!(
            "warning, critical (k = {}, h = {} logit s, gate NIS {} held {} s{})",
            c.reference_logit,
            c.threshold,
            c.gate,
            c.decisive_s,
            crate::cli::evaluate::critical_paths(
                c.frozen_fix_s,
                c.held_jump.map(|j| (j.gate, j.hold_s)),
                c.held_step.map(|s| (s.gate, s.hold_s)),
                c.held_offset.map(|h| (h.gate, h.hold_s))
            )
        ),
        None => "warning only (no critical level: nothing it raises pages)".to_string(),
    }
}

/// A model's details without the metrics table, several lines.
pub fn describe_without_metrics(m: &v1::Model) -> String {
    let mut out = format!(
        "{}{}\n  display name   {}\n  source         {}\n  created        {}\n",
        m.name,
        if m.active { " (active)" } else { "" },
        m.display_name,
        m.source,
        time(m.create_time.as_ref()),
    );
    if !m.training_operation.is_empty() {
        out.push_str(&format!("  trained by     {}\n", m.training_operation));
    }
    if let Some(op) = &m.operating_point {
        out.push_str(&format!(
            "  operating pt.  theta = {:.3}, N_p = {}\n",
            op.theta, op.persistence
        ));
    }
    out.push_str(&format!("  severities     {}\n", severities(m)));
    out.push_str(&format!(
        "  architecture   {} ({} parameters)\n  artifact       schema {}, {}, sha256 {}\n  \
         provenance     seed {}, {} epochs, {:.1} s, data: {}\n",
        m.architecture,
        m.parameter_count,
        m.schema_version,
        bytes(m.size_bytes),
        m.sha256,
        m.seed,
        m.epochs_run,
        m.train_wall_time_s,
        if m.training_data.is_empty() {
            "-".to_string()
        } else {
            m.training_data.join(", ")
        },
    ));
    if !m.notes.is_empty() {
        out.push_str(&format!("  notes          {}\n", m.notes));
    }
    out
}

pub async fn run(args: Args) -> Result<()> {
    let connection = args.server.connect().await?;
    let mut client = connection.models();
    match args.command {
        Command::List => {
            let models = all_pages(
                "listing models",
                // Page size 0: the server's default.
                async |page_token| {
                    let request = v1::ListModelsRequest {
                        page_token,
                        ..Default::default()
                    };
                    client.list_models(request).await
                },
                |page| (page.models, page.next_page_token),
            )
            .await?;
            let header = [
                "  name",
                "display",
                "source",
                "theta/N_p",
                "severities",
                "val. AUROC",
                "created",
            ];
            print_table(&header, &models, |m| {
                let op = m.operating_point.unwrap_or_default();
                vec![
                    format!("{}{}", if m.active { "* " } else { "  " }, m.name),
                    m.display_name.clone(),
                    m.source.clone(),
                    format!("{:.3}/{}", op.theta, op.persistence),
                    if m.critical.is_some() {
                        "warning+critical"
                    } else {
                        "warning only"
                    }
                    .to_string(),
                    super::opt(m.validation_metrics.as_ref().and_then(|v| v.auroc), 4),
                    time(m.create_time.as_ref()),
                ]
            });
        }
        Command::Get { name } => {
            let request = v1::GetModelRequest { name: name.clone() };
            let model = retry::unary(
                format!("getting {name}"),
                Idempotency::Idempotent,
                async || client.get_model(request.clone()).await,
            )
            .await?;
            print!("{}", describe(&model));
        }
        Command::Activate { name } => {
            let request = v1::SetActiveModelRequest { name: name.clone() };
            let model = retry::unary(
                format!("activating {name}"),
                Idempotency::Idempotent,
                async || client.set_active_model(request.clone()).await,
            )
            .await?;
            println!("{} is now the active model", model.name);
        }
        Command::Delete { name } => {
            let request = v1::DeleteModelRequest { name: name.clone() };
            retry::unary(
                format!("deleting {name}"),
                Idempotency::Idempotent,
                async || client.delete_model(request.clone()).await,
            )
            .await?;
            println!("deleted {name}");
        }
        Command::Export { name, out } => {
            let context = format!("exporting {name}");
            let request = v1::ExportModelRequest { name: name.clone() };
            let mut chunks = reply(context.clone(), client.export_model(request)).await?;
            // Write next to the target and rename at the end: a failed export leaves no partial file.
            let mut partial = out.clone().into_os_string();
            partial.push(".partial");
            let partial = PathBuf::from(partial);
            let mut file = std::io::BufWriter::new(
                std::fs::File::create(&partial)
                    .with_context(|| format!("creating {}", partial.display()))?,
            );
            let mut written = 0u64;
            let result: Result<()> = async {
                while let Some(chunk) = chunks.message().await.map_err(rpc(context.clone()))? {
                    file.write_all(&chunk.data)
                        .with_context(|| format!("writing {}", partial.display()))?;
                    written += chunk.data.len() as u64;
                }
                file.flush()
                    .with_context(|| format!("writing {}", partial.display()))?;
                Ok(())
            }
            .await;
            drop(file);
            if let Err(error) = result {
                let _ = std::fs::remove_file(&partial);
                return Err(error);
            }
            std::fs::rename(&partial, &out)
                .with_context(|| format!("renaming {} to {}", partial.display(), out.display()))?;
            println!("wrote {} ({})", out.display(), bytes(written));
        }
        Command::Import {
            file,
            name,
            activate,
        } => {
            let content = read_upload(&file)?;
            let requests =
                import_requests(display_name(name.as_deref(), &file), activate, &content);
            let import = client.import_model(tokio_stream::iter(requests));
            let model = reply(format!("importing {}", file.display()), import).await?;
            print!("imported {}", describe(&model));
        }
        Command::Shadow(command) => super::shadow::run(client, command).await?,
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_import_is_a_header_then_chunks() {
        let content = vec![b'{'; UPLOAD_CHUNK_BYTES + 1];
        let requests = import_requests("m".into(), true, &content);
        assert_eq!(requests.len(), 3);
        assert!(matches!(
            &requests[0].kind,
            Some(ImportKind::Header(h)) if h.display_name == "m" && h.activate
        ));
        assert!(matches!(&requests[2].kind, Some(ImportKind::Chunk(c)) if c.len() == 1));
    }
}
