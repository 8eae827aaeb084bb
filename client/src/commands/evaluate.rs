//! `spoofwatch evaluate`: score a model artifact on labelled data.

use std::path::PathBuf;
use std::sync::Arc;

use anyhow::{Context, Result};
use spoofwatch_core::evaluation::{Evaluation, evaluate_tracks};
use spoofwatch_core::model::artifact::ModelArtifact;

use super::{RulesArg, write_json};
use crate::input::load_tracks;
use crate::report::{delays, metrics_table};

#[derive(Debug, clap::Args)]
pub struct Args {
    /// Model artifact (JSON) written by `spoofwatch train`.
    #[arg(long)]
    model: PathBuf,
    /// Labelled recorded data (AV-GPS or telemetry CSV).
    #[arg(long, required = true, num_args = 1..)]
    data: Vec<PathBuf>,
    /// Write the metrics as JSON here.
    #[arg(long)]
    json: Option<PathBuf>,
    /// Write per-row probabilities and alarms as CSV here.
    #[arg(long)]
    rows: Option<PathBuf>,
    /// Event rules for ADR and delays.
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
    let artifact = load_artifact(&args.model)?;
    let tracks = load_tracks(&args.data)?;
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
            "model": args.model.display().to_string(),
            "operating_point": op,
            "overall": evaluation.overall,
            "per_vehicle": per_vehicle,
        });
        write_json(path, &doc)?;
    }
    if let Some(path) = &args.rows {
        write_rows(path, &evaluation)?;
    }
    Ok(())
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
