//! `spoofwatch incidents`: area incidents (vehicles nearby spoofed alike): `list` the stored ones
//! as a table or JSON lines, `get` one, `watch` them open, gain vehicles and end as JSON lines,
//! resuming after reconnects, and `end` or `dismiss` one by hand (an admin, with a reason).
//!
//! It owns the command line and the JSON shape of an incident; the resumable feed is the library's
//! [`IncidentWatch`], tables come from `remote`.

use std::io::Write;
use std::time::Duration;

use anyhow::Result;
use serde_json::{Value, json};
use spoofwatch_proto::v1;

use super::alarms::{parse_seconds, print_watch};
use super::{ResourceArgs, opt, pages_up_to, print_table, time};
use crate::alarm_watch::{IncidentWatch, WatchOptions};
use crate::cli::server_flags::ServerArgs;
use crate::error::reply;

/// `spoofwatch incidents <command>` with the server flags.
pub type Args = ResourceArgs<Command>;

#[derive(Debug, clap::Subcommand)]
pub enum Command {
    /// List stored incidents in id order.
    List(ListArgs),
    /// One incident, with its vehicles, as JSON.
    Get(GetArgs),
    /// Print incidents opening, gaining vehicles and ending as they happen, one JSON object per
    /// line, each with its cursor; reconnects and resumes after the last cursor when the server
    /// is unavailable.
    Watch(WatchArgs),
    /// End an open incident by hand: the threat is over. Its area stops lowering vehicles'
    /// thresholds at once; its vehicles' alarms stay as they are. Needs an admin credential.
    End(EndArgs),
    /// Dismiss an open incident: it was never real (fabricated or mistaken). As `end`, recorded
    /// as dismissed. Needs an admin credential.
    Dismiss(EndArgs),
}

/// Which incidents `list` shows.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, clap::ValueEnum)]
pub enum StateArg {
    /// Open and ended.
    #[default]
    Any,
    Open,
    Ended,
}

#[derive(Debug, clap::Args)]
pub struct ListArgs {
    /// Open, ended or any.
    #[arg(long, value_enum, default_value_t)]
    pub state: StateArg,
    /// At most this many incidents (default: all).
    #[arg(long)]
    pub limit: Option<usize>,
    /// One JSON object per line instead of a table.
    #[arg(long)]
    pub json: bool,
}

#[derive(Debug, clap::Args)]
pub struct GetArgs {
    /// The incident's id.
    pub id: i64,
}

#[derive(Debug, clap::Args)]
pub struct EndArgs {
    /// The incident's id.
    pub id: i64,
    /// Why, for the audit record stored with the incident (1 to 500 characters, one line).
    #[arg(long)]
    pub reason: String,
}

#[derive(Debug, clap::Args)]
pub struct WatchArgs {
    /// First replay every event after this cursor (0: every stored event); default: only new
    /// events. Each printed line carries its cursor; pass the last one to resume.
    #[arg(long, value_parser = clap::value_parser!(i64).range(0..))]
    pub after: Option<i64>,
    /// Keep reconnecting for this many seconds while the server is unavailable (0: never).
    #[arg(long, default_value_t = 300.0, value_parser = parse_seconds)]
    pub reconnect_for: f64,
    /// Stop after this many events (default: never).
    #[arg(long)]
    pub count: Option<u64>,
    /// Stop once caught up (after the `caught_up` line).
    #[arg(long)]
    pub until_caught_up: bool,
}

pub async fn run(args: Args) -> Result<()> {
    match args.command {
        Command::List(list) => run_list(&args.server, list).await,
        Command::Get(get) => run_get(&args.server, get).await,
        Command::Watch(watch) => run_watch(&args.server, watch).await,
        Command::End(end) => run_end(&args.server, end, false).await,
        Command::Dismiss(end) => run_end(&args.server, end, true).await,
    }
}

async fn run_end(server: &ServerArgs, args: EndArgs, dismiss: bool) -> Result<()> {
    let connection = server.connect().await?;
    let request = v1::EndIncidentRequest {
        id: args.id,
        reason: args.reason,
        dismiss,
    };
    let what = if dismiss {
        "dismissing the incident"
    } else {
        "ending the incident"
    };
    let incident = reply(what, connection.alarms().end_incident(request)).await?;
    println!(
        "{}",
        serde_json::to_string_pretty(&incident_json(&incident))?
    );
    Ok(())
}

async fn run_list(server: &ServerArgs, args: ListArgs) -> Result<()> {
    let connection = server.connect().await?;
    let mut client = connection.alarms();
    let state = match args.state {
        StateArg::Any => v1::IncidentStateFilter::Unspecified,
        StateArg::Open => v1::IncidentStateFilter::Open,
        StateArg::Ended => v1::IncidentStateFilter::Ended,
    };
    let incidents = pages_up_to(
        "listing incidents",
        args.limit.unwrap_or(usize::MAX),
        async |page_token| {
            let request = v1::ListIncidentsRequest {
                state: state as i32,
                page_token,
                ..v1::ListIncidentsRequest::default()
            };
            client.list_incidents(request).await
        },
        |page| (page.incidents, page.next_page_token),
    )
    .await?;
    if args.json {
        let mut out = std::io::stdout().lock();
        for incident in &incidents {
            writeln!(out, "{}", incident_json(incident))?;
        }
        return Ok(());
    }
    print_table(
        &[
            "id",
            "kind",
            "state",
            "closed_by",
            "vehicles",
            "opened",
            "ended",
            "centre",
            "radius_km",
            "estimate",
            "confidence",
            "sources",
            "credentials",
        ],
        &incidents,
        |i| {
            vec![
                i.id.to_string(),
                kind_name(i.kind).to_string(),
                state_name(i).to_string(),
                i.closure
                    .as_ref()
                    .map_or_else(|| "-".to_string(), |c| c.closed_by.clone()),
                i.vehicles.len().to_string(),
                time(i.opened_time.as_ref()),
                time(i.ended_time.as_ref()),
                format!("{:.5},{:.5}", i.centre_latitude_deg, i.centre_longitude_deg),
                opt(Some(i.radius_m / 1_000.0), 1),
                estimate(i),
                format!("{:.2}", i.confidence),
                i.sources.to_string(),
                if i.credentials.is_empty() {
                    "-".to_string()
                } else {
                    i.credentials.join("; ")
                },
            ]
        },
    );
    Ok(())
}

async fn run_get(server: &ServerArgs, args: GetArgs) -> Result<()> {
    let connection = server.connect().await?;
    let incident = reply(
        "getting the incident",
        connection
            .alarms()
            .get_incident(v1::GetIncidentRequest { id: args.id }),
    )
    .await?;
    println!(
        "{}",
        serde_json::to_string_pretty(&incident_json(&incident))?
    );
    Ok(())
}

async fn run_watch(server: &ServerArgs, args: WatchArgs) -> Result<()> {
    let connection = server.connect().await?;
    let options = WatchOptions {
        after_cursor: args.after,
        reconnect_for: Duration::from_secs_f64(args.reconnect_for),
        ..WatchOptions::default()
    };
    let watch = IncidentWatch::incidents(connection, &options);
    let caught_up =
        |event: &v1::IncidentEvent| event.kind == v1::IncidentEventKind::CaughtUp as i32;
    print_watch(
        watch,
        (args.count, args.until_caught_up),
        caught_up,
        event_json,
    )
    .await
}

/// `open`, `ended` (on its own or by hand) or `dismissed`.
fn state_name(i: &v1::Incident) -> &'static str {
    match i.closure.as_ref().map(|c| c.kind()) {
        _ if i.open => "open",
        Some(v1::IncidentClosureKind::Dismissed) => "dismissed",
        _ => "ended",
    }
}

/// An admin's closure as JSON (`null` for an incident open or ended on its own).
fn closure_json(closure: Option<&v1::IncidentClosure>) -> Value {
    let Some(c) = closure else {
        return Value::Null;
    };
    let kind = match c.kind() {
        v1::IncidentClosureKind::Ended => "ended",
        v1::IncidentClosureKind::Dismissed => "dismissed",
        v1::IncidentClosureKind::Unspecified => "unknown",
    };
    json!({
        "kind": kind,
        "reason": c.reason,
        "closed_by": c.closed_by,
        "closed_time": c.closed_time.as_ref().map(ToString::to_string),
    })
}

fn kind_name(kind: i32) -> &'static str {
    match v1::IncidentKind::try_from(kind) {
        Ok(v1::IncidentKind::FalsePosition) => "false_position",
        Ok(v1::IncidentKind::Translation) => "translation",
        Ok(v1::IncidentKind::Drift) => "drift",
        _ => "unknown",
    }
}

/// The estimate as a table cell.
fn estimate(i: &v1::Incident) -> String {
    match v1::IncidentKind::try_from(i.kind) {
        Ok(v1::IncidentKind::FalsePosition) => {
            format!(
                "at {:.5},{:.5}",
                i.false_latitude_deg, i.false_longitude_deg
            )
        }
        Ok(v1::IncidentKind::Translation) => {
            format!("{:.0} m E, {:.0} m N", i.offset_east_m, i.offset_north_m)
        }
        Ok(v1::IncidentKind::Drift) => {
            format!(
                "{:.2} m/s E, {:.2} m/s N",
                i.drift_east_mps, i.drift_north_mps
            )
        }
        _ => "-".to_string(),
    }
}

/// An incident as one JSON object (the shape `list --json`, `get` and `watch` print).
pub fn incident_json(i: &v1::Incident) -> Value {
    let time = |t: Option<&prost_types::Timestamp>| t.map(ToString::to_string);
    let kind = v1::IncidentKind::try_from(i.kind).ok();
    let estimate = match kind {
        Some(v1::IncidentKind::FalsePosition) => json!({
            "latitude_deg": i.false_latitude_deg, "longitude_deg": i.false_longitude_deg,
        }),
        Some(v1::IncidentKind::Translation) => json!({
            "offset_east_m": i.offset_east_m, "offset_north_m": i.offset_north_m,
        }),
        Some(v1::IncidentKind::Drift) => json!({
            "drift_east_mps": i.drift_east_mps, "drift_north_mps": i.drift_north_mps,
        }),
        _ => Value::Null,
    };
    json!({
        "id": i.id,
        "kind": kind_name(i.kind),
        "estimate": estimate,
        "open": i.open,
        "centre_latitude_deg": i.centre_latitude_deg,
        "centre_longitude_deg": i.centre_longitude_deg,
        "radius_m": i.radius_m,
        "onset_s": i.onset_s,
        "confirmed_s": i.confirmed_s,
        "last_evidence_s": i.last_evidence_s,
        "ended_s": i.ended_s,
        "confidence": i.confidence,
        "opened_time": time(i.opened_time.as_ref()),
        "ended_time": time(i.ended_time.as_ref()),
        "sources": i.sources,
        "credentials": i.credentials,
        "closure": closure_json(i.closure.as_ref()),
        "vehicles": i.vehicles.iter().map(|v| json!({
            "vehicle_id": v.vehicle_id,
            "alarm_id": v.alarm_id,
            "onset_s": v.onset_s,
            "latitude_deg": v.latitude_deg,
            "longitude_deg": v.longitude_deg,
            "offset_east_m": v.offset_east_m,
            "offset_north_m": v.offset_north_m,
            "drift_east_mps": v.drift_east_mps,
            "drift_north_mps": v.drift_north_mps,
            "alarm_open": v.alarm_open,
            "credential": v.credential,
        })).collect::<Vec<_>>(),
    })
}

/// A watch event as one JSON object: `cursor`, `kind` (`opened`, `joined`, `ended`, `caught_up`)
/// and, except for `caught_up`, the `incident`.
pub fn event_json(event: &v1::IncidentEvent) -> Value {
    let kind = match v1::IncidentEventKind::try_from(event.kind) {
        Ok(v1::IncidentEventKind::Opened) => "opened",
        Ok(v1::IncidentEventKind::Joined) => "joined",
        Ok(v1::IncidentEventKind::Ended) => "ended",
        Ok(v1::IncidentEventKind::CaughtUp) => "caught_up",
        _ => "unknown",
    };
    let mut value = json!({"cursor": event.cursor, "kind": kind});
    if let Some(incident) = &event.incident {
        value["incident"] = incident_json(incident);
    }
    value
}
