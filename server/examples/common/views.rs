//! The test views the benchmarks share: each test instance of a category
//! turned to 8 yaws on a table, seen by the standard camera ring with depth
//! noise, subsampled to about 2,000 points (the shape-engine issue's size),
//! or whole (3,500-16,000 points, what a client sends) with `FULL_VIEWS=1`,
//! or each point taken K times with 0.5 mm of seeded jitter with
//! `DENSE_VIEWS=K` (a denser sensor's view: K = 13 gives about 200,000).
use graspd::geometry::camera::{standard_view, DepthCamera, DepthNoise, Intrinsics, Scene};
use graspd::tools::{self, Category, Split};
use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};

/// One view: the cloud (world frame, z up, table at z = 0) and the camera
/// position it was seen from.
pub struct View {
    pub cloud: Vec<Point3<f64>>,
    #[allow(dead_code)]
    pub viewpoint: [f64; 3],
    /// The instance's ground-truth keypoints in the world frame.
    #[allow(dead_code)]
    pub keypoints_world: Vec<[f64; 3]>,
}

pub fn test_views(category: Category) -> Result<Vec<View>, Box<dyn std::error::Error>> {
    let family = tools::family(category)?;
    let mut views = Vec::new();
    for inst in family.iter().filter(|i| i.split == Split::Test) {
        for view in 0..8 {
            let rot = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 0.7 * view as f64);
            let zmin = inst.mesh.vertices.iter().map(|p| (rot * p).z).fold(f64::INFINITY, f64::min);
            let pose = Isometry3::from_parts(Translation3::new(0.0, 0.0, -zmin), rot);
            let scene = Scene::new(&inst.mesh, pose, Some(0.0))?;
            let (lo, hi) = inst.mesh.aabb().ok_or("empty mesh")?;
            let centre = pose * Point3::from((lo.coords + hi.coords) / 2.0);
            let intrinsics = Intrinsics::default();
            let cam_pose = standard_view(view, 8, centre, inst.mesh.diagonal(), intrinsics)?;
            let cam = DepthCamera { intrinsics, world_from_camera: cam_pose, noise: DepthNoise::default() };
            let cloud = cam.capture(&scene, view as u64)?.points_world;
            let step = if full_views() || dense_views() > 1 { 1 } else { (cloud.len() / 2000).max(1) };
            let cloud: Vec<_> = cloud.iter().step_by(step).copied().collect();
            let cloud = densified(cloud, dense_views(), view as u64);
            let t = cam_pose.translation.vector;
            let keypoints_world =
                inst.keypoints.iter().map(|k| (pose * Point3::from(k.position)).coords.into()).collect();
            views.push(View { cloud, viewpoint: [t.x, t.y, t.z], keypoints_world });
        }
    }
    Ok(views)
}

/// Whether the benchmarks take the whole views (`FULL_VIEWS=1`).
pub fn full_views() -> bool {
    std::env::var("FULL_VIEWS").is_ok_and(|v| v == "1")
}

/// How many times `DENSE_VIEWS` takes each point (1: once).
pub fn dense_views() -> usize {
    std::env::var("DENSE_VIEWS").ok().and_then(|v| v.parse().ok()).unwrap_or(1).max(1)
}

/// Each point `k` times, jittered by 0.5 mm (Gaussian, seeded).
fn densified(cloud: Vec<Point3<f64>>, k: usize, seed: u64) -> Vec<Point3<f64>> {
    use rand::SeedableRng;
    use rand_distr::{Distribution, Normal};
    if k <= 1 {
        return cloud;
    }
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let jitter = Normal::new(0.0, 0.0005).expect("a valid normal");
    let mut out = Vec::with_capacity(cloud.len() * k);
    for p in &cloud {
        for _ in 0..k {
            out.push(p + Vector3::from_fn(|_, _| jitter.sample(&mut rng)));
        }
    }
    out
}
