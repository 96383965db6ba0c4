//! The robot hand: its model (URDF + keypoints file), forward kinematics and
//! analytic Jacobians of the task-space keypoints.
//!
//! The bundled hand is a right Schunk SIH-like hand
//! (`assets/hands/sih_right`, [`HandModel::default_sih`]): 11 revolute joints,
//! 5 actuated — in order index bend, middle bend, ring+little bend, thumb
//! rotation, thumb bend — and 6 mimic joints coupled 1:1.
//!
//! ```no_run
//! use graspd::hand::{HandKinematics, HandModel};
//! use nalgebra::Isometry3;
//! let hand = HandModel::default_sih().unwrap();
//! let mut kin = HandKinematics::new(&hand);
//! kin.update(&hand, &Isometry3::identity(), hand.open_hand());
//! let jac = kin.update_keypoint_jacobian(&hand); // 36 × 11: [δt, δω, δq_a]
//! ```

pub mod keypoints;
pub mod kinematics;
pub mod mesh_collision;
pub mod model;

pub use keypoints::Keypoint;
pub use kinematics::{perturb_wrist, HandKinematics, WRIST_DOF};
pub use model::{
    CollisionPrimitive, CollisionShape, HandModel, HandModelError, Joint, JointDrive, JointId, JointKind, Link, LinkId,
    SIH_ASSET_DIR,
};

#[cfg(test)]
mod tests;
