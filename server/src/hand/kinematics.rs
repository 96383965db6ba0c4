//! Forward kinematics and analytic Jacobians of a [`HandModel`].
//!
//! Inputs: the wrist pose (the root link's frame in the world) and the
//! actuated vector q_a (order: [`HandModel::actuated_joints`], i.e. file order
//! of the non-mimic moving joints). Mimic joints follow their drivers,
//! q_j = multiplier·q_a\[driver\] + offset.
//!
//! # Jacobian convention
//! Columns are `[δt (3), δω (3), δq_a (n_a)]`. The wrist perturbation is
//! expressed in world axes about the wrist origin ([`perturb_wrist`]):
//! t ← t + δt, R ← exp(δω)·R. A point p fixed to the hand therefore moves
//! by δp = δt + δω × (p − t) + Σ ∂p/∂q_a·δq_a, so its wrist block is
//! `[I₃, −[p − t]×]`. Rotating about the wrist rather than the world origin
//! keeps the rotation columns of the size of the hand (not of its distance
//! from the world origin), which conditions the grasp least squares.
//! A mimic joint's column is added to its driver's, scaled by the multiplier.

use nalgebra::{
    DMatrix, Dyn, Isometry3, Matrix, Point3, StorageMut, Translation3, Unit, UnitQuaternion, Vector3, Vector6, U3,
};

use super::model::{HandModel, JointDrive, JointKind, LinkId};

/// Number of wrist columns in every Jacobian.
pub const WRIST_DOF: usize = 6;

/// Applies a wrist perturbation `[δt, δω]` with the convention of the
/// Jacobians: t ← t + δt, R ← exp(δω)·R (δω a world-frame rotation vector).
pub fn perturb_wrist(wrist: &Isometry3<f64>, delta: &Vector6<f64>) -> Isometry3<f64> {
    let dt = Vector3::new(delta[0], delta[1], delta[2]);
    let dw = Vector3::new(delta[3], delta[4], delta[5]);
    Isometry3::from_parts(
        Translation3::from(wrist.translation.vector + dt),
        UnitQuaternion::from_scaled_axis(dw) * wrist.rotation,
    )
}

/// Per-configuration kinematic state of one hand, reused across calls so the
/// solver loop does not allocate. Create with [`HandKinematics::new`], fill
/// with [`HandKinematics::update`]; every later call must pass the same model.
#[derive(Clone, Debug)]
pub struct HandKinematics {
    wrist: Isometry3<f64>,
    joint_positions: Vec<f64>,
    link_poses: Vec<Isometry3<f64>>,
    /// World axis and a world point on it, per joint id (after `update`).
    joint_axes: Vec<Vector3<f64>>,
    joint_points: Vec<Vector3<f64>>,
    keypoints: Vec<Point3<f64>>,
    fingertips: Vec<Point3<f64>>,
    collision_poses: Vec<Isometry3<f64>>,
    keypoint_jacobian: DMatrix<f64>,
}

impl HandKinematics {
    /// State for `model`, at the identity wrist and the open hand.
    pub fn new(model: &HandModel) -> Self {
        let n_links = model.links().len();
        let n_joints = model.joints().len();
        let mut s = Self {
            wrist: Isometry3::identity(),
            joint_positions: vec![0.0; model.moving_joints().len()],
            link_poses: vec![Isometry3::identity(); n_links],
            joint_axes: vec![Vector3::zeros(); n_joints],
            joint_points: vec![Vector3::zeros(); n_joints],
            keypoints: vec![Point3::origin(); model.keypoints().len()],
            fingertips: vec![Point3::origin(); model.fingertips().len()],
            collision_poses: vec![Isometry3::identity(); model.collision_primitives().len()],
            keypoint_jacobian: DMatrix::zeros(3 * model.keypoints().len(), WRIST_DOF + model.num_actuated()),
        };
        s.update(model, &Isometry3::identity(), model.open_hand());
        s
    }

    /// Forward kinematics: every link, joint axis, keypoint, fingertip and
    /// collision primitive in the world frame. Does not allocate.
    ///
    /// Panics if `q_actuated.len() != model.num_actuated()` or if this state
    /// was made for a model of a different size (programming errors).
    pub fn update(&mut self, model: &HandModel, wrist: &Isometry3<f64>, q_actuated: &[f64]) {
        assert_eq!(self.link_poses.len(), model.links().len(), "HandKinematics used with another model");
        self.wrist = *wrist;
        model.expand_joint_positions(q_actuated, &mut self.joint_positions);

        let joints = model.joints();
        let order = model.link_order();
        self.link_poses[order[0]] = *wrist;
        for &l in &order[1..] {
            let j = model.links()[l].parent_joint.expect("non-root link has a parent joint");
            let joint = &joints[j];
            let frame = self.link_poses[joint.parent] * joint.origin;
            self.joint_axes[j] = frame.rotation * joint.axis.into_inner();
            self.joint_points[j] = frame.translation.vector;
            let q = joint.position_index.map_or(0.0, |k| self.joint_positions[k]);
            self.link_poses[l] = match joint.kind {
                JointKind::Fixed => frame,
                JointKind::Revolute | JointKind::Continuous => frame * UnitQuaternion::from_axis_angle(&joint.axis, q),
                JointKind::Prismatic => frame * Translation3::from(joint.axis.into_inner() * q),
            };
        }
        for (p, k) in self.keypoints.iter_mut().zip(model.keypoints()) {
            *p = self.link_poses[k.link] * Point3::from(k.offset);
        }
        for (p, k) in self.fingertips.iter_mut().zip(model.fingertips()) {
            *p = self.link_poses[k.link] * Point3::from(k.offset);
        }
        for (pose, c) in self.collision_poses.iter_mut().zip(model.collision_primitives()) {
            *pose = self.link_poses[c.link] * c.origin;
        }
    }

    /// The wrist pose of the last update.
    pub fn wrist(&self) -> &Isometry3<f64> {
        &self.wrist
    }
    /// All moving joints' positions (order [`HandModel::moving_joints`]).
    pub fn joint_positions(&self) -> &[f64] {
        &self.joint_positions
    }
    /// World pose of every link (index: [`LinkId`]).
    pub fn link_poses(&self) -> &[Isometry3<f64>] {
        &self.link_poses
    }
    pub fn link_pose(&self, link: LinkId) -> &Isometry3<f64> {
        &self.link_poses[link]
    }
    /// World positions of the model's keypoints, in its order.
    pub fn keypoints(&self) -> &[Point3<f64>] {
        &self.keypoints
    }
    /// World positions of the model's fingertips, in its order.
    pub fn fingertips(&self) -> &[Point3<f64>] {
        &self.fingertips
    }
    /// World pose of each of [`HandModel::collision_primitives`], in its order.
    pub fn collision_poses(&self) -> &[Isometry3<f64>] {
        &self.collision_poses
    }
    /// The palm normal in the world frame.
    pub fn palm_normal(&self, model: &HandModel) -> Unit<Vector3<f64>> {
        self.link_poses[model.root_link()].rotation * model.palm_normal()
    }

    /// Jacobian of a world point rigidly attached to `link` (e.g. a contact
    /// point on a collision primitive), written into `out` (3 × (6 + n_a),
    /// overwritten), convention in the module doc. Does not allocate.
    pub fn point_jacobian<S>(
        &self,
        model: &HandModel,
        link: LinkId,
        point: &Point3<f64>,
        out: &mut Matrix<f64, U3, Dyn, S>,
    ) where
        S: StorageMut<f64, U3, Dyn>,
    {
        point_jacobian_into(self, model, link, point, out);
    }

    /// Stacked Jacobian of all keypoints, (3·K) × (6 + n_a), keypoint i in
    /// rows 3i..3i+3, for the state of the last update. Reuses its buffer.
    pub fn update_keypoint_jacobian(&mut self, model: &HandModel) -> &DMatrix<f64> {
        // Taken out for the duration so the state can be read while the
        // matrix is written; an empty DMatrix owns no allocation.
        let mut jac = std::mem::replace(&mut self.keypoint_jacobian, DMatrix::zeros(0, 0));
        for (i, k) in model.keypoints().iter().enumerate() {
            let mut rows = jac.fixed_rows_mut::<3>(3 * i);
            point_jacobian_into(self, model, k.link, &self.keypoints[i], &mut rows);
        }
        self.keypoint_jacobian = jac;
        &self.keypoint_jacobian
    }

    /// The stacked keypoint Jacobian of the last [`Self::update_keypoint_jacobian`].
    pub fn keypoint_jacobian(&self) -> &DMatrix<f64> {
        &self.keypoint_jacobian
    }
}

fn point_jacobian_into<S>(
    state: &HandKinematics,
    model: &HandModel,
    link: LinkId,
    point: &Point3<f64>,
    out: &mut Matrix<f64, U3, Dyn, S>,
) where
    S: StorageMut<f64, U3, Dyn>,
{
    assert_eq!(out.ncols(), WRIST_DOF + model.num_actuated(), "Jacobian width");
    out.fill(0.0);
    let p = point.coords;
    let r = p - state.wrist.translation.vector;
    for a in 0..3 {
        out[(a, a)] = 1.0;
    }
    // δω × r for unit δω along each world axis: the columns of −[r]×.
    out[(1, 3)] = -r.z;
    out[(2, 3)] = r.y;
    out[(0, 4)] = r.z;
    out[(2, 4)] = -r.x;
    out[(0, 5)] = -r.y;
    out[(1, 5)] = r.x;

    let joints = model.joints();
    let links = model.links();
    let mut l = link;
    while let Some(j) = links[l].parent_joint {
        let joint = &joints[j];
        l = joint.parent;
        let (column, scale) = match joint.drive {
            JointDrive::Fixed => continue,
            JointDrive::Actuated { index } => (WRIST_DOF + index, 1.0),
            JointDrive::Mimic { driver, multiplier, .. } => (WRIST_DOF + driver, multiplier),
        };
        let axis = state.joint_axes[j];
        let dp = match joint.kind {
            JointKind::Revolute | JointKind::Continuous => axis.cross(&(p - state.joint_points[j])),
            JointKind::Prismatic => axis,
            JointKind::Fixed => continue,
        };
        for a in 0..3 {
            out[(a, column)] += scale * dp[a];
        }
    }
}
