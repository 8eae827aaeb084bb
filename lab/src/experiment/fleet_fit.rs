//! The "fleet-fit" experiment (`docs/detector.md` §12): the detector fitted to a fleet from its
//! attack-free recordings with core's `fit_fleet`, exactly as the server's fit job runs it, on two
//! fleets the bundled model was not trained on:
//!
//! - `dataset2`: AV-GPS Dataset-2's rover (real, poor compass, unsigned speed when reversing). It is
//!   one vehicle; its trajectories (separate power-ons) stand for the fleet's vehicles. The fit uses
//!   the earlier part of its normal driving and tests on the later part.
//! - `wide-sensors`: simulated vehicles at 5 Hz whose compasses are off by up to ±15° and whose
//!   speed scale is off by up to ±10 % (each vehicle its own, constant over its drives), with every
//!   other error source of the fleet distribution. Beside the fit's own test part, both models are
//!   scored on an independent clean fleet of the same kind (`--clean-hours`), enough hours to bound
//!   the critical level's rate.
//!
//! Owns the two fleets and the report. Must not fit or score itself (core's `fleet_fit` does).

use std::fmt::Write as _;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::AtomicBool;
use std::time::Instant;

use anyhow::{Context, Result};
use serde::Serialize;
use spoofwatch_client::cli::evaluate::load_artifact;
use spoofwatch_client::cli::fit_report::render as render_fit;
use spoofwatch_core::fleet_fit::attacks::detection_grid;
use spoofwatch_core::fleet_fit::data::drives;
use spoofwatch_core::fleet_fit::score::{ModelScore, score};
use spoofwatch_core::fleet_fit::{FleetFitReport, FleetFitSpec, fit_fleet};
use spoofwatch_core::metrics::Pace;
use spoofwatch_core::rng::Rng;
use spoofwatch_core::sample::Track;
use spoofwatch_core::scenario::{DriveDistribution, simulate_drive};
use spoofwatch_core::train::data::trajectory_ranges;
use spoofwatch_proto::wire::fit::fit_report_to_proto;

use super::common::{AnchorRebaseArg, load_avgps, write_report};
use super::parallel::{default_threads, map_parallel};

/// Sample rate of the simulated fleet (Hz).
const FLEET_RATE_HZ: f64 = 5.0;
/// Widest compass and speed-scale errors of the simulated fleet.
const HEADING_BIAS_DEG: f64 = 15.0;
const SPEED_SCALE_ERROR: f64 = 0.10;
/// Length of a simulated drive (s).
const DRIVE_S: f64 = 1_800.0;

#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum Fleet {
    Dataset2,
    WideSensors,
}

#[derive(Debug, clap::Args)]
pub struct Args {
    /// The fleet to fit to.
    #[arg(long, value_enum)]
    fleet: Fleet,
    /// The starting model (its configuration and, unless --from-scratch, its weights).
    #[arg(long, default_value = "models/default.json")]
    model: PathBuf,
    /// Output directory (report.json, report.md, model.json).
    #[arg(long)]
    out: PathBuf,
    /// Directory of the AV-GPS recordings (for `dataset2`).
    #[arg(long, env = "SPOOFWATCH_AVGPS_DIR")]
    data_dir: Option<PathBuf>,
    #[arg(long, default_value_t = 42)]
    seed: u64,
    /// Training epochs.
    #[arg(long, default_value_t = 10)]
    epochs: u32,
    /// Train new weights instead of starting from the model's.
    #[arg(long)]
    from_scratch: bool,
    /// Re-base the fitted model's offset anchors when the calibration in use changes: in service
    /// only, both operating points chosen without it (`margin`, as the service's fits do), in the
    /// search too (`serve`), in training too (`train-and-serve`), or not at all (`off`).
    #[arg(long, value_enum, default_value = "margin")]
    anchor_rebase: AnchorRebaseArg,
    /// Simulated fleet: vehicles, and half-hour drives per vehicle.
    #[arg(long, default_value_t = 24)]
    vehicles: u64,
    #[arg(long, default_value_t = 4)]
    drives_per_vehicle: u64,
    /// Simulated fleet: attack-free vehicle-hours of the independent clean fleet both models are
    /// scored on (0: none).
    #[arg(long, default_value_t = 300)]
    clean_hours: u64,
    /// Worker threads for simulating and scoring (default: every core).
    #[arg(long)]
    threads: Option<usize>,
}

#[derive(Serialize)]
struct Report {
    fleet: String,
    model: String,
    seed: u64,
    epochs: u32,
    fit: FleetFitReport,
    /// The independent clean fleet (simulated fleet only): the fitted and the starting model.
    independent_clean: Option<(ModelScore, ModelScore)>,
    independent_clean_hours: f64,
    wall_time_s: f64,
    /// The fit alone (`fit_fleet`: checks, split, prior, injection, training, operating points and
    /// the test part's scoring), without simulating the fleet or scoring the independent one.
    fit_wall_time_s: f64,
}

pub fn run(args: Args) -> Result<()> {
    let started = Instant::now();
    let threads = args.threads.unwrap_or_else(default_threads);
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    let starting = load_artifact(&args.model)?;
    let (recordings, description) = match args.fleet {
        Fleet::Dataset2 => {
            let dir = args
                .data_dir
                .as_ref()
                .context("--data-dir (or SPOOFWATCH_AVGPS_DIR) is needed for dataset2")?;
            (
                trajectories_as_vehicles(&load_avgps(dir)?.dataset2),
                "AV-GPS-Dataset-2.csv's attack-free driving, its trajectories as vehicles"
                    .to_string(),
            )
        }
        Fleet::WideSensors => (
            wide_sensor_fleet(args.seed, args.vehicles, args.drives_per_vehicle, threads)?,
            format!(
                "{} simulated vehicles × {} drives of {DRIVE_S} s at {FLEET_RATE_HZ} Hz, compasses \
                 within ±{HEADING_BIAS_DEG}°, speed scale within ±{}%",
                args.vehicles,
                args.drives_per_vehicle,
                SPEED_SCALE_ERROR * 100.0
            ),
        ),
    };
    let spec = FleetFitSpec {
        seed: args.seed,
        max_epochs: args.epochs,
        from_scratch: args.from_scratch,
        sample_rate_hz: None,
        data_description: vec![description],
        anchor_rebase: args.anchor_rebase.into(),
    };
    eprintln!("fitting to {} recordings", recordings.len());
    let mut on_epoch = |e: &spoofwatch_core::train::EpochProgress| {
        eprintln!(
            "epoch {}: train {:.4} val {:.4}",
            e.epoch, e.train_loss, e.val_loss
        )
    };
    let fit_started = Instant::now();
    let fitted = fit_fleet(
        &spec,
        &recordings,
        &[],
        &starting,
        &mut on_epoch,
        &AtomicBool::new(false),
    )?;
    let fit_wall_time_s = fit_started.elapsed().as_secs_f64();
    let mut written = fitted.artifact.clone();
    written.provenance.train_wall_time_s = 0.0;
    spoofwatch_client::cli::json::write_json(&args.out.join("model.json"), &written)?;

    let (independent_clean, independent_clean_hours) = if args.fleet == Fleet::WideSensors
        && args.clean_hours > 0
    {
        let clean = wide_sensor_fleet(args.seed ^ 0x00C1_EA4F_1EE7, args.clean_hours, 2, threads)?;
        let clean_drives = drives(&clean);
        let hours = clean_drives.iter().map(|d| d.hours()).sum();
        let rates = [FLEET_RATE_HZ];
        let fitted_model = Arc::new(fitted.artifact.clone());
        let chunks: Vec<Vec<_>> = clean_drives.chunks(8).map(<[_]>::to_vec).collect();
        let scores = map_parallel(&chunks, threads, |chunk| {
            (
                score(&fitted_model, chunk, &rates, &[], &detection_grid()),
                score(&starting, chunk, &rates, &[], &detection_grid()),
            )
        });
        (Some(merge(scores)), hours)
    } else {
        (None, 0.0)
    };
    let report = Report {
        fleet: format!("{:?}", args.fleet),
        model: args.model.display().to_string(),
        seed: args.seed,
        epochs: args.epochs,
        fit: fitted.report,
        independent_clean,
        independent_clean_hours,
        wall_time_s: started.elapsed().as_secs_f64(),
        fit_wall_time_s,
    };
    let markdown = render(&report);
    write_report(&args.out, &report, &markdown)
}

/// Each trajectory of `dataset` as a vehicle of its own.
fn trajectories_as_vehicles(dataset: &[Track]) -> Vec<Track> {
    let mut out = Vec::new();
    for track in dataset {
        for (k, range) in trajectory_ranges(&track.records).into_iter().enumerate() {
            let mut records = track.records[range].to_vec();
            records[0].trajectory_break = true;
            out.push(Track {
                vehicle_id: format!("{}~{k}", track.vehicle_id),
                records,
            });
        }
    }
    out
}

/// `vehicles` × `drives` simulated drives of the fleet distribution at 5 Hz, each vehicle with its
/// own compass and speed-scale error, one after another in time.
fn wide_sensor_fleet(seed: u64, vehicles: u64, drives: u64, threads: usize) -> Result<Vec<Track>> {
    let jobs: Vec<(u64, u64)> = (0..vehicles)
        .flat_map(|v| (0..drives).map(move |d| (v, d)))
        .collect();
    map_parallel(&jobs, threads, |&(vehicle, drive)| {
        let mut rng = Rng::seed_from_u64(seed ^ vehicle.wrapping_mul(0x9E37_79B9_7F4A_7C15));
        let heading = rng.uniform_range(-HEADING_BIAS_DEG, HEADING_BIAS_DEG);
        let scale = rng.uniform_range(-SPEED_SCALE_ERROR, SPEED_SCALE_ERROR);
        let mut spec = DriveDistribution::fleet().draw(seed.wrapping_add(vehicle * 1_000 + drive));
        spec.duration_s = DRIVE_S;
        spec.rate_hz = FLEET_RATE_HZ;
        spec.onboard_errors.heading_bias_deg = heading;
        spec.onboard_errors.speed_scale_error = scale;
        let id = format!("wide-{vehicle}");
        let mut track = simulate_drive(&spec, &id).with_context(|| format!("simulating {id}"))?;
        let offset = drive as f64 * 2.0 * DRIVE_S;
        for record in &mut track.records {
            record.sample.timestamp_s += offset;
            record.label = None;
        }
        Ok(track)
    })
    .into_iter()
    .collect()
}

/// The clean counts of several scores of the same rates, added up.
fn merge(scores: Vec<(ModelScore, ModelScore)>) -> (ModelScore, ModelScore) {
    let (mut fitted, mut starting) = (ModelScore::default(), ModelScore::default());
    for (f, s) in &scores {
        fitted.add_clean(f);
        starting.add_clean(s);
    }
    (fitted, starting)
}

fn render(report: &Report) -> String {
    let mut md = format!(
        "# Fleet fit: {}\n\nStarting model `{}`, seed {}, {} epochs; the fit {:.0} s, {:.0} s in all.\n\n\
         ```text\n{}```\n\n",
        report.fleet,
        report.model,
        report.seed,
        report.epochs,
        report.fit_wall_time_s,
        report.wall_time_s,
        render_fit(&fit_report_to_proto(&report.fit))
    );
    if let Some((fitted, starting)) = &report.independent_clean {
        let _ = writeln!(
            md,
            "## False alarms on an independent clean fleet ({:.0} vehicle-hours)\n",
            report.independent_clean_hours
        );
        clean_table(&mut md, fitted, starting);
    }
    md
}

fn clean_table(md: &mut String, fitted: &ModelScore, starting: &ModelScore) {
    md.push_str(
        "| rate | road | drives | hours | warning fitted | warning bundled | critical fitted | \
         critical bundled |\n|---|---|---|---|---|---|---|---|\n",
    );
    for (f, s) in fitted.clean.iter().zip(&starting.clean) {
        let _ = writeln!(
            md,
            "| {} Hz | {} | {} | {:.2} | {} ({:.3}/h) | {} ({:.3}/h) | {} ({:.4}/h) | {} ({:.4}/h) |",
            f.rate_hz,
            f.pace.map_or("all", Pace::name),
            f.drives,
            f.hours,
            f.warning_onsets,
            f.warning_per_hour,
            s.warning_onsets,
            s.warning_per_hour,
            f.critical_onsets,
            f.critical_per_hour,
            s.critical_onsets,
            s.critical_per_hour
        );
    }
    md.push('\n');
}
