//! `spoofwatch demo`: an in-process server, a simulated 6-minute drive with a slow GNSS drift
//! attack, streamed live over StreamDetect with a compact text view, then a summary.
//!
//! This file owns the command line; the demo lives in `drive` and needs the `inprocess` feature
//! (the server crate). Without it the command explains how to get it and does nothing else.

use anyhow::Result;

use super::detect::parse_rate;

#[cfg(feature = "inprocess")]
mod drive;

#[derive(Debug, clap::Args)]
pub struct Args {
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

#[cfg(feature = "inprocess")]
pub async fn run(args: Args) -> Result<()> {
    drive::run(args).await
}

#[cfg(not(feature = "inprocess"))]
pub async fn run(_args: Args) -> Result<()> {
    Err(super::no_in_process_server("demo"))
}
