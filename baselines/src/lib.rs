//! The paper's learned comparators, fitted under HO-LLN's protocol so that only the model differs:
//! the same training and validation tracks, the same evidence pass (ν, trajectories, scaled ξ_t),
//! the same class weights α_c, early stopping on the same validation loss, and the operating point
//! (θ, N_p) chosen on the validation rows by the same rule and grid.
//!
//! Learners: a per-sample MLP, GRU and LSTM sequence models ([`nets`], candle), gradient-boosted
//! trees ([`gbdt`], forust). Inputs: ξ_t in either feature schema, or (the GPS-IDS-style row) raw
//! AV-GPS vehicle-dynamics columns ([`rows::GPS_IDS_COLUMNS`]). These are offline comparators for
//! the experiments; nothing here is served. Must not do I/O.

mod common;
pub mod gbdt;
pub mod nets;
pub mod rows;

use serde::Serialize;
use spoofwatch_core::alarm::{
    N_P_GRID, OperatingPoint, OperatingPointRule, choose_operating_point, confirmed_alarms,
    theta_grid,
};
use spoofwatch_core::evaluation::Scored;
use spoofwatch_core::evidence::FeatureSchema;
use spoofwatch_core::evidence::{EvidenceFit, fit_evidence};
use spoofwatch_core::geo::Projection;
use spoofwatch_core::metrics::{EventRules, Metrics, ScoredRow};
use spoofwatch_core::train::TrainConfig;
use spoofwatch_core::train::spec::{
    DEFAULT_KAPPA_RHO, Recipe, SMALL_DATA_BATCH, SMALL_DATA_LEARNING_RATE,
};

pub use crate::common::{BaselineError, Epoch};
use crate::gbdt::{TreeParams, Trees};
use crate::nets::{Net, NetKind};
pub use crate::rows::{Dataset, GPS_IDS_COLUMNS, Input, RowTable};

/// Which model learns.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Learner {
    Mlp,
    Gru,
    Lstm,
    Trees,
}

/// A baseline: a learner on an input.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub struct Baseline {
    pub learner: Learner,
    pub input: Input,
}

impl Baseline {
    /// The paper's four learned baselines on ξ_t of `schema`.
    pub fn on_evidence(schema: FeatureSchema) -> [Baseline; 4] {
        [Learner::Trees, Learner::Mlp, Learner::Lstm, Learner::Gru].map(|learner| Baseline {
            learner,
            input: Input::Evidence(schema),
        })
    }

    /// The GPS-IDS-style row: gradient-boosted trees on raw vehicle-dynamics columns.
    pub const GPS_IDS: Baseline = Baseline {
        learner: Learner::Trees,
        input: Input::Columns,
    };

    /// Report name, e.g. "LSTM (ξ v2)".
    pub fn name(&self) -> String {
        let learner = match (self.learner, self.input) {
            (Learner::Trees, Input::Columns) => return "GPS-IDS trees (AV-GPS columns)".into(),
            (Learner::Trees, _) => "XGBoost-style trees",
            (Learner::Mlp, _) => "MLP",
            (Learner::Gru, _) => "GRU",
            (Learner::Lstm, _) => "LSTM",
        };
        format!("{learner} ({})", self.input.name())
    }
}

/// How every baseline is trained and calibrated: HO-LLN's settings.
#[derive(Clone, Debug)]
pub struct Protocol {
    /// Seed, epochs, optimiser, class-weight clip, early stopping: HO-LLN's `TrainConfig`.
    pub config: TrainConfig,
    /// HO-LLN's batch/learning-rate recipe for the recurrent nets.
    pub recipe: Recipe,
    pub projection: Projection,
    pub rule: OperatingPointRule,
    pub trees: TreeParams,
}

impl Protocol {
    /// HO-LLN's defaults with this seed, epoch limit and operating-point rule.
    pub fn new(seed: u64, max_epochs: usize, rule: OperatingPointRule) -> Self {
        Self {
            config: TrainConfig {
                seed,
                max_epochs,
                ..TrainConfig::default()
            },
            recipe: Recipe::Auto,
            projection: Projection::default(),
            rule,
            trees: TreeParams::default(),
        }
    }
}

enum Model {
    Net(Net),
    Trees(Trees),
}

/// A fitted, calibrated baseline.
pub struct Fitted {
    pub baseline: Baseline,
    pub operating_point: OperatingPoint,
    /// Per epoch (nets) or tree (ensembles).
    pub history: Vec<Epoch>,
    /// The kept epoch or number of trees.
    pub best_epoch: usize,
    /// Metrics at the operating point on the validation rows.
    pub validation: Metrics,
    evidence: EvidenceFit,
    model: Model,
}

/// Fits `baseline` on `train`, early-stopped and calibrated on `validation`.
pub fn fit(
    baseline: Baseline,
    train: Dataset<'_>,
    validation: Dataset<'_>,
    protocol: &Protocol,
) -> Result<Fitted, BaselineError> {
    let (kappa, rho) = DEFAULT_KAPPA_RHO;
    let evidence = fit_evidence(
        train.tracks,
        protocol.projection,
        kappa,
        rho,
        baseline.input.schema(),
    )?;
    let train_table = RowTable::build(&evidence, baseline.input, train)?;
    let validation_table = RowTable::build(&evidence, baseline.input, validation)?;
    let config = &protocol.config;
    let weights = train_table.class_weights(config.class_weight_min, config.class_weight_max)?;
    let train_weights = train_table.loss_weights(weights);
    let validation_weights = validation_table.loss_weights(weights);
    let (model, history, best_epoch) = match baseline.learner {
        Learner::Trees => {
            let (trees, history) = Trees::fit(
                protocol.trees,
                config.seed,
                &train_table,
                &train_weights,
                &validation_table,
                &validation_weights,
            )?;
            let kept = trees.trees();
            (Model::Trees(trees), history, kept)
        }
        learner => {
            let kind = match learner {
                Learner::Mlp => NetKind::Mlp,
                Learner::Gru => NetKind::Gru,
                _ => NetKind::Lstm,
            };
            let windows: usize = train_table
                .trajectories
                .iter()
                .map(|t| t.len().div_ceil(config.window))
                .sum();
            let config = if protocol.recipe.is_small_data(windows) {
                TrainConfig {
                    batch_size: SMALL_DATA_BATCH,
                    learning_rate: SMALL_DATA_LEARNING_RATE,
                    ..config.clone()
                }
            } else {
                config.clone()
            };
            let (net, history, best) = Net::fit(
                kind,
                &config,
                &train_table,
                &train_weights,
                &validation_table,
                &validation_weights,
            )?;
            (Model::Net(net), history, best)
        }
    };
    let rows = model.scored_rows(validation_table)?;
    let selection = choose_operating_point(
        &rows,
        &theta_grid(),
        N_P_GRID,
        EventRules::Spec,
        protocol.rule,
    )?;
    Ok(Fitted {
        baseline,
        operating_point: selection.point,
        history,
        best_epoch,
        validation: selection.metrics,
        evidence,
        model,
    })
}

impl Model {
    /// `table`'s rows with this model's spoofing probabilities as scores.
    fn scored_rows(&self, table: RowTable) -> Result<Vec<ScoredRow>, BaselineError> {
        let probabilities = match self {
            Model::Net(net) => net.probabilities(&table)?,
            Model::Trees(trees) => trees.probabilities(&table),
        };
        let mut rows = table.rows;
        for (row, p) in rows.iter_mut().zip(probabilities) {
            row.score = p;
        }
        Ok(rows)
    }
}

impl Fitted {
    /// Scores and confirmed alarms at the operating point on `data` (a fresh state per trajectory).
    pub fn score(&self, data: Dataset<'_>) -> Result<Scored, BaselineError> {
        let table = RowTable::build(&self.evidence, self.baseline.input, data)?;
        let rows = self.model.scored_rows(table)?;
        let alarms = confirmed_alarms(&rows, self.operating_point);
        Ok(Scored {
            rows,
            alarms,
            offset: Vec::new(),
            speed_mps: Vec::new(),
        })
    }
}
