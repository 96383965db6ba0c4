//! Grasp in task space (paper §III-C, eq. 6): find the wrist pose and the
//! actuated joints whose keypoints best match the transferred demonstration
//! keypoints, without piercing the registered tool or the table; the paper's
//! CG and WP baselines; the pre-grasp RL episodes start from.
//!
//! ```no_run
//! use graspd::grasp::{Grasp, GraspSolver, GraspTargets, Scene, SolveOptions};
//! use graspd::hand::HandModel;
//! # fn targets() -> Vec<nalgebra::Point3<f64>> { vec![] }
//! let hand = HandModel::default_sih().unwrap();
//! let mut solver = GraspSolver::new(&hand, SolveOptions::default());
//! let targets = GraspTargets::uniform(targets());
//! let warm = solver.cold_start(&targets).unwrap(); // or the canonical grasp moved by the registered pose
//! let (grasp, report) = solver.solve(&targets, &warm, &Scene::default()).unwrap();
//! ```
//!
//! Units: metres and radians everywhere; reports give millimetres (and the
//! paper's task-space distance centimetres) where the field name says so.

pub mod baselines;
pub mod demo;
pub mod linalg;
pub mod penetration;
pub mod pregrasp;
pub mod solver;
pub mod transfer;

#[cfg(test)]
mod tests;

use nalgebra::{Isometry3, Point3};
use thiserror::Error;

use crate::hand::{HandKinematics, HandModel};

pub use baselines::{baseline_cg, baseline_wp, BaselineGrasp};
pub use demo::{
    check_demonstration, close_until_contact, finger_links, CloseOptions, ClosedGrasp, DemoCheck, DemoCheckOptions,
    DemoFileError, Demonstration, FingerClearance, NamedPoint, PoseFile, DEMO_DIR,
};
pub use penetration::{Clearance, HandSpheres, Scene, ToolCollider};
pub use pregrasp::{pregrasp, PreGrasp, PreGraspOptions};
pub use solver::{GraspSolver, PenetrationOptions, SolveOptions};

/// What the grasp must keep: one world point per hand keypoint (the hand's
/// keypoint order, [`HandModel::keypoints`]) and a weight for each.
#[derive(Clone, Debug, PartialEq)]
pub struct GraspTargets {
    pub keypoints_world: Vec<Point3<f64>>,
    /// One non-negative finite weight per keypoint; not all zero.
    pub weights: Vec<f64>,
}

impl GraspTargets {
    /// All weights 1.
    pub fn uniform(keypoints_world: Vec<Point3<f64>>) -> Self {
        let weights = vec![1.0; keypoints_world.len()];
        Self { keypoints_world, weights }
    }

    /// Checks the targets against `hand` (count, finiteness, weights).
    pub fn validate(&self, hand: &HandModel) -> Result<(), GraspError> {
        let expected = hand.keypoints().len();
        if self.keypoints_world.len() != expected {
            return Err(GraspError::WrongKeypointCount { expected, got: self.keypoints_world.len() });
        }
        if self.weights.len() != expected {
            return Err(GraspError::WrongWeightCount { expected, got: self.weights.len() });
        }
        if let Some(index) = self.keypoints_world.iter().position(|p| !p.coords.iter().all(|v| v.is_finite())) {
            return Err(GraspError::NonFiniteKeypoint { index });
        }
        if let Some(index) = self.weights.iter().position(|w| !(w.is_finite() && *w >= 0.0)) {
            return Err(GraspError::InvalidWeight { index, value: self.weights[index] });
        }
        if self.weights.iter().all(|&w| w == 0.0) {
            return Err(GraspError::AllWeightsZero);
        }
        Ok(())
    }
}

/// A hand configuration: wrist pose and joints.
#[derive(Clone, Debug, PartialEq)]
pub struct Grasp {
    /// The root (palm) link's frame in the world.
    pub wrist_pose_world: Isometry3<f64>,
    /// Actuated joints, order [`HandModel::actuated_joints`] (rad or m).
    pub actuated: Vec<f64>,
    /// Every moving joint, mimics expanded, order [`HandModel::moving_joints`].
    pub joints: Vec<f64>,
}

impl Grasp {
    /// A grasp from its wrist pose and actuated joints (mimics expanded here).
    /// Panics if `actuated` has the wrong length (a programming error; use
    /// [`Grasp::validate`] on untrusted input).
    pub fn new(hand: &HandModel, wrist_pose_world: Isometry3<f64>, actuated: Vec<f64>) -> Self {
        let mut joints = vec![0.0; hand.moving_joints().len()];
        hand.expand_joint_positions(&actuated, &mut joints);
        Self { wrist_pose_world, actuated, joints }
    }

    /// The open hand at `wrist_pose_world`.
    pub fn open(hand: &HandModel, wrist_pose_world: Isometry3<f64>) -> Self {
        Self::new(hand, wrist_pose_world, hand.open_hand().to_vec())
    }

    /// Checks lengths and finiteness against `hand` (limits are not checked:
    /// a start outside them is clamped by the solver).
    pub fn validate(&self, hand: &HandModel) -> Result<(), GraspError> {
        let expected = hand.num_actuated();
        if self.actuated.len() != expected {
            return Err(GraspError::WrongActuatedCount { expected, got: self.actuated.len() });
        }
        let pose = self.wrist_pose_world.to_homogeneous();
        if !pose.iter().chain(&self.actuated).all(|v| v.is_finite()) {
            return Err(GraspError::NonFiniteGrasp);
        }
        Ok(())
    }

    /// World keypoints of this grasp (allocates; for reports and tests).
    pub fn keypoints_world(&self, hand: &HandModel) -> Vec<Point3<f64>> {
        let mut kin = HandKinematics::new(hand);
        kin.update(hand, &self.wrist_pose_world, &self.actuated);
        kin.keypoints().to_vec()
    }
}

/// Distance of solved keypoints to their targets.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize)]
pub struct ResidualStats {
    /// Unweighted mean Euclidean distance, millimetres.
    pub mean: f64,
    /// Largest Euclidean distance, millimetres.
    pub max: f64,
}

/// How a solve went.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SolveReport {
    /// Keypoint residuals of the returned grasp, millimetres.
    pub residual_mm: ResidualStats,
    /// Deepest penetration of any hand collision primitive into the tool or
    /// below the table, millimetres (0 when clear or when no scene was given).
    pub penetration_mm: f64,
    /// Levenberg–Marquardt iterations, summed over all starts run.
    pub iterations: usize,
    /// Starts run (the solver stops early once a start fits exactly).
    pub starts: usize,
    /// Starts of those stopped early, stalled far above the best cost
    /// (`SolveOptions::abandon_factor`).
    pub abandoned_starts: usize,
    /// Which start gave the returned grasp (0: the caller's warm start).
    pub best_start: usize,
    /// Whether the best start met a convergence test (not the iteration cap).
    pub converged: bool,
    pub elapsed_ms: f64,
}

/// Errors of the grasp module: bad input, never bad luck (an unreachable
/// target still returns the best grasp and its residual).
#[derive(Debug, Error, PartialEq)]
pub enum GraspError {
    #[error("expected {expected} target keypoints (one per hand keypoint), got {got}")]
    WrongKeypointCount { expected: usize, got: usize },
    #[error("expected {expected} keypoint weights, got {got}")]
    WrongWeightCount { expected: usize, got: usize },
    #[error("target keypoint {index} is not finite")]
    NonFiniteKeypoint { index: usize },
    #[error("keypoint weight {index} is {value}; weights must be finite and non-negative")]
    InvalidWeight { index: usize, value: f64 },
    #[error("all keypoint weights are zero")]
    AllWeightsZero,
    #[error("expected {expected} actuated joint values, got {got}")]
    WrongActuatedCount { expected: usize, got: usize },
    #[error("the grasp's wrist pose or joints are not finite")]
    NonFiniteGrasp,
    #[error("tool mesh: {reason}")]
    BadToolMesh { reason: String },
    #[error("the open hand already pierces the scene by {depth_mm:.2} mm at this wrist pose")]
    OpenHandPenetrates { depth_mm: f64 },
    #[error("invalid option {what}: {reason}")]
    InvalidOption { what: &'static str, reason: String },
    #[error("{what} is not finite")]
    NonFinite { what: &'static str },
    #[error(
        "the demonstration was made with hand `{demo_hand}`, not `{hand}` (author one with it: `graspd demo author --hand-urdf U --hand-keypoints K`)"
    )]
    DemonstrationOfAnotherHand { demo_hand: String, hand: String },
}

/// The paper's Table I metric: mean distance between the grasp's keypoints
/// and the targets, in centimetres (unweighted).
pub fn task_space_distance_cm(hand: &HandModel, grasp: &Grasp, targets: &[Point3<f64>]) -> f64 {
    let kps = grasp.keypoints_world(hand);
    residual_stats(&kps, targets).mean / 10.0
}

/// Mean and max distance between two point lists, millimetres.
pub fn residual_stats(points: &[Point3<f64>], targets: &[Point3<f64>]) -> ResidualStats {
    assert_eq!(points.len(), targets.len(), "point list lengths");
    if points.is_empty() {
        return ResidualStats::default();
    }
    let (mut sum, mut max) = (0.0_f64, 0.0_f64);
    for (p, t) in points.iter().zip(targets) {
        let d = (p - t).norm();
        sum += d;
        max = max.max(d);
    }
    ResidualStats { mean: 1e3 * sum / points.len() as f64, max: 1e3 * max }
}
