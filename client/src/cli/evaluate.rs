//! `spoofwatch evaluate`: score a model artifact on labelled data, or (`--server`) run an
//! evaluation job on a server (`remote::evaluate`).
//!
//! Offline it loads ([`Offline::load`]) then scores and reports ([`Offline::score`]) in two steps,
//! so that the research binary can check and draw a vehicle's trace around them. It owns the
//! tables, JSON and row CSV of an evaluation, not the scoring (core's `evaluate_tracks`).

use std::path::PathBuf;
use std::sync::Arc;

use anyhow::{Context, Result};
use spoofwatch_core::evaluation::{Evaluation, evaluate_tracks};
use spoofwatch_core::model::artifact::ModelArtifact;
use spoofwatch_core::sample::Track;

use crate::cli::flags::RulesArg;
use crate::cli::json::write_json;
use crate::cli::remote;
use crate::cli::server_flags::TransportArgs;
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
    transport: TransportArgs,
    /// Remote mode: stored datasets to score (`datasets/{id}` or `{id}`).
    #[arg(long = "dataset", num_args = 1.., requires = "server")]
    datasets: Vec<String>,
    /// Write the metrics as JSON here.
    #[arg(long, conflicts_with = "server")]
    json: Option<PathBuf>,
    /// Write per-row probabilities and alarms as CSV here.
    #[arg(long, conflicts_with = "server")]
    rows: Option<PathBuf>,
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
        let job = remote::evaluate::Job {
            server,
            connect: args.transport.options(args.token),
            model: args.model.unwrap_or_default(),
            datasets: args.datasets,
        };
        return remote::block_on(remote::evaluate::run(job));
    }
    Offline::load(args)?.score()?;
    Ok(())
}

/// An offline evaluation, loaded: the model and the labelled data, and where its outputs go.
pub struct Offline {
    /// The model artifact's path, as given.
    pub model: PathBuf,
    pub artifact: Arc<ModelArtifact>,
    pub tracks: Vec<Track>,
    rules: RulesArg,
    json: Option<PathBuf>,
    rows: Option<PathBuf>,
}

impl Offline {
    /// Loads the model and the data of offline `args`.
    pub fn load(args: Args) -> Result<Self> {
        let Some(model) = args.model.map(PathBuf::from) else {
            anyhow::bail!("--model is required for offline evaluation");
        };
        let artifact = load_artifact(&model)?;
        let tracks = load_tracks(&args.data)?;
        Ok(Self {
            model,
            artifact,
            tracks,
            rules: args.rules,
            json: args.json,
            rows: args.rows,
        })
    }

    /// Scores the data, prints the metrics table and writes --json and --rows.
    pub fn score(&self) -> Result<Evaluation> {
        let evaluation = evaluate_tracks(&self.artifact, &self.tracks, self.rules.into());
        let op = self.artifact.operating_point;
        println!("operating point: theta = {:.2}, N_p = {}", op.theta, op.n_p);
        match &self.artifact.critical {
            Some(test) => println!(
                "critical test: k = {}, h = {} logit·s, decisive hold {} s{}",
                test.reference_logit,
                test.threshold,
                test.decisive_s,
                critical_paths(
                    test.frozen_fix_s,
                    test.held_jump.map(|j| (j.gate, j.hold_s)),
                    test.held_step.map(|s| (s.gate, s.hold_s)),
                    test.held_offset.map(|h| (h.gate, h.hold_s))
                )
            ),
            None => println!("critical test: none (the model raises warnings only)"),
        }
        let mut table = vec![("overall".to_string(), &evaluation.overall)];
        table.extend(evaluation.per_vehicle.iter().map(|(v, m)| (v.clone(), m)));
        if let Some(critical) = &evaluation.critical {
            table.push(("overall, critical".to_string(), critical));
        }
        print!("{}", metrics_table(&table));
        println!("event delays (s): {}", delays(&evaluation.overall));
        if let Some(critical) = &evaluation.critical {
            println!("event delays to critical (s): {}", delays(critical));
        }
        if let Some(path) = &self.json {
            let per_vehicle: serde_json::Map<String, serde_json::Value> = evaluation
                .per_vehicle
                .iter()
                .map(|(v, m)| Ok((v.clone(), serde_json::to_value(m)?)))
                .collect::<Result<_, serde_json::Error>>()?;
            let doc = serde_json::json!({
                "model": self.model.display().to_string(),
                "operating_point": op,
                "overall": evaluation.overall,
                "critical": evaluation.critical,
                "per_vehicle": per_vehicle,
            });
            write_json(path, &doc)?;
        }
        if let Some(path) = &self.rows {
            write_rows(path, &evaluation)?;
        }
        Ok(evaluation)
    }
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
        "severity",
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
            d.severity.map_or(String::new(), |s| s.name().to_string()),
        ])?;
    }
    out.flush()?;
    Ok(())
}

/// The critical test's extra paths as printed after its other parameters: a frozen fix's hold
/// (seconds beyond its first 2 s), a held jump's, a held jump's tested by its arrival step, and a
/// held offset's (gate NIS, hold in seconds); empty without any.
pub fn critical_paths(
    frozen_fix_s: Option<f64>,
    held_jump: Option<(f64, f64)>,
    held_step: Option<(f64, f64)>,
    held_offset: Option<(f64, f64)>,
) -> String {
    let mut paths = String::new();
    if let Some(hold) = frozen_fix_s {
        paths.push_str(&format!(
            ", a frozen fix held {hold} s beyond its first 2 s"
        ));
    }
    if let Some((gate, hold)) = held_jump {
        paths.push_str(&format!(", a jump held {hold} s at NIS {gate} or more"));
    }
    if let Some((gate, hold)) = held_step {
        paths.push_str(&format!(
            ", a jump held {hold} s that arrived at a step NIS of {gate} or more"
        ));
    }
    if let Some((gate, hold)) = held_offset {
        paths.push_str(&format!(", an offset held {hold} s at NIS {gate} or more"));
    }
    paths
}
