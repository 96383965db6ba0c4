//! Real scanned tools (YCB mug, drill, hammer from ../shared/data/ycb):
//! each must register to its category from single partial views. There is
//! no ground-truth keypoint on a scan, so the figures are the Chamfer error
//! of the completed shape to the scan's full surface and the fit quality.

use super::transfer::{chamfer_mm, percentiles, Percentiles};
use crate::geometry::camera::{quarter_turn_on, standard_view, DepthCamera, DepthNoise, Intrinsics, Scene};
use crate::geometry::sample_points;
use crate::shape::cpd::to_p3;
use crate::shape::{RegisterOptions, Registrar};
use crate::tools::Category;
use nalgebra::{Isometry3, Point3};
use serde::Serialize;
use std::path::{Path, PathBuf};

/// The YCB object standing for each category.
pub fn ycb_mesh_path(shared_data: &Path, category: Category) -> PathBuf {
    let dir = match category {
        Category::Mug => "025_mug",
        Category::Drill => "035_power_drill",
        Category::Hammer => "048_hammer",
    };
    shared_data.join("ycb").join(dir).join("mesh.obj")
}

#[derive(Clone, Debug, Serialize)]
pub struct YcbReport {
    pub category: String,
    pub mesh: String,
    pub views: usize,
    /// The registration was told the camera position (else it estimated it).
    pub known_viewpoint: bool,
    /// The registration was told the table's height (the scan resting on it).
    pub known_table: bool,
    /// Each view merged with a second camera's, a quarter turn round the scan.
    pub second_view: bool,
    pub chamfer_mm: Percentiles,
    pub inlier_fraction: Percentiles,
    pub confident_fraction: f64,
    pub scale: Percentiles,
    pub fit_ms: Percentiles,
}

/// How the scans are seen and what the registration is told.
#[derive(Clone, Copy, Debug)]
pub struct YcbProtocol {
    /// Camera views around the scan, and the seed of their depth noise.
    pub views: usize,
    pub seed: u64,
    /// Tell the registration the camera position (else it estimates it).
    pub known_viewpoint: bool,
    /// Tell it the table's height (the scan resting on it).
    pub known_table: bool,
    /// Merge each view with a second camera's, a quarter turn round the
    /// scan and 25° up (as `eval transfer --second-view`); with
    /// `known_viewpoint` the registration is told both cameras.
    pub second_view: bool,
}

pub fn evaluate(
    registrar: &Registrar,
    category: Category,
    mesh_path: &Path,
    protocol: YcbProtocol,
    base: &RegisterOptions,
) -> Result<YcbReport, Box<dyn std::error::Error>> {
    let YcbProtocol { views, seed, known_viewpoint, known_table, second_view } = protocol;
    let mesh = crate::io::read_mesh(mesh_path)?.mesh;
    let truth = to_p3(&sample_points(&mesh, 4000, 99)?);
    let (lo, _) = mesh.aabb().ok_or("empty mesh")?;
    let centre = mesh.aabb().map(|(lo, hi)| Point3::from((lo.coords + hi.coords) / 2.0)).ok_or("empty mesh")?;
    let scene = Scene::new(&mesh, Isometry3::identity(), Some(lo.z))?;
    let (mut chamfer, mut inliers, mut scale, mut ms, mut confident) =
        (Vec::new(), Vec::new(), Vec::new(), Vec::new(), 0);
    for view in 0..views {
        let pose = standard_view(view, views, centre, mesh.diagonal(), Intrinsics::default())?;
        let cam =
            DepthCamera { intrinsics: Intrinsics::default(), world_from_camera: pose, noise: DepthNoise::default() };
        let mut cloud = cam.capture(&scene, seed + view as u64)?.points_world;
        let viewpoint = known_viewpoint.then(|| pose.translation.vector.into());
        let mut second_viewpoint = None;
        if second_view {
            let (k, count) = quarter_turn_on(view, views);
            let pose = standard_view(k, count, centre, mesh.diagonal(), Intrinsics::default())?;
            let cam = DepthCamera { world_from_camera: pose, ..cam };
            cloud.extend(cam.capture(&scene, (seed + view as u64) ^ 1)?.points_world);
            second_viewpoint = known_viewpoint.then(|| pose.translation.vector.into());
        }
        let support_height = known_table.then_some(lo.z).or(base.support_height);
        let opts = RegisterOptions { seed: seed + view as u64, viewpoint, second_viewpoint, support_height, ..*base };
        let reg = registrar.register(&cloud, &opts)?;
        chamfer.push(chamfer_mm(&to_p3(&registrar.completed_shape(&reg)), &truth));
        inliers.push(reg.fit.inlier_fraction);
        scale.push(reg.scale);
        ms.push(reg.elapsed_ms);
        confident += reg.fit.confident as usize;
    }
    Ok(YcbReport {
        category: category.name().into(),
        mesh: mesh_path.display().to_string(),
        views,
        known_viewpoint,
        known_table,
        second_view,
        chamfer_mm: percentiles(chamfer),
        inlier_fraction: percentiles(inliers),
        confident_fraction: confident as f64 / views.max(1) as f64,
        scale: percentiles(scale),
        fit_ms: percentiles(ms),
    })
}
