//! The few dense kernels the model needs, written so LLVM vectorises them without fast-math.
//!
//! A plain `sum += a[i] * b[i]` loop cannot be vectorised (f64 addition is not associative), so `dot`
//! keeps eight independent partial sums; the summation order is fixed, hence results are reproducible.
//! `axpy`-shaped loops (`y[i] += a * x[i]`) vectorise as they are.

/// Logistic sigmoid, stable for large |x| (never NaN for finite or infinite x).
#[inline]
pub(crate) fn sigmoid(x: f64) -> f64 {
    if x >= 0.0 {
        1.0 / (1.0 + (-x).exp())
    } else {
        let e = x.exp();
        e / (1.0 + e)
    }
}

/// Sign with `sign(0) = 0`: the subgradient we use for `|x|` at 0.
#[inline]
pub(crate) fn sign(x: f64) -> f64 {
    if x > 0.0 {
        1.0
    } else if x < 0.0 {
        -1.0
    } else {
        0.0
    }
}

/// Dot product over the common length with a fixed summation order.
#[inline]
pub(crate) fn dot(a: &[f64], b: &[f64]) -> f64 {
    let n = a.len().min(b.len());
    let (a, b) = (&a[..n], &b[..n]);
    let mut acc = [0.0f64; 8];
    let mut a_chunks = a.chunks_exact(8);
    let mut b_chunks = b.chunks_exact(8);
    for (x, y) in (&mut a_chunks).zip(&mut b_chunks) {
        for k in 0..8 {
            acc[k] += x[k] * y[k];
        }
    }
    let mut tail = 0.0;
    for (x, y) in a_chunks.remainder().iter().zip(b_chunks.remainder()) {
        tail += x * y;
    }
    ((acc[0] + acc[1]) + (acc[2] + acc[3])) + ((acc[4] + acc[5]) + (acc[6] + acc[7])) + tail
}

/// `out = W x + b` for a row-major `W` with `out.len()` rows and `x.len()` columns.
#[inline]
pub(crate) fn affine(w: &[f64], b: &[f64], x: &[f64], out: &mut [f64]) {
    let cols = x.len();
    for ((row, bias), y) in w.chunks_exact(cols).zip(b).zip(out.iter_mut()) {
        *y = bias + dot(row, x);
    }
}

/// `y += a x`.
#[inline]
pub(crate) fn axpy(a: f64, x: &[f64], y: &mut [f64]) {
    for (yi, xi) in y.iter_mut().zip(x) {
        *yi += a * xi;
    }
}

/// Backward of `out = W x + b` for one step: `gW += d xᵀ`, `gb += d`, and `dx += Wᵀ d` when wanted.
#[inline]
pub(crate) fn affine_backward(
    w: &[f64],
    x: &[f64],
    d_out: &[f64],
    grad_w: &mut [f64],
    grad_b: &mut [f64],
    d_x: Option<&mut [f64]>,
) {
    let cols = x.len();
    for ((grad_row, gb), &d) in grad_w
        .chunks_exact_mut(cols)
        .zip(grad_b.iter_mut())
        .zip(d_out)
    {
        *gb += d;
        if d != 0.0 {
            axpy(d, x, grad_row);
        }
    }
    if let Some(d_x) = d_x {
        for (row, &d) in w.chunks_exact(cols).zip(d_out) {
            if d != 0.0 {
                axpy(d, row, d_x);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dot_and_affine_match_hand_computed_values() {
        let a: Vec<f64> = (1..=11).map(f64::from).collect();
        let b = vec![1.0; 11];
        assert_eq!(dot(&a, &b), 66.0);
        // W = [[1, 2], [3, 4]], x = [1, -1], b = [0.5, -0.5] → [-0.5, -1.5]
        let mut out = [0.0; 2];
        affine(&[1.0, 2.0, 3.0, 4.0], &[0.5, -0.5], &[1.0, -1.0], &mut out);
        assert_eq!(out, [-0.5, -1.5]);
    }

    #[test]
    fn affine_backward_is_outer_product_and_transpose() {
        let w = [1.0, 2.0, 3.0, 4.0];
        let (mut gw, mut gb, mut dx) = ([0.0; 4], [0.0; 2], [0.0; 2]);
        affine_backward(
            &w,
            &[1.0, -1.0],
            &[2.0, 3.0],
            &mut gw,
            &mut gb,
            Some(&mut dx),
        );
        assert_eq!(gw, [2.0, -2.0, 3.0, -3.0]);
        assert_eq!(gb, [2.0, 3.0]);
        assert_eq!(dx, [2.0 + 9.0, 4.0 + 12.0]);
    }

    #[test]
    fn sigmoid_is_stable_and_sign_of_zero_is_zero() {
        assert_eq!(sigmoid(0.0), 0.5);
        assert_eq!(sigmoid(-1000.0), 0.0);
        assert_eq!(sigmoid(1000.0), 1.0);
        assert!((sigmoid(2.0) + sigmoid(-2.0) - 1.0).abs() < 1e-15);
        assert_eq!(sign(0.0), 0.0);
        assert_eq!(sign(-0.0), 0.0);
        assert_eq!(sign(-3.0), -1.0);
    }
}
