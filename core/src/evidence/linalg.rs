//! 2×2 symmetric matrix helpers for Σ and Σ^{-1/2} (closed form: no allocation, no iteration).
//!
//! Owns the 2×2 linear algebra of the evidence. Must not know about samples.

/// A 2×2 matrix, row-major: `m[row][column]`.
pub type Mat2 = [[f64; 2]; 2];

/// The identity matrix.
pub const IDENTITY: Mat2 = [[1.0, 0.0], [0.0, 1.0]];

/// Eigenvalues below this are floored before the inverse square root (as the reference does), so a
/// singular or slightly indefinite matrix still gives a finite result.
pub const EIGENVALUE_FLOOR: f64 = 1e-12;

/// `m + λ·I`.
pub fn add_diagonal(m: Mat2, lambda: f64) -> Mat2 {
    [[m[0][0] + lambda, m[0][1]], [m[1][0], m[1][1] + lambda]]
}

/// `m · v`.
pub fn mul_vec(m: &Mat2, v: [f64; 2]) -> [f64; 2] {
    [
        m[0][0] * v[0] + m[0][1] * v[1],
        m[1][0] * v[0] + m[1][1] * v[1],
    ]
}

/// `x · y`.
pub fn mul(x: &Mat2, y: &Mat2) -> Mat2 {
    [
        [
            x[0][0] * y[0][0] + x[0][1] * y[1][0],
            x[0][0] * y[0][1] + x[0][1] * y[1][1],
        ],
        [
            x[1][0] * y[0][0] + x[1][1] * y[1][0],
            x[1][0] * y[0][1] + x[1][1] * y[1][1],
        ],
    ]
}

/// `m^{-1}` from the adjugate (non-finite for a singular `m`).
pub fn inverse(m: &Mat2) -> Mat2 {
    let k = 1.0 / (m[0][0] * m[1][1] - m[0][1] * m[1][0]);
    [[m[1][1] * k, -m[0][1] * k], [-m[1][0] * k, m[0][0] * k]]
}

/// Closed-form eigendecomposition of a symmetric 2×2 matrix (the off-diagonal taken as the mean of
/// the two given entries): eigenvalues λ₁, λ₂ along (cos θ, sin θ) and (−sin θ, cos θ).
struct SymmetricEigen {
    lambda1: f64,
    lambda2: f64,
    cos: f64,
    sin: f64,
}

impl SymmetricEigen {
    fn of(m: &Mat2) -> Self {
        let a = m[0][0];
        let b = 0.5 * (m[0][1] + m[1][0]);
        let c = m[1][1];
        // Rotation by θ with tan 2θ = 2b/(a−c) diagonalises S; eigenvector 1 = (cos θ, sin θ).
        let theta = 0.5 * (2.0 * b).atan2(a - c);
        let (sin, cos) = theta.sin_cos();
        // Rayleigh quotients: accurate eigenvalues even when they are close.
        Self {
            lambda1: a * cos * cos + 2.0 * b * cos * sin + c * sin * sin,
            lambda2: a * sin * sin - 2.0 * b * cos * sin + c * cos * cos,
            cos,
            sin,
        }
    }

    /// The symmetric matrix with the same eigenvectors and eigenvalues `f1`, `f2`.
    fn with_values(&self, f1: f64, f2: f64) -> Mat2 {
        let (cos, sin) = (self.cos, self.sin);
        let off = (f1 - f2) * cos * sin;
        [
            [f1 * cos * cos + f2 * sin * sin, off],
            [off, f1 * sin * sin + f2 * cos * cos],
        ]
    }
}

/// The symmetric 2×2 `m` with its eigenvalues raised to at least 1 (the smallest matrix above both
/// `m` and I along `m`'s eigenvectors); `None` when none is below 1.
pub fn floor_at_identity(m: &Mat2) -> Option<Mat2> {
    let eigen = SymmetricEigen::of(m);
    if eigen.lambda1 >= 1.0 && eigen.lambda2 >= 1.0 {
        return None;
    }
    Some(eigen.with_values(eigen.lambda1.max(1.0), eigen.lambda2.max(1.0)))
}

/// Symmetric inverse square root `S^{-1/2}` of a symmetric 2×2 matrix, from its closed-form
/// eigendecomposition with eigenvalues floored at [`EIGENVALUE_FLOOR`]. Non-finite input gives
/// non-finite output.
pub fn inverse_sqrt_symmetric(m: &Mat2) -> Mat2 {
    let eigen = SymmetricEigen::of(m);
    let f1 = 1.0 / eigen.lambda1.max(EIGENVALUE_FLOOR).sqrt();
    let f2 = 1.0 / eigen.lambda2.max(EIGENVALUE_FLOOR).sqrt();
    eigen.with_values(f1, f2)
}

/// `S^{-1/2}` of a symmetric positive-definite 2×2 matrix without trigonometry (per-step Σ_t is
/// one): with s = √det S and t = √(tr S + 2s), √S = (S + sI)/t, hence
/// S^{-1/2} = adj(S + sI)/(s·t). Falls back to [`inverse_sqrt_symmetric`] when S is not
/// positive definite (or overflows).
pub fn inverse_sqrt_positive_definite(m: &Mat2) -> Mat2 {
    let (a, c) = (m[0][0], m[1][1]);
    let b = 0.5 * (m[0][1] + m[1][0]);
    let determinant = a * c - b * b;
    if !(determinant > 0.0 && determinant.is_finite() && a > 0.0) {
        return inverse_sqrt_symmetric(m);
    }
    let s = determinant.sqrt();
    let t = (a + c + 2.0 * s).sqrt();
    let k = 1.0 / (s * t);
    [[(c + s) * k, -b * k], [-b * k, (a + s) * k]]
}

/// True when `m` is finite, symmetric (to 1e-9 relative) and positive definite.
pub fn is_symmetric_positive_definite(m: &Mat2) -> bool {
    let finite = m.iter().flatten().all(|x| x.is_finite());
    let scale = m[0][0].abs().max(m[1][1].abs()).max(f64::MIN_POSITIVE);
    let symmetric = (m[0][1] - m[1][0]).abs() <= 1e-9 * scale;
    let determinant = m[0][0] * m[1][1] - m[0][1] * m[1][0];
    finite && symmetric && m[0][0] > 0.0 && determinant > 0.0
}

#[cfg(test)]
mod tests {
    use super::*;

    fn assert_close(m: Mat2, expected: Mat2) {
        for (row, expected_row) in m.iter().zip(expected) {
            for (x, e) in row.iter().zip(expected_row) {
                assert!((x - e).abs() < 1e-12, "{m:?} != {expected:?}");
            }
        }
    }

    #[test]
    fn flooring_at_the_identity_raises_only_the_small_eigenvalues() {
        let floored = |m: Mat2| floor_at_identity(&m).expect("an eigenvalue below 1");
        // diag(0.25, 4): the first axis is raised to 1, the second kept.
        assert_close(floored([[0.25, 0.0], [0.0, 4.0]]), [[1.0, 0.0], [0.0, 4.0]]);
        assert_eq!(floor_at_identity(&[[2.0, 0.0], [0.0, 3.0]]), None);
        // [[2, 1], [1, 2]]: eigenvalues 3 along (1, 1) and 1 along (1, −1): kept.
        assert_eq!(floor_at_identity(&[[2.0, 1.0], [1.0, 2.0]]), None);
        // [[0.5, 0.25], [0.25, 0.5]]: eigenvalues 0.75 and 0.25, both raised: exactly I.
        assert_close(floored([[0.5, 0.25], [0.25, 0.5]]), IDENTITY);
        // [[1.25, 0.75], [0.75, 1.25]]: 2 along (1, 1), 0.5 along (1, −1) raised to 1:
        // 2·½(1,1)(1,1)ᵀ + 1·½(1,−1)(1,−1)ᵀ = [[1.5, 0.5], [0.5, 1.5]].
        assert_close(
            floored([[1.25, 0.75], [0.75, 1.25]]),
            [[1.5, 0.5], [0.5, 1.5]],
        );
    }

    #[test]
    fn inverse_and_product_undo_each_other() {
        let m = [[4.0, 1.0], [2.0, 3.0]];
        // det = 10: m^{-1} = [[0.3, −0.1], [−0.2, 0.4]].
        assert_close(inverse(&m), [[0.3, -0.1], [-0.2, 0.4]]);
        assert_close(mul(&m, &inverse(&m)), IDENTITY);
        assert_close(mul(&m, &IDENTITY), m);
    }

    #[test]
    fn inverse_sqrt_of_a_diagonal_matrix() {
        let r = inverse_sqrt_symmetric(&[[4.0, 0.0], [0.0, 9.0]]);
        assert!((r[0][0] - 0.5).abs() < 1e-15 && (r[1][1] - 1.0 / 3.0).abs() < 1e-15);
        assert!(r[0][1].abs() < 1e-15 && r[1][0].abs() < 1e-15);
    }

    #[test]
    fn inverse_sqrt_of_a_rotated_matrix() {
        // [[5, 3], [3, 5]] has eigenvalues 8 and 2 on (1,1)/√2 and (1,−1)/√2, so
        // S^{-1/2} = ½[[1/√8 + 1/√2, 1/√8 − 1/√2], [same, same]].
        let r = inverse_sqrt_symmetric(&[[5.0, 3.0], [3.0, 5.0]]);
        let (p, m) = (1.0 / 8.0_f64.sqrt(), 1.0 / 2.0_f64.sqrt());
        assert!((r[0][0] - 0.5 * (p + m)).abs() < 1e-14, "{r:?}");
        assert!((r[0][1] - 0.5 * (p - m)).abs() < 1e-14, "{r:?}");
        assert!((r[1][1] - 0.5 * (p + m)).abs() < 1e-14, "{r:?}");
        // And R·S·R = I.
        let identity = mul(&mul(&r, &[[5.0, 3.0], [3.0, 5.0]]), &r);
        for (i, row) in identity.iter().enumerate() {
            for (j, v) in row.iter().enumerate() {
                let want = if i == j { 1.0 } else { 0.0 };
                assert!((v - want).abs() < 1e-13, "{identity:?}");
            }
        }
    }

    #[test]
    fn inverse_sqrt_of_a_scalar_matrix_and_a_singular_one() {
        let r = inverse_sqrt_symmetric(&[[4.0, 0.0], [0.0, 4.0]]);
        assert_eq!(r, [[0.5, 0.0], [0.0, 0.5]]);
        // Singular: eigenvalue 0 floored to 1e-12 → 1e6 on that eigenvector, still finite.
        let r = inverse_sqrt_symmetric(&[[1.0, 0.0], [0.0, 0.0]]);
        assert!(
            (r[0][0] - 1.0).abs() < 1e-15 && (r[1][1] - 1e6).abs() < 1e-6,
            "{r:?}"
        );
    }

    #[test]
    fn fast_inverse_sqrt_agrees_with_the_eigen_form() {
        for m in [
            [[5.0, 3.0], [3.0, 5.0]],
            [[3.936, 0.183], [0.183, 2.150]],
            [[2.125, 1e-17], [1e-17, 2.0609]],
            [[1e-6, 0.0], [0.0, 1e4]],
        ] {
            let fast = inverse_sqrt_positive_definite(&m);
            let eigen = inverse_sqrt_symmetric(&m);
            for i in 0..2 {
                for j in 0..2 {
                    let scale = eigen[0][0].abs().max(eigen[1][1].abs());
                    assert!((fast[i][j] - eigen[i][j]).abs() < 1e-12 * scale, "{m:?}");
                }
            }
        }
        // Not positive definite → the floored eigen form.
        let singular = [[1.0, 0.0], [0.0, 0.0]];
        assert_eq!(
            inverse_sqrt_positive_definite(&singular),
            inverse_sqrt_symmetric(&singular)
        );
    }

    #[test]
    fn positive_definiteness() {
        assert!(is_symmetric_positive_definite(&[[2.0, 1.0], [1.0, 2.0]]));
        assert!(!is_symmetric_positive_definite(&[[1.0, 2.0], [2.0, 1.0]]));
        assert!(!is_symmetric_positive_definite(&[[1.0, 0.5], [0.0, 1.0]]));
        assert!(!is_symmetric_positive_definite(&[
            [f64::NAN, 0.0],
            [0.0, 1.0]
        ]));
        assert!(!is_symmetric_positive_definite(&[[0.0, 0.0], [0.0, 0.0]]));
    }

    /// Independent check with nalgebra's symmetric eigen-decomposition on a spread of matrices.
    #[test]
    fn closed_form_matches_nalgebra_symmetric_eigen() {
        use nalgebra::{Matrix2, SymmetricEigen};
        let cases: [Mat2; 4] = [
            [
                [3.9358913556405484, 0.1832531432589464],
                [0.1832531432589464, 2.1495387906372634],
            ],
            [[1e-3, 0.0], [0.0, 4e2]],
            [[2.0, 1.999], [1.999, 2.0]],
            [[5.0, -2.5], [-2.5, 3.0]],
        ];
        for m in cases {
            let eig = SymmetricEigen::new(Matrix2::new(m[0][0], m[0][1], m[1][0], m[1][1]));
            let inv_sqrt_diag = eig.eigenvalues.map(|l| 1.0 / l.sqrt());
            let expected = eig.eigenvectors
                * Matrix2::from_diagonal(&inv_sqrt_diag)
                * eig.eigenvectors.transpose();
            for got in [
                inverse_sqrt_symmetric(&m),
                inverse_sqrt_positive_definite(&m),
            ] {
                for i in 0..2 {
                    for j in 0..2 {
                        let (a, b) = (got[i][j], expected[(i, j)]);
                        assert!(
                            (a - b).abs() <= 1e-9 * b.abs().max(1.0),
                            "{m:?}: {a} vs {b}"
                        );
                    }
                }
            }
        }
    }
}
