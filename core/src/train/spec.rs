//! What a training job is asked to do: [`TrainingSpec`], with `Default` = the project's defaults.
//!
//! Owns the job-level defaults (κ/ρ, recipe, split fractions, operating-point rule); the optimiser's
//! (seed, epochs, SPEC §6) are [`TrainConfig`]'s `Default` next to the trainer, so the CLI, the server
//! and the experiments read every default from one place. Must not touch data or run anything:
//! [`super::detector`] executes a spec.

use crate::alarm::OperatingPointRule;
use crate::evidence::calibration::CalibrationPrior;
use crate::evidence::{DEFAULT_KAPPA, DEFAULT_RHO, FeatureSchema};
use crate::geo::Projection;
use crate::metrics::EventRules;
use crate::model::{Ablation, Model, ModelConfig};
use crate::train::{Sequence, TrainConfig};

/// (κ, ρ) of the evidence accumulator when they are not selected on validation (SPEC §4).
pub const DEFAULT_KAPPA_RHO: (f64, f64) = (DEFAULT_KAPPA, DEFAULT_RHO);
/// Small (κ, ρ) grid searched when the caller asks for selection on validation (SPEC §4).
pub const KAPPA_RHO_GRID: [(f64, f64); 6] = [
    (0.0, 0.95),
    (0.0, 0.98),
    (0.0, 0.99),
    (1.0, 0.95),
    (1.0, 0.98),
    (1.0, 0.99),
];

/// Whether a trained model's offset anchors re-base the motion behind them when the calibration in
/// use changes ([`OffsetParams::rebase_on_calibration`](crate::evidence::offset::OffsetParams),
/// `docs/detector.md` §4.2). At a fixed operating point re-basing removes false alarms; each search
/// measured so far that chose its points on re-based evidence spent the room it made on
/// sensitivity and landed at or over a budget on test hours (docs/experiments.md). `Margin` keeps
/// that room as a margin instead.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum AnchorRebase {
    /// Neither in training nor in service.
    Off,
    /// Trained, and both operating points chosen, on evidence without it; served with it (the
    /// bundled default's, and every training path's unless asked otherwise). The false alarms it
    /// removes stay below the budgets the points were chosen for.
    #[default]
    Margin,
    /// The network is trained, and the anchors' noise and growth fitted, on evidence without it;
    /// the operating points are chosen, and the model serves, with it.
    Serve,
    /// Trained, chosen and served with it; the anchors' noise and growth are still fitted
    /// without it, so the gates they set stay the wider ones.
    TrainAndServe,
}

impl AnchorRebase {
    /// Whether the operating points are chosen on re-based evidence.
    pub fn when_choosing(self) -> bool {
        matches!(self, Self::Serve | Self::TrainAndServe)
    }

    /// Whether the finished model serves with re-basing.
    pub fn when_serving(self) -> bool {
        self != Self::Off
    }
}

/// Fractions of each trajectory given to train and validation; the rest is test (SPEC §9).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SplitFractions {
    pub train: f64,
    pub validation: f64,
}

impl Default for SplitFractions {
    fn default() -> Self {
        Self {
            train: 0.70,
            validation: 0.15,
        }
    }
}

/// How the evidence accumulator's (κ, ρ) are chosen.
#[derive(Clone, Debug, PartialEq)]
pub enum KappaRho {
    /// These values.
    Fixed(f64, f64),
    /// One model per [`KAPPA_RHO_GRID`] entry; the best validation F1 (then lower validation loss) wins.
    SelectOnValidation,
}

impl Default for KappaRho {
    fn default() -> Self {
        let (kappa, rho) = DEFAULT_KAPPA_RHO;
        Self::Fixed(kappa, rho)
    }
}

impl KappaRho {
    /// `SelectOnValidation` when `select`, else the default fixed pair.
    pub fn selected_if(select: bool) -> Self {
        if select {
            Self::SelectOnValidation
        } else {
            Self::default()
        }
    }

    /// The candidate pairs to train.
    pub fn candidates(&self) -> Vec<(f64, f64)> {
        match self {
            Self::Fixed(kappa, rho) => vec![(*kappa, *rho)],
            Self::SelectOnValidation => KAPPA_RHO_GRID.to_vec(),
        }
    }
}

/// How the optimiser settings are chosen.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Recipe {
    /// Exactly [`TrainingSpec::train`] (SPEC §6 by default).
    Spec,
    /// [`SMALL_DATA_BATCH`] windows per step at [`SMALL_DATA_LEARNING_RATE`]: for training sets too
    /// small for SPEC §6's batches of 16 windows (Dataset-2 alone gives ~19 windows, i.e. ~2
    /// optimiser steps per epoch, and the SPEC recipe does not converge in 30 epochs).
    SmallData,
    /// `SmallData` when the training data holds fewer than [`SMALL_DATA_WINDOWS`] windows, else `Spec`.
    #[default]
    Auto,
}

/// Below this many training windows (16 SPEC batches per epoch; the reference's Dataset-1 training
/// split gives ~340), [`Recipe::Auto`] switches to the small-data recipe.
pub const SMALL_DATA_WINDOWS: usize = 256;
/// Small-data recipe: windows per optimiser step and learning rate, chosen by Dataset-2 validation
/// F1 over batch {1, 2, 4} × learning rate {1e-3, 2e-3, 3e-3} (`docs/experiments.md`, "Training
/// recipe").
pub const SMALL_DATA_BATCH: usize = 2;
pub const SMALL_DATA_LEARNING_RATE: f64 = 3e-3;

impl Recipe {
    /// Whether this recipe uses the small-data batch and learning rate for `windows` training
    /// windows.
    pub fn is_small_data(self, windows: usize) -> bool {
        match self {
            Recipe::Spec => false,
            Recipe::SmallData => true,
            Recipe::Auto => windows < SMALL_DATA_WINDOWS,
        }
    }

    /// The training configuration this recipe gives for `sequences`.
    pub fn apply(self, base: &TrainConfig, sequences: &[Sequence]) -> TrainConfig {
        let windows: usize = sequences
            .iter()
            .map(|s| s.features.len().div_ceil(base.window.max(1)))
            .sum();
        if self.is_small_data(windows) {
            TrainConfig {
                batch_size: SMALL_DATA_BATCH,
                learning_rate: SMALL_DATA_LEARNING_RATE,
                ..base.clone()
            }
        } else {
            base.clone()
        }
    }
}

/// Everything that shapes a trained detector. `Default` = the project's defaults (the only place
/// they are written).
#[derive(Clone, Debug, PartialEq)]
pub struct TrainingSpec {
    /// Chronological split of [`super::detector::TrainingData::Chronological`] data.
    pub split: SplitFractions,
    /// Model widths and ablations (the feature groups live in `model.ablation.features`).
    pub model: ModelConfig,
    /// Seed, epochs and optimiser settings.
    pub train: TrainConfig,
    /// How `train` is adapted to the data size.
    pub recipe: Recipe,
    /// Local frame for GNSS displacements.
    pub projection: Projection,
    /// Fixed (κ, ρ) or a selection on validation.
    pub kappa_rho: KappaRho,
    /// How (θ, N_p) is chosen on validation.
    pub operating_point: OperatingPointRule,
    /// Event rules of the operating-point search and of the reported validation metrics.
    pub rules: EventRules,
    /// Free-form description of the training data for the artifact's provenance.
    pub data_description: Vec<String>,
    /// The fleet's prior on the onboard calibration, fitted on its attack-free recordings
    /// (`None`: the default prior).
    pub calibration_prior: Option<CalibrationPrior>,
    /// Weights to start training from (a model of the same configuration, e.g. the bundled
    /// default); `None`: seeded initialisation.
    pub initial_model: Option<Model>,
    /// Whether the trained model's offset anchors re-base their dead reckoning when the
    /// calibration in use changes ([`AnchorRebase`]); in service only by default.
    pub anchor_rebase: AnchorRebase,
}

impl Default for TrainingSpec {
    fn default() -> Self {
        Self {
            split: SplitFractions::default(),
            model: ModelConfig::default(),
            train: TrainConfig::default(),
            recipe: Recipe::default(),
            projection: Projection::default(),
            kappa_rho: KappaRho::default(),
            operating_point: OperatingPointRule::BestValidationF1,
            rules: EventRules::Spec,
            data_description: Vec::new(),
            calibration_prior: None,
            initial_model: None,
            anchor_rebase: AnchorRebase::default(),
        }
    }
}

impl TrainingSpec {
    /// The defaults with this seed, epoch limit, feature schema, ablation and (κ, ρ) rule: what the
    /// CLI flags and a remote job request describe.
    pub fn with(
        seed: u64,
        max_epochs: u32,
        schema: FeatureSchema,
        ablation: Ablation,
        kappa_rho: KappaRho,
    ) -> Self {
        let defaults = Self::default();
        Self {
            model: ModelConfig {
                ablation,
                schema,
                ..defaults.model
            },
            train: TrainConfig {
                seed,
                max_epochs: max_epochs as usize,
                ..defaults.train
            },
            kappa_rho,
            ..defaults
        }
    }

    /// Number of (κ, ρ) candidates trained, each for up to `train.max_epochs` epochs.
    pub fn candidate_count(&self) -> usize {
        self.kappa_rho.candidates().len()
    }
}
