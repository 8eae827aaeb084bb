//! The "fleet-alarms" experiment (`docs/detector.md` §7.4): both alarm severities of one model,
//! measured the way a fleet counts them.
//!
//! 1. **Choose the critical test** on validation data, unless the model keeps its own: attack-free
//!    hour-long drives of the fleet distribution at 1, 5 and 10 Hz (enough hours that a budget of
//!    one per hundred binds at every rate) and the offsets suite's attacked drives, early and late,
//!    at every rate. The warning level (θ and lifecycle) stays the model's.
//! 2. **Clean fleets**: attack-free hour-long drives of the fleet distribution (every error source
//!    of a real fleet: GNSS bias, multipath, outages with offset reacquisition, heading bias and its
//!    wander, static hold, speed scale, lag), seeds apart from validation's; onsets per
//!    vehicle-hour at each level, per rate and road kind, with every onset's time.
//! 3. **Detection**: the offsets suite's attacked test drives; per attack, onset and rate, the
//!    share alarmed within the warning deadline, the share critical within the critical one, and the
//!    critical episode's coverage of the attack; every drive's outcome in `drives.csv`, with what
//!    explains a miss (the vehicle's speed and standing share, the anchors' track age at onset).
//!
//! Owns the fleet study's drives and report. Must not fit evidence, train or change the warning
//! level (core and the offsets suite do).

use std::fmt::Write as _;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

use anyhow::{Context, Result};
use serde::Serialize;
use spoofwatch_client::cli::evaluate::load_artifact;
use spoofwatch_core::alarm::OperatingPointRule;
use spoofwatch_core::critical_search::{CriticalSelection, choose_critical_within};
use spoofwatch_core::detector::{Decision, offset_signal, run_records};
use spoofwatch_core::evaluation::{Scored, score_tracks, trajectory_key};
use spoofwatch_core::metrics::{EventRules, ScoredRow};
use spoofwatch_core::model::artifact::ModelArtifact;
use spoofwatch_core::scenario::{AttackKind, DriveDistribution, Range, RoadKind, simulate_drive};
use spoofwatch_core::severity::{CriticalTest, Severity};

use super::offsets::{
    AFTER_START_S, Distribution, OUTAGE_S, Population, RATES_HZ, TestDrive, TestKind, drive_seed,
    median, test_set,
};
use super::parallel::{default_threads, map_parallel};
use super::subtle::delay_and_coverage;

/// The paging budget: critical onsets per attack-free vehicle-hour, at every rate.
pub const CRITICAL_BUDGET_PER_HOUR: f64 = 0.01;
/// The dashboard budget the warning level is held to (per vehicle-hour, at every rate).
const WARNING_BUDGET_PER_HOUR: f64 = 1.0;
/// Length of a clean drive (s): an hour, as a vehicle in service drives.
const CLEAN_DRIVE_S: f64 = 3_600.0;
/// Drifts may take this much longer to turn critical than to alarm: the sequential test's threshold
/// for a hundred times fewer false alarms is about ln 100 ≈ 4.6 nats above the warning's ≈ 8.
const DRIFT_CRITICAL_FACTOR: f64 = 1.5;
/// Mixed into the seed of the validation drives, so that no validation drive is a test drive.
const VALIDATION_SEED: u64 = 0x005E_ED0F_7A11;

#[derive(Debug, clap::Args)]
pub struct Args {
    /// The model whose alarms are measured (its θ and lifecycle are the warning level).
    #[arg(long, default_value = "models/default.json")]
    model: PathBuf,
    /// Output directory (report.json, report.md, onsets.csv, drives.csv).
    #[arg(long)]
    out: PathBuf,
    /// Seed of the drives.
    #[arg(long, default_value_t = 42)]
    seed: u64,
    /// Attack-free validation hours per sample rate for choosing the critical test (at least 100,
    /// so that one false alarm per hundred hours binds at every rate).
    #[arg(long, default_value_t = 150, value_parser = clap::value_parser!(u64).range(100..=100_000))]
    validation_hours: u64,
    /// Attack-free test hours per sample rate.
    #[arg(long, default_value_t = 1000, value_parser = clap::value_parser!(u64).range(1..=100_000))]
    test_hours: u64,
    /// The distribution the attacked drives (validation and test) are drawn from.
    #[arg(long, value_enum, default_value = "fleet")]
    distribution: Distribution,
    /// Attacked drives per attack kind, onset and rate, for validation and for the test.
    #[arg(long, default_value_t = 10, value_parser = clap::value_parser!(u64).range(1..=1000))]
    repeats: u64,
    /// Measure the model's own critical test instead of choosing one.
    #[arg(long)]
    keep_critical: bool,
    /// Choose the critical test with the fleet fit's guard band: its onsets one Poisson deviation
    /// below the budget's count, and its twice-as-sensitive twin within that too
    /// (`docs/detector.md` §12.3).
    #[arg(long, conflicts_with = "keep_critical")]
    guard_band: bool,
    /// Choose the critical test on evidence whose anchors do not re-base when the calibration in
    /// use changes, then write and measure the model with re-basing on: the warning point's
    /// choice under `offsets --anchor-rebase margin` (`docs/detector.md` §4.2).
    #[arg(long, conflicts_with = "keep_critical")]
    serve_rebased: bool,
    /// Write the model with the chosen critical test to this file (without its training wall time,
    /// so that retraining writes the same bytes).
    #[arg(long)]
    write_model: Option<PathBuf>,
    /// Drive every clean drive (validation and test) without these error sources of the fleet
    /// distribution: `wander`, `static-hold`, `reacquisition` (ablations of the drives, not of
    /// the detector).
    #[arg(long, value_delimiter = ',', value_parser = ["wander", "static-hold", "reacquisition"])]
    without: Vec<String>,
    /// Worker threads (default: every core).
    #[arg(long)]
    threads: Option<usize>,
}

/// Onsets of one level on the clean drives of one rate and road kind.
#[derive(Clone, Debug, Default, Serialize)]
struct CleanCount {
    rate_hz: f64,
    road: &'static str,
    severity: &'static str,
    drives: u64,
    hours: f64,
    onsets: u64,
    per_hour: f64,
    /// Of them, within [`AFTER_START_S`] of a session start or an outage's end.
    after_start_or_outage: u64,
}

/// One alarm onset (or escalation) on a clean drive.
#[derive(Clone, Debug, Serialize)]
struct CleanOnset {
    vehicle_id: String,
    rate_hz: f64,
    road: &'static str,
    severity: &'static str,
    time_s: f64,
    /// Seconds since the session started or the last outage ended.
    since_resumed_s: f64,
    /// The dominant evidence at that sample.
    why: &'static str,
}

/// Detection of one attack kind, onset and rate at both levels.
#[derive(Clone, Debug, Serialize)]
struct AttackRow {
    attack: String,
    magnitude: Option<f64>,
    rate_hz: f64,
    early_onset: bool,
    drives: usize,
    warning_deadline_s: f64,
    critical_deadline_s: f64,
    warning_in_time: f64,
    critical_in_time: f64,
    critical_median_delay_s: Option<f64>,
    critical_coverage: Option<f64>,
}

/// One attacked test drive at both levels: a row of `drives.csv`, which says why a drive missed
/// a deadline (the vehicle standing, or anchors placed only seconds before the attack).
#[derive(Clone, Debug, Serialize)]
struct DriveOutcome {
    vehicle_id: String,
    attack: String,
    magnitude: Option<f64>,
    rate_hz: f64,
    early_onset: bool,
    onset_s: f64,
    /// This drive's deadlines (a fix frozen while standing counts from when the vehicle moves off).
    warning_deadline_s: f64,
    critical_deadline_s: f64,
    /// Mean onboard speed from the onset to the warning deadline (m/s).
    mean_speed_mps: f64,
    /// Share of the rows from the onset to the critical deadline where the vehicle stands
    /// (onboard speed below [`STANDING_MPS`]).
    standing_share: f64,
    /// Seconds the track the anchors stood on had lasted at the attack's first row (§4.2).
    track_age_at_onset_s: Option<f64>,
    warning_delay_s: Option<f64>,
    warning_in_time: bool,
    critical_delay_s: Option<f64>,
    critical_in_time: bool,
    critical_coverage: Option<f64>,
}

/// Below this onboard speed (m/s) a vehicle stands, for [`DriveOutcome::standing_share`].
const STANDING_MPS: f64 = 0.5;

#[derive(Debug, Serialize)]
struct Report {
    protocol: &'static str,
    model: String,
    seed: u64,
    critical_budget_per_hour: f64,
    warning_budget_per_hour: f64,
    validation_hours_per_rate: u64,
    /// Whether the critical test was chosen with the guard band.
    guard_band: bool,
    /// Whether the critical test was chosen without re-basing and the model measured with it.
    serve_rebased: bool,
    test_hours_per_rate: u64,
    /// Error sources of the fleet distribution left out of the clean drives.
    without: Vec<String>,
    critical: CriticalTest,
    /// The search's outcome on validation (`None` with `--keep-critical`).
    selection: Option<CriticalSelection>,
    clean: Vec<CleanCount>,
    attacks: Vec<AttackRow>,
    /// Every attacked test drive's outcome (written to `drives.csv`, not to the report).
    #[serde(skip)]
    drives: Vec<DriveOutcome>,
    wall_time_s: f64,
}

pub fn run(args: Args) -> Result<()> {
    let started = Instant::now();
    let threads = args.threads.unwrap_or_else(default_threads);
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    let mut artifact = ModelArtifact::clone(&*load_artifact(&args.model)?);
    let (Some(lifecycle), theta) = (artifact.lifecycle, artifact.operating_point.theta) else {
        anyhow::bail!(
            "{}: severities need the alarm lifecycle in seconds (a `v3` model)",
            args.model.display()
        );
    };
    let selection = if args.keep_critical {
        None
    } else {
        eprintln!("choosing the critical test on validation drives");
        if args.serve_rebased {
            artifact.set_anchor_rebasing(false);
        }
        let (rows, offset) = validation_rows(&artifact, &args, threads)?;
        let budget = if args.guard_band {
            OperatingPointRule::WithinFalseAlarmBudgetWithMargin {
                per_hour: CRITICAL_BUDGET_PER_HOUR,
            }
        } else {
            OperatingPointRule::WithinFalseAlarmBudget {
                per_hour: CRITICAL_BUDGET_PER_HOUR,
            }
        };
        let selection =
            choose_critical_within(&rows, &offset, theta, &lifecycle, budget, EventRules::Spec)
                .context("choosing the critical test")?;
        artifact.critical = Some(selection.test);
        if args.serve_rebased {
            artifact.set_anchor_rebasing(true);
        }
        Some(selection)
    };
    let Some(critical) = artifact.critical else {
        anyhow::bail!(
            "{}: the model has no critical test to keep",
            args.model.display()
        );
    };
    if let Some(path) = &args.write_model {
        let mut written = artifact.clone();
        // The one field that differs between two runs of the same training: a model written here
        // (the bundled default) is reproducible bit for bit.
        written.provenance.train_wall_time_s = 0.0;
        written.provenance.notes = format!(
            "{}; critical test chosen by `spoofwatch-lab experiment fleet-alarms --seed {} \
             --validation-hours {} --repeats {}`",
            written.provenance.notes, args.seed, args.validation_hours, args.repeats
        );
        let file =
            std::fs::File::create(path).with_context(|| format!("creating {}", path.display()))?;
        written.write(std::io::BufWriter::new(file))?;
        eprintln!("wrote {}", path.display());
    }
    let artifact = Arc::new(artifact);
    eprintln!("clean fleets: {} h per rate", args.test_hours);
    let (clean, onsets) = clean_fleets(&artifact, &args, threads)?;
    eprintln!("attacked test drives");
    let (attacks, drives) = attack_rows(&artifact, &args, threads)?;
    let report = Report {
        protocol: "fleet-alarms: the critical test chosen on attack-free validation hours of the \
                   fleet distribution and the offsets suite's attacked validation drives; clean \
                   fleets and attacked test drives from seeds apart",
        model: args.model.display().to_string(),
        seed: args.seed,
        critical_budget_per_hour: CRITICAL_BUDGET_PER_HOUR,
        warning_budget_per_hour: WARNING_BUDGET_PER_HOUR,
        validation_hours_per_rate: args.validation_hours,
        guard_band: args.guard_band,
        serve_rebased: args.serve_rebased,
        test_hours_per_rate: args.test_hours,
        without: args.without.clone(),
        critical,
        selection,
        clean,
        attacks,
        drives,
        wall_time_s: started.elapsed().as_secs_f64(),
    };
    write_outputs(&args.out, &report, &onsets)
}

/// The fleet distribution without the error sources named in `without`.
fn fleet_distribution(without: &[String]) -> DriveDistribution {
    let mut distribution = DriveDistribution::fleet();
    let off = Range { min: 0.0, max: 0.0 };
    for source in without {
        match source.as_str() {
            "wander" => distribution.heading_bias_wander_std_deg = off,
            "static-hold" => distribution.static_hold_share = 0.0,
            _ => distribution.reacquisition_offset_std_m = off,
        }
    }
    distribution
}

/// A drive of `distribution` of an hour at `rate_hz`, with its road kind.
fn fleet_drive(
    distribution: &DriveDistribution,
    seed: u64,
    rate_hz: f64,
    vehicle_id: &str,
) -> Result<(spoofwatch_core::sample::Track, RoadKind)> {
    let mut spec = distribution.draw(seed);
    spec.duration_s = CLEAN_DRIVE_S;
    spec.rate_hz = rate_hz;
    let road = spec.road_kind();
    let track =
        simulate_drive(&spec, vehicle_id).with_context(|| format!("simulating {vehicle_id}"))?;
    Ok((track, road))
}

/// Validation rows: `validation_hours` clean fleet drives per rate and the offsets suite's attacked
/// drives, scored at the warning level, with their offset evidence.
fn validation_rows(
    artifact: &ModelArtifact,
    args: &Args,
    threads: usize,
) -> Result<(
    Vec<ScoredRow>,
    Vec<spoofwatch_core::lifecycle::OffsetSignal>,
)> {
    let seed = args.seed ^ VALIDATION_SEED;
    let warning_only = Arc::new(ModelArtifact {
        critical: None,
        ..artifact.clone()
    });
    let distribution = fleet_distribution(&args.without);
    let attacked = test_set((seed, args.distribution), args.repeats, 0, threads)?;
    let mut tracks: Vec<_> = attacked
        .attacked
        .into_iter()
        .map(|d| d.injected.track)
        .collect();
    for (rate_index, &rate_hz) in RATES_HZ.iter().enumerate() {
        let indices: Vec<u64> = (0..args.validation_hours).collect();
        let clean = map_parallel(&indices, threads, |&i| {
            let index = rate_index as u64 * 1_000_000 + i;
            let id = format!("validation-fleet-{rate_hz}hz-{i}");
            fleet_drive(
                &distribution,
                drive_seed(seed, Population::FleetValidation, index),
                rate_hz,
                &id,
            )
            .map(|(track, _)| track)
        });
        for track in clean {
            tracks.push(track?);
        }
    }
    let parts = map_parallel(&tracks, threads, |track| {
        score_tracks(&warning_only, std::slice::from_ref(track))
    });
    let mut scored = Scored::default();
    for (number, mut part) in parts.into_iter().enumerate() {
        // Each track was scored alone (its keys start at 0): give it the keys of its place.
        for row in &mut part.rows {
            row.trajectory = trajectory_key(number, row.trajectory as u32);
        }
        scored.append(part);
    }
    Ok((scored.rows, scored.offset))
}

/// Onsets of both levels on `test_hours` clean fleet drives per rate, counted per rate and road
/// kind, and every onset.
fn clean_fleets(
    artifact: &Arc<ModelArtifact>,
    args: &Args,
    threads: usize,
) -> Result<(Vec<CleanCount>, Vec<CleanOnset>)> {
    let distribution = fleet_distribution(&args.without);
    let mut counts = Vec::new();
    let mut onsets = Vec::new();
    for (rate_index, &rate_hz) in RATES_HZ.iter().enumerate() {
        let indices: Vec<u64> = (0..args.test_hours).collect();
        let drives = map_parallel(
            &indices,
            threads,
            |&i| -> Result<(RoadKind, f64, Vec<CleanOnset>)> {
                let index = rate_index as u64 * 1_000_000 + i;
                let id = format!("fleet-{rate_hz}hz-{i}");
                let (track, road) = fleet_drive(
                    &distribution,
                    drive_seed(args.seed, Population::FleetClean, index),
                    rate_hz,
                    &id,
                )?;
                let decisions = run_records(artifact, &track.records);
                let times: Vec<f64> = track.records.iter().map(|r| r.sample.timestamp_s).collect();
                let hours = drive_hours(&times);
                Ok((
                    road,
                    hours,
                    drive_onsets(&id, rate_hz, road, &times, &decisions),
                ))
            },
        );
        for road in [RoadKind::Urban, RoadKind::Highway] {
            for severity in Severity::ALL {
                counts.push(CleanCount {
                    rate_hz,
                    road: road.name(),
                    severity: severity.name(),
                    ..CleanCount::default()
                });
            }
        }
        for drive in drives {
            let (road, hours, drive_onsets) = drive?;
            for count in counts
                .iter_mut()
                .filter(|c| c.rate_hz == rate_hz && c.road == road.name())
            {
                count.drives += 1;
                count.hours += hours;
                for onset in drive_onsets.iter().filter(|o| o.severity == count.severity) {
                    count.onsets += 1;
                    count.after_start_or_outage +=
                        u64::from(onset.since_resumed_s <= AFTER_START_S);
                }
            }
            onsets.extend(drive_onsets);
        }
    }
    for count in &mut counts {
        count.per_hour = count.onsets as f64 / count.hours.max(f64::MIN_POSITIVE);
    }
    Ok((counts, onsets))
}

/// Hours of driving: the sum of the steps between samples, outages left out.
fn drive_hours(times: &[f64]) -> f64 {
    times
        .windows(2)
        .map(|w| w[1] - w[0])
        .filter(|&step| step > 0.0 && step <= OUTAGE_S)
        .sum::<f64>()
        / 3600.0
}

/// Every warning onset and every escalation to critical of one clean drive.
fn drive_onsets(
    vehicle_id: &str,
    rate_hz: f64,
    road: RoadKind,
    times: &[f64],
    decisions: &[Decision],
) -> Vec<CleanOnset> {
    let mut onsets = Vec::new();
    let mut resumed_s = f64::NEG_INFINITY;
    for (i, (&time_s, decision)) in times.iter().zip(decisions).enumerate() {
        if i == 0 || time_s - times[i - 1] > OUTAGE_S {
            resumed_s = time_s;
        }
        let mut push = |severity: Severity| {
            onsets.push(CleanOnset {
                vehicle_id: vehicle_id.to_string(),
                rate_hz,
                road: road.name(),
                severity: severity.name(),
                time_s,
                since_resumed_s: time_s - resumed_s,
                why: decision.explanation.dominant.name(),
            });
        };
        if decision.alarm_onset {
            push(Severity::Warning);
        }
        if decision.escalation {
            push(Severity::Critical);
        }
    }
    onsets
}

/// The critical deadline of a test attack: a drift's is [`DRIFT_CRITICAL_FACTOR`] times its
/// warning deadline; decisive attacks (jumps, hops, frozen fixes) keep theirs.
fn critical_deadline_s(kind: &AttackKind, warning_deadline_s: f64) -> f64 {
    match kind {
        AttackKind::RampDrift { .. }
        | AttackKind::AcceleratingDrift { .. }
        | AttackKind::TogglingDrift { .. } => warning_deadline_s * DRIFT_CRITICAL_FACTOR,
        _ => warning_deadline_s,
    }
}

/// The offsets suite's attacked test drives at both levels: each kind, rate and onset's shares, and
/// every drive's outcome.
fn attack_rows(
    artifact: &Arc<ModelArtifact>,
    args: &Args,
    threads: usize,
) -> Result<(Vec<AttackRow>, Vec<DriveOutcome>)> {
    let set = test_set((args.seed, args.distribution), args.repeats, 0, threads)?;
    let outcomes = map_parallel(&set.attacked, threads, |drive| {
        drive_outcome(artifact, drive, &set.kinds[drive.kind_index])
    });
    let mut rows = Vec::new();
    for (rate_index, &rate_hz) in RATES_HZ.iter().enumerate() {
        for (kind_index, kind) in set.kinds.iter().enumerate() {
            for early in [true, false] {
                rows.push(attack_row(
                    kind,
                    rate_hz,
                    early,
                    set.attacked
                        .iter()
                        .zip(&outcomes)
                        .filter(|(d, _)| {
                            (d.rate_index, d.kind_index, d.early) == (rate_index, kind_index, early)
                        })
                        .map(|(_, outcome)| outcome),
                ));
            }
        }
    }
    Ok((rows, outcomes))
}

/// One attacked drive run through the detector and scored at both levels.
fn drive_outcome(
    artifact: &Arc<ModelArtifact>,
    drive: &TestDrive,
    kind: &TestKind,
) -> DriveOutcome {
    let records = &drive.injected.track.records;
    let decisions = run_records(artifact, records);
    let warning = scored_levels(records, &decisions, |d| d.alarm);
    let critical = scored_levels(records, &decisions, |d| {
        d.severity == Some(Severity::Critical)
    });
    let (warning_delay_s, _) = delay_and_coverage(&drive.injected, &warning);
    let (critical_delay_s, critical_coverage) = delay_and_coverage(&drive.injected, &critical);
    // A drive's own deadline counts from when it moves off (a fix frozen while standing).
    let extra_s = drive.deadline_s - kind.within_s;
    let critical_deadline_s = critical_deadline_s(&kind.kind, kind.within_s) + extra_s;
    let first = *drive.injected.attack_rows().start();
    let onset_time = records[first].sample.timestamp_s;
    let speeds: Vec<f64> = records[first..]
        .iter()
        .take_while(|r| r.sample.timestamp_s - onset_time <= critical_deadline_s)
        .map(|r| r.sample.speed_mps)
        .collect();
    let standing = speeds.iter().filter(|s| s.abs() < STANDING_MPS).count();
    DriveOutcome {
        vehicle_id: drive.injected.track.vehicle_id.clone(),
        attack: kind.label(),
        magnitude: kind.kind.magnitude(),
        rate_hz: RATES_HZ[drive.rate_index],
        early_onset: drive.early,
        onset_s: drive.onset_s,
        warning_deadline_s: drive.deadline_s,
        critical_deadline_s,
        mean_speed_mps: drive.mean_speed_mps,
        standing_share: standing as f64 / speeds.len().max(1) as f64,
        track_age_at_onset_s: decisions[first].evidence.offset.map(|o| o.track_age_s),
        warning_delay_s,
        warning_in_time: warning_delay_s.is_some_and(|d| d <= drive.deadline_s),
        critical_delay_s,
        critical_in_time: critical_delay_s.is_some_and(|d| d <= critical_deadline_s),
        critical_coverage,
    }
}

fn attack_row<'a>(
    kind: &TestKind,
    rate_hz: f64,
    early: bool,
    drives: impl Iterator<Item = &'a DriveOutcome>,
) -> AttackRow {
    let (mut count, mut warning_in_time, mut critical_in_time) = (0usize, 0usize, 0usize);
    let (mut delays, mut coverages) = (Vec::new(), Vec::new());
    for drive in drives {
        count += 1;
        warning_in_time += usize::from(drive.warning_in_time);
        critical_in_time += usize::from(drive.critical_in_time);
        delays.extend(drive.critical_delay_s);
        coverages.extend(drive.critical_coverage);
    }
    let share = |n: usize| n as f64 / count.max(1) as f64;
    AttackRow {
        attack: kind.label(),
        magnitude: kind.kind.magnitude(),
        rate_hz,
        early_onset: early,
        drives: count,
        warning_deadline_s: kind.within_s,
        critical_deadline_s: critical_deadline_s(&kind.kind, kind.within_s),
        warning_in_time: share(warning_in_time),
        critical_in_time: share(critical_in_time),
        critical_median_delay_s: median(delays),
        critical_coverage: (!coverages.is_empty())
            .then(|| coverages.iter().sum::<f64>() / coverages.len() as f64),
    }
}

/// One drive's decisions as a [`Scored`] whose alarms are the rows where `alarmed` holds.
fn scored_levels(
    records: &[spoofwatch_core::sample::Record],
    decisions: &[Decision],
    alarmed: impl Fn(&Decision) -> bool,
) -> Scored {
    Scored {
        rows: records
            .iter()
            .zip(decisions)
            .map(|(record, d)| ScoredRow {
                trajectory: u64::from(d.evidence.trajectory),
                time_s: record.sample.timestamp_s,
                valid: d.evidence.valid,
                label: record.label.unwrap_or(false),
                score: d.probability,
            })
            .collect(),
        alarms: decisions.iter().map(alarmed).collect(),
        offset: decisions
            .iter()
            .map(|d| offset_signal(&d.evidence))
            .collect(),
        speed_mps: records.iter().map(|r| r.sample.speed_mps).collect(),
    }
}

fn write_outputs(out: &std::path::Path, report: &Report, onsets: &[CleanOnset]) -> Result<()> {
    super::common::write_report(out, report, &render_markdown(report))?;
    let path = out.join("drives.csv");
    let mut writer =
        csv::Writer::from_path(&path).with_context(|| format!("creating {}", path.display()))?;
    for drive in &report.drives {
        writer.serialize(drive)?;
    }
    writer.flush().context("writing drives.csv")?;
    let mut csv = String::from("vehicle_id,rate_hz,road,severity,time_s,since_resumed_s,why\n");
    for o in onsets {
        let _ = writeln!(
            csv,
            "{},{},{},{},{:.1},{:.1},{}",
            o.vehicle_id, o.rate_hz, o.road, o.severity, o.time_s, o.since_resumed_s, o.why
        );
    }
    let path = out.join("onsets.csv");
    std::fs::write(&path, csv).with_context(|| format!("writing {}", path.display()))
}

fn render_markdown(report: &Report) -> String {
    let mut md = String::new();
    let c = &report.critical;
    let _ = writeln!(
        md,
        "# fleet-alarms\n\nModel `{}`, seed {}, clean drives of the fleet distribution{}. Critical \
         test: k = {} (p̂ {:.4}), h = {} logit·s, NIS gate {} held {} s{}.\n",
        report.model,
        report.seed,
        if report.without.is_empty() {
            String::new()
        } else {
            format!(" without {}", report.without.join(", "))
        },
        c.reference_logit,
        1.0 / (1.0 + (-c.reference_logit).exp()),
        c.threshold,
        c.gate,
        c.decisive_s,
        spoofwatch_client::cli::evaluate::critical_paths(
            c.frozen_fix_s,
            c.held_jump.map(|j| (j.gate, j.hold_s)),
            c.held_step.map(|s| (s.gate, s.hold_s)),
            c.held_offset.map(|h| (h.gate, h.hold_s))
        )
    );
    if let Some(selection) = &report.selection {
        let _ = writeln!(
            md,
            "Validation ({} attack-free hours per rate{}): critical onsets per rate:",
            report.validation_hours_per_rate,
            if report.guard_band {
                ", with the guard band"
            } else {
                ""
            }
        );
        for (rate, onsets, hours) in &selection.false_onsets_by_rate {
            let _ = writeln!(md, "- {rate} Hz: {onsets} in {hours:.1} h");
        }
        let _ = writeln!(
            md,
            "- attack events escalated: {} of {}\n",
            selection.metrics.detected_events, selection.metrics.events
        );
    }
    let _ = writeln!(
        md,
        "## Clean fleets ({} attack-free hours per rate)\n\n| rate | road | level | drives | hours | onsets | per hour | within {AFTER_START_S} s of a start or outage |\n|---|---|---|---|---|---|---|---|",
        report.test_hours_per_rate
    );
    for row in &report.clean {
        let _ = writeln!(
            md,
            "| {} Hz | {} | {} | {} | {:.1} | {} | {:.4} | {} |",
            row.rate_hz,
            row.road,
            row.severity,
            row.drives,
            row.hours,
            row.onsets,
            row.per_hour,
            row.after_start_or_outage
        );
    }
    let _ = writeln!(
        md,
        "\n## Detection (share within the deadline, early onset / late onset)\n\n| attack | warning deadline | critical deadline | rate | warning | critical | critical coverage (late) |\n|---|---|---|---|---|---|---|"
    );
    for pair in report.attacks.chunks(2) {
        let [early, late] = pair else { continue };
        let _ = writeln!(
            md,
            "| {}{} | {} s | {} s | {} Hz | {:.2} / {:.2} | {:.2} / {:.2} | {} |",
            late.attack,
            late.magnitude.map_or(String::new(), |m| format!(" {m}")),
            late.warning_deadline_s,
            late.critical_deadline_s,
            late.rate_hz,
            early.warning_in_time,
            late.warning_in_time,
            early.critical_in_time,
            late.critical_in_time,
            late.critical_coverage
                .map_or("–".to_string(), |c| format!("{c:.2}"))
        );
    }
    let _ = writeln!(md, "\nWall time {:.0} s.", report.wall_time_s);
    md
}
