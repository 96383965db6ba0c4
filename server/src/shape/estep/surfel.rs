//! The E-step of a mixture whose components are surface elements (surfels):
//! each moving point carries a unit normal, and its Gaussian has variance
//! σ_n² along the normal and σ_t² across it. Its blocked kernels also run
//! the isotropic mixture's truncated E-step (round surfels, `EStep::blocked`).
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

/// Moving points a block: one AVX2 vector, half an AVX-512 one (whose
/// vectors hold a block against two data points). Blocks of 16 were twice
/// as wide (mean bounding radius 15 against 10.5 mm on the mug's polish
/// level), and a block is evaluated wherever its sphere comes within the
/// cutoff of a group's: with 8, the polish's vectors a mug E-step fall by
/// about a quarter (drill 29 %, hammer 17 %), at twice the block loads and
/// sum updates a vector. Measured against 16, the builds run in turn:
/// `bench_estep` surfels 800 × 800, median of six runs' fastest, AVX-512
/// 87.5 → 76.5 µs, AVX2 171.4 → 162.3, portable 362.5 → 319.6;
/// `VIEWPOINT=known bench_register`, median of 30 runs' mean of each view's
/// fastest fit, mug 6.18 → 5.81 ms, drill 5.12 → 4.93, hammer 5.17 → 5.17
/// (10 runs: AVX2 mug 8.96 → 8.14, portable 14.95 → 13.76); keypoints
/// within 0.01 mm (`eval transfer --views 12`, seeds 7 / 11 / 23).
const BLOCK: usize = 8;
type Lanes = [f32; BLOCK];
/// A block's lanes twice over: its points (`Block`), and its posterior sums,
/// into whose halves the AVX-512 and portable kernels add their two data
/// points' shares (the AVX2 kernel into the first); `store` adds the halves.
type Wide = [f32; 2 * BLOCK];

/// Data points a group: near one another (a leaf of `spatial_order`), they
/// share one test of which blocks are in reach, and the kernels load each
/// block once for the group and update its sums once.
const GROUP: usize = 4;

/// One block of moving points, structure of arrays, each lane held twice
/// (on both halves of a `Wide`): the AVX-512 and portable kernels set a
/// block against two data points at once and read it whole, the AVX2 kernel
/// reads the first half. Stored twice rather than broadcast at each use:
/// measured (`bench_estep`, surfels 800 × 800, fastest of six runs) AVX-512
/// 84.4 → 75.5 µs, portable 368.8 → 317.2 µs, AVX2 the same.
#[derive(Clone, Copy, Default)]
struct Block {
    y: [Wide; 3],
    n: [Wide; 3],
    pi: Wide,
}

/// The moving points of a surfel E-step in blocks of nearby points, each
/// with a bounding sphere, and the data points in groups of nearby points,
/// each with one too: a group skips the blocks whose sphere lies beyond the
/// cutoff from its own (a neighbour list without the list: on a 2,000-point
/// view most blocks are far from most data points, and a block is one
/// vector of work or none).
#[derive(Clone, Default)]
pub(super) struct SurfelBuffers {
    /// Moving point of each block slot (the spatial order, made at the first
    /// call of a fit: the model moves little within one); `usize::MAX` pads.
    order: Vec<usize>,
    /// How many moving points `order` orders (its slots less the padding).
    ordered: usize,
    blocks: Vec<Block>,
    /// Bounding spheres of the blocks as columns (centre x, y, z and
    /// radius), for the kernel's vector test of which blocks a group reaches.
    spheres: [Vec<f32>; 4],
    /// The affinities of a group's rows, block k's at k·GROUP.. (two rows
    /// make one sixteen-lane vector of the AVX-512 and portable kernels).
    row: Vec<Lanes>,
    /// Per block: the P1 and PX sums.
    acc: Vec<[Wide; 4]>,
    live: Vec<u32>,
    /// The data points in `spatial_order`, their indices in the caller's
    /// order, and the bounding sphere (centre, radius) of each group of
    /// `GROUP` consecutive ones; made once per `EStep` (its data are fixed).
    x: Vec<[f32; 3]>,
    x_index: Vec<usize>,
    groups: Vec<[f32; 4]>,
    /// Per group: its radius plus the E-step's cutoff, the reach its
    /// blocks' spheres are tested against.
    reach: Vec<f32>,
}

impl SurfelBuffers {
    /// The data (once), the moving points, their normals (none for round
    /// components, which never read them) and their weights.
    fn load(&mut self, x: &[P3], y: &[P3], normals: Option<&[P3]>, weights: Option<&[f64]>) {
        self.load_data(x);
        let m = y.len();
        if self.ordered != m {
            self.order = model_order(y);
            self.ordered = m;
        }
        let nb = self.order.len() / BLOCK;
        self.blocks.resize(nb, Block::default());
        self.spheres.iter_mut().for_each(|c| c.clear());
        for (block, slots) in self.blocks.iter_mut().zip(self.order.chunks_exact(BLOCK)) {
            // Padding repeats the block's first point with no weight.
            let k: [usize; BLOCK] = std::array::from_fn(|l| if slots[l] == usize::MAX { slots[0] } else { slots[l] });
            for l in 0..BLOCK {
                let w = match (slots[l], weights) {
                    (usize::MAX, _) => 0.0,
                    (_, Some(w)) => w[k[l]],
                    (_, None) => 1.0,
                };
                block.pi[l] = w as f32;
            }
            for d in 0..3 {
                for l in 0..BLOCK {
                    block.y[d][l] = y[k[l]][d] as f32;
                }
            }
            if let Some(n) = normals {
                for d in 0..3 {
                    for l in 0..BLOCK {
                        let v = n[k[l]][d];
                        block.n[d][l] = if v.abs() < NORMAL_FLUSH { 0.0 } else { v as f32 };
                    }
                }
            }
            for lanes in block.y.iter_mut().chain(block.n.iter_mut()).chain([&mut block.pi]) {
                lanes.copy_within(..BLOCK, BLOCK);
            }
            for (col, v) in self.spheres.iter_mut().zip(block_sphere(&block.y)) {
                col.push(v);
            }
        }
        self.row.resize(nb * GROUP, [0.0; BLOCK]);
        self.acc.clear();
        self.acc.resize(nb, [[0.0; 2 * BLOCK]; 4]);
        // Whole vectors (of 16) of block indices are stored past the live ones.
        self.live.resize(nb.next_multiple_of(16) + 16, 0);
    }

    /// The data in groups of nearby points (once: the data are fixed).
    pub(super) fn load_data(&mut self, x: &[P3]) {
        if self.x_index.len() != x.len() {
            self.x_index = spatial_order(x, GROUP);
            self.x = self.x_index.iter().map(|&i| x[i].map(|v| v as f32)).collect();
            self.groups = self.x_index.chunks(GROUP).map(|g| bounding_sphere(g.iter().map(|&i| &x[i]))).collect();
        }
    }

    /// Takes `order` (from [`model_order`]) for the moving points of the
    /// calls to come, when it orders `m` of them.
    pub(super) fn use_model_order(&mut self, order: &[usize], m: usize) {
        if order.len() == m.div_ceil(BLOCK) * BLOCK && order.iter().filter(|&&i| i != usize::MAX).count() == m {
            self.order.clear();
            self.order.extend_from_slice(order);
            self.ordered = m;
        }
    }

    fn store(&self, out: &mut Posteriors) {
        for (slots, a) in self.order.chunks_exact(BLOCK).zip(&self.acc) {
            for (l, &i) in slots.iter().enumerate() {
                if i != usize::MAX {
                    let sum = |c: &Wide| (c[l] + c[l + BLOCK]) as f64;
                    out.p1[i] = sum(&a[0]);
                    out.px[i] = [sum(&a[1]), sum(&a[2]), sum(&a[3])];
                }
            }
        }
    }
}

/// The order the blocked kernels put moving points in: blocks of `BLOCK`
/// nearby points (padded with `usize::MAX`). A fit's model keeps its
/// neighbourhoods as it moves (a similarity, and the latent's smooth
/// deformation), so an order made once on a model level's rest shape
/// serves all its fits (`EStep::use_model_order`): ordering the moving
/// points at each fit's first E-step took about 4 % of a mug's registration.
pub fn model_order(points: &[P3]) -> Vec<usize> {
    let mut order = spatial_order(points, BLOCK);
    compact_blocks(points, &mut order, BLOCK);
    order.resize(points.len().div_ceil(BLOCK) * BLOCK, usize::MAX);
    order
}

/// Swaps points between neighbouring blocks while a swap brings both nearer
/// their blocks' centroids (balanced k-means: the blocks keep their sizes).
fn compact_blocks(p: &[P3], order: &mut [usize], block: usize) {
    const PASSES: usize = 50;
    for _ in 0..PASSES {
        let spheres: Vec<([f64; 3], f64)> =
            order.chunks(block).map(|b| centroid_and_radius(b.iter().map(|&i| &p[i]))).collect();
        let mut swapped = false;
        for a in 0..spheres.len() {
            for b in a + 1..spheres.len() {
                let ((ca, ra), (cb, rb)) = (&spheres[a], &spheres[b]);
                if dist2(ca, cb).sqrt() > ra + rb {
                    continue;
                }
                let (lo, hi) = order.split_at_mut(b * block);
                let len_b = block.min(hi.len());
                let (ba, bb) = (&mut lo[a * block..(a + 1) * block], &mut hi[..len_b]);
                for ia in ba.iter_mut() {
                    for ib in bb.iter_mut() {
                        let (i, j) = (*ia, *ib);
                        let gain = dist2(&p[i], ca) + dist2(&p[j], cb) - dist2(&p[i], cb) - dist2(&p[j], ca);
                        if gain > 1e-12 {
                            (*ia, *ib) = (j, i);
                            swapped = true;
                        }
                    }
                }
            }
        }
        if !swapped {
            break;
        }
    }
}

/// The centroid of a block's points and their largest distance from it (a
/// padding lane repeats the first point, as `bounding_sphere` counts it),
/// in single precision from the lanes the kernels read: a sphere is made
/// for every block at every E-step, and in double precision from the
/// points these took 3 % of a mug's registration. The radius is rounded
/// up by a part in 10⁵, far above f32's rounding here, so that no point
/// the kernels read lies outside its block's sphere.
fn block_sphere(y: &[Wide; 3]) -> [f32; 4] {
    // Halved pairwise, each step lane by lane (a vector's work).
    #[inline(always)]
    fn fold(v: [f32; BLOCK], op: impl Fn(f32, f32) -> f32) -> f32 {
        let v: [f32; 4] = std::array::from_fn(|i| op(v[i], v[i + 4]));
        let v: [f32; 2] = std::array::from_fn(|i| op(v[i], v[i + 2]));
        op(v[0], v[1])
    }
    let c = [0, 1, 2].map(|d| fold(std::array::from_fn(|l| y[d][l]), |a, b| a + b) / BLOCK as f32);
    let r2: [f32; BLOCK] = std::array::from_fn(|l| {
        let (dx, dy, dz) = (y[0][l] - c[0], y[1][l] - c[1], y[2][l] - c[2]);
        dx * dx + dy * dy + dz * dz
    });
    // A plain select, not f32::max, whose NaN rules stay scalar.
    [c[0], c[1], c[2], fold(r2, |a, b| if a > b { a } else { b }).sqrt() * (1.0 + 1e-5)]
}

/// The centroid of some points and their largest distance from it.
fn bounding_sphere<'p>(points: impl Iterator<Item = &'p P3> + Clone) -> [f32; 4] {
    let (c, r) = centroid_and_radius(points);
    [c[0] as f32, c[1] as f32, c[2] as f32, r as f32]
}

/// [`bounding_sphere`] in double precision.
fn centroid_and_radius<'p>(points: impl Iterator<Item = &'p P3> + Clone) -> ([f64; 3], f64) {
    let (mut c, mut k) = ([0.0f64; 3], 0.0);
    for p in points.clone() {
        (0..3).for_each(|d| c[d] += p[d]);
        k += 1.0;
    }
    c = c.map(|v| v / f64::max(k, 1.0));
    let r2 = points.map(|p| dist2(p, &c)).fold(0.0, f64::max);
    (c, r2.sqrt())
}

/// The points' indices in leaves of `leaf` nearby points: a k-d split,
/// each cut across the widest extent at a multiple of `leaf` near the
/// middle, so that every leaf but the last is whole. (A Morton order cut
/// into runs of `leaf` left some runs spanning the curve's jumps: their
/// spheres reached over most of a mug.)
fn spatial_order(p: &[P3], leaf: usize) -> Vec<usize> {
    /// Each cut selects on (coordinate, index) pairs copied out of the
    /// points: the comparisons read neighbouring memory instead of following
    /// an index into the points. The pairs compare exactly as the indices
    /// did, so the order is the same. Measured (`bench_register mug` with a
    /// timer here): 36-39 → 31-32 µs an order, about twenty orders a fit.
    /// Each pair is one integer, the coordinate's bits made to sort as
    /// `f64::total_cmp` above the index: compared without a closure's
    /// branches, in the same order (so the same selection).
    fn split(p: &[P3], idx: &mut [usize], leaf: usize, keyed: &mut Vec<u128>) {
        if idx.len() <= leaf {
            return;
        }
        let (mut lo, mut hi) = ([f64::INFINITY; 3], [f64::NEG_INFINITY; 3]);
        for &i in idx.iter() {
            for d in 0..3 {
                lo[d] = lo[d].min(p[i][d]);
                hi[d] = hi[d].max(p[i][d]);
            }
        }
        let axis = (0..3).max_by(|&a, &b| (hi[a] - lo[a]).total_cmp(&(hi[b] - lo[b]))).unwrap_or(0);
        let cut = (idx.len().div_ceil(leaf) / 2).max(1) * leaf;
        keyed.clear();
        keyed.extend(idx.iter().map(|&i| (u128::from(total_order_bits(p[i][axis])) << 64) | i as u128));
        keyed.select_nth_unstable(cut);
        for (i, k) in idx.iter_mut().zip(keyed.iter()) {
            *i = *k as u64 as usize;
        }
        let (left, right) = idx.split_at_mut(cut);
        split(p, left, leaf, keyed);
        split(p, right, leaf, keyed);
    }
    let mut order: Vec<usize> = (0..p.len()).collect();
    split(p, &mut order, leaf.max(1), &mut Vec::with_capacity(p.len()));
    order
}

/// The bits of `v` as an integer that orders as `f64::total_cmp` does.
fn total_order_bits(v: f64) -> u64 {
    let b = v.to_bits();
    if b >> 63 == 1 {
        !b
    } else {
        b | 1 << 63
    }
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
        if surfels.normals.len() < y.len() {
            out.reset(y.len(), self.x.len());
            return ResidualSums::default();
        }
        let (kt, kd) = exponents(surfels);
        let cutoff = self.cutoff_sigmas * surfels.tangent_sigma2.sqrt();
        self.run_blocked::<false, true>(
            y,
            Some(surfels.normals),
            (kt, kd),
            surfels.equivalent_sigma2(),
            cutoff,
            weights,
            w,
            out,
        )
    }

    /// The isotropic E-step (`run_weighted`'s sums) by the same blocks:
    /// round surfels, whose kernel leaves out the normals and the residual
    /// sums. Pairs beyond `cutoff_sigmas`·σ are dropped by whole blocks.
    pub(super) fn run_round(&mut self, y: &[P3], weights: Option<&[f64]>, sigma2: f64, w: f64, out: &mut Posteriors) {
        let cutoff = self.cutoff_sigmas * sigma2.sqrt();
        self.run_blocked::<true, true>(y, None, (exponent_f32(sigma2), 0.0), sigma2, cutoff, weights, w, out);
    }

    /// [`Self::run_round`]'s negative log-likelihood alone: the kernels
    /// close each data point's row and skip the posterior sums (their
    /// stores and second pass over the blocks), the same likelihood to the
    /// bit. Scoring poses (the race's survivors, the yaw sweep) needs no more.
    pub(super) fn round_likelihood(&mut self, y: &[P3], weights: Option<&[f64]>, sigma2: f64, w: f64) -> f64 {
        let cutoff = self.cutoff_sigmas * sigma2.sqrt();
        let mut out = std::mem::take(&mut self.scratch);
        self.run_blocked::<true, false>(y, None, (exponent_f32(sigma2), 0.0), sigma2, cutoff, weights, w, &mut out);
        let nll = out.neg_log_likelihood;
        self.scratch = out;
        nll
    }

    /// The blocked E-step with exponent factors `kt`, `kd` (see `exponents`)
    /// and the isotropic variance of the same normalising constant; without
    /// `STATS`, only the likelihood and Pᵀ1 (`out`'s P1 and PX stay 0).
    #[allow(clippy::too_many_arguments)]
    fn run_blocked<const ROUND: bool, const STATS: bool>(
        &mut self,
        y: &[P3],
        normals: Option<&[P3]>,
        (kt, kd): (f32, f32),
        sigma2: f64,
        cutoff: f64,
        weights: Option<&[f64]>,
        w: f64,
        out: &mut Posteriors,
    ) -> ResidualSums {
        let (m, n) = (y.len(), self.x.len());
        out.reset(m, n);
        if m == 0 || n == 0 {
            return ResidualSums::default();
        }
        let k = Factors { kt, kd, c: outlier_constant(sigma2, w, m, n) };
        let mut b = std::mem::take(&mut self.surfel_buf);
        b.load(&self.x, y, normals, weights);
        // Added here, in plain code: inside the AVX-512 kernel LLVM added
        // this scalar with a packed instruction whose other lanes held
        // whatever the register did, sometimes subnormal numbers (a
        // microcode assist on Intel, and `a_registration_computes_no_subnormal_numbers` failed).
        b.reach.clear();
        b.reach.extend(b.groups.iter().map(|g| g[3] + cutoff as f32));
        let mut rows = Rows { pt1: &mut out.pt1, log_den: LogSum::default(), sums: ResidualSums::default(), c: k.c };
        blocked_surfels::<ROUND, STATS>(self.simd, &mut b, k, &mut rows);
        let (log_den, sums) = (rows.log_den, rows.sums);
        if STATS {
            b.store(out);
        }
        self.surfel_buf = b;
        out.np = out.p1.iter().sum();
        out.neg_log_likelihood = n as f64 * 1.5 * sigma2.ln() - log_den.total();
        sums
    }
}

/// The blocked kernels; `ROUND`: isotropic components (no normals, no
/// residual sums); `STATS`: the posterior sums P1 and PX too (else only
/// each row's total, closed into `rows`).
fn blocked_surfels<const ROUND: bool, const STATS: bool>(
    simd: Simd,
    b: &mut SurfelBuffers,
    k: Factors,
    rows: &mut Rows,
) {
    #[cfg(target_arch = "x86_64")]
    {
        // SAFETY: `simd` comes from `Simd::detect`: the CPU runs what these are compiled for.
        match simd {
            Simd::Avx512 => return unsafe { avx512::blocked_surfels::<ROUND, STATS>(b, k, rows) },
            Simd::Avx2 => return unsafe { avx2::blocked_surfels::<ROUND, STATS>(b, k, rows) },
            Simd::Portable => {}
        }
    }
    let _ = simd;
    blocked_surfels_rows::<ROUND, STATS>(b, k, rows)
}

/// The kernel's constants: the exponent factors (`exponents`) and the outlier term.
#[derive(Clone, Copy)]
struct Factors {
    kt: f32,
    kd: f32,
    c: f64,
}

/// What the kernels add up over the data points besides P1 and PX.
struct Rows<'a> {
    /// Pᵀ1, in the caller's order of the data points.
    pt1: &'a mut [f64],
    log_den: LogSum,
    sums: ResidualSums,
    /// The outlier term.
    c: f64,
}

impl Rows<'_> {
    /// Closes data point `j`'s row from its sums of affinity, affinity·(n·r)²
    /// and affinity·|r|²; returns the inverse of its total (with the outlier term).
    #[inline(always)]
    fn close(&mut self, j: usize, [sum, along, total]: [f64; 3]) -> f64 {
        let (den, inv) = row_total(sum, self.c);
        self.log_den.add(den);
        self.pt1[j] = sum * inv;
        self.sums.along_normals += inv * along;
        self.sums.total += inv * total;
        inv
    }
}

/// A group's data points, `GROUP` of them: a last group of fewer repeats
/// its last point in the missing rows, which the kernels do not close and
/// which add nothing to the sums.
#[inline(always)]
fn whole_group(xg: &[[f32; 3]]) -> [[f32; 3]; GROUP] {
    let mut xs = [xg[xg.len() - 1]; GROUP];
    xs[..xg.len()].copy_from_slice(xg);
    xs
}

/// The blocks whose sphere lies within `reach` of group `g`'s centre
/// (`SurfelBuffers::reach`), as indices at the start of `live`; returns how many.
#[inline(always)]
fn live_blocks<const FMA: bool>(spheres: &[Vec<f32>; 4], g: &[f32; 4], reach: f32, live: &mut [u32]) -> usize {
    let [cx, cy, cz, radius] = spheres;
    let mut count = 0;
    // Branch-free compaction.
    for (k, (((cx, cy), cz), r)) in cx.iter().zip(cy).zip(cz).zip(radius).enumerate() {
        let (dx, dy, dz) = (g[0] - cx, g[1] - cy, g[2] - cz);
        let r = reach + r;
        live[count] = k as u32;
        count += (madd::<FMA>(dx, dx, madd::<FMA>(dy, dy, dz * dz)) <= r * r) as usize;
    }
    count
}

/// The portable kernel (unfused, for CPUs with neither AVX2 nor AVX-512):
/// two data points at a time (the blocks within reach tested once a group),
/// on sixteen lanes: a block's eight points on each half, as the AVX-512
/// kernel lays them out (over eight lanes LLVM unrolled the loops whole and
/// left them scalar: compiled for AVX2, 3-4 times slower than blocks of 16). The affinities
/// w·2^{kt·|r|² + kd·(n·r)²} with the rows' sums of affinity,
/// affinity·(n·r)² and affinity·|r|², then the posteriors into the blocks'
/// P1 and PX. Written over fixed-size lanes so that every loop vectorises.
#[inline(always)]
fn blocked_surfels_rows<const ROUND: bool, const STATS: bool>(b: &mut SurfelBuffers, k: Factors, rows: &mut Rows) {
    const W: usize = 2 * BLOCK;
    const PAIRS: usize = GROUP / 2;
    let SurfelBuffers { blocks, spheres, row, acc, live, x, x_index, groups, reach, .. } = b;
    let Factors { kt, kd, .. } = k;
    for ((xg, jg), (g, &reach)) in x.chunks(GROUP).zip(x_index.chunks(GROUP)).zip(groups.iter().zip(reach.iter())) {
        let count = live_blocks::<false>(spheres, g, reach, live);
        let live = &live[..count];
        let xs = whole_group(xg);
        // Pair q's coordinates: point 2q on the lower half, 2q + 1 on the upper.
        let xw: [[Wide; 3]; PAIRS] =
            std::array::from_fn(|q| std::array::from_fn(|d| std::array::from_fn(|l| xs[2 * q + l / BLOCK][d])));
        let mut part = [[[0.0f32; W]; 3]; PAIRS];
        for &k in live {
            let bk = &blocks[k as usize];
            let (y, n, pi) = (&bk.y, &bk.n, &bk.pi);
            let rk = row[k as usize * GROUP..(k as usize + 1) * GROUP].as_flattened_mut();
            for (q, (out, [ps, pn, pr])) in rk.chunks_exact_mut(W).zip(part.iter_mut()).enumerate() {
                let xq = &xw[q];
                for l in 0..W {
                    let (dx, dy, dz) = (xq[0][l] - y[0][l], xq[1][l] - y[1][l], xq[2][l] - y[2][l]);
                    let r2 = madd::<false>(dx, dx, madd::<false>(dy, dy, dz * dz));
                    if ROUND {
                        let e = pi[l] * exp2_neg_f32::<false>(kt * r2);
                        if STATS {
                            out[l] = e;
                        }
                        ps[l] += e;
                        continue;
                    }
                    let an = madd::<false>(n[0][l], dx, madd::<false>(n[1][l], dy, n[2][l] * dz));
                    let an2 = an * an;
                    let e = pi[l] * exp2_neg_f32::<false>(madd::<false>(kd, an2, kt * r2));
                    out[l] = e;
                    ps[l] += e;
                    // The variances' sums leave out the faintest pairs: their
                    // affinity times a small squared residual would land among
                    // f32's subnormals.
                    let g = if e < RESIDUAL_SUMS_FLOOR { 0.0 } else { e };
                    pn[l] = madd::<false>(g, an2, pn[l]);
                    pr[l] = madd::<false>(g, r2, pr[l]);
                }
            }
        }
        // Each row's inverse total on its half; 0 for the rows a last group lacks.
        let mut inv = [[0.0f32; W]; PAIRS];
        for (q, (sums, inv)) in part.iter().zip(inv.iter_mut()).enumerate() {
            for h in 0..2 {
                let Some(&j) = jg.get(2 * q + h) else { continue };
                let half = |v: &Wide| v[h * BLOCK..(h + 1) * BLOCK].iter().map(|&v| v as f64).sum::<f64>();
                let i = rows.close(j, [half(&sums[0]), half(&sums[1]), half(&sums[2])]) as f32;
                inv[h * BLOCK..(h + 1) * BLOCK].fill(i);
            }
        }
        for &k in live.iter().filter(|_| STATS) {
            let rk = row[k as usize * GROUP..(k as usize + 1) * GROUP].as_flattened();
            let ak = &mut acc[k as usize];
            for (q, e) in rk.chunks_exact(W).enumerate() {
                for l in 0..W {
                    let p = e[l] * inv[q][l];
                    ak[0][l] += p;
                    ak[1][l] = madd::<false>(p, xw[q][0][l], ak[1][l]);
                    ak[2][l] = madd::<false>(p, xw[q][1][l], ak[2][l]);
                    ak[3][l] = madd::<false>(p, xw[q][2][l], ak[3][l]);
                }
            }
        }
    }
}

/// The same sums in AVX2 intrinsics, a block to a vector, a group's four
/// rows at a time: each block's points, normals and sums are loaded once for
/// the four. By hand because over eight lanes LLVM unrolled the portable
/// kernel's loops whole and left them scalar (the AVX2 path 3-4 times
/// slower than with blocks of 16).
#[cfg(target_arch = "x86_64")]
mod avx2 {
    use super::super::exp2_neg_f32x8;
    use super::{whole_group, Factors, Rows, SurfelBuffers, BLOCK, GROUP, RESIDUAL_SUMS_FLOOR};
    use std::arch::x86_64::*;

    const _: () = assert!(BLOCK == 8);

    /// # Safety
    /// The CPU must have AVX2 and FMA.
    #[target_feature(enable = "avx2,fma")]
    pub(super) unsafe fn blocked_surfels<const ROUND: bool, const STATS: bool>(
        b: &mut SurfelBuffers,
        k: Factors,
        rows: &mut Rows,
    ) {
        let SurfelBuffers { blocks, spheres, row, acc, live, x, x_index, groups, reach, .. } = b;
        let nb = blocks.len();
        assert!(row.len() >= nb * GROUP && acc.len() == nb && live.len() >= nb);
        assert!(spheres.iter().all(|c| c.len() == nb) && x.len() == x_index.len() && reach.len() == groups.len());
        let f =
            Consts { kt: _mm256_set1_ps(k.kt), kd: _mm256_set1_ps(k.kd), floor: _mm256_set1_ps(RESIDUAL_SUMS_FLOOR) };
        for (((xg, jg), g), &r) in x.chunks(GROUP).zip(x_index.chunks(GROUP)).zip(groups.iter()).zip(reach.iter()) {
            let count = super::live_blocks::<true>(spheres, g, r, live);
            let xs = whole_group(xg);
            // SAFETY: `live` holds block indices below nb; the buffers' lengths are asserted above.
            unsafe { group::<ROUND, STATS>(blocks, row, acc, &live[..count], &xs, jg, &f, rows) };
        }
    }

    struct Consts {
        kt: __m256,
        kd: __m256,
        floor: __m256,
    }

    /// A vector's lanes summed in double precision, in lane order (as the portable kernel).
    #[target_feature(enable = "avx2")]
    fn lane_sum_f64(v: __m256) -> f64 {
        let mut l = [0.0f32; BLOCK];
        // SAFETY: `l` holds eight lanes.
        unsafe { _mm256_storeu_ps(l.as_mut_ptr(), v) };
        l.iter().map(|&v| v as f64).sum()
    }

    /// The rows of the group's data points `xs` (the caller's indices `js`,
    /// fewer than `GROUP` in a last group) over the blocks `live`.
    ///
    /// # Safety
    /// `live` holds indices of `blocks`, `acc` is as long as `blocks` and `row` GROUP times longer.
    #[target_feature(enable = "avx2,fma")]
    #[allow(clippy::too_many_arguments)]
    unsafe fn group<const ROUND: bool, const STATS: bool>(
        blocks: &[super::Block],
        row: &mut [super::Lanes],
        acc: &mut [[super::Wide; 4]],
        live: &[u32],
        xs: &[[f32; 3]; GROUP],
        js: &[usize],
        f: &Consts,
        rows: &mut Rows,
    ) {
        let zero = _mm256_setzero_ps();
        let mut xv = [[zero; 3]; GROUP];
        for b in 0..GROUP {
            for i in 0..3 {
                xv[b][i] = _mm256_set1_ps(xs[b][i]);
            }
        }
        let mut part = [[zero; 3]; GROUP];
        let row = row.as_mut_ptr();
        for &k in live {
            let k = k as usize;
            // SAFETY: k < blocks.len() (the caller's contract).
            let bk = unsafe { blocks.get_unchecked(k) };
            let (mut y, mut n) = ([zero; 3], [zero; 3]);
            for i in 0..3 {
                // SAFETY: each column holds sixteen lanes; this reads the first eight.
                y[i] = unsafe { _mm256_loadu_ps(bk.y[i].as_ptr()) };
                if !ROUND {
                    // SAFETY: as above.
                    n[i] = unsafe { _mm256_loadu_ps(bk.n[i].as_ptr()) };
                }
            }
            // SAFETY: as above.
            let pi = unsafe { _mm256_loadu_ps(bk.pi.as_ptr()) };
            for b in 0..GROUP {
                let d = [_mm256_sub_ps(xv[b][0], y[0]), _mm256_sub_ps(xv[b][1], y[1]), _mm256_sub_ps(xv[b][2], y[2])];
                let r2 = _mm256_fmadd_ps(d[0], d[0], _mm256_fmadd_ps(d[1], d[1], _mm256_mul_ps(d[2], d[2])));
                // SAFETY: k·GROUP + b < row.len().
                let out = unsafe { row.add(k * GROUP + b).cast::<f32>() };
                if ROUND {
                    // SAFETY: the CPU has AVX2 and FMA (this function's features).
                    let e = _mm256_mul_ps(pi, unsafe { exp2_neg_f32x8(_mm256_mul_ps(f.kt, r2)) });
                    if STATS {
                        // SAFETY: as above.
                        unsafe { _mm256_storeu_ps(out, e) };
                    }
                    part[b][0] = _mm256_add_ps(part[b][0], e);
                    continue;
                }
                let an = _mm256_fmadd_ps(n[0], d[0], _mm256_fmadd_ps(n[1], d[1], _mm256_mul_ps(n[2], d[2])));
                let an2 = _mm256_mul_ps(an, an);
                let t = _mm256_fmadd_ps(f.kd, an2, _mm256_mul_ps(f.kt, r2));
                // SAFETY: as above.
                let e = _mm256_mul_ps(pi, unsafe { exp2_neg_f32x8(t) });
                // SAFETY: as above.
                unsafe { _mm256_storeu_ps(out, e) };
                part[b][0] = _mm256_add_ps(part[b][0], e);
                // As the portable kernel: the faintest pairs stay out of the variances' sums.
                let g = _mm256_and_ps(_mm256_cmp_ps::<_CMP_GE_OQ>(e, f.floor), e);
                part[b][1] = _mm256_fmadd_ps(g, an2, part[b][1]);
                part[b][2] = _mm256_fmadd_ps(g, r2, part[b][2]);
            }
        }
        let mut inv = [zero; GROUP];
        for (b, &j) in js.iter().enumerate() {
            let sums = [lane_sum_f64(part[b][0]), lane_sum_f64(part[b][1]), lane_sum_f64(part[b][2])];
            inv[b] = _mm256_set1_ps(rows.close(j, sums) as f32);
        }
        if !STATS {
            return;
        }
        for &k in live {
            let k = k as usize;
            // SAFETY: k < acc.len().
            let ak = unsafe { acc.get_unchecked_mut(k) };
            let mut a = [zero; 4];
            for (v, c) in a.iter_mut().zip(ak.iter()) {
                // SAFETY: each sum holds sixteen lanes; these sums live on the first eight.
                *v = unsafe { _mm256_loadu_ps(c.as_ptr()) };
            }
            for b in 0..GROUP {
                // SAFETY: as in the first pass.
                let p = _mm256_mul_ps(unsafe { _mm256_loadu_ps(row.add(k * GROUP + b).cast()) }, inv[b]);
                a[0] = _mm256_add_ps(a[0], p);
                a[1] = _mm256_fmadd_ps(p, xv[b][0], a[1]);
                a[2] = _mm256_fmadd_ps(p, xv[b][1], a[2]);
                a[3] = _mm256_fmadd_ps(p, xv[b][2], a[3]);
            }
            for (c, v) in ak.iter_mut().zip(a) {
                // SAFETY: as above.
                unsafe { _mm256_storeu_ps(c.as_mut_ptr(), v) };
            }
        }
    }
}

/// The same sums in AVX-512 intrinsics, a group's four rows at a time, two
/// to a vector (a block's eight points on each half): each block's points,
/// normals and sums are loaded once for the four. Written by hand for the
/// reason `estep::avx512`'s kernels are: LLVM kept the portable kernel's row
/// sums in memory (a store-to-load chain a pair) and its compaction scalar.
#[cfg(target_arch = "x86_64")]
mod avx512 {
    use super::super::avx512::weighted_exp2_neg_f32x16;
    use super::{whole_group, Factors, Rows, SurfelBuffers, BLOCK, GROUP, RESIDUAL_SUMS_FLOOR};
    use std::arch::x86_64::*;

    /// Lanes of an AVX-512 vector of f32.
    const WIDTH: usize = 16;
    /// Data points a vector: one on each half.
    const PAIR: usize = WIDTH / BLOCK;
    const _: () = assert!(PAIR == 2 && GROUP.is_multiple_of(PAIR));
    /// The upper half's lanes.
    const UPPER: __mmask16 = 0xFF00;

    /// # Safety
    /// The CPU must have AVX-512F.
    #[target_feature(enable = "avx512f")]
    pub(super) unsafe fn blocked_surfels<const ROUND: bool, const STATS: bool>(
        b: &mut SurfelBuffers,
        k: Factors,
        rows: &mut Rows,
    ) {
        let SurfelBuffers { blocks, spheres, row, acc, live, x, x_index, groups, reach, .. } = b;
        let nb = blocks.len();
        assert!(row.len() >= nb * GROUP && acc.len() == nb && live.len() >= nb.next_multiple_of(WIDTH) + WIDTH);
        assert!(spheres.iter().all(|c| c.len() == nb) && x.len() == x_index.len() && reach.len() == groups.len());
        let f =
            Consts { kt: _mm512_set1_ps(k.kt), kd: _mm512_set1_ps(k.kd), floor: _mm512_set1_ps(RESIDUAL_SUMS_FLOOR) };
        for (((xg, jg), g), &r) in x.chunks(GROUP).zip(x_index.chunks(GROUP)).zip(groups.iter()).zip(reach.iter()) {
            let count = live_blocks(spheres, g, r, live);
            let xs = whole_group(xg);
            // SAFETY: `live` holds block indices below nb; the buffers' lengths are asserted above.
            unsafe { group::<ROUND, STATS>(blocks, row, acc, &live[..count], &xs, jg, &f, rows) };
        }
    }

    struct Consts {
        kt: __m512,
        kd: __m512,
        floor: __m512,
    }

    /// `super::live_blocks` in vectors, compacted by `vpcompressd` into a register.
    #[target_feature(enable = "avx512f")]
    fn live_blocks(spheres: &[Vec<f32>; 4], g: &[f32; 4], reach: f32, live: &mut [u32]) -> usize {
        let nb = spheres[3].len();
        // No closures in here or in `group`: a closure is its own function,
        // compiled without this one's target features (see `estep::avx512`).
        let gv = [_mm512_set1_ps(g[0]), _mm512_set1_ps(g[1]), _mm512_set1_ps(g[2])];
        let reach = _mm512_set1_ps(reach);
        let lanes = _mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
        let mut count = 0;
        for o in (0..nb).step_by(WIDTH) {
            let tail: __mmask16 = if nb - o >= WIDTH { 0xFFFF } else { (1u16 << (nb - o)) - 1 };
            // SAFETY: the mask covers only lanes below nb, the columns' length.
            let [cx, cy, cz, r] = unsafe {
                [
                    _mm512_maskz_loadu_ps(tail, spheres[0].as_ptr().add(o)),
                    _mm512_maskz_loadu_ps(tail, spheres[1].as_ptr().add(o)),
                    _mm512_maskz_loadu_ps(tail, spheres[2].as_ptr().add(o)),
                    _mm512_maskz_loadu_ps(tail, spheres[3].as_ptr().add(o)),
                ]
            };
            let (dx, dy, dz) = (_mm512_sub_ps(gv[0], cx), _mm512_sub_ps(gv[1], cy), _mm512_sub_ps(gv[2], cz));
            let d2 = _mm512_fmadd_ps(dx, dx, _mm512_fmadd_ps(dy, dy, _mm512_mul_ps(dz, dz)));
            let r = _mm512_add_ps(reach, r);
            let inside = _mm512_mask_cmp_ps_mask::<_CMP_LE_OQ>(tail, d2, _mm512_mul_ps(r, r));
            let idx = _mm512_maskz_compress_epi32(inside, _mm512_add_epi32(_mm512_set1_epi32(o as i32), lanes));
            // SAFETY: `live` has a whole vector of room past any count ≤ nb (asserted by the caller).
            unsafe { _mm512_storeu_si512(live.as_mut_ptr().add(count).cast(), idx) };
            count += inside.count_ones() as usize;
        }
        count
    }

    /// The two halves' lane sums in double precision, each in lane order.
    #[target_feature(enable = "avx512f")]
    fn half_sums_f64(v: __m512) -> [f64; 2] {
        let mut l = [0.0f32; WIDTH];
        // SAFETY: `l` holds sixteen lanes.
        unsafe { _mm512_storeu_ps(l.as_mut_ptr(), v) };
        let (mut lo, mut hi) = (0.0, 0.0);
        for i in 0..BLOCK {
            lo += l[i] as f64;
            hi += l[i + BLOCK] as f64;
        }
        [lo, hi]
    }

    /// The rows of the group's data points `xs` (the caller's indices `js`,
    /// fewer than `GROUP` in a last group) over the blocks `live`.
    ///
    /// # Safety
    /// `live` holds indices of `blocks`, `acc` is as long as `blocks` and `row` GROUP times longer.
    #[target_feature(enable = "avx512f")]
    #[allow(clippy::too_many_arguments)]
    unsafe fn group<const ROUND: bool, const STATS: bool>(
        blocks: &[super::Block],
        row: &mut [super::Lanes],
        acc: &mut [[super::Wide; 4]],
        live: &[u32],
        xs: &[[f32; 3]; GROUP],
        js: &[usize],
        f: &Consts,
        rows: &mut Rows,
    ) {
        const PAIRS: usize = GROUP / PAIR;
        let zero = _mm512_setzero_ps();
        // Pair q's data points: 2q on the lower half, 2q + 1 on the upper.
        let mut xv = [[zero; 3]; PAIRS];
        for q in 0..PAIRS {
            for i in 0..3 {
                let (lo, hi) = (_mm512_set1_ps(xs[2 * q][i]), _mm512_set1_ps(xs[2 * q + 1][i]));
                xv[q][i] = _mm512_mask_blend_ps(UPPER, lo, hi);
            }
        }
        let mut part = [[zero; 3]; PAIRS];
        let row = row.as_mut_ptr();
        for &k in live {
            let k = k as usize;
            // SAFETY: k < blocks.len() (the caller's contract).
            let bk = unsafe { blocks.get_unchecked(k) };
            let (mut y, mut n) = ([zero; 3], [zero; 3]);
            for i in 0..3 {
                // SAFETY: each column holds sixteen lanes (its eight twice).
                y[i] = unsafe { _mm512_loadu_ps(bk.y[i].as_ptr()) };
                if !ROUND {
                    // SAFETY: as above.
                    n[i] = unsafe { _mm512_loadu_ps(bk.n[i].as_ptr()) };
                }
            }
            // SAFETY: as above.
            let pi = unsafe { _mm512_loadu_ps(bk.pi.as_ptr()) };
            for q in 0..PAIRS {
                let d = [_mm512_sub_ps(xv[q][0], y[0]), _mm512_sub_ps(xv[q][1], y[1]), _mm512_sub_ps(xv[q][2], y[2])];
                let r2 = _mm512_fmadd_ps(d[0], d[0], _mm512_fmadd_ps(d[1], d[1], _mm512_mul_ps(d[2], d[2])));
                // Rows k·GROUP + 2q and + 2q + 1: sixteen lanes in a row.
                // SAFETY: k·GROUP + 2q + 1 < row.len().
                let out = unsafe { row.add(k * GROUP + PAIR * q).cast::<f32>() };
                if ROUND {
                    let e = weighted_exp2_neg_f32x16(pi, _mm512_mul_ps(f.kt, r2));
                    if STATS {
                        // SAFETY: as above.
                        unsafe { _mm512_storeu_ps(out, e) };
                    }
                    part[q][0] = _mm512_add_ps(part[q][0], e);
                    continue;
                }
                let an = _mm512_fmadd_ps(n[0], d[0], _mm512_fmadd_ps(n[1], d[1], _mm512_mul_ps(n[2], d[2])));
                let an2 = _mm512_mul_ps(an, an);
                let e = weighted_exp2_neg_f32x16(pi, _mm512_fmadd_ps(f.kd, an2, _mm512_mul_ps(f.kt, r2)));
                // SAFETY: as above.
                unsafe { _mm512_storeu_ps(out, e) };
                part[q][0] = _mm512_add_ps(part[q][0], e);
                // As the portable kernel: the faintest pairs stay out of the variances' sums.
                let keep = _mm512_cmp_ps_mask::<_CMP_GE_OQ>(e, f.floor);
                part[q][1] = _mm512_mask3_fmadd_ps(e, an2, part[q][1], keep);
                part[q][2] = _mm512_mask3_fmadd_ps(e, r2, part[q][2], keep);
            }
        }
        // Each row's inverse total on its half; 0 for the rows a last group lacks.
        let mut inv = [zero; PAIRS];
        for q in 0..PAIRS {
            let sums = [half_sums_f64(part[q][0]), half_sums_f64(part[q][1]), half_sums_f64(part[q][2])];
            let mut half = [0.0f32; PAIR];
            for (h, v) in half.iter_mut().enumerate() {
                if let Some(&j) = js.get(PAIR * q + h) {
                    *v = rows.close(j, [sums[0][h], sums[1][h], sums[2][h]]) as f32;
                }
            }
            inv[q] = _mm512_mask_blend_ps(UPPER, _mm512_set1_ps(half[0]), _mm512_set1_ps(half[1]));
        }
        if !STATS {
            return;
        }
        for &k in live {
            let k = k as usize;
            // SAFETY: k < acc.len().
            let ak = unsafe { acc.get_unchecked_mut(k) };
            let mut a = [zero; 4];
            for (v, c) in a.iter_mut().zip(ak.iter()) {
                // SAFETY: each sum holds sixteen lanes.
                *v = unsafe { _mm512_loadu_ps(c.as_ptr()) };
            }
            for q in 0..PAIRS {
                // SAFETY: as in the first pass.
                let e = unsafe { _mm512_loadu_ps(row.add(k * GROUP + PAIR * q).cast()) };
                let p = _mm512_mul_ps(e, inv[q]);
                a[0] = _mm512_add_ps(a[0], p);
                a[1] = _mm512_fmadd_ps(p, xv[q][0], a[1]);
                a[2] = _mm512_fmadd_ps(p, xv[q][1], a[2]);
                a[3] = _mm512_fmadd_ps(p, xv[q][2], a[3]);
            }
            for (c, v) in ak.iter_mut().zip(a) {
                // SAFETY: as above.
                unsafe { _mm512_storeu_ps(c.as_mut_ptr(), v) };
            }
        }
    }
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

    /// A kernel's f32 sums against f64 ones: likelihood, P1, PX and Pᵀ1.
    fn assert_posteriors_near(out: &Posteriors, want: &Posteriors, simd: Simd) {
        let nll = want.neg_log_likelihood;
        assert!(
            (out.neg_log_likelihood - nll).abs() < 1e-5 * nll.abs(),
            "{simd:?}: {} vs {nll}",
            out.neg_log_likelihood
        );
        assert!((out.np - want.np).abs() < 1e-4 * want.np);
        assert!(out.p1.len() == want.p1.len() && out.px.len() == want.px.len() && out.pt1.len() == want.pt1.len());
        for (i, (p1, px)) in out.p1.iter().zip(&out.px).enumerate() {
            assert!((p1 - want.p1[i]).abs() < 1e-4 + 1e-3 * want.p1[i], "{simd:?}: p1[{i}]");
            for d in 0..3 {
                assert!((px[d] - want.px[i][d]).abs() < 1e-5 + 1e-3 * want.px[i][d].abs(), "{simd:?}: px[{i}]");
            }
        }
        for (j, pt1) in out.pt1.iter().enumerate() {
            assert!((pt1 - want.pt1[j]).abs() < 1e-4, "{simd:?}: pt1[{j}]");
        }
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
        let (x, _) = sheet(301, 1, 0.0);
        let (y, normals) = sheet(101, 2, 0.002);
        let pi: Vec<f64> = (0..y.len()).map(|i| if i % 7 == 0 { 0.2 } else { 1.1 }).collect();
        let s = Surfels { normals: &normals, tangent_sigma2: 0.006f64.powi(2), normal_sigma2: 0.0015f64.powi(2) };
        let mut e = EStep::new(&x);
        e.simd = simd;
        e.cutoff_sigmas = cutoff_sigmas;
        let mut out = Posteriors::default();
        let sums = e.run_surfels(&y, &s, Some(&pi), 0.1, &mut out);
        let (want, want_sums) = reference(&x, &y, &s, &pi, 0.1);
        assert_posteriors_near(&out, &want, simd);
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

    /// `EStep::blocked`: truncated isotropic E-steps by the round kernels
    /// (blocks beyond 6σ skipped on a 20 cm sheet) against the dense f64 sums.
    #[test]
    fn blocked_isotropic_sums_match_the_dense_ones_on_every_kernel() {
        let (x, _) = sheet(301, 5, 0.0);
        let (y, _) = sheet(150, 6, 0.002);
        let pi: Vec<f64> = (0..y.len()).map(|i| if i % 5 == 0 { 0.3 } else { 1.2 }).collect();
        let sigma2 = 0.006f64.powi(2);
        let mut dense = EStep::new(&x);
        dense.truncate_below = 0.0;
        let mut want = Posteriors::default();
        dense.run_weighted(&y, Some(&pi), sigma2, 0.1, &mut want);
        for simd in Simd::available() {
            let mut e = EStep::new(&x);
            e.simd = simd;
            e.blocked = true;
            e.truncate_below = 1.0;
            e.cutoff_sigmas = 6.0;
            assert!(e.truncates(sigma2));
            let mut out = Posteriors::default();
            e.run_weighted(&y, Some(&pi), sigma2, 0.1, &mut out);
            assert_posteriors_near(&out, &want, simd);
            // The likelihood alone (no posterior sums) is the same number to the bit.
            assert_eq!(e.neg_log_likelihood(&y, Some(&pi), sigma2, 0.1), out.neg_log_likelihood, "{simd:?}");
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

    #[test]
    fn total_order_bits_order_as_total_cmp() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        let mut v = vec![0.0, -0.0, 1.0, -1.0, f64::INFINITY, f64::NEG_INFINITY, f64::MIN_POSITIVE, -f64::MIN_POSITIVE];
        v.extend((0..200).map(|_| rng.random_range(-1.0..1.0) * 10f64.powi(rng.random_range(-5..5))));
        for a in &v {
            for b in &v {
                assert_eq!(total_order_bits(*a).cmp(&total_order_bits(*b)), a.total_cmp(b), "{a} {b}");
            }
        }
    }

    #[test]
    fn model_blocks_are_whole_compact_and_cover_every_point() {
        // A mug-like shell: two coaxial walls 4 mm apart.
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(9);
        let p: Vec<P3> = (0..800)
            .map(|i| {
                let (a, z): (f64, f64) = (rng.random_range(0.0..std::f64::consts::TAU), rng.random_range(0.0..0.1));
                let r = if i % 2 == 0 { 0.04 } else { 0.036 };
                [r * a.cos(), r * a.sin(), z]
            })
            .collect();
        let order = model_order(&p);
        assert_eq!(order.len(), 800);
        let mut seen = order.clone();
        seen.sort_unstable();
        assert!(seen.iter().enumerate().all(|(i, &j)| i == j), "every point once");
        let radii = |o: &[usize]| -> f64 {
            o.chunks(BLOCK).map(|b| f64::from(bounding_sphere(b.iter().map(|&i| &p[i]))[3])).sum::<f64>()
        };
        // The swaps leave the blocks no wider than the k-d split's.
        let split = spatial_order(&p, BLOCK);
        assert!(radii(&order) < radii(&split), "{} vs {}", radii(&order), radii(&split));
    }
}
