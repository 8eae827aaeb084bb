//! `spoofwatch detect`: replay a recording over StreamDetect, one concurrent stream per vehicle
//! (optionally reconnecting), printing detections as they arrive and a fleet summary at the end.
//!
//! Replay and the stream protocol belong to `crate::replay` and `DetectStream`, the
//! summary's tally to `crate::fleet`; this module owns only the flags and the
//! console/CSV/JSON output. The console shows replies as they arrive (failovers included); the CSV
//! and the fleet summary are made at the end from the final rows (`ReplayLog`: one detection per
//! recorded row, resent rows replacing earlier ones).

use std::collections::HashMap;
use std::path::PathBuf;
use std::time::Duration;

use crate::error::describe_rpc_status;
use crate::failover::DEFAULT_FAILOVER_S;
use crate::fleet::{FleetSummary, FleetTally, OnsetCounts, WorstVehicle};
use crate::input::load_tracks;
use crate::replay::{
    ReplayEvent, ReplayOptions, ReplaySummary, ReplayedDetection, batch_due_times,
    replay_tracks_over, server_vehicle_id,
};
use crate::replay_log::ReplayLog;
use crate::timeline::{Timeline, TimelineRow};
use anyhow::{Context, Result, bail};
use spoofwatch_core::sample::Track;
use spoofwatch_proto::v1;
use spoofwatch_proto::wire::limits::MAX_BATCH_SAMPLES;
use tokio::sync::mpsc;

use crate::cli::json::write_json;
use crate::cli::server_flags::ServerArgs;

#[derive(Debug, clap::Args)]
pub struct Args {
    #[command(flatten)]
    pub server: ServerArgs,
    /// Recorded data to replay (AV-GPS or telemetry CSV); every vehicle gets its own stream.
    #[arg(long, required = true, num_args = 1..)]
    pub data: Vec<PathBuf>,
    /// Samples per second per vehicle; 0 sends as fast as the server answers.
    #[arg(long, default_value_t = 0.0, value_parser = parse_rate)]
    pub rate: f64,
    /// Samples per batch (1 to 1000).
    #[arg(long, default_value_t = 1, value_parser = parse_batch)]
    pub batch: usize,
    /// Model to use (`models/{id}` or `{id}`); default: the server's active model.
    #[arg(long)]
    pub model: Option<String>,
    /// Write every detection as CSV (vehicle_id, line, timestamp_s, probability, positive, alarm,
    /// alarm_onset, valid, why, offset_m, offset_bearing_deg, drift_mps, drift_bearing_deg,
    /// model, severity); timestamp_s is the recorded one, `why` the dominant evidence (empty from
    /// a server that does not explain), bearings in degrees clockwise from north, `model` the one
    /// that made the detection (`models/{id}`), `severity` the open alarm's (`warning`,
    /// `critical`; empty while no alarm is on).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Print only alarm onsets, escalations to critical and ends, and the per-vehicle and fleet
    /// summaries.
    #[arg(long)]
    pub quiet: bool,
    /// Reconnect every vehicle after about this many seconds of recorded time (0: never), as when
    /// its cellular link drops: the stream is closed and a new one opened with
    /// SessionStart{reset: false}, which resumes the vehicle's session on the server, and the
    /// replay goes on with the next sample. Each interval is drawn from 0.5–1.5 × this value,
    /// per vehicle, from --seed.
    #[arg(long, value_name = "SECONDS", default_value_t = 0.0, value_parser = parse_reconnect_every)]
    pub reconnect_every: f64,
    /// Seed of the reconnect times (with the vehicle id: the same vehicle and seed reconnect at the
    /// same samples).
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// When a vehicle's stream fails because its server went away (a replica died or drained),
    /// keep reconnecting for up to this many seconds (with backoff), then resend every batch the
    /// server's session has not seen (from SessionAccepted.last_seq; the whole recording on a
    /// replica without the session). 0: fail at once.
    #[arg(long, value_name = "SECONDS", default_value_t = DEFAULT_FAILOVER_S, value_parser = parse_failover_secs)]
    pub failover_secs: f64,
    /// Also write the fleet summary (samples, attack-free hours, false-alarm onsets by where they
    /// start, detections, worst vehicles) as JSON.
    #[arg(long, value_name = "PATH")]
    pub summary: Option<PathBuf>,
    /// With --rate: print, and write to this CSV, the delivery interval by interval (samples due,
    /// delivered, on time, latency p50/p99/max from when each batch was due; see
    /// --timeline-every).
    #[arg(long, value_name = "PATH")]
    pub timeline: Option<PathBuf>,
    /// Vehicles' streams sharing one HTTP/2 connection; more vehicles open more connections (a
    /// connection carries at most about a thousand concurrent streams: HAProxy's limit is 1,000,
    /// the server's 1,024).
    #[arg(long, default_value_t = 500, value_parser = clap::value_parser!(u32).range(1..=1000))]
    pub streams_per_connection: u32,
    /// The timeline's interval in seconds.
    #[arg(long, value_name = "SECONDS", default_value_t = 60.0, value_parser = parse_interval)]
    pub timeline_every: f64,
}

/// A timeline interval in seconds: finite and > 0.
pub fn parse_interval(text: &str) -> Result<f64, String> {
    match parse_reconnect_every(text)? {
        0.0 => Err("must be more than 0 seconds".to_string()),
        seconds => Ok(seconds),
    }
}

/// A reconnect interval in seconds: finite and ≥ 0.
pub fn parse_reconnect_every(text: &str) -> Result<f64, String> {
    let seconds: f64 = text
        .parse()
        .map_err(|_| format!("{text:?} is not a number"))?;
    if !(seconds.is_finite() && seconds >= 0.0) {
        return Err(format!("must be a finite time ≥ 0 in seconds, got {text}"));
    }
    Ok(seconds)
}

/// A failover deadline in seconds: finite and ≥ 0.
pub fn parse_failover_secs(text: &str) -> Result<f64, String> {
    parse_reconnect_every(text)
}

/// A rate in Hz: finite and ≥ 0.
pub fn parse_rate(text: &str) -> Result<f64, String> {
    let rate: f64 = text
        .parse()
        .map_err(|_| format!("{text:?} is not a number"))?;
    if !(rate.is_finite() && rate >= 0.0) {
        return Err(format!("must be a finite rate ≥ 0 in Hz, got {text}"));
    }
    Ok(rate)
}

/// A batch size from 1 to 1000.
pub fn parse_batch(text: &str) -> Result<usize, String> {
    let batch: usize = text
        .parse()
        .map_err(|_| format!("{text:?} is not a whole number"))?;
    if !(1..=MAX_BATCH_SAMPLES).contains(&batch) {
        return Err(format!(
            "must be 1 to {MAX_BATCH_SAMPLES} samples, got {batch}"
        ));
    }
    Ok(batch)
}

/// The CSV columns of `--out`.
const CSV_HEADER: [&str; 15] = [
    "vehicle_id",
    "line",
    "timestamp_s",
    "probability",
    "positive",
    "alarm",
    "alarm_onset",
    "valid",
    "why",
    "offset_m",
    "offset_bearing_deg",
    "drift_mps",
    "drift_bearing_deg",
    "model",
    "severity",
];

fn flag(b: bool) -> &'static str {
    if b { "1" } else { "0" }
}

/// The snake_case name of a detection's dominant evidence (`none`, `jump`, …); `None` when the
/// detection carries no explanation (an older server) or an unknown kind.
pub fn why_name(why: Option<&v1::Explanation>) -> Option<&'static str> {
    let kind = v1::EvidenceKind::try_from(why?.dominant).ok()?;
    Some(match kind {
        v1::EvidenceKind::Unspecified => return None,
        v1::EvidenceKind::None => "none",
        v1::EvidenceKind::Jump => "jump",
        v1::EvidenceKind::HeldOffset => "held_offset",
        v1::EvidenceKind::Drift => "drift",
        v1::EvidenceKind::FrozenFix => "frozen_fix",
        v1::EvidenceKind::Energy => "energy",
    })
}

/// The lowercase name of a severity on the wire (`warning`, `critical`); `None` for UNSPECIFIED
/// (no alarm open) or a number this build does not know.
pub fn severity_name(severity: i32) -> Option<&'static str> {
    match v1::AlarmSeverity::try_from(severity).ok()? {
        v1::AlarmSeverity::Unspecified => None,
        v1::AlarmSeverity::Warning => Some("warning"),
        v1::AlarmSeverity::Critical => Some("critical"),
    }
}

/// `jump: offset 482.0 m toward 45°, drift 0.30 m/s toward 120°`, or `None` when nothing stands
/// out (or the detection carries no explanation).
pub fn why_text(why: Option<&v1::Explanation>) -> Option<String> {
    let name = why_name(why).filter(|name| *name != "none")?;
    let why = why?;
    Some(format!(
        "{name}: offset {:.1} m toward {:.0}°, drift {:.2} m/s toward {:.0}°",
        why.offset_m, why.offset_bearing_deg, why.drift_mps, why.drift_bearing_deg
    ))
}

/// One detection as a CSV row.
pub fn csv_row(d: &ReplayedDetection) -> [String; 15] {
    let det = &d.detection;
    let valid = det.evidence.as_ref().is_some_and(|e| e.valid);
    let why = det.why.as_ref();
    let number = |value: fn(&v1::Explanation) -> f64| {
        why.map(value).map_or_else(String::new, |v| v.to_string())
    };
    [
        d.vehicle_id.clone(),
        d.line.to_string(),
        d.recorded_timestamp_s.to_string(),
        det.probability.to_string(),
        flag(det.positive).into(),
        flag(det.alarm).into(),
        flag(det.alarm_onset).into(),
        flag(valid).into(),
        why_name(why).unwrap_or_default().to_string(),
        number(|w| w.offset_m),
        number(|w| w.offset_bearing_deg),
        number(|w| w.drift_mps),
        number(|w| w.drift_bearing_deg),
        d.model.to_string(),
        severity_name(det.severity).unwrap_or_default().to_string(),
    ]
}

/// One detection as a console line: `vehicle  t  p=0.123  ALARM onset  jump: offset 482.0 m
/// toward 45°, drift 0.30 m/s toward 120°` (the why only when something stands out); an alarm
/// that opens critical is `CRITICAL onset`, one that turns critical later `CRITICAL`.
pub fn console_line(d: &ReplayedDetection) -> String {
    let det = &d.detection;
    let marker = if det.alarm_onset && det.alarm_escalated {
        "CRITICAL onset"
    } else if det.alarm_onset {
        "ALARM onset"
    } else if det.alarm_escalated {
        "CRITICAL"
    } else if det.alarm {
        "ALARM"
    } else if det.alarm_end {
        "alarm end"
    } else {
        ""
    };
    let why = why_text(det.why.as_ref()).unwrap_or_default();
    format!(
        "{:<20} {:>14.2}  p={:.3}  {marker:<11}  {why}",
        d.vehicle_id, d.recorded_timestamp_s, det.probability
    )
    .trim_end()
    .to_string()
}

/// One vehicle's summary line.
pub fn summary_line(s: &ReplaySummary) -> String {
    let latency = s.mean_latency().map_or_else(
        || "-".to_string(),
        |l| format!("{:.2} ms", l.as_secs_f64() * 1e3),
    );
    let reconnects = match s.reconnects() {
        0 => String::new(),
        n => format!(", {n} reconnects ({} resumed)", s.resumed_reconnects),
    };
    let failovers = match s.failovers {
        0 => String::new(),
        n => format!(", {n} failovers"),
    };
    format!(
        "{}: {} samples, {} detections, {} alarms ({} turned critical), {} rejected batches{reconnects}{failovers}, mean batch latency {latency}",
        s.vehicle_id,
        s.samples_sent,
        s.detections,
        s.alarm_onsets,
        s.critical_alarms,
        s.rejected_batches
    )
}

/// `n (s at session starts, g after gaps, e elsewhere)`.
fn onset_breakdown(counts: &OnsetCounts) -> String {
    format!("{} {}", counts.total(), places(counts))
}

/// `(s within 30 s of a session start, g within 30 s after a gap, e elsewhere)`.
fn places(counts: &OnsetCounts) -> String {
    format!(
        "({} within 30 s of a session start, {} within 30 s after a gap, {} elsewhere)",
        counts.session_start, counts.after_gap, counts.elsewhere
    )
}

/// One worst vehicle: its counts and the first few onsets.
fn worst_vehicle_line(v: &WorstVehicle) -> String {
    const SHOWN: usize = 5;
    let onsets: Vec<String> = v
        .onsets
        .iter()
        .take(SHOWN)
        .map(|o| {
            let stream = match (o.stream, o.on_resumed_stream) {
                (0, _) => "its first stream".to_string(),
                (k, true) => format!("reconnect {k}, resumed"),
                (k, false) => format!("reconnect {k}, afresh"),
            };
            format!(
                "line {} ({:.1} s into {stream})",
                o.line, o.after_stream_start_s
            )
        })
        .collect();
    let more = if v.onsets.len() > SHOWN { ", …" } else { "" };
    format!(
        "  {}: {} in {:.2} attack-free h; {}{more}",
        v.vehicle_id,
        onset_breakdown(&v.false_alarms),
        v.attack_free_hours,
        onsets.join(", ")
    )
}

/// The fleet summary as console lines.
pub fn fleet_lines(s: &FleetSummary) -> Vec<String> {
    let per_hour = |rate: Option<f64>| rate.map_or_else(|| "-".to_string(), |r| format!("{r:.2}"));
    let rate = per_hour(s.false_alarms_per_attack_free_hour);
    let critical_rate = per_hour(s.critical_false_alarms_per_attack_free_hour);
    let mut lines = vec![
        format!(
            "fleet: {} vehicles, {} samples, {:.2} attack-free hours; {} streams ({} reconnects, {} resumed, {} failovers, {} of them onto another model, {} replies lost with failed streams); {} GNSS gaps (> {} s)",
            s.vehicles,
            s.samples,
            s.attack_free_hours,
            s.streams,
            s.reconnects,
            s.resumed_reconnects,
            s.failovers,
            s.failovers_onto_another_model,
            s.replies_lost,
            s.gaps,
            s.gap_step_s
        ),
        format!(
            "false alarms (onsets on attack-free rows): {} on {} vehicles, {rate} per attack-free hour",
            onset_breakdown(&s.false_alarms),
            s.vehicles_with_false_alarms
        ),
        format!(
            "  of those at session starts, {} came soon after a reconnect that resumed the session (no restart for the detector)",
            s.session_start_onsets_on_resumed_streams
        ),
        format!(
            "detections (onsets on attacked rows): {}; onsets on unlabelled rows: {}",
            s.detections, s.unlabelled_onsets
        ),
        format!(
            "critical (paging) alarms: {} on attack-free rows {}, {critical_rate} per attack-free hour; {} on attacked rows",
            s.critical_false_alarms.total(),
            places(&s.critical_false_alarms),
            s.critical_detections
        ),
    ];
    if !s.worst_vehicles.is_empty() {
        lines.push("worst vehicles:".to_string());
        lines.extend(s.worst_vehicles.iter().map(worst_vehicle_line));
    }
    lines
}

/// The columns of `--timeline`.
const TIMELINE_HEADER: [&str; 9] = [
    "start_s",
    "end_s",
    "due",
    "delivered",
    "delivered_pct",
    "on_time_pct",
    "p50_ms",
    "p99_ms",
    "max_ms",
];

/// One timeline row for the console and the CSV (latencies empty when nothing was delivered).
fn timeline_cells(row: &TimelineRow) -> [String; 9] {
    let ms = |v: Option<f64>| v.map_or_else(String::new, |v| format!("{v:.2}"));
    [
        format!("{}", row.start_s),
        format!("{}", row.end_s),
        row.due.to_string(),
        row.delivered.to_string(),
        format!("{:.3}", row.delivered_pct()),
        format!("{:.3}", row.on_time_pct()),
        ms(row.p50_ms),
        ms(row.p99_ms),
        ms(row.max_ms),
    ]
}

/// Prints the timeline and writes it as CSV.
fn write_timeline(path: &std::path::Path, rows: &[TimelineRow]) -> Result<()> {
    let mut writer =
        csv::Writer::from_path(path).with_context(|| format!("creating {}", path.display()))?;
    writer.write_record(TIMELINE_HEADER)?;
    println!("timeline (latency from when each batch was due):");
    println!(
        "{:>8} {:>8} {:>9} {:>11} {:>10} {:>10} {:>10} {:>10}",
        "from s", "to s", "due", "delivered %", "on time %", "p50 ms", "p99 ms", "max ms"
    );
    for row in rows {
        let cells = timeline_cells(row);
        println!(
            "{:>8} {:>8} {:>9} {:>11} {:>10} {:>10} {:>10} {:>10}",
            cells[0], cells[1], cells[2], cells[4], cells[5], cells[6], cells[7], cells[8]
        );
        writer.write_record(&cells)?;
    }
    writer.flush()?;
    Ok(())
}

/// The vehicle ids the replay must rewrite for the server, as (recorded, sent) pairs; an error
/// when two recorded ids would become one (they would share, and fight over, one session).
fn renamed_vehicles(tracks: &[Track]) -> Result<Vec<(String, String)>> {
    let mut owner_of_sent: HashMap<String, &str> = HashMap::new();
    let mut renamed = Vec::new();
    for track in tracks {
        let sent = server_vehicle_id(&track.vehicle_id);
        if let Some(other) = owner_of_sent.insert(sent.clone(), &track.vehicle_id)
            && other != track.vehicle_id
        {
            bail!(
                "vehicles {other:?} and {:?} would both be sent as {sent:?}; rename one",
                track.vehicle_id
            );
        }
        if sent != track.vehicle_id {
            renamed.push((track.vehicle_id.clone(), sent));
        }
    }
    Ok(renamed)
}

pub async fn run(args: Args) -> Result<()> {
    let tracks = load_tracks(&args.data)?;
    if tracks.is_empty() {
        bail!("no vehicle data in the given files");
    }
    for (recorded, sent) in renamed_vehicles(&tracks)? {
        eprintln!(
            "note: vehicle {recorded:?} is sent as {sent:?} (vehicle ids are at most 128 of [A-Za-z0-9._:-])"
        );
    }
    let connections = args
        .server
        .connect_pool(tracks.len(), args.streams_per_connection as usize)
        .await?;
    let options = ReplayOptions {
        rate_hz: args.rate,
        batch_size: args.batch,
        model: args.model.clone().unwrap_or_default(),
        reconnect_every_s: args.reconnect_every,
        reconnect_seed: args.seed,
        failover_s: args.failover_secs,
        started: None,
    };
    let mut timeline = match &args.timeline {
        Some(_) if args.rate == 0.0 => {
            bail!("--timeline needs --rate above 0: an unpaced replay has no due times")
        }
        Some(_) => {
            let every = Duration::from_secs_f64(args.timeline_every);
            // On time: answered before the vehicle's next batch was due.
            let pace = Duration::from_secs_f64(args.batch as f64 / args.rate);
            let mut timeline = Timeline::new(every, pace);
            for track in &tracks {
                for (due, samples) in batch_due_times(track, &options) {
                    timeline.add_due(due, samples);
                }
            }
            Some(timeline)
        }
        None => None,
    };
    let mut csv = match &args.out {
        Some(path) => {
            let mut writer = csv::Writer::from_path(path)
                .with_context(|| format!("creating {}", path.display()))?;
            writer.write_record(CSV_HEADER)?;
            Some(writer)
        }
        None => None,
    };

    let samples: usize = tracks.iter().map(|track| track.records.len()).sum();
    println!("replaying {} vehicles, {samples} samples", tracks.len());
    let (events_tx, mut events) = mpsc::channel(1024);
    let replay = {
        tokio::spawn(
            async move { replay_tracks_over(&connections, tracks, &options, events_tx).await },
        )
    };
    let mut log = ReplayLog::default();
    while let Some(event) = events.recv().await {
        match &event {
            ReplayEvent::Accepted {
                vehicle_id,
                stream,
                accepted,
            } => {
                if !args.quiet && *stream == 0 {
                    println!("{vehicle_id}: session accepted, model {}", accepted.model);
                } else if !args.quiet {
                    let how = if accepted.resumed {
                        "resumed"
                    } else {
                        "started afresh"
                    };
                    println!(
                        "{vehicle_id}: reconnected, session {how} after {} samples",
                        accepted.samples_seen
                    );
                }
            }
            ReplayEvent::Failover {
                vehicle_id,
                accepted,
                resend_from,
                ..
            } => {
                let how = if accepted.resumed {
                    format!("session resumed at seq {}", accepted.last_seq)
                } else {
                    "no session there: started afresh".to_string()
                };
                eprintln!(
                    "{vehicle_id}: stream failed; reconnected ({how}), resending from record {resend_from}"
                );
            }
            ReplayEvent::Detection(detection) => {
                let det = &detection.detection;
                if !args.quiet || det.alarm_onset || det.alarm_escalated || det.alarm_end {
                    println!("{}", console_line(detection));
                }
            }
            ReplayEvent::ItemError {
                vehicle_id,
                seq,
                lines,
                status,
                ..
            } => eprintln!(
                "{vehicle_id}: batch {seq} (lines {}–{}) rejected: {}",
                lines.0,
                lines.1,
                describe_rpc_status(status)
            ),
        }
        log.record(event);
    }
    // The final rows: the CSV (vehicle by vehicle) and the fleet tally.
    let mut fleet = FleetTally::default();
    for (_, events) in log.vehicles() {
        for event in events {
            fleet.record(event);
            let ReplayEvent::Detection(detection) = event else {
                continue;
            };
            if let Some(writer) = csv.as_mut() {
                writer.write_record(csv_row(detection))?;
            }
            if let Some(timeline) = timeline.as_mut() {
                timeline.add_delivered(detection.due, detection.latency);
            }
        }
    }
    if let Some(mut writer) = csv {
        writer.flush()?;
    }
    let results = replay.await.context("the replay task failed")?;
    let mut failures = 0;
    for result in results {
        match result {
            Ok(summary) => println!("{}", summary_line(&summary)),
            Err(error) => {
                failures += 1;
                eprintln!("error: {error}");
            }
        }
    }
    let summary = fleet.summary();
    for line in fleet_lines(&summary) {
        println!("{line}");
    }
    if let Some(path) = &args.out {
        println!("wrote {}", path.display());
    }
    if let Some(path) = &args.summary {
        write_json(path, &summary)?;
        println!("wrote {}", path.display());
    }
    if let (Some(path), Some(timeline)) = (&args.timeline, timeline) {
        write_timeline(path, &timeline.rows())?;
        println!("wrote {}", path.display());
    }
    if failures > 0 {
        bail!("{failures} vehicle stream(s) failed");
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn track(id: &str) -> Track {
        Track {
            vehicle_id: id.to_string(),
            records: Vec::new(),
        }
    }

    fn detection(why: Option<v1::Explanation>) -> ReplayedDetection {
        ReplayedDetection {
            vehicle_id: "car-1".into(),
            line: 7,
            recorded_timestamp_s: 12.0,
            detection: v1::Detection {
                probability: 0.91,
                alarm: true,
                alarm_onset: true,
                why,
                ..v1::Detection::default()
            },
            model: "models/m1".into(),
            ..ReplayedDetection::default()
        }
    }

    fn jump() -> v1::Explanation {
        v1::Explanation {
            dominant: v1::EvidenceKind::Jump as i32,
            offset_east_m: 300.0,
            offset_north_m: 400.0,
            offset_m: 500.0,
            offset_bearing_deg: 36.87,
            drift_mps: 0.25,
            drift_bearing_deg: 90.0,
            ..v1::Explanation::default()
        }
    }

    #[test]
    fn an_onset_says_why_on_the_console_and_in_the_csv() {
        let line = console_line(&detection(Some(jump())));
        assert!(
            line.ends_with(
                "ALARM onset  jump: offset 500.0 m toward 37°, drift 0.25 m/s toward 90°"
            ),
            "{line}"
        );
        let row = csv_row(&detection(Some(jump())));
        assert_eq!(row.len(), CSV_HEADER.len());
        assert_eq!(
            &row[8..],
            ["jump", "500", "36.87", "0.25", "90", "models/m1", ""]
        );
    }

    #[test]
    fn nothing_standing_out_or_an_older_server_adds_nothing() {
        let none = v1::Explanation {
            dominant: v1::EvidenceKind::None as i32,
            ..v1::Explanation::default()
        };
        assert!(console_line(&detection(Some(none))).ends_with("ALARM onset"));
        assert!(console_line(&detection(None)).ends_with("ALARM onset"));
        let mut critical = detection(None);
        critical.detection.alarm_escalated = true;
        critical.detection.severity = v1::AlarmSeverity::Critical as i32;
        assert!(console_line(&critical).ends_with("CRITICAL onset"));
        assert_eq!(csv_row(&critical)[14], "critical");
        critical.detection.alarm_onset = false;
        assert!(console_line(&critical).ends_with("CRITICAL"));
        assert_eq!(&csv_row(&detection(Some(none)))[8..10], ["none", "0"]);
        assert_eq!(&csv_row(&detection(None))[8..13], ["", "", "", "", ""]);
    }

    #[test]
    fn rewritten_vehicle_ids_are_named_and_collisions_refused() {
        let tracks = [track("car-1"), track("sim0#ramp")];
        assert_eq!(
            renamed_vehicles(&tracks).expect("no collision"),
            vec![("sim0#ramp".to_string(), "sim0_ramp".to_string())]
        );
        let colliding = [track("a#b"), track("a/b")];
        let error = renamed_vehicles(&colliding).expect_err("a collision");
        assert!(error.to_string().contains("\"a_b\""), "{error}");
    }
}
