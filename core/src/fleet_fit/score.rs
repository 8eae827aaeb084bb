//! How a model does on a fleet's test part (`docs/detector.md` §12.4): alarm onsets per
//! vehicle-hour at each level on the clean test drives, per sample rate, and per kind of the
//! detection grid the share alarmed within each level's deadline and the share of the attack's rows
//! the alarm covers. The fitted model and the starting one are scored alike, side by side.
//!
//! Owns the counting. Must not inject, fit or train.

use std::sync::Arc;

use serde::{Deserialize, Serialize};

use super::attacks::{GridKind, TestAttack};
use super::data::Drive;
use crate::detector::{Decision, run_records};
use crate::model::artifact::ModelArtifact;
use crate::severity::Severity;

/// Onsets on the clean test drives of one sample rate.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct CleanRate {
    pub rate_hz: f64,
    pub drives: usize,
    pub hours: f64,
    /// Alarm onsets (every alarm opens as a warning or higher).
    pub warning_onsets: u64,
    /// Alarms that were or became critical.
    pub critical_onsets: u64,
    pub warning_per_hour: f64,
    pub critical_per_hour: f64,
}

/// Detection of one grid kind.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct KindScore {
    pub attack: String,
    pub injected: u64,
    pub warning_within_s: f64,
    pub critical_within_s: f64,
    /// Alarmed (any level) within the warning deadline.
    pub warned: u64,
    /// Critical within the critical deadline.
    pub critical: u64,
    /// Mean share of the attack's rows with an alarm open, and with a critical one.
    pub warning_coverage: f64,
    pub critical_coverage: f64,
}

/// One model's score on the test part.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ModelScore {
    pub clean: Vec<CleanRate>,
    pub detection: Vec<KindScore>,
}

/// Scores `artifact` on the clean test drives (grouped by `rates`) and the attacked test pieces.
pub fn score(
    artifact: &Arc<ModelArtifact>,
    clean: &[Drive],
    rates: &[f64],
    attacks: &[TestAttack],
    grid: &[GridKind],
) -> ModelScore {
    let mut by_rate: Vec<CleanRate> = rates
        .iter()
        .map(|&rate_hz| CleanRate {
            rate_hz,
            ..CleanRate::default()
        })
        .collect();
    for drive in clean {
        let decisions = run_records(artifact, &drive.track.records);
        let Some(cell) = by_rate.iter_mut().min_by(|a, b| {
            (a.rate_hz - drive.rate_hz)
                .abs()
                .total_cmp(&(b.rate_hz - drive.rate_hz).abs())
        }) else {
            continue;
        };
        cell.drives += 1;
        cell.hours += drive.hours();
        cell.warning_onsets += decisions.iter().filter(|d| d.alarm_onset).count() as u64;
        cell.critical_onsets += critical_onsets(&decisions);
    }
    for cell in &mut by_rate {
        let hours = cell.hours.max(f64::MIN_POSITIVE);
        cell.warning_per_hour = cell.warning_onsets as f64 / hours;
        cell.critical_per_hour = cell.critical_onsets as f64 / hours;
    }
    let mut detection: Vec<KindScore> = grid
        .iter()
        .map(|g| KindScore {
            attack: g.kind.describe(),
            warning_within_s: g.warning_within_s,
            critical_within_s: g.critical_within_s,
            ..KindScore::default()
        })
        .collect();
    for attack in attacks {
        let decisions = run_records(artifact, &attack.track.records);
        let cell = &mut detection[attack.grid_index];
        let outcome = attack_outcome(attack, &decisions);
        cell.injected += 1;
        cell.warned += u64::from(
            outcome
                .warned_after_s
                .is_some_and(|s| s <= cell.warning_within_s),
        );
        cell.critical += u64::from(
            outcome
                .critical_after_s
                .is_some_and(|s| s <= cell.critical_within_s),
        );
        cell.warning_coverage += outcome.warning_coverage;
        cell.critical_coverage += outcome.critical_coverage;
    }
    for cell in &mut detection {
        let n = cell.injected.max(1) as f64;
        cell.warning_coverage /= n;
        cell.critical_coverage /= n;
    }
    ModelScore {
        clean: by_rate,
        detection,
    }
}

/// Alarms that were or became critical: escalations, at most one per alarm.
fn critical_onsets(decisions: &[Decision]) -> u64 {
    decisions.iter().filter(|d| d.escalation).count() as u64
}

/// What one attack met.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
struct AttackOutcome {
    warned_after_s: Option<f64>,
    critical_after_s: Option<f64>,
    warning_coverage: f64,
    critical_coverage: f64,
}

fn attack_outcome(attack: &TestAttack, decisions: &[Decision]) -> AttackOutcome {
    let rows = &attack.track.records;
    let onset_s = rows[attack.first_row].sample.timestamp_s;
    let mut outcome = AttackOutcome::default();
    let span = attack.first_row..=attack.last_row;
    let count = (attack.last_row + 1 - attack.first_row) as f64;
    for i in span {
        let after_s = rows[i].sample.timestamp_s - onset_s;
        let decision = &decisions[i];
        if decision.alarm {
            outcome.warned_after_s.get_or_insert(after_s);
            outcome.warning_coverage += 1.0 / count;
        }
        if decision.severity == Some(Severity::Critical) {
            outcome.critical_after_s.get_or_insert(after_s);
            outcome.critical_coverage += 1.0 / count;
        }
    }
    outcome
}
