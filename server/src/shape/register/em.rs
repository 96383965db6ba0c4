//! The EM the stages share (CPD's E-step against the posed, deformed
//! model; an M-step of pose and scale in closed form, then the latent's MAP
//! update from `latent`'s normal equations), its SQUAREM acceleration, and what a fit is given: the pose, the
//! view's visibility weights and the table's support.

use super::latent::{add_support_term, solve, LatentStep};
use super::{RegisterOptions, LOOSE_SCALE_PRIOR_STD};
use crate::shape::cpd::{weighted_similarity, Normalization};
use crate::shape::estep::{initial_sigma2, EStep, Posteriors, P3};
use crate::shape::freespace::FreeSpace;
use crate::shape::space::LinearModel;
use nalgebra::{Matrix3, Rotation3, Vector3};

/// Similarity pose: x = s·R·y + t (y normalised canonical, x cloud frame).
#[derive(Clone, Copy, Debug)]
pub(super) struct Pose {
    pub(super) r: Matrix3<f64>,
    pub(super) t: Vector3<f64>,
    pub(super) s: f64,
}

impl Pose {
    pub(super) fn apply(&self, y: &P3) -> P3 {
        let p = self.s * (self.r * Vector3::from(*y)) + self.t;
        [p.x, p.y, p.z]
    }
}

/// The plane the tool rests on: up·x = height (cloud frame). A fit adds
/// ½·K·(height − lowest)²/σ² to its objective, the model's lowest point
/// moved through the mean of its contact points (those within
/// [`CONTACT_BAND_M`] of it: one point alone would jump from iteration to
/// iteration), with K = `weight` × the observed points' total posterior
/// (Np): the support weighs as much as that share of the view, at every σ.
#[derive(Clone, Copy, Debug)]
pub(super) struct Support {
    pub(super) up: Vector3<f64>,
    pub(super) height: f64,
    pub(super) weight: f64,
}

/// The support holds a fit whose canonical z lies within acos(0.87) ≈ 30°
/// of up: a tool resting as its category was modelled (the mug on its foot,
/// the drill on its battery, the hammer on its head's side), whose base is a
/// face the shape space's training fits align. A tool on its side touches
/// along a curved flank whose place follows the space's diameter modes, and
/// holding it there made a knocked-over mug's keypoints worse (eval transfer
/// --on-side --views 12, seeds 7 / 11, test median 2.10 / 2.10 mm without
/// the table, 2.43 / 2.48 with it held).
pub(super) const REST_POSE_COS: f64 = 0.87;

/// The contact points' mean height, and where it should be.
#[derive(Clone, Copy, Debug)]
pub(super) struct Contact {
    pub(super) mean: f64,
    pub(super) target: f64,
}

/// Model points this close (m) to the lowest one touch the support.
const CONTACT_BAND_M: f64 = 0.002;

impl Support {
    pub(super) fn new(up: Option<Vector3<f64>>, opts: &RegisterOptions) -> Option<Self> {
        let (up, height) = (up?, opts.support_height?);
        (opts.support_weight > 0.0 && height.is_finite()).then_some(Self { up, height, weight: opts.support_weight })
    }

    /// The model's contact points at this pose (indices into `y_model`, in
    /// `idx`), and the height their mean should have for the lowest point to
    /// touch the support: the band's mean lies above the lowest point (a
    /// rounded base's fillet is in it), and aiming the mean at the plane
    /// sank the lowest point 1 mm into the table.
    pub(super) fn contact(&self, pose: &Pose, y_model: &[P3], idx: &mut Vec<usize>) -> Option<Contact> {
        let um = pose.r.transpose() * self.up;
        let lift = self.up.dot(&pose.t);
        let height = |y: &P3| pose.s * (um.x * y[0] + um.y * y[1] + um.z * y[2]) + lift;
        let lowest = y_model.iter().map(height).fold(f64::INFINITY, f64::min);
        idx.clear();
        let mut sum = 0.0;
        for (i, y) in y_model.iter().enumerate() {
            let h = height(y);
            if h <= lowest + CONTACT_BAND_M {
                idx.push(i);
                sum += h;
            }
        }
        let mean = sum / idx.len().max(1) as f64;
        (!idx.is_empty()).then_some(Contact { mean, target: self.height + (mean - lowest) })
    }

    /// The support's term in the latent's normal equations (model frame,
    /// units of `LatentStep::solve`): the contact's mean height is
    /// s·(uₘ·base̅ + gᵀℓ) + up·t with g = Σ Bᵢᵀuₘ/|C| and uₘ = Rᵀup, so the
    /// term is ½(e − gᵀℓ)² times K with e = (target − up·t)/s − uₘ·base̅.
    pub(super) fn latent_row(&self, step: &LatentStep, pose: &Pose, idx: &[usize], target: f64) -> (Vec<f64>, f64) {
        let um = pose.r.transpose() * self.up;
        let n = idx.len().max(1) as f64;
        let mean = |cols: &[Vec<f64>; 3]| -> f64 {
            idx.iter().map(|&i| um.x * cols[0][i] + um.y * cols[1][i] + um.z * cols[2][i]).sum::<f64>() / n
        };
        let g = step.basis.iter().map(mean).collect();
        let e = (target - self.up.dot(&pose.t)) / pose.s - mean(&step.base);
        (g, e)
    }
}

#[derive(Clone)]
pub(super) struct Fit {
    pub(super) pose: Pose,
    pub(super) latent: Vec<f64>,
    pub(super) sigma2: f64,
    pub(super) nll: f64,
    pub(super) iterations: usize,
}

/// What the camera can see: canonical normals of the model points and the
/// viewpoint in the cloud's frame.
#[derive(Clone, Copy)]
pub(super) struct View<'a> {
    pub(super) normals: &'a [P3],
    pub(super) viewpoint: Option<Vector3<f64>>,
    /// The view's range image: facing model points behind a seen surface are hidden too.
    pub(super) occlusion: Option<&'a FreeSpace>,
    /// A second camera whose points the view holds too (the cloud merges
    /// two cameras' views): a model point facing it, and not behind a
    /// surface it saw (`second_occlusion`, in the fine stages), counts as
    /// seen, the first camera's range image notwithstanding.
    pub(super) second: Option<Vector3<f64>>,
    /// The view's range image from the second camera: a point facing it
    /// behind a surface it saw is not seen by it.
    pub(super) second_occlusion: Option<&'a FreeSpace>,
}

/// Mixing weight of a model point facing away from the camera.
const HIDDEN_WEIGHT: f64 = 0.1;
/// Mixing weight of a hidden model point in the fine stage, where the range
/// image also hides facing points behind a seen surface. Lower than
/// [`HIDDEN_WEIGHT`] because the occlusion test is then exact enough to trust:
/// measured (8 views, seed 7, training tools), the registered keypoints'
/// median camera-depth bias went from -1.73/-0.91/-0.89 mm (mug, hammer, drill;
/// negative = toward the camera) at 0.1 without occlusion to -0.88/-0.13/-0.33
/// mm at 0.05; 0.0 overshoots (+1 mm) and 0.02 was worse on test instances.
const HIDDEN_WEIGHT_FINE: f64 = 0.05;
/// In the fine stages (with the range image), a model point whose surface
/// the camera's ray meets at more than acos(0.15) ≈ 81° from its normal
/// counts as hidden too. A depth camera samples such a surface with few
/// pixels (foreshortening; real sensors drop them), so the view holds
/// almost nothing there, and at full weight these points (a mug body's
/// flanks) were pulled onto the nearer, well-seen surface: a bias toward
/// the camera. Measured (eval transfer --views 12, test keypoint median /
/// p90 in mm, seeds 7 / 11 / 23, 0 → 0.15): mug 2.40 / 10.2, 2.28 / 7.6,
/// 2.53 / 8.5 → 2.17 / 11.9, 2.18 / 7.1, 2.59 / 8.1 (depth bias seed 7
/// −1.18 → −1.04 mm); drill 2.42 / 5.2, 2.54 / 4.8, 2.36 / 5.1 → 2.36 /
/// 5.1, 2.41 / 5.1, 2.39 / 5.2; hammer 2.09 / 3.8, 1.93 / 3.7, 2.04 / 4.2
/// → 2.05 / 3.8, 1.85 / 3.6, 2.02 / 4.1. 0.1, 0.2 and 0.3 on the mug, seed
/// 7: 2.28 / 13.3, 2.23 / 9.4, 2.31 / 9.5; 0.2 lost on the mug's other
/// seeds and the drill. The medians fell in 8 of the 9 runs; the p90s
/// moved both ways (the mug's seed 7 in views that hide its handle). Real
/// YCB (`eval ycb --views 8`, Chamfer median): mug 3.57 → 3.57, drill 5.21
/// → 5.08, hammer 3.78 → 3.73 mm.
const GRAZING_COS: f64 = 0.15;
/// Least depth (m) by which a seen surface must lie in front of a model point to hide it.
const OCCLUSION_MARGIN_M: f64 = 0.002;

impl View<'_> {
    /// Mixing weights (mean 1) from back-face culling, or None without a viewpoint.
    ///
    /// With the range image, a facing point is hidden when the camera saw a
    /// surface more than 3σ (and 2 mm) in front of it. Without this, the
    /// self-occluded parts (a mug's far wall, a handle behind the body) pull the
    /// model onto the visible surface in front of them: measured, registered
    /// keypoints sat 1-1.9 mm (median) too near the camera. The tolerance
    /// follows σ so that a fit still far from the data is not cut off from it.
    pub(super) fn weights<'w>(
        &self,
        pose: &Pose,
        y_world: &[P3],
        sigma2: f64,
        out: &'w mut Vec<f64>,
    ) -> Option<&'w [f64]> {
        self.weights_turned(self.normals.iter().map(|n| pose.r * Vector3::from(*n)), y_world, sigma2, out)
    }

    /// [`Self::weights`] with the model's normals already turned into the
    /// cloud's frame (`normals_world`, one per point of `y_world`), where
    /// the caller turned them for other work too.
    pub(super) fn weights_turned<'w>(
        &self,
        normals_world: impl Iterator<Item = Vector3<f64>>,
        y_world: &[P3],
        sigma2: f64,
        out: &'w mut Vec<f64>,
    ) -> Option<&'w [f64]> {
        let vp = self.viewpoint?;
        if self.normals.len() != y_world.len() {
            return None;
        }
        let tol = (3.0 * sigma2.sqrt()).max(OCCLUSION_MARGIN_M);
        let fine = self.occlusion.is_some();
        let (hidden_weight, grazing_cos) = if fine { (HIDDEN_WEIGHT_FINE, GRAZING_COS) } else { (HIDDEN_WEIGHT, 0.0) };
        out.clear();
        // How far each point faces the camera (≤ 0: away), in a pass of
        // plain arithmetic that vectorises; then the occlusion test, a
        // lookup, only where a point faces it. One pass with both took 6 %
        // of a mug's registration.
        let facing = |vp: Vector3<f64>, n: &Vector3<f64>, y: &P3| {
            let to_camera = vp - Vector3::from(*y);
            let facing = n.dot(&to_camera);
            // The coarse stage and the race (no grazing margin) skip the norm's
            // square root, the same result (measured, `VIEWPOINT=known
            // bench_register mug 3`, two alternating pairs: coarse 2.40 / 2.38
            // → 2.30 / 2.32 ms p50, race 1.98 / 1.92 → 1.88 / 1.88).
            if grazing_cos != 0.0 {
                facing - grazing_cos * to_camera.norm()
            } else {
                facing
            }
        };
        match self.second {
            None => out.extend(normals_world.zip(y_world).map(|(n, y)| facing(vp, &n, y))),
            // A point facing the second camera and not behind a surface it
            // saw is seen by it: +∞, so that the first camera's occlusion
            // test below passes it over.
            Some(vp2) => out.extend(normals_world.zip(y_world).map(|(n, y)| {
                let seen_by_second =
                    facing(vp2, &n, y) > 0.0 && !self.second_occlusion.is_some_and(|fs| fs.hidden_behind_seen(y, tol));
                if seen_by_second {
                    f64::INFINITY
                } else {
                    facing(vp, &n, y)
                }
            })),
        }
        let mut total = 0.0;
        for (w, y) in out.iter_mut().zip(y_world) {
            let hidden = *w <= 0.0 || (w.is_finite() && self.occlusion.is_some_and(|fs| fs.hidden_behind_seen(y, tol)));
            *w = if hidden { hidden_weight } else { 1.0 };
            total += *w;
        }
        let mean = total / out.len().max(1) as f64;
        out.iter_mut().for_each(|w| *w /= mean);
        Some(out)
    }
}

/// The translation that best maps the model onto the data for the pose's
/// rotation and scale, given the posteriors: t = μx − s·R·μy.
fn fitted_translation(x: &[P3], y_model: &[P3], post: &Posteriors, pose: &Pose) -> Vector3<f64> {
    let (mut mx, mut my) = (Vector3::zeros(), Vector3::zeros());
    for (xn, w) in x.iter().zip(&post.pt1) {
        mx += Vector3::from(*xn) * *w;
    }
    for (ym, w) in y_model.iter().zip(&post.p1) {
        my += Vector3::from(*ym) * *w;
    }
    mx / post.np - pose.s * (pose.r * (my / post.np))
}

/// The E-step set-up of registration fits.
pub(super) fn new_estep(x: &[P3]) -> EStep {
    let mut estep = EStep::new(x);
    // A fit needs the pairs within a few σ only (e^{-12.5} beyond 5σ).
    estep.cutoff_sigmas = 5.0;
    estep.single_precision = true;
    // Once σ is small, skip blocks of model points beyond the cutoff
    // (`EStep::blocked`) rather than list the pairs within it: on
    // registration's sets (≤ 800 a side) the blocks beat the dense sums once
    // the cutoff is below 0.6 of the view's radius, where the neighbour list
    // beat them only below 0.3. Measured (`VIEWPOINT=known bench_register C
    // 1`, two runs, the refine stage's time over the polish's, which it
    // leaves alone): mug 0.97 → 0.89, hammer 1.15 → 0.66; at 1.0 the mug's
    // 80 × 100 coarse fits slowed by a tenth. Keypoints equal to 1e-4 mm
    // (eval transfer --views 12 --seed 7, all three categories).
    estep.blocked = true;
    estep.truncate_below = 0.6;
    estep
}

/// A subset of the view prepared once for the E-steps of every fit on it:
/// [`new_estep`]'s settings and the blocked kernels' groups of nearby data
/// points. Ordering those groups for each fit took about 2 % of a mug's
/// registration: ten orders a fit, where four subsets are distinct.
pub(super) struct ViewPoints(EStep);

impl ViewPoints {
    pub(super) fn new(x: &[P3]) -> Self {
        let mut estep = new_estep(x);
        estep.prepare_blocks();
        Self(estep)
    }

    pub(super) fn points(&self) -> &[P3] {
        self.0.data()
    }

    /// A fit's own E-step on these points.
    pub(super) fn estep(&self) -> EStep {
        self.0.clone()
    }
}

/// EM over pose (and latent, when `prior` is given).
///
/// Latent fits converge slowly: the latent and the translation drift
/// together a little further each iteration (measured on a drill view's
/// refine: the first mode −0.39 → −1.34 over 25 iterations, each step 0.88 of
/// the last). With `opts.accelerate`, those fits take SQUAREM steps
/// (Varadhan & Roland 2008, scheme S3): two EM steps, then a jump along
/// their path, kept only when the likelihood there is no worse.
#[allow(clippy::too_many_arguments)]
pub(super) fn em(
    model: &LinearModel,
    view: View,
    x: &ViewPoints,
    pose: Pose,
    latent: Vec<f64>,
    prior: Option<(&[f64], &LatentStep)>,
    support: Option<Support>,
    sigma2_init: Option<f64>,
    opts: &RegisterOptions,
    iters: usize,
    norm: &Normalization,
) -> Fit {
    let mut run = EmRun::new(FitInputs { model, view, x, prior, support, opts, norm });
    let mut st = EmState { pose, latent, sigma2: 0.0 };
    run.load(&st);
    st.sigma2 = sigma2_init.unwrap_or_else(|| initial_sigma2(x.points(), &run.y_world));
    let accelerate = opts.accelerate && prior.is_some();
    let (st, nll, iterations) = squarem(&mut run, st, accelerate, iters, opts.tol);
    Fit { pose: st.pose, latent: st.latent, sigma2: st.sigma2, nll, iterations }
}

/// One fit's EM map, as [`squarem`] drives it.
pub(super) trait EmMap {
    type State: Clone;
    /// Evaluate the model at a state set from outside.
    fn load(&mut self, st: &Self::State);
    /// E-step at `st` (loaded), then the M-step into `st`: the E-step's
    /// negative log-likelihood, or None when no data point is explained.
    /// The view's weights are those of the last step unless `refresh_weights`.
    fn step(&mut self, st: &mut Self::State, refresh_weights: bool) -> Option<f64>;
    /// SQUAREM's jump from three successive states and its step length α
    /// (see [`squarem_jump`]).
    fn extrapolate(
        &self,
        s0: &Self::State,
        s1: &Self::State,
        s2: &Self::State,
        max_step: f64,
    ) -> Option<(Self::State, f64)>;
}

/// At most `iters` EM steps of `map` from `st` (loaded), until the relative
/// change of the negative log-likelihood falls below `tol`; with
/// `accelerate`, in SQUAREM cycles. The last state, its E-step's negative
/// log-likelihood and the steps taken.
pub(super) fn squarem<M: EmMap>(
    map: &mut M,
    mut st: M::State,
    accelerate: bool,
    iters: usize,
    tol: f64,
) -> (M::State, f64, usize) {
    let (mut prev, mut nll, mut it) = (f64::INFINITY, f64::INFINITY, 0);
    // One EM step; break when no point is explained or the fit has converged.
    macro_rules! em_step {
        ($st:expr, $refresh:expr) => {{
            it += 1;
            match map.step(&mut $st, $refresh) {
                None => break,
                Some(v) => {
                    nll = v;
                    if (prev - nll).abs() <= tol * nll.abs().max(1e-12) {
                        break;
                    }
                    prev = nll;
                    v
                }
            }
        }};
    }
    let mut max_step = SQUAREM_FIRST_MAX_STEP;
    while it < iters {
        let s0 = st.clone();
        // The visibility weights follow the pose at every plain step; a
        // SQUAREM cycle holds them over its three steps, which then are steps
        // of one mixture (refreshed each step, their flips made the
        // likelihood jitter by ±0.1 % and 44 % of the jumps were refused).
        em_step!(st, true);
        if !accelerate || it + 2 > iters {
            continue;
        }
        let s1 = st.clone();
        let nll1 = em_step!(st, false);
        let s2 = st.clone();
        let Some((jump, alpha)) = map.extrapolate(&s0, &s1, &s2, max_step) else { continue };
        st = jump;
        map.load(&st);
        let nll_jump = em_step!(st, false);
        if nll_jump <= nll1 {
            if alpha <= -max_step {
                max_step = (max_step * 2.0).min(SQUAREM_LARGEST_STEP);
            }
        } else {
            // Worse than plain EM's last: back to its point, and shorter jumps.
            max_step = (max_step / 2.0).max(1.0);
            // (s2's own likelihood is unknown until its E-step; nll1 bounds it.)
            st = s2;
            map.load(&st);
            (prev, nll) = (nll1, nll1);
        }
    }
    (st, nll, it)
}

/// The pose's scale bounds (`RegisterOptions::scale_range`, relative to
/// the canonical size) in the normalised frame's units.
pub(super) fn scale_bounds(opts: &RegisterOptions, norm: &Normalization) -> (f64, f64) {
    (opts.scale_range.0 * norm.scale, opts.scale_range.1 * norm.scale)
}

/// SQUAREM's coordinates of a fit's state, made commensurate: rotation as
/// a rotation vector from a reference state's (radians), translation over
/// its scale, log scale, log σ of each variance, and the latent over its
/// prior std.
pub(super) struct JumpCoords {
    r0: Matrix3<f64>,
    unit: f64,
    std: Vec<f64>,
    scale_range: (f64, f64),
}

impl JumpCoords {
    /// Coordinates about `pose`; `scale_range` bounds the scale a jump may reach.
    pub(super) fn new(pose: &Pose, prior_var: Option<&[f64]>, q: usize, scale_range: (f64, f64)) -> Self {
        let std = match prior_var {
            Some(var) => var.iter().map(|v| v.max(1e-12).sqrt()).collect(),
            None => vec![1.0; q],
        };
        Self { r0: pose.r, unit: pose.s.max(1e-12), std, scale_range }
    }

    pub(super) fn pack(&self, pose: &Pose, variances: &[f64], latent: &[f64]) -> Vec<f64> {
        let w = Rotation3::from_matrix_unchecked(self.r0.transpose() * pose.r).scaled_axis();
        let mut v = vec![w.x, w.y, w.z];
        v.extend((pose.t / self.unit).iter());
        v.push(pose.s.ln());
        v.extend(variances.iter().map(|s2| 0.5 * s2.ln()));
        v.extend(latent.iter().zip(&self.std).map(|(l, sd)| l / sd));
        v
    }

    /// The pose, the `n_variances` variances and the latent at `th`.
    pub(super) fn unpack(&self, th: &[f64], n_variances: usize) -> (Pose, Vec<f64>, Vec<f64>) {
        let rot = self.r0 * Rotation3::new(Vector3::new(th[0], th[1], th[2])).into_inner();
        // Re-orthonormalise (the product drifts by round-off only, but a
        // rotation must stay one).
        let rot = Rotation3::from_matrix(&rot).into_inner();
        let (smin, smax) = self.scale_range;
        let pose = Pose { r: rot, t: Vector3::new(th[3], th[4], th[5]) * self.unit, s: th[6].exp().clamp(smin, smax) };
        let variances = th[7..7 + n_variances].iter().map(|l| (2.0 * l).exp().max(1e-10)).collect();
        let latent = th[7 + n_variances..].iter().zip(&self.std).map(|(l, sd)| l * sd).collect();
        (pose, variances, latent)
    }
}

/// SQUAREM's jump from three successive points (t1 = F(t0), t2 = F(t1)):
/// θ' = θ0 − 2αr + α²v with r = θ1 − θ0, v = θ2 − 2θ1 + θ0 and α =
/// −|r|/|v| (−1 gives t2 back, so α is kept within [−max_step, −1]). None
/// when the path is straight enough that the jump is no step at all, or
/// degenerate.
pub(super) fn squarem_jump(t0: &[f64], t1: &[f64], t2: &[f64], max_step: f64) -> Option<(Vec<f64>, f64)> {
    let r: Vec<f64> = t1.iter().zip(t0).map(|(a, b)| a - b).collect();
    let v: Vec<f64> = (0..t0.len()).map(|i| t2[i] - 2.0 * t1[i] + t0[i]).collect();
    let (rn, vn) = (r.iter().map(|a| a * a).sum::<f64>().sqrt(), v.iter().map(|a| a * a).sum::<f64>().sqrt());
    if !(vn > 1e-15 && rn.is_finite()) {
        return None;
    }
    let alpha = (-rn / vn).clamp(-max_step, -1.0);
    if alpha > -1.0 - 1e-9 {
        return None;
    }
    let th: Vec<f64> = (0..t0.len()).map(|i| t0[i] - 2.0 * alpha * r[i] + alpha * alpha * v[i]).collect();
    th.iter().all(|a| a.is_finite()).then_some((th, alpha))
}

/// SQUAREM's longest jump, in EM steps, at first and at most.
const SQUAREM_FIRST_MAX_STEP: f64 = 4.0;
const SQUAREM_LARGEST_STEP: f64 = 64.0;

/// The parameters EM moves.
#[derive(Clone)]
struct EmState {
    pose: Pose,
    latent: Vec<f64>,
    sigma2: f64,
}

/// What one fit is of: the model, the view, the data and the priors.
#[derive(Clone, Copy)]
struct FitInputs<'a> {
    model: &'a LinearModel,
    view: View<'a>,
    x: &'a ViewPoints,
    prior: Option<(&'a [f64], &'a LatentStep)>,
    support: Option<Support>,
    opts: &'a RegisterOptions,
    norm: &'a Normalization,
}

/// One fit's inputs and reused buffers.
struct EmRun<'a> {
    inputs: FitInputs<'a>,
    estep: EStep,
    post: Posteriors,
    /// The model at the state's latent, in its own frame and posed.
    y_model: Vec<P3>,
    y_world: Vec<P3>,
    /// The view's mixing weights (`View::weights`) of the last refresh, and whether there are any.
    weights: Vec<f64>,
    has_weights: bool,
    /// The model's points touching the support (`Support::contact`).
    contact: Vec<usize>,
}

impl<'a> EmRun<'a> {
    pub(super) fn new(inputs: FitInputs<'a>) -> Self {
        let m = inputs.model.len();
        let mut estep = inputs.x.estep();
        estep.use_model_order(inputs.model.block_order(), m);
        Self {
            estep,
            post: Posteriors::default(),
            y_model: Vec::with_capacity(m),
            y_world: Vec::with_capacity(m),
            weights: Vec::new(),
            has_weights: false,
            contact: Vec::new(),
            inputs,
        }
    }

    pub(super) fn scale_range(&self) -> (f64, f64) {
        scale_bounds(self.inputs.opts, self.inputs.norm)
    }
}

impl EmMap for EmRun<'_> {
    type State = EmState;

    fn load(&mut self, st: &EmState) {
        self.inputs.model.evaluate_into(&st.latent, &mut self.y_model);
        self.y_world.clear();
        self.y_world.extend(self.y_model.iter().map(|y| st.pose.apply(y)));
    }

    fn step(&mut self, st: &mut EmState, refresh_weights: bool) -> Option<f64> {
        let (x, opts, norm) = (self.inputs.x.points(), self.inputs.opts, self.inputs.norm);
        let sigma2 = st.sigma2;
        if refresh_weights {
            self.has_weights = self.inputs.view.weights(&st.pose, &self.y_world, sigma2, &mut self.weights).is_some();
        }
        let w = self.has_weights.then_some(self.weights.as_slice());
        self.estep.run_weighted(&self.y_world, w, sigma2, opts.outlier_weight, &mut self.post);
        let post = &self.post;
        let nll = post.neg_log_likelihood;
        if !(post.np > 1e-9) {
            return None;
        }
        // Pose.
        let pose = &mut st.pose;
        let step = weighted_similarity(x, &self.y_model, post, opts.estimate_scale);
        pose.r = step.rotation;
        pose.s = if opts.estimate_scale {
            // MAP scale: the data term (s²·yy − 2s·tr)/2σ² plus (s − s0)²/2τ².
            let std = opts.scale_prior_std.unwrap_or(LOOSE_SCALE_PRIOR_STD);
            let (s0, tau) = (norm.scale, std.max(1e-6) * norm.scale);
            let s_map = (step.trace / sigma2 + s0 / (tau * tau)) / (step.yy / sigma2 + 1.0 / (tau * tau));
            let (smin, smax) = self.scale_range();
            s_map.clamp(smin, smax)
        } else {
            norm.scale
        };
        // Translation re-derived for a clamped scale: t = μx − s R μy.
        pose.t = fitted_translation(x, &self.y_model, post, pose);
        // The support moves the translation along up: the data term is
        // Np/2σ²·|t − t*|² about the fitted t*, the support's K/2σ²·(height −
        // h̄)², so the optimum takes K/(Np + K) of the gap.
        let support = self.inputs.support;
        let touching = support.and_then(|sp| sp.contact(pose, &self.y_model, &mut self.contact));
        if let (Some(sp), Some(c)) = (support, touching) {
            pose.t += sp.up * (sp.weight / (1.0 + sp.weight) * (c.target - c.mean));
        }
        // Latent (MAP): (Σ P1 BᵀB + σ²/s² Λ⁻¹) ℓ = Σ Bᵀ(PX̃ − P1 ȳ).
        if let Some((var, step)) = self.inputs.prior {
            if !st.latent.is_empty() {
                let reg = sigma2 / (pose.s * pose.s) * opts.latent_prior_weight;
                let row = support.zip(touching).map(|(sp, c)| sp.latent_row(step, pose, &self.contact, c.target));
                let (mut a, mut b) = step.sums(post, pose, None).system(step.q, (1.0, 0.0, 1.0), reg, var);
                if let Some((g, e)) = &row {
                    add_support_term(&mut a, &mut b, g, *e, support.map_or(0.0, |sp| sp.weight) * post.np);
                }
                if let Some(sol) = solve(a, b) {
                    st.latent.copy_from_slice(&sol);
                    self.inputs.model.evaluate_into(&st.latent, &mut self.y_model);
                }
            }
        }
        for (w, y) in self.y_world.iter_mut().zip(&self.y_model) {
            *w = pose.apply(y);
        }
        // σ² from the sufficient statistics.
        let mut num = 0.0;
        for (xn, w) in x.iter().zip(&post.pt1) {
            num += w * (xn[0] * xn[0] + xn[1] * xn[1] + xn[2] * xn[2]);
        }
        for i in 0..self.y_world.len() {
            let (y, px) = (&self.y_world[i], &post.px[i]);
            num += post.p1[i] * (y[0] * y[0] + y[1] * y[1] + y[2] * y[2])
                - 2.0 * (px[0] * y[0] + px[1] * y[1] + px[2] * y[2]);
        }
        st.sigma2 = (num / (3.0 * post.np)).abs().max(1e-10);
        Some(nll)
    }

    fn extrapolate(&self, s0: &EmState, s1: &EmState, s2: &EmState, max_step: f64) -> Option<(EmState, f64)> {
        let var = self.inputs.prior.map(|(var, _)| var);
        let coords = JumpCoords::new(&s0.pose, var, s0.latent.len(), self.scale_range());
        let pack = |s: &EmState| coords.pack(&s.pose, &[s.sigma2], &s.latent);
        let (th, alpha) = squarem_jump(&pack(s0), &pack(s1), &pack(s2), max_step)?;
        let (pose, variances, latent) = coords.unpack(&th, 1);
        Some((EmState { pose, latent, sigma2: variances[0] }, alpha))
    }
}
