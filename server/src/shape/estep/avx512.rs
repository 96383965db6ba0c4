//! The single-precision E-step kernels in AVX-512, sixteen lanes a vector.
//!
//! The same sums, in the same order per lane, as the AVX2 kernels beside
//! them in `estep.rs`; two things make them more than twice as wide:
//! - a tail of 8 points (the buffers are padded to whole 8-lane vectors) is
//!   a masked load, not a scalar remainder or more padding;
//! - the exponential (`exp2_neg_f32`'s series) scales by 2ⁿ with `vscalefps`
//!   instead of integer shifts into the exponent, and its cut is a zeroing
//!   mask on the product with the weight.
//!
//! Written by hand for the reason the AVX2 ones are: the registration's time
//! is these loops (measured: the dense sums were 41 % of a mug fit on AVX2),
//! and neither LLVM's vectorisers nor a portable-SIMD crate on stable Rust
//! give the masked tails and the scalef exponential.

use std::arch::x86_64::*;

use super::{close_row, F32Buffers, LogSum, Posteriors, LANES, P3};
use crate::shape::fastexp::{EXP2_CUT_F32, EXP2_SERIES_F32};

const WIDE: usize = 16;

/// The load mask for the vector at `o` of a buffer of `len` (a multiple of 8).
#[inline(always)]
fn tail_mask(o: usize, len: usize) -> __mmask16 {
    if len - o >= WIDE {
        0xFFFF
    } else {
        0x00FF
    }
}

/// w·`exp2_neg_f32`(t) on sixteen lanes: the same series, with 2ⁿ applied
/// by `vscalefps` and the cut a zeroing mask on the product.
#[target_feature(enable = "avx512f")]
#[inline]
fn weighted_exp2_neg_f32x16(w: __m512, t: __m512) -> __m512 {
    let n = _mm512_roundscale_ps::<{ _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC }>(t);
    let f = _mm512_sub_ps(t, n);
    let mut p = _mm512_set1_ps(EXP2_SERIES_F32[0]);
    for c in &EXP2_SERIES_F32[1..] {
        p = _mm512_fmadd_ps(p, f, _mm512_set1_ps(*c));
    }
    let above = _mm512_cmp_ps_mask::<_CMP_GE_OQ>(t, _mm512_set1_ps(EXP2_CUT_F32));
    _mm512_maskz_mul_ps(above, w, _mm512_scalef_ps(p, n))
}

/// The sum of a vector's lanes, folded to eight for `close_row`.
#[target_feature(enable = "avx512f")]
#[inline]
fn fold_to_eight(v: __m512) -> [f32; LANES] {
    let mut l = [0.0f32; WIDE];
    // SAFETY: `l` holds sixteen lanes.
    unsafe { _mm512_storeu_ps(l.as_mut_ptr(), v) };
    std::array::from_fn(|i| l[i] + l[i + LANES])
}

/// `dense_rows_f32_avx2` on sixteen lanes.
///
/// # Safety
/// The CPU must have AVX-512F.
#[target_feature(enable = "avx512f")]
pub(super) unsafe fn dense_rows<const STATS: bool>(b: &mut F32Buffers, m: usize, k: f32, c: f64, out: &mut Posteriors) {
    let F32Buffers { x, ys, pi, row, acc, .. } = b;
    let m8 = pi.len();
    assert!(m8.is_multiple_of(LANES) && ys.iter().all(|v| v.len() == m8) && m <= m8);
    // The row and the sums are whole wide vectors: masked stores are slow
    // (measured on Zen 5: a quarter of this kernel's time).
    let m16 = m8.next_multiple_of(WIDE);
    row.resize(m16, 0.0);
    for a in acc.iter_mut() {
        a.clear();
        a.resize(m16, 0.0);
    }
    let (yx, yy, yz, w) = (ys[0].as_ptr(), ys[1].as_ptr(), ys[2].as_ptr(), pi.as_ptr());
    let r = row.as_mut_ptr();
    let [p1, px0, px1, px2] = acc;
    let (p1, px0, px1, px2) = (p1.as_mut_ptr(), px0.as_mut_ptr(), px1.as_mut_ptr(), px2.as_mut_ptr());
    let kv = _mm512_set1_ps(k);
    let mut log_den = LogSum::default();
    for (j, xn) in x.iter().enumerate() {
        let (x0, x1, x2) = (_mm512_set1_ps(xn[0]), _mm512_set1_ps(xn[1]), _mm512_set1_ps(xn[2]));
        let mut part = _mm512_setzero_ps();
        for o in (0..m8).step_by(WIDE) {
            let mk = tail_mask(o, m8);
            // SAFETY (all loads and stores here): the mask covers only lanes below m8, the
            // moving points' length; `row` and the sums hold m16.
            let dx = _mm512_sub_ps(x0, _mm512_maskz_loadu_ps(mk, yx.add(o)));
            let dy = _mm512_sub_ps(x1, _mm512_maskz_loadu_ps(mk, yy.add(o)));
            let dz = _mm512_sub_ps(x2, _mm512_maskz_loadu_ps(mk, yz.add(o)));
            let d2 = _mm512_fmadd_ps(dx, dx, _mm512_fmadd_ps(dy, dy, _mm512_mul_ps(dz, dz)));
            let v = weighted_exp2_neg_f32x16(_mm512_maskz_loadu_ps(mk, w.add(o)), _mm512_mul_ps(kv, d2));
            _mm512_storeu_ps(r.add(o), v);
            part = _mm512_add_ps(part, v);
        }
        let (pt1, inv) = close_row(&fold_to_eight(part), c, &mut log_den);
        if !STATS {
            continue;
        }
        out.pt1[j] = pt1;
        let inv32 = inv as f32;
        let (wi, w0, w1, w2) = (
            _mm512_set1_ps(inv32),
            _mm512_set1_ps(xn[0] * inv32),
            _mm512_set1_ps(xn[1] * inv32),
            _mm512_set1_ps(xn[2] * inv32),
        );
        for o in (0..m8).step_by(WIDE) {
            let v = _mm512_loadu_ps(r.add(o));
            _mm512_storeu_ps(p1.add(o), _mm512_fmadd_ps(v, wi, _mm512_loadu_ps(p1.add(o))));
            _mm512_storeu_ps(px0.add(o), _mm512_fmadd_ps(v, w0, _mm512_loadu_ps(px0.add(o))));
            _mm512_storeu_ps(px1.add(o), _mm512_fmadd_ps(v, w1, _mm512_loadu_ps(px1.add(o))));
            _mm512_storeu_ps(px2.add(o), _mm512_fmadd_ps(v, w2, _mm512_loadu_ps(px2.add(o))));
        }
    }
    if STATS {
        let [p1, px0, px1, px2] = acc;
        for i in 0..m {
            out.p1[i] = p1[i] as f64;
            out.px[i] = [px0[i] as f64, px1[i] as f64, px2[i] as f64];
        }
    }
    out.neg_log_likelihood -= log_den.total();
}

/// `dense_centroids_f32_avx2` on sixteen lanes.
///
/// # Safety
/// The CPU must have AVX-512F.
#[target_feature(enable = "avx512f")]
pub(super) unsafe fn dense_centroids(b: &F32Buffers, x: &[P3], k: f32, c: f64) -> ([f64; 3], [f64; 3], f64) {
    let F32Buffers { x: x32, ys, pi, .. } = b;
    let m8 = pi.len();
    assert!(m8.is_multiple_of(LANES) && ys.iter().all(|v| v.len() == m8) && x32.len() == x.len());
    let (yx, yy, yz, w) = (ys[0].as_ptr(), ys[1].as_ptr(), ys[2].as_ptr(), pi.as_ptr());
    let kv = _mm512_set1_ps(k);
    let hsum = |v: __m512| fold_to_eight(v).iter().map(|&l| l as f64).sum::<f64>();
    let (mut mx, mut my, mut np) = ([0.0; 3], [0.0; 3], 0.0);
    for (xn, x64) in x32.iter().zip(x) {
        let (x0, x1, x2) = (_mm512_set1_ps(xn[0]), _mm512_set1_ps(xn[1]), _mm512_set1_ps(xn[2]));
        let (mut part, mut s0, mut s1, mut s2) =
            (_mm512_setzero_ps(), _mm512_setzero_ps(), _mm512_setzero_ps(), _mm512_setzero_ps());
        for o in (0..m8).step_by(WIDE) {
            let mk = tail_mask(o, m8);
            // SAFETY (loads): the mask covers only lanes below m8, every buffer's length.
            let (py0, py1, py2) = (
                _mm512_maskz_loadu_ps(mk, yx.add(o)),
                _mm512_maskz_loadu_ps(mk, yy.add(o)),
                _mm512_maskz_loadu_ps(mk, yz.add(o)),
            );
            let (dx, dy, dz) = (_mm512_sub_ps(x0, py0), _mm512_sub_ps(x1, py1), _mm512_sub_ps(x2, py2));
            let d2 = _mm512_fmadd_ps(dx, dx, _mm512_fmadd_ps(dy, dy, _mm512_mul_ps(dz, dz)));
            let v = weighted_exp2_neg_f32x16(_mm512_maskz_loadu_ps(mk, w.add(o)), _mm512_mul_ps(kv, d2));
            part = _mm512_add_ps(part, v);
            s0 = _mm512_fmadd_ps(v, py0, s0);
            s1 = _mm512_fmadd_ps(v, py1, s1);
            s2 = _mm512_fmadd_ps(v, py2, s2);
        }
        let sum = hsum(part);
        let inv = 1.0 / (sum + c);
        let pt1 = sum * inv;
        np += pt1;
        for (d, s) in [s0, s1, s2].into_iter().enumerate() {
            mx[d] += pt1 * x64[d];
            my[d] += hsum(s) * inv;
        }
    }
    (mx, my, np)
}
