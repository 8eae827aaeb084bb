//! The paper's learned nets on ξ_t with candle's CPU tensors and autograd: a per-sample MLP
//! (ξ → 128 → 64 → 1, ReLU, dropout 0.1) and one-layer GRU/LSTM (64 hidden) sequence models with a
//! linear head, trained like HO-LLN: weighted BCE on ν = 1 rows, AdamW with gradient clipping,
//! ReduceLROnPlateau, early stopping on the validation loss with the best checkpoint kept, and (for
//! the recurrent nets) truncated BPTT over non-overlapping windows whose start states come from a
//! zero-state pass over each training trajectory at the start of every epoch.
//!
//! Every random draw (initialisation, shuffling, dropout masks) comes from the seeded core RNG, so
//! a fit is a function of its seed. The cells are written with candle's tensor ops (the gradients
//! are candle's); they precompute the input projection of a whole window in one product.

use candle_core::{D, DType, Device, Tensor, Var};
use candle_nn::ops::sigmoid;
use candle_nn::{AdamW, Optimizer, ParamsAdamW};
use serde::Serialize;
use spoofwatch_core::metrics::auroc;
use spoofwatch_core::rng::Rng;
use spoofwatch_core::train::TrainConfig;

use crate::common::{BaselineError, Epoch};
use crate::rows::RowTable;

/// Which net.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum NetKind {
    Mlp,
    Gru,
    Lstm,
}

impl NetKind {
    fn gates(self) -> usize {
        match self {
            NetKind::Mlp => 0,
            NetKind::Gru => 3,
            NetKind::Lstm => 4,
        }
    }
}

/// Sizes of the paper's baselines (`docs/baselines.md`).
pub const MLP_HIDDEN: [usize; 2] = [128, 64];
pub const MLP_DROPOUT: f64 = 0.1;
pub const MLP_BATCH: usize = 512;
pub const RECURRENT_HIDDEN: usize = 64;
/// Rows scored per inference batch (MLP) and trajectories per batch (recurrent nets).
const MLP_INFERENCE_ROWS: usize = 8192;
const RECURRENT_INFERENCE_TRAJECTORIES: usize = 64;

impl From<candle_core::Error> for BaselineError {
    fn from(error: candle_core::Error) -> Self {
        BaselineError::Tensor(error.to_string())
    }
}

/// A net's parameters: trainable variables in a fixed order.
struct Params {
    kind: NetKind,
    vars: Vec<Var>,
}

/// U(±1/√fan_in) weights (PyTorch's default bound) and zero biases, from the seeded RNG.
fn init(rng: &mut Rng, shape: (usize, usize)) -> Result<Var, BaselineError> {
    let bound = 1.0 / (shape.1 as f64).sqrt();
    let values: Vec<f32> = (0..shape.0 * shape.1)
        .map(|_| rng.uniform_range(-bound, bound) as f32)
        .collect();
    Ok(Var::from_tensor(&Tensor::from_vec(
        values,
        shape,
        &Device::Cpu,
    )?)?)
}

fn zeros(len: usize) -> Result<Var, BaselineError> {
    Ok(Var::zeros(len, DType::F32, &Device::Cpu)?)
}

impl Params {
    /// Layout: MLP [w1, b1, w2, b2, w3, b3]; GRU/LSTM [w_ih, w_hh, b_ih, b_hh, w_head, b_head].
    fn new(kind: NetKind, width: usize, rng: &mut Rng) -> Result<Self, BaselineError> {
        let vars = match kind {
            NetKind::Mlp => {
                let [h1, h2] = MLP_HIDDEN;
                vec![
                    init(rng, (h1, width))?,
                    zeros(h1)?,
                    init(rng, (h2, h1))?,
                    zeros(h2)?,
                    init(rng, (1, h2))?,
                    zeros(1)?,
                ]
            }
            NetKind::Gru | NetKind::Lstm => {
                let (g, h) = (kind.gates(), RECURRENT_HIDDEN);
                vec![
                    init(rng, (g * h, width))?,
                    init(rng, (g * h, h))?,
                    zeros(g * h)?,
                    zeros(g * h)?,
                    init(rng, (1, h))?,
                    zeros(1)?,
                ]
            }
        };
        Ok(Self { kind, vars })
    }

    /// Detached copies of the current values (a checkpoint, or an inference-only net).
    fn snapshot(&self) -> Result<Vec<Tensor>, BaselineError> {
        Ok(self
            .vars
            .iter()
            .map(|v| v.as_tensor().detach().copy())
            .collect::<candle_core::Result<_>>()?)
    }
}

/// x · wᵀ + b for x of shape [.., in].
fn linear(x: &Tensor, w: &Tensor, b: &Tensor) -> candle_core::Result<Tensor> {
    x.broadcast_matmul(&w.t()?)?.broadcast_add(b)
}

/// MLP logits [B] of rows x [B, width]; `dropout` masks (already scaled by 1/(1−p)) in training.
fn mlp_logits(
    p: &[Tensor],
    x: &Tensor,
    dropout: Option<[Tensor; 2]>,
) -> candle_core::Result<Tensor> {
    let mut h1 = linear(x, &p[0], &p[1])?.relu()?;
    if let Some([m1, _]) = &dropout {
        h1 = (h1 * m1)?;
    }
    let mut h2 = linear(&h1, &p[2], &p[3])?.relu()?;
    if let Some([_, m2]) = &dropout {
        h2 = (h2 * m2)?;
    }
    linear(&h2, &p[4], &p[5])?.squeeze(D::Minus1)
}

/// Recurrent state: [h] (GRU) or [h, c] (LSTM), each [B, H].
type State = Vec<Tensor>;

fn zero_state(kind: NetKind, batch: usize) -> candle_core::Result<State> {
    let count = if kind == NetKind::Lstm { 2 } else { 1 };
    (0..count)
        .map(|_| Tensor::zeros((batch, RECURRENT_HIDDEN), DType::F32, &Device::Cpu))
        .collect()
}

/// One step of the cell from the input projection `xw` [B, G·H] (bias included).
fn cell_step(
    kind: NetKind,
    p: &[Tensor],
    xw: &Tensor,
    state: &State,
) -> candle_core::Result<State> {
    let hw = linear(&state[0], &p[1], &p[3])?;
    match kind {
        NetKind::Lstm => {
            let gates = (xw + hw)?.chunk(4, 1)?;
            let (i, f) = (sigmoid(&gates[0])?, sigmoid(&gates[1])?);
            let (g, o) = (gates[2].tanh()?, sigmoid(&gates[3])?);
            let c = ((f * &state[1])? + (i * g)?)?;
            let h = (o * c.tanh()?)?;
            Ok(vec![h, c])
        }
        // PyTorch's GRU: n = tanh(x_n + r ⊙ (W_hn h + b_hn)), h' = (1 − z) ⊙ n + z ⊙ h.
        _ => {
            let x = xw.chunk(3, 1)?;
            let hh = hw.chunk(3, 1)?;
            let r = sigmoid(&(&x[0] + &hh[0])?)?;
            let z = sigmoid(&(&x[1] + &hh[1])?)?;
            let n = (&x[2] + (r * &hh[2])?)?.tanh()?;
            let h = ((&n - (&z * &n)?)? + (z * &state[0])?)?;
            Ok(vec![h])
        }
    }
}

/// Logits [B, T] of windows x [B, T, width] from `state`, and the final state.
fn recurrent_logits(
    kind: NetKind,
    p: &[Tensor],
    x: &Tensor,
    mut state: State,
) -> candle_core::Result<(Tensor, State)> {
    let steps = x.dim(1)?;
    let xw = linear(x, &p[0], &p[2])?;
    let mut hidden = Vec::with_capacity(steps);
    for t in 0..steps {
        state = cell_step(kind, p, &xw.narrow(1, t, 1)?.squeeze(1)?, &state)?;
        hidden.push(state[0].clone());
    }
    let hidden = Tensor::stack(&hidden, 1)?;
    Ok((linear(&hidden, &p[4], &p[5])?.squeeze(D::Minus1)?, state))
}

/// Σ w·BCE(logits, y) / Σ[w > 0], the stable form max(z, 0) − z·y + ln(1 + e^−|z|).
fn weighted_bce(
    logits: &Tensor,
    labels: &Tensor,
    weights: &Tensor,
    rows: f64,
) -> candle_core::Result<Tensor> {
    let bce =
        ((logits.relu()? - (logits * labels)?)? + (logits.abs()?.neg()?.exp()? + 1.0)?.log()?)?;
    (bce * weights)?.sum_all()? / rows.max(1.0)
}

/// A trained net (its parameters at the best validation epoch).
pub struct Net {
    kind: NetKind,
    params: Vec<Tensor>,
}

/// Rows of one recurrent training window.
#[derive(Clone, Copy, Debug)]
struct Window {
    trajectory: usize,
    start: usize,
    end: usize,
}

/// One sequence's recurrent state as plain rows: one row per state tensor ([h] or [h, c]).
type StateRows = Vec<Vec<f32>>;
/// Window-start states of one epoch, one per window.
type StartStates = Vec<StateRows>;

fn batch_tensor(values: Vec<f32>, shape: (usize, usize)) -> candle_core::Result<Tensor> {
    Tensor::from_vec(values, shape, &Device::Cpu)
}

impl Net {
    /// Fits a `kind` net on `train` (loss weights `train_weights`), choosing the checkpoint on
    /// `validation`. Batch size and learning rate come from `config` for the recurrent nets (the
    /// HO-LLN recipe) and from the paper's MLP recipe for the MLP.
    pub fn fit(
        kind: NetKind,
        config: &TrainConfig,
        train: &RowTable,
        train_weights: &[f32],
        validation: &RowTable,
        validation_weights: &[f32],
    ) -> Result<(Self, Vec<Epoch>, usize), BaselineError> {
        let mut rng = Rng::seed_from_u64(config.seed);
        let params = Params::new(kind, train.width, &mut rng)?;
        let mut optimizer = AdamW::new(
            params.vars.clone(),
            ParamsAdamW {
                lr: config.learning_rate,
                beta1: config.beta1,
                beta2: config.beta2,
                eps: config.eps,
                weight_decay: config.weight_decay,
            },
        )?;
        let windows = match kind {
            NetKind::Mlp => Vec::new(),
            _ => plan_windows(train, config.window),
        };
        let mut items: Vec<usize> = match kind {
            NetKind::Mlp => train.valid_rows(),
            _ => (0..windows.len()).collect(),
        };
        let batch = if kind == NetKind::Mlp {
            MLP_BATCH
        } else {
            config.batch_size
        };
        let mut history = Vec::new();
        let mut best = (f64::INFINITY, params.snapshot()?, 0usize);
        let (mut since_best, mut since_plateau_best, mut plateau_best) = (0, 0, f64::INFINITY);
        for epoch in 1..=config.max_epochs {
            let starts = match kind {
                NetKind::Mlp => Vec::new(),
                _ => {
                    let current = Net {
                        kind,
                        params: params.snapshot()?,
                    };
                    current.window_start_states(train, &windows, config.window)?
                }
            };
            rng.shuffle(&mut items);
            let (mut loss_sum, mut loss_rows) = (0.0, 0.0);
            for chunk in items.chunks(batch) {
                let (loss, rows) = match kind {
                    NetKind::Mlp => mlp_batch_loss(&params, train, train_weights, chunk, &mut rng)?,
                    _ => {
                        window_batch_loss(&params, train, train_weights, &windows, &starts, chunk)?
                    }
                };
                let mut grads = loss.backward()?;
                clip_gradients(&params, &mut grads, config.grad_clip_norm)?;
                optimizer.step(&grads)?;
                loss_sum += f64::from(loss.to_scalar::<f32>()?) * rows;
                loss_rows += rows;
            }
            let current = Net {
                kind,
                params: params.snapshot()?,
            };
            let probabilities = current.probabilities(validation)?;
            let (val_loss, val_auroc) =
                validation_loss(validation, validation_weights, &probabilities);
            history.push(Epoch {
                epoch,
                train_loss: loss_sum / loss_rows.max(1.0),
                val_loss,
                val_auroc,
            });
            if val_loss < best.0 - config.early_stop_min_delta {
                best = (val_loss, current.params, epoch);
                since_best = 0;
            } else {
                since_best += 1;
            }
            if val_loss < plateau_best * (1.0 - config.plateau_threshold) {
                (plateau_best, since_plateau_best) = (val_loss, 0);
            } else {
                since_plateau_best += 1;
                if since_plateau_best > config.plateau_patience {
                    let lr = (optimizer.learning_rate() * config.plateau_factor)
                        .max(config.min_learning_rate);
                    optimizer.set_learning_rate(lr);
                    since_plateau_best = 0;
                }
            }
            if since_best > config.early_stop_patience {
                break;
            }
        }
        Ok((
            Net {
                kind,
                params: best.1,
            },
            history,
            best.2,
        ))
    }

    /// Spoofing probability of every row of `table` (recurrent nets: each trajectory from the zero
    /// state, as served).
    pub fn probabilities(&self, table: &RowTable) -> Result<Vec<f64>, BaselineError> {
        let logits = match self.kind {
            NetKind::Mlp => {
                let mut out = Vec::with_capacity(table.rows.len());
                for start in (0..table.rows.len()).step_by(MLP_INFERENCE_ROWS) {
                    let end = (start + MLP_INFERENCE_ROWS).min(table.rows.len());
                    let x = batch_tensor(
                        table.features[start * table.width..end * table.width].to_vec(),
                        (end - start, table.width),
                    )?;
                    out.extend(mlp_logits(&self.params, &x, None)?.to_vec1::<f32>()?);
                }
                out
            }
            _ => self.run_trajectories(table, None)?.0,
        };
        Ok(logits
            .into_iter()
            .map(|z| 1.0 / (1.0 + (-f64::from(z)).exp()))
            .collect())
    }

    /// Runs every trajectory of `table` from the zero state in padded batches; returns the logits
    /// per row and, with `window`, the state at every window start (in [`plan_windows`]' order
    /// before filtering: trajectory by trajectory, every `window` rows).
    fn run_trajectories(
        &self,
        table: &RowTable,
        window: Option<usize>,
    ) -> Result<(Vec<f32>, Vec<StartStates>), BaselineError> {
        let mut logits = vec![0.0f32; table.rows.len()];
        let mut starts: Vec<StartStates> = vec![Vec::new(); table.trajectories.len()];
        // Similar lengths together, so little of each batch is padding.
        let mut order: Vec<usize> = (0..table.trajectories.len()).collect();
        order.sort_by_key(|&i| table.trajectories[i].len());
        for group in order.chunks(RECURRENT_INFERENCE_TRAJECTORIES) {
            let longest = group
                .iter()
                .map(|&i| table.trajectories[i].len())
                .max()
                .unwrap_or(0);
            let mut x = vec![0.0f32; group.len() * longest * table.width];
            for (b, &i) in group.iter().enumerate() {
                let range = table.trajectories[i].clone();
                let dst = b * longest * table.width;
                x[dst..dst + range.len() * table.width].copy_from_slice(
                    &table.features[range.start * table.width..range.end * table.width],
                );
            }
            let x = Tensor::from_vec(x, (group.len(), longest, table.width), &Device::Cpu)?;
            let xw = linear(&x, &self.params[0], &self.params[2])?;
            let mut state = zero_state(self.kind, group.len())?;
            let mut step_logits = Vec::with_capacity(longest);
            for t in 0..longest {
                if window.is_some_and(|w| t % w == 0) {
                    let rows: Vec<StateRows> = state
                        .iter()
                        .map(|s| s.to_vec2::<f32>())
                        .collect::<candle_core::Result<_>>()?;
                    for (b, &i) in group.iter().enumerate() {
                        if t < table.trajectories[i].len() {
                            starts[i].push(rows.iter().map(|r| r[b].clone()).collect());
                        }
                    }
                }
                state = cell_step(
                    self.kind,
                    &self.params,
                    &xw.narrow(1, t, 1)?.squeeze(1)?,
                    &state,
                )?;
                step_logits.push(linear(&state[0], &self.params[4], &self.params[5])?.squeeze(1)?);
            }
            let all = Tensor::stack(&step_logits, 1)?.to_vec2::<f32>()?;
            for (b, &i) in group.iter().enumerate() {
                let range = table.trajectories[i].clone();
                logits[range.clone()].copy_from_slice(&all[b][..range.len()]);
            }
        }
        Ok((logits, starts))
    }

    /// The carried start state of every training window: a zero-state pass over each trajectory.
    fn window_start_states(
        &self,
        train: &RowTable,
        windows: &[Window],
        window: usize,
    ) -> Result<StartStates, BaselineError> {
        let window = window.max(1);
        let (_, starts) = self.run_trajectories(train, Some(window))?;
        Ok(windows
            .iter()
            .map(|w| {
                let index = (w.start - train.trajectories[w.trajectory].start) / window;
                starts[w.trajectory][index].clone()
            })
            .collect())
    }
}

/// Non-overlapping windows of `window` rows tiling every trajectory; those with a ν = 1 row train.
fn plan_windows(table: &RowTable, window: usize) -> Vec<Window> {
    let mut windows = Vec::new();
    for (trajectory, range) in table.trajectories.iter().enumerate() {
        for start in range.clone().step_by(window.max(1)) {
            let end = (start + window).min(range.end);
            if table.rows[start..end].iter().any(|r| r.valid) {
                windows.push(Window {
                    trajectory,
                    start,
                    end,
                });
            }
        }
    }
    windows
}

/// Loss of one MLP minibatch of rows, with fresh dropout masks; and the rows it averages over.
fn mlp_batch_loss(
    params: &Params,
    table: &RowTable,
    weights: &[f32],
    rows: &[usize],
    rng: &mut Rng,
) -> Result<(Tensor, f64), BaselineError> {
    let x: Vec<f32> = rows
        .iter()
        .flat_map(|&i| table.row(i).iter().copied())
        .collect();
    let x = batch_tensor(x, (rows.len(), table.width))?;
    let keep = 1.0 - MLP_DROPOUT;
    let mut mask = |width: usize| -> candle_core::Result<Tensor> {
        let values: Vec<f32> = (0..rows.len() * width)
            .map(|_| {
                if rng.uniform() < keep {
                    (1.0 / keep) as f32
                } else {
                    0.0
                }
            })
            .collect();
        batch_tensor(values, (rows.len(), width))
    };
    let masks = [mask(MLP_HIDDEN[0])?, mask(MLP_HIDDEN[1])?];
    let p: Vec<Tensor> = params.vars.iter().map(|v| v.as_tensor().clone()).collect();
    let logits = mlp_logits(&p, &x, Some(masks))?;
    let labels: Vec<f32> = rows
        .iter()
        .map(|&i| f32::from(u8::from(table.rows[i].label)))
        .collect();
    let w: Vec<f32> = rows.iter().map(|&i| weights[i]).collect();
    let count = rows.len() as f64;
    let loss = weighted_bce(
        &logits,
        &Tensor::from_vec(labels, rows.len(), &Device::Cpu)?,
        &Tensor::from_vec(w, rows.len(), &Device::Cpu)?,
        count,
    )?;
    Ok((loss, count))
}

/// Loss of one batch of recurrent windows (padded to the longest), each from its carried state.
fn window_batch_loss(
    params: &Params,
    table: &RowTable,
    weights: &[f32],
    windows: &[Window],
    starts: &StartStates,
    chosen: &[usize],
) -> Result<(Tensor, f64), BaselineError> {
    let longest = chosen
        .iter()
        .map(|&w| windows[w].end - windows[w].start)
        .max()
        .unwrap_or(0);
    let (b, width) = (chosen.len(), table.width);
    let mut x = vec![0.0f32; b * longest * width];
    let mut labels = vec![0.0f32; b * longest];
    let mut w = vec![0.0f32; b * longest];
    for (k, &index) in chosen.iter().enumerate() {
        let window = windows[index];
        for (t, row) in (window.start..window.end).enumerate() {
            let at = k * longest + t;
            x[at * width..(at + 1) * width].copy_from_slice(table.row(row));
            labels[at] = f32::from(u8::from(table.rows[row].label));
            w[at] = weights[row];
        }
    }
    let rows = w.iter().filter(|&&v| v > 0.0).count() as f64;
    let state_count = starts.first().map_or(0, Vec::len);
    let state = (0..state_count)
        .map(|s| {
            let values: Vec<f32> = chosen
                .iter()
                .flat_map(|&i| starts[i][s].iter().copied())
                .collect();
            batch_tensor(values, (b, RECURRENT_HIDDEN))
        })
        .collect::<candle_core::Result<State>>()?;
    let p: Vec<Tensor> = params.vars.iter().map(|v| v.as_tensor().clone()).collect();
    let x = Tensor::from_vec(x, (b, longest, width), &Device::Cpu)?;
    let (logits, _) = recurrent_logits(params.kind, &p, &x, state)?;
    let loss = weighted_bce(
        &logits,
        &batch_tensor(labels, (b, longest))?,
        &batch_tensor(w, (b, longest))?,
        rows,
    )?;
    Ok((loss, rows))
}

/// Scales the gradients so their global L2 norm is at most `max_norm` (as HO-LLN's training does).
fn clip_gradients(
    params: &Params,
    grads: &mut candle_core::backprop::GradStore,
    max_norm: f64,
) -> Result<(), BaselineError> {
    let mut squared = 0.0f64;
    for var in &params.vars {
        if let Some(g) = grads.get(var) {
            squared += f64::from(g.sqr()?.sum_all()?.to_scalar::<f32>()?);
        }
    }
    let norm = squared.sqrt();
    if norm > max_norm && norm.is_finite() {
        let scale = max_norm / norm;
        for var in &params.vars {
            if let Some(g) = grads.remove(var) {
                grads.insert(var, (g * scale)?);
            }
        }
    }
    Ok(())
}

/// HO-LLN's validation loss (Σ α·ℓ over ν = 1 rows / their count) and AUROC of `probabilities`.
pub fn validation_loss(
    table: &RowTable,
    weights: &[f32],
    probabilities: &[f64],
) -> (f64, Option<f64>) {
    let (mut sum, mut count) = (0.0, 0usize);
    let (mut scores, mut labels) = (Vec::new(), Vec::new());
    for (i, row) in table.rows.iter().enumerate() {
        if !row.valid {
            continue;
        }
        let p = probabilities[i].clamp(1e-12, 1.0 - 1e-12);
        let loss = if row.label { -p.ln() } else { -(1.0 - p).ln() };
        sum += f64::from(weights[i]) * loss;
        count += 1;
        scores.push(probabilities[i]);
        labels.push(row.label);
    }
    (sum / count.max(1) as f64, auroc(&scores, &labels))
}

#[cfg(test)]
mod tests {
    use spoofwatch_core::metrics::ScoredRow;

    use super::*;

    /// A table of two trajectories (3 and 9 rows) of random 2-wide features, every row valid.
    fn two_trajectories() -> RowTable {
        let mut rng = Rng::seed_from_u64(5);
        let rows = 12;
        RowTable {
            rows: (0..rows)
                .map(|i| ScoredRow {
                    trajectory: u64::from(i >= 3),
                    time_s: i as f64,
                    valid: true,
                    label: i % 2 == 0,
                    score: f64::NAN,
                })
                .collect(),
            features: (0..rows * 2).map(|_| rng.normal() as f32).collect(),
            width: 2,
            trajectories: vec![0..3, 3..12],
        }
    }

    /// Each window starts from the state a zero-state pass reaches at its first row, also when the
    /// first trajectory is shorter than a window.
    #[test]
    fn windows_start_from_the_carried_state() {
        let table = two_trajectories();
        let mut rng = Rng::seed_from_u64(1);
        for kind in [NetKind::Gru, NetKind::Lstm] {
            let params = Params::new(kind, table.width, &mut rng).expect("params");
            let net = Net {
                kind,
                params: params.snapshot().expect("snapshot"),
            };
            let windows = plan_windows(&table, 4);
            let spans: Vec<(usize, usize)> = windows.iter().map(|w| (w.start, w.end)).collect();
            assert_eq!(spans, [(0, 3), (3, 7), (7, 11), (11, 12)]);
            let starts = net
                .window_start_states(&table, &windows, 4)
                .expect("start states");
            for (window, start) in windows.iter().zip(&starts) {
                let first = table.trajectories[window.trajectory].start;
                let before = window.start - first;
                let expected: Vec<f32> = if before == 0 {
                    vec![0.0; RECURRENT_HIDDEN]
                } else {
                    let x = Tensor::from_vec(
                        table.features[first * 2..window.start * 2].to_vec(),
                        (1, before, 2),
                        &Device::Cpu,
                    )
                    .expect("x");
                    let zero = zero_state(kind, 1).expect("zero state");
                    let (_, state) = recurrent_logits(kind, &net.params, &x, zero).expect("run");
                    state[0].to_vec2::<f32>().expect("h")[0].clone()
                };
                for (a, b) in start[0].iter().zip(&expected) {
                    assert!(
                        (a - b).abs() < 1e-5,
                        "{kind:?} window at {}: {a} vs {b}",
                        window.start
                    );
                }
            }
        }
    }

    /// candle's gradients of our cells and loss agree with central differences (f32, so loose).
    #[test]
    fn gradients_match_finite_differences() {
        let table = two_trajectories();
        let labels: Vec<f32> = table
            .rows
            .iter()
            .map(|r| f32::from(u8::from(r.label)))
            .collect();
        let mut rng = Rng::seed_from_u64(3);
        for kind in [NetKind::Mlp, NetKind::Gru, NetKind::Lstm] {
            let params = Params::new(kind, table.width, &mut rng).expect("params");
            // The weighted loss of the whole table as one batch (MLP) or one sequence.
            let loss = || -> Tensor {
                let p: Vec<Tensor> = params.vars.iter().map(|v| v.as_tensor().clone()).collect();
                let features = table.features.clone();
                let (logits, shape) = if kind == NetKind::Mlp {
                    let x = batch_tensor(features, (12, 2)).expect("x");
                    (mlp_logits(&p, &x, None).expect("logits"), vec![12])
                } else {
                    let x = Tensor::from_vec(features, (1, 12, 2), &Device::Cpu).expect("x");
                    let zero = zero_state(kind, 1).expect("zero");
                    (
                        recurrent_logits(kind, &p, &x, zero).expect("run").0,
                        vec![1, 12],
                    )
                };
                let y = Tensor::from_vec(labels.clone(), shape.clone(), &Device::Cpu).expect("y");
                let w = Tensor::from_vec(vec![1.5f32; 12], shape, &Device::Cpu).expect("w");
                weighted_bce(&logits, &y, &w, 12.0).expect("loss")
            };
            let grads = loss().backward().expect("backward");
            for (index, var) in params.vars.iter().enumerate() {
                let first = |t: &Tensor| -> (Vec<f32>, f32) {
                    let values = t
                        .flatten_all()
                        .and_then(|f| f.to_vec1::<f32>())
                        .expect("values");
                    let v0 = values[0];
                    (values, v0)
                };
                let (_, analytic) = first(grads.get(var).expect("every parameter has a gradient"));
                let (original, _) = first(var.as_tensor());
                // Moves the parameter tensor's first entry by `delta` and evaluates the loss.
                let loss_at = |delta: f32| -> f32 {
                    let mut values = original.clone();
                    values[0] += delta;
                    let set = |v: Vec<f32>| {
                        let t = Tensor::from_vec(v, var.shape(), &Device::Cpu).expect("tensor");
                        var.set(&t).expect("set");
                    };
                    set(values);
                    let l = loss().to_scalar::<f32>().expect("scalar");
                    set(original.clone());
                    l
                };
                let eps = 1e-2;
                let numeric = (loss_at(eps) - loss_at(-eps)) / (2.0 * eps);
                let tolerance = 2e-3 + 2e-2 * numeric.abs().max(analytic.abs());
                assert!(
                    (numeric - analytic).abs() < tolerance,
                    "{kind:?} parameter {index}: analytic {analytic} vs numeric {numeric}"
                );
            }
        }
    }

    /// The stable BCE form equals the textbook −[y ln σ(z) + (1−y) ln(1−σ(z))].
    #[test]
    fn weighted_bce_matches_the_textbook_form() {
        let z = [-3.0f32, -0.5, 0.0, 0.7, 4.0];
        let y = [0.0f32, 1.0, 1.0, 0.0, 1.0];
        let w = [1.0f32, 2.0, 0.0, 0.5, 1.0];
        let tensor = |v: &[f32]| Tensor::from_slice(v, v.len(), &Device::Cpu).expect("tensor");
        let loss = weighted_bce(&tensor(&z), &tensor(&y), &tensor(&w), 4.0)
            .and_then(|t| t.to_scalar::<f32>())
            .expect("loss");
        let expected: f64 = z
            .iter()
            .zip(&y)
            .zip(&w)
            .map(|((&z, &y), &w)| {
                let p = 1.0 / (1.0 + (-f64::from(z)).exp());
                f64::from(w) * -(f64::from(y) * p.ln() + (1.0 - f64::from(y)) * (1.0 - p).ln())
            })
            .sum::<f64>()
            / 4.0;
        assert!(
            (f64::from(loss) - expected).abs() < 1e-6,
            "{loss} vs {expected}"
        );
    }
}
