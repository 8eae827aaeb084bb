//! `spoofwatch`: the Spoofwatch operator's command-line client (offline scoring and the gRPC
//! commands against a running server).
//!
//! It only parses the command line and maps the result to an exit status; the commands live in the
//! library's `cli` module. It links no server, no learned baselines and no plotting.

use std::process::ExitCode;

use clap::Parser;
use spoofwatch_client::cli;

fn main() -> ExitCode {
    cli::exit::exit_code(cli::run(cli::Cli::parse()))
}
