//! A virtual depth camera: what a segmented RGB-D view of a tool looks like.
//!
//! Pinhole model in the OpenCV convention (camera frame: x right, y down,
//! z forward). Each pixel casts one ray into the scene (parry BVH); the first
//! hit decides what the pixel sees, so self-occlusion and occlusion by the
//! table are exact. Only pixels that see the tool survive segmentation.
//! Depth noise is axial (along the ray) and grows with depth, like
//! structured-light and stereo sensors.

use super::mesh::TriMesh;
use super::sample::to_parry;
use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use parry3d::query::{Ray, RayCast};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::Distribution;

#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Intrinsics {
    pub width: u32,
    pub height: u32,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
}

impl Default for Intrinsics {
    /// A 640×480 sensor with a 63° horizontal field of view (RealSense-like).
    fn default() -> Self {
        Self { width: 640, height: 480, fx: 525.0, fy: 525.0, cx: 319.5, cy: 239.5 }
    }
}

/// Axial depth noise σ(z) = `sigma_m` + `quadratic_per_m` · z², random
/// pixel dropout, and a segmentation that leaks onto the table.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct DepthNoise {
    pub sigma_m: f64,
    pub quadratic_per_m: f64,
    pub dropout: f64,
    /// The tool's mask dilated by this many pixels: the table's pixels
    /// that lie near the tool's silhouette are kept as the tool's (what a
    /// learned segmentation's blurred edge gives where the tool meets the
    /// table and around it). 0: exact segmentation.
    #[serde(default)]
    pub mask_leak_px: u32,
    /// A vertical bar in front of the tool (a pole, the robot's own arm)
    /// hides this share of the tool's image width: the segmented cloud lacks
    /// the pixels behind it, and nothing in the cloud says they were hidden.
    /// Placed over the tool's columns by the capture's seed. 0: nothing in front.
    #[serde(default)]
    pub occluder_share: f64,
}

impl DepthNoise {
    pub const NONE: Self =
        Self { sigma_m: 0.0, quadratic_per_m: 0.0, dropout: 0.0, mask_leak_px: 0, occluder_share: 0.0 };
}

impl Default for DepthNoise {
    fn default() -> Self {
        Self { sigma_m: 0.001, quadratic_per_m: 0.0012, dropout: 0.0, mask_leak_px: 0, occluder_share: 0.0 }
    }
}

#[derive(Clone, Debug, PartialEq)]
pub struct DepthCamera {
    pub intrinsics: Intrinsics,
    /// Pose of the camera frame in the world frame.
    pub world_from_camera: Isometry3<f64>,
    pub noise: DepthNoise,
}

/// What one view of a tool gives: the segmented partial cloud in both frames.
#[derive(Clone, Debug, Default)]
pub struct PartialView {
    pub points_world: Vec<Point3<f64>>,
    pub points_camera: Vec<Point3<f64>>,
    /// (u, v) pixel of each point.
    pub pixels: Vec<[u32; 2]>,
}

/// The tool placed in the world, optionally on a table plane z = `table_z`.
pub struct Scene {
    tool: parry3d::shape::TriMesh,
    world_from_tool: Isometry3<f64>,
    table_z: Option<f64>,
}

#[derive(Debug, thiserror::Error)]
pub enum CameraError {
    #[error("the tool mesh is empty or degenerate")]
    BadMesh,
    #[error("camera looks along its up vector (eye, target and up are collinear)")]
    DegenerateLookAt,
    #[error("invalid intrinsics: {0}")]
    BadIntrinsics(String),
}

impl Scene {
    pub fn new(tool: &TriMesh, world_from_tool: Isometry3<f64>, table_z: Option<f64>) -> Result<Self, CameraError> {
        let tool = to_parry(tool).ok_or(CameraError::BadMesh)?;
        Ok(Self { tool, world_from_tool, table_z })
    }

    /// Moves the tool to another pose (its mesh's search tree is kept).
    pub fn place(&mut self, world_from_tool: Isometry3<f64>) {
        self.world_from_tool = world_from_tool;
    }
}

/// Camera pose looking from `eye` at `target`, image "up" toward `up` (OpenCV frame).
pub fn look_at(eye: Point3<f64>, target: Point3<f64>, up: Vector3<f64>) -> Result<Isometry3<f64>, CameraError> {
    let z = (target - eye).try_normalize(1e-12).ok_or(CameraError::DegenerateLookAt)?;
    let x = z.cross(&-up).try_normalize(1e-9).ok_or(CameraError::DegenerateLookAt)?;
    let y = z.cross(&x);
    let rot = nalgebra::Rotation3::from_basis_unchecked(&[x, y, z]);
    Ok(Isometry3::from_parts(Translation3::from(eye.coords), UnitQuaternion::from_rotation_matrix(&rot)))
}

impl DepthCamera {
    /// Renders the segmented partial cloud of the scene's tool.
    pub fn capture(&self, scene: &Scene, seed: u64) -> Result<PartialView, CameraError> {
        let k = self.intrinsics;
        if k.width == 0 || k.height == 0 || !(k.fx > 0.0 && k.fy > 0.0) || k.width > 16384 || k.height > 16384 {
            return Err(CameraError::BadIntrinsics(format!("{k:?}")));
        }
        // Rays are cast in the tool frame (parry meshes are local).
        let tool_from_camera = scene.world_from_tool.inverse() * self.world_from_camera;
        let (u0, u1, v0, v1) = self.tool_pixel_bounds(scene);
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut view = PartialView::default();
        let origin_t = tool_from_camera.translation.vector;
        let to_f32 = |v: Vector3<f64>| parry3d::math::Vector::new(v.x as f32, v.y as f32, v.z as f32);
        let unit = rand_distr::StandardNormal;
        let ray_cam = |u: u32, v: u32| Vector3::new((u as f64 - k.cx) / k.fx, (v as f64 - k.cy) / k.fy, 1.0);
        // Depth along the camera's z at which the ray meets the table.
        let table_depth = |d_cam: &Vector3<f64>| {
            let tz = scene.table_z?;
            let d_world = self.world_from_camera.rotation * d_cam;
            let o_world = self.world_from_camera.translation.vector;
            let t = (tz - o_world.z) / d_world.z;
            (d_world.z.abs() > 1e-12 && t > 0.0).then_some(t)
        };
        let emit = |view: &mut PartialView, rng: &mut ChaCha8Rng, d_cam: Vector3<f64>, depth: f64, px: [u32; 2]| {
            let sigma = self.noise.sigma_m + self.noise.quadratic_per_m * depth * depth;
            let n: f64 = if sigma > 0.0 { unit.sample(rng) } else { 0.0 };
            let noisy = (depth + sigma * n).max(1e-6);
            let p_cam = Point3::from(d_cam * noisy);
            view.points_world.push(self.world_from_camera * p_cam);
            view.points_camera.push(p_cam);
            view.pixels.push(px);
        };
        for v in v0..v1 {
            for u in u0..u1 {
                // Direction with unit z in the camera frame, so the ray parameter is depth.
                let d_cam = ray_cam(u, v);
                let d_tool = tool_from_camera.rotation * d_cam;
                let ray = Ray::new(to_f32(origin_t), to_f32(d_tool));
                let Some(t_tool) = scene.tool.cast_local_ray(&ray, 100.0, true) else { continue };
                let depth = t_tool as f64;
                // The table hides what lies beneath it.
                if table_depth(&d_cam).is_some_and(|t| t < depth) {
                    continue;
                }
                if self.noise.dropout > 0.0 && rand::Rng::random::<f64>(&mut rng) < self.noise.dropout {
                    continue;
                }
                emit(&mut view, &mut rng, d_cam, depth, [u, v]);
            }
        }
        // The occluder's columns, from the tool's own pixels (before any leak).
        let occluded = self.occluder_columns(&view, seed);
        let leak = self.noise.mask_leak_px;
        if leak > 0 && scene.table_z.is_some() && !view.pixels.is_empty() {
            // The mask dilated by `leak` pixels (a square): the table's pixels in it.
            let (lu, lv) = (u0.saturating_sub(leak), v0.saturating_sub(leak));
            let (hu, hv) = ((u1 + leak).min(k.width), (v1 + leak).min(k.height));
            let w = (hu - lu) as usize;
            let mut tool = vec![false; w * (hv - lv) as usize];
            for [u, v] in &view.pixels {
                tool[(v - lv) as usize * w + (u - lu) as usize] = true;
            }
            let near = |u: u32, v: u32| {
                let (a, b) = (u.saturating_sub(leak).max(lu), v.saturating_sub(leak).max(lv));
                let (c, d) = ((u + leak).min(hu - 1), (v + leak).min(hv - 1));
                (b..=d).any(|y| (a..=c).any(|x| tool[(y - lv) as usize * w + (x - lu) as usize]))
            };
            for v in lv..hv {
                for u in lu..hu {
                    if tool[(v - lv) as usize * w + (u - lu) as usize] || !near(u, v) {
                        continue;
                    }
                    let d_cam = ray_cam(u, v);
                    let Some(depth) = table_depth(&d_cam) else { continue };
                    // Not where the tool stands in front of the table (a pixel dropped out).
                    let d_tool = tool_from_camera.rotation * d_cam;
                    let ray = Ray::new(to_f32(origin_t), to_f32(d_tool));
                    if scene.tool.cast_local_ray(&ray, depth as f32, true).is_some() {
                        continue;
                    }
                    emit(&mut view, &mut rng, d_cam, depth, [u, v]);
                }
            }
        }
        if let Some(cols) = occluded {
            view.hide_columns(cols);
        }
        Ok(view)
    }

    /// The image columns [first, end) the occluder hides (`DepthNoise::occluder_share`).
    fn occluder_columns(&self, view: &PartialView, seed: u64) -> Option<(u32, u32)> {
        let share = self.noise.occluder_share;
        if !(share > 0.0) || view.pixels.is_empty() {
            return None;
        }
        let (lo, hi) = view.pixels.iter().fold((u32::MAX, 0), |(lo, hi), [u, _]| (lo.min(*u), hi.max(*u + 1)));
        let width = ((share.min(1.0) * (hi - lo) as f64).round() as u32).max(1);
        // Its own stream: the depth noise of the pixels it leaves stays as without it.
        let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x6f63_636c_7564_6572);
        let first = lo + rand::Rng::random_range(&mut rng, 0..=(hi - lo).saturating_sub(width));
        Some((first, first + width))
    }

    /// Pixel rectangle covering the projected bounding box of the tool (rays
    /// outside it cannot hit the tool, so they are not cast).
    fn tool_pixel_bounds(&self, scene: &Scene) -> (u32, u32, u32, u32) {
        let k = self.intrinsics;
        let aabb = scene.tool.local_aabb();
        let (lo, hi) = (aabb.mins, aabb.maxs);
        let camera_from_tool = self.world_from_camera.inverse() * scene.world_from_tool;
        let (mut umin, mut umax, mut vmin, mut vmax) =
            (f64::INFINITY, f64::NEG_INFINITY, f64::INFINITY, f64::NEG_INFINITY);
        for i in 0..8 {
            let c = Point3::new(
                if i & 1 == 0 { lo.x } else { hi.x } as f64,
                if i & 2 == 0 { lo.y } else { hi.y } as f64,
                if i & 4 == 0 { lo.z } else { hi.z } as f64,
            );
            let p = camera_from_tool * c;
            if p.z <= 1e-6 {
                // A corner behind the camera: fall back to the full image.
                return (0, k.width, 0, k.height);
            }
            let (u, v) = (k.fx * p.x / p.z + k.cx, k.fy * p.y / p.z + k.cy);
            umin = umin.min(u);
            umax = umax.max(u);
            vmin = vmin.min(v);
            vmax = vmax.max(v);
        }
        let clamp = |x: f64, n: u32| x.clamp(0.0, n as f64) as u32;
        (
            clamp(umin.floor(), k.width),
            clamp(umax.ceil() + 1.0, k.width),
            clamp(vmin.floor(), k.height),
            clamp(vmax.ceil() + 1.0, k.height),
        )
    }
}

impl PartialView {
    /// Drops the points whose pixel lies in columns [first, end).
    fn hide_columns(&mut self, (first, end): (u32, u32)) {
        let all = std::mem::take(self);
        let points = all.points_world.into_iter().zip(all.points_camera).zip(all.pixels);
        for ((world, camera), px) in points.filter(|(_, [u, _])| !(first..end).contains(u)) {
            self.points_world.push(world);
            self.points_camera.push(camera);
            self.pixels.push(px);
        }
    }
}

/// The standard viewpoints around an object: `count` azimuths evenly spaced,
/// alternating elevations of 25° and 45°, at a distance where the object fills
/// about a third of the image. View `k` is fixed for a given object size.
pub fn standard_view(
    k: usize,
    count: usize,
    target: Point3<f64>,
    object_size: f64,
    intrinsics: Intrinsics,
) -> Result<Isometry3<f64>, CameraError> {
    let count = count.max(1);
    let azimuth = std::f64::consts::TAU * (k % count) as f64 / count as f64;
    let elevation = if k.is_multiple_of(2) { 25f64 } else { 45f64 }.to_radians();
    let fov_half = ((intrinsics.width as f64 / 2.0) / intrinsics.fx).atan();
    let distance = (object_size.max(1e-3) * 1.5 / fov_half.tan()).max(0.25);
    let dir = Vector3::new(azimuth.cos() * elevation.cos(), azimuth.sin() * elevation.cos(), elevation.sin());
    look_at(target + dir * distance, target, Vector3::z())
}

/// The standard view a quarter turn on round the object from view `k` of
/// `count`, as [`standard_view`]'s `(k, count)`: azimuth index 4k + count
/// of 4·count, at 25° up (a second camera's look at what view `k` shows
/// from the side).
pub fn quarter_turn_on(k: usize, count: usize) -> (usize, usize) {
    (4 * k + count, 4 * count)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn box_mesh(lo: Point3<f64>, hi: Point3<f64>) -> TriMesh {
        let v = |i: usize| {
            Point3::new(
                if i & 1 == 0 { lo.x } else { hi.x },
                if i & 2 == 0 { lo.y } else { hi.y },
                if i & 4 == 0 { lo.z } else { hi.z },
            )
        };
        let vertices = (0..8).map(v).collect();
        // Faces wound outward (vertex index bits: x=1, y=2, z=4).
        let triangles = vec![
            [0, 2, 3],
            [0, 3, 1],
            [4, 5, 7],
            [4, 7, 6],
            [0, 1, 5],
            [0, 5, 4],
            [2, 6, 7],
            [2, 7, 3],
            [0, 4, 6],
            [0, 6, 2],
            [1, 3, 7],
            [1, 7, 5],
        ];
        TriMesh::new(vertices, triangles)
    }

    #[test]
    fn box_mesh_is_outward() {
        let m = box_mesh(Point3::new(-0.05, -0.05, 0.0), Point3::new(0.05, 0.05, 0.1));
        assert!(m.is_watertight());
        assert!(m.signed_volume() > 0.0);
    }

    #[test]
    fn noiseless_view_sees_only_the_near_faces_at_the_right_depth() {
        let m = box_mesh(Point3::new(-0.05, -0.05, 0.0), Point3::new(0.05, 0.05, 0.1));
        let scene = Scene::new(&m, Isometry3::identity(), Some(0.0)).unwrap();
        let pose = look_at(Point3::new(0.5, 0.0, 0.05), Point3::new(0.0, 0.0, 0.05), Vector3::z()).unwrap();
        let cam = DepthCamera { intrinsics: Intrinsics::default(), world_from_camera: pose, noise: DepthNoise::NONE };
        let view = cam.capture(&scene, 0).unwrap();
        assert!(view.points_world.len() > 500, "{} points", view.points_world.len());
        for (pw, pc) in view.points_world.iter().zip(&view.points_camera) {
            assert!((pw.x - 0.05).abs() < 1e-5, "hit behind the front face: {pw}");
            assert!((pc.z - 0.45).abs() < 1e-5);
        }
    }

    #[test]
    fn depth_noise_has_the_requested_spread_and_is_seeded() {
        let m = box_mesh(Point3::new(-0.05, -0.05, 0.0), Point3::new(0.05, 0.05, 0.1));
        let scene = Scene::new(&m, Isometry3::identity(), None).unwrap();
        let pose = look_at(Point3::new(0.5, 0.0, 0.05), Point3::new(0.0, 0.0, 0.05), Vector3::z()).unwrap();
        let noise =
            DepthNoise { sigma_m: 0.002, quadratic_per_m: 0.0, dropout: 0.0, mask_leak_px: 0, occluder_share: 0.0 };
        let cam = DepthCamera { intrinsics: Intrinsics::default(), world_from_camera: pose, noise };
        let a = cam.capture(&scene, 3).unwrap();
        let b = cam.capture(&scene, 3).unwrap();
        assert_eq!(a.points_world, b.points_world);
        let n = a.points_camera.len() as f64;
        let var = a.points_camera.iter().map(|p| (p.z - 0.45).powi(2)).sum::<f64>() / n;
        assert!((var.sqrt() - 0.002).abs() < 0.0003, "std {}", var.sqrt());
    }

    /// A leaking mask adds table points in a band about the tool's
    /// silhouette, no wider than the dilation, and leaves the tool's own.
    #[test]
    fn a_leaking_mask_adds_the_tables_pixels_beside_the_tool() {
        let m = box_mesh(Point3::new(-0.05, -0.05, 0.0), Point3::new(0.05, 0.05, 0.1));
        let scene = Scene::new(&m, Isometry3::identity(), Some(0.0)).unwrap();
        let pose = look_at(Point3::new(0.4, 0.1, 0.35), Point3::new(0.0, 0.0, 0.05), Vector3::z()).unwrap();
        let cam = |leak| DepthCamera {
            intrinsics: Intrinsics::default(),
            world_from_camera: pose,
            noise: DepthNoise { mask_leak_px: leak, ..DepthNoise::NONE },
        };
        let exact = cam(0).capture(&scene, 0).unwrap();
        let leaky = cam(3).capture(&scene, 0).unwrap();
        assert_eq!(leaky.points_world[..exact.points_world.len()], exact.points_world[..]);
        let table = &leaky.points_world[exact.points_world.len()..];
        assert!(table.len() > 100 && table.len() < exact.points_world.len() / 2, "{} table points", table.len());
        assert!(table.iter().all(|p| p.z.abs() < 1e-9), "off the table");
        // None under the box's footprint; beside it, or behind it where the
        // pixels above its top edge see the table beyond.
        for p in table {
            let out = (p.x.abs() - 0.05).max(p.y.abs() - 0.05);
            assert!(out > -1e-9 && out < 0.25, "{p}");
        }
        // In front of the box (toward the camera, +x) the band is 3 pixels: a few millimetres.
        let front = table.iter().filter(|p| p.x > 0.05).map(|p| p.x - 0.05).fold(0.0, f64::max);
        assert!(front > 0.001 && front < 0.008, "front band {front}");
    }

    /// An occluder takes one band of columns, `occluder_share` of the
    /// tool's image width, out of the view; every other point is as
    /// without it, depth noise included.
    #[test]
    fn an_occluder_hides_a_band_of_the_tools_columns() {
        let m = box_mesh(Point3::new(-0.05, -0.05, 0.0), Point3::new(0.05, 0.05, 0.1));
        let scene = Scene::new(&m, Isometry3::identity(), Some(0.0)).unwrap();
        let pose = look_at(Point3::new(0.4, 0.1, 0.35), Point3::new(0.0, 0.0, 0.05), Vector3::z()).unwrap();
        let cam = |share| DepthCamera {
            intrinsics: Intrinsics::default(),
            world_from_camera: pose,
            noise: DepthNoise { occluder_share: share, ..DepthNoise::default() },
        };
        let clean = cam(0.0).capture(&scene, 5).unwrap();
        let (lo, hi) = clean.pixels.iter().fold((u32::MAX, 0), |(lo, hi), [u, _]| (lo.min(*u), hi.max(*u + 1)));
        let mut bands = Vec::new();
        for seed in [5, 6, 7] {
            let clean = cam(0.0).capture(&scene, seed).unwrap();
            let hidden = cam(0.3).capture(&scene, seed).unwrap();
            let kept: Vec<_> = clean
                .pixels
                .iter()
                .zip(&clean.points_world)
                .filter(|(px, _)| hidden.pixels.contains(px))
                .map(|(_, p)| *p)
                .collect();
            assert_eq!(kept, hidden.points_world, "seed {seed}: the kept points changed");
            let gone: Vec<u32> =
                clean.pixels.iter().filter(|px| !hidden.pixels.contains(px)).map(|[u, _]| *u).collect();
            let (a, b) = (*gone.iter().min().unwrap(), *gone.iter().max().unwrap() + 1);
            // Every pixel of the band's columns is gone, and none outside it.
            assert_eq!(gone.len(), clean.pixels.iter().filter(|[u, _]| (a..b).contains(u)).count());
            let width = (b - a) as f64 / (hi - lo) as f64;
            assert!((width - 0.3).abs() < 0.02, "seed {seed}: band {a}..{b} of {lo}..{hi}");
            bands.push(a);
        }
        bands.dedup();
        assert!(bands.len() > 1, "the seed does not place the band: {bands:?}");
    }

    #[test]
    fn table_hides_what_is_below_it() {
        // A box half sunk into the table, seen from above at an angle.
        let m = box_mesh(Point3::new(-0.05, -0.05, -0.05), Point3::new(0.05, 0.05, 0.05));
        let scene = Scene::new(&m, Isometry3::identity(), Some(0.0)).unwrap();
        let pose = look_at(Point3::new(0.4, 0.0, 0.3), Point3::origin(), Vector3::z()).unwrap();
        let cam = DepthCamera { intrinsics: Intrinsics::default(), world_from_camera: pose, noise: DepthNoise::NONE };
        let view = cam.capture(&scene, 0).unwrap();
        assert!(!view.points_world.is_empty());
        assert!(view.points_world.iter().all(|p| p.z >= -1e-6));
    }
}
