//! The `spoofwatch` command line: its shape ([`Cli`]), dispatch ([`run`]) and the commands
//! themselves. Offline commands call `spoofwatch-core` directly; the remote ones (`remote/`) talk
//! gRPC to a server through this library's connection.
//!
//! The commands are here, in the library, so that the research binary (`spoofwatch-lab`) reuses
//! their argument structs and code and only adds its own commands and an in-process server. This
//! module owns the command-line shape and dispatch, not any command's logic; nothing under it may
//! depend on the server crate.

pub mod evaluate;
pub mod evidence;
pub mod exit;
pub mod fit;
pub mod fit_report;
pub mod flags;
pub mod json;
pub mod remote;
pub mod scenario;
pub mod server_flags;
pub mod train;
pub mod training_flags;

#[cfg(test)]
mod tests;

use clap::{Parser, Subcommand};

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
    /// Train an HO-LLN detector and write its model artifact.
    Train(train::Args),
    /// Fit the detector to a fleet from its attack-free recordings (offline or on a server).
    Fit(fit::Args),
    /// Score a model artifact on labelled data (or a stored model on a server's datasets).
    Evaluate(evaluate::Args),
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
    /// Area incidents on a server (vehicles nearby spoofed alike): list, get, watch.
    Incidents(remote::incidents::Args),
    /// Live demo against --server: a simulated drive with a GNSS drift attack, detected as it streams.
    Demo(remote::demo::Args),
    /// Load benchmark of --server: throughput, batch latency and per-session memory.
    Bench(remote::bench::Args),
}

/// Runs the parsed command.
pub fn run(cli: Cli) -> anyhow::Result<()> {
    match cli.command {
        Command::Evidence(args) => evidence::run(args),
        Command::Scenario(cmd) => scenario::run(cmd),
        Command::Train(args) => train::run(args),
        Command::Fit(args) => fit::run(args),
        Command::Evaluate(args) => evaluate::run(args),
        Command::Health(args) => remote::block_on(remote::health::run(args)),
        Command::Detect(args) => remote::block_on(remote::detect::run(args)),
        Command::Datasets(args) => remote::block_on(remote::datasets::run(args)),
        Command::Jobs(args) => remote::block_on(remote::jobs::run(args)),
        Command::Models(args) => remote::block_on(remote::models::run(args)),
        Command::Sessions(args) => remote::block_on(remote::sessions::run(args)),
        Command::Alarms(args) => remote::block_on(remote::alarms::run(args)),
        Command::Incidents(args) => remote::block_on(remote::incidents::run(args)),
        Command::Demo(args) => remote::block_on(remote::demo::run(args)),
        Command::Bench(args) => remote::block_on(remote::bench::run(args)),
    }
}
