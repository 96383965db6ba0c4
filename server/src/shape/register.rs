//! Online registration (paper §II-A, eq. 5, done as a product must): from one
//! segmented, partial, noisy cloud of a tool in an unknown pose, estimate the
//! latent shape ℓ, the rotation, translation and scale together.
//!
//! The observed points are the data of a Gaussian mixture centred on the
//! deformed, posed canonical model points, plus a uniform outlier term (CPD's
//! direction: unseen model points cost nothing, so occlusion is harmless).
//! EM: the E-step of CPD; the M-step alternates a closed-form weighted
//! similarity (pose, scale) and a closed-form MAP latent update (the model is
//! affine in ℓ, with the PCA variances as the Gaussian prior). σ² is
//! re-estimated every iteration, so the fit anneals from coarse to fine.
//!
//! The pose is unknown, so several rotation hypotheses (principal axes of the
//! view against the canonical's, and, when the world's up is known, the tool
//! upright at several yaws) are first scored cheaply on small subsets with
//! the mean shape; the best survive to the full latent fit, which ends with a
//! few iterations on a model twice as dense (the polish).
//!
//! Here: the options, the result and the stages in order
//! (`Registrar::register`). Beside it: `em` (the EM every stage runs, its
//! SQUAREM acceleration, the pose, the view's visibility weights and the
//! table's support), `starts` (the coarse stage's starting poses and the
//! test of a view showing its tool standing), `sweep` (the turn about the
//! tool's axis a view leaves open), `viewpoint` (the camera's position when
//! not given) and `surfels` (the polish's anisotropic fit).

use super::estep::{dist2, EStep, P3};
use super::freespace::FreeSpace;
use super::grid::RadiusGrid;
use super::sampling::{drop_far_points, drop_stray_points, even_subsample, subsample, BulkBox, TableBand};
use super::space::{AnchoredModel, LinearModel, NamedPoint, ShapeSpace};
use nalgebra::{Matrix3, Point3, Unit, UnitQuaternion, Vector3};
use rand::SeedableRng;
use serde::Serialize;
use std::time::Instant;

mod em;
mod latent;
mod starts;
mod surfels;
mod sweep;
mod unexplained;
mod viewpoint;

use em::{em, Fit, Pose, Support, View, ViewPoints, REST_POSE_COS};
use latent::LatentStep;
use starts::{principal_frame, side_facing, Starts, UPRIGHT_ONE_WAY, UPRIGHT_SIDE_FACING};

use sweep::{sweep_axis, SweptTurns, TurningLine, YawSweep};
use unexplained::AzimuthMasks;
use viewpoint::estimate_viewpoint;

#[derive(Debug, thiserror::Error, PartialEq)]
pub enum RegisterError {
    #[error("empty cloud")]
    Empty,
    #[error("cloud has a non-finite coordinate at point {0}")]
    NonFinite(usize),
    #[error("cloud has {got} points; a fit needs at least {need}")]
    TooFewPoints { got: usize, need: usize },
    #[error("cloud has no extent (all its points, or all but a few, at one place)")]
    Degenerate,
    #[error("cloud extent {extent_m:.3} m is not a hand-held tool's (expected {min_m} to {max_m} m); check the units")]
    AbsurdScale { extent_m: f64, min_m: f64, max_m: f64 },
}

#[derive(Clone, Copy, Debug, Serialize, serde::Deserialize)]
pub struct RegisterOptions {
    /// The world's up direction in the cloud's frame, if known (a table prior).
    pub up: Option<[f64; 3]>,
    /// The camera's origin in the cloud's frame, if known (the origin for a
    /// cloud in the camera frame). Model points facing away from it get a
    /// small mixing weight: they cannot have produced an observation.
    pub viewpoint: Option<[f64; 3]>,
    /// A second camera's origin in the cloud's frame, when the cloud merges
    /// two cameras' views (a robot's second look): model points facing it
    /// and not behind a surface it saw (its own range image) keep their full
    /// mixing weight though the first camera (`viewpoint`) does not see
    /// them. Used only with `viewpoint`; given alone, it is taken as
    /// `viewpoint`. Measured (eval transfer --second-view, mug test, seeds 7
    /// / 11, median / p90 mm): the first camera alone 1.88 / 3.68, 2.12 /
    /// 4.35; both, facing only 1.64 / 3.61, 1.73 / 3.31; both with the
    /// second's range image 1.48 / 3.20, 1.63 / 2.96.
    #[serde(default)]
    pub second_viewpoint: Option<[f64; 3]>,
    /// Estimate a uniform scale on top of the latent shape.
    pub estimate_scale: bool,
    /// Fit the latent shape (false: the undeformed mean shape, pose only).
    pub fit_latent: bool,
    /// Allowed scale relative to the category's canonical size.
    pub scale_range: (f64, f64),
    /// Weight of the latent's Gaussian prior relative to the textbook MAP.
    /// Neighbouring points of one depth view are not independent evidence
    /// (noise and missing surface are correlated), so the data term overstates
    /// its certainty. 2 since the spaces keep their small modes: measured
    /// with all 9 (before the refine re-annealed), eval transfer --views
    /// 12, seed 7, test keypoint median / p90, weight 10 /
    /// 4 / 2 / 1: drill 2.39 / 5.31, 2.30 / 5.30, 2.18 / 5.07, 2.08 / 4.74
    /// mm; hammer 2.47 / 4.88, 2.31 / 4.42, 2.09 / 4.07, 2.00 / 4.48; mug
    /// 2.81 / 10.4, 2.57 / 14.3, 2.40 / 11.8, 2.33 / 14.7 (the mug's p90
    /// lies in views that hide its handle: see the next option).
    pub latent_prior_weight: f64,
    /// The same for a view that leaves the pose open
    /// (`FitQuality::ambiguous_pose`: a mug's handle hidden): such a view
    /// says little about the shape either, and a looser latent takes the
    /// wrong pose's shape. None: `latent_prior_weight`. Measured (mug, seeds
    /// 7 / 11 / 23, test keypoint median / p90, with weight 2): None 2.40 /
    /// 11.8, 2.32 / 7.6, 2.47 / 12.6 mm; 10: 2.40 / 10.9, 2.34 / 7.6, 2.56 / 9.2.
    pub ambiguous_latent_prior_weight: Option<f64>,
    /// The refine starts at the race's σ² plus this many times the shape
    /// space's own per-coordinate variance (the training shapes about the
    /// mean, scaled to the pose), then anneals. From the race's σ² alone
    /// (3-5 mm), a part whose length is a latent mode settled where it was:
    /// a hammer handle 50 mm longer than the mean shape's, its end in view,
    /// was fitted 17-37 mm short (the observed end is explained as outliers,
    /// and the points along a uniform handle hold the model where it lies);
    /// started at the training latent, the same fit stayed within 2 mm. 0:
    /// off. Measured (9 modes, weights 2 / 10, seed 7, hammer training
    /// keypoint p90): 0 6.6 mm, 4 5.6, 16 3.9; test median / p90 2.09 / 4.07
    /// → 2.09 / 3.82 mm. The rigid baseline (no latent) does not re-anneal.
    /// Its cost: the refine's E-steps are denser at the larger σ (refine
    /// stage 1.1 → 1.9 ms on the mug, `bench_register`), and hammers grasped
    /// from the camera are registered 2-4 % smaller than before (their latent
    /// now takes the length), which `sim nail --grasp-from register` felt on
    /// two tools that tip as the hand closes (see the README).
    pub refine_shape_sigma2: f64,
    /// Std of the Gaussian prior on the relative scale (around 1): without it,
    /// scale and the latent size modes trade freely on a partial view.
    /// `None`: the category's ([`default_scale_prior_std`]).
    pub scale_prior_std: Option<f64>,
    pub outlier_weight: f64,
    pub coarse_points: usize,
    pub coarse_model_points: usize,
    pub coarse_iters: usize,
    /// Iterations after which coarse starts that have met are merged (see
    /// `COARSE_MERGE_ANGLE`); 0, or `coarse_iters` or more, turns merging off.
    /// Measured (`bench_register`, p50): drill 4.75 → 4.43 ms, hammer 4.90 →
    /// 4.58 ms, mug unchanged; eval transfer --split test --views 32 medians
    /// unchanged within 0.02 mm.
    pub coarse_merge_after: usize,
    pub fine_points: usize,
    pub fine_iters: usize,
    /// Observed points and iterations of the polish: the refine's fit
    /// continued on a model twice as dense (0: none). See `POLISH_MODEL_POINTS`.
    pub polish_points: usize,
    pub polish_iters: usize,
    /// Polish with surfel components (see `estep::Surfels`): each model
    /// point's Gaussian flat along the surface, σ_n² along its normal and
    /// σ_t² across, instead of one σ² for both. Isotropic components must
    /// stay as wide as the model's point spacing (5-6 mm on the 800-point
    /// polish model) and blur the fit along the view, where a depth camera
    /// is most precise; a surfel's σ_n falls to the sensor's noise (0.9 mm
    /// here). Latent fits only: the rigid canonical, fitted this way, got
    /// worse (mug test median 3.44 → 3.92 mm, seed 7). Measured, eval
    /// transfer --views 12, seeds 7 / 11 / 23, means, test keypoint median /
    /// p90 (mm), off → on: mug 2.35 / 8.3 → 1.92 / 8.7 (views not flagged
    /// ambiguous: median 2.09 → 1.65), drill 2.26 / 4.9 → 2.23 / 5.0, hammer
    /// 1.98 / 3.8 → 1.95 / 3.7; training tools mug 2.16 → 1.96, drill 1.40
    /// → 1.25, hammer 1.52 → 1.42; keypoint depth bias (median along the
    /// view) mug −0.98 → −0.33, drill +0.46 → +0.15, hammer −0.10 → −0.03 mm. Cost: the
    /// polish stage about twice as long (`bench_register`, 2-core Xeon, p50:
    /// mug 2.2 → 4.6 ms, hammer 2.4 → 4.2).
    pub surfels: bool,
    /// The final fit stops when the relative change of the negative log-likelihood falls below this.
    pub tol: f64,
    /// The same for the coarse stage and the race, whose job is to rank poses, not to polish one.
    pub ranking_tol: f64,
    /// Yaw hypotheses of the upright tool when `up` is known.
    pub yaws: usize,
    /// Hypotheses kept from the coarse stage for the race at full resolution.
    pub keep: usize,
    /// More coarse hypotheses raced when the race's best contradicts the
    /// view (free-space violation over `RACE_CONTRADICTED`): the coarse
    /// stage ranks on the mean shape at 80 points, and a tool far from the
    /// mean shape can leave its true pose fifth or sixth. A reserve takes
    /// the lead only by `AMBIGUITY_MARGIN`. Measured, `eval transfer
    /// --category mug --views 12`, seeds 7 / 11 / 23, 0 → 2: training
    /// keypoint p90 15.0 / 11.2 / 21.9 → 12.5 / 11.2 / 20.6 mm (four views'
    /// poses found again, none lost), test identical; on its side
    /// (`--on-side --views 8 --seed 11`) training p90 28.8 → 16.1; drill
    /// and hammer identical; `bench_register mug` the same speed (one of 24
    /// views races the reserve).
    #[serde(default)]
    pub keep_contradicted: usize,
    /// Iterations of each hypothesis in that race, and the observed points it uses.
    pub race_iters: usize,
    pub race_points: usize,
    /// Race penalty (nats per observed point) of a tool upside down relative to
    /// its canonical rest pose, scaled by (1 − cos tilt)/2 (half on its side).
    /// Needs `up`. Tools on a table mostly rest as they were modelled; without
    /// it a flat hammer flipped over its handle explains a view about as well.
    pub upright_prior: f64,
    /// Turns about the up axis scored around the race's winner (0: no sweep).
    /// 16 (22.5°): measured on eval transfer mug --views 12, seeds 7, 11, 23,
    /// test / train keypoint p90 12.9 / 25.8 mm against 15.6 / 26.7 with 24
    /// and 17.1 / 26.1 with 12, drill and hammer the same for all three, and
    /// each turn costs two dense E-steps on the polish model.
    pub yaw_sweep_steps: usize,
    /// Score margin (nats per observed point) within which swept turns explain the view equally well.
    /// 0.08: on the polish model's smoother scores, eval transfer mug --views 12, seeds 7, 11, 23,
    /// test / train keypoint p90 10.3 / 24.7 mm (0.03: 20.1 / 28.1; 0.05: 12.9 / 25.8; 0.12:
    /// 11.4 / 22.8 with a third of training views flagged), drill and hammer the same.
    pub yaw_sweep_margin: f64,
    /// Screen the sweep's turns on the race's sparser model first and score
    /// only those near its best on the dense one (see `SWEEP_SCREEN_MARGIN`).
    /// Measured (`VIEWPOINT=known bench_register C 3`, two alternating pairs,
    /// race stage p50): mug 3.6 / 3.5 → 2.1 / 2.2 ms, drill 2.7 / 3.0 → 1.3 /
    /// 1.4, hammer 3.2 / 3.1 → 1.5 / 1.7; eval transfer keypoint errors
    /// identical (mug seeds 7, 11, 23 with and without the camera position
    /// and on its side, drill and hammer seed 7 without it).
    pub yaw_sweep_screen: bool,
    /// Race the sweep's challenger (a turn outside the arc whose likelihood,
    /// without the free-space penalty, beats every turn in the arc by this
    /// many nats per point; see `sweep`) from the race's start and take it
    /// if its score beats the lead's. The race poses the mean shape, and a
    /// handle turned to the camera that the mean shape's handle overhangs
    /// is penalised at its true turn. None: no challenger.
    /// Measured, `eval transfer --category mug --views 12`, seeds 7 / 11 /
    /// 23 / 31 / 47 / 59, test and train: 0.03 against None, six views
    /// 65-174° off found again (five of training mugs, and `mug_test_01`
    /// view 3 of seed 31, 173° off with its handle facing the camera), none
    /// lost; test keypoint p90 seed 31 12.5 → 9.3 mm, the others identical;
    /// training 20.6 / 11.9 / 19.4 → 16.6 / 10.3 / 17.8 (seeds 23 / 31 /
    /// 47), the others identical. 0.1 found two; 0.0 four more and lost two
    /// (nothing told those challengers apart: they led by 0.01-0.32 nats
    /// whether right or wrong). Drill and hammer (seeds 7 / 11 / 23, and
    /// on their side), the mug on its side: identical; the mug without the
    /// camera's position (`--unknown-viewpoint --views 8`, seeds 7 / 11):
    /// training p90 32.0 / 44.1 → 27.9 / 37.1 mm, test identical. Where no
    /// challenger is named it costs nothing (`bench_register mug` names none).
    #[serde(default)]
    pub sweep_challenger_margin: Option<f64>,
    /// Where the yaw arc is open, count at each turn of the finished fit
    /// the view's points its shape leaves unexplained, and turn it to the
    /// turns that leave fewest (see `unexplained`): a handle peeking past
    /// the body settles what the sweep's averaged scores could not. The
    /// reported `yaw_arc` narrows with it (and `ambiguous_pose` with
    /// `narrowing_settles_ambiguity`). Measured, `eval transfer --category mug --views 12`,
    /// seeds 7 / 11 / 23 / 31 / 47 / 59, against false: ten training views
    /// 20-54° off brought to 1-10°, one 124° off moved to 168°; test
    /// identical on all six seeds; training keypoint p90 12.5 / 11.2 / 16.6
    /// / 10.3 / 17.8 / 14.3 → 12.5 / 11.2 / 13.7 / 9.6 / 13.7 / 11.9 mm;
    /// the canonical baseline's six views better, none worse. Without the
    /// camera's position (`--unknown-viewpoint --views 8`, seeds 7 / 11):
    /// training p90 27.9 / 37.1 → 27.9 / 35.0. Drill, hammer, the three on
    /// their side and the YCB scans: identical. Cost: 0.4 ms on a
    /// 15,000-point view with an open arc (a fifth of a mug's fits), none
    /// elsewhere.
    #[serde(default)]
    pub narrow_by_unexplained: bool,
    /// Where the narrowing names one run of turns under 30° wide, and the
    /// finished shape leaves at most 1 % of the view unexplained there, the
    /// sweep's wider arc no longer makes the pose ambiguous, nor does a
    /// race rival that is the fit turned to a turn the counts refute (one
    /// leaving more points unexplained than the run). Other rivals (end
    /// over end, off the rest pose) stand. Measured, `eval transfer
    /// --category mug --views 12`, seeds 7 / 11 / 23 / 31 / 47 / 59,
    /// against false: five training views 1-10° off no longer flagged
    /// (ambiguous share seeds 23 / 31 / 47 0.317 / 0.258 / 0.267 → 0.300 /
    /// 0.250 / 0.250), none wrong unflagged (the misled share unchanged);
    /// without the 1 % bar a view 168° off (`mug_train_04`, 4 % unexplained
    /// at every turn) was. Test views, keypoints and arcs identical; the
    /// same with the camera not given (`--unknown-viewpoint --views 8`,
    /// seeds 7 / 11: one more training view unflagged) and with a leaking
    /// mask (`--mask-leak-px 4 --unknown-table --views 6 --seed 7`).
    #[serde(default)]
    pub narrowing_settles_ambiguity: bool,
    /// Accelerate the refine's latent fit with SQUAREM steps (see `em`; the
    /// polish: `accelerate_polish`).
    /// Measured, eval transfer --views 12, seeds 7 / 11 / 23, test keypoint
    /// median / p90 (mm) off → on: mug 2.95 / 12.6, 2.63 / 8.5, 2.89 / 9.8 →
    /// 2.76 / 11.3, 2.54 / 8.2, 2.83 / 9.4; hammer 2.61 / 5.4, 2.64 / 5.2,
    /// 2.76 / 6.8 → 2.58 / 5.2, 2.48 / 5.1, 2.68 / 6.5; drill 2.49 / 5.5, 2.55
    /// / 5.3, 2.75 / 5.5 → 2.57 / 5.6, 2.68 / 5.4, 2.64 / 5.7 (its training
    /// median 1.57 / 1.61 / 1.60 → 1.47 / 1.48 / 1.49: nearer the data is not
    /// always nearer an unseen drill). Refine stage p50 (`bench_register`)
    /// 0.1-0.7 ms shorter: the fits still end at `fine_iters` more often than
    /// at `tol`, and 20 iterations cost the mug's p90 (seed 7 11.3 → 13.9 mm).
    pub accelerate: bool,
    /// Accelerate the surfel polish with SQUAREM steps too (the same driver,
    /// `em::squarem`). Plain, its σ_n falls and its σ_t and latent drift a
    /// little further each iteration, still moving at the 10th (a test mug's
    /// view: the first mode −2.21 → −1.80 over them), and SQUAREM takes it
    /// nearer convergence in the same iterations and time. On clean views
    /// that gained a little; with 2 mm depth noise and 10 % outliers it lost
    /// more (the unconverged polish is the better fit there), so it is off.
    /// Measured, eval transfer, test keypoint median / p90 mm, off → on:
    /// clean (--views 12, means of seeds 7 / 11 / 23) mug 1.72 / 8.68 →
    /// 1.70 / 8.59, drill 1.63 / 4.19 → 1.57 / 4.31, hammer 1.47 / 3.37 →
    /// 1.47 / 3.06 (fresh seeds 31 / 47 / 59: mug 1.76 / 11.90 → 1.70 /
    /// 11.58); --outliers 0.1 --noise-mm 2 (--views 8, the same seeds) drill
    /// 2.05 / 4.54 → 2.06 / 4.81 (training median 1.61 → 1.73), hammer
    /// 1.82 / 3.75 → 2.01 / 3.88 (training 1.60 → 1.82; the polish's
    /// latent prior at twice or four times its weight did not mend it: 2.02
    /// and 1.99; nor an outlier weight of 0.2: 2.00, plain 1.80), mug (seed
    /// 7) 2.44 / 22.3 → 2.48 / 22.3.
    pub accelerate_polish: bool,
    /// Subsample the view evenly over its surface (one point per voxel)
    /// instead of uniformly over its points. A depth view is dense where the
    /// tool faces and is near the camera; thin parts that settle the pose (a
    /// mug's handle) are few of its points and would be few of a random subset.
    pub even_sampling: bool,
    /// With `up`, also start from the tool lying on its side (the canonical
    /// turned ±90° about its x axis, at each of the `yaws`), besides upright.
    /// None: only for categories whose canonical's principal axes are too
    /// alike to settle the pose from a view's, and then only where the view
    /// does not show a tool standing upright (`UPRIGHT_SIDE_FACING`) (the mug: a mug knocked over,
    /// test views on its side, 8 views: keypoint error median / p90 9.1 / 115
    /// → 4.0 / 9.2 mm). It doubles the coarse stage's hypotheses (mug fit p50
    /// 5.9 → 7.5 ms, `bench_register`), and for an elongated tool the principal axes already cover its
    /// sides while the extra starts let a flat hammer's view be explained on
    /// its edge (hammer train p90 7.9 → 20 mm with them).
    pub lying_hypotheses: Option<bool>,
    /// Where the lying starts were made, also race the race's winner turned
    /// end over end (180° about the canonical's x axis: a mug's rim and base
    /// swapped, its handle kept), and call the pose ambiguous
    /// (`FitQuality::ambiguous_pose`) when that explains the view within
    /// `AMBIGUITY_MARGIN` of it. A mug on its side seen across its body,
    /// neither its inside nor its base in view, fits almost as well either
    /// end first: of 156 views on their side (seed 7) 16 ended more than 45°
    /// off, most of them end over end, and 4 of those were not flagged; with
    /// the check all 16 are. Measured (mug, `eval transfer --views 12
    /// --on-side`, seeds 7 / 11 / 23): keypoint median / p90 unchanged
    /// (test 2.14 / 18.32 → 2.15 / 18.32, train 1.88 / 25.08 → 1.88 / 25.07
    /// mm), views flagged test 12 → 17 %, train 18 → 28 %, and the keypoint
    /// p90 of the views not flagged test 8.99 → 6.25, train 6.75 → 4.55 mm
    /// (means of the three); about 0.3 ms more a fit on those views. Without
    /// the camera's position (`--unknown-viewpoint`, seed 7) test / train
    /// median 2.53 / 2.65 → 2.64 / 2.69 mm (flagged views fit with the
    /// stronger latent prior), p90 unchanged, unflagged p90 11.34 / 7.22 →
    /// 10.32 / 4.65 mm. Standing views and the drill and hammer (no lying
    /// starts) are untouched.
    pub flip_check: bool,
    /// The race's runner-up (another basin, at least 30° from the lead)
    /// within this many nats a point of the lead's score gets the latent
    /// fits too, when the lead is off the category's rest pose; the
    /// runner-up's finished fit is reported when it scores better by more
    /// than `AMBIGUITY_MARGIN`, and within it the pose is ambiguous. None:
    /// the race decides. The race ranks poses on the mean shape, and a tool
    /// far from it lost its true pose there: a training hammer on its side
    /// turned half round, claw and face swapped. Measured, `eval transfer
    /// --on-side --views 8`, seeds 7 / 11 / 23, keypoint p90 mm, None →
    /// Some(1.0): hammer train 22.1 / 20.4 / 19.4 → 7.2 / 5.6 / 3.7 (sure and
    /// wrong, `misled_fraction`, 10.0 / 11.2 / 6.2 → 6.2 / 5.0 / 5.0 %), test
    /// 2.8 / 3.4 / 4.7 → 2.8 / 3.0 / 3.9; mug train 12.0 / 39.1 / 6.4 → 12.0
    /// / 28.8 / 5.1, test 8.6 / 5.5 / 10.6 → 8.6 / 7.1 / 9.5; drill the
    /// same. Swapping whenever the runner-up scored better at all: mug test
    /// 10.9 / 7.1 (seeds 7 / 11). At rest (an upright mug) it does not run:
    /// the yaw sweep has settled the turn the view leaves open there, and a
    /// runner-up finished without the sweep took an edge of that arc (mug
    /// test p90, seeds 7 / 11 / 23: 10.8 / 6.8 / 8.5 → 10.8 / 6.1 / 22.8 when
    /// it ran). Cost where it runs: a hammer on its side p50 4.5-5.8 →
    /// 6.5-6.8 ms.
    #[serde(default)]
    pub recheck_runner_up: Option<f64>,
    /// Without `viewpoint`, estimate the camera's position from the view and
    /// the best coarse fit, and again from the race's winner, and fit from
    /// there on as if it were given (see `estimate_viewpoint`; reported as
    /// `Registration::estimated_viewpoint`). Measured (eval transfer
    /// --unknown-viewpoint, 8 views, test / train median keypoint error): mug
    /// 5.16 / 4.43 → 3.30 / 2.90 mm, drill 3.26 / 2.87 → 2.90 / 2.11 mm;
    /// hammers (flat: the estimate rarely settles) unchanged; 1.5-2 ms more a fit.
    pub estimate_viewpoint: bool,
    /// The plane the tool rests on, when the caller knows it (a table top):
    /// up·x = this height in the cloud's frame (needs `up`). The latent fits
    /// (refine and polish) then hold the tool's lowest point on it (see
    /// `Support`). A view from above shows nothing of a tool's underside:
    /// without it the completed shape's lowest point floated or sank 2-3 mm
    /// (10th and 90th percentiles, eval transfer --views 12 --seed 7), and
    /// the latent and scale that set the tool's height with it. Measured,
    /// eval transfer --views 12, seeds 7 / 11 / 23, test keypoint median /
    /// p90 (mm), without → with: mug 1.77 / 9.8, 1.97 / 7.9, 2.03 / 8.5 →
    /// 1.79 / 10.3, 1.71 / 8.4, 1.97 / 8.7; drill 2.32 / 5.1, 2.10 / 4.6,
    /// 2.27 / 5.4 → 2.11 / 4.9, 1.96 / 5.0, 2.12 / 5.0; hammer 2.05 / 3.5,
    /// 1.81 / 3.6, 2.00 / 4.1 → 1.71 / 3.9, 1.61 / 4.3, 1.65 / 4.8 (the
    /// hammer's p90: one test hammer's head_top, 1 mm further along the
    /// handle once its head's height is held: the two share modes); training
    /// medians mug 1.88 / 1.97 / 2.04 → 1.82 / 1.85 / 1.97, drill 1.24 /
    /// 1.25 / 1.27 → 1.16 / 1.20 / 1.19, hammer 1.48 / 1.35 / 1.42 → 1.38 /
    /// 1.29 / 1.38.
    pub support_height: Option<f64>,
    /// How strongly the support holds, as a share of the observed points'
    /// weight (see `Support`). 0.1 measured alike (seed 7, test median /
    /// p90: mug 1.80 / 10.7, drill 2.17 / 5.2, hammer 1.67 / 3.8 mm).
    pub support_weight: f64,
    pub seed: u64,
}

impl Default for RegisterOptions {
    fn default() -> Self {
        Self {
            up: Some([0.0, 0.0, 1.0]),
            viewpoint: None,
            second_viewpoint: None,
            estimate_scale: true,
            fit_latent: true,
            scale_range: (0.6, 1.6),
            scale_prior_std: None,
            latent_prior_weight: 2.0,
            ambiguous_latent_prior_weight: Some(10.0),
            refine_shape_sigma2: 16.0,
            outlier_weight: 0.1,
            coarse_points: 80,
            coarse_model_points: 100,
            // 10 iterations and tol 3e-5 saved 0.4-0.6 ms (mug 5.55 → 4.93 ms
            // p50) but the mug lost its pose more often: eval transfer --views 16,
            // seeds 7 and 8, mug p90 test 16.1 / 8.3 → 35.0 / 17.1 mm, train
            // 32.2 / 40.3 → 57.4 / 43.8 mm. The coarse ranking needs converged fits.
            coarse_iters: 15,
            coarse_merge_after: 5,
            fine_points: 400,
            fine_iters: 40,
            polish_points: 800,
            polish_iters: 10,
            surfels: true,
            tol: 1e-5,
            ranking_tol: 1e-4,
            yaws: 6,
            keep: 4,
            keep_contradicted: 2,
            race_iters: 10,
            race_points: 200,
            upright_prior: 0.1,
            yaw_sweep_steps: 16,
            yaw_sweep_margin: 0.08,
            yaw_sweep_screen: true,
            sweep_challenger_margin: Some(0.03),
            narrow_by_unexplained: true,
            narrowing_settles_ambiguity: true,
            accelerate: true,
            accelerate_polish: false,
            even_sampling: true,
            lying_hypotheses: None,
            flip_check: true,
            recheck_runner_up: Some(1.0),
            estimate_viewpoint: true,
            support_height: None,
            support_weight: 0.5,
            seed: 0,
        }
    }
}

/// A race's best fit whose free-space violation exceeds this sends the
/// reserve hypotheses to the race (`RegisterOptions::keep_contradicted`).
/// Right fits violate 0.00-0.02 (see `FitQuality::contradicted_fraction`);
/// the training mugs whose coarse stage lost the true pose, 0.05-0.09.
const RACE_CONTRADICTED: f64 = 0.04;

/// Inlier fraction from which a fit is called confident. Measured on
/// single views (`confidence_scan 8`: the three test tools of each category
/// and the YCB scans, each registered as all three categories): the test
/// tools as their own category 0.82-0.98, with 2 mm depth noise and 10 %
/// outliers 0.63-0.88 (65 of 72 views confident); another category's tool
/// at most 0.64, 0.58 with the noise (none of 432 views confident); the YCB
/// mug 0.82-0.98, hammer 0.60-0.86, drill 0.46-0.65 (its scan lies outside
/// the procedural family's span).
pub const CONFIDENT_INLIER_FRACTION: f64 = 0.7;

/// What else a confident fit needs (see the fields of [`FitQuality`]).
/// Measured on single views (`eval transfer --views 12`, all three
/// categories, seeds 7 / 11 / 23, and with ±30 % scale, 10 % outliers and
/// 2 mm noise, unknown camera and table, mugs on their side: about 3,000
/// views): coverage 0.19 or more (a mug on its side; 0.22 upright), latent
/// length at most 7.7, and no view's verdict changed by these rules.
/// Degenerate clouds (a blob 6 mm wide, two or three points repeated, one
/// point repeated with a few scattered) cover 0.000-0.064; shapes folded
/// onto a line of points, latent 9-14. A real view thinned to 60 points
/// still covers 0.28-0.33 (the radius follows the points' spacing).
pub const CONFIDENT_COVERAGE: f64 = 0.12;
pub const CONFIDENT_LATENT_MAHALANOBIS: f64 = 10.0;
pub const CONFIDENT_VIEW_WIDTH_MM: f64 = 5.0;

/// Points of the view and of the completed surface the coverage is counted on.
const COVERAGE_SAMPLES: usize = 400;
/// Points of the view the inlier fraction is counted on (a uniform sample;
/// 400 cost 0.02 ms less and called 145 rather than 150 of the 156 noisy
/// drill views confident, `eval transfer --outliers 0.1 --noise-mm 2`).
const QUALITY_POINTS: usize = 600;
/// The largest coverage radius, in inlier radii (a view sparser than this
/// covers less than it shows).
const COVERAGE_REACH: f64 = 2.5;

/// How well the fitted shape explains the cloud.
#[derive(Clone, Copy, Debug, Serialize, PartialEq)]
pub struct FitQuality {
    /// Fraction of the cloud, less the table's points, within `inlier_mm`
    /// of the completed shape (measured on a uniform sample of the points
    /// kept; the other points set aside count as outside).
    pub inlier_fraction: f64,
    /// Fraction of the cloud set aside before the fit: isolated points
    /// (flying pixels, speckle, segmentation leaks), points far from the
    /// cloud's bulk, and the given table's points.
    pub stray_fraction: f64,
    /// The same as a count of the cloud's points (for a cloud above
    /// [`WORKING_POINTS`], estimated from the working subsample's share).
    pub stray_points: usize,
    /// Of `stray_points`, those set aside as a leaking segmentation's table
    /// ([`TableBand`]: the given table's, or the one the leak shows; 0 when
    /// the view does not leak or no up direction is known).
    pub table_points: usize,
    /// RMS distance of the inliers to the completed shape, millimetres.
    pub residual_mm: f64,
    pub inlier_mm: f64,
    /// Fraction of the completed shape's surface near a point of the cloud
    /// (within `inlier_mm`, or twice the cloud's median point spacing where
    /// that is larger, at most 2.5 × `inlier_mm`): how much of the tool the
    /// view shows. One camera
    /// view shows a quarter to a half of a tool; a line of points, a blob a
    /// few millimetres wide or a handful of distinct points lie on the
    /// surface of almost any shape (all inliers) yet cover a few percent of
    /// it, and say nothing of the tool.
    pub coverage: f64,
    /// Mahalanobis length of the fitted latent under the shape space's
    /// prior (√Σ ℓⱼ²/varⱼ; 0 without a latent): how far the shape lies
    /// outside the family the space was built from.
    pub latent_mahalanobis: f64,
    /// The view's width across its longest direction (√12 times its spread
    /// along the second principal axis: a uniform strip's width), mm. A
    /// tool's view is centimetres wide; a line of points has none, and the
    /// latent folds the shape onto it (measured: a 30 cm line on the mug
    /// space, every point an inlier, coverage 0.6, latent 9.1).
    pub view_width_mm: f64,
    /// false when the cloud is not explained by this category (another
    /// tool, a table, noise) or shows too little of it to say (see `coverage`).
    pub confident: bool,
    /// Another pose, at least 30° away, explains the view almost as well (a
    /// mug whose handle is hidden): the orientation is not determined by this
    /// view; take another.
    pub ambiguous_pose: bool,
    /// Share of the fitted shape's camera-facing surface that the view
    /// contradicts: it lies where the camera saw nothing, or in front of
    /// what the camera saw (None without a camera position, given or
    /// estimated). Something in front of the tool (a pole, the robot's arm)
    /// hides part of it from the camera and the segmented cloud does not say
    /// so: that part reads as seen through. Measured (`eval transfer --views
    /// 8 --seed 11`, camera given, test and train): views with nothing in
    /// front 0.00-0.06 where the fit was right, 0.07-0.10 where it was wrong
    /// (a mug's handle on the wrong side, a hammer end over end); a bar
    /// hiding 30 % of the tool's image width (`--occluder-share 0.3`) mug
    /// 0.14-0.45, drill 0.09-0.57, hammer 0.01-0.55. With the camera
    /// estimated it is less telling (drill 0.00-0.30 on right fits). Not a
    /// gate: most occluded views still fit right (mug 80 of 104), and the
    /// wrong ones are mostly flagged ambiguous already.
    pub contradicted_fraction: Option<f64>,
}

#[derive(Clone, Debug, Serialize)]
pub struct Registration {
    pub latent: Vec<f64>,
    /// Pose of the category's canonical frame in the cloud's frame.
    pub rotation_cloud_from_canonical: UnitQuaternion<f64>,
    pub translation_cloud_from_canonical: Vector3<f64>,
    /// Uniform scale relative to the canonical size.
    pub scale: f64,
    /// Final σ², m² (after a surfel polish, the isotropic σ² with the same
    /// normalising constant: σ⁶ = σ_t⁴σ_n²).
    pub sigma2: f64,
    pub fit: FitQuality,
    /// Canonical keypoints moved through the deformation and the pose (cloud frame).
    pub keypoints: Vec<NamedPoint>,
    pub hypotheses: usize,
    pub iterations: usize,
    pub elapsed_ms: f64,
    pub stage_ms: StageTimes,
    /// The camera position the fit assumed (cloud frame) when none was given:
    /// estimated from the view and a first fit (`RegisterOptions::estimate_viewpoint`);
    /// None when one was given or the view did not settle it.
    pub estimated_viewpoint: Option<[f64; 3]>,
    /// The turns about the tool's upright axis that explain the view about
    /// as well as the reported pose; None when no yaw sweep ran (no up
    /// direction, or `yaw_sweep_steps` below 4) or when the reported pose is
    /// the race's runner-up, not the swept one (`recheck_runner_up`).
    pub yaw_arc: Option<YawArc>,
    /// The lowest z of the cloud's points the fit kept (stray, far and
    /// table points set aside), cloud frame, metres: for a z-up cloud, no
    /// higher than the table the tool stands on (with the registered
    /// shape's, `graspd grasp`'s table when none is given and no leak
    /// showed one).
    pub lowest_kept_z: f64,
    /// The table a leaking segmentation showed (height along up, cloud
    /// frame, metres), when none was given: the fit held the tool on it.
    pub found_table_height: Option<f64>,
}

/// The arc of turns a view leaves open (`RegisterOptions::yaw_sweep_steps`):
/// a mug whose handle is hidden fits about as well at any turn that keeps
/// the handle out of sight, and the registration reports the middle of that
/// arc. The keypoints off the axis are uncertain by as much as the turn
/// moves them ([`YawArc::spread`]); a wide arc says: take another view.
#[derive(Clone, Copy, Debug, Serialize, PartialEq)]
pub struct YawArc {
    /// The tool's canonical axis nearest the up direction when it is within
    /// 10° of it, else the up direction, in the cloud's frame (unit); the arc
    /// turns about it through the canonical frame's origin
    /// (`Registration::translation_cloud_from_canonical`).
    pub axis_cloud: [f64; 3],
    /// Turns up to this far either way of the reported pose score within
    /// `yaw_sweep_margin` of the best; 0 when no other sweep step does.
    /// Resolution: one sweep step (22.5° with the default 16 steps).
    pub half_width_rad: f64,
}

impl YawArc {
    /// How far `point` (cloud frame) moves when the tool turns by the arc's
    /// half width about its axis through `pivot`: the chord 2·r·sin(h/2),
    /// r the point's distance from the axis.
    pub fn spread(&self, pivot: &Vector3<f64>, point: &Vector3<f64>) -> f64 {
        let a = Vector3::from(self.axis_cloud);
        let d = point - pivot;
        let r = (d - a * a.dot(&d)).norm();
        2.0 * r * (self.half_width_rad.min(std::f64::consts::PI) / 2.0).sin()
    }
}

impl Registration {
    /// How far each keypoint moves across the yaw arc ([`YawArc::spread`]),
    /// metres, in `keypoints` order; None without an arc.
    pub fn keypoint_spread_m(&self) -> Option<Vec<f64>> {
        let arc = self.yaw_arc?;
        let pivot = self.translation_cloud_from_canonical;
        Some(self.keypoints.iter().map(|k| arc.spread(&pivot, &Vector3::from(k.position))).collect())
    }
}

/// Where a registration's time went.
#[derive(Clone, Copy, Debug, Default, Serialize)]
pub struct StageTimes {
    pub coarse: f64,
    pub race: f64,
    pub refine: f64,
    pub polish: f64,
    pub quality: f64,
}

/// The model point sets used by a fit, each affine in the latent.
struct Models {
    /// Canonical outward normals of each level's points (normalised frame = canonical axes).
    coarse_normals: Vec<P3>,
    race_normals: Vec<P3>,
    /// The coarse level's candidate points, and the first of them at the
    /// default `coarse_model_points`, kept so that its block order
    /// (`LinearModel::block_order`) is made once, not every registration.
    coarse: LinearModel,
    coarse_default: LinearModel,
    /// Middle resolution, for the race between the surviving hypotheses.
    race: LinearModel,
    /// The refine's level, and the densest, for the last few iterations (the polish).
    fine: LatentLevel,
    polish: LatentLevel,
    surface: LinearModel,
    keypoints: LinearModel,
}

impl Models {
    fn new(space: &ShapeSpace, deformable: bool) -> Self {
        let kp: Vec<P3> = space.keypoints.iter().map(|k| k.position).collect();
        let model = |z: &[P3]| {
            if deformable {
                space.linear_model(z)
            } else {
                LinearModel::new(z.iter().map(|p| space.norm.forward(p)).collect(), Vec::new())
            }
        };
        let surface = model(&space.surface);
        // Model subsets chosen on the canonical (not the mean) so both model kinds use the same points.
        let canonical: Vec<P3> = space.surface.iter().map(|p| space.norm.forward(p)).collect();
        let polish_idx = crate::geometry::farthest_point_order(&canonical, POLISH_MODEL_POINTS);
        // Farthest-point orders nest: each level's points are the first of the next's.
        let fine_idx = &polish_idx[..FINE_MODEL_POINTS.min(polish_idx.len())];
        let race_idx = &polish_idx[..200.min(polish_idx.len())];
        let coarse_idx = &polish_idx[..120.min(polish_idx.len())];
        let normals = |idx: &[usize]| idx.iter().map(|&i| space.surface_normals[i]).collect();
        let level = |idx: &[usize]| {
            let model = surface.select(idx);
            let normals: Vec<P3> = normals(idx);
            LatentLevel { step: LatentStep::new(&model, &normals), model, normals }
        };
        let models = Self {
            fine: level(fine_idx),
            polish: level(&polish_idx),
            coarse_normals: normals(coarse_idx),
            race_normals: normals(race_idx),
            coarse: surface.select(coarse_idx),
            coarse_default: surface
                .select(&coarse_idx[..RegisterOptions::default().coarse_model_points.min(coarse_idx.len())]),
            race: surface.select(race_idx),
            surface,
            keypoints: model(&kp),
        };
        // The blocked E-steps' orders, made here (a few ms for the polish's
        // level) rather than in the first registration.
        for level in [&models.coarse_default, &models.race, &models.fine.model, &models.polish.model] {
            level.block_order();
        }
        models
    }
}

/// A model level the latent is fitted on: its points, their canonical
/// normals and its latent normal equations.
struct LatentLevel {
    model: LinearModel,
    normals: Vec<P3>,
    step: LatentStep,
}

/// Per-coordinate variance of the training shapes' model points about the
/// mean shape's (`model.base`, the latent at zero; normalised units²).
fn shape_spread2(model: &LinearModel, latents: &[Vec<f64>]) -> f64 {
    if model.basis.is_empty() || latents.is_empty() {
        return 0.0;
    }
    let mut sum = 0.0;
    for l in latents {
        let y = model.evaluate(l);
        sum += y.iter().zip(&model.base).map(|(a, b)| super::estep::dist2(a, b)).sum::<f64>();
    }
    sum / (3.0 * (latents.len() * model.len()) as f64)
}

/// Model points of the refine stage and of the polish (farthest-point
/// samples of the canonical surface). The polish's density is most of the
/// accuracy on a partial view (measured, eval transfer 32 views, test
/// median mug / drill / hammer: 400 model and observed points 3.84 / 3.01 /
/// 2.99 mm; 800 and 800: 2.96 / 2.78 / 2.64; 400 then 10 iterations at 800:
/// 2.91 / 2.58 / 2.59), and iterations at its size cost twice those at the
/// refine's, so the refine converges on the sparser level first.
const FINE_MODEL_POINTS: usize = 400;
const POLISH_MODEL_POINTS: usize = 800;

/// A shape space prepared for fast online registration.
pub struct Registrar {
    pub space: ShapeSpace,
    deformable: Models,
    /// The undeformed canonical: the `canonical` baseline (latent not fitted).
    rigid: Models,
    /// Principal axes (columns, descending variance) and centroid of the canonical surface, normalised.
    axes: Matrix3<f64>,
    centroid: Vector3<f64>,
    /// Whether the lying hypotheses are tried when the options leave it open.
    lying_by_default: bool,
    /// The scale prior's std when the options leave it open.
    scale_prior_std: f64,
    /// Per-coordinate variance of the training shapes about the mean shape
    /// on the refine's model points (normalised units², see [`shape_spread2`]).
    shape_spread2: f64,
}

/// The scale prior of a category without a tighter one: ±15 % (a tool may
/// be larger or smaller than any the shape space was built from).
pub const LOOSE_SCALE_PRIOR_STD: f64 = 0.15;

/// The scale prior's std for a shape space's category, when the options
/// leave it open. The hammers' is tight (2 %): the family's sizes lie
/// within its latent (every training and test hammer is at scale 1), and
/// with the loose prior a partial view traded the latent's length and
/// thickness modes for a scale of 0.87-0.95 on some training hammers; the
/// keypoints moved little, but the grasp's offsets from the handle shrank
/// with the scale and loosened the pinch. `sim nail --grasp-from register
/// --episodes 10` at std 0.15 / 0.03 / 0.02 / 0.01: canonical and training
/// hammers, seeds 0-9, 83 / 93 / 99 / 106 of 110; seeds 100-109, 78 / 86 /
/// 91 / 89 of 100; test hammers 20 / 20 / 25 / 29 of 30. Not 0.01: a hammer
/// 30 % larger or smaller than the family must still register (`graspd eval
/// transfer --category hammer --scale-jitter 0.3`, test keypoint error
/// median / p90: 2.65 / 5.6 mm loose, 2.91 / 7.9 at 0.02, 3.19 / 10.7 at
/// 0.01). The price at 0.02, unjittered: test 2.63 / 4.85 → 2.86 / 5.2 mm,
/// training p90 6.8 → 12.7 mm (the handle's end, whose length the latent now
/// carries). Mugs keep the loose prior: the large test mugs are larger than
/// any training mug (with 0.02, test mugs 21 → 19 of 30 placed).
pub fn default_scale_prior_std(category: &str) -> f64 {
    match category.parse::<crate::tools::Category>() {
        Ok(crate::tools::Category::Hammer) => 0.02,
        _ => LOOSE_SCALE_PRIOR_STD,
    }
}

/// Adjacent principal variances closer than this ratio do not tell their axes
/// apart on a partial view, so the principal-axis hypotheses cannot settle how
/// the tool lies. Canonicals (larger / smaller of each adjacent pair): mug
/// 0.84, 0.80; drill 0.35, 0.20; hammer 0.06, 0.12.
const AXES_APART_RATIO: f64 = 0.6;

impl Registrar {
    pub fn new(space: ShapeSpace) -> Self {
        let deformable = Models::new(&space, true);
        let rigid = Models::new(&space, false);
        let (axes, var, centroid) = principal_frame(&deformable.surface.base);
        let lying_by_default = var[1] > AXES_APART_RATIO * var[0] || var[2] > AXES_APART_RATIO * var[1];
        let scale_prior_std = default_scale_prior_std(&space.category);
        let shape_spread2 = shape_spread2(&deformable.fine.model, &space.train_latents);
        Self { deformable, rigid, axes, centroid, lying_by_default, scale_prior_std, shape_spread2, space }
    }

    pub fn register(&self, cloud: &[Point3<f64>], opts: &RegisterOptions) -> Result<Registration, RegisterError> {
        // A second camera alone is the camera.
        let opts = &match (opts.viewpoint, opts.second_viewpoint) {
            (None, Some(only)) => RegisterOptions { viewpoint: Some(only), second_viewpoint: None, ..*opts },
            _ => *opts,
        };
        let t0 = Instant::now();
        let opts =
            &RegisterOptions { scale_prior_std: Some(opts.scale_prior_std.unwrap_or(self.scale_prior_std)), ..*opts };
        check(cloud)?;
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(opts.seed);
        let working = working_points(cloud, &mut rng);
        let bulk = check_extent(&working)?;
        let near = drop_far_points(&working, &bulk);
        let (tool, found_table) = drop_table_points(&near, up_direction(opts), opts.support_height);
        // A leak shows the table the tool stands on: it holds the tool as a
        // given one would (`eval transfer --unknown-table --views 6 --seed 7
        // --mask-leak-px 2 / 4`, test keypoint median: drill 1.83 / 1.80 →
        // 1.71 / 1.54 mm, hammer 1.87 / 1.77 → 1.50 / 1.59, mug 2.34 / 2.13
        // → 2.20 / 2.24).
        let opts = &RegisterOptions { support_height: opts.support_height.or(found_table), ..*opts };
        let all = drop_stray_points(&tool, &mut rng);
        let fine_x = view_subset(&all, opts.fine_points, opts.even_sampling, &mut rng);
        let race_x = subsample(&fine_x, opts.race_points, &mut rng);
        let coarse_pts = ViewPoints::new(&subsample(&race_x, opts.coarse_points, &mut rng));
        let models = if opts.fit_latent { &self.deformable } else { &self.rigid };
        let coarse_n = opts.coarse_model_points.min(models.coarse.len());
        let coarse_model = if coarse_n == models.coarse_default.len() {
            std::borrow::Cow::Borrowed(&models.coarse_default)
        } else {
            std::borrow::Cow::Owned(models.coarse.select(&(0..coarse_n).collect::<Vec<_>>()))
        };
        let coarse_normals = &models.coarse_normals[..coarse_n];
        let viewpoint = opts.viewpoint.map(Vector3::from);
        let second = opts.second_viewpoint.map(Vector3::from);
        let up = up_direction(opts);

        let ranking = RegisterOptions { tol: opts.ranking_tol, ..*opts };
        let ms = |t: Instant| t.elapsed().as_secs_f64() * 1e3;
        let mut stage = StageTimes::default();
        let t_stage = Instant::now();
        // Coarse: every hypothesis, mean shape, similarity only.
        let standing = match up {
            Some(up) if self.lying_by_default && opts.lying_hypotheses.is_none() => {
                let (side_facing, one_way) = side_facing(&fine_x, &up);
                if trace_enabled() {
                    eprintln!(
                        "  side-facing normals {side_facing:.3} (upright from {UPRIGHT_SIDE_FACING}), one way {one_way:.3} (at most {UPRIGHT_ONE_WAY})"
                    );
                }
                side_facing >= UPRIGHT_SIDE_FACING && one_way <= UPRIGHT_ONE_WAY
            }
            _ => false,
        };
        let starts = Starts {
            principal_axes: !standing,
            lying: opts.lying_hypotheses.unwrap_or(self.lying_by_default && !standing),
        };
        let hyps = self.hypotheses(&fine_x, up, opts.yaws, starts);
        let coarse_fit = |pose: Pose, sigma2: Option<f64>, iters: usize| {
            let view = View { normals: coarse_normals, viewpoint, occlusion: None, second, second_occlusion: None };
            em(
                &coarse_model,
                view,
                &coarse_pts,
                pose,
                vec![0.0; 0],
                None,
                None,
                sigma2,
                &ranking,
                iters,
                &self.space.norm,
            )
        };
        // Starts that have met after a few iterations are one fit from there on
        // (a drill's 10 starts end in ~4 poses); each stands for its merged starts
        // in the ranking, so the race keeps the same survivors.
        let merging = (1..opts.coarse_iters).contains(&opts.coarse_merge_after);
        let merge_after = if merging { opts.coarse_merge_after } else { opts.coarse_iters };
        let mut first: Vec<Fit> = hyps.iter().map(|&pose| coarse_fit(pose, None, merge_after)).collect();
        first.sort_by(|a, b| a.nll.total_cmp(&b.nll));
        let mut merged: Vec<(Fit, usize)> = Vec::new();
        for fit in first {
            match merged
                .iter_mut()
                .find(|(m, _)| merging && rotation_between(&m.pose.r, &fit.pose.r) < COARSE_MERGE_ANGLE)
            {
                Some((_, starts)) => *starts += 1,
                None => merged.push((fit, 1)),
            }
        }
        let mut scored: Vec<(f64, Pose, f64)> = merged
            .into_iter()
            .flat_map(|(fit, starts)| {
                let converged = fit.iterations < merge_after;
                let fit = if converged || !merging {
                    fit
                } else {
                    coarse_fit(fit.pose, Some(fit.sigma2), opts.coarse_iters - merge_after)
                };
                std::iter::repeat_n((fit.nll, fit.pose, fit.sigma2), starts)
            })
            .collect();
        scored.sort_by(|a, b| a.0.total_cmp(&b.0));
        let given_viewpoint = viewpoint.is_some();
        let viewpoint = match (viewpoint, scored.first()) {
            (None, Some((_, pose, _))) if opts.estimate_viewpoint => {
                estimate_viewpoint(&models.race, &models.race_normals, pose, &race_x, up)
            }
            _ => viewpoint,
        };
        // Fine: the best few, with the latent.
        let q = if opts.fit_latent { self.space.modes() } else { 0 };
        stage.coarse = ms(t_stage);
        let t_stage = Instant::now();
        let prior = opts.fit_latent.then_some(self.space.variances.as_slice());
        let free_space_points = viewpoint.map(|_| subsample(&all, 4000, &mut rng));
        let free_space = viewpoint
            .zip(free_space_points.as_ref())
            .and_then(|(vp, pts)| FreeSpace::new(pts, vp, FREE_SPACE_MARGIN_M));
        // The second camera's range image, from the same points.
        let second_free_space =
            second.zip(free_space_points.as_ref()).and_then(|(vp, pts)| FreeSpace::new(pts, vp, FREE_SPACE_MARGIN_M));
        let mut best: Option<(f64, Fit)> = None;
        let mut raced: Vec<(f64, Fit)> = Vec::new();
        let mut iterations = 0;
        // The survivors race a few iterations at full resolution (the coarse
        // level cannot see a mug's handle well enough to settle its yaw); the
        // winner then runs to convergence.
        // The best `keep` coarse fits, less those in the basin of a better one:
        // racing a fit twice only costs time.
        // The next ones in other basins are the reserve, raced only if the
        // race's best contradicts the view.
        let (mut survivors, mut reserve): (Vec<&(f64, Pose, f64)>, Vec<_>) = (Vec::new(), Vec::new());
        for (i, fit) in scored.iter().enumerate() {
            if i >= opts.keep.max(1) && reserve.len() >= opts.keep_contradicted {
                break;
            }
            if !survivors.iter().chain(&reserve).any(|s| same_basin(&s.1, &fit.1)) {
                if i < opts.keep.max(1) {
                    survivors.push(fit)
                } else {
                    reserve.push(fit)
                }
            }
        }
        let race_pts = ViewPoints::new(&race_x);
        let mut scorer = race_pts.estep();
        scorer.use_model_order(models.polish.model.block_order(), models.polish.model.len());
        // Scores rank raced poses: one alone, with no end-over-end check to
        // compare it with, needs none (a drill's or hammer's usual race).
        let flip_check = starts.lying && opts.flip_check;
        let scoring = survivors.len() > 1 || flip_check;
        // One raced pose: EM on the mean shape from `pose`, then its score
        // (0 when not `scoring`).
        let race = |scorer: &mut EStep, pose: Pose, sigma2: f64| -> (Fit, f64, f64, f64) {
            // Start at the coarse fit's σ² (loosened for the finer model): re-annealing
            // from the data's spread would redo the coarse stage at full resolution.
            // Poses race on the mean shape: a free latent lets a wrong pose deform
            // into a fit as good as the right one's (measured: most gross failures).
            let fit = em(
                &models.race,
                View { normals: &models.race_normals, viewpoint, occlusion: None, second, second_occlusion: None },
                &race_pts,
                pose,
                vec![0.0; q],
                None,
                None,
                Some(2.0 * sigma2),
                &ranking,
                opts.race_iters,
                &self.space.norm,
            );
            // Likelihood per observed point, penalised by the share of the model
            // the view contradicts; both on the densest model, as the yaw sweep
            // below scores (measured, eval transfer --views 12, seeds 7, 11, 23,
            // against the race model's own likelihood: hammer train keypoint
            // p90 10.7 → 8.4 mm, mug unambiguous test / train p90 5.9 / 6.9 →
            // 4.7 / 5.8, drill unchanged).
            if !scoring {
                return (fit, f64::NAN, f64::NAN, 0.0);
            }
            let (nll_pt, violation, score) =
                pose_score(scorer, &models.polish, &fit, viewpoint, free_space.as_ref(), up, opts);
            (fit, nll_pt, violation, score)
        };
        let mut best_violation = f64::NAN;
        let n_survivors = survivors.len();
        let mut queue = survivors.into_iter();
        let mut reserve = reserve.into_iter();
        loop {
            let next = queue
                .next()
                .or_else(|| (scoring && best_violation > RACE_CONTRADICTED).then(|| reserve.next()).flatten());
            let Some((_, pose, sigma2)) = next else { break };
            let racing_reserve = raced.len() >= n_survivors;
            let (fit, nll_pt, violation, score) = race(&mut scorer, *pose, *sigma2);
            iterations += fit.iterations;
            if trace_enabled() {
                let q = UnitQuaternion::from_matrix(&fit.pose.r);
                let (roll, pitch, yaw) = q.euler_angles();
                let (roll, pitch, yaw) = (roll.to_degrees(), pitch.to_degrees(), yaw.to_degrees());
                if scoring {
                    eprintln!(
                        "   race: rpy {roll:.0} {pitch:.0} {yaw:.0}°, nll/pt {nll_pt:.3}, free-space violation {violation:.3}, score {score:.3}"
                    );
                } else {
                    eprintln!("   race: rpy {roll:.0} {pitch:.0} {yaw:.0}°, alone (not scored)");
                }
            }
            raced.push((score, fit.clone()));
            // A reserve hypothesis, ranked below the four by the coarse
            // stage, takes the lead only by the ambiguity margin; within it
            // the race is ambiguous anyway (the runner-up below). Measured
            // (the six views of `a_mug_whose_true_pose_ranked_fifth_...`: the
            // reserve's winners led by 0.006-0.65 nats; `sim place
            // --instances all --grasp-from register`: one training mug's
            // view lost by a reserve 0.012 ahead).
            let bar = if racing_reserve { AMBIGUITY_MARGIN } else { 0.0 };
            if best.as_ref().is_none_or(|b| score < b.0 - bar) {
                best = Some((score, fit));
                best_violation = violation;
            }
        }
        let (mut lead_score, mut lead) = best.expect("at least one hypothesis");
        // The best raced fit in another basin than the lead's (at least 30°
        // away); within the margin of the lead's score, the pose is ambiguous.
        let mut runner_up = raced
            .into_iter()
            .filter(|(_, f)| rotation_between(&lead.pose.r, &f.pose.r) > 30f64.to_radians())
            .min_by(|a, b| a.0.total_cmp(&b.0));
        // The rotations of the poses that explain the view within the margin
        // of the lead's and lie at least 30° from it: while any stands, the
        // pose is ambiguous.
        let mut rivals: Vec<Matrix3<f64>> = Vec::new();
        if let Some((_, f)) = runner_up.as_ref().filter(|(sc, _)| sc - lead_score < AMBIGUITY_MARGIN) {
            rivals.push(f.pose.r);
        }
        // A tool that may lie on its side may lie either end first: race the
        // lead turned end over end too (see `RegisterOptions::flip_check`).
        if flip_check {
            let end_over_end = Matrix3::from_diagonal(&Vector3::new(1.0, -1.0, -1.0));
            let p = lead.pose;
            let r = p.r * end_over_end;
            // Turned about the mean shape's centroid, which stays where it was.
            let flipped = Pose { r, s: p.s, t: p.t + p.s * (p.r * self.centroid - r * self.centroid) };
            let (fit, _, _, score) = race(&mut scorer, flipped, lead.sigma2);
            iterations += fit.iterations;
            if trace_enabled() {
                eprintln!("   end over end: score {score:.3}, {:+.3} from the lead", score - lead_score);
            }
            if score - lead_score < AMBIGUITY_MARGIN {
                rivals.push(r);
            }
        }
        // On a table, the turn about the up axis is what a view most often leaves
        // open (a mug with its handle hidden): sweep it, and take the middle of the
        // turns the view allows rather than whichever edge EM happened to reach.
        // Scored on the densest model: the race's 200 points are 16 mm
        // apart on a mug, σ here is 4-5 mm, and the mixture's likelihood
        // then changes by 0.1-0.3 nats a point from one 15° turn to the
        // next with the points' spacing alone, more than a half-hidden
        // handle's whole evidence. Measured with the turn about the tool's
        // own axis (`sweep_axis`), eval transfer mug --views 12, seeds 7,
        // 11, 23, mean of the three: test / train keypoint p90 27.1 / 46.2
        // → 15.8 / 26.1 mm, train unambiguous p90 17.1 → 6.9, rotation
        // p90 39 / 71° → 28 / 40°; about 1 ms more a fit (bench_register).
        // (fit, the arc's half width when the sweep ran, EM iterations, the challenger)
        type Swept = (Fit, Option<f64>, usize, Option<Pose>);
        let canonical_origin = Vector3::from(self.space.norm.forward(&[0.0; 3]));
        let sweep = |lead: Fit, viewpoint: Option<Vector3<f64>>, free_space: Option<&FreeSpace>| -> Swept {
            let (Some(up), true) = (up, opts.yaw_sweep_steps >= 4) else { return (lead, None, 0, None) };
            let sweep = YawSweep {
                model: &models.polish.model,
                normals: &models.polish.normals,
                screen: Some((&models.race, &models.race_normals)),
                x: &race_pts,
                viewpoint,
                second,
                free_space,
                origin: canonical_origin,
            };
            let SweptTurns { centre, half_width, challenger } = sweep.run(&lead, up, opts);
            let Some(start) = centre else { return (lead, Some(half_width), 0, challenger) };
            let fit = em(
                &models.race,
                View { normals: &models.race_normals, viewpoint, occlusion: None, second, second_occlusion: None },
                &race_pts,
                start,
                lead.latent.clone(),
                None,
                None,
                Some(lead.sigma2),
                &ranking,
                opts.race_iters,
                &self.space.norm,
            );
            let n = fit.iterations;
            (fit, Some(half_width), n, challenger)
        };
        let (swept, mut arc_half_width, n, challenger) = sweep(lead, viewpoint, free_space.as_ref());
        iterations += n;
        lead = swept;
        // The sweep's challenger races as the survivors did; taking the
        // lead, it is swept in turn and the old lead is its runner-up.
        if let (Some(pose), true) = (challenger, scoring) {
            let (fit, nll_pt, violation, score) = race(&mut scorer, pose, lead.sigma2);
            iterations += fit.iterations;
            if trace_enabled() {
                eprintln!(
                    "   challenger raced: nll/pt {nll_pt:.3}, violation {violation:.3}, score {score:.3} against the lead's {lead_score:.3}"
                );
            }
            if score < lead_score {
                rivals.clear();
                if lead_score - score < AMBIGUITY_MARGIN
                    && rotation_between(&lead.pose.r, &fit.pose.r) > 30f64.to_radians()
                {
                    rivals.push(lead.pose.r);
                }
                runner_up = Some((lead_score, lead));
                lead_score = score;
                let (swept, half_width, n, _) = sweep(fit, viewpoint, free_space.as_ref());
                iterations += n;
                lead = swept;
                arc_half_width = half_width;
            }
        }
        // The race's winner is a better pose than the coarse stage's best: an
        // estimated viewpoint is estimated again from it for the final fits
        // (measured, eval transfer --unknown-viewpoint test / train median: mug
        // 3.41 / 3.14 → 3.30 / 2.90 mm, drill 3.10 / 2.13 → 2.90 / 2.07, before
        // the whole-surface check).
        let reestimated = (!given_viewpoint && opts.estimate_viewpoint)
            .then(|| estimate_viewpoint(&models.race, &models.race_normals, &lead.pose, &race_x, up))
            .flatten();
        let raced_blind = viewpoint.is_none();
        let (viewpoint, free_space) = match reestimated {
            Some(vp) => (Some(vp), FreeSpace::new(&subsample(&all, 4000, &mut rng), vp, FREE_SPACE_MARGIN_M)),
            None => (viewpoint, free_space),
        };
        // A race run without a camera (the first estimate refused) cannot see
        // which turns hide the handle: its sweep is flat and its middle
        // arbitrary. When the second estimate settles, sweep again with it.
        // Measured, eval transfer mug --views 8 --unknown-viewpoint, seeds 11 /
        // 7 / 23: test keypoint p90 70.7 / 14.1 / 58.5 → 67.9 / 14.1 / 30.8
        // mm, train 57.6 / 37.6 / 23.5 → 52.6 / 21.8 / 23.5; medians equal or
        // better; drill, hammer, the mug on its side and the YCB mug unchanged.
        if raced_blind && viewpoint.is_some() {
            let (swept, half_width, n, _) = sweep(lead, viewpoint, free_space.as_ref());
            iterations += n;
            lead = swept;
            arc_half_width = half_width;
        }
        let open = |half_width: Option<f64>| half_width.is_some_and(|h| 2.0 * h > 30f64.to_radians());
        let mut sweep_open = open(arc_half_width);
        let ambiguous_pose = !rivals.is_empty() || sweep_open;
        stage.race = ms(t_stage);
        // The latent fits, from `start` on a level and a subset of the view.
        let latent_opts = match opts.ambiguous_latent_prior_weight {
            Some(w) if ambiguous_pose => RegisterOptions { latent_prior_weight: w, ..*opts },
            _ => *opts,
        };
        // The polish's subset, drawn before the latent fits (which draw nothing).
        let polish_pts = (opts.polish_points > 0 && opts.polish_iters > 0)
            .then(|| ViewPoints::new(&view_subset(&all, opts.polish_points, opts.even_sampling, &mut rng)));
        let fine_pts = ViewPoints::new(&fine_x);
        // The latent fits from a raced pose: refine, then polish. (fit, EM
        // iterations, refine ms, polish ms)
        // The view of the latent fits: every camera's range image.
        let fine_view = View {
            normals: &[],
            viewpoint,
            occlusion: free_space.as_ref(),
            second,
            second_occlusion: second_free_space.as_ref(),
        };
        let complete = |start: &Fit| -> (Fit, usize, f64, f64) {
            let t_stage = Instant::now();
            // The support holds the latent fits only: in the coarse stage and the
            // race it pinned the mean shape and picked worse poses (eval transfer
            // --views 12 --seed 7, test keypoint median / p90: mug 1.79 / 10.3 →
            // 1.95 / 27.6 mm, drill 2.11 / 4.9 → 2.19 / 4.9). And only for a tool
            // resting as its category was modelled (see `REST_POSE_COS`).
            let support = Support::new(up, opts).filter(|sp| rests_as_modelled(&start.pose.r, &sp.up));
            let fit_latent = |level: &LatentLevel, x: &ViewPoints, start: &Fit, sigma2: f64, iters: usize| {
                em(
                    &level.model,
                    View { normals: &level.normals, ..fine_view },
                    x,
                    start.pose,
                    start.latent.clone(),
                    prior.map(|var| (var, &level.step)),
                    support,
                    Some(sigma2),
                    &latent_opts,
                    iters,
                    &self.space.norm,
                )
            };
            // The refine re-anneals from the shape space's spread (see `refine_shape_sigma2`).
            let spread2 = if opts.fit_latent { self.shape_spread2 * start.pose.s * start.pose.s } else { 0.0 };
            let refine_sigma2 = start.sigma2 + opts.refine_shape_sigma2.max(0.0) * spread2;
            let fit = fit_latent(&models.fine, &fine_pts, start, refine_sigma2, opts.fine_iters);
            let mut n = fit.iterations;
            let refine_ms = ms(t_stage);
            let t_stage = Instant::now();
            // Polish: the refine's fit continued on the densest model and more of the view.
            let fit = match &polish_pts {
                Some(polish_pts) => {
                    let polished = if opts.fit_latent && opts.surfels {
                        let level = &models.polish;
                        surfels::em_surfels(
                            level,
                            View { normals: &level.normals, ..fine_view },
                            polish_pts,
                            &fit,
                            prior,
                            support,
                            fit.sigma2,
                            &latent_opts,
                            opts.polish_iters,
                            &self.space.norm,
                        )
                    } else {
                        fit_latent(&models.polish, polish_pts, &fit, fit.sigma2, opts.polish_iters)
                    };
                    n += polished.iterations;
                    polished
                }
                None => fit,
            };
            (fit, n, refine_ms, ms(t_stage))
        };
        let (mut fit, n, refine_ms, polish_ms) = complete(&lead);
        iterations += n;
        (stage.refine, stage.polish) = (refine_ms, polish_ms);
        // The race ranks poses on the mean shape; a tool far from it (a
        // hammer whose head is longer) can lose its true pose there to a
        // turned one. The runner-up within `recheck_runner_up` of the lead
        // gets the latent fits too, and the two finished fits are compared.
        // Only off the category's rest pose: at rest, the yaw sweep has
        // settled the turn the view leaves open, and a runner-up fitted
        // without it took an edge of that arc instead of its middle.
        let at_rest = up.is_some_and(|up| rests_as_modelled(&lead.pose.r, &up));
        if let Some((runner_score, runner)) =
            runner_up.filter(|(sc, _)| !at_rest && opts.recheck_runner_up.is_some_and(|m| sc - lead_score < m))
        {
            let t_stage = Instant::now();
            let (other, n, _, _) = complete(&runner);
            iterations += n;
            // Scored as the race scores.
            let mut final_score =
                |f: &Fit| pose_score(&mut scorer, &models.polish, f, viewpoint, free_space.as_ref(), up, opts).2;
            let (mine, theirs) = (final_score(&fit), final_score(&other));
            if trace_enabled() {
                eprintln!(
                    "   runner-up (race {:+.3} from the lead) fitted: score {theirs:.3} against the lead's {mine:.3}",
                    runner_score - lead_score
                );
            }
            if (theirs - mine).abs() < AMBIGUITY_MARGIN {
                rivals.push(other.pose.r);
            }
            if theirs < mine - AMBIGUITY_MARGIN {
                fit = other;
                arc_half_width = None;
            }
            stage.polish += ms(t_stage);
        }
        // An open arc that a part peeking past the body settles (see
        // `unexplained`): turn the fit to the turns that explain the view's
        // every point. Open arcs only; where the sweep settled the turn, its
        // dense scores placed the handle already.
        if let (true, Some(h), Some(up)) = (opts.narrow_by_unexplained, arc_half_width.filter(|h| *h > 0.0), up) {
            let t_stage = Instant::now();
            let shape: Vec<P3> = models.polish.model.evaluate(&fit.latent).iter().map(|y| fit.pose.apply(y)).collect();
            let line = TurningLine::of(&fit.pose, canonical_origin, up);
            let bin = std::f64::consts::TAU / unexplained::BINS as f64;
            // The arc and one sweep step past each end, within half a turn.
            let step = std::f64::consts::TAU / opts.yaw_sweep_steps.max(1) as f64;
            let reach = (((h + step) / bin).ceil() as i64).min(unexplained::BINS as i64 / 2);
            let counts = AzimuthMasks::new(&shape, line.pivot, line.axis).unexplained(&all, -reach..=reach);
            if trace_enabled() {
                eprintln!(
                    "   unexplained view points by turn of {:.2}° (-{reach}..{reach}), {} points, {:.0} µs: {counts:?}",
                    bin.to_degrees(),
                    all.len(),
                    t_stage.elapsed().as_secs_f64() * 1e6
                );
            }
            if let Some(n) = unexplained::narrowed(&counts, reach as usize, all.len()) {
                let (a, b) = (n.first as i64 - reach, n.last as i64 - reach);
                let turn = (a + b) as f64 / 2.0 * bin;
                fit.pose = line.turned(&fit.pose, turn);
                arc_half_width = Some((b - a) as f64 * bin / 2.0);
                // Settled where the counts name one run and the finished
                // shape explains nearly every point there: a shape far from
                // the tool (`mug_train_04`, tall and tapered), missing 4 % of
                // the view at every turn, was narrowed 168° off. Beyond the
                // turns counted the sweep's scores were worse by its margin.
                let settles = n.alone && n.least * 100 <= all.len();
                if opts.narrowing_settles_ambiguity && settles {
                    sweep_open = open(arc_half_width);
                    // A rival that is the fit turned about the line to a
                    // turn the counts refute explains the view less well.
                    rivals.retain(|r| {
                        let Some(theta) = turn_about(&(r * fit.pose.r.transpose()), &line.axis) else { return true };
                        let i = ((turn + theta) / bin).round() as i64 + reach;
                        let refuted = usize::try_from(i).ok().and_then(|i| counts.get(i)).is_some_and(|&c| c > n.bar);
                        !refuted && rotation_between(r, &fit.pose.r) > 30f64.to_radians()
                    });
                }
                if trace_enabled() {
                    eprintln!("   narrowed to turns {a}..{b}: turned {:.1}°", turn.to_degrees());
                }
            }
            stage.polish += ms(t_stage);
        }
        // What the view says against the fit: its camera-facing surface where
        // the camera saw nothing, or saw past it.
        let contradicted = free_space.as_ref().map(|fs| {
            let level = &models.polish;
            let y: Vec<P3> = level.model.evaluate(&fit.latent).iter().map(|y| fit.pose.apply(y)).collect();
            fs.violation_fraction(&y, level.normals.iter().map(|n| fit.pose.r * Vector3::from(*n)))
        });
        if trace_enabled() {
            eprintln!("   polished: free-space violation {:.4}", contradicted.unwrap_or(f64::NAN));
        }
        let t_stage = Instant::now();
        // Inliers are counted on a uniform sample of the view: the fit's
        // subsample spreads its points evenly over space, and so takes sparse
        // points (outliers the stray test kept) out of proportion to the dense
        // surface. Measured (`confidence_scan`, the test tools' own category,
        // 8 views each, 2 mm depth noise and 10 % outliers): reported inlier
        // fraction 0.58-0.69 against 0.70-0.87 of the whole cloud within the
        // same radius, and 10 of 72 views confident. Drawn last, so that the
        // fit's own draws are as before.
        let quality_x = subsample(&all, QUALITY_POINTS, &mut rng);
        let set_aside =
            SetAside { stray: working.len() - all.len() - (near.len() - tool.len()), table: near.len() - tool.len() };
        let mut quality = self.quality(models, &fit, &quality_x, &all, set_aside, working.len());
        if working.len() < cloud.len() {
            // Counted on a working subsample, they stand for the same share of the cloud.
            let share = |n: usize| (n as f64 * cloud.len() as f64 / working.len() as f64).round() as usize;
            (quality.stray_points, quality.table_points) =
                (share(set_aside.stray + set_aside.table), share(set_aside.table));
        }
        quality.ambiguous_pose = !rivals.is_empty() || sweep_open;
        quality.contradicted_fraction = contradicted;
        stage.quality = ms(t_stage);
        let keypoints = models
            .keypoints
            .evaluate(&fit.latent)
            .iter()
            .zip(&self.space.keypoints)
            .map(|(y, k)| NamedPoint { name: k.name.clone(), position: fit.pose.apply(y) })
            .collect();
        // Canonical frame (metres) → cloud: x = s·R·(z − c)/σn + t.
        let norm = self.space.norm;
        let rel = fit.pose.s / norm.scale;
        let c = Vector3::from(norm.centre);
        Ok(Registration {
            latent: fit.latent.clone(),
            rotation_cloud_from_canonical: UnitQuaternion::from_matrix(&fit.pose.r),
            translation_cloud_from_canonical: fit.pose.t - rel * (fit.pose.r * c),
            scale: rel,
            sigma2: fit.sigma2,
            fit: quality,
            keypoints,
            hypotheses: hyps.len(),
            iterations,
            elapsed_ms: t0.elapsed().as_secs_f64() * 1e3,
            stage_ms: stage,
            estimated_viewpoint: viewpoint.filter(|_| !given_viewpoint).map(|v| [v.x, v.y, v.z]),
            yaw_arc: match (arc_half_width, up) {
                (Some(half_width_rad), Some(up)) => {
                    let a = sweep_axis(&fit.pose.r, up);
                    Some(YawArc { axis_cloud: [a.x, a.y, a.z], half_width_rad })
                }
                _ => None,
            },
            lowest_kept_z: all.iter().map(|p| p[2]).fold(f64::INFINITY, f64::min),
            found_table_height: found_table,
        })
    }

    /// The completed shape in the cloud's frame (dense canonical samples, deformed and posed).
    pub fn completed_shape(&self, reg: &Registration) -> Vec<Point3<f64>> {
        let pose = self.pose_of(reg);
        self.models_of(reg).surface.evaluate(&reg.latent).iter().map(|y| Point3::from(pose.apply(y))).collect()
    }

    /// Any canonical points (canonical frame, metres), on the surface or off
    /// it (a demonstration's hand keypoints), moved onto the registered tool.
    pub fn transfer(&self, reg: &Registration, canonical_points: &[P3]) -> Vec<P3> {
        if reg.latent.is_empty() {
            return self.posed(reg, canonical_points);
        }
        self.transfer_anchored(reg, &self.space.anchored_model(canonical_points))
    }

    /// As [`Self::transfer`], for points whose [`AnchoredModel`] was made
    /// beforehand (once, for points carried onto every registered tool).
    pub fn transfer_anchored(&self, reg: &Registration, model: &AnchoredModel) -> Vec<P3> {
        if reg.latent.is_empty() {
            return self.posed(reg, model.canonical());
        }
        self.posed(reg, &model.evaluate(&reg.latent))
    }

    /// Canonical-frame points (metres) in the cloud's frame by the registered pose.
    fn posed(&self, reg: &Registration, canonical: &[P3]) -> Vec<P3> {
        let pose = self.pose_of(reg);
        canonical.iter().map(|z| pose.apply(&self.space.norm.forward(z))).collect()
    }

    /// A registration without latent (the `canonical` baseline) uses the undeformed models.
    fn models_of(&self, reg: &Registration) -> &Models {
        if reg.latent.is_empty() {
            &self.rigid
        } else {
            &self.deformable
        }
    }

    fn pose_of(&self, reg: &Registration) -> Pose {
        let norm = self.space.norm;
        let r = *reg.rotation_cloud_from_canonical.to_rotation_matrix().matrix();
        let c = Vector3::from(norm.centre);
        Pose { r, t: reg.translation_cloud_from_canonical + reg.scale * (r * c), s: reg.scale * norm.scale }
    }

    /// `set_aside` of the cloud's `cloud_points` were set aside before the fit.
    /// `x`: a uniform sample of `view`, every point kept after stray removal.
    fn quality(
        &self,
        models: &Models,
        fit: &Fit,
        x: &[P3],
        view: &[P3],
        set_aside: SetAside,
        cloud_points: usize,
    ) -> FitQuality {
        // The table's points are not the tool's: not counted against the fit.
        let tool_points = (cloud_points - set_aside.table).max(1);
        let stray_share = set_aside.stray as f64 / tool_points as f64;
        let stray_fraction = (set_aside.stray + set_aside.table) as f64 / cloud_points as f64;
        let shape: Vec<P3> = models.surface.evaluate(&fit.latent).iter().map(|y| fit.pose.apply(y)).collect();
        // Sample spacing of the completed surface inflates nearest-point distances; allow for it.
        let size = fit.pose.s;
        let inlier_m = (0.004f64).max(0.03 * size);
        // Only distances within the inlier radius count: a grid of that
        // radius answers them exactly, without the k-d tree's build over the
        // whole surface (measured, `bench_register`: the quality stage 0.24 → 0.18-0.21 ms).
        let mut grid = RadiusGrid::default();
        grid.build(&shape, inlier_m);
        let (mut n_in, mut sum2) = (0usize, 0.0);
        for p in x {
            if let Some(d2) = grid.nearest_within(p, inlier_m * inlier_m) {
                n_in += 1;
                sum2 += d2;
            }
        }
        let inlier_fraction = n_in as f64 / x.len().max(1) as f64 * (1.0 - stray_share);
        let residual_mm = if n_in > 0 { (sum2 / n_in as f64).sqrt() * 1e3 } else { f64::INFINITY };
        // Coverage on at most COVERAGE_SAMPLES of each side: a share, not an exact count.
        let thin =
            |v: &[P3]| -> Vec<P3> { v.iter().step_by(v.len().div_ceil(COVERAGE_SAMPLES).max(1)).copied().collect() };
        let view = thin(view);
        // A sparse view (200 points of a mug: 9 mm apart) covers the surface
        // between its points: the radius grows with the points' spacing, up
        // to `reach` (duplicated points have none, and cover nothing more).
        let reach = COVERAGE_REACH * inlier_m;
        grid.build(&view, reach);
        let cover_m = (2.0 * median_spacing(&grid, &view, reach)).clamp(inlier_m, reach);
        let surface = thin(&shape);
        let covered = surface.iter().filter(|s| grid.nearest_within(s, cover_m * cover_m).is_some()).count();
        let coverage = covered as f64 / surface.len().max(1) as f64;
        let view_width_mm = (12.0 * principal_frame(&view).1[1].max(0.0)).sqrt() * 1e3;
        let latent_mahalanobis =
            fit.latent.iter().zip(&self.space.variances).map(|(l, v)| l * l / v).sum::<f64>().sqrt();
        FitQuality {
            inlier_fraction,
            stray_fraction,
            stray_points: set_aside.stray + set_aside.table,
            table_points: set_aside.table,
            residual_mm,
            inlier_mm: inlier_m * 1e3,
            coverage,
            latent_mahalanobis,
            view_width_mm,
            confident: inlier_fraction >= CONFIDENT_INLIER_FRACTION
                && coverage >= CONFIDENT_COVERAGE
                && latent_mahalanobis <= CONFIDENT_LATENT_MAHALANOBIS
                && view_width_mm >= CONFIDENT_VIEW_WIDTH_MM,
            ambiguous_pose: false,
            contradicted_fraction: None,
        }
    }
}

/// Median distance from a point of `x` to its nearest other point (on at
/// most 50 of them), at most `reach`; `grid` is built on `x` with `reach`.
fn median_spacing(grid: &RadiusGrid, x: &[P3], reach: f64) -> f64 {
    let mut near = Vec::new();
    let mut d: Vec<f64> = (0..x.len())
        .step_by(x.len().div_ceil(50).max(1))
        .map(|i| {
            near.clear();
            grid.collect_within(&x[i], reach * reach, &mut near);
            let others = near.iter().filter(|&&j| j as usize != i);
            others.map(|&j| dist2(&x[i], &x[j as usize])).fold(reach * reach, f64::min).sqrt()
        })
        .collect();
    if d.is_empty() {
        return 0.0;
    }
    let mid = d.len() / 2;
    *d.select_nth_unstable_by(mid, f64::total_cmp).1
}

/// Two raced poses whose scores (nats per observed point) differ by less than
/// this explain the view equally well.
const AMBIGUITY_MARGIN: f64 = 0.2;

/// Noise forgiven by the free-space test, metres.
const FREE_SPACE_MARGIN_M: f64 = 0.006;
/// Score penalty (nats per observed point) for contradicting the whole visible model.
const FREE_SPACE_PENALTY: f64 = 4.0;

/// A raced pose's score, lower is better: `dense_score`'s likelihood per
/// observed point, penalised by the share of the model the view contradicts
/// and by the tilt of the canonical z from `up` (`RegisterOptions::upright_prior`).
/// (nll a point, violation, score)
#[allow(clippy::too_many_arguments)]
fn pose_score(
    estep: &mut EStep,
    level: &LatentLevel,
    fit: &Fit,
    viewpoint: Option<Vector3<f64>>,
    free_space: Option<&FreeSpace>,
    up: Option<Vector3<f64>>,
    opts: &RegisterOptions,
) -> (f64, f64, f64) {
    let (nll_pt, violation) = dense_score(estep, level, fit, viewpoint, free_space, opts);
    let tilt = up.map_or(0.0, |up| (1.0 - (fit.pose.r * Vector3::z()).dot(&up)) / 2.0);
    (nll_pt, violation, nll_pt + FREE_SPACE_PENALTY * violation + opts.upright_prior * tilt)
}

/// Whether a pose (rotation of the canonical frame) rests as its category
/// was modelled: the canonical z within `REST_POSE_COS` of `up`.
fn rests_as_modelled(r: &Matrix3<f64>, up: &Vector3<f64>) -> bool {
    (r * Vector3::z()).dot(up) > REST_POSE_COS
}

/// A fit's negative log-likelihood per observed point and the share of its
/// camera-facing model the view contradicts, both with `level`'s points at
/// the fit's pose, latent and σ². `estep` holds the view's points; one
/// serves every raced fit, so that once σ is small its truncated sums reuse
/// the level's k-d blocks (measured, `bench_register` with a timer here:
/// mug 140-160 → 124-134 µs a call; eval transfer --views 12 --seed 7 identical).
fn dense_score(
    estep: &mut EStep,
    level: &LatentLevel,
    fit: &Fit,
    viewpoint: Option<Vector3<f64>>,
    free_space: Option<&FreeSpace>,
    opts: &RegisterOptions,
) -> (f64, f64) {
    let y: Vec<P3> = level.model.evaluate(&fit.latent).iter().map(|y| fit.pose.apply(y)).collect();
    let second = opts.second_viewpoint.map(Vector3::from);
    let view = View { normals: &level.normals, viewpoint, occlusion: None, second, second_occlusion: None };
    score_posed(estep, &view, &fit.pose, &y, fit.sigma2, free_space, opts, &mut Vec::new())
}

/// A posed model's score against the view in `estep`: its negative
/// log-likelihood per observed point (the likelihood alone: the posterior
/// sums are not needed) and the share of its camera-facing points the view
/// contradicts. `view.normals` are the model points' canonical normals;
/// `weights` is scratch.
#[allow(clippy::too_many_arguments)]
fn score_posed(
    estep: &mut EStep,
    view: &View,
    pose: &Pose,
    y_world: &[P3],
    sigma2: f64,
    free_space: Option<&FreeSpace>,
    opts: &RegisterOptions,
    weights: &mut Vec<f64>,
) -> (f64, f64) {
    // The normals turned once for both (the same values each would make);
    // without a viewpoint neither reads them.
    let turned: Vec<Vector3<f64>> = match view.viewpoint {
        Some(_) => view.normals.iter().map(|n| pose.r * Vector3::from(*n)).collect(),
        None => Vec::new(),
    };
    let w = view.weights_turned(turned.iter().copied(), y_world, sigma2, weights);
    let nll = estep.neg_log_likelihood(y_world, w, sigma2, opts.outlier_weight);
    let violation = free_space.map_or(0.0, |fs| fs.violation_fraction(y_world, turned.iter().copied()));
    (nll / estep.data().len().max(1) as f64, violation)
}

/// Coarse starts whose rotations are this close after `coarse_merge_after`
/// iterations are merged. Measured: drill and hammer starts that meet are
/// within 1°; the mug's (a body symmetric about its axis) are not, so none merge.
const COARSE_MERGE_ANGLE: f64 = 5.0 * std::f64::consts::PI / 180.0;

/// Two coarse fits whose rotations are within this angle are in one basin of the likelihood.
const SAME_BASIN_ANGLE: f64 = 20.0 * std::f64::consts::PI / 180.0;

fn same_basin(a: &Pose, b: &Pose) -> bool {
    rotation_between(&a.r, &b.r) < SAME_BASIN_ANGLE
}

/// Angle of the rotation from `a` to `b`, robust to round-off: nalgebra's
/// `angle()` takes acos of a trace that drifts past 3 for equal rotations (NaN).
/// The angle (radians, in (−π, π]) of `r` about `axis` when `r` is a turn
/// about it to within 10°: its twist about the axis, where its swing (what
/// is left once the twist is undone) is that small; None otherwise.
fn turn_about(r: &Matrix3<f64>, axis: &Unit<Vector3<f64>>) -> Option<f64> {
    let q = UnitQuaternion::from_matrix(r);
    let theta = 2.0 * q.imag().dot(axis).atan2(q.w);
    let swing = UnitQuaternion::from_axis_angle(axis, -theta) * q;
    let theta = (theta + std::f64::consts::PI).rem_euclid(std::f64::consts::TAU) - std::f64::consts::PI;
    (swing.angle() < 10f64.to_radians()).then_some(theta)
}

fn rotation_between(a: &Matrix3<f64>, b: &Matrix3<f64>) -> f64 {
    let trace = (a.transpose() * b).trace();
    ((trace - 1.0) / 2.0).clamp(-1.0, 1.0).acos()
}

/// At most `n` points of the view: spread evenly over its surface, or uniformly.
pub(super) fn view_subset(x: &[P3], n: usize, even: bool, rng: &mut rand_chacha::ChaCha8Rng) -> Vec<P3> {
    if even {
        even_subsample(x, n, rng)
    } else {
        subsample(x, n, rng)
    }
}

/// The most points a registration works from. Every stage uses far fewer
/// (800 for the polish, 6,000 for the stray test, 4,000 for the free-space
/// image), but the stray test and the even subsamples pass over every point
/// they are given: a 200,000-point view (a denser sensor, merged views) cost
/// about 17 ms there, against 1 ms for a 15,000-point camera view. Larger
/// clouds are first subsampled uniformly (seeded) to this many; a camera
/// view of a tool (5,000-30,000 points) is used whole.
pub const WORKING_POINTS: usize = 1 << 15;

/// The cloud as the registration's points: all of them up to
/// [`WORKING_POINTS`], else a seeded uniform subsample of that many.
fn working_points(cloud: &[Point3<f64>], rng: &mut rand_chacha::ChaCha8Rng) -> Vec<P3> {
    let point = |p: &Point3<f64>| [p.x, p.y, p.z];
    if cloud.len() <= WORKING_POINTS {
        return cloud.iter().map(point).collect();
    }
    let mut idx = rand::seq::index::sample(rng, cloud.len(), WORKING_POINTS).into_vec();
    idx.sort_unstable();
    idx.into_iter().map(|i| point(&cloud[i])).collect()
}

/// The fewest points a fit needs.
const MIN_POINTS: usize = 20;

fn check(cloud: &[Point3<f64>]) -> Result<(), RegisterError> {
    if cloud.is_empty() {
        return Err(RegisterError::Empty);
    }
    if let Some(i) = cloud.iter().position(|p| !(p.x.is_finite() && p.y.is_finite() && p.z.is_finite())) {
        return Err(RegisterError::NonFinite(i));
    }
    if cloud.len() < MIN_POINTS {
        return Err(RegisterError::TooFewPoints { got: cloud.len(), need: MIN_POINTS });
    }
    Ok(())
}

/// The bulk of the cloud ([`BulkBox`]) when its size is a hand-held tool's.
/// Measured on the bulk, not the bounding box: a few far points are strays
/// (set aside and counted), not a reason to refuse the cloud; a cloud in
/// millimetres or kilometres is refused whatever its strays.
fn check_extent(working: &[P3]) -> Result<BulkBox, RegisterError> {
    let bulk = BulkBox::of(working).ok_or(RegisterError::Empty)?;
    let extent = bulk.diagonal();
    if extent < 1e-9 {
        return Err(RegisterError::Degenerate);
    }
    let (min_m, max_m) = (0.005, 5.0);
    if !(min_m..=max_m).contains(&extent) {
        return Err(RegisterError::AbsurdScale { extent_m: extent, min_m, max_m });
    }
    Ok(bulk)
}

/// Points of the cloud set aside before the fit (of the working points).
#[derive(Clone, Copy, Debug)]
struct SetAside {
    stray: usize,
    table: usize,
}

/// The cloud without a table's points ([`TableBand`]) when the up
/// direction is known: the given table's, else the one the cloud's lowest
/// points would stand on (its 1st percentile of height: a leaking mask's
/// table is a tenth or more of the cloud), with that table's height when
/// it was found so. A view that does not leak loses nothing either way.
fn drop_table_points<'a>(
    x: &'a [P3],
    up: Option<Vector3<f64>>,
    given: Option<f64>,
) -> (std::borrow::Cow<'a, [P3]>, Option<f64>) {
    use std::borrow::Cow;
    let Some(up) = up else { return (Cow::Borrowed(x), None) };
    let band = TableBand::default();
    let heights: Vec<f64> = x.iter().map(|p| up.x * p[0] + up.y * p[1] + up.z * p[2]).collect();
    let up = [up.x, up.y, up.z];
    let table = match given {
        Some(t) => t,
        None => {
            // On every k-th point (at most 4,096): a percentile needs no more.
            let mut sorted: Vec<f64> = heights.iter().step_by(heights.len().div_ceil(4096)).copied().collect();
            let k = sorted.len() / 100;
            let lowest = *sorted.select_nth_unstable_by(k, f64::total_cmp).1;
            match band.leaking_table(x, &heights, up, lowest) {
                Some(t) => t,
                None => return (Cow::Borrowed(x), None),
            }
        }
    };
    let Some(table_point) = band.table_points(x, &heights, up, table) else { return (Cow::Borrowed(x), None) };
    let kept: Vec<P3> = x.iter().zip(&table_point).filter(|(_, &t)| !t).map(|(p, _)| *p).collect();
    if kept.len() < MIN_POINTS.max(x.len() / 5) {
        // Hardly anything but the table: fitted whole, it is answered as the poor fit it is.
        return (Cow::Borrowed(x), None);
    }
    (Cow::Owned(kept), Some(table).filter(|_| given.is_none()))
}

/// The world's up as a unit vector in the cloud's frame, when known (a zero
/// vector, which callers are told not to give, reads as z).
fn up_direction(opts: &RegisterOptions) -> Option<Vector3<f64>> {
    opts.up.map(|up| Vector3::from(up).try_normalize(1e-9).unwrap_or_else(Vector3::z))
}

/// Per-hypothesis diagnostics on stderr (GRASPD_REGISTER_TRACE set).
fn trace_enabled() -> bool {
    static ON: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *ON.get_or_init(|| std::env::var_os("GRASPD_REGISTER_TRACE").is_some())
}
