//! Scenes: a table, tools and (optionally) the hand, assembled into one MJCF
//! document and compiled, with the indices the controllers need.

use std::sync::Arc;

use mujoco_rs::prelude::{MjData, MjModel, MjtObjBase};
use mujoco_rs::wrappers::mj_model::traits::ModelType;
use nalgebra::{Isometry3, Vector3};

use crate::engine::{load_mjcf, SimError};
use crate::hand::{body_pose, hand_mjcf, pose_to_qpos, HandAsset, HandIndex, HandMjcfOptions};
use crate::mjcf::{nums, vec3, MjcfDocument, PhysicsOptions, WORLD_CONAFFINITY, WORLD_CONTYPE};
use crate::tool::ToolBody;

/// The table: a box whose top face is the plane z = `top_z`.
#[derive(Clone, Debug, PartialEq)]
pub struct Table {
    pub top_z: f64,
    /// Half extents of the top in x and y, metres.
    pub half_size: [f64; 2],
    /// Wood or laminate (sliding 0.5); a tool-table contact uses the larger
    /// of the two friction values.
    pub friction: [f64; 3],
}

impl Default for Table {
    fn default() -> Self {
        Self { top_z: 0.0, half_size: [0.4, 0.4], friction: [0.5, 0.005, 0.0001] }
    }
}

/// What goes into a scene.
#[derive(Clone, Debug, Default)]
pub struct SceneSpec<'a> {
    pub name: String,
    pub physics: PhysicsOptions,
    pub table: Option<Table>,
    /// Tools and their initial poses (tool frame in the world).
    pub tools: Vec<(&'a ToolBody, Isometry3<f64>)>,
    /// The hand, its options and its initial wrist pose.
    pub hand: Option<(&'a HandAsset, HandMjcfOptions, Isometry3<f64>)>,
    /// Further MJCF worldbody elements (a task's fixtures: the nail's board
    /// and the nail), written after the tools.
    pub extra_bodies: Vec<String>,
    /// Further `<contact>` elements (pairs, exclusions) for those fixtures.
    pub extra_contact: Vec<String>,
}

impl SceneSpec<'_> {
    /// The MJCF text of the scene.
    pub fn to_mjcf(&self) -> String {
        let mut doc = MjcfDocument::new(&self.name, self.physics.clone());
        if let Some(t) = &self.table {
            // 4 cm thick, hanging below the top face.
            let half_thickness = 0.02;
            doc.worldbody.push(format!(
                r#"<geom name="table" type="box" size="{}" pos="{}" contype="{WORLD_CONTYPE}" conaffinity="{WORLD_CONAFFINITY}" condim="4" friction="{}" group="0"/>"#,
                nums(&[t.half_size[0], t.half_size[1], half_thickness]),
                vec3(&Vector3::new(0.0, 0.0, t.top_z - half_thickness)),
                nums(&t.friction)
            ));
        }
        for (tool, pose) in &self.tools {
            doc.assets.extend(tool.assets());
            doc.worldbody.push(tool.body(pose));
        }
        doc.worldbody.extend(self.extra_bodies.iter().cloned());
        doc.contact.extend(self.extra_contact.iter().cloned());
        if let Some((asset, opts, wrist)) = &self.hand {
            let h = hand_mjcf(asset, opts, wrist);
            doc.worldbody.extend(h.bodies);
            doc.equality.extend(h.equality);
            doc.actuator.extend(h.actuator);
        }
        doc.to_xml()
    }

    /// Compiles the scene and resolves its parts.
    pub fn build(&self) -> Result<Scene, SimError> {
        let model = load_mjcf(&self.to_mjcf())?;
        let hand = match &self.hand {
            Some((asset, _, _)) => Some(HandIndex::new(&model, asset.model())?),
            None => None,
        };
        let tools = self.tools.iter().map(|(t, _)| ToolIndex::new(&model, t)).collect::<Result<_, _>>()?;
        let table = match &self.table {
            Some(t) => Some((
                model
                    .name_to_id(MjtObjBase::mjOBJ_GEOM, "table")
                    .ok_or_else(|| SimError::MissingElement { kind: "geom", name: "table".into() })?,
                t.top_z,
            )),
            None => None,
        };
        Ok(Scene { model: Arc::new(model), hand, tools, table })
    }
}

/// A compiled scene. The model is shared: every environment's `MjData`
/// holds a reference-counted handle to it.
#[derive(Debug)]
pub struct Scene {
    pub model: Arc<MjModel>,
    pub hand: Option<HandIndex>,
    /// In the order of [`SceneSpec::tools`].
    pub tools: Vec<ToolIndex>,
    /// The table's geom id and top height.
    pub table: Option<(usize, f64)>,
}

impl Scene {
    /// Whether any contact of the current state is between the bodies `a`
    /// and `b` (either order). Body 0 is the world, which owns the table.
    pub fn in_contact<M: ModelType>(&self, data: &MjData<M>, a: usize, b: usize) -> bool {
        let body = |g: i32| usize::try_from(g).map(|g| self.model.geom_bodyid()[g] as usize).ok();
        data.contact().iter().any(|c| match (body(c.geom[0]), body(c.geom[1])) {
            (Some(x), Some(y)) => (x == a && y == b) || (x == b && y == a),
            _ => false,
        })
    }
}

/// Where a tool lives in a compiled model.
#[derive(Clone, Debug)]
pub struct ToolIndex {
    pub body: usize,
    /// qpos address of its free joint.
    pub qpos: usize,
    /// qvel address of its free joint.
    pub dof: usize,
    /// Extreme points of the tool, tool frame ([`ToolBody::support_points`]).
    pub support_points: Vec<nalgebra::Point3<f64>>,
}

impl ToolIndex {
    fn new(model: &MjModel, tool: &ToolBody) -> Result<Self, SimError> {
        let missing = |kind, name: String| SimError::MissingElement { kind, name };
        let body =
            model.name_to_id(MjtObjBase::mjOBJ_BODY, &tool.name).ok_or_else(|| missing("body", tool.name.clone()))?;
        let free_name = format!("{}_free", tool.name);
        let joint = model.name_to_id(MjtObjBase::mjOBJ_JOINT, &free_name).ok_or_else(|| missing("joint", free_name))?;
        Ok(Self {
            body,
            qpos: model.jnt_qposadr()[joint] as usize,
            dof: model.jnt_dofadr()[joint] as usize,
            support_points: tool.support_points(),
        })
    }

    /// The tool frame in the world (after `forward` or a step).
    pub fn pose<M: ModelType>(&self, data: &MjData<M>) -> Isometry3<f64> {
        body_pose(data, self.body)
    }

    /// Places the tool at rest.
    pub fn set_pose<M: ModelType>(&self, data: &mut MjData<M>, pose: &Isometry3<f64>) {
        data.qpos_mut()[self.qpos..self.qpos + 7].copy_from_slice(&pose_to_qpos(pose));
        data.qvel_mut()[self.dof..self.dof + 6].fill(0.0);
    }

    /// Height of the tool's lowest point in the world.
    pub fn lowest_z<M: ModelType>(&self, data: &MjData<M>) -> f64 {
        let pose = self.pose(data);
        self.support_points.iter().map(|p| (pose * p).z).fold(f64::INFINITY, f64::min)
    }

    /// Linear and angular speed of the tool (m/s, rad/s).
    pub fn speed<M: ModelType>(&self, data: &MjData<M>) -> (f64, f64) {
        let v = &data.qvel()[self.dof..self.dof + 6];
        (Vector3::new(v[0], v[1], v[2]).norm(), Vector3::new(v[3], v[4], v[5]).norm())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion};

    /// The canonical mug, dropped tilted from 5 cm, comes to rest upright on
    /// the table: the hulls, the mass properties and the contact settings
    /// make a stable resting tool.
    #[test]
    fn a_dropped_mug_comes_to_rest_upright_on_the_table() {
        let (_, body) = crate::tool::canonical_mug();
        let start = Isometry3::from_parts(
            Translation3::new(0.05, -0.03, 0.05),
            UnitQuaternion::from_euler_angles(0.15, -0.1, 0.7),
        );
        let spec = SceneSpec {
            name: "mug_drop".into(),
            physics: PhysicsOptions::default(),
            table: Some(Table::default()),
            tools: vec![(&body, start)],
            hand: None,
            ..Default::default()
        };
        let scene = spec.build().unwrap();
        let tool = &scene.tools[0];
        let mut data = MjData::new(scene.model.clone());
        data.forward();
        let steps = (2.0 / scene.model.opt().timestep).round() as usize;
        let mut fell_by = 0.0f64;
        for _ in 0..steps {
            data.step();
            fell_by = fell_by.max(0.05 - tool.pose(&data).translation.z);
        }
        let pose = tool.pose(&data);
        let up = pose.rotation * Vector3::z();
        assert!(up.z > (2.0f64).to_radians().cos(), "mug tilted {:.1}° from upright", up.z.acos().to_degrees());
        // The base (the tool frame's origin, its lowest plane) sits on the table top.
        assert!(pose.translation.z.abs() < 1.5e-3, "base at z = {} m", pose.translation.z);
        assert!(tool.lowest_z(&data).abs() < 1.5e-3, "lowest point at z = {} m", tool.lowest_z(&data));
        assert!(scene.in_contact(&data, tool.body, 0), "the mug does not touch the table (world body)");
        assert!(fell_by > 0.045, "the mug never reached the table ({fell_by} m)");
        let (v, w) = tool.speed(&data);
        assert!(v < 1e-3 && w < 1e-2, "still moving: {v} m/s, {w} rad/s");
        // It landed near where it was dropped (no sliding away or bouncing off).
        let drift = (pose.translation.vector.xy() - start.translation.vector.xy()).norm();
        assert!(drift < 0.02, "slid {drift} m");
    }
}
