//! `spoofwatch alarms`: the fleet's confirmed alarms (AlarmService): `list` the stored ones as a
//! table or JSON lines, `watch` onsets, escalations and ends as JSON lines, resuming after
//! reconnects; both filter by the least severity (`--severity`).
//!
//! It owns the command line and the JSON shape of an alarm; the resumable feed is the library's
//! [`AlarmWatch`], tables come from `remote`.

use std::io::Write;
use std::time::Duration;

use crate::alarm_watch::{AlarmWatch, ResumableWatch, WatchCall, WatchOptions};
use crate::error::describe_status;
use anyhow::{Context, Result};
use serde_json::{Value, json};
use spoofwatch_proto::v1;

use super::detect::{severity_name, why_name};
use super::{ResourceArgs, opt, pages_up_to, print_table, time};
use crate::cli::server_flags::ServerArgs;

/// `spoofwatch alarms <command>` with the server flags.
pub type Args = ResourceArgs<Command>;

#[derive(Debug, clap::Subcommand)]
pub enum Command {
    /// List stored alarms in opening order.
    List(ListArgs),
    /// Print alarm onsets, escalations and ends as they happen, one JSON object per line, each
    /// with its cursor; reconnects and resumes after the last cursor when the server is
    /// unavailable.
    Watch(WatchArgs),
}

/// The least severity shown.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, clap::ValueEnum)]
pub enum SeverityArg {
    /// Every alarm (warnings and critical ones).
    #[default]
    Warning,
    /// Only alarms that are critical: opened critical or escalated (for `watch`: critical onsets,
    /// escalations and the ends of critical alarms).
    Critical,
}

impl SeverityArg {
    /// The filter on the wire.
    pub fn to_proto(self) -> v1::AlarmSeverity {
        match self {
            SeverityArg::Warning => v1::AlarmSeverity::Warning,
            SeverityArg::Critical => v1::AlarmSeverity::Critical,
        }
    }
}

/// Which alarms `list` shows.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, clap::ValueEnum)]
pub enum StateArg {
    /// Open and closed.
    #[default]
    Any,
    /// Still on.
    Open,
    /// Ended.
    Closed,
}

#[derive(Debug, clap::Args)]
pub struct ListArgs {
    /// Only this vehicle.
    #[arg(long)]
    pub vehicle: Option<String>,
    /// Only alarms raised by this model (`models/{id}` or `{id}`).
    #[arg(long)]
    pub model: Option<String>,
    /// Only alarms whose onset (server time) is at or after this RFC 3339 time, e.g.
    /// 2025-06-01T00:00:00Z.
    #[arg(long, value_parser = parse_time)]
    pub since: Option<prost_types::Timestamp>,
    /// Only alarms whose onset (server time) is before this RFC 3339 time.
    #[arg(long, value_parser = parse_time)]
    pub until: Option<prost_types::Timestamp>,
    /// Open, closed or any.
    #[arg(long, value_enum, default_value_t)]
    pub state: StateArg,
    /// The least severity listed: warning (every alarm) or critical.
    #[arg(long, value_enum, default_value_t)]
    pub severity: SeverityArg,
    /// At most this many alarms (default: all).
    #[arg(long)]
    pub limit: Option<usize>,
    /// One JSON object per line instead of a table.
    #[arg(long)]
    pub json: bool,
}

#[derive(Debug, clap::Args)]
pub struct WatchArgs {
    /// Only this vehicle's events.
    #[arg(long)]
    pub vehicle: Option<String>,
    /// First replay every event after this cursor (0: every stored event); default: only new
    /// events. Each printed line carries its cursor; pass the last one to resume.
    #[arg(long, value_parser = clap::value_parser!(i64).range(0..))]
    pub after: Option<i64>,
    /// The least severity of the events printed: warning (every event) or critical (critical
    /// onsets, escalations and the ends of critical alarms).
    #[arg(long, value_enum, default_value_t)]
    pub severity: SeverityArg,
    /// Keep reconnecting for this many seconds while the server is unavailable (0: never).
    #[arg(long, default_value_t = 300.0, value_parser = parse_seconds)]
    pub reconnect_for: f64,
    /// Stop after this many events other than `caught_up` (default: never).
    #[arg(long)]
    pub count: Option<u64>,
    /// Stop once caught up (after the `caught_up` line): print what happened after `--after`
    /// and exit.
    #[arg(long)]
    pub until_caught_up: bool,
}

/// Seconds: finite and >= 0.
pub(super) fn parse_seconds(text: &str) -> Result<f64, String> {
    match text.parse::<f64>() {
        Ok(seconds) if seconds.is_finite() && seconds >= 0.0 => Ok(seconds),
        _ => Err(format!("must be a number of seconds >= 0, got {text:?}")),
    }
}

/// An RFC 3339 time.
fn parse_time(text: &str) -> Result<prost_types::Timestamp, String> {
    text.parse()
        .map_err(|_| format!("{text:?} is not an RFC 3339 time such as 2025-06-01T12:00:00Z"))
}

pub async fn run(args: Args) -> Result<()> {
    match args.command {
        Command::List(list) => run_list(&args.server, list).await,
        Command::Watch(watch) => run_watch(&args.server, watch).await,
    }
}

/// The ListAlarms request of `args` (first page).
pub fn list_request(args: &ListArgs) -> v1::ListAlarmsRequest {
    let state = match args.state {
        StateArg::Any => v1::AlarmStateFilter::Unspecified,
        StateArg::Open => v1::AlarmStateFilter::Open,
        StateArg::Closed => v1::AlarmStateFilter::Closed,
    };
    v1::ListAlarmsRequest {
        vehicle_id: args.vehicle.clone().unwrap_or_default(),
        model: args.model.clone().unwrap_or_default(),
        onset_after: args.since,
        onset_before: args.until,
        state: state as i32,
        page_size: 0,
        page_token: String::new(),
        severity: args.severity.to_proto() as i32,
    }
}

async fn run_list(server: &ServerArgs, args: ListArgs) -> Result<()> {
    let connection = server.connect().await?;
    let mut client = connection.alarms();
    let request = list_request(&args);
    let alarms = pages_up_to(
        "listing alarms",
        args.limit.unwrap_or(usize::MAX),
        async |page_token| {
            let request = v1::ListAlarmsRequest {
                page_token,
                ..request.clone()
            };
            client.list_alarms(request).await
        },
        |page| (page.alarms, page.next_page_token),
    )
    .await?;
    if args.json {
        let mut out = std::io::stdout().lock();
        for alarm in &alarms {
            writeln!(out, "{}", alarm_json(alarm))?;
        }
        return Ok(());
    }
    print_table(
        &[
            "id",
            "vehicle",
            "model",
            "severity",
            "onset",
            "end",
            "onset_s",
            "escalated_s",
            "end_s",
            "peak",
            "samples",
            "state",
            "why",
            "offset",
            "credential",
        ],
        &alarms,
        |a| {
            vec![
                a.id.to_string(),
                a.vehicle_id.clone(),
                a.model.clone(),
                severity_name(a.severity).unwrap_or("-").to_string(),
                time(a.onset_time.as_ref()),
                time(a.end_time.as_ref()),
                format!("{:.1}", a.onset_timestamp_s),
                opt(a.escalated_timestamp_s, 1),
                opt(a.end_timestamp_s, 1),
                format!("{:.3}", a.peak_probability),
                a.samples.to_string(),
                if a.open { "open" } else { "closed" }.to_string(),
                why_name(a.why.as_ref()).unwrap_or("-").to_string(),
                a.why.as_ref().map_or_else(
                    || "-".to_string(),
                    |w| format!("{:.0} m @ {:.0}°", w.offset_m, w.offset_bearing_deg),
                ),
                a.credential.clone().unwrap_or_else(|| "-".to_string()),
            ]
        },
    );
    Ok(())
}

async fn run_watch(server: &ServerArgs, args: WatchArgs) -> Result<()> {
    let connection = server.connect().await?;
    let options = WatchOptions {
        vehicle_id: args.vehicle.clone().unwrap_or_default(),
        min_severity: args.severity.to_proto(),
        after_cursor: args.after,
        reconnect_for: Duration::from_secs_f64(args.reconnect_for),
    };
    let watch = AlarmWatch::new(connection, options);
    let caught_up = |event: &v1::AlarmEvent| event.kind == v1::AlarmEventKind::CaughtUp as i32;
    print_watch(
        watch,
        (args.count, args.until_caught_up),
        caught_up,
        event_json,
    )
    .await
}

/// Prints a resumable watch's events as JSON lines, reconnecting (each reconnect noted on standard
/// error) until `count` events other than CAUGHT_UP, the CAUGHT_UP line with `until_caught_up`, or
/// Ctrl-C. Used by `alarms watch` and `incidents watch`.
pub(super) async fn print_watch<C: WatchCall>(
    watch: ResumableWatch<C>,
    (count, until_caught_up): (Option<u64>, bool),
    is_caught_up: impl Fn(&C::Event) -> bool,
    to_json: impl Fn(&C::Event) -> Value,
) -> Result<()> {
    let mut watch = watch.with_reconnect_notice(Box::new(|status, cursor| {
        eprintln!(
            "watch ended ({}); reconnecting{}",
            describe_status(status),
            resume_hint(cursor)
        );
    }));
    let mut events = 0;
    let mut out = std::io::stdout().lock();
    while count.is_none_or(|count| events < count) {
        let next = tokio::select! {
            next = watch.next() => next,
            _ = tokio::signal::ctrl_c() => {
                eprintln!("stopped{}", resume_hint(watch.cursor()));
                return Ok(());
            }
        };
        let event =
            next.with_context(|| format!("the watch ended{}", resume_hint(watch.cursor())))?;
        let caught_up = is_caught_up(&event);
        if !caught_up {
            events += 1;
        }
        writeln!(out, "{}", to_json(&event))?;
        out.flush()?;
        if caught_up && until_caught_up {
            break;
        }
    }
    Ok(())
}

/// `; resume with --after N` when there is a cursor.
pub(super) fn resume_hint(cursor: Option<i64>) -> String {
    cursor.map_or_else(String::new, |c| format!("; resume with --after {c}"))
}

/// An alarm as one JSON object (the shape `list --json` and `watch` print).
pub fn alarm_json(alarm: &v1::Alarm) -> Value {
    let time = |t: Option<&prost_types::Timestamp>| t.map(ToString::to_string);
    json!({
        "id": alarm.id,
        "vehicle_id": alarm.vehicle_id,
        "model": alarm.model,
        "severity": severity_name(alarm.severity),
        "escalated_timestamp_s": alarm.escalated_timestamp_s,
        "escalated_time": time(alarm.escalated_time.as_ref()),
        "onset_timestamp_s": alarm.onset_timestamp_s,
        "end_timestamp_s": alarm.end_timestamp_s,
        "onset_time": time(alarm.onset_time.as_ref()),
        "end_time": time(alarm.end_time.as_ref()),
        "peak_probability": alarm.peak_probability,
        "samples": alarm.samples,
        "open": alarm.open,
        "credential": alarm.credential,
        "why": alarm.why.as_ref().map(|why| json!({
            "dominant": why_name(Some(why)),
            "offset_east_m": why.offset_east_m,
            "offset_north_m": why.offset_north_m,
            "offset_m": why.offset_m,
            "offset_bearing_deg": why.offset_bearing_deg,
            "drift_east_mps": why.drift_east_mps,
            "drift_north_mps": why.drift_north_mps,
            "drift_mps": why.drift_mps,
            "drift_bearing_deg": why.drift_bearing_deg,
        })),
    })
}

/// A watch event as one JSON object: `cursor`, `kind` (`onset`, `escalated`, `end`, `caught_up`)
/// and, except for `caught_up`, the `alarm`.
pub fn event_json(event: &v1::AlarmEvent) -> Value {
    let kind = match v1::AlarmEventKind::try_from(event.kind) {
        Ok(v1::AlarmEventKind::Onset) => "onset",
        Ok(v1::AlarmEventKind::Escalated) => "escalated",
        Ok(v1::AlarmEventKind::End) => "end",
        Ok(v1::AlarmEventKind::CaughtUp) => "caught_up",
        _ => "unknown",
    };
    let mut value = json!({"cursor": event.cursor, "kind": kind});
    if let Some(alarm) = &event.alarm {
        value["alarm"] = alarm_json(alarm);
    }
    value
}
