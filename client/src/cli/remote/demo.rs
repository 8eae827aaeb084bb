//! `spoofwatch demo --server URL`: a simulated 6-minute drive with a slow GNSS drift attack,
//! streamed live over StreamDetect to a running server with a compact text view, then a summary.
//!
//! This file owns the command line; the drive itself lives in `drive`. Without `--server` the
//! command names `spoofwatch-lab demo`, which runs the same drive against an in-process server.

use anyhow::Result;

use super::detect::parse_rate;
use crate::cli::server_flags::OptionalServerArgs;

pub mod drive;

#[derive(Debug, clap::Args)]
pub struct Args {
    #[command(flatten)]
    pub server: OptionalServerArgs,
    /// Samples streamed per second (the drive is recorded at 1 Hz; 20 plays it 20× faster).
    #[arg(long, default_value_t = 20.0, value_parser = parse_rate)]
    pub rate: f64,
    /// Seed of the simulated drive.
    #[arg(long, default_value_t = 7)]
    pub seed: u64,
    /// Drift velocity of the attack (m/s, 0.05–2).
    #[arg(long, default_value_t = 2.0)]
    pub drift: f64,
}

/// The demo against `--server`.
pub async fn run(args: Args) -> Result<()> {
    let Some(url) = args.server.server.as_deref() else {
        return Err(super::needs_server("demo"));
    };
    let (track, attack) = drive::scenario(args.seed, args.drift)?;
    let options = args.server.options();
    drive::stream_drive(url, &options, &track, &attack, args.rate).await
}
