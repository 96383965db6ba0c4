//! The CPD E-step: posteriors of the Gaussian mixture centred on the moving
//! points Y (M) given the fixed data X (N), with a uniform outlier component.
//!
//! Only the sufficient statistics leave this module (P1, Pᵀ1, PX and the
//! negative log-likelihood), so memory is O(M + N): the M×N posterior matrix
//! is never stored. Two evaluations of the same sums:
//! - dense: every pair, streamed one data point at a time;
//! - truncated: once σ is small, pairs farther than `cutoff_sigmas`·σ are
//!   negligible (e^{-32} at 8σ); a uniform grid over X finds the pairs that
//!   matter (see `grid.rs` for why not a k-d tree), and a Verlet neighbour
//!   list keeps them over the iterations in which the model moves little;
//!   or (`EStep::blocked`, the registration's small sets) whole blocks of
//!   nearby moving points are skipped by groups of nearby data points
//!   (`surfel`'s kernels with round components).

use super::fastexp::{exp2_neg_f32, exp_neg, madd, EXP2_CUT_F32, EXP2_SERIES_F32};
use super::grid::RadiusGrid;
use rayon::prelude::*;

#[cfg(target_arch = "x86_64")]
mod avx512;
mod surfel;

pub use surfel::{model_order, ResidualSums, Surfels};

use crate::simd::Simd;

pub type P3 = [f64; 3];

/// Sufficient statistics of one E-step.
#[derive(Clone, Debug, Default)]
pub struct Posteriors {
    /// Σ_n P_mn, per moving point.
    pub p1: Vec<f64>,
    /// Σ_m P_mn, per data point.
    pub pt1: Vec<f64>,
    /// Σ_n P_mn x_n, per moving point.
    pub px: Vec<P3>,
    /// Σ P_mn.
    pub np: f64,
    /// −Σ_n log(Σ_m e^{-d²/2σ²} + c) + N·3/2·log σ² (up to constants).
    pub neg_log_likelihood: f64,
}

impl Posteriors {
    /// Zeroed sums for `m` moving and `n` data points (buffers kept).
    fn reset(&mut self, m: usize, n: usize) {
        self.p1.clear();
        self.p1.resize(m, 0.0);
        self.pt1.clear();
        self.pt1.resize(n, 0.0);
        self.px.clear();
        self.px.resize(m, [0.0; 3]);
        self.np = 0.0;
        self.neg_log_likelihood = 0.0;
    }
}

/// Distance in σ beyond which pairs are dropped in truncated mode, by default:
/// e^{-32} relative weight, below any effect on a fit.
pub const CUTOFF_SIGMAS: f64 = 8.0;

/// Cloning keeps what was made of the data (see [`EStep::prepare_blocks`]).
#[derive(Clone)]
pub struct EStep {
    x: Vec<P3>,
    grid: RadiusGrid,
    /// Radius the grid was last built for.
    grid_radius: f64,
    /// Bounding radius of X around its centroid: decides dense or truncated.
    x_radius: f64,
    /// Pairs farther than this many σ are dropped once that prunes most pairs.
    pub cutoff_sigmas: f64,
    /// Truncate when the cutoff radius is below this fraction of the data's
    /// bounding radius; below it, the pairs that matter are few enough that
    /// finding them beats evaluating all of them.
    pub truncate_below: f64,
    /// Truncated E-steps skip whole blocks of nearby moving points beyond
    /// the cutoff from groups of nearby data points (`surfel`'s kernels,
    /// round components, f32) instead of listing the pairs within it.
    pub blocked: bool,
    /// Evaluate the dense sums in f32 (twice the SIMD lanes). For fits that
    /// need no more (registration); CPD keeps f64 to agree with its peers.
    pub single_precision: bool,
    f32buf: F32Buffers,
    /// Split the dense single-precision E-step's data rows over rayon's pool
    /// in fixed chunks (`dense_chunks`). For CPD, whose E-step is one of the
    /// few things running; a registration keeps one thread (the daemon runs
    /// one per request) and the bits of the sums in one pass.
    pub parallel_rows: bool,
    chunk_scratch: Vec<DenseScratch>,
    // Reused buffers.
    ys: [Vec<f64>; 3],
    row: Vec<f64>,
    acc: [Vec<f64>; 4],
    pi: Vec<f64>,
    den: Vec<f64>,
    list: NeighbourList,
    /// Statistics computed and thrown away by `neg_log_likelihood`.
    scratch: Posteriors,
    /// The kernels taken (`Simd::detect` at construction; tests lower it).
    simd: Simd,
    surfel_buf: surfel::SurfelBuffers,
}

impl EStep {
    pub fn new(x: &[P3]) -> Self {
        let n = x.len().max(1) as f64;
        let c = x.iter().fold([0.0; 3], |a, p| [a[0] + p[0] / n, a[1] + p[1] / n, a[2] + p[2] / n]);
        let x_radius = x.iter().map(|p| dist2(p, &c)).fold(0.0, f64::max).sqrt();
        Self {
            x: x.to_vec(),
            grid: RadiusGrid::default(),
            grid_radius: 0.0,
            x_radius,
            cutoff_sigmas: CUTOFF_SIGMAS,
            truncate_below: 0.5,
            blocked: false,
            single_precision: false,
            f32buf: F32Buffers::default(),
            parallel_rows: false,
            chunk_scratch: Vec::new(),
            ys: Default::default(),
            row: Vec::new(),
            acc: Default::default(),
            pi: Vec::new(),
            den: Vec::new(),
            list: NeighbourList::default(),
            scratch: Posteriors::default(),
            simd: Simd::detect(Simd::Avx512),
            surfel_buf: Default::default(),
        }
    }

    pub fn data(&self) -> &[P3] {
        &self.x
    }

    /// Computes the posteriors of `y` (the moving GMM centroids) into `out`.
    /// `w` is the outlier weight in [0, 1).
    pub fn run(&mut self, y: &[P3], sigma2: f64, w: f64, out: &mut Posteriors) {
        self.run_weighted(y, None, sigma2, w, out)
    }

    /// As `run`, with mixing weights of the centroids (mean 1; CPD's equal
    /// weights are all ones). A registration gives centroids the camera cannot
    /// see a small weight: they cannot have produced an observation.
    pub fn run_weighted(&mut self, y: &[P3], weights: Option<&[f64]>, sigma2: f64, w: f64, out: &mut Posteriors) {
        if self.blocked && self.truncates(sigma2) {
            // It zeroes `out` itself and finishes the sums.
            self.run_round(y, weights, sigma2, w, out);
            return;
        }
        let (m, n) = (y.len(), self.x.len());
        out.reset(m, n);
        if m == 0 || n == 0 {
            return;
        }
        let c = outlier_constant(sigma2, w, m, n);
        if self.truncates(sigma2) && self.list_fits(y, self.cutoff_sigmas * sigma2.sqrt()) {
            let cutoff = self.cutoff_sigmas * sigma2.sqrt();
            self.run_truncated(y, weights, sigma2, c, cutoff * cutoff, out);
        } else {
            self.run_dense(y, weights, sigma2, c, out);
        }
        out.np = out.p1.iter().sum();
        out.neg_log_likelihood += n as f64 * 1.5 * sigma2.ln();
    }

    /// The negative log-likelihood alone (as `Posteriors::neg_log_likelihood`
    /// of `run_weighted`), for scoring a pose without fitting it: in the dense
    /// single-precision regime it skips the posterior sums, a sixth of the
    /// work, and in the blocked one their second pass (`round_likelihood`).
    pub fn neg_log_likelihood(&mut self, y: &[P3], weights: Option<&[f64]>, sigma2: f64, w: f64) -> f64 {
        let (m, n) = (y.len(), self.x.len());
        if self.blocked && self.truncates(sigma2) {
            return self.round_likelihood(y, weights, sigma2, w);
        }
        let mut post = std::mem::take(&mut self.scratch);
        if m == 0 || n == 0 || self.truncates(sigma2) || !self.single_precision {
            self.run_weighted(y, weights, sigma2, w, &mut post);
        } else {
            post.neg_log_likelihood = n as f64 * 1.5 * sigma2.ln();
            let c = outlier_constant(sigma2, w, m, n);
            self.dense_f32::<false>(y, weights, sigma2, c, &mut post);
        }
        let nll = post.neg_log_likelihood;
        self.scratch = post;
        nll
    }

    /// Groups the data for the blocked kernels now rather than at their
    /// first E-step, so that clones of this one (the fits of a registration
    /// on the same points) share the work.
    pub fn prepare_blocks(&mut self) {
        self.surfel_buf.load_data(&self.x);
    }

    /// Orders the moving points of the blocked E-steps to come by `order`
    /// ([`model_order`] of a model of `m` points at rest) instead of
    /// ordering them at the first; ignored when it does not order `m` points.
    pub fn use_model_order(&mut self, order: &[usize], m: usize) {
        self.surfel_buf.use_model_order(order, m);
    }

    /// The shift that moves the posterior-weighted centroid of `y` onto the
    /// data's: (Σₙ pt1ₙ xₙ − Σₘₙ Pₘₙ yₘ) / Np, the translation half of an
    /// M-step with rotation and scale held. Where the dense single-precision
    /// AVX2 kernel applies (the yaw sweep's translation refit), in one pass
    /// that keeps only per-row sums (measured: a sweep turn's posterior
    /// E-step 23 µs against 16 for the likelihood alone); from the full
    /// posteriors otherwise. None when no data point is explained.
    pub fn centroid_shift(&mut self, y: &[P3], weights: Option<&[f64]>, sigma2: f64, w: f64) -> Option<[f64; 3]> {
        let (m, n) = (y.len(), self.x.len());
        if m == 0 || n == 0 {
            return None;
        }
        let c = outlier_constant(sigma2, w, m, n);
        #[cfg(target_arch = "x86_64")]
        {
            if self.single_precision && !self.truncates(sigma2) && self.simd >= Simd::Avx2 {
                let b = &mut self.f32buf;
                b.load(&self.x, y, weights);
                let k = exponent_f32(sigma2);
                // SAFETY: `Simd::detect` found the features the functions are compiled for.
                let (mx, my, np) = unsafe {
                    match self.simd {
                        Simd::Avx512 => avx512::dense_centroids(b, &self.x, k, c),
                        _ => dense_centroids_f32_avx2(b, &self.x, k, c),
                    }
                };
                return (np > 1e-9).then(|| [0, 1, 2].map(|d| (mx[d] - my[d]) / np));
            }
        }
        let mut post = std::mem::take(&mut self.scratch);
        self.run_weighted(y, weights, sigma2, w, &mut post);
        let np = post.np;
        let (mut mx, mut my) = ([0.0; 3], [0.0; 3]);
        for (xn, p) in self.x.iter().zip(&post.pt1) {
            (0..3).for_each(|d| mx[d] += p * xn[d]);
        }
        for (ym, p) in y.iter().zip(&post.p1) {
            (0..3).for_each(|d| my[d] += p * ym[d]);
        }
        self.scratch = post;
        (np > 1e-9).then(|| [0, 1, 2].map(|d| (mx[d] - my[d]) / np))
    }

    /// Whether an E-step at `sigma2` takes the neighbour list: when the
    /// cutoff ball holds a small share of the data volume.
    fn truncates(&self, sigma2: f64) -> bool {
        self.x.len() >= 64 && self.cutoff_sigmas * sigma2.sqrt() < self.truncate_below * self.x_radius
    }

    /// The dense sums in single precision (with the posterior sums when
    /// `STATS`), in the AVX2 kernel where the CPU has it.
    fn dense_f32<const STATS: bool>(
        &mut self,
        y: &[P3],
        weights: Option<&[f64]>,
        sigma2: f64,
        c: f64,
        out: &mut Posteriors,
    ) {
        let (m, k, simd) = (y.len(), exponent_f32(sigma2), self.simd);
        let b = &mut self.f32buf;
        b.load(&self.x, y, weights);
        let F32Buffers { x, ys, pi, row, acc, .. } = b;
        let (chunks, len) = if STATS && self.parallel_rows { dense_chunks(x.len()) } else { (1, x.len()) };
        if chunks == 1 {
            let pt1: &mut [f64] = if STATS { &mut out.pt1 } else { &mut [] };
            let job = DenseRows { x, ys, pi, row, acc, pt1 };
            out.neg_log_likelihood -= dense_f32_rows::<STATS>(simd, job, k, c);
            if STATS {
                add_posterior_sums(acc, m, out);
            }
            return;
        }
        // Split over the pool by fixed chunks of data rows, each with its own
        // sums, added in chunk order.
        self.chunk_scratch.resize_with(chunks, DenseScratch::default);
        let (ys, pi) = (&*ys, &*pi);
        let logs: Vec<f64> = self.chunk_scratch[..chunks]
            .par_iter_mut()
            .zip(x.par_chunks(len))
            .zip(out.pt1.par_chunks_mut(len))
            .map(|((s, xc), pt1)| {
                let job = DenseRows { x: xc, ys, pi, row: &mut s.row, acc: &mut s.acc, pt1 };
                dense_f32_rows::<true>(simd, job, k, c)
            })
            .collect();
        for (s, log) in self.chunk_scratch[..chunks].iter().zip(&logs) {
            add_posterior_sums(&s.acc, m, out);
            out.neg_log_likelihood -= log;
        }
    }

    fn run_dense(&mut self, y: &[P3], weights: Option<&[f64]>, sigma2: f64, c: f64, out: &mut Posteriors) {
        if self.single_precision {
            self.dense_f32::<true>(y, weights, sigma2, c, out);
            return;
        }
        let m = y.len();
        let k = -0.5 / sigma2;
        self.pi.clear();
        match weights {
            Some(wt) => self.pi.extend_from_slice(&wt[..m]),
            None => self.pi.resize(m, 1.0),
        }
        for (d, ys) in self.ys.iter_mut().enumerate() {
            ys.clear();
            ys.extend(y.iter().map(|p| p[d]));
        }
        self.row.resize(m, 0.0);
        let (ys, row, x, acc, pi) = (&self.ys, &mut self.row, &self.x, &mut self.acc, &self.pi);
        #[cfg(target_arch = "x86_64")]
        {
            if self.simd >= Simd::Avx2 {
                // SAFETY: `Simd::detect` found the features the function is compiled for.
                unsafe { dense_rows_avx2(x, ys, pi, row, acc, m, k, c, out) };
                return;
            }
        }
        dense_rows(x, ys, pi, row, acc, m, k, c, out);
    }

    /// Whether the neighbour list at this cutoff stays within its memory
    /// budget ([`max_listed_pairs`]). A list already built fits; before a
    /// new one, 64 evenly spaced moving points count their neighbours in the
    /// grid and the mean stands for all. Over the budget the E-step stays
    /// dense (streamed, O(M + N) memory) until σ shrinks: two 20,000-point
    /// clouds listed 10⁸ pairs (1.8 GB) at the first truncated step.
    fn list_fits(&mut self, y: &[P3], cutoff: f64) -> bool {
        if !matches!(self.list.state(y, cutoff), ListState::Stale) {
            return true;
        }
        let radius = cutoff * (1.0 + VERLET_SKIN);
        if radius > self.grid_radius || radius < 0.5 * self.grid_radius {
            self.grid.build(&self.x, radius);
            self.grid_radius = radius;
        }
        let samples = y.len().min(64);
        let mut found = Vec::new();
        for s in 0..samples {
            self.grid.collect_within(&y[s * y.len() / samples], radius * radius, &mut found);
        }
        let estimate = found.len() as f64 / samples.max(1) as f64 * y.len() as f64;
        estimate <= max_listed_pairs(y.len(), self.x.len()) as f64
    }

    fn run_truncated(
        &mut self,
        y: &[P3],
        weights: Option<&[f64]>,
        sigma2: f64,
        c: f64,
        cutoff2: f64,
        out: &mut Posteriors,
    ) {
        let cutoff = cutoff2.sqrt();
        match self.list.state(y, cutoff) {
            ListState::Current => {}
            ListState::Loose { moved } => self.list.shrink(&self.x, (cutoff * (1.0 + VERLET_SKIN)).max(cutoff + moved)),
            ListState::Stale => {
                let radius = cutoff * (1.0 + VERLET_SKIN);
                // Rebuild when σ has shrunk enough that the cells hold far too much, or grown past them.
                if radius > self.grid_radius || radius < 0.5 * self.grid_radius {
                    self.grid.build(&self.x, radius);
                    self.grid_radius = radius;
                }
                self.list.build(&self.grid, y, radius, self.simd >= Simd::Avx2);
            }
        }
        let k = -0.5 / sigma2;
        if self.single_precision {
            let b = &mut self.f32buf;
            b.load(&self.x, y, weights);
            #[cfg(target_arch = "x86_64")]
            {
                if self.simd >= Simd::Avx2 {
                    if !self.list.padded_current {
                        self.list.pad(b);
                    }
                    let pp = &self.list.padded;
                    // SAFETY: `Simd::detect` found the features the functions are compiled for.
                    // (AVX-512 measured no faster here: rows are runs of a few vectors.)
                    unsafe { padded_pairs_f32_avx2(b, pp, exponent_f32(sigma2), c, out) };
                    return;
                }
            }
            let NeighbourList { starts, data, .. } = &self.list;
            listed_pairs_f32::<false>(b, starts, data, exponent_f32(sigma2), c, out);
            return;
        }
        let NeighbourList { starts, data, .. } = &self.list;
        // Affinities of the listed pairs, moving point by moving point; the
        // exponentials in one pass over a flat buffer, so they vectorise.
        let e = &mut self.row;
        e.clear();
        for (i, yi) in y.iter().enumerate() {
            for &j in &data[starts[i] as usize..starts[i + 1] as usize] {
                e.push(k * dist2(&self.x[j as usize], yi));
            }
        }
        e.iter_mut().for_each(|v| *v = exp_neg(*v));
        self.den.clear();
        self.den.resize(self.x.len(), 0.0);
        for i in 0..y.len() {
            let wi = weights.map_or(1.0, |w| w[i]);
            let range = starts[i] as usize..starts[i + 1] as usize;
            for (v, &j) in e[range.clone()].iter_mut().zip(&data[range]) {
                *v *= wi;
                self.den[j as usize] += *v;
            }
        }
        let mut log_den = LogSum::default();
        for (j, d) in self.den.iter_mut().enumerate() {
            let sum = *d;
            let (den, inv) = row_total(sum, c);
            out.pt1[j] = sum * inv;
            log_den.add(den);
            *d = inv;
        }
        out.neg_log_likelihood -= log_den.total();
        for i in 0..y.len() {
            let range = starts[i] as usize..starts[i + 1] as usize;
            let (mut p1, mut px) = (0.0, [0.0; 3]);
            for (v, &j) in e[range.clone()].iter().zip(&data[range]) {
                let p = v * self.den[j as usize];
                let xn = &self.x[j as usize];
                p1 += p;
                px[0] += p * xn[0];
                px[1] += p * xn[1];
                px[2] += p * xn[2];
            }
            out.p1[i] = p1;
            out.px[i] = px;
        }
    }
}

/// Extra radius of a neighbour list beyond the cutoff, as a fraction of it:
/// the room the moving points have before the list must be rebuilt.
const VERLET_SKIN: f64 = 0.3;

/// The neighbour list's budget: 256 pairs a point of both clouds, at most
/// 2²⁴ (about 20 bytes a pair with its single-precision layout: 340 MB).
fn max_listed_pairs(m: usize, n: usize) -> usize {
    (256 * (m + n)).min(1 << 24)
}

/// What a neighbour list needs before an E-step at some cutoff.
enum ListState {
    /// It lists every pair within the cutoff and not too many more.
    Current,
    /// It lists every pair within the cutoff, but its radius has become
    /// far larger than the cutoff (σ shrank); the moving points have moved
    /// at most `moved` since the build.
    Loose { moved: f64 },
    /// Some pair within the cutoff may be missing: rebuild.
    Stale,
}

/// A Verlet neighbour list (molecular dynamics' device): for every moving
/// point, the data points within the cutoff plus a skin when it was built.
/// EM moves the model a little each iteration; while no point has moved
/// farther than the skin allows, every pair within the cutoff is still on
/// the list, and an iteration evaluates the listed pairs without searching.
#[derive(Clone, Default)]
struct NeighbourList {
    /// Pairs grouped by moving point: `data[starts[i]..starts[i + 1]]`.
    starts: Vec<u32>,
    data: Vec<u32>,
    /// The moving points when the list was built, and its radius.
    y_built: Vec<P3>,
    radius: f64,
    /// The same pairs laid out for the vector kernel, and whether that
    /// layout is of the current list (it is made on first use after a build).
    padded: PaddedPairs,
    padded_current: bool,
}

impl NeighbourList {
    /// Whether every pair of `y` with the data within `cutoff` is listed (a
    /// pair's distance falls at most by the moving point's displacement since
    /// the build), and if so whether the list is so loose that it should be
    /// trimmed to the cutoff.
    fn state(&self, y: &[P3], cutoff: f64) -> ListState {
        if y.len() != self.y_built.len() || self.radius < cutoff {
            return ListState::Stale;
        }
        let moved2 = y.iter().zip(&self.y_built).fold(0.0f64, |m, (a, b)| m.max(dist2(a, b)));
        let moved = moved2.sqrt();
        if moved > self.radius - cutoff {
            ListState::Stale
        } else if cutoff * (1.0 + 2.0 * VERLET_SKIN) < self.radius {
            ListState::Loose { moved }
        } else {
            ListState::Current
        }
    }

    /// Keeps only the pairs within `radius` (< the built radius) of the
    /// moving points as built: the list a build at `radius` would have made,
    /// for one pass over the pairs instead of a grid search (measured: a
    /// search of 800 moving points cost ten E-steps over their list, and
    /// annealing σ loosened the list every few iterations).
    fn shrink(&mut self, x: &[P3], radius: f64) {
        let r2 = radius * radius;
        let mut kept = 0;
        let mut start = 0;
        for i in 0..self.y_built.len() {
            let end = self.starts[i + 1] as usize;
            let yi = self.y_built[i];
            for p in start..end {
                let j = self.data[p];
                self.data[kept] = j;
                kept += (dist2(&x[j as usize], &yi) <= r2) as usize;
            }
            start = end;
            self.starts[i + 1] = kept as u32;
        }
        self.data.truncate(kept);
        self.radius = radius;
        self.padded_current = false;
    }

    fn build(&mut self, grid: &RadiusGrid, y: &[P3], radius: f64, allow_avx2: bool) {
        self.starts.clear();
        self.data.clear();
        self.starts.push(0);
        grid.collect_rows(y, radius * radius, allow_avx2, &mut self.starts, &mut self.data);
        self.y_built.clear();
        self.y_built.extend_from_slice(y);
        self.radius = radius;
        self.padded_current = false;
    }

    /// Lays the pairs out as `PaddedPairs`, with the data of `b`.
    fn pad(&mut self, b: &F32Buffers) {
        let pp = &mut self.padded;
        let n = b.xs[0].len();
        // Row starts first, so the columns are sized once and written by index.
        pp.starts.clear();
        pp.starts.push(0);
        let mut total = 0;
        for w in self.starts.windows(2) {
            total += ((w[1] - w[0]) as usize).next_multiple_of(LANES);
            pp.starts.push(total as u32);
        }
        pp.data.clear();
        pp.data.resize(total, n as u32);
        for c in pp.x.iter_mut() {
            c.clear();
            c.resize(total, FAR_AWAY);
        }
        let [x0, x1, x2] = &mut pp.x;
        for (w, &o) in self.starts.windows(2).zip(&pp.starts) {
            let row = &self.data[w[0] as usize..w[1] as usize];
            let o = o as usize;
            for (k, &j) in row.iter().enumerate() {
                pp.data[o + k] = j;
                x0[o + k] = b.xs[0][j as usize];
                x1[o + k] = b.xs[1][j as usize];
                x2[o + k] = b.xs[2][j as usize];
            }
        }
        self.padded_current = true;
    }
}

/// The dense E-step sums, one data point (row) at a time. Written so that
/// every loop vectorises: structure-of-arrays accumulators (PX as three
/// columns, not [f64; 3] rows) and a four-way partial sum for the row total.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn dense_rows(
    x: &[P3],
    ys: &[Vec<f64>; 3],
    pi: &[f64],
    row: &mut [f64],
    acc: &mut [Vec<f64>; 4],
    m: usize,
    k: f64,
    c: f64,
    out: &mut Posteriors,
) {
    let (yx, yy, yz, pi) = (&ys[0][..m], &ys[1][..m], &ys[2][..m], &pi[..m]);
    for a in acc.iter_mut() {
        a.clear();
        a.resize(m, 0.0);
    }
    let [p1, px0, px1, px2] = acc;
    let (p1, px0, px1, px2) = (&mut p1[..m], &mut px0[..m], &mut px1[..m], &mut px2[..m]);
    let mut log_den = LogSum::default();
    for (j, xn) in x.iter().enumerate() {
        let row = &mut row[..m];
        for ((((r, a), b), c), w) in row.iter_mut().zip(yx).zip(yy).zip(yz).zip(pi) {
            let (dx, dy, dz) = (xn[0] - a, xn[1] - b, xn[2] - c);
            *r = w * exp_neg(k * (dx * dx + dy * dy + dz * dz));
        }
        let mut part = [0.0f64; 4];
        let chunks = row.chunks_exact(4);
        let tail: f64 = chunks.remainder().iter().sum();
        for ch in chunks {
            for l in 0..4 {
                part[l] += ch[l];
            }
        }
        let sum = part[0] + part[1] + part[2] + part[3] + tail;
        let (den, inv) = row_total(sum, c);
        log_den.add(den);
        out.pt1[j] = sum * inv;
        let (w0, w1, w2) = (xn[0] * inv, xn[1] * inv, xn[2] * inv);
        for ((((r, a), b), c), d) in
            row.iter().zip(p1.iter_mut()).zip(px0.iter_mut()).zip(px1.iter_mut()).zip(px2.iter_mut())
        {
            *a += r * inv;
            *b += r * w0;
            *c += r * w1;
            *d += r * w2;
        }
    }
    for i in 0..m {
        out.p1[i] = p1[i];
        out.px[i] = [px0[i], px1[i], px2[i]];
    }
    out.neg_log_likelihood -= log_den.total();
}

/// The same loops compiled for AVX2 + FMA (4 doubles a lane, fused multiply-add):
/// about 3× the baseline x86-64 build. Chosen at run time, so one binary runs everywhere.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
#[allow(clippy::too_many_arguments)]
unsafe fn dense_rows_avx2(
    x: &[P3],
    ys: &[Vec<f64>; 3],
    pi: &[f64],
    row: &mut [f64],
    acc: &mut [Vec<f64>; 4],
    m: usize,
    k: f64,
    c: f64,
    out: &mut Posteriors,
) {
    dense_rows(x, ys, pi, row, acc, m, k, c, out)
}

/// f32 lanes of an AVX2 register.
const LANES: usize = 8;

#[derive(Clone, Default)]
struct F32Buffers {
    x: Vec<[f32; 3]>,
    /// The data again as three columns, for the neighbour lists' indexed loads.
    xs: [Vec<f32>; 3],
    ys: [Vec<f32>; 3],
    pi: Vec<f32>,
    row: Vec<f32>,
    acc: [Vec<f32>; 4],
}

impl F32Buffers {
    /// The data (converted once), the moving points and their weights (every call).
    fn load(&mut self, x: &[P3], y: &[P3], weights: Option<&[f64]>) {
        if self.x.len() != x.len() {
            self.x = x.iter().map(|p| [p[0] as f32, p[1] as f32, p[2] as f32]).collect();
            for (d, col) in self.xs.iter_mut().enumerate() {
                *col = x.iter().map(|p| p[d] as f32).collect();
            }
        }
        // Padded to whole vectors with weightless points (their affinities are
        // exactly 0): a scalar remainder of a few points costs as much as a
        // dozen vectors (measured: 100 moving points ran slower than 104).
        let m8 = y.len().div_ceil(LANES) * LANES;
        for (d, ys) in self.ys.iter_mut().enumerate() {
            ys.clear();
            ys.extend(y.iter().map(|p| p[d] as f32));
            ys.resize(m8, 0.0);
        }
        self.pi.clear();
        match weights {
            Some(w) => self.pi.extend(w[..y.len()].iter().map(|&v| v as f32)),
            None => self.pi.resize(y.len(), 1.0),
        }
        self.pi.resize(m8, 0.0);
        self.row.resize(m8, 0.0);
    }
}

/// One pass of a dense single-precision kernel over data rows `x` (all the
/// data, or one chunk of it): the moving points it reads (padded, `load`),
/// the scratch it writes (`row`; `acc` ends holding the chunk's P1 and PX
/// sums), and with `STATS` the rows' shares into `pt1` (x.len() long).
/// The kernels return Σ log of the rows' totals.
pub(super) struct DenseRows<'a> {
    pub x: &'a [[f32; 3]],
    pub ys: &'a [Vec<f32>; 3],
    pub pi: &'a [f32],
    pub row: &'a mut Vec<f32>,
    pub acc: &'a mut [Vec<f32>; 4],
    pub pt1: &'a mut [f64],
}

/// A dense kernel's own scratch, one per chunk of a split E-step.
#[derive(Clone, Default)]
struct DenseScratch {
    row: Vec<f32>,
    acc: [Vec<f32>; 4],
}

/// Data rows below which a dense E-step is not split (`EStep::parallel_rows`),
/// and the most chunks it is split into: fixed by the data's size alone, so
/// the sums, added chunk after chunk, are the same on any thread count.
const MIN_CHUNK_ROWS: usize = 128;
const MAX_CHUNKS: usize = 8;

/// How many chunks of how many rows (a multiple of `ROW_BLOCK`) a split
/// dense E-step over `n` data rows takes.
fn dense_chunks(n: usize) -> (usize, usize) {
    let chunks = (n / MIN_CHUNK_ROWS).clamp(1, MAX_CHUNKS);
    let len = n.div_ceil(chunks).next_multiple_of(ROW_BLOCK).max(ROW_BLOCK);
    (n.div_ceil(len).max(1), len)
}

/// The truncated E-step over a neighbour list, in single precision.
/// `starts`/`data` must index the moving points and the data loaded in `b`.
#[inline(always)]
fn listed_pairs_f32<const FMA: bool>(
    b: &mut F32Buffers,
    starts: &[u32],
    data: &[u32],
    k: f32,
    c: f64,
    out: &mut Posteriors,
) {
    let F32Buffers { xs, ys, pi, row: e, acc, .. } = b;
    let m = starts.len() - 1;
    let n = xs[0].len();
    let (x0, x1, x2) = (&xs[0][..n], &xs[1][..n], &xs[2][..n]);
    // Exponents pair by pair (indexed loads: scalar), then the exponentials
    // over the flat buffer (vectorised), then the weights and row totals.
    e.clear();
    e.resize(data.len(), 0.0);
    for i in 0..m {
        let range = starts[i] as usize..starts[i + 1] as usize;
        let (yx, yy, yz) = (ys[0][i], ys[1][i], ys[2][i]);
        for (v, &j) in e[range.clone()].iter_mut().zip(&data[range]) {
            let j = j as usize;
            let (dx, dy, dz) = (x0[j] - yx, x1[j] - yy, x2[j] - yz);
            *v = k * madd::<FMA>(dx, dx, madd::<FMA>(dy, dy, dz * dz));
        }
    }
    e.iter_mut().for_each(|v| *v = exp2_neg_f32::<FMA>(*v));
    let den = &mut acc[0];
    den.clear();
    den.resize(n, 0.0);
    for i in 0..m {
        let range = starts[i] as usize..starts[i + 1] as usize;
        let w = pi[i];
        for (v, &j) in e[range.clone()].iter_mut().zip(&data[range]) {
            *v *= w;
            den[j as usize] += *v;
        }
    }
    let log_den = invert_row_totals(den, c, &mut out.pt1);
    let inv = &acc[0][..n];
    for i in 0..m {
        let range = starts[i] as usize..starts[i + 1] as usize;
        let (mut p1, mut a, mut bb, mut cc) = (0.0f32, 0.0f32, 0.0f32, 0.0f32);
        for (v, &j) in e[range.clone()].iter().zip(&data[range]) {
            let j = j as usize;
            let p = v * inv[j];
            p1 += p;
            a = madd::<FMA>(p, x0[j], a);
            bb = madd::<FMA>(p, x1[j], bb);
            cc = madd::<FMA>(p, x2[j], cc);
        }
        out.p1[i] = p1 as f64;
        out.px[i] = [a as f64, bb as f64, cc as f64];
    }
    out.neg_log_likelihood -= log_den.total();
}

/// `dense_rows` in single precision; per-point sums stay in f64. `FMA`: the
/// caller is compiled with fused multiply-add (the distance, the exponential's
/// polynomial and the accumulations each become one instruction per term;
/// measured 17 % off a mug registration).
#[inline(always)]
fn dense_rows_f32<const FMA: bool, const STATS: bool>(job: DenseRows<'_>, k: f32, c: f64) -> f64 {
    let DenseRows { x, ys, pi, row, acc, pt1: pt1_out } = job;
    // The moving points come padded to whole vectors (`load`).
    let m8 = pi.len();
    let (yx, yy, yz, pi) = (&ys[0][..m8], &ys[1][..m8], &ys[2][..m8], &pi[..m8]);
    row.resize(m8, 0.0);
    for a in acc.iter_mut() {
        a.clear();
        a.resize(m8, 0.0);
    }
    let [p1, px0, px1, px2] = acc;
    let (p1, px0, px1, px2) = (&mut p1[..m8], &mut px0[..m8], &mut px1[..m8], &mut px2[..m8]);
    // No closures in here: a closure is its own function, compiled without
    // the caller's target features, and its `mul_add` becomes a library call.
    let mut log_den = LogSum::default();
    for (j, xn) in x.iter().enumerate() {
        let row = &mut row[..m8];
        for ((((r, a), bb), cc), w) in row.iter_mut().zip(yx).zip(yy).zip(yz).zip(pi) {
            *r = affinity::<FMA>(xn, *a, *bb, *cc, *w, k);
        }
        let mut part = [0.0f32; LANES];
        for ch in row.chunks_exact(LANES) {
            for l in 0..LANES {
                part[l] += ch[l];
            }
        }
        let (pt1, inv) = close_row(&part, c, &mut log_den);
        if !STATS {
            continue;
        }
        pt1_out[j] = pt1;
        let inv32 = inv as f32;
        let (w0, w1, w2) = (xn[0] * inv32, xn[1] * inv32, xn[2] * inv32);
        for ((((r, a), bb), cc), d) in
            row.iter().zip(p1.iter_mut()).zip(px0.iter_mut()).zip(px1.iter_mut()).zip(px2.iter_mut())
        {
            *a = madd::<FMA>(*r, inv32, *a);
            *bb = madd::<FMA>(*r, w0, *bb);
            *cc = madd::<FMA>(*r, w1, *cc);
            *d = madd::<FMA>(*r, w2, *d);
        }
    }
    log_den.total()
}

/// A data point's row total with the outlier term `c`, and its inverse.
/// With no outlier term (w = 0) a row can sum to zero: its only listed pairs
/// lie past the cutoff's skin and underflowed (in f32 beyond about 13σ).
/// Such a point is left out, as an outlier would be (inverse 0), where 1/0
/// would make every posterior sum NaN; its likelihood term is the smallest
/// positive total, so the objective stays finite.
#[inline(always)]
fn row_total(sum: f64, c: f64) -> (f64, f64) {
    let den = sum + c;
    if den > 0.0 {
        (den, 1.0 / den)
    } else {
        (f64::MIN_POSITIVE, 0.0)
    }
}

/// Closes one data point's row of the dense f32 sums from its per-lane
/// partial totals: the row total plus the outlier term `c` goes into the
/// likelihood; returns the point's Pᵀ1 entry and the inverse of that total.
#[inline(always)]
fn close_row(part: &[f32; LANES], c: f64, log_den: &mut LogSum) -> (f64, f64) {
    let sum = part.iter().map(|&v| v as f64).sum::<f64>();
    let (den, inv) = row_total(sum, c);
    log_den.add(den);
    (sum * inv, inv)
}

/// The neighbour-list sums' row totals (per data point, in `den`) turned
/// into their inverses with the outlier term `c`, their shares into `pt1`;
/// returns the log-sum of the totals for the likelihood.
#[inline(always)]
fn invert_row_totals(den: &mut [f32], c: f64, pt1: &mut [f64]) -> LogSum {
    let mut log_den = LogSum::default();
    for (d, share) in den.iter_mut().zip(pt1.iter_mut()) {
        let sum = *d as f64;
        let (total, inv) = row_total(sum, c);
        *share = sum * inv;
        log_den.add(total);
        *d = inv as f32;
    }
    log_den
}

/// Σ ln dᵢ over the row totals of an E-step with one logarithm in all
/// (libm's ln is a scalar call: one per row was a tenth of a small
/// registration's E-step, one per eight rows still 2 % of a mug's). Each
/// normal factor splits exactly into its binary exponent, summed as an
/// integer, and its mantissa in [1, 2), multiplied into a running mantissa
/// kept in [1, 2) by exact halvings; the one rounding per factor is the
/// product's. A factor that is zero, subnormal, infinite or NaN is taken
/// as its own logarithm.
struct LogSum {
    /// Σ of the binary exponents taken out.
    exponents: i64,
    /// The running product of mantissas, in [1, 2).
    mantissa: f64,
    /// Logarithms of the factors outside the normal range.
    rest: f64,
}

impl Default for LogSum {
    fn default() -> Self {
        Self { exponents: 0, mantissa: 1.0, rest: 0.0 }
    }
}

impl LogSum {
    const EXPONENT_BITS: u64 = 0x7ff << 52;
    const ONE_BITS: u64 = 1023 << 52;

    #[inline(always)]
    fn add(&mut self, d: f64) {
        let bits = d.to_bits();
        let field = bits & Self::EXPONENT_BITS;
        if d <= 0.0 || field == 0 || field == Self::EXPONENT_BITS {
            self.rest += d.ln();
            return;
        }
        self.exponents += (field >> 52) as i64 - 1023;
        let m = f64::from_bits((bits & !Self::EXPONENT_BITS) | Self::ONE_BITS);
        let p = self.mantissa * m;
        // p < 4: halving is exact.
        (self.mantissa, self.exponents) = if p >= 2.0 { (0.5 * p, self.exponents + 1) } else { (p, self.exponents) };
    }

    fn total(&self) -> f64 {
        self.rest + self.mantissa.ln() + self.exponents as f64 * std::f64::consts::LN_2
    }
}

/// w·2^{k·|x − y|²} for one data point x and one centroid y (k from `exponent_f32`).
#[inline(always)]
fn affinity<const FMA: bool>(x: &[f32; 3], yx: f32, yy: f32, yz: f32, w: f32, k: f32) -> f32 {
    let (dx, dy, dz) = (x[0] - yx, x[1] - yy, x[2] - yz);
    w * exp2_neg_f32::<FMA>(k * madd::<FMA>(dx, dx, madd::<FMA>(dy, dy, dz * dz)))
}

/// The single-precision kernels' k: e^{−d²/2σ²} = 2^{k·d²} with k = −log₂e/2σ².
fn exponent_f32(sigma2: f64) -> f32 {
    (-0.5 * std::f64::consts::LOG2_E / sigma2) as f32
}

/// A coordinate far from any cloud: its affinities are exactly 0.
const FAR_AWAY: f32 = 1e10;

/// A neighbour list laid out for eight-wide sums: each moving point's pairs
/// padded to whole vectors (padding: data index n, a spare slot, at
/// `FAR_AWAY`), and the pairs' data coordinates copied in, so the distances
/// load contiguously instead of through the indices.
#[derive(Clone, Default)]
struct PaddedPairs {
    starts: Vec<u32>,
    data: Vec<u32>,
    x: [Vec<f32>; 3],
}

/// The truncated E-step over padded pairs in AVX2 (`listed_pairs_f32` with
/// vector distances, exponentials and posterior sums; only the row totals
/// are a scalar scatter). Measured: the neighbour-list sums were a quarter
/// of a hammer registration's time.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn padded_pairs_f32_avx2(b: &mut F32Buffers, pp: &PaddedPairs, k: f32, c: f64, out: &mut Posteriors) {
    use std::arch::x86_64::*;
    let F32Buffers { xs, ys, pi, row: e, acc, .. } = b;
    let m = pp.starts.len() - 1;
    let n = xs[0].len();
    let total = pp.data.len();
    assert!(total.is_multiple_of(LANES) && pp.x.iter().all(|v| v.len() == total) && ys[0].len() >= m && pi.len() >= m);
    e.clear();
    e.resize(total, 0.0);
    let (x0, x1, x2) = (pp.x[0].as_ptr(), pp.x[1].as_ptr(), pp.x[2].as_ptr());
    let ep = e.as_mut_ptr();
    let kv = _mm256_set1_ps(k);
    for i in 0..m {
        let (s, t) = (pp.starts[i] as usize, pp.starts[i + 1] as usize);
        let (yx, yy, yz) = (_mm256_set1_ps(ys[0][i]), _mm256_set1_ps(ys[1][i]), _mm256_set1_ps(ys[2][i]));
        let w = _mm256_set1_ps(pi[i]);
        for o in (s..t).step_by(LANES) {
            // SAFETY (loads and stores here): o + 8 ≤ total, every buffer's length.
            let dx = _mm256_sub_ps(_mm256_loadu_ps(x0.add(o)), yx);
            let dy = _mm256_sub_ps(_mm256_loadu_ps(x1.add(o)), yy);
            let dz = _mm256_sub_ps(_mm256_loadu_ps(x2.add(o)), yz);
            let d2 = _mm256_fmadd_ps(dx, dx, _mm256_fmadd_ps(dy, dy, _mm256_mul_ps(dz, dz)));
            _mm256_storeu_ps(ep.add(o), _mm256_mul_ps(w, exp2_neg_f32x8(_mm256_mul_ps(kv, d2))));
        }
    }
    // Row totals per data point (a scatter), then their inverses; slot n is the padding's.
    let den = &mut acc[0];
    den.clear();
    den.resize(n + 1, 0.0);
    // Bounds-checked: an index above n stops here, before the gathers below rely on it.
    for (v, &j) in e.iter().zip(&pp.data) {
        den[j as usize] += *v;
    }
    let log_den = invert_row_totals(&mut den[..n], c, &mut out.pt1);
    den[n] = 0.0;
    let (inv, idx) = (den.as_ptr(), pp.data.as_ptr());
    for i in 0..m {
        let (s, t) = (pp.starts[i] as usize, pp.starts[i + 1] as usize);
        let (mut p1, mut a, mut bb, mut cc) =
            (_mm256_setzero_ps(), _mm256_setzero_ps(), _mm256_setzero_ps(), _mm256_setzero_ps());
        for o in (s..t).step_by(LANES) {
            // SAFETY: every index is at most n (the scatter above checked), and `den` holds n + 1.
            let j = _mm256_loadu_si256(idx.add(o) as *const __m256i);
            let p = _mm256_mul_ps(_mm256_loadu_ps(ep.add(o)), _mm256_i32gather_ps::<4>(inv, j));
            p1 = _mm256_add_ps(p1, p);
            a = _mm256_fmadd_ps(p, _mm256_loadu_ps(x0.add(o)), a);
            bb = _mm256_fmadd_ps(p, _mm256_loadu_ps(x1.add(o)), bb);
            cc = _mm256_fmadd_ps(p, _mm256_loadu_ps(x2.add(o)), cc);
        }
        out.p1[i] = lane_sum(p1) as f64;
        out.px[i] = [lane_sum(a) as f64, lane_sum(bb) as f64, lane_sum(cc) as f64];
    }
    out.neg_log_likelihood -= log_den.total();
}

/// The sum of a vector's eight lanes.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
unsafe fn lane_sum(v: std::arch::x86_64::__m256) -> f32 {
    let mut l = [0.0f32; LANES];
    std::arch::x86_64::_mm256_storeu_ps(l.as_mut_ptr(), v);
    l.iter().sum()
}

/// `dense_rows_f32` written in AVX2 intrinsics, eight moving points a vector,
/// four data points (rows) a block as `avx512::dense_rows` (the reasons are
/// there). By hand because LLVM's loop vectoriser processes 32 points an
/// iteration and leaves the rest to scalar code (the 100-point coarse model
/// spent a tenth of its time on its last 4 points), and its SLP vectoriser
/// does not vectorise the exponential's select when the loop is written per
/// vector. Same operations in the same order as `dense_rows_f32::<true, STATS>`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn dense_rows_f32_avx2<const STATS: bool>(job: DenseRows<'_>, k: f32, c: f64) -> f64 {
    let DenseRows { x, ys, pi, row, acc, pt1: pt1_out } = job;
    let m8 = pi.len();
    assert!(m8.is_multiple_of(LANES) && ys.iter().all(|v| v.len() == m8) && (!STATS || pt1_out.len() == x.len()));
    row.resize(ROW_BLOCK * m8, 0.0);
    for a in acc.iter_mut() {
        a.clear();
        a.resize(m8, 0.0);
    }
    let rows = RowsAvx2 {
        moving: MovingAvx2::new(ys, pi, k),
        c,
        row: row.as_mut_ptr(),
        acc: [acc[0].as_mut_ptr(), acc[1].as_mut_ptr(), acc[2].as_mut_ptr(), acc[3].as_mut_ptr()],
    };
    let mut log_den = LogSum::default();
    let mut blocks = x.chunks_exact(ROW_BLOCK);
    for (i, block) in blocks.by_ref().enumerate() {
        // SAFETY: `rows` points into buffers of the lengths it records.
        let pt1 = rows.block::<ROW_BLOCK, STATS>(block.try_into().expect("a whole block"), &mut log_den);
        if STATS {
            pt1_out[i * ROW_BLOCK..(i + 1) * ROW_BLOCK].copy_from_slice(&pt1);
        }
    }
    let done = x.len() - blocks.remainder().len();
    for (i, xn) in blocks.remainder().iter().enumerate() {
        // SAFETY: as above.
        let pt1 = rows.block::<1, STATS>(&[*xn], &mut log_den);
        if STATS {
            pt1_out[done + i] = pt1[0];
        }
    }
    log_den.total()
}

/// A dense single-precision pass on the widest kernel `simd` allows.
fn dense_f32_rows<const STATS: bool>(simd: Simd, job: DenseRows<'_>, k: f32, c: f64) -> f64 {
    #[cfg(target_arch = "x86_64")]
    {
        // SAFETY: `simd` comes from `Simd::detect` (or a test that checked
        // the CPU): the CPU runs what these are compiled for.
        match simd {
            Simd::Avx512 => return unsafe { avx512::dense_rows::<STATS>(job, k, c) },
            Simd::Avx2 => return unsafe { dense_rows_f32_avx2::<STATS>(job, k, c) },
            Simd::Portable => {}
        }
    }
    let _ = simd;
    dense_rows_f32::<false, STATS>(job, k, c)
}

/// Adds the single-precision posterior sums (P1, PX as three columns) of
/// the first `m` moving points to `out` (zeroed by `run_weighted`): one
/// pass's sums, or each chunk's in turn.
fn add_posterior_sums(acc: &[Vec<f32>; 4], m: usize, out: &mut Posteriors) {
    let [p1, px0, px1, px2] = acc;
    for i in 0..m {
        out.p1[i] += p1[i] as f64;
        let px = &mut out.px[i];
        px[0] += px0[i] as f64;
        px[1] += px1[i] as f64;
        px[2] += px2[i] as f64;
    }
}

/// Data points a block of the dense kernels takes.
const ROW_BLOCK: usize = 4;

/// The moving points (three columns) and their weights, `m8` long, with the
/// exponent's factor k: what every dense AVX2 kernel reads.
#[cfg(target_arch = "x86_64")]
struct MovingAvx2 {
    y: [*const f32; 3],
    w: *const f32,
    m8: usize,
    k: std::arch::x86_64::__m256,
}

#[cfg(target_arch = "x86_64")]
impl MovingAvx2 {
    /// # Safety
    /// The CPU has AVX.
    #[target_feature(enable = "avx2,fma")]
    unsafe fn new(ys: &[Vec<f32>; 3], pi: &[f32], k: f32) -> Self {
        let m8 = pi.len();
        Self {
            y: [ys[0].as_ptr(), ys[1].as_ptr(), ys[2].as_ptr()],
            w: pi.as_ptr(),
            m8,
            k: std::arch::x86_64::_mm256_set1_ps(k),
        }
    }

    /// The moving points' three coordinates and their weights at `o`.
    ///
    /// # Safety
    /// o + 8 ≤ m8; the CPU has AVX2.
    #[target_feature(enable = "avx2,fma")]
    #[inline]
    unsafe fn at(&self, o: usize) -> [std::arch::x86_64::__m256; 4] {
        use std::arch::x86_64::*;
        [
            _mm256_loadu_ps(self.y[0].add(o)),
            _mm256_loadu_ps(self.y[1].add(o)),
            _mm256_loadu_ps(self.y[2].add(o)),
            _mm256_loadu_ps(self.w.add(o)),
        ]
    }

    /// w·2^{k·|x − y|²} for the broadcast data point `x` and the moving points `yw` (from `at`).
    ///
    /// # Safety
    /// The CPU has AVX2 and FMA.
    #[target_feature(enable = "avx2,fma")]
    #[inline]
    unsafe fn affinity(
        &self,
        x: &[std::arch::x86_64::__m256; 3],
        yw: &[std::arch::x86_64::__m256; 4],
    ) -> std::arch::x86_64::__m256 {
        use std::arch::x86_64::*;
        let (dx, dy, dz) = (_mm256_sub_ps(x[0], yw[0]), _mm256_sub_ps(x[1], yw[1]), _mm256_sub_ps(x[2], yw[2]));
        let d2 = _mm256_fmadd_ps(dx, dx, _mm256_fmadd_ps(dy, dy, _mm256_mul_ps(dz, dz)));
        _mm256_mul_ps(yw[3], exp2_neg_f32x8(_mm256_mul_ps(self.k, d2)))
    }

    /// Per data point of `xs`: Σₘ aₘ and Σₘ aₘ yₘ over its affinities aₘ
    /// (`dense_centroids_f32_avx2`'s block).
    ///
    /// # Safety
    /// The pointers hold the lengths `MovingAvx2` records; the CPU has AVX2 and FMA.
    #[target_feature(enable = "avx2,fma")]
    #[inline]
    unsafe fn centroid_block<const B: usize>(&self, xs: &[[f32; 3]; B]) -> [[f64; 4]; B] {
        use std::arch::x86_64::*;
        // No closures here (see `RowsAvx2::block`).
        let xv = broadcast_avx2(xs);
        let mut acc = [[_mm256_setzero_ps(); 4]; B];
        for o in (0..self.m8).step_by(LANES) {
            let yw = self.at(o);
            for b in 0..B {
                let v = self.affinity(&xv[b], &yw);
                acc[b][0] = _mm256_add_ps(acc[b][0], v);
                acc[b][1] = _mm256_fmadd_ps(v, yw[0], acc[b][1]);
                acc[b][2] = _mm256_fmadd_ps(v, yw[1], acc[b][2]);
                acc[b][3] = _mm256_fmadd_ps(v, yw[2], acc[b][3]);
            }
        }
        let mut totals = [[0.0; 4]; B];
        for b in 0..B {
            for i in 0..4 {
                let mut lanes = [0.0f32; LANES];
                _mm256_storeu_ps(lanes.as_mut_ptr(), acc[b][i]);
                let mut sum = 0.0;
                for l in lanes {
                    sum += l as f64;
                }
                totals[b][i] = sum;
            }
        }
        totals
    }
}

/// The `B` data points `xs`, each coordinate on every lane.
///
/// # Safety
/// The CPU has AVX.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn broadcast_avx2<const B: usize>(xs: &[[f32; 3]; B]) -> [[std::arch::x86_64::__m256; 3]; B] {
    use std::arch::x86_64::*;
    let mut xv = [[_mm256_setzero_ps(); 3]; B];
    for b in 0..B {
        for i in 0..3 {
            xv[b][i] = _mm256_set1_ps(xs[b][i]);
        }
    }
    xv
}

/// `dense_rows_f32_avx2`'s buffers: the moving points, and `ROW_BLOCK` rows
/// and the four sums (P1, PX as three columns), each `m8` long.
#[cfg(target_arch = "x86_64")]
struct RowsAvx2 {
    moving: MovingAvx2,
    c: f64,
    row: *mut f32,
    acc: [*mut f32; 4],
}

#[cfg(target_arch = "x86_64")]
impl RowsAvx2 {
    /// As `avx512::Rows::block`, on eight lanes.
    ///
    /// # Safety
    /// The pointers hold the lengths `RowsAvx2` records; B ≤ `ROW_BLOCK`; the
    /// CPU has AVX2 and FMA.
    #[target_feature(enable = "avx2,fma")]
    #[inline]
    unsafe fn block<const B: usize, const STATS: bool>(&self, xs: &[[f32; 3]; B], log_den: &mut LogSum) -> [f64; B] {
        use std::arch::x86_64::*;
        // No closures in here: a closure is compiled without this function's
        // target features, and each intrinsic in it becomes a call.
        let m8 = self.moving.m8;
        let xv = broadcast_avx2(xs);
        let mut part = [_mm256_setzero_ps(); B];
        for o in (0..m8).step_by(LANES) {
            // SAFETY (loads and stores here): o + 8 ≤ m8; each row holds m8 from b·m8.
            let yw = self.moving.at(o);
            for b in 0..B {
                let v = self.moving.affinity(&xv[b], &yw);
                _mm256_storeu_ps(self.row.add(b * m8 + o), v);
                part[b] = _mm256_add_ps(part[b], v);
            }
        }
        let mut pt1 = [0.0; B];
        let mut scale = [[_mm256_setzero_ps(); 4]; B];
        for b in 0..B {
            let mut lanes = [0.0f32; LANES];
            _mm256_storeu_ps(lanes.as_mut_ptr(), part[b]);
            let (share, inv) = close_row(&lanes, self.c, log_den);
            pt1[b] = share;
            let inv32 = inv as f32;
            scale[b] = [
                _mm256_set1_ps(inv32),
                _mm256_set1_ps(xs[b][0] * inv32),
                _mm256_set1_ps(xs[b][1] * inv32),
                _mm256_set1_ps(xs[b][2] * inv32),
            ];
        }
        if STATS {
            for o in (0..m8).step_by(LANES) {
                // SAFETY: the sums and each row hold m8.
                let mut sums = [_mm256_setzero_ps(); 4];
                for i in 0..4 {
                    sums[i] = _mm256_loadu_ps(self.acc[i].add(o));
                }
                for b in 0..B {
                    let v = _mm256_loadu_ps(self.row.add(b * m8 + o));
                    for i in 0..4 {
                        sums[i] = _mm256_fmadd_ps(v, scale[b][i], sums[i]);
                    }
                }
                for i in 0..4 {
                    _mm256_storeu_ps(self.acc[i].add(o), sums[i]);
                }
            }
        }
        pt1
    }
}

/// `EStep::centroid_shift`'s sums over the dense pairs in AVX2: per data
/// row its total and the affinity-weighted sum of the moving points, closed
/// into Σₙ pt1ₙ xₙ (with `x`, the data in double precision), Σₘₙ Pₘₙ yₘ and
/// Np; four data points a block (see `avx512::dense_centroids`).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn dense_centroids_f32_avx2(b: &F32Buffers, x: &[P3], k: f32, c: f64) -> ([f64; 3], [f64; 3], f64) {
    let F32Buffers { x: x32, ys, pi, .. } = b;
    let m8 = pi.len();
    assert!(m8.is_multiple_of(LANES) && ys.iter().all(|v| v.len() == m8) && x32.len() == x.len());
    let moving = MovingAvx2::new(ys, pi, k);
    let mut sums = [[0.0; 3], [0.0; 3]];
    let mut np = 0.0;
    for (block, block64) in x32.chunks_exact(ROW_BLOCK).zip(x.chunks_exact(ROW_BLOCK)) {
        // SAFETY: `moving` points into buffers of the lengths it records.
        let totals = moving.centroid_block::<ROW_BLOCK>(block.try_into().expect("a whole block"));
        close_centroid_rows(&totals, block64, c, &mut sums, &mut np);
    }
    let done = x.len() - x.len() % ROW_BLOCK;
    for (xn, x64) in x32[done..].iter().zip(&x[done..]) {
        // SAFETY: as above.
        let totals = moving.centroid_block::<1>(&[*xn]);
        close_centroid_rows(&totals, std::slice::from_ref(x64), c, &mut sums, &mut np);
    }
    let [mx, my] = sums;
    (mx, my, np)
}

/// Per data point, its row total and the affinity-weighted sum of the moving
/// points, closed into Σₙ pt1ₙ xₙ (`sums[0]`), Σₘₙ Pₘₙ yₘ (`sums[1]`) and Np.
fn close_centroid_rows(totals: &[[f64; 4]], x: &[P3], c: f64, sums: &mut [[f64; 3]; 2], np: &mut f64) {
    for (t, xn) in totals.iter().zip(x) {
        let (_, inv) = row_total(t[0], c);
        let pt1 = t[0] * inv;
        *np += pt1;
        for d in 0..3 {
            sums[0][d] += pt1 * xn[d];
            sums[1][d] += t[d + 1] * inv;
        }
    }
}

/// `exp2_neg_f32::<true>` on eight lanes.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn exp2_neg_f32x8(t: std::arch::x86_64::__m256) -> std::arch::x86_64::__m256 {
    use std::arch::x86_64::*;
    const MAGIC: f32 = 12582912.0; // 1.5·2²³
    let cut = _mm256_set1_ps(EXP2_CUT_F32);
    let magic = _mm256_set1_ps(MAGIC);
    let below = _mm256_cmp_ps::<_CMP_LT_OQ>(t, cut);
    let t = _mm256_max_ps(t, cut);
    let r = _mm256_add_ps(t, magic);
    let n = _mm256_sub_ps(r, magic);
    let f = _mm256_sub_ps(t, n);
    let mut p = _mm256_set1_ps(EXP2_SERIES_F32[0]);
    for c in &EXP2_SERIES_F32[1..] {
        p = _mm256_fmadd_ps(p, f, _mm256_set1_ps(*c));
    }
    let ni = _mm256_sub_epi32(_mm256_castps_si256(r), _mm256_castps_si256(magic));
    let scale = _mm256_castsi256_ps(_mm256_slli_epi32::<23>(_mm256_add_epi32(ni, _mm256_set1_epi32(127))));
    _mm256_andnot_ps(below, _mm256_mul_ps(p, scale))
}

/// The uniform outlier term of CPD: (2πσ²)^{3/2} · w/(1−w) · M/N.
pub fn outlier_constant(sigma2: f64, w: f64, m: usize, n: usize) -> f64 {
    let w = w.clamp(0.0, 0.999);
    (2.0 * std::f64::consts::PI * sigma2).powf(1.5) * w / (1.0 - w) * m as f64 / n as f64
}

/// Mean squared distance over all pairs / 3: CPD's initial σ², in O(M + N).
pub fn initial_sigma2(x: &[P3], y: &[P3]) -> f64 {
    let (n, m) = (x.len() as f64, y.len() as f64);
    if n == 0.0 || m == 0.0 {
        return 1.0;
    }
    let sx = x.iter().fold([0.0; 3], |a, p| [a[0] + p[0], a[1] + p[1], a[2] + p[2]]);
    let sy = y.iter().fold([0.0; 3], |a, p| [a[0] + p[0], a[1] + p[1], a[2] + p[2]]);
    let xx: f64 = x.iter().map(|p| dot(p, p)).sum();
    let yy: f64 = y.iter().map(|p| dot(p, p)).sum();
    ((m * xx + n * yy - 2.0 * dot(&sx, &sy)) / (3.0 * m * n)).max(1e-12)
}

#[inline]
pub fn dot(a: &P3, b: &P3) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

#[inline]
pub fn dist2(a: &P3, b: &P3) -> f64 {
    let (dx, dy, dz) = (a[0] - b[0], a[1] - b[1], a[2] - b[2]);
    dx * dx + dy * dy + dz * dz
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    fn cloud(n: usize, seed: u64) -> Vec<P3> {
        let mut r = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        (0..n).map(|_| [r.random::<f64>(), r.random::<f64>(), r.random::<f64>()]).collect()
    }

    /// The textbook E-step with the full matrix, as the reference.
    fn reference(x: &[P3], y: &[P3], s2: f64, w: f64) -> Posteriors {
        let c = outlier_constant(s2, w, y.len(), x.len());
        let mut out = Posteriors {
            p1: vec![0.0; y.len()],
            pt1: vec![0.0; x.len()],
            px: vec![[0.0; 3]; y.len()],
            ..Default::default()
        };
        for (j, xn) in x.iter().enumerate() {
            let g: Vec<f64> = y.iter().map(|ym| (-dist2(xn, ym) / (2.0 * s2)).exp()).collect();
            let den: f64 = g.iter().sum::<f64>() + c;
            for (i, gi) in g.iter().enumerate() {
                let p = gi / den;
                out.p1[i] += p;
                out.pt1[j] += p;
                for d in 0..3 {
                    out.px[i][d] += p * xn[d];
                }
            }
        }
        out.np = out.p1.iter().sum();
        out
    }

    /// Relative closeness (absolute below 1).
    fn assert_close(a: &Posteriors, b: &Posteriors, tol: f64) {
        let close = |u: f64, v: f64| (u - v).abs() < tol * v.abs().max(1.0);
        for (u, v) in a.p1.iter().zip(&b.p1) {
            assert!(close(*u, *v), "p1 {u} vs {v}");
        }
        for (u, v) in a.pt1.iter().zip(&b.pt1) {
            assert!(close(*u, *v), "pt1 {u} vs {v}");
        }
        for (u, v) in a.px.iter().zip(&b.px) {
            for d in 0..3 {
                assert!(close(u[d], v[d]), "px {u:?} vs {v:?}");
            }
        }
        assert!(close(a.np, b.np));
    }

    /// With no outlier term (w = 0), a data point no moving point reaches
    /// (its affinities underflow) is left out instead of turning every sum
    /// into NaN: the rest match the textbook E-step without it.
    #[test]
    fn a_data_point_nothing_reaches_is_left_out_without_an_outlier_term() {
        let y = cloud(200, 6);
        let mut x = cloud(300, 5);
        x[17] = [1e3, -1e3, 1e3];
        let without: Vec<P3> = x.iter().enumerate().filter(|&(j, _)| j != 17).map(|(_, p)| *p).collect();
        for single_precision in [false, true] {
            for sigma2 in [0.05, 1e-4] {
                let mut e = EStep::new(&x);
                e.single_precision = single_precision;
                let mut out = Posteriors::default();
                e.run(&y, sigma2, 0.0, &mut out);
                assert!(out.np.is_finite() && out.neg_log_likelihood.is_finite(), "{single_precision} {sigma2}");
                assert_eq!(out.pt1[17], 0.0);
                let mut alone = EStep::new(&without);
                alone.single_precision = single_precision;
                let mut want = Posteriors::default();
                alone.run(&y, sigma2, 0.0, &mut want);
                let tol = if single_precision { 1e-4 } else { 1e-9 };
                assert!(
                    (out.np - want.np).abs() < tol * want.np,
                    "{single_precision} {sigma2}: {} vs {}",
                    out.np,
                    want.np
                );
                for (u, v) in out.p1.iter().zip(&want.p1) {
                    assert!((u - v).abs() < tol * v.abs().max(1.0), "{single_precision} {sigma2}: p1 {u} vs {v}");
                }
            }
        }
    }

    /// A neighbour list that would exceed its budget is not built: the
    /// E-step stays dense (the same bits as one that never truncates), and
    /// a later, smaller σ lists its pairs as before.
    #[test]
    fn a_neighbour_list_over_budget_is_not_built() {
        let (x, y) = (cloud(6000, 7), cloud(6000, 8));
        let sigma2 = 0.05f64 * 0.05;
        let mut e = EStep::new(&x);
        assert!(e.truncates(sigma2), "the test needs the truncated regime");
        let mut out = Posteriors::default();
        e.run(&y, sigma2, 0.1, &mut out);
        assert!(e.list.data.is_empty(), "{} pairs listed", e.list.data.len());
        let mut dense = EStep::new(&x);
        dense.truncate_below = 0.0;
        let mut want = Posteriors::default();
        dense.run(&y, sigma2, 0.1, &mut want);
        assert!(out.p1.iter().zip(&want.p1).all(|(a, b)| a.to_bits() == b.to_bits()));
        assert_eq!(out.neg_log_likelihood.to_bits(), want.neg_log_likelihood.to_bits());
        // At σ = 0.01 the pairs fit (about 0.7 % of the cube around each point).
        e.run(&y, 1e-4, 0.1, &mut out);
        assert!(!e.list.data.is_empty() && e.list.data.len() <= max_listed_pairs(6000, 6000));
        assert_close(&out, &reference(&x, &y, 1e-4, 0.1), 1e-6);
    }

    #[test]
    fn dense_matches_the_textbook_e_step() {
        let (x, y) = (cloud(50, 1), cloud(40, 2));
        let mut e = EStep::new(&x);
        let mut out = Posteriors::default();
        e.run(&y, 0.05, 0.1, &mut out);
        assert_close(&out, &reference(&x, &y, 0.05, 0.1), 1e-10);
    }

    #[test]
    fn single_precision_matches_the_textbook_e_step() {
        let (x, y) = (cloud(300, 5), cloud(200, 6));
        let mut e = EStep::new(&x);
        e.single_precision = true;
        let mut out = Posteriors::default();
        e.run(&y, 0.05, 0.1, &mut out);
        assert_close(&out, &reference(&x, &y, 0.05, 0.1), 1e-4);
    }

    /// The kernel levels this CPU runs (each at most once).
    fn simd_levels() -> Vec<Simd> {
        let mut levels: Vec<Simd> = [Simd::Portable, Simd::Avx2, Simd::Avx512].map(Simd::detect).to_vec();
        levels.dedup();
        levels
    }

    #[test]
    fn every_single_precision_kernel_matches_the_textbook_e_step() {
        // 203 moving points: not a whole number of vectors (a masked tail in AVX-512).
        let (x, y) = (cloud(300, 5), cloud(203, 6));
        for simd in simd_levels() {
            // Dense (large σ) and truncated (small σ) regimes.
            for (s2, truncated) in [(0.05, false), (4e-4, true)] {
                let mut e = EStep::new(&x);
                e.single_precision = true;
                e.simd = simd;
                let mut out = Posteriors::default();
                e.run(&y, s2, 0.1, &mut out);
                assert_eq!(!e.list.data.is_empty(), truncated, "σ² {s2}");
                assert_close(&out, &reference(&x, &y, s2, 0.1), 1e-4);
                let nll = e.neg_log_likelihood(&y, None, s2, 0.1);
                assert!((nll - out.neg_log_likelihood).abs() < 1e-6 * nll.abs().max(1.0), "{simd:?}, σ² {s2}");
            }
        }
    }

    /// The dense single-precision E-step split over the pool in chunks of
    /// data rows (CPD's `parallel_rows`) gives the textbook sums on every
    /// kernel level, and the same bits on 1 and 3 threads; a row count that
    /// is no whole number of chunks or blocks (1,001) leaves a short last chunk.
    #[test]
    fn the_split_dense_e_step_matches_the_textbook_one_on_any_thread_count() {
        let (x, y) = (cloud(1001, 21), cloud(203, 22));
        assert!(dense_chunks(x.len()).0 > 1, "the test must split");
        for simd in simd_levels() {
            let run = |threads: usize| {
                let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().expect("a pool");
                pool.install(|| {
                    let mut e = EStep::new(&x);
                    (e.single_precision, e.parallel_rows, e.simd) = (true, true, simd);
                    let mut out = Posteriors::default();
                    e.run(&y, 0.05, 0.1, &mut out);
                    out
                })
            };
            let (one, three) = (run(1), run(3));
            assert_close(&one, &reference(&x, &y, 0.05, 0.1), 1e-4);
            assert!(
                one.p1 == three.p1 && one.px == three.px && one.pt1 == three.pt1,
                "{simd:?}: the sums depend on the thread count"
            );
            assert_eq!(one.neg_log_likelihood, three.neg_log_likelihood);
        }
    }

    #[test]
    fn centroid_shift_matches_the_posteriors_in_every_kernel() {
        // 203 moving points (not a whole number of vectors), with weights.
        let (x, y) = (cloud(300, 13), cloud(203, 14));
        let weights: Vec<f64> = (0..y.len()).map(|i| if i % 4 == 0 { 0.05 } else { 1.0 }).collect();
        let s2 = 0.05;
        // The textbook posteriors, in double precision.
        let mut e = EStep::new(&x);
        let mut post = Posteriors::default();
        e.run_weighted(&y, Some(&weights), s2, 0.1, &mut post);
        let mut want = [0.0; 3];
        for d in 0..3 {
            let mx: f64 = x.iter().zip(&post.pt1).map(|(p, w)| w * p[d]).sum();
            let my: f64 = y.iter().zip(&post.p1).map(|(p, w)| w * p[d]).sum();
            want[d] = (mx - my) / post.np;
        }
        for simd in simd_levels() {
            let mut e = EStep::new(&x);
            e.single_precision = true;
            e.simd = simd;
            let got = e.centroid_shift(&y, Some(&weights), s2, 0.1).unwrap();
            for d in 0..3 {
                assert!((got[d] - want[d]).abs() < 1e-5, "{simd:?}: {got:?} vs {want:?}");
            }
        }
        // Nothing explained: no shift.
        let far: Vec<P3> = y.iter().map(|p| [p[0] + 100.0, p[1], p[2]]).collect();
        assert_eq!(EStep::new(&x).centroid_shift(&far, None, 1e-4, 0.1), None);
    }

    #[test]
    fn likelihood_alone_matches_the_full_e_step() {
        let (x, y) = (cloud(300, 5), cloud(200, 6));
        let weights: Vec<f64> = (0..y.len()).map(|i| if i % 3 == 0 { 0.1 } else { 1.3 }).collect();
        for single in [false, true] {
            // Dense (large σ) and truncated (small σ) regimes.
            for s2 in [0.05, 1e-4] {
                let mut e = EStep::new(&x);
                e.single_precision = single;
                let mut out = Posteriors::default();
                e.run_weighted(&y, Some(&weights), s2, 0.1, &mut out);
                let alone = e.neg_log_likelihood(&y, Some(&weights), s2, 0.1);
                let tol = 1e-6 * out.neg_log_likelihood.abs().max(1.0);
                assert!(
                    (alone - out.neg_log_likelihood).abs() < tol,
                    "single {single}, σ² {s2}: {alone} vs {}",
                    out.neg_log_likelihood
                );
            }
        }
    }

    #[test]
    fn truncated_matches_the_textbook_e_step_at_small_sigma() {
        let (x, y) = (cloud(3000, 3), cloud(500, 4));
        let s2 = 0.0004; // σ = 2 cm in a unit cube: truncated mode
        let mut e = EStep::new(&x);
        let mut out = Posteriors::default();
        e.run(&y, s2, 0.1, &mut out);
        assert_close(&out, &reference(&x, &y, s2, 0.1), 1e-7);
    }

    #[test]
    fn single_precision_truncated_matches_the_textbook_e_step() {
        let (x, y) = (cloud(2000, 7), cloud(400, 8));
        let s2 = 0.0004;
        let mut e = EStep::new(&x);
        e.single_precision = true;
        let mut out = Posteriors::default();
        e.run(&y, s2, 0.1, &mut out);
        assert!(!e.list.data.is_empty(), "truncated mode was not used");
        assert_close(&out, &reference(&x, &y, s2, 0.1), 1e-4);
    }

    #[test]
    fn neighbour_list_is_kept_over_small_moves_and_rebuilt_after_large_ones() {
        let (x, mut y) = (cloud(3000, 9), cloud(300, 10));
        let s2 = 0.0004;
        for single_precision in [false, true] {
            let mut e = EStep::new(&x);
            e.single_precision = single_precision;
            let mut out = Posteriors::default();
            e.run(&y, s2, 0.1, &mut out);
            let built = e.list.y_built.clone();
            // A shift well inside the skin (0.3 × 8σ = 4.8 cm here): the list stays.
            y.iter_mut().for_each(|p| p[0] += 0.002);
            e.run(&y, s2, 0.1, &mut out);
            assert_eq!(e.list.y_built, built, "list rebuilt after a small move");
            let tol = if single_precision { 1e-4 } else { 1e-7 };
            assert_close(&out, &reference(&x, &y, s2, 0.1), tol);
            // A shift past the skin: the list is rebuilt and the result still exact.
            y.iter_mut().for_each(|p| p[1] += 0.1);
            e.run(&y, s2, 0.1, &mut out);
            assert_ne!(e.list.y_built, built, "list kept after a large move");
            assert_close(&out, &reference(&x, &y, s2, 0.1), tol);
        }
    }

    #[test]
    fn a_list_loosened_by_a_shrinking_sigma_is_trimmed_not_rebuilt() {
        let (x, mut y) = (cloud(3000, 11), cloud(300, 12));
        for single_precision in [false, true] {
            let mut e = EStep::new(&x);
            e.single_precision = single_precision;
            let mut out = Posteriors::default();
            e.run(&y, 4e-4, 0.1, &mut out);
            let (built, pairs) = (e.list.y_built.clone(), e.list.data.len());
            // σ halved and a small move: the list covers the pairs but is twice too wide.
            y.iter_mut().for_each(|p| p[2] += 0.001);
            e.run(&y, 1e-4, 0.1, &mut out);
            assert_eq!(e.list.y_built, built, "list rebuilt instead of trimmed");
            assert!(e.list.data.len() < pairs / 2, "list not trimmed: {} of {pairs} pairs", e.list.data.len());
            let tol = if single_precision { 1e-4 } else { 1e-7 };
            assert_close(&out, &reference(&x, &y, 1e-4, 0.1), tol);
            // Further iterations on the trimmed list stay exact.
            y.iter_mut().for_each(|p| p[0] -= 0.001);
            e.run(&y, 1e-4, 0.1, &mut out);
            assert_close(&out, &reference(&x, &y, 1e-4, 0.1), tol);
        }
    }
    #[test]
    fn log_sum_matches_the_sum_of_logarithms_over_any_range() {
        let mut r = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        let mut d: Vec<f64> = (0..1001).map(|_| 10f64.powf(r.random::<f64>() * 120.0 - 60.0)).collect();
        // Past the normal range too: subnormal and huge.
        d.extend([1e-310, 3e-320, 1e300, 1e305, 1e308, 1.999_999_999_999_999_8]);
        let mut l = LogSum::default();
        d.iter().for_each(|&v| l.add(v));
        let want: f64 = d.iter().map(|v| v.ln()).sum();
        assert!((l.total() - want).abs() < 1e-12 * want.abs().max(1.0), "{} vs {want}", l.total());
        // A row nothing reached at all.
        l.add(0.0);
        assert_eq!(l.total(), f64::NEG_INFINITY);
    }
}
