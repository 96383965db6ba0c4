//! exp(x) for x ≤ 0, branch-free so LLVM vectorises the E-step loops.
//!
//! Written by hand because libm's `exp` is a scalar call per element: the
//! Gaussian affinities of the E-step are most of CPD's time, and this version
//! runs several times faster at a relative error below 1e-11, far under the
//! noise of any point cloud.

const LOG2E: f64 = std::f64::consts::LOG2_E;
/// 1.5·2⁵²: adding it rounds a double to an integer held in the low mantissa bits.
const ROUND_MAGIC: f64 = 6755399441055744.0;

/// e^x for x ≤ 0 (x below −600 returns exactly 0; positive x is not supported).
///
/// Exactly 0, not a tiny number: the E-step multiplies these by weights and
/// coordinates, and products below f64's normal range (subnormals) run about a
/// hundred times slower on x86.
#[inline(always)]
pub fn exp_neg(x: f64) -> f64 {
    // A plain select, not f64::max (whose NaN rules block vectorisation).
    let t = (if x < -600.0 { -600.0 } else { x }) * LOG2E;
    let r = t + ROUND_MAGIC;
    let n = r - ROUND_MAGIC;
    // |f| ≤ ln2/2.
    let f = (t - n) * std::f64::consts::LN_2;
    // Taylor series of e^f to degree 11: truncation error < 2e-16 on |f| ≤ 0.347.
    // Not formatted: rustfmt spins without end on this nesting (rustfmt 1.95).
    #[rustfmt::skip]
    let p = 1.0
        + f * (1.0
            + f * (1.0 / 2.0
                + f * (1.0 / 6.0
                    + f * (1.0 / 24.0
                        + f * (1.0 / 120.0
                            + f * (1.0 / 720.0
                                + f * (1.0 / 5040.0
                                    + f * (1.0 / 40320.0
                                        + f * (1.0 / 362880.0 + f * (1.0 / 3628800.0 + f * (1.0 / 39916800.0)))))))))));
    let ni = (r.to_bits() as i64).wrapping_sub(ROUND_MAGIC.to_bits() as i64);
    let scale = f64::from_bits(((ni + 1023) as u64) << 52);
    if x < -600.0 {
        0.0
    } else {
        p * scale
    }
}

/// a·b + c, as one fused instruction when `FMA` (only for callers compiled
/// with the `fma` target feature: elsewhere `mul_add` is a slow library call).
#[inline(always)]
pub fn madd<const FMA: bool>(a: f32, b: f32, c: f32) -> f32 {
    if FMA {
        a.mul_add(b, c)
    } else {
        a * b + c
    }
}

/// Below this exponent of 2 (e⁻⁶⁰ ≈ 1e-26) the single-precision exponentials
/// return exactly 0: f32 subnormals begin at e⁻⁸⁷, and a product with a
/// weight or a coordinate would land among them (measured: a registration
/// with view weights ran 5× slower from that alone).
pub const EXP2_CUT_F32: f32 = -60.0 * std::f32::consts::LOG2_E;

/// Coefficients of 2^f for |f| ≤ 1/2, highest first: a degree-4 polynomial
/// fitted for the least largest relative error with its constant held at 1
/// (2.9·10⁻⁶ evaluated in f32), in place of the degree-6 series of
/// e^{f·ln2} (2.3·10⁻⁷): two fused multiply-adds fewer for each pair of an
/// E-step, and no more error than f32's rounding of the argument t = k·d²
/// already makes at the far end of the range (up to 4·10⁻⁶ near the cut).
/// Measured, `eval transfer --views 12`, seeds 7 / 11 / 23, all three
/// categories: every keypoint median and p90 within 0.004 mm of the series'
/// (degree 5, 1.9·10⁻⁷: within 0.0005 mm); `VIEWPOINT=known bench_register
/// mug 1`, medians of 16 runs in turn: degree 6 → 5, 5.01 → 4.96 ms; 5 → 4,
/// 4.82 → 4.75 ms. The
/// fit: iteratively reweighted least squares on 40,000 points of the
/// interval (a discrete Remez exchange), in numpy.
pub const EXP2_SERIES_F32: [f32; 5] = [0.009_582_798, 0.055_906_292, 0.240_240_99, 0.693_124_2, 1.0];

/// 2^t for t ≤ 0 in single precision (relative error below 1e-5: f32's
/// rounding of the argument at large |t|, the polynomial's 3e-6 near 0), exactly 0 below
/// `EXP2_CUT_F32`: the registration's E-step, where f32 is plenty, computes
/// e^{k·d²} as 2^{k·log₂e·d²} with log₂e folded into k. The vector kernels
/// (`estep`) do the same operations in the same order; the polynomial is
/// evaluated in fused multiply-adds when `FMA`.
#[inline(always)]
pub fn exp2_neg_f32<const FMA: bool>(t: f32) -> f32 {
    const MAGIC: f32 = 12582912.0; // 1.5·2²³
    let below = t < EXP2_CUT_F32;
    let t = if below { EXP2_CUT_F32 } else { t };
    let r = t + MAGIC;
    let n = r - MAGIC;
    let f = t - n;
    let mut p = EXP2_SERIES_F32[0];
    for c in &EXP2_SERIES_F32[1..] {
        p = madd::<FMA>(p, f, *c);
    }
    let ni = (r.to_bits() as i32).wrapping_sub(MAGIC.to_bits() as i32);
    let e = p * f32::from_bits(((ni + 127) as u32) << 23);
    if below {
        0.0
    } else {
        e
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    #[test]
    fn matches_std_exp() {
        let mut worst: f64 = 0.0;
        for i in 0..200_000 {
            let x = -(i as f64) * 0.0029; // down to −580, above the cut
            let (a, b) = (exp_neg(x), x.exp());
            worst = worst.max(((a - b) / b).abs());
        }
        assert!(worst < 1e-12, "worst relative error {worst}");
        assert_eq!(exp_neg(0.0), 1.0);
        let mut worst32: f64 = 0.0;
        for i in 0..100_000 {
            let t = -(i as f32) * 0.00086; // down to −86, the cut
            let (a, b) = (exp2_neg_f32::<false>(t) as f64, (t as f64).exp2());
            worst32 = worst32.max(((a - b) / b).abs());
        }
        assert!(worst32 < 1e-5, "worst f32 relative error {worst32}");
        for i in 0..100_000 {
            let t = -(i as f32) * 0.00086;
            let (a, b) = (exp2_neg_f32::<true>(t) as f64, (t as f64).exp2());
            assert!(((a - b) / b).abs() < 1e-5, "fused: 2^{t} = {a}, not {b}");
        }
        assert_eq!(exp_neg(-1e6), 0.0);
        assert_eq!(exp2_neg_f32::<false>(-87.0), 0.0);
        assert_eq!(exp2_neg_f32::<false>(-1e30), 0.0);
        // Just above the cut: a normal number, not a subnormal.
        assert!(exp2_neg_f32::<false>(-86.5).is_normal() && exp_neg(-599.0).is_normal());
    }
}
