//! What every learner shares: the one error of the baselines and the epochs of their training
//! curves.
//!
//! Owns [`BaselineError`] and [`Epoch`]. Must not fit or score anything (the learners and the
//! protocol in `lib.rs` do).

use serde::Serialize;
use spoofwatch_core::alarm::AlarmError;
use spoofwatch_core::evidence::EvidenceFitError;

/// Why a baseline could not be fitted or scored.
#[derive(Debug, thiserror::Error)]
pub enum BaselineError {
    #[error(transparent)]
    Data(#[from] EvidenceFitError),
    #[error("the raw-column input needs the recording's columns, and none were given")]
    NoColumns,
    #[error(
        "{vehicle}: source line {line} is not among the raw columns (columns of another file?)"
    )]
    MissingRow { vehicle: String, line: u64 },
    #[error("training needs ν = 1 rows of both classes")]
    OneClass,
    #[error("tensor computation: {0}")]
    Tensor(String),
    #[error("gradient boosting: {0}")]
    Trees(String),
    #[error("operating point: {0}")]
    OperatingPoint(#[from] AlarmError),
}

/// One epoch of a net, or one tree of an ensemble (then `val_auroc` is `None`).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Epoch {
    pub epoch: usize,
    pub train_loss: f64,
    pub val_loss: f64,
    pub val_auroc: Option<f64>,
}

impl From<&spoofwatch_core::train::EpochProgress> for Epoch {
    /// HO-LLN's own epoch, for curves drawn beside the baselines'.
    fn from(e: &spoofwatch_core::train::EpochProgress) -> Self {
        Self {
            epoch: e.epoch,
            train_loss: e.train_loss,
            val_loss: e.val_loss,
            val_auroc: e.val_auroc,
        }
    }
}
