//! Loss and hand-derived backpropagation through time over one window.
//!
//! Loss (SPEC §6, as the reference): weighted binary cross-entropy in logit form on the masked (ν = 1)
//! rows, `L = Σ_masked w_t·ℓ(z_t, y_t) / N_masked`. The incoming state of a window is a constant:
//! gradients stop at window boundaries (truncated BPTT).
//!
//! Owns the gradients of one training window. Must not update parameters (that is `train/optim.rs`).

use super::fastmath::sigmoid;
use super::forward::{PAIRS, StepScratch};
use super::linalg::{affine_backward, axpy, sign};
use super::{LiquidState, Model, ModelConfig, ModelError, Params, check_lengths};
use crate::evidence::Features;

/// Weighted BCE with logits, `w·(max(z,0) − z·y + ln(1 + e^{−|z|}))` (log-sum-exp stable).
pub fn bce_with_logits(logit: f64, label: bool, weight: f64) -> f64 {
    let y = if label { 1.0 } else { 0.0 };
    weight * (logit.max(0.0) - logit * y + (-logit.abs()).exp().ln_1p())
}

/// d/dz of [`bce_with_logits`]: `w·(σ(z) − y)`.
fn bce_with_logits_grad(logit: f64, label: bool, weight: f64) -> f64 {
    let y = if label { 1.0 } else { 0.0 };
    weight * (sigmoid(logit) - y)
}

/// One training window: per-step inputs, labels, loss mask (ν = 1 rows) and per-row loss weights.
#[derive(Clone, Copy, Debug)]
pub struct TrainingWindow<'a> {
    /// Scaled ξ rows.
    pub features: &'a [Features],
    /// δ_t per row (clamped as in serving).
    pub deltas: &'a [f64],
    /// Spoofing labels.
    pub labels: &'a [bool],
    /// Rows that count in the loss (ν = 1).
    pub mask: &'a [bool],
    /// Per-row loss weights (the class weight α of the row's label).
    pub weights: &'a [f64],
}

impl TrainingWindow<'_> {
    fn validate(&self) -> Result<(), ModelError> {
        check_lengths(
            self.features.len(),
            &[
                ("deltas", self.deltas.len()),
                ("labels", self.labels.len()),
                ("mask", self.mask.len()),
                ("weights", self.weights.len()),
            ],
        )
    }
}

/// Unnormalised loss of one window: the caller divides by the masked-row count of its batch.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct WindowLoss {
    /// Σ over masked rows of `w_t·ℓ_t`.
    pub loss_sum: f64,
    /// Number of masked rows.
    pub masked_rows: usize,
}

/// Loss and gradient of one window on its own (normalised by its own masked-row count).
#[derive(Clone, Debug)]
pub struct WindowGradient {
    /// Mean weighted loss over the masked rows (0 when there are none).
    pub loss: f64,
    /// Number of masked rows.
    pub masked_rows: usize,
    /// dL/dθ for every parameter tensor.
    pub gradient: Params,
    /// Liquid state after the window's last step.
    pub state_out: LiquidState,
}

/// Reusable buffers for BPTT (one per thread): the forward activations of every step and the
/// backward work vectors.
#[derive(Clone, Debug, Default)]
pub struct Tape {
    steps: Vec<StepScratch>,
    d_logits: Vec<f64>,
    back: BackwardScratch,
}

/// Gradient work vectors of one step.
#[derive(Clone, Debug, Default)]
struct BackwardScratch {
    /// dL/dh and dL/dv of the state after the current step (before it: of the state it came from).
    dh: Vec<f64>,
    dv: Vec<f64>,
    d_pre_candidate: Vec<f64>,
    d_pre_tau_h: Vec<f64>,
    d_pre_tau_v: Vec<f64>,
    d_zeta: Vec<f64>,
    d_fusion_in: Vec<f64>,
    /// dL/ds̄ per role.
    d_bar: [Vec<f64>; 3],
    /// dL/ds per role, then dL/d(pre-activation) per role.
    d_s: [Vec<f64>; 3],
}

impl BackwardScratch {
    fn fit(&mut self, config: &ModelConfig) {
        for buffer in [
            &mut self.dh,
            &mut self.dv,
            &mut self.d_pre_candidate,
            &mut self.d_pre_tau_h,
            &mut self.d_pre_tau_v,
        ] {
            buffer.resize(config.d_h, 0.0);
        }
        self.d_zeta.resize(config.d_zeta, 0.0);
        self.d_fusion_in.resize(config.fusion_input_len(), 0.0);
        for buffer in self.d_bar.iter_mut().chain(self.d_s.iter_mut()) {
            buffer.resize(config.d_s, 0.0);
        }
    }
}

impl Model {
    /// Head logits for every step of a sequence, continuing from `state` (the same arithmetic as
    /// [`Model::step`], which returns σ of these).
    pub fn forward_logits(
        &self,
        xs: &[Features],
        deltas: &[f64],
        state: &mut LiquidState,
    ) -> Result<Vec<f64>, ModelError> {
        check_lengths(xs.len(), &[("deltas", deltas.len())])?;
        self.check_state(state)?;
        Ok(self.map_sequence(xs, deltas, state, Self::forward_step))
    }

    /// Loss, gradient and outgoing state of one window starting from `state_in` (a constant).
    pub fn loss_and_gradient(
        &self,
        window: &TrainingWindow<'_>,
        state_in: &LiquidState,
    ) -> Result<WindowGradient, ModelError> {
        let mut state = state_in.clone();
        let mut gradient = Params::zeros(&self.config);
        let mut tape = Tape::default();
        let loss = self.accumulate_window_gradient(window, &mut state, &mut tape, &mut gradient)?;
        let (mean_loss, masked_rows) = (loss.loss_sum, loss.masked_rows);
        let mean_loss = if masked_rows > 0 {
            gradient.scale(1.0 / masked_rows as f64);
            mean_loss / masked_rows as f64
        } else {
            0.0
        };
        Ok(WindowGradient {
            loss: mean_loss,
            masked_rows,
            gradient,
            state_out: state,
        })
    }

    /// Runs the window forward from `state` (advanced to the window's end) and ADDS the gradient of the
    /// unnormalised loss `Σ_masked w_t·ℓ_t` to `gradient` (which must be shaped for this model).
    pub fn accumulate_window_gradient(
        &self,
        window: &TrainingWindow<'_>,
        state: &mut LiquidState,
        tape: &mut Tape,
        gradient: &mut Params,
    ) -> Result<WindowLoss, ModelError> {
        window.validate()?;
        self.check_state(state)?;
        gradient.validate(&self.config)?;
        let steps = window.features.len();
        if tape.steps.len() < steps {
            tape.steps.resize_with(steps, StepScratch::default);
        }
        tape.d_logits.clear();
        let mut loss = WindowLoss {
            loss_sum: 0.0,
            masked_rows: 0,
        };
        let mut last_masked = None;
        for t in 0..steps {
            let logit = self.forward_step(
                state,
                &window.features[t],
                window.deltas[t],
                &mut tape.steps[t],
            );
            let (label, weight) = (window.labels[t], window.weights[t]);
            let d_logit = if window.mask[t] {
                loss.loss_sum += bce_with_logits(logit, label, weight);
                loss.masked_rows += 1;
                last_masked = Some(t);
                bce_with_logits_grad(logit, label, weight)
            } else {
                0.0
            };
            tape.d_logits.push(d_logit);
        }
        let back = &mut tape.back;
        back.fit(&self.config);
        back.dh.fill(0.0);
        back.dv.fill(0.0);
        // Steps after the last masked row receive no gradient at all.
        if let Some(last) = last_masked {
            for t in (0..=last).rev() {
                self.backward_step(&tape.steps[t], tape.d_logits[t], back, gradient);
            }
        }
        Ok(loss)
    }

    fn check_state(&self, state: &LiquidState) -> Result<(), ModelError> {
        if state.fits(&self.config) {
            Ok(())
        } else {
            Err(ModelError::StateWidth {
                expected: self.config.d_h,
                found: state.h().len().max(state.v().len()),
            })
        }
    }

    /// Backward of one step. On entry `back.dh/dv` are dL/d(state after the step), on exit dL/d(state
    /// before it); parameter gradients are added to `grad`.
    fn backward_step(
        &self,
        rec: &StepScratch,
        d_logit: f64,
        back: &mut BackwardScratch,
        grad: &mut Params,
    ) {
        self.backward_head(rec, d_logit, back, grad);
        self.backward_cell(rec, back);
        self.backward_cell_layers(rec, back, grad);
        self.backward_fusion(rec, back, grad);
        self.backward_exchange(rec, back, grad);
        self.backward_encoders(rec, back, grad);
    }

    /// logit = w_o·[h; v] + b_o.
    fn backward_head(
        &self,
        rec: &StepScratch,
        d_logit: f64,
        back: &mut BackwardScratch,
        grad: &mut Params,
    ) {
        let dh_len = self.config.d_h;
        let w_out = self.params.w_out.data();
        let g_out = grad.w_out.data_mut();
        axpy(d_logit, &rec.h, &mut g_out[..dh_len]);
        axpy(d_logit, &w_out[..dh_len], &mut back.dh);
        if !self.config.ablation.first_order_cell {
            axpy(d_logit, &rec.v, &mut g_out[dh_len..]);
            axpy(d_logit, &w_out[dh_len..], &mut back.dv);
        }
        grad.b_out.data_mut()[0] += d_logit;
    }

    /// The state update: from dL/d(h_t, v_t) to dL/d(h_{t−1}, v_{t−1}) and the pre-activation
    /// gradients of the candidate and time-constant heads.
    fn backward_cell(&self, rec: &StepScratch, back: &mut BackwardScratch) {
        let config = &self.config;
        let tau_range = config.tau_max - config.tau_min;
        let delta = rec.delta;
        let first_order = config.ablation.first_order_cell;
        for k in 0..config.d_h {
            let dh = back.dh[k];
            let gamma = rec.gamma[k];
            let pull = rec.candidate[k] - rec.h_prev[k];
            let (d_gamma, d_candidate) = if first_order {
                // h_t = h_{t−1} + γ (h̃ − h_{t−1})
                back.dh[k] = dh * (1.0 - gamma);
                back.dv[k] = 0.0;
                (dh * pull, dh * gamma)
            } else {
                // v_t = β v_{t−1} + (1 − β)(h̃ − h_{t−1});  h_t = h_{t−1} + γ v_t
                let beta = rec.beta[k];
                let dv_total = back.dv[k] + dh * gamma;
                let d_beta = dv_total * (rec.v_prev[k] - pull);
                back.dh[k] = dh - dv_total * (1.0 - beta);
                back.dv[k] = dv_total * beta;
                // β = exp(−δ/τ^v): dβ/dτ^v = β δ / τ^v²;  τ^v = τ_min + R σ(a)
                let tau_v = rec.tau_v[k];
                let sig_v = rec.sig_tau_v[k];
                let d_tau_v = d_beta * beta * delta / (tau_v * tau_v);
                back.d_pre_tau_v[k] = d_tau_v * tau_range * sig_v * (1.0 - sig_v);
                (dh * rec.v[k], dv_total * (1.0 - beta))
            };
            // γ = 1 − exp(−δ/τ^h): dγ/dτ^h = −(1 − γ) δ / τ^h²
            let tau_h = rec.tau_h[k];
            let sig_h = rec.sig_tau_h[k];
            let d_tau_h = -d_gamma * (1.0 - gamma) * delta / (tau_h * tau_h);
            back.d_pre_tau_h[k] = d_tau_h * tau_range * sig_h * (1.0 - sig_h);
            let candidate = rec.candidate[k];
            back.d_pre_candidate[k] = d_candidate * (1.0 - candidate * candidate);
        }
    }

    /// The three ζ → (h̃, τ^h, τ^v) layers: weight gradients and dL/dζ.
    fn backward_cell_layers(
        &self,
        rec: &StepScratch,
        back: &mut BackwardScratch,
        grad: &mut Params,
    ) {
        let p = &self.params;
        back.d_zeta.fill(0.0);
        // The τ^v layer is absent in the first-order cell; the order of accumulation into dL/dζ is
        // fixed (h̃, τ^h, τ^v) so training stays bit-reproducible.
        let tau_v = match (&p.w_tau_v, &mut grad.w_tau_v, &mut grad.b_tau_v) {
            (Some(w), Some(gw), Some(gb)) => Some((w, &back.d_pre_tau_v, gw, gb)),
            _ => None,
        };
        let layers = [
            Some((
                &p.w_candidate,
                &back.d_pre_candidate,
                &mut grad.w_candidate,
                &mut grad.b_candidate,
            )),
            Some((
                &p.w_tau_h,
                &back.d_pre_tau_h,
                &mut grad.w_tau_h,
                &mut grad.b_tau_h,
            )),
            tau_v,
        ];
        for (w, d_pre, grad_w, grad_b) in layers.into_iter().flatten() {
            affine_backward(
                w.data(),
                &rec.zeta,
                d_pre,
                grad_w.data_mut(),
                grad_b.data_mut(),
                Some(&mut back.d_zeta),
            );
        }
    }

    /// ζ = tanh(W_H [s̄^I; s̄^E; s̄^P; j] + b_H) and j = s̄^I ⊙ s̄^E ⊙ s̄^P: gives dL/ds̄ per role.
    fn backward_fusion(&self, rec: &StepScratch, back: &mut BackwardScratch, grad: &mut Params) {
        let ds = self.config.d_s;
        for (d, &zeta) in back.d_zeta.iter_mut().zip(&rec.zeta) {
            *d *= 1.0 - zeta * zeta;
        }
        back.d_fusion_in.fill(0.0);
        affine_backward(
            self.params.w_fusion.data(),
            &rec.fusion_in,
            &back.d_zeta,
            grad.w_fusion.data_mut(),
            grad.b_fusion.data_mut(),
            Some(&mut back.d_fusion_in),
        );
        for (role, d_bar) in back.d_bar.iter_mut().enumerate() {
            d_bar.copy_from_slice(&back.d_fusion_in[role * ds..(role + 1) * ds]);
        }
        if !self.config.ablation.no_third_order {
            let bar = |role: usize, k: usize| rec.fusion_in[role * ds + k];
            let [d_i, d_e, d_p] = &mut back.d_bar;
            for k in 0..ds {
                let d_j = back.d_fusion_in[3 * ds + k];
                d_i[k] += d_j * bar(1, k) * bar(2, k);
                d_e[k] += d_j * bar(0, k) * bar(2, k);
                d_p[k] += d_j * bar(0, k) * bar(1, k);
            }
        }
    }

    /// s̄^a = s^a + ½ Σ_b C_ab (s^b − s^a), C_ab = σ(w_C·[|s^a − s^b|; s^a ⊙ s^b] + b_C): gives dL/ds.
    fn backward_exchange(&self, rec: &StepScratch, back: &mut BackwardScratch, grad: &mut Params) {
        let ds = self.config.d_s;
        for (d_s, d_bar) in back.d_s.iter_mut().zip(&back.d_bar) {
            d_s.copy_from_slice(d_bar);
        }
        let p = &self.params;
        let (Some(w_c), Some(g_w), Some(g_b)) = (
            &p.w_conductance,
            &mut grad.w_conductance,
            &mut grad.b_conductance,
        ) else {
            return;
        };
        let (w_abs, w_prod) = w_c.data().split_at(ds);
        for (pair, &(a, b)) in PAIRS.iter().enumerate() {
            let c = rec.conductance[pair];
            let (s_a, s_b) = (&rec.s[a], &rec.s[b]);
            let (bar_a, bar_b) = (&back.d_bar[a], &back.d_bar[b]);
            let mut d_c = 0.0;
            for k in 0..ds {
                d_c += 0.5 * (bar_a[k] - bar_b[k]) * (s_b[k] - s_a[k]);
            }
            let d_z = d_c * c * (1.0 - c);
            g_b.data_mut()[0] += d_z;
            let (g_abs, g_prod) = g_w.data_mut().split_at_mut(ds);
            let [d_s0, d_s1, d_s2] = &mut back.d_s;
            let (d_sa, d_sb) = match (a, b) {
                (0, 1) => (d_s0, d_s1),
                (0, _) => (d_s0, d_s2),
                _ => (d_s1, d_s2),
            };
            for k in 0..ds {
                // Linear flow terms: ∂s̄^a/∂s^a = −½C, ∂s̄^a/∂s^b = ½C (and symmetrically for s̄^b).
                let flow = 0.5 * c * (bar_b[k] - bar_a[k]);
                let diff = s_a[k] - s_b[k];
                // |·| uses sign(0) = 0.
                let d_abs = w_abs[k] * sign(diff);
                g_abs[k] += d_z * diff.abs();
                g_prod[k] += d_z * s_a[k] * s_b[k];
                d_sa[k] += flow + d_z * (d_abs + w_prod[k] * s_b[k]);
                d_sb[k] += -flow + d_z * (-d_abs + w_prod[k] * s_a[k]);
            }
        }
    }

    /// s^r = σ(W_r x_r + b_r): encoder weight gradients (inputs are data, no gradient needed).
    fn backward_encoders(&self, rec: &StepScratch, back: &mut BackwardScratch, grad: &mut Params) {
        for (d_s, s) in back.d_s.iter_mut().zip(&rec.s) {
            for (d, &value) in d_s.iter_mut().zip(s) {
                *d *= value * (1.0 - value);
            }
        }
        let p = &self.params;
        let [d_i, d_e, d_p] = &back.d_s;
        let roles = [
            (
                &p.w_instant,
                &rec.x_instant[..],
                d_i,
                &mut grad.w_instant,
                &mut grad.b_instant,
            ),
            (
                &p.w_evolution,
                &rec.x_evolution[..],
                d_e,
                &mut grad.w_evolution,
                &mut grad.b_evolution,
            ),
            (
                &p.w_persistence,
                &rec.x_persistence[..self.config.persistence_width()],
                d_p,
                &mut grad.w_persistence,
                &mut grad.b_persistence,
            ),
        ];
        for (w, x, d_out, grad_w, grad_b) in roles {
            affine_backward(
                w.data(),
                x,
                d_out,
                grad_w.data_mut(),
                grad_b.data_mut(),
                None,
            );
        }
    }
}
