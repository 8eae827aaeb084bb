//! The flags that describe a training job, shared by `spoofwatch train` (local and `--server` mode)
//! and the experiments. Defaults come from spoofwatch-core's training constants, never from here.
//!
//! Owns flag parsing only: the local command turns [`TrainingFlags`] into a core `TrainingSpec`, the
//! remote command into a wire request. Must not train, connect or print.

use crate::cli::server_flags::TransportArgs;
use clap::ValueEnum;
use clap::builder::{PossibleValuesParser, TypedValueParser};
use spoofwatch_core::evidence::FeatureSchema;
use spoofwatch_core::model::{Ablation, FeatureGroups};
use spoofwatch_core::train::spec::{KappaRho, Recipe, TrainingSpec};
use spoofwatch_core::train::{DEFAULT_MAX_EPOCHS, DEFAULT_SEED};

use crate::cli::flags::ProjectionArg;

/// Model-shaping flags shared by `train` and the experiments.
#[derive(Debug, Clone, clap::Args)]
pub struct TrainingFlags {
    /// Training seed (weights, shuffling); same seed and data give a bit-identical model.
    #[arg(long, default_value_t = DEFAULT_SEED)]
    pub seed: u64,
    /// Maximum number of epochs (early stopping may end sooner).
    #[arg(long, default_value_t = DEFAULT_MAX_EPOCHS)]
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
    /// Ablation: keep the rows right after an attack's end in the loss (by default the first 10 s
    /// after the spoofer leaves are masked: its exit jump is labelled normal).
    #[arg(long)]
    pub no_exit_mask: bool,
    /// Ablation: no per-vehicle noise levels (every channel is normalised by the training
    /// population's noise alone).
    #[arg(long)]
    pub no_vehicle_levels: bool,
    /// Ablation: trust the onboard calibration by the clock (its channels on after 240 s of valid
    /// data) instead of by its own uncertainty.
    #[arg(long)]
    pub timer_trust: bool,
    /// Ablation: with offset evidence (`v3`), persistence N_p in rows instead of the alarm
    /// lifecycle in seconds.
    #[arg(long)]
    pub rows_lifecycle: bool,
    /// Ablation: evidence groups given to the model.
    #[arg(long, default_value = FeatureGroups::All.name(), value_parser = feature_groups())]
    pub features: FeatureGroups,
    /// Evidence channels: `v3` (the bundled default's: the paper's ξ, directional drift channels and
    /// the offsets from dead-reckoning anchors), `v2` (without the offsets: never alarms on a jump)
    /// or `paper`.
    #[arg(
        long,
        default_value = FeatureSchema::default().name(),
        value_parser = PossibleValuesParser::new(FeatureSchema::NAMED.map(|(name, _)| name))
            .map(|name| FeatureSchema::from_name(&name).unwrap_or_default()),
    )]
    pub schema: FeatureSchema,
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

/// Parses `--features`: one of [`FeatureGroups::NAMED`].
pub fn feature_groups() -> impl TypedValueParser<Value = FeatureGroups> {
    PossibleValuesParser::new(FeatureGroups::NAMED.map(|(name, _)| name))
        .map(|name| FeatureGroups::from_name(&name).unwrap_or_default())
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

impl TrainingFlags {
    /// The flags' defaults (core's training defaults, full model), as clap gives them.
    #[cfg(test)]
    pub fn defaults() -> Self {
        Self {
            seed: DEFAULT_SEED,
            epochs: DEFAULT_MAX_EPOCHS,
            no_exchange: false,
            no_third_order: false,
            first_order_cell: false,
            no_exit_mask: false,
            no_vehicle_levels: false,
            timer_trust: false,
            rows_lifecycle: false,
            features: FeatureGroups::default(),
            schema: FeatureSchema::default(),
            select_kappa_rho: false,
            projection: ProjectionArg::default(),
            recipe: RecipeArg::default(),
            verbose: false,
        }
    }

    /// The ablation these flags select.
    pub fn ablation(&self) -> Ablation {
        Ablation {
            no_exchange: self.no_exchange,
            no_third_order: self.no_third_order,
            first_order_cell: self.first_order_cell,
            features: self.features,
            no_exit_mask: self.no_exit_mask,
            no_vehicle_levels: self.no_vehicle_levels,
            timer_trust: self.timer_trust,
            rows_lifecycle: self.rows_lifecycle,
        }
    }

    /// The training spec these flags describe.
    pub fn spec(&self, data_description: Vec<String>) -> TrainingSpec {
        TrainingSpec {
            projection: self.projection.into(),
            recipe: self.recipe.into(),
            data_description,
            ..TrainingSpec::with(
                self.seed,
                self.epochs,
                self.schema,
                self.ablation(),
                KappaRho::selected_if(self.select_kappa_rho),
            )
        }
    }
}

/// Remote-mode flags of `spoofwatch train`.
#[derive(Debug, Clone, clap::Args)]
pub struct RemoteTrainingFlags {
    /// Train on this Spoofwatch server instead of locally (remote mode; --data/--val/--out are then
    /// not used). Deliberately not read from SPOOFWATCH_SERVER, so offline training stays offline.
    #[arg(long)]
    pub server: Option<String>,
    /// Bearer token for the server.
    #[arg(long, env = "SPOOFWATCH_TOKEN", hide_env_values = true)]
    pub token: Option<String>,
    #[command(flatten)]
    pub transport: TransportArgs,
    /// Remote mode: datasets to train on (`datasets/{id}` or `{id}`).
    #[arg(long = "dataset", num_args = 1..)]
    pub datasets: Vec<String>,
    /// Remote mode: validation datasets; without them every trajectory is split 70/15/15.
    #[arg(long = "val-dataset", num_args = 1..)]
    pub val_datasets: Vec<String>,
    /// Remote mode: make the trained model the active one when the job succeeds.
    #[arg(long)]
    pub activate: bool,
    /// Remote mode: display name of the job and its model.
    #[arg(long)]
    pub name: Option<String>,
}

impl RemoteTrainingFlags {
    /// Remote-mode flags given without `--server` (clap cannot require `--server` for them: it
    /// conflicts with `--data`, which waives the requirement).
    pub fn remote_only_flags_given(&self) -> Vec<&'static str> {
        let mut given = Vec::new();
        if !self.datasets.is_empty() {
            given.push("--dataset");
        }
        if !self.val_datasets.is_empty() {
            given.push("--val-dataset");
        }
        if self.activate {
            given.push("--activate");
        }
        if self.name.is_some() {
            given.push("--name");
        }
        given
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn default_flags_describe_the_default_spec() {
        assert_eq!(
            TrainingFlags::defaults().spec(Vec::new()),
            TrainingSpec::default()
        );
    }

    #[test]
    fn remote_only_flags_are_named() {
        let given = RemoteTrainingFlags {
            server: None,
            token: None,
            transport: TransportArgs::default(),
            datasets: vec!["d".into()],
            val_datasets: vec!["datasets/v".into()],
            activate: true,
            name: Some("run".into()),
        };
        assert_eq!(
            given.remote_only_flags_given(),
            vec!["--dataset", "--val-dataset", "--activate", "--name"]
        );
        let none = RemoteTrainingFlags {
            server: None,
            token: None,
            transport: TransportArgs::default(),
            datasets: Vec::new(),
            val_datasets: Vec::new(),
            activate: false,
            name: None,
        };
        assert!(none.remote_only_flags_given().is_empty());
    }
}
