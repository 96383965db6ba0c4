//! The vector unit's state after faer's dense kernels.
//!
//! faer's matrix products run the `gemm` crate's AVX/AVX-512 microkernels,
//! which return with the upper halves of the vector registers dirty (no
//! `vzeroupper`). Until something clears them, every legacy-SSE instruction
//! after (all of our code built for baseline x86-64) carries a false
//! dependency on those halves. On the 2-core Zen 5 machine: a plain scalar
//! loop runs 2.4× slower after one 1000×20 product, and the kernel factor's
//! pivoted Cholesky 3.5× slower (35 ms → 125 ms) once an earlier factor has
//! run faer's products. Our own AVX kernels (`#[target_feature]`) clear the
//! state on return, as LLVM compiles them; faer's do not, so each call site
//! of a faer product or decomposition calls [`clear_upper_state`] after it.

/// Zeroes the upper halves of the vector registers (`vzeroupper`) where the
/// CPU has AVX; nothing elsewhere. Costs about a cycle.
#[inline]
pub fn clear_upper_state() {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx") {
        // SAFETY: the CPU runs AVX (checked just above).
        unsafe { std::arch::x86_64::_mm256_zeroupper() }
    }
}

/// The SSE/AVX unit's sticky flags raised while `f` runs on this thread:
/// denormal operand (0x02) and underflow (0x10) among them. For tests that
/// hold a computation out of f32's and f64's subnormal range, where Intel
/// cores take a microcode assist per result (AMD's do not, but raise the
/// same flags, so the tests fail on either).
#[cfg(all(test, target_arch = "x86_64"))]
pub(crate) fn sticky_fp_flags<R>(f: impl FnOnce() -> R) -> (R, u32) {
    const FLAGS: u32 = 0x3F;
    let mut csr = 0u32;
    // SAFETY: stmxcsr stores MXCSR's 32 bits into `csr`; ldmxcsr loads back
    // the value read with only its sticky status flags cleared (rounding and
    // exception masks unchanged).
    unsafe {
        std::arch::asm!("stmxcsr [{}]", in(reg) &mut csr, options(nostack));
        csr &= !FLAGS;
        std::arch::asm!("ldmxcsr [{}]", in(reg) &csr, options(nostack));
    }
    let r = f();
    // SAFETY: as above.
    unsafe { std::arch::asm!("stmxcsr [{}]", in(reg) &mut csr, options(nostack)) };
    (r, csr & FLAGS)
}

/// MXCSR's denormal-operand and underflow flags.
#[cfg(all(test, target_arch = "x86_64"))]
pub(crate) const SUBNORMAL_FLAGS: u32 = 0x02 | 0x10;
