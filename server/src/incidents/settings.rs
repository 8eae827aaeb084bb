//! How this server correlates area incidents: the area, the timeline alarms are placed on, and
//! whether the sessions score with the area prior.
//!
//! Owns [`IncidentSettings`] and [`IncidentTimeline`] (the configuration reads its flags into
//! them). Must not read flags or the store, or correlate anything (that is `super::correlator`).

use spoofwatch_core::incident::AreaConfig;

/// Which clock places alarms in time for area incidents.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, clap::ValueEnum)]
pub enum IncidentTimeline {
    /// The servers' wall clock at each onset and end (live fleets).
    #[default]
    Wall,
    /// The vehicles' sample times: replays of recordings whose vehicles share one clock.
    Samples,
}

/// How this server correlates incidents.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct IncidentSettings {
    pub area: AreaConfig,
    pub timeline: IncidentTimeline,
    /// Whether samples inside an open incident's area are scored with the area prior.
    pub prior: bool,
}
