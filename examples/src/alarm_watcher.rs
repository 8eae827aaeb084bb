//! An alarm watcher: follows the fleet's alarm events from a cursor. It first replays what was
//! stored after the cursor, then says CAUGHT_UP, then follows live events; a consumer keeps the
//! last cursor it handled and resumes from it after a restart, on any replica.

use std::io::Write;

use spoofwatch_proto::v1;
use spoofwatch_proto::v1::alarm_service_client::AlarmServiceClient;

use crate::Error;

/// Follows alarm events after `after_cursor` (`None`: only events from now on) at `url`, writing
/// one line per event to `out`; with `stop_when_caught_up` it returns once the replay is done.
/// Returns the last cursor seen (to resume from).
pub async fn run(
    url: &str,
    after_cursor: Option<i64>,
    stop_when_caught_up: bool,
    out: &mut impl Write,
) -> Result<i64, Error> {
    let mut client = AlarmServiceClient::connect(url.to_string()).await?;
    let request = v1::WatchAlarmsRequest {
        vehicle_id: String::new(), // the whole fleet
        after_cursor,
        stop_when_caught_up,
        // Every event: warnings and critical ones (CRITICAL would send only what pages).
        severity: v1::AlarmSeverity::Unspecified as i32,
    };
    let mut events = client.watch_alarms(request).await?.into_inner();
    let mut cursor = after_cursor.unwrap_or(0);
    while let Some(event) = events.message().await? {
        cursor = event.cursor;
        match (event.kind(), event.alarm) {
            (v1::AlarmEventKind::CaughtUp, _) => writeln!(out, "caught up at cursor {cursor}")?,
            (kind, Some(alarm)) => writeln!(
                out,
                "cursor {cursor}: {kind:?} alarm {} of {} ({:?}, p = {:.2})",
                alarm.id,
                alarm.vehicle_id,
                alarm.severity(),
                alarm.peak_probability
            )?,
            (kind, None) => writeln!(out, "cursor {cursor}: {kind:?}")?,
        }
    }
    Ok(cursor)
}
