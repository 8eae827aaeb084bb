//! Replaying recorded tracks over `StreamDetect`, one [`DetectStream`] per vehicle: batching,
//! pacing, replay timestamps and tying each detection back to its recorded row. The stream
//! protocol itself lives in [`crate::detect_stream`]; printing belongs to the commands.
//!
//! Reconnects: with [`ReplayOptions::reconnect_every_s`] a vehicle's stream is closed and a new one
//! opened every so often ([`stream_starts`]), as when a vehicle's cellular link drops. The new
//! stream sends `SessionStart{reset: false}`, which is what a reconnecting vehicle sends: the server
//! resumes the vehicle's in-memory session (same detector state, `SessionAccepted.resumed`), and the
//! replay continues with the next sample. The first stream always starts afresh (`reset: true`).
//!
//! Failover: a stream that fails because its server went away (a replica died or drained, a
//! balancer cut it) is reopened with `reset: false` within [`ReplayOptions::failover_s`]. Batch seq
//! numbers are positions in the recording, so the session's `SessionAccepted.last_seq` says exactly
//! what to resend; a session that was not resumed (a replica that never had it) is started over
//! with `reset: true` and the whole recording resent, which yields the same detections as the
//! first time. A session the server started afresh under another model (a roll-out:
//! `SessionAccepted.replaced_model`) goes on with the batches not yet answered, as a vehicle would.
//! Resent detections replace the earlier ones ([`crate::replay_log`]).
//!
//! Pacing: a paced vehicle's batches are due one pace interval apart from its send phase, a
//! fraction of the interval drawn from its id ([`batch_due_times`]); each detection carries its
//! batch's due time and the latency from it, for a timeline of the whole replay
//! ([`crate::timeline`]).
//!
//! The server sees only timestamps: it cannot see a recording's own trajectory breaks, and it rejects
//! time going backwards. [`replay_timestamps`] therefore shifts later timestamps so that each break
//! becomes a 10 s forward gap, which makes the server start a new trajectory exactly where offline
//! evaluation does, while every δ inside a trajectory stays as recorded.

use std::collections::VecDeque;
use std::sync::Arc;
use std::time::Duration;

use spoofwatch_core::evidence::MAX_BACKWARD_S;
use spoofwatch_core::sample::{Record, Sample, Track};
use spoofwatch_proto::v1;
use spoofwatch_proto::wire::convert::sample_to_proto;
use spoofwatch_proto::wire::is_vehicle_id_char;
use spoofwatch_proto::wire::limits::{MAX_BATCH_SAMPLES, MAX_FORWARD_JUMP_S, MAX_VEHICLE_ID_LEN};
use tokio::sync::mpsc;

use crate::connection::Connection;
use crate::detect_stream::{BatchOutcome, DetectStream};
use crate::error::ClientError;
use crate::failover::{DEFAULT_FAILOVER_S, FailoverEpisode};
pub use crate::reconnects::stream_starts;
use crate::reconnects::{id_hash, reconnect_rng};

/// The forward gap (s) a recorded trajectory break becomes in a replay: beyond the 5 s gap rule of
/// SPEC §3 (a new trajectory on the server) and beyond the gaps the offset anchors carry across
/// (`docs/detector.md` §4.2), so the server re-anchors exactly where offline evaluation does.
pub const REPLAY_BREAK_GAP_S: f64 = 2.0 * spoofwatch_core::evidence::offset::MAX_CARRY_GAP_S;

/// Timestamps to send for a track's records, in order.
///
/// From the first record on, every timestamp is shifted by a running offset. At a record with
/// `trajectory_break`, where time steps backwards by more than 0.5 s, or where it jumps forward by
/// more than the server accepts ([`MAX_FORWARD_JUMP_S`]), the offset changes so that the record
/// lands [`REPLAY_BREAK_GAP_S`] after the latest timestamp sent so far. Inside a
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
            let far_ahead = t + offset - latest > MAX_FORWARD_JUMP_S;
            if record.trajectory_break || pending_break || backwards || far_ahead {
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
        .map(|c| if is_vehicle_id_char(c) { c } else { '_' })
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
    /// Close and reopen each vehicle's stream after about this much recorded time (s); 0 = never.
    /// See [`stream_starts`].
    pub reconnect_every_s: f64,
    /// Seed of the per-vehicle jitter of reconnect times.
    pub reconnect_seed: u64,
    /// After a stream fails because its server went away, keep reconnecting (with backoff) for
    /// up to this many seconds, then resend what the server has not seen; 0 = fail at once.
    pub failover_s: f64,
    /// The replay's start, from which every vehicle's batches are due ([`batch_due_times`]);
    /// `None`: when [`replay_tracks`] starts (or, for [`replay_track`] alone, the vehicle's replay).
    pub started: Option<tokio::time::Instant>,
}

impl Default for ReplayOptions {
    fn default() -> Self {
        Self {
            rate_hz: 0.0,
            batch_size: 1,
            model: String::new(),
            reconnect_every_s: 0.0,
            reconnect_seed: 1,
            failover_s: DEFAULT_FAILOVER_S,
            started: None,
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
        if !(self.reconnect_every_s.is_finite() && self.reconnect_every_s >= 0.0) {
            return Err(ClientError::InvalidOption {
                option: "reconnect-every",
                reason: format!(
                    "must be a finite, non-negative time in seconds, got {}",
                    self.reconnect_every_s
                ),
            });
        }
        if !(self.failover_s.is_finite() && self.failover_s >= 0.0) {
            return Err(ClientError::InvalidOption {
                option: "failover-secs",
                reason: format!(
                    "must be a finite, non-negative time in seconds, got {}",
                    self.failover_s
                ),
            });
        }
        Ok(())
    }
}

/// One detection of a replay, tied back to its recorded row.
#[derive(Clone, Debug, Default)]
pub struct ReplayedDetection {
    /// The vehicle id sent to the server.
    pub vehicle_id: String,
    /// Index of the record within its track.
    pub index: usize,
    /// 1-based line of the record in its source file.
    pub line: u64,
    /// The record's own timestamp (the detection carries the replayed one).
    pub recorded_timestamp_s: f64,
    /// The record's ground truth (`Some(true)` = attacked), `None` when unlabelled.
    pub label: Option<bool>,
    /// Which of the vehicle's streams carried it (0 = the first).
    pub stream: u32,
    /// The first detection received on its stream.
    pub first_on_stream: bool,
    /// The model that made it (`models/{id}`, as its stream's `SessionAccepted.model`).
    pub model: Arc<str>,
    /// When its batch was due, from the replay's start (see [`batch_due_times`]).
    pub due: Duration,
    /// From when its batch was due to when this reply came: what the vehicle waited, resends after
    /// a failover and a late start included.
    pub latency: Duration,
    /// The server's verdict.
    pub detection: v1::Detection,
}

/// What a replay reports while it runs.
// Detections are nearly every event (one per sample), so they are not boxed: the other variants'
// unused space costs less than an allocation per sample.
#[allow(clippy::large_enum_variant)]
#[derive(Clone, Debug)]
pub enum ReplayEvent {
    /// The server accepted a stream (the first, or a reconnect).
    Accepted {
        vehicle_id: String,
        /// Which of the vehicle's streams (0 = the first).
        stream: u32,
        accepted: v1::SessionAccepted,
    },
    /// A stream failed (its server went away) and a new one was accepted: the detections that
    /// follow, from record `resend_from` on, replace any received before for those records.
    Failover {
        vehicle_id: String,
        /// Which of the vehicle's streams (counting every stream opened).
        stream: u32,
        /// The reconnect's answer: `resumed` with `last_seq`, or a session started afresh (then
        /// the whole recording is resent, on a `reset: true` session).
        accepted: v1::SessionAccepted,
        /// Index of the first record resent.
        resend_from: usize,
        /// Samples the resumed session had applied whose replies never came (cut with the
        /// connection): their detections are lost, as they would be for a vehicle, and they are
        /// not sent again.
        replies_lost: u64,
        /// Samples an earlier failover counted in `replies_lost` that this one resends (the
        /// session it found had not got as far): their detections come after all.
        replies_recovered: u64,
    },
    /// One sample's detection, in sample order.
    Detection(ReplayedDetection),
    /// The server rejected a batch (its samples get no detection; the stream goes on).
    ItemError {
        vehicle_id: String,
        seq: u64,
        /// Index of the batch's first record.
        index: usize,
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
    /// Samples in the recording.
    pub samples_sent: u64,
    /// Detections in the final output (one per sample of every batch not rejected; resent
    /// batches count once).
    pub detections: u64,
    /// Batches rejected with an ItemError.
    pub rejected_batches: u64,
    /// Confirmed alarm onsets in the final output.
    pub alarm_onsets: u64,
    /// Of those alarms, the ones that turned critical (at their onset or later).
    pub critical_alarms: u64,
    /// Streams opened (1 + reconnects, failovers included).
    pub streams: u32,
    /// Reconnects the server answered by resuming the session (`SessionAccepted.resumed`).
    pub resumed_reconnects: u32,
    /// Streams reopened after a failure (each a [`ReplayEvent::Failover`]).
    pub failovers: u32,
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

    /// Streams opened after the first.
    pub fn reconnects(&self) -> u32 {
        self.streams.saturating_sub(1)
    }
}

/// A batch ready to send, with the index of its first record. Its seq is its position in the
/// recording's batches plus one, so a session's `last_seq` says exactly which batches it has seen.
#[derive(Clone, Debug)]
struct PlannedBatch {
    first_index: usize,
    /// A planned reconnect opens a new stream with this batch.
    opens_stream: bool,
    batch: v1::SampleBatch,
}

/// What the server answered to one batch, kept until the summary (a failover may redo it).
#[derive(Clone, Copy, Debug)]
struct BatchResult {
    detections: u64,
    alarm_onsets: u64,
    critical_alarms: u64,
    rejected: bool,
    /// Applied by the session, its reply lost with a failed stream.
    reply_lost: bool,
}

/// How the next stream of a vehicle starts.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Opening {
    /// The replay's first stream: `reset: true`.
    First,
    /// A planned reconnect ([`ReplayOptions::reconnect_every_s`]): `reset: false`, go on.
    Planned,
    /// After a failure: `reset: false`, then resend from the session's `last_seq` (or from the
    /// start with `reset: true` when the session was not resumed).
    Failover,
}

/// Replays one track: its records with [`replay_timestamps`], in batches of `options.batch_size`
/// (paced by `options.rate_hz`, at most [`crate::detect_stream::MAX_IN_FLIGHT_BATCHES`]
/// unanswered), over one `StreamDetect` call per [`stream_starts`] segment. The first call sends
/// `SessionStart{reset: true}`, every reconnect `reset: false`; each call is finished (all its
/// batches answered) before the next opens. Every reply is forwarded to `events` as it arrives.
///
/// A stream that fails because its server went away ([`crate::failover::is_failover_error`]) is
/// reopened with backoff for up to `options.failover_s`: resumed, the batches after the session's
/// `last_seq` are resent; not resumed (a replica without the session), the whole recording is
/// resent on a `reset: true` session. A [`ReplayEvent::Failover`] says from which record on the
/// detections that follow replace those received before (see [`crate::replay_log::ReplayLog`]).
pub async fn replay_track(
    connection: &Connection,
    track: &Track,
    options: &ReplayOptions,
    events: mpsc::Sender<ReplayEvent>,
) -> Result<ReplaySummary, ClientError> {
    options.validate()?;
    let vehicle_id = server_vehicle_id(&track.vehicle_id);
    let plan = plan_replay(track, &vehicle_id, options);
    let replay = VehicleReplay {
        track,
        results: vec![None; plan.len()],
        plan,
        summary: ReplaySummary {
            vehicle_id: vehicle_id.clone(),
            samples_sent: track.records.len() as u64,
            ..ReplaySummary::default()
        },
        pacer: Pacer::new(options, &vehicle_id),
        vehicle_id,
        options,
        events,
        streams_opened: 0,
        model: Arc::from(""),
        session_start: 0,
    };
    replay.run(connection).await
}

/// One vehicle's replay in progress.
struct VehicleReplay<'a> {
    track: &'a Track,
    vehicle_id: String,
    options: &'a ReplayOptions,
    events: mpsc::Sender<ReplayEvent>,
    plan: Vec<PlannedBatch>,
    /// The latest answer to each planned batch.
    results: Vec<Option<BatchResult>>,
    summary: ReplaySummary,
    pacer: Pacer,
    streams_opened: u32,
    /// The model of the current stream.
    model: Arc<str>,
    /// The first batch the server's current session for the vehicle was sent: 0, or where the
    /// replay went on after a roll-out started the session afresh under another model.
    session_start: usize,
}

impl VehicleReplay<'_> {
    /// Streams every planned batch, failing over when a stream's server goes away.
    async fn run(mut self, connection: &Connection) -> Result<ReplaySummary, ClientError> {
        let failover_total = Duration::from_secs_f64(self.options.failover_s);
        let mut opening = Opening::First;
        let mut position = 0;
        // Set while streams keep failing without an answer; cleared by progress.
        let mut episode: Option<FailoverEpisode> = None;
        loop {
            let stream = match self.open(connection, opening, &mut position).await {
                Ok(stream) => stream,
                Err(error) => {
                    Self::fail_over(&mut episode, failover_total, error).await?;
                    continue;
                }
            };
            let end = self.segment_end(position);
            let mut answered = 0;
            let outcome = self
                .stream_batches(stream, position, end, &mut answered)
                .await;
            if answered > 0 {
                episode = None;
            }
            match outcome {
                Ok(()) if end == self.plan.len() => break,
                Ok(()) => {
                    position = end;
                    opening = Opening::Planned;
                }
                Err(error) => {
                    Self::fail_over(&mut episode, failover_total, error).await?;
                    opening = Opening::Failover;
                }
            }
        }
        for result in self.results.iter().flatten() {
            self.summary.detections += result.detections;
            self.summary.alarm_onsets += result.alarm_onsets;
            self.summary.critical_alarms += result.critical_alarms;
            self.summary.rejected_batches += u64::from(result.rejected);
        }
        Ok(self.summary)
    }

    /// Waits before the next attempt after `error`, or returns it when it is final (failover off,
    /// not a lost server, or past the deadline).
    async fn fail_over(
        episode: &mut Option<FailoverEpisode>,
        total: Duration,
        error: ClientError,
    ) -> Result<(), ClientError> {
        if total.is_zero() {
            return Err(error);
        }
        episode
            .get_or_insert_with(|| FailoverEpisode::new(total))
            .wait_before_retry(error)
            .await
    }

    /// The batch after the last one of the stream that starts at `position`.
    fn segment_end(&self, position: usize) -> usize {
        (position + 1..self.plan.len())
            .find(|&k| self.plan[k].opens_stream)
            .unwrap_or(self.plan.len())
    }

    /// Marks the batches before `applied` that have no answer as done (the session applied them;
    /// their replies were lost); returns their samples.
    fn mark_applied_through(&mut self, applied: usize) -> u64 {
        let mut lost = 0;
        for (result, planned) in self.results[..applied].iter_mut().zip(&self.plan) {
            if result.is_none() {
                lost += planned.batch.samples.len() as u64;
                *result = Some(BatchResult {
                    detections: 0,
                    alarm_onsets: 0,
                    critical_alarms: 0,
                    rejected: false,
                    reply_lost: true,
                });
            }
        }
        lost
    }

    /// The first batch without an answer (replies come in order, and batches applied without one
    /// are marked, so every batch before it is done).
    fn first_unanswered(&self) -> usize {
        self.results
            .iter()
            .position(Option::is_none)
            .unwrap_or(self.plan.len())
    }

    /// The record a replay resumed at batch `position` resends from.
    fn first_index_of(&self, position: usize) -> usize {
        self.plan
            .get(position)
            .map_or(self.track.records.len(), |b| b.first_index)
    }

    /// Opens the next stream and reports it; after a failure, moves `position` to the first batch
    /// the server has not seen (see [`Opening::Failover`]).
    async fn open(
        &mut self,
        connection: &Connection,
        opening: Opening,
        position: &mut usize,
    ) -> Result<DetectStream, ClientError> {
        let reset = opening == Opening::First;
        let model = &self.options.model;
        let (stream, accepted) =
            DetectStream::start(connection, &self.vehicle_id, model, reset).await?;
        let previous_model = std::mem::replace(&mut self.model, Arc::from(accepted.model.as_str()));
        let stream_number = self.streams_opened;
        let event = match opening {
            Opening::First | Opening::Planned => {
                self.summary.resumed_reconnects += u32::from(!reset && accepted.resumed);
                (
                    stream,
                    ReplayEvent::Accepted {
                        vehicle_id: self.vehicle_id.clone(),
                        stream: stream_number,
                        accepted,
                    },
                )
            }
            Opening::Failover => {
                let mut replies_lost = 0;
                let applied_none = accepted.last_seq == 0 && accepted.samples_seen == 0;
                // Started afresh under another model (a roll-out), also when the stream that was
                // told so failed before this replay heard it: the retry then finds that fresh
                // session, resumed with nothing applied, on a model the answers so far did not
                // come from.
                let rolled_out = !accepted.replaced_model.is_empty()
                    || (accepted.resumed && applied_none && *accepted.model != *previous_model);
                let stream = if accepted.resumed && accepted.last_seq > 0 {
                    // A session that kept its state: exactly the batches after its last_seq are
                    // missing.
                    let last_seq = usize::try_from(accepted.last_seq).unwrap_or(usize::MAX);
                    if last_seq > self.plan.len() {
                        return Err(ClientError::Protocol(format!(
                            "the session of {} reports last_seq {last_seq}, beyond this recording's {} batches",
                            self.vehicle_id,
                            self.plan.len()
                        )));
                    }
                    self.summary.resumed_reconnects += 1;
                    replies_lost = self.mark_applied_through(last_seq);
                    *position = last_seq;
                    stream
                } else if rolled_out {
                    // As a vehicle does, go on with the batches not yet answered; what the
                    // previous model said stands.
                    self.summary.resumed_reconnects += u32::from(accepted.resumed);
                    self.session_start = self.first_unanswered();
                    *position = self.session_start;
                    stream
                } else if accepted.resumed && applied_none {
                    // A session with nothing applied yet: from where it started.
                    self.summary.resumed_reconnects += 1;
                    *position = self.session_start;
                    stream
                } else {
                    // A replica without the session: start the vehicle over, exactly as the first
                    // stream did (once sessions are handed over, this happens only when none was).
                    stream.finish().await?;
                    let (fresh, fresh_accepted) =
                        DetectStream::start(connection, &self.vehicle_id, model, true).await?;
                    self.model = Arc::from(fresh_accepted.model.as_str());
                    self.session_start = 0;
                    *position = 0;
                    fresh
                };
                self.summary.failovers += 1;
                let mut replies_recovered = 0;
                for (result, planned) in self.results[*position..]
                    .iter_mut()
                    .zip(&self.plan[*position..])
                {
                    if result.take().is_some_and(|r| r.reply_lost) {
                        replies_recovered += planned.batch.samples.len() as u64;
                    }
                }
                let resend_from = self.first_index_of(*position);
                (
                    stream,
                    ReplayEvent::Failover {
                        vehicle_id: self.vehicle_id.clone(),
                        stream: stream_number,
                        accepted,
                        resend_from,
                        replies_lost,
                        replies_recovered,
                    },
                )
            }
        };
        let (stream, event) = event;
        self.streams_opened += 1;
        self.summary.streams += 1;
        let _ = self.events.send(event).await;
        Ok(stream)
    }

    /// Sends batches `from..to` on `stream`, forwards every reply, then finishes the call;
    /// `answered` counts the replies received (also when the stream fails).
    async fn stream_batches(
        &mut self,
        mut stream: DetectStream,
        from: usize,
        to: usize,
        answered: &mut usize,
    ) -> Result<(), ClientError> {
        let stream_number = self.streams_opened - 1;
        // Replies come in order: the positions of the batches awaiting one, oldest first.
        let mut awaiting: VecDeque<usize> = VecDeque::new();
        let mut next = from;
        let mut first_on_stream = true;
        loop {
            let can_send = next < to && stream.has_room();
            let waiting = stream.in_flight() > 0;
            if !can_send && !waiting {
                break;
            }
            tokio::select! {
                // A reply that is already there is taken before more is sent, so latencies stay true.
                biased;
                reply = stream.recv(), if waiting => {
                    let reply = reply?;
                    *answered += 1;
                    self.summary.batch_latencies.push(reply.latency);
                    let position = awaiting.pop_front().ok_or_else(|| {
                        ClientError::Protocol("a reply to a batch that was never sent".into())
                    })?;
                    let first_index = self.plan[position].first_index;
                    let timing = (
                        self.pacer.due_after_start(position),
                        self.pacer.due(position).elapsed(),
                    );
                    let mut result = BatchResult { detections: 0, alarm_onsets: 0, critical_alarms: 0, rejected: false, reply_lost: false };
                    match reply.outcome {
                        BatchOutcome::Detections(detections) => {
                            for (offset, detection) in detections.into_iter().enumerate() {
                                result.detections += 1;
                                result.alarm_onsets += u64::from(detection.alarm_onset);
                                result.critical_alarms += u64::from(detection.alarm_escalated);
                                self.forward(first_index + offset, stream_number, first_on_stream, timing, detection)
                                    .await;
                                first_on_stream = false;
                            }
                        }
                        // Applied on an earlier stream of this session: nothing new to forward.
                        BatchOutcome::Duplicate => {}
                        BatchOutcome::Rejected(status) => {
                            result.rejected = true;
                            let first = &self.track.records[first_index];
                            let last = &self.track.records[first_index + reply.batch.len - 1];
                            let _ = self
                                .events
                                .send(ReplayEvent::ItemError {
                                    vehicle_id: self.vehicle_id.clone(),
                                    seq: reply.batch.seq,
                                    index: first_index,
                                    lines: (first.line, last.line),
                                    status,
                                })
                                .await;
                        }
                    }
                    self.results[position] = Some(result);
                }
                () = tokio::time::sleep_until(self.pacer.due(next)), if can_send => {
                    let planned = &self.plan[next];
                    stream.send_batch(planned.batch.seq, planned.batch.samples.clone()).await?;
                    awaiting.push_back(next);
                    next += 1;
                }
            }
        }
        stream.finish().await
    }

    /// Sends the detection of record `index` to the events; `(due, latency)` as in
    /// [`ReplayedDetection`].
    async fn forward(
        &self,
        index: usize,
        stream: u32,
        first_on_stream: bool,
        (due, latency): (Duration, Duration),
        detection: v1::Detection,
    ) {
        let record = &self.track.records[index];
        let _ = self
            .events
            .send(ReplayEvent::Detection(ReplayedDetection {
                vehicle_id: self.vehicle_id.clone(),
                index,
                line: record.line,
                recorded_timestamp_s: record.sample.timestamp_s,
                label: record.label,
                stream,
                first_on_stream,
                model: Arc::clone(&self.model),
                due,
                latency,
                detection,
            }))
            .await;
    }
}

/// A vehicle's whole plan: its batches, in order, over every stream it will open.
fn plan_replay(track: &Track, vehicle_id: &str, options: &ReplayOptions) -> Vec<PlannedBatch> {
    let timestamps = replay_timestamps(&track.records);
    let mut rng = reconnect_rng(options.reconnect_seed, vehicle_id);
    let starts = stream_starts(&timestamps, options.reconnect_every_s, &mut rng);
    plan_streams(&track.records, &timestamps, options.batch_size, &starts)
        .into_iter()
        .flatten()
        .collect()
}

/// When a vehicle's batches are due (see [`batch_due_times`]).
struct Pacer {
    /// The replay's start.
    started: tokio::time::Instant,
    /// The vehicle's send phase: its first batch's due time after the start.
    phase: Duration,
    pace: Option<Duration>,
}

impl Pacer {
    fn new(options: &ReplayOptions, vehicle_id: &str) -> Self {
        let pace = pace_per_batch(options);
        Self {
            started: options.started.unwrap_or_else(tokio::time::Instant::now),
            phase: pace.map_or(Duration::ZERO, |pace| send_phase(pace, vehicle_id)),
            pace,
        }
    }

    /// When the batch at `position` in the plan is due, after the replay's start.
    fn due_after_start(&self, position: usize) -> Duration {
        self.phase
            + self
                .pace
                .map_or(Duration::ZERO, |p| p.mul_f64(position as f64))
    }

    fn due(&self, position: usize) -> tokio::time::Instant {
        self.started + self.due_after_start(position)
    }
}

/// Where in each pace interval a vehicle sends: a fraction of `pace` from its id, so that a fleet's
/// vehicles are spread over the interval (as real ones are) instead of all sending at once.
fn send_phase(pace: Duration, vehicle_id: &str) -> Duration {
    // The top 53 bits as a fraction in [0, 1).
    let fraction = (id_hash(vehicle_id) >> 11) as f64 / (1_u64 << 53) as f64;
    pace.mul_f64(fraction)
}

/// When each batch of `track` is due under `options`, from the replay's start, with its number of
/// samples: paced, batch k at the vehicle's send phase (spread over one pace interval by vehicle
/// id) + k × pace, where pace = batch size / rate; unpaced, all at the start. A batch resent after a
/// failover keeps its due time (it leaves at once, late).
pub fn batch_due_times(track: &Track, options: &ReplayOptions) -> Vec<(Duration, usize)> {
    let vehicle_id = server_vehicle_id(&track.vehicle_id);
    let pacer = Pacer::new(options, &vehicle_id);
    plan_replay(track, &vehicle_id, options)
        .iter()
        .enumerate()
        .map(|(position, planned)| (pacer.due_after_start(position), planned.batch.samples.len()))
        .collect()
}

/// The batches of each stream: the records from one stream start to the next, in batches of at
/// most `batch_size` that never span a stream start; seq counts from 1 across all streams (a
/// resumed session keeps its last seq), so seq − 1 is a batch's position in the whole recording.
fn plan_streams(
    records: &[Record],
    timestamps: &[f64],
    batch_size: usize,
    stream_starts: &[usize],
) -> Vec<Vec<PlannedBatch>> {
    let mut seq = 0;
    let ends = stream_starts
        .iter()
        .skip(1)
        .copied()
        .chain(std::iter::once(records.len()));
    stream_starts
        .iter()
        .zip(ends)
        .map(|(&start, end)| {
            (start..end)
                .step_by(batch_size)
                .map(|first_index| {
                    seq += 1;
                    let last = (first_index + batch_size).min(end);
                    let samples = records[first_index..last]
                        .iter()
                        .zip(&timestamps[first_index..last])
                        .map(|(record, &t)| replayed_sample(&record.sample, t))
                        .collect();
                    PlannedBatch {
                        first_index,
                        opens_stream: first_index == start,
                        batch: v1::SampleBatch { seq, samples },
                    }
                })
                .collect()
        })
        .collect()
}

/// Time between batches, `None` for as fast as possible.
fn pace_per_batch(options: &ReplayOptions) -> Option<Duration> {
    (options.rate_hz > 0.0)
        .then(|| Duration::from_secs_f64(options.batch_size as f64 / options.rate_hz))
}

/// Replays every track concurrently (one task and stream per vehicle) over one connection. Events
/// of all vehicles are interleaved on `events`; the summaries come back in track order.
pub async fn replay_tracks(
    connection: &Connection,
    tracks: Vec<Track>,
    options: &ReplayOptions,
    events: mpsc::Sender<ReplayEvent>,
) -> Vec<Result<ReplaySummary, ClientError>> {
    replay_tracks_over(std::slice::from_ref(connection), tracks, options, events).await
}

/// [`replay_tracks`] over several connections, vehicle `i` on `connections[i % n]`: one HTTP/2
/// connection carries only so many concurrent streams (a balancer's or server's limit, about a
/// thousand), so a large fleet needs several.
pub async fn replay_tracks_over(
    connections: &[Connection],
    tracks: Vec<Track>,
    options: &ReplayOptions,
    events: mpsc::Sender<ReplayEvent>,
) -> Vec<Result<ReplaySummary, ClientError>> {
    let options = ReplayOptions {
        started: Some(options.started.unwrap_or_else(tokio::time::Instant::now)),
        ..options.clone()
    };
    let handles: Vec<_> = tracks
        .into_iter()
        .zip(connections.iter().cycle())
        .map(|(track, connection)| {
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
    use spoofwatch_proto::wire::VehicleId;

    use super::*;

    fn record(t: f64, trajectory_break: bool) -> Record {
        Record {
            sample: Sample::new(t, 32.23, -110.91, 3.0, 90.0),
            label: None,
            comparator_alarm: None,
            line: 0,
            trajectory_break,
            warmup: false,
        }
    }

    fn records(rows: &[(f64, bool)]) -> Vec<Record> {
        rows.iter().map(|&(t, b)| record(t, b)).collect()
    }

    #[test]
    fn a_replayed_sample_carries_the_receiver_status_of_the_csv() {
        let csv = "vehicle_id,timestamp,latitude,longitude,speed_mps,heading_deg,spoofing_state,jamming_state,satellites_used,hdop\n\
                   v,10,32.23,-110.91,3.0,90,indicated,2,11,1.5\n";
        let recording =
            spoofwatch_core::data::read(csv.as_bytes(), "flags.csv").expect("a telemetry CSV");
        let sent = replayed_sample(&recording.tracks[0].records[0].sample, 700.0);
        assert_eq!(sent.timestamp_s, 700.0);
        assert_eq!(sent.spoofing_state(), v1::SpoofingState::Indicated);
        assert_eq!(sent.jamming_state(), v1::JammingState::Warning);
        assert_eq!((sent.satellites_used, sent.hdop), (Some(11), Some(1.5)));
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
    fn a_recorded_break_becomes_a_replay_break_gap_and_later_deltas_are_kept() {
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
            vec![100.0, 101.0, 701.0, 702.5, 1302.5, 1303.5]
        );
    }

    #[test]
    fn backward_steps_are_gaps_beyond_half_a_second_and_breaks_follow_the_latest_timestamp() {
        let cases = [
            (
                "time going backwards by more than half a second becomes a replay break gap",
                [(50.0, false), (51.0, false), (50.4, false), (51.4, false)],
                [50.0, 51.0, 651.0, 652.0],
            ),
            (
                // −0.3 s is within the 0.5 s tolerance: no new trajectory offline, none in the replay.
                "a small backward step is kept like offline evaluation does",
                [(50.0, false), (51.0, false), (50.7, false), (51.7, false)],
                [50.0, 51.0, 50.7, 51.7],
            ),
            (
                // After a tolerated −0.3 s step the latest timestamp is still 51.0: the break is at 651.0.
                "a break lands after the latest timestamp sent",
                [(50.0, false), (51.0, false), (50.7, false), (0.0, true)],
                [50.0, 51.0, 50.7, 651.0],
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
    fn a_jump_further_ahead_than_the_server_accepts_becomes_a_replay_break_gap() {
        // Two days apart without a break flag; a one-hour pause is kept as it is.
        let rows = records(&[
            (0.0, false),
            (1.0, false),
            (172_801.0, false),
            (172_802.0, false),
        ]);
        assert_eq!(replay_timestamps(&rows), vec![0.0, 1.0, 601.0, 602.0]);
        let rows = records(&[(0.0, false), (3_600.0, false)]);
        assert_eq!(replay_timestamps(&rows), vec![0.0, 3_600.0]);
    }

    #[test]
    fn a_break_on_a_non_finite_timestamp_moves_to_the_next_finite_record() {
        let rows = records(&[(10.0, false), (f64::NAN, true), (3.0, false), (4.0, false)]);
        let replayed = replay_timestamps(&rows);
        assert_eq!(replayed[0], 10.0);
        assert!(replayed[1].is_nan());
        assert_eq!(&replayed[2..], &[610.0, 611.0]);
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
        for recorded in ["", "sim/normal0#ramp-1mps", "é 🚗", &"x/".repeat(300)] {
            let sent = server_vehicle_id(recorded);
            assert!(VehicleId::parse(&sent).is_ok(), "{recorded:?} -> {sent:?}");
        }
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
    fn batches_cover_every_record_once_never_span_a_stream_start_and_keep_counting_seq() {
        let rows = records(&[
            (0.0, false),
            (1.0, false),
            (2.0, false),
            (3.0, false),
            (4.0, false),
            (5.0, false),
        ]);
        let times = replay_timestamps(&rows);
        let shape = |plan: &[Vec<PlannedBatch>]| -> Vec<Vec<(u64, usize, usize)>> {
            plan.iter()
                .map(|stream| {
                    stream
                        .iter()
                        .map(|p| (p.batch.seq, p.first_index, p.batch.samples.len()))
                        .collect()
                })
                .collect()
        };
        let one_stream = plan_streams(&rows[..5], &times[..5], 2, &[0]);
        assert_eq!(
            shape(&one_stream),
            vec![vec![(1, 0, 2), (2, 2, 2), (3, 4, 1)]]
        );
        assert_eq!(one_stream[0][2].batch.samples[0].timestamp_s, 4.0);
        // A reconnect before record 3: batch [2, 3] would span it, so it is cut at 3.
        let reconnected = plan_streams(&rows, &times, 2, &[0, 3]);
        assert_eq!(
            shape(&reconnected),
            vec![vec![(1, 0, 2), (2, 2, 1)], vec![(3, 3, 2), (4, 5, 1)]]
        );
        assert_eq!(
            shape(&plan_streams(&[], &[], 2, &[0])),
            vec![Vec::new()],
            "an empty track is one stream without batches"
        );
    }

    fn drive(id: &str, samples: usize) -> Track {
        Track {
            vehicle_id: id.to_string(),
            records: (0..samples).map(|i| record(i as f64, false)).collect(),
        }
    }

    #[test]
    fn paced_batches_are_due_one_interval_apart_from_a_phase_of_the_vehicle() {
        let options = ReplayOptions {
            rate_hz: 2.0,
            batch_size: 2,
            ..ReplayOptions::default()
        };
        // 5 samples in batches of 2 at 2 samples/s: one batch a second, the last one short.
        let due = batch_due_times(&drive("car-1", 5), &options);
        let phase = due[0].0;
        assert!(phase < Duration::from_secs(1), "{phase:?}");
        let expected: Vec<_> = [(0, 2), (1, 2), (2, 1)]
            .map(|(k, n)| (phase + Duration::from_secs(k), n))
            .into();
        assert_eq!(due, expected);
        // The phase is the vehicle's own: the same every time, another for another vehicle.
        assert_eq!(batch_due_times(&drive("car-1", 1), &options)[0].0, phase);
        let phases: std::collections::BTreeSet<Duration> = (0..20)
            .map(|i| batch_due_times(&drive(&format!("car-{i}"), 1), &options)[0].0)
            .collect();
        assert_eq!(phases.len(), 20);
    }

    #[test]
    fn unpaced_batches_are_all_due_at_the_start() {
        let due = batch_due_times(&drive("car-1", 3), &ReplayOptions::default());
        assert_eq!(due, vec![(Duration::ZERO, 1); 3]);
    }

    #[test]
    fn without_reconnects_there_is_one_stream() {
        let times: Vec<f64> = (0..1000).map(f64::from).collect();
        let mut rng = reconnect_rng(1, "car");
        assert_eq!(stream_starts(&times, 0.0, &mut rng), vec![0]);
    }

    #[test]
    fn reconnects_come_after_about_the_given_recorded_time_and_differ_between_vehicles() {
        // 1 h at 2 Hz with a 20 s gap in the middle.
        let times: Vec<f64> = (0..7200)
            .map(|k| f64::from(k) * 0.5 + if k >= 3600 { 20.0 } else { 0.0 })
            .collect();
        let every_s = 60.0;
        let mut rng = reconnect_rng(7, "car-1");
        let starts = stream_starts(&times, every_s, &mut rng);
        assert_eq!(starts[0], 0);
        let intervals: Vec<f64> = starts
            .windows(2)
            .map(|w| times[w[1]] - times[w[0]])
            .collect();
        assert!(
            (intervals.len() as f64) > 3600.0 / (1.5 * every_s),
            "{intervals:?}"
        );
        for interval in &intervals {
            // The first record at least the drawn interval (30–90 s) after the stream's start; one
            // interval spans the gap and may end up to its 20 s later.
            assert!(
                (30.0..=111.0).contains(interval),
                "{interval} s in {intervals:?}"
            );
        }
        assert!(
            intervals.iter().any(|&i| i < 50.0) && intervals.iter().any(|&i| i > 70.0),
            "jittered: {intervals:?}"
        );
        let again = stream_starts(&times, every_s, &mut reconnect_rng(7, "car-1"));
        assert_eq!(again, starts, "deterministic from seed and vehicle");
        let other_vehicle = stream_starts(&times, every_s, &mut reconnect_rng(7, "car-2"));
        assert_ne!(other_vehicle, starts);
        let other_seed = stream_starts(&times, every_s, &mut reconnect_rng(8, "car-1"));
        assert_ne!(other_seed, starts);
    }

    #[test]
    fn a_non_finite_timestamp_never_starts_a_stream() {
        let times = [f64::NAN, 0.0, 1.0, f64::NAN, 2.0, 3.0, 4.0];
        let mut rng = reconnect_rng(1, "car");
        // Every interval is at least 0.5 × 2 s = 1 s and at most 3 s.
        let starts = stream_starts(&times, 2.0, &mut rng);
        assert_eq!(starts[0], 0);
        assert!(!starts.contains(&1) && !starts.contains(&3), "{starts:?}");
        assert!(starts.len() >= 2, "{starts:?}");
    }

    #[test]
    fn a_negative_or_infinite_reconnect_time_is_refused() {
        for reconnect_every_s in [-1.0, f64::INFINITY, f64::NAN] {
            let options = ReplayOptions {
                reconnect_every_s,
                ..ReplayOptions::default()
            };
            assert!(matches!(
                options.validate(),
                Err(ClientError::InvalidOption {
                    option: "reconnect-every",
                    ..
                })
            ));
        }
    }
}
