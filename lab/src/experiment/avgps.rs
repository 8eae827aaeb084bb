//! The "av-gps" experiment of SPEC §9.

use std::sync::Arc;
use std::time::Instant;

use anyhow::{Context, Result};
use serde::Serialize;
use spoofwatch_baselines::{Baseline, Dataset, Epoch, GPS_IDS_COLUMNS, Learner, Protocol};
use spoofwatch_client::cli::json::write_json;
use spoofwatch_client::cli::train::train_with_progress;
use spoofwatch_client::report::{delays, metrics_table, seeds_table};
use spoofwatch_core::alarm::{OperatingPoint, OperatingPointRule};
use spoofwatch_core::cusum::{CusumComparator, fit_cusum_comparator};
use spoofwatch_core::data::{NumericColumns, read_numeric_columns};
use spoofwatch_core::evaluation::{Scored, evaluate_tracks, trajectory_key};
use spoofwatch_core::evidence::FeatureSchema;
use spoofwatch_core::metrics::{EventRules, Metrics, ScoredRow};
use spoofwatch_core::model::{Ablation, FeatureGroups};
use spoofwatch_core::sample::Track;
use spoofwatch_core::train::detector::TrainingData;
use spoofwatch_core::train::spec::{KappaRho, Recipe, TrainingSpec};

use super::common::{CommonArgs, prepare, seed_list};
use super::parallel::{default_threads, map_parallel};
use super::plots;
use super::training_attacks::with_injections;
use crate::figures;
use spoofwatch_core::model::artifact::ModelArtifact;

#[derive(Debug, clap::Args)]
pub struct Args {
    #[command(flatten)]
    common: CommonArgs,
    /// Headline model: train with injected subtle attacks added to the training part (SPEC §9 switch;
    /// off by default because it lowers the AV-GPS scores, see `docs/experiments.md`).
    #[arg(long)]
    subtle_training: bool,
    /// Skip the retrained ablations (faster).
    #[arg(long)]
    no_ablations: bool,
    /// Train the comparison (HO-LLN in both feature schemas and every baseline) with this many
    /// seeds (`--seed`, `--seed` + 1, ...) and report mean ± std; variants and ablations use
    /// `--seed` only.
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u64).range(1..=20))]
    seeds: u64,
    /// Leave out the learned baselines (MLP, GRU, LSTM, trees, GPS-IDS).
    #[arg(long)]
    no_baselines: bool,
}

/// One trained configuration.
#[derive(Clone, Debug)]
struct Variant {
    name: &'static str,
    /// The paper's rows use the paper's ξ; the v2 row shows what the drift channels change here.
    schema: FeatureSchema,
    ablation: Ablation,
    subtle_training: bool,
    recipe: Recipe,
    select_kappa_rho: bool,
}

/// One model to train: an HO-LLN variant or a baseline, with its seed.
#[derive(Clone, Debug)]
enum Job {
    HoLln(Variant, u64),
    Baseline(Baseline, u64),
}

impl Job {
    /// Rough relative cost, to start the longest fits first on the worker threads.
    fn cost(&self) -> u32 {
        match self {
            Job::Baseline(b, _) if matches!(b.learner, Learner::Lstm | Learner::Gru) => 3,
            Job::HoLln(..) => 2,
            Job::Baseline(..) => 1,
        }
    }
}

/// Scores of one detector on the two test sets.
#[derive(Clone, Debug, Serialize)]
pub struct VariantReport {
    pub name: String,
    pub seed: u64,
    pub subtle_training: bool,
    pub operating_point: OperatingPoint,
    pub train_wall_time_s: f64,
    pub epochs_run: u32,
    pub dataset2_test: Metrics,
    pub dataset3: Metrics,
    /// Loss and validation AUROC per epoch (per tree for the tree ensembles).
    pub training_curve: Vec<Epoch>,
}

impl VariantReport {
    /// Progress on stderr: the experiment trains dozens of models.
    fn log_trained(&self) {
        eprintln!(
            "av-gps: {} (seed {}) trained in {:.1} s",
            self.name, self.seed, self.train_wall_time_s
        );
    }
}

#[derive(Debug, Serialize)]
struct CusumReport {
    comparator: CusumComparator,
    dataset2_test: Metrics,
    dataset3: Metrics,
}

#[derive(Debug, Serialize)]
struct Report {
    protocol: &'static str,
    event_rules: &'static str,
    seed: u64,
    headline: String,
    operating_point: OperatingPoint,
    train_wall_time_s: f64,
    experiment_wall_time_s: f64,
    dataset2_test: Metrics,
    dataset3: Metrics,
    ekf_dataset3: Metrics,
    cusum: CusumReport,
    /// Every trained model: the variants (first seed) and the comparison (every seed).
    variants: Vec<VariantReport>,
    dataset3_delays_s: Vec<Option<f64>>,
    seeds: Vec<u64>,
    /// Detectors trained with every seed, in table order.
    compared: Vec<String>,
}

/// The two HO-LLN rows of the comparison (trained with every seed; the other variants with the first).
const HOLLN_PAPER: &str = "HO-LLN (ξ paper)";
const HOLLN_V2: &str = "HO-LLN (ξ v2)";
const HOLLN_SUBTLE: &str = "HO-LLN + subtle training";

fn variants(ablations: bool, headline_subtle: bool) -> Vec<Variant> {
    let full = Ablation::default();
    let mut list = vec![
        Variant {
            name: HOLLN_PAPER,
            schema: FeatureSchema::Paper,
            ablation: full,
            subtle_training: false,
            recipe: Recipe::Auto,
            select_kappa_rho: false,
        },
        Variant {
            name: HOLLN_V2,
            schema: FeatureSchema::V2,
            ablation: full,
            subtle_training: false,
            recipe: Recipe::Auto,
            select_kappa_rho: false,
        },
        Variant {
            name: HOLLN_SUBTLE,
            schema: FeatureSchema::Paper,
            ablation: full,
            subtle_training: true,
            recipe: Recipe::Auto,
            select_kappa_rho: false,
        },
        Variant {
            name: "HO-LLN, SPEC §6 recipe (batch 16, lr 1e-3)",
            schema: FeatureSchema::Paper,
            ablation: full,
            subtle_training: headline_subtle,
            recipe: Recipe::Spec,
            select_kappa_rho: false,
        },
        Variant {
            name: "HO-LLN, (κ, ρ) selected on validation",
            schema: FeatureSchema::Paper,
            ablation: full,
            subtle_training: headline_subtle,
            recipe: Recipe::Auto,
            select_kappa_rho: true,
        },
        Variant {
            name: "HO-LLN v2 (drift channels) + subtle training",
            schema: FeatureSchema::V2,
            ablation: full,
            subtle_training: true,
            recipe: Recipe::Auto,
            select_kappa_rho: false,
        },
    ];
    if ablations {
        let with = |name, ablation| Variant {
            name,
            schema: FeatureSchema::Paper,
            ablation,
            subtle_training: headline_subtle,
            recipe: Recipe::Auto,
            select_kappa_rho: false,
        };
        let features = |f| Ablation {
            features: f,
            ..full
        };
        list.extend([
            with(
                "no exchange",
                Ablation {
                    no_exchange: true,
                    ..full
                },
            ),
            with(
                "no third-order term",
                Ablation {
                    no_third_order: true,
                    ..full
                },
            ),
            with(
                "first-order cell",
                Ablation {
                    first_order_cell: true,
                    ..full
                },
            ),
            with(
                "accumulation removed",
                features(FeatureGroups::NoAccumulation),
            ),
            with("evolution removed", features(FeatureGroups::NoEvolution)),
            with(
                "evolution and q removed",
                features(FeatureGroups::NoEvolutionNoQ),
            ),
            with(
                "low-order evidence only",
                features(FeatureGroups::LowOrderOnly),
            ),
            with("validity only", features(FeatureGroups::ValidityOnly)),
        ]);
    }
    list
}

/// The EKF Detector column of Dataset-3 scored as a confirmed alarm (SPEC §8 fixed check).
fn ekf_metrics(dataset3: &[Track]) -> Metrics {
    let mut scored = Scored::default();
    for (i, track) in dataset3.iter().enumerate() {
        for r in &track.records {
            let alarm = r.comparator_alarm.unwrap_or(false);
            scored.rows.push(ScoredRow {
                trajectory: trajectory_key(i, 0),
                time_s: r.sample.timestamp_s,
                valid: true,
                label: r.label.unwrap_or(false),
                score: f64::from(u8::from(alarm)),
            });
            scored.alarms.push(alarm);
        }
    }
    scored.metrics(EventRules::Spec)
}

/// The jobs of the experiment: every variant with the first seed, and the comparison (HO-LLN in
/// both schemas and the baselines) with every seed.
fn jobs(args: &Args, seeds: &[u64]) -> Vec<Job> {
    let all = variants(!args.no_ablations, args.subtle_training);
    let mut jobs: Vec<Job> = Vec::new();
    for (k, &seed) in seeds.iter().enumerate() {
        for variant in &all {
            if k == 0 || [HOLLN_PAPER, HOLLN_V2].contains(&variant.name) {
                jobs.push(Job::HoLln(variant.clone(), seed));
            }
        }
        if !args.no_baselines {
            for schema in [FeatureSchema::Paper, FeatureSchema::V2] {
                jobs.extend(Baseline::on_evidence(schema).map(|b| Job::Baseline(b, seed)));
            }
            jobs.push(Job::Baseline(Baseline::GPS_IDS, seed));
        }
    }
    // Longest first (a stable sort keeps the report order within a cost class).
    jobs.sort_by_key(|job| std::cmp::Reverse(job.cost()));
    jobs
}

/// The comparison's detectors, in table order.
fn compared_names(baselines: bool) -> Vec<String> {
    let mut names = vec![HOLLN_PAPER.to_string(), HOLLN_V2.to_string()];
    if baselines {
        for schema in [FeatureSchema::Paper, FeatureSchema::V2] {
            names.extend(Baseline::on_evidence(schema).map(|b| b.name()));
        }
        names.push(Baseline::GPS_IDS.name());
    }
    names
}

/// Reads the GPS-IDS columns of one of the AV-GPS files (only the GPS-IDS baseline uses them).
fn raw_columns(args: &Args, file: &str) -> Result<Option<NumericColumns>> {
    if args.no_baselines {
        return Ok(None);
    }
    let path = args.common.data_dir.join(file);
    let reader =
        std::fs::File::open(&path).with_context(|| format!("opening {}", path.display()))?;
    Ok(Some(read_numeric_columns(reader, file, &GPS_IDS_COLUMNS)?))
}

pub fn run(args: Args) -> Result<()> {
    let started = Instant::now();
    let (data, split) = prepare(&args.common, 0.0)?;
    let subtle_train = with_injections(&split.train, args.common.seed, 0.0)?;
    let columns2 = raw_columns(&args, "AV-GPS-Dataset-2.csv")?;
    let columns3 = raw_columns(&args, "AV-GPS-Dataset-3.csv")?;
    let seeds = seed_list(args.common.seed, args.seeds);
    let jobs = jobs(&args, &seeds);
    let threads = args.common.threads.unwrap_or_else(default_threads);
    eprintln!(
        "av-gps: training {} models on {} threads ({} D2 training rows, {} with injected attacks)",
        jobs.len(),
        threads,
        rows(&split.train),
        rows(&subtle_train)
    );
    let on_d2 = |tracks| Dataset {
        tracks,
        columns: columns2.as_ref(),
    };
    let results = map_parallel(&jobs, threads, |job| -> Result<_> {
        match job {
            Job::HoLln(variant, seed) => {
                let train = if variant.subtle_training {
                    &subtle_train
                } else {
                    &split.train
                };
                let mut data_description = vec![
                    "AV-GPS-Dataset-2.csv chronological 70% (train) / 15% (validation)".into(),
                ];
                if variant.subtle_training {
                    data_description
                        .push("plus injected subtle attacks in the training part".into());
                }
                let spec = TrainingSpec {
                    recipe: variant.recipe,
                    data_description,
                    ..TrainingSpec::with(
                        *seed,
                        args.common.epochs,
                        variant.schema,
                        variant.ablation,
                        KappaRho::selected_if(variant.select_kappa_rho),
                    )
                };
                let training_data = TrainingData::Explicit {
                    train: train.clone(),
                    validation: split.validation.clone(),
                };
                let trained = train_with_progress(&spec, training_data, false)
                    .with_context(|| format!("training variant {} (seed {seed})", variant.name))?;
                let training_curve = trained.history.iter().map(Epoch::from).collect();
                let artifact = Arc::new(trained.artifact);
                let report = VariantReport {
                    name: variant.name.to_string(),
                    seed: *seed,
                    subtle_training: variant.subtle_training,
                    operating_point: artifact.operating_point,
                    train_wall_time_s: artifact.provenance.train_wall_time_s,
                    epochs_run: artifact.provenance.epochs_run,
                    dataset2_test: evaluate_tracks(&artifact, &split.test, EventRules::Spec)
                        .overall,
                    dataset3: evaluate_tracks(&artifact, &data.dataset3, EventRules::Spec).overall,
                    training_curve,
                };
                report.log_trained();
                Ok((report, Some(artifact)))
            }
            Job::Baseline(baseline, seed) => {
                let fit_started = Instant::now();
                let protocol = Protocol::new(
                    *seed,
                    args.common.epochs as usize,
                    OperatingPointRule::BestValidationF1,
                );
                let fitted = spoofwatch_baselines::fit(
                    *baseline,
                    on_d2(&split.train),
                    on_d2(&split.validation),
                    &protocol,
                )
                .with_context(|| format!("fitting {} (seed {seed})", baseline.name()))?;
                let score =
                    |data| -> Result<Metrics> { Ok(fitted.score(data)?.metrics(EventRules::Spec)) };
                let report = VariantReport {
                    name: baseline.name(),
                    seed: *seed,
                    subtle_training: false,
                    operating_point: fitted.operating_point,
                    train_wall_time_s: fit_started.elapsed().as_secs_f64(),
                    epochs_run: fitted.history.len() as u32,
                    dataset2_test: score(on_d2(&split.test))?,
                    dataset3: score(Dataset {
                        tracks: &data.dataset3,
                        columns: columns3.as_ref(),
                    })?,
                    training_curve: fitted.history,
                };
                report.log_trained();
                Ok((report, None))
            }
        }
    });
    let results = results.into_iter().collect::<Result<Vec<_>>>()?;
    let headline_name = if args.subtle_training {
        HOLLN_SUBTLE
    } else {
        HOLLN_PAPER
    };
    let (headline, artifact) = results
        .iter()
        .find(|(r, _)| r.name == headline_name && r.seed == seeds[0])
        .and_then(|(r, a)| Some((r, a.as_ref()?)))
        .context("the headline model is among the trained variants")?;
    let model_path = args.common.out.join("model.json");
    let file = std::fs::File::create(&model_path)
        .with_context(|| format!("creating {}", model_path.display()))?;
    artifact.write(std::io::BufWriter::new(file))?;
    write_figures(
        &args.common.out,
        artifact,
        &data.dataset3,
        &results,
        &compared_names(!args.no_baselines),
        seeds[0],
    )?;

    let comparator = fit_cusum_comparator(
        &split.train,
        &split.validation,
        spoofwatch_core::geo::Projection::Wgs84Local,
        OperatingPointRule::BestValidationF1,
    )
    .context("fitting the CUSUM comparator")?;
    let cusum_on = |tracks: &[Track]| comparator.score_tracks(tracks).metrics(EventRules::Spec);
    let cusum = CusumReport {
        dataset2_test: cusum_on(&split.test),
        dataset3: cusum_on(&data.dataset3),
        comparator,
    };
    let report = Report {
        protocol: "av-gps",
        event_rules: "spec",
        seed: args.common.seed,
        headline: headline.name.clone(),
        operating_point: headline.operating_point,
        train_wall_time_s: headline.train_wall_time_s,
        experiment_wall_time_s: started.elapsed().as_secs_f64(),
        dataset2_test: headline.dataset2_test.clone(),
        dataset3: headline.dataset3.clone(),
        dataset3_delays_s: headline.dataset3.delays_s.clone(),
        ekf_dataset3: ekf_metrics(&data.dataset3),
        cusum,
        variants: results.into_iter().map(|(r, _)| r).collect(),
        compared: compared_names(!args.no_baselines),
        seeds,
    };
    write_json(&args.common.out.join("report.json"), &report)?;
    let markdown = render_markdown(&report);
    std::fs::write(args.common.out.join("report.md"), &markdown)
        .with_context(|| format!("writing {}", args.common.out.join("report.md").display()))?;
    print!("{markdown}");
    Ok(())
}

/// The figures of report.md: the headline model's Dataset-3 trace (the paper's case study) and the
/// first seed's training curves (epochs of HO-LLN and the nets; trees of the ensembles).
fn write_figures(
    out: &std::path::Path,
    headline: &Arc<ModelArtifact>,
    dataset3: &[Track],
    results: &[(VariantReport, Option<Arc<ModelArtifact>>)],
    compared: &[String],
    first_seed: u64,
) -> Result<()> {
    let track = dataset3.first().context("Dataset-3 has a track")?;
    let evaluation = evaluate_tracks(headline, std::slice::from_ref(track), EventRules::Spec);
    let trace = figures::trace_of(
        "Dataset-3 case study: headline HO-LLN (ξ paper)",
        &evaluation.rows,
        &track.records,
        headline.operating_point.theta,
    )?;
    plots::write_svg(out, CASE_STUDY_SVG, &figures::trace_svg(&trace)?)?;
    // In table order, the first seed's run of each compared detector.
    let curves: Vec<(String, &[Epoch])> = compared
        .iter()
        .filter_map(|name| {
            results
                .iter()
                .find(|(r, _)| r.seed == first_seed && r.name == *name)
        })
        .map(|(r, _)| (r.name.clone(), r.training_curve.as_slice()))
        .collect();
    let title = format!("Training on Dataset-2 (seed {first_seed})");
    plots::write_training_curves(out, &title, &curves)
}

const CASE_STUDY_SVG: &str = "case-study-dataset3.svg";

fn rows(tracks: &[Track]) -> usize {
    tracks.iter().map(|t| t.records.len()).sum()
}

/// The paper's published rows (Table "Cross-scenario performance", Table "Dataset-3 event-level").
const PAPER_ROWS: &str = "\
| Paper, Dataset-2 (published) | 0.9899 | 0.9872 | 0.9567 | 0.9598 | 0.9536 | 0.0131 | 0.75 | 19.0 | - | - |
| Paper, Dataset-3 (published) | 0.9233 | 0.9661 | 0.8727 | 0.9205 | 0.8296 | 0.1266 | 1.00 | 35.0 | 29 | 2 |
";

fn render_markdown(report: &Report) -> String {
    let op = report.operating_point;
    let mut md = format!(
        "# av-gps experiment\n\n\
         Headline model: **{}**, seed {}, operating point θ = {:.2}, N_p = {} (chosen on the Dataset-2 \
         validation part), training {:.1} s, whole experiment {:.1} s. Event rules: SPEC §8 \
         (a detection needs a new confirmed-alarm onset inside the event).\n\n\
         ## Cross-scenario performance (paper layout)\n\n",
        report.headline,
        report.seed,
        op.theta,
        op.n_p,
        report.train_wall_time_s,
        report.experiment_wall_time_s
    );
    md.push_str(&format!(
        "Figures: [Dataset-3 case study]({CASE_STUDY_SVG}), [training curves]({}), \
         [tree ensembles' curves]({}).\n\n",
        plots::CURVES_SVG,
        plots::TREE_CURVES_SVG
    ));
    let table = metrics_table(&[
        ("HO-LLN, Dataset-2 test (ours)", &report.dataset2_test),
        ("HO-LLN, Dataset-3 (ours)", &report.dataset3),
        ("EKF Detector, Dataset-3", &report.ekf_dataset3),
    ]);
    md.push_str(&table);
    md.push_str(PAPER_ROWS);
    md.push_str(&format!(
        "\nDataset-3 event delays (s): ours {}; EKF {}; paper 16.0, 54.0.\n\n",
        delays(&report.dataset3),
        delays(&report.ekf_dataset3)
    ));
    let c = &report.cusum.comparator.cusum;
    md.push_str(&format!(
        "## χ²/CUSUM comparator\n\nk = {}, h = {:.3}, N_p = {} (chosen on the same validation part).\n\n",
        c.drift_k, c.threshold_h, c.n_p
    ));
    md.push_str(&metrics_table(&[
        ("CUSUM, Dataset-2 test", &report.cusum.dataset2_test),
        ("CUSUM, Dataset-3", &report.cusum.dataset3),
    ]));
    md.push_str(&comparison_markdown(report));
    md.push_str(&format!(
        "\n## Variants (seed {}, each retrained; subtle = injected subtle attacks in training)\n\n",
        report.seed
    ));
    let mut rows = Vec::new();
    for v in report.variants.iter().filter(|v| v.seed == report.seed) {
        let tag = if v.subtle_training { " [subtle]" } else { "" };
        rows.push((format!("{}{tag}, D2 test", v.name), &v.dataset2_test));
        rows.push((format!("{}{tag}, D3", v.name), &v.dataset3));
    }
    md.push_str(&metrics_table(&rows));
    md
}

/// HO-LLN against every baseline on both test sets, mean ± std over the seeds (paper layout).
fn comparison_markdown(report: &Report) -> String {
    let seeds: Vec<String> = report.seeds.iter().map(u64::to_string).collect();
    let mut md = format!(
        "\n## HO-LLN and the learned baselines: mean ± std over {} seed(s) ({})\n\n\
         Same training and validation parts, class weights, early stopping and validation-chosen \
         operating point for every detector; ξ paper / ξ v2 = the paper's evidence / with the drift \
         channels; GPS-IDS = trees on raw AV-GPS vehicle-dynamics columns. Standard deviations are \
         sample (n − 1) over seeds.\n",
        seeds.len(),
        seeds.join(", ")
    );
    let of = |name: &str, pick: fn(&VariantReport) -> &Metrics| -> Vec<&Metrics> {
        report
            .variants
            .iter()
            .filter(|v| v.name == name && report.seeds.contains(&v.seed))
            .map(pick)
            .collect()
    };
    for (title, pick) in [
        (
            "Dataset-2 test",
            (|v| &v.dataset2_test) as fn(&VariantReport) -> &Metrics,
        ),
        ("Dataset-3", |v| &v.dataset3),
    ] {
        let rows: Vec<(String, Vec<&Metrics>)> = report
            .compared
            .iter()
            .map(|name| (name.clone(), of(name, pick)))
            .collect();
        md.push_str(&format!("\n### {title}\n\n"));
        md.push_str(&seeds_table(&rows));
    }
    md
}
