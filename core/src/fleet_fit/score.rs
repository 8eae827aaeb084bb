//! How a model does on a fleet's test part (`docs/detector.md` §12.4): alarm onsets per
//! vehicle-hour at each level on the clean test drives, per sample rate and per road kind (the
//! budgets' [`Pace`]: town or open road), and per kind of the
//! detection grid the share alarmed within each level's deadline and the share of the attack's rows
//! the alarm covers. The fitted model and the starting one are scored alike, side by side.
//!
//! Owns the counting. Must not inject, fit or train.

use std::sync::Arc;

use serde::{Deserialize, Serialize};

use super::attacks::{GridKind, TestAttack};
use super::data::Drive;
use crate::detector::{Decision, run_records};
use crate::metrics::Pace;
use crate::model::artifact::ModelArtifact;
use crate::severity::Severity;

/// Onsets on the clean test drives of one sample rate, or of one rate and road kind.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct CleanRate {
    pub rate_hz: f64,
    /// `None`: every drive of the rate; else its town or its open-road drives.
    #[serde(default)]
    pub pace: Option<Pace>,
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

impl CleanRate {
    fn add(&mut self, other: &CleanRate) {
        self.drives += other.drives;
        self.hours += other.hours;
        self.warning_onsets += other.warning_onsets;
        self.critical_onsets += other.critical_onsets;
        let hours = self.hours.max(f64::MIN_POSITIVE);
        self.warning_per_hour = self.warning_onsets as f64 / hours;
        self.critical_per_hour = self.critical_onsets as f64 / hours;
    }
}

impl ModelScore {
    /// Adds `other`'s clean counts (of drives apart from this score's) cell by cell, keeping
    /// each rate's cells together: for a clean fleet scored in batches.
    pub fn add_clean(&mut self, other: &ModelScore) {
        for cell in &other.clean {
            let same = |c: &CleanRate| c.rate_hz == cell.rate_hz && c.pace == cell.pace;
            let index = self.clean.iter().position(same).unwrap_or_else(|| {
                self.clean.push(CleanRate {
                    rate_hz: cell.rate_hz,
                    pace: cell.pace,
                    ..CleanRate::default()
                });
                self.clean.len() - 1
            });
            self.clean[index].add(cell);
        }
        self.clean
            .sort_by(|a, b| a.rate_hz.total_cmp(&b.rate_hz).then(a.pace.cmp(&b.pace)));
    }
}

/// Scores `artifact` on the clean test drives (grouped by `rates`, and each rate again by road
/// kind) and the attacked test pieces.
pub fn score(
    artifact: &Arc<ModelArtifact>,
    clean: &[Drive],
    rates: &[f64],
    attacks: &[TestAttack],
    grid: &[GridKind],
) -> ModelScore {
    let mut by_rate = ModelScore {
        clean: rates
            .iter()
            .map(|&rate_hz| CleanRate {
                rate_hz,
                ..CleanRate::default()
            })
            .collect(),
        detection: Vec::new(),
    };
    for drive in clean {
        let Some(rate_hz) = rates.iter().copied().min_by(|a, b| {
            (a - drive.rate_hz)
                .abs()
                .total_cmp(&(b - drive.rate_hz).abs())
        }) else {
            continue;
        };
        let decisions = run_records(artifact, &drive.track.records);
        let speeds: Vec<f64> = drive
            .track
            .records
            .iter()
            .map(|r| r.sample.speed_mps)
            .collect();
        let drive_cell = CleanRate {
            rate_hz,
            pace: None,
            drives: 1,
            hours: drive.hours(),
            warning_onsets: decisions.iter().filter(|d| d.alarm_onset).count() as u64,
            critical_onsets: critical_onsets(&decisions),
            ..CleanRate::default()
        };
        let pace_cell = CleanRate {
            pace: Some(Pace::of(&speeds)),
            ..drive_cell.clone()
        };
        by_rate.add_clean(&ModelScore {
            clean: vec![drive_cell, pace_cell],
            detection: Vec::new(),
        });
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
        clean: by_rate.clean,
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

#[cfg(test)]
mod tests {
    use super::*;

    fn cell(rate_hz: f64, pace: Option<Pace>, hours: f64, warnings: u64) -> CleanRate {
        CleanRate {
            rate_hz,
            pace,
            drives: 1,
            hours,
            warning_onsets: warnings,
            critical_onsets: warnings / 2,
            ..CleanRate::default()
        }
    }

    fn clean(cells: Vec<CleanRate>) -> ModelScore {
        ModelScore {
            clean: cells,
            detection: Vec::new(),
        }
    }

    #[test]
    fn clean_counts_add_up_by_rate_and_road_kind_in_order() {
        let mut total = clean(vec![
            cell(5.0, None, 2.0, 2),
            cell(5.0, Some(Pace::Town), 2.0, 2),
        ]);
        total.add_clean(&clean(vec![
            cell(1.0, None, 1.0, 0),
            cell(5.0, Some(Pace::OpenRoad), 0.5, 3),
            cell(5.0, None, 0.5, 3),
        ]));
        let keys: Vec<(f64, Option<Pace>)> =
            total.clean.iter().map(|c| (c.rate_hz, c.pace)).collect();
        assert_eq!(
            keys,
            vec![
                (1.0, None),
                (5.0, None),
                (5.0, Some(Pace::Town)),
                (5.0, Some(Pace::OpenRoad)),
            ]
        );
        // 5 Hz, every drive: 2 + 3 onsets in 2 + 0.5 hours, 2 per hour; critical 1 + 1 in 2.5 h.
        let all = &total.clean[1];
        assert_eq!(
            (all.drives, all.warning_onsets, all.critical_onsets),
            (2, 5, 2)
        );
        assert!((all.warning_per_hour - 2.0).abs() < 1e-12);
        assert!((all.critical_per_hour - 0.8).abs() < 1e-12);
        // A cell first met in the added score keeps its own counts: 3 in half an hour.
        assert!(
            (total.clean[3].warning_per_hour - 6.0).abs() < 1e-12,
            "{:?}",
            total.clean[3]
        );
    }
}
