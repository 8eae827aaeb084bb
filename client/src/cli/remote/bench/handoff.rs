//! The hand-off phase of `spoofwatch bench` (`--handoff N`): how long a vehicle whose session lives
//! in another replica's snapshot takes to get its first detection on a new replica.
//!
//! 1. Prepare: N vehicles each stream `PREPARE_BATCHES` batches to the first server and end their
//!    streams; the server stores each session's snapshot before it ends the stream.
//! 2. Hand-off: the same vehicles start streams on the second server (which has never held them),
//!    `concurrency` at a time. Per vehicle: start → `SessionAccepted` (the snapshot read from the
//!    shared database and restored) → the next batch's detections. Every one must resume from the
//!    snapshot at the seq it stopped at, or the phase fails.
//! 3. Baseline, side by side: N vehicles the database has never seen start the same way on the
//!    second server (the snapshot lookup finds nothing).
//!
//! Before 2, as many fresh vehicles as start at once warm the second server up, untimed (its
//! database pool opens connections on demand: a cold pool would be charged to the hand-off).
//!
//! Without `--server`, `spoofwatch-lab bench` runs both servers in its process on one temporary
//! SQLite database.

use std::sync::Arc;
use std::time::{Duration, Instant};

use crate::connection::{ConnectOptions, Connection};
use crate::detect_stream::DetectStream;
use crate::error::ClientError;
use crate::synthetic::LoopDriver;
use anyhow::{Context, Result, bail};
use tokio::sync::Semaphore;

use super::{ms, percentile};

/// Batches each vehicle streams to the first server before the hand-off.
const PREPARE_BATCHES: u64 = 6;
/// Vehicles prepared at once on the first server.
const PREPARE_CONCURRENCY: usize = 64;
/// Longest one vehicle's preparation or hand-off may take.
const VEHICLE_LIMIT: Duration = Duration::from_secs(120);

/// What the phase is given.
#[derive(Clone, Copy)]
pub struct HandoffShape<'a> {
    pub vehicles: u32,
    /// Vehicles starting on the second server at once.
    pub concurrency: u32,
    pub batch: usize,
    pub prefix: &'a str,
    pub per_connection: usize,
}

/// One vehicle's start on the second server.
#[derive(Debug, Clone, Copy)]
struct Start {
    /// Start request sent → `SessionAccepted` received.
    accepted: Duration,
    /// Start request sent → the first batch's detections received.
    first_detection: Duration,
}

/// Streams `PREPARE_BATCHES` batches for `vehicle` from a fresh session and ends the stream.
async fn prepare(
    connection: Connection,
    vehicle: String,
    seed: u64,
    batch: usize,
) -> Result<(), ClientError> {
    let (mut stream, _) = DetectStream::start(&connection, &vehicle, "", true).await?;
    let mut driver = LoopDriver::new(seed);
    for seq in 1..=PREPARE_BATCHES {
        stream.detect(seq, driver.next_batch(batch)).await?;
    }
    stream.finish().await
}

/// Starts `vehicle`'s stream and times it to its first detections. `resume_at`: the seq the
/// session must resume from (its snapshot's), or `None` for a vehicle never seen.
async fn start(
    connection: Connection,
    vehicle: String,
    seed: u64,
    batch: usize,
    resume_at: Option<u64>,
) -> Result<Start, ClientError> {
    let mut driver = LoopDriver::new(seed);
    let next_seq = match resume_at {
        // The batches already sent, so the next batch continues the drive.
        Some(last_seq) => {
            for _ in 0..last_seq {
                driver.next_batch(batch);
            }
            last_seq + 1
        }
        None => 1,
    };
    let samples = driver.next_batch(batch);
    let sent = Instant::now();
    let (mut stream, accepted) = DetectStream::start(&connection, &vehicle, "", false).await?;
    let accepted_after = sent.elapsed();
    let expected = resume_at.unwrap_or(0);
    if accepted.last_seq != expected || accepted.from_snapshot != resume_at.is_some() {
        return Err(ClientError::Protocol(format!(
            "{vehicle}: expected to resume at seq {expected} (from a snapshot: {}), the server \
             accepted at {} (from a snapshot: {}; refused: {:?})",
            resume_at.is_some(),
            accepted.last_seq,
            accepted.from_snapshot,
            accepted.snapshot_refused
        )));
    }
    stream.detect(next_seq, samples).await?;
    let first_detection = sent.elapsed();
    stream.finish().await?;
    Ok(Start {
        accepted: accepted_after,
        first_detection,
    })
}

/// Runs `work(i, connection)` for i in 0..count, `concurrency` at a time; fails on the first error.
async fn for_each_vehicle<T, F, Fut>(
    connections: &[Connection],
    count: u32,
    concurrency: usize,
    work: F,
) -> Result<Vec<T>>
where
    T: Send + 'static,
    F: Fn(u32, Connection) -> Fut,
    Fut: Future<Output = Result<T, ClientError>> + Send + 'static,
{
    let permits = Arc::new(Semaphore::new(concurrency.max(1)));
    let mut tasks = Vec::with_capacity(count as usize);
    for i in 0..count {
        let permit = Arc::clone(&permits).acquire_owned().await?;
        let job = work(i, connections[i as usize % connections.len()].clone());
        tasks.push(tokio::spawn(async move {
            let outcome = tokio::time::timeout(VEHICLE_LIMIT, job).await;
            drop(permit);
            outcome
        }));
    }
    let mut out = Vec::with_capacity(tasks.len());
    for (i, task) in tasks.into_iter().enumerate() {
        let outcome = task.await.context("a vehicle task failed")?;
        let value = outcome
            .map_err(|_| anyhow::anyhow!("vehicle {i} took longer than {VEHICLE_LIMIT:?}"))?
            .with_context(|| format!("vehicle {i}"))?;
        out.push(value);
    }
    Ok(out)
}

/// Starts `count` vehicles named `{prefix}-{i}` on `connections`, timed.
async fn timed_starts(
    connections: &[Connection],
    shape: &HandoffShape<'_>,
    name: &str,
    resume_at: Option<u64>,
) -> Result<Vec<Start>> {
    let batch = shape.batch;
    let prefix = format!("{}-{name}", shape.prefix);
    for_each_vehicle(
        connections,
        shape.vehicles,
        shape.concurrency as usize,
        |i, connection| {
            start(
                connection,
                format!("{prefix}-{i}"),
                u64::from(i),
                batch,
                resume_at,
            )
        },
    )
    .await
}

/// One row: the distribution of `starts`.
fn row(label: &str, starts: &[Start]) -> String {
    let mut accepted: Vec<Duration> = starts.iter().map(|s| s.accepted).collect();
    let mut first: Vec<Duration> = starts.iter().map(|s| s.first_detection).collect();
    accepted.sort_unstable();
    first.sort_unstable();
    format!(
        "| {label} | {} | {} | {} | {} | {} | {} |\n",
        starts.len(),
        ms(percentile(&accepted, 0.5)),
        ms(percentile(&accepted, 0.99)),
        ms(percentile(&first, 0.5)),
        ms(percentile(&first, 0.99)),
        ms(first.last().copied()),
    )
}

/// Prepares the vehicles on `from`, then times their hand-off to `to` against fresh starts there.
pub async fn handoff_phase(
    from: &str,
    to: &str,
    options: ConnectOptions,
    shape: HandoffShape<'_>,
) -> Result<()> {
    if from == to {
        bail!("--handoff-to must name another server than --server");
    }
    let count = shape.vehicles as usize;
    let batch = shape.batch;
    let handed = format!("{}-handoff", shape.prefix);
    println!(
        "hand-off: {} vehicles stream {PREPARE_BATCHES} batches of {batch} to {from} and end their \
         streams; then each starts on {to}, {} at a time, and is timed from its start request to \
         SessionAccepted and to the next batch's detections; beside them as many vehicles never \
         seen start there the same way",
        shape.vehicles, shape.concurrency
    );
    let first = Connection::pool(
        from,
        &options,
        count.min(PREPARE_CONCURRENCY),
        shape.per_connection,
    )
    .await?;
    for_each_vehicle(
        &first,
        shape.vehicles,
        PREPARE_CONCURRENCY,
        |i, connection| prepare(connection, format!("{handed}-{i}"), u64::from(i), batch),
    )
    .await
    .context("preparing the vehicles on the first server")?;

    let second = Connection::pool(
        to,
        &options,
        count.min(shape.concurrency as usize),
        shape.per_connection,
    )
    .await?;
    // Untimed: the second server's database connections and the streams' connections warm up.
    let warm_up = HandoffShape {
        vehicles: shape.concurrency.min(shape.vehicles),
        ..shape
    };
    timed_starts(&second, &warm_up, "warm-up", None)
        .await
        .context("warming up the second server")?;
    let resumed = timed_starts(&second, &shape, "handoff", Some(PREPARE_BATCHES))
        .await
        .context("the hand-off to the second server")?;
    let fresh = timed_starts(&second, &shape, "fresh", None)
        .await
        .context("the fresh starts on the second server")?;
    print!(
        "| start on the new replica | vehicles | accepted p50 (ms) | accepted p99 (ms) | \
         first detection p50 (ms) | first detection p99 (ms) | first detection max (ms) |\n\
         |---|---:|---:|---:|---:|---:|---:|\n{}{}",
        row("from the snapshot", &resumed),
        row("fresh (never seen)", &fresh)
    );
    Ok(())
}
