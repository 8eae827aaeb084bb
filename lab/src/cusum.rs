//! `spoofwatch-lab cusum`: the classical χ²/CUSUM comparator (SPEC §9).
//!
//! It owns the fit and the report of one comparator run, not the comparator (core's `cusum`).

use std::path::PathBuf;

use anyhow::{Context, Result};
use spoofwatch_client::cli::flags::{ProjectionArg, RulesArg};
use spoofwatch_client::cli::json::write_json;
use spoofwatch_client::input::load_tracks;
use spoofwatch_client::report::{delays, metrics_table};
use spoofwatch_core::alarm::OperatingPointRule;
use spoofwatch_core::cusum::fit_cusum_comparator;
use spoofwatch_core::train::data::split_chronologically;
use spoofwatch_core::train::spec::SplitFractions;

#[derive(Debug, clap::Args)]
pub struct Args {
    /// Labelled data to fit on. Σ̂ and μ_e come from its chronological training part (70% of each
    /// trajectory) and (k, h, N_p) from the next 15%, unless --val is given.
    #[arg(long, required = true, num_args = 1..)]
    train: Vec<PathBuf>,
    /// Labelled validation data for (k, h, N_p); then all of --train fits Σ̂ and μ_e.
    #[arg(long, num_args = 1..)]
    val: Vec<PathBuf>,
    /// Labelled data to score.
    #[arg(long, required = true, num_args = 1..)]
    data: Vec<PathBuf>,
    /// Write the fitted parameters and metrics as JSON here.
    #[arg(long)]
    json: Option<PathBuf>,
    #[arg(long, value_enum, default_value_t)]
    projection: ProjectionArg,
    #[arg(long, value_enum, default_value_t)]
    rules: RulesArg,
}

pub fn run(args: Args) -> Result<()> {
    let train = load_tracks(&args.train)?;
    let (fit_tracks, val_tracks) = if args.val.is_empty() {
        let split = split_chronologically(&train, SplitFractions::default());
        (split.train, split.validation)
    } else {
        (train, load_tracks(&args.val)?)
    };
    let comparator = fit_cusum_comparator(
        &fit_tracks,
        &val_tracks,
        args.projection.into(),
        OperatingPointRule::BestValidationF1,
    )
    .context("fitting the CUSUM comparator")?;
    let data = load_tracks(&args.data)?;
    let metrics = comparator.score_tracks(&data).metrics(args.rules.into());
    let c = &comparator.cusum;
    println!(
        "CUSUM: mu_e = {:.4}, drift k = {}, threshold h = {:.4}, N_p = {}",
        c.mu_e, c.drift_k, c.threshold_h, c.n_p
    );
    print!("{}", metrics_table(&[("data".to_string(), &metrics)]));
    println!("event delays (s): {}", delays(&metrics));
    if let Some(path) = &args.json {
        write_json(
            path,
            &serde_json::json!({ "comparator": comparator, "metrics": metrics }),
        )?;
    }
    Ok(())
}
