//! Fitting the detector to a fleet from its own attack-free recordings (`docs/detector.md` §12):
//! a fleet has hours of its own vehicles' normal driving and no labelled attacks, so the fit learns
//! what normal looks like there and teaches attacks by injecting them into that driving.
//!
//! 1. Check the recordings and split their attack-free drives by time into fit, validation and test
//!    parts that never share a drive ([`data`]).
//! 2. Fit the fleet's priors: the onboard calibration's ([`prior`]); GNSS noise, the drift and
//!    offset channels' normalisation (so that the per-vehicle levels start at the fleet's own) and
//!    the scaler come with the evidence fit of training.
//! 3. Inject the training mix into the fit and validation drives ([`attacks`]).
//! 4. Train the starting model's configuration, from its weights or from scratch.
//! 5. Choose the warning operating point on the validation part, and the critical test when the
//!    validation part has enough clean hours at every rate to hold its budget; otherwise keep the
//!    starting model's, and say so. Both keep a margin below their budget on the validation hours
//!    ([`OperatingPointRule::WithinFalseAlarmBudgetWithMargin`]): a fleet's validation part is a
//!    few dozen hours, on which the best of hundreds of points looks better than it is.
//! 6. Score the fitted and the starting model on the test part alike ([`score`]).
//!
//! Owns the pipeline and its report. Must not do I/O or know about jobs, progress display or wire
//! formats (callers get epochs through `on_epoch`); the evidence, training and search rules are
//! their modules'.

pub mod attacks;
pub mod data;
pub mod prior;
pub mod score;

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use serde::{Deserialize, Serialize};

use crate::alarm::OperatingPointRule;
use crate::critical_search::choose_critical_within;
use crate::evaluation::score_tracks;
use crate::metrics::{self, EventRules, Metrics};
use crate::model::artifact::ModelArtifact;
use crate::sample::Track;
use crate::scenario::ScenarioError;
use crate::severity::CriticalTest;
use crate::train::EpochProgress;
use crate::train::detector::{TrainDetectorError, TrainingData, train_detector};
use crate::train::spec::{AnchorRebase, KappaRho, TrainingSpec};

use self::data::{Drive, FitDataError};
use self::prior::FittedPrior;
use self::score::ModelScore;

/// The warning level's budget: false alarms per attack-free vehicle-hour.
pub const WARNING_BUDGET_PER_HOUR: f64 = 1.0;
/// The critical level's: one per hundred vehicle-hours.
pub const CRITICAL_BUDGET_PER_HOUR: f64 = 0.01;
/// Most injected pieces trained on, from the fit part and from the validation part each: bounds a
/// fit's time on a large fleet (the clean drives are all used).
pub const MAX_INJECTED_PIECES: usize = 400;
/// Mixed into the seed for the validation part's injected attacks and the test part's.
const VALIDATION_STREAM: u64 = 0x005E_ED0F_7A11;
const TEST_STREAM: u64 = 0x007E_570F_7A11;

/// What a fleet fit is asked to do.
#[derive(Clone, Debug, PartialEq)]
pub struct FleetFitSpec {
    pub seed: u64,
    /// Training epochs (at least 1).
    pub max_epochs: u32,
    /// Train new weights instead of starting from the starting model's.
    pub from_scratch: bool,
    /// The sample rate the recordings are said to have (Hz); `None`: whatever they have.
    pub sample_rate_hz: Option<f64>,
    /// Describes the data in the fitted model's provenance.
    pub data_description: Vec<String>,
    /// Whether the fitted model's anchors re-base when the calibration in use changes (in
    /// service only, `Margin`, in the service's fits; the lab measures the others).
    pub anchor_rebase: AnchorRebase,
}

/// The fitted model and its report.
#[derive(Clone, Debug)]
pub struct FleetFit {
    pub artifact: ModelArtifact,
    pub report: FleetFitReport,
    /// The warning level's metrics on the validation part (clean and injected).
    pub validation: Metrics,
    pub history: Vec<EpochProgress>,
    pub cancelled: bool,
}

/// One part of the split.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct PartSummary {
    pub drives: usize,
    pub vehicles: usize,
    pub hours: f64,
}

/// How the critical test was decided.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CriticalChoice {
    pub test: Option<CriticalTest>,
    /// `chosen` on the validation part, or `kept` from the starting model.
    pub how: String,
    pub reason: String,
}

/// What the fit did and bought.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FleetFitReport {
    pub fit: PartSummary,
    pub validation: PartSummary,
    pub test: PartSummary,
    /// The sample rates found (Hz).
    pub rates_hz: Vec<f64>,
    pub calibration_prior: FittedPrior,
    /// GNSS noise: Σ̂'s per-axis standard deviations (m), fitted and the starting model's.
    pub gnss_sigma_m: [f64; 2],
    pub starting_gnss_sigma_m: [f64; 2],
    pub from_scratch: bool,
    pub injected_training_pieces: usize,
    pub injected_validation_pieces: usize,
    pub warning_theta: f64,
    pub critical: CriticalChoice,
    /// The test part, for the fitted model and for the starting one.
    pub fitted: ModelScore,
    pub starting: ModelScore,
}

/// Why a fit failed.
#[derive(Debug, thiserror::Error)]
pub enum FleetFitError {
    #[error("{field}: {0}", field = .0.field())]
    Data(FitDataError),
    #[error("injecting attacks into the fleet's drives")]
    Scenario(#[from] ScenarioError),
    #[error(transparent)]
    Train(#[from] TrainDetectorError),
    #[error("the starting model has no alarm lifecycle in seconds (a `v3` model is needed)")]
    StartingModel,
}

// By hand rather than `#[from]`: the message already holds the data error's, which as a source
// would be printed twice in an error chain.
impl From<FitDataError> for FleetFitError {
    fn from(error: FitDataError) -> Self {
        Self::Data(error)
    }
}

/// Fits `starting`'s configuration to the fleet of `recordings` (attack-free; rows labelled
/// attacked are left out), validating on `validation` when given, else on a part of the
/// recordings (module docs).
pub fn fit_fleet(
    spec: &FleetFitSpec,
    recordings: &[Track],
    validation: &[Track],
    starting: &Arc<ModelArtifact>,
    on_epoch: &mut dyn FnMut(&EpochProgress),
    cancel: &AtomicBool,
) -> Result<FleetFit, FleetFitError> {
    if starting.lifecycle.is_none() {
        return Err(FleetFitError::StartingModel);
    }
    let drives = data::drives(recordings);
    data::check(recordings, &drives, spec.sample_rate_hz)?;
    let given = data::drives(validation);
    if !validation.is_empty() && given.is_empty() {
        return Err(FitDataError::Validation(format!(
            "no attack-free drive of at least {} s",
            data::MIN_DRIVE_S
        ))
        .into());
    }
    let split = data::split(drives, given)?;
    let tracks = |part: &[Drive]| -> Vec<Track> { part.iter().map(|d| d.track.clone()).collect() };
    let (fit_tracks, validation_tracks) = (tracks(&split.fit), tracks(&split.validation));
    let projection = starting.evidence.projection;
    let prior = prior::fit_calibration_prior(&fit_tracks, projection);

    let injected_fit = attacks::training_injections(&fit_tracks, spec.seed, MAX_INJECTED_PIECES)?;
    let injected_validation = attacks::training_injections(
        &validation_tracks,
        spec.seed ^ VALIDATION_STREAM,
        MAX_INJECTED_PIECES,
    )?;
    let training = training_spec(spec, starting, &prior);
    let trained = train_detector(
        &training,
        TrainingData::Explicit {
            train: [fit_tracks, injected_fit.clone()].concat(),
            validation: [validation_tracks.clone(), injected_validation.clone()].concat(),
        },
        on_epoch,
        cancel,
    )?;
    let mut artifact = trained.artifact;
    let rates = data::rates(&[&split.fit[..], &split.validation, &split.test].concat());
    // A cancelled fit registers nothing: it stops here rather than choose and score for minutes.
    let cancelled = cancel.load(Ordering::Relaxed);
    let critical = if cancelled {
        CriticalChoice {
            test: starting.critical,
            how: "kept".to_string(),
            reason: "the fit was cancelled".to_string(),
        }
    } else {
        // Chosen on the evidence the warning point was chosen on (without re-basing under
        // `Margin`), then served as the artifact says.
        let mut chosen_on = artifact.clone();
        chosen_on.set_anchor_rebasing(spec.anchor_rebase.when_choosing());
        choose_critical_level(
            &chosen_on,
            starting,
            &[validation_tracks, injected_validation.clone()].concat(),
        )
    };
    artifact.critical = critical.test;

    let grid = attacks::detection_grid();
    let test_attacks = if cancelled {
        Vec::new()
    } else {
        attacks::test_injections(&tracks(&split.test), spec.seed ^ TEST_STREAM)?
    };
    let fitted = Arc::new(artifact.clone());
    let score = |model: &Arc<ModelArtifact>| {
        if cancelled {
            score::ModelScore::default()
        } else {
            score::score(model, &split.test, &rates, &test_attacks, &grid)
        }
    };
    let report = FleetFitReport {
        fit: summary(&split.fit),
        validation: summary(&split.validation),
        test: summary(&split.test),
        rates_hz: rates.clone(),
        calibration_prior: prior,
        gnss_sigma_m: sigma_m(&artifact),
        starting_gnss_sigma_m: sigma_m(starting),
        from_scratch: spec.from_scratch,
        injected_training_pieces: injected_fit.len(),
        injected_validation_pieces: injected_validation.len(),
        warning_theta: artifact.operating_point.theta,
        critical,
        fitted: score(&fitted),
        starting: score(starting),
    };
    Ok(FleetFit {
        artifact,
        report,
        validation: trained.validation,
        history: trained.history,
        cancelled,
    })
}

/// The training spec of a fit: the starting model's configuration and (κ, ρ), the fleet's prior,
/// its weights unless from scratch, and the warning point within its budget with a margin.
fn training_spec(
    spec: &FleetFitSpec,
    starting: &ModelArtifact,
    prior: &FittedPrior,
) -> TrainingSpec {
    let config = starting.model.config().clone();
    let evidence = &starting.evidence;
    TrainingSpec {
        model: config.clone(),
        projection: evidence.projection,
        operating_point: OperatingPointRule::WithinFalseAlarmBudgetWithMargin {
            per_hour: WARNING_BUDGET_PER_HOUR,
        },
        data_description: spec.data_description.clone(),
        calibration_prior: prior.kept_default.is_none().then_some(prior.prior),
        initial_model: (!spec.from_scratch).then(|| starting.model.clone()),
        anchor_rebase: spec.anchor_rebase,
        ..TrainingSpec::with(
            spec.seed,
            spec.max_epochs,
            config.schema,
            config.ablation,
            KappaRho::Fixed(evidence.kappa, evidence.rho),
        )
    }
}

/// The critical test: chosen on `validation` when every rate there has enough clean hours for its
/// budget to bind, else the starting model's.
fn choose_critical_level(
    fitted: &ModelArtifact,
    starting: &ModelArtifact,
    validation: &[Track],
) -> CriticalChoice {
    let kept = |reason: String| CriticalChoice {
        test: starting.critical,
        how: "kept".to_string(),
        reason,
    };
    let Some(lifecycle) = fitted.lifecycle else {
        return kept("the fitted model has no lifecycle in seconds".to_string());
    };
    let warning_only = Arc::new(ModelArtifact {
        critical: None,
        ..fitted.clone()
    });
    let scored = score_tracks(&warning_only, validation);
    let groups = metrics::rate_groups(&scored.rows);
    let needed = 1.0 / CRITICAL_BUDGET_PER_HOUR;
    if let Some(short) = groups.iter().find(|g| g.normal_hours < needed) {
        return kept(format!(
            "{:.1} attack-free validation hours at {} Hz cannot hold one critical alarm per \
             {needed} hours (at least {needed} are needed at every rate)",
            short.normal_hours, short.rate_hz
        ));
    }
    match choose_critical_within(
        &scored.rows,
        &scored.offset,
        fitted.operating_point.theta,
        &lifecycle,
        OperatingPointRule::WithinFalseAlarmBudgetWithMargin {
            per_hour: CRITICAL_BUDGET_PER_HOUR,
        },
        EventRules::Spec,
    ) {
        Ok(selection) => CriticalChoice {
            test: Some(selection.test),
            how: "chosen".to_string(),
            reason: format!(
                "on {:.0} attack-free validation hours",
                metrics::normal_hours(&scored.rows)
            ),
        },
        Err(error) => kept(format!(
            "no critical test of the grid keeps itself and its twice-as-sensitive twin within the \
             budget (a test counts its twin's onsets): {error}"
        )),
    }
}

fn summary(part: &[Drive]) -> PartSummary {
    let vehicles: std::collections::BTreeSet<&str> =
        part.iter().map(|d| d.vehicle_id.as_str()).collect();
    PartSummary {
        drives: part.len(),
        vehicles: vehicles.len(),
        hours: part.iter().map(Drive::hours).sum(),
    }
}

fn sigma_m(artifact: &ModelArtifact) -> [f64; 2] {
    let s = artifact.evidence.sigma_hat;
    [s[0][0].max(0.0).sqrt(), s[1][1].max(0.0).sqrt()]
}
