//! The "offsets" experiment (`docs/detector.md` §9): every attack kind a spoofer takes a vehicle
//! over with (jumps, hops, frozen fixes, ramps, accelerating and toggling drifts), each at 1, 5 and
//! 10 Hz and starting both 15 s after a session starts and minutes into it, on realistic simulated
//! drives (onboard errors, multipath, outages, 1–30 m/s). It reports, per detector, attack and
//! rate, the share detected within the attack's deadline and the alarm's coverage of the attack,
//! and the false alarms per attack-free hour measured separately at each rate (with those that
//! follow a session start or an outage's end counted apart).
//!
//! Owns the offset suite's drives, training mix and report. Must not fit or score detectors itself
//! (core and the baselines do).

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

use anyhow::{Context, Result};
use serde::Serialize;
use spoofwatch_client::cli::evaluate::load_artifact;
use spoofwatch_client::cli::train::train_with_progress;
use spoofwatch_core::cusum::fit_cusum_comparator;
use spoofwatch_core::evaluation::{Scored, score_tracks};
use spoofwatch_core::evidence::FeatureSchema;
use spoofwatch_core::gate::ResidualGate;
use spoofwatch_core::glr::fit_glr_comparator;
use spoofwatch_core::metrics::normal_hours;
use spoofwatch_core::model::artifact::ModelArtifact;
use spoofwatch_core::model::{Ablation, FeatureGroups};
use spoofwatch_core::rng::Rng;
use spoofwatch_core::sample::Track;
use spoofwatch_core::scenario::{
    AttackKind, AttackSpec, DriveDistribution, InjectedTrack, Outages, inject, simulate_drive,
    training_attack,
};
use spoofwatch_core::train::TrainConfig;
use spoofwatch_core::train::detector::TrainingData;
use spoofwatch_core::train::spec::{AnchorRebase, KappaRho, TrainingSpec};

use super::common::{AnchorRebaseArg, CommonArgs, prepare, seed_list, write_report};
use super::parallel::{default_threads, map_parallel};
use super::subtle::{
    BUDGET, FALSE_ALARM_BUDGET_PER_HOUR, delay_and_coverage, operating_point_json, within_budget,
};
use super::training_attacks::recorded_and_simulated;

#[derive(Debug, clap::Args)]
pub struct Args {
    #[command(flatten)]
    common: CommonArgs,
    /// Randomised simulated drives for training, and as many for validation (half attacked).
    #[arg(long, default_value_t = 96)]
    drives: u64,
    /// Attack-free one-hour test drives per sample rate (24 ≈ 24 attack-free hours per rate).
    #[arg(long, default_value_t = 24)]
    clean_drives: u64,
    /// Attack-free one-hour validation drives per sample rate (6 = 6 attack-free hours per rate), so
    /// that the false-alarm budget binds at each tested rate when the operating point is chosen,
    /// not only pooled over the randomised drives' many rates.
    #[arg(long, default_value_t = 6)]
    validation_clean_drives: u64,
    /// Test drives per attack kind, onset and sample rate.
    #[arg(long, default_value_t = 10)]
    repeats: u64,
    /// The distribution every drive of the suite (training, validation, test) is drawn from.
    #[arg(long, value_enum, default_value = "realistic")]
    distribution: Distribution,
    /// Trust the onboard calibration by the clock (the 240 s warm-up) instead of by its own
    /// uncertainty (a retrained ablation).
    #[arg(long)]
    timer_trust: bool,
    /// Re-base the offset anchors when the calibration in use changes: in service only, the
    /// operating point chosen without it (`margin`, the bundled default's), in the operating
    /// point's search too (`serve`), or in training too (`train-and-serve`).
    #[arg(long, value_enum, default_value = "off")]
    anchor_rebase: AnchorRebaseArg,
    /// Train the HO-LLN models with this many seeds (the training seed, + 1, …).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u64).range(1..=20))]
    seeds: u64,
    /// Seed of the models' weights (default: `--seed`, which also draws the drives).
    #[arg(long)]
    training_seed: Option<u64>,
    /// Feature schema of the main model (`v2` is the ablation without offset evidence).
    #[arg(long, default_value = "v3", value_parser = schema_name)]
    schema: FeatureSchema,
    /// Evidence groups of the main model (a retrained ablation).
    #[arg(long, default_value = FeatureGroups::All.name(), value_parser = spoofwatch_client::cli::training_flags::feature_groups())]
    features: FeatureGroups,
    /// Keep the rows after an attack's end in the loss (ablation of the exit masking).
    #[arg(long)]
    no_exit_mask: bool,
    /// Attacked training and validation drives go on for 30 s to this many seconds (uniform) after
    /// the attack, so that the model sees the evidence an attack charged decay.
    #[arg(long, default_value_t = MIN_AFTER_ATTACK_S, value_parser = after_attack_s)]
    after_attack_s: f64,
    /// Normalise every channel by the training population's noise alone (ablation of the
    /// per-vehicle levels).
    #[arg(long)]
    no_vehicle_levels: bool,
    /// Choose the persistence N_p in rows instead of the alarm lifecycle in seconds (ablation).
    #[arg(long)]
    rows_lifecycle: bool,
    /// Also train and score the paper-schema HO-LLN.
    #[arg(long)]
    paper: bool,
    /// Train and validate on the simulated drives only (without Dataset-2).
    #[arg(long)]
    simulated_only: bool,
    /// Also score these model artifacts, each at an operating point chosen on this validation data
    /// within the same budget.
    #[arg(long)]
    also: Vec<PathBuf>,
}

fn after_attack_s(text: &str) -> Result<f64, String> {
    let seconds: f64 = text.parse().map_err(|error| format!("{text:?}: {error}"))?;
    if (MIN_AFTER_ATTACK_S..=3_600.0).contains(&seconds) {
        Ok(seconds)
    } else {
        Err(format!(
            "{seconds} s is outside {MIN_AFTER_ATTACK_S}–3600 s"
        ))
    }
}

fn schema_name(name: &str) -> Result<FeatureSchema, String> {
    FeatureSchema::from_name(name).ok_or_else(|| format!("unknown feature schema {name:?}"))
}

/// Sample rates of the test drives (Hz).
pub(super) const RATES_HZ: [f64; 3] = [1.0, 5.0, 10.0];
/// Length of a clean validation or test drive (s): an hour, because a vehicle's levels take the first
/// half hour to settle, and a budget met on short drives need not hold on a vehicle in service.
const CLEAN_DRIVE_S: f64 = 3_600.0;
/// Length of a clean training drive (s).
const TRAINING_CLEAN_DRIVE_S: f64 = 3_600.0;
/// Length of a test attack (s).
const TEST_ATTACK_S: f64 = 120.0;
/// How long a test drive goes on after its attack (s).
const TEST_AFTER_ATTACK_S: f64 = 30.0;
/// How long a training drive goes on after its attack, at least (s).
const MIN_AFTER_ATTACK_S: f64 = 30.0;
/// The early onset: this long after the session starts (s).
const EARLY_ONSET_S: f64 = 15.0;
/// Late onsets are drawn from this range (s): the onboard calibration is warm.
const LATE_ONSET_S: (f64, f64) = (300.0, 600.0);
/// A false alarm this soon after a session starts or an outage ends is counted apart (s).
pub(super) const AFTER_START_S: f64 = 30.0;
/// Dataset-2's validation parts and its injected training pieces are scored as continuations of the
/// rover's stream, after this many seconds of its earlier rows (s): the per-vehicle levels and the
/// dead-reckoning misfit need minutes to learn a vehicle, as they have on a vehicle in service.
const RECORDED_WARMUP_S: f64 = 900.0;
/// Rows further apart than this (s) are an outage.
pub(super) const OUTAGE_S: f64 = 5.0;

/// A test attack and its deadline: detected counts only within it.
pub(super) struct TestKind {
    pub(super) kind: AttackKind,
    pub(super) within_s: f64,
    motion: Motion,
}

/// What the vehicle does when a test attack starts. A frozen fix is only visible once the vehicle
/// moves away from it: frozen while standing is its own test, timed from when the vehicle moves off.
#[derive(Clone, Copy, PartialEq)]
enum Motion {
    /// Wherever the drive happens to be.
    Any,
    /// Moving (onboard speed ≥ [`MOVING_MPS`]) on every row from the onset to the deadline.
    Moving,
    /// Standing (onboard speed < [`STANDING_MPS`]) at the onset, and moving off within
    /// [`MOVE_OFF_WITHIN_S`]; the deadline counts from the first row at [`MOVING_MPS`] or more.
    Standing,
}

/// A vehicle at this onboard speed or more is moving (m/s).
const MOVING_MPS: f64 = 2.0;
/// A vehicle below this onboard speed is standing (m/s).
const STANDING_MPS: f64 = 0.3;
/// A standing test vehicle moves off within this long after the onset (s).
const MOVE_OFF_WITHIN_S: f64 = 60.0;
/// Drives drawn at most per test drive to find one with the motion its test asks for.
const MOTION_ATTEMPTS: u64 = 400;

impl TestKind {
    fn any(kind: AttackKind, within_s: f64) -> Self {
        Self {
            kind,
            within_s,
            motion: Motion::Any,
        }
    }

    pub(super) fn label(&self) -> String {
        let family = self.kind.family();
        match self.motion {
            Motion::Any => family.to_string(),
            Motion::Moving => format!("{family} while moving"),
            Motion::Standing => format!("{family} while standing"),
        }
    }

    /// Seconds after the onset by which `track` (attacked from `onset_s`) must be alarmed, or `None`
    /// when its motion is not the one this test asks for.
    fn deadline_s(&self, track: &Track, onset_s: f64) -> Option<f64> {
        let start = track.records.first()?.sample.timestamp_s;
        let speeds_from = |from_s: f64| {
            track
                .records
                .iter()
                .map(move |r| (r.sample.timestamp_s - start - onset_s, r.sample.speed_mps))
                .skip_while(move |&(t, _)| t < from_s)
        };
        match self.motion {
            Motion::Any => Some(self.within_s),
            Motion::Moving => speeds_from(0.0)
                .take_while(|&(t, _)| t <= self.within_s)
                .all(|(_, v)| v >= MOVING_MPS)
                .then_some(self.within_s),
            Motion::Standing => {
                let mut speeds = speeds_from(0.0);
                let (_, at_onset) = speeds.next()?;
                if at_onset >= STANDING_MPS {
                    return None;
                }
                let (move_off_s, _) = speeds
                    .take_while(|&(t, _)| t <= MOVE_OFF_WITHIN_S)
                    .find(|&(_, v)| v >= MOVING_MPS)?;
                Some(move_off_s + self.within_s)
            }
        }
    }
}

/// The test grid with the deadlines the detector is held to.
fn test_kinds() -> Vec<TestKind> {
    let mut kinds = Vec::new();
    for offset_m in [5.0, 20.0, 50.0, 500.0, 50_000.0] {
        kinds.push(TestKind::any(AttackKind::Jump { offset_m }, 10.0));
    }
    for motion in [Motion::Moving, Motion::Standing] {
        kinds.push(TestKind {
            kind: AttackKind::FrozenPosition,
            within_s: 10.0,
            motion,
        });
    }
    for (offset_m, hold_s) in [(200.0, 5.0), (50_000.0, 10.0)] {
        kinds.push(TestKind::any(
            AttackKind::Hopping { offset_m, hold_s },
            15.0,
        ));
    }
    for (velocity_mps, within_s) in [(0.5, 60.0), (1.0, 30.0), (2.0, 30.0)] {
        kinds.push(TestKind::any(
            AttackKind::RampDrift { velocity_mps },
            within_s,
        ));
    }
    kinds.push(TestKind::any(
        AttackKind::AcceleratingDrift {
            acceleration_mps2: 0.05,
        },
        60.0,
    ));
    kinds.push(TestKind::any(
        AttackKind::TogglingDrift {
            velocity_mps: 1.0,
            period_s: 10.0,
        },
        30.0,
    ));
    kinds
}

/// Seeds of the drive populations (kept apart so no drive appears in two of them).
#[derive(Clone, Copy)]
pub(super) enum Population {
    Train = 11,
    Validation = 12,
    CleanTest = 13,
    AttackedTest = 14,
    CleanValidation = 15,
    /// Attack-free fleet drives of the fleet-alarms study, and its validation drives.
    FleetClean = 16,
    FleetValidation = 17,
}

pub(super) fn drive_seed(seed: u64, population: Population, index: u64) -> u64 {
    seed.wrapping_mul(1_000_003)
        .wrapping_add((population as u64) << 40)
        .wrapping_add(index)
}

/// The distribution the suite's drives are drawn from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub(super) enum Distribution {
    /// `DriveDistribution::realistic()`: GNSS bias, multipath, onboard errors, outages.
    Realistic,
    /// `DriveDistribution::fleet()`: the realistic drives plus what a fleet in service adds (a
    /// heading bias that wanders, receivers that hold their fix at standstill, reacquisition
    /// with an offset first fix).
    Fleet,
}

impl Distribution {
    /// Its constructor's name (`DriveDistribution::realistic()`, `::fleet()`).
    fn name(self) -> &'static str {
        match self {
            Self::Realistic => "realistic",
            Self::Fleet => "fleet",
        }
    }

    fn drives(self) -> DriveDistribution {
        match self {
            Self::Realistic => DriveDistribution::realistic(),
            Self::Fleet => DriveDistribution::fleet(),
        }
    }
}

/// A drive of `distribution` lasting `duration_s` (its rate forced to `rate_hz` when given);
/// without outages when it will carry an attack (an attack must not span a trajectory break).
fn drive(
    (seed, distribution): (u64, Distribution),
    duration_s: f64,
    rate_hz: Option<f64>,
    outages: bool,
    vehicle_id: &str,
) -> Result<Track> {
    let mut spec = distribution.drives().draw(seed);
    spec.duration_s = duration_s;
    if let Some(rate_hz) = rate_hz {
        spec.rate_hz = rate_hz;
    }
    if !outages {
        spec.outages = Outages::default();
    }
    simulate_drive(&spec, vehicle_id).with_context(|| format!("simulating {vehicle_id}"))
}

/// `kind` injected `onset_s` into a drive at `rate_hz` (random direction), the drive going on for
/// `after_s` after the attack.
fn attacked(
    (seed, distribution): (u64, Distribution),
    kind: AttackKind,
    (onset_s, duration_s, after_s): (f64, f64, f64),
    rate_hz: Option<f64>,
    vehicle_id: &str,
) -> Result<InjectedTrack> {
    let mut rng = Rng::seed_from_u64(seed ^ 0x000F_F5E7);
    let attack = AttackSpec {
        kind,
        direction_deg: rng.uniform_range(0.0, 360.0).floor(),
        onset_s,
        duration_s,
        seed: Some(seed),
    };
    let base = drive(
        (seed, distribution),
        onset_s + duration_s + after_s,
        rate_hz,
        false,
        vehicle_id,
    )?;
    inject(&base, &attack)
        .with_context(|| format!("injecting {} into {vehicle_id}", kind.describe()))
}

/// `count` drives of the randomised training mix: every other one attacked (a random kind and
/// magnitude, onset early — 10–60 s, drifts of 1 m/s or more — in a third of them, else 240–600 s;
/// 60–180 s long, the drive going on for 30 s to `max_after_s` after it), the others clean with
/// outages, an hour; every rate of the realistic distribution.
fn training_mix(
    (seed, distribution): (u64, Distribution),
    population: Population,
    (count, max_after_s): (u64, f64),
    threads: usize,
) -> Result<Vec<Track>> {
    let indices: Vec<u64> = (0..count).collect();
    map_parallel(&indices, threads, |&i| {
        let drive_seed = drive_seed(seed, population, i);
        let id = format!("mix{}-{i}", population as u8);
        if i % 2 == 1 {
            return drive(
                (drive_seed, distribution),
                TRAINING_CLEAN_DRIVE_S,
                None,
                true,
                &id,
            );
        }
        let mut rng = Rng::seed_from_u64(drive_seed ^ 0x7EA1_A77A);
        let early = rng.below(3) == 0;
        let onset_s = if early {
            rng.uniform_range(10.0, 60.0)
        } else {
            rng.uniform_range(240.0, 600.0)
        }
        .round();
        let kind = training_attack(&mut rng, early);
        let duration_s = rng.uniform_range(60.0, 180.0).round();
        // Drawn last, so that the default (30 s) leaves every other draw as it was.
        let after_s = rng.uniform_range(MIN_AFTER_ATTACK_S, max_after_s).round();
        let timing = (onset_s, duration_s, after_s);
        attacked((drive_seed, distribution), kind, timing, None, &id).map(|a| a.track)
    })
    .into_iter()
    .collect()
}

/// One attacked test drive and what it is.
pub(super) struct TestDrive {
    pub(super) injected: InjectedTrack,
    pub(super) kind_index: usize,
    pub(super) rate_index: usize,
    pub(super) early: bool,
    pub(super) onset_s: f64,
    /// Detected counts when the alarm opens within this many seconds of the onset.
    pub(super) deadline_s: f64,
    pub(super) mean_speed_mps: f64,
}

/// Mean onboard speed of `injected` from its attack's first row to `deadline_s` after it (m/s).
fn mean_speed_to_deadline(injected: &InjectedTrack, deadline_s: f64) -> f64 {
    let records = &injected.track.records[*injected.attack_rows().start()..];
    let onset_time = records[0].sample.timestamp_s;
    let (sum, rows) = records
        .iter()
        .take_while(|r| r.sample.timestamp_s - onset_time <= deadline_s)
        .fold((0.0, 0usize), |(sum, rows), r| {
            (sum + r.sample.speed_mps, rows + 1)
        });
    sum / rows.max(1) as f64
}

/// The drives every detector is scored on.
pub(super) struct TestSet {
    pub(super) kinds: Vec<TestKind>,
    pub(super) attacked: Vec<TestDrive>,
    /// Clean drives per rate.
    clean: Vec<Vec<Track>>,
    threads: usize,
}

pub(super) fn test_set(
    (seed, distribution): (u64, Distribution),
    repeats: u64,
    clean_drives_per_rate: u64,
    threads: usize,
) -> Result<TestSet> {
    let kinds = test_kinds();
    let mut jobs = Vec::new();
    for rate_index in 0..RATES_HZ.len() {
        for kind_index in 0..kinds.len() {
            for early in [true, false] {
                for _ in 0..repeats {
                    jobs.push((jobs.len() as u64, rate_index, kind_index, early));
                }
            }
        }
    }
    let attacked = map_parallel(&jobs, threads, |&(i, rate_index, kind_index, early)| {
        let test_kind = &kinds[kind_index];
        // Drives are drawn until one has the motion the test asks for (the first, for most).
        for attempt in 0..MOTION_ATTEMPTS {
            let seed = drive_seed(seed, Population::AttackedTest, i + (attempt << 32));
            let onset_s = if early {
                EARLY_ONSET_S
            } else {
                Rng::seed_from_u64(seed ^ 0x0A5E7)
                    .uniform_range(LATE_ONSET_S.0, LATE_ONSET_S.1)
                    .round()
            };
            let injected = attacked(
                (seed, distribution),
                test_kind.kind,
                (onset_s, TEST_ATTACK_S, TEST_AFTER_ATTACK_S),
                Some(RATES_HZ[rate_index]),
                &format!("test-{i}"),
            )?;
            if let Some(deadline_s) = test_kind.deadline_s(&injected.track, onset_s) {
                return Ok(TestDrive {
                    mean_speed_mps: mean_speed_to_deadline(&injected, deadline_s),
                    injected,
                    kind_index,
                    rate_index,
                    early,
                    onset_s,
                    deadline_s,
                });
            }
        }
        anyhow::bail!(
            "no drive in {MOTION_ATTEMPTS} draws for {} at {} Hz",
            test_kind.label(),
            RATES_HZ[rate_index]
        )
    })
    .into_iter()
    .collect::<Result<Vec<_>>>()?;
    Ok(TestSet {
        kinds,
        attacked,
        clean: clean_drives(
            (seed, distribution),
            Population::CleanTest,
            clean_drives_per_rate,
            threads,
        )?,
        threads,
    })
}

/// `per_rate` attack-free drives of [`CLEAN_DRIVE_S`] (with outages) at each of [`RATES_HZ`].
fn clean_drives(
    (seed, distribution): (u64, Distribution),
    population: Population,
    per_rate: u64,
    threads: usize,
) -> Result<Vec<Vec<Track>>> {
    let name = match population {
        Population::CleanValidation => "validation-clean",
        _ => "clean",
    };
    RATES_HZ
        .iter()
        .enumerate()
        .map(|(rate_index, rate_hz)| {
            let indices: Vec<u64> = (0..per_rate).collect();
            map_parallel(&indices, threads, |&i| {
                let index = rate_index as u64 * 1_000_000 + i;
                drive(
                    (drive_seed(seed, population, index), distribution),
                    CLEAN_DRIVE_S,
                    Some(*rate_hz),
                    true,
                    &format!("{name}-{rate_hz}hz-{i}"),
                )
            })
            .into_iter()
            .collect()
        })
        .collect()
}

/// One detector's results for one attack kind, onset and rate.
#[derive(Clone, Debug, Serialize)]
struct AttackCell {
    family: String,
    magnitude: Option<f64>,
    rate_hz: f64,
    early_onset: bool,
    drives: usize,
    /// The deadline after the onset (a test while standing: after the vehicle moves off).
    within_s: f64,
    /// Share of drives detected within the deadline.
    detected_in_time: f64,
    /// Share detected at all during the attack.
    detected: f64,
    median_delay_s: Option<f64>,
    /// Mean over detected drives of the share of attacked valid rows alarmed from the first onset
    /// to the attack's end.
    coverage: Option<f64>,
}

/// False alarms on the clean drives of one rate.
#[derive(Clone, Debug, Serialize)]
struct CleanCell {
    rate_hz: f64,
    attack_free_hours: f64,
    false_alarm_onsets: u64,
    per_hour: f64,
    /// Onsets within 30 s of the drive's start or of an outage's end.
    after_start_or_outage: u64,
    /// Onsets on a row whose offset was held beyond the decisive gate (the rest were opened by
    /// p̂ alone).
    with_held_offset: u64,
}

#[derive(Debug, Serialize)]
struct DetectorReport {
    name: String,
    seed: Option<u64>,
    /// The operating point (and lifecycle), `null` when none was within the budget on validation.
    operating_point: serde_json::Value,
    attacks: Vec<AttackCell>,
    clean: Vec<CleanCell>,
    /// Every attacked test drive's outcome (written to `drives.csv`, not to the report).
    #[serde(skip)]
    drives: Vec<DriveOutcome>,
}

/// One attacked test drive under one detector: a row of `drives.csv`.
#[derive(Clone, Debug, Serialize)]
struct DriveOutcome {
    detector: String,
    seed: Option<u64>,
    vehicle_id: String,
    attack: String,
    magnitude: Option<f64>,
    rate_hz: f64,
    early_onset: bool,
    onset_s: f64,
    deadline_s: f64,
    /// Mean onboard speed from the onset to the deadline (m/s).
    mean_speed_mps: f64,
    /// Seconds from the onset to the alarm's first onset in the attack; empty when missed.
    delay_s: Option<f64>,
    in_time: bool,
    coverage: Option<f64>,
}

/// Per-track scores of `tracks`, one [`Scored`] per track, `score` called on chunks in parallel.
fn per_track(
    tracks: &[Track],
    threads: usize,
    score: &(impl Fn(&[Track]) -> Scored + Sync),
) -> Vec<Scored> {
    let jobs: Vec<usize> = (0..tracks.len()).collect();
    map_parallel(&jobs, threads, |&i| score(std::slice::from_ref(&tracks[i])))
}

pub(super) fn median(mut values: Vec<f64>) -> Option<f64> {
    values.sort_by(f64::total_cmp);
    let n = values.len();
    (n > 0).then(|| {
        if n % 2 == 1 {
            values[n / 2]
        } else {
            0.5 * (values[n / 2 - 1] + values[n / 2])
        }
    })
}

impl TestSet {
    fn report(
        &self,
        name: &str,
        seed: Option<u64>,
        operating_point: serde_json::Value,
        score: impl Fn(&[Track]) -> Scored + Sync,
    ) -> DetectorReport {
        let tracks: Vec<Track> = self
            .attacked
            .iter()
            .map(|d| d.injected.track.clone())
            .collect();
        let scored = per_track(&tracks, self.threads, &score);
        let mut attacks = Vec::new();
        let mut outcomes = Vec::new();
        for (rate_index, &rate_hz) in RATES_HZ.iter().enumerate() {
            for (kind_index, test_kind) in self.kinds.iter().enumerate() {
                for early in [true, false] {
                    let mut delays = Vec::new();
                    let mut in_time = 0;
                    let mut coverages = Vec::new();
                    let mut drives = 0;
                    for (drive, scored) in self.attacked.iter().zip(&scored) {
                        if (drive.rate_index, drive.kind_index, drive.early)
                            != (rate_index, kind_index, early)
                        {
                            continue;
                        }
                        drives += 1;
                        let (delay, coverage) = delay_and_coverage(&drive.injected, scored);
                        let in_deadline = delay.is_some_and(|d| d <= drive.deadline_s);
                        in_time += usize::from(in_deadline);
                        outcomes.push(DriveOutcome {
                            detector: name.to_string(),
                            seed,
                            vehicle_id: drive.injected.track.vehicle_id.clone(),
                            attack: test_kind.label(),
                            magnitude: test_kind.kind.magnitude(),
                            rate_hz,
                            early_onset: early,
                            onset_s: drive.onset_s,
                            deadline_s: drive.deadline_s,
                            mean_speed_mps: drive.mean_speed_mps,
                            delay_s: delay,
                            in_time: in_deadline,
                            coverage,
                        });
                        if let Some(delay) = delay {
                            delays.push(delay);
                            coverages.extend(coverage);
                        }
                    }
                    let share = |n: usize| n as f64 / drives.max(1) as f64;
                    attacks.push(AttackCell {
                        family: test_kind.label(),
                        magnitude: test_kind.kind.magnitude(),
                        rate_hz,
                        early_onset: early,
                        drives,
                        within_s: test_kind.within_s,
                        detected_in_time: share(in_time),
                        detected: share(delays.len()),
                        coverage: (!coverages.is_empty())
                            .then(|| coverages.iter().sum::<f64>() / coverages.len() as f64),
                        median_delay_s: median(delays),
                    });
                }
            }
        }
        let clean = RATES_HZ
            .iter()
            .zip(&self.clean)
            .map(|(&rate_hz, drives)| {
                let scored = per_track(drives, self.threads, &score);
                clean_cell(rate_hz, &scored)
            })
            .collect();
        DetectorReport {
            name: name.to_string(),
            seed,
            operating_point,
            attacks,
            clean,
            drives: outcomes,
        }
    }
}

/// False-alarm onsets on clean drives of one rate, and those soon after a start or an outage.
fn clean_cell(rate_hz: f64, scored: &[Scored]) -> CleanCell {
    let mut onsets = 0;
    let mut after_start = 0;
    let mut with_held_offset = 0;
    let mut hours = 0.0;
    for track in scored {
        hours += normal_hours(&track.rows);
        let mut resumed_s = f64::NEG_INFINITY;
        for i in 0..track.rows.len() {
            let time = track.rows[i].time_s;
            if i == 0 || time - track.rows[i - 1].time_s > OUTAGE_S {
                resumed_s = time;
            }
            let onset = track.alarms[i] && (i == 0 || !track.alarms[i - 1]);
            if onset {
                onsets += 1;
                if track.offset.get(i).is_some_and(|o| o.held_s.is_some()) {
                    with_held_offset += 1;
                }
                if time - resumed_s <= AFTER_START_S {
                    after_start += 1;
                }
            }
        }
    }
    CleanCell {
        rate_hz,
        attack_free_hours: hours,
        false_alarm_onsets: onsets,
        per_hour: onsets as f64 / hours.max(f64::MIN_POSITIVE),
        after_start_or_outage: after_start,
        with_held_offset,
    }
}

#[derive(Debug, Serialize)]
struct Report {
    protocol: &'static str,
    seed: u64,
    training_seeds: Vec<u64>,
    schema: &'static str,
    features: &'static str,
    exit_mask: bool,
    /// Attacked training drives go on for 30 s to this long after the attack (s).
    after_attack_s: f64,
    vehicle_levels: bool,
    lifecycle_in_seconds: bool,
    false_alarm_budget_per_hour: f64,
    rates_hz: Vec<f64>,
    test_drives_per_cell: u64,
    clean_drives_per_rate: u64,
    validation_clean_drives_per_rate: u64,
    detectors: Vec<DetectorReport>,
    experiment_wall_time_s: f64,
}

pub fn run(args: Args) -> Result<()> {
    let started = Instant::now();
    let threads = args.common.threads.unwrap_or_else(default_threads);
    let (_, split) = prepare(&args.common, RECORDED_WARMUP_S)?;
    let seed = args.common.seed;
    let (train, validation) = recorded_and_simulated(
        &split,
        seed,
        RECORDED_WARMUP_S,
        args.simulated_only,
        training_mix(
            (seed, args.distribution),
            Population::Train,
            (args.drives, args.after_attack_s),
            threads,
        )?,
        [
            training_mix(
                (seed, args.distribution),
                Population::Validation,
                (args.drives, args.after_attack_s),
                threads,
            )?,
            clean_drives(
                (seed, args.distribution),
                Population::CleanValidation,
                args.validation_clean_drives,
                threads,
            )?
            .concat(),
        ]
        .concat(),
    )?;
    let test = test_set(
        (seed, args.distribution),
        args.repeats,
        args.clean_drives,
        threads,
    )?;
    eprintln!(
        "offsets: {} training and {} validation tracks; test: {} attacked drives, {} clean drives",
        train.len(),
        validation.len(),
        test.attacked.len(),
        test.clean.iter().map(Vec::len).sum::<usize>()
    );
    let spec_for = |schema: FeatureSchema, training_seed: u64, features| TrainingSpec {
        data_description: [
            (!args.simulated_only).then(|| {
                format!(
                    "AV-GPS-Dataset-2.csv chronological 70/15 + injected attacks in both \
                     (validation parts and injected pieces after {RECORDED_WARMUP_S} s of \
                     warm-up rows)"
                )
            }),
            Some(format!(
                "{} randomised simulated drives each for training and validation \
                 (DriveDistribution::{}(); half attacked: jumps 5 m–50 km, hops, frozen \
                 fixes, ramps, accelerating and toggling drifts, a third starting 10–60 s in, \
                 their drifts at 1 m/s or more), and {} attack-free {CLEAN_DRIVE_S} s \
                 validation drives at each of 1, 5 and 10 Hz",
                args.drives,
                args.distribution.name(),
                args.validation_clean_drives
            )),
        ]
        .into_iter()
        .flatten()
        .collect(),
        anchor_rebase: args.anchor_rebase.into(),
        ..TrainingSpec::with(
            training_seed,
            args.common.epochs,
            schema,
            Ablation {
                features,
                no_exit_mask: args.no_exit_mask,
                no_vehicle_levels: args.no_vehicle_levels,
                timer_trust: args.timer_trust,
                rows_lifecycle: args.rows_lifecycle,
                ..Ablation::default()
            },
            KappaRho::default(),
        )
    };
    let training_seeds = seed_list(args.training_seed.unwrap_or(seed), args.seeds);
    let mut jobs: Vec<(FeatureSchema, u64)> = Vec::new();
    for &training_seed in &training_seeds {
        jobs.push((args.schema, training_seed));
        if args.paper {
            jobs.push((FeatureSchema::Paper, training_seed));
        }
    }
    let trained = map_parallel(&jobs, threads, |&(schema, training_seed)| -> Result<_> {
        let features = if schema == args.schema {
            args.features
        } else {
            FeatureGroups::All
        };
        let spec = TrainingSpec {
            train: TrainConfig {
                seed: training_seed,
                ..spec_for(schema, training_seed, features).train
            },
            ..spec_for(schema, training_seed, features)
        };
        let job_started = Instant::now();
        let data = TrainingData::Explicit {
            train: train.clone(),
            validation: validation.clone(),
        };
        let trained = train_with_progress(&spec, data, false)
            .with_context(|| format!("training HO-LLN ({})", schema.name()))?;
        let name = format!("HO-LLN {}", schema.name());
        eprintln!(
            "offsets: {name} (seed {training_seed}) trained in {:.1} s",
            job_started.elapsed().as_secs_f64()
        );
        // The lab chooses the point again, on the validation drives of every rate, and on the
        // evidence the training chose it on.
        let rebase = AnchorRebase::from(args.anchor_rebase);
        let mut chosen_on = trained.artifact;
        chosen_on.set_anchor_rebasing(rebase.when_choosing());
        let (artifact, _) = within_budget(&name, chosen_on, &validation);
        let served = artifact.map(|mut artifact| {
            artifact.set_anchor_rebasing(rebase.when_serving());
            Arc::new(artifact)
        });
        Ok((name, training_seed, served))
    });
    let mut detectors = Vec::new();
    for result in trained {
        let (name, training_seed, artifact) = result?;
        if let Some(artifact) = &artifact
            && training_seed == training_seeds[0]
        {
            let file = format!("model-{}.json", artifact.schema().name());
            artifact.write(std::io::BufWriter::new(
                std::fs::File::create(args.common.out.join(&file))
                    .with_context(|| format!("creating {file}"))?,
            ))?;
        }
        detectors.push(model_report(
            &test,
            &name,
            Some(training_seed),
            artifact.as_ref(),
        )?);
    }
    for path in &args.also {
        let name = path.display().to_string();
        let (artifact, _) = within_budget(&name, (*load_artifact(path)?).clone(), &validation);
        detectors.push(model_report(
            &test,
            &name,
            None,
            artifact.map(Arc::new).as_ref(),
        )?);
    }
    let projection = spec_for(args.schema, seed, FeatureGroups::All).projection;
    match fit_glr_comparator(&train, &validation, projection, BUDGET) {
        Ok(glr) => detectors.push(test.report(
            "directional GLR",
            None,
            serde_json::to_value(glr.operating_point)?,
            |tracks| glr.score_tracks(tracks),
        )),
        Err(error) => eprintln!("directional GLR: {error}"),
    }
    match fit_cusum_comparator(&train, &validation, projection, BUDGET) {
        Ok(cusum) => detectors.push(test.report(
            "CUSUM",
            None,
            serde_json::to_value(&cusum.cusum)?,
            |tracks| cusum.score_tracks(tracks),
        )),
        Err(error) => eprintln!("CUSUM: {error}"),
    }
    let gate = ResidualGate::default();
    detectors.push(test.report(
        "residual gate (5 m step or 5 m over 10 s, held 1 s)",
        None,
        serde_json::to_value(gate)?,
        |tracks| gate.score_tracks(tracks, projection),
    ));
    let report = Report {
        protocol: "offsets",
        seed,
        training_seeds,
        schema: args.schema.name(),
        features: args.features.name(),
        exit_mask: !args.no_exit_mask,
        after_attack_s: args.after_attack_s,
        vehicle_levels: !args.no_vehicle_levels,
        lifecycle_in_seconds: !args.rows_lifecycle,
        false_alarm_budget_per_hour: FALSE_ALARM_BUDGET_PER_HOUR,
        rates_hz: RATES_HZ.to_vec(),
        test_drives_per_cell: args.repeats,
        clean_drives_per_rate: args.clean_drives,
        validation_clean_drives_per_rate: args.validation_clean_drives,
        detectors,
        experiment_wall_time_s: started.elapsed().as_secs_f64(),
    };
    write_drives(&args.common.out.join("drives.csv"), &report.detectors)?;
    write_report(&args.common.out, &report, &render_markdown(&report))
}

/// Every detector's outcome on every attacked test drive, one CSV row each.
fn write_drives(path: &std::path::Path, detectors: &[DetectorReport]) -> Result<()> {
    let mut writer =
        csv::Writer::from_path(path).with_context(|| format!("creating {}", path.display()))?;
    for outcome in detectors.iter().flat_map(|d| &d.drives) {
        writer.serialize(outcome)?;
    }
    writer.flush().context("writing drives.csv")?;
    Ok(())
}

/// An HO-LLN artifact's report, or an empty one when no operating point was within the budget.
fn model_report(
    test: &TestSet,
    name: &str,
    seed: Option<u64>,
    artifact: Option<&Arc<ModelArtifact>>,
) -> Result<DetectorReport> {
    let Some(artifact) = artifact else {
        return Ok(DetectorReport {
            name: name.to_string(),
            seed,
            operating_point: serde_json::Value::Null,
            attacks: Vec::new(),
            clean: Vec::new(),
            drives: Vec::new(),
        });
    };
    let point = operating_point_json(artifact);
    Ok(test.report(name, seed, point, |tracks| score_tracks(artifact, tracks)))
}

fn magnitude_label(cell: &AttackCell) -> String {
    let unit = match cell.family.as_str() {
        "ramp_drift" | "toggling_drift" => " m/s",
        "accelerating_drift" => " m/s²",
        _ => " m",
    };
    cell.magnitude
        .map_or_else(String::new, |m| format!(" {m}{unit}"))
}

fn render_markdown(report: &Report) -> String {
    let mut md = format!(
        "# offsets experiment\n\nRealistic simulated drives (onboard errors, multipath, outages, \
         1–30 m/s), {} test drives per attack, onset and rate; attacks last {TEST_ATTACK_S} s and \
         start {EARLY_ONSET_S} s after the session starts (early) or {}–{} s into it (late). Every \
         learned and fitted detector's operating point is chosen on validation data within ≤ {} \
         false alarm per attack-free hour; the residual gate is fixed. A frozen fix is tested on \
         vehicles moving (≥ {MOVING_MPS} m/s) until the deadline, and on vehicles standing at the \
         onset, whose deadline counts from when they move off (within {MOVE_OFF_WITHIN_S} s). \
         Cells: share detected within the deadline (early / late onset), then the alarm's coverage \
         of the attack after its onset (late onset).\n",
        report.test_drives_per_cell,
        LATE_ONSET_S.0,
        LATE_ONSET_S.1,
        report.false_alarm_budget_per_hour
    );
    for detector in &report.detectors {
        md.push_str(&format!(
            "\n## {}{}\n\n",
            detector.name,
            detector
                .seed
                .map_or_else(String::new, |s| format!(" (seed {s})"))
        ));
        if detector.operating_point.is_null() {
            md.push_str("No operating point within the budget on validation.\n");
            continue;
        }
        md.push_str(&format!(
            "Operating point: `{}`\n\n",
            detector.operating_point
        ));
        md.push_str(&attack_table(&detector.attacks, |early| {
            let (early, late) = (&detector.attacks[early], &detector.attacks[early + 1]);
            format!(
                "{:.2} / {:.2}, cov {}",
                early.detected_in_time,
                late.detected_in_time,
                late.coverage
                    .map_or_else(|| "–".into(), |c| format!("{c:.2}"))
            )
        }));
        md.push_str("\n| rate | attack-free hours | false alarms | per hour | within 30 s of a start or outage | with a held offset |\n|---|---|---|---|---|---|\n");
        for c in &detector.clean {
            md.push_str(&format!(
                "| {} Hz | {:.1} | {} | {:.2} | {} | {} |\n",
                c.rate_hz,
                c.attack_free_hours,
                c.false_alarm_onsets,
                c.per_hour,
                c.after_start_or_outage,
                c.with_held_offset
            ));
        }
    }
    md.push_str(&seeds_summary(report));
    md.push_str(&format!(
        "\nWall time {:.0} s.\n",
        report.experiment_wall_time_s
    ));
    md
}

/// The attack table: a row per attack kind and magnitude, a column per rate; `cell` formats a rate's
/// cell from the index of its early-onset cell in `attacks` (the late one follows it).
fn attack_table(attacks: &[AttackCell], cell: impl Fn(usize) -> String) -> String {
    let mut md = String::from("| attack | deadline |");
    for rate in RATES_HZ {
        md.push_str(&format!(" {rate} Hz |"));
    }
    md.push_str("\n|---|---|");
    md.push_str(&"---|".repeat(RATES_HZ.len()));
    md.push('\n');
    let per_rate = attacks.len() / RATES_HZ.len().max(1);
    for index in (0..per_rate).step_by(2) {
        let first = &attacks[index];
        md.push_str(&format!(
            "| {}{} | {} s |",
            first.family,
            magnitude_label(first),
            first.within_s
        ));
        for rate_index in 0..RATES_HZ.len() {
            md.push_str(&format!(" {} |", cell(rate_index * per_rate + index)));
        }
        md.push('\n');
    }
    md
}

/// "median [min–max]" of `values` (two decimals); "–" for none.
fn median_and_range(values: Vec<f64>) -> String {
    let low = values.iter().copied().fold(f64::INFINITY, f64::min);
    let high = values.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    match median(values) {
        Some(m) if low < high => format!("{m:.2} [{low:.2}–{high:.2}]"),
        Some(m) => format!("{m:.2}"),
        None => "–".into(),
    }
}

/// For a learned detector trained with several seeds, each cell's median and range over the seeds
/// (those without an operating point within the budget are counted apart); empty for one seed.
fn seeds_summary(report: &Report) -> String {
    let mut md = String::new();
    let mut names: Vec<&str> = Vec::new();
    for d in &report.detectors {
        if d.seed.is_some() && !names.contains(&d.name.as_str()) {
            names.push(&d.name);
        }
    }
    for name in names {
        let runs: Vec<&DetectorReport> = report
            .detectors
            .iter()
            .filter(|d| d.name == name && d.seed.is_some())
            .collect();
        let scored: Vec<&DetectorReport> = runs
            .iter()
            .copied()
            .filter(|d| !d.operating_point.is_null())
            .collect();
        if runs.len() < 2 || scored.is_empty() {
            continue;
        }
        md.push_str(&format!(
            "\n## {name} over {} seeds: median [min–max]\n\n{} of {} seeds with an operating point \
             within the budget. Cells: detected within the deadline, early onset; late onset; the \
             late attack's coverage.\n\n",
            runs.len(),
            scored.len(),
            runs.len()
        ));
        let over_seeds = |index: usize, value: fn(&AttackCell) -> Option<f64>| {
            median_and_range(
                scored
                    .iter()
                    .filter_map(|d| d.attacks.get(index).and_then(value))
                    .collect(),
            )
        };
        md.push_str(&attack_table(&scored[0].attacks, |early| {
            format!(
                "{}; {}; cov {}",
                over_seeds(early, |c| Some(c.detected_in_time)),
                over_seeds(early + 1, |c| Some(c.detected_in_time)),
                over_seeds(early + 1, |c| c.coverage)
            )
        }));
        md.push_str("\n| rate | false alarms per attack-free hour | within 30 s of a start or outage |\n|---|---|---|\n");
        for (rate_index, rate) in RATES_HZ.iter().enumerate() {
            let clean = |value: fn(&CleanCell) -> f64| {
                median_and_range(
                    scored
                        .iter()
                        .filter_map(|d| d.clean.get(rate_index).map(value))
                        .collect(),
                )
            };
            md.push_str(&format!(
                "| {rate} Hz | {} | {} |\n",
                clean(|c| c.per_hour),
                clean(|c| c.after_start_or_outage as f64)
            ));
        }
    }
    md
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cell(rate_hz: f64, early_onset: bool, detected: f64, coverage: Option<f64>) -> AttackCell {
        AttackCell {
            family: "jump".into(),
            magnitude: Some(20.0),
            rate_hz,
            early_onset,
            drives: 10,
            within_s: 10.0,
            detected_in_time: detected,
            detected,
            median_delay_s: Some(1.0),
            coverage,
        }
    }

    fn detector(seed: u64, scored: bool, early: f64, per_hour: f64) -> DetectorReport {
        DetectorReport {
            name: "HO-LLN v3".into(),
            seed: Some(seed),
            operating_point: if scored {
                serde_json::json!({"theta": 0.9})
            } else {
                serde_json::Value::Null
            },
            attacks: RATES_HZ
                .iter()
                .flat_map(|&r| [cell(r, true, early, None), cell(r, false, 1.0, Some(0.5))])
                .collect(),
            clean: RATES_HZ
                .iter()
                .map(|&rate_hz| CleanCell {
                    rate_hz,
                    attack_free_hours: 5.0,
                    false_alarm_onsets: 1,
                    per_hour,
                    after_start_or_outage: 0,
                    with_held_offset: 0,
                })
                .collect(),
            drives: Vec::new(),
        }
    }

    fn report(detectors: Vec<DetectorReport>) -> Report {
        Report {
            protocol: "offsets",
            seed: 42,
            training_seeds: vec![42, 43, 44],
            schema: "v3",
            features: "all",
            exit_mask: true,
            after_attack_s: MIN_AFTER_ATTACK_S,
            vehicle_levels: true,
            lifecycle_in_seconds: true,
            false_alarm_budget_per_hour: 1.0,
            rates_hz: RATES_HZ.to_vec(),
            test_drives_per_cell: 10,
            clean_drives_per_rate: 24,
            validation_clean_drives_per_rate: 12,
            detectors,
            experiment_wall_time_s: 1.0,
        }
    }

    #[test]
    fn several_seeds_are_summarised_by_median_and_range_over_the_seeds_with_a_point() {
        let md = seeds_summary(&report(vec![
            detector(42, true, 0.3, 0.5),
            detector(43, true, 0.7, 0.2),
            detector(44, true, 0.4, 0.9),
            // No operating point: counted, not summarised.
            detector(45, false, 0.0, 0.0),
        ]));
        assert!(md.contains("## HO-LLN v3 over 4 seeds"), "{md}");
        assert!(md.contains("3 of 4 seeds with an operating point"), "{md}");
        // Early onset: median 0.4 of 0.3, 0.4, 0.7; late: all 1.00, no range; coverage 0.5.
        assert!(
            md.contains("| jump 20 m | 10 s | 0.40 [0.30–0.70]; 1.00; cov 0.50 |"),
            "{md}"
        );
        assert!(md.contains("| 1 Hz | 0.50 [0.20–0.90] | 0.00 |"), "{md}");
    }

    #[test]
    fn one_seed_has_no_summary() {
        assert_eq!(
            seeds_summary(&report(vec![detector(42, true, 0.3, 0.5)])),
            ""
        );
    }

    /// A 1 Hz track whose onboard speed at second `t` is `speed(t)`, for `seconds` seconds.
    fn track_with_speeds(seconds: u32, speed: impl Fn(f64) -> f64) -> Track {
        use spoofwatch_core::sample::{Record, Sample};
        Track {
            vehicle_id: "v".into(),
            records: (0..seconds)
                .map(|t| Record {
                    sample: Sample::new(
                        1000.0 + f64::from(t),
                        48.0,
                        11.0,
                        speed(f64::from(t)),
                        0.0,
                    ),
                    label: None,
                    comparator_alarm: None,
                    line: u64::from(t) + 2,
                    trajectory_break: false,
                    warmup: false,
                })
                .collect(),
        }
    }

    #[test]
    fn a_frozen_fix_is_tested_on_the_motion_its_test_names() {
        let frozen = |motion| TestKind {
            kind: AttackKind::FrozenPosition,
            within_s: 10.0,
            motion,
        };
        let (moving, standing) = (frozen(Motion::Moving), frozen(Motion::Standing));
        let cruising = track_with_speeds(200, |_| 8.0);
        // Stands until 40 s, then moves off: at 20 s it is standing, moving off 20 s later.
        let stop_and_go = track_with_speeds(200, |t| if t < 40.0 { 0.1 } else { 5.0 });
        // Slows to a crawl 5 s after the onset at 20 s: not moving until the deadline.
        let slowing = track_with_speeds(200, |t| if t < 25.0 { 8.0 } else { 1.0 });
        assert_eq!(moving.deadline_s(&cruising, 20.0), Some(10.0));
        assert_eq!(moving.deadline_s(&slowing, 20.0), None);
        assert_eq!(moving.deadline_s(&stop_and_go, 20.0), None);
        assert_eq!(standing.deadline_s(&stop_and_go, 20.0), Some(30.0));
        assert_eq!(standing.deadline_s(&cruising, 20.0), None);
        // Moving off more than a minute after the onset is not a test drive.
        assert_eq!(standing.deadline_s(&stop_and_go, -50.0), None);
        let any = TestKind::any(AttackKind::FrozenPosition, 10.0);
        assert_eq!(any.deadline_s(&slowing, 20.0), Some(10.0));
        assert_eq!(moving.label(), "frozen_position while moving");
    }

    #[test]
    fn attack_free_validation_drives_run_at_each_tested_rate_and_are_not_test_drives() {
        // 1 / the median sampling interval: an hour-long drive has outages.
        let rate_of = |track: &Track| {
            let mut intervals: Vec<f64> = track
                .records
                .windows(2)
                .map(|w| w[1].sample.timestamp_s - w[0].sample.timestamp_s)
                .collect();
            intervals.sort_by(f64::total_cmp);
            1.0 / intervals[intervals.len() / 2]
        };
        let validation = clean_drives(
            (7, Distribution::Realistic),
            Population::CleanValidation,
            1,
            1,
        )
        .unwrap();
        let test = clean_drives((7, Distribution::Realistic), Population::CleanTest, 1, 1).unwrap();
        assert_eq!(validation.len(), RATES_HZ.len());
        for ((drives, test_drives), rate_hz) in validation.iter().zip(&test).zip(RATES_HZ) {
            let drive = &drives[0];
            assert!(
                (rate_of(drive) - rate_hz).abs() < 0.05 * rate_hz,
                "{}",
                rate_of(drive)
            );
            assert!(drive.records.iter().all(|r| r.label != Some(true)));
            assert!(drive.vehicle_id.starts_with("validation-clean-"));
            assert_ne!(drive.records[5].sample, test_drives[0].records[5].sample);
        }
    }
}
