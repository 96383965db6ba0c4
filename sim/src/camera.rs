//! The scene's depth camera, and the lab frame its clouds are given in.
//!
//! For a grasp from the daemon the simulator does what a lab does: a fixed
//! RGB-D camera looks at the table, the tool's pixels are segmented, and the
//! partial cloud goes to graspd (paper Table III: an unseen tool is grasped
//! from such a view). MuJoCo's renderer needs an OpenGL context, which a
//! headless machine lacks, so the view is graspd's own virtual depth camera
//! (`graspd::geometry::camera`): one ray per pixel against the tool's mesh,
//! the table plane hiding what lies below it, axial noise growing with depth,
//! all seeded. The mesh is posed where MuJoCo has the tool's body (the
//! camera sees the tool's surface, not its convex collision hulls). Only the
//! tool is in the view: the cloud is taken before the episode's first step,
//! with the hand away (the segmentation a lab gets from a mask of the tool).
//!
//! The mount ([`SceneCamera::default`]): 640×480, 525 px focal length (63°
//! horizontal field of view, RealSense-like), the eye at (0.50, −0.35, 0.50)
//! m in the simulator's frame, above the table's +x, −y corner, looking at
//! (0, 0, 0.05): 0.76 m from the table's centre, 36° down. From there a mug
//! at its start (handle toward +x, turned by up to ±45°) shows its handle,
//! and a tool fills about 70×80 pixels (3-5 thousand points). Noise:
//! graspd's default (σ = 1 mm + 1.2 mm/m² · depth²: 1.7 mm at 0.76 m).
//!
//! The lab frame ([`LabFrame::default`]) is the frame the camera is
//! calibrated in and the daemon answers in (the robot's base, as on a real
//! arm): its origin on the table top at the middle of the table's −y edge,
//! x toward the far side of the table (the simulator's +y), z up. The
//! simulator's own frame is MuJoCo's world (origin at the table's centre).
//! Points go to the daemon in the lab frame and its grasps come back in it;
//! [`LabFrame::sim_from_lab`] converts them.

use graspd::geometry::camera::{look_at, DepthCamera, DepthNoise, Intrinsics, Scene as CameraScene};
use graspd::geometry::TriMesh;
use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};

use crate::engine::SimError;

/// A fixed depth camera in the scene (module docs).
#[derive(Clone, Debug, PartialEq)]
pub struct SceneCamera {
    pub intrinsics: Intrinsics,
    /// The camera's optical centre, simulator frame, metres.
    pub eye_sim: Point3<f64>,
    /// The point it looks at, simulator frame, metres.
    pub target_sim: Point3<f64>,
    pub noise: DepthNoise,
}

impl Default for SceneCamera {
    fn default() -> Self {
        Self {
            intrinsics: Intrinsics::default(),
            eye_sim: Point3::new(0.50, -0.35, 0.50),
            target_sim: Point3::new(0.0, 0.0, 0.05),
            noise: DepthNoise::default(),
        }
    }
}

impl SceneCamera {
    /// The camera frame (OpenCV: x right, y down, z forward) in the simulator's frame.
    pub fn sim_from_camera(&self) -> Result<Isometry3<f64>, SimError> {
        look_at(self.eye_sim, self.target_sim, Vector3::z()).map_err(|e| SimError::Camera { reason: e.to_string() })
    }

    /// The segmented partial cloud of `mesh` (tool frame) with the tool at
    /// `tool_pose_sim`, the table top at z = `table_z`: simulator frame,
    /// metres. The noise and any dropout are drawn from `seed`.
    pub fn capture(
        &self,
        mesh: &TriMesh,
        tool_pose_sim: &Isometry3<f64>,
        table_z: f64,
        seed: u64,
    ) -> Result<Vec<Point3<f64>>, SimError> {
        let camera_error = |e: graspd::geometry::camera::CameraError| SimError::Camera { reason: e.to_string() };
        let scene = CameraScene::new(mesh, *tool_pose_sim, Some(table_z)).map_err(camera_error)?;
        let camera =
            DepthCamera { intrinsics: self.intrinsics, world_from_camera: self.sim_from_camera()?, noise: self.noise };
        Ok(camera.capture(&scene, seed).map_err(camera_error)?.points_world)
    }
}

/// The frame the camera is calibrated in and the daemon answers in: z up,
/// so it differs from the simulator's frame by a turn about z and a shift
/// (module docs).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LabFrame {
    sim_from_lab: Isometry3<f64>,
}

impl Default for LabFrame {
    fn default() -> Self {
        // The middle of the default table's −y edge (half size 0.4 m), x along the simulator's +y.
        Self::new(Point3::new(0.0, -0.4, 0.0), std::f64::consts::FRAC_PI_2)
    }
}

impl LabFrame {
    /// The lab frame with its origin at `origin_sim` and its x axis turned
    /// by `yaw` about z from the simulator's (z stays up: the daemon's table
    /// plane and up direction are given in it).
    pub fn new(origin_sim: Point3<f64>, yaw: f64) -> Self {
        Self {
            sim_from_lab: Isometry3::from_parts(
                Translation3::from(origin_sim.coords),
                UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw),
            ),
        }
    }

    pub fn sim_from_lab(&self) -> Isometry3<f64> {
        self.sim_from_lab
    }

    pub fn lab_from_sim(&self) -> Isometry3<f64> {
        self.sim_from_lab.inverse()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use graspd::geometry::sample::to_parry;
    use graspd::tools::{self, Category};
    use parry3d::query::PointQuery;

    /// Distance of `p` (tool frame) to the mesh's surface.
    fn surface_distance(mesh: &parry3d::shape::TriMesh, p: &Point3<f64>) -> f64 {
        let q = parry3d::math::Vector::new(p.x as f32, p.y as f32, p.z as f32);
        mesh.project_local_point(q, false).point.distance(q) as f64
    }

    fn mug_pose() -> Isometry3<f64> {
        Isometry3::from_parts(
            Translation3::new(0.04, -0.03, 0.0),
            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 0.6),
        )
    }

    /// Without noise every point lies on the mug's surface where the mug
    /// is (a cloud of the mug at another pose would not), none below the
    /// table, and the view has thousands of points on the side facing the camera.
    #[test]
    fn the_cloud_lies_on_the_tool_at_its_pose() {
        let mug = tools::instance(Category::Mug, "mug_canonical").unwrap();
        let parry = to_parry(&mug.mesh).unwrap();
        let camera = SceneCamera { noise: DepthNoise::NONE, ..SceneCamera::default() };
        let pose = mug_pose();
        let cloud = camera.capture(&mug.mesh, &pose, 0.0, 0).unwrap();
        assert!(cloud.len() > 2000, "{} points", cloud.len());
        let tool_from_sim = pose.inverse();
        let worst = cloud.iter().map(|p| surface_distance(&parry, &(tool_from_sim * p))).fold(0.0, f64::max);
        assert!(worst < 1e-4, "a point {worst} m off the surface");
        assert!(cloud.iter().all(|p| p.z >= -1e-6), "a point below the table");
        // The points face the camera: their mean is nearer to it than the mug's axis.
        let mean = cloud.iter().fold(Vector3::zeros(), |a, p| a + p.coords) / cloud.len() as f64;
        let axis = pose.translation.vector + Vector3::new(0.0, 0.0, mean.z);
        assert!((camera.eye_sim.coords - mean).norm() < (camera.eye_sim.coords - axis).norm());
        // The mug elsewhere: most points are off its surface there.
        let elsewhere = Isometry3::translation(0.05, 0.0, 0.0) * pose;
        let off = cloud.iter().filter(|p| surface_distance(&parry, &(elsewhere.inverse() * *p)) > 2e-3).count();
        assert!(off > cloud.len() / 2, "{off} of {}", cloud.len());
    }

    /// With the default noise the points stay within a few σ of the surface
    /// (σ ≈ 1.7 mm at this range), and the same seed gives the same cloud.
    #[test]
    fn the_noisy_cloud_is_seeded_and_near_the_surface() {
        let mug = tools::instance(Category::Mug, "mug_canonical").unwrap();
        let parry = to_parry(&mug.mesh).unwrap();
        let camera = SceneCamera::default();
        let pose = mug_pose();
        let a = camera.capture(&mug.mesh, &pose, 0.0, 3).unwrap();
        let b = camera.capture(&mug.mesh, &pose, 0.0, 3).unwrap();
        let c = camera.capture(&mug.mesh, &pose, 0.0, 4).unwrap();
        assert_eq!(a, b);
        assert_ne!(a, c);
        let tool_from_sim = pose.inverse();
        let d: Vec<f64> = a.iter().map(|p| surface_distance(&parry, &(tool_from_sim * p))).collect();
        let rms = (d.iter().map(|x| x * x).sum::<f64>() / d.len() as f64).sqrt();
        assert!(rms > 2e-4 && rms < 3e-3, "rms {rms}");
        assert!(a.iter().all(|p| p.z >= -0.01), "a point far below the table");
    }

    /// The table hides a tool sunk halfway into it: no point below its top.
    #[test]
    fn the_table_occludes() {
        let mug = tools::instance(Category::Mug, "mug_canonical").unwrap();
        let camera = SceneCamera { noise: DepthNoise::NONE, ..SceneCamera::default() };
        let sunk = Isometry3::translation(0.0, 0.0, -0.05);
        let cloud = camera.capture(&mug.mesh, &sunk, 0.0, 0).unwrap();
        assert!(!cloud.is_empty());
        assert!(cloud.iter().all(|p| p.z >= -1e-6));
    }

    #[test]
    fn the_lab_frame_is_the_table_edge_turned_a_quarter() {
        let lab = LabFrame::default();
        // The lab's x axis is the simulator's +y; its origin the table's −y edge.
        let p = lab.sim_from_lab() * Point3::new(0.4, 0.0, 0.0);
        assert!((p - Point3::origin()).norm() < 1e-12, "{p}");
        let up = lab.sim_from_lab() * Vector3::z();
        assert!((up - Vector3::z()).norm() < 1e-12);
        let round = lab.lab_from_sim() * (lab.sim_from_lab() * Point3::new(0.1, 0.2, 0.3));
        assert!((round - Point3::new(0.1, 0.2, 0.3)).norm() < 1e-12);
    }
}
