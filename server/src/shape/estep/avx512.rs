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

use super::{close_centroid_rows, close_row, DenseRows, F32Buffers, LogSum, LANES, P3, ROW_BLOCK as BLOCK};
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
pub(super) fn weighted_exp2_neg_f32x16(w: __m512, t: __m512) -> __m512 {
    let cut = _mm512_set1_ps(EXP2_CUT_F32);
    let above = _mm512_cmp_ps_mask::<_CMP_GE_OQ>(t, cut);
    // Clamped before the series, as the AVX2 kernel does: the zeroing mask
    // below drops these lanes, but `vscalefps` still computes them, and a
    // result in (or under) f32's subnormal range takes a microcode assist on
    // Intel cores (AMD's Zen 5 showed nothing). Measured on a 2-core Xeon
    // (`VIEWPOINT=known bench_register mug 2`, p50): race stage 27.8 → 4.1
    // ms, whole fit 47.0 → 17.1 ms (the AVX2 kernels: 22.3, race 6.4).
    let t = _mm512_max_ps(t, cut);
    let n = _mm512_roundscale_ps::<{ _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC }>(t);
    let f = _mm512_sub_ps(t, n);
    let mut p = _mm512_set1_ps(EXP2_SERIES_F32[0]);
    for c in &EXP2_SERIES_F32[1..] {
        p = _mm512_fmadd_ps(p, f, _mm512_set1_ps(*c));
    }
    _mm512_maskz_mul_ps(above, w, _mm512_scalef_ps(p, n))
}

/// The sum of a vector's lanes, folded to eight for `close_row`.
#[target_feature(enable = "avx512f")]
#[inline]
fn fold_to_eight(v: __m512) -> [f32; LANES] {
    let mut l = [0.0f32; WIDE];
    // SAFETY: `l` holds sixteen lanes.
    unsafe { _mm512_storeu_ps(l.as_mut_ptr(), v) };
    let mut eight = [0.0; LANES];
    for i in 0..LANES {
        eight[i] = l[i] + l[i + LANES];
    }
    eight
}

/// The sum of a vector's lanes in double precision.
#[target_feature(enable = "avx512f")]
#[inline]
pub(super) fn lane_sum_f64(v: __m512) -> f64 {
    let mut sum = 0.0;
    for l in fold_to_eight(v) {
        sum += l as f64;
    }
    sum
}

/// `dense_rows_f32_avx2` on sixteen lanes, four data points (rows) at a
/// time: the moving points are loaded once per block, and the posterior sums
/// read and written once per block instead of once per row. Measured: with
/// the short rows of the coarse and race models (100-200 points, 7-13
/// vectors), row by row spent as long closing rows and updating the sums as
/// on the exponentials. The sums are added row after row as before, so the
/// results are the same bit for bit.
///
/// # Safety
/// The CPU must have AVX-512F.
#[target_feature(enable = "avx512f")]
pub(super) unsafe fn dense_rows<const STATS: bool>(job: DenseRows<'_>, k: f32, c: f64) -> f64 {
    let DenseRows { x, ys, pi, row, acc, pt1: pt1_out } = job;
    let m8 = pi.len();
    assert!(m8.is_multiple_of(LANES) && ys.iter().all(|v| v.len() == m8) && (!STATS || pt1_out.len() == x.len()));
    // The rows and the sums are whole wide vectors, so only the moving
    // points' loads need a tail mask (masked stores are slow on AMD).
    let m16 = m8.next_multiple_of(WIDE);
    row.resize(BLOCK * m16, 0.0);
    for a in acc.iter_mut() {
        a.clear();
        a.resize(m16, 0.0);
    }
    let rows = Rows {
        moving: Moving::new(ys, pi, k),
        m16,
        c,
        row: row.as_mut_ptr(),
        acc: acc.each_mut().map(|a| a.as_mut_ptr()),
    };
    let mut log_den = LogSum::default();
    let mut blocks = x.chunks_exact(BLOCK);
    for (i, block) in blocks.by_ref().enumerate() {
        // SAFETY: `rows` points into buffers of the lengths it records.
        let pt1 = unsafe { rows.block::<BLOCK, STATS>(block.try_into().expect("a whole block"), &mut log_den) };
        if STATS {
            pt1_out[i * BLOCK..(i + 1) * BLOCK].copy_from_slice(&pt1);
        }
    }
    let done = x.len() - blocks.remainder().len();
    for (i, xn) in blocks.remainder().iter().enumerate() {
        // SAFETY: as above.
        let pt1 = unsafe { rows.block::<1, STATS>(&[*xn], &mut log_den) };
        if STATS {
            pt1_out[done + i] = pt1[0];
        }
    }
    log_den.total()
}

/// The moving points (three columns) and their weights, `m8` long, with the
/// exponent's factor k: what every dense AVX-512 kernel reads.
struct Moving {
    y: [*const f32; 3],
    w: *const f32,
    m8: usize,
    k: __m512,
}

impl Moving {
    #[target_feature(enable = "avx512f")]
    fn new(ys: &[Vec<f32>; 3], pi: &[f32], k: f32) -> Self {
        Self { y: [ys[0].as_ptr(), ys[1].as_ptr(), ys[2].as_ptr()], w: pi.as_ptr(), m8: pi.len(), k: _mm512_set1_ps(k) }
    }

    /// The moving points' three coordinates and their weights at `o`, zero past m8.
    ///
    /// # Safety
    /// o < m8 and m8 a multiple of 8 (the mask covers only lanes below m8).
    #[target_feature(enable = "avx512f")]
    #[inline]
    unsafe fn at(&self, o: usize) -> [__m512; 4] {
        let mk = tail_mask(o, self.m8);
        // SAFETY: the mask covers only lanes below m8, every buffer's length.
        unsafe {
            [
                _mm512_maskz_loadu_ps(mk, self.y[0].add(o)),
                _mm512_maskz_loadu_ps(mk, self.y[1].add(o)),
                _mm512_maskz_loadu_ps(mk, self.y[2].add(o)),
                _mm512_maskz_loadu_ps(mk, self.w.add(o)),
            ]
        }
    }

    /// w·2^{k·|x − y|²} for the broadcast data point `x` and the moving points `yw` (from `at`).
    #[target_feature(enable = "avx512f")]
    #[inline]
    fn affinity(&self, x: &[__m512; 3], yw: &[__m512; 4]) -> __m512 {
        let (dx, dy, dz) = (_mm512_sub_ps(x[0], yw[0]), _mm512_sub_ps(x[1], yw[1]), _mm512_sub_ps(x[2], yw[2]));
        let d2 = _mm512_fmadd_ps(dx, dx, _mm512_fmadd_ps(dy, dy, _mm512_mul_ps(dz, dz)));
        weighted_exp2_neg_f32x16(yw[3], _mm512_mul_ps(self.k, d2))
    }

    /// Per data point of `xs`: Σₘ aₘ and Σₘ aₘ yₘ over its affinities aₘ
    /// (`dense_centroids`'s block).
    ///
    /// # Safety
    /// The pointers hold the lengths `Moving` records.
    #[target_feature(enable = "avx512f")]
    #[inline]
    unsafe fn centroid_block<const B: usize>(&self, xs: &[[f32; 3]; B]) -> [[f64; 4]; B] {
        // No closures here (see `Rows::block`).
        let xv = broadcast(xs);
        let mut acc = [[_mm512_setzero_ps(); 4]; B];
        for o in (0..self.m8).step_by(WIDE) {
            // SAFETY: o < m8.
            let yw = unsafe { self.at(o) };
            for b in 0..B {
                let v = self.affinity(&xv[b], &yw);
                acc[b][0] = _mm512_add_ps(acc[b][0], v);
                acc[b][1] = _mm512_fmadd_ps(v, yw[0], acc[b][1]);
                acc[b][2] = _mm512_fmadd_ps(v, yw[1], acc[b][2]);
                acc[b][3] = _mm512_fmadd_ps(v, yw[2], acc[b][3]);
            }
        }
        let mut totals = [[0.0; 4]; B];
        for b in 0..B {
            for i in 0..4 {
                totals[b][i] = lane_sum_f64(acc[b][i]);
            }
        }
        totals
    }
}

/// The `B` data points `xs`, each coordinate on every lane.
#[target_feature(enable = "avx512f")]
#[inline]
fn broadcast<const B: usize>(xs: &[[f32; 3]; B]) -> [[__m512; 3]; B] {
    let mut xv = [[_mm512_setzero_ps(); 3]; B];
    for b in 0..B {
        for i in 0..3 {
            xv[b][i] = _mm512_set1_ps(xs[b][i]);
        }
    }
    xv
}

/// `dense_rows`' buffers: the moving points, `BLOCK` rows of `m16` and the
/// four sums (P1, PX as three columns), `m16` long.
struct Rows {
    moving: Moving,
    m16: usize,
    c: f64,
    row: *mut f32,
    acc: [*mut f32; 4],
}

impl Rows {
    /// The rows of the `B` data points `xs`: their totals closed into the
    /// likelihood (in order), and with `STATS` their shares (returned) and
    /// their posteriors added to the sums.
    ///
    /// # Safety
    /// The pointers hold the lengths `Rows` records; B ≤ `BLOCK`.
    #[target_feature(enable = "avx512f")]
    #[inline]
    unsafe fn block<const B: usize, const STATS: bool>(&self, xs: &[[f32; 3]; B], log_den: &mut LogSum) -> [f64; B] {
        // No closures in here: a closure is its own function, compiled without
        // this one's target features, and each intrinsic in it becomes a call.
        let xv = broadcast(xs);
        let mut part = [_mm512_setzero_ps(); B];
        for o in (0..self.moving.m8).step_by(WIDE) {
            // SAFETY: o < m8; each row holds m16 from b·m16, and B ≤ BLOCK rows fit.
            let yw = unsafe { self.moving.at(o) };
            for b in 0..B {
                let v = self.moving.affinity(&xv[b], &yw);
                unsafe { _mm512_storeu_ps(self.row.add(b * self.m16 + o), v) };
                part[b] = _mm512_add_ps(part[b], v);
            }
        }
        let mut pt1 = [0.0; B];
        let mut scale = [[_mm512_setzero_ps(); 4]; B];
        for b in 0..B {
            let (share, inv) = close_row(&fold_to_eight(part[b]), self.c, log_den);
            pt1[b] = share;
            let inv32 = inv as f32;
            scale[b] = [
                _mm512_set1_ps(inv32),
                _mm512_set1_ps(xs[b][0] * inv32),
                _mm512_set1_ps(xs[b][1] * inv32),
                _mm512_set1_ps(xs[b][2] * inv32),
            ];
        }
        if STATS {
            for o in (0..self.m16).step_by(WIDE) {
                // SAFETY: the sums and each row hold m16.
                let mut sums = [_mm512_setzero_ps(); 4];
                for i in 0..4 {
                    sums[i] = unsafe { _mm512_loadu_ps(self.acc[i].add(o)) };
                }
                for b in 0..B {
                    let v = unsafe { _mm512_loadu_ps(self.row.add(b * self.m16 + o)) };
                    for i in 0..4 {
                        sums[i] = _mm512_fmadd_ps(v, scale[b][i], sums[i]);
                    }
                }
                for i in 0..4 {
                    unsafe { _mm512_storeu_ps(self.acc[i].add(o), sums[i]) };
                }
            }
        }
        pt1
    }
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
    let moving = Moving::new(ys, pi, k);
    let mut sums = [[0.0; 3], [0.0; 3]];
    let mut np = 0.0;
    let mut blocks = x32.chunks_exact(BLOCK).zip(x.chunks_exact(BLOCK));
    for (block, block64) in blocks.by_ref() {
        // SAFETY: `moving` points into buffers of the lengths it records.
        let totals = unsafe { moving.centroid_block::<BLOCK>(block.try_into().expect("a whole block")) };
        close_centroid_rows(&totals, block64, c, &mut sums, &mut np);
    }
    let done = x.len() - x.len() % BLOCK;
    for (xn, x64) in x32[done..].iter().zip(&x[done..]) {
        // SAFETY: as above.
        let totals = unsafe { moving.centroid_block::<1>(&[*xn]) };
        close_centroid_rows(&totals, std::slice::from_ref(x64), c, &mut sums, &mut np);
    }
    let [mx, my] = sums;
    (mx, my, np)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::shape::fastexp::exp2_neg_f32;
    use crate::simd::{sticky_fp_flags, SUBNORMAL_FLAGS};

    /// Lanes far below the cut must not pass through f32's subnormal range
    /// on their way to the zero they are masked to: an Intel core takes a
    /// microcode assist for each (the race ran 6× slower for it on a Xeon).
    /// The processor's sticky underflow flag tells whether any did (it is
    /// raised by a tiny inexact result: hence the fractional exponents).
    #[test]
    fn the_exponential_neither_underflows_nor_differs_from_the_scalar_one() {
        if !std::is_x86_feature_detected!("avx512f") {
            eprintln!("skipped: this CPU has no AVX-512F");
            return;
        }
        let ts: [f32; 16] = [
            0.0,
            -1.0,
            -10.5,
            -86.3,
            -87.3,
            -100.3,
            -126.3,
            -130.3,
            -140.3,
            -149.3,
            -150.3,
            -200.3,
            -1e3,
            -1e6,
            -1e30,
            f32::NEG_INFINITY,
        ];
        #[target_feature(enable = "avx512f")]
        fn run(w: f32, ts: &[f32; 16]) -> [f32; 16] {
            let mut out = [0.0f32; 16];
            // SAFETY: both arrays hold sixteen lanes.
            unsafe {
                let v = weighted_exp2_neg_f32x16(_mm512_set1_ps(w), _mm512_loadu_ps(ts.as_ptr()));
                _mm512_storeu_ps(out.as_mut_ptr(), v);
            }
            out
        }
        // Opaque inputs: with a weight known to be 1, LLVM moves the zeroing
        // mask onto `vscalefps` and the test would see nothing.
        // SAFETY: AVX-512F is present (checked above).
        let (out, flags) = sticky_fp_flags(|| unsafe { run(std::hint::black_box(1.0), std::hint::black_box(&ts)) });
        assert_eq!(flags & SUBNORMAL_FLAGS, 0, "MXCSR flags {flags:#x} after the exponentials of {ts:?}");
        for (t, e) in ts.iter().zip(out) {
            assert_eq!(e, exp2_neg_f32::<true>(*t), "2^{t}");
        }
    }
}
