//! The shadow's Prometheus counts: a batch's tally delta turned into the `spoofwatch_shadow_*`
//! counters (names and help live in `crate::telemetry`). Never the real alarm metrics: a would-be
//! alarm is not an alarm.

use super::tally::Tally;
use crate::telemetry;

/// Records what one batch (or one let-go) counted.
pub fn counted(delta: &Tally) {
    telemetry::shadow_samples("scored", delta.samples_scored);
    telemetry::shadow_onsets("live", "warning", delta.live_warning);
    telemetry::shadow_onsets("live", "critical", delta.live_critical);
    telemetry::shadow_onsets("shadow", "warning", delta.shadow_warning);
    telemetry::shadow_onsets("shadow", "critical", delta.shadow_critical);
    telemetry::shadow_agreement("alarm", "alarm", delta.agree_alarm);
    telemetry::shadow_agreement("quiet", "quiet", delta.agree_quiet);
    telemetry::shadow_agreement("alarm", "quiet", delta.live_only);
    telemetry::shadow_agreement("quiet", "alarm", delta.shadow_only);
    telemetry::shadow_unmatched("live", delta.live_episodes_without_shadow);
    telemetry::shadow_unmatched("shadow", delta.shadow_episodes_without_live);
}

/// A vehicle's shadow state started (or, `idle`, was let go) for `reason`.
pub fn vehicle_started(reason: &'static str) {
    telemetry::shadow_vehicle_starts(reason, 1);
}
