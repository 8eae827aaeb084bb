//! Experiment "incidents": regional spoofing replayed through the real server (an in-process server,
//! its correlator on the vehicles' sample clock), and clean fleets with independent attacks.
//!
//! - **Spoofed areas.** For each attack (a common translation, a common false position, a common
//!   drift) and seed, a fleet scene (`scenario::generate_fleet`: N vehicles, about K routed through
//!   the spoofer's circle) is replayed, every vehicle on its own stream, paced so that the vehicles
//!   advance together. Reported: the captured vehicles (ground truth), the share alarmed during
//!   their capture (or within 30 s of its end), their median delay from capture to alarm, the time
//!   from the first capture to the incident, how many incidents opened and whether their vehicles
//!   were captured ones. Each scene is replayed twice, without and with the area prior
//!   (`--incident-prior`); the vehicles captured after the incident opened are the ones it can help.
//! - **Clean fleets.** A scene whose spoofer captures no one, with independent attacks (jumps and
//!   drifts in random directions, at random times) injected into a share of its vehicles: every
//!   alarm is one vehicle's own. Reported: vehicle-hours, alarm onsets, and incidents (there must be
//!   none), one fleet per seed.
//! - **The prior's cost.** Attack-free hour-long drives at 1, 5 and 10 Hz scored by the bundled
//!   model as if inside an open incident's area throughout, against their own evidence alone, at
//!   both levels: the alarm onsets (every episode opens as a warning at least) and the escalations
//!   to critical. The prior may speed the warning; it must never make an alarm critical.
//!
//! It owns the scenes' setup, the replay and the tallies; the correlation is the server's.

use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use serde::Serialize;
use spoofwatch_client::connection::Connection;
use spoofwatch_client::replay::{ReplayEvent, ReplayOptions, replay_tracks, server_vehicle_id};
use spoofwatch_core::detector::Detector;
use spoofwatch_core::model::artifact::ModelArtifact;
use spoofwatch_core::rng::Rng;
use spoofwatch_core::scenario::{
    AttackKind, AttackSpec, DriveDistribution, DriveSpec, FleetScene, FleetSpec, RegionalAttack,
    Spoofer, generate_fleet, inject, simulate_drive,
};
use spoofwatch_proto::v1;
use spoofwatch_server::config::IncidentTimeline;
use spoofwatch_server::inprocess::InProcessServer;
use tokio::sync::mpsc;

use super::parallel::{default_threads, map_parallel};

/// An alarm this long after a capture's end still answers it (the spoofer's exit).
const ANSWER_GRACE_S: f64 = 30.0;

#[derive(Debug, clap::Args)]
pub struct Args {
    /// Output directory (report.md, report.json).
    #[arg(long)]
    out: PathBuf,
    /// Scene seeds (each attack is run once per seed).
    #[arg(long, value_delimiter = ',', default_value = "1,2,3")]
    seeds: Vec<u64>,
    /// Vehicles per spoofed scene, and how many are routed through the spoofer's circle.
    #[arg(long, default_value_t = 200)]
    vehicles: usize,
    #[arg(long, default_value_t = 30)]
    pass_through: usize,
    /// Length of a spoofed scene (s); the spoofer is active from a quarter to three quarters of it.
    #[arg(long, default_value_t = 1_800.0)]
    duration_s: f64,
    /// Vehicles and hours of the clean fleet (0 vehicles: none).
    #[arg(long, default_value_t = 500)]
    clean_vehicles: usize,
    #[arg(long, default_value_t = 2.0)]
    clean_hours: f64,
    /// Share of the clean fleet's vehicles with one independent attack.
    #[arg(long, default_value_t = 0.2)]
    independent_share: f64,
    /// Samples per second each vehicle is replayed at (all vehicles together advance at this pace).
    #[arg(long, default_value_t = 40.0)]
    pace_hz: f64,
    /// Attack-free one-hour drives per sample rate (1, 5 and 10 Hz) that measure what the area
    /// prior costs: each is scored as if it spent the whole hour inside an open incident's area.
    #[arg(long, default_value_t = 30)]
    prior_drives: u64,
    /// The distribution those drives are drawn from: `realistic`, or `fleet` (the one the bundled
    /// model's critical test was chosen and measured on).
    #[arg(long, default_value = "realistic", value_parser = ["realistic", "fleet"])]
    prior_distribution: String,
    /// Measure only the prior's cost (no spoofed scenes, no clean fleets).
    #[arg(long)]
    prior_only: bool,
}

/// One spoofed scene's result.
#[derive(Debug, Serialize)]
struct SceneRow {
    attack: &'static str,
    seed: u64,
    /// Scored with the area prior (the server's `--incident-prior`).
    prior: bool,
    vehicles: usize,
    captured: usize,
    captured_alarmed: usize,
    median_delay_s: Option<f64>,
    /// Captured after the first incident opened: how many, and their median delay (the vehicles
    /// the prior can help).
    captured_later: usize,
    later_median_delay_s: Option<f64>,
    first_capture_s: Option<f64>,
    /// From the first capture to the first incident's confirmation (sample clock).
    time_to_incident_s: Option<f64>,
    incidents: usize,
    incident_kinds: Vec<String>,
    incident_vehicles: usize,
    /// Vehicles in an incident that were never captured.
    uncaptured_in_incidents: usize,
    alarm_onsets: usize,
    /// Onsets outside every capture of their vehicle (and its grace after the capture's end).
    other_onsets: usize,
}

/// The clean fleet's result.
#[derive(Debug, Serialize)]
struct CleanRow {
    seed: u64,
    vehicles: usize,
    vehicle_hours: f64,
    independently_attacked: usize,
    alarm_onsets: usize,
    incidents: usize,
}

/// What the area prior costs at one sample rate: attack-free drives scored on their own evidence and
/// as if inside an open incident's area throughout.
#[derive(Debug, Serialize)]
struct PriorCostRow {
    rate_hz: f64,
    hours: f64,
    /// Alarm onsets (the warning level: every episode opens as one) outside and inside the area.
    onsets_without: usize,
    onsets_with: usize,
    /// Escalations to critical outside and inside the area.
    critical_without: usize,
    critical_with: usize,
    /// Drives that escalated more often inside the area than outside.
    drives_more_critical_with: usize,
}

#[derive(Debug, Serialize)]
struct Report {
    scenes: Vec<SceneRow>,
    clean: Vec<CleanRow>,
    prior_cost: Vec<PriorCostRow>,
}

pub fn run(args: Args) -> Result<()> {
    if args.pass_through > args.vehicles || args.seeds.is_empty() {
        bail!("--pass-through must be at most --vehicles, and --seeds must name at least one seed");
    }
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    let runtime = tokio::runtime::Runtime::new()?;
    let mut report = Report {
        scenes: Vec::new(),
        clean: Vec::new(),
        prior_cost: prior_cost(args.prior_drives, &args.prior_distribution)?,
    };
    for row in &report.prior_cost {
        println!("{row:?}");
    }
    let seeds: &[u64] = if args.prior_only { &[] } else { &args.seeds };
    for &seed in seeds {
        for (name, attack) in attacks() {
            let spec = spoofed_spec(&args, seed, attack);
            let scene = generate_fleet(&spec).context("generating the scene")?;
            for prior in [false, true] {
                let row = runtime.block_on(spoofed_scene(&args, name, seed, prior, &scene))?;
                println!("{row:?}");
                report.scenes.push(row);
            }
        }
    }
    if args.clean_vehicles > 0 {
        for &seed in seeds {
            let row = runtime.block_on(clean_fleet(&args, seed))?;
            println!("{row:?}");
            report.clean.push(row);
        }
    }
    std::fs::write(
        args.out.join("report.json"),
        serde_json::to_string_pretty(&report)?,
    )?;
    std::fs::write(args.out.join("report.md"), markdown(&args, &report))?;
    println!("wrote {}", args.out.join("report.md").display());
    Ok(())
}

/// The three regional attacks.
fn attacks() -> [(&'static str, RegionalAttack); 3] {
    [
        (
            "translation 150 m",
            RegionalAttack::Translation {
                east_m: 120.0,
                north_m: 90.0,
            },
        ),
        (
            "false position",
            RegionalAttack::Position {
                lat_deg: 32.26,
                lon_deg: -110.88,
            },
        ),
        (
            "drift 1.5 m/s",
            RegionalAttack::Drift {
                east_mps: -0.9,
                north_mps: 1.2,
            },
        ),
    ]
}

fn spoofed_spec(args: &Args, seed: u64, attack: RegionalAttack) -> FleetSpec {
    FleetSpec {
        vehicles: args.vehicles,
        pass_through: args.pass_through,
        duration_s: args.duration_s,
        spoofer: Spoofer {
            start_s: args.duration_s / 4.0,
            duration_s: args.duration_s / 2.0,
            attack,
            ..Spoofer::default()
        },
        seed,
        ..FleetSpec::default()
    }
}

/// What a replay through a fresh server gives: each vehicle's alarm onsets (recorded sample times)
/// and the stored incidents.
struct Replayed {
    onsets: HashMap<String, Vec<f64>>,
    incidents: Vec<v1::Incident>,
}

async fn replay(
    args: &Args,
    prior: bool,
    tracks: Vec<spoofwatch_core::sample::Track>,
) -> Result<Replayed> {
    let server = InProcessServer::start(|config| {
        config.incident_timeline = IncidentTimeline::Samples;
        config.incident_prior = prior;
    })
    .await?;
    let connection = Connection::connect(server.url(), None).await?;
    let options = ReplayOptions {
        rate_hz: args.pace_hz,
        batch_size: 10,
        ..ReplayOptions::default()
    };
    let (tx, mut rx) = mpsc::channel(4_096);
    let collect = tokio::spawn(async move {
        let mut onsets: HashMap<String, Vec<f64>> = HashMap::new();
        while let Some(event) = rx.recv().await {
            if let ReplayEvent::Detection(d) = event
                && d.detection.alarm_onset
            {
                onsets
                    .entry(d.vehicle_id)
                    .or_default()
                    .push(d.recorded_timestamp_s);
            }
        }
        onsets
    });
    let started = Instant::now();
    for result in replay_tracks(&connection, tracks, &options, tx).await {
        result.context("a vehicle's replay")?;
    }
    let onsets = collect.await?;
    // The correlator runs every second on the stored alarms: give it a few rounds.
    tokio::time::sleep(Duration::from_secs(4)).await;
    let mut alarms = connection.alarms();
    let incidents = alarms
        .list_incidents(v1::ListIncidentsRequest {
            page_size: 500,
            ..v1::ListIncidentsRequest::default()
        })
        .await?
        .into_inner()
        .incidents;
    eprintln!("replayed in {:.0} s", started.elapsed().as_secs_f64());
    for incident in &incidents {
        eprintln!("{incident:?}");
    }
    server.shutdown().await?;
    Ok(Replayed { onsets, incidents })
}

async fn spoofed_scene(
    args: &Args,
    attack: &'static str,
    seed: u64,
    prior: bool,
    scene: &FleetScene,
) -> Result<SceneRow> {
    let replayed = replay(args, prior, scene.tracks.clone()).await?;
    let first_confirmed = replayed
        .incidents
        .iter()
        .map(|i| i.confirmed_s)
        .fold(None, |acc: Option<f64>, t| {
            Some(acc.map_or(t, |a| a.min(t)))
        });
    let mut delays = Vec::new();
    let mut later_delays = Vec::new();
    let mut captured_later = 0;
    let mut first_capture: Option<f64> = None;
    let mut captured_ids = Vec::new();
    let answers_a_capture = |vehicle: &spoofwatch_core::scenario::VehicleTruth, t: f64| {
        vehicle
            .captures
            .iter()
            .any(|c| t >= c.start.timestamp_s && t <= c.end.timestamp_s + ANSWER_GRACE_S)
    };
    let other_onsets = scene
        .truth
        .vehicles
        .iter()
        .map(|vehicle| {
            let id = server_vehicle_id(&vehicle.vehicle_id);
            replayed.onsets.get(&id).map_or(0, |onsets| {
                onsets
                    .iter()
                    .filter(|&&t| !answers_a_capture(vehicle, t))
                    .count()
            })
        })
        .sum();
    for vehicle in scene.truth.vehicles.iter().filter(|v| v.captured) {
        let id = server_vehicle_id(&vehicle.vehicle_id);
        let onsets = replayed.onsets.get(&id).map(Vec::as_slice).unwrap_or(&[]);
        let capture = &vehicle.captures[0];
        let start = capture.start.timestamp_s;
        first_capture = Some(first_capture.map_or(start, |f: f64| f.min(start)));
        let later = first_confirmed.is_some_and(|confirmed| start > confirmed);
        captured_later += usize::from(later);
        if let Some(onset) = onsets
            .iter()
            .copied()
            .find(|&t| t >= start && t <= capture.end.timestamp_s + ANSWER_GRACE_S)
        {
            delays.push(onset - start);
            if later {
                later_delays.push(onset - start);
            }
        }
        captured_ids.push(id);
    }
    let incident_vehicles: Vec<&str> = replayed
        .incidents
        .iter()
        .flat_map(|i| i.vehicles.iter().map(|v| v.vehicle_id.as_str()))
        .collect();
    Ok(SceneRow {
        attack,
        seed,
        prior,
        vehicles: scene.tracks.len(),
        captured: captured_ids.len(),
        captured_alarmed: delays.len(),
        median_delay_s: median(&mut delays),
        captured_later,
        later_median_delay_s: median(&mut later_delays),
        first_capture_s: first_capture,
        time_to_incident_s: first_confirmed.zip(first_capture).map(|(c, f)| c - f),
        incidents: replayed.incidents.len(),
        incident_kinds: replayed
            .incidents
            .iter()
            .map(|i| i.kind().as_str_name().to_string())
            .collect(),
        incident_vehicles: incident_vehicles.len(),
        uncaptured_in_incidents: incident_vehicles
            .iter()
            .filter(|v| !captured_ids.iter().any(|c| c == *v))
            .count(),
        alarm_onsets: replayed.onsets.values().map(Vec::len).sum(),
        other_onsets,
    })
}

async fn clean_fleet(args: &Args, seed: u64) -> Result<CleanRow> {
    let duration_s = args.clean_hours * 3_600.0;
    // The spoofer sits 500 km away: it captures no one.
    let spec = FleetSpec {
        vehicles: args.clean_vehicles,
        pass_through: 0,
        duration_s,
        spoofer: Spoofer {
            lat_deg: 36.7,
            radius_m: 10.0,
            start_s: 0.0,
            duration_s,
            ..Spoofer::default()
        },
        seed: seed + 1_000,
        ..FleetSpec::default()
    };
    let scene = generate_fleet(&spec).context("generating the clean fleet")?;
    let mut rng = Rng::seed_from_u64(seed ^ 0x1d3f);
    let mut tracks = scene.tracks;
    let mut attacked = 0;
    for track in &mut tracks {
        if rng.uniform() >= args.independent_share {
            continue;
        }
        let kind = if rng.uniform() < 0.5 {
            AttackKind::Jump {
                offset_m: 30.0 + 470.0 * rng.uniform(),
            }
        } else {
            AttackKind::RampDrift {
                velocity_mps: 0.5 + 1.5 * rng.uniform(),
            }
        };
        let direction_deg = 360.0 * rng.uniform() % 360.0;
        // An attack lies inside one trajectory: a few onsets are tried around the drive's outages.
        let injected = (0..5).find_map(|_| {
            let attack = AttackSpec {
                kind,
                direction_deg,
                onset_s: 300.0 + (duration_s - 900.0) * rng.uniform(),
                duration_s: 300.0,
                seed: None,
            };
            inject(track, &attack).ok()
        });
        let Some(injected) = injected else {
            continue;
        };
        let vehicle_id = track.vehicle_id.clone();
        *track = injected.track;
        track.vehicle_id = vehicle_id;
        attacked += 1;
    }
    let replayed = replay(args, true, tracks).await?;
    Ok(CleanRow {
        seed,
        vehicles: args.clean_vehicles,
        vehicle_hours: args.clean_vehicles as f64 * args.clean_hours,
        independently_attacked: attacked,
        alarm_onsets: replayed.onsets.values().map(Vec::len).sum(),
        incidents: replayed.incidents.len(),
    })
}

/// Sample rates the prior's cost is measured at (Hz).
const PRIOR_RATES_HZ: [f64; 3] = [1.0, 5.0, 10.0];
/// Length of a drive that measures the prior's cost (s).
const PRIOR_DRIVE_S: f64 = 3_600.0;

/// The bundled model's alarm onsets and escalations to critical on `drives` attack-free hour-long
/// drives of `distribution` per rate, scored on their own evidence and as if inside an open
/// incident's area throughout (the worst case: a vehicle that never leaves the area).
fn prior_cost(drives: u64, distribution: &str) -> Result<Vec<PriorCostRow>> {
    let model = Arc::new(
        ModelArtifact::from_slice(include_bytes!("../../../models/default.json"))
            .context("the bundled model")?,
    );
    let distribution = match distribution {
        "fleet" => DriveDistribution::fleet(),
        _ => DriveDistribution::realistic(),
    };
    let seeds: Vec<u64> = (0..drives).collect();
    PRIOR_RATES_HZ
        .iter()
        .map(|&rate_hz| {
            let counts = map_parallel(&seeds, default_threads(), |&seed| {
                let spec = DriveSpec {
                    duration_s: PRIOR_DRIVE_S,
                    rate_hz,
                    ..distribution.draw(0x9121_0000 + seed)
                };
                let track = simulate_drive(&spec, &format!("prior-{rate_hz}hz-{seed}"))?;
                // (alarm onsets, escalations to critical)
                let levels = |in_area: bool| {
                    let mut detector = Detector::new(Arc::clone(&model));
                    track.records.iter().fold((0, 0), |(onsets, critical), r| {
                        let decision =
                            detector.step_with_prior(&r.sample, r.trajectory_break, in_area);
                        (
                            onsets + usize::from(decision.alarm_onset),
                            critical + usize::from(decision.escalation),
                        )
                    })
                };
                Ok::<_, anyhow::Error>((levels(false), levels(true)))
            });
            let counts = counts.into_iter().collect::<Result<Vec<_>>>()?;
            Ok(PriorCostRow {
                rate_hz,
                hours: drives as f64 * PRIOR_DRIVE_S / 3_600.0,
                onsets_without: counts.iter().map(|c| c.0.0).sum(),
                onsets_with: counts.iter().map(|c| c.1.0).sum(),
                critical_without: counts.iter().map(|c| c.0.1).sum(),
                critical_with: counts.iter().map(|c| c.1.1).sum(),
                drives_more_critical_with: counts.iter().filter(|c| c.1.1 > c.0.1).count(),
            })
        })
        .collect()
}

/// The one-sided 95 % upper confidence bound of a Poisson mean after `events` events: the mean
/// under which `events` or fewer occur with probability 0.05 (3.0 for none, the rule of three).
fn poisson_upper_95(events: usize) -> f64 {
    let at_most = |mean: f64| {
        let mut term = (-mean).exp();
        let mut sum = term;
        for k in 1..=events {
            term *= mean / k as f64;
            sum += term;
        }
        sum
    };
    let (mut low, mut high) = (0.0, 10.0 + 4.0 * events as f64);
    for _ in 0..100 {
        let middle = 0.5 * (low + high);
        if at_most(middle) > 0.05 {
            low = middle;
        } else {
            high = middle;
        }
    }
    high
}

fn median(values: &mut [f64]) -> Option<f64> {
    if values.is_empty() {
        return None;
    }
    values.sort_by(f64::total_cmp);
    let middle = values.len() / 2;
    Some(if values.len() % 2 == 1 {
        values[middle]
    } else {
        0.5 * (values[middle - 1] + values[middle])
    })
}

fn markdown(args: &Args, report: &Report) -> String {
    let opt = |v: Option<f64>| v.map_or_else(|| "–".to_string(), |v| format!("{v:.0}"));
    let mut out = format!(
        "# Incidents\n\n`spoofwatch-lab experiment incidents --seeds {} --vehicles {} --pass-through {} \
         --duration-s {} --clean-vehicles {} --clean-hours {} --pace-hz {} --prior-drives {} \
         --prior-distribution {}{}`\n\n\
         | attack | seed | prior | captured | alarmed | median delay (s) | captured after the incident | their median delay (s) | time to incident (s) | incidents | in incident | not captured |\n\
         |---|---|---|---|---|---|---|---|---|---|---|---|\n",
        args.seeds
            .iter()
            .map(u64::to_string)
            .collect::<Vec<_>>()
            .join(","),
        args.vehicles,
        args.pass_through,
        args.duration_s,
        args.clean_vehicles,
        args.clean_hours,
        args.pace_hz,
        args.prior_drives,
        args.prior_distribution,
        if args.prior_only { " --prior-only" } else { "" },
    );
    for r in &report.scenes {
        out.push_str(&format!(
            "| {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} |\n",
            r.attack,
            r.seed,
            if r.prior { "on" } else { "off" },
            r.captured,
            r.captured_alarmed,
            opt(r.median_delay_s),
            r.captured_later,
            opt(r.later_median_delay_s),
            opt(r.time_to_incident_s),
            r.incidents,
            r.incident_vehicles,
            r.uncaptured_in_incidents,
        ));
    }
    out.push_str(
        "\n| clean fleet seed | vehicles | vehicle-hours | independently attacked | alarm onsets | incidents |\n|---|---|---|---|---|---|\n",
    );
    for r in &report.clean {
        out.push_str(&format!(
            "| {} | {} | {:.0} | {} | {} | {} |\n",
            r.seed,
            r.vehicles,
            r.vehicle_hours,
            r.independently_attacked,
            r.alarm_onsets,
            r.incidents
        ));
    }
    out.push_str(
        "\nThe area prior's cost: attack-free hour-long drives scored as if inside an open incident's \
         area throughout, and on their own evidence alone (outside); per vehicle-hour (events), with the \
         one-sided 95 % upper bound of the critical rate.\n\n\
         | rate | hours | warning outside | warning inside | critical outside | critical inside | drives more critical inside |\n\
         |---|---|---|---|---|---|---|\n",
    );
    let level = |events: usize, hours: f64| format!("{:.2} ({events})", events as f64 / hours);
    let critical = |events: usize, hours: f64| {
        format!(
            "{:.4} ({events}; ≤ {:.4})",
            events as f64 / hours,
            poisson_upper_95(events) / hours
        )
    };
    let pooled = PriorCostRow {
        rate_hz: 0.0,
        hours: report.prior_cost.iter().map(|r| r.hours).sum(),
        onsets_without: report.prior_cost.iter().map(|r| r.onsets_without).sum(),
        onsets_with: report.prior_cost.iter().map(|r| r.onsets_with).sum(),
        critical_without: report.prior_cost.iter().map(|r| r.critical_without).sum(),
        critical_with: report.prior_cost.iter().map(|r| r.critical_with).sum(),
        drives_more_critical_with: report
            .prior_cost
            .iter()
            .map(|r| r.drives_more_critical_with)
            .sum(),
    };
    for r in report.prior_cost.iter().chain([&pooled]) {
        let rate = if r.rate_hz > 0.0 {
            format!("{} Hz", r.rate_hz)
        } else {
            "all".to_string()
        };
        out.push_str(&format!(
            "| {rate} | {:.0} | {} | {} | {} | {} | {} |\n",
            r.hours,
            level(r.onsets_without, r.hours),
            level(r.onsets_with, r.hours),
            critical(r.critical_without, r.hours),
            critical(r.critical_with, r.hours),
            r.drives_more_critical_with,
        ));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_poisson_bound_is_the_tabulated_one() {
        // Garwood's one-sided 95 % upper limits for 0, 1, 2 and 10 events.
        for (events, bound) in [(0, 2.996), (1, 4.744), (2, 6.296), (10, 16.962)] {
            assert!(
                (poisson_upper_95(events) - bound).abs() < 0.01,
                "{events}: {}",
                poisson_upper_95(events)
            );
        }
    }
}
