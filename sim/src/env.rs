//! Environments stepped by actions: the tasks (Place mug, Position drill,
//! Drive nail) as a trainer or a policy drives them, one flat action in,
//! one flat observation, a reward and the task's success rule out, every
//! control step (30 Hz), in the layouts of [`crate::obs`].
//!
//! - [`TaskEnv`]: one environment on one tool. [`TaskEnv::reset`] draws the
//!   episode's start (and goal) from its seed within the task's documented
//!   ranges, gets the grasp plan for the tool where it starts (in-process,
//!   or the camera's view through the daemon or the engine, as the planner
//!   says) and puts the hand at the plan's start; [`TaskEnv::step`] applies
//!   an action (the wrist command moved by the clamped deltas, the joint
//!   targets clamped to the hand's limits), steps the physics one control
//!   interval and returns the paper's reward for the new state. An episode
//!   lasts 10 s (300 steps); success is judged by the task's rule on the
//!   state, and what counts is its value at the end.
//! - [`VecTaskEnv`]: N environments (on one or several tools of a category:
//!   a trainer's mix of training tools) stepped in parallel on a rayon pool,
//!   observations, rewards and flags in flat batch buffers, each finished
//!   episode reset at once with the next seed (its last observation kept in
//!   [`VecTaskEnv::final_observations`]). Tools share one compiled scene
//!   each; every environment has its own `MjData`.
//! - [`Expert`]: the task's scripted controller expressed as actions through
//!   this interface (it reads privileged state: the tool's pose, the nail):
//!   demonstrations for a trainer, and the check that the action path can
//!   do what the scripted episodes do.
//!
//! A policy's output is outside input: an action of the wrong length or
//! with a value that is not finite is refused with an error naming it, and
//! nothing is stepped.

use std::sync::Arc;

use graspd::hand::HandModel;
use graspd::tools::Instance;
use mujoco_rs::prelude::{MjData, MjModel};
use nalgebra::{Isometry3, Point3};
use rayon::prelude::*;
use serde::Serialize;

use crate::carry::{clearance, TaskRig, HEIGHT_POINTS};
use crate::engine::SimError;
use crate::episode::{reset_to_pregrasp, substeps, LiftSetup};
use crate::hand::HandAsset;
use crate::nail::{face_of, NailController, NailFixture, NailIndex, NailSetup};
use crate::obs::{observe, Action, ActionLayout, ActionLimits, ObservationLayout};
use crate::place::{PlaceController, PlaceSetup, PoseController};
use crate::plan::{GraspInfo, GraspPlan, GraspPlanner};
use crate::position::{DrillController, DrillSetup};
use crate::scene::{Scene, Table};
pub use crate::task::Task;
use crate::task::{self, nail_reward, pose_reward, GraspState, NailEpisode, NailState, PoseEpisode, PoseState};

/// One environment's MuJoCo state, on its tool's shared model.
pub type EnvData = MjData<Arc<MjModel>>;

/// A task's setup: the same as its scripted episodes' (physics, ranges,
/// fixture; the script is the [`Expert`]'s).
#[derive(Clone, Debug)]
pub enum TaskSetup {
    Place(PlaceSetup),
    Position(DrillSetup),
    Nail(NailSetup),
}

impl TaskSetup {
    /// The task's defaults, as `sim place|position|nail` runs them.
    pub fn new(task: Task) -> Self {
        match task {
            Task::PlaceMug => Self::Place(PlaceSetup::default()),
            Task::PositionDrill => Self::Position(DrillSetup::default()),
            Task::DriveNail => Self::Nail(NailSetup::default()),
        }
    }

    pub fn task(&self) -> Task {
        match self {
            Self::Place(_) => Task::PlaceMug,
            Self::Position(_) => Task::PositionDrill,
            Self::Nail(_) => Task::DriveNail,
        }
    }

    pub fn base(&self) -> &LiftSetup {
        match self {
            Self::Place(s) => &s.base,
            Self::Position(s) => &s.base,
            Self::Nail(s) => &s.base,
        }
    }

    pub fn base_mut(&mut self) -> &mut LiftSetup {
        match self {
            Self::Place(s) => &mut s.base,
            Self::Position(s) => &mut s.base,
            Self::Nail(s) => &mut s.base,
        }
    }

    fn validate(&self) -> Result<(), SimError> {
        match self {
            Self::Place(s) => s.ranges.validate(),
            Self::Position(s) => s.ranges.validate(),
            Self::Nail(s) => {
                s.ranges.validate()?;
                s.fixture.validate()
            }
        }
    }

    /// Episode `seed`'s start (and goal) on a table top at `table_z`.
    fn draw(&self, seed: u64, table_z: f64) -> Draw {
        match self {
            Self::Place(s) => Draw::Pose(s.ranges.sample(seed, table_z)),
            Self::Position(s) => Draw::Pose(s.ranges.sample(seed, table_z)),
            Self::Nail(s) => Draw::Nail(s.ranges.sample(seed, table_z)),
        }
    }
}

/// Everything that sets up a task's environments besides the tools.
#[derive(Clone, Debug)]
pub struct EnvSetup {
    pub task: TaskSetup,
    pub limits: ActionLimits,
}

impl EnvSetup {
    pub fn new(task: Task) -> Self {
        Self { task: TaskSetup::new(task), limits: ActionLimits::default() }
    }
}

/// One episode's draw.
#[derive(Clone, Debug)]
enum Draw {
    Pose(PoseEpisode),
    Nail(NailEpisode),
}

impl Draw {
    fn start(&self) -> Isometry3<f64> {
        match self {
            Self::Pose(e) => e.start,
            Self::Nail(e) => e.start,
        }
    }
}

/// One tool's compiled scene and in-process plan, shared by its environments.
struct ToolRig {
    instance: Instance,
    scene: Scene,
    /// The in-process plan, tool frame at the origin (`None`: planned per episode).
    plan: Option<GraspPlan>,
    height_points: Vec<Point3<f64>>,
    table_z: f64,
    /// Drive nail: the nail in the scene and the hammer's face (tool frame).
    nail: Option<(NailIndex, Point3<f64>)>,
}

impl ToolRig {
    fn build(
        asset: &HandAsset,
        planner: &mut GraspPlanner,
        instance: &Instance,
        setup: &TaskSetup,
    ) -> Result<(Self, EnvData), SimError> {
        let task = setup.task();
        if instance.category != task.category() {
            return Err(SimError::Config {
                reason: format!(
                    "{} takes a {}, not `{}` ({})",
                    task.name(),
                    task.category(),
                    instance.name,
                    instance.category
                ),
            });
        }
        let (bodies, contact) = match setup {
            TaskSetup::Nail(s) => {
                // The board stands where the ranges put it, whatever the seed.
                let board = s.ranges.sample(0, Table::default().top_z).board;
                (s.fixture.bodies(&board), NailFixture::contact())
            }
            _ => (Vec::new(), Vec::new()),
        };
        let rig = TaskRig::build(asset, planner, instance, setup.base(), task.name(), bodies, contact)?;
        let nail = match setup {
            TaskSetup::Nail(_) => Some((NailIndex::new(&rig.scene.model)?, face_of(instance)?)),
            _ => None,
        };
        let TaskRig { plan, instance, scene, data, height_points, table } = rig;
        if scene.hand.is_none() || scene.tools.is_empty() || height_points.len() != HEIGHT_POINTS {
            return Err(SimError::Config { reason: format!("the {} scene lacks its hand or tool", task.name()) });
        }
        Ok((Self { instance, scene, plan, height_points, table_z: table.top_z, nail }, data))
    }
}

/// The state of the episode under way.
struct Episode {
    seed: u64,
    draw: Draw,
    /// The plan carried to the tool's start.
    plan: GraspPlan,
    info: GraspInfo,
    /// The generalised demonstration in the tool frame (it rides with the tool).
    demo_tool: Vec<Point3<f64>>,
    /// The wrist command (the arm's end-effector target) and joint targets.
    command: Isometry3<f64>,
    q: Vec<f64>,
    steps: usize,
    /// Drive nail: the nail's depth after the last step.
    depth_m: f64,
    episode_return: f64,
}

/// What one step gave.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct StepResult {
    /// The paper's reward for the state after the step (all terms, weighted).
    pub reward: f64,
    /// The task's success rule on that state.
    pub success: bool,
    /// The episode's time is up (10 s): reset before stepping again.
    pub done: bool,
}

/// How a finished episode went.
#[derive(Clone, Debug, Serialize)]
pub struct EpisodeSummary {
    pub env: usize,
    pub instance: String,
    pub seed: u64,
    /// The task's rule at the end of the episode.
    pub success: bool,
    pub episode_return: f64,
    pub steps: usize,
    pub grasp: GraspInfo,
}

/// One environment: a task on one tool (module docs).
pub struct TaskEnv {
    task: Task,
    setup: Arc<EnvSetup>,
    hand: HandModel,
    rig: Arc<ToolRig>,
    data: EnvData,
    substeps: usize,
    steps_per_episode: usize,
    obs_layout: ObservationLayout,
    episode: Option<Episode>,
}

impl TaskEnv {
    /// An environment of `setup`'s task on `instance` (the planner's
    /// category), its scene compiled; [`Self::reset`] starts an episode.
    pub fn new(
        asset: &HandAsset,
        planner: &mut GraspPlanner,
        instance: &Instance,
        setup: EnvSetup,
    ) -> Result<Self, SimError> {
        setup.task.validate()?;
        let (rig, data) = ToolRig::build(asset, planner, instance, &setup.task)?;
        Ok(Self::on_rig(asset.model(), planner, Arc::new(rig), data, Arc::new(setup)))
    }

    fn on_rig(
        hand: &HandModel,
        planner: &GraspPlanner,
        rig: Arc<ToolRig>,
        data: EnvData,
        setup: Arc<EnvSetup>,
    ) -> Self {
        let control_hz = setup.task.base().physics.control_hz;
        Self {
            task: setup.task.task(),
            substeps: substeps(&rig.scene, control_hz),
            steps_per_episode: ((task::EPISODE_S * control_hz).round() as usize).max(1),
            obs_layout: ObservationLayout { keypoints: hand.keypoints().len(), latent_dim: planner.latent_dim() },
            hand: hand.clone(),
            setup,
            rig,
            data,
            episode: None,
        }
    }

    pub fn task(&self) -> Task {
        self.task
    }

    pub fn instance(&self) -> &Instance {
        &self.rig.instance
    }

    pub fn observation_layout(&self) -> ObservationLayout {
        self.obs_layout
    }

    pub fn action_layout(&self) -> ActionLayout {
        ActionLayout { actuated: self.hand.num_actuated() }
    }

    /// Control steps in an episode (10 s at the control rate).
    pub fn steps_per_episode(&self) -> usize {
        self.steps_per_episode
    }

    /// Starts episode `seed`: its draw, its grasp plan (from `planner`, the
    /// category's), the scene at rest with the hand at the plan's start.
    pub fn reset(&mut self, planner: &mut GraspPlanner, seed: u64) -> Result<(), SimError> {
        self.episode = None;
        let rig = &self.rig;
        let draw = self.setup.task.draw(seed, rig.table_z);
        let start = draw.start();
        let (plan, info) = planner.episode_plan(&rig.instance, rig.plan.as_ref(), &start, rig.table_z, seed)?;
        let plan = plan.carried(&self.hand, &start);
        reset_to_pregrasp(&rig.scene, &mut self.data, &self.hand, &plan, &start)?;
        let tool_from_world = start.inverse();
        let demo_tool = plan.demo_keypoints.iter().map(|p| tool_from_world * p).collect();
        let (command, q) = plan.start_configuration();
        let (command, q) = (command, q.to_vec());
        let depth_m = rig.nail.as_ref().map_or(0.0, |(n, _)| n.depth(&self.data));
        self.episode =
            Some(Episode { seed, draw, plan, info, demo_tool, command, q, steps: 0, depth_m, episode_return: 0.0 });
        Ok(())
    }

    fn episode(&self) -> Result<&Episode, SimError> {
        self.episode.as_ref().ok_or_else(|| SimError::Config { reason: "no episode under way: reset first".into() })
    }

    /// The observation now, written into `out` (the layout's length).
    pub fn observe_into(&self, out: &mut [f32]) -> Result<(), SimError> {
        let e = self.episode()?;
        observe(&self.rig.scene, &self.data, &e.demo_tool, &e.plan.latent, &self.goal(e))?.write_into(out)
    }

    /// The observation now, as a vector.
    pub fn observation(&self) -> Result<Vec<f32>, SimError> {
        let mut v = vec![0.0; self.obs_layout.len()];
        self.observe_into(&mut v)?;
        Ok(v)
    }

    /// The goal segment of the observation (module docs of [`crate::obs`]):
    /// the goal pose, or the top of the nail's head.
    fn goal(&self, e: &Episode) -> Isometry3<f64> {
        match (&e.draw, &self.rig.nail) {
            (Draw::Pose(p), _) => p.goal,
            (Draw::Nail(_), Some((nail, _))) => {
                let h = nail.head_top(&self.data);
                Isometry3::translation(h.x, h.y, h.z)
            }
            (Draw::Nail(_), None) => Isometry3::identity(),
        }
    }

    /// Checks a flat action against the layout.
    pub fn parse_action(&self, action: &[f32]) -> Result<Action, SimError> {
        Action::from_slice(&self.action_layout(), action)
    }

    /// One control step with `action` (module docs). An error, and nothing
    /// stepped, for a bad action, or without an episode under way or after its end.
    pub fn step(&mut self, action: &[f32]) -> Result<StepResult, SimError> {
        let action = self.parse_action(action)?;
        let e = self.episode()?;
        if e.steps >= self.steps_per_episode {
            return Err(SimError::Config { reason: format!("episode {} is over: reset first", e.seed) });
        }
        Ok(self.step_parsed(&action))
    }

    fn step_parsed(&mut self, action: &Action) -> StepResult {
        let Some(e) = self.episode.as_mut() else { return StepResult { reward: 0.0, success: false, done: true } };
        let rig = &*self.rig;
        let (Some(hand), Some(tool)) = (rig.scene.hand.as_ref(), rig.scene.tools.first()) else {
            unreachable!("ToolRig::build checks the hand and the tool")
        };
        e.command = action.apply(&e.command, &self.setup.limits);
        e.q.copy_from_slice(&action.joint_targets);
        self.hand.clamp_actuated(&mut e.q);
        hand.set_wrist_target(&mut self.data, &e.command);
        hand.set_joint_targets(&mut self.data, &e.q);
        for _ in 0..self.substeps {
            self.data.step();
        }
        e.steps += 1;
        let pose = tool.pose(&self.data);
        let hand_keypoints = hand.keypoints(&self.data);
        let demo_world: Vec<Point3<f64>> = e.demo_tool.iter().map(|p| pose * p).collect();
        let grasp = GraspState {
            hand_keypoints: &hand_keypoints,
            demo_keypoints: &demo_world,
            clearance_m: clearance(&rig.height_points, &pose, rig.table_z),
        };
        let (reward, success) = match (&e.draw, &rig.nail) {
            (Draw::Pose(p), _) => {
                let r = pose_reward(&PoseState { tool_pose: pose, goal: p.goal, grasp });
                (r.total, task::reached(&pose, &p.goal))
            }
            (Draw::Nail(_), Some((nail, face))) => {
                let depth = nail.depth(&self.data);
                let r = nail_reward(&NailState {
                    face: pose * face,
                    nail_head: nail.head_top(&self.data),
                    depth_m: depth,
                    previous_depth_m: e.depth_m,
                    grasp,
                });
                e.depth_m = depth;
                (r.total, task::nail_driven(depth))
            }
            (Draw::Nail(_), None) => unreachable!("a Drive-nail rig has its nail"),
        };
        e.episode_return += reward;
        StepResult { reward, success, done: e.steps >= self.steps_per_episode }
    }

    /// The episode under way, summed up so far (`env`: its index in a batch).
    pub fn summary(&self, env: usize) -> Result<EpisodeSummary, SimError> {
        let e = self.episode()?;
        Ok(EpisodeSummary {
            env,
            instance: self.rig.instance.name.clone(),
            seed: e.seed,
            success: self.success_now()?,
            episode_return: e.episode_return,
            steps: e.steps,
            grasp: e.info.clone(),
        })
    }

    /// The task's rule on the state now.
    pub fn success_now(&self) -> Result<bool, SimError> {
        let e = self.episode()?;
        Ok(match (&e.draw, &self.rig.nail) {
            (Draw::Pose(p), _) => task::reached(&self.tool_pose()?, &p.goal),
            (Draw::Nail(_), Some((nail, _))) => task::nail_driven(nail.depth(&self.data)),
            (Draw::Nail(_), None) => false,
        })
    }

    /// Privileged state (for the [`Expert`] and checks, not a policy's input):
    /// the tool's pose in the world.
    pub fn tool_pose(&self) -> Result<Isometry3<f64>, SimError> {
        let tool =
            self.rig.scene.tools.first().ok_or(SimError::MissingElement { kind: "tool", name: "tool".into() })?;
        Ok(tool.pose(&self.data))
    }

    /// The wrist command and joint targets now.
    pub fn command(&self) -> Result<(Isometry3<f64>, &[f64]), SimError> {
        let e = self.episode()?;
        Ok((e.command, &e.q))
    }

    /// Seconds into the episode.
    pub fn time_s(&self) -> f64 {
        let control_hz = self.setup.task.base().physics.control_hz;
        self.episode.as_ref().map_or(0.0, |e| e.steps as f64 / control_hz)
    }

    /// The episode's grasp plan, carried to the tool's start.
    pub fn plan(&self) -> Result<&GraspPlan, SimError> {
        Ok(&self.episode()?.plan)
    }

    /// The MuJoCo state (for checks and pictures).
    pub fn data(&self) -> &EnvData {
        &self.data
    }
}

/// The scripted controller of the env's task as a source of actions.
pub struct Expert {
    /// The episode it was made for.
    seed: u64,
    controller: ExpertController,
}

enum ExpertController {
    Place(PlaceController),
    Position(DrillController),
    Nail(NailController),
}

impl Expert {
    /// The expert for `env`'s episode under way (made after each reset).
    pub fn new(env: &TaskEnv) -> Result<Self, SimError> {
        let e = env.episode()?;
        let controller = match (&env.setup.task, &e.draw, &env.rig.nail) {
            (TaskSetup::Place(s), Draw::Pose(p), _) => {
                ExpertController::Place(PlaceController::new(&env.hand, &e.plan, p.goal, &s.script))
            }
            (TaskSetup::Position(s), Draw::Pose(p), _) => {
                ExpertController::Position(DrillController::new(&env.hand, &e.plan, p.goal, &s.script))
            }
            (TaskSetup::Nail(s), Draw::Nail(_), Some((nail, face))) => {
                ExpertController::Nail(NailController::new(&env.hand, &e.plan, *face, &s.script, nail.home_depth_m))
            }
            _ => return Err(SimError::Config { reason: "the environment's draw does not match its task".into() }),
        };
        Ok(Self { seed: e.seed, controller })
    }

    /// The action for the next control step of `env`, written into `out`
    /// (the action layout's length).
    pub fn act(&mut self, env: &TaskEnv, out: &mut [f32]) -> Result<(), SimError> {
        let len = env.action_layout().len();
        if out.len() != len {
            return Err(SimError::Config { reason: format!("action buffer of {} for a layout of {len}", out.len()) });
        }
        let (command, q_now) = env.command()?;
        let mut q = q_now.to_vec();
        let t = env.time_s() + 1.0 / env.setup.task.base().physics.control_hz;
        let pose = env.tool_pose()?;
        let target = match &mut self.controller {
            ExpertController::Place(c) => c.targets(t, &pose, &mut q),
            ExpertController::Position(c) => PoseController::targets(c, t, &pose, &mut q),
            ExpertController::Nail(c) => {
                let Some((nail, _)) = &env.rig.nail else {
                    return Err(SimError::Config { reason: "a Drive-nail environment without its nail".into() });
                };
                c.targets(t, &pose, &nail.head_top(&env.data), nail.depth(&env.data), &mut q)
            }
        };
        for (o, v) in out.iter_mut().zip(Action::between(&command, &target, &q).to_vec()) {
            *o = v;
        }
        Ok(())
    }
}

/// The most environments (and threads) one batch takes: each holds a
/// MuJoCo state of about 1 MB, and a request for millions is a mistake to
/// refuse, not memory to run out of.
pub const MAX_ENVS: usize = 4096;

/// N environments stepped in parallel (module docs).
pub struct VecTaskEnv {
    envs: Vec<TaskEnv>,
    planner: GraspPlanner,
    pool: rayon::ThreadPool,
    next_seed: u64,
    obs_len: usize,
    act_len: usize,
    observations: Vec<f32>,
    final_observations: Vec<f32>,
    rewards: Vec<f32>,
    successes: Vec<bool>,
    dones: Vec<bool>,
    finished: Vec<EpisodeSummary>,
}

impl VecTaskEnv {
    /// `n_envs` environments of `setup`'s task on `threads` threads,
    /// environment i on `instances[i % len]` (each tool's scene compiled
    /// once), all reset: environment i to seed `first_seed + i`; later
    /// episodes take the following seeds in the order they start.
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        asset: &HandAsset,
        mut planner: GraspPlanner,
        instances: &[Instance],
        setup: EnvSetup,
        n_envs: usize,
        threads: usize,
        first_seed: u64,
    ) -> Result<Self, SimError> {
        if n_envs == 0 || instances.is_empty() {
            return Err(SimError::Config { reason: "at least one environment and one tool are needed".into() });
        }
        if n_envs > MAX_ENVS || threads > MAX_ENVS {
            return Err(SimError::Config {
                reason: format!("{n_envs} environments on {threads} threads: at most {MAX_ENVS} of either"),
            });
        }
        setup.task.validate()?;
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads.max(1))
            .thread_name(|i| format!("sim-env-{i}"))
            .build()
            .map_err(|e| SimError::Config { reason: format!("cannot start {threads} threads: {e}") })?;
        let setup = Arc::new(setup);
        let mut rigs: Vec<(Arc<ToolRig>, Option<EnvData>)> = Vec::new();
        for instance in instances.iter().take(n_envs) {
            let (rig, data) = ToolRig::build(asset, &mut planner, instance, &setup.task)?;
            rigs.push((Arc::new(rig), Some(data)));
        }
        let mut envs = Vec::with_capacity(n_envs);
        for i in 0..n_envs {
            let (rig, data) = &mut rigs[i % instances.len()];
            let data = data.take().unwrap_or_else(|| MjData::new(rig.scene.model.clone()));
            envs.push(TaskEnv::on_rig(asset.model(), &planner, rig.clone(), data, setup.clone()));
        }
        let (obs_len, act_len) = (envs[0].obs_layout.len(), envs[0].action_layout().len());
        let mut v = Self {
            envs,
            planner,
            pool,
            next_seed: first_seed,
            obs_len,
            act_len,
            observations: vec![0.0; n_envs * obs_len],
            final_observations: vec![0.0; n_envs * obs_len],
            rewards: vec![0.0; n_envs],
            successes: vec![false; n_envs],
            dones: vec![false; n_envs],
            finished: Vec::new(),
        };
        v.reset_all(first_seed)?;
        Ok(v)
    }

    /// Starts every environment afresh: environment i with seed
    /// `first_seed + i`, later episodes with the seeds after those. Finished
    /// summaries not yet drained are kept.
    pub fn reset_all(&mut self, first_seed: u64) -> Result<(), SimError> {
        self.next_seed = first_seed;
        self.dones.fill(false);
        self.successes.fill(false);
        self.rewards.fill(0.0);
        for i in 0..self.envs.len() {
            self.reset_env(i)?;
        }
        Ok(())
    }

    fn reset_env(&mut self, i: usize) -> Result<(), SimError> {
        let seed = self.next_seed;
        self.next_seed = self.next_seed.wrapping_add(1);
        let env = &mut self.envs[i];
        env.reset(&mut self.planner, seed)?;
        env.observe_into(&mut self.observations[i * self.obs_len..(i + 1) * self.obs_len])
    }

    pub fn len(&self) -> usize {
        self.envs.len()
    }

    pub fn is_empty(&self) -> bool {
        self.envs.is_empty()
    }

    pub fn observation_layout(&self) -> ObservationLayout {
        self.envs[0].observation_layout()
    }

    pub fn action_layout(&self) -> ActionLayout {
        self.envs[0].action_layout()
    }

    /// One control step of every environment with `actions` (N rows of the
    /// action layout, row i for environment i). Every row is checked before
    /// anything is stepped: a bad one is an error naming its environment.
    /// Then [`Self::observations`], [`Self::rewards`], [`Self::successes`]
    /// and [`Self::dones`] hold the step's results; a finished environment
    /// has been reset (its row is the new episode's first observation, the
    /// last one of the finished episode is in [`Self::final_observations`],
    /// its summary in [`Self::drain_finished`]).
    pub fn step(&mut self, actions: &[f32]) -> Result<(), SimError> {
        let n = self.envs.len();
        if actions.len() != n * self.act_len {
            return Err(SimError::Config {
                reason: format!("{} action values for {n} environments of {} each", actions.len(), self.act_len),
            });
        }
        let parsed = actions
            .chunks_exact(self.act_len)
            .enumerate()
            .map(|(i, a)| {
                self.envs[i]
                    .parse_action(a)
                    .map_err(|e| SimError::Config { reason: format!("environment {i}'s action: {e}") })
            })
            .collect::<Result<Vec<_>, _>>()?;
        let obs_len = self.obs_len;
        let (envs, pool) = (&mut self.envs, &self.pool);
        let results: Vec<Result<StepResult, SimError>> = pool.install(|| {
            envs.par_iter_mut()
                .zip(parsed.par_iter())
                .zip(self.observations.par_chunks_mut(obs_len))
                .map(|((env, action), obs)| {
                    let r = env.step_parsed(action);
                    env.observe_into(obs)?;
                    Ok(r)
                })
                .collect()
        });
        for (i, r) in results.into_iter().enumerate() {
            let r = r?;
            self.rewards[i] = r.reward as f32;
            self.successes[i] = r.success;
            self.dones[i] = r.done;
        }
        for i in 0..n {
            if self.dones[i] {
                let row = i * obs_len..(i + 1) * obs_len;
                self.final_observations[row.clone()].copy_from_slice(&self.observations[row]);
                self.finished.push(self.envs[i].summary(i)?);
                self.reset_env(i)?;
            }
        }
        Ok(())
    }

    /// N observation rows (after the last step or reset).
    pub fn observations(&self) -> &[f32] {
        &self.observations
    }

    /// The last observation of each environment whose episode ended at the
    /// last step (rows of the others are stale).
    pub fn final_observations(&self) -> &[f32] {
        &self.final_observations
    }

    pub fn rewards(&self) -> &[f32] {
        &self.rewards
    }

    pub fn successes(&self) -> &[bool] {
        &self.successes
    }

    pub fn dones(&self) -> &[bool] {
        &self.dones
    }

    /// Summaries of the episodes finished since the last call.
    pub fn drain_finished(&mut self) -> Vec<EpisodeSummary> {
        std::mem::take(&mut self.finished)
    }

    pub fn env(&self, i: usize) -> Option<&TaskEnv> {
        self.envs.get(i)
    }

    /// Every environment's expert action for the next step, into `actions`
    /// (N rows), each from its expert in `experts` (one per environment;
    /// `None`, or one made for an episode that has ended, is made anew).
    pub fn expert_actions(&self, experts: &mut [Option<Expert>], actions: &mut [f32]) -> Result<(), SimError> {
        if experts.len() != self.envs.len() || actions.len() != self.envs.len() * self.act_len {
            return Err(SimError::Config { reason: "one expert and one action row per environment".into() });
        }
        for ((env, expert), out) in self.envs.iter().zip(experts.iter_mut()).zip(actions.chunks_exact_mut(self.act_len))
        {
            let seed = env.episode()?.seed;
            if expert.as_ref().is_none_or(|x| x.seed != seed) {
                *expert = Some(Expert::new(env)?);
            }
            if let Some(x) = expert.as_mut() {
                x.act(env, out)?;
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::place::place_instance;
    use graspd::tools::{self, Category};

    fn env_on(task: Task, name: &str) -> (HandAsset, GraspPlanner, TaskEnv) {
        let asset = HandAsset::default_sih().unwrap();
        let mut planner = GraspPlanner::new(asset.model(), task.category(), 0).unwrap();
        let instance = tools::instance(task.category(), name).unwrap();
        let env = TaskEnv::new(&asset, &mut planner, &instance, EnvSetup::new(task)).unwrap();
        (asset, planner, env)
    }

    /// Runs one episode with the expert's actions; (success at the end, return).
    fn expert_episode(env: &mut TaskEnv, planner: &mut GraspPlanner, seed: u64) -> (bool, f64, usize) {
        env.reset(planner, seed).unwrap();
        let mut expert = Expert::new(env).unwrap();
        let mut action = vec![0.0; env.action_layout().len()];
        let (mut sum, mut steps) = (0.0, 0);
        loop {
            expert.act(env, &mut action).unwrap();
            let r = env.step(&action).unwrap();
            sum += r.reward;
            steps += 1;
            if r.done {
                return (r.success, sum, steps);
            }
        }
    }

    /// The scripted controllers, fed through the action interface (wrist
    /// deltas clamped to the limits, joint targets), do what the scripted
    /// episodes do: the mug is placed, the drill positioned, the nail
    /// driven, each from the pre-grasp in 300 steps; the return counts the
    /// success reward; and the scripted Place episode of the same seed
    /// agrees.
    #[test]
    fn the_expert_through_actions_does_each_task() {
        for (task, name) in [
            (Task::PlaceMug, "mug_canonical"),
            (Task::PositionDrill, "drill_canonical"),
            (Task::DriveNail, "hammer_canonical"),
        ] {
            let (_, mut planner, mut env) = env_on(task, name);
            assert_eq!(env.steps_per_episode(), 300);
            for seed in [100, 101] {
                let (success, ret, steps) = expert_episode(&mut env, &mut planner, seed);
                assert_eq!(steps, 300);
                assert!(success, "{task:?} seed {seed}: return {ret:.1}");
                let summary = env.summary(0).unwrap();
                assert!(summary.success && (summary.episode_return - ret).abs() < 1e-6, "{summary:?}");
                if task != Task::DriveNail {
                    // 100 a step while the rule holds: at least a second of it.
                    assert!(ret > 100.0 * 30.0, "{task:?} seed {seed}: return {ret:.1}");
                }
            }
        }
        let asset = HandAsset::default_sih().unwrap();
        let mut planner = GraspPlanner::new(asset.model(), Category::Mug, 0).unwrap();
        let mug = tools::instance(Category::Mug, "mug_canonical").unwrap();
        let scripted = place_instance(&asset, &mut planner, &mug, &PlaceSetup::default(), 100, 2).unwrap();
        assert!(scripted.iter().all(|o| o.success));
    }

    /// Zero wrist deltas and the pre-grasp's joints: the hand hovers, the
    /// mug stays where it was drawn, nothing is placed, and the observation
    /// carries the episode's goal and the hand where it started.
    #[test]
    fn a_holding_policy_moves_nothing() {
        let (_, mut planner, mut env) = env_on(Task::PlaceMug, "mug_canonical");
        env.reset(&mut planner, 7).unwrap();
        let start = env.tool_pose().unwrap();
        let (wrist0, q0) = env.command().unwrap();
        let hold = Action::hold(q0).to_vec();
        let layout = env.observation_layout();
        let obs0 = env.observation().unwrap();
        let mut last = StepResult { reward: 0.0, success: true, done: false };
        while !last.done {
            last = env.step(&hold).unwrap();
            assert!(last.reward.is_finite());
        }
        assert!(!last.success);
        let moved = (env.tool_pose().unwrap().translation.vector - start.translation.vector).norm();
        assert!(moved < 0.005, "the mug moved {:.1} mm", moved * 1e3);
        let obs = env.observation().unwrap();
        let goal = layout.segment("goal_position").unwrap();
        assert_eq!(obs[goal.offset..goal.offset + 3], obs0[goal.offset..goal.offset + 3]);
        let wrist = layout.segment("wrist_position").unwrap();
        for k in 0..3 {
            assert!((obs[wrist.offset + k] as f64 - wrist0.translation.vector[k]).abs() < 0.01, "{obs:?}");
        }
        // The episode is over: another step is refused until a reset.
        assert!(env.step(&hold).is_err());
        env.reset(&mut planner, 8).unwrap();
        assert!(env.step(&hold).is_ok());
    }

    /// A policy's bad output is refused, naming it, and nothing is stepped.
    #[test]
    fn bad_actions_are_refused() {
        let (asset, mut planner, mut env) = env_on(Task::PlaceMug, "mug_canonical");
        let n = env.action_layout().len();
        assert!(env.step(&vec![0.0; n]).is_err(), "no episode yet");
        env.reset(&mut planner, 1).unwrap();
        let err = env.step(&vec![0.0; n - 1]).unwrap_err().to_string();
        assert!(err.contains("action of 10 values"), "{err}");
        let mut nan = vec![0.0; n];
        nan[4] = f32::NAN;
        let err = env.step(&nan).unwrap_err().to_string();
        assert!(err.contains("action value 4"), "{err}");
        assert_eq!(env.time_s(), 0.0);
        // Joint targets past the limits are clamped, not refused.
        let mut far = vec![0.0; n];
        far[6..].fill(100.0);
        assert!(env.step(&far).is_ok());
        let (_, q) = env.command().unwrap();
        for (q, [_, hi]) in q.iter().zip(asset.model().actuated_limits()) {
            assert_eq!(q, hi);
        }
        // The wrong tool for the task is refused.
        let drill = tools::instance(Category::Drill, "drill_canonical").unwrap();
        let err = TaskEnv::new(&asset, &mut planner, &drill, EnvSetup::new(Task::PlaceMug)).err().unwrap().to_string();
        assert!(err.contains("place takes a mug"), "{err}");
    }

    /// Same seeds, same episodes: two batches, one on one thread and one on
    /// two, driven by the expert for a second, agree bit for bit.
    #[test]
    fn batches_are_deterministic_whatever_the_threads() {
        let asset = HandAsset::default_sih().unwrap();
        let mugs = [tools::instance(Category::Mug, "mug_train_03").unwrap()];
        let run = |threads: usize| {
            let planner = GraspPlanner::new(asset.model(), Category::Mug, 0).unwrap();
            let mut envs =
                VecTaskEnv::new(&asset, planner, &mugs, EnvSetup::new(Task::PlaceMug), 3, threads, 40).unwrap();
            let mut experts: Vec<Option<Expert>> = (0..3).map(|_| None).collect();
            let mut actions = vec![0.0; 3 * envs.action_layout().len()];
            let mut rewards = Vec::new();
            for _ in 0..30 {
                envs.expert_actions(&mut experts, &mut actions).unwrap();
                envs.step(&actions).unwrap();
                rewards.extend_from_slice(envs.rewards());
            }
            (envs.observations().to_vec(), rewards)
        };
        let (one, two) = (run(1), run(2));
        assert!(one.0.iter().zip(&two.0).all(|(a, b)| a.to_bits() == b.to_bits()));
        assert_eq!(one.1, two.1);
        // The three episodes differ (seeds 40, 41, 42).
        let o = one.0.len() / 3;
        assert_ne!(one.0[..o], one.0[o..2 * o]);
    }

    /// A batch on two tools: every environment ends its episode at step
    /// 300 and is reset with the next seed at once; the finished episodes'
    /// summaries name their tools and seeds; a bad row is refused naming
    /// its environment before anything is stepped.
    #[test]
    fn the_batch_steps_resets_and_refuses_bad_rows() {
        let asset = HandAsset::default_sih().unwrap();
        let planner = GraspPlanner::new(asset.model(), Category::Mug, 0).unwrap();
        let mugs: Vec<Instance> =
            ["mug_canonical", "mug_train_00"].iter().map(|n| tools::instance(Category::Mug, n).unwrap()).collect();
        let mut envs = VecTaskEnv::new(&asset, planner, &mugs, EnvSetup::new(Task::PlaceMug), 3, 2, 10).unwrap();
        let (n, a, o) = (envs.len(), envs.action_layout().len(), envs.observation_layout().len());
        assert_eq!(envs.observations().len(), n * o);
        let mut actions = vec![0.0f32; n * a];
        for i in 0..n {
            let (_, q) = envs.env(i).unwrap().command().unwrap();
            actions[i * a + 6..(i + 1) * a].copy_from_slice(&q.iter().map(|&x| x as f32).collect::<Vec<_>>());
        }
        let mut bad = actions.clone();
        bad[a + 2] = f32::INFINITY;
        let err = envs.step(&bad).unwrap_err().to_string();
        assert!(err.contains("environment 1"), "{err}");
        assert!(envs.step(&actions[..a]).is_err());
        let huge = VecTaskEnv::new(
            &asset,
            GraspPlanner::new(asset.model(), Category::Mug, 0).unwrap(),
            &mugs,
            EnvSetup::new(Task::PlaceMug),
            1 << 40,
            2,
            0,
        );
        assert!(huge.err().is_some_and(|e| e.to_string().contains("at most 4096")));
        assert_eq!(envs.env(0).unwrap().time_s(), 0.0);
        let first_goals: Vec<f32> = (0..n).map(|i| envs.observations()[i * o + o - 7]).collect();
        for k in 0..300 {
            envs.step(&actions).unwrap();
            assert!(envs.rewards().iter().all(|r| r.is_finite()));
            assert_eq!(envs.dones().iter().all(|&d| d), k == 299, "step {k}");
        }
        let done = envs.drain_finished();
        let seeds: Vec<(u64, &str)> = done.iter().map(|s| (s.seed, s.instance.as_str())).collect();
        assert_eq!(seeds, [(10, "mug_canonical"), (11, "mug_train_00"), (12, "mug_canonical")]);
        assert!(done.iter().all(|s| !s.success && s.steps == 300));
        // Reset with seeds 13-15: new goals, and the clock back at zero.
        assert!(envs.env(0).unwrap().time_s() == 0.0 && envs.env(0).unwrap().summary(0).unwrap().seed == 13);
        let goals: Vec<f32> = (0..n).map(|i| envs.observations()[i * o + o - 7]).collect();
        assert_ne!(goals, first_goals);
        let last: Vec<f32> = (0..n).map(|i| envs.final_observations()[i * o + o - 7]).collect();
        assert_eq!(last, first_goals);
    }
}
