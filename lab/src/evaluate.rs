//! `spoofwatch-lab evaluate`: the operator's `evaluate` (its flags, scoring, tables and files come
//! from the client library), plus `--plot`: the SVG trace of one vehicle drawn from the same
//! evaluation. It owns only choosing that vehicle and drawing its trace.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use spoofwatch_client::cli::evaluate::{self as operator, Offline};
use spoofwatch_core::evaluation::Evaluation;
use spoofwatch_core::sample::Track;

use crate::figures;

// No group of its own: the flattened operator `Args` already names one `Args`.
#[derive(Debug, clap::Args)]
#[group(skip)]
pub struct Args {
    #[command(flatten)]
    evaluate: operator::Args,
    /// Draw the trace of one vehicle (p̂ with θ, confirmed alarm, truth, why the detector says so,
    /// the recording's own detector when it has one, evidence channels, and with offset evidence
    /// the slow anchor's offset against its 5σ gate) as SVG here.
    #[arg(long, conflicts_with = "server")]
    plot: Option<PathBuf>,
    /// The vehicle whose trace --plot draws (default: the first).
    #[arg(long, requires = "plot")]
    plot_vehicle: Option<String>,
}

pub fn run(args: Args) -> Result<()> {
    let Some(path) = args.plot else {
        return operator::run(args.evaluate);
    };
    let offline = Offline::load(args.evaluate)?;
    // Before evaluating, so that a wrong --plot-vehicle fails at once.
    let index = plot_track_index(&offline.tracks, args.plot_vehicle.as_deref())?;
    let evaluation = offline.score()?;
    let theta = offline.artifact.operating_point.theta;
    let svg = vehicle_trace_svg(&offline.tracks, index, &evaluation, &offline.model, theta)?;
    std::fs::write(&path, svg).with_context(|| format!("writing {}", path.display()))?;
    println!("trace figure written to {}", path.display());
    Ok(())
}

/// The index of the track of `vehicle` (default: the first track).
fn plot_track_index(tracks: &[Track], vehicle: Option<&str>) -> Result<usize> {
    let Some(id) = vehicle else {
        anyhow::ensure!(!tracks.is_empty(), "the data has no vehicle to plot");
        return Ok(0);
    };
    tracks
        .iter()
        .position(|t| t.vehicle_id == id)
        .with_context(|| {
            let known: Vec<&str> = tracks.iter().map(|t| t.vehicle_id.as_str()).collect();
            format!("no vehicle {id:?} in the data; it has {}", known.join(", "))
        })
}

/// The SVG trace of the `index`-th track.
fn vehicle_trace_svg(
    tracks: &[Track],
    index: usize,
    evaluation: &Evaluation,
    model: &Path,
    theta: f64,
) -> Result<String> {
    let track = tracks.get(index).context("no track to plot")?;
    // `evaluate_tracks` writes the rows track after track.
    let start: usize = tracks[..index].iter().map(|t| t.records.len()).sum();
    let rows = evaluation
        .rows
        .get(start..start + track.records.len())
        .context("the evaluation has fewer rows than the data")?;
    let title = format!("{} — model {}", track.vehicle_id, model.display());
    let trace = figures::trace_of(title, rows, &track.records, theta)?;
    figures::trace_svg(&trace)
}
