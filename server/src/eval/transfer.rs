//! Keypoint-transfer accuracy from single partial views (issue: shape engine).
//!
//! Each trial places an instance at a random pose on a table (z = 0), renders
//! one view with the virtual depth camera (noise, optional outliers), and
//! registers it with the category's shape space. Errors are measured against
//! the instance's ground-truth semantic keypoints, posed the same way, and the
//! completed shape against the instance's true surface. Two baselines run on
//! the same views: `canonical` (our pose fit, latent held at zero: the
//! undeformed canonical) and `cpd_partial` (non-rigid CPD of the canonical,
//! placed by that pose fit, straight onto the partial view).
//!
//! Semantic keypoints are a few named points on the tool; a grasp depends on
//! others: the demonstration's hand keypoints carried onto the tool (the grasp
//! targets, some centimetres off the surface). On training instances their
//! truth is defined (the instance's own latent, at the true pose, as `graspd
//! eval grasp` uses it), so the report adds their error there: a registration
//! that trades the latent's size modes for its uniform scale can keep the
//! semantic keypoints and still move the fingers' targets.

use super::ambiguity;
use crate::geometry::camera::{quarter_turn_on, standard_view, DepthCamera, DepthNoise, Intrinsics, Scene};
use crate::geometry::{sample_points, PointTree};
use crate::shape::cpd::{self, EmOptions, NonRigidOptions};
use crate::shape::estep::P3;
use crate::shape::{RegisterOptions, Registrar};
use crate::tools::{Instance, Split};
use kiddo::SquaredEuclidean;
use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use rand::{Rng, SeedableRng};
use serde::Serialize;
use std::time::Instant;

#[derive(Clone, Copy, Debug)]
pub struct TransferEvalOptions {
    pub views: usize,
    pub noise: DepthNoise,
    /// Fraction of extra outlier points (uniform in the view's bounding box, grown by 20%).
    pub outliers: f64,
    /// Uniform scale jitter of the instance (±, relative).
    pub scale_jitter: f64,
    /// Lay the tool on its side (rotated 90° about its x axis) instead of its natural rest pose.
    pub on_side: bool,
    /// Register samples of the whole surface instead of a camera view (a
    /// diagnostic: separates the shape space's error from the partial view's).
    pub full_surface: bool,
    /// Merge each view with a second camera's, a quarter turn round the tool
    /// and 25° up (a robot's second look). With `known_viewpoint` the
    /// registration is told both cameras (`RegisterOptions::viewpoint`,
    /// `second_viewpoint`), without it neither.
    pub second_view: bool,
    /// The second camera's calibration error: its points moved by this
    /// distance (m) and turned by this angle (rad) about their centroid,
    /// each in a direction drawn from the view's seed.
    pub second_view_misalign: [f64; 2],
    pub seed: u64,
    pub register: RegisterOptions,
    /// Tell the registration where the camera is (the known viewpoint of a real set-up).
    pub known_viewpoint: bool,
    /// Tell the registration the table's height (z = 0: the tool rests on
    /// it), as a calibrated set-up knows it (`RegisterOptions::support_height`).
    /// The canonical baseline is fitted without it, its better way: held on
    /// the table, the undeformed canonical's wrong height and base move its
    /// keypoints (eval transfer --views 12 --seed 7, test median with / without:
    /// mug 4.36 / 3.44, drill 4.98 / 3.90, hammer 4.66 / 4.42 mm).
    pub known_table: bool,
}

impl Default for TransferEvalOptions {
    fn default() -> Self {
        Self {
            views: 8,
            noise: DepthNoise::default(),
            outliers: 0.0,
            scale_jitter: 0.0,
            on_side: false,
            full_surface: false,
            second_view: false,
            second_view_misalign: [0.0; 2],
            seed: 7,
            register: RegisterOptions::default(),
            known_viewpoint: true,
            known_table: true,
        }
    }
}

#[derive(Clone, Debug, Serialize)]
pub struct Percentiles {
    pub median: f64,
    pub p90: f64,
    pub mean: f64,
}

#[derive(Clone, Debug, Serialize)]
pub struct MethodErrors {
    pub keypoint_error_mm: Percentiles,
    pub chamfer_mm: Percentiles,
    /// The demonstration's hand keypoints carried onto the tool, against the
    /// same carried through the instance's true latent and pose (training
    /// instances only: test tools have no true latent; absent when none was scored).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub grasp_target_error_mm: Option<Percentiles>,
}

#[derive(Clone, Debug, Serialize)]
pub struct SplitReport {
    pub split: String,
    pub instances: usize,
    pub trials: usize,
    /// Views not scored: the camera saw fewer than 50 points of the tool, or
    /// the scene could not be set up (counted, so that nothing vanishes silently).
    pub skipped_views: usize,
    pub points_per_view: Percentiles,
    pub ours: MethodErrors,
    pub canonical: MethodErrors,
    pub cpd_partial: MethodErrors,
    pub fit_ms: FitTimes,
    pub confident_fraction: f64,
    /// Angle between the estimated and the true tool orientation (ours).
    pub rotation_error_deg: Percentiles,
    /// Share of views flagged `ambiguous_pose`, and the keypoint error over the others.
    pub ambiguous_fraction: f64,
    pub unambiguous_keypoint_error_mm: Percentiles,
    /// Share of views answered with assurance (confident, pose not
    /// ambiguous) yet with a keypoint more than `MISLED_MM` off: the answers
    /// a user has no reason to doubt and should.
    pub misled_fraction: f64,
    /// Per view, the mean keypoint error vector (ours) along the camera's
    /// viewing axis; negative: the registered keypoints sit nearer the camera
    /// than the truth. A partial view is seen from one side only, so a fit that
    /// lets the hidden side pull on the seen surface shows here as a bias
    /// that averaging over views does not remove.
    pub keypoint_depth_bias_mm: Percentiles,
    /// Without the camera position (`--unknown-viewpoint`): how often the
    /// registration estimated one and how far it was from the true camera.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub estimated_viewpoint: Option<ViewpointErrors>,
    /// The views whose registration left a yaw arc open (`Registration::yaw_arc`
    /// wider than zero), and whether the truth lies within what it reports.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub yaw_arc: Option<YawArcCalibration>,
    /// What the views themselves leave open, and the floor that puts under
    /// any method's keypoint error (upright tools; see `eval::ambiguity`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub view_ambiguity: Option<ViewAmbiguity>,
}

/// What the views themselves leave open (`eval::ambiguity`): the true
/// tool's turns about its upright axis that each view cannot see, and the
/// keypoint error that leaves to any method. Judged on the camera's clean
/// image: without depth noise, mask leak, occluder or outliers, which only
/// leave more open.
#[derive(Clone, Debug, Serialize)]
pub struct ViewAmbiguity {
    /// Views assessed (upright tools).
    pub views: usize,
    /// Share of them whose true tool turns at least 5° unseen.
    pub open_fraction: f64,
    /// Half the unseen turns' span, over the open views.
    pub half_width_deg: Percentiles,
    /// The floor: an estimator that knows the true shape and answers the
    /// middle of each view's unseen turns, the truth uniform over them
    /// (expected over each arc). No method's pooled quantiles on these views
    /// can be lower in expectation.
    pub keypoint_error_floor_mm: Percentiles,
    /// The same estimator on the truth's actual turn in each view (one draw of the floor).
    pub keypoint_error_at_middle_mm: Percentiles,
    /// On the open views alone: ours, the floor, and the floor's draw.
    pub open_keypoint_error_mm: Percentiles,
    pub open_keypoint_error_floor_mm: Percentiles,
    pub open_keypoint_error_at_middle_mm: Percentiles,
}

/// How well the reported yaw arcs bound the errors they stand for.
#[derive(Clone, Debug, Serialize)]
pub struct YawArcCalibration {
    /// Share of the views with an open arc.
    pub views_fraction: f64,
    pub half_width_deg: Percentiles,
    /// Share of those views whose orientation error is within the half width
    /// and half a sweep step (the arc's resolution).
    pub rotation_within_arc: f64,
    /// Share of their keypoints whose error is within the keypoint's spread
    /// across the arc plus `KEYPOINT_SPREAD_ALLOWANCE_MM` (the shape's own error).
    pub keypoints_within_spread: f64,
    /// Keypoint error (ours) on these views, and the spread reported for them.
    pub keypoint_error_mm: Percentiles,
    pub keypoint_spread_mm: Percentiles,
}

/// The shape's own error a keypoint may add to its spread across a yaw arc
/// (the unambiguous views' keypoint p90 is 3-4 mm on all three categories).
pub const KEYPOINT_SPREAD_ALLOWANCE_MM: f64 = 5.0;

/// The estimated cameras against the true ones, seen from each view's centroid.
#[derive(Clone, Debug, Serialize)]
pub struct ViewpointErrors {
    /// Share of the views for which the registration estimated a camera
    /// (the others it fitted without one: the view did not settle it).
    pub estimated_fraction: f64,
    /// Angle between the estimated and the true direction to the camera.
    pub direction_error_deg: Percentiles,
    /// Estimated over true distance from the centroid.
    pub distance_ratio: Percentiles,
}

#[derive(Clone, Debug, Serialize)]
pub struct FitTimes {
    pub p50: f64,
    pub p99: f64,
    pub max: f64,
}

/// A keypoint this far off (mm) makes a grasp miss: a mug's handle turned
/// by 30° about its body moves about 25 mm.
pub const MISLED_MM: f64 = 20.0;

struct Trial {
    points: usize,
    kp: [Vec<f64>; 3],
    /// Mean keypoint error (ours) along the viewing axis, mm.
    depth_bias_mm: f64,
    /// Grasp-target errors (ours, canonical), empty without a true latent.
    targets: [Vec<f64>; 2],
    chamfer: [f64; 3],
    fit_ms: f64,
    confident: bool,
    ambiguous: bool,
    rotation_error_deg: f64,
    camera: CameraEstimate,
    /// The yaw arc's half width (radians) and each keypoint's spread across it (mm).
    arc: Option<(f64, Vec<f64>)>,
    /// The true tool's turns the view cannot see (radians, about the truth)
    /// and each true keypoint's distance from the turning axis (m); upright views only.
    unseen: Option<((f64, f64), Vec<f64>)>,
}

/// What the registration knew of the camera in one trial.
#[derive(Clone, Copy)]
enum CameraEstimate {
    /// Given (or no camera: whole-surface samples).
    Given,
    /// Not given, and the view did not settle an estimate.
    NotEstimated,
    /// Not given; estimated this far off the true camera, seen from the view's centroid.
    Estimated { direction_deg: f64, distance_ratio: f64 },
}

/// Runs the evaluation on the instances of one split. `grasp_targets` are
/// the demonstration's hand keypoints in the canonical frame (may be empty).
pub fn evaluate(
    registrar: &Registrar,
    instances: &[&Instance],
    split: Split,
    grasp_targets: &[P3],
    opts: &TransferEvalOptions,
    mut progress: impl FnMut(),
) -> SplitReport {
    let mut trials = Vec::new();
    let mut skipped_views = 0;
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(opts.seed);
    for inst in instances {
        let truth_surface = sample_points(&inst.mesh, 4000, 99).map(|p| cpd::to_p3(&p)).unwrap_or_default();
        // The grasp targets on this instance (canonical frame), where its true latent is known.
        let space = &registrar.space;
        let true_targets: Option<Vec<P3>> = space
            .instances
            .iter()
            .position(|n| *n == inst.name)
            .filter(|_| !grasp_targets.is_empty())
            .map(|k| space.deform_anchored(grasp_targets, &space.train_latents[k]));
        let targets = true_targets.as_deref().map(|truth| (grasp_targets, truth));
        for view in 0..opts.views {
            match trial(registrar, inst, &truth_surface, targets, view, opts, &mut rng) {
                Some(t) => trials.push(t),
                None => skipped_views += 1,
            }
            progress();
        }
    }
    let collect = |k: usize| {
        let targets: Vec<f64> = trials.iter().filter_map(|t| t.targets.get(k)).flatten().copied().collect();
        MethodErrors {
            keypoint_error_mm: percentiles(trials.iter().flat_map(|t| t.kp[k].iter().copied()).collect()),
            chamfer_mm: percentiles(trials.iter().map(|t| t.chamfer[k]).collect()),
            grasp_target_error_mm: (!targets.is_empty()).then(|| percentiles(targets)),
        }
    };
    let times = percentiles_raw(trials.iter().map(|t| t.fit_ms).collect());
    SplitReport {
        split: split.name().to_string(),
        instances: instances.len(),
        trials: trials.len(),
        skipped_views,
        points_per_view: percentiles(trials.iter().map(|t| t.points as f64).collect()),
        ours: collect(0),
        canonical: collect(1),
        cpd_partial: collect(2),
        fit_ms: FitTimes { p50: times.0, p99: times.1, max: times.2 },
        confident_fraction: trials.iter().filter(|t| t.confident).count() as f64 / trials.len().max(1) as f64,
        rotation_error_deg: percentiles(trials.iter().map(|t| t.rotation_error_deg).collect()),
        ambiguous_fraction: trials.iter().filter(|t| t.ambiguous).count() as f64 / trials.len().max(1) as f64,
        unambiguous_keypoint_error_mm: percentiles(
            trials.iter().filter(|t| !t.ambiguous).flat_map(|t| t.kp[0].iter().copied()).collect(),
        ),
        misled_fraction: trials
            .iter()
            .filter(|t| t.confident && !t.ambiguous && t.kp[0].iter().any(|e| *e > MISLED_MM))
            .count() as f64
            / trials.len().max(1) as f64,
        keypoint_depth_bias_mm: percentiles(trials.iter().map(|t| t.depth_bias_mm).collect()),
        estimated_viewpoint: viewpoint_errors(&trials),
        yaw_arc: yaw_arc_calibration(&trials, std::f64::consts::TAU / opts.register.yaw_sweep_steps.max(1) as f64),
        view_ambiguity: view_ambiguity(&trials),
    }
}

/// What the views leave open against what ours made of them (None: no
/// trial was assessed, e.g. tools on their side).
fn view_ambiguity(trials: &[Trial]) -> Option<ViewAmbiguity> {
    let assessed: Vec<(&Trial, (f64, f64), &[f64])> =
        trials.iter().filter_map(|t| t.unseen.as_ref().map(|(arc, r)| (t, *arc, r.as_slice()))).collect();
    if assessed.is_empty() {
        return None;
    }
    let open: Vec<_> = assessed.iter().filter(|(_, (lo, hi), _)| hi - lo >= OPEN_TURN.to_radians()).collect();
    let floor = |views: &[&(&Trial, (f64, f64), &[f64])]| {
        percentiles(views.iter().flat_map(|(_, arc, r)| ambiguity::floor_errors_mm(r, *arc, FLOOR_SAMPLES)).collect())
    };
    // The truth lies at turn 0 of its arc: the middle is that far from it.
    let at_middle = |views: &[&(&Trial, (f64, f64), &[f64])]| {
        percentiles(
            views
                .iter()
                .flat_map(|(_, (lo, hi), r)| {
                    let middle = (lo + hi) / 2.0;
                    r.iter().map(move |&r| 1e3 * ambiguity::chord(r, middle))
                })
                .collect(),
        )
    };
    let all: Vec<_> = assessed.iter().collect();
    Some(ViewAmbiguity {
        views: assessed.len(),
        open_fraction: open.len() as f64 / assessed.len() as f64,
        half_width_deg: percentiles(open.iter().map(|(_, (lo, hi), _)| (hi - lo).to_degrees() / 2.0).collect()),
        keypoint_error_floor_mm: floor(&all),
        keypoint_error_at_middle_mm: at_middle(&all),
        open_keypoint_error_mm: percentiles(open.iter().flat_map(|(t, _, _)| t.kp[0].iter().copied()).collect()),
        open_keypoint_error_floor_mm: floor(&open),
        open_keypoint_error_at_middle_mm: at_middle(&open),
    })
}

/// A view whose true tool turns this far (degrees, end to end) unseen counts as open.
const OPEN_TURN: f64 = 5.0;

/// Turns per keypoint over which the floor's expectation is taken.
const FLOOR_SAMPLES: usize = 8;

/// The open arcs against the truth (None: no view left one open). `sweep_step`
/// (radians) is the arc's resolution: the truth may lie half a step beyond its edge.
fn yaw_arc_calibration(trials: &[Trial], sweep_step: f64) -> Option<YawArcCalibration> {
    let open: Vec<(&Trial, f64, &[f64])> = trials
        .iter()
        .filter_map(|t| t.arc.as_ref().filter(|(h, _)| *h > 0.0).map(|(h, s)| (t, *h, s.as_slice())))
        .collect();
    if open.is_empty() {
        return None;
    }
    let n = open.len() as f64;
    let rotation_within =
        open.iter().filter(|(t, h, _)| t.rotation_error_deg.to_radians() <= h + sweep_step / 2.0).count() as f64;
    let pairs: Vec<(f64, f64)> =
        open.iter().flat_map(|(t, _, s)| t.kp[0].iter().copied().zip(s.iter().copied())).collect();
    let within = pairs.iter().filter(|(e, s)| *e <= s + KEYPOINT_SPREAD_ALLOWANCE_MM).count() as f64;
    Some(YawArcCalibration {
        views_fraction: n / trials.len() as f64,
        half_width_deg: percentiles(open.iter().map(|(_, h, _)| h.to_degrees()).collect()),
        rotation_within_arc: rotation_within / n,
        keypoints_within_spread: within / pairs.len().max(1) as f64,
        keypoint_error_mm: percentiles(pairs.iter().map(|p| p.0).collect()),
        keypoint_spread_mm: percentiles(pairs.iter().map(|p| p.1).collect()),
    })
}

/// The estimated cameras' errors over the trials that had to estimate one (None: no such trial).
fn viewpoint_errors(trials: &[Trial]) -> Option<ViewpointErrors> {
    let asked = trials.iter().filter(|t| !matches!(t.camera, CameraEstimate::Given)).count();
    if asked == 0 {
        return None;
    }
    let estimated: Vec<(f64, f64)> = trials
        .iter()
        .filter_map(|t| match t.camera {
            CameraEstimate::Estimated { direction_deg, distance_ratio } => Some((direction_deg, distance_ratio)),
            _ => None,
        })
        .collect();
    Some(ViewpointErrors {
        estimated_fraction: estimated.len() as f64 / asked as f64,
        direction_error_deg: percentiles(estimated.iter().map(|e| e.0).collect()),
        distance_ratio: percentiles(estimated.iter().map(|e| e.1).collect()),
    })
}

/// Where a trial puts the tool and its camera, as `GRASPD_EVAL_TRACE`
/// prints it under "to reproduce": enough to render the same view again
/// (`examples/repro_view.rs`, the tests of views the eval found).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Placement {
    /// Turn about the world's z, radians.
    pub yaw: f64,
    /// Uniform scale of the instance's mesh.
    pub scale: f64,
    /// The tool's origin on the table (x, y), metres.
    pub at: [f64; 2],
    /// Lying on its side: turned a quarter about x before the yaw.
    pub on_side: bool,
}

/// A tool placed on the table (z = 0) and the camera of one of the eval's views.
pub struct PlacedView {
    /// The instance's mesh at the placement's scale, in the tool's frame.
    pub mesh: crate::geometry::TriMesh,
    pub world_from_tool: Isometry3<f64>,
    pub camera: DepthCamera,
}

impl Placement {
    /// An upright tool at scale 1.
    pub fn upright(yaw: f64, at: [f64; 2]) -> Self {
        Self { yaw, scale: 1.0, at, on_side: false }
    }

    /// The rotation of the tool's frame into the world's.
    pub fn rotation(&self) -> UnitQuaternion<f64> {
        let base = if self.on_side {
            UnitQuaternion::from_axis_angle(&Vector3::x_axis(), std::f64::consts::FRAC_PI_2)
        } else {
            UnitQuaternion::identity()
        };
        UnitQuaternion::from_axis_angle(&Vector3::z_axis(), self.yaw) * base
    }

    /// `mesh` placed, its lowest point on the table, and the camera of view
    /// `view` of `views` (`standard_view` round the placed mesh's box).
    pub fn place(
        &self,
        mesh: &crate::geometry::TriMesh,
        view: usize,
        views: usize,
        noise: DepthNoise,
    ) -> Option<PlacedView> {
        let mut mesh = mesh.clone();
        let scale = self.scale;
        mesh.map_vertices(|p| Point3::from(p.coords * scale));
        let rot = self.rotation();
        let zmin = mesh.vertices.iter().map(|p| (rot * p).z).fold(f64::INFINITY, f64::min);
        let world_from_tool = Isometry3::from_parts(Translation3::new(self.at[0], self.at[1], -zmin), rot);
        let centre = world_from_tool * Point3::from(mesh.aabb().map(|(lo, hi)| (lo.coords + hi.coords) / 2.0)?);
        let intrinsics = Intrinsics::default();
        let world_from_camera = standard_view(view, views, centre, mesh.diagonal(), intrinsics).ok()?;
        Some(PlacedView { mesh, world_from_tool, camera: DepthCamera { intrinsics, world_from_camera, noise } })
    }

    /// The second camera of `--second-view` for view `view` of `views`: a
    /// quarter turn on round the tool, 25° up (`quarter_turn_on`).
    pub fn second_view(
        &self,
        mesh: &crate::geometry::TriMesh,
        view: usize,
        views: usize,
        noise: DepthNoise,
    ) -> Option<PlacedView> {
        let (k, count) = quarter_turn_on(view, views);
        self.place(mesh, k, count, noise)
    }
}

impl PlacedView {
    /// The scene the camera sees: the placed tool on the table.
    pub fn scene(&self) -> Option<Scene> {
        Scene::new(&self.mesh, self.world_from_tool, Some(0.0)).ok()
    }

    /// The camera's segmented view of the tool (world frame).
    pub fn capture(&self, seed: u64) -> Option<Vec<Point3<f64>>> {
        Some(self.camera.capture(&self.scene()?, seed).ok()?.points_world)
    }

    /// The camera's position (world frame), as the registration is told it.
    pub fn viewpoint(&self) -> [f64; 3] {
        let v = self.camera.world_from_camera.translation.vector;
        [v.x, v.y, v.z]
    }
}

/// Moves `points` rigidly by `distance` (m) and `angle` (rad) about their
/// centroid, in directions drawn from `seed`: a camera's calibration error.
fn misalign(points: &mut [Point3<f64>], [distance, angle]: [f64; 2], seed: u64) {
    if points.is_empty() || (distance == 0.0 && angle == 0.0) {
        return;
    }
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed ^ 0x6d69_7361_6c69_676e);
    let mut direction = || {
        let (z, phi) = (2.0 * rng.random::<f64>() - 1.0, std::f64::consts::TAU * rng.random::<f64>());
        let r = (1.0 - z * z).max(0.0).sqrt();
        Vector3::new(r * phi.cos(), r * phi.sin(), z)
    };
    let (axis, shift) = (direction(), direction() * distance);
    let turn = UnitQuaternion::from_scaled_axis(axis * angle);
    let centroid = points.iter().fold(Vector3::zeros(), |a, p| a + p.coords) / points.len() as f64;
    for p in points.iter_mut() {
        *p = Point3::from(centroid + turn * (p.coords - centroid) + shift);
    }
}

fn trial(
    registrar: &Registrar,
    inst: &Instance,
    truth_surface: &[P3],
    // The demonstration's grasp targets and the same on this instance (canonical frame).
    grasp_targets: Option<(&[P3], &[P3])>,
    view: usize,
    opts: &TransferEvalOptions,
    rng: &mut rand_chacha::ChaCha8Rng,
) -> Option<Trial> {
    // Place the tool: random yaw and position on the table, optional scale and side rest.
    let scale = 1.0 + opts.scale_jitter * (2.0 * rng.random::<f64>() - 1.0);
    let yaw = rng.random::<f64>() * std::f64::consts::TAU;
    let at = [0.2 * (rng.random::<f64>() - 0.5), 0.2 * (rng.random::<f64>() - 0.5)];
    let placement = Placement { yaw, scale, at, on_side: opts.on_side };
    let placed = placement.place(&inst.mesh, view, opts.views, opts.noise)?;
    let (mesh, world_from_tool, cam) = (&placed.mesh, placed.world_from_tool, &placed.camera);
    let rot = world_from_tool.rotation;
    let pose_pt = |p: &P3| -> P3 {
        let q = world_from_tool * Point3::from(Vector3::from(*p) * scale);
        [q.x, q.y, q.z]
    };
    let truth_kp: Vec<P3> = inst.keypoints.iter().map(|k| pose_pt(&k.position)).collect();
    let truth_world: Vec<P3> = truth_surface.iter().map(pose_pt).collect();

    let mut scene = placed.scene()?;
    let capture_seed: u64 = rng.random();
    let mut cloud = if opts.full_surface {
        sample_points(mesh, 3000, capture_seed).ok()?.into_iter().map(|p| world_from_tool * p).collect()
    } else {
        cam.capture(&scene, capture_seed).ok()?.points_world
    };
    if cloud.len() < 50 {
        return None;
    }
    let second_capture_seed = (opts.second_view && !opts.full_surface).then(|| rng.random::<u64>());
    let mut second_viewpoint = None;
    if let Some(seed) = second_capture_seed {
        let placed2 = placement.second_view(&inst.mesh, view, opts.views, opts.noise)?;
        let mut second = placed2.capture(seed)?;
        misalign(&mut second, opts.second_view_misalign, seed);
        cloud.extend(second);
        second_viewpoint = Some(placed2.viewpoint());
    }
    add_outliers(&mut cloud, opts.outliers, rng);
    // What the view itself leaves open: turns of the upright true tool about
    // its own vertical axis that the camera cannot see.
    let unseen = (!opts.on_side && !opts.full_surface && !opts.second_view)
        .then(|| ambiguity::unseen_turns(cam, &mut scene, world_from_tool))
        .flatten()
        .map(|arc| {
            let axis = world_from_tool.translation.vector;
            (arc, truth_kp.iter().map(|k| (Vector3::from(*k) - axis).xy().norm()).collect())
        });

    // Ours.
    let register_seed: u64 = rng.random();
    let trace = std::env::var_os("GRASPD_EVAL_TRACE").is_some();
    if trace {
        let (r, p, y) = rot.euler_angles();
        eprintln!(
            "{} view {view}: truth rpy {:.0} {:.0} {:.0}° (to reproduce: yaw {yaw} rad, scale {scale}, at [{}, {}], capture seed {capture_seed}, register seed {register_seed}{})",
            inst.name,
            r.to_degrees(),
            p.to_degrees(),
            y.to_degrees(),
            at[0],
            at[1],
            second_capture_seed.map(|s| format!(", second view's capture seed {s}")).unwrap_or_default(),
        );
    }
    let t0 = Instant::now();
    let (cam_pose, t_cam) = (cam.world_from_camera, cam.world_from_camera.translation.vector);
    // With a second view, both cameras (`--unknown-viewpoint`: neither).
    let viewpoint = (opts.known_viewpoint && !opts.full_surface).then_some(placed.viewpoint());
    let second_viewpoint = second_viewpoint.filter(|_| viewpoint.is_some());
    let support_height = opts.known_table.then_some(0.0).or(opts.register.support_height);
    let reg = registrar
        .register(
            &cloud,
            &RegisterOptions { seed: register_seed, viewpoint, support_height, second_viewpoint, ..opts.register },
        )
        .ok()?;
    let fit_ms = t0.elapsed().as_secs_f64() * 1e3;
    let ours_kp: Vec<P3> = reg.keypoints.iter().map(|k| k.position).collect();
    let ours_shape = cpd::to_p3(&registrar.completed_shape(&reg));

    // Baseline 1: the undeformed canonical, pose fitted by the same machinery.
    let canon = registrar
        .register(
            &cloud,
            &RegisterOptions {
                seed: rng.random(),
                fit_latent: false,
                viewpoint,
                second_viewpoint,
                support_height: None,
                ..opts.register
            },
        )
        .ok()?;
    let canon_kp: Vec<P3> = canon.keypoints.iter().map(|k| k.position).collect();
    let canon_shape = cpd::to_p3(&registrar.completed_shape(&canon));

    // Baseline 2: non-rigid CPD of the placed canonical straight onto the view.
    let placed_surface = registrar.completed_shape(&canon);
    let placed_kp: Vec<P3> = canon_kp.clone();
    let stride = (cloud.len() / 1500).max(1);
    let nr = cpd::non_rigid(
        &placed_surface.iter().step_by(4).copied().collect::<Vec<_>>(),
        &cloud.iter().step_by(stride).copied().collect::<Vec<_>>(),
        &NonRigidOptions {
            em: EmOptions { w: 0.1, max_iters: 80, tol: 1e-5 },
            beta: 0.35,
            lambda: 1.0,
            ..Default::default()
        },
    )
    .ok()?;
    let cpd_kp = nr.field.apply(&placed_kp);
    let cpd_shape = nr.field.apply(&cpd::to_p3(&placed_surface));

    let rotation_error_deg = (reg.rotation_cloud_from_canonical * rot.inverse()).angle().to_degrees();
    let camera = match (viewpoint.is_some() || opts.full_surface, reg.estimated_viewpoint) {
        (true, _) => CameraEstimate::Given,
        (false, None) => CameraEstimate::NotEstimated,
        (false, Some(est)) => {
            let centre = cloud.iter().fold(Vector3::zeros(), |a, p| a + p.coords) / cloud.len().max(1) as f64;
            let (e, truth) = (Vector3::from(est) - centre, t_cam - centre);
            CameraEstimate::Estimated {
                direction_deg: e.angle(&truth).to_degrees(),
                distance_ratio: e.norm() / truth.norm().max(1e-12),
            }
        }
    };
    let err = |pred: &[P3], truth: &[P3]| {
        pred.iter().zip(truth).map(|(a, b)| crate::shape::estep::dist2(a, b).sqrt() * 1e3).collect::<Vec<_>>()
    };
    let kp_err = |pred: &[P3]| err(pred, &truth_kp);
    let depth_bias_mm = {
        let view_axis = cam_pose.rotation * Vector3::z();
        let n = ours_kp.len().max(1) as f64;
        let sum: f64 =
            ours_kp.iter().zip(&truth_kp).map(|(a, b)| (Vector3::from(*a) - Vector3::from(*b)).dot(&view_axis)).sum();
        1e3 * sum / n
    };
    let targets = match grasp_targets {
        Some((demo, truth)) => {
            let truth: Vec<P3> = truth.iter().map(pose_pt).collect();
            [err(&registrar.transfer(&reg, demo), &truth), err(&registrar.transfer(&canon, demo), &truth)]
        }
        None => [Vec::new(), Vec::new()],
    };
    Some(Trial {
        points: cloud.len(),
        kp: [kp_err(&ours_kp), kp_err(&canon_kp), kp_err(&cpd_kp)],
        depth_bias_mm,
        targets,
        chamfer: [chamfer_mm(&ours_shape, &truth_world), chamfer_mm(&canon_shape, &truth_world), chamfer_mm(&cpd_shape, &truth_world)],
        fit_ms,
        confident: reg.fit.confident,
        ambiguous: reg.fit.ambiguous_pose,
        rotation_error_deg,
        camera,
        arc: reg.yaw_arc.zip(reg.keypoint_spread_m()).map(|(a, s)| (a.half_width_rad, s.iter().map(|x| x * 1e3).collect())),
        unseen,
    })
    .inspect(|t| {
        if trace {
            let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
            eprintln!(
                "{} view {view}: {} pts, confident {}, ambiguous {}, contradicted {:.3}, rot err {:.1}°, scale {:.3} (true {scale:.3}), inliers {:.2}, coverage {:.3}, mahalanobis {:.2}, kp mean ours {:.1} canonical {:.1} cpd {:.1} mm, {:.1} ms",
                inst.name, t.points, t.confident, t.ambiguous, reg.fit.contradicted_fraction.unwrap_or(f64::NAN), t.rotation_error_deg, reg.scale, reg.fit.inlier_fraction, reg.fit.coverage, reg.fit.latent_mahalanobis, mean(&t.kp[0]), mean(&t.kp[1]), mean(&t.kp[2]), t.fit_ms
            );
            let near: Vec<usize> = truth_kp
                .iter()
                .map(|k| cloud.iter().filter(|p| crate::shape::estep::dist2(&[p.x, p.y, p.z], k) < 0.015 * 0.015).count())
                .collect();
            let (first, last) = (truth_kp.first().copied().unwrap_or_default(), truth_kp.last().copied().unwrap_or_default());
            let to_cam = (t_cam - Vector3::from(last)).xy().normalize();
            let to_kp = (Vector3::from(first) - Vector3::from(last)).xy().normalize();
            // Whether the view saw each keypoint's surroundings, and (for the mug:
            // handle_middle about base_centre) how far round from the camera the first lies.
            eprintln!(
                "   cloud points within 15 mm of each true keypoint {near:?}; keypoint 0 azimuth about the last from the camera's {:.0}°; yaw arc open ±{:.1}°; the true tool turns unseen {}",
                to_cam.angle(&to_kp).to_degrees(),
                t.arc.as_ref().map_or(0.0, |(h, _)| h.to_degrees()),
                t.unseen.as_ref().map_or("(not assessed)".into(), |((lo, hi), _)| format!("{:.1}..{:.1}°", lo.to_degrees(), hi.to_degrees()))
            );
            eprintln!("   ours per keypoint {:?}  canonical {:?}", t.kp[0].iter().map(|x| (x * 10.0).round() / 10.0).collect::<Vec<_>>(), t.kp[1].iter().map(|x| (x * 10.0).round() / 10.0).collect::<Vec<_>>());
            match t.camera {
                CameraEstimate::Estimated { direction_deg, distance_ratio } => eprintln!(
                    "   estimated camera {direction_deg:.1}° off the true direction, {distance_ratio:.2} of its distance"
                ),
                CameraEstimate::NotEstimated => eprintln!("   camera not estimated (the view did not settle it)"),
                CameraEstimate::Given => {}
            }
            if std::env::var_os("GRASPD_EVAL_TRACE_VEC").is_some() {
                let v: Vec<[f64; 3]> = ours_kp
                    .iter()
                    .zip(&truth_kp)
                    .map(|(a, b)| {
                        let d = rot.inverse() * (Vector3::from(*a) - Vector3::from(*b));
                        [(d.x * 1e4).round() / 10.0, (d.y * 1e4).round() / 10.0, (d.z * 1e4).round() / 10.0]
                    })
                    .collect();
                eprintln!("   ours error vectors (tool frame, mm) {v:?}");
                let zmin = ours_shape.iter().map(|p| p[2]).fold(f64::INFINITY, f64::min);
                let czmin = canon_shape.iter().map(|p| p[2]).fold(f64::INFINITY, f64::min);
                eprintln!("   lowest point of the completed shape z = {:.2} mm (canonical {:.2})", zmin * 1e3, czmin * 1e3);
            }
            if !t.targets[0].is_empty() {
                eprintln!("   grasp targets mean ours {:.1} canonical {:.1} mm, latent {:?}", mean(&t.targets[0]), mean(&t.targets[1]), reg.latent.iter().map(|l| (l * 100.0).round() / 100.0).collect::<Vec<_>>());
            }
        }
    })
}

/// Adds `fraction`·N points uniform in the cloud's bounding box grown by 20%.
pub fn add_outliers(cloud: &mut Vec<Point3<f64>>, fraction: f64, rng: &mut rand_chacha::ChaCha8Rng) {
    if fraction <= 0.0 || cloud.is_empty() {
        return;
    }
    let (lo, hi) = cloud.iter().fold((cloud[0], cloud[0]), |(lo, hi), p| (lo.inf(p), hi.sup(p)));
    let pad = (hi - lo) * 0.2;
    let (lo, hi) = (lo - pad, hi + pad);
    let n = (cloud.len() as f64 * fraction).round() as usize;
    for _ in 0..n {
        cloud.push(Point3::new(
            rng.random_range(lo.x..=hi.x),
            rng.random_range(lo.y..=hi.y),
            rng.random_range(lo.z..=hi.z),
        ));
    }
}

/// Symmetric mean nearest-neighbour distance, millimetres.
pub fn chamfer_mm(a: &[P3], b: &[P3]) -> f64 {
    if a.is_empty() || b.is_empty() {
        return f64::INFINITY;
    }
    let one_way = |from: &[P3], to: &[P3]| {
        let tree = PointTree::new_from_slice(to);
        from.iter().map(|p| tree.nearest_one::<SquaredEuclidean>(p).distance.sqrt()).sum::<f64>() / from.len() as f64
    };
    0.5 * (one_way(a, b) + one_way(b, a)) * 1e3
}

/// Value at fraction `q` of sorted, non-empty `v` (index rounded).
fn quantile_sorted(v: &[f64], q: f64) -> f64 {
    v[((v.len() - 1) as f64 * q).round() as usize]
}

pub fn percentiles(mut v: Vec<f64>) -> Percentiles {
    v.retain(|x| x.is_finite());
    if v.is_empty() {
        return Percentiles { median: f64::NAN, p90: f64::NAN, mean: f64::NAN };
    }
    v.sort_by(f64::total_cmp);
    Percentiles {
        median: quantile_sorted(&v, 0.5),
        p90: quantile_sorted(&v, 0.9),
        mean: v.iter().sum::<f64>() / v.len() as f64,
    }
}

/// (p50, p99, max) of `v`, NaN when empty.
fn percentiles_raw(mut v: Vec<f64>) -> (f64, f64, f64) {
    if v.is_empty() {
        return (f64::NAN, f64::NAN, f64::NAN);
    }
    v.sort_by(f64::total_cmp);
    (quantile_sorted(&v, 0.5), quantile_sorted(&v, 0.99), v[v.len() - 1])
}
