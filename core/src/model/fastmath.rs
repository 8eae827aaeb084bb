//! exp, expm1, tanh and the logistic sigmoid in pure Rust, written branch-free so LLVM vectorises them
//! over slices.
//!
//! Why not `f64::exp`: a step evaluates ~480 transcendental functions and the libm calls were ~45% of
//! its time; libm results may also differ in the last bit between machines/glibc builds, which would
//! break bit-for-bit reproducibility of training across machines. These use Cody–Waite range reduction
//! and a degree-13 Taylor polynomial (truncation < 1e-17 on |r| ≤ ln2/2); accuracy is within a few ulp
//! of the correctly rounded result (tests bound it against std). Results below e^−708 flush to 0.
//!
//! Owns the scalar/lane math functions the kernels use. Must not depend on the model types.

const LOG2_E: f64 = std::f64::consts::LOG2_E;
/// ln 2 split so that `k · LN2_HI` is exact for |k| < 2^11 (fdlibm constants).
const LN2_HI: f64 = 0.693_147_180_369_123_8;
const LN2_LO: f64 = 1.908_214_929_270_587_7e-10;
/// 1.5 · 2^52: adding and subtracting it rounds to the nearest integer, and the integer sits in the
/// low mantissa bits of the sum.
const ROUNDING_SHIFTER: f64 = 6_755_399_441_055_744.0;
/// Inputs above this overflow to +∞ (e^709.78 is the largest finite value).
const EXP_OVERFLOW: f64 = 709.782_712_893_384;
/// Inputs are clamped to `[EXP_CLAMP_LOW, EXP_OVERFLOW]` before the reduction, so k ∈ [−1021, 1024]
/// and 2^(k−1) is a normal number.
const EXP_CLAMP_LOW: f64 = -708.0;

/// e^r − 1 for |r| ≤ ln2/2: the Taylor series to r^13, `r + r²·p(r)` with p evaluated by Estrin's
/// scheme (short dependency chains, so neighbouring elements overlap in the pipeline).
#[inline(always)]
fn expm1_poly(r: f64) -> f64 {
    // p(r) = Σ_{i=0}^{11} r^i / (i + 2)!
    const C: [f64; 12] = [
        1.0 / 2.0,
        1.0 / 6.0,
        1.0 / 24.0,
        1.0 / 120.0,
        1.0 / 720.0,
        1.0 / 5_040.0,
        1.0 / 40_320.0,
        1.0 / 362_880.0,
        1.0 / 3_628_800.0,
        1.0 / 39_916_800.0,
        1.0 / 479_001_600.0,
        1.0 / 6_227_020_800.0,
    ];
    let r2 = r * r;
    let r4 = r2 * r2;
    let r8 = r4 * r4;
    let q0 = C[0] + C[1] * r;
    let q1 = C[2] + C[3] * r;
    let q2 = C[4] + C[5] * r;
    let q3 = C[6] + C[7] * r;
    let q4 = C[8] + C[9] * r;
    let q5 = C[10] + C[11] * r;
    let s0 = q0 + q1 * r2;
    let s1 = q2 + q3 * r2;
    let s2 = q4 + q5 * r2;
    let p = (s0 + s1 * r4) + s2 * r8;
    r + r2 * p
}

/// Range reduction x = k·ln2 + r, |r| ≤ ln2/2, of an already clamped x. Returns 2^(k−1) and e^r − 1.
#[inline(always)]
fn reduce(clamped: f64) -> (f64, f64) {
    let shifted = clamped * LOG2_E + ROUNDING_SHIFTER;
    let k = shifted - ROUNDING_SHIFTER;
    let r = (clamped - k * LN2_HI) - k * LN2_LO;
    let k_bits = shifted.to_bits().wrapping_sub(ROUNDING_SHIFTER.to_bits());
    // Exponent field of 2^(k−1) is k − 1 + 1023.
    let half_scale = f64::from_bits(k_bits.wrapping_add(1022) << 52);
    (half_scale, expm1_poly(r))
}

/// e^x = 2·(2^(k−1) + 2^(k−1)(e^r − 1)); the final ×2 is exact and lets k = 1024 near overflow.
#[inline(always)]
pub(crate) fn exp(x: f64) -> f64 {
    let (half_scale, em1) = reduce(x.clamp(EXP_CLAMP_LOW, EXP_OVERFLOW));
    let value = (half_scale + half_scale * em1) * 2.0;
    if x > EXP_OVERFLOW {
        f64::INFINITY
    } else if x < EXP_CLAMP_LOW {
        0.0
    } else if x.is_nan() {
        x
    } else {
        value
    }
}

/// e^x − 1 = 2·((2^(k−1) − ½) + 2^(k−1)(e^r − 1)): no cancellation near 0 (k = 0 gives exactly
/// e^r − 1) nor just above ln2/2.
#[inline(always)]
pub(crate) fn expm1(x: f64) -> f64 {
    let (half_scale, em1) = reduce(x.clamp(EXP_CLAMP_LOW, EXP_OVERFLOW));
    let value = ((half_scale - 0.5) + half_scale * em1) * 2.0;
    if x > EXP_OVERFLOW {
        f64::INFINITY
    } else if x < EXP_CLAMP_LOW {
        -1.0
    } else if x.is_nan() {
        x
    } else {
        value
    }
}

/// tanh(x) = −expm1(−2|x|) / (2 + expm1(−2|x|)), with the sign of x.
#[inline(always)]
pub(crate) fn tanh(x: f64) -> f64 {
    let m = expm1(-2.0 * x.abs());
    let magnitude = -m / (2.0 + m);
    if x.is_nan() { x } else { magnitude.copysign(x) }
}

/// Logistic sigmoid 1/(1 + e^−x); 0 at −∞ and 1 at +∞, never NaN for non-NaN x.
#[inline(always)]
pub(crate) fn sigmoid(x: f64) -> f64 {
    1.0 / (1.0 + exp(-x))
}

/// `values[i] = f(values[i])`, e.g. `map_in_place(v, tanh)`. Generic so each `f` is inlined into its
/// own loop, which LLVM vectorises.
#[inline(always)]
pub(crate) fn map_in_place(values: &mut [f64], f: impl Fn(f64) -> f64) {
    for value in values {
        *value = f(*value);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Rng;

    /// Distance in units in the last place (same sign, finite values).
    fn ulps(a: f64, b: f64) -> u64 {
        if a == b {
            return 0;
        }
        let (a, b) = (a.to_bits() as i64, b.to_bits() as i64);
        a.abs_diff(b)
    }

    fn samples() -> Vec<f64> {
        let mut rng = Rng::seed_from_u64(17);
        let mut xs: Vec<f64> = (0..20_000)
            .map(|_| rng.uniform_range(-40.0, 40.0))
            .collect();
        xs.extend((0..20_000).map(|_| rng.uniform_range(-1.0, 1.0)));
        xs.extend((0..5_000).map(|_| rng.uniform_range(-700.0, 700.0)));
        xs.extend((0..5_000).map(|_| rng.normal() * 1e-6));
        xs.extend([0.0, -0.0, 0.34657359, -0.34657359, 1.0, -1.0, 20.0, -20.0]);
        xs
    }

    #[test]
    fn exp_and_expm1_are_within_a_few_ulp_of_std() {
        let (mut worst_exp, mut worst_expm1) = (0, 0);
        for x in samples() {
            worst_exp = worst_exp.max(ulps(exp(x), x.exp()));
            worst_expm1 = worst_expm1.max(ulps(expm1(x), x.exp_m1()));
        }
        eprintln!("worst: exp {worst_exp} ulp, expm1 {worst_expm1} ulp");
        assert!(worst_exp <= 2, "exp: {worst_exp} ulp");
        assert!(worst_expm1 <= 3, "expm1: {worst_expm1} ulp");
    }

    #[test]
    fn tanh_and_sigmoid_are_accurate() {
        for x in samples() {
            let t = tanh(x);
            assert!(
                ulps(t, x.tanh()) <= 4 || (t - x.tanh()).abs() < 1e-300,
                "tanh({x}) = {t}"
            );
            let reference = 1.0 / (1.0 + (-x).exp());
            assert!(
                (sigmoid(x) - reference).abs() <= 4.0 * f64::EPSILON * reference,
                "{x}"
            );
        }
    }

    #[test]
    fn special_values() {
        assert_eq!(exp(0.0), 1.0);
        assert!(ulps(exp(1.0), std::f64::consts::E) <= 1);
        assert_eq!(exp(f64::INFINITY), f64::INFINITY);
        assert_eq!(exp(800.0), f64::INFINITY);
        assert_eq!(exp(f64::NEG_INFINITY), 0.0);
        assert_eq!(exp(-1000.0), 0.0);
        assert!(exp(709.7).is_finite() && exp(709.7) > 1e308);
        assert!(exp(f64::NAN).is_nan() && tanh(f64::NAN).is_nan() && expm1(f64::NAN).is_nan());
        assert_eq!(expm1(0.0), 0.0);
        assert_eq!(expm1(f64::NEG_INFINITY), -1.0);
        assert_eq!(tanh(0.0), 0.0);
        assert_eq!(tanh(f64::INFINITY), 1.0);
        assert_eq!(tanh(-1e300), -1.0);
        assert_eq!(sigmoid(0.0), 0.5);
        assert_eq!(sigmoid(-1e300), 0.0);
        assert_eq!(sigmoid(1e300), 1.0);
        let mut values = [0.0, 1.0, -2.0];
        map_in_place(&mut values, tanh);
        assert_eq!(values, [tanh(0.0), tanh(1.0), tanh(-2.0)]);
    }
}
