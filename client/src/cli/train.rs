//! `spoofwatch train`: train an HO-LLN detector offline and write its artifact.

use std::path::PathBuf;
use std::sync::atomic::AtomicBool;

use anyhow::{Context, Result};
use spoofwatch_core::train::detector::{TrainedDetector, TrainingData, train_detector};
use spoofwatch_core::train::spec::TrainingSpec;

use crate::cli::flags::RulesArg;
use crate::cli::training_flags::{RemoteTrainingFlags, TrainingFlags};
use crate::input::load_tracks;
use crate::report::metrics_table;

#[derive(Debug, clap::Args)]
pub struct Args {
    /// Labelled training data (AV-GPS or telemetry CSV).
    #[arg(long, num_args = 1.., required_unless_present = "server", conflicts_with = "server")]
    data: Vec<PathBuf>,
    /// Labelled validation data. Without it every trajectory of --data is split chronologically
    /// 70/15/15 into train/validation/test parts (SPEC §9) and the test part is reported.
    #[arg(long, num_args = 1.., conflicts_with = "server")]
    val: Vec<PathBuf>,
    /// Where to write the model artifact.
    #[arg(long, required_unless_present = "server", conflicts_with = "server")]
    out: Option<PathBuf>,
    #[command(flatten)]
    model: TrainingFlags,
    /// Event rules for the reported metrics (offline mode).
    #[arg(long, value_enum, default_value_t)]
    rules: RulesArg,
    #[command(flatten)]
    remote: RemoteTrainingFlags,
}

pub fn run(args: Args) -> Result<()> {
    if args.remote.server.is_some() {
        return crate::cli::remote::block_on(crate::cli::remote::train::run(
            args.remote,
            args.model,
        ));
    }
    let remote_only = args.remote.remote_only_flags_given();
    if !remote_only.is_empty() {
        anyhow::bail!(
            "remote-training flags need --server: {}",
            remote_only.join(", ")
        );
    }
    let Some(out) = args.out.clone() else {
        anyhow::bail!("--out is required for offline training");
    };
    run_offline(args, out)
}

fn run_offline(args: Args, out: PathBuf) -> Result<()> {
    let data = TrainingData::split_unless_validation(
        load_tracks(&args.data)?,
        if args.val.is_empty() {
            Vec::new()
        } else {
            load_tracks(&args.val)?
        },
    );
    let names: Vec<String> = args.data.iter().map(|p| p.display().to_string()).collect();
    let spec = args.model.spec(names);
    let trained = train_with_progress(&spec, data, args.model.verbose)?;
    let file =
        std::fs::File::create(&out).with_context(|| format!("creating {}", out.display()))?;
    trained.artifact.write(std::io::BufWriter::new(file))?;

    let op = trained.artifact.operating_point;
    let prov = &trained.artifact.provenance;
    println!(
        "trained {} epochs (best {}), {:.1} s; operating point theta = {:.2}, N_p = {}; wrote {}",
        prov.epochs_run,
        prov.best_epoch,
        prov.train_wall_time_s,
        op.theta,
        op.n_p,
        out.display()
    );
    let mut table = vec![("validation".to_string(), &trained.validation)];
    let test_metrics = trained.held_out_metrics(args.rules.into());
    if let Some(test) = &test_metrics {
        table.push(("test (chronological 15%)".to_string(), test));
    }
    print!("{}", metrics_table(&table));
    Ok(())
}

/// Trains with an epoch progress bar on a terminal; Ctrl-C is left to the OS (offline runs are short).
pub fn train_with_progress(
    spec: &TrainingSpec,
    data: TrainingData,
    verbose: bool,
) -> Result<TrainedDetector> {
    let epochs = spec.train.max_epochs * spec.candidate_count();
    let bar = crate::progress::bar(epochs as u64, "training");
    let cancel = AtomicBool::new(false);
    let trained = train_detector(
        spec,
        data,
        &mut |p| {
            let line = format!(
                "epoch {} loss {:.4} val {:.4} auroc {} lr {:.1e}",
                p.epoch,
                p.train_loss,
                p.val_loss,
                p.val_auroc.map_or("-".into(), |a| format!("{a:.4}")),
                p.learning_rate
            );
            if verbose {
                eprintln!("{line}");
            }
            bar.inc(1);
            bar.set_message(line);
        },
        &cancel,
    )
    .context("training the detector")?;
    bar.finish_and_clear();
    Ok(trained)
}
