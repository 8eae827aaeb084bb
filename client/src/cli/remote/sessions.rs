//! `spoofwatch sessions`: the server's in-memory vehicle sessions.
//!
//! It owns how sessions are described; paging and tables come from `remote`.

use crate::error::reply;
use crate::routing::for_vehicle;
use anyhow::Result;
use spoofwatch_proto::v1;

use super::{ResourceArgs, all_pages, print_table, time};

/// `spoofwatch {resource} <command>` with the server flags.
pub type Args = ResourceArgs<Command>;

#[derive(Debug, clap::Subcommand)]
pub enum Command {
    /// List the sessions, by vehicle id.
    List,
    /// Show one vehicle's session.
    Get {
        /// The vehicle id.
        vehicle_id: String,
    },
    /// Forget a session's history (its next sample starts a new trajectory); it keeps its model.
    Reset {
        /// The vehicle id.
        vehicle_id: String,
    },
}

/// A session's state, several lines.
pub fn describe(s: &v1::Session) -> String {
    format!(
        "{}\n  model          {}\n  connected      {}\n  samples        {} in {} trajectories (last seq {}, \
         last sample t = {} s)\n  alarm          {} ({} raised)\n  last activity  {}\n",
        s.vehicle_id,
        s.model,
        yes_no(s.connected),
        s.samples,
        s.trajectories,
        s.last_seq,
        s.last_timestamp_s,
        if s.alarm_active { "ON" } else { "off" },
        s.alarms_raised,
        time(s.last_activity.as_ref()),
    )
}

fn yes_no(b: bool) -> &'static str {
    if b { "yes" } else { "no" }
}

pub async fn run(args: Args) -> Result<()> {
    let connection = args.server.connect().await?;
    let mut client = connection.detection();
    match args.command {
        Command::List => {
            let sessions = all_pages(
                "listing sessions",
                async |page_token| {
                    let request = v1::ListSessionsRequest {
                        page_size: 0,
                        page_token,
                    };
                    client.list_sessions(request).await
                },
                |page| (page.sessions, page.next_page_token),
            )
            .await?;
            let header = [
                "vehicle",
                "model",
                "connected",
                "samples",
                "alarm",
                "raised",
                "last activity",
            ];
            print_table(&header, &sessions, |s| {
                vec![
                    s.vehicle_id.clone(),
                    s.model.clone(),
                    yes_no(s.connected).to_string(),
                    s.samples.to_string(),
                    if s.alarm_active { "ON" } else { "-" }.to_string(),
                    s.alarms_raised.to_string(),
                    time(s.last_activity.as_ref()),
                ]
            });
        }
        Command::Get { vehicle_id } => {
            let request = v1::GetSessionRequest {
                vehicle_id: vehicle_id.clone(),
            };
            let session = reply(
                format!("getting the session of {vehicle_id}"),
                client.get_session(for_vehicle(&vehicle_id, request)),
            )
            .await?;
            print!("{}", describe(&session));
        }
        Command::Reset { vehicle_id } => {
            let request = v1::ResetSessionRequest {
                vehicle_id: vehicle_id.clone(),
            };
            let session = reply(
                format!("resetting the session of {vehicle_id}"),
                client.reset_session(for_vehicle(&vehicle_id, request)),
            )
            .await?;
            print!("reset {}", describe(&session));
        }
    }
    Ok(())
}
