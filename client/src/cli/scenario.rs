//! `spoofwatch scenario`: labelled subtle-attack scenarios in the telemetry CSV format.

use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use clap::ValueEnum;
use spoofwatch_core::data::telemetry::write_tracks;
use spoofwatch_core::sample::Track;
use spoofwatch_core::scenario::{
    AttackDuration, AttackKind, AttackSpec, DriveDistribution, DriveSpec, FleetSpec, InjectedTrack,
    RAMP_SWEEP_VELOCITIES_MPS, RegionalAttack, ScenarioError, ScenarioPlan, Spoofer, generate,
    generate_fleet, inject, normal_runs, simulate_drive,
};

use crate::cli::json::write_json;
use crate::input::load_tracks;

#[derive(Debug, clap::Subcommand)]
pub enum Command {
    /// Simulated drives (kinematically consistent truth, metre-level GNSS noise), optionally attacked.
    Simulate(SimulateArgs),
    /// One attack injected into the normal stretches of recorded data.
    Inject(InjectArgs),
    /// A sweep of attacks (default: ramp drifts at 0.05–2 m/s) injected into recorded or simulated bases.
    Sweep(SweepArgs),
    /// A fleet in one area with a regional spoofer that captures every receiver within its radius, and
    /// the ground truth of who was captured, when and where.
    Fleet(FleetArgs),
}

/// Attack family.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum KindArg {
    /// Offset growing at a constant velocity (magnitude: m/s, 0.05–2).
    Ramp,
    /// Offset growing with constant acceleration (magnitude: m/s², 0.01–0.5).
    Accel,
    /// GNSS position frozen at the onset fix (no magnitude).
    Frozen,
    /// Constant offset from the onset (magnitude: metres).
    Jump,
    /// Teleports every `--hold` seconds up to `--magnitude` metres from the onset fix, frozen between.
    Hop,
    /// A ramp (magnitude: m/s) whose fix shows the true position for 1 s every `--hold` seconds.
    Toggle,
}

fn kind(family: KindArg, magnitude: Option<f64>, hold_s: f64) -> Result<AttackKind> {
    let need = |what: &str| {
        magnitude.with_context(|| format!("--magnitude is required for {what} attacks"))
    };
    Ok(match family {
        KindArg::Ramp => AttackKind::RampDrift {
            velocity_mps: need("ramp")?,
        },
        KindArg::Accel => AttackKind::AcceleratingDrift {
            acceleration_mps2: need("accel")?,
        },
        KindArg::Frozen => AttackKind::FrozenPosition,
        KindArg::Jump => AttackKind::Jump {
            offset_m: need("jump")?,
        },
        KindArg::Hop => AttackKind::Hopping {
            offset_m: need("hop")?,
            hold_s,
        },
        KindArg::Toggle => AttackKind::TogglingDrift {
            velocity_mps: need("toggle")?,
            period_s: hold_s,
        },
    })
}

/// Where the attack goes and what it looks like.
#[derive(Debug, clap::Args)]
pub struct AttackArgs {
    /// Attack family.
    #[arg(long, value_enum)]
    attack: KindArg,
    /// Attack magnitude (m/s for ramp, m/s² for accel, m for jump and hop).
    #[arg(long)]
    magnitude: Option<f64>,
    /// Seconds between the hops of a hop attack, or between the toggles to the true position of a
    /// toggle attack.
    #[arg(long, default_value_t = 4.0)]
    hold: f64,
    /// Direction of the false displacement, degrees clockwise from north.
    #[arg(long, default_value_t = 90.0)]
    direction: f64,
    /// Attack onset, seconds after each base's first sample.
    #[arg(long)]
    onset: f64,
    /// Attack duration in seconds.
    #[arg(long, default_value_t = 60.0)]
    duration: f64,
}

impl AttackArgs {
    fn spec(&self) -> Result<AttackSpec> {
        let spec = AttackSpec {
            kind: kind(self.attack, self.magnitude, self.hold)?,
            direction_deg: self.direction,
            onset_s: self.onset,
            duration_s: self.duration,
            seed: None,
        };
        spec.validate()?;
        Ok(spec)
    }
}

#[derive(Debug, clap::Args)]
pub struct SimulateArgs {
    /// Output telemetry CSV.
    #[arg(long)]
    out: PathBuf,
    /// Number of vehicles (one drive each, seeds seed, seed+1, …).
    #[arg(long, default_value_t = 1)]
    vehicles: u64,
    /// Drive length in seconds.
    #[arg(long, default_value_t = 600.0)]
    duration: f64,
    /// Output sample rate in Hz (the default drive; refused with --realistic, which draws the rate).
    #[arg(long, default_value_t = 1.0, conflicts_with = "realistic")]
    rate: f64,
    /// Draw each vehicle's drive from the realistic distribution (1–30 m/s, 1–10 Hz, varied GNSS noise,
    /// onboard scale/bias/timing errors, multipath, outages in half the drives) with seed+i. Outages are
    /// missing rows; an --attack window that spans one is refused.
    #[arg(long)]
    realistic: bool,
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Optionally attack every drive (see `inject`).
    #[arg(long, requires = "onset")]
    attack: Option<KindArg>,
    #[arg(long)]
    magnitude: Option<f64>,
    #[arg(long, default_value_t = 4.0)]
    hold: f64,
    #[arg(long, default_value_t = 90.0)]
    direction: f64,
    #[arg(long)]
    onset: Option<f64>,
    #[arg(long, default_value_t = 60.0)]
    attack_duration: f64,
    /// Also write the attacks (onset, direction, magnitude, rows) as JSON.
    #[arg(long)]
    manifest: Option<PathBuf>,
}

#[derive(Debug, clap::Args)]
pub struct InjectArgs {
    /// Recorded data; its normal (label 0 or unlabelled) stretches are the bases.
    #[arg(long, required = true, num_args = 1..)]
    data: Vec<PathBuf>,
    /// Output telemetry CSV.
    #[arg(long)]
    out: PathBuf,
    #[command(flatten)]
    attack: AttackArgs,
    /// Also write the attacks as JSON.
    #[arg(long)]
    manifest: Option<PathBuf>,
}

#[derive(Debug, clap::Args)]
pub struct SweepArgs {
    /// Recorded data whose normal stretches are bases (optional).
    #[arg(long, num_args = 1..)]
    data: Vec<PathBuf>,
    /// Simulated drives added as bases.
    #[arg(long, default_value_t = 0)]
    drives: u64,
    /// Length of each simulated drive (s).
    #[arg(long, default_value_t = 600.0)]
    drive_duration: f64,
    /// Ramp-drift velocities (m/s), comma-separated.
    #[arg(long, value_delimiter = ',', default_values_t = RAMP_SWEEP_VELOCITIES_MPS)]
    velocities: Vec<f64>,
    /// Attack duration (s).
    #[arg(long, default_value_t = 60.0)]
    duration: f64,
    /// Scenarios per (base, velocity), with random onsets and directions.
    #[arg(long, default_value_t = 1)]
    repeats: usize,
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Output telemetry CSV.
    #[arg(long)]
    out: PathBuf,
    /// Also write the attacks as JSON.
    #[arg(long)]
    manifest: Option<PathBuf>,
}

/// What a regional spoofer does to the receivers it captures.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum RegionalArg {
    /// Every captured receiver reports --false-lat/--false-lon (with its own metre-level error).
    Position,
    /// Every captured fix is displaced by --east-m/--north-m.
    Translation,
    /// Every captured fix drifts at --east-mps/--north-mps from the vehicle's capture on.
    Drift,
}

#[derive(Debug, clap::Args)]
pub struct FleetArgs {
    /// Output telemetry CSV (label 1 = a row captured by the spoofer).
    #[arg(long)]
    out: PathBuf,
    /// Output ground truth JSON: the spec and, per vehicle, whether, when and where it was captured.
    #[arg(long)]
    truth: PathBuf,
    /// Number of vehicles.
    #[arg(long, default_value_t = FleetSpec::default().vehicles)]
    vehicles: usize,
    /// Vehicles routed through the spoofer's circle while it is active; the others keep clear of it.
    #[arg(long, default_value_t = FleetSpec::default().pass_through)]
    pass_through: usize,
    /// Latitude of the area's centre (degrees).
    #[arg(long, default_value_t = FleetSpec::default().centre_lat_deg, allow_negative_numbers = true)]
    centre_lat: f64,
    /// Longitude of the area's centre (degrees).
    #[arg(long, default_value_t = FleetSpec::default().centre_lon_deg, allow_negative_numbers = true)]
    centre_lon: f64,
    /// Side of the square area the other vehicles start in (m).
    #[arg(long, default_value_t = FleetSpec::default().area_size_m)]
    area_m: f64,
    /// Length of every drive (s).
    #[arg(long, default_value_t = FleetSpec::default().duration_s)]
    duration: f64,
    /// Sample rate of every vehicle (Hz; e.g. 1, 5 or 10).
    #[arg(long, default_value_t = FleetSpec::default().rate_hz)]
    rate: f64,
    /// Spoofer latitude (degrees; default: the area's centre).
    #[arg(long, allow_negative_numbers = true)]
    spoofer_lat: Option<f64>,
    /// Spoofer longitude (degrees; default: the area's centre).
    #[arg(long, allow_negative_numbers = true)]
    spoofer_lon: Option<f64>,
    /// Capture radius of the spoofer (m).
    #[arg(long, default_value_t = Spoofer::default().radius_m)]
    radius_m: f64,
    /// Spoofer switch-on, seconds from the start.
    #[arg(long, default_value_t = Spoofer::default().start_s)]
    start: f64,
    /// How long the spoofer is active (s).
    #[arg(long, default_value_t = Spoofer::default().duration_s)]
    attack_duration: f64,
    /// What captured receivers report.
    #[arg(long, value_enum, default_value_t = RegionalArg::Drift)]
    attack: RegionalArg,
    /// False latitude of `--attack position` (degrees).
    #[arg(long, allow_negative_numbers = true)]
    false_lat: Option<f64>,
    /// False longitude of `--attack position` (degrees).
    #[arg(long, allow_negative_numbers = true)]
    false_lon: Option<f64>,
    /// East displacement of `--attack translation` (m; an omitted component is 0).
    #[arg(long, allow_negative_numbers = true)]
    east_m: Option<f64>,
    /// North displacement of `--attack translation` (m; an omitted component is 0).
    #[arg(long, allow_negative_numbers = true)]
    north_m: Option<f64>,
    /// East drift velocity of `--attack drift` (m/s; an omitted component is 0; with neither
    /// component given, 1 m/s east).
    #[arg(long, allow_negative_numbers = true)]
    east_mps: Option<f64>,
    /// North drift velocity of `--attack drift` (m/s; an omitted component is 0).
    #[arg(long, allow_negative_numbers = true)]
    north_mps: Option<f64>,
    /// Captured receivers raise their own spoofing flag (recorded in the ground truth).
    #[arg(long)]
    flag_on_capture: bool,
    /// Seed of the drives, the routing and the placement.
    #[arg(long, default_value_t = FleetSpec::default().seed)]
    seed: u64,
}

impl FleetArgs {
    /// The attack, refusing the options of another attack.
    fn attack(&self) -> Result<RegionalAttack> {
        let options = [
            ("--false-lat", self.false_lat, RegionalArg::Position),
            ("--false-lon", self.false_lon, RegionalArg::Position),
            ("--east-m", self.east_m, RegionalArg::Translation),
            ("--north-m", self.north_m, RegionalArg::Translation),
            ("--east-mps", self.east_mps, RegionalArg::Drift),
            ("--north-mps", self.north_mps, RegionalArg::Drift),
        ];
        let attack_name = |attack: RegionalArg| {
            attack
                .to_possible_value()
                .map(|v| v.get_name().to_owned())
                .unwrap_or_default()
        };
        for (flag, value, attack) in options {
            if value.is_some() && attack != self.attack {
                bail!(
                    "{flag} belongs to --attack {}, not --attack {}",
                    attack_name(attack),
                    attack_name(self.attack)
                );
            }
        }
        Ok(match self.attack {
            RegionalArg::Position => {
                let (Some(lat_deg), Some(lon_deg)) = (self.false_lat, self.false_lon) else {
                    bail!("--attack position needs --false-lat and --false-lon");
                };
                RegionalAttack::Position { lat_deg, lon_deg }
            }
            RegionalArg::Translation => {
                if self.east_m.is_none() && self.north_m.is_none() {
                    bail!("--attack translation needs --east-m and/or --north-m");
                }
                RegionalAttack::Translation {
                    east_m: self.east_m.unwrap_or(0.0),
                    north_m: self.north_m.unwrap_or(0.0),
                }
            }
            RegionalArg::Drift => match (self.east_mps, self.north_mps) {
                (None, None) => RegionalAttack::default(),
                (east, north) => RegionalAttack::Drift {
                    east_mps: east.unwrap_or(0.0),
                    north_mps: north.unwrap_or(0.0),
                },
            },
        })
    }

    /// The fleet spec the options describe, validated (a bad value names its option).
    pub fn spec(&self) -> Result<FleetSpec> {
        let spec = FleetSpec {
            vehicles: self.vehicles,
            pass_through: self.pass_through,
            centre_lat_deg: self.centre_lat,
            centre_lon_deg: self.centre_lon,
            area_size_m: self.area_m,
            duration_s: self.duration,
            rate_hz: self.rate,
            spoofer: Spoofer {
                lat_deg: self.spoofer_lat.unwrap_or(self.centre_lat),
                lon_deg: self.spoofer_lon.unwrap_or(self.centre_lon),
                radius_m: self.radius_m,
                start_s: self.start,
                duration_s: self.attack_duration,
                attack: self.attack()?,
            },
            distribution: DriveDistribution::realistic(),
            flag_on_capture: self.flag_on_capture,
            seed: self.seed,
        };
        match spec.validate() {
            Ok(()) => Ok(spec),
            Err(err @ ScenarioError::InvalidFleet { field, .. }) => match fleet_flag(field) {
                Some(flag) => bail!("{flag}: {err}"),
                None => Err(err.into()),
            },
            Err(err) => Err(err.into()),
        }
    }
}

/// The option that sets a field of the fleet spec.
fn fleet_flag(field: &str) -> Option<&'static str> {
    Some(match field {
        "vehicles" => "--vehicles",
        "pass_through" => "--pass-through",
        "centre_lat_deg" => "--centre-lat",
        "centre_lon_deg" => "--centre-lon",
        "area_size_m" => "--area-m",
        "duration_s" => "--duration",
        "rate_hz" => "--rate",
        "vehicles * duration_s * rate_hz" => "--vehicles × --duration × --rate",
        "spoofer.lat_deg" => "--spoofer-lat",
        "spoofer.lon_deg" => "--spoofer-lon",
        "spoofer.radius_m" => "--radius-m",
        "spoofer.start_s" => "--start",
        "spoofer.duration_s" => "--attack-duration",
        "spoofer.attack.lat_deg" => "--false-lat",
        "spoofer.attack.lon_deg" => "--false-lon",
        "spoofer.attack.east_m" => "--east-m",
        "spoofer.attack.north_m" => "--north-m",
        "spoofer.attack.east_mps" => "--east-mps",
        "spoofer.attack.north_mps" => "--north-mps",
        "spoofer.attack" => "--attack",
        _ => return None,
    })
}

pub fn run(cmd: Command) -> Result<()> {
    match cmd {
        Command::Simulate(args) => simulate(args),
        Command::Inject(args) => inject_into_data(args),
        Command::Sweep(args) => sweep(args),
        Command::Fleet(args) => fleet(args),
    }
}

fn fleet(args: FleetArgs) -> Result<()> {
    let spec = args.spec()?;
    let scene = generate_fleet(&spec).context("generating the fleet scene")?;
    let file = std::fs::File::create(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    write_tracks(std::io::BufWriter::new(file), &scene.tracks)
        .with_context(|| format!("writing {}", args.out.display()))?;
    write_json(&args.truth, &scene.truth)?;
    let truth = &scene.truth;
    let rows: usize = scene.tracks.iter().map(|t| t.records.len()).sum();
    let routed = truth.vehicles.iter().filter(|v| v.routed_through).count();
    eprintln!(
        "wrote {} vehicles, {rows} rows ({} spoofed) to {}; {} vehicles captured ({routed} routed \
         through the spoofed area); ground truth in {}",
        scene.tracks.len(),
        truth.spoofed_rows,
        args.out.display(),
        truth.captured_vehicles,
        args.truth.display()
    );
    Ok(())
}

/// Drives `sim0`, `sim1`, … with the specs `spec_of(seed)`, `spec_of(seed + 1)`, ….
fn drives(count: u64, seed: u64, spec_of: impl Fn(u64) -> DriveSpec) -> Result<Vec<Track>> {
    (0..count)
        .map(|k| {
            let vehicle_id = format!("sim{k}");
            simulate_drive(&spec_of(seed.wrapping_add(k)), &vehicle_id)
                .with_context(|| format!("simulating {vehicle_id}"))
        })
        .collect()
}

fn normal_bases(paths: &[PathBuf]) -> Result<Vec<Track>> {
    Ok(load_tracks(paths)?.iter().flat_map(normal_runs).collect())
}

fn simulate(args: SimulateArgs) -> Result<()> {
    let duration_s = args.duration;
    let bases = if args.realistic {
        let distribution = DriveDistribution::realistic();
        drives(args.vehicles, args.seed, |seed| DriveSpec {
            duration_s,
            ..distribution.draw(seed)
        })?
    } else {
        drives(args.vehicles, args.seed, |seed| DriveSpec {
            duration_s,
            rate_hz: args.rate,
            seed,
            ..DriveSpec::default()
        })?
    };
    let (tracks, injected) = match (args.attack, args.onset) {
        (Some(family), Some(onset)) => {
            let spec = AttackArgs {
                attack: family,
                magnitude: args.magnitude,
                hold: args.hold,
                direction: args.direction,
                onset,
                duration: args.attack_duration,
            }
            .spec()?;
            let injected = inject_all(&bases, &spec)?;
            (injected.iter().map(|i| i.track.clone()).collect(), injected)
        }
        _ => (bases, Vec::new()),
    };
    write_output(&args.out, &tracks, &injected, args.manifest.as_ref())
}

fn inject_all(bases: &[Track], spec: &AttackSpec) -> Result<Vec<InjectedTrack>> {
    bases
        .iter()
        .map(|b| inject(b, spec).with_context(|| format!("injecting into {}", b.vehicle_id)))
        .collect()
}

fn inject_into_data(args: InjectArgs) -> Result<()> {
    let spec = args.attack.spec()?;
    let bases = normal_bases(&args.data)?;
    let injected = inject_all(&bases, &spec)?;
    let tracks: Vec<Track> = injected.iter().map(|i| i.track.clone()).collect();
    write_output(&args.out, &tracks, &injected, args.manifest.as_ref())
}

fn sweep(args: SweepArgs) -> Result<()> {
    let mut bases = normal_bases(&args.data)?;
    bases.extend(drives(args.drives, args.seed, |seed| DriveSpec {
        duration_s: args.drive_duration,
        seed,
        ..DriveSpec::default()
    })?);
    if bases.is_empty() {
        bail!("no bases: give --data with normal rows and/or --drives N");
    }
    let plan = ScenarioPlan::ramp_sweep(
        &args.velocities,
        AttackDuration::Seconds(args.duration),
        args.repeats,
        args.seed,
    );
    let injected = generate(&bases, &plan).context("generating the sweep")?;
    let tracks: Vec<Track> = injected.iter().map(|i| i.track.clone()).collect();
    write_output(&args.out, &tracks, &injected, args.manifest.as_ref())
}

fn write_output(
    out: &PathBuf,
    tracks: &[Track],
    injected: &[InjectedTrack],
    manifest: Option<&PathBuf>,
) -> Result<()> {
    let file = std::fs::File::create(out).with_context(|| format!("creating {}", out.display()))?;
    write_tracks(std::io::BufWriter::new(file), tracks)
        .with_context(|| format!("writing {}", out.display()))?;
    let rows: usize = tracks.iter().map(|t| t.records.len()).sum();
    eprintln!(
        "wrote {} vehicles, {rows} rows ({} attacked) to {}",
        tracks.len(),
        injected.len(),
        out.display()
    );
    if let Some(path) = manifest {
        let entries: Vec<_> = injected
            .iter()
            .map(|i| {
                serde_json::json!({
                    "vehicle_id": i.track.vehicle_id,
                    "base_vehicle_id": i.base_vehicle_id,
                    "attack": i.attack,
                    "onset_timestamp_s": i.onset_timestamp_s(),
                    "first_attack_row": i.first_attack_row,
                    "last_attack_row": i.last_attack_row,
                })
            })
            .collect();
        write_json(path, &entries)?;
    }
    Ok(())
}
