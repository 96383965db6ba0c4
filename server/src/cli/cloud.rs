use super::{print_json, CliResult};
use clap::Args;
use graspd::geometry::camera::{standard_view, DepthCamera, DepthNoise, Intrinsics, Scene};
use nalgebra::{Isometry3, Point3};
use std::path::PathBuf;

#[derive(Args)]
pub struct CloudArgs {
    /// Mesh file (OBJ or STL), metres.
    #[arg(long)]
    mesh: PathBuf,
    /// Which of the standard viewpoints (0-based).
    #[arg(long, default_value_t = 0)]
    view: usize,
    /// Number of standard viewpoints around the object.
    #[arg(long, default_value_t = 8)]
    views: usize,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Constant axial depth noise σ, millimetres.
    #[arg(long, default_value_t = 1.0)]
    noise_mm: f64,
    /// The segmentation leaks onto the table: the tool's mask dilated by
    /// this many pixels.
    #[arg(long, default_value_t = 0)]
    mask_leak_px: u32,
    /// Something in front of the tool hides this share of its image width.
    #[arg(long, default_value_t = 0.0)]
    occluder_share: f64,
    /// Output cloud (.ply, .pcd, .xyz, .npy), world frame.
    #[arg(long)]
    out: PathBuf,
    /// Also write the cloud in the camera frame here.
    #[arg(long)]
    out_camera: Option<PathBuf>,
    #[arg(long)]
    json: bool,
}

pub fn run(a: CloudArgs) -> CliResult {
    let loaded = graspd::io::read_mesh(&a.mesh)?;
    for w in &loaded.warnings {
        tracing::warn!("{}: {w}", a.mesh.display());
    }
    let mesh = loaded.mesh;
    let (lo, hi) = mesh.aabb().ok_or("mesh has no vertices")?;
    let centre = Point3::from((lo.coords + hi.coords) / 2.0);
    let table_z = Some(lo.z);
    let scene = Scene::new(&mesh, Isometry3::identity(), table_z)?;
    let intrinsics = Intrinsics::default();
    let pose = standard_view(a.view, a.views, centre, mesh.diagonal(), intrinsics)?;
    if !(0.0..1.0).contains(&a.occluder_share) {
        return Err(format!("--occluder-share {}: from 0 up to 1", a.occluder_share).into());
    }
    let noise = DepthNoise {
        sigma_m: a.noise_mm.max(0.0) * 1e-3,
        mask_leak_px: a.mask_leak_px,
        occluder_share: a.occluder_share,
        ..DepthNoise::default()
    };
    let cam = DepthCamera { intrinsics, world_from_camera: pose, noise };
    let view = cam.capture(&scene, a.seed)?;
    graspd::io::write_cloud(&a.out, &view.points_world)?;
    if let Some(p) = &a.out_camera {
        graspd::io::write_cloud(p, &view.points_camera)?;
    }
    let q = pose.rotation.coords;
    let summary = serde_json::json!({
        "points": view.points_world.len(),
        "out": a.out,
        "frame": "world (mesh frame, z up, table at the mesh's lowest z)",
        "camera_pose_world": {"translation": pose.translation.vector.as_slice(), "rotation_xyzw": [q.x, q.y, q.z, q.w]},
        "intrinsics": intrinsics,
    });
    if a.json {
        print_json(&summary)?;
    } else {
        println!("{} points -> {}", view.points_world.len(), a.out.display());
    }
    Ok(())
}
