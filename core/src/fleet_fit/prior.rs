//! The fleet's prior on its vehicles' onboard calibration (`docs/detector.md` §12.2), fitted on
//! its attack-free drives: each drive's calibration is learnt under the widest prior the detector
//! accepts, and the drives whose calibration became known give the fleet's mean and spread.
//!
//! A fleet of cars with good sensors gets a tight prior, so their calibration is trusted within
//! seconds; a fleet with poor compasses a wide one, so their own errors raise no alarms.
//!
//! Owns the prior's estimate. Must not build evidence itself (it runs the streaming builder), fit
//! the other evidence parameters or train.

use serde::{Deserialize, Serialize};

use crate::evidence::calibration::{
    CALIBRATION_PRIOR_STD_MAX, CALIBRATION_PRIOR_STD_MIN, CalibrationPrior, CalibrationTrust,
};
use crate::evidence::drift::DriftParams;
use crate::evidence::{EvidenceParams, build_track, normal_residuals, robust_residual_sigma};
use crate::geo::Projection;
use crate::sample::Track;

/// A drive's calibration counts once its information trust (under the widest prior) reaches this:
/// its remaining error is at most a fifth of that prior's (about 4 % speed scale, 6° heading).
pub const KNOWN_TRUST: f64 = 0.8;
/// Fewest drives with a known calibration for a fitted prior; with fewer the default stays.
pub const MIN_KNOWN_DRIVES: usize = 3;
/// No fitted spread is narrower than this (speed scale 1 %, heading 1°, lag 0.2 s): what one
/// drive's estimate is known to, and what a compass wanders by within an hour.
pub const SPREAD_FLOOR: [f64; 3] = [0.01, 1.0 * std::f64::consts::PI / 180.0, 0.2];
/// One-sided 95 % normal quantile: the spread is widened to the upper bound of its estimate.
const UPPER_95: f64 = 1.645;

/// The fitted prior and what it came from.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FittedPrior {
    /// The prior the fitted model carries.
    pub prior: CalibrationPrior,
    /// Drives whose calibration became known, of all fit drives.
    pub known_drives: usize,
    pub drives: usize,
    /// Each known drive's calibration: speed scale error, heading bias (°), lag (s).
    pub estimates: Vec<[f64; 3]>,
    /// Why the default prior was kept, when it was.
    pub kept_default: Option<String>,
}

/// Fits the calibration prior on `drives` (attack-free, labelled so).
pub fn fit_calibration_prior(drives: &[Track], projection: Projection) -> FittedPrior {
    let kept = |reason: String, estimates: Vec<[f64; 3]>| FittedPrior {
        prior: CalibrationPrior::default(),
        known_drives: estimates.len(),
        drives: drives.len(),
        estimates,
        kept_default: Some(reason),
    };
    let sigma = match robust_residual_sigma(&normal_residuals(drives, projection)) {
        Ok(sigma) => sigma,
        Err(error) => return kept(format!("no GNSS noise estimate: {error}"), Vec::new()),
    };
    let params = EvidenceParams {
        drift: Some(DriftParams {
            trust: CalibrationTrust::Information,
            calibration_prior: Some(CalibrationPrior {
                mean: [0.0; 3],
                std: CALIBRATION_PRIOR_STD_MAX,
            }),
            ..DriftParams::unwhitened(sigma)
        }),
        ..EvidenceParams::unnormalised(projection)
    };
    let estimates: Vec<[f64; 3]> = drives
        .iter()
        .filter_map(|drive| known_calibration(&params, drive))
        .collect();
    if estimates.len() < MIN_KNOWN_DRIVES {
        return kept(
            format!(
                "{} of {} drives taught a known calibration (at least {MIN_KNOWN_DRIVES} needed: \
                 drives that turn and change speed teach it)",
                estimates.len(),
                drives.len()
            ),
            estimates,
        );
    }
    FittedPrior {
        prior: prior_from(&estimates),
        known_drives: estimates.len(),
        drives: drives.len(),
        estimates,
        kept_default: None,
    }
}

/// The calibration in use at the drive's last valid row (heading in degrees), if it is known.
fn known_calibration(params: &EvidenceParams, drive: &Track) -> Option<[f64; 3]> {
    let evidence = build_track(params, &drive.records);
    let last = evidence.iter().rev().find(|e| e.valid)?.drift?;
    (last.warm_up >= KNOWN_TRUST && last.calibration.iter().all(|x| x.is_finite()))
        .then_some(last.calibration)
}

/// The mean of `estimates` (heading in degrees) and their spread, widened to its one-sided 95 %
/// upper bound for the number of drives, floored at [`SPREAD_FLOOR`] and kept within the limits a
/// prior may have.
pub fn prior_from(estimates: &[[f64; 3]]) -> CalibrationPrior {
    let n = estimates.len() as f64;
    let radians = |i: usize, x: f64| if i == 1 { x.to_radians() } else { x };
    let mut mean = [0.0; 3];
    let mut std = [0.0; 3];
    for i in 0..3 {
        let values: Vec<f64> = estimates.iter().map(|e| radians(i, e[i])).collect();
        let m = values.iter().sum::<f64>() / n;
        let variance = if n > 1.0 {
            values.iter().map(|v| (v - m) * (v - m)).sum::<f64>() / (n - 1.0)
        } else {
            0.0
        };
        let widened = variance.sqrt() * (1.0 + UPPER_95 / (2.0 * (n - 1.0).max(1.0)).sqrt());
        std[i] = widened
            .max(SPREAD_FLOOR[i])
            .clamp(CALIBRATION_PRIOR_STD_MIN[i], CALIBRATION_PRIOR_STD_MAX[i]);
        mean[i] = m;
    }
    CalibrationPrior { mean, std }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scenario::{DriveDistribution, simulate_drive};

    #[test]
    fn the_prior_is_the_drives_mean_and_widened_spread_within_its_floor() {
        // Heading biases 2°, 4°, 6°, 8° (mean 5°, sample std 2.582°); speed scales all 1 %; lags 0.
        let estimates = [
            [0.01, 2.0, 0.0],
            [0.01, 4.0, 0.0],
            [0.01, 6.0, 0.0],
            [0.01, 8.0, 0.0],
        ];
        let prior = prior_from(&estimates);
        assert!((prior.mean[0] - 0.01).abs() < 1e-15);
        assert!((prior.mean[1] - 5f64.to_radians()).abs() < 1e-12);
        // √(20/3) · (1 + 1.645/√6) = 2.582 · 1.6716 = 4.316°.
        let expected = (20.0f64 / 3.0).sqrt() * (1.0 + 1.645 / 6f64.sqrt());
        assert!(
            (prior.std[1].to_degrees() - expected).abs() < 1e-9,
            "{prior:?}"
        );
        assert_eq!(prior.std[0], SPREAD_FLOOR[0], "no spread: the floor");
        assert_eq!(prior.std[2], SPREAD_FLOOR[2]);
        assert_eq!(prior.problem(), None);
        // A spread beyond what the detector accepts is held at its limit.
        let wild = prior_from(&[[0.0, -80.0, 0.0], [0.0, 80.0, 0.0], [0.0, 0.0, 0.0]]);
        assert_eq!(wild.std[1], CALIBRATION_PRIOR_STD_MAX[1]);
    }

    #[test]
    fn a_fleet_with_biased_compasses_gets_a_prior_around_its_bias() {
        // Four drives whose compasses all read 10° off, with a speed scale 4 % high: the fitted mean
        // finds both, and the spread stays narrow enough to trust a vehicle sooner than the default.
        let drives: Vec<Track> = (0..4)
            .map(|i| {
                let mut spec = DriveDistribution::realistic().draw(100 + i);
                spec.duration_s = 1_200.0;
                spec.rate_hz = 1.0;
                spec.onboard_errors.heading_bias_deg = 10.0;
                spec.onboard_errors.speed_scale_error = 0.04;
                spec.heading_bias_wander = Default::default();
                let mut track = simulate_drive(&spec, &format!("car-{i}")).expect("drive");
                for r in &mut track.records {
                    r.label = Some(false);
                }
                track
            })
            .collect();
        let fitted = fit_calibration_prior(&drives, Projection::default());
        assert_eq!(fitted.kept_default, None, "{fitted:?}");
        let [scale, heading, _] = fitted.prior.mean;
        assert!(
            (heading.to_degrees().abs() - 10.0).abs() < 2.0,
            "{fitted:?}"
        );
        assert!((scale.abs() - 0.04).abs() < 0.015, "{fitted:?}");
        assert!(fitted.prior.problem().is_none());
    }
}
