//! The fit of the offset parameters from training: each anchor's GNSS noise R and growth c²
//! (raw and calibrated) from the offsets seen while driving normally.
//!
//! Owns [`OffsetPoint`] and [`offset_params_from_points`]. Must not run the anchors (the evidence
//! fit feeds it their points) or know the vehicle's levels.

use super::params::{ANCHOR_COUNT, NOISE_RANGE_M2, OffsetParams};
use crate::evidence::EvidenceError;
use crate::evidence::stats::quantile_sorted;

/// One second of normal driving as one anchor saw it (the fit's input).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct OffsetPoint {
    /// ‖U_cal‖: net distance dead-reckoned with the warm calibration behind the anchor (m).
    pub carried_m: f64,
    /// ‖U_raw‖: the same before the calibration was warm (m).
    pub raw_carried_m: f64,
    /// ‖o‖ (m).
    pub offset_m: f64,
}

impl OffsetPoint {
    /// The calibration state whose growth this point measures: raw or calibrated when the other
    /// part of U is at most [`MIXED_SHARE`] of it; `None` for a mix of both.
    fn calibrated(&self) -> Option<bool> {
        if self.carried_m <= MIXED_SHARE * self.raw_carried_m {
            Some(false)
        } else if self.raw_carried_m <= MIXED_SHARE * self.carried_m {
            Some(true)
        } else {
            None
        }
    }

    /// ‖U‖ of its group.
    fn group_carried_m(&self) -> f64 {
        self.carried_m.max(self.raw_carried_m)
    }
}

/// A point measures one calibration state's growth when the other part of U is at most this share
/// of it (its variance then adds at most a few per cent).
const MIXED_SHARE: f64 = 0.05;

/// Fewest points per anchor and calibration state for a fit of that group.
pub const MIN_OFFSET_POINTS: usize = 30;
/// c² of uncalibrated dead reckoning when the data cannot tell: a heading bias of about 3° makes
/// an error of 5 % of the distance travelled.
pub const RAW_GROWTH_PRIOR: f64 = 0.05 * 0.05;
/// The least c² of calibrated dead reckoning: 1 % of the distance (a residual heading error of
/// half a degree and a speed scale off by half a per cent). An anchor that follows GNSS carries
/// short distances only, and a fit from them can extrapolate a growth near 0 to the kilometres a
/// frozen anchor carries.
pub const CALIBRATED_GROWTH_FLOOR: f64 = 0.01 * 0.01;
/// Equal-count bins of ‖U‖ per group of points.
const FIT_BINS: usize = 10;
/// The quantile the noise is matched at, and χ²₂'s value there (−2 ln 0.01). A bin's per-axis
/// variance is its 99 % quantile of ‖o‖² over this: the scale is matched where the gates work, in
/// the tail, and pooled over vehicles it is the scale of the noisier ones (receivers differ by 25×
/// in variance; a quieter vehicle's own level brings it down to a quarter of it).
pub const FIT_QUANTILE: f64 = 0.99;
pub const CHI2_2_AT_FIT_QUANTILE: f64 = 9.210_340_371_976_184;

/// Each anchor's R and c² (raw, calibrated) from its points: the points are grouped by the
/// calibration state their U was dead-reckoned in (mixed points are left out), binned by ‖U‖ (equal
/// counts, per group), each bin gives a variance v (its 99 % quantile of ‖o‖² / 9.21) at its median
/// ‖U‖², and v = R + c²_raw‖U‖²·[raw] + c²_cal‖U‖²·[calibrated] is fitted by least squares with
/// c² ≥ 0 (a negative slope is dropped and the rest refitted), each slope then raised to the bins'
/// upper envelope, the calibrated one at least [`CALIBRATED_GROWTH_FLOOR`]. Without calibrated
/// points the calibrated growth is the raw one; without raw points the raw growth is
/// [`RAW_GROWTH_PRIOR`].
pub fn offset_params_from_points(
    points: &[Vec<OffsetPoint>; ANCHOR_COUNT],
    step_noise_m2: f64,
) -> Result<OffsetParams, EvidenceError> {
    let mut params = OffsetParams {
        vehicle_levels: true,
        step_noise_m2: step_noise_m2.clamp(NOISE_RANGE_M2.0, NOISE_RANGE_M2.1),
        ..OffsetParams::unnormalised()
    };
    for (k, anchor_points) in points.iter().enumerate() {
        let group = |calibrated: bool| -> Vec<OffsetPoint> {
            anchor_points
                .iter()
                .copied()
                .filter(|p| p.calibrated() == Some(calibrated))
                .collect()
        };
        let (raw, calibrated) = (group(false), group(true));
        let has_raw = raw.len() >= MIN_OFFSET_POINTS;
        let has_calibrated = calibrated.len() >= MIN_OFFSET_POINTS;
        if !has_raw && !has_calibrated {
            return Err(EvidenceError::TooFewOffsetRows {
                rows: anchor_points.len(),
                minimum: MIN_OFFSET_POINTS,
            });
        }
        let mut rows: Vec<[f64; 3]> = Vec::new();
        if has_raw {
            rows.extend(binned(raw).map(|(x, v)| [x, 0.0, v]));
        }
        if has_calibrated {
            rows.extend(binned(calibrated).map(|(x, v)| [0.0, x, v]));
        }
        let [noise, raw_growth, calibrated_growth] = upper_envelope(
            &rows,
            non_negative_fit(&rows, [true, has_raw, has_calibrated]),
        );
        params.noise_m2[k] = noise.clamp(NOISE_RANGE_M2.0, NOISE_RANGE_M2.1);
        let calibrated_growth = calibrated_growth.clamp(CALIBRATED_GROWTH_FLOOR, 1.0);
        // An anchor that never ran long uncalibrated (the slow one settles after the warm-up)
        // takes the physical prior for raw onboard errors; calibration never makes them worse.
        let raw_growth = if has_raw {
            raw_growth.min(1.0)
        } else {
            RAW_GROWTH_PRIOR.max(calibrated_growth)
        };
        params.raw_growth[k] = raw_growth;
        params.calibrated_growth[k] = if has_calibrated {
            calibrated_growth
        } else {
            raw_growth
        };
    }
    params.validate()?;
    Ok(params)
}

/// (median ‖U‖², 99 % quantile of ‖o‖² / 9.21) per equal-count bin of ‖U‖.
fn binned(mut points: Vec<OffsetPoint>) -> impl Iterator<Item = (f64, f64)> {
    points.sort_by(|a, b| a.group_carried_m().total_cmp(&b.group_carried_m()));
    let size = points.len().div_ceil(FIT_BINS);
    let bins: Vec<(f64, f64)> = points
        .chunks(size)
        .map(|bin| {
            let carried = bin[bin.len() / 2].group_carried_m();
            let mut squared: Vec<f64> = bin.iter().map(|p| p.offset_m * p.offset_m).collect();
            squared.sort_by(f64::total_cmp);
            let tail = quantile_sorted(&squared, FIT_QUANTILE).unwrap_or(0.0);
            (carried * carried, tail / CHI2_2_AT_FIT_QUANTILE)
        })
        .collect();
    bins.into_iter()
}

/// The fitted line raised to an upper envelope of the bins: each slope becomes large enough that
/// no bin of its group lies above R + c²x. Dead-reckoning error differs between vehicles (the
/// calibration leaves each its own residual heading error), so the population's growth must cover
/// the vehicles that drift most; a vehicle's own level brings it down for the others.
fn upper_envelope(rows: &[[f64; 3]], beta: [f64; 3]) -> [f64; 3] {
    let mut out = beta;
    for row in rows {
        for group in 0..2 {
            let x = row[group];
            if x > 0.0 {
                out[group + 1] = out[group + 1].max((row[2] - beta[0]) / x);
            }
        }
    }
    out
}

/// Least squares of v = β₀ + β₁x₁ + β₂x₂ over `rows` ([x₁, x₂, v]) on the `active` coefficients,
/// dropping a slope that comes out negative (and refitting) until none does. Inactive and dropped
/// coefficients are 0.
fn non_negative_fit(rows: &[[f64; 3]], mut active: [bool; 3]) -> [f64; 3] {
    loop {
        let beta = solve_normal_equations(rows, active);
        match (1..3).find(|&j| active[j] && beta[j] < 0.0) {
            Some(j) => active[j] = false,
            None => return beta,
        }
    }
}

/// The least-squares coefficients of the active columns [1, x₁, x₂] by Gaussian elimination with
/// partial pivoting on the normal equations; a singular system leaves the slopes 0 and the
/// intercept the mean.
fn solve_normal_equations(rows: &[[f64; 3]], active: [bool; 3]) -> [f64; 3] {
    let columns: Vec<usize> = (0..3).filter(|&j| active[j]).collect();
    let n = columns.len();
    let feature = |row: &[f64; 3], j: usize| if j == 0 { 1.0 } else { row[j - 1] };
    let mut a = vec![vec![0.0; n + 1]; n];
    for row in rows {
        for (i, &ci) in columns.iter().enumerate() {
            for (j, &cj) in columns.iter().enumerate() {
                a[i][j] += feature(row, ci) * feature(row, cj);
            }
            a[i][n] += feature(row, ci) * row[2];
        }
    }
    let mean = rows.iter().map(|r| r[2]).sum::<f64>() / rows.len().max(1) as f64;
    let fallback = [mean, 0.0, 0.0];
    for pivot in 0..n {
        let best = (pivot..n)
            .max_by(|&x, &y| a[x][pivot].abs().total_cmp(&a[y][pivot].abs()))
            .unwrap_or(pivot);
        if a[best][pivot].abs() < 1e-12 * (1.0 + a[best][n].abs()) {
            return fallback;
        }
        a.swap(pivot, best);
        let (upper, lower) = a.split_at_mut(pivot + 1);
        let pivot_row = &upper[pivot];
        for row in lower.iter_mut() {
            let factor = row[pivot] / pivot_row[pivot];
            for (cell, above) in row.iter_mut().zip(pivot_row).skip(pivot) {
                *cell -= factor * above;
            }
        }
    }
    let mut solution = vec![0.0; n];
    for i in (0..n).rev() {
        let tail: f64 = (i + 1..n).map(|j| a[i][j] * solution[j]).sum();
        solution[i] = (a[i][n] - tail) / a[i][i];
    }
    let mut beta = [0.0; 3];
    for (value, &column) in solution.iter().zip(&columns) {
        beta[column] = *value;
    }
    if beta.iter().all(|b| b.is_finite()) {
        beta
    } else {
        fallback
    }
}
