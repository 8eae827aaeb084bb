//! AdamW, global gradient-norm clipping, ReduceLROnPlateau and early stopping (SPEC §6), written to
//! follow PyTorch's definitions so the reference's hyper-parameters mean the same thing here.
//!
//! Owns AdamW, clipping, the plateau scheduler and early stopping. Must not know about sequences or
//! models beyond their parameter tensors.

use crate::model::Params;

/// Scales `grad` so its global L2 norm is at most `max_norm` (PyTorch `clip_grad_norm_`: factor
/// `max_norm / (norm + 1e-6)` when that is below 1). Returns the norm before clipping.
pub(crate) fn clip_global_norm(grad: &mut Params, max_norm: f64) -> f64 {
    let norm = grad.l2_norm();
    let factor = max_norm / (norm + 1e-6);
    if factor < 1.0 {
        grad.scale(factor);
    }
    norm
}

/// AdamW with decoupled weight decay applied to matrices (tensors with ≥ 2 dims) only.
#[derive(Clone, Debug)]
pub(crate) struct AdamW {
    first_moment: Params,
    second_moment: Params,
    steps: i32,
    beta1: f64,
    beta2: f64,
    eps: f64,
    weight_decay: f64,
}

impl AdamW {
    /// Zero moments shaped like `params`.
    pub(crate) fn new(
        params: &Params,
        beta1: f64,
        beta2: f64,
        eps: f64,
        weight_decay: f64,
    ) -> Self {
        let mut zeros = params.clone();
        zeros.fill_zero();
        Self {
            first_moment: zeros.clone(),
            second_moment: zeros,
            steps: 0,
            beta1,
            beta2,
            eps,
            weight_decay,
        }
    }

    /// One update of `params` with gradient `grad` at learning rate `lr`.
    pub(crate) fn update(&mut self, params: &mut Params, grad: &Params, lr: f64) {
        self.steps = self.steps.saturating_add(1);
        let correction1 = 1.0 - self.beta1.powi(self.steps);
        let correction2 = 1.0 - self.beta2.powi(self.steps);
        let step_size = lr / correction1;
        let correction2_sqrt = correction2.sqrt();
        let (beta1, beta2, eps) = (self.beta1, self.beta2, self.eps);
        let decay = 1.0 - lr * self.weight_decay;
        let tensors = params
            .tensors_mut()
            .into_iter()
            .zip(grad.tensors())
            .zip(self.first_moment.tensors_mut())
            .zip(self.second_moment.tensors_mut());
        for ((((_, param), (_, g)), (_, m)), (_, v)) in tensors {
            let decays = param.is_matrix();
            let values = param.data_mut().iter_mut().zip(g.data());
            let moments = m.data_mut().iter_mut().zip(v.data_mut().iter_mut());
            for ((p, &g), (m, v)) in values.zip(moments) {
                if decays {
                    *p *= decay;
                }
                *m = beta1 * *m + (1.0 - beta1) * g;
                *v = beta2 * *v + (1.0 - beta2) * g * g;
                let denominator = v.sqrt() / correction2_sqrt + eps;
                *p -= step_size * *m / denominator;
            }
        }
    }
}

/// ReduceLROnPlateau (mode min, relative threshold, no cooldown), stepped once per epoch.
#[derive(Clone, Debug)]
pub(crate) struct PlateauScheduler {
    factor: f64,
    patience: usize,
    threshold: f64,
    min_lr: f64,
    best: f64,
    bad_epochs: usize,
}

impl PlateauScheduler {
    pub(crate) fn new(factor: f64, patience: usize, threshold: f64, min_lr: f64) -> Self {
        Self {
            factor,
            patience,
            threshold,
            min_lr,
            best: f64::INFINITY,
            bad_epochs: 0,
        }
    }

    /// The learning rate for the next epoch after observing `metric` at rate `lr`.
    pub(crate) fn step(&mut self, metric: f64, lr: f64) -> f64 {
        // A NaN metric is never an improvement.
        if metric < self.best * (1.0 - self.threshold) {
            self.best = metric;
            self.bad_epochs = 0;
        } else {
            self.bad_epochs += 1;
        }
        if self.bad_epochs > self.patience {
            self.bad_epochs = 0;
            let reduced = (lr * self.factor).max(self.min_lr);
            // PyTorch ignores reductions smaller than 1e-8.
            if lr - reduced > 1e-8 {
                return reduced;
            }
        }
        lr
    }
}

/// Early stopping on a metric to minimise: improvement = `metric < best − min_delta`; stop once more
/// than `patience` consecutive epochs did not improve.
#[derive(Clone, Debug)]
pub(crate) struct EarlyStopping {
    patience: usize,
    min_delta: f64,
    best: f64,
    bad_epochs: usize,
}

impl EarlyStopping {
    pub(crate) fn new(patience: usize, min_delta: f64) -> Self {
        Self {
            patience,
            min_delta,
            best: f64::INFINITY,
            bad_epochs: 0,
        }
    }

    /// Records `metric`; returns `(improved, stop)`.
    pub(crate) fn observe(&mut self, metric: f64) -> (bool, bool) {
        let improved = metric < self.best - self.min_delta;
        if improved {
            self.best = metric;
            self.bad_epochs = 0;
        } else {
            self.bad_epochs += 1;
        }
        (improved, self.bad_epochs > self.patience)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::{Model, ModelConfig};

    fn tiny_params() -> Params {
        let config = ModelConfig {
            d_s: 1,
            d_zeta: 1,
            d_h: 1,
            ..ModelConfig::default()
        };
        Model::init(config, 0).expect("valid").params().clone()
    }

    #[test]
    fn adamw_first_step_matches_hand_computation() {
        let mut params = tiny_params();
        let mut grad = params.clone();
        for (i, (_, t)) in grad.tensors_mut().into_iter().enumerate() {
            t.data_mut().fill(if i % 2 == 0 { 0.5 } else { -2.0 });
        }
        let before = params.clone();
        let mut adam = AdamW::new(&params, 0.9, 0.999, 1e-8, 0.1);
        adam.update(&mut params, &grad, 0.01);
        // Step 1: m̂ = g, v̂ = g², so the Adam step is lr·g/(|g| + eps); matrices first decay by (1 − lr·wd).
        for (((name, after), (_, old)), (_, g)) in params
            .tensors()
            .into_iter()
            .zip(before.tensors())
            .zip(grad.tensors())
        {
            for ((&a, &p), &g) in after.data().iter().zip(old.data()).zip(g.data()) {
                let decayed = if after.is_matrix() {
                    p * (1.0 - 0.01 * 0.1)
                } else {
                    p
                };
                let expected = decayed - 0.01 * g / (g.abs() + 1e-8);
                assert!((a - expected).abs() < 1e-15, "{name}: {a} vs {expected}");
            }
        }
    }

    #[test]
    fn clipping_scales_to_the_maximum_norm() {
        let mut grad = tiny_params();
        grad.fill_zero();
        grad.tensors_mut()[0].1.data_mut()[..2].copy_from_slice(&[3.0, 4.0]);
        assert_eq!(clip_global_norm(&mut grad, 1.0), 5.0);
        assert!((grad.l2_norm() - 5.0 / (5.0 + 1e-6)).abs() < 1e-15);
        // Below the maximum nothing changes.
        let copy = grad.clone();
        clip_global_norm(&mut grad, 10.0);
        assert_eq!(grad, copy);
    }

    #[test]
    fn plateau_halves_after_patience_and_respects_the_floor() {
        let mut scheduler = PlateauScheduler::new(0.5, 2, 1e-4, 0.3);
        let mut lr = 1.0;
        // 1.0 improves; 0.99995 is within the relative threshold (not an improvement).
        for (metric, expected_lr) in [(1.0, 1.0), (0.99995, 1.0), (1.2, 1.0), (1.1, 0.5)] {
            lr = scheduler.step(metric, lr);
            assert_eq!(lr, expected_lr);
        }
        for _ in 0..3 {
            lr = scheduler.step(2.0, lr);
        }
        assert_eq!(lr, 0.3);
        for _ in 0..6 {
            lr = scheduler.step(2.0, lr);
        }
        assert_eq!(lr, 0.3);
    }

    #[test]
    fn early_stopping_needs_more_than_patience_bad_epochs() {
        let mut stopping = EarlyStopping::new(2, 1e-6);
        assert_eq!(stopping.observe(1.0), (true, false));
        assert_eq!(stopping.observe(1.0 - 1e-7), (false, false));
        assert_eq!(stopping.observe(f64::NAN), (false, false));
        assert_eq!(stopping.observe(0.5), (true, false));
        assert_eq!(stopping.observe(0.6), (false, false));
        assert_eq!(stopping.observe(0.6), (false, false));
        assert_eq!(stopping.observe(0.6), (false, true));
    }
}
