//! Training: the use case and the HO-LLN optimiser behind it.
//!
//! - [`spec`]: what a training job is asked to do ([`spec::TrainingSpec`], its defaults).
//! - [`data`]: from labelled tracks to model-ready sequences (split, evidence fit, sequences).
//! - [`detector`]: the one use case, [`detector::train_detector`]: spec + data → calibrated artifact.
//! - this module: the optimiser loop over sequences ([`train`]), which must not know about tracks,
//!   evidence or artifacts (the submodules build on it, never the other way round).
//!
//! Training of the HO-LLN model (SPEC §6): weighted BCE on ν = 1 rows, truncated BPTT over windows
//! with the state carried between the windows of a trajectory, AdamW, gradient clipping,
//! ReduceLROnPlateau, early stopping and a best-validation checkpoint. Seeded and bit-reproducible.
//!
//! Carried states: batches mix windows of different trajectories in shuffled order, so a window's
//! incoming state cannot come from the window processed just before it. At the start of every epoch a
//! forward pass over each training trajectory, with the current parameters and from the zero state,
//! records the state at every window start; the epoch's windows start from those states (treated as
//! constants: gradients stop at window boundaries). Windows tile a trajectory without overlap
//! (overlapping windows, as in the reference, would make "the carried state" ambiguous).

pub mod data;
pub mod detector;
mod optim;
mod parallel;
pub mod spec;

use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use serde::{Deserialize, Serialize};

use crate::evidence::{FEATURE_NAMES, Features};
use crate::metrics::auroc;
use crate::model::{
    LiquidState, Model, ModelConfig, ModelError, Params, StepScratch, Tape, TrainingWindow,
    WindowLoss, bce_with_logits, probability_from_logit,
};
use crate::rng::Rng;
use optim::{AdamW, EarlyStopping, PlateauScheduler, clip_global_norm};
use parallel::parallel_map;

/// Mixed into the seed for the window-shuffling stream, so it differs from the initialisation stream.
const SHUFFLE_STREAM: u64 = 0x5EED_5A17_0000_0001;

/// One trajectory of scaled evidence with labels: the unit the liquid state lives in.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Sequence {
    /// Scaled ξ rows (order `FEATURE_NAMES`, ν last).
    pub features: Vec<Features>,
    /// δ_t per row in seconds (0 or NaN at the trajectory start; clamped to [0, 5] as in serving).
    pub deltas: Vec<f64>,
    /// Spoofing labels.
    pub labels: Vec<bool>,
    /// ν_t: only these rows enter the loss and the metrics.
    pub valid: Vec<bool>,
}

/// Seed of the weights and of the window shuffling when none is given.
pub const DEFAULT_SEED: u64 = 42;
/// Maximum epochs when none is given (early stopping may end sooner).
pub const DEFAULT_MAX_EPOCHS: u32 = 30;
/// Most epochs a remote training job may ask for (bounds a job's run time on a shared server).
pub const MAX_EPOCHS: u32 = 200;

/// Training hyper-parameters. `Default` = SPEC §6 with [`DEFAULT_SEED`] and [`DEFAULT_MAX_EPOCHS`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TrainConfig {
    /// Seed of the initialisation and of the window shuffling.
    pub seed: u64,
    /// Maximum number of epochs.
    pub max_epochs: usize,
    /// Truncated-BPTT window length (steps).
    pub window: usize,
    /// Windows per optimiser step.
    pub batch_size: usize,
    /// Initial AdamW learning rate.
    pub learning_rate: f64,
    /// AdamW β1.
    pub beta1: f64,
    /// AdamW β2.
    pub beta2: f64,
    /// AdamW ε.
    pub eps: f64,
    /// Decoupled weight decay, applied to matrices (≥ 2 dims) only.
    pub weight_decay: f64,
    /// Maximum global L2 norm of the batch gradient.
    pub grad_clip_norm: f64,
    /// Lower clip of the class weights α_c.
    pub class_weight_min: f64,
    /// Upper clip of the class weights α_c.
    pub class_weight_max: f64,
    /// ReduceLROnPlateau factor.
    pub plateau_factor: f64,
    /// ReduceLROnPlateau patience (epochs).
    pub plateau_patience: usize,
    /// ReduceLROnPlateau relative threshold.
    pub plateau_threshold: f64,
    /// Learning-rate floor.
    pub min_learning_rate: f64,
    /// Early stopping: stop after more than this many epochs without improvement.
    pub early_stop_patience: usize,
    /// Early stopping: an improvement must beat the best validation loss by more than this.
    pub early_stop_min_delta: f64,
    /// Worker threads for per-window gradients and forward passes. Results do not depend on it.
    pub threads: usize,
}

impl Default for TrainConfig {
    fn default() -> Self {
        Self {
            seed: DEFAULT_SEED,
            max_epochs: DEFAULT_MAX_EPOCHS as usize,
            window: 256,
            batch_size: 16,
            learning_rate: 1e-3,
            beta1: 0.9,
            beta2: 0.999,
            eps: 1e-8,
            weight_decay: 1e-4,
            grad_clip_norm: 1.0,
            class_weight_min: 0.05,
            class_weight_max: 50.0,
            plateau_factor: 0.5,
            plateau_patience: 8,
            plateau_threshold: 1e-4,
            min_learning_rate: 1e-6,
            early_stop_patience: 12,
            early_stop_min_delta: 1e-6,
            threads: 2,
        }
    }
}

impl TrainConfig {
    /// Checks every field's range.
    pub fn validate(&self) -> Result<(), TrainError> {
        let positive_counts = [
            ("max_epochs", self.max_epochs),
            ("window", self.window),
            ("batch_size", self.batch_size),
            ("threads", self.threads),
        ];
        check_all(&positive_counts, |n| n > 0, "must be at least 1")?;
        let positive = [
            ("learning_rate", self.learning_rate),
            ("eps", self.eps),
            ("grad_clip_norm", self.grad_clip_norm),
            ("class_weight_min", self.class_weight_min),
        ];
        check_all(
            &positive,
            |v| v.is_finite() && v > 0.0,
            "must be finite and > 0",
        )?;
        let non_negative = [
            ("weight_decay", self.weight_decay),
            ("plateau_threshold", self.plateau_threshold),
            ("min_learning_rate", self.min_learning_rate),
            ("early_stop_min_delta", self.early_stop_min_delta),
        ];
        check_all(
            &non_negative,
            |v| v.is_finite() && v >= 0.0,
            "must be finite and >= 0",
        )?;
        let unit_open = [
            ("beta1", self.beta1),
            ("beta2", self.beta2),
            ("plateau_factor", self.plateau_factor),
        ];
        check_all(&unit_open, |v| (0.0..1.0).contains(&v), "must be in [0, 1)")?;
        if !(self.class_weight_max.is_finite() && self.class_weight_max >= self.class_weight_min) {
            return Err(invalid(
                "class_weight_max",
                "must be finite and >= class_weight_min",
            ));
        }
        if self.learning_rate * self.weight_decay >= 1.0 {
            return Err(invalid(
                "weight_decay",
                "learning_rate × weight_decay must be < 1",
            ));
        }
        Ok(())
    }
}

/// The first of `fields` that fails `ok`, as an invalid-config error with `reason`.
fn check_all<T: Copy>(
    fields: &[(&'static str, T)],
    ok: impl Fn(T) -> bool,
    reason: &str,
) -> Result<(), TrainError> {
    match fields.iter().find(|(_, value)| !ok(*value)) {
        Some((field, _)) => Err(invalid(field, reason)),
        None => Ok(()),
    }
}

fn invalid(field: &'static str, reason: &str) -> TrainError {
    TrainError::InvalidConfig {
        field,
        reason: reason.to_owned(),
    }
}

/// Loss weights α_c = N/(2 N_c) over the training ν = 1 rows, clipped.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ClassWeights {
    /// α for label 0 (normal).
    pub normal: f64,
    /// α for label 1 (spoofed).
    pub spoofed: f64,
}

impl ClassWeights {
    /// Balanced weights from the valid rows of `sequences`, clipped to `[min, max]`; `None` when a
    /// class has no valid row.
    pub fn balanced(sequences: &[Sequence], min: f64, max: f64) -> Option<Self> {
        let (mut normal, mut spoofed) = (0usize, 0usize);
        for sequence in sequences {
            for (&label, _) in sequence
                .labels
                .iter()
                .zip(&sequence.valid)
                .filter(|(_, v)| **v)
            {
                if label {
                    spoofed += 1;
                } else {
                    normal += 1;
                }
            }
        }
        Self::from_counts(normal, spoofed, min, max)
    }

    /// Balanced weights for `normal` and `spoofed` valid rows, clipped to `[min, max]`; `None` when
    /// a count is 0. (The baselines count their rows themselves and weigh them the same way.)
    pub fn from_counts(normal: usize, spoofed: usize, min: f64, max: f64) -> Option<Self> {
        if normal == 0 || spoofed == 0 {
            return None;
        }
        let total = (normal + spoofed) as f64;
        let weight = |count: usize| (total / (2.0 * count as f64)).clamp(min, max);
        Some(Self {
            normal: weight(normal),
            spoofed: weight(spoofed),
        })
    }

    /// α of a row's label.
    pub fn of(&self, label: bool) -> f64 {
        if label { self.spoofed } else { self.normal }
    }
}

/// Progress after one completed epoch.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EpochProgress {
    /// 1-based epoch number.
    pub epoch: usize,
    /// Weighted loss over the epoch's training windows (Σ w·ℓ / Σ masked rows, parameters moving).
    pub train_loss: f64,
    /// Weighted loss over the whole validation trajectories from the zero state (as served).
    pub val_loss: f64,
    /// Validation AUROC on ν = 1 rows (`None` with a single class).
    pub val_auroc: Option<f64>,
    /// Learning rate used during this epoch.
    pub learning_rate: f64,
    /// Seconds since training started.
    pub elapsed_s: f64,
}

/// Loss and AUROC of a model over whole trajectories (zero state at each start, no resets).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ValidationMetrics {
    /// Σ over ν = 1 rows of α·ℓ, divided by the number of those rows.
    pub loss: f64,
    /// AUROC of p̂ on ν = 1 rows (`None` with a single class).
    pub auroc: Option<f64>,
    /// Number of ν = 1 rows.
    pub valid_rows: usize,
}

/// Result of [`train`].
#[derive(Clone, Debug)]
pub struct TrainOutcome {
    /// The best-validation-loss checkpoint.
    pub model: Model,
    /// One entry per completed epoch.
    pub history: Vec<EpochProgress>,
    /// 1-based epoch of the checkpoint.
    pub best_epoch: usize,
    /// Validation loss of the checkpoint.
    pub best_val_loss: f64,
    /// Training stopped because the validation loss stopped improving.
    pub stopped_early: bool,
    /// Training was cancelled after at least one completed epoch (the partial epoch is discarded).
    pub cancelled: bool,
    /// Class weights used by the loss.
    pub class_weights: ClassWeights,
}

/// Errors of training.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TrainError {
    /// A hyper-parameter is out of range.
    #[error("invalid training configuration: {field} {reason}")]
    InvalidConfig {
        /// The field.
        field: &'static str,
        /// What is wrong.
        reason: String,
    },
    /// A split has no sequence or no row.
    #[error("the {split} set is empty")]
    EmptySplit {
        /// `training` or `validation`.
        split: &'static str,
    },
    /// Per-row vectors of a sequence differ in length.
    #[error("{split} sequence {sequence}: {field} has {found} entries, features have {expected}")]
    LengthMismatch {
        /// `training` or `validation`.
        split: &'static str,
        /// Index of the sequence in its split.
        sequence: usize,
        /// `deltas`, `labels` or `valid`.
        field: &'static str,
        /// Number of feature rows.
        expected: usize,
        /// Length of `field`.
        found: usize,
    },
    /// A feature value is NaN or infinite.
    #[error("{split} sequence {sequence}, row {row}: feature {feature} is not finite")]
    NonFiniteFeature {
        /// `training` or `validation`.
        split: &'static str,
        /// Index of the sequence in its split.
        sequence: usize,
        /// Row inside the sequence.
        row: usize,
        /// Feature name.
        feature: &'static str,
    },
    /// No row of a split has ν = 1.
    #[error("the {split} set has no valid (nu = 1) row")]
    NoValidRows {
        /// `training` or `validation`.
        split: &'static str,
    },
    /// The training ν = 1 rows contain a single class.
    #[error("the training set's valid rows are all {}", if *.spoofed { "spoofed" } else { "normal" })]
    SingleClass {
        /// The only label present.
        spoofed: bool,
    },
    /// The loss or the gradient became non-finite.
    #[error("training diverged in epoch {epoch} (non-finite loss or gradient)")]
    Diverged {
        /// 1-based epoch.
        epoch: usize,
    },
    /// Cancelled before the first epoch completed (there is no validated model to return).
    #[error("training was cancelled before the first epoch completed")]
    Cancelled,
    /// A model error (configuration or internal shape problem).
    #[error(transparent)]
    Model(#[from] ModelError),
}

/// A training window: rows `[start, end)` of one training sequence.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct WindowSpan {
    sequence: usize,
    /// Index of the window inside its sequence (into the carried start states).
    index: usize,
    start: usize,
    end: usize,
}

/// Non-overlapping windows of `window` rows tiling every sequence; those with a ν = 1 row are returned
/// for training (the others still carry the state through the epoch-start pass).
fn plan_windows(sequences: &[Sequence], window: usize) -> Vec<WindowSpan> {
    let mut spans = Vec::new();
    for (sequence, data) in sequences.iter().enumerate() {
        let length = data.features.len();
        for (index, start) in (0..length).step_by(window).enumerate() {
            let end = (start + window).min(length);
            if data.valid[start..end].iter().any(|&v| v) {
                spans.push(WindowSpan {
                    sequence,
                    index,
                    start,
                    end,
                });
            }
        }
    }
    spans
}

/// The liquid state at every window start of `sequence`, from a zero-state forward pass.
fn window_start_states(
    model: &Model,
    sequence: &Sequence,
    window: usize,
    scratch: &mut StepScratch,
) -> Vec<LiquidState> {
    let mut state = LiquidState::zeros(model.config());
    let mut starts = Vec::new();
    for (t, (x, &delta)) in sequence.features.iter().zip(&sequence.deltas).enumerate() {
        if t % window == 0 {
            starts.push(state.clone());
        }
        model.step(&mut state, x, delta, scratch);
    }
    starts
}

fn check_split(sequences: &[Sequence], split: &'static str) -> Result<usize, TrainError> {
    let mut valid_rows = 0;
    for (index, sequence) in sequences.iter().enumerate() {
        let expected = sequence.features.len();
        for (field, found) in [
            ("deltas", sequence.deltas.len()),
            ("labels", sequence.labels.len()),
            ("valid", sequence.valid.len()),
        ] {
            if found != expected {
                return Err(TrainError::LengthMismatch {
                    split,
                    sequence: index,
                    field,
                    expected,
                    found,
                });
            }
        }
        for (row, x) in sequence.features.iter().enumerate() {
            if let Some(feature) = x.iter().position(|v| !v.is_finite()) {
                return Err(TrainError::NonFiniteFeature {
                    split,
                    sequence: index,
                    row,
                    feature: FEATURE_NAMES[feature],
                });
            }
        }
        valid_rows += sequence.valid.iter().filter(|&&v| v).count();
    }
    if sequences.iter().all(|s| s.features.is_empty()) {
        return Err(TrainError::EmptySplit { split });
    }
    if valid_rows == 0 {
        return Err(TrainError::NoValidRows { split });
    }
    Ok(valid_rows)
}

/// Validation loss and AUROC of `model` over whole trajectories, each from the zero state.
pub fn validation_metrics(
    model: &Model,
    sequences: &[Sequence],
    weights: ClassWeights,
    threads: usize,
) -> Result<ValidationMetrics, TrainError> {
    check_split(sequences, "validation")?;
    let mut scratches: Vec<StepScratch> = (0..threads.max(1))
        .map(|_| StepScratch::new(model.config()))
        .collect();
    let logits = parallel_map(sequences, &mut scratches, |_, sequence| {
        let mut state = LiquidState::zeros(model.config());
        model.forward_logits(&sequence.features, &sequence.deltas, &mut state)
    });
    let (mut loss_sum, mut scores, mut labels) = (0.0, Vec::new(), Vec::new());
    for (sequence, logits) in sequences.iter().zip(logits) {
        let logits = logits?;
        for ((&logit, &label), _) in logits
            .iter()
            .zip(&sequence.labels)
            .zip(&sequence.valid)
            .filter(|(_, v)| **v)
        {
            loss_sum += bce_with_logits(logit, label, weights.of(label));
            scores.push(probability_from_logit(logit));
            labels.push(label);
        }
    }
    Ok(ValidationMetrics {
        loss: loss_sum / labels.len() as f64,
        auroc: auroc(&scores, &labels),
        valid_rows: labels.len(),
    })
}

/// Trains a model of configuration `model_config` on `train`, selecting on `val`.
///
/// `on_epoch` is called after every completed epoch. `cancel` is polled before every batch: a
/// cancelled run returns promptly with the best checkpoint so far (`cancelled = true`, partial epoch
/// discarded), or [`TrainError::Cancelled`] if no epoch had completed.
pub fn train(
    train: &[Sequence],
    val: &[Sequence],
    model_config: ModelConfig,
    config: &TrainConfig,
    on_epoch: &mut dyn FnMut(&EpochProgress),
    cancel: &AtomicBool,
) -> Result<TrainOutcome, TrainError> {
    let initial = Model::init(model_config, config.seed)?;
    train_from(train, val, initial, config, on_epoch, cancel)
}

/// [`train`] starting from `initial`'s weights instead of a seeded initialisation (fitting a
/// trained model to a fleet's data). The seed still orders the windows.
pub fn train_from(
    train: &[Sequence],
    val: &[Sequence],
    initial: Model,
    config: &TrainConfig,
    on_epoch: &mut dyn FnMut(&EpochProgress),
    cancel: &AtomicBool,
) -> Result<TrainOutcome, TrainError> {
    config.validate()?;
    initial.config().validate()?;
    if train.is_empty() {
        return Err(TrainError::EmptySplit { split: "training" });
    }
    if val.is_empty() {
        return Err(TrainError::EmptySplit {
            split: "validation",
        });
    }
    check_split(train, "training")?;
    check_split(val, "validation")?;
    let Some(class_weights) =
        ClassWeights::balanced(train, config.class_weight_min, config.class_weight_max)
    else {
        let spoofed = train
            .iter()
            .any(|s| s.labels.iter().zip(&s.valid).any(|(&l, &v)| l && v));
        return Err(TrainError::SingleClass { spoofed });
    };
    Trainer::new(train, val, initial, config, class_weights).run(on_epoch, cancel)
}

/// The state of one training run.
struct Trainer<'a> {
    train: &'a [Sequence],
    val: &'a [Sequence],
    config: &'a TrainConfig,
    class_weights: ClassWeights,
    /// Per training sequence, α of each row's label.
    row_weights: Vec<Vec<f64>>,
    windows: Vec<WindowSpan>,
    model: Model,
    optimizer: AdamW,
    shuffle: Rng,
    tapes: Vec<Tape>,
    scratches: Vec<StepScratch>,
}

/// Loss sums of one epoch's training batches.
struct EpochLoss {
    loss_sum: f64,
    masked_rows: usize,
}

impl<'a> Trainer<'a> {
    fn new(
        train: &'a [Sequence],
        val: &'a [Sequence],
        model: Model,
        config: &'a TrainConfig,
        class_weights: ClassWeights,
    ) -> Self {
        let optimizer = AdamW::new(
            model.params(),
            config.beta1,
            config.beta2,
            config.eps,
            config.weight_decay,
        );
        let row_weights = train
            .iter()
            .map(|s| s.labels.iter().map(|&l| class_weights.of(l)).collect())
            .collect();
        let scratches = (0..config.threads)
            .map(|_| StepScratch::new(model.config()))
            .collect();
        Self {
            train,
            val,
            config,
            class_weights,
            row_weights,
            windows: plan_windows(train, config.window),
            model,
            optimizer,
            shuffle: Rng::seed_from_u64(config.seed ^ SHUFFLE_STREAM),
            tapes: (0..config.threads).map(|_| Tape::default()).collect(),
            scratches,
        }
    }

    fn run(
        mut self,
        on_epoch: &mut dyn FnMut(&EpochProgress),
        cancel: &AtomicBool,
    ) -> Result<TrainOutcome, TrainError> {
        let started = Instant::now();
        let mut learning_rate = self.config.learning_rate;
        let mut scheduler = PlateauScheduler::new(
            self.config.plateau_factor,
            self.config.plateau_patience,
            self.config.plateau_threshold,
            self.config.min_learning_rate,
        );
        let mut stopping = EarlyStopping::new(
            self.config.early_stop_patience,
            self.config.early_stop_min_delta,
        );
        let mut history: Vec<EpochProgress> = Vec::new();
        let mut best: Option<(usize, f64, Params)> = None;
        let (mut stopped_early, mut cancelled) = (false, false);
        for epoch in 1..=self.config.max_epochs {
            let Some(epoch_loss) = self.train_epoch(epoch, learning_rate, cancel)? else {
                cancelled = true;
                break;
            };
            let val = validation_metrics(
                &self.model,
                self.val,
                self.class_weights,
                self.config.threads,
            )?;
            let progress = EpochProgress {
                epoch,
                train_loss: epoch_loss.loss_sum / epoch_loss.masked_rows.max(1) as f64,
                val_loss: val.loss,
                val_auroc: val.auroc,
                learning_rate,
                elapsed_s: started.elapsed().as_secs_f64(),
            };
            let (improved, stop) = stopping.observe(val.loss);
            if improved {
                best = Some((epoch, val.loss, self.model.params().clone()));
            }
            learning_rate = scheduler.step(val.loss, learning_rate);
            on_epoch(&progress);
            history.push(progress);
            if stop {
                stopped_early = epoch < self.config.max_epochs;
                break;
            }
        }
        if history.is_empty() {
            return Err(TrainError::Cancelled);
        }
        // No improving epoch at all means every validation loss was NaN: report divergence.
        let Some((best_epoch, best_val_loss, params)) = best else {
            return Err(TrainError::Diverged {
                epoch: history.len(),
            });
        };
        Ok(TrainOutcome {
            model: Model::from_parts(self.model.config().clone(), params)?,
            history,
            best_epoch,
            best_val_loss,
            stopped_early,
            cancelled,
            class_weights: self.class_weights,
        })
    }

    /// One pass over the shuffled training windows; `None` when cancelled.
    fn train_epoch(
        &mut self,
        epoch: usize,
        learning_rate: f64,
        cancel: &AtomicBool,
    ) -> Result<Option<EpochLoss>, TrainError> {
        if cancel.load(Ordering::Relaxed) {
            return Ok(None);
        }
        let model = &self.model;
        let window = self.config.window;
        let start_states = parallel_map(self.train, &mut self.scratches, |scratch, sequence| {
            window_start_states(model, sequence, window, scratch)
        });
        let mut order = self.windows.clone();
        self.shuffle.shuffle(&mut order);
        let mut total = EpochLoss {
            loss_sum: 0.0,
            masked_rows: 0,
        };
        for batch in order.chunks(self.config.batch_size) {
            if cancel.load(Ordering::Relaxed) {
                return Ok(None);
            }
            let (mut gradient, loss) = self.batch_gradient(batch, &start_states)?;
            let rows = loss.masked_rows.max(1) as f64;
            gradient.scale(1.0 / rows);
            let norm = clip_global_norm(&mut gradient, self.config.grad_clip_norm);
            if !(norm.is_finite() && loss.loss_sum.is_finite()) {
                return Err(TrainError::Diverged { epoch });
            }
            self.optimizer
                .update(self.model.params_mut(), &gradient, learning_rate);
            total.loss_sum += loss.loss_sum;
            total.masked_rows += loss.masked_rows;
        }
        Ok(Some(total))
    }

    /// Sum over the batch's windows of the unnormalised loss gradients. Each window's gradient is
    /// computed on its own (possibly on another thread) and the sum is taken in batch order, so the
    /// result does not depend on the thread count.
    fn batch_gradient(
        &mut self,
        batch: &[WindowSpan],
        start_states: &[Vec<LiquidState>],
    ) -> Result<(Params, WindowLoss), TrainError> {
        let (model, train, row_weights) = (&self.model, self.train, &self.row_weights);
        let per_window = parallel_map(batch, &mut self.tapes, |tape, span| {
            let sequence = &train[span.sequence];
            let rows = span.start..span.end;
            let window = TrainingWindow {
                features: &sequence.features[rows.clone()],
                deltas: &sequence.deltas[rows.clone()],
                labels: &sequence.labels[rows.clone()],
                mask: &sequence.valid[rows.clone()],
                weights: &row_weights[span.sequence][rows],
            };
            let mut state = start_states[span.sequence][span.index].clone();
            let mut gradient = Params::zeros(model.config());
            model
                .accumulate_window_gradient(&window, &mut state, tape, &mut gradient)
                .map(|loss| (gradient, loss))
        });
        let mut sum = Params::zeros(model.config());
        let mut loss = WindowLoss {
            loss_sum: 0.0,
            masked_rows: 0,
        };
        for result in per_window {
            let (gradient, window_loss) = result?;
            sum.add_assign(&gradient);
            loss.loss_sum += window_loss.loss_sum;
            loss.masked_rows += window_loss.masked_rows;
        }
        Ok((sum, loss))
    }
}

#[cfg(test)]
mod tests;
