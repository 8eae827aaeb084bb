//! `spoofwatch`: the Spoofwatch command-line client (offline experiments and the gRPC commands).

mod commands;

use std::process::ExitCode;

use clap::Parser;
// The offline commands refer to these as `crate::input` etc.; they live in the library.
use spoofwatch_client::{input, progress, report};

fn main() -> ExitCode {
    let cli = commands::Cli::parse();
    match commands::run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(err) => {
            eprintln!("error: {err:#}");
            ExitCode::FAILURE
        }
    }
}
