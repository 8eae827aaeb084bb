//! `spoofwatch`: the Spoofwatch command-line client (offline experiments and the gRPC commands).
//!
//! It only parses the command line and maps errors to exit codes; commands live in `commands`.

mod commands;

use std::process::ExitCode;

use clap::Parser;
// The offline commands refer to these as `crate::input` etc.; they live in the library.
use spoofwatch_client::{figures, input, progress, report};

fn main() -> ExitCode {
    let cli = commands::Cli::parse();
    match commands::run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        // `spoofwatch evidence ... | head` closes the pipe early: that is not a failure.
        Err(err) if is_broken_pipe(&err) => ExitCode::SUCCESS,
        Err(err) => {
            eprintln!("error: {err:#}");
            ExitCode::FAILURE
        }
    }
}

fn is_broken_pipe(err: &anyhow::Error) -> bool {
    err.chain().any(|cause| {
        cause
            .downcast_ref::<std::io::Error>()
            .is_some_and(|e| e.kind() == std::io::ErrorKind::BrokenPipe)
            || cause
                .downcast_ref::<csv::Error>()
                .is_some_and(|e| matches!(e.kind(), csv::ErrorKind::Io(io) if io.kind() == std::io::ErrorKind::BrokenPipe))
    })
}
