//! `spoofwatch detect`: replay a recording over StreamDetect, one concurrent stream per vehicle,
//! printing detections as they arrive.
//!
//! Replay and the stream protocol belong to `spoofwatch_client::replay` and `DetectStream`; this
//! module owns only the flags and the console/CSV output.

use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use spoofwatch_client::error::describe_rpc_status;
use spoofwatch_client::input::load_tracks;
use spoofwatch_client::replay::{
    ReplayEvent, ReplayOptions, ReplaySummary, ReplayedDetection, replay_tracks,
};
use spoofwatch_proto::wire::limits::MAX_BATCH_SAMPLES;
use tokio::sync::mpsc;

use super::ServerArgs;

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
    /// alarm_onset, valid); timestamp_s is the recorded one.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Print only alarm onsets and ends, and the per-vehicle summaries.
    #[arg(long)]
    pub quiet: bool,
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
const CSV_HEADER: [&str; 8] = [
    "vehicle_id",
    "line",
    "timestamp_s",
    "probability",
    "positive",
    "alarm",
    "alarm_onset",
    "valid",
];

fn flag(b: bool) -> &'static str {
    if b { "1" } else { "0" }
}

/// One detection as a CSV row.
pub fn csv_row(d: &ReplayedDetection) -> [String; 8] {
    let det = &d.detection;
    let valid = det.evidence.as_ref().is_some_and(|e| e.valid);
    [
        d.vehicle_id.clone(),
        d.line.to_string(),
        d.recorded_timestamp_s.to_string(),
        det.probability.to_string(),
        flag(det.positive).into(),
        flag(det.alarm).into(),
        flag(det.alarm_onset).into(),
        flag(valid).into(),
    ]
}

/// One detection as a console line: `vehicle  t  p=0.123  ALARM onset`.
pub fn console_line(d: &ReplayedDetection) -> String {
    let det = &d.detection;
    let marker = if det.alarm_onset {
        "ALARM onset"
    } else if det.alarm {
        "ALARM"
    } else if det.alarm_end {
        "alarm end"
    } else {
        ""
    };
    format!(
        "{:<20} {:>14.2}  p={:.3}  {marker}",
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
    format!(
        "{}: {} samples, {} detections, {} alarms, {} rejected batches, mean batch latency {latency}",
        s.vehicle_id, s.samples_sent, s.detections, s.alarm_onsets, s.rejected_batches
    )
}

pub async fn run(args: Args) -> Result<()> {
    let tracks = load_tracks(&args.data)?;
    if tracks.is_empty() {
        bail!("no vehicle data in the given files");
    }
    let connection = args.server.connect().await?;
    let options = ReplayOptions {
        rate_hz: args.rate,
        batch_size: args.batch,
        model: args.model.clone().unwrap_or_default(),
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

    let (events_tx, mut events) = mpsc::channel(1024);
    let replay = {
        let connection = connection.clone();
        tokio::spawn(async move { replay_tracks(&connection, tracks, &options, events_tx).await })
    };
    while let Some(event) = events.recv().await {
        match event {
            ReplayEvent::Accepted {
                vehicle_id,
                accepted,
            } => {
                if !args.quiet {
                    println!("{vehicle_id}: session accepted, model {}", accepted.model);
                }
            }
            ReplayEvent::Detection(detection) => {
                let det = &detection.detection;
                if !args.quiet || det.alarm_onset || det.alarm_end {
                    println!("{}", console_line(&detection));
                }
                if let Some(writer) = csv.as_mut() {
                    writer.write_record(csv_row(&detection))?;
                }
            }
            ReplayEvent::ItemError {
                vehicle_id,
                seq,
                lines,
                status,
            } => eprintln!(
                "{vehicle_id}: batch {seq} (lines {}–{}) rejected: {}",
                lines.0,
                lines.1,
                describe_rpc_status(&status)
            ),
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
    if let Some(path) = &args.out {
        println!("wrote {}", path.display());
    }
    if failures > 0 {
        bail!("{failures} vehicle stream(s) failed");
    }
    Ok(())
}
