//! What the scripted task episodes (Place mug, Position drill, Drive nail)
//! share, so that each task's module holds only its own path and rules:
//!
//! - [`TaskRig`]: a tool's scene (built once, episodes reset it), its
//!   in-process grasp plan (made once; a daemon's grasps are asked for per
//!   episode, from the camera's view of the tool where it starts: see
//!   [`TaskRig::episode_plan`]) and the points sampled on its mesh for the
//!   lift term;
//! - [`CarryController`]: the lift script, then a wrist command that moves
//!   the *held tool* along a desired tool pose. The command is the desired
//!   tool motion (since the lift ended) applied to the lifted wrist command,
//!   corrected every step by a share of the tool's remaining pose error: an
//!   integral action, because the weld between the mocap target and the
//!   palm sags under the tool's weight, and the tool may have turned in the
//!   hand while lifting (a hammer swings round its handle). The correction
//!   is capped so that a dropped tool does not send the hand chasing it;
//! - [`EpisodeStepper`]: one control step (targets, physics substeps timed)
//!   and the state every task's grasp terms read (hand and demonstration
//!   keypoints, the tool's clearance above the table).

use std::sync::Arc;
use std::time::Instant;

use graspd::geometry::sample::sample_points;
use graspd::hand::HandModel;
use graspd::tools::Instance;
use mujoco_rs::prelude::{MjData, MjModel};
use mujoco_rs::wrappers::mj_model::traits::ModelType;
use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion};

use crate::engine::SimError;
use crate::episode::{reset_to_pregrasp, squeezed, substeps, LiftController, LiftScript, LiftSetup};
use crate::hand::{HandAsset, HandIndex};
use crate::plan::{neutral_wrist, GraspFrom, GraspInfo, GraspPlan, GraspPlanner};
use crate::scene::{Scene, SceneSpec, Table, ToolIndex};
use crate::task::GraspState;
use crate::tool::ToolBody;

/// Points sampled on the tool's mesh for its height (the lift term), and their seed.
pub const HEIGHT_POINTS: usize = 512;
pub const HEIGHT_POINTS_SEED: u64 = 7;

/// The integral correction of a carried tool's pose.
#[derive(Clone, Debug, PartialEq)]
pub struct Steering {
    /// Share of the tool's remaining pose error added to the wrist command each control step.
    pub gain: f64,
    /// Largest total correction of the wrist command (metres, radians).
    pub max_correction_m: f64,
    pub max_correction_rad: f64,
}

impl Default for Steering {
    fn default() -> Self {
        Self { gain: 0.15, max_correction_m: 0.05, max_correction_rad: 0.5 }
    }
}

/// The lift script followed by steering of the held tool (module docs).
/// Stateful: it remembers where the tool was when the lift ended and the
/// correction it has built up; [`Self::reset`] between episodes.
#[derive(Clone, Debug)]
pub struct CarryController {
    lift: LiftController,
    lifted_wrist: Isometry3<f64>,
    q_squeeze: Vec<f64>,
    steering: Steering,
    tool_at_lift: Option<Isometry3<f64>>,
    correction: Isometry3<f64>,
    last_wrist: Option<Isometry3<f64>>,
}

impl CarryController {
    pub fn new(hand: &HandModel, plan: &GraspPlan, script: &LiftScript, steering: &Steering) -> Self {
        let lift = LiftController::new(hand, plan, script);
        Self {
            lifted_wrist: lift.lifted_wrist(),
            lift,
            q_squeeze: squeezed(hand, &plan.grasp, script.squeeze_rad),
            steering: steering.clone(),
            tool_at_lift: None,
            correction: Isometry3::identity(),
            last_wrist: None,
        }
    }

    pub fn reset(&mut self) {
        self.tool_at_lift = None;
        self.correction = Isometry3::identity();
        self.last_wrist = None;
    }

    /// End of the lift script (approach, close, settle, lift, hold), seconds.
    pub fn lift_duration(&self) -> f64 {
        self.lift.duration()
    }

    /// The lift script's targets at `t` (before [`Self::lift_duration`]).
    pub fn lift_targets(&self, t: f64, q: &mut [f64]) -> Isometry3<f64> {
        self.lift.targets(t, q)
    }

    /// The joint targets that hold the tool (the grasp plus the squeeze).
    pub fn q_squeeze(&self) -> &[f64] {
        &self.q_squeeze
    }

    /// The tool's pose when the carry began: `tool_pose` the first time this
    /// is called (the first control step after the lift), then that one.
    pub fn carry_start(&mut self, tool_pose: &Isometry3<f64>) -> Isometry3<f64> {
        *self.tool_at_lift.get_or_insert(*tool_pose)
    }

    /// The wrist command that carries the tool, now at `tool_pose`, toward
    /// `desired`; the joint targets (into `q`) hold it.
    pub fn steer(&mut self, desired: &Isometry3<f64>, tool_pose: &Isometry3<f64>, q: &mut [f64]) -> Isometry3<f64> {
        let from = self.carry_start(tool_pose);
        q.copy_from_slice(&self.q_squeeze);
        self.correct(desired, tool_pose);
        let wrist = self.correction * desired * from.inverse() * self.lifted_wrist;
        self.last_wrist = Some(wrist);
        wrist
    }

    /// The wrist command for `desired` with the correction as it stands (not
    /// updated: the tool's error during an impact is not the grip's drift).
    pub fn command(&mut self, desired: &Isometry3<f64>, q: &mut [f64]) -> Isometry3<f64> {
        let from = self.tool_at_lift.unwrap_or(*desired);
        q.copy_from_slice(&self.q_squeeze);
        let wrist = self.correction * desired * from.inverse() * self.lifted_wrist;
        self.last_wrist = Some(wrist);
        wrist
    }

    /// The last wrist command of [`Self::steer`] or [`Self::command`] (the lifted wrist before any).
    pub fn last_wrist(&self) -> Isometry3<f64> {
        self.last_wrist.unwrap_or(self.lifted_wrist)
    }

    /// Adds a share of the tool's pose error to the correction, turning about
    /// the tool's own position (so a turn does not also shift it), capped.
    fn correct(&mut self, desired: &Isometry3<f64>, actual: &Isometry3<f64>) {
        let k = self.steering.gain;
        let c = actual.translation.vector;
        let rot = UnitQuaternion::identity().slerp(&(desired.rotation * actual.rotation.inverse()), k);
        let shift = k * (desired.translation.vector - c);
        let step = Translation3::from(c + shift) * rot * Translation3::from(-c);
        let next = step * self.correction;
        if next.translation.vector.norm() <= self.steering.max_correction_m
            && next.rotation.angle() <= self.steering.max_correction_rad
        {
            self.correction = next;
        }
    }
}

/// The lowest of `points` (tool frame) above `table_z` with the tool at `pose`.
pub fn clearance(points: &[Point3<f64>], pose: &Isometry3<f64>, table_z: f64) -> f64 {
    points.iter().map(|p| (pose * p).z).fold(f64::INFINITY, f64::min) - table_z
}

/// One tool's scene and in-process plan, ready for episodes.
pub struct TaskRig {
    /// The in-process plan with the tool frame at the world origin (carried
    /// to each episode's start); `None` when grasps come from the daemon.
    pub plan: Option<GraspPlan>,
    pub instance: Instance,
    pub scene: Scene,
    pub data: MjData<Arc<MjModel>>,
    /// Points on the tool's mesh, tool frame (the lift term's height).
    pub height_points: Vec<Point3<f64>>,
    pub table: Table,
}

impl TaskRig {
    /// Plans the grasp of `instance` (in-process planners), builds its body
    /// and a scene named `{task}_{instance}` with the table, the tool, the
    /// hand (at the pre-grasp, or at the neutral pose when grasps come from
    /// the daemon; every episode resets it) and `extra_bodies` (MJCF
    /// worldbody elements, e.g. a board) with `extra_contact` (contact pairs
    /// and exclusions).
    pub fn build(
        asset: &HandAsset,
        planner: &mut GraspPlanner,
        instance: &Instance,
        base: &LiftSetup,
        task: &str,
        extra_bodies: Vec<String>,
        extra_contact: Vec<String>,
    ) -> Result<Self, SimError> {
        let plan = match planner.grasp_from() {
            GraspFrom::InProcess => Some(planner.plan(instance)?),
            GraspFrom::Daemon | GraspFrom::Register => None,
        };
        let tool = ToolBody::from_instance(instance, &base.decomposition)?;
        let height_points = sample_points(&instance.mesh, HEIGHT_POINTS, HEIGHT_POINTS_SEED)
            .map_err(|e| SimError::Tool { reason: format!("sampling the tool's surface: {e}") })?;
        let table = Table::default();
        let spec = SceneSpec {
            name: format!("{task}_{}", instance.name),
            physics: base.physics.clone(),
            table: Some(table.clone()),
            tools: vec![(&tool, Isometry3::identity())],
            hand: Some((
                asset,
                base.hand.clone(),
                plan.as_ref().map_or_else(|| neutral_wrist(table.top_z), |p| p.pregrasp.wrist_pose_world),
            )),
            extra_bodies,
            extra_contact,
        };
        let scene = spec.build()?;
        let data = MjData::new(scene.model.clone());
        Ok(Self { plan, instance: instance.clone(), scene, data, height_points, table })
    }

    /// The plan of an episode whose tool starts at `tool_start` (the tool
    /// frame at the world origin, as [`Self::plan`]): the in-process plan,
    /// or the daemon's grasp of the camera's view (seeded by `seed`), with
    /// the planner's start mode applied; and how it was obtained.
    pub fn episode_plan(
        &self,
        planner: &mut GraspPlanner,
        tool_start: &Isometry3<f64>,
        seed: u64,
    ) -> Result<(GraspPlan, GraspInfo), SimError> {
        planner.episode_plan(&self.instance, self.plan.as_ref(), tool_start, self.table.top_z, seed)
    }

    /// Runs the seeded episodes `first_seed`, `first_seed + 1`, ... on this
    /// rig: each is drawn by `draw(seed, table top z)`, gets the plan for the
    /// tool's start (`start_of`) and is run by `run`; the plan's info goes
    /// with each outcome. One loop for every task, so that all seed alike.
    pub fn run_seeded<E, O>(
        &mut self,
        planner: &mut GraspPlanner,
        first_seed: u64,
        episodes: usize,
        draw: impl Fn(u64, f64) -> E,
        start_of: impl Fn(&E) -> Isometry3<f64>,
        mut run: impl FnMut(&mut Self, &GraspPlan, &E) -> Result<O, SimError>,
    ) -> Result<Vec<(O, GraspInfo)>, SimError> {
        let mut out = Vec::with_capacity(episodes);
        for e in 0..episodes as u64 {
            let seed = first_seed.wrapping_add(e);
            let episode = draw(seed, self.table.top_z);
            let (plan, info) = self.episode_plan(planner, &start_of(&episode), seed)?;
            out.push((run(self, &plan, &episode)?, info));
        }
        Ok(out)
    }
}

/// The per-step machinery of a scripted task episode (module docs).
pub struct EpisodeStepper<'a> {
    pub hand: &'a HandIndex,
    pub tool: &'a ToolIndex,
    substeps: usize,
    physics_s: f64,
    physics_steps: usize,
    /// The demonstration's keypoints in the tool frame: they ride with the tool.
    demo_tool: Vec<Point3<f64>>,
    demo_world: Vec<Point3<f64>>,
    hand_keypoints: Vec<Point3<f64>>,
    /// GRASPD_SIM_TRACE set (and not 0): diagnostics on stderr.
    pub trace: bool,
}

impl<'a> EpisodeStepper<'a> {
    /// Resets `data` to the episode's start: the tool at `tool_start`, the
    /// hand at the start of `plan` (already carried to `tool_start`).
    pub fn start<M: ModelType>(
        scene: &'a Scene,
        data: &mut MjData<M>,
        hand_model: &HandModel,
        plan: &GraspPlan,
        tool_start: &Isometry3<f64>,
        control_hz: f64,
    ) -> Result<Self, SimError> {
        reset_to_pregrasp(scene, data, hand_model, plan, tool_start)?;
        // A no-op unless this thread records an episode for pictures (crate::render::record).
        crate::render::record_start(scene, data);
        let hand = scene.hand.as_ref().ok_or(SimError::MissingElement { kind: "hand", name: "hand".into() })?;
        let tool = scene.tools.first().ok_or(SimError::MissingElement { kind: "tool", name: "tool".into() })?;
        let tool_from_world = tool_start.inverse();
        let demo_tool: Vec<Point3<f64>> = plan.demo_keypoints.iter().map(|p| tool_from_world * p).collect();
        Ok(Self {
            hand,
            tool,
            substeps: substeps(scene, control_hz),
            physics_s: 0.0,
            physics_steps: 0,
            demo_world: demo_tool.clone(),
            demo_tool,
            hand_keypoints: Vec::new(),
            trace: std::env::var_os("GRASPD_SIM_TRACE").is_some_and(|v| v != "0"),
        })
    }

    /// Commands the wrist and the joints and steps the physics through one control interval.
    pub fn step<M: ModelType>(&mut self, data: &mut MjData<M>, wrist: &Isometry3<f64>, q: &[f64]) {
        self.hand.set_wrist_target(data, wrist);
        self.hand.set_joint_targets(data, q);
        let t0 = Instant::now();
        for _ in 0..self.substeps {
            data.step();
        }
        self.physics_s += t0.elapsed().as_secs_f64();
        self.physics_steps += self.substeps;
        crate::render::record_step(data);
    }

    /// The grasp terms' inputs now, the tool at `tool_pose`.
    pub fn grasp_state<M: ModelType>(
        &mut self,
        data: &MjData<M>,
        tool_pose: &Isometry3<f64>,
        height_points: &[Point3<f64>],
        table_z: f64,
    ) -> GraspState<'_> {
        for (w, p) in self.demo_world.iter_mut().zip(&self.demo_tool) {
            *w = tool_pose * p;
        }
        self.hand_keypoints = self.hand.keypoints(data);
        GraspState {
            hand_keypoints: &self.hand_keypoints,
            demo_keypoints: &self.demo_world,
            clearance_m: clearance(height_points, tool_pose, table_z),
        }
    }

    /// Wall time of the physics steps so far, microseconds per step.
    pub fn physics_us_per_step(&self) -> f64 {
        1e6 * self.physics_s / self.physics_steps.max(1) as f64
    }
}
