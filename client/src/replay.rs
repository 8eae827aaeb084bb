//! Replaying recorded tracks over `StreamDetect`, one [`DetectStream`] per vehicle: batching,
//! pacing, replay timestamps and tying each detection back to its recorded row. The stream
//! protocol itself lives in [`crate::detect_stream`]; printing belongs to the commands.
//!
//! The server sees only timestamps: it cannot see a recording's own trajectory breaks, and it rejects
//! time going backwards. [`replay_timestamps`] therefore shifts later timestamps so that each break
//! becomes a 10 s forward gap, which makes the server start a new trajectory exactly where offline
//! evaluation does, while every δ inside a trajectory stays as recorded.

use std::time::Duration;

use spoofwatch_core::evidence::MAX_BACKWARD_S;
use spoofwatch_core::sample::{Record, Sample, Track};
use spoofwatch_proto::v1;
use spoofwatch_proto::wire::convert::sample_to_proto;
use spoofwatch_proto::wire::limits::{MAX_BATCH_SAMPLES, MAX_VEHICLE_ID_LEN};
use tokio::sync::mpsc;

use crate::connection::Connection;
use crate::detect_stream::{BatchOutcome, DetectStream};
use crate::error::ClientError;

/// The forward gap (s) a recorded trajectory break becomes in a replay; anything above the 5 s
/// gap rule of SPEC §3 starts a new trajectory on the server.
pub const REPLAY_BREAK_GAP_S: f64 = 10.0;

/// Timestamps to send for a track's records, in order.
///
/// From the first record on, every timestamp is shifted by a running offset. At a record with
/// `trajectory_break`, or where time steps backwards by more than 0.5 s, the offset changes so that
/// the record lands [`REPLAY_BREAK_GAP_S`] after the latest timestamp sent so far. Inside a
/// trajectory the differences between consecutive timestamps are unchanged. A non-finite timestamp
/// is passed through (the server rejects it); a break on it moves to the next finite record.
pub fn replay_timestamps(records: &[Record]) -> Vec<f64> {
    let mut replayed = Vec::with_capacity(records.len());
    let mut offset = 0.0;
    // (recorded timestamp of the previous finite record, latest replayed timestamp)
    let mut previous: Option<(f64, f64)> = None;
    let mut pending_break = false;
    for record in records {
        let t = record.sample.timestamp_s;
        if !t.is_finite() {
            pending_break |= record.trajectory_break;
            replayed.push(t);
            continue;
        }
        if let Some((previous_t, latest)) = previous {
            let backwards = t - previous_t < -MAX_BACKWARD_S;
            if record.trajectory_break || pending_break || backwards {
                offset = latest + REPLAY_BREAK_GAP_S - t;
            }
        }
        pending_break = false;
        let shifted = t + offset;
        let latest = previous.map_or(shifted, |(_, latest)| latest.max(shifted));
        previous = Some((t, latest));
        replayed.push(shifted);
    }
    replayed
}

/// A core sample on the wire, sent with `timestamp_s` instead of its own.
pub fn replayed_sample(sample: &Sample, timestamp_s: f64) -> v1::Sample {
    v1::Sample {
        timestamp_s,
        ..sample_to_proto(sample)
    }
}

/// A vehicle id the server accepts: characters outside `[A-Za-z0-9._:-]` (e.g. the `#` and `/` of
/// generated scenario ids) become `_`, at most 128 characters, `vehicle` when empty.
pub fn server_vehicle_id(id: &str) -> String {
    let cleaned: String = id
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | ':' | '-') {
                c
            } else {
                '_'
            }
        })
        .take(MAX_VEHICLE_ID_LEN)
        .collect();
    if cleaned.is_empty() {
        "vehicle".to_string()
    } else {
        cleaned
    }
}

/// How to replay a track.
#[derive(Clone, Debug)]
pub struct ReplayOptions {
    /// Samples per second per vehicle; 0 sends as fast as the server takes them.
    pub rate_hz: f64,
    /// Samples per `SampleBatch` (1 to 1,000).
    pub batch_size: usize,
    /// `models/{id}` or `{id}`; empty = the server's active model.
    pub model: String,
}

impl Default for ReplayOptions {
    fn default() -> Self {
        Self {
            rate_hz: 0.0,
            batch_size: 1,
            model: String::new(),
        }
    }
}

impl ReplayOptions {
    /// Checks the rate and batch size.
    pub fn validate(&self) -> Result<(), ClientError> {
        if !(self.rate_hz.is_finite() && self.rate_hz >= 0.0) {
            return Err(ClientError::InvalidOption {
                option: "rate",
                reason: format!(
                    "must be a finite, non-negative rate in Hz, got {}",
                    self.rate_hz
                ),
            });
        }
        if !(1..=MAX_BATCH_SAMPLES).contains(&self.batch_size) {
            return Err(ClientError::InvalidOption {
                option: "batch",
                reason: format!(
                    "must be 1 to {MAX_BATCH_SAMPLES} samples, got {}",
                    self.batch_size
                ),
            });
        }
        Ok(())
    }
}

/// One detection of a replay, tied back to its recorded row.
#[derive(Clone, Debug)]
pub struct ReplayedDetection {
    /// The vehicle id sent to the server.
    pub vehicle_id: String,
    /// Index of the record within its track.
    pub index: usize,
    /// 1-based line of the record in its source file.
    pub line: u64,
    /// The record's own timestamp (the detection carries the replayed one).
    pub recorded_timestamp_s: f64,
    /// The server's verdict.
    pub detection: v1::Detection,
}

/// What a replay reports while it runs.
#[derive(Clone, Debug)]
pub enum ReplayEvent {
    /// The server accepted the session.
    Accepted {
        vehicle_id: String,
        accepted: v1::SessionAccepted,
    },
    /// One sample's detection, in sample order.
    Detection(ReplayedDetection),
    /// The server rejected a batch (its samples get no detection; the stream goes on).
    ItemError {
        vehicle_id: String,
        seq: u64,
        /// Lines of the batch's first and last record.
        lines: (u64, u64),
        status: tonic_types::Status,
    },
}

/// What one vehicle's replay did.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ReplaySummary {
    /// The vehicle id sent to the server.
    pub vehicle_id: String,
    /// Samples sent.
    pub samples_sent: u64,
    /// Detections received.
    pub detections: u64,
    /// Batches rejected with an ItemError.
    pub rejected_batches: u64,
    /// Confirmed alarm onsets.
    pub alarm_onsets: u64,
    /// Round trip of each answered batch (sent → its reply).
    pub batch_latencies: Vec<Duration>,
}

impl ReplaySummary {
    /// Mean batch round trip, `None` when no batch was answered.
    pub fn mean_latency(&self) -> Option<Duration> {
        let n = u32::try_from(self.batch_latencies.len()).ok()?;
        if n == 0 {
            return None;
        }
        Some(self.batch_latencies.iter().sum::<Duration>() / n)
    }
}

/// Replays one track over its own `StreamDetect` call: `SessionStart{reset: true}`, then the
/// records in batches (paced by `options.rate_hz`, at most
/// [`crate::detect_stream::MAX_IN_FLIGHT_BATCHES`] unanswered)
/// with [`replay_timestamps`]. Every reply is forwarded to `events` as it arrives; the call ends
/// when all batches are answered.
pub async fn replay_track(
    connection: &Connection,
    track: &Track,
    options: &ReplayOptions,
    events: mpsc::Sender<ReplayEvent>,
) -> Result<ReplaySummary, ClientError> {
    options.validate()?;
    let vehicle_id = server_vehicle_id(&track.vehicle_id);
    let timestamps = replay_timestamps(&track.records);
    let (mut stream, accepted) =
        DetectStream::start(connection, &vehicle_id, &options.model, true).await?;
    let _ = events
        .send(ReplayEvent::Accepted {
            vehicle_id: vehicle_id.clone(),
            accepted,
        })
        .await;

    let mut batches = batch_requests(&track.records, &timestamps, options.batch_size).into_iter();
    let mut next_batch = batches.next();
    let mut summary = ReplaySummary {
        vehicle_id: vehicle_id.clone(),
        samples_sent: track.records.len() as u64,
        ..ReplaySummary::default()
    };
    let pace = pace_per_batch(options);
    let started = tokio::time::Instant::now();
    let mut sent: u32 = 0;
    loop {
        let can_send = next_batch.is_some() && stream.has_room();
        let awaiting = stream.in_flight() > 0;
        if !can_send && !awaiting {
            break;
        }
        // Paced: batch k leaves at k × pace; otherwise as soon as the window has room.
        let send_at = pace.map_or(started, |pace| started + pace * sent);
        tokio::select! {
            // A reply that is already there is taken before more is sent, so latencies stay true.
            biased;
            reply = stream.recv(), if awaiting => {
                let reply = reply?;
                summary.batch_latencies.push(reply.latency);
                let first_index = (reply.batch.seq - 1) as usize * options.batch_size;
                match reply.outcome {
                    BatchOutcome::Detections(detections) => {
                        for (offset, detection) in detections.into_iter().enumerate() {
                            let index = first_index + offset;
                            let record = &track.records[index];
                            summary.detections += 1;
                            summary.alarm_onsets += u64::from(detection.alarm_onset);
                            let _ = events
                                .send(ReplayEvent::Detection(ReplayedDetection {
                                    vehicle_id: vehicle_id.clone(),
                                    index,
                                    line: record.line,
                                    recorded_timestamp_s: record.sample.timestamp_s,
                                    detection,
                                }))
                                .await;
                        }
                    }
                    BatchOutcome::Rejected(status) => {
                        summary.rejected_batches += 1;
                        let first = &track.records[first_index];
                        let last = &track.records[first_index + reply.batch.len - 1];
                        let _ = events
                            .send(ReplayEvent::ItemError {
                                vehicle_id: vehicle_id.clone(),
                                seq: reply.batch.seq,
                                lines: (first.line, last.line),
                                status,
                            })
                            .await;
                    }
                }
            }
            () = tokio::time::sleep_until(send_at), if can_send => {
                if let Some((seq, _, batch)) = next_batch.take() {
                    stream.send_batch(seq, batch.samples).await?;
                    sent += 1;
                    next_batch = batches.next();
                }
            }
        }
    }
    stream.finish().await?;
    Ok(summary)
}

/// The records as `(seq, first index, batch)`, seq counting from 1.
fn batch_requests(
    records: &[Record],
    timestamps: &[f64],
    batch_size: usize,
) -> Vec<(u64, usize, v1::SampleBatch)> {
    records
        .chunks(batch_size)
        .zip(timestamps.chunks(batch_size))
        .enumerate()
        .map(|(k, (chunk, times))| {
            let seq = k as u64 + 1;
            let samples = chunk
                .iter()
                .zip(times)
                .map(|(record, &t)| replayed_sample(&record.sample, t))
                .collect();
            (seq, k * batch_size, v1::SampleBatch { seq, samples })
        })
        .collect()
}

/// Time between batches, `None` for as fast as possible.
fn pace_per_batch(options: &ReplayOptions) -> Option<Duration> {
    (options.rate_hz > 0.0)
        .then(|| Duration::from_secs_f64(options.batch_size as f64 / options.rate_hz))
}

/// Replays every track concurrently (one task and stream per vehicle). Events of all vehicles are
/// interleaved on `events`; the summaries come back in track order.
pub async fn replay_tracks(
    connection: &Connection,
    tracks: Vec<Track>,
    options: &ReplayOptions,
    events: mpsc::Sender<ReplayEvent>,
) -> Vec<Result<ReplaySummary, ClientError>> {
    let handles: Vec<_> = tracks
        .into_iter()
        .map(|track| {
            let connection = connection.clone();
            let options = options.clone();
            let events = events.clone();
            tokio::spawn(async move { replay_track(&connection, &track, &options, events).await })
        })
        .collect();
    drop(events);
    let mut results = Vec::with_capacity(handles.len());
    for handle in handles {
        results.push(
            handle
                .await
                .unwrap_or_else(|e| Err(ClientError::Protocol(format!("replay task failed: {e}")))),
        );
    }
    results
}

#[cfg(test)]
mod tests {
    use super::*;

    fn record(t: f64, trajectory_break: bool) -> Record {
        Record {
            sample: Sample::new(t, 32.23, -110.91, 3.0, 90.0),
            label: None,
            comparator_alarm: None,
            line: 0,
            trajectory_break,
        }
    }

    fn records(rows: &[(f64, bool)]) -> Vec<Record> {
        rows.iter().map(|&(t, b)| record(t, b)).collect()
    }

    #[test]
    fn a_track_without_breaks_is_sent_unchanged() {
        let rows = records(&[
            (100.0, true),
            (101.0, false),
            (101.2, false),
            (108.0, false),
        ]);
        // The first record's break flag needs no gap; a recorded 6.8 s gap is kept as it is.
        assert_eq!(replay_timestamps(&rows), vec![100.0, 101.0, 101.2, 108.0]);
    }

    #[test]
    fn a_recorded_break_becomes_a_ten_second_gap_and_later_deltas_are_kept() {
        // A date change restarts the clock at 5 s; a second break with time moving forwards by 1 s.
        let rows = records(&[
            (100.0, false),
            (101.0, false),
            (5.0, true),
            (6.5, false),
            (7.0, true),
            (8.0, false),
        ]);
        assert_eq!(
            replay_timestamps(&rows),
            vec![100.0, 101.0, 111.0, 112.5, 122.5, 123.5]
        );
    }

    #[test]
    fn backward_steps_are_gaps_beyond_half_a_second_and_breaks_follow_the_latest_timestamp() {
        let cases = [
            (
                "time going backwards by more than half a second becomes a ten-second gap",
                [(50.0, false), (51.0, false), (50.4, false), (51.4, false)],
                [50.0, 51.0, 61.0, 62.0],
            ),
            (
                // −0.3 s is within the 0.5 s tolerance: no new trajectory offline, none in the replay.
                "a small backward step is kept like offline evaluation does",
                [(50.0, false), (51.0, false), (50.7, false), (51.7, false)],
                [50.0, 51.0, 50.7, 51.7],
            ),
            (
                // After a tolerated −0.3 s step the latest timestamp is still 51.0: the break is at 61.0.
                "a break lands after the latest timestamp sent",
                [(50.0, false), (51.0, false), (50.7, false), (0.0, true)],
                [50.0, 51.0, 50.7, 61.0],
            ),
        ];
        for (case, rows, expected) in cases {
            assert_eq!(
                replay_timestamps(&records(&rows)),
                expected.to_vec(),
                "{case}"
            );
        }
    }

    #[test]
    fn a_break_on_a_non_finite_timestamp_moves_to_the_next_finite_record() {
        let rows = records(&[(10.0, false), (f64::NAN, true), (3.0, false), (4.0, false)]);
        let replayed = replay_timestamps(&rows);
        assert_eq!(replayed[0], 10.0);
        assert!(replayed[1].is_nan());
        assert_eq!(&replayed[2..], &[20.0, 21.0]);
    }

    #[test]
    fn every_replayed_trajectory_starts_exactly_where_the_offline_builder_starts_one() {
        use spoofwatch_core::evidence::{EvidenceBuilder, EvidenceParams};
        use spoofwatch_core::geo::Projection;
        let params = EvidenceParams::new([[1.0, 0.0], [0.0, 1.0]], 2.0, Projection::default())
            .expect("identity covariance is valid");
        let rows = records(&[
            (0.0, false),
            (1.0, false),
            (9.0, false), // recorded gap > 5 s
            (10.0, false),
            (3.0, false), // backwards
            (4.0, true),  // source break
            (4.2, false),
            (3.9, false), // tolerated backwards step
            (5.0, false),
        ]);
        let mut offline = EvidenceBuilder::new(params);
        let offline_starts: Vec<bool> = rows
            .iter()
            .map(|r| offline.push(&r.sample, r.trajectory_break).trajectory_start)
            .collect();
        // The server's builder sees only the replayed timestamps, never a break flag.
        let mut server = EvidenceBuilder::new(params);
        let replayed = replay_timestamps(&rows);
        let server_starts: Vec<bool> = rows
            .iter()
            .zip(&replayed)
            .map(|(r, &t)| {
                let mut sample = r.sample;
                sample.timestamp_s = t;
                server.push(&sample, false).trajectory_start
            })
            .collect();
        assert_eq!(server_starts, offline_starts);
        assert_eq!(
            offline_starts,
            vec![true, false, true, false, true, true, false, false, false]
        );
    }

    #[test]
    fn vehicle_ids_are_made_acceptable_to_the_server() {
        assert_eq!(server_vehicle_id("AV-GPS-Dataset-2"), "AV-GPS-Dataset-2");
        assert_eq!(
            server_vehicle_id("sim/normal0#ramp-1mps"),
            "sim_normal0_ramp-1mps"
        );
        assert_eq!(server_vehicle_id(""), "vehicle");
        assert_eq!(server_vehicle_id(&"x".repeat(300)).len(), 128);
    }

    #[test]
    fn options_out_of_range_are_refused() {
        let bad_rate = ReplayOptions {
            rate_hz: -1.0,
            ..ReplayOptions::default()
        };
        assert!(matches!(
            bad_rate.validate(),
            Err(ClientError::InvalidOption { option: "rate", .. })
        ));
        for batch_size in [0, 1001] {
            let bad_batch = ReplayOptions {
                batch_size,
                ..ReplayOptions::default()
            };
            assert!(matches!(
                bad_batch.validate(),
                Err(ClientError::InvalidOption {
                    option: "batch",
                    ..
                })
            ));
        }
    }

    #[test]
    fn batches_cover_every_record_once_with_increasing_seq() {
        let rows = records(&[
            (0.0, false),
            (1.0, false),
            (2.0, false),
            (3.0, false),
            (4.0, false),
        ]);
        let times = replay_timestamps(&rows);
        let batches = batch_requests(&rows, &times, 2);
        let shape: Vec<(u64, usize, usize)> = batches
            .iter()
            .map(|(seq, first, b)| (*seq, *first, b.samples.len()))
            .collect();
        assert_eq!(shape, vec![(1, 0, 2), (2, 2, 2), (3, 4, 1)]);
        assert_eq!(batches[2].2.seq, 3);
        assert_eq!(batches[2].2.samples[0].timestamp_s, 4.0);
    }
}
