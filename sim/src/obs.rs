//! Observations and actions of the tool-use tasks (paper §IV-A), in one flat
//! documented layout that a policy, the trainer and the daemon's policy
//! sessions share. Nothing here touches MuJoCo except [`observe`]; the
//! layout types belong in the wire contract once the sessions exist.
//!
//! Observation, f32, world frame (z up, metres, quaternions (x, y, z, w)
//! with w ≥ 0 so that one rotation has one encoding):
//!
//! | segment | length |
//! |---|---|
//! | `wrist_position` | 3 |
//! | `wrist_orientation_xyzw` | 4 |
//! | `hand_keypoints` | 3·K (K = 12: keypoint order of the hand model, x y z each) |
//! | `demo_keypoints` | 3·K (the generalised demonstration, riding with the tool) |
//! | `latent` | L (the tool's shape-space latent; L per category) |
//! | `goal_position` | 3 |
//! | `goal_orientation_xyzw` | 4 |
//!
//! The goal segment per task: Place mug and Position drill, the goal pose
//! of the tool frame ([`crate::task::PoseEpisode::goal`]); Drive nail, the
//! top of the nail's head (it sinks as the nail goes in, so the policy sees
//! the depth) with the nail's axis as orientation (the identity: the nail
//! stands along world z). One layout serves all three tasks.
//!
//! Action, f32:
//!
//! | segment | length |
//! |---|---|
//! | `wrist_delta_position` | 3 (world frame, metres this control step) |
//! | `wrist_delta_rotation` | 3 (rotation vector, world axes, about the wrist's own position, radians) |
//! | `joint_targets` | A (A = 5: the actuated joints' absolute targets, radians, actuated order) |
//!
//! The wrist deltas change the *commanded* wrist (the arm's end-effector
//! target), not the measured one, so that a zero action holds the command
//! still; they are clamped to [`ActionLimits`].

use mujoco_rs::prelude::MjData;
use mujoco_rs::wrappers::mj_model::traits::ModelType;
use nalgebra::{Isometry3, Point3, Quaternion, Translation3, UnitQuaternion, Vector3};
use serde::Serialize;

use crate::engine::SimError;
use crate::scene::Scene;

/// A named run of values in a flat vector.
#[derive(Clone, Debug, PartialEq, Eq, Serialize)]
pub struct Segment {
    pub name: &'static str,
    pub offset: usize,
    pub len: usize,
}

fn segments(parts: &[(&'static str, usize)]) -> Vec<Segment> {
    let mut offset = 0;
    parts
        .iter()
        .map(|&(name, len)| {
            let s = Segment { name, offset, len };
            offset += len;
            s
        })
        .collect()
}

/// The observation layout for a hand with `keypoints` keypoints and a category with `latent_dim` modes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub struct ObservationLayout {
    pub keypoints: usize,
    pub latent_dim: usize,
}

impl ObservationLayout {
    /// The segments, in order (module docs).
    pub fn segments(&self) -> Vec<Segment> {
        segments(&[
            ("wrist_position", 3),
            ("wrist_orientation_xyzw", 4),
            ("hand_keypoints", 3 * self.keypoints),
            ("demo_keypoints", 3 * self.keypoints),
            ("latent", self.latent_dim),
            ("goal_position", 3),
            ("goal_orientation_xyzw", 4),
        ])
    }

    pub fn len(&self) -> usize {
        14 + 6 * self.keypoints + self.latent_dim
    }

    pub fn is_empty(&self) -> bool {
        false
    }

    /// The segment called `name`.
    pub fn segment(&self, name: &str) -> Option<Segment> {
        self.segments().into_iter().find(|s| s.name == name)
    }
}

/// The action layout for a hand with `actuated` actuated joints.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub struct ActionLayout {
    pub actuated: usize,
}

impl ActionLayout {
    pub fn segments(&self) -> Vec<Segment> {
        segments(&[("wrist_delta_position", 3), ("wrist_delta_rotation", 3), ("joint_targets", self.actuated)])
    }

    pub fn len(&self) -> usize {
        6 + self.actuated
    }

    pub fn is_empty(&self) -> bool {
        false
    }
}

/// One observation, as values.
#[derive(Clone, Debug, PartialEq)]
pub struct Observation {
    pub wrist: Isometry3<f64>,
    pub hand_keypoints: Vec<Point3<f64>>,
    pub demo_keypoints: Vec<Point3<f64>>,
    pub latent: Vec<f64>,
    pub goal: Isometry3<f64>,
}

/// (x, y, z, w) with w ≥ 0.
fn quat_xyzw(q: &UnitQuaternion<f64>) -> [f64; 4] {
    let s = if q.w < 0.0 { -1.0 } else { 1.0 };
    [s * q.i, s * q.j, s * q.k, s * q.w]
}

fn layout_error(reason: String) -> SimError {
    SimError::Config { reason }
}

impl Observation {
    /// Its layout; an error if the two keypoint sets differ in length.
    pub fn layout(&self) -> Result<ObservationLayout, SimError> {
        if self.hand_keypoints.len() != self.demo_keypoints.len() {
            return Err(layout_error(format!(
                "{} hand keypoints but {} demonstration keypoints",
                self.hand_keypoints.len(),
                self.demo_keypoints.len()
            )));
        }
        Ok(ObservationLayout { keypoints: self.hand_keypoints.len(), latent_dim: self.latent.len() })
    }

    /// Writes the flat observation into `out` (exactly the layout's length:
    /// a batch buffer's row, no allocation).
    pub fn write_into(&self, out: &mut [f32]) -> Result<(), SimError> {
        let layout = self.layout()?;
        if out.len() != layout.len() {
            return Err(layout_error(format!("observation buffer of {} for a layout of {}", out.len(), layout.len())));
        }
        let t = self.wrist.translation.vector;
        let g = self.goal.translation.vector;
        let values = [t.x, t.y, t.z]
            .into_iter()
            .chain(quat_xyzw(&self.wrist.rotation))
            .chain(self.hand_keypoints.iter().flat_map(|p| [p.x, p.y, p.z]))
            .chain(self.demo_keypoints.iter().flat_map(|p| [p.x, p.y, p.z]))
            .chain(self.latent.iter().copied())
            .chain([g.x, g.y, g.z])
            .chain(quat_xyzw(&self.goal.rotation));
        for (o, v) in out.iter_mut().zip(values) {
            *o = v as f32;
        }
        Ok(())
    }

    pub fn to_vec(&self) -> Result<Vec<f32>, SimError> {
        let mut v = vec![0.0; self.layout()?.len()];
        self.write_into(&mut v)?;
        Ok(v)
    }

    /// Reads a flat observation back (a session's or a recording's), refusing
    /// a wrong length, non-finite values or a zero quaternion.
    pub fn from_slice(layout: &ObservationLayout, v: &[f32]) -> Result<Self, SimError> {
        if v.len() != layout.len() {
            return Err(layout_error(format!("observation of {} values for a layout of {}", v.len(), layout.len())));
        }
        if let Some(i) = v.iter().position(|x| !x.is_finite()) {
            return Err(layout_error(format!("observation value {i} is not finite")));
        }
        let v: Vec<f64> = v.iter().map(|&x| x as f64).collect();
        let pose = |p: &[f64], q: &[f64]| -> Result<Isometry3<f64>, SimError> {
            let q = Quaternion::new(q[3], q[0], q[1], q[2]);
            if q.norm() < 1e-6 {
                return Err(layout_error("a zero quaternion in the observation".into()));
            }
            Ok(Isometry3::from_parts(Translation3::new(p[0], p[1], p[2]), UnitQuaternion::from_quaternion(q)))
        };
        let points = |s: &[f64]| s.chunks_exact(3).map(|c| Point3::new(c[0], c[1], c[2])).collect::<Vec<_>>();
        let k = 3 * layout.keypoints;
        let (wrist, rest) = v.split_at(7);
        let (hand, rest) = rest.split_at(k);
        let (demo, rest) = rest.split_at(k);
        let (latent, goal) = rest.split_at(layout.latent_dim);
        Ok(Self {
            wrist: pose(&wrist[..3], &wrist[3..])?,
            hand_keypoints: points(hand),
            demo_keypoints: points(demo),
            latent: latent.to_vec(),
            goal: pose(&goal[..3], &goal[3..])?,
        })
    }
}

/// Largest wrist change per control step. At 30 Hz the defaults allow
/// 0.6 m/s and 3 rad/s, beyond what the scripted controller uses.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ActionLimits {
    pub max_translation_m: f64,
    pub max_rotation_rad: f64,
}

impl Default for ActionLimits {
    fn default() -> Self {
        Self { max_translation_m: 0.02, max_rotation_rad: 0.1 }
    }
}

/// One action, as values.
#[derive(Clone, Debug, PartialEq)]
pub struct Action {
    pub wrist_delta_position: Vector3<f64>,
    pub wrist_delta_rotation: Vector3<f64>,
    pub joint_targets: Vec<f64>,
}

impl Action {
    /// The action that holds the wrist command and sets the joints to `q`.
    pub fn hold(q: &[f64]) -> Self {
        Self {
            wrist_delta_position: Vector3::zeros(),
            wrist_delta_rotation: Vector3::zeros(),
            joint_targets: q.to_vec(),
        }
    }

    /// The action that takes the wrist command from `from` to `to` (unclamped).
    pub fn between(from: &Isometry3<f64>, to: &Isometry3<f64>, q: &[f64]) -> Self {
        Self {
            wrist_delta_position: to.translation.vector - from.translation.vector,
            wrist_delta_rotation: (to.rotation * from.rotation.inverse()).scaled_axis(),
            joint_targets: q.to_vec(),
        }
    }

    pub fn layout(&self) -> ActionLayout {
        ActionLayout { actuated: self.joint_targets.len() }
    }

    pub fn to_vec(&self) -> Vec<f32> {
        let (p, r) = (&self.wrist_delta_position, &self.wrist_delta_rotation);
        [p.x, p.y, p.z, r.x, r.y, r.z].into_iter().chain(self.joint_targets.iter().copied()).map(|v| v as f32).collect()
    }

    /// Reads a policy's output, refusing a wrong length or non-finite values.
    pub fn from_slice(layout: &ActionLayout, v: &[f32]) -> Result<Self, SimError> {
        if v.len() != layout.len() {
            return Err(layout_error(format!("action of {} values for a layout of {}", v.len(), layout.len())));
        }
        if let Some(i) = v.iter().position(|x| !x.is_finite()) {
            return Err(layout_error(format!("action value {i} is not finite")));
        }
        let f = |i: usize| v[i] as f64;
        Ok(Self {
            wrist_delta_position: Vector3::new(f(0), f(1), f(2)),
            wrist_delta_rotation: Vector3::new(f(3), f(4), f(5)),
            joint_targets: v[6..].iter().map(|&x| x as f64).collect(),
        })
    }

    /// The next wrist command: the deltas, clamped to `limits`, applied to
    /// `command` (the rotation about the command's own position).
    pub fn apply(&self, command: &Isometry3<f64>, limits: &ActionLimits) -> Isometry3<f64> {
        let clamp = |v: &Vector3<f64>, max: f64| {
            let n = v.norm();
            if n > max {
                v * (max / n)
            } else {
                *v
            }
        };
        let dp = clamp(&self.wrist_delta_position, limits.max_translation_m);
        let dr = UnitQuaternion::from_scaled_axis(clamp(&self.wrist_delta_rotation, limits.max_rotation_rad));
        Isometry3::from_parts(Translation3::from(command.translation.vector + dp), dr * command.rotation)
    }
}

/// The observation of a scene's state: the measured palm pose and hand
/// keypoints, the demonstration's keypoints (tool frame) carried by the
/// tool's current pose, the latent and the goal.
pub fn observe<M: ModelType>(
    scene: &Scene,
    data: &MjData<M>,
    demo_keypoints_tool: &[Point3<f64>],
    latent: &[f64],
    goal: &Isometry3<f64>,
) -> Result<Observation, SimError> {
    let hand = scene.hand.as_ref().ok_or(SimError::MissingElement { kind: "hand", name: "hand".into() })?;
    let tool = scene.tools.first().ok_or(SimError::MissingElement { kind: "tool", name: "tool".into() })?;
    let pose = tool.pose(data);
    Ok(Observation {
        wrist: hand.wrist_pose(data),
        hand_keypoints: hand.keypoints(data),
        demo_keypoints: demo_keypoints_tool.iter().map(|p| pose * p).collect(),
        latent: latent.to_vec(),
        goal: *goal,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> Observation {
        let k = |base: f64| (0..12).map(|i| Point3::new(base + i as f64, base + 0.5, -(i as f64))).collect();
        Observation {
            wrist: Isometry3::from_parts(
                Translation3::new(0.1, 0.2, 0.3),
                UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 0.5),
            ),
            hand_keypoints: k(100.0),
            demo_keypoints: k(200.0),
            latent: vec![7.0, 8.0, 9.0],
            goal: Isometry3::from_parts(
                Translation3::new(-0.4, 0.5, 0.0),
                // w < 0 on purpose: the layout stores the w ≥ 0 twin.
                UnitQuaternion::from_quaternion(Quaternion::new(-0.6, 0.0, 0.0, 0.8)),
            ),
        }
    }

    /// The layout's size and order, and every value where the layout says.
    #[test]
    fn observation_layout_has_the_documented_size_and_order() {
        let o = sample();
        let layout = o.layout().unwrap();
        assert_eq!(layout.len(), 3 + 4 + 36 + 36 + 3 + 3 + 4);
        let names: Vec<&str> = layout.segments().iter().map(|s| s.name).collect();
        assert_eq!(
            names,
            [
                "wrist_position",
                "wrist_orientation_xyzw",
                "hand_keypoints",
                "demo_keypoints",
                "latent",
                "goal_position",
                "goal_orientation_xyzw"
            ]
        );
        // Contiguous and covering.
        let segs = layout.segments();
        for w in segs.windows(2) {
            assert_eq!(w[0].offset + w[0].len, w[1].offset);
        }
        assert_eq!(segs.last().map(|s| s.offset + s.len), Some(layout.len()));

        let v = o.to_vec().unwrap();
        assert_eq!(v.len(), layout.len());
        let at = |name: &str| {
            let s = layout.segment(name).unwrap();
            v[s.offset..s.offset + s.len].to_vec()
        };
        assert_eq!(at("wrist_position"), [0.1f32, 0.2, 0.3]);
        let (s, c) = (0.25f64.sin() as f32, 0.25f64.cos() as f32);
        assert_eq!(at("wrist_orientation_xyzw"), [0.0, 0.0, s, c]);
        assert_eq!(at("hand_keypoints")[..6], [100.0, 100.5, 0.0, 101.0, 100.5, -1.0]);
        assert_eq!(at("demo_keypoints")[33..], [211.0, 200.5, -11.0]);
        assert_eq!(at("latent"), [7.0, 8.0, 9.0]);
        assert_eq!(at("goal_position"), [-0.4, 0.5, 0.0]);
        assert_eq!(at("goal_orientation_xyzw"), [0.0, 0.0, -0.8, 0.6]);

        // Back again (to f32 precision).
        let back = Observation::from_slice(&layout, &v).unwrap();
        assert!((back.wrist.translation.vector - o.wrist.translation.vector).norm() < 1e-6);
        assert!(back.goal.rotation.angle_to(&o.goal.rotation) < 1e-6);
        assert_eq!(back.latent, o.latent.iter().map(|&x| x as f32 as f64).collect::<Vec<_>>());
        assert_eq!(back.demo_keypoints[11], Point3::new(211.0, 200.5, -11.0));

        // Wrong lengths and non-finite values are errors, not panics.
        assert!(Observation::from_slice(&layout, &v[1..]).is_err());
        let mut bad = v.clone();
        bad[10] = f32::NAN;
        assert!(Observation::from_slice(&layout, &bad).is_err());
        let mut short = o.clone();
        short.demo_keypoints.pop();
        assert!(short.to_vec().is_err());
        assert!(o.write_into(&mut [0.0; 5]).is_err());
    }

    #[test]
    fn action_layout_order_and_clamped_application() {
        let a = Action {
            wrist_delta_position: Vector3::new(0.001, -0.002, 0.003),
            wrist_delta_rotation: Vector3::new(0.0, 0.0, 0.05),
            joint_targets: vec![0.1, 0.2, 0.3, 0.4, 0.5],
        };
        let layout = a.layout();
        assert_eq!(layout.len(), 11);
        let names: Vec<&str> = layout.segments().iter().map(|s| s.name).collect();
        assert_eq!(names, ["wrist_delta_position", "wrist_delta_rotation", "joint_targets"]);
        let v = a.to_vec();
        assert_eq!(v, [0.001f32, -0.002, 0.003, 0.0, 0.0, 0.05, 0.1, 0.2, 0.3, 0.4, 0.5]);
        let back = Action::from_slice(&layout, &v).unwrap();
        assert!((back.wrist_delta_rotation.z - 0.05).abs() < 1e-7);
        assert!(Action::from_slice(&layout, &v[..10]).is_err());
        assert!(Action::from_slice(&layout, &[f32::INFINITY; 11]).is_err());

        // Applied about the wrist's own position; small deltas pass unclamped.
        let w = Isometry3::from_parts(Translation3::new(0.3, 0.0, 0.2), UnitQuaternion::identity());
        let next = a.apply(&w, &ActionLimits::default());
        assert!((next.translation.vector - Vector3::new(0.301, -0.002, 0.203)).norm() < 1e-12);
        assert!((next.rotation.angle() - 0.05).abs() < 1e-12);
        // `between` inverts `apply` within the limits.
        let b = Action::between(&w, &next, &a.joint_targets);
        let again = b.apply(&w, &ActionLimits::default());
        assert!((again.translation.vector - next.translation.vector).norm() < 1e-12);
        assert!(again.rotation.angle_to(&next.rotation) < 1e-12);
        // Large deltas are clamped to the limits.
        let big = Action {
            wrist_delta_position: Vector3::new(1.0, 0.0, 0.0),
            wrist_delta_rotation: Vector3::new(2.0, 0.0, 0.0),
            ..a.clone()
        };
        let next = big.apply(&w, &ActionLimits::default());
        assert!(((next.translation.vector - w.translation.vector).norm() - 0.02).abs() < 1e-12);
        assert!((next.rotation.angle() - 0.1).abs() < 1e-12);
        // The zero action holds the command.
        assert_eq!(Action::hold(&[0.0; 5]).apply(&w, &ActionLimits::default()), w);
    }

    /// A real scene's observation: the canonical mug's demonstrated grasp
    /// set directly (no physics step) puts the hand's keypoints on the
    /// demonstration's, and the layout carries the category's latent.
    #[test]
    fn observe_reads_the_scene_in_the_layout() {
        use crate::hand::HandAsset;
        use crate::place::PlaceSetup;
        use crate::plan::GraspPlanner;
        use crate::scene::{SceneSpec, Table};
        use crate::tool::{ToolBody, ToolMaterial};
        use graspd::tools::{self, Category};
        use mujoco_rs::prelude::MjData;

        let asset = HandAsset::default_sih().unwrap();
        let mut planner = GraspPlanner::new(asset.model(), Category::Mug, 0).unwrap();
        let mug = tools::instance(Category::Mug, "mug_canonical").unwrap();
        let setup = PlaceSetup::default();
        let episode = setup.ranges.sample(3, 0.0);
        let plan = planner.plan(&mug).unwrap().carried(asset.model(), &episode.start);
        let tool =
            ToolBody::from_mesh("mug", &mug.mesh, ToolMaterial::for_category(Category::Mug), &setup.base.decomposition)
                .unwrap();
        let spec = SceneSpec {
            name: "observe".into(),
            physics: setup.base.physics.clone(),
            table: Some(Table::default()),
            tools: vec![(&tool, episode.start)],
            hand: Some((&asset, setup.base.hand.clone(), plan.grasp.wrist_pose_world)),
            ..Default::default()
        };
        let scene = spec.build().unwrap();
        let mut data = MjData::new(scene.model.clone());
        scene.tools[0].set_pose(&mut data, &episode.start);
        let hand = scene.hand.as_ref().unwrap();
        hand.set_configuration(&mut data, asset.model(), &plan.grasp.wrist_pose_world, &plan.grasp.actuated);
        data.forward();
        let demo_tool: Vec<Point3<f64>> = plan.demo_keypoints.iter().map(|p| episode.start.inverse() * p).collect();
        let o = observe(&scene, &data, &demo_tool, &plan.latent, &episode.goal).unwrap();
        let layout = o.layout().unwrap();
        assert_eq!(layout.keypoints, 12);
        assert_eq!(layout.latent_dim, planner.latent_dim());
        assert!(layout.latent_dim > 0);
        assert_eq!(o.to_vec().unwrap().len(), 14 + 72 + planner.latent_dim());
        let dk = crate::task::mean_keypoint_distance(&o.hand_keypoints, &o.demo_keypoints);
        assert!(dk < 1e-3, "hand keypoints {dk} m from the demonstration's at the demonstrated grasp");
        assert!((o.wrist.translation.vector - plan.grasp.wrist_pose_world.translation.vector).norm() < 1e-9);
        assert_eq!(o.goal, episode.goal);
    }
}
