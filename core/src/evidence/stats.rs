//! The numpy/pandas statistics the evidence fits and the scaler share: the median, the type-7 quantile
//! and the ddof-1 covariance of 2-vectors.
//!
//! Owns these pure statistics helpers. Must not know about tracks, evidence or parameters.

use super::linalg::Mat2;

/// ddof-1 sample covariance of 2-vectors (needs at least 2 rows; NaN otherwise).
pub(super) fn covariance(rows: &[[f64; 2]]) -> Mat2 {
    let n = rows.len() as f64;
    let mean = rows
        .iter()
        .fold([0.0; 2], |acc, r| [acc[0] + r[0] / n, acc[1] + r[1] / n]);
    let mut sum = [[0.0; 2]; 2];
    for r in rows {
        let d = [r[0] - mean[0], r[1] - mean[1]];
        for (i, row) in sum.iter_mut().enumerate() {
            for (j, cell) in row.iter_mut().enumerate() {
                *cell += d[i] * d[j];
            }
        }
    }
    sum.map(|row| row.map(|s| s / (n - 1.0)))
}

/// numpy median: the mean of the two middle values for an even count. Sorts `values` in place;
/// `None` when empty. NaN sorts last (callers pass finite values).
pub fn median(values: &mut [f64]) -> Option<f64> {
    values.sort_unstable_by(f64::total_cmp);
    let n = values.len();
    match n {
        0 => None,
        _ if n % 2 == 1 => Some(values[n / 2]),
        _ => Some(0.5 * (values[n / 2 - 1] + values[n / 2])),
    }
}

/// pandas/numpy default ("linear", Hyndman–Fan type 7) quantile of SORTED values; `None` when empty.
pub fn quantile_sorted(sorted: &[f64], p: f64) -> Option<f64> {
    let last = sorted.len().checked_sub(1)?;
    let h = last as f64 * p.clamp(0.0, 1.0);
    let below = h.floor() as usize;
    let above = (below + 1).min(last);
    let fraction = h - below as f64;
    Some(sorted[below] + fraction * (sorted[above] - sorted[below]))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn numpy_median_odd_and_even() {
        assert_eq!(median(&mut [3.0, 1.0, 2.0]), Some(2.0));
        assert_eq!(median(&mut [4.0, 1.0, 3.0, 2.0]), Some(2.5));
        assert_eq!(median(&mut []), None);
    }

    #[test]
    fn type7_quantiles() {
        // n = 5: h = 4p. Q25 → h = 1 → 2; Q75 → h = 3 → 4; Q10 → h = 0.4 → 1 + 0.4·(2 − 1) = 1.4.
        let x = [1.0, 2.0, 3.0, 4.0, 10.0];
        assert_eq!(quantile_sorted(&x, 0.25), Some(2.0));
        assert_eq!(quantile_sorted(&x, 0.75), Some(4.0));
        assert!((quantile_sorted(&x, 0.1).expect("non-empty") - 1.4).abs() < 1e-15);
        // n = 4: Q25 → h = 0.75 → 1 + 0.75 = 1.75; Q75 → h = 2.25 → 3 + 0.25·6 = 4.5.
        let y = [1.0, 2.0, 3.0, 9.0];
        assert_eq!(quantile_sorted(&y, 0.25), Some(1.75));
        assert_eq!(quantile_sorted(&y, 0.75), Some(4.5));
        assert_eq!(quantile_sorted(&[7.0], 0.5), Some(7.0));
        assert_eq!(quantile_sorted(&[], 0.5), None);
    }
}
