//! `graspd hand`: the hand model (joints, couplings, limits, keypoints) and
//! random reachable keypoint sets (targets for retargeting benchmarks).

use super::{print_json, CliResult};
use clap::Subcommand;
use graspd::grasp::{Grasp, PoseFile};
use graspd::hand::{CollisionShape, HandModel, JointDrive, JointKind};
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::path::PathBuf;

#[derive(Subcommand)]
pub enum HandCommand {
    /// Joints, actuated joints, mimic couplings, limits and keypoints of the hand.
    Info {
        #[command(flatten)]
        hand: HandArgs,
        #[arg(long)]
        json: bool,
    },
    /// Random reachable configurations and their keypoints (forward kinematics):
    /// a target file for `graspd retarget --keypoints` (JSON on stdout).
    Sample {
        #[arg(long, default_value_t = 100)]
        n: usize,
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Wrist positions are uniform in a cube of this half size around the origin, metres.
        #[arg(long, default_value_t = 0.2)]
        extent_m: f64,
        #[command(flatten)]
        hand: HandArgs,
        #[arg(long)]
        json: bool,
    },
}

/// The hand a command works with: the bundled SIH-like hand, or another
/// one from its URDF (collision primitives; meshes as the capsules enclosing them) and keypoints file
/// (format: assets/hands/sih_right/README.md). Every command that solves,
/// checks or authors a grasp takes these options.
#[derive(clap::Args, Clone, Debug, Default)]
pub struct HandArgs {
    /// URDF of another hand than the bundled SIH-like one (with --hand-keypoints).
    #[arg(long, alias = "urdf", requires = "hand_keypoints")]
    pub hand_urdf: Option<PathBuf>,
    /// The keypoints file of the --hand-urdf hand.
    #[arg(long, alias = "keypoints", requires = "hand_urdf")]
    pub hand_keypoints: Option<PathBuf>,
}

impl HandArgs {
    pub fn load(&self) -> Result<HandModel, Box<dyn std::error::Error>> {
        Ok(match (&self.hand_urdf, &self.hand_keypoints) {
            (Some(u), Some(k)) => HandModel::from_urdf_file(u, k)?,
            _ => HandModel::default_sih()?,
        })
    }
}

fn kind_name(kind: JointKind) -> &'static str {
    match kind {
        JointKind::Fixed => "fixed",
        JointKind::Revolute => "revolute",
        JointKind::Continuous => "continuous",
        JointKind::Prismatic => "prismatic",
    }
}

/// JSON-safe limit (±∞ of a continuous joint as null).
fn finite_or_null(v: f64) -> serde_json::Value {
    if v.is_finite() {
        serde_json::json!(v)
    } else {
        serde_json::Value::Null
    }
}

pub fn info_json(hand: &HandModel) -> serde_json::Value {
    let actuated_names: Vec<&str> = hand.actuated_names().collect();
    let joints: Vec<serde_json::Value> = hand
        .joints()
        .iter()
        .map(|j| {
            let t = j.origin.translation.vector;
            let q = j.origin.rotation.coords;
            let drive = match j.drive {
                JointDrive::Fixed => serde_json::json!({"kind": "fixed"}),
                JointDrive::Actuated { index } => serde_json::json!({"kind": "actuated", "index": index}),
                JointDrive::Mimic { driver, multiplier, offset } => serde_json::json!({
                    "kind": "mimic", "joint": actuated_names[driver], "multiplier": multiplier, "offset": offset
                }),
            };
            serde_json::json!({
                "name": j.name,
                "type": kind_name(j.kind),
                "parent": hand.links()[j.parent].name,
                "child": hand.links()[j.child].name,
                "origin": {"translation": [t.x, t.y, t.z], "rotation_xyzw": [q.x, q.y, q.z, q.w]},
                "axis": [j.axis.x, j.axis.y, j.axis.z],
                "limits": [finite_or_null(j.lower), finite_or_null(j.upper)],
                "drive": drive,
            })
        })
        .collect();
    let actuated: Vec<serde_json::Value> = hand
        .actuated_names()
        .zip(hand.actuated_limits())
        .zip(hand.open_hand())
        .map(|((name, &[lo, hi]), open)| {
            serde_json::json!({"name": name, "limits": [finite_or_null(lo), finite_or_null(hi)], "open": open})
        })
        .collect();
    let mimic: Vec<serde_json::Value> = hand
        .joints()
        .iter()
        .filter_map(|j| match j.drive {
            JointDrive::Mimic { driver, multiplier, offset } => Some(serde_json::json!({
                "joint": j.name, "mimics": actuated_names[driver], "multiplier": multiplier, "offset": offset
            })),
            _ => None,
        })
        .collect();
    let points = |ks: &[graspd::hand::Keypoint]| -> Vec<serde_json::Value> {
        ks.iter()
            .map(|k| serde_json::json!({"name": k.name, "link": hand.links()[k.link].name, "offset": [k.offset.x, k.offset.y, k.offset.z]}))
            .collect()
    };
    // Each primitive in its link's frame (a collision mesh appears as the
    // cylinder and two spheres of the capsule enclosing it).
    let collisions: Vec<serde_json::Value> = hand
        .collision_primitives()
        .iter()
        .map(|c| {
            let (t, q) = (c.origin.translation.vector, c.origin.rotation.coords);
            let shape = match c.shape {
                CollisionShape::Box { half_extents: h } => {
                    serde_json::json!({"box": {"half_extents": [h.x, h.y, h.z]}})
                }
                CollisionShape::Sphere { radius } => serde_json::json!({"sphere": {"radius": radius}}),
                CollisionShape::Cylinder { radius, half_length } => {
                    serde_json::json!({"cylinder": {"radius": radius, "half_length": half_length}})
                }
            };
            serde_json::json!({
                "link": hand.links()[c.link].name,
                "name": c.name,
                "origin": {"translation": [t.x, t.y, t.z], "rotation_xyzw": [q.x, q.y, q.z, q.w]},
                "shape": shape,
            })
        })
        .collect();
    let n = hand.palm_normal();
    serde_json::json!({
        "name": hand.name(),
        "root_link": hand.links()[hand.root_link()].name,
        "links": hand.links().len(),
        "joints": joints,
        "moving_joints": hand.moving_joints().iter().map(|&j| hand.joints()[j].name.as_str()).collect::<Vec<_>>(),
        "actuated": actuated,
        "mimic": mimic,
        "keypoints": points(hand.keypoints()),
        "fingertips": points(hand.fingertips()),
        "palm_normal": [n.x, n.y, n.z],
        "collision_primitives": collisions,
    })
}

/// A random actuated vector within the limits (±π for unlimited joints).
pub fn random_actuated(hand: &HandModel, rng: &mut ChaCha8Rng) -> Vec<f64> {
    hand.actuated_limits()
        .iter()
        .map(|&[lo, hi]| {
            let (lo, hi) = (lo.max(-std::f64::consts::PI), hi.min(std::f64::consts::PI));
            lo + (hi - lo) * rng.random::<f64>()
        })
        .collect()
}

/// A uniformly random rotation (Shoemake) and a position in the cube ±`extent`.
pub fn random_wrist(rng: &mut ChaCha8Rng, extent: f64) -> Isometry3<f64> {
    let (u1, u2, u3): (f64, f64, f64) = (rng.random(), rng.random(), rng.random());
    let tau = std::f64::consts::TAU;
    let (a, b) = ((1.0 - u1).sqrt(), u1.sqrt());
    let q = nalgebra::Quaternion::new(
        b * (tau * u3).cos(),
        a * (tau * u2).sin(),
        a * (tau * u2).cos(),
        b * (tau * u3).sin(),
    );
    let t =
        Vector3::new(rng.random::<f64>(), rng.random::<f64>(), rng.random::<f64>()).map(|v| (2.0 * v - 1.0) * extent);
    Isometry3::from_parts(Translation3::from(t), UnitQuaternion::from_quaternion(q))
}

pub fn run(cmd: HandCommand) -> CliResult {
    match cmd {
        HandCommand::Info { hand, json } => {
            let hand = hand.load()?;
            if json {
                print_json(&info_json(&hand))?;
            } else {
                println!(
                    "{}: {} links, {} moving joints ({} actuated), {} keypoints, {} fingertips",
                    hand.name(),
                    hand.links().len(),
                    hand.moving_joints().len(),
                    hand.num_actuated(),
                    hand.keypoints().len(),
                    hand.fingertips().len()
                );
                for (name, [lo, hi]) in hand.actuated_names().zip(hand.actuated_limits()) {
                    println!("  actuated {name:<28} [{lo:>7.3}, {hi:>7.3}]");
                }
                for j in hand.joints() {
                    if let JointDrive::Mimic { driver, multiplier, offset } = j.drive {
                        let d = hand.actuated_names().nth(driver).unwrap_or("?");
                        println!("  mimic    {:<28} = {multiplier} × {d} + {offset}", j.name);
                    }
                }
                for k in hand.keypoints() {
                    println!("  keypoint {:<14} on {}", k.name, hand.links()[k.link].name);
                }
            }
        }
        HandCommand::Sample { n, seed, extent_m, hand, json: _ } => {
            if !(extent_m.is_finite() && extent_m >= 0.0) {
                return Err(format!("--extent-m {extent_m}: expected a non-negative number").into());
            }
            let hand = hand.load()?;
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            let sets: Vec<serde_json::Value> = (0..n)
                .map(|_| {
                    let truth = Grasp::new(&hand, random_wrist(&mut rng, extent_m), random_actuated(&hand, &mut rng));
                    let kps: Vec<[f64; 3]> = truth.keypoints_world(&hand).iter().map(|p| [p.x, p.y, p.z]).collect();
                    serde_json::json!({
                        "keypoints": kps,
                        "truth": {"wrist_pose": PoseFile::from_isometry(&truth.wrist_pose_world), "actuated": truth.actuated, "joints": truth.joints},
                    })
                })
                .collect();
            print_json(&serde_json::json!({
                "hand": hand.name(),
                "seed": seed,
                "keypoint_names": hand.keypoints().iter().map(|k| k.name.as_str()).collect::<Vec<_>>(),
                "actuated_names": hand.actuated_names().collect::<Vec<_>>(),
                "moving_joint_names": hand.moving_joints().iter().map(|&j| hand.joints()[j].name.as_str()).collect::<Vec<_>>(),
                "sets": sets,
            }))?;
        }
    }
    Ok(())
}
