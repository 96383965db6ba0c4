//! Grasps and pre-grasps for simulated tools, from graspd's engine in-process
//! (the daemon client comes later; the numbers are the same library's):
//!
//! - the canonical tool: the demonstrated grasp itself (the demonstration
//!   was authored on it), its pre-grasp checked against the canonical mesh;
//! - a training tool: the demonstration transferred through the tool's
//!   latent in the category's shape space (its registered shape at the
//!   canonical pose), solved and backed off, exactly as `graspd eval grasp`
//!   (paper Table I) does.
//!
//! Both are computed with the tool at its canonical pose on a table at z = 0
//! and carried to the tool's pose in the scene (a rigid motion moves the
//! grasp with the tool).

use std::path::{Path, PathBuf};

use graspd::grasp::transfer::{solve_transferred, TransferredTool};
use graspd::grasp::{pregrasp, Demonstration, Grasp, GraspSolver, PreGraspOptions, Scene, SolveOptions, ToolCollider};
use graspd::hand::HandModel;
use graspd::shape::{builtin, ShapeSpace};
use graspd::tools::{Category, Instance, Split};
use nalgebra::{Isometry3, Point3};

use crate::engine::SimError;

/// Where graspd's CLI caches the built-in shape spaces (`assets/spaces`).
pub fn spaces_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../assets/spaces")
}

/// A grasp to execute and the pose the episode starts from.
#[derive(Clone, Debug)]
pub struct GraspPlan {
    pub grasp: Grasp,
    pub pregrasp: Grasp,
    /// graspd's check: no hand sphere pierces the tool or the table at the pre-grasp.
    pub pregrasp_collision_free: bool,
    /// "demonstration" (canonical tool) or "transferred" (through the shape space).
    pub source: &'static str,
    /// Paper Table I metric of the solved grasp (0 for the demonstration itself).
    pub task_space_distance_cm: f64,
    /// The generalised demonstration: the 12 keypoint targets the grasp was
    /// solved for (the demonstration's own on the canonical tool), world
    /// frame, hand keypoint order. The keypoint reward and the observations use them.
    pub demo_keypoints: Vec<Point3<f64>>,
    /// The tool's latent in the category's shape space (zeros: the canonical tool).
    pub latent: Vec<f64>,
}

impl GraspPlan {
    /// The plan with the tool moved rigidly to `tool_pose` (the plan was made
    /// with the tool frame at the world origin).
    pub fn carried(&self, hand: &HandModel, tool_pose: &Isometry3<f64>) -> Self {
        let carry = |g: &Grasp| Grasp::new(hand, tool_pose * g.wrist_pose_world, g.actuated.clone());
        Self {
            grasp: carry(&self.grasp),
            pregrasp: carry(&self.pregrasp),
            demo_keypoints: self.demo_keypoints.iter().map(|p| tool_pose * p).collect(),
            ..self.clone()
        }
    }
}

/// Plans grasps for a category's instances (one shape space, one demonstration).
pub struct GraspPlanner {
    hand: HandModel,
    demo: Demonstration,
    space: ShapeSpace,
    solver: GraspSolver,
    pregrasp: PreGraspOptions,
}

fn engine_error(e: impl std::fmt::Display) -> SimError {
    SimError::Plan { reason: e.to_string() }
}

impl GraspPlanner {
    /// Loads the category's bundled demonstration and its shape space (built
    /// and cached under `assets/spaces` when missing, as the CLI does).
    pub fn new(hand: &HandModel, category: Category, seed: u64) -> Result<Self, SimError> {
        let demo = Demonstration::builtin(category).map_err(engine_error)?;
        let space = builtin::load_or_build(category, &spaces_dir(), |_, _| {}).map_err(engine_error)?;
        let solver = GraspSolver::new(hand, SolveOptions { seed, ..SolveOptions::default() });
        Ok(Self { hand: hand.clone(), demo, space, solver, pregrasp: PreGraspOptions::default() })
    }

    /// The plan for `instance`, the tool frame at the world origin, the table top at z = 0.
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
            });
        }
        let k = self.space.instances.iter().position(|n| n == &instance.name).ok_or_else(|| SimError::Plan {
            reason: format!(
                "`{}` is not a training instance of the {} shape space",
                instance.name, self.space.category
            ),
        })?;
        let canonical = graspd::tools::family(instance.category)
            .map_err(engine_error)?
            .into_iter()
            .find(|i| i.split == Split::Canonical)
            .ok_or_else(|| SimError::Plan { reason: "the family has no canonical instance".into() })?;
        let keypoints = self.demo.keypoints(hand).map_err(engine_error)?;
        let tool = TransferredTool::from_latent(&self.space, &self.space.train_latents[k], &keypoints, &canonical.mesh)
            .map_err(engine_error)?;
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
            latent: self.space.train_latents[k].clone(),
        })
    }

    pub fn hand(&self) -> &HandModel {
        &self.hand
    }

    /// Dimension of the category's latent (shape-space modes).
    pub fn latent_dim(&self) -> usize {
        self.space.modes.len()
    }
}
