//! The CLI's commands: offline ones call `spoofwatch-core` directly, the remote ones (`remote/`)
//! talk gRPC to a server through the `spoofwatch_client` library.
//!
//! It owns the command-line shape and dispatch, not any command's logic.

mod cusum;
mod evaluate;
mod evidence;
mod experiment;
mod remote;
mod scenario;
mod train;
mod training_flags;

#[cfg(test)]
mod tests;

use clap::{Parser, Subcommand, ValueEnum};
use spoofwatch_core::geo::Projection;
use spoofwatch_core::metrics::EventRules;

/// Spoofwatch: GNSS-spoofing detection for vehicle fleets (HO-LLN liquid evidence detector).
#[derive(Debug, Parser)]
#[command(name = "spoofwatch", version, about, long_about = None)]
pub struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Per-row causal evidence (δt, ν, r, η, η̇, η̈, q, a, ã) of recorded data, as CSV.
    Evidence(evidence::Args),
    /// Generate labelled subtle-attack scenarios (telemetry CSV).
    #[command(subcommand)]
    Scenario(scenario::Command),
    /// Fit the classical χ²/CUSUM comparator and report its metrics.
    Cusum(cusum::Args),
    /// Train an HO-LLN detector and write its model artifact.
    Train(train::Args),
    /// Score a model artifact on labelled data (or a stored model on a server's datasets).
    Evaluate(evaluate::Args),
    /// Reproducible experiments (reports in an output directory).
    #[command(subcommand)]
    Experiment(experiment::Command),
    /// Check that a server is serving (grpc.health.v1; exit status 0 when SERVING).
    Health(remote::health::Args),
    /// Replay recorded data to a server over StreamDetect, one stream per vehicle.
    Detect(remote::detect::Args),
    /// Manage datasets on a server.
    Datasets(remote::datasets::Args),
    /// Manage training and evaluation jobs on a server.
    Jobs(remote::jobs::Args),
    /// Manage the models on a server.
    Models(remote::models::Args),
    /// Inspect and reset the vehicle sessions a server holds in memory.
    Sessions(remote::sessions::Args),
    /// The fleet's confirmed alarms on a server: list the stored ones, watch onsets and ends.
    Alarms(remote::alarms::Args),
    /// Live demo: an in-process server detecting a simulated drive with a GNSS drift attack.
    Demo(remote::demo::Args),
    /// Load benchmark over loopback: throughput, batch latency and per-session memory.
    Bench(remote::bench::Args),
}

/// Runs the parsed command.
pub fn run(cli: Cli) -> anyhow::Result<()> {
    match cli.command {
        Command::Evidence(args) => evidence::run(args),
        Command::Scenario(cmd) => scenario::run(cmd),
        Command::Cusum(args) => cusum::run(args),
        Command::Train(args) => train::run(args),
        Command::Evaluate(args) => evaluate::run(args),
        Command::Experiment(cmd) => experiment::run(cmd),
        Command::Health(args) => remote::block_on(remote::health::run(args)),
        Command::Detect(args) => remote::block_on(remote::detect::run(args)),
        Command::Datasets(args) => remote::block_on(remote::datasets::run(args)),
        Command::Jobs(args) => remote::block_on(remote::jobs::run(args)),
        Command::Models(args) => remote::block_on(remote::models::run(args)),
        Command::Sessions(args) => remote::block_on(remote::sessions::run(args)),
        Command::Alarms(args) => remote::block_on(remote::alarms::run(args)),
        Command::Demo(args) => remote::block_on(remote::demo::run(args)),
        Command::Bench(args) => remote::block_on(remote::bench::run(args)),
    }
}

/// Local east/north frame used for GNSS displacements.
#[derive(Clone, Copy, Debug, Default, ValueEnum)]
pub enum ProjectionArg {
    /// WGS-84 meridian/prime-vertical radii at the previous fix (default).
    #[default]
    Wgs84,
    /// The reference code's spherical equirectangular frame (R = 6,378,137 m).
    Equirectangular,
}

impl From<ProjectionArg> for Projection {
    fn from(p: ProjectionArg) -> Self {
        match p {
            ProjectionArg::Wgs84 => Projection::Wgs84Local,
            ProjectionArg::Equirectangular => Projection::Equirectangular,
        }
    }
}

/// Event rules for ADR/delay.
#[derive(Clone, Copy, Debug, Default, ValueEnum)]
pub enum RulesArg {
    /// SPEC §8: label-continuity events, detection needs a new alarm onset.
    #[default]
    Spec,
    /// The paper's legacy evaluator (events split at ν = 0, earlier alarms count with delay 0).
    Legacy,
}

impl From<RulesArg> for EventRules {
    fn from(r: RulesArg) -> Self {
        match r {
            RulesArg::Spec => EventRules::Spec,
            RulesArg::Legacy => EventRules::Legacy,
        }
    }
}

/// Writes pretty JSON to a file.
fn write_json<T: serde::Serialize>(path: &std::path::Path, value: &T) -> anyhow::Result<()> {
    use anyhow::Context;
    let file =
        std::fs::File::create(path).with_context(|| format!("creating {}", path.display()))?;
    serde_json::to_writer_pretty(std::io::BufWriter::new(file), value)
        .with_context(|| format!("writing {}", path.display()))
}
