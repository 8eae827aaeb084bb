//! Gradient-boosted trees (the paper's XGBoost row and the GPS-IDS-style row) with forust: XGBoost's
//! histogram algorithm in pure Rust, seeded row and column sampling, early stopping on a validation
//! set. Single-threaded so a fit is the same on any machine (the experiments run fits in parallel).

use forust_ml::data::Matrix;
use forust_ml::gradientbooster::GradientBooster;
use forust_ml::metric::Metric;
use forust_ml::objective::ObjectiveType;
use forust_ml::sampler::SampleMethod;
use serde::Serialize;

use crate::common::{BaselineError, Epoch};
use crate::rows::RowTable;

/// The paper's XGBoost recipe (`docs/baselines.md`).
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct TreeParams {
    pub max_trees: usize,
    pub max_depth: usize,
    pub learning_rate: f32,
    pub subsample: f32,
    pub colsample_bytree: f64,
    /// Trees without a better validation log-loss before stopping.
    pub early_stopping_rounds: usize,
}

impl Default for TreeParams {
    fn default() -> Self {
        Self {
            max_trees: 250,
            max_depth: 3,
            learning_rate: 0.03,
            subsample: 0.9,
            colsample_bytree: 0.9,
            early_stopping_rounds: 25,
        }
    }
}

/// A fitted ensemble.
pub struct Trees {
    booster: Box<GradientBooster>,
}

/// Column-major copy of the chosen rows' features (forust's layout); NaN stays NaN (missing).
fn column_major(table: &RowTable, rows: &[usize]) -> Vec<f64> {
    let mut data = Vec::with_capacity(rows.len() * table.width);
    for column in 0..table.width {
        data.extend(rows.iter().map(|&i| f64::from(table.row(i)[column])));
    }
    data
}

/// Labels and loss weights of the chosen rows.
fn targets(table: &RowTable, rows: &[usize], weights: &[f32]) -> (Vec<f64>, Vec<f64>) {
    rows.iter()
        .map(|&i| {
            (
                f64::from(u8::from(table.rows[i].label)),
                f64::from(weights[i]),
            )
        })
        .unzip()
}

impl Trees {
    /// Fits on the ν = 1 rows of `train` with their loss weights, stopping early on the validation
    /// log-loss (weighted the same way); returns the ensemble and the log-loss after every tree.
    pub fn fit(
        params: TreeParams,
        seed: u64,
        train: &RowTable,
        train_weights: &[f32],
        validation: &RowTable,
        validation_weights: &[f32],
    ) -> Result<(Self, Vec<Epoch>), BaselineError> {
        let train_rows = train.valid_rows();
        let validation_rows = validation.valid_rows();
        let train_data = column_major(train, &train_rows);
        let (y, w) = targets(train, &train_rows, train_weights);
        let validation_data = column_major(validation, &validation_rows);
        let (val_y, val_w) = targets(validation, &validation_rows, validation_weights);
        let mut booster = GradientBooster::default()
            .set_objective_type(ObjectiveType::LogLoss)
            .set_iterations(params.max_trees)
            .set_max_depth(params.max_depth)
            .set_learning_rate(params.learning_rate)
            .set_sample_method(SampleMethod::Random)
            .set_subsample(params.subsample)
            .set_colsample_bytree(params.colsample_bytree)
            .set_seed(seed)
            .set_parallel(false)
            .set_evaluation_metric(Some(Metric::LogLoss))
            .set_early_stopping_rounds(Some(params.early_stopping_rounds));
        let train_matrix = Matrix::new(&train_data, train_rows.len(), train.width);
        let validation_matrix = Matrix::new(&validation_data, validation_rows.len(), train.width);
        // The last evaluation set decides early stopping; the first gives the training curve.
        let evaluation = vec![
            (
                Matrix::new(&train_data, train_rows.len(), train.width),
                y.as_slice(),
                w.as_slice(),
            ),
            (validation_matrix, val_y.as_slice(), val_w.as_slice()),
        ];
        booster
            .fit(&train_matrix, &y, &w, Some(evaluation))
            .map_err(|e| BaselineError::Trees(e.to_string()))?;
        let history = booster
            .evaluation_history
            .as_ref()
            .map(|h| {
                (0..h.rows)
                    .map(|tree| Epoch {
                        epoch: tree + 1,
                        train_loss: *h.get(tree, 0),
                        val_loss: *h.get(tree, 1),
                        val_auroc: None,
                    })
                    .collect()
            })
            .unwrap_or_default();
        Ok((
            Self {
                booster: Box::new(booster),
            },
            history,
        ))
    }

    /// Trees kept (the best validation iteration).
    pub fn trees(&self) -> usize {
        self.booster
            .best_iteration
            .map_or(self.booster.trees.len(), |best| best + 1)
    }

    /// Spoofing probability of every row of `table`.
    pub fn probabilities(&self, table: &RowTable) -> Vec<f64> {
        let all: Vec<usize> = (0..table.rows.len()).collect();
        let data = column_major(table, &all);
        let matrix = Matrix::new(&data, all.len(), table.width);
        self.booster
            .predict(&matrix, false)
            .into_iter()
            .map(|logit| 1.0 / (1.0 + (-logit).exp()))
            .collect()
    }
}
