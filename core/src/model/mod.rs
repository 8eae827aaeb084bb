//! The HO-LLN model (SPEC §5): role encoders → symmetric exchange → third-order fusion → second-order
//! liquid cell → logistic head, with a streaming `step`, a sequence forward built on it, and a
//! hand-derived BPTT backward (`backward.rs`).
//!
//! Input: already-scaled ξ vectors ([`Features`], order [`crate::evidence::FEATURE_NAMES`], ν last) and
//! the time step δ_t in seconds.
//!
//! Owns the model: configuration, parameters, forward/backward and the artifact ([`artifact`]). Must
//! not know about tracks, evidence building, training loops or alarms.

pub mod artifact;
mod backward;
mod fastmath;
mod forward;
mod linalg;
mod params;

use serde::{Deserialize, Serialize};

use crate::evidence::{DRIFT_FEATURES_START, FEATURE_CAPACITY, FeatureSchema, Features};
use crate::rng::Rng;
use crate::sample::readable;

pub use backward::{Tape, TrainingWindow, WindowGradient, WindowLoss, bce_with_logits};
pub use forward::StepScratch;
pub use params::{Params, Tensor};

/// Default smallest liquid time constant (s).
pub const DEFAULT_TAU_MIN_S: f64 = 0.05;
/// Default largest liquid time constant (s).
pub const DEFAULT_TAU_MAX_S: f64 = 10.0;
/// δ_t is clamped to `[0, MAX_DELTA_S]` (NaN → 0) before it reaches the liquid cell.
pub const MAX_DELTA_S: f64 = 5.0;
/// Largest accepted width of any layer (guards against absurd allocations from a bad config).
pub const MAX_DIMENSION: usize = 4096;
/// Most trainable scalars a model may have. A sample's cost grows with them (the bundled model's
/// 21,883 take about 4.4 µs per sample), so this bounds what any servable model costs per sample to
/// about 16 times the bundled model's.
pub const MAX_PARAMETERS: usize = 350_000;
/// Smallest accepted τ_min (s). Trained models use 0.05 s; below a millisecond a time constant is far
/// shorter than any sample interval and the cell just copies its candidate.
pub const MIN_TAU_S: f64 = 1e-3;
/// Largest accepted τ_max (s). Trained models use 10 s; a day is far beyond any memory a drive needs.
pub const MAX_TAU_S: f64 = 86_400.0;
/// Largest accepted |value| of a parameter. Trained weights stay below 1.5 (the bundled models: at most
/// 0.93 and 1.32; Xavier init at most √3 ≈ 1.73), so 1e4 leaves a margin of thousands while keeping every
/// pre-activation finite: inputs are clipped to ±20 and no layer is wider than [`MAX_DIMENSION`] × 4,
/// so |pre-activation| ≤ 1e4 · 20 · 16384 + 1e4 ≈ 3.3e9, and every state is squashed by tanh/σ after.
pub const MAX_ABS_PARAMETER: f64 = 1e4;

/// ξ indices feeding the instantaneous role I = [η_E, η_N, q].
pub const INSTANT_INPUTS: [usize; 3] = [0, 1, 6];
/// ξ indices feeding the evolution role E = [η̇_E, η̇_N, η̈_E, η̈_N].
pub const EVOLUTION_INPUTS: [usize; 4] = [2, 3, 4, 5];
/// ξ indices feeding the persistence role P = [ã, ν] and, in the v2 and v3 schemas, the drift and
/// offset channels: they are persistence evidence too (integrated over 10–120 s, or held since a
/// trusted fix), and P is where the third-order term lets persistence gate the instantaneous and
/// evolution roles. The paper schema reads the first 2, v2 the first 14.
pub const PERSISTENCE_INPUTS: [usize; MAX_PERSISTENCE_INPUTS] = [
    7, 8, 9, 10, 11, 12, 13, 14, 15, 16, 17, 18, 19, 20, 21, 22, 23, 24, 25,
];
/// Width of P in the widest schema.
pub const MAX_PERSISTENCE_INPUTS: usize = 2 + FEATURE_CAPACITY - DRIFT_FEATURES_START;

/// Errors of the model module.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ModelError {
    /// The widths give more than [`MAX_PARAMETERS`] trainable scalars.
    #[error(
        "the model's widths give {parameters} parameters, more than the {MAX_PARAMETERS} a model may have (its cost per sample grows with them)"
    )]
    TooManyParameters {
        /// How many the widths give.
        parameters: usize,
    },
    /// A layer width is zero or larger than [`MAX_DIMENSION`].
    #[error("model dimension {name} = {value} is outside 1..={MAX_DIMENSION}")]
    InvalidDimension {
        /// Which width (`d_s`, `d_zeta`, `d_h`).
        name: &'static str,
        /// The rejected value.
        value: usize,
    },
    /// The time-constant range is not `MIN_TAU_S <= tau_min < tau_max <= MAX_TAU_S`.
    #[error(
        "liquid time constants must satisfy {MIN_TAU_S} <= tau_min < tau_max <= {MAX_TAU_S}; got tau_min = {}, tau_max = {}",
        readable(*tau_min),
        readable(*tau_max)
    )]
    InvalidTimeConstants {
        /// Configured τ_min.
        tau_min: f64,
        /// Configured τ_max.
        tau_max: f64,
    },
    /// A tensor's data length does not match its shape.
    #[error("tensor {name}: data has {found} values but its shape needs {expected}")]
    TensorLength {
        /// Tensor name (`<tensor>` for an unnamed one).
        name: String,
        /// Product of the shape.
        expected: usize,
        /// Actual data length.
        found: usize,
    },
    /// A tensor the configuration needs is absent.
    #[error("parameter tensor {name} is missing for this model configuration")]
    MissingParameter {
        /// Tensor name.
        name: &'static str,
    },
    /// A tensor is present that the configuration does not use (e.g. `w_tau_v` with a first-order cell).
    #[error("parameter tensor {name} is not used by this model configuration")]
    UnexpectedParameter {
        /// Tensor name.
        name: &'static str,
    },
    /// A tensor has the wrong shape for the configuration.
    #[error("parameter tensor {name} has shape {found:?}, expected {expected:?}")]
    ShapeMismatch {
        /// Tensor name.
        name: &'static str,
        /// Shape the configuration needs.
        expected: Vec<usize>,
        /// Shape found.
        found: Vec<usize>,
    },
    /// A tensor holds NaN or ±∞.
    #[error("parameter tensor {name} has a non-finite value at flat index {index}")]
    NonFiniteParameter {
        /// Tensor name.
        name: &'static str,
        /// Flat row-major index of the first bad value.
        index: usize,
    },
    /// A tensor holds a finite value beyond ±[`MAX_ABS_PARAMETER`].
    #[error(
        "parameter tensor {name} has {} at flat index {index}, beyond ±{MAX_ABS_PARAMETER:e}",
        readable(*value)
    )]
    ParameterOutOfRange {
        /// Tensor name.
        name: &'static str,
        /// Flat row-major index of the first bad value.
        index: usize,
        /// The value.
        value: f64,
    },
    /// Per-step inputs of a sequence or window do not have the same length.
    #[error("{field} has {found} entries but the sequence has {expected} steps")]
    LengthMismatch {
        /// Which input (`deltas`, `labels`, `mask`, `weights`).
        field: &'static str,
        /// Number of feature rows.
        expected: usize,
        /// Length of `field`.
        found: usize,
    },
    /// A liquid state does not match the model width.
    #[error("liquid state has width {found}, the model needs d_h = {expected}")]
    StateWidth {
        /// The model's d_h.
        expected: usize,
        /// The state's width.
        found: usize,
    },
}

/// Every per-step input of a sequence has one entry per feature row (`expected` of them).
fn check_lengths(expected: usize, inputs: &[(&'static str, usize)]) -> Result<(), ModelError> {
    match inputs.iter().find(|(_, found)| *found != expected) {
        Some(&(field, found)) => Err(ModelError::LengthMismatch {
            field,
            expected,
            found,
        }),
        None => Ok(()),
    }
}

/// Which evidence groups reach the encoders (SPEC §5 ablations, and the drift groups). Removed
/// inputs are set to 0 before the encoders, so shapes stay fixed; a role whose inputs are all removed
/// has the constant state σ(b).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FeatureGroups {
    /// Every ξ entry.
    #[default]
    All,
    /// Drop the accumulated persistence ã.
    NoAccumulation,
    /// Drop the residual evolution η̇, η̈ (the E role sees nothing).
    NoEvolution,
    /// Drop η̇, η̈ and the excess q.
    NoEvolutionNoQ,
    /// Keep only η and ν.
    LowOrderOnly,
    /// Keep only ν.
    ValidityOnly,
    /// Drop every drift channel (v2 reduced to the paper's ξ, same shapes).
    NoDrift,
    /// Drop the uncalibrated drift channels.
    NoRawDrift,
    /// Drop the calibrated drift channels.
    NoCalibratedDrift,
    /// Drop the drift statistic (max over scales).
    NoDriftStatistic,
    /// Drop the warm-up indicator ω.
    NoWarmUp,
    /// Drop the stale-fix duration.
    NoStaleFix,
    /// Drop the log residual size.
    NoResidualLog,
    /// Drop every offset channel (v3 reduced to v2, same shapes).
    NoOffset,
}

impl FeatureGroups {
    /// Every variant with its name on the command line and on the wire (`TrainingSpec.features`).
    pub const NAMED: [(&'static str, FeatureGroups); 14] = [
        ("all", Self::All),
        ("no-accumulation", Self::NoAccumulation),
        ("no-evolution", Self::NoEvolution),
        ("no-evolution-no-q", Self::NoEvolutionNoQ),
        ("low-order-only", Self::LowOrderOnly),
        ("validity-only", Self::ValidityOnly),
        ("no-drift", Self::NoDrift),
        ("no-raw-drift", Self::NoRawDrift),
        ("no-calibrated-drift", Self::NoCalibratedDrift),
        ("no-drift-statistic", Self::NoDriftStatistic),
        ("no-warm-up", Self::NoWarmUp),
        ("no-stale-fix", Self::NoStaleFix),
        ("no-residual-log", Self::NoResidualLog),
        ("no-offset", Self::NoOffset),
    ];

    /// The variant's name in [`Self::NAMED`].
    pub fn name(self) -> &'static str {
        Self::NAMED
            .iter()
            .find(|(_, groups)| *groups == self)
            .map_or("all", |(name, _)| name)
    }

    /// The variant named `name` in [`Self::NAMED`].
    pub fn from_name(name: &str) -> Option<Self> {
        Self::NAMED
            .iter()
            .find(|(n, _)| *n == name)
            .map(|(_, groups)| *groups)
    }

    /// For each ξ index (order of `FEATURE_NAMES`), whether the input is kept.
    pub fn kept(self) -> [bool; FEATURE_CAPACITY] {
        let removed: &[usize] = match self {
            Self::All => &[],
            Self::NoAccumulation => &[7],
            Self::NoEvolution => &[2, 3, 4, 5],
            Self::NoEvolutionNoQ => &[2, 3, 4, 5, 6],
            Self::LowOrderOnly => &[
                2, 3, 4, 5, 6, 7, 9, 10, 11, 12, 13, 14, 15, 16, 17, 18, 19, 20, 21, 22, 23, 24, 25,
            ],
            Self::ValidityOnly => &[
                0, 1, 2, 3, 4, 5, 6, 7, 9, 10, 11, 12, 13, 14, 15, 16, 17, 18, 19, 20, 21, 22, 23,
                24, 25,
            ],
            Self::NoDrift => &[9, 10, 11, 12, 13, 14, 15, 16, 17, 18, 19, 20],
            Self::NoOffset => &[21, 22, 23, 24, 25],
            Self::NoRawDrift => &[9, 10, 11, 12],
            Self::NoCalibratedDrift => &[13, 14, 15, 16],
            Self::NoDriftStatistic => &[17],
            Self::NoWarmUp => &[18],
            Self::NoStaleFix => &[19],
            Self::NoResidualLog => &[20],
        };
        let mut kept = [true; FEATURE_CAPACITY];
        for &index in removed {
            kept[index] = false;
        }
        kept
    }
}

/// Architecture switches for honest ablations (each variant is retrained by the caller).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Ablation {
    /// s̄ = s: no conductance layer at all.
    pub no_exchange: bool,
    /// The product j is left out of the fusion input (W_H has 3·d_s columns).
    pub no_third_order: bool,
    /// v ≡ 0: h_t = h_{t−1} + γ(h̃ − h_{t−1}); no τ^v head; the head reads `[h]` only (a `[h; 0]` head
    /// would carry d_h weights that can never receive a gradient).
    pub first_order_cell: bool,
    /// Evidence groups fed to the encoders.
    pub features: FeatureGroups,
    /// Train on the rows right after an attack's end too (the spoofer's exit jump labelled normal
    /// teaches a model that a big step means "attack over"; by default they leave the loss).
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub no_exit_mask: bool,
    /// Normalise every channel by the training population's noise alone: no per-vehicle levels and
    /// no dead-reckoning misfit (the drift and offset channels' online adaptation is off).
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub no_vehicle_levels: bool,
    /// Trust the onboard calibration by the clock (the calibrated channels on after 240 s of valid
    /// data) instead of by its own uncertainty.
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub timer_trust: bool,
    /// With offset evidence, choose the persistence N_p in rows (the rule of older schemas) instead
    /// of the alarm lifecycle in seconds.
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub rows_lifecycle: bool,
}

/// Model widths, time-constant range and ablation switches. `Default` = SPEC §5.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ModelConfig {
    /// Role-state width d_s.
    pub d_s: usize,
    /// Fusion width d_ζ.
    pub d_zeta: usize,
    /// Liquid state width d_h (h and v).
    pub d_h: usize,
    /// Smallest time constant τ_min (s), for both τ^h and τ^v.
    pub tau_min: f64,
    /// Largest time constant τ_max (s).
    pub tau_max: f64,
    /// Ablation switches.
    pub ablation: Ablation,
    /// The evidence channels the model reads. A stored configuration without it predates named
    /// schemas and is the paper's.
    #[serde(default = "FeatureSchema::legacy")]
    pub schema: FeatureSchema,
}

impl ModelConfig {
    /// Alarms follow the lifecycle in seconds (`docs/detector.md` §7.1): offset evidence, unless
    /// the ablation keeps the persistence in rows.
    pub fn lifecycle_in_seconds(&self) -> bool {
        self.schema.has_offset() && !self.ablation.rows_lifecycle
    }
}

impl Default for ModelConfig {
    fn default() -> Self {
        Self {
            d_s: 32,
            d_zeta: 64,
            d_h: 64,
            tau_min: DEFAULT_TAU_MIN_S,
            tau_max: DEFAULT_TAU_MAX_S,
            ablation: Ablation::default(),
            schema: FeatureSchema::default(),
        }
    }
}

impl ModelConfig {
    /// Checks the widths and the time-constant range.
    pub fn validate(&self) -> Result<(), ModelError> {
        for (name, value) in [
            ("d_s", self.d_s),
            ("d_zeta", self.d_zeta),
            ("d_h", self.d_h),
        ] {
            if value == 0 || value > MAX_DIMENSION {
                return Err(ModelError::InvalidDimension { name, value });
            }
        }
        let parameters = Params::count_for(self);
        if parameters > MAX_PARAMETERS {
            return Err(ModelError::TooManyParameters { parameters });
        }
        let ordered = self.tau_min >= MIN_TAU_S && self.tau_max > self.tau_min;
        if !(ordered && self.tau_max <= MAX_TAU_S) {
            return Err(ModelError::InvalidTimeConstants {
                tau_min: self.tau_min,
                tau_max: self.tau_max,
            });
        }
        Ok(())
    }

    /// Width of the fusion input `[s̄^I; s̄^E; s̄^P; j]` (without `j` under `no_third_order`).
    pub fn fusion_input_len(&self) -> usize {
        if self.ablation.no_third_order {
            3 * self.d_s
        } else {
            4 * self.d_s
        }
    }

    /// Width of the persistence role's input P (2 for the paper's ξ, 14 for v2).
    pub fn persistence_width(&self) -> usize {
        2 + self.schema.feature_count() - DRIFT_FEATURES_START
    }

    /// Width of the head input: `[h; v]`, or `[h]` for the first-order cell.
    pub fn head_input_len(&self) -> usize {
        if self.ablation.first_order_cell {
            self.d_h
        } else {
            2 * self.d_h
        }
    }
}

/// The liquid state (h, v) of one trajectory. Zero at a trajectory start.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LiquidState {
    h: Vec<f64>,
    v: Vec<f64>,
}

impl LiquidState {
    /// The zero state for a model of this configuration.
    pub fn zeros(config: &ModelConfig) -> Self {
        Self {
            h: vec![0.0; config.d_h],
            v: vec![0.0; config.d_h],
        }
    }

    /// A state from explicit vectors (both of the model width d_h).
    pub fn from_parts(h: Vec<f64>, v: Vec<f64>) -> Result<Self, ModelError> {
        if h.len() != v.len() {
            return Err(ModelError::StateWidth {
                expected: h.len(),
                found: v.len(),
            });
        }
        Ok(Self { h, v })
    }

    /// Memory state h.
    pub fn h(&self) -> &[f64] {
        &self.h
    }

    /// Evolution state v (identically 0 for the first-order cell).
    pub fn v(&self) -> &[f64] {
        &self.v
    }

    /// Whether this state has the width `config` needs.
    pub fn fits(&self, config: &ModelConfig) -> bool {
        self.h.len() == config.d_h && self.v.len() == config.d_h
    }

    /// Resets to zero (a new trajectory), keeping the allocation.
    pub fn reset(&mut self) {
        self.h.fill(0.0);
        self.v.fill(0.0);
    }
}

/// A trained (or initialised) HO-LLN model: configuration plus validated parameters.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "ModelParts")]
pub struct Model {
    config: ModelConfig,
    params: Params,
}

/// Unvalidated serde form of [`Model`] (the artifact reader checks it with [`Model::from_parts`]).
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct ModelParts {
    pub(crate) config: ModelConfig,
    pub(crate) params: Params,
}

impl TryFrom<ModelParts> for Model {
    type Error = ModelError;

    fn try_from(parts: ModelParts) -> Result<Self, Self::Error> {
        Model::from_parts(parts.config, parts.params)
    }
}

impl Model {
    /// A fresh model: Xavier-uniform weights and zero biases drawn from `seed`.
    pub fn init(config: ModelConfig, seed: u64) -> Result<Self, ModelError> {
        config.validate()?;
        let params = Params::xavier(&config, &mut Rng::seed_from_u64(seed));
        Ok(Self { config, params })
    }

    /// A model from stored parameters, checked against the configuration (names, shapes, finiteness).
    pub fn from_parts(config: ModelConfig, params: Params) -> Result<Self, ModelError> {
        config.validate()?;
        params.validate(&config)?;
        Ok(Self { config, params })
    }

    /// The configuration.
    pub fn config(&self) -> &ModelConfig {
        &self.config
    }

    /// The parameter tensors.
    pub fn params(&self) -> &Params {
        &self.params
    }

    /// Mutable parameters for the optimiser (shapes are fixed; values must stay finite).
    pub(crate) fn params_mut(&mut self) -> &mut Params {
        &mut self.params
    }

    /// Number of trainable scalars.
    pub fn parameter_count(&self) -> usize {
        self.params.scalar_count()
    }

    /// Advances one vehicle by one sample and returns p̂_t.
    ///
    /// `x` is the scaled ξ_t; non-finite entries are read as 0 (the scaler's NaN convention), so a bad
    /// value can never poison the state for the rest of the trajectory. `delta_t` is clamped to
    /// `[0, MAX_DELTA_S]` (NaN → 0); pass 0 at a trajectory start so the state does not move.
    /// A state of the wrong width (built for another model) is reset to zeros first, as a new
    /// trajectory. `scratch` holds the intermediate activations so that no step allocates.
    pub fn step(
        &self,
        state: &mut LiquidState,
        x: &Features,
        delta_t: f64,
        scratch: &mut StepScratch,
    ) -> f64 {
        if !state.fits(&self.config) {
            *state = LiquidState::zeros(&self.config);
        }
        let logit = self.forward_step(state, x, delta_t, scratch);
        fastmath::sigmoid(logit)
    }

    /// p̂ for every step of a sequence, continuing from `state` (left at the final state). Built on
    /// [`Model::step`], so both give bit-identical outputs.
    pub fn forward_sequence(
        &self,
        xs: &[Features],
        deltas: &[f64],
        state: &mut LiquidState,
    ) -> Result<Vec<f64>, ModelError> {
        check_lengths(xs.len(), &[("deltas", deltas.len())])?;
        Ok(self.map_sequence(xs, deltas, state, Self::step))
    }

    /// Runs `step` over a sequence whose lengths the caller has checked, with one scratch for all
    /// steps: the loop shared by [`Model::forward_sequence`] and [`Model::forward_logits`].
    pub(crate) fn map_sequence(
        &self,
        xs: &[Features],
        deltas: &[f64],
        state: &mut LiquidState,
        step: fn(&Self, &mut LiquidState, &Features, f64, &mut StepScratch) -> f64,
    ) -> Vec<f64> {
        let mut scratch = StepScratch::new(&self.config);
        xs.iter()
            .zip(deltas)
            .map(|(x, &delta)| step(self, state, x, delta, &mut scratch))
            .collect()
    }
}

/// p̂ = σ(logit), exactly as [`Model::step`] computes it from the head logit.
pub fn probability_from_logit(logit: f64) -> f64 {
    fastmath::sigmoid(logit)
}

/// δ_t as the liquid cell sees it: NaN → 0, then clamped to `[0, MAX_DELTA_S]`.
pub fn clamp_delta(delta_t: f64) -> f64 {
    if delta_t.is_nan() {
        0.0
    } else {
        delta_t.clamp(0.0, MAX_DELTA_S)
    }
}

#[cfg(test)]
mod tests;
