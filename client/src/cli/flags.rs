//! Value flags that several commands share: the local frame of GNSS displacements and the event
//! rules of ADR and delays. Owns only their command-line spelling and mapping to core's types.

use clap::ValueEnum;
use spoofwatch_core::geo::Projection;
use spoofwatch_core::metrics::EventRules;

/// Local east/north frame used for GNSS displacements.
#[derive(Clone, Copy, Debug, Default, ValueEnum)]
pub enum ProjectionArg {
    /// WGS-84 meridian/prime-vertical radii at the previous fix (default).
    #[default]
    Wgs84,
    /// The reference code's spherical equirectangular frame (R = 6,378,137 m).
    Equirectangular,
}

impl From<ProjectionArg> for Projection {
    fn from(p: ProjectionArg) -> Self {
        match p {
            ProjectionArg::Wgs84 => Projection::Wgs84Local,
            ProjectionArg::Equirectangular => Projection::Equirectangular,
        }
    }
}

/// Event rules for ADR/delay.
#[derive(Clone, Copy, Debug, Default, ValueEnum)]
pub enum RulesArg {
    /// SPEC §8: label-continuity events, detection needs a new alarm onset.
    #[default]
    Spec,
    /// The paper's legacy evaluator (events split at ν = 0, earlier alarms count with delay 0).
    Legacy,
}

impl From<RulesArg> for EventRules {
    fn from(r: RulesArg) -> Self {
        match r {
            RulesArg::Spec => EventRules::Spec,
            RulesArg::Legacy => EventRules::Legacy,
        }
    }
}
