//! Named parameter tensors of the HO-LLN model (also used for their gradients and optimiser moments).
//!
//! Storage is plain row-major `Vec<f64>`: at these sizes (≤ 64×128) hand-written loops are simpler than
//! nalgebra views, allocation-free in the serving path, and give a summation order we control (which keeps
//! training bit-for-bit reproducible).
//!
//! Owns the parameter tensors, their layout and initialisation. Must not compute forward or backward
//! passes.

use serde::{Deserialize, Serialize};

use super::{MAX_ABS_PARAMETER, ModelConfig, ModelError};
use crate::rng::Rng;

/// One parameter tensor: a shape and its row-major data (`data.len()` = product of `shape`).
///
/// Matrices are `[rows, cols]` and act as `y = W x` (rows = outputs, cols = inputs).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Tensor {
    shape: Vec<usize>,
    data: Vec<f64>,
}

impl Tensor {
    /// A tensor; fails when the data length does not match the shape.
    pub fn new(shape: Vec<usize>, data: Vec<f64>) -> Result<Self, ModelError> {
        let expected: usize = shape.iter().product();
        if data.len() != expected {
            return Err(ModelError::TensorLength {
                name: "<tensor>".to_owned(),
                expected,
                found: data.len(),
            });
        }
        Ok(Self { shape, data })
    }

    /// An all-zero tensor of the given shape.
    pub fn zeros(shape: &[usize]) -> Self {
        Self {
            shape: shape.to_vec(),
            data: vec![0.0; shape.iter().product()],
        }
    }

    /// The shape (`[rows, cols]` for matrices, `[n]` for vectors).
    pub fn shape(&self) -> &[usize] {
        &self.shape
    }

    /// Row-major values.
    pub fn data(&self) -> &[f64] {
        &self.data
    }

    /// Mutable row-major values (the shape cannot change).
    pub fn data_mut(&mut self) -> &mut [f64] {
        &mut self.data
    }

    /// Whether this tensor is a matrix (≥ 2 dims); only matrices get weight decay.
    pub fn is_matrix(&self) -> bool {
        self.shape.len() >= 2
    }
}

/// Whether a tensor is a weight (Xavier-uniform init) or a bias (zero init).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum ParamKind {
    Weight,
    Bias,
}

/// Every parameter tensor of the model, by name. Optional tensors exist only when the architecture uses
/// them (`no_exchange` removes the conductance layer, `first_order_cell` removes the τ^v head), so the
/// parameter count of an ablation is honest.
///
/// Serialises as a JSON object `name → {shape, data}`; unknown names are rejected.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Params {
    /// Instantaneous-role encoder `W_I` `[d_s, 3]` (inputs η_E, η_N, q).
    pub(crate) w_instant: Tensor,
    /// `b_I` `[d_s]`.
    pub(crate) b_instant: Tensor,
    /// Evolution-role encoder `W_E` `[d_s, 4]` (inputs η̇_E, η̇_N, η̈_E, η̈_N).
    pub(crate) w_evolution: Tensor,
    /// `b_E` `[d_s]`.
    pub(crate) b_evolution: Tensor,
    /// Persistence-role encoder `W_P` `[d_s, 2]` (inputs ã, ν).
    pub(crate) w_persistence: Tensor,
    /// `b_P` `[d_s]`.
    pub(crate) b_persistence: Tensor,
    /// Shared conductance weights `w_C` `[2 d_s]` over `[|s^i − s^j|; s^i ⊙ s^j]`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub(crate) w_conductance: Option<Tensor>,
    /// Conductance bias `b_C` `[1]`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub(crate) b_conductance: Option<Tensor>,
    /// Fusion `W_H` `[d_ζ, 4 d_s]` (`[d_ζ, 3 d_s]` without the third-order term).
    pub(crate) w_fusion: Tensor,
    /// `b_H` `[d_ζ]`.
    pub(crate) b_fusion: Tensor,
    /// Liquid candidate `W_c` `[d_h, d_ζ]`.
    pub(crate) w_candidate: Tensor,
    /// `b_c` `[d_h]`.
    pub(crate) b_candidate: Tensor,
    /// Memory time-constant head `W_τh` `[d_h, d_ζ]`.
    pub(crate) w_tau_h: Tensor,
    /// `b_τh` `[d_h]`.
    pub(crate) b_tau_h: Tensor,
    /// Evolution time-constant head `W_τv` `[d_h, d_ζ]` (absent in the first-order cell).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub(crate) w_tau_v: Option<Tensor>,
    /// `b_τv` `[d_h]`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub(crate) b_tau_v: Option<Tensor>,
    /// Output head `w_o` `[2 d_h]` over `[h; v]` (`[d_h]` over `[h]` in the first-order cell).
    pub(crate) w_out: Tensor,
    /// `b_o` `[1]`.
    pub(crate) b_out: Tensor,
}

impl Params {
    /// Builds every tensor the configuration needs, in the canonical order, with `make(name, shape, kind)`.
    fn build(config: &ModelConfig, mut make: impl FnMut(&[usize], ParamKind) -> Tensor) -> Self {
        use ParamKind::{Bias, Weight};
        let (ds, dz, dh) = (config.d_s, config.d_zeta, config.d_h);
        let ablation = &config.ablation;
        Self {
            w_instant: make(&[ds, 3], Weight),
            b_instant: make(&[ds], Bias),
            w_evolution: make(&[ds, 4], Weight),
            b_evolution: make(&[ds], Bias),
            w_persistence: make(&[ds, config.persistence_width()], Weight),
            b_persistence: make(&[ds], Bias),
            w_conductance: (!ablation.no_exchange).then(|| make(&[2 * ds], Weight)),
            b_conductance: (!ablation.no_exchange).then(|| make(&[1], Bias)),
            w_fusion: make(&[dz, config.fusion_input_len()], Weight),
            b_fusion: make(&[dz], Bias),
            w_candidate: make(&[dh, dz], Weight),
            b_candidate: make(&[dh], Bias),
            w_tau_h: make(&[dh, dz], Weight),
            b_tau_h: make(&[dh], Bias),
            w_tau_v: (!ablation.first_order_cell).then(|| make(&[dh, dz], Weight)),
            b_tau_v: (!ablation.first_order_cell).then(|| make(&[dh], Bias)),
            w_out: make(&[config.head_input_len()], Weight),
            b_out: make(&[1], Bias),
        }
    }

    /// How many scalars a model of `config` has, counted from the shapes alone (nothing of that
    /// size is allocated: a configuration is checked before its tensors exist).
    pub fn count_for(config: &ModelConfig) -> usize {
        let mut count = 0usize;
        Self::build(config, |shape, _| {
            count = count.saturating_add(shape.iter().fold(1usize, |n, d| n.saturating_mul(*d)));
            Tensor {
                shape: shape.to_vec(),
                data: Vec::new(),
            }
        });
        count
    }

    /// All-zero tensors shaped for `config` (gradient accumulators, optimiser moments).
    pub fn zeros(config: &ModelConfig) -> Self {
        Self::build(config, |shape, _| Tensor::zeros(shape))
    }

    /// Xavier-uniform weights (a 1-D weight vector is a layer with one output) and zero biases, drawn
    /// from `rng` in the canonical tensor order.
    pub(crate) fn xavier(config: &ModelConfig, rng: &mut Rng) -> Self {
        Self::build(config, |shape, kind| {
            let mut tensor = Tensor::zeros(shape);
            if kind == ParamKind::Weight {
                let (fan_out, fan_in) = match shape {
                    [rows, cols] => (*rows, *cols),
                    [n] => (1, *n),
                    _ => (1, 1),
                };
                let bound = (6.0 / (fan_in + fan_out) as f64).sqrt();
                for value in tensor.data_mut() {
                    *value = rng.uniform_range(-bound, bound);
                }
            }
            tensor
        })
    }

    /// `(name, tensor)` for every present tensor, in the canonical order.
    pub fn tensors(&self) -> Vec<(&'static str, &Tensor)> {
        let slots: [(&'static str, Option<&Tensor>); 18] = [
            ("w_instant", Some(&self.w_instant)),
            ("b_instant", Some(&self.b_instant)),
            ("w_evolution", Some(&self.w_evolution)),
            ("b_evolution", Some(&self.b_evolution)),
            ("w_persistence", Some(&self.w_persistence)),
            ("b_persistence", Some(&self.b_persistence)),
            ("w_conductance", self.w_conductance.as_ref()),
            ("b_conductance", self.b_conductance.as_ref()),
            ("w_fusion", Some(&self.w_fusion)),
            ("b_fusion", Some(&self.b_fusion)),
            ("w_candidate", Some(&self.w_candidate)),
            ("b_candidate", Some(&self.b_candidate)),
            ("w_tau_h", Some(&self.w_tau_h)),
            ("b_tau_h", Some(&self.b_tau_h)),
            ("w_tau_v", self.w_tau_v.as_ref()),
            ("b_tau_v", self.b_tau_v.as_ref()),
            ("w_out", Some(&self.w_out)),
            ("b_out", Some(&self.b_out)),
        ];
        slots
            .into_iter()
            .filter_map(|(name, tensor)| tensor.map(|t| (name, t)))
            .collect()
    }

    /// Mutable `(name, tensor)` for every present tensor, in the canonical order.
    pub fn tensors_mut(&mut self) -> Vec<(&'static str, &mut Tensor)> {
        let slots: [(&'static str, Option<&mut Tensor>); 18] = [
            ("w_instant", Some(&mut self.w_instant)),
            ("b_instant", Some(&mut self.b_instant)),
            ("w_evolution", Some(&mut self.w_evolution)),
            ("b_evolution", Some(&mut self.b_evolution)),
            ("w_persistence", Some(&mut self.w_persistence)),
            ("b_persistence", Some(&mut self.b_persistence)),
            ("w_conductance", self.w_conductance.as_mut()),
            ("b_conductance", self.b_conductance.as_mut()),
            ("w_fusion", Some(&mut self.w_fusion)),
            ("b_fusion", Some(&mut self.b_fusion)),
            ("w_candidate", Some(&mut self.w_candidate)),
            ("b_candidate", Some(&mut self.b_candidate)),
            ("w_tau_h", Some(&mut self.w_tau_h)),
            ("b_tau_h", Some(&mut self.b_tau_h)),
            ("w_tau_v", self.w_tau_v.as_mut()),
            ("b_tau_v", self.b_tau_v.as_mut()),
            ("w_out", Some(&mut self.w_out)),
            ("b_out", Some(&mut self.b_out)),
        ];
        slots
            .into_iter()
            .filter_map(|(name, tensor)| tensor.map(|t| (name, t)))
            .collect()
    }

    /// The tensor called `name`, if present.
    pub fn get(&self, name: &str) -> Option<&Tensor> {
        self.tensors()
            .into_iter()
            .find_map(|(n, t)| (n == name).then_some(t))
    }

    /// Total number of scalar parameters.
    pub fn scalar_count(&self) -> usize {
        self.tensors().iter().map(|(_, t)| t.data.len()).sum()
    }

    /// Checks names, shapes, finiteness and the magnitude bound [`MAX_ABS_PARAMETER`] against what
    /// `config` needs.
    pub fn validate(&self, config: &ModelConfig) -> Result<(), ModelError> {
        let template = Self::zeros(config);
        let expected = template.tensors();
        let found = self.tensors();
        for (name, want) in &expected {
            let Some((_, have)) = found.iter().find(|(n, _)| n == name) else {
                return Err(ModelError::MissingParameter { name });
            };
            if have.shape != want.shape {
                return Err(ModelError::ShapeMismatch {
                    name,
                    expected: want.shape.clone(),
                    found: have.shape.clone(),
                });
            }
            if have.data.len() != want.data.len() {
                return Err(ModelError::TensorLength {
                    name: (*name).to_owned(),
                    expected: want.data.len(),
                    found: have.data.len(),
                });
            }
            if let Some(index) = have.data.iter().position(|v| !v.is_finite()) {
                return Err(ModelError::NonFiniteParameter { name, index });
            }
            if let Some((index, &value)) = have
                .data
                .iter()
                .enumerate()
                .find(|(_, v)| v.abs() > MAX_ABS_PARAMETER)
            {
                return Err(ModelError::ParameterOutOfRange { name, index, value });
            }
        }
        if let Some((name, _)) = found
            .iter()
            .find(|(n, _)| !expected.iter().any(|(e, _)| e == n))
        {
            return Err(ModelError::UnexpectedParameter { name });
        }
        Ok(())
    }

    /// Sets every entry to zero (reusing the allocations).
    pub(crate) fn fill_zero(&mut self) {
        for (_, tensor) in self.tensors_mut() {
            tensor.data.fill(0.0);
        }
    }

    /// `self += other`, entry by entry in the canonical order (same configuration required).
    pub(crate) fn add_assign(&mut self, other: &Params) {
        for ((_, mine), (_, theirs)) in self.tensors_mut().into_iter().zip(other.tensors()) {
            for (a, b) in mine.data.iter_mut().zip(&theirs.data) {
                *a += b;
            }
        }
    }

    /// `self *= factor`.
    pub(crate) fn scale(&mut self, factor: f64) {
        for (_, tensor) in self.tensors_mut() {
            for value in &mut tensor.data {
                *value *= factor;
            }
        }
    }

    /// Euclidean norm over every entry (summed in the canonical order).
    pub(crate) fn l2_norm(&self) -> f64 {
        self.tensors()
            .iter()
            .flat_map(|(_, t)| t.data.iter())
            .map(|v| v * v)
            .sum::<f64>()
            .sqrt()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::evidence::FeatureSchema;
    use crate::model::{Ablation, FeatureGroups};

    #[test]
    fn default_parameter_count_is_hand_computed() {
        // Encoders (32·3+32)+(32·4+32)+(32·14+32) = 768 (v2: P = [ã, ν, 10 drift and 2 integrity
        // channels]); conductance 64+1; fusion 64·128+64 = 8256; cell 3·(64·64+64) = 12480; head 128+1.
        let v2 = ModelConfig {
            schema: FeatureSchema::V2,
            ..ModelConfig::default()
        };
        assert_eq!(
            Params::zeros(&v2).scalar_count(),
            768 + 65 + 8256 + 12480 + 129
        );
        // v3 (the default) adds 5 offset channels to P: 5·32 more encoder weights.
        assert_eq!(ModelConfig::default().schema, FeatureSchema::V3);
        assert_eq!(
            Params::zeros(&ModelConfig::default()).scalar_count(),
            768 + 160 + 65 + 8256 + 12480 + 129
        );
        assert_eq!(Params::zeros(&v2).tensors().len(), 18);
        // The paper's P = [ã, ν]: encoders 384.
        let paper = ModelConfig {
            schema: FeatureSchema::Paper,
            ..ModelConfig::default()
        };
        assert_eq!(
            Params::zeros(&paper).scalar_count(),
            384 + 65 + 8256 + 12480 + 129
        );
    }

    #[test]
    fn ablations_remove_the_tensors_they_do_not_use() {
        let config = ModelConfig {
            ablation: Ablation {
                no_exchange: true,
                no_third_order: true,
                first_order_cell: true,
                features: FeatureGroups::All,
                ..Ablation::default()
            },
            schema: FeatureSchema::Paper,
            ..ModelConfig::default()
        };
        let params = Params::zeros(&config);
        let names: Vec<_> = params.tensors().iter().map(|(n, _)| *n).collect();
        assert!(!names.contains(&"w_conductance") && !names.contains(&"b_tau_v"));
        assert_eq!(
            params.get("w_fusion").map(Tensor::shape),
            Some(&[64, 96][..])
        );
        assert_eq!(params.get("w_out").map(Tensor::shape), Some(&[64][..]));
        // 384 + (64·96+64) + 2·(64·64+64) + (64+1)
        assert_eq!(params.scalar_count(), 384 + 6208 + 8320 + 65);
    }

    #[test]
    fn xavier_respects_bounds_and_zero_biases() {
        let config = ModelConfig::default();
        let params = Params::xavier(&config, &mut Rng::seed_from_u64(3));
        let bound = (6.0f64 / (128.0 + 64.0)).sqrt();
        let fusion = params.w_fusion.data();
        assert!(fusion.iter().all(|v| v.abs() <= bound));
        assert!(fusion.iter().any(|v| v.abs() > 0.9 * bound));
        assert!(params.b_fusion.data().iter().all(|&v| v == 0.0));
        let conductance_bound = (6.0f64 / 65.0).sqrt();
        let conductance = params.w_conductance.as_ref().map(Tensor::data);
        assert!(conductance.is_some_and(|c| c.iter().all(|v| v.abs() <= conductance_bound)));
    }

    #[test]
    fn validate_reports_the_first_problem_precisely() {
        let config = ModelConfig::default();
        let mut params = Params::zeros(&config);
        assert!(params.validate(&config).is_ok());
        params.w_tau_v = None;
        assert!(matches!(
            params.validate(&config),
            Err(ModelError::MissingParameter { name: "w_tau_v" })
        ));
        let mut params = Params::zeros(&config);
        params.b_out.data[0] = f64::NAN;
        assert!(matches!(
            params.validate(&config),
            Err(ModelError::NonFiniteParameter {
                name: "b_out",
                index: 0
            })
        ));
        let first_order = ModelConfig {
            ablation: Ablation {
                first_order_cell: true,
                ..Ablation::default()
            },
            ..ModelConfig::default()
        };
        let params = Params::zeros(&config);
        assert!(matches!(
            params.validate(&first_order),
            Err(ModelError::ShapeMismatch { name: "w_out", .. })
        ));
    }
}
