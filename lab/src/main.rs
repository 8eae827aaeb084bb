//! `spoofwatch-lab`: the research command line. The standard experiments and their figures, the
//! classical comparator, an evaluation that also draws a vehicle's trace, and the demo and load
//! benchmark against a server started in this process.
//!
//! It parses the command line and dispatches; commands shared with the operator's `spoofwatch`
//! come from the client library's `cli` module and are never copied here. Not shipped in the
//! container image.

mod bench;
mod cusum;
mod demo;
mod evaluate;
mod experiment;
mod figures;

use std::process::ExitCode;

use clap::{Parser, Subcommand};
use spoofwatch_client::cli::{exit, remote};

/// Spoofwatch research tools: experiments, comparators, figures, and an in-process server.
#[derive(Debug, Parser)]
#[command(name = "spoofwatch-lab", version, about, long_about = None)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Reproducible experiments (reports and figures in an output directory).
    #[command(subcommand)]
    Experiment(experiment::Command),
    /// Fit the classical χ²/CUSUM comparator and report its metrics.
    Cusum(cusum::Args),
    /// `spoofwatch evaluate`, and with --plot the SVG trace of one vehicle.
    Evaluate(evaluate::Args),
    /// Live demo: a simulated drive with a GNSS drift attack, detected by an in-process server
    /// (or --server).
    Demo(remote::demo::Args),
    /// Load benchmark over loopback against an in-process server (or --server): throughput, batch
    /// latency and per-session memory.
    Bench(remote::bench::Args),
}

fn main() -> ExitCode {
    let result = match Cli::parse().command {
        Command::Experiment(cmd) => experiment::run(cmd),
        Command::Cusum(args) => cusum::run(args),
        Command::Evaluate(args) => evaluate::run(args),
        Command::Demo(args) => remote::block_on(demo::run(args)),
        Command::Bench(args) => remote::block_on(bench::run(args)),
    };
    exit::exit_code(result)
}

#[cfg(test)]
mod tests {
    use clap::CommandFactory;

    #[test]
    fn the_command_line_is_well_formed() {
        super::Cli::command().debug_assert();
    }
}
