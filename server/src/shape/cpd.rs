//! Coherent Point Drift (Myronenko & Song, 2010): rigid (with scale) and
//! non-rigid registration of a moving point set Y onto data X.
//!
//! Our own implementation because it is the core of the product and the
//! public ones fall short in the ways method.md lists: they store the dense
//! M×N posterior (out of memory at tens of thousands of points), take β in
//! absolute units (a shape space of metre-sized tools turns rigid), and run
//! the full O(M³) solve every iteration.
//!
//! Both clouds are mapped by one similarity (the source's centroid and RMS
//! radius) into normalised coordinates, so β, λ and the outlier weight mean the
//! same thing for a mug and a hammer; results come back in the caller's units.

use super::estep::{dot, initial_sigma2, EStep, Posteriors, P3};
use super::kernel::{gaussian, LowRankKernel};
use super::mstep::{self, LowRankFactor};
use crate::simd::clear_upper_state;
use faer::prelude::*;
use faer::Side;
use nalgebra::{Matrix3, Point3, Vector3};
use std::borrow::Cow;
use std::time::Instant;

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum CpdError {
    #[error("{which} cloud is empty")]
    Empty { which: &'static str },
    #[error("{which} cloud has a non-finite coordinate at point {index}")]
    NonFinite { which: &'static str, index: usize },
    #[error("{which} cloud has all its points at one place (no extent to register)")]
    Degenerate { which: &'static str },
    #[error("invalid parameter {name} = {value}: {why}")]
    BadParameter { name: &'static str, value: f64, why: &'static str },
    #[error("the clouds lost all correspondence (every point an outlier); check units and overlap")]
    NoCorrespondence,
}

/// Options shared by every CPD variant.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct EmOptions {
    /// Outlier weight w in [0, 1).
    pub w: f64,
    pub max_iters: usize,
    /// Stop when the relative change of the negative log-likelihood falls below this (0: run all iterations).
    pub tol: f64,
}

impl Default for EmOptions {
    fn default() -> Self {
        Self { w: 0.1, max_iters: 150, tol: 1e-5 }
    }
}

impl EmOptions {
    fn validate(&self) -> Result<(), CpdError> {
        if !(0.0..1.0).contains(&self.w) {
            return Err(CpdError::BadParameter { name: "w", value: self.w, why: "must lie in [0, 1)" });
        }
        if !(self.tol >= 0.0) {
            return Err(CpdError::BadParameter { name: "tol", value: self.tol, why: "must be ≥ 0" });
        }
        Ok(())
    }
}

/// The similarity into CPD's normalised coordinates: p ↦ (p − centre) / scale.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Normalization {
    pub centre: [f64; 3],
    pub scale: f64,
}

impl Normalization {
    /// Centroid and RMS radius of `pts`.
    pub fn of(pts: &[P3]) -> Self {
        let n = pts.len().max(1) as f64;
        let c = pts.iter().fold([0.0; 3], |a, p| [a[0] + p[0] / n, a[1] + p[1] / n, a[2] + p[2] / n]);
        let r2 = pts.iter().map(|p| super::estep::dist2(p, &c)).sum::<f64>() / n;
        Self { centre: c, scale: r2.sqrt().max(1e-300) }
    }
    pub fn forward(&self, p: &P3) -> P3 {
        let c = &self.centre;
        [(p[0] - c[0]) / self.scale, (p[1] - c[1]) / self.scale, (p[2] - c[2]) / self.scale]
    }
    pub fn inverse(&self, p: &P3) -> P3 {
        let c = &self.centre;
        [p[0] * self.scale + c[0], p[1] * self.scale + c[1], p[2] * self.scale + c[2]]
    }
}

pub fn to_p3(pts: &[Point3<f64>]) -> Vec<P3> {
    pts.iter().map(|p| [p.x, p.y, p.z]).collect()
}

pub fn to_points(pts: &[P3]) -> Vec<Point3<f64>> {
    pts.iter().map(|p| Point3::new(p[0], p[1], p[2])).collect()
}

/// Checks a cloud from outside: non-empty, finite, with extent.
pub fn check_cloud(which: &'static str, pts: &[P3]) -> Result<(), CpdError> {
    if pts.is_empty() {
        return Err(CpdError::Empty { which });
    }
    if let Some(index) = pts.iter().position(|p| !p.iter().all(|x| x.is_finite())) {
        return Err(CpdError::NonFinite { which, index });
    }
    let n = Normalization::of(pts);
    let extent = pts.iter().map(|p| p.iter().fold(0.0f64, |a, x| a.max(x.abs()))).fold(0.0, f64::max);
    if !(n.scale > 1e-12 * extent.max(1e-300)) || n.scale < 1e-9 {
        return Err(CpdError::Degenerate { which });
    }
    Ok(())
}

/// How an EM run ended.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct EmReport {
    pub iterations: usize,
    pub converged: bool,
    /// Final σ² in the caller's units (m²).
    pub sigma2: f64,
    pub elapsed_ms: f64,
}

// ---------------------------------------------------------------- rigid

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RigidOptions {
    pub em: EmOptions,
    /// Estimate a uniform scale too (similarity transform).
    pub scale: bool,
}

impl Default for RigidOptions {
    fn default() -> Self {
        Self { em: EmOptions::default(), scale: true }
    }
}

/// target ≈ scale · rotation · source + translation (caller's units).
#[derive(Clone, Debug)]
pub struct RigidResult {
    pub rotation: Matrix3<f64>,
    pub translation: Vector3<f64>,
    pub scale: f64,
    pub moved: Vec<Point3<f64>>,
    pub report: EmReport,
}

pub fn rigid(source: &[Point3<f64>], target: &[Point3<f64>], opts: &RigidOptions) -> Result<RigidResult, CpdError> {
    rigid_reporting(source, target, opts, &mut |_| {})
}

/// As [`rigid`], calling `on_iteration` with the count of EM iterations
/// done after each (a progress bar's feed).
pub fn rigid_reporting(
    source: &[Point3<f64>],
    target: &[Point3<f64>],
    opts: &RigidOptions,
    on_iteration: &mut dyn FnMut(usize),
) -> Result<RigidResult, CpdError> {
    let t0 = Instant::now();
    opts.em.validate()?;
    let (ys, xs) = (to_p3(source), to_p3(target));
    check_cloud("source", &ys)?;
    check_cloud("target", &xs)?;
    let norm = Normalization::of(&ys);
    let y0: Vec<P3> = ys.iter().map(|p| norm.forward(p)).collect();
    let x: Vec<P3> = xs.iter().map(|p| norm.forward(p)).collect();
    let mut estep = EStep::new(&x);
    let mut post = Posteriors::default();
    let (mut r, mut t, mut s) = (Matrix3::identity(), Vector3::zeros(), 1.0);
    let mut y = y0.clone();
    let mut sigma2 = initial_sigma2(&x, &y);
    let (mut prev, mut iterations, mut converged) = (f64::INFINITY, 0, false);
    while iterations < opts.em.max_iters {
        iterations += 1;
        estep.run(&y, sigma2, opts.em.w, &mut post);
        if !(post.np > 1e-9) {
            return Err(CpdError::NoCorrespondence);
        }
        let step = weighted_similarity(&x, &y0, &post, opts.scale);
        (r, t, s) = (step.rotation, step.translation, step.scale);
        sigma2 = step.sigma2.max(1e-10);
        for (yi, y0i) in y.iter_mut().zip(&y0) {
            let p = s * (r * Vector3::from(*y0i)) + t;
            *yi = [p.x, p.y, p.z];
        }
        on_iteration(iterations);
        let nll = post.neg_log_likelihood;
        if opts.em.tol > 0.0 && ((prev - nll).abs() <= opts.em.tol * nll.abs().max(1e-12) || sigma2 <= 1e-10) {
            converged = true;
            break;
        }
        prev = nll;
    }
    // Back to caller units: x = n⁻¹(s R n(y) + t) ⇒ translation absorbs the centres.
    let c = Vector3::from(norm.centre);
    let translation = c + t * norm.scale - s * (r * c);
    let moved = to_points(&y.iter().map(|p| norm.inverse(p)).collect::<Vec<_>>());
    Ok(RigidResult {
        rotation: r,
        translation,
        scale: s,
        moved,
        report: EmReport {
            iterations,
            converged,
            sigma2: sigma2 * norm.scale * norm.scale,
            elapsed_ms: t0.elapsed().as_secs_f64() * 1e3,
        },
    })
}

pub struct SimilarityStep {
    pub rotation: Matrix3<f64>,
    pub translation: Vector3<f64>,
    pub scale: f64,
    pub sigma2: f64,
    /// tr(AᵀR) and Σ P1‖y − μy‖²: the scale's sufficient statistics (s = trace / yy).
    pub trace: f64,
    pub yy: f64,
}

/// Closed-form weighted Procrustes of the M-step: the similarity minimising
/// Σ P_mn ‖x_n − (s R y_m + t)‖², from the sufficient statistics only.
pub fn weighted_similarity(x: &[P3], y: &[P3], post: &Posteriors, with_scale: bool) -> SimilarityStep {
    let np = post.np;
    let mut mu_x = Vector3::zeros();
    for (xn, w) in x.iter().zip(&post.pt1) {
        mu_x += Vector3::from(*xn) * *w;
    }
    mu_x /= np;
    let mut mu_y = Vector3::zeros();
    for (ym, w) in y.iter().zip(&post.p1) {
        mu_y += Vector3::from(*ym) * *w;
    }
    mu_y /= np;
    // A = Σ_m (PX_m − P1_m μx)(y_m − μy)ᵀ
    let mut a = Matrix3::zeros();
    let mut yy = 0.0;
    for ((ym, px), p1) in y.iter().zip(&post.px).zip(&post.p1) {
        let dy = Vector3::from(*ym) - mu_y;
        a += (Vector3::from(*px) - mu_x * *p1) * dy.transpose();
        yy += p1 * dy.norm_squared();
    }
    let mut xx = 0.0;
    for (xn, w) in x.iter().zip(&post.pt1) {
        xx += w * (Vector3::from(*xn) - mu_x).norm_squared();
    }
    let r = best_rotation(&a);
    let tr = (a.transpose() * r).trace();
    let s = if with_scale && yy > 0.0 { (tr / yy).max(1e-6) } else { 1.0 };
    let t = mu_x - s * (r * mu_y);
    let sigma2 = if with_scale { (xx - s * tr) / (3.0 * np) } else { (xx - 2.0 * tr + yy) / (3.0 * np) };
    SimilarityStep { rotation: r, translation: t, scale: s, sigma2: sigma2.abs(), trace: tr, yy }
}

/// The rotation R maximising tr(AᵀR): A's orthogonal polar factor when
/// det A > 0, found by Higham's scaled Newton iteration (X ← (γX +
/// X⁻ᵀ/γ)/2, six to eight steps of a 3×3 inverse); otherwise, or when the
/// iteration does not settle (A near singular), from the SVD with the
/// smallest singular direction flipped. The SVD alone, through nalgebra's
/// eigen-solver of AᵀA, was half an M-step on the coarse stage's 100 points
/// (0.56 of 1.1 µs); the iteration takes 0.24 µs.
pub fn best_rotation(a: &Matrix3<f64>) -> Matrix3<f64> {
    const TOL: f64 = 1e-14;
    // X⁻ᵀ is X's cofactor matrix over its determinant; the cofactors' columns
    // are the cross products of X's.
    let cofactors = |x: &Matrix3<f64>| {
        let (c0, c1, c2) = (x.column(0), x.column(1), x.column(2));
        let cof = Matrix3::from_columns(&[c1.cross(&c2), c2.cross(&c0), c0.cross(&c1)]);
        let det = c0.dot(&cof.column(0));
        (cof, det)
    };
    let norm = a.norm();
    if norm > 0.0 && norm.is_finite() && a.determinant() > 1e-9 * norm * norm * norm {
        let mut x = *a / norm;
        for _ in 0..20 {
            let (cof, det) = cofactors(&x);
            if !(det > 0.0) {
                break;
            }
            // γ = (‖X⁻¹‖ / ‖X‖)^½, the scaling that makes the steps converge from afar.
            let gamma = (cof.norm() / (det * x.norm())).sqrt();
            let next = (x * gamma + cof / (gamma * det)) * 0.5;
            let change = (next - x).norm();
            x = next;
            if change <= TOL {
                // One more plain step polishes the last rounding.
                let (cof, det) = cofactors(&x);
                return (x + cof / det) * 0.5;
            }
        }
    }
    svd_rotation(a)
}

/// The rotation R maximising tr(AᵀR) from A's SVD U S Vᵀ: U Vᵀ, its last
/// singular direction flipped where that would reflect.
fn svd_rotation(a: &Matrix3<f64>) -> Matrix3<f64> {
    let svd = a.svd(true, true);
    let (u, vt) = (svd.u.unwrap_or_else(Matrix3::identity), svd.v_t.unwrap_or_else(Matrix3::identity));
    let d = (u * vt).determinant().signum();
    let c = Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, if d == 0.0 { 1.0 } else { d }));
    u * c * vt
}

// ------------------------------------------------------------ non-rigid

#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct NonRigidOptions {
    pub em: EmOptions,
    /// Kernel width in units of the source's RMS radius.
    pub beta: f64,
    /// Smoothness weight λ.
    pub lambda: f64,
    /// Largest kernel rank kept (the low-rank factor stops earlier when the
    /// spectrum has decayed below `rank_tol`).
    pub max_rank: usize,
    /// Kernel eigenvalues below this fraction of the largest are dropped.
    /// The default 1e-6 is the shape-space build's: its fits feed a PCA
    /// that keeps 9 modes, and 1e-6 is within 2 % of the object's size of
    /// full rank with about two thirds of the ranks (bench/README.md).
    /// `graspd cpd` defaults to 1e-8, where it is compared with full-rank peers.
    pub rank_tol: f64,
}

impl Default for NonRigidOptions {
    fn default() -> Self {
        Self { em: EmOptions::default(), beta: 0.5, lambda: 2.0, max_rank: 300, rank_tol: 1e-6 }
    }
}

impl NonRigidOptions {
    fn validate(&self) -> Result<(), CpdError> {
        self.em.validate()?;
        if !(self.beta > 1e-4 && self.beta < 1e4) {
            return Err(CpdError::BadParameter {
                name: "beta",
                value: self.beta,
                why: "relative kernel width must lie in (1e-4, 1e4)",
            });
        }
        if !(self.lambda > 0.0 && self.lambda.is_finite()) {
            return Err(CpdError::BadParameter { name: "lambda", value: self.lambda, why: "must be positive" });
        }
        Ok(())
    }
}

/// A Gaussian-kernel displacement field v(z) = G(z, C)·W around centres C,
/// held in normalised coordinates. Defined for any point, not only the centres:
/// that is what moves a demonstration's keypoints.
#[derive(Clone, Debug)]
pub struct DeformationField {
    pub norm: Normalization,
    /// Centres C in normalised coordinates.
    pub centres: Vec<P3>,
    /// Kernel weights W (M×3), normalised units.
    pub weights: Mat<f64>,
    /// Kernel width, normalised units.
    pub beta: f64,
}

impl DeformationField {
    /// Moves points given in the caller's units: z + v(z).
    pub fn apply(&self, pts: &[P3]) -> Vec<P3> {
        let zn: Vec<P3> = pts.iter().map(|p| self.norm.forward(p)).collect();
        let g = gaussian(&zn, &self.centres, self.beta);
        let v = &g * &self.weights;
        clear_upper_state();
        zn.iter()
            .enumerate()
            .map(|(i, z)| self.norm.inverse(&[z[0] + v[(i, 0)], z[1] + v[(i, 1)], z[2] + v[(i, 2)]]))
            .collect()
    }

    /// Jacobian determinant of z ↦ z + v(z) at points `z` (caller's units).
    /// With Gaussian g_j = exp(−‖z − c_j‖² / 2β²) (normalised coordinates),
    /// J = I − Σ_j g_j·w_j (z − c_j)ᵀ / β², exactly; the normalisation is a
    /// similarity, so J is the same in the caller's units. det J ≤ 0 marks a
    /// fold: the field turns part of the shape inside out. A surface fit cannot
    /// see one (a handle mirrored across its own plane lies on the same
    /// surface), but a point beside the surface lands on the wrong side
    /// (measured: a thumb keypoint beside a hammer handle moved 62 mm while the
    /// palm moved 12).
    pub fn jacobian_determinants(&self, z: &[P3]) -> Vec<f64> {
        // In chunks: the kernel holds M Gaussians a point (3 MB a chunk at M = 406).
        z.chunks(1024)
            .flat_map(|c| JacobianKernel::new(self.norm, &self.centres, self.beta, c).determinants(&self.weights))
            .collect()
    }
}

/// [`DeformationField::jacobian_determinants`] at fixed points for any
/// field on the same centres and width. A shape-space build checks each
/// training fit and each training latent for folds on the same surface
/// samples: the Gaussians, most of the cost (3,000 × 406 exponentials a
/// check), are computed here once, and each field's determinants are then
/// one product with its weights.
pub struct JacobianKernel {
    /// The points, normalised.
    zn: Vec<P3>,
    centres: Vec<P3>,
    /// g_ij = exp(−‖z_i − c_j‖² / 2β²).
    g: Mat<f64>,
    beta: f64,
}

impl JacobianKernel {
    /// The kernel at points `z` (caller's units) of fields on `centres`
    /// (normalised by `norm`) with width `beta` (normalised units).
    pub fn new(norm: Normalization, centres: &[P3], beta: f64, z: &[P3]) -> Self {
        let zn: Vec<P3> = z.iter().map(|p| norm.forward(p)).collect();
        let g = gaussian(&zn, centres, beta);
        Self { zn, centres: centres.to_vec(), g, beta }
    }

    /// det J at each point for the field with kernel weights `weights` (M×3).
    /// J_i = I − Σ_j g_ij w_j (z_i − c_j)ᵀ / β² = I − (a_i z_iᵀ − B_i) / β²
    /// with a = G·W and B_i = Σ_j g_ij w_j c_jᵀ: one N×M by M×12 product.
    pub fn determinants(&self, weights: &Mat<f64>) -> Vec<f64> {
        let m = self.centres.len();
        let rhs = Mat::from_fn(m, 12, |j, col| match col {
            0..3 => weights[(j, col)],
            _ => weights[(j, (col - 3) / 3)] * self.centres[j][(col - 3) % 3],
        });
        let prod = &self.g * &rhs;
        clear_upper_state();
        let s = -1.0 / (self.beta * self.beta);
        self.zn
            .iter()
            .enumerate()
            .map(|(i, z)| {
                let j = Matrix3::from_fn(|r, c| {
                    let delta = if r == c { 1.0 } else { 0.0 };
                    delta + s * (prod[(i, r)] * z[c] - prod[(i, 3 + 3 * r + c)])
                });
                j.determinant()
            })
            .collect()
    }

    /// The smallest of [`Self::determinants`] (+∞ with no points).
    pub fn min_determinant(&self, weights: &Mat<f64>) -> f64 {
        self.determinants(weights).into_iter().fold(f64::INFINITY, f64::min)
    }
}

#[derive(Clone, Debug)]
pub struct NonRigidResult {
    pub moved: Vec<Point3<f64>>,
    pub field: DeformationField,
    pub kernel_rank: usize,
    /// The largest eigenvalue the kernel factor left out, relative to the largest kept.
    pub kernel_tail_ratio: f64,
    pub report: EmReport,
}

/// Non-rigid CPD of `source` onto `target`.
pub fn non_rigid(
    source: &[Point3<f64>],
    target: &[Point3<f64>],
    opts: &NonRigidOptions,
) -> Result<NonRigidResult, CpdError> {
    non_rigid_reporting(source, target, opts, &mut |_| {})
}

/// As [`non_rigid`], calling `on_iteration` with the count of EM iterations
/// done after each (the kernel factor comes before the first).
pub fn non_rigid_reporting(
    source: &[Point3<f64>],
    target: &[Point3<f64>],
    opts: &NonRigidOptions,
    on_iteration: &mut (dyn FnMut(usize) + Send),
) -> Result<NonRigidResult, CpdError> {
    let ys = to_p3(source);
    check_cloud("source", &ys)?;
    opts.validate()?;
    let norm = Normalization::of(&ys);
    let y0: Vec<P3> = ys.iter().map(|p| norm.forward(p)).collect();
    on_pool(|| {
        let kernel = LowRankKernel::new(&y0, opts.beta, opts.max_rank, opts.rank_tol);
        fit_non_rigid(&y0, norm, &kernel, target, &[], 0.0, opts, on_iteration)
    })
}

/// Pairs from which a non-rigid CPD splits its dense E-step over the pool
/// (`EStep::parallel_rows`). Below, one thread: shape-space builds (400
/// centres, 1,600 points) already fit their instances in parallel, and keep
/// the bits of their sums.
const PARALLEL_ESTEP_MIN_PAIRS: usize = 1 << 20;

/// Runs `f` on a worker of rayon's pool, or inline when already on one. The
/// kernel factor and the M-step split their products over the pool; from a
/// thread outside it, every split parks the caller and wakes a worker (two
/// context switches, about 2,000 a 100-iteration CPD). On the peer benchmark's
/// 1,024 points that was a third of a one-thread `graspd cpd` (wall 486 →
/// 390 ms) and a sixth on two threads (346 → 292 ms).
fn on_pool<R: Send>(f: impl FnOnce() -> R + Send) -> R {
    if rayon::current_thread_index().is_some() {
        f()
    } else {
        rayon::scope(|_| f())
    }
}

/// A known correspondence: source point `source` belongs at `target`
/// (caller's units). Shape-space builds use the semantic keypoints of
/// annotated training instances: CPD alone matches surfaces, not meaning, and
/// lets points slide along them.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Landmark {
    pub source: usize,
    pub target: P3,
}

/// Non-rigid CPD with a precomputed kernel factor for the normalised source
/// `y0` (a shape-space build registers one canonical to many instances).
pub fn non_rigid_with_kernel(
    y0: &[P3],
    norm: Normalization,
    kernel: &LowRankKernel,
    target: &[Point3<f64>],
    opts: &NonRigidOptions,
) -> Result<NonRigidResult, CpdError> {
    non_rigid_with_landmarks(y0, norm, kernel, target, &[], 0.0, opts)
}

/// As `non_rigid_with_kernel`, with landmark correspondences (extended CPD,
/// Golyanik et al. 2016): each adds `weight`·‖x_l − y_l‖²/2σ² to the
/// objective, i.e. it counts as `weight` observations pinned to that source
/// point. The landmarks enter the M-step only; σ² stays the data's.
pub fn non_rigid_with_landmarks(
    y0: &[P3],
    norm: Normalization,
    kernel: &LowRankKernel,
    target: &[Point3<f64>],
    landmarks: &[Landmark],
    weight: f64,
    opts: &NonRigidOptions,
) -> Result<NonRigidResult, CpdError> {
    on_pool(|| fit_non_rigid(y0, norm, kernel, target, landmarks, weight, opts, &mut |_| {}))
}

#[allow(clippy::too_many_arguments)]
fn fit_non_rigid(
    y0: &[P3],
    norm: Normalization,
    kernel: &LowRankKernel,
    target: &[Point3<f64>],
    landmarks: &[Landmark],
    weight: f64,
    opts: &NonRigidOptions,
    on_iteration: &mut dyn FnMut(usize),
) -> Result<NonRigidResult, CpdError> {
    let t0 = Instant::now();
    opts.validate()?;
    let xs = to_p3(target);
    check_cloud("target", &xs)?;
    if let Some(l) = landmarks.iter().find(|l| l.source >= y0.len() || !l.target.iter().all(|v| v.is_finite())) {
        return Err(CpdError::BadParameter {
            name: "landmark",
            value: l.source as f64,
            why: "source index out of range or target not finite",
        });
    }
    if !(weight >= 0.0 && weight.is_finite()) {
        return Err(CpdError::BadParameter { name: "landmark weight", value: weight, why: "must be finite and ≥ 0" });
    }
    let pins: Vec<(usize, P3)> = landmarks.iter().map(|l| (l.source, norm.forward(&l.target))).collect();
    let x: Vec<P3> = xs.iter().map(|p| norm.forward(p)).collect();
    let m = y0.len();
    let k = kernel.rank();
    let mut estep = EStep::new(&x);
    estep.parallel_rows = m * x.len() >= PARALLEL_ESTEP_MIN_PAIRS;
    let mut post = Posteriors::default();
    let mut y = y0.to_vec();
    let mut z = vec![[0.0; 3]; k];
    let mut z_prev = z.clone();
    let factor = LowRankFactor::new(kernel.q.as_ref());
    let (mut cg_iterations, mut direct_solves) = (0usize, 0usize);
    let mut sigma2 = initial_sigma2(&x, &y);
    let xx: Vec<f64> = x.iter().map(|p| dot(p, p)).collect();
    let (mut prev, mut iterations, mut converged) = (f64::INFINITY, 0, false);
    while iterations < opts.em.max_iters {
        iterations += 1;
        // Single-precision E-step sums (f64 per-point totals) while σ is
        // well above f32's resolution of the coordinates: a fifth of the EM
        // time at 1,024 points, the moved points within 0.7 µm of the double-
        // precision E-step's on the peer benchmark's mug pair. A fit that
        // collapses onto its data (σ → 0, no noise) ends in double precision,
        // where distances of a few σ are still resolved.
        estep.single_precision = sigma2 >= SINGLE_PRECISION_MIN_SIGMA2;
        estep.run(&y, sigma2, opts.em.w, &mut post);
        if !(post.np > 1e-9) {
            return Err(CpdError::NoCorrespondence);
        }
        // M-step (Woodbury): W = (F − dP Q (sΛ⁻¹ + Qᵀ dP Q)⁻¹ Qᵀ F) / s,
        // F = PX − dP·Y0, s = λσ². No division by P1, so unmatched points are fine.
        let s = opts.lambda * sigma2;
        // Landmarks join P1 and PX for the M-step only (σ² below stays the data's);
        // plain CPD, the common case, borrows the posteriors as they are.
        let (p1, px): (Cow<[f64]>, Cow<[P3]>) = if pins.is_empty() {
            (Cow::Borrowed(&post.p1), Cow::Borrowed(&post.px))
        } else {
            let (mut p1, mut px) = (post.p1.clone(), post.px.clone());
            for &(i, t) in &pins {
                p1[i] += weight;
                for d in 0..3 {
                    px[i][d] += weight * t[d];
                }
            }
            (Cow::Owned(p1), Cow::Owned(px))
        };
        let f: Vec<P3> = (0..m).map(|i| std::array::from_fn(|d| px[i][d] - p1[i] * y0[i][d])).collect();
        let qtf = factor.transpose_times(&f);
        // The displacement is G·W = Q·z with z = A⁻¹ Qᵀ F (Woodbury gives
        // Qᵀ W = Λ⁻¹ z), so only the k×3 system is needed: by conjugate
        // gradients from the last iteration's z (each product O(M k), where
        // forming Qᵀ dP Q is O(M k²): most of an iteration at k ≈ 370),
        // and directly should they stall.
        // Start from the last two solutions' linear extrapolation: the EM
        // path is smooth, and this takes 10 % fewer iterations than starting
        // from the last (777 against 865 over the peer benchmark's 100).
        let guess: Vec<P3> = if iterations > 2 {
            z.iter().zip(&z_prev).map(|(a, b)| std::array::from_fn(|c| 2.0 * a[c] - b[c])).collect()
        } else {
            z.clone()
        };
        let solved = match mstep::pcg(&factor, &kernel.lambda, &p1, s, &qtf, &guess, mstep::PCG_TOLERANCE) {
            Some((zz, its)) => {
                cg_iterations += its;
                zz
            }
            None => {
                direct_solves += 1;
                let dpq = Mat::from_fn(m, k, |i, j| p1[i] * kernel.q[(i, j)]);
                let mut a = kernel.q.transpose() * &dpq;
                for (j, l) in kernel.lambda.iter().enumerate() {
                    a[(j, j)] += s / l.max(1e-300);
                }
                let b = Mat::from_fn(k, 3, |j, c| qtf[j][c]);
                let zz = match a.llt(Side::Lower) {
                    Ok(llt) => llt.solve(&b),
                    Err(_) => a.partial_piv_lu().solve(&b),
                };
                clear_upper_state();
                (0..k).map(|j| [zz[(j, 0)], zz[(j, 1)], zz[(j, 2)]]).collect()
            }
        };
        z_prev = std::mem::replace(&mut z, solved);
        let gw = factor.times(&z);
        for i in 0..m {
            y[i] = [y0[i][0] + gw[i][0], y0[i][1] + gw[i][1], y0[i][2] + gw[i][2]];
        }
        // σ² from the sufficient statistics.
        let mut num: f64 = post.pt1.iter().zip(&xx).map(|(a, b)| a * b).sum();
        for i in 0..m {
            num += post.p1[i] * dot(&y[i], &y[i]) - 2.0 * dot(&post.px[i], &y[i]);
        }
        sigma2 = (num / (3.0 * post.np)).abs().max(1e-10);
        on_iteration(iterations);
        let nll = post.neg_log_likelihood;
        if opts.em.tol > 0.0 && ((prev - nll).abs() <= opts.em.tol * nll.abs().max(1e-12) || sigma2 <= 1e-10) {
            converged = true;
            break;
        }
        prev = nll;
    }
    // The field's weights: the part of W in span(Q), Q Λ⁻¹ z (the rest the
    // low-rank kernel ignores but the exact kernel G(z, C) of the field
    // would amplify), so that the field agrees with `moved`.
    let lz: Vec<P3> = z.iter().zip(&kernel.lambda).map(|(zj, l)| zj.map(|v| v / l.max(1e-300))).collect();
    let wr = factor.times(&lz);
    let w = Mat::from_fn(m, 3, |i, c| wr[i][c]);
    tracing::debug!(iterations, rank = k, cg_iterations, direct_solves, "cpd M-steps");
    let moved = to_points(&y.iter().map(|p| norm.inverse(p)).collect::<Vec<_>>());
    Ok(NonRigidResult {
        moved,
        field: DeformationField { norm, centres: y0.to_vec(), weights: w, beta: opts.beta },
        kernel_rank: k,
        kernel_tail_ratio: kernel.tail_ratio,
        report: EmReport {
            iterations,
            converged,
            sigma2: sigma2 * norm.scale * norm.scale,
            elapsed_ms: t0.elapsed().as_secs_f64() * 1e3,
        },
    })
}

/// σ² (normalised units: the source's RMS radius is 1) below which the
/// non-rigid E-step runs in double precision: σ = 10⁻⁴, where f32 coordinates
/// (about 10⁻⁷) still put the exponent of a pair 2σ apart within 0.2 %.
const SINGLE_PRECISION_MIN_SIGMA2: f64 = 1e-8;

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Rotation3, Unit};
    use rand::{Rng, SeedableRng};

    /// `best_rotation` against the SVD's answer: random matrices of either
    /// sign of determinant, nearly singular ones and rank-deficient ones,
    /// each a proper rotation within 1e-12 of the SVD's and scoring
    /// tr(AᵀR) no lower.
    #[test]
    fn best_rotation_is_the_svds_proper_rotation() {
        let mut r = rand_chacha::ChaCha8Rng::seed_from_u64(9);
        let mut cases: Vec<Matrix3<f64>> = (0..300)
            .map(|_| Matrix3::from_fn(|_, _| r.random_range(-1.0..1.0)) * 10f64.powi(r.random_range(-4..3)))
            .collect();
        // Nearly singular and rank-deficient (a planar or linear view's cross-covariance).
        for k in 0..20 {
            let u = Rotation3::new(Vector3::new(0.3 * k as f64, 0.7, -0.2)).into_inner();
            let v = Rotation3::new(Vector3::new(-0.1, 0.2 * k as f64, 0.9)).into_inner();
            let s = [1.0, 0.3, [1e-6, 1e-10, 0.0, -1e-8][k % 4]];
            cases.push(u * Matrix3::from_diagonal(&Vector3::from(s)) * v.transpose());
        }
        let (mut polar, mut fallback) = (0, 0);
        for a in &cases {
            let got = best_rotation(a);
            let want = svd_rotation(a);
            assert!((got.transpose() * got - Matrix3::identity()).norm() < 1e-12, "{a}: not orthogonal");
            assert!((got.determinant() - 1.0).abs() < 1e-12, "{a}: not proper");
            let (tg, tw) = ((a.transpose() * got).trace(), (a.transpose() * want).trace());
            assert!(tg >= tw - 1e-12 * a.norm(), "{a}: tr {tg} below the SVD's {tw}");
            // The same rotation where the optimum is unique (σ₂ + σ₃ well above 0).
            let sv = a.singular_values();
            if sv[1] + sv[2] > 1e-6 * sv[0] {
                assert!((got - want).norm() < 1e-12, "{a}: {got} vs {want}");
            }
            if a.determinant() > 1e-9 * a.norm().powi(3) {
                polar += 1;
            } else {
                fallback += 1;
            }
        }
        // Both paths were taken.
        assert!(polar > 100 && fallback > 100, "{polar} polar, {fallback} by the SVD");
    }

    fn blob(n: usize, seed: u64) -> Vec<Point3<f64>> {
        // An anisotropic, asymmetric cloud so that the rotation is identifiable.
        let mut r = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        (0..n)
            .map(|_| {
                let (a, b, c): (f64, f64, f64) = (r.random(), r.random(), r.random());
                Point3::new(0.12 * a * a, 0.06 * b, 0.03 * c + 0.02 * a)
            })
            .collect()
    }

    #[test]
    fn rigid_recovers_a_similarity() {
        let src = blob(400, 1);
        let rot = Rotation3::from_axis_angle(&Unit::new_normalize(Vector3::new(0.3, -0.5, 1.0)), 0.6);
        let t = Vector3::new(0.4, -0.2, 0.1);
        let dst: Vec<_> = src.iter().map(|p| Point3::from(1.3 * (rot * p.coords) + t)).collect();
        let res = rigid(&src, &dst, &RigidOptions { em: EmOptions { w: 0.0, max_iters: 200, tol: 1e-9 }, scale: true })
            .unwrap();
        assert!((res.rotation - rot.matrix()).norm() < 1e-4, "{}", res.rotation);
        assert!((res.scale - 1.3).abs() < 1e-4);
        assert!((res.translation - t).norm() < 1e-4);
        let err = res.moved.iter().zip(&dst).map(|(a, b)| (a - b).norm()).fold(0.0, f64::max);
        assert!(err < 1e-4, "max error {err}");
    }

    #[test]
    fn non_rigid_fits_a_smooth_bend_in_caller_units() {
        let src = blob(600, 2);
        // A smooth bend: z shifts with x², magnitude 1.5 cm.
        let dst: Vec<_> = src.iter().map(|p| Point3::new(p.x, p.y, p.z + 1.0 * p.x * p.x)).collect();
        let opts = NonRigidOptions {
            em: EmOptions { w: 0.0, max_iters: 200, tol: 1e-8 },
            beta: 0.8,
            lambda: 0.5,
            ..Default::default()
        };
        let res = non_rigid(&src, &dst, &opts).unwrap();
        let errs: Vec<f64> = res.moved.iter().zip(&dst).map(|(a, b)| (a - b).norm()).collect();
        let mean = errs.iter().sum::<f64>() / errs.len() as f64;
        assert!(mean < 1.5e-3, "mean error {mean}");
        // The field moves points that were never samples, consistently.
        let moved_again = res.field.apply(&to_p3(&src));
        let diff =
            moved_again.iter().zip(&res.moved).map(|(a, b)| (Vector3::from(*a) - b.coords).norm()).fold(0.0, f64::max);
        assert!(diff < 2e-3, "field vs moved: {diff}");
    }

    #[test]
    fn landmarks_pin_what_the_surface_leaves_free() {
        // A ring turned 15° about its own axis: the surfaces coincide, so plain
        // CPD has no reason to move; a landmark says where one point went.
        let ring = |turn: f64| -> Vec<Point3<f64>> {
            (0..360)
                .map(|i| {
                    let a = i as f64 * std::f64::consts::TAU / 360.0 + turn;
                    Point3::new(0.05 * a.cos(), 0.05 * a.sin(), 0.004 * ((i % 3) as f64))
                })
                .collect()
        };
        let (src, dst) = (ring(0.0), ring(15f64.to_radians()));
        let opts = NonRigidOptions {
            em: EmOptions { w: 0.0, max_iters: 150, tol: 1e-8 },
            beta: 1.0,
            lambda: 1.0,
            ..Default::default()
        };
        let y = to_p3(&src);
        let norm = Normalization::of(&y);
        let y0: Vec<P3> = y.iter().map(|p| norm.forward(p)).collect();
        let kernel = LowRankKernel::new(&y0, opts.beta, opts.max_rank, opts.rank_tol);
        let target = to_p3(&dst)[0];
        let free = non_rigid_with_kernel(&y0, norm, &kernel, &dst, &opts).unwrap();
        let pinned =
            non_rigid_with_landmarks(&y0, norm, &kernel, &dst, &[Landmark { source: 0, target }], 20.0, &opts).unwrap();
        let miss = |r: &NonRigidResult| (r.moved[0].coords - Vector3::from(target)).norm();
        // 15° on a 5 cm ring is 13 mm of arc.
        assert!(miss(&free) > 0.008, "plain CPD moved along the ring: {}", miss(&free));
        assert!(miss(&pinned) < 0.003, "landmark missed by {}", miss(&pinned));
        let bad = Landmark { source: 9999, target };
        assert!(matches!(
            non_rigid_with_landmarks(&y0, norm, &kernel, &dst, &[bad], 1.0, &opts),
            Err(CpdError::BadParameter { name: "landmark", .. })
        ));
    }

    #[test]
    fn bad_input_is_an_error_not_a_panic() {
        let ok = blob(50, 3);
        let opts = NonRigidOptions::default();
        assert_eq!(non_rigid(&[], &ok, &opts).unwrap_err(), CpdError::Empty { which: "source" });
        let mut nan = ok.clone();
        nan[7].y = f64::NAN;
        assert_eq!(non_rigid(&ok, &nan, &opts).unwrap_err(), CpdError::NonFinite { which: "target", index: 7 });
        let same = vec![Point3::new(1.0, 2.0, 3.0); 20];
        assert_eq!(rigid(&same, &ok, &RigidOptions::default()).unwrap_err(), CpdError::Degenerate { which: "source" });
        let bad_w = NonRigidOptions { em: EmOptions { w: 1.0, ..Default::default() }, ..Default::default() };
        assert!(matches!(non_rigid(&ok, &ok, &bad_w), Err(CpdError::BadParameter { name: "w", .. })));
    }
}
