//! Grasps and pre-grasps for simulated tools, and where an episode's hand
//! starts.
//!
//! Where the grasp comes from ([`GraspFrom`]):
//!
//! - `inprocess` (the default): graspd's engine in this process, once per
//!   tool, with the tool at its canonical pose on a table at z = 0, carried
//!   to each episode's start (a rigid motion moves the grasp with the tool):
//!   - the canonical tool: the demonstrated grasp itself (the demonstration
//!     was authored on it), its pre-grasp checked against the canonical mesh;
//!   - a training tool: the demonstration transferred through the tool's
//!     latent in the category's shape space (its registered shape at the
//!     canonical pose), solved and backed off, exactly as `graspd eval grasp`
//!     (paper Table I) does. Test tools have no latent: they need the daemon;
//! - `daemon`: a running `graspd serve`, per episode, from the scene depth
//!   camera's view of the tool where it stands ([`crate::daemon`]): any tool
//!   of the family, test tools included (paper Table III);
//! - `register`: the same view registered and grasped by graspd's engine in
//!   this process, as the daemon does it (no daemon needed; the same grasps
//!   but for the transport).
//!
//! Where the hand starts ([`StartMode`], the paper's ablations, Table II):
//!
//! - `pregrasp`: at the generalised grasp's pre-grasp (the default);
//! - `canonical` (w/o GG): the canonical demonstration's grasp carried by
//!   the tool's pose (the true pose in-process; the daemon's registered pose,
//!   scale included, from the daemon), no shape-space transfer; its
//!   pre-grasp backed off in-process the same way;
//! - `neutral` (w/o PG): the open hand at [`neutral_wrist`], above the
//!   table; the script reaches the pre-grasp's line itself
//!   ([`crate::episode::LiftScript::reach_s`]).
//!
//! The keypoint targets of the reward (the generalised demonstration) are the
//! same in every mode: the start changes what the hand does, not the task.

use std::path::{Path, PathBuf};
use std::str::FromStr;

use graspd::grasp::transfer::{solve_transferred, Similarity, TransferModel, TransferredTool};
use graspd::grasp::{
    pregrasp, task_space_distance_cm, Demonstration, Grasp, GraspSolver, PreGraspOptions, Scene, SolveOptions,
    ToolCollider,
};
use graspd::hand::HandModel;
use graspd::shape::{builtin, ShapeSpace};
use graspd::tools::{Category, Instance, Split};
use nalgebra::{Isometry3, Matrix3, Point3, Rotation3, Translation3, UnitQuaternion, Vector3};
use serde::Serialize;

use crate::camera::{LabFrame, SceneCamera};
use crate::daemon::DaemonGrasper;
use crate::engine::SimError;

/// Where graspd's CLI caches the built-in shape spaces (`assets/spaces`).
pub fn spaces_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../assets/spaces")
}

/// The instances of `family` (of `category`) that `which` names:
/// `canonical`, `train`, `test`, `all` (canonical and train: the tools with
/// a training latent) or one instance's name.
pub fn choose_instances<'a>(
    family: &'a [Instance],
    category: Category,
    which: &str,
) -> Result<Vec<&'a Instance>, SimError> {
    let by = |keep: &dyn Fn(Split) -> bool| family.iter().filter(|i| keep(i.split)).collect::<Vec<_>>();
    let chosen = match which {
        "canonical" => by(&|s| s == Split::Canonical),
        "train" => by(&|s| s == Split::Train),
        "test" => by(&|s| s == Split::Test),
        "all" => by(&|s| s != Split::Test),
        name => family.iter().filter(|i| i.name == name).collect(),
    };
    if chosen.is_empty() {
        return Err(SimError::Config {
            reason: format!("no {category} instance `{which}` (canonical, train, test, all, or a name)"),
        });
    }
    Ok(chosen)
}

/// Where an episode's grasp comes from (module docs).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum GraspFrom {
    InProcess,
    Daemon,
    Register,
}

impl GraspFrom {
    pub fn name(self) -> &'static str {
        match self {
            Self::InProcess => "inprocess",
            Self::Daemon => "daemon",
            Self::Register => "register",
        }
    }
}

impl FromStr for GraspFrom {
    type Err = SimError;
    fn from_str(s: &str) -> Result<Self, SimError> {
        match s {
            "inprocess" => Ok(Self::InProcess),
            "daemon" => Ok(Self::Daemon),
            "register" => Ok(Self::Register),
            other => {
                Err(SimError::Config { reason: format!("grasp source `{other}`: `inprocess`, `daemon` or `register`") })
            }
        }
    }
}

/// Where an episode's hand starts (module docs).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum StartMode {
    #[default]
    PreGrasp,
    Canonical,
    Neutral,
}

impl StartMode {
    pub fn name(self) -> &'static str {
        match self {
            Self::PreGrasp => "pregrasp",
            Self::Canonical => "canonical",
            Self::Neutral => "neutral",
        }
    }
}

impl FromStr for StartMode {
    type Err = SimError;
    fn from_str(s: &str) -> Result<Self, SimError> {
        match s {
            "pregrasp" => Ok(Self::PreGrasp),
            "canonical" => Ok(Self::Canonical),
            "neutral" => Ok(Self::Neutral),
            other => {
                Err(SimError::Config { reason: format!("start mode `{other}`: `pregrasp`, `canonical` or `neutral`") })
            }
        }
    }
}

/// The neutral start's wrist (w/o PG), simulator frame: 30 cm above a
/// table top at `table_z`, 20 cm toward the table's −x edge from its
/// centre, palm down, fingers toward +x (palm frame: fingers +z, palmar
/// side +y). Away from every task's tools and fixtures, above all of them.
pub fn neutral_wrist(table_z: f64) -> Isometry3<f64> {
    let fingers = Vector3::x();
    let palmar = -Vector3::z();
    let side = palmar.cross(&fingers);
    let rotation = Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[side, palmar, fingers]));
    Isometry3::from_parts(
        Translation3::new(-0.20, 0.0, table_z + 0.30),
        UnitQuaternion::from_rotation_matrix(&rotation),
    )
}

/// Where the hand is when an episode begins.
#[derive(Clone, Debug, PartialEq)]
pub enum HandStart {
    /// At the plan's pre-grasp (which moves with the tool).
    PreGrasp,
    /// At a fixed pose in the simulator's frame (not carried with the tool),
    /// joints at `actuated`; the script reaches the pre-grasp's line first.
    Fixed { wrist_world: Isometry3<f64>, actuated: Vec<f64> },
}

/// A grasp to execute and the pose the episode starts from.
#[derive(Clone, Debug)]
pub struct GraspPlan {
    pub grasp: Grasp,
    pub pregrasp: Grasp,
    /// graspd's check: no hand sphere pierces the tool or the table at the pre-grasp.
    pub pregrasp_collision_free: bool,
    /// "demonstration" (canonical tool), "transferred" (through the shape
    /// space), "daemon" (graspd serve, from the camera's view), "registered"
    /// (the camera's view registered in this process, `--grasp-from register`) or
    /// "canonical" (the demonstration carried by the tool's pose: w/o GG).
    pub source: &'static str,
    /// Paper Table I metric of the grasp against the generalised
    /// demonstration, cm (0 for the demonstration on its own tool).
    pub task_space_distance_cm: f64,
    /// The generalised demonstration: the 12 keypoint targets the grasp was
    /// solved for (the demonstration's own on the canonical tool), world
    /// frame, hand keypoint order. The keypoint reward and the observations use them.
    pub demo_keypoints: Vec<Point3<f64>>,
    /// The tool's latent in the category's shape space (zeros: the canonical tool).
    pub latent: Vec<f64>,
    /// Where the hand starts (the pre-grasp unless the start mode says otherwise).
    pub start: HandStart,
}

impl GraspPlan {
    /// The plan with the tool moved rigidly to `tool_pose` (the plan was made
    /// with the tool frame at the world origin). A fixed start stays where it is.
    pub fn carried(&self, hand: &HandModel, tool_pose: &Isometry3<f64>) -> Self {
        let carry = |g: &Grasp| Grasp::new(hand, tool_pose * g.wrist_pose_world, g.actuated.clone());
        Self {
            grasp: carry(&self.grasp),
            pregrasp: carry(&self.pregrasp),
            demo_keypoints: self.demo_keypoints.iter().map(|p| tool_pose * p).collect(),
            ..self.clone()
        }
    }

    /// The hand's configuration at the episode's start (wrist, actuated joints).
    pub fn start_configuration(&self) -> (Isometry3<f64>, &[f64]) {
        match &self.start {
            HandStart::PreGrasp => (self.pregrasp.wrist_pose_world, &self.pregrasp.actuated),
            HandStart::Fixed { wrist_world, actuated } => (*wrist_world, actuated),
        }
    }
}

/// How an episode's grasp was obtained (for the reports).
#[derive(Clone, Debug, Default, Serialize)]
pub struct GraspInfo {
    /// `inprocess`, `daemon` or `register`.
    pub grasp_from: &'static str,
    /// `pregrasp`, `canonical` or `neutral`.
    pub start: &'static str,
    /// The plan's source (see [`GraspPlan::source`]).
    pub source: &'static str,
    pub task_space_distance_cm: f64,
    pub pregrasp_collision_free: bool,
    /// From a camera view only (daemon or register): the Grasp call's round
    /// trip as the client sees it (daemon: cloud into shared memory, sent,
    /// answered; register: the in-process call), and the engine's time, ms.
    pub latency_ms: Option<f64>,
    pub daemon_engine_ms: Option<f64>,
    /// From a camera view only: points of the view, and the registration's verdicts.
    pub cloud_points: Option<usize>,
    pub registration_confident: Option<bool>,
    pub ambiguous_pose: Option<bool>,
    /// From a camera view only: the turns about the tool's upright axis the
    /// view left open, half width (rad; 0: settled).
    pub yaw_half_width_rad: Option<f64>,
    /// From a camera view only: the share of the fitted shape's camera-facing
    /// surface the view contradicts (something in front of the tool raises it).
    pub contradicted_fraction: Option<f64>,
    /// From a camera view only: how far the registered canonical frame is from the
    /// tool's own frame (its origin's offset, m; its turn, rad) and the
    /// registered scale. A tool's mesh is given in its category's canonical
    /// frame, so a good registration is near zero offset and turn (a
    /// training or test tool's shape differs, so not exactly zero).
    pub registered_offset_m: Option<f64>,
    pub registered_turn_rad: Option<f64>,
    pub registered_scale: Option<f64>,
    /// From a camera view of a training tool only: how far the generalised
    /// demonstration the grasp was solved for lies from the one through the
    /// tool's own latent at its true pose (what `inprocess` solves for), mm.
    pub target_error_mm: Option<TargetError>,
    pub daemon_warnings: Vec<String>,
}

/// Distances between two sets of keypoint targets, mm.
#[derive(Clone, Copy, Debug, Default, Serialize)]
pub struct TargetError {
    pub mean: f64,
    pub max: f64,
}

impl TargetError {
    pub fn between(a: &[Point3<f64>], b: &[Point3<f64>]) -> Self {
        let d: Vec<f64> = a.iter().zip(b).map(|(p, q)| 1e3 * (p - q).norm()).collect();
        let n = d.len().max(1) as f64;
        Self { mean: d.iter().sum::<f64>() / n, max: d.iter().copied().fold(0.0, f64::max) }
    }
}

/// Plans grasps for a category's instances (one shape space, one
/// demonstration), in-process or from a daemon, for a start mode.
pub struct GraspPlanner {
    hand: HandModel,
    category: Category,
    demo: Demonstration,
    space: ShapeSpace,
    solver: GraspSolver,
    /// The demonstration and canonical mesh as models of the latent, made on
    /// the first transferred plan and kept for the category's other tools.
    transfer: Option<TransferModel>,
    pregrasp: PreGraspOptions,
    start: StartMode,
    daemon: Option<DaemonGrasper>,
}

fn engine_error(e: impl std::fmt::Display) -> SimError {
    SimError::Plan { reason: e.to_string() }
}

impl GraspPlanner {
    /// Loads the category's bundled demonstration and its shape space (built
    /// and cached under `assets/spaces` when missing, as the CLI does).
    /// Plans in-process, episodes start at the pre-grasp.
    pub fn new(hand: &HandModel, category: Category, seed: u64) -> Result<Self, SimError> {
        let demo = Demonstration::builtin(category).map_err(engine_error)?;
        Self::with_demonstration(hand, category, seed, demo)
    }

    /// [`Self::new`] with `demo` instead of the bundled demonstration (made
    /// with `hand`: checked here).
    pub fn with_demonstration(
        hand: &HandModel,
        category: Category,
        seed: u64,
        demo: Demonstration,
    ) -> Result<Self, SimError> {
        demo.checked_keypoints(hand).map_err(engine_error)?;
        let space = builtin::load_or_build(category, &spaces_dir(), |_, _| {}).map_err(engine_error)?;
        let solver = GraspSolver::new(hand, SolveOptions { seed, ..SolveOptions::default() });
        Ok(Self {
            hand: hand.clone(),
            category,
            demo,
            space,
            solver,
            transfer: None,
            pregrasp: PreGraspOptions::default(),
            start: StartMode::PreGrasp,
            daemon: None,
        })
    }

    /// Episodes start as `start` says.
    pub fn with_start(mut self, start: StartMode) -> Self {
        self.start = start;
        self
    }

    /// Grasps come from this daemon (connected: [`DaemonGrasper::connect`]).
    pub fn with_daemon(mut self, daemon: DaemonGrasper) -> Self {
        self.daemon = Some(daemon);
        self
    }

    /// Grasps from the camera's view as the daemon makes them, by graspd's
    /// engine in this process ([`DaemonGrasper::in_process`]): `--grasp-from register`.
    pub fn with_engine_camera(self, camera: SceneCamera, lab: LabFrame) -> Result<Self, SimError> {
        let grasper = DaemonGrasper::in_process(&self.hand, self.category, self.space.clone(), camera, lab)?;
        Ok(self.with_daemon(grasper))
    }

    pub fn grasp_from(&self) -> GraspFrom {
        match &self.daemon {
            Some(d) if d.is_daemon() => GraspFrom::Daemon,
            Some(_) => GraspFrom::Register,
            None => GraspFrom::InProcess,
        }
    }

    pub fn start_mode(&self) -> StartMode {
        self.start
    }

    /// The in-process plan for `instance`, the tool frame at the world origin, the table top at z = 0.
    pub fn plan(&mut self, instance: &Instance) -> Result<GraspPlan, SimError> {
        let hand = &self.hand;
        if instance.split == Split::Canonical {
            let grasp = self.demo.grasp_at(hand, &Isometry3::identity()).map_err(engine_error)?;
            let collider = ToolCollider::new(&instance.mesh, Isometry3::identity()).map_err(engine_error)?;
            let scene = Scene { tool: Some(&collider), table_height_world: self.demo.table.then_some(0.0) };
            let pre = pregrasp(hand, &grasp, &scene, &self.pregrasp).map_err(engine_error)?;
            return Ok(GraspPlan {
                grasp,
                pregrasp: pre.grasp,
                pregrasp_collision_free: pre.collision_free,
                source: "demonstration",
                task_space_distance_cm: 0.0,
                demo_keypoints: self.demo.keypoints(hand).map_err(engine_error)?,
                latent: vec![0.0; self.space.modes.len()],
                start: HandStart::PreGrasp,
            });
        }
        let k = self.training_index(instance).ok_or_else(|| SimError::Plan {
            reason: if instance.split == Split::Test {
                format!(
                    "`{}` is a test instance: it has no latent in the {} shape space, so it is grasped from the camera's view through the daemon (--grasp-from daemon)",
                    instance.name, self.space.category
                )
            } else {
                format!("`{}` is not a training instance of the {} shape space", instance.name, self.space.category)
            },
        })?;
        let latent = self.space.train_latents[k].clone();
        let tool = TransferredTool::from_latent(self.transfer_model()?, &latent).map_err(engine_error)?;
        // As `graspd eval grasp`: the table under the registered shape.
        let table = self.demo.table.then(|| tool.lowest_z());
        let out =
            solve_transferred(&mut self.solver, &self.demo, &tool, table, &self.pregrasp).map_err(engine_error)?;
        Ok(GraspPlan {
            grasp: out.grasp,
            pregrasp: out.pregrasp.grasp,
            pregrasp_collision_free: out.pregrasp.collision_free,
            source: "transferred",
            task_space_distance_cm: out.task_space_distance_cm,
            demo_keypoints: tool.targets.clone(),
            latent,
            start: HandStart::PreGrasp,
        })
    }

    /// The demonstration and canonical mesh as models of the latent, made
    /// on the first call and kept for the category's other tools.
    fn transfer_model(&mut self) -> Result<&TransferModel, SimError> {
        if self.transfer.is_none() {
            let keypoints = self.demo.keypoints(&self.hand).map_err(engine_error)?;
            let canonical = self.canonical_instance()?;
            self.transfer = Some(TransferModel::new(&self.space, &keypoints, &canonical.mesh));
        }
        Ok(self.transfer.as_ref().expect("made above"))
    }

    /// Where `instance` is among the shape space's training tools (its latent's row).
    fn training_index(&self, instance: &Instance) -> Option<usize> {
        self.space.instances.iter().position(|n| n == &instance.name)
    }

    fn canonical_instance(&self) -> Result<Instance, SimError> {
        graspd::tools::family(self.category)
            .map_err(engine_error)?
            .into_iter()
            .find(|i| i.split == Split::Canonical)
            .ok_or_else(|| SimError::Plan { reason: "the family has no canonical instance".into() })
    }

    /// The plan of one episode, the tool frame at the world origin (as
    /// [`Self::plan`]; carried to the episode's start by the episode), with
    /// the tool standing at `tool_start` (simulator frame) on a table at
    /// `table_z`. In-process: `base` (this tool's [`Self::plan`], made once)
    /// or a new one; from the daemon: the camera's view of the tool at
    /// `tool_start` (noise and registration seeded by `seed`). Then the start
    /// mode is applied.
    pub fn episode_plan(
        &mut self,
        instance: &Instance,
        base: Option<&GraspPlan>,
        tool_start: &Isometry3<f64>,
        table_z: f64,
        seed: u64,
    ) -> Result<(GraspPlan, GraspInfo), SimError> {
        let mut info =
            GraspInfo { grasp_from: self.grasp_from().name(), start: self.start.name(), ..GraspInfo::default() };
        let (mut plan, tool_from_canonical) = match &mut self.daemon {
            None => {
                let plan = match base {
                    Some(p) => p.clone(),
                    None => self.plan(instance)?,
                };
                (plan, Similarity::identity())
            }
            Some(daemon) => {
                let d = daemon.grasp(
                    &self.hand,
                    self.category,
                    &instance.mesh,
                    tool_start,
                    table_z,
                    self.demo.table,
                    seed,
                )?;
                if d.latent.len() != self.space.modes.len() {
                    return Err(SimError::Daemon {
                        prefix: daemon.prefix().to_owned(),
                        reason: format!(
                            "its latent has {} values, the simulator's shape space {} modes",
                            d.latent.len(),
                            self.space.modes.len()
                        ),
                    });
                }
                // The generalised demonstration the daemon solved for: the
                // demonstration's keypoints through the latent and the
                // registered pose (what graspd's Registrar::transfer does),
                // in the simulator's copy of the same shape space.
                let keypoints: Vec<[f64; 3]> =
                    self.demo.keypoints(&self.hand).map_err(engine_error)?.iter().map(|p| [p.x, p.y, p.z]).collect();
                let targets: Vec<Point3<f64>> = self
                    .space
                    .deform_anchored(&keypoints, &d.latent)
                    .into_iter()
                    .map(|z| d.tool_from_canonical.apply(&Point3::from(z)))
                    .collect();
                info.latency_ms = Some(d.latency_ms);
                info.daemon_engine_ms = Some(d.engine_ms);
                info.cloud_points = Some(d.cloud_points);
                info.registration_confident = Some(d.registration_confident);
                info.ambiguous_pose = Some(d.ambiguous_pose);
                info.yaw_half_width_rad = d.yaw_half_width_rad;
                info.contradicted_fraction = d.contradicted_fraction;
                info.registered_offset_m = Some(d.tool_from_canonical.translation.norm());
                info.registered_turn_rad = Some(d.tool_from_canonical.rotation.angle());
                info.registered_scale = Some(d.tool_from_canonical.scale);
                info.daemon_warnings = d.warnings.clone();
                let plan = GraspPlan {
                    grasp: d.grasp,
                    pregrasp: d.pregrasp,
                    pregrasp_collision_free: d.pregrasp_collision_free,
                    source: if daemon.is_daemon() { "daemon" } else { "registered" },
                    task_space_distance_cm: d.task_space_distance_cm,
                    demo_keypoints: targets,
                    latent: d.latent,
                    start: HandStart::PreGrasp,
                };
                (plan, d.tool_from_canonical)
            }
        };
        if self.daemon.is_some() {
            if let Some(k) = self.training_index(instance) {
                let latent = self.space.train_latents[k].clone();
                let truth = self.transfer_model()?.targets(&latent);
                info.target_error_mm = Some(TargetError::between(&plan.demo_keypoints, &truth));
            }
        }
        match self.start {
            StartMode::PreGrasp => {}
            StartMode::Canonical => {
                // w/o GG: the demonstrated wrist and joints, moved only by
                // where the tool is thought to be (no shape-space transfer).
                let hand = &self.hand;
                let demo = self.demo.grasp_at(hand, &Isometry3::identity()).map_err(engine_error)?;
                let grasp = Grasp::new(hand, tool_from_canonical.carry(&demo.wrist_pose_world), demo.actuated.clone());
                let collider = ToolCollider::new(&instance.mesh, Isometry3::identity()).map_err(engine_error)?;
                let scene = Scene { tool: Some(&collider), table_height_world: self.demo.table.then_some(0.0) };
                let pre = pregrasp(hand, &grasp, &scene, &self.pregrasp).map_err(engine_error)?;
                plan.task_space_distance_cm = task_space_distance_cm(hand, &grasp, &plan.demo_keypoints);
                plan.grasp = grasp;
                plan.pregrasp = pre.grasp;
                plan.pregrasp_collision_free = pre.collision_free;
                plan.source = "canonical";
            }
            StartMode::Neutral => {
                plan.start =
                    HandStart::Fixed { wrist_world: neutral_wrist(table_z), actuated: self.hand.open_hand().to_vec() };
            }
        }
        info.source = plan.source;
        info.task_space_distance_cm = plan.task_space_distance_cm;
        info.pregrasp_collision_free = plan.pregrasp_collision_free;
        Ok((plan, info))
    }

    pub fn hand(&self) -> &HandModel {
        &self.hand
    }

    /// Dimension of the category's latent (shape-space modes).
    pub fn latent_dim(&self) -> usize {
        self.space.modes.len()
    }
}
