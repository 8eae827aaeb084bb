//! The training use case: [`train_detector`] turns a [`TrainingSpec`] and labelled tracks into a
//! calibrated model artifact. The CLI `train`, the server's training job and the experiments all call
//! it; nothing else assembles a trained artifact.
//!
//! Steps (SPEC §4–7): split the data, fit the evidence statistics on the training part, train the
//! HO-LLN model on sequences ([`crate::train::train`]), score the validation part with the streaming
//! detector and choose (θ, N_p) by the spec's operating-point rule. Must not do I/O or know about
//! progress display, job queues or wire formats (callers get epochs through `on_epoch`).

use std::sync::Arc;
use std::sync::atomic::AtomicBool;
use std::time::Instant;

use crate::alarm::{
    AlarmError, N_P_GRID, OperatingPoint, Selection, choose_lifecycle, choose_operating_point,
    lifecycle_theta_grid, theta_grid,
};
use crate::evaluation::score_tracks;
use crate::evidence::calibration::CalibrationTrust;
use crate::evidence::{EvidenceFitError, EvidenceOptions, fit_evidence_with};
use crate::metrics::{EventRules, Metrics};
use crate::model::artifact::{ARTIFACT_SCHEMA_VERSION, ModelArtifact, Provenance};
use crate::sample::Track;
use crate::train::data::{sequences, split_chronologically};
use crate::train::spec::{AnchorRebase, TrainingSpec};
use crate::train::{EpochProgress, TrainError, train, train_from};

/// The labelled tracks of a training job and how validation data is obtained.
#[derive(Clone, Debug, PartialEq)]
pub enum TrainingData {
    /// Every trajectory is split chronologically by [`TrainingSpec::split`] into
    /// train/validation/test parts (SPEC §9); the test part is kept as [`TrainedDetector::held_out`].
    Chronological(Vec<Track>),
    /// Explicit training and validation tracks; nothing is held out.
    Explicit {
        train: Vec<Track>,
        validation: Vec<Track>,
    },
}

impl TrainingData {
    /// Chronological when `validation` is empty, else explicit: the rule of the CLI and the server.
    pub fn split_unless_validation(tracks: Vec<Track>, validation: Vec<Track>) -> Self {
        if validation.is_empty() {
            Self::Chronological(tracks)
        } else {
            Self::Explicit {
                train: tracks,
                validation,
            }
        }
    }
}

/// A trained, operating-point-calibrated detector and how it got there.
#[derive(Clone, Debug)]
pub struct TrainedDetector {
    pub artifact: ModelArtifact,
    pub history: Vec<EpochProgress>,
    /// Metrics at the chosen operating point on the validation part.
    pub validation: Metrics,
    /// The chronological test part (empty with explicit validation data).
    pub held_out: Vec<Track>,
}

impl TrainedDetector {
    /// Metrics of the artifact on the held-out test part; `None` when nothing was held out.
    pub fn held_out_metrics(&self, rules: EventRules) -> Option<Metrics> {
        if self.held_out.is_empty() {
            return None;
        }
        let artifact = Arc::new(self.artifact.clone());
        Some(crate::evaluation::evaluate_tracks(&artifact, &self.held_out, rules).overall)
    }
}

/// Errors of the whole training job.
#[derive(Debug, thiserror::Error)]
pub enum TrainDetectorError {
    #[error(transparent)]
    Data(#[from] EvidenceFitError),
    #[error("training: {0}")]
    Train(#[from] TrainError),
    #[error(
        "the starting model's configuration (widths, schema, ablation) differs from the one to train"
    )]
    StartingModel,
    #[error("no operating point: the validation data needs both normal and spoofed valid rows")]
    NoOperatingPoint,
    #[error("no operating point within the false-alarm budget: {0}")]
    OverBudget(AlarmError),
}

/// Trains the detector `spec` describes on `data` (SPEC §4–7). With several (κ, ρ) candidates, the
/// one with the best validation F1 (then lower validation loss) wins. `on_epoch` sees every epoch
/// of every candidate; `cancel` stops training at the next batch (see [`crate::train::train`]), and
/// the run ends with [`TrainError::Cancelled`].
pub fn train_detector(
    spec: &TrainingSpec,
    data: TrainingData,
    on_epoch: &mut dyn FnMut(&EpochProgress),
    cancel: &AtomicBool,
) -> Result<TrainedDetector, TrainDetectorError> {
    let started = Instant::now();
    let (train, validation, held_out) = match data {
        TrainingData::Chronological(tracks) => {
            let split = split_chronologically(&tracks, spec.split);
            (split.train, split.validation, split.test)
        }
        TrainingData::Explicit { train, validation } => (train, validation, Vec::new()),
    };
    let mut best: Option<(TrainedDetector, f64)> = None;
    for (kappa, rho) in spec.kappa_rho.candidates() {
        let candidate = train_candidate(&train, &validation, spec, kappa, rho, on_epoch, cancel)?;
        let val_loss = candidate
            .history
            .iter()
            .map(|e| e.val_loss)
            .fold(f64::INFINITY, f64::min);
        let better = match &best {
            None => true,
            Some((b, b_loss)) => {
                let (f1, b_f1) = (candidate.validation.f1, b.validation.f1);
                f1 > b_f1 || (f1 == b_f1 && val_loss < *b_loss)
            }
        };
        if better {
            best = Some((candidate, val_loss));
        }
    }
    // `candidates()` is never empty, so a first candidate always exists.
    let Some((mut trained, _)) = best else {
        unreachable!("KappaRho::candidates is never empty")
    };
    trained.artifact.provenance.train_wall_time_s = started.elapsed().as_secs_f64();
    trained.held_out = held_out;
    Ok(trained)
}

fn train_candidate(
    train_tracks: &[Track],
    validation: &[Track],
    spec: &TrainingSpec,
    kappa: f64,
    rho: f64,
    on_epoch: &mut dyn FnMut(&EpochProgress),
    cancel: &AtomicBool,
) -> Result<TrainedDetector, TrainDetectorError> {
    let fit = fit_evidence_with(
        train_tracks,
        spec.projection,
        kappa,
        rho,
        spec.model.schema,
        EvidenceOptions {
            vehicle_levels: !spec.model.ablation.no_vehicle_levels,
            trust: if spec.model.ablation.timer_trust {
                CalibrationTrust::Timers
            } else {
                CalibrationTrust::Information
            },
            calibration_prior: spec.calibration_prior,
            rebase_anchors: spec.anchor_rebase == AnchorRebase::TrainAndServe,
        },
    )?;
    let mask_exits = !spec.model.ablation.no_exit_mask;
    let train_seqs = sequences(&fit, train_tracks, mask_exits);
    let val_seqs = sequences(&fit, validation, mask_exits);
    let train_config = spec.recipe.apply(&spec.train, &train_seqs);
    let outcome = match &spec.initial_model {
        Some(initial) => {
            if initial.config() != &spec.model {
                return Err(TrainDetectorError::StartingModel);
            }
            train_from(
                &train_seqs,
                &val_seqs,
                initial.clone(),
                &train_config,
                on_epoch,
                cancel,
            )?
        }
        None => train(
            &train_seqs,
            &val_seqs,
            spec.model.clone(),
            &train_config,
            on_epoch,
            cancel,
        )?,
    };
    // A cancelled run registers nothing: it stops here rather than search for an operating point
    // with half-trained weights, which may find none and so end as a failure, not a cancellation.
    if outcome.cancelled {
        return Err(TrainError::Cancelled.into());
    }
    // Under `Serve` the operating points below are chosen on the evidence the model serves; under
    // `Margin` on the evidence without re-basing, which the model serves with once they are chosen.
    let mut evidence = fit.params;
    if let Some(offset) = evidence.offset.as_mut() {
        offset.rebase_on_calibration = spec.anchor_rebase.when_choosing();
    }
    let mut artifact = ModelArtifact {
        schema_version: ARTIFACT_SCHEMA_VERSION,
        feature_names: ModelArtifact::feature_names_of(spec.model.schema),
        model: outcome.model,
        evidence,
        scaler: fit.scaler,
        // Provisional: probabilities do not depend on it; replaced below.
        operating_point: OperatingPoint { theta: 0.5, n_p: 1 },
        lifecycle: None,
        critical: None,
        provenance: Provenance {
            created_by: format!("spoofwatch {}", env!("CARGO_PKG_VERSION")),
            training_data: Provenance::bounded_training_data(spec.data_description.clone()),
            seed: spec.train.seed,
            training_rows: train_seqs.iter().map(|s| s.features.len() as u64).sum(),
            epochs_run: outcome.history.len() as u32,
            best_epoch: outcome.best_epoch as u32,
            train_wall_time_s: 0.0,
            validation_metrics: None,
            notes: format!(
                "kappa={kappa} rho={rho}; batch {} windows, learning rate {}; Sigma/mu_e from {} \
                 normal valid training rows",
                train_config.batch_size, train_config.learning_rate, fit.normal_rows
            ),
        },
    };
    let scored = score_tracks(&Arc::new(artifact.clone()), validation);
    let no_point = |error| match error {
        AlarmError::OverBudget { .. } => TrainDetectorError::OverBudget(error),
        _ => TrainDetectorError::NoOperatingPoint,
    };
    // Offset evidence comes with the lifecycle in seconds; older schemas keep the persistence N_p.
    let (point, lifecycle, metrics) = if spec.model.lifecycle_in_seconds() {
        let selection = choose_lifecycle(
            &scored.rows,
            &scored.offset,
            &scored.speed_mps,
            &lifecycle_theta_grid(),
            spec.rules,
            spec.operating_point,
        )
        .map_err(no_point)?;
        (
            selection.point,
            Some(selection.lifecycle),
            selection.metrics,
        )
    } else {
        let Selection { point, metrics } = choose_operating_point(
            &scored.rows,
            &theta_grid(),
            N_P_GRID,
            spec.rules,
            spec.operating_point,
        )
        .map_err(no_point)?;
        (point, None, metrics)
    };
    artifact.operating_point = point;
    artifact.lifecycle = lifecycle;
    artifact.set_anchor_rebasing(spec.anchor_rebase.when_serving());
    artifact.provenance.validation_metrics = Some(metrics.clone());
    Ok(TrainedDetector {
        artifact,
        history: outcome.history,
        validation: metrics,
        held_out: Vec::new(),
    })
}
