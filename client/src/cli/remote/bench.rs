//! `spoofwatch bench`: a load benchmark over loopback.
//!
//! Throughput phase, per vehicle count S: S vehicles, each on its own StreamDetect stream or (with
//! `--vehicles-per-message K`) K per message on S/K StreamDetectFleet gateway streams. Each stream
//! sends its next message as soon as the previous one's reply is back (one outstanding message per
//! stream), or at a given rate, for a fixed time; reports samples/s, the per-message round trip
//! (p50/p99/p99.9/max), the share of the messages due within the phase that were answered (late
//! answers count: the percentiles show lateness), and the server's CPU time per sample (while the
//! phase sends: not opening and closing its streams) and resident memory when its process id is
//! known.
//! Memory phase: opens many short sessions (start + one batch, then the stream closes; the session
//! stays in memory until idle eviction) and reports the server's resident memory before and after.
//!
//! Hand-off phase (`--handoff N`, instead of the others): see [`handoff`].
//! Administrative load beside the throughput phases (`--admin-load`): see [`admin_load`].
//! A shadow model beside them (`--shadow`): see [`shadow`].
//!
//! Streams are driven through the client's `DetectStream` and `FleetDetectStream`; this module owns
//! only the load shape and the measurements. Without `--server` it names `spoofwatch-lab bench`, which
//! runs the same phases against servers in its own process.

use std::sync::Arc;
use std::time::{Duration, Instant};

use crate::connection::{ConnectOptions, Connection};
use crate::detect_stream::DetectStream;
use crate::error::ClientError;
use crate::fleet_stream::FleetDetectStream;
use crate::synthetic::LoopDriver;
pub(crate) use crate::timeline::percentile;
use anyhow::{Context, Result, bail};
use spoofwatch_proto::v1;
use spoofwatch_proto::wire::is_vehicle_id_char;
use tokio::sync::{Barrier, Semaphore};

use super::detect::parse_batch;
use crate::cli::server_flags::OptionalServerArgs;

mod admin_load;
mod h2_streams;
mod handoff;
mod shadow;

use admin_load::AdminLoad;
use shadow::BenchShadow;

/// Sessions opened at once in the memory phase.
const MEMORY_PHASE_CONCURRENCY: usize = 64;
/// Extra time a phase may take beyond its nominal length before it is abandoned.
const PHASE_SLACK: Duration = Duration::from_secs(60);
/// Most concurrent streams in a phase, and most sessions in the memory phase.
const MAX_STREAMS: u32 = 200_000;
const MAX_SESSIONS: u32 = 100_000;

#[derive(Debug, clap::Args)]
pub struct Args {
    #[command(flatten)]
    pub server: OptionalServerArgs,
    /// Concurrent stream counts, one throughput phase each.
    #[arg(long, value_delimiter = ',', default_value = "1,100,1000",
          value_parser = clap::value_parser!(u32).range(1..=i64::from(MAX_STREAMS)))]
    pub streams: Vec<u32>,
    /// Samples per batch (1 to 1000).
    #[arg(long, default_value_t = 10, value_parser = parse_batch)]
    pub batch: usize,
    /// Length of each throughput phase in seconds (up to 600).
    #[arg(long, default_value_t = 5.0, value_parser = parse_seconds)]
    pub seconds: f64,
    /// Seconds each phase's streams send before the measured phase begins (0 to 60): their first
    /// messages after every stream opened at once are neither timed nor counted.
    #[arg(long, default_value_t = 0.0, value_parser = parse_warmup)]
    pub warmup: f64,
    /// Offered load in samples/s over all streams, spread evenly (0: as fast as replies come back,
    /// i.e. saturation). Latency at a given load needs a rate; saturation measures capacity.
    #[arg(long, default_value_t = 0.0)]
    pub rate: f64,
    /// How paced streams' sends are spread over each period: `streams`, each stream at its own
    /// moment; `connections`, the streams of one connection together and the connections spread (a
    /// gateway forwarding its vehicles' fixes of one GNSS second at once).
    #[arg(long, value_enum, default_value_t = Spread::Streams)]
    pub spread: Spread,
    /// Sessions opened in the memory phase (0 skips it).
    #[arg(long, default_value_t = 10_000,
          value_parser = clap::value_parser!(u32).range(0..=i64::from(MAX_SESSIONS)))]
    pub sessions: u32,
    /// Process id of the external --server, to read its resident memory and CPU time from /proc.
    #[arg(long, requires = "server")]
    pub server_pid: Option<u32>,
    /// Streams sharing one HTTP/2 connection (a gateway multiplexes many vehicles on one).
    #[arg(long, default_value_t = 50, value_parser = clap::value_parser!(u32).range(1..=10_000))]
    pub streams_per_connection: u32,
    /// Vehicle ids start with this, so that several load processes can share one server.
    #[arg(long, default_value = "bench", value_parser = parse_prefix)]
    pub vehicle_prefix: String,
    /// Vehicles per message: above 1, the `--streams` vehicles travel this many per message on
    /// StreamDetectFleet (gateway) streams instead of one StreamDetect stream each.
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=1000))]
    pub vehicles_per_message: u32,
    /// Runs an administrator's work beside every throughput phase, on connections of its own:
    /// two clients uploading 100,000-record datasets, one importing a model of about 300,000
    /// parameters, four scoring 1,000-sample Detect calls on such a model, and a health check
    /// every 50 ms. Their timings follow the results table. Needs the admin role.
    #[arg(long, conflicts_with = "handoff")]
    pub admin_load: bool,
    /// Runs a shadow of this model (`models/{id}`) on every vehicle beside the throughput phases;
    /// what it scored and shed follows the results table. Needs the admin role.
    #[arg(long, conflicts_with = "handoff")]
    pub shadow: Option<String>,
    /// Runs only the hand-off phase, with this many vehicles: they stream to --server, then start
    /// on --handoff-to (a replica on the same database), timed to their first detection, beside as
    /// many fresh starts. Without --server, `spoofwatch-lab bench` runs two in-process servers on one
    /// temporary database.
    #[arg(long, default_value_t = 0,
          value_parser = clap::value_parser!(u32).range(0..=i64::from(MAX_SESSIONS)))]
    pub handoff: u32,
    /// The replica the --handoff vehicles move to.
    #[arg(long, requires = "server")]
    pub handoff_to: Option<String>,
    /// --handoff vehicles starting on the new replica at once (1: each alone; N: a whole replica's
    /// vehicles failing over together).
    #[arg(long, default_value_t = 1,
          value_parser = clap::value_parser!(u32).range(1..=i64::from(MAX_SESSIONS)))]
    pub handoff_concurrency: u32,
}

/// How the sends of paced streams are spread over a period.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Spread {
    /// Each stream at its own moment.
    Streams,
    /// The streams of one connection at the same moment, the connections spread.
    Connections,
}

/// A vehicle-id prefix: 1–64 characters that keep the ids valid (letters, digits, `-`, `_`, `.`, `:`).
pub fn parse_prefix(text: &str) -> Result<String, String> {
    // The prefix starts every vehicle id of the run, so it follows the vehicle-id rule.
    let valid = (1..=64).contains(&text.len()) && text.chars().all(is_vehicle_id_char);
    if valid {
        Ok(text.to_string())
    } else {
        Err(format!(
            "must be 1–64 letters, digits, '-', '_', '.' or ':', got {text:?}"
        ))
    }
}

/// Seconds from `text`: a finite number for which `allowed` holds, else an error naming `range`.
fn parse_seconds_where(
    text: &str,
    allowed: impl Fn(f64) -> bool,
    range: &str,
) -> Result<f64, String> {
    let seconds: f64 = text
        .parse()
        .map_err(|_| format!("{text:?} is not a number of seconds"))?;
    if seconds.is_finite() && allowed(seconds) {
        Ok(seconds)
    } else {
        Err(format!("must be {range} seconds, got {text}"))
    }
}

/// A warm-up: 0 to 60 s.
fn parse_warmup(text: &str) -> Result<f64, String> {
    parse_seconds_where(text, |s| (0.0..=60.0).contains(&s), "0 to 60")
}

/// A phase length: more than 0 and at most 600 s.
pub fn parse_seconds(text: &str) -> Result<f64, String> {
    parse_seconds_where(
        text,
        |s| s > 0.0 && s <= 600.0,
        "more than 0 and at most 600",
    )
}

/// VmRSS in kB from a `/proc/<pid>/status` text.
pub fn parse_vm_rss_kb(status: &str) -> Option<u64> {
    status
        .lines()
        .find_map(|line| line.strip_prefix("VmRSS:"))
        .and_then(|rest| rest.split_whitespace().next())
        .and_then(|kb| kb.parse().ok())
}

/// CPU time (user + system, all threads) in seconds from a `/proc/<pid>/stat` text.
pub fn parse_cpu_seconds(stat: &str) -> Option<f64> {
    // The command name (field 2) may contain spaces; the fields after its closing parenthesis are
    // state (3), …, utime (14) and stime (15), in clock ticks of USER_HZ = 100 (a fixed kernel ABI).
    let after_name = &stat[stat.rfind(')')? + 1..];
    let mut fields = after_name.split_whitespace().skip(11);
    let utime: u64 = fields.next()?.parse().ok()?;
    let stime: u64 = fields.next()?.parse().ok()?;
    Some((utime + stime) as f64 / 100.0)
}

/// CPU seconds a process has used so far.
fn cpu_seconds(pid: u32) -> Result<f64> {
    let path = format!("/proc/{pid}/stat");
    let stat = std::fs::read_to_string(&path).with_context(|| format!("reading {path}"))?;
    parse_cpu_seconds(&stat).with_context(|| format!("unexpected format of {path}"))
}

/// Resident memory of a process in kB.
fn resident_kb(pid: u32) -> Result<u64> {
    let path = format!("/proc/{pid}/status");
    let status = std::fs::read_to_string(&path).with_context(|| format!("reading {path}"))?;
    parse_vm_rss_kb(&status).with_context(|| format!("no VmRSS line in {path}"))
}

/// What one stream of a throughput phase measured.
#[derive(Debug, Default)]
struct StreamResult {
    samples: u64,
    /// Batches due by the phase's end at the stream's pace (0 at saturation).
    scheduled: u64,
    latencies: Vec<Duration>,
    error: Option<String>,
}

/// One row of the results table.
#[derive(Debug)]
struct PhaseResult {
    /// Vehicles (one StreamDetect stream each, or `per_message` per gateway message).
    streams: u32,
    per_message: u32,
    samples_per_s: f64,
    batches: usize,
    p50: Option<Duration>,
    p99: Option<Duration>,
    p999: Option<Duration>,
    max: Option<Duration>,
    /// Answered / scheduled batches (paced phases only).
    delivered: Option<f64>,
    /// Server CPU per sample (µs), when its process id is known.
    server_cpu_us_per_sample: Option<f64>,
    /// Server resident memory at the end of the phase (kB), when its process id is known.
    server_rss_kb: Option<u64>,
    errors: usize,
}

/// The benchmark of `--server` (the hand-off phase with `--handoff`).
pub async fn run(args: Args) -> Result<()> {
    let Some(url) = args.server.server.as_deref() else {
        return Err(super::needs_server("bench"));
    };
    let options = args.server.options();
    if args.handoff > 0 {
        let Some(to) = args.handoff_to.as_deref() else {
            bail!("--handoff with --server needs --handoff-to (another replica)");
        };
        return handoff(&args, url, to, options).await;
    }
    load(&args, url, options, args.server_pid).await
}

/// The hand-off phase: `args.handoff` vehicles move from the server at `from` to the one at `to`
/// (a replica on the same database).
pub async fn handoff(args: &Args, from: &str, to: &str, options: ConnectOptions) -> Result<()> {
    // A tag of this run keeps its vehicles apart from an earlier run's on the same database.
    let run = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_millis());
    let prefix = format!("{}-{run}-{}", args.vehicle_prefix, std::process::id());
    let shape = handoff::HandoffShape {
        vehicles: args.handoff,
        concurrency: args.handoff_concurrency,
        batch: args.batch,
        prefix: &prefix,
        per_connection: args.streams_per_connection as usize,
    };
    handoff::handoff_phase(from, to, options, shape).await
}

/// The throughput and memory phases against the server at `url`; `pid` is its process id when
/// known (for its CPU time and resident memory).
pub async fn load(args: &Args, url: &str, options: ConnectOptions, pid: Option<u32>) -> Result<()> {
    // Fail early and readably when the server is not there.
    Connection::connect_with(url, &options).await?;
    if !(args.rate.is_finite() && args.rate >= 0.0) {
        anyhow::bail!("--rate must be a non-negative number of samples per second");
    }
    let load = if args.rate > 0.0 {
        let spread = match args.spread {
            Spread::Streams => "each stream at its own moment of the period",
            Spread::Connections => "the streams of a connection together",
        };
        format!("offered load {} samples/s, {spread}", args.rate)
    } else {
        "saturation (each stream sends as soon as its reply is back)".to_string()
    };
    let carrier = match args.vehicles_per_message {
        1 => "one StreamDetect stream per vehicle".to_string(),
        k => format!("{k} vehicles per message on StreamDetectFleet streams"),
    };
    println!(
        "throughput: {} s per phase, batches of {} samples per vehicle, {carrier}, one outstanding \
         message per stream, {load}",
        args.seconds, args.batch
    );
    let shadow = match &args.shadow {
        Some(model) => Some(BenchShadow::start(url, &options, model).await?),
        None => None,
    };
    let mut results = Vec::new();
    let mut admin_tables = Vec::new();
    for &streams in &args.streams {
        // Each stream sends one batch per `pace` when a rate is given.
        let pace = (args.rate > 0.0)
            .then(|| Duration::from_secs_f64(f64::from(streams) * args.batch as f64 / args.rate));
        let shape = PhaseShape {
            streams,
            per_message: args.vehicles_per_message,
            per_connection: args.streams_per_connection as usize,
            batch: args.batch,
            seconds: args.seconds,
            warmup: args.warmup,
            pace,
            spread: args.spread,
            prefix: &args.vehicle_prefix,
            server_pid: pid,
        };
        let admin = match args.admin_load {
            true => Some(AdminLoad::start(url, &options).await?),
            false => None,
        };
        let phase = throughput_phase(url, options.clone(), shape);
        let limit = Duration::from_secs_f64(args.seconds) + PHASE_SLACK;
        let result = tokio::time::timeout(limit, phase)
            .await
            .with_context(|| format!("the {streams}-stream phase did not finish in {limit:?}"))??;
        results.push(result);
        if let Some(admin) = admin {
            admin_tables.push(admin.finish().await?);
        }
    }
    print!("{}", results_table(&results, args.batch));
    for table in admin_tables {
        print!("\n{table}");
    }
    if let Some(shadow) = shadow {
        print!("\n{}", shadow.finish().await?);
    }

    if args.sessions > 0 {
        let shape = MemoryShape {
            sessions: args.sessions,
            batch: args.batch,
            prefix: &args.vehicle_prefix,
            server_pid: pid,
        };
        memory_phase(url, options, shape).await?;
    }
    Ok(())
}

pub(super) fn ms(d: Option<Duration>) -> String {
    d.map_or_else(|| "-".into(), |d| format!("{:.2}", d.as_secs_f64() * 1e3))
}

fn results_table(results: &[PhaseResult], batch: usize) -> String {
    let mut out = String::from(
        "| vehicles | per message | batch | samples/s | messages | p50 (ms) | p99 (ms) | \
         p99.9 (ms) | max (ms) | delivered | server CPU µs/sample | server RSS (MiB) | errors |\n\
         |---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|\n",
    );
    for r in results {
        out.push_str(&format!(
            "| {} | {} | {batch} | {:.0} | {} | {} | {} | {} | {} | {} | {} | {} | {} |\n",
            r.streams,
            r.per_message,
            r.samples_per_s,
            r.batches,
            ms(r.p50),
            ms(r.p99),
            ms(r.p999),
            ms(r.max),
            r.delivered
                .map_or_else(|| "-".into(), |d| format!("{:.2} %", d * 100.0)),
            r.server_cpu_us_per_sample
                .map_or_else(|| "-".into(), |us| format!("{us:.1}")),
            r.server_rss_kb
                .map_or_else(|| "-".into(), |kb| format!("{:.0}", kb as f64 / 1024.0)),
            r.errors
        ));
    }
    out
}

/// The load of one throughput phase.
struct PhaseShape<'a> {
    /// Vehicles.
    streams: u32,
    /// Vehicles per message (1: a StreamDetect stream each; more: StreamDetectFleet streams).
    per_message: u32,
    per_connection: usize,
    batch: usize,
    seconds: f64,
    warmup: f64,
    /// Each stream sends one batch per pace (`None`: saturation).
    pace: Option<Duration>,
    spread: Spread,
    prefix: &'a str,
    server_pid: Option<u32>,
}

async fn throughput_phase(
    url: &str,
    options: ConnectOptions,
    shape: PhaseShape<'_>,
) -> Result<PhaseResult> {
    let streams = shape.streams;
    let per_message = shape.per_message as usize;
    let count = (streams as usize).div_ceil(per_message);
    let connections = count.div_ceil(shape.per_connection.max(1)).max(1);
    // Paced one-vehicle streams over plaintext go straight on HTTP/2, one task per connection;
    // the rest through tonic, one task per stream.
    let direct = match (shape.pace, per_message) {
        (Some(pace), 1) => h2_streams::Target::plaintext(url, &options).map(|t| (t, pace)),
        _ => None,
    };
    let drivers = if direct.is_some() { connections } else { count };
    // Everyone (and this task) starts measuring once all streams are open.
    let timing = PhaseTiming {
        batch: shape.batch,
        length: Duration::from_secs_f64(shape.seconds),
        warmup: Duration::from_secs_f64(shape.warmup),
        barrier: Arc::new(Barrier::new(drivers + 1)),
        sent_all: Arc::new(Barrier::new(drivers)),
    };
    let (length, warmup, barrier) = (timing.length, timing.warmup, Arc::clone(&timing.barrier));
    let vehicle = |v: usize| (format!("{}-s{streams}-{v}", shape.prefix), v as u64);
    // Paced streams start spread over one period so that not all their messages arrive in
    // lockstep: each stream, or each connection's streams together.
    let offset = |pace: Duration, i: usize| {
        let (place, places) = match shape.spread {
            Spread::Streams => (i, count),
            Spread::Connections => (i % connections, connections),
        };
        pace.mul_f64(place as f64 / places as f64)
    };
    let tasks: Vec<tokio::task::JoinHandle<Vec<StreamResult>>> = if let Some((target, pace)) =
        direct
    {
        (0..connections)
            .map(|c| {
                // Stream i is on connection i % connections, as with tonic's pool.
                let (vehicles, offsets) = (c..count)
                    .step_by(connections)
                    .map(|i| (vehicle(i), offset(pace, i)))
                    .unzip();
                let (target, timing) = (target.clone(), timing.clone());
                tokio::spawn(async move {
                    h2_streams::drive_connection(&target, &timing, vehicles, (pace, offsets)).await
                })
            })
            .collect()
    } else {
        let pool = Connection::pool(url, &options, count, shape.per_connection).await?;
        (0..count)
            .map(|i| {
                let connection = pool[i % pool.len()].clone();
                let load = StreamLoad {
                    timing: timing.clone(),
                    schedule: shape.pace.map(|pace| (pace, offset(pace, i))),
                };
                let first = i * per_message;
                let vehicles: Vec<(String, u64)> = (first
                    ..(first + per_message).min(streams as usize))
                    .map(vehicle)
                    .collect();
                tokio::spawn(async move {
                    let result = if per_message == 1 {
                        let vehicle = vehicles.into_iter().next().unwrap_or_default();
                        let opened = VehicleStream::open(&connection, &load, vehicle);
                        drive(&load, opened).await
                    } else {
                        let opened = GatewayStream::open(&connection, &load, vehicles);
                        drive(&load, opened).await
                    };
                    vec![result]
                })
            })
            .collect()
    };
    barrier.wait().await;
    // The server's CPU time over the measured phase: from the warm-up's end to the end of sending,
    // before the streams close (closing stores every session's snapshot, which is not the cost of
    // a message).
    let cpu_window = shape.server_pid.map(|pid| {
        tokio::spawn(async move {
            tokio::time::sleep(warmup).await;
            let before = cpu_seconds(pid)?;
            tokio::time::sleep(length).await;
            Ok::<_, anyhow::Error>((before, cpu_seconds(pid)?))
        })
    });
    let mut all = Vec::new();
    let mut samples = 0u64;
    let mut scheduled = 0u64;
    let mut errors = 0usize;
    for task in tasks {
        let results = task.await.unwrap_or_else(|e| {
            vec![StreamResult {
                error: Some(format!("stream task failed: {e}")),
                ..StreamResult::default()
            }]
        });
        for result in results {
            samples += result.samples;
            scheduled += result.scheduled;
            all.extend(result.latencies);
            if let Some(error) = result.error {
                if errors == 0 {
                    eprintln!("{streams} streams: {error}");
                }
                errors += 1;
            }
        }
    }
    let cpu = match cpu_window {
        Some(reading) => Some(reading.await.context("reading the server's CPU time")??),
        None => None,
    };
    let server_rss_kb = shape.server_pid.map(resident_kb).transpose()?;
    all.sort_unstable();
    let server_cpu_us_per_sample = match cpu {
        Some((before, after)) if samples > 0 => Some((after - before) * 1e6 / samples as f64),
        _ => None,
    };
    Ok(PhaseResult {
        streams,
        per_message: shape.per_message,
        // The samples counted are those sent in the measured phase.
        samples_per_s: samples as f64 / shape.seconds,
        batches: all.len(),
        p50: percentile(&all, 0.50),
        p99: percentile(&all, 0.99),
        p999: percentile(&all, 0.999),
        max: all.last().copied(),
        delivered: (scheduled > 0).then(|| (all.len() as f64 / scheduled as f64).min(1.0)),
        server_cpu_us_per_sample,
        server_rss_kb,
        errors,
    })
}

/// Batches due within `length` for a stream that sends every `pace` from `offset` on.
fn scheduled_batches(length: Duration, pace: Duration, offset: Duration) -> u64 {
    if offset >= length {
        return 0;
    }
    ((length - offset).as_secs_f64() / pace.as_secs_f64()).ceil() as u64
}

/// What every stream of a phase shares: what it sends, for how long, and where the streams meet.
#[derive(Clone)]
struct PhaseTiming {
    /// Samples per vehicle per message.
    batch: usize,
    length: Duration,
    /// Sent before the measured `length`, untimed and uncounted.
    warmup: Duration,
    barrier: Arc<Barrier>,
    /// Passed by every stream once it has sent its last message: streams close only after that,
    /// so that closing (each closed session's snapshot is stored) does not weigh on the last
    /// messages of the others.
    sent_all: Arc<Barrier>,
}

/// What a stream of a phase is given: what it sends and when.
struct StreamLoad {
    timing: PhaseTiming,
    /// (pace, offset of the first send), or `None` at saturation.
    schedule: Option<(Duration, Duration)>,
}

/// A stream under load: sends message `seq` and returns the samples it carried once its reply is
/// back.
trait LoadStream: Sized {
    async fn send(&mut self, seq: u64) -> Result<u64, ClientError>;
    async fn finish(self) -> Result<(), ClientError>;
}

/// One vehicle on its own StreamDetect stream.
struct VehicleStream {
    stream: DetectStream,
    driver: LoopDriver,
    batch: usize,
}

impl VehicleStream {
    async fn open(
        connection: &Connection,
        load: &StreamLoad,
        (vehicle_id, seed): (String, u64),
    ) -> Result<Self, ClientError> {
        let (stream, _) = DetectStream::start(connection, &vehicle_id, "", true).await?;
        Ok(Self {
            stream,
            driver: LoopDriver::new(seed),
            batch: load.timing.batch,
        })
    }
}

impl LoadStream for VehicleStream {
    async fn send(&mut self, seq: u64) -> Result<u64, ClientError> {
        let samples = self.driver.next_batch(self.batch);
        self.stream.detect(seq, samples).await?;
        Ok(self.batch as u64)
    }

    async fn finish(self) -> Result<(), ClientError> {
        self.stream.finish().await
    }
}

/// Several vehicles on one StreamDetectFleet stream, each message carrying a batch of every one.
struct GatewayStream {
    stream: FleetDetectStream,
    vehicles: Vec<(String, LoopDriver)>,
    batch: usize,
}

impl GatewayStream {
    async fn open(
        connection: &Connection,
        load: &StreamLoad,
        vehicles: Vec<(String, u64)>,
    ) -> Result<Self, ClientError> {
        Ok(Self {
            stream: FleetDetectStream::open(connection).await?,
            vehicles: vehicles
                .into_iter()
                .map(|(id, seed)| (id, LoopDriver::new(seed)))
                .collect(),
            batch: load.timing.batch,
        })
    }
}

impl LoadStream for GatewayStream {
    async fn send(&mut self, seq: u64) -> Result<u64, ClientError> {
        let batch = self.batch;
        let message: Vec<v1::VehicleSamples> = self
            .vehicles
            .iter_mut()
            .map(|(id, driver)| v1::VehicleSamples {
                vehicle_id: id.clone(),
                model: String::new(),
                samples: driver.next_batch(batch),
                // Each run starts its vehicles afresh (their timestamps start over).
                reset: seq == 1,
            })
            .collect();
        let samples = (message.len() * batch) as u64;
        let reply = self.stream.detect(seq, message).await?;
        match reply.iter().find_map(|v| v.error.as_ref()) {
            Some(status) => Err(ClientError::Protocol(format!(
                "a vehicle was refused: {}",
                crate::error::describe_rpc_status(status)
            ))),
            None => Ok(samples),
        }
    }

    async fn finish(self) -> Result<(), ClientError> {
        self.stream.finish().await
    }
}

/// Drives one stream through a phase: messages paced or back to back, one outstanding at a time.
async fn drive<S: LoadStream>(
    load: &StreamLoad,
    opened: impl Future<Output = Result<S, ClientError>>,
) -> StreamResult {
    let opened = opened.await;
    // Every task passes both barriers exactly once, even when its stream failed.
    load.timing.barrier.wait().await;
    let mut result = StreamResult::default();
    let stream = match opened {
        Ok(stream) => send_all(load, stream, &mut result).await,
        Err(error) => {
            result.error = Some(error.to_string());
            None
        }
    };
    load.timing.sent_all.wait().await;
    if let Some(stream) = stream
        && let Err(error) = stream.finish().await
    {
        result.error = Some(error.to_string());
    }
    result
}

/// Sends a stream's messages of the phase; the stream, unless it failed.
async fn send_all<S: LoadStream>(
    load: &StreamLoad,
    mut stream: S,
    result: &mut StreamResult,
) -> Option<S> {
    let measured_from = Instant::now() + load.timing.warmup;
    result.scheduled = load.schedule.map_or(0, |(pace, offset)| {
        scheduled_batches(load.timing.warmup + load.timing.length, pace, offset)
            - scheduled_batches(load.timing.warmup, pace, offset)
    });
    let deadline = measured_from + load.timing.length;
    let mut next_send = load
        .schedule
        .map(|(_, offset)| tokio::time::Instant::now() + offset);
    let mut seq = 0;
    loop {
        // Whether this message is measured: by its slot when paced, else by when it is sent.
        let measured = match (next_send.as_mut(), load.schedule) {
            (Some(at), Some((pace, _))) => {
                // Every slot due before the deadline is sent, even when the wake-up comes later.
                let slot = at.into_std();
                if slot >= deadline {
                    break;
                }
                tokio::time::sleep_until(*at).await;
                *at += pace;
                slot >= measured_from
            }
            _ if Instant::now() >= deadline => break,
            _ => Instant::now() >= measured_from,
        };
        seq += 1;
        let sent = Instant::now();
        match stream.send(seq).await {
            Ok(samples) if measured => {
                result.latencies.push(sent.elapsed());
                result.samples += samples;
            }
            Ok(_) => {}
            Err(error) => {
                result.error = Some(error.to_string());
                return None;
            }
        }
    }
    Some(stream)
}

/// One short session: start, one batch, close.
async fn open_session(
    connection: Connection,
    vehicle_id: String,
    seed: u64,
    batch: usize,
) -> Result<(), ClientError> {
    let (mut stream, _) = DetectStream::start(&connection, &vehicle_id, "", true).await?;
    stream
        .detect(1, LoopDriver::new(seed).next_batch(batch))
        .await?;
    stream.finish().await
}

/// The load of the memory phase.
struct MemoryShape<'a> {
    sessions: u32,
    batch: usize,
    prefix: &'a str,
    server_pid: Option<u32>,
}

async fn memory_phase(url: &str, options: ConnectOptions, shape: MemoryShape<'_>) -> Result<()> {
    let MemoryShape {
        sessions,
        batch,
        prefix,
        server_pid: pid,
    } = shape;
    let before = pid.map(resident_kb).transpose()?;
    let pool = Connection::pool(url, &options, MEMORY_PHASE_CONCURRENCY, 1).await?;
    let permits = Arc::new(Semaphore::new(MEMORY_PHASE_CONCURRENCY));
    let started = Instant::now();
    let work = async {
        let mut tasks = Vec::with_capacity(sessions as usize);
        for i in 0..sessions {
            let permit = Arc::clone(&permits)
                .acquire_owned()
                .await
                .context("the session semaphore closed")?;
            let connection = pool[i as usize % pool.len()].clone();
            let vehicle_id = format!("{prefix}-mem-{i}");
            tasks.push(tokio::spawn(async move {
                let outcome = open_session(connection, vehicle_id, u64::from(i), batch).await;
                drop(permit);
                outcome
            }));
        }
        let mut failed = 0usize;
        let mut first_error = None;
        for task in tasks {
            let outcome = task
                .await
                .map_err(|e| ClientError::Protocol(format!("session task failed: {e}")))
                .and_then(|r| r);
            if let Err(error) = outcome {
                failed += 1;
                first_error.get_or_insert(error.to_string());
            }
        }
        Ok::<_, anyhow::Error>((failed, first_error))
    };
    let limit = Duration::from_secs(sessions as u64 / 10 + 1) + PHASE_SLACK;
    let (failed, first_error) = tokio::time::timeout(limit, work)
        .await
        .with_context(|| format!("the memory phase did not finish in {limit:?}"))??;
    let elapsed = started.elapsed();
    let after = pid.map(resident_kb).transpose()?;
    let opened = u64::from(sessions) - failed as u64;
    println!(
        "memory: opened {opened} sessions (start + one batch of {batch}, then closed) in {:.1} s",
        elapsed.as_secs_f64()
    );
    if let Some(error) = first_error {
        eprintln!("{failed} sessions failed; first error: {error}");
    }
    match (before, after, pid) {
        (Some(before), Some(after), Some(pid)) => {
            let growth = after.saturating_sub(before);
            println!(
                "server resident memory (VmRSS of pid {pid}): {:.1} MiB before, {:.1} MiB after, \
                 +{:.1} MiB = {:.2} KiB per session",
                before as f64 / 1024.0,
                after as f64 / 1024.0,
                growth as f64 / 1024.0,
                if opened > 0 {
                    growth as f64 / opened as f64
                } else {
                    0.0
                }
            );
        }
        _ => println!("server memory: not measured (pass --server-pid PID of the external server)"),
    }
    if failed > 0 && opened == 0 {
        bail!("no session could be opened");
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn vm_rss_is_read_from_proc_status() {
        let status = "Name:\tspoofwatch\nVmPeak:\t  200000 kB\nVmRSS:\t   51234 kB\nThreads:\t4\n";
        assert_eq!(parse_vm_rss_kb(status), Some(51_234));
        assert_eq!(parse_vm_rss_kb("Name:\tx\n"), None);
    }

    #[test]
    fn cpu_time_is_read_from_proc_stat() {
        // utime 250 and stime 50 ticks of 10 ms; the name contains a space and a parenthesis.
        let stat = "4242 (spoof (w) s) S 1 4242 4242 0 -1 4194560 900 0 0 0 250 50 0 0 20 0 9 0";
        assert_eq!(parse_cpu_seconds(stat), Some(3.0));
        assert_eq!(parse_cpu_seconds("4242 (x) S 1"), None);
        assert!(cpu_seconds(std::process::id()).expect("/proc is readable") >= 0.0);
    }

    #[test]
    fn scheduled_batches_count_the_sends_due_in_the_phase() {
        let s = Duration::from_secs;
        assert_eq!(scheduled_batches(s(10), s(1), s(0)), 10);
        assert_eq!(
            scheduled_batches(s(10), s(1), Duration::from_millis(500)),
            10
        );
        assert_eq!(scheduled_batches(s(10), s(3), s(0)), 4);
        assert_eq!(scheduled_batches(s(10), s(20), s(15)), 0);
    }

    #[test]
    fn vehicle_prefixes_keep_ids_valid() {
        assert_eq!(parse_prefix("load-2"), Ok("load-2".to_string()));
        assert!(parse_prefix("").is_err());
        assert!(parse_prefix("a b").is_err());
        assert!(parse_prefix(&"x".repeat(65)).is_err());
    }

    #[test]
    fn this_process_has_a_resident_size() {
        let kb = resident_kb(std::process::id()).expect("/proc is readable on Linux");
        assert!(kb > 0);
    }

    #[test]
    fn phase_lengths_are_bounded() {
        assert_eq!(parse_seconds("5"), Ok(5.0));
        assert!(parse_seconds("0").is_err());
        assert!(parse_seconds("601").is_err());
        assert!(parse_seconds("NaN").is_err());
    }
}
