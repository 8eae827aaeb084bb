//! One forward step, recording every activation the backward pass needs.
//!
//! Serving and training run this same function: `Model::step` keeps one `StepScratch` per caller and
//! overwrites it, training keeps one per time step of a window (its tape).
//!
//! Owns the forward arithmetic of one step. Must not allocate per step or keep gradients (that is
//! `backward.rs`).

use super::fastmath::{exp, expm1, map_in_place, sigmoid, tanh};
use super::linalg::{affine, dot};
use super::{
    EVOLUTION_INPUTS, INSTANT_INPUTS, LiquidState, MAX_PERSISTENCE_INPUTS, Model, ModelConfig,
    PERSISTENCE_INPUTS, clamp_delta,
};
use crate::evidence::Features;

/// Role indices into the `[I, E, P]` arrays.
pub(crate) const ROLE_I: usize = 0;
pub(crate) const ROLE_E: usize = 1;
pub(crate) const ROLE_P: usize = 2;
/// The three exchange pairs, in the order of `StepScratch::conductance`: (I,E), (I,P), (E,P).
pub(crate) const PAIRS: [(usize, usize); 3] =
    [(ROLE_I, ROLE_E), (ROLE_I, ROLE_P), (ROLE_E, ROLE_P)];

/// Intermediate activations of one step (reusable buffers; create once per vehicle or per thread).
#[derive(Clone, Debug, Default)]
pub struct StepScratch {
    /// Role inputs after ablation masking and NaN → 0: I (3), E (4), P (2 or 12: the first
    /// `ModelConfig::persistence_width()` entries are used).
    pub(crate) x_instant: [f64; 3],
    pub(crate) x_evolution: [f64; 4],
    pub(crate) x_persistence: [f64; MAX_PERSISTENCE_INPUTS],
    /// Role states s^I, s^E, s^P.
    pub(crate) s: [Vec<f64>; 3],
    /// Conductances C_IE, C_IP, C_EP (0 without exchange).
    pub(crate) conductance: [f64; 3],
    /// Fusion input `[s̄^I; s̄^E; s̄^P; j]` (the s̄ blocks are the aligned role states).
    pub(crate) fusion_in: Vec<f64>,
    pub(crate) zeta: Vec<f64>,
    /// Candidate h̃.
    pub(crate) candidate: Vec<f64>,
    /// σ(W_τh ζ + b_τh), τ^h, γ.
    pub(crate) sig_tau_h: Vec<f64>,
    pub(crate) tau_h: Vec<f64>,
    pub(crate) gamma: Vec<f64>,
    /// σ(W_τv ζ + b_τv), τ^v, β (unused by the first-order cell).
    pub(crate) sig_tau_v: Vec<f64>,
    pub(crate) tau_v: Vec<f64>,
    pub(crate) beta: Vec<f64>,
    /// State before and after the step.
    pub(crate) h_prev: Vec<f64>,
    pub(crate) v_prev: Vec<f64>,
    pub(crate) h: Vec<f64>,
    pub(crate) v: Vec<f64>,
    /// Clamped δ_t.
    pub(crate) delta: f64,
    /// Head logit.
    pub(crate) logit: f64,
}

impl StepScratch {
    /// Buffers sized for `config`.
    pub fn new(config: &ModelConfig) -> Self {
        let mut scratch = Self::default();
        scratch.fit(config);
        scratch
    }

    /// Resizes the buffers when they were made for another configuration (cheap when they fit).
    pub(crate) fn fit(&mut self, config: &ModelConfig) {
        let (ds, dz, dh) = (config.d_s, config.d_zeta, config.d_h);
        if self.s[0].len() == ds
            && self.fusion_in.len() == config.fusion_input_len()
            && self.zeta.len() == dz
            && self.h.len() == dh
        {
            return;
        }
        for role in &mut self.s {
            role.resize(ds, 0.0);
        }
        self.fusion_in.resize(config.fusion_input_len(), 0.0);
        self.zeta.resize(dz, 0.0);
        for buffer in [
            &mut self.candidate,
            &mut self.sig_tau_h,
            &mut self.tau_h,
            &mut self.gamma,
            &mut self.sig_tau_v,
            &mut self.tau_v,
            &mut self.beta,
            &mut self.h_prev,
            &mut self.v_prev,
            &mut self.h,
            &mut self.v,
        ] {
            buffer.resize(dh, 0.0);
        }
    }
}

impl Model {
    /// One step: records activations in `rec`, advances `state` (which must fit the model), returns
    /// the head logit.
    pub(crate) fn forward_step(
        &self,
        state: &mut LiquidState,
        x: &Features,
        delta_t: f64,
        rec: &mut StepScratch,
    ) -> f64 {
        let config = &self.config;
        rec.fit(config);
        self.encode_roles(x, rec);
        self.exchange_and_fuse(rec);
        rec.delta = clamp_delta(delta_t);
        self.liquid_cell(state, rec);
        let p = &self.params;
        let head_h = dot(&p.w_out.data()[..config.d_h], &rec.h);
        let head_v = if config.ablation.first_order_cell {
            0.0
        } else {
            dot(&p.w_out.data()[config.d_h..], &rec.v)
        };
        rec.logit = (head_h + head_v) + p.b_out.data()[0];
        rec.logit
    }

    /// s^r = σ(W_r x_r + b_r) for the three roles, after ablation masking.
    fn encode_roles(&self, x: &Features, rec: &mut StepScratch) {
        let kept = self.config.ablation.features.kept();
        let input = |i: usize| {
            let value = x[i];
            if kept[i] && value.is_finite() {
                value
            } else {
                0.0
            }
        };
        rec.x_instant = INSTANT_INPUTS.map(input);
        rec.x_evolution = EVOLUTION_INPUTS.map(input);
        rec.x_persistence = PERSISTENCE_INPUTS.map(input);
        let p = &self.params;
        let [s_i, s_e, s_p] = &mut rec.s;
        affine(p.w_instant.data(), p.b_instant.data(), &rec.x_instant, s_i);
        affine(
            p.w_evolution.data(),
            p.b_evolution.data(),
            &rec.x_evolution,
            s_e,
        );
        affine(
            p.w_persistence.data(),
            p.b_persistence.data(),
            &rec.x_persistence[..self.config.persistence_width()],
            s_p,
        );
        for role in &mut rec.s {
            map_in_place(role, sigmoid);
        }
    }

    /// Conductances, aligned states s̄ (written into the fusion input), the third-order product and ζ.
    fn exchange_and_fuse(&self, rec: &mut StepScratch) {
        let ds = self.config.d_s;
        let p = &self.params;
        rec.conductance = [0.0; 3];
        if let (Some(w_c), Some(b_c)) = (&p.w_conductance, &p.b_conductance) {
            let (w_abs, w_prod) = w_c.data().split_at(ds);
            for (pair, &(a, b)) in PAIRS.iter().enumerate() {
                let (s_a, s_b) = (&rec.s[a], &rec.s[b]);
                let mut z = b_c.data()[0];
                for k in 0..ds {
                    z += w_abs[k] * (s_a[k] - s_b[k]).abs() + w_prod[k] * (s_a[k] * s_b[k]);
                }
                rec.conductance[pair] = sigmoid(z);
            }
        }
        let [c_ie, c_ip, c_ep] = rec.conductance;
        let [s_i, s_e, s_p] = &rec.s;
        let (aligned, product) = rec.fusion_in.split_at_mut(3 * ds);
        let (bar_i, rest) = aligned.split_at_mut(ds);
        let (bar_e, bar_p) = rest.split_at_mut(ds);
        for k in 0..ds {
            let (i, e, q) = (s_i[k], s_e[k], s_p[k]);
            // s̄^i = s^i + ½ Σ_{j≠i} C_ij (s^j − s^i); the pairwise flows cancel in Σ_i s̄^i.
            bar_i[k] = i + 0.5 * (c_ie * (e - i) + c_ip * (q - i));
            bar_e[k] = e + 0.5 * (c_ie * (i - e) + c_ep * (q - e));
            bar_p[k] = q + 0.5 * (c_ip * (i - q) + c_ep * (e - q));
        }
        if !self.config.ablation.no_third_order {
            for k in 0..ds {
                product[k] = bar_i[k] * bar_e[k] * bar_p[k];
            }
        }
        affine(
            p.w_fusion.data(),
            p.b_fusion.data(),
            &rec.fusion_in,
            &mut rec.zeta,
        );
        map_in_place(&mut rec.zeta, tanh);
    }

    /// h̃, τ^h, τ^v, γ, β and the state update.
    fn liquid_cell(&self, state: &mut LiquidState, rec: &mut StepScratch) {
        let config = &self.config;
        let p = &self.params;
        let tau_range = config.tau_max - config.tau_min;
        rec.h_prev.copy_from_slice(&state.h);
        rec.v_prev.copy_from_slice(&state.v);
        affine(
            p.w_candidate.data(),
            p.b_candidate.data(),
            &rec.zeta,
            &mut rec.candidate,
        );
        map_in_place(&mut rec.candidate, tanh);
        // Each transcendental runs over a whole buffer so that it vectorises.
        affine(
            p.w_tau_h.data(),
            p.b_tau_h.data(),
            &rec.zeta,
            &mut rec.sig_tau_h,
        );
        map_in_place(&mut rec.sig_tau_h, sigmoid);
        for k in 0..config.d_h {
            rec.tau_h[k] = config.tau_min + tau_range * rec.sig_tau_h[k];
            rec.gamma[k] = -rec.delta / rec.tau_h[k];
        }
        // γ = 1 − exp(−δ/τ^h) = −expm1(−δ/τ^h) (accurate for small δ/τ).
        map_in_place(&mut rec.gamma, expm1);
        for gamma in &mut rec.gamma {
            *gamma = -*gamma;
        }
        if let (Some(w_tv), Some(b_tv)) = (&p.w_tau_v, &p.b_tau_v) {
            affine(w_tv.data(), b_tv.data(), &rec.zeta, &mut rec.sig_tau_v);
            map_in_place(&mut rec.sig_tau_v, sigmoid);
            for k in 0..config.d_h {
                rec.tau_v[k] = config.tau_min + tau_range * rec.sig_tau_v[k];
                rec.beta[k] = -rec.delta / rec.tau_v[k];
            }
            map_in_place(&mut rec.beta, exp);
            for k in 0..config.d_h {
                let pull = rec.candidate[k] - rec.h_prev[k];
                rec.v[k] = rec.beta[k] * rec.v_prev[k] + (1.0 - rec.beta[k]) * pull;
                rec.h[k] = rec.h_prev[k] + rec.gamma[k] * rec.v[k];
            }
        } else {
            for k in 0..config.d_h {
                let pull = rec.candidate[k] - rec.h_prev[k];
                rec.v[k] = 0.0;
                rec.h[k] = rec.h_prev[k] + rec.gamma[k] * pull;
            }
        }
        state.h.copy_from_slice(&rec.h);
        state.v.copy_from_slice(&rec.v);
    }
}
