//! Prometheus metrics, recording side: every metric's name, type and help text ([`METRICS`]) and
//! the cheap recording calls the subsystems make. It imports nothing of the server, so every
//! subsystem (the store included) may record; the `GET /metrics` endpoint, which reads the
//! subsystems' state at scrape time, is `crate::metrics_endpoint`.
//!
//! Recording goes through the `metrics` facade. Until [`install`] sets the process-wide Prometheus
//! recorder (only when a metrics listener is configured), every call is a no-op. Counting is per
//! batch, never per sample: one batch is a StreamDetect batch, a Detect call or a StreamDetectFleet
//! message. The per-batch handles are looked up once at install ([`HOT`]), so a scored batch costs a
//! few atomic additions with metrics on and one atomic load with them off; rarer events use the
//! facade's macros (a registry lookup each).
//!
//! Gauges that mirror state kept elsewhere (open sessions, the outbox backlog, jobs by state, the
//! active model) are set by the endpoint at scrape time rather than updated on every change. The
//! recorder is per process: several servers in one process (tests) share the counters.

use std::future::Future;
use std::sync::{Mutex, OnceLock, PoisonError};
use std::time::Instant;

use metrics::{
    Counter, Gauge, Histogram, counter, describe_counter, describe_gauge, describe_histogram,
    gauge, histogram,
};
use metrics_exporter_prometheus::{BuildError, Matcher, PrometheusBuilder, PrometheusHandle};
use spoofwatch_core::severity::Severity;
use tonic::{Code, Status};
use tonic_types::StatusExt;

pub const BUILD_INFO: &str = "spoofwatch_build_info";
pub const ACTIVE_MODEL_INFO: &str = "spoofwatch_active_model_info";
pub const DETECTION_BATCHES: &str = "spoofwatch_detection_batches_total";
pub const DETECTION_SAMPLES: &str = "spoofwatch_detection_samples_total";
pub const DETECTION_ALARMING: &str = "spoofwatch_detection_alarming_samples_total";
pub const DETECTION_BATCH_SECONDS: &str = "spoofwatch_detection_batch_duration_seconds";
pub const REJECTED_BATCHES: &str = "spoofwatch_detection_rejected_batches_total";
pub const DUPLICATE_BATCHES: &str = "spoofwatch_detection_duplicate_batches_total";
pub const REJECTED_SAMPLES: &str = "spoofwatch_detection_rejected_samples_total";
pub const UNAUTHENTICATED: &str = "spoofwatch_unauthenticated_requests_total";
pub const PERMISSION_DENIED: &str = "spoofwatch_permission_denied_total";
pub const IDENTITY_RELOADS: &str = "spoofwatch_identity_reloads_total";
pub const ALARM_ONSETS: &str = "spoofwatch_alarm_onsets_total";
pub const ALARM_ESCALATIONS: &str = "spoofwatch_alarm_escalations_total";
pub const ALARM_ENDS: &str = "spoofwatch_alarm_ends_total";
pub const ALARMS_OPEN: &str = "spoofwatch_alarms_open";
pub const ALARM_BACKLOG: &str = "spoofwatch_alarm_outbox_backlog";
pub const ALARM_STORED: &str = "spoofwatch_alarm_outbox_stored_writes_total";
pub const ALARM_FAILED_BATCHES: &str = "spoofwatch_alarm_outbox_failed_batches_total";
pub const ALARM_DROPPED_ONSETS: &str = "spoofwatch_alarm_outbox_dropped_onsets_total";
pub const ALARM_INVALID: &str = "spoofwatch_alarm_outbox_invalid_writes_total";
pub const INCIDENTS_OPENED: &str = "spoofwatch_incidents_opened_total";
pub const INCIDENT_VEHICLES_JOINED: &str = "spoofwatch_incident_vehicles_joined_total";
pub const INCIDENTS_ENDED: &str = "spoofwatch_incidents_ended_total";
pub const INCIDENT_CORRELATOR: &str = "spoofwatch_incident_correlator_held";
pub const SNAPSHOT_BACKLOG: &str = "spoofwatch_session_snapshots_backlog";
pub const SNAPSHOT_LAG: &str = "spoofwatch_session_snapshots_lag_seconds";
pub const SNAPSHOT_STORED: &str = "spoofwatch_session_snapshots_stored_total";
pub const SNAPSHOT_UNREAD: &str = "spoofwatch_session_snapshots_unread_total";
pub const SESSIONS_OPEN: &str = "spoofwatch_sessions_open";
pub const SESSIONS_CONNECTED: &str = "spoofwatch_sessions_connected";
pub const REPLY_BYTES_QUEUED: &str = "spoofwatch_stream_reply_bytes_queued";
pub const SESSIONS_EVICTED: &str = "spoofwatch_sessions_evicted_total";
pub const SESSIONS_REFUSED: &str = "spoofwatch_sessions_refused_total";
pub const JOBS: &str = "spoofwatch_jobs";
pub const JOBS_FINISHED: &str = "spoofwatch_jobs_finished_total";
pub const STORE_FAULTS: &str = "spoofwatch_store_faults_total";
pub const DB_SECONDS: &str = "spoofwatch_db_operation_duration_seconds";
pub const SHADOW_RUNNING: &str = "spoofwatch_shadow_running";
pub const SHADOW_SAMPLES: &str = "spoofwatch_shadow_samples_total";
pub const SHADOW_QUEUE: &str = "spoofwatch_shadow_queue_samples";
pub const SHADOW_ONSETS: &str = "spoofwatch_shadow_onsets_total";
pub const SHADOW_AGREEMENT: &str = "spoofwatch_shadow_agreement_samples_total";
pub const SHADOW_UNMATCHED: &str = "spoofwatch_shadow_unmatched_episodes_total";
pub const SHADOW_STARTS: &str = "spoofwatch_shadow_vehicle_starts_total";
/// In seconds, Prometheus's base unit of time.
pub const SHADOW_VEHICLE_SECONDS: &str = "spoofwatch_shadow_vehicle_seconds";
pub const SHADOW_BATCH_SECONDS: &str = "spoofwatch_shadow_batch_scoring_seconds";
pub const SHADOW_IDLE_PRIORITY: &str = "spoofwatch_shadow_worker_idle_priority";

/// What kind of Prometheus metric a name is.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Kind {
    Counter,
    Gauge,
    Histogram,
}

/// Every metric: name, kind, and the HELP text (label values are listed with their recording
/// calls below, and in `docs/operating.md`, "Metrics").
pub const METRICS: &[(&str, Kind, &str)] = &[
    (
        BUILD_INFO,
        Kind::Gauge,
        "Always 1; the label `version` is the server's version.",
    ),
    (
        ACTIVE_MODEL_INFO,
        Kind::Gauge,
        "1 for the model that sessions without an explicit model are served (label `model`); 0 for models active earlier in this process.",
    ),
    (
        DETECTION_BATCHES,
        Kind::Counter,
        "Batches scored, by `rpc` (a StreamDetect batch, a Detect call or a StreamDetectFleet message).",
    ),
    (
        DETECTION_SAMPLES,
        Kind::Counter,
        "Samples scored, by `rpc`; each returned one detection.",
    ),
    (
        DETECTION_ALARMING,
        Kind::Counter,
        "Detections returned with the alarm on, by `rpc`.",
    ),
    (
        DETECTION_BATCH_SECONDS,
        Kind::Histogram,
        "Time to score one batch, from its arrival to its reply (session lock wait included), by `rpc`.",
    ),
    (
        REJECTED_BATCHES,
        Kind::Counter,
        "Batches refused, by `rpc` and `reason` (a fleet vehicle's entry counts as a batch of its own).",
    ),
    (
        DUPLICATE_BATCHES,
        Kind::Counter,
        "Resent batches acknowledged without scoring (their seq was already applied), by `rpc` (a fleet vehicle's entry counts as a batch).",
    ),
    (
        REJECTED_SAMPLES,
        Kind::Counter,
        "Samples in refused batches, by `rpc` and `reason`.",
    ),
    (
        UNAUTHENTICATED,
        Kind::Counter,
        "API calls refused as unidentified: no credential, a wrong or revoked bearer token, or a revoked or unusable client certificate.",
    ),
    (
        PERMISSION_DENIED,
        Kind::Counter,
        "API calls refused because the caller's role or vehicles do not include them, by `role` and `method` (the gRPC path).",
    ),
    (
        IDENTITY_RELOADS,
        Kind::Counter,
        "Changes of the roles file or the admin token file, by `result` (applied, or refused: the previous identities stay).",
    ),
    (
        ALARM_ONSETS,
        Kind::Counter,
        "Alarm onsets (a vehicle's confirmed spoofing alarm turned on), by the `severity` it opened with (warning, critical).",
    ),
    (
        ALARM_ESCALATIONS,
        Kind::Counter,
        "Open warning alarms that turned critical (`severity` is always critical).",
    ),
    (
        ALARM_ENDS,
        Kind::Counter,
        "Alarm ends (the alarm turned off, or its session reset, changed model, was evicted or the server stopped), by the `severity` it ended with.",
    ),
    (
        ALARMS_OPEN,
        Kind::Gauge,
        "Alarms on right now, by `severity` (warning, critical).",
    ),
    (
        ALARM_BACKLOG,
        Kind::Gauge,
        "Alarm events waiting in the outbox to be stored.",
    ),
    (
        ALARM_STORED,
        Kind::Counter,
        "Alarm events (onsets, escalations and ends) stored in the database.",
    ),
    (
        ALARM_FAILED_BATCHES,
        Kind::Counter,
        "Outbox write batches the database refused (each is retried).",
    ),
    (
        ALARM_DROPPED_ONSETS,
        Kind::Counter,
        "Alarm onsets not stored because the outbox was full.",
    ),
    (
        ALARM_INVALID,
        Kind::Counter,
        "Alarm events not stored because of invalid values.",
    ),
    (
        INCIDENTS_OPENED,
        Kind::Counter,
        "Area incidents opened by this server's correlator (vehicles nearby spoofed alike).",
    ),
    (
        INCIDENT_VEHICLES_JOINED,
        Kind::Counter,
        "Vehicles that joined an open area incident, by this server's correlator.",
    ),
    (
        INCIDENTS_ENDED,
        Kind::Counter,
        "Area incidents ended: by this server's correlator, or by hand through this server (EndIncident).",
    ),
    (
        INCIDENT_CORRELATOR,
        Kind::Gauge,
        "1 while this server holds the database's incident correlator lease (one server of a database at a time), else 0.",
    ),
    (
        SNAPSHOT_BACKLOG,
        Kind::Gauge,
        "Session snapshots waiting to be stored (at most one per vehicle).",
    ),
    (
        SNAPSHOT_LAG,
        Kind::Gauge,
        "How long the oldest session snapshot waiting to be stored has waited, in seconds (0 when none waits): a vehicle handed over now continues from up to this much earlier.",
    ),
    (
        SNAPSHOT_STORED,
        Kind::Counter,
        "Session snapshots stored (hand-off state of vehicle sessions).",
    ),
    (
        SESSIONS_OPEN,
        Kind::Gauge,
        "Vehicle sessions held in memory.",
    ),
    (
        SESSIONS_CONNECTED,
        Kind::Gauge,
        "Vehicle sessions with a live StreamDetect stream.",
    ),
    (
        REPLY_BYTES_QUEUED,
        Kind::Gauge,
        "Bytes of encoded replies the detection streams hold for their clients to read.",
    ),
    (
        SESSIONS_EVICTED,
        Kind::Counter,
        "Sessions evicted after being idle without a stream.",
    ),
    (
        SNAPSHOT_UNREAD,
        Kind::Counter,
        "Streams refused (UNAVAILABLE, to be retried) because their vehicle's stored session could \
         not be read in time.",
    ),
    (
        SESSIONS_REFUSED,
        Kind::Counter,
        "New sessions refused because the session table was full (--max-sessions).",
    ),
    (
        JOBS,
        Kind::Gauge,
        "Training and evaluation jobs in this process, by `state` (queued, running).",
    ),
    (
        JOBS_FINISHED,
        Kind::Counter,
        "Jobs finished, by `state` (succeeded, failed, cancelled).",
    ),
    (
        STORE_FAULTS,
        Kind::Counter,
        "Database faults seen, by `kind` (full, read_only, io, busy, cant_open, corrupt, lost, closed, unreachable).",
    ),
    (
        DB_SECONDS,
        Kind::Histogram,
        "Time of selected database writes, by `op` (alarm_batch_write, job_create, job_start, job_progress, job_finish).",
    ),
    (
        SHADOW_RUNNING,
        Kind::Gauge,
        "1 while a shadow runs (its candidate labelled `model`), else 0.",
    ),
    (
        SHADOW_SAMPLES,
        Kind::Counter,
        "Samples of shadowed vehicles, by `outcome`: `scored` by the candidate, or `shed` (the queue was full or the shadow's CPU budget spent; the live reply never waits).",
    ),
    (
        SHADOW_QUEUE,
        Kind::Gauge,
        "Samples waiting for the shadow's worker (bounded; beyond it work is shed).",
    ),
    (
        SHADOW_ONSETS,
        Kind::Counter,
        "Alarm episodes begun on shadowed vehicles while both models scored, by `model` (`live` or `shadow`) and `level` (`warning`: every episode; `critical`: those that were or turned critical). The shadow's are would-be alarms, never paged.",
    ),
    (
        SHADOW_AGREEMENT,
        Kind::Counter,
        "Samples both models scored, by what each said: `live` and `shadow`, each `alarm` or `quiet`.",
    ),
    (
        SHADOW_UNMATCHED,
        Kind::Counter,
        "Ended alarm episodes of one `model` (`live` or `shadow`) during which the other never alarmed.",
    ),
    (
        SHADOW_STARTS,
        Kind::Counter,
        "Vehicle shadow states started, by `reason`: `first` (first sample on this process: also after a restart or hand-off), `shed`, `idle` (let go after sitting idle) or `reset` (the live session restarted its time line).",
    ),
    (
        SHADOW_VEHICLE_SECONDS,
        Kind::Gauge,
        "Vehicle-hours the running shadow covered on this process (the denominator of onsets per vehicle-hour).",
    ),
    (
        SHADOW_BATCH_SECONDS,
        Kind::Histogram,
        "The candidate's scoring time per batch, off the request path (its CPU cost).",
    ),
    (
        SHADOW_IDLE_PRIORITY,
        Kind::Gauge,
        "1 when the shadow's worker thread runs at idle CPU priority (Linux SCHED_IDLE: it gets a core only when nothing else wants it), 0 when that could not be set and it runs at the lowest nice value instead.",
    ),
];

/// The detection RPCs, the values of the `rpc` label.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Rpc {
    StreamDetect,
    Detect,
    StreamDetectFleet,
}

impl Rpc {
    /// In the order of their index into [`HOT`].
    const ALL: [Rpc; 3] = [Rpc::StreamDetect, Rpc::Detect, Rpc::StreamDetectFleet];

    fn index(self) -> usize {
        self as usize
    }

    fn label(self) -> &'static str {
        match self {
            Rpc::StreamDetect => "StreamDetect",
            Rpc::Detect => "Detect",
            Rpc::StreamDetectFleet => "StreamDetectFleet",
        }
    }
}

/// The values of the `reason` label of refused batches: a small fixed set.
pub const REJECTION_REASONS: [&str; 10] = [
    "batch_size",
    "invalid_sample",
    "invalid_request",
    "too_large",
    "session_limit",
    "model_not_found",
    "no_active_model",
    "unavailable",
    "permission_denied",
    "other",
];

/// The `reason` of a refusal: INVALID_ARGUMENT by the class of its first violated field (the
/// batch's sample count, a sample's value or time, or anything else of the request), every other
/// code by what it means at the detection edge.
pub fn rejection_reason(status: &Status) -> &'static str {
    match status.code() {
        Code::InvalidArgument => {
            let field = status
                .get_details_bad_request()
                .and_then(|bad| bad.field_violations.into_iter().next())
                .map(|violation| violation.field)
                .unwrap_or_default();
            if field.ends_with("samples") {
                "batch_size"
            } else if field.contains("samples[") {
                "invalid_sample"
            } else {
                "invalid_request"
            }
        }
        Code::OutOfRange => "too_large",
        Code::ResourceExhausted => "session_limit",
        Code::NotFound => "model_not_found",
        Code::FailedPrecondition => "no_active_model",
        Code::Unavailable => "unavailable",
        Code::PermissionDenied => "permission_denied",
        _ => "other",
    }
}

/// Buckets of the batch latency: a sample costs a few µs, a batch holds up to 1,000 of them.
const BATCH_BUCKETS: [f64; 14] = [
    0.000_05, 0.000_1, 0.000_25, 0.000_5, 0.001, 0.002_5, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5,
    1.0,
];
/// Buckets of database writes: SQLite commits take milliseconds, a busy or failing disk seconds.
const DB_BUCKETS: [f64; 12] = [
    0.000_5, 0.001, 0.002_5, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 5.0,
];

/// The process-wide recorder's handle, once installed.
static HANDLE: Mutex<Option<PrometheusHandle>> = Mutex::new(None);

/// The handles a scored batch updates, per [`Rpc`] (set once the recorder is installed).
struct BatchHandles {
    batches: Counter,
    samples: Counter,
    alarming: Counter,
    latency: Histogram,
}

static HOT: OnceLock<[BatchHandles; 3]> = OnceLock::new();
/// [`REPLY_BYTES_QUEUED`]'s handle (set once the recorder is installed): it changes twice a reply.
static REPLY_BYTES: OnceLock<Gauge> = OnceLock::new();

/// Installs the Prometheus recorder (once per process; later calls return the same handle),
/// describes every metric and sets the labelled counters to zero so that they are scraped before
/// their first event; `store_fault_kinds` are the `kind` labels of [`STORE_FAULTS`].
pub fn install(
    store_fault_kinds: impl IntoIterator<Item = &'static str>,
) -> Result<PrometheusHandle, BuildError> {
    let mut installed = HANDLE.lock().unwrap_or_else(PoisonError::into_inner);
    if let Some(handle) = installed.as_ref() {
        return Ok(handle.clone());
    }
    let handle = PrometheusBuilder::new()
        .set_buckets_for_metric(
            Matcher::Full(DETECTION_BATCH_SECONDS.into()),
            &BATCH_BUCKETS,
        )?
        .set_buckets_for_metric(Matcher::Full(DB_SECONDS.into()), &DB_BUCKETS)?
        .set_buckets_for_metric(Matcher::Full(SHADOW_BATCH_SECONDS.into()), &BATCH_BUCKETS)?
        .install_recorder()?;
    for &(name, kind, help) in METRICS {
        match kind {
            Kind::Counter => describe_counter!(name, help),
            Kind::Gauge => describe_gauge!(name, help),
            Kind::Histogram => describe_histogram!(name, help),
        }
    }
    gauge!(BUILD_INFO, "version" => env!("CARGO_PKG_VERSION")).set(1);
    let _ = HOT.set(Rpc::ALL.map(|rpc| BatchHandles {
        batches: counter!(DETECTION_BATCHES, "rpc" => rpc.label()),
        samples: counter!(DETECTION_SAMPLES, "rpc" => rpc.label()),
        alarming: counter!(DETECTION_ALARMING, "rpc" => rpc.label()),
        latency: histogram!(DETECTION_BATCH_SECONDS, "rpc" => rpc.label()),
    }));
    for rpc in Rpc::ALL {
        for name in [
            DETECTION_BATCHES,
            DETECTION_SAMPLES,
            DETECTION_ALARMING,
            DUPLICATE_BATCHES,
        ] {
            counter!(name, "rpc" => rpc.label()).increment(0);
        }
        for reason in REJECTION_REASONS {
            counter!(REJECTED_BATCHES, "rpc" => rpc.label(), "reason" => reason).increment(0);
            counter!(REJECTED_SAMPLES, "rpc" => rpc.label(), "reason" => reason).increment(0);
        }
    }
    for severity in Severity::ALL {
        let severity = severity.name();
        counter!(ALARM_ONSETS, "severity" => severity).increment(0);
        counter!(ALARM_ENDS, "severity" => severity).increment(0);
        gauge!(ALARMS_OPEN, "severity" => severity).increment(0.0);
    }
    counter!(ALARM_ESCALATIONS, "severity" => Severity::Critical.name()).increment(0);
    for name in [
        UNAUTHENTICATED,
        SESSIONS_EVICTED,
        SESSIONS_REFUSED,
        SNAPSHOT_UNREAD,
        INCIDENTS_OPENED,
        INCIDENT_VEHICLES_JOINED,
        INCIDENTS_ENDED,
    ] {
        counter!(name).increment(0);
    }
    gauge!(INCIDENT_CORRELATOR).increment(0.0);
    let _ = REPLY_BYTES.set(gauge!(REPLY_BYTES_QUEUED));
    gauge!(REPLY_BYTES_QUEUED).increment(0.0);
    for result in ["applied", "refused"] {
        counter!(IDENTITY_RELOADS, "result" => result).increment(0);
    }
    for kind in store_fault_kinds {
        counter!(STORE_FAULTS, "kind" => kind).increment(0);
    }
    for state in ["succeeded", "failed", "cancelled"] {
        counter!(JOBS_FINISHED, "state" => state).increment(0);
    }
    register_shadow_metrics();
    *installed = Some(handle.clone());
    Ok(handle)
}

/// A batch was scored: `samples` detections returned, `alarming` of them with the alarm on.
pub fn batch_scored(rpc: Rpc, samples: usize, alarming: usize, started: Instant) {
    let Some(hot) = HOT.get() else {
        return;
    };
    let handles = &hot[rpc.index()];
    handles.latency.record(started.elapsed());
    handles.batches.increment(1);
    handles.samples.increment(samples as u64);
    handles.alarming.increment(alarming as u64);
}

/// A batch of `samples` samples was refused with `status`.
pub fn batch_rejected(rpc: Rpc, status: &Status, samples: usize) {
    let (rpc, reason) = (rpc.label(), rejection_reason(status));
    counter!(REJECTED_BATCHES, "rpc" => rpc, "reason" => reason).increment(1);
    counter!(REJECTED_SAMPLES, "rpc" => rpc, "reason" => reason).increment(samples as u64);
}

/// A detection stream ended with `status` from the transport: counted as a refused batch when the
/// message was over the size limit (other transport errors are the client going away).
pub fn stream_failed(rpc: Rpc, status: &Status) {
    if status.code() == Code::OutOfRange {
        batch_rejected(rpc, status, 0);
    }
}

/// The detection streams' reply buffers took (`bytes` > 0) or gave back (< 0) encoded bytes.
pub fn reply_bytes_queued(bytes: f64) {
    if let Some(gauge) = REPLY_BYTES.get() {
        gauge.increment(bytes);
    }
}

/// A resent batch was acknowledged without scoring.
pub fn batch_duplicate(rpc: Rpc) {
    counter!(DUPLICATE_BATCHES, "rpc" => rpc.label()).increment(1);
}

/// An API call was refused as unidentified.
pub fn unauthenticated() {
    counter!(UNAUTHENTICATED).increment(1);
}

/// An API call was refused for its caller's role or vehicles.
pub fn permission_denied(role: &'static str, method: &'static str) {
    counter!(PERMISSION_DENIED, "role" => role, "method" => method).increment(1);
}

/// The identity files changed: `applied`, or refused (the previous identities stay).
pub fn identities_reloaded(applied: bool) {
    let result = if applied { "applied" } else { "refused" };
    counter!(IDENTITY_RELOADS, "result" => result).increment(1);
}

/// An alarm turned on as `severity`.
pub fn alarm_onset(severity: Severity) {
    counter!(ALARM_ONSETS, "severity" => severity.name()).increment(1);
    gauge!(ALARMS_OPEN, "severity" => severity.name()).increment(1.0);
}

/// An open warning turned critical.
pub fn alarm_escalated() {
    let (warning, critical) = (Severity::Warning.name(), Severity::Critical.name());
    counter!(ALARM_ESCALATIONS, "severity" => critical).increment(1);
    gauge!(ALARMS_OPEN, "severity" => warning).decrement(1.0);
    gauge!(ALARMS_OPEN, "severity" => critical).increment(1.0);
}

/// An alarm of `severity` turned off (or its session ended while alarming).
pub fn alarm_end(severity: Severity) {
    counter!(ALARM_ENDS, "severity" => severity.name()).increment(1);
    gauge!(ALARMS_OPEN, "severity" => severity.name()).decrement(1.0);
}

/// This server took (or lost) the incident correlator's lease.
pub fn incident_correlator_held(held: bool) {
    gauge!(INCIDENT_CORRELATOR).set(if held { 1.0 } else { 0.0 });
}

/// An area incident opened.
pub fn incident_opened() {
    counter!(INCIDENTS_OPENED).increment(1);
}

/// A vehicle joined an open area incident.
pub fn incident_vehicle_joined() {
    counter!(INCIDENT_VEHICLES_JOINED).increment(1);
}

/// An area incident ended.
pub fn incident_ended() {
    counter!(INCIDENTS_ENDED).increment(1);
}

/// `count` idle sessions were evicted.
pub fn sessions_evicted(count: usize) {
    counter!(SESSIONS_EVICTED).increment(count as u64);
}

/// A new session was refused: the table is full.
pub fn session_refused() {
    counter!(SESSIONS_REFUSED).increment(1);
}

/// A stream was refused because its vehicle's stored session could not be read.
pub fn snapshot_unread() {
    counter!(SNAPSHOT_UNREAD).increment(1);
}

/// A job finished in `state` (succeeded, failed or cancelled).
pub fn job_finished(state: &'static str) {
    counter!(JOBS_FINISHED, "state" => state).increment(1);
}

/// A database fault of `kind` (a `FaultKind` label) was seen.
pub fn store_fault(kind: &'static str) {
    counter!(STORE_FAULTS, "kind" => kind).increment(1);
}

/// The shadow's labelled counters at zero, so that they are scraped before their first event.
fn register_shadow_metrics() {
    for outcome in ["scored", "shed"] {
        counter!(SHADOW_SAMPLES, "outcome" => outcome).increment(0);
    }
    for model in ["live", "shadow"] {
        for level in ["warning", "critical"] {
            counter!(SHADOW_ONSETS, "model" => model, "level" => level).increment(0);
        }
        counter!(SHADOW_UNMATCHED, "model" => model).increment(0);
    }
    for live in ["alarm", "quiet"] {
        for shadow in ["alarm", "quiet"] {
            counter!(SHADOW_AGREEMENT, "live" => live, "shadow" => shadow).increment(0);
        }
    }
    for reason in ["first", "shed", "idle", "reset"] {
        counter!(SHADOW_STARTS, "reason" => reason).increment(0);
    }
    gauge!(SHADOW_QUEUE).set(0.0);
    gauge!(SHADOW_VEHICLE_SECONDS).set(0.0);
}

/// `n` samples of shadowed vehicles were `scored` or `shed`.
pub fn shadow_samples(outcome: &'static str, n: u64) {
    counter!(SHADOW_SAMPLES, "outcome" => outcome).increment(n);
}

/// `n` episodes of `model` began at `level`.
pub fn shadow_onsets(model: &'static str, level: &'static str, n: u64) {
    if n > 0 {
        counter!(SHADOW_ONSETS, "model" => model, "level" => level).increment(n);
    }
}

/// `n` samples on which the live model said `live` and the candidate `shadow`.
pub fn shadow_agreement(live: &'static str, shadow: &'static str, n: u64) {
    if n > 0 {
        counter!(SHADOW_AGREEMENT, "live" => live, "shadow" => shadow).increment(n);
    }
}

/// `n` ended episodes of `model` during which the other model never alarmed.
pub fn shadow_unmatched(model: &'static str, n: u64) {
    if n > 0 {
        counter!(SHADOW_UNMATCHED, "model" => model).increment(n);
    }
}

/// `n` vehicle shadow states started for `reason`.
pub fn shadow_vehicle_starts(reason: &'static str, n: u64) {
    if n > 0 {
        counter!(SHADOW_STARTS, "reason" => reason).increment(n);
    }
}

/// The candidate scored one batch in `elapsed`; `queued` samples wait, and the running shadow
/// covered `vehicle_hours` on this process.
pub fn shadow_batch(elapsed: std::time::Duration, queued: usize, vehicle_hours: f64) {
    histogram!(SHADOW_BATCH_SECONDS).record(elapsed);
    gauge!(SHADOW_QUEUE).set(queued as f64);
    gauge!(SHADOW_VEHICLE_SECONDS).set(vehicle_hours * 3_600.0);
}

/// The shadow's worker thread runs at idle CPU priority (`idle`) or at the fallback.
pub fn shadow_worker_idle_priority(idle: bool) {
    gauge!(SHADOW_IDLE_PRIORITY).set(if idle { 1.0 } else { 0.0 });
}

/// A shadow of `model` started (`running`) or stopped on this process.
pub fn shadow_running(model: &str, running: bool) {
    gauge!(SHADOW_RUNNING, "model" => model.to_string()).set(if running { 1.0 } else { 0.0 });
    if !running {
        gauge!(SHADOW_VEHICLE_SECONDS).set(0.0);
    }
}

/// Runs the database operation `op` and records how long it took (also when it failed).
pub async fn db_timed<F: Future>(op: &'static str, operation: F) -> F::Output {
    let started = Instant::now();
    let output = operation.await;
    histogram!(DB_SECONDS, "op" => op).record(started.elapsed());
    output
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::status::{invalid_field, not_found, resource_exhausted, shutting_down};

    #[test]
    fn refusals_are_classed_by_their_first_field_or_their_code() {
        // Every reason is one of the label values registered at zero.
        let reason = |status: Status| {
            let reason = rejection_reason(&status);
            assert!(REJECTION_REASONS.contains(&reason), "{reason}");
            reason
        };
        assert_eq!(
            reason(invalid_field("batch.samples", "must hold 1 to 1000")),
            "batch_size"
        );
        assert_eq!(
            reason(invalid_field("vehicles[2].samples", "must hold 1 to 1000")),
            "batch_size"
        );
        assert_eq!(
            reason(invalid_field(
                "batch.samples[3].latitude_deg",
                "must be finite"
            )),
            "invalid_sample"
        );
        assert_eq!(
            reason(invalid_field(
                "vehicles[0].samples[1].timestamp_s",
                "goes backwards"
            )),
            "invalid_sample"
        );
        assert_eq!(
            reason(invalid_field("start.vehicle_id", "required")),
            "invalid_request"
        );
        assert_eq!(
            reason(Status::invalid_argument("no details")),
            "invalid_request"
        );
        assert_eq!(reason(Status::out_of_range("too large")), "too_large");
        assert_eq!(reason(resource_exhausted("full")), "session_limit");
        assert_eq!(reason(not_found("model", "models/x")), "model_not_found");
        assert_eq!(reason(shutting_down()), "unavailable");
        assert_eq!(reason(Status::internal("bug")), "other");
    }

    #[test]
    fn every_metric_is_named_once_with_its_unit_and_help() {
        let mut names: Vec<&str> = METRICS.iter().map(|(name, _, _)| *name).collect();
        names.sort_unstable();
        names.dedup();
        assert_eq!(names.len(), METRICS.len(), "a name is listed twice");
        for &(name, kind, help) in METRICS {
            assert!(name.starts_with("spoofwatch_"), "{name}");
            assert!(!help.is_empty(), "{name} has no help text");
            match kind {
                Kind::Counter => assert!(name.ends_with("_total"), "{name}"),
                Kind::Histogram => assert!(name.ends_with("_seconds"), "{name}"),
                Kind::Gauge => assert!(!name.ends_with("_total"), "{name}"),
            }
        }
    }
}
