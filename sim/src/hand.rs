//! The hand in MuJoCo, generated from graspd's hand model (URDF + keypoints
//! file, [`graspd::hand::HandModel`]), so the simulator and the grasp solver
//! share one description of the hand:
//!
//! - one body per link, in the kinematic tree's order; hinge (revolute,
//!   continuous) or slide (prismatic) joints at the link frames, fixed joints
//!   as rigidly attached bodies;
//! - collision geoms from the URDF's collision primitives (a cylinder with a
//!   sphere of its radius at each end, as our URDF writes a capsule, becomes
//!   one MuJoCo capsule: the same solid, and a cheaper contact);
//! - one equality constraint per mimic joint, q_f = offset + multiplier·q_d
//!   (MuJoCo's `polycoef`);
//! - a position servo on each actuated joint, its control range the
//!   actuated limits (narrowed by the followers, as the grasp solver uses);
//! - a site per task-space keypoint (`kp_<name>`) and fingertip (`tip_<name>`);
//! - the root link (the palm, whose frame is the wrist pose) on a free joint,
//!   welded to a mocap body `wrist_target`: moving the mocap body is the arm's
//!   end-effector control (the paper's UR5e).
//!
//! Masses and inertias are the URDF's `<inertial>` elements (the graspd hand
//! model does not carry them, so the URDF is read a second time here); a link
//! without one gets its inertia from its geoms at MuJoCo's default density.
//!
//! The hand does not collide with itself (the grasp solver does not model
//! finger-finger contact either, and the SIH's coupled fingers hardly meet);
//! it collides with tools and the table (see [`crate::mjcf::HAND_CONTYPE`]).

use std::fmt::Write as _;
use std::path::Path;

use graspd::hand::{CollisionShape, HandModel, JointDrive, JointKind, LinkId, SIH_ASSET_DIR};
use mujoco_rs::prelude::{MjData, MjModel, MjtObjBase};
use mujoco_rs::wrappers::mj_model::traits::ModelType;
use nalgebra::{Isometry3, Point3, Quaternion, Translation3, UnitQuaternion};

use crate::engine::SimError;
use crate::mjcf::{esc, num, nums, pose_attrs, vec3, HAND_CONAFFINITY, HAND_CONTYPE};

/// Name of the mocap body the wrist is welded to.
pub const WRIST_TARGET_BODY: &str = "wrist_target";
/// Name of the palm's free joint.
pub const WRIST_FREE_JOINT: &str = "wrist_free";
/// Name of the weld between the mocap body and the palm.
pub const WRIST_WELD: &str = "wrist_weld";

/// A link's mass properties from the URDF.
#[derive(Clone, Debug, PartialEq)]
pub struct LinkInertial {
    /// The inertia frame in the link frame (URDF `<inertial><origin>`).
    pub origin: Isometry3<f64>,
    /// kg.
    pub mass: f64,
    /// kg·m², about the inertia frame: ixx, iyy, izz, ixy, ixz, iyz (MJCF's
    /// `fullinertia` order).
    pub inertia: [f64; 6],
}

/// graspd's hand model with the mass properties the simulator also needs.
#[derive(Clone, Debug)]
pub struct HandAsset {
    model: HandModel,
    /// Per link (index: [`LinkId`]); `None` where the URDF gives no inertial.
    inertials: Vec<Option<LinkInertial>>,
}

impl HandAsset {
    /// The bundled right SIH-like hand (`assets/hands/sih_right`).
    pub fn default_sih() -> Result<Self, SimError> {
        let dir = Path::new(SIH_ASSET_DIR);
        Self::from_files(dir.join("sih_right.urdf"), dir.join("keypoints.json"))
    }

    pub fn from_files(urdf_path: impl AsRef<Path>, keypoints_path: impl AsRef<Path>) -> Result<Self, SimError> {
        let read =
            |p: &Path| std::fs::read_to_string(p).map_err(|source| SimError::Io { path: p.to_path_buf(), source });
        let urdf_path = urdf_path.as_ref();
        Self::from_strs_in(&read(urdf_path)?, &read(keypoints_path.as_ref())?, urdf_path.parent())
    }

    /// From URDF text and keypoints JSON text.
    pub fn from_strs(urdf: &str, keypoints_json: &str) -> Result<Self, SimError> {
        Self::from_strs_in(urdf, keypoints_json, None)
    }

    /// [`Self::from_strs`] with collision mesh files relative to `mesh_dir`.
    pub fn from_strs_in(urdf: &str, keypoints_json: &str, mesh_dir: Option<&Path>) -> Result<Self, SimError> {
        let model = HandModel::from_urdf_str_in(urdf, keypoints_json, mesh_dir)?;
        // The model above parsed the same text, so this parse succeeds; the
        // guard is for the XML libraries' panics, as in graspd's loader.
        let robot = std::panic::catch_unwind(|| urdf_rs::read_from_string(urdf))
            .map_err(|_| SimError::Hand(malformed("the URDF parser panicked on this input")))?
            .map_err(|e| SimError::Hand(malformed(&e.to_string())))?;
        let mut inertials = vec![None; model.links().len()];
        for link in &robot.links {
            let Some(id) = model.link_index(&link.name) else { continue };
            inertials[id] = link_inertial(link)?;
        }
        Ok(Self { model, inertials })
    }

    pub fn model(&self) -> &HandModel {
        &self.model
    }

    /// The URDF's mass properties of a link, if it has any.
    pub fn inertial(&self, link: LinkId) -> Option<&LinkInertial> {
        self.inertials.get(link).and_then(Option::as_ref)
    }
}

fn malformed(reason: &str) -> graspd::hand::HandModelError {
    graspd::hand::HandModelError::MalformedUrdf { reason: reason.to_owned() }
}

fn link_inertial(link: &urdf_rs::Link) -> Result<Option<LinkInertial>, SimError> {
    let i = &link.inertial;
    let t = &i.inertia;
    let inertia = [t.ixx, t.iyy, t.izz, t.ixy, t.ixz, t.iyz];
    // urdf-rs reads a missing <inertial> as all zeros.
    if i.mass.value == 0.0 && inertia.iter().all(|&v| v == 0.0) {
        return Ok(None);
    }
    let bad = |reason: String| SimError::Inertial { link: link.name.clone(), reason };
    if !(i.mass.value.is_finite() && i.mass.value > 0.0) {
        return Err(bad(format!("mass {} is not a positive finite number", i.mass.value)));
    }
    if !inertia.iter().all(|v| v.is_finite()) {
        return Err(bad("inertia is not finite".into()));
    }
    let [x, y, z] = i.origin.xyz.0;
    let [roll, pitch, yaw] = i.origin.rpy.0;
    if ![x, y, z, roll, pitch, yaw].iter().all(|v| v.is_finite()) {
        return Err(bad("origin is not finite".into()));
    }
    // URDF rpy: fixed-axis X, Y, Z, i.e. Rz·Ry·Rx, nalgebra's from_euler_angles.
    let origin = Isometry3::from_parts(Translation3::new(x, y, z), UnitQuaternion::from_euler_angles(roll, pitch, yaw));
    Ok(Some(LinkInertial { origin, mass: i.mass.value, inertia }))
}

/// Drive, contact and wrist settings of the generated hand.
#[derive(Clone, Debug, PartialEq)]
pub struct HandMjcfOptions {
    /// Position-servo stiffness of each actuated joint, N·m/rad.
    pub kp: f64,
    /// Torque limit of each servo, N·m.
    pub force_limit: f64,
    /// Viscous damping of every joint, N·m·s/rad.
    pub joint_damping: f64,
    /// Rotor inertia added to every joint, kg·m². Keeps the light phalanges
    /// (~1e-5 kg·m²) stable under the servos at the 1/120 s timestep (the
    /// stiffness term is explicit even with the implicit integrator).
    pub armature: f64,
    /// Sliding, torsional, rolling friction of the hand's geoms (MuJoCo takes
    /// the larger of the two geoms' values per contact).
    pub friction: [f64; 3],
    /// Contact dimensionality of the hand's geoms: 4 adds torsional friction,
    /// which stops a pinched tool spinning about the contact normal.
    pub condim: u32,
    /// Time constant and damping ratio of the wrist weld (MuJoCo `solref`).
    pub weld_solref: [f64; 2],
    /// Cancel gravity on the hand's bodies: the arm carries the hand and the
    /// finger drives their own phalanges; what is simulated is the hand-tool
    /// interaction.
    pub gravity_compensation: bool,
}

impl Default for HandMjcfOptions {
    /// Servo gains from the scripted mug lift (`sim lift`, canonical and 10
    /// training mugs): kp 4 N·m/rad with a 2 N·m limit held 9 of 11; kp 2
    /// (limit 1, the authors' ±1) held 8, kp 6 held 9, and commanding harder
    /// squeezes pushed the mugs over more often than it held them.
    fn default() -> Self {
        Self {
            kp: 4.0,
            force_limit: 2.0,
            joint_damping: 0.1,
            armature: 0.002,
            friction: [1.0, 0.005, 0.0001],
            condim: 4,
            weld_solref: [0.02, 1.0],
            gravity_compensation: true,
        }
    }
}

/// The hand's MJCF elements, to be placed into a document's sections.
#[derive(Clone, Debug)]
pub struct HandMjcf {
    /// The mocap body and the hand's body tree (two `<worldbody>` children).
    pub bodies: Vec<String>,
    pub equality: Vec<String>,
    pub actuator: Vec<String>,
}

/// Generates the hand, its wrist at `wrist` (the palm frame in the world).
pub fn hand_mjcf(asset: &HandAsset, opts: &HandMjcfOptions, wrist: &Isometry3<f64>) -> HandMjcf {
    let model = &asset.model;
    let mut tree = String::new();
    write_body(asset, opts, model.root_link(), None, wrist, 0, &mut tree);

    let mut equality = vec![format!(
        r#"<weld name="{WRIST_WELD}" body1="{WRIST_TARGET_BODY}" body2="{}" relpose="0 0 0 1 0 0 0" solref="{}"/>"#,
        esc(&model.links()[model.root_link()].name),
        nums(&opts.weld_solref)
    )];
    let joints = model.joints();
    for j in joints {
        if let JointDrive::Mimic { driver, multiplier, offset } = j.drive {
            let driver_name = &joints[model.actuated_joints()[driver]].name;
            // joint1 − qpos0 = polycoef(joint2 − qpos0); both reference
            // positions are 0 here (no `ref` is written).
            equality.push(format!(
                r#"<joint name="couple_{}" joint1="{}" joint2="{}" polycoef="{} {} 0 0 0"/>"#,
                esc(&j.name),
                esc(&j.name),
                esc(driver_name),
                num(offset),
                num(multiplier)
            ));
        }
    }

    let actuator = model
        .actuated_joints()
        .iter()
        .zip(model.actuated_limits())
        .map(|(&j, &[lo, hi])| {
            let name = esc(&joints[j].name);
            let range = if lo.is_finite() && hi.is_finite() {
                format!(r#" ctrlrange="{} {}""#, num(lo), num(hi))
            } else {
                String::new()
            };
            format!(
                r#"<position name="{name}" joint="{name}" kp="{}"{range} forcerange="{} {}"/>"#,
                num(opts.kp),
                num(-opts.force_limit),
                num(opts.force_limit)
            )
        })
        .collect();

    let mocap = format!(r#"<body name="{WRIST_TARGET_BODY}" mocap="true"{}/>"#, pose_attrs(wrist));
    HandMjcf { bodies: vec![mocap, tree], equality, actuator }
}

/// Writes link `link` (attached to its parent through `joint`, placed at
/// `pose` in the parent body) and its subtree.
fn write_body(
    asset: &HandAsset,
    opts: &HandMjcfOptions,
    link: LinkId,
    joint: Option<usize>,
    pose: &Isometry3<f64>,
    depth: usize,
    out: &mut String,
) {
    let model = &asset.model;
    let pad = "  ".repeat(depth);
    let gravcomp = if opts.gravity_compensation { r#" gravcomp="1""# } else { "" };
    let _ = writeln!(out, r#"{pad}<body name="{}"{}{gravcomp}>"#, esc(&model.links()[link].name), pose_attrs(pose));
    let inner = "  ".repeat(depth + 1);
    match joint.map(|j| &model.joints()[j]) {
        None => {
            let _ = writeln!(out, r#"{inner}<freejoint name="{WRIST_FREE_JOINT}"/>"#);
        }
        Some(j) => {
            let kind = match j.kind {
                JointKind::Fixed => None,
                JointKind::Revolute | JointKind::Continuous => Some("hinge"),
                JointKind::Prismatic => Some("slide"),
            };
            if let Some(kind) = kind {
                let range = if j.lower.is_finite() && j.upper.is_finite() {
                    format!(r#" range="{} {}""#, num(j.lower), num(j.upper))
                } else {
                    String::new()
                };
                let _ = writeln!(
                    out,
                    r#"{inner}<joint name="{}" type="{kind}" axis="{}"{range} damping="{}" armature="{}"/>"#,
                    esc(&j.name),
                    vec3(&j.axis),
                    num(opts.joint_damping),
                    num(opts.armature)
                );
            }
        }
    }
    if let Some(i) = asset.inertial(link) {
        let _ = writeln!(
            out,
            r#"{inner}<inertial{} mass="{}" fullinertia="{}"/>"#,
            pose_attrs(&i.origin),
            num(i.mass),
            nums(&i.inertia)
        );
    }
    for geom in link_geoms(model, link) {
        let _ = writeln!(
            out,
            r#"{inner}<geom {geom} contype="{HAND_CONTYPE}" conaffinity="{HAND_CONAFFINITY}" condim="{}" friction="{}" group="1"/>"#,
            opts.condim,
            nums(&opts.friction)
        );
    }
    for (prefix, points) in [("kp", model.keypoints()), ("tip", model.fingertips())] {
        for k in points.iter().filter(|k| k.link == link) {
            let _ = writeln!(
                out,
                r#"{inner}<site name="{prefix}_{}" pos="{}" size="0.003" group="4"/>"#,
                esc(&k.name),
                vec3(&k.offset)
            );
        }
    }
    for (id, j) in model.joints().iter().enumerate() {
        if j.parent == link {
            write_body(asset, opts, j.child, Some(id), &j.origin, depth + 1, out);
        }
    }
    let _ = writeln!(out, "{pad}</body>");
}

/// How far a sphere's centre may sit from a cylinder's end, metres, for the
/// pair to be read as one capsule (the URDF's rpy are written to 1e-9 rad).
const CAPSULE_TOLERANCE_M: f64 = 1e-6;

/// The `type`/`size`/`pos`/`quat` attributes of a link's collision geoms,
/// capsules recognised.
fn link_geoms(model: &HandModel, link: LinkId) -> Vec<String> {
    let prims: Vec<_> = model.collision_primitives().iter().filter(|c| c.link == link).collect();
    let mut used = vec![false; prims.len()];
    let mut out = Vec::new();
    for (i, c) in prims.iter().enumerate() {
        let CollisionShape::Cylinder { radius, half_length } = c.shape else { continue };
        let ends = [-1.0, 1.0].map(|s| c.origin * Point3::new(0.0, 0.0, s * half_length));
        let cap = ends.map(|end| {
            prims.iter().enumerate().position(|(k, p)| {
                !used[k]
                    && matches!(p.shape, CollisionShape::Sphere { radius: r } if (r - radius).abs() < 1e-12)
                    && (Point3::from(p.origin.translation.vector) - end).norm() < CAPSULE_TOLERANCE_M
            })
        });
        if let [Some(a), Some(b)] = cap {
            if a != b {
                used[i] = true;
                used[a] = true;
                used[b] = true;
                out.push(format!(
                    r#"type="capsule" size="{} {}"{}"#,
                    num(radius),
                    num(half_length),
                    pose_attrs(&c.origin)
                ));
            }
        }
    }
    for (c, _) in prims.iter().zip(&used).filter(|(_, u)| !**u) {
        let shape = match c.shape {
            CollisionShape::Box { half_extents } => format!(r#"type="box" size="{}""#, vec3(&half_extents)),
            CollisionShape::Sphere { radius } => format!(r#"type="sphere" size="{}""#, num(radius)),
            CollisionShape::Cylinder { radius, half_length } => {
                format!(r#"type="cylinder" size="{} {}""#, num(radius), num(half_length))
            }
        };
        out.push(format!("{shape}{}", pose_attrs(&c.origin)));
    }
    out
}

/// Where the hand's parts live in a compiled model: resolved once by name,
/// then used to read and write the state without lookups.
#[derive(Clone, Debug)]
pub struct HandIndex {
    /// Body id of the root link (the palm).
    pub palm_body: usize,
    /// qpos address of the palm's free joint (position, then quaternion w, x, y, z).
    pub wrist_qpos: usize,
    /// qvel address of the palm's free joint (6 dofs).
    pub wrist_dof: usize,
    /// Index into mocap_pos / mocap_quat of the wrist target.
    pub mocap: usize,
    /// qpos address of each moving joint (order of [`HandModel::moving_joints`]).
    pub joint_qpos: Vec<usize>,
    /// qvel address of each moving joint.
    pub joint_dof: Vec<usize>,
    /// Actuator id of each actuated joint (order of [`HandModel::actuated_joints`]).
    pub actuators: Vec<usize>,
    /// Site id of each task-space keypoint, in the hand model's order.
    pub keypoint_sites: Vec<usize>,
    /// Site id of each fingertip.
    pub fingertip_sites: Vec<usize>,
    /// Body id of every link (index: [`LinkId`]).
    pub link_bodies: Vec<usize>,
}

fn find(model: &MjModel, kind: MjtObjBase, what: &'static str, name: &str) -> Result<usize, SimError> {
    model.name_to_id(kind, name).ok_or_else(|| SimError::MissingElement { kind: what, name: name.to_owned() })
}

impl HandIndex {
    /// Finds the hand generated by [`hand_mjcf`] in a compiled model.
    pub fn new(model: &MjModel, hand: &HandModel) -> Result<Self, SimError> {
        let body = |name: &str| find(model, MjtObjBase::mjOBJ_BODY, "body", name);
        let joint = |name: &str| find(model, MjtObjBase::mjOBJ_JOINT, "joint", name);
        let site = |name: String| find(model, MjtObjBase::mjOBJ_SITE, "site", &name);
        let palm_body = body(&hand.links()[hand.root_link()].name)?;
        let free = joint(WRIST_FREE_JOINT)?;
        let target = body(WRIST_TARGET_BODY)?;
        let mocap = usize::try_from(model.body_mocapid()[target])
            .map_err(|_| SimError::MissingElement { kind: "mocap body", name: WRIST_TARGET_BODY.into() })?;
        let mut joint_qpos = Vec::new();
        let mut joint_dof = Vec::new();
        for &j in hand.moving_joints() {
            let id = joint(&hand.joints()[j].name)?;
            joint_qpos.push(model.jnt_qposadr()[id] as usize);
            joint_dof.push(model.jnt_dofadr()[id] as usize);
        }
        let actuators = hand
            .actuated_names()
            .map(|n| find(model, MjtObjBase::mjOBJ_ACTUATOR, "actuator", n))
            .collect::<Result<_, _>>()?;
        let keypoint_sites =
            hand.keypoints().iter().map(|k| site(format!("kp_{}", k.name))).collect::<Result<_, _>>()?;
        let fingertip_sites =
            hand.fingertips().iter().map(|k| site(format!("tip_{}", k.name))).collect::<Result<_, _>>()?;
        let link_bodies = hand.links().iter().map(|l| body(&l.name)).collect::<Result<_, _>>()?;
        Ok(Self {
            palm_body,
            wrist_qpos: model.jnt_qposadr()[free] as usize,
            wrist_dof: model.jnt_dofadr()[free] as usize,
            mocap,
            joint_qpos,
            joint_dof,
            actuators,
            keypoint_sites,
            fingertip_sites,
            link_bodies,
        })
    }

    /// Puts the hand at rest at `wrist` with actuated joints `q_actuated`
    /// (followers through the couplings): joint positions, the wrist target,
    /// the servo targets; velocities zero. Call `data.forward()` after the
    /// whole scene is set.
    pub fn set_configuration<M: ModelType>(
        &self,
        data: &mut MjData<M>,
        hand: &HandModel,
        wrist: &Isometry3<f64>,
        q_actuated: &[f64],
    ) {
        let mut q_full = vec![0.0; hand.moving_joints().len()];
        hand.expand_joint_positions(q_actuated, &mut q_full);
        let qpos = data.qpos_mut();
        qpos[self.wrist_qpos..self.wrist_qpos + 7].copy_from_slice(&pose_to_qpos(wrist));
        for (&adr, &q) in self.joint_qpos.iter().zip(&q_full) {
            qpos[adr] = q;
        }
        let qvel = data.qvel_mut();
        qvel[self.wrist_dof..self.wrist_dof + 6].fill(0.0);
        for &adr in &self.joint_dof {
            qvel[adr] = 0.0;
        }
        self.set_wrist_target(data, wrist);
        self.set_joint_targets(data, q_actuated);
    }

    /// Commands the wrist (the arm's end-effector pose).
    pub fn set_wrist_target<M: ModelType>(&self, data: &mut MjData<M>, wrist: &Isometry3<f64>) {
        let q = pose_to_qpos(wrist);
        data.mocap_pos_mut()[self.mocap].copy_from_slice(&q[..3]);
        data.mocap_quat_mut()[self.mocap].copy_from_slice(&q[3..]);
    }

    /// Commands the actuated joints (servo targets, clamped by MuJoCo to the control range).
    pub fn set_joint_targets<M: ModelType>(&self, data: &mut MjData<M>, q_actuated: &[f64]) {
        let ctrl = data.ctrl_mut();
        for (&a, &q) in self.actuators.iter().zip(q_actuated) {
            ctrl[a] = q;
        }
    }

    /// The palm's pose in the world (after `forward` or a step).
    pub fn wrist_pose<M: ModelType>(&self, data: &MjData<M>) -> Isometry3<f64> {
        body_pose(data, self.palm_body)
    }

    /// Actuated joint positions (order of the actuated vector).
    pub fn actuated_positions<M: ModelType>(&self, data: &MjData<M>, hand: &HandModel) -> Vec<f64> {
        hand.actuated_joints()
            .iter()
            .map(|&j| {
                let k = hand.joints()[j].position_index.expect("actuated joints move");
                data.qpos()[self.joint_qpos[k]]
            })
            .collect()
    }

    /// All moving joints' positions (order of [`HandModel::moving_joints`]).
    pub fn joint_positions<M: ModelType>(&self, data: &MjData<M>) -> Vec<f64> {
        self.joint_qpos.iter().map(|&a| data.qpos()[a]).collect()
    }

    /// World positions of the task-space keypoints (after `forward` or a step).
    pub fn keypoints<M: ModelType>(&self, data: &MjData<M>) -> Vec<Point3<f64>> {
        self.keypoint_sites.iter().map(|&s| Point3::from(data.site_xpos()[s])).collect()
    }
}

/// A body's world pose from MuJoCo's xpos / xquat.
pub fn body_pose<M: ModelType>(data: &MjData<M>, body: usize) -> Isometry3<f64> {
    let p = data.xpos()[body];
    let q = data.xquat()[body];
    Isometry3::from_parts(
        Translation3::new(p[0], p[1], p[2]),
        UnitQuaternion::from_quaternion(Quaternion::new(q[0], q[1], q[2], q[3])),
    )
}

/// A pose as a free joint's 7 qpos values (x, y, z, qw, qx, qy, qz).
pub fn pose_to_qpos(pose: &Isometry3<f64>) -> [f64; 7] {
    let t = pose.translation.vector;
    let q = pose.rotation;
    [t.x, t.y, t.z, q.w, q.i, q.j, q.k]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::load_mjcf;
    use crate::mjcf::{MjcfDocument, PhysicsOptions};
    use graspd::hand::HandKinematics;
    use nalgebra::Vector3;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    fn hand_document(asset: &HandAsset, opts: &HandMjcfOptions) -> String {
        let mut doc = MjcfDocument::new("hand", PhysicsOptions::default());
        let h = hand_mjcf(asset, opts, &Isometry3::translation(0.0, 0.0, 0.5));
        doc.worldbody.extend(h.bodies);
        doc.equality.extend(h.equality);
        doc.actuator.extend(h.actuator);
        doc.to_xml()
    }

    fn random_wrist(rng: &mut ChaCha8Rng) -> Isometry3<f64> {
        let t = Vector3::new(rng.random_range(-0.5..0.5), rng.random_range(-0.5..0.5), rng.random_range(0.0..1.0));
        let axis = Vector3::new(rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0));
        let r = UnitQuaternion::from_scaled_axis(axis * rng.random_range(0.0..3.0));
        Isometry3::from_parts(Translation3::from(t), r)
    }

    fn random_actuated(hand: &HandModel, rng: &mut ChaCha8Rng) -> Vec<f64> {
        hand.actuated_limits().iter().map(|&[lo, hi]| rng.random_range(lo..=hi)).collect()
    }

    #[test]
    fn generated_sih_compiles_with_its_parts() {
        let asset = HandAsset::default_sih().unwrap();
        let xml = hand_document(&asset, &HandMjcfOptions::default());
        let model = load_mjcf(&xml).unwrap_or_else(|e| panic!("{e}\n{xml}"));
        let hand = asset.model();
        let index = HandIndex::new(&model, hand).unwrap();
        // 11 hinges + the free joint; 5 servos; 6 couplings + the weld;
        // 12 keypoints + 5 fingertips.
        assert_eq!(model.ffi().njnt, 12);
        assert_eq!(model.ffi().nu as usize, hand.num_actuated());
        assert_eq!(model.ffi().neq, 7);
        assert_eq!(model.ffi().nsite, 17);
        assert_eq!(index.joint_qpos.len(), 11);
        // Every phalanx's cylinder + two spheres became one capsule; the palm keeps its two boxes.
        assert_eq!(model.ffi().ngeom, 2 + 11, "geoms:\n{xml}");
        assert!(xml.matches("type=\"capsule\"").count() == 11, "{xml}");
        // URDF masses reach MuJoCo.
        let palm = index.palm_body;
        assert!((model.body_mass()[palm] - 0.55).abs() < 1e-12);
        let total: f64 = model.body_subtreemass()[palm];
        assert!(total > 0.55 && total < 1.0, "hand mass {total}");
    }

    /// MuJoCo's keypoint sites and graspd's forward kinematics agree for
    /// random wrist poses and joint configurations: the generated tree
    /// (origins, axes, couplings, site offsets) is the hand model's.
    #[test]
    fn keypoint_sites_match_graspd_forward_kinematics() {
        let asset = HandAsset::default_sih().unwrap();
        let hand = asset.model();
        let model = load_mjcf(&hand_document(&asset, &HandMjcfOptions::default())).unwrap();
        let index = HandIndex::new(&model, hand).unwrap();
        let mut data = MjData::new(&model);
        let mut kin = HandKinematics::new(hand);
        let mut rng = ChaCha8Rng::seed_from_u64(6);
        let mut worst: f64 = 0.0;
        for _ in 0..200 {
            let wrist = random_wrist(&mut rng);
            let q = random_actuated(hand, &mut rng);
            index.set_configuration(&mut data, hand, &wrist, &q);
            data.kinematics();
            kin.update(hand, &wrist, &q);
            for (mj, ours) in index.keypoints(&data).iter().zip(kin.keypoints()) {
                worst = worst.max((mj - ours).norm());
            }
            for (&s, ours) in index.fingertip_sites.iter().zip(kin.fingertips()) {
                worst = worst.max((Point3::from(data.site_xpos()[s]) - ours).norm());
            }
            for (l, &b) in index.link_bodies.iter().enumerate() {
                let pose = body_pose(&data, b);
                let ours = kin.link_pose(l);
                worst = worst.max((pose.translation.vector - ours.translation.vector).norm());
                assert!(pose.rotation.angle_to(&ours.rotation) < 1e-6, "link {l} orientation");
            }
        }
        assert!(worst < 1e-3, "largest keypoint / link distance {worst} m");
        // In practice they agree to rounding; a loose bound would hide a wrong offset.
        assert!(worst < 1e-9, "largest keypoint / link distance {worst} m");
    }

    /// Simulated: the servos bring the actuated joints to their targets, the
    /// couplings hold the followers, and the palm follows the mocap target.
    #[test]
    fn servos_couplings_and_wrist_weld_track_their_targets() {
        let asset = HandAsset::default_sih().unwrap();
        let hand = asset.model();
        let model = load_mjcf(&hand_document(&asset, &HandMjcfOptions::default())).unwrap();
        let index = HandIndex::new(&model, hand).unwrap();
        let mut data = MjData::new(&model);
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let start = Isometry3::translation(0.0, 0.0, 0.5);
        index.set_configuration(&mut data, hand, &start, hand.open_hand());
        data.forward();
        let target = random_actuated(hand, &mut rng);
        let wrist_goal = Isometry3::from_parts(
            Translation3::new(0.1, -0.05, 0.6),
            UnitQuaternion::from_euler_angles(0.3, -0.2, 0.5),
        );
        index.set_joint_targets(&mut data, &target);
        index.set_wrist_target(&mut data, &wrist_goal);
        for _ in 0..(2.0 / model.opt().timestep) as usize {
            data.step();
        }
        let q = index.actuated_positions(&data, hand);
        for (k, (a, b)) in q.iter().zip(&target).enumerate() {
            assert!((a - b).abs() < 1e-3, "actuated joint {k}: at {a}, target {b}");
        }
        let mut expected = vec![0.0; hand.moving_joints().len()];
        hand.expand_joint_positions(&q, &mut expected);
        for (k, (a, b)) in index.joint_positions(&data).iter().zip(&expected).enumerate() {
            assert!((a - b).abs() < 1e-3, "moving joint {k}: at {a}, coupling says {b}");
        }
        let wrist = index.wrist_pose(&data);
        let dt = (wrist.translation.vector - wrist_goal.translation.vector).norm();
        assert!(dt < 1e-3, "wrist {dt} m from its target");
        assert!(wrist.rotation.angle_to(&wrist_goal.rotation) < 1e-3);
    }

    #[test]
    fn a_bad_inertial_is_an_error_naming_the_link() {
        let dir = Path::new(SIH_ASSET_DIR);
        let urdf = std::fs::read_to_string(dir.join("sih_right.urdf")).unwrap();
        let keypoints = std::fs::read_to_string(dir.join("keypoints.json")).unwrap();
        let bad = urdf.replacen(r#"<mass value="0.55"/>"#, r#"<mass value="-1"/>"#, 1);
        assert_ne!(bad, urdf);
        let err = HandAsset::from_strs(&bad, &keypoints).unwrap_err().to_string();
        assert!(err.contains("palm") && err.contains("mass"), "{err}");
    }
}
