//! `spoofwatch train`: train an HO-LLN detector offline and write its artifact.

use std::path::PathBuf;
use std::sync::atomic::AtomicBool;

use anyhow::{Context, Result};
use clap::ValueEnum;
use spoofwatch_core::model::{Ablation, FeatureGroups, ModelConfig};
use spoofwatch_core::pipeline::{
    DetectorTrainingOptions, KAPPA_RHO_GRID, Recipe, SplitFractions, TrainedDetector,
    split_chronologically, train_detector,
};
use spoofwatch_core::sample::Track;
use spoofwatch_core::train::TrainConfig;

use super::remote::train::RemoteArgs;
use super::{ProjectionArg, RulesArg};
use crate::input::load_tracks;
use crate::report::metrics_table;

/// Model-shaping flags shared by `train` and the experiments.
#[derive(Debug, Clone, clap::Args)]
pub struct ModelFlags {
    /// Training seed (weights, shuffling); same seed and data give a bit-identical model.
    #[arg(long, default_value_t = 42)]
    pub seed: u64,
    /// Maximum number of epochs (early stopping may end sooner).
    #[arg(long, default_value_t = 30)]
    pub epochs: u32,
    /// Ablation: no symmetric exchange between evidence roles.
    #[arg(long)]
    pub no_exchange: bool,
    /// Ablation: no third-order joint-activation term.
    #[arg(long)]
    pub no_third_order: bool,
    /// Ablation: first-order liquid cell (no evolution state v).
    #[arg(long)]
    pub first_order_cell: bool,
    /// Ablation: evidence groups given to the model.
    #[arg(long, value_enum, default_value_t)]
    pub features: FeaturesArg,
    /// Select (κ, ρ) on validation from a small grid (trains one model per candidate).
    #[arg(long)]
    pub select_kappa_rho: bool,
    /// Local frame for GNSS displacements.
    #[arg(long, value_enum, default_value_t)]
    pub projection: ProjectionArg,
    /// Optimiser recipe: `auto` uses the small-data recipe (batches of 2 windows, learning rate
    /// 3e-3) when the training data holds fewer than 256 windows of 256 steps, else SPEC §6.
    #[arg(long, value_enum, default_value_t)]
    pub recipe: RecipeArg,
    /// Print one line per epoch on stderr.
    #[arg(long)]
    pub verbose: bool,
}

/// Optimiser recipe.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, ValueEnum)]
pub enum RecipeArg {
    /// Small-data recipe below 256 training windows, SPEC §6 above.
    #[default]
    Auto,
    /// SPEC §6 exactly (batches of 16 windows, learning rate 1e-3).
    Spec,
    /// Batches of 2 windows, learning rate 3e-3.
    SmallData,
}

impl From<RecipeArg> for Recipe {
    fn from(r: RecipeArg) -> Self {
        match r {
            RecipeArg::Auto => Recipe::Auto,
            RecipeArg::Spec => Recipe::Spec,
            RecipeArg::SmallData => Recipe::SmallData,
        }
    }
}

/// Evidence groups kept (SPEC §5 ablations).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, ValueEnum)]
pub enum FeaturesArg {
    #[default]
    All,
    NoAccumulation,
    NoEvolution,
    NoEvolutionNoQ,
    LowOrderOnly,
    ValidityOnly,
}

impl From<FeaturesArg> for FeatureGroups {
    fn from(f: FeaturesArg) -> Self {
        match f {
            FeaturesArg::All => FeatureGroups::All,
            FeaturesArg::NoAccumulation => FeatureGroups::NoAccumulation,
            FeaturesArg::NoEvolution => FeatureGroups::NoEvolution,
            FeaturesArg::NoEvolutionNoQ => FeatureGroups::NoEvolutionNoQ,
            FeaturesArg::LowOrderOnly => FeatureGroups::LowOrderOnly,
            FeaturesArg::ValidityOnly => FeatureGroups::ValidityOnly,
        }
    }
}

impl ModelFlags {
    /// The flags' defaults (full model, seed 42, 30 epochs).
    pub fn defaults() -> Self {
        Self {
            seed: 42,
            epochs: 30,
            no_exchange: false,
            no_third_order: false,
            first_order_cell: false,
            features: FeaturesArg::All,
            select_kappa_rho: false,
            projection: ProjectionArg::Wgs84,
            recipe: RecipeArg::Auto,
            verbose: false,
        }
    }

    /// Training options these flags describe.
    pub fn options(&self, data_description: Vec<String>) -> DetectorTrainingOptions {
        let model = ModelConfig {
            ablation: Ablation {
                no_exchange: self.no_exchange,
                no_third_order: self.no_third_order,
                first_order_cell: self.first_order_cell,
                features: self.features.into(),
            },
            ..ModelConfig::default()
        };
        let train = TrainConfig {
            seed: self.seed,
            max_epochs: self.epochs as usize,
            ..TrainConfig::default()
        };
        DetectorTrainingOptions {
            model,
            train,
            projection: self.projection.into(),
            recipe: self.recipe.into(),
            kappa_rho: if self.select_kappa_rho {
                KAPPA_RHO_GRID.to_vec()
            } else {
                vec![(0.0, 0.98)]
            },
            data_description,
            ..DetectorTrainingOptions::default()
        }
    }
}

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
    model: ModelFlags,
    /// Event rules for the reported metrics (offline mode).
    #[arg(long, value_enum, default_value_t)]
    rules: RulesArg,
    #[command(flatten)]
    remote: RemoteArgs,
}

pub fn run(args: Args) -> Result<()> {
    if args.remote.server.is_some() {
        return super::remote::block_on(super::remote::train::run(args.remote, args.model));
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
    let data = load_tracks(&args.data)?;
    let names: Vec<String> = args.data.iter().map(|p| p.display().to_string()).collect();
    let (train, validation, test) = if args.val.is_empty() {
        let split = split_chronologically(&data, SplitFractions::default());
        (split.train, split.validation, split.test)
    } else {
        (data, load_tracks(&args.val)?, Vec::new())
    };
    let options = args.model.options(names);
    let trained = train_with_progress(&train, &validation, &options, args.model.verbose)?;
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
    let test_metrics;
    if !test.is_empty() {
        let artifact = std::sync::Arc::new(trained.artifact.clone());
        test_metrics =
            spoofwatch_core::evaluation::evaluate_tracks(&artifact, &test, args.rules.into())
                .overall;
        table.push(("test (chronological 15%)".to_string(), &test_metrics));
    }
    print!("{}", metrics_table(&table));
    Ok(())
}

/// Trains with an epoch progress bar on a terminal; Ctrl-C is left to the OS (offline runs are short).
pub fn train_with_progress(
    train: &[Track],
    validation: &[Track],
    options: &DetectorTrainingOptions,
    verbose: bool,
) -> Result<TrainedDetector> {
    let candidates = options.kappa_rho.len() as u64;
    let bar = crate::progress::bar(options.train.max_epochs as u64 * candidates, "training");
    let cancel = AtomicBool::new(false);
    let trained = train_detector(
        train,
        validation,
        options,
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
