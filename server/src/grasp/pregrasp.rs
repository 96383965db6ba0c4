//! The pre-grasp RL episodes start from (paper §III-D): the solved grasp
//! backed off along the palm normal, its joints part-way between the open
//! hand and the grasp, and a check that it is clear of the tool and table.

use nalgebra::{Isometry3, Translation3};

use super::penetration::{clearance, HandSpheres, Scene};
use super::{Grasp, GraspError};
use crate::hand::{HandKinematics, HandModel};

#[derive(Clone, Debug, PartialEq)]
pub struct PreGraspOptions {
    /// Distance the wrist moves back against the palm normal, metres.
    pub backoff_m: f64,
    /// Joints at open + fraction·(grasp − open): 0 is the open hand, 1 the grasp.
    pub joint_fraction: f64,
    /// Sphere-cover spacing for the clearance check (fraction of radius).
    pub sphere_spacing: f64,
}

impl Default for PreGraspOptions {
    fn default() -> Self {
        Self { backoff_m: 0.08, joint_fraction: 0.3, sphere_spacing: 0.5 }
    }
}

#[derive(Clone, Debug, PartialEq)]
pub struct PreGrasp {
    pub grasp: Grasp,
    /// No hand sphere pierces the tool or the table.
    pub collision_free: bool,
    /// Smallest hand-to-scene distance, metres (+∞ for an empty scene).
    pub min_clearance_m: f64,
}

pub fn pregrasp(
    hand: &HandModel,
    grasp: &Grasp,
    scene: &Scene,
    options: &PreGraspOptions,
) -> Result<PreGrasp, GraspError> {
    grasp.validate(hand)?;
    if !(options.backoff_m.is_finite() && options.joint_fraction.is_finite()) {
        return Err(GraspError::NonFinite { what: "pre-grasp options" });
    }
    let wrist = grasp.wrist_pose_world;
    let normal_world = wrist.rotation * hand.palm_normal().into_inner();
    let backed = Isometry3::from_parts(
        Translation3::from(wrist.translation.vector - options.backoff_m * normal_world),
        wrist.rotation,
    );
    let f = options.joint_fraction;
    let mut q: Vec<f64> = hand.open_hand().iter().zip(&grasp.actuated).map(|(o, g)| o + f * (g - o)).collect();
    hand.clamp_actuated(&mut q);
    let pre = Grasp::new(hand, backed, q);

    let mut kin = HandKinematics::new(hand);
    kin.update(hand, &pre.wrist_pose_world, &pre.actuated);
    let c = clearance(&HandSpheres::new(hand, options.sphere_spacing), &kin, scene);
    Ok(PreGrasp { grasp: pre, collision_free: c.collision_free(), min_clearance_m: c.min_clearance_m })
}
