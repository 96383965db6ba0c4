//! The vector units: which kernels a CPU runs ([`Simd`], chosen in one
//! place for every hand-vectorised kernel: E-step, kernel factor, M-step),
//! and their state after faer's dense kernels ([`clear_upper_state`]).
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

/// A level of hand-written vector kernels. Every kernel with levels takes the
/// widest the CPU has ([`Simd::detect`]); tests hold each of
/// [`Simd::available`] to the portable sums.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub enum Simd {
    /// Loops written for LLVM's vectoriser (plain x86-64: unfused, so its
    /// sums round differently from the others').
    Portable,
    /// AVX2 and FMA, eight f32 lanes.
    Avx2,
    /// AVX-512F, sixteen f32 lanes.
    Avx512,
}

impl Simd {
    /// Whether this CPU runs the level's kernels.
    pub fn runs(self) -> bool {
        #[cfg(target_arch = "x86_64")]
        {
            match self {
                Simd::Portable => true,
                Simd::Avx2 => std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma"),
                Simd::Avx512 => std::is_x86_feature_detected!("avx512f"),
            }
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            self == Simd::Portable
        }
    }

    /// Every level this CPU runs, portable first (tests and benchmarks hold
    /// them to each other), whatever `GRASPD_SIMD` says.
    pub fn available() -> Vec<Simd> {
        [Simd::Portable, Simd::Avx2, Simd::Avx512].into_iter().filter(|l| l.runs()).collect()
    }

    /// The widest level this CPU runs, up to `cap` and to the environment's
    /// `GRASPD_SIMD` (portable, avx2 or avx512): the kernels' sums round
    /// differently, so fits agree bit for bit only between machines on one level.
    pub fn detect(cap: Simd) -> Simd {
        static ENV_CAP: std::sync::OnceLock<Simd> = std::sync::OnceLock::new();
        let env_cap = *ENV_CAP.get_or_init(|| match std::env::var("GRASPD_SIMD").as_deref() {
            Ok("portable") => Simd::Portable,
            Ok("avx2") => Simd::Avx2,
            Ok("avx512") | Err(std::env::VarError::NotPresent) => Simd::Avx512,
            Ok(other) => {
                tracing::warn!("GRASPD_SIMD={other:?} is none of portable, avx2, avx512: not capping the kernels");
                Simd::Avx512
            }
            Err(std::env::VarError::NotUnicode(v)) => {
                tracing::warn!("GRASPD_SIMD={v:?} is not UTF-8: not capping the kernels");
                Simd::Avx512
            }
        });
        let cap = cap.min(env_cap);
        // Called for every E-step: no allocation (`available` makes a Vec).
        [Simd::Avx512, Simd::Avx2].into_iter().find(|&l| l <= cap && l.runs()).unwrap_or(Simd::Portable)
    }
}

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

/// Unmasks (`trap`) or masks again MXCSR's denormal-operand exception on
/// this thread: unmasked, the next instruction that reads a subnormal
/// operand raises SIGFPE (for finding it under a debugger; see
/// `a_registration_computes_no_subnormal_numbers`).
#[cfg(all(test, target_arch = "x86_64"))]
pub(crate) fn trap_subnormal_operands(trap: bool) {
    const DENORMAL_MASK: u32 = 0x100;
    let mut csr = 0u32;
    // SAFETY: as in `sticky_fp_flags`; changes the status flags and the
    // denormal-operand mask bit, nothing else.
    unsafe {
        std::arch::asm!("stmxcsr [{}]", in(reg) &mut csr, options(nostack));
        csr = if trap { csr & !(DENORMAL_MASK | 0x3F) } else { csr | DENORMAL_MASK };
        std::arch::asm!("ldmxcsr [{}]", in(reg) &csr, options(nostack));
    }
}

/// MXCSR's denormal-operand and underflow flags.
#[cfg(all(test, target_arch = "x86_64"))]
pub(crate) const SUBNORMAL_FLAGS: u32 = 0x02 | 0x10;
