//! The randomised attack mix detectors are taught on: jumps of 5 m–50 km, hops, frozen fixes, ramps,
//! accelerating and toggling drifts, each drawn with its magnitude. The offsets suite's training
//! drives and a fleet fit's injected pieces draw from it, so that both teach the same attacks.
//!
//! Owns the draw of one attack kind. Must not place attacks in time or inject them (that is the
//! caller's, with [`super::inject`]).

use super::AttackKind;
use crate::rng::Rng;

/// A log-uniform draw in [low, high].
pub fn log_uniform(rng: &mut Rng, low: f64, high: f64) -> f64 {
    (low.ln() + rng.uniform() * (high.ln() - low.ln())).exp()
}

/// One random attack of the training mix: jumps of 5 m–50 km, hops, frozen fixes, ramps,
/// accelerating and toggling drifts. An `early` one (in a session's first minute) drifts at 1 m/s or
/// more: before the onboard calibration is known, a vehicle's own speed-scale and heading errors
/// drift its dead reckoning by up to a few tenths of a metre per second, so a slower drift from the
/// first seconds is not an attack the model can be taught.
pub fn training_attack(rng: &mut Rng, early: bool) -> AttackKind {
    let drift_mps = |rng: &mut Rng, low: f64| log_uniform(rng, if early { 1.0 } else { low }, 2.0);
    match rng.below(7) {
        0 => AttackKind::Jump {
            offset_m: log_uniform(rng, 5.0, 50_000.0),
        },
        1 => AttackKind::Hopping {
            offset_m: log_uniform(rng, 50.0, 50_000.0),
            hold_s: rng.uniform_range(1.0, 30.0).round(),
        },
        2 => AttackKind::FrozenPosition,
        3 | 4 => AttackKind::RampDrift {
            velocity_mps: drift_mps(rng, 0.2),
        },
        5 if early => AttackKind::RampDrift {
            velocity_mps: drift_mps(rng, 0.2),
        },
        5 => AttackKind::AcceleratingDrift {
            acceleration_mps2: log_uniform(rng, 0.01, 0.3),
        },
        _ => AttackKind::TogglingDrift {
            velocity_mps: drift_mps(rng, 0.3),
            period_s: rng.uniform_range(5.0, 30.0).round(),
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn early_attacks_never_drift_slower_than_a_metre_per_second() {
        let mut rng = Rng::seed_from_u64(7);
        let mut families = std::collections::BTreeSet::new();
        for _ in 0..2000 {
            let kind = training_attack(&mut rng, true);
            families.insert(kind.family());
            kind.validate().expect("every drawn attack is valid");
            if let AttackKind::RampDrift { velocity_mps }
            | AttackKind::TogglingDrift { velocity_mps, .. } = kind
            {
                assert!((1.0..=2.0).contains(&velocity_mps), "{kind:?}");
            }
            assert!(!matches!(kind, AttackKind::AcceleratingDrift { .. }));
        }
        assert_eq!(families.len(), 5, "{families:?}");
        let late: std::collections::BTreeSet<_> = (0..2000)
            .map(|_| training_attack(&mut rng, false).family())
            .collect();
        assert_eq!(late.len(), 6, "{late:?}");
    }

    #[test]
    fn log_uniform_stays_within_its_bounds() {
        let mut rng = Rng::seed_from_u64(1);
        for _ in 0..1000 {
            let x = log_uniform(&mut rng, 5.0, 50_000.0);
            assert!((5.0..=50_000.0).contains(&x));
        }
    }
}
