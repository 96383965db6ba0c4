//! The paper's baselines (Table I):
//! - CG, canonical grasp: the demonstration's grasp kept in the object
//!   frame — its wrist moved by the registered rigid pose, its joints kept.
//! - WP, wrist pose: the wrist moved through the deformation — by the rigid
//!   transform that best maps the demonstration's keypoints onto the
//!   transferred ones — its joints kept. (For fixed joints this is also the
//!   best wrist in the least-squares sense, so WP bounds what moving the
//!   wrist alone can do.)

use nalgebra::Isometry3;

use super::linalg::fit_rigid;
use super::{task_space_distance_cm, Grasp, GraspError, GraspTargets};
use crate::hand::HandModel;

/// A baseline's grasp and its task-space distance to the targets.
#[derive(Clone, Debug, PartialEq)]
pub struct BaselineGrasp {
    pub grasp: Grasp,
    /// Mean keypoint-to-target distance, centimetres (paper Table I).
    pub task_space_distance_cm: f64,
}

/// CG. `canonical`: the demonstration's grasp with the canonical tool at
/// `canonical_tool_pose_world`; `tool_pose_world`: the registered pose of
/// the observed tool (same tool frame convention).
pub fn baseline_cg(
    hand: &HandModel,
    canonical: &Grasp,
    canonical_tool_pose_world: &Isometry3<f64>,
    tool_pose_world: &Isometry3<f64>,
    targets: &GraspTargets,
) -> Result<BaselineGrasp, GraspError> {
    targets.validate(hand)?;
    canonical.validate(hand)?;
    let wrist_tool = canonical_tool_pose_world.inverse() * canonical.wrist_pose_world;
    let grasp = Grasp::new(hand, tool_pose_world * wrist_tool, canonical.actuated.clone());
    let task_space_distance_cm = task_space_distance_cm(hand, &grasp, &targets.keypoints_world);
    Ok(BaselineGrasp { grasp, task_space_distance_cm })
}

/// WP. `canonical`: the demonstration's grasp (world frame of the
/// demonstration); `targets`: the transferred keypoints, whose weights
/// weight the rigid fit.
pub fn baseline_wp(hand: &HandModel, canonical: &Grasp, targets: &GraspTargets) -> Result<BaselineGrasp, GraspError> {
    targets.validate(hand)?;
    canonical.validate(hand)?;
    let demo = canonical.keypoints_world(hand);
    let motion = fit_rigid(&demo, &targets.keypoints_world, &targets.weights);
    let grasp = Grasp::new(hand, motion * canonical.wrist_pose_world, canonical.actuated.clone());
    let task_space_distance_cm = task_space_distance_cm(hand, &grasp, &targets.keypoints_world);
    Ok(BaselineGrasp { grasp, task_space_distance_cm })
}
