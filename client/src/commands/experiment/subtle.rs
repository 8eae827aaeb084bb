//! The "subtle" experiment of SPEC §9, and the injected subtle attacks used for training.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::Instant;

use anyhow::{Context, Result};
use serde::Serialize;
use spoofwatch_core::alarm::{N_P_GRID, OperatingPointRule, choose_operating_point, theta_grid};
use spoofwatch_core::cusum::{CusumComparator, fit_cusum_comparator};
use spoofwatch_core::evaluation::{evaluate_tracks, score_tracks};
use spoofwatch_core::evidence::FeatureSchema;
use spoofwatch_core::metrics::{EventRules, Metrics};
use spoofwatch_core::model::artifact::ModelArtifact;
use spoofwatch_core::sample::Track;
use spoofwatch_core::scenario::{
    AttackDuration, AttackKind, DriveSpec, InjectedTrack, RAMP_SWEEP_VELOCITIES_MPS, ScenarioPlan,
    generate, normal_runs, simulate_drive,
};
use spoofwatch_core::train::detector::TrainingData;
use spoofwatch_core::train::spec::{KappaRho, TrainingSpec};

use super::parallel::{default_threads, map_parallel};
use super::{CommonArgs, prepare, with_injections};
use crate::commands::train::train_with_progress;
use crate::commands::write_json;

/// Attacks injected into training (and, in the subtle experiment, validation) data: magnitudes a
/// metre-level GNSS/odometry residual can reveal, so the labels are learnable.
const TRAINING_KINDS: [AttackKind; 7] = [
    AttackKind::RampDrift { velocity_mps: 0.5 },
    AttackKind::RampDrift { velocity_mps: 1.0 },
    AttackKind::RampDrift { velocity_mps: 2.0 },
    AttackKind::AcceleratingDrift {
        acceleration_mps2: 0.05,
    },
    AttackKind::AcceleratingDrift {
        acceleration_mps2: 0.2,
    },
    AttackKind::FrozenPosition,
    AttackKind::Jump { offset_m: 30.0 },
];

/// Length of the pieces normal tracks are cut into before injection, and of each attack (s).
const TRAINING_PIECE_S: f64 = 300.0;
const TRAINING_ATTACK_S: f64 = 90.0;

/// Cuts tracks into consecutive pieces of about `piece_s` seconds (shorter remainders are dropped).
fn pieces(tracks: &[Track], piece_s: f64) -> Vec<Track> {
    let mut out = Vec::new();
    for track in tracks {
        let mut start = 0;
        for (i, r) in track.records.iter().enumerate() {
            let t0 = track.records[start].sample.timestamp_s;
            if r.sample.timestamp_s - t0 >= piece_s {
                let mut records = track.records[start..i].to_vec();
                records[0].trajectory_break = true;
                out.push(Track {
                    vehicle_id: format!("{}@{}", track.vehicle_id, out.len()),
                    records,
                });
                start = i;
            }
        }
    }
    out
}

fn is_normal(track: &Track) -> bool {
    track.records.iter().all(|r| r.label != Some(true))
}

/// Labelled copies of the normal tracks' pieces, every training attack kind injected into each piece
/// (random onset and direction), for training.
pub fn training_injections(tracks: &[Track], seed: u64) -> Result<Vec<Track>> {
    let normal: Vec<Track> = tracks.iter().filter(|t| is_normal(t)).cloned().collect();
    let bases = pieces(&normal, TRAINING_PIECE_S);
    let mut out = Vec::new();
    for (i, base) in bases.iter().enumerate() {
        let plan = ScenarioPlan {
            kinds: TRAINING_KINDS.to_vec(),
            directions_deg: Vec::new(),
            duration: AttackDuration::Seconds(TRAINING_ATTACK_S),
            onset_s: None,
            margin_fraction: 0.15,
            repeats: 1,
            seed: seed.wrapping_add(i as u64),
        };
        let injected = generate(std::slice::from_ref(base), &plan)
            .with_context(|| format!("injecting a training attack into {}", base.vehicle_id))?;
        out.extend(injected.into_iter().map(|i| i.track));
    }
    Ok(out)
}

#[derive(Debug, clap::Args)]
pub struct Args {
    #[command(flatten)]
    common: CommonArgs,
    /// Simulated drives used as extra attack-free bases (10 minutes each).
    #[arg(long, default_value_t = 6)]
    drives: u64,
    /// Scenarios per (base, attack) with random onsets and directions.
    #[arg(long, default_value_t = 3)]
    repeats: usize,
}

/// Test grid: every attack family over its SPEC §9 magnitude range.
fn test_kinds() -> Vec<AttackKind> {
    let mut kinds: Vec<AttackKind> = RAMP_SWEEP_VELOCITIES_MPS
        .iter()
        .map(|&velocity_mps| AttackKind::RampDrift { velocity_mps })
        .collect();
    kinds.extend(
        [0.01, 0.02, 0.05, 0.1, 0.2, 0.5]
            .map(|acceleration_mps2| AttackKind::AcceleratingDrift { acceleration_mps2 }),
    );
    kinds.push(AttackKind::FrozenPosition);
    kinds.extend([5.0, 20.0, 100.0, 1000.0].map(|offset_m| AttackKind::Jump { offset_m }));
    kinds
}

const TEST_ATTACK_S: f64 = 60.0;
/// The false-alarm budget of the issue: at most one false alarm per hour of attack-free driving.
const FALSE_ALARM_BUDGET_PER_HOUR: f64 = 1.0;
const DETECTION_WINDOW_S: f64 = 30.0;
const DRIVE_S: f64 = 600.0;

/// One detector's results for one attack kind and magnitude.
#[derive(Clone, Debug, Default, Serialize)]
pub struct AttackRow {
    pub family: String,
    pub magnitude: Option<f64>,
    pub events: usize,
    pub adr: f64,
    /// Fraction detected within 30 s of onset.
    pub adr_30s: f64,
    pub median_delay_s: Option<f64>,
}

#[derive(Debug, Serialize)]
struct DetectorReport {
    operating_point: serde_json::Value,
    attacks: Vec<AttackRow>,
    attack_free_hours: f64,
    false_alarm_events: u64,
    false_alarms_per_hour: f64,
    smallest_ramp_mps_adr90_within_30s: Option<f64>,
}

/// HO-LLN and CUSUM at operating points chosen by one rule.
#[derive(Debug, Serialize)]
struct Comparison {
    ho_lln: DetectorReport,
    cusum: DetectorReport,
}

#[derive(Debug, Serialize)]
struct Report {
    protocol: &'static str,
    seed: u64,
    scenarios: usize,
    bases: Vec<String>,
    /// Operating points of SPEC §7 (best validation F1).
    validation_f1: Comparison,
    /// Best validation F1 among the points with at most [`FALSE_ALARM_BUDGET_PER_HOUR`] false alarms
    /// per attack-free hour of validation data.
    within_budget: Comparison,
    false_alarm_budget_per_hour: f64,
    experiment_wall_time_s: f64,
}

fn median(values: &mut [f64]) -> Option<f64> {
    if values.is_empty() {
        return None;
    }
    values.sort_by(f64::total_cmp);
    let n = values.len();
    Some(if n % 2 == 1 {
        values[n / 2]
    } else {
        (values[n / 2 - 1] + values[n / 2]) / 2.0
    })
}

/// Groups per-scenario delays (one event each) by attack kind.
fn attack_rows(scenarios: &[InjectedTrack], delays: &[Option<f64>]) -> Vec<AttackRow> {
    let mut groups: BTreeMap<String, (AttackKind, Vec<Option<f64>>)> = BTreeMap::new();
    for (s, d) in scenarios.iter().zip(delays) {
        let key = format!(
            "{:>10}{:>12.4}",
            s.attack.kind.family(),
            s.attack.kind.magnitude().unwrap_or(0.0)
        );
        groups
            .entry(key)
            .or_insert_with(|| (s.attack.kind, Vec::new()))
            .1
            .push(*d);
    }
    groups
        .into_values()
        .map(|(kind, delays)| {
            let events = delays.len();
            let mut detected: Vec<f64> = delays.iter().flatten().copied().collect();
            let fast = detected
                .iter()
                .filter(|&&d| d <= DETECTION_WINDOW_S)
                .count();
            AttackRow {
                family: kind.family().to_string(),
                magnitude: kind.magnitude(),
                events,
                adr: detected.len() as f64 / events as f64,
                adr_30s: fast as f64 / events as f64,
                median_delay_s: median(&mut detected),
            }
        })
        .collect()
}

fn smallest_ramp(rows: &[AttackRow]) -> Option<f64> {
    let ramp = AttackKind::RampDrift { velocity_mps: 1.0 }.family();
    rows.iter()
        .filter(|r| r.family == ramp && r.adr_30s >= 0.9)
        .filter_map(|r| r.magnitude)
        .reduce(f64::min)
}

fn hours(tracks: &[Track]) -> f64 {
    tracks
        .iter()
        .filter_map(|t| {
            Some(t.records.last()?.sample.timestamp_s - t.records.first()?.sample.timestamp_s)
        })
        .sum::<f64>()
        / 3600.0
}

/// The attacked scenarios and attack-free bases every detector is scored on.
struct TestSet<'a> {
    scenarios: &'a [InjectedTrack],
    bases: &'a [Track],
    threads: usize,
}

impl TestSet<'_> {
    fn report(
        &self,
        operating_point: serde_json::Value,
        delays: &[Option<f64>],
        attack_free: &Metrics,
    ) -> DetectorReport {
        let attacks = attack_rows(self.scenarios, delays);
        let attack_free_hours = hours(self.bases);
        DetectorReport {
            operating_point,
            smallest_ramp_mps_adr90_within_30s: smallest_ramp(&attacks),
            attacks,
            attack_free_hours,
            false_alarm_events: attack_free.false_alarm_events,
            false_alarms_per_hour: attack_free.false_alarm_events as f64 / attack_free_hours,
        }
    }

    fn ho_lln(&self, artifact: &Arc<ModelArtifact>) -> Result<DetectorReport> {
        let delays = map_parallel(self.scenarios, self.threads, |s| {
            first_delay(
                evaluate_tracks(artifact, std::slice::from_ref(&s.track), EventRules::Spec).overall,
            )
        });
        let attack_free = evaluate_tracks(artifact, self.bases, EventRules::Spec).overall;
        Ok(self.report(
            serde_json::to_value(artifact.operating_point)?,
            &delays,
            &attack_free,
        ))
    }

    fn cusum(&self, comparator: &CusumComparator) -> Result<DetectorReport> {
        let delays = map_parallel(self.scenarios, self.threads, |s| {
            let scored = comparator.score_tracks(std::slice::from_ref(&s.track));
            first_delay(scored.metrics(EventRules::Spec))
        });
        let attack_free = comparator
            .score_tracks(self.bases)
            .metrics(EventRules::Spec);
        Ok(self.report(
            serde_json::to_value(&comparator.cusum)?,
            &delays,
            &attack_free,
        ))
    }
}

/// Delay of a scenario's single attack event (`None` when missed).
fn first_delay(metrics: Metrics) -> Option<f64> {
    metrics.delays_s.first().copied().flatten()
}

pub fn run(args: Args) -> Result<()> {
    let started = Instant::now();
    let (data, split) = prepare(&args.common)?;
    // Injected attacks in training and validation: the operating point is chosen for subtle attacks.
    let train = with_injections(&split.train, args.common.seed)?;
    let validation = with_injections(&split.validation, args.common.seed ^ 0x5EED)?;

    let mut bases: Vec<Track> = split
        .test
        .iter()
        .filter(|t| is_normal(t))
        .cloned()
        .collect();
    for track in &data.dataset3 {
        bases.extend(normal_runs(track));
    }
    for k in 0..args.drives {
        let spec = DriveSpec {
            duration_s: DRIVE_S,
            seed: args.common.seed.wrapping_mul(1000).wrapping_add(k),
            ..DriveSpec::default()
        };
        bases.push(simulate_drive(&spec, &format!("sim{k}")).context("simulating a drive")?);
    }
    let plan = ScenarioPlan {
        kinds: test_kinds(),
        directions_deg: Vec::new(),
        duration: AttackDuration::Seconds(TEST_ATTACK_S),
        onset_s: None,
        margin_fraction: 0.1,
        repeats: args.repeats,
        seed: args.common.seed.wrapping_add(7),
    };
    let scenarios = generate(&bases, &plan).context("generating the test scenarios")?;
    eprintln!(
        "subtle: {} scenarios on {} attack-free bases ({:.2} h)",
        scenarios.len(),
        bases.len(),
        hours(&bases)
    );

    let spec = TrainingSpec {
        data_description: vec![
            "AV-GPS-Dataset-2.csv chronological 70/15 + injected subtle attacks in both".into(),
        ],
        ..TrainingSpec::with(
            args.common.seed,
            args.common.epochs,
            FeatureSchema::default(),
            Default::default(),
            KappaRho::default(),
        )
    };
    let data = TrainingData::Explicit {
        train: train.clone(),
        validation: validation.clone(),
    };
    let trained = train_with_progress(&spec, data, false)?;
    let artifact = Arc::new(trained.artifact);
    artifact.write(std::io::BufWriter::new(
        std::fs::File::create(args.common.out.join("model.json")).context("creating model.json")?,
    ))?;
    let comparator = fit_cusum_comparator(
        &train,
        &validation,
        spec.projection,
        OperatingPointRule::BestValidationF1,
    )
    .context("fitting the CUSUM comparator")?;
    let budget = OperatingPointRule::WithinFalseAlarmBudget {
        per_hour: FALSE_ALARM_BUDGET_PER_HOUR,
    };

    let threads = args.common.threads.unwrap_or_else(default_threads);
    let within_budget_point = choose_operating_point(
        &score_tracks(&artifact, &validation).rows,
        &theta_grid(),
        N_P_GRID,
        EventRules::Spec,
        budget,
    )
    .context("choosing the HO-LLN operating point within the false-alarm budget")?
    .point;
    let budgeted_artifact = Arc::new(ModelArtifact {
        operating_point: within_budget_point,
        ..(*artifact).clone()
    });
    let budgeted_comparator = fit_cusum_comparator(&train, &validation, spec.projection, budget)
        .context("fitting the CUSUM comparator within the false-alarm budget")?;
    let test = TestSet {
        scenarios: &scenarios,
        bases: &bases,
        threads,
    };
    let report = Report {
        protocol: "subtle",
        seed: args.common.seed,
        scenarios: scenarios.len(),
        bases: bases.iter().map(|b| b.vehicle_id.clone()).collect(),
        validation_f1: Comparison {
            ho_lln: test.ho_lln(&artifact)?,
            cusum: test.cusum(&comparator)?,
        },
        within_budget: Comparison {
            ho_lln: test.ho_lln(&budgeted_artifact)?,
            cusum: test.cusum(&budgeted_comparator)?,
        },
        false_alarm_budget_per_hour: FALSE_ALARM_BUDGET_PER_HOUR,
        experiment_wall_time_s: started.elapsed().as_secs_f64(),
    };
    write_json(&args.common.out.join("report.json"), &report)?;
    let markdown = render_markdown(&report);
    std::fs::write(args.common.out.join("report.md"), &markdown).context("writing report.md")?;
    print!("{markdown}");
    Ok(())
}

fn fmt_opt(x: Option<f64>) -> String {
    x.map_or_else(|| "-".into(), |v| format!("{v:.1}"))
}

fn render_markdown(report: &Report) -> String {
    let mut md = format!(
        "# subtle experiment\n\n{} scenarios (60 s attacks, random onsets and directions) injected into {} \
         attack-free bases: Dataset-2 normal test parts, Dataset-3 normal runs, simulated drives. \
         Detection = a new confirmed-alarm onset inside the attack (SPEC §8); ADR@30s counts detections \
         within 30 s of onset. Each detector is scored at two operating points chosen on validation data: \
         the best F1 (SPEC §7), and the best F1 among the points with at most {} false alarm(s) per \
         attack-free hour.\n\n\
         | operating point | detector | smallest ramp with ADR@30s ≥ 0.9 | false alarms per hour |\n\
         |---|---|---|---|\n",
        report.scenarios,
        report.bases.len(),
        report.false_alarm_budget_per_hour,
    );
    let sections = [
        ("best validation F1", &report.validation_f1),
        ("within the false-alarm budget", &report.within_budget),
    ];
    for (rule, comparison) in sections {
        for (name, d) in [("HO-LLN", &comparison.ho_lln), ("CUSUM", &comparison.cusum)] {
            md.push_str(&format!(
                "| {rule} | {name} | {} | {:.2} ({} in {:.2} h) |\n",
                d.smallest_ramp_mps_adr90_within_30s
                    .map_or("none".into(), |v| format!("{v} m/s")),
                d.false_alarms_per_hour,
                d.false_alarm_events,
                d.attack_free_hours,
            ));
        }
    }
    for (rule, comparison) in sections {
        md.push_str(&format!(
            "\n## {rule}\n\nHO-LLN at {}; CUSUM at {}.\n\n\
             | attack | magnitude | events | HO-LLN ADR | HO-LLN ADR@30s | HO-LLN median delay (s) | CUSUM ADR | CUSUM ADR@30s | CUSUM median delay (s) |\n\
             |---|---|---|---|---|---|---|---|---|\n",
            comparison.ho_lln.operating_point, comparison.cusum.operating_point,
        ));
        let (model, cusum) = (&comparison.ho_lln.attacks, &comparison.cusum.attacks);
        for (m, c) in model.iter().zip(cusum) {
            md.push_str(&format!(
                "| {} | {} | {} | {:.2} | {:.2} | {} | {:.2} | {:.2} | {} |\n",
                m.family,
                m.magnitude.map_or("-".into(), |v| v.to_string()),
                m.events,
                m.adr,
                m.adr_30s,
                fmt_opt(m.median_delay_s),
                c.adr,
                c.adr_30s,
                fmt_opt(c.median_delay_s),
            ));
        }
    }
    md
}
