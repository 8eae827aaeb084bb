//! `spoofwatch models shadow`: try a candidate model beside the live one before it pages anyone.
//!
//! It owns how a shadow's scope is given on the command line and how its summary and would-be
//! alarms read; the connection and tables come from `remote`.

use anyhow::{Result, bail};
use spoofwatch_proto::v1;
use spoofwatch_proto::v1::model_service_client::ModelServiceClient;

use super::{all_pages, print_table, time};
use crate::connection::AuthenticatedChannel;
use crate::retry::{self, Idempotency};

#[derive(Debug, clap::Subcommand)]
pub enum Command {
    /// Start a shadow: the candidate scores every sample of the chosen vehicles beside the live
    /// model; its would-be alarms are stored apart and never paged.
    Start {
        /// The candidate, `models/{id}` or `{id}`.
        model: String,
        /// Every vehicle.
        #[arg(long, conflicts_with_all = ["share", "vehicles"])]
        all: bool,
        /// A share of the vehicles in (0, 1], chosen by a stable hash of the vehicle id.
        #[arg(long, conflicts_with = "vehicles")]
        share: Option<f64>,
        /// These vehicles (comma-separated ids).
        #[arg(long, value_delimiter = ',')]
        vehicles: Option<Vec<String>>,
    },
    /// Show a shadow and how the candidate compares with the live model (default: the newest).
    Status {
        /// `shadows/{id}` or `{id}`.
        name: Option<String>,
    },
    /// Stop the running shadow (or the named one); its summary stays stored.
    Stop {
        /// `shadows/{id}` or `{id}`.
        name: Option<String>,
    },
    /// List a shadow's would-be alarms, newest first (default: the newest shadow).
    Alarms {
        /// `shadows/{id}` or `{id}`.
        name: Option<String>,
        /// Only this vehicle's.
        #[arg(long)]
        vehicle: Option<String>,
    },
}

/// The StartShadow request the flags describe.
pub fn start_request(
    model: String,
    all: bool,
    share: Option<f64>,
    vehicles: Option<Vec<String>>,
) -> Result<v1::StartShadowRequest> {
    use v1::start_shadow_request::Scope;
    let scope = match (all, share, vehicles) {
        (true, None, None) => Scope::AllVehicles(true),
        (false, Some(share), None) => Scope::Share(share),
        (false, None, Some(vehicle_ids)) => Scope::Vehicles(v1::ShadowVehicles { vehicle_ids }),
        _ => bail!("name the vehicles: --all, --share <fraction> or --vehicles <ids>"),
    };
    Ok(v1::StartShadowRequest {
        model,
        scope: Some(scope),
    })
}

/// A shadow and its comparison, several lines.
pub fn describe(shadow: &v1::Shadow) -> String {
    let mut out = format!(
        "{} ({})\n  candidate      {}\n  vehicles       {}\n  started        {} by {}\n",
        shadow.name,
        if shadow.running { "running" } else { "stopped" },
        shadow.model,
        shadow.scope,
        time(shadow.start_time.as_ref()),
        shadow.started_by,
    );
    if !shadow.running {
        out.push_str(&format!(
            "  stopped        {} by {}\n",
            time(shadow.stop_time.as_ref()),
            shadow.stopped_by
        ));
    }
    let Some(s) = &shadow.summary else {
        return out;
    };
    let levels = |l: Option<v1::ShadowLevels>| l.unwrap_or_default();
    let rates = |r: Option<v1::ShadowRates>| r.unwrap_or_default();
    let (live, cand) = (levels(s.live_onsets), levels(s.shadow_onsets));
    let (live_rate, cand_rate) = (
        rates(s.live_onsets_per_vehicle_hour),
        rates(s.shadow_onsets_per_vehicle_hour),
    );
    out.push_str(&format!(
        "  scored         {} samples, {} shed; {:.2} vehicle-hours, {} vehicles, {} vehicle restarts \
         (after shed {}, idle {}, reset {})\n",
        s.samples_scored,
        s.samples_shed,
        s.vehicle_hours,
        s.vehicles,
        s.vehicle_restarts,
        s.starts_after_shed,
        s.starts_after_idle,
        s.starts_after_reset,
    ));
    out.push_str(&format!(
        "  onsets         live: {} warning, {} critical ({:.2} / {:.2} per vehicle-hour)\n\
         \x20                candidate: {} warning, {} critical ({:.2} / {:.2} per vehicle-hour)\n",
        live.warning,
        live.critical,
        live_rate.warning,
        live_rate.critical,
        cand.warning,
        cand.critical,
        cand_rate.warning,
        cand_rate.critical,
    ));
    out.push_str(&format!(
        "  samples        both alarm {}, both quiet {}, live only {}, candidate only {}\n\
         \x20 episodes       live without candidate {}, candidate without live {}\n\
         \x20 cost           {:.1} µs of scoring per sample, off the request path; {} would-be alarms\n",
        s.agree_alarm,
        s.agree_quiet,
        s.live_only,
        s.shadow_only,
        s.live_episodes_without_shadow,
        s.shadow_episodes_without_live,
        s.shadow_micros_per_sample,
        s.alarms,
    ));
    out
}

pub async fn run(
    mut client: ModelServiceClient<AuthenticatedChannel>,
    command: Command,
) -> Result<()> {
    match command {
        Command::Start {
            model,
            all,
            share,
            vehicles,
        } => {
            let request = start_request(model.clone(), all, share, vehicles)?;
            let shadow = retry::unary(
                format!("starting a shadow of {model}"),
                Idempotency::NotIdempotent,
                async || client.start_shadow(request.clone()).await,
            )
            .await?;
            print!("started {}", describe(&shadow));
        }
        Command::Status { name } => {
            let request = v1::GetShadowRequest {
                name: name.unwrap_or_default(),
            };
            let shadow = retry::unary(
                "reading the shadow".to_string(),
                Idempotency::Idempotent,
                async || client.get_shadow(request.clone()).await,
            )
            .await?;
            print!("{}", describe(&shadow));
        }
        Command::Stop { name } => {
            let request = v1::StopShadowRequest {
                name: name.unwrap_or_default(),
            };
            let shadow = retry::unary(
                "stopping the shadow".to_string(),
                Idempotency::Idempotent,
                async || client.stop_shadow(request.clone()).await,
            )
            .await?;
            print!("stopped {}", describe(&shadow));
        }
        Command::Alarms { name, vehicle } => {
            let (shadow, vehicle_id) = (name.unwrap_or_default(), vehicle.unwrap_or_default());
            let alarms = all_pages(
                "listing the shadow's would-be alarms",
                async |page_token| {
                    let request = v1::ListShadowAlarmsRequest {
                        shadow: shadow.clone(),
                        vehicle_id: vehicle_id.clone(),
                        page_token,
                        ..Default::default()
                    };
                    client.list_shadow_alarms(request).await
                },
                |page| (page.alarms, page.next_page_token),
            )
            .await?;
            let header = [
                "id", "vehicle", "onset s", "end s", "severity", "peak", "live too", "ended",
            ];
            print_table(&header, &alarms, |a| {
                vec![
                    a.id.to_string(),
                    a.vehicle_id.clone(),
                    format!("{:.1}", a.onset_timestamp_s),
                    a.end_timestamp_s
                        .map_or_else(|| "open".to_string(), |t| format!("{t:.1}")),
                    a.severity.clone(),
                    format!("{:.3}", a.peak_probability),
                    if a.live_alarmed { "yes" } else { "no" }.to_string(),
                    if a.end_reason.is_empty() {
                        "-".to_string()
                    } else {
                        a.end_reason.clone()
                    },
                ]
            });
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_start_names_exactly_one_scope() {
        use v1::start_shadow_request::Scope;
        let all = start_request("m".into(), true, None, None).unwrap();
        assert_eq!(all.scope, Some(Scope::AllVehicles(true)));
        let share = start_request("m".into(), false, Some(0.1), None).unwrap();
        assert_eq!(share.scope, Some(Scope::Share(0.1)));
        assert!(start_request("m".into(), false, None, None).is_err());
    }
}
