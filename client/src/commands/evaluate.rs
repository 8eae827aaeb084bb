//! `spoofwatch evaluate`: score a model artifact on labelled data, or (`--server`) run an
//! evaluation job on a server (`remote::evaluate`).

use std::path::{Path, PathBuf};
use std::sync::Arc;

use anyhow::{Context, Result};
use spoofwatch_core::evaluation::{Evaluation, evaluate_tracks};
use spoofwatch_core::model::artifact::ModelArtifact;
use spoofwatch_core::sample::Track;

use super::{RulesArg, write_json};
use crate::figures;
use crate::input::load_tracks;
use crate::report::{delays, metrics_table};

#[derive(Debug, clap::Args)]
pub struct Args {
    /// Model artifact (JSON) written by `spoofwatch train`; with --server a stored model
    /// (`models/{id}` or `{id}`, default: the active model).
    #[arg(long, required_unless_present = "server")]
    model: Option<String>,
    /// Labelled recorded data (AV-GPS or telemetry CSV).
    #[arg(long, num_args = 1.., required_unless_present = "server", conflicts_with = "server")]
    data: Vec<PathBuf>,
    /// Evaluate on this Spoofwatch server (an evaluation job over its --dataset's) instead of
    /// locally. Deliberately not read from SPOOFWATCH_SERVER, so offline evaluation stays offline.
    #[arg(long, requires = "datasets")]
    server: Option<String>,
    /// Bearer token for the server.
    #[arg(long, env = "SPOOFWATCH_TOKEN", hide_env_values = true)]
    token: Option<String>,
    #[command(flatten)]
    transport: super::remote::TransportArgs,
    /// Remote mode: stored datasets to score (`datasets/{id}` or `{id}`).
    #[arg(long = "dataset", num_args = 1.., requires = "server")]
    datasets: Vec<String>,
    /// Write the metrics as JSON here.
    #[arg(long, conflicts_with = "server")]
    json: Option<PathBuf>,
    /// Write per-row probabilities and alarms as CSV here.
    #[arg(long, conflicts_with = "server")]
    rows: Option<PathBuf>,
    /// Draw the trace of one vehicle (p̂ with θ, confirmed alarm, truth, the recording's own
    /// detector when it has one, evidence channels) as SVG here.
    #[arg(long, conflicts_with = "server")]
    plot: Option<PathBuf>,
    /// The vehicle whose trace --plot draws (default: the first).
    #[arg(long, requires = "plot")]
    plot_vehicle: Option<String>,
    /// Event rules for ADR and delays (offline; a server job uses SPEC §8's).
    #[arg(long, value_enum, default_value_t)]
    rules: RulesArg,
}

pub fn load_artifact(path: &PathBuf) -> Result<Arc<ModelArtifact>> {
    let file = std::fs::File::open(path).with_context(|| format!("opening {}", path.display()))?;
    let artifact = ModelArtifact::read(std::io::BufReader::new(file))
        .with_context(|| format!("loading model {}", path.display()))?;
    Ok(Arc::new(artifact))
}

pub fn run(args: Args) -> Result<()> {
    if let Some(server) = args.server {
        let job = super::remote::evaluate::Job {
            server,
            connect: args.transport.options(args.token),
            model: args.model.unwrap_or_default(),
            datasets: args.datasets,
        };
        return super::remote::block_on(super::remote::evaluate::run(job));
    }
    let Some(model) = args.model.as_deref().map(PathBuf::from) else {
        anyhow::bail!("--model is required for offline evaluation");
    };
    let artifact = load_artifact(&model)?;
    let tracks = load_tracks(&args.data)?;
    // Before evaluating, so that a wrong --plot-vehicle fails at once.
    let plot_index = args
        .plot
        .as_ref()
        .map(|_| plot_track_index(&tracks, args.plot_vehicle.as_deref()))
        .transpose()?;
    let evaluation = evaluate_tracks(&artifact, &tracks, args.rules.into());
    let op = artifact.operating_point;
    println!("operating point: theta = {:.2}, N_p = {}", op.theta, op.n_p);
    let mut table = vec![("overall".to_string(), &evaluation.overall)];
    table.extend(evaluation.per_vehicle.iter().map(|(v, m)| (v.clone(), m)));
    print!("{}", metrics_table(&table));
    println!("event delays (s): {}", delays(&evaluation.overall));
    if let Some(path) = &args.json {
        let per_vehicle: serde_json::Map<String, serde_json::Value> = evaluation
            .per_vehicle
            .iter()
            .map(|(v, m)| Ok((v.clone(), serde_json::to_value(m)?)))
            .collect::<Result<_, serde_json::Error>>()?;
        let doc = serde_json::json!({
            "model": model.display().to_string(),
            "operating_point": op,
            "overall": evaluation.overall,
            "per_vehicle": per_vehicle,
        });
        write_json(path, &doc)?;
    }
    if let Some(path) = &args.rows {
        write_rows(path, &evaluation)?;
    }
    if let (Some(path), Some(index)) = (&args.plot, plot_index) {
        let svg = vehicle_trace_svg(&tracks, index, &evaluation, &model, op.theta)?;
        std::fs::write(path, svg).with_context(|| format!("writing {}", path.display()))?;
        println!("trace figure written to {}", path.display());
    }
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

fn write_rows(path: &PathBuf, evaluation: &Evaluation) -> Result<()> {
    let mut out =
        csv::Writer::from_path(path).with_context(|| format!("creating {}", path.display()))?;
    out.write_record([
        "vehicle_id",
        "line",
        "trajectory",
        "time_s",
        "label",
        "nu",
        "probability",
        "positive",
        "alarm",
        "alarm_onset",
    ])?;
    for row in &evaluation.rows {
        let d = &row.decision;
        let flag = |b: bool| if b { "1" } else { "0" }.to_string();
        out.write_record([
            row.vehicle_id.clone(),
            row.line.to_string(),
            d.evidence.trajectory.to_string(),
            row.time_s.to_string(),
            row.label.map_or(String::new(), flag),
            flag(d.evidence.valid),
            d.probability.to_string(),
            flag(d.positive),
            flag(d.alarm),
            flag(d.alarm_onset),
        ])?;
    }
    out.flush()?;
    Ok(())
}
