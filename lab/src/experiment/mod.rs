//! `spoofwatch-lab experiment`: the standard experiments of SPEC §9. This file owns their command
//! line and dispatch; what they share lives in `common` (data loading, the chronological split) and
//! `training_attacks` (injected training attacks). Training goes through core's `train_detector`
//! like every other caller; this module must not fit or score detectors itself.

mod avgps;
mod common;
mod fleet_alarms;
mod fleet_fit;
mod incidents;
mod offsets;
mod parallel;
mod plots;
mod subtle;
mod subtle_d2;
mod training_attacks;

use anyhow::Result;

#[derive(Debug, clap::Subcommand)]
pub enum Command {
    /// Train on Dataset-2 (chronological 70/15/15), test on Dataset-2's test part and all of
    /// Dataset-3; CUSUM, EKF, subtle-attack training and ablations side by side.
    AvGps(avgps::Args),
    /// Detection delay and ADR per subtle attack type and magnitude; false alarms per hour.
    Subtle(subtle::Args),
    /// Ramps injected into Dataset-2's real normal trajectories, cross-validated by trajectory.
    SubtleD2(subtle_d2::Args),
    /// Jumps, hops, frozen fixes and drifts at 1, 5 and 10 Hz, early and late in a session;
    /// false alarms per hour at each rate.
    Offsets(offsets::Args),
    /// Both alarm severities as a fleet counts them: the critical test chosen on attack-free
    /// validation hours, clean fleets of 1,000 vehicle-hours per rate, detection at both levels.
    FleetAlarms(fleet_alarms::Args),
    /// The detector fitted to a fleet from its attack-free recordings (Dataset-2's rover, or a
    /// simulated fleet with compasses and speed sensors beyond the bundled model's range), scored
    /// beside the bundled default.
    FleetFit(fleet_fit::Args),
    /// Regional spoofing replayed through the server: captured vehicles alarmed, their delay, the
    /// time to the area incident; clean fleets with independent attacks make no incident.
    Incidents(incidents::Args),
}

pub fn run(cmd: Command) -> Result<()> {
    match cmd {
        Command::AvGps(args) => avgps::run(args),
        Command::Subtle(args) => subtle::run(args),
        Command::SubtleD2(args) => subtle_d2::run(args),
        Command::Offsets(args) => offsets::run(args),
        Command::Incidents(args) => incidents::run(args),
        Command::FleetAlarms(args) => fleet_alarms::run(args),
        Command::FleetFit(args) => fleet_fit::run(args),
    }
}
