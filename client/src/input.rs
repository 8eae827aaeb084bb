//! Loading recorded data files (AV-GPS or telemetry CSV, detected by header).

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use spoofwatch_core::data::read_path;
use spoofwatch_core::sample::Track;

/// Reads every file and returns all their tracks, in file order.
pub fn load_tracks(paths: &[PathBuf]) -> Result<Vec<Track>> {
    let mut tracks = Vec::new();
    for path in paths {
        tracks.extend(load_file(path)?);
    }
    Ok(tracks)
}

/// Reads one file's tracks.
pub fn load_file(path: &Path) -> Result<Vec<Track>> {
    let recording = read_path(path).with_context(|| format!("loading {}", path.display()))?;
    Ok(recording.tracks)
}
