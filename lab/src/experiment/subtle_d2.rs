//! `spoofwatch-lab experiment subtle-d2`: ramps injected into Dataset-2's real normal trajectories,
//! cross-validated by trajectory. Each fold holds one normal trajectory out as the test drive and
//! trains on the rest of Dataset-2 plus the subtle experiment's simulated mix, exactly as the
//! bundled default is trained; the operating point is chosen within the same false-alarm budget.
//! Dataset-2 is a ~1 m/s rover with a poor compass, far from the simulated cars: this is where the
//! drift channels meet real onboard errors.

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use serde::Serialize;
use spoofwatch_client::cli::evaluate::load_artifact;
use spoofwatch_client::cli::train::train_with_progress;
use spoofwatch_core::evaluation::score_tracks;
use spoofwatch_core::evidence::FeatureSchema;
use spoofwatch_core::rng::Rng;
use spoofwatch_core::sample::Track;
use spoofwatch_core::scenario::{AttackKind, AttackSpec, inject};
use spoofwatch_core::train::data::trajectory_ranges;
use spoofwatch_core::train::detector::TrainingData;
use spoofwatch_core::train::spec::{KappaRho, TrainingSpec};

use super::common::{CommonArgs, load_avgps, write_report};
use super::parallel::{default_threads, map_parallel};
use super::subtle::{
    ATTACK_S, DetectorReport, FALSE_ALARM_BUDGET_PER_HOUR, Population, TestSet, comparator_reports,
    operating_point_json, simulated_mix, within_budget,
};
use super::training_attacks::{is_normal, with_injections};

#[derive(Debug, clap::Args)]
pub struct Args {
    #[command(flatten)]
    common: CommonArgs,
    /// Randomised simulated drives per split added to training and validation (as `subtle`).
    #[arg(long, default_value_t = 48)]
    drives: u64,
    /// Also score these model artifacts on every held-out trajectory, each at its own operating
    /// point (a model trained without Dataset-2, such as the bundled default, has never seen any
    /// of its trajectories).
    #[arg(long)]
    also: Vec<PathBuf>,
}

/// Ramp velocities injected into the held-out trajectory (m/s); the goal is 2 m/s in 60 s.
const RAMPS_MPS: [f64; 4] = [0.5, 1.0, 1.5, 2.0];
/// Attacks start this far apart in the held-out trajectory (one attack per test copy)…
const ONSET_SPACING_S: f64 = 150.0;
/// …from this far in (the calibration has warmed up) to `ATTACK_S` + 10 s before its end.
const FIRST_ONSET_S: f64 = 300.0;
/// A normal trajectory shorter than this is not a fold.
const MIN_FOLD_S: f64 = 600.0;
/// Share of a held-in normal trajectory used for training; the rest validates.
const TRAIN_SHARE: f64 = 0.7;

/// Dataset-2's trajectories as tracks of their own (each starting a trajectory).
fn trajectories(dataset: &[Track]) -> Vec<Track> {
    let mut out = Vec::new();
    for track in dataset {
        for range in trajectory_ranges(&track.records) {
            let mut records = track.records[range].to_vec();
            records[0].trajectory_break = true;
            out.push(Track {
                vehicle_id: format!("{}~{}", track.vehicle_id, out.len()),
                records,
            });
        }
    }
    out
}

fn duration_s(track: &Track) -> f64 {
    match (track.records.first(), track.records.last()) {
        (Some(first), Some(last)) => last.sample.timestamp_s - first.sample.timestamp_s,
        _ => 0.0,
    }
}

/// Splits a track at `share` of its rows; the second part starts a trajectory.
fn split_at_share(track: &Track, share: f64) -> (Track, Track) {
    let cut = ((track.records.len() as f64 * share) as usize).clamp(1, track.records.len() - 1);
    let mut tail = track.records[cut..].to_vec();
    tail[0].trajectory_break = true;
    let part = |suffix: &str, records: Vec<_>| Track {
        vehicle_id: format!("{}{suffix}", track.vehicle_id),
        records,
    };
    (
        part("/train", track.records[..cut].to_vec()),
        part("/validation", tail),
    )
}

/// Copies of `track` with one ramp each: every magnitude at every onset, random directions.
fn ramp_scenarios(track: &Track, seed: u64, threads: usize) -> Result<TestSet> {
    let mut rng = Rng::seed_from_u64(seed);
    let last_onset = duration_s(track) - ATTACK_S - 10.0;
    let mut scenarios = Vec::new();
    let mut onset_s = FIRST_ONSET_S;
    while onset_s <= last_onset {
        for velocity_mps in RAMPS_MPS {
            let attack = AttackSpec {
                kind: AttackKind::RampDrift { velocity_mps },
                direction_deg: rng.uniform_range(0.0, 360.0),
                onset_s,
                duration_s: ATTACK_S,
                seed: Some(seed),
            };
            scenarios.push(
                inject(track, &attack)
                    .with_context(|| format!("injecting a ramp into {}", track.vehicle_id))?,
            );
        }
        onset_s += ONSET_SPACING_S;
    }
    Ok(TestSet {
        scenarios,
        clean: vec![track.clone()],
        threads,
    })
}

/// One fold: the held-out trajectory and every detector on it.
#[derive(Debug, Serialize)]
struct Fold {
    test_trajectory: String,
    test_hours: f64,
    attacks_per_magnitude: usize,
    detectors: Vec<DetectorReport>,
}

#[derive(Debug, Serialize)]
struct Report {
    protocol: &'static str,
    seed: u64,
    false_alarm_budget_per_hour: f64,
    ramps_mps: [f64; 4],
    folds: Vec<Fold>,
    experiment_wall_time_s: f64,
}

/// Training and validation data of a fold, and its test set.
struct FoldData {
    name: String,
    train: Vec<Track>,
    validation: Vec<Track>,
    test: TestSet,
}

fn fold_data(
    all: &[Track],
    held_out: usize,
    seed: u64,
    drives: u64,
    threads: usize,
) -> Result<FoldData> {
    let (mut train, mut validation) = (Vec::new(), Vec::new());
    for (i, track) in all.iter().enumerate() {
        if i == held_out {
            continue;
        }
        if is_normal(track) && duration_s(track) >= MIN_FOLD_S {
            let (head, tail) = split_at_share(track, TRAIN_SHARE);
            train.push(head);
            validation.push(tail);
        } else {
            train.push(track.clone());
        }
    }
    Ok(FoldData {
        name: all[held_out].vehicle_id.clone(),
        train: [
            with_injections(&train, seed, 0.0)?,
            simulated_mix(seed, Population::Train, drives, threads)?,
        ]
        .concat(),
        validation: [
            with_injections(&validation, seed ^ 0x5EED, 0.0)?,
            simulated_mix(seed, Population::Validation, drives, threads)?,
        ]
        .concat(),
        test: ramp_scenarios(&all[held_out], seed ^ held_out as u64, threads)?,
    })
}

pub fn run(args: Args) -> Result<()> {
    let started = Instant::now();
    let threads = args.common.threads.unwrap_or_else(default_threads);
    let data = load_avgps(&args.common.data_dir)?;
    std::fs::create_dir_all(&args.common.out)
        .with_context(|| format!("creating {}", args.common.out.display()))?;
    let seed = args.common.seed;
    let all = trajectories(&data.dataset2);
    let folds: Vec<usize> = (0..all.len())
        .filter(|&i| is_normal(&all[i]) && duration_s(&all[i]) >= MIN_FOLD_S)
        .collect();
    if folds.len() < 2 {
        bail!(
            "Dataset-2 has {} normal trajectories of at least {MIN_FOLD_S} s; cross-validation needs 2",
            folds.len()
        );
    }
    let fold_data = folds
        .iter()
        .map(|&k| fold_data(&all, k, seed, args.drives, threads))
        .collect::<Result<Vec<_>>>()?;
    let spec = TrainingSpec {
        data_description: vec![
            "AV-GPS-Dataset-2.csv without one normal trajectory (held-in normal trajectories 70/30), \
             with injected subtle attacks"
                .into(),
            format!("{} randomised simulated drives each for training and validation", args.drives),
        ],
        ..TrainingSpec::with(
            seed,
            args.common.epochs,
            FeatureSchema::V2,
            Default::default(),
            KappaRho::default(),
        )
    };
    let trained = map_parallel(&fold_data, threads, |fold| {
        let data = TrainingData::Explicit {
            train: fold.train.clone(),
            validation: fold.validation.clone(),
        };
        train_with_progress(&spec, data, false)
            .with_context(|| format!("training HO-LLN v2 without {}", fold.name))
    });
    let also = args
        .also
        .iter()
        .map(|path| Ok((path.display().to_string(), load_artifact(path)?)))
        .collect::<Result<Vec<_>>>()?;
    let mut report_folds = Vec::new();
    for (fold, trained) in fold_data.iter().zip(trained) {
        let name = "HO-LLN v2";
        let mut detectors = Vec::new();
        let test = &fold.test;
        let artifact = within_budget(name, trained?.artifact, &fold.validation).0;
        detectors.push(test.model_report(name, artifact.map(Arc::new).as_ref())?);
        for (name, artifact) in &also {
            detectors.push(test.report(name, operating_point_json(artifact), |tracks| {
                Ok(score_tracks(artifact, tracks))
            })?);
        }
        detectors.extend(comparator_reports(
            &fold.train,
            &fold.validation,
            spec.projection,
            test,
        )?);
        report_folds.push(Fold {
            test_trajectory: fold.name.clone(),
            test_hours: duration_s(&fold.test.clean[0]) / 3600.0,
            attacks_per_magnitude: fold.test.scenarios.len() / RAMPS_MPS.len(),
            detectors,
        });
    }
    let report = Report {
        protocol: "subtle-d2: Dataset-2 normal trajectories with injected ramps, cross-validated by trajectory",
        seed,
        false_alarm_budget_per_hour: FALSE_ALARM_BUDGET_PER_HOUR,
        ramps_mps: RAMPS_MPS,
        folds: report_folds,
        experiment_wall_time_s: started.elapsed().as_secs_f64(),
    };
    write_report(&args.common.out, &report, &render_markdown(&report))
}

fn render_markdown(report: &Report) -> String {
    let mut md = format!(
        "# subtle-d2 experiment\n\nRamps injected into one held-out Dataset-2 normal trajectory per fold \
         (onsets every {ONSET_SPACING_S} s from {FIRST_ONSET_S} s, {ATTACK_S} s long, random \
         directions); training on the rest of Dataset-2 plus the subtle experiment's simulated mix; \
         operating points within ≤ {} false alarm per attack-free validation hour; a model given \
         with --also keeps its own. Share detected within 30 s / 60 s per ramp velocity, then the \
         alarm's mean coverage of the detected ramps from their onset; false alarms per hour on the \
         clean held-out trajectory.\n\n| held-out trajectory | detector |",
        report.false_alarm_budget_per_hour
    );
    for v in RAMPS_MPS {
        md.push_str(&format!(" {v} m/s |"));
    }
    md.push_str(" false alarms per hour |\n|---|---|");
    md.push_str(&"---|".repeat(RAMPS_MPS.len() + 1));
    md.push('\n');
    for fold in &report.folds {
        for d in &fold.detectors {
            md.push_str(&format!(
                "| {} ({:.2} h, {} attacks per velocity) | {} |",
                fold.test_trajectory, fold.test_hours, fold.attacks_per_magnitude, d.name
            ));
            if d.operating_point.is_null() {
                md.push_str(" no operating point within the budget |\n");
                continue;
            }
            for row in &d.attacks {
                md.push_str(&format!(
                    " {:.2} / {:.2}, cov {} |",
                    row.adr_30s,
                    row.adr_60s,
                    row.coverage
                        .map_or_else(|| "–".into(), |c| format!("{c:.2}"))
                ));
            }
            md.push_str(&format!(
                " {:.2} ({} in {:.2} h) |\n",
                d.false_alarms_per_hour, d.false_alarm_events, d.attack_free_hours
            ));
        }
    }
    md
}
