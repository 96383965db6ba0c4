//! The pre-grasp RL episodes start from (paper §III-D): the solved grasp
//! backed off along the palm normal, its joints part-way between the open
//! hand and the grasp, and a check that it is clear of the tool and table.

use nalgebra::{Isometry3, Translation3, Vector3};

use super::penetration::{clearance, Clearance, HandSpheres, Scene};
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
    /// When the preferred pre-grasp (above) touches the tool or table, search
    /// nearby ones: longer back-offs, an open hand, approach directions tilted
    /// from the palm normal. The first clear one in that order of preference
    /// is taken. Off: the preferred one is returned as it is, clear or not.
    pub search: bool,
    /// Clearance the search asks of a pre-grasp and of the first half of its
    /// straight approach to the grasp, metres.
    pub min_clearance_m: f64,
}

impl Default for PreGraspOptions {
    fn default() -> Self {
        Self { backoff_m: 0.08, joint_fraction: 0.3, sphere_spacing: 0.5, search: true, min_clearance_m: 0.005 }
    }
}

#[derive(Clone, Debug, PartialEq)]
pub struct PreGrasp {
    pub grasp: Grasp,
    /// No hand sphere pierces the tool or the table.
    pub collision_free: bool,
    /// Smallest hand-to-scene distance, metres (+∞ for an empty scene).
    pub min_clearance_m: f64,
    /// Where the search ended: the back-off (metres), the approach's angle to
    /// the palm normal (radians) and the joint fraction used.
    pub backoff_m: f64,
    pub approach_tilt_rad: f64,
    pub joint_fraction: f64,
    /// Candidates checked (1 when the preferred pre-grasp was clear).
    pub candidates: usize,
}

/// The pre-grasp of `grasp`: backed off against the palm normal, joints
/// part-way open (options), clear of the scene. A wrap grasp often is not
/// clear straight back (measured on the drill demonstration's transfers: 2 of
/// 10 training drills; the fingers around the grip meet the battery), so a
/// touching one is searched around: back-offs × 1, 1.5, 2; the joint fraction,
/// then the open hand; approach directions tilted 15-60° toward eight
/// azimuths. A candidate must keep `min_clearance_m` at its pose and halfway
/// along the straight approach to the grasp (so it does not come through the
/// tool). Without a clear one, the preferred pre-grasp is returned, flagged.
pub fn pregrasp(
    hand: &HandModel,
    grasp: &Grasp,
    scene: &Scene,
    options: &PreGraspOptions,
) -> Result<PreGrasp, GraspError> {
    grasp.validate(hand)?;
    if !(options.backoff_m.is_finite() && options.joint_fraction.is_finite() && options.min_clearance_m.is_finite()) {
        return Err(GraspError::NonFinite { what: "pre-grasp options" });
    }
    let spheres = HandSpheres::new(hand, options.sphere_spacing);
    let mut kin = HandKinematics::new(hand);
    let wrist = grasp.wrist_pose_world;
    let normal_world = wrist.rotation * hand.palm_normal().into_inner();
    let candidate = |direction: &Vector3<f64>, backoff: f64, fraction: f64| -> Grasp {
        let backed =
            Isometry3::from_parts(Translation3::from(wrist.translation.vector - backoff * direction), wrist.rotation);
        let mut q: Vec<f64> =
            hand.open_hand().iter().zip(&grasp.actuated).map(|(o, g)| o + fraction * (g - o)).collect();
        hand.clamp_actuated(&mut q);
        Grasp::new(hand, backed, q)
    };
    let mut clearance_of = |g: &Grasp| {
        kin.update(hand, &g.wrist_pose_world, &g.actuated);
        clearance(&spheres, &kin, scene)
    };
    let preferred = candidate(&normal_world, options.backoff_m, options.joint_fraction);
    let c = clearance_of(&preferred);
    let result = |g: Grasp, c: Clearance, backoff_m, approach_tilt_rad, joint_fraction, candidates| PreGrasp {
        grasp: g,
        collision_free: c.collision_free(),
        min_clearance_m: c.min_clearance_m,
        backoff_m,
        approach_tilt_rad,
        joint_fraction,
        candidates,
    };
    let clear_enough = |c: &Clearance| c.min_clearance_m >= options.min_clearance_m;
    if !options.search || clear_enough(&c) {
        return Ok(result(preferred, c, options.backoff_m, 0.0, options.joint_fraction, 1));
    }
    // Two unit vectors across the normal, for the tilted directions.
    let across = normal_world
        .cross(&Vector3::x())
        .try_normalize(1e-6)
        .unwrap_or_else(|| normal_world.cross(&Vector3::y()).normalize());
    let across2 = normal_world.cross(&across);
    let mut checked = 1;
    for tilt_deg in [0.0_f64, 15.0, 30.0, 45.0, 60.0] {
        let tilt = tilt_deg.to_radians();
        let azimuths = if tilt_deg == 0.0 { 1 } else { 8 };
        for scale in [1.0, 1.5, 2.0] {
            for fraction in [options.joint_fraction, 0.0] {
                // Directions that lift the wrist (world z up) first: a
                // pre-grasp that misses the tool most often meets the table.
                let mut directions: Vec<Vector3<f64>> = (0..azimuths)
                    .map(|k| {
                        let phi = std::f64::consts::TAU * k as f64 / azimuths as f64;
                        tilt.cos() * normal_world + tilt.sin() * (phi.cos() * across + phi.sin() * across2)
                    })
                    .collect();
                directions.sort_by(|a, b| a.z.total_cmp(&b.z));
                for direction in directions {
                    let backoff = scale * options.backoff_m;
                    if tilt_deg == 0.0 && scale == 1.0 && fraction == options.joint_fraction {
                        continue; // the preferred one
                    }
                    checked += 1;
                    let g = candidate(&direction, backoff, fraction);
                    let c = clearance_of(&g);
                    if !clear_enough(&c) {
                        continue;
                    }
                    // Halfway in, with the pre-grasp's joints.
                    let halfway = candidate(&direction, 0.5 * backoff, fraction);
                    if !clear_enough(&clearance_of(&halfway)) {
                        continue;
                    }
                    return Ok(result(g, c, backoff, tilt, fraction, checked));
                }
            }
        }
    }
    Ok(result(preferred, c, options.backoff_m, 0.0, options.joint_fraction, checked))
}
