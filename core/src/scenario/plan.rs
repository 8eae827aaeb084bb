//! Scenario sets: a grid of attacks injected into every base track, placed from a seed.
//!
//! Owns scenario grids and their seeded placement. Must not alter samples itself (it calls `inject`).

use serde::{Deserialize, Serialize};

use super::{AttackKind, AttackSpec, InjectedTrack, ScenarioError, compact, inject};
use crate::rng::Rng;
use crate::sample::Track;

/// The ramp-drift velocities of the standard "subtle" sweep (m/s).
pub const RAMP_SWEEP_VELOCITIES_MPS: [f64; 6] = [0.05, 0.1, 0.25, 0.5, 1.0, 2.0];

/// How long each attack lasts.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum AttackDuration {
    /// A fixed number of seconds (> 0).
    Seconds(f64),
    /// A fraction of the base track's time span, in (0, 1).
    TrackFraction(f64),
}

/// A grid of attacks to inject into each base track (SPEC §9 "subtle" experiment).
///
/// For each base track, each kind, each direction slot and each repeat, [`generate`] yields one labelled
/// track. Unless fixed, the onset is drawn uniformly among the rows whose time after the start lies in
/// [margin·span, (1 − margin)·span − duration], so normal rows remain before and after the attack and
/// the attack starts exactly at a sample. Draws come from a stream derived from (seed, base index, kind
/// index, direction index, repeat), so adding bases or kinds does not move the others.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ScenarioPlan {
    /// Attack kinds with their magnitudes (the grid).
    pub kinds: Vec<AttackKind>,
    /// Fixed directions (degrees clockwise from north); empty = draw a whole-degree direction per scenario.
    #[serde(default)]
    pub directions_deg: Vec<f64>,
    /// Attack length.
    pub duration: AttackDuration,
    /// Fixed onset (s after each base track's start); `None` = drawn in the middle part (see above).
    #[serde(default)]
    pub onset_s: Option<f64>,
    /// Fraction of the span kept attack-free at each end, in [0, 0.5).
    pub margin_fraction: f64,
    /// Scenarios per (base, kind, direction), each with its own draw (≥ 1).
    pub repeats: usize,
    /// Seed of all draws.
    pub seed: u64,
}

impl ScenarioPlan {
    /// Default attack-free margin at each end of a base track.
    pub const DEFAULT_MARGIN_FRACTION: f64 = 0.2;

    /// Ramp drifts at the given velocities (e.g. [`RAMP_SWEEP_VELOCITIES_MPS`]), random directions,
    /// the default margin.
    pub fn ramp_sweep(
        velocities_mps: &[f64],
        duration: AttackDuration,
        repeats: usize,
        seed: u64,
    ) -> Self {
        Self {
            kinds: velocities_mps
                .iter()
                .map(|&velocity_mps| AttackKind::RampDrift { velocity_mps })
                .collect(),
            directions_deg: Vec::new(),
            duration,
            onset_s: None,
            margin_fraction: Self::DEFAULT_MARGIN_FRACTION,
            repeats,
            seed,
        }
    }

    /// Checks the grid, directions, duration, margin and repeats.
    pub fn validate(&self) -> Result<(), ScenarioError> {
        let invalid = |field, problem: String| Err(ScenarioError::InvalidPlan { field, problem });
        if self.kinds.is_empty() {
            return invalid("kinds", "needs at least one attack kind".into());
        }
        for kind in &self.kinds {
            kind.validate()?;
        }
        if let Some(bad) = self
            .directions_deg
            .iter()
            .find(|d| !(d.is_finite() && (0.0..360.0).contains(*d)))
        {
            return invalid(
                "directions_deg",
                format!("{bad} is not a bearing in [0, 360)"),
            );
        }
        if let Some(onset) = self.onset_s
            && !(onset.is_finite() && onset >= 0.0)
        {
            return invalid("onset_s", format!("must be finite and >= 0 s, got {onset}"));
        }
        let margin = self.margin_fraction;
        if !(margin.is_finite() && (0.0..0.5).contains(&margin)) {
            return invalid(
                "margin_fraction",
                format!("must be in [0, 0.5), got {margin}"),
            );
        }
        match self.duration {
            AttackDuration::Seconds(s) if !(s.is_finite() && s > 0.0) => {
                return invalid(
                    "duration",
                    format!("seconds must be finite and > 0, got {s}"),
                );
            }
            AttackDuration::TrackFraction(f)
                if !(f.is_finite() && f > 0.0 && f + 2.0 * margin < 1.0) =>
            {
                return invalid(
                    "duration",
                    format!(
                        "track fraction must be > 0 and leave room for both margins \
                         (fraction + 2·margin < 1), got {f} with margin {margin}"
                    ),
                );
            }
            _ => {}
        }
        if self.repeats == 0 {
            return invalid("repeats", "must be at least 1".into());
        }
        Ok(())
    }

    /// Number of scenarios [`generate`] yields for `base_count` base tracks.
    pub fn scenario_count(&self, base_count: usize) -> usize {
        base_count * self.kinds.len() * self.directions_deg.len().max(1) * self.repeats
    }

    /// One-line summary, e.g. `ramp-0.05mps,ramp-0.1mps × dir random × 120 s × margin 0.2 × 3 repeats, seed 7`.
    pub fn describe(&self) -> String {
        let kinds: Vec<String> = self.kinds.iter().map(AttackKind::describe).collect();
        let directions = if self.directions_deg.is_empty() {
            "random".to_owned()
        } else {
            let fixed: Vec<String> = self.directions_deg.iter().map(|&d| compact(d)).collect();
            fixed.join(",")
        };
        let duration = match self.duration {
            AttackDuration::Seconds(s) => format!("{} s", compact(s)),
            AttackDuration::TrackFraction(f) => format!("{} of span", compact(f)),
        };
        format!(
            "{} × dir {directions} × {duration} × margin {} × {} repeats, seed {}",
            kinds.join(","),
            compact(self.margin_fraction),
            self.repeats,
            self.seed
        )
    }
}

/// Injects every attack of `plan` into every base track (normal data), in the order base → kind →
/// direction → repeat. Vehicle ids are `<base>#<attack>-s<seed>-r<repeat>`, unique when base ids are.
pub fn generate(bases: &[Track], plan: &ScenarioPlan) -> Result<Vec<InjectedTrack>, ScenarioError> {
    plan.validate()?;
    let direction_slots: Vec<Option<f64>> = if plan.directions_deg.is_empty() {
        vec![None]
    } else {
        plan.directions_deg.iter().copied().map(Some).collect()
    };
    let mut out = Vec::with_capacity(plan.scenario_count(bases.len()));
    for (base_index, base) in bases.iter().enumerate() {
        for (kind_index, kind) in plan.kinds.iter().enumerate() {
            for (direction_index, fixed_direction) in direction_slots.iter().enumerate() {
                for repeat in 0..plan.repeats {
                    let indices = [base_index, kind_index, direction_index, repeat];
                    let mut rng = Rng::seed_from_u64(scenario_seed(plan.seed, indices));
                    let direction_deg = fixed_direction.unwrap_or_else(|| rng.below(360) as f64);
                    let (onset_s, duration_s) = place_attack(base, plan, &mut rng)?;
                    let spec = AttackSpec {
                        kind: *kind,
                        direction_deg,
                        onset_s,
                        duration_s,
                        seed: Some(plan.seed),
                    };
                    let mut injected = inject(base, &spec)?;
                    injected.track.vehicle_id.push_str(&format!("-r{repeat}"));
                    out.push(injected);
                }
            }
        }
    }
    Ok(out)
}

/// (onset, duration) in seconds. Unless the plan fixes the onset, it is a sample's time after the start,
/// drawn uniformly among rows that leave the margins (and at least one row) free before and after.
fn place_attack(
    base: &Track,
    plan: &ScenarioPlan,
    rng: &mut Rng,
) -> Result<(f64, f64), ScenarioError> {
    let (Some(first), Some(last)) = (base.records.first(), base.records.last()) else {
        return Err(ScenarioError::EmptyTrack {
            vehicle_id: base.vehicle_id.clone(),
        });
    };
    let t0 = first.sample.timestamp_s;
    let span_s = last.sample.timestamp_s - t0;
    let duration_s = match plan.duration {
        AttackDuration::Seconds(s) => s,
        AttackDuration::TrackFraction(f) => f * span_s,
    };
    if let Some(onset_s) = plan.onset_s {
        return Ok((onset_s, duration_s));
    }
    let earliest_s = plan.margin_fraction * span_s;
    let latest_s = (1.0 - plan.margin_fraction) * span_s - duration_s;
    // Row 0 is excluded so at least one normal row precedes the attack.
    let candidates: Vec<f64> = base
        .records
        .iter()
        .skip(1)
        .map(|r| r.sample.timestamp_s - t0)
        .filter(|tau| *tau >= earliest_s && *tau <= latest_s)
        .collect();
    if candidates.is_empty() {
        return Err(ScenarioError::AttackDoesNotFit {
            vehicle_id: base.vehicle_id.clone(),
            duration_s,
            span_s,
            margin_fraction: plan.margin_fraction,
        });
    }
    Ok((candidates[rng.below(candidates.len())], duration_s))
}

/// Independent per-scenario seed: SplitMix64 finalizer chained over the plan seed and indices.
fn scenario_seed(plan_seed: u64, indices: [usize; 4]) -> u64 {
    indices.iter().fold(mix64(plan_seed), |acc, &index| {
        mix64(acc ^ mix64(index as u64 + 1))
    })
}

fn mix64(value: u64) -> u64 {
    let mut z = value.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}
