//! The E-step of a mixture whose components are surface elements (surfels):
//! each moving point carries a unit normal, and its Gaussian has variance
//! σ_n² along the normal and σ_t² across it.
//!
//! Why: a model sampled at a few hundred points must keep isotropic
//! components as wide as the points' spacing to cover the surface between
//! them, and that width blurs the fit along the normal too, where a depth
//! view is most precise (the registered surface sat 0.4-1 mm off the
//! observed one along the view). A surfel's σ_t takes the spacing and its
//! σ_n the sensor's noise (measured on the polish: σ_t 5.4 mm, σ_n 0.9 mm
//! on a mug view with 1 mm depth noise).
//!
//! Besides CPD's sums this returns the posterior-weighted squared residuals
//! along the normals and in all, from which the fit re-estimates σ_n² and
//! σ_t² (a conditional maximisation at the E-step's model, before its pose
//! and latent move: ECM; these sums cost two multiply-adds a pair, where
//! re-estimating them about the moved model needed six sums a moving point
//! updated for every pair).

use super::{dist2, exponent_f32, outlier_constant, row_total, EStep, LogSum, Posteriors, P3};
use crate::shape::fastexp::{exp2_neg_f32, madd};
use crate::simd::Simd;

/// The mixture's components: a normal per moving point and the two variances.
#[derive(Clone, Copy)]
pub struct Surfels<'a> {
    /// Unit normals of the moving points, in the data's frame.
    pub normals: &'a [P3],
    /// Variance across the surface (σ_t²) and along the normal (σ_n²).
    pub tangent_sigma2: f64,
    pub normal_sigma2: f64,
}

impl Surfels<'_> {
    /// The isotropic variance with the same normalising constant
    /// (σ³ = σ_t²σ_n): the outlier term and the likelihood use it.
    pub fn equivalent_sigma2(&self) -> f64 {
        (self.tangent_sigma2 * self.tangent_sigma2 * self.normal_sigma2).cbrt()
    }
}

/// Posterior-weighted squared residuals r = x − y of an E-step:
/// Σ Pₘₙ (nₘ·r)² and Σ Pₘₙ |r|².
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ResidualSums {
    pub along_normals: f64,
    pub total: f64,
}

impl ResidualSums {
    /// The variances that maximise the likelihood at these sums: (σ_t², σ_n²).
    pub fn variances(&self, np: f64) -> (f64, f64) {
        let np = np.max(1e-300);
        (((self.total - self.along_normals) / (2.0 * np)).max(1e-10), (self.along_normals / np).max(1e-10))
    }
}

/// Affinities below this (e^{-27.7}) count toward the posteriors but not
/// toward the variances' residual sums, so that every product there stays
/// a normal f32 number (a subnormal costs a microcode assist on Intel: see
/// `fastexp::EXP2_CUT_F32`). Such a pair's share of σ_n² is negligible
/// unless its data point is explained by nothing else, and then the
/// outlier term takes it.
const RESIDUAL_SUMS_FLOOR: f32 = 9.094947e-13; // 2^-40

/// Normal components smaller than this are taken as 0: the projection of a
/// residual on them would be a subnormal number.
const NORMAL_FLUSH: f64 = 1e-6;

/// Moving points a block: one AVX-512 vector, two AVX2 ones.
const BLOCK: usize = 16;
type Lanes = [f32; BLOCK];

/// One block of moving points, structure of arrays.
#[derive(Clone, Copy, Default)]
struct Block {
    y: [Lanes; 3],
    n: [Lanes; 3],
    pi: Lanes,
}

/// The moving points of a surfel E-step in blocks of nearby points, each
/// with a bounding sphere: a data point skips the blocks whose sphere lies
/// beyond the cutoff (a neighbour list without the list: on a 2,000-point
/// view most blocks are far from most data points, and a block is one
/// vector of work or none).
#[derive(Default)]
pub(super) struct SurfelBuffers {
    /// Moving point of each block slot (the spatial order, made at the first
    /// call of a fit: the model moves little within one); `usize::MAX` pads.
    order: Vec<usize>,
    blocks: Vec<Block>,
    /// Bounding spheres of the blocks as columns (centre x, y, z and
    /// radius), for the kernel's vector test of which blocks a data point reaches.
    spheres: [Vec<f32>; 4],
    /// Per block: the row's affinities, and the P1 and PX sums.
    row: Vec<Lanes>,
    acc: Vec<[Lanes; 4]>,
    live: Vec<u32>,
    x: Vec<[f32; 3]>,
}

impl SurfelBuffers {
    fn load(&mut self, x: &[P3], y: &[P3], s: &Surfels, weights: Option<&[f64]>) {
        if self.x.len() != x.len() {
            self.x = x.iter().map(|p| [p[0] as f32, p[1] as f32, p[2] as f32]).collect();
        }
        let m = y.len();
        if self.order.iter().filter(|&&i| i != usize::MAX).count() != m {
            self.order = spatial_order(y);
        }
        let nb = self.order.len() / BLOCK;
        self.blocks.resize(nb, Block::default());
        self.spheres.iter_mut().for_each(|c| c.clear());
        for (block, slots) in self.blocks.iter_mut().zip(self.order.chunks_exact(BLOCK)) {
            // Padding repeats the block's first point with no weight, so it leaves the sphere alone.
            let first = slots[0];
            let mut c = [0.0f64; 3];
            for (l, &i) in slots.iter().enumerate() {
                let (k, w) = if i == usize::MAX { (first, 0.0) } else { (i, weights.map_or(1.0, |w| w[i])) };
                for d in 0..3 {
                    block.y[d][l] = y[k][d] as f32;
                    let nd = s.normals[k][d];
                    block.n[d][l] = if nd.abs() < NORMAL_FLUSH { 0.0 } else { nd as f32 };
                    c[d] += y[k][d] / BLOCK as f64;
                }
                block.pi[l] = w as f32;
            }
            let r2 = slots.iter().map(|&i| dist2(&y[if i == usize::MAX { first } else { i }], &c)).fold(0.0, f64::max);
            for (col, v) in self.spheres.iter_mut().zip([c[0], c[1], c[2], r2.sqrt()]) {
                col.push(v as f32);
            }
        }
        self.row.resize(nb, [0.0; BLOCK]);
        self.acc.clear();
        self.acc.resize(nb, [[0.0; BLOCK]; 4]);
    }

    fn store(&self, out: &mut Posteriors) {
        for (slots, a) in self.order.chunks_exact(BLOCK).zip(&self.acc) {
            for (l, &i) in slots.iter().enumerate() {
                if i != usize::MAX {
                    out.p1[i] = a[0][l] as f64;
                    out.px[i] = [a[1][l] as f64, a[2][l] as f64, a[3][l] as f64];
                }
            }
        }
    }
}

/// The moving points sorted along a Morton curve of a 64³ grid over their
/// bounding box, padded to whole blocks with `usize::MAX`.
fn spatial_order(y: &[P3]) -> Vec<usize> {
    let (mut lo, mut hi) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
    for p in y {
        for d in 0..3 {
            lo[d] = lo[d].min(p[d]);
            hi[d] = hi[d].max(p[d]);
        }
    }
    let side = (0..3).map(|d| hi[d] - lo[d]).fold(0.0, f64::max).max(1e-12);
    let code = |p: &P3| {
        let mut key = 0u64;
        let cell = [0, 1, 2].map(|d| (((p[d] - lo[d]) / side * 63.999).clamp(0.0, 63.0)) as u64);
        for bit in 0..6 {
            for (d, c) in cell.iter().enumerate() {
                key |= ((c >> bit) & 1) << (3 * bit + d);
            }
        }
        key
    };
    let mut order: Vec<usize> = (0..y.len()).collect();
    order.sort_by_key(|&i| (code(&y[i]), i));
    order.resize(y.len().div_ceil(BLOCK) * BLOCK, usize::MAX);
    order
}

/// The exponent factors: 2^{kt·|r|² + kd·(n·r)²} = e^{−|r_t|²/2σ_t² − (n·r)²/2σ_n²}.
fn exponents(s: &Surfels) -> (f32, f32) {
    let kt = exponent_f32(s.tangent_sigma2);
    (kt, exponent_f32(s.normal_sigma2) - kt)
}

impl EStep {
    /// The E-step of the surfel mixture at `y`; fills `out` as `run_weighted`
    /// does and returns the squared residuals. Pairs farther than
    /// `cutoff_sigmas`·σ_t (the wider axis) apart are dropped by whole blocks.
    pub fn run_surfels(
        &mut self,
        y: &[P3],
        surfels: &Surfels,
        weights: Option<&[f64]>,
        w: f64,
        out: &mut Posteriors,
    ) -> ResidualSums {
        let (m, n) = (y.len(), self.x.len());
        out.reset(m, n);
        if m == 0 || n == 0 || surfels.normals.len() < m {
            return ResidualSums::default();
        }
        let sigma2 = surfels.equivalent_sigma2();
        let (kt, kd) = exponents(surfels);
        let cutoff = (self.cutoff_sigmas * surfels.tangent_sigma2.sqrt()) as f32;
        let k = Factors { kt, kd, cutoff, c: outlier_constant(sigma2, w, m, n) };
        let mut b = std::mem::take(&mut self.surfel_buf);
        b.load(&self.x, y, surfels, weights);
        let sums = blocked_surfels(self.simd, &mut b, k, out);
        b.store(out);
        self.surfel_buf = b;
        out.np = out.p1.iter().sum();
        out.neg_log_likelihood += n as f64 * 1.5 * sigma2.ln();
        sums
    }
}

fn blocked_surfels(simd: Simd, b: &mut SurfelBuffers, k: Factors, out: &mut Posteriors) -> ResidualSums {
    #[cfg(target_arch = "x86_64")]
    {
        // SAFETY: `simd` comes from `Simd::detect`: the CPU runs what these are compiled for.
        match simd {
            Simd::Avx512 => return unsafe { blocked_surfels_avx512(b, k, out) },
            Simd::Avx2 => return unsafe { blocked_surfels_avx2(b, k, out) },
            Simd::Portable => {}
        }
    }
    let _ = simd;
    blocked_surfels_rows::<false>(b, k, out)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512vl,avx2,fma")]
unsafe fn blocked_surfels_avx512(b: &mut SurfelBuffers, k: Factors, out: &mut Posteriors) -> ResidualSums {
    blocked_surfels_rows::<true>(b, k, out)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn blocked_surfels_avx2(b: &mut SurfelBuffers, k: Factors, out: &mut Posteriors) -> ResidualSums {
    blocked_surfels_rows::<true>(b, k, out)
}

/// The kernel's constants: the exponent factors (`exponents`), the cutoff
/// distance (m) and the outlier term.
#[derive(Clone, Copy)]
struct Factors {
    kt: f32,
    kd: f32,
    cutoff: f32,
    c: f64,
}

/// Data point by data point: the blocks within reach, their affinities
/// w·2^{kt·|r|² + kd·(n·r)²} with the row's sums of affinity, affinity·(n·r)²
/// and affinity·|r|², then the posteriors into the blocks' P1 and PX.
/// Written over fixed-size lanes so that every loop vectorises.
#[inline(always)]
fn blocked_surfels_rows<const FMA: bool>(b: &mut SurfelBuffers, k: Factors, out: &mut Posteriors) -> ResidualSums {
    let SurfelBuffers { blocks, spheres, row, acc, live, x, .. } = b;
    let Factors { kt, kd, cutoff, c } = k;
    let [cx, cy, cz, radius] = &*spheres;
    let reach2: Vec<f32> = radius.iter().map(|r| (cutoff + r) * (cutoff + r)).collect();
    let mut inside = vec![0u32; radius.len()];
    live.resize(radius.len(), 0);
    let mut log_den = LogSum::default();
    let mut sums = ResidualSums::default();
    for (xn, share) in x.iter().zip(out.pt1.iter_mut()) {
        for ((((v, cx), cy), cz), r2) in inside.iter_mut().zip(cx).zip(cy).zip(cz).zip(&reach2) {
            let (dx, dy, dz) = (xn[0] - cx, xn[1] - cy, xn[2] - cz);
            *v = (madd::<FMA>(dx, dx, madd::<FMA>(dy, dy, dz * dz)) <= *r2) as u32;
        }
        // Branch-free compaction of the blocks within reach.
        let mut count = 0;
        for (k, &v) in inside.iter().enumerate() {
            live[count] = k as u32;
            count += v as usize;
        }
        let live = &live[..count];
        let (mut part, mut part_n, mut part_r) = ([0.0f32; BLOCK], [0.0f32; BLOCK], [0.0f32; BLOCK]);
        for &k in live {
            let (bk, rk) = (&blocks[k as usize], &mut row[k as usize]);
            for l in 0..BLOCK {
                let (dx, dy, dz) = (xn[0] - bk.y[0][l], xn[1] - bk.y[1][l], xn[2] - bk.y[2][l]);
                let an = madd::<FMA>(bk.n[0][l], dx, madd::<FMA>(bk.n[1][l], dy, bk.n[2][l] * dz));
                let r2 = madd::<FMA>(dx, dx, madd::<FMA>(dy, dy, dz * dz));
                let an2 = an * an;
                let e = bk.pi[l] * exp2_neg_f32::<FMA>(madd::<FMA>(kd, an2, kt * r2));
                rk[l] = e;
                part[l] += e;
                // The variances' sums leave out the faintest pairs: their
                // affinity times a small squared residual would land among
                // f32's subnormals.
                let g = if e < RESIDUAL_SUMS_FLOOR { 0.0 } else { e };
                part_n[l] = madd::<FMA>(g, an2, part_n[l]);
                part_r[l] = madd::<FMA>(g, r2, part_r[l]);
            }
        }
        let sum = part.iter().map(|&v| v as f64).sum::<f64>();
        let (den, inv) = row_total(sum, c);
        log_den.add(den);
        *share = sum * inv;
        sums.along_normals += inv * part_n.iter().map(|&v| v as f64).sum::<f64>();
        sums.total += inv * part_r.iter().map(|&v| v as f64).sum::<f64>();
        let inv = inv as f32;
        for &k in live {
            let (rk, ak) = (&row[k as usize], &mut acc[k as usize]);
            for l in 0..BLOCK {
                let p = rk[l] * inv;
                ak[0][l] += p;
                ak[1][l] = madd::<FMA>(p, xn[0], ak[1][l]);
                ak[2][l] = madd::<FMA>(p, xn[1], ak[2][l]);
                ak[3][l] = madd::<FMA>(p, xn[2], ak[3][l]);
            }
        }
    }
    out.neg_log_likelihood -= log_den.total();
    sums
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    /// The textbook surfel E-step in f64, every pair.
    fn reference(x: &[P3], y: &[P3], s: &Surfels, pi: &[f64], w: f64) -> (Posteriors, ResidualSums) {
        let (m, n) = (y.len(), x.len());
        let c = outlier_constant(s.equivalent_sigma2(), w, m, n);
        let mut out = Posteriors { p1: vec![0.0; m], pt1: vec![0.0; n], px: vec![[0.0; 3]; m], ..Default::default() };
        let mut sums = ResidualSums::default();
        for (j, xn) in x.iter().enumerate() {
            let r: Vec<[f64; 3]> = y.iter().map(|yi| [xn[0] - yi[0], xn[1] - yi[1], xn[2] - yi[2]]).collect();
            let an: Vec<f64> = (0..m).map(|i| super::super::dot(&s.normals[i], &r[i])).collect();
            let r2: Vec<f64> = r.iter().map(|v| super::super::dot(v, v)).collect();
            let e: Vec<f64> = (0..m)
                .map(|i| {
                    let along = an[i] * an[i];
                    pi[i] * (-(r2[i] - along) / (2.0 * s.tangent_sigma2) - along / (2.0 * s.normal_sigma2)).exp()
                })
                .collect();
            let den: f64 = e.iter().sum::<f64>() + c;
            out.neg_log_likelihood -= den.ln();
            for i in 0..m {
                let p = e[i] / den;
                out.p1[i] += p;
                out.pt1[j] += p;
                for d in 0..3 {
                    out.px[i][d] += p * xn[d];
                }
                sums.along_normals += p * an[i] * an[i];
                sums.total += p * r2[i];
            }
        }
        out.np = out.p1.iter().sum();
        out.neg_log_likelihood += n as f64 * 1.5 * s.equivalent_sigma2().ln();
        (out, sums)
    }

    /// Points on a wavy sheet (the data) and a sparser, shifted copy with normals (the model).
    fn sheet(n: usize, seed: u64, shift: f64) -> (Vec<P3>, Vec<P3>) {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let (mut p, mut nrm) = (Vec::new(), Vec::new());
        for _ in 0..n {
            let (u, v): (f64, f64) = (rng.random_range(-0.1..0.1), rng.random_range(-0.1..0.1));
            p.push([u, v, 0.01 * (20.0 * u).sin() + shift + rng.random_range(-0.001..0.001)]);
            let g = 0.2 * (20.0 * u).cos();
            let l = (1.0 + g * g).sqrt();
            nrm.push([-g / l, 0.0, 1.0 / l]);
        }
        (p, nrm)
    }

    /// `cutoff_sigmas` 6 drops pairs beyond 36 mm by whole blocks (most of
    /// them on a 20 cm sheet), 100 none; both must give the textbook sums.
    fn check(simd: Simd, cutoff_sigmas: f64) {
        let (x, _) = sheet(300, 1, 0.0);
        let (y, normals) = sheet(101, 2, 0.002);
        let pi: Vec<f64> = (0..y.len()).map(|i| if i % 7 == 0 { 0.2 } else { 1.1 }).collect();
        let s = Surfels { normals: &normals, tangent_sigma2: 0.006f64.powi(2), normal_sigma2: 0.0015f64.powi(2) };
        let mut e = EStep::new(&x);
        e.simd = simd;
        e.cutoff_sigmas = cutoff_sigmas;
        let mut out = Posteriors::default();
        let sums = e.run_surfels(&y, &s, Some(&pi), 0.1, &mut out);
        let (want, want_sums) = reference(&x, &y, &s, &pi, 0.1);
        let nll = want.neg_log_likelihood;
        assert!((out.neg_log_likelihood - nll).abs() < 1e-5 * nll.abs(), "{} vs {nll}", out.neg_log_likelihood);
        assert!((out.np - want.np).abs() < 1e-4 * want.np);
        for i in 0..y.len() {
            assert!((out.p1[i] - want.p1[i]).abs() < 1e-4 + 1e-3 * want.p1[i], "p1[{i}]");
            for d in 0..3 {
                assert!((out.px[i][d] - want.px[i][d]).abs() < 1e-5 + 1e-3 * want.px[i][d].abs(), "px[{i}]");
            }
        }
        for j in 0..x.len() {
            assert!((out.pt1[j] - want.pt1[j]).abs() < 1e-4, "pt1[{j}]");
        }
        for (got, exp) in [(sums.along_normals, want_sums.along_normals), (sums.total, want_sums.total)] {
            assert!((got - exp).abs() < 1e-3 * exp, "residual sums {sums:?} vs {want_sums:?}");
        }
        // The variances these give: σ_n below σ_t on a sheet seen nearly flat.
        let (t2, n2) = sums.variances(out.np);
        assert!(n2 < t2, "σ_t² {t2}, σ_n² {n2}");
    }

    #[test]
    fn surfel_sums_match_the_textbook_e_step_on_every_kernel_with_and_without_skipped_blocks() {
        for simd in Simd::available() {
            check(simd, 100.0);
            check(simd, 6.0);
        }
    }

    #[test]
    fn round_surfels_are_the_isotropic_mixture() {
        let (x, _) = sheet(200, 3, 0.0);
        let (y, normals) = sheet(64, 4, 0.001);
        let s = Surfels { normals: &normals, tangent_sigma2: 4e-6, normal_sigma2: 4e-6 };
        let mut e = EStep::new(&x);
        e.single_precision = true;
        let (mut a, mut b) = (Posteriors::default(), Posteriors::default());
        e.run_surfels(&y, &s, None, 0.1, &mut a);
        e.run_weighted(&y, None, 4e-6, 0.1, &mut b);
        assert!((a.neg_log_likelihood - b.neg_log_likelihood).abs() < 1e-4 * b.neg_log_likelihood.abs());
        for i in 0..y.len() {
            assert!((a.p1[i] - b.p1[i]).abs() < 1e-4, "p1[{i}]");
        }
    }
}
