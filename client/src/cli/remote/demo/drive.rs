//! The demo drive: the simulated drive with its drift attack, streamed to a server with a live
//! text view, and the summary against the ground truth. Which server (a running one, or the research
//! binary's in-process one) is the caller's choice. Streaming goes through `replay_track`; this
//! module must not talk the stream protocol itself.

use crate::connection::{ConnectOptions, Connection};
use crate::error::{describe_rpc_status, reply};
use crate::replay::{ReplayEvent, ReplayOptions, replay_track};
use anyhow::{Context, Result, bail};
use spoofwatch_core::sample::Track;
use spoofwatch_core::scenario::{AttackKind, AttackSpec, DriveSpec, inject, simulate_drive};
use spoofwatch_proto::v1;
use tokio::sync::mpsc;

/// Width of the probability bar in characters.
const BAR_WIDTH: usize = 40;

/// The demo scenario: a 6-minute drive at 1 Hz, a ramp drift from 150 s for 150 s.
pub fn scenario(seed: u64, drift_mps: f64) -> Result<(Track, AttackSpec)> {
    let drive = DriveSpec {
        duration_s: 360.0,
        rate_hz: 1.0,
        seed,
        ..DriveSpec::default()
    };
    let track = simulate_drive(&drive, "demo-car").context("simulating the drive")?;
    let attack = AttackSpec {
        kind: AttackKind::RampDrift {
            velocity_mps: drift_mps,
        },
        direction_deg: 60.0,
        onset_s: 150.0,
        duration_s: 150.0,
        seed: None,
    };
    let injected = inject(&track, &attack).context("injecting the attack")?;
    Ok((injected.track, attack))
}

/// `[#####|.....]`: the probability as a bar with the threshold θ marked.
pub fn probability_bar(p: f64, theta: f64) -> String {
    let cells = |x: f64| ((x.clamp(0.0, 1.0) * BAR_WIDTH as f64).round() as usize).min(BAR_WIDTH);
    let filled = cells(p);
    let threshold = cells(theta).min(BAR_WIDTH - 1);
    (0..BAR_WIDTH)
        .map(|i| match (i < filled, i == threshold) {
            (_, true) => '|',
            (true, false) => '#',
            (false, false) => ' ',
        })
        .collect()
}

/// What happened, against the ground truth.
#[derive(Debug, Default, PartialEq)]
pub struct DemoSummary {
    /// First attacked second (relative to the drive start).
    pub attack_onset_s: Option<f64>,
    /// Last attacked second.
    pub attack_end_s: Option<f64>,
    /// First confirmed alarm onset inside the attack window.
    pub alarm_onset_s: Option<f64>,
    /// Alarm onsets outside the attack window.
    pub false_alarms: usize,
}

/// Summarises (relative time, attacked, alarm onset) rows. An alarm onset counts as a detection
/// when it falls inside the attack window (the alarm may outlive the window by a few samples; only
/// onsets matter here).
pub fn summarise(rows: &[(f64, bool, bool)]) -> DemoSummary {
    let attack_onset_s = rows.iter().find(|r| r.1).map(|r| r.0);
    let attack_end_s = rows.iter().rev().find(|r| r.1).map(|r| r.0);
    let onsets = rows.iter().filter(|r| r.2);
    let mut summary = DemoSummary {
        attack_onset_s,
        attack_end_s,
        ..DemoSummary::default()
    };
    for &(t, attacked, _) in onsets {
        if attacked {
            summary.alarm_onset_s.get_or_insert(t);
        } else {
            summary.false_alarms += 1;
        }
    }
    summary
}

/// Streams `track` (attacked as `attack` says) to the server at `url`, `rate` samples per second,
/// printing each detection as it comes and the summary at the end.
pub async fn stream_drive(
    url: &str,
    options: &ConnectOptions,
    track: &Track,
    attack: &AttackSpec,
    rate: f64,
) -> Result<()> {
    let connection = Connection::connect_with(url, options).await?;
    println!(
        "drive: {} samples at 1 Hz streamed at {rate} samples/s; attack: {} (ground truth marked ATTACK)",
        track.records.len(),
        attack.describe()
    );
    let options = ReplayOptions {
        rate_hz: rate,
        batch_size: 1,
        // The demo drives one named server: if it fails, there is nothing to fail over to.
        failover_s: 0.0,
        ..ReplayOptions::default()
    };
    let (events_tx, mut events) = mpsc::channel(256);
    let replay = {
        let connection = connection.clone();
        let track = track.clone();
        tokio::spawn(async move { replay_track(&connection, &track, &options, events_tx).await })
    };
    let t0 = track.records.first().map_or(0.0, |r| r.sample.timestamp_s);
    let mut theta = 0.5;
    let mut rows = Vec::with_capacity(track.records.len());
    while let Some(event) = events.recv().await {
        match event {
            ReplayEvent::Accepted { accepted, .. } => {
                theta = operating_threshold(&connection, &accepted.model).await?;
                println!(
                    "model {} (alarm threshold θ = {theta:.2}, '|' in the bar)",
                    accepted.model
                );
                println!(
                    "{:>6}  {:<5}  [{}]  truth   alarm",
                    "t (s)",
                    "p",
                    " ".repeat(BAR_WIDTH)
                );
            }
            ReplayEvent::Detection(d) => {
                let attacked = track.records[d.index].label == Some(true);
                let det = &d.detection;
                let t = d.recorded_timestamp_s - t0;
                rows.push((t, attacked, det.alarm_onset));
                let alarm = match (det.alarm_onset, det.alarm) {
                    (true, _) => "ALARM ◀ onset",
                    (false, true) => "ALARM",
                    _ => "",
                };
                println!(
                    "{t:>6.0}  {:.3}  [{}]  {:<6}  {alarm}",
                    det.probability,
                    probability_bar(det.probability, theta),
                    if attacked { "ATTACK" } else { "" },
                );
            }
            ReplayEvent::ItemError { seq, status, .. } => {
                eprintln!("batch {seq} rejected: {}", describe_rpc_status(&status));
            }
            // Failover is off: never sent.
            ReplayEvent::Failover { .. } => {}
        }
    }
    let summary = replay.await.context("the replay task failed")??;
    let demo = summarise(&rows);
    println!();
    println!("summary ({} detections):", summary.detections);
    match (demo.attack_onset_s, demo.attack_end_s) {
        (Some(start), Some(end)) => println!("  attack      {start:.0} s – {end:.0} s"),
        _ => println!("  attack      none"),
    }
    match (demo.alarm_onset_s, demo.attack_onset_s) {
        (Some(alarm), Some(onset)) => println!(
            "  alarm onset {alarm:.0} s (delay {:.0} s after the attack began)",
            alarm - onset
        ),
        _ => println!("  alarm onset none during the attack (missed)"),
    }
    println!("  false alarms {}", demo.false_alarms);
    if summary.detections != track.records.len() as u64 {
        bail!(
            "expected {} detections, got {}",
            track.records.len(),
            summary.detections
        );
    }
    Ok(())
}

/// θ of the model serving the session.
async fn operating_threshold(connection: &Connection, model: &str) -> Result<f64> {
    let request = v1::GetModelRequest {
        name: model.to_string(),
    };
    let model = reply(
        format!("getting {model}"),
        connection.models().get_model(request),
    )
    .await?;
    Ok(model.operating_point.map_or(0.5, |op| op.theta))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_bar_fills_to_the_probability_and_marks_the_threshold() {
        let bar = probability_bar(0.25, 0.5);
        assert_eq!(bar.chars().count(), BAR_WIDTH);
        assert_eq!(bar.chars().filter(|&c| c == '#').count(), 10);
        assert_eq!(bar.chars().position(|c| c == '|'), Some(20));
        let full = probability_bar(1.0, 0.5);
        assert_eq!(full.chars().filter(|&c| c == '#').count(), BAR_WIDTH - 1);
    }

    #[test]
    fn the_summary_separates_detection_from_false_alarms() {
        // (t, attacked, alarm onset)
        let rows = [
            (0.0, false, false),
            (1.0, false, true), // false alarm before the attack
            (2.0, true, false),
            (3.0, true, false),
            (4.0, true, true),  // detection, 2 s after onset
            (5.0, true, true),  // a later onset inside the window: not a false alarm
            (6.0, false, true), // false alarm after the attack
        ];
        let summary = summarise(&rows);
        assert_eq!(
            summary,
            DemoSummary {
                attack_onset_s: Some(2.0),
                attack_end_s: Some(5.0),
                alarm_onset_s: Some(4.0),
                false_alarms: 2,
            }
        );
    }

    #[test]
    fn the_scenario_attacks_150_seconds_from_second_150() {
        let (track, _) = scenario(7, 1.5).expect("valid scenario");
        assert_eq!(track.records.len(), 361);
        let attacked: Vec<f64> = track
            .records
            .iter()
            .filter(|r| r.label == Some(true))
            .map(|r| r.sample.timestamp_s)
            .collect();
        assert_eq!(attacked.len(), 150);
        assert_eq!(attacked.first(), Some(&150.0));
        assert_eq!(attacked.last(), Some(&299.0));
    }
}
