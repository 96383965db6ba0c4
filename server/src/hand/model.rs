//! The hand as a kinematic tree: links, joints, couplings, collision
//! primitives, loaded from a URDF plus a keypoints file.
//!
//! The URDF is parsed by `urdf-rs` and then checked and converted into our own
//! tree, so that the kinematics never meet a malformed model: every problem
//! is reported at load time as a [`HandModelError`] naming the element.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use nalgebra::{Isometry3, Translation3, Unit, UnitQuaternion, Vector3};
use thiserror::Error;

use super::keypoints::{parse_keypoints_json, Keypoint};

/// Index of a link in [`HandModel::links`].
pub type LinkId = usize;
/// Index of a joint in [`HandModel::joints`].
pub type JointId = usize;

/// Everything that can be wrong with a hand description.
#[derive(Debug, Error)]
pub enum HandModelError {
    #[error("cannot read {path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("malformed URDF: {reason}")]
    MalformedUrdf { reason: String },
    #[error("URDF robot `{robot}` has no links")]
    NoLinks { robot: String },
    #[error("link `{link}` is defined more than once")]
    DuplicateLink { link: String },
    #[error("joint `{joint}` is defined more than once")]
    DuplicateJoint { joint: String },
    #[error("joint `{joint}`: {role} link `{link}` is not defined")]
    MissingLink { joint: String, role: &'static str, link: String },
    #[error("link `{link}` is the child of both joint `{first}` and joint `{second}`: a closed chain, not a tree")]
    MultipleParents { link: String, first: String, second: String },
    #[error("the joint graph has several root links ({}); a hand has exactly one base link", roots.join(", "))]
    MultipleRoots { roots: Vec<String> },
    #[error("the joint graph has a loop through link `{link}`")]
    KinematicLoop { link: String },
    #[error("joint `{joint}`: type `{kind}` is not supported (fixed, revolute, continuous and prismatic are)")]
    UnsupportedJointType { joint: String, kind: String },
    #[error("joint `{joint}`: axis {axis:?} is not a nonzero finite vector")]
    InvalidAxis { joint: String, axis: [f64; 3] },
    #[error("joint `{joint}`: {reason} (lower {lower}, upper {upper})")]
    InvalidLimits { joint: String, lower: f64, upper: f64, reason: &'static str },
    #[error("joint `{joint}`: mimics unknown joint `{target}`")]
    MimicUnknownJoint { joint: String, target: String },
    #[error("joint `{joint}`: mimics itself")]
    MimicSelf { joint: String },
    #[error("joint `{joint}`: mimics joint `{target}`, which itself mimics `{target_driver}`; name `{target_driver}` directly")]
    MimicOfMimic { joint: String, target: String, target_driver: String },
    #[error("joint `{joint}`: mimics fixed joint `{target}`")]
    MimicOfFixed { joint: String, target: String },
    #[error("joint `{joint}`: mimic {what} is not finite")]
    InvalidMimic { joint: String, what: &'static str },
    #[error("joint `{joint}`: its limits and those of the joints mimicking it leave no range (lower {lower}, upper {upper})")]
    InconsistentMimicLimits { joint: String, lower: f64, upper: f64 },
    #[error("{element}: {what} is not finite")]
    NonFinite { element: String, what: &'static str },
    #[error("link `{link}`, collision {index}: {reason}")]
    InvalidCollision { link: String, index: usize, reason: String },
    #[error("malformed keypoints file: {reason}")]
    MalformedKeypoints { reason: String },
    #[error("{section} `{name}`: link `{link}` is not in the URDF")]
    KeypointUnknownLink { section: &'static str, name: String, link: String },
    #[error("{section} `{name}` is defined more than once")]
    DuplicateKeypoint { section: &'static str, name: String },
    #[error("palm_normal {normal:?} is not a nonzero finite vector")]
    InvalidPalmNormal { normal: [f64; 3] },
    #[error("open_hand, joint `{joint}`: {reason}")]
    InvalidOpenHand { joint: String, reason: String },
}

/// How a joint moves.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum JointKind {
    Fixed,
    /// Rotation about the axis, within finite limits.
    Revolute,
    /// Rotation about the axis, unlimited.
    Continuous,
    /// Translation along the axis (metres), within finite limits.
    Prismatic,
}

/// What sets a joint's position.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum JointDrive {
    /// Does not move.
    Fixed,
    /// An independent degree of freedom: component `index` of the actuated vector.
    Actuated { index: usize },
    /// Follows an actuated joint (URDF `<mimic>`):
    /// q = multiplier · q_actuated\[driver\] + offset.
    Mimic { driver: usize, multiplier: f64, offset: f64 },
}

/// A joint of the tree.
#[derive(Clone, Debug)]
pub struct Joint {
    pub name: String,
    pub kind: JointKind,
    pub parent: LinkId,
    pub child: LinkId,
    /// The joint frame in the parent link frame (URDF `<origin>`); the child
    /// link frame coincides with it at q = 0.
    pub origin: Isometry3<f64>,
    /// Unit axis in the joint frame (unused for fixed joints).
    pub axis: Unit<Vector3<f64>>,
    /// Position limits (rad or m); ±∞ for continuous joints, 0 for fixed ones.
    pub lower: f64,
    pub upper: f64,
    pub drive: JointDrive,
    /// Index in the full joint-position vector (every non-fixed joint, in
    /// file order); `None` for fixed joints.
    pub position_index: Option<usize>,
}

/// A rigid body of the tree.
#[derive(Clone, Debug)]
pub struct Link {
    pub name: String,
    /// The joint whose child this link is; `None` for the root (the palm).
    pub parent_joint: Option<JointId>,
}

/// A collision primitive in its own frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum CollisionShape {
    /// Centred box.
    Box {
        half_extents: Vector3<f64>,
    },
    Sphere {
        radius: f64,
    },
    /// Centred cylinder, axis along its frame's z (the URDF convention).
    Cylinder {
        radius: f64,
        half_length: f64,
    },
}

/// A collision primitive attached to a link.
#[derive(Clone, Debug)]
pub struct CollisionPrimitive {
    pub link: LinkId,
    /// URDF `<collision name=...>`, if any.
    pub name: Option<String>,
    /// The primitive's frame in the link frame.
    pub origin: Isometry3<f64>,
    pub shape: CollisionShape,
}

/// A hand: kinematic tree, couplings, collision primitives, task-space
/// keypoints. Immutable after loading; the per-configuration state lives in
/// [`super::HandKinematics`].
#[derive(Clone, Debug)]
pub struct HandModel {
    name: String,
    links: Vec<Link>,
    joints: Vec<Joint>,
    root: LinkId,
    /// Every link, each after its parent (forward kinematics order).
    link_order: Vec<LinkId>,
    /// Non-fixed joints in file order: the full joint-position vector.
    moving_joints: Vec<JointId>,
    /// Actuated joints in file order: the actuated vector.
    actuated_joints: Vec<JointId>,
    /// Limits of each actuated joint, narrowed by those of its mimic followers.
    actuated_limits: Vec<[f64; 2]>,
    collisions: Vec<CollisionPrimitive>,
    keypoints: Vec<Keypoint>,
    fingertips: Vec<Keypoint>,
    palm_normal: Unit<Vector3<f64>>,
    open_hand: Vec<f64>,
}

/// Directory of the bundled SIH model, fixed at compile time.
pub const SIH_ASSET_DIR: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../assets/hands/sih_right");

impl HandModel {
    /// Loads a hand from a URDF file and its keypoints file (format: see
    /// `assets/hands/sih_right/README.md`).
    pub fn from_urdf_file(
        urdf_path: impl AsRef<Path>,
        keypoints_path: impl AsRef<Path>,
    ) -> Result<Self, HandModelError> {
        let read = |p: &Path| {
            std::fs::read_to_string(p).map_err(|source| HandModelError::Io { path: p.to_path_buf(), source })
        };
        let urdf = read(urdf_path.as_ref())?;
        let keypoints = read(keypoints_path.as_ref())?;
        Self::from_urdf_str_in(&urdf, &keypoints, urdf_path.as_ref().parent())
    }

    /// Loads a hand from URDF text and keypoints JSON text (collision mesh
    /// files relative to the current directory).
    pub fn from_urdf_str(urdf: &str, keypoints_json: &str) -> Result<Self, HandModelError> {
        Self::from_urdf_str_in(urdf, keypoints_json, None)
    }

    /// [`Self::from_urdf_str`] with collision mesh files found relative to
    /// `mesh_dir` (the URDF's directory; see
    /// [`super::mesh_collision::resolve_mesh_path`]).
    pub fn from_urdf_str_in(urdf: &str, keypoints_json: &str, mesh_dir: Option<&Path>) -> Result<Self, HandModelError> {
        // urdf-rs goes through two XML libraries; a panic in either must not
        // take the daemon down on a bad file, so it is caught and reported.
        let parsed = std::panic::catch_unwind(|| urdf_rs::read_from_string(urdf))
            .map_err(|_| HandModelError::MalformedUrdf { reason: "the URDF parser panicked on this input".into() })?;
        let robot = parsed.map_err(|e| HandModelError::MalformedUrdf { reason: e.to_string() })?;
        let mut model = build_tree(&robot, mesh_dir)?;
        let file = parse_keypoints_json(keypoints_json, &model)?;
        model.keypoints = file.keypoints;
        model.fingertips = file.fingertips;
        model.palm_normal = file.palm_normal;
        model.open_hand = file.open_hand;
        Ok(model)
    }

    /// The bundled right Schunk SIH-like hand (`assets/hands/sih_right`).
    pub fn default_sih() -> Result<Self, HandModelError> {
        let dir = Path::new(SIH_ASSET_DIR);
        Self::from_urdf_file(dir.join("sih_right.urdf"), dir.join("keypoints.json"))
    }

    /// URDF `<robot name=...>`.
    pub fn name(&self) -> &str {
        &self.name
    }
    pub fn links(&self) -> &[Link] {
        &self.links
    }
    /// All joints, fixed ones included, in file order.
    pub fn joints(&self) -> &[Joint] {
        &self.joints
    }
    /// The base link (the palm); its frame is the wrist pose.
    pub fn root_link(&self) -> LinkId {
        self.root
    }
    /// Links with every parent before its children.
    pub fn link_order(&self) -> &[LinkId] {
        &self.link_order
    }
    pub fn link_index(&self, name: &str) -> Option<LinkId> {
        self.links.iter().position(|l| l.name == name)
    }
    pub fn joint_index(&self, name: &str) -> Option<JointId> {
        self.joints.iter().position(|j| j.name == name)
    }
    /// Non-fixed joints (actuated and mimic) in file order: the order of
    /// [`super::HandKinematics::joint_positions`].
    pub fn moving_joints(&self) -> &[JointId] {
        &self.moving_joints
    }
    /// Actuated joints in file order: the order of the actuated vector q_a.
    pub fn actuated_joints(&self) -> &[JointId] {
        &self.actuated_joints
    }
    pub fn num_actuated(&self) -> usize {
        self.actuated_joints.len()
    }
    pub fn actuated_names(&self) -> impl Iterator<Item = &str> + '_ {
        self.actuated_joints.iter().map(|&j| self.joints[j].name.as_str())
    }
    /// [lower, upper] of each actuated joint, intersected with the ranges its
    /// mimic followers allow (a follower at its limit stops the driver).
    pub fn actuated_limits(&self) -> &[[f64; 2]] {
        &self.actuated_limits
    }
    /// Clamps an actuated vector into [`Self::actuated_limits`].
    pub fn clamp_actuated(&self, q_actuated: &mut [f64]) {
        for (q, [lo, hi]) in q_actuated.iter_mut().zip(&self.actuated_limits) {
            *q = q.clamp(*lo, *hi);
        }
    }
    /// Expands an actuated vector into the full joint-position vector
    /// (order of [`Self::moving_joints`]) through the mimic couplings.
    pub fn expand_joint_positions(&self, q_actuated: &[f64], q_full: &mut [f64]) {
        assert_eq!(q_actuated.len(), self.actuated_joints.len(), "actuated vector length");
        assert_eq!(q_full.len(), self.moving_joints.len(), "full joint vector length");
        for (q, &j) in q_full.iter_mut().zip(&self.moving_joints) {
            *q = match self.joints[j].drive {
                JointDrive::Actuated { index } => q_actuated[index],
                JointDrive::Mimic { driver, multiplier, offset } => multiplier * q_actuated[driver] + offset,
                JointDrive::Fixed => 0.0,
            };
        }
    }
    /// Collision primitives of all links, links in file order.
    pub fn collision_primitives(&self) -> &[CollisionPrimitive] {
        &self.collisions
    }
    /// The task-space keypoints, in file order.
    pub fn keypoints(&self) -> &[Keypoint] {
        &self.keypoints
    }
    pub fn keypoint_index(&self, name: &str) -> Option<usize> {
        self.keypoints.iter().position(|k| k.name == name)
    }
    /// Fingertip points, for contact checks.
    pub fn fingertips(&self) -> &[Keypoint] {
        &self.fingertips
    }
    /// Outward normal of the palmar surface in the root (palm) frame.
    pub fn palm_normal(&self) -> Unit<Vector3<f64>> {
        self.palm_normal
    }
    /// The open-hand actuated configuration (pre-grasp start).
    pub fn open_hand(&self) -> &[f64] {
        &self.open_hand
    }
}

fn finite3(v: &[f64; 3], element: impl FnOnce() -> String, what: &'static str) -> Result<(), HandModelError> {
    if v.iter().all(|x| x.is_finite()) {
        Ok(())
    } else {
        Err(HandModelError::NonFinite { element: element(), what })
    }
}

fn pose_to_isometry(pose: &urdf_rs::Pose, element: impl Fn() -> String) -> Result<Isometry3<f64>, HandModelError> {
    finite3(&pose.xyz.0, &element, "origin xyz")?;
    finite3(&pose.rpy.0, &element, "origin rpy")?;
    let [x, y, z] = pose.xyz.0;
    let [roll, pitch, yaw] = pose.rpy.0;
    // URDF rpy are fixed-axis X, Y, Z rotations: R = Rz(yaw)·Ry(pitch)·Rx(roll),
    // which is what nalgebra's from_euler_angles builds.
    Ok(Isometry3::from_parts(Translation3::new(x, y, z), UnitQuaternion::from_euler_angles(roll, pitch, yaw)))
}

/// Converts the parsed URDF into our tree and checks it.
fn build_tree(robot: &urdf_rs::Robot, mesh_dir: Option<&Path>) -> Result<HandModel, HandModelError> {
    if robot.links.is_empty() {
        return Err(HandModelError::NoLinks { robot: robot.name.clone() });
    }
    let mut link_ids: HashMap<&str, LinkId> = HashMap::new();
    let mut links = Vec::with_capacity(robot.links.len());
    for l in &robot.links {
        if link_ids.insert(l.name.as_str(), links.len()).is_some() {
            return Err(HandModelError::DuplicateLink { link: l.name.clone() });
        }
        links.push(Link { name: l.name.clone(), parent_joint: None });
    }

    // Joints: topology, kind, origin, axis, limits. Drives come after, once
    // every joint is known (a mimic may name a joint further down the file).
    let mut joint_ids: HashMap<&str, JointId> = HashMap::new();
    let mut joints: Vec<Joint> = Vec::with_capacity(robot.joints.len());
    for uj in &robot.joints {
        let name = uj.name.clone();
        if joint_ids.insert(uj.name.as_str(), joints.len()).is_some() {
            return Err(HandModelError::DuplicateJoint { joint: name });
        }
        let find = |role: &'static str, link: &str| {
            link_ids.get(link).copied().ok_or_else(|| HandModelError::MissingLink {
                joint: uj.name.clone(),
                role,
                link: link.to_owned(),
            })
        };
        let parent = find("parent", &uj.parent.link)?;
        let child = find("child", &uj.child.link)?;
        if let Some(first) = links[child].parent_joint {
            return Err(HandModelError::MultipleParents {
                link: links[child].name.clone(),
                first: joints[first].name.clone(),
                second: name,
            });
        }
        links[child].parent_joint = Some(joints.len());

        let kind = match uj.joint_type {
            urdf_rs::JointType::Fixed => JointKind::Fixed,
            urdf_rs::JointType::Revolute => JointKind::Revolute,
            urdf_rs::JointType::Continuous => JointKind::Continuous,
            urdf_rs::JointType::Prismatic => JointKind::Prismatic,
            ref other => {
                return Err(HandModelError::UnsupportedJointType {
                    joint: name,
                    kind: format!("{other:?}").to_lowercase(),
                })
            }
        };
        let origin = pose_to_isometry(&uj.origin, || format!("joint `{}`", uj.name))?;

        let raw_axis = uj.axis.xyz.0;
        let axis = if kind == JointKind::Fixed {
            // A fixed joint's axis is meaningless; do not reject a file over it.
            Vector3::x_axis()
        } else {
            let v = Vector3::from(raw_axis);
            let n = v.norm();
            if !n.is_finite() || n < 1e-9 {
                return Err(HandModelError::InvalidAxis { joint: name, axis: raw_axis });
            }
            Unit::new_unchecked(v / n)
        };

        let (lower, upper) = match kind {
            JointKind::Fixed => (0.0, 0.0),
            JointKind::Continuous => (f64::NEG_INFINITY, f64::INFINITY),
            JointKind::Revolute | JointKind::Prismatic => {
                let (lo, hi) = (uj.limit.lower, uj.limit.upper);
                let bad = |reason| HandModelError::InvalidLimits { joint: name.clone(), lower: lo, upper: hi, reason };
                if !lo.is_finite() || !hi.is_finite() {
                    return Err(bad("limits must be finite (use type=\"continuous\" for an unlimited joint)"));
                }
                if lo > hi {
                    return Err(bad("lower limit above upper limit"));
                }
                if lo == hi {
                    // Also what an omitted <limit> reads as in URDF 1.0.
                    return Err(bad("zero-width limits (missing <limit>?)"));
                }
                (lo, hi)
            }
        };

        joints.push(Joint {
            name,
            kind,
            parent,
            child,
            origin,
            axis,
            lower,
            upper,
            drive: JointDrive::Fixed,
            position_index: None,
        });
    }

    let (root, link_order) = find_root_and_order(&links, &joints)?;

    // Drives: first the independent joints, in file order...
    let mut moving_joints = Vec::new();
    let mut actuated_joints = Vec::new();
    for (id, (uj, j)) in robot.joints.iter().zip(joints.iter_mut()).enumerate() {
        if j.kind == JointKind::Fixed {
            continue;
        }
        j.position_index = Some(moving_joints.len());
        moving_joints.push(id);
        if uj.mimic.is_none() {
            j.drive = JointDrive::Actuated { index: actuated_joints.len() };
            actuated_joints.push(id);
        }
    }
    // ...then the followers, each pointing at an independent joint.
    for id in 0..joints.len() {
        let Some(mimic) = &robot.joints[id].mimic else { continue };
        if joints[id].kind == JointKind::Fixed {
            // A fixed joint cannot follow anything; the tag has no effect.
            continue;
        }
        let name = joints[id].name.clone();
        let target_id = *joint_ids
            .get(mimic.joint.as_str())
            .ok_or_else(|| HandModelError::MimicUnknownJoint { joint: name.clone(), target: mimic.joint.clone() })?;
        if target_id == id {
            return Err(HandModelError::MimicSelf { joint: name });
        }
        let target = &robot.joints[target_id];
        if let Some(tm) = &target.mimic {
            return Err(HandModelError::MimicOfMimic {
                joint: name,
                target: target.name.clone(),
                target_driver: tm.joint.clone(),
            });
        }
        let JointDrive::Actuated { index: driver } = joints[target_id].drive else {
            return Err(HandModelError::MimicOfFixed { joint: name, target: target.name.clone() });
        };
        let multiplier = mimic.multiplier.unwrap_or(1.0);
        let offset = mimic.offset.unwrap_or(0.0);
        if !multiplier.is_finite() {
            return Err(HandModelError::InvalidMimic { joint: name, what: "multiplier" });
        }
        if !offset.is_finite() {
            return Err(HandModelError::InvalidMimic { joint: name, what: "offset" });
        }
        joints[id].drive = JointDrive::Mimic { driver, multiplier, offset };
    }

    let actuated_limits = actuated_limits(&joints, &actuated_joints)?;

    let mut collisions = Vec::new();
    for (link_id, ul) in robot.links.iter().enumerate() {
        for (index, c) in ul.collision.iter().enumerate() {
            convert_collision(link_id, ul, index, c, mesh_dir, &mut collisions)?;
        }
    }

    let n_actuated = actuated_joints.len();
    Ok(HandModel {
        name: robot.name.clone(),
        links,
        joints,
        root,
        link_order,
        moving_joints,
        actuated_joints,
        actuated_limits,
        collisions,
        keypoints: Vec::new(),
        fingertips: Vec::new(),
        palm_normal: Vector3::y_axis(),
        open_hand: vec![0.0; n_actuated],
    })
}

/// The single root, and a parent-before-child order of all links.
fn find_root_and_order(links: &[Link], joints: &[Joint]) -> Result<(LinkId, Vec<LinkId>), HandModelError> {
    let roots: Vec<LinkId> = (0..links.len()).filter(|&l| links[l].parent_joint.is_none()).collect();
    if roots.len() > 1 {
        return Err(HandModelError::MultipleRoots { roots: roots.iter().map(|&l| links[l].name.clone()).collect() });
    }
    let Some(&root) = roots.first() else {
        // Every link has a parent: the parent chains must cycle.
        return Err(HandModelError::KinematicLoop { link: links[0].name.clone() });
    };
    let mut children: Vec<Vec<LinkId>> = vec![Vec::new(); links.len()];
    for j in joints {
        children[j.parent].push(j.child);
    }
    let mut order = Vec::with_capacity(links.len());
    let mut seen = vec![false; links.len()];
    order.push(root);
    seen[root] = true;
    let mut k = 0;
    while k < order.len() {
        for &c in &children[order[k]] {
            if !seen[c] {
                seen[c] = true;
                order.push(c);
            }
        }
        k += 1;
    }
    // With one parent per link, a link the root cannot reach sits on (or
    // below) a cycle of parent links.
    if let Some(l) = seen.iter().position(|s| !s) {
        // Walk up to a link on the cycle itself, for a precise message.
        let mut on_cycle = l;
        for _ in 0..links.len() {
            on_cycle = joints[links[on_cycle].parent_joint.expect("non-root link has a parent")].parent;
        }
        return Err(HandModelError::KinematicLoop { link: links[on_cycle].name.clone() });
    }
    Ok((root, order))
}

/// Actuated limits narrowed by every follower: a follower q_f = m·q_d + o
/// with limits [l, u] confines q_d to [(l − o)/m, (u − o)/m] (swapped for m < 0).
fn actuated_limits(joints: &[Joint], actuated: &[JointId]) -> Result<Vec<[f64; 2]>, HandModelError> {
    let mut limits: Vec<[f64; 2]> = actuated.iter().map(|&j| [joints[j].lower, joints[j].upper]).collect();
    for j in joints {
        if let JointDrive::Mimic { driver, multiplier, offset } = j.drive {
            if multiplier == 0.0 {
                continue;
            }
            let a = (j.lower - offset) / multiplier;
            let b = (j.upper - offset) / multiplier;
            let (lo, hi) = if a <= b { (a, b) } else { (b, a) };
            let lim = &mut limits[driver];
            lim[0] = lim[0].max(lo);
            lim[1] = lim[1].min(hi);
        }
    }
    for (lim, &j) in limits.iter().zip(actuated) {
        // An unlimited driver followed by nothing keeps [−∞, ∞]; only an empty
        // or single-point range is an error.
        if lim[0] >= lim[1] {
            return Err(HandModelError::InconsistentMimicLimits {
                joint: joints[j].name.clone(),
                lower: lim[0],
                upper: lim[1],
            });
        }
    }
    Ok(limits)
}

fn convert_collision(
    link: LinkId,
    ul: &urdf_rs::Link,
    index: usize,
    c: &urdf_rs::Collision,
    mesh_dir: Option<&Path>,
    out: &mut Vec<CollisionPrimitive>,
) -> Result<(), HandModelError> {
    let bad = |reason: String| HandModelError::InvalidCollision { link: ul.name.clone(), index, reason };
    let origin = pose_to_isometry(&c.origin, || format!("link `{}`, collision {index}", ul.name))?;
    let positive = |what: &str, v: f64| {
        if v.is_finite() && v > 0.0 {
            Ok(v)
        } else {
            Err(bad(format!("{what} {v} is not a positive finite length")))
        }
    };
    let mut push = |origin: Isometry3<f64>, shape: CollisionShape| {
        out.push(CollisionPrimitive { link, name: c.name.clone(), origin, shape });
    };
    // Our primitives have no capsule: a cylinder along the frame's z and a
    // sphere at each end (one sphere where the segment has no length).
    let mut push_capsule = |frame: Isometry3<f64>, radius: f64, half_length: f64| {
        if half_length > 0.0 {
            push(frame, CollisionShape::Cylinder { radius, half_length });
            for s in [-1.0, 1.0] {
                push(frame * Translation3::new(0.0, 0.0, s * half_length), CollisionShape::Sphere { radius });
            }
        } else {
            push(frame, CollisionShape::Sphere { radius });
        }
    };
    match &c.geometry {
        urdf_rs::Geometry::Box { size } => {
            let [x, y, z] = size.0;
            let half_extents = Vector3::new(positive("box x", x)?, positive("box y", y)?, positive("box z", z)?) / 2.0;
            push(origin, CollisionShape::Box { half_extents });
        }
        urdf_rs::Geometry::Sphere { radius } => {
            push(origin, CollisionShape::Sphere { radius: positive("sphere radius", *radius)? });
        }
        urdf_rs::Geometry::Cylinder { radius, length } => {
            let radius = positive("cylinder radius", *radius)?;
            let half_length = positive("cylinder length", *length)? / 2.0;
            push(origin, CollisionShape::Cylinder { radius, half_length });
        }
        urdf_rs::Geometry::Capsule { radius, length } => {
            // URDF 1.2 capsule: `length` is the cylindrical part along z.
            let radius = positive("capsule radius", *radius)?;
            let half_length = positive("capsule length", *length)? / 2.0;
            push_capsule(origin, radius, half_length);
        }
        urdf_rs::Geometry::Mesh { filename, scale } => {
            // The capsule enclosing the mesh (`mesh_collision`): a part of
            // the hand dropped, or shrunk, would pass through tools unnoticed.
            let path = super::mesh_collision::resolve_mesh_path(filename, mesh_dir);
            let loaded = crate::io::read_mesh(&path).map_err(|e| {
                bad(format!(
                    "mesh `{filename}` ({}): {e}; OBJ and STL meshes are read, or describe the shape with box, sphere, cylinder or capsule",
                    path.display()
                ))
            })?;
            let s = scale.map_or([1.0; 3], |s| s.0);
            if !s.iter().all(|v| v.is_finite() && *v != 0.0) {
                return Err(bad(format!("mesh `{filename}`: scale {s:?} is not finite and nonzero")));
            }
            let points: Vec<Vector3<f64>> =
                loaded.mesh.vertices.iter().map(|p| Vector3::new(s[0] * p.x, s[1] * p.y, s[2] * p.z)).collect();
            let capsule = super::mesh_collision::enclosing_capsule(&points)
                .ok_or_else(|| bad(format!("mesh `{filename}` ({}): no finite vertices", path.display())))?;
            tracing::info!(
                "link `{}`: collision mesh `{filename}` taken as the capsule enclosing it (radius {:.1} mm, segment {:.1} mm)",
                ul.name,
                1e3 * capsule.radius,
                2e3 * capsule.half_length
            );
            push_capsule(origin * capsule.frame, capsule.radius, capsule.half_length);
        }
    }
    Ok(())
}
