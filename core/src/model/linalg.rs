//! The few dense kernels the model needs, written so LLVM vectorises them without fast-math.
//!
//! A plain `sum += a[i] * b[i]` loop cannot be vectorised (f64 addition is not associative), so `dot`
//! keeps `LANES` independent partial sums per row; the summation order is fixed, hence results are reproducible.
//! `axpy`-shaped loops (`y[i] += a * x[i]`) vectorise as they are.
//!
//! Owns the dense kernels of the model. Must not change their operation order: golden-bit tests pin it.

use wide::f64x4;

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

/// Lane width of the dot-product kernels: each row keeps this many partial sums, one per column
/// residue, combined as `((l0 + l1) + (l2 + l3)) + tail` (a fixed order, so results are reproducible).
const LANES: usize = 4;

#[inline]
fn combine(lanes: [f64; LANES], tail: f64) -> f64 {
    ((lanes[0] + lanes[1]) + (lanes[2] + lanes[3])) + tail
}

/// Dot product over the common length with a fixed summation order.
#[inline]
pub(crate) fn dot(a: &[f64], b: &[f64]) -> f64 {
    let n = a.len().min(b.len());
    let body = n - n % LANES;
    let mut lanes = [0.0f64; LANES];
    for (x, y) in a[..body]
        .chunks_exact(LANES)
        .zip(b[..body].chunks_exact(LANES))
    {
        for l in 0..LANES {
            lanes[l] += x[l] * y[l];
        }
    }
    let mut tail = 0.0;
    for (x, y) in a[body..n].iter().zip(&b[body..n]) {
        tail += x * y;
    }
    combine(lanes, tail)
}

/// Four dot products `rows[r] · x` at once: each load of `x` serves four rows (the single-row kernel
/// is load-bound). Same per-row summation order as [`dot`], so results are identical to it.
///
/// The four lanes of a row are one `f64x4` (exact IEEE multiply then add, as in `dot`): left to
/// itself, LLVM vectorises this loop across rows and pays a shuffle for every multiply.
#[inline]
fn dot4(rows: [&[f64]; 4], x: &[f64]) -> [f64; 4] {
    let n = x.len();
    let (x_chunks, _) = x.as_chunks::<LANES>();
    let [w0, w1, w2, w3] = rows.map(|row| row[..n].as_chunks::<LANES>().0);
    let mut lanes = [f64x4::ZERO; 4];
    let columns = x_chunks.iter().zip(w0).zip(w1).zip(w2).zip(w3);
    for ((((&xs, &a), &b), &c), &d) in columns {
        let xs = f64x4::from(xs);
        lanes[0] += f64x4::from(a) * xs;
        lanes[1] += f64x4::from(b) * xs;
        lanes[2] += f64x4::from(c) * xs;
        lanes[3] += f64x4::from(d) * xs;
    }
    let body = n - n % LANES;
    let mut out = [0.0; 4];
    for (r, row) in rows.iter().enumerate() {
        let mut tail = 0.0;
        for (w, v) in row[body..n].iter().zip(&x[body..n]) {
            tail += w * v;
        }
        out[r] = combine(lanes[r].to_array(), tail);
    }
    out
}

/// `out = W x + b` for a row-major `W` with `out.len()` rows and `x.len()` columns.
#[inline]
pub(crate) fn affine(w: &[f64], b: &[f64], x: &[f64], out: &mut [f64]) {
    let cols = x.len();
    if cols == 0 {
        for (y, bias) in out.iter_mut().zip(b) {
            *y = *bias;
        }
        return;
    }
    let rows = out.len().min(b.len()).min(w.len() / cols);
    let blocked = rows - rows % 4;
    let w_blocks = w[..blocked * cols].chunks_exact(4 * cols);
    let out_blocks = out[..blocked].chunks_exact_mut(4);
    for ((block, ys), bs) in w_blocks.zip(out_blocks).zip(b[..blocked].chunks_exact(4)) {
        let (r0, rest) = block.split_at(cols);
        let (r1, rest) = rest.split_at(cols);
        let (r2, r3) = rest.split_at(cols);
        let sums = dot4([r0, r1, r2, r3], x);
        for ((y, bias), sum) in ys.iter_mut().zip(bs).zip(sums) {
            *y = bias + sum;
        }
    }
    let w_rest = w[blocked * cols..rows * cols].chunks_exact(cols);
    for ((row, bias), y) in w_rest.zip(&b[blocked..rows]).zip(&mut out[blocked..rows]) {
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
    fn blocked_rows_equal_single_row_dots_bitwise() {
        let mut rng = crate::rng::Rng::seed_from_u64(4);
        for (rows, cols) in [(9, 13), (4, 4), (5, 3), (8, 128), (3, 1)] {
            let w: Vec<f64> = (0..rows * cols).map(|_| rng.normal()).collect();
            let b: Vec<f64> = (0..rows).map(|_| rng.normal()).collect();
            let x: Vec<f64> = (0..cols).map(|_| rng.normal()).collect();
            let mut out = vec![0.0; rows];
            affine(&w, &b, &x, &mut out);
            for r in 0..rows {
                let expected = b[r] + dot(&w[r * cols..(r + 1) * cols], &x);
                assert_eq!(
                    out[r].to_bits(),
                    expected.to_bits(),
                    "{rows}x{cols} row {r}"
                );
                let naive: f64 = b[r] + (0..cols).map(|c| w[r * cols + c] * x[c]).sum::<f64>();
                assert!((out[r] - naive).abs() < 1e-12);
            }
        }
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
    fn sign_of_zero_is_zero() {
        assert_eq!(sign(0.0), 0.0);
        assert_eq!(sign(-0.0), 0.0);
        assert_eq!(sign(-3.0), -1.0);
    }
}
