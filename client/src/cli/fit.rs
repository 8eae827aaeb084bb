//! `spoofwatch fit`: fit the detector to a fleet from its own attack-free recordings, offline or as
//! a job on a server, and show what the fit bought beside the model it started from. The fit itself
//! is core's `fleet_fit`; this command only reads, writes and prints.

use std::path::PathBuf;
use std::sync::atomic::AtomicBool;

use anyhow::{Context, Result, bail};
use spoofwatch_core::fleet_fit::{FleetFitSpec, fit_fleet};
use spoofwatch_core::train::spec::AnchorRebase;
use spoofwatch_proto::v1;
use spoofwatch_proto::wire::fit::fit_report_to_proto;

use crate::cli::evaluate::load_artifact;
use crate::cli::fit_report::render;
use crate::cli::json::write_json;
use crate::cli::training_flags::RemoteTrainingFlags;
use crate::input::load_tracks;

#[derive(Debug, clap::Args)]
pub struct Args {
    /// The fleet's attack-free recordings (AV-GPS or telemetry CSV; rows labelled attacked are left
    /// out). At least an hour of driving of at least two vehicles.
    #[arg(long, num_args = 1.., required_unless_present = "server", conflicts_with = "server")]
    data: Vec<PathBuf>,
    /// Attack-free validation recordings; without them a fifth of the drives (by time) validates.
    #[arg(long, num_args = 1.., conflicts_with = "server")]
    val: Vec<PathBuf>,
    /// The model to start from (its configuration, and its weights unless --from-scratch).
    #[arg(long, default_value = "models/default.json", conflicts_with = "server")]
    model: PathBuf,
    /// Remote mode: the stored model to start from (`models/{id}`); default the active one.
    #[arg(long)]
    starting_model: Option<String>,
    /// Where to write the fitted model artifact.
    #[arg(long, required_unless_present = "server", conflicts_with = "server")]
    out: Option<PathBuf>,
    /// Also write the fit's report as JSON here (offline mode).
    #[arg(long, conflicts_with = "server")]
    report: Option<PathBuf>,
    /// Train new weights instead of starting from the model's.
    #[arg(long)]
    from_scratch: bool,
    /// The recordings' sample rate (Hz): refused when the drives have another.
    #[arg(long)]
    sample_rate_hz: Option<f64>,
    /// Training epochs.
    #[arg(long, default_value_t = 10, value_parser = clap::value_parser!(u32).range(1..=200))]
    epochs: u32,
    /// Seed of the injected attacks and of training.
    #[arg(long, default_value_t = 42)]
    seed: u64,
    #[command(flatten)]
    remote: RemoteTrainingFlags,
}

pub fn run(args: Args) -> Result<()> {
    if let Some(rate) = args.sample_rate_hz
        && !(rate.is_finite() && rate > 0.0 && rate <= 100.0)
    {
        bail!("--sample-rate-hz must be a rate above 0 and up to 100 Hz, got {rate}");
    }
    if args.remote.server.is_some() {
        let request = job_request(&args);
        return crate::cli::remote::block_on(crate::cli::remote::train::run_job(
            &args.remote,
            request,
            args.epochs,
        ));
    }
    let remote_only = args.remote.remote_only_flags_given();
    if !remote_only.is_empty() || args.starting_model.is_some() {
        bail!("remote flags need --server");
    }
    let Some(out) = args.out.clone() else {
        bail!("--out is required for an offline fit");
    };
    run_offline(&args, &out)
}

fn job_request(args: &Args) -> v1::CreateTrainingJobRequest {
    v1::CreateTrainingJobRequest {
        datasets: args.remote.datasets.clone(),
        validation_datasets: args.remote.val_datasets.clone(),
        spec: Some(v1::TrainingSpec {
            seed: args.seed,
            max_epochs: args.epochs,
            ..v1::TrainingSpec::default()
        }),
        display_name: args.remote.name.clone().unwrap_or_default(),
        activate: args.remote.activate,
        fleet_fit: Some(v1::FleetFit {
            starting_model: args.starting_model.clone().unwrap_or_default(),
            from_scratch: args.from_scratch,
            sample_rate_hz: args.sample_rate_hz.unwrap_or(0.0),
        }),
    }
}

fn run_offline(args: &Args, out: &PathBuf) -> Result<()> {
    let starting = load_artifact(&args.model)?;
    let recordings = load_tracks(&args.data)?;
    let validation = if args.val.is_empty() {
        Vec::new()
    } else {
        load_tracks(&args.val)?
    };
    let spec = FleetFitSpec {
        seed: args.seed,
        max_epochs: args.epochs,
        from_scratch: args.from_scratch,
        sample_rate_hz: args.sample_rate_hz,
        data_description: args.data.iter().map(|p| p.display().to_string()).collect(),
        anchor_rebase: AnchorRebase::Margin,
    };
    let bar = crate::progress::bar(u64::from(args.epochs), "fitting");
    let fitted = fit_fleet(
        &spec,
        &recordings,
        &validation,
        &starting,
        &mut |p| {
            bar.inc(1);
            bar.set_message(format!(
                "epoch {} loss {:.4} val {:.4}",
                p.epoch, p.train_loss, p.val_loss
            ));
        },
        &AtomicBool::new(false),
    )
    .context("fitting the detector to the fleet")?;
    bar.finish_and_clear();
    let file = std::fs::File::create(out).with_context(|| format!("creating {}", out.display()))?;
    fitted.artifact.write(std::io::BufWriter::new(file))?;
    if let Some(path) = &args.report {
        write_json(path, &fitted.report)?;
    }
    println!("fitted model written to {}", out.display());
    print!("{}", render(&fit_report_to_proto(&fitted.report)));
    Ok(())
}
