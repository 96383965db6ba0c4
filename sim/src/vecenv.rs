//! Vectorised environments: N copies of one scene, each with its own
//! `MjData` on the shared model, stepped in parallel on a rayon pool (one
//! environment is one task; MuJoCo's step is single-threaded and allocation
//! free, so the environments scale with the cores).
//!
//! Its user is `sim bench`, the physics' throughput alone: an environment
//! runs the scripted lift ([`ActionStream::Scripted`]) or holds its first
//! targets ([`ActionStream::Hold`], the "zero action": no change of wrist
//! pose or joint targets), and restarts at the pre-grasp when the script
//! ends. The tasks stepped by a policy's actions, with observations and
//! rewards, are [`crate::env`].

use std::sync::Arc;
use std::time::Instant;

use graspd::hand::HandModel;
use mujoco_rs::prelude::{MjData, MjModel};
use nalgebra::Isometry3;
use rayon::prelude::*;

use crate::engine::SimError;
use crate::episode::{reset_to_pregrasp, substeps, LiftController, LiftScript};
use crate::plan::GraspPlan;
use crate::scene::Scene;

/// What drives the environments.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ActionStream {
    /// The scripted lift: approach, close, lift, hold (contact-rich).
    Scripted,
    /// The pre-grasp's targets held still (no contact with the tool).
    Hold,
}

struct Env {
    data: MjData<Arc<MjModel>>,
    /// Control steps into the current episode.
    step: usize,
    episodes: usize,
    q: Vec<f64>,
    physics_s: f64,
}

/// N lift environments of one scene.
pub struct VecLift {
    scene: Scene,
    hand: HandModel,
    plan: GraspPlan,
    tool_pose: Isometry3<f64>,
    controller: LiftController,
    actions: ActionStream,
    control_hz: f64,
    substeps: usize,
    steps_per_episode: usize,
    envs: Vec<Env>,
    pool: rayon::ThreadPool,
}

impl VecLift {
    /// `n_envs` environments on `threads` worker threads. Environment i
    /// starts i/n of the way into its episode (stepped there before this
    /// returns), so that at any moment the batch mixes all phases, as
    /// independent episodes of a trainer do.
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        scene: Scene,
        hand: &HandModel,
        plan: GraspPlan,
        tool_pose: Isometry3<f64>,
        script: &LiftScript,
        actions: ActionStream,
        control_hz: f64,
        n_envs: usize,
        threads: usize,
    ) -> Result<Self, SimError> {
        if n_envs == 0 {
            return Err(SimError::Config { reason: "at least one environment is needed".into() });
        }
        if n_envs > crate::env::MAX_ENVS || threads > crate::env::MAX_ENVS {
            return Err(SimError::Config {
                reason: format!(
                    "{n_envs} environments on {threads} threads: at most {} of either",
                    crate::env::MAX_ENVS
                ),
            });
        }
        if !(control_hz.is_finite() && control_hz > 0.0) {
            return Err(SimError::Config { reason: format!("control rate {control_hz} Hz is not positive") });
        }
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads.max(1))
            .thread_name(|i| format!("sim-env-{i}"))
            .build()
            .map_err(|e| SimError::Config { reason: format!("cannot start {threads} threads: {e}") })?;
        let controller = LiftController::new(hand, &plan, script);
        let steps_per_episode = ((controller.duration() * control_hz).round() as usize).max(1);
        let mut envs = Vec::with_capacity(n_envs);
        for _ in 0..n_envs {
            let mut data = MjData::new(scene.model.clone());
            reset_to_pregrasp(&scene, &mut data, hand, &plan, &tool_pose)?;
            envs.push(Env { data, step: 0, episodes: 0, q: plan.pregrasp.actuated.clone(), physics_s: 0.0 });
        }
        let mut v = Self {
            substeps: substeps(&scene, control_hz),
            scene,
            hand: hand.clone(),
            plan,
            tool_pose,
            controller,
            actions,
            control_hz,
            steps_per_episode,
            envs,
            pool,
        };
        let n = v.envs.len();
        for i in 0..n {
            for _ in 0..i * steps_per_episode / n {
                v.step_env(i);
            }
        }
        for e in &mut v.envs {
            e.physics_s = 0.0;
            e.episodes = 0;
        }
        Ok(v)
    }

    pub fn len(&self) -> usize {
        self.envs.len()
    }
    pub fn is_empty(&self) -> bool {
        self.envs.is_empty()
    }

    /// One control step of every environment, in parallel.
    pub fn step(&mut self) {
        let (ctx, envs, pool) = self.split();
        pool.install(|| envs.par_iter_mut().for_each(|e| ctx.step(e)));
    }

    fn step_env(&mut self, i: usize) {
        let (ctx, envs, _) = self.split();
        ctx.step(&mut envs[i]);
    }

    /// What every environment's step reads, beside the environments it writes.
    fn split(&mut self) -> (StepContext<'_>, &mut Vec<Env>, &rayon::ThreadPool) {
        let ctx = StepContext {
            scene: &self.scene,
            hand: &self.hand,
            plan: &self.plan,
            tool_pose: &self.tool_pose,
            controller: &self.controller,
            actions: self.actions,
            control_hz: self.control_hz,
            substeps: self.substeps,
            steps_per_episode: self.steps_per_episode,
        };
        (ctx, &mut self.envs, &self.pool)
    }

    pub fn substeps(&self) -> usize {
        self.substeps
    }

    /// The scene the environments simulate.
    pub fn scene(&self) -> &Scene {
        &self.scene
    }

    /// One environment's MuJoCo state (for observations and checks).
    pub fn data(&self, i: usize) -> Option<&MjData<Arc<MjModel>>> {
        self.envs.get(i).map(|e| &e.data)
    }

    /// Physics time and episodes since construction (or the last [`Self::reset_stats`]).
    pub fn physics_stats(&self) -> (f64, u64) {
        (self.envs.iter().map(|e| e.physics_s).sum(), self.envs.iter().map(|e| e.episodes as u64).sum())
    }

    pub fn reset_stats(&mut self) {
        for e in &mut self.envs {
            e.physics_s = 0.0;
            e.episodes = 0;
        }
    }
}

/// What one environment's step reads, shared by the pool's tasks.
struct StepContext<'a> {
    scene: &'a Scene,
    hand: &'a HandModel,
    plan: &'a GraspPlan,
    tool_pose: &'a Isometry3<f64>,
    controller: &'a LiftController,
    actions: ActionStream,
    control_hz: f64,
    substeps: usize,
    steps_per_episode: usize,
}

impl StepContext<'_> {
    fn step(&self, e: &mut Env) {
        let Some(hand) = &self.scene.hand else { return };
        if self.actions == ActionStream::Scripted {
            let t = (e.step + 1) as f64 / self.control_hz;
            let wrist = self.controller.targets(t, &mut e.q);
            hand.set_wrist_target(&mut e.data, &wrist);
            hand.set_joint_targets(&mut e.data, &e.q);
        }
        let t0 = Instant::now();
        for _ in 0..self.substeps {
            e.data.step();
        }
        e.physics_s += t0.elapsed().as_secs_f64();
        e.step += 1;
        if e.step >= self.steps_per_episode {
            // The scene was built by this crate, so the reset cannot miss its parts.
            let _ = reset_to_pregrasp(self.scene, &mut e.data, self.hand, self.plan, self.tool_pose);
            e.step = 0;
            e.episodes += 1;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::episode::{run_lift, LiftSetup};
    use crate::hand::HandAsset;
    use crate::plan::GraspPlanner;
    use crate::scene::{SceneSpec, Table};
    use crate::tool::{ToolBody, ToolMaterial};
    use graspd::tools::{self, Category};

    /// Environments stepped in parallel follow exactly the trajectory of the
    /// same episode run alone (MuJoCo is deterministic; environments share
    /// the model and nothing else).
    #[test]
    fn parallel_environments_match_a_lone_episode() {
        let asset = HandAsset::default_sih().unwrap();
        let hand = asset.model();
        let mug = tools::instance(Category::Mug, "mug_canonical").unwrap();
        let plan = GraspPlanner::new(hand, Category::Mug, 0).unwrap().plan(&mug).unwrap();
        let setup = LiftSetup::default();
        let tool =
            ToolBody::from_mesh("mug", &mug.mesh, ToolMaterial::for_category(Category::Mug), &setup.decomposition)
                .unwrap();
        let spec = SceneSpec {
            name: "vec".into(),
            physics: setup.physics.clone(),
            table: Some(Table::default()),
            tools: vec![(&tool, Isometry3::identity())],
            hand: Some((&asset, setup.hand.clone(), plan.pregrasp.wrist_pose_world)),
            ..Default::default()
        };
        let lone_scene = spec.build().unwrap();
        let mut lone = MjData::new(lone_scene.model.clone());
        let out = run_lift(&lone_scene, &mut lone, hand, &plan, &Isometry3::identity(), &setup.script, 30.0).unwrap();
        assert!(out.held);
        // The same episode by hand, one control step short of its end (where
        // a vectorised environment restarts).
        let steps = out.control_steps - 1;
        reset_to_pregrasp(&lone_scene, &mut lone, hand, &plan, &Isometry3::identity()).unwrap();
        let controller = LiftController::new(hand, &plan, &setup.script);
        let lone_hand = lone_scene.hand.as_ref().unwrap();
        let mut q = plan.pregrasp.actuated.clone();
        for k in 0..steps {
            let wrist = controller.targets((k + 1) as f64 / 30.0, &mut q);
            lone_hand.set_wrist_target(&mut lone, &wrist);
            lone_hand.set_joint_targets(&mut lone, &q);
            for _ in 0..setup.physics.substeps {
                lone.step();
            }
        }

        let mut v = VecLift::new(
            spec.build().unwrap(),
            hand,
            plan,
            Isometry3::identity(),
            &setup.script,
            ActionStream::Scripted,
            30.0,
            4,
            2,
        )
        .unwrap();
        // Environment 0 starts at the episode's beginning (the others are
        // mid-episode and wrap around meanwhile).
        for _ in 0..steps {
            v.step();
        }
        let tool_body = v.scene().tools[0].body;
        let (a, b) = (v.data(0).unwrap().xpos()[tool_body], lone.xpos()[tool_body]);
        assert_eq!(a, b, "parallel environment 0 diverged from the lone episode");
        // And it is holding the mug, 9 cm up (not a trivially equal rest state).
        assert!(a[2] > 0.05, "tool at {a:?}");
        assert!(v.data(3).unwrap().time() > 0.0);
    }
}
