//! The shadow calls of ModelService (StartShadow, GetShadow, StopShadow, ListShadowAlarms): their
//! requests decoded with field-level errors, carried out on [`Shadows`], and answered in their
//! wire form. The models edge (`crate::models::service`) routes the calls here; errors map to gRPC
//! once, in `crate::error`.

use spoofwatch_proto::v1;
use spoofwatch_proto::wire::ModelName;
use spoofwatch_proto::wire::convert::timestamp_from_ms;
use tonic::Status;

use super::scope::ShadowScope;
use super::tally::Tally;
use super::{ShadowError, Shadows};
use crate::edge::{model_name, optional_vehicle_id};
use crate::status::invalid_field;
use crate::store::{ShadowAlarmRow, ShadowRow, ShadowStart};

/// Most would-be alarms in one page.
const MAX_PAGE: u32 = 1_000;
const DEFAULT_PAGE: u32 = 100;

/// A StartShadow request decoded: the candidate and its scope.
pub fn decode_start(request: &v1::StartShadowRequest) -> Result<(ModelName, ShadowScope), Status> {
    use v1::start_shadow_request::Scope;
    let model = model_name("model", &request.model)?;
    let scope = match &request.scope {
        Some(Scope::AllVehicles(true)) => ShadowScope::All,
        Some(Scope::AllVehicles(false)) => {
            return Err(invalid_field(
                "all_vehicles",
                "must be true when given (or name share or vehicles instead)",
            ));
        }
        Some(Scope::Share(share)) => ShadowScope::share(*share).map_err(scope_status)?,
        Some(Scope::Vehicles(list)) => {
            ShadowScope::vehicles(&list.vehicle_ids).map_err(scope_status)?
        }
        None => {
            return Err(invalid_field(
                "scope",
                "name the vehicles: all_vehicles, a share in (0, 1] or a vehicles list",
            ));
        }
    };
    Ok((model, scope))
}

fn scope_status(error: super::scope::ScopeError) -> Status {
    invalid_field(error.field, error.reason)
}

/// A `shadows/{id}` (or `{id}`) field; empty is `None`.
pub fn shadow_id(field: &str, name: &str) -> Result<Option<i64>, Status> {
    if name.is_empty() {
        return Ok(None);
    }
    let id = name.strip_prefix("shadows/").unwrap_or(name);
    match id.parse::<i64>() {
        Ok(id) if id > 0 => Ok(Some(id)),
        _ => Err(invalid_field(
            field,
            format!("must be shadows/{{id}} with a positive integer id, got {name:?}"),
        )),
    }
}

impl Shadows {
    /// Starts a shadow of `model` over `scope`, run at once by this server and within
    /// [`super::SHADOW_POLL`] by every other.
    pub async fn start(
        &self,
        model: &ModelName,
        scope: ShadowScope,
        started_by: &str,
    ) -> Result<v1::Shadow, ShadowError> {
        self.registry.get(model).await?;
        let scope_json = serde_json::to_value(&scope).unwrap_or_default();
        let _change = self.change.lock().await;
        let row = match self
            .store
            .start_shadow(model.id(), &scope_json, started_by)
            .await?
        {
            ShadowStart::Started(row) => row,
            ShadowStart::AlreadyRunning(row) => return Err(ShadowError::AlreadyRunning(row.id)),
        };
        self.run(Some(row.clone())).await?;
        drop(_change);
        tracing::info!(shadow = row.id, %model, scope = %scope.describe(), by = started_by, "shadow started");
        self.describe(row).await
    }

    /// Stops the shadow `id` (`None`: the running one); its summary stays stored.
    pub async fn stop(&self, id: Option<i64>, stopped_by: &str) -> Result<v1::Shadow, ShadowError> {
        let _change = self.change.lock().await;
        let id = match id {
            Some(id) => id,
            None => match self.store.running_shadow().await? {
                Some(row) => row.id,
                None => return Err(ShadowError::NotFound("running".to_string())),
            },
        };
        if self.current().is_some_and(|r| r.id == id) {
            self.run(None).await?;
        }
        let row = self
            .store
            .stop_shadow(id, stopped_by)
            .await?
            .ok_or_else(|| ShadowError::NotFound(format!("shadows/{id}")))?;
        drop(_change);
        tracing::info!(shadow = id, by = stopped_by, "shadow stopped");
        self.describe(row).await
    }

    /// The shadow `id` (`None`: the newest) with its counts over every replica.
    pub async fn get(&self, id: Option<i64>) -> Result<v1::Shadow, ShadowError> {
        let row = self.store.get_shadow(id).await?.ok_or_else(|| match id {
            Some(id) => ShadowError::NotFound(format!("shadows/{id}")),
            None => ShadowError::NoneStarted,
        })?;
        self.describe(row).await
    }

    /// A page of the would-be alarms of shadow `id` (`None`: the newest), of one vehicle or all.
    pub async fn alarms(
        &self,
        request: &v1::ListShadowAlarmsRequest,
    ) -> Result<v1::ListShadowAlarmsResponse, Status> {
        let id = shadow_id("shadow", &request.shadow)?;
        let vehicle = optional_vehicle_id("vehicle_id", &request.vehicle_id)?;
        let size = match request.page_size {
            0 => DEFAULT_PAGE,
            n if n < 0 => return Err(invalid_field("page_size", "must not be negative")),
            n => (n as u32).min(MAX_PAGE),
        };
        let before = match request.page_token.as_str() {
            "" => None,
            token => Some(
                token
                    .parse::<i64>()
                    .map_err(|_| invalid_field("page_token", "invalid page token"))?,
            ),
        };
        let row = self
            .store
            .get_shadow(id)
            .await
            .map_err(Status::from)?
            .ok_or_else(|| {
                Status::from(match id {
                    Some(id) => ShadowError::NotFound(format!("shadows/{id}")),
                    None => ShadowError::NoneStarted,
                })
            })?;
        let mut rows = self
            .store
            .list_shadow_alarms(
                row.id,
                vehicle.as_ref().map(|v| v.as_str()),
                before,
                size + 1,
            )
            .await
            .map_err(Status::from)?;
        let more = rows.len() > size as usize;
        rows.truncate(size as usize);
        let next_page_token = match (more, rows.last()) {
            (true, Some(last)) => last.id.to_string(),
            _ => String::new(),
        };
        Ok(v1::ListShadowAlarmsResponse {
            alarms: rows.iter().map(alarm_to_proto).collect(),
            next_page_token,
        })
    }

    /// A stored shadow with its summary; this process's counts are stored first, so that the
    /// server answering sees its own counts whole.
    async fn describe(&self, row: ShadowRow) -> Result<v1::Shadow, ShadowError> {
        if self.counting() == row.id {
            self.flush().await;
        }
        let tally = Tally::sum(&self.store.shadow_tallies(row.id).await?);
        let (vehicles, starts, alarms) = self.store.shadow_counts(row.id).await?;
        let scope: Option<ShadowScope> = serde_json::from_value(row.scope_json.0.clone()).ok();
        let summary = summary(&tally, vehicles, starts, alarms);
        let mut shadow = v1::Shadow {
            name: format!("shadows/{}", row.id),
            model: format!("models/{}", row.model_id),
            scope: scope
                .as_ref()
                .map_or_else(|| "unknown".to_string(), ShadowScope::describe),
            running: row.stopped_at_ms.is_none(),
            start_time: Some(timestamp_from_ms(row.started_at_ms)),
            stop_time: row.stopped_at_ms.map(timestamp_from_ms),
            started_by: row.started_by,
            stopped_by: row.stopped_by.unwrap_or_default(),
            summary: Some(summary),
            ..v1::Shadow::default()
        };
        match scope {
            Some(ShadowScope::All) => shadow.all_vehicles = true,
            Some(ShadowScope::Share { share }) => shadow.share = share,
            Some(ShadowScope::Vehicles { vehicle_ids }) => {
                shadow.vehicle_ids = vehicle_ids.into_iter().collect();
            }
            None => {}
        }
        Ok(shadow)
    }
}

/// A shadow's summary on the wire.
fn summary(tally: &Tally, vehicles: u64, starts: u64, alarms: u64) -> v1::ShadowSummary {
    let levels = |warning, critical| v1::ShadowLevels { warning, critical };
    let rates = |warning, critical| v1::ShadowRates {
        warning: tally.per_vehicle_hour(warning),
        critical: tally.per_vehicle_hour(critical),
    };
    v1::ShadowSummary {
        samples_scored: tally.samples_scored,
        samples_shed: tally.samples_shed,
        vehicle_hours: tally.vehicle_hours(),
        vehicles,
        vehicle_restarts: starts.saturating_sub(vehicles),
        starts_after_shed: tally.starts_after_shed,
        starts_after_idle: tally.starts_after_idle,
        starts_after_reset: tally.starts_after_reset,
        live_onsets: Some(levels(tally.live_warning, tally.live_critical)),
        shadow_onsets: Some(levels(tally.shadow_warning, tally.shadow_critical)),
        live_onsets_per_vehicle_hour: Some(rates(tally.live_warning, tally.live_critical)),
        shadow_onsets_per_vehicle_hour: Some(rates(tally.shadow_warning, tally.shadow_critical)),
        agree_alarm: tally.agree_alarm,
        agree_quiet: tally.agree_quiet,
        live_only: tally.live_only,
        shadow_only: tally.shadow_only,
        live_episodes_without_shadow: tally.live_episodes_without_shadow,
        shadow_episodes_without_live: tally.shadow_episodes_without_live,
        shadow_micros_per_sample: tally.micros_per_sample(),
        alarms,
    }
}

/// A would-be alarm on the wire.
fn alarm_to_proto(row: &ShadowAlarmRow) -> v1::ShadowAlarm {
    v1::ShadowAlarm {
        id: u64::try_from(row.id).unwrap_or(0),
        shadow: format!("shadows/{}", row.shadow_id),
        vehicle_id: row.vehicle_id.clone(),
        model: format!("models/{}", row.model_id),
        onset_timestamp_s: row.onset_timestamp_s,
        end_timestamp_s: row.end_timestamp_s,
        severity: row.severity.clone(),
        escalated_timestamp_s: row.escalated_timestamp_s,
        peak_probability: row.peak_probability,
        end_reason: row.end_reason.clone().unwrap_or_default(),
        onset_time: Some(timestamp_from_ms(row.onset_at_ms)),
        end_time: row.ended_at_ms.map(timestamp_from_ms),
        live_alarmed: row.live_alarmed,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shadow_names_are_checked() {
        assert_eq!(shadow_id("name", "").unwrap(), None);
        assert_eq!(shadow_id("name", "shadows/3").unwrap(), Some(3));
        assert_eq!(shadow_id("name", "3").unwrap(), Some(3));
        for bad in ["shadows/", "shadows/0", "x", "shadows/-1"] {
            assert!(shadow_id("name", bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn a_start_without_a_scope_or_with_a_bad_share_names_the_field() {
        use v1::start_shadow_request::Scope;
        let request = |scope| v1::StartShadowRequest {
            model: "models/m".into(),
            scope,
        };
        let field = |status: Status| {
            use tonic_types::StatusExt;
            status.get_details_bad_request().unwrap().field_violations[0]
                .field
                .clone()
        };
        assert_eq!(field(decode_start(&request(None)).unwrap_err()), "scope");
        assert_eq!(
            field(decode_start(&request(Some(Scope::Share(1.5)))).unwrap_err()),
            "share"
        );
        assert!(matches!(
            decode_start(&request(Some(Scope::AllVehicles(true)))),
            Ok((_, ShadowScope::All))
        ));
    }
}
