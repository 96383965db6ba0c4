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

/// Test support: the bundled hand under other names, for tests (here and in
/// the simulator's) that must tell whether another hand was used.
#[doc(hidden)]
pub mod renamed {
    use std::path::{Path, PathBuf};

    /// The renamed hand's robot name.
    pub const ROBOT: &str = "sih_renamed";
    /// Its first actuated joint (the bundled hand's `palm_to_if_proximal`).
    pub const JOINT: &str = "palm_to_index_base";

    /// Files of the renamed hand.
    pub struct RenamedHand {
        pub urdf: PathBuf,
        pub keypoints: PathBuf,
        /// The bundled mug demonstration, renamed to match.
        pub mug_demo: PathBuf,
    }

    impl RenamedHand {
        /// `--hand-urdf U --hand-keypoints K`.
        pub fn args(&self) -> [&str; 4] {
            fn s(p: &Path) -> &str {
                p.to_str().expect("a UTF-8 temporary path")
            }
            ["--hand-urdf", s(&self.urdf), "--hand-keypoints", s(&self.keypoints)]
        }
    }

    /// Writes into `dir` the bundled hand (same kinematics and shapes) with
    /// its robot named [`ROBOT`] and `palm_to_if_proximal` named [`JOINT`],
    /// its keypoints file and the mug demonstration to match.
    pub fn write(dir: &Path) -> std::io::Result<RenamedHand> {
        let rename = |from: &Path, to: PathBuf| -> std::io::Result<PathBuf> {
            let text = std::fs::read_to_string(from)?
                .replace("palm_to_if_proximal", JOINT)
                .replace("\"sih_right\"", &format!("\"{ROBOT}\""));
            std::fs::write(&to, text)?;
            Ok(to)
        };
        let hands = Path::new(super::SIH_ASSET_DIR);
        Ok(RenamedHand {
            urdf: rename(&hands.join("sih_right.urdf"), dir.join("hand.urdf"))?,
            keypoints: rename(&hands.join("keypoints.json"), dir.join("keypoints.json"))?,
            mug_demo: rename(&Path::new(crate::grasp::demo::DEMO_DIR).join("mug.json"), dir.join("mug.json"))?,
        })
    }
}
