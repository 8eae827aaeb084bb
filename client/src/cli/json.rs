//! The JSON files commands write (metrics, reports, summaries): pretty-printed, with the path in
//! every error. Owns only the writing, not what goes in.

use std::path::Path;

use anyhow::Context;

/// Writes pretty JSON to a file.
pub fn write_json<T: serde::Serialize>(path: &Path, value: &T) -> anyhow::Result<()> {
    let file =
        std::fs::File::create(path).with_context(|| format!("creating {}", path.display()))?;
    serde_json::to_writer_pretty(std::io::BufWriter::new(file), value)
        .with_context(|| format!("writing {}", path.display()))
}
