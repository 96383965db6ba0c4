//! Calibration of the fit-quality rule: the inlier fraction, at several
//! radii, of real YCB scans registered to their own category and to the
//! other two. `cargo run --release --example confidence_scan [VIEWS]`.
use graspd::eval::ycb::ycb_mesh_path;
use graspd::geometry::camera::{standard_view, DepthCamera, DepthNoise, Intrinsics, Scene};
use graspd::shape::cpd::to_p3;
use graspd::shape::{builtin, RegisterOptions, Registrar};
use graspd::tools::Category;
use kiddo::immutable::float::kdtree::ImmutableKdTree;
use kiddo::SquaredEuclidean;
use nalgebra::{Isometry3, Point3};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let views: usize = std::env::args().nth(1).map_or(Ok(8), |s| s.parse())?;
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../assets/spaces");
    let data = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data");
    let cats = [Category::Mug, Category::Drill, Category::Hammer];
    let registrars: Vec<Registrar> = cats
        .iter()
        .map(|&c| builtin::load_or_build(c, &root, |_, _| {}).map(Registrar::new))
        .collect::<Result<_, _>>()?;
    let radii = [0.004, 0.006, 0.008, 0.010];
    for &object in &cats {
        let mesh = graspd::io::read_mesh(ycb_mesh_path(&data, object))?.mesh;
        let (lo, hi) = mesh.aabb().ok_or("empty mesh")?;
        let centre = Point3::from((lo.coords + hi.coords) / 2.0);
        let scene = Scene::new(&mesh, Isometry3::identity(), Some(lo.z))?;
        for (ci, &category) in cats.iter().enumerate() {
            let mut rows: Vec<Vec<f64>> = Vec::new();
            let mut base = Vec::new();
            for view in 0..views {
                let pose = standard_view(view, views, centre, mesh.diagonal(), Intrinsics::default())?;
                let cam = DepthCamera {
                    intrinsics: Intrinsics::default(),
                    world_from_camera: pose,
                    noise: DepthNoise::default(),
                };
                let cloud = cam.capture(&scene, view as u64)?.points_world;
                let reg =
                    registrars[ci].register(&cloud, &RegisterOptions { seed: view as u64, ..Default::default() })?;
                base.push(reg.fit.inlier_fraction);
                let shape = to_p3(&registrars[ci].completed_shape(&reg));
                let tree: ImmutableKdTree<f64, u32, 3, 32> = ImmutableKdTree::new_from_slice(&shape);
                let d: Vec<f64> = cloud
                    .iter()
                    .map(|p| tree.nearest_one::<SquaredEuclidean>(&[p.x, p.y, p.z]).distance.sqrt())
                    .collect();
                rows.push(
                    radii.iter().map(|r| d.iter().filter(|&&x| x <= *r).count() as f64 / d.len() as f64).collect(),
                );
            }
            let mean = |i: usize| rows.iter().map(|r| r[i]).sum::<f64>() / rows.len() as f64;
            let min = |i: usize| rows.iter().map(|r| r[i]).fold(1.0, f64::min);
            let max = |i: usize| rows.iter().map(|r| r[i]).fold(0.0, f64::max);
            print!(
                "{:>6} scan as {:>6}: reported {:.2}",
                object.name(),
                category.name(),
                base.iter().sum::<f64>() / base.len() as f64
            );
            for (i, r) in radii.iter().enumerate() {
                print!(" | {:.0} mm {:.2} [{:.2}, {:.2}]", r * 1e3, mean(i), min(i), max(i));
            }
            println!();
        }
    }
    Ok(())
}
