//! Authoring a demonstration grasp: "close until contact".
//!
//! The hand starts open at a chosen wrist pose and every actuated joint
//! moves from the open configuration toward its closed value at once; a
//! joint stops the moment any collision sphere it moves would pierce the
//! tool or the table (found by stepping, then bisection to `tolerance_m`),
//! or when it reaches its closed value. Fingers therefore end resting on
//! the surface, so the demonstration's keypoints lie on the tool, where a
//! transferred grasp can find them again.

use nalgebra::{Isometry3, Point3};

use super::penetration::{HandSpheres, Scene};
use super::{Grasp, GraspError};
use crate::hand::{HandKinematics, HandModel, JointDrive};

#[derive(Clone, Debug, PartialEq)]
pub struct CloseOptions {
    /// Closed value of each actuated joint; `None`: for each joint, the
    /// limit farther from the open hand (for the SIH: fingers and thumb
    /// rotation to their lower limit, thumb bend to its upper limit).
    pub closed: Option<Vec<f64>>,
    /// Largest joint move per step before contact is checked (rad or m):
    /// small enough that no phalanx jumps across a thin part.
    pub max_step: f64,
    /// Contact is located to this distance (metres).
    pub tolerance_m: f64,
    pub sphere_spacing: f64,
}

impl Default for CloseOptions {
    fn default() -> Self {
        Self { closed: None, max_step: 0.01, tolerance_m: 1e-4, sphere_spacing: 0.5 }
    }
}

/// The closed grasp and how each joint stopped.
#[derive(Clone, Debug, PartialEq)]
pub struct ClosedGrasp {
    pub grasp: Grasp,
    /// Per actuated joint: it stopped on contact (true) or at its closed value.
    pub in_contact: Vec<bool>,
    /// Smallest hand-to-scene distance at the end, metres (≥ 0, ≤ tolerance
    /// for joints in contact unless the palm is closer).
    pub min_clearance_m: f64,
}

/// Closes the open hand at `wrist_pose_world` onto the scene. Fails if the
/// open hand already pierces the scene (the wrist pose is wrong).
pub fn close_until_contact(
    hand: &HandModel,
    wrist_pose_world: &Isometry3<f64>,
    scene: &Scene,
    options: &CloseOptions,
) -> Result<ClosedGrasp, GraspError> {
    let n = hand.num_actuated();
    let open = hand.open_hand().to_vec();
    let closed = match &options.closed {
        Some(c) if c.len() != n => return Err(GraspError::WrongActuatedCount { expected: n, got: c.len() }),
        Some(c) => {
            let mut c = c.clone();
            hand.clamp_actuated(&mut c);
            c
        }
        None => open
            .iter()
            .zip(hand.actuated_limits())
            .map(|(&o, &[lo, hi])| if (o - lo).abs() >= (hi - o).abs() { lo } else { hi })
            .collect(),
    };
    if !closed.iter().all(|v| v.is_finite()) {
        return Err(GraspError::NonFinite { what: "closed configuration" });
    }
    for (what, v) in [("max_step", options.max_step), ("tolerance_m", options.tolerance_m)] {
        if !(v.is_finite() && v > 0.0) {
            return Err(GraspError::InvalidOption { what, reason: format!("{v} is not a positive finite number") });
        }
    }
    Grasp::open(hand, *wrist_pose_world).validate(hand)?;

    let spheres = HandSpheres::new(hand, options.sphere_spacing);
    let moved_by = spheres_moved_by(hand, &spheres);
    let mut kin = HandKinematics::new(hand);
    let clearance_of = |kin: &mut HandKinematics, q: &[f64], k: usize| {
        kin.update(hand, wrist_pose_world, q);
        min_clearance(&spheres, kin, scene, &moved_by[k])
    };

    kin.update(hand, wrist_pose_world, &open);
    let all: Vec<usize> = (0..spheres.spheres().len()).collect();
    let start = min_clearance(&spheres, &kin, scene, &all);
    if start < 0.0 {
        return Err(GraspError::OpenHandPenetrates { depth_mm: -1e3 * start });
    }

    // Progress s ∈ [0, 1] of each joint along open → closed.
    let mut s = vec![0.0; n];
    let mut moving: Vec<bool> = (0..n).map(|k| closed[k] != open[k]).collect();
    let mut in_contact = vec![false; n];
    let ds: Vec<f64> = (0..n).map(|k| (options.max_step / (closed[k] - open[k]).abs()).min(1.0)).collect();
    // s = 1 is the closed value exactly (no rounding past a limit).
    let at = |s: &[f64]| -> Vec<f64> {
        (0..n).map(|k| if s[k] >= 1.0 { closed[k] } else { open[k] + s[k] * (closed[k] - open[k]) }).collect()
    };
    while moving.iter().any(|&m| m) {
        for k in 0..n {
            if !moving[k] {
                continue;
            }
            let mut trial = s.clone();
            trial[k] = (s[k] + ds[k]).min(1.0);
            if clearance_of(&mut kin, &at(&trial), k) >= 0.0 {
                s[k] = trial[k];
                if s[k] >= 1.0 {
                    moving[k] = false;
                }
                continue;
            }
            // Contact between s[k] (clear) and trial[k]: bisect, keeping the
            // clear side, until it is within tolerance of the surface.
            let (mut lo, mut hi) = (s[k], trial[k]);
            let mut probe = s.clone();
            for _ in 0..60 {
                probe[k] = lo;
                if clearance_of(&mut kin, &at(&probe), k) <= options.tolerance_m {
                    break;
                }
                probe[k] = 0.5 * (lo + hi);
                if clearance_of(&mut kin, &at(&probe), k) >= 0.0 {
                    lo = probe[k];
                } else {
                    hi = probe[k];
                }
            }
            s[k] = lo;
            moving[k] = false;
            in_contact[k] = true;
        }
    }
    let q = at(&s);
    kin.update(hand, wrist_pose_world, &q);
    let min_clearance_m = min_clearance(&spheres, &kin, scene, &all);
    Ok(ClosedGrasp { grasp: Grasp::new(hand, *wrist_pose_world, q), in_contact, min_clearance_m })
}

/// For each actuated joint, the spheres on links it moves (directly or
/// through a mimic joint).
fn spheres_moved_by(hand: &HandModel, spheres: &HandSpheres) -> Vec<Vec<usize>> {
    let mut out = vec![Vec::new(); hand.num_actuated()];
    for (i, s) in spheres.spheres().iter().enumerate() {
        let mut l = s.link;
        let mut drivers = Vec::new();
        while let Some(j) = hand.links()[l].parent_joint {
            let joint = &hand.joints()[j];
            match joint.drive {
                JointDrive::Actuated { index } | JointDrive::Mimic { driver: index, .. } => drivers.push(index),
                JointDrive::Fixed => {}
            }
            l = joint.parent;
        }
        drivers.sort_unstable();
        drivers.dedup();
        for k in drivers {
            out[k].push(i);
        }
    }
    out
}

fn min_clearance(spheres: &HandSpheres, kin: &HandKinematics, scene: &Scene, set: &[usize]) -> f64 {
    let mut min = f64::INFINITY;
    for &i in set {
        let c: Point3<f64> = spheres.center_world(kin, i);
        let r = spheres.spheres()[i].radius;
        if let Some(tool) = scene.tool {
            if let Some((sd, _)) = tool.signed_distance(&c, f64::INFINITY) {
                min = min.min(sd - r);
            }
        }
        if let Some(h) = scene.table_height_world {
            min = min.min(c.z - h - r);
        }
    }
    min
}

/// A demonstration as stored in `assets/demos/*.json`: the grasp in the
/// canonical tool's frame and the keypoints it defines there (the points the
/// shape space moves onto other tools).
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Demonstration {
    /// URDF robot name of the hand it was made with.
    pub hand: String,
    /// Free text: which tool (e.g. "mug/canonical").
    pub tool: String,
    pub wrist_pose_tool: PoseFile,
    /// Actuated joint name → value (rad or m).
    pub actuated: std::collections::BTreeMap<String, f64>,
    /// The hand's keypoints in the tool frame, in the hand's keypoint order.
    pub keypoints_tool: Vec<NamedPoint>,
}

/// A pose in a file: translation (metres) and unit quaternion (x, y, z, w).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PoseFile {
    pub translation: [f64; 3],
    pub rotation_xyzw: [f64; 4],
}

#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NamedPoint {
    pub name: String,
    pub position: [f64; 3],
}

impl PoseFile {
    pub fn from_isometry(pose: &Isometry3<f64>) -> Self {
        let t = pose.translation.vector;
        let q = pose.rotation.coords; // (i, j, k, w)
        Self { translation: [t.x, t.y, t.z], rotation_xyzw: [q.x, q.y, q.z, q.w] }
    }

    /// The pose; the quaternion is normalised, and must be finite and nonzero.
    pub fn to_isometry(&self) -> Result<Isometry3<f64>, GraspError> {
        let [x, y, z, w] = self.rotation_xyzw;
        let q = nalgebra::Quaternion::new(w, x, y, z);
        if !(self.translation.iter().chain(&self.rotation_xyzw).all(|v| v.is_finite()) && q.norm() > 1e-9) {
            return Err(GraspError::NonFinite { what: "pose (or its quaternion is zero)" });
        }
        Ok(Isometry3::from_parts(
            nalgebra::Translation3::new(self.translation[0], self.translation[1], self.translation[2]),
            nalgebra::UnitQuaternion::from_quaternion(q),
        ))
    }
}

impl Demonstration {
    /// Records `grasp` made on a tool placed at `tool_pose_world`.
    pub fn new(hand: &HandModel, tool: &str, grasp: &Grasp, tool_pose_world: &Isometry3<f64>) -> Self {
        let to_tool = tool_pose_world.inverse();
        let keypoints_tool = hand
            .keypoints()
            .iter()
            .zip(grasp.keypoints_world(hand))
            .map(|(k, p)| {
                let p = to_tool * p;
                NamedPoint { name: k.name.clone(), position: [p.x, p.y, p.z] }
            })
            .collect();
        Self {
            hand: hand.name().to_owned(),
            tool: tool.to_owned(),
            wrist_pose_tool: PoseFile::from_isometry(&(to_tool * grasp.wrist_pose_world)),
            actuated: hand.actuated_names().map(str::to_owned).zip(grasp.actuated.iter().copied()).collect(),
            keypoints_tool,
        }
    }

    /// The demonstrated grasp with the tool at `tool_pose_world` (the CG
    /// grasp, and the natural warm start). Checks the file against `hand`.
    pub fn grasp_at(&self, hand: &HandModel, tool_pose_world: &Isometry3<f64>) -> Result<Grasp, GraspError> {
        let mut q = Vec::with_capacity(hand.num_actuated());
        for name in hand.actuated_names() {
            let v = *self.actuated.get(name).ok_or_else(|| GraspError::InvalidOption {
                what: "demonstration actuated joints",
                reason: format!("no value for joint `{name}` of hand `{}`", hand.name()),
            })?;
            q.push(v);
        }
        if self.actuated.len() != q.len() {
            return Err(GraspError::InvalidOption {
                what: "demonstration actuated joints",
                reason: format!("{} values for a hand with {} actuated joints", self.actuated.len(), q.len()),
            });
        }
        let grasp = Grasp::new(hand, tool_pose_world * self.wrist_pose_tool.to_isometry()?, q);
        grasp.validate(hand)?;
        Ok(grasp)
    }

    /// The keypoints in the tool frame, checked against `hand`'s keypoint names.
    pub fn keypoints(&self, hand: &HandModel) -> Result<Vec<Point3<f64>>, GraspError> {
        if self.keypoints_tool.len() != hand.keypoints().len() {
            return Err(GraspError::WrongKeypointCount {
                expected: hand.keypoints().len(),
                got: self.keypoints_tool.len(),
            });
        }
        self.keypoints_tool
            .iter()
            .zip(hand.keypoints())
            .enumerate()
            .map(|(index, (p, k))| {
                if p.name != k.name {
                    return Err(GraspError::InvalidOption {
                        what: "demonstration keypoints",
                        reason: format!("keypoint {index} is `{}`, the hand's is `{}`", p.name, k.name),
                    });
                }
                if !p.position.iter().all(|v| v.is_finite()) {
                    return Err(GraspError::NonFiniteKeypoint { index });
                }
                Ok(Point3::from(p.position))
            })
            .collect()
    }
}
